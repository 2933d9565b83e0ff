"""Which segments and robots are near each robot: a uniform grid of cells, so that a
batch of scans tests each robot's rays only against what it can reach.

A point's candidates are the items overlapping its 3 x 3 block of cells (cells as
wide as the reach); they are then cut to those truly within reach and packed into
a padded index matrix (-1 where a row has fewer), ready for numpy.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np


class CellIndex:
    """Items (axis-aligned boxes ``xmin, ymin, xmax, ymax``) by grid cell."""

    def __init__(self, boxes: np.ndarray, cell: float) -> None:
        self.cell = cell
        self._cells: dict[tuple[int, int], list[int]] = defaultdict(list)
        lows = np.floor(boxes[:, 0:2] / cell).astype(int)
        highs = np.floor(boxes[:, 2:4] / cell).astype(int)
        for item, ((x0, y0), (x1, y1)) in enumerate(zip(lows, highs, strict=True)):
            for cx in range(x0, x1 + 1):
                for cy in range(y0, y1 + 1):
                    self._cells[(cx, cy)].append(item)
        self._blocks: dict[tuple[int, int], np.ndarray] = {}

    def _block(self, cx: int, cy: int) -> np.ndarray:
        found = self._blocks.get((cx, cy))
        if found is None:
            items = {i for dx in (-1, 0, 1) for dy in (-1, 0, 1)
                     for i in self._cells.get((cx + dx, cy + dy), ())}
            found = self._blocks[(cx, cy)] = np.array(sorted(items), dtype=np.intp)
        return found

    def near(self, points: np.ndarray) -> np.ndarray:
        """Candidate items of each point, shape (len(points), k), padded with -1."""
        cells = np.floor(points / self.cell).astype(int)
        unique, inverse = np.unique(cells, axis=0, return_inverse=True)
        blocks = [self._block(int(cx), int(cy)) for cx, cy in unique]
        width = max((len(b) for b in blocks), default=0)
        table = np.full((len(blocks), width), -1, dtype=np.intp)
        for row, block in enumerate(blocks):
            table[row, :len(block)] = block
        return table[inverse.ravel()]


def boxes_of_segments(segments: np.ndarray) -> np.ndarray:
    """The bounding box of each segment (x0, y0, x1, y1)."""
    xs, ys = segments[:, [0, 2]], segments[:, [1, 3]]
    return np.column_stack([xs.min(1), ys.min(1), xs.max(1), ys.max(1)])


def within(candidates: np.ndarray, distances: np.ndarray, reach: float) -> np.ndarray:
    """``candidates`` cut to those whose ``distances`` (same shape) are within
    ``reach``, packed to the left and padded with -1 to the widest row."""
    keep = (candidates >= 0) & (distances <= reach)
    width = int(keep.sum(axis=1).max(initial=0))
    order = np.argsort(~keep, axis=1, kind="stable")[:, :width]
    packed = np.take_along_axis(candidates, order, axis=1)
    packed[~np.take_along_axis(keep, order, axis=1)] = -1
    return packed


def segment_distances(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Distance from each point (R, 2) to each of its segments (R, K, 4)."""
    p = segments[..., 0:2]
    e = segments[..., 2:4] - p
    rel = points[:, None, :] - p
    length2 = np.maximum(np.einsum("rki,rki->rk", e, e), 1e-18)
    s = np.clip(np.einsum("rki,rki->rk", rel, e) / length2, 0.0, 1.0)
    closest = p + e * s[..., None]
    return np.hypot(*(points[:, None, :] - closest).transpose(2, 0, 1))
