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
        self.state = np.array(pose, dtype=np.float64)     # x, y, heading
        self.scale = 1.0 + rng.uniform(-1.0, 1.0, 3) * np.asarray(error)
        self.bias = 0.0                  # rad per m (a fault)

    def advance(self, distance: np.ndarray, rotation: np.ndarray) -> None:
        """Advance by a run of steps, each a wheel ``distance`` and ``rotation``."""
        dead_reckon(self.state, self.scale, distance,
                    rotation * self.scale[2] + self.bias * np.abs(distance))

    def pose(self) -> tuple[float, float, float]:
        x, y, theta = self.state
        return (float(x), float(y), float(theta))


def dead_reckon(state: np.ndarray, scale: np.ndarray, distance: np.ndarray,
                rotation: np.ndarray) -> None:
    """Advance poses ``state`` (x, y, heading in the last axis: one robot's or a
    fleet's) in place by a run of steps, each a wheel ``distance`` and an (already
    scaled) ``rotation``: shape (steps, *state.shape[:-1]). The distance is scaled by
    ``scale``'s x error, along the robot's own heading, as Stage's ``odom_error`` is
    (its y error, sideways, is none of a two-wheeled robot's): scaled along the
    world's x and y, the error depended on which way the robot faced."""
    turned = np.cumsum(rotation, axis=0)
    middle = state[..., 2] + turned - rotation / 2.0         # heading midway through each
    state[..., 0] += (distance * np.cos(middle)).sum(axis=0) * scale[..., 0]
    state[..., 1] += (distance * np.sin(middle)).sum(axis=0) * scale[..., 0]
    state[..., 2] = _wrapped(state[..., 2] + turned[-1])


def dead_reckon_arcs(state: np.ndarray, scale: np.ndarray, distance: np.ndarray,
                     rotation: np.ndarray, steps: int) -> None:
    """``dead_reckon`` for runs of ``steps`` equal steps, one run per pose (each a
    wheel ``distance`` and a scaled ``rotation`` per step), in closed form: the
    steps' midway headings are evenly spaced, so their sum is one chord."""
    half = rotation / 2.0
    heading = state[..., 2] + steps * half                   # midway through the run
    length = distance * chord_sum(steps, half)
    state[..., 0] += length * np.cos(heading) * scale[..., 0]
    state[..., 1] += length * np.sin(heading) * scale[..., 0]
    state[..., 2] = _wrapped(state[..., 2] + steps * rotation)


def chord_sum(steps: int, half_turn: np.ndarray) -> np.ndarray:
    """Length of the sum of ``steps`` unit vectors, each turned ``2 * half_turn`` from
    the one before: ``sin(steps * half_turn) / sin(half_turn)``. It points midway
    between the first and the last."""
    return np.divide(np.sin(steps * half_turn), np.sin(half_turn),
                     out=np.full_like(half_turn, float(steps)), where=np.abs(half_turn) > 1e-9)


def _wrapped(heading: np.ndarray) -> np.ndarray:
    """Headings into [-pi, pi)."""
    return np.remainder(heading + math.pi, math.tau) - math.pi
