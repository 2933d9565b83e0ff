"""RAVE served: a world stepped in real time, one robot server process per robot on
an authenticated resource port, and a PB3A driver module that drives a robot through
it and can be re-pointed to another robot while running."""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import psutil
import pytest
from conftest import HeldKey, alive, eventually, rave_started, unused_port
from sample_modules import Cruise, Spin

from pb3a import RuntimeFailure, RuntimeTimeout, System
from pb3a.transport.addresses import host_of
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient
from rave import World, cli, render
from rave.server import RobotServers, WorldProcess, WorldServer
from rave.sonar import COUNT as SONARS


@pytest.fixture
def served():
    world = World.load("rave/worlds/arena.toml", seed=2)       # r1 sim, r2 hardware
    server = WorldServer(world)
    robots = RobotServers(server.address, list(world.robots))
    clients = {name: ControlClient(ClusterKey.load(), address)
               for name, address in robots.addresses.items()}
    yield robots, clients
    for client in clients.values():
        client.close()
    robots.close()
    server.close()


def _gps(client: ControlClient) -> tuple[float, float, float]:
    return tuple(client.call("sensors")["gps"])


def test_a_robot_server_relays_commands_sensors_and_faults(served) -> None:
    robots, clients = served
    sensed = clients["r1"].call("sensors")
    assert len(sensed["sonar"]) == 16 and sensed["backend"] == "sim"
    start = _gps(clients["r1"])
    clients["r1"].call("drive", v=0.5, w=0.0)
    eventually(lambda: _gps(clients["r1"])[0] > start[0] + 0.2, what="r1 driving")
    clients["r2"].call("inject", fault="motors_off", params={})
    clients["r2"].call("drive", v=0.5, w=0.0)
    still = _gps(clients["r2"])
    after = clients["r1"].call("sensors")["time"] + 0.5
    eventually(lambda: clients["r1"].call("sensors")["time"] > after, what="0.5 s of time")
    assert _gps(clients["r2"]) == pytest.approx(still, abs=1e-6)
    with pytest.raises(RuntimeFailure, match="faults are injected into hardware robots"):
        clients["r1"].call("inject", fault="motors_off", params={})
    with pytest.raises(RuntimeFailure, match="robot r1 has no operation 'describe'"):
        clients["r1"].call("describe")
    # what a request lacks is named (a bare KeyError: 'w' was all it said)
    with pytest.raises(RuntimeFailure, match=r"drive needs v and w \(m/s, rad/s\)"):
        clients["r1"].call("drive", v=0.5)
    with pytest.raises(RuntimeFailure, match="swap needs a backend"):
        clients["r1"].call("swap")
    pids = [process.pid for process in robots._processes.values()]
    robots.close()
    assert not any(alive(pid) for pid in pids)


def test_a_killed_robot_server_stops_answering_and_the_others_serve_on(served) -> None:
    """``kill`` ends one robot's server at once, as a crash would: its calls go
    unanswered, the other robot's server serves on, and a name with no server is
    named with those running."""
    robots, clients = served
    pid = robots._processes["r2"].pid
    robots.kill("r2")
    assert not alive(pid) and set(robots.addresses) == {"r1"}
    with pytest.raises(RuntimeTimeout):
        clients["r2"].call("sensors", timeout=0.5)
    assert len(clients["r1"].call("sensors")["sonar"]) == 16
    with pytest.raises(KeyError, match="no robot server of 'r2' runs; those running: r1"):
        robots.kill("r2")


def test_a_robot_silent_for_the_watchdog_s_of_world_time_is_stopped() -> None:
    """With ``watchdog_s``, a robot none of whose requests came for that long in the
    world's time is stopped, as a Pioneer's controller stops when its client falls
    silent: requests of any kind feed it, a drive sets the robot going again. (Without
    it, the mapping scenario's robot whose server was killed ran on its last command
    for good, circling or sliding along walls into the standby robot's view, which
    mapped it as walls that are not there.)"""
    world = World.load("rave/worlds/arena.toml", seed=2)       # r1 sim, r2 hardware
    server = WorldServer(world, lockstep=True, watchdog_s=1.0)
    client = ControlClient(ClusterKey.load(), server.address)
    r1, r2 = world.robot("r1"), world.robot("r2")
    try:
        client.call("drive", robot="r1", v=0.3, w=0.1)
        client.call("drive", robot="r2", v=0.3, w=0.0)
        for _ in range(4):          # r2's controller moves the world on; r1 is heard too
            client.call("advance", robot="r2", dt=0.5)
            client.call("sensors", robot="r1")
        assert r1.commanded() == pytest.approx((0.3, 0.1)) and r2.commanded() != (0, 0)
        start = r1.gps()
        client.call("advance", robot="r2", dt=0.9)       # r1 silent for 0.9 s: not yet
        assert r1.commanded() == pytest.approx((0.3, 0.1))
        client.call("advance", robot="r2", dt=0.2)       # ... past 1 s: stopped
        assert r1.commanded() == (0.0, 0.0) and r2.commanded() == pytest.approx((0.3, 0.0))
        assert math.dist(r1.gps()[:2], start[:2]) > 0.2  # (it did drive until then)
        client.call("advance", robot="r2", dt=2.0)
        stopped_at = r1.gps()
        client.call("advance", robot="r2", dt=2.0)
        assert r1.gps() == pytest.approx(stopped_at, abs=1e-9)     # it stands
        client.call("drive", robot="r1", v=0.3, w=0.0)              # and goes again
        client.call("advance", robot="r1", dt=3.0)       # (its own advance feeds it)
        assert r1.commanded() == pytest.approx((0.3, 0.0))
        assert math.dist(r1.gps()[:2], stopped_at[:2]) > 0.5
        assert r2.commanded() == (0.0, 0.0)              # r2 silent through r1's 3 s
    finally:
        client.close()
        server.close()
    with World.load("rave/worlds/arena.toml", robots=False) as bare:
        for wrong in (-1.0, math.inf, math.nan):
            with pytest.raises(ValueError, match="watchdog_s is the seconds of silence"):
                WorldServer(bare, watchdog_s=wrong)


def test_a_robot_whose_server_is_killed_is_stopped_by_the_watchdog() -> None:
    """The mapping scenario's ``robot_link`` fault, in a world run in real time: the
    robot driving when its server dies stands within ``watchdog_s`` of world time."""
    world = World.load("rave/worlds/arena.toml", seed=2)
    server = WorldServer(world, watchdog_s=1.0)
    robots = RobotServers(server.address, ["r1"])
    client = ControlClient(ClusterKey.load(), robots.addresses["r1"])
    r1 = world.robot("r1")
    try:
        client.call("drive", v=0.2, w=0.3)
        start = client.call("sensors")["time"]
        # asked for its readings all along (as its driver would), it drives on
        eventually(lambda: client.call("sensors")["time"] > start + 1.5,
                   what="1.5 s of world time")
        with server._lock:
            assert r1.commanded() == pytest.approx((0.2, 0.3))
            heard_at = server._heard["r1"]       # (its last request, before the kill)
        robots.kill("r1")

        def stopped() -> bool:
            with server._lock:
                return r1.commanded() == (0.0, 0.0)
        eventually(stopped, timeout=10.0, what="the silent robot stopped")
        with server._lock:                       # not before a whole watchdog_s of silence
            assert world.time >= heard_at + 1.0 - 1e-9
    finally:
        client.close()
        robots.close()
        server.close()


def test_a_robot_server_signalled_as_it_starts_stops_cleanly(tmp_path, monkeypatch) -> None:
    """SIGTERM while a robot server process starts (held as it loads its key) ends it
    closed, exit status 0, and its owner says it stopped before serving."""
    server = WorldServer(World.load("rave/worlds/arena.toml", seed=2))
    held = HeldKey(tmp_path)
    monkeypatch.setenv("PB3A_KEY_FILE", str(held.path))      # (for the child it spawns)
    monkeypatch.delenv("PB3A_KEY")
    exits: list[int | None] = []
    closing = RobotServers.close

    def close(self: RobotServers, timeout: float = 5.0) -> None:
        processes = list(self._processes.values())
        closing(self, timeout)
        exits.extend(process.exitcode for process in processes)
    monkeypatch.setattr(RobotServers, "close", close)
    failed: list[BaseException] = []

    def start() -> None:
        try:
            RobotServers(server.address, ["r1"])
        except BaseException as exc:        # (what its owner is told)
            failed.append(exc)
    starting = threading.Thread(target=start)
    starting.start()
    try:
        held.wait_for_reader()
        [pid] = held.users()
        os.kill(pid, signal.SIGTERM)
        held.give()
        starting.join(30)
    finally:
        server.close()
    assert not starting.is_alive()
    assert exits == [0]
    assert [str(exc) for exc in failed] == [
        "the robot server of r1 stopped before serving (its error, if any, is in the log "
        "above)"]


def test_a_lockstep_world_advances_only_when_its_controller_asks() -> None:
    world = World.load("rave/worlds/arena.toml", seed=2)       # r1 sim
    server = WorldServer(world, lockstep=True)
    robots = RobotServers(server.address, ["r1"])
    r1 = ControlClient(ClusterKey.load(), robots.addresses["r1"])
    try:
        r1.call("drive", v=0.5, w=0.0)
        before = r1.call("sensors")
        assert r1.call("sensors")["time"] == before["time"] == 0.0   # nobody asked
        assert r1.call("advance", dt=2.0) == pytest.approx(2.0)
        after = r1.call("sensors")
        assert after["time"] == pytest.approx(2.0)
        assert after["gps"][0] == pytest.approx(before["gps"][0] + 1.0, abs=0.02)
        with pytest.raises(RuntimeFailure, match="dt must be between 0 and 10"):
            r1.call("advance", dt=-1.0)
        # a controller's turn in one request: drive, advance, and the readings then
        turned = r1.call("cycle", dt=1.0, v=0.0, w=0.5)
        assert turned["time"] == pytest.approx(3.0)
        assert turned["gps"][:2] == pytest.approx(r1.call("sensors")["gps"][:2])
        assert turned["gps"][0] == pytest.approx(after["gps"][0], abs=0.02)  # on the spot
        assert turned["gps"][2] == pytest.approx(after["gps"][2] + 0.5, abs=0.02)
        assert r1.call("cycle", dt=0.5)["time"] == pytest.approx(3.5)  # the command holds
        with pytest.raises(RuntimeFailure, match="give both v and w"):
            r1.call("cycle", dt=0.1, v=0.2)
    finally:
        r1.close()
        robots.close()
        server.close()
    world = World.load("rave/worlds/arena.toml", seed=2)
    server = WorldServer(world)                                 # real time
    client = ControlClient(ClusterKey.load(), server.address)
    try:
        with pytest.raises(RuntimeFailure, match="serve it in lock-step"):
            client.call("advance", robot="r1", dt=0.1)
    finally:
        client.close()
        server.close()


class _HeldWorld(WorldServer):
    """A world server whose ``sensors`` waits for ``go`` while ``hold`` is set."""

    def __init__(self, world: World, **kwargs) -> None:
        self.hold, self.asked, self.go = threading.Event(), threading.Event(), threading.Event()
        super().__init__(world, **kwargs)

    def _handle(self, op: str, args: dict):
        if op == "sensors" and self.hold.is_set():
            self.asked.set()
            self.go.wait(5.0)
        return super()._handle(op, args)


def test_a_turn_its_driver_gave_up_on_while_the_world_was_busy_does_not_advance_it() -> None:
    """A robot server drops a request it has not begun within the time its caller
    waits, as a device served with ``serve_device`` does: a lock-step turn that timed
    out behind a slow one ran once the world was free, and a controller that asked
    again advanced the world twice."""
    server = _HeldWorld(World.load("rave/worlds/arena.toml", seed=2), lockstep=True)
    robots = RobotServers(server.address, ["r1"])
    slow, r1 = (ControlClient(ClusterKey.load(), robots.addresses["r1"]) for _ in range(2))
    sensing = threading.Thread(target=slow.call, args=("sensors",), daemon=True)
    try:
        server.hold.set()
        sensing.start()
        assert server.asked.wait(10.0)                # relayed: the robot server is busy
        with pytest.raises(RuntimeTimeout):
            r1.call("advance", timeout=0.3, dt=1.0)
        time.sleep(0.2)      # (counted from when the request came there, a moment later)
        server.hold.clear()
        server.go.set()
        sensing.join(5.0)
        assert r1.call("sensors")["time"] == 0.0         # the turn given up: not taken
        assert r1.call("advance", dt=1.0) == pytest.approx(1.0)
    finally:
        server.go.set()
        slow.close()
        r1.close()
        robots.close()
        server.close()


def test_a_world_in_a_process_of_its_own_is_held_then_paced_and_stops_with_its_owner() -> None:
    served = WorldProcess("rave/worlds/arena.toml", seed=2, rate=0.0, hardware=("r1",),
                          add={"r9": (2.0, 6.5, 0.0)})
    client = ControlClient(ClusterKey.load(), served.address)
    try:
        described = client.call("describe")
        assert described["robots"]["r1"]["backend"] == "hardware" and "r9" in described["robots"]
        client.call("drive", robot="r1", v=0.5, w=0.0)
        assert client.call("describe")["time"] == 0.0                # held: no time passes
        assert client.call("pace", rate=20.0) == 0.0                 # its time when paced
        eventually(lambda: client.call("describe")["time"] > 1.0, what="time at 20x")
        held_at = client.call("pace", rate=0.0)
        assert client.call("describe")["time"] == held_at            # held again
        # (inf and 1e-12 killed the stepper: its wait overflowed)
        for rate in (-1.0, math.inf, 1e-12):
            with pytest.raises(RuntimeFailure, match=r"a finite number, 0 \(holds it\) or "
                               rf"at least 1e-06, not {rate}"):
                client.call("pace", rate=rate)
        time = client.call("pace", rate=20.0)
        eventually(lambda: client.call("describe")["time"] > time + 0.5, what="time at 20x")
        with pytest.raises(RuntimeFailure, match="its operations: describe, pace"):
            client.call("fly", robot="r1")
    finally:
        client.close()
        pid = served._process.pid
        served.close()
    assert not alive(pid)


def test_a_world_paced_beyond_what_the_machine_can_still_answers_and_stops() -> None:
    """At a million times real time the world runs as fast as it can, in short holds:
    requests are answered between them and ``close`` stops its stepper."""
    server = WorldServer(World.load("rave/worlds/arena.toml", seed=2), rate=1e6)
    client = ControlClient(ClusterKey.load(), server.address)
    try:
        first = client.call("describe", timeout=2.0)["time"]
        eventually(lambda: client.call("describe", timeout=2.0)["time"] > first,
                   what="the world's time moving on between answers")
    finally:
        client.close()
        server.close()
    assert not server._stepper.is_alive()


def test_a_lockstep_world_refuses_a_pace() -> None:
    server = WorldServer(World.load("rave/worlds/arena.toml", seed=2), lockstep=True)
    client = ControlClient(ClusterKey.load(), server.address)
    try:
        with pytest.raises(RuntimeFailure, match="runs in lock-step: its controller advances"):
            client.call("pace", rate=2.0)
    finally:
        client.close()
        server.close()


@pytest.mark.parametrize(("lockstep", "dt", "refusal"), [
    (False, 0.1, "runs by itself"), (True, -1.0, "dt must be between 0 and 10")])
def test_a_refused_cycle_drives_nothing(lockstep: bool, dt: float, refusal: str) -> None:
    world = World.load("rave/worlds/arena.toml", seed=2)       # r1 sim
    server = WorldServer(world, rate=0.0, lockstep=lockstep)
    client = ControlClient(ClusterKey.load(), server.address)
    try:
        with pytest.raises(RuntimeFailure, match=refusal):
            client.call("cycle", robot="r1", v=0.5, w=0.2, dt=dt)
        assert world.robot("r1")._body.commanded() == (0.0, 0.0)
    finally:
        client.close()
        server.close()


def test_a_served_world_whose_emulator_dies_goes_on_once_the_robot_is_swapped(caplog) -> None:
    world = World.load("rave/worlds/arena.toml", seed=2)       # r2 hardware
    server = WorldServer(world)
    client = ControlClient(ClusterKey.load(), server.address)
    try:
        os.kill(world.robot("r2")._body.emulator.pid, signal.SIGKILL)
        eventually(lambda: "emulator of robot r2 is gone" in caplog.text,
                   what="the failed step logged")
        assert caplog.text.count("emulator of robot r2 is gone") == 1   # once, not per tick
        stuck = client.call("describe")["time"]
        client.call("swap", robot="r2", backend="sim")         # mended, as the error says
        eventually(lambda: client.call("describe")["time"] > stuck + 0.3,
                   what="the world stepping again")
    finally:
        client.close()
        server.close()


def test_a_driver_module_drives_a_robot_and_is_re_pointed_while_running(served) -> None:
    robots, clients = served
    system = System("driven")
    system.add("driver", "agents.robot_driver:RobotDriver",
               state={"resource": robots.addresses["r1"]})
    system.add("pilot", Cruise)
    system.link("driver.sonar", "pilot.sonar")
    system.link("pilot.command", "driver.command")
    with system.launch() as run:
        r1, r2 = _gps(clients["r1"]), _gps(clients["r2"])
        eventually(lambda: math.dist(_gps(clients["r1"])[:2], r1[:2]) > 0.2,
                   timeout=15, what="r1 driven through its server")
        assert run.state("pilot")["scans"] > 0
        run.set_state("driver", resource=robots.addresses["r2"])
        eventually(lambda: math.dist(_gps(clients["r2"])[:2], r2[:2]) > 0.1,
                   timeout=15, what="r2 driven after the driver was re-pointed")
        left = _gps(clients["r1"])
        after = clients["r1"].call("sensors")["time"] + 0.5
        eventually(lambda: clients["r1"].call("sensors")["time"] > after, what="time passing")
        state = run.state("driver")
    assert math.dist(_gps(clients["r1"])[:2], left[:2]) < 0.01        # released: stopped
    assert state["failures"] == 0


def _turning(client: ControlClient) -> bool:
    return abs(client.call("sensors")["velocity"][2]) > 0.1


def test_a_robot_whose_controller_is_gone_is_stopped_after_the_command_timeout(
        served) -> None:
    """Its driver's reading every period fed the robot server's watchdog, so a robot whose
    controller hung, failed or was removed turned on for good (a reviewer's: still
    turning 3 s after ``remove``, 8 s after its worker was killed)."""
    robots, clients = served
    system = System("spun")
    system.add("driver", "agents.robot_driver:RobotDriver",
               state={"resource": robots.addresses["r1"]})
    system.add("pilot", Spin)
    system.link("pilot.command", "driver.command")
    with system.launch() as run:
        eventually(lambda: _turning(clients["r1"]), what="r1 turning")
        run.remove("pilot")
        eventually(lambda: not _turning(clients["r1"]), timeout=10,
                   what="r1 stopped once no command came for the driver's command_timeout")
        state = run.state("driver")
    assert (state["stale"], state["stale_stops"], state["failures"]) == (True, 1, 0)


@pytest.mark.parametrize("change", ["migrate", "swap"])
def test_a_driver_moved_or_swapped_drives_its_robot_on_by_the_command_it_holds(
        served, change) -> None:
    """The driver let go of its robot (stopped it) as it moved or was swapped, and the
    new one never sent the command its input still held: a controller that writes only on
    change (here once) left the robot standing for good (a reviewer's, both ways)."""
    robots, clients = served
    system = System("held").node("a").node("b")
    system.add("driver", "agents.robot_driver:RobotDriver", node="a",
               state={"resource": robots.addresses["r1"], "command_timeout": 0})
    system.add("pilot", Spin, node="a", state={"once": True})
    system.link("pilot.command", "driver.command")
    with system.launch() as run:
        eventually(lambda: _turning(clients["r1"]), what="r1 turning")
        if change == "migrate":
            run.migrate("driver", to="b", timeout=10.0)
        else:
            run.swap("driver", "agents.robot_driver:RobotDriver", timeout=10.0)
        # (the old driver's stop may come a little after the change returns)
        after = clients["r1"].call("sensors")["time"] + 0.5
        eventually(lambda: clients["r1"].call("sensors")["time"] > after, what="time passing")
        assert _turning(clients["r1"]), f"r1 stands after the {change}"
        assert run.state("pilot")["written"] == 1


def test_a_driver_that_cannot_reach_its_robot_says_so_in_the_log() -> None:
    """A driver pointed where no robot server listens (the world not started, a wrong
    port) showed as running, errors 0, and ``pb3a logs --module driver`` was empty."""
    system = System("unreached")
    system.add("driver", "agents.robot_driver:RobotDriver",
               state={"resource": f"tcp://127.0.0.1:{unused_port()}", "silent_after": 2})
    with system.launch() as run:
        said: list[str] = []

        def logged() -> bool:
            said[:] = [entry.message for entry in run.logs(0, module="driver")]
            return any("said on failure (robot_link)" in line for line in said)
        eventually(logged, timeout=15, what="the driver's warnings in the log")
    assert "did not answer 'sensors'" in said[0], said


def test_the_rave_command_serves_a_world_injects_faults_and_renders(tmp_path, capsys) -> None:
    with rave_started("rave/worlds/arena.toml") as lines:
        assert lines[0].startswith("world arena at tcp://127.0.0.1:")
        robots = dict(line.split()[1::2] for line in lines[1:])     # name -> address
        assert set(robots) == {"r1", "r2"}
        assert cli.main(["fault", robots["r2"], "sonar_dead", "--sonars", "3", "4"]) == 0
        client = ControlClient(ClusterKey.load(), robots["r2"])
        try:
            sonar = client.call("sensors")["sonar"]
        finally:
            client.close()
        assert sonar[3] == sonar[4] == 5.0
        assert cli.main(["fault", robots["r1"], "motors_off"]) == 1        # simulated
        said = capsys.readouterr().err     # as the world says it, not at the world's address
        assert said.startswith("rave fault: robot r1 is simulated: faults are injected "
                               "into hardware robots"), said
    assert cli.main(["render", "rave/worlds/lab.toml", "-o", str(tmp_path / "lab.png")]) == 0
    assert (tmp_path / "lab.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # a bundled world by its name, as the scenarios take it (it was "[Errno 2]")
    assert cli.main(["render", "room", "-o", str(tmp_path / "room.png")]) == 0
    assert (tmp_path / "room.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert cli.main(["render", "rooom", "-o", str(tmp_path / "x.png")]) == 1
    assert ("no world 'rooom': the bundled worlds are arena, lab, room, or give the path of a "
            "world file") in capsys.readouterr().err


def test_the_rave_command_serves_on_the_ports_it_is_given_and_names_one_in_use(capsys) -> None:
    """Its servers took free ports, other ones at every start, so a configuration's
    robot addresses were wrong once the simulator was started again: ``--port`` puts
    the world at PORT and robot i at PORT + i; a port in use is named at once, and so is
    a port that leaves none for the last robot."""
    base = unused_port()
    while not all(_free(base + i) for i in (-1, 1, 2)):    # (the second's world: base - 1)
        base = unused_port()
    with rave_started("arena", "--port", str(base)) as lines:
        assert lines == [f"world arena at tcp://127.0.0.1:{base}",
                         f"robot r1 at tcp://127.0.0.1:{base + 1}",
                         f"robot r2 at tcp://127.0.0.1:{base + 2}"], lines
        client = ControlClient(ClusterKey.load(), f"tcp://127.0.0.1:{base + 2}")
        try:
            assert len(client.call("sensors")["sonar"]) == SONARS     # (r2 answers)
        finally:
            client.close()
        # a second simulator, its r1 on the first's world port: that is named, none starts
        assert cli.main(["start", "arena", "--port", str(base - 1)]) == 1
        said = capsys.readouterr().err
        assert said.startswith(f"rave start: cannot listen on tcp://127.0.0.1:{base}: port "
                               f"{base} is in use"), said
    assert cli.main(["start", "arena", "--port", "65534"]) == 1
    assert "--port 65534 leaves no port for robot 2 of 2" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["start", "arena", "--port", "70000"])
    assert "'70000' is not a port" in capsys.readouterr().err


def _free(port: int) -> bool:
    with socket.socket() as probe:
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def test_the_rave_command_on_every_interface_prints_addresses_rave_fault_takes(
        capsys) -> None:
    """``rave start --listen 0.0.0.0`` (to serve robots to other machines) prints this
    machine's address on its default route: it printed ``tcp://0.0.0.0:PORT``, which
    ``rave fault`` and a ``RobotDriver`` refuse as naming every interface."""
    with rave_started("arena", "--listen", "0.0.0.0") as lines:
        ours = {entry.address for entries in psutil.net_if_addrs().values()
                for entry in entries}
        addresses = dict(line.split()[1::2] for line in lines)     # name -> address
        assert all(host_of(address) in ours for address in addresses.values()), lines
        assert cli.main(["fault", addresses["r2"], "sonar_dead"]) == 0, \
            capsys.readouterr().err


def test_the_rave_command_stops_a_silent_robot_after_its_watchdog_unless_told_never(
        capsys) -> None:
    """``rave start`` stops a robot none of whose requests came for 2 s of the world's
    time, as a Pioneer's controller does (``--watchdog 0``: never): a robot whose
    server lost its driver (killed, re-pointed away) drove on with its last command
    for good, 0.32 m in 4 s, and the command had no option to stop it."""
    starts = {watchdog: subprocess.Popen(
        [sys.executable, "-m", "rave.cli", "start", "arena", *watchdog],
        stdout=subprocess.PIPE, text=True) for watchdog in ((), ("--watchdog", "0"))}
    clients, driven = [], []
    try:
        for process in starts.values():
            lines = [process.stdout.readline().strip() for _ in range(3)]
            r1, r2 = (ControlClient(ClusterKey.load(), line.split()[-1]) for line in lines[1:])
            clients += [r1, r2]
            driven.append(r1.call("drive", v=0.2, w=0.0)["time"])  # (the world's time then)
        # each r1 silent for 2.5 s of its world's time, which its r2 tells (a request for
        # r1 would feed its watchdog): the two worlds' at once
        for r2, since in zip(clients[1::2], driven, strict=True):
            eventually(lambda r2=r2, since=since: r2.call("sensors")["time"] > since + 2.5,
                       what="2.5 s of the world's time")
        moved = []
        for client in clients[::2]:
            before = client.call("sensors")
            def later(client=client, after=before["time"] + 0.3) -> dict | None:
                sensed = client.call("sensors")
                return sensed if sensed["time"] > after else None
            now = eventually(later, what="0.3 s of the world's time")
            moved.append(math.dist(before["gps"][:2], now["gps"][:2]))
        assert moved[0] < 1e-9 and moved[1] > 0.03, moved
        for process in starts.values():
            process.send_signal(signal.SIGTERM)
            assert process.wait(timeout=15) == 0
    finally:
        for client in clients:
            client.close()
        for process in starts.values():
            if process.poll() is None:
                process.kill()
                process.wait(5)
            process.stdout.close()
    for wrong in ("-1", "nan", "inf", "soon"):
        with pytest.raises(SystemExit):
            cli.main(["start", "arena", "--watchdog", wrong])
        assert f"--watchdog: {wrong!r} is not a number of seconds, 0 or more" in \
            capsys.readouterr().err


def test_python_m_rave_is_the_rave_command() -> None:
    """It said "'rave' is a package and cannot be directly executed"."""
    done = subprocess.run([sys.executable, "-m", "rave", "--help"], capture_output=True,
                          text=True, timeout=60, check=False)
    assert done.returncode == 0 and "serve a world and its robots" in done.stdout, done.stderr


def test_the_rave_command_names_a_mistake_instead_of_a_traceback(tmp_path, capsys) -> None:
    """A seed below 0 and an address without tcp:// ended in numpy's and ZeroMQ's
    tracebacks; -o without a suffix printed one name and wrote NAME.png beside it."""
    with pytest.raises(SystemExit):
        cli.main(["start", "rave/worlds/lab.toml", "--seed", "-1"])
    assert "'-1' is not a seed: give a whole number, 0 or more" in capsys.readouterr().err
    assert cli.main(["fault", "127.0.0.1:7400", "motors_off"]) == 1
    assert "must be a string tcp://HOST:PORT" in capsys.readouterr().err
    started = time.monotonic()            # nobody there: it waited 10 s, with no --timeout
    assert cli.main(["fault", "tcp://127.0.0.1:1", "motors_off", "--timeout", "0.3"]) == 1
    assert "did not answer 'inject' within 0.3 s" in capsys.readouterr().err
    assert time.monotonic() - started < 3
    for output in (tmp_path / "lab", tmp_path):
        assert cli.main(["render", "rave/worlds/lab.toml", "-o", str(output)]) == 1
        assert "give an image file, its suffix the format" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == [] and not (tmp_path.parent / f"{tmp_path.name}.png"
                                                   ).exists()
    # a suffix matplotlib has no format for, and a directory that is not there: their
    # tracebacks (ValueError, FileNotFoundError) once the world was loaded
    assert cli.main(["render", "rave/worlds/lab.toml", "-o", str(tmp_path / "lab.v2")]) == 1
    assert "give an image file, its suffix the format" in capsys.readouterr().err
    missing = tmp_path / "no-such-dir" / "lab.png"
    assert cli.main(["render", "rave/worlds/lab.toml", "-o", str(missing)]) == 1
    assert f"-o {missing}: cannot be written (No such file or directory)" in \
        capsys.readouterr().err
    assert cli.main(["render", "rave/worlds/lab.toml", "-o", str(tmp_path / "lab.PNG")]) == 0


def test_a_recorded_run_becomes_an_animated_gif(tmp_path) -> None:
    frames = []
    with World.load("rave/worlds/arena.toml", seed=1) as world:
        world.robot("r1").drive(0.5, 0.3)
        for _ in range(5):
            world.step(0.2)
            frames.append(render.snapshot(world))
    path = render.animate(frames, tmp_path / "run.gif", fps=5)
    assert path.read_bytes()[:6] == b"GIF89a"
    assert frames[0].world["robots"]["r1"]["pose"] != frames[-1].world["robots"]["r1"]["pose"]


def test_an_occupancy_map_is_drawn_under_the_world(tmp_path) -> None:
    import matplotlib.image

    world = World(size=(8, 6), seed=1)
    world.add_wall((0, 0), (8, 0))
    world.add_robot("r", (2.0, 3.0, 0.0))
    bare = render.render(world, tmp_path / "bare.png", with_sonar=False)
    grid = np.zeros((6, 8))
    grid[:, 4:] = 1.0                                        # the right half occupied
    mapped = render.render(world, tmp_path / "mapped.png", with_sonar=False,
                           occupancy=(grid, (0.0, 8.0, 0.0, 6.0)))
    before, after = (matplotlib.image.imread(p)[..., :3].mean(axis=2) for p in (bare, mapped))
    assert before.shape == after.shape
    width = before.shape[1]
    right, left = slice(width * 5 // 8, width * 7 // 8), slice(width // 8, width * 3 // 8)
    assert after[:, right].mean() < before[:, right].mean() - 0.2   # darkened: occupied
    assert after[:, left].mean() == pytest.approx(before[:, left].mean(), abs=0.05)
