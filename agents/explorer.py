"""``Explorer``: frontier-based exploration (Yamauchi 1997) on a probability map.

The robot goes where the known meets the unknown. A *frontier* cell is a free cell
next to a wide unknown area; connected frontier cells form regions, tiny ones
dropped. ``FrontierPlanner`` prices each region by the shortest path (Dijkstra on
the grid, over free space kept ``clearance`` clear of the robot's body, pushed to
the middle of passages) to a cell within ``approach`` of it, against its size, and
returns a path to the best. ``FrontierExplorer`` follows the path by pure pursuit
under sonar reflexes, replans on a schedule and as soon as its target is reached,
revealed or blocked, faces a target it reached that is still unresolved, sets aside
(blacklists) frontiers it cannot reach or resolve, for longer at each failure, and
stops, ``done``, when no reachable frontier is left.

Sonar maps are not laser maps: an echo's arc spreads over a 30 degree cone and
often draws a doorway seen from afar as a wall. So the planner falls back on a
tighter clearance, cells the robot has travelled stay traversable whatever the map
later says, and once the true frontiers are exhausted it looks at walls with a
wide unknown area behind them (``hidden_frontiers``) from close by.

Neither class knows PB3A; the ``Explorer`` module puts the explorer behind ports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from agents.grid import FREE, OCCUPIED, OCCUPIED_ABOVE, Grid, classify
from pb3a import Input, Module, Output
from rave.pioneer import RADIUS
from rave.sonar import RING

_CROSS = ndimage.generate_binary_structure(2, 1)       # 4-neighbours
_SQUARE = ndimage.generate_binary_structure(2, 2)      # 8-neighbours
# (row, column) steps to the neighbours a cell links to; with the links from the
# cells that step onto it, every cell reaches its 8 neighbours
_STEPS = ((0, 1), (1, 0), (1, 1), (1, -1))

# How far ahead of the robot's centre each transducer sits along its beam: a reading
# plus this, less the radius, is the gap between the robot's body and the echo.
_SONAR_REACH = RING[:, 0] * np.cos(RING[:, 2]) + RING[:, 1] * np.sin(RING[:, 2])
_FRONT = [2, 3, 4, 5]          # -30 .. +30 deg: cones cover -45 .. +45
_LEFT, _RIGHT = [0, 1], [6, 7]  # +90, +50 and -50, -90 deg
_REAR = [10, 11, 12, 13]       # -150 .. +150 deg


@dataclass(frozen=True)
class Plan:
    """Where to go next: a frontier ``target`` (world x, y; ``None`` when no frontier
    is reachable), ``hidden`` if it is one of ``hidden_frontiers``, and the ``path`` to
    a free cell near it from the robot's cell, (n, 3): each cell's world x, y and
    clearance (m from the nearest occupied cell), at ``cost``; ``regions`` counts the
    frontier regions not blacklisted, reachable or not."""

    target: np.ndarray | None
    path: np.ndarray
    cost: float
    regions: int
    hidden: bool = False


def frontiers(free: np.ndarray, unknown: np.ndarray, min_unknown: int = 100) -> np.ndarray:
    """Frontier cells (bool): free cells with a 4-neighbour in an unknown area of at
    least ``min_unknown`` cells. Smaller unknown pockets (cells a sensor happened to
    miss, the inside of a piece of furniture) are not worth a trip."""
    return free & ndimage.binary_dilation(_wide(unknown, min_unknown), _CROSS)


def hidden_frontiers(free: np.ndarray, occupied: np.ndarray, unknown: np.ndarray,
                     min_unknown: int = 300) -> np.ndarray:
    """Free cells facing a thin band of occupied cells (two cells at most) with an
    unknown area of at least ``min_unknown`` cells behind it. A sonar echo's arc
    spreads over the whole cone, so a sonar map often shows a doorway seen from afar
    as a wall; looked at from close by, the doorway may open."""
    band = occupied & ndimage.binary_dilation(_wide(unknown, min_unknown), _CROSS,
                                              iterations=2)
    return free & ndimage.binary_dilation(band, _CROSS)


def _wide(cells: np.ndarray, min_cells: int) -> np.ndarray:
    """The cells of ``cells`` in 4-connected areas of at least ``min_cells``."""
    labels, count = ndimage.label(cells, _CROSS)
    sizes = np.bincount(labels.ravel(), minlength=count + 1)
    sizes[0] = 0
    return sizes[labels] >= min_cells


class FrontierPlanner:
    """Chooses a frontier and a path to it on maps of ``grid``.

    A cell is traversable when it is free and its centre lies at least ``RADIUS +
    clearance`` from every occupied cell (or ``RADIUS + squeeze``, when nothing can be
    reached otherwise); unknown cells are not, except under the robot and on its
    trail. A step's cost is its length, times up to ``1 + proximity_cost`` within
    ``comfort`` m of an occupied cell. A region is reached at the cheapest cell within
    ``approach`` m of it (``shortfall_cost`` more per metre short of it). Its utility
    is ``gain_weight`` times its size (m of frontier) less that cost (m), and
    ``keep_bonus`` more for the region within ``keep_radius`` of the current target,
    so that the robot does not dither between two. Regions of fewer than
    ``min_region`` cells, and frontiers of unknown areas under ``min_unknown`` cells,
    are no targets; a blacklisted point removes the frontier cells within
    ``blacklist_radius`` of it.
    """

    def __init__(self, grid: Grid, *, clearance: float = 0.1, squeeze: float = 0.05,
                 comfort: float = 0.7, proximity_cost: float = 4.0, approach: float = 1.0,
                 shortfall_cost: float = 0.1,
                 min_region: int = 5, min_unknown: int = 100, gain_weight: float = 1.0,
                 keep_bonus: float = 1.0, keep_radius: float = 1.0,
                 blacklist_radius: float = 1.0, look_behind_walls: bool = True) -> None:
        self.grid = grid
        self.lethal = RADIUS + clearance
        self.squeezed = RADIUS + min(squeeze, clearance)
        self.comfort = max(comfort, self.lethal + grid.resolution)
        self.proximity_cost, self.min_region, self.min_unknown = (
            proximity_cost, min_region, min_unknown)
        self.gain_weight, self.keep_bonus, self.keep_radius = gain_weight, keep_bonus, keep_radius
        self.blacklist_radius = blacklist_radius
        self.look_behind_walls = look_behind_walls
        self.xs, self.ys = grid.centers()
        reach = max(1, round(approach / grid.resolution))
        dr, dc = np.mgrid[-reach:reach + 1, -reach:reach + 1]
        self._approach = dr * dr + dc * dc <= reach * reach    # the cells a goal may be in
        self._shortfall = shortfall_cost * np.hypot(dr, dc) * grid.resolution
        self._reach = reach
        rows, cols = grid.shape
        index = np.arange(rows * cols).reshape(rows, cols)
        sources, targets, lengths = [], [], []
        for dr_, dc_ in _STEPS:
            src = index[0:rows - dr_, max(0, -dc_):cols - max(0, dc_)]
            dst = index[dr_:rows, max(0, dc_):cols - max(0, -dc_)]
            sources.append(src.ravel())
            targets.append(dst.ravel())
            lengths.append(np.full(src.size, math.hypot(dr_, dc_) * grid.resolution))
        self._src, self._dst = np.concatenate(sources), np.concatenate(targets)
        self._length = np.concatenate(lengths)

    def plan(self, probabilities: np.ndarray, pose: Any,
             blacklist: np.ndarray | None = None, keep: Any = None,
             trail: np.ndarray | None = None) -> Plan:
        """The best frontier for a robot at ``pose`` (x, y, heading) and the path to
        it, trying the true frontiers before hidden ones, each with ``clearance``
        before ``squeeze`` (the robot's reflexes guard a tight passage). Frontier
        cells near a ``blacklist`` point (k, 2) are left out; the ``trail`` (bool, the
        map's shape), where the robot has been, is traversable whatever the map
        says, as sonar maps smear echoes across the doorways it came through."""
        if probabilities.shape != self.grid.shape:
            raise ValueError(f"the map is {probabilities.shape} cells, the planner's grid "
                             f"{self.grid.shape}: plan on the map's grid")
        grid = self.grid
        classes = classify(probabilities)
        occupied, free = classes == OCCUPIED, classes == FREE
        # the robot stands on free ground, whatever the map has learnt of it yet
        underfoot = (np.hypot(self.xs - pose[0], self.ys - pose[1])
                     <= RADIUS + grid.resolution) & ~occupied
        underfoot[self._cell(pose)] = True
        if trail is not None:
            underfoot |= trail
        free |= underfoot
        unknown = ~free & ~occupied
        allowed = np.ones(grid.shape, dtype=bool)
        if blacklist is not None:
            for bx, by in np.asarray(blacklist, dtype=np.float64).reshape(-1, 2):
                allowed &= np.hypot(self.xs - bx, self.ys - by) > self.blacklist_radius
        clear = (ndimage.distance_transform_edt(~occupied) * grid.resolution
                 if occupied.any() else np.full(grid.shape, np.inf))
        cost = 1.0 + self.proximity_cost * np.clip(
            (self.comfort - clear) / (self.comfort - self.lethal), 0.0, 1.0)
        tiers = [(False, lambda: frontiers(free, unknown, self.min_unknown))]
        if self.look_behind_walls:          # only when no true frontier can be reached
            tiers.append((True, lambda: hidden_frontiers(free, occupied, unknown)))
        regions = 0
        for hidden, cells in tiers:
            labels, count = ndimage.label(cells() & allowed, _SQUARE)
            sizes = np.bincount(labels.ravel(), minlength=count + 1)[1:]
            if not hidden:
                regions = int(np.count_nonzero(sizes >= self.min_region))
            if not (sizes >= self.min_region).any():
                continue
            for lethal in (self.lethal, self.squeezed):
                traversable = (free & (clear >= lethal)) | underfoot
                best = self._best(traversable, cost, clear, pose, labels, sizes, keep)
                if best is not None:
                    target, path, cost = best
                    return Plan(target, path, cost, regions, hidden)
        return Plan(None, np.zeros((0, 3)), math.inf, regions)

    def _cell(self, pose: Any) -> tuple[int, int]:
        """(row, column) of the cell the robot is in (the nearest, off the grid)."""
        rows, cols = self.grid.shape
        row, col = self.grid.cell(pose[0], pose[1])
        return int(np.clip(row, 0, rows - 1)), int(np.clip(col, 0, cols - 1))

    def _best(self, traversable: np.ndarray, cost: np.ndarray, clear: np.ndarray,
              pose: Any, labels: np.ndarray, sizes: np.ndarray, keep: Any,
              ) -> tuple[np.ndarray, np.ndarray, float] | None:
        """The best region of ``labels`` (of ``min_region`` cells at least) reachable
        over ``traversable`` cells, each step priced by the ``cost`` of its two cells:
        the target, the path to it and its cost; or None."""
        grid, (rows, cols) = self.grid, self.grid.shape
        start_row, start_col = self._cell(pose)
        start = start_row * cols + start_col
        flat_ok, flat_cost = traversable.ravel(), cost.ravel()
        linked = flat_ok[self._src] & flat_ok[self._dst]
        src, dst = self._src[linked], self._dst[linked]
        weights = self._length[linked] * 0.5 * (flat_cost[src] + flat_cost[dst])
        graph = sparse.csr_matrix((weights, (src, dst)), shape=(rows * cols, rows * cols))
        distance, previous = csgraph.dijkstra(graph, directed=False, indices=start,
                                              return_predecessors=True)
        distance = distance.reshape(rows, cols)
        # a frontier cell costs the cheapest path to a traversable cell near it, plus a
        # little for each metre that cell falls short of it
        approach = ndimage.grey_erosion(distance, footprint=self._approach,
                                        structure=-self._shortfall, mode="constant",
                                        cval=np.inf)
        ids = np.arange(1, len(sizes) + 1)
        costs = np.asarray(ndimage.minimum(approach, labels, ids))
        candidates = (sizes >= self.min_region) & np.isfinite(costs)
        if not candidates.any():
            return None
        utility = self.gain_weight * sizes * grid.resolution - costs
        if keep is not None and len(keep):
            near_keep = np.hypot(self.xs - keep[0], self.ys - keep[1])
            kept = np.asarray(ndimage.minimum(near_keep, labels, ids)) <= self.keep_radius
            utility = utility + self.keep_bonus * kept
        best = int(np.flatnonzero(candidates)[np.argmax(utility[candidates])])
        row, col = ndimage.minimum_position(approach, labels, best + 1)
        goal = self._goal_near(distance, row, col)
        target = np.array(grid.center(row, col), dtype=np.float64)
        return target, self._path(previous, start, goal, clear), float(costs[best])

    def _goal_near(self, distance: np.ndarray, row: int, col: int) -> int:
        """The flat index of the cell in the approach disc of (row, col) that the
        approach cost of (row, col) came from."""
        reach, cols = self._reach, distance.shape[1]
        r0, c0 = max(0, row - reach), max(0, col - reach)
        window = distance[r0:row + reach + 1, c0:col + reach + 1]
        disc = (slice(r0 - (row - reach), r0 - (row - reach) + window.shape[0]),
                slice(c0 - (col - reach), c0 - (col - reach) + window.shape[1]))
        cost = np.where(self._approach[disc], window + self._shortfall[disc], np.inf)
        wr, wc = np.unravel_index(np.argmin(cost), window.shape)
        return int((r0 + wr) * cols + c0 + wc)

    def _path(self, previous: np.ndarray, start: int, goal: int, clear: np.ndarray,
              ) -> np.ndarray:
        """World x, y and clearance of the cells from ``start`` to ``goal``."""
        cells = [goal]
        while cells[-1] != start:
            cells.append(int(previous[cells[-1]]))
        rows, cols = np.divmod(np.array(cells[::-1]), clear.shape[1])
        return np.column_stack([*self.grid.center(rows, cols), clear[rows, cols]])


class FrontierExplorer:
    """Turns maps, poses and sonar readings into velocity commands that explore.

    It drives at up to ``max_speed`` m/s and ``max_turn`` rad/s toward a point up to
    ``lookahead`` m along its path, replans every ``replan_every`` s, gives a target
    up when it has not moved ``stuck_distance`` m in ``patience`` s, faces a reached
    but unresolved target for ``look_time`` s, and sets a frontier aside for
    ``forget_after`` s, twice as long at each further failure there. Other keywords
    go to its ``FrontierPlanner``.

    Its memory (the attributes named in ``MEMORY``) is plain data: copy it into a
    new explorer of the same grid and settings and it carries on where this one was.
    Time is the sum of the ``dt`` given to ``step``, so it runs in simulated time.
    """

    MEMORY = ("target", "path", "blacklist", "done", "plans", "replans", "stuck", "clock",
              "behind_wall", "planned_at", "anchor", "looking_until", "looked_at", "trail")

    def __init__(self, grid: Grid, *, max_speed: float = 0.4, max_turn: float = 1.0,
                 clearance: float = 0.1, lookahead: float = 0.5, replan_every: float = 2.0,
                 patience: float = 8.0, forget_after: float = 60.0, look_time: float = 2.0,
                 **planning: Any) -> None:
        self.planner = FrontierPlanner(grid, clearance=clearance, **planning)
        self.max_speed, self.max_turn, self.lookahead = max_speed, max_turn, lookahead
        self.replan_every, self.patience, self.forget_after = replan_every, patience, forget_after
        self.look_time = look_time
        self.min_lookahead = 0.2       # m
        self.arrive_within = 0.25      # m from the path's end
        self.turn_in_place = 0.8       # rad of heading error beyond which it stops to turn
        self.stuck_distance = 0.3      # m it must move within ``patience`` s
        self.stop_gap, self.slow_gap, self.side_gap = 0.1, 0.5, 0.15   # m from the body
        self.backoff_speed = 0.1       # m/s
        self.target: list[float] = []  # (x, y) of the frontier it goes to
        self.behind_wall = False       # the target is a hidden frontier (``Plan.hidden``)
        self.path = np.zeros((0, 3))   # the rest of the path to it (as ``Plan.path``)
        self.blacklist: list[list[float]] = []   # (x, y, until, failures) per bad frontier
        self.done = False
        self.plans = self.replans = self.stuck = 0   # as ``Explorer``'s
        self.clock = 0.0
        self.planned_at = -math.inf
        self.anchor = [math.nan, math.nan, 0.0]  # where it last moved from, and when
        self.looking_until = -math.inf  # clock until which it faces its target
        self.looked_at: list[float] = []     # the target it last did
        self.trail = np.zeros(grid.shape, dtype=bool)   # cells its centre has been near

    def memory(self) -> dict[str, Any]:
        """What it needs to carry on elsewhere."""
        return {name: getattr(self, name) for name in self.MEMORY}

    def restore(self, memory: dict[str, Any]) -> None:
        """Carry on from ``memory`` (as ``memory()`` gave it)."""
        for name in self.MEMORY:
            setattr(self, name, memory[name])
        self.path = np.asarray(self.path, dtype=np.float64).reshape(-1, 3)

    def step(self, probabilities: np.ndarray, pose: Any, sonar: np.ndarray | None,
             dt: float) -> tuple[float, float]:
        """The command (v m/s, w rad/s) for the next ``dt`` seconds."""
        self.clock += dt
        x, y = float(pose[0]), float(pose[1])
        self._leave_trail(x, y)
        standing = self._standing(x, y)
        if self.clock < self.looking_until:
            return self._face(pose)
        if self.target and standing and self.clock - self.anchor[2] > self.patience:
            self.stuck += 1
            self._set_aside(self.target)
            self.anchor[2] = self.clock
            self._plan(probabilities, pose)
        elif self._plan_due(probabilities, x, y):
            self._plan(probabilities, pose)
        if self.done or not self.target:
            return (0.0, 0.0)
        if self.clock < self.looking_until:
            return self._face(pose)
        v, w = self._pursue(pose)
        return self._reflexes(v, w, sonar) if sonar is not None else (v, w)

    # -- deciding when to plan ----------------------------------------------------------
    def _standing(self, x: float, y: float) -> bool:
        """Whether the robot is still within ``stuck_distance`` of its anchor; the
        anchor moves to it when it is not."""
        if not math.hypot(x - self.anchor[0], y - self.anchor[1]) < self.stuck_distance:
            self.anchor = [x, y, self.clock]
            return False
        return True

    def _plan_due(self, probabilities: np.ndarray, x: float, y: float) -> bool:
        """Whether to plan now: on schedule, and as soon as the target is reached,
        revealed or its path blocked."""
        due = self.clock - self.planned_at >= self.replan_every
        if not self.target:       # at once, unless it is done: then on schedule
            return due or not self.done
        if due:
            return True
        end_x, end_y, _ = self.path[-1]
        if math.hypot(end_x - x, end_y - y) < self.arrive_within:
            return True
        if not (self.behind_wall or self._still_frontier(probabilities)):
            return True
        return self._path_blocked(probabilities)

    def _still_frontier(self, probabilities: np.ndarray) -> bool:
        """Whether a frontier cell is still within a cell of the target (looked for
        in a window around it, not over the whole map)."""
        row, col = self.planner.grid.cell(self.target[0], self.target[1])
        r0, c0 = max(0, row - 2), max(0, col - 2)
        classes = classify(probabilities[r0:row + 3, c0:col + 3])
        unknown = (classes != FREE) & (classes != OCCUPIED)
        edge = (classes == FREE) & ndimage.binary_dilation(unknown, _CROSS)
        r, c = row - r0, col - c0
        return bool(edge[max(0, r - 1):r + 2, max(0, c - 1):c + 2].any())

    def _path_blocked(self, probabilities: np.ndarray) -> bool:
        """Whether a cell of the path ahead, off the trail, has been mapped occupied
        since it was planned."""
        rows, cols = self.planner.grid.cell(self.path[:, 0], self.path[:, 1])
        return bool(((probabilities[rows, cols] > OCCUPIED_ABOVE) & ~self.trail[rows, cols])
                    .any())

    def _leave_trail(self, x: float, y: float) -> None:
        """Mark the robot's cell and its 4-neighbours as travelled."""
        grid = self.planner.grid
        row, col = grid.cell(x, y)
        rows, cols = row + np.array([0, -1, 1, 0, 0]), col + np.array([0, 0, 0, -1, 1])
        inside = grid.inside(rows, cols)
        self.trail[rows[inside], cols[inside]] = True

    def _plan(self, probabilities: np.ndarray, pose: Any) -> None:
        """Choose the target and path (or find it is done) without the frontiers set
        aside."""
        pursuing = bool(self.target)
        active = [entry[:2] for entry in self.blacklist if entry[2] > self.clock]
        plan = self.planner.plan(probabilities, pose, np.array(active).reshape(-1, 2),
                                 keep=self.target, trail=self.trail)
        self.plans += 1
        self.replans += pursuing
        self.planned_at = self.clock
        self.done = plan.target is None
        self.target, self.path = [], np.zeros((0, 3))
        if plan.target is None:
            return
        x, y = float(pose[0]), float(pose[1])
        end_x, end_y, _ = plan.path[-1]
        if math.hypot(end_x - x, end_y - y) < self.arrive_within:
            # It stands where it would go and the frontier is still there. A sonar map
            # resolves it best looked at squarely: face it for a while; if it is still
            # there after that, it cannot be resolved from here, and the next step
            # plans without it.
            if self.looked_at and math.hypot(
                    self.looked_at[0] - plan.target[0],
                    self.looked_at[1] - plan.target[1]) <= self.planner.blacklist_radius:
                self._set_aside(plan.target.tolist())
                self.planned_at = -math.inf
                return
            self.looked_at = plan.target.tolist()
            self.looking_until = self.clock + self.look_time
            self.anchor = [x, y, self.clock]
        elif not pursuing:
            self.anchor = [x, y, self.clock]
        self.target, self.path, self.behind_wall = plan.target.tolist(), plan.path, plan.hidden

    def _set_aside(self, point: list[float]) -> None:
        """Blacklist the frontier at ``point``: for ``forget_after`` s, twice as long
        at each further failure there."""
        for entry in self.blacklist:
            if math.hypot(entry[0] - point[0], entry[1] - point[1]) <= \
                    self.planner.blacklist_radius:
                entry[3] += 1
                entry[2] = self.clock + self.forget_after * 2 ** (entry[3] - 1)
                return
        self.blacklist.append([float(point[0]), float(point[1]),
                               self.clock + self.forget_after, 1.0])

    # -- driving ------------------------------------------------------------------------
    def _face(self, pose: Any) -> tuple[float, float]:
        """Turn on the spot toward the target."""
        x, y, theta = pose
        alpha = math.remainder(math.atan2(self.target[1] - y, self.target[0] - x) - theta,
                               math.tau)
        return 0.0, float(np.clip(2.0 * alpha, -self.max_turn, self.max_turn))

    def _pursue(self, pose: Any) -> tuple[float, float]:
        """Pure pursuit of a point along the path: ``lookahead`` m ahead in the open,
        nearer where the path runs close to walls (a far point cuts corners), slower
        there too; turns on the spot when that point is far off its heading."""
        x, y, theta = pose
        offsets = np.hypot(self.path[:, 0] - x, self.path[:, 1] - y)
        nearest = int(np.argmin(offsets))
        self.path, offsets = self.path[nearest:], offsets[nearest:]
        near = self.path[offsets <= self.lookahead, 2].min(initial=self.path[0, 2])
        lookahead = float(np.clip(near - RADIUS, self.min_lookahead, self.lookahead))
        beyond = np.flatnonzero(offsets >= lookahead)
        px, py = self.path[beyond[0], :2] if len(beyond) else self.path[-1, :2]
        distance = math.hypot(px - x, py - y)
        alpha = math.remainder(math.atan2(py - y, px - x) - theta, math.tau)
        if abs(alpha) > self.turn_in_place:
            return 0.0, float(np.clip(2.0 * alpha, -self.max_turn, self.max_turn))
        planner = self.planner
        room = np.clip((near - planner.lethal) / (planner.comfort - planner.lethal), 0.0, 1.0)
        v = self.max_speed * math.cos(alpha) * (0.5 + 0.5 * room)
        curvature = 2.0 * math.sin(alpha) / max(distance, 1e-3)
        if abs(v * curvature) > self.max_turn:          # keep the arc, slow down
            v = self.max_turn / abs(curvature)
        return v, v * curvature

    def _reflexes(self, v: float, w: float, sonar: np.ndarray) -> tuple[float, float]:
        """Sonar reflexes over the pursuit: slow down as the way ahead narrows, back
        off turning to the open side when too close, veer from a side too near."""
        gaps = np.asarray(sonar, dtype=np.float64) + _SONAR_REACH - RADIUS
        front, left, right = gaps[_FRONT].min(), gaps[_LEFT].min(), gaps[_RIGHT].min()
        if front < self.stop_gap:
            v = -self.backoff_speed if gaps[_REAR].min() > 2 * self.stop_gap else 0.0
            w = math.copysign(0.5 * self.max_turn, gaps[[0, 1, 2]].min() - gaps[[5, 6, 7]].min())
        elif v > 0:
            v *= min(1.0, (front - self.stop_gap) / (self.slow_gap - self.stop_gap))
        w += 3.0 * (max(0.0, self.side_gap - right) - max(0.0, self.side_gap - left))
        return v, float(np.clip(w, -self.max_turn, self.max_turn))


class Explorer(Module):
    """Explores the unknown of the ``map`` it is fed, writing velocity ``command``s.

    Feed it the mapper's probability grid (``agents.grid``), the robot's pose from
    the localization system and its sonar ring (optional: without it, no reflexes).
    When no reachable frontier is left it writes (0, 0) and is ``done``; it still
    looks every ``replan_every`` s, so a map that grows, or a frontier set aside and
    forgotten, sets it going again. Its state is all it needs to carry on toward the
    same target after a move.
    """

    map = Input(np.ndarray, dtype="float32")                    # occupancy probabilities
    pose = Input(np.ndarray, shape=(3,), dtype="float64")       # x, y (m), heading (rad)
    sonar = Input(np.ndarray, shape=(16,), dtype="float64")     # m, Pioneer ring order
    command = Output(np.ndarray, shape=(2,), dtype="float64")   # v (m/s), w (rad/s)
    period = 0.1

    resolution = 0.1               # m per cell, the mapper's
    size = [10.0, 8.0]             # m, the world's width and height
    max_speed = 0.4                # m/s
    clearance = 0.1                # m kept between the robot's body and mapped walls
    replan_every = 2.0             # s
    forget_after = 60.0            # s a frontier it could not reach is first set aside
    # what it has done and is doing (``FrontierExplorer.MEMORY``)
    target: list[float] = []       # (x, y) of the frontier it goes to; [] when none
    behind_wall = False            # the target is a hidden frontier (``Plan.hidden``)
    path = np.zeros((0, 3))        # x, y, clearance of the cells still to follow to it
    blacklist: list[list[float]] = []   # (x, y, until, failures) per frontier set aside
    done = False                   # no reachable frontier is left
    plans = 0                      # plans made
    replans = 0                    # of them, made while it still had a target
    stuck = 0                      # times it made no headway and gave up a target
    clock = 0.0                    # s of exploring
    planned_at = -math.inf         # clock of the last plan
    anchor = [math.nan, math.nan, 0.0]   # where it last moved from, and when
    looking_until = -math.inf      # clock until which it faces its target
    looked_at: list[float] = []    # the target it last did
    trail = np.zeros((0, 0), dtype=bool)   # cells it has been on (sized in setup)

    def setup(self) -> None:
        grid = Grid.of(self.size, self.resolution)
        if self.trail.shape != grid.shape:       # a fresh explorer
            self.trail = np.zeros(grid.shape, dtype=bool)
        self._explorer = FrontierExplorer(
            grid, max_speed=self.max_speed, clearance=self.clearance,
            replan_every=self.replan_every, forget_after=self.forget_after)
        self._explorer.restore({name: getattr(self, name) for name in FrontierExplorer.MEMORY})

    def step(self) -> None:
        if not (self.map.has_value and self.pose.has_value):
            self.command.write(np.zeros(2))      # nothing to go by yet: stand
            return
        sonar = self.sonar.read() if self.sonar.has_value else None
        v, w = self._explorer.step(self.map.read(), self.pose.read(), sonar, self.period)
        for name, value in self._explorer.memory().items():
            setattr(self, name, value)
        self.command.write(np.array([v, w], dtype=np.float64))
