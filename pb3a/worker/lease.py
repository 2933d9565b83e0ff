"""``Lease``: how long a worker on a remote node may run its modules unattended.

A remote node's executor holds its own lease from the launcher (``NodeShare``) and
writes where it ends (``time.monotonic``, one clock on one machine) on its node's
``LeaseBoard``, a few bytes of memory every worker of the node maps and reads itself.
A frozen or hung executor cannot fence its workers, so a worker whose lease runs out
stops its own modules (as on SIGTERM) and exits ``LEASE_LAPSED``, while the launcher
starts them elsewhere; no body runs meanwhile (``holds``): that is what keeps a module
from running beside its failed-over copy.

The lease is out only when the executor did not extend it: what the worker's threads
are doing cannot delay its news. (The end used to come as a request on the worker's
pipe, read by a Python thread: a module's C call holding the GIL, a long construction
or any request held that thread, the grants waited unread, and heuristics of time in
which they could have been read, capped at 2 s, told starvation from a dead executor;
past the cap the worker stopped itself while its executor ran, and its modules were
restarted without their state.)
"""

from __future__ import annotations

import logging
import math
import mmap
import os
import signal
import struct
import threading
import time
from typing import TYPE_CHECKING

from pb3a.transport._ringcore import fence

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable

log = logging.getLogger("pb3a.worker")

LEASE_CHECK_S = 0.1      # how often a worker with a lease looks at it
# How long a lease is out before the worker stops itself: an executor whose lease runs
# out fences itself within its own look's 0.1 s and stops its workers (exit 0), and a
# renewal it reads meanwhile still extends its lease (``NodeShare.renew``); the worker's
# own stop is for an executor that cannot (frozen, hung), and comes before the launcher
# starts the modules elsewhere, about 0.5 s after the lease ends (a teardown run later
# would run beside the copy).
LEASE_GRACE_S = 0.2
# How long after its lease's end a fenced worker is gone at the latest, its teardowns
# cut short if need be: the launcher starts its modules elsewhere from LOSS_S -
# HEARTBEAT_S - LEASE_S (0.5 s) after that end (pb3a.node.remote checks it), and a
# teardown run later ran beside the copy (a 1 s one delayed its neighbour's 0.5 s into
# the copy's run: a driver's could switch off a device the copy had just opened).
GONE_BY_S = 0.45
# The exit status of a worker that stopped its modules because its lease lapsed: its
# executor tells it from a stop it asked for (0) and, if its own lease runs, restarts
# the modules (see Restarts.died). A code neither Python nor a shell gives, and few
# programs choose (it was 3: a module's code that exited with 3 was said to have been
# frozen past its lease).
LEASE_LAPSED = 117

# A LeaseBoard's bytes: the number of the write begun last, of the write done last
# (little-endian, 8 bytes: they never wrap), then the end (a native double).
_BEGUN, _DONE, _END = 0, 8, 16
_WIDTH = 8
_SIZE = 24
_TRIES = 50     # reads that find a write under way before the last end read stands


class LeaseBoard:
    """Where a remote node's executor writes its lease's end and its workers read it:
    an anonymous memory file (``memfd_create``), sent to each worker as it starts
    beside its doorbell. Nothing is named in /dev/shm, so nothing is left behind: the
    memory goes with the last process that holds it, a SIGKILLed executor's too.

    No read sees a torn end, whatever the machine splits Python's stores and loads
    into: each byte of the two counts is stored and loaded on its own (a byte cannot
    tear), fenced, in Lamport's orders (1977, "Concurrent reading and writing"): the
    writer counts a write begun (most significant byte first), writes the end, counts
    it done (least significant first); a reader loads the count done (most significant
    first: at most its value as that load ends), the end, the count begun (least
    significant first: at least its value as that load began), and keeps the end only
    if the two are equal: no write ran in between."""

    def __init__(self, fd: int, *, writer: bool = False) -> None:
        self.fd = fd                    # kept by the executor to send; a worker closes it
        self._map = mmap.mmap(fd, _SIZE)
        self._bytes = memoryview(self._map)
        self._writing = threading.Lock() if writer else None
        self._count = 0                 # the writer's writes
        self._last = -math.inf          # the last end read whole (see ``end``)

    @classmethod
    def create(cls) -> LeaseBoard:
        """A new board, the executor's, whose end is ``math.inf`` (no lease: none runs
        before a launcher binds the executor) until it ``write``s one."""
        fd = os.memfd_create("pb3a-lease", os.MFD_CLOEXEC)
        os.ftruncate(fd, _SIZE)
        board = cls(fd, writer=True)
        board.write(math.inf)
        return board

    @classmethod
    def opened(cls, fd: int) -> LeaseBoard:
        """A worker's view of the board sent as ``fd`` (the descriptor is closed: the
        mapping holds the memory)."""
        try:
            return cls(fd)
        finally:
            os.close(fd)

    def write(self, end: float) -> None:
        """The lease now ends at ``end`` (``time.monotonic``)."""
        assert self._writing is not None, "a worker's board is read only"
        with self._writing:
            self._count += 1
            self._store(_BEGUN, reversed(range(_WIDTH)))
            struct.pack_into("d", self._map, _END, end)
            fence()
            self._store(_DONE, range(_WIDTH))

    def end(self) -> float:
        """Where the lease ends now. A read that keeps finding a write under way (the
        executor stopped or starved in the middle of one) gets the last end read whole,
        which that write only extends."""
        for _ in range(_TRIES):
            done = self._load(_DONE, reversed(range(_WIDTH)))
            end = struct.unpack_from("d", self._map, _END)[0]
            fence()
            if self._load(_BEGUN, range(_WIDTH)) == done:
                self._last = end
                return end
        return self._last

    def _store(self, at: int, order: Iterable[int]) -> None:
        for index in order:
            self._bytes[at + index] = (self._count >> 8 * index) & 0xFF
            fence()

    def _load(self, at: int, order: Iterable[int]) -> int:
        count = 0
        for index in order:
            count |= self._bytes[at + index] << 8 * index
            fence()
        return count

    def close(self) -> None:
        self._bytes.release()
        self._map.close()
        if self._writing is not None:
            os.close(self.fd)


class Lease:
    """A worker's lease, read from its node's ``board``; none (an embedded node's
    workers) always holds, and so does one not taken yet (a spare given no module)."""

    def __init__(self, closing: threading.Event, holding: Callable[[], str],
                 board: LeaseBoard | None = None) -> None:
        self._closing = closing        # the worker stops: the watch ends
        self._holding = holding        # what the worker runs, named when the lease lapses
        self._board = board
        self._taken = False
        self._taking = threading.Lock()
        self._known = -math.inf        # the furthest end read (ends only move on, once set)
        self.lapsed = False            # it ran out: the worker exits LEASE_LAPSED

    @property
    def applies(self) -> bool:
        """Whether the worker runs under a lease at all (a remote node's)."""
        return self._board is not None

    def take(self) -> None:
        """The worker runs modules from now on: watch the lease, and stop the worker
        once it has been out for ``LEASE_GRACE_S`` (once; nothing without a board)."""
        with self._taking:
            if self._board is None or self._taken:
                return
            # One end read whole first, the one a read meeting writes falls back on: the
            # watch's first read met a write under way, its executor preempted in it, got
            # none (-inf), and stopped the worker with its lease a second ahead.
            deadline = time.monotonic() + LEASE_GRACE_S
            while self._board.end() == -math.inf and time.monotonic() < deadline:
                time.sleep(0.001)
            self._taken = True
        threading.Thread(target=self._watch, daemon=True, name="pb3a-lease").start()

    def holds(self) -> bool:
        """Whether the worker's modules may run now: no lease, or one that runs (read
        now: a worker let run again after its node was frozen past its lease steps
        nothing, and one frozen alone runs on, its executor's lease running)."""
        if self._board is None or not self._taken:
            return True
        now = time.monotonic()          # (before the read: an end read later is no older)
        if now <= self._known:          # (read again only once past it: a read costs
            return not self.lapsed      # about 2 us, and every body asks)
        end = self._board.end()
        if end < math.inf:              # (inf: no lease yet, before its executor's bind)
            self._known = max(self._known, end)
        return not self.lapsed and now <= end

    def _watch(self) -> None:
        """Stop the worker once its lease has been out for ``LEASE_GRACE_S``: however
        late this thread looks (starved), it reads the end its executor wrote last."""
        assert self._board is not None
        while not self._closing.wait(LEASE_CHECK_S):
            now = time.monotonic()
            if now > self._board.end() + LEASE_GRACE_S:
                self._lapse()
                return

    def _lapse(self) -> None:
        """The lease ran out: stop every module, as a SIGTERM does (once), and be gone
        ``GONE_BY_S`` after the lease's end whatever the teardowns still do."""
        self.lapsed = True
        # The stop first: the log goes to the executor, which is frozen, and its pipe may
        # be full: a log that waited for room there kept the modules running for good.
        os.kill(os.getpid(), signal.SIGTERM)     # (the stop a SIGTERM makes)
        assert self._board is not None
        threading.Thread(target=_gone_by, args=(self._board.end() + GONE_BY_S,),
                         daemon=True, name="pb3a-lease-gone").start()
        # (both causes named: on a cut cable the executor fenced itself, saying so, and
        # this line blamed it alone, at times before the executor's)
        log.error("the worker of %s: its lease ran out, its executor extending it no more "
                  "(the executor fenced itself after losing the launcher, or it is frozen "
                  "or hung): its modules stop", self._holding())


def _gone_by(deadline: float) -> None:
    """End this worker at ``deadline`` (``time.monotonic``), its exit ``LEASE_LAPSED``,
    if its stop has not ended it by then."""
    time.sleep(max(0.0, deadline - time.monotonic()))
    os._exit(LEASE_LAPSED)      # (no teardown, no flush: they would run beside the copy)
