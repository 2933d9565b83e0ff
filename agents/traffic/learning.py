"""``QLearning``: a junction controller that learns when to end a green, by
Q-learning, its table in its state.

Each second of green after the minimum it chooses between holding the green and
giving way to the busiest red (the two actions of an actuated controller), seeing
how long the green has been shown, the vehicles approaching its stop lines, those
halting on its lanes and the vehicles on the red side, each in a few bands. The
reward is minus the vehicles halting at the junction a second later. The table
(``table``: state key -> [value of holding, value of giving way]) is the module's
state, so it moves and swaps with the module. One swapped in with an empty table
takes the one trained offline (``table_file``, made by ``python -m
agents.traffic.training``). Where its table cannot tell the actions apart (a state
never seen, or seen once), it acts as ``GapOut``.
"""

from __future__ import annotations

import json
import random
from pathlib import Path
from typing import Any

from agents.limits import GREEN, SECONDS, SHARE, finite, whole
from agents.traffic.controller import JunctionController, busiest_red, in_transition, served
from agents.traffic.messages import JunctionReading
from pb3a.model.module import StateRefused, reflective

TRAINED = Path(__file__).with_name("q_table.json")
HOLD, GIVE_WAY = 0, 1
ELAPSED_BANDS = (0.0, 10.0, 20.0, 30.0, 45.0)      # a band starts at each of these
COMING_BANDS = (0, 1, 2, 4)
COUNT_BANDS = (0, 1, 3, 6, 10, 16)


def _band(value: float, starts: tuple[float, ...]) -> int:
    return sum(value >= start for start in starts) - 1


def state_key(reading: JunctionReading) -> str:
    """What the learner sees of ``reading``, as the table's key."""
    coming = served(reading, reading.green, reading.approaching)
    halting = served(reading, reading.green, reading.queues)
    red, _ = busiest_red(reading, reading.vehicles)
    return (f"{_band(reading.elapsed, ELAPSED_BANDS)}|{_band(coming, COMING_BANDS)}|"
            f"{_band(halting, COUNT_BANDS)}|{_band(red, COUNT_BANDS)}")


class QLearning(JunctionController):
    """Q-learning of when to give way; the table is its state."""

    table: dict[str, list[float]] = {}
    table_file = str(TRAINED)       # the table to start from when ``table`` is empty
    learning = True                 # False: act on the table, change nothing
    epsilon = 0.0                   # exploration (training uses more)
    alpha = 0.05
    gamma = 0.95
    min_green_s = 5.0
    max_green_s = 60.0
    seed = 0
    updates = 0
    _limits = {"epsilon": SHARE, "alpha": SHARE, "gamma": SHARE, "min_green_s": SECONDS,
              "max_green_s": GREEN}

    def setup(self) -> None:
        super().setup()
        if not self.table and self.table_file and Path(self.table_file).is_file():
            self.table = read_table(self.table_file, type(self).__name__)
        elif self.table is type(self).table:
            self.table = {}                     # its own, not the class's
        self._random = random.Random(self.seed)
        self._pending: tuple[str, int] | None = None   # the decision not yet learnt from
        self._accrued, self._seconds = 0.0, 0           # its cost so far, and how long

    @reflective                 # (it takes the fields Module's does: they are checked)
    def set_state(self, state: dict[str, Any]) -> None:
        """Set state (what ``state_problems`` refuses is refused, nothing set); a ``seed``
        set while it runs draws its explorations from then on. A ``table_file`` given
        without a table (or with an empty one) is read now, so the learner set up already
        (running, or swapped in by a performance agent, which gives the state after the
        swap's setup) goes by it; a file that holds no table is refused, nothing set."""
        loaded = None
        if state.get("table_file") and not state.get("table"):
            try:
                loaded = read_table(state["table_file"], type(self).__name__)
            except ValueError as exc:   # (a refusal, not the worker's failure)
                raise StateRefused([str(exc)]) from None
        super().set_state(state)
        if loaded is not None:
            self.table = loaded
            if "_random" in vars(self):
                self._pending = None            # (a decision taken on another table)
        if "seed" in state and "_random" in vars(self):
            self._random = random.Random(self.seed)

    @classmethod
    def state_problems(cls, state: dict[str, Any]) -> list[str]:
        """What ``JunctionController`` refuses, and a table that is not one of state key
        -> [value of holding, value of giving way] (two finite numbers), a ``learning``
        that is not true or false, a ``seed`` that is not a whole number, a
        ``table_file`` that is not a path (a file that holds no table is refused as it is
        read: at setup, or by ``set_state``)."""
        problems = super().state_problems(state)
        wrong = table_problems(state["table"]) if "table" in state else []
        if "learning" in state and not isinstance(state["learning"], bool):
            wrong.append(f"learning must be true or false, got {state['learning']!r}")
        if "seed" in state and not whole(state["seed"]):
            wrong.append(f"seed must be a whole number, 0 or more, got {state['seed']!r}")
        if "table_file" in state and not isinstance(state["table_file"], str):
            wrong.append(f"table_file must be the path of a table's file, or '' for none, "
                         f"got {state['table_file']!r}")
        return problems + [f"{cls.__name__}'s {problem}" for problem in wrong]

    def choose(self, reading: JunctionReading) -> int:
        if len(reading.layout.greens) == 1:
            return 0
        if self._pending is not None:           # the cost of the last decision, so far
            self._accrued -= self.gamma ** self._seconds * sum(reading.queues.values())
            self._seconds += 1
        if in_transition(reading) or reading.elapsed + 1e-9 < self.min_green_s:
            return reading.target
        key = state_key(reading)
        if self.learning and self._pending is not None:
            self._learn(key)
        red, green = busiest_red(reading, reading.vehicles)
        if red == 0:
            action = HOLD
        elif reading.elapsed + 1e-9 >= self.max_green_s:
            action = GIVE_WAY
        elif self.epsilon and self._random.random() < self.epsilon:
            action = self._random.randrange(2)
        elif key in self.table and self.table[key][HOLD] != self.table[key][GIVE_WAY]:
            values = self.table[key]
            action = GIVE_WAY if values[GIVE_WAY] > values[HOLD] else HOLD
        else:                                   # nothing learnt to tell: as GapOut would
            action = HOLD if served(reading, reading.green, reading.approaching) else GIVE_WAY
        self._pending, self._accrued, self._seconds = (key, action), 0.0, 0
        return reading.green if action == HOLD else green

    def _learn(self, next_key: str) -> None:
        """Update the value of the pending decision: the discounted halting since it
        was taken, then the best value of the state it led to."""
        key, action = self._pending
        following = self.table.get(next_key)
        future = max(following) if following else 0.0
        target = self._accrued + self.gamma ** self._seconds * future
        values = self.table.get(key)
        if values is None:      # both actions start at the first value seen, so an
            self.table[key] = [target, target]    # untried one does not look better
        else:
            values[action] += self.alpha * (target - values[action])
        self.updates += 1


def table_problems(table: Any) -> list[str]:
    """What keeps ``table`` from being a learner's: not a table of state key -> [value of
    holding, value of giving way], two finite numbers (the first such entry named)."""
    if not isinstance(table, dict):
        return [f"table must be a table of state key = [value of holding, value of giving "
                f"way], got {table!r:.80}"]
    for key, values in table.items():
        if not (isinstance(key, str) and isinstance(values, (list, tuple))
                and len(values) == 2 and all(finite(v) for v in values)):
            return [f"table[{key!r}] must be [value of holding, value of giving way], two "
                    f"finite numbers, got {values!r:.80}"]
    return []


def read_table(path: str | Path, who: str = "QLearning") -> dict[str, list[float]]:
    """The table kept in the file at ``path`` (as ``save_table`` writes it); ValueError
    naming the file and what is wrong with it."""
    try:
        table = json.loads(Path(path).read_text())["table"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        reason = f"no key {exc}" if isinstance(exc, KeyError) else (
            f"{type(exc).__name__}: {exc}")
        raise ValueError(f"{who}: table_file {path}: it holds no table ({reason})") from None
    problems = table_problems(table)
    if problems:
        raise ValueError(f"{who}: table_file {path}: {problems[0]}")
    return {key: [float(v) for v in values] for key, values in table.items()}


def save_table(table: dict[str, Any], path: Path, how: dict[str, Any]) -> Path:
    """Write ``table`` with how it was made (``how``), sorted so that the same training
    writes the same file."""
    rounded = {key: [round(v, 4) for v in values] for key, values in sorted(table.items())}
    path.write_text(json.dumps({"how": how, "table": rounded}, indent=0, sort_keys=True))
    return path
