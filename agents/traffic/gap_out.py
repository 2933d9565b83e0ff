"""``GapOut``: an actuated controller on local detectors. It holds a green while
vehicles keep coming to its stop lines (a moving vehicle due within ``passage_s``,
the actuated signal's passage time, by the reading's ``arriving_in``) and gives way
once that stream gaps out, or at ``max_green_s``, to the green with the most
vehicles on its lanes.

It wastes no green on an empty approach and cuts no platoon in half, which is what
makes SUMO's actuated programs good. The red side is counted as every vehicle on
its lanes, not only those already halting: a car braking for the red is waiting
too. With ``switch_ratio`` > 0 it also gives way early when the red side has that
many times the vehicles the green still serves.
"""

from __future__ import annotations

import math

from agents.limits import GREEN, RATIO, SECONDS
from agents.traffic.controller import JunctionController, busiest_red, in_transition, served
from agents.traffic.messages import JunctionReading


class GapOut(JunctionController):
    """Extends a green while vehicles approach it; then serves the busiest red."""

    min_green_s = 5.0
    max_green_s = 40.0
    passage_s = 4.0                 # a vehicle due within this holds the green
    switch_ratio = 0.0              # 0: never cut a stream short for the red side
    _limits = {"min_green_s": SECONDS, "max_green_s": GREEN, "passage_s": SECONDS,
              "switch_ratio": RATIO}

    def choose(self, reading: JunctionReading) -> int:
        if in_transition(reading) or reading.elapsed + 1e-9 < self.min_green_s:
            return reading.target
        if len(reading.layout.greens) == 1:
            return 0
        busiest, green = busiest_red(reading, reading.vehicles)
        if busiest == 0:                        # nobody at red
            return reading.green
        lanes = {lane for lane, _ in reading.layout.movements(reading.green)}
        due = any(reading.arriving_in.get(lane, math.inf) <= self.passage_s for lane in lanes)
        if not due or reading.elapsed + 1e-9 >= self.max_green_s:
            return green
        if self.switch_ratio > 0 and busiest >= self.switch_ratio * (
                served(reading, reading.green, reading.approaching)
                + served(reading, reading.green, reading.queues)):
            return green
        return reading.green
