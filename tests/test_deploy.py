"""The systemd units in ``deploy/systemd``: systemd accepts them, and their command line,
run as the node unit runs it, serves a system and stops as the unit stops it (SIGTERM
to the controller alone, KillMode=mixed) leaving no process and no /dev/shm segment."""

from __future__ import annotations

import configparser
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import psutil
import pytest
from conftest import alive, eventually
from sample_modules import Collector, Counter

from pb3a import System
from pb3a.transport.shm import live_segments

pytestmark = pytest.mark.timeout(120)

REPO = Path(__file__).resolve().parent.parent
UNITS = REPO / "deploy" / "systemd"
INSTALLED = "/opt/pb3a/venv/bin/pb3a"         # where the units expect the pb3a command


def _unit(name: str) -> configparser.ConfigParser:
    unit = configparser.ConfigParser(interpolation=None, strict=True)
    unit.optionxform = str                         # systemd keys are case-sensitive
    unit.read_string((UNITS / name).read_text())
    return unit


def _environment_file(name: str) -> dict[str, str]:
    lines = (UNITS / name).read_text().splitlines()
    return dict(line.split("=", 1) for line in lines if line and not line.startswith("#"))


def _exec_start(unit: configparser.ConfigParser, env: dict[str, str]) -> list[str]:
    """ExecStart as systemd expands it: ``${X}`` is one word, a lone ``$X`` is split at
    whitespace (zero or more words); the installed pb3a is this interpreter's."""
    words: list[str] = []
    for word in unit["Service"]["ExecStart"].split():
        if re.fullmatch(r"\$\w+", word):
            words += env[word[1:]].split()
        else:
            words.append(re.sub(r"\$\{(\w+)\}", lambda match: env[match[1]], word))
    assert words[0] == INSTALLED
    return [sys.executable, "-m", "pb3a", *words[1:]]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                    reason="systemd-analyze (systemd) is not installed here")
def test_systemd_accepts_the_units(tmp_path: Path) -> None:
    names = ["pb3a-node.service", "pb3a-modules.service"]
    for name in names:                 # (verify insists that the command exists)
        text = (UNITS / name).read_text().replace(INSTALLED, f"{sys.executable} -m pb3a")
        (tmp_path / name).write_text(text)
    checked = subprocess.run(["systemd-analyze", "verify", *(str(tmp_path / n) for n in names)],
                             capture_output=True, text=True, timeout=60, check=False)
    said = [line for line in (checked.stdout + checked.stderr).splitlines()
            if any(name in line for name in names)]
    assert checked.returncode == 0 and not said, checked.stdout + checked.stderr


def test_the_node_unit_serves_a_system_and_stops_leaving_nothing_behind(tmp_path: Path) -> None:
    unit = _unit("pb3a-node.service")
    assert unit["Service"]["KillMode"] == "mixed"       # SIGTERM to the controller alone
    assert unit["Service"]["Environment"] == "PB3A_KEY_FILE=/etc/pb3a/cluster.key"
    key_file = tmp_path / "cluster.key"                 # the test's key, as the unit reads it
    key_file.write_text(os.environ["PB3A_KEY"])
    key_file.chmod(0o600)
    env = {**_environment_file("node.env"), "PB3A_LISTEN": "tcp://127.0.0.1:0",
           "PB3A_NODE_OPTIONS": "--max-cpu 101"}
    run_env = {**os.environ, "PB3A_KEY_FILE": str(key_file),
               "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), str(REPO)])}
    del run_env["PB3A_KEY"]
    daemon = subprocess.Popen(_exec_start(unit, env), env=run_env, stdout=subprocess.PIPE,
                              text=True)
    try:
        banner = daemon.stdout.readline().strip()
        node, _, address = banner.removeprefix("node ").partition(" at ")
        assert node == env["PB3A_NODE"], banner
        system = System("unit").node(node, address=address)
        system.add("tick", Counter, node=node, period=0.002)
        system.add("got", Collector, node=node)
        system.link("tick.out", "got.x")                  # a ring in /dev/shm on that node
        with system.launch() as run:
            eventually(lambda: run.state("got")["received"] > 50, timeout=30,
                       what="values through the node's ring")
            below = [p.pid for p in psutil.Process(daemon.pid).children(recursive=True)]
            segments = [name for pid in below for name in live_segments(pid)]
            assert segments, "the node's ring should be in /dev/shm"
            daemon.send_signal(signal.SIGTERM)             # systemctl stop
            stop_timeout = float(unit["Service"]["TimeoutStopSec"])
            assert daemon.wait(timeout=stop_timeout) == 0
            eventually(lambda: not any(map(alive, below)), timeout=5,
                       what="the executor and its workers to end with the controller")
            assert [name for pid in below for name in live_segments(pid)] == []
            assert run._launcher.wait_health(node, up=False, timeout=10)   # seen as lost
    finally:
        if daemon.poll() is None:
            daemon.kill()
            daemon.wait(5)
        daemon.stdout.close()
