"""Soak and chaos: three nodes, about 10,000 values/s over queue links, random migrations
and worker kills for ``--minutes`` (default 10), driven by ``pb3a stress``'s machinery.

Three node controllers run on this machine (``pb3a node start``, started here and
stopped after). Three checked pipelines cross them (``SequenceSource`` on one node ->
``SequenceChecker`` on the next, 3,300 values/s each); a fourth, the victims, is where
workers get killed (restart "fresh"). Every ``--kill-every`` seconds a victim's worker
is SIGKILLed; every ``--migrate-every`` seconds a checked module moves to another node.

The run is two stress runs, the first minute and the rest; after each, every module
goes back to its home node and the soak takes the footprint of every process. At the
end (sources stopped, checkers drained): on every checked link, nothing lost,
duplicated or reordered; every PB3A process alive at both footprints grew its RSS by
under 5 %; all the processes together hold no more file descriptors, threads or
/dev/shm segments than at the first minute; and no process or segment is left after
the shutdown.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import psutil

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, main_guard, steal_report, steal_seconds, wait_for
from _modules import SequenceChecker, SequenceSource

from pb3a import System
from pb3a.cli.stress import Stress
from pb3a.cli.stress_options import StressOptions
from pb3a.transport.shm import live_segments

NODES = ("n1", "n2", "n3")
PIPELINES = 3                 # checked ones; each 3,300 values/s
BATCH, PERIOD_S = 33, 0.01
VICTIMS = ("victim_source", "victim_checker")
RSS_GROWTH_GOAL = 0.05
BASELINE_S = 60.0             # the first minute: figures from then are the baseline
QUIET_S = 3.0                 # after the modules went home, before the footprint


def _controller(name: str, stack: contextlib.ExitStack) -> str:
    """Start ``pb3a node start --name NAME`` (stopped when ``stack`` closes); its address."""
    here = str(Path(__file__).resolve().parent)         # (the modules are in _modules.py)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        filter(None, [here, os.environ.get("PYTHONPATH")]))}
    process = subprocess.Popen(
        [sys.executable, "-m", "pb3a", "node", "start", "--name", name, "--listen",
         "tcp://127.0.0.1:0", "--max-cpu", "101"], stdout=subprocess.PIPE, text=True, env=env)

    def stop() -> None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5)
        process.stdout.close()
    stack.callback(stop)
    ready, _, _ = select.select([process.stdout], [], [], 30)
    if not ready:
        raise TimeoutError(f"node controller {name} did not start within 30 s")
    return process.stdout.readline().split(" at ")[-1].strip()


def build(addresses: dict[str, str]) -> System:
    system = System("soak")
    for name, address in addresses.items():
        system.node(name, address=address)
    for i in range(PIPELINES):
        source, checker = f"source{i}", f"checker{i}"
        system.add(source, SequenceSource, node=NODES[i], period=PERIOD_S,
                   state={"batch": BATCH})
        system.add(checker, SequenceChecker, node=NODES[(i + 1) % len(NODES)])
        system.link(f"{source}.out", f"{checker}.x", policy="queue:100000")
    system.add(VICTIMS[0], SequenceSource, node=NODES[0], period=PERIOD_S, restart="fresh",
               state={"batch": 10})
    system.add(VICTIMS[1], SequenceChecker, node=NODES[2], restart="fresh")
    system.link(f"{VICTIMS[0]}.out", f"{VICTIMS[1]}.x", policy="queue:100000")
    return system


def footprint() -> dict[int, dict[str, Any]]:
    """Every process of this soak (this one and its descendants): RSS, fds, threads and
    its shared-memory segments, by pid."""
    found = {}
    me = psutil.Process()
    for process in [me, *me.children(recursive=True)]:
        with contextlib.suppress(psutil.Error):
            found[process.pid] = {"name": " ".join(process.cmdline())[-60:],
                                  "rss": process.memory_info().rss,
                                  "fds": process.num_fds(), "threads": process.num_threads(),
                                  "segments": len(live_segments(process.pid))}
    return found


def compare(first: dict[int, dict[str, Any]], last: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """Fds, threads and segments of all the processes at both moments (the same modules
    on the same nodes, but workers that were restarted or moved are new processes);
    and per process alive at both, the growth of each and of its RSS."""
    totals = {key: {"first": sum(p[key] for p in first.values()),
                    "last": sum(p[key] for p in last.values())}
              for key in ("fds", "threads", "segments")}
    kept = sorted(set(first) & set(last))
    rows = {pid: {"process": last[pid]["name"],
                  "rss_growth": round(last[pid]["rss"] / first[pid]["rss"] - 1, 4),
                  **{f"{key}_growth": last[pid][key] - first[pid][key]
                     for key in ("fds", "threads", "segments")}} for pid in kept}
    worst = {key: max((row[key] for row in rows.values()), default=0)
             for key in ("rss_growth", "fds_growth", "threads_growth", "segments_growth")}
    return {"totals": totals, "processes_compared": len(kept), "worst": worst,
            "per_process": rows}


def _drained(run: Any, i: int) -> dict[str, int]:
    """Pipeline ``i``'s figures once its checker has everything its source sent."""
    sent = run.state(f"source{i}")["sent"]

    def caught_up() -> dict[str, Any] | None:
        state = run.state(f"checker{i}")
        return state if state["received"] + state["skipped"] >= sent else None

    try:
        state = wait_for(caught_up, timeout=60, what=f"checker{i} to get all {sent} values")
    except TimeoutError:                # the last values never came: lost, counted below
        state = run.state(f"checker{i}")
        state["skipped"] += sent - state["received"] - state["skipped"]
    return {"sent": sent, "received": state["received"], "lost": state["skipped"],
            "repeated_or_reordered": state["repeated"]}


def body(result: dict[str, Any]) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--kill-every", type=float, default=10.0, metavar="SECONDS")
    parser.add_argument("--migrate-every", type=float, default=7.0, metavar="SECONDS")
    parser.add_argument("--seed", type=int, default=16)
    args = parser.parse_args()
    os.environ.setdefault("PB3A_KEY", os.urandom(32).hex())   # never the user's key
    seconds = args.minutes * 60
    baseline_at = min(BASELINE_S, seconds / 2)
    result.update(benchmark="soak", machine=machine(), minutes=args.minutes,
                  target_values_per_s=round((PIPELINES * BATCH) / PERIOD_S))
    with contextlib.ExitStack() as stack:
        addresses = {name: _controller(name, stack) for name in NODES}
        system = build(addresses)
        plan = system.plan()
        checked = [name for name in plan.modules if name.startswith(("source", "checker"))]
        steal_before, started = steal_seconds(), time.monotonic()
        with system.launch() as run:
            reports, footprints = [], []
            # two stress runs, the first minute and the rest; after each, every module
            # back home and a moment's quiet, so both footprints have the same placement
            for phase, phase_s in enumerate((baseline_at, seconds - baseline_at)):
                options = StressOptions(phase_s, kill_every=args.kill_every,
                                        kill_among=frozenset(VICTIMS),
                                        migrate_every=args.migrate_every,
                                        migrate_among=frozenset(checked), sample_s=5.0,
                                        seed=args.seed + phase)
                reports.append(Stress(plan, options, sys.stderr).run_on(run))
                for name in checked:
                    if run.where(name) != plan.modules[name].node:
                        run.migrate(name, plan.modules[name].node)
                time.sleep(QUIET_S)           # (moves and restarts end their threads)
                footprints.append(footprint())
            for i in range(PIPELINES):
                run.set_state(f"source{i}", sending=False)
            links = {f"source{i}.out->checker{i}.x": _drained(run, i) for i in range(PIPELINES)}
        wall = time.monotonic() - started
        steal = steal_seconds() - steal_before
    ours = {pid for footprint_ in footprints for pid in footprint_} - {os.getpid()}
    processes = []
    for pid in ours:
        with contextlib.suppress(psutil.Error):
            processes.append(psutil.Process(pid))
    _, alive = psutil.wait_procs(processes, timeout=10)
    result["processes_left_after_shutdown"] = [process.pid for process in alive]
    result["segments_left_after_shutdown"] = [name for pid in {*ours, os.getpid()}
                                              for name in live_segments(pid)]
    result["stress_summaries"] = {"first_minute": reports[0]["summary"],
                                  "rest": reports[1]["summary"]}
    result["checked_links"] = links
    result["footprint"] = compare(*footprints)
    result["footprint"]["baseline_at_s"] = baseline_at
    result["steal"] = steal_report(steal, wall)
    worst, totals = result["footprint"]["worst"], result["footprint"]["totals"]
    kills = sum(report["summary"]["kills"] for report in reports)
    moves = sum(report["summary"]["migrations"] for report in reports)
    lossless = all(link["lost"] == 0 and link["repeated_or_reordered"] == 0
                   and link["received"] == link["sent"] for link in links.values())
    result["goals"] = {
        "nothing_lost_or_duplicated_on_checked_links": {"met": lossless},
        "rss_growth_under_5_pct": {"measured": worst["rss_growth"],
                                   "met": worst["rss_growth"] < RSS_GROWTH_GOAL},
        "no_growth_of_fds_threads_segments": {
            "measured": {key: total["last"] - total["first"] for key, total in totals.items()},
            "met": all(total["last"] <= total["first"] for total in totals.values())
            and not result["segments_left_after_shutdown"]
            and not result["processes_left_after_shutdown"]},
        "kills_and_migrations_happened": {
            "measured": {"kills": kills, "migrations": moves},
            "met": kills > 0 and moves > 0}}


if __name__ == "__main__":
    main_guard(body)
