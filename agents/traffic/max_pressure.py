"""``MaxPressure``: the green whose movements have the most pressure, the vehicles
queued on their incoming lanes less those standing on the lanes they lead to
(Varaiya's max-pressure control, stable for any demand the junction can serve).

What stands downstream comes from the neighbouring junction's queues when it sends
them (``neighbour_i``), else from the driver's count on the outgoing lane.
"""

from __future__ import annotations

from agents.limits import SECONDS
from agents.traffic.controller import JunctionController, in_transition
from agents.traffic.messages import JunctionReading


class MaxPressure(JunctionController):
    """Every ``hold_s`` seconds of green, the green of greatest pressure."""

    hold_s = 10.0
    _limits = {"hold_s": SECONDS}

    def choose(self, reading: JunctionReading) -> int:
        if in_transition(reading):
            return reading.target
        if reading.elapsed + 1e-9 < self.hold_s:
            return reading.green
        pressures = [self.pressure(reading, g) for g in range(len(reading.layout.greens))]
        best = max(pressures)
        if pressures[reading.green] >= best:        # ties keep the green shown
            return reading.green
        return pressures.index(best)

    def pressure(self, reading: JunctionReading, green: int) -> float:
        """Queued vehicles on the movements of ``green`` less those downstream."""
        total = 0.0
        for lane_in, lane_out in set(reading.layout.movements(green)):
            total += reading.queues.get(lane_in, 0) - self.downstream(reading, lane_out)
        return total
