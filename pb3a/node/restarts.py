"""Restarts: what a worker's death brings to the modules that ran in it.

The policies are per module (``restart = "never" | "fresh" | "last-state"``);
``Restarts`` applies them for its ``Executor`` when a worker dies, within each
worker's ``RestartBudget``: Erlang's MaxR/MaxT, more than ``limit`` restarts of one
worker within ``window`` seconds gives up, so a crash loop cannot spin. A restart
takes the node's lock as a launch's start does, and lets it go while the revived
modules' ``setup`` runs (an agent may call its runtime from there, which takes it).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from pb3a.errors import RuntimeFailure, RuntimeTimeout
from pb3a.node.workers import REQUEST_TIMEOUT
from pb3a.worker.lease import LEASE_GRACE_S, LEASE_LAPSED

if TYPE_CHECKING:
    from collections.abc import Callable, Collection
    from concurrent.futures import Future
    from contextlib import AbstractContextManager

    from pb3a.node.lives import Lives
    from pb3a.node.module_record import ModuleRecord
    from pb3a.node.workers import WorkerHandle, WorkerPool
    from pb3a.stats import FailureLog

log = logging.getLogger("pb3a.executor")

RESTART_INTENSITY = (5, 30.0)   # at most 5 restarts of one worker in 30 s
# A worker stopped by a SIGTERM is warned of unless its node begins to stop within this:
# the same signal reached the launcher (sent to the whole process group)
STOP_FOLLOWS_S = 2.0
LOCK_TIMEOUT = 60.0      # longest a restart or a shutdown waits for the node's lock


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


@dataclass(frozen=True)
class _Revival:
    """A module a restart revived, and which of its restarts that was."""

    record: ModuleRecord
    restart: int                      # ``record.restarts`` then: a later restart changes it
    from_checkpoint: bool = False     # restored from its last checkpoint (``last-state``)


class RestartHost(Protocol):
    """What a restart does its work through: the node's ``Executor``."""

    modules: dict[str, ModuleRecord]
    workers: WorkerPool
    lives: Lives
    failures: FailureLog
    leased: Callable[[], bool]

    def held(self, what: str, timeout: float = ..., *,
             acts_on: Collection[str] = ...) -> AbstractContextManager[Any]: ...
    def instantiate(self, record: ModuleRecord, state: dict[str, Any] | bytes) -> None: ...
    def rewire(self, revived: set[str]) -> None: ...
    def fail(self, name: str, code: int | None, reason: str) -> None: ...
    def tell(self, kind: str, name: str, **detail: Any) -> None: ...


class Restarts:
    """Applies the restart policies of a node's modules when their worker dies (the
    ``WorkerPool`` tells ``died``), each worker within its ``RestartBudget``."""

    def __init__(self, node: RestartHost) -> None:
        self._node = node
        self._budgets: dict[str, RestartBudget] = {}  # worker key -> its restarts

    def forget(self, key: str) -> None:
        """Worker ``key`` was stopped on purpose: a new one of that name starts afresh."""
        self._budgets.pop(key, None)

    def died(self, handle: WorkerHandle) -> None:
        """The worker pool's word that ``handle``'s process has ended."""
        try:
            self._after_death(handle)
        finally:
            self._node.lives.changed()

    def _after_death(self, handle: WorkerHandle) -> None:
        code = handle.process.exitcode
        if code == LEASE_LAPSED and self._node.leased() and not self._node.lives.stopping.is_set():
            # Its lease lapsed, but this executor's runs again: the executor, starved,
            # read a renewal after its lease had been out for LEASE_GRACE_S, before its own
            # watch saw it out and fenced it (the renewal, dated from the launcher's newest
            # answer, extends it all the same: nothing runs its modules elsewhere). They
            # were stopped as no one asked: their restart policy says what comes.
            log.warning("worker %s (pid %s, modules %s) stopped them: its lease had been "
                        "out for %g s when its executor, starved, renewed it (the machine "
                        "overloaded?)", handle.key, handle.pid, ", ".join(handle.modules),
                        LEASE_GRACE_S)
        elif code in (0, LEASE_LAPSED):   # stopped on purpose (SIGTERM), or fenced: not a crash
            said = ("worker %s (pid %s) stopped; its modules %s are stopped", handle.key,
                    handle.pid, ", ".join(handle.modules))
            if code == 0:
                threading.Thread(target=self._say_stopped, args=said, daemon=True,
                                 name="pb3a-stopped").start()
            else:
                log.warning(*said)
            for name in handle.modules:
                self._node.modules[name].status = "stopped"
            return
        else:
            log.warning("worker %s (pid %s, modules %s) died with exit code %s",
                        handle.key, handle.pid, ", ".join(handle.modules), code)
        threading.Thread(target=self._recover, args=(handle, code), daemon=True,
                         name=f"pb3a-restart-{handle.key}").start()

    def _say_stopped(self, *said: object) -> None:
        """Warn of a worker stopped by a SIGTERM, unless this node stops meanwhile: a
        SIGTERM to the whole process group (`timeout`, `kill -- -PGID`) reaches the
        launcher and its nodes with their workers, and a warning per worker was noise on
        a clean stop. One that stops alone (someone's SIGTERM, a module's exit) is said."""
        if self._node.lives.closing.wait(STOP_FOLLOWS_S):
            log.info(*said)
        else:
            log.warning(*said)

    def _recover(self, handle: WorkerHandle, code: int | None) -> None:
        """Restart what ran in a dead worker as a launch starts it (``Running.start``):
        under the lock, the policies applied, the modules instantiated and rewired in a
        new process (``_revive``) and their start sent; without it, their ``setup`` runs,
        since an agent may call ``self.runtime`` from ``setup``, which takes the lock
        (``_started``); under it again, what came of it (``_restarted``)."""
        what = f"restart the modules of worker {handle.key}"
        with self._node.lives.reviving(set(handle.modules), what):
            try:
                self._node.lives.await_let_go(handle, what, LOCK_TIMEOUT)
                with self._node.held(what, acts_on=list(handle.modules)):
                    if self._node.lives.stopping.is_set():    # a shutdown may have come first
                        return
                    revived = self._revive(handle, code)
                    if not revived:
                        return
                    # sent now, to the process just set up, whatever happens once the
                    # lock is free
                    process = handle.process
                    future = self._node.workers.submit(handle.key, "start", names=list(revived))
                outcome = self._started(future, handle.key, process)
                with self._node.held(what, acts_on=list(handle.modules)):
                    if not self._node.lives.stopping.is_set():
                        self._restarted(handle, code, revived, outcome)
            except RuntimeTimeout as exc:       # the lock was not free within its deadline
                self._node.failures.add(f"restart of worker {handle.key} failed: {exc}")
                # its modules are not running, whatever their records said: failed, and said
                for name in list(handle.modules):
                    record = self._node.modules.get(name)
                    if record is not None and record.status != "failed":
                        record.status = "failed"
                        self._node.tell("module_failed", name, exit_code=code,
                                   reason=f"its restart could not take the node's lock: {exc}")

    def _revive(self, handle: WorkerHandle, code: int | None) -> dict[str, _Revival]:
        """Apply the ``restart`` policy of every module that ran in the dead worker, up to
        its start (lock held): ``never`` leaves it failed; ``fresh`` instantiates it with
        its configured state, ``last-state`` with its last checkpoint, in a new process.
        Rings are kept, so a restarted reader resumes where the dead one stopped and a
        restarted writer continues the sequence; a restarted writer of a remote link
        publishes under a new incarnation, which ``republished`` has the reader's node
        follow. The modules revived, to start; none if it failed (they are failed)."""
        budget = self._budgets.setdefault(handle.key, RestartBudget())
        names = list(handle.modules)
        revive = [n for n in names if self._node.modules[n].spec.restart != "never"]
        reason = "restart = 'never'"
        if not budget.spend() and revive:
            reason = (f"restart = '{self._node.modules[revive[0]].spec.restart}', but its worker "
                      f"died {budget.deaths} times in {budget.window:.0f} s: gave up")
            revive = []
        for name in names:
            if name not in revive and self._node.modules[name].status != "failed":
                self._node.fail(name, code, reason)
        if not revive:      # (a restart or an add later gets a new process: ensure)
            return {}
        records = {name: self._node.modules[name] for name in revive}
        for record in records.values():
            record.status = "starting"
            record.restarts += 1            # (also tells this restart from a later one)
        checkpointed = set()
        try:
            if not handle.alive:            # (an add may have started one meanwhile)
                self._node.workers.spawn(handle)
            for name, record in records.items():
                state: dict[str, Any] | bytes = record.spec.state
                if record.spec.restart == "last-state" and record.checkpoint is not None:
                    # as it came, read in the worker and restored in full: its fields
                    # made at run time were refused there, and the restart failed
                    state = record.checkpoint
                    checkpointed.add(name)
                self._node.instantiate(record, state)
            self._node.rewire(set(records))
        except Exception as exc:            # whatever it was, the modules say it
            self._give_up(handle, code, records, f"its restart failed: {exc}")
            return {}
        return {name: _Revival(record, record.restarts, name in checkpointed)
                for name, record in records.items()}

    def _started(self, future: Future[Any], key: str,
                 process: Any) -> tuple[bool, Exception | None, dict[str, str]]:
        """Wait, without the lock, for the revived modules' ``setup`` and start:
        (started, the error if the start failed, the modules whose ``setup`` raised
        with their errors); neither if the new worker died too (its restart policy
        applies again)."""
        try:
            failed = self._node.workers.result(future, "start", key, REQUEST_TIMEOUT)
        except (RuntimeFailure, RuntimeTimeout) as exc:
            return False, None if process.ended() else exc, {}
        return True, None, failed

    def _restarted(self, handle: WorkerHandle, code: int | None, revived: dict[str, _Revival],
                   outcome: tuple[bool, Exception | None, dict[str, str]]) -> None:
        """Record what came of a restart's start (lock held), for the revived modules
        still this restart's and still starting: another operation may have moved,
        removed or stopped one while the lock was free, or a later restart taken over."""
        started, error, failed = outcome
        records = {name: revival.record for name, revival in revived.items()
                   if self._current(name, revival) and revival.record.status == "starting"}
        if not records:
            return
        if error is not None or (failed and set(records) <= set(failed)):
            self._give_up(handle, code, records, f"its restart failed: "
                          f"{error or '; '.join(failed.values())}")
            return
        if not started:                      # the new worker died as well
            return
        for name in [name for name in records if name in failed]:   # the others run
            self._node.fail(name, code, f"its restart failed: {failed[name]}")
            del records[name]
        for record in records.values():
            record.status = "running"
        log.warning("restarted %s (exit code %s)", ", ".join(records), code)
        for name, record in records.items():
            said = {}
            if record.spec.restart == "last-state":
                said["from_checkpoint"] = checkpointed = revived[name].from_checkpoint
                if not checkpointed:
                    # (a checkpoint that failed was said once, as the first did; its
                    # state is found lost here)
                    log.warning("module %r restarted with its configured state, not its "
                                "last one: no checkpoint of it had been taken (its worker "
                                "died before the first, or its state cannot be pickled: see "
                                "the error 'cannot checkpoint module %r', if any)", name, name)
            self._node.tell("module_restarted", name, reason="its worker died", exit_code=code,
                            policy=record.spec.restart, **said)

    def _current(self, name: str, revival: _Revival) -> bool:
        """Whether module ``name`` is still the one ``revival`` revived."""
        record = revival.record
        return self._node.modules.get(name) is record and record.restarts == revival.restart

    def _give_up(self, handle: WorkerHandle, code: int | None,
                 records: dict[str, ModuleRecord], reason: str) -> None:
        """A restart failed: stop its new worker, unless it hosts others by now (none of
        these modules may run while reported failed), and fail each module, saying why."""
        others = [name for name in handle.modules if name not in records
                  and name in self._node.modules and self._node.modules[name].status != "failed"]
        if handle.alive and not others:
            self._node.workers.halt(handle)
        for name in records:
            self._node.fail(name, code, reason)
