"""The colour-blob camera: other robots (and coloured obstacles) seen as blobs, found
by HSI colour matching the way a CMUcam-style blob finder reports them.

No image is rendered: each candidate within the field of view and range is tested
for line of sight with one ray, then reported with its bearing (radians, positive
to the left), apparent size (the angle it spans) and hue (degrees, HSI).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rave import raycast

FOV = math.radians(60.0)
RANGE = 8.0

COLORS = {
    "red": (1.0, 0.0, 0.0), "green": (0.0, 0.8, 0.0), "blue": (0.0, 0.0, 1.0),
    "yellow": (1.0, 1.0, 0.0), "cyan": (0.0, 1.0, 1.0), "magenta": (1.0, 0.0, 1.0),
    "orange": (1.0, 0.5, 0.0), "purple": (0.5, 0.0, 0.5), "white": (1.0, 1.0, 1.0),
    "grey": (0.5, 0.5, 0.5), "black": (0.0, 0.0, 0.0),
}


def rgb(color: str | tuple[float, float, float]) -> tuple[float, float, float]:
    """A colour name, ``#rrggbb``, or an (r, g, b) tuple in [0, 1], as (r, g, b)."""
    if isinstance(color, tuple):
        return color
    if color.startswith("#") and len(color) == 7:
        return tuple(int(color[i:i + 2], 16) / 255.0 for i in (1, 3, 5))  # type: ignore[return-value]
    try:
        return COLORS[color]
    except KeyError:
        raise ValueError(f"unknown colour {color!r}: use one of {', '.join(COLORS)} "
                         "or #rrggbb") from None


def hsi(color: str | tuple[float, float, float]) -> tuple[float, float, float]:
    """Hue (degrees), saturation and intensity of a colour (Gonzalez & Woods)."""
    r, g, b = rgb(color)
    intensity = (r + g + b) / 3.0
    if intensity == 0.0:
        return 0.0, 0.0, 0.0
    saturation = 1.0 - min(r, g, b) / intensity
    denom = math.sqrt((r - g) ** 2 + (r - b) * (g - b))
    if denom == 0.0:
        return 0.0, saturation, intensity
    theta = math.degrees(math.acos(max(-1.0, min(1.0, 0.5 * ((r - g) + (r - b)) / denom))))
    return (theta if b <= g else 360.0 - theta), saturation, intensity


def hue_distance(a: float, b: float) -> float:
    """The circular distance between two hues, in degrees."""
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)


@dataclass(frozen=True)
class Blob:
    """One coloured thing the camera sees."""

    bearing: float      # radians from the heading, positive to the left
    size: float         # radians it spans
    hue: float          # degrees (HSI)
    distance: float     # metres (a blob finder's size already implies it)


@dataclass(frozen=True)
class Target:
    """Something with a colour that a camera may see: a disc at (x, y), or, with an
    ``outline``, the polygon of those corners (a coloured obstacle)."""

    x: float
    y: float
    radius: float
    color: str | tuple[float, float, float]
    outline: tuple[tuple[float, float], ...] | None = None


def look(pose: tuple[float, float, float], targets: list[Target], occluders: np.ndarray,
         hue: float | None = None, tolerance: float = 15.0,
         discs: np.ndarray | None = None) -> list[Blob]:
    """The blobs seen from ``pose``: saturated targets in view and in range whose
    centre is not hidden behind ``occluders`` (segments) or ``discs`` (x, y, radius:
    the other robots, a target's own disc aside), matching ``hue`` within
    ``tolerance`` degrees when given; nearest first."""
    x, y, theta = pose
    discs = np.zeros((0, 3)) if discs is None else np.asarray(discs, dtype=np.float64)
    blobs = []
    for target in targets:
        h, s, i = hsi(target.color)
        if s < 0.25 or not 0.1 <= i <= 0.95:          # grey, black or washed out
            continue
        if hue is not None and hue_distance(h, hue) > tolerance:
            continue
        seen = _view(x, y, theta, target)
        if seen is None:
            continue
        near, (nx, ny), bearing, size = seen
        bearing = math.remainder(bearing - theta, math.tau)
        if near > RANGE or abs(bearing) > FOV / 2:
            continue
        ray = np.array([[(nx - x) / near, (ny - y) / near]])
        # (a hair short of the nearest point: the target's own edges must not hide it)
        others = discs[(discs[:, 0] != target.x) | (discs[:, 1] != target.y)]
        hidden = raycast.cast(np.array([[x, y]]), ray, near * (1 - 1e-9), occluders, others)
        if np.isfinite(hidden.ranges[0]):
            continue
        blobs.append(Blob(bearing, size, h, near))
    return sorted(blobs, key=lambda blob: blob.distance)


def _view(x: float, y: float, theta: float, target: Target,
          ) -> tuple[float, tuple[float, float], float, float] | None:
    """How ``target`` looks from (x, y), facing ``theta``: the distance to its nearest
    point, that point, the bearing of its middle (world frame) and the angle it spans;
    None from inside. A disc is seen whole (a robot: its centre must be in view); an
    outline only as far as it lies in the field of view, as the camera's image holds
    it (``_outline_view``)."""
    if target.outline is not None:
        return _outline_view(x, y, theta, np.asarray(target.outline, dtype=np.float64))
    dx, dy = target.x - x, target.y - y
    distance = math.hypot(dx, dy)
    if distance <= target.radius:
        return None
    near = distance - target.radius
    point = (x + dx * near / distance, y + dy * near / distance)
    return near, point, math.atan2(dy, dx), 2.0 * math.asin(target.radius / distance)


def _outline_view(x: float, y: float, theta: float, corners: np.ndarray,
                  ) -> tuple[float, tuple[float, float], float, float] | None:
    """The part of polygon ``corners`` within the field of view from (x, y) facing
    ``theta``: its nearest point and the bearings it spans, from each edge's share of
    the view (an edge subtends less than half a turn, its bearings in order along it).
    So a camera inside a U-shaped obstacle's pocket sees its back, and one beside a
    long bench sees the bench fill its view, not the disc round its corners."""
    if _inside(x, y, corners):
        return None
    half, viewer = FOV / 2, np.array([x, y])
    low, high, nearest = math.inf, -math.inf, None
    for start, end in zip(corners, np.roll(corners, -1, axis=0), strict=True):
        first = math.atan2(start[1] - y, start[0] - x)
        turn = math.remainder(math.atan2(end[1] - y, end[0] - x) - first, math.tau)
        a = math.remainder(first - theta, math.tau)
        lo, hi = max(min(a, a + turn), -half), min(max(a, a + turn), half)
        if lo > hi:
            continue                                # this edge is out of view
        ends = [_along(viewer, theta + bearing, start, end) for bearing in (lo, hi)]
        point, gap = _nearest_on(viewer, *ends)
        if gap <= 0.0:
            return None                             # touching it
        low, high = min(low, lo), max(high, hi)
        if nearest is None or gap < nearest[0]:
            nearest = (gap, point)
    if nearest is None:
        return None
    return nearest[0], nearest[1], theta + (low + high) / 2, high - low


def _along(viewer: np.ndarray, bearing: float, start: np.ndarray, end: np.ndarray,
           ) -> np.ndarray:
    """Where the ray from ``viewer`` at ``bearing`` meets the line start-end, clamped to
    the segment (an edge seen end-on: its nearer end)."""
    u, edge = np.array([math.cos(bearing), math.sin(bearing)]), end - start
    across = edge[0] * u[1] - edge[1] * u[0]
    if abs(across) < 1e-12:
        return start if np.hypot(*(start - viewer)) <= np.hypot(*(end - viewer)) else end
    offset = viewer - start
    t = (offset[0] * u[1] - offset[1] * u[0]) / across
    return start + min(max(t, 0.0), 1.0) * edge


def _nearest_on(viewer: np.ndarray, a: np.ndarray, b: np.ndarray,
                ) -> tuple[tuple[float, float], float]:
    """The point of segment a-b nearest ``viewer``, and its distance."""
    ab = b - a
    t = float(np.clip(np.dot(viewer - a, ab) / max(float(np.dot(ab, ab)), 1e-18), 0.0, 1.0))
    point = a + t * ab
    return (float(point[0]), float(point[1])), float(np.hypot(*(point - viewer)))


def _inside(x: float, y: float, corners: np.ndarray) -> bool:
    """Whether (x, y) is inside the polygon ``corners`` (even-odd rule)."""
    inside = False
    for (x0, y0), (x1, y1) in zip(corners, np.roll(corners, -1, axis=0), strict=True):
        if (y0 > y) != (y1 > y) and x < x0 + (y - y0) * (x1 - x0) / (y1 - y0):
            inside = not inside
    return inside
