"""Modules for the manager's browser tests and its screenshots: a sensor whose level
the State Editor changes, a probe that shows what reaches it (a plot and a gauge),
and a mapper that builds an occupancy grid (a live image) while it runs."""

from __future__ import annotations

import math
import os
import time

import numpy as np

from pb3a.model.module import Module
from pb3a.model.ports import Input, InputPort, Output


class Sensor(Module):
    """Writes ``level`` plus a small ripple every ``period`` seconds on ``out``; gives
    itself ``pace`` as its period once it is set (``self.period = pace``)."""

    out = Output(float)
    period = 0.02
    level = 1.0
    ripple = 0.0
    label = "sensor"
    steps = 0
    pace = 0.0

    def step(self) -> None:
        self.steps += 1
        self.out.write(self.level + self.ripple * math.sin(self.steps / 8))
        if self.pace:
            self.period, self.pace = self.pace, 0.0


class Probe(Module):
    """Keeps the last value that reached ``x`` and the last few, for the State Editor."""

    x = Input(float, policy="queue:16")
    last = 0.0
    seen = 0
    recent: list = []
    load = 0.0
    hold = ""                       # a file: while it exists, each call waits (up to 30 s)
    displays = {"last": "plot", "load": ("gauge", 0.0, 10.0)}

    def on_input(self, port: InputPort) -> None:
        until = time.monotonic() + 30.0
        while self.hold and os.path.exists(self.hold) and time.monotonic() < until:
            time.sleep(0.01)
        self.last = float(port.read())
        self.seen += 1
        self.load = min(abs(self.last), 10.0)
        self.recent = [*self.recent[-4:], round(self.last, 3)]


class Mapper(Module):
    """Walks a grid, marking the cells it visits: an occupancy grid built while it runs."""

    speed = Input(float)
    coverage = Output(float)
    period = 0.05
    grid = np.zeros((40, 56))
    pose = np.array([20.0, 28.0])
    enabled = True
    settings: dict = {"decay": 0.995, "brush": 2, "mode": "explore"}
    displays = {"grid": "image", "coverage_now": "plot"}
    coverage_now = 0.0
    t = 0

    def step(self) -> None:
        if not self.enabled:
            return
        self.t += 1
        t = self.t
        rows, cols = self.grid.shape
        self.pose = np.array([rows / 2 + (rows / 2 - 3) * math.sin(t / 23),
                              cols / 2 + (cols / 2 - 3) * math.sin(t / 17 + 1)])
        r, c = (int(v) for v in self.pose)
        brush = int(self.settings.get("brush", 2))
        self.grid *= float(self.settings.get("decay", 1.0))
        self.grid[max(r - brush, 0):r + brush + 1, max(c - brush, 0):c + brush + 1] = 1.0
        self.coverage_now = float((self.grid > 0.5).mean())
        self.coverage.write(self.coverage_now)


class Holder(Module):
    """State of the kinds the State Editor must keep as they are: a dict of floats, a
    list of float pairs, small and narrow number arrays, a grid whose unreached cells
    hold the largest float (a common sentinel)."""

    settings: dict = {"decay": 1.0, "brush": 2.5}
    waypoints: list = [(0.0, 0.0), (1.0, 2.0)]
    small = np.zeros(3, dtype=np.int8)
    narrow = np.zeros(2, dtype=np.float32)
    level = np.float32(1.0)
    cost = np.full((4, 4), np.finfo(np.float64).max)


class Controller(Module):
    """A PID controller whose gains are tuned while it runs: settings on the class (kp,
    ki, kd, limits, mode); read-outs it makes itself (``error``, made in setup, and the
    array ``trace``), which a document cannot hold."""

    measured = Input(float)
    command = Output(float)
    period = 0.02
    kp = 1.0
    ki = 0.0
    kd = 0.0
    limits = (-1.0, 1.0)
    mode = "auto"
    trace = np.zeros(4)

    def setup(self) -> None:
        self.error = 0.0
        self.integral = 0.0

    def step(self) -> None:
        self.error = 1.0 - self.error * 0.5
        self.integral += self.error * self.period
        low, high = self.limits
        self.command.write(min(max(self.kp * self.error + self.ki * self.integral, low), high))


class FileNamed(Module):
    """Holds a file name that is not UTF-8 (Latin-1 on Linux), as ``os.fsdecode`` gives
    it: a string with a lone surrogate, which UTF-8 cannot encode."""

    last_file = os.fsdecode(b"caf\xe9.txt")
    level = 0.5


class Weights(Module):
    """A small float array of more digits than a cell shows, and a NaN."""

    weights = np.array([20.123456789, 0.000123456789, 123456.789, np.nan])


class Flags(Module):
    """A small array of flags."""

    flags = np.array([True, False, True, False, False])


class Paced(Module):
    """Steps every 20 ms at a fixed rate, its class's own, each step taking ``work``
    seconds: with more than a period of work the periods it is late by are skipped and
    counted as its overruns."""

    period = 0.02
    fixed_rate = True
    work = 0.0

    def step(self) -> None:
        time.sleep(self.work)
