"""Live migration between two embedded nodes: the pause, the state moved, and the
whole call, for a relay module fed at 1 kHz and feeding a reader.

What is measured: ``REPS`` migrations back and forth of ``relay`` (a queue input, an
output, a little state) while ``Clock`` writes to it every millisecond, through the
public API only: ``run.migrate`` returns ``pause_s`` (the module paused at the source
until started at the destination) and ``state_bytes``; the bench also times the whole
call (which includes starting the destination worker). Afterwards it checks that the
reader got every value once and in order.

Baseline in the same run: a ``swap`` of the same module (an in-place change of code
with the same pause-and-resume, but no new process and no re-wiring).

``--controller``: node ``b`` runs behind a node controller (its own executor process,
every operation an authenticated request) instead of being embedded.
"""

from __future__ import annotations

import contextlib
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, main_guard, percentile, steal_report, steal_seconds, summary, wait_for
from _modules import Clock, MigrationRelay, OrderedReader

from pb3a import System
from pb3a.daemons.node_controller import Limits, NodeController
from pb3a.transport.auth import ClusterKey

REPS = 40


def body(result: dict[str, Any]) -> None:
    remote = "--controller" in sys.argv
    with contextlib.ExitStack() as stack:
        address = None
        if remote:
            controller = NodeController("b", ClusterKey.load(), limits=Limits(101.0))
            stack.callback(controller.close)
            address = controller.address
        measure(result, address)


def measure(result: dict[str, Any], address: str | None) -> None:
    result.update(benchmark="migration", machine=machine(), reps=REPS,
                  node_b="node controller" if address else "embedded")
    system = System("bench-migration")
    system.node("a")
    system.node("b", address=address)
    system.add("clock", Clock, node="a", period=0.001)
    system.add("relay", MigrationRelay, node="a")
    system.add("reader", OrderedReader, node="a")
    system.link("clock.out", "relay.x")
    system.link("relay.out", "reader.x")
    steal0, t0 = steal_seconds(), time.monotonic()
    pauses, sizes, calls, swaps = [], [], [], []
    with system.launch() as run:
        wait_for(lambda: run.state("reader")["count"] > 100, 10.0, "values at the reader")
        for i in range(REPS):
            started = time.monotonic()
            report = run.migrate("relay", to="ba"[i % 2])
            calls.append(time.monotonic() - started)
            pauses.append(report.pause_s)
            sizes.append(report.state_bytes)
        for _ in range(REPS // 4):
            started = time.monotonic()
            run.swap("relay", MigrationRelay)
            swaps.append(time.monotonic() - started)
        run.remove("clock")                         # its link drains into the relay
        relay = wait_for(lambda: (s := run.stats().modules["relay"]).inputs["x"][
            "pending"] == 0 and s, 10.0, "the relay drained")
        written = relay.inputs["x"].received
        reader = wait_for(lambda: (s := run.state("reader"))["count"] >= written and s,
                          10.0, "every value at the reader")
    ms = [p * 1e3 for p in pauses]
    result["pause_ms"] = {**summary(ms, 2), "p90": round(percentile(ms, 90), 2)}
    result["state_bytes"] = summary(sizes, 0)
    result["migrate_call_ms"] = summary([c * 1e3 for c in calls], 2)
    result["baseline_swap_call_ms"] = summary([s * 1e3 for s in swaps], 2)
    result["values"] = {"written": written, "read": reader["count"],
                        "out_of_order": reader["out_of_order"],
                        "duplicates": reader["duplicates"]}
    result["steal"] = steal_report(steal_seconds() - steal0, time.monotonic() - t0)


if __name__ == "__main__":
    main_guard(body)
