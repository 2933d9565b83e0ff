"""Modules the benchmarks launch. Importable (not ``__main__``), so that worker
processes load them by reference, as they would a user's modules.

Benchmarks drive them through state: ``run.set_state(...)`` to start a burst or a
recording, ``run.state(...)`` to read the figures back.
"""

from __future__ import annotations

import math
import time

import numpy as np

from pb3a import Input, InputPort, Module, Output, RuntimeTimeout

ARRAY_SHAPE = (131072,)        # 1 MiB of float64
IDLE_S = 0.02                  # how long an idle burst writer sleeps inside step()


class IntBurst(Module):
    """Writes ``count`` values as fast as it can each time ``go`` is raised, then idles.

    ``started`` and ``finished`` are ``time.monotonic()`` just before the burst's first
    write and just after its last.
    """

    out = Output(int)
    period = 0.0
    count = 1000
    batch = 0       # 0: one write() per value; N: write_many() of N values at a time
    go = 0          # bursts asked for (the benchmark raises it)
    done = 0        # bursts written
    started = math.nan
    finished = math.nan

    def step(self) -> None:
        if self.done >= self.go:
            time.sleep(IDLE_S)     # period 0 would otherwise spin a core between bursts
            return
        write, value, batch = self.out.write, self._value, self.batch
        self.started = time.monotonic()
        if batch:
            for first in range(0, self.count, batch):
                self.out.write_many([value(i) for i in range(first, min(first + batch,
                                                                          self.count))])
        else:
            for i in range(self.count):
                write(value(i))
        self.finished = time.monotonic()
        self.done += 1

    def _value(self, i: int) -> object:
        return i


class ArrayBurst(IntBurst):
    """``IntBurst`` writing the same 1 MiB float64 array every time."""

    out = Output(np.ndarray, shape=ARRAY_SHAPE, dtype="float64")

    def setup(self) -> None:
        self._payload = np.ones(ARRAY_SHAPE)

    def _value(self, i: int) -> object:
        return self._payload


class IntCounter(Module):
    """Counts the values it receives and records when the first and last arrived.

    ``drops`` is the input's cumulative drop counter as of the last value; ``views``
    counts values that arrived as read-only views not owning their data (arrays).
    """

    x = Input(int, policy="queue:100000")
    count = 0
    drops = 0
    views = 0
    first = math.nan
    last = math.nan

    def on_input(self, port: InputPort) -> None:
        port.read()
        self._arrived(port)

    def _arrived(self, port: InputPort) -> None:
        now = time.monotonic()
        if not self.count:
            self.first = now
        self.last = now
        self.count += 1
        self.drops = port.drops


class ArrayCounter(IntCounter):
    """``IntCounter`` for 1 MiB arrays: reads one element of each, never copies it."""

    x = Input(np.ndarray, shape=ARRAY_SHAPE, dtype="float64", policy="queue:8")
    touched = 0.0

    def on_input(self, port: InputPort) -> None:
        array = port.read()
        self.touched = float(array[0])
        if not array.flags.writeable and not array.flags.owndata:
            self.views += 1
        del array                  # hand the ring slot back at once
        self._arrived(port)


class Clock(Module):
    """Writes ``time.monotonic()`` every ``period`` seconds (threaded)."""

    out = Output(float)
    period = 0.001

    def step(self) -> None:
        self.out.write(time.monotonic())


class LatencyProbe(Module):
    """Event-driven: while ``recording``, stores ``now - value`` (seconds), up to ``limit``."""

    x = Input(float, policy="queue:64")
    recording = False
    limit = 3000
    samples: list[float] = []

    def on_input(self, port: InputPort) -> None:
        sent = port.read()
        now = time.monotonic()
        if self.recording and len(self.samples) < self.limit:
            self.samples.append(now - sent)


class Gain(Module):
    """Event-driven: writes ``x * gain`` on ``y``."""

    x = Input(float)
    y = Output(float)
    gain = 1.0

    def on_input(self, port: InputPort) -> None:
        self.y.write(port.read() * self.gain)


class MigrationRelay(Module):
    """Event-driven: passes every value on (the module the migration bench moves)."""

    x = Input(float, policy="queue:10000")
    out = Output(float)
    relayed = 0

    def on_input(self, port: InputPort) -> None:
        self.out.write(port.read())
        self.relayed += 1


BIG_STATE_BYTES = 10 * 2**20    # the state the migration bench moves (10 MiB of float64)


class BigState(Module):
    """Event-driven, with 10 MiB of numpy state: each value is stored in ``field`` and
    passed on (the module the migration bench moves to measure a big state)."""

    x = Input(float, policy="queue:10000")
    out = Output(float)
    field: np.ndarray | None = None
    relayed = 0

    def setup(self) -> None:
        if self.field is None:          # (a moved module keeps the field it brought)
            self.field = np.arange(BIG_STATE_BYTES // 8, dtype=np.float64)

    def on_input(self, port: InputPort) -> None:
        value = port.read()
        self.field[self.relayed % self.field.size] = value
        self.out.write(value)
        self.relayed += 1


class OrderedReader(Module):
    """Counts values and checks they only grow (``Clock`` writes increasing times)."""

    x = Input(float, policy="queue:100000")
    count = 0
    last = -1.0
    out_of_order = 0
    duplicates = 0

    def on_input(self, port: InputPort) -> None:
        value = port.read()
        if value == self.last:
            self.duplicates += 1
        elif value < self.last:
            self.out_of_order += 1
        self.last = value
        self.count += 1


class SequenceSource(Module):
    """Writes the integers 0, 1, 2 ... in batches of ``batch`` per step while
    ``sending``; ``sent`` is how many so far (the soak's rate: batch / period)."""

    out = Output(int)
    period = 0.01
    batch = 33
    sending = True
    sent = 0

    def step(self) -> None:
        if self.sending:
            self.out.write_many(range(self.sent, self.sent + self.batch))
            self.sent += self.batch


class SequenceChecker(Module):
    """Checks a ``SequenceSource``'s integers arrive once each and in order: counts
    those received, those seen again or out of order, and those skipped."""

    x = Input(int, policy="queue:100000")
    received = 0
    expected = 0
    repeated = 0            # a value below the next expected one: duplicated or reordered
    skipped = 0             # values never seen: lost

    def on_input(self, port: InputPort) -> None:
        for value in port.read_all():
            self.received += 1
            if value == self.expected:
                self.expected += 1
            elif value < self.expected:
                self.repeated += 1
            else:
                self.skipped += value - self.expected
                self.expected = value + 1


class Camera(Module):
    """Writes a ``size``-byte frame every ``period``, numbered, with when it was written
    (unix seconds) in its first 16 bytes; ``sent`` counts the frames that went, and
    ``timeouts`` the writes a lossless link held back past the writer's timeout."""

    out = Output(np.ndarray)
    period = 0.1
    size = 1 << 20
    sent = 0
    timeouts = 0

    def step(self) -> None:
        frame = np.zeros(self.size, np.uint8)
        frame[:16].view(np.float64)[:] = (self.sent + 1, time.time())
        try:
            self.out.write(frame)
        except RuntimeTimeout:
            self.timeouts += 1
            return
        self.sent += 1


class Viewer(Module):
    """Reads a ``Camera``'s frames: how many came, how many it never saw (``skipped``),
    any that came again or out of order, and the oldest a frame was on arrival."""

    x = Input(np.ndarray, policy="queue:8")
    received = 0
    last = 0
    skipped = 0
    repeated = 0
    max_age_s = 0.0

    def on_input(self, port: InputPort) -> None:
        number, written = port.read()[:16].view(np.float64)
        if number <= self.last:
            self.repeated += 1
            return
        self.skipped += int(number) - self.last - 1
        self.last = int(number)
        self.received += 1
        self.max_age_s = max(self.max_age_s, time.time() - written)
