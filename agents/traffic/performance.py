"""``PerformanceAgent``: one per junction, it measures the junction's demand and delay
and swaps its controller for the one its rules give, with guard rails.

It reads the junction's sensors (``measures``) and the driver's simulated ``clock``.
Over the last ``window_s`` simulated seconds it measures demand (vehicles arriving
per minute) and delay (vehicles halting, on average: vehicle-seconds of waiting per
second). ``rules`` map them to a controller: the last rule whose ``demand_at_least``
and ``queue_at_least`` both hold names the controller (a key of ``controllers``,
each a class and the state it is given when swapped in).

Guard rails:

- at least ``min_between_swaps_s`` simulated seconds between two swaps by the rules,
  also across a re-pointed driver's new run (its clock from 0), whose measures make a
  window of their own;
- when the detectors fail (an implausible measure, or none for ``silent_after_s``
  of the driver's clock and ``silent_wall_s`` of wall time: a lock-step run goes
  faster than the messages between modules, and their lag is no failure), it swaps
  to ``fallback`` (fixed time, which needs no detector) at once, and leaves it only
  after a whole window of plausible measures.

A controller's table or weights (state ``table``) is kept when it is swapped out and
given back when it is swapped in again, so a learner does not forget. Each swap is a
``module_swapped`` event of the system, and a record on ``swapped`` and in ``swaps``.
"""

from __future__ import annotations

import time
from collections import deque
from typing import Any

from agents.traffic.messages import JunctionMeasures
from pb3a import Agent, Input, InputPort, Output

KEPT_STATE = ("table",)             # a controller's learnt state, kept across swaps


def _check_controllers(state: dict[str, Any]) -> None:
    """ValueError naming each controller a ``PerformanceAgent`` of ``state`` is told to
    run (``running``, ``chosen``, ``fallback``, a rule's ``use``) that is not in its
    ``controllers``."""
    unknown = {state["running"], state["chosen"] or state["running"], state["fallback"],
               *(r["use"] for r in state["rules"])} - set(state["controllers"])
    if unknown:
        raise ValueError(f"{state['controller']}'s performance agent: no controller "
                         f"{', '.join(sorted(unknown))} in controllers "
                         f"({', '.join(sorted(state['controllers'])) or 'none'})")


class PerformanceAgent(Agent):
    """Swaps a junction's controller by measured demand and delay, with guard rails."""

    measures = Input(JunctionMeasures, policy="queue:512")
    clock = Input(float, policy="latest")
    swapped = Output(dict)

    controller = ""                 # the controller's instance name ("W/controller")
    controllers: dict[str, dict[str, Any]] = {}     # name -> {class, state}
    rules: list[dict[str, Any]] = []                # [{use, demand_at_least, queue_at_least}]
    running = ""                    # the controller's name (a key of controllers) now
    fallback = "fixed_time"         # the controller for failed detectors
    window_s = 60.0
    min_between_swaps_s = 120.0
    silent_after_s = 10.0           # simulated seconds without a measure ...
    silent_wall_s = 0.5             # ... for at least this long in wall time
    period = 0.1                    # how often silence is checked, besides on the clock
    # read-outs
    demand_per_min = 0.0
    mean_queue = 0.0
    detectors_ok = True
    swaps: list[dict[str, Any]] = []
    last_swap_s = -1e9
    chosen = ""                     # the controller chosen ("": running's); the fallback
                                    # stands in for it while the detectors fail

    def setup(self) -> None:
        self.chosen = self.chosen or self.running
        _check_controllers(self.get_state())
        self._window: deque[JunctionMeasures] = deque()
        self._last_measure_s: float | None = None   # (or the clock's start, for silence)
        self._measured_s: float | None = None       # the time of the last measure taken
        self._plausible_since: float | None = None
        self._kept: dict[str, dict[str, Any]] = {}
        self._clock_s: float | None = None
        self._behind_since: float | None = None     # wall time the measures fell behind
        self._wall = time.monotonic

    def set_state(self, state: dict[str, Any]) -> None:
        """Set state; rules, a fallback or a running controller it has not got are
        refused by name, as at setup, and nothing is set (taken, its next swap failed)."""
        _check_controllers({**self.get_state(), **state})
        super().set_state(state)

    def on_input(self, port: InputPort) -> None:
        if port.name == "clock":
            self._clock_s = port.read()
            if self._last_measure_s is None:    # none yet: silent since the clock began
                self._last_measure_s = self._clock_s
            self._check_silence()
            return
        for measure in port.read_all():
            self._take(measure)

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
        span = max(measure.time - self._window[0].time, 1.0)
        self.demand_per_min = 60.0 * sum(m.arrivals for m in self._window) / span
        self.mean_queue = sum(m.queue for m in self._window) / len(self._window)
        if measure.time - self._plausible_since < self.window_s:
            return                                  # not a whole window to judge by yet
        if not self.detectors_ok:
            self.detectors_ok = True
            self.last_swap_s = -1e9                 # the way back is not held up
        wanted = self.choice()
        if wanted != self.running and measure.time - self.last_swap_s >= self.min_between_swaps_s:
            self._swap(wanted, measure.time, f"demand {self.demand_per_min:.1f}/min, "
                                             f"queue {self.mean_queue:.1f}")
            self.chosen = wanted

    def choice(self) -> str:
        """The controller the rules give for the demand and queue measured now (when
        none holds, the one chosen before, not a fallback standing in for it)."""
        chosen = self.chosen
        for rule in self.rules:
            if (self.demand_per_min >= rule.get("demand_at_least", 0.0)
                    and self.mean_queue >= rule.get("queue_at_least", 0.0)):
                chosen = rule["use"]
        return chosen

    def _check_silence(self) -> None:
        now, last = self._clock_s, self._last_measure_s
        if now is not None and last is not None and last > now:
            # a measure ahead of the clock is of a run that ended (the driver was
            # re-pointed, its clock from 0): silence counts from the new clock
            self._last_measure_s = last = now
            self._behind_since = None
        if now is None or last is None or now - last <= self.silent_after_s:
            return
        if self._behind_since is None:
            self._behind_since = self._wall()
        if self._wall() - self._behind_since >= self.silent_wall_s and self.detectors_ok:
            self._plausible_since = None
            self._window.clear()
            self._fail(now, f"no detector reading for {now - last:.0f} s")

    def _fail(self, now: float, why: str) -> None:
        if self.running != self.fallback:
            self._swap(self.fallback, now, f"detectors failed: {why}")
        # only once swapped: a swap that failed is tried again at the next look
        self.detectors_ok = False

    # -- swapping ---------------------------------------------------------------------
    def _swap(self, name: str, now: float, reason: str) -> None:
        leaving = self.running
        live = self.runtime.state(self.controller)
        self._kept[leaving] = {k: live[k] for k in KEPT_STATE if k in live}
        spec = self.controllers[name]
        self.runtime.swap(self.controller, spec["class"])
        self.runtime.set_state(self.controller, {**spec.get("state", {}),
                                                 **self._kept.get(name, {})})
        self.running, self.last_swap_s = name, now
        record = {"time": now, "controller": self.controller, "from": leaving, "to": name,
                  "reason": reason}
        self.swaps = [*self.swaps, record]
        self.swapped.write(record)
