"""``PerformanceAgent``: one per junction, it measures the junction's demand and delay
and swaps its controller for the one its rules give, with guard rails.

It reads the junction's sensors (``measures``) and the driver's simulated ``clock``.
Over the last ``window_s`` simulated seconds it measures demand (vehicles arriving
per minute) and delay (vehicles halting, on average: vehicle-seconds of waiting per
second). ``rules`` map them to a controller: the last rule whose ``demand_at_least``
and ``queue_at_least`` both hold names the controller (a key of ``controllers``,
each a class and the state it is given when swapped in). The rule of the controller
chosen holds down to ``1 - hysteresis`` of its thresholds, so a measure that wobbles
about a threshold does not swap back and forth: in a saturated junction fewer
vehicles get in, and the demand it measures falls while the surge lasts.

Guard rails:

- at least ``min_between_swaps_s`` simulated seconds between two swaps by the rules,
  also across a re-pointed driver's new run (its clock from 0), whose measures make a
  window of their own;
- when the detectors fail (an implausible measure, or none for ``silent_after_s``
  of the driver's clock, each of its clocks having waited ``silent_wall_s`` of wall
  time for its measure: measures come through the sensors, the clock straight from
  the driver, and their lag is no failure), it swaps to ``fallback`` (fixed time, which
  needs no detector) at once, and leaves it only after a whole window of plausible
  measures.

In lock-step (``done`` linked to the driver's ``done_i``) it says on ``done`` the
simulated time of each measure it has dealt with, a swap it called for made: the
driver waits for it, so the swap runs from the next step on, however loaded the
machine. It does not hold the simulation for measures that do not come: a clock
that has waited ``silent_wall_s`` for its measure (at once while its detectors are
failed) is said done too. Each clock waits anew: once one had waited, every later
clock was said done at once, so a stall of half a second on the measures' way let
the driver run ``silent_after_s`` ahead of them, out of lock-step, and brought the
fallback in for a lag.

A controller's table or weights (state ``table``) is kept (``kept``, the agent's
state: it moves with the agent) when it is swapped out and given back when it is
swapped in again, so a learner does not forget. Each swap is a
``module_swapped`` event of the system, and a record on ``swapped`` and in ``swaps``.
"""

from __future__ import annotations

import copy
import time
from collections import deque
from typing import Any

from agents.limits import (
    RATIO,
    SECONDS,
    SHARE,
    SPAN,
    Limit,
    finite,
    missing_modules,
    out_of_limits,
    refuse_own_state,
)
from agents.traffic.messages import JunctionMeasures
from pb3a import Agent, Input, InputPort, Module, Output
from pb3a.config import checks
from pb3a.errors import RuntimeCancelled
from pb3a.loading.references import class_ref, resolve_class

KEPT_STATE = ("table",)             # a controller's learnt state, kept across swaps
RULE_THRESHOLDS = ("demand_at_least", "queue_at_least")
RULE_KEYS = ("use", *RULE_THRESHOLDS)
CONTROLLER_KEYS = ("class", "state")
_LIMITS: dict[str, Limit] = {
    "window_s": SPAN, "min_between_swaps_s": SECONDS, "silent_after_s": SPAN,
    "silent_wall_s": SECONDS, "hysteresis": SHARE}


# the settings that name controllers: each one of ``controllers`` (judged when the state
# gives them all)
_NAMING = ("controllers", "rules", "running", "chosen", "fallback")


def _settings_problems(state: dict[str, Any]) -> list[str]:
    """What a ``PerformanceAgent`` could not go by of ``state``, each problem naming the
    setting (see the class's docstring)."""
    problems = out_of_limits(_LIMITS, state)
    if "controller" in state and (not isinstance(state["controller"], str)
                                  or checks.path(state["controller"], "module")):
        problems.append(f"controller must be the controller's module name (e.g. "
                        f"'W/controller'), got {state['controller']!r}")
    controllers, rules = state.get("controllers", {}), state.get("rules", [])
    if "controllers" in state and not isinstance(controllers, dict):
        problems.append(f"controllers must be a table of name = {{ class, state }}, "
                        f"got {controllers!r}")
    elif "controllers" in state:
        for name, spec in controllers.items():
            problems += _controller_problems(name, spec)
    if "rules" in state and not isinstance(rules, list):
        problems.append(f"rules must be a list of {{ use, demand_at_least, queue_at_least }}"
                        f", got {rules!r}")
    elif "rules" in state:
        for index, rule in enumerate(rules):
            problems += _rule_problems(index, rule)
    problems += _kept_problems(state)
    if not problems and set(_NAMING) <= set(state):
        unknown = {state["running"], state["chosen"] or state["running"], state["fallback"],
                   *(r["use"] for r in rules)} - set(controllers)
        if unknown:
            problems.append(f"no controller {', '.join(sorted(map(str, unknown)))} in "
                            f"controllers ({', '.join(sorted(controllers)) or 'none'})")
    return problems


def _kept_problems(state: dict[str, Any]) -> list[str]:
    """What is wrong with what the agent keeps of its own (it moves with it, and may be
    set in the State Editor): the time of its last swap, its record, its judgement of
    the detectors, the learnt state it keeps."""
    problems = []
    if "last_swap_s" in state and not finite(state["last_swap_s"]):
        problems.append(f"last_swap_s must be a number (simulated seconds), got "
                        f"{state['last_swap_s']!r}")
    if "swaps" in state and not isinstance(state["swaps"], list):
        problems.append(f"swaps must be a list of the swaps' records, got {state['swaps']!r}")
    if "detectors_ok" in state and not isinstance(state["detectors_ok"], bool):
        problems.append(f"detectors_ok must be true or false, got {state['detectors_ok']!r}")
    kept = state.get("kept", {})
    if not (isinstance(kept, dict) and all(isinstance(v, dict) for v in kept.values())):
        problems.append(f"kept must be a table of controller name = {{ its learnt state }}, "
                        f"got {kept!r:.80}")
    return problems


def _who(controller: Any) -> str:
    """The agent, as its errors name it: by the controller it swaps, if it has one."""
    return f"{controller}'s performance agent" if controller and isinstance(
        controller, str) else "PerformanceAgent"


def _controller_problems(name: str, spec: Any) -> list[str]:
    """What keeps ``controllers[name]`` from being swapped in: not a table, a key other
    than class and state, a class that does not resolve to a module, a state the class
    refuses (set on a fresh instance, as the system sets a module's configured state)."""
    where = f"controllers.{name}"
    problems = _table_problems(where, spec, CONTROLLER_KEYS,
                               "{ class = 'package.module:Class', state = { ... } }")
    if not isinstance(spec, dict):
        return problems
    if "class" not in spec:
        return [*problems, f"{where} has no class ('package.module:Class')"]
    try:
        cls = resolve_class(spec["class"])
    except (ValueError, ImportError, LookupError, TypeError) as exc:
        return [*problems, f"{where}.class: {exc}"]
    if not issubclass(cls, Module):
        return [*problems, f"{where}.class: {class_ref(cls)} is not a pb3a.Module"]
    given = spec.get("state", {})
    wrong = checks.state(cls, given)
    if not wrong:
        try:
            cls().set_state(copy.deepcopy(given))
        except Exception as exc:  # the class's own check: whatever it raises, it refuses
            wrong = [f"{cls.__name__} refuses it: {type(exc).__name__}: {exc}"]
    return [*problems, *(f"{where}.state: {problem}" for problem in wrong)]


def _table_problems(where: str, value: Any, keys: tuple[str, ...], shape: str) -> list[str]:
    """``value`` (at ``where``) not a table of ``shape``, or its keys not among ``keys``."""
    if not isinstance(value, dict):
        return [f"{where} must be a table {shape}, got {value!r}"]
    return [f"{where}: {problem}" for problem in checks.unknown_keys(
        {key: None for key in value if key not in keys}, keys)]


def _rule_problems(index: int, rule: Any) -> list[str]:
    """What is wrong with ``rules[index]``: not a table, no ``use``, a key it does not
    know (a misspelt threshold was taken as 0: the rule always held), a threshold that
    is not a finite number, 0 or more (NaN never held)."""
    where = f"rules[{index}]"
    problems = _table_problems(where, rule, RULE_KEYS,
                               "{ use, demand_at_least, queue_at_least }")
    if not isinstance(rule, dict):
        return problems
    if not isinstance(rule.get("use"), str):
        problems.append(f"{where} needs 'use', the name of a controller, got "
                        f"{rule.get('use')!r}")
    words, ok = RATIO
    problems += [f"{where}.{key} must be {words}, got {rule[key]!r}"
                 for key in RULE_THRESHOLDS if key in rule and not ok(rule[key])]
    return problems


def _own_defaults(ref: str, live: dict[str, Any], given: dict[str, Any]) -> dict[str, Any]:
    """The settings a controller of class ``ref`` swapped in for one whose state was
    ``live`` takes from its class: those both classes have (a swap carries them over:
    GapOut's ``max_green_s`` into QLearning) and ``given`` does not set. So it runs with
    the state its spec gives and its class's own for the rest, as it does alone, not
    with what the controller before it happened to have."""
    cls = resolve_class(ref)
    names = set(cls.state_names())
    return {key: copy.deepcopy(getattr(cls, key)) for key in live
            if key in names and key not in given}


class PerformanceAgent(Agent):
    """Swaps a junction's controller by measured demand and delay, with guard rails.

    A swap is two requests: the class, then the controller's state. ``running`` and the
    record follow the class, as soon as the system has swapped it: what ``running`` names
    is what the junction runs. A state the new controller refuses (or a request that
    fails) leaves it running with the state the swap carried over: its record says so
    (``state_error``), the error is raised once (the system logs it), and the agent does
    not swap again for it, so it neither loops nor keeps a learner's table under another
    controller's name. A swap the system refuses (a controller busy past the timeout, a
    class whose setup fails) changes nothing and raises; a swap to the fallback is
    tried again at the next look, one by the rules after ``min_between_swaps_s``.

    Its settings are checked by ``state_problems`` (so by ``pb3a check``, ``add``, the
    State Editor, a live ``set_state``, which then sets nothing, and at setup), each
    problem named: the times finite (``window_s`` and ``silent_after_s`` above 0,
    ``min_between_swaps_s`` and ``silent_wall_s`` 0 or more), ``hysteresis`` from 0 to
    1, ``controller`` a module name, each of ``controllers`` a class that resolves to a
    module with a ``state`` the class takes (tried on a fresh instance, as the system
    gives a module its configured state), each rule a table of ``use`` and thresholds
    (finite, 0 or more) with no other key, every controller it may run one of
    ``controllers``, and what it keeps of its own (moved with it, or set in the State
    Editor) of its kind: ``last_swap_s`` a number, ``swaps`` a list, ``detectors_ok``
    true or false, ``kept`` a table of tables. At setup it also asks
    the system whether ``controller`` is one of its modules (reads may be asked from
    setup); ``set_state`` cannot ask (whoever sets the state holds the system's
    configuration lock), nor can setup outside a launched system (a ``ModuleHarness``
    without a runtime), so a ``controller`` set later is checked only by its first swap.
    """

    measures = Input(JunctionMeasures, policy="queue:512")
    clock = Input(float, policy="latest")
    swapped = Output(dict)
    done = Output(float)            # the simulated time of the step it has dealt with

    controller = ""                 # the controller's instance name ("W/controller")
    controllers: dict[str, dict[str, Any]] = {}     # name -> {class, state}
    rules: list[dict[str, Any]] = []                # [{use, demand_at_least, queue_at_least}]
    running = ""                    # the controller's name (a key of controllers) now
    fallback = "fixed_time"         # the controller for failed detectors
    window_s = 60.0
    hysteresis = 0.0                # the chosen controller's rule holds down to
                                    # (1 - hysteresis) of its thresholds
    min_between_swaps_s = 120.0
    silent_after_s = 10.0           # simulated seconds without a measure ...
    silent_wall_s = 0.5             # ... each clock ahead of them this long in wall time
    period = 0.1                    # how often silence is checked, besides on the clock
    # read-outs
    demand_per_min = 0.0
    mean_queue = 0.0
    detectors_ok = True
    swaps: list[dict[str, Any]] = []
    last_swap_s = -1e9
    chosen = ""                     # the controller chosen ("": running's); the fallback
                                    # stands in for it while the detectors fail
    kept: dict[str, dict[str, Any]] = {}    # per controller swapped out, its learnt
                                    # state (KEPT_STATE: a learner's table), given back
                                    # when it is swapped in again; state, so it moves

    def setup(self) -> None:
        self.chosen = self.chosen or self.running
        refuse_own_state(self)
        missing = missing_modules(self, [("controller", self.controller)])
        if missing:
            raise ValueError(f"{self.controller}'s performance agent: {missing[0]}")
        self._window: deque[JunctionMeasures] = deque()
        self._last_measure_s: float | None = None   # (or the clock's start, for silence)
        self._measured_s: float | None = None       # the time of the last measure taken
        self._plausible_since: float | None = None
        self._clock_s: float | None = None
        self._behind_since: float | None = None     # wall time the clock went ahead of
                                                    # the measures, and which clock
        self._behind_clock: float | None = None
        self._done_s: float | None = None           # the time last said done
        self._wall = time.monotonic

    @classmethod
    def state_problems(cls, state: dict[str, Any]) -> list[str]:
        """What the agent could not go by (a time out of range, a rule key it does not
        know, a controller class that does not resolve or refuses its state, rules, a
        fallback or a running controller it has not got), each naming the setting.
        (Whether ``controller`` is a module of the system is asked at setup: see the
        class's docstring.)"""
        return super().state_problems(state) + [
            f"{cls.__name__}'s {problem}" for problem in _settings_problems(state)]

    def on_input(self, port: InputPort) -> None:
        if port.name == "clock":
            self._clock_s = port.read()
            if self._last_measure_s is None:    # none yet: silent since the clock began
                self._last_measure_s = self._clock_s
            self._check_silence()
            return
        failure: Exception | None = None
        for measure in port.read_all():         # every one taken, a swap failing or not
            try:
                self._take(measure)
            except Exception as exc:  # (a swap the system refused: said once, below)
                failure = failure or exc
            self._say_done(measure.time)
        if failure is not None:
            raise failure

    def step(self) -> None:
        self._check_silence()

    # -- measuring --------------------------------------------------------------------
    def _take(self, measure: JunctionMeasures) -> None:
        last = self._measured_s
        if last is not None and measure.time < last:
            # the driver was re-pointed (a new run, its clock from 0): the window starts
            # afresh, and the time since the last swap carries over to the new clock
            self.last_swap_s = measure.time - (last - self.last_swap_s)
            self._window.clear()
            self._plausible_since = None
        self._measured_s = measure.time
        self._last_measure_s, self._behind_since = measure.time, None
        if not measure.plausible:
            self._plausible_since = None
            self._window.clear()
            self._fail(measure.time, "implausible detector values")
            return
        if self._plausible_since is None:
            self._plausible_since = measure.time
        self._window.append(measure)
        while self._window and self._window[0].time <= measure.time - self.window_s:
            self._window.popleft()
        # (a measure's arrivals came since the one before it, so a whole window of 60
        # measures a second apart holds 60 s of arrivals, divided here by the 59 s from
        # its first to its last: 60/59 of what came. Left so: the scenario's grid rules
        # were set and measured with it, and counting 60 s would let a junction at 29
        # vehicles a minute late in the grid's surge, at its hysteresis bound of 29.25,
        # swap back; see docs/applications.md, the scenario's goals.)
        span = max(measure.time - self._window[0].time, 1.0)
        self.demand_per_min = 60.0 * sum(m.arrivals for m in self._window) / span
        self.mean_queue = sum(m.queue for m in self._window) / len(self._window)
        if measure.time - self._plausible_since < self.window_s:
            return                                  # not a whole window to judge by yet
        if not self.detectors_ok:
            self.detectors_ok = True
            if self.running != self.chosen:         # the fallback stands in for the
                self.last_swap_s = -1e9             # rules' choice: the way back is not
                                                    # held up (when the rules chose it,
                                                    # no swap was made: their time holds)
        wanted = self.choice()
        if wanted != self.running and measure.time - self.last_swap_s >= self.min_between_swaps_s:
            self._swap(wanted, measure.time, f"demand {self.demand_per_min:.1f}/min, "
                                             f"queue {self.mean_queue:.1f}", chosen=True)

    def choice(self) -> str:
        """The controller the rules give for the demand and queue measured now (when
        none holds, the one chosen before, not a fallback standing in for it)."""
        chosen = self.chosen
        for rule in self.rules:
            keep = 1.0 - self.hysteresis if rule["use"] == self.chosen else 1.0
            if (self.demand_per_min >= keep * rule.get("demand_at_least", 0.0)
                    and self.mean_queue >= keep * rule.get("queue_at_least", 0.0)):
                chosen = rule["use"]
        return chosen

    def _check_silence(self) -> None:
        now, last = self._clock_s, self._last_measure_s
        if now is not None and last is not None and last > now:
            # a measure ahead of the clock is of a run that ended (the driver was
            # re-pointed, its clock from 0): silence counts from the new clock
            self._last_measure_s = last = now
            self._behind_since = None
        if now is None or last is None or now <= last:
            return
        if self._behind_since is None or now != self._behind_clock:
            self._behind_since, self._behind_clock = self._wall(), now
        waited = self._wall() - self._behind_since >= self.silent_wall_s
        try:
            if waited and now - last > self.silent_after_s and self.detectors_ok:
                self._plausible_since = None
                self._window.clear()
                self._fail(now, f"no detector reading for {now - last:.0f} s")
        finally:            # (a fallback swap refused is tried again, not waited for)
            if waited or not self.detectors_ok:
                self._say_done(now)     # measures this late may never come

    def _say_done(self, time_s: float) -> None:
        """Say on ``done`` that the step of ``time_s`` is dealt with (once)."""
        if time_s != self._done_s:
            self._done_s = time_s
            self.done.write(time_s)

    def _fail(self, now: float, why: str) -> None:
        try:
            if self.running != self.fallback:
                self._swap(self.fallback, now, f"detectors failed: {why}")
        finally:
            # only once swapped: a swap that failed is tried again at the next look (a
            # swap made whose state could not be set is made: it is not tried again)
            if self.running == self.fallback:
                self.detectors_ok = False

    # -- swapping ---------------------------------------------------------------------
    def _swap(self, name: str, now: float, reason: str, *, chosen: bool = False) -> None:
        """Swap the controller for ``name`` (``chosen``: the rules' choice, not the
        fallback) and give it its state; recorded as soon as the class is swapped. A
        state that cannot be set is in the record (``state_error``) and raised once."""
        leaving = self.running
        spec = self.controllers[name]
        try:
            # (its state read first, in the same try: a controller whose state could
            # not be read was asked again at every measure, past min_between_swaps_s)
            live = self.runtime.state(self.controller)
            self.runtime.swap(self.controller, spec["class"])
        except RuntimeCancelled:
            raise           # the agent is stopping: not a swap refused
        except Exception:   # nothing has changed; the rules' swap is tried again after
            if chosen:      # min_between_swaps_s, not at every measure (a class whose
                self.last_swap_s = now      # setup fails failed each second), the
            raise                           # fallback's at the next look
        # From here the junction runs the new class: so says the record, whatever comes.
        self.kept = {**self.kept, leaving: {k: live[k] for k in KEPT_STATE if k in live}}
        self.running, self.last_swap_s = name, now
        if chosen:
            self.chosen = name
        record = {"time": now, "controller": self.controller, "from": leaving, "to": name,
                  "reason": reason}
        failure: Exception | None = None
        try:
            given = spec.get("state", {})
            self.runtime.set_state(self.controller, {**_own_defaults(spec["class"], live, given),
                                                     **given, **self.kept.get(name, {})})
        except Exception as exc:  # whatever it is, the swap was made: record it first
            failure = exc
            record["state_error"] = f"{type(exc).__name__}: {exc}"
        self.swaps = [*self.swaps, record]
        self.swapped.write(record)
        if isinstance(failure, RuntimeCancelled):
            raise failure       # the agent is stopping (the system stops, say): said quietly
        if failure is not None:
            raise RuntimeError(
                f"{self.controller}'s performance agent swapped it from {leaving} to "
                f"{name} ({spec['class']}), but could not set its state: "
                f"{record['state_error']}; it runs on with the state the swap carried over "
                f"(the agent does not try again)") from failure
