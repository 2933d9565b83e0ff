"""``Failover``: what becomes of a remote node that is lost, and of its modules.

A watchdog declares a node lost when its executor stops answering, starts its modules
again on the nodes that survive, and lets the node in again once its controller
answers. It changes the system through the ``Launcher``'s tables and wiring, as a
migration does, from above: the launcher does not import it (``Running`` starts it; its
threads run in the launcher's background, which its shutdown joins).

Each ``RemoteNode`` heartbeats its executor, which fences itself when the heartbeats
stop; a node that does not answer for ``LOSS_S`` is declared lost. Its modules whose
``restart`` policy is ``fresh`` or ``last-state`` fail over: they start again on a
surviving node (their ``fallback`` nodes in order, else the least busy one, either
only if its controller admits them), ``last-state`` ones from their last checkpoint,
which every node sends the launcher, off the node that runs the module. Their links
are wired again and what is known lost counted on them. The others are dropped with
their links, each said by a ``module_lost`` event that holds what it takes to add it
again (class, configured state, links). A lost node whose controller answers again is
admitted under a new node epoch; anything the fenced executor of an older epoch says
is refused (``Launcher.check_node_epoch``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
import time
from typing import TYPE_CHECKING, Any

import psutil

from pb3a.errors import RuntimeFailure, RuntimeTimeout
from pb3a.launch.launcher import WATCH_S
from pb3a.model.environment import env_name
from pb3a.node.executor import REPORT_TIMEOUT
from pb3a.node.remote import HEARTBEAT_S, LOSS_S
from pb3a.transport.replication import follower_id

if TYPE_CHECKING:
    from collections.abc import Iterable

    from pb3a.config.plan import FlatLink, FlatModule
    from pb3a.launch.env_keeper import EnvKeeper
    from pb3a.launch.launcher import Launcher
    from pb3a.node.remote import RemoteNode
    from pb3a.stats import NodeReport

log = logging.getLogger("pb3a.launcher")

FAIL_OVER_WAIT_S = 1.0  # a failover's wait for the configuration lock, each look
# A node silent this long (two heartbeats unanswered) has its controller asked whether
# its executor died, at most once a heartbeat and for that long: a controller that says
# it did, its every process ended, has the node lost then, not at LOSS_S.
SUSPECT_S = 2 * HEARTBEAT_S
REJOIN_S = 1.0          # how often it asks a lost node's controller whether it is back
PLACE_TIMEOUT = 0.5     # a controller's answer about its load and admission


class Failover:
    """The watchdog over a launcher's remote nodes: each one lost, its modules failed
    over; each one back, admitted again."""

    def __init__(self, launcher: Launcher, env: EnvKeeper) -> None:
        self.launcher, self.env = launcher, env
        self._rejoining: set[str] = set()
        self._failing_over: dict[str, float] = {}     # lost node -> when, until done
        self._asked: dict[str, float] = {}    # silent node -> when its controller was asked
        # a lost node's env module and the links from it, restored when it rejoins
        self._env_kept: dict[str, tuple[FlatModule, list[FlatLink]]] = {}

    def start(self) -> None:
        """Start the watchdog, once the launcher has started its nodes (until it shuts
        down)."""
        self.launcher.start_background(threading.Thread(target=self._watch,
                                                        name="pb3a-heartbeat", daemon=True))

    # -- heartbeats -------------------------------------------------------------------
    def _watch(self) -> None:
        """Declare lost a remote node silent for ``LOSS_S``; ask lost ones' controllers
        whether they are back. (Nothing here waits for a node that may be gone.)"""
        next_rejoin = time.monotonic()
        while not self.launcher.stopping.wait(WATCH_S):
            try:
                next_rejoin = self._look(next_rejoin)
            except Exception:               # (the watchdog alone sees nodes go: it goes on)
                log.exception("the watchdog's look at the nodes failed")

    def _look(self, next_rejoin: float) -> float:
        """One look of the watchdog; when to look for lost nodes' return next."""
        launcher = self.launcher
        now = time.monotonic()
        for name, node in list(launcher.remotes.items()):
            if node.lost or launcher.remotes.get(name) is not node:
                continue        # (lost already, or admitted anew since the list was taken)
            if launcher.health[name]["up"]:
                launcher.health[name]["rtt"] = node.rtt
                silent = node.silent_s()
                if (silent > LOSS_S or node.ended) and not launcher.stopping.is_set():
                    self._lose(name, node, silent)
                elif silent > SUSPECT_S and now - self._asked.get(name, -LOSS_S) > HEARTBEAT_S:
                    self._asked[name] = now
                    threading.Thread(target=node.executor_ended, args=(HEARTBEAT_S,),
                                     daemon=True, name=f"pb3a-ended-{name}").start()
        if now < next_rejoin:
            return next_rejoin
        for name in list(launcher.remotes):
            if not launcher.health[name]["up"] and name not in self._rejoining \
                    and name not in self._failing_over:     # (its modules first)
                self._rejoining.add(name)
                threading.Thread(target=self._rejoin, args=(name,), daemon=True,
                                 name=f"pb3a-rejoin-{name}").start()
        return now + REJOIN_S

    # -- a lost node ------------------------------------------------------------------
    def _lose(self, node: str, remote: RemoteNode, silent_s: float) -> None:
        """Declare ``node`` lost, as ``remote``, the admission of it found silent: every
        call to it fails at once from now on; its modules fail over or are dropped, with
        their links (``_try_fail_over``); the env modules say so. Nothing is done if
        ``remote`` is no longer the node's: a rejoin admitted it anew meanwhile (the
        watchdog measured the old admission's silence against the new one's health, and
        lost the node just let in)."""
        launcher = self.launcher
        lost_at = time.monotonic()
        with launcher.changed:              # (a rejoin admits a node under it)
            if remote.lost or launcher.remotes.get(node) is not remote:
                return
            remote.lose()
            # no round trip now: its last one, shown on, was made up
            launcher.health[node].update(up=False, rtt=float("nan"))
            launcher.changed.notify_all()
        # (a copy: another node's failover thread may change the specs meanwhile); a
        # module a move was landing there is not said to be there: the move puts it back
        # where it ran (it was said lost with the node, and then ran on)
        there = sorted(name for name, spec in list(launcher.specs.items()) if spec.node == node)
        arriving = [name for name in there if launcher.arriving.get(name) == node]
        gone = [name for name in there if name not in arriving]
        landing = f"; a move was landing {', '.join(arriving)} there" if arriving else ""
        ended = remote.ended
        why = f"no heartbeat for {silent_s:.1f} s" + (
            f"; its controller says its executor {ended}" if ended else "")
        there_were = f"its modules {', '.join(gone)} were there" if gone else "no module was there"
        launcher.failures.add(f"node {node} lost ({why}); {there_were}{landing}")
        launcher.events.record("node_lost", node, modules=gone, arriving=arriving,
                               silent_s=silent_s, executor=ended)
        self._failing_over[node] = lost_at
        # on a thread of its own: placing the modules may wait for a node that went too,
        # which only the watchdog, free, declares lost (then the wait fails at once)
        launcher.start_background(threading.Thread(
            target=self._fail_over_until_done, args=(node, lost_at),
            name=f"pb3a-failover-{node}", daemon=True))

    def _fail_over_until_done(self, node: str, lost_at: float) -> None:
        """Try to fail ``node``'s modules over every ``WATCH_S`` until it is done."""
        while node in self._failing_over and not self.launcher.stopping.is_set():
            self._try_fail_over(node, lost_at)
            if node in self._failing_over:
                self.launcher.stopping.wait(WATCH_S)

    def _try_fail_over(self, node: str, lost_at: float) -> None:
        """Fail over lost ``node``'s modules once its executor has fenced itself, if the
        configuration lock comes within ``FAIL_OVER_WAIT_S``; else its failover thread
        tries again ``WATCH_S`` later (a change holding the lock long, or failing, must
        not end it)."""
        launcher = self.launcher
        remote = launcher.remotes.get(node)
        if remote is not None and time.monotonic() < remote.fenced_by():
            return                          # its modules may still run there
        # lent to the modules it starts: one that reads the runtime from its setup (an
        # agent checking the modules its settings name) is answered, as in a move (it
        # waited for the lock the failover held, the start ran out of time, and the
        # module was failed, not failed over)
        moving = [name for name, spec in list(launcher.specs.items()) if spec.node == node]
        with contextlib.ExitStack() as held:
            try:
                held.enter_context(launcher.lock.held(f"fail over lost node {node}",
                                                      FAIL_OVER_WAIT_S, lend=moving))
            except RuntimeTimeout:
                return                      # the lock: the next look (nothing done yet)
            try:
                self._fail_over_lost(node, lost_at)
            except Exception:               # once begun, never again: logged
                log.exception("failing over the modules of lost node %s failed", node)
            self._failing_over.pop(node, None)

    def _fail_over_lost(self, node: str, lost_at: float) -> None:
        """``_try_fail_over``'s work, the configuration lock held."""
        launcher = self.launcher
        # read under the lock: a move to the node that failed when it was lost put
        # its modules back where they came from before it let the lock go
        gone = sorted(name for name, spec in launcher.specs.items() if spec.node == node)
        touched = {key: link for key, link in launcher.links.items()
                   if link.src in gone or link.dst in gone}
        env = env_name(node)            # back with the node, if it rejoins
        if env in launcher.specs:
            self._env_kept[node] = (launcher.specs[env], [
                link for link in touched.values() if link.src == env])
        # what a surviving writer writes while its link is unwired is lost: counted
        written = self._written([link for link in touched.values() if link.src not in gone])
        reader = follower_id(node, launcher.remotes[node].node_epoch)   # (the lost admission's)
        for link in touched.values():
            with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
                self._drop_half(link, gone, reader)
        moved, refused = self._fail_over(node, gone)
        lost = [launcher.specs.pop(name) for name in gone if name not in moved]
        for key, link in touched.items():
            if link.src not in launcher.specs or link.dst not in launcher.specs:
                del launcher.links[key]
                if env not in (link.src, link.dst):     # (an env's come back with it)
                    launcher.events.record("link_removed", key)
        for spec in lost:
            if spec.name != env:        # (an env module belongs to its node: back with it)
                self._tell_lost(spec, node, refused.get(spec.name), touched.values())
        launcher.reattach([link for key, link in touched.items() if key in launcher.links],
                          f"after the loss of node {node}")
        rewired = [launcher.links[key] for key in written if key in launcher.links]
        for key, count in self._written(rewired).items():
            launcher.lost_values[key] += max(0, count - written[key])
        not_started: set[str] = set()
        for target in dict.fromkeys(moved.values()):
            started = [name for name, to in moved.items() if to == target]
            try:
                launcher.nodes[target].start_modules(started, failing=True)
            except (RuntimeFailure, RuntimeTimeout) as exc:
                not_started.update(getattr(exc, "failed", started))
                launcher.failures.add(f"failover of {', '.join(started)} to node "
                                      f"{target} failed: {exc}")
        for name, target in moved.items():
            if name in not_started:             # failed there (module_failed), not over
                continue
            launcher.events.record("module_failed_over", name, source=node,
                                   destination=target, policy=launcher.specs[name].restart,
                                   from_checkpoint=launcher.specs[name].restart == "last-state"
                                   and name in launcher.checkpoints,
                                   restart_s=time.monotonic() - lost_at)
        self.env.update()

    def _tell_lost(self, spec: FlatModule, node: str, refused: str | None,
                   links: Iterable[FlatLink]) -> None:
        """Say that module ``spec`` went with lost ``node`` (its policy, or ``refused``:
        why no node took it), with what it takes to add it again: an agent or a user
        reading the event can (it was gone from the system without a word)."""
        cls = f"{spec.cls.__module__}:{spec.cls.__qualname__}"
        reason = refused or "its restart policy is never"
        self.launcher.failures.add(f"module {spec.name} ({cls}) went with node {node}: {reason}")
        # (its period only if configured or set: None is the class's own; it and the
        # fallback were left out, and a module added again from the event ran at its
        # class's rate and went for good with its next node)
        self.launcher.events.record("module_lost", spec.name, node=node, reason=reason, cls=cls,
                                    state=dict(spec.state), restart=spec.restart,
                                    period=spec.period if spec.own_period else None,
                                    fixed_rate=spec.fixed_rate,
                                    fallback=list(spec.fallback),
                                    links=[{"from": f"{link.src}.{link.src_port}",
                                            "to": f"{link.dst}.{link.dst_port}",
                                            "policy": str(link.policy)} for link in links
                                           if spec.name in (link.src, link.dst)])

    def _fail_over(self, lost: str, gone: list[str]) -> tuple[dict[str, str], dict[str, str]]:
        """Instantiate each module of ``gone`` whose restart policy allows it on a
        surviving node, from its last checkpoint for ``last-state``: module -> node, and
        module -> why no node took it. All are placed first, so that each target boots
        their workers side by side."""
        launcher = self.launcher
        movers = [name for name in gone if launcher.specs[name].restart != "never"
                  and name != env_name(lost)]        # an env module belongs to its node
        loads = self._loads(lost) if movers else {}
        placed: dict[str, FlatModule] = {}
        refused: dict[str, str] = {}
        for name in movers:
            spec = launcher.specs[name]
            target = self._place(spec, loads)
            if target is None:
                refused[name] = (f"no surviving node {'of its fallback ' if spec.fallback else ''}"
                                 "admits it")
                continue
            placed[name] = dataclasses.replace(spec, node=target)
            loads[target] = loads[target][0], loads[target][1] + 1
        coming: dict[str, list[FlatModule]] = {}
        for spec in placed.values():
            coming.setdefault(spec.node, []).append(spec)
        for target, specs in coming.items():
            with contextlib.suppress(RuntimeFailure, RuntimeTimeout):   # (add_module boots
                launcher.nodes[target].spawn_workers(specs)                 # them, failing this)
        moved = {}
        for name, moved_spec in placed.items():
            # a checkpoint goes as it came, read in the worker: its classes may be
            # installed on the robots only, not where the launcher runs
            state: dict[str, Any] | bytes = (
                launcher.checkpoints[name] if moved_spec.restart == "last-state"
                and name in launcher.checkpoints else moved_spec.state)
            target: str | None = moved_spec.node
            last = ""                           # why the last node tried did not take it
            while target is not None:
                try:
                    launcher.nodes[target].add_module(dataclasses.replace(moved_spec, node=target),
                                                      state=state)
                    break
                except (RuntimeFailure, RuntimeTimeout) as exc:
                    last = launcher.failures.add(f"module {name} not restarted on node "
                                                 f"{target}: {exc}")
                    loads.pop(target, None)     # the next that admits it, if any
                    target = self._place(launcher.specs[name], loads)
            if target is None:
                refused[name] = f"no surviving node could start it ({last})"
                continue
            launcher.specs[name] = dataclasses.replace(moved_spec, node=target)
            moved[name] = target
        return moved, refused

    def _loads(self, lost: str) -> dict[str, tuple[float, int]]:
        """Each surviving node's CPU use (percent, as its controller or, embedded, this
        machine measures it) and module count: the least loaded is tried first."""
        launcher = self.launcher
        loads = {}
        here = psutil.cpu_percent(interval=None)
        for name in launcher.nodes:
            if name == lost or not launcher.health[name]["up"] or self._going(name):
                continue                    # (a node gone too, not declared lost yet)
            cpu = here
            if name in launcher.remotes:
                try:
                    cpu = launcher.remotes[name].controller.call("status",
                                                                 PLACE_TIMEOUT)["cpu_percent"]
                except (RuntimeFailure, RuntimeTimeout):
                    continue
            loads[name] = (cpu, sum(spec.node == name for spec in launcher.specs.values()))
        return loads

    def _place(self, spec: FlatModule, loads: dict[str, tuple[float, int]]) -> str | None:
        """The first node that admits ``spec``: of its fallback nodes in order if it names
        any, else of the surviving ones from the least loaded."""
        candidates = ([node for node in spec.fallback if node in loads] if spec.fallback
                      else sorted(loads, key=lambda node: loads[node]))
        for node in candidates:
            if node not in self.launcher.remotes:
                return node                   # an embedded node: the launcher's machine
            try:
                self.launcher.remotes[node].controller.call("admit", PLACE_TIMEOUT,
                                                            what=f"module {spec.name}")
                return node
            except (RuntimeFailure, RuntimeTimeout) as exc:
                log.warning("failover of %s: %s", spec.name, exc)
        return None

    def _written(self, links: list[FlatLink]) -> dict[str, int]:
        """How many values the writer of each link has written on its port so far (one
        report from each writer's node)."""
        reports: dict[str, NodeReport | None] = {}
        counts = {}
        for link in links:
            node = self.launcher.specs[link.src].node
            if node not in reports:
                try:
                    reports[node] = self.launcher.nodes[node].report(REPORT_TIMEOUT)
                except (RuntimeFailure, RuntimeTimeout):
                    reports[node] = None
            report = reports[node]
            entry = None if report is None else report.modules.get(link.src)
            counts[link.key] = 0 if entry is None else entry.outputs.get(link.src_port, 0)
        return counts

    def _drop_half(self, link: FlatLink, gone: list[str], reader: bytes) -> None:
        """Unwire the surviving half of a link whose other end was on a lost node; what
        its reader knows it never got, or what the lost node's follower (``reader``)
        never acknowledged to its writer, is counted on the link."""
        launcher = self.launcher
        if link.src in gone and link.dst not in gone:
            launcher.lost_values[link.key] += launcher.node_of(link.dst).close_inbound(
                [(link, (0, None))])[0]
        elif link.dst in gone and link.src not in gone:
            writer = launcher.node_of(link.src)
            launcher.lost_values[link.key] += writer.unacknowledged(link, reader)
            writer.unpublish([link])

    def _rejoin(self, name: str) -> None:
        """Admit lost node ``name`` again if its controller answers: the fenced executor
        is stopped, a new one started under the next node epoch; its env module is
        back. Its modules stay where they failed over to: move them back at will."""
        launcher = self.launcher
        try:
            old = launcher.remotes[name]
            if launcher.stopping.is_set():
                return
            # (said while it is lost too: it said the last answer before the loss)
            launcher.health[name]["controller"] = old.controller_answers(HEARTBEAT_S * 2)
            if old.refusal != launcher.health[name].get("refused", ""):
                if old.refusal:     # (once per reason: the rejoin asks every second)
                    log.warning("node %s cannot rejoin: its controller answers but refuses "
                                "the launcher: %s", name, old.refusal)
                launcher.health[name]["refused"] = old.refusal
            if not launcher.health[name]["controller"]:
                return
            old.stop_executor(timeout=5.0)        # (it fenced itself; killed if it did not)
            epoch = old.node_epoch + 1
            try:
                node = launcher.start_remote_node(name, node_epoch=epoch)
            except (RuntimeFailure, RuntimeTimeout) as exc:   # (asked again in a second)
                log.warning("node %s answers again but could not be admitted: %s", name, exc)
                return
            adopted = False
            try:
                with launcher.lock.held(f"admit node {name} again"):
                    if launcher.stopping.is_set():
                        return
                    old.close()
                    with launcher.changed:      # (the watchdog loses a node under it)
                        launcher.nodes[name] = launcher.remotes[name] = node
                        adopted = True
                        launcher.health[name].update(up=True, rtt=node.rtt, controller=True,
                                                     epoch=epoch)
                        launcher.changed.notify_all()
                    launcher.introduce()
                    self._restore_env(name)
                    self.env.update()
            except RuntimeTimeout as exc:               # (the lock: asked again in a second)
                log.warning("node %s answers again but could not be admitted: %s", name, exc)
                return
            finally:
                if not adopted:          # its executor, and the heartbeats that renew it
                    node.shutdown()
            log.warning("node %s is back (epoch %d)", name, epoch)
            launcher.events.record("node_joined", name, epoch=epoch, address=node.address)
        finally:
            self._rejoining.discard(name)

    def _restore_env(self, node: str) -> None:
        """Bring back a rejoined node's env module and its links that were there when the
        node was lost (to modules still running)."""
        launcher = self.launcher
        spec, links = self._env_kept.pop(node, (None, []))
        if spec is None or spec.name in launcher.specs:
            return
        launcher.add_module(spec)
        for link in links:
            if link.dst in launcher.specs and link.key not in launcher.links:
                launcher.connect(link)
        launcher.nodes[node].start_modules([spec.name])

    def _going(self, name: str) -> bool:
        """Whether remote node ``name`` has been silent half the time that makes it lost:
        no place for a module failing over (a slow node that missed two heartbeats is)."""
        remote = self.launcher.remotes.get(name)
        return remote is not None and remote.silent_s() > LOSS_S / 2
