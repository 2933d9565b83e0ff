"""``Fleet``: the simulated robots of a world, moved and scanned together.

A thousand robots cannot each run Python code at every 10 ms physics step, so the
fleet works on arrays. Each simulated robot is a dynamic disc pulled by a kinematic
control body through a pivot joint and a gear joint that correct velocity only
(``max_bias = 0``, pymunk's tank pattern): the solver, not our code, gives the
robot its velocity, so contacts still stop it, and commands take effect within
the step (zeroth order). Before each step one batch call reads every body and
one writes the control bodies' velocities; after it one batch call reads poses
and velocities back, and odometry advances for all at once. Sonar is scanned for
all of them together, at most once per ``SONAR_PERIOD`` of simulated time.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import pymunk
import pymunk.batch

from rave import sonar
from rave.neighbours import CellIndex, boxes_of_segments, segment_distances, within
from rave.odometry import dead_reckon
from rave.raycast import cast_rings

if TYPE_CHECKING:
    from rave.simulated import SimulatedBody
    from rave.world import World

SONAR_PERIOD = 0.1                       # s: simulated sonar refresh (10 Hz)
NOISE = sonar.SonarNoise(sigma0=0.005, sigma_per_m=0.005)
_F = pymunk.batch.BodyFields
_READ = _F.BODY_ID | _F.POSITION | _F.ANGLE | _F.VELOCITY | _F.ANGULAR_VELOCITY
_WRITE = _F.VELOCITY | _F.ANGULAR_VELOCITY


class Fleet:
    """Every simulated robot of one world, as rows of arrays (one slot each)."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.members: list[SimulatedBody] = []
        self.command = np.zeros((0, 2))          # v, w
        self.pose = np.zeros((0, 3))             # x, y, heading (after the last step)
        self.velocity = np.zeros((0, 3))         # vx, vy, w
        self.odometry = np.zeros((0, 3))
        self.odometry_scale = np.ones((0, 3))
        self.readings = np.zeros((0, sonar.COUNT))
        self.rng = np.random.default_rng([world.seed, 1 << 30])
        self._scanned = -1                       # the sonar tick the readings are from
        self._buffer = pymunk.batch.Buffer()       # read into (pymunk owns its memory)
        self._out: np.ndarray | None = None         # written from (kept alive while used)
        self._ids = np.zeros(0, dtype=np.uintp)  # body ids in the space's batch order
        self._rows = self._controls = np.zeros(0, dtype=np.intp)
        self._segments: tuple[np.ndarray, CellIndex] | None = None

    # -- membership --------------------------------------------------------------------
    def add(self, member: SimulatedBody, pose: tuple[float, float, float],
            velocity: tuple[float, float, float], odometry: tuple[float, ...],
            scale: np.ndarray) -> int:
        self.members.append(member)
        self.command = np.vstack([self.command, [0.0, 0.0]])
        self.pose = np.vstack([self.pose, pose])
        self.velocity = np.vstack([self.velocity, velocity])
        self.odometry = np.vstack([self.odometry, odometry])
        self.odometry_scale = np.vstack([self.odometry_scale, scale])
        self._changed()
        return len(self.members) - 1

    def remove(self, member: SimulatedBody) -> None:
        slot = self.members.index(member)
        del self.members[slot]
        for name in ("command", "pose", "velocity", "odometry", "odometry_scale"):
            setattr(self, name, np.delete(getattr(self, name), slot, axis=0))
        for later in self.members[slot:]:
            later.slot -= 1
        self._changed()

    def _changed(self) -> None:
        self._ids = np.zeros(0, dtype=np.uintp)   # re-map batch rows at the next step
        self._scanned = -1

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
        return np.frombuffer(buffer.float_buf(), dtype=np.float64).reshape(-1, 6)

    def before_step(self) -> None:
        """Give each control body its robot's commanded velocity (world frame)."""
        if not self.members:
            return
        state = self._read()
        heading = state[self._rows, 2]
        out = state[:, 3:6].copy()             # every other body keeps its velocity
        v, w = self.command[:, 0], self.command[:, 1]
        out[self._controls, 0] = v * np.cos(heading)
        out[self._controls, 1] = v * np.sin(heading)
        out[self._controls, 2] = w
        # A separate buffer: one whose memory numpy owns must never be cleared or grown
        # by pymunk, which would free or realloc it.
        self._out = np.ascontiguousarray(out.ravel())
        writing = pymunk.batch.Buffer()
        writing.set_float_buf(self._out)
        pymunk.batch.set_space_bodies(self.world.space, _WRITE, writing)

    def after_step(self, dt: float) -> None:
        """Read every robot's pose and velocity back; advance their odometry."""
        if not self.members:
            return
        state = self._read()[self._rows]
        self.pose = state[:, 0:3].copy()
        self.pose[:, 2] = np.remainder(self.pose[:, 2] + math.pi, math.tau) - math.pi
        self.velocity = state[:, 3:6].copy()
        heading = state[:, 2]
        distance = (self.velocity[:, 0] * np.cos(heading)
                    + self.velocity[:, 1] * np.sin(heading)) * dt
        rotation = self.velocity[:, 2] * dt * self.odometry_scale[:, 2]
        dead_reckon(self.odometry, self.odometry_scale, distance, rotation)

    # -- sonar ---------------------------------------------------------------------------
    def sonar(self, slot: int) -> np.ndarray:
        """The robot's readings from this sonar period (scanned for all at once)."""
        tick = int(self.world.time / SONAR_PERIOD + 1e-9)
        if tick != self._scanned:
            self.scan()
            self._scanned = tick
        return self.readings[slot].copy()

    def scan(self) -> None:
        """Every simulated robot's 16 transducers against every layer and every other
        robot, in one batch."""
        poses = self.pose
        reach = sonar.MAX_RANGE + 0.3               # transducers sit up to 0.26 m out
        centers = poses[:, 0:2]
        segments = self.segment_candidates(centers, reach)
        discs = self._disc_candidates(centers, reach)
        origins, headings, directions = sonar.ring_rays(poses)
        ranges = cast_rings(origins, headings, directions, sonar.CONE / 2, sonar.MAX_RANGE,
                            segments, discs)
        self.readings = sonar.finish(ranges.min(axis=2), NOISE, self.rng)

    def segment_candidates(self, centers: np.ndarray, reach: float) -> np.ndarray:
        """Each point's obstacle edges within ``reach``: (R, k, 4), NaN-padded."""
        all_segments = self.world.segments()
        if self._segments is None or self._segments[0] is not all_segments:
            index = CellIndex(boxes_of_segments(all_segments), reach)
            self._segments = (all_segments, index)
        index = self._segments[1]
        padded = np.vstack([all_segments, np.full((1, 4), np.nan)])
        near = index.near(centers)
        near = within(near, segment_distances(centers, padded[near]), reach)
        return padded[near]

    def _disc_candidates(self, centers: np.ndarray, reach: float) -> np.ndarray:
        discs = self.world.all_discs()                 # simulated robots first, by slot
        if len(discs) < 2:
            return np.zeros((len(centers), 0, 3))
        radius = discs[:, 2:3]
        index = CellIndex(np.hstack([discs[:, 0:2] - radius, discs[:, 0:2] + radius]), reach)
        near = index.near(centers)
        near[near == np.arange(len(centers))[:, None]] = -1          # not itself
        padded = np.vstack([discs, np.full((1, 3), np.nan)])
        found = padded[near]
        gap = np.hypot(found[..., 0] - centers[:, None, 0], found[..., 1] - centers[:, None, 1])
        near = within(near, gap - found[..., 2], reach)
        return padded[near]
