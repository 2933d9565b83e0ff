"""``ShmRing``: a single-producer, single-consumer byte ring in shared memory.

One ring carries one local link between two worker processes. Records are
variable-sized and 64-byte aligned; a record that would straddle the end is
preceded by a pad record. Large arrays are handed to the reader as read-only
views into the ring (zero copy); the bytes stay reserved until the last view
is garbage-collected, then the reader releases them.

A link of pinned large arrays (one shape and dtype) also gets a pool of equal
slots: each array is copied into the lowest free slot and the ring carries only
a small record naming it. Slots come back in any order as their views go, so a
writer whose reader keeps up reuses the same few slots, which stay in cache.

A value received from another node can be written straight into a slot before its
record is staged (``claim``: the remote link decrypts into it, see ``replication``);
staging it then copies nothing. A claimed slot whose value is never staged (its tag
failed, or it was dropped) is freed, and the reader never sees it.

A ring is dropping or lossless, as its link's policy says (a header word set by the
creator). Without room, a dropping ring's writer waits briefly, then drops the value
(the reader counts the sequence gap); a lossless ring's writer waits up to its
timeout, then raises RuntimeTimeout and sends nothing: the value is never dropped.
A value the reader cannot decode (one that pickles but does not unpickle) is skipped
and counted like a drop, on either kind: the records after it still go.

Memory ordering. Every access to the header words goes through the C half,
``_ringcore.RingCore``: the writer stores a record, then publishes ``head`` with
a release store; the reader loads ``head`` with acquire, then reads the records
(and hands bytes back by a release store of ``tail``, which the writer loads with
acquire). The sleep hand-shake is Dekker's: the reader stores ``waiting``, fences,
loads ``head``; the writer stores ``head``, fences, loads ``waiting``; so a
wake-up cannot be lost. The C half also holds the hot path (scalar writes, the
drain loop, the reader's sleep), which after an idle millisecond runs with cold
caches where every Python operation costs microseconds.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import threading
import time
import weakref
from collections import deque
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from pb3a.errors import link_stuck
from pb3a.transport import codec
from pb3a.transport._ringcore import RingCore, segment_size, sleep
from pb3a.transport.shm import attach_segment, close_segment, create_segment, unlink_segment

if TYPE_CHECKING:
    from collections.abc import Sequence

__all__ = ["ZERO_COPY_MIN", "Landed", "RingSize", "ShmRing", "sleep"]

_MAGIC = 0x50423341_52494E47  # "PB3ARING"
_DATA = 512                      # header size; data starts here (page offset 512: 64-aligned)
# word indexes (offset / 8) of the header fields the creator sets (the rest: _ringcore.c)
_W_MAGIC, _W_CAP, _W_SLOTS, _W_SLOT_BYTES, _W_FLAGS = 0, 1, 2, 3, 4
_LOSSLESS = 1                    # flag: the writer waits for room, never drops
_REC_HEAD = 24                   # u32 length, u16 kind, u16 meta length, u64 seq, f64 sent_at
ZERO_COPY_MIN = 64 * 1024        # arrays at least this large are read as views
WRITE_TIMEOUT = 0.1              # how long a writer waits for space before dropping a value
_SPIN_S = 100e-6                 # a lossless writer polls this long for space before sleeping
_ALIGN = 64
_LAYOUTS = 64                    # array record layouts a writer remembers
UNDECODABLE_REPORT_S = 1.0       # a link's undecodable values are logged at most this often
_UNDECODABLE = object()          # what _decode returns for a record it cannot decode

log = logging.getLogger("pb3a.ring")


class RingSize(NamedTuple):
    """What a link's segment holds: ring bytes, a pool of slots for large arrays, and
    whether its writer waits for room rather than drops (a lossless link)."""

    capacity: int
    slots: int = 0
    slot_bytes: int = 0
    lossless: bool = False


def _align(n: int, to: int = _ALIGN) -> int:
    return (n + to - 1) & ~(to - 1)


def _body(kind: int, meta_len: int) -> int:
    """Where a record's payload starts (a SLOT record's: the slot's index)."""
    return _align(_REC_HEAD + meta_len, _ALIGN if kind == codec.ARRAY else 8)


def check_fits(kind: int, meta_len: int, size: int, room: RingSize) -> None:
    """``ValueError``, saying what to declare, unless a value encoded as ``kind`` (with
    ``meta_len`` bytes of meta and ``size`` of payload) fits a ring made with ``room``:
    what a ring's writer checks, for a writer on another node to check before sending."""
    if kind == codec.ARRAY and ZERO_COPY_MIN <= size <= room.slot_bytes:
        return                                        # a slot of the pool takes it
    capacity = _align(max(room.capacity, 4096))       # (as ``create`` makes it)
    if _align(_body(kind, meta_len) + size) > capacity:
        raise _too_large(kind, size, capacity)


def _too_large(kind: int, size: int, capacity: int) -> ValueError:
    # (the ring knows the value, not the port: an Output(object) was told to declare a
    # shape and dtype, which only an np.ndarray output takes)
    fix = ("declare the output as Output(np.ndarray, shape=..., dtype=...), which sizes "
           "its links for such arrays" if kind == codec.ARRAY else
           "values this large need an output of type object (its links have 16 MiB "
           "rings), or send smaller ones")
    return ValueError(f"a value of {size} bytes does not fit this link's {capacity}-byte "
                      f"ring: {fix}")


class Landed:
    """A large array written into a claimed slot of ``ring``, not staged yet: staged
    in that ring, it becomes the slot's record without a copy; anywhere else (or once
    staged) it is read through ``array``. Dropped without being staged, it frees the
    slot (a weak finalizer: no slot leaks whatever path the value takes)."""

    __slots__ = ("__weakref__", "_free", "meta", "nbytes", "ring", "slot")

    def __init__(self, ring: ShmRing, slot: int, meta: bytes, nbytes: int) -> None:
        self.ring, self.slot, self.meta, self.nbytes = ring, slot, meta, nbytes
        self._free = weakref.finalize(self, ring.core.unclaim_slot, slot)

    @property
    def buffer(self) -> memoryview:
        """The slot's bytes, writable: where the value is written before staging."""
        start = self.slot * self.ring.core.stride
        return self.ring._pool[start:start + self.nbytes]

    @property
    def array(self) -> np.ndarray:
        """A read-only view of the value (valid while the slot is claimed: before it is
        staged, or by the one who staged it until the reader may have taken it)."""
        dtype, shape, count = codec.array_meta(self.meta)
        view = np.frombuffer(self.buffer, dtype=dtype, count=count).reshape(shape)
        view.flags.writeable = False
        return view

    @property
    def staged(self) -> bool:
        return not self._free.alive

    def abandon(self) -> None:
        """Never to be staged (its tag failed): the slot is free now."""
        self._free()


class ShmRing:
    """One local link. The executor creates it; the writer and reader attach."""

    def __init__(self, segment: Any, owner: bool) -> None:
        self._seg = segment
        self._owner = owner
        self.core = RingCore(segment.buf)     # the C half (the worker's sleep uses it)
        self.capacity = self.core.capacity
        self._data = segment.buf[_DATA:_DATA + self.capacity]
        core = self.core
        self._pool = segment.buf[core.pool_offset:core.pool_offset + core.slots * core.stride]
        self._slot_views: dict[int, weakref.ref[np.ndarray]] = {}   # reader: slot -> view
        self.name = segment.name.lstrip("/")
        self.lossless = bool(int.from_bytes(segment.buf[8 * _W_FLAGS:8 * _W_FLAGS + 8],
                                            "little") & _LOSSLESS)
        self.label = self.name        # the link, for error messages (its writer sets it)
        self.waits = 0                # writer: writes that waited (or wait) for room ...
        self.wait_s = 0.0             # ... and the seconds they waited
        self._cancelled = False       # writer: the link is being cut; do not wait
        self._through = 0             # writer: pauses under way that let its writes through
        self._through_lock = threading.Lock()
        # reader-side bookkeeping (only the reading process uses these)
        self._leases: deque[list[Any]] = deque()   # [start, end, released, ref] per lease
        self._lease_lock = threading.Lock()
        self._closed = False
        self._undecodable = 0         # values the current drain could not decode ...
        self._first_error = ""        # ... the first one's error ...
        self._unreported = 0          # ... and those not logged yet (at most once a second)
        self._report_at = 0.0
        # writer side: record layout of each array (dtype, shape) this link has carried
        self._layouts: dict[tuple[np.dtype, tuple[int, ...]], tuple[int, bytes, int, int]] = {}

    # -- life cycle ---------------------------------------------------------
    @classmethod
    def create(cls, name: str, capacity: int, slots: int = 0, slot_bytes: int = 0,
               lossless: bool = False) -> ShmRing:
        """Create a ring of ``capacity`` data bytes (rounded up to 64), with a pool of
        ``slots`` slots of ``slot_bytes`` each for arrays that fit one; ``lossless``:
        its writer waits for room instead of dropping."""
        capacity = _align(max(capacity, 4096))
        segment = create_segment(name, segment_size(capacity, slots, slot_bytes))
        try:
            words = segment.buf[:_DATA].cast("Q")
            words[_W_CAP] = capacity
            words[_W_SLOTS] = slots
            words[_W_SLOT_BYTES] = slot_bytes
            words[_W_FLAGS] = _LOSSLESS if lossless else 0
            words[_W_MAGIC] = _MAGIC
            words.release()
            return cls(segment, owner=True)
        except BaseException:       # (Ctrl-C too: nobody else knows of the segment yet)
            unlink_segment(segment)
            raise

    @classmethod
    def attach(cls, name: str) -> ShmRing:
        """Attach to a ring the executor created."""
        segment = attach_segment(name)
        words = segment.buf[:8].cast("Q")
        magic = words[0]
        words.release()
        if magic != _MAGIC:
            close_segment(segment)
            raise ValueError(f"shared-memory segment {name!r} is not a PB3A ring")
        return cls(segment, owner=False)

    def close(self) -> None:
        """Drop this process's mapping (the owner also unlinks the segment)."""
        self._closed = True
        self.core.release()
        with contextlib.suppress(BufferError):   # array views still alive
            self._data.release()
        with contextlib.suppress(BufferError):
            self._pool.release()
        if self._owner:
            unlink_segment(self._seg)
        else:
            close_segment(self._seg)

    # -- writer -------------------------------------------------------------
    # The writer's head, seq and the last tail it saw live in the C half: after an
    # idle millisecond every access to the shared segment costs microseconds
    # (cold caches), so the hot path touches it as little as it can.
    def set_bell(self, fd: int) -> None:
        """Ring this eventfd after publishing when the reader said it is going to sleep."""
        self.core.bell = fd

    def resume_writer(self) -> None:
        """A new writer takes over: slots a dead writer took but never published are free."""
        self.core.resume_writer()

    def write(self, value: Any, timeout: float = WRITE_TIMEOUT) -> bool:
        """Append one value; waits up to ``timeout`` for space.

        Dropping ring: then drops it and returns False; the sequence number advances
        either way, so the reader sees the gap and counts the drop. Lossless ring:
        then raises RuntimeTimeout (naming the link) and sends nothing."""
        core = self.core
        done = core.put(value)                # ints and floats: all in C
        if done < 0:
            done = self._stage(value, time.monotonic(), timeout)
            core.publish()
            if not done:
                self._no_room(timeout, 1)
        elif not done:
            done = self._wait_space(_ALIGN, timeout) and core.put(value) > 0
            if not done:
                self._no_room(timeout, 1)
        return bool(done)

    def write_many(self, values: Sequence[Any], timeout: float = WRITE_TIMEOUT,
                   sent_at: float | None = None) -> int:
        """Append values in order and publish them at once; returns how many fit.

        ``sent_at`` (monotonic) is when they were written, if not now: values that
        came from another node keep their time for the reader's latency figure.
        ``timeout`` bounds the batch's waits for room in all, not per value (a stalled
        reader holds its writer once). Then a dropping ring drops what does not fit
        (gaps the reader counts); a lossless one publishes the values that fit, and
        RuntimeTimeout says how many did not go."""
        if self.lossless:
            return self._write_lossless(values, timeout, sent_at)
        return self._fill(values, sent_at, timeout, drop=True)

    def _write_lossless(self, values: Sequence[Any], timeout: float,
                        sent_at: float | None) -> int:
        written = self.offer(values, sent_at, timeout)
        if written < len(values):
            raise link_stuck(self.label, timeout, len(values) - written)
        return written

    def offer(self, values: Sequence[Any], sent_at: float | None = None,
              timeout: float = 0.0) -> int:
        """Write values in order while they fit, waiting up to ``timeout`` in all for
        room; publish them and return how many went (never drops, never raises for
        want of room). A lossless ring's feeder that must not block (the bridge) offers
        with no timeout and keeps the rest for later."""
        return self._fill(values, sent_at, timeout, drop=False)

    def _fill(self, values: Sequence[Any], sent_at: float | None, timeout: float, *,
              drop: bool) -> int:
        """Stage values in order, waiting up to ``timeout`` in all (not per value) for
        room; a value that finds none is skipped, a gap the reader counts (``drop``), or
        ends the batch. Publish what went; return how many."""
        core = self.core
        now = time.monotonic() if sent_at is None else sent_at   # one time for the batch
        deadline = None
        written = 0
        for value in values:
            done = core.stage(value, now)      # ints and floats: all in C
            if done < 0:                       # (-1 also for an int beyond 64 bits)
                done = self._stage(value, now, 0.0)
            if not done and timeout > 0:
                if deadline is None:
                    deadline = time.monotonic() + timeout
                left = deadline - time.monotonic()
                done = left > 0 and self._stage_waiting(value, now, left)
            if not done:
                if not drop:
                    break
                self._skip()
            written += bool(done)
        core.publish()
        return written

    def _stage_waiting(self, value: Any, now: float, timeout: float) -> bool:
        """Stage one value that did not fit, waiting up to ``timeout`` for room."""
        done = self.core.stage(value, now)
        if done < 0:
            return self._stage(value, now, timeout)
        return self._wait_space(_ALIGN, timeout) and self.core.stage(value, now) > 0

    def claim(self, meta: bytes, nbytes: int) -> Landed | None:
        """A free slot for an array of ``nbytes`` (ARRAY ``meta``) that the caller
        writes in place before staging it (``Landed.buffer``); None if this ring has no
        slot that size or none is free (then stage the array as usual)."""
        if not ZERO_COPY_MIN <= nbytes <= self.core.slot_bytes:
            return None
        slot = self.core.claim_slot()
        return None if slot < 0 else Landed(self, slot, meta, nbytes)

    def _stage_landed(self, landed: Landed, now: float, timeout: float) -> bool:
        """Stage a value already in a claimed slot of this ring: the record only."""
        _, meta, body, length = self._layout(codec.ARRAY, landed.meta, landed.nbytes)
        core = self.core
        done = bool(core.stage_claimed(landed.slot, meta, body, length, now) or (
            timeout > 0 and self._wait_space(length, timeout)
            and core.stage_claimed(landed.slot, meta, body, length, now)))
        if done:
            landed._free.detach()             # the reader's now: it frees the slot
        return done

    def _stage(self, value: Any, now: float, timeout: float) -> bool:
        """Stage one record for anything but an int or float (unpublished); False when
        there was no room. An array is copied once, straight from its own buffer, into
        the ring (one already in a claimed slot of this ring, not at all)."""
        if type(value) is Landed:
            if value.ring is self and not value.staged:
                return self._stage_landed(value, now, timeout)
            value = value.array
        layout = None
        if type(value) is np.ndarray and value.flags.c_contiguous:
            layout = self._layouts.get((value.dtype, value.shape))
        if layout is None:
            kind, meta, payload = codec.encode(value)
            layout = self._layout(kind, meta, codec.payload_size(kind, payload))
            if kind == codec.ARRAY and payload is value:   # the same for every such array
                if len(self._layouts) >= _LAYOUTS:           # (shapes that keep changing)
                    self._layouts.clear()
                self._layouts[value.dtype, value.shape] = layout
        else:
            payload = value
        kind, meta, body, length = layout
        core = self.core
        return bool(core.stage_record(kind, meta, payload, body, length, now) or (
            timeout > 0 and self._wait_space(length, timeout, kind == codec.SLOT)
            and core.stage_record(kind, meta, payload, body, length, now)))

    def _layout(self, kind: int, meta: bytes, size: int) -> tuple[int, bytes, int, int]:
        """``(kind, meta, body, length)`` of a record: where its payload starts, its size.
        An array that fits a slot becomes a SLOT record, whose body is the slot's index."""
        if kind == codec.ARRAY and ZERO_COPY_MIN <= size <= self.core.slot_bytes:
            body = _body(codec.SLOT, len(meta))
            return codec.SLOT, meta, body, _align(body + 8)
        body = _body(kind, len(meta))
        length = _align(body + size)
        if length > self.capacity:
            raise _too_large(kind, size, self.capacity)
        return kind, meta, body, length

    def _skip(self) -> None:
        """A value dropped for want of space: its sequence number is a gap the reader counts."""
        self.core.seq += 1
        self.core.publish()

    def _no_room(self, timeout: float, unsent: int) -> None:
        """A write found no room in time: dropped (a gap) on a dropping ring; on a
        lossless ring nothing is sent and the writer learns it."""
        if self.lossless:
            raise link_stuck(self.label, timeout, unsent)
        self._skip()

    def _wait_space(self, length: int, timeout: float, slot: bool = False) -> bool:
        """Publish what is there, then wait up to ``timeout`` until a ``length``-byte
        record (and a pad before it) fits, and a slot is free if ``slot``; a wait is
        counted in ``waits`` and ``wait_s``. Gives up at once when the link is being cut."""
        core = self.core
        core.publish()
        if core.room(length, slot):
            return True
        start = time.monotonic()
        deadline = start + timeout
        self.waits += 1                   # as it begins: a writer stuck now shows
        # A lossless writer waits often (whenever its reader lags a little): it polls
        # for a moment first, since a reader that keeps up frees room within
        # microseconds and a sleep lasts tens of them, a bubble in the stream.
        spin = start + _SPIN_S if self.lossless else start
        pause = 20e-6
        try:
            while not self._cancelled and (now := time.monotonic()) < deadline:
                if self._through:
                    self._flush_for_pause()
                if now < spin:
                    time.sleep(0)             # (lets the process's other threads run)
                else:
                    time.sleep(pause)
                    pause = min(pause * 2, 1e-3)
                if core.room(length, slot):
                    return True
            return False
        finally:
            self.wait_s += time.monotonic() - start

    def cancel(self) -> None:
        """The link is being cut: a write waiting for room gives up now."""
        self._cancelled = True

    def let_through(self, on: bool) -> None:
        """Writer: a pause (or stop) of the writer begins (``on``) or ends. It waits for
        the writer's call, which may be a write waiting for room here while the reader is
        slow, stopped or paused: while a pause is under way, such a write asks the reader
        to take everything in the ring, room in its input or not, so it goes in and the
        call ends; nothing is lost. Once the last pause ends, the reader takes only what
        its input has room for again. (A write waiting for a slot still waits: the
        reader's views hold the slots.)"""
        if not self.lossless:
            return
        with self._through_lock:       # (pauses may overlap: the last one clears it)
            self._through += 1 if on else -1
            if not self._through:
                self.core.flush = False

    def _flush_for_pause(self) -> None:
        """A write waiting for room while a pause is under way (``let_through``): ask for
        the flush, from the writing thread (whose bell is open while it writes), under the
        lock (a flag set after the last pause ended would unbound the ring for good)."""
        with self._through_lock:
            if self._through and not self.core.flush:
                self.request_flush()

    def request_flush(self) -> None:
        """Writer: ask the reader to take everything in the ring now, room in its input
        or not (a lossless link closing while its reader may be paused), and wake it."""
        self.core.flush = True
        fd = self.core.bell
        if fd >= 0:
            with contextlib.suppress(BlockingIOError):   # rung enough already
                os.write(fd, (1).to_bytes(8, "little"))

    @property
    def flush_requested(self) -> bool:
        """Reader: the writer asked for everything to be taken now (``request_flush``)."""
        return self.core.flush

    # -- reader -------------------------------------------------------------
    def has_data(self) -> bool:
        return self.core.has_data()

    def drain(self, limit: int = 1024) -> tuple[list[Any], float, int]:
        """Decode up to ``limit`` values.

        Returns ``(values, sent_at, gaps)``: ``sent_at`` is when the newest value
        was written (monotonic clock), ``gaps`` how many values the writer dropped,
        plus those that could not be decoded here (skipped, and logged).
        """
        self._undecodable = 0
        values, sent_at, gaps = self.core.drain(limit, self._decode)
        if self._undecodable:
            values = [value for value in values if value is not _UNDECODABLE]
            gaps += self._undecodable
            self._report_undecodable()
        return values, sent_at, gaps

    def _decode(self, kind: int, offset: int, length: int, meta_len: int, start: int) -> Any:
        """A record the C half does not decode itself (anything but int and float). One
        that cannot be decoded (say, a pickled exception whose ``__init__`` takes other
        arguments) is skipped and counted: records keep their bounds, so the ones after
        it still go, where failing the drain would stop the link at it for good."""
        try:
            return self._decode_record(kind, offset, length, meta_len, start)
        except Exception as exc:
            if kind == codec.SLOT:
                self._free_unread_slot(offset, length, meta_len)
            if not self._undecodable:
                self._first_error = f"{type(exc).__name__}: {exc}"   # (text: holds no view)
            self._undecodable += 1
            return _UNDECODABLE

    def _report_undecodable(self) -> None:
        self._unreported += self._undecodable
        now = time.monotonic()
        if now < self._report_at:
            return
        log.error("link %s: %d value(s) could not be decoded by the reader and were "
                  "dropped (counted in the input's drops), e.g. %s",
                  self.label, self._unreported, self._first_error)
        self._unreported = 0
        self._report_at = now + UNDECODABLE_REPORT_S

    def _free_unread_slot(self, offset: int, length: int, meta_len: int) -> None:
        """The slot named by a SLOT record that could not be decoded is free again (no
        view of it will free it), if the record holds a slot of the pool not in view."""
        body = offset + _body(codec.SLOT, meta_len)
        if body + 8 <= offset + length:
            slot = int.from_bytes(self._data[body:body + 8], "little")
            if slot < self.core.slots and slot not in self._slot_views:
                self.core.free_slot(slot)

    def _decode_record(self, kind: int, offset: int, length: int, meta_len: int,
                       start: int) -> Any:
        data = self._data
        if kind == codec.PICKLE and not meta_len:
            return pickle.loads(data[offset + _REC_HEAD:offset + length])
        meta = bytes(data[offset + _REC_HEAD:offset + _REC_HEAD + meta_len])
        body = offset + _body(kind, meta_len)
        if kind == codec.SLOT:
            return self._slot_view(meta, int.from_bytes(data[body:body + 8], "little"))
        payload = data[body:offset + length]
        if kind == codec.ARRAY and offset + length - body >= ZERO_COPY_MIN:
            return self._lease_view(meta, payload, start, start + length)
        return codec.decode_small(kind, meta, payload)

    def _lease_view(self, meta: bytes, payload: memoryview, start: int, end: int) -> np.ndarray:
        dtype, shape, count = codec.array_meta(meta)
        view = np.frombuffer(payload, dtype=dtype, count=count).reshape(shape)
        view.flags.writeable = False
        lease: list[Any] = [start, end, 0, None]
        # When the last reference to the view goes, the weak reference's callback
        # returns the lease (the ref itself lives in the lease until then).
        lease[3] = weakref.ref(view, lambda _, lease=lease: self._return_lease(lease))
        with self._lease_lock:
            self._leases.append(lease)
            self.core.leases = len(self._leases)   # the C drain stops moving the tail
        return view

    def _slot_view(self, meta: bytes, slot: int) -> np.ndarray:
        dtype, shape, count = codec.array_meta(meta)
        if slot >= self.core.slots or count * dtype.itemsize > self.core.slot_bytes:
            raise RuntimeError(f"corrupt ring record: slot {slot} of {self.core.slots} "
                               f"cannot hold {count} x {dtype}: the writer misbehaved")
        start = slot * self.core.stride
        view = np.frombuffer(self._pool, dtype=dtype, count=count, offset=start).reshape(shape)
        view.flags.writeable = False
        # When the last reference to the view goes, the callback frees the slot.
        self._slot_views[slot] = weakref.ref(view, lambda ref: self._free_slot(ref, slot))
        return view

    def _free_slot(self, ref: weakref.ref[np.ndarray], slot: int) -> None:
        if self._slot_views.get(slot) is ref:
            del self._slot_views[slot]
            self.core.free_slot(slot)      # (does nothing once the ring is closed)

    def _return_lease(self, lease: list[Any]) -> None:
        lease[2], lease[3] = 1, None
        if not self._closed:          # a view may outlive the link it came from
            self._release()

    def _release(self) -> None:
        # The tail may pass only records nobody still views, in ring order.
        with self._lease_lock:
            leases = self._leases
            while leases and leases[0][2]:
                leases.popleft()
            self.core.leases = len(leases)
            self.core.store_tail(leases[0][0] if leases else self.core.rpos)

    def resume_reader(self) -> None:
        """A new reader process takes over: views held by a dead reader are gone."""
        self.core.resume_reader()

    def statistics(self) -> dict[str, int]:
        """Bytes in use and counters, for ``stats()``."""
        core = self.core
        head, tail, written = core.counters()
        slots = core.slots_used() if core.slots else 0
        return {"capacity": self.capacity + core.slots * core.slot_bytes,
                "used": head - tail + slots * core.slot_bytes, "written": written}
