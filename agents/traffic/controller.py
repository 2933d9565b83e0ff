"""``JunctionController``: the ports every junction controller shares, so any one can
be swapped for another while the system runs.

A controller answers each ``JunctionReading`` with a ``PhaseRequest`` at once (the
driver's lock-step waits for it) and hears its neighbours' queues on
``neighbour_0`` … ``neighbour_3`` (``NeighbourQueues``: the queues its outgoing lanes
lead into). Subclasses only say which green they want, in ``choose``. They decide
from the reading's ``green``, ``target``, ``stage`` and ``elapsed`` (what the driver's
``SignalHead`` shows), not from a phase of their own: a controller swapped in
mid-phase carries on from the phase in progress.

Each subclass lists its numeric settings and what they must be (``_limits``): a
value out of range is refused by name (``state_problems``: by ``pb3a check``, ``add``,
the State Editor, a live ``set_state``, which sets nothing, and at ``setup``), instead
of a green of -5 s that the signal head would quietly stretch.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar

from agents.limits import Limit, out_of_limits, refuse_own_state
from agents.traffic.messages import JunctionReading, NeighbourQueues, PhaseRequest
from pb3a import Input, InputPort, Module, Output

NEIGHBOUR_SLOTS = 4             # a junction's neighbours downstream, at most

def _neighbour_ports() -> dict[str, Input]:
    return {f"neighbour_{slot}": Input(NeighbourQueues, policy="latest")
            for slot in range(NEIGHBOUR_SLOTS)}


_NeighbourSlots = type("_NeighbourSlots", (), _neighbour_ports())


class JunctionController(_NeighbourSlots, Module, abc.ABC):
    """Readings in, one phase request per reading out; ``choose`` decides (an
    abstract method: the base class itself never runs)."""

    reading = Input(JunctionReading, policy="queue:8")
    request = Output(PhaseRequest)
    decisions = 0                           # readings answered
    _limits: ClassVar[dict[str, Limit]] = {}     # each numeric setting: what it must be

    def setup(self) -> None:
        refuse_own_state(self)
        self._downstream: dict[str, int] = {}

    @classmethod
    def state_problems(cls, state: dict[str, Any]) -> list[str]:
        """Each setting of ``state`` out of its ``_limits``, and a maximum green below
        the minimum one (when the state gives both), each naming the setting."""
        problems = super().state_problems(state)
        wrong = out_of_limits(cls._limits, state)
        if not wrong and "min_green_s" in state and "max_green_s" in state:
            least, most = state["min_green_s"], state["max_green_s"]
            if most < least:
                wrong.append(f"max_green_s ({most!r}) must be at least min_green_s "
                             f"({least!r})")
        return problems + [f"{cls.__name__}'s {problem}" for problem in wrong]

    def on_input(self, port: InputPort) -> None:
        if port.name.startswith("neighbour_"):
            for message in port.read_all():
                self._downstream.update(message.queues)
            return
        for reading in port.read_all():
            green = self.choose(reading)
            self.request.write(PhaseRequest(reading.junction, reading.step, green,
                                            reading.run))
            self.decisions += 1

    @abc.abstractmethod
    def choose(self, reading: JunctionReading) -> int:
        """The green phase to ask for after ``reading``."""

    def downstream(self, reading: JunctionReading, lane: str) -> int:
        """Vehicles standing on outgoing ``lane``: the neighbour's count of its halting
        vehicles when it has sent one, else the driver's count of all on it."""
        return self._downstream.get(lane, reading.outgoing.get(lane, 0))


def in_transition(reading: JunctionReading) -> bool:
    """True while the lights move from one green to another (yellow, all-red)."""
    return reading.stage != "green" or reading.target != reading.green


def served(reading: JunctionReading, green: int, counts: dict[str, int]) -> int:
    """The sum of ``counts`` (a reading's count per lane) over the lanes green phase
    ``green`` lets go."""
    lanes = {lane for lane, _ in reading.layout.movements(green)}
    return sum(counts.get(lane, 0) for lane in lanes)


def served_queue(reading: JunctionReading, green: int) -> int:
    """The halting vehicles on the lanes that green phase ``green`` lets go."""
    return served(reading, green, reading.queues)


def busiest_red(reading: JunctionReading, counts: dict[str, int]) -> tuple[int, int]:
    """(count, green) of the green phase not shown with the most of ``counts`` on its
    lanes (a junction of two greens or more)."""
    greens = range(len(reading.layout.greens))
    return max((served(reading, g, counts), g) for g in greens if g != reading.green)
