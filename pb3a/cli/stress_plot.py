"""The picture of a ``pb3a stress`` report: per link, values per second and p99 latency
over time; per node, CPU and available memory; the moments of load, cuts, kills and
moves marked on every panel."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

SPANS = {"load": ("load_on", "load_off", "tab:orange", "CPU load"),
         "cut": ("cut", "uncut", "0.6", "node cut")}
MOMENTS = {"kill": ("tab:red", "worker killed"), "migration": ("tab:blue", "module moved"),
           "module_restarted": ("tab:green", "module restarted"),
           "module_failed_over": ("tab:purple", "failed over"),
           "node_lost": ("black", "node lost"), "node_joined": ("tab:gray", "node back")}


def plot(report: dict[str, Any], path: Path) -> bool:
    """Draw ``report`` into ``path`` (PNG); False if matplotlib is missing."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    samples = report["samples"]
    t = [sample["t"] for sample in samples]
    fig, axes = plt.subplots(2, 2, figsize=(12, 7), sharex=True)
    (rates, p99s), (cpus, memory) = axes
    for key in report["summary"]["links"]:
        # (a gap where the reader was silent: its rate, not known, is null in the report)
        rates.plot(t, [_or_nan(s["links"].get(key, {}).get("values_per_s")) for s in samples],
                   label=key)
        p99s.plot(t, [_ms(s["links"].get(key, {}).get("latency_p99_s")) for s in samples],
                  label=key)
    for node in report["summary"]["nodes"]:
        cpus.plot(t, [_or_nan(s["nodes"][node]["cpu"]) for s in samples], label=node)
        memory.plot(t, [_or_nan(s["nodes"][node]["memory_available"]) / 2**30
                        for s in samples], label=node)
    _mark(report["marks"], [rates, p99s, cpus, memory], report["summary"]["duration_s"])
    rates.set_ylabel("values / s")
    p99s.set_ylabel("latency p99 (ms)")
    p99s.set_yscale("log")
    cpus.set_ylabel("CPU busy (%)")
    cpus.set_ylim(0, 105)
    memory.set_ylabel("memory available (GiB)")
    for axis in (cpus, memory):
        axis.set_xlabel("time (s)")
    for axis, title in ((rates, "per link"), (p99s, "per link"), (cpus, "per node, env.cpu"),
                        (memory, "per node, env.memory_available")):
        axis.set_title(title, fontsize=9)
        axis.legend(fontsize=7, loc="upper right")
    handles = [plt.Rectangle((0, 0), 1, 1, color=colour, alpha=0.25)
               for _, _, colour, _ in SPANS.values()]
    handles += [plt.Line2D([], [], color=colour, linestyle=":")
                for colour, _ in MOMENTS.values()]
    labels = [label for *_, label in SPANS.values()] + [label for _, label in MOMENTS.values()]
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8)
    fig.suptitle(f"pb3a stress: {report['system']}")
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return True


def _mark(marks: list[dict[str, Any]], axes: list[Any], end: float) -> None:
    """Shade the spans (load, cuts) and draw a dotted line at each moment."""
    for on, off, colour, _ in SPANS.values():
        opened: dict[str, float] = {}
        for mark in marks:
            if mark["kind"] == on:
                opened[mark["subject"]] = mark["t"]
            elif mark["kind"] == off and mark["subject"] in opened:
                start = opened.pop(mark["subject"])
                for axis in axes:
                    axis.axvspan(start, mark["t"], color=colour, alpha=0.15)
        for start in opened.values():
            for axis in axes:
                axis.axvspan(start, end, color=colour, alpha=0.15)
    for mark in marks:
        if mark["kind"] in MOMENTS:
            for axis in axes:
                axis.axvline(mark["t"], color=MOMENTS[mark["kind"]][0], linestyle=":",
                             linewidth=1)


def _ms(seconds: float | None) -> float:
    return math.nan if seconds is None else seconds * 1e3


def _or_nan(value: float | None) -> float:
    return math.nan if value is None else value
