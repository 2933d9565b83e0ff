"""``Executor``: the supervisor of one node (the paper's NetExecutor).

It owns everything on its node: the worker processes (one per module, or a few
packed ones; ``WorkerPool``), its links and every shared-memory ring (``Wiring``), the
bridge that receives remote links, and the records of the modules that run here. A
crashed worker is restarted by its modules' ``restart`` policies (``Restarts``); what
such a restart and the requests that meet it wait for is kept by its ``Lives``.
Shutdown stops modules in reverse start order, then the processes (terminate, then
kill), then unlinks every segment. It implements ``Node``.
"""

from __future__ import annotations

import contextlib
import importlib
import itertools
import logging
import threading
import time
from concurrent.futures import Future
from contextlib import AbstractContextManager
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import cloudpickle

from pb3a.config.description import DEFAULT_SPARES
from pb3a.config.plan import FlatLink, FlatModule
from pb3a.deadline import before_answer, bounding, capped, lifted
from pb3a.errors import ConfigError, ModuleNotFound, PB3AError, RuntimeFailure, RuntimeTimeout
from pb3a.loading.served import forget
from pb3a.loading.sources import CodeSources
from pb3a.model.module import fixed_rate_of, stepped_period
from pb3a.node.bridge import Bridge
from pb3a.node.class_check import ImportLane
from pb3a.node.lives import Lives
from pb3a.node.module_record import ModuleRecord
from pb3a.node.protocol import Endpoint, Reached
from pb3a.node.resources import ResourceMeter
from pb3a.node.restarts import LOCK_TIMEOUT, Restarts
from pb3a.node.ring_sizes import RingSize
from pb3a.node.wiring import Wiring
from pb3a.node.workers import (
    REQUEST_TIMEOUT,
    WorkerHandle,
    WorkerPool,
    WorkerSettings,
    stale_preload,
)
from pb3a.stats import FailureLog, InputStats, ModuleStats, NodeReport, WaitStats
from pb3a.transport import pickling
from pb3a.transport.auth import ClusterKey
from pb3a.transport.replication import follower_id
from pb3a.transport.shm import memory_domain, reap_orphans, segment_name, unlink_name
from pb3a.transport.snapshot import Snapshot, make_room, read_piece, write_piece

if TYPE_CHECKING:
    from collections.abc import Callable, Collection, Iterator

log = logging.getLogger("pb3a.executor")
_module_log = logging.getLogger("pb3a.module")

REPORT_TIMEOUT = 5.0
_WAITS_FOR_THE_MODULE = frozenset({"get_state", "set_state"})


class Executor:
    """Runs one node's modules in worker processes on this machine; thread-safe; every
    request has a deadline."""

    def __init__(self, node: str, *, workers: int = 0, cpus: list[int] | None = None,
                 checkpoint_s: float = 1.0, log_level: int = logging.WARNING,
                 code: CodeSources | None = None, host: str = "127.0.0.1",
                 lock: AbstractContextManager[Any] | None = None, epoch: int = 0,
                 spares: int = DEFAULT_SPARES) -> None:
        self.node = node
        self.epoch = epoch                  # the system's: older replication is refused
        self.node_epoch = 1                 # this admission of the node (a remote one's)
        self.packing = workers              # packed worker processes (0: one per module)
        self.quota = 0                      # modules per packed worker at start
        self.host = host                    # where remote readers reach this node's outputs
        self.modules: dict[str, ModuleRecord] = {}
        self.wiring = Wiring(self)                    # its links and their rings
        self.failures = FailureLog(log)               # what went wrong, for stats and logs
        self.meter = ResourceMeter(cpus)              # the machine's CPU and memory
        self.imports = ImportLane()                   # background imports vs requests
        self.handler: Any = None                      # applies agents' requests (op, args)
        self.republished: Any = None                  # told (link, endpoint) after a restart
        self.on_event: Any = None                     # told (kind, module, detail): restarts
        self.on_checkpoint: Any = None                # told (module, state) for last-state
        # whether this node's lease runs now (a remote node's share sets it, and its
        # workers' ``WorkerSettings.lease``: an embedded node has none, and never lapses)
        self.leased: Callable[[], bool] = lambda: True
        self._key: ClusterKey | None = None           # the cluster key (loaded on first use)
        self._bridge: Bridge | None = None            # remote links in (made on first use)
        self._making = threading.Lock()               # held to make the key or the bridge
        self._last_errors: dict[str, str] = {}        # module -> its last exception, logged
        # worker key -> a report's stats request it has not answered yet (frozen, stuck):
        # not asked again, nor waited for, until it does
        self._unanswered: dict[str, Future[Any]] = {}
        # Held by a restart and by whoever changes the configuration (the launcher's
        # global lock when the executor runs in the launcher's process).
        self.lock = lock or threading.RLock()
        # Python modules reloaded here (``forget``), which a worker started later drops
        # too before it loads a class (``instantiate``); first, those this process's
        # forkserver preloaded for an earlier launch whose files have changed since
        self.reloaded: list[str] = list(stale_preload())
        if self.reloaded:
            log.info("node %s: module %s changed since this process's forkserver imported "
                     "it: its workers import it again", node, ", ".join(self.reloaded))
        reap_orphans()
        self.restarts = Restarts(self)                # what a worker's death brings
        self.workers = WorkerPool(
            WorkerSettings(cpus, checkpoint_s, log_level, code or CodeSources(), spares),
            self._notice, self.restarts.died)
        # a module between its worker's death and its restart's end, a change holding
        # it paused, the node stopping: what restarts and requests wait for
        self.lives = Lives(self.modules, self.workers)
        if code is not None:                # (a node share learns it later: configure)
            self.workers.warm()

    def configure(self, *, checkpoint_s: float, log_level: int, code: CodeSources,
                  epoch: int, spares: int = DEFAULT_SPARES, node_epoch: int = 1) -> None:
        """Settings a node executor process learns from its launcher (before any module)."""
        settings = self.workers.settings
        settings.checkpoint_s, settings.log_level = checkpoint_s, log_level
        settings.spares = spares
        settings.code = code
        self.epoch, self.node_epoch = epoch, node_epoch
        # a node of its own has remote links: its spare workers open their replicators
        # as they boot, not in the preparation of a move to here
        self.workers.spare_requests = [("ready_to_publish", self.publishing())]
        self.workers.warm()
        # This process resolves the classes of modules that come to the node (a move,
        # an add): import them now, in the background, not in a move's critical path;
        # one at a time in ``imports``, whose lock requests are decoded under too.
        threading.Thread(target=_import_quietly, args=(code.preload, self.imports),
                         name="pb3a-preload", daemon=True).start()

    @property
    def bridge(self) -> Bridge:
        """The receiving end of remote links (made on first use, once)."""
        # (made twice, by a report and a move opening the first remote link here, the
        # move's ring was in one and the sender followed by the other, which dropped
        # every value the link carried from then on)
        with self._making:
            if self._bridge is None:
                self._bridge = Bridge(self._loaded_key(), self.epoch,
                                      follower_id(self.node, self.node_epoch))
            return self._bridge

    @property
    def key(self) -> ClusterKey:
        """The cluster key remote links are sealed with (loaded on first use)."""
        with self._making:
            return self._loaded_key()

    def _loaded_key(self) -> ClusterKey:
        if self._key is None:                          # (``_making`` held)
            self._key = ClusterKey.load()
        return self._key

    def call(self, worker: str, op: str, timeout: float = REQUEST_TIMEOUT, /,
             _fd: int | None = None, **args: Any) -> Any:
        """One request to a worker; its answer (waited for no longer than the deadline of
        the call in progress, if it has one: ``pb3a.deadline``)."""
        return self.workers.call(worker, op, capped(timeout), _fd=_fd, **args)

    def call_module(self, name: str, op: str, timeout: float = REQUEST_TIMEOUT, /,
                    **args: Any) -> Any:
        """Send one request about module ``name`` to its worker and wait for the answer.
        One that waits for the module's lock gives up before its caller does: if its
        caller's time runs out, it was not done, rather than done later. A module not on
        this node (removed, moved or restarted meanwhile) is ``ModuleNotFound``, here as
        across the network (it was a bare KeyError, a RuntimeFailure from afar)."""
        record = self.modules.get(name)
        if record is None:
            raise ModuleNotFound(f"module {name!r} is not on node {self.node} (removed, "
                                 "moved or restarted meanwhile)")
        if not self.alive(record.worker):
            raise RuntimeFailure(_not_running(name, record))
        timeout = capped(timeout)
        if op in _WAITS_FOR_THE_MODULE:      # (a short timeout keeps most of its time)
            args["within"] = before_answer(timeout)
        return self.call(record.worker, op, timeout, name=name, **args)

    def alive(self, key: str) -> bool:
        """Whether worker ``key`` runs and takes requests."""
        return self.workers[key].serving

    def await_restart(self, name: str, timeout: float) -> bool:
        """If module ``name``'s worker has died and its restart policy is still to act
        (or its restart is under way), wait up to ``timeout`` for that to end, without
        the node's lock, which the restart takes; True if it had to wait (a request
        that failed in the window is worth asking again), False at once otherwise."""
        return self.lives.await_restart(name, timeout)

    def restarting(self, record: ModuleRecord) -> bool:
        """Whether the module's worker is gone and its restart policy has yet to say what
        comes: a link wired meanwhile is wired at its end by that restart (``rewire``),
        from the executor's tables and rings; a request to the dead worker would fail,
        and leave the other end unwired (a move failed as its module's worker died)."""
        return not self.alive(record.worker) and record.status not in ("failed", "stopped")

    # -- placement -------------------------------------------------------------
    def place(self, spec: FlatModule) -> str:
        """The worker key a module runs in: its group, its own process, or a packed one.

        Packed modules fill the node's workers in declaration order, so modules
        declared together (usually linked together) share a process and their links
        stay in memory; modules added later go to the least-loaded worker.
        """
        if spec.group:
            return f"{spec.node}/g-{spec.group}"
        if not self.packing:
            return f"{spec.node}/m-{spec.name.replace('/', '.')}"
        counts = {f"{spec.node}-p{i}": 0 for i in range(self.packing)}
        for record in self.modules.values():
            if record.worker in counts:
                counts[record.worker] += 1
        for key, count in counts.items():
            if count < self.quota:
                return key
        return min(counts, key=counts.__getitem__)

    def expect(self, specs: list[FlatModule]) -> None:
        """Size the packed workers for the modules about to be added, in their order;
        start the workers of the others now (``spawn_workers``)."""
        if self.packing:
            count = sum(1 for spec in specs if not spec.group)
            self.quota = -(-count // self.packing)
        self.spawn_workers(specs)

    def spawn_workers(self, specs: list[FlatModule]) -> None:
        """Start the workers of modules that run in a process of their own (unpacked or
        grouped) now, side by side: ``add_module`` then finds them booting or booted."""
        for spec in specs:
            if spec.group or not self.packing:
                self.workers.ensure(self.place(spec), spec.node)

    def release_workers(self, specs: list[FlatModule]) -> None:
        """Stop the workers ``spawn_workers`` started for ``specs`` that host nothing."""
        for spec in specs:
            if spec.group or not self.packing:
                key = self.place(spec)
                handle = self.workers.handles.get(key)
                if handle is not None and not handle.modules:
                    self.workers.retire(key)
                    self.restarts.forget(key)

    # -- modules -------------------------------------------------------------
    def add_module(self, spec: FlatModule, *,
                   state: dict[str, Any] | bytes | None = None) -> None:
        """Instantiate a module in its worker (not started)."""
        blob = _class_blob(spec)
        key = self.place(spec)
        handle = self.workers.ensure(key, spec.node)
        record = ModuleRecord(spec, key, blob)
        self.modules[spec.name] = record
        handle.modules.append(spec.name)
        try:
            self.instantiate(record, spec.state if state is None else state)
        except BaseException:
            del self.modules[spec.name]
            # (stopped on another thread: a worker that did not answer, frozen say,
            # takes seconds to end, which the caller's deadline has not)
            self._vacate(key, spec.name, wait=False)
            raise

    def instantiate(self, record: ModuleRecord, state: dict[str, Any] | bytes) -> None:
        """Make module ``record`` in its worker with ``state`` (not started)."""
        spec = record.spec
        self.call(record.worker, "add", name=spec.name, cls=record.blob, period=spec.period,
                  restart=spec.restart, state=state, reloaded=tuple(self.reloaded),
                  fixed_rate=spec.fixed_rate)

    def start_modules(self, names: list[str], failing: bool = False,
                      leave_late: bool = False) -> None:
        """Run ``setup`` and start the modules, in order (those not running yet: a module
        an agent moved while the system started runs already).

        A worker that dies meanwhile is left to its modules' restart policies. A module
        whose ``setup`` raises, or whose worker's start runs out of time (it is halted
        there), does not run; the others start all the same, and ``RuntimeFailure``
        names each that did not, with why (its ``failed``: their names; its
        ``timed_out``: those of them whose start ran out of time). With
        ``failing`` they are failed here too (``module_failed``), for a caller that
        keeps them (failover); others drop them or put them back.

        With ``leave_late``, a start its worker has taken but whose ``setup`` outlasts the
        deadline of the call in progress (``pb3a.deadline``) is not halted: it is left
        to finish (``_finish_late``), and ``RuntimeTimeout`` names those modules (its
        ``late``); those that failed are then failed here, as with ``failing`` (a move
        past its point of no return keeps them where they are).
        """
        # one request per run of modules that share a worker (a group, a packed worker)
        waiting = [self.modules[name] for name in names]
        runs = itertools.groupby((r for r in waiting if r.status != "running"),
                                 key=lambda record: record.worker)
        failed: dict[str, str] = {}
        timed_out: list[str] = []
        late: list[str] = []
        for worker, records in runs:
            batch = list(records)
            starting = [record.spec.name for record in batch]
            future, sent = None, time.monotonic()
            try:
                if leave_late:          # (its future kept: a late answer is awaited)
                    future = self.workers.submit(worker, "start", names=starting)
                    failed.update(self.workers.result(future, "start", worker,
                                                      capped(REQUEST_TIMEOUT)))
                else:
                    failed.update(self.call(worker, "start", names=starting))
            except (RuntimeFailure, RuntimeTimeout) as exc:
                if not isinstance(exc, RuntimeTimeout) and self.workers[worker].process.ended():
                    continue
                if future is not None and isinstance(exc, RuntimeTimeout) \
                        and not future.done():
                    late += starting        # (taken by the worker: not withdrawn)
                    future.add_done_callback(lambda done, batch=batch: threading.Thread(
                        target=self._finish_late, args=(done, batch), daemon=True,
                        name="pb3a-late-start").start())
                    giving_up = threading.Timer(
                        max(0.0, sent + REQUEST_TIMEOUT - time.monotonic()),
                        self._give_up_late, (future, worker, batch))
                    giving_up.daemon = True
                    giving_up.start()
                    continue
                # a start out of time may still go through once a setup returns: halted
                # now, they never run
                with lifted(), contextlib.suppress(RuntimeFailure, RuntimeTimeout):
                    self.call(worker, "halt", names=starting)
                failed.update(dict.fromkeys(starting, str(exc)))
                if isinstance(exc, RuntimeTimeout):
                    timed_out += starting
                continue
            for record in batch:
                if record.spec.name not in failed:
                    record.status = "running"
        self.workers.replenish()          # for the spares they took
        if failing or late:
            for name, error in failed.items():
                self.fail(name, None, error)
        if late:
            error = RuntimeTimeout(
                f"the setup of {', '.join(late)} at node {self.node} had not returned when "
                "the call's time ran out; left to finish there")
            error.late = late                       # type: ignore[attr-defined]
            error.failed = sorted(failed)           # type: ignore[attr-defined]
            raise error
        if failed:
            error = RuntimeFailure("; ".join(dict.fromkeys(failed.values())))
            error.failed = sorted(failed)           # type: ignore[attr-defined]
            error.timed_out = sorted(timed_out)     # type: ignore[attr-defined]
            raise error

    def _give_up_late(self, future: Future[Any], worker: str,
                      batch: list[ModuleRecord]) -> None:
        """A start left to finish (``start_modules``) that outlasts the start's own
        deadline (``REQUEST_TIMEOUT`` from when it was sent) is given up, as any start
        out of time is: halted, its modules never run, and are failed."""
        if future.done():
            return
        with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
            self.call(worker, "halt", names=[record.spec.name for record in batch])
        self._record_late(batch, dict.fromkeys(
            (record.spec.name for record in batch),
            f"its setup did not return within {REQUEST_TIMEOUT:g} s"))

    def _finish_late(self, future: Future[Any], batch: list[ModuleRecord]) -> None:
        """What came of a start left to finish (its answer, or its worker's death)."""
        try:
            failed = future.result(0)
        except (RuntimeFailure, RuntimeTimeout) as exc:
            handle = self.workers.handles.get(batch[0].worker)
            if handle is None or handle.process.ended():     # its restart policies'
                return
            failed = {record.spec.name: str(exc) for record in batch}
        except Exception as exc:                # (whatever it was, the modules say it)
            failed = {record.spec.name: f"{type(exc).__name__}: {exc}" for record in batch}
        self._record_late(batch, failed)

    def _record_late(self, batch: list[ModuleRecord], failed: dict[str, str]) -> None:
        """Under the node's lock: the modules of a start left to finish that are still
        starting running, or failed (those in ``failed``, with why); one moved, removed
        or given up on meanwhile is left alone."""
        try:
            with self.held(f"finish the start of {', '.join(r.spec.name for r in batch)}"):
                for record in batch:
                    name = record.spec.name
                    if self.modules.get(name) is not record or record.status != "starting":
                        continue
                    if name in failed:
                        self.fail(name, None, failed[name])
                    else:
                        record.status = "running"
        except RuntimeTimeout as exc:
            log.warning("a start left to finish was not recorded: %s", exc)

    def swap(self, name: str, spec: FlatModule) -> tuple[list[str], list[str]]:
        """Replace a module's class by ``spec.cls`` in place; the state names kept, and
        those dropped."""
        record = self.modules[name]
        if not self.alive(record.worker):   # (it said "worker 'a/m-calib' is not running")
            raise RuntimeFailure(_not_running(name, record))
        blob = _class_blob(spec)
        kept, dropped = self.call(record.worker, "swap", name=name, cls=blob, period=spec.period)
        record.spec, record.blob = spec, blob
        return kept, dropped

    def retime(self, name: str, period: float, timeout: float = REQUEST_TIMEOUT) -> None:
        """Step the module every ``period`` seconds from now on; its restarts too."""
        record = self.modules[name]
        if not self.alive(record.worker):
            raise RuntimeFailure(_not_running(name, record))
        self.call(record.worker, "retime", capped(timeout), name=name, period=period)
        record.spec = replace(record.spec, period=period, own_period=True)

    def learn_period(self, name: str, timeout: float = REQUEST_TIMEOUT) -> float | None:
        """The period module ``name`` steps at now, read from its worker; one it set
        itself (``self.period = ...``) its record takes as given, so that its restarts
        keep it. Nothing is set in the worker."""
        record = self.modules[name]
        period = self.call_module(name, "period", timeout)
        if period is not None and period != record.spec.period:
            record.spec = replace(record.spec, period=period, own_period=True)
        return period

    def pause(self, name: str, timeout: float = REQUEST_TIMEOUT, rewire: bool = False) -> bool:
        """Hold a module's lock (no step, no event) until ``resume``; False if it does not
        run here (any more). ``rewire``: see ``NodeShare.pause``."""
        record = self.modules.get(name)
        if record is None or not self.alive(record.worker):
            return False
        # held before it is asked: a worker that dies from here on is restarted once the
        # change lets go of the module, not meanwhile (in a new worker, unpaused, its
        # outputs published anew: the change went on as if it still held it)
        self.lives.hold(record, True)
        # the answer's wait, a second more than the pause's own (less, for a caller's
        # deadline: then the pause gives up a margin before it)
        answer_s = capped(timeout + 1.0)
        timeout = min(timeout, before_answer(answer_s))
        try:
            # ``until``: a worker that reads this late (it was frozen) must not pause the
            # module once this call has given up: nobody would resume it
            self.call(record.worker, "pause", answer_s, name=name, timeout=timeout,
                      until=time.monotonic() + timeout, rewire=rewire)
        except BaseException:
            self.lives.hold(record, False)
            raise
        return True

    def resume(self, name: str) -> None:
        """Release a module paused by ``pause`` (one whose worker died meanwhile is
        restarted now), whatever the deadline of the call in progress: a module left
        paused would stay so."""
        record = self.modules.get(name)
        try:
            if record is not None and self.alive(record.worker):
                with lifted():
                    self.call(record.worker, "resume", name=name)
        finally:
            if record is not None:
                self.lives.hold(record, False)

    def stop_module(self, name: str, timeout: float = 5.0) -> None:
        """Stop stepping and dispatching, then run the module's ``teardown``: its worker
        is given ``timeout`` and 1 s more to answer, no longer than the deadline of the
        call in progress (``pb3a.deadline``: a shutdown's), and then gives up first.
        ``RuntimeTimeout`` if it has not stopped by then (busy in a body, which the
        worker names): it is left as it was, not torn down."""
        record = self.modules[name]
        if record.status == "running" and self.alive(record.worker):
            answer_s = capped(timeout + 1.0)
            try:
                self.call(record.worker, "stop", answer_s, name=name,
                          grace=min(timeout, before_answer(answer_s)))
            except RuntimeTimeout:
                record.unstopped = True
                raise
        record.status, record.unstopped = "stopped", False
        self.lives.hold(record, False)

    def kill_module(self, name: str) -> int:
        """SIGKILL the worker of module ``name``, which did not answer its stop (frozen in
        ``step`` or ``teardown``): a ``remove`` with ``force``. Not a crash, so no restart
        follows; the module is stopped (its ``teardown`` unfinished), to be removed
        (``remove_module``). The worker's process id. Refused (``RuntimeFailure``,
        nothing done) if the worker runs other modules too (packed workers, a group):
        they would be lost with it, and they are named."""
        record = self.modules[name]
        handle = self.workers[record.worker]
        others = [other for other in handle.modules if other != name]
        if others:
            raise RuntimeFailure(
                f"its worker {record.worker!r} was not killed: it also runs "
                f"{', '.join(others)}, which would be lost with it (a worker runs several "
                "modules when the node packs them, `workers = N`, or they share a group); "
                f"remove {', '.join(others)} first, and force then kills it")
        pid = handle.pid
        if handle.alive:
            self.workers.kill(record.worker)
            log.warning("module %s did not answer its stop: its worker %s (pid %s) was "
                        "killed, its teardown unfinished", name, record.worker, pid)
        record.status = "stopped"
        self.lives.hold(record, False)
        return pid

    def remove_module(self, name: str) -> None:
        """Drop a module (its links are gone) and stop its worker if it hosted nothing else.
        A worker that does not answer in time (frozen, stuck) has the module dropped all
        the same: it takes the request when it can, and, left empty, is stopped on another
        thread (not waited for), and the call raises."""
        record = self.modules.pop(name)
        self.lives.hold(record, False)
        try:
            if self.alive(record.worker):
                self.call(record.worker, "remove", name=name)
        except (RuntimeFailure, RuntimeTimeout):
            self._vacate(record.worker, name, wait=False)
            raise
        self._vacate(record.worker, name)

    def fail_module(self, name: str, reason: str) -> None:
        """Module ``name``, not started, will not run (its state could not be put back
        after a failed move): failed for ``reason``, said, what feeds it unhooked. One
        whose worker died is left to its restart policy, which acts on it."""
        record = self.modules.get(name)
        if record is not None and record.status != "failed" and not self.restarting(record):
            self.fail(name, None, reason)

    def memory_domain(self) -> str:
        """Where this node's shared-memory segments can be seen (see ``retire``)."""
        return memory_domain()

    def reserve(self, name: str, timeout: float = REQUEST_TIMEOUT) -> str:
        """Room for module ``name``'s snapshot, made before a migration pauses it: a
        segment of this executor the size of the module's state now, measured without
        waiting for a call in progress (the answer waited for up to ``timeout``;
        ``release`` it)."""
        segment = segment_name("state")
        size = self.call_module(name, "snapshot_size", timeout)
        try:
            make_room(segment, size)
        except OSError as exc:
            raise RuntimeFailure(f"no room for the {size}-byte snapshot of module {name!r} in "
                                 f"shared memory ({exc.strerror}): make /dev/shm larger, or "
                                 "the module's state smaller") from None
        return segment

    def retire(self, name: str, segment: str, carry: bool) -> Snapshot:
        """The migration fence: ``teardown``, then capture the module's state and unconsumed
        inputs into ``segment`` (see ``reserve``), and drop the module here; it runs
        nowhere until restored (``land``). With ``carry`` (a destination in another
        memory domain) the parts travel in the snapshot instead. The worker the module
        leaves is stopped by ``release``, after the pause, if nothing else runs there."""
        record = self.modules[name]
        if not self.alive(record.worker):
            raise RuntimeFailure(_died_moving(name, record))
        try:
            # ``until``: a worker that is late (frozen, or a teardown that overran) keeps
            # the module, as this executor then does (what is left of a caller's
            # deadline, if less than the capture's own)
            answer_s = capped(REQUEST_TIMEOUT)
            snapshot: Snapshot = self.call(record.worker, "migrate_out", answer_s,
                                           name=name, segment=segment,
                                           until=time.monotonic()
                                           + before_answer(answer_s))
        except RuntimeFailure as exc:
            if self.alive(record.worker):
                raise
            raise RuntimeFailure(_died_moving(name, record)) from exc
        del self.modules[name]
        self.workers[record.worker].modules.remove(name)
        self.lives.hold(record, False)
        return snapshot.carry() if carry else snapshot

    def land(self, name: str, snapshot: Snapshot) -> float:
        """Restore what ``retire`` captured into the (instantiated, not started) module;
        the seconds its worker took. A snapshot carried, or staged here in pieces, is
        unlinked once restored (or not)."""
        here = snapshot.lay_out(segment_name("state")) if snapshot.carried else snapshot
        try:
            return self.call_module(name, "migrate_in", snapshot=here)
        finally:
            if here is not snapshot or snapshot.staged:
                unlink_name(here.segment)

    def read_snapshot(self, segment: str, offset: int, size: int) -> bytes:
        return read_piece(segment, offset, size)

    def write_snapshot(self, segment: str, size: int, offset: int, data: bytes) -> str:
        if not segment:
            segment = segment_name("state")
            make_room(segment, size)
        write_piece(segment, offset, data)
        return segment

    def release(self, segment: str) -> None:
        """A migration from here is over (or did not happen): unlink the segment reserved
        for it and stop the workers it left empty (a move back home after a failed
        landing reuses its worker)."""
        unlink_name(segment)
        for key, handle in list(self.workers.handles.items()):
            if not handle.modules:
                self.workers.retire(key, wait=False)
                self.restarts.forget(key)

    def _vacate(self, key: str, name: str, wait: bool = True) -> None:
        """``name`` no longer runs in worker ``key``; stop the worker if it is empty now
        (``wait``: until it has ended, else on another thread)."""
        handle = self.workers[key]
        handle.modules.remove(name)
        if not handle.modules:
            self.workers.retire(key, wait=wait)
            self.restarts.forget(key)

    def forget(self, module: str) -> None:
        """Drop cached copies of Python module ``module`` here and in every worker, and
        in every worker started later (``reloaded``: forked from a forkserver that
        imported it before, a restart or a move ran the code from before the reload,
        also after a swap to the new one)."""
        forget(module)
        if module not in self.reloaded:
            self.reloaded.append(module)
        for key, handle in list(self.workers.handles.items()):
            if handle.alive:
                self.call(key, "forget", module=module)

    # -- links (``Wiring``) -----------------------------------------------------------
    def connect(self, links: list[FlatLink]) -> None:
        """Wire links with both ends here (``Wiring.connect``)."""
        self.wiring.connect(links)

    def detach(self, links: list[FlatLink]) -> None:
        """Unwire links with both ends here (``Wiring.detach``)."""
        self.wiring.detach(links)

    def ready_to_publish(self, name: str) -> None:
        """Bind module ``name``'s publishing sockets now (``Wiring.ready_to_publish``)."""
        self.wiring.ready_to_publish(name)

    def publish(self, links: list[FlatLink]) -> list[Endpoint]:
        """The writing halves of remote links (``Wiring.publish``)."""
        return self.wiring.publish(links)

    def publishing(self) -> dict[str, Any]:
        """What a worker publishes with: the cluster key, this node's address, the epoch."""
        return {"secret": self.key.secret, "host": self.host, "epoch": self.epoch}

    def unpublish(self, links: list[FlatLink]) -> list[Reached]:
        """Stop publishing for each link (``Wiring.unpublish``)."""
        return self.wiring.unpublish(links)

    def unacknowledged(self, link: FlatLink, reader: bytes) -> int:
        """What a lost follower never acknowledged (``Wiring.unacknowledged``)."""
        return self.wiring.unacknowledged(link, reader)

    def open_inbound(self, links: list[tuple[FlatLink, RingSize | None]]) -> None:
        """The reading halves of remote links (``Wiring.open_inbound``)."""
        self.wiring.open_inbound(links)

    def follow(self, links: list[tuple[FlatLink, Endpoint]]) -> None:
        """Receive each link's output from its sender (``Wiring.follow``)."""
        self.wiring.follow(links)

    def close_inbound(self, links: list[tuple[FlatLink, Reached]]) -> list[int]:
        """Stop receiving remote links (``Wiring.close_inbound``)."""
        return self.wiring.close_inbound(links)

    # -- figures ---------------------------------------------------------------
    def report(self, timeout: float = REPORT_TIMEOUT) -> NodeReport:
        """Figures of every module of this node (one request to each worker, waited for
        ``timeout`` in all), its rings' fill, its remote links' losses, its CPU (since
        the last report) and memory, and how many spare workers it has booted."""
        asked = {key: handle for key, handle in list(self.workers.handles.items())
                 if handle.serving}
        # a worker that has not answered an earlier report is silent at once: waited for
        # at each report, one frozen worker made every report wait its whole deadline
        # (the manager's live figures came every 5 s, not every 0.5 s)
        unanswered = {key: future for key, future in self._unanswered.items()
                      if not future.done() and asked.get(key) is getattr(
                          future, "pb3a_worker", None)}
        # (each to the handle taken above: a report runs beside the changes, and a move
        # may have dropped the worker since; that one's request fails, and it is silent)
        futures = {key: self.workers.submit_to(handle, "stats")
                   for key, handle in asked.items() if key not in unanswered}
        reports: dict[str, Any] = {}
        deadline = time.monotonic() + timeout           # one for all: they answer at once
        for key, future in futures.items():             # (each frozen worker took 5 s more)
            with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
                reports[key] = self.workers.result(future, "stats", key,
                                                   max(0.0, deadline - time.monotonic()))
        self._unanswered = {**unanswered, **{key: future for key, future in futures.items()
                                             if not future.done()}}
        for key, answer in reports.items():
            asked[key].last_answer = answer
        silent = {key: handle.pid for key, handle in asked.items()
                  if key not in reports and handle.alive}
        for key, handle in list(self.workers.handles.items()):      # stopped, or stopping
            if key not in reports and handle.last_figures:
                reports[key] = {**handle.last_figures, "pid": None}
            elif key in silent and handle.last_answer:     # (its figures then, not zeros)
                reports[key] = handle.last_answer
        modules = {name: self._module_stats(record, reports.get(record.worker),
                                            silent.get(record.worker),
                                            self.lives.revival(name))
                   for name, record in list(self.modules.items())}  # (a change adds some)
        rings = {key: ring.get("used", 0) for report in reports.values()
                 for key, ring in report.get("rings", {}).items()}
        lost, drops = self.wiring.inbound_losses()
        return NodeReport(modules, rings, lost, self.failures.lines(), self.meter.sample(),
                          len(self.workers.spare_pids()), drops)

    def worker_pids(self) -> list[int]:
        """The process ids of this node's running workers."""
        return [handle.pid for handle in list(self.workers.handles.values()) if handle.alive]

    @staticmethod
    def _module_stats(record: ModuleRecord, report: dict[str, Any] | None,
                      silent_pid: int | None,
                      revival: tuple[str, float] | None = None) -> ModuleStats:
        """A module's figures from its worker's ``report``; ``silent_pid``: its worker's
        process id if it runs but did not answer in time (``silent``: it was shown
        with no process, as if it had none), ``report`` its last answer then, if any
        (a frozen worker's modules showed zeros); ``revival``: its restart under way, if
        any (``Lives.revival``), named as the change in progress."""
        spec = record.spec
        base = {"cls": f"{spec.cls.__module__}:{spec.cls.__qualname__}", "node": spec.node,
                "worker": record.worker, "status": record.status,
                "period": stepped_period(spec.cls, spec.period),
                "fixed_rate": fixed_rate_of(spec.cls, spec.fixed_rate),
                "restarts": record.restarts, "checkpoints": record.checkpoints}
        if revival is not None:
            base |= {"change": revival[0], "change_s": max(0.0, time.monotonic() - revival[1])}
        figures = None if report is None else report["modules"].get(spec.name)
        if figures is None:
            return ModuleStats(**base, pid=silent_pid, silent=silent_pid is not None)
        calling, calling_s = ("", 0.0) if silent_pid is not None else \
            figures["calling"] or ("", 0.0)
        return ModuleStats(
            **{**base, "cls": figures["class"], "period": figures["period"],
               "fixed_rate": figures["fixed_rate"]},
            overruns=figures["overruns"],
            pid=report["pid"],
            running=figures["running"] and record.status == "running" and silent_pid is None,
            silent=silent_pid is not None,
            calling=calling, calling_s=calling_s,
            steps=figures["steps"], events=figures["events"], errors=figures["errors"],
            last_error=figures["last_error"], last_error_at=figures["last_error_at"],
            cpu=figures["cpu"],
            inputs={name: InputStats(**port) for name, port in figures["inputs"].items()},
            outputs=dict(figures["outputs"]),
            output_waits={name: WaitStats(waits["waits"], waits["wait_s"])
                          for name, waits in figures["waits"].items()},
            link_waits={key: WaitStats(*link) for waits in figures["waits"].values()
                        for key, link in waits["links"].items()})

    # -- what workers tell ---------------------------------------------------------
    def _notice(self, handle: WorkerHandle, kind: str, args: dict[str, Any]) -> None:
        if kind == "figures":       # (its last words: it reads no request from now on)
            handle.last_figures = args
            self.workers.answer_waiting(handle, "stats", {**args, "pid": None})
        elif kind == "checkpoint":
            record = self.modules.get(args["name"])
            if record is not None:
                record.checkpoint = args["state"]
                record.checkpoints += 1
                if record.spec.restart == "last-state" and self.on_checkpoint is not None:
                    self.on_checkpoint(args["name"], args["state"])   # kept off this node
        elif kind == "error":
            self._log_error(args["name"], args["where"], args["trace"], args["suppressed"])
        elif kind == "log":                 # a record the worker logged, logged here
            logging.getLogger(args["logger"]).log(
                args["level"], "[worker %s] %s", handle.key, args["message"],
                extra={"pb3a_node": self.node, "pb3a_module": args.get("module", "")})
        elif kind == "request":
            threading.Thread(target=self._serve_request, args=(handle, args), daemon=True,
                             name="pb3a-agent-request").start()

    def _log_error(self, name: str, where: str, trace: str, suppressed: int) -> None:
        """A module's exception: with its traceback the first time (or when it is another
        one), then one line with how many there were (the worker reports at most one a
        second, counting the others)."""
        error = trace.rstrip().rpartition("\n")[2]
        more = f" ({suppressed} more since the last report)" if suppressed else ""
        extra = {"pb3a_module": name, "pb3a_node": self.node}
        if self._last_errors.get(name) == error:
            _module_log.error("module %r raised in %s again%s: %s", name, where, more, error,
                              extra=extra)
        else:
            self._last_errors[name] = error
            _module_log.error("module %r raised in %s%s:\n%s", name, where, more,
                              trace.rstrip(), extra=extra)

    def _serve_request(self, handle: WorkerHandle, request: dict[str, Any]) -> None:
        """Apply an agent's request through ``handler`` and send the answer back."""
        try:
            args = cloudpickle.loads(request["args"])
            if self.handler is None:
                raise RuntimeFailure("this executor takes no requests from agents")
            answer = {"id": request["id"], "ok": True, "result": self.handler(request["op"], args)}
        except PB3AError as exc:        # the agent gets the same error (ModuleNotFound ...)
            answer = {"id": request["id"], "ok": False, "result": exc}
        except Exception as exc:
            answer = {"id": request["id"], "ok": False, "result": f"{type(exc).__name__}: {exc}"}
        try:
            handle.send(None, "answer", answer)
        except (OSError, ValueError):
            return                                 # the worker is gone
        except Exception as exc:                   # the result cannot be pickled
            with contextlib.suppress(OSError, ValueError):
                handle.send(None, "answer", {"id": request["id"], "ok": False, "result": (
                    f"the answer could not be pickled: {type(exc).__name__}: {exc}")})

    # -- the lock, and what a restart (``Restarts``) does here -----------------------
    def held(self, what: str, timeout: float = LOCK_TIMEOUT, *,
             acts_on: Collection[str] = ()) -> AbstractContextManager[Any]:
        """``self.lock``, held for ``what`` (which the launcher's lock names to a waiter,
        and its figures on the modules it ``acts_on``); ``RuntimeTimeout`` if it is not
        free within ``timeout``."""
        held = getattr(self.lock, "held", None)
        return _within(self.lock, what, timeout) if held is None else \
            held(what, timeout, acts_on=acts_on)

    def rewire(self, revived: set[str]) -> None:
        """Attach every link of restarted modules again (``Wiring.rewire``)."""
        self.wiring.rewire(revived)

    def fail(self, name: str, code: int | None, reason: str) -> None:
        """Module ``name`` will not run again by itself: record and say why, and unhook
        what feeds it."""
        record = self.modules[name]
        record.status = "failed"
        self.failures.add(f"module {name} failed (worker exit code {code}); {reason}")
        self.tell("module_failed", name, exit_code=code, reason=reason)
        self.wiring.unhook(name)

    def tell(self, kind: str, name: str, **detail: Any) -> None:
        """Report an event about module ``name`` to ``on_event`` (the system's log)."""
        if self.on_event is not None:
            self.on_event(kind, name, **detail)

    # -- shutdown ------------------------------------------------------------
    def fence(self, gone_by: float | None = None) -> None:
        """Stop every module's stepping now, without the executor's lock (a request may
        hold it, waiting on a worker): its node's lease ran out, so its modules are about
        to be restarted elsewhere; a worker still tearing down at ``gone_by`` is killed
        (``WorkerPool.fence``). ``shutdown`` follows."""
        self.lives.closing.set()
        self.lives.stop()        # (a restart waiting for a change to let go waits no more)
        self.workers.fence(gone_by)

    def shutdown(self, timeout: float = 10.0) -> None:
        """Stop modules in reverse start order, then workers, then free every ring, within
        ``timeout`` and a moment to kill what did not stop (``WorkerPool.close``). The
        executor's lock is waited for half of ``timeout`` at most (a request holding it
        fails once its worker is gone); the rest is done without it if need be. A module
        whose worker does not answer by the deadline is not torn down: its worker is
        killed."""
        self.lives.closing.set()
        deadline = time.monotonic() + timeout
        with contextlib.ExitStack() as held:
            try:
                held.enter_context(self.held(f"shut down node {self.node}", timeout / 2))
            except RuntimeTimeout as exc:
                log.warning("%s: shutting down without it", exc)
            for name in reversed(list(self.modules)):
                record = self.modules.get(name)
                said = record is not None and record.unstopped
                try:            # (without the lock, a request may have removed it)
                    if record is not None:
                        # (its request waits no longer than the deadline: ``stop_module``)
                        with bounding(deadline - time.monotonic()):
                            self.stop_module(name, timeout=2.0)
                except Exception as exc:
                    # (once: the launcher's stop just before, or a remove's, said it
                    # and named the module; it was logged twice)
                    log.log(logging.INFO if said else logging.WARNING,
                            "module %r was not stopped (its worker is killed): %s", name, exc)
            self.lives.stop()
            self.workers.close(max(0.0, deadline - time.monotonic()))
            if self._bridge is not None:
                self._bridge.shutdown()
            self.wiring.close()
            self.meter.close()


@contextlib.contextmanager
def _within(lock: threading.RLock, what: str, timeout: float) -> Iterator[None]:
    """Hold ``lock`` for ``what``, waiting ``timeout`` seconds at most."""
    if not lock.acquire(timeout=timeout):
        raise RuntimeTimeout(f"{what}: the node's lock was not free within {timeout:g} s")
    try:
        yield
    finally:
        lock.release()


def _class_blob(spec: FlatModule) -> bytes:
    """The module's class pickled for its worker; ``ConfigError`` naming the class
    attributes that cannot travel (a class defined in a script goes by value, with
    them), where pickle's own error named only a type."""
    try:
        return pickling.dumps(spec.cls)
    except Exception as exc:
        raise ConfigError([f"module {spec.name}: "
                           f"{pickling.unsendable_class_reason(spec.cls, exc)}"]) from None


def _import_quietly(modules: tuple[str, ...], lane: ImportLane) -> None:
    """Import ``modules``, each in ``lane``; one that fails is left to fail, with its
    message, when a module of it is added (or when the launch checks its classes)."""
    for name in modules:
        with lane.importing(name), contextlib.suppress(Exception):
            importlib.import_module(name)


def _died_moving(name: str, record: ModuleRecord) -> str:
    """Why module ``name``, paused for a move, cannot be captured: its worker died."""
    return (f"the worker of module {name!r} died during its move, so it was not moved; "
            f"its restart policy ({record.spec.restart!r}) says what comes on node "
            f"{record.spec.node} once the move has let go of it")


def _not_running(name: str, record: ModuleRecord) -> str:
    """Why a request about module ``name`` cannot go: said of the module, not its worker."""
    if record.status == "failed":
        return (f"module {name!r} is not running: it failed (`pb3a status` and its log "
                "say why; a restart runs it again)")
    if record.status == "stopped":
        return f"module {name!r} is not running: it is stopped"
    return (f"module {name!r} is not running now: its worker has gone, and its restart "
            f"policy ({record.spec.restart!r}) says what comes; ask again once it runs")
