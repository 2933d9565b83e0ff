"""``Fleet``: the simulated robots of a world, moved and scanned together.

A thousand robots cannot each run Python code at every 10 ms physics step, so the
fleet works on arrays. Each simulated robot is a dynamic disc pulled by a kinematic
control body through a pivot joint and a gear joint that correct velocity only
(``max_bias = 0``, pymunk's tank pattern): the solver, not our code, gives the
robot its velocity, so contacts still stop it, and commands take effect within
the step (zeroth order). Before each step one batch call writes the control
bodies' velocities; after it one batch call reads every body back, and dead
reckoning is done for many steps at once. Sonar is scanned for all of them
together, at most once per ``SONAR_PERIOD`` of simulated time.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import pymunk
import pymunk.batch

from rave import sonar
from rave.neighbours import NeighbourLists
from rave.odometry import dead_reckon
from rave.simulated import MAX_SPEED, MAX_TURN

if TYPE_CHECKING:
    from rave.simulated import SimulatedBody
    from rave.world import World

SONAR_PERIOD = 0.1                       # s: simulated sonar refresh (10 Hz)
WHEEL_STEPS = 50                         # physics steps dead-reckoned at once, at most
NOISE = sonar.SonarNoise(sigma0=0.005, sigma_per_m=0.005)
_F = pymunk.batch.BodyFields
_READ = _F.BODY_ID | _F.POSITION | _F.ANGLE | _F.VELOCITY | _F.ANGULAR_VELOCITY
_WRITE = _F.VELOCITY | _F.ANGULAR_VELOCITY
_LIMITS = np.array([MAX_SPEED, MAX_TURN])


class Fleet:
    """Every simulated robot of one world, as rows of arrays (one slot each)."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.members: list[SimulatedBody] = []
        self.command = np.zeros((0, 2))          # v, w
        self.pose = np.zeros((0, 3))             # x, y, heading (after the last step)
        self.velocity = np.zeros((0, 3))         # vx, vy, w
        self.odometry_scale = np.ones((0, 3))
        self.readings = np.zeros((0, sonar.COUNT))
        self.rng = np.random.default_rng([world.seed, 1 << 30])
        self._odometry = np.zeros((0, 3))
        self._wheels: list[np.ndarray] = []      # per step not yet dead-reckoned
        self._dt = 0.0                           # their step
        self._scanned = -1                       # the sonar tick the readings are from
        self._buffer = pymunk.batch.Buffer()       # read into (pymunk owns its memory)
        self._writing = pymunk.batch.Buffer()      # written from ``_out``, kept alive
        self._out: np.ndarray | None = None
        self._state: np.ndarray | None = None    # every body after the last step
        self._ids = np.zeros(0, dtype=np.uintp)  # body ids in the space's batch order
        self._rows = self._controls = np.zeros(0, dtype=np.intp)
        self.neighbours = NeighbourLists(sonar.MAX_RANGE + sonar.CASTER.radius)

    # -- membership --------------------------------------------------------------------
    def add(self, member: SimulatedBody, pose: tuple[float, float, float],
            velocity: tuple[float, float, float], odometry: tuple[float, ...],
            scale: np.ndarray) -> int:
        self._dead_reckon()
        self.members.append(member)
        self.command = np.vstack([self.command, [0.0, 0.0]])
        self.pose = np.vstack([self.pose, pose])
        self.velocity = np.vstack([self.velocity, velocity])
        self._odometry = np.vstack([self._odometry, odometry])
        self.odometry_scale = np.vstack([self.odometry_scale, scale])
        self.bodies_changed()
        return len(self.members) - 1

    def remove(self, member: SimulatedBody) -> None:
        self._dead_reckon()
        slot = self.members.index(member)
        del self.members[slot]
        for name in ("command", "pose", "velocity", "_odometry", "odometry_scale"):
            setattr(self, name, np.delete(getattr(self, name), slot, axis=0))
        for later in self.members[slot:]:
            later.slot -= 1
        self.bodies_changed()

    def bodies_changed(self) -> None:
        """Bodies came into the space or left it: re-map batch rows at the next step."""
        self._state = None
        self._scanned = -1
        self.neighbours.forget()

    # -- physics -------------------------------------------------------------------------
    def _read(self) -> np.ndarray:
        buffer = self._buffer
        buffer.clear()
        pymunk.batch.get_space_bodies(self.world.space, _READ, buffer)
        ids = np.frombuffer(buffer.int_buf(), dtype=np.uintp)
        if not np.array_equal(ids, self._ids):
            self._ids = ids.copy()
            row = {int(body_id): i for i, body_id in enumerate(self._ids)}
            self._rows = np.array([row[m.body.id] for m in self.members], dtype=np.intp)
            self._controls = np.array([row[m.control.id] for m in self.members], dtype=np.intp)
        return np.frombuffer(buffer.float_buf(), dtype=np.float64).reshape(-1, 6).copy()

    def before_step(self) -> None:
        """Give each control body its robot's commanded velocity (world frame).

        Nothing moves a body between two steps but the world's hardware robots, which
        place their stand-ins after this, so the bodies as the last step left them
        are read only once, after that step."""
        if not self.members:
            return
        if self._state is None:
            self._state = self._read()
        state = self._state
        heading = state[self._rows, 2]
        out = self._out
        if out is None or out.shape != state[:, 3:6].shape:
            # Memory numpy owns, which pymunk only reads: it would free or realloc a
            # buffer of its own that it cleared or grew.
            out = self._out = np.empty_like(state[:, 3:6])
            self._writing.set_float_buf(out.ravel())
        out[:] = state[:, 3:6]                    # every other body keeps its velocity
        v = self.command[:, 0]
        out[self._controls, 0] = v * np.cos(heading)
        out[self._controls, 1] = v * np.sin(heading)
        out[self._controls, 2] = self.command[:, 1]
        pymunk.batch.set_space_bodies(self.world.space, _WRITE, self._writing)

    def after_step(self, dt: float) -> None:
        """Read every robot's pose and velocity back after a step of ``dt``; keep what
        the wheels did for dead reckoning, done for many steps at once."""
        if not self.members:
            return
        self._state = self._read()
        mine = self._state[self._rows]
        self.pose = mine[:, 0:3]
        self.pose[:, 2] = np.remainder(self.pose[:, 2] + math.pi, math.tau) - math.pi
        self.velocity = mine[:, 3:6]
        self._wheels.append(mine[:, 2:6])                    # heading, vx, vy, w
        self._dt = dt
        if len(self._wheels) >= WHEEL_STEPS:
            self._dead_reckon()

    @property
    def odometry(self) -> np.ndarray:
        """Every robot's dead-reckoned (x, y, heading), up to the last step."""
        self._dead_reckon()
        return self._odometry

    def _dead_reckon(self) -> None:
        if not self._wheels:
            return
        wheels = np.array(self._wheels)                      # (steps, robots, 4)
        self._wheels.clear()
        heading = wheels[..., 0]
        distance = (wheels[..., 1] * np.cos(heading) + wheels[..., 2] * np.sin(heading)) * self._dt
        rotation = wheels[..., 3] * (self._dt * self.odometry_scale[:, 2])
        dead_reckon(self._odometry, self.odometry_scale, distance, rotation)

    # -- every simulated robot at once (large headless experiments) ------------------
    @property
    def names(self) -> list[str]:
        """The simulated robots' names, in slot order (the rows of the arrays)."""
        return [member.name for member in self.members]

    def sonar_all(self) -> np.ndarray:
        """Every simulated robot's 16 readings from this sonar period, (R, 16)."""
        self._scan_if_due()
        return self.readings.copy()

    def drive_all(self, v: np.ndarray | float, w: np.ndarray | float) -> None:
        """Command every simulated robot at once (arrays in slot order, or one value
        for all), clipped to the robots' limits as ``Robot.drive`` does."""
        try:
            command = np.column_stack(np.broadcast_arrays(
                np.asarray(v, dtype=np.float64), np.asarray(w, dtype=np.float64),
                np.zeros(len(self.members))))[:, 0:2]
        except ValueError:
            raise ValueError(f"drive_all: v and w must be single values or "
                             f"{len(self.members)} values each, in slot order") from None
        if not np.isfinite(command).all():
            raise ValueError("drive_all needs finite speeds")
        np.clip(command, -_LIMITS, _LIMITS, out=command)
        self.command[:] = command

    # -- sonar ---------------------------------------------------------------------------
    def sonar(self, slot: int) -> np.ndarray:
        """The robot's readings from this sonar period (scanned for all at once)."""
        self._scan_if_due()
        return self.readings[slot].copy()

    def _scan_if_due(self) -> None:
        tick = int(self.world.time / SONAR_PERIOD + 1e-9)
        if tick != self._scanned:
            self.scan()
            self._scanned = tick

    def scan(self) -> None:
        """Every simulated robot's 16 transducers against every layer and every other
        robot, in one batch."""
        nearest = self.ranges().reshape(-1, sonar.COUNT, sonar.RAYS).min(axis=2)
        self.readings = sonar.finish(nearest, NOISE, self.rng)

    def ranges(self) -> np.ndarray:
        """Every robot's sonar rays (R, 16 x RAYS, ring order), noiseless: the range to
        each ray's first hit, ``inf`` for none."""
        segments, discs = self.world.segments(), self.world.all_discs()
        segment_pairs, disc_pairs = self.neighbours.pairs(self.pose[:, 0:2], segments, discs)
        return sonar.CASTER.cast(self.pose, segments, segment_pairs, discs, disc_pairs,
                                 self.world.depths())
