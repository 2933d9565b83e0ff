"""Which obstacles and robots may be near each robot: cell lists on a uniform grid,
so that a batch of scans tests each robot only against what it can reach.

Every item (an axis-aligned box ``xmin, ymin, xmax, ymax``) is listed under each
cell that its box, grown by the reach, overlaps; a point's candidates are then
just its own cell's list, with no search. The lists live in one sorted array
(compressed sparse rows), built and queried with whole-array numpy operations, and
queries return flat (point, item) pairs rather than padded matrices: a crowd's
robots see very different numbers of things, and padding every row to the
busiest one would cost more than the work itself.
"""

from __future__ import annotations

import numpy as np


class CellLists:
    """Items by grid cell: each cell lists every item within ``reach`` of it."""

    def __init__(self, boxes: np.ndarray, reach: float, cell: float) -> None:
        self.cell = cell
        count = len(boxes)
        grown = np.column_stack([boxes[:, 0:2] - reach, boxes[:, 2:4] + reach])
        self.origin = grown[:, 0:2].min(axis=0) if count else np.zeros(2)
        low = self._cell_of(grown[:, 0:2])
        high = self._cell_of(grown[:, 2:4])
        self.shape = high.max(axis=0) + 1 if count else np.ones(2, dtype=np.int64)
        span = high - low + 1                                   # cells across, per item
        per_item = span[:, 0] * span[:, 1]
        item, offset = expand(per_item)
        cx = low[item, 0] + offset % span[item, 0]
        cy = low[item, 1] + offset // span[item, 0]
        keys = cx * self.shape[1] + cy
        order = np.argsort(keys)
        self._keys = keys[order]
        self._items = item[order]

    def _cell_of(self, points: np.ndarray) -> np.ndarray:
        return np.floor((points - self.origin) / self.cell).astype(np.int64)

    def pairs(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every (point, item) pair in which the item may be within reach of the point
        (a superset: callers cut by exact distance): two index arrays."""
        cells = self._cell_of(points)
        inside = ((cells >= 0) & (cells < self.shape)).all(axis=1)
        keys = cells[:, 0] * self.shape[1] + cells[:, 1]
        first = np.searchsorted(self._keys, keys, side="left")
        last = np.where(inside, np.searchsorted(self._keys, keys, side="right"), first)
        point, offset = expand(last - first)
        return point, self._items[first[point] + offset]


class NeighbourLists:
    """Which segments and discs each of a fleet's robots may reach, kept from scan to
    scan (Verlet lists): found for ``reach + skin``, the pairs hold every item within
    ``reach`` until some robot or disc has moved half the skin since, and are only
    then found again. Robot ``i`` is disc ``i`` and does not see itself."""

    def __init__(self, reach: float, skin: float = 0.5, segment_cell: float = 1.0) -> None:
        self.reach, self.skin, self.segment_cell = reach, skin, segment_cell
        self._segments: tuple[np.ndarray, CellLists] | None = None
        self._centers = self._discs = np.zeros((0, 2))
        self._pairs: tuple[tuple[np.ndarray, np.ndarray],
                           tuple[np.ndarray, np.ndarray]] | None = None

    def pairs(self, centers: np.ndarray, segments: np.ndarray, discs: np.ndarray,
              ) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """(robot, segment) and (robot, disc) index pairs for robots at ``centers``."""
        if self._pairs is None or self._stale(centers, segments, discs):
            self._pairs = self._build(centers, segments, discs)
        return self._pairs

    def forget(self) -> None:
        """Robots came or went (rows now stand for others): find the pairs anew."""
        self._pairs = None

    def _stale(self, centers: np.ndarray, segments: np.ndarray, discs: np.ndarray) -> bool:
        if (self._segments is None or self._segments[0] is not segments
                or centers.shape != self._centers.shape or len(discs) != len(self._discs)):
            return True
        moved = max(_farthest(centers - self._centers), _farthest(discs[:, 0:2] - self._discs))
        return moved > self.skin / 2

    def _build(self, centers: np.ndarray, segments: np.ndarray, discs: np.ndarray,
               ) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
        reach = self.reach + self.skin
        if self._segments is None or self._segments[0] is not segments:   # they stand still
            self._segments = (segments, CellLists(boxes_of_segments(segments), reach,
                                                  self.segment_cell))
        robot, disc = CellLists(boxes_of_discs(discs), reach, reach / 2).pairs(centers)
        other = robot != disc
        self._centers, self._discs = centers.copy(), discs[:, 0:2].copy()
        return self._segments[1].pairs(centers), (robot[other], disc[other])


def _farthest(moves: np.ndarray) -> float:
    return float((moves * moves).sum(axis=1).max(initial=0.0)) ** 0.5


def expand(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For rows with ``counts`` entries each: the row and the index within its row of
    every entry, in order (``counts`` [2, 0, 3] gives rows [0, 0, 2, 2, 2] and
    offsets [0, 1, 0, 1, 2])."""
    row = np.repeat(np.arange(len(counts)), counts)
    starts = np.cumsum(counts) - counts
    return row, np.arange(len(row)) - starts[row]


def boxes_of_segments(segments: np.ndarray) -> np.ndarray:
    """The bounding box of each segment (x0, y0, x1, y1)."""
    xs, ys = segments[:, [0, 2]], segments[:, [1, 3]]
    return np.column_stack([xs.min(1), ys.min(1), xs.max(1), ys.max(1)])


def boxes_of_discs(discs: np.ndarray) -> np.ndarray:
    """The bounding box of each disc (x, y, radius)."""
    radius = discs[:, 2:3]
    return np.hstack([discs[:, 0:2] - radius, discs[:, 0:2] + radius])
