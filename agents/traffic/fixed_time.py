"""``FixedTime``: each green in turn for ``green_s`` seconds, whatever the traffic.

The reference every adaptive controller is measured against, and the fallback when a
junction's detectors fail: it needs nothing from them but the phase shown.
"""

from __future__ import annotations

from agents.limits import GREEN
from agents.traffic.controller import JunctionController, in_transition
from agents.traffic.messages import JunctionReading


class FixedTime(JunctionController):
    """Cycles through the junction's greens, ``green_s`` seconds each."""

    green_s = 25.0
    _limits = {"green_s": GREEN}

    def choose(self, reading: JunctionReading) -> int:
        if in_transition(reading):
            return reading.target
        if reading.elapsed + 1e-9 < self.green_s:
            return reading.green
        return (reading.green + 1) % len(reading.layout.greens)
