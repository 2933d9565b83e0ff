"""``Lab``: everything a robot application runs against, on one machine.

A RAVE world served by a ``WorldServer`` in a process of its own (real time, or
faster, or in lock-step for a simulated world), one robot server per robot (its TCP
resource port, what a ``RobotDriver`` talks to), and one node controller per
on-board computer (``pb3a node start`` in a process of its own, as it would run on
the robot). The application's system is then launched against these addresses like
any other; the lab owns every process it started and stops them all on ``close``.
"""

from __future__ import annotations

import contextlib
import os
import selectors
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient
from rave.server import RobotServers, WorldProcess
from rave.worldfile import world_file

START_TIMEOUT = 30.0          # seconds for a node controller to say where it listens
CALL_TIMEOUT = 5.0


class NodeControllerProcess:
    """``pb3a node start --name NAME`` on a free loopback port, in a child process."""

    def __init__(self, name: str, timeout: float = START_TIMEOUT) -> None:
        self.name = name
        self.process = subprocess.Popen(
            [sys.executable, "-m", "scenarios.lab_node", str(os.getpid()), "node", "start",
             "--name", name, "--listen", "tcp://127.0.0.1:0", "--max-cpu", "101"],
            stdout=subprocess.PIPE, text=True,
            # another machine's daemon: a Ctrl-C at the terminal is the launcher's to
            # act on (it stops these with the rest); sent to these too, they stopped
            # under the running system, which then took 12 s to end, reporting them
            # lost. Out of the terminal's session, it ends with this process
            # (``lab_node``), however this one ends.
            start_new_session=True)
        self._relay: threading.Thread | None = None
        try:
            self.address = self._banner(timeout).rpartition(" at ")[2]
        except BaseException:
            self.close()
            raise
        # What its executors and workers print after the banner (a module's print, a
        # warning) goes on to our stderr: left unread, the pipe filled after 64 KiB
        # and the next print blocked its module for good. (Not to our stdout: the
        # scenarios print their report there.)
        self._relay = threading.Thread(target=self._relay_output, daemon=True,
                                       name=f"pb3a-lab-{name}-output")
        self._relay.start()

    def _banner(self, timeout: float) -> str:
        """The first line it prints ("node NAME at ADDRESS"), within ``timeout``."""
        assert self.process.stdout is not None
        with selectors.DefaultSelector() as selector:
            selector.register(self.process.stdout, selectors.EVENT_READ)
            if not selector.select(timeout):
                raise TimeoutError(f"the node controller of {self.name} did not start "
                                   f"within {timeout} s")
        line = self.process.stdout.readline().strip()
        if not line.startswith(f"node {self.name} at "):
            raise RuntimeError(f"the node controller of {self.name} failed to start: "
                               f"{line or 'it exited'}")
        return line

    def _relay_output(self) -> None:
        """Copy its output to our stderr until the pipe's end (every writer gone)."""
        assert self.process.stdout is not None
        with contextlib.suppress(OSError, ValueError), self.process.stdout:
            for line in self.process.stdout:
                sys.stderr.write(line)

    def close(self, timeout: float = 15.0) -> None:
        """Stop it (and so the executors it runs): SIGTERM, then SIGKILL."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(5.0)
        if self._relay is not None:
            # (it closes the pipe at its end; a worker that outlived the controller
            # for a moment may still hold it open)
            self._relay.join(5.0)
        elif self.process.stdout is not None:
            self.process.stdout.close()


class Lab:
    """A served world (``rate`` simulated seconds per second, or in ``lockstep``), its
    robot servers, and a node controller per name in ``onboard``. ``add`` places more
    robots (name: pose); ``hardware`` names robots to serve by the emulated hardware
    back end whatever the world file says; ``watchdog_s`` stops a robot silent that
    long, as its controller would (``WorldServer``)."""

    def __init__(self, world: str | Path, *, seed: int = 0, onboard: tuple[str, ...] = (),
                 hardware: tuple[str, ...] = (), rate: float = 1.0, lockstep: bool = False,
                 add: dict[str, tuple[float, float, float]] | None = None,
                 watchdog_s: float = 0.0) -> None:
        self.world_server: WorldProcess | None = None
        self.robot_servers: RobotServers | None = None
        self.nodes: dict[str, NodeControllerProcess] = {}
        self._clients: dict[str, ControlClient] = {}
        try:
            # (each world in a process of its own: see WorldProcess)
            self.world_server = WorldProcess(world_file(str(world)), seed=seed, rate=rate,
                                             lockstep=lockstep, add=add, hardware=hardware,
                                             watchdog_s=watchdog_s)
            self.described = self.describe()
            self.size: tuple[float, float] = tuple(self.described["size"])
            self.robot_servers = RobotServers(self.world_server.address,
                                              list(self.described["robots"]))
            for name in onboard:
                self.nodes[name] = NodeControllerProcess(name)
        except BaseException:
            self.close()
            raise

    @property
    def robots(self) -> dict[str, str]:
        """Each robot's resource port (its robot server's address), by name."""
        assert self.robot_servers is not None
        return dict(self.robot_servers.addresses)

    def robot(self, name: str, op: str, **args: Any) -> Any:
        """Ask robot ``name``'s server to do ``op`` (``inject``, ``sensors``, ...), as
        ``rave fault`` would."""
        return self._client(self.robots[name]).call(op, CALL_TIMEOUT, **args)

    def kill_robot_server(self, name: str) -> None:
        """Kill robot ``name``'s server, as a crash or a cut cable would end it: its
        driver hears nothing from the robot from now on."""
        assert self.robot_servers is not None
        self.robot_servers.kill(name)

    def describe(self) -> dict[str, Any]:
        """The world as plain data now (``World.describe``), from the world server."""
        assert self.world_server is not None
        return self._client(self.world_server.address).call("describe", CALL_TIMEOUT)

    def poses(self) -> dict[str, tuple[float, float, float]]:
        """Every robot's true pose now, from the world server."""
        return {name: tuple(robot["pose"]) for name, robot in self.describe()["robots"].items()}

    def pace(self, rate: float) -> float:
        """Run the world at ``rate`` times real time from now on (0 holds it); the
        world's time now."""
        assert self.world_server is not None
        return float(self._client(self.world_server.address).call("pace", CALL_TIMEOUT,
                                                                  rate=rate))

    def time(self) -> float:
        """The world's time now (simulated seconds), from the world server."""
        return float(self.describe()["time"])

    def _client(self, address: str) -> ControlClient:
        if address not in self._clients:
            self._clients[address] = ControlClient(ClusterKey.load(), address)
        return self._clients[address]

    def close(self) -> None:
        """Stop the node controllers, the robot servers and the world."""
        for client in self._clients.values():
            with contextlib.suppress(Exception):
                client.close()
        self._clients.clear()
        for node in self.nodes.values():
            node.close()
        self.nodes.clear()
        if self.robot_servers is not None:
            self.robot_servers.close()
        if self.world_server is not None:
            self.world_server.close()       # (closes the world)

    def __enter__(self) -> Lab:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def wait_until(deadline: float) -> None:
    """Let a scenario's phase run until ``deadline`` (monotonic): the scenario's own
    clock, not synchronisation."""
    while (left := deadline - time.monotonic()) > 0:
        time.sleep(min(left, 0.5))
