"""``SocketLoop``: one thread that owns some ZeroMQ sockets.

ZeroMQ sockets must not be used from two threads at once, so every socket of a
follower, control client or control server belongs to one loop: the loop polls
them, runs timers, and runs calls that other threads hand over (``call`` waits
for the result, ``submit`` does not). A PUSH/PULL pair over inproc wakes it.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import secrets
import threading
import time
from typing import TYPE_CHECKING, Any

import zmq

from pb3a.errors import RuntimeTimeout

if TYPE_CHECKING:
    from collections.abc import Callable

log = logging.getLogger("pb3a.loop")

POLL_MS = 50          # longest sleep between timer checks


class SocketLoop:
    """Polls registered sockets and runs handed-over calls, on its own thread."""

    def __init__(self, name: str, context: zmq.Context | None = None) -> None:
        self.context = context or zmq.Context.instance()
        self._handlers: dict[zmq.Socket, Callable[[zmq.Socket], None]] = {}
        self._poller = zmq.Poller()
        self._calls: collections.deque[Callable[[], None]] = collections.deque()
        self._timers: list[list[Any]] = []            # [interval (None: once), next due, fn]
        address = f"inproc://pb3a-loop-{secrets.token_hex(6)}"
        self._wake_r = self.context.socket(zmq.PULL)
        self._wake_r.bind(address)
        self._wake_w = self.context.socket(zmq.PUSH)
        self._wake_w.connect(address)
        self._wake_lock = threading.Lock()            # the one socket other threads touch
        self._poller.register(self._wake_r, zmq.POLLIN)
        self._closing = False
        self._then: Callable[[], None] | None = None     # the owner's part of the close
        self._finished = False
        self._finish_lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def on_loop(self) -> bool:
        return threading.current_thread() is self._thread

    # -- set-up (from any thread: done on the loop's) -------------------------------
    def register(self, sock: zmq.Socket, on_ready: Callable[[zmq.Socket], None]) -> None:
        """Call ``on_ready(sock)`` on the loop whenever ``sock`` has input."""
        def add() -> None:
            self._handlers[sock] = on_ready
            self._poller.register(sock, zmq.POLLIN)
        self.call(add)

    def unregister(self, sock: zmq.Socket) -> None:
        def remove() -> None:
            if self._handlers.pop(sock, None) is not None:
                self._poller.unregister(sock)
        self.call(remove)

    def every(self, interval: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the loop about every ``interval`` seconds."""
        self.call(lambda: self._timers.append([interval, time.monotonic() + interval, fn]))

    def later(self, delay: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` once on the loop, ``delay`` seconds from now (call it on the loop)."""
        self._timers.append([None, time.monotonic() + delay, fn])

    # -- calls from other threads ------------------------------------------------
    def submit(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the loop thread soon; do not wait."""
        if self._closing:
            return
        self._calls.append(fn)
        with self._wake_lock, contextlib.suppress(zmq.Again):   # (full: it wakes anyway)
            if not self._wake_w.closed:
                self._wake_w.send(b"", zmq.NOBLOCK)

    def call(self, fn: Callable[[], Any], timeout: float = 5.0) -> Any:
        """Run ``fn`` on the loop thread and return its result (or raise its error)."""
        if self.on_loop:
            return fn()
        done = threading.Event()
        outcome: list[Any] = [None, None]

        def run() -> None:
            try:
                outcome[0] = fn()
            except BaseException as exc:        # handed back to the caller
                outcome[1] = exc
            finally:
                done.set()
        self.submit(run)
        if not done.wait(timeout):
            raise RuntimeTimeout(f"{self._thread.name}: no answer from its thread in {timeout} s")
        if outcome[1] is not None:
            raise outcome[1]
        return outcome[0]

    def close(self, timeout: float = 2.0, *, wait: bool = True,
              then: Callable[[], None] | None = None) -> None:
        """Stop the thread, then run ``then`` (the owner closing its sockets, if it
        gives one) and close the wake-up sockets, once. Called on the loop's thread, or
        with ``wait`` False, it returns at once and the thread does that as it ends: a
        socket closed under the running loop failed its next poll. So a finalizer may
        call it on any thread, the loop's own too: it then waits for no lock, nor for
        the thread."""
        if not self._closing:
            self._then = then
            self._closing = True
            # (not waiting for the lock: a finalizer may run on a thread that holds it,
            # in ``submit``; its holder wakes the loop anyway, or the loop sees the
            # close within POLL_MS)
            if self._wake_lock.acquire(blocking=False):
                try:
                    with contextlib.suppress(zmq.Again):
                        if not self._wake_w.closed:         # (the thread has ended)
                            self._wake_w.send(b"", zmq.NOBLOCK)
                finally:
                    self._wake_lock.release()
        if self.on_loop or not wait:
            return
        self._thread.join(timeout)
        self._finish()              # (the thread's end did it, or it is stuck: done here)

    def _finish(self) -> None:
        """The end of a close: the owner's ``then``, and the wake-up sockets (once)."""
        with self._finish_lock:
            if self._finished:
                return
            self._finished = True
        if self._then is not None:
            self._guarded(self._then)
        with self._wake_lock:
            self._wake_w.close(0)
        self._wake_r.close(0)

    # -- the thread --------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._turns()
        finally:
            if self._closing:
                self._finish()

    def _turns(self) -> None:
        while not self._closing:
            now = time.monotonic()
            for timer in list(self._timers):
                if now >= timer[1]:
                    if timer[0] is None:
                        self._timers.remove(timer)
                    else:
                        timer[1] = now + timer[0]
                    self._guarded(timer[2])
            wait_ms = POLL_MS                             # (timers added just now count)
            for timer in self._timers:
                wait_ms = min(wait_ms, max(0, int((timer[1] - now) * 1000)))
            try:
                ready = dict(self._poller.poll(wait_ms))
            except zmq.ZMQError:
                if self._closing:
                    return
                raise
            if self._wake_r in ready:
                while self._wake_r.poll(0):
                    self._wake_r.recv()
            while self._calls:
                self._guarded(self._calls.popleft())
            for sock, handler in list(self._handlers.items()):
                if sock in ready:
                    self._guarded(lambda handler=handler, sock=sock: handler(sock))
        while self._calls:          # submitted before the close: an answer, say
            self._guarded(self._calls.popleft())

    def _guarded(self, fn: Callable[[], None]) -> None:
        try:
            fn()
        except Exception:
            log.exception("%s: a task failed; the loop goes on", self._thread.name)
