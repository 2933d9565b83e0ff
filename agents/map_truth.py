"""A world's true map, and how good a learnt map is against it.

``truth`` rasterizes a RAVE world's obstacles onto a ``Grid``: a cell is occupied if
an obstacle's edge passes within half a cell's diagonal of its centre (through it, or
a wall along a cell border: on both sides) or it lies inside a closed obstacle, free
otherwise. Virtual obstacles count by default: a hardware robot's hybrid sonar
senses them like real ones, so a map learnt from it shows them. ``score`` compares a
map with it:

- *accuracy*: of the cells the map classifies (free or occupied), the share
  classified right. A cell the map calls occupied is right if the truth has an
  occupied cell within ``tolerance`` steps to a side cell of it (4-neighbours: with
  1, the cell or one of the four beside it, not a diagonal one): a wall's true cells
  are a rasterization, and a sonar arc placed half a cell off is not a wrong map.
- *coverage*: of the free cells a robot could sense (free cells connected to where
  it starts), the share the map calls free.
- *walls*: of the occupied cells that face that free space (the walls a robot could
  sense), the share the map calls occupied within ``tolerance`` cells. Accuracy
  alone does not ask for walls: a map that calls every cell free, knowing no wall,
  is right about 0.89 of the bundled worlds' cells.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from agents.grid import FREE, OCCUPIED, Grid, classify


def truth(world: Any, grid: Grid) -> np.ndarray:
    """The world's true map on ``grid``: a bool array, True where occupied (by real and
    virtual obstacles alike: a robot maps both). ``world`` is a ``rave.World`` or its
    ``describe()``."""
    obstacles = world.describe()["obstacles"] if hasattr(world, "describe") else world["obstacles"]
    xs, ys = grid.centers()
    occupied = np.zeros(grid.shape, dtype=bool)
    reach = grid.resolution / np.sqrt(2.0)         # a segment through a cell passes this near
    for obstacle in obstacles:                     # its centre
        points = np.asarray(obstacle["points"], dtype=np.float64)
        ends = np.vstack([points, points[:1]]) if obstacle["closed"] else points
        for (x0, y0), (x1, y1) in itertools.pairwise(ends):
            occupied |= _distance(xs, ys, x0, y0, x1, y1) <= reach
        if obstacle["closed"]:
            occupied |= _inside(xs, ys, points)
    return occupied


def reachable(occupied: np.ndarray, grid: Grid, start: tuple[float, float]) -> np.ndarray:
    """The free cells connected (4-neighbours) to the cell at ``start`` (x, y)."""
    labels, _ = ndimage.label(~occupied)
    row, col = grid.cell(start[0], start[1])
    if not grid.inside(row, col) or occupied[row, col]:
        raise ValueError(f"the start {start} is not in a free cell of the grid")
    return labels == labels[row, col]


@dataclass(frozen=True)
class MapScore:
    """How a learnt map compares with the truth (shares between 0 and 1)."""

    accuracy: float          # of the cells the map classifies, the share classified right
    coverage: float          # of the reachable free cells, the share the map calls free
    classified: int          # cells the map classifies (free or occupied)
    walls: float = 0.0       # of the wall cells facing them, the share it calls occupied


def score(probabilities: np.ndarray, occupied: np.ndarray, free_space: np.ndarray,
          tolerance: int = 1) -> MapScore:
    """Score a map (probabilities on the truth's grid) against ``truth`` (``occupied``)
    and the reachable ``free_space``; see the module's docstring."""
    if probabilities.shape != occupied.shape:
        raise ValueError(f"the map is {probabilities.shape} cells and the truth "
                         f"{occupied.shape}: score them on one grid")
    classes = classify(probabilities)
    near_wall = ndimage.binary_dilation(occupied, iterations=tolerance) if tolerance else occupied
    said_free, said_occupied = classes == FREE, classes == OCCUPIED
    right = np.count_nonzero(said_free & ~occupied) + np.count_nonzero(said_occupied & near_wall)
    classified = int(np.count_nonzero(said_free | said_occupied))
    reachable_free = int(np.count_nonzero(free_space))
    faces = occupied & ndimage.binary_dilation(free_space)
    found = ndimage.binary_dilation(said_occupied, iterations=tolerance) if tolerance \
        else said_occupied
    return MapScore(accuracy=float(right / classified) if classified else 0.0,
                    coverage=(float(np.count_nonzero(said_free & free_space) / reachable_free)
                              if reachable_free else 0.0),
                    classified=classified,
                    walls=(float(np.count_nonzero(faces & found) / np.count_nonzero(faces))
                           if faces.any() else 0.0))


def _distance(xs: np.ndarray, ys: np.ndarray, x0: float, y0: float, x1: float,
              y1: float) -> np.ndarray:
    """Distance of every point (xs, ys) from the segment (x0, y0)-(x1, y1)."""
    dx, dy = x1 - x0, y1 - y0
    length2 = dx * dx + dy * dy
    t = np.zeros_like(xs) if length2 == 0 else np.clip(
        ((xs - x0) * dx + (ys - y0) * dy) / length2, 0.0, 1.0)
    return np.hypot(xs - (x0 + t * dx), ys - (y0 + t * dy))


def _inside(xs: np.ndarray, ys: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Whether each point lies inside ``polygon`` (even-odd rule)."""
    inside = np.zeros(xs.shape, dtype=bool)
    for (x0, y0), (x1, y1) in zip(polygon, np.roll(polygon, -1, axis=0), strict=True):
        crosses = (y0 > ys) != (y1 > ys)
        with np.errstate(divide="ignore", invalid="ignore"):
            at = x0 + (ys - y0) * (x1 - x0) / (y1 - y0)
        inside ^= crosses & (xs < at)
    return inside
