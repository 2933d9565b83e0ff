"""The hardware back end: a stand-in for a physical Pioneer, and its place in the
world model.

There is no robot here, so ``Emulator`` is one: its own physical world holding
only the real obstacles, second-order dynamics (motor lag, acceleration limits,
wheel slip), a sonar ring fired on the ARCOS schedule (one transducer per array
every 40 ms) with noise, dropouts and specular reflection, and injectable faults.
It can run in this process or behind a robot server in its own.

``HardwareBody`` puts it in RAVE's world: a kinematic disc at the pose the robot
reports, which simulated robots bump into and sense, while its hybrid sonar
returns, per transducer, the nearer of the real reading and the virtual one
computed from the world model (virtual obstacles and other robots) at that pose.
Virtual obstacles never reach the real component.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pymunk

from rave import sonar
from rave.fleet import NOISE
from rave.layers import REAL, ROBOT, WALL_RADIUS
from rave.simulated import MASS, RADIUS

if TYPE_CHECKING:
    from rave.odometry import Odometer
    from rave.world import World

FAULTS = ("motors_off", "sonar_dead", "odometry_bias")
FIRE_S = 0.040                      # one transducer per array per 40 ms (ARCOS)
REAL_NOISE = sonar.SonarNoise(sigma0=0.01, sigma_per_m=0.01, dropout=0.02, specular=True)


@dataclass
class Dynamics:
    """How the physical robot answers a command."""

    lag_s: float = 0.25              # first-order motor lag
    accel: float = 0.3               # m/s^2
    angular_accel: float = math.radians(100.0)
    slip_sigma: float = 0.02         # wheel slip: random walk of the fraction lost


class Emulator:
    """One physical robot and the real part of the world around it."""

    def __init__(self, segments: np.ndarray, pose: tuple[float, float, float],
                 rng: np.random.Generator, velocity: tuple[float, float] = (0.0, 0.0),
                 dynamics: Dynamics | None = None) -> None:
        self.rng = rng
        self.dynamics = dynamics or Dynamics()
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


class HardwareBody:
    """A hardware robot in the world model: where it reports to be, what it senses."""

    kind = "hardware"

    def __init__(self, world: World, name: str, pose: tuple[float, float, float],
                 odometer: Odometer, rng: np.random.Generator,
                 velocity: tuple[float, float] = (0.0, 0.0)) -> None:
        self.world, self.name, self.odometer = world, name, odometer
        self.emulator = Emulator(world.segments(virtual=False), pose, rng, velocity)
        self.body = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        self.shape = pymunk.Circle(self.body, RADIUS)
        self.shape.filter = pymunk.ShapeFilter(categories=ROBOT, mask=ROBOT)
        world.space.add(self.body, self.shape)
        world.hardware.append(self)
        world.fleet.bodies_changed()
        self._place()

    def _place(self) -> None:
        x, y, theta = self.emulator.pose()
        vx, vy, w = self.emulator.velocity()
        self.body.position, self.body.angle = (x, y), theta
        self.body.velocity, self.body.angular_velocity = (vx, vy), w
        self.world.space.reindex_shapes_for_body(self.body)

    def command(self, v: float, w: float) -> None:
        self.emulator.command(v, w)

    def commanded(self) -> tuple[float, float]:
        return (self.emulator.command_v, self.emulator.command_w)

    def advance(self, dt: float) -> None:
        """Step the physical robot and its odometry. Its stand-in in the world model is
        placed where the robot was, moving as it was, so the world's step carries it
        to about where the robot now is (kinematic bodies push by their velocity)."""
        self._place()
        self.odometer.advance(*self.emulator.step(dt))

    def odometry(self) -> tuple[float, float, float]:
        return self.odometer.pose()

    def pose(self) -> tuple[float, float, float]:
        return self.emulator.pose()

    def velocity(self) -> tuple[float, float, float]:
        return self.emulator.velocity()

    def sonar(self, rng: np.random.Generator) -> np.ndarray:
        """Hybrid: per transducer, the nearer of the real and the virtual reading (a
        dead transducer senses nothing, virtual or real)."""
        world = self.world
        virtual = sonar.read(self.pose(), world.segments(real=False),
                             world.discs(exclude=self.name), NOISE, rng)
        hybrid = np.minimum(self.emulator.sonar(), virtual)
        hybrid[list(self.emulator.faults.get("sonar_dead", ()))] = sonar.MAX_RANGE
        return hybrid

    def close(self) -> None:
        self.world.hardware.remove(self)
        self.world.space.remove(self.body, self.shape)
        self.world.fleet.bodies_changed()
