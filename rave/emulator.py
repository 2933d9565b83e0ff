"""The hardware back end's robot: an emulated Pioneer in a process of its own.

There is no robot here, so ``Emulator`` is one: its own physical world holding
only the real obstacles, second-order dynamics (motor lag, acceleration limits,
wheel slip), a sonar ring fired on the ARCOS schedule (one transducer per array
every 40 ms) with noise, dropouts and specular reflection, and injectable faults.

It runs apart from the world model, as a physical robot does: ``EmulatorProcess``
starts one in a child process and talks to it over
a private socket pair, one request and one answer at a time. The world sends
commands and faults; each ``advance`` steps the robot through a run of physics
steps and brings back where it was at each of them, what its wheel encoders
counted and its latest sonar ring, so one round trip serves a whole world step.
The child stops when asked, or when its parent's end of the socket closes.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import socket
import subprocess
import sys
import traceback
import weakref
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
import pymunk

from rave import sonar
from rave.layers import REAL, ROBOT, WALL_RADIUS
from rave.pioneer import ACCEL, ANGULAR_ACCEL, MASS, MOTOR_LAG_S, RADIUS

START_TIMEOUT = 30.0                # s: a child imports numpy and pymunk first
ANSWER_TIMEOUT = 5.0
STEP_TIMEOUT = 1e-3      # and this per physics step asked for (an emulator does ~10,000/s)

FAULTS = ("motors_off", "sonar_dead", "odometry_bias")
FIRE_S = 0.040                      # one transducer per array per 40 ms (ARCOS)
REAL_NOISE = sonar.SonarNoise(sigma0=0.01, sigma_per_m=0.01, dropout=0.02, specular=True)


@dataclass
class Dynamics:
    """How the physical robot answers a command."""

    lag_s: float = MOTOR_LAG_S
    accel: float = ACCEL
    angular_accel: float = ANGULAR_ACCEL
    slip_sigma: float = 0.02         # wheel slip: random walk of the fraction lost


class Emulator:
    """One physical robot and the real part of the world around it."""

    def __init__(self, segments: np.ndarray, pose: tuple[float, float, float],
                 rng: np.random.Generator, velocity: tuple[float, float] = (0.0, 0.0),
                 ) -> None:
        self.rng = rng
        self.dynamics = Dynamics()
        self.segments = np.empty((0, 4))
        self.space = pymunk.Space()
        self.add_walls(segments)
        self.body = pymunk.Body(MASS, math.inf)
        self.body.position = pose[:2]
        self.body.angle = pose[2]
        self.body.velocity_func = self._move
        shape = pymunk.Circle(self.body, RADIUS)
        shape.filter = pymunk.ShapeFilter(categories=ROBOT, mask=REAL)
        self.space.add(self.body, shape)
        self.command_v, self.command_w = 0.0, 0.0
        self.v, self.w = velocity                  # what the motors turn at
        self.slip = 0.0
        self.faults: dict[str, object] = {}
        self.time = 0.0
        self._fired = 0                            # transducer firings so far
        self.readings = sonar.read(self.pose(), segments, None, REAL_NOISE, rng)

    def add_walls(self, segments: np.ndarray) -> None:
        """Real obstacles (their edges, shape (n, 4)) that the robot bumps into and senses."""
        for x0, y0, x1, y1 in segments:
            wall = pymunk.Segment(self.space.static_body, (x0, y0), (x1, y1), WALL_RADIUS)
            wall.filter = pymunk.ShapeFilter(categories=REAL)
            self.space.add(wall)
        self.segments = np.concatenate([self.segments, segments])

    def _move(self, body: pymunk.Body, gravity: object, damping: float, dt: float) -> None:
        moving = self.v * (1.0 - self.slip)
        body.velocity = (moving * math.cos(body.angle), moving * math.sin(body.angle))
        body.angular_velocity = self.w * (1.0 - self.slip)

    def command(self, v: float, w: float) -> None:
        self.command_v, self.command_w = v, w

    def step(self, dt: float) -> tuple[float, float]:
        """Advance ``dt``; returns what the wheel encoders measured (distance, rotation)."""
        d = self.dynamics
        target_v, target_w = (0.0, 0.0) if "motors_off" in self.faults else (
            self.command_v, self.command_w)
        if "motors_off" in self.faults:
            self.v = self.w = 0.0                  # no power: the wheels stop at once
        gain = 1.0 - math.exp(-dt / d.lag_s)
        self.v += _clamp((target_v - self.v) * gain, d.accel * dt)
        self.w += _clamp((target_w - self.w) * gain, d.angular_accel * dt)
        if self.v or self.w:
            self.slip = min(0.3, abs(self.slip + self.rng.normal(0.0, d.slip_sigma * dt)))
        self.space.step(dt)
        self.time += dt
        self._fire()
        return self.v * dt, self.w * dt

    def _fire(self) -> None:
        due = int(self.time / FIRE_S + 1e-9)
        if due <= self._fired:
            return
        # the transducers whose turn came (one per array per firing), newest pose
        firings = range(self._fired, due)
        which = np.unique(np.array([[k % 8, 8 + k % 8] for k in firings]).ravel())
        self._fired = due
        self.readings[which] = sonar.read(self.pose(), self.segments, None, REAL_NOISE,
                                          self.rng, which)

    def sonar(self) -> np.ndarray:
        readings = self.readings.copy()
        dead = self.faults.get("sonar_dead")
        if dead is not None:
            readings[list(dead)] = sonar.MAX_RANGE  # type: ignore[call-overload]
        return readings

    def pose(self) -> tuple[float, float, float]:
        x, y = self.body.position
        return (x, y, math.remainder(self.body.angle, math.tau))

    def velocity(self) -> tuple[float, float, float]:
        vx, vy = self.body.velocity
        return (vx, vy, self.body.angular_velocity)


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


@dataclass
class Report:
    """What the robot reported over a run of ``n`` steps: its pose and velocity (x, y,
    heading, vx, vy, w) at the start of each step and after the last, (n + 1, 6); the
    encoders' (distance, rotation) per step, (n, 2); its sonar ring now, (16,)."""

    states: np.ndarray
    encoders: np.ndarray
    sonar: np.ndarray


class EmulatorProcess:
    """The world's handle on one emulated robot running in its own process."""

    def __init__(self, name: str, segments: np.ndarray, pose: tuple[float, float, float],
                 seed: int, velocity: tuple[float, float] = (0.0, 0.0)) -> None:
        self.name = name
        self._advancing = 0                     # steps asked for by ``begin_advance``
        ours, theirs = socket.socketpair()
        with theirs:
            self._process = subprocess.Popen(
                [sys.executable, "-P", "-c", _CHILD, str(theirs.fileno())],
                pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL, env=_child_environment())
        self._conn = Connection(ours.detach())
        # Whoever forgets to close it, the child still goes with this handle.
        self._finalizer = weakref.finalize(self, _stop, self._process, self._conn)
        try:
            self.report: Report = self._ask(("start", segments, pose, seed, velocity),
                                            START_TIMEOUT)
        except BaseException:       # stopped now, not when the failed handle is collected
            self._finalizer()
            raise

    def command(self, v: float, w: float) -> None:
        self._ask(("command", v, w))

    def fault(self, name: str, value: Any) -> None:
        self.report.sonar = self._ask(("fault", name, value))     # dead at once

    def clear(self, name: str) -> None:
        self.report.sonar = self._ask(("clear", name))

    def add_walls(self, segments: np.ndarray) -> None:
        self._ask(("walls", segments))

    def check(self) -> None:
        """RuntimeError, saying what to do, if the emulator's process is gone."""
        if self._process.poll() is not None:
            raise self._gone()

    def begin_advance(self, steps: int, dt: float) -> None:
        """Ask for ``steps`` physics steps of ``dt``; ``end_advance`` takes the answer
        (in between, other robots' emulators can be stepping too)."""
        self._send(("advance", steps, dt))
        self._advancing = steps

    def end_advance(self) -> Report:
        """The answer to ``begin_advance``, waited for as long as its steps may take."""
        self.report = self._answer(ANSWER_TIMEOUT + self._advancing * STEP_TIMEOUT)
        return self.report

    def _ask(self, request: tuple[Any, ...], timeout: float = ANSWER_TIMEOUT) -> Any:
        self._send(request)
        return self._answer(timeout)

    def _send(self, request: tuple[Any, ...]) -> None:
        try:
            self._conn.send(request)
        except OSError:
            raise self._gone() from None

    def _answer(self, timeout: float) -> Any:
        try:
            answered = self._conn.poll(timeout)
            if answered:
                status, value = self._conn.recv()
        except (EOFError, OSError):
            raise self._gone() from None
        if not answered:        # (a TimeoutError is an OSError: not inside the try)
            # A late answer would be taken for the next one: it is dead to us.
            self._process.kill()
            raise TimeoutError(f"the emulator of robot {self.name} did not answer "
                               f"within {timeout:g} s and was stopped")
        if status == "error":
            raise RuntimeError(f"the emulator of robot {self.name} failed:\n{value}")
        return value

    def _gone(self) -> RuntimeError:
        try:
            code = self._process.wait(1.0)
        except subprocess.TimeoutExpired:
            code = None
        return RuntimeError(f"the emulator of robot {self.name} is gone (its process "
                            f"{self._process.pid} exited with {code}); swap the robot "
                            "to 'sim' or add it again")

    @property
    def pid(self) -> int:
        return self._process.pid

    def close(self) -> None:
        """Stop the child (asked first, killed if it does not go within 2 s)."""
        self._finalizer()


def _stop(process: subprocess.Popen[bytes], conn: Connection) -> None:
    with contextlib.suppress(OSError):
        conn.send(("stop",))
    conn.close()
    try:
        process.wait(2.0)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(2.0)


def _state(emulator: Emulator) -> tuple[float, ...]:
    return (*emulator.pose(), *emulator.velocity())


def _serve(conn: Connection) -> None:
    """The child: answer the parent's requests until told to stop or orphaned."""
    emulator: Emulator | None = None
    while True:
        try:
            op, *args = conn.recv()
        except (EOFError, OSError):
            return                                        # the parent is gone
        if op == "stop":
            return
        try:
            if op == "start":
                segments, pose, seed, velocity = args
                emulator = Emulator(segments, pose, np.random.default_rng(seed), velocity)
                answer: Any = Report(np.array([_state(emulator)]), np.zeros((0, 2)),
                                     emulator.sonar())
            elif emulator is None:
                raise RuntimeError(f"{op!r} before 'start'")
            elif op == "advance":
                steps, dt = args
                states, encoders = [], []
                for _ in range(steps):
                    states.append(_state(emulator))
                    encoders.append(emulator.step(dt))
                states.append(_state(emulator))
                answer = Report(np.array(states), np.array(encoders).reshape(-1, 2),
                                emulator.sonar())
            elif op == "command":
                answer = emulator.command(*args)
            elif op == "fault":
                emulator.faults[args[0]] = args[1]
                answer = emulator.sonar()
            elif op == "clear":
                emulator.faults.pop(args[0], None)
                answer = emulator.sonar()
            elif op == "walls":
                answer = emulator.add_walls(args[0])
            else:
                raise ValueError(f"no operation {op!r}")
        except Exception:                                 # the parent gets the traceback
            conn.send(("error", traceback.format_exc()))
        else:
            conn.send(("ok", answer))


def serve_child(fd: int) -> None:
    """The child's entry point, serving over the inherited socket ``fd``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)          # the parent decides when to stop
    _serve(Connection(fd))


# Run by import (not ``-m``), so that what the child pickles is ``rave.emulator.Report``;
# with -P, so that a file in the current directory named as a standard module (a
# user's ``random.py``) is not imported for it.
_CHILD = "import sys; from rave.emulator import serve_child; serve_child(int(sys.argv[1]))"


def _child_environment() -> dict[str, str]:
    """This environment, with this copy of ``rave`` first on the child's path."""
    here = str(Path(__file__).resolve().parent.parent)
    path = os.environ.get("PYTHONPATH")
    return {**os.environ, "PYTHONPATH": here + (os.pathsep + path if path else "")}
