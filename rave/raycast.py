"""Vectorized ray casting against the world's segments and robot discs (numpy).

Every range sensor in RAVE (sonar cones, camera line of sight, the hybrid
sensors' virtual component) is a batch of rays cast here at once: one numpy
expression per batch instead of a pymunk query per ray. Segments farther than
the rays can reach are culled first. A whole fleet's sonar rings go through
``RingCaster``, whose pair loop is C.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rave import _raycore
from rave.neighbours import boxes_of_segments

_EPS = 1e-12


@dataclass
class Hits:
    """Per ray: the range to the first hit (``inf`` for none) and the cosine of the
    angle between the ray and the surface normal there (1 = head-on)."""

    ranges: np.ndarray
    incidence_cos: np.ndarray


def cast(origins: np.ndarray, directions: np.ndarray, max_range: float,
         segments: np.ndarray, discs: np.ndarray | None = None) -> Hits:
    """Cast rays (``origins``, unit ``directions``: shape (r, 2)) against ``segments``
    (shape (n, 4): x0, y0, x1, y1) and ``discs`` (shape (m, 3): x, y, radius)."""
    count = len(origins)
    ranges = np.full(count, np.inf)
    cosines = np.ones(count)
    if len(segments):
        segments = _near(segments, origins, max_range)
    if len(segments):
        _against_segments(origins, directions, max_range, segments, ranges, cosines)
    if discs is not None and len(discs):
        _against_discs(origins, directions, max_range, discs, ranges, cosines)
    return Hits(ranges, cosines)


def _near(segments: np.ndarray, origins: np.ndarray, reach: float) -> np.ndarray:
    """The segments within ``reach`` of any origin (a cheap bounding-box test)."""
    low = origins.min(axis=0) - reach
    high = origins.max(axis=0) + reach
    boxes = boxes_of_segments(segments)
    keep = (boxes[:, 2:4] >= low).all(axis=1) & (boxes[:, 0:2] <= high).all(axis=1)
    return segments[keep]


def _against_segments(origins: np.ndarray, directions: np.ndarray, max_range: float,
                      segments: np.ndarray, ranges: np.ndarray, cosines: np.ndarray) -> None:
    t = segment_hits(origins[:, None, 0], origins[:, None, 1], directions[:, None, 0],
                     directions[:, None, 1], segments[None, :, 0], segments[None, :, 1],
                     segments[None, :, 2] - segments[None, :, 0],
                     segments[None, :, 3] - segments[None, :, 1], max_range)
    nearest = np.argmin(t, axis=1)
    best = t[np.arange(len(origins)), nearest]
    closer = best < ranges
    edge = segments[nearest, 2:4] - segments[nearest, 0:2]
    length = np.maximum(np.hypot(edge[:, 0], edge[:, 1]), _EPS)
    cos = np.abs(directions[:, 0] * edge[:, 1] - directions[:, 1] * edge[:, 0]) / length
    ranges[closer] = best[closer]
    cosines[closer] = cos[closer]


def _against_discs(origins: np.ndarray, directions: np.ndarray, max_range: float,
                   discs: np.ndarray, ranges: np.ndarray, cosines: np.ndarray) -> None:
    t = disc_hits(origins[:, None, 0], origins[:, None, 1], directions[:, None, 0],
                  directions[:, None, 1], discs[None, :, 0], discs[None, :, 1],
                  discs[None, :, 2], max_range)
    nearest = np.argmin(t, axis=1)
    best = t[np.arange(len(origins)), nearest]
    closer = best < ranges
    hit = origins + directions * np.where(np.isfinite(best), best, 0.0)[:, None]
    normal = hit - discs[nearest, 0:2]
    norm = np.maximum(np.hypot(normal[:, 0], normal[:, 1]), _EPS)
    cos = np.abs(np.einsum("rk,rk->r", normal, directions)) / norm
    ranges[closer] = best[closer]
    cosines[closer] = cos[closer]


def segment_hits(ox: np.ndarray, oy: np.ndarray, dx: np.ndarray, dy: np.ndarray,
                 px: np.ndarray, py: np.ndarray, ex: np.ndarray, ey: np.ndarray,
                 max_range: float) -> np.ndarray:
    """How far along rays ``o + t d`` (unit ``d``) each meets segment ``p + u e``
    (0 <= u <= 1), ``inf`` where it does not within ``max_range``; arrays broadcast."""
    # Solved with 2D cross products: t = (w x e) / (d x e), u = (w x d) / (d x e),
    # w = p - o. The sign and size tests on u's numerator spare a division.
    wx, wy = px - ox, py - oy
    denom = dx * ey - dy * ex
    nu = wx * dy - wy * dx
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (wx * ey - wy * ex) / denom
    miss = ~((np.abs(denom) >= _EPS) & (t >= 0) & (t <= max_range) & (nu * denom >= 0)
             & (np.abs(nu) <= np.abs(denom)))
    t[miss] = np.inf
    return t


def disc_hits(ox: np.ndarray, oy: np.ndarray, dx: np.ndarray, dy: np.ndarray,
              cx: np.ndarray, cy: np.ndarray, radius: np.ndarray, max_range: float,
              ) -> np.ndarray:
    """How far along rays ``o + t d`` (unit ``d``) each meets the disc at ``c``, ``inf``
    where it does not within ``max_range``; arrays broadcast. A ray from inside the
    disc meets it at once (0): a transducer off the robot's rim, touching another
    robot, is inside that robot's disc, and read no echo from it."""
    mx, my = ox - cx, oy - cy
    b = mx * dx + my * dy
    c = mx * mx + my * my - radius * radius
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        t = np.where(c > 0, -b - np.sqrt(disc), 0.0)
    t[~((disc >= 0) & (t >= 0) & (t <= max_range))] = np.inf
    return t


class RingCaster:
    """One sensor ring's rays, fixed in the robot's frame, cast for many robots at once.

    Dense casting tests every ray against every obstacle near its robot; most of
    those tests miss because the obstacle lies at another bearing. Here each
    (robot, obstacle) pair first becomes the run of rays that can meet it: the
    obstacle's bearing interval seen from the robot's centre, widened by how far a
    transducer sits off the centre, selects a run of the ring's rays sorted by
    bearing. Only those (pair, ray) combinations are intersected, in the robot's
    frame (where the ring's rays are constants), and each ray keeps its nearest
    hit. The result is that of casting every ray against everything. The pair loop
    is C (``_raycore.c``, the formulas of ``segment_hits`` and ``disc_hits``):
    as numpy expressions its fixed cost per call bounded a fleet's scan.
    """

    BINS = 720                    # bearing bins of the run look-up (0.5 deg each)

    def __init__(self, offsets: np.ndarray, bearings: np.ndarray, max_range: float) -> None:
        """``offsets`` (M, 2) and ``bearings`` (M,): each ray's origin and direction
        in the robot's frame."""
        bearings = np.remainder(bearings, math.tau)
        self.order = np.argsort(bearings, kind="stable").astype(np.intp)   # by bearing
        self.count = len(bearings)
        ox, oy = offsets[self.order, 0], offsets[self.order, 1]
        dx, dy = np.cos(bearings[self.order]), np.sin(bearings[self.order])
        # A ray from within ``radius`` of the centre that points away from it meets a
        # point at distance r from the centre within asin(radius / r) of that point's
        # bearing: the widening below. (Pointing away keeps the angle under 90 deg.)
        if np.any(ox * dx + oy * dy < 0):
            raise ValueError("every ray of a ring must point away from the robot's centre")
        self._rays = np.stack([ox, oy, dx, dy])               # (4, M)
        self.radius = float(np.sqrt(ox * ox + oy * oy).max(initial=0.0))
        self.max_range = max_range
        # How many rays (sorted, the ring twice round) lie below each bin's edge: a
        # run from bearing a to b is taken as whole bins, a superset found by two
        # table look-ups instead of binary searches.
        twice = np.concatenate([bearings[self.order], bearings[self.order] + math.tau])
        edges = np.arange(2 * self.BINS + 2) * (math.tau / self.BINS)
        self._below = np.searchsorted(twice, edges, side="left")

    def cast(self, poses: np.ndarray, segments: np.ndarray,
             segment_pairs: tuple[np.ndarray, np.ndarray], discs: np.ndarray,
             disc_pairs: tuple[np.ndarray, np.ndarray], depths: np.ndarray | None = None,
             ) -> np.ndarray:
        """Ranges (R, M) of the rays of robots at ``poses`` (R, 3), ``inf`` where a ray
        meets nothing, against the ``segments`` (n, 4) and ``discs`` (m, 3) paired with
        each robot by (robot index, item index) arrays; unpaired items are not seen.
        ``depths`` (n,), as ``World.depths``, let a robot skip the far sides of convex
        obstacles it is well outside of."""
        if depths is None:
            depths = np.full(len(segments), np.inf)
        nearest = np.full((len(poses), self.count), np.inf)
        _raycore.cast_pairs(_floats(poses), self._rays, self.order, self._below,
                            _floats(segments), _floats(depths), *map(_indices, segment_pairs),
                            _floats(discs), *map(_indices, disc_pairs), nearest, self.radius,
                            self.max_range)
        return nearest


def _floats(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


def _indices(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.intp)
