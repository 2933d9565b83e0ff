"""The simulated back end: a robot that exists only in RAVE's world model.

Zeroth-order: a commanded velocity takes effect at once. The body is a dynamic
pymunk disc whose velocity is set inside the physics step (``velocity_func``), so
contacts still stop it: it stops at real and virtual walls alike, and is pushed by
hardware robots' bodies. Its sonar sees every layer of the world model.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import pymunk

from rave import sonar
from rave.layers import ROBOT, SEES_ALL

if TYPE_CHECKING:
    from rave.world import World

RADIUS = 0.25            # Pioneer 3-DX, m
MASS = 9.0               # kg
NOISE = sonar.SonarNoise(sigma0=0.005, sigma_per_m=0.005)


class SimulatedBody:
    """A robot body in the world model that moves exactly as commanded."""

    kind = "sim"

    def __init__(self, world: World, name: str, pose: tuple[float, float, float],
                 velocity: tuple[float, float] = (0.0, 0.0)) -> None:
        self.world, self.name = world, name
        self.v, self.w = velocity
        self.body = pymunk.Body(MASS, math.inf)
        self.body.position = pose[:2]
        self.body.angle = pose[2]
        self.body.velocity_func = self._drive
        self.shape = pymunk.Circle(self.body, RADIUS)
        self.shape.filter = pymunk.ShapeFilter(categories=ROBOT, mask=SEES_ALL)
        self.shape.friction = 0.0
        world.space.add(self.body, self.shape)

    def _drive(self, body: pymunk.Body, gravity: object, damping: float, dt: float) -> None:
        body.velocity = (self.v * math.cos(body.angle), self.v * math.sin(body.angle))
        body.angular_velocity = self.w

    def command(self, v: float, w: float) -> None:
        self.v, self.w = v, w

    def advance(self, dt: float) -> None:
        """Nothing to do before the world's physics step."""

    def moved(self, dt: float) -> tuple[float, float]:
        """Distance and rotation over the last step, as contacts let it move."""
        vx, vy = self.body.velocity
        theta = self.body.angle
        return ((vx * math.cos(theta) + vy * math.sin(theta)) * dt,
                self.body.angular_velocity * dt)

    def pose(self) -> tuple[float, float, float]:
        x, y = self.body.position
        return (x, y, math.remainder(self.body.angle, math.tau))

    def velocity(self) -> tuple[float, float, float]:
        vx, vy = self.body.velocity
        return (vx, vy, self.body.angular_velocity)

    def sonar(self, rng: np.random.Generator) -> np.ndarray:
        world = self.world
        return sonar.read(self.pose(), world.segments(), world.discs(exclude=self.name),
                          NOISE, rng)

    def close(self) -> None:
        self.world.space.remove(self.body, self.shape)
