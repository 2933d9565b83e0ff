"""``JunctionSensors``: what a junction's detectors say, made into the figures its
modules use: totals (queue, waiting time, arrivals) for its performance agent and
the queue per incoming lane for the neighbours upstream.

It also judges whether a reading is plausible: a count that is negative or above
``lane_capacity`` (vehicles halting, arriving, moving, due, delayed or leaving on a
lane), a negative waiting time or a negative or non-finite time to the stop line is
a failed detector, not traffic. (Only the queues, arrivals and waiting times were judged:
what gap-out and time loss decide by, the vehicles due and the delayed ones, could
fail unseen, and the fallback never came.)
"""

from __future__ import annotations

import math
from typing import Any

from agents.limits import refuse_own_state, whole
from agents.traffic.messages import JunctionMeasures, JunctionReading, NeighbourQueues
from pb3a import Input, InputPort, Module, Output


def plausible(reading: JunctionReading, lane_capacity: int) -> bool:
    """False when a detector of ``reading`` gives a value no lane can have."""
    counts = (*reading.queues.values(), *reading.arrivals.values(),
              *reading.vehicles.values(), *reading.approaching.values(),
              *reading.delayed.values(), *reading.outgoing.values())
    return (all(0 <= c <= lane_capacity for c in counts)
            and all(0 <= w < math.inf for w in reading.waiting.values())
            and all(0 <= t < math.inf for t in reading.arriving_in.values()))


class JunctionSensors(Module):
    """A junction's reading in; its totals and its queues per lane out."""

    reading = Input(JunctionReading, policy="queue:8")
    measures = Output(JunctionMeasures)
    queues = Output(NeighbourQueues)
    lane_capacity = 200                 # halting vehicles a lane can hold, at most
    implausible = 0                     # readings judged implausible

    def setup(self) -> None:
        refuse_own_state(self)

    @classmethod
    def state_problems(cls, state: dict[str, Any]) -> list[str]:
        """A ``lane_capacity`` that is not a whole number, 1 or more (below 1, every
        reading was a failed detector, and the junction ran fixed time for good, blamed
        on its detectors)."""
        problems = super().state_problems(state)
        capacity = state.get("lane_capacity", 1)
        if not whole(capacity, 1):
            problems.append(f"{cls.__name__}'s lane_capacity must be a whole number of "
                            f"vehicles, 1 or more, got {capacity!r}")
        return problems

    def on_input(self, port: InputPort) -> None:
        for reading in port.read_all():
            ok = plausible(reading, self.lane_capacity)
            self.implausible += not ok
            self.measures.write(JunctionMeasures(
                reading.junction, reading.step, reading.time,
                queue=sum(reading.queues.values()), waiting_s=sum(reading.waiting.values()),
                arrivals=sum(reading.arrivals.values()), plausible=ok))
            self.queues.write(NeighbourQueues(reading.junction, reading.time,
                                              dict(reading.queues)))
