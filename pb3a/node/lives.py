"""``Lives``: when a node's modules are between two lives, and who waits for that.

A module's worker dies and its restart policy revives it in a new one (``Executor``'s
restart). In between, a request about the module is worth asking again once the
restart has ended (``await_restart``), and the restart itself waits until no change
(a move, a relink) holds the module paused (``await_let_go``), so that it does not
revive a module a move goes on to capture. One condition is notified at each moment
they wait for: a worker's death seen, a restart ended, a change letting go of a
module, the node stopping.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Iterator

    from pb3a.node.module_record import ModuleRecord
    from pb3a.node.workers import WorkerHandle, WorkerPool

log = logging.getLogger("pb3a.executor")


class Lives:
    """The moments of a node's modules' lives that its restarts and its changes wait
    for; thread-safe. It reads the executor's records and workers (the same objects,
    not copies) and sets a record's ``held``."""

    def __init__(self, modules: dict[str, ModuleRecord], workers: WorkerPool) -> None:
        self._modules = modules                 # the executor's records (the same dict)
        self._workers = workers
        self.stopping = threading.Event()       # its modules stopped, or fenced: no restart
        self.closing = threading.Event()        # a shutdown or a fence has begun
        # notified as a module's life changes: its worker's death seen, its restart
        # ended, a change letting go of it, the node stopping (``await_restart``,
        # ``await_let_go``)
        self._condition = threading.Condition()
        # modules whose restart is under way: what it is, and since when
        self._reviving: dict[str, tuple[str, float]] = {}

    def await_restart(self, name: str, timeout: float) -> bool:
        """Wait up to ``timeout`` while module ``name`` is between two lives (see
        ``Executor.await_restart``); whether it had to wait."""
        deadline = time.monotonic() + timeout
        waited = False
        with self._condition:
            while self._between_lives(name):
                waited = True
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                # (in slices: a module removed or moved meanwhile is not notified of)
                self._condition.wait(min(left, 0.1))
        return waited

    def _between_lives(self, name: str) -> bool:
        """Whether module ``name`` is between its worker's death (seen or not yet) and
        the end of what its restart policy does about it."""
        record = self._modules.get(name)
        if record is None or record.status in ("failed", "stopped") or self.closing.is_set():
            return False
        if name in self._reviving:
            return True
        handle = self._workers.handles.get(record.worker)
        # (a request may fail on the broken pipe of a worker whose death is not yet seen)
        return handle is not None and not (
            handle.serving and not handle.outbox.closed and handle.process.is_alive())

    def changed(self) -> None:
        """A module's life changed: whoever waits for one looks again."""
        with self._condition:
            self._condition.notify_all()

    def stop(self) -> None:
        """The node stops: no restart begins, and none waits for a change any more."""
        self.stopping.set()
        self.changed()

    @contextlib.contextmanager
    def reviving(self, names: set[str], what: str) -> Iterator[None]:
        """Modules ``names`` are being restarted (``what``) while in this block
        (``await_restart`` waits for its end, and ``revival`` says it)."""
        self._reviving.update(dict.fromkeys(names, (what, time.monotonic())))
        try:
            yield
        finally:
            for name in names:
                self._reviving.pop(name, None)
            self.changed()

    def revival(self, name: str) -> tuple[str, float] | None:
        """The restart under way of module ``name`` and when it began, if there is one
        (the node's figures name it: a launcher on another machine knows nothing of it)."""
        return self._reviving.get(name)

    def hold(self, record: ModuleRecord, held: bool) -> None:
        """Note whether a change holds ``record``'s module paused (see
        ``Executor.pause``)."""
        with self._condition:
            record.held = held
            if not held:
                self._condition.notify_all()

    def await_let_go(self, handle: WorkerHandle, what: str, timeout: float) -> None:
        """Wait (without the node's lock) until no change holds a module of dead worker
        ``handle`` paused, up to ``timeout``: its restart must not revive a module a
        move has paused (and goes on to capture). Once the worker is dead no change can
        pause its modules again (``Executor.pause`` finds it gone), so this holds once
        it returns. On an embedded node the restart then waits for the configuration
        lock, which the change holds throughout; on a remote one each of the change's
        requests takes the node's lock on its own, and a restart could run between two."""
        def held() -> list[str]:
            return [name for name in list(handle.modules)
                    if (record := self._modules.get(name)) is not None and record.held]
        with self._condition:
            if not self._condition.wait_for(lambda: not held() or self.stopping.is_set(),
                                         timeout):
                log.warning("%s: %s held paused by a change for %g s; restarted all the "
                            "same", what, ", ".join(held()), timeout)
