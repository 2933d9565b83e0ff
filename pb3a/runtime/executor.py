"""``Executor``: the supervisor of one node (the paper's NetExecutor).

It owns everything on its node: the worker processes (one per module, or a
few packed ones), every shared-memory ring, the bridge that receives remote
links, and the records of the modules that run here. Links with both ends here
are wired by ``connect``; a remote link is wired in halves (``publish`` at the
writer's node, ``open_inbound`` and ``follow`` at the reader's) by the
``Launcher``, which alone sees every node. A single
monitor thread reads every worker pipe and process sentinel; requests wait on
futures with deadlines; a crashed worker is restarted by its modules'
``restart`` policies. Shutdown stops modules in reverse start order, then the
processes (terminate, then kill), then unlinks every segment.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import math
import multiprocessing
import multiprocessing.connection
import os
import socket
import threading
import time
from collections import deque
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass, field
from multiprocessing import reduction
from typing import Any

import cloudpickle
import numpy as np

from pb3a.errors import RuntimeFailure, RuntimeTimeout
from pb3a.kernel.config import FlatLink, FlatModule
from pb3a.kernel.ports import Policy
from pb3a.kernel.served import forget
from pb3a.kernel.worker import worker_main
from pb3a.runtime.bridge import Bridge
from pb3a.runtime.processes import start_without_main
from pb3a.runtime.recovery import recover
from pb3a.runtime.stats import node_report
from pb3a.transport.auth import ClusterKey
from pb3a.transport.doorbell import new_bell
from pb3a.transport.ring import ZERO_COPY_MIN, RingSize, ShmRing
from pb3a.transport.shm import reap_orphans, segment_name

log = logging.getLogger("pb3a.executor")

REQUEST_TIMEOUT = 10.0
SMALL_RING = 1 << 20
LARGE_RING = 16 << 20
ARRAYS_PER_RING = 4       # pinned arrays in flight on a link, at least
MAX_ARRAYS_PER_RING = 64  # ... and at most (64 MiB for 1 MiB arrays)
SLOT_RECORDS_RING = 64 << 10   # a pool's ring carries only the records naming slots

_context = multiprocessing.get_context("forkserver")
_context.set_forkserver_preload(["pb3a.kernel.worker", "numpy", "cloudpickle"])


@dataclass
class WorkerHandle:
    key: str
    node: str
    bell: int = field(default_factory=new_bell)    # the worker's doorbell (an eventfd)
    process: Any = None
    conn: Any = None
    modules: list[str] = field(default_factory=list)
    restarts: deque[float] = field(default_factory=deque)
    alive: bool = False
    pid: int = 0
    send_lock: threading.Lock = field(default_factory=threading.Lock)

    def send(self, message: Any, fd: int | None = None) -> None:
        """Send on the worker's pipe, with a descriptor right behind it if given."""
        with self.send_lock:                     # several threads may send at once
            self.conn.send(message)
            if fd is not None:
                reduction.send_handle(self.conn, fd, self.pid)


@dataclass
class ModuleRecord:
    spec: FlatModule
    worker: str
    blob: bytes
    status: str = "starting"          # starting | running | failed | stopped
    checkpoint: bytes | None = None
    checkpoints: int = 0              # checkpoints received (restart = "last-state")
    restarts: int = 0


class Executor:
    """Runs one node's modules in worker processes on this machine; thread-safe; every
    request has a deadline."""

    def __init__(self, node: str, *, workers: int = 0, cpus: list[int] | None = None,
                 checkpoint_s: float = 1.0, log_level: int = logging.WARNING,
                 module_servers: list[str] | None = None, host: str = "127.0.0.1",
                 lock: threading.RLock | None = None, epoch: int = 0) -> None:
        self.node = node
        self.epoch = epoch                  # the system's: older replication is refused
        self.module_servers = list(module_servers or [])   # workers import from these too
        self.packing = workers              # packed worker processes (0: one per module)
        self.cpus = cpus                    # the CPUs the node's workers run on (None: all)
        self.quota = 0                      # modules per packed worker at start
        self.host = host                    # where remote readers reach this node's outputs
        self.checkpoint_s = checkpoint_s
        self.log_level = log_level
        self.modules: dict[str, ModuleRecord] = {}
        self.links: dict[str, FlatLink] = {}          # links with both ends here
        self.inbound: dict[str, FlatLink] = {}        # remote links read here
        self.outbound: dict[str, FlatLink] = {}       # remote links written here
        self.rings: dict[str, ShmRing] = {}
        self.workers: dict[str, WorkerHandle] = {}
        self.failures: list[str] = []                 # what went wrong, for stats and logs
        self.handler: Any = None                      # applies agents' requests (op, args)
        self.republished: Any = None                  # told (link, endpoint) after a restart
        self._bridge: Bridge | None = None            # remote links in (made on first use)
        self._futures: dict[int, Future[Any]] = {}
        self._ids = itertools.count()
        # Held by a restart and by whoever changes the configuration (the launcher's
        # global lock when the executor runs in the launcher's process).
        self.lock = lock or threading.RLock()
        self._stopping = threading.Event()
        self._wake_r, self._wake_w = socket.socketpair()
        self._monitor = threading.Thread(target=self._watch, name="pb3a-monitor", daemon=True)
        reap_orphans()
        self._monitor.start()

    @property
    def bridge(self) -> Bridge:
        """The receiving end of remote links (the cluster key is loaded on first use)."""
        if self._bridge is None:
            self._bridge = Bridge(ClusterKey.load(), self.epoch)
        return self._bridge

    # -- placement and processes -------------------------------------------
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
        """Size the packed workers for the modules about to be added, in their order."""
        if self.packing:
            count = sum(1 for spec in specs if not spec.group)
            self.quota = -(-count // self.packing)

    def spawn(self, handle: WorkerHandle) -> None:
        """Start (or restart) the worker process behind ``handle``."""
        parent, child = _context.Pipe()
        process = _context.Process(
            target=worker_main, name=f"pb3a-worker-{handle.key}", daemon=True,
            args=(child, handle.key, self.checkpoint_s, self.log_level,
                  self.cpus, self.module_servers))
        start_without_main(process)
        child.close()
        # The doorbell is the worker's first read: send it before anyone can send a request.
        reduction.send_handle(parent, handle.bell, process.pid)
        handle.process, handle.conn, handle.alive, handle.pid = process, parent, True, process.pid
        self._poke()

    def ensure_worker(self, key: str, node: str) -> WorkerHandle:
        handle = self.workers.get(key)
        if handle is None:
            handle = WorkerHandle(key, node)
            self.workers[key] = handle
            self.spawn(handle)
        return handle

    # -- requests ------------------------------------------------------------
    def call(self, worker: str, op: str, timeout: float = REQUEST_TIMEOUT, /,
             **args: Any) -> Any:
        """Send one request to a worker and wait for its answer."""
        return self.result(self.submit(worker, op, **args), op, worker, timeout)

    def call_module(self, name: str, op: str, timeout: float = REQUEST_TIMEOUT, /,
                    **args: Any) -> Any:
        """Send one request about module ``name`` to its worker and wait for the answer."""
        return self.call(self.modules[name].worker, op, timeout, name=name, **args)

    def submit(self, worker: str, op: str, /, _fd: int | None = None, **args: Any) -> Future[Any]:
        """Send one request to a worker (and a descriptor after it); the future holds
        its answer."""
        handle = self.workers[worker]
        future: Future[Any] = Future()
        if not handle.alive:
            future.set_exception(RuntimeFailure(f"worker {worker!r} is not running"))
            return future
        req_id = next(self._ids)
        self._futures[req_id] = future
        future.pb3a_worker = worker   # type: ignore[attr-defined]
        try:
            handle.send((req_id, op, args), _fd)
        except (OSError, ValueError) as exc:
            # Whoever pops a future completes it: the monitor may have done so already
            # (the worker's death seen meanwhile).
            if self._futures.pop(req_id, None) is not None:
                future.set_exception(RuntimeFailure(f"worker {worker!r} is gone: {exc}"))
        return future

    @staticmethod
    def result(future: Future[Any], op: str, key: str, timeout: float) -> Any:
        try:
            return future.result(timeout)
        except FutureTimeout:
            raise RuntimeTimeout(
                f"worker {key!r} did not answer {op!r} within {timeout} s") from None

    # -- modules -------------------------------------------------------------
    def add_module(self, spec: FlatModule, *, state: dict[str, Any] | None = None) -> None:
        """Instantiate a module in its worker (not started)."""
        key = self.place(spec)
        handle = self.ensure_worker(key, spec.node)
        record = ModuleRecord(spec, key, cloudpickle.dumps(spec.cls))
        self.modules[spec.name] = record
        handle.modules.append(spec.name)
        try:
            self.instantiate(record, spec.state if state is None else state)
        except BaseException:
            del self.modules[spec.name]
            self.vacate(key, spec.name)
            raise

    def instantiate(self, record: ModuleRecord, state: dict[str, Any]) -> None:
        """Create the module in its worker with ``state`` (not started)."""
        spec = record.spec
        self.call(record.worker, "add", name=spec.name, cls=record.blob, period=spec.period,
                  restart=spec.restart, state=state)

    def start_modules(self, names: list[str]) -> None:
        """Run ``setup`` and start the modules, in order.

        A worker that dies meanwhile is left to its modules' restart policies.
        """
        for name in names:
            record = self.modules[name]
            try:
                self.call(record.worker, "start", names=[name])
            except RuntimeFailure:
                process = self.workers[record.worker].process
                process.join(1.0)          # a pipe error may come before the death is seen
                if process.is_alive():
                    raise
                continue
            record.status = "running"

    def swap(self, name: str, spec: FlatModule) -> list[str]:
        """Replace a module's class by ``spec.cls`` in place; the state names kept."""
        record = self.modules[name]
        blob = cloudpickle.dumps(spec.cls)
        kept = self.call(record.worker, "swap", name=name, cls=blob)
        record.spec, record.blob = spec, blob
        return kept

    def pause(self, name: str, timeout: float = REQUEST_TIMEOUT) -> bool:
        """Hold a module's lock (no step, no event) until ``resume``; False if it does not
        run here (any more)."""
        record = self.modules.get(name)
        if record is None or not self.workers[record.worker].alive:
            return False
        self.call(record.worker, "pause", timeout + 1.0, name=name, timeout=timeout)
        return True

    def resume(self, name: str) -> None:
        record = self.modules.get(name)
        if record is not None and self.workers[record.worker].alive:
            self.call(record.worker, "resume", name=name)

    def stop_module(self, name: str, timeout: float = 5.0) -> None:
        """Stop stepping and dispatching, then run the module's ``teardown``."""
        record = self.modules[name]
        if record.status == "running" and self.workers[record.worker].alive:
            self.call(record.worker, "stop", timeout + 1.0, name=name, grace=timeout)
        record.status = "stopped"

    def remove_module(self, name: str) -> None:
        """Drop a module (its links are gone) and stop its worker if it hosted nothing else."""
        record = self.modules.pop(name)
        if self.workers[record.worker].alive:
            self.call(record.worker, "remove", name=name)
        self.vacate(record.worker, name)

    def retire(self, name: str) -> bytes:
        """The migration fence: ``teardown``, then capture the module's state and unconsumed
        inputs and drop it here; it runs nowhere until restored (``land``)."""
        record = self.modules[name]
        captured = self.call(record.worker, "migrate_out", name=name)
        del self.modules[name]
        self.vacate(record.worker, name)
        return captured

    def land(self, name: str, captured: bytes) -> None:
        """Restore what ``retire`` captured into the (instantiated, not started) module."""
        self.call_module(name, "migrate_in", captured=captured)

    def vacate(self, key: str, name: str) -> None:
        """``name`` no longer runs in worker ``key``; stop the worker if it is empty now."""
        handle = self.workers[key]
        handle.modules.remove(name)
        if not handle.modules:
            self._stop_worker(handle, timeout=2.0)
            del self.workers[handle.key]

    def forget(self, module: str) -> None:
        """Drop cached copies of Python module ``module`` here and in every worker."""
        forget(module)
        for key, handle in list(self.workers.items()):
            if handle.alive:
                self.call(key, "forget", module=module)

    # -- links with both ends here ---------------------------------------------
    def connect(self, link: FlatLink) -> None:
        """Wire one link: in memory inside a worker, else through a new ring."""
        self.links[link.key] = link
        self.attach_reader(link)
        self.attach_writer(link)

    def attach_reader(self, link: FlatLink) -> None:
        """The reading side: attach the link's ring (created here) in the reader's worker."""
        src, dst = self.modules[link.src], self.modules[link.dst]
        if src.worker == dst.worker:
            return
        ring = self._ring(link.key, ring_size(src.spec.cls, link.src_port, link.policy))
        self.call(dst.worker, "link_in", key=link.key, dst=link.dst, dst_port=link.dst_port,
                  ring=ring.name, policy=str(link.policy))

    def attach_writer(self, link: FlatLink) -> None:
        """The writing side: connect the output to the ring, or straight to the input."""
        src, dst = self.modules[link.src], self.modules[link.dst]
        if src.worker == dst.worker:
            self.call(src.worker, "link_out", key=link.key, src=link.src, src_port=link.src_port,
                      dst=link.dst, dst_port=link.dst_port, policy=str(link.policy))
        else:
            self.call(src.worker, "link_out", key=link.key, src=link.src, src_port=link.src_port,
                      ring=self.rings[link.key].name, _fd=self.workers[dst.worker].bell)

    def unhook_writer(self, link: FlatLink) -> None:
        """Stop feeding a link whose reader is gone for good (its ring stays until removed)."""
        self.call(self.modules[link.src].worker, "unlink_out", key=link.key)

    def detach(self, link: FlatLink) -> None:
        """Unwire a link: the writer stops first, then the reader takes in everything
        still on the way, so a new wiring cannot overtake it."""
        self.links.pop(link.key, None)
        src = self.modules.get(link.src)
        if src is not None and self.workers[src.worker].alive:
            self.call(src.worker, "unlink_out", key=link.key)
        self._unlink_in(link)

    def _unlink_in(self, link: FlatLink) -> None:
        dst = self.modules.get(link.dst)
        if dst is not None and self.workers[dst.worker].alive:
            self.call(dst.worker, "unlink_in", key=link.key)
        ring = self.rings.pop(link.key, None)
        if ring is not None:
            ring.close()

    def _ring(self, key: str, size: RingSize | None) -> ShmRing:
        ring = self.rings.get(key)
        if ring is None:
            if size is None:
                raise RuntimeError(f"link {key} has no ring to reopen")
            ring = self.rings[key] = ShmRing.create(segment_name("ring"), *size)
        return ring

    # -- remote links, one half each ---------------------------------------------------
    def publish(self, link: FlatLink) -> tuple[str, str, bytes]:
        """The writing half: publish the output (once per output, whoever reads it);
        returns the endpoint (data address, control address, sender incarnation)."""
        self.outbound[link.key] = link
        data, control, incarnation = self.call(
            self.modules[link.src].worker, "publish_out", key=link.key, src=link.src,
            src_port=link.src_port, secret=self.bridge.key.secret, host=self.host,
            epoch=self.epoch)
        return data, control, incarnation

    def unpublish(self, link: FlatLink) -> int:
        """Stop publishing for ``link``; the sequence number the sender reached."""
        self.outbound.pop(link.key, None)
        src = self.modules.get(link.src)
        if src is None or not self.workers[src.worker].alive:
            return 0
        return self.call(src.worker, "unpublish_out", key=link.key)

    def open_inbound(self, link: FlatLink, size: RingSize | None) -> None:
        """The reading half: a ring into the reader's worker, which the bridge fills
        (``size`` None: the link's ring exists already)."""
        self.inbound[link.key] = link
        dst = self.modules[link.dst]
        ring = self._ring(link.key, size)
        self.call(dst.worker, "link_in", key=link.key, dst=link.dst, dst_port=link.dst_port,
                  ring=ring.name, policy=str(link.policy))
        self.bridge.open(link.key, _topic(link), ring.name, self.workers[dst.worker].bell)

    def follow(self, link: FlatLink, endpoint: tuple[str, str, bytes]) -> None:
        """Receive ``link``'s output from the sender at ``endpoint`` (see ``publish``)."""
        self.bridge.follow(_topic(link), *endpoint)

    def close_inbound(self, link: FlatLink, reached: int = 0) -> None:
        """Stop receiving ``link`` once the values before ``reached`` are in."""
        self.inbound.pop(link.key, None)
        self.bridge.close(link.key, reached)
        self._unlink_in(link)

    def report(self) -> dict[str, Any]:
        """This node's figures (see ``stats.node_report``)."""
        return node_report(self)

    # -- monitor -------------------------------------------------------------
    def _poke(self) -> None:
        with contextlib.suppress(OSError):
            self._wake_w.send(b"\x01")

    def _watch(self) -> None:
        while not self._stopping.is_set():
            handles = [h for h in list(self.workers.values()) if h.alive]
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
        try:
            while handle.conn.poll():
                req_id, ok, result = handle.conn.recv()
                if req_id is None:
                    self._notice(handle, ok, result)
                    continue
                future = self._futures.pop(req_id, None)
                if future is None:
                    continue
                if ok is True:
                    future.set_result(result)
                else:
                    future.set_exception(RuntimeFailure(f"worker {handle.key!r}: {result}"))
        except (EOFError, OSError):
            return                                     # it died: the sentinel reports it

    def _notice(self, handle: WorkerHandle, kind: str, args: dict[str, Any]) -> None:
        if kind == "checkpoint":
            record = self.modules.get(args["name"])
            if record is not None:
                record.checkpoint = args["state"]
                record.checkpoints += 1
        elif kind == "error":
            count = args["suppressed"]
            more = f" ({count} more since the last report)" if count else ""
            logging.getLogger("pb3a.module").error(
                "module %r raised in %s%s:\n%s", args["name"], args["where"], more, args["trace"])
        elif kind == "request":
            threading.Thread(target=self._serve_request, args=(handle, args), daemon=True,
                             name="pb3a-agent-request").start()

    def _serve_request(self, handle: WorkerHandle, request: dict[str, Any]) -> None:
        """Apply an agent's request through ``handler`` and send the answer back."""
        try:
            args = cloudpickle.loads(request["args"])
            if self.handler is None:
                raise RuntimeFailure("this executor takes no requests from agents")
            answer = {"id": request["id"], "ok": True, "result": self.handler(request["op"], args)}
        except Exception as exc:
            answer = {"id": request["id"], "ok": False, "result": f"{type(exc).__name__}: {exc}"}
        with contextlib.suppress(OSError, ValueError):
            handle.send((None, "answer", answer))

    def _died(self, handle: WorkerHandle) -> None:
        handle.alive = False
        with contextlib.suppress(OSError):
            handle.conn.close()
        for req_id, future in list(self._futures.items()):
            if getattr(future, "pb3a_worker", None) == handle.key \
                    and self._futures.pop(req_id, None) is not None:
                future.set_exception(RuntimeFailure(f"worker {handle.key!r} died"))
        if self._stopping.is_set():
            return
        code = handle.process.exitcode
        if code == 0:                 # stopped on purpose (SIGTERM): not a crash
            log.warning("worker %s (pid %s) stopped; its modules %s are stopped", handle.key,
                        handle.pid, ", ".join(handle.modules))
            for name in handle.modules:
                self.modules[name].status = "stopped"
            return
        log.warning("worker %s (pid %s, modules %s) died with exit code %s",
                    handle.key, handle.pid, ", ".join(handle.modules), code)
        threading.Thread(target=self._recover, args=(handle, code), daemon=True,
                         name=f"pb3a-restart-{handle.key}").start()

    def _recover(self, handle: WorkerHandle, code: int | None) -> None:
        with self.lock:
            if not self._stopping.is_set():     # a shutdown may have come first
                recover(self, handle, code)

    # -- shutdown ------------------------------------------------------------
    def _stop_worker(self, handle: WorkerHandle, timeout: float) -> None:
        handle.alive = False
        with contextlib.suppress(OSError):
            os.close(handle.bell)              # writers hold their own duplicates
        if handle.process is None:
            return
        with contextlib.suppress(OSError, ValueError):
            handle.conn.send(None)
        handle.process.join(timeout)
        if handle.process.is_alive():
            handle.process.terminate()
            handle.process.join(1.0)
        if handle.process.is_alive():
            handle.process.kill()
            handle.process.join(1.0)
        with contextlib.suppress(OSError):
            handle.conn.close()
        self._poke()

    def shutdown(self, timeout: float = 10.0) -> None:
        """Stop modules in reverse start order, then workers, then free every ring."""
        deadline = time.monotonic() + timeout
        with self.lock:
            for name in reversed(list(self.modules)):
                left = max(0.1, deadline - time.monotonic())
                try:
                    self.stop_module(name, timeout=min(2.0, left))
                except (RuntimeFailure, RuntimeTimeout) as exc:
                    log.warning("stopping module %r: %s", name, exc)
            self._stopping.set()
            for handle in reversed(list(self.workers.values())):
                self._stop_worker(handle, timeout=max(0.1, min(2.0, deadline - time.monotonic())))
            if self._bridge is not None:
                self._bridge.shutdown()
            for ring in self.rings.values():
                ring.close()
            self.rings.clear()
        self._poke()
        self._monitor.join(2.0)
        self._wake_r.close()
        self._wake_w.close()


def _topic(link: FlatLink) -> str:
    """The topic a remote link's output is published under."""
    return f"{link.src}.{link.src_port}"


def ring_size(cls: type, port: str, policy: Policy) -> RingSize:
    """The ring for a link. Pinned arrays: room for the values the input may hold as
    zero-copy views (its queue) plus a few in flight, at least ARRAYS_PER_RING and at
    most MAX_ARRAYS_PER_RING; large ones (read as views) in a pool of slots beside a
    small ring. Other values: a ring of a default size."""
    spec = cls.outputs[port]
    if spec.shape is not None and spec.dtype is not None:
        nbytes = math.prod(spec.shape) * spec.dtype.itemsize
        held = policy.size + 2 if policy.kind == "queue" else 0
        count = min(max(ARRAYS_PER_RING, held), MAX_ARRAYS_PER_RING)
        if nbytes >= ZERO_COPY_MIN:
            return RingSize(SLOT_RECORDS_RING, count, nbytes)
        return RingSize(max(SMALL_RING, count * (nbytes + 128)))
    if issubclass(spec.type, np.ndarray) or spec.type is object:
        return RingSize(LARGE_RING)
    return RingSize(SMALL_RING)
