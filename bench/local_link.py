"""Throughput of one link: PB3A against multiprocessing.Queue and raw ZeroMQ.

``local_link.py`` measures a local link (two worker processes on one node: a
shared-memory ring); ``local_link.py --remote`` a link between two embedded nodes
(authenticated ZeroMQ PUB/SUB with sequence numbers, flow control and the receiving
node's bridge), against raw pyzmq PUSH/PULL over tcp on loopback, with the goal of
issue 16: every PB3A row at least ``REMOTE_GOAL`` (0.7) times it, same run.

What is measured: values delivered / (receiver's last receipt - sender's first send),
both read from CLOCK_MONOTONIC, which all processes share. Two payloads:

- small: Python ints ``0..N-1``;
- array: one 1 MiB float64 array, written N times; the reader touches one element of
  each (PB3A hands it a read-only view into the ring: zero copy) and reports GB/s.
  PB3A runs it twice, same run, same size: on the reader's dropping ``queue:8`` input
  (``pb3a``), and with the link's policy ``lossless:8`` (``pb3a_lossless``: the writer
  waits for room instead of dropping); the ``lossless`` entry compares the two (rate,
  values lost, lossless/dropping).

How: PB3A goes through the public API only: ``System`` with a writer module
(``IntBurst``/``ArrayBurst``: period 0, one burst of N writes inside ``step``) and an
event-driven reader (``IntCounter``/``ArrayCounter``, a ``queue`` input), each in its
own worker process (the default). The reader records first/last arrival and the count
in its state; ``run.state`` reads them back. One system is launched per payload and
stays up: each repetition is one burst, after a warm-up burst.

The baselines run in the same script, with the same counts, in fork-started child
pairs: ``multiprocessing.Queue`` (put/get, pickling) and pyzmq PUSH/PULL over ipc
(ints as 8 raw bytes; arrays sent ``copy=False`` and read as ``np.frombuffer`` views
of the received frame). Every trial warms up first; repetitions run round robin
(rep-major) so machine noise spreads evenly; figures are medians with min/max, and
ratios are between medians of this run.

For arrays the script also measures the writer's ceiling in the same run: one process
copying the array ``N`` times into shared memory, alternating between two slots
(``copy_ceiling``): the fewest with which a writer can fill one while its reader
holds the other, and the most cache-friendly. A local link cannot beat one copy per
value; the ratio says how close to it PB3A gets, whatever this host's memory speed
that minute.
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing
import os
import socket
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
import zmq
from _common import (
    machine,
    main_guard,
    run_forked,
    steal_report,
    steal_seconds,
    summary,
    wait_for,
)
from _modules import ARRAY_SHAPE, ArrayBurst, ArrayCounter, IntBurst, IntCounter

from pb3a import Module, System
from pb3a.transport.shm import create_segment, segment_name, unlink_segment

REPS = 5
BATCH = 64                 # values per write_many() call in the batched PB3A row
SMALL_N, SMALL_WARM = 50_000, 2_000
ARRAY_N, ARRAY_WARM = 1_000, 50
ARRAY_BYTES = int(np.prod(ARRAY_SHAPE)) * 8
TIMEOUT = 30.0             # bound of any one trial (seconds)
RECV_TIMEOUT = 10.0        # bound of any one blocking receive in a baseline child
GOALS = {"small": ("pb3a >= 5x mp.Queue (msgs/s)", 5.0),
         "array": ("pb3a >= 10 GB/s with zero-copy views", 10.0)}
LOSSLESS = "lossless:8"    # the lossless row's link policy (the dropping row: queue:8)
LOSSLESS_GOAL = 0.9        # lossless at >= 0.9x the dropping policy's rate, nothing lost
LINK = "writer.out->reader.x"
REMOTE_GOAL = 0.7          # a remote link at >= 0.7x raw pyzmq over tcp, same run (issue 16)


# -- PB3A ---------------------------------------------------------------------------
class Pb3aLink:
    """A launched writer -> reader system; every ``burst(n)`` is one trial."""

    def __init__(self, writer: type[Module], reader: type[Module], batch: int = 0,
                 remote: bool = False, policy: str | None = None) -> None:
        system = System(f"bench-{writer.__name__.lower()}-{policy or 'declared'}")
        if remote:
            system.node("a")
            system.node("b")
        # the reader is added (so started) first: ready before values flow
        system.add("reader", reader, node="b" if remote else None)
        system.add("writer", writer, state={"batch": batch}, node="a" if remote else None)
        system.link("writer.out", "reader.x", policy=policy)      # (LINK)
        self.run = system.launch()
        self.bursts = 0
        self.drops = 0

    def burst(self, n: int) -> dict[str, Any]:
        """Write ``n`` values in one burst; wait until all are delivered (or dropped)."""
        run = self.run
        run.set_state("reader", count=0, views=0, first=math.nan, last=math.nan)
        self.bursts += 1
        run.set_state("writer", count=n, go=self.bursts)
        drops_before = self.drops

        arrived = [-1]

        def finished() -> tuple[dict[str, Any], int] | None:
            state = run.state("reader")
            if arrived[0] < state["count"] < n:     # (still arriving: no stats asked)
                arrived[0] = state["count"]
                return None
            arrived[0] = state["count"]
            # (the link's drops, not the reader's: values a remote link's sender did not
            # send, slower than its writer, are counted by the follower, and its reader
            # only learns of drops as a value arrives: none came after the last ones)
            drops = run.stats().links[LINK].drops
            return (state, drops) if state["count"] + drops - drops_before >= n else None

        try:
            reader, self.drops = wait_for(finished, TIMEOUT, f"{n} values at the reader",
                                          poll=0.05)
        except TimeoutError as exc:
            state = {k: v for k, v in run.state("reader").items() if k != "touched"}
            raise TimeoutError(f"{exc}; reader state: {state}, link: "
                               f"{run.stats().links[LINK]}") from None
        writer = run.state("writer")
        return {"count": reader["count"], "seconds": reader["last"] - writer["started"],
                "drops": self.drops - drops_before, "views": reader["views"],
                "writer_seconds": writer["finished"] - writer["started"]}

    def close(self) -> None:
        self.run.close()


# -- baselines (each function runs in a forked child) -------------------------------
def _endpoints(kind: str, channel: Any, role: str, array: bool) -> tuple[Any, Any]:
    """``(io, close)`` of one end: ``io(value)`` sends (role "send"), ``io()`` receives."""
    if kind == "mp_queue":
        if role == "send":
            return channel.put, lambda: None
        return (lambda: channel.get(timeout=RECV_TIMEOUT)), lambda: None
    context = zmq.Context()
    sock = context.socket(zmq.PUSH if role == "send" else zmq.PULL)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.SNDTIMEO if role == "send" else zmq.RCVTIMEO, int(RECV_TIMEOUT * 1000))
    (sock.connect if role == "send" else sock.bind)(channel)

    def close() -> None:
        sock.close(linger=0)
        context.term()

    if role == "send" and array:
        return (lambda value: sock.send(value, copy=False)), close
    if role == "send":
        return (lambda value: sock.send(value.to_bytes(8, "little", signed=True))), close
    if array:
        return (lambda: np.frombuffer(sock.recv(copy=False).buffer, np.float64)), close
    return (lambda: int.from_bytes(sock.recv(), "little", signed=True)), close


def _sender(kind: str, channel: Any, array: bool, n: int, warm: int, warmed: Any,
            finished: Any, conn: Any) -> None:
    send, close = _endpoints(kind, channel, "send", array)
    payload = np.ones(ARRAY_SHAPE) if array else None
    for i in range(warm):
        send(payload if array else i)
    warmed.wait(RECV_TIMEOUT)
    started = time.monotonic()
    for i in range(n):
        send(payload if array else i)
    conn.send(started)
    finished.wait(TIMEOUT)        # keep the channel open until everything is received
    close()


def _receiver(kind: str, channel: Any, array: bool, n: int, warm: int, warmed: Any,
              finished: Any, conn: Any) -> None:
    receive, close = _endpoints(kind, channel, "recv", array)
    for _ in range(warm):
        receive()
    warmed.set()
    count, first, last, touched = 0, math.nan, math.nan, 0.0
    with contextlib.suppress(Exception):           # a timeout ends the trial short
        for _ in range(n):
            value = receive()
            if array:
                touched += value[0]                 # touch the array, do not copy it
            last = time.monotonic()
            if not count:
                first = last
            count += 1
    finished.set()
    conn.send({"count": count, "first": first, "last": last})
    close()


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def baseline(kind: str, array: bool, n: int, warm: int, tmp: str) -> dict[str, Any]:
    """One trial of a baseline transport in a fresh pair of forked processes."""
    ctx = multiprocessing.get_context("fork")
    warmed, finished = ctx.Event(), ctx.Event()
    if kind == "mp_queue":
        channel: Any = ctx.Queue()
    elif kind == "zmq_tcp":
        channel = f"tcp://127.0.0.1:{_free_port()}"
    else:
        channel = f"ipc://{tmp}/link-{os.getpid()}-{time.monotonic_ns()}"
    received, started = run_forked(
        [(_receiver, (kind, channel, array, n, warm, warmed, finished)),
         (_sender, (kind, channel, array, n, warm, warmed, finished))], TIMEOUT)
    if kind == "mp_queue":
        channel.close()
        channel.cancel_join_thread()
    if started is None or received is None:
        raise RuntimeError(f"{kind} trial failed (a child timed out or died)")
    return {"count": received["count"], "seconds": received["last"] - started, "drops": 0}


def _copy_ceiling(n: int, warm: int, conn: Any) -> None:
    """The writer's limit: copy the array ``n`` times into two shared slots in turn."""
    segment = create_segment(segment_name("benchcopy"), 2 * ARRAY_BYTES)
    try:
        slots = np.ndarray((2, *ARRAY_SHAPE), np.float64, segment.buf)
        payload = np.ones(ARRAY_SHAPE)
        for i in range(warm):
            np.copyto(slots[i % len(slots)], payload)
        started = time.monotonic()
        for i in range(n):
            np.copyto(slots[i % len(slots)], payload)
        conn.send({"count": n, "seconds": time.monotonic() - started, "drops": 0})
        del slots
    finally:
        unlink_segment(segment)


def copy_ceiling(n: int, warm: int) -> dict[str, Any]:
    """One trial of ``_copy_ceiling`` in a fresh forked process."""
    (result,) = run_forked([(_copy_ceiling, (n, warm))], TIMEOUT)
    if result is None:
        raise RuntimeError("copy ceiling trial failed (the child timed out or died)")
    return result


# -- the suite ----------------------------------------------------------------------
def suite(payload: str, tmp: str, remote: bool = False) -> dict[str, Any]:
    """All repetitions of one payload ("small" or "array"), round robin over methods."""
    array = payload == "array"
    n, warm = (ARRAY_N, ARRAY_WARM) if array else (SMALL_N, SMALL_WARM)
    if remote:
        n, warm = n // 5, warm // 5
    links = {"pb3a": Pb3aLink(ArrayBurst, ArrayCounter, remote=remote) if array
             else Pb3aLink(IntBurst, IntCounter, remote=remote)}
    if array:       # the same link, lossless: the writer waits instead of dropping
        links["pb3a_lossless"] = Pb3aLink(ArrayBurst, ArrayCounter, remote=remote,
                                          policy=LOSSLESS)
    else:           # the same link written with write_many(), 64 values per call
        links["pb3a_write_many"] = Pb3aLink(IntBurst, IntCounter, batch=BATCH, remote=remote)
    baselines: tuple[str, ...] = ("zmq_tcp",) if remote else ("mp_queue", "zmq_ipc")
    if array and not remote:
        baselines += ("copy_ceiling",)
    trials: dict[str, list[dict[str, Any]]] = {name: [] for name in links}
    trials.update({kind: [] for kind in baselines})
    steal0, t0 = steal_seconds(), time.monotonic()
    try:
        for link in links.values():
            link.burst(warm)
        for _ in range(REPS):
            for name, link in links.items():
                trials[name].append(link.burst(n))
            for kind in baselines:
                trials[kind].append(copy_ceiling(n, warm) if kind == "copy_ceiling"
                                    else baseline(kind, array, n, warm, tmp))
    finally:
        for link in links.values():
            link.close()
    wall = time.monotonic() - t0

    unit, scale = ("gb_per_s", ARRAY_BYTES / 1e9) if array else ("msgs_per_s", 1.0)
    digits = 3 if array else 0

    def rates(runs: list[dict[str, Any]], seconds: str = "seconds") -> dict[str, Any]:
        return summary([t["count"] * scale / t[seconds] for t in runs], digits)

    figures = {name: rates(runs) for name, runs in trials.items()}
    ratio = {f"{mine}/{name}": round(figures[mine]["median"] / figures[name]["median"], 2)
             for mine in links for name in baselines}
    delivered = sum(t["count"] for t in trials["pb3a"])
    if remote:                              # every PB3A row against the wire
        measured = {mine: ratio[f"{mine}/zmq_tcp"] for mine in links}
        goal: dict[str, Any] = {"goal": {
            "text": f"pb3a >= {REMOTE_GOAL}x raw pyzmq over tcp", "goal": REMOTE_GOAL,
            "measured": measured,
            "met": {mine: value >= REMOTE_GOAL for mine, value in measured.items()}}}
    else:
        goal_text, limit = GOALS[payload]
        measured = figures["pb3a"]["median"] if array else ratio["pb3a/mp_queue"]
        goal = {"goal": {"text": goal_text, "measured": measured, "met": measured >= limit}}
    if array:
        goal["lossless"] = lossless_report(figures, trials, n)
    return {
        "payload": "float64[131072] (1 MiB)" if array else "int 0..N-1",
        "values_per_trial": n, "warm_up_values": warm, "reps": REPS,
        unit: figures, "ratios_of_medians": ratio, **goal,
        # how fast the PB3A writer got rid of the burst (its write() calls alone)
        f"pb3a_writer_side_{unit}": rates(trials["pb3a"], "writer_seconds"),
        "pb3a_drops": sum(t["drops"] for t in trials["pb3a"]),
        "pb3a_read_only_view_share": round(
            sum(t["views"] for t in trials["pb3a"]) / max(1, delivered), 3),
        "steal": steal_report(steal_seconds() - steal0, wall),
    }


def lossless_report(figures: dict[str, Any], trials: dict[str, list[dict[str, Any]]],
                    n: int) -> dict[str, Any]:
    """The lossless row against the dropping one: rates, values lost, their ratio."""
    lost = {name: sum(n - t["count"] for t in trials[name]) for name in ("pb3a", "pb3a_lossless")}
    ratio = round(figures["pb3a_lossless"]["median"] / figures["pb3a"]["median"], 2)
    return {
        "policies": {"pb3a": "queue:8 (dropping)", "pb3a_lossless": LOSSLESS},
        "gb_per_s_median": {name: figures[name]["median"] for name in lost},
        "values_lost": lost, "values_sent": n * len(trials["pb3a"]),
        "ratio_lossless_to_dropping": ratio,
        "goal": {"text": f"lossless >= {LOSSLESS_GOAL}x dropping, with zero loss",
                 "measured": ratio,
                 "met": ratio >= LOSSLESS_GOAL and lost["pb3a_lossless"] == 0},
    }


def body(result: dict[str, Any]) -> None:
    remote = "--remote" in sys.argv[1:]
    result.update(benchmark="remote_link" if remote else "local_link", machine=machine())
    with tempfile.TemporaryDirectory(prefix="pb3a-bench-") as tmp:
        result["small_int"] = suite("small", tmp, remote)
        result["array_1mib"] = suite("array", tmp, remote)


if __name__ == "__main__":
    main_guard(body, {"--remote": "between two nodes (ZeroMQ) instead of on one machine"})
