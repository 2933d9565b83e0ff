"""``Fleet``: the simulated robots of a world, moved and scanned together.

A thousand robots cannot each run Python code at every 10 ms physics step, so the
fleet works on arrays. Each simulated robot is a dynamic disc pulled by a kinematic
control body through a pivot joint that corrects velocity only (``max_bias = 0``,
pymunk's tank pattern): the solver, not our code, gives the robot its velocity, so
contacts still stop it, and commands take effect within the step (zeroth order).
Before each step one batch call writes the control bodies' velocities and the
robots' turn rates; after it one batch call reads every body back, and dead
reckoning is done for many steps at once. Sonar is scanned for all of them
together, at most once per ``SONAR_PERIOD`` of simulated time.
"""

from __future__ import annotations

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
_READ = _F.POSITION | _F.ANGLE | _F.VELOCITY | _F.ANGULAR_VELOCITY
_WRITE = _F.VELOCITY | _F.ANGULAR_VELOCITY
_LIMITS = np.array([MAX_SPEED, MAX_TURN])


class Fleet:
    """Every simulated robot of one world, as rows of arrays (one slot each)."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.members: list[SimulatedBody] = []
        self.command = np.zeros((0, 2))          # v, w
        self.pose = np.zeros((0, 3))             # x, y, heading as turned (not wrapped)
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
        self._out = np.zeros((0, 3))             # every body's velocity for the next step
        self._mine = np.zeros((0, 6))            # the robots' rows of the last read
        self._mapped = False                     # the rows below fit the space's bodies
        self._rows: slice | np.ndarray = slice(0, 0)       # the robots' batch rows
        self._controls: slice | np.ndarray = slice(0, 0)   # their control bodies' rows
        # A wide skin: pairs found beyond the reach cost the caster one distance
        # test each, far less than finding the lists again more often.
        self.neighbours = NeighbourLists(sonar.MAX_RANGE + sonar.CASTER.radius, skin=1.0)

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
        self._mapped = False
        self._scanned = -1
        self.neighbours.forget()

    # -- physics -------------------------------------------------------------------------
    def _read(self) -> np.ndarray:
        """Every body of the space after the last step, (B, 6): a view of pymunk's
        buffer, good until the next read."""
        buffer = self._buffer
        buffer.clear()
        pymunk.batch.get_space_bodies(self.world.space, _READ, buffer)
        state = np.frombuffer(buffer.float_buf(), dtype=np.float64).reshape(-1, 6)
        # The space's batch order changes only when bodies come or go (we are told,
        # or someone else added to the space: the count then differs).
        if not self._mapped or len(state) != len(self._out):
            self._map()
        return state

    def _map(self) -> None:
        """Find the robots' and their control bodies' rows among the space's bodies."""
        ids = pymunk.batch.Buffer()
        pymunk.batch.get_space_bodies(self.world.space, _F.BODY_ID, ids)
        row = {int(body_id): i for i, body_id in enumerate(np.frombuffer(ids.int_buf(),
                                                                         dtype=np.uintp))}
        self._rows = _progression([row[m.body.id] for m in self.members])
        self._controls = _progression([row[m.control.id] for m in self.members])
        self._out = np.empty((len(row), 3))
        # Memory numpy owns, which pymunk only reads: it would free or realloc a
        # buffer of its own that it cleared or grew.
        self._writing.set_float_buf(self._out.ravel())
        self._mapped = True

    def before_step(self) -> None:
        """Give every robot its commanded velocity: its control body the speed along
        its heading (world frame), the robot itself the turn rate.

        Nothing moves a body between two steps but the world's hardware robots, which
        place their stand-ins after this, so the bodies are read once, after each
        step, and every other body is written back the velocity it had then."""
        if not self.members:
            return
        if not self._mapped:
            self._keep(self._read())
        out, controls, v = self._out, self._controls, self.command[:, 0]
        heading = self.pose[:, 2]
        out[controls, 0] = v * np.cos(heading)
        out[controls, 1] = v * np.sin(heading)
        out[self._rows, 2] = self.command[:, 1]
        pymunk.batch.set_space_bodies(self.world.space, _WRITE, self._writing)

    def after_step(self, dt: float) -> None:
        """Read every robot's pose and velocity back after a step of ``dt``; keep what
        the wheels did for dead reckoning, done for many steps at once."""
        if not self.members:
            return
        self._keep(self._read())
        self._wheels.append(self._mine[:, 2:6])                    # heading, vx, vy, w
        self._dt = dt
        if len(self._wheels) >= WHEEL_STEPS:
            self._dead_reckon()

    def _keep(self, state: np.ndarray) -> None:
        """Take the robots' rows of a read, and every body's velocity to write back."""
        np.copyto(self._out, state[:, 3:6])
        mine = self._mine = state[self._rows].copy()   # (a view when rows are a slice)
        self.pose = mine[:, 0:3]
        self.velocity = mine[:, 3:6]

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
        self.readings = sonar.readings(self.ranges(), NOISE, self.rng)

    def ranges(self) -> np.ndarray:
        """Every robot's sonar rays (R, 16 x RAYS, ring order), noiseless: the range to
        each ray's first hit, ``inf`` for none."""
        segments, discs = self.world.segments(), self.world.all_discs()
        segment_pairs, disc_pairs = self.neighbours.pairs(self.pose[:, 0:2], segments, discs)
        return sonar.CASTER.cast(self.pose, segments, segment_pairs, discs, disc_pairs,
                                 self.world.depths())


def _progression(rows: list[int]) -> slice | np.ndarray:
    """Rows as a slice when they are evenly spaced (robots added one after another
    are), which numpy indexes much faster than an index array."""
    if len(rows) < 2:
        return slice(rows[0], rows[0] + 1) if rows else slice(0, 0)
    step = rows[1] - rows[0]
    if step > 0 and rows == list(range(rows[0], rows[-1] + 1, step)):
        return slice(rows[0], rows[-1] + 1, step)
    return np.array(rows, dtype=np.intp)
