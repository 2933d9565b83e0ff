"""``Environment``: the built-in per-node ``env`` module.

Every node has one, named ``env-NODE``; it is started when a link reads one of its
outputs (a link from ``env-a.cpu`` in a configuration, or ``run.link`` later). Its
outputs carry psutil readings of the node's resources, sampled every ``period``
seconds (default 1; declare ``env-NODE`` yourself, class ``pb3a:Environment``, to
set another period): agents read them like any other port to decide to move. A
node pinned to some CPUs (``cpus`` in its table) reports the load of those CPUs.

``nodes`` carries every node's health as the launcher's heartbeats see it (up or
lost, and the round-trip time of the last heartbeat); ``node_lost`` is the event:
a node's name, written once, at the first sample after the launcher lost it.
"""

from __future__ import annotations

import os

import numpy as np
import psutil

from pb3a.model.module import Module
from pb3a.model.ports import Output

PREFIX = "env-"


class Environment(Module):
    """A node's resources as output ports."""

    cpu = Output(float)                  # mean busy percent of the node's CPUs
    cpu_per_core = Output(np.ndarray)    # busy percent of each of them
    memory_available = Output(float)     # bytes
    load = Output(np.ndarray)            # 1, 5 and 15-minute load averages
    nodes = Output(dict)                 # node -> {"up": bool, "rtt": seconds}
    node_lost = Output(str)              # a lost node's name (once)
    period = 1.0
    health: dict = {}                    # node -> {"up", "rtt"}: set by the launcher

    def setup(self) -> None:
        self._told: set[str] = set()
        self._cpus = sorted(os.sched_getaffinity(0))   # the node's, if it is pinned
        psutil.cpu_percent(percpu=True)  # the first reading covers the time since this

    def step(self) -> None:
        per_core = psutil.cpu_percent(percpu=True)
        busy = np.asarray([per_core[cpu] for cpu in self._cpus if cpu < len(per_core)],
                          dtype=np.float64)
        self.cpu_per_core.write(busy)
        self.cpu.write(float(busy.mean()) if busy.size else 0.0)
        self.memory_available.write(float(psutil.virtual_memory().available))
        self.load.write(np.asarray(psutil.getloadavg(), dtype=np.float64))
        if self.health:
            self.nodes.write(dict(self.health))
        for node, health in self.health.items():
            if not health["up"] and node not in self._told:
                self._told.add(node)
                self.node_lost.write(node)


def env_name(node: str) -> str:
    """The name of ``node``'s env module."""
    return f"{PREFIX}{node}"
