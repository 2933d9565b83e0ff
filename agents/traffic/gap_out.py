"""``GapOut``: an actuated controller on local detectors. It holds a green while
vehicles keep coming to its stop lines (the reading's ``approaching``: moving
vehicles due within a few seconds) and gives way once the stream gaps out, or when
the queue waiting at red grows ``switch_ratio`` times what the green still serves,
or at ``max_green_s``.

It wastes no green on an empty approach and cuts no platoon in half, which is what
makes SUMO's actuated programs good; unlike them it also weighs the queue at red.
"""

from __future__ import annotations

from agents.traffic.controller import JunctionController, in_transition, served_queue
from agents.traffic.messages import JunctionReading


def served_approaching(reading: JunctionReading, green: int) -> int:
    """The vehicles due at the stop lines of the lanes ``green`` lets go."""
    lanes = {lane for lane, _ in reading.layout.movements(green)}
    return sum(reading.approaching.get(lane, 0) for lane in lanes)


class GapOut(JunctionController):
    """Extends a green while vehicles approach it; serves the longest queue next."""

    min_green_s = 5.0
    max_green_s = 40.0
    switch_ratio = 3.0

    def choose(self, reading: JunctionReading) -> int:
        if in_transition(reading) or reading.elapsed + 1e-9 < self.min_green_s:
            return reading.target
        greens = len(reading.layout.greens)
        if greens == 1:
            return 0
        queues = [served_queue(reading, g) for g in range(greens)]
        longest, green = max((queues[g], g) for g in range(greens) if g != reading.green)
        if longest == 0:                        # nobody waits at red
            return reading.green
        coming = served_approaching(reading, reading.green)
        if (coming > 0 and reading.elapsed + 1e-9 < self.max_green_s
                and longest < self.switch_ratio * (coming + queues[reading.green])):
            return reading.green
        return green
