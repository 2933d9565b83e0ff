"""Occupancy-grid mapping from a Pioneer sonar ring: ``OccupancyGrid`` and ``Mapper``.

``OccupancyGrid`` is the numpy core: a log-odds array on an ``agents.grid.Grid``
that ``update(pose, ranges)`` folds one reading of the 16-transducer ring into,
by the Bayesian log-odds rule with a cone inverse sensor model (``SonarModel``).
``Mapper`` is the PB3A module around it: sonar readings and the localization pose
in, the probability map out, the log-odds grid in its state so that a migrated
mapper goes on with the map it had.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
from scipy import ndimage

from agents.grid import Grid
from agents.limits import refuse_own_state, whole
from pb3a import Input, InputPort, Module, Output
from rave.sonar import MAX_RANGE, RING


@dataclass(frozen=True)
class SonarModel:
    """The inverse sensor model of one transducer: what a reading says of the cells
    in its cone, as log-odds added to them (Thrun et al., *Probabilistic Robotics*
    9.2; Moravec and Elfes 1985).

    Cells nearer than the echo are free, cells within ``thickness / 2`` of it are
    occupied, cells beyond it are untouched; both updates fade off the acoustic axis
    by a Gaussian of the bearing. Echoes from ``max_occupied_range`` on, and no echo
    at all (``MAX_RANGE``), only clear free space out to ``max_free_range``, and
    weakly (``free_no_echo``): a beam meeting a smooth wall at a grazing angle is
    reflected away and reads as nothing, so "no echo" says little about what lies in
    the cone. The clamp keeps every cell revisable: a robot standing still, folding
    in the same reading again and again, takes a cell no further than ``clamp``
    (p = 0.982 at 4), from where eight readings of free space on the axis clear it.

    A beam meeting a smooth surface further than ``specular_deg`` from its normal
    (on the acoustic axis; the hardware's 20 degrees plus the cone's half-width) is
    reflected away: neither its echo nor its silence says anything of that surface.
    So a cell the map already holds occupied, whose surface (the local run of
    occupied cells, by the gradient of the smoothed map) the beam meets at such a
    grazing angle, keeps what it has; other cells take the free update. 90 turns
    this off.

    The defaults were tuned on the lab world (``tests/test_agents_mapper.py``): a
    free update as strong as the occupied one carves away the parts of each 30 degree
    arc that are not wall, and a weak no-echo update keeps specular misses from
    clearing walls.
    """

    cone_deg: float = 30.0            # full width of the beam
    sigma_deg: float = 7.5            # angular weighting: exp(-bearing^2 / 2 sigma^2)
    thickness: float = 0.15           # m: depth of the occupied band at the echo
    occupied: float = 0.6             # log-odds of an echo, on the axis (p = 0.65)
    free: float = -0.6                # log-odds of a cell an echoing beam passed
    free_no_echo: float = -0.05       # ... and of one a long or no-echo beam passed
    max_occupied_range: float = 3.5   # m: longer echoes clear free space only ...
    max_free_range: float = 3.0       # m: ... out to here
    clamp: float = 4.0                # log-odds stay within [-clamp, clamp]
    specular_deg: float = 35.0        # beams meeting a mapped surface beyond this from
                                      # its normal do not clear it

    def __post_init__(self) -> None:
        if not (0 < self.cone_deg < 180 and self.sigma_deg > 0 and self.thickness > 0
                and self.occupied > 0 > self.free and self.free_no_echo <= 0
                and self.max_free_range > 0 and self.max_occupied_range > 0
                and self.clamp > 0 and 0 < self.specular_deg <= 90):
            raise ValueError(f"a sonar model needs a cone in (0, 180) degrees, positive "
                             f"sigma, thickness, ranges, clamp and occupied update, free "
                             f"updates below zero and a specular angle in (0, 90], not "
                             f"{self}")


class OccupancyGrid:
    """A log-odds occupancy map on ``grid``, learnt from sonar ring readings.

    ``log_odds`` (float32, ``grid.shape``), ``last_ranges`` (the ring's previous
    reading) and ``unfolded`` (per transducer, the updates since its reading was last
    folded in) are updated in place, so a caller that keeps the arrays (a module's
    state) always holds the current map; pass existing ones to carry on from them.

    With ``skip_repeats``, a transducer whose reading is exactly its previous one is
    left out: a real ring fires each transducer every 320 ms while its robot reports
    every 100 ms, so most of a report repeats the last one, and folding a reading in
    again would count one echo three times, at poses it was not taken from. A reading
    of no echo (``MAX_RANGE``) is the exception: it is the same number whether the
    transducer fired again or not, so a repeat of it is taken for a new firing once
    ``refire_every`` updates have passed since it was last folded in (3: a firing
    cycle at the robot's 100 ms reports). Were every repeat left out, a beam that
    keeps hearing nothing (down a corridor whose walls reflect it away, across an
    open floor) would count once however long it looked, and the space ahead of the
    robot would never be cleared.
    """

    def __init__(self, grid: Grid, model: SonarModel | None = None,
                 log_odds: np.ndarray | None = None, last_ranges: np.ndarray | None = None,
                 skip_repeats: bool = True, unfolded: np.ndarray | None = None,
                 refire_every: int = 3) -> None:
        self.grid = grid
        self.model = model or SonarModel()
        if log_odds is None:
            log_odds = np.zeros(grid.shape, dtype=np.float32)
        if log_odds.shape != grid.shape or log_odds.dtype != np.float32:
            raise ValueError(f"the log-odds array must be float32 of the grid's shape "
                             f"{grid.shape}, not {log_odds.dtype} {log_odds.shape}")
        if last_ranges is None:
            last_ranges = np.full(len(RING), np.nan)
        if last_ranges.shape != (len(RING),) or last_ranges.dtype != np.float64:
            raise ValueError(f"the last ranges must be float64 of shape ({len(RING)},), "
                             f"not {last_ranges.dtype} {last_ranges.shape}")
        if unfolded is None:
            unfolded = np.zeros(len(RING))
        if unfolded.shape != (len(RING),) or unfolded.dtype != np.float64:
            raise ValueError(f"the unfolded counts must be float64 of shape ({len(RING)},), "
                             f"not {unfolded.dtype} {unfolded.shape}")
        self.log_odds, self.last_ranges, self.unfolded = log_odds, last_ranges, unfolded
        self.skip_repeats, self.refire_every = skip_repeats, refire_every
        self._tan_half_cone = math.tan(math.radians(self.model.cone_deg) / 2)
        self._inverse_2sigma2 = 1.0 / (2 * math.radians(self.model.sigma_deg) ** 2)
        self._cos_specular = math.cos(math.radians(self.model.specular_deg))

    def update(self, pose: Any, ranges: Any) -> None:
        """Fold in one ring reading: ``ranges`` (16, m, Pioneer order; non-finite
        readings are skipped) taken at ``pose`` (x, y, heading) in the world. A pose
        that is not three finite numbers is refused (ValueError), nothing changed."""
        model, res = self.model, self.grid.resolution
        x, y, theta = (float(v) for v in pose)
        if not all(map(math.isfinite, (x, y, theta))):
            raise ValueError(f"a reading's pose must be finite (x, y, heading), not {pose!r}")
        ranges = np.array(ranges, dtype=np.float64)
        usable = np.isfinite(ranges)
        self.unfolded += 1
        if self.skip_repeats:
            usable &= (ranges != self.last_ranges) | (
                (ranges >= MAX_RANGE) & (self.unfolded >= self.refire_every))
        self.unfolded[usable] = 0
        self.last_ranges[:] = ranges
        echo = usable & (ranges < model.max_occupied_range)
        half = model.thickness / 2
        # free space: cells nearer than free_to; occupied: those within half of the echo
        free_to = np.where(echo, ranges - half, np.minimum(ranges, model.max_free_range))
        reach = np.where(usable, np.where(echo, ranges + half, free_to), 0.0)
        cos, sin = math.cos(theta), math.sin(theta)
        origin_x = x + cos * RING[:, 0] - sin * RING[:, 1]
        origin_y = y + sin * RING[:, 0] + cos * RING[:, 1]
        heading = theta + RING[:, 2]
        # the window of cells any cone reaches, and every cell's place in each cone
        rows, cols = self.grid.shape
        col0 = max(0, math.floor((origin_x - reach).min() / res))
        col1 = min(cols, math.ceil((origin_x + reach).max() / res))
        row0 = max(0, math.floor((origin_y - reach).min() / res))
        row1 = min(rows, math.ceil((origin_y + reach).max() / res))
        if not reach.any() or col0 >= col1 or row0 >= row1:
            return
        dx = ((np.arange(col0, col1) + 0.5) * res)[None, None, :] - origin_x[:, None, None]
        dy = ((np.arange(row0, row1) + 0.5) * res)[None, :, None] - origin_y[:, None, None]
        axis_x, axis_y = np.cos(heading)[:, None, None], np.sin(heading)[:, None, None]
        along = dx * axis_x + dy * axis_y               # (16, rows, cols): along the axis
        across = dy * axis_x - dx * axis_y              # ... and off it, left positive
        distance = np.hypot(along, across)
        # a cell is in a cone when the cone reaches within half a cell of its centre
        # (near the ring a cone is narrower than a cell, and testing centres alone
        # would leave holes between the beams), at the bearing of that nearest part
        inside = ((distance < reach[:, None, None]) & (along > 0)
                  & (np.abs(across) <= along * self._tan_half_cone + res / 2))
        sensor, row, col = np.nonzero(inside)           # only cells in a cone from here on
        r = distance[sensor, row, col]
        off = across[sensor, row, col]
        bearing = np.arctan2(np.sign(off) * np.maximum(np.abs(off) - res / 2, 0.0),
                             along[sensor, row, col])
        passed = np.where(echo, model.free, model.free_no_echo)[sensor]
        evidence = np.where(r < free_to[sensor], passed, 0.0)
        if self._cos_specular > 0:
            evidence[self._grazing(sensor, row, col, row0, col0, dx, dy)] = 0.0
        evidence += np.where(echo[sensor] & (np.abs(r - ranges[sensor]) <= half),
                             model.occupied, 0.0)
        evidence *= np.exp(-bearing * bearing * self._inverse_2sigma2)
        window = self.log_odds[row0:row1, col0:col1]
        change = np.bincount(row * (col1 - col0) + col, weights=evidence,
                             minlength=window.size).reshape(window.shape)
        np.clip(window + change, -model.clamp, model.clamp, out=window, casting="unsafe")

    def _grazing(self, sensor: np.ndarray, row: np.ndarray, col: np.ndarray, row0: int,
                 col0: int, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
        """Which of the cells (``row``, ``col`` in the window from ``row0``, ``col0``,
        each in the cone of ``sensor``, ``dx``, ``dy`` from it) the map holds
        occupied with a surface the beam meets at a grazing angle: the angle between
        the beam and the gradient of the smoothed map (the surface's normal) is
        beyond ``specular_deg``."""
        occupied = self.log_odds[row0 + row, col0 + col] > 0
        if not occupied.any():
            return occupied
        rows, cols = self.grid.shape
        pad = 2                              # the gradient needs cells round the window
        r0, c0 = max(0, row0 - pad), max(0, col0 - pad)
        r1 = min(rows, row0 + int(row.max()) + 1 + pad)
        c1 = min(cols, col0 + int(col.max()) + 1 + pad)
        smooth = ndimage.gaussian_filter(np.clip(self.log_odds[r0:r1, c0:c1], 0.0, None),
                                         1.0)
        grad_y, grad_x = np.gradient(smooth)
        at = (row0 - r0 + row[occupied], col0 - c0 + col[occupied])
        nx, ny = grad_x[at], grad_y[at]
        bx, by = dx[sensor[occupied], 0, col[occupied]], dy[sensor[occupied], row[occupied], 0]
        norm = np.hypot(nx, ny) * np.hypot(bx, by)
        grazing = (norm > 1e-12) & (np.abs(nx * bx + ny * by)
                                    < self._cos_specular * np.maximum(norm, 1e-12))
        occupied[occupied] = grazing
        return occupied

    def probabilities(self) -> np.ndarray:
        """The map as occupancy probabilities (float32, ``agents.grid``'s convention)."""
        return (1.0 / (1.0 + np.exp(-self.log_odds))).astype(np.float32)


class Mapper(Module):
    """Builds an occupancy map from a robot's sonar ring and its localization pose.

    Each reading on ``sonar`` is folded in at the newest pose on ``pose`` (the
    driver's ``gps``; readings before any pose are ignored). ``RobotDriver`` writes a
    step's pose before its reading, so that is the reading's own pose; also the first
    reading from a robot the driver was just pointed at is folded in where that robot
    stands, not where the last one stood. The map is written on ``map`` every
    ``publish_every`` updates, and every update says when and at which pose it was
    made on ``updated`` (so a watcher knows which robot's reading it was). The state
    holds the map itself (``log_odds``), so a mapper moved to another node, or handed
    to another robot, carries on with it.
    """

    sonar = Input(np.ndarray, shape=(16,), dtype="float64")
    pose = Input(np.ndarray, shape=(3,), dtype="float64")
    map = Output(np.ndarray, dtype="float32")
    updated = Output(np.ndarray, shape=(4,), dtype="float64")   # (time.time(), x, y, heading)
    size = [12.0, 9.0]                          # m: the world's width and height
    resolution = 0.1                            # m per cell
    model = asdict(SonarModel())                # SonarModel's fields; may give only some
    skip_repeats = True                         # see OccupancyGrid
    publish_every = 1
    log_odds = np.zeros((0, 0), dtype=np.float32)   # the map; (re)made to fit in setup
    last_ranges = np.full(16, np.nan)
    unfolded = np.zeros(16)                     # see OccupancyGrid
    updates = 0
    last_update = 0.0                           # time.time() of the last update
    unplaced = 0                                # readings skipped: their pose not finite

    def setup(self) -> None:
        refuse_own_state(self)
        self._build()

    @classmethod
    def state_problems(cls, state: dict[str, Any]) -> list[str]:
        """A size, resolution, ``publish_every`` or sonar model it could not map with,
        each naming it (taken, every reading failed from then on)."""
        wrong = []
        if "size" in state and "resolution" in state:
            wrong += Grid.problems(state["size"], state["resolution"])
        every = state.get("publish_every", 1)       # (a NaN failed every reading)
        if not whole(every, 1):
            wrong.append(f"publish_every must be a whole number of readings, 1 or more, "
                         f"got {every!r}")
        if "model" in state:
            wrong += _model_problems(state["model"])
        return super().state_problems(state) + [f"{cls.__name__}'s {problem}"
                                                for problem in wrong]

    def on_input(self, port: InputPort) -> None:
        if port.name != "sonar" or not self.pose.has_value:
            return
        mapper = self._current()
        pose = self.pose.read()
        if not np.isfinite(pose).all():          # (a localization that lost the robot)
            self.sonar.read()
            self.unplaced += 1
            return
        mapper.update(pose, self.sonar.read())
        self.updates += 1
        self.last_update = time.time()
        self.updated.write(np.array([self.last_update, *pose[:3]]))
        if self.updates % self.publish_every == 0:
            self.map.write(mapper.probabilities())

    def _current(self) -> OccupancyGrid:
        """The core on the current state, rebuilt if a ``set_state`` changed it."""
        core: OccupancyGrid | None = self.__dict__.get("_core")
        if (core is None or core.log_odds is not self.log_odds
                or core.last_ranges is not self.last_ranges
                or core.unfolded is not self.unfolded
                or core.skip_repeats != self.skip_repeats
                or core.grid != Grid.of(self.size, self.resolution)
                or asdict(core.model) != self.model):
            core = self._build()
        return core

    def _build(self) -> OccupancyGrid:
        """A core on the state, which is made to fit: the model completed with
        defaults, a fresh map if the old one is not of the grid's shape, a copy of a
        read-only one (arrays that came through a port are)."""
        grid, model = Grid.of(self.size, self.resolution), SonarModel(**self.model)
        self.model = asdict(model)
        self.log_odds = _writable(self.log_odds, np.float32)
        if self.log_odds.shape != grid.shape:
            self.log_odds = np.zeros(grid.shape, dtype=np.float32)
        self.last_ranges = _writable(self.last_ranges, np.float64)
        if self.last_ranges.shape != (len(RING),):
            self.last_ranges = np.full(len(RING), np.nan)
        self.unfolded = _writable(self.unfolded, np.float64)
        if self.unfolded.shape != (len(RING),):
            self.unfolded = np.zeros(len(RING))
        core = OccupancyGrid(grid, model, self.log_odds, self.last_ranges,
                             bool(self.skip_repeats), self.unfolded)
        self.__dict__["_core"] = core
        return core


def _model_problems(model: Any) -> list[str]:
    """Why ``model`` is not a ``Mapper``'s sonar model: a table of some of
    ``SonarModel``'s parameters (the rest its defaults), in their ranges."""
    if not isinstance(model, dict):
        return [f"model must be a table of the sonar model's parameters, got {model!r}"]
    parameters = [field.name for field in fields(SonarModel)]
    unknown = sorted(set(model) - set(parameters))
    if unknown:
        return [f"model: the sonar model has no parameter {', '.join(map(str, unknown))}; "
                f"its parameters: {', '.join(parameters)}"]
    try:
        SonarModel(**model)
    except (TypeError, ValueError) as exc:
        return [f"model: {exc}"]
    return []


def _writable(array: Any, dtype: type) -> np.ndarray:
    """``array`` as ``dtype``, copied only if it is not already a writable one."""
    array = np.asarray(array, dtype=dtype)
    return array if array.flags.writeable else array.copy()
