"""Vectorized ray casting against the world's segments and robot discs (numpy).

Every range sensor in RAVE (sonar cones, camera line of sight, the hybrid
sensors' virtual component) is a batch of rays cast here at once: one numpy
expression per batch instead of a pymunk query per ray. Segments farther than
the rays can reach are culled first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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


CHUNK = 128                 # robots per pass: keeps the temporaries in cache


def cast_rings(origins: np.ndarray, headings: np.ndarray, directions: np.ndarray,
               half_angle: float, max_range: float, segments: np.ndarray,
               discs: np.ndarray) -> np.ndarray:
    """Ranges for many robots' sensor rings at once: ``origins`` (R, T, 2) and
    ``headings`` (R, T), one per transducer; ``directions`` (R, T, N, 2), N rays each
    within ``half_angle`` of the heading; each robot's own candidate ``segments``
    (R, K, 4) and ``discs`` (R, D, 3), NaN-padded. Returns (R, T, N), ``inf`` where
    nothing is hit.

    Each transducer first keeps only what can meet its cone (a segment or disc wholly
    outside one edge of the cone, or behind it, cannot), so the rays are tested
    against a few candidates instead of all those around the robot."""
    out = np.empty(directions.shape[:3])
    for start in range(0, len(origins), CHUNK):
        part = slice(start, start + CHUNK)
        o, h, d = origins[part], headings[part], directions[part]
        cone = _Cone(o, h, half_angle)
        ranges = _ring_segments(o, d, max_range, cone.segments(segments[part]))
        if discs.shape[1]:
            np.minimum(ranges, _ring_discs(o, d, max_range, cone.discs(discs[part])),
                       out=ranges)
        out[part] = ranges
    return out


class _Cone:
    """The cones of a batch of transducers, and what each may meet."""

    def __init__(self, origins: np.ndarray, headings: np.ndarray, half_angle: float) -> None:
        self.origins = origins
        # unit vectors of each cone's two edges and of its axis, (R, T) each
        self.left = (np.cos(headings + half_angle), np.sin(headings + half_angle))
        self.right = (np.cos(headings - half_angle), np.sin(headings - half_angle))
        self.axis = (np.cos(headings), np.sin(headings))

    def _sides(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
        """For points (R, T, K) relative to the origins: how far left of the left edge,
        right of the right edge, and ahead along the axis."""
        lx, ly = (v[..., None] for v in self.left)
        rx, ry = (v[..., None] for v in self.right)
        ax, ay = (v[..., None] for v in self.axis)
        return lx * y - ly * x, ry * x - rx * y, ax * x + ay * y

    def segments(self, segments: np.ndarray) -> np.ndarray:
        """Per transducer, the segments that may cross its cone: (R, T, k, 4)."""
        ox, oy = self.origins[..., 0, None], self.origins[..., 1, None]
        ax, ay = segments[:, None, :, 0] - ox, segments[:, None, :, 1] - oy
        bx, by = segments[:, None, :, 2] - ox, segments[:, None, :, 3] - oy
        left_a, right_a, ahead_a = self._sides(ax, ay)
        left_b, right_b, ahead_b = self._sides(bx, by)
        keep = ~(((left_a > 0) & (left_b > 0)) | ((right_a > 0) & (right_b > 0))
                 | ((ahead_a < 0) & (ahead_b < 0)) | np.isnan(ax))
        return _packed(segments, keep)

    def discs(self, discs: np.ndarray) -> np.ndarray:
        """Per transducer, the discs that may reach into its cone: (R, T, k, 3)."""
        x = discs[:, None, :, 0] - self.origins[..., 0, None]
        y = discs[:, None, :, 1] - self.origins[..., 1, None]
        left, right, ahead = self._sides(x, y)
        radius = discs[:, None, :, 2]
        keep = ~((left > radius) | (right > radius) | (ahead < -radius) | np.isnan(x))
        return _packed(discs, keep)


def _packed(items: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """``items`` (R, K, f) chosen per transducer by ``keep`` (R, T, K), packed to the
    left: (R, T, k, f), NaN-padded."""
    width = int(keep.sum(axis=2).max(initial=0))
    order = np.argsort(~keep, axis=2, kind="stable")[..., :width]
    kept = np.take_along_axis(keep, order, axis=2)
    chosen = items[np.arange(len(items))[:, None, None], order]
    chosen[~kept] = np.nan
    return chosen


def _ring_segments(o: np.ndarray, d: np.ndarray, max_range: float,
                   seg: np.ndarray) -> np.ndarray:
    # t = (w x e) / (d x e) and u = (w x d) / (d x e) with w = p - o: the numerator
    # of t depends on the transducer, not the ray, so it is computed once per origin.
    px, py = seg[..., 0], seg[..., 1]                           # (R, T, k)
    ex, ey = seg[..., 2] - px, seg[..., 3] - py
    wx, wy = px - o[..., 0, None], py - o[..., 1, None]
    nt = (wx * ey - wy * ex)[:, :, None, :]
    dx, dy = d[..., 0, None], d[..., 1, None]                   # (R, T, N, 1)
    ex, ey, wx, wy = ex[:, :, None], ey[:, :, None], wx[:, :, None], wy[:, :, None]
    denom = dx * ey - dy * ex
    nu = wx * dy - wy * dx
    with np.errstate(divide="ignore", invalid="ignore"):
        t = nt / denom
    hit = (t >= 0) & (t <= max_range) & (nu * denom >= 0) & (np.abs(nu) <= np.abs(denom))
    return np.where(hit, t, np.inf).min(axis=3, initial=np.inf)


def _ring_discs(o: np.ndarray, d: np.ndarray, max_range: float,
                discs: np.ndarray) -> np.ndarray:
    mx = (o[..., 0, None] - discs[..., 0])[:, :, None, :]
    my = (o[..., 1, None] - discs[..., 1])[:, :, None, :]
    c = mx * mx + my * my - (discs[..., 2] ** 2)[:, :, None, :]
    b = mx * d[..., 0, None] + my * d[..., 1, None]
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    hit = (disc >= 0) & (c > 0) & (t >= 0) & (t <= max_range)
    return np.where(hit, t, np.inf).min(axis=3, initial=np.inf)
