"""``EnvKeeper``: what every node's env module knows of the system, kept up to date.

Each node's env module (``pb3a.model.environment``) measures its own node; what only
the launcher knows, it is told as state every ``ENV_S``: the health of every node and
the node's round-trip time to each, its own worker processes (to tell its system's
load from the rest of the machine's) and the latest moves and losses. The same thread
asks each remote node's controller whether it answers and merges the node's log into
the launcher's (``run.logs()``). A change that moves modules, fails them over or lets a
node in again tells the env modules at once (``update``). Like ``Failover``, it acts
on the ``Launcher`` from above (``Running`` makes it); its thread runs in the
launcher's background, which its shutdown joins.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from typing import TYPE_CHECKING

from pb3a.errors import ModuleNotFound, RuntimeFailure, RuntimeTimeout
from pb3a.model.environment import env_name
from pb3a.node.remote import HEARTBEAT_S

if TYPE_CHECKING:
    from pb3a.launch.launcher import Launcher
    from pb3a.node.remote import RemoteNode

log = logging.getLogger("pb3a.launcher")

ENV_S = 1.0             # how often the env modules are told, and the logs merged
ENV_TOLD = 256          # the latest moves (and losses) the env modules are given each time


class EnvKeeper:
    """Keeps the env modules' view of ``launcher``'s system, and its remote nodes' logs
    merged into its log book."""

    def __init__(self, launcher: Launcher) -> None:
        self.launcher = launcher
        self._log_seen: dict[str, int] = {}     # remote node -> its last entry merged

    def start(self) -> None:
        """Keep the view, once the launcher has started its nodes (until it shuts down;
        also without remote nodes: the env modules' view)."""
        self.launcher.start_background(threading.Thread(target=self._keep, name="pb3a-env",
                                                        daemon=True))

    def _keep(self) -> None:
        """Every ``ENV_S`` until the system stops: each remote node's controller health
        and log, and the env modules' view (on a thread of its own: a node going silent
        meanwhile must not hold up the detection of its loss). A pass that fails is
        logged, and the next one comes (it ended the thread, and the env modules were
        told nothing more)."""
        launcher = self.launcher
        while not launcher.stopping.wait(ENV_S):
            try:
                self._pass()
            except Exception:
                log.exception("keeping the env modules' view failed; it goes on")

    def _pass(self) -> None:
        """One pass of ``_keep``."""
        launcher = self.launcher
        for name, node in list(launcher.remotes.items()):
            if launcher.health[name]["up"] and not launcher.silent(name):
                launcher.health[name]["controller"] = node.controller_answers(HEARTBEAT_S)
                self._merge_log(name, node)
        self.update()

    def _merge_log(self, name: str, node: RemoteNode) -> None:
        """Take in what node ``name`` logged since the last look."""
        with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
            for entry in node.logs(self._log_seen.get(name, 0)):
                self._log_seen[name] = entry.seq
                self.launcher.logbook.add(entry.time, entry.level, entry.logger,
                                          entry.message, name, entry.module, entry.process)

    def update(self) -> None:
        """Tell every node's env module (as its state) the health of every node and its
        round-trip time to each, the node's worker processes (its own load) and the
        latest moves and losses, each with its event's number (it tells each once). An
        env module between nodes (removed, or restarted, from its node, its spec not yet
        dropped or started again) is told at the next pass."""
        launcher = self.launcher
        events = launcher.events.since(0)
        moves = [{"seq": event.seq, "module": event.subject, **event.detail}
                 for event in events
                 if event.kind in ("module_moved", "module_failed_over")][-ENV_TOLD:]
        losses = [{"seq": event.seq, "node": event.subject} for event in events
                  if event.kind == "node_lost"][-ENV_TOLD:]
        for name, node in list(launcher.nodes.items()):
            env = env_name(name)
            if env not in launcher.specs or not launcher.health[name]["up"] \
                    or launcher.silent(name):
                continue
            with contextlib.suppress(RuntimeFailure, RuntimeTimeout, ModuleNotFound):
                rtts = self._rtts_from(name)
                # (a lost peer has no round-trip time: the node's last one to it is past)
                table = {peer: {"up": health["up"], "rtt": rtts.get(peer, float("nan"))
                                if health["up"] else float("nan")}
                         for peer, health in launcher.health.items()}
                launcher.call(env, "set_state", ENV_S, state={
                    "health": table, "moves": moves, "losses": losses,
                    "own_pids": node.worker_pids()})

    def _rtts_from(self, name: str) -> dict[str, float]:
        """Round-trip times from node ``name`` to every node: measured by the node itself
        if it is remote; for an embedded node, this process's (it runs here): 0 to the
        other embedded nodes, the heartbeat's to the remote ones."""
        launcher = self.launcher
        if name in launcher.remotes:
            return {**launcher.remotes[name].rtts(), name: 0.0}
        return {peer: launcher.health[peer]["rtt"] if peer in launcher.remotes else 0.0
                for peer in launcher.nodes}
