"""``Fleet``: the simulated robots of a world, moved and scanned together.

A thousand robots cannot each run Python code at every 10 ms physics step, so the
fleet works on arrays. Each simulated robot is a dynamic disc pulled by a kinematic
control body through a pivot joint that corrects velocity only (``max_bias = 0``,
pymunk's tank pattern): the solver, not our code, gives the robot its velocity, so
contacts still stop it, and commands take effect within the step (zeroth order).
The control body turns about the robot's centre of curvature, so it carries a
command for as long as the command holds: bodies are written (one batch call)
only when commands change, and read (one batch call) only when someone looks,
with dead reckoning done for each stretch between reads. Sonar is scanned for
all of them together, at most once per ``SONAR_PERIOD`` of simulated time.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import pymunk
import pymunk.batch

from rave import sonar
from rave.neighbours import NeighbourLists
from rave.odometry import chord_sum, dead_reckon_arcs
from rave.pioneer import MAX_SPEED, MAX_TURN
from rave.scene import Scene

SONAR_PERIOD = 0.1                       # s: simulated sonar refresh (10 Hz)
WHEEL_STEPS = 50                         # physics steps dead-reckoned at once, at most
FAR = 1e6                                # m: a turn wider than this is driven straight
ONE_BY_ONE = 16                          # new commands set body by body, at most (else
                                         # one batch write of every body is cheaper)
_F = pymunk.batch.BodyFields
_READ = _F.POSITION | _F.ANGLE | _F.VELOCITY | _F.ANGULAR_VELOCITY
_WRITE = _F.VELOCITY | _F.ANGULAR_VELOCITY
_LIMITS = np.array([MAX_SPEED, MAX_TURN])


class Member(Protocol):
    """A simulated robot as its fleet holds it (``SimulatedBody``)."""

    name: str
    slot: int                   # its row in the fleet's arrays
    body: pymunk.Body           # the robot's disc
    control: pymunk.Body        # the kinematic body that pulls it


class Fleet:
    """Every simulated robot of one world, as rows of arrays (one slot each)."""

    def __init__(self, world: Scene) -> None:
        self.world = world
        self.members: list[Member] = []
        self._command = np.zeros((0, 2))         # v, w
        self._commanded = False                  # since the last step
        self.odometry_scale = np.ones((0, 3))
        self.readings = np.zeros((0, sonar.COUNT))
        self.rng = np.random.default_rng([world.seed, 1 << 30])
        self._odometry = np.zeros((0, 3))
        self._applied = np.zeros((0, 2))         # the commands the control bodies carry
        self._pose = np.zeros((0, 3))            # x, y, heading as turned (not wrapped)
        self._velocity = np.zeros((0, 3))        # vx, vy, w
        self._state = np.zeros((0, 6))           # every body, as last read
        self._fresh = True                       # no step since that read
        self._steps = 0                          # steps since the odometry's last stretch
        self._scanned = -1                       # the sonar tick the readings are from
        self._buffer = pymunk.batch.Buffer()       # read into (pymunk owns its memory)
        self._writing = pymunk.batch.Buffer()      # written from ``_out``, kept alive
        self._out = np.zeros((0, 3))             # every body's velocity, to write
        self._mapped = False                     # the rows below fit the space's bodies
        self._robot_rows = np.zeros(0, dtype=np.intp)      # the robots' batch rows
        self._control_rows = np.zeros(0, dtype=np.intp)    # their control bodies' rows
        self._rows: slice | np.ndarray = slice(0, 0)       # the first, as read fastest
        # A wide skin: pairs found beyond the reach cost the caster one distance
        # test each, far less than finding the lists again more often.
        self.neighbours = NeighbourLists(sonar.MAX_RANGE + sonar.CASTER.radius, skin=1.0)

    # -- membership --------------------------------------------------------------------
    def add(self, member: Member, pose: tuple[float, float, float],
            velocity: tuple[float, float, float], odometry: tuple[float, ...],
            scale: np.ndarray) -> int:
        if self._steps:                  # the others' odometry, up to now (with no step
            self._refresh()              # since the last read, the bodies have not moved)
        self.members.append(member)
        self._command = np.vstack([self._command, [0.0, 0.0]])
        self._applied = np.vstack([self._applied, [np.nan, np.nan]])    # (never equal)
        self._commanded = True
        self._pose = np.vstack([self._pose, pose])
        self._velocity = np.vstack([self._velocity, velocity])
        self._odometry = np.vstack([self._odometry, odometry])
        self.odometry_scale = np.vstack([self.odometry_scale, scale])
        self.bodies_changed()
        return len(self.members) - 1

    def remove(self, member: Member) -> None:
        if self._steps:                  # (as in add)
            self._refresh()
        slot = self.members.index(member)
        del self.members[slot]
        for name in ("_command", "_applied", "_pose", "_velocity", "_odometry",
                     "odometry_scale"):
            setattr(self, name, np.delete(getattr(self, name), slot, axis=0))
        for later in self.members[slot:]:
            later.slot -= 1
        self.bodies_changed()

    def bodies_changed(self) -> None:
        """Bodies came into the space or left it: re-map batch rows at the next read."""
        self._mapped = self._fresh = False
        self._scanned = -1
        self.neighbours.forget()

    # -- physics -------------------------------------------------------------------------
    # A robot's command moves it along a circle about its instantaneous centre of
    # curvature (ICC), radius v / w. Its control body is made to turn about that
    # centre at w: the control body's centre of gravity is put there, its joint
    # anchor stays at the robot, so the anchor's velocity (what the joint gives the
    # robot) is the command's velocity along the robot's heading at every step
    # without any writes. A robot's own turn rate, once written, persists: nothing
    # exerts a torque on a frictionless disc pulled at its centre. So bodies are
    # written only when commands change and read only when someone looks.

    @property
    def pose(self) -> np.ndarray:
        """Every robot's (x, y, heading as turned, not wrapped), after the last step."""
        self._refresh()
        return self._pose

    @property
    def velocity(self) -> np.ndarray:
        """Every robot's (vx, vy, w), after the last step."""
        self._refresh()
        return self._velocity

    def before_step(self) -> None:
        """Give robots whose command changed their new motion (see above)."""
        if self._commanded:
            self._commanded = False
            self._apply()

    def after_step(self) -> None:
        """A step moved the bodies: what was read is stale. Odometry is integrated over
        each stretch between two reads; a stretch is kept short enough for its
        arithmetic (``_integrate``) by reading at least every ``WHEEL_STEPS``."""
        self._fresh = False
        self._steps += 1
        if self._steps >= WHEEL_STEPS and self.members:
            self._refresh()

    def _apply(self) -> None:
        """Give the robots whose command changed their motion: the control body's
        velocity, turn rate and centre of gravity (the centre of curvature, in its
        own frame: it has turned), and the robot's turn rate."""
        state = self._refresh()
        changed = np.flatnonzero((self._command != self._applied).any(axis=1))
        self._applied[changed] = self._command[changed]
        v, w = self._command[changed].T
        heading = self._pose[changed, 2]
        turning = np.abs(w) * FAR > np.abs(v)
        radius = np.divide(v, w, out=np.zeros_like(v), where=turning)
        ahead = np.where(turning, 0.0, v)
        offset = heading - state[self._control_rows[changed], 2]
        motion = np.column_stack([ahead * np.cos(heading), ahead * np.sin(heading),
                                  np.where(turning, w, 0.0), w, -radius * np.sin(offset),
                                  radius * np.cos(offset)]).tolist()
        members = self.members
        if len(changed) > ONE_BY_ONE:          # one batch write of every body
            out = self._out
            np.copyto(out, state[:, 3:6])       # every other body keeps its velocity
            out[self._control_rows[changed]] = [row[0:3] for row in motion]
            out[self._robot_rows[changed], 2] = w
            pymunk.batch.set_space_bodies(self.world.space, _WRITE, self._writing)
            for slot, (*_, cx, cy) in zip(changed.tolist(), motion, strict=True):
                members[slot].control.center_of_gravity = (cx, cy)
        else:
            for slot, (vx, vy, wc, wr, cx, cy) in zip(changed.tolist(), motion, strict=True):
                control = members[slot].control
                control.velocity, control.angular_velocity = (vx, vy), wc
                control.center_of_gravity = (cx, cy)
                members[slot].body.angular_velocity = wr

    def _refresh(self) -> np.ndarray:
        """Read the bodies if a step moved them since the last read, and integrate the
        odometry over that stretch; every body's state (B, 6), good until a read."""
        if not self._fresh and self.members:
            state = self._state = self._read()
            mine = np.array(state[self._rows])       # (indexed by a slice: a view)
            if self._steps:
                self._integrate(mine[:, 0:3])
            self._pose, self._velocity = mine[:, 0:3], mine[:, 3:6]
            self._steps = 0
        self._fresh = True
        return self._state

    def _read(self) -> np.ndarray:
        """Every body of the space, (B, 6): a view of pymunk's buffer."""
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
        self._robot_rows = np.array([row[m.body.id] for m in self.members], dtype=np.intp)
        self._control_rows = np.array([row[m.control.id] for m in self.members], dtype=np.intp)
        self._rows = _progression(self._robot_rows.tolist())
        self._out = np.empty((len(row), 3))
        # Memory numpy owns, which pymunk only reads: it would free or realloc a
        # buffer of its own that it cleared or grew.
        self._writing.set_float_buf(self._out.ravel())
        self._mapped = True

    def _integrate(self, pose: np.ndarray) -> None:
        """Dead-reckon the stretch of ``_steps`` steps that ended at ``pose``.

        Within a stretch a robot's command is fixed, so unhindered it moves the same
        distance every step, each along its heading as the step began: the pose
        change is a sum of equal chords, turned by equal angles, which gives that
        distance. (Reading every ``WHEEL_STEPS`` keeps a stretch's turn well short of
        a half circle, where the sum would vanish.) Where something held a robot
        back, the distance is the stretch's mean; so is it for the first step after
        a command change, which pymunk still moves with the velocity solved before
        (it moves bodies before it solves): millimetres over metres."""
        k, start = self._steps, self._pose
        half = (pose[:, 2] - start[:, 2]) / (2 * k)          # half the turn per step
        along = start[:, 2] + (k - 1) * half                # the chords' sum points along
        distance = ((pose[:, 0] - start[:, 0]) * np.cos(along)
                    + (pose[:, 1] - start[:, 1]) * np.sin(along)) / chord_sum(k, half)
        dead_reckon_arcs(self._odometry, self.odometry_scale, distance,
                         2 * half * self.odometry_scale[:, 2], k)

    @property
    def odometry(self) -> np.ndarray:
        """Every robot's dead-reckoned (x, y, heading), up to the last step."""
        self._refresh()
        return self._odometry

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
        command = np.empty_like(self._command)
        try:
            command[:, 0], command[:, 1] = v, w
        except ValueError:
            raise ValueError(f"drive_all: v and w must be numbers, single values or "
                             f"{len(self.members)} values each, in slot order") from None
        if not np.isfinite(command).all():
            raise ValueError("drive_all needs finite speeds")
        np.clip(command, -_LIMITS, _LIMITS, out=self._command)
        self._commanded = True

    def drive(self, slot: int, v: float, w: float) -> None:
        """Command one robot (already clipped, as ``Robot.drive`` does)."""
        self._command[slot] = (v, w)
        self._commanded = True

    @property
    def command(self) -> np.ndarray:
        """Every robot's (v, w) as commanded, read-only (``drive_all`` commands them)."""
        view = self._command.view()
        view.flags.writeable = False
        return view

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
        self.readings = sonar.readings(self.ranges(), sonar.MODEL_NOISE, self.rng)

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
