"""``RobotDriver`` on its own, against a fake robot server: commands, sensors, the
world's clock, stopping safely, and lock-step."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import agents.robot_driver
import pb3a.model.driver
from agents.robot_driver import RobotDriver
from pb3a import RuntimeCancelled, RuntimeFailure, RuntimeTimeout
from pb3a.testing import ModuleHarness


class FakeRobotServer:
    """A robot server's client: records requests, answers ``sensors`` (and
    ``cycle``) with the time of a world that ``advance`` (and ``cycle``) moves on."""

    requests: list[tuple[str, dict[str, Any]]] = []
    time = 0.0
    ungreeted = False

    def __init__(self, key: Any, address: str, **options: Any) -> None:
        self.address = address

    def call(self, op: str, timeout: float, **args: Any) -> Any:
        self.requests.append((op, args))
        if not np.isfinite([args.get("v", 0.0), args.get("w", 0.0)]).all():
            raise RuntimeFailure(f"drive({args['v']}, {args['w']}) needs finite speeds")
        if op in ("advance", "cycle"):
            FakeRobotServer.time += args["dt"]
            if op == "advance":
                return FakeRobotServer.time
        if op in ("sensors", "cycle"):
            return {"time": FakeRobotServer.time, "sonar": [1.0] * 16, "odometry": [0.0] * 3,
                    "gps": [0.0] * 3, "velocity": [0.0] * 3}
        return None

    def close(self) -> None:
        pass


@pytest.fixture
def robot(monkeypatch) -> type[FakeRobotServer]:
    monkeypatch.setattr(pb3a.model.driver, "ControlClient", FakeRobotServer)
    # (its robots' hosts are names no resolver knows: the fake is reached all the same)
    monkeypatch.setattr(pb3a.model.driver, "unknown_host", lambda address, timeout: None)
    monkeypatch.setattr(FakeRobotServer, "requests", [])
    monkeypatch.setattr(FakeRobotServer, "time", 0.0)
    return FakeRobotServer


class Clock:
    """The driver's clocks, moved on by the test: ``monotonic`` and ``time`` (a wall
    clock, for what the driver keeps in its state)."""

    def __init__(self) -> None:
        self.now = 1_000.0

    def monotonic(self) -> float:
        return self.now

    def time(self) -> float:
        return self.now + 1.7e9


@pytest.fixture
def clock(monkeypatch) -> Clock:
    clock = Clock()
    monkeypatch.setattr(agents.robot_driver, "time", clock)
    return clock


def ops(robot: type[FakeRobotServer]) -> list[str]:
    return [op for op, _ in robot.requests]


def failing(monkeypatch, error: type[Exception], record: bool = False) -> list[bool]:
    """Make the fake robot raise ``error`` for every request while the flag returned is
    up (it is at first: ``flag[0] = False`` lets requests through); with ``record``, the
    failed requests are recorded too."""
    answer, down = FakeRobotServer.call, [True]

    def call(self, op: str, timeout: float, **args: Any) -> Any:
        if down[0]:
            if record:
                FakeRobotServer.requests.append((op, args))
            raise error(f"{self.address} did not answer {op!r}")
        return answer(self, op, timeout, **args)
    monkeypatch.setattr(FakeRobotServer, "call", call)
    return down


def test_a_command_drives_the_robot_as_it_comes_and_each_period_writes_the_readings(
        robot) -> None:
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400"})
    harness.step()                                  # no command yet: only sensing
    harness.feed("command", np.array([0.4, 0.1]))
    assert ops(robot) == ["sensors", "drive"]       # at once, not at the next period
    assert robot.requests[1][1] == {"v": 0.4, "w": 0.1}
    harness.step()
    assert ops(robot) == ["sensors", "drive", "sensors"]
    assert len(harness.written["sonar"]) == len(harness.written["clock"]) == 2
    # each reading names the command that moved the robot up to it
    assert [list(a) for a in harness.written["applied"]] == [[0.0, 0.0], [0.4, 0.1]]


def test_a_command_the_robot_did_not_take_is_sent_again_with_the_next_reading(
        robot, monkeypatch) -> None:
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400"})
    answer = FakeRobotServer.call

    def lost(self, op: str, timeout: float, **args: Any) -> Any:
        if op == "drive" and not any(o == "drive" for o, _ in robot.requests):
            robot.requests.append((op, args))
            raise RuntimeError("robot did not answer")
        return answer(self, op, timeout, **args)

    monkeypatch.setattr(FakeRobotServer, "call", lost)
    harness.feed("command", np.array([0.2, 0.0]))
    assert harness.module.failures == 1
    harness.step()
    assert ops(robot) == ["drive", "drive", "sensors"]
    assert list(harness.last("applied")) == [0.0, 0.0]      # it moved only from now on
    harness.step()
    assert ops(robot)[3:] == ["sensors"] and list(harness.last("applied")) == [0.2, 0.0]


def test_a_disabled_driver_keeps_its_robot_standing(robot) -> None:
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400"})
    harness.feed("command", np.array([0.4, 0.1]))
    harness.step()
    assert ops(robot) == ["drive", "sensors"]
    harness.module.set_state({"enabled": False})
    robot.requests.clear()
    harness.feed("command", np.array([0.5, 0.0]))
    harness.step(2)
    assert ops(robot) == ["stop", "sensors"] * 2
    assert len(harness.written["sonar"]) == 3                 # still sensing


def test_in_lockstep_every_command_advances_the_world_once(robot) -> None:
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400",
                                                "lockstep_s": 0.25})
    harness.step()                   # the controller waits for a first reading: it gets one
    assert ops(robot) == ["sensors"] and harness.written["clock"] == [0.0]
    for _ in range(3):
        harness.feed("command", np.array([0.3, 0.0]))
    harness.step()                   # commands come: the period adds nothing
    # each in one request: drive, advance, read
    assert robot.requests[1:] == [("cycle", {"dt": 0.25, "v": 0.3, "w": 0.0})] * 3
    assert harness.written["clock"] == [0.0, 0.25, 0.5, 0.75]
    assert [list(a) for a in harness.written["applied"][1:]] == [[0.3, 0.0]] * 3
    harness.module.set_state({"enabled": False})       # stopped, and the world goes on
    robot.requests.clear()
    harness.feed("command", np.array([0.3, 0.0]))
    assert ops(robot) == ["stop", "cycle"] and robot.requests[1][1] == {"dt": 0.25}
    assert harness.written["clock"][-1] == 1.0
    assert list(harness.written["applied"][-1]) == [0.0, 0.0]


def test_a_running_driver_re_pointed_at_another_robot_reads_it_at_once(robot) -> None:
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400"})
    harness.step()
    harness.feed("command", np.array([0.3, 0.0]))
    harness.module.set_state({"resource": "tcp://standby:7400"})
    assert len(harness.written["sonar"]) == 2                 # no step in between
    # the old robot is stopped; the new one takes the command in force
    assert ops(robot) == ["sensors", "drive", "stop", "drive", "sensors"]
    harness.module.set_state({"enabled": True})                # not a re-point: no reading
    assert len(harness.written["sonar"]) == 2


@pytest.mark.parametrize("lockstep_s", [0.0, 0.25])
def test_a_command_that_is_not_finite_stops_the_robot_and_the_driver_senses_on(
        robot, lockstep_s) -> None:
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400",
                                                "lockstep_s": lockstep_s})
    harness.feed("command", np.array([0.4, 0.1]))
    harness.feed("command", np.array([np.nan, 0.1]))          # a controller gone wrong
    assert harness.module.failures == 1
    assert "command (nan, 0.1) is not finite: the robot is stopped" in harness.module.last_error
    assert robot.requests[1][1] == {"v": 0.0, "w": 0.0, **({"dt": 0.25} if lockstep_s else {})}
    robot.requests.clear()
    harness.module.set_state({"lockstep_s": 0.0})
    harness.step(2)                        # (before, each period resent NaN and read nothing)
    assert ops(robot) == ["sensors"] * 2 and harness.module.failures == 1
    assert list(harness.last("applied")) == [0.0, 0.0]


def test_commands_to_a_silent_robot_wait_for_the_next_period(robot, monkeypatch) -> None:
    """Each command was sent as it came, each waiting out the request's timeout: with
    the robot server dead and a command every period, the driver's lock was never
    free, and the move away from that robot failed ("busy in a call for 5 s")."""
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400"})
    down = failing(monkeypatch, RuntimeError, record=True)
    harness.step()                                  # the robot is silent
    harness.feed("command", np.array([0.1, 0.0]))
    harness.feed("command", np.array([0.3, 0.0]))
    assert ops(robot) == ["sensors"]                # not tried as they came
    down[0] = False
    harness.step()                                  # the period tries the latest one
    assert robot.requests[1:] == [("drive", {"v": 0.3, "w": 0.0}), ("sensors", {})]
    harness.feed("command", np.array([0.2, 0.0]))  # it answers again: sent at once
    assert robot.requests[-1] == ("drive", {"v": 0.2, "w": 0.0})


def test_a_request_the_runtime_cancels_is_not_taken_for_a_silent_robot(robot,
                                                                       monkeypatch) -> None:
    """A pause, swap or move cancels the driver's request in progress; it was counted as
    the robot's silence (a failure, silent 1), so the next command waited for the next
    period, and a few in a row made a false robot_link failure."""
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400",
                                                "silent_after": 1})
    cancel = failing(monkeypatch, RuntimeCancelled)      # (a pause, say)
    harness.step()
    harness.feed("command", np.array([0.1, 0.0]))
    module = harness.module
    assert (module.silent, module.failures, module.last_error) == (0, 0, "")
    assert harness.written["failure"] == []
    cancel[0] = False
    harness.feed("command", np.array([0.3, 0.0]))       # sent as it comes
    assert robot.requests == [("drive", {"v": 0.3, "w": 0.0})]


def test_a_silent_robot_is_told_to_stop_when_let_go_but_not_waited_for_long(
        robot, monkeypatch) -> None:
    """Its teardown (a move away from it, a re-point) waited the whole request timeout
    for the stop of a robot whose server had died: a move's capture took 1 s."""
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400"})
    harness.step()
    waited: list[tuple[str, float]] = []
    answer, down = FakeRobotServer.call, [False]

    def gone(self, op: str, timeout: float, **args: Any) -> Any:
        waited.append((op, timeout))
        if down[0]:
            raise RuntimeTimeout(f"{self.address} did not answer {op!r}")
        return answer(self, op, timeout, **args)
    monkeypatch.setattr(FakeRobotServer, "call", gone)
    harness.module.set_state({"resource": "tcp://robot:7401"})     # let go while it answers
    assert waited[0] == ("stop", 1.0)
    down[0] = True
    harness.step()                                  # silent now
    waited.clear()
    harness.module.teardown()
    assert waited == [("stop", 0.1)]


def test_a_robot_that_stops_answering_is_said_once_per_onset_on_failure(
        robot, monkeypatch) -> None:
    """The driver only counted its failures: with the robot server gone, nothing was
    written, so nothing downstream (the monitor samples readings) ever heard of it."""
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400",
                                                "silent_after": 3})
    down = failing(monkeypatch, RuntimeError)
    harness.step(5)
    failure, = harness.written["failure"]
    assert failure["fault"] == "robot_link" and failure["detail"]["unanswered"] == 3
    assert "did not answer 'sensors'" in failure["detail"]["error"]
    down[0] = False
    harness.step()                                  # it answers: a new onset may come
    down[0] = True
    harness.step(3)
    assert len(harness.written["failure"]) == 2
    with pytest.raises(ValueError, match="silent_after must be a whole number"):
        harness.module.set_state({"silent_after": 0})


def test_a_command_the_robot_does_not_take_counts_toward_its_silence(
        robot, monkeypatch) -> None:
    """Commands sent as they come, each waiting out its deadline before the first period
    found the robot silent, were not counted: detection took 5, 7 or 9 of those 1 s
    deadlines, at random (the mapping scenario's bound of 8 s failed now and then)."""
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400",
                                                "silent_after": 3})
    failing(monkeypatch, RuntimeError)
    harness.feed("command", np.array([0.3, 0.0]))       # tried as it comes: unanswered
    assert harness.state["silent"] == 1
    harness.feed("command", np.array([0.2, 0.0]))       # silent: kept for the period
    assert harness.state["silent"] == 1
    harness.step(2)
    failure, = harness.written["failure"]
    assert failure["detail"]["unanswered"] == 3 and harness.state["failures"] == 3


def test_a_re_pointed_driver_judges_its_new_robot_anew(robot, monkeypatch) -> None:
    """The old robot's silence carried over: a dead new robot was said after fewer of
    its own requests, or never, if the old one had been said already."""
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400",
                                                "silent_after": 3})
    failing(monkeypatch, RuntimeTimeout)        # (the old one's stop too, as it is let go)
    harness.step(3)                                 # the old robot said, once
    harness.module.set_state({"resource": "tcp://standby:7400"})   # dead too
    assert harness.state["silent"] == 1             # the new robot's first request
    harness.step(2)
    old, new = harness.written["failure"]
    assert (old["detail"]["resource"], new["detail"]["resource"]) == (
        "tcp://robot:7400", "tcp://standby:7400")


def test_a_resource_that_is_not_an_address_is_refused_or_taken_for_a_silent_robot(
        robot) -> None:
    """'127.0.0.1:7400' (no tcp://) was kept: every request failed with ZeroMQ's
    "Invalid argument", counted as no silence, so no robot_link failure ever came."""
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400"})
    with pytest.raises(ValueError, match=r"RobotDriver's resource must be a string "
                                         r"tcp://HOST:PORT .*got '10\.0\.0\.7:7400'"):
        harness.module.set_state({"resource": "10.0.0.7:7400"})
    with pytest.raises(ValueError, match=r"'tcp://\*:7400' names every interface"):
        harness.module.set_state({"resource": "tcp://*:7400"})     # (what a listener binds)
    assert harness.state["resource"] == "tcp://robot:7400"

    class Misaddressed(RobotDriver):
        resource = "robot:7400"                 # a class's own: no set_state saw it
        silent_after = 2

    harness = ModuleHarness(Misaddressed)
    harness.step(3)
    failure, = harness.written["failure"]
    assert failure["fault"] == "robot_link"
    assert "resource must be a string tcp://HOST:PORT" in failure["detail"]["error"]


def test_a_command_not_renewed_within_command_timeout_stops_the_robot_once(
        robot, clock, caplog) -> None:
    """A controller that hung, failed or was removed left its robot driving on its last
    command for good: each period's reading fed the robot server's watchdog (a reviewer's
    robot spun for 8 s and more after its controller's worker was killed)."""
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400"})
    harness.feed("command", np.array([0.0, 0.5]))
    clock.now += 0.9
    harness.step()                                  # within the timeout (1 s): drives on
    assert ops(robot) == ["drive", "sensors"] and not harness.state["stale"]
    clock.now += 0.2
    caplog.set_level("WARNING", logger="agents.robot_driver")
    harness.step(3)                                 # 1.1 s without a command: stopped, once
    assert robot.requests[2:] == [("drive", {"v": 0.0, "w": 0.0}), ("sensors", {})] + [
        ("sensors", {})] * 2
    assert (harness.state["stale"], harness.state["stale_stops"]) == (True, 1)
    assert list(harness.last("applied")) == [0.0, 0.0]
    said, = [record.getMessage() for record in caplog.records]
    assert "no command for 1 s" in said and "tcp://robot:7400 is stopped" in said
    robot.requests.clear()
    harness.feed("command", np.array([0.0, 0.5]))   # a new one drives it again
    assert robot.requests == [("drive", {"v": 0.0, "w": 0.5})] and not harness.state["stale"]
    clock.now += 1.5
    harness.step()                                  # stopped again: logged 10 s apart at most
    assert harness.state["stale_stops"] == 2 and len(caplog.records) == 1
    clock.now += 10.0
    harness.feed("command", np.array([0.0, 0.5]))
    clock.now += 1.5
    harness.step()
    assert "(1 more like it since the last said)" in caplog.records[-1].getMessage()


def test_a_command_timeout_of_0_holds_a_command_for_good(robot, clock) -> None:
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400",
                                                "command_timeout": 0})
    harness.feed("command", np.array([0.0, 0.5]))
    clock.now += 3600.0
    harness.step()
    assert ops(robot) == ["drive", "sensors"] and harness.state["stale_stops"] == 0
    for wrong in (-1.0, None, float("inf")):
        with pytest.raises(ValueError, match=r"command_timeout must be a number of seconds, "
                                             r"0 or more, got .* \(0: a command holds for"):
            harness.module.set_state({"command_timeout": wrong})


def test_a_driver_set_up_anew_sends_its_held_command_again_unless_it_is_stale(
        robot, clock) -> None:
    """A driver moved, swapped or restarted stopped its robot as it let go (``release``)
    and forgot the command its input still held: a controller that writes only on change
    left the robot standing for good. One older than ``command_timeout`` is not sent (the
    timeout would have stopped the robot)."""
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400"})
    module = harness.module
    harness.feed("command", np.array([0.0, 0.5]))
    for age, sent in ((0.5, True), (1.5, False)):
        clock.now += age
        module.teardown()                           # let go: stopped
        module.set_state(module.get_state())        # (its state carried, as a move does)
        module.setup()                              # the input holds the command still
        robot.requests.clear()
        harness.step()
        assert robot.requests[0] == (("drive", {"v": 0.0, "w": 0.5}) if sent
                                     else ("sensors", {}))
        assert harness.state["stale"] is not sent
    module.set_state({"resource": "tcp://standby:7400"})     # re-pointed: stale, not sent
    assert ("drive", {"v": 0.0, "w": 0.5}) not in robot.requests[2:]


def test_a_robot_that_does_not_answer_is_said_in_the_log_and_so_is_its_answer_again(
        robot, clock, monkeypatch, caplog) -> None:
    """A driver that could not reach its robot (a wrong address, the world not started,
    killed mid-run) ran with no error and logged nothing: only its state told."""
    caplog.set_level("WARNING", logger="agents.robot_driver")
    harness = ModuleHarness(RobotDriver, state={"resource": "tcp://robot:7400",
                                                "silent_after": 3})
    down = failing(monkeypatch, RuntimeTimeout)
    harness.step()
    first, = [record.getMessage() for record in caplog.records]
    assert "tcp://robot:7400 did not answer 'sensors'" in first and "after 3 " in first
    harness.step(4)                                 # silent: said once more, at the third
    assert len(caplog.records) == 2
    assert "has not answered 3 requests in a row, said on failure (robot_link)" in \
        caplog.records[1].getMessage()
    down[0] = False
    harness.step()
    assert caplog.records[2].getMessage() == ("RobotDriver: the robot at tcp://robot:7400 "
                                              "answers again, after 5 unanswered requests")
    down[0] = True                                  # it comes and goes: 10 s apart at most
    harness.step()
    down[0] = False
    harness.step()
    assert len(caplog.records) == 3
    clock.now += 10.0
    down[0] = True
    harness.step()
    assert "(1 more like it since the last said)" in caplog.records[3].getMessage()
