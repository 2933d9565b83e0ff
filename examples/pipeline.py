"""The pipeline of the specification: a ``Ticker`` counting into a ``Scale``.

``FastScale`` does what ``Scale`` does with the same ports and state, so a
running system can swap one for the other (``run.swap("scale",
"examples.pipeline:FastScale")``) without losing the gain it was tuned to.
"""

from __future__ import annotations

from pb3a.model.module import Module
from pb3a.model.ports import Input, InputPort, Output


class Scale(Module):
    """Multiplies every value on ``x`` by ``gain`` and writes it on ``y``."""

    x = Input(float)
    y = Output(float)
    gain = 2.0

    def on_input(self, port: InputPort) -> None:
        self.y.write(self.x.read() * self.gain)


class FastScale(Scale):
    """``Scale`` with the same ports and state; a call that finds no value does nothing."""

    def on_input(self, port: InputPort) -> None:
        value = self.x.read(default=None)
        if value is not None:
            self.y.write(float(value) * float(self.gain))


class Ticker(Module):
    """Counts up at each step (one every ``period`` seconds, plus the step's own time)
    and writes the count on ``out``."""

    out = Output(int)
    period = 0.01
    count = 0

    def step(self) -> None:
        self.count += 1
        self.out.write(self.count)
