"""``Explorer``: frontier-based exploration (Yamauchi 1997) on a probability map.

The robot goes where the known meets the unknown. A *frontier* cell is a free cell
next to a wide unknown area; connected frontier cells form regions, tiny ones
dropped. ``FrontierPlanner`` prices each region by the shortest path (Dijkstra on
the grid, over free space kept ``clearance`` clear of the robot's body, pushed to
the middle of passages) to a cell in sight of it within ``approach``, against its
size, and returns a path to the best. ``FrontierExplorer`` follows the path by pure
pursuit under sonar reflexes, replans on a schedule and as soon as its target is
reached, revealed or blocked, faces a target it reached that is still unresolved,
sets aside (blacklists) frontiers it cannot reach or resolve, for longer at each
failure, and stops, ``done``, when no reachable frontier is left.

Sonar maps are not laser maps: an echo's arc spreads over a 30 degree cone and
often draws a doorway seen from afar as a wall, a beam meeting a wall at a grazing
angle is reflected away and hears nothing, and a beam that hears nothing clears
free space only slowly. So the planner falls back on a tighter clearance, cells the
robot has travelled stay traversable whatever the map later says, echoes the robot
heard close by are kept clear of whatever the map says, and once the true frontiers
are exhausted it looks from close by at walls with space it cannot get to behind
them (``hidden_frontiers``): first those with free space it saw through them, then
those with a wide unknown area. A frontier it stands at is set aside only when
looking at it resolves nothing. Its reflexes brake for what its ring hears on the
arc it drives, in time for a robot that reacts late and brakes gently.

A robot's pose may jump (the explorer handed, with its memory, to another robot):
it then plans afresh from there at once, and holds nothing of the jump against a
frontier. The map may hold the new robot's body as the first robot's sonar drew it,
an arc wider than the body, so near where it was handed over the map's walls give way
to what the new robot's own sonar hears; and the robot it drove before stands at the
end of its trail, so the trail there is dropped and that robot's body kept clear of.

Neither class knows PB3A; the ``Explorer`` module puts the explorer behind ports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from agents.grid import (
    FREE,
    FREE_BELOW,
    OCCUPIED,
    OCCUPIED_ABOVE,
    UNKNOWN,
    Grid,
    classify,
)
from agents.limits import SPAN, Limit, finite, out_of_limits, refuse_own_state
from pb3a import Input, Module, Output
from pb3a.model.module import reflective
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
                     min_unknown: int = 300, band: int = 2) -> np.ndarray:
    """Free cells facing a thin band of occupied cells (``band`` cells at most) with
    an ``unknown`` area of at least ``min_unknown`` cells behind it (the planner
    passes, too, free space the robot cannot get to). A sonar echo's arc spreads over
    the whole cone, so a sonar map often shows a doorway seen from afar as a wall;
    looked at from close by, the doorway may open."""
    band = occupied & ndimage.binary_dilation(_wide(unknown, min_unknown), _CROSS,
                                              iterations=band)
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
    ``approach`` m of it in sight of it (``shortfall_cost`` more per metre short of
    it: as much as a metre driven, so the robot stops short only where driving on is
    dear or impossible). Its utility
    is ``gain_weight`` times its size (m of frontier) less that cost (m), and
    ``keep_bonus`` more for the region within ``keep_radius`` of the current target,
    so that the robot does not dither between two. Regions of fewer than
    ``min_region`` cells, and frontiers of unknown areas under ``min_unknown`` cells,
    are no targets; a blacklisted point removes the frontier cells within
    ``blacklist_radius`` of it.
    """

    def __init__(self, grid: Grid, *, clearance: float = 0.1, squeeze: float = 0.05,
                 comfort: float = 0.7, proximity_cost: float = 4.0, approach: float = 1.0,
                 shortfall_cost: float = 1.0,
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
        self.body_smear = 0.75         # m round ``plan``'s ``handed_at`` (within the
                                       # echoes a robot's ring plans round)
        self.min_beyond = 30           # cells of free space out of reach worth a look
        self.closer_cost = 20.0        # shortfall_cost times this with ``plan``'s ``closer``
        self.look_behind_walls = look_behind_walls
        self.xs, self.ys = grid.centers()
        self.approach, self.shortfall_cost = approach, shortfall_cost
        # the cells a frontier cell may be reached from (offsets within ``approach``,
        # nearest first) and the cells on the straight line to each
        reach = max(1, round(approach / grid.resolution))
        dr, dc = np.mgrid[-reach:reach + 1, -reach:reach + 1]
        inside = dr * dr + dc * dc <= reach * reach
        offsets = np.column_stack([dr[inside], dc[inside]])
        offsets = offsets[np.argsort(np.hypot(offsets[:, 0], offsets[:, 1]), kind="stable")]
        steps = np.linspace(0.0, 1.0, 2 * reach + 1)
        self._offsets = offsets
        self._lines = np.rint(offsets[:, None, :] * steps[None, :, None]).astype(np.int64)
        self._shortfall = shortfall_cost * np.hypot(offsets[:, 0], offsets[:, 1]) \
            * grid.resolution
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
             trail: np.ndarray | None = None, obstacles: np.ndarray | None = None,
             closer: Any = None, handed_at: Any = None) -> Plan:
        """The best frontier for a robot at ``pose`` (x, y, heading) and the path to
        it, trying the true frontiers before hidden ones, each with ``clearance``
        before ``squeeze`` (the robot's reflexes guard a tight passage). Frontier
        cells near a ``blacklist`` point (k, 2) are left out; the ``trail`` (bool, the
        map's shape), where the robot has been, is traversable whatever the map
        says, as sonar maps smear echoes across the doorways it came through; cells
        of ``obstacles`` (bool, the map's shape: what the robot's own sonar heard
        lately, close by) are kept clear of as if the map had them occupied, as a
        sonar map loses walls that beams graze. With ``closer`` (x, y: a frontier it
        looked at in vain from where it stood) it plans a path to the cell nearest
        that point that the robot reaches in sight of it, and nothing else. With
        ``handed_at`` (x, y: where the robot stood while another robot mapped, the
        explorer then handed to it), cells the map has occupied within
        ``body_smear`` m of that point are free unless ``obstacles`` has them: the
        other robot's sonar drew this robot's body there as an arc across its 30
        degree cone, wider than the body, walling it in."""
        if probabilities.shape != self.grid.shape:
            raise ValueError(f"the map is {probabilities.shape} cells, the planner's grid "
                             f"{self.grid.shape}: give the explorer the size and "
                             "resolution of the map it is fed (the Mapper's)")
        grid = self.grid
        classes = classify(probabilities)
        occupied, free = classes == OCCUPIED, classes == FREE
        # the robot stands on free ground, whatever the map has learnt of it yet (or
        # learnt of it as another robot's body, seen before the explorer was handed
        # to it)
        off = np.hypot(self.xs - pose[0], self.ys - pose[1])
        occupied &= off > RADIUS
        if handed_at is not None and len(handed_at):
            body = occupied & (np.hypot(self.xs - handed_at[0], self.ys - handed_at[1])
                               <= self.body_smear)
            occupied &= ~body
            free |= body
        underfoot = (off <= RADIUS + grid.resolution) & ~occupied
        underfoot[self._cell(pose)] = True
        if trail is not None:
            underfoot |= trail
        free |= underfoot
        unknown = ~free & ~occupied
        allowed = np.ones(grid.shape, dtype=bool)
        if blacklist is not None:
            for bx, by in np.asarray(blacklist, dtype=np.float64).reshape(-1, 2):
                allowed &= np.hypot(self.xs - bx, self.ys - by) > self.blacklist_radius
        blocking = occupied if obstacles is None else occupied | (obstacles & ~underfoot)
        clear = (ndimage.distance_transform_edt(~blocking) * grid.resolution
                 if blocking.any() else np.full(grid.shape, np.inf))
        cost = 1.0 + self.proximity_cost * np.clip(
            (self.comfort - clear) / (self.comfort - self.lethal), 0.0, 1.0)
        tiers = [(False, lambda: frontiers(free, unknown, self.min_unknown))]
        if closer is not None:
            only = np.zeros(grid.shape, dtype=bool)
            only[self._cell(closer)] = True
            tiers = [(False, lambda: only)]
        elif self.look_behind_walls:        # only when no true frontier can be reached:
            # first the bands with free space it saw through them behind (doorways the
            # map has drawn shut), then those with unknown space behind
            tiers.append((True, lambda: self._shut_doorways(free, occupied, clear, underfoot,
                                                            pose)))
            tiers.append((True, lambda: hidden_frontiers(free, occupied, unknown)))
        regions = 0
        for hidden, cells in tiers:
            labels, count = ndimage.label(cells() & allowed, _SQUARE)
            sizes = np.bincount(labels.ravel(), minlength=count + 1)[1:]
            if not hidden:
                regions = int(np.count_nonzero(sizes >= self.min_region))
            if closer is not None:
                sizes = np.maximum(sizes, self.min_region)
            elif not (sizes >= self.min_region).any():
                continue
            for lethal in (self.lethal, self.squeezed):
                traversable = (free & (clear >= lethal)) | underfoot
                best = self._best(traversable, ~blocking, cost, clear, pose, labels, sizes,
                                  keep, closer)
                if best is not None:
                    target, path, cost = best
                    return Plan(target, path, cost, regions, hidden)
        return Plan(None, np.zeros((0, 3)), math.inf, regions)

    def _shut_doorways(self, free: np.ndarray, occupied: np.ndarray, clear: np.ndarray,
                       underfoot: np.ndarray, pose: Any) -> np.ndarray:
        """Hidden frontiers facing bands of occupied cells (up to 4 cells thick) with
        free space the robot cannot get to behind them (further than ``lethal`` from
        the cells it reaches with a squeeze): it saw that space through a doorway
        that the map has since drawn shut."""
        traversable = (free & (clear >= self.squeezed)) | underfoot
        labels, _ = ndimage.label(traversable, _SQUARE)
        reach = labels == labels[self._cell(pose)]
        near = ndimage.distance_transform_edt(~reach) * self.grid.resolution <= self.lethal
        beyond = free & ~near
        return hidden_frontiers(free & near, occupied, beyond, self.min_beyond, band=4)

    def _cell(self, pose: Any) -> tuple[int, int]:
        """(row, column) of the cell the robot is in (the nearest, off the grid)."""
        rows, cols = self.grid.shape
        row, col = self.grid.cell(pose[0], pose[1])
        return int(np.clip(row, 0, rows - 1)), int(np.clip(col, 0, cols - 1))

    def _best(self, traversable: np.ndarray, see: np.ndarray, cost: np.ndarray,
              clear: np.ndarray, pose: Any, labels: np.ndarray, sizes: np.ndarray,
              keep: Any, closer: Any = None) -> tuple[np.ndarray, np.ndarray, float] | None:
        """The best region of ``labels`` (of ``min_region`` cells at least) reachable
        over ``traversable`` cells, each step priced by the ``cost`` of its two cells:
        the target, the path to it and its cost; or None. A frontier cell is reached
        at a traversable cell within ``approach`` m of it in sight of it (no cell on
        the straight line between that the sonar does not ``see`` through): not
        through a wall."""
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
        # A frontier cell costs the cheapest path to a cell the robot reaches in
        # sight of it (no occupied cell on the straight line between) within
        # ``approach`` m, and ``shortfall_cost`` for each metre between the two.
        distance = distance.reshape(rows, cols)
        frontier_rows, frontier_cols = np.nonzero(labels)
        goal_rows = frontier_rows[:, None] + self._offsets[None, :, 0]
        goal_cols = frontier_cols[:, None] + self._offsets[None, :, 1]
        on_grid = (goal_rows >= 0) & (goal_rows < rows) & (goal_cols >= 0) & (goal_cols < cols)
        goal_rows, goal_cols = np.where(on_grid, goal_rows, 0), np.where(on_grid, goal_cols, 0)
        cost_there = np.where(on_grid, distance[goal_rows, goal_cols], np.inf)
        line_rows = np.clip(frontier_rows[:, None, None] + self._lines[None, :, :, 0], 0,
                            rows - 1)
        line_cols = np.clip(frontier_cols[:, None, None] + self._lines[None, :, :, 1], 0,
                            cols - 1)
        in_sight = see[line_rows, line_cols].all(axis=2)
        shortfall = self._shortfall * (1.0 if closer is None else self.closer_cost)
        cost_there = np.where(in_sight, cost_there + shortfall, np.inf)
        choice = np.argmin(cost_there, axis=1)
        picked = np.arange(len(choice))
        approach = np.full((rows, cols), np.inf)
        approach[frontier_rows, frontier_cols] = cost_there[picked, choice]
        goals = np.zeros((rows, cols), dtype=np.int64)
        goals[frontier_rows, frontier_cols] = (goal_rows[picked, choice] * cols
                                               + goal_cols[picked, choice])
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
        goal = int(goals[row, col])
        target = np.array(grid.center(row, col), dtype=np.float64)
        return target, self._path(previous, start, goal, clear), float(costs[best])

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

    It counts only the time it spends trying to get somewhere toward ``patience``
    (not the time it spends looking), and sets a target it stands at aside only when
    looking at it for ``look_time`` s reduced the unresolved cells round it by less
    than ``look_gain`` (see ``_unresolved``); a pose further than ``jump_distance``
    from the last is another robot's (none moves that far in a step, and no two robots'
    centres are that close), and it plans afresh from there at once.

    Its memory (the attributes named in ``MEMORY``) is plain data: copy it into a
    new explorer of the same grid and settings and it carries on where this one was.
    Time is the sum of the ``dt`` given to ``step``, so it runs in simulated time.
    """

    MEMORY = ("target", "path", "blacklist", "done", "plans", "replans", "stuck", "clock",
              "behind_wall", "planned_at", "anchor", "looking_until", "looked_at", "trail",
              "last_pose", "echoes", "handed_at")

    def __init__(self, grid: Grid, *, max_speed: float = 0.4, max_turn: float = 1.0,
                 clearance: float = 0.1, lookahead: float = 0.5, replan_every: float = 2.0,
                 patience: float = 8.0, forget_after: float = 60.0, look_time: float = 2.0,
                 look_gain: float = 0.3, jump_distance: float = 0.4,
                 **planning: Any) -> None:
        self.planner = FrontierPlanner(grid, clearance=clearance, **planning)
        self.max_speed, self.max_turn, self.lookahead = max_speed, max_turn, lookahead
        self.replan_every, self.patience, self.forget_after = replan_every, patience, forget_after
        self.look_time, self.look_gain, self.jump_distance = look_time, look_gain, jump_distance
        self.look_radius = 1.0         # m round a target whose cells looking should resolve
        self.min_lookahead = 0.2       # m
        self.arrive_within = 0.25      # m from the path's end
        self.turn_in_place = 0.8       # rad of heading error beyond which it stops to turn
        self.stuck_distance = 0.3      # m it must move within ``patience`` s
        self.stop_gap, self.side_gap = 0.1, 0.15   # m from the body
        self.backoff_speed = 0.1       # m/s
        self.braking, self.reaction = 0.3, 0.4      # m/s^2 a robot brakes at, s before it does
        self.side_margin = 0.03        # m kept between the body and an echo it passes
        self._alpha = 0.0              # rad from its heading to the point it pursues
        self.echo_range, self.echo_memory = 1.5, 1.0   # m: echoes it steers by; s kept
        self.obstacle_range = 0.7      # m: echoes it plans round (a cone is 0.4 m wide there)
        self.min_speed = 0.05          # m/s: slower than this on its arc, it turns instead
        self.nearer_by = 0.2           # m nearer a frontier it looked at in vain worth going
        self.look_ahead_travel = 1.0   # m along its arc it checks for echoes
        self.left_behind = 1.0         # m round a robot it was handed from whose trail
                                       # is dropped (one whose link was cut runs on a
                                       # little after its last report)
        self._heard = np.zeros((0, 3))  # echoes (world x, y, clock): not memory, as a move
                                        # to another robot leaves them behind
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
        # the targets it looked at lately: (x, y, unresolved then, 1 once it planned to
        # get nearer, clock)
        self.looked_at: list[list[float]] = []
        self.trail = np.zeros(grid.shape, dtype=bool)   # cells its centre has been near
        self.last_pose: list[float] = []     # (x, y) at the last step
        self.echoes = np.zeros(grid.shape, dtype=bool)  # cells it heard an echo in, close by
        self.handed_at: list[float] = []     # (x, y) where it was handed to this robot,
                                             # until the robot leaves the body's smear

    def memory(self) -> dict[str, Any]:
        """What it needs to carry on elsewhere."""
        return {name: getattr(self, name) for name in self.MEMORY}

    def restore(self, memory: dict[str, Any]) -> None:
        """Carry on from ``memory`` (as ``memory()`` gave it)."""
        for name in self.MEMORY:
            if name in memory:          # (a memory from before ``last_pose``: without it)
                setattr(self, name, memory[name])
        self.path = np.asarray(self.path, dtype=np.float64).reshape(-1, 3)
        if self.looked_at and not isinstance(self.looked_at[0], (list, tuple)):
            self.looked_at = [[*self.looked_at[:2], math.inf, 0.0, self.clock]]  # (before
                                                                # looks were kept apart)
        self.looked_at = [list(entry) for entry in self.looked_at]
        self.echoes = np.array(self.echoes, dtype=bool)  # (read-only off a port: a copy)
        self.trail = np.array(self.trail, dtype=bool)

    def step(self, probabilities: np.ndarray, pose: Any, sonar: np.ndarray | None,
             dt: float) -> tuple[float, float]:
        """The command (v m/s, w rad/s) for the next ``dt`` seconds."""
        self.clock += dt
        x, y = float(pose[0]), float(pose[1])
        if self.last_pose and math.hypot(x - self.last_pose[0],
                                         y - self.last_pose[1]) > self.jump_distance:
            self._jumped(x, y, *self.last_pose)
        elif self.handed_at and math.hypot(x - self.handed_at[0], y - self.handed_at[1]) \
                > self.planner.body_smear:
            self.handed_at = []
        self.last_pose = [x, y]
        self._leave_trail(x, y)
        if sonar is not None:
            self._hear(sonar, pose)
        standing = self._standing(x, y)
        if self.clock < self.looking_until:
            self.anchor[2] += dt            # looking is not trying to get anywhere
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
        return self._reflexes(v, w, sonar, pose) if sonar is not None else (v, w)

    def _jumped(self, x: float, y: float, left_x: float, left_y: float) -> None:
        """The pose jumped further than a robot moves in a step: the explorer was
        handed to another robot (or the localization was reset). What it was doing
        was for where it was; it plans afresh from here at once, setting nothing
        aside for the jump. The robot it drove stands where it left it (``left_x``,
        ``left_y``), at the end of its trail: the trail there is no way through
        any more, and its body is an obstacle (else the planner, trusting the
        trail over the map and the echoes, routes the new robot through it)."""
        self.anchor = [x, y, self.clock]
        self.looking_until, self.looked_at = -math.inf, []
        self.target, self.path, self.behind_wall = [], np.zeros((0, 3)), False
        self.planned_at, self.done = -math.inf, False
        self._heard = np.zeros((0, 3))
        left = np.hypot(self.planner.xs - left_x, self.planner.ys - left_y)
        self.trail[left <= self.left_behind] = False
        self.echoes[left <= RADIUS] = True
        self.handed_at = [x, y]

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
        if due or not len(self.path):   # (a target set without its path: plan one)
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
        """Whether a cell of the path ahead, off the trail (and off the robot's body
        as the robot before it mapped it, see ``handed_at``), has been mapped occupied
        since it was planned, or the robot heard an echo close to it since."""
        rows, cols = self.planner.grid.cell(self.path[:, 0], self.path[:, 1])
        mapped = (probabilities[rows, cols] > OCCUPIED_ABOVE) & ~self.trail[rows, cols]
        if self.handed_at:
            mapped &= np.hypot(self.path[:, 0] - self.handed_at[0],
                               self.path[:, 1] - self.handed_at[1]) > self.planner.body_smear
        if mapped.any():
            return True
        heard = self._heard[(self._heard[:, 2] > self.planned_at)
                            & (self._heard[:, 2] > self.clock - self.echo_memory)]
        if not len(heard):
            return False
        gap = np.hypot(heard[:, None, 0] - self.path[None, :, 0],
                       heard[:, None, 1] - self.path[None, :, 1])
        return bool((gap < RADIUS + self.side_margin).any())

    def _leave_trail(self, x: float, y: float) -> None:
        """Mark the robot's cell and its 4-neighbours as travelled, and forget the
        echoes heard in cells under its body (nothing is where it stands: it is
        another robot's body, seen before the explorer was handed to it)."""
        grid = self.planner.grid
        row, col = grid.cell(x, y)
        rows, cols = row + np.array([0, -1, 1, 0, 0]), col + np.array([0, 0, 0, -1, 1])
        inside = grid.inside(rows, cols)
        self.trail[rows[inside], cols[inside]] = True
        reach = math.ceil(RADIUS / grid.resolution)
        r0, c0 = max(0, row - reach), max(0, col - reach)
        window = self.echoes[r0:row + reach + 1, c0:col + reach + 1]
        if window.any():
            cell_x, cell_y = grid.center(*np.ogrid[r0:r0 + window.shape[0],
                                                   c0:c0 + window.shape[1]])
            window[np.hypot(cell_x - x, cell_y - y) < RADIUS] = False

    def _plan(self, probabilities: np.ndarray, pose: Any) -> None:
        """Choose the target and path (or find it is done) without the frontiers set
        aside."""
        pursuing = bool(self.target)
        active = [entry[:2] for entry in self.blacklist if entry[2] > self.clock]
        self.looked_at = [entry for entry in self.looked_at
                          if entry[4] > self.clock - self.forget_after]
        plan = self.planner.plan(probabilities, pose, np.array(active).reshape(-1, 2),
                                 keep=self.target, trail=self.trail, obstacles=self.echoes,
                                 handed_at=self.handed_at)
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
            # resolves it best looked at squarely: face it for a while. If looking
            # resolved some round it (a beam with no echo clears free space only
            # slowly), it looks on. If it resolved nothing, the frontier may be out of
            # its sight (round a doorway's jamb): it plans to get as near it as it can
            # (``closer``); when it cannot get nearer, or nearer did not help either,
            # the frontier cannot be resolved, and the next step plans without it.
            unresolved = self._unresolved(probabilities, plan.target)
            looked = next((entry for entry in reversed(self.looked_at) if math.hypot(
                entry[0] - plan.target[0], entry[1] - plan.target[1])
                <= self.planner.blacklist_radius), None)
            if looked is None:
                self.looked_at.append([*plan.target.tolist(), unresolved, 0.0, self.clock])
            elif looked[2] - unresolved >= self.look_gain:
                looked[2], looked[3], looked[4] = unresolved, 0.0, self.clock
            else:
                if not looked[3]:
                    nearer = self.planner.plan(probabilities, pose, trail=self.trail,
                                               obstacles=self.echoes, closer=plan.target,
                                               handed_at=self.handed_at)
                    if nearer.target is not None and math.hypot(
                            nearer.path[-1, 0] - x, nearer.path[-1, 1] - y) \
                            >= self.arrive_within + self.nearer_by:
                        looked[2], looked[3], looked[4] = unresolved, 1.0, self.clock
                        self.target, self.path = plan.target.tolist(), nearer.path
                        self.behind_wall = plan.hidden
                        self.anchor = [x, y, self.clock]
                        return
                self._set_aside(plan.target.tolist())
                self.looked_at.remove(looked)
                self.planned_at = -math.inf
                return
            self.looking_until = self.clock + self.look_time
            self.anchor = [x, y, self.clock]
        elif not pursuing:
            self.anchor = [x, y, self.clock]
        self.target, self.path, self.behind_wall = plan.target.tolist(), plan.path, plan.hidden

    def _unresolved(self, probabilities: np.ndarray, point: Any) -> float:
        """How far the cells within ``look_radius`` of ``point`` are from being
        classified: the sum of their probabilities' distances inside the unknown band
        (0.15 for a cell nothing is known of, 0 for a free or occupied one)."""
        grid = self.planner.grid
        rows, cols = grid.shape
        reach = round(self.look_radius / grid.resolution)
        row, col = grid.cell(point[0], point[1])
        r0, r1 = max(0, row - reach), min(rows, row + reach + 1)
        c0, c1 = max(0, col - reach), min(cols, col + reach + 1)
        if r0 >= r1 or c0 >= c1:
            return 0.0
        dr, dc = np.ogrid[r0 - row:r1 - row, c0 - col:c1 - col]
        margin = (OCCUPIED_ABOVE - FREE_BELOW) / 2
        window = np.abs(probabilities[r0:r1, c0:c1] - UNKNOWN)
        return float(np.clip(margin - window, 0.0, None)[dr * dr + dc * dc <= reach * reach]
                     .sum())

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
        self._alpha = alpha
        planner = self.planner
        room = np.clip((near - planner.lethal) / (planner.comfort - planner.lethal), 0.0, 1.0)
        if abs(alpha) > self.turn_in_place * (0.5 + 0.5 * room):   # sooner near walls
            return 0.0, float(np.clip(2.0 * alpha, -self.max_turn, self.max_turn))
        v = self.max_speed * math.cos(alpha) * (0.5 + 0.5 * room)
        curvature = 2.0 * math.sin(alpha) / max(distance, 1e-3)
        if abs(v * curvature) > self.max_turn:          # keep the arc, slow down
            v = self.max_turn / abs(curvature)
        return v, v * curvature

    def _reflexes(self, v: float, w: float, sonar: np.ndarray, pose: Any,
                  ) -> tuple[float, float]:
        """Sonar reflexes over the pursuit: go no faster along the arc (v, w) than
        lets the robot stop short of the echoes on it, heard now or in the last
        ``echo_memory`` s; back off turning to the open side when too close; veer
        from a side too near."""
        gaps = np.asarray(sonar, dtype=np.float64) + _SONAR_REACH - RADIUS
        front, left, right = gaps[_FRONT].min(), gaps[_LEFT].min(), gaps[_RIGHT].min()
        if front < self.stop_gap:
            v = -self.backoff_speed if gaps[_REAR].min() > 2 * self.stop_gap else 0.0
            w = math.copysign(0.5 * self.max_turn, gaps[[0, 1, 2]].min() - gaps[[5, 6, 7]].min())
        elif v > 0:
            travel = self._free_travel(self._heard_here(pose), v, w)
            allowed = self._stoppable(travel - self.stop_gap)
            if allowed < self.min_speed:        # blocked on this arc: turn on the spot
                v, w = 0.0, float(np.clip(2.0 * self._alpha, -self.max_turn, self.max_turn))
            elif allowed < v:                   # slower along the same arc
                v, w = allowed, w * allowed / v
        w += 3.0 * (max(0.0, self.side_gap - right) - max(0.0, self.side_gap - left))
        return v, float(np.clip(w, -self.max_turn, self.max_turn))

    def _hear(self, sonar: np.ndarray, pose: Any) -> None:
        """Keep the ring's echoes within ``echo_range`` (world x, y and clock) for
        ``echo_memory`` s, and note the cells of those within ``obstacle_range``. A
        beam that meets a surface at a grazing angle is reflected away and hears
        nothing, so an obstacle heard a moment ago is taken to be still there when a
        beam goes silent as the robot turns past it; and a sonar map loses walls
        that beams graze, so the planner keeps clear of what the robot heard close by
        whatever the map says."""
        x, y, theta = (float(value) for value in pose)
        cos, sin = math.cos(theta), math.sin(theta)
        ranges = np.asarray(sonar, dtype=np.float64)
        near = np.isfinite(ranges) & (ranges < self.echo_range)
        local = RING[near, :2] + ranges[near, None] * np.column_stack(
            [np.cos(RING[near, 2]), np.sin(RING[near, 2])])
        heard = np.column_stack([x + cos * local[:, 0] - sin * local[:, 1],
                                 y + sin * local[:, 0] + cos * local[:, 1],
                                 np.full(len(local), self.clock)])
        kept = self._heard[self._heard[:, 2] > self.clock - self.echo_memory]
        self._heard = np.vstack([kept, heard])
        close = heard[ranges[near] < self.obstacle_range]
        rows, cols = self.planner.grid.cell(close[:, 0], close[:, 1])
        inside = self.planner.grid.inside(rows, cols)
        self.echoes[rows[inside], cols[inside]] = True

    def _heard_here(self, pose: Any) -> np.ndarray:
        """The echoes kept, in the robot's frame (x ahead, y left), (n, 2)."""
        x, y, theta = (float(value) for value in pose)
        cos, sin = math.cos(theta), math.sin(theta)
        dx, dy = self._heard[:, 0] - x, self._heard[:, 1] - y
        return np.column_stack([cos * dx + sin * dy, -sin * dx + cos * dy])

    def _free_travel(self, points: np.ndarray, v: float, w: float) -> float:
        """How far (m) the robot goes along the arc of (v, w) before its body comes
        within ``side_margin`` of one of ``points`` (its frame); ``look_ahead_travel``
        when it does not within that."""
        if not len(points):
            return self.look_ahead_travel
        along = np.arange(1, round(self.look_ahead_travel / 0.05) + 1) * 0.05
        curvature = w / v
        if abs(curvature) < 1e-6:
            xs, ys = along, np.zeros_like(along)
        else:
            xs = np.sin(curvature * along) / curvature
            ys = (1.0 - np.cos(curvature * along)) / curvature
        near = np.hypot(points[None, :, 0] - xs[:, None], points[None, :, 1] - ys[:, None])
        hit = np.flatnonzero((near < RADIUS + self.side_margin).any(axis=1))
        return float(along[hit[0]] - 0.05) if len(hit) else self.look_ahead_travel

    def _stoppable(self, distance: float) -> float:
        """The speed (m/s) from which the robot still stops within ``distance`` m:
        it goes on for ``reaction`` s (the command's way to the motors, their lag),
        then brakes at ``braking`` m/s^2."""
        if distance <= 0:
            return 0.0
        a, tau = self.braking, self.reaction
        return a * (math.sqrt(tau * tau + 2.0 * distance / a) - tau)


class Explorer(Module):
    """Explores the unknown of the ``map`` it is fed, writing velocity ``command``s.

    Feed it the mapper's probability grid (``agents.grid``), the robot's pose from
    the localization system and its sonar ring (optional: without it, no reflexes).
    When no reachable frontier is left it writes (0, 0) and is ``done``; it still
    looks every ``replan_every`` s, so a map that grows, or a frontier set aside and
    forgotten, sets it going again. Its clock moves on ``period`` for each new pose
    (each report of the robot), so what it measures in time (patience, looking) is
    the robot's time, whatever the step's jitter. Its state is all it needs to carry
    on toward the same target after a move, and to another robot: it plans afresh
    where the pose jumps to.
    """

    map = Input(np.ndarray, dtype="float32")                    # occupancy probabilities
    pose = Input(np.ndarray, shape=(3,), dtype="float64")       # x, y (m), heading (rad)
    sonar = Input(np.ndarray, shape=(16,), dtype="float64")     # m, Pioneer ring order
    command = Output(np.ndarray, shape=(2,), dtype="float64")   # v (m/s), w (rad/s)
    period = 0.1

    resolution = 0.1               # m per cell, the mapper's
    size = [12.0, 9.0]             # m, the world's width and height (the Mapper's too)
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
    looked_at: list[list[float]] = []   # the targets it looked at lately (x, y,
                                        # unresolved then, nearer, clock)
    trail = np.zeros((0, 0), dtype=bool)   # cells it has been on (sized in setup)
    last_pose: list[float] = []    # (x, y) at the last step: a pose far from it is a jump
    echoes = np.zeros((0, 0), dtype=bool)  # cells it heard an echo in, close by (sized in
                                           # setup)
    handed_at: list[float] = []    # (x, y) where it was handed to this robot, while near it

    def setup(self) -> None:
        refuse_own_state(self)
        self._make()
        # Set up with a pose already in (moved with its ports, maybe to another robot:
        # the remedy's hand-over), it stands until the robot reports again: that pose
        # may be the one the robot it drove before last had, and a step on it sent the
        # standby robot the failed one's command.
        self._stale_pose = self.pose.has_value
        if self._stale_pose:
            self.pose.read()

    def _make(self) -> None:
        """The planner, made from the state (its memory restored)."""
        grid = Grid.of(self.size, self.resolution)
        if self.trail.shape != grid.shape:       # a fresh explorer
            self.trail = np.zeros(grid.shape, dtype=bool)
        if self.echoes.shape != grid.shape:
            self.echoes = np.zeros(grid.shape, dtype=bool)
        self._explorer = FrontierExplorer(
            grid, max_speed=self.max_speed, clearance=self.clearance,
            replan_every=self.replan_every, forget_after=self.forget_after)
        self._explorer.restore({name: getattr(self, name) for name in FrontierExplorer.MEMORY})
        self._last: np.ndarray | None = None   # the command last written

    @classmethod
    def state_problems(cls, state: dict[str, Any]) -> list[str]:
        """A setting it could not go by, each naming it: a size or resolution no grid is
        made of, a speed, clearance or time out of its limits (a negative max_speed drove
        it backwards, where its reflexes do not look)."""
        wrong = out_of_limits(_LIMITS, state)
        if "size" in state and "resolution" in state:
            wrong += Grid.problems(state["size"], state["resolution"])
        return super().state_problems(state) + [f"{cls.__name__}'s {problem}"
                                                for problem in wrong]

    @reflective                 # (it takes the fields Module's does: they are checked)
    def set_state(self, state: dict[str, Any]) -> None:
        """Set state (what ``state_problems`` refuses is refused, nothing set); a running
        explorer goes by it from its next step (its settings, and what it remembers: a
        target, a frontier set aside), rather than writing its own memory back over it."""
        super().set_state(state)
        if "_explorer" in vars(self):            # running: made again from the state
            self._make()

    def step(self) -> None:
        if not (self.map.has_value and self.pose.has_value):
            self.command.write(np.zeros(2))      # nothing to go by yet: stand
            return
        if self._stale_pose:                     # (see setup)
            if not self.pose.pending:
                self.command.write(np.zeros(2))
                return
            self._stale_pose = False
        if not self.pose.pending and self._last is not None:
            # No report from the robot since the last step: its time has not moved on
            # as far as the explorer can tell (a step that runs early, a driver that
            # is late), so the explorer's clock, which its patience and its looking
            # are measured in, does not either; the last command holds.
            self.command.write(self._last)
            return
        sonar = self.sonar.read() if self.sonar.has_value else None
        v, w = self._explorer.step(self.map.read(), self.pose.read(), sonar, self.period)
        self._last = np.array([v, w], dtype=np.float64)
        for name, value in self._explorer.memory().items():
            setattr(self, name, value)
        self.command.write(np.array([v, w], dtype=np.float64))


_LIMITS: dict[str, Limit] = {
    "max_speed": ("a speed above 0 (m/s)", lambda v: finite(v) and v > 0),
    "clearance": ("a distance, 0 or more (m)", lambda v: finite(v) and v >= 0),
    "replan_every": SPAN,
    "forget_after": SPAN,
}
