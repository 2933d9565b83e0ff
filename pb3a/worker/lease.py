"""``Lease``: how long a worker on a remote node may run its modules unattended.

Its executor grants it again and again; a frozen or hung executor cannot fence its
workers, so a worker whose lease runs out stops its own modules (as on SIGTERM) and
exits ``LEASE_LAPSED``, while the launcher starts them elsewhere.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Callable

log = logging.getLogger("pb3a.worker")

LEASE_CHECK_S = 0.1      # how often a worker with a lease looks at it
# The exit status of a worker that stopped its modules because its lease lapsed: its
# executor tells it from a stop it asked for (0) and, if its own lease runs, restarts
# the modules (the worker alone was frozen; see Restarts.died). A code neither Python
# nor a shell gives, and few programs choose (it was 3: a module's code that exited
# with 3 was said to have been frozen past its lease).
LEASE_LAPSED = 117


class Lease:
    """A worker's lease; one that was never granted always holds (an embedded node's
    workers, a spare not yet given a module)."""

    def __init__(self, closing: threading.Event, holding: Callable[[], str]) -> None:
        self._closing = closing        # the worker stops: the watch ends
        self._holding = holding        # what the worker runs, named when the lease lapses
        self._until: float | None = None
        self.lapsed = False            # it ran out: the worker exits LEASE_LAPSED
        self._lapsing = threading.Lock()

    def grant(self, until: float) -> None:
        """The executor is alive: run on until ``until``, its own lease's end (its
        ``time.monotonic()``, the same clock on one machine: a grant read late, after
        this worker was frozen, extends nothing). Until the launcher has started the
        modules elsewhere, no body runs once it is out (``holds``): a frozen node let
        run again stepped its modules once beside their failed-over copies before its
        lease was looked at. A grant that finds the lease run out already (the worker
        was frozen past it, the grants queued meanwhile) revives nothing: it lapses all
        the same, whichever of its threads runs first."""
        first = self._until is None
        if not self.holds():
            self._lapse()
            return
        self._until = until
        if first:
            threading.Thread(target=self._watch, daemon=True, name="pb3a-lease").start()

    def holds(self) -> bool:
        """Whether the worker's modules may run now: no lease, or one that runs."""
        until = self._until
        return until is None or time.monotonic() <= until

    def _watch(self) -> None:
        while not self._closing.wait(LEASE_CHECK_S):
            if not self.holds():
                self._lapse()
                return

    def _lapse(self) -> None:
        """The lease ran out: stop every module, as a SIGTERM does (once)."""
        with self._lapsing:             # (its two threads may find it at once: one stop)
            if self.lapsed:
                return
            self.lapsed = True
        # The stop first: the log goes to the executor, which is frozen, and its pipe may
        # be full: a log that waited for room there kept the modules running for good.
        os.kill(os.getpid(), signal.SIGTERM)     # (the stop a SIGTERM makes)
        # (both causes named: on a cut cable the executor fenced itself, saying so, and
        # this line blamed it alone, at times before the executor's)
        log.error("the worker of %s: its lease ran out, its executor granting it no more "
                  "(the executor fenced itself after losing the launcher, or it is frozen "
                  "or hung): its modules stop", self._holding())
