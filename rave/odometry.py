"""Dead reckoning: a robot's pose integrated from what its wheels report, with the
systematic error every real odometer has (Stage's ``odom_error`` model)."""

from __future__ import annotations

import math

import numpy as np

ERROR = (0.03, 0.03, 0.05)       # largest fractional error of x, y and heading increments


class Odometer:
    """Integrates distance and rotation increments into a pose, each scaled by this
    robot's own error (drawn once) and, under the ``odometry_bias`` fault, a heading
    drift per metre travelled."""

    def __init__(self, pose: tuple[float, float, float], rng: np.random.Generator,
                 error: tuple[float, float, float] = ERROR) -> None:
        self.x, self.y, self.theta = pose
        self.scale = 1.0 + rng.uniform(-1.0, 1.0, 3) * np.asarray(error)
        self.bias = 0.0                  # rad per m (a fault)

    def advance(self, distance: float, rotation: float) -> None:
        rotation = rotation * self.scale[2] + self.bias * abs(distance)
        heading = self.theta + rotation / 2.0
        self.x += distance * math.cos(heading) * self.scale[0]
        self.y += distance * math.sin(heading) * self.scale[1]
        self.theta = math.remainder(self.theta + rotation, math.tau)

    def pose(self) -> tuple[float, float, float]:
        return (float(self.x), float(self.y), float(self.theta))
