"""The executor process of one node share: an ``Executor`` behind an authenticated
control server.

A node controller starts one per configuration on its node; the launcher then
talks to it directly (``RemoteNode``): ``bind`` says where the launcher is, then
every ``executor`` request applies one ``Executor`` operation under the executor's
lock. Agents' requests, restarted writers, events and the checkpoints of
``last-state`` modules go back to the launcher, which keeps the checkpoints off this
node so that it can restart the modules elsewhere when the node is lost.

The launcher holds the executor on a lease, renewed by its heartbeats. When the
lease runs out (the launcher stopped, or a cable was cut) the executor fences
itself: every module stops stepping at once (its workers are signalled, whatever
request holds the executor's lock), each is torn down, and it exits, before the launcher
can have declared the node lost and restarted those modules on another node (the
lease is shorter than the launcher's loss timeout), so two copies of a module never
run at once. The process also exits when told to (``shutdown``), when its controller
stops it (SIGTERM), or when its controller dies (its parent-death pipe closes): it
never outlives its owners.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import threading
import time
from typing import Any

from pb3a.config.description import DEFAULT_SPARES
from pb3a.daemons.executor_family import take_mark
from pb3a.deadline import bounding
from pb3a.errors import RuntimeFailure, RuntimeTimeout
from pb3a.loading.sources import CodeSources
from pb3a.log_format import log_to, name_process
from pb3a.logbook import LogBook
from pb3a.node.class_check import unloadable
from pb3a.node.executor import Executor
from pb3a.node.protocol import REMOTE_OPERATIONS
from pb3a.node.remote import HEARTBEAT_S, LEASE_S
from pb3a.node.restarts import LOCK_TIMEOUT
from pb3a.processes import mark_as, serve_as_child, stop_on_sigterm
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient, ControlServer, TooLarge, UnknownOperation
from pb3a.worker.lease import GONE_BY_S, LeaseBoard
from pb3a.worker.process import agent_wait

log = logging.getLogger("pb3a.node")

PEER_PING_S = 1.0         # how often the round-trip time to each peer is measured
# A launcher not heard from for longer than this (two heartbeats, and one's way) may be
# gone: a second launcher is told how long, and that this executor stops on its own
SILENT_BOUND_S = 2 * HEARTBEAT_S + 0.1
UNBOUND_S = 30.0          # an executor no launcher binds within this stops (the launcher
                          # that had it started went meanwhile: a Ctrl-C, a crash)


class NodeShare:
    """One configuration's share of a node: the handler of its control server."""

    def __init__(self, config: str, node: str, workers: int = 0,
                 cpus: list[int] | None = None, host: str = "127.0.0.1",
                 stopped: threading.Event | None = None, unbound_s: float = UNBOUND_S) -> None:
        self.config, self.node = config, node
        self.key = ClusterKey.load()
        self.executor = Executor(node, workers=workers, cpus=cpus, host=host)
        self.executor.handler = self._agent_request
        self.executor.republished = self._republished
        self.executor.on_event = self._tell_event
        self.executor.on_checkpoint = self._keep_checkpoint
        self.launcher: ControlClient | None = None
        self.node_epoch = 0                            # this admission of the node
        self._lease_s = LEASE_S
        self._leased_at = time.monotonic()             # the launcher's last heartbeat
        self._ticked_at = time.monotonic()             # the lease's watch last looked
        # where the workers read the lease's end themselves (``renew`` writes it)
        self.board = self.executor.workers.settings.lease = LeaseBoard.create()
        self.executor.leased = self._leased
        self._checkpoints: dict[str, bytes] = {}       # the newest, not yet sent
        self._checkpointed = threading.Condition()
        # module -> the smallest of its checkpoints refused as too large to send (bytes)
        self._unsent: dict[str, int] = {}
        self.server: ControlServer | None = None
        self.peers: dict[str, ControlClient] = {}     # other nodes, pinged for their RTT
        self.rtts: dict[str, float] = {}
        self.stopped = stopped if stopped is not None else threading.Event()
        self.logbook = LogBook()                       # the launcher merges it into its own
        logging.getLogger().addHandler(self.logbook)
        self._bound = threading.Event()
        threading.Thread(target=self._await_bind, args=(unbound_s,), daemon=True,
                         name="pb3a-unbound").start()

    def _await_bind(self, unbound_s: float) -> None:
        """Stop unless a launcher binds this executor within ``unbound_s``: no lease
        runs before, and nobody else would stop it."""
        if not self._bound.wait(unbound_s) and not self.stopped.is_set():
            log.error("node %s: no launcher took this executor for %r within %g s: it "
                      "stops", self.node, self.config, unbound_s)
            self.stopped.set()

    def handle(self, op: str, args: dict[str, Any]) -> Any:
        ex = self.executor
        if op == "executor":
            if args["method"] not in REMOTE_OPERATIONS:
                raise ValueError(f"a node executor has no operation {args['method']!r}")
            # (the lock within the launcher's wait: past it, nobody waits for the answer)
            with ex.held(f"{args['method']} from the launcher",
                         args.get("within", LOCK_TIMEOUT)), _bounded(args):
                return getattr(ex, args["method"])(*args["args"], **args["kwargs"])
        if op == "start":       # beside the executor's other requests, without its lock,
            with _bounded(args):    # as on an embedded node: see executor_main
                ex.start_modules(args["names"], args.get("failing", False),
                                 args.get("leave_late", False))
            return None
        if op == "await_restart":   # without the lock too: the restart takes it
            return ex.await_restart(args["name"], args["timeout"])
        if op == "report":          # without the lock too: a look waits for no change
            with _bounded(args):
                return ex.report(args["timeout"])
        if op == "bind":
            return self.bind(args["launcher"], args["checkpoint_s"], args["log_level"],
                      args["code"], args.get("lease_s", LEASE_S), args.get("epoch", 0),
                      args.get("node_epoch", 1), args.get("spares", DEFAULT_SPARES))
        if op == "unloadable":      # before any module: see pb3a.node.class_check
            return unloadable(args["refs"], ex.imports, args["timeout"], args["longer"],
                              ex.workers.settings.code)
        if op == "peers":
            self.meet(args["peers"])
            return None
        if op == "rtts":
            return dict(self.rtts)
        if op == "logs":
            return self.logbook.since(args["since"])
        if op == "describe":
            return {"config": self.config, "node": self.node, "modules": sorted(ex.modules)}
        if op == "shutdown":
            self.stopped.set()
            return None
        raise UnknownOperation(op)

    def bind(self, launcher: str, checkpoint_s: float, log_level: int, code: CodeSources,
             lease_s: float = LEASE_S, epoch: int = 0, node_epoch: int = 1,
             spares: int = DEFAULT_SPARES) -> float:
        """Work for the launcher at ``launcher`` (before any module is added), in its
        system's ``epoch`` (older requests and replication are refused from now on), as
        the node's admission ``node_epoch``, on a lease of ``lease_s`` seconds, keeping
        ``spares`` idle workers booted; the answer is the first renewal's (``renew``)."""
        if self.launcher is not None:
            raise RuntimeFailure(self._already_bound(self.launcher.address))
        # (the lease first: a renewal as soon as bound writes with it, and the ends the
        # board gives only move on, which its workers count on, see Lease.holds)
        self.node_epoch, self._lease_s = node_epoch, lease_s
        self._bound.set()                   # (a slow bind, a large code install: not stopped)
        # the import path before anything imports: the configuration's modules, imported
        # by the preload that configure starts, were found on the path from before
        # (a directory of that name in the controller's, and the check of the launch's
        # classes found that copy, which the workers did not)
        code.install(self.key)
        self.executor.configure(checkpoint_s=checkpoint_s, log_level=log_level, code=code,
                                epoch=epoch, spares=spares, node_epoch=node_epoch)
        if self.server is not None:
            self.server.advance_epoch(epoch)
        self.launcher = ControlClient(self.key, launcher)
        self._ticked_at = time.monotonic()      # (before: the renewal writes a running lease)
        renewed = self.renew()
        for target, name in ((self._keep_lease, "lease"), (self._measure_peers, "peers"),
                             (self._send_checkpoints, "checkpoints")):
            threading.Thread(target=target, name=f"pb3a-{name}", daemon=True).start()
        return renewed

    def _already_bound(self, launcher: str) -> str:
        """Why a second launcher may not bind this executor: the first runs it; or, if
        that one has not been heard from for more than two heartbeats (killed, say), how
        long, and that this executor stops itself once its lease runs out (the launcher
        run again at once was told to stop a system that no longer existed)."""
        silent = time.monotonic() - self._leased_at
        if silent <= SILENT_BOUND_S and not self.stopped.is_set():
            return (f"node {self.node} already works for {launcher}: stop that "
                    "system first, or launch this one under another name")
        return (f"node {self.node} already works for {launcher}, last heard "
                f"from {silent:.1f} s ago: if that launcher is gone (killed, or cut off), "
                f"its executor here stops itself once its lease runs out ({self._lease_s:g} s "
                "without it): try again in a moment")

    def renew(self, args: dict[str, Any] | None = None) -> float:
        """The launcher's heartbeat (an instant operation): the lease runs on, dated from
        ``since`` (the newest of these answers the launcher had heard as it renewed: this
        process's clock) plus a heartbeat's way, not from now. A renewal read late (a slow
        downlink, this process starved) ran the lease past the end the launcher counts
        on (``RemoteNode.fenced_by``), and a module stepped on beside its failed-over
        copy. The answer is now, the next renewal's ``since``. The workers read the new
        end at once (``board``), while the lease runs: the end of one that ran out, or
        of an executor that was frozen past it, is not moved on for them."""
        now = time.monotonic()
        since = (args or {}).get("since")
        start = now if since is None else min(now, since + HEARTBEAT_S)
        if start > self._leased_at:
            self._leased_at = start
            if self._bound.is_set() and self._leased():    # (none before a bind)
                self.board.write(start + self._lease_s)
        return now

    def meet(self, peers: dict[str, str]) -> None:
        """Measure the round-trip time to each other node (name -> control address) from
        now on; the launcher stands for the nodes embedded in it."""
        for client in self.peers.values():
            client.close()
        self.peers = {name: ControlClient(self.key, address, epoch=self.executor.epoch)
                      for name, address in peers.items()}
        self.rtts = {}

    def _agent_request(self, op: str, args: dict[str, Any]) -> Any:
        if self.launcher is None:
            raise RuntimeFailure(f"node {self.node} has no launcher to ask")
        return self.launcher.call("agent", agent_wait(args.get("timeout")), request=op,
                                  args=args, **self._signed())

    def _signed(self) -> dict[str, Any]:
        """What the launcher checks before it takes anything from this executor: an
        executor of an earlier admission of the node was fenced, and is refused."""
        return {"node": self.node, "node_epoch": self.node_epoch}

    def _keep_checkpoint(self, module: str, state: bytes) -> None:
        """A module's newest checkpoint, for the launcher (only the newest is sent)."""
        with self._checkpointed:
            self._checkpoints[module] = state
            self._checkpointed.notify()

    def _send_checkpoints(self) -> None:
        """Send each module's newest checkpoint to the launcher. One too large for a
        control message is not kept there, which is said once (again only if one was
        sent since); and one no smaller than a checkpoint of that module refused is
        refused without being made into a request: its request carries its bytes whole
        beside what every one of the module's carries (its name, the node's, the node's
        epoch), so it is at least as large. A module whose state outgrew a message
        (80 MiB) was pickled whole into a request at every checkpoint, only to be
        refused, on this executor's CPU, which its heartbeats' answers need. A smaller
        one is tried, and sent once it fits."""
        while not self.stopped.is_set():
            with self._checkpointed:
                self._checkpointed.wait_for(lambda: self._checkpoints or self.stopped.is_set(),
                                            1.0)
                pending, self._checkpoints = self._checkpoints, {}
            for module, state in pending.items():
                if len(state) >= self._unsent.get(module, math.inf):
                    continue                            # (it would be refused again)
                try:
                    self._call_launcher("checkpoint", module=module, state=state)
                except TooLarge as exc:   # (said once: it is refused the same each time)
                    if module not in self._unsent:
                        log.warning("module %s's checkpoints are not kept by the launcher "
                                    "(%s): if node %s is lost, the module starts afresh "
                                    "where it fails over", module, exc, self.node)
                    self._unsent[module] = len(state)   # (smaller than any refused before)
                else:
                    self._unsent.pop(module, None)

    def _republished(self, link: Any, endpoint: tuple[str, str, bytes]) -> None:
        self._tell_launcher("republished", link=link, endpoint=endpoint)

    def _tell_event(self, kind: str, subject: str, **detail: Any) -> None:
        """A restart or failure here goes into the launcher's events."""
        self._tell_launcher("event", kind=kind, subject=subject, detail=detail)

    def _tell_launcher(self, op: str, **args: Any) -> None:
        """Tell the launcher what a restart did, from another thread: a restart runs
        under the executor's lock, which the launcher may be waiting for."""
        threading.Thread(target=self._call_launcher, args=(op,), kwargs=args,
                         name=f"pb3a-{op}", daemon=True).start()

    def _call_launcher(self, op: str, **args: Any) -> None:
        """Call the launcher, which may be gone or cut off (what it misses, it asks for
        again or does without); a request too large to send raises ``TooLarge``."""
        if self.launcher is not None:
            try:
                self.launcher.call(op, **args, **self._signed())
            except TooLarge:
                raise
            except (RuntimeFailure, RuntimeTimeout):
                pass

    def _leased(self) -> bool:
        """Whether this executor's lease runs now: renewed within the lease, and its watch
        not held up as long (this process frozen: the heartbeats it then reads late,
        queued while it was stopped, renew nothing the launcher still counts on)."""
        if not self._bound.is_set():
            return not self.stopped.is_set()    # no lease before a launcher binds it
        now = time.monotonic()
        return (not self.stopped.is_set() and now - self._leased_at <= self._lease_s
                and now - self._ticked_at <= self._lease_s)

    def _keep_lease(self) -> None:
        """Fence: stop everything once the launcher's heartbeats stop for the lease, or
        once this process was frozen (stopped, starved) that long: the launcher may have
        failed its modules over meanwhile, whatever heartbeats were queued for it."""
        lease_s = self._lease_s
        while not self.stopped.wait(min(0.1, lease_s / 4)):
            now = time.monotonic()
            silent, held_up = now - self._leased_at, now - self._ticked_at
            if silent > lease_s or held_up > lease_s:
                # (its watch's last look stays where it was: until ``stopped`` is set, a
                # heartbeat read late, queued while it was frozen, renewed the lease for
                # its grants and restarts, after the watch had seen the freeze)
                why = (f"no heartbeat from the launcher for {silent:.1f} s" if silent > lease_s
                       else f"it was frozen for {held_up:.1f} s")
                # (the lease to its last digit: "%.1f" said 1.25 s was 1.2 s)
                log.error("node %s: %s (its lease is %g s): fenced, its modules stop",
                          self.node, why, lease_s)
                # at once (shutting down may wait for a request), its workers gone by the
                # time the launcher may start their modules elsewhere
                self.executor.fence(gone_by=self._leased_at + lease_s + GONE_BY_S)
                self.stopped.set()
            else:
                self._ticked_at = now

    def _measure_peers(self) -> None:
        """Ping every peer now and then: the round-trip times the env module shows."""
        while not self.stopped.wait(PEER_PING_S):
            for name, client in list(self.peers.items()):
                rtt = client.ping(PEER_PING_S)
                if rtt is not None:
                    self.rtts[name] = rtt

    def close(self) -> None:
        self.executor.shutdown()
        for client in [*self.peers.values(), *filter(None, [self.launcher])]:
            client.close()
        self.board.close()


def _bounded(args: dict[str, Any]) -> contextlib.AbstractContextManager[Any]:
    """The deadline a launcher's request carries (``bound``: seconds, when a call of its
    is bounded, a move say), for every wait it makes here; none without."""
    bound = args.get("bound")
    return contextlib.nullcontext() if bound is None else bounding(bound)


def executor_main(config: str, node: str, workers: int, cpus: list[int] | None,
                  host: str, conn: Any, level: int = logging.WARNING,
                  unbound_s: float = UNBOUND_S, mark: str | None = None) -> None:
    """Entry point of an executor process: serve until shut down, signalled or orphaned.
    ``mark``: its family's (``executor_family``), handed to every process it starts."""
    if mark is not None:
        take_mark(mark)
    name_process(f"executor {config}", node)        # its log lines: [executor CONFIG@NODE]
    log_to(sys.stderr, level)
    mark_as("a node's executor")
    stopped = threading.Event()
    stop_on_sigterm(stopped)            # before anything that must be closed
    share = NodeShare(config, node, workers, cpus, host, stopped, unbound_s)
    server = share.server = ControlServer(share.key, share.handle, host,
                                          name="pb3a-node-executor",
                                          instant={"lease": share.renew},
                                          # setup may ask the launcher about this node,
                                          # which asks this executor, and a restart
                                          # waited for takes its lock, and a report
                                          # waits for no change: not in one lane
                                          aside={"start", "await_restart", "report"},
                                          decode_lock=share.executor.imports.lock,
                                          title=f"node {node}'s executor for {config!r}")
    try:
        serve_as_child(conn, server.address, share.stopped)
    finally:
        server.close()
        share.close()
