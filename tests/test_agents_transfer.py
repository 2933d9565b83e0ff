"""``TransferAgent`` on its own: it decides on the learner's success rate, moves the
learner's macro without waiting, the driver re-pointed and the learner set for the
robot on arrival, and reports once the move has ended."""

from __future__ import annotations

import re
from typing import Any

import cloudpickle
import pytest

from agents.transfer import KEEP_OUTCOMES, TransferAgent, success_rate
from pb3a import ConfigError, MigrationReport, ModuleNotFound, RuntimeFailure, RuntimeTimeout
from pb3a.testing import ModuleHarness


class Move:
    """What a non-blocking migrate gives an agent; the test says when it ends."""

    def __init__(self) -> None:
        self.ended = False
        self.failure = ""           # the move ends in this error
        self.error: Exception | None = None     # or in this one, as it is

    def wait(self, timeout: float) -> bool:
        return self.ended

    def result(self, timeout: float) -> MigrationReport:
        assert self.ended
        if self.error is not None:
            raise self.error
        if self.failure:
            raise RuntimeFailure(self.failure)
        return MigrationReport("brain", "ws", "robot", 0.02, 1000, 4, prepare_s=0.09)


class Runtime:
    def __init__(self) -> None:
        self.calls: list[tuple] = []
        self.move = Move()
        self.driver = {"lockstep_s": 0.2}

    def state(self, name: str) -> dict:
        return dict(self.driver)

    def migrate(self, name: str, to: str, *, wait: bool = True,
                state: dict | None = None) -> Move:
        self.calls.append(("migrate", name, to, wait, state))
        return self.move

    def set_state(self, name: str, values: dict) -> None:
        self.calls.append(("set_state", name, values))
        self.driver.update(values)

    def where(self, name: str) -> str:
        if name not in ("brain/driver", "brain/learner"):
            raise ModuleNotFound(f"no module {name!r} in system 'lab'")
        return "robot" if self.move.ended else "sim"


STATE = {"to_node": "robot", "to_resource": "tcp://127.0.0.1:7421", "window": 10,
         "threshold": 0.8, "min_episodes": 10, "learner_state": {"epsilon": 0.05}}


def test_success_rate_counts_the_last_window() -> None:
    assert success_rate([False] * 5 + [True] * 4, 4) == 1.0
    assert success_rate([True, False], 10) == 0.5
    assert success_rate([], 3) == 0.0


WRONG = pytest.mark.parametrize(("wrong", "named"), [
    ({"window": 0}, "window must be a whole number of episodes, 1 or more, got 0"),
    ({"window": 2.5}, "window must be a whole number of episodes, 1 or more, got 2.5"),
    ({"threshold": 1.2}, "threshold must be a success rate from 0 (at once) to 1, got 1.2"),
    ({"threshold": -0.1}, "threshold must be a success rate from 0 (at once) to 1, got -0.1"),
    ({"min_episodes": -1}, "min_episodes must be a whole number, 0 or more, got -1"),
    # (TOML's true was taken as 1)
    ({"min_episodes": True}, "min_episodes must be a whole number, 0 or more, got True"),
    ({"threshold": True}, "threshold must be a success rate from 0 (at once) to 1, got True"),
    ({"to_node": ""}, "to_node must be the name of the hardware robot's node, got ''"),
    ({"to_resource": "127.0.0.1:7421"}, "to_resource, the hardware robot's server, must be "
                                        "a string tcp://HOST:PORT")])


@WRONG
def test_settings_that_could_never_or_always_transfer_are_refused_by_name(
        wrong: dict, named: str) -> None:
    with pytest.raises(ValueError, match=re.escape(named)):
        ModuleHarness(TransferAgent, state={**STATE, **wrong}, runtime=Runtime())


@WRONG
def test_such_a_setting_set_while_it_runs_is_refused_by_name_and_nothing_is_set(
        wrong: dict, named: str) -> None:
    agent = ModuleHarness(TransferAgent, state=STATE, runtime=Runtime())
    with pytest.raises(ValueError, match=re.escape(named)):
        agent.module.set_state({"min_episodes": 3, **wrong})
    assert {name: agent.state[name] for name in STATE} == STATE


def test_it_waits_for_the_success_rate_then_moves_with_the_driver_re_pointed_on_arrival() -> None:
    runtime = Runtime()
    agent = ModuleHarness(TransferAgent, state=STATE, runtime=runtime)
    for success in [False] * 6 + [True] * 7:     # last 10: 7 of 10, not yet
        agent.feed("episode", {"success": success})
    assert runtime.calls == []
    agent.feed("episode", {"success": True})     # 8 of the last 10
    assert runtime.calls == [("set_state", "brain/driver", {"lockstep_s": 0.0}),
                             ("migrate", "brain", "robot", False, {
                                 "brain/driver": {"resource": "tcp://127.0.0.1:7421"},
                                 "brain/learner": {"epsilon": 0.05}})]
    agent.step()                                 # the move has not ended: nothing more
    agent.feed("episode", {"success": True})
    assert len(runtime.calls) == 2 and agent.written["transfer"] == []
    runtime.move.ended = True
    agent.step()
    assert len(runtime.calls) == 2               # nothing left to set once it has moved
    (report,) = agent.written["transfer"]
    assert 0 < report["decided_at"] <= report["moved_at"]
    assert report["success_rate"] >= 0.8
    assert (report["pause_s"], report["prepare_s"]) == (0.02, 0.09)
    assert set(report["phases"]) >= {"capture_s", "restore_s", "start_s"}
    agent.step()
    assert len(runtime.calls) == 2 and len(agent.written["transfer"]) == 1     # once


def test_it_keeps_the_outcomes_its_window_needs_and_counts_every_episode() -> None:
    agent = ModuleHarness(TransferAgent, state={**STATE, "min_episodes": 5000, "window": 20},
                          runtime=Runtime())
    for index in range(KEEP_OUTCOMES + 300):
        agent.feed("episode", {"success": index % 2 == 0})
    assert agent.state["episodes"] == KEEP_OUTCOMES + 300
    assert len(agent.state["outcomes"]) == KEEP_OUTCOMES      # before: one per episode
    agent.module.set_state({"window": KEEP_OUTCOMES + 100})
    agent.feed("episode", {"success": True})
    assert len(agent.state["outcomes"]) == KEEP_OUTCOMES + 1  # growing to the new window


def test_without_a_destination_or_a_learner_it_is_refused_at_setup() -> None:
    """Both were found once learning was done: a destination missing raised at every
    episode from then on, a misspelt learner failed every move."""
    with pytest.raises(ValueError, match="to_node must be the name of the hardware robot's node"):
        ModuleHarness(TransferAgent, state={"min_episodes": 1, "window": 1},
                      runtime=Runtime())
    with pytest.raises(ValueError, match="learner: no module 'brain/lerner'"):
        ModuleHarness(TransferAgent, state={**STATE, "learner": "brain/lerner"},
                      runtime=Runtime())


def test_a_move_the_runtime_refuses_as_asked_is_not_tried_again() -> None:
    """A node the system does not have was asked for again at every episode (56 failed
    moves in 3 s, the simulation's lock-step switched off and on each time)."""
    class NoSuchNode(Runtime):            # (a Pending: the error comes as its result)
        def migrate(self, name: str, to: str, **options: Any) -> Move:
            move = super().migrate(name, to, **options)
            move.ended, move.error = True, ConfigError([
                f"migrate {name}: no node {to!r}; nodes: ws, robot"])
            return move
    runtime = NoSuchNode()
    agent = ModuleHarness(TransferAgent, state={**STATE, "to_node": "robt"}, runtime=runtime)
    for _ in range(10):
        agent.feed("episode", {"success": True})
    agent.step()                                        # the move's end: refused
    for _ in range(20):
        agent.feed("episode", {"success": True})
        agent.step()
    (failed,) = agent.written["transfer"]
    assert "no node 'robt'" in failed["error"] and "no node 'robt'" in agent.state["refused"]
    assert [call[0] for call in runtime.calls].count("migrate") == 1
    assert runtime.driver["lockstep_s"] == 0.2          # the simulation goes on


def test_a_failed_move_gives_the_simulation_back_and_is_tried_again_later() -> None:
    runtime = Runtime()
    agent = ModuleHarness(TransferAgent, state=STATE, runtime=runtime)
    for _ in range(10):
        agent.feed("episode", {"success": True})
    assert runtime.driver["lockstep_s"] == 0.0           # the simulation stopped for the move
    runtime.move.ended, runtime.move.failure = True, "node 'robot' is not up"
    agent.step()                                         # the move failed: said, not raised
    (failed,) = agent.written["transfer"]
    assert "node 'robot' is not up" in failed["error"] and not failed["moved_at"]
    assert runtime.driver["lockstep_s"] == 0.2           # the simulation goes on as it was
    assert agent.state["decided_at"] == 0.0 and agent.state["failed_moves"] == 1
    agent.step()
    assert len(agent.written["transfer"]) == 1           # said once
    runtime.move = Move()
    agent.feed("episode", {"success": True})             # at the next episode: again
    assert runtime.calls[-1][0] == "migrate" and runtime.driver["lockstep_s"] == 0.0
    runtime.move.ended = True
    agent.step()
    assert agent.written["transfer"][-1]["moved_at"] > 0


@pytest.mark.parametrize("arrived", [True, False])
def test_an_agent_restored_while_its_move_was_under_way_finds_out_how_it_ended(
        arrived: bool) -> None:
    """The move's handle is not state: restored from a checkpoint (or moved itself)
    mid-move, the agent neither reported nor decided again, for good."""
    runtime = Runtime()
    agent = ModuleHarness(TransferAgent, state=STATE, runtime=runtime)
    for _ in range(10):
        agent.feed("episode", {"success": True})
    assert agent.state["decided_at"] and not agent.state["moved_at"]
    later = Runtime()
    later.move.ended = arrived
    restored = ModuleHarness(TransferAgent, state=cloudpickle.loads(cloudpickle.dumps(
        agent.state)), runtime=later)
    restored.step()
    transfer, = restored.written["transfer"]
    if arrived:
        assert restored.state["moved_at"] and "error" not in transfer
    else:
        assert "is not on the robot's node" in transfer["error"]
        assert restored.state["failed_moves"] == 1 and not restored.state["decided_at"]


def test_a_runtime_error_as_it_decides_is_a_failed_move_decided_again_later() -> None:
    """A timeout reading the driver's state, after deciding, left the agent decided for
    good: never moving, never deciding again."""
    class Flaky(Runtime):
        failures = 1

        def state(self, name: str) -> dict:
            if self.failures:
                self.failures -= 1
                raise RuntimeTimeout("node busy")
            return super().state(name)
    runtime = Flaky()
    agent = ModuleHarness(TransferAgent, state=STATE, runtime=runtime)
    for _ in range(10):
        agent.feed("episode", {"success": True})
    assert agent.state["failed_moves"] == 1 and "node busy" in agent.written["transfer"][0]["error"]
    # the driver, never stopped, is left running as it was (it was given a lock-step of
    # 0 "back": a world stepped by its driver alone stood still, and the learner with it)
    assert runtime.calls == [] and runtime.driver["lockstep_s"] == 0.2
    agent.feed("episode", {"success": True})
    assert [call[0] for call in runtime.calls].count("migrate") == 1     # decided again
