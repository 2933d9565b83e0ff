"""``RobotDriver``: a RAVE robot as PB3A ports.

It lives in ``agents/`` rather than ``rave/`` because it is a PB3A module: RAVE's
simulator core does not depend on PB3A, and the driver is where the two meet. It
imports nothing of RAVE (it speaks to the robot server's port), so a worker that
takes it in, as when a control system migrates, does not load the simulator. It
talks to the robot's server (``rave start``) through its resource port, so the
controller behind its ports can run on any node; re-pointing ``resource`` moves it
to another robot while it runs (the old one is stopped first). Setting ``enabled`` to
False stops the robot safely: it is told to stop every period and commands are
ignored, while its sensors are still read out. A command that is not finite (a
controller gone wrong) stops the robot too, and is counted in ``failures``. A robot
that does not answer ``silent_after`` requests in a row (a period's, or a command's
sent as it came) is said once on ``failure``
(fault ``robot_link``), as a monitor says a fault: nothing downstream of a driver
whose robot server died would otherwise hear of it (no reading comes to be judged).
The log says it too: at the first unanswered request, as it is said on ``failure``, and
when the robot answers again.

Against a world served in lock-step (``rave start --lockstep``), set ``lockstep_s``:
each command then drives the robot, advances the world by ``lockstep_s`` simulated
seconds and answers with the new readings (one ``cycle`` request), so the world moves
exactly as fast as the controller decides. A controller that waits for a first reading
gets one every ``period`` until commands come. ``clock`` carries the world's time of
each reading, for controllers that must keep time by the world rather than the wall
clock, and ``applied`` the command that moved the robot up to those readings, for
monitors that compare commanded with measured motion: over the robot's time since the
last reading, the mean of the commands it ran on, each from when it took it (the
robot server's answer to ``drive`` says when, in the world's time; a server that does
not say is taken to have taken it as long after the last reading as the driver's own
clock says). A command that came late in the interval drove only the end of it: named
as the interval's command, it is the step response of a robot told to turn that
turned the other way most of the interval (a monitor read 0.5 rad/s of a standby
robot's turn, the one its control system gave it on arrival, as its motors failing).
``drove`` gives the same commands one by one, each with the world's time the robot
took it, for a monitor that follows the robot's response through them: under
acceleration limits the response to a mean of commands is not the mean of their
responses (a robot turning one way, told late in a long step to turn the other, had
0.2 rad/s left of the first turn that the mean did not give it, for as long as the
limits took to reverse it: a false motors alarm). A step's outputs are written
``applied``, ``drove``, ``gps``, ``sonar``, ``odometry``, ``clock``: the pose before the
reading taken there, and the clock last. A command is sent to the robot
as it comes, not at the driver's next period.

A command holds only ``command_timeout`` seconds (1 s; 0: for good), as ROS's
diff_drive_controller's ``cmd_vel_timeout``: when no new command has come for that
long (its controller hung, failed, was removed or cut off), the driver stops the robot
at its next period, once, sets ``stale`` and says so in the log, and the next command
drives it again. The robot server's watchdog does not cover this: the driver's reading
every period feeds it, whatever the controller does. A controller must therefore write
its command at least that often (every shipped one writes it every step or decision:
0.1 to 0.2 s); one that writes only on change (an arbiter, teleoperation, "drive until
told") needs ``command_timeout = 0``. A driver set up anew (moved, swapped, restarted:
the one that let go stopped the robot) or re-pointed sends the command its input holds
at its first period, unless it is older than ``command_timeout`` (``commanded_at``, in
its state, says when it came).
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from agents.limits import SECONDS, out_of_limits, whole
from pb3a import Driver, Input, InputPort, Output, RuntimeCancelled
from pb3a.model.module import StateRefused, reflective
from pb3a.throttle import Throttle

SILENT_STOP_S = 0.1          # how long a silent robot's stop is waited for, when let go
SAY_EVERY_S = 10.0           # a line of one kind is logged at most this often (the rest counted)

log = logging.getLogger("agents.robot_driver")

class RobotDriver(Driver):
    """Velocity command in; sonar, odometry, gps, clock and camera out, every
    ``period`` (or, in lock-step, after every command)."""

    command = Input(np.ndarray, shape=(2,), dtype="float64")   # v (m/s), w (rad/s)
    sonar = Output(np.ndarray, shape=(16,), dtype="float64")
    odometry = Output(np.ndarray, shape=(3,), dtype="float64")
    gps = Output(np.ndarray, shape=(3,), dtype="float64")
    clock = Output(float)        # the world's time of the readings (s)
    applied = Output(np.ndarray, shape=(2,), dtype="float64")   # what drove the robot up to
                                                                # these readings (v, w)
    # the same command by command: a row (the world's time it took it, v, w) each, the
    # first the one in force at the last reading (from then on)
    drove = Output(np.ndarray, dtype="float64")
    camera = Output(list)
    # once per onset, when the robot has not answered ``silent_after`` requests in a
    # row: {"fault": "robot_link", "probability": 1.0, "detail", "at"}, as a monitor's
    failure = Output(dict)
    period = 0.1
    with_camera = False          # the camera costs a request more per period
    enabled = True               # False: keep the robot standing, ignore commands
    lockstep_s = 0.0             # > 0: each command advances a lock-step world this long
    failures = 0                 # requests the robot did not answer
    last_error = ""
    silent_after = 5             # requests in a row without an answer that make a failure
    silent = 0                   # requests in a row the robot has not answered
    command_timeout = 1.0        # s a command holds without a new one (0: for good)
    stale = False                # the robot was stopped: no command came for command_timeout
    stale_stops = 0              # times it was
    commanded_at = 0.0           # (time.time()) when the last command came; 0: none yet

    def setup(self) -> None:
        # (a class's own, which no set_state saw; RobotDriver's rule alone: a resource of
        # the class's that no address is, is a silent robot, a fault the remedy acts on)
        wrong = _own_problems(type(self).__name__, {"silent_after": self.silent_after,
                                                    "command_timeout": self.command_timeout})
        if wrong:
            raise StateRefused(wrong)
        self._read_at = 0.0      # (monotonic) when readings were last written
        self._in_force = np.zeros(2)     # the command the robot runs on now
        self._since: float | None = None         # the world's time of the last reading
        # the commands the robot ran on since then: (world time it took each, command),
        # the first the one in force at the last reading
        self._drove: list[tuple[float, np.ndarray]] = []
        # (monotonic) when the last command came: a driver set up anew (moved, swapped)
        # takes it from its state, whose clock is the wall's
        self._commanded_at: float | None = None if not self.commanded_at else \
            time.monotonic() - max(0.0, time.time() - self.commanded_at)
        self._stops_said = Throttle(SAY_EVERY_S)
        self._silences_said = Throttle(SAY_EVERY_S)
        self._telling = False    # the robot's silence now was said in the log: so is its end
        # The command its input holds, sent again at the first period: the driver that
        # let go of the robot (moved, swapped, restarted) stopped it, and a controller
        # that writes only on change would never move it again.
        self._unsent: np.ndarray | None = self._held()   # one the robot has not taken yet

    @classmethod
    def state_problems(cls, state: dict[str, Any]) -> list[str]:
        """What ``Driver`` refuses, a ``silent_after`` that is not a whole number of
        requests, 1 or more (with 0 a silent robot was never said: its count starts at 1),
        and a ``command_timeout`` that is not a number of seconds, 0 or more."""
        return super().state_problems(state) + _own_problems(cls.__name__, state)

    @reflective                 # (it takes the fields Module's does: they are checked)
    def set_state(self, state: dict[str, Any]) -> None:
        """Set state (what ``state_problems`` refuses is refused, nothing set); a running
        driver re-pointed at another robot reads it at once, rather than at its next
        period (a control system handed to a standby robot sees that robot a period
        sooner)."""
        repointed = state.get("resource", self.resource) != self.resource
        super().set_state(state)
        if repointed and "silent" not in state:
            self.silent = 0          # the old robot's silence: the new one is judged anew
        if repointed and "_read_at" in vars(self):
            self._since, self._drove = None, []  # (another robot, maybe another clock)
            self._unsent = self._held()  # the new robot has not taken the one in force yet
            self._serve(self._unsent, advance=0.0)

    def step(self) -> None:
        self._stop_if_stale()
        if self.lockstep_s > 0 and time.monotonic() - self._read_at < self.period:
            return               # lock-step: commands drive it (see on_input)
        self._serve(self._unsent, advance=0.0)

    def on_input(self, port: InputPort) -> None:
        command = self._checked(port.read())
        self._commanded_at, self.commanded_at, self.stale = time.monotonic(), time.time(), False
        if self.lockstep_s > 0:
            self._serve(command, advance=self.lockstep_s)
            return
        # A command is sent as it comes, not at the next period: waiting for the
        # period would add up to one (0.1 s) to the loop's latency, which a robot with
        # inertia turns into collisions. A command the robot did not take is sent
        # again with the next period's reading.
        if not self.enabled:
            return               # ignored: every period tells the robot to stop
        self._unsent = command
        if self.silent:
            # A robot that did not answer at the last period is tried at the next one
            # only: each try may last the whole request timeout, and with a command
            # every period the driver's lock would never be free (for a move, say).
            return
        try:
            self._apply(self._unsent)
        except RuntimeCancelled:
            return               # the runtime stops the driver: sent again by the next one
        except (RuntimeError, OSError) as exc:
            self._unanswered(exc)

    def _held(self) -> np.ndarray | None:
        """The command the ``command`` input holds, for a robot that has not taken it, or
        None: it holds none, or one older than ``command_timeout``, which is not sent
        again (the robot stands, ``stale``, as the timeout would have left it)."""
        if not self.command.has_value:
            return None
        held = self._checked(self.command.read())
        now = time.monotonic()
        if self._commanded_at is None:
            self._commanded_at = now        # (its age unknown: the timeout counts from now)
        elif self.command_timeout and now - self._commanded_at > self.command_timeout:
            self.stale = True
            return None
        return held

    def _stop_if_stale(self) -> None:
        """Stop the robot (at this period: ``_unsent``) if no command has come for
        ``command_timeout`` s, once until the next comes, and say so (``_say``)."""
        if (not self.command_timeout or self.stale or not self.enabled
                or self._commanded_at is None
                or time.monotonic() - self._commanded_at <= self.command_timeout):
            return
        self.stale, self.stale_stops = True, self.stale_stops + 1
        self._unsent = np.zeros(2)      # (sent again at the next period if not taken)
        _say(self._stops_said, f"{type(self).__name__}: no command for "
             f"{self.command_timeout:g} s (its controller hung, failed or gone?): the "
             f"robot at {self.resource} is stopped until the next one comes")

    def _checked(self, command: np.ndarray) -> np.ndarray:
        """``command``, or a stop where it is not finite: the robot refuses it, so sent on
        it would leave the robot on the last command and the driver resending it every
        period, reading nothing. Counted, and said in ``last_error``."""
        if np.isfinite(command).all():
            return command
        self.failures += 1
        self.last_error = (f"command ({', '.join(map(str, command.tolist()))}) is not "
                           "finite: the robot is stopped")
        return np.zeros(2)

    def _apply(self, command: np.ndarray | None) -> None:
        """Drive by ``command`` (none: the last one holds), or stop a disabled robot."""
        if not self.enabled:
            self._taken(np.zeros(2), self.request("stop"))
        elif command is not None:
            self._taken(command, self.request("drive", v=float(command[0]),
                                              w=float(command[1])))

    def _taken(self, command: np.ndarray, answer: Any = None) -> None:
        """The robot runs on ``command`` now (since the world's time the robot server's
        ``answer`` gives, if it gives one), nothing is left to send."""
        self._in_force = np.array(command, dtype=np.float64)
        self._unsent = None
        if self._since is None:
            return                   # no reading yet: no interval to account for
        at = answer.get("time") if isinstance(answer, dict) else None
        if not isinstance(at, int | float) or not np.isfinite(at):
            at = self._since + (time.monotonic() - self._read_at)
        self._drove.append((float(at), self._in_force))

    def _applied(self, now: float, before: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What drove the robot from the last reading to one at the world's time ``now``:
        the commands it ran on, each weighted by how long, and each with the time it
        took it (``drove``'s rows, the first from the last reading on); ``before`` (the
        command in force when this reading was asked for) when no time has passed, or
        at the first reading."""
        since, drove = self._since, self._drove
        self._since, self._drove = now, [(now, self._in_force)]
        if since is None or not now > since or not drove:
            return before, np.array([[now, *before]])
        starts = np.maximum.accumulate(np.clip([at for at, _ in drove], since, now))
        commands = np.array([command for _, command in drove])
        lasted = np.diff([*starts, now])
        return (np.array(lasted @ commands) / (now - since),
                np.column_stack([starts, commands]))

    def _cycle(self, command: np.ndarray | None, advance: float) -> dict[str, Any]:
        """Drive by ``command``, advance a lock-step world and read the robot, in one
        request rather than three (a simulation decides as fast as they go round)."""
        if command is None or not self.enabled:
            self._apply(command)                 # the last command holds, or stop
            return self.request("cycle", dt=advance)
        answer = self.request("cycle", dt=advance, v=float(command[0]), w=float(command[1]))
        self._taken(command)
        return answer

    def _serve(self, command: np.ndarray | None, advance: float) -> None:
        """Apply ``command`` (see ``_apply``), advance a lock-step world, and write the
        readings; a robot that does not answer is counted."""
        before = self._in_force
        try:
            if advance:
                answer = self._cycle(command, advance)
                before = self._in_force          # (the world moved under the new one)
                self._since = None               # (it did, all the step long)
            else:
                self._apply(command)
                answer = self.request("sensors")
            blobs = self.request("camera") if self.with_camera else None
        except RuntimeCancelled:
            return               # the runtime stops the driver (a move, a swap): not silence
        except (RuntimeError, OSError) as exc:
            self._unanswered(exc)
            return
        if self.silent and self._telling:
            log.warning("%s: the robot at %s answers again, after %d unanswered requests",
                        type(self).__name__, self.resource, self.silent)
        self.silent, self._telling = 0, False
        sensed = {key: np.asarray(answer[key], dtype=np.float64)
                  for key in ("sonar", "odometry", "gps")}
        self._read_at = time.monotonic()
        applied, drove = self._applied(float(answer["time"]), before)
        # In this order: a consumer that takes the pose at each reading (a mapper) has
        # the reading's own pose by then, and one that waits for a whole step's readings
        # (a monitor, a learner) waits for ``clock``, written last.
        self.applied.write(applied)
        self.drove.write(drove)
        self.gps.write(sensed["gps"])
        self.sonar.write(sensed["sonar"])
        self.odometry.write(sensed["odometry"])
        self.clock.write(float(answer["time"]))
        if blobs is not None:
            self.camera.write(blobs)

    def _unanswered(self, exc: Exception) -> None:
        """A request the robot did not answer (a period's, or a command sent as it
        came): counted, and said on ``failure`` at the ``silent_after``-th in a row.
        A command's counts too: up to two of them, each waiting out the deadline, could
        come before the first period's, and detection took 5, 7 or 9 s at random."""
        self.failures += 1
        self.last_error = str(exc)
        self.silent += 1
        # Said in the log too, at its first request and as it is said on failure (a
        # driver whose robot was never reached ran with no error and no line: only its
        # state told), once every SAY_EVERY_S at most for a robot that comes and goes
        if self.silent == 1 and self.silent_after > 1:
            self._telling = _say(self._silences_said, f"{exc}; tried again at each period, "
                                 "said on failure (robot_link) after "
                                 f"{self.silent_after} unanswered requests in a row")
        if self.silent == self.silent_after:          # said once, until it answers again
            self.failure.write({"fault": "robot_link", "probability": 1.0,
                                "detail": {"resource": self.resource,
                                           "unanswered": self.silent, "error": str(exc)},
                                "at": time.time()})
            said = (f"{type(self).__name__}: the robot at {self.resource} has not answered "
                    f"{self.silent} requests in a row, said on failure (robot_link): {exc}")
            if self._telling:
                log.warning("%s", said)
            else:
                self._telling = _say(self._silences_said, said)

    def release(self, client: Any) -> None:
        # Leave the robot standing. One that did not answer at the last period is told
        # too, but not waited for long: a move away from a robot whose server died
        # (its teardown runs this) would wait the whole timeout.
        client.call("stop", min(self.timeout, SILENT_STOP_S) if self.silent else self.timeout)


def _say(kind: Throttle, message: str) -> bool:
    """Log warning ``message`` unless ``kind`` holds it back (one of its kind was logged
    less than ``SAY_EVERY_S`` ago); whether it was. The next one logged says how many
    were held back (a controller that writes every 1.5 s against a 1 s timeout would log
    a stop every 1.5 s)."""
    held = kind.let(time.monotonic())
    if held is None:
        return False
    log.warning("%s%s", message, f" ({held} more like it since the last said)" if held else "")
    return True


def _own_problems(name: str, state: dict[str, Any]) -> list[str]:
    """``RobotDriver.state_problems``'s own rules, for class ``name``: those of the fields
    ``state`` gives."""
    problems = []
    requests = state.get("silent_after", 1)
    if not whole(requests, 1):
        problems.append(f"{name}'s silent_after must be a whole number of requests, 1 or "
                        f"more, got {requests!r}")
    problems += [f"{name}'s {problem} (0: a command holds for good)" for problem in
                 out_of_limits({"command_timeout": SECONDS}, state)]
    return problems
