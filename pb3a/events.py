"""What happened to a running system, as numbered events: moves (and moves that
failed), swaps, restarts, failures, lost nodes, modules and links added or removed.

The launcher keeps the most recent ones (``EventLog``); ``run.events(since)`` returns
those after a sequence number, waiting up to a timeout for the next, so a program
(or ``pb3a.connect``, from another process) follows them by polling without missing
one, and sees when it fell too far behind (the first event it gets is not
``since + 1``).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from pb3a.errors import bounded_wait

KINDS = ("module_added", "module_removed", "module_moved", "migration_failed",
         "module_swapped", "module_restarted", "module_failed", "module_failed_over",
         "module_lost", "link_added", "link_removed", "node_lost", "node_joined",
         "module_retimed")


@dataclass(frozen=True)
class Event:
    """One thing that happened. ``subject`` is a module, link or node name."""

    seq: int
    kind: str
    subject: str
    time: float                                   # wall clock, seconds since the epoch
    detail: dict[str, Any] = field(default_factory=dict)


class EventLog:
    """The most recent events of one system, numbered from 1; thread-safe."""

    def __init__(self, keep: int = 10_000) -> None:
        self._events: deque[Event] = deque(maxlen=keep)
        self._seq = 0
        self._ended = False
        self._cond = threading.Condition()

    def record(self, kind: str, subject: str, **detail: Any) -> Event:
        """Add an event of one of ``KINDS``."""
        if kind not in KINDS:
            raise ValueError(f"unknown event kind {kind!r}; kinds: {', '.join(KINDS)}")
        with self._cond:
            self._seq += 1
            event = Event(self._seq, kind, subject, time.time(), detail)
            self._events.append(event)
            self._cond.notify_all()
        return event

    def since(self, seq: int = 0, timeout: float = 0.0, last: int | None = None) -> list[Event]:
        """The events after ``seq`` (oldest first), waiting up to ``timeout`` seconds for
        one when there is none yet (None is refused: ``TypeError``); with ``last``, only
        the newest ``last`` of them (``last=1``: where the log stands, read in one event,
        not the whole log)."""
        timeout = bounded_wait(timeout, "events since")
        if last is not None and (type(last) is not int or last < 1):
            raise ValueError(f"events: last must be a whole number from 1, not {last!r}")
        with self._cond:
            self._cond.wait_for(lambda: self._seq > seq or self._ended, timeout)
            after = [event for event in self._events if event.seq > seq]
        return after if last is None else after[-last:]

    def end(self) -> None:
        """No more events will come (the system stopped): every wait returns now, and
        later ones at once."""
        with self._cond:
            self._ended = True
            self._cond.notify_all()

    @property
    def last(self) -> int:
        """The sequence number of the newest event (0: none yet)."""
        return self._seq
