"""The hardware back end's place in RAVE's world model.

``HardwareBody`` stands for a physical robot, which here is an emulator in its own
process (``rave/emulator.py``): a kinematic disc at the pose the robot reports,
which simulated robots bump into and sense, while its hybrid sonar returns, per
transducer, the nearer of the real reading and the virtual one computed from the
world model (virtual obstacles and other robots) at that pose. Virtual obstacles
never reach the real component.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import pymunk

from rave import sonar
from rave.emulator import EmulatorProcess
from rave.layers import ROBOT
from rave.pioneer import RADIUS
from rave.scene import Scene

if TYPE_CHECKING:
    from rave.fleet import Fleet
    from rave.odometry import Odometer


class HardwareHost(Scene, Protocol):
    """A world that hardware robots join (``World``): it steps those in ``hardware``,
    and its ``fleet``, which senses them, is told when one comes or goes."""

    fleet: Fleet
    hardware: list[HardwareBody]


class HardwareBody:
    """A hardware robot in the world model: where it reports to be, what it senses."""

    kind = "hardware"

    def __init__(self, world: HardwareHost, name: str, pose: tuple[float, float, float],
                 odometer: Odometer, rng: np.random.Generator,
                 velocity: tuple[float, float] = (0.0, 0.0)) -> None:
        self.world, self.name, self.odometer = world, name, odometer
        self.faults: dict[str, Any] = {}
        self._command = (0.0, 0.0)
        self.emulator = EmulatorProcess(name, world.segments(virtual=False), pose,
                                        int(rng.integers(2**63)), velocity)
        self.body = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        self.shape = pymunk.Circle(self.body, RADIUS)
        self.shape.filter = pymunk.ShapeFilter(categories=ROBOT, mask=ROBOT)
        world.space.add(self.body, self.shape)
        world.hardware.append(self)
        world.fleet.bodies_changed()
        self.place(-1)

    def command(self, v: float, w: float) -> None:
        self.emulator.command(v, w)
        self._command = (v, w)

    def commanded(self) -> tuple[float, float]:
        return self._command

    def inject(self, fault: str, value: Any) -> None:
        self.emulator.fault(fault, value)
        self.faults[fault] = value

    def clear(self, fault: str) -> None:
        self.emulator.clear(fault)
        self.faults.pop(fault, None)

    def end_advance(self) -> None:
        """Take the robot's report on the steps asked for (``emulator.begin_advance``);
        its odometry advances by what its encoders counted."""
        encoders = self.emulator.end_advance().encoders
        if len(encoders):
            self.odometer.advance(encoders[:, 0], encoders[:, 1])

    def place(self, step: int) -> None:
        """Put the stand-in where the robot was at the start of physics ``step`` of the
        last advance (-1: where it is now), moving as it was, so that the world's step
        carries it to about where the robot went (kinematic bodies push by their
        velocity)."""
        x, y, theta, vx, vy, w = self.emulator.report.states[step]
        self.body.position, self.body.angle = (x, y), theta
        self.body.velocity, self.body.angular_velocity = (vx, vy), w
        self.world.space.reindex_shapes_for_body(self.body)

    def hold(self) -> None:
        """Keep the stand-in still where the robot last reported (its emulator failed
        to step: where it went is not known)."""
        self.place(-1)
        self.body.velocity, self.body.angular_velocity = (0.0, 0.0), 0.0

    def odometry(self) -> tuple[float, float, float]:
        return self.odometer.pose()

    def pose(self) -> tuple[float, float, float]:
        x, y, theta = self.emulator.report.states[-1, 0:3]
        return (float(x), float(y), float(theta))

    def velocity(self) -> tuple[float, float, float]:
        vx, vy, w = self.emulator.report.states[-1, 3:6]
        return (float(vx), float(vy), float(w))

    def real_sonar(self) -> np.ndarray:
        """The physical ring's latest readings (what the robot itself senses)."""
        return self.emulator.report.sonar.copy()

    def sonar(self, rng: np.random.Generator) -> np.ndarray:
        """Hybrid: per transducer, the nearer of the real and the virtual reading (a
        dead transducer senses nothing, virtual or real)."""
        world = self.world
        virtual = sonar.read(self.pose(), world.segments(real=False),
                             world.discs(exclude=self.name), sonar.MODEL_NOISE, rng)
        hybrid = np.minimum(self.real_sonar(), virtual)
        hybrid[list(self.faults.get("sonar_dead", ()))] = sonar.MAX_RANGE
        return hybrid

    def close(self) -> None:
        self.emulator.close()
        self.world.hardware.remove(self)
        self.world.space.remove(self.body, self.shape)
        self.world.fleet.bodies_changed()
