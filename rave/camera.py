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
    """Something with a colour that a camera may see: a disc at (x, y)."""

    x: float
    y: float
    radius: float
    color: str | tuple[float, float, float]


def look(pose: tuple[float, float, float], targets: list[Target], occluders: np.ndarray,
         hue: float | None = None, tolerance: float = 15.0) -> list[Blob]:
    """The blobs seen from ``pose``: saturated targets in view and in range whose
    centre is not hidden behind ``occluders`` (segments), matching ``hue`` within
    ``tolerance`` degrees when given; nearest first."""
    x, y, theta = pose
    blobs = []
    for target in targets:
        h, s, i = hsi(target.color)
        if s < 0.25 or not 0.1 <= i <= 0.95:          # grey, black or washed out
            continue
        if hue is not None and hue_distance(h, hue) > tolerance:
            continue
        dx, dy = target.x - x, target.y - y
        distance = math.hypot(dx, dy)
        bearing = math.remainder(math.atan2(dy, dx) - theta, math.tau)
        if distance <= target.radius or distance > RANGE or abs(bearing) > FOV / 2:
            continue
        ray = np.array([[dx / distance, dy / distance]])
        hidden = raycast.cast(np.array([[x, y]]), ray, distance - target.radius, occluders)
        if np.isfinite(hidden.ranges[0]):
            continue
        size = 2.0 * math.asin(min(1.0, target.radius / distance))
        blobs.append(Blob(bearing, size, h, distance - target.radius))
    return sorted(blobs, key=lambda blob: blob.distance)
