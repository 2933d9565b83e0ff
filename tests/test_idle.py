"""Idle modules cost no CPU: waiting blocks, it does not spin."""

from __future__ import annotations

import time

import psutil
import pytest
from conftest import eventually
from sample_modules import Idle

from pb3a import System

# alone: it loads the CPUs or measures against them (see the Makefile's test target)
pytestmark = [pytest.mark.timeout(60), pytest.mark.serial]


def _cpu_seconds(pids: list[int]) -> float:
    total = 0.0
    for pid in pids:
        times = psutil.Process(pid).cpu_times()
        total += times.user + times.system
    return total


def test_ten_idle_modules_use_under_five_percent_of_a_core() -> None:
    system = System("idle")
    for i in range(10):
        system.add(f"idle{i}", Idle)
    with system.launch() as run:
        pids = eventually(lambda: [m.pid for m in run.stats().modules.values()
                                   if m.pid], what="worker pids")
        assert len(set(pids)) == 10
        time.sleep(0.5)                      # let start-up work finish before measuring
        before, started = _cpu_seconds(pids), time.monotonic()
        time.sleep(3.0)                      # the measurement window itself
        used = _cpu_seconds(pids) - before
        elapsed = time.monotonic() - started
    share = used / elapsed
    assert share < 0.05, f"10 idle modules used {share:.1%} of a core"
