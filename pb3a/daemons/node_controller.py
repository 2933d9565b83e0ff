"""``NodeController``: the daemon of one machine (``pb3a node start --name N --listen ADDR``).

It admits or refuses work by its measured resources (psutil CPU and memory against
its limits) and says why when it refuses; starts one executor process per
configuration and answers with that executor's address when it already runs; and
stops an executor gracefully (SIGTERM: modules stop in reverse order) or forcefully
(SIGKILL) on request. Every request is authenticated; executors it started die
with it.
"""

from __future__ import annotations

import collections
import logging
import multiprocessing
import signal
import threading
import time
from dataclasses import dataclass
from typing import Any, NamedTuple, NoReturn

import psutil

from pb3a.config import checks
from pb3a.daemons import executor_family
from pb3a.daemons.node_share import UNBOUND_S, executor_main
from pb3a.errors import RuntimeFailure, bounded_wait
from pb3a.node.remote import HEARTBEAT_S
from pb3a.processes import start_resource_tracker, start_without_main, terminal_signals_held
from pb3a.throttle import Throttle
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlServer, UnknownOperation
from pb3a.transport.pickling import PYTHON
from pb3a.transport.shm import reap_child, reap_orphans

log = logging.getLogger("pb3a.node")

_context = multiprocessing.get_context("spawn")      # a clean interpreter per executor
START_TIMEOUT = 30.0
SAMPLE_S = 0.5
# Admission judges the CPU over this many samples (5 s): one busy half-second on a
# small machine refused launches and failovers at random.
CPU_WINDOW = 10
SAMPLE_FAILURE_LOG_S = 60.0    # a sampler turn that fails is logged at most this often
# A refusal is logged at most this often; the refusals not logged meanwhile are counted
# in the next line logged (launchers that try again and again must not fill the journal)
REFUSAL_LOG_S = 60.0
# A controller that stops answers this long at most, once it has stopped its executors,
# for their launchers to ask how each ended (``executor_ended``): a launcher asks once
# its executor has missed two heartbeats, and again a heartbeat later (the executor
# stops answering them as its stop begins). Told so, a launcher has the node lost at
# once, its reason said; else it waited 2 s (``LOSS_S``), as for a cut cable.
TELL_S = 4 * HEARTBEAT_S


def how_it_ended(status: int | None) -> str:
    """How an executor that ended on its own did (its exit status or signal), as said
    after "the executor": killed (the OOM killer's SIGKILL) or failed."""
    if status == 0:
        return "stopped itself"
    if status is None or status > 0:
        return f"exited with status {status}"
    try:
        how = f"was killed by {signal.Signals(-status).name}"
    except ValueError:
        how = f"was killed by signal {-status}"
    if -status == signal.SIGKILL:
        how += ", by the kernel's OOM killer if `journalctl -k` says so"
    return how


def _log_end(node: str, config: str, address: str, status: int | None) -> None:
    """Say that the executor for ``config`` ended on its own, and how: killed or failed
    at WARNING (the node's log said nothing, and the launcher only that the node was
    silent, as for a cut cable); one that stopped itself (its lease run out, or taken by
    no launcher), which it logged, at INFO."""
    if status == 0:
        log.info("node %s: the executor for %r at %s stopped itself", node, config, address)
        return
    log.warning("node %s: the executor for %r at %s %s; its modules stopped with it",
                node, config, address, how_it_ended(status))


class _Executor(NamedTuple):
    """An executor this controller started: its process, the pipe it answered its start
    on, its address, and the mark its family carries (``executor_family``)."""

    process: Any
    pipe: Any
    address: str
    mark: str


class Refused(RuntimeFailure):
    """The node will not take this work; the message says which resource is short, and
    the limit to raise. A PB3A error, so that the caller gets it as it is (it read
    "start_executor at ... failed: Refused: ...")."""


@dataclass
class Limits:
    """What a node accepts work under."""

    max_cpu_percent: float = 90.0         # mean over the machine's CPUs and the last 5 s
    min_memory_bytes: int = 256 << 20     # available memory that must remain


class NodeController:
    """Admits, starts and stops the executors of one node."""

    def __init__(self, name: str, key: ClusterKey, host: str = "127.0.0.1", port: int = 0,
                 limits: Limits | None = None) -> None:
        if problems := checks.name(name, "node"):    # configurations could never name it
            raise ValueError(problems[0])
        self.name = name
        self.limits = limits or Limits()
        self.unbound_s = UNBOUND_S          # an executor not taken by a launcher this long stops
        self._executors: dict[str, _Executor] = {}      # by configuration
        # by configuration, the last executor that ended on its own (not stopped by a
        # launcher), with how: a launcher asks (``executor_ended``); those of them it has
        # not yet been told of, stopped as this controller stops (``close``)
        self._ended: dict[str, tuple[_Executor, str]] = {}
        self._lock = threading.Lock()
        self._untold: set[str] = set()
        self._told = threading.Condition(self._lock)
        self._closing = False               # set by close: no executor starts from then on
        self._cpu_samples: collections.deque[float] = collections.deque(maxlen=CPU_WINDOW)
        self._refusals_logged = Throttle(REFUSAL_LOG_S)    # (the others counted)
        self._cpu = self._sample_cpu()
        self._sampling = threading.Event()
        self._sampler = threading.Thread(target=self._sample, name="pb3a-node-sampler",
                                         daemon=True)
        self._sampler.start()
        # (its ping answers its name, which a launcher compares with the node's name in
        # its configuration: ``pb3a.node.remote._named_otherwise``)
        self._server = ControlServer(key, self._handle, host, port, name="pb3a-node",
                                     title=f"node {name}'s controller",
                                     instant={"ping": lambda args: {"node": name}})
        self.address = self._server.address

    # -- admission ----------------------------------------------------------------
    def _sample(self) -> None:
        """Sample the CPU and forget ended executors every ``SAMPLE_S`` until closed. A turn
        that fails is logged and the next one taken (one burst of idle connections, EMFILE
        in ``psutil``, ended the thread for good: admission judged a frozen CPU figure,
        and ended executors were never forgotten again)."""
        logged_at = -SAMPLE_FAILURE_LOG_S
        while not self._sampling.wait(SAMPLE_S):
            for what, step in (("sampling its CPU", self._take_cpu_sample),
                               ("forgetting the executors that ended", self._forget_ended)):
                try:
                    step()
                except Exception as exc:
                    if time.monotonic() - logged_at >= SAMPLE_FAILURE_LOG_S:
                        logged_at = time.monotonic()
                        log.warning("node %s: %s failed (%s: %s); it tries again every "
                                    "%g s", self.name, what, type(exc).__name__, exc, SAMPLE_S)

    def _take_cpu_sample(self) -> None:
        self._cpu = self._sample_cpu()

    def _forget_ended(self) -> None:
        """Forget the executors that ended on their own (their launcher killed, or none
        took them), and free what each held here: a controller that ran for months
        kept three descriptors for each, and ran out of them."""
        with self._lock:
            ended = {config: entry for config, entry in self._executors.items()
                     if not entry.process.is_alive()}
            for config in ended:
                del self._executors[config]
        for config, entry in ended.items():
            entry.pipe.close()
            entry.process.join(1.0)              # (ended: at once)
            status = entry.process.exitcode
            _log_end(self.name, config, entry.address, status)
            reap_child(entry.process.pid)  # (the segments of one that could not free them)
            entry.process.close()
            with self._lock:
                if config not in self._executors:       # (none started since)
                    self._ended[config] = (entry, how_it_ended(status))
        if ended:
            reap_orphans()                # (and of its workers)

    def _sample_cpu(self) -> float:
        """One more CPU sample; the mean of the window's."""
        self._cpu_samples.append(psutil.cpu_percent(interval=None))
        return sum(self._cpu_samples) / len(self._cpu_samples)

    def admit(self, what: str) -> None:
        """Raise ``Refused`` with the reason if the node cannot take ``what`` now, and log
        it (at most once a minute, counting the others: the node's log, where an operator
        looks first, said nothing, and only the launcher's showed it)."""
        cpu, memory = self._cpu, psutil.virtual_memory().available
        if cpu > self.limits.max_cpu_percent:
            self._refuse(f"node {self.name} refuses {what}: CPU {cpu:.0f}% busy, above its "
                         f"limit of {self.limits.max_cpu_percent:.0f}% (its controller's "
                         "--max-cpu: raise it, or free the CPU)")
        if memory < self.limits.min_memory_bytes:
            self._refuse(f"node {self.name} refuses {what}: {memory >> 20} MiB of memory "
                         f"available, below its limit of {self.limits.min_memory_bytes >> 20}"
                         " MiB (its controller's --min-memory: lower it, or free memory)")

    def _refuse(self, why: str) -> NoReturn:
        more = self._refusals_logged.let(time.monotonic())
        if more is not None:
            log.warning("%s%s", why, f" ({more} more refused in the last "
                        f"{REFUSAL_LOG_S:g} s, not logged)" if more else "")
        raise Refused(why)

    # -- executors ----------------------------------------------------------------
    def start_executor(self, config: str, workers: int = 0, cpus: list[int] | None = None,
                       host: str = "127.0.0.1", node: str | None = None,
                       python: str | None = None) -> tuple[str, bool]:
        """The address of ``config``'s executor here, and whether it was started now
        (False: it ran already, perhaps for another launch, which its caller must not
        stop). The executor is node ``node``, as the configuration names it (by default
        this controller's ``--name``): one named otherwise signed what it told the
        launcher with a name the launcher did not know as that node's, and was refused
        (a restarted module's events, its link's new sender, checkpoints, agents).
        ``Refused`` if the launcher runs another ``python`` (major.minor) than this one."""
        if python is not None and python != PYTHON:
            raise Refused(f"node {self.name} runs Python {PYTHON} and the launcher Python "
                          f"{python}: run one Python version (major.minor) on every machine "
                          "of a system, since module classes and state travel pickled for one")
        with self._lock:
            # (a start whose request came as the controller closed, after close took
            # its list, left an executor that nothing stopped: it ran on unbound for
            # 30 s, or as long as its launcher renewed its lease)
            if self._closing:
                raise Refused(f"node {self.name}'s controller is closing: it starts no "
                              f"executor for {config!r}; start it again, then launch")
            running = self._executors.get(config)
            if running is not None and running.process.is_alive():
                return running.address, False
            self.admit(f"an executor for {config!r}")
            parent, child = _context.Pipe()
            mark = executor_family.new_mark()
            process = _context.Process(
                target=executor_main, name=f"pb3a-executor-{config}",
                args=(config, node or self.name, workers, cpus, host, child, logging.WARNING,
                      self.unbound_s, mark))
            # (held off until its handlers are set: a Ctrl-C at the node's terminal as
            # its interpreter started killed it, a crash dump or a traceback there)
            start_resource_tracker()                  # (first: its start takes them back)
            with terminal_signals_held():
                start_without_main(process)
            child.close()
            try:            # (the pipe is readable at once, empty, if the executor died)
                address = parent.recv() if parent.poll(START_TIMEOUT) else None
            except EOFError:
                address = None
            if address is None:
                process.join(1.0)           # (dead: its exit status says so)
                process.kill()
                process.join(5.0)
                parent.close()
                why = (f"did not start within {START_TIMEOUT:g} s" if process.exitcode in
                       (None, -9) else f"exited with status {process.exitcode} as it started")
                raise RuntimeError(f"the executor for {config!r} {why}: node {self.name}'s "
                                   "log says why")
            self._executors[config] = _Executor(process, parent, address, mark)
            self._ended.pop(config, None)
            return address, True

    def stop_executor(self, config: str, force: bool = False, timeout: float = 15.0,
                      executor: str | None = None) -> bool:
        """Stop ``config``'s executor: SIGTERM (modules stop in order), or SIGKILL with
        ``force`` or when it does not end within ``timeout``. False if none ran, or if
        ``executor`` (its address, as ``start_executor`` gave it) names another one: a
        stop sent by a launcher while this machine was cut off is delivered when the
        cable is back, by then perhaps to the executor of the next launch of the same
        system, which it killed."""
        with self._lock:
            entry = self._executors.get(config)
            if entry is not None and executor is not None and entry.address != executor:
                log.warning("node %s: a stop of the executor for %r at %s, which runs no "
                            "more, left the one at %s running (a request sent before, "
                            "delivered late)", self.name, config, executor, entry.address)
                return False
            entry = self._executors.pop(config, None)
        if entry is None:
            return False
        process, pipe = entry.process, entry.pipe
        if force:
            process.kill()
        else:
            process.terminate()
        process.join(timeout)
        if process.is_alive():
            process.kill()
            process.join(5.0)
        pipe.close()
        if not process.is_alive():  # (one stuck in the kernel still uses its segments)
            reap_child(process.pid)  # the segments of an executor that could not free them
        reap_orphans()              # (and of its workers)
        return True

    def executors(self) -> dict[str, str]:
        """Running configurations and their executors' addresses."""
        with self._lock:
            return {config: entry.address for config, entry in self._executors.items()
                    if entry.process.is_alive()}

    def executor_ended(self, config: str, executor: str, timeout: float) -> str | None:
        """How ``config``'s executor at address ``executor`` ended, once it has ended on
        its own and every process of its family has too (those still alive are killed
        now); None while it runs, if this controller did not start it, or if one of its
        family outlived ``timeout``. Its launcher asks this of a node gone silent: its
        modules may then start elsewhere at once, nothing of the executor left to run
        them, where it would wait for their lease to run out."""
        self._forget_ended()        # (one that ended since the sampler's last look)
        with self._lock:
            entry, how = self._ended.get(config, (None, ""))
        if entry is None or entry.address != executor:
            return None
        if not executor_family.end(entry.mark, timeout):
            log.warning("node %s: a process the executor for %r at %s started outlived a "
                        "SIGKILL for %g s", self.name, config, executor, timeout)
            return None
        reap_orphans()              # (the segments of the processes ended now)
        with self._told:
            self._untold.discard(config)
            self._told.notify_all()
        return how

    def _handle(self, op: str, args: dict[str, Any]) -> Any:
        if op == "start_executor":
            return self.start_executor(args["config"], args.get("workers", 0),
                                       args.get("cpus"), args.get("host", "127.0.0.1"),
                                       args.get("node"), args.get("python"))
        if op == "stop_executor":
            return self.stop_executor(args["config"], bool(args.get("force", False)),
                                      bounded_wait(args.get("timeout", 15.0), "stop_executor"),
                                      args.get("executor"))
        if op == "executor_ended":
            return self.executor_ended(args["config"], args["executor"],
                                       bounded_wait(args.get("timeout", 1.0), "executor_ended"))
        if op == "admit":
            self.admit(str(args.get("what", "work")))
            return True
        if op == "status":
            return {"node": self.name, "python": PYTHON, "cpu_percent": self._cpu,
                    "memory_available": psutil.virtual_memory().available,
                    "executors": self.executors()}
        raise UnknownOperation(op, ("start_executor", "stop_executor", "executor_ended",
                                    "admit", "status"))

    @property
    def rejected(self) -> Any:
        return self._server.rejected

    def close(self, why: str = "closed") -> None:
        """Stop every executor (gracefully), then the controller; one that died on its
        own is reaped too, and the segments it left removed. ``why``: what stops it (a
        signal's name), logged with the executors that stop. Each executor's launcher
        is told, if it asks within ``TELL_S``, that the executor was stopped as its
        node controller stopped: the controller logged nothing, and the launcher took
        the node for cut off, lost 2 s later with no reason. One that had ended on its
        own already is said as it ended, not as stopped."""
        self._forget_ended()
        with self._lock:        # (a start under way holds it: its executor is listed)
            self._closing = True
            entries = dict(self._executors)
        if entries:
            log.warning("node %s: stopping (%s): executors for %s stop", self.name, why,
                        ", ".join(map(repr, entries)))
        else:
            log.info("node %s: stopping (%s)", self.name, why)
        for config, entry in entries.items():
            if self.stop_executor(config, executor=entry.address):
                with self._lock:
                    self._ended[config] = (entry, "was stopped: its node controller "
                                                  f"stopped ({why})")
                    self._untold.add(config)
        with self._told:
            self._told.wait_for(lambda: not self._untold, TELL_S)
        self._sampling.set()
        self._server.close()
