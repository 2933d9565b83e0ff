"""``Robot``: one robot as a controller sees it, whichever back end serves it.

The same calls drive a simulated robot and a hardware one (``backend`` is chosen at
``add_robot`` and may be swapped while running: the controller keeps its
``Robot`` and notices nothing but the physics). ``gps`` and ``others`` are virtual
sensors with no physical analogue.
"""

from __future__ import annotations

import math
from numbers import Integral, Real
from typing import Any, Protocol

import numpy as np

from rave import camera, sonar
from rave.emulator import FAULTS
from rave.hardware import HardwareBody, HardwareHost
from rave.odometry import Odometer
from rave.pioneer import MAX_SPEED, MAX_TURN
from rave.simulated import SimulatedBody

BACKENDS = ("sim", "hardware")


class RobotHost(HardwareHost, Protocol):
    """A world that robots join (``World``), each by name in ``robots``."""

    robots: dict[str, Robot]


class Robot:
    """Drive it, read its sensors; ``swap`` its back end while it runs."""

    def __init__(self, world: RobotHost, name: str, pose: tuple[float, float, float], *,
                 backend: str, color: str, index: int) -> None:
        _check_backend(name, backend)
        camera.rgb(color)                                   # a clear error now, not later
        self.world, self.name, self.color = world, name, color
        self.rng = np.random.default_rng([world.seed, index])
        self.odometer = Odometer(pose, self.rng)
        self._body = self._make(backend, pose, (0.0, 0.0), (0.0, 0.0))

    def _make(self, backend: str, pose: tuple[float, float, float],
              velocity: tuple[float, float], command: tuple[float, float],
              ) -> SimulatedBody | HardwareBody:
        if backend == "sim":
            body: SimulatedBody | HardwareBody = SimulatedBody(
                self.world.fleet, self.name, pose, self.odometer, velocity)
        else:
            body = HardwareBody(self.world, self.name, pose, self.odometer, self.rng, velocity)
        body.command(*command)
        return body

    @property
    def backend(self) -> str:
        """``"sim"`` or ``"hardware"``."""
        return self._body.kind

    # -- actuators -------------------------------------------------------------------
    def drive(self, v: float, w: float) -> None:
        """Go at ``v`` m/s forward and turn at ``w`` rad/s (left positive), clipped to
        the robot's limits; the command holds until the next one."""
        if not (math.isfinite(v) and math.isfinite(w)):
            raise ValueError(f"robot {self.name}: drive({v}, {w}) needs finite speeds")
        self._body.command(max(-MAX_SPEED, min(MAX_SPEED, v)), max(-MAX_TURN, min(MAX_TURN, w)))

    def stop(self) -> None:
        self.drive(0.0, 0.0)

    def commanded(self) -> tuple[float, float]:
        """The command in force (v, w), as clipped to the robot's limits."""
        return self._body.commanded()

    # -- sensors ---------------------------------------------------------------------
    def sonar(self) -> np.ndarray:
        """16 ranges in metres, Pioneer ring order (0-7 front, left to right; 8-15
        rear, right round to left), 0.1-5 m; 5 m means no echo."""
        return self._body.sonar(self.rng)

    def odometry(self) -> tuple[float, float, float]:
        """Dead-reckoned (x, y, heading) from the wheels, drifting as real ones do."""
        return self._body.odometry()

    def camera(self, hue: float | None = None, tolerance: float = 15.0) -> list[camera.Blob]:
        """Colour blobs in view (60 degrees, 8 m), nearest first; only those within
        ``tolerance`` degrees of ``hue`` when given."""
        return camera.look(self.gps(), self.world.targets(exclude=self.name),
                           self.world.segments(), hue, tolerance,
                           self.world.discs(exclude=self.name))

    def gps(self) -> tuple[float, float, float]:
        """(Virtual) the robot's pose in the world: exact for a simulated robot, as
        reported by the localization system for a hardware one."""
        return self._body.pose()

    def velocity(self) -> tuple[float, float, float]:
        """(Virtual) (vx, vy, angular velocity) in the world frame."""
        return self._body.velocity()

    def others(self) -> dict[str, tuple[float, float, float, float]]:
        """(Virtual) every other robot's (x, y, vx, vy)."""
        return {name: (*robot.gps()[:2], *robot.velocity()[:2])
                for name, robot in self.world.robots.items() if name != self.name}

    # -- back ends and faults ----------------------------------------------------------
    def swap(self, backend: str) -> None:
        """Serve this robot by the other back end from now on, at its current pose and
        speed; commands, odometry and the controller's handle carry over (a hardware
        robot's faults do not). Refused, as nothing changes, where the other back end's
        robot would overlap an obstacle: a hardware robot that drove into a virtual one
        was swapped to "sim" inside it, and stood boxed in."""
        _check_backend(self.name, backend)
        if backend == self.backend:
            return
        pose, (vx, vy, w) = self._body.pose(), self._body.velocity()
        hits = self.world.blocking(backend, pose[0], pose[1])
        if hits:
            raise ValueError(f"robot {self.name}: at ({pose[0]:.2f}, {pose[1]:.2f}) a {backend} "
                             f"robot would overlap {', '.join(hits)}; drive it clear first")
        command = self._body.commanded()
        speed = vx * math.cos(pose[2]) + vy * math.sin(pose[2])   # (negative: reversing)
        old = self._body
        old.close()
        self.odometer.bias = 0.0        # its faults went with the hardware robot
        try:
            self._body = self._make(backend, pose, (speed, w), command)
        except BaseException:           # (an emulator that would not start) as it was
            self._body = self._make(old.kind, pose, (speed, w), command)
            raise

    def inject(self, fault: str, **params: Any) -> None:
        """Inject a fault into a hardware robot: ``motors_off``, ``sonar_dead``
        (``sonars=[i, ...]``, all by default) or ``odometry_bias`` (``bias`` rad/m)."""
        body = self._hardware(fault)
        if fault == "sonar_dead":
            body.inject(fault, self._sonars(params.get("sonars", range(sonar.COUNT))))
        elif fault == "odometry_bias":
            bias = params.get("bias", 0.05)
            if not (isinstance(bias, Real) and math.isfinite(bias)):
                raise ValueError(f"robot {self.name}: odometry_bias's bias must be a finite "
                                 f"number (rad per m), not {bias!r}")
            self.odometer.bias = float(bias)
            body.inject(fault, self.odometer.bias)
        else:
            body.inject(fault, True)

    def clear(self, fault: str | None = None) -> None:
        """Remove one fault, or all of them."""
        body = self._hardware(fault)
        for name in [fault] if fault else list(body.faults):
            body.clear(name)
            if name == "odometry_bias":
                self.odometer.bias = 0.0

    def _sonars(self, sonars: Any) -> tuple[int, ...]:
        """The transducers a ``sonar_dead`` fault names, checked here: a wrong one would
        break the robot's emulator at every step, or (negative) silence another one."""
        chosen = tuple(sonars) if isinstance(sonars, list | tuple | range) else (sonars,)
        if not all(isinstance(i, Integral) and not isinstance(i, bool) and 0 <= i < sonar.COUNT
                   for i in chosen):
            raise ValueError(f"robot {self.name}: sonar_dead's sonars must be transducer "
                             f"numbers 0-{sonar.COUNT - 1}, not {sonars!r}")
        return tuple(int(i) for i in chosen)

    def _hardware(self, fault: str | None) -> HardwareBody:
        if fault is not None and fault not in FAULTS:
            raise ValueError(f"robot {self.name}: unknown fault {fault!r}; faults: "
                             f"{', '.join(FAULTS)}")
        if not isinstance(self._body, HardwareBody):
            raise ValueError(f"robot {self.name} is simulated: faults are injected into "
                             "hardware robots (swap it to 'hardware' first)")
        return self._body

    def _close(self) -> None:
        self._body.close()


def _check_backend(name: str, backend: str) -> None:
    if backend not in BACKENDS:
        raise ValueError(f"robot {name}: backend must be one of {', '.join(BACKENDS)}, "
                         f"not {backend!r}")
