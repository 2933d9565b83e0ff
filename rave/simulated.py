"""The simulated back end: a robot that exists only in RAVE's world model.

Zeroth-order: a commanded velocity takes effect within the physics step. The robot
is a dynamic disc driven by its fleet (see ``fleet.py``), so contacts still stop it:
it stops at real and virtual walls alike and is pushed by hardware robots' bodies.
Its sonar sees every layer of the world model.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import pymunk

from rave.layers import ROBOT, SEES_ALL
from rave.pioneer import MASS, RADIUS

if TYPE_CHECKING:
    from rave.fleet import Fleet
    from rave.odometry import Odometer

GRIP = 2000.0            # N: what the control joint may exert: 1.5 m/s within a step,
                         # yet less than a wall pushes back (contacts win)


class SimulatedBody:
    """A robot body in the world model that moves as commanded: one slot of its
    world's ``fleet``."""

    kind = "sim"

    def __init__(self, fleet: Fleet, name: str, pose: tuple[float, float, float],
                 odometer: Odometer, velocity: tuple[float, float] = (0.0, 0.0)) -> None:
        self.fleet, self.name, self.odometer = fleet, name, odometer
        self.space = fleet.world.space
        self.body = pymunk.Body(MASS, pymunk.moment_for_circle(MASS, 0.0, RADIUS))
        self.body.position, self.body.angle = pose[:2], pose[2]
        self.shape = pymunk.Circle(self.body, RADIUS)
        self.shape.filter = pymunk.ShapeFilter(categories=ROBOT, mask=SEES_ALL)
        self.shape.friction = 0.0              # contacts push, never spin it
        # The control body carries the commanded velocity; the joint pulls the robot
        # along inside the physics step's solver, where contacts can stop it. (A
        # velocity written straight onto the robot would move it before the solver
        # saw its contacts, and it would sink into walls.) The turn rate is written
        # straight onto the robot: a turning disc without friction pushes nothing.
        # The fleet turns the control body about the robot's centre of curvature,
        # so it carries a command without being written at every step.
        self.control = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        self.control.position = pose[:2]
        self.joint = pymunk.PivotJoint(self.control, self.body, (0, 0), (0, 0))
        self.joint.max_bias, self.joint.max_force = 0.0, GRIP
        self.space.add(self.body, self.shape, self.control, self.joint)
        v, w = velocity
        start = (v * math.cos(pose[2]), v * math.sin(pose[2]), w)
        self.slot = fleet.add(self, pose, start, odometer.pose(), odometer.scale)

    def command(self, v: float, w: float) -> None:
        self.fleet.drive(self.slot, v, w)

    def commanded(self) -> tuple[float, float]:
        v, w = self.fleet.command[self.slot]
        return (float(v), float(w))

    def pose(self) -> tuple[float, float, float]:
        x, y, theta = self.fleet.pose[self.slot]
        return (float(x), float(y), math.remainder(theta, math.tau))

    def velocity(self) -> tuple[float, float, float]:
        vx, vy, w = self.fleet.velocity[self.slot]
        return (float(vx), float(vy), float(w))

    def odometry(self) -> tuple[float, float, float]:
        x, y, theta = self.fleet.odometry[self.slot]
        return (float(x), float(y), float(theta))

    def sonar(self, rng: np.random.Generator) -> np.ndarray:
        return self.fleet.sonar(self.slot)

    def close(self) -> None:
        """Leave the world; the odometer goes on from where the fleet had it."""
        self.odometer.state[:] = self.odometry()
        self.fleet.remove(self)
        self.space.remove(self.body, self.shape, self.control, self.joint)
