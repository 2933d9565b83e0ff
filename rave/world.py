"""``World``: RAVE's world model, a 2D world in pymunk stepped at a fixed rate.

It holds the walls and obstacles (each real or ``virtual``: a virtual one exists only
here, so simulated robots and the virtual half of hybrid sensors sense it, and real
robots' bodies pass through it), the simulated robots, and where the hardware robots
report to be. Stepping is deterministic for a given seed: the same calls give the
same poses and readings.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from numbers import Real
from pathlib import Path
from typing import Any

import numpy as np
import pymunk

from rave import worldfile
from rave.camera import Target
from rave.fleet import Fleet
from rave.hardware import HardwareBody
from rave.layers import REAL, VIRTUAL, WALL_RADIUS
from rave.pioneer import RADIUS
from rave.robot import Robot

PHYSICS_DT = 0.01                    # s: physics runs at 100 Hz whatever step() is given


@dataclass(frozen=True)
class Obstacle:
    """A wall (two points) or a closed polygon (box or polygon), real or virtual."""

    points: tuple[tuple[float, float], ...]
    closed: bool
    virtual: bool = False
    color: str | None = None

    def edges(self) -> list[tuple[float, float, float, float]]:
        pts = list(self.points) + ([self.points[0]] if self.closed else [])
        return [(*a, *b) for a, b in itertools.pairwise(pts)]

    def depths(self) -> list[float]:
        """Per edge, how far the obstacle lies behind it, on its left (the inside of a
        convex polygon wound anticlockwise); ``inf`` where an edge has no inside (walls,
        polygons not convex or wound clockwise). A ray from beyond that depth behind
        an edge is outside the obstacle and meets another of its edges first."""
        edges = np.array(self.edges(), dtype=np.float64)
        points = np.array(self.points, dtype=np.float64)
        e = edges[:, 2:4] - edges[:, 0:2]
        rel = points[None, :, :] - edges[:, None, 0:2]
        left = (e[:, None, 0] * rel[..., 1] - e[:, None, 1] * rel[..., 0]) / np.hypot(
            e[:, 0], e[:, 1])[:, None]                       # each vertex, from each edge
        if not self.closed or (left < -1e-9).any():
            return [math.inf] * len(edges)
        return left.max(axis=1).tolist()


class World:
    """Walls, obstacles and robots; ``step(dt)`` advances simulated time."""

    def __init__(self, size: tuple[float, float] = (10.0, 8.0), seed: int = 0,
                 name: str = "world") -> None:
        self.size, self.seed, self.name = (float(size[0]), float(size[1])), int(seed), name
        self.space = pymunk.Space()
        self.obstacles: list[Obstacle] = []
        self.robots: dict[str, Robot] = {}
        self._added = 0                              # robots added so far (their indices)
        self.time = 0.0
        self._steps = 0
        self._debt = 0.0
        self._segments: dict[tuple[bool, bool], tuple[np.ndarray, np.ndarray]] = {}
        self.fleet = Fleet(self)                     # the simulated robots, as arrays
        self.hardware: list[HardwareBody] = []       # the hardware robots' bodies
        self._closed = False

    @classmethod
    def load(cls, path: str | Path, seed: int = 0, *, robots: bool = True) -> World:
        """A world from a TOML world file (see ``rave/worldfile.py``), or a bundled one
        by name (``"arena"``, as ``rave start`` takes it: a path relative to the
        repository worked from its root only); with ``robots`` False, its walls and
        obstacles only (no emulator process is started for the hardware robots the file
        places)."""
        path = worldfile.world_file(str(path))
        plan = worldfile.read(path)
        world = cls(plan.size, seed, plan.name)
        for wall in plan.walls:
            world.add_wall(**wall)
        for box in plan.boxes:
            world.add_box(**box)
        for polygon in plan.polygons:
            world.add_polygon(**polygon)
        problems = world._misplaced(plan, str(path))
        if problems:                             # (before any emulator is started)
            raise worldfile.WorldError(problems)
        try:
            for robot in plan.robots if robots else ():
                world.add_robot(**robot)
        except BaseException:           # the emulators started so far stop with it
            world.close()
            raise
        return world

    def _misplaced(self, plan: worldfile.Plan, source: str) -> list[str]:
        """Every robot of ``plan`` that overlaps an obstacle it would collide with (a
        hardware robot passes through virtual ones) or a robot placed before it: it
        would run stuck, or be shoved through a wall."""
        labels = [f"{table}[{i}]" for table in ("walls", "boxes", "polygons")
                  for i in range(len(getattr(plan, table)))]
        problems, placed = [], []
        for i, robot in enumerate(plan.robots):
            x, y, _ = robot["pose"]
            hits = [label for label, obstacle in zip(labels, self.obstacles, strict=True)
                    if _blocks(obstacle, robot["backend"], x, y)]
            hits += [f"robot {name!r}" for name, (px, py) in placed
                     if math.hypot(x - px, y - py) < 2 * RADIUS]
            if hits:
                problems.append(f"{source} robots[{i}] {robot['name']!r}: at ({x}, {y}) "
                                f"it overlaps {', '.join(hits)}; a robot needs {RADIUS:g} m "
                                "clear of obstacles and other robots")
            placed.append((robot["name"], (x, y)))
        return problems

    # -- building -----------------------------------------------------------------
    def add_wall(self, start: tuple[float, float], end: tuple[float, float], *,
                 virtual: bool = False) -> None:
        ends = (_point(start, "wall"), _point(end, "wall"))
        if ends[0] == ends[1]:
            raise ValueError(f"wall: both its ends are {ends[0]}: a wall needs a length")
        self._add(Obstacle(ends, closed=False, virtual=virtual))

    def add_box(self, center: tuple[float, float], size: tuple[float, float], *,
                angle: float = 0.0, virtual: bool = False, color: str | None = None) -> None:
        """A rectangle of ``size`` (width, height) around ``center``, turned by ``angle``
        radians."""
        (cx, cy), (w, h) = _point(center, "box"), _point(size, "box")
        if not (w > 0 and h > 0):
            raise ValueError(f"box: size must be (width, height), both > 0, not {size}")
        if not (isinstance(angle, Real) and math.isfinite(angle)):
            raise ValueError(f"box: angle must be a finite number of radians, not {angle!r}")
        c, s = math.cos(angle), math.sin(angle)
        corners = [(dx * w / 2, dy * h / 2) for dx, dy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        points = tuple((cx + c * x - s * y, cy + s * x + c * y) for x, y in corners)
        self._add(Obstacle(points, closed=True, virtual=virtual, color=color))

    def add_polygon(self, points: list[tuple[float, float]], *, virtual: bool = False,
                    color: str | None = None) -> None:
        if len(points) < 3:
            raise ValueError(f"a polygon needs at least 3 points, not {len(points)}")
        corners = [_point(p, "polygon") for p in points]
        if _signed_area(corners) < 0:
            corners.reverse()                   # anticlockwise: the inside on the left
        self._add(Obstacle(tuple(corners), closed=True, virtual=virtual, color=color))

    def _add(self, obstacle: Obstacle) -> None:
        if not obstacle.virtual:         # not while a hardware robot is known to be gone
            for body in self.hardware:
                body.emulator.check()
        layer = VIRTUAL if obstacle.virtual else REAL
        for x0, y0, x1, y1 in obstacle.edges():
            shape = pymunk.Segment(self.space.static_body, (x0, y0), (x1, y1), WALL_RADIUS)
            shape.filter = pymunk.ShapeFilter(categories=layer)
            shape.friction = 0.0
            self.space.add(shape)
        self.obstacles.append(obstacle)
        self._segments.clear()
        if not obstacle.virtual:                 # hardware robots' physical worlds too
            edges = np.array(obstacle.edges(), dtype=np.float64)
            failure = None
            for body in self.hardware:           # (one dying now leaves none behind it out)
                try:
                    body.emulator.add_walls(edges)
                except (RuntimeError, TimeoutError) as exc:
                    failure = failure or exc
            if failure is not None:
                raise failure

    def add_robot(self, name: str, pose: tuple[float, float, float], *, backend: str = "sim",
                  color: str = "red") -> Robot:
        """A robot at ``pose`` (x, y, heading in radians) served by ``backend`` ("sim" or
        "hardware")."""
        self._check_open()
        if name in self.robots:
            raise ValueError(f"world {self.name} has a robot {name!r} already")
        place = (float(pose[0]), float(pose[1]), float(pose[2]))
        if not all(map(math.isfinite, place)):
            raise ValueError(f"robot {name}: pose must be finite (x, y, heading), not {place}")
        x, y, heading = place
        # (into [-pi, pi), as every later reading: odometry gave 4 pi until it moved)
        place = (x, y, (heading + math.pi) % math.tau - math.pi)
        hits = self.blocking(backend, x, y)
        hits += [f"robot {other!r}" for other, robot in self.robots.items()
                 if math.dist((x, y), robot.gps()[:2]) < 2 * RADIUS]
        if hits:                        # (as a world file's robot is refused)
            raise ValueError(f"robot {name}: at ({x:g}, {y:g}) it overlaps {', '.join(hits)}; "
                             f"a robot needs {RADIUS:g} m clear of obstacles and other robots")
        robot = Robot(self, name, place, backend=backend, color=color, index=self._added)
        self._added += 1                # (never reused: a robot's noise is its own)
        self.robots[name] = robot
        return robot

    def blocking(self, backend: str, x: float, y: float) -> list[str]:
        """The obstacles a robot on ``backend`` at (x, y) would overlap (a hardware robot
        passes through virtual ones), named for a message."""
        return [f"obstacle {i} ({obstacle.points[0]}, ...)"
                for i, obstacle in enumerate(self.obstacles) if _blocks(obstacle, backend, x, y)]

    def close(self) -> None:
        """Stop the hardware robots' emulator processes (also on leaving a ``with``);
        the world steps and takes robots no more."""
        self._closed = True
        for hardware in list(self.hardware):
            hardware.emulator.close()

    def _check_open(self) -> None:
        # (a closed world's step said its emulators were gone, and to swap their robots)
        if self._closed:
            raise RuntimeError(f"world {self.name!r} is closed")

    def __enter__(self) -> World:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def remove_robot(self, name: str) -> None:
        self.robot(name)._close()
        del self.robots[name]

    def robot(self, name: str) -> Robot:
        try:
            return self.robots[name]
        except KeyError:
            raise KeyError(f"world {self.name} has no robot {name!r}; robots: "
                           f"{', '.join(self.robots) or '(none)'}") from None

    # -- time ---------------------------------------------------------------------
    def step(self, dt: float) -> None:
        """Advance simulated time by ``dt`` seconds in fixed physics steps (a remainder
        shorter than one is carried to the next call)."""
        if not 0 <= dt < math.inf:
            raise ValueError(f"step({dt}): dt must be a finite number of seconds, 0 or more "
                             "(time only goes forward)")
        self._check_open()
        due = int((self._debt + dt + 1e-12) / PHYSICS_DT)
        failed, failure = self._advance_hardware(due) if due else ([], None)
        self._debt += dt - due * PHYSICS_DT
        for step in range(due):
            self.fleet.before_step()
            for hardware in self.hardware:
                if hardware in failed:
                    hardware.hold()
                else:
                    hardware.place(step)
            self.space.step(PHYSICS_DT)
            self.fleet.after_step()
        self._steps += due
        self.time = self._steps * PHYSICS_DT
        if failure is not None:
            raise failure

    def _advance_hardware(self, steps: int) -> tuple[list[HardwareBody], Exception | None]:
        """Step the hardware robots first, all at once in their emulators' processes:
        nothing in the world model pushes a physical robot. Their stand-ins then follow
        the reported poses step by step, pushing simulated robots. Every answer asked
        for is taken, even when one robot fails, so that none is read out of turn.
        None is asked while one is known to be gone: the world cannot step then, and
        the others would run ahead of it at every try. One found failing as it steps
        (silent, or gone meanwhile) is returned with its error: the others have
        taken the step, so the world takes it too, that robot standing where it last
        reported (the others stayed a step ahead of the world for good)."""
        for hardware in self.hardware:
            hardware.emulator.check()
        asked, failed, failure = [], [], None
        for hardware in self.hardware:
            try:
                hardware.emulator.begin_advance(steps, PHYSICS_DT)
                asked.append(hardware)
            except (RuntimeError, TimeoutError) as exc:
                failed.append(hardware)
                failure = failure or exc
        for hardware in asked:
            try:
                hardware.end_advance()
            except (RuntimeError, TimeoutError) as exc:
                failed.append(hardware)
                failure = failure or exc
        return failed, failure

    # -- what sensors see -----------------------------------------------------------------
    def pose(self, name: str) -> tuple[float, float, float]:
        """Ground truth (x, y, heading) of a robot (a hardware robot's reported pose)."""
        return self.robot(name).gps()

    def segments(self, real: bool = True, virtual: bool = True) -> np.ndarray:
        """Every edge of the obstacles of the chosen layers, shape (n, 4)."""
        return self._edges(real, virtual)[0]

    def depths(self, real: bool = True, virtual: bool = True) -> np.ndarray:
        """How far each of ``segments()`` has its obstacle behind it (``Obstacle.depths``)."""
        return self._edges(real, virtual)[1]

    def _edges(self, real: bool, virtual: bool) -> tuple[np.ndarray, np.ndarray]:
        key = (real, virtual)
        cached = self._segments.get(key)
        if cached is None:
            chosen = [o for o in self.obstacles if (virtual if o.virtual else real)]
            edges = [edge for o in chosen for edge in o.edges()]
            depths = [depth for o in chosen for depth in o.depths()]
            cached = self._segments[key] = (np.array(edges, dtype=np.float64).reshape(-1, 4),
                                            np.array(depths, dtype=np.float64))
        return cached

    def all_discs(self) -> np.ndarray:
        """Every robot as (x, y, radius): the simulated ones first, in fleet order,
        then the hardware ones."""
        simulated = len(self.fleet.pose)
        discs = np.empty((simulated + len(self.hardware), 3))
        discs[:simulated, 0:2] = self.fleet.pose[:, 0:2]
        for row, hardware in enumerate(self.hardware, simulated):
            discs[row, 0:2] = hardware.pose()[:2]
        discs[:, 2] = RADIUS
        return discs

    def discs(self, exclude: str | None = None) -> np.ndarray:
        """Every robot but ``exclude`` as (x, y, radius), shape (m, 3)."""
        return np.array([(*robot.gps()[:2], RADIUS) for name, robot in self.robots.items()
                         if name != exclude], dtype=np.float64).reshape(-1, 3)

    def targets(self, exclude: str | None = None) -> list[Target]:
        """What cameras may see: every other robot, and coloured obstacles (their
        outlines)."""
        found = [Target(*robot.gps()[:2], RADIUS, robot.color)
                 for name, robot in self.robots.items() if name != exclude]
        for obstacle in self.obstacles:
            if obstacle.color is not None:
                pts = np.asarray(obstacle.points)
                center = pts.mean(axis=0)
                radius = float(np.hypot(*(pts - center).T).max())
                found.append(Target(float(center[0]), float(center[1]), radius, obstacle.color,
                                    outline=tuple(obstacle.points)))
        return found

    def describe(self) -> dict[str, Any]:
        """The world as plain data (for rendering and robot servers)."""
        return {"name": self.name, "size": self.size, "time": self.time,
                "obstacles": [vars(o) for o in self.obstacles],
                "robots": {name: {"pose": r.gps(), "backend": r.backend, "color": r.color}
                           for name, r in self.robots.items()}}


def _clearance(obstacle: Obstacle, x: float, y: float) -> float:
    """How far (x, y) lies from the obstacle's edges; 0 inside a closed one."""
    edges = np.array(obstacle.edges(), dtype=np.float64)
    start, along = edges[:, 0:2], edges[:, 2:4] - edges[:, 0:2]
    rel = np.array([x, y]) - start
    t = np.clip((rel * along).sum(axis=1) / np.maximum((along * along).sum(axis=1), 1e-12),
                0.0, 1.0)
    gap = float(np.hypot(*(rel - t[:, None] * along).T).min())
    if obstacle.closed:                           # inside: an odd number of edges cross
        y0, y1 = edges[:, 1], edges[:, 3]         # the ray from (x, y) towards +x
        spans = (y0 > y) != (y1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            cross = edges[:, 0] + (y - y0) * (edges[:, 2] - edges[:, 0]) / (y1 - y0)
        if np.count_nonzero(spans & (x < cross)) % 2:
            return 0.0
    return gap


def _signed_area(points: list[tuple[float, float]]) -> float:
    """Twice the area enclosed, positive when the points go round anticlockwise."""
    return sum(x0 * y1 - x1 * y0 for (x0, y0), (x1, y1)
               in itertools.pairwise([*points, points[0]]))


def _blocks(obstacle: Obstacle, backend: str, x: float, y: float) -> bool:
    """Whether a robot on ``backend`` at (x, y) overlaps ``obstacle`` (a hardware robot
    passes through virtual ones): it would run stuck, or be shoved through it."""
    return not (obstacle.virtual and backend == "hardware") and \
        _clearance(obstacle, x, y) < RADIUS + WALL_RADIUS


def _point(value: Any, what: str) -> tuple[float, float]:
    """A point (or a size) as two floats; one that is not finite is refused, naming
    ``what`` it belongs to (it would poison the physics and every robot's scan)."""
    x, y = value
    point = (float(x), float(y))
    if not all(map(math.isfinite, point)):
        raise ValueError(f"{what}: points must be finite (x, y), not {point}")
    return point
