"""``ResourceMeter``: a node's CPU and memory, measured when its report is asked for.

Each meter keeps its own previous reading of the CPU times, so two nodes run by one
process (embedded nodes) measure independently: ``psutil.cpu_percent`` keeps one
previous reading per process and would give the second caller a near-empty interval.
A node pinned to some CPUs reports the load of those.
"""

from __future__ import annotations

import os

import psutil

from pb3a.stats import NodeResources


class ResourceMeter:
    """The busy share of some CPUs since the previous sample, and the machine's memory."""

    def __init__(self, cpus: list[int] | None = None) -> None:
        self.cpus = sorted(cpus) if cpus else sorted(os.sched_getaffinity(0))
        self._last = self._times()

    def _times(self) -> list[tuple[float, float]]:
        """(busy, total) CPU seconds of each measured CPU."""
        per_cpu = psutil.cpu_times(percpu=True)
        times = []
        for cpu in self.cpus:
            if cpu < len(per_cpu):
                sample = per_cpu[cpu]
                idle = sample.idle + getattr(sample, "iowait", 0.0)
                # guest time is counted in user time already (as psutil.cpu_percent does)
                total = (sum(sample) - getattr(sample, "guest", 0.0)
                         - getattr(sample, "guest_nice", 0.0))
                times.append((total - idle, total))
        return times

    def sample(self) -> NodeResources:
        """CPU busy percent since the last sample (or since the meter was made), and memory."""
        now = self._times()
        busy = sum(b - pb for (b, _), (pb, _) in zip(now, self._last, strict=False))
        total = sum(t - pt for (_, t), (_, pt) in zip(now, self._last, strict=False))
        self._last = now
        memory = psutil.virtual_memory()
        cpu = 100.0 * busy / total if total > 0 else 0.0
        return NodeResources(min(100.0, max(0.0, cpu)), int(memory.available),
                             int(memory.total))
