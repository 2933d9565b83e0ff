"""``agents.explorer``: frontiers, plans, reflexes and the ``Explorer`` module, on
hand-made maps and on RAVE worlds explored by a simulated robot.

The worlds' maps come from a perfect sensor, not from the mapper: every tick, the
cells within ``SENSOR_RANGE`` of the robot in plain sight (rays marched over the
true grid) become free (0.1) or, where a ray stops, occupied (0.9).
"""

from __future__ import annotations

import math
import pickle
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.explorer import (
    Explorer,
    FrontierExplorer,
    FrontierPlanner,
    frontiers,
    hidden_frontiers,
)
from agents.grid import UNKNOWN, Grid
from agents.map_truth import reachable, score, truth
from agents.occupancy import OccupancyGrid
from pb3a.testing import ModuleHarness
from rave import World
from rave.layers import WALL_RADIUS
from rave.pioneer import RADIUS
from rave.sonar import MAX_RANGE

WORLDS = Path(__file__).resolve().parents[1] / "rave" / "worlds"
SENSOR_RANGE = 3.5                                   # m
RAYS = np.linspace(-math.pi, math.pi, 180, endpoint=False)
FREE_P, OCCUPIED_P = np.float32(0.1), np.float32(0.9)
TICK = 0.1                                           # s, the explorer's period
TOUCH = RADIUS + WALL_RADIUS                         # the robot's centre this near a wall


def _world_without_robots(name: str, seed: int = 1) -> World:
    """The world of ``rave/worlds/<name>.toml`` without its robots (one is a hardware
    robot, with an emulator process, that these tests do not need)."""
    return World.load(WORLDS / f"{name}.toml", seed, robots=False)


def _reveal(probabilities: np.ndarray, occupied: np.ndarray, grid: Grid, pose: Any) -> None:
    """What a perfect range sensor at ``pose`` shows, written into ``probabilities``."""
    steps = np.arange(0.0, SENSOR_RANGE, grid.resolution / 3)
    rows, cols = grid.cell(pose[0] + np.cos(RAYS)[:, None] * steps,
                           pose[1] + np.sin(RAYS)[:, None] * steps)
    inside = grid.inside(rows, cols)
    rows, cols = np.where(inside, rows, 0), np.where(inside, cols, 0)
    stopped = occupied[rows, cols] | ~inside
    first = np.where(stopped.any(axis=1), stopped.argmax(axis=1), len(steps))
    seen = np.arange(len(steps)) < first[:, None]
    probabilities[rows[seen], cols[seen]] = FREE_P
    hit = np.flatnonzero(first < len(steps))
    hit = hit[inside[hit, first[hit]]]
    probabilities[rows[hit, first[hit]], cols[hit, first[hit]]] = OCCUPIED_P


def _distance_to_walls(x: float, y: float, segments: np.ndarray) -> float:
    start, end = segments[:, 0:2], segments[:, 2:4]
    along = end - start
    t = np.clip(((x - start[:, 0]) * along[:, 0] + (y - start[:, 1]) * along[:, 1])
                / (along ** 2).sum(axis=1), 0.0, 1.0)
    return float(np.hypot(x - start[:, 0] - t * along[:, 0],
                          y - start[:, 1] - t * along[:, 1]).min())


@dataclass
class Run:
    """What happened while an ``Explorer`` drove a simulated robot."""

    explorer: ModuleHarness
    coverage: list[tuple[float, float]] = field(default_factory=list)  # (s, share), 5 s apart
    closest: float = math.inf            # m: nearest the robot's centre came to a wall
    done_at: float | None = None         # s
    final_coverage: float = 0.0

    def coverage_by(self, seconds: float) -> float:
        return max((share for at, share in self.coverage if at <= seconds), default=0.0)


def _explore(world: World, start: tuple[float, float, float], seconds: float,
             sensed: Any = None, **state: Any) -> Run:
    """Drive a simulated robot from ``start`` by an ``Explorer`` (with ``state``)
    for ``seconds`` of simulated time, or until it is done, the map shown by a
    perfect sensor of the obstacles of ``sensed`` (the world's by default)."""
    grid = Grid.of(world.size)
    occupied = truth(world if sensed is None else sensed, grid)
    free_space = reachable(occupied, grid, start[:2])
    robot = world.add_robot("explorer", start, backend="sim")
    run = Run(ModuleHarness(Explorer, state={"size": list(world.size), **state}))
    probabilities, segments = grid.blank(), world.segments()
    for tick in range(round(seconds / TICK)):
        pose = np.array(world.pose("explorer"))
        _reveal(probabilities, occupied, grid, pose)
        run.explorer.feed("map", probabilities)
        run.explorer.feed("pose", pose)
        run.explorer.feed("sonar", robot.sonar())
        run.explorer.step()
        if tick % 50 == 0:
            run.coverage.append((world.time, score(probabilities, occupied, free_space).coverage))
        if run.explorer.state["done"]:
            run.done_at = world.time
            break
        robot.drive(*run.explorer.last("command"))
        world.step(TICK)
        run.closest = min(run.closest, _distance_to_walls(*world.pose("explorer")[:2], segments))
    run.final_coverage = score(probabilities, occupied, free_space).coverage
    return run


# -- frontiers and plans on hand-made maps ---------------------------------------------------
def _room(width: float = 6.0, height: float = 4.0) -> tuple[Grid, np.ndarray]:
    """A map of a walled ``width`` x ``height`` m room, all known: free inside."""
    grid = Grid(width, height)
    probabilities = np.full(grid.shape, FREE_P)
    probabilities[[0, -1], :] = probabilities[:, [0, -1]] = OCCUPIED_P
    return grid, probabilities


def test_frontiers_border_wide_unknown_areas_only() -> None:
    _, probabilities = _room()
    probabilities[10:30, 40:59] = UNKNOWN          # the east end, unseen: 380 cells
    probabilities[20:23, 10:13] = UNKNOWN          # a pocket a sensor missed: 9 cells
    classes = probabilities < 0.35
    found = frontiers(classes, probabilities == UNKNOWN)
    rows, cols = np.nonzero(found)
    assert (cols == 39).sum() == 20                # the west edge of the unseen end
    assert ((rows == 9) | (rows == 30)).sum() == 2 * 19   # and its north and south edges
    assert not found[19:24, 9:14].any()            # no trip for the pocket
    assert found.sum() == 20 + 2 * 19


def test_hidden_frontiers_face_a_thin_wall_with_a_wide_unknown_behind() -> None:
    _, probabilities = _room()
    probabilities[1:-1, 31:59] = UNKNOWN           # beyond a wall at column 30
    probabilities[1:-1, 30] = OCCUPIED_P
    free, unknown = probabilities < 0.35, probabilities == UNKNOWN
    occupied = probabilities > 0.65
    assert not frontiers(free, unknown).any()      # the wall hides everything
    rows, cols = np.nonzero(hidden_frontiers(free, occupied, unknown))
    assert set(cols) == {29} and len(rows) == 38   # the cells along the wall's near side
    probabilities[1:-1, 26:30] = OCCUPIED_P        # a thick wall is a wall
    assert not hidden_frontiers(probabilities < 0.35, probabilities > 0.65, unknown).any()


def test_a_plan_goes_through_the_doorway_keeping_clear_of_the_walls() -> None:
    grid, probabilities = _room(8.0, 4.0)
    probabilities[1:-1, 40] = OCCUPIED_P           # a wall at x = 4 m ...
    probabilities[25:35, 40] = FREE_P              # ... with a 1 m doorway, y 2.5-3.5 m
    probabilities[1:-1, 60:79] = UNKNOWN           # the east end, unseen
    planner = FrontierPlanner(grid)
    plan = planner.plan(probabilities, (1.0, 1.0, 0.0))
    assert plan.target is not None and not plan.hidden
    assert plan.target[0] == pytest.approx(5.95)   # the free cells next to the unknown
    x, y, clearance = plan.path.T
    assert x[-1] >= plan.target[0] - 1.0           # ends within ``approach`` of it
    through = np.flatnonzero(np.abs(x - 4.05) < 0.06)
    assert through.size and (np.abs(y[through] - 3.0) <= 0.1).all()   # the doorway's middle
    assert (clearance >= planner.lethal).all()     # clear of every wall
    length = np.hypot(np.diff(x), np.diff(y)).sum()
    assert length <= plan.cost <= (1 + planner.proximity_cost) * length


def test_past_a_doorway_a_sonar_map_narrows_it_squeezes_through_or_keeps_to_its_trail() -> None:
    grid, probabilities = _room(8.0, 4.0)
    probabilities[1:-1, 40] = OCCUPIED_P           # a wall at x = 4 m ...
    probabilities[17:23, 40] = FREE_P              # ... its doorway drawn 0.6 m wide
    probabilities[1:-1, 55:79] = UNKNOWN           # unseen from x = 5.5 m on
    planner, robot = FrontierPlanner(grid), (1.0, 2.0, 0.0)
    squeezed = planner.plan(probabilities, robot)
    assert squeezed.target[0] == pytest.approx(5.45) and not squeezed.hidden
    assert planner.squeezed <= squeezed.path[:, 2].min() < planner.lethal
    probabilities[17:23, 40] = OCCUPIED_P          # echoes drawn right across it
    closed = planner.plan(probabilities, robot)
    # the frontier beyond is out of reach, but the robot saw free space through the
    # wall: it goes to look at the wall from close by, where the doorway was
    assert closed.hidden and closed.regions == 1
    assert closed.target[0] == pytest.approx(3.95) and abs(closed.target[1] - 2.0) < 0.5
    trail = np.zeros(grid.shape, dtype=bool)
    trail[20, 10:50] = True                        # ... where the robot once went through
    through = planner.plan(probabilities, robot, trail=trail)
    assert through.target[0] == pytest.approx(5.45)
    at_the_doorway = np.abs(through.path[:, 0] - 4.05) < 0.3
    assert np.allclose(through.path[at_the_doorway, 1], 2.05)    # along the trail


def test_when_a_wall_hides_every_frontier_it_goes_to_look_at_the_wall() -> None:
    grid, probabilities = _room(8.0, 4.0)
    probabilities[1:-1, 40] = OCCUPIED_P           # a wall at x = 4 m, doorway unseen
    probabilities[1:-1, 41:79] = UNKNOWN
    planner = FrontierPlanner(grid)
    plan = planner.plan(probabilities, (1.0, 2.0, 0.0))
    assert plan.hidden and plan.regions == 0 and plan.target[0] == pytest.approx(3.95)
    assert FrontierPlanner(grid, look_behind_walls=False).plan(
        probabilities, (1.0, 2.0, 0.0)).target is None


def test_at_a_frontier_that_stays_it_looks_at_it_then_sets_it_aside() -> None:
    grid, probabilities = _room(8.0, 4.0)
    probabilities[1:-1, 40] = OCCUPIED_P           # a wall hiding everything beyond
    probabilities[1:-1, 41:79] = UNKNOWN
    explorer, pose = FrontierExplorer(grid, look_time=2.0), (3.6, 2.0, math.pi)
    v, w = explorer.step(probabilities, pose, None, TICK)
    first = list(explorer.target)
    assert first[0] == pytest.approx(3.95) and abs(first[1] - 2.0) < 0.3
    assert v == 0.0 and abs(w) == explorer.max_turn          # turns round to face it
    for _ in range(round(explorer.look_time / TICK)):        # the map stays the same
        explorer.step(probabilities, pose, None, TICK)
    # looking resolved nothing: it plans to get nearer, finds it cannot, sets it aside
    explorer.step(probabilities, pose, None, TICK)
    assert [entry[:2] for entry in explorer.blacklist] == [first]
    explorer.step(probabilities, pose, None, TICK)           # and it plans without it
    assert np.hypot(explorer.target[0] - first[0], explorer.target[1] - first[1]) > 1.0
    assert explorer.stuck == 0


def test_a_blacklisted_frontier_is_no_target() -> None:
    grid, probabilities = _room()
    probabilities[29:39, 20:30] = UNKNOWN          # two unseen 1 m squares on the north
    probabilities[29:39, 48:58] = UNKNOWN          # wall, the first nearer the robot
    planner = FrontierPlanner(grid, blacklist_radius=1.6)
    robot = (1.0, 1.0, 0.0)
    near = planner.plan(probabilities, robot)
    assert near.regions == 2 and 1.8 < near.target[0] < 3.2
    far = planner.plan(probabilities, robot, blacklist=np.array([near.target]))
    assert far.regions == 1 and far.target[0] > 4.6
    none = planner.plan(probabilities, robot, blacklist=np.array([near.target, far.target]))
    assert none.target is None and none.regions == 0


def test_with_nothing_left_to_see_it_is_done_and_stands() -> None:
    grid, probabilities = _room()
    explorer = FrontierExplorer(grid)
    assert explorer.step(probabilities, (3.0, 2.0, 0.0), None, TICK) == (0.0, 0.0)
    assert explorer.done and explorer.plans == 1 and explorer.target == []
    with pytest.raises(ValueError, match="give the explorer the size and resolution"):
        FrontierExplorer(Grid(5.0, 4.0)).step(probabilities, (3.0, 2.0, 0.0), None, TICK)


def test_sonar_reflexes_slow_down_and_back_off_before_an_unmapped_obstacle() -> None:
    grid, probabilities = _room()
    probabilities[1:-1, 45:59] = UNKNOWN           # a frontier straight ahead
    pose, clear = (1.5, 2.0, 0.0), np.full(16, MAX_RANGE)

    def command(front: float) -> tuple[float, float]:
        sonar = clear.copy()
        sonar[2:6] = front                         # the front transducers, -30..+30 deg
        explorer = FrontierExplorer(grid)
        explorer.obstacle_range = 0.0              # the reflexes alone, not the plan
        explorer.step(probabilities, pose, clear, TICK)     # plans, in the open
        return explorer.step(probabilities, pose, sonar, TICK)

    (free_v, _), (slowed_v, _), (close_v, close_w) = command(5.0), command(0.4), command(0.12)
    assert free_v == pytest.approx(0.4, abs=0.05)
    assert 0.0 < slowed_v < 0.75 * free_v
    assert close_v < 0.0 and close_w != 0.0        # backs off, turning away


# -- exploring worlds --------------------------------------------------------------------------
def test_it_explores_the_lab_without_touching_a_wall() -> None:
    world = _world_without_robots("lab")
    try:
        run = _explore(world, (1.0, 1.5, 0.0), seconds=320.0)
    finally:
        world.close()
    # measured: 76 % by 120 s, 97 % by 150 s, done at 231 s with 99 %, never nearer a
    # wall than 0.42 m. (Slower than when it set aside the corners it could not see
    # round from a metre off, and went through walls to look at them: it now looks
    # at frontiers it can see, and goes nearer before it gives one up.)
    assert run.coverage_by(150.0) >= 0.85
    assert run.done_at is not None and run.done_at <= 300.0
    assert run.final_coverage >= 0.95
    assert run.closest > TOUCH + 0.05
    assert run.explorer.last("command").tolist() == [0.0, 0.0]
    assert run.explorer.state["stuck"] == 0


def test_it_explores_the_arena_round_its_obstacles() -> None:
    world = _world_without_robots("arena")
    try:
        run = _explore(world, (1.0, 4.0, 0.0), seconds=200.0)
    finally:
        world.close()
    # measured: 81 % by 80 s, 91 % by 90 s, done at 95 s with 98 %, never nearer a
    # wall than 0.40 m
    assert run.coverage_by(100.0) >= 0.85
    assert run.done_at is not None and run.done_at <= 150.0
    assert run.final_coverage >= 0.95
    assert run.closest > TOUCH + 0.05


def test_a_frontier_behind_what_only_its_sonar_sees_is_given_up_not_pushed_at() -> None:
    # a corridor closed at x = 3 m by a glass pane the map never shows: the sensor
    # sees through it, the sonar echoes off it
    world = World((8.0, 2.0), seed=1, name="glass")
    for start, end in (((0, 0), (8, 0)), ((8, 0), (8, 2)), ((8, 2), (0, 2)), ((0, 2), (0, 0))):
        world.add_wall(start, end)
    sensed = world.describe()
    world.add_wall((3.0, 0.0), (3.0, 2.0))
    try:
        run = _explore(world, (1.0, 1.0, 0.0), seconds=60.0, sensed=sensed)
        x = world.pose("explorer")[0]
    finally:
        world.close()
    state = run.explorer.state
    # what it heard close by closes the corridor to the planner: the frontiers past
    # the pane are out of reach, and it is done without driving into the pane
    assert state["echoes"][:, 28:31].any() and not state["echoes"][:, 31:].any()
    assert run.done_at is not None and run.done_at <= 20.0          # measured: 5.7 s
    assert x < 3.0 - RADIUS and run.closest > TOUCH + 0.05      # measured: 0.74 m
    assert state["stuck"] == 0
    assert run.explorer.last("command").tolist() == [0.0, 0.0]


def test_state_set_while_it_runs_is_what_it_goes_by() -> None:
    """A setting or a memory set on a running explorer (the State Editor, an agent) is
    taken at once, not overwritten by the explorer's own at its next step."""
    world = _world_without_robots("arena")
    try:
        explorer = _explore(world, (1.0, 4.0, 0.0), seconds=20.0).explorer
        aside = [9.5, 7.5, 1e9, 1.0]                 # (x, y, until, failures)
        explorer.module.set_state({"max_speed": 0.1,
                                   "blacklist": [*explorer.state["blacklist"], aside]})
        grid = Grid.of(world.size)
        occupied, probabilities = truth(world, grid), grid.blank()
        robot, speeds = world.robot("explorer"), []
        for _ in range(100):
            pose = np.array(world.pose("explorer"))
            _reveal(probabilities, occupied, grid, pose)
            explorer.feed("map", probabilities)
            explorer.feed("pose", pose)
            explorer.feed("sonar", robot.sonar())
            explorer.step()
            speeds.append(explorer.last("command")[0])
            robot.drive(*explorer.last("command"))
            world.step(TICK)
    finally:
        world.close()
    assert max(speeds) <= 0.1 + 1e-9 and max(speeds) > 0.05         # slower, and moving
    assert aside in explorer.state["blacklist"]


def test_after_a_move_it_carries_on_toward_the_same_target() -> None:
    world = _world_without_robots("arena")
    try:
        original = _explore(world, (1.0, 4.0, 0.0), seconds=20.0).explorer
        assert original.state["target"] and not original.state["done"]
        plans_before = original.state["plans"]
        # the state goes to another process (pickled) and the module starts again there
        moved = ModuleHarness(Explorer, state=pickle.loads(pickle.dumps(original.state)))
        assert moved.state["target"] == original.state["target"]
        np.testing.assert_array_equal(moved.state["path"], original.state["path"])
        grid = Grid.of(world.size)
        occupied, probabilities = truth(world, grid), grid.blank()
        robot = world.robot("explorer")
        for _ in range(100):
            pose = np.array(world.pose("explorer"))
            _reveal(probabilities, occupied, grid, pose)
            for harness in (original, moved):
                harness.feed("map", probabilities)
                harness.feed("pose", pose)
                harness.feed("sonar", robot.sonar())
                harness.step()
            np.testing.assert_array_equal(moved.last("command"), original.last("command"))
            robot.drive(*moved.last("command"))
            world.step(TICK)
    finally:
        world.close()
    assert moved.state["plans"] == original.state["plans"] > plans_before
    assert moved.state["target"] == original.state["target"]


def test_without_a_map_or_a_pose_it_stands() -> None:
    explorer = ModuleHarness(Explorer, state={"size": [6.0, 4.0]})
    explorer.step()
    explorer.feed("pose", np.array([1.0, 2.0, 0.0]))
    explorer.step()
    assert [c.tolist() for c in explorer.written["command"]] == [[0.0, 0.0], [0.0, 0.0]]
    _, probabilities = _room()
    probabilities[:, 45:59] = UNKNOWN
    explorer.feed("map", probabilities)
    explorer.step()
    assert explorer.last("command")[0] != 0.0 or explorer.last("command")[1] != 0.0


def test_set_up_again_with_a_pose_in_it_stands_until_the_robot_reports_again() -> None:
    """Moved with its ports (handed to the standby robot), the pose it holds may be the
    failed robot's: it stepped on it and sent the standby that robot's command. It stands
    until a new report comes, then goes by that."""
    _, probabilities = _room()
    probabilities[:, 45:59] = UNKNOWN
    explorer = ModuleHarness(Explorer, state={"size": [6.0, 4.0]})
    explorer.feed("map", probabilities)
    explorer.feed("pose", np.array([1.0, 2.0, 0.0]))
    explorer.step()
    assert np.any(explorer.last("command") != 0.0)
    explorer.feed("pose", np.array([1.2, 2.0, 0.0]))    # a report not yet stepped on
    explorer.module.setup()                 # as after a move or a swap: ports kept
    explorer.step(3)
    assert explorer.last("command").tolist() == [0.0, 0.0]
    explorer.feed("pose", np.array([1.0, 1.0, math.pi / 2]))
    explorer.step()
    assert np.any(explorer.last("command") != 0.0)


def test_a_grid_setup_would_refuse_set_while_it_runs_is_refused_and_nothing_is_set() -> None:
    """A resolution of 0 set on a running explorer is refused as setup refuses it; before,
    it stayed in the state (the explorer going by its old grid, and refusing to start again
    after a move) with max_speed set alongside it."""
    explorer = ModuleHarness(Explorer, state={"size": [6.0, 4.0]})
    with pytest.raises(ValueError, match="positive size and resolution"):
        explorer.module.set_state({"resolution": 0.0, "max_speed": 0.1})
    assert (explorer.state["resolution"], explorer.state["max_speed"]) == (0.1, 0.4)
    explorer.module.set_state({"resolution": 0.2})
    assert explorer.state["trail"].shape == (20, 30)            # made again for it
    # an infinite size was stored before setup failed on it; a negative speed drove
    # the explorer backwards, where its reflexes do not look; a tiny resolution would
    # have made a map of billions of cells
    for wrong, named in (({"size": [math.inf, 4.0]}, "positive size and resolution"),
                         ({"max_speed": -0.4}, "max_speed must be a speed above 0"),
                         ({"replan_every": math.nan}, "replan_every must be a number of"),
                         ({"resolution": 1e-5}, "cells, more than 10,000,000")):
        with pytest.raises(ValueError, match=named):
            explorer.module.set_state(wrong)
    assert (explorer.state["size"], explorer.state["max_speed"]) == ([6.0, 4.0], 0.4)


# -- on a hardware robot, with the mapper, as in the live pipeline ---------------------------
def _explore_hardware(name: str, seed: int, seconds: float, delay: int = 1,
                      hand_over_at: float | None = None) -> dict[str, Any]:
    """The mapping application's loop in one process: the world's first robot on the
    emulated hardware back end (second-order motors, a sonar ring with noise,
    dropouts and specular reflection), an ``OccupancyGrid`` fed its ring and pose
    every 0.1 s, and a ``FrontierExplorer`` that sees pose, map and sonar ``delay``
    ticks late and whose command reaches the robot ``delay`` ticks later (as the
    pipeline's ports and periods do). With ``hand_over_at`` the explorer, its memory
    pickled, moves to the world's second robot then. Coverage every 5 s, what
    happened to the explorer, and how near the robot came to a wall."""
    world = World.load(WORLDS / f"{name}.toml", seed=seed)
    try:
        names = list(world.robots)
        for robot_name in names[:2]:
            world.robot(robot_name).swap("hardware")
        robot = world.robot(names[0])
        grid = Grid.of(world.size)
        occupied = truth(world, grid)
        free_space = reachable(occupied, grid, world.pose(names[0])[:2])
        mapper, explorer = OccupancyGrid(grid), FrontierExplorer(grid)
        seen: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        commands = [(0.0, 0.0)] * delay
        segments = world.segments(virtual=False)
        out: dict[str, Any] = {"coverage": [], "accuracy": [], "closest": math.inf,
                               "set_aside_at": [], "jumped": None}
        while world.time < seconds:
            if hand_over_at is not None and world.time >= hand_over_at:
                hand_over_at = None
                blacklist = len(explorer.blacklist)
                explorer.restore(pickle.loads(pickle.dumps(explorer.memory())))
                robot.stop()
                robot = world.robot(names[1])
                seen.clear()
                out["jumped"] = {"plans": explorer.plans, "blacklist": blacklist,
                                 "stuck": explorer.stuck, "at": robot.gps()}
            sonar, pose = robot.sonar(), np.array(robot.gps())
            mapper.update(pose, sonar)
            seen.append((mapper.probabilities(), pose, sonar))
            before = len(explorer.blacklist)
            commands.append(explorer.step(*seen[max(0, len(seen) - 1 - delay)], TICK))
            if len(explorer.blacklist) > before:
                out["set_aside_at"].append(world.time)
            if out["jumped"] is not None and "plans_after" not in out["jumped"]:
                out["jumped"].update(plans_after=explorer.plans, target=list(explorer.target))
            robot.drive(*commands.pop(0))
            world.step(TICK)
            out["closest"] = min(out["closest"], _distance_to_walls(*robot.gps()[:2], segments))
            if round(world.time / TICK) % 50 == 0:
                figures = score(mapper.probabilities(), occupied, free_space)
                out["coverage"].append((round(world.time), figures.coverage))
                out["accuracy"].append(figures.accuracy)
        out["explorer"] = explorer
        return out
    finally:
        world.close()


def test_on_a_hardware_robot_it_maps_the_lab_instead_of_giving_up_near_the_start() -> None:
    # The live failure: the mapper folded a beam that hears no echo in only once (its
    # reading, the sonar's maximum, repeats exactly), so the corridor ahead stayed
    # unknown; the explorer stood a metre off the frontier, looked at it for 2 s,
    # set it aside with everything within a metre, and was done at (1.5, 2.2) with
    # 12 % after 17 s.
    run = _explore_hardware("lab", seed=1, seconds=45.0)
    coverage = dict(run["coverage"])
    # measured: 11, 14, 22, 29, 34, 43, 47, 49, 49 % at 5 ... 45 s, nothing set
    # aside, accuracy 0.95-0.97, never nearer a wall than 0.59 m
    assert coverage[20] >= 0.2 and coverage[40] >= 0.4
    assert all(a < b for a, b in zip([coverage[10], coverage[20], coverage[30]],
                                      [coverage[20], coverage[30], coverage[40]],
                                      strict=True))
    assert not run["explorer"].done and not [t for t in run["set_aside_at"] if t < 20.0]
    assert min(run["accuracy"]) >= 0.9
    assert run["closest"] > TOUCH


def test_handed_to_another_robot_it_plans_afresh_there_and_holds_nothing_against_the_jump(
        ) -> None:
    # The remedy moves the control macro, explorer and all, to the standby robot: its
    # pose jumps across the lab.
    run = _explore_hardware("lab", seed=2, seconds=30.0, hand_over_at=20.0)
    jumped = run["jumped"]
    assert jumped["plans_after"] == jumped["plans"] + 1          # at once
    target = np.array(jumped["target"])
    assert target.size and np.hypot(*(target - np.array(jumped["at"][:2]))) < 3.0
    explorer = run["explorer"]
    assert explorer.stuck == jumped["stuck"] and len(explorer.blacklist) == jumped["blacklist"]
    assert not explorer.done and run["coverage"][-1][1] > run["coverage"][3][1]


def test_handed_to_a_robot_the_other_drew_as_a_wall_it_drives_through_that_wall() -> None:
    # The lab's standby robot, seen by the mapping robot's sonar from down the
    # corridor, was drawn as an arc across the corridor (a 30 degree cone is wider
    # than a body) 0.4 m from where it stands: handed the explorer, it looked at the
    # pocket behind it and looped round the arc for 20 s of its 40.
    grid, probabilities = _room(8.0, 3.0)
    probabilities[1:-1, 1:16] = UNKNOWN            # the west end, unseen
    probabilities[3:24, 61] = OCCUPIED_P           # the arc, 0.4 m west of the standby
    explorer = FrontierExplorer(grid)
    explorer.step(probabilities, (3.0, 1.0, 0.0), None, TICK)   # the first robot
    explorer.step(probabilities, (6.5, 1.5, math.pi), None, TICK)   # handed over
    assert explorer.target and explorer.target[0] < 2.0 and not explorer.behind_wall
    x, y, _ = explorer.path.T
    through = np.abs(x - 6.15) < 0.06
    assert through.any() and ((y[through] > 0.5) & (y[through] < 2.3)).all()   # not round
    assert explorer.handed_at == [6.5, 1.5]
    for step in range(1, 10):                      # once it has left the arc behind,
        explorer.step(probabilities, (6.5 - 0.1 * step, 1.5, math.pi), None, TICK)
    assert explorer.handed_at == []                # the map has its word there again


def test_handed_to_another_robot_it_does_not_plan_through_the_one_left_on_its_trail(
        ) -> None:
    # The failed robot stands where its trail ends, in a doorway: the trail, which
    # the planner trusts over the map and the echoes, led the standby into it.
    grid, probabilities = _room(8.0, 4.0)
    probabilities[20, :] = OCCUPIED_P              # a wall at y = 2 m with two doorways,
    probabilities[20, 55:65] = FREE_P              # x 5.5-6.5 m
    probabilities[20, 15:25] = FREE_P              # and x 1.5-2.5 m
    probabilities[33:-1, 1:-1] = UNKNOWN           # beyond, unseen from y = 3.3 m on
    explorer = FrontierExplorer(grid)
    explorer.trail[10, 10:61] = True               # along y = 1 m, then up into the
    explorer.trail[10:21, 60] = True               # doorway at x = 6 m, where it stops
    left = (6.05, 2.05, math.pi / 2)
    explorer.step(probabilities, left, None, TICK)
    explorer.step(probabilities, (7.0, 1.0, math.pi), None, TICK)   # handed over
    x, y, _ = explorer.path.T
    assert np.hypot(x - left[0], y - left[1]).min() > 2 * RADIUS
    assert (np.hypot(x - 2.05, y - 2.05) < 0.2).any()          # through the other doorway
    assert explorer.trail[10, 10:40].all() and not explorer.trail[15:21, 60].any()


def test_looking_does_not_count_against_its_patience_and_a_stale_pose_stops_its_clock(
        ) -> None:
    grid, probabilities = _room(8.0, 4.0)
    probabilities[1:-1, 40] = OCCUPIED_P
    probabilities[1:-1, 41:79] = UNKNOWN
    explorer = FrontierExplorer(grid, look_time=2.0, patience=1.0)
    pose = (3.6, 2.0, math.pi)
    explorer.step(probabilities, pose, None, TICK)
    assert explorer.looking_until > explorer.clock
    for _ in range(15):                                      # 1.5 s looking, standing
        explorer.step(probabilities, pose, None, TICK)
    assert explorer.stuck == 0
    module = ModuleHarness(Explorer, state={"size": [8.0, 4.0]})
    module.feed("map", probabilities)
    module.feed("pose", np.array(pose))
    module.step()
    clock = module.state["clock"]
    module.step()                                            # no new report from the robot
    assert module.state["clock"] == clock
    np.testing.assert_array_equal(module.written["command"][-1], module.written["command"][-2])
    module.feed("pose", np.array(pose))
    module.step()
    assert module.state["clock"] == pytest.approx(clock + TICK)


def test_an_explorer_and_a_mapper_with_their_defaults_fit_and_a_misfit_names_the_fix() -> None:
    """Their default sizes differed (10 x 8 m and 12 x 9 m): wired with both, the
    explorer refused every map, in words that named no setting."""
    from agents.occupancy import Mapper

    mapper = ModuleHarness(Mapper)
    grid = Grid.of(mapper.state["size"], mapper.state["resolution"])
    explorer = ModuleHarness(Explorer)
    explorer.feed("map", np.full(grid.shape, UNKNOWN, dtype=np.float32))
    explorer.feed("pose", np.array([2.0, 2.0, 0.0]))
    explorer.step()                                  # planned on the mapper's grid
    small = ModuleHarness(Explorer, state={"size": [10.0, 8.0]})
    small.feed("map", np.full(grid.shape, UNKNOWN, dtype=np.float32))
    small.feed("pose", np.array([2.0, 2.0, 0.0]))
    with pytest.raises(ValueError, match=r"the map is \(90, 120\) cells, the planner's grid "
                                         r"\(80, 100\): give the explorer the size and "
                                         r"resolution of the map it is fed"):
        small.step()


def test_a_target_set_without_its_path_is_planned_to_afresh() -> None:
    """``set_state({"target": ..., "path": []})`` failed the next step with an
    IndexError: the explorer looked for the end of a path it did not have."""
    from agents.occupancy import Mapper

    mapper = ModuleHarness(Mapper, state={"size": [10.0, 8.0]})
    mapper.feed("pose", np.array([2.0, 2.0, 0.0]))
    mapper.feed("sonar", np.full(16, 2.0))
    explorer = ModuleHarness(Explorer, state={"size": [10.0, 8.0]})
    explorer.feed("map", mapper.last("map"))
    explorer.feed("pose", np.array([2.0, 2.0, 0.0]))
    explorer.step()
    plans = explorer.state["plans"]
    explorer.module.set_state({"target": [5.0, 4.0], "path": np.zeros((0, 3))})
    explorer.feed("pose", np.array([2.01, 2.0, 0.0]))
    explorer.step()
    assert explorer.state["plans"] == plans + 1 and len(explorer.state["path"])
