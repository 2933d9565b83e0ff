"""``RemedyAgent``: what to do about a hardware failure, chosen by case-based reasoning.

A failure (from a hardware monitor) is turned into features; the most similar cases of
the case base (``agents/cases.toml`` and the user's own file) are adapted to the
running system in turn, and the first that makes sense there is carried out: move the
control macro to the standby robot's node and point its driver at that robot, swap
the failed sensor's consumer for a class that does without it, or stop the robot.
When nothing fits, or a remedy fails, the robot is stopped. Each outcome is judged
after a while and retained in the user's case file, so the base learns.

The pure part (``situation_of``, ``SystemView``, ``check_remedy``, ``plan``) knows
nothing of PB3A's runtime; ``RemedyAgent`` carries the plan out and watches it.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import numbers
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from agents.case_base import AdaptationError, CaseBase, CaseFileError, Feature, Match, adapt
from agents.limits import Limit, finite, missing_modules, out_of_limits, refuse_own_state
from pb3a import Agent, Input, InputPort, Output
from pb3a.errors import ModuleNotFound, PB3AError
from pb3a.model.module import reflective

if TYPE_CHECKING:
    from pb3a.stats import SystemStats

SHIPPED_CASES = Path(__file__).with_name("cases.toml")
ACTIONS = ("move_macro", "swap", "stop", "carry_on")
HISTORY_KEPT = 200                    # remedies remembered in ``history``
_HISTORY_KEYS = ("failure", "remedy", "case", "similarity", "reason", "started", "ended",
                 "judged", "worked", "outcome")
_CLASS_REF = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_][\w.]*$")
log = logging.getLogger("agents.remedy")


def situation_of(failure: dict[str, Any], *, standby: bool,
                 consumed: bool = True) -> dict[str, Feature]:
    """The features of ``failure`` (a monitor's ``{"fault", "probability", "at",
    "detail"}``): its fault, probability, how many sensors failed, whether a standby
    robot is at hand, whether a module of the system reads the failed sensor
    (``consumed``), and the detail's own numbers (finite ones, as plain Python numbers,
    numpy's too), strings and booleans.

    How many sensors failed is the detail's ``failed_sensors`` if it says, else the
    length of its longest list: a detail's lists run side by side, an entry per failed
    sensor (the sonar monitor's ``sonars`` and ``silent_sweep``), so they are not added
    up (3 dead transducers were counted as 6, and a case for many taken)."""
    detail = failure.get("detail") or {}
    features: dict[str, Feature] = {}
    for name, value in detail.items():
        if isinstance(value, (str, bool)):
            features[name] = value
        elif isinstance(value, numbers.Integral):
            features[name] = int(value)
        elif isinstance(value, numbers.Real) and math.isfinite(value):
            features[name] = float(value)
    lists = [len(value) for value in detail.values() if isinstance(value, (list, tuple))]
    features.update(
        fault=str(failure.get("fault", "unknown")),
        probability=float(failure.get("probability", 1.0)),
        failed_sensors=features.get("failed_sensors", max(lists, default=0)),
        standby=standby, consumed=consumed)
    return features


@dataclass(frozen=True)
class SystemView:
    """What the checks of a remedy need to know of the running system."""

    classes: dict[str, str]          # module -> "package.module:Class"
    nodes: dict[str, str]            # module -> the node it runs on
    up: frozenset[str]               # the nodes that are up
    known: frozenset[str] = frozenset()   # every node of the system, up or not

    @classmethod
    def of(cls, stats: SystemStats) -> SystemView:
        """The view of a system's figures (``runtime.stats()``)."""
        return cls({name: module.cls for name, module in stats.modules.items()},
                   {name: module.node for name, module in stats.modules.items()},
                   frozenset(name for name, node in stats.nodes.items() if node.up),
                   frozenset(stats.nodes))


def check_remedy(remedy: dict[str, Any], view: SystemView) -> None:
    """AdaptationError unless ``remedy`` makes sense in the system ``view`` shows."""
    action = remedy.get("action")
    if action == "move_macro":
        macro, to, driver = remedy.get("macro", ""), remedy.get("to", ""), remedy.get("driver")
        if not any(name.startswith(f"{macro}/") for name in view.nodes):
            raise AdaptationError(f"no macro {macro!r} runs")
        if driver not in view.nodes:
            raise AdaptationError(f"no driver {driver!r} runs")
        if to not in view.up:
            raise AdaptationError(f"node {to!r} is not up")
        if view.nodes[driver] == to:
            raise AdaptationError(f"{macro!r} already runs on {to!r}")
        if not remedy.get("resource"):
            raise AdaptationError("no robot server to point the driver at")
    elif action == "swap":
        module, cls = remedy.get("module"), remedy.get("cls", "")
        if module not in view.classes:
            raise AdaptationError(f"no module {module!r} runs")
        if not isinstance(cls, str) or not _CLASS_REF.match(cls):
            raise AdaptationError(f"{cls!r} is not a class reference 'package.module:Class'")
        if view.classes[module] == cls:
            raise AdaptationError(f"{module!r} already is a {cls}")
    elif action == "stop":
        if remedy.get("driver") not in view.nodes:
            raise AdaptationError(f"no driver {remedy.get('driver')!r} runs")
    elif action != "carry_on":           # (carry_on changes nothing: always sensible)
        raise AdaptationError(f"unknown action {action!r}; actions: {', '.join(ACTIONS)}")


@dataclass(frozen=True)
class Plan:
    """The remedy chosen, the case it came from ("" for the fallback stop) and why."""

    remedy: dict[str, Any]
    case: str
    similarity: float
    reason: str


def plan(base: CaseBase, situation: dict[str, Feature], placeholders: dict[str, Any],
         view: SystemView) -> Plan:
    """The remedy of the most similar case that adapts to ``placeholders`` and passes
    ``check_remedy``; else stopping the robot (``placeholders["driver"]``). Carrying on
    is refused when a module reads the failed sensor (``consumed``): a case for an
    unread sensor may still be similar enough when the case made for it cannot be
    adapted (no fallback class), and would carry on with a module reading bad data."""
    refused = []
    for match in base.retrieve(situation):
        try:
            remedy = adapt(match.case.remedy, placeholders)
            check_remedy(remedy, view)
            if remedy.get("action") == "carry_on" and situation.get("consumed"):
                raise AdaptationError("a module reads the failed sensor: cannot carry on")
        except AdaptationError as exc:
            refused.append(f"case {match.case.id!r}: {exc}")
            continue
        return Plan(remedy, match.case.id, match.similarity, "; ".join(refused))
    why = "; ".join(refused) or f"no case is {base.setting('min_similarity'):.0%} similar"
    return Plan({"action": "stop", "driver": placeholders["driver"]}, "", 0.0, why)


def check_actions(base: CaseBase) -> None:
    """CaseFileError, naming its file and case, for a remedy the agent cannot carry out."""
    for case in base.cases:
        if case.remedy["action"] not in ACTIONS:
            raise CaseFileError(f"{case.source}: case {case.id!r}: unknown action "
                                f"{case.remedy['action']!r}; actions: {', '.join(ACTIONS)}")


_ALWAYS_CONSUMED = ("motors", "robot_link")   # faults the whole robot's work depends on
_LIMITS: dict[str, Limit] = {
    "settle_s": ("a finite number of seconds, 0 or more", lambda v: finite(v) and v >= 0),
    "verify_s": ("a finite number of seconds, 0 or more", lambda v: finite(v) and v >= 0),
    "move_timeout_s": ("a finite number of seconds, above 0", lambda v: finite(v) and v > 0),
}


# what a remedy sets on a driver, and why (a driver of one's own must have them)
_SETS = {"enabled": "False, to stop the robot",
         "resource": "the standby robot's address, as the driver arrives there"}
_NAMES = ("macro", "driver", "standby_node", "standby_resource", "watch", "cases_path")


def _shape_problems(state: dict[str, Any]) -> list[str]:
    """What in ``state`` is not of the kind the agent reads: names and addresses are
    text, ``consumers`` and ``fallbacks`` map a sensor to a module or to a class (a list
    of consumers was taken, and the first failure raised inside the agent: no remedy,
    not even the stop)."""
    problems = [f"{key} must be text, got {state[key]!r}" for key in _NAMES
                if key in state and not isinstance(state[key], str)]
    for key, what in (("consumers", "the module that reads it"),
                      ("fallbacks", "a class doing without it, 'package.module:Class'")):
        if key not in state:
            continue
        value = state[key]
        if not isinstance(value, dict) or not all(
                isinstance(k, str) and isinstance(v, str) for k, v in value.items()):
            problems.append(f"{key} must map each sensor (a fault's kind) to {what}, "
                            f"as {{\"sonar\": ...}}, got {value!r}")
        elif key == "fallbacks":
            problems += [f"fallbacks[{sensor!r}] = {ref!r} is not 'package.module:Class'"
                         for sensor, ref in value.items() if not _CLASS_REF.match(ref)]
    return problems


def _settings_problems(state: dict[str, Any]) -> list[str]:
    """What of ``state`` a ``RemedyAgent`` could not carry out, each naming the setting:
    no ``driver``, settings of the wrong kind or out of range (a NaN verify_s never
    judged a remedy, and every later failure waited for good), a ``case_base`` given
    that does not fit or has a case's unknown action."""
    problems = _shape_problems(state) + out_of_limits(_LIMITS, state)
    if state.get("driver", "control/driver") == "":
        problems.append("driver must name the RobotDriver to stop or re-point (e.g. "
                        "'control/driver'), got ''")
    if not problems and state.get("case_base"):
        try:
            check_actions(CaseBase.from_dict(state["case_base"]))
        except CaseFileError as exc:     # (it names the case, and the file it came from)
            said = str(exc)
            problems.append(said if said.startswith("case_base") else f"case_base: {said}")
    return problems


def _case_base(state: dict[str, Any]) -> CaseBase:
    """The case base a ``RemedyAgent`` of ``state`` (refused of nothing) goes by: its
    ``case_base``, or ({}) the shipped cases and the user's file. ``CaseFileError``,
    naming its file and case, for a case file it cannot read or carry out."""
    if state["case_base"]:
        return CaseBase.from_dict(state["case_base"])
    path = state["cases_path"]
    base = CaseBase.load([SHIPPED_CASES, *([path] if Path(path).expanduser().exists()
                                           else [])])
    check_actions(base)
    return base


class RemedyAgent(Agent):
    """Failures in, one remedy per failure onset, its outcome judged and learned.

    A remedy runs through phases kept in ``action`` (state, so a moved or restored
    agent carries on): ``moving`` until the macro's move ends (the driver re-pointed
    as it arrives), ``verifying`` for ``verify_s`` seconds, then judged. It worked if the
    ``watch``ed module (the driver, or the swapped module) wrote outputs meanwhile and
    the fault did not come back later than ``settle_s`` after the action ended (earlier
    reports are echoes of the old robot). A failed remedy is followed by a stop. While
    a remedy runs, failures of its fault are not acted on and failures of other kinds
    wait in ``deferred``; once the robot is stopped (``stopped``) the agent acts no
    more until someone sets ``stopped`` back to False.
    """

    failure = Input(dict, policy="queue:64")     # {"fault", "probability", "at", "detail"}
    driver_failure = Input(dict, policy="queue:64")   # the same, from the RobotDriver
                                                      # (robot_link: its robot is silent)
    # {"event": "chosen" | "worked" | "failed", "at", "fault", "action", "remedy", "case"
    # ("" for the fallback stop), "similarity", "reason" (cases passed over), "outcome",
    # and for a move the agent saw end, "move": {"prepare_s", "pause_s", "phases",
    # "seen_done_s"} (its MigrationReport's, where the pause went, and when the agent saw
    # it done after choosing it)};
    # or {"event": "not_saved", "at", "reason"} when the case file cannot be written
    remedy = Output(dict)
    period = 0.2

    macro = "control"                     # the control system: the macro to move
    driver = "control/driver"             # its RobotDriver
    standby_node = ""                     # the standby robot's node ("" = none)
    standby_resource = ""                 # and its robot server's address
    consumers: dict[str, str] = {}        # sensor (fault kind) -> module that reads it
    fallbacks: dict[str, str] = {}        # sensor -> "package.module:Class" doing without
    watch = ""                            # module whose outputs show a move worked ("": driver)
    cases_path = "~/.pb3a/remedy-cases.toml"   # the user's case file: read, and learned into
    case_base: dict[str, Any] = {}        # the case base itself ({}: load it from the files)
    move_timeout_s = 60.0                 # a move not ended by then has failed
    settle_s = 2.0                        # s after an action in which its fault only echoes
    verify_s = 6.0                        # s after an action at which it is judged
    action: dict[str, Any] = {}           # the remedy under way ({}: none)
    deferred: list[dict[str, Any]] = []   # failures of other kinds that came meanwhile
    history: list[dict[str, Any]] = []    # every remedy and how it went, oldest first
    stopped = False

    def setup(self) -> None:
        refuse_own_state(self)
        self._use(_case_base(self.get_state()))
        self._check_modules()
        self._check_drivers()
        # A move's Pending cannot be pickled: a moved or restored agent has none, and
        # looks at where the driver runs instead.
        self._pending: Any = None

    def _check_modules(self) -> None:
        """ValueError naming each module the settings name that the system does not
        have (a misspelt driver was found only by the fallback stop, which failed: the
        robot drove on)."""
        problems = missing_modules(self, [
            ("driver", self.driver), ("watch", self.watch),
            *((f"consumers[{sensor!r}]", module) for sensor, module in self.consumers.items())])
        if problems:
            raise ValueError("RemedyAgent: " + "; ".join(problems))

    def _check_drivers(self) -> None:
        """ValueError naming each driver a remedy of this agent would act on that lacks
        the state the remedy sets: ``enabled`` for a stop (the fallback stop's driver
        always), ``resource`` for a move to the standby (when there is one). A user's
        own driver without ``enabled`` was taken: a failure calling for a stop left the
        robot driving, the stop only recorded as not having worked. Not checked when
        the runtime cannot be asked now: the remedy then tells."""
        needs: dict[str, dict[str, str]] = {self.driver: {"enabled": "the fallback stop"}}
        for case in self._base.cases:
            try:
                remedy = adapt(case.remedy, self._placeholders(
                    str(case.symptoms.get("fault", ""))))
            except AdaptationError:
                continue                  # (it can never be chosen here: nothing to check)
            field, what = {"stop": ("enabled", "the stop"),
                           "move_macro": ("resource", "the move to the standby")}.get(
                               remedy["action"], ("", ""))
            if field and isinstance(remedy.get("driver"), str):
                needs.setdefault(remedy["driver"], {}).setdefault(
                    field, f"{what} of case {case.id!r}")
        problems = []
        for driver, fields in needs.items():
            try:
                state = self.runtime.state(driver)
            except ModuleNotFound:
                continue                  # (_check_modules names the driver, or the case fails)
            except (PB3AError, RuntimeError, AttributeError):
                return
            problems += [f"driver {driver!r} has no state {field!r}, which {what} sets "
                         f"({_SETS[field]}); its state is: {', '.join(sorted(state))}"
                         for field, what in fields.items() if field not in state]
        if problems:
            raise ValueError("RemedyAgent: " + "; ".join(problems))

    def _placeholders(self, fault: str) -> dict[str, Any]:
        """What a case's remedy is adapted with for a failure of ``fault``."""
        return {"macro": self.macro, "driver": self.driver, "fault": fault,
                "standby_node": self.standby_node,
                "standby_resource": self.standby_resource,
                "consumer": self.consumers.get(fault, ""),
                "fallback": self.fallbacks.get(fault, "")}

    @classmethod
    def state_problems(cls, state: dict[str, Any]) -> list[str]:
        """What it could not carry out (``_settings_problems``), each naming the setting.
        (Case files are read at setup and by ``set_state``, on the machine it runs on.)"""
        return super().state_problems(state) + [
            f"{cls.__name__}'s {problem}" for problem in _settings_problems(state)]

    @reflective                 # (it takes the fields Module's does: they are checked)
    def set_state(self, state: dict[str, Any]) -> None:
        """Set state (what ``state_problems`` refuses is refused, nothing set); a running
        agent plans by a ``case_base`` set (or, set to {}, by the case files again) from
        its next failure, rather than by the base it made at setup, which it wrote back
        over the state as it learnt. A case file it cannot read or carry out is refused
        too (``CaseFileError``), and nothing is set."""
        with self._admitting(state) as state:  # (judged before the case files are read)
            base = _case_base({**self.get_state(), **state})
            super().set_state(state)
        if "_base" in vars(self):
            self._use(base)

    def _use(self, base: CaseBase) -> None:
        """Plan by ``base`` (and keep it in the state, if the state had none)."""
        self._base = base
        if not self.case_base:
            self.case_base = base.to_dict()

    def on_input(self, port: InputPort) -> None:
        self.step()            # a failure is acted on at once, not at the next period

    def step(self) -> None:
        now = time.time()      # wall time: it goes into state that may move between nodes
        for failure in [*self.failure.read_all(), *self.driver_failure.read_all()]:
            self._receive(failure, now)
        if self.action:
            self._advance(now)
        while not self.action and self.deferred and not self.stopped:
            self._receive(self.deferred.pop(0), now)

    # -- failures -----------------------------------------------------------------------
    def _receive(self, failure: dict[str, Any], now: float) -> None:
        fault, at = failure.get("fault"), failure.get("at", now)
        if self.stopped:
            return
        if self.action:
            current = self.action
            if fault == current["failure"].get("fault"):
                if current["ended"] is not None and at >= current["ended"] + self.settle_s:
                    current["recurred"] = True
            elif all(fault != waiting.get("fault") for waiting in self.deferred):
                self.deferred.append(failure)
            return
        if at > self._settled(fault):
            self._begin(failure, now)

    def _settled(self, fault: Any) -> float:
        """When the last remedy for ``fault`` was judged: reports up to then are about a
        failure already dealt with."""
        return max((entry["judged"] for entry in self.history
                    if entry["failure"].get("fault") == fault), default=float("-inf"))

    # -- choosing and carrying out a remedy -------------------------------------------
    def _begin(self, failure: dict[str, Any], now: float) -> None:
        fault = str(failure.get("fault", "unknown"))
        try:
            view = SystemView.of(self.runtime.stats())
        except PB3AError:
            view = SystemView({}, {}, frozenset())
        standby = (bool(self.standby_resource) and self.standby_node in view.up
                   and view.nodes.get(self.driver) != self.standby_node)
        situation = situation_of(failure, standby=standby,
                                 consumed=fault in self.consumers
                                 or fault in _ALWAYS_CONSUMED)
        chosen = plan(self._base, situation, self._placeholders(fault), view)
        if self.standby_node and view.known and self.standby_node not in view.known:
            # (a misspelt standby node made it stop the robot, saying nothing of why)
            missing = (f"standby_node {self.standby_node!r} is no node of the system "
                       f"(nodes: {', '.join(sorted(view.known))})")
            chosen = dataclasses.replace(chosen, reason="; ".join(
                filter(None, (missing, chosen.reason))))
        self._start(failure, situation, chosen, now)

    def _start(self, failure: dict[str, Any], situation: dict[str, Feature], chosen: Plan,
               now: float) -> None:
        remedy = chosen.remedy
        self.action = {"failure": failure, "situation": situation, "remedy": remedy,
                       "case": chosen.case, "similarity": chosen.similarity,
                       "reason": chosen.reason, "started": now, "ended": None,
                       "phase": "", "watch": "", "baseline": 0, "recurred": False}
        self._report("chosen", now)
        try:
            if remedy["action"] == "move_macro":
                self.action["phase"] = "moving"
                # The driver is re-pointed at the standby robot as it arrives on the
                # standby's node: the standby robot is never driven from the failing one,
                # and a move that fails leaves the driver as it was.
                self._pending = self.runtime.migrate(
                    remedy["macro"], remedy["to"], wait=False,
                    state={remedy["driver"]: {"resource": remedy["resource"]}})
            elif remedy["action"] == "swap":
                self.runtime.swap(remedy["module"], remedy["cls"])
                self._verify(remedy["module"], now)
            elif remedy["action"] == "carry_on":
                self._conclude(True, f"no module reads the {failure.get('fault')} sensor: "
                               "carried on", now)
            else:
                self.runtime.set_state(remedy["driver"], {"enabled": False})
                self.stopped, self.deferred = True, []
                enabled = self.runtime.state(remedy["driver"]).get("enabled")
                self._conclude(enabled is False, f"{remedy['driver']} has enabled = "
                               f"{enabled!r}", now)
        except PB3AError as exc:
            self._conclude(False, f"{remedy['action']} failed: {exc}", now)

    def _advance(self, now: float) -> None:
        action = self.action
        if action["phase"] == "moving":
            self._advance_move(now)
        elif action["recurred"]:
            self._conclude(False, f"the {action['failure'].get('fault')} fault came back",
                           now)
        elif now >= action["ended"] + self.verify_s:
            active = self._written(action["watch"]) > action["baseline"]
            self._conclude(active, f"{action['watch']} is at work" if active else
                           f"{action['watch']} wrote nothing in {self.verify_s:g} s", now)

    def _advance_move(self, now: float) -> None:
        remedy = self.action["remedy"]
        try:
            if self._pending is not None:
                if not self._pending.done():
                    moved = False
                else:
                    report = self._pending.result(0.0)     # raises if the move failed
                    moved = True
                    self.action["move"] = {
                        "prepare_s": round(report.prepare_s, 4),
                        "pause_s": round(report.pause_s, 4),
                        "phases": {name: round(value, 4) for name, value
                                   in dataclasses.asdict(report.phases).items()},
                        "seen_done_s": round(now - self.action["started"], 4)}
            else:
                moved = self.runtime.where(remedy["driver"]) == remedy["to"]
            if not moved:
                if now - self.action["started"] > self.move_timeout_s:
                    self._conclude(False, f"the move had not ended after "
                                   f"{self.move_timeout_s:g} s", now)
                return
        except PB3AError as exc:
            self._conclude(False, f"move_macro failed: {exc}", now)
            return
        self._pending = None
        self.standby_node = self.standby_resource = ""     # the standby is in use now
        self._verify(self.watch or remedy["driver"], now)

    def _verify(self, watch: str, now: float) -> None:
        self.action.update(phase="verifying", ended=now, watch=watch,
                           baseline=self._written(watch))

    def _written(self, module: str) -> int:
        """Values ``module`` has written, over all its outputs (0 if it cannot be told)."""
        try:
            stats = self.runtime.stats().modules.get(module)
        except PB3AError:
            return 0
        return sum(stats.outputs.values()) if stats is not None else 0

    # -- judging, learning ------------------------------------------------------------
    def _conclude(self, worked: bool, outcome: str, now: float) -> None:
        action, self.action, self._pending = self.action, {}, None
        action.update(judged=now, worked=worked, outcome=outcome)
        self.history = [*self.history, {key: action[key] for key in _HISTORY_KEYS}]
        self.history = self.history[-HISTORY_KEPT:]
        self._report("worked" if worked else "failed", now, action)
        if not worked:      # (a stop that failed was only recorded: the robot drove on)
            log.error("RemedyAgent: %s for the %s failure did not work: %s",
                      action["remedy"]["action"], action["failure"].get("fault"), outcome)
        if action["remedy"]["action"] == "move_macro" and action["ended"] is not None:
            # failures reported before the move ended were about the robot left behind
            self.deferred = [f for f in self.deferred if f.get("at", now) >= action["ended"]]
        if not worked and action["remedy"]["action"] != "stop":
            self._start(action["failure"], action["situation"],
                        Plan({"action": "stop", "driver": self.driver}, "", 0.0,
                             f"case {action['case']!r} failed: {outcome}"), now)
        if action["case"]:          # (after the stop: nothing learnt may hold it up)
            self._retain(action, worked, now)

    def _retain(self, action: dict[str, Any], worked: bool, now: float) -> None:
        match = Match(self._base.case(action["case"]), action["similarity"])
        self._base.retain(match, action["situation"], worked, self.cases_path)
        self.case_base = self._base.to_dict()
        try:
            self._base.save(self.cases_path)
        except OSError as exc:
            self.remedy.write({"event": "not_saved", "at": now,
                               "reason": f"{self.cases_path}: {exc}"})

    def _report(self, event: str, now: float, action: dict[str, Any] | None = None) -> None:
        """Write on ``remedy`` what was chosen (``event`` "chosen") or how it went."""
        action = action or self.action
        self.remedy.write({"event": event, "at": now, "fault": action["failure"].get("fault"),
                           "action": action["remedy"]["action"], "remedy": action["remedy"],
                           "case": action["case"], "similarity": action["similarity"],
                           "reason": action["reason"], "outcome": action.get("outcome", ""),
                           **({"move": action["move"]} if "move" in action else {})})
