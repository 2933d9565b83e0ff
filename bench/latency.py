"""One-way latency of a local link at 1 kHz, and the CPU it costs: PB3A against the
eventfd floor.

What is measured: for each value, receipt time minus the ``time.monotonic()`` the
writer put in it (CLOCK_MONOTONIC is shared by all processes), in microseconds:
median and p99 per repetition; and the CPU each side used over the measurement
window, in percent of one core.

How: PB3A goes through the public API only: a threaded ``Clock`` module (period
0.001 s: write, then sleep a period) feeds an event-driven ``LatencyProbe`` that
stores ``now - value`` in its state while ``recording``; each module runs in its own
worker process (the default). Each repetition launches a fresh system; after a
warm-up the bench starts a recording with ``run.set_state``, waits the nominal
recording time (reading the probe's state takes its lock, so polling early would
delay values), then reads the samples with ``run.state``, and shuts the system down. CPU is psutil's
user+system time of the two worker processes (pids from ``run.stats()``) over the
recording window.

Baseline (the physical floor of a blocking wake-up here): two fork-started
processes; every 1 ms the sender stores a timestamp in a shared page (slot ``tick %
512``, so a late reader never sees a half-written or newer stamp) and writes an
eventfd; the receiver blocks in ``eventfd_read`` and subtracts. Same sample count,
same warm-up, same write-then-sleep pacing; each child measures its own CPU time.

This VM's host sometimes steals a large share of its CPU, which ruins latency
figures: the steal time over each window is reported beside them.
"""

from __future__ import annotations

import mmap
import os
import statistics
import struct
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import psutil
from _common import (
    machine,
    main_guard,
    percentile,
    run_forked,
    steal_report,
    steal_seconds,
    summary,
    wait_for,
)
from _modules import Clock, LatencyProbe

from pb3a import System

REPS = 3
SAMPLES = 3000
WARM_SAMPLES = 500
PERIOD = 0.001
SLOTS = mmap.PAGESIZE // 8     # the floor's tick i stamps slot i % SLOTS: no torn reads
TRIAL_TIMEOUT = 10 * SAMPLES * PERIOD + 10.0
GOALS = {"median_us": 80.0, "p99_us": 200.0, "cpu_pct_of_one_core": 7.0}


def _cpu_seconds(process: psutil.Process) -> float:
    times = process.cpu_times()
    return times.user + times.system


def pb3a_trial() -> dict[str, Any]:
    """Launch ``Clock -> LatencyProbe``, warm up, record SAMPLES values, shut down.

    A fresh system per trial, so that nothing of PB3A runs during the floor's trials.
    """
    system = System("bench-latency")
    system.add("probe", LatencyProbe, state={"limit": SAMPLES})
    system.add("clock", Clock, period=PERIOD)
    system.link("clock.out", "probe.x")
    with system.launch() as run:
        modules = run.stats().modules
        workers = {"reader": psutil.Process(modules["probe"].pid),
                   "writer": psutil.Process(modules["clock"].pid)}
        time.sleep(WARM_SAMPLES * PERIOD)           # warm-up: values flow, none recorded
        values0 = run.stats().links["clock.out->probe.x"].values
        cpu0 = {side: _cpu_seconds(p) for side, p in workers.items()}
        t0 = time.monotonic()
        run.set_state("probe", samples=[], recording=True)

        def recorded() -> dict[str, Any] | None:
            state = run.state("probe")
            return state if len(state["samples"]) >= SAMPLES else None

        # Reading the probe's state takes its lock and pickles the samples: each poll
        # delays the values behind it. So wait the nominal recording time first.
        time.sleep(SAMPLES * PERIOD)
        state = wait_for(recorded, TRIAL_TIMEOUT, f"{SAMPLES} samples", poll=0.25)
        wall = time.monotonic() - t0
        cpu = {side: 100.0 * (_cpu_seconds(p) - cpu0[side]) / wall for side, p in workers.items()}
        values = run.stats().links["clock.out->probe.x"].values - values0
        rate = values / (time.monotonic() - t0)
    return {"samples": state["samples"], "cpu_pct": cpu, "rate_hz": rate}


# -- the eventfd floor (each function runs in a forked child) -------------------------
def _tick_sender(efd: int, page: mmap.mmap, conn: Any) -> None:
    cpu0, t0 = time.process_time(), time.monotonic()
    for i in range(WARM_SAMPLES + SAMPLES):
        if i == WARM_SAMPLES:
            cpu0, t0 = time.process_time(), time.monotonic()
        struct.pack_into("d", page, 8 * (i % SLOTS), time.monotonic())
        os.eventfd_write(efd, 1)
        time.sleep(PERIOD)
    conn.send(100.0 * (time.process_time() - cpu0) / (time.monotonic() - t0))


def _tick_receiver(efd: int, page: mmap.mmap, conn: Any) -> None:
    samples: list[float] = []
    ticks = coalesced = 0
    cpu0, t0 = time.process_time(), time.monotonic()
    while ticks < WARM_SAMPLES + SAMPLES:
        count = os.eventfd_read(efd)           # blocks; the parent bounds the whole trial
        now = time.monotonic()
        ticks += count
        sent = struct.unpack_from("d", page, 8 * ((ticks - 1) % SLOTS))[0]
        if ticks > WARM_SAMPLES:
            if not samples:                    # the measurement window starts here
                cpu0, t0 = time.process_time(), now
            samples.append(now - sent)
            coalesced += count - 1             # ticks that arrived while we were late
    wall = time.monotonic() - t0
    conn.send({"samples": samples, "cpu_pct": 100.0 * (time.process_time() - cpu0) / wall,
               "rate_hz": (ticks - WARM_SAMPLES) / wall, "coalesced": coalesced})


def eventfd_trial() -> dict[str, Any]:
    """One trial of the floor in a fresh pair of forked processes."""
    efd = os.eventfd(0)
    page = mmap.mmap(-1, mmap.PAGESIZE)             # anonymous MAP_SHARED: shared after fork
    try:
        received, sender_cpu = run_forked([(_tick_receiver, (efd, page)),
                                           (_tick_sender, (efd, page))], TRIAL_TIMEOUT)
    finally:
        os.close(efd)
        page.close()
    if received is None or sender_cpu is None:
        raise RuntimeError("eventfd trial failed (a child timed out or died)")
    return {"samples": received["samples"], "rate_hz": received["rate_hz"],
            "cpu_pct": {"reader": received["cpu_pct"], "writer": sender_cpu},
            "coalesced": received["coalesced"]}


# -- the suite --------------------------------------------------------------------------
def describe(trials: list[dict[str, Any]]) -> dict[str, Any]:
    """Latency and CPU figures of one method over its repetitions."""
    micro = [[s * 1e6 for s in t["samples"]] for t in trials]
    medians = [statistics.median(m) for m in micro]
    p99s = [percentile(m, 99) for m in micro]
    return {
        "median_us": summary(medians, 1),
        "p99_us": summary(p99s, 1),
        "max_us": summary([max(m) for m in micro], 1),
        "cpu_pct_of_one_core": {side: summary([t["cpu_pct"][side] for t in trials], 1)
                                for side in ("reader", "writer")},
        "achieved_rate_hz": summary([t["rate_hz"] for t in trials], 0),
        # each repetition beside the steal during it, to tell noise from cost
        "per_rep": [{"samples": len(m), "median_us": round(med, 1), "p99_us": round(p99, 1),
                     "steal_pct_of_all_cpus": t["steal"]["steal_pct_of_all_cpus"]}
                    for m, med, p99, t in zip(micro, medians, p99s, trials, strict=True)],
    }


def body(result: dict[str, Any]) -> None:
    result.update(benchmark="latency", machine=machine(), nominal_rate_hz=1 / PERIOD,
                  samples_per_trial=SAMPLES, warm_up_samples=WARM_SAMPLES, reps=REPS)
    trials: dict[str, list[dict[str, Any]]] = {"pb3a": [], "eventfd_floor": []}
    steal_run, t_run = steal_seconds(), time.monotonic()
    for _ in range(REPS):
        for name, trial in (("pb3a", pb3a_trial), ("eventfd_floor", eventfd_trial)):
            steal0, t0 = steal_seconds(), time.monotonic()
            figures = trial()
            figures["steal"] = steal_report(steal_seconds() - steal0, time.monotonic() - t0)
            trials[name].append(figures)
    methods = {name: describe(runs) for name, runs in trials.items()}
    result["methods"] = methods
    result["eventfd_floor_coalesced_ticks"] = sum(t["coalesced"] for t in trials["eventfd_floor"])
    pb, floor = methods["pb3a"], methods["eventfd_floor"]
    result["ratios_of_medians"] = {
        f"pb3a/eventfd_floor {key}": round(pb[key]["median"] / floor[key]["median"], 2)
        for key in ("median_us", "p99_us")}
    cpu = pb["cpu_pct_of_one_core"]
    measured = {"median_us": pb["median_us"]["median"], "p99_us": pb["p99_us"]["median"],
                "reader_cpu_pct": cpu["reader"]["median"],
                "writer_cpu_pct": cpu["writer"]["median"]}
    limits = {**GOALS, "reader_cpu_pct": GOALS["cpu_pct_of_one_core"],
              "writer_cpu_pct": GOALS["cpu_pct_of_one_core"]}
    result["goals"] = {key: {"limit": limits[key], "measured": value, "met": value <= limits[key]}
                       for key, value in measured.items()}
    result["steal_whole_run"] = steal_report(steal_seconds() - steal_run,
                                             time.monotonic() - t_run)


if __name__ == "__main__":
    main_guard(body, {})
