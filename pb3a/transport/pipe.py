"""The ends of a worker's pipe, neither of which ever waits for the other side.

``Outbox`` sends, from the executor to a worker and from the worker back. A side
that reads nothing (stopped, starved, or its reading thread stuck) fills its pipe,
and a plain ``Connection.send`` then waits for room for good: past its caller's
timeout, holding whatever lock its caller holds (a change's configuration lock, a
stop's, a module's). An outbox writes what the pipe takes at once and leaves the
rest, in order, to a thread that runs only while something is left. A message none
of which has gone can be withdrawn: a request whose caller gave up before the other
side read a byte of it never runs later.

``Inbox`` reads, on the executor's side. One thread reads every worker of a node;
a worker frozen halfway through a large message (a checkpoint, a state) held it
waiting for the rest, and every other worker's answers and death with it. An inbox
takes in what the pipe holds and hands out only whole messages.

Messages are framed as ``multiprocessing.connection.Connection`` frames them, and a
descriptor goes as ``multiprocessing.reduction.send_handle`` sends it, so the worker
reads with a plain ``Connection`` (``recv_bytes``, ``reduction.recv_handle``).
"""

from __future__ import annotations

import array
import contextlib
import logging
import os
import select
import socket
import struct
import threading
from collections import deque
from dataclasses import dataclass

log = logging.getLogger("pb3a.pipe")

_LENGTH = struct.Struct("!i")            # Connection's frame header
_LONG_LENGTH = struct.Struct("!Q")       # after a header of -1, for 2 GiB and more
# How often a drain that waits for room looks whether its outbox was closed.
DRAIN_POLL_S = 0.5
# What an inbox asks of its pipe per read (a socket pair holds about 200 KiB).
READ_CHUNK = 256 * 1024


def frame(payload: bytes) -> list[memoryview]:
    """``payload`` with the header ``Connection.recv_bytes`` reads it by (no empty piece:
    a write of nothing would never be done)."""
    if len(payload) > 0x7fffffff:
        header = _LENGTH.pack(-1) + _LONG_LENGTH.pack(len(payload))
    else:
        header = _LENGTH.pack(len(payload))
    return [memoryview(header)] + ([memoryview(payload)] if payload else [])


@dataclass(eq=False)
class Outgoing:
    """One message in an outbox: the bytes still to go, then a descriptor."""

    pieces: list[memoryview]
    fd: int | None = None                  # our duplicate, closed once it went
    started: bool = False                  # some of it went: it can no longer be withdrawn
    done: bool = False                     # all of it went, or it was dropped
    sent: bool = False                     # all of it went

    @classmethod
    def framed(cls, payloads: list[bytes], fd: int | None = None) -> Outgoing:
        """``payloads``, each framed, then a duplicate of ``fd`` (the caller's may close)."""
        return cls([piece for payload in payloads for piece in frame(payload)],
                   None if fd is None else os.dup(fd))

    def _consume(self, count: int) -> None:
        self.started = True
        while count:
            first = self.pieces[0]
            if count < len(first):
                self.pieces[0] = first[count:]
                return
            count -= len(first)
            self.pieces.pop(0)

    def _close_fd(self) -> None:
        if self.fd is not None:
            with contextlib.suppress(OSError):
                os.close(self.fd)
            self.fd = None


class Outbox:
    """The sending end of one pipe (a Unix stream socket): ``put`` never waits."""

    def __init__(self, fileno: int, *, ends_on_break: bool = False) -> None:
        # A duplicate of the pipe's descriptor, so that the drain never writes to a
        # number the connection closed and the system gave to another file; ``close``
        # must therefore be called with the connection's (the worker sees the end of
        # its pipe only once both are closed).
        self._socket = socket.socket(fileno=os.dup(fileno))
        self._lock = threading.Lock()
        self._sent = threading.Condition(self._lock)    # a message went, or was dropped
        self._queue: deque[Outgoing] = deque()
        self._closed = False
        self._draining = False
        # the executor's: broken by a signal (a Ctrl-C), the worker must read the end of
        # its pipe (and exit), not wait for good, alive and unreachable
        self._ends_on_break = ends_on_break

    @property
    def closed(self) -> bool:
        """Whether nothing more goes: closed, or broken (the other end is gone)."""
        return self._closed

    def put(self, payloads: list[bytes], fd: int | None = None) -> Outgoing:
        """Send ``payloads``, each framed, then ``fd`` (duplicated: the caller may close
        its own at once). What the pipe has no room for now goes later, in order;
        ``OSError`` if the pipe is closed or broken (the worker is gone)."""
        item = Outgoing.framed(payloads, fd)
        with self._lock:
            self._enqueue(item)
            self._drain_rest()
        return item

    def withdraw(self, item: Outgoing) -> bool:
        """Take ``item`` back if none of it went; True if so (the worker never sees it)."""
        with self._lock:
            if item.started or item.done:
                return False
            self._queue.remove(item)
            item._close_fd()
            item.done = True
            self._sent.notify_all()
            return True

    def wait_sent(self, item: Outgoing, timeout: float) -> bool:
        """Wait up to ``timeout`` for all of ``item`` to go; True if it did (False: it
        still waits, or was dropped with a broken pipe)."""
        with self._sent:
            return self._sent.wait_for(lambda: item.done, timeout) and item.sent

    def waiting(self) -> int:
        """How many messages wait for room in the pipe."""
        with self._lock:
            return len(self._queue)

    def close(self, timeout: float = 0.0) -> None:
        """Drop what has not gone within ``timeout`` and close our end (with the
        connection's, the other side reads the end of its pipe)."""
        with self._sent:
            self._sent.wait_for(lambda: self._closed or not self._queue, timeout)
            self._break()
            self._socket.close()

    # -- writing (the lock held) -------------------------------------------------------
    def _enqueue(self, item: Outgoing) -> None:
        if self._closed:
            item._close_fd()
            raise BrokenPipeError("its pipe is closed")
        self._queue.append(item)
        if len(self._queue) == 1:
            try:
                self._flush()
            except OSError:
                self._break()
                raise

    def _flush(self) -> None:
        """Write what the pipe takes now, first message first."""
        while self._queue:
            item = self._queue[0]
            try:
                while item.pieces:
                    item._consume(self._socket.sendmsg(item.pieces, (), socket.MSG_DONTWAIT))
                if item.fd is not None:
                    # as multiprocessing.reduction.sendfds: one byte, the count, with it
                    rights = array.array("i", [item.fd])
                    self._socket.sendmsg([b"\x01"], [(socket.SOL_SOCKET, socket.SCM_RIGHTS,
                                                      rights)], socket.MSG_DONTWAIT)
                    item.started = True
                    item._close_fd()
            except BlockingIOError:
                return
            except BaseException:
                # The pipe failed, or a signal's exception (a worker's SIGTERM, a Ctrl-C,
                # a handler's own Exception) was raised as a write returned: how much of
                # it went is unknown, and the other side would read the rest of the
                # stream out of step (or a message twice). Nothing more goes.
                self._break()
                if self._ends_on_break:       # (the worker reads the end of its pipe)
                    with contextlib.suppress(OSError):
                        self._socket.shutdown(socket.SHUT_WR)
                raise
            self._queue.popleft()
            item.done = item.sent = True
            self._sent.notify_all()

    def _drain_rest(self) -> None:
        """Leave what is still queued to the drain thread, started if none runs."""
        if self._queue and not self._draining:
            drain = threading.Thread(target=self._drain, name="pb3a-outbox", daemon=True)
            self._draining = True
            try:
                drain.start()
            except BaseException:
                # (a signal's exception as it starts, or no thread to be had: left set,
                # nothing more ever went; the next put starts one. A second drain, if
                # this one started after all, is harmless: both write under the lock)
                self._draining = False
                raise

    def _break(self) -> None:
        """The pipe is broken (or closed): what waits is dropped, nothing more goes."""
        self._closed = True
        for item in self._queue:
            item._close_fd()
            item.done = True
        self._queue.clear()
        self._sent.notify_all()

    def _drain(self) -> None:
        """Write the rest as the pipe makes room, until nothing is left or it closes."""
        room = select.poll()      # (not select(): it fails for descriptors past 1023)
        while True:
            failure = None
            with self._lock:
                try:
                    if not self._closed:
                        self._flush()
                except OSError:                  # the other side is gone: its death
                    self._break()                # fails the requests that wait on it
                except Exception as exc:         # (left, it would stall them all)
                    failure = exc
                    self._break()
                if self._closed or not self._queue:
                    self._draining = False
                fd = None if not self._draining else self._socket.fileno()
            if failure is not None:    # (not under the lock: a worker's log goes by it)
                log.error("the drain of a worker's pipe failed; it is closed",
                          exc_info=failure)
            if fd is None:
                return
            # Closed meanwhile, its number may be another file's by now: a wait on that
            # ends early or late, and the next pass, under the lock, sees it closed.
            room.register(fd, select.POLLOUT)
            room.poll(DRAIN_POLL_S * 1000)
            room.unregister(fd)


class Inbox:
    """The reading end of one pipe: ``read`` takes what has come, never waiting."""

    def __init__(self, fileno: int) -> None:
        # a duplicate, as the outbox's: ``close`` goes with the connection's
        self._socket = socket.socket(fileno=os.dup(fileno))
        self._buffer = bytearray()
        self._ended = False

    def read(self) -> list[bytes]:
        """The whole messages that came since the last read, oldest first (part of
        one stays for the next read); ``EOFError`` once the pipe ended and every whole
        message was read."""
        while not self._ended:
            try:
                chunk = self._socket.recv(READ_CHUNK, socket.MSG_DONTWAIT)
            except BlockingIOError:
                break
            except ConnectionResetError:
                chunk = b""
            self._buffer += chunk
            self._ended = not chunk
        messages, start = [], 0
        with memoryview(self._buffer) as buffer:     # (a slice of it is not a copy)
            while True:
                size, header = self._frame_at(start)
                if size is None or len(buffer) < start + header + size:
                    break
                messages.append(bytes(buffer[start + header:start + header + size]))
                start += header + size
        del self._buffer[:start]
        if self._ended and not messages:
            raise EOFError("the worker's pipe ended" + (
                " in the middle of a message" if self._buffer else ""))
        return messages

    def _frame_at(self, start: int) -> tuple[int | None, int]:
        """The size of the message whose header begins at ``start``, and the header's
        (None: its header has not all come)."""
        if len(self._buffer) < start + _LENGTH.size:
            return None, 0
        (size,) = _LENGTH.unpack_from(self._buffer, start)
        if size != -1:
            return size, _LENGTH.size
        if len(self._buffer) < start + _LENGTH.size + _LONG_LENGTH.size:
            return None, 0
        return _LONG_LENGTH.unpack_from(self._buffer, start + _LENGTH.size)[0], \
            _LENGTH.size + _LONG_LENGTH.size

    def close(self) -> None:
        """Close our end (with the connection's)."""
        self._socket.close()
