"""``ConfigurationLock``: the launcher's global lock, held by every change to a running
system (from the API, the command line or an agent) so that changes apply one at a time.

It comes first in the lock order (then module locks: see ``pb3a.worker.waits``).
Every wait for it has a deadline, and a wait that runs out names what holds the lock
and for how long, instead of hanging.

A change that starts modules waits, holding the lock, for their ``setup``; an agent
whose ``setup`` asks the runtime would wait for the lock in turn, each for the other.
So the holder lends the lock to the modules it starts (``held(..., lend=names)``):
while it holds, requests of theirs that change nothing may run as its ``guest``, one
at a time.
"""

from __future__ import annotations

import contextlib
import threading
import time
from typing import TYPE_CHECKING

from pb3a.errors import RuntimeTimeout

if TYPE_CHECKING:
    from collections.abc import Collection, Iterator

DEFAULT_TIMEOUT = 60.0      # longest a change waits for the one in progress


class ConfigurationLock:
    """A re-entrant lock whose holders say what they do."""

    def __init__(self, timeout: float = DEFAULT_TIMEOUT) -> None:
        self.timeout = timeout
        self._lock = threading.RLock()
        self._doing: list[tuple[str, float]] = []     # (what, since), outermost first
        self._lent: frozenset[str] = frozenset()      # modules the holder lends it to
        self._guests = threading.Lock()               # one guest at a time

    @contextlib.contextmanager
    def held(self, what: str, timeout: float | None = None, *,
             lend: Collection[str] = ()) -> Iterator[None]:
        """Hold the lock for ``what`` (e.g. "migrate relay to b"); ``RuntimeTimeout``
        naming the holder if it is not free within ``timeout`` (default: ``self.timeout``).
        The modules in ``lend`` may be its ``guest`` meanwhile."""
        self._acquire(what, timeout)
        outer, self._lent = self._lent, self._lent | frozenset(lend)
        try:
            yield
        finally:
            self._lent = outer
            self._release()

    def lends_to(self, module: str) -> bool:
        """True if the holder lends the lock to ``module`` (or to a macro it is in)."""
        lent = self._lent
        return any(module == name or module.startswith(f"{name}/") for name in lent)

    @contextlib.contextmanager
    def guest(self, what: str, timeout: float) -> Iterator[None]:
        """Run ``what``, asked by a module lent to from its ``setup`` (which the
        holder waits for, so it changes nothing meanwhile), beside the holder."""
        if not self._guests.acquire(timeout=timeout):
            raise RuntimeTimeout(f"{what}: waited {timeout:g} s for another module's "
                                 f"request during {self.doing()}")
        try:
            yield
        finally:
            self._guests.release()

    def doing(self) -> str:
        """What the holder does, quoted ("'add spy'"), or "nothing"."""
        doing = self._doing[:1]
        return repr(doing[0][0]) if doing else "nothing"

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
