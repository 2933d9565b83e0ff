"""``Throttle``: one of a kind let through at most once every so many seconds."""

from __future__ import annotations

from pb3a.throttle import Throttle


def test_one_is_let_through_once_every_so_often_and_says_how_many_were_held_back() -> None:
    """The robot driver, the node controller and the worker each kept their own copy of
    this: the first one let through at once, those within ``every`` s of it held back
    and counted, the next one after that let through with their count."""
    gate = Throttle(10.0)
    assert gate.let(1000.0) == 0                    # the first, at once
    assert gate.let(1000.0) is None                 # held back ...
    assert gate.let(1009.9) is None                 # ... until every s have passed
    assert gate.let(1010.0) == 2                    # let through: 2 held back before it
    assert gate.let(1015.0) is None
    assert gate.let(1020.0) == 1                    # the time counts from the last let
    assert gate.let(1100.0) == 0                    # none held back since
    assert Throttle(60.0).let(0.0) == 0             # (whatever the clock reads at first)
