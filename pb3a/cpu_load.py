"""``CPULoad``: hold chosen CPUs busy at chosen levels, for stress runs and experiments.

Each loaded CPU gets burner processes pinned to it that spin for a share of every
10 ms period and sleep the rest (so the load is smooth at any sampling interval, not
on and off). Twice a second a controller thread reads each CPU's busy time, as
``psutil.cpu_percent`` does, and corrects the share, so the CPU reads the level asked
whatever else runs there: the burners top up the rest, and back off when that alone
exceeds the level. Use it as a context manager: leaving the block stops every burner
(and a burner whose owner died stops by itself).
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Mapping
from typing import Any

import psutil

from pb3a.node.workers import forkserver_context
from pb3a.processes import start_without_main

PERIOD_S = 0.01           # one busy-then-idle cycle of a burner
ADJUST_S = 0.5            # how often the controller corrects the burners' share
GAIN = 0.8                # share of the error corrected at each adjustment
BURNER_START_S = 30.0     # a burner's start from the forkserver, at the most


class CPULoad:
    """Hold each CPU of ``levels`` (CPU number -> percent busy) at its level.

    ``burners_per_cpu`` processes share each CPU's load: more than one makes the CPU's
    other tasks wait longer for their turn at the same level (at 100 %, two burners
    leave a third task a third of the CPU instead of half).
    """

    def __init__(self, levels: Mapping[int, float], *, burners_per_cpu: int = 1) -> None:
        present = sorted(os.sched_getaffinity(0))
        for cpu, level in levels.items():
            if cpu not in present:
                raise ValueError(f"cannot load CPU {cpu}: this process may run on CPUs "
                                 f"{', '.join(map(str, present))} only")
            if not 0.0 <= level <= 100.0:
                raise ValueError(f"the level for CPU {cpu} is {level:g}: give a percent "
                                 "from 0 to 100")
        if burners_per_cpu < 1:
            raise ValueError(f"burners_per_cpu is {burners_per_cpu}: give 1 or more")
        self.levels = dict(levels)
        self.readings: dict[int, float] = {}   # each CPU's busy percent, last adjustment
        self._burners_per_cpu = burners_per_cpu
        # (the forkserver PB3A starts its workers from: quick, and safe from a threaded
        # process)
        self._context = forkserver_context()
        self._shares = {cpu: self._context.RawValue("d", level / 100.0)
                        for cpu, level in self.levels.items()}
        self._stop = self._context.Event()
        self._stopped = threading.Event()
        self._burners: list[Any] = []
        self._controller = threading.Thread(target=self._control, daemon=True,
                                            name="pb3a-cpu-load")

    @property
    def pids(self) -> list[int]:
        """The burner processes' ids."""
        return [burner.pid for burner in self._burners]

    @property
    def running(self) -> bool:
        """True from ``start`` to ``stop``."""
        return bool(self._burners) and not self._stopped.is_set()

    def start(self) -> None:
        """Start the burners and the controller."""
        for cpu, share in self._shares.items():
            for _ in range(self._burners_per_cpu):
                burner = self._context.Process(
                    target=_burn, args=(cpu, share, self._stop, os.getpid()), daemon=True,
                    name=f"pb3a-burn-cpu{cpu}")
                self._burners.append(burner)
                # (the forkserver the workers use may be frozen: a start waits so long)
                start_without_main(burner, timeout=BURNER_START_S)
        self._controller.start()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop every burner (killed if it has not ended after ``timeout`` seconds)."""
        self._stopped.set()
        self._stop.set()
        if self._controller.is_alive():
            self._controller.join(timeout)
        deadline = time.monotonic() + timeout
        for burner in self._burners:
            burner.join(max(0.0, deadline - time.monotonic()))
            if burner.is_alive():
                burner.kill()
                burner.join(1.0)

    def __enter__(self) -> CPULoad:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _control(self) -> None:
        before = _busy_and_total()
        while not self._stopped.wait(ADJUST_S):
            now = _busy_and_total()
            for cpu, share in self._shares.items():
                busy, total = (now[cpu][i] - before[cpu][i] for i in (0, 1))
                if total <= 0:
                    continue
                reading = 100.0 * busy / total
                self.readings[cpu] = reading
                error = (self.levels[cpu] - reading) / 100.0
                share.value = min(1.0, max(0.0, share.value + GAIN * error))
            before = now


def _busy_and_total() -> list[tuple[float, float]]:
    """Per CPU: busy and total seconds since boot, counted as psutil.cpu_percent does
    (guest time is already in user time; idle and I/O wait are not busy)."""
    found = []
    for times in psutil.cpu_times(percpu=True):
        total = sum(times) - getattr(times, "guest", 0.0) - getattr(times, "guest_nice", 0.0)
        found.append((total - times.idle - getattr(times, "iowait", 0.0), total))
    return found


def _burn(cpu: int, share: Any, stop: Any, owner: int) -> None:
    """In a burner: spin ``share`` of every period on ``cpu`` until told to stop or
    until its owner is gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)     # a terminal's Ctrl-C: the owner decides
    signal.signal(signal.SIGHUP, signal.SIG_IGN)     # (its closing: the same)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)    # (the forkserver ignores it)
    os.sched_setaffinity(0, [cpu])
    start = time.monotonic()
    while True:
        busy_until = start + share.value * PERIOD_S
        while time.monotonic() < busy_until:
            pass
        start += PERIOD_S
        left = start - time.monotonic()
        if left < 0:                    # it did not get the CPU for a while: start afresh
            start, left = time.monotonic(), 0.0
        if stop.wait(left) or not _alive(owner):
            return


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True
