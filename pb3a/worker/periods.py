"""``PeriodTeller``: the periods a worker's modules assign themselves, told to the runtime.

A module that assigns ``self.period`` steps at it from its next sleep on
(``ModuleActor.assign_period``); the launcher's record of its period, which a move, a
restart and ``stats`` go by, learns it from the request an agent sends for its own
period (``set_state(name, period=...)``), sent here without waiting for the answer: a
body must not wait for the configuration lock, which a change waiting for that very
body (a move, a swap) may hold. The request then waits for the change to end, and
sets the period where the module runs after it.

One request per module is under way at a time, and a period assigned meanwhile is told
once it is answered (the last one only): requests sent side by side are carried out in
any order (each on a thread of its own in the executor), and a module that set 0.5,
then 2, was kept at 0.5. A period set from elsewhere that reaches the configuration
lock between an assignment and its request is replaced by it: the last to reach the
lock wins, on the module and in the record alike.
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Callable

log = logging.getLogger("pb3a.module")


class PeriodTeller:
    """Tells the runtime each period a module assigned itself, through ``ask(name,
    period, answered)``, which sends the request and calls ``answered(ok, result)``
    once it is answered; False if it could not be sent (the executor is gone)."""

    def __init__(self, ask: Callable[[str, float, Callable[[bool, Any], None]], bool]) -> None:
        self._ask = ask
        self._lock = threading.Lock()
        # module -> the period to tell once its request under way is answered (None:
        # none); a module is here while a request of its is under way
        self._after: dict[str, float | None] = {}

    def tell(self, name: str, period: float) -> None:
        """Module ``name`` assigned itself ``period``: tell the runtime, never waiting."""
        with self._lock:
            if name in self._after:
                self._after[name] = period
                return
            self._after[name] = None
        self._send(name, period)

    def _send(self, name: str, period: float) -> None:
        if not self._ask(name, period, lambda ok, result: self._told(name, period, ok, result)):
            self._told(name, period, False, "its executor is gone")

    def _told(self, name: str, period: float, ok: bool, result: Any) -> None:
        """The answer to the request telling ``period``; the next one goes, if any."""
        if not ok:
            # (it runs at it here: only where the module starts again is it lost)
            log.warning("module %r steps every %g s, which it set itself, but the runtime "
                        "did not learn it, so a move or a restart of its worker starts it at "
                        "its period before: %s", name, period, result)
        with self._lock:
            after = self._after.pop(name, None)
            if after is not None:
                self._after[name] = None
        if after is not None:
            self._send(name, after)
