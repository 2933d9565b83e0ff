"""Vectorized ray casting against the world's segments and robot discs (numpy).

Every range sensor in RAVE (sonar cones, camera line of sight, the hybrid
sensors' virtual component) is a batch of rays cast here at once: one numpy
expression per batch instead of a pymunk query per ray. Segments farther than
the rays can reach are culled first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
    xs, ys = segments[:, [0, 2]], segments[:, [1, 3]]
    keep = ((xs.max(axis=1) >= low[0]) & (xs.min(axis=1) <= high[0])
            & (ys.max(axis=1) >= low[1]) & (ys.min(axis=1) <= high[1]))
    return segments[keep]


def _against_segments(origins: np.ndarray, directions: np.ndarray, max_range: float,
                      segments: np.ndarray, ranges: np.ndarray, cosines: np.ndarray) -> None:
    # origin + t*direction = p + u*(q - p): solved with 2D cross products, for every
    # (ray, segment) pair at once.
    p = segments[None, :, 0:2]
    e = segments[None, :, 2:4] - segments[None, :, 0:2]
    d = directions[:, None, :]
    w = p - origins[:, None, :]
    denom = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]
    parallel = np.abs(denom) < _EPS
    denom = np.where(parallel, 1.0, denom)
    t = (w[..., 0] * e[..., 1] - w[..., 1] * e[..., 0]) / denom
    u = (w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]) / denom
    t = np.where(~parallel & (t >= 0) & (t <= max_range) & (u >= 0) & (u <= 1), t, np.inf)
    nearest = np.argmin(t, axis=1)
    rows = np.arange(len(origins))
    best = t[rows, nearest]
    closer = best < ranges
    edge = e[0, nearest]
    length = np.maximum(np.hypot(edge[:, 0], edge[:, 1]), _EPS)
    cos = np.abs(directions[:, 0] * edge[:, 1] - directions[:, 1] * edge[:, 0]) / length
    ranges[closer] = best[closer]
    cosines[closer] = cos[closer]


def _against_discs(origins: np.ndarray, directions: np.ndarray, max_range: float,
                   discs: np.ndarray, ranges: np.ndarray, cosines: np.ndarray) -> None:
    m = origins[:, None, :] - discs[None, :, 0:2]
    b = np.einsum("rnk,rk->rn", m, directions)
    c = np.einsum("rnk,rnk->rn", m, m) - discs[None, :, 2] ** 2
    disc = b * b - c
    root = np.sqrt(np.maximum(disc, 0.0))
    t = -b - root
    t = np.where((disc >= 0) & (c > 0) & (t >= 0) & (t <= max_range), t, np.inf)
    nearest = np.argmin(t, axis=1)
    rows = np.arange(len(origins))
    best = t[rows, nearest]
    closer = best < ranges
    hit = origins + directions * np.where(np.isfinite(best), best, 0.0)[:, None]
    normal = hit - discs[nearest, 0:2]
    norm = np.maximum(np.hypot(normal[:, 0], normal[:, 1]), _EPS)
    cos = np.abs(np.einsum("rk,rk->r", normal, directions)) / norm
    ranges[closer] = best[closer]
    cosines[closer] = cos[closer]
