"""``Grid``: the geometry every map in ``agents`` shares, and what a map's cells mean.

A map is a 2-D numpy array of occupancy probabilities, row ``i`` and column ``j``
covering ``x`` in ``[j, j + 1) * resolution`` and ``y`` in ``[i, i + 1) *
resolution`` of the world (origin at the world's corner, ``y`` up, so row 0 is the
south edge). ``UNKNOWN`` (0.5) is a cell nothing has been learnt about; below
``FREE_BELOW`` it counts as free, above ``OCCUPIED_ABOVE`` as occupied. The mapper
writes such arrays, the explorer plans on them, and ``agents.map_truth`` scores them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

UNKNOWN = 0.5
MOST_CELLS = 10_000_000   # a map larger than this is a mistaken size or resolution
FREE_BELOW = 0.35
OCCUPIED_ABOVE = 0.65
# what ``classify`` says of a cell
OCCUPIED, FREE, UNSEEN = 1, 0, -1


@dataclass(frozen=True)
class Grid:
    """A ``width`` x ``height`` m area in square cells of ``resolution`` m."""

    width: float
    height: float
    resolution: float = 0.1

    def __post_init__(self) -> None:
        sides = (self.width, self.height, self.resolution)
        if not all(math.isfinite(side) and side > 0 for side in sides):
            raise ValueError(f"a grid needs a positive size and resolution (finite), not "
                             f"{self.width} x {self.height} m at {self.resolution} m")
        rows, columns = self.shape
        if rows * columns > MOST_CELLS:      # (every reading, every move pickles it)
            raise ValueError(f"a grid of {self.width} x {self.height} m at "
                             f"{self.resolution} m has {rows * columns:,} cells, more than "
                             f"{MOST_CELLS:,}: make the resolution coarser")

    @classmethod
    def of(cls, size: Any, resolution: float = 0.1) -> Grid:
        """The grid over a world of ``size`` (width, height), e.g. ``world.size``."""
        try:       # (a number alone said only "'float' object is not subscriptable")
            width, height = (float(side) for side in size)
        except (TypeError, ValueError):
            raise ValueError(f"a grid's size is [width, height] in metres, not "
                             f"{size!r}") from None
        return cls(width, height, float(resolution))

    @classmethod
    def problems(cls, size: Any, resolution: Any) -> list[str]:
        """Why no grid is made of ``size`` and ``resolution`` (a module's ``size`` and
        ``resolution``, in its ``state_problems``): none if one is."""
        try:
            cls.of(size, resolution)
        except (TypeError, ValueError) as exc:
            return [f"size and resolution make no grid: {exc}"]
        return []

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns)."""
        return (math.ceil(self.height / self.resolution - 1e-9),
                math.ceil(self.width / self.resolution - 1e-9))

    def blank(self) -> np.ndarray:
        """A map of this grid that knows nothing yet (float32, every cell ``UNKNOWN``)."""
        return np.full(self.shape, UNKNOWN, dtype=np.float32)

    def cell(self, x: Any, y: Any) -> tuple[Any, Any]:
        """(row, column) of the cell holding world point (x, y); works on arrays. Points
        outside give indices outside the grid: check them with ``inside``."""
        # (1e-9 of a cell: 0.3 / 0.1 is 2.9999999999999996, and a point on a border
        # belongs to the cell above it, as the module's docstring has it)
        return (np.floor(np.asarray(y) / self.resolution + 1e-9).astype(np.int64),
                np.floor(np.asarray(x) / self.resolution + 1e-9).astype(np.int64))

    def center(self, row: Any, col: Any) -> tuple[Any, Any]:
        """World (x, y) of a cell's centre; works on arrays."""
        return ((np.asarray(col) + 0.5) * self.resolution,
                (np.asarray(row) + 0.5) * self.resolution)

    def inside(self, row: Any, col: Any) -> Any:
        """Whether (row, column) is a cell of the grid; works on arrays."""
        rows, cols = self.shape
        return (np.asarray(row) >= 0) & (np.asarray(row) < rows) & \
            (np.asarray(col) >= 0) & (np.asarray(col) < cols)

    def centers(self) -> tuple[np.ndarray, np.ndarray]:
        """World x and y of every cell's centre, each an array of the grid's shape."""
        rows, cols = self.shape
        return self.center(*np.mgrid[0:rows, 0:cols])


def classify(probabilities: np.ndarray) -> np.ndarray:
    """Each cell as ``OCCUPIED``, ``FREE`` or ``UNSEEN`` (int8), by the thresholds above."""
    classes = np.full(probabilities.shape, UNSEEN, dtype=np.int8)
    classes[probabilities < FREE_BELOW] = FREE
    classes[probabilities > OCCUPIED_ABOVE] = OCCUPIED
    return classes
