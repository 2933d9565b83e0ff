"""``QLearning``: a junction controller that learns which green to show by Q-learning
on its queues, its table in its state.

The state it sees is the green shown, how long it has been shown (three bands) and
the halting vehicles each green would serve (six bands); its actions are the greens.
It decides every ``decision_s`` once the minimum green has passed, and learns from
the next decision: the reward is minus the vehicles halting then. The table
(``table``: state key -> one value per green) is the module's state, so it moves and
swaps with the module; a controller swapped in with an empty table takes the one
trained offline for the bundled networks (``table_file``, made by
``python -m agents.traffic.training``). States the table has never seen get the
longest-queue choice, a safe default.
"""

from __future__ import annotations

import json
import random
from pathlib import Path
from typing import Any

from agents.traffic.controller import JunctionController, in_transition, served_queue
from agents.traffic.messages import JunctionReading

TRAINED = Path(__file__).with_name("q_table.json")
QUEUE_BANDS = (0, 1, 3, 6, 10, 16)          # a band starts at each of these
ELAPSED_BANDS = (0.0, 15.0, 35.0)


def _band(value: float, starts: tuple[float, ...]) -> int:
    return sum(value >= start for start in starts) - 1


def state_key(reading: JunctionReading) -> str:
    """What the learner sees of ``reading``, as the table's key."""
    greens = len(reading.layout.greens)
    queues = ".".join(str(_band(served_queue(reading, g), QUEUE_BANDS)) for g in range(greens))
    return f"{greens}|{reading.green}|{_band(reading.elapsed, ELAPSED_BANDS)}|{queues}"


class QLearning(JunctionController):
    """Q-learning on banded queues and the phase shown; the table is its state."""

    table: dict[str, list[float]] = {}
    table_file = str(TRAINED)       # the table to start from when ``table`` is empty
    learning = True                 # False: act on the table, change nothing
    epsilon = 0.0                   # exploration (training uses more)
    alpha = 0.1
    gamma = 0.8
    min_green_s = 8.0
    decision_s = 4.0
    seed = 0
    updates = 0

    def setup(self) -> None:
        super().setup()
        if not self.table and self.table_file and Path(self.table_file).is_file():
            self.table = json.loads(Path(self.table_file).read_text())["table"]
        else:
            self.table = dict(self.table)       # its own, not the class's
        self._random = random.Random(self.seed)
        self._pending: tuple[str, int] | None = None   # the decision not yet learnt from
        self._decided_at = -1e9

    def choose(self, reading: JunctionReading) -> int:
        if in_transition(reading) or reading.elapsed + 1e-9 < self.min_green_s:
            return reading.target
        if reading.time - self._decided_at + 1e-9 < self.decision_s:
            return reading.green
        key = state_key(reading)
        if self.learning and self._pending is not None:
            self._learn(*self._pending, -float(sum(reading.queues.values())), key)
        greens = len(reading.layout.greens)
        values = self.table.get(key)
        if self.epsilon and self._random.random() < self.epsilon:
            action = self._random.randrange(greens)
        elif values is None:
            queues = [served_queue(reading, g) for g in range(greens)]
            action = reading.green if queues[reading.green] >= max(queues) else \
                queues.index(max(queues))
        else:
            best = max(values)
            action = reading.green if values[reading.green] >= best else values.index(best)
        self._pending = (key, action)
        self._decided_at = reading.time
        return action

    def _learn(self, key: str, action: int, reward: float, next_key: str) -> None:
        greens = int(key.partition("|")[0])
        values = self.table.setdefault(key, [0.0] * greens)
        following = self.table.get(next_key)
        future = max(following) if following else 0.0
        values[action] += self.alpha * (reward + self.gamma * future - values[action])
        self.updates += 1


def save_table(table: dict[str, Any], path: Path, how: dict[str, Any]) -> Path:
    """Write ``table`` with how it was made (``how``), sorted so that the same training
    writes the same file."""
    rounded = {key: [round(v, 4) for v in values] for key, values in sorted(table.items())}
    path.write_text(json.dumps({"how": how, "table": rounded}, indent=0, sort_keys=True))
    return path
