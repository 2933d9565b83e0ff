"""``WatchedProcess``: a worker process from the forkserver, watched through a pidfd of
its own.

multiprocessing learns how a forkserver's child ended from the forkserver, which writes
its exit status to a pipe. A forkserver that dies (SIGKILL, the OOM killer) closes all
those pipes at once, and every worker it had started looked dead (exit code 255) while
it ran on. A pidfd (Linux 5.3) becomes readable when that one process ends, whoever its
parent is, and a signal sent through it cannot reach another process that took its
number. The exit status still comes from the forkserver's pipe, read once the pidfd
says the process ended.
"""

from __future__ import annotations

import contextlib
import multiprocessing.process
import os
import select
import signal
import threading
import weakref
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Iterator

# How long an ended worker's exit status is waited for from its forkserver: it writes
# it as soon as it reaps the child, unless it is frozen or gone (then it is unknown).
STATUS_WAIT_S = 1.0
# How long a worker is given to be seen ended once a request to it failed: the pipe's
# error may come before its death is seen.
DEATH_SEEN_S = 1.0


def _forget_parents_children() -> None:
    """In a child the program forks itself (``os.fork``), forget the parent's
    ``multiprocessing`` children, which it cannot join. A worker is on that list from
    its start until ``WatchedProcess`` takes it off: a script that forked as its
    system's spare workers booted had its child join one as it exited, which failed
    ('can only join a child process') with a traceback. (A child that multiprocessing
    starts is given an empty list itself.)"""
    multiprocessing.process._children.clear()   # type: ignore[attr-defined]


os.register_at_fork(after_in_child=_forget_parents_children)


class WatchedProcess:
    """A started ``multiprocessing`` process, with the calls the pool makes on it:
    ``is_alive``, ``join``, ``exitcode``, ``terminate``, ``kill``, ``sentinel`` (a
    descriptor readable once it ended) for the pool's monitor, and ``close`` once it
    ended."""

    def __init__(self, process: Any) -> None:
        self._process = process
        self.pid: int = process.pid
        # ProcessLookupError if it ended and was reaped already: its start failed
        self.sentinel: int = os.pidfd_open(process.pid)
        # (the backstop: ``close`` closes it as soon as its owner is done with it)
        self._close = weakref.finalize(self, os.close, self.sentinel)
        self._ended = False
        # One thread at a time reads the status pipe: two at once split its bytes, and
        # one read 255. multiprocessing reads it too, for every child on its list, at
        # each start, from whichever thread starts: the process leaves that list (its
        # pool stops it; it ends by itself with its node's end, a SIGKILL's too).
        self._status_lock = threading.Lock()
        self._status: int | None = None       # its exit status, once read
        self._status_closed = False            # the status pipe closed: _status is all
        # The threads using the pidfd now (a poll, a signal): ``close`` waits for them (a
        # number closed under one could be reused by another descriptor, which it then
        # waited on, or another process's pidfd, which it then signalled).
        self._uses = threading.Condition()
        self._using = 0
        self._closed = False
        multiprocessing.process._children.discard(process)   # type: ignore[attr-defined]

    def is_alive(self) -> bool:
        """Whether the process runs (its forkserver's state does not matter)."""
        return not self._wait(0)

    def join(self, timeout: float | None = None) -> None:
        """Wait up to ``timeout`` seconds for the process to end (None: for good)."""
        self._wait(timeout)

    def ended(self, within: float = DEATH_SEEN_S) -> bool:
        """Whether the process has ended, or ends within ``within`` seconds."""
        return self._wait(within)

    @property
    def exitcode(self) -> int | None:
        """None while it runs; once ended, its status as its forkserver reported it (a
        negative signal number if a signal ended it), None if the forkserver does not
        answer, 255 if it is gone: the status went with it."""
        return self._read_status(STATUS_WAIT_S)

    def terminate(self) -> None:
        """SIGTERM the process, if it has not ended."""
        self._signal(signal.SIGTERM)

    def kill(self) -> None:
        """SIGKILL the process, if it has not ended."""
        self._signal(signal.SIGKILL)

    def close(self, status_wait: float = STATUS_WAIT_S) -> bool:
        """If the process ended, close its pidfd, and the forkserver's status pipe once
        the exit status is read (waited for ``status_wait`` seconds): later calls answer
        from what was seen. Whether both are closed (now or before); nothing is while it
        runs, and the pipe is kept while the status is unknown (call again). (Left to
        the garbage collector, the three descriptors of each worker stayed open long
        after its system's close, in a process that launches one system after
        another.) Only where no other thread may wait on ``sentinel`` (the pool's
        monitor, or once it has ended); this object's own calls in progress are waited
        for."""
        if not self._wait(0):
            return False
        with self._uses:
            # (an ended process's pidfd is readable: a poll in progress returns at once)
            if not self._closed and self._uses.wait_for(lambda: not self._using,
                                                        STATUS_WAIT_S):
                self._closed = True
                self._close()
        if self._read_status(status_wait) is not None:
            with self._status_lock:
                if not self._status_closed:
                    self._process.close()       # (its status is read: nothing is lost)
                    self._status_closed = True
        return self._closed and self._status_closed

    def _read_status(self, wait: float) -> int | None:
        """The exit status, waited for up to ``wait`` seconds once the process ended."""
        if not self._wait(0):
            return None
        with self._status_lock:
            if self._status is None and not self._status_closed:
                self._process.join(wait)
                self._status = self._process.exitcode
            return self._status

    def _wait(self, timeout: float | None) -> bool:
        """Whether the process ended, waiting up to ``timeout`` seconds for it."""
        if not self._ended:
            with self._pidfd() as pidfd:
                if pidfd is not None:
                    poller = select.poll()
                    poller.register(pidfd, select.POLLIN)
                    if poller.poll(None if timeout is None else timeout * 1000):
                        self._ended = True
        return self._ended

    def _signal(self, number: int) -> None:
        if self._ended:
            return
        with self._pidfd() as pidfd, contextlib.suppress(ProcessLookupError):
            if pidfd is not None:                  # (ProcessLookupError: it ended meanwhile)
                signal.pidfd_send_signal(pidfd, number)

    @contextlib.contextmanager
    def _pidfd(self) -> Iterator[int | None]:
        """The pidfd, kept open while inside; None if it is closed (the process ended)."""
        with self._uses:
            usable = not self._closed
            self._using += usable
        if not usable:
            yield None
            return
        try:
            yield self.sentinel
        finally:
            with self._uses:
                self._using -= 1
                self._uses.notify_all()
