"""``ShmRing``: a single-producer, single-consumer byte ring in shared memory.

One ring carries one local link between two worker processes. Records are
variable-sized and 64-byte aligned; a record that would straddle the end is
preceded by a pad record. Large arrays are handed to the reader as read-only
views into the ring (zero copy); the bytes stay reserved until the last view
is garbage-collected, then the reader releases them.

Memory ordering. Counters are 8-byte aligned words read and written through a
``memoryview`` cast to ``'Q'``: each access is one plain load or store. The
writer stores the record, then the new ``head``; the reader loads ``head``,
then the record. This is correct on x86-64 (TSO: stores are not reordered with
stores, loads not with loads). Weaker memory models (ARM) would need fences,
which CPython cannot issue; PB3A refuses to create rings there (see
``ShmRing.create``). The sleep hand-shake is Dekker's: the
reader stores ``waiting`` then loads ``head``; the writer stores ``head`` then
loads ``waiting``. TSO may reorder a store with a later load, so both sides
put a full fence between them (``_fence``: a lock acquire is a locked
instruction), and a wake-up cannot be lost.
"""

from __future__ import annotations

import contextlib
import pickle
import platform
import struct
import threading
import time
import weakref
from collections import deque
from typing import TYPE_CHECKING, Any

import numpy as np

from pb3a.transport import codec
from pb3a.transport.shm import attach_segment, close_segment, create_segment, unlink_segment

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

_MAGIC = 0x50423341_52494E47  # "PB3ARING"
_DATA = 512                      # header size; data starts here (page offset 512: 64-aligned)
# word indexes (offset / 8) of the header fields, one cache line each
_W_MAGIC, _W_CAP, _W_HEAD, _W_TAIL, _W_RPOS, _W_SEQ, _W_WAITING = 0, 1, 8, 16, 24, 32, 40
_REC = struct.Struct("<IHHQd")   # length, kind, meta length, seq, sent_at (monotonic)
_REC_INT = struct.Struct("<IHHQdq")     # a record holding an int64 right after the header
_REC_FLOAT = struct.Struct("<IHHQdd")   # ... or a float64
_F64 = struct.Struct("<d")
_SCALARS = {int: codec.INT, float: codec.FLOAT}
_I64_MIN, _I64_MAX = -(1 << 63), (1 << 63) - 1
ZERO_COPY_MIN = 64 * 1024        # arrays at least this large are read as views
WRITE_TIMEOUT = 0.1              # how long a writer waits for space before dropping a value
_ALIGN = 64


def _align(n: int, to: int = _ALIGN) -> int:
    return (n + to - 1) & ~(to - 1)


_fence_lock = threading.Lock()


def _fence() -> None:
    """A full memory barrier: acquiring a lock executes a locked (fencing) instruction."""
    _fence_lock.acquire()
    _fence_lock.release()


class ShmRing:
    """One local link. The executor creates it; the writer and reader attach."""

    def __init__(self, segment: Any, owner: bool) -> None:
        self._seg = segment
        self._owner = owner
        self._words = segment.buf[:_DATA].cast("Q")
        self.capacity = self._words[_W_CAP]
        self._data = segment.buf[_DATA:_DATA + self.capacity]
        self.name = segment.name.lstrip("/")
        # reader-side bookkeeping (only the reading process uses these)
        self._rpos = self._words[_W_RPOS]
        self._leases: deque[list[Any]] = deque()   # [start, end, released, ref] per lease
        self._lease_lock = threading.Lock()
        self.expected_seq = -1
        self._closed = False
        self.wake: Callable[[], None] | None = None   # the writer's doorbell pull
        self.attach_writer()

    # -- life cycle ---------------------------------------------------------
    @classmethod
    def create(cls, name: str, capacity: int) -> ShmRing:
        """Create a ring of ``capacity`` data bytes (rounded up to 64)."""
        if platform.machine().lower() not in ("x86_64", "amd64"):
            raise RuntimeError(
                "PB3A's shared-memory rings rely on x86-64 store ordering; "
                f"this machine is {platform.machine()}")
        capacity = _align(max(capacity, 4096))
        segment = create_segment(name, _DATA + capacity)
        words = segment.buf[:_DATA].cast("Q")
        words[_W_CAP] = capacity
        words[_W_MAGIC] = _MAGIC
        words.release()
        return cls(segment, owner=True)

    @classmethod
    def attach(cls, name: str) -> ShmRing:
        """Attach to a ring the executor created."""
        segment = attach_segment(name)
        if segment.buf[:8].cast("Q")[0] != _MAGIC:
            close_segment(segment)
            raise ValueError(f"shared-memory segment {name!r} is not a PB3A ring")
        return cls(segment, owner=False)

    def close(self) -> None:
        """Drop this process's mapping (the owner also unlinks the segment)."""
        self._closed = True
        for view in (self._words, self._data):
            with contextlib.suppress(BufferError):   # array views still alive
                view.release()
        if self._owner:
            unlink_segment(self._seg)
        else:
            close_segment(self._seg)

    # -- writer -------------------------------------------------------------
    # The writer keeps head, seq and the last tail it saw in local variables:
    # after an idle millisecond every access to the shared segment costs
    # microseconds (cold caches), so the hot path touches it four times.
    def attach_writer(self) -> None:
        """Become the link's (only) writer: continue from the counters in the segment."""
        words = self._words
        self._head, self._seq, self._tail = words[_W_HEAD], words[_W_SEQ], words[_W_TAIL]

    def write(self, value: Any, timeout: float = WRITE_TIMEOUT) -> bool:
        """Append one value; waits up to ``timeout`` for space, then drops it.

        Returns False when dropped. The sequence number advances either way, so
        the reader sees the gap and counts the drop.
        """
        kind = _SCALARS.get(type(value))
        if kind is None or (kind == codec.INT and not _I64_MIN <= value <= _I64_MAX):
            return self.write_many((value,), timeout) == 1
        seq = self._seq                        # the common case, kept short
        self._seq = seq + 1
        self._words[_W_SEQ] = seq + 1
        head = self._put_scalar(self._head, seq, kind, value, time.monotonic(), timeout)
        if head < 0:
            return False
        self._publish(head)
        return True

    def write_many(self, values: Sequence[Any], timeout: float = WRITE_TIMEOUT) -> int:
        """Append values in order and publish them at once; returns how many fit."""
        data, cap = self._data, self.capacity
        seq = self._seq
        self._seq = seq + len(values)
        self._words[_W_SEQ] = self._seq
        head = self._head
        now = time.monotonic()                 # one write time for the whole batch
        written = 0
        for value in values:
            kind = _SCALARS.get(type(value))
            if kind is not None and (kind == codec.FLOAT or _I64_MIN <= value <= _I64_MAX):
                end = self._put_scalar(head, seq, kind, value, now, timeout)
                if end >= 0:
                    head = end
                    written += 1
                seq += 1
                continue
            if type(value) is np.ndarray or type(value) is bytes:
                kind, meta, payload = codec.encode(value)
                size = codec.payload_size(kind, payload)
            else:
                kind, meta, payload = codec.PICKLE, b"", pickle.dumps(value, 5)
                size = len(payload)
            body = _align(_REC.size + len(meta), _ALIGN if kind == codec.ARRAY else 8)
            length = _align(body + size)
            if length > cap:
                raise ValueError(
                    f"a value of {size} bytes does not fit this link's {cap}-byte ring; "
                    "declare shape= and dtype= on the ports, or raise ring_bytes")
            start = self._reserve(head, length, timeout)
            if start < 0:
                seq += 1
                continue                       # dropped: the reader sees the gap
            offset = start % cap
            record = _REC.pack(length, kind, len(meta), seq, now) + meta
            if kind == codec.ARRAY:
                data[offset:offset + len(record)] = record
                target = np.ndarray(payload.shape, payload.dtype, buffer=data,
                                    offset=offset + body)
                np.copyto(target, payload)      # any dtype, 0-d included
                del target
            elif len(record) == body and size <= 4096:     # one copy into the segment
                data[offset:offset + body + size] = record + payload
            else:
                data[offset:offset + len(record)] = record
                data[offset + body:offset + body + size] = payload
            head = start + length
            seq += 1
            written += 1
        self._publish(head)
        return written

    def _put_scalar(self, head: int, seq: int, kind: int, value: int | float, now: float,
                    timeout: float) -> int:
        """Write an int64 or float64 record (the value rides in the header); the new
        head, or -1 if there was no room."""
        start = self._reserve(head, _ALIGN, timeout)
        if start < 0:
            return -1
        (_REC_INT if kind == codec.INT else _REC_FLOAT).pack_into(
            self._data, start % self.capacity, _ALIGN, kind, 0, seq, now, value)
        return start + _ALIGN

    def _reserve(self, head: int, length: int, timeout: float) -> int:
        """Room for a ``length``-byte record at ``head``: its start position (after a pad
        record if it would straddle the end), or -1 if no room came within ``timeout``."""
        cap = self.capacity
        offset = head % cap
        pad = cap - offset if offset + length > cap else 0
        end = head + pad + length
        if end - self._tail > cap:
            self._tail = self._words[_W_TAIL]
            if end - self._tail > cap:
                self._publish(head)            # let the reader see what is there
                if not self._wait_space(end - cap, timeout):
                    return -1
        if pad:
            _REC.pack_into(self._data, offset, pad, codec.PAD, 0, 0, 0.0)
        return head + pad

    def _publish(self, head: int) -> None:
        if head != self._head:
            self._head = head
            self._words[_W_HEAD] = head          # after the records (TSO: store order)
            if self.wake is not None:
                _fence()                         # order the head store before this load
                if self._words[_W_WAITING]:
                    self.wake()                  # the reader said it is going to sleep

    def _wait_space(self, needed_tail: int, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        pause = 20e-6
        while (tail := self._words[_W_TAIL]) < needed_tail:
            if time.monotonic() >= deadline:
                return False
            time.sleep(pause)
            pause = min(pause * 2, 1e-3)
        self._tail = tail
        return True

    # -- reader -------------------------------------------------------------
    def set_waiting(self, flag: bool) -> None:
        """Reader: announce sleep (True) before the last check of ``has_data``."""
        self._words[_W_WAITING] = 1 if flag else 0
        if flag:
            _fence()     # the waiting store must be visible before we load head

    def has_data(self) -> bool:
        return self._words[_W_HEAD] != self._rpos

    def drain(self, limit: int = 1024) -> tuple[list[Any], float, int]:
        """Decode up to ``limit`` values.

        Returns ``(values, sent_at, gaps)``: ``sent_at`` is when the newest value
        was written (monotonic clock), ``gaps`` how many values the writer dropped.
        """
        words, data, cap = self._words, self._data, self.capacity
        head = words[_W_HEAD]
        rpos = start = self._rpos
        values: list[Any] = []
        append = values.append
        gaps = 0
        sent_at = 0.0
        expected = self.expected_seq
        unpack = _REC_INT.unpack_from
        while rpos != head and len(values) < limit:
            offset = rpos % cap
            length, kind, meta_len, seq, sent_at, number = unpack(data, offset)
            begin = rpos
            rpos += length
            if kind == codec.INT:
                append(number)
            elif kind == codec.FLOAT:
                append(_F64.unpack_from(data, offset + _REC.size)[0])
            elif kind == codec.PAD:
                continue
            elif kind == codec.PICKLE and not meta_len:
                append(pickle.loads(data[offset + _REC.size:offset + length]))
            else:
                meta = bytes(data[offset + _REC.size:offset + _REC.size + meta_len])
                body = _align(_REC.size + meta_len, _ALIGN if kind == codec.ARRAY else 8)
                payload = data[offset + body:offset + length]
                if kind == codec.ARRAY and length - body >= ZERO_COPY_MIN:
                    append(self._lease_view(meta, payload, begin, rpos))
                else:
                    append(codec.decode_small(kind, meta, payload))
            if seq != expected and expected >= 0:
                gaps += seq - expected
            expected = seq + 1
        self.expected_seq = expected
        self._rpos = rpos
        if rpos != start:
            words[_W_RPOS] = rpos
            self._release()
        return values, sent_at, gaps

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
        return view

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
            tail = leases[0][0] if leases else self._rpos
        if tail > self._words[_W_TAIL]:
            self._words[_W_TAIL] = tail

    def resume_reader(self) -> None:
        """A new reader process takes over: views held by a dead reader are gone."""
        self._rpos = self._words[_W_RPOS]
        self._words[_W_TAIL] = self._rpos

    def statistics(self) -> dict[str, int]:
        """Bytes in use and counters, for ``stats()``."""
        words = self._words
        return {"capacity": self.capacity, "used": words[_W_HEAD] - words[_W_TAIL],
                "written": words[_W_SEQ]}
