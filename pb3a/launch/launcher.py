"""``Launcher``: the one place that sees every node of a running system.

It splits the plan into node shares and starts one executor per node: in this
process for a node without an ``address`` (the embedded default), through the node
controller at its address otherwise (``RemoteNode``). It wires every link (a link
inside a node by that node; a remote link in halves: published at the writer's
node, followed at the reader's) and applies every change under one global
configuration lock. A watchdog pings every remote node; one that does not answer
for ``LOSS_S`` is declared lost: its modules and their links are dropped, the rest
goes on, and each node's ``env`` module reports it.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from typing import TYPE_CHECKING, Any

from pb3a.errors import ModuleNotFound, RuntimeFailure, RuntimeTimeout
from pb3a.events import EventLog
from pb3a.latencies import percentile
from pb3a.launch.configuration_lock import ConfigurationLock
from pb3a.logbook import LogBook
from pb3a.model.environment import env_name
from pb3a.node.executor import Executor
from pb3a.node.remote import RemoteNode
from pb3a.node.ring_sizes import ring_size
from pb3a.node.workers import REQUEST_TIMEOUT
from pb3a.stats import LinkStats, ModuleStats, NodeReport, NodeStats, SystemStats

if TYPE_CHECKING:
    from collections.abc import Iterator

    from pb3a.config.plan import FlatLink, FlatModule, Plan
    from pb3a.node.protocol import Node

log = logging.getLogger("pb3a.launcher")

HEARTBEAT_S = 0.25      # how often the launcher pings each remote node
LOSS_S = 2.0            # no answer for this long: the node is lost (reported within 3 s)
ENV_EVERY = 4           # heartbeats between two updates of the env modules' node table


class Launcher:
    """Every node's executor, where each module runs, every link; thread-safe."""

    def __init__(self, plan: Plan, *, checkpoint_s: float = 1.0,
                 log_level: int = logging.WARNING) -> None:
        self.plan = plan
        self.checkpoint_s, self.log_level = checkpoint_s, log_level
        self.lock = ConfigurationLock()               # the global configuration lock
        # Stamped on replication and launcher <-> executor messages: frames of an
        # earlier run of a system (a lower epoch) are refused as stale.
        self.epoch = time.time_ns() // 1_000_000
        self.nodes: dict[str, Node] = {}
        self.remotes: dict[str, RemoteNode] = {}      # the nodes that run elsewhere
        self.specs: dict[str, FlatModule] = {}       # every module; its node is spec.node
        self.links: dict[str, FlatLink] = {}
        self.failures: list[str] = []
        self.events = EventLog()                      # what happened, for run.events()
        self.logbook = LogBook()                      # the recent log, for run.logs()
        self._log_seen: dict[str, int] = {}           # remote node -> its last entry merged
        self.handler: Any = None                      # applies agents' requests (op, args)
        self.health: dict[str, dict[str, Any]] = {}   # node -> up, rtt, address
        self.changed = threading.Condition()          # notified when a node's health changes
        self._stopping = threading.Event()
        self._watchdog: threading.Thread | None = None

    # -- nodes ----------------------------------------------------------------------
    def start_nodes(self, callback: str | None) -> None:
        """One executor per node; ``callback`` is where remote executors reach this
        launcher (agents' requests, restarts), needed when any node has an address."""
        logging.getLogger().addHandler(self.logbook)
        # A node started here is reached where the remote nodes reach the launcher.
        here = "127.0.0.1" if callback is None else callback.removeprefix("tcp://").rpartition(":")[0]
        for name, node in self.plan.nodes.items():
            if node.address is None:
                executor = Executor(name, workers=node.workers, cpus=node.cpus,
                                    host=node.advertise or here,
                                    checkpoint_s=self.checkpoint_s, log_level=self.log_level,
                                    code=self.plan.code, lock=self.lock,
                                    epoch=self.epoch)
                executor.handler = self._agent_request
                executor.republished = self.republished
                executor.on_event = self.events.record
                self.nodes[name] = executor
                self.health[name] = {"up": True, "rtt": 0.0, "address": None}
            else:
                assert callback is not None, "remote nodes call the launcher back"
                self.nodes[name] = self.remotes[name] = RemoteNode(
                    name, node.address, config=self.plan.name, launcher=callback,
                    advertise=node.advertise,
                    workers=node.workers, cpus=node.cpus, checkpoint_s=self.checkpoint_s,
                    log_level=self.log_level, code=self.plan.code,
                    epoch=self.epoch)
                self.health[name] = {"up": True, "rtt": float("nan"), "address": node.address,
                                     "controller": True}
        for remote in self.remotes.values():   # the launcher stands for its embedded nodes
            remote.meet({name: self.remotes[name].address if name in self.remotes else callback
                         for name in self.nodes if name != remote.name})
        # (also without remote nodes: it keeps the env modules' view up to date)
        self._watchdog = threading.Thread(target=self._watch, name="pb3a-heartbeat",
                                          daemon=True)
        self._watchdog.start()

    def _agent_request(self, op: str, args: dict[str, Any]) -> Any:
        if self.handler is None:
            raise RuntimeFailure("this system takes no requests from agents")
        return self.handler(op, args)

    def node_of(self, name: str) -> Node:
        """The executor of the node module ``name`` runs on."""
        spec = self.specs.get(name)
        if spec is None:
            known = ", ".join(self.specs) or "(none)"
            raise ModuleNotFound(f"no module {name!r} in system {self.plan.name!r}; "
                                 f"modules: {known}")
        return self.nodes[spec.node]

    def remote(self, link: FlatLink) -> bool:
        """True if the link joins two nodes (it then goes over ZeroMQ)."""
        return self.specs[link.src].node != self.specs[link.dst].node

    # -- modules ----------------------------------------------------------------------
    def expect(self, specs: list[FlatModule]) -> None:
        for name, node in self.nodes.items():
            node.expect([spec for spec in specs if spec.node == name])

    def add_module(self, spec: FlatModule, *, state: dict[str, Any] | None = None) -> None:
        """Instantiate a module on its node (not started)."""
        self.nodes[spec.node].add_module(spec, state=state)
        self.specs[spec.name] = spec

    def call(self, name: str, op: str, timeout: float = REQUEST_TIMEOUT, /,
             **args: Any) -> Any:
        """One request about module ``name`` to its worker, wherever it runs."""
        return self.node_of(name).call_module(name, op, timeout, **args)

    def remove_module(self, name: str) -> None:
        """Stop a module, drop its links, free its process."""
        node = self.node_of(name)
        node.stop_module(name)
        for key in [k for k, link in self.links.items() if name in (link.src, link.dst)]:
            self.disconnect(key)
        node.remove_module(name)
        del self.specs[name]

    @contextlib.contextmanager
    def paused(self, names: list[str], timeout: float = REQUEST_TIMEOUT) -> Iterator[None]:
        """Hold the modules' locks (no step, no event) while the block rewires them."""
        held = []
        try:
            for name in dict.fromkeys(names):
                if name in self.specs and self.node_of(name).pause(name, timeout):
                    held.append(name)
            yield
        finally:
            for name in reversed(held):
                if name in self.specs:
                    self.node_of(name).resume(name)

    # -- links ------------------------------------------------------------------------
    def connect(self, link: FlatLink) -> None:
        """Add and wire a link."""
        self.links[link.key] = link
        self.attach(link)

    def attach(self, link: FlatLink) -> None:
        """Wire a known link where its ends run now: shared memory or in memory inside a
        node; across nodes, the reader's ring first, then the writer publishes, then
        the reader follows (so nothing published is missed)."""
        if not self.remote(link):
            self.node_of(link.src).connect(link)
            return
        reader, writer = self.node_of(link.dst), self.node_of(link.src)
        reader.open_inbound(link, ring_size(self.specs[link.src].cls, link.src_port,
                                            link.policy))
        reader.follow(link, writer.publish(link))

    def detach(self, link: FlatLink) -> None:
        """Unwire a link (it stays known): the writer stops first, then the reader takes
        in everything still on the way."""
        if not self.remote(link):
            self.node_of(link.src).detach(link)
            return
        reached = self.node_of(link.src).unpublish(link)
        self.node_of(link.dst).close_inbound(link, reached)

    def disconnect(self, key: str) -> None:
        """Unwire a link and forget it."""
        self.detach(self.links[key])
        del self.links[key]

    def republished(self, link: FlatLink, endpoint: tuple[str, str, bytes]) -> None:
        """A restarted writer publishes ``link`` anew: its reader follows the new sender."""
        with self.lock.held(f"follow the restarted writer of {link.key}"):
            if self.links.get(link.key) == link and link.dst in self.specs:
                self.node_of(link.dst).follow(link, endpoint)

    # -- figures ----------------------------------------------------------------------
    def stats(self) -> SystemStats:
        """Every node's report, joined: modules where the launcher says they run, the
        per-link table (from the reader's side), failures, node health."""
        reports: list[NodeReport] = []
        for name, node in list(self.nodes.items()):
            if not self.health[name]["up"]:
                continue
            try:
                reports.append(node.report())
            except (RuntimeFailure, RuntimeTimeout) as exc:
                log.warning("node %s did not report: %s", name, exc)   # its modules: absent
        # a module being migrated is on two nodes for a moment: the launcher says where
        modules = {name: entry for report in reports for name, entry in report.modules.items()
                   if name in self.specs and entry.node == self.specs[name].node}
        failures = [*self.failures, *(f for report in reports for f in report.failures)]
        return SystemStats(self.plan.name, modules, _link_table(self.links, modules, reports),
                           self.node_table(), failures)

    def node_table(self) -> dict[str, NodeStats]:
        """Every node's health as the heartbeats see it."""
        return {name: NodeStats(health["up"], health["rtt"], health["address"],
                                health.get("controller"))
                for name, health in self.health.items()}

    # -- heartbeats -------------------------------------------------------------------
    def _watch(self) -> None:
        remotes = self.remotes
        last = dict.fromkeys(remotes, time.monotonic())
        beats = 0
        while not self._stopping.wait(HEARTBEAT_S):
            for name, node in remotes.items():
                if not self.health[name]["up"]:
                    continue
                rtt = node.ping(timeout=HEARTBEAT_S * 2)
                if rtt is not None:
                    last[name] = time.monotonic()
                    self.health[name]["rtt"] = rtt
                elif time.monotonic() - last[name] > LOSS_S and not self._stopping.is_set():
                    self._lose(name, time.monotonic() - last[name])
            beats += 1
            if beats % ENV_EVERY == 0:
                for name, node in remotes.items():
                    if self.health[name]["up"]:
                        self.health[name]["controller"] = node.controller_answers(HEARTBEAT_S)
                        self._merge_log(name, node)
                self.update_env()

    def _merge_log(self, name: str, node: RemoteNode) -> None:
        """Take in what node ``name`` logged since the last look."""
        with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
            for entry in node.logs(self._log_seen.get(name, 0)):
                self._log_seen[name] = entry.seq
                self.logbook.add(entry.time, entry.level, entry.logger, entry.message,
                                 name, entry.module)

    def _lose(self, node: str, silent_s: float) -> None:
        """Declare ``node`` lost: every call to it fails at once from now on; its modules
        and their links are dropped; the env modules say so."""
        self.remotes[node].lose()
        with self.changed:
            self.health[node]["up"] = False
            self.changed.notify_all()
        gone = sorted(name for name, spec in self.specs.items() if spec.node == node)
        self.failures.append(f"node {node} lost (no heartbeat for {silent_s:.1f} s); its "
                             f"modules {', '.join(gone) or '(none)'} are gone")
        log.error(self.failures[-1])
        self.events.record("node_lost", node, modules=gone, silent_s=silent_s)
        with self.lock.held(f"drop lost node {node}"):
            for key, link in list(self.links.items()):
                if link.src in gone or link.dst in gone:
                    with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
                        self._drop_half(link, gone)
                    del self.links[key]
            for name in gone:
                del self.specs[name]
            self.update_env()

    def _drop_half(self, link: FlatLink, gone: list[str]) -> None:
        """Unwire the surviving half of a link whose other end was on a lost node."""
        if link.src in gone and link.dst not in gone:
            self.node_of(link.dst).close_inbound(link)
        elif link.dst in gone and link.src not in gone:
            self.node_of(link.src).unpublish(link)

    def update_env(self) -> None:
        """Tell every node's env module (as its state) the health of every node and its
        round-trip time to each, the node's worker processes (its own load) and the
        moves made so far."""
        moves = [{"module": event.subject, **event.detail} for event in self.events.since(0)
                 if event.kind == "module_moved"]
        for name, node in self.nodes.items():
            env = env_name(name)
            if env not in self.specs or not self.health[name]["up"]:
                continue
            with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
                rtts = self._rtts_from(name)
                table = {peer: {"up": health["up"], "rtt": rtts.get(peer, float("nan"))}
                         for peer, health in self.health.items()}
                self.call(env, "set_state", state={"health": table, "moves": moves,
                                                   "own_pids": node.worker_pids()})

    def _rtts_from(self, name: str) -> dict[str, float]:
        """Round-trip times from node ``name`` to every node: measured by the node itself
        if it is remote; for an embedded node, this process's (it runs here): 0 to the
        other embedded nodes, the heartbeat's to the remote ones."""
        if name in self.remotes:
            return {**self.remotes[name].rtts(), name: 0.0}
        return {peer: self.health[peer]["rtt"] if peer in self.remotes else 0.0
                for peer in self.nodes}

    def wait_health(self, node: str, up: bool, timeout: float) -> bool:
        """Block until ``node`` is (not) up; False on timeout."""
        with self.changed:
            return self.changed.wait_for(lambda: self.health[node]["up"] == up, timeout)

    # -- shutdown ---------------------------------------------------------------------
    def shutdown(self, timeout: float = 10.0) -> None:
        """Stop modules in reverse start order (across nodes), then every node."""
        deadline = time.monotonic() + timeout
        self._stopping.set()
        if self._watchdog is not None:
            self._watchdog.join(2.0)
        with self.lock.held("shut the system down"):
            for name in reversed(list(self.specs)):
                left = max(0.1, deadline - time.monotonic())
                try:
                    self.node_of(name).stop_module(name, min(2.0, left))
                except (RuntimeFailure, RuntimeTimeout) as exc:
                    log.warning("stopping module %r: %s", name, exc)
            for node in reversed(list(self.nodes.values())):
                node.shutdown(max(0.5, deadline - time.monotonic()))
        logging.getLogger().removeHandler(self.logbook)


def _link_table(links: dict[str, FlatLink], modules: dict[str, ModuleStats],
                reports: list[NodeReport]) -> dict[str, LinkStats]:
    """Per link: values, drops, pending, latency, rate, transport, from the reader's node;
    the writes that waited for room, from the writer's."""
    rings = {key: used for report in reports for key, used in report.ring_bytes_used.items()}
    lost = {key: count for report in reports for key, count in report.link_failures.items()}
    table = {}
    for key, link in links.items():
        src, dst = modules.get(link.src), modules.get(link.dst)
        port = dst.inputs.get(link.dst_port) if dst else None
        transport = ("zmq" if src and dst and src.node != dst.node else
                     "memory" if src and dst and src.worker == dst.worker else "shm")
        figures = {} if port is None else {
            "values": port.received, "drops": port.drops, "pending": port.pending,
            "latency": port.latency, "rate": port.rate, "link_failures": port.link_failures,
            "latency_counts": port.latency_counts,
            **{f"latency_p{q}": percentile(port.latency_counts, q) for q in (50, 90, 99)}}
        figures["link_failures"] = figures.get("link_failures", 0) + lost.get(key, 0)
        waits = src.link_waits.get(key) if src else None
        if waits is not None:
            figures.update(waits=waits.waits, wait_s=waits.wait_s)
        table[key] = LinkStats(f"{link.src}.{link.src_port}", f"{link.dst}.{link.dst_port}",
                               str(link.policy), transport, **figures,
                               ring_bytes_used=rings.get(key, 0))
    return table
