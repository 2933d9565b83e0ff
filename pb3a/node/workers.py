"""``WorkerPool``: the worker processes of one node and the requests sent to them.

Workers start from a forkserver with numpy, cloudpickle and the worker code
preloaded. A pool keeps a few of them booted and idle (``WorkerSettings.spares``): a
module that arrives (a migration, an add) takes one over instead of waiting for a
process to start, which is most of a move's preparation. Each worker has a private
pipe: requests carry an id and wait on a future with a deadline. One monitor thread
reads every pipe and every process sentinel; neither it nor a sender ever waits for a
worker that reads or writes nothing (``transport.pipe``); a worker's notices (checkpoints,
errors, agents' requests) go to ``on_notice``, its death, after every request
waiting on it has failed, to ``on_death``.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import multiprocessing
import multiprocessing.connection
import os
import pickle
import socket
import threading
import time
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass, field
from multiprocessing import forkserver, reduction
from typing import TYPE_CHECKING, Any

import cloudpickle

from pb3a.config.description import DEFAULT_SPARES
from pb3a.deadline import capped, left, spoken
from pb3a.errors import RuntimeFailure, RuntimeTimeout
from pb3a.loading.references import file_of
from pb3a.loading.served import reload_problem
from pb3a.loading.sources import CodeSources
from pb3a.node import forkserver_owner
from pb3a.node.watched_process import STATUS_WAIT_S, WatchedProcess
from pb3a.processes import start_resource_tracker, start_without_main, terminal_signals_held
from pb3a.transport import pickling
from pb3a.transport.doorbell import new_bell
from pb3a.transport.pipe import Inbox, Outbox, Outgoing
from pb3a.worker.process import REFUSED, TIMED_OUT, worker_main

if TYPE_CHECKING:
    from collections.abc import Callable

    from pb3a.worker.lease import LeaseBoard

log = logging.getLogger("pb3a.executor")

REQUEST_TIMEOUT = 10.0
# A stopping worker told to exit that has not is sent SIGTERM (its modules' teardowns
# run on it) and waited for this long, then SIGKILLed and waited for this long (a
# bound only). A pool's close that has run out of time gives it EXIT_AT_LEAST_S to
# exit when told, no time on SIGTERM (a frozen worker ignores it), then SIGKILL.
TERMINATE_WAIT_S = 1.0
KILL_WAIT_S = 1.0
EXIT_AT_LEAST_S = 0.1
# A wait shorter than this, what was left of a caller's time, says only that: a worker
# that had not answered within it is not taken for stuck.
HURRIED_S = 0.1
_UNREADABLE = (None, None)      # the head of a message that could not be read
# What a request that goes unanswered waits for, where that is not any body: a stop
# stuck in a teardown was said to be stuck in "step, on_input, setup"
_STUCK_IN = {"stop": "its teardown, or the step or on_input the stop waits for",
             "start": "its setup", "swap": "the new class's setup, or the old one's teardown"}

_context = multiprocessing.get_context("forkserver")
# A worker's start waits this long for the forkserver (its first start includes the
# forkserver's own, with the preload): one frozen (stopped, hung) fails the start
# instead of holding it, and the lock of the change that asked, for good.
SPAWN_TIMEOUT_S = 30.0
# numpy imports numpy.random only when first used: 25-30 ms in a fresh worker, which
# fell inside a migration's pause when a module made a generator in its ``setup``
PRELOAD = ("pb3a.node.forkserver_signals", "pb3a.worker.process", "numpy", "numpy.random",
           "cloudpickle")
# Imported last: the preload is done (``pb3a.node.forkserver_signals``).
PRELOADED = "pb3a.node.forkserver_preloaded"


def _start_forkserver_child(process: Any, stopping: threading.Event | None = None) -> None:
    """Start ``process`` from the forkserver. One that ends as it starts, before it
    answers, most likely died preloading a module of the configuration that raises when
    imported (its traceback is on stderr): the start is tried again from a forkserver
    without those, and the worker's own import of the module then fails the module's
    start with the module's error. Not once ``stopping`` is set: the pool's close
    stopped a forkserver still preloading (``WorkerPool.close``)."""
    for attempt in range(_FORKSERVER_ATTEMPTS):
        if attempt:
            # multiprocessing starts a new forkserver only once the last has exited
            # (``waitpid``), which comes a moment after it closed its end: tried at
            # once, every retry met the dying one again
            time.sleep(_FORKSERVER_BACKOFF_S * 2 ** (attempt - 1))
        try:
            _start_forkserver()
            start_without_main(process, timeout=SPAWN_TIMEOUT_S)
            forkserver_owner.answered()
            return
        except (EOFError, ConnectionError):
            if stopping is not None and stopping.is_set():
                raise RuntimeFailure("no worker was started: the node is shutting "
                                     "down") from None
        except RuntimeTimeout as exc:
            _stop_a_hung_preload(exc)
            raise
        # Every start that met a dying forkserver tries again, whichever saw it first: a
        # module's and a spare's start met the same one, and the second found the
        # preload dropped by the first and failed. And more than once: a start made
        # before the drop may have started another forkserver with the preload, which
        # dies as the first did, and the retry met that one.
        with _preload_lock:
            if _preloading_configuration.is_set():
                log.warning("the forkserver ended as it preloaded the configuration's "
                            "modules (one raised as it was imported? see above); workers "
                            "import them themselves from now on")
                _preload(())
    raise RuntimeFailure("the forkserver that starts this node's workers ended as it "
                         f"started, {_FORKSERVER_ATTEMPTS} times; its error, if it had one, "
                         "is on stderr")


def _start_forkserver() -> None:
    """Start the forkserver, if none runs, with the terminal's signals held off until
    ``pb3a.node.forkserver_signals`` ignores them: a Ctrl-C to the process group as its
    interpreter started (``pb3a run``'s first second) killed it, a crash dump ("Fatal
    Python error: init_import_site") or a traceback on the terminal."""
    global _preloaded_files
    start_resource_tracker()                  # (first: its start takes them back here)
    with _preload_lock:
        configuration = _configuration_preload
    # (read before it may start: one edited as it starts is imported anew by workers)
    files = {module: file_of(module) for module in configuration}
    with terminal_signals_held():
        forkserver.ensure_running()
    pid = forkserver_owner.running()
    with _preload_lock:
        if pid is not None and _preloaded_files[0] != pid:
            _preloaded_files = (pid, files)


def stale_preload() -> tuple[str, ...]:
    """The configuration's modules that this process's forkserver preloaded and whose
    files have changed since (their path, mtime or size; ``references.file_of``), those
    that may be reloaded (``served.reload_problem``): a worker it forks holds them as
    they were, and a later launch in this process (a notebook, a sweep) ran the code
    from before the edit. Empty if the forkserver running was not started here."""
    with _preload_lock:
        pid, files = _preloaded_files
    if pid is None or pid != forkserver_owner.running():
        return ()
    return tuple(module for module, file in files.items()
                 if file_of(module) != file and reload_problem(module) is None)


def _stop_a_hung_preload(timeout: RuntimeTimeout) -> None:
    """A start got no answer: if the forkserver has answered none yet, it is stuck in
    its preload (a module file that hangs as it is imported, most likely), and every
    later start would wait for it too. It is stopped, and the next one preloads none
    of the configuration's modules (a worker then imports its module itself, and its
    start fails as that import does); ``timeout`` says so."""
    with _preload_lock:
        pid = forkserver_owner.running()
        preload = ", ".join(
            name for name in (forkserver_owner.preload_of(pid) if pid is not None else ())
            if name not in (*PRELOAD, PRELOADED)
            and not name.startswith(forkserver_owner.OWNER_MARK)) or "PB3A's own"
        if forkserver_owner.stop_if_preloading() is None:
            return
        _preload(())
    log.warning("the forkserver (pid %s) had not finished importing its preload (%s) "
                "%g s after a start asked it for a worker; it was stopped, and workers "
                "import the configuration's modules themselves from now on",
                pid, preload, SPAWN_TIMEOUT_S)
    timeout.args = (f"{timeout}; it had not finished importing the modules it preloads "
                    f"({preload}): one of them hangs as it is imported? It was stopped, "
                    "and workers import them themselves from now on",)


# How often a worker's start is tried when the forkserver ends as it starts (each
# forkserver started before the preload was dropped may die of it once), the first
# retry after a pause of this, each later one after twice the last.
_FORKSERVER_ATTEMPTS = 4
_FORKSERVER_BACKOFF_S = 0.05


# Set while the forkserver (the next to start, if none runs) preloads a configuration's
# modules: one process has one forkserver, whichever pool set it.
_preloading_configuration = threading.Event()
_preload_lock = threading.Lock()
_preload_chosen_by: int | None = None      # the process that last chose it
_configuration_preload: tuple[str, ...] = ()     # the configuration's modules in it
# The forkserver started here last (its pid) and the files of the configuration's modules
# it preloads as they were when it started (``stale_preload``).
_preloaded_files: tuple[int | None, dict[str, tuple[str, int, int] | None]] = (None, {})


def _preload(configuration: tuple[str, ...]) -> None:
    """What the next forkserver to start imports: PB3A's worker code, and ``configuration``
    (between them, the entry that names this process as its owner; last, the one that
    says it is done: ``pb3a.node.forkserver_signals``)."""
    global _preload_chosen_by, _configuration_preload
    _context.set_forkserver_preload([*PRELOAD, forkserver_owner.owner_mark(),
                                     *configuration, PRELOADED])
    _configuration_preload = configuration
    _preload_chosen_by = os.getpid()
    if configuration:
        _preloading_configuration.set()
    else:
        _preloading_configuration.clear()


def forkserver_context() -> multiprocessing.context.ForkServerContext:
    """The context that starts PB3A's other processes (``CPULoad``'s burners) from this
    process's one forkserver, which is then the workers' kind whoever starts it first:
    started by a burner as multiprocessing's plain one, it watched no owner, neither for
    the workers started from it later nor for its socket in /tmp."""
    with _preload_lock:
        if _preload_chosen_by != os.getpid():
            _preload(())
    _start_forkserver()          # (started by a process's start, it took no care of signals)
    return _context


@dataclass(eq=False)
class WorkerHandle:
    """One worker process: its pipe, its doorbell, the modules it hosts."""

    key: str
    node: str
    bell: int = field(default_factory=new_bell)    # the worker's doorbell (an eventfd)
    process: WatchedProcess | None = None
    conn: Any = None                       # the pipe (the two ends below are ours)
    outbox: Outbox | None = None
    inbox: Inbox | None = None
    head: tuple[int | None, Any] | None = None    # a message whose payload is to come
    modules: list[str] = field(default_factory=list)
    alive: bool = False
    pid: int = 0
    # what the worker's modules had done when it stopped (its stats), told as it stopped
    last_figures: dict[str, Any] | None = None
    # its last answer to a report (its stats), shown while it does not answer (frozen)
    last_answer: dict[str, Any] | None = None
    # held to read the pipe and to close it: a worker stopped by another thread must
    # not have its pipe closed under the monitor reading it
    read_lock: threading.RLock = field(default_factory=threading.RLock)

    @property
    def serving(self) -> bool:
        """Whether the worker takes requests: it runs, and has not begun to stop (one
        that did, on a SIGTERM, has told its last figures and reads no more)."""
        return self.alive and self.last_figures is None

    def send(self, req_id: int | None, op: str, args: Any,
             fd: int | None = None) -> Outgoing:
        """Send a request (or, with ``req_id`` None, an answer to one of the worker's)
        through its outbox, never waiting: its head, its arguments pickled on their own,
        then a descriptor if given. The arguments go by cloudpickle, so a class the
        launcher's own script defines travels by value, and one the worker cannot read
        fails only its request. A ``TypeError`` or ``PicklingError`` says they cannot be
        pickled, an ``OSError`` that the pipe is closed: nothing went."""
        return self.send_pickled(req_id, op, pickling.dumps(args), fd)

    def send_pickled(self, req_id: int | None, op: str, body: bytes,
                     fd: int | None = None) -> Outgoing:
        """``send`` with the arguments pickled already (``body``); an ``OSError`` says the
        pipe is closed: nothing went."""
        return self.outbox.put([pickle.dumps((req_id, op, fd is not None)), body], fd)

    def close_pipe(self) -> None:
        """Close both ends of ours (the worker then reads the end of its pipe)."""
        with self.read_lock:
            for end in (self.outbox, self.inbox, self.conn):
                if end is not None:
                    with contextlib.suppress(OSError):
                        end.close()


@dataclass(frozen=True)
class WorkerRequest:
    """One request to a worker, to be sent beside others (``WorkerPool.side_by_side``)."""

    worker: str
    op: str
    args: dict[str, Any]
    fd: int | None = None             # a descriptor sent right behind it


@dataclass
class WorkerSettings:
    """What every worker of a node is started with."""

    cpus: list[int] | None = None          # the CPUs the node's workers run on (None: all)
    checkpoint_s: float = 1.0              # how often ``last-state`` modules checkpoint
    log_level: int = logging.WARNING
    code: CodeSources = field(default_factory=CodeSources)    # where workers import from
    spares: int = DEFAULT_SPARES           # booted idle workers kept for modules that arrive
    # where a remote node's executor writes its lease's end for its workers (an embedded
    # node's have none: they never lapse)
    lease: LeaseBoard | None = None


class WorkerPool:
    """Starts, calls, watches and stops one node's worker processes; thread-safe."""

    def __init__(self, settings: WorkerSettings,
                 on_notice: Callable[[WorkerHandle, str, dict[str, Any]], None],
                 on_death: Callable[[WorkerHandle], None]) -> None:
        self.settings = settings
        self.handles: dict[str, WorkerHandle] = {}
        self._on_notice, self._on_death = on_notice, on_death
        self._futures: dict[int, Future[Any]] = {}
        self._ids = itertools.count()
        self._stopping = threading.Event()
        self._spares: list[WorkerHandle] = []      # booted, hosting nothing, not in handles
        self._spares_lock = threading.Lock()
        self._booting: threading.Thread | None = None      # booting spares
        # stopping workers (retire, no wait), each with the thread that stops it
        self._retiring: list[tuple[threading.Thread, WorkerHandle]] = []
        # requests a spare is sent as it boots (its replicator opened, say): (op, args)
        self.spare_requests: list[tuple[str, dict[str, Any]]] = []
        # processes stopped by other threads, whose descriptors the monitor closes between
        # two of its waits (one it may be polling is not closed under it); those not
        # ended yet, or whose exit status has not come yet, are kept for its next round
        self._to_close: list[WatchedProcess] = []
        self._to_close_lock = threading.Lock()
        self._wake_r, self._wake_w = socket.socketpair()
        self._monitor = threading.Thread(target=self._watch, name="pb3a-monitor", daemon=True)
        self._monitor.start()

    def warm(self) -> None:
        """Start the forkserver now, in the background, with the configuration's modules
        imported (``settings.code.preload``): a node that has no modules yet (one that
        modules will move to) would otherwise pay for it in the first migration's
        critical path. One forkserver serves a process: the first pool to start it
        chooses what it preloads; a module that cannot be imported there, such as
        served code, is skipped. Then the spares boot (again: the settings changed)."""
        _preload(self.settings.code.preload)
        with self._spares_lock:              # booted with the settings before these
            stale, self._spares = self._spares, []
        for handle in stale:
            self._stop(handle, 1.0)
        self._replenish_with(_start_forkserver)

    def spare_pids(self) -> list[int]:
        """The process ids of the spare workers booted now."""
        with self._spares_lock:
            return [handle.pid for handle in self._spares if handle.alive]

    def __getitem__(self, key: str) -> WorkerHandle:
        return self.handles[key]

    # -- processes -----------------------------------------------------------
    def spawn(self, handle: WorkerHandle) -> None:
        """Start (or restart) the worker process behind ``handle``."""
        settings = self.settings
        parent, child = _context.Pipe()
        process = _context.Process(
            target=worker_main, name=f"pb3a-worker-{handle.key}", daemon=True,
            args=(child, handle.key, settings.checkpoint_s, settings.log_level,
                  settings.cpus, settings.code, settings.lease is not None))
        try:
            _start_forkserver_child(process, self._stopping)
        except BaseException:
            parent.close()
            child.close()
            raise
        child.close()
        try:
            watched = WatchedProcess(process)
        except ProcessLookupError:
            parent.close()
            process.join(STATUS_WAIT_S)
            code = process.exitcode
            if code is not None:                 # (its status pipe, else the collector's)
                process.close()
            raise RuntimeFailure(f"worker {handle.key!r} ended as it started (exit code "
                                 f"{code})") from None
        # The doorbell is the worker's first read (then its lease's board, if it has one):
        # sent before anyone can send a request.
        try:
            reduction.send_handle(parent, handle.bell, process.pid)
            if settings.lease is not None:
                reduction.send_handle(parent, settings.lease.fd, process.pid)
            outbox = Outbox(parent.fileno(), ends_on_break=True)
            inbox = Inbox(parent.fileno())
        except OSError:
            parent.close()
            watched.kill()
            watched.join(STATUS_WAIT_S)
            watched.close()                      # (the monitor never saw it)
            raise
        # its ends before ``alive``: the monitor reads every live handle's inbox
        handle.process, handle.conn, handle.pid = watched, parent, process.pid
        handle.outbox, handle.inbox, handle.head = outbox, inbox, None
        handle.alive = True
        handle.last_figures = handle.last_answer = None
        self._poke()

    def ensure(self, key: str, node: str) -> WorkerHandle:
        """The worker ``key``, started if it does not exist yet (not once the pool is
        stopping: a change that goes on without the lock of a shutdown starts none)."""
        handle = self.handles.get(key)
        if handle is not None and not handle.alive and not self._stopping.is_set():
            self.spawn(handle)          # its modules died with it, none restarted
        if handle is None:
            if self._stopping.is_set():
                raise RuntimeFailure(f"node {node} is shutting down: no worker is started")
            with self._spares_lock:    # (one that died unseen yet, or stops, is skipped)
                while self._spares and not (self._spares[0].serving
                                            and self._spares[0].process.is_alive()):
                    self._spares.pop(0)
                spare = self._spares.pop(0) if self._spares else None
            if spare is not None:                # booted already: only its name changes
                spare.key, spare.node = key, node
                self.handles[key] = spare
                return spare
            handle = self.handles[key] = WorkerHandle(key, node)
            self.spawn(handle)
        return handle

    def replenish(self) -> None:
        """Boot spare workers until there are ``settings.spares`` again, in the background:
        call it once the modules that took spares have started, so that the new ones
        boot after a move's pause, not during it (their start takes CPU)."""
        with self._spares_lock:
            if len(self._spares) >= self.settings.spares:
                return
        self._replenish_with(lambda: None)

    def _replenish_with(self, first: Callable[[], object]) -> None:
        """``first()``, then spares booted, on one thread at a time (``close`` joins it)."""
        with self._spares_lock:
            if self._stopping.is_set() or (self._booting and self._booting.is_alive()):
                return
            self._booting = threading.Thread(target=self._replenish, args=(first,),
                                             name="pb3a-spares", daemon=True)
            self._booting.start()

    def _replenish(self, first: Callable[[], object]) -> None:
        try:
            first()
        except (OSError, RuntimeError, EOFError) as exc:   # (EOF: it was interrupted as
            if not self._stopping.is_set():                   # it started; or the close
                log.warning("the worker forkserver did not start: %s", exc)   # stopped it)
            return
        while not self._stopping.is_set():
            with self._spares_lock:
                if len(self._spares) >= self.settings.spares:
                    return
            handle = WorkerHandle("spare", "")
            try:
                self.spawn(handle)
            except (OSError, RuntimeError, EOFError) as exc:   # (one that arrives starts its own)
                if not self._stopping.is_set():    # (the close stopped its forkserver: said)
                    log.warning("no spare worker booted: %s", exc)
                return
            for op, args in self.spare_requests:
                self._submit(handle, op, None, args)     # (answered before any other)
            with self._spares_lock:
                if not self._stopping.is_set():
                    self._spares.append(handle)
                    continue
            self._stop(handle, 1.0)              # the pool closed meanwhile
            return

    def retire(self, key: str, timeout: float = 2.0, *, wait: bool = True) -> None:
        """Stop worker ``key`` and forget it. With ``wait=False`` it is told to stop and
        joined on another thread (``close`` waits for that): for a worker a move left
        empty, whose exit need not hold up the move's end."""
        handle = self.handles.pop(key)
        if wait:
            self._stop(handle, timeout)
            return
        stopping = threading.Thread(target=self._stop, args=(handle, timeout),
                                    name="pb3a-retire", daemon=True)
        self._retiring = [(thread, retired) for thread, retired in self._retiring
                          if thread.is_alive()]
        self._retiring.append((stopping, handle))
        stopping.start()

    # -- requests ------------------------------------------------------------
    def call(self, key: str, op: str, timeout: float = REQUEST_TIMEOUT, /,
             _fd: int | None = None, **args: Any) -> Any:
        """Send one request to a worker (a descriptor right behind it if given) and wait
        for its answer."""
        return self.result(self.submit(key, op, _fd=_fd, **args), op, key, timeout)

    def submit(self, key: str, op: str, /, _fd: int | None = None, **args: Any) -> Future[Any]:
        """Send one request to a worker; the future holds its answer."""
        return self._submit(self.handles[key], op, _fd, args)

    def submit_to(self, handle: WorkerHandle, op: str, /, **args: Any) -> Future[Any]:
        """``submit`` to a worker by the handle the caller took, which the pool may have
        dropped since (then the future fails: it is not running)."""
        return self._submit(handle, op, None, args)

    def _submit(self, handle: WorkerHandle, op: str, fd: int | None,
                args: dict[str, Any]) -> Future[Any]:
        future: Future[Any] = Future()
        if not handle.serving:
            future.set_exception(RuntimeFailure(f"worker {handle.key!r} is not running"))
            return future
        try:
            body = pickling.dumps(args)
        except Exception as exc:                 # not picklable: nothing is sent
            future.set_exception(RuntimeFailure(
                f"{op!r} for worker {handle.key!r}: its arguments cannot be pickled: "
                f"{type(exc).__name__}: {exc}"))
            return future
        req_id = next(self._ids)
        self._futures[req_id] = future
        future.pb3a_worker = handle   # type: ignore[attr-defined]
        future.pb3a_request = req_id   # type: ignore[attr-defined]
        future.pb3a_op = op   # type: ignore[attr-defined]
        try:
            future.pb3a_outgoing = handle.send_pickled(  # type: ignore[attr-defined]
                req_id, op, body, fd)
        except OSError as exc:
            # Its pipe broken, the worker is ending: the monitor fails the request once it
            # sees it end, having read what it said before (its last figures answer a
            # report's request: ``answer_waiting``; failed here, a report made as the
            # worker stopped showed it silent). Unless the monitor saw that already.
            # Whoever pops a future completes it.
            if not handle.alive and self._futures.pop(req_id, None) is not None:
                future.set_exception(RuntimeFailure(f"worker {handle.key!r} is gone: {exc}"))
        return future

    def side_by_side(self, requests: list[WorkerRequest | None]) -> list[Any]:
        """Send every request (None: nothing to do), then wait for every answer, all
        within one ``REQUEST_TIMEOUT`` (or the deadline of the call in progress); the
        answers in order (None for None), or the first error once all have answered or
        the time is up. A worker takes its requests in order."""
        sent = [None if request is None else
                (request, self.submit(request.worker, request.op, _fd=request.fd,
                                      **request.args))
                for request in requests]
        deadline = time.monotonic() + capped(REQUEST_TIMEOUT)
        answers: list[Any] = []
        failure: BaseException | None = None
        for pending in sent:
            answers.append(None)
            if pending is None:
                continue
            request, future = pending
            try:
                answers[-1] = self.result(future, request.op, request.worker,
                                          max(0.0, deadline - time.monotonic()))
            except (RuntimeFailure, RuntimeTimeout) as exc:
                failure = failure or exc
        if failure is not None:
            raise failure
        return answers

    def result(self, future: Future[Any], op: str, key: str, timeout: float) -> Any:
        """The answer ``future`` holds within ``timeout``, else ``RuntimeTimeout``."""
        try:
            return future.result(timeout)
        except FutureTimeout:
            # the answer itself may be a RuntimeTimeout, which is a TimeoutError as
            # concurrent.futures' is; or it came just after the wait ran out
            if future.done():
                return future.result()
        handle: WorkerHandle = future.pb3a_worker   # type: ignore[attr-defined]
        outgoing = getattr(future, "pb3a_outgoing", None)
        if outgoing is not None and handle.outbox.withdraw(outgoing):
            self._futures.pop(future.pb3a_request, None)   # type: ignore[attr-defined]
            future.cancel()                     # (done: no answer will ever come)
            raise RuntimeTimeout(
                f"worker {key!r} read nothing of {op!r} within {spoken(timeout)} s, so it was "
                "withdrawn and will not run: the worker reads nothing from its pipe "
                "(stopped, starved, or stuck in a call), or not fast enough for what "
                "was sent before; its log and `pb3a status` may say which")
        if future.done():                        # (it died meanwhile, say)
            return future.result()
        if timeout < HURRIED_S and left() is not None:
            # (all the caller's time left: a worker not done in milliseconds is not stuck)
            raise RuntimeTimeout(f"worker {key!r} had not answered {op!r} in the "
                                 f"{spoken(timeout)} s left of the call's time")
        raise RuntimeTimeout(
            f"worker {key!r} did not answer {op!r} within {spoken(timeout)} s: a module there "
            f"is stuck in a long call ({_STUCK_IN.get(op, 'step, on_input, setup')}), or its "
            "machine is overloaded; its log and `pb3a status` may say which")

    # -- the monitor -----------------------------------------------------------
    def _poke(self) -> None:
        with contextlib.suppress(OSError):
            self._wake_w.send(b"\x01")

    def _watch(self) -> None:
        while not self._stopping.is_set():
            try:
                self._watch_once()
            except Exception:               # the node's only reader and watcher: never die
                log.exception("worker monitor: unexpected error; going on")

    def _watch_once(self) -> None:
        """Close the processes stopped meanwhile, read every worker's pipe that has
        something, and see every death."""
        self._close_stopped()
        handles = [h for h in [*self.handles.values(), *self._spares] if h.alive]
        by_conn = {h.conn: h for h in handles}
        by_sentinel = {h.process.sentinel: h for h in handles}
        ready = multiprocessing.connection.wait(
            [self._wake_r, *by_conn, *by_sentinel], timeout=1.0)
        for item in ready:
            if item is self._wake_r:
                with contextlib.suppress(BlockingIOError):
                    self._wake_r.recv(4096)
            elif item in by_conn:
                self._read(by_conn[item])
        for item in ready:
            if item in by_sentinel and by_sentinel[item].alive:
                self._read(by_sentinel[item])      # replies sent before it died
                self._died(by_sentinel[item])

    def _read(self, handle: WorkerHandle) -> None:
        with handle.read_lock:
            if not handle.conn.closed:
                self._read_open(handle)

    def _read_open(self, handle: WorkerHandle) -> None:
        try:
            messages = handle.inbox.read()
        except (EOFError, OSError):
            return                                     # it died: the sentinel reports it
        for message in messages:
            try:
                self._take(handle, message)
            except Exception:          # (one that raises must not lose those after it)
                log.exception("worker %s: a message from it could not be taken", handle.key)

    def _take(self, handle: WorkerHandle, message: bytes) -> None:
        """One message from ``handle``'s worker: a head, or the payload of the last."""
        if handle.head is None:
            handle.head = _UNREADABLE      # (if it cannot be read, its payload still comes)
            handle.head = pickle.loads(message)
            return
        head, handle.head = handle.head, None
        if head is _UNREADABLE:
            return
        req_id, ok = head
        try:
            result = cloudpickle.loads(message)
        except Exception as exc:                       # fails its request, not the pipe
            if req_id is None:
                log.error("worker %s: a %s notice could not be read here: %s: %s",
                          handle.key, ok, type(exc).__name__, exc)
                return
            ok, result = False, ("its answer could not be read here: "
                                 f"{type(exc).__name__}: {exc}")
        if req_id is None:
            self._on_notice(handle, ok, result)
            return
        future = self._futures.pop(req_id, None)
        if future is None:
            return
        if ok is True:
            future.set_result(result)
        elif ok == TIMED_OUT:                          # the caller may try again
            future.set_exception(RuntimeTimeout(f"worker {handle.key!r}: {result}"))
        elif ok == REFUSED:                            # the caller's to mend, as said
            future.set_exception(RuntimeFailure(result))
        else:
            future.set_exception(RuntimeFailure(f"worker {handle.key!r}: {result}"))

    def _close_stopped(self, until: float | None = None) -> None:
        """Close the descriptors of the processes stopped by other threads (``_end``),
        those that have ended (``WatchedProcess.close``); on the monitor's thread,
        between its waits, or once it has ended. Their exit status is not waited for
        (the next round looks again), or, with ``until`` (monotonic), until then but
        ``EXIT_AT_LEAST_S`` at least, each (a frozen forkserver sends none)."""
        with self._to_close_lock:
            stopped, self._to_close = self._to_close, []
        left = [process for process in stopped if not process.close(
            0.0 if until is None else
            min(STATUS_WAIT_S, max(EXIT_AT_LEAST_S, until - time.monotonic())))]
        if left:
            with self._to_close_lock:
                self._to_close.extend(left)

    def _died(self, handle: WorkerHandle) -> None:
        handle.alive = False
        # (seen ended: what it says is kept; its status, if it has not come yet, is read
        # by whoever needs it, not waited for here, and its pipe closed in a later round)
        if not handle.process.close(0.0):
            self._hand_to_monitor(handle.process)
        handle.close_pipe()
        self._fail_requests(handle, "died")
        if self.handles.get(handle.key) is not handle:     # a spare: it hosted nothing
            with self._spares_lock:
                self._spares = [spare for spare in self._spares if spare is not handle]
            return
        if not self._stopping.is_set():
            self._on_death(handle)

    # -- stopping --------------------------------------------------------------
    def halt(self, handle: WorkerHandle, timeout: float = 2.0) -> None:
        """Stop the process behind ``handle`` (a restart that failed), not as a crash: the
        handle stays, with its doorbell and its modules, failed, until they are removed
        (``retire``)."""
        handle.alive = False
        self._end(handle, timeout)

    def kill(self, key: str) -> None:
        """SIGKILL worker ``key`` now (a worker whose module did not answer its stop,
        removed with ``force``), not as a crash: no restart follows. Its end is waited
        for ``KILL_WAIT_S`` (a bound only); the handle stays, with its modules, until
        they are removed (``retire``)."""
        handle = self.handles[key]
        handle.alive = False                # (the monitor takes its end for no death)
        if handle.process is not None:
            handle.process.kill()
            handle.process.join(KILL_WAIT_S)
            self._hand_to_monitor(handle.process)
        handle.close_pipe()
        self._fail_requests(handle, "was killed")
        self._poke()

    def _stop(self, handle: WorkerHandle, timeout: float, until: float | None = None) -> None:
        handle.alive = False
        bell, handle.bell = handle.bell, -1    # closed once (the number may be reused)
        if bell >= 0:
            with contextlib.suppress(OSError):
                os.close(bell)                 # writers hold their own duplicates
        self._end(handle, timeout, until)

    def _end(self, handle: WorkerHandle, timeout: float, until: float | None = None) -> None:
        """Tell the process to exit and wait ``timeout``, then terminate it and wait
        ``TERMINATE_WAIT_S`` (no later than ``until``, monotonic, if given), then kill
        it; close its pipe."""
        if handle.process is None:
            return
        with contextlib.suppress(OSError):
            handle.outbox.put([pickle.dumps(None)])
        handle.process.join(timeout)
        if handle.process.is_alive():
            handle.process.terminate()
            handle.process.join(TERMINATE_WAIT_S if until is None else
                                min(TERMINATE_WAIT_S, max(0.0, until - time.monotonic())))
        if handle.process.is_alive():
            # (SIGKILL ends even a stopped process at once: this wait is a bound only)
            handle.process.kill()
            handle.process.join(KILL_WAIT_S)
        self._hand_to_monitor(handle.process)
        handle.close_pipe()
        self._fail_requests(handle, "was stopped")     # none waits for its deadline
        self._poke()

    def _hand_to_monitor(self, process: WatchedProcess) -> None:
        """Have the monitor close ``process``'s descriptors once it has ended: it may be
        polling its pidfd now (``_close_stopped``); ``_poke`` wakes it."""
        with self._to_close_lock:
            self._to_close.append(process)

    def answer_waiting(self, handle: WorkerHandle, op: str, result: Any) -> None:
        """Answer with ``result`` every ``op`` request still waiting for ``handle``'s
        answer, which its worker told as it stopped reading requests."""
        for req_id, future in list(self._futures.items()):
            if getattr(future, "pb3a_worker", None) is handle \
                    and getattr(future, "pb3a_op", None) == op \
                    and self._futures.pop(req_id, None) is not None:
                future.set_result(result)

    def _fail_requests(self, handle: WorkerHandle, what: str) -> None:
        """Fail every request still waiting for ``handle``'s answer: its worker ``what``."""
        for req_id, future in list(self._futures.items()):
            if getattr(future, "pb3a_worker", None) is handle \
                    and self._futures.pop(req_id, None) is not None:
                future.set_exception(RuntimeFailure(f"worker {handle.key!r} {what}"))

    def fence(self, gone_by: float | None = None) -> None:
        """SIGTERM every worker at once, taking no lock and waiting for nothing: each
        stops its modules' stepping as the signal arrives, then tears them down and
        exits, which fails the requests waiting on it (``close`` stops what is left).
        One still there at ``gone_by`` (``time.monotonic``) is killed, its teardowns cut
        short: its modules may be starting elsewhere then (``GONE_BY_S``)."""
        with self._spares_lock:
            handles = [*self._spares, *self.handles.values()]
        for handle in handles:
            if handle.alive and handle.process is not None:
                with contextlib.suppress(OSError, ValueError):   # (gone meanwhile)
                    handle.process.terminate()
        if gone_by is not None:
            threading.Thread(target=self._kill_at, args=(handles, gone_by), daemon=True,
                             name="pb3a-fence-kill").start()

    def _kill_at(self, handles: list[WorkerHandle], deadline: float) -> None:
        time.sleep(max(0.0, deadline - time.monotonic()))
        for handle in handles:
            if handle.alive and handle.process is not None:
                if handle.modules:            # (a spare has nothing to tear down)
                    log.warning("worker %s (modules %s) still tearing down as its modules "
                                "may start elsewhere: killed", handle.key,
                                ", ".join(handle.modules))
                with contextlib.suppress(OSError, ValueError):   # (gone meanwhile)
                    handle.process.kill()

    def close(self, timeout: float) -> None:
        """Stop every worker (in reverse start order) within ``timeout`` seconds, then the
        monitor, then the forkserver if it is still importing its preload
        (``forkserver_owner.stop_if_preloading``). Deaths from here on are stops, not
        crashes. Once the time is up, a worker that has not exited (frozen, stuck) is
        given ``EXIT_AT_LEAST_S`` to exit when told, then killed at once: a close
        overruns its timeout by that much per such worker. A worker retired in the
        background (``retire(wait=False)``) that has not ended by then is killed too.
        Every stopped worker's descriptors (its pidfd, its exit status's pipe) are
        closed by the end, not left to the garbage collector."""
        deadline = time.monotonic() + timeout
        self._stopping.set()
        if self._booting is not None:            # (it stops what it booted meanwhile)
            if self._booting.is_alive():
                # a boot waiting for a forkserver that has answered nothing (hung in its
                # preload?) waits for the stop of that forkserver below: stopped first,
                # not after this join has waited out the close's whole time for it
                self._stop_if_preloading()
            self._booting.join(max(0.1, deadline - time.monotonic()))
        with self._spares_lock:     # (listed until stopped: a close a Ctrl-C interrupts
            spares = list(self._spares)     # is done again, and stops them then)
        for handle in [*spares, *reversed(list(self.handles.values()))]:
            left = deadline - time.monotonic()
            self._stop(handle, max(EXIT_AT_LEAST_S, min(2.0, left)), until=deadline)
        with self._spares_lock:
            self._spares = []
        for thread, handle in self._retiring:
            thread.join(max(0.1, deadline - time.monotonic()))
            if thread.is_alive() and handle.process is not None:
                # its time is up, as for the workers above: killed, not left to the
                # thread, which this process's exit may cut short before its own kill
                handle.process.kill()
                thread.join(KILL_WAIT_S)
        self._poke()
        self._monitor.join(2.0)
        if not self._monitor.is_alive():     # (else it may poll them: the collector's)
            self._close_stopped(until=deadline)
        self._wake_r.close()
        self._wake_w.close()
        # One still preloading (hung in an import?) would stay until this process
        # exits; one that has started workers, this pool's or another's, stays.
        self._stop_if_preloading()

    @staticmethod
    def _stop_if_preloading() -> None:
        """Stop this process's forkserver if it has answered no start yet
        (``forkserver_owner.stop_if_preloading``), saying so."""
        stopped = forkserver_owner.stop_if_preloading()
        if stopped is not None:
            log.info("the forkserver (pid %s) had not finished its preload: stopped",
                     stopped)

