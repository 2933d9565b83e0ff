"""``ConfigurationLock``: the launcher's global lock, held by every change to a running
system (from the API, the command line or an agent) so that changes apply one at a time.

It comes first in the lock order (then module locks: see ``pb3a.worker.waits``).
Every wait for it has a deadline, and a wait that runs out names what holds the lock
and for how long, instead of hanging.
"""

from __future__ import annotations

import contextlib
import threading
import time
from typing import TYPE_CHECKING

from pb3a.errors import RuntimeTimeout

if TYPE_CHECKING:
    from collections.abc import Iterator

DEFAULT_TIMEOUT = 60.0      # longest a change waits for the one in progress


class ConfigurationLock:
    """A re-entrant lock whose holders say what they do."""

    def __init__(self, timeout: float = DEFAULT_TIMEOUT) -> None:
        self.timeout = timeout
        self._lock = threading.RLock()
        self._doing: list[tuple[str, float]] = []     # (what, since), outermost first

    @contextlib.contextmanager
    def held(self, what: str, timeout: float | None = None) -> Iterator[None]:
        """Hold the lock for ``what`` (e.g. "migrate relay to b"); ``RuntimeTimeout``
        naming the holder if it is not free within ``timeout`` (default: ``self.timeout``)."""
        self._acquire(what, timeout)
        try:
            yield
        finally:
            self._release()

    def holder(self) -> str:
        """What holds the lock, in words."""
        doing = self._doing[:1]
        if not doing:
            return "nothing holds now"
        what, since = doing[0]
        return f"{what!r} has held for {time.monotonic() - since:.1f} s"

    def __enter__(self) -> ConfigurationLock:
        self._acquire("a change to the system", None)
        return self

    def __exit__(self, *exc: object) -> None:
        self._release()

    def _acquire(self, what: str, timeout: float | None) -> None:
        wait = self.timeout if timeout is None else timeout
        if not self._lock.acquire(timeout=wait):
            raise RuntimeTimeout(f"{what}: waited {wait:g} s for the system's configuration "
                                 f"lock, which {self.holder()}; try again when it is done")
        self._doing.append((what, time.monotonic()))

    def _release(self) -> None:
        self._doing.pop()
        self._lock.release()
