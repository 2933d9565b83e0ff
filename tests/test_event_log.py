"""``EventLog``: the launcher's numbered events, read after a sequence number."""

from __future__ import annotations

import pytest

from pb3a.events import EventLog


def test_the_newest_events_alone_are_read_with_last() -> None:
    """``since(seq, last=N)`` is the newest N of the events after ``seq``: a reader
    learns where the log stands from one event, not the whole log (``pb3a swap`` and
    ``pb3a add`` read it before their change, then the events after it)."""
    log = EventLog()
    for name in "abcde":
        log.record("module_added", name)
    assert [event.seq for event in log.since(0, last=1)] == [5]
    assert [event.subject for event in log.since(0, last=2)] == ["d", "e"]
    assert [event.seq for event in log.since(4, last=3)] == [5]
    assert log.since(5, last=1) == []
    assert len(log.since(0)) == 5
    for wrong in (0, -1, 1.0, True):
        with pytest.raises(ValueError, match="last must be a whole number from 1"):
            log.since(0, last=wrong)
