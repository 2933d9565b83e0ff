"""What travels between the traffic driver and the junctions' modules.

The driver writes a ``JunctionReading`` per junction and control step, and a
``NetworkReading`` for the whole network; a controller answers a reading with a
``PhaseRequest`` naming the green phase it wants. All are frozen dataclasses, so
they cross processes as they are.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class JunctionLayout:
    """A signalized junction as its controller sees it: the lanes its lights govern
    and the green phases it may ask for."""

    junction: str
    links: tuple[tuple[str, str], ...]   # per signal index: (incoming lane, outgoing lane)
    greens: tuple[str, ...]              # the green phases' states (SUMO's G/g/r per link)
    lanes_in: tuple[str, ...]            # incoming lanes, each once, in signal order
    lanes_out: tuple[str, ...]

    def movements(self, green: int) -> tuple[tuple[str, str], ...]:
        """The (incoming, outgoing) lane pairs that green phase ``green`` lets go."""
        return tuple(link for link, c in zip(self.links, self.greens[green], strict=True)
                     if c in "Gg")


@dataclass(frozen=True)
class JunctionReading:
    """One junction's detectors and lights at the start of control step ``step``."""

    junction: str
    step: int
    time: float                          # simulated seconds
    layout: JunctionLayout
    green: int                           # the green phase shown, or the one being left
    target: int                          # the green being moved to (== green: none)
    stage: str                           # "green", "yellow" or "all_red"
    elapsed: float                       # seconds in this stage
    signal: str                          # what the lights showed over the last step
    queues: dict[str, int]               # halting vehicles per incoming lane
    waiting: dict[str, float]            # their accumulated waiting time (s) per lane
    arrivals: dict[str, int]             # vehicles new on each incoming lane this step
    outgoing: dict[str, int]             # vehicles on each outgoing lane
    vehicles: dict[str, int] = field(default_factory=dict)   # all vehicles (moving
                                         # too) on each incoming lane
    approaching: dict[str, int] = field(default_factory=dict)   # moving vehicles due
                                         # at the stop line within APPROACH_S, per lane
    arriving_in: dict[str, float] = field(default_factory=dict)   # seconds until the
                                         # nearest moving vehicle reaches the stop line,
                                         # per lane that has one (an actuated signal's
                                         # passage time is judged against it)
    delayed: dict[str, int] = field(default_factory=dict)   # vehicles within 100 m of
                                         # the stop line that have lost over 1 s since
                                         # they came onto the lane (SUMO's delay_based)
    run: int = 0                         # which of the driver's simulations it is of
                                         # (it counts them: a re-pointed one is another)


@dataclass(frozen=True)
class PhaseRequest:
    """A controller's answer to the reading of step ``step`` (of the driver's simulation
    ``run``, the reading's; 0: not said, taken as the one running): show green phase
    ``green`` (an index into the layout's ``greens``) as soon as it is legal."""

    junction: str
    step: int
    green: int
    run: int = 0


@dataclass(frozen=True)
class NetworkReading:
    """The whole network at the start of control step ``step``."""

    step: int
    time: float                          # simulated seconds
    running: int                         # vehicles on the roads
    waiting_to_enter: int                # vehicles due that could not enter yet
    departed: int                        # vehicles that entered, since the start
    arrived: int                         # vehicles that reached their destination
    teleports: int                       # vehicles SUMO moved out of a jam, since the start
    halting: int                         # vehicles standing on the signalized approaches


@dataclass(frozen=True)
class JunctionMeasures:
    """What a junction's sensors make of one reading: its totals, for the junction's
    performance agent. ``plausible`` is False when a detector gave a value no road
    can have (a negative count, more vehicles than a lane holds)."""

    junction: str
    step: int
    time: float                          # simulated seconds
    queue: int                           # halting vehicles on its incoming lanes
    waiting_s: float                     # their accumulated waiting time
    arrivals: int                        # vehicles new on its incoming lanes this step
    plausible: bool


@dataclass(frozen=True)
class NeighbourQueues:
    """A junction's halting vehicles per incoming lane, sent to the junctions upstream:
    for them, these are the queues their outgoing lanes run into."""

    junction: str
    time: float
    queues: dict[str, int]
