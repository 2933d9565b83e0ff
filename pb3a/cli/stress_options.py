"""What a stress run is asked to do (``StressOptions``), and how the command line reads
its option values (``--load``, ``--cut-node``, ``--kill-among``): apart from
``pb3a.cli.stress``, which does it, so that reading the command line imports none of
the runtime that the run needs."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field

from pb3a.errors import MOST_SECONDS


@dataclass(frozen=True)
class Window:
    """From ``start`` seconds into the run, for ``seconds`` (None: to the end)."""

    start: float = 0.0
    seconds: float | None = None

    def end(self, run_s: float) -> float:
        return run_s if self.seconds is None else min(run_s, self.start + self.seconds)


@dataclass(frozen=True)
class StressOptions:
    """What to do to the system, and how often to look."""

    seconds: float
    loads: list[tuple[dict[int, float], Window]] = field(default_factory=list)
    kill_every: float | None = None
    kill_among: frozenset[str] = frozenset()         # empty: every module of the system
    migrate_every: float | None = None
    migrate_among: frozenset[str] = frozenset()      # empty: every module of the system
    cuts: list[tuple[str, Window]] = field(default_factory=list)
    sample_s: float = 1.0
    seed: int | None = None


def parse_levels(text: str) -> dict[int, float]:
    """``"0,1:80"`` (CPUs, a colon, a percent) as ``{0: 80.0, 1: 80.0}``; ValueError
    saying what is wrong (whether this machine has those CPUs, ``CPULoad`` says)."""
    cpus, _, level = text.partition(":")
    try:
        return dict.fromkeys((int(cpu) for cpu in cpus.split(",")), float(level))
    except ValueError:
        raise ValueError(f"{text!r} is not CPUS:PERCENT (e.g. 0,1:80 loads CPUs 0 and 1 "
                         "to 80 %)") from None


def load(text: str) -> tuple[dict[int, float], Window]:
    """``--load CPUS:PERCENT[@T[+D]]``: the levels per CPU, and when."""
    levels, at, when = text.partition("@")
    try:
        parsed = parse_levels(levels)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return parsed, window(when, text) if at else Window()


def cut(text: str) -> tuple[str, Window]:
    """``--cut-node NAME@T[+D]``: the node, and when."""
    node, at, when = text.partition("@")
    if not node or not at:
        raise argparse.ArgumentTypeError(f"{text!r} is not NAME@T[+D] (e.g. b@10+5 cuts node b "
                                         "at 10 s for 5 s)")
    return node, window(when, text)


def names(text: str) -> frozenset[str]:
    """``M1,M2``: module names."""
    return frozenset(name.strip() for name in text.split(",") if name.strip())


def window(text: str, what: str) -> Window:
    """``T`` or ``T+D`` (seconds) as a Window; ``what`` is the whole value, named in
    the error."""
    start, plus, length = text.partition("+")
    try:
        span = Window(float(start), float(length) if plus else None)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what}: {text!r} is not T or T+D (seconds)") from None
    if not (0 <= span.start <= MOST_SECONDS) or (
            span.seconds is not None and not 0 < span.seconds <= MOST_SECONDS):
        raise argparse.ArgumentTypeError(f"{what}: {text!r}: T must be 0 or more and D more "
                                         "than 0")
    return span
