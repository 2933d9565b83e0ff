"""``pb3a stress FILE``: run a configuration under chosen CPU load and faults, and report
how each link and node fared over time (JSON, PNG, a live progress line).

Load: ``--load CPUS:PERCENT[@T[+D]]`` holds CPUs at a level (``pb3a.cpu_load``), for
the whole run or from T for D seconds. Faults: ``--kill-worker-every N`` SIGKILLs a
random worker (its modules come back by their ``restart`` policy);
``--migrate-every N`` moves a random module to a random other node; ``--cut-node
NAME@T[+D]`` freezes a node on this machine as if its cable were cut
(``pb3a.launch.faults``). Every ``--sample`` seconds the run records, per link, the
values per second, latency percentiles of the values delivered since the last sample,
drops and failures, and per node its CPU and memory as its ``env`` ports give them (a
``stress-probe-NODE`` module per node reads them).

``Stress(plan, options, out).run_on(run)`` works on a system already launched: the
soak (``bench/soak.py``) drives its own system through it.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import math
import random
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TextIO

from pb3a import latencies
from pb3a.cli.stress_options import StressOptions, Window
from pb3a.config.plan import Plan
from pb3a.cpu_load import CPULoad
from pb3a.errors import ModuleNotFound, PB3AError, RuntimeFailure, RuntimeTimeout
from pb3a.launch.faults import Freeze, kill_worker
from pb3a.launch.running import Running, launch
from pb3a.model.environment import PREFIX as ENV_PREFIX
from pb3a.model.environment import Environment, env_name
from pb3a.model.module import Module
from pb3a.model.ports import Input, InputPort
from pb3a.stats import LinkStats, SystemStats, plain
from pb3a.transport.auth import ClusterKeyError

SCHEMA = "pb3a-stress/1"
PROBE_PREFIX = "stress-probe-"
SILENT_S = 0.5          # a node whose heartbeats stopped this long is not asked for readings
PLAIN_EVERY_S = 5.0          # progress lines when the output is not a terminal
EVENTS_MARKED = ("module_restarted", "module_failed", "module_failed_over", "node_lost",
                 "node_joined")


class EnvProbe(Module):
    """Keeps the latest CPU and memory readings of its node's ``env`` module."""

    cpu = Input(float)
    cpu_per_core = Input(object)
    memory_available = Input(float)
    readings: dict = {}

    def on_input(self, port: InputPort) -> None:
        value = port.read()
        self.readings = {**self.readings, port.name: (
            [float(v) for v in value] if port.name == "cpu_per_core" else float(value))}


def stress_command(args: argparse.Namespace) -> int:
    """Launch FILE, stress it, write ``stress.json`` and ``stress.png`` to ``--out``."""
    from pb3a.cli.files import load_plan
    from pb3a.cli.status import sigterm_interrupts
    from pb3a.processes import start_resource_tracker

    options = StressOptions(args.seconds, args.load, args.kill_every, args.kill_among,
                            args.migrate_every, args.migrate_among, args.cuts, args.sample_s,
                            args.seed)
    plan = load_plan(args.file, "stress", args.import_timeout)
    if plan is None:
        return 1
    out = Path(args.out)
    start_resource_tracker()            # (before the CPU load's Event starts the tracker)
    try:
        stress = Stress(plan, options, sys.stdout)
        out.mkdir(parents=True, exist_ok=True)
        with sigterm_interrupts(), launch(plan) as run:
            report = stress.run_on(run)
    except (PB3AError, ClusterKeyError, ValueError, OSError) as exc:
        print(f"pb3a stress: {exc}", file=sys.stderr)
        return 1
    print(summary_text(report))
    try:
        (out / "stress.json").write_text(json.dumps(report, indent=2))
        from pb3a.cli.stress_plot import plot
        drawn = plot(report, out / "stress.png")
    except OSError as exc:                # the run is over: its summary is above
        print(f"pb3a stress: cannot write the report to {out}: {exc.strerror or exc}",
              file=sys.stderr)
        return 1
    print(f"pb3a stress: wrote {out / 'stress.json'}"
          + (f" and {out / 'stress.png'}" if drawn
             else " (no PNG: matplotlib is missing; pip install 'pb3a[plot]')"))
    if any(mark["kind"] == "interrupted" for mark in report["marks"]):
        print("pb3a stress: the report covers the run until it was interrupted",
              file=sys.stderr)
        raise KeyboardInterrupt         # (main: exit 130, as any command interrupted)
    return 0


class Stress:
    """One stress run of ``plan``: its schedule, the faults it injects, the samples it
    takes. Bad options raise ValueError naming each option to fix, before anything runs."""

    def __init__(self, plan: Plan, options: StressOptions, out: TextIO) -> None:
        self.plan, self.options, self.out = plan, options, out
        self.run: Running                                  # (given to run_on)
        problems = [f"{option}: there is no module {name!r}"
                    for option, names in (("--kill-among", options.kill_among),
                                          ("--migrate-among", options.migrate_among))
                    for name in sorted(names) if name not in plan.modules]
        if options.migrate_every and len(plan.nodes) < 2:
            problems.append("--migrate-every: the system has one node, so nowhere to move to")
        # (one that starts when the run has ended never ran, and the report looked as if
        # the system had taken it well)
        problems += [f"{option}: it starts at {window.start:g} s, not before the run's end "
                     f"at {options.seconds:g} s (--for)"
                     for option, windows in (("--load", [w for _, w in options.loads]),
                                             ("--cut-node", [w for _, w in options.cuts]))
                     for window in windows if window.start >= options.seconds]
        self.loads: list[tuple[CPULoad, Window]] = []
        for levels, window in options.loads:
            with _problem(problems, "--load"):
                self.loads.append((CPULoad(levels), window))
        self.freezes: list[tuple[Freeze, Window]] = []
        for node, window in options.cuts:
            with _problem(problems, "--cut-node"):
                self.freezes.append((Freeze(plan, node), window))
        if problems:
            raise ValueError("; ".join(problems))
        user = [name for name in plan.modules if not name.startswith(ENV_PREFIX)]
        self.kill_among = sorted(options.kill_among or user)
        self.migrate_among = sorted(options.migrate_among or user)
        self.probes = {node: f"{PROBE_PREFIX}{node}" for node in plan.nodes}
        self.rng = random.Random(options.seed)
        self.marks: list[dict[str, Any]] = []
        self.samples: list[dict[str, Any]] = []
        self.counts = {"kills": 0, "migrations": 0, "migrations_failed": 0, "cuts": 0}
        self._links: dict[str, dict[str, Any]] = {}       # per link: last figures, totals
        self._events_seen = 0
        self._started = time.monotonic()
        self._wall_started = time.time()
        self._last_printed = -PLAIN_EVERY_S

    def run_on(self, run: Running) -> dict[str, Any]:
        """Stress ``run`` (``plan`` launched) for ``options.seconds``; the report (its
        fields: the README's "pb3a stress" section). Ctrl-C ends it early. Whatever
        happens, every load is stopped and every node thawed at the end."""
        self.run = run
        try:
            self._go()
        finally:
            try:        # thawed first: at once, and a second Ctrl-C while the loads stop
                for freeze, _ in self.freezes:      # (up to seconds) left nodes stopped
                    self._cut(freeze, on=False)
            finally:
                for load, _ in self.loads:
                    self._load(load, on=False)
        self._sample()
        if self.out.isatty():
            self.out.write("\n")
        return self.report()

    # -- the schedule -----------------------------------------------------------------
    def _go(self) -> None:
        run_s = self.options.seconds
        self._add_probes()
        self._started, self._wall_started = time.monotonic(), time.time()
        for key, link in _measured(self.run.stats()).items():   # count from here on
            self._links[key] = {"at": 0.0, "values": link.values, "drops": link.drops,
                                "link_failures": link.link_failures,
                                "counts": dict(link.latency_counts)}
        timed: list[tuple[float, Callable[[], None]]] = []
        for load, window in self.loads:
            timed += [(window.start, functools.partial(self._load, load, on=True)),
                      (window.end(run_s), functools.partial(self._load, load, on=False))]
        for freeze, window in self.freezes:
            timed += [(window.start, functools.partial(self._cut, freeze, on=True)),
                      (window.end(run_s), functools.partial(self._cut, freeze, on=False))]
        timed.sort(key=lambda item: item[0])
        periodic = [(period, action) for period, action in (
            (self.options.sample_s, self._sample), (self.options.kill_every, self._kill),
            (self.options.migrate_every, self._migrate)) if period]
        due = [period for period, _ in periodic]
        try:
            while (now := self.elapsed()) < run_s:
                while timed and timed[0][0] <= now:
                    timed.pop(0)[1]()
                for i, (period, action) in enumerate(periodic):
                    if due[i] <= now:
                        action()
                        due[i] += period
                soonest = min([run_s, *due, *(at for at, _ in timed[:1])])
                if self.run.wait(max(0.0, soonest - self.elapsed())):
                    break                                     # the system stopped
        except KeyboardInterrupt:
            self.mark("interrupted", "")

    def elapsed(self) -> float:
        return time.monotonic() - self._started

    def mark(self, kind: str, subject: str, at: float | None = None, **detail: Any) -> None:
        self.marks.append({"t": round(self.elapsed() if at is None else at, 3), "kind": kind,
                           "subject": subject, **detail})

    # -- load and faults ----------------------------------------------------------------
    def _load(self, load: CPULoad, on: bool) -> None:
        cpus = ",".join(map(str, load.levels))
        if on:
            load.start()
            self.mark("load_on", f"CPU {cpus}", levels=load.levels)
        elif load.running:
            load.stop()
            self.mark("load_off", f"CPU {cpus}")

    def _cut(self, freeze: Freeze, on: bool) -> None:
        if on:
            self.mark("cut", freeze.node, pids=freeze.freeze())
            self.counts["cuts"] += 1
        elif freeze.frozen:
            freeze.thaw()
            self.mark("uncut", freeze.node)

    def _kill(self) -> None:
        with contextlib.suppress(PB3AError):
            killed = kill_worker(self.run, self.plan, self.rng, self.kill_among)
            if killed is not None:
                self.counts["kills"] += 1
                self.mark("kill", killed.worker, pid=killed.pid, node=killed.node,
                          modules=list(killed.modules))

    def _migrate(self) -> None:
        up = [name for name, node in self.run.nodes().items() if node.up]
        name = self.rng.choice(self.migrate_among)
        try:
            here = self.run.where(name)
            there = self.rng.choice([node for node in up if node != here] or [here])
            if there == here:
                return
            report = self.run.migrate(name, there, timeout=max(5.0, self.options.sample_s))
        except (ModuleNotFound, RuntimeFailure, RuntimeTimeout) as exc:
            self.counts["migrations_failed"] += 1
            self.mark("migration_failed", name, reason=str(exc))
            return
        self.counts["migrations"] += 1
        self.mark("migration", name, source=report.source, destination=report.destination,
                  pause_s=report.pause_s)

    # -- figures --------------------------------------------------------------------------
    def _add_probes(self) -> None:
        """A probe per node, fed by the node's env module (started here if the system
        has none, sampling as often as this run samples)."""
        stats = self.run.stats()          # (an earlier run may have added them)
        running = stats.modules
        for node, probe in self.probes.items():
            if probe in running or not stats.nodes[node].up:
                continue
            if env_name(node) not in running:
                self.run.add(env_name(node), Environment, node=node,
                             period=self.options.sample_s)
            self.run.add(probe, EnvProbe, node=node)
            for port in ("cpu", "cpu_per_core", "memory_available"):
                self.run.link(f"{env_name(node)}.{port}", f"{probe}.{port}")

    def _sample(self) -> None:
        at = self.elapsed()
        try:
            stats = self.run.stats(timeout=max(1.0, self.options.sample_s))
        except (RuntimeFailure, RuntimeTimeout):
            return
        links = {key: self._link_sample(key, link, at)
                 for key, link in _measured(stats).items()}
        nodes = {name: self._node_sample(name, stats) for name in self.plan.nodes}
        load = {cpu: round(reading, 1) for load, _ in self.loads if load.running
                for cpu, reading in load.readings.items()}
        self.samples.append({"t": round(at, 3), "links": links, "nodes": nodes,
                             "load_read": load})
        self._mark_events()
        self._progress(at, stats)

    def _link_sample(self, key: str, link: LinkStats, at: float) -> dict[str, Any]:
        last = self._links.setdefault(key, {"at": 0.0, "values": 0, "drops": 0,
                                            "link_failures": 0, "counts": {}})
        totals = last.setdefault("totals", {"values": 0, "drops": 0, "link_failures": 0,
                                            "counts": {}})
        if link.silent:
            # its reader silent: its figures are not known now (its node's last report's,
            # or 0 for a worker that did not answer, which read as a counter started
            # anew, and the count came back whole on top of the totals once it answered
            # again); the next known ones count from the last, and its rate meanwhile
            # is a gap
            return {"values": totals["values"], "drops": totals["drops"],
                    "link_failures": totals["link_failures"], "values_per_s": math.nan,
                    **_percentiles({})}
        sample = {}
        for figure in ("values", "drops", "link_failures"):
            now = getattr(link, figure)
            added = now - last[figure] if now >= last[figure] else now   # restarted: anew
            totals[figure] += added
            last[figure] = now
            sample[figure] = totals[figure]
            if figure == "values":
                sample["values_per_s"] = round(added / max(1e-9, at - last["at"]), 1)
        interval = latencies.since(link.latency_counts, last["counts"])
        last["counts"], last["at"] = dict(link.latency_counts), at
        for index, count in interval.items():
            totals["counts"][index] = totals["counts"].get(index, 0) + count
        sample.update(_percentiles(interval))
        return sample

    def _node_sample(self, node: str, stats: SystemStats) -> dict[str, Any]:
        health = stats.nodes.get(node)
        readings: dict[str, Any] = {}
        if health is not None and health.up and health.silent_s < SILENT_S:
            with contextlib.suppress(ModuleNotFound, RuntimeFailure, RuntimeTimeout):
                readings = self.run.state(self.probes[node], timeout=1.0)["readings"]
        return {"up": bool(health and health.up), "cpu": readings.get("cpu"),
                "cpu_per_core": readings.get("cpu_per_core"),
                "memory_available": readings.get("memory_available")}

    def _mark_events(self) -> None:
        with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
            for event in self.run.events(self._events_seen):
                self._events_seen = event.seq
                if event.kind in EVENTS_MARKED:
                    self.mark(event.kind, event.subject, at=event.time - self._wall_started,
                              **plain(event.detail))
                if event.kind == "node_joined":        # its probe went with it: again
                    self._add_probes()

    def _progress(self, at: float, stats: SystemStats) -> None:
        latest = self.samples[-1]
        rate = sum(link["values_per_s"] for link in latest["links"].values()
                   if not math.isnan(link["values_per_s"]))          # (a silent one's)
        drops = sum(link["drops"] for link in latest["links"].values())
        failures = sum(link["link_failures"] for link in latest["links"].values())
        cpus = " ".join(f"{name} {node['cpu']:.0f}%" if node["cpu"] is not None else
                        f"{name} {'-' if node['up'] else 'LOST'}"
                        for name, node in latest["nodes"].items())
        line = (f"{at:5.0f}/{self.options.seconds:g} s  {rate:8.0f} values/s  drops {drops}  "
                f"failures {failures}  kills {self.counts['kills']}  moves "
                f"{self.counts['migrations']}  cpu {cpus}")
        if self.out.isatty():
            self.out.write("\r" + line + "\x1b[K")
        elif at - self._last_printed >= PLAIN_EVERY_S:
            self._last_printed = at
            self.out.write(line + "\n")
        self.out.flush()

    def report(self) -> dict[str, Any]:
        duration = self.samples[-1]["t"] if self.samples else 0.0
        links = {}
        for key, last in self._links.items():
            totals = last["totals"]
            links[key] = {"values": totals["values"], "drops": totals["drops"],
                          "link_failures": totals["link_failures"],
                          "values_per_s": round(totals["values"] / max(duration, 1e-9), 1),
                          **_percentiles(totals["counts"])}
        nodes = {}
        for name in self.plan.nodes:
            cpu = [s["nodes"][name]["cpu"] for s in self.samples
                   if s["nodes"][name]["cpu"] is not None]
            memory = [s["nodes"][name]["memory_available"] for s in self.samples
                      if s["nodes"][name]["memory_available"] is not None]
            nodes[name] = {"cpu_mean": round(sum(cpu) / len(cpu), 1) if cpu else None,
                           "cpu_max": round(max(cpu), 1) if cpu else None,
                           "memory_available_min": min(memory) if memory else None}
        kinds = [mark["kind"] for mark in self.marks]
        return plain({
            "schema": SCHEMA, "system": self.plan.name,
            "options": {**dataclasses.asdict(self.options),
                        "kill_among": self.kill_among, "migrate_among": self.migrate_among},
            # (the system's events are marked at their own time when next polled: sorted,
            # a node lost before it was uncut reads so even if the poll came after)
            "started": self._wall_started, "samples": self.samples,
            "marks": sorted(self.marks, key=lambda mark: mark["t"]),
            "summary": {"duration_s": duration,
                        "values_per_s": round(sum(link["values_per_s"]
                                                  for link in links.values()), 1),
                        **self.counts, "restarts": kinds.count("module_restarted"),
                        "modules_failed": kinds.count("module_failed"),
                        "nodes_lost": kinds.count("node_lost"),
                        "failovers": kinds.count("module_failed_over"),
                        "nodes_joined": kinds.count("node_joined"),
                        "links": links, "nodes": nodes}})


def _measured(stats: SystemStats) -> dict[str, LinkStats]:
    """The system's links, without those feeding the probes."""
    return {key: link for key, link in stats.links.items()
            if not link.dst.startswith(PROBE_PREFIX)}


@contextlib.contextmanager
def _problem(problems: list[str], option: str) -> Iterator[None]:
    """A ValueError inside the block is one more problem with ``option``."""
    try:
        yield
    except ValueError as exc:
        problems.append(f"{option}: {exc}")


def _percentiles(counts: dict[int, int]) -> dict[str, float]:
    return {f"latency_p{q}_s": latencies.percentile(counts, q) for q in (50, 90, 99)}


def summary_text(report: dict[str, Any]) -> str:
    """A few lines for the terminal: totals, then one line per link and per node."""
    summary = report["summary"]
    lines = [f"{report['system']}: {summary['duration_s']:.0f} s, "
             f"{summary['values_per_s']:.0f} values/s, kills {summary['kills']}, "
             f"restarts {summary['restarts']}, moves {summary['migrations']}"
             + (f" ({failed} failed)" if (failed := summary["migrations_failed"]) else "")
             + ", "
             f"cuts {summary['cuts']}, nodes lost {summary['nodes_lost']}, failovers "
             f"{summary['failovers']}, nodes rejoined {summary['nodes_joined']}"]
    for key, link in summary["links"].items():
        p99 = link["latency_p99_s"]
        lines.append(f"  {key}: {link['values']} values ({link['values_per_s']:.0f}/s), "
                     f"drops {link['drops']}, failures {link['link_failures']}, p99 "
                     + ("-" if p99 is None else f"{p99 * 1e3:.2f} ms"))
    for name, node in summary["nodes"].items():
        if node["cpu_mean"] is not None:
            lines.append(f"  node {name}: cpu mean {node['cpu_mean']:.0f}%, max "
                         f"{node['cpu_max']:.0f}%")
    return "\n".join(lines)
