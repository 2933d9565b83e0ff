"""``TimeLoss``: SUMO's ``delay_based`` strategy as a controller of ours. It holds a
green while vehicles on it are being delayed (the reading's ``delayed``: near the
stop line and over a second lost since they came onto the lane) and then serves the
red with the most delayed vehicles.

Unlike gap-out, a stream arriving at full speed does not hold the green (it is not
delayed yet), while a queue still starting up does, however long it is. On an
unsaturated network that costs it against gap-out; in a saturated surge, where every
green has a standing queue to discharge, it wins (``docs/applications.md``).
"""

from __future__ import annotations

from agents.limits import GREEN, SECONDS
from agents.traffic.controller import JunctionController, busiest_red, in_transition, served
from agents.traffic.messages import JunctionReading


class TimeLoss(JunctionController):
    """Extends a green while its vehicles lose time; then serves the most delayed red."""

    min_green_s = 5.0
    max_green_s = 50.0
    _limits = {"min_green_s": SECONDS, "max_green_s": GREEN}

    def choose(self, reading: JunctionReading) -> int:
        if in_transition(reading) or reading.elapsed + 1e-9 < self.min_green_s:
            return reading.target
        if len(reading.layout.greens) == 1:
            return 0
        most, green = busiest_red(reading, reading.delayed)
        if most == 0:                               # nobody losing time at red
            return reading.green
        if (served(reading, reading.green, reading.delayed) == 0
                or reading.elapsed + 1e-9 >= self.max_green_s):
            return green
        return reading.green
