"""The remedy agent: its case base (retrieve, adapt, retain, files), the agent through
its ports against a recording runtime, and the robot driver's ``enabled`` flag."""

from __future__ import annotations

import math
import pickle
import re
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any, ClassVar

import numpy as np
import pytest

import agents.remedy as remedy_module
from agents.case_base import AdaptationError, Case, CaseBase, CaseFileError, Match, adapt
from agents.remedy import (
    SHIPPED_CASES,
    RemedyAgent,
    SystemView,
    check_remedy,
    plan,
    situation_of,
)
from pb3a import MigrationReport, Module, ModuleNotFound, RuntimeFailure
from pb3a.launch.migration import MigrationPhases
from pb3a.model.module import restore_state
from pb3a.testing import ModuleHarness

SONAR_FREE = "agents.explorer:SonarFreeExplorer"


def write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def situation(fault: str, *, standby: bool = False, failed: int = 0,
              probability: float = 0.9) -> dict[str, Any]:
    return {"fault": fault, "probability": probability, "failed_sensors": failed,
            "standby": standby}


# -- the case base -------------------------------------------------------------------

@pytest.mark.parametrize(("symptoms", "expected"), [
    (situation("motors", standby=True), "motors-standby"),
    (situation("motors", standby=False), "motors-alone"),
    (situation("sonar", failed=2, standby=True), "sonar-few"),
    (situation("sonar", failed=9, standby=True), "sonar-many-standby"),
    (situation("sonar", failed=9, standby=False), "sonar-many-alone"),
    (situation("odometry"), "odometry-drift"),
    (situation("robot_link", standby=True, probability=1.0), "robot-link-standby"),
    (situation("robot_link", standby=False, probability=1.0), "robot-link-alone"),
])
def test_the_shipped_base_retrieves_the_case_made_for_each_failure(symptoms, expected) -> None:
    matches = CaseBase.load([SHIPPED_CASES]).retrieve(symptoms)
    assert matches[0].case.id == expected
    assert matches[0].similarity == 1.0


def test_a_fault_no_case_knows_retrieves_nothing() -> None:
    base = CaseBase.load([SHIPPED_CASES])
    assert base.retrieve(situation("battery", standby=True)) == []


def test_numbers_match_by_distance_over_their_scale(tmp_path) -> None:
    base = CaseBase.load([write(tmp_path / "cases.toml", """
        [scales]
        dead = 4
        [[case]]
        id = "range"
        symptoms = { dead = [2, 4] }
        remedy = { action = "stop" }
        [[case]]
        id = "flag"
        symptoms = { standby = true }
        remedy = { action = "stop" }
    """)])
    ranged, flag = base.cases
    assert base.similarity(ranged, {"dead": 3}) == 1.0
    assert base.similarity(ranged, {"dead": 5}) == 0.75
    assert base.similarity(ranged, {"dead": 9}) == 0.0
    assert base.similarity(ranged, {}) == 0.0
    assert base.similarity(flag, {"standby": True}) == 1.0
    assert base.similarity(flag, {"standby": 1}) == 0.0        # a count is not a flag


def test_adaptation_fills_placeholders_and_names_the_missing_ones() -> None:
    template = {"action": "move_macro", "to": "{standby_node}", "sensors": "{dead}",
                "note": "from {macro} to {standby_node}", "nested": {"x": ["{macro}"]}}
    values = {"standby_node": "r2-node", "dead": [3, 4], "macro": "control"}
    assert adapt(template, values) == {
        "action": "move_macro", "to": "r2-node", "sensors": [3, 4],
        "note": "from control to r2-node", "nested": {"x": ["control"]}}
    with pytest.raises(AdaptationError, match=r"no value for \{standby_node\}"):
        adapt(template, {**values, "standby_node": ""})


def _view(driver_node: str = "r1", explorer: str = "agents.explorer:Explorer") -> SystemView:
    return SystemView({"control/driver": "agents.robot_driver:RobotDriver",
                       "control/explorer": explorer},
                      {"control/driver": driver_node, "control/explorer": driver_node},
                      frozenset({"r1", "r2"}))


@pytest.mark.parametrize(("remedy", "view", "refusal"), [
    ({"action": "move_macro", "macro": "control", "to": "r1", "driver": "control/driver",
      "resource": "tcp://r2:7400"}, _view(), "'control' already runs on 'r1'"),
    ({"action": "move_macro", "macro": "control", "to": "r3", "driver": "control/driver",
      "resource": "tcp://r3:7400"}, _view(), "node 'r3' is not up"),
    ({"action": "move_macro", "macro": "ctrl", "to": "r2", "driver": "control/driver",
      "resource": "tcp://r2:7400"}, _view(), "no macro 'ctrl' runs"),
    ({"action": "swap", "module": "control/explorer", "cls": SONAR_FREE},
     _view(explorer=SONAR_FREE), "already is a"),
    ({"action": "swap", "module": "control/explorer", "cls": "SonarFree"}, _view(),
     "not a class reference"),
    ({"action": "swap", "module": "control/mapper", "cls": SONAR_FREE}, _view(),
     "no module 'control/mapper' runs"),
    ({"action": "dance"}, _view(), "unknown action 'dance'"),
])
def test_an_adapted_remedy_that_makes_no_sense_is_refused(remedy, view, refusal) -> None:
    with pytest.raises(AdaptationError, match=refusal):
        check_remedy(remedy, view)


def test_a_plan_passes_over_cases_that_do_not_adapt_and_ends_in_a_stop() -> None:
    base = CaseBase.load([SHIPPED_CASES])
    values = {"macro": "control", "driver": "control/driver", "fault": "sonar",
              "standby_node": "r2", "standby_resource": "tcp://r2:7400",
              "consumer": "control/explorer", "fallback": ""}
    # no class does without the sonar: the next case, moving to the standby, is taken
    moved = plan(base, situation("sonar", failed=2, standby=True), values, _view())
    assert (moved.case, moved.remedy["action"], moved.remedy["to"]) == (
        "sonar-many-standby", "move_macro", "r2")
    assert "case 'sonar-few': no value for {fallback}" in moved.reason
    stopped = plan(base, situation("battery"), values, _view())
    assert stopped.remedy == {"action": "stop", "driver": "control/driver"}
    assert stopped.case == "" and "no case is 75% similar" in stopped.reason


def test_retention_counts_attempts_learns_new_cases_and_reloads(tmp_path) -> None:
    user = tmp_path / "mine" / "cases.toml"
    base = CaseBase.load([SHIPPED_CASES])
    close = base.retrieve(situation("motors", standby=True))[0]
    base.retain(close, situation("motors", standby=True), True, user)
    base.retain(close, situation("motors", standby=True), False, user)
    # far below the case's probability range (similarity 0.94): a success there is new
    far = situation("motors", standby=True, probability=0.1)
    learned = base.retain(base.retrieve(far)[0], far, True, user)
    assert learned.id == "motors-standby/learned-1"
    assert learned.remedy == close.case.remedy and learned.symptoms == far
    base.save(user)

    shipped_text = SHIPPED_CASES.read_text()
    again = CaseBase.load([SHIPPED_CASES, user])
    counted = again.case("motors-standby")
    assert (counted.tried, counted.worked) == (2, 1)
    assert again.case("motors-standby/learned-1").worked == 1
    assert again.retrieve(far)[0].case.id == "motors-standby/learned-1"
    assert [p.name for p in user.parent.iterdir()] == ["cases.toml"]     # no temp file left
    assert SHIPPED_CASES.read_text() == shipped_text
    assert [case.id for case in CaseBase.load([user]).cases] == [
        "motors-standby", "motors-standby/learned-1"]


def test_a_base_carried_elsewhere_saves_to_the_users_file_there(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("HOME", str(tmp_path / "alice"))
    base = CaseBase.load([SHIPPED_CASES])
    motors = situation("motors", standby=True)
    base.retain(base.retrieve(motors)[0], motors, True, "~/.pb3a/cases.toml")
    carried = CaseBase.from_dict(pickle.loads(pickle.dumps(base.to_dict())))
    monkeypatch.setenv("HOME", str(tmp_path / "bob"))       # another node, another home
    carried.save("~/.pb3a/cases.toml")
    saved = CaseBase.load([tmp_path / "bob" / ".pb3a" / "cases.toml"])
    assert [(case.id, case.worked) for case in saved.cases] == [("motors-standby", 1)]


def test_any_case_survives_being_written_and_read_back(tmp_path) -> None:
    odd = Case("odd \"one\"", {"fault": "sonar", "odd key": [1e-07, 0.5], "n": 3},
               {"action": "swap", "set": {"gains": [1, 2.5], "on": True, "x.y": "\x7f"}},
               'a "quoted"\nnote \\ é\t', 2, 1, str(tmp_path / "odd.toml"))
    CaseBase([odd]).save(tmp_path / "odd.toml")
    (back,) = CaseBase.load([tmp_path / "odd.toml"]).cases
    assert back == odd


def test_saving_a_user_file_keeps_its_settings(tmp_path) -> None:
    user = write(tmp_path / "cases.toml", 'min_similarity = 0.5\n[weights]\n"odd key" = 2\n')
    base = CaseBase.load([SHIPPED_CASES, user])
    base.retain(base.retrieve(situation("odometry"))[0], situation("odometry"), True, user)
    base.save(user)
    reloaded = CaseBase.load([SHIPPED_CASES, user])
    assert reloaded.setting("min_similarity") == 0.5
    assert reloaded.settings[str(user)] == {"min_similarity": 0.5,
                                            "weights": {"odd key": 2}}
    assert reloaded.case("odometry-drift").tried == 1


def test_a_users_case_wins_when_it_matches_better_or_as_well(tmp_path) -> None:
    shipped = write(tmp_path / "shipped.toml", """
        [[case]]
        id = "generic"
        symptoms = { fault = "sonar", failed_sensors = 4 }
        remedy = { action = "stop" }
    """)
    user = write(tmp_path / "user.toml", """
        [scales]
        failed_sensors = 8
        [[case]]
        id = "two-dead"
        symptoms = { fault = "sonar", failed_sensors = 2 }
        remedy = { action = "swap", module = "{consumer}", cls = "my.explorers:Cautious" }
    """)
    base = CaseBase.load([shipped, user])
    assert base.retrieve(situation("sonar", failed=2))[0].case.id == "two-dead"
    assert base.retrieve(situation("sonar", failed=4))[0].case.id == "generic"
    tie = CaseBase.load([shipped, write(tmp_path / "tie.toml", """
        [[case]]
        id = "mine"
        symptoms = { fault = "sonar", failed_sensors = 4 }
        remedy = { action = "swap", module = "x", cls = "a.b:C" }
    """)])
    assert tie.retrieve(situation("sonar", failed=4))[0].case.id == "mine"
    replaced = CaseBase.load([SHIPPED_CASES, write(tmp_path / "same-id.toml", """
        [[case]]
        id = "motors-alone"
        symptoms = { fault = "motors" }
        remedy = { action = "stop", driver = "{driver}" }
    """)])
    assert [case.id for case in replaced.cases].count("motors-alone") == 1
    assert replaced.case("motors-alone").symptoms == {"fault": "motors"}


@pytest.mark.parametrize(("case", "problem"), [
    ('id = "broken"\nremedy = { action = "stop" }', "case 'broken': no symptoms"),
    ('id = "broken"\nsymptoms = { fault = "motors" }', "case 'broken': no remedy action"),
    ('id = "broken"\nsymptoms = { probability = [0.9, 0.1] }\nremedy = { action = "stop" }',
     r"case 'broken': symptom probability = \[0.9, 0.1\] is not"),
    ('id = "broken"\nsymptom = { fault = "motors" }\nremedy = { action = "stop" }',
     "case 'broken': unknown keys 'symptom'"),
    ('id = "broken"\ntried = 1\nworked = 2\nsymptoms = { fault = "x" }\n'
     'remedy = { action = "stop" }', "case 'broken': tried = 1 and worked = 2"),
    ('symptoms = { fault = "x" }\nremedy = { action = "stop" }', "case number 1 has no id"),
])
def test_a_malformed_case_names_its_file_and_case(tmp_path, case, problem) -> None:
    path = write(tmp_path / "bad.toml", f"[[case]]\n{case}\n")
    with pytest.raises(CaseFileError, match=f"{re.escape(str(path))}: {problem}"):
        CaseBase.load([SHIPPED_CASES, path])


def test_a_file_that_is_not_toml_or_not_there_is_named(tmp_path) -> None:
    path = write(tmp_path / "bad.toml", "[[case]\nid = 1\n")
    with pytest.raises(CaseFileError, match=f"{re.escape(str(path))}: not valid TOML"):
        CaseBase.load([path])
    with pytest.raises(CaseFileError, match=r"missing\.toml: cannot read the case file"):
        CaseBase.load([tmp_path / "missing.toml"])


def test_an_agent_refuses_a_case_whose_action_it_cannot_carry_out(tmp_path) -> None:
    path = write(tmp_path / "user.toml", '[[case]]\nid = "odd"\nsymptoms = { fault = "x" }\n'
                                         'remedy = { action = "reboot" }\n')
    problem = f"{re.escape(str(path))}: case 'odd': unknown action 'reboot'"
    with pytest.raises(CaseFileError, match=problem):
        ModuleHarness(RemedyAgent, state={"cases_path": str(path)}, runtime=FakeRuntime())


@pytest.mark.parametrize("wrong", [{"verify_s": float("nan")}, {"settle_s": -1.0},
                                   {"move_timeout_s": 0.0}, {"verify_s": "6"}])
def test_an_agent_refuses_timings_it_could_never_judge_a_remedy_by(wrong) -> None:
    """A NaN verify_s was taken: the remedy stayed 'verifying' for good, and every later
    failure of another kind waited behind it."""
    (key, _), = wrong.items()
    with pytest.raises(ValueError, match=f"{key} must be a finite number of seconds"):
        ModuleHarness(RemedyAgent, state=wrong, runtime=FakeRuntime())


@pytest.mark.parametrize(("wrong", "problem"), [
    ({"consumers": ["control/explorer"]}, "consumers must map each sensor"),
    ({"consumers": {"sonar": 3}}, "consumers must map each sensor"),
    ({"fallbacks": {"sonar": "SonarFree"}}, "fallbacks['sonar'] = 'SonarFree' is not "
                                             "'package.module:Class'"),
    ({"standby_node": 2}, "standby_node must be text, got 2"),
])
def test_an_agent_refuses_settings_of_a_kind_it_cannot_read(wrong, problem) -> None:
    """A list of consumers was taken: the first failure raised inside the agent, and the
    robot was neither remedied nor stopped."""
    with pytest.raises(ValueError, match=re.escape(problem)):
        ModuleHarness(RemedyAgent, state=wrong, runtime=FakeRuntime())
    harness = ModuleHarness(RemedyAgent, runtime=FakeRuntime())
    with pytest.raises(ValueError, match=re.escape(problem)):
        harness.module.set_state(wrong)
    assert harness.state["consumers"] == {} and harness.state["fallbacks"] == {}


class CountedRemedyAgent(RemedyAgent):
    """A remedy agent that counts the times its class is asked what it refuses."""

    asked: list[dict[str, Any]] = []

    @classmethod
    def state_problems(cls, state: dict[str, Any]) -> list[str]:
        CountedRemedyAgent.asked.append(state)
        return super().state_problems(state)


def test_an_edit_is_judged_once_and_not_refused_what_the_agent_s_state_broke_before(
        tmp_path) -> None:
    """Its own set_state judged an edit against the whole state, then Module's judged it
    again: an agent whose state already broke a rule (as its own steps may take a field)
    had every edit of another field refused naming that field, and could not be given
    its own state back (a move, a restart); each edit asked the hook twice."""
    harness = ModuleHarness(CountedRemedyAgent, runtime=FakeRuntime(), state={
        "cases_path": str(tmp_path / "learned.toml")})
    CountedRemedyAgent.asked.clear()
    harness.module.set_state({"settle_s": 1.0})
    assert len(CountedRemedyAgent.asked) == 1 and harness.state["settle_s"] == 1.0
    harness.module.verify_s = -1.0                  # (set as its own steps might)
    harness.module.set_state({"stopped": True})
    assert harness.state["stopped"] is True and harness.state["verify_s"] == -1.0
    with pytest.raises(ValueError, match=re.escape("settle_s must be a finite number")):
        harness.module.set_state({"settle_s": -2.0, "stopped": False})
    assert harness.state["settle_s"] == 1.0 and harness.state["stopped"] is True
    fresh = ModuleHarness(CountedRemedyAgent, runtime=FakeRuntime(), state={
        "cases_path": str(tmp_path / "learned.toml")})
    restore_state(fresh.module, harness.state)      # its own state back: no edit
    assert fresh.state["verify_s"] == -1.0 and fresh.state["stopped"] is True


class Audited(Module):
    """A user's cooperative mixin, after the agent's class: it sees each state set, then
    hands it on."""

    def set_state(self, state: dict[str, Any]) -> None:
        AuditedRemedyAgent.seen.append(sorted(state))
        super().set_state(state)


class AuditedRemedyAgent(CountedRemedyAgent, Audited):
    seen: ClassVar[list[list[str]]] = []


def test_a_mixin_s_set_state_still_sees_what_the_agent_is_given(tmp_path) -> None:
    """Judged once, the edit was set by the agent's own set_state rather than handed on to
    the base's: a user's mixin between them (auditing every change) saw nothing, of an
    edit or of the agent's own state given back."""
    harness = ModuleHarness(AuditedRemedyAgent, runtime=FakeRuntime(), state={
        "cases_path": str(tmp_path / "learned.toml")})
    AuditedRemedyAgent.seen.clear()
    CountedRemedyAgent.asked.clear()
    harness.module.set_state({"settle_s": 1.0})
    assert AuditedRemedyAgent.seen == [["settle_s"]] and len(CountedRemedyAgent.asked) == 1
    fresh = ModuleHarness(AuditedRemedyAgent, runtime=FakeRuntime(), state={
        "cases_path": str(tmp_path / "learned.toml")})
    AuditedRemedyAgent.seen.clear()
    restore_state(fresh.module, harness.state)
    assert AuditedRemedyAgent.seen == [sorted(harness.state)]
    assert fresh.state["settle_s"] == 1.0


@pytest.mark.parametrize(("wrong", "problem"), [
    ({"driver": "control/drvr"}, "driver: no module 'control/drvr'"),
    ({"consumers": {"sonar": "control/explore"}}, "consumers['sonar']: no module "
                                                  "'control/explore'"),
    ({"watch": "control/mapr"}, "watch: no module 'control/mapr'"),
])
def test_an_agent_refuses_at_setup_a_module_the_system_does_not_have(wrong, problem) -> None:
    """A misspelt driver was found only when the fallback stop failed: the robot drove
    on."""
    with pytest.raises(ValueError, match=re.escape(problem)):
        ModuleHarness(RemedyAgent, state=wrong, runtime=FakeRuntime())


@pytest.mark.parametrize(("driver", "standby", "problem"), [
    ({"resource": "toy://r1"}, "", "driver 'control/driver' has no state 'enabled', which "
     "the fallback stop sets (False, to stop the robot); its state is: resource"),
    ({"enabled": True, "robot": "toy://r1"}, "r2", "driver 'control/driver' has no state "
     "'resource', which the move to the standby of case 'motors-standby' sets"),
])
def test_an_agent_refuses_at_setup_a_driver_without_the_state_its_remedies_set(
        tmp_path, driver, standby, problem) -> None:
    """A user's own driver without ``enabled`` was taken: a failure calling for a stop
    left the robot driving, the stop only recorded as not having worked."""
    runtime = FakeRuntime(driver=driver)
    with pytest.raises(ValueError, match=re.escape(problem)):
        ModuleHarness(RemedyAgent, runtime=runtime, state={
            "standby_node": standby, "standby_resource": "toy://r2" * bool(standby),
            "cases_path": str(tmp_path / "learned.toml")})


def test_a_driver_without_resource_is_taken_when_there_is_no_standby_to_move_to(
        tmp_path) -> None:
    ModuleHarness(RemedyAgent, runtime=FakeRuntime(driver={"enabled": True}),
                  state={"cases_path": str(tmp_path / "learned.toml")})


# -- the agent, through its ports, against a recording runtime --------------------------

@dataclass
class FakeModule:
    cls: str
    node: str
    written: int = 0


class FakePending:
    """A move that ends when the test says so."""

    def __init__(self) -> None:
        self.outcome: tuple[str, Any] | None = None

    def done(self) -> bool:
        return self.outcome is not None

    def result(self, timeout: float = 60.0) -> Any:
        status, value = self.outcome
        if status == "failed":
            raise RuntimeFailure(value)
        return value


@dataclass
class FakeRuntime:
    """The part of ``Agent.runtime`` the remedy agent uses; it records every change."""

    calls: list[tuple[Any, ...]] = field(default_factory=list)
    up: dict[str, bool] = field(default_factory=lambda: {"r1": True, "r2": True})
    modules: dict[str, FakeModule] = field(default_factory=lambda: {
        "control/driver": FakeModule("agents.robot_driver:RobotDriver", "r1"),
        "control/explorer": FakeModule("agents.explorer:Explorer", "r1"),
        "control/mapper": FakeModule("agents.occupancy:Mapper", "r1")})
    driver: dict[str, Any] = field(default_factory=lambda: {"enabled": True,
                                                            "resource": "tcp://r1:7400"})
    moves: list[FakePending] = field(default_factory=list)

    def stats(self) -> Any:
        return SimpleNamespace(
            nodes={name: SimpleNamespace(up=up) for name, up in self.up.items()},
            modules={name: SimpleNamespace(cls=m.cls, node=m.node, outputs={"out": m.written})
                     for name, m in self.modules.items()})

    def migrate(self, name: str, to: str, *, wait: bool = True,
                state: dict[str, dict[str, Any]] | None = None) -> FakePending:
        self.calls.append(("migrate", name, to, wait, state))
        self.moves.append(FakePending())
        self.arriving = state or {}
        return self.moves[-1]

    def end_move(self, to: str = "r2") -> None:
        for name, module in self.modules.items():
            if name.startswith("control/"):
                module.node = to
        self.driver.update(self.arriving.get("control/driver", {}))     # set on arrival
        phases = MigrationPhases(unwire_s=0.02, capture_s=0.03, restore_s=0.04,
                                 rewire_s=0.05, start_s=0.01)
        self.moves[-1].outcome = ("done", MigrationReport("control", "r1", to, pause_s=0.15,
                                                          state_bytes=1, links=15,
                                                          phases=phases, prepare_s=0.1))

    def where(self, name: str) -> str:
        if name not in self.modules:
            raise ModuleNotFound(f"no module {name!r} in system 'lab'")
        return self.modules[name].node

    def set_state(self, name: str, values: dict[str, Any]) -> None:
        self.calls.append(("set_state", name, values))
        if name == "control/driver":
            self.driver.update(values)

    def state(self, name: str, **_: Any) -> dict[str, Any]:
        return dict(self.driver)

    def swap(self, name: str, cls: str) -> list[str]:
        self.calls.append(("swap", name, cls))
        self.modules[name].cls = cls
        return []


class Clock:
    def __init__(self) -> None:
        self.now = 1_000.0

    def time(self) -> float:
        return self.now


@pytest.fixture
def clock(monkeypatch) -> Clock:
    clock = Clock()
    monkeypatch.setattr(remedy_module, "time", clock)
    return clock


def agent(tmp_path: Path, runtime: FakeRuntime, **state: Any) -> ModuleHarness:
    return ModuleHarness(RemedyAgent, runtime=runtime, name="remedy", state={
        "standby_node": "r2", "standby_resource": "tcp://r2:7400",
        "consumers": {"sonar": "control/explorer"}, "fallbacks": {"sonar": SONAR_FREE},
        "cases_path": str(tmp_path / "learned.toml"), **state})


def failure(fault: str, at: float, **detail: Any) -> dict[str, Any]:
    return {"fault": fault, "probability": 0.95, "at": at, "detail": detail}


# the macro moves to the standby's node, its driver re-pointed at the standby as it arrives
MOVE = ("migrate", "control", "r2", False, {"control/driver": {"resource": "tcp://r2:7400"}})


def events(harness: ModuleHarness) -> list[tuple[str, str, str]]:
    return [(out["event"], out["action"], out["case"]) for out in harness.written["remedy"]]


def test_motors_failure_moves_the_macro_with_the_driver_re_pointed_on_arrival(tmp_path,
                                                                             clock) -> None:
    runtime = FakeRuntime()
    harness = agent(tmp_path, runtime)
    harness.feed("failure", failure("motors", clock.now))
    harness.step()
    assert runtime.calls == [MOVE]

    for late in (0.1, 0.5):                      # the monitor goes on reporting
        clock.now += 0.2
        harness.feed("failure", failure("motors", clock.now - late))
        harness.step()
    assert runtime.calls == [MOVE]

    runtime.end_move()
    clock.now += 0.2
    harness.step()
    assert runtime.calls == [MOVE] and runtime.driver["resource"] == "tcp://r2:7400"
    assert harness.state["standby_node"] == ""
    moved_at = clock.now

    runtime.modules["control/driver"].written += 10         # r2's sensors flow
    clock.now += 1.0                       # an echo of r1, within settle_s: not a recurrence
    harness.feed("failure", failure("motors", clock.now))
    harness.step()
    clock.now = moved_at + harness.state["verify_s"]
    harness.step()

    assert len(runtime.calls) == 1
    assert events(harness) == [("chosen", "move_macro", "motors-standby"),
                               ("worked", "move_macro", "motors-standby")]
    # what the move cost, for a report (the agent saw it done 0.6 s after choosing it)
    assert harness.written["remedy"][-1]["move"] == {
        "prepare_s": 0.1, "pause_s": 0.15, "seen_done_s": 0.6,
        "phases": {"unwire_s": 0.02, "capture_s": 0.03, "transfer_s": 0.0,
                   "restore_s": 0.04, "rewire_s": 0.05, "start_s": 0.01}}
    assert "move" not in harness.written["remedy"][0]
    (entry,) = harness.state["history"]
    assert entry["worked"] and entry["ended"] == moved_at
    assert harness.state["action"] == {}
    learned = CaseBase.load([tmp_path / "learned.toml"]).case("motors-standby")
    assert (learned.tried, learned.worked) == (1, 1)

    clock.now += 1.0                       # reported before it was judged: already handled
    harness.feed("failure", failure("motors", clock.now - 2.0))
    harness.step()
    assert len(runtime.calls) == 1
    harness.feed("failure", failure("motors", clock.now))      # r2's motors now: no standby
    harness.step()
    assert runtime.calls[1] == ("set_state", "control/driver", {"enabled": False})
    assert events(harness)[-2:] == [("chosen", "stop", "motors-alone"),
                                    ("worked", "stop", "motors-alone")]


def test_a_robot_its_driver_cannot_reach_is_left_for_the_standby(tmp_path, clock) -> None:
    """The driver's word that its robot is silent (its server died): mapping stopped
    without a remedy, since the monitor, which judges readings, got none."""
    runtime = FakeRuntime()
    harness = agent(tmp_path, runtime)
    harness.feed("driver_failure", {"fault": "robot_link", "probability": 1.0,
                                    "at": clock.now, "detail": {"periods": 5}})
    harness.step()
    assert runtime.calls == [MOVE]
    assert events(harness) == [("chosen", "move_macro", "robot-link-standby")]


def test_a_fault_that_comes_back_after_the_move_fails_it_and_stops(tmp_path, clock) -> None:
    runtime = FakeRuntime()
    harness = agent(tmp_path, runtime)
    harness.feed("failure", failure("motors", clock.now))
    harness.step()
    runtime.end_move()
    harness.step()
    clock.now += harness.state["settle_s"] + 0.5
    harness.feed("failure", failure("motors", clock.now))
    harness.step()
    assert runtime.calls[-1] == ("set_state", "control/driver", {"enabled": False})
    assert [event for event, _, _ in events(harness)] == ["chosen", "failed", "chosen", "worked"]
    assert harness.state["history"][0]["outcome"] == "the motors fault came back"
    assert harness.state["stopped"] and runtime.driver["enabled"] is False
    learned = CaseBase.load([tmp_path / "learned.toml"]).case("motors-standby")
    assert (learned.tried, learned.worked) == (1, 0)

    harness.feed("failure", failure("sonar", clock.now + 1, sonars=[3]))    # stopped: no more
    harness.step()
    assert len(runtime.calls) == 2


def test_a_move_that_fails_leaves_the_standby_alone_and_stops(tmp_path, clock) -> None:
    runtime = FakeRuntime()
    harness = agent(tmp_path, runtime)
    harness.feed("failure", failure("motors", clock.now))
    harness.step()
    runtime.moves[-1].outcome = ("failed", "node r2 refused the modules")
    harness.step()
    assert runtime.calls[1:] == [("set_state", "control/driver", {"enabled": False})]
    assert "node r2 refused the modules" in harness.state["history"][0]["outcome"]
    assert runtime.driver["resource"] == "tcp://r1:7400"    # never re-pointed: not arrived


def test_a_remedy_that_fails_is_logged_as_an_error(tmp_path, clock, caplog) -> None:
    """A stop that failed was only recorded in the history: nothing said the robot drove
    on."""
    runtime = FakeRuntime()
    harness = agent(tmp_path, runtime)
    runtime.set_state = lambda name, values: (_ for _ in ()).throw(
        RuntimeFailure("module 'control/driver': no state 'enabled'"))
    with caplog.at_level("ERROR", logger="agents.remedy"):
        harness.feed("failure", failure("battery", clock.now))
        harness.step()
    assert harness.state["history"][0]["worked"] is False
    (record,) = [r for r in caplog.records if r.name == "agents.remedy"]
    assert record.levelname == "ERROR"
    assert "stop for the battery failure did not work: stop failed: module " in record.message


def test_a_restored_agent_finishes_its_move_by_looking_where_the_driver_runs(
        tmp_path, clock) -> None:
    runtime = FakeRuntime()
    harness = agent(tmp_path, runtime)
    harness.feed("failure", failure("motors", clock.now))
    harness.step()
    state = pickle.loads(pickle.dumps(harness.state))     # as a migration carries it
    assert state["action"]["phase"] == "moving"

    restored = ModuleHarness(RemedyAgent, runtime=runtime, state=state)
    restored.step()
    assert len(runtime.calls) == 1                        # the move has not ended yet
    runtime.end_move()
    restored.step()
    assert runtime.calls == [MOVE] and restored.state["action"]["phase"] == "verifying"


def test_a_move_not_seen_to_end_in_time_has_failed(tmp_path, clock) -> None:
    runtime = FakeRuntime()
    harness = agent(tmp_path, runtime)
    harness.feed("failure", failure("motors", clock.now))
    harness.step()
    restored = ModuleHarness(RemedyAgent, runtime=runtime, state=harness.state)
    clock.now += harness.state["move_timeout_s"] + 1
    restored.step()
    assert runtime.calls[1:] == [("set_state", "control/driver", {"enabled": False})]
    assert "had not ended after 60 s" in restored.state["history"][0]["outcome"]


def test_dead_sonars_swap_their_consumer_for_one_that_does_without(tmp_path, clock) -> None:
    runtime = FakeRuntime()
    harness = agent(tmp_path, runtime)
    harness.feed("failure", failure("sonar", clock.now, sonars=[3, 4]))
    harness.step()
    assert runtime.calls == [("swap", "control/explorer", SONAR_FREE)]
    runtime.modules["control/explorer"].written += 5
    clock.now += harness.state["verify_s"]
    harness.step()
    assert events(harness)[-1] == ("worked", "swap", "sonar-few")

    harness.feed("failure", failure("sonar", clock.now + 1, sonars=[3, 4, 5]))
    harness.step()                    # already swapped: on to the robot whose sonars work
    assert runtime.calls[-1] == MOVE
    chosen = harness.written["remedy"][-1]
    assert chosen["case"] == "sonar-many-standby" and "already is a" in chosen["reason"]


def test_a_monitor_s_sonar_detail_counts_each_dead_transducer_once(tmp_path, clock) -> None:
    """The monitor's detail names the dead transducers in two lists side by side; both
    were counted, so 3 dead sonars made 6 and the case for many was taken (the robot
    moved away, or stopped), not the swap."""
    detail = {"sonars": [3, 9, 12], "silent_sweep": [4.0, 4.0, 4.0]}
    assert situation_of(failure("sonar", 0.0, **detail), standby=True)["failed_sensors"] == 3
    said = situation_of(failure("sonar", 0.0, failed_sensors=2, **detail), standby=True)
    assert said["failed_sensors"] == 2                   # a detail that says, is believed
    runtime = FakeRuntime()
    harness = agent(tmp_path, runtime)
    harness.feed("failure", failure("sonar", clock.now, **detail))
    harness.step()
    assert runtime.calls == [("swap", "control/explorer", SONAR_FREE)]


def test_a_detail_s_numpy_and_non_finite_numbers_learn_a_case_that_reads_back(tmp_path,
                                                                            clock) -> None:
    """A numpy number in a failure's detail was written into the learned case as
    ``np.float64(-0.31)``, a file no agent could read again; a NaN made learning raise
    before the robot was stopped for a remedy that had failed."""
    detail = {"v_residual": np.float64(-0.31), "w_residual": math.nan, "count": np.int64(4)}
    for worked in (True, False):
        runtime = FakeRuntime()
        (tmp_path / str(worked)).mkdir()
        harness = agent(tmp_path / str(worked), runtime)
        # (a probability below the case's: a remedy that works is learned as a new case)
        harness.feed("failure", {**failure("motors", clock.now, **detail), "probability": 0.0})
        harness.step()
        assert runtime.calls == [MOVE]
        if worked:
            runtime.end_move()
            harness.step()
            runtime.modules["control/driver"].written += 10
            clock.now += harness.state["verify_s"]
        else:
            runtime.moves[-1].outcome = ("failed", "node r2 is not up")
        harness.step()
        base = CaseBase.load([tmp_path / str(worked) / "learned.toml"])
        if worked:      # a new case, the situation as its symptoms
            (learned,) = [case for case in base.cases if "/learned-" in case.id]
            assert learned.symptoms["v_residual"] == -0.31 and learned.symptoms["count"] == 4
            assert "w_residual" not in learned.symptoms
        else:           # the robot stopped, and the case counts the attempt
            assert runtime.calls[-1] == ("set_state", "control/driver", {"enabled": False})
            assert events(harness)[-2:] == [("chosen", "stop", ""), ("worked", "stop", "")]
            assert base.case("motors-standby").tried == 1


def test_a_failure_no_case_fits_stops_the_robot(tmp_path, clock) -> None:
    runtime = FakeRuntime()
    harness = agent(tmp_path, runtime)
    harness.feed("failure", failure("battery", clock.now))
    harness.step()
    assert runtime.calls == [("set_state", "control/driver", {"enabled": False})]
    (chosen, done) = harness.written["remedy"]
    assert (chosen["case"], chosen["action"], done["event"]) == ("", "stop", "worked")
    assert not (tmp_path / "learned.toml").exists()        # the fallback is no case to learn


def test_a_failure_of_another_kind_waits_for_the_remedy_under_way(tmp_path, clock) -> None:
    runtime = FakeRuntime()
    harness = agent(tmp_path, runtime)
    harness.feed("failure", failure("motors", clock.now))
    harness.feed("failure", failure("sonar", clock.now + 0.1, sonars=[1]))   # r1's sonar
    harness.step()
    runtime.end_move()
    clock.now += 1.0
    harness.step()
    harness.feed("failure", failure("odometry", clock.now + 0.1))       # r2's odometry
    runtime.modules["control/driver"].written += 3
    clock.now += harness.state["verify_s"]
    harness.step()
    assert [event[:2] for event in events(harness)] == [
        ("chosen", "move_macro"), ("worked", "move_macro"),
        ("chosen", "carry_on"), ("worked", "carry_on")]     # nothing reads odometry
    assert harness.state["deferred"] == []


def test_the_agents_state_pickles_in_the_middle_of_a_move(tmp_path, clock) -> None:
    runtime = FakeRuntime()
    harness = agent(tmp_path, runtime)
    harness.feed("failure", failure("motors", clock.now))
    harness.step()
    assert pickle.loads(pickle.dumps(harness.state))["action"]["case"] == "motors-standby"
    base = CaseBase.from_dict(pickle.loads(pickle.dumps(harness.state["case_base"])))
    assert base.case("sonar-few").remedy["action"] == "swap"
    retained = base.retain(Match(base.case("sonar-few"), 1.0), situation("sonar"), True,
                           tmp_path / "x.toml")
    assert retained.tried == 1


# -- the robot driver's enabled flag -------------------------------------------------


def test_a_sensor_nothing_reads_fails_and_the_mission_carries_on(tmp_path, clock) -> None:
    runtime = FakeRuntime()
    harness = agent(tmp_path, runtime)            # (its consumers name no odometry reader)
    harness.feed("failure", failure("odometry", clock.now, drift_per_m=0.05))
    harness.step()
    assert runtime.calls == []                    # nothing moved, swapped or stopped
    assert events(harness) == [("chosen", "carry_on", "unread-sensor"),
                               ("worked", "carry_on", "unread-sensor")]
    assert not harness.state["stopped"]
    harness.feed("failure", failure("motors", clock.now + 1))
    harness.step()                                # and a real fault is still acted on
    assert runtime.calls[-1] == MOVE


def test_a_sensor_a_module_reads_is_never_carried_on_with(tmp_path, clock) -> None:
    # the localizer reads odometry, and there is no class that does without it: the
    # swap cannot be made, and carrying on ("no module reads it") would be false
    runtime = FakeRuntime()
    runtime.modules["control/localizer"] = FakeModule("my.localizers:Odometric", "r1")
    harness = agent(tmp_path, runtime, consumers={"odometry": "control/localizer"})
    harness.feed("failure", failure("odometry", clock.now, drift_per_m=0.05))
    harness.step()
    assert runtime.calls == [("set_state", "control/driver", {"enabled": False})]
    chosen = harness.written["remedy"][0]
    assert (chosen["action"], chosen["case"]) == ("stop", "")
    assert "no value for {fallback}" in chosen["reason"]
    assert "a module reads" in chosen["reason"]
    assert not (tmp_path / "learned.toml").exists()   # no carry_on case learned for it


def test_a_case_base_set_while_it_runs_is_what_it_goes_by(tmp_path, clock) -> None:
    """A case base set on a running agent (the State Editor, another agent) is planned by
    from the next failure, and kept as it learns; one with a remedy it cannot carry out
    is refused, naming the case, and nothing is set."""
    runtime = FakeRuntime()
    harness = agent(tmp_path, runtime)
    base = harness.state["case_base"]
    odd = {**base["cases"][0], "id": "odd", "remedy": {"action": "reboot"}}
    with pytest.raises(ValueError, match=r"RemedyAgent's case_base: .*case 'odd': unknown "
                                         "action 'reboot'"):
        harness.module.set_state({"case_base": {**base, "cases": [*base["cases"], odd]}})
    # checked as a file's cases are (a bare KeyError came at the first failure)
    for wrong, named in [
            ({"cases": base["cases"]}, r"case_base: give what CaseBase.to_dict\(\) gives"),
            ({**base, "cases": [{**odd, "remedy": {}}]}, "case 'odd': no remedy action"),
            ({**base, "cases": [{**odd, "tried": -1}]}, "tried = -1 and worked = 0 must be"),
            ({**base, "settings": {"mine.toml": {"min_similarity": 2}}},
             r"the settings of mine.toml\): min_similarity must be a number from 0 to 1")]:
        with pytest.raises(ValueError, match=named):       # (its state_problems: StateRefused)
            harness.module.set_state({"case_base": wrong})
    assert harness.state["case_base"] == base
    without_motors = [case for case in base["cases"]
                      if case["symptoms"].get("fault") != "motors"]
    harness.module.set_state({"case_base": {**base, "cases": without_motors}})
    harness.feed("failure", failure("motors", clock.now))
    assert runtime.calls == [("set_state", "control/driver", {"enabled": False})]
    assert events(harness) == [("chosen", "stop", ""), ("worked", "stop", "")]
    assert harness.state["case_base"]["cases"] == without_motors


def test_a_standby_node_the_system_does_not_have_is_named_as_the_robot_is_stopped(
        tmp_path, clock) -> None:
    """A misspelt standby node made the agent stop the robot, its reason empty."""
    runtime = FakeRuntime()
    harness = agent(tmp_path, runtime, standby_node="robot2")
    harness.feed("failure", failure("motors", clock.now))
    harness.step()
    chosen = harness.written["remedy"][0]
    assert (chosen["event"], chosen["action"]) == ("chosen", "stop")
    assert chosen["reason"].startswith("standby_node 'robot2' is no node of the system "
                                       "(nodes: r1, r2)")
