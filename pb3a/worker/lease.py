"""``Lease``: how long a worker on a remote node may run its modules unattended.

Its executor grants it again and again; a frozen or hung executor cannot fence its
workers, so a worker whose lease runs out stops its own modules (as on SIGTERM) and
exits ``LEASE_LAPSED``, while the launcher starts them elsewhere.

No body runs while the lease is out (``holds``): that is what keeps a module from
running beside its failed-over copy. The worker's own stop (its modules' ``teardown``)
comes once the lease has been out for ``LEASE_GRACE_S`` of time in which the thread
that reads the grants was free to read them, for a worker whose threads were starved
rather than its executor gone: a module's one long C call that holds the GIL (a
pickle of a large list, a solver) kept the grants unread in the pipe, and the worker
stopped itself as the call let go, its executor alive and its grants waiting (a
module stepping for 1.5 s that way was restarted at every step, then failed for
good); so did a module's construction longer than the lease, which holds that thread.
Starved or held, it stops after ``LEASE_STARVED_S``: the grace is kept short, since
the launcher starts the modules elsewhere about half a second after the lease ends,
and a teardown run later would run beside the copy.
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
# How long a lease stays out, in time the grants could be read in, before the worker
# stops itself: grants queued behind a starved or held thread are read meanwhile
LEASE_GRACE_S = 0.2
LEASE_STARVED_S = 2.0    # ... and at most, out however starved it is
_LATE_S = 0.2            # a look at the lease this late: its thread (and the rest) starved
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
        self.answering = False         # the thread that reads the grants is in a request
        self._lapsing = threading.Lock()

    def grant(self, until: float) -> None:
        """The executor is alive: run on until ``until``, its own lease's end (its
        ``time.monotonic()``, the same clock on one machine: a grant read late, after
        this worker or its node was frozen, is over already and extends nothing). No
        body runs once the lease is out (``holds``): a frozen node let run again stepped
        its modules once beside their failed-over copies before its lease was looked at.
        A grant whose ``until`` is still ahead brings a lease that ran out back: its
        executor's lease holds now, so its node was not declared lost and nothing runs
        the modules elsewhere (the worker alone was starved or stopped)."""
        if self.lapsed:
            return
        if self._until is None:
            self._until = until
            threading.Thread(target=self._watch, daemon=True, name="pb3a-lease").start()
        else:
            self._until = max(self._until, until)

    def holds(self) -> bool:
        """Whether the worker's modules may run now: no lease, or one that runs."""
        until = self._until
        return until is None or time.monotonic() <= until

    def _watch(self) -> None:
        """Stop the worker once its lease has been out for ``LEASE_GRACE_S`` of time in
        which the grants could be read: a wait of this thread that ended late was
        starved, and so was the thread that reads the grants, and a time that thread
        spent in a request (``answering``) it read none; neither counts (the grants
        queued meanwhile bring the lease back once read). At most ``LEASE_STARVED_S``."""
        seen: float | None = None   # the lease's end when this thread saw it out
        calm = 0.0                  # how long out since, in time the grants could be read
        last = time.monotonic()
        while not self._closing.wait(LEASE_CHECK_S):
            now = time.monotonic()
            waited, last = now - last, now
            until = self._until
            if until is None or now <= until:
                continue
            if until != seen:       # (out anew: a grant read since moved its end on)
                seen, calm = until, 0.0
                continue
            if waited <= LEASE_CHECK_S + _LATE_S and not self.answering:
                calm += waited
            if calm >= LEASE_GRACE_S or now - until >= LEASE_STARVED_S:
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
