"""agents.learner: the reactive policy learner learns to reach goals on the simulated
robot, what it learnt gives the hardware robot a head start, it recovers from
collisions, and as a module it carries on from its pickled state."""

from __future__ import annotations

import copy
import math

import cloudpickle
import numpy as np
import pytest

from agents.learner import (
    COLLISION,
    KEEP_EPISODES,
    SUCCESS,
    Parameters,
    PolicyLearner,
    ReactiveLearner,
    success_rate,
)
from pb3a.testing import ModuleHarness
from rave import World

PERIOD = 0.25                       # s: one decision per world step
# the room's corners, 1 m in: the box in the middle stands across both diagonals
GOALS = [[1.0, 1.0], [6.0, 4.0], [6.0, 1.0], [1.0, 4.0]]
TRAINING = 80                       # episodes on the simulated robot
TRIAL = 12                          # episodes on the hardware robot, each way
CLEAR = np.full(16, 5.0)            # nothing within range
MIRRORED = [7, 6, 5, 4, 3, 2, 1, 0, 15, 14, 13, 12, 11, 10, 9, 8]   # ring, left for right


def room(backend: str, seed: int) -> World:
    """A 7 x 5 m room with a 1.2 x 1.0 m box in the middle and a robot "r" (close it)."""
    world = World(size=(7.0, 5.0), seed=seed)
    corners = [(0.0, 0.0), (7.0, 0.0), (7.0, 5.0), (0.0, 5.0)]
    for start, end in zip(corners, corners[1:] + corners[:1], strict=True):
        world.add_wall(start, end)
    world.add_box(center=(3.5, 2.5), size=(1.2, 1.0))
    world.add_robot("r", (1.0, 1.0, 0.0), backend=backend)
    return world


def drive(learner: ReactiveLearner, world: World, episodes: int) -> float:
    """Run ``episodes`` more episodes, one decision per ``PERIOD`` of simulated time;
    the simulated seconds they took."""
    robot, start = world.robot("r"), world.time
    stop = learner.episode_count + episodes
    while learner.episode_count < stop:
        command, _ = learner.decide(robot.sonar(), np.asarray(robot.gps()), world.time)
        robot.drive(*command)
        world.step(PERIOD)
    return world.time - start


@pytest.fixture(scope="module")
def trained() -> tuple[ReactiveLearner, float]:
    """A learner after ``TRAINING`` episodes on the simulated robot, and the simulated
    seconds they took."""
    learner = ReactiveLearner(GOALS, seed=1)
    with room("sim", seed=1) as world:
        seconds = drive(learner, world, TRAINING)
    return learner, seconds


def test_the_learner_comes_to_reach_most_goals_on_the_simulated_robot(
        trained: tuple[ReactiveLearner, float]) -> None:
    learner, seconds = trained
    first, last = success_rate(learner.episodes[:10]), success_rate(learner.episodes, last=20)
    assert last >= 0.8 and last >= first + 0.25, (first, last)
    assert seconds < 40 * 60                     # of simulated time
    assert learner.epsilon < 0.05                # exploration has died down


def test_a_table_learnt_in_simulation_gives_the_hardware_robot_a_head_start(
        trained: tuple[ReactiveLearner, float]) -> None:
    learnt, _ = trained
    rates = {}
    for name, start in (("transferred", {"q": learnt.q.copy(), "epsilon": learnt.epsilon}),
                        ("fresh", {})):
        learner = ReactiveLearner(GOALS, seed=2, **start)
        with room("hardware", seed=2) as world:     # the same noise for both
            drive(learner, world, TRIAL)
        rates[name] = success_rate(learner.episodes)
    assert rates["transferred"] >= 0.5 and rates["transferred"] >= rates["fresh"] + 0.25, rates


def test_after_a_collision_the_robot_backs_up_turns_away_and_goes_for_the_next_goal() -> None:
    learner = ReactiveLearner([[5.0, 0.0], [0.0, 5.0]], seed=3)
    pose = np.zeros(3)
    learner.decide(CLEAR, pose, 0.0)
    blocked = CLEAR.copy()
    blocked[[2, 3]] = 0.2                        # front-left: the nearer side is the left
    command, finished = learner.decide(blocked, pose, 0.25)
    assert finished is not None and finished.outcome == COLLISION and finished.steps == 1
    assert learner.q.min() < 0                   # the penalty was learnt
    assert command.tolist() == [-0.2, 0.0]       # backing up while the bumper is blocked
    command, _ = learner.decide(blocked, pose, 0.5)
    assert command.tolist() == [-0.2, 0.0]
    cleared = CLEAR.copy()
    cleared[[2, 3]] = 0.6                        # the bumper reads clear again
    command, _ = learner.decide(cleared, pose, 0.75)
    assert command[0] == 0.0 and command[1] < 0  # turning right, away from the left
    now, turned = 0.75, 0
    while learner.recovery:
        now += PERIOD
        command, _ = learner.decide(CLEAR, pose, now)
        turned += 1
    assert 2 <= turned <= 6                      # 0.5-1.5 s, then the policy's action
    assert learner.underway["steps"] == 1 and learner.goal_index == 1
    assert [outcome for outcome, _, _ in learner.episodes] == [COLLISION]


def test_its_state_keeps_the_last_episodes_and_counts_them_all() -> None:
    """Its state moves with it and is checkpointed: one entry per episode for as long
    as it learns made both cost more and more."""
    done = [(SUCCESS, 3, 1.0)] * KEEP_EPISODES
    learner = ReactiveLearner([[5.0, 0.0]], seed=3, episodes=list(done),
                              episode_count=KEEP_EPISODES + 500)
    pose = np.zeros(3)
    learner.decide(CLEAR, pose, 0.0)
    blocked = CLEAR.copy()
    blocked[[2, 3]] = 0.2
    _, finished = learner.decide(blocked, pose, 0.25)            # a collision ends it
    assert finished.index == KEEP_EPISODES + 500
    assert learner.episode_count == KEEP_EPISODES + 501
    assert len(learner.episodes) == KEEP_EPISODES and learner.episodes[-1][0] == COLLISION
    assert ReactiveLearner([[5.0, 0.0]], **{   # a state of before: counted by its list
        k: v for k, v in learner.state().items() if k != "episode_count"}).episode_count \
        == KEEP_EPISODES


def test_the_speed_guard_slows_the_robot_as_it_nears_an_obstacle_whatever_it_decided(
        ) -> None:
    ahead_only = {"actions": [[0.3, 0.0]], "mirror": False}
    guarded = ReactiveLearner([[9.0, 0.0]], Parameters.of({**ahead_only, "guard_range": 0.4}))
    unguarded = ReactiveLearner([[9.0, 0.0]], Parameters.of(ahead_only))
    pose, speeds = np.zeros(3), []
    for t, front in enumerate((2.0, 0.6, 0.45, 0.38)):
        sonar = CLEAR.copy()
        sonar[3] = front
        command, _ = guarded.decide(sonar, pose, t * PERIOD)
        speeds.append(round(float(command[0]), 3))
        assert unguarded.decide(sonar, pose, t * PERIOD)[0].tolist() == [0.3, 0.0]
    assert speeds == [0.3, 0.2, 0.05, 0.0]       # 1/s times the range beyond 0.4 m
    sonar = CLEAR.copy()
    sonar[3] = 0.2                               # a collision: backing up is not held
    command, finished = guarded.decide(sonar, pose, 4 * PERIOD)
    assert finished is not None and finished.outcome == COLLISION and command[0] < 0


def test_a_situation_is_which_sectors_are_near_and_where_the_goal_lies() -> None:
    learner = ReactiveLearner(GOALS)
    here = np.array([2.0, 2.0, math.pi / 2])                  # facing +y
    ahead, left, behind, right = ([2.0, 4.0], [0.0, 2.0], [2.0, 0.0], [4.0, 2.0])
    clear = [learner.situation(CLEAR, here, np.array(goal))
             for goal in (ahead, left, behind, right)]
    assert clear == [120, 122, 124, 126]         # every sector clear (15), bearing 0-7
    near = CLEAR.copy()
    near[3] = 0.5                                # front-left (2, 3) near: 15 - 2
    assert learner.situation(near, here, np.array(ahead)) == 13 * 8
    near[[0, 7]] = 0.69                          # left and right too: 15 - 2 - 1 - 8
    assert learner.situation(near, here, np.array(ahead)) == 4 * 8


def test_a_learner_rebuilt_from_its_state_decides_as_the_one_that_carried_on() -> None:
    rng = np.random.default_rng(7)
    inputs = [(rng.uniform(0.25, 5.0, 16), rng.uniform(0.0, 7.0, 3)) for _ in range(80)]
    learner = ReactiveLearner(GOALS, seed=7)
    for step, (sonar, pose) in enumerate(inputs[:40]):
        learner.decide(sonar, pose, step * PERIOD)
    rebuilt = ReactiveLearner(GOALS, seed=7, **copy.deepcopy(learner.state()))
    for step, (sonar, pose) in enumerate(inputs[40:], 40):
        carried_on, _ = learner.decide(sonar, pose, step * PERIOD)
        assert np.array_equal(rebuilt.decide(sonar, pose, step * PERIOD)[0], carried_on)
    assert np.array_equal(rebuilt.q, learner.q) and rebuilt.episodes == learner.episodes
    assert COLLISION in [outcome for outcome, _, _ in learner.episodes]   # recoveries too


def test_what_is_learnt_of_a_situation_is_learnt_of_its_mirror_image() -> None:
    learner = ReactiveLearner([[3.0, 1.0]], Parameters(alpha=0.5), seed=4)
    sonar = CLEAR.copy()
    sonar[[0, 1]] = 0.5                          # an obstacle on the left
    pose = np.array([0.0, 0.0, 0.0])
    learner.decide(sonar, pose, 0.0)
    situation, action = learner.underway["state"], learner.underway["action"]
    learner.decide(np.full(16, 0.2), pose, 0.25)                      # a collision
    mirror = learner.situation(sonar[MIRRORED], pose, np.array([3.0, -1.0]))
    v, w = learner.parameters.actions[action]
    mirror_action = learner.parameters.actions.index((v, -w))
    assert mirror != situation
    assert learner.q[mirror, mirror_action] == learner.q[situation, action] < 0
    assert np.count_nonzero(learner.q) == 2


def test_nothing_is_learnt_across_a_long_pause_nor_when_learning_is_off() -> None:
    learner = ReactiveLearner([[3.0, 0.0]], seed=5)
    pose = np.zeros(3)
    learner.decide(CLEAR, pose, 0.0)
    learner.decide(CLEAR, np.array([0.3, 0.0, 0.0]), 5.0)      # a migration, say
    assert not learner.q.any() and learner.underway["steps"] == 2
    learner.q[:] = np.random.default_rng(5).normal(size=learner.q.shape)
    table, epsilon, rng = learner.q.copy(), learner.epsilon, learner.rng.bit_generator.state
    for step in range(20):                       # the robot is carried to the goal
        learner.decide(CLEAR, np.array([0.15 * step, 0.0, 0.0]), 5.25 + step * PERIOD,
                       learn=False)
    assert learner.episodes[0][0] == SUCCESS
    assert np.array_equal(learner.q, table) and learner.epsilon == epsilon
    assert learner.rng.bit_generator.state == rng


def test_parameters_and_table_are_checked() -> None:
    assert Parameters.of({"thresholds": [0.5, 1.0]}).thresholds == (0.5, 1.0)
    assert Parameters.of({"thresholds": [0.5, 1.0]}).states == 3 ** 4 * 8
    with pytest.raises(ValueError, match=r"unknown learner parameter.*'alfa'"):
        Parameters.of({"alfa": 0.1})
    with pytest.raises(ValueError, match=r"shape \(4, 3\) does not fit"):
        ReactiveLearner(GOALS, q=np.zeros((4, 3)))
    with pytest.raises(ValueError, match="mirror each other"):
        ReactiveLearner(GOALS, Parameters(actions=((0.3, 0.0), (0.0, 1.0))))
    with pytest.raises(ValueError, match="transducers 0-15"):
        Parameters.of({"sectors": [[0, 1], [16]]})
    with pytest.raises(ValueError, match="at least one goal"):
        ReactiveLearner([])


def test_the_module_commands_reports_episodes_and_carries_on_from_its_pickled_state() -> None:
    # goals 2 m ahead and behind; decisions by the world's clock, every 0.2 s of it
    state = {"goals": [[2.0, 0.0], [0.0, 0.0]], "seed": 6}
    harness = ModuleHarness(PolicyLearner, state=state)
    harness.feed("clock", 0.0)
    assert harness.written["command"] == []                 # nothing sensed yet
    assert harness.state["q"].shape == (128, 3)             # made at setup
    harness.feed("sonar", CLEAR)
    for tick, x in enumerate((0.0, 0.5, 1.0)):
        harness.feed("pose", np.array([x, 0.0, 0.0]))
        harness.feed("clock", 0.2 * tick)
        harness.feed("clock", 0.2 * tick + 0.1)              # a reading between decisions
    assert len(harness.written["command"]) == 3 and harness.written["episode"] == []
    assert harness.last("command").shape == (2,)
    harness.feed("pose", np.array([1.8, 0.0, 0.0]))        # within 0.4 m of the goal
    harness.feed("clock", 0.6)
    (episode,) = harness.written["episode"]
    assert episode["success"] and episode["index"] == 0 and episode["steps"] == 3
    assert episode["seconds"] == pytest.approx(0.6)          # world time
    assert episode["goal"] == (2.0, 0.0) and episode["epsilon"] < 0.3

    # mid-episode, the state goes through cloudpickle as it does in a migration
    restored = ModuleHarness(PolicyLearner,
                             state=cloudpickle.loads(cloudpickle.dumps(harness.state)))
    rng = np.random.default_rng(6)
    for tick in range(30):
        sonar, pose = rng.uniform(0.4, 5.0, 16), rng.uniform(0.5, 1.5, 3)
        for each in (harness, restored):
            each.feed("sonar", sonar)
            each.feed("pose", pose)
            each.feed("clock", 0.8 + 0.2 * tick)
        assert np.array_equal(restored.last("command"), harness.last("command"))
    assert np.array_equal(restored.state["q"], harness.state["q"])
    carried_on, going_on = harness.state["underway"], restored.state["underway"]
    assert going_on["started"] == carried_on["started"]             # the same episode
    assert going_on["steps"] == carried_on["steps"] == 31     # (its first at 0.6 s)

    # moved to a robot in another world, whose clock reads 5 s: the episode goes on there
    q_before, started = restored.state["q"].copy(), going_on["started"]
    restored.feed("clock", 5.0)
    moved = restored.state["underway"]
    assert moved["steps"] == 32 and moved["at"] == 5.0
    assert moved["started"] == pytest.approx(started + 5.0 - (0.8 + 0.2 * 29))
    assert np.array_equal(restored.state["q"], q_before)        # nothing learnt across

    harness.close()                                         # the robot is left standing
    assert harness.last("command").tolist() == [0.0, 0.0]


def test_the_module_decides_on_the_reading_nearest_each_decision_even_when_readings_jitter(
        ) -> None:
    # a driver's readings every 0.1 s of world time, each up to 4 ms early or late: a
    # decision every second reading, never a whole reading late (0.3 s)
    harness = ModuleHarness(PolicyLearner, state={"goals": [[5.0, 0.0]], "seed": 2})
    harness.feed("sonar", CLEAR)
    harness.feed("pose", np.zeros(3))
    rng = np.random.default_rng(2)
    decided = []
    for tick in range(200):
        now = 0.1 * tick + rng.uniform(-0.004, 0.004)
        before = len(harness.written["command"])
        harness.feed("clock", now)
        if len(harness.written["command"]) > before:
            decided.append(now)
    gaps = np.diff(decided)
    assert len(decided) == 100 and gaps.max() < 0.21 and gaps.min() > 0.19
    harness.close()


@pytest.mark.parametrize(("overrides", "named"), [
    ({"thresholds": [1.0, 0.5]}, "thresholds"),       # unsorted: every sector mis-sensed
    ({"thresholds": [0.0, 0.5]}, "thresholds"),
    ({"bearings": 0}, "bearings"),
    ({"gamma": 1.5}, "gamma"),
    ({"alpha": 0.0}, "alpha"),
    ({"epsilon_decay": 1.2}, "epsilon_decay"),
    ({"trace_decay": -0.1}, "trace_decay"),
    ({"actions": []}, "actions"),
    ({"goal_radius": 0.0}, "goal_radius"),
    ({"timeout": -1.0}, "timeout"),
    ({"turn_time": [1.5, 0.5]}, "turn_time"),
    ({"max_gap": float("nan")}, "max_gap"),
])
def test_a_parameter_out_of_range_is_refused_by_name(overrides, named) -> None:
    with pytest.raises(ValueError, match=rf"out of range: {named} = "):
        Parameters.of(overrides)
    assert Parameters.of({"thresholds": [0.5, 1.0], "bearings": 16}).states == 3 ** 4 * 16


def test_what_it_could_not_decide_by_set_while_it_runs_is_refused_and_nothing_is_set(
        ) -> None:
    """Goals, a parameter or a table set on a running learner that setup would refuse are
    refused by name, and it decides on by what it had; what it can decide by is taken."""
    harness = ModuleHarness(PolicyLearner, state={"goals": [[5.0, 0.0]], "seed": 2})
    harness.feed("sonar", CLEAR)
    harness.feed("pose", np.zeros(3))
    harness.feed("clock", 0.0)
    for wrong, named in (({"parameters": {"gamma": 1.5}}, "gamma = 1.5"),
                         ({"parameters": {"speed": 1.0}}, "unknown learner parameter"),
                         ({"goals": []}, "at least one goal"),
                         ({"q": np.zeros((4, 3))}, "table of shape")):
        with pytest.raises(ValueError, match=named):
            harness.module.set_state({**wrong, "learning": False})
    assert harness.state["parameters"] == {} and harness.state["learning"]
    harness.module.set_state({"goals": [[0.0, 3.0]], "parameters": {"gamma": 0.5}})
    harness.feed("clock", 0.2)
    assert len(harness.written["command"]) == 2
    assert harness.state["underway"]["distance"] == pytest.approx(3.0)    # the new goal


def test_a_learner_moved_while_recovering_carries_its_manoeuvre_onto_the_new_clock() -> None:
    """The gap between the worlds' clocks was measured from the episode under way,
    which a recovery does not have: moved while turning away from an obstacle, at 500 s
    of simulation to a robot at 20 s, it turned in place for 480 s of robot time."""
    learner = ModuleHarness(PolicyLearner, state={"goals": [[5.0, 5.0]], "decision_s": 0.2,
                                                  "seed": 3})
    clear, hit = np.full(16, 3.0), np.full(16, 3.0)
    hit[3] = 0.1
    pose = np.array([1.0, 1.0, 0.0])

    def tick(harness: ModuleHarness, sonar: np.ndarray, now: float) -> None:
        harness.feed("sonar", sonar)
        harness.feed("pose", pose)
        harness.feed("clock", now)
    for now, sonar in ((500.2, clear), (500.4, clear), (500.6, hit), (500.8, clear)):
        tick(learner, sonar, now)                        # a collision, then its recovery
    assert learner.state["recovery"] and not learner.state["underway"]
    moved = ModuleHarness(PolicyLearner, state=cloudpickle.loads(cloudpickle.dumps(
        learner.state)))
    turning = 0
    for step in range(1, 100):
        tick(moved, clear, 20.0 + 0.2 * step)
        v, w = moved.last("command")
        if not (v == 0.0 and w != 0.0):
            break
        turning += 1
    assert turning < 20, f"turned in place for {turning} decisions"   # (its own 0.8 s)
