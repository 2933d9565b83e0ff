"""Legal signal sequences: what a junction's lights show while controllers ask for
phases.

A controller only names the green phase it wants (an index into the program's green
phases). ``SignalHead`` decides what the lights show: it keeps the current green for
at least ``min_green_s``, then goes through yellow for every movement that loses its
green (and an all-red interval when the junction's program has one) before the new
green. The head, not the controller, owns this sequence, so a controller replaced in
the middle of a phase, or one that asks for something else every second, can never
show two conflicting greens or skip a yellow. Pure Python; no SUMO.

Signal states are SUMO's strings, one character per controlled link: ``G`` (green,
priority), ``g`` (green, yielding), ``y`` (yellow), ``r`` (red).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

GREEN = frozenset("Gg")


def is_green_phase(state: str) -> bool:
    """True for a phase that lets some movement go and is no transition."""
    return any(c in GREEN for c in state) and not any(c in "yYu" for c in state)


@dataclass(frozen=True)
class SignalPlan:
    """A junction's green phases and the transition times between them, as its
    SUMO program has them."""

    greens: tuple[str, ...]         # the green phases' states, in program order
    yellow_s: float                 # how long yellow is shown
    all_red_s: float                # how long everything is red after yellow (0: none)

    @classmethod
    def from_program(cls, phases: Sequence[tuple[str, float]]) -> SignalPlan:
        """The plan of a SUMO program given as (state, duration) pairs: its green
        phases, its longest yellow, and its longest all-red phase if it has one."""
        greens = tuple(state for state, _ in phases if is_green_phase(state))
        if not greens:
            raise ValueError("the program has no green phase: "
                             + ", ".join(state for state, _ in phases))
        if len({len(state) for state, _ in phases}) != 1:
            raise ValueError("the program's phases control different numbers of links")
        yellows = [d for state, d in phases if any(c in "yY" for c in state)]
        all_reds = [d for state, d in phases if set(state) <= set("rs")]
        return cls(greens, max(yellows, default=3.0), max(all_reds, default=0.0))

    def yellow(self, source: int, target: int) -> str:
        """The yellow from green ``source`` to green ``target``: yellow for the
        movements that lose their green, the others as they are."""
        return "".join("y" if c in GREEN and t not in GREEN else c
                       for c, t in zip(self.greens[source], self.greens[target], strict=True))

    def all_red(self, source: int, target: int) -> str:
        """Red for everything but the movements green in both phases."""
        return "".join(c if c in GREEN and t in GREEN else "r"
                       for c, t in zip(self.greens[source], self.greens[target], strict=True))


class SignalHead:
    """One junction's lights: phase requests in, a legal state for each interval out.

    Call ``request(green)`` whenever a controller asks, then ``show(dt)`` once per
    simulation interval for the state to show during the next ``dt`` seconds. A
    request made during a transition waits for the transition's end and the next
    minimum green: a transition, once begun, always finishes.
    """

    def __init__(self, plan: SignalPlan, min_green_s: float, green: int = 0) -> None:
        if not 0 <= green < len(plan.greens):
            raise ValueError(f"green phase {green} is not one of 0..{len(plan.greens) - 1}")
        self.plan = plan
        self.min_green_s = min_green_s
        self.green = green          # the green shown, or the one being left
        self.target = green         # the green being moved to (== green: none)
        self.stage = "green"        # green | yellow | all_red
        self.elapsed = 0.0          # seconds in this stage
        self.requested = green

    def request(self, green: int) -> None:
        """Ask for green phase ``green``; ``ValueError`` for one the plan lacks."""
        if not (isinstance(green, int) and 0 <= green < len(self.plan.greens)):
            raise ValueError(f"no green phase {green!r}: this junction has "
                             f"{len(self.plan.greens)} (0..{len(self.plan.greens) - 1})")
        self.requested = green

    def show(self, dt: float) -> str:
        """The state for the next ``dt`` seconds, moving on through the sequence."""
        self._move_on()
        state = self._state()
        self.elapsed += dt
        return state

    def _move_on(self) -> None:
        # Stages of zero length (no all-red, say) are passed in the same call.
        while True:
            if self.stage == "green":
                if self.requested == self.green or self.elapsed < self.min_green_s:
                    return
                if "y" not in self.plan.yellow(self.green, self.requested):
                    # nothing loses its green: the new movements may simply start
                    self.green = self.target = self.requested
                    self.elapsed = 0.0
                    return
                self.target, self.stage, self.elapsed = self.requested, "yellow", 0.0
            elif self.stage == "yellow" and self.elapsed >= self.plan.yellow_s:
                self.stage, self.elapsed = "all_red", 0.0
            elif self.stage == "all_red" and self.elapsed >= self.plan.all_red_s:
                self.green, self.stage, self.elapsed = self.target, "green", 0.0
            else:
                return

    def _state(self) -> str:
        if self.stage == "yellow":
            return self.plan.yellow(self.green, self.target)
        if self.stage == "all_red":
            return self.plan.all_red(self.green, self.target)
        return self.plan.greens[self.green]
