"""``PolicyLearner``: a reactive goal-seeking, obstacle-avoiding policy, learnt by
tabular Q(lambda) on a robot's sonar and its goal's bearing.

The robot's situation is coarse on purpose: four sonar sectors, each near or clear,
and the goal's bearing in one of eight sectors (128 situations); its actions are
(v, w) pairs held for a decision period. Neither depends on how quickly the robot
answers a command, so a table learnt on RAVE's simulated robot (zeroth-order) is a
good start on the hardware robot (second-order, noisy, real time). The table, the
exploration rate, the random generator and the episode under way are the module's
state: the learner migrates with what it has learnt and goes on where it was.

An episode drives to one goal. It ends in success (within ``goal_radius``), in a
collision (a bumper transducer reads below ``collision_range``), after which the
robot backs up and turns away (a real robot cannot be put back by hand), or at its
``timeout``. The next episode goes for the next goal, from wherever the robot is.

An optional speed guard (``Parameters.guard_range``) holds the forward speed down as
the robot nears an obstacle, whatever the policy decided: a robot with inertia,
which the simulated one has not, then brakes in time for what the table learnt.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, fields
from typing import Any, ClassVar

import numpy as np

from agents.limits import finite
from pb3a import Input, InputPort, Module, Output

SUCCESS, COLLISION, TIMEOUT = "success", "collision", "timeout"
EPSILON = 0.3        # the exploration rate an untrained learner starts with
# Episodes kept (the last ones): its state, which moves and is checkpointed, would
# otherwise grow by one at every episode for as long as it learns.
KEEP_EPISODES = 1000


@dataclass(frozen=True)
class Parameters:
    """How the learner senses, acts, is rewarded and learns; the module's
    ``parameters`` state (a dict) overrides any of them."""

    # (v m/s, w rad/s): forward, turn left, turn right (in place: turning near an
    # obstacle never runs into it)
    actions: tuple[tuple[float, float], ...] = ((0.3, 0.0), (0.0, 1.2), (0.0, -1.2))
    # sonar sectors (Pioneer ring indices), each sensed as its nearest transducer's
    # reading: left, front-left, front-right, right
    sectors: tuple[tuple[int, ...], ...] = ((0, 1), (2, 3), (4, 5), (6, 7))
    thresholds: tuple[float, ...] = (0.7,)   # m: a sector is near below, clear beyond
    bearings: int = 8                        # goal bearing sectors, the first dead ahead
    alpha: float = 0.3                       # learning rate
    gamma: float = 0.9                       # discount per decision
    trace_decay: float = 0.7                 # lambda: how far back credit goes (0: one step)
    # learn from each transition for its mirror image too (left for right), the
    # robot being symmetric: it needs symmetric sectors and actions
    mirror: bool = True
    epsilon_decay: float = 0.97              # exploration rate kept after each episode
    epsilon_min: float = 0.02
    goal_radius: float = 0.4                 # m: success within this of the goal
    bumper: tuple[int, ...] = (1, 2, 3, 4, 5, 6)   # transducers that sense a collision
    collision_range: float = 0.3             # m
    # m: an on-board speed guard (as ARIA's avoid-front action) when positive:
    # forward speed is held to ``guard_gain`` (1/s) times how far the bumper's nearest
    # reading is beyond ``guard_range``, so the robot slows as it nears an obstacle,
    # whatever it decided, and stops short of it; 0 turns the guard off
    guard_range: float = 0.0
    guard_gain: float = 1.0
    timeout: float = 60.0                    # s an episode may last
    progress_reward: float = 10.0            # per metre nearer the goal
    step_cost: float = 0.1                   # per decision
    collision_penalty: float = 10.0
    success_bonus: float = 10.0
    # after a collision: back up until the bumper reads ``clear_range`` (or the rear
    # is blocked, or ``backup_limit`` s pass), then turn away for ``turn_time`` s
    backup_speed: float = 0.2                # m/s
    clear_range: float = 0.6                 # m
    backup_limit: float = 3.0                # s
    turn_time: tuple[float, float] = (0.5, 1.5)    # s, drawn at random
    # s: a transition that took longer (a pause, a migration) is not learnt from
    max_gap: float = 1.0

    def __post_init__(self) -> None:
        used = [i for sector in self.sectors for i in sector] + list(self.bumper)
        if not all(isinstance(i, int) and 0 <= i < 16 for i in used):
            raise ValueError(f"sectors and bumper name transducers 0-15 of the ring, not "
                             f"{self.sectors} and {self.bumper}")
        wrong = [f"{name} = {getattr(self, name)!r} ({what})"
                 for name, what, right in self._CHECKS if not right(getattr(self, name))]
        if wrong:
            raise ValueError("learner parameter(s) out of range: " + "; ".join(wrong))

    # (parameter, what it must be, whether it is): a value out of range would not fail
    # but learn nonsense (unsorted thresholds mis-sense every sector, a discount above 1
    # diverges) or fail at the first decision with no word of which parameter it was
    _CHECKS: ClassVar[tuple[tuple[str, str, Any], ...]] = (
        ("actions", "(v, w) pairs, at least one",
         lambda a: len(a) > 0 and all(len(x) == 2 and all(map(finite, x)) for x in a)),
        ("sectors", "transducer groups, at least one, none empty",
         lambda s: len(s) > 0 and all(len(x) > 0 for x in s)),
        ("thresholds", "ranges above 0 in increasing order",
         lambda t: all(map(finite, t)) and all(a < b for a, b in zip(
             (0.0, *t), t, strict=False))),
        ("bearings", "a whole number of sectors, 1 or more",
         lambda b: isinstance(b, int) and b >= 1),
        ("alpha", "in (0, 1]", lambda x: finite(x) and 0 < x <= 1),
        ("gamma", "in [0, 1]", lambda x: finite(x) and 0 <= x <= 1),
        ("trace_decay", "in [0, 1]", lambda x: finite(x) and 0 <= x <= 1),
        ("epsilon_decay", "in (0, 1]", lambda x: finite(x) and 0 < x <= 1),
        ("epsilon_min", "in [0, 1]", lambda x: finite(x) and 0 <= x <= 1),
        ("goal_radius", "above 0", lambda x: finite(x) and x > 0),
        ("collision_range", "0 or more", lambda x: finite(x) and x >= 0),
        ("guard_range", "0 or more", lambda x: finite(x) and x >= 0),
        ("guard_gain", "above 0", lambda x: finite(x) and x > 0),
        ("timeout", "above 0", lambda x: finite(x) and x > 0),
        ("backup_speed", "0 or more", lambda x: finite(x) and x >= 0),
        ("clear_range", "0 or more", lambda x: finite(x) and x >= 0),
        ("backup_limit", "0 or more", lambda x: finite(x) and x >= 0),
        ("turn_time", "(low, high) with 0 <= low <= high",
         lambda t: len(t) == 2 and all(map(finite, t)) and 0 <= t[0] <= t[1]),
        ("max_gap", "above 0", lambda x: finite(x) and x > 0),
    )

    @classmethod
    def of(cls, overrides: dict[str, Any]) -> Parameters:
        """The defaults with ``overrides`` (lists, as from a file, become tuples);
        ValueError names an unknown parameter."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise ValueError(f"unknown learner parameter(s) {', '.join(map(repr, unknown))}; "
                             f"they are: {', '.join(sorted(known))}")
        return cls(**{name: _frozen(value) for name, value in overrides.items()})

    @property
    def levels(self) -> int:
        """How many range levels a sector may be in."""
        return len(self.thresholds) + 1

    @property
    def states(self) -> int:
        """How many situations the learner tells apart: the rows of its table."""
        return self.levels ** len(self.sectors) * self.bearings


@dataclass(frozen=True)
class Episode:
    """One finished episode."""

    index: int
    outcome: str                             # SUCCESS, COLLISION or TIMEOUT
    steps: int                               # decisions taken
    seconds: float
    goal: tuple[float, float]


class ReactiveLearner:
    """Decides, once a decision period, what the robot does next, and learns from
    what came of its last decision (Q(lambda), epsilon-greedy).

    Every argument but ``goals``, ``parameters`` and ``seed`` is state that
    ``state()`` gives back; an empty ``q`` is a fresh (all-zero) table and an empty
    ``rng_state`` a generator seeded with ``seed``. Arrays, lists and dicts given
    are used, not copied: the learner updates them in place.
    """

    def __init__(self, goals: Any, parameters: Parameters | None = None, *, seed: int = 0,
                 q: np.ndarray | None = None, trace: np.ndarray | None = None,
                 epsilon: float = EPSILON, goal_index: int = 0,
                 episodes: list[tuple[str, int, float]] | None = None,
                 episode_count: int = 0, underway: dict[str, Any] | None = None,
                 recovery: dict[str, Any] | None = None,
                 rng_state: dict[str, Any] | None = None) -> None:
        self.parameters = p = parameters or Parameters()
        self.goals = np.asarray(goals, dtype=np.float64).reshape(-1, 2)
        if not len(self.goals):
            raise ValueError("the learner needs at least one goal: [[x, y], ...]")
        self.q = _table(q, p, "table")
        self.trace = _table(trace, p, "trace")      # each cell's share in what comes next
        self.epsilon = float(epsilon)
        self.goal_index = int(goal_index) % len(self.goals)
        self.episodes = [] if episodes is None else episodes    # the last KEEP_EPISODES
        self.episode_count = max(int(episode_count), len(self.episodes))   # all of them
        # the episode under way ({}: none, one begins at the next decision): when it
        # began, decisions so far, and the last one's situation, action, distance to
        # the goal and time, which the next decision learns from
        self.underway = {} if underway is None else underway
        self.recovery = {} if recovery is None else recovery   # the manoeuvre under way
        self.rng = np.random.default_rng(seed)
        if rng_state:
            self.rng.bit_generator.state = rng_state
        self._actions = np.array(p.actions, dtype=np.float64)
        self._sector_of = np.concatenate([np.asarray(s, dtype=np.intp) for s in p.sectors])
        self._sector_starts = np.cumsum([0] + [len(s) for s in p.sectors[:-1]])
        self._level_weights = p.levels ** np.arange(len(p.sectors))
        self._bumper = np.asarray(p.bumper, dtype=np.intp)
        self._mirror = _mirror(p) if p.mirror else None

    def state(self) -> dict[str, Any]:
        """What the learner has learnt and where it is: the keyword arguments that make
        an equal learner (with the same goals, parameters and seed)."""
        return {"q": self.q, "trace": self.trace, "epsilon": self.epsilon,
                "goal_index": self.goal_index, "episodes": self.episodes,
                "episode_count": self.episode_count,
                "underway": self.underway, "recovery": self.recovery,
                "rng_state": self.rng.bit_generator.state}

    # -- perceiving -----------------------------------------------------------------
    def situation(self, sonar: np.ndarray, pose: np.ndarray, goal: np.ndarray) -> int:
        """The table row for these sonar readings and this goal seen from ``pose``."""
        p = self.parameters
        nearest = np.minimum.reduceat(sonar[self._sector_of], self._sector_starts)
        levels = np.searchsorted(p.thresholds, nearest, side="right")
        bearing = math.atan2(goal[1] - pose[1], goal[0] - pose[0]) - pose[2]
        sector = round(bearing / (math.tau / p.bearings)) % p.bearings
        return int(levels @ self._level_weights) * p.bearings + sector

    # -- deciding -------------------------------------------------------------------
    def decide(self, sonar: np.ndarray, pose: np.ndarray, now: float, *, learn: bool = True,
               ) -> tuple[np.ndarray, Episode | None]:
        """The command (v, w) to hold until the next decision, and the episode this
        decision ended, if any. ``now`` is in seconds on a clock that all of a
        learner's decisions share; with ``learn`` False the policy is greedy and the
        table and exploration rate are left alone."""
        if self.recovery:
            command = self._recover(sonar, now)
            if command is not None:
                return command, None
        if not self.underway:
            self.underway.update(started=now, steps=0, state=-1, action=-1,
                                 distance=math.nan, at=now)
        goal = self.goals[self.goal_index]
        distance = math.hypot(goal[0] - pose[0], goal[1] - pose[1])
        situation = self.situation(sonar, pose, goal)
        outcome = self._outcome(sonar, distance, now)
        if learn:
            self._learn(situation, distance, outcome, now)
        if outcome is not None:
            finished = self._finish(outcome, now, learn)
            if outcome == COLLISION:
                self.recovery.update(phase="back", since=now)
            command, _ = self.decide(sonar, pose, now, learn=learn)   # or the next goal's
            return command, finished
        action = self._choose(situation, learn)
        self.underway.update(steps=self.underway["steps"] + 1, state=situation, action=action,
                             distance=distance, at=now)
        return self._guarded(self._actions[action].copy(), sonar), None

    def _guarded(self, command: np.ndarray, sonar: np.ndarray) -> np.ndarray:
        """``command`` with its forward speed held by the guard (see ``Parameters``)."""
        p = self.parameters
        if p.guard_range > 0 and command[0] > 0:
            room = sonar[self._bumper].min() - p.guard_range
            command[0] = min(command[0], max(0.0, p.guard_gain * room))
        return command

    def _outcome(self, sonar: np.ndarray, distance: float, now: float) -> str | None:
        p, underway = self.parameters, self.underway
        if underway["steps"] == 0:          # only what the learner's own actions brought
            return None
        if distance < p.goal_radius:
            return SUCCESS
        if sonar[self._bumper].min() < p.collision_range:
            return COLLISION
        if now - underway["started"] >= p.timeout:
            return TIMEOUT
        return None

    def _learn(self, situation: int, distance: float, outcome: str | None, now: float) -> None:
        """Update the table for the last decision's outcome, sharing the error with the
        decisions before it by their traces."""
        p, last = self.parameters, self.underway
        if last["state"] < 0:
            return
        if now - last["at"] > p.max_gap:
            self.trace[:] = 0.0              # nothing before the gap earned what follows
            return
        reward = p.progress_reward * (last["distance"] - distance) - p.step_cost
        if outcome == SUCCESS:
            target = reward + p.success_bonus
        elif outcome == COLLISION:
            target = reward - p.collision_penalty
        else:       # a timeout only cuts the episode short: the situation still has a future
            target = reward + p.gamma * self.q[situation].max()
        error = target - self.q[last["state"], last["action"]]
        self.trace *= p.gamma * p.trace_decay
        self.trace[last["state"], last["action"]] = 1.0        # replacing traces
        if self._mirror is not None:
            states, actions = self._mirror
            self.trace[states[last["state"]], actions[last["action"]]] = 1.0
        self.q += p.alpha * error * self.trace

    def _choose(self, situation: int, learn: bool) -> int:
        if learn and self.rng.random() < self.epsilon:
            return int(self.rng.integers(len(self._actions)))
        values = self.q[situation]
        best = np.flatnonzero(values == values.max())
        if len(best) == 1 or not learn:
            return int(best[0])
        return int(best[self.rng.integers(len(best))])       # untried ties: no favourite

    def _finish(self, outcome: str, now: float, learn: bool) -> Episode:
        p, underway = self.parameters, self.underway
        goal = self.goals[self.goal_index]
        episode = Episode(self.episode_count, outcome, underway["steps"],
                          now - underway["started"], (float(goal[0]), float(goal[1])))
        self.episodes.append((outcome, episode.steps, episode.seconds))
        del self.episodes[:-KEEP_EPISODES]
        self.episode_count += 1
        if learn:
            self.epsilon = max(p.epsilon_min, self.epsilon * p.epsilon_decay)
        self.goal_index = (self.goal_index + 1) % len(self.goals)
        self.trace[:] = 0.0
        underway.clear()
        return episode

    # -- recovering from a collision ------------------------------------------------------
    def _recover(self, sonar: np.ndarray, now: float) -> np.ndarray | None:
        """The manoeuvre's command now, or None once it is over: back up until the
        bumper is clear, then turn away from the nearer side for a while."""
        p, recovery = self.parameters, self.recovery
        if recovery["phase"] == "back":
            clear = sonar[self._bumper].min() >= p.clear_range
            blocked = sonar[8:16].min() < p.collision_range
            if not (clear or blocked or now - recovery["since"] >= p.backup_limit):
                return np.array([-p.backup_speed, 0.0])
            turn = max(abs(w) for _, w in p.actions)
            away = -turn if sonar[0:4].min() < sonar[4:8].min() else turn
            recovery.update(phase="turn", w=away, until=now + self.rng.uniform(*p.turn_time))
        if now < recovery["until"]:
            return np.array([0.0, recovery["w"]])
        recovery.clear()
        return None


def success_rate(episodes: list[tuple[str, int, float]], last: int | None = None) -> float:
    """The share of successes among the ``last`` episodes (all by default); NaN for none."""
    chosen = episodes[-last:] if last else episodes
    if not chosen:
        return math.nan
    return sum(outcome == SUCCESS for outcome, _, _ in chosen) / len(chosen)


def _table(given: np.ndarray | None, p: Parameters, what: str) -> np.ndarray:
    """``given``, or zeros when it is empty, checked against the parameters' shape."""
    shape = (p.states, len(p.actions))
    if given is None or given.size == 0:
        return np.zeros(shape)
    if given.shape != shape:
        raise ValueError(f"a {what} of shape {given.shape} does not fit these parameters, "
                         f"which tell {shape[0]} situations and {shape[1]} actions apart")
    return given


def _mirror(p: Parameters) -> tuple[np.ndarray, np.ndarray]:
    """Each situation's and each action's mirror image (left for right): the indices of
    the situation with the sectors' levels swapped and the bearing negated, and of the
    action turning the other way. ValueError if the sectors or actions have none."""
    # the Pioneer ring mirrored: front 0..7 (left to right), rear 8..15 (right to left)
    flip = {i: 7 - i if i < 8 else 23 - i for i in range(16)}
    sectors = [frozenset(s) for s in p.sectors]
    actions = list(p.actions)
    try:
        sector_mirror = [sectors.index(frozenset(flip[i] for i in s)) for s in sectors]
        action_mirror = np.array([actions.index((v, -w)) for v, w in actions])
    except ValueError:
        raise ValueError("mirror learning needs sectors and actions that mirror each "
                         "other (left for right); set the parameter mirror false") from None
    situations = np.arange(p.states)
    codes, bearings = np.divmod(situations, p.bearings)
    weights = p.levels ** np.arange(len(sectors))
    levels = codes[:, None] // weights % p.levels         # (situations, sectors)
    mirrored = levels[:, sector_mirror] @ weights          # a mirror is its own inverse
    return mirrored * p.bearings + (-bearings) % p.bearings, action_mirror


def _frozen(value: Any) -> Any:
    """Lists, at any depth, as tuples (so that parameters read from a file compare and
    hash like the defaults)."""
    return tuple(_frozen(v) for v in value) if isinstance(value, list | tuple) else value


class PolicyLearner(Module):
    """Learns to reach ``goals`` while avoiding obstacles, one decision every
    ``decision_s`` of the world's time.

    Feed it the robot's ``sonar``, its localization ``pose`` and the world's ``clock``
    (a ``RobotDriver``'s ``sonar``, ``gps`` and ``clock``); link ``command`` to the
    driver's. It decides on the reading nearest ``decision_s`` after its last decision
    (the first one less than half a reading interval before it), by the world's clock,
    not the wall clock: against a world served in lock-step (the driver's
    ``lockstep_s`` equal to ``decision_s``) every reading is a decision and the world
    moves only as fast as the learner decides; against a robot in real time it decides
    every ``decision_s``. ``episode`` gets a dict at the end of every episode: index,
    outcome, success, steps, seconds (world time), goal, epsilon, at (``time.time()``),
    clock (the world's time at its end). Set ``learning`` False to run the learnt
    policy greedily with no updates.

    After a migration the episode under way goes on toward its goal; the one
    transition that spans the move is not learnt from. Moved to another robot, it
    reads another world's clock: a clock that goes back, or jumps by more than
    ``Parameters.max_gap``, carries the episode under way over to it.
    """

    sonar = Input(np.ndarray, shape=(16,), dtype="float64")
    pose = Input(np.ndarray, shape=(3,), dtype="float64")
    clock = Input(float)             # the world's time of the readings (s)
    command = Output(np.ndarray, shape=(2,), dtype="float64")
    episode = Output(dict)
    decision_s = 0.2                 # world s between decisions
    goals: list[list[float]] = []    # [[x, y], ...] in the world's frame, visited in turn
    learning = True
    parameters: dict[str, Any] = {}  # overrides of ``Parameters``' defaults
    seed = 0
    decided_at = -math.inf           # world time of the last decision
    read_at = -math.inf              # world time of the last reading
    # what it has learnt and where it is (see ``ReactiveLearner``)
    q = np.zeros((0, 0))
    trace = np.zeros((0, 0))
    epsilon = EPSILON
    goal_index = 0
    episodes: list[tuple[str, int, float]] = []
    episode_count = 0
    underway: dict[str, Any] = {}
    recovery: dict[str, Any] = {}
    rng_state: dict[str, Any] = {}

    def setup(self) -> None:
        # made here, goals, parameters and table are checked before the first decision
        vars(self).update(self._learner().state())

    def on_input(self, port: InputPort) -> None:
        if port.name != "clock" or not (self.sonar.has_value and self.pose.has_value):
            return
        now = float(port.read())
        # Readings come every ``interval`` with jitter: waiting for one at least
        # ``decision_s`` on would let a reading a millisecond early pass, and the
        # decision wait a whole interval more.
        interval = now - self.read_at
        self.read_at = now
        early = interval / 2 if 0 < interval <= self.decision_s else 0.0
        if self.decided_at <= now < self.decided_at + self.decision_s - early - 1e-6:
            return                           # not yet (a clock that went back: another world)
        # Rebuilt from the state at every decision (tens of microseconds), so that state
        # set while running (an agent turning ``learning`` off, a new ``epsilon`` or
        # ``goals``) counts from the next decision.
        learner = self._learner()
        self._carry_over(learner, now)
        command, finished = learner.decide(self.sonar.read(), self.pose.read(), now,
                                           learn=self.learning)
        vars(self).update(learner.state())
        self.decided_at = now
        self.command.write(command)
        if finished is not None:
            self.episode.write({**asdict(finished), "success": finished.outcome == SUCCESS,
                                "epsilon": self.epsilon, "at": time.time(), "clock": now})

    def _carry_over(self, learner: ReactiveLearner, now: float) -> None:
        """If the clock is another world's, move the episode under way (and a recovery
        manoeuvre) onto it, and learn nothing from the transition across. The gap is
        from the last decision (a recovery has no episode under way: measured from the
        episode, a robot moved while recovering turned until the clock caught up)."""
        gap = now - self.decided_at
        if not self.decided_at or 0 <= gap <= learner.parameters.max_gap:
            return
        underway = learner.underway
        if underway:
            underway.update(started=underway["started"] + gap, at=now, state=-1)
        for key in ("since", "until"):
            if key in learner.recovery:
                learner.recovery[key] += gap

    @classmethod
    def state_problems(cls, state: dict[str, Any]) -> list[str]:
        """Goals, parameters or a table (or other memory) the learner could not decide by
        (taken, they failed every decision from then on): the learner is made of the
        state, when it gives all it is made of, and what it refuses is said."""
        problems = super().state_problems(state)
        if set(_LEARNER_FIELDS) <= set(state):
            try:
                _learner_of(state)
            except (TypeError, ValueError) as exc:
                problems.append(f"{cls.__name__}'s learner cannot be made of its state: {exc}")
        return problems

    def teardown(self) -> None:
        self.command.write(np.zeros(2))      # the robot stands while the learner is away

    def _learner(self) -> ReactiveLearner:
        return _learner_of(self.get_state())


_LEARNER_FIELDS = ("goals", "parameters", "seed", "q", "trace", "epsilon", "goal_index",
                   "episodes", "episode_count", "underway", "recovery", "rng_state")


def _learner_of(state: dict[str, Any]) -> ReactiveLearner:
    """The learner a ``PolicyLearner`` of ``state`` decides by; ValueError for goals,
    parameters or a table it could not decide by."""
    return ReactiveLearner(
        state["goals"], Parameters.of(state["parameters"]), seed=state["seed"], q=state["q"],
        trace=state["trace"], epsilon=state["epsilon"], goal_index=state["goal_index"],
        episodes=state["episodes"], episode_count=state["episode_count"],
        underway=state["underway"], recovery=state["recovery"],
        rng_state=state["rng_state"])
