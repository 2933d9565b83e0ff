"""``PeriodTeller``: the runtime told of the periods a worker's modules assign themselves.

A module that assigns ``self.period`` steps at it at once (``ModuleActor.assign_period``);
the launcher's record of its period, which a move, a restart, a swap and ``stats`` go
by, learns it from a request its worker sends without waiting for the answer
(``learn_period``): a body must not wait for the configuration lock, which a change
waiting for that very body (a move, a swap) may hold. The request carries no period:
once it holds the lock, the launcher reads the one the module steps at then, where it
runs, and sets nothing there. What the record learns is so the module's last word,
whatever came between: requests that carried the period set the module back to an
older one (one carrying 0.03 carried out after one carrying 0.04), and one from before
a move, a restart or a ``set_state``, carried out after it, put back what it replaced.

Per module, one request is under way at a time, and one a second at most: a module that
sets its period at every step (an adaptive rate) has its record learn it once a second,
the lock taken once a second, not at every step (56 a second, each a round trip to the
worker, an event, and the whole structure sent again to every page of the manager).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Any

from pb3a.errors import ModuleNotFound, SystemStopped

if TYPE_CHECKING:
    from collections.abc import Callable

log = logging.getLogger("pb3a.module")

TELL_EVERY_S = 1.0          # at most one request a module, this often


class PeriodTeller:
    """Tells the runtime that a module assigned itself a period, through ``ask(name,
    answered)``, which sends the request and calls ``answered(ok, result)`` once it is
    answered; False if it could not be sent (the executor is gone)."""

    def __init__(self, ask: Callable[[str, Callable[[bool, Any], None]], bool],
                 every: float = TELL_EVERY_S) -> None:
        self._ask, self._every = ask, every
        self._lock = threading.Lock()
        self._owed: set[str] = set()        # modules whose runtime is to learn anew
        self._asking: set[str] = set()      # ... whose request is under way
        self._waiting: set[str] = set()     # ... whose next request waits for its time
        self._asked: dict[str, float] = {}  # module -> when its last request went

    def tell(self, name: str) -> None:
        """Module ``name`` assigned itself a period: tell the runtime, never waiting."""
        with self._lock:
            self._owed.add(name)
        self._next(name)

    def _next(self, name: str) -> None:
        """Send module ``name``'s request, if one is owed, none is under way and
        ``every`` has passed since the last; once it has, if that alone is missing."""
        with self._lock:
            if name not in self._owed or name in self._asking or name in self._waiting:
                return
            now = time.monotonic()
            wait = self._asked.get(name, now - self._every) + self._every - now
            if wait > 0:
                self._waiting.add(name)
                timer = threading.Timer(wait, self._waited, (name,))
                timer.daemon = True
                timer.start()
                return
            self._owed.discard(name)
            self._asking.add(name)
            self._asked[name] = now
        if not self._ask(name, lambda ok, result: self._answered(name, ok, result)):
            log.debug("module %r: its period was not told: its executor is gone", name)
            with self._lock:
                self._asking.discard(name)

    def _waited(self, name: str) -> None:
        with self._lock:
            self._waiting.discard(name)
        self._next(name)

    def _answered(self, name: str, ok: bool, result: Any) -> None:
        if not ok:
            # (it runs at it here: only where the module starts again is it lost; a
            # module removed meanwhile, or a system stopped, has nothing to keep)
            quiet = isinstance(result, (ModuleNotFound, SystemStopped))
            log.log(logging.DEBUG if quiet else logging.WARNING,
                    "module %r set its own period, but the runtime's record of it did not "
                    "learn it, so a move or a restart of its worker starts it at its "
                    "period before: %s", name, result)
        with self._lock:
            self._asking.discard(name)
        self._next(name)
