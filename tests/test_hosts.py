"""Nodes on other hosts: each in a network namespace of its own, joined to the test's by
a veth pair, so that loopback is not shared and every address a node hands out must be
one the other hosts can reach. The namespaces are made and removed here (root and
``ip netns`` are needed; the tests are skipped, saying why, where they cannot be made)."""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import psutil
import pytest
from conftest import alive, eventually
from sample_modules import Chain, Collector, Copies, Counter, Journal, Relay, Stamped

from pb3a import RuntimeFailure, RuntimeTimeout, System
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient

REPO = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.timeout(120)
OUTAGE_S = 8.0          # how long a cut cable stays cut, at least


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


class Lan:
    """A bridge in the test's namespace (the launcher's host) and hosts plugged into it,
    each a network namespace with one veth cable: a small lab network. A test's second
    network is ``Lan(net=1)``; with ``here=False`` the launcher's host is not on it."""

    def __init__(self, net: int = 0, here: bool = True) -> None:
        tag = os.getpid() % 100000
        self.subnet = f"10.{231 + net}.{100 + tag % 100}"
        self.bridge = f"pb{tag}n{net}"
        self.address = f"{self.subnet}.1" if here else None   # the launcher's host here
        self.hosts: list[Host] = []
        self.cables = 0                                # hosts plugged in (their addresses)
        _run(["ip", "link", "add", self.bridge, "type", "bridge"])
        if here:
            _run(["ip", "addr", "add", f"{self.address}/24", "dev", self.bridge])
        _run(["ip", "link", "set", self.bridge, "up"])

    def host(self, name: str) -> Host:
        host = Host(self, name)
        self.hosts.append(host)
        return host

    def remove(self) -> None:
        for host in self.hosts:
            host.remove()
        subprocess.run(["ip", "link", "del", self.bridge], check=False, capture_output=True)


class Host:
    """A network namespace plugged into the lan by a veth cable (and into other lans by
    more cables: ``plug``)."""

    def __init__(self, lan: Lan, name: str) -> None:
        self.name = name
        self.ns = f"pb3a-{os.getpid()}-{name}"
        self.cables: list[str] = []
        self.daemons: list[subprocess.Popen[str]] = []
        _run(["ip", "netns", "add", self.ns])
        _run(*self.inside(["ip", "link", "set", "lo", "up"]))
        self.address = self.plug(lan)

    def plug(self, lan: Lan) -> str:
        """Plug this host into ``lan`` with a cable of its own; its address there."""
        lan.cables += 1
        address = f"{lan.subnet}.{1 + lan.cables}"
        cable = f"{lan.bridge}{self.name}"[:13]       # interface names: 15 characters
        inner = f"{cable}in"
        self.cables.append(cable)
        for command in (["ip", "link", "add", cable, "type", "veth", "peer", "name", inner],
                        ["ip", "link", "set", inner, "netns", self.ns],
                        ["ip", "link", "set", cable, "master", lan.bridge],
                        ["ip", "link", "set", cable, "up"],
                        *self.inside(["ip", "addr", "add", f"{address}/24", "dev", inner],
                                     ["ip", "link", "set", inner, "up"])):
            _run(command)
        return address

    def inside(self, *commands: list[str]) -> list[list[str]]:
        return [["ip", "netns", "exec", self.ns, *command] for command in commands]

    def start(self, *pb3a: str) -> str:
        """Run ``pb3a ...`` (a daemon) in this host; the line it prints when ready."""
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), str(REPO)])}
        daemon = subprocess.Popen(*self.inside([sys.executable, "-m", "pb3a", *pb3a]),
                                  stdout=subprocess.PIPE, text=True, env=env)
        self.daemons.append(daemon)
        return daemon.stdout.readline().strip()

    def node(self, name: str) -> str:
        """Start a node controller here for node ``name``; its address."""
        address = f"tcp://{self.address}:7100"
        assert self.start("node", "start", "--name", name, "--listen", address,
                          "--max-cpu", "101") == f"node {name} at {address}"
        return address

    def executors(self) -> list[int]:
        """The pids of the executors this host's node controller runs."""
        return [child.pid for daemon in self.daemons
                for child in psutil.Process(daemon.pid).children()
                if "resource_tracker" not in " ".join(child.cmdline())]

    def cut(self, up: bool = False) -> None:
        """Unplug this host's cables (or plug them back)."""
        for cable in self.cables:
            _run(["ip", "link", "set", cable, "up" if up else "down"])

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
        for cable in self.cables:
            subprocess.run(["ip", "link", "del", cable], check=False, capture_output=True)


def _run(command: list[str]) -> None:
    subprocess.run(command, check=True, capture_output=True)


@pytest.fixture
def lan() -> Iterator[Lan]:
    if WHY_NOT:
        pytest.skip(WHY_NOT)
    network = Lan()
    try:
        yield network
    finally:
        network.remove()


def test_links_cross_to_a_node_on_another_host_both_ways(lan: Lan) -> None:
    system = System("two-hosts").node("a").node("b", address=lan.host("b").node("b"))
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


def test_a_launcher_with_nodes_on_its_loopback_and_on_another_host_listens_where_both_reach_it(
        lan: Lan) -> None:
    """Given no address to listen at, the launcher listened towards its first remote
    node: one on this machine's 127.0.0.1 gave 127.0.0.1, where node b, on another host,
    cannot call it back, and the launch was refused ("cannot listen on
    tcp://127.0.0.1:0"), naming an address nobody gave. It listens towards b."""
    with socket.socket() as probe:                  # (a free port of this machine)
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), str(REPO)])}
    here = subprocess.Popen([sys.executable, "-m", "pb3a", "node", "start", "--name", "a",
                             "--listen", address, "--max-cpu", "101"],
                            stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert here.stdout.readline().strip() == f"node a at {address}"
        system = System("loopback-and-far").node("a", address=address)
        system.node("b", address=lan.host("b").node("b"))
        system.add("tick_b", Counter, node="b", period=0.01)
        system.add("at_a", Collector, node="a")
        # (from b: a, on 127.0.0.1, publishes where only this machine reaches it)
        system.link("tick_b.out", "at_a.x")
        with system.launch() as run:
            eventually(lambda: run.state("at_a")["received"] > 0, timeout=30,
                       what="values from node b at this machine's node a")
            listens_at = run.address
    finally:
        here.terminate()
        here.wait(15)
        here.stdout.close()
    assert listens_at.startswith(f"tcp://{lan.address}:"), listens_at


def test_a_node_on_every_interface_of_a_host_with_no_route_out_gives_its_one_address(
        lan: Lan) -> None:
    """A controller listening on every interface prints the address of its default
    route's interface; on a robot's LAN with no gateway it printed loopback's, which a
    user then gave the other machines. A host with one address on a network gives
    that one (with two, loopback's still: which one the others reach is not known)."""
    robot = lan.host("robot")
    assert robot.start("node", "start", "--name", "robot", "--listen", "tcp://0.0.0.0:7100",
                       "--max-cpu", "101") == f"node robot at tcp://{robot.address}:7100"


def test_a_host_on_two_networks_binds_on_one_address_and_advertises_another(
        lan: Lan) -> None:
    # The launcher's host and robot m are on a management network and on the lab's;
    # robot r is on the lab's only. The launcher reaches m's controller on the first;
    # r reaches m where m advertises, and the launcher's node where the launcher
    # chose (the interface towards the nodes), both on the second.
    management = Lan(net=1)
    try:
        m, r = lan.host("m"), lan.host("r")
        m_management = m.plug(management)
        # (on every interface it prints its default route's address, here loopback's:
        # m has no default route, and two networks; tcp://0.0.0.0:7100, printed before,
        # reaches nobody)
        assert m.start("node", "start", "--name", "m", "--listen", "tcp://0.0.0.0:7100",
                       "--max-cpu", "101") == "node m at tcp://127.0.0.1:7100"
        controller = f"tcp://{m_management}:7100"
        system = System("two-networks").node("a")
        system.node("m", address=controller, advertise=m.address).node("r", address=r.node("r"))
        for node in "amr":
            system.add(f"tick_{node}", Counter, node=node, period=0.002)
        for src, dst in ("ar", "ra", "mr", "rm"):
            system.add(f"{src}_to_{dst}", Collector, node=dst)
            system.link(f"tick_{src}.out", f"{src}_to_{dst}.x")
        with system.launch() as run:
            for name in ("ar", "ra", "mr", "rm"):
                eventually(lambda name=f"{name[0]}_to_{name[1]}": run.state(name)["received"]
                           > 50, timeout=30, what=f"values on {name[0]} -> {name[1]}")
            launcher = run.address
        assert launcher.startswith(f"tcp://{lan.address}:")   # not the management address

        wrong = System("wrong-advertise").node("m", address=controller,
                                                advertise=f"{lan.subnet}.99")
        wrong.add("tick", Counter, node="m")
        started = time.monotonic()
        with pytest.raises(RuntimeFailure, match=(
                rf"node m: its executor did not answer within 5 s at tcp://{lan.subnet}\.99:"
                rf"\d+, on the host other nodes reach node m at \({lan.subnet}\.99\); make "
                r"\[nodes\.m\] advertise an address of that machine")):
            wrong.launch()
        assert time.monotonic() - started < 20
        client = ControlClient(ClusterKey.load(), controller)
        try:
            assert client.call("status")["executors"] == {}        # none left running
        finally:
            client.close()
    finally:
        management.remove()


LAB_MODULES = '''
from pb3a import Input, Module

FILE_VERSION = {version}


class Tally(Module):
    """Counts the values it is sent; ``loaded`` says which file its code came from."""

    x = Input(int, policy="queue:100000")
    count = 0
    loaded = 0

    def setup(self):
        self.loaded = FILE_VERSION

    def on_input(self, port):
        port.read()
        self.count += 1
'''


def test_three_hosts_fan_out_move_back_and_forth_and_serve_code(lan: Lan, tmp_path) -> None:
    served = tmp_path / "served"
    served.mkdir()
    (served / "labmods.py").write_text(LAB_MODULES.format(version=1))
    server_host = lan.host("d")
    server = f"tcp://{server_host.address}:7300"
    assert server_host.start("modules", "serve", str(served), "--listen", server).endswith(
        f"at {server}")
    b, c = lan.host("b").node("b"), lan.host("c").node("c")
    system = System("lab", module_servers=[server])
    system.node("a").node("b", address=b).node("c", address=c)
    system.add("src", Counter, node="a", period=0.001)
    system.add("relay", Relay, node="b")
    for node in ("a", "b", "c"):                       # fan-out to every host
        system.add(f"at_{node}", Collector, node=node)
        system.link("relay.out", f"at_{node}.x")
    system.add("tally", "labmods:Tally", node="c")     # code only the module server has
    system.link("src.out", "relay.x")
    system.link("src.out", "tally.x")
    system.add("chain", Chain, node="a")
    with system.launch() as run:
        eventually(lambda: all(run.state(f"at_{n}")["received"] > 50 for n in "abc"),
                   timeout=30, what="values at every host")
        for i in range(100):                           # under the steady flow from src
            run.migrate("relay", to="c" if i % 2 == 0 else "b")
        assert run.migrate("chain", to="c").destination == "c"
        assert {run.where("chain/a"), run.where("chain/b")} == {"c"}
        (served / "labmods.py").write_text(LAB_MODULES.format(version=2))
        run.reload("labmods")
        assert run.state("tally")["loaded"] == 1
        assert "count" in run.swap("tally", "labmods:Tally")
        assert run.state("tally")["loaded"] == 2            # the new file's code runs
        relayed = run.state("relay")["relayed"]
        eventually(lambda: all(run.state(f"at_{n}")["received"] >= relayed for n in "abc"),
                   timeout=30, what="every value relayed before, at every host")
        states = {n: run.state(f"at_{n}") for n in "abc"}
        counted = run.state("tally")["count"]
    for state in states.values():                      # in order, once, none missing
        assert state["out_of_order"] == 0 and state["duplicates"] == 0
        assert state["last"] == state["received"]
    assert counted > 0


def test_a_cut_off_node_fences_itself_its_modules_fail_over_and_it_rejoins(
        lan: Lan, tmp_path: Path) -> None:
    far = lan.host("b")
    stops = tmp_path / "stops"
    system = System("cut").node("a").node("b", address=far.node("b"))
    system.add("src", Counter, node="a", period=0.002)
    system.add("at_b", Collector, node="b")
    system.add("at_a", Collector, node="a")
    system.add("stamp", Stamped, node="b", restart="fresh", state={"stopped_file": str(stops)})
    system.add("copies", Copies, node="a")
    system.link("src.out", "at_b.x")
    system.link("src.out", "at_a.x")
    system.link("stamp.out", "copies.x")
    with system.launch() as run:
        eventually(lambda: run.state("at_b")["received"] > 20, timeout=30, what="values at b")
        (executor,) = far.executors()
        cut = time.monotonic()
        far.cut()                                  # the far side goes on running, alone
        lost = run._launcher.wait_health("b", up=False, timeout=10)
        detected = time.monotonic() - cut
        eventually(lambda: not alive(executor), timeout=10,
                   what="the cut-off executor stopping by itself (the cable still down)")
        eventually(lambda: len(run.state("copies")["copies"]) == 2,
                   what="the failed-over copy of stamp delivering on a")
        events = [(e.kind, e.subject) for e in run.events()]
        stats = run.stats()
        before = run.state("at_a")["received"]
        eventually(lambda: run.state("at_a")["received"] > before + 50, what="a goes on")
        # an outage of 8 s (the launcher's connection to the controller, made before the
        # cut, was then in TCP's retransmission backoff: b rejoined 4-10 s after the cable
        # was back, where a new connection is answered at once)
        run.wait(max(0.0, OUTAGE_S - (time.monotonic() - cut)))
        far.cut(up=True)
        back = time.monotonic()
        eventually(lambda: run.stats().nodes["b"].up, timeout=20, what="b admitted again")
        rejoin_s = time.monotonic() - back
        assert run.migrate("stamp", to="b").destination == "b"
        moved_back = run.state("copies")["received"]
        eventually(lambda: run.state("copies")["received"] > moved_back + 50,
                   what="values of stamp moved back to b")
        copies, rejoined = run.state("copies"), run.stats().nodes["b"]
    assert lost and detected < 3.0, f"the cut was detected after {detected:.2f} s"
    assert ("node_lost", "b") in events and ("module_failed_over", "stamp") in events
    assert stats.nodes["b"].up is False and "at_b" not in stats.modules
    assert any("node b lost" in failure for failure in stats.failures)
    stopped = dict(line.split() for line in stops.read_text().splitlines())
    old, _ = copies["copies"]                   # moving back kept the copy it was
    assert float(stopped[old]) < copies["first_at"][1], "two copies delivered at once"
    assert copies["stale"] == 0 and rejoined.epoch == 2
    assert rejoin_s < 3.0, f"b rejoined {rejoin_s:.2f} s after the cable was back"


def test_a_module_of_a_node_cut_off_as_the_system_stops_is_unconfirmed_not_killed(
        lan: Lan, tmp_path: Path) -> None:
    """The system stopped 0.5 s after node b's cable was cut (b silent, not yet lost):
    b's module was named in ``not_torn_down``, and ``pb3a run`` said its worker was
    killed, its teardown not run, where b fenced itself and ran the teardown (nothing
    here could reach that worker). It is named ``unreached``, its node unconfirmed, and
    its teardown runs on b, the cable still down."""
    far = lan.host("b")
    journal = tmp_path / "journal"
    system = System("cut-as-it-stops").node("a").node("b", address=far.node("b"))
    system.add("far", Journal, node="b", state={"path": str(journal), "label": "far"})
    run = system.launch(timeout=30)
    try:
        far.cut()
        eventually(lambda: run._launcher.silent("b"), what="b silent (two heartbeats missed)")
        run.close(timeout=10.0)
        eventually(lambda: "stop far" in journal.read_text(), timeout=10,
                   what="far torn down on b, fenced")
    finally:
        run.close()                                  # (nothing, once closed)
    assert run.not_torn_down == []
    assert run.unconfirmed == ["b"]
    assert run.unreached == {"b": ["far"]}


def test_a_node_controller_not_reached_is_told_refused_or_unanswered(lan: Lan) -> None:
    """A launch whose node controller did not answer said, whatever the reason, "start
    one there": also to someone whose controller ran, listening on 127.0.0.1 only, and
    to someone whose robot was cut off. A plain connection there now tells which: the
    port refused (nothing listens there: start one, or see where it listens), something
    accepted that is no controller answering (a frozen one), or the host did not
    answer (the machine, the network, a firewall). The three are nodes of one launch,
    each on a host of its own: their starts run side by side (one 5 s wait, not three),
    and each is named with its own reason."""
    refused, frozen, cut = lan.host("b"), lan.host("c"), lan.host("d")
    assert refused.start("node", "start", "--name", "b", "--listen", "tcp://127.0.0.1:7100",
                         "--max-cpu", "101") == "node b at tcp://127.0.0.1:7100"
    frozen_at = frozen.node("c")                   # on its address, but stopped
    os.kill(frozen.daemons[-1].pid, signal.SIGSTOP)
    try:
        assert cut.node("d")                       # a robot whose controller runs, ...
        cut.cut()                                  # ... cut off
        system = System("unreached").node("a")
        for name, host in (("b", refused), ("c", frozen), ("d", cut)):
            system.node(name, address=f"tcp://{host.address}:7100")
            system.add(f"far_{name}", Collector, node=name)
        started = time.monotonic()
        with pytest.raises(RuntimeFailure) as raised:     # (not all timed out: b refused)
            system.launch()
        assert time.monotonic() - started < 10
    finally:
        os.kill(frozen.daemons[-1].pid, signal.SIGCONT)
    head, *lines = str(raised.value).split("\n  ")
    assert head == ("system 'unreached' was not started: 3 of its 3 remote nodes did not "
                    "start an executor (no module was started):"), head
    said = dict(zip("bcd", lines, strict=True))

    def prefix(name: str, host: Host) -> str:
        return (rf"node {name}: no node controller answered at "
                rf"tcp://{re.escape(host.address)}:7100 within 5 s; ")

    assert re.match(rf"node b: no node controller at tcp://{re.escape(refused.address)}:7100; "
                    rf"nothing listens on port 7100 at "
                    rf"{re.escape(refused.address)} \(the connection was refused\): start a "
                    r"node controller there .*one that listens on 127\.0\.0\.1, or on "
                    r"another of that machine's addresses, is not reached there",
                    said["b"]), said["b"]
    assert re.match(prefix("c", frozen) + rf"something accepts connections on port 7100 at "
                    rf"{re.escape(frozen.address)}, but does not answer as a node "
                    r"controller: check that it is one", said["c"]), said["c"]
    assert re.match(prefix("d", cut) + rf"{re.escape(cut.address)} did not answer on port "
                    r"7100 \((no answer|No route to host)\): check that the machine is up "
                    r"and on this network", said["d"]), said["d"]
    assert frozen_at == f"tcp://{frozen.address}:7100"


def test_a_node_that_does_not_reach_another_s_publications_is_named_with_the_fix(
        lan: Lan) -> None:
    """Node r, on the lab's network only, cannot reach node m, on another network that
    only the launcher's host shares: the launch failed "no hand-shake with the sender of
    tick.out at tcp://...", naming neither node nor what to open or set (deploy.md's
    table had to)."""
    other = Lan(net=1)
    try:
        r, m = lan.host("r"), other.host("m")
        system = System("unreached").node("a").node("r", address=r.node("r"))
        system.node("m", address=m.node("m"))
        system.add("tick", Counter, node="m", period=0.01)
        system.add("at_r", Collector, node="r")
        system.link("tick.out", "at_r.x")
        with pytest.raises(RuntimeTimeout, match=(
                rf"node r: no hand-shake with the sender of tick\.out at "
                rf"tcp://{re.escape(m.address)}:\d+ within 10 s: node r does not reach where m "
                r"publishes; open the ephemeral ports of m to r, or set advertise in "
                r"\[nodes\.m\] to an address r reaches there")):
            system.launch()
    finally:
        other.remove()
