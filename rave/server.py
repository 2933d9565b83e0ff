"""Serving a running world: ``WorldServer`` steps a world in real time, and one robot
server process per robot (the paper's shell program) relays a controller's requests
over the robot's TCP resource port.

Every port speaks PB3A's authenticated control protocol (the cluster key; nothing
is unpickled before the frame is authenticated), so a PB3A ``Driver`` connects to a
robot server directly, from this machine or another. A robot server adds its
robot's name and forwards each request to the world server; the controller never
learns which back end serves the robot, and the back end can be swapped under it.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import threading
import time
from pathlib import Path
from typing import Any

from pb3a.errors import RuntimeFailure
from pb3a.processes import serve_as_child, start_without_main, stop_on_sigterm
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient, ControlServer
from rave.world import PHYSICS_DT, World

log = logging.getLogger("rave.server")

_context = multiprocessing.get_context("spawn")
START_TIMEOUT = 30.0
RELAY_TIMEOUT = 2.0
ROBOT_OPS = ("drive", "stop", "sensors", "camera", "inject", "clear", "swap", "advance",
             "cycle")
MAX_ADVANCE_S = 10.0          # simulated seconds one ``advance`` may ask for
TICK_S = 0.005                # s of wall time between a fast-paced world's steps (about)
MIN_RATE = 1e-6              # a world paced slower than this would wait longer than threads can
MOST_STEPS = 50               # physics steps in one world step at most: beyond 100x real
                              # time the machine sets the pace, in holds short enough for
                              # requests to get in between (and ``close`` to stop it)


class WorldServer:
    """A world stepped at ``rate`` times real time, and its robots' requests answered
    between two world steps.

    A world step is one physics step (10 ms) up to twice real time; faster, it is the
    whole number of physics steps nearest 5 ms of wall time (four at 8x; at most
    ``MOST_STEPS``), taken in one round trip to each hardware robot's emulator, not one
    per physics step.

    With ``lockstep`` the world does not step by itself: it advances only when a
    controller asks (``advance``, ``dt`` simulated seconds, answered with the world's
    time once done), so a simulated experiment runs exactly as fast as its controllers
    decide, faster than real time on a fast machine and never ahead of them. Meant for
    one controlling client (several would each advance the shared clock). ``cycle`` is
    a lock-step controller's whole turn in one request: drive by ``v`` and ``w`` if
    given, advance ``dt``, and answer with the robot's readings then.

    With ``watchdog_s`` (> 0), a robot none of whose requests has come for that long
    in the world's time is stopped, as a Pioneer's controller stops the motors when
    its client falls silent (ARCOS's communication watchdog): a robot whose server
    crashed or whose link was cut stands, instead of running on its last command
    for good. Any request for the robot (``sensors`` too, which a driver sends every
    period) feeds it; a ``drive`` after it bit sets the robot going again. 0 (the
    default) keeps the last command however long the robot is silent."""

    def __init__(self, world: World, host: str = "127.0.0.1", port: int = 0,
                 rate: float = 1.0, lockstep: bool = False, watchdog_s: float = 0.0) -> None:
        if not lockstep:
            _check_rate(rate)
        _check_watchdog(watchdog_s)
        self.world, self.rate, self.lockstep = world, rate, lockstep
        self.watchdog_s = watchdog_s
        self._heard: dict[str, float] = {}   # robot: the world's time of its last request
        self._lock = threading.Lock()                      # the world is not thread-safe
        self._stopping = threading.Event()
        self._paced = threading.Event()                    # the rate changed
        self._failing = ""                                 # why the last step failed
        self._server = ControlServer(ClusterKey.load(), self._handle, host, port,
                                     name="rave-world")
        self.address = self._server.address
        self._stepper = threading.Thread(target=self._run, name="rave-world-step",
                                         daemon=True)
        if not lockstep:
            self._stepper.start()

    def _run(self) -> None:
        next_at = time.monotonic()
        while not self._stopping.is_set():
            if self._paced.is_set():
                self._paced.clear()
                next_at = time.monotonic()
            with self._lock:                   # (the rate is read with the world: a
                rate = self.rate               # world held by ``pace`` steps no more)
                if rate:
                    steps = min(MOST_STEPS, max(1, round(TICK_S * rate / PHYSICS_DT)))
                    self._step(steps * PHYSICS_DT)
            if not rate:                       # held: no simulated time passes
                self._paced.wait()
                continue
            next_at += steps * PHYSICS_DT / rate
            # a real-time loop: wait for the next tick (or a new pace), never drift
            self._paced.wait(max(0.0, next_at - time.monotonic()))

    def _step(self, dt: float) -> None:
        """Step the world; a step that fails (a hardware robot's emulator gone) is logged
        once and tried again at the next tick, so the world goes on as soon as it is
        mended (the robot swapped to sim) instead of its stepper dying."""
        try:
            self.world.step(dt)
            self._watch()
        except Exception as exc:
            if str(exc) != self._failing:
                log.error("world %s cannot step: %s", self.world.name, exc)
            self._failing = str(exc)
        else:
            self._failing = ""

    def _watch(self) -> None:
        """Stop each moving robot that has been silent for ``watchdog_s`` of the world's
        time (see the class docstring). Called with the world's lock held."""
        if not self.watchdog_s:
            return
        now = self.world.time
        for name, robot in self.world.robots.items():
            # (a robot not heard from yet: silent since the server started)
            silent = now - self._heard.setdefault(name, now)
            if silent > self.watchdog_s and robot.commanded() != (0.0, 0.0):
                robot.stop()

    def pace(self, rate: float) -> float:
        """Run the world at ``rate`` times real time from now on; 0 holds it (no
        simulated time passes, requests are still answered). The world's time now."""
        if self.lockstep:
            raise ValueError(f"world {self.world.name} runs in lock-step: its controller "
                             "advances it")
        _check_rate(rate)
        with self._lock:
            self.rate = rate
            self._paced.set()
            return self.world.time

    def _handle(self, op: str, args: dict[str, Any]) -> Any:
        if op == "pace":
            return self.pace(float(args.get("rate", 1.0)))
        with self._lock:
            if op == "describe":
                return self.world.describe()
            if op not in ROBOT_OPS:
                raise ValueError(f"the world server has no operation {op!r}; its operations: "
                                 f"describe, pace, and the robots' {', '.join(ROBOT_OPS)}")
            if "robot" not in args:
                raise ValueError(f"{op}: name the robot (robot = NAME): the world's robots "
                                 f"are {', '.join(self.world.robots) or 'none'}")
            name = args.pop("robot")
            robot = self.world.robot(name)
            self._heard[name] = self.world.time          # (the watchdog's food)
            if op == "advance":
                return self._advance(float(args.get("dt", PHYSICS_DT)), name)
            if op == "cycle":
                if ("v" in args) != ("w" in args):
                    raise ValueError("cycle: give both v and w (drive, then advance), or "
                                     "neither (advance on the command in force)")
                dt = float(args.get("dt", PHYSICS_DT))
                self._check_advance(dt)     # before driving: a refused turn changes nothing
                if "v" in args:
                    _apply(robot, "drive", args, self.world.time)
                self._advance(dt, name)
                return _apply(robot, "sensors", {}, self.world.time)
            return _apply(robot, op, args, self.world.time)

    def _advance(self, dt: float, asking: str) -> float:
        self._check_advance(dt)
        self.world.step(dt)
        self._heard[asking] = self.world.time   # (its controller was there all along)
        self._watch()
        return self.world.time

    def _check_advance(self, dt: float) -> None:
        if not self.lockstep:
            raise ValueError(f"world {self.world.name} runs by itself ({self.rate} x real "
                             "time); serve it in lock-step (rave start --lockstep) to "
                             "advance it from a controller")
        if not 0 <= dt <= MAX_ADVANCE_S:
            raise ValueError(f"advance(dt={dt}): dt must be between 0 and {MAX_ADVANCE_S} s")

    def close(self) -> None:
        """Stop stepping and serving, and close the world (it is this server's now)."""
        self._stopping.set()
        self._paced.set()
        if self._stepper.is_alive():
            self._stepper.join(2.0)
        self._server.close()
        self.world.close()


# what an operation must be given, and how to say it (a KeyError said no more)
NEEDED = {"drive": (("v", "w"), "v and w (m/s, rad/s)"), "inject": (("fault",), "a fault"),
          "swap": (("backend",), "a backend ('sim' or 'hardware')")}


def _apply(robot: Any, op: str, args: dict[str, Any], now: float) -> Any:
    keys, said = NEEDED.get(op, ((), ""))
    if any(key not in args for key in keys):
        raise ValueError(f"{op} needs {said}")
    if op == "sensors":
        return {"time": now, "sonar": robot.sonar().tolist(), "odometry": robot.odometry(),
                "gps": robot.gps(), "velocity": robot.velocity(), "backend": robot.backend}
    if op == "camera":
        return [vars(blob) for blob in robot.camera(args.get("hue"),
                                                     args.get("tolerance", 15.0))]
    if op in ("drive", "stop"):
        if op == "drive":
            robot.drive(float(args["v"]), float(args["w"]))
        else:
            robot.stop()
        # the world's time from which the robot runs on it: a driver tells by it what
        # drove the robot between two readings (``RobotDriver``'s ``applied``)
        return {"time": now}
    if op == "inject":
        robot.inject(args["fault"], **args.get("params", {}))
    elif op == "clear":
        robot.clear(args.get("fault"))
    elif op == "swap":
        robot.swap(args["backend"])
    return None


def _check_watchdog(watchdog_s: float) -> None:
    if not (isinstance(watchdog_s, int | float) and 0 <= watchdog_s < math.inf):
        raise ValueError(f"a world server's watchdog_s is the seconds of silence after "
                         f"which a robot is stopped, a finite number, 0 (none) or more, "
                         f"not {watchdog_s!r}")


def _check_rate(rate: float) -> None:
    # (below MIN_RATE a tick's wait is more than a thread can wait: the stepper died)
    if not (rate == 0 or MIN_RATE <= rate < math.inf):
        raise ValueError(f"a world's rate is how many times real time it runs, a finite "
                         f"number, 0 (holds it) or at least {MIN_RATE:g}, not {rate}")


class WorldProcess:
    """A ``WorldServer`` in a process of its own, serving the world file ``path``
    (``seed``; robots ``add``-ed as name: pose; the robots named in ``hardware`` on the
    emulated hardware back end; the server's ``watchdog_s``). Its physics and its
    requests then never wait for the interpreter lock of the process that started it
    (a scenario serving several worlds, or a launcher)."""

    def __init__(self, path: str | Path, *, seed: int = 0, rate: float = 1.0,
                 lockstep: bool = False, add: dict[str, tuple[float, float, float]] | None = None,
                 hardware: tuple[str, ...] = (), host: str = "127.0.0.1",
                 watchdog_s: float = 0.0) -> None:
        _check_watchdog(watchdog_s)          # (here: the child's error would be lost)
        parent, child = _context.Pipe()
        self._pipe = parent                  # held open: the server stops when it closes
        self._process = _context.Process(
            target=world_server_main, daemon=True, name=f"rave-world-{Path(path).stem}",
            args=(str(path), seed, rate, lockstep, dict(add or {}), tuple(hardware), host,
                  watchdog_s, child))
        start_without_main(self._process)
        child.close()
        try:
            self.address = _served_at(parent, f"the world server of {path}")
        except BaseException:
            self.close()
            raise

    def close(self, timeout: float = 5.0) -> None:
        """Stop serving and close the world (its back ends' processes too)."""
        self._pipe.close()                   # (the child stops on its parent's EOF)
        _stop(self._process, timeout)


def world_server_main(path: str, seed: int, rate: float, lockstep: bool,
                      add: dict[str, tuple[float, float, float]], hardware: tuple[str, ...],
                      host: str, watchdog_s: float, conn: Any) -> None:
    """A world server process (see ``WorldProcess``)."""
    stopped = threading.Event()
    stop_on_sigterm(stopped)                 # before the world's emulators are started
    world = World.load(path, seed=seed)
    try:
        for name, pose in add.items():
            world.add_robot(name, pose, color="blue")
        for name in hardware:
            world.robot(name).swap("hardware")
        server = WorldServer(world, host, rate=rate, lockstep=lockstep,
                             watchdog_s=watchdog_s)
    except BaseException:
        world.close()
        raise
    try:
        serve_as_child(conn, server.address, stopped)
    finally:
        server.close()                       # (closes the world)


def _stop(process: Any, timeout: float) -> None:
    """Wait for a server process told to stop (its pipe closed); terminate it, then
    kill it, if it does not within ``timeout``."""
    process.join(timeout)
    if process.is_alive():
        process.terminate()
        process.join(timeout)
    if process.is_alive():
        process.kill()
        process.join(1.0)


def _served_at(pipe: Any, what: str) -> str:
    """The address a server process just started tells over ``pipe``, or why not."""
    if not pipe.poll(START_TIMEOUT):
        raise RuntimeError(f"{what} did not start within {START_TIMEOUT} s")
    try:
        return pipe.recv()
    except EOFError:
        raise RuntimeError(f"{what} stopped before serving (its error, if any, is in the "
                           "log above)") from None


class RobotServers:
    """One robot server process per robot of a served world; stops them all, or one."""

    def __init__(self, world_address: str, robots: list[str], host: str = "127.0.0.1",
                 ports: list[int] | None = None) -> None:
        """``ports``: each robot's, in order (None: free ones)."""
        self.addresses: dict[str, str] = {}
        self._processes: dict[str, Any] = {}
        self._pipes: dict[str, Any] = {}   # held open: a server stops when its closes
        try:
            for name, port in zip(robots, ports or [0] * len(robots), strict=True):
                parent, child = _context.Pipe()
                process = _context.Process(target=robot_server_main, daemon=True,
                                           name=f"rave-robot-{name}",
                                           args=(name, world_address, host, child, port))
                start_without_main(process)
                child.close()
                self._processes[name] = process
                self._pipes[name] = parent
                self.addresses[name] = _served_at(parent, f"the robot server of {name}")
        except BaseException:
            self.close()
            raise

    def kill(self, name: str) -> None:
        """Kill robot ``name``'s server at once, as a crash or a cut cable would end it:
        its driver's calls go unanswered from now on (the robot keeps its last command,
        unless the world server's watchdog stops it)."""
        if name not in self._processes:
            raise KeyError(f"no robot server of {name!r} runs; those running: "
                           f"{', '.join(self._processes) or 'none'}")
        process = self._processes.pop(name)
        process.kill()
        process.join(5.0)
        self._pipes.pop(name).close()
        del self.addresses[name]

    def close(self, timeout: float = 5.0) -> None:
        for pipe in self._pipes.values():
            pipe.close()                   # (each stops on its parent's EOF, side by side)
        for process in self._processes.values():
            _stop(process, timeout)
        self._processes.clear()
        self._pipes.clear()


def robot_server_main(name: str, world_address: str, host: str, conn: Any,
                      port: int = 0) -> None:
    """A robot server process: relay requests for robot ``name`` to the world server,
    dropping one not begun within the time its caller waits (see ``serve_device``)."""
    stopped = threading.Event()
    stop_on_sigterm(stopped)
    key = ClusterKey.load()
    world = ControlClient(key, world_address)

    def relay(op: str, args: dict[str, Any]) -> Any:
        if op not in ROBOT_OPS:
            raise ValueError(f"robot {name} has no operation {op!r}; operations: "
                             f"{', '.join(ROBOT_OPS)}")
        try:
            return world.call(op, RELAY_TIMEOUT, robot=name, **args)
        except RuntimeFailure as exc:           # (a RuntimeTimeout is not one: as it is)
            # said as the world said it: the world server's address, which the caller
            # never gave, and the exception's name meant nothing to it
            said = str(exc).removeprefix(f"{op} at {world_address} failed: ")
            raise RuntimeFailure(said.removeprefix("ValueError: ")) from None

    # (a request its driver no longer waits for is dropped, as a device's: a turn asked
    # again after a timeout, the world busy, would advance it twice)
    server = ControlServer(key, relay, host, port, name=f"rave-robot-{name}",
                           title=f"the robot server of {name}", expires=True)
    try:
        serve_as_child(conn, server.address, stopped)
    finally:
        server.close()
        world.close()
