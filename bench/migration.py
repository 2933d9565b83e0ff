"""Live migration between two nodes: the pause, where it goes, the state moved and the
whole call, for a small module fed at 1 kHz and for one with 10 MiB of numpy state
fed at 500 Hz, each feeding a reader.

What is measured, per case: migrations back and forth between nodes ``a`` and ``b``
while ``Clock`` writes to the moving module, through the public API only:
``run.migrate`` returns ``pause_s`` (the module paused at the source until started
at the destination), its ``phases`` (where the pause went) and ``state_bytes``; the
bench also times the whole call (which includes starting the destination worker).
Afterwards it checks that the reader got every value once and in order.

``small_state``: ``MigrationRelay`` (a queue input, an output, a counter), 40 moves.
``big_state``: ``BigState`` (the same, plus 10 MiB of float64 it writes into), 20
moves; the goal is a median pause of at most 25 ms.

Baseline in the same run: a ``swap`` of the same module (an in-place change of code
with the same pause-and-resume, but no new process, no re-wiring, no state moved).

``--controller``: node ``b`` runs behind a node controller (its own executor process,
every operation an authenticated request) instead of being embedded.
"""

from __future__ import annotations

import contextlib
import dataclasses
import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, main_guard, percentile, steal_report, steal_seconds, summary, wait_for
from _modules import BigState, Clock, MigrationRelay, OrderedReader

from pb3a import System
from pb3a.daemons.node_controller import Limits, NodeController
from pb3a.transport.auth import ClusterKey

# case -> (module, period of its writer, migrations)
CASES = {"small_state": (MigrationRelay, 0.001, 40), "big_state": (BigState, 0.002, 20)}
GOAL_BIG_PAUSE_MS = 25.0


def body(result: dict[str, Any]) -> None:
    remote = "--controller" in sys.argv
    result.update(benchmark="migration", machine=machine(),
                  node_b="node controller" if remote else "embedded")
    with contextlib.ExitStack() as stack:
        address = None
        if remote:
            controller = NodeController("b", ClusterKey.load(), limits=Limits(101.0))
            stack.callback(controller.close)
            address = controller.address
        steal0, t0 = steal_seconds(), time.monotonic()
        for case, (cls, period, reps) in CASES.items():
            result[case] = measure(case, cls, period, reps, address)
        result["steal"] = steal_report(steal_seconds() - steal0, time.monotonic() - t0)
    pause = result["big_state"]["pause_ms"]["median"]
    result["goal"] = {"big_state_median_pause_ms_at_most": GOAL_BIG_PAUSE_MS,
                      "met": pause <= GOAL_BIG_PAUSE_MS}


def measure(case: str, cls: type, period: float, reps: int,
            address: str | None) -> dict[str, Any]:
    system = System(f"bench-migration-{case.replace('_', '-')}")
    system.node("a")
    system.node("b", address=address)
    system.add("clock", Clock, node="a", period=period)
    system.add("mover", cls, node="a")
    system.add("reader", OrderedReader, node="a")
    system.link("clock.out", "mover.x")
    system.link("mover.out", "reader.x")
    reports, calls, swaps = [], [], []
    with system.launch() as run:
        wait_for(lambda: run.state("reader")["count"] > 100, 10.0, "values at the reader")
        for i in range(reps):
            started = time.monotonic()
            reports.append(run.migrate("mover", to="ba"[i % 2]))
            calls.append(time.monotonic() - started)
        for _ in range(max(1, reps // 4)):
            started = time.monotonic()
            run.swap("mover", cls)
            swaps.append(time.monotonic() - started)
        run.remove("clock")                         # its link drains into the mover
        mover = wait_for(lambda: (s := run.stats().modules["mover"]).inputs["x"]
                         .pending == 0 and s, 10.0, "the mover drained")
        written = mover.inputs["x"].received
        reader = wait_for(lambda: (s := run.state("reader"))["count"] >= written and s,
                          10.0, "every value at the reader")
    ms = [report.pause_s * 1e3 for report in reports]
    phases = [dataclasses.asdict(report.phases) for report in reports]
    return {
        "reps": reps, "writer_hz": round(1 / period),
        "pause_ms": {**summary(ms, 2), "p90": round(percentile(ms, 90), 2)},
        "phases_median_ms": {name.removesuffix("_s"): round(statistics.median(
            phase[name] for phase in phases) * 1e3, 2) for name in phases[0]},
        "state_bytes": summary([report.state_bytes for report in reports], 0),
        "migrate_call_ms": summary([c * 1e3 for c in calls], 2),
        "baseline_swap_call_ms": summary([s * 1e3 for s in swaps], 2),
        "values": {"written": written, "read": reader["count"],
                   "out_of_order": reader["out_of_order"],
                   "duplicates": reader["duplicates"]},
    }


if __name__ == "__main__":
    main_guard(body, {"--controller": "node b behind a node controller, not embedded"})
