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

Run: ``.venv/bin/python bench/link_cpu.py`` (about 20 s).
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
from _modules import ARRAY_SHAPE, ArrayBurst, ArrayCounter
from local_link import Pb3aLink, _free_port

from pb3a.transport.auth import ClusterKey, Payloads

SECONDS = 6.0              # of PB3A bursts
CRYPTO_N = 200             # arrays sealed and opened to time the two passes
BURST = 500                # arrays per PB3A burst
RAW_N, RAW_WARM = 3_000, 100
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
              roles: dict[int, str], n: int) -> dict[str, float]:
    """Microseconds of CPU per array of each thread that used any, by role/name."""
    figures: dict[str, float] = {}
    for task, (seconds, name) in after.items():
        used = seconds - before.get(task, (0.0, name))[0]
        if used > 0:
            pid = int(task.split("/")[2])
            key = f"{roles.get(pid, pid)}/{name}"
            figures[key] = round(figures.get(key, 0.0) + used / n * 1e6, 1)
    return dict(sorted(figures.items(), key=lambda item: -item[1]))


def pb3a_side() -> dict[str, Any]:
    link = Pb3aLink(ArrayBurst, ArrayCounter, remote=True)
    try:
        link.burst(BURST)                # warm-up
        me = psutil.Process()
        roles = {me.pid: "launcher (nodes a, b: the follower)"}
        modules = link.run.stats().modules
        roles.update({modules[name].pid: f"{name} worker" for name in ("writer", "reader")})
        roles.update({child.pid: "forkserver" for child in me.children(recursive=True)
                      if child.pid not in roles})
        before = thread_cpu(list(roles))
        n, busy_s, started = 0, 0.0, time.monotonic()
        while time.monotonic() - started < SECONDS:
            trial = link.burst(BURST)
            n += trial["count"]
            busy_s += trial["seconds"]
        after = thread_cpu(list(roles))
    finally:
        link.close()
    return _side(per_array(before, after, roles, n), busy_s / n * 1e6, n)


def _raw_receiver(port: int, report: Any) -> None:
    context = zmq.Context()
    sock = context.socket(zmq.PULL)
    sock.connect(f"tcp://127.0.0.1:{port}")
    for _ in range(RAW_WARM):
        np.frombuffer(sock.recv(copy=False).buffer, np.float64)[0]
    before = thread_cpu([os.getpid()])
    first = None
    for _ in range(RAW_N):
        np.frombuffer(sock.recv(copy=False).buffer, np.float64)[0]
        first = first or time.monotonic()
    wall = time.monotonic() - first
    report.send((wall, before, thread_cpu([os.getpid()])))
    sock.close(0)
    context.term()


def _raw_sender(port: int, report: Any) -> None:
    context = zmq.Context()
    sock = context.socket(zmq.PUSH)
    sock.bind(f"tcp://127.0.0.1:{port}")
    array = np.ones(ARRAY_SHAPE)
    for _ in range(RAW_WARM):
        sock.send(array, copy=False)
    before = thread_cpu([os.getpid()])
    for _ in range(RAW_N):
        sock.send(array, copy=False)
    report.send((0.0, before, thread_cpu([os.getpid()])))
    sock.close(linger=10_000)            # (every array delivered before it goes)
    context.term()


def raw_side() -> dict[str, Any]:
    port = _free_port()
    reports = run_forked([(_raw_receiver, (port,)), (_raw_sender, (port,))], timeout=60)
    if None in reports:
        raise RuntimeError("a raw pyzmq child died or timed out")
    figures: dict[str, float] = {}
    wall = 0.0
    for role, (seconds, before, after) in zip(("receiver", "sender"), reports, strict=True):
        wall = max(wall, seconds)
        pid = int(next(iter(after)).split("/")[2])
        figures.update(per_array(before, after, {pid: role}, RAW_N))
    return _side(figures, wall / RAW_N * 1e6, RAW_N)


def _side(threads: dict[str, float], wall_us: float, n: int) -> dict[str, Any]:
    cpu_us = sum(threads.values())
    return {"arrays": n, "gb_per_s": round(ARRAY_BYTES / wall_us / 1e3, 2),
            "wall_us_per_array": round(wall_us, 1), "cpu_us_per_array": round(cpu_us, 1),
            "cpus_busy": round(cpu_us / wall_us / os.cpu_count(), 2),
            "cpu_us_per_array_by_thread": threads}


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
    result.update(benchmark="link_cpu", machine=machine())
    result["pb3a_remote"] = pb3a_side()
    result["zmq_tcp"] = raw_side()
    result["payload_us"] = payload_passes()
    result["cpu_ratio"] = round(result["pb3a_remote"]["cpu_us_per_array"]
                                / result["zmq_tcp"]["cpu_us_per_array"], 2)


if __name__ == "__main__":
    main_guard(body)
