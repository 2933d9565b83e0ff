"""``LongestQueueFirst``: the green that serves the longest queue, held for at least
``min_green_s`` and at most ``max_green_s`` while others wait.

It ends a green early once its own lanes are empty and another has vehicles
waiting, and changes before ``max_green_s`` only for a queue ``switch_ratio`` times
its own, so it does not pay a yellow for every small difference.
"""

from __future__ import annotations

from agents.limits import GREEN, RATIO, SECONDS
from agents.traffic.controller import JunctionController, in_transition, served_queue
from agents.traffic.messages import JunctionReading


class LongestQueueFirst(JunctionController):
    """Serves the longest queue, within minimum and maximum greens."""

    min_green_s = 8.0
    max_green_s = 45.0
    switch_ratio = 2.0
    _limits = {"min_green_s": SECONDS, "max_green_s": GREEN, "switch_ratio": RATIO}

    def choose(self, reading: JunctionReading) -> int:
        if in_transition(reading) or reading.elapsed + 1e-9 < self.min_green_s:
            return reading.target
        queues = [served_queue(reading, g) for g in range(len(reading.layout.greens))]
        shown = queues[reading.green]
        others = [(q, g) for g, q in enumerate(queues) if g != reading.green]
        if not others:
            return reading.green
        longest, green = max(others)
        if longest == 0:
            return reading.green
        if (shown == 0 or reading.elapsed + 1e-9 >= self.max_green_s
                or longest >= self.switch_ratio * shown):
            return green
        return reading.green
