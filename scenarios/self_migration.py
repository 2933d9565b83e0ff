"""Self-migration under CPU load: an agent watches its nodes' ``env`` ports and moves a
compute-heavy module away from the node that stress processes load.

Two nodes share this machine, each pinned to one CPU (``a`` to CPU 0, ``b`` to CPU 1),
so each ``env`` module reports its own node. A source on ``b`` emits a time stamp
every 5 ms; ``compute`` (on ``a``) spends a fixed amount of CPU time on each and
passes it on; the sink on ``b`` records each value's arrival and end-to-end latency.
After a quiet phase, stress processes pinned to CPU 0 load node ``a``; the ``Mover``
agent sees node ``a`` busy from outside the system and node ``b`` not, and migrates
``compute`` to ``b``. It reads each node's ``cpu_outside`` (the load that is not the
system's own), so once ``compute`` has moved, the load it brings to ``b`` does not
make ``b`` look worse than ``a``: it moves once, not back and forth. The same run
with the agent disabled is the baseline; the report counts the moves.

Run it: ``python -m scenarios.self_migration [--out DIR] [--quick]`` (or ``pb3a
scenario self-migration``). It prints a JSON report (throughput and latency before,
during and after the load, with and without adaptation) and writes
``self_migration.png`` and ``self_migration.json`` to DIR.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from pb3a import Agent, Environment, Input, InputPort, Module, Output, System
from pb3a.cli.arguments import seed
from pb3a.cli.log_output import show_logs
from pb3a.cpu_load import CPULoad
from pb3a.model.module import reflective
from pb3a.pending import Pending
from scenarios import output_directory, summary
from scenarios.lab import wait_until

RATE_HZ = 200.0
WORK_S = 0.002                 # CPU seconds of work per value in ``compute``
WINDOW_S = 0.5                 # throughput and latency are reported per window
PHASES = {"full": (5.0, 10.0, 5.0), "quick": (2.0, 5.0, 2.0)}   # quiet, loaded, after
STRESS_PROCESSES = 2           # burners on CPU 0: compute gets a third of it


class Source(Module):
    """Emits ``time.monotonic()`` every period."""

    out = Output(float)
    period = 1.0 / RATE_HZ

    def step(self) -> None:
        self.out.write(time.monotonic())


class Compute(Module):
    """Spends ``work_s`` of its own CPU time on every value, then passes it on."""

    x = Input(float, policy="queue:10000")
    y = Output(float)
    work_s = WORK_S
    handled = 0

    def on_input(self, port: InputPort) -> None:
        stamp = port.read()
        end = time.thread_time() + self.work_s
        while time.thread_time() < end:       # CPU work, the same however busy the core
            pass
        self.handled += 1
        self.y.write(stamp)


class Sink(Module):
    """Records when each value arrived and how long it took from the source."""

    x = Input(float, policy="queue:100000")
    arrivals: list[float] = []
    latencies: list[float] = []

    def on_input(self, port: InputPort) -> None:
        stamp = port.read()
        now = time.monotonic()
        self.arrivals.append(now)
        self.latencies.append(now - stamp)


class Mover(Agent):
    """Moves ``target`` off a node that stays busy with load from outside the system.

    Busy means an outside load above ``busy_pct`` for ``patience`` samples in a row
    while the other node's is at least ``margin_pct`` lower. Outside load (``env``'s
    ``cpu_outside``) leaves out the system's own workers, so moving ``target`` does not
    make its new node look busy. A move runs in the background (``wait=False``): the
    agent goes on sampling, and decides again only once the move has ended. The first
    ``warmup_s`` after it starts are ignored: the system's start-up loads the CPUs."""

    outside_a = Input(float)
    outside_b = Input(float)
    target = "compute"
    enabled = True
    busy_pct = 50.0
    margin_pct = 25.0
    patience = 2
    strikes = 0
    moved_at: list[float] = []
    moved_to: list[str] = []
    seen: dict[str, float] = {}       # the outside loads it saw last, per node (percent)
    warmup_s = 1.0

    def setup(self) -> None:
        self._started = time.monotonic()
        self._moving: Pending | None = None
        self._here: str | None = self.runtime.where(self.target)

    @reflective                 # (it takes the fields Module's does: they are checked)
    def set_state(self, state: dict[str, Any]) -> None:
        """Set state; the node of a ``target`` set while it runs (where load is judged)
        is looked up at the next sample, not in here: set_state comes under the
        configuration lock a runtime request waits for."""
        super().set_state(state)
        if "target" in state:
            self._here = None

    def on_input(self, port: InputPort) -> None:
        load = {"a": self.outside_a.read(0.0), "b": self.outside_b.read(0.0)}
        self.seen = load
        if time.monotonic() - self._started < self.warmup_s or not self.enabled:
            return
        if self._moving is not None:
            if not self._moving.done():
                return                            # one move at a time
            self._moving, self._here = None, None
        if self._here is None:
            self._here = self.runtime.where(self.target)
        here = self._here
        there = min(load, key=load.__getitem__)
        if load[here] > self.busy_pct and load[there] < load[here] - self.margin_pct:
            self.strikes += 1
        else:
            self.strikes = 0
        if self.strikes >= self.patience and there != here:
            self._moving = self.runtime.migrate(self.target, there, wait=False)
            self.strikes = 0
            self.moved_at.append(time.monotonic())
            self.moved_to.append(there)


def build(adaptive: bool, env_period: float = 0.25) -> System:
    system = System("self-migration")
    system.node("a", cpus=[0])
    system.node("b", cpus=[1 % (os.cpu_count() or 1)])
    for node in ("a", "b"):
        system.add(f"env-{node}", Environment, node=node, period=env_period)
    system.add("source", Source, node="b")
    system.add("compute", Compute, node="a")
    system.add("sink", Sink, node="b")
    system.add("mover", Mover, node="b", state={"enabled": adaptive})
    system.link("source.out", "compute.x")
    system.link("compute.y", "sink.x")
    system.link("env-a.cpu_outside", "mover.outside_a")
    system.link("env-b.cpu_outside", "mover.outside_b")
    return system


def run_once(adaptive: bool, phases: tuple[float, float, float]) -> dict[str, Any]:
    """One run: quiet, loaded (stress on CPU 0), after; the sink's records and events."""
    quiet, loaded, after = phases
    with build(adaptive).launch() as run:
        start = time.monotonic()
        wait_until(start + quiet)
        load_on = time.monotonic()
        with CPULoad({0: 100.0}, burners_per_cpu=STRESS_PROCESSES):
            wait_until(load_on + loaded)
            seen = run.state("mover")["seen"]          # (as the load ends)
        load_off = time.monotonic()
        wait_until(load_off + after)
        sink, mover = run.state("sink"), run.state("mover")
        node = run.stats().modules["compute"].node
    return {"start": start, "load_on": load_on, "load_off": load_off,
            "end": load_off + after, "arrivals": sink["arrivals"],
            "latencies": sink["latencies"], "moved_at": mover["moved_at"],
            "moved_to": mover["moved_to"], "seen_loaded": seen,
            "compute_node_at_end": node}


def no_move_reason(seen: dict[str, float]) -> str:
    """Why the agent made no move, from the outside loads it saw as the load ended."""
    a, b = seen.get("a", 0.0), seen.get("b", 0.0)
    rule = (f"it moves compute off node a (CPU 0) once a is over {Mover.busy_pct:g} % busy "
            f"from outside the system and node b (CPU 1) at least {Mover.margin_pct:g} "
            f"points less; as the load ended it saw a at {a:.0f} % and b at {b:.0f} %")
    if a <= Mover.busy_pct:
        return f"{rule}: the load on CPU 0 did not show (is CPU 0 this process's to load?)"
    if b >= a - Mover.margin_pct:
        return f"{rule}: something else on this machine keeps CPU 1 busy too"
    return f"{rule}: it saw that too briefly ({Mover.patience} samples in a row are needed)"


def windows(record: dict[str, Any]) -> list[dict[str, float]]:
    """Throughput (values/s) and median latency (ms) per window, from the start."""
    start, end = record["start"], record["end"]
    count = int((end - start) / WINDOW_S)
    buckets: list[list[float]] = [[] for _ in range(count)]
    for arrival, latency in zip(record["arrivals"], record["latencies"], strict=True):
        index = int((arrival - start) / WINDOW_S)
        if 0 <= index < count:
            buckets[index].append(latency)
    return [{"t": (i + 0.5) * WINDOW_S, "rate": len(b) / WINDOW_S,
             "latency_ms": 1e3 * statistics.median(b) if b else float("nan")}
            for i, b in enumerate(buckets)]


def phase_figures(record: dict[str, Any]) -> dict[str, dict[str, float]]:
    """Per phase: values per second, and latency median and p95 in ms."""
    bounds = {"before": (record["start"], record["load_on"]),
              "during": (record["load_on"], record["load_off"]),
              "after": (record["load_off"], record["end"])}
    figures = {}
    for phase, (lo, hi) in bounds.items():
        lat = sorted(1e3 * latency for arrival, latency in
                     zip(record["arrivals"], record["latencies"], strict=True)
                     if lo <= arrival < hi)
        figures[phase] = {
            "values_per_s": round(len(lat) / (hi - lo), 1),
            "latency_median_ms": round(statistics.median(lat), 2) if lat else None,
            "latency_p95_ms": round(lat[int(0.95 * (len(lat) - 1))], 2) if lat else None}
    return figures


def plot(records: dict[str, dict[str, Any]], path: Path) -> bool:
    """Throughput and latency over time for both runs; False if matplotlib is missing."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    styles = {"adaptive": ("tab:blue", "agent on (migrates)"),
              "static": ("tab:red", "agent off")}
    for name, record in records.items():
        colour, label = styles[name]
        series = windows(record)
        t = [w["t"] for w in series]
        top.plot(t, [w["rate"] for w in series], color=colour, label=label)
        bottom.plot(t, [w["latency_ms"] for w in series], color=colour, label=label)
        for moved in record["moved_at"]:
            for axis in (top, bottom):
                axis.axvline(moved - record["start"], color=colour, linestyle=":")
    record = records["adaptive"]
    for axis in (top, bottom):
        axis.axvspan(record["load_on"] - record["start"], record["load_off"] - record["start"],
                     color="0.85", label="CPU 0 under stress")
    top.set_ylabel("values / s")
    bottom.set_ylabel("latency, median (ms)")
    bottom.set_yscale("log")
    bottom.set_xlabel("time (s)")
    top.set_title("compute under CPU load on its node: migrating vs staying")
    top.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pb3a scenario self-migration",
                                     description=summary(__doc__))
    parser.add_argument("--out", default=".",
                        help="directory for the PNG and JSON (default: this one)")
    parser.add_argument("--quick", action="store_true", help="shorter phases (2/5/2 s)")
    # (every scenario takes the same arguments: a script looping over them with a seed
    # stopped here on "unrecognized arguments")
    parser.add_argument("--seed", type=seed, default=1,
                        help="taken as every scenario takes it, and reported; nothing in "
                             "this one is drawn at random")
    args = parser.parse_args(argv)
    show_logs()
    if (os.cpu_count() or 1) < 2:
        print("self_migration needs two CPUs (one per node)", file=sys.stderr)
        return 2
    try:
        out = output_directory(args.out)
    except ValueError as exc:
        print(f"self_migration: {exc}", file=sys.stderr)
        return 2
    phases = PHASES["quick" if args.quick else "full"]
    records = {"adaptive": run_once(True, phases), "static": run_once(False, phases)}
    report = {"scenario": "self-migration", "seed": args.seed, "phases_s": dict(zip(
        ("quiet", "loaded", "after"), phases, strict=True)),
        "rate_hz": RATE_HZ, "work_ms_per_value": WORK_S * 1e3,
        "runs": {name: {"phases": phase_figures(r),
                        "moves": len(r["moved_at"]),
                        "migrated_after_load_s": [round(m - r["load_on"], 2)
                                                  for m in r["moved_at"]],
                        "outside_load_seen_pct": {node: round(load, 1) for node, load
                                                  in r["seen_loaded"].items()},
                        "compute_node_at_end": r["compute_node_at_end"]}
                 for name, r in records.items()}}
    if plot(records, out / "self_migration.png"):
        report["plot"] = str(out / "self_migration.png")
    (out / "self_migration.json").write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    if not records["adaptive"]["moved_at"]:
        print(f"self_migration: the agent made no move: "
              f"{no_move_reason(records['adaptive']['seen_loaded'])}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
