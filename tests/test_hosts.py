"""Nodes on other hosts: each in a network namespace of its own, joined to the test's by
a veth pair, so that loopback is not shared and every address a node hands out must be
one the other hosts can reach. The namespaces are made and removed here (root and
``ip netns`` are needed; the tests are skipped, saying why, where they cannot be made)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import eventually
from sample_modules import Collector, Counter, Relay

from pb3a import System

REPO = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.timeout(120)


def _can_make_namespaces() -> str:
    """Why namespaces cannot be made here, or an empty string."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "the ip command (iproute2) is missing"
    probe = f"pb3a-probe-{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True,
                          check=False)
    if made.returncode != 0:
        return f"ip netns add failed: {made.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], check=False)
    return ""


WHY_NOT = _can_make_namespaces()


class Host:
    """A network namespace with one veth link to the test's namespace."""

    def __init__(self, name: str, subnet: int) -> None:
        self.ns = f"pb3a-{os.getpid()}-{name}"
        self.outer = f"pb{os.getpid() % 100000}{name}"[:15]     # interface names: 15 chars
        self.inner = f"{self.outer[:13]}in"
        self.address = f"10.231.{subnet}.2"
        self.gateway = f"10.231.{subnet}.1"
        self.daemons: list[subprocess.Popen[str]] = []
        for command in (["ip", "netns", "add", self.ns],
                        ["ip", "link", "add", self.outer, "type", "veth", "peer", "name",
                         self.inner],
                        ["ip", "link", "set", self.inner, "netns", self.ns],
                        ["ip", "addr", "add", f"{self.gateway}/24", "dev", self.outer],
                        ["ip", "link", "set", self.outer, "up"],
                        *self.inside(["ip", "addr", "add", f"{self.address}/24", "dev",
                                      self.inner],
                                     ["ip", "link", "set", self.inner, "up"],
                                     ["ip", "link", "set", "lo", "up"])):
            subprocess.run(command, check=True, capture_output=True)

    def inside(self, *commands: list[str]) -> list[list[str]]:
        return [["ip", "netns", "exec", self.ns, *command] for command in commands]

    def start(self, *pb3a: str) -> str:
        """Run ``pb3a ...`` (a daemon) in this host; the line it prints when ready."""
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), str(REPO)])}
        daemon = subprocess.Popen(*self.inside([sys.executable, "-m", "pb3a", *pb3a]),
                                  stdout=subprocess.PIPE, text=True, env=env)
        self.daemons.append(daemon)
        return daemon.stdout.readline().strip()

    def remove(self) -> None:
        for daemon in self.daemons:
            daemon.terminate()
            try:
                daemon.wait(15)
            except subprocess.TimeoutExpired:
                daemon.kill()
                daemon.wait(5)
            daemon.stdout.close()
        subprocess.run(["ip", "netns", "del", self.ns], check=False, capture_output=True)
        subprocess.run(["ip", "link", "del", self.outer], check=False, capture_output=True)


@pytest.fixture
def far_host() -> Iterator[Host]:
    if WHY_NOT:
        pytest.skip(WHY_NOT)
    host = Host("b", 100 + os.getpid() % 100)
    try:
        yield host
    finally:
        host.remove()


def test_links_cross_to_a_node_on_another_host_both_ways(far_host: Host) -> None:
    banner = far_host.start("node", "start", "--name", "b", "--listen",
                            f"tcp://{far_host.address}:7100", "--max-cpu", "101")
    assert banner == f"node b at tcp://{far_host.address}:7100"
    system = System("two-hosts").node("a").node("b", address=f"tcp://{far_host.address}:7100")
    system.add("tick_a", Counter, node="a", period=0.002)
    system.add("tick_b", Counter, node="b", period=0.002)
    system.add("at_b", Collector, node="b")
    system.add("at_a", Collector, node="a")
    system.add("relay", Relay, node="a")
    system.link("tick_a.out", "at_b.x")          # from the launcher's host to the other
    system.link("tick_b.out", "relay.x")         # and back, through a module that moves
    system.link("relay.out", "at_a.x")
    with system.launch() as run:
        for name in ("at_b", "at_a"):
            eventually(lambda name=name: run.state(name)["received"] > 100, timeout=30,
                       what=f"values at {name} across the hosts")
        for to in ("b", "a", "b", "a"):
            assert run.migrate("relay", to=to).destination == to
        before = run.state("at_a")["received"]
        eventually(lambda: run.state("at_a")["received"] > before + 100, timeout=30,
                   what="values after moving relay between the hosts")
        states = {name: run.state(name) for name in ("at_a", "at_b")}
        links = run.stats().links
    for state in states.values():
        assert state["out_of_order"] == 0 and state["duplicates"] == 0
    assert {key: link.transport for key, link in links.items()} == {
        "tick_a.out->at_b.x": "zmq", "tick_b.out->relay.x": "zmq",
        "relay.out->at_a.x": "shm"}                   # relay is back beside at_a
    assert all(link.link_failures == 0 for link in links.values())
