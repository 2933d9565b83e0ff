"""The Pioneer 3-DX sonar ring and the sonar model: a cone of rays per transducer.

Order follows the Pioneer ring: 0-7 the front array from +90 deg (left) to -90 deg
(right), 8-15 the rear array from -90 deg round to +90 deg. Each reading is the
nearest echo among ``RAYS`` rays spread over the transducer's ``CONE``; on a
hardware robot a ray striking a smooth surface beyond ``SPECULAR_DEG`` from its
normal returns no echo (specular reflection), so a grazing wall may read as
nothing at all. Ranges are clipped to [``MIN_RANGE``, ``MAX_RANGE``]; no echo reads
``MAX_RANGE``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rave import _raycore, raycast

# (x mm, y mm, heading deg) of each transducer in the robot's frame (ARIA p3dx.p)
RING_MM = np.array([
    (69, 136, 90), (114, 119, 50), (148, 78, 30), (166, 27, 10),
    (166, -27, -10), (148, -78, -30), (114, -119, -50), (69, -136, -90),
    (-157, -136, -90), (-203, -119, -130), (-237, -78, -150), (-255, -27, -170),
    (-255, 27, 170), (-237, 78, 150), (-203, 119, 130), (-157, 136, 90),
], dtype=np.float64)
RING = np.column_stack([RING_MM[:, :2] / 1000.0, np.radians(RING_MM[:, 2])])
COUNT = len(RING)
MIN_RANGE, MAX_RANGE = 0.1, 5.0
CONE = math.radians(30.0)
RAYS = 5
SPECULAR_DEG = 20.0
_SPREAD = np.linspace(-CONE / 2, CONE / 2, RAYS)
# every ray of the ring (transducer by transducer), cast for whole fleets at once
CASTER = raycast.RingCaster(np.repeat(RING[:, 0:2], RAYS, axis=0),
                            (RING[:, 2:3] + _SPREAD).ravel(), MAX_RANGE)


@dataclass
class SonarNoise:
    """How a reading departs from the geometric range."""

    sigma0: float = 0.01          # m
    sigma_per_m: float = 0.01     # m of standard deviation per m of range
    dropout: float = 0.0          # probability that a reading returns no echo
    specular: bool = False        # grazing rays return no echo
    quantum: float = 0.001        # readings are whole millimetres


# Readings computed from the world model (a simulated robot's ring, the virtual half
# of a hardware robot's hybrid one): a little noise, every echo heard.
MODEL_NOISE = SonarNoise(sigma0=0.005, sigma_per_m=0.005)


def rays(pose: tuple[float, float, float], which: np.ndarray | None = None,
         ) -> tuple[np.ndarray, np.ndarray]:
    """Origins and unit directions of the cone rays of transducers ``which`` (all by
    default) for a robot at ``pose``: shape (len(which) * RAYS, 2) each."""
    origins, _, directions = ring_rays(np.asarray([pose], dtype=np.float64))
    chosen = slice(None) if which is None else which
    return np.repeat(origins[0, chosen], RAYS, axis=0), directions[0, chosen].reshape(-1, 2)


def read(pose: tuple[float, float, float], segments: np.ndarray, discs: np.ndarray | None,
         noise: SonarNoise, rng: np.random.Generator, which: np.ndarray | None = None,
         ) -> np.ndarray:
    """The readings of transducers ``which`` (all by default) against ``segments`` and
    ``discs``, in metres."""
    origins, directions = rays(pose, which)
    hits = raycast.cast(origins, directions, MAX_RANGE, segments, discs)
    ranges = hits.ranges
    if noise.specular:
        grazing = hits.incidence_cos < math.cos(math.radians(SPECULAR_DEG))
        ranges = np.where(grazing, np.inf, ranges)
    return readings(ranges, noise, rng)


def readings(ranges: np.ndarray, noise: SonarNoise, rng: np.random.Generator) -> np.ndarray:
    """Readings from the ranges of each transducer's ``RAYS`` rays (consecutive in the
    last axis; ``inf``: no echo): the nearest echo, noise, dropouts, clipping to the
    sensor's range, millimetres."""
    ranges = np.ascontiguousarray(ranges, dtype=np.float64)
    shape = (*ranges.shape[:-1], ranges.shape[-1] // RAYS)
    normal = rng.normal(0.0, 1.0, shape)
    dropped = rng.random(shape) < noise.dropout if noise.dropout else None
    out = np.empty(shape)
    _raycore.readings(ranges, RAYS, normal, dropped, out, noise.sigma0, noise.sigma_per_m,
                      noise.quantum, MIN_RANGE, MAX_RANGE)
    return out


def ring_rays(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For robots at ``poses`` (R, 3): each transducer's origin (R, 16, 2) and heading
    (R, 16), and the unit directions of its cone's rays (R, 16, RAYS, 2)."""
    x, y, theta = poses[:, 0:1], poses[:, 1:2], poses[:, 2:3]
    c, s = np.cos(theta), np.sin(theta)
    origins = np.stack([x + c * RING[:, 0] - s * RING[:, 1],
                        y + s * RING[:, 0] + c * RING[:, 1]], axis=-1)
    headings = theta + RING[:, 2]
    angles = headings[:, :, None] + _SPREAD
    return origins, headings, np.stack([np.cos(angles), np.sin(angles)], axis=-1)
