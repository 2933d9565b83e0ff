"""``RuntimeWait``: a module body waiting for the runtime's answer, and what may happen
on its thread meanwhile.

An agent calls ``self.runtime`` from a body (``step``, ``on_input``, ``setup``), so
it holds its module's lock while the launcher applies the request, and the launcher
may need that lock for the request itself or for another one: a program reading the
agent's state, another agent editing it, a migration pausing it. Waiting there
would be a deadlock. So the lock order is: the launcher's configuration lock first,
then module locks; and a body that waits for the runtime gives way:

- a request that needs the module's lock only for a moment (read or set its
  state) is run on the waiting body's own thread, which holds the lock: the body is
  suspended at a known point, inside its runtime call;
- a request that needs the module stopped (pause for a migration or a relink, swap,
  stop, remove) cancels the wait: the body's runtime call raises ``RuntimeCancelled``
  (a ``RuntimeFailure``, "cancelled: ..."), the body returns, and the lock is free.

A driver waiting for its device (``Driver.request``) gives way too, but takes no
edits: an edit runs the module's own ``set_state``, which may make a request of its
own inside the one waiting (a re-pointed driver reads its new device at once), so it
waits for the request to end, as for any body. Reads run on its thread.

Nothing else ever waits for a module lock while holding one.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from typing import TYPE_CHECKING, Any

from pb3a.errors import PB3AError, RuntimeCancelled, RuntimeFailure, RuntimeTimeout

RUNNING_S = 10.0     # the longest posted work that has begun is waited for past its deadline

if TYPE_CHECKING:
    from collections.abc import Callable


class RuntimeWait:
    """One runtime call (or device request) in progress: the answer to come, and work
    posted meanwhile (edits of the module's state only if it ``takes_edits``)."""

    def __init__(self, what: str, takes_edits: bool = True) -> None:
        self.what = what                          # the request, for messages
        self._takes_edits = takes_edits
        self._cond = threading.Condition()
        self._posted: deque[tuple[Callable[[], Any], Future[Any]]] = deque()
        self._answer: tuple[bool, Any] | None = None
        self._cancelled = ""
        self._open = True

    def answer(self, ok: bool, result: Any) -> None:
        """The runtime's answer arrived (from the worker's control thread)."""
        with self._cond:
            self._answer = (ok, result)
            self._cond.notify_all()

    @property
    def cancelled(self) -> str:
        """Why the wait was cancelled ("": it was not)."""
        return self._cancelled

    def cancel(self, reason: str) -> None:
        """Make the waiting call raise ``RuntimeCancelled("cancelled: reason")``."""
        with self._cond:
            if not self._cancelled:
                self._cancelled = reason
            self._cond.notify_all()

    def post(self, work: Callable[[], Any], edit: bool = False) -> Future[Any] | None:
        """Run ``work`` on the waiting thread (which holds the module lock); its future,
        or None when the call has ended, or ``work`` is an ``edit`` and this wait takes
        none (then take the lock as usual)."""
        if edit and not self._takes_edits:
            return None
        future: Future[Any] = Future()
        with self._cond:
            if not self._open:
                return None
            self._posted.append((work, future))
            self._cond.notify_all()
        return future

    def result(self, timeout: float) -> Any:
        """Wait for the answer, running posted work meanwhile; the answer's result, or
        the PB3A error the runtime raised (``ModuleNotFound``, ``ConfigError`` ...), or
        ``RuntimeFailure`` (refused, cancelled: ``RuntimeCancelled``) or
        ``RuntimeTimeout``."""
        deadline = time.monotonic() + timeout
        try:
            while True:
                with self._cond:
                    while not (self._posted or self._answer or self._cancelled):
                        left = deadline - time.monotonic()
                        if left <= 0 or not self._cond.wait(left):
                            raise RuntimeTimeout(
                                f"the runtime did not answer {self.what} within {timeout} s")
                    if self._cancelled:
                        raise RuntimeCancelled(f"{self.what} cancelled: {self._cancelled}")
                    if self._answer is not None and not self._posted:
                        ok, result = self._answer
                        if not ok and isinstance(result, PB3AError):
                            raise result        # (ModuleNotFound, ConfigError ...: as asked)
                        if not ok:
                            raise RuntimeFailure(f"{self.what} failed: {result}")
                        return result
                    work, future = self._posted.popleft()
                _run(work, future)
        finally:
            self.close()

    def close(self) -> None:
        """No more posts: work posted but not run fails, so its poster takes the lock."""
        with self._cond:
            self._open = False
            left, self._posted = self._posted, deque()
        for _, future in left:
            if future.set_running_or_notify_cancel():     # (not given up on already)
                future.set_exception(_Closed())


class _Closed(Exception):
    """The wait ended before posted work ran (its poster then takes the lock itself)."""


def _run(work: Callable[[], Any], future: Future[Any]) -> None:
    if not future.set_running_or_notify_cancel():
        return                     # its poster gave up waiting: it is not done at all
    try:
        future.set_result(work())
    except BaseException as exc:
        future.set_exception(exc)


def run_posted(future: Future[Any], timeout: float) -> tuple[bool, Any]:
    """Wait for posted work: ``(True, result)``, or ``(False, None)`` when the wait ended
    before running it. Its own exception is raised."""
    try:
        return True, future.result(timeout)
    except _Closed:
        return False, None
    except FutureTimeout:
        if future.cancel():        # not begun: it never will be
            return False, None
        return True, future.result(RUNNING_S)     # begun: it ends soon (a state's copy)
