"""``Throttle``: one of a kind let through at most once every so many seconds, those held
back in between counted, so that the next one let through says how many there were.

A cause that repeats fast (a robot that comes and goes, a node refusing every launch, a
module raising at every step) is then said once in a while, not every time, nor
forgotten. What is let through, and how the count is worded, is the caller's: a log
line (``agents.robot_driver``, ``pb3a.daemons.node_controller``), a report to another
process (``pb3a.worker.process``).
"""

from __future__ import annotations

import math


class Throttle:
    """Lets one through at most once every ``every`` seconds, counting those held back.

    The times are the caller's ``now``, read from one monotonic clock
    (``time.monotonic()``): a test gives those it likes, and a caller whose clock a test
    replaces keeps that clock. Not locked: for one thread at a time (two at once may
    both be let through)."""

    def __init__(self, every: float) -> None:
        self.every = every
        self._let_at = -math.inf        # when one was let through last
        self._held = 0                  # those held back since

    def let(self, now: float) -> int | None:
        """At ``now``: None if one was let through less than ``every`` s before (this one
        is held back, and counted); else this one is let through, and the number held back
        since the one before it (0: none)."""
        if now - self._let_at < self.every:
            self._held += 1
            return None
        held, self._let_at, self._held = self._held, now, 0
        return held
