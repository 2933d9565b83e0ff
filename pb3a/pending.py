"""``Pending``: an operation the runtime carries out in the background.

``migrate(..., wait=False)`` returns one, from the API, a connection or an agent: the
caller goes on (an agent's step returns, so the move can pause it) and asks later
whether it is done and how it went.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

from pb3a.errors import PB3AError, RuntimeFailure, RuntimeTimeout

if TYPE_CHECKING:
    from collections.abc import Callable

RUNNING, DONE, FAILED = "running", "done", "failed"


class Pending:
    """The result to come of one background operation.

    ``poll(timeout)`` asks the runtime for ``(status, value)``, waiting up to ``timeout``
    for the operation to end: ``("running", None)``, ``("done", result)`` or
    ``("failed", error)``: the PB3A error it raised, or a message.
    """

    def __init__(self, what: str, poll: Callable[[float], tuple[str, Any]]) -> None:
        self.what = what
        self._poll = poll
        self._outcome: tuple[str, Any] | None = None

    def done(self) -> bool:
        """True once the operation has ended, well or not (does not wait)."""
        return self._look(0.0) is not None

    def wait(self, timeout: float) -> bool:
        """``done()``, waiting up to ``timeout`` seconds for the end: it returns as the
        operation ends, where polling ``done()`` would learn of it a poll later."""
        deadline = time.monotonic() + timeout
        outcome = self._look(timeout)
        while outcome is None and time.monotonic() < deadline:
            outcome = self._look(max(0.0, deadline - time.monotonic()))
        return outcome is not None

    def result(self, timeout: float = 60.0) -> Any:
        """Its result, waiting up to ``timeout`` seconds; if it failed, the PB3A error it
        raised (``ConfigError`` for a node the system does not have ...) or else
        ``RuntimeFailure``; ``RuntimeTimeout`` if it has not ended in time."""
        if not self.wait(timeout):
            raise RuntimeTimeout(f"{self.what} had not ended after {timeout:g} s")
        status, value = self._outcome
        if status == FAILED and isinstance(value, PB3AError):
            raise value
        if status == FAILED:
            raise RuntimeFailure(f"{self.what} failed: {value}")
        return value

    def _look(self, timeout: float) -> tuple[str, Any] | None:
        if self._outcome is None:
            status, value = self._poll(timeout)
            if status != RUNNING:
                self._outcome = (status, value)
        return self._outcome

    def __repr__(self) -> str:
        state = "running" if self._outcome is None else self._outcome[0]
        return f"<Pending {self.what}: {state}>"
