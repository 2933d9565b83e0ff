"""``Snapshot``: a retired module's state and unconsumed inputs, laid out in shared
memory, so that a migration moves big states without copying them through pipes and
sockets.

``capture`` pickles with cloudpickle, protocol 5, and out-of-band buffers: numpy
arrays (and other large contiguous buffers) are not copied into the pickle but
written, each aligned, after it in one segment. The segment's owner made room for
it beforehand (``make_room``, sized by ``measure``), outside the migration's pause:
writing into pages already allocated is about twice as fast. ``restore`` maps the
segment copy-on-write and unpickles with the buffers as views of the mapping: the
arrays at the destination use the segment's pages, nothing is copied, and what the
module writes stays its own (the segment stays as captured, for a migration that has
to land at its source again). Between machines, ``carry`` takes the parts out of the
segment as bytes, and ``lay_out`` writes them into a segment on the other machine;
through a node's control channel, whose messages are bounded, they go in pieces
(``read_piece``, ``write_piece``: see ``pb3a.node.remote``).

Whoever named the segment (its executor, whose pid the name carries) makes room for
it and unlinks it (``unlink_name``); mappings outlive the name.
"""

from __future__ import annotations

import mmap
import os
import pickle
import time
from dataclasses import dataclass
from typing import Any

import cloudpickle

from pb3a.transport import pickling
from pb3a.transport.shm import segment_path, unlink_name

_ALIGN = 64                     # each buffer starts on a cache line (numpy wants alignment)


@dataclass(frozen=True)
class Snapshot:
    """Where a captured module is: a segment on its machine, or its parts themselves."""

    segment: str                            # the segment holding the parts ("": carried)
    parts: tuple[tuple[int, int], ...]      # (offset, size): the pickle, then each buffer
    carried: tuple[bytes, ...] = ()         # the parts, on their way to another machine
    capture_s: float = 0.0                  # how long the source worker took to capture
    staged: bool = False                    # its segment was written here in pieces: the
                                            # one who lands it unlinks it

    @property
    def nbytes(self) -> int:
        """The size of the capture: the pickle and its out-of-band buffers."""
        return sum(size for _, size in self.parts)

    @staticmethod
    def measure(value: Any) -> int:
        """The segment size a capture of ``value`` would take (its buffers not copied)."""
        return _layout(_pickled(value))[1]

    @classmethod
    def capture(cls, value: Any, segment: str, since: float) -> Snapshot:
        """Pickle ``value`` into segment ``segment`` (made by ``make_room``, resized to
        fit); ``since`` is when the capture began (``time.perf_counter()``)."""
        parts = _write(segment, _pickled(value))
        return cls(segment, parts, capture_s=time.perf_counter() - since)

    def restore(self) -> Any:
        """The captured value, its buffers mapped (copy-on-write) from the segment."""
        if self.carried:
            raise ValueError("a carried snapshot is restored once laid out (lay_out)")
        fd = os.open(segment_path(self.segment), os.O_RDONLY)
        try:
            mapping = mmap.mmap(fd, _end(self.parts), access=mmap.ACCESS_COPY)
        finally:
            os.close(fd)
        view = memoryview(mapping)
        pickled, *buffers = (view[at:at + size] for at, size in self.parts)
        return cloudpickle.loads(pickled, buffers=buffers)

    def carry(self) -> Snapshot:
        """The same snapshot with its parts as bytes, for another machine."""
        fd = os.open(segment_path(self.segment), os.O_RDONLY)
        try:
            carried = tuple(_read(fd, at, size) for at, size in self.parts)
        finally:
            os.close(fd)
        return Snapshot("", self.parts, carried, self.capture_s)

    def lay_out(self, segment: str) -> Snapshot:
        """A carried snapshot written into a new segment ``segment`` on this machine."""
        views = [memoryview(part) for part in self.carried]
        make_room(segment, _layout(views)[1])
        return Snapshot(segment, _write(segment, views), capture_s=self.capture_s)

    @property
    def end(self) -> int:
        """The size of a segment that holds its parts where they are."""
        return _end(self.parts)


def read_piece(segment: str, offset: int, size: int) -> bytes:
    """``size`` bytes of segment ``segment`` from ``offset``."""
    fd = os.open(segment_path(segment), os.O_RDONLY)
    try:
        return _read(fd, offset, size)
    finally:
        os.close(fd)


def write_piece(segment: str, offset: int, data: bytes) -> None:
    """Write ``data`` into segment ``segment`` (made by ``make_room``) at ``offset``."""
    fd = os.open(segment_path(segment), os.O_RDWR)
    try:
        _pwrite(fd, memoryview(data), offset)
    finally:
        os.close(fd)


def make_room(segment: str, size: int) -> None:
    """Create segment ``segment`` with ``size`` bytes allocated (the owner's side, before
    a capture: ``ENOSPC`` here, if the shared-memory file system is too small, comes
    before anything has paused)."""
    fd = os.open(segment_path(segment), os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        os.posix_fallocate(fd, 0, max(size, 1))
    except BaseException:
        unlink_name(segment)
        raise
    finally:
        os.close(fd)


def _pickled(value: Any) -> list[memoryview]:
    """``value`` pickled: the pickle, then its out-of-band buffers (not copied)."""
    buffers: list[pickle.PickleBuffer] = []
    pickled = pickling.dumps(value, buffer_callback=buffers.append)
    return [memoryview(pickled), *(buffer.raw() for buffer in buffers)]


def _layout(views: list[memoryview]) -> tuple[tuple[tuple[int, int], ...], int]:
    """Where ``views`` go, one after the other and aligned; and where they end."""
    parts, at = [], 0
    for view in views:
        parts.append((at, view.nbytes))
        at += -(-view.nbytes // _ALIGN) * _ALIGN
    return tuple(parts), max(at, 1)


def _end(parts: tuple[tuple[int, int], ...]) -> int:
    at, size = parts[-1]
    return at + size


def _write(segment: str, views: list[memoryview]) -> tuple[tuple[int, int], ...]:
    """Write ``views`` into segment ``segment`` (resized to fit them); their places."""
    parts, end = _layout(views)
    fd = os.open(segment_path(segment), os.O_RDWR)
    try:
        os.ftruncate(fd, end)
        for (offset, _), view in zip(parts, views, strict=True):
            _pwrite(fd, view, offset)
    finally:
        os.close(fd)
    return parts


def _pwrite(fd: int, view: memoryview, offset: int) -> None:
    while view.nbytes:                         # (a write may stop short of the whole)
        written = os.pwrite(fd, view, offset)
        view, offset = view[written:], offset + written


def _read(fd: int, at: int, size: int) -> bytes:
    chunks = []
    while size:
        chunk = os.pread(fd, size, at)
        if not chunk:
            raise EOFError(f"a snapshot segment ends {size} bytes short")
        chunks.append(chunk)
        at, size = at + len(chunk), size - len(chunk)
    return b"".join(chunks)
