"""Starting and stopping many modules: launch time, memory, shutdown time.

What is measured, for 100 and for 1,000 modules:

- ``launch_s``: from the ``system.launch()`` call to its return (every module
  instantiated, every link wired, every ``setup`` run and every module started);
- memory after a settle time with values flowing: RSS, USS and PSS summed over the
  launcher process and all its descendants (worker processes, multiprocessing's
  forkserver and resource tracker). RSS counts pages shared between processes (numpy,
  the shared-memory rings) once per process, USS not at all, PSS split between them:
  PSS is the machine's real total, and the goal is judged on it;
- ``shutdown_s``: ``run.close()``, which stops every module and worker and frees
  every ring.

How: ``System("big-N")`` on one node of 4 workers: every module packed into them
(placement: the workers filled in declaration order, so a chain shares a process and
its links stay in memory; the report counts each kind). Modules form chains of 10:
a threaded ``Clock`` (period 0.1 s) feeding 9 event-driven ``Gain`` modules. Each
size runs in a fresh interpreter (this script re-run with ``--modules N``), so each
launch pays the same cold start a user's script pays and no run inherits another's
memory. The node keeps its two spare workers booted, as every node does by default
(``--spares N`` for another count); they are counted with the helpers.
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import psutil
from _common import machine, main_guard, steal_report, steal_seconds
from _modules import Clock, Gain

from pb3a import System

SIZES = (100, 1000)
CHAIN = 10
WORKERS = 4
SOURCE_PERIOD = 0.1
SETTLE_S = 2.0
CHILD_TIMEOUT = 100.0
GOALS = {"launch_s": 10.0, "pss_gib": 4.0}
GIB = 1 << 30


def build(modules: int, spares: int | None = None) -> System:
    """``modules // CHAIN`` chains: a Clock feeding CHAIN - 1 Gains, one after the other,
    on a node that keeps ``spares`` idle workers booted (None: the default)."""
    system = System(f"big-{modules}").node(
        "local", workers=WORKERS, **({} if spares is None else {"spares": spares}))
    for chain in range(modules // CHAIN):
        system.add(f"c{chain}m0", Clock, period=SOURCE_PERIOD)
        for i in range(1, CHAIN):
            system.add(f"c{chain}m{i}", Gain)
            port = "out" if i == 1 else "y"
            system.link(f"c{chain}m{i - 1}.{port}", f"c{chain}m{i}.x")
    return system


def memory(workers: set[int]) -> dict[str, Any]:
    """RSS, USS and PSS (GiB) summed over this process and all its descendants."""
    me = psutil.Process()
    totals = {"rss": 0, "uss": 0, "pss": 0}
    kinds = {"launcher": 0, "workers": 0, "helpers": 0}
    for process in [me, *me.children(recursive=True)]:
        try:
            info = process.memory_full_info()
        except psutil.Error:
            continue
        for key in totals:
            totals[key] += getattr(info, key, 0)
        kind = "launcher" if process.pid == me.pid else (
            "workers" if process.pid in workers else "helpers")
        kinds[kind] += 1
    return {**{f"{key}_gib": round(value / GIB, 3) for key, value in totals.items()},
            "processes": kinds}


def measure(modules: int, spares: int | None = None) -> dict[str, Any]:
    """Launch, settle, look, shut down: one size, in this interpreter."""
    system = build(modules, spares)
    steal0, t_all = steal_seconds(), time.monotonic()
    t0 = time.monotonic()
    run = system.launch()
    launch_s = time.monotonic() - t0
    try:
        time.sleep(SETTLE_S)
        stats = run.stats()
        workers = {m.pid for m in stats.modules.values() if m.pid}
        mem = memory(workers)
        ends = [m for name, m in stats.modules.items() if name.endswith(f"m{CHAIN - 1}")]
        transports = [link.transport for link in stats.links.values()]
    finally:
        t1 = time.monotonic()
        run.close()
        shutdown_s = time.monotonic() - t1
    return {
        "modules": len(stats.modules), "worker_processes": len(workers),
        "links": {"shm": transports.count("shm"), "memory": transports.count("memory")},
        "launch_s": round(launch_s, 3),
        "launch_ms_per_module": round(1000 * launch_s / modules, 2),
        "memory_after_settle": mem,
        "chains_delivering_to_their_end": sum(1 for m in ends if m.events > 0),
        "chains": len(ends),
        "shutdown_s": round(shutdown_s, 3),
        "steal": steal_report(steal_seconds() - steal0, time.monotonic() - t_all),
    }


def in_fresh_interpreter(modules: int, spares: int | None) -> dict[str, Any]:
    """Run ``measure(modules, spares)`` in a new Python process; bounded by CHILD_TIMEOUT."""
    command = [sys.executable, str(Path(__file__).resolve()), "--modules", str(modules)]
    if spares is not None:
        command += ["--spares", str(spares)]
    with subprocess.Popen(command, stdout=subprocess.PIPE, text=True) as child:
        try:
            out, _ = child.communicate(timeout=CHILD_TIMEOUT)
        except subprocess.TimeoutExpired:
            child.send_signal(signal.SIGINT)       # its `finally` closes the running system
            try:
                out, _ = child.communicate(timeout=15.0)
            except subprocess.TimeoutExpired:
                child.kill()
                out, _ = child.communicate()
    try:
        return json.loads(out)
    except json.JSONDecodeError:
        return {"error": f"no result (exit status {child.returncode}, timeout "
                         f"{CHILD_TIMEOUT} s)"}


def body(result: dict[str, Any], spares: int | None) -> None:
    result.update(benchmark="startup", machine=machine(), workers=WORKERS,
                  spares="default" if spares is None else spares,
                  chain_length=CHAIN, source_period_s=SOURCE_PERIOD, settle_s=SETTLE_S)
    runs = {str(n): in_fresh_interpreter(n, spares) for n in SIZES}
    result["runs"] = runs
    small, big = runs[str(SIZES[0])], runs[str(SIZES[-1])]
    if "error" in small or "error" in big:
        raise RuntimeError("a size failed; see runs")
    result["scaling_1000_vs_100"] = {
        key: round(big[key] / small[key], 2) for key in ("launch_s", "shutdown_s")}
    result["scaling_1000_vs_100"]["pss"] = round(
        big["memory_after_settle"]["pss_gib"] / small["memory_after_settle"]["pss_gib"], 2)
    measured = {"launch_s": big["launch_s"], "pss_gib": big["memory_after_settle"]["pss_gib"]}
    result["goals_1000_modules"] = {
        key: {"limit": GOALS[key], "measured": value, "met": value < GOALS[key]}
        for key, value in measured.items()}


def one_size(modules: int, spares: int | None) -> None:
    main_guard(lambda result: result.update(measure(modules, spares)))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--modules", type=int, help="measure one size in this interpreter")
    parser.add_argument("--spares", type=int,
                        help="idle workers the node keeps booted (default: a node's, 2)")
    args = parser.parse_args()
    if args.modules:
        one_size(args.modules, args.spares)
    else:
        main_guard(lambda result: body(result, args.spares))
