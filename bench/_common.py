"""What every benchmark script shares: repetition statistics, bounded waits, forked
children, the machine (its steal time, load and the pb3a commit measured), and printing
one JSON object.

Nothing here asserts: a benchmark reports what it saw, and a failure (a timeout, a
child that died) ends up as an ``"error"`` entry in the JSON it prints.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import platform
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import psutil

_fork = multiprocessing.get_context("fork")


def summary(values: Sequence[float], digits: int = 3) -> dict[str, float | int]:
    """Median, min and max of the repetitions (and how many there were)."""
    if not values:
        return {"median": math.nan, "min": math.nan, "max": math.nan, "n": 0}
    return {"median": round(statistics.median(values), digits),
            "min": round(min(values), digits), "max": round(max(values), digits),
            "n": len(values)}


def percentile(values: Sequence[float], q: float) -> float:
    """The ``q``-th percentile (0-100), linearly interpolated; NaN for no values."""
    if not values:
        return math.nan
    ordered = sorted(values)
    rank = (len(ordered) - 1) * q / 100.0
    low = math.floor(rank)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (rank - low)


def wait_for(check: Callable[[], Any], timeout: float, what: str, poll: float = 0.02) -> Any:
    """Poll ``check`` until it returns something truthy; TimeoutError after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {what} within {timeout} s (last: {value!r})")
        time.sleep(poll)


def run_forked(jobs: Sequence[tuple[Callable[..., None], tuple[Any, ...]]],
               timeout: float) -> list[Any]:
    """Run each ``target(*args, conn)`` in its own fork-started child, all at once.

    Returns what each child sent on ``conn`` (``None`` if it sent nothing). Children
    still alive at the deadline are terminated, then killed; all are joined.
    """
    children = []
    for target, args in jobs:
        receive, send = _fork.Pipe(duplex=False)
        child = _fork.Process(target=target, args=(*args, send), daemon=True)
        child.start()
        send.close()
        children.append((child, receive))
    deadline = time.monotonic() + timeout
    results: list[Any] = []
    for _, receive in children:
        try:
            ready = receive.poll(max(0.0, deadline - time.monotonic()))
            results.append(receive.recv() if ready else None)
        except EOFError:                      # the child died without answering
            results.append(None)
        finally:
            receive.close()
    for child, _ in children:
        child.join(max(0.1, deadline - time.monotonic()))
        for stop in (child.terminate, child.kill):
            if child.is_alive():
                stop()
                child.join(1.0)
    return results


def steal_seconds() -> float:
    """CPU time the hypervisor stole from this VM so far (all CPUs; 0 where unknown)."""
    return float(getattr(psutil.cpu_times(), "steal", 0.0))


def steal_report(steal_s: float, wall_s: float) -> dict[str, float]:
    """Stolen CPU seconds over a window, also as a percentage of all CPUs' time in it."""
    cpus = psutil.cpu_count() or 1
    share = 100.0 * steal_s / (wall_s * cpus) if wall_s > 0 else math.nan
    return {"steal_s": round(steal_s, 2), "wall_s": round(wall_s, 2),
            "steal_pct_of_all_cpus": round(share, 1)}


def machine() -> dict[str, Any]:
    """Where the figures come from: the machine, its load, and the code measured."""
    return {"cpus": psutil.cpu_count(), "python": platform.python_version(),
            "platform": platform.platform(), "load_average_1_5_15": os.getloadavg(),
            "pb3a_commit": _commit()}


def _commit() -> str:
    """The checkout's short commit, marked when pb3a/ has uncommitted changes."""
    repo = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(["git", "-C", str(repo), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, timeout=5).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "pb3a"],
                               capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return f"{head} (pb3a/ modified)" if dirty else head or "unknown"


def parse_seeds(text: str) -> list[int]:
    """A ``--seeds`` argument: a range ``1-4`` or a list ``1,5,9``."""
    if "-" in text:
        first, last = text.split("-")
        return list(range(int(first), int(last) + 1))
    return [int(seed) for seed in text.split(",")]


def main_guard(body: Callable[[dict[str, Any]], None],
               flags: dict[str, str] | None = None) -> None:
    """Run ``body(result)``, then print ``result`` as JSON even if the body failed.

    A failure is reported as ``result["error"]`` and exit status 1. ``flags`` (option ->
    help), for a bench that reads no other arguments: the command line is read first,
    so ``--help`` says what the bench measures and a mistaken option is refused (both
    ran the whole bench before).
    """
    if flags is not None:
        doc = sys.modules["__main__"].__doc__ or ""
        parser = argparse.ArgumentParser(description=" ".join(doc.strip().split("\n\n")[0].split()))
        for flag, what in flags.items():
            parser.add_argument(flag, action="store_true", help=what)
        parser.parse_args()
    result: dict[str, Any] = {}
    failed = False
    try:
        body(result)
    except Exception as exc:
        result["error"] = f"{type(exc).__name__}: {exc}"
        failed = True
    print(json.dumps(result, indent=2, allow_nan=True))
    sys.exit(1 if failed else 0)
