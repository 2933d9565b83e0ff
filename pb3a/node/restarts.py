"""The restart budget: how often a crashed worker may be restarted before giving up.

The policies themselves are per module (``restart = "never" | "fresh" |
"last-state"``) and applied by the ``Executor``; the budget is Erlang's MaxR/MaxT:
more than ``limit`` restarts of one worker within ``window`` seconds gives up, so a
crash loop cannot spin.
"""

from __future__ import annotations

import time
from collections import deque

RESTART_INTENSITY = (5, 30.0)   # at most 5 restarts of one worker in 30 s


class RestartBudget:
    """Restarts of one worker within a sliding window."""

    def __init__(self, limit: int = RESTART_INTENSITY[0],
                 window: float = RESTART_INTENSITY[1]) -> None:
        self.limit, self.window = limit, window
        self._times: deque[float] = deque()

    def spend(self) -> bool:
        """Count one more death; False when the worker is over its budget (give up)."""
        now = time.monotonic()
        self._times.append(now)
        while self._times and now - self._times[0] > self.window:
            self._times.popleft()
        return len(self._times) <= self.limit

    @property
    def deaths(self) -> int:
        """Deaths counted within the window."""
        return len(self._times)
