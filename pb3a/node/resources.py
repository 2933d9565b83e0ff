"""``ResourceMeter``: a node's CPU and memory, for its report.

The CPU's busy share is that of the last whole second (``INTERVAL_S``, the env
module's period), which the meter's own thread samples whoever asks, so every caller
asked at about the same time reads the same figure: one measured since the previous
report, as it was, covered a few milliseconds when another client had just asked (an
agent polling it read a steady 50 % load as 86, 0, 0, 100, 0 ... whenever the command
line, the manager or another agent asked too). Each meter keeps its own readings, so
two nodes run by one process (embedded nodes) measure independently
(``psutil.cpu_percent`` keeps one previous reading per process). A node pinned to some
CPUs reports the load of those.
"""

from __future__ import annotations

import os
import threading

import psutil

from pb3a.stats import NodeResources

INTERVAL_S = 1.0        # the window of a node's CPU reading (the env module's period)
CLOSE_WAIT_S = 1.0      # how long closing waits for the sampling thread to end


class ResourceMeter:
    """The busy share of some CPUs over the last whole ``interval``, and the machine's
    memory. ``close`` it (its thread samples until then)."""

    def __init__(self, cpus: list[int] | None = None, interval: float = INTERVAL_S) -> None:
        self.cpus = sorted(cpus) if cpus else sorted(os.sched_getaffinity(0))
        self.interval = interval
        self._made = self._times()
        self._busy: float | None = None       # percent, the last whole interval's
        self._closed = threading.Event()
        self._sampler = threading.Thread(target=self._sample_each_interval,
                                         name="pb3a-cpu-meter", daemon=True)
        self._sampler.start()

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

    def _sample_each_interval(self) -> None:
        before = self._made
        while not self._closed.wait(self.interval):
            now = self._times()
            self._busy, before = _busy(before, now), now

    def sample(self) -> NodeResources:
        """CPU busy percent over the last whole interval (in the first, since the meter
        was made), and memory."""
        cpu = self._busy
        if cpu is None:
            cpu = _busy(self._made, self._times())
        memory = psutil.virtual_memory()
        return NodeResources(cpu, int(memory.available), int(memory.total))

    def close(self) -> None:
        """Stop sampling (a reading after this is that of the last interval sampled)."""
        self._closed.set()
        if self._sampler is not threading.current_thread():
            self._sampler.join(CLOSE_WAIT_S)


def _busy(before: list[tuple[float, float]], now: list[tuple[float, float]]) -> float:
    """The busy percent of the CPUs between two readings of ``ResourceMeter._times``."""
    busy = sum(b - pb for (b, _), (pb, _) in zip(now, before, strict=False))
    total = sum(t - pt for (_, t), (_, pt) in zip(now, before, strict=False))
    cpu = 100.0 * busy / total if total > 0 else 0.0
    return min(100.0, max(0.0, cpu))
