"""The deadline of the call in progress, kept by every wait made for it (as a Trio
cancel scope is): a change bounded by its caller's ``timeout`` (a move) sets one
around its steps, and the requests those steps make to nodes and workers wait no
longer than what is left of it, however deep they are asked, instead of their own
fixed deadlines.

``bounding(seconds)`` sets it for the block (an inner one never outlasts an outer
one); ``capped(seconds)`` is how long a wait of ``seconds`` may take under it;
``lifted()`` sets it aside for what must run to its end whatever the caller's time
left (undoing a change: resuming what was paused, putting a module back, halting a
start given up on), which keeps its own fixed deadlines.
"""

from __future__ import annotations

import contextlib
import contextvars
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Iterator

# what one who answers leaves of a wait for its answer's way back (a quarter, if less)
ANSWER_MARGIN_S = 0.25
# the end (``time.monotonic()``) of the call in progress on this thread, None if unbounded
_END: contextvars.ContextVar[float | None] = contextvars.ContextVar("pb3a_deadline",
                                                                   default=None)


@contextlib.contextmanager
def bounding(seconds: float) -> Iterator[None]:
    """Every wait in the block ends within ``seconds`` from now (or by the end of the
    bound it is in, if that comes first)."""
    end, outer = time.monotonic() + max(0.0, seconds), _END.get()
    token = _END.set(end if outer is None else min(end, outer))
    try:
        yield
    finally:
        _END.reset(token)


@contextlib.contextmanager
def lifted() -> Iterator[None]:
    """No bound in the block: what must finish (an undo) keeps its own deadlines."""
    token = _END.set(None)
    try:
        yield
    finally:
        _END.reset(token)


def left() -> float | None:
    """The seconds left of the bound in force (0 once past), None if there is none."""
    end = _END.get()
    return None if end is None else max(0.0, end - time.monotonic())


def capped(seconds: float) -> float:
    """``seconds``, or what is left of the bound in force if that is less."""
    remaining = left()
    return seconds if remaining is None else min(seconds, remaining)


def before_answer(seconds: float) -> float:
    """How much of a wait of ``seconds`` for an answer the one answering may use: it
    gives up ``ANSWER_MARGIN_S`` (a quarter of a short wait) before, so that its answer
    arrives while it is still waited for."""
    return seconds - min(ANSWER_MARGIN_S, seconds / 4)


def spoken(seconds: float) -> str:
    """Seconds to two figures, as a person says them, for a message about a wait: what
    is left of a caller's deadline, 0.999 s of 1 s, is "1"; 120 s is not "1.2e+02"."""
    return f"{float(f'{seconds:.2g}'):g}"
