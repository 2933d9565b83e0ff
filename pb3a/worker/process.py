"""The worker process: hosts one or more module actors for its executor.

A worker has three kinds of threads: the control thread (requests from the
executor over a private pipe, answered in order), the receiver (drains every
inbound ring, sleeping on the process's doorbell when all are empty), and the
event pool (or the receiver itself, when the worker hosts a single module) plus
one step thread per threaded module. The worker exits when the
executor says so or when the pipe closes (the executor died).
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import logging
import os
import pickle
import signal
import sys
import threading
import time
from multiprocessing import reduction
from typing import TYPE_CHECKING, Any

import cloudpickle

from pb3a.errors import RuntimeCancelled, RuntimeTimeout
from pb3a.loading import served
from pb3a.loading.references import class_ref
from pb3a.loading.served import forget
from pb3a.loading.sources import CodeSources
from pb3a.model.agent import Agent, RuntimeClient
from pb3a.model.module import StateRefused, restore_state
from pb3a.model.ports import InputPort, Policy, WaitCounter
from pb3a.model.state_edits import configured
from pb3a.processes import mark_as
from pb3a.throttle import Throttle
from pb3a.transport import pickling
from pb3a.transport.codec import local_copy
from pb3a.transport.doorbell import BellPull
from pb3a.transport.pipe import Outbox, Outgoing
from pb3a.transport.ring import RingSize, ShmRing, sleep
from pb3a.transport.snapshot import Snapshot
from pb3a.worker.actor import EventPool, ModuleActor, SetupError, running_module
from pb3a.worker.inbound import GUARD_TIMEOUT, InboundLink, LosslessInboundLink
from pb3a.worker.lease import LEASE_LAPSED, Lease, LeaseBoard
from pb3a.worker.log_forwarding import LogForwarder
from pb3a.worker.periods import PeriodTeller
from pb3a.worker.publications import Publications
from pb3a.worker.waits import RuntimeWait

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator, Sequence

log = logging.getLogger("pb3a.worker")

SPIN_S = 100e-6          # values closer than this count as dense; poll this long for the next
ERROR_REPORT_S = 1.0     # a module's exceptions are reported at most this often (all counted)
AGENT_REQUEST_TIMEOUT = 30.0   # an agent's request to the runtime (a migration, say)
RUNTIME_WAY_BACK_S = 1.0       # ... given a timeout: its answer's way back beyond it
TIMED_OUT = "timed out"   # a reply's status for a request that ran out of time (not False)
REFUSED = "refused"       # for one whose arguments the module refused: the message is whole
LAST_WORDS_S = 0.5        # a stopping worker's wait to tell its figures (the executor frozen?)
# Log records and error reports are dropped (and counted) while this many messages wait
# for the executor to read: a module logging in a loop must not fill the memory.
NOTICE_BACKLOG = 100
_DROPPABLE = frozenset({"log", "error"})


class Refused(Exception):
    """A request the module refused for what it asked (a state name it lacks, a value
    of the wrong kind, one its class refuses): its message is for the caller as it is,
    with no worker named."""
# Requests that wait for a module's lock (and may run its hooks, which may call the
# runtime, whose answer this thread reads): never on the control thread.
_TAKES_A_MODULE_LOCK = frozenset({"get_state", "set_state", "pause", "start", "swap", "stop",
                                  "remove", "snapshot_size", "halt"})


class Worker:
    """Everything one worker process runs; ``serve`` is its control loop."""

    def __init__(self, conn: Any, key: str, bell: int, checkpoint_s: float,
                 board: LeaseBoard | None = None) -> None:
        self.conn = conn
        self.key = key
        self.actors: dict[str, ModuleActor] = {}
        # the Python modules reloaded that this process has dropped (``op_forget``)
        self.reloaded: set[str] = set()
        self.restart_policy: dict[str, str] = {}
        self.pool = EventPool()
        self._bell_fd = bell                     # ours to close; the receiver sleeps on it
        self._wake = BellPull(os.dup(bell))
        self.inbound: dict[str, InboundLink] = {}
        # what the receiver loops over, replaced (never mutated) when links change
        # (and whether some are lossless: those whose input is full are left alone)
        self._receiving: tuple[list[InboundLink], list[Any], bool] = ([], [], False)
        self.outbound: dict[str, tuple[str, str, ShmRing | None, BellPull | None]] = {}
        self.publications = Publications()       # outputs replicated to other nodes
        # What goes to the executor never waits for it (a frozen executor reads
        # nothing): a module's log record or error report, an agent's request.
        self.outbox = Outbox(conn.fileno())
        self._checkpoints: dict[str, Outgoing] = {}    # the last one each, if unsent
        self._uncheckpointed: set[str] = set()   # modules whose checkpoint failed, said once
        self._dropped = 0                   # notices dropped while the executor read nothing
        self._dropping = threading.Lock()   # (counted by any module's thread)
        # agents' requests awaiting answers, and those telling a period (``PeriodTeller``)
        self._requests: dict[int, RuntimeWait | _Answered] = {}
        self.periods = PeriodTeller(self._ask_period)  # the periods modules set themselves
        self._paused: set[str] = set()
        self._held: dict[str, threading.Event] = {}   # paused where they wait: see op_pause
        self._set_up_on_resume: set[str] = set()     # see op_migrate_out
        self._error_reports: dict[str, Throttle] = {}     # by module
        self._ready: list[Callable[..., None]] = []      # actors' dispatches, inline
        self._request_ids = itertools.count()
        self._closing = threading.Event()
        # (its modules named: a spare that took them still has the key "spare")
        self.lease = Lease(self._closing, lambda: ", ".join(self.actors) or "no module",
                           board)
        self._shut_down = False
        self._checkpoint_s = checkpoint_s
        self._threads = [threading.Thread(target=self._receive, name="pb3a-receiver", daemon=True),
                         threading.Thread(target=self._checkpoint, name="pb3a-checkpoint",
                                          daemon=True)]
        self._solo = False                     # one module here: dispatch inline
        for thread in self._threads:
            thread.start()
        self._receiver_id = self._threads[0].ident

    # -- control loop ------------------------------------------------------
    def serve(self) -> None:
        while True:
            try:
                head = self.conn.recv()
                if head is None:
                    break
                req_id, op, with_fd = head
                body = self.conn.recv_bytes()
            except (EOFError, OSError):
                break                                   # the executor is gone
            try:
                args = pickle.loads(body)
            except Exception as exc:                    # fails this request, not the worker
                if with_fd:                             # (its descriptor is not for the next)
                    os.close(reduction.recv_handle(self.conn))
                why = f"could not be read in worker {self.key}: {type(exc).__name__}: {exc}"
                if req_id is None:
                    log.error("an answer to a request %s", why)
                else:
                    self.send((req_id, False, f"the request {op!r} {why}"))
                continue
            if req_id is None:                          # an answer to one of our requests
                self._answer(**args)
            elif op in _TAKES_A_MODULE_LOCK:
                # This thread must go on reading: the module may be a body waiting for
                # the answer to its own runtime request (see ``waits``).
                threading.Thread(target=self._handle, args=(req_id, op, args), daemon=True,
                                 name=f"pb3a-{op}").start()
            else:
                self._handle(req_id, op, args)
        self.shutdown()

    def _handle(self, req_id: int, op: str, args: dict[str, Any]) -> None:
        try:
            result = getattr(self, f"op_{op}")(**args)
            reply = (req_id, True, result)
        except TimeoutError as exc:             # (a module busy past the request's wait)
            reply = (req_id, TIMED_OUT, f"{type(exc).__name__}: {exc}")
        except Refused as exc:
            reply = (req_id, REFUSED, str(exc))
        except Exception as exc:
            log.debug("request %s failed", op, exc_info=True)
            reply = (req_id, False, f"{type(exc).__name__}: {exc}")
        self.send(reply)

    def send(self, message: tuple[int | None, Any, Any]) -> Outgoing | None:
        """Send a reply ``(req_id, ok, result)`` or a notice ``(None, kind, payload)``
        to the executor, never waiting for it: what its pipe has no room for goes later,
        in order. Its head goes, then its payload pickled on its own, so a payload that
        cannot be pickled here (a state holding a lock) or read there (a class only this
        process can import) fails only its own request, saying why, and never the pipe.

        While the executor reads nothing, a module's checkpoint replaces its last one
        not yet gone, and log records and error reports past ``NOTICE_BACKLOG`` waiting
        messages are dropped, and counted in a warning sent once there is room. The
        message, or None if it was not sent."""
        req_id, kind, payload = message
        if req_id is None and kind in _DROPPABLE and self.outbox.waiting() >= NOTICE_BACKLOG:
            with self._dropping:
                self._dropped += 1
            return None
        try:
            body = pickling.dumps(payload)   # (a class sent by value, too)
        except Exception as exc:
            if req_id is None:
                log.error("a %s notice could not be pickled: %s: %s", kind,
                          type(exc).__name__, exc)
                return None
            kind, body = False, pickling.dumps("its answer could not be pickled: "
                                               + pickling.unpicklable_reason(exc, payload))
        if kind == "checkpoint":
            earlier = self._checkpoints.pop(payload["name"], None)
            if earlier is not None:
                self.outbox.withdraw(earlier)        # (unless it began to go)
        try:
            self._tell_dropped()
            sent = self.outbox.put([pickle.dumps((req_id, kind)), body])
        except OSError:                              # the executor is gone
            self._closing.set()
            return None
        if kind == "checkpoint":
            self._checkpoints[payload["name"]] = sent
        return sent

    def _tell_dropped(self) -> None:
        """A warning with how many notices were dropped since the last one, once nothing
        waits to go (the executor reads again)."""
        if not self._dropped or self.outbox.waiting():
            return
        with self._dropping:
            dropped, self._dropped = self._dropped, 0
        if dropped:
            self.outbox.put([pickle.dumps((None, "log")), pickling.dumps({
                "level": logging.WARNING, "logger": log.name, "message": (
                    f"{dropped} log records and error reports of this worker were "
                    "dropped: its executor read nothing for a while (frozen, or "
                    "starved of CPU)")})])

    def shutdown(self) -> None:
        if self._shut_down:
            return
        self._shut_down = True
        if threading.current_thread() is threading.main_thread():
            # a second SIGTERM (the executor's, once its wait runs out) must not cut the
            # teardowns short: SIGKILL is what ends a worker that overruns them
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
        self._closing.set()
        self.bell_self()                      # the receiver leaves its sleep and its loop
        # Every module stops stepping at once, then each is torn down in reverse start
        # order: a slow teardown must not leave the others running (a fenced node's
        # modules must be still before their failed-over copies start elsewhere).
        for actor in list(self.actors.values()):        # (a removal may run meanwhile)
            actor.halt()
        # Their figures as they stopped, which the executor shows for them once this
        # process is gone: a SIGTERM to the whole process group stops the workers before
        # the launcher asks for its last table, which then read zeros.
        try:
            figures = self.send((None, "figures", self.op_stats()))
        except Exception:                    # (a removal changed the modules meanwhile)
            log.debug("the worker's last figures could not be taken", exc_info=True)
        else:             # (if the executor is frozen, the teardowns and the exit go on)
            if figures is not None:
                self.outbox.wait_sent(figures, LAST_WORDS_S)
        stopped = [actor for actor in reversed(list(self.actors.values()))
                   if actor.stop(timeout=1.0)]
        self.pool.close(timeout=1.0)
        for link in list(self.inbound.values()):
            try:
                link.close()
            except Exception:                 # (closed all the same)
                log.exception("cannot take the rest of link %s", link.ring.label)
        for _, _, ring, pull in self.outbound.values():
            if ring is not None:
                ring.close()
            if pull is not None:
                pull.close()
        self.publications.close()
        self._threads[0].join(1.0)            # (before its doorbell's descriptor goes)
        for actor in stopped:                 # (a module's files written out and closed)
            actor.let_go()
        os.close(self._bell_fd)
        self._wake.close()
        # what is still going (an answer, the teardowns' log records) goes before the
        # process ends, unless the executor is frozen
        self.outbox.close(LAST_WORDS_S)

    # -- requests from the executor ----------------------------------------
    def op_add(self, name: str, cls: bytes, period: float | None, restart: str,
               state: dict[str, Any] | bytes, reloaded: tuple[str, ...] = (),
               fixed_rate: bool | None = None) -> None:
        """A module, run under its node's lease from now on (``Lease.take``: a spare
        holds none while it runs nothing); ``fixed_rate``: the configuration's (None:
        its class's).
        ``state`` as bytes is the module's own (a checkpoint, the state it had before a
        restart), restored in full (``restore_state``); as a dict, the configuration's.
        ``reloaded``: the Python modules reloaded on the node, dropped here first if this
        process has not (its forkserver imported them before the reload)."""
        self.lease.take()
        for module in reloaded:
            if module not in self.reloaded:
                self.op_forget(module)
        klass = _load_class(cls)
        module = _made(name, klass)
        self._give_runtime(name, module)
        if isinstance(state, bytes):        # (read here, where the module's code is)
            restore_state(module, cloudpickle.loads(state))
        elif state:
            try:
                module.set_state(_as_held(module, state))
            except Exception as exc:        # (its own set_state: a key it does not take)
                raise Refused(f"module {name!r} ({class_ref(klass)}): setting its state "
                              f"({', '.join(map(str, state))}) failed: "
                              f"{type(exc).__name__}: {exc}") from None
        actor = ModuleActor(name, module, self._schedule, period, on_error=self._report_error,
                            on_period=self.periods.tell, fixed_rate=fixed_rate)
        if self.lease.applies:
            actor.may_run = self.lease.holds
        self.actors[name] = actor
        self.restart_policy[name] = restart
        self._retime()

    def _retime(self) -> None:
        self._solo = solo = len(self.actors) == 1
        for actor in self.actors.values():
            actor.timed = not solo

    def op_start(self, names: list[str]) -> dict[str, str]:
        """Start the modules in order: those whose ``setup`` raised do not run (the
        others start all the same), each named with its error."""
        failed = {}
        for name in names:
            try:
                self.actors[name].start()
            except SetupError as exc:
                failed[name] = str(exc)
        return failed

    def op_halt(self, names: list[str]) -> None:
        """Modules whose start was given up on: one still in its ``setup`` never runs
        once it returns, one that started meanwhile is stopped."""
        for name in names:
            actor = self.actors.get(name)
            if actor is None:
                continue
            if actor.running:
                actor.stop(timeout=1.0)
            else:
                actor.halt()

    def op_stop(self, name: str, grace: float) -> bool:
        """Stop module ``name`` and run its ``teardown``; TimeoutError, saying what it is
        busy in, if it has not stopped within ``grace`` (a module stuck in ``on_input``
        answered False, which was taken for stopped: its worker was killed, its
        teardown never run, nothing said)."""
        actor = self.actors[name]
        if not actor.stop(grace):
            raise TimeoutError(f"module {name!r} did not stop within {grace:.1f} s: it is busy "
                               f"{actor.busy_in() or 'in a call'}, and its teardown has not "
                               f"{'finished' if actor.tearing_down else 'run'}")
        return True

    def op_retime(self, name: str, period: float) -> None:
        """Step module ``name`` every ``period`` seconds from its next step on."""
        self.actors[name].retime(period)

    def op_period(self, name: str) -> float | None:
        """The period module ``name`` steps at now (None: only on events)."""
        return self.actors[name].period

    def op_pause(self, name: str, timeout: float, until: float | None = None,
                 rewire: bool = False) -> None:
        """Hold the module's lock so it neither steps nor handles events (for rewiring),
        not past ``until`` (``time.monotonic()``), when its executor stops waiting: a
        pause read late (this worker was frozen) or taken late would never be resumed.
        With ``rewire`` (only its links change), a body waiting in a runtime call is held
        where it waits (``ModuleActor.hold_waiting``) rather than cancelled."""
        actor = self.actors[name]
        wait = timeout if until is None else min(timeout, until - time.monotonic())
        late = TimeoutError(f"module {name!r} was not paused in time: its executor "
                            "stopped waiting (this worker was frozen)")
        if wait <= 0:
            raise late
        release = actor.hold_waiting(wait) if rewire else None
        if release is not None:
            if until is not None and time.monotonic() > until:    # (frozen as it took it)
                release.set()
                raise late
            self._held[name] = release
            return
        if not actor.acquire_stopped(wait, f"module {name!r} is being paused (to move "
                                     "it, or to rewire its links)"):
            raise TimeoutError(f"module {name!r} did not finish its call within {timeout} s")
        if until is not None and time.monotonic() > until:    # (frozen as it took it)
            actor.lock.release()
            raise late
        self._paused.add(name)

    def op_resume(self, name: str) -> None:
        held = self._held.pop(name, None)
        if held is not None:
            if name in self.actors:
                self.actors[name].paused_over()
            held.set()
        if name in self._paused:
            self._paused.discard(name)
            actor = self.actors[name]
            actor.paused_over()
            actor.lock.release()
            if name in self._set_up_on_resume:      # (its move failed after its teardown)
                self._set_up_on_resume.discard(name)
                threading.Thread(target=self._set_up_again, args=(name, actor), daemon=True,
                                 name="pb3a-start").start()

    def _set_up_again(self, name: str, actor: ModuleActor) -> None:
        """Start a module again whose move failed after its ``teardown`` (see
        ``op_migrate_out``), once its old step thread has ended."""
        actor.join(timeout=1.0)
        failed = self.op_start([name])
        if failed:
            log.error("module %r did not start again after its move failed: %s", name,
                      failed[name])

    def op_snapshot_size(self, name: str) -> int:
        """The bytes a migration's snapshot of the module would take now: room made for
        it before the move pauses anything. Measured under the module's lock if it is
        free, else not at all (0: the capture, in the pause, makes the room): a measure
        that waited for a call in progress made a module in a long step wait for two
        steps before it moved (a 3 s step ran out a move's 4.5 s), and one beside the
        call would run the module's ``get_state`` beside its body."""
        actor = self.actors[name]
        if not actor.lock.acquire(timeout=0):
            return 0
        try:
            holdings = actor.holdings()
            with _movable(name, holdings["state"]):     # (before anything of the move)
                return Snapshot.measure(holdings)
        finally:
            actor.lock.release()

    def op_migrate_out(self, name: str, segment: str, until: float | None = None) -> Snapshot:
        """Retire a paused module for its move: its state and unconsumed inputs, laid out
        in shared-memory segment ``segment`` (which its executor made and unlinks).

        Not past ``until`` (``time.monotonic()``), when its executor stops waiting and
        keeps the module here: one read late (this worker was frozen) is not retired; one
        whose retirement fails or ends late (its ``teardown`` overran) stays here, paused,
        and is set up again when the failed move lets it go (``op_resume``)."""
        started = time.perf_counter()
        if name not in self._paused:
            raise RuntimeError(f"module {name!r} must be paused before it migrates")
        if until is not None and time.monotonic() > until:
            raise TimeoutError(f"module {name!r} was not retired: its move had stopped "
                               "waiting (this worker was frozen); it stays here")
        actor = self.actors[name]
        captured = actor.retire()
        try:
            with _movable(name, captured["state"]):
                snapshot = Snapshot.capture(captured, segment, since=started)
            if until is not None and time.monotonic() > until:
                raise TimeoutError(f"module {name!r} was retired too late for its move "
                                   "(its teardown, or this worker, was slow): it stays here")
        except BaseException:
            actor.reinstate()
            self._set_up_on_resume.add(name)
            raise
        del self.actors[name]
        self._paused.discard(name)
        actor.lock.release()
        if actor.join(timeout=1.0):
            self.pool.submit(actor.let_go)      # (after the answer: not in the move's pause)
        self.restart_policy.pop(name, None)
        self._retime()
        return snapshot

    def op_migrate_in(self, name: str, snapshot: Snapshot) -> float:
        """Take over a module's state and unconsumed inputs (added, not yet started);
        the seconds it took."""
        started = time.perf_counter()
        self.actors[name].restore(snapshot.restore())
        return time.perf_counter() - started

    def op_remove(self, name: str) -> None:
        actor = self.actors.pop(name, None)
        if actor is None:       # failed in the process this one replaced: never made here
            return
        if actor.running or actor.torn_down:    # (stopped first: a close, a restart)
            if actor.stop(timeout=1.0):
                actor.let_go()      # (for good: its files closed now, not at some collection)
        else:
            actor.halt()        # (a start whose setup still runs does not run it after)
        self.restart_policy.pop(name, None)
        self._retime()

    def op_link_in(self, key: str, dst: str, dst_port: str, ring: str, policy: str) -> None:
        port = self.actors[dst].inputs[dst_port]
        port.set_policy(Policy.parse(policy))
        port.fed_by(key)
        shm_ring = ShmRing.attach(ring)
        shm_ring.resume_reader()   # a restarted reader continues where the last one stopped
        shm_ring.label = key       # a value it cannot decode is logged naming its link
        if shm_ring.lossless:
            port._on_room = self._room_made
            self.inbound[key] = LosslessInboundLink(shm_ring, port)
        else:
            self.inbound[key] = InboundLink(shm_ring, port)
        self._inbound_changed()

    def op_unlink_in(self, key: str) -> int:
        link = self.inbound.pop(key, None)
        if link is None:
            return 0
        link.port.unfed_by(key)
        self._inbound_changed()
        return link.close()

    def _inbound_changed(self) -> None:
        links = list(self.inbound.values())
        lossless = any(isinstance(link, LosslessInboundLink) for link in links)
        self._receiving = (links, [link.ring.core for link in links], lossless)
        self.bell_self()

    def _room_made(self) -> None:
        """A module read from a full lossless input: the receiver drains its ring again
        (woken, unless it is the receiver itself that read: it looks anyway)."""
        if threading.get_ident() != self._receiver_id:
            self.bell_self()

    def op_link_out(self, key: str, src: str, src_port: str, ring: str | None = None,
                    dst: str = "", dst_port: str = "", policy: str = "latest") -> None:
        if ring is None:                                 # both ends in this process
            self._link_out_memory(key, src, src_port, dst, dst_port, policy)
            return
        # The reader's doorbell follows this request on the pipe (SCM_RIGHTS): take it
        # before anything can fail, or the next request would read it as its own.
        pull = BellPull(reduction.recv_handle(self.conn))
        try:
            self._link_out_ring(key, src, src_port, ring, pull)
        except BaseException:
            pull.close()
            raise

    def _link_out_memory(self, key: str, src: str, src_port: str, dst: str, dst_port: str,
                         policy: str) -> None:
        port = self.actors[src].outputs[src_port]
        target = self.actors[dst].inputs[dst_port]
        parsed = Policy.parse(policy)
        target.set_policy(parsed)
        target.fed_by(key)
        if parsed.lossless:
            # The writer waits for room in the input itself (outside the reader's module
            # lock: the reader's read wakes it), as it would for room in a ring.
            counter = WaitCounter()

            def one_waiting(value: Any, timeout: float, target: InputPort = target) -> None:
                target.put([local_copy(value)], timeout, key, counter)

            def many_waiting(values: Sequence[Any], timeout: float,
                             target: InputPort = target) -> None:
                target.put([local_copy(v) for v in values], timeout, key, counter)
            port.connect(key, one_waiting, many_waiting, lossless=True, counter=counter)
        else:
            def one(value: Any, target: InputPort = target) -> None:
                target.deliver(local_copy(value), time.monotonic())

            def many(values: Sequence[Any], target: InputPort = target) -> None:
                target.deliver_many([local_copy(v) for v in values], time.monotonic())
            port.connect(key, one, many)
        self.outbound[key] = (src, src_port, None, None)

    def _link_out_ring(self, key: str, src: str, src_port: str, ring: str,
                       pull: BellPull) -> None:
        port = self.actors[src].outputs[src_port]
        shm_ring = ShmRing.attach(ring)
        shm_ring.resume_writer()   # a restarted writer gets back slots it never published
        shm_ring.set_bell(pull.fileno())
        shm_ring.label = key           # a lossless write that times out names its link
        port.connect(key, shm_ring.write, shm_ring.write_many, lossless=shm_ring.lossless,
                     counter=shm_ring)
        self.outbound[key] = (src, src_port, shm_ring, pull)

    def op_unlink_out(self, key: str) -> None:
        entry = self.outbound.pop(key, None)
        if entry is None:
            return
        src, src_port, ring, pull = entry
        if src in self.actors:
            self.actors[src].outputs[src_port].disconnect(key)
        if ring is None:                # in memory: the reader's input is in this worker
            for actor in self.actors.values():
                for port in actor.inputs.values():
                    port.unfed_by(key)
        else:
            ring.close()
        if pull is not None:
            pull.ring()      # the reader drains what is left
            pull.close()

    def op_publish_out(self, key: str, src: str, src_port: str, secret: bytes,
                       host: str, epoch: int = 0,
                       room: RingSize | None = None) -> tuple[str, str, bytes]:
        """Replicate an output to another node: (data address, control address,
        incarnation) for the reading node to follow."""
        return self.publications.add(key, f"{src}.{src_port}",
                                     self.actors[src].outputs[src_port], secret, host, epoch,
                                     room)

    def op_ready_to_publish(self, secret: bytes, host: str, epoch: int = 0) -> None:
        """Bind the sockets that replicate outputs to other nodes before they are needed."""
        self.publications.open(secret, host, epoch)

    def op_unpublish_out(self, key: str) -> tuple[int, bytes | None]:
        return self.publications.remove(key)

    def op_unacknowledged_out(self, key: str, reader: bytes) -> int:
        return self.publications.unacknowledged(key, reader)

    def op_forget(self, module: str) -> list[str]:
        """Drop cached copies of ``module``: the next load or swap gets the new code."""
        self.reloaded.add(module)
        return forget(module)

    def op_get_state(self, name: str, within: float = 10.0) -> dict[str, Any]:
        return self.actors[name].capture(within)

    def op_set_state(self, name: str, state: dict[str, Any], within: float = 10.0) -> None:
        try:
            self.actors[name].apply(state, within)
        # a name it lacks, a value of another kind, one its class refuses (state_problems)
        except (KeyError, TypeError, StateRefused) as exc:
            why = exc.args[0] if len(exc.args) == 1 else exc
            raise Refused(f"module {name!r}: {why}; nothing was set") from None

    def op_swap(self, name: str, cls: bytes, period: float | None
                ) -> tuple[list[str], list[str]]:
        module = _made(name, _load_class(cls))
        self._give_runtime(name, module)
        return self.actors[name].swap(module, period)

    def op_stats(self) -> dict[str, Any]:
        modules = {name: actor.statistics() for name, actor in self.actors.items()}
        if len(modules) == 1:             # everything this process does is for its module
            next(iter(modules.values()))["cpu"] = time.process_time()
        links = {key: link.ring.statistics() for key, link in self.inbound.items()}
        return {"pid": os.getpid(), "modules": modules, "rings": links}

    def _report_error(self, actor: ModuleActor, where: str, trace: str) -> None:
        """Tell the executor (which logs it) about an exception, at most once a second each."""
        reports = self._error_reports.get(actor.name)
        if reports is None:
            reports = self._error_reports[actor.name] = Throttle(ERROR_REPORT_S)
        suppressed = reports.let(time.monotonic())
        if suppressed is None:
            return
        self.send((None, "error", {"name": actor.name, "where": where, "trace": trace,
                                   "suppressed": suppressed}))

    # -- agents' requests to the executor ----------------------------------
    def _give_runtime(self, name: str, module: Any) -> None:
        if isinstance(module, Agent):
            module.__dict__["_pb3a_runtime"] = RuntimeClient(
                name, functools.partial(self.request, name))

    def request(self, agent: str, op: str, args: dict[str, Any],
                timeout: float | None = None) -> Any:
        """An agent's request to the runtime (a configuration change, a read); waits for
        the answer (the request's ``timeout`` and the way back), giving way meanwhile to
        requests that need the agent (``waits``)."""
        timeout = agent_wait(timeout)
        actor = self.actors[agent]
        req_id = next(self._request_ids)
        with actor.waiting(f"{agent}'s request {op!r}") as wait:
            self._requests[req_id] = wait
            try:
                # who asks, and whether from its setup: a change that waits for that
                # setup lets it read (``Operations``)
                asker = {"_asker": (agent, actor.in_setup)}
                sent = self.send((None, "request", {"id": req_id, "op": op,
                                                    "args": pickling.dumps({**args, **asker})}))
                try:
                    return wait.result(timeout)
                except RuntimeCancelled as cancelled:    # (the agent is being paused:
                    if sent is not None and self.outbox.withdraw(sent):  # moved, swapped)
                        raise RuntimeCancelled(f"{cancelled}; it was withdrawn and will "
                                               "not run") from None
                    # Read already, it waits for the configuration lock, which the change
                    # pausing this agent holds: once that ends it may run. (An agent that
                    # asked again at once made the change twice.)
                    raise RuntimeCancelled(f"{cancelled}; it had reached the runtime and may "
                                           "still be carried out once that change ends: "
                                           "see where things are before asking again") from None
                except RuntimeTimeout:
                    if sent is None or not self.outbox.withdraw(sent):
                        raise
                raise RuntimeTimeout(
                    f"the runtime read nothing of {wait.what} within {timeout:g} s, so it "
                    "was withdrawn and will not run: this module's executor reads nothing "
                    "from its workers (frozen, or starved of CPU)")
            finally:
                self._requests.pop(req_id, None)

    def _ask_period(self, name: str, answered: Callable[[bool, Any], None]) -> bool:
        """Ask the runtime's record to learn the period module ``name`` set itself
        (``PeriodTeller``), not waiting: ``answered`` is called with the answer. False if
        it could not be sent."""
        req_id = next(self._request_ids)

        def answer(ok: bool, result: Any) -> None:
            self._requests.pop(req_id, None)
            answered(ok, result)

        self._requests[req_id] = _Answered(answer)
        # (no asker: it asks for no change, and waits for one starting the module)
        if self.send((None, "request", {"id": req_id, "op": "learn_period",
                                        "args": pickling.dumps({"name": name})})) is None:
            self._requests.pop(req_id, None)
            return False
        return True

    def _answer(self, id: int, ok: bool, result: Any) -> None:
        wait = self._requests.get(id)
        if wait is not None:
            wait.answer(ok, result)

    # -- receiver ----------------------------------------------------------
    def bell_self(self) -> None:
        self._wake.ring()

    def _schedule(self, task: Callable[[], None]) -> None:
        """Run a module's event dispatch: inline on the receiver when it is alone here.

        A worker hosting a single module saves the hand-off to a pool thread (tens
        of microseconds after an idle period); with several modules the pool runs
        them in parallel, so one slow handler does not delay another's delivery.
        """
        if self._solo and threading.get_ident() == self._receiver_id:
            self._ready.append(task)
        else:
            self.pool.submit(task)

    def _run_ready(self) -> None:
        tasks, self._ready = self._ready, []
        for task in tasks:
            if task.__self__.lock.locked():      # type: ignore[attr-defined]
                self.pool.submit(task)           # busy stepping: do not block the receiver
            else:                                # (and if taken since, it ends: see there)
                task(inline=True)

    def _receive(self) -> None:
        # Drain every ring, run what became ready, then announce sleep and look once
        # more (the announcement and the look are the reader's half of the ring's
        # wake-up hand-shake) before sleeping on the doorbell.
        # A link whose drain fails is set aside for a while, out of the sleep too (its
        # data would wake the receiver at once); the others go on.
        gap = last = 0.0                   # time between the last two deliveries
        while not self._closing.is_set():
            try:
                links, cores, lossless = self._receiving
                count = 0
                aside = False
                for link in links:
                    if link.resume_at:
                        if time.monotonic() < link.resume_at:
                            aside = True
                            continue
                        link.resume_at = 0.0
                    try:
                        count += link.drain()
                    except Exception:
                        link.set_aside()
                        aside = True
                if count:
                    now = time.monotonic()
                    gap, last = now - last, now
                if self._ready:
                    self._run_ready()
                    if self._ready:               # a module has more to do: drain first
                        continue
                if lossless or aside:     # a full input's ring waits for a read
                    links = [link for link in links if not link.resume_at and link.wanted()]
                    cores = [link.ring.core for link in links]
                if gap < SPIN_S and self._spin(links):
                    continue
                sleep(self._bell_fd, cores, GUARD_TIMEOUT)
            except Exception:
                log.exception("receiver: unexpected error; going on")

    @staticmethod
    def _spin(links: list[InboundLink]) -> bool:
        """While values flow densely, poll briefly before sleeping: the next value is
        likely microseconds away, and sleeping would make its writer ring (a system
        call) and its reader wake (tens of microseconds). Sparse traffic never spins."""
        deadline = time.monotonic() + SPIN_S
        while time.monotonic() < deadline:
            if any(link.ring.has_data() for link in links):
                return True
            time.sleep(0)                         # let the process's other threads run
        return False

    def _checkpoint(self) -> None:
        """Every ``checkpoint_s``: the ``last-state`` modules' checkpoints, and how many
        notices were dropped, once the executor reads again (none may come to carry it)."""
        while not self._closing.wait(self._checkpoint_s):
            with contextlib.suppress(OSError):
                self._tell_dropped()
            for name, policy in list(self.restart_policy.items()):
                actor = self.actors.get(name)
                if policy == "last-state" and actor is not None and actor.running:
                    try:
                        blob = actor.checkpoint()
                    except Exception as exc:
                        # (said once, not with a traceback at every checkpoint; and never
                        # the end of this thread, which checkpoints the others too)
                        if name not in self._uncheckpointed:
                            self._uncheckpointed.add(name)
                            log.error("cannot checkpoint module %r; a restart starts it from "
                                      "its last checkpoint, or fresh: %s", name,
                                      exc if isinstance(exc, pickling.Unpicklable)
                                      else f"{type(exc).__name__}: {exc}")
                        continue
                    self._uncheckpointed.discard(name)
                    self.send((None, "checkpoint", {"name": name, "state": blob}))


class _Answered:
    """A request whose answer no one waits for: ``answer`` calls back."""

    def __init__(self, answer: Callable[[bool, Any], None]) -> None:
        self.answer = answer


def agent_wait(timeout: float | None) -> float:
    """How long an agent's request is waited for, given its own ``timeout`` (None: the
    system's default, within ``AGENT_REQUEST_TIMEOUT``)."""
    return AGENT_REQUEST_TIMEOUT if timeout is None else timeout + RUNTIME_WAY_BACK_S


def _load_class(cls: bytes) -> type:
    """A module's class, sent by reference or by value. One whose module cannot be
    imported while a module server of this process does not answer, or refuses, names
    that server, as ``resolve_class`` does (the error said only which module was not
    found)."""
    try:
        return cloudpickle.loads(cls)
    except ImportError as exc:
        trouble = served.server_trouble()
        if not trouble:
            raise
        raise type(exc)(f"{exc}{trouble}", name=exc.name) from exc


def _made(name: str, cls: type) -> Any:
    """An instance of module ``name``'s class, made with no arguments as every module is;
    ``Refused`` naming the module, its class and that step if that raises (the error
    named only the worker: "worker 'local-p0': TypeError: ... missing 1 required
    positional argument")."""
    try:
        return cls()
    except Exception as exc:
        raise Refused(f"module {name!r}: making its class {class_ref(cls)} with no arguments "
                      f"failed: {type(exc).__name__}: {exc}") from None


@contextlib.contextmanager
def _movable(name: str, state: dict[str, Any]) -> Iterator[None]:
    """Pickling module ``name``'s ``state`` for a move: one that cannot be is ``Refused``
    naming its fields (pickle's error named only the type: "cannot pickle
    '_thread.lock' object")."""
    try:
        yield
    except pickling.PICKLING_ERRORS as exc:
        raise Refused(f"module {name!r} cannot move: its state cannot be pickled: "
                      + pickling.unpicklable_reason(exc, state)) from None


def _as_held(module: Any, state: dict[str, Any]) -> dict[str, Any]:
    """A configuration's ``state`` made the types of what the new ``module`` holds
    (``configured``): a file's list for an array field an array of its dtype, a list for
    a tuple one, a whole number for a float one a float (``self.weights += 1`` failed
    on the list). What does not fit is set as it is: the check has named it."""
    made = {}
    for key, value in state.items():
        try:
            made[key] = configured(key, getattr(module, key, None), value)
        except (TypeError, ValueError):
            made[key] = value
    return made


class _Terminated(BaseException):
    """SIGTERM arrived: stop the modules and exit cleanly. Not an ``Exception``: a
    request running on the control thread (a module's ``__init__`` in ``add``) must
    not catch it as its own failure and serve on."""


def _on_sigterm(signum: int, frame: object) -> None:
    raise _Terminated


def worker_main(conn: Any, key: str, checkpoint_s: float, level: int,
                cpus: list[int] | None = None, code: CodeSources | None = None,
                leased: bool = False) -> None:
    """Entry point of a worker process.

    Ctrl-C in a terminal reaches every process of the group, and so does a SIGHUP when
    the terminal closes: workers ignore both and let their launcher stop them in order.
    SIGTERM stops the worker's modules and exits with status 0, which the executor takes
    as a stop, not a crash. A ``leased`` worker (a remote node's) is sent its node's
    ``LeaseBoard`` right after its doorbell.
    """
    mark_as("a worker")
    if cpus:
        os.sched_setaffinity(0, cpus)           # before any thread: they all inherit it
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)          # (the terminal closed: the same)
    signal.signal(signal.SIGTERM, _on_sigterm)
    try:        # signalled as it starts (a SIGTERM to the whole group): nothing to stop
        forward = LogForwarder(level, running_module)
        logging.getLogger().addHandler(forward)
        logging.getLogger().setLevel(level)
        bell = reduction.recv_handle(conn)      # the executor sends our doorbell first
        board = LeaseBoard.opened(reduction.recv_handle(conn)) if leased else None
        (code or CodeSources()).install()
        worker = Worker(conn, key, bell, checkpoint_s, board)
    except (_Terminated, EOFError):             # (EOF: the executor went as it started us,
        return                                  # a Ctrl-C then) exit 0: a stop, not a crash
    try:
        forward.send = worker.send
        worker.serve()
    except _Terminated:
        worker.shutdown()
        if worker.lease.lapsed:
            sys.exit(LEASE_LAPSED)
