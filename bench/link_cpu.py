"""Where a remote 1 MiB array link spends its CPU, per thread, against raw pyzmq.

``local_link.py --remote`` says how fast the link is; this says why. It runs the same
PB3A link (two embedded nodes, ``ArrayBurst`` -> ``ArrayCounter``, the public API)
with back-to-back bursts for ``SECONDS``, and raw pyzmq PUSH/PULL over tcp on loopback
(one array sent ``copy=False`` over and over, read as a view) for ``RAW_N`` arrays, and
reads every thread's CPU time from ``/proc/PID/task/TID/stat`` before and after. It
reports, per thread (process role and thread name), microseconds of CPU per array,
and for each side the wall time per array and how busy the CPUs were inside the
bursts (CPU per array / (wall per array x CPUs)): near 1.0 means the link is bound by
CPU, not by waiting.

It also times, in the same run, the two passes the link cannot do without (``auth``):
sealing one array into a fresh frame and opening it into a buffer (``payload_us``).
Their sum is CPU a sealed link spends per array on top of everything raw pyzmq does;
on a CPU whose AES-GCM runs without VAES it alone exceeds raw pyzmq's whole transfer.

Both runs report how long the PB3A writer waited for its follower's acknowledgements
(flow control: ``writer_waits``) beside how long its bursts took: a writer that waits
most of its bursts is held by what comes after it, not by its own thread.

With ``--small`` it does the same for small ints written one ``write()`` each
(``IntBurst`` -> ``IntCounter``, bursts of ``SMALL_BURST`` for ``SECONDS``; raw pyzmq
sends each int as 8 bytes, ``SMALL_RAW_N`` of them), in nanoseconds of CPU per value.

Run: ``.venv/bin/python bench/link_cpu.py`` (about 20 s; ``--small``: about 10 s).
"""

from __future__ import annotations

import glob
import os
import secrets
import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
import psutil
import zmq
from _common import machine, main_guard, run_forked
from _modules import ARRAY_SHAPE, ArrayBurst, ArrayCounter, IntBurst, IntCounter
from local_link import Pb3aLink, _free_port

from pb3a.transport.auth import ClusterKey, Payloads

SECONDS = 6.0              # of PB3A bursts
CRYPTO_N = 200             # arrays sealed and opened to time the two passes
BURST = 500                # arrays per PB3A burst
RAW_N, RAW_WARM = 3_000, 100
SMALL_BURST = 10_000       # ints per PB3A burst (--small)
SMALL_RAW_N = 200_000      # ints raw pyzmq sends (--small)
ARRAY_BYTES = int(np.prod(ARRAY_SHAPE)) * 8
_TICK = os.sysconf("SC_CLK_TCK")


def thread_cpu(pids: list[int]) -> dict[str, tuple[float, str]]:
    """CPU seconds so far of every thread of ``pids``: task path -> (seconds, name)."""
    out = {}
    for pid in pids:
        for task in glob.glob(f"/proc/{pid}/task/*"):
            try:
                with open(f"{task}/stat") as file:
                    stat = file.read()
            except OSError:
                continue                 # (a thread that ended meanwhile)
            name = stat[stat.index("(") + 1:stat.rindex(")")]
            fields = stat[stat.rindex(")") + 2:].split()
            out[task] = ((int(fields[11]) + int(fields[12])) / _TICK, name)
    return out


def per_array(before: dict[str, tuple[float, str]], after: dict[str, tuple[float, str]],
              roles: dict[int, str], n: int, scale: float = 1e6) -> dict[str, float]:
    """CPU per value (microseconds; ``scale=1e9``: nanoseconds) of each thread that
    used any, by role/name."""
    figures: dict[str, float] = {}
    for task, (seconds, name) in after.items():
        used = seconds - before.get(task, (0.0, name))[0]
        if used > 0:
            pid = int(task.split("/")[2])
            key = f"{roles.get(pid, pid)}/{name}"
            figures[key] = figures.get(key, 0.0) + used / n * scale
    return {key: round(value, 1) for key, value in
            sorted(figures.items(), key=lambda item: -item[1])}


def pb3a_side(small: bool = False) -> dict[str, Any]:
    link = (Pb3aLink(IntBurst, IntCounter, remote=True) if small
            else Pb3aLink(ArrayBurst, ArrayCounter, remote=True))
    burst = SMALL_BURST if small else BURST
    try:
        link.burst(burst)                # warm-up
        me = psutil.Process()
        roles = {me.pid: "launcher (nodes a, b: the follower)"}
        modules = link.run.stats().modules
        roles.update({modules[name].pid: f"{name} worker" for name in ("writer", "reader")})
        roles.update({child.pid: "forkserver" for child in me.children(recursive=True)
                      if child.pid not in roles})
        waits_before = link.run.stats().modules["writer"].output_waits["out"]
        before = thread_cpu(list(roles))
        n, busy_s, writing_s, started = 0, 0.0, 0.0, time.monotonic()
        while time.monotonic() - started < SECONDS:
            trial = link.burst(burst)
            n += trial["count"]
            busy_s += trial["seconds"]
            writing_s += trial["writer_seconds"]
        after = thread_cpu(list(roles))
        waits = link.run.stats().modules["writer"].output_waits["out"]
    finally:
        link.close()
    if small:
        side = _small_side(per_array(before, after, roles, n, 1e9), busy_s / n * 1e9, n)
    else:
        side = _side(per_array(before, after, roles, n), busy_s / n * 1e6, n)
    side["writer_waits"] = {"waits": waits.waits - waits_before.waits,
                            "wait_s": round(waits.wait_s - waits_before.wait_s, 3),
                            "writing_s": round(writing_s, 3)}
    return side


def _raw_receiver(port: int, small: bool, report: Any) -> None:
    context = zmq.Context()
    sock = context.socket(zmq.PULL)
    sock.connect(f"tcp://127.0.0.1:{port}")

    def receive() -> None:
        if small:
            int.from_bytes(sock.recv(), "little", signed=True)
        else:
            np.frombuffer(sock.recv(copy=False).buffer, np.float64)[0]
    for _ in range(RAW_WARM):
        receive()
    before = thread_cpu([os.getpid()])
    first = None
    for _ in range(SMALL_RAW_N if small else RAW_N):
        receive()
        first = first or time.monotonic()
    wall = time.monotonic() - first
    report.send((wall, before, thread_cpu([os.getpid()])))
    sock.close(0)
    context.term()


def _raw_sender(port: int, small: bool, report: Any) -> None:
    context = zmq.Context()
    sock = context.socket(zmq.PUSH)
    sock.bind(f"tcp://127.0.0.1:{port}")
    array = np.ones(ARRAY_SHAPE)
    if small:
        send = lambda i: sock.send(i.to_bytes(8, "little", signed=True))  # noqa: E731
    else:
        send = lambda i: sock.send(array, copy=False)  # noqa: E731
    for i in range(RAW_WARM):
        send(i)
    before = thread_cpu([os.getpid()])
    for i in range(SMALL_RAW_N if small else RAW_N):
        send(i)
    report.send((0.0, before, thread_cpu([os.getpid()])))
    sock.close(linger=10_000)            # (every array delivered before it goes)
    context.term()


def raw_side(small: bool = False) -> dict[str, Any]:
    port = _free_port()
    reports = run_forked([(_raw_receiver, (port, small)), (_raw_sender, (port, small))],
                         timeout=60)
    if None in reports:
        raise RuntimeError("a raw pyzmq child died or timed out")
    n, scale = (SMALL_RAW_N, 1e9) if small else (RAW_N, 1e6)
    figures: dict[str, float] = {}
    wall = 0.0
    for role, (seconds, before, after) in zip(("receiver", "sender"), reports, strict=True):
        wall = max(wall, seconds)
        pid = int(next(iter(after)).split("/")[2])
        figures.update(per_array(before, after, {pid: role}, n, scale))
    if small:
        return _small_side(figures, wall / n * 1e9, n)
    return _side(figures, wall / n * 1e6, n)


def _side(threads: dict[str, float], wall_us: float, n: int) -> dict[str, Any]:
    cpu_us = sum(threads.values())
    return {"arrays": n, "gb_per_s": round(ARRAY_BYTES / wall_us / 1e3, 2),
            "wall_us_per_array": round(wall_us, 1), "cpu_us_per_array": round(cpu_us, 1),
            "cpus_busy": round(cpu_us / wall_us / os.cpu_count(), 2),
            "cpu_us_per_array_by_thread": threads}


def _small_side(threads: dict[str, float], wall_ns: float, n: int) -> dict[str, Any]:
    cpu_ns = sum(threads.values())
    return {"values": n, "values_per_s": round(1e9 / wall_ns),
            "wall_ns_per_value": round(wall_ns), "cpu_ns_per_value": round(cpu_ns),
            "cpus_busy": round(cpu_ns / wall_ns / os.cpu_count(), 2),
            "cpu_ns_per_value_by_thread": threads}


def payload_passes() -> dict[str, float]:
    """Median µs to seal one array into a fresh frame and to open it into a reused
    buffer (the writer's and the follower's passes, without the rest of the link)."""
    payloads = Payloads(ClusterKey(secrets.token_bytes(32)), owner=secrets.token_bytes(16))
    array, out = np.random.default_rng(1).random(ARRAY_SHAPE), np.empty(ARRAY_BYTES, np.uint8)
    seal_s, open_s = [], []
    for _ in range(CRYPTO_N):
        started = time.perf_counter()
        counter, frame = payloads.seal(array, b"bound")
        sealed = time.perf_counter()
        payloads.open_into(payloads.owner, counter, b"bound", frame, out)
        seal_s.append(sealed - started)
        open_s.append(time.perf_counter() - sealed)
    return {"seal": round(statistics.median(seal_s) * 1e6, 1),
            "open": round(statistics.median(open_s) * 1e6, 1)}


def body(result: dict[str, Any]) -> None:
    if "--small" in sys.argv[1:]:
        result.update(benchmark="link_cpu_small", machine=machine())
        result["pb3a_remote"] = pb3a_side(small=True)
        result["zmq_tcp"] = raw_side(small=True)
        result["cpu_ratio"] = round(result["pb3a_remote"]["cpu_ns_per_value"]
                                    / result["zmq_tcp"]["cpu_ns_per_value"], 2)
        return
    result.update(benchmark="link_cpu", machine=machine())
    result["pb3a_remote"] = pb3a_side()
    result["zmq_tcp"] = raw_side()
    result["payload_us"] = payload_passes()
    result["cpu_ratio"] = round(result["pb3a_remote"]["cpu_us_per_array"]
                                / result["zmq_tcp"]["cpu_us_per_array"], 2)


if __name__ == "__main__":
    main_guard(body, {"--small": "small values instead of 1 MiB arrays"})
