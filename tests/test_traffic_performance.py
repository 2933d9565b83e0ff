"""``PerformanceAgent`` on its own, with a recording runtime: it swaps by its rules
after a whole window, no sooner than its minimum time between swaps, falls back to
fixed time at once when the detectors fail (silent or implausible) and comes back
after a window of good readings, keeps a learner's table across swaps; and in a
running system, where its swaps are the system's events."""

from __future__ import annotations

import contextlib
import pickle
from pathlib import Path
from typing import Any

import pytest
from conftest import eventually

from agents.traffic.messages import JunctionMeasures
from agents.traffic.performance import PerformanceAgent
from pb3a import System
from pb3a.errors import ModuleNotFound, RuntimeCancelled, RuntimeFailure, RuntimeTimeout
from pb3a.loading.references import resolve_class
from pb3a.testing import ModuleHarness

CONTROLLERS = {
    "fixed_time": {"class": "agents.traffic.fixed_time:FixedTime", "state": {"green_s": 25.0}},
    "gap_out": {"class": "agents.traffic.gap_out:GapOut", "state": {"max_green_s": 40.0}},
    "max_pressure": {"class": "agents.traffic.max_pressure:MaxPressure", "state": {}},
    "q_learning": {"class": "agents.traffic.learning:QLearning", "state": {}},
}


class RecordingRuntime:
    """What the agent asks of the system, kept; a controller's state served back."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, ...]] = []
        self.controller_state: dict[str, Any] = {}

    def state(self, name: str) -> dict[str, Any]:
        return dict(self.controller_state)

    def swap(self, name: str, cls: str) -> list[str]:
        self.calls.append(("swap", name, cls.rpartition(":")[2]))
        self.controller_state = {}
        return []

    def set_state(self, name: str, values: dict[str, Any]) -> None:
        self.calls.append(("set_state", name, tuple(sorted(values))))
        self.controller_state.update(values)

    def where(self, name: str) -> str:
        if name != "W/controller":
            raise ModuleNotFound(f"no module {name!r} in system 'city'; modules: "
                                 "W/controller, W/agent")
        return "local"

    def swaps(self) -> list[str]:
        return [call[2] for call in self.calls if call[0] == "swap"]


def agent(**state: Any) -> tuple[ModuleHarness, RecordingRuntime]:
    runtime = RecordingRuntime()
    harness = ModuleHarness(PerformanceAgent, runtime=runtime, state={
        "controller": "W/controller", "controllers": CONTROLLERS, "running": "gap_out",
        "window_s": 60.0, "min_between_swaps_s": 120.0, "silent_after_s": 10.0,
        "silent_wall_s": 0.0,
        "rules": [{"use": "gap_out"}, {"use": "max_pressure", "queue_at_least": 6.0}],
        **state})
    return harness, runtime


def measure(time: float, queue: int = 0, arrivals: int = 0, *, plausible: bool = True,
            ) -> JunctionMeasures:
    return JunctionMeasures("W", int(time), time, queue, 0.0, arrivals, plausible)


def feed(harness: ModuleHarness, start: float, end: float, **values: Any) -> None:
    """A measure (and the driver's clock) every simulated second of [start, end)."""
    for second in range(int(start), int(end)):
        harness.feed("measures", measure(float(second), **values))
        harness.feed("clock", float(second))


def test_it_swaps_by_its_rules_once_it_has_measured_a_whole_window() -> None:
    harness, runtime = agent()
    feed(harness, 0, 59, queue=9)            # congested, but not yet a whole window
    assert runtime.swaps() == []
    feed(harness, 59, 61, queue=9)
    assert runtime.swaps() == ["MaxPressure"]
    assert runtime.calls[-1] == ("set_state", "W/controller", ())   # its configured state
    swap = harness.state["swaps"][0]
    assert (swap["time"], swap["from"], swap["to"]) == (60.0, "gap_out", "max_pressure")
    assert "queue 9.0" in swap["reason"] and harness.last("swapped") == swap
    assert harness.state["running"] == "max_pressure" and harness.state["mean_queue"] == 9.0


def test_it_waits_the_minimum_time_between_two_swaps() -> None:
    harness, runtime = agent()
    feed(harness, 0, 61, queue=9)            # swapped at 60 s
    feed(harness, 61, 179, queue=0)          # light again at once: it must not flap
    assert runtime.swaps() == ["MaxPressure"]
    feed(harness, 179, 181, queue=0)         # 120 s after the first swap
    assert runtime.swaps() == ["MaxPressure", "GapOut"]
    assert [s["time"] for s in harness.state["swaps"]] == [60.0, 180.0]


def test_with_hysteresis_the_chosen_rule_holds_until_its_measure_falls_well_below() -> None:
    """A saturated junction lets fewer vehicles in, so the demand it measures falls
    while the surge lasts: without hysteresis it swapped back mid-surge."""
    rules = [{"use": "gap_out"}, {"use": "max_pressure", "demand_at_least": 45.0}]
    for hysteresis, mid_surge in ((0.0, ["MaxPressure", "GapOut"]), (0.35, ["MaxPressure"])):
        harness, runtime = agent(rules=rules, hysteresis=hysteresis)
        feed(harness, 0, 61, arrivals=1)                  # 60 a minute: swapped at 60 s
        for second in range(61, 400):                     # 30 a minute: above 45 * 0.65
            harness.feed("measures", measure(float(second), arrivals=second % 2))
            harness.feed("clock", float(second))
        assert runtime.swaps() == mid_surge, hysteresis
        feed(harness, 400, 600, arrivals=0)               # light again: back for both
        assert runtime.swaps() == ["MaxPressure", "GapOut"], hysteresis


def test_silent_detectors_bring_fixed_time_at_once_and_it_comes_back_after() -> None:
    harness, runtime = agent(silent_wall_s=0.5)
    wall = [50.0]
    harness.module._wall = lambda: wall[0]
    feed(harness, 0, 61, queue=9)            # (a swap at 60 s: the minimum time runs)
    for second in range(61, 75):             # the readings stop; the clock goes on
        harness.feed("clock", float(second))
    assert runtime.swaps() == ["MaxPressure"]   # they may only lag: wait a little
    wall[0] += 0.6
    harness.step()
    assert runtime.swaps() == ["MaxPressure", "FixedTime"]   # within the minimum time
    assert harness.state["detectors_ok"] is False
    assert "no detector reading for 14 s" in harness.state["swaps"][-1]["reason"]
    feed(harness, 75, 134, queue=1)          # readings again: not a whole window yet
    assert runtime.swaps()[-1] == "FixedTime"
    feed(harness, 134, 136, queue=1)
    assert runtime.swaps()[-1] == "GapOut" and harness.state["detectors_ok"] is True


def test_it_says_done_with_each_measure_after_the_swap_it_called_for() -> None:
    """In lock-step the driver waits for ``done``: a swap decided on a measure is made
    before that measure's time is said done, so it runs from the next step on."""
    harness, runtime = agent()
    said: list[tuple[float, list[str]]] = []
    harness.module.done.write = lambda time_s: said.append((time_s, runtime.swaps()))
    feed(harness, 0, 61, queue=9)
    assert [time_s for time_s, _ in said] == [float(second) for second in range(61)]
    assert said[59] == (59.0, []) and said[60] == (60.0, ["MaxPressure"])


def test_it_does_not_hold_the_lock_step_for_measures_that_do_not_come() -> None:
    """A clock ahead of the measures is said done once it has waited ``silent_wall_s``
    for them (they may only lag), each clock anew, and at once while the detectors are
    failed."""
    harness, runtime = agent(silent_wall_s=0.5)
    wall = [50.0]
    harness.module._wall = lambda: wall[0]
    feed(harness, 0, 20, queue=1)
    harness.feed("clock", 20.0)              # its measure lags
    harness.step()
    assert harness.last("done") == 19.0
    harness.feed("measures", measure(20.0, queue=1))
    assert harness.last("done") == 20.0
    harness.feed("clock", 21.0)              # the measures stop
    wall[0] += 0.4
    harness.step()
    assert harness.last("done") == 20.0
    wall[0] += 0.2
    harness.step()
    assert harness.last("done") == 21.0 and harness.state["detectors_ok"] is True
    for second in range(22, 32):
        harness.feed("clock", float(second))
        assert harness.last("done") == float(second) - 1     # it waits for its measure
        wall[0] += 0.5
        harness.step()
        assert harness.last("done") == float(second)
    assert runtime.swaps() == ["FixedTime"] and harness.state["detectors_ok"] is False
    harness.feed("measures", measure(32.0, queue=1, plausible=False))
    harness.feed("clock", 33.0)              # failed: not waited for at all
    assert harness.last("done") == 33.0


def test_measures_half_a_second_late_once_are_no_failure_and_keep_the_lock_step() -> None:
    """Once a clock had waited ``silent_wall_s``, every later one was said done at once:
    the driver ran on without the measures, and 10 s of its clock later, no wall time
    having passed, the detectors were taken as failed and fixed time swapped in."""
    harness, runtime = agent(silent_wall_s=0.5)
    wall = [50.0]
    harness.module._wall = lambda: wall[0]
    feed(harness, 0, 5, queue=1)
    harness.feed("clock", 5.0)               # its measure is 0.6 s late
    wall[0] += 0.6
    harness.step()
    assert harness.last("done") == 5.0
    for second in range(6, 16):              # the clocks after it wait for theirs
        harness.feed("clock", float(second))
        assert harness.last("done") == 5.0
    harness.feed("measures", measure(5.0, queue=1))
    feed(harness, 6, 16, queue=1)            # the measures catch up
    assert harness.last("done") == 15.0
    assert runtime.swaps() == [] and harness.state["detectors_ok"] is True


def test_a_failure_met_on_fixed_time_its_rules_chose_keeps_the_time_between_swaps() -> None:
    """The rules had chosen fixed time, the fallback too, so a failure needed no swap;
    yet coming back from it dropped the time of the last swap, and the rules swapped
    again 71 s after it, for a minimum of 120."""
    harness, runtime = agent(rules=[{"use": "gap_out"},
                                    {"use": "fixed_time", "queue_at_least": 6.0}])
    feed(harness, 0, 61, queue=9)             # the rules' fixed time, at 60 s
    feed(harness, 61, 70, queue=9)
    harness.feed("measures", measure(70.0, queue=9, plausible=False))
    assert runtime.swaps() == ["FixedTime"] and harness.state["detectors_ok"] is False
    feed(harness, 71, 179, queue=0)           # back after a window (131 s); light
    assert harness.state["detectors_ok"] is True
    assert runtime.swaps() == ["FixedTime"]   # not before 120 s after the last swap
    feed(harness, 179, 181, queue=0)
    assert runtime.swaps() == ["FixedTime", "GapOut"]
    assert [s["time"] for s in harness.state["swaps"]] == [60.0, 180.0]


def test_a_re_pointed_driver_s_new_run_is_judged_on_its_own_with_the_guard_rails_kept() -> None:
    """The driver re-pointed: its clock and the measures start again from 0. The old
    run's window was kept (for as long as that run had lasted) and the time since a
    swap counted back from the old clock."""
    harness, runtime = agent()
    feed(harness, 0, 200, queue=9)           # swapped at 60 s; then re-pointed
    feed(harness, 0, 61, queue=0)            # a light run: a whole window of it
    assert harness.state["mean_queue"] == 0.0 and harness.state["demand_per_min"] == 0.0
    assert runtime.swaps() == ["MaxPressure", "GapOut"]
    assert harness.state["swaps"][-1]["time"] == 60.0
    feed(harness, 0, 119, queue=9)           # re-pointed at once: the swap was 0 s ago
    assert runtime.swaps() == ["MaxPressure", "GapOut"]
    feed(harness, 119, 121, queue=9)
    assert runtime.swaps() == ["MaxPressure", "GapOut", "MaxPressure"]


def test_silence_is_noticed_in_a_re_pointed_driver_s_new_run() -> None:
    harness, runtime = agent()
    feed(harness, 0, 200, queue=1)
    for second in range(12):                 # re-pointed; no reading comes
        harness.feed("clock", float(second))
    assert runtime.swaps() == ["FixedTime"] and harness.state["detectors_ok"] is False


def test_it_comes_back_from_fixed_time_to_its_controller_when_no_rule_holds() -> None:
    """Rules without a catch-all: the way back took the fallback as the choice."""
    harness, runtime = agent(rules=[{"use": "max_pressure", "queue_at_least": 6.0}])
    feed(harness, 0, 30, queue=1)
    harness.feed("measures", measure(30.0, queue=1, plausible=False))
    assert runtime.swaps() == ["FixedTime"]
    feed(harness, 31, 92, queue=1)           # a whole window of good readings
    assert runtime.swaps() == ["FixedTime", "GapOut"] and harness.state["detectors_ok"]


def test_detectors_silent_from_the_start_bring_fixed_time() -> None:
    harness, runtime = agent()
    for second in range(12):
        harness.feed("clock", float(second))
    assert runtime.swaps() == ["FixedTime"] and harness.state["detectors_ok"] is False


def test_a_fallback_swap_that_fails_is_tried_again() -> None:
    """The system could not swap (the controller busy past the swap's timeout): the
    agent had marked the detectors failed first, so silence never tried again."""
    harness, runtime = agent()
    refused = [TimeoutError("module 'W/controller' was busy in a call for 10.0 s")]
    swap = runtime.swap

    def failing_swap(name: str, cls: str) -> list[str]:
        if refused:
            raise refused.pop()
        return swap(name, cls)

    runtime.swap = failing_swap
    feed(harness, 0, 30, queue=1)
    for second in range(30, 40):             # the readings stop
        harness.feed("clock", float(second))
    with pytest.raises(TimeoutError):
        harness.feed("clock", 40.0)          # the fallback swap fails ...
    assert runtime.swaps() == [] and harness.state["running"] == "gap_out"
    harness.step()                           # ... and is made at the next look
    assert runtime.swaps() == ["FixedTime"] and harness.state["running"] == "fixed_time"
    assert harness.state["detectors_ok"] is False


def test_a_swap_by_the_rules_the_system_refuses_is_tried_again_after_the_minimum_time(
        ) -> None:
    """A class whose setup fails could never be swapped in, and the agent tried at every
    measure, each time the class set up in the controller's worker and an error (59 in
    a second of a run of the crossing); the measures that came with a refused one were
    dropped from its window."""
    harness, runtime = agent()

    def refusing_swap(name: str, cls: str) -> list[str]:
        runtime.calls.append(("swap", name, cls.rpartition(":")[2]))
        raise RuntimeFailure(f"worker 'local-p1': SetupError: module {name!r}: MaxPressure "
                             "raised in setup: RuntimeError: no; not swapped, GapOut runs on")

    runtime.swap = refusing_swap
    port = harness.inputs["measures"]
    refused = []
    for second in range(0, 400, 5):         # the measures come five at a time
        for each in range(second, second + 5):
            port.deliver(measure(float(each), queue=9))
        try:
            harness.module.on_input(port)
        except RuntimeFailure as exc:
            refused.append((second, exc))
        assert harness.state["mean_queue"] == 9.0 and len(harness.module._window) == (
            min(second + 5, 60)), second
    assert [second for second, _ in refused] == [60, 180, 300]
    assert runtime.swaps() == ["MaxPressure"] * 3 and harness.state["running"] == "gap_out"
    assert "not swapped, GapOut runs on" in str(refused[0][1])


def test_a_controller_whose_state_cannot_be_read_is_asked_again_after_the_minimum_time(
        ) -> None:
    """The state read before the swap was outside the swap's refusal: a controller that
    did not answer was asked at every measure, each call waiting out its timeout."""
    harness, runtime = agent()
    asked = []

    def silent(name: str) -> dict[str, Any]:
        asked.append(name)
        raise RuntimeTimeout(f"{name} did not answer 'state' within 5 s")

    runtime.state = silent
    port = harness.inputs["measures"]
    for second in range(200):
        port.deliver(measure(float(second), queue=9))
        with contextlib.suppress(RuntimeTimeout):
            harness.module.on_input(port)
    assert len(asked) == 2 and runtime.swaps() == [] and harness.state["running"] == "gap_out"


def test_implausible_readings_bring_fixed_time() -> None:
    harness, runtime = agent()
    feed(harness, 0, 30, queue=1)
    harness.feed("measures", measure(30.0, queue=1, plausible=False))
    assert runtime.swaps() == ["FixedTime"]
    assert "implausible" in harness.state["swaps"][0]["reason"]
    feed(harness, 31, 60, queue=1)
    harness.feed("measures", measure(60.0, plausible=False))   # again: it stays, no swap
    assert runtime.swaps() == ["FixedTime"]


def test_a_learners_table_is_kept_when_swapped_out_and_given_back() -> None:
    harness, runtime = agent(running="q_learning", rules=[
        {"use": "q_learning"}, {"use": "gap_out", "queue_at_least": 6.0}])
    runtime.controller_state = {"table": {"1|0|0|2": [-3.0, -4.0]}, "updates": 7}
    feed(harness, 0, 61, queue=9)
    assert runtime.swaps() == ["GapOut"]
    feed(harness, 61, 181, queue=0)
    assert runtime.swaps() == ["GapOut", "QLearning"]
    assert runtime.controller_state["table"] == {"1|0|0|2": [-3.0, -4.0]}


class CarryingRuntime(RecordingRuntime):
    """One real controller; a swap carries its state over where the new class has the
    same setting, as the system's swap does."""

    def __init__(self, controller: Any) -> None:
        super().__init__()
        self.controller = controller

    def state(self, name: str) -> dict[str, Any]:
        return self.controller.get_state()

    def swap(self, name: str, cls: str) -> list[str]:
        self.calls.append(("swap", name, cls.rpartition(":")[2]))
        old, self.controller = self.controller.get_state(), resolve_class(cls)()
        self.controller.set_state({k: v for k, v in old.items()
                                   if k in self.controller.state_names()})
        return []

    def set_state(self, name: str, values: dict[str, Any]) -> None:
        self.calls.append(("set_state", name, tuple(sorted(values))))
        self.controller.set_state(values)


def test_a_controller_swapped_in_has_its_class_s_settings_where_its_spec_gives_none() -> None:
    """The swap carries a setting over where both classes have it: Q-learning (given no
    state) ran with the gap-out's minimum and maximum greens of 8 and 40 s, not its own
    5 and 60, as it does alone; after longest-queue-first, with its 12 and 30."""
    from agents.traffic.gap_out import GapOut

    gap_out = GapOut()
    gap_out.set_state({"min_green_s": 8.0, "max_green_s": 40.0})
    runtime = CarryingRuntime(gap_out)
    harness = ModuleHarness(PerformanceAgent, runtime=runtime, state={
        "controller": "W/controller", "controllers": CONTROLLERS, "running": "gap_out",
        "rules": [{"use": "gap_out"}, {"use": "q_learning", "queue_at_least": 6.0}]})
    feed(harness, 0, 61, queue=9)
    assert runtime.swaps() == ["QLearning"]
    learner = runtime.controller.get_state()
    assert (learner["min_green_s"], learner["max_green_s"]) == (5.0, 60.0)
    feed(harness, 61, 200, queue=0)          # and back: gap-out as its spec says
    assert runtime.swaps() == ["QLearning", "GapOut"]
    assert (runtime.controller.min_green_s, runtime.controller.max_green_s) == (5.0, 40.0)


def test_the_tables_it_keeps_move_with_it() -> None:
    """They were kept out of its state (set empty by setup), so an agent moved to
    another node, or restarted from its last state, gave a learner swapped back in the
    table it started from, all it had learnt lost."""
    harness, runtime = agent(running="q_learning", rules=[
        {"use": "q_learning"}, {"use": "gap_out", "queue_at_least": 6.0}])
    runtime.controller_state = {"table": {"1|0|0|2": [-3.0, -4.0]}}
    feed(harness, 0, 61, queue=9)            # swapped out at 60 s: its table kept
    assert runtime.swaps() == ["GapOut"]
    moved = ModuleHarness(PerformanceAgent, runtime=runtime,   # (as a move carries it)
                          state=pickle.loads(pickle.dumps(harness.state)))
    feed(moved, 61, 181, queue=0)
    assert runtime.swaps() == ["GapOut", "QLearning"]
    assert runtime.controller_state["table"] == {"1|0|0|2": [-3.0, -4.0]}


def test_rules_naming_a_controller_it_does_not_have_are_refused_by_name() -> None:
    with pytest.raises(ValueError, match="no controller webster in controllers"):
        agent(rules=[{"use": "webster"}])


def test_such_rules_set_while_it_runs_are_refused_by_name_and_nothing_is_set() -> None:
    """Taken, they failed its next swap (a KeyError deep in it)."""
    harness, runtime = agent()
    with pytest.raises(ValueError, match="no controller webster in controllers"):
        harness.module.set_state({"rules": [{"use": "webster", "queue_at_least": 6.0}],
                                  "window_s": 30.0})
    assert harness.state["rules"][-1]["use"] == "max_pressure"
    assert harness.state["window_s"] == 60.0
    feed(harness, 0, 61, queue=9)
    assert runtime.swaps() == ["MaxPressure"]


def test_a_swap_whose_state_cannot_be_set_is_recorded_said_once_and_not_made_again() -> None:
    """Swap and state are two requests. Before, a state the new controller refused left
    it running with ``running`` naming the old one: the agent swapped again at every
    measure (an error each), and the new class's table was kept under the old name."""
    harness, runtime = agent(running="q_learning", rules=[
        {"use": "q_learning"}, {"use": "gap_out", "queue_at_least": 6.0}])
    table = {"1|0|0|2": [-3.0, -4.0]}
    runtime.controller_state = {"table": table, "updates": 7}
    set_state = runtime.set_state

    def refusing_set_state(name: str, values: dict[str, Any]) -> None:
        if runtime.swaps()[-1] == "GapOut":
            raise KeyError("GapOut has no state 'max_gren_s'")
        set_state(name, values)

    runtime.set_state = refusing_set_state
    feed(harness, 0, 60, queue=9)
    with pytest.raises(RuntimeError, match=r"swapped it from q_learning to gap_out .*"
                       r"could not set its state: KeyError") as said:
        harness.feed("measures", measure(60.0, queue=9))
    assert "runs on with the state the swap carried over" in str(said.value)
    assert runtime.swaps() == ["GapOut"] and harness.state["running"] == "gap_out"
    swap = harness.state["swaps"][-1]
    assert (swap["from"], swap["to"]) == ("q_learning", "gap_out")
    assert "max_gren_s" in swap["state_error"] and harness.last("swapped") == swap
    feed(harness, 61, 120, queue=9)          # no error again, no swap again
    assert runtime.swaps() == ["GapOut"] and len(harness.state["swaps"]) == 1
    feed(harness, 120, 181, queue=0)         # back to the learner: its own table
    assert runtime.swaps() == ["GapOut", "QLearning"]
    assert runtime.controller_state["table"] == table
    assert harness.state["running"] == "q_learning" and "state_error" not in \
        harness.state["swaps"][-1]


def test_a_swap_cut_short_by_the_system_stopping_is_recorded_and_said_quietly() -> None:
    """A swap in flight as the system stops (the driver's run over, the agents still
    taking their last measures): the controller's state request is cancelled, and the
    agent wrapped that in a RuntimeError, a traceback in the scenario's output ("could
    not set its state: RuntimeCancelled: ... the module is stopping"). Cancelled, a
    body's request is no error: the worker logs it at debug level."""
    harness, runtime = agent()

    def cancelled(name: str, values: dict[str, Any]) -> None:
        raise RuntimeCancelled("W/agent's request 'set_state' cancelled: the module is "
                               "stopping")

    runtime.set_state = cancelled
    feed(harness, 0, 60, queue=9)
    with pytest.raises(RuntimeCancelled):
        harness.feed("measures", measure(60.0, queue=9))
    swap, = harness.state["swaps"]
    assert swap["to"] == "max_pressure" and "the module is stopping" in swap["state_error"]


def test_a_fallback_swap_whose_state_cannot_be_set_is_made_once() -> None:
    harness, runtime = agent()
    set_state = runtime.set_state

    def refusing_set_state(name: str, values: dict[str, Any]) -> None:
        if runtime.swaps()[-1] == "FixedTime":
            raise ValueError("FixedTime: green_s must be ...")
        set_state(name, values)

    runtime.set_state = refusing_set_state
    feed(harness, 0, 30, queue=1)
    with pytest.raises(RuntimeError, match="to fixed_time"):
        harness.feed("measures", measure(30.0, queue=1, plausible=False))
    assert harness.state["running"] == "fixed_time" and harness.state["detectors_ok"] is False
    harness.feed("measures", measure(31.0, queue=1, plausible=False))
    harness.step()
    assert runtime.swaps() == ["FixedTime"]


BAD_SETTINGS = [             # (settings, what the refusal names)
    ({"window_s": -10.0}, "window_s must be a number of seconds above 0, got -10.0"),
    ({"window_s": float("nan")}, "window_s must be"),
    ({"min_between_swaps_s": float("nan")}, "min_between_swaps_s must be a number of "
                                            "seconds, 0 or more, got nan"),
    ({"min_between_swaps_s": -1.0}, "min_between_swaps_s must be"),
    ({"silent_after_s": float("inf")}, "silent_after_s must be"),
    ({"silent_after_s": 0.0}, "silent_after_s must be"),
    ({"silent_wall_s": True}, "silent_wall_s must be"),
    ({"hysteresis": 1.5}, "hysteresis must be a number from 0 to 1, got 1.5"),
    ({"rules": [{"use": "max_pressure", "demand_atleast": 100.0}]},
     "rules[0]: unknown key 'demand_atleast' (did you mean 'demand_at_least'?)"),
    ({"rules": [{"use": "gap_out"}, {"use": "max_pressure", "queue_at_least": float("nan")}]},
     "rules[1].queue_at_least must be a number, 0 or more, got nan"),
    ({"rules": [{"queue_at_least": 6.0}]}, "rules[0] needs 'use'"),
    ({"rules": {"use": "gap_out"}}, "rules must be a list"),
    ({"controller": ""}, "controller must be the controller's module name"),
    ({"controllers": {**CONTROLLERS, "gap_out": {
        "class": "agents.traffic.gap_out:GapOot", "state": {}}}},
     "controllers.gap_out.class: module 'agents.traffic.gap_out' has no class 'GapOot' "
     "(did you mean 'GapOut'?)"),
    ({"controllers": {**CONTROLLERS, "gap_out": {"class": "agents.traffic.gapout:GapOut"}}},
     "controllers.gap_out.class: cannot import module 'agents.traffic.gapout'"),
    ({"controllers": {**CONTROLLERS, "gap_out": {
        "class": "agents.traffic.gap_out:GapOut", "state": {"max_gren_s": 40.0}}}},
     "controllers.gap_out.state: agents.traffic.gap_out:GapOut has no state 'max_gren_s' "
     "(did you mean 'max_green_s'?)"),
    ({"controllers": {**CONTROLLERS, "gap_out": {
        "class": "agents.traffic.gap_out:GapOut", "state": {"max_green_s": -5.0}}}},
     "controllers.gap_out.state: GapOut's max_green_s must be a number of seconds, 1 or "
     "more (a control step), got -5.0"),
    ({"controllers": {**CONTROLLERS, "gap_out": {
        "class": "agents.traffic.gap_out:GapOut", "sate": {}}}},
     "controllers.gap_out: unknown key 'sate' (did you mean 'state'?)"),
    ({"controllers": {**CONTROLLERS, "gap_out": {"class": "pb3a:System"}}},
     "controllers.gap_out.class: pb3a.system:System is not a pb3a.Module"),
    # what it keeps of its own (moved with it, set in the State Editor): a last swap
    # at "x" failed every measure (TypeError) and at NaN never swapped again, swaps
    # that were no list failed the next swap after it was made, a detectors_ok of
    # "no" read as true
    ({"last_swap_s": "x"}, "last_swap_s must be a number (simulated seconds), got 'x'"),
    ({"last_swap_s": float("nan")}, "last_swap_s must be a number"),
    ({"swaps": None}, "swaps must be a list of the swaps' records, got None"),
    ({"detectors_ok": "no"}, "detectors_ok must be true or false, got 'no'"),
    ({"kept": {"q_learning": [1]}}, "kept must be a table of controller name = { its "
                                    "learnt state }, got {'q_learning': [1]}"),
    ({"controllers": {**CONTROLLERS, "q_learning": {
        "class": "agents.traffic.learning:QLearning", "state": {"table": {"k": [1.0]}}}}},
     "controllers.q_learning.state: QLearning's table['k'] must be"),
]


@pytest.mark.parametrize(("wrong", "named"), BAD_SETTINGS,
                         ids=[next(iter(w)) + f"-{i}" for i, (w, _) in enumerate(BAD_SETTINGS)])
def test_a_setting_it_could_not_go_by_is_refused_by_name_at_setup(
        wrong: dict[str, Any], named: str) -> None:
    """Before, each was taken: a negative window failed every measure (IndexError), a
    NaN minimum time never swapped, a misspelt threshold was 0 (the rule always held),
    a class or a controller's state that would not do failed every swap to it."""
    with pytest.raises(ValueError, match=r"^PerformanceAgent's ") as refused:
        agent(**wrong)
    assert named in str(refused.value)


@pytest.mark.parametrize(("wrong", "named"), BAD_SETTINGS,
                         ids=[next(iter(w)) + f"-{i}" for i, (w, _) in enumerate(BAD_SETTINGS)])
def test_such_a_setting_set_while_it_runs_is_refused_by_name_and_nothing_is_set(
        wrong: dict[str, Any], named: str) -> None:
    harness, runtime = agent()
    before = harness.state
    with pytest.raises(ValueError, match=r"^PerformanceAgent's ") as refused:
        harness.module.set_state({"fallback": "gap_out", "silent_after_s": 20.0, **wrong})
    assert named in str(refused.value)
    assert harness.state == before
    feed(harness, 0, 61, queue=9)            # it goes on by its settings
    assert runtime.swaps() == ["MaxPressure"]


def test_a_controller_that_is_no_module_of_the_system_is_refused_at_setup() -> None:
    with pytest.raises(ValueError, match="performance agent: controller: "
                       "no module 'W/controler'"):
        agent(controller="W/controler")
    # without a system to ask (a harness of its own), it cannot tell: it sets up
    harness = ModuleHarness(PerformanceAgent, state={
        "controller": "W/controler", "controllers": CONTROLLERS, "running": "gap_out"})
    assert harness.state["controller"] == "W/controler"


@pytest.mark.timeout(60)
def test_in_a_system_a_controller_that_is_no_module_fails_the_launch_naming_it() -> None:
    """Asked from setup, the system answers (ModuleNotFound, from its worker): before, every
    measure failed ('no module') for as long as it ran."""
    from agents.traffic.gap_out import GapOut

    system = System("junction")
    system.add("controller", GapOut)
    system.add("agent", PerformanceAgent, state={
        "controller": "controler", "controllers": CONTROLLERS, "running": "gap_out"})
    with pytest.raises(RuntimeFailure, match="performance agent: controller: "
                       "no module 'controler' in system 'junction'; modules: controller"):
        system.launch().close()
    system = System("junction")
    system.add("controller", GapOut)
    system.add("agent", PerformanceAgent, state={
        "controller": "controller", "controllers": CONTROLLERS, "running": "gap_out"})
    with system.launch() as running:
        assert running.state("agent")["controller"] == "controller"


NETWORKS = Path(__file__).resolve().parent.parent / "scenarios" / "traffic"


@pytest.mark.timeout(120)
def test_in_a_system_its_swap_is_an_event_and_answers_from_the_next_step(
        tmp_path: Path) -> None:
    """The crossing with the scenario's junction macro; the agent's rules say a
    max-pressure whose setup takes 0.3 s once the queue is over one vehicle: it swaps,
    mid-run, the swap is a system event, and, the agent being in the driver's lock-step
    (its ``done``), the new controller's first reading is of the step after the measure
    that called for it. Before, SUMO ran on while the swap was made, as many steps as
    the machine's load allowed (so the grid's figures moved with the load)."""
    pytest.importorskip("libsumo", reason="SUMO (the traffic extra) is not installed")
    from scenarios import traffic

    resource = NETWORKS / "cross.toml"
    slow = {"class": "sample_modules:SlowToSwapIn", "state": {"hold_s": 10.0}}
    system = traffic.configuration(
        resource, seed=2, duration_s=900.0, found=traffic.layouts(resource, tmp_path),
        cache=tmp_path, agent_state={
            "controllers": {**traffic.controllers(), "slow": slow},
            "rules": [{"use": "gap_out"}, {"use": "slow", "queue_at_least": 1.0}],
            "min_between_swaps_s": 1000.0})
    with system.launch() as running:
        result = eventually(lambda: running.state("sumo")["result"], timeout=60,
                            what="the 900 s run to end")
        swaps = running.state("C/agent")["swaps"]
        first_step = running.state("C/controller")["first_step"]
        events = [e for e in running.events(since=0, timeout=1.0)
                  if e.kind == "module_swapped"]
    assert [s["to"] for s in swaps] == ["slow"] and 60 <= swaps[0]["time"] < 300
    assert [(e.subject, e.detail["cls"]) for e in events] == [
        ("C/controller", "sample_modules:SlowToSwapIn")]
    assert first_step == swaps[0]["time"] + 1            # (a control step is 1 s)
    assert result["rejected"] == 0 and result["late"] == 0 and result["teleports"] == 0


@pytest.mark.timeout(60)
def test_a_junction_the_file_names_keeps_its_own_settings(tmp_path: Path,
                                                         monkeypatch) -> None:
    pytest.importorskip("libsumo", reason="SUMO (the traffic extra) is not installed")
    from scenarios import traffic

    own = tmp_path / "traffic.toml"
    own.write_text(traffic.CONFIG.read_text() + '\n[modules.C]\nmacro = "junction"\n'
                   'state = { controller = { max_green_s = 60.0 }, '
                   'agent = { min_between_swaps_s = 300.0 } }\n')
    monkeypatch.setattr(traffic, "CONFIG", own)
    resource = NETWORKS / "cross.toml"
    system = traffic.configuration(resource, 1, 60.0, traffic.layouts(resource, tmp_path),
                                   tmp_path)
    with system.launch() as running:
        controller, agent = running.state("C/controller"), running.state("C/agent")
    assert controller["max_green_s"] == 60.0
    assert agent["min_between_swaps_s"] == 300.0 and agent["controller"] == "C/controller"
    # and given again when its agent swaps back to it (40 s came back: the file's)
    assert agent["controllers"]["gap_out"]["state"]["max_green_s"] == 60.0
    assert agent["controllers"]["time_loss"] == traffic.controllers()["time_loss"]
    # the junction's controller and the agent's running one are the same, or named
    own.write_text(traffic.CONFIG.read_text().replace(
        'passage_s = 4.0, switch_ratio = 0.0 }\n\n[macros.junction.modules.agent]',
        'passage_s = 3.0, switch_ratio = 0.0 }\n\n[macros.junction.modules.agent]'))
    with pytest.raises(ValueError, match=r"the junction's controller .* is not the agent's "
                                         r"running one, gap_out"):
        traffic.configuration(resource, 1, 60.0, traffic.layouts(resource, tmp_path), tmp_path)
