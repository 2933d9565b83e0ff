"""Types of the commands' options (seconds, seeds, NAME=VALUE pairs), for ``argparse``: a value
out of range is refused as the command line is read, with the usage and a sentence,
never accepted to fail later (a NaN run length ran for no time; an infinite timeout
overflowed a clock, with a traceback; a seed of -1 ended in numpy's)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

from pb3a.errors import MOST_SECONDS


def seconds(text: str) -> float:
    """A finite number of seconds above 0 (how long to run, how often)."""
    return _seconds(text, "a number of seconds above 0", lambda value: value > 0)


def wait_seconds(text: str) -> float:
    """A finite number of seconds, 0 or more (how long to wait for an answer)."""
    return _seconds(text, "a number of seconds, 0 or more", lambda value: value >= 0)


def seed(text: str, most: int | None = None) -> int:
    """A random seed: a whole number, 0 or more (numpy takes no other: -1 ended in its
    traceback, from a world server's process), and at most ``most``."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0 or (most is not None and value > most):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a seed: give a whole number, 0 or more"
            + ("" if most is None else f" and at most {most}"))
    return value


def port(text: str) -> int:
    """A TCP port to listen on: 1 to 65535, or 0 for a free one."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a port: give a whole number from 1 to 65535 (0: a free one)")
    return value


def percent(text: str) -> float:
    """A finite percentage, 0 or more (a limit: above 100 never reached). A NaN limit
    was taken, and no load is above NaN: it switched the node's CPU check off."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"{text!r} is not a percentage, 0 or more")
    return value


def mebibytes(text: str) -> int:
    """A whole number of MiB, 0 or more (a negative one switched a check off too)."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number of MiB, 0 or more")
    return value


def state_pair(text: str) -> str:
    """A ``NAME=VALUE`` pair of ``--state``, which takes every word up to the next option:
    one without "=" is the command's ADDR or another positional, given after it."""
    if "=" not in text:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not NAME=VALUE: --state takes the words after it up to the next "
            "option, so give it after the command's ADDR, NAME and class")
    return text


def _seconds(text: str, words: str, ok: Callable[[float], bool]) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and ok(value) and value <= MOST_SECONDS):
        raise argparse.ArgumentTypeError(f"{text!r} is not {words} (at most {MOST_SECONDS:g})")
    return value
