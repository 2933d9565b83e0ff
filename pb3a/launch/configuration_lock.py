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

A change may leave part of its work running past its hold (undoing a move whose
module's worker is still busy: ``carry_on``): until that part ends, every other wait
for the lock waits for it too, so no later change races it.

What changes the system now, and which modules it acts on, is read without waiting
for the lock (``changing``): a read of the figures or of where a module runs must
answer while a long change holds it, which is when one wants to look.
"""

from __future__ import annotations

import contextlib
import threading
import time
from typing import TYPE_CHECKING

from pb3a.errors import RuntimeTimeout

if TYPE_CHECKING:
    from collections.abc import Callable, Collection, Iterator

DEFAULT_TIMEOUT = 60.0      # longest a change waits for the one in progress


class ConfigurationLock:
    """A re-entrant lock whose holders say what they do."""

    def __init__(self, timeout: float = DEFAULT_TIMEOUT) -> None:
        self.timeout = timeout
        self._lock = threading.RLock()
        # (what, since, the modules it acts on), outermost first
        self._doing: list[tuple[str, float, frozenset[str]]] = []
        self._lent: frozenset[str] = frozenset()      # modules the holder lends it to
        self._guests = threading.Lock()               # one guest at a time
        self._owner: int | None = None                # the holder's thread ident
        # work a change left running past its hold (``carry_on``): thread -> (what,
        # since, the modules it acts on)
        self._tails: dict[threading.Thread, tuple[str, float, frozenset[str]]] = {}
        self._tails_changed = threading.Condition()

    @contextlib.contextmanager
    def held(self, what: str, timeout: float | None = None, *,
             lend: Collection[str] = (), acts_on: Collection[str] | None = None,
             ) -> Iterator[None]:
        """Hold the lock for ``what`` (e.g. "migrate relay to b"); ``RuntimeTimeout``
        naming the holder if it is not free within ``timeout`` (default: ``self.timeout``).
        The modules in ``lend`` may be its ``guest`` meanwhile; ``acts_on``: the modules
        (or macro instances) it changes, for ``changing`` (default: those in ``lend``)."""
        self._acquire(what, timeout, frozenset(lend if acts_on is None else acts_on))
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

    def carry_on(self, what: str, work: Callable[[], None]) -> threading.Thread:
        """Run ``work`` (part of the change that holds the lock: undoing it, say) on a
        thread of its own, which may outlast the hold: until ``work`` returns, every
        other wait for the lock waits for it too. Asked by the holder, under the lock
        (so that no other change comes in between); the thread, started."""
        if self._owner != threading.get_ident():
            raise RuntimeError(f"{what}: carried on by a thread that does not hold the "
                               "configuration lock")

        def run() -> None:
            try:
                work()
            finally:
                with self._tails_changed:
                    del self._tails[thread]
                    self._tails_changed.notify_all()
        thread = threading.Thread(target=run, name="pb3a-carry-on", daemon=True)
        with self._tails_changed:
            self._tails[thread] = (what, time.monotonic(), self._acted_on())
        thread.start()
        return thread

    def changing(self) -> dict[str, tuple[str, float]]:
        """The modules (or macro instances) that a change in progress acts on, each with
        what that change is and the ``time.monotonic()`` it began: the holder's (its
        outermost hold's name, the modules of every hold) and work changes left running.
        Read without waiting for the lock (one copy of each list: never half written)."""
        found: dict[str, tuple[str, float]] = {}
        doing = list(self._doing)
        if doing:
            what, since, _ = doing[0]
            found |= {name: (what, since) for _, _, names in doing for name in names}
        for what, since, names in list(self._tails.values()):
            found |= {name: (what, since) for name in names if name not in found}
        return found

    def doing(self) -> str:
        """What the holder does, quoted ("'add spy'"), or "nothing"."""
        doing = self._doing[:1]
        return repr(doing[0][0]) if doing else "nothing"

    def holder(self) -> str:
        """What holds the lock, in words (work a change left running, if none)."""
        doing = self._doing[:1] or list(self._tails.values())[:1]
        if not doing:
            return "nothing holds now"
        what, since, _ = doing[0]
        return f"{what!r} has held for {time.monotonic() - since:.1f} s"

    def __enter__(self) -> ConfigurationLock:
        self._acquire("a change to the system", None, frozenset())
        return self

    def __exit__(self, *exc: object) -> None:
        self._release()

    def _acquire(self, what: str, timeout: float | None, acts_on: frozenset[str]) -> None:
        wait = self.timeout if timeout is None else timeout
        deadline = time.monotonic() + wait
        while True:
            if not self._after_tails(deadline) or not self._lock.acquire(
                    timeout=max(0.0, deadline - time.monotonic())):
                raise RuntimeTimeout(f"{what}: waited {wait:g} s for the system's "
                                     f"configuration lock, which {self.holder()}; try "
                                     "again when it is done")
            # (a tail is begun under the lock only: none can begin once it is held)
            if self._owner == threading.get_ident() or not self._others_tails():
                break
            self._lock.release()
        if not self._doing:
            self._owner = threading.get_ident()
        self._doing.append((what, time.monotonic(), acts_on))

    def _acted_on(self) -> frozenset[str]:
        """The modules the holder's holds act on (asked by the holder)."""
        return frozenset().union(*(names for _, _, names in self._doing))

    def _after_tails(self, deadline: float) -> bool:
        """Wait until no work a change left running (``carry_on``) runs, but this
        thread's own, or its holder's, up to ``deadline``; whether none does."""
        if self._owner == threading.get_ident():
            return True                 # (re-entered: what it left running it waits for)
        with self._tails_changed:
            return self._tails_changed.wait_for(
                lambda: not self._others_tails(), max(0.0, deadline - time.monotonic()))

    def _others_tails(self) -> bool:
        """Whether work a change left running runs on a thread other than this one."""
        me = threading.current_thread()
        return any(thread is not me for thread in list(self._tails))   # (one copy, atomic)

    def _release(self) -> None:
        self._doing.pop()
        if not self._doing:
            self._owner = None
        self._lock.release()


def change_to(module: str, changing: dict[str, tuple[str, float]]) -> tuple[str, float] | None:
    """The change in ``changing`` (``ConfigurationLock.changing``) that acts on
    ``module``, or on a macro instance it is in (a macro moves whole), if any."""
    parts = module.split("/")
    for depth in range(len(parts), 0, -1):
        found = changing.get("/".join(parts[:depth]))
        if found is not None:
            return found
    return None
