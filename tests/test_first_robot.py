"""The tutorial ``docs/first_robot.md``: its files are the examples' as they are, and its
steps, run as a reader runs them (``rave start``, ``pb3a run``, then ``pb3a`` commands
from another shell), drive, tune, swap, adapt and move the robot."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
from conftest import eventually, rave_started

import examples.first_robot
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient

REPO = Path(__file__).resolve().parents[1]
TUTORIAL = (REPO / "docs" / "first_robot.md").read_text()
MODULES = REPO / "examples" / "first_robot.py"
SYSTEM = REPO / "examples" / "first_robot.toml"


def _blocks(language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", TUTORIAL, re.DOTALL)


def test_the_tutorial_shows_the_example_files_as_they_are_and_its_test_passes() -> None:
    """Every Python block of the tutorial is the example module's text, but the one that
    tests it, which is run; its configuration block is the example file's."""
    code = MODULES.read_text()
    test, *shown = sorted(_blocks("python"), key=lambda block: "ModuleHarness" not in block)
    assert "ModuleHarness" in test and shown
    for block in shown:
        assert block in code, block
    (toml,) = _blocks("toml")
    assert toml in SYSTEM.read_text()
    exec(test, {"np": np, "Wanderer": examples.first_robot.Wanderer})


def _pb3a(*argv: str) -> str:
    """``pb3a ARGV`` from another shell; what it printed (it must succeed)."""
    done = subprocess.run([sys.executable, "-m", "pb3a", *argv], capture_output=True,
                          text=True, timeout=60, cwd=REPO)
    assert done.returncode == 0, (argv, done.stdout, done.stderr)
    return done.stdout.strip()


def test_the_tutorial_s_steps_drive_tune_swap_adapt_and_move_the_robot(
        tmp_path: Path) -> None:
    with rave_started("room", robots=1) as (world, served):    # (free ports, as a test's)
        assert world.startswith("world room at ")
        name, robot = served.split()[1::2]                  # robot r1 at ADDR
        assert name == "r1", served
        system = tmp_path / "first_robot.toml"
        system.write_text(SYSTEM.read_text().replace("tcp://127.0.0.1:7101", robot))
        client = ControlClient(ClusterKey.load(), robot)
        run = subprocess.Popen([sys.executable, "-m", "pb3a", "run", str(system)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               cwd=REPO, start_new_session=True)
        try:
            first = run.stdout.readline()
            assert first.startswith("pb3a: system 'first-robot' running"), first
            address = first.split()[-1]

            def moved_from(start: list[float]) -> bool:
                now = client.call("sensors")["gps"]
                return float(np.hypot(now[0] - start[0], now[1] - start[1])) > 0.2

            def state(module: str) -> dict:
                return json.loads(_pb3a("state", address, module))
            start = client.call("sensors")["gps"]
            eventually(lambda: moved_from(start), what="the robot driving")       # 3.
            assert state("pilot") == {"speed": 0.3, "clearance": 0.6, "turn": 1.0}
            _pb3a("set", address, "pilot", "speed=0.5")                             # 4.
            assert state("pilot")["speed"] == 0.5
            assert _pb3a("swap", address, "pilot", "examples.first_robot:WallFollower") == (
                "pilot is now examples.first_robot:WallFollower; state kept: clearance, "
                "speed, turn")                                                      # 5.
            _pb3a("set", address, "pilot", "clearance=0.3", "speed=0.6")            # 6.
            eventually(lambda: state("careful")["near_misses"] > 0, timeout=90,
                       what="a near miss the agent saw")
            assert state("pilot")["speed"] < 0.6
            moved = _pb3a("migrate", address, "pilot", "base")                      # 7.
            assert moved.startswith("pilot: robot -> base, paused "), moved
            start = client.call("sensors")["gps"]
            eventually(lambda: moved_from(start), what="the robot driving on")
            os.killpg(run.pid, signal.SIGINT)                                       # 8.
            out, err = run.communicate(timeout=30)
            assert run.returncode == 0 and out.rstrip().endswith("pb3a: stopped cleanly"), err
        finally:
            client.close()
            if run.poll() is None:
                os.killpg(run.pid, signal.SIGKILL)
                run.communicate(timeout=10)
