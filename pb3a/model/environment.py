"""``Environment``: the built-in per-node ``env`` module.

Every node has one, named ``env-NODE``; it is started when a link reads one of its
outputs (a link from ``env-a.cpu`` in a configuration, or ``run.link`` later). Its
outputs carry psutil readings of the node's resources, sampled every ``period``
seconds (default 1; declare ``env-NODE`` yourself, class ``pb3a:Environment``, to
set another period): agents read them like any other port to decide to move. A
node pinned to some CPUs (``cpus`` in its table) reports the load of those CPUs.

``cpu`` is how busy the node's CPUs are; ``cpu_own`` how much of that this system's
own worker processes on the node use, and ``cpu_outside`` the rest: load from
outside the system. An agent that moves its own load away sees ``cpu`` fall but
``cpu_outside`` stay, so it does not mistake its own load for the node's.

``nodes`` carries every node's health as the launcher's heartbeats see it (up or
lost, and the round-trip time of the last heartbeat); ``node_lost`` is the event:
a node's name, written once per loss, at the first sample after the launcher lost
it (also when it was back by then).
``module_moved`` is the event of a migration anywhere in the system (``module``,
``source``, ``destination``, ``pause_s``), once per move, at the next sample (up to
a period after the move: the agent that asked for it learns of its end at once from
its ``Pending``); a module restarted on another node because its node was lost is one
too (``policy``, ``from_checkpoint`` and ``restart_s`` instead of ``pause_s``). Each
port's meaning and unit is its docstring, which ``help(pb3a.Environment)`` shows.
"""

from __future__ import annotations

import contextlib
import os
import textwrap
import time

import numpy as np
import psutil

from pb3a.model.module import Module
from pb3a.model.ports import Output

PREFIX = "env-"


def _port(port: Output, doc: str) -> Output:
    """``port``, with ``doc`` as its docstring, which ``help()`` shows under its name
    (wrapped: it does not wrap a long line)."""
    port.__doc__ = textwrap.fill(doc, 80)
    return port


class Environment(Module):
    """A node's resources as output ports, sampled every ``period`` seconds (1 by
    default; declare ``env-NODE`` yourself, class ``pb3a:Environment``, for another):
    module ``env-NODE``, started when a link reads one of its outputs
    (``system.link("env-a.cpu", "agent.cpu")``). What each output carries, and in
    what unit, is its docstring (listed by ``help()``); a CPU figure is that of the
    last period, over the node's CPUs (its pinned ones, if pinned). The events
    (``node_lost``, ``module_moved``) come at its next sample, up to a period after
    what they tell."""

    cpu = _port(Output(float), "Percent (0-100): how busy the node's CPUs were over the "
                "last period, on average.")
    cpu_per_core = _port(Output(np.ndarray), "Percent (0-100) per CPU of the node, over "
                         "the last period, in CPU-number order (a float64 array).")
    cpu_own = _port(Output(float), "Percent (0-100) of the node's CPUs that this "
                    "system's worker processes on the node used over the last period (at "
                    "most ``cpu``): the load it brought.")
    cpu_outside = _port(Output(float), "Percent (0-100): ``cpu - cpu_own``, the load "
                        "from outside this system, which moving its modules away leaves.")
    memory_available = _port(Output(float), "Bytes of memory the machine has available "
                             "(psutil's ``available``).")
    load = _port(Output(np.ndarray), "The machine's 1, 5 and 15-minute load averages "
                 "(processes runnable or running, not a percent; a float64 array of 3).")
    nodes = _port(Output(dict), "Every node's health as the launcher's heartbeats see "
                  "it: node -> {\"up\": bool, \"rtt\": seconds of this node's last "
                  "round trip to it, NaN while it is lost}, each sample.")
    node_lost = _port(Output(str), "A lost node's name: an event, once per loss, at the "
                      "first sample after the launcher lost it (also when it was back by "
                      "then).")
    module_moved = _port(Output(dict), "A module moved anywhere in the system: an event, "
                         "{\"module\", \"source\", \"destination\", \"pause_s\": the "
                         "seconds it was paused}, once per move, at this module's next "
                         "sample, up to a period (1 s by default) after the move ended; "
                         "for a module restarted elsewhere because its node was lost, "
                         "\"policy\", \"from_checkpoint\" and \"restart_s\" instead of "
                         "\"pause_s\". An agent that asked for the move learns of its end "
                         "at once from the ``Pending`` that ``runtime.migrate(..., "
                         "wait=False)`` returns (``done()``, ``result()``).")
    period = 1.0
    # set by the launcher: every node's health; this node's worker processes; the latest
    # moves and nodes lost, each with the sequence number of its event, so each is told
    # once (also a node lost and back between two samples) however many came before
    health: dict = {}                    # node -> {"up", "rtt"}
    own_pids: list = []
    moves: list = []                     # [{"seq", "module", "source", "destination", ...}]
    losses: list = []                    # [{"seq", "node"}]

    def setup(self) -> None:
        self._told = max((told["seq"] for told in (*self.moves, *self.losses)),
                         default=0)     # what came before this start is history
        self._cpus = sorted(os.sched_getaffinity(0))   # the node's, if it is pinned
        self._processes: dict[int, psutil.Process] = {}
        self._cpu_s: dict[int, float] = {}      # worker pid -> its CPU seconds, last sample
        self._sampled = time.monotonic()
        self._own_cpu()
        psutil.cpu_percent(percpu=True)  # the first reading covers the time since this

    def step(self) -> None:
        per_core = psutil.cpu_percent(percpu=True)
        busy = np.asarray([per_core[cpu] for cpu in self._cpus if cpu < len(per_core)],
                          dtype=np.float64)
        cpu = float(busy.mean()) if busy.size else 0.0
        used, now = self._own_cpu(), time.monotonic()
        elapsed, self._sampled = now - self._sampled, now
        own = 100.0 * used / (elapsed * max(1, len(self._cpus))) if elapsed > 0 else 0.0
        own = min(own, cpu)
        self.cpu_per_core.write(busy)
        self.cpu.write(cpu)
        self.cpu_own.write(own)
        self.cpu_outside.write(cpu - own)
        self.memory_available.write(float(psutil.virtual_memory().available))
        self.load.write(np.asarray(psutil.getloadavg(), dtype=np.float64))
        if self.health:
            self.nodes.write(dict(self.health))
        told = self._told
        for loss in self.losses:
            if loss["seq"] > told:
                self.node_lost.write(loss["node"])
        for move in self.moves:
            if move["seq"] > told:
                self.module_moved.write({k: v for k, v in move.items() if k != "seq"})
        self._told = max((t["seq"] for t in (*self.moves, *self.losses)), default=told)

    def _own_cpu(self) -> float:
        """CPU seconds this system's workers on this node used since the last sample (a
        worker counts from its first sample on; one gone meanwhile is left out)."""
        used, seen = 0.0, {}
        for pid in self.own_pids:
            with contextlib.suppress(psutil.Error):
                process = self._processes.get(pid) or psutil.Process(pid)
                self._processes[pid] = process
                times = process.cpu_times()
                seen[pid] = times.user + times.system
                used += seen[pid] - self._cpu_s.get(pid, seen[pid])
        self._cpu_s = seen
        self._processes = {pid: self._processes[pid] for pid in seen}
        return used


def env_name(node: str) -> str:
    """The name of ``node``'s env module."""
    return f"{PREFIX}{node}"
