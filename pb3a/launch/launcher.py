"""``Launcher``: the one place that sees every node of a running system.

It splits the plan into node shares and starts one executor per node: in this
process for a node without an ``address`` (the embedded default), through the node
controller at its address otherwise (``RemoteNode``). It wires every link (a link
inside a node by that node; a remote link in halves: published at the writer's
node, followed at the reader's) and applies every change under one global
configuration lock.

The loss of a remote node, its modules' failover and its rejoin are ``Failover``'s
(``failover.py``), and what the env modules are told is ``EnvKeeper``'s
(``env_keeper.py``): both act on the launcher from above; their threads run in the
launcher's background, joined as it shuts down.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import logging
import math
import threading
import time
from typing import TYPE_CHECKING, Any

from pb3a.config.checks import did_you_mean
from pb3a.deadline import bounding, lifted
from pb3a.errors import ModuleNotFound, RuntimeFailure, RuntimeTimeout
from pb3a.events import EventLog
from pb3a.latencies import percentile
from pb3a.launch.configuration_lock import ConfigurationLock, change_to
from pb3a.launch.remote_starts import RemoteStarts, not_started
from pb3a.loading.references import by_reference, class_ref
from pb3a.logbook import LogBook
from pb3a.model.environment import PREFIX as ENV_PREFIX
from pb3a.model.module import fixed_rate_of, stepped_period
from pb3a.node.bridge import NoHandshake
from pb3a.node.executor import REPORT_TIMEOUT, Executor
from pb3a.node.remote import (
    HEARTBEAT_S,
    LOSS_S,
    ON_THEIR_OWN,
    SILENT_S,
    STOP_AT_LEAST_S,
    RemoteNode,
)
from pb3a.node.ring_sizes import ring_size
from pb3a.node.workers import REQUEST_TIMEOUT
from pb3a.stats import FailureLog, LinkStats, ModuleStats, NodeReport, NodeStats, SystemStats
from pb3a.transport.addresses import host_of

if TYPE_CHECKING:
    from collections.abc import Iterator

    from pb3a.config.plan import FlatLink, FlatModule, Plan
    from pb3a.node.protocol import Endpoint, Node, Reached

log = logging.getLogger("pb3a.launcher")

WATCH_S = 0.1           # how often the watchdog looks at the nodes' heartbeats
STOP_TIMEOUT = 5.0      # a module's teardown when it is removed
# A removal with ``force`` of a module that did not answer its stop: what its worker's
# kill, its links' unwiring and its drop may take past the call's deadline (a few ms)
KILLED_REMOVAL_S = 2.0
# how to give a launch's slow steps more time (the nodes' starts, their classes' check)
LAUNCH_LONGER = ("give the system a longer timeout (timeout = SECONDS at the top of its "
                 "file, or launch(timeout=...))")


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
        self.failures = FailureLog(log)
        self.checkpoints: dict[str, bytes] = {}      # module -> its newest (last-state)
        self.lost_values: collections.Counter[str] = collections.Counter()  # per link key
        self.arriving: dict[str, str] = {}            # module -> the node a move lands it on
        self.unconfirmed: list[str] = []    # remote nodes whose stop was not confirmed
        # remote node -> the modules there whose stop did not reach it (cut off, frozen,
        # lost): each stops on its own as the node's lease runs out, unconfirmed
        self.unreached: dict[str, list[str]] = {}
        # What a shutdown has done, so that one interrupted (a Ctrl-C) is finished by the
        # next: the modules it has stopped or given up on, the nodes it has shut down,
        # and the threads shutting the remote ones down
        self._given_up: list[str] = []      # modules that did not stop at shutdown
        self._settled: set[str] = set()
        self._shut: set[str] = set()
        self._shutting: dict[str, threading.Thread] = {}
        self._shut_down = False             # a shutdown has run to its end
        self._callback: str | None = None            # where remote executors reach us
        self.events = EventLog()                      # what happened, for run.events()
        self.logbook = LogBook()                      # the recent log, for run.logs()
        self.handler: Any = None                      # applies agents' requests (op, args)
        self.health: dict[str, dict[str, Any]] = {}   # node -> up, rtt, address
        # node -> the last report it gave in time, and the admission that gave it (a
        # node admitted again shows nothing of the one before)
        self._last_reports: dict[str, tuple[RemoteNode | None, NodeReport]] = {}
        self.changed = threading.Condition()          # notified when a node's health changes
        self.stopping = threading.Event()             # set as the shutdown begins
        # threads that act on the system on their own (the env keeper; the watchdog and
        # each failover): joined as it shuts down
        self._background: list[threading.Thread] = []

    # -- nodes ----------------------------------------------------------------------
    def start_nodes(self, callback: str | None, timeout: float) -> None:
        """One executor per node; ``callback`` is where remote executors reach this
        launcher (agents' requests, restarts), needed when any node has an address.

        The remote nodes' controllers start their executors side by side
        (``RemoteStarts``), within about ``timeout`` seconds: one after another, ten
        robots paid each one's start in turn, and the first that did not answer ended
        the launch (5 s later) naming it alone. One error names every node that did not
        start one (a single node's own error as it was); the executors that did
        start are left in ``nodes`` for the shutdown that follows to stop."""
        logging.getLogger().addHandler(self.logbook)
        self._callback = callback
        # A node started here is reached where the remote nodes reach the launcher.
        here = "127.0.0.1" if callback is None else host_of(callback)
        remote = [name for name, node in self.plan.nodes.items() if node.address is not None]
        assert callback is not None or not remote, "remote nodes call the launcher back"
        starts = RemoteStarts(self.start_remote_node, remote,
                              {name: str(self.plan.nodes[name].address) for name in remote},
                              timeout, LAUNCH_LONGER)
        embedded: dict[str, Executor] = {}
        try:
            for name, node in self.plan.nodes.items():    # (meanwhile, on this thread)
                if node.address is None:
                    embedded[name] = self._embedded_executor(name, here)
        finally:
            started: dict[str, RemoteNode] = {}
            try:
                started, failures = starts.settle()
            finally:
                # in the plan's order, as they were started before: a shutdown stops
                # them in reverse. (A settle a Ctrl-C cut short stopped the remote
                # executors it had: the embedded ones are the close's, their spare
                # workers left to the process's exit before)
                for name, node in self.plan.nodes.items():
                    if name in embedded:
                        self.nodes[name] = embedded[name]
                        self.health[name] = {"up": True, "rtt": 0.0, "address": None,
                                             "epoch": 1}
                    elif name in started:
                        self.nodes[name] = self.remotes[name] = started[name]
                        self.health[name] = {"up": True, "rtt": float("nan"),
                                             "address": node.address, "controller": True,
                                             "epoch": 1}
        if failures:
            raise not_started(self.plan.name, len(remote), failures)
        self.introduce()

    def _embedded_executor(self, name: str, here: str) -> Executor:
        """The executor of node ``name``, which has no address: it runs in this process,
        reached by the other nodes at ``here`` (unless it advertises a host)."""
        node = self.plan.nodes[name]
        executor = Executor(name, workers=node.workers, cpus=node.cpus,
                            host=node.advertise or here,
                            checkpoint_s=self.checkpoint_s, log_level=self.log_level,
                            code=self.plan.code, lock=self.lock,
                            epoch=self.epoch, spares=node.spares)
        executor.handler = self._agent_request
        executor.republished = functools.partial(self.republished, node=name)
        executor.on_event = self.events.record
        executor.on_checkpoint = self.checkpoints.__setitem__
        return executor

    def check_classes(self, timeout: float) -> None:
        """Have every remote node load the classes of the modules it is to run, all nodes
        side by side, before any module is added anywhere: ``RuntimeFailure`` naming
        each class some node cannot load (the node, the module, the class, why and what
        to do), within ``timeout`` seconds. It was found as the first node that could
        not read a request naming one, in words that named no module and no file, and
        one that hung held the launch up for a minute. The embedded nodes run in this
        process, which loaded every class as the plan was made: they are not asked."""
        asked = {node: {spec.name: class_ref(spec.cls) for spec in self.plan.modules.values()
                        if spec.node == node and by_reference(spec.cls)}
                 for node in self.remotes}
        answers: dict[str, dict[str, str]] = {}

        def ask(node: str) -> None:
            try:
                answers[node] = self.remotes[node].unloadable(asked[node], timeout,
                                                              LAUNCH_LONGER)
            except (RuntimeFailure, RuntimeTimeout) as exc:
                answers[node] = {"": f"it did not say whether it loads them: {exc}"}

        threads = [threading.Thread(target=ask, args=(node,), name=f"pb3a-classes-{node}",
                                    daemon=True) for node, refs in asked.items() if refs]
        for thread in threads:
            thread.start()
        for thread in threads:      # (each call is bounded by ``timeout``: this is slack)
            thread.join(timeout + 1.0)
        problems, classes, silent_nodes = [], 0, 0
        for node, refs in asked.items():
            silent = {"": f"it did not answer within {timeout:g} s"} if refs else {}
            for name, why in answers.get(node, silent).items():
                address = self.plan.nodes[node].address
                classes += bool(name)
                silent_nodes += not name
                problems.append(
                    f"node {node} ({address}): {why}" if not name else
                    f"node {node} ({address}): module {name!r}, class {refs[name]!r}: {why}")
        if problems:
            parts = []
            if classes:
                parts.append("1 class cannot be loaded on the node that runs it" if classes == 1
                             else f"{classes} classes cannot be loaded on the nodes that run "
                             "them")
            if silent_nodes:
                parts.append("1 node did not say whether it loads its classes"
                             if silent_nodes == 1 else f"{silent_nodes} nodes did not say "
                             "whether they load their classes")
            which = ", and ".join(parts)
            raise RuntimeFailure("\n  ".join([
                f"system {self.plan.name!r} was not started: {which} (no module was "
                "started):", *problems]))

    def start_remote_node(self, name: str, node_epoch: int) -> RemoteNode:
        """Have node ``name``'s controller start an executor for this system."""
        node = self.plan.nodes[name]
        assert node.address is not None and self._callback is not None
        return RemoteNode(name, node.address, config=self.plan.name, launcher=self._callback,
                          advertise=node.advertise, workers=node.workers, cpus=node.cpus,
                          checkpoint_s=self.checkpoint_s, log_level=self.log_level,
                          code=self.plan.code, epoch=self.epoch, node_epoch=node_epoch,
                          spares=node.spares)

    def introduce(self) -> None:
        """Tell every remote node where its peers are (for their round-trip times); the
        launcher stands for its embedded nodes."""
        for remote in self.remotes.values():
            if not remote.lost:
                with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
                    remote.meet({name: self.remotes[name].address if name in self.remotes
                                 else self._callback for name in self.nodes
                                 if name != remote.name})

    def start_background(self, thread: threading.Thread) -> None:
        """Start ``thread``, which acts on the system on its own until ``stopping`` is
        set: the shutdown waits for it (2 s at most) before it stops anything."""
        # (listed once started: one a Ctrl-C left unstarted failed the shutdown's join,
        # "cannot join thread before it is started", exit 1 and a traceback)
        thread.start()
        self._background = [*(t for t in self._background if t.is_alive()), thread]

    def check_node_epoch(self, node: str, node_epoch: int) -> None:
        """Refuse what an executor of an earlier admission of ``node`` says: it was
        fenced when the node was lost."""
        current = self.health.get(node, {}).get("epoch")
        if node_epoch != current or not self.health[node]["up"]:
            raise RuntimeFailure(f"stale: node {node}'s executor of epoch {node_epoch} was "
                                 f"fenced; the node's epoch is {current}"
                                 f"{'' if self.health.get(node, {}).get('up') else ' (lost)'}")

    def _agent_request(self, op: str, args: dict[str, Any]) -> Any:
        if self.handler is None:
            raise RuntimeFailure("this system takes no requests from agents")
        return self.handler(op, args)

    def node_of(self, name: str) -> Node:
        """The executor of the node module ``name`` runs on."""
        spec = self.specs.get(name)
        if spec is None:
            raise ModuleNotFound(f"no module {name!r} in system {self.plan.name!r}; "
                                 + self.which_modules(name))
        return self.nodes[spec.node]

    def which_modules(self, name: str) -> str:
        """What to name instead of ``name``, which no module has: a macro instance's
        modules (a link may name its exports, but reading or changing one module names
        it by its path); for an ``env-NODE`` module, how to start it
        (a link reading it does) or that there is no such node; else every module."""
        names = list(self.specs)            # (one copy: a read may ask during a change)
        inner = [module for module in names if module.startswith(f"{name}/")]
        if inner:
            return f"it is a macro instance: name one of its modules, {', '.join(inner)}"
        modules = f"modules: {', '.join(names) or '(none)'}{did_you_mean(name, names)}"
        if name.startswith(ENV_PREFIX):
            node = name[len(ENV_PREFIX):]
            if node not in self.plan.nodes:
                return (f"there is no node {node!r} (nodes: {', '.join(self.plan.nodes)}); "
                        f"{modules}")
            return (f"it is node {node}'s env module, which runs once a link reads it "
                    f'(at launch, or linked since), or added: run.add("{name}", '
                    f'pb3a.Environment, node="{node}") (pb3a add ADDR {name} '
                    f"pb3a:Environment --node {node}); {modules}")
        return modules

    def crosses_nodes(self, link: FlatLink) -> bool:
        """True if the link joins two nodes (it then goes over ZeroMQ)."""
        return self.specs[link.src].node != self.specs[link.dst].node

    # -- modules ----------------------------------------------------------------------
    def expect(self, specs: list[FlatModule]) -> None:
        for name, node in self.nodes.items():
            node.expect([spec for spec in specs if spec.node == name])

    def add_module(self, spec: FlatModule, *,
                   state: dict[str, Any] | bytes | None = None) -> None:
        """Instantiate a module on its node (not started); ``state`` as for
        ``Node.add_module``."""
        self.nodes[spec.node].add_module(spec, state=state)
        self.specs[spec.name] = spec

    def call(self, name: str, op: str, timeout: float = REQUEST_TIMEOUT, /,
             **args: Any) -> Any:
        """One request about module ``name`` to its worker, wherever it runs."""
        return self.node_of(name).call_module(name, op, timeout, **args)

    def remove_module(self, name: str, *, force: bool = False,
                      restarting: bool = False) -> int | None:
        """Stop a module, drop its links, free its process. One that does not answer its
        stop in time (frozen in ``step`` or ``teardown``) is left as it was, and
        ``RuntimeTimeout`` says so and names ``force``; with ``force`` its worker is
        killed instead (``Node.kill_module``: refused, the module left as it was, if the
        worker runs others), and the rest of the removal is given ``KILLED_REMOVAL_S``
        past the deadline of the call, which the stop used up. The killed worker's
        process id, None if the module stopped. ``restarting``: the module is started
        again next, so it stays in ``specs`` meanwhile (a look at the system between the
        two left it out: ``stats`` did not list it)."""
        node = self.node_of(name)
        killed = None
        try:
            node.stop_module(name, STOP_TIMEOUT)
        except RuntimeTimeout as exc:
            if not force:
                asked = "restart" if restarting else "remove"
                raise RuntimeTimeout(
                    f"{exc}; module {name} was left as it was: {asked}({name!r}, "
                    f"force=True) (`pb3a {asked} ADDR {name} --force`) kills its worker "
                    "if it does not answer") from None
            with lifted(), bounding(KILLED_REMOVAL_S):
                try:
                    killed = node.kill_module(name)
                except RuntimeFailure as refused:
                    raise RuntimeFailure(f"{'restart' if restarting else 'remove'} {name} "
                                         f"with force: {exc}; {refused}") from None
                self._drop_stopped(name, node, restarting)
            return killed
        self._drop_stopped(name, node, restarting)
        return killed

    def _drop_stopped(self, name: str, node: Node, restarting: bool = False) -> None:
        """The end of a removal, the module stopped: its links unwired, then the module
        dropped from its node and from the system (but for its spec, if ``restarting``)."""
        for key in [k for k, link in self.links.items() if name in (link.src, link.dst)]:
            self.disconnect(key)
        node.remove_module(name)
        if not restarting:
            del self.specs[name]
        self.checkpoints.pop(name, None)

    @contextlib.contextmanager
    def paused(self, names: list[str], timeout: float = REQUEST_TIMEOUT) -> Iterator[None]:
        """Hold the modules' locks (no step, no event) while the block rewires them. A
        body waiting in a runtime call is held there, not cancelled: an agent's request
        to move or relink a module it writes to paused the agent, its writer, which
        cancelled that very request (the change went on)."""
        held = []
        try:
            for name in dict.fromkeys(names):
                if name in self.specs and self.node_of(name).pause(name, timeout, rewire=True):
                    held.append(name)
            yield
        finally:        # each on its own: one on a node lost meanwhile stops none
            for name in reversed(held):   # of the others from being resumed
                if name in self.specs:
                    try:
                        self.node_of(name).resume(name)
                    except (RuntimeFailure, RuntimeTimeout) as exc:
                        log.warning("module %s not resumed after a pause: %s", name, exc)

    # -- links ------------------------------------------------------------------------
    def reattach(self, links: list[FlatLink], when: str) -> None:
        """Wire each of ``links`` again on its own: one that cannot be (an end on a node
        lost meanwhile) is a failure of the system, logged, and keeps none of the others
        from being wired."""
        for link in links:
            try:
                self.attach(link)
            except (RuntimeFailure, RuntimeTimeout) as exc:
                self.failures.add(f"link {link.key} not wired again {when}: {exc}")

    def connect(self, *links: FlatLink) -> None:
        """Add and wire links (those inside one node in one request to it). A new link's
        figures are its own: what a link of the same name lost before is forgotten."""
        for link in links:
            if link.key not in self.links:
                self.lost_values.pop(link.key, None)
            self.links[link.key] = link
        self.attach(*links)

    def attach(self, *links: FlatLink) -> None:
        """Wire known links where their ends run now: shared memory or in memory inside
        a node, one request to the node for all of its own; across nodes, the readers'
        rings first, then the writers publish, then the readers follow (so nothing
        published is missed), one request to a node for each of the three steps."""
        for node, inside in self._by_node(links, "src", remote=False).items():
            self.nodes[node].connect(inside)
        readers = self._by_node(links, "dst", remote=True)
        for node, inbound in readers.items():
            self.nodes[node].open_inbound([
                (link, ring_size(self.specs[link.src].cls, link.src_port, link.policy))
                for link in inbound])
        endpoints: dict[str, Endpoint] = {}
        for node, outbound in self._by_node(links, "src", remote=True).items():
            endpoints.update(zip([link.key for link in outbound],
                                 self.nodes[node].publish(outbound), strict=True))
        for node, inbound in readers.items():      # (a writer that restarts: when it has)
            try:
                self.nodes[node].follow([(link, endpoints[link.key]) for link in inbound
                                         if endpoints[link.key] is not None])
            except NoHandshake as exc:
                raise NoHandshake(self._unreached(node, inbound, exc)) from None

    def _unreached(self, node: str, inbound: list[FlatLink], exc: NoHandshake) -> str:
        """What to do when ``node`` could not follow the senders of ``inbound``: it said
        which address had no hand-shake, not which nodes, nor what to open or set."""
        senders = sorted({self.specs[link.src].node for link in inbound} - {node})
        whose = " and ".join(senders)
        tables = ", ".join(f"[nodes.{sender}]" for sender in senders)
        return (f"node {node}: {exc}: node {node} does not reach where {whose} "
                f"publish{'es' if len(senders) == 1 else ''}; open the ephemeral ports of "
                f"{whose} to {node}, or set advertise in {tables} to an address {node} "
                "reaches there")

    def detach(self, *links: FlatLink) -> None:
        """Unwire links (they stay known): each writer stops first, then its reader
        takes in everything still on the way; one request to a node for all the links
        inside it, and one for each step of those that cross to another."""
        for node, inside in self._by_node(links, "src", remote=False).items():
            self.nodes[node].detach(inside)
        reached: dict[str, Reached] = {}
        for node, outbound in self._by_node(links, "src", remote=True).items():
            reached.update(zip([link.key for link in outbound],
                               self.nodes[node].unpublish(outbound), strict=True))
        for node, inbound in self._by_node(links, "dst", remote=True).items():
            self.nodes[node].close_inbound([(link, reached[link.key]) for link in inbound])

    def _by_node(self, links: tuple[FlatLink, ...], end: str,
                 *, remote: bool) -> dict[str, list[FlatLink]]:
        """The links that cross nodes (``remote``) or stay inside one, by the node of
        their ``end`` (``"src"`` or ``"dst"``)."""
        found: dict[str, list[FlatLink]] = {}
        for link in links:
            if self.crosses_nodes(link) == remote:
                found.setdefault(self.specs[getattr(link, end)].node, []).append(link)
        return found

    def disconnect(self, key: str) -> None:
        """Unwire a link and forget it."""
        self.detach(self.links[key])
        del self.links[key]

    def republished(self, link: FlatLink, endpoint: Endpoint, node: str) -> None:
        """A writer restarted on ``node`` publishes ``link`` anew: its reader follows the
        new sender, if the writer still runs there and the link still crosses nodes. (A
        remote node says so once the configuration lock is free: a move that held it
        meanwhile may have taken the writer elsewhere, or the reader to the writer's
        node; following this sender then stopped the values from where it runs now.)"""
        with self.lock.held(f"follow the restarted writer of {link.key}"):
            if (self.links.get(link.key) == link and link.src in self.specs
                    and link.dst in self.specs and self.specs[link.src].node == node
                    and self.crosses_nodes(link)):
                self.node_of(link.dst).follow([(link, endpoint)])

    # -- figures ----------------------------------------------------------------------
    def stats(self, timeout: float = REPORT_TIMEOUT) -> SystemStats:
        """Every node's report, joined: modules where the launcher says they run, the
        per-link table (from the reader's side), failures, node health; within
        ``timeout``, a node whose report has not come by then left out.

        Read without the configuration lock (a long change held every look at a stuck
        system until it ended): from a copy of the launcher's tables taken first, each
        module in it shown once, with the change in progress that acts on it, if any
        (``ModuleStats.change``). A module is shown where that copy has it: one mid-move
        with the figures of whichever node has it, or silent (between two nodes'
        reports; as a module whose lost node a failover is leaving)."""
        changing = self.lock.changing()
        specs, links = dict(self.specs), dict(self.links)    # (one copy each, atomic)
        reports = self._reports(timeout, specs)
        changing |= self.lock.changing()      # (and a change begun since: it may be mid-way)
        found: dict[str, list[ModuleStats]] = {}
        for report in reports.values():
            for name, entry in report.modules.items():
                found.setdefault(name, []).append(entry)
        now = time.monotonic()
        modules: dict[str, ModuleStats] = {}
        for name, spec in specs.items():
            change = change_to(name, changing)
            # a module being migrated is on two nodes for a moment: the launcher says
            # where; moving, it may be on the other one only (captured, or moved since
            # the copy), or (captured, the other's report taken before it came) on none
            entries = found.get(name, [])
            entry = next((e for e in entries if e.node == spec.node), None) \
                or next(iter(entries), None)
            if entry is None and change is not None:     # (no figures: none its own)
                entry = ModuleStats(class_ref(spec.cls), spec.node, "", "running",
                                    silent=True, period=stepped_period(spec.cls, spec.period),
                                    fixed_rate=fixed_rate_of(spec.cls, spec.fixed_rate))
            if entry is None:               # (its node lost, or not asked)
                continue
            entry = dataclasses.replace(entry, node=spec.node)
            if change is not None:
                entry = dataclasses.replace(entry, change=change[0],
                                            change_s=max(0.0, now - change[1]))
            modules[name] = entry
        # (dated alike: sorted, they are in the order they happened, wherever)
        failures = sorted([*self.failures.lines(),
                           *(f for report in reports.values() for f in report.failures)])
        nodes = self.node_table()
        for name, report in reports.items():
            if name not in nodes:
                continue
            figures: dict[str, Any] = {"spare_workers": report.spare_workers}
            if report.resources is not None:        # (its fields are NodeStats' names)
                figures |= dataclasses.asdict(report.resources)
            nodes[name] = dataclasses.replace(nodes[name], **figures)
        return SystemStats(self.plan.name, modules,
                           _link_table(links, modules, list(reports.values()),
                                       dict(self.lost_values)),
                           nodes, failures)

    def _reports(self, timeout: float,
                 specs: dict[str, FlatModule]) -> dict[str, NodeReport]:
        """Every node's report, by node, asked of all at once, within ``timeout``. A node
        that has missed two heartbeats, or misses them meanwhile, is not asked, or not
        waited for; it, and one whose report is late, has its modules as its last report
        had them, silent, with their figures then (``_silenced``), placed as ``specs`` (a
        copy of the launcher's) has them, until it is declared lost. (A node silent but not lost
        left its modules out: ``stats().modules["ctl"]`` raised KeyError for a second
        and more before a failover, and on a 1 s freeze that changed nothing else.)"""
        reports: dict[str, NodeReport] = {}
        deadline = time.monotonic() + timeout

        def ask(name: str, node: Node) -> None:
            # the workers' figures get what the way back leaves of the timeout
            rtt = self.health[name]["rtt"] if name in self.remotes else 0.0
            way_back = 0.1 + 2 * (HEARTBEAT_S if math.isnan(rtt) else rtt)   # (NaN: unknown)
            try:
                reports[name] = node.report(min(REPORT_TIMEOUT,
                                                max(timeout / 2, timeout - way_back)))
            except (RuntimeFailure, RuntimeTimeout) as exc:
                log.warning("node %s did not report: %s", name, exc)

        up = {name: node for name, node in list(self.nodes.items())
              if self.health[name]["up"]}
        asked = {name: threading.Thread(target=ask, args=(name, node), daemon=True,
                                        name=f"pb3a-report-{name}")
                 for name, node in up.items() if not self.silent(name)}
        for thread in asked.values():
            thread.start()
        for name, thread in asked.items():
            while thread.is_alive() and not self.silent(name) and time.monotonic() < deadline:
                thread.join(max(0.0, min(WATCH_S, deadline - time.monotonic())))
        given = {name: reports[name] for name in asked if name in reports}
        self._last_reports.update({name: (self.remotes.get(name), report)
                                   for name, report in given.items()})
        for name in up.keys() - given.keys():
            if not self.silent(name):
                log.warning("node %s did not report within %g s", name, timeout)
            placed = [spec for spec in specs.values() if spec.node == name]
            admission, last = self._last_reports.get(name, (None, None))
            if last is None or admission is not self.remotes.get(name):
                last = NodeReport({}, {}, {}, [])
            names = {spec.name for spec in placed}
            read = {key for key, link in list(self.links.items()) if link.dst in names}
            given[name] = _silenced(last, name, placed, read)
        return given

    def silent(self, name: str) -> bool:
        """Whether remote node ``name`` missed its last two heartbeats."""
        remote = self.remotes.get(name)
        return remote is not None and remote.silent_s() > SILENT_S

    def node_table(self) -> dict[str, NodeStats]:
        """Every node's health as the heartbeats see it: a lost node's silence goes on
        counting (it said 0.0 once the node was lost)."""
        return {name: NodeStats(health["up"], health["rtt"], health["address"],
                                health.get("controller"), health["epoch"],
                                self.remotes[name].silent_s() if name in self.remotes
                                else 0.0, refused=health.get("refused", ""))
                for name, health in list(self.health.items())}

    def wait_health(self, node: str, up: bool, timeout: float) -> bool:
        """Block until ``node`` is (not) up; False on timeout."""
        with self.changed:
            return self.changed.wait_for(lambda: self.health[node]["up"] == up, timeout)

    # -- shutdown ---------------------------------------------------------------------
    @property
    def stopped(self) -> bool:
        """True once ``shutdown`` has begun."""
        return self.stopping.is_set()

    @property
    def not_torn_down(self) -> list[str]:
        """The modules a shutdown did not stop, in the order it stops them: those that
        did not stop in time (their workers are killed) and, until a shutdown has run
        to its end (one was interrupted), those it has not stopped yet."""
        if not self.stopped or self._shut_down:
            return list(self._given_up)
        return [*self._given_up, *self._left_to_stop()]

    def _left_to_stop(self) -> list[str]:
        """The modules the shutdown has still to stop, in reverse start order."""
        return [name for name in reversed(list(self.specs)) if name not in self._settled]

    def shutdown(self, timeout: float = 10.0) -> None:
        """Stop modules in reverse start order (across nodes), then every node, within
        about ``timeout`` seconds: a change in progress is waited for half of it at
        most (then the system stops all the same, the change failing as it can).

        One interrupted (a Ctrl-C's KeyboardInterrupt, wherever it comes) is finished by
        the next call, within that call's ``timeout``: the modules it stopped, or gave
        up on, are not stopped again, nor are the nodes it shut down; a remote node's
        shutdown still under way is waited for, not begun again."""
        deadline = time.monotonic() + timeout
        self.stopping.set()
        for thread in self._background:
            thread.join(max(0.0, min(2.0, deadline - time.monotonic())))
        for remote in self.remotes.values():
            remote.wind_down(deadline)   # (one that does not answer fences itself anyway)
        self._lose_silent_nodes()                    # gone, not yet declared: no waiting
        with contextlib.ExitStack() as held:
            try:
                held.enter_context(self.lock.held("shut the system down", timeout / 2))
            except RuntimeTimeout as exc:
                log.warning("%s: stopping it all the same", exc)
            # Without the lock, a change may remove a module or a node meanwhile: each is
            # stopped on its own, and nothing that fails keeps the rest from stopping.
            with self._losing_silent_nodes():
                for name in self._left_to_stop():
                    try:
                        # its request waits no longer than the deadline (a frozen worker's
                        # stop would have waited 1 s past it, as its grace ran out)
                        with bounding(deadline - time.monotonic()):
                            self.node_of(name).stop_module(name, 2.0)
                    except Exception as exc:
                        self._not_stopped(name, exc)
                    self._settled.add(name)
            # side by side: a node that does not answer holds up no other; this machine's
            # own nodes (their processes and segments are here) are waited for
            for name, node in reversed(list(self.nodes.items())):
                if name in self.remotes and name not in self._shutting:
                    thread = threading.Thread(target=self._shut_node,
                                              args=(name, node, deadline, STOP_AT_LEAST_S),
                                              name=f"pb3a-shutdown-{name}", daemon=True)
                    thread.start()
                    self._shutting[name] = thread
            for name, node in reversed(list(self.nodes.items())):
                if name not in self.remotes and name not in self._shut:
                    self._shut_node(name, node, deadline, 0.0)
            for thread in self._shutting.values():   # (what each is given past the
                                                     # deadline, and a moment to begin)
                thread.join(max(0.0, deadline - time.monotonic()) + STOP_AT_LEAST_S + 0.25)
        # (a lost node's controller that answered killed an executor fenced already: its
        # modules stopped on their own, unconfirmed)
        self.unconfirmed = [name for name, node in self.remotes.items()
                            if not node.stopped or (node.lost and name in self.unreached)]
        # (a node silent as its module's stop was sent, which answered its own stop
        # since: that module stopped with its executor, confirmed)
        self.unreached = {name: modules for name, modules in self.unreached.items()
                          if name in self.unconfirmed}
        logging.getLogger().removeHandler(self.logbook)
        self.events.end()            # (a follower waiting for more is told there is none)
        self.logbook.end()
        self._shut_down = True

    def _not_stopped(self, name: str, exc: Exception) -> None:
        """Say why module ``name``'s stop failed (``exc``). On a remote node that did not
        answer (lost, or silent: cut off, frozen) nothing of the launcher's side killed
        its worker: the module stops on its own as the node's lease runs out, its
        teardown cut short if it is long, and its node's stop is unconfirmed. (It was
        said killed, its teardown not run, where the node's log showed it run.)
        Elsewhere its worker is killed, its teardown not run."""
        node = self.specs[name].node if name in self.specs else None
        remote = self.remotes.get(node) if node is not None else None
        if remote is not None and (remote.lost or self.silent(remote.name)):
            if name not in self.unreached.setdefault(remote.name, []):
                self.unreached[remote.name].append(name)
            log.warning("module %r: its node %s did not answer its stop (%s): it stops on "
                        "its own %s", name, remote.name, exc, ON_THEIR_OWN)
            return
        # (a module stuck in on_input was killed at close, unsaid)
        if name not in self._given_up:     # (a Ctrl-C came as it was said)
            self._given_up.append(name)
        log.warning("module %r was not stopped (its worker is killed): %s", name, exc)

    @contextlib.contextmanager
    def _losing_silent_nodes(self) -> Iterator[None]:
        """While the modules stop, and once they have, declare lost a remote node that
        has answered no heartbeat for ``LOSS_S``: the watchdog has stopped with the
        close. Such a node froze or was cut off, and its lease has run out, so its
        workers have stopped their modules on their own (or will as soon as they run
        again): the stop waited for fails at once, and the next ones go on in order (a
        module whose node froze as the close waited for its teardown held the close to
        its end, and the modules of this machine after it were killed, their teardowns
        unrun). Nothing else is not waited for: a node answers its heartbeats apart from
        its requests, however long a teardown takes, and one silent for less may be
        only slow (on a loaded machine, 0.6 s as it tore a module down: taken for lost
        after 0.5 s, its executor was killed, its module's teardown run beside those
        of the modules started before it, and said not to have run). No watcher where
        no remote node answers (at exit, Python 3.12.0-1 refuses to start a thread)."""
        if all(node.lost for node in self.remotes.values()):
            yield
            return
        done = threading.Event()

        def watch() -> None:
            while not done.wait(HEARTBEAT_S / 2):
                self._lose_silent_nodes()
        watcher = threading.Thread(target=watch, name="pb3a-close-watch", daemon=True)
        watcher.start()
        try:
            yield
        finally:
            done.set()
            watcher.join(1.0)
            self._lose_silent_nodes()

    def _lose_silent_nodes(self) -> None:
        for node in list(self.remotes.values()):
            if not node.lost and node.silent_s() > LOSS_S:
                log.warning("node %s has answered no heartbeat for %.1f s: it is not waited "
                            "for as the system stops", node.name, node.silent_s())
                node.lose()

    def _shut_node(self, name: str, node: Node, deadline: float, at_least: float) -> None:
        """Shut node ``name`` down in what is left of the time, or ``at_least`` seconds if
        less is left (none for a node of this machine: its workers that did not stop
        are then killed at once); log what fails. Once it has returned, the node is
        shut down (``_shut``): a shutdown interrupted before does it again."""
        try:
            node.shutdown(max(at_least, deadline - time.monotonic()))
        except Exception:
            log.exception("shutting node %s down", name)
        self._shut.add(name)


def _link_table(links: dict[str, FlatLink], modules: dict[str, ModuleStats],
                reports: list[NodeReport], lost_values: dict[str, int]) -> dict[str, LinkStats]:
    """Per link: values, drops, pending, latency, rate, transport, from the reader's node
    (drops: its ring's and, on a remote link, the values its sender did not send); the
    writes that waited for room, from the writer's; the values lost for good, from the
    reader's node and from the failovers. A silent reader's link is said ``silent``: its
    figures are not known now, those shown are the last its reader's node gave (it
    showed 0 values and a link across nodes as shm, the reader's node being silent)."""
    rings = {key: used for report in reports for key, used in report.ring_bytes_used.items()}
    lost, dropped = collections.Counter(lost_values), collections.Counter()
    for report in reports:
        lost.update(report.link_failures)
        dropped.update(report.link_drops)
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
        figures["drops"] = figures.get("drops", 0) + dropped.get(key, 0)   # (not sent)
        waits = src.link_waits.get(key) if src else None
        if waits is not None:
            figures.update(waits=waits.waits, wait_s=waits.wait_s)
        table[key] = LinkStats(f"{link.src}.{link.src_port}", f"{link.dst}.{link.dst_port}",
                               str(link.policy), transport, **figures,
                               ring_bytes_used=rings.get(key, 0),
                               silent=dst is not None and dst.silent)
    return table


def _silenced(report: NodeReport, node: str, placed: list[FlatModule],
              read: set[str]) -> NodeReport:
    """The modules ``placed`` on ``node`` as it shows them when it did not answer in
    time: silent, not running, with the figures its last ``report`` had (steps, events,
    CPU, errors, inputs, outputs, waits: a silence reset them to zero, and a cut cable
    showed a module that had handled 1511 events as one that had handled none), with
    that report's failures, and the ring fill, link losses and drops of the links
    ``read`` there still (not of one whose reader has moved since: counted twice); one
    that came since (a failover, a move) as the launcher has it, running with no
    process known and no figures (it was left out of the figures)."""
    modules = {}
    for spec in placed:
        entry = report.modules.get(spec.name)
        modules[spec.name] = ModuleStats(
            class_ref(spec.cls), node, "", "running", silent=True,
            period=stepped_period(spec.cls, spec.period),
            fixed_rate=fixed_rate_of(spec.cls, spec.fixed_rate),
        ) if entry is None else dataclasses.replace(
            entry, silent=True, running=False, calling="", calling_s=0.0, change="",
            change_s=0.0)
    def still(figures: dict[str, int]) -> dict[str, int]:
        return {key: value for key, value in figures.items() if key in read}
    return NodeReport(modules, still(report.ring_bytes_used), still(report.link_failures),
                      list(report.failures), None, report.spare_workers,
                      still(report.link_drops))
