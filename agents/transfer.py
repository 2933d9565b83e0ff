"""``TransferAgent``: ends learning in simulation and moves the learner to the robot.

A policy learned on a simulated robot is a head start, not the end: the real robot's
dynamics and noise differ, so learning goes on there. This agent watches the
learner's episodes; once the success rate over the last ``window`` episodes reaches
``threshold`` (after at least ``min_episodes``), it stops stepping the simulation
(the driver's ``lockstep_s`` 0: a real robot is not stepped either) and moves the
learner's macro (the learner with its driver) to the hardware robot's node without
waiting. The driver is re-pointed at the hardware robot (``resource``) and the
learner given its state for the real robot (``learner_state``, e.g. a lower
exploration rate) on arrival (``migrate(..., state=...)``): they start on the robot's
node already set for it, and a move that fails leaves them as they were. It acts
once. A move that fails gives the simulation back its lock-step (the learner goes on
learning there), is said on ``transfer`` (``error``) and counted in ``failed_moves``,
and the agent decides again at a later episode, unless the runtime refused the move as
asked (a node the system does not have: ``refused`` says why). ``transfer`` reports when it decided
and when the move ended (``moved_at``: the driver was re-pointed as it arrived, inside
the move), in unix time, and the move's pause, where it went and the preparation
before it (``pause_s``, ``phases``, ``prepare_s``: see ``MigrationReport``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from typing import Any

from agents.limits import Limit, missing_modules, out_of_limits, refuse_own_state, whole
from pb3a import Agent, Input, InputPort, Output
from pb3a.errors import ConfigError, PB3AError
from pb3a.transport.addresses import tcp_address_problems


def success_rate(outcomes: list[bool], window: int) -> float:
    """The share of successes among the last ``window`` outcomes (0 if none)."""
    recent = outcomes[-window:]
    return sum(recent) / len(recent) if recent else 0.0


KEEP_OUTCOMES = 1000      # outcomes kept beyond the window (the state would grow without end)


_LIMITS: dict[str, Limit] = {
    "window": ("a whole number of episodes, 1 or more", lambda v: whole(v, 1)),
    "threshold": ("a success rate from 0 (at once) to 1", lambda v: not isinstance(v, bool)
                  and isinstance(v, int | float) and 0 <= v <= 1),
    "min_episodes": ("a whole number, 0 or more", whole),
    "to_node": ("the name of the hardware robot's node", lambda v: isinstance(v, str) and v != ""),
}


def _settings_problems(state: dict[str, Any]) -> list[str]:
    """What of ``state`` a ``TransferAgent`` could never or would always transfer by,
    each naming the setting (a window of 0 read every episode; a threshold above 1 never
    transferred, silently; without a destination it raised at every episode once
    learning was done)."""
    problems = out_of_limits(_LIMITS, state)
    if "to_resource" in state:
        problems += tcp_address_problems(state["to_resource"],
                                         "to_resource, the hardware robot's server,")
    return problems


class TransferAgent(Agent):
    """Moves ``macro`` to ``to_node`` and re-points ``driver`` at ``to_resource`` once
    the learner succeeds often enough in simulation."""

    episode = Input(dict, policy="queue:1000")     # the learner's episodes, in order
    transfer = Output(dict)
    macro = "brain"                 # what moves: the learner and its driver
    driver = "brain/driver"
    learner = "brain/learner"
    to_node = ""                    # the hardware robot's on-board node
    to_resource = ""                # the hardware robot's resource port
    learner_state: dict[str, Any] = {}   # set on the learner once it runs on the robot
    window = 20
    threshold = 0.8
    min_episodes = 20
    outcomes: list[bool] = []       # the last ones: max(window, KEEP_OUTCOMES)
    episodes = 0                    # heard of, all told
    decided_at = 0.0                # unix times; 0: not yet
    moved_at = 0.0
    move: dict[str, Any] = {}       # the migration's pause_s, prepare_s and phases
    failed_moves = 0
    refused = ""                    # why the move can never be made, once the runtime said
    lockstep_s: float | None = None  # the driver's, as the move stopped it (None: not
                                     # stopped), given back if the move fails
    period = 0.02                   # the longest a look at a move in progress waits

    def setup(self) -> None:
        refuse_own_state(self)
        self._check_modules()
        self._moving: Any = None    # the Pending of the move (not state: not picklable)

    def _check_modules(self) -> None:
        """ValueError naming the driver or learner the system does not have (found
        when the move was tried, after learning)."""
        problems = missing_modules(self, [("driver", self.driver), ("learner", self.learner)])
        if problems:
            raise ValueError("TransferAgent: " + "; ".join(problems))

    @classmethod
    def state_problems(cls, state: dict[str, Any]) -> list[str]:
        """A setting it could never or would always transfer by (see
        ``_settings_problems``), each naming it."""
        problems = super().state_problems(state)
        return problems + [f"{cls.__name__}'s {problem}"
                           for problem in _settings_problems(state)]

    def on_input(self, port: InputPort) -> None:
        for episode in port.read_all():
            self.outcomes.append(bool(episode["success"]))
            self.episodes += 1
        del self.outcomes[:-max(self.window, KEEP_OUTCOMES)]
        if self.decided_at or self.refused or self.episodes < self.min_episodes:
            return
        if success_rate(self.outcomes, self.window) >= self.threshold:
            self.decided_at = time.time()
            arriving = {self.driver: {"resource": self.to_resource}}
            if self.learner_state:
                arriving[self.learner] = dict(self.learner_state)
            try:
                # the simulation stops first (its lock-step loop would compete with the
                # move for the CPU), then the learner and its driver move
                self.lockstep_s = None      # (stays so if the driver's cannot be read)
                self.lockstep_s = float(self.runtime.state(self.driver).get("lockstep_s",
                                                                            0.0))
                self.runtime.set_state(self.driver, {"lockstep_s": 0.0})
                self._moving = self.runtime.migrate(self.macro, self.to_node, wait=False,
                                                    state=arriving)
            except PB3AError as exc:        # (any of the three: decided again later)
                self._failed(exc)

    def step(self) -> None:
        if self.decided_at and not self.moved_at and self._moving is None:
            self._resume()
            return
        # waits for the move's end (a period at most): the transfer is timed to when the
        # agent knows it ended, and this knows it as it ends
        if self._moving is None or not self._moving.wait(self.period):
            return
        try:
            report = self._moving.result(0)
        except PB3AError as exc:
            self._failed(exc)
            return
        finally:
            self._moving = None
        self.moved_at = time.time()
        self.move = {"pause_s": report.pause_s, "prepare_s": report.prepare_s,
                     "phases": dataclasses.asdict(report.phases)}
        self.transfer.write({"decided_at": self.decided_at, "moved_at": self.moved_at,
                             **self.move,
                             "episodes": self.episodes,
                             "success_rate": success_rate(self.outcomes, self.window)})

    def _resume(self) -> None:
        """Decided, but the move's handle is gone (this agent was restored from its
        state: a checkpoint, a move of its own): where the learner runs says whether
        the move happened."""
        try:
            arrived = self.runtime.where(self.learner) == self.to_node
        except PB3AError as exc:
            self._failed(exc)
            return
        if not arrived:
            self._failed(RuntimeError("the move was lost with the agent's own restart or "
                                      "move, and the learner is not on the robot's node"))
            return
        self.moved_at = time.time()         # (no report of its pause: it is gone)
        self.transfer.write({"decided_at": self.decided_at, "moved_at": self.moved_at,
                             "episodes": self.episodes,
                             "success_rate": success_rate(self.outcomes, self.window)})

    def _failed(self, error: Exception) -> None:
        """The move failed: the brain is where it was, so its simulation gets its
        lock-step back; said once, and decided again at a later episode, unless the
        runtime refused the move as it was asked (``ConfigError``: no such node, say),
        which no later episode changes (``refused`` says why; it was tried again at
        every episode)."""
        self.failed_moves += 1
        if isinstance(error, ConfigError):
            self.refused = str(error)
        # (a driver whose state could not be read was not stopped: what it runs with is
        # not known here, and is left as it is)
        if self.lockstep_s is not None:
            with contextlib.suppress(PB3AError):    # (tried again at the next decision)
                self.runtime.set_state(self.driver, {"lockstep_s": self.lockstep_s})
            self.lockstep_s = None
        self.transfer.write({"decided_at": self.decided_at, "moved_at": 0.0,
                             "error": f"{type(error).__name__}: {error}",
                             "episodes": self.episodes,
                             "success_rate": success_rate(self.outcomes, self.window)})
        self.decided_at = 0.0
