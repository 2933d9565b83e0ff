"""``stop_in_turn``: a close's stops of its modules, each given a fair share of its time.

The modules stop in reverse start order, one after the other, as long as each stops
within its share: what is left of the close divided among the modules still to stop,
itself included (so the time a quick stop leaves goes to those after it). A module
that has not stopped when its share ends (frozen in a body, its worker or its node
slow to answer) is not waited for in turn any longer: its stop goes on, on its own
thread, until its own deadline (never past the close's), and the next module's stop
begins beside it. A frozen module on a remote node held the close for all of its
time, and the modules of this machine after it were then killed, their teardowns
unrun, though they would have stopped at once.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING

from pb3a.deadline import bounding

if TYPE_CHECKING:
    from collections.abc import Callable

log = logging.getLogger("pb3a.launcher")

# past the close's deadline, for all the stops' threads: returning once their requests
# have given up (each is bounded by the deadline)
RETURN_S = 0.1


def stop_in_turn(names: list[str], stop: Callable[[str], None], deadline: float) -> list[str]:
    """Stop each of ``names`` in that order with ``stop`` (which raises if the module did
    not stop) by ``deadline`` (``time.monotonic()``), each waited for its fair share of
    the time left before the next one's stop begins; the modules that did not stop, in
    that order, each named in a warning (with why, or as still stopping at the
    deadline)."""
    failures: dict[str, Exception] = {}

    def stopped(name: str) -> None:
        try:
            # its requests wait no longer than the close (a frozen worker's stop would
            # have waited 1 s past it, as its grace ran out)
            with bounding(deadline - time.monotonic()):
                stop(name)
        except Exception as exc:
            failures[name] = exc

    threads = []
    for index, name in enumerate(names):
        thread = threading.Thread(target=stopped, args=(name,), daemon=True,
                                  name=f"pb3a-stop-{name}")
        thread.start()
        threads.append(thread)
        thread.join(max(0.0, deadline - time.monotonic()) / (len(names) - index))
    for thread in threads:
        thread.join(max(0.0, deadline + RETURN_S - time.monotonic()))
    unstopped = []
    for name, thread in zip(names, threads, strict=True):
        if thread.is_alive():              # (first: once it has ended, its failure is said)
            log.warning("module %r was not stopped (its worker is killed): its stop had not "
                        "ended when the close's time ran out", name)
        elif name in failures:
            # (a module stuck in on_input was killed at close, unsaid)
            log.warning("module %r was not stopped (its worker is killed): %s", name,
                        failures[name])
        else:
            continue
        unstopped.append(name)
    return unstopped
