"""RAVE's simulator core: sonar geometry, hybrid sensing, the two back ends, faults,
back-end swap, the camera, world files and determinism."""

from __future__ import annotations

import contextlib
import math
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import pytest
from conftest import alive, eventually

from rave import World, WorldError, camera, odometry, raycast, sonar
from rave import emulator as rave_emulator
from rave import fleet as fleet_module
from rave.emulator import EmulatorProcess
from rave.sonar import SonarNoise

REPO = Path(__file__).resolve().parent.parent
EXACT = SonarNoise(sigma0=0.0, sigma_per_m=0.0)
WorldMaker = Callable[..., World]


@pytest.fixture
def world_of(request: pytest.FixtureRequest) -> WorldMaker:
    """``World(...)``, closed (its hardware robots' emulator processes stopped) when
    the test ends."""
    def make(*args: Any, **kwargs: Any) -> World:
        world = World(*args, **kwargs)
        request.addfinalizer(world.close)
        return world
    return make
POSE = (2.0, 2.0, 0.0)


def _expected(transducer: int, wall_x: float, pose=POSE) -> float:
    """The nearest cone ray's range to the vertical wall x = wall_x, computed apart."""
    x, _, theta = pose
    ox, oy, heading = sonar.RING[transducer]
    angles = theta + heading + np.radians(np.linspace(-15, 15, 5))
    origin_x = x + ox * math.cos(theta) - oy * math.sin(theta)
    ranges = (wall_x - origin_x) / np.cos(angles)
    ranges = ranges[(ranges > 0) & (ranges <= 5.0)]
    return float(ranges.min()) if len(ranges) else 5.0


def test_sonar_ranges_match_the_geometry_of_walls_the_cone_and_the_maximum_range() -> None:
    wall = np.array([[4.0, -10.0, 4.0, 10.0]])
    readings = sonar.read(POSE, wall, None, EXACT, np.random.default_rng(0))
    for transducer in range(8):
        assert readings[transducer] == pytest.approx(_expected(transducer, 4.0), abs=0.0011)
    assert readings[3] == pytest.approx(1.836, abs=0.001)      # 10 deg: the cone's -5..25
    assert readings[0] == readings[7] == sonar.MAX_RANGE        # parallel: beyond 5 m
    assert (readings[8:] == sonar.MAX_RANGE).all()              # the rear sees nothing
    turned = sonar.read((2.0, 2.0, math.radians(40)), wall, None, EXACT,
                        np.random.default_rng(0))
    assert turned[5] == pytest.approx(_expected(5, 4.0, (2.0, 2.0, math.radians(40))),
                                      abs=0.0011)               # a wall seen at an angle
    near = sonar.read((3.8, 2.0, 0.0), wall, None, EXACT, np.random.default_rng(0))
    assert near[3] == sonar.MIN_RANGE                           # closer than 0.1 m


def test_a_grazing_wall_returns_no_echo_on_hardware_but_does_in_simulation() -> None:
    corridor = np.array([[-10.0, 2.5, 10.0, 2.5]])              # along the heading
    specular = SonarNoise(sigma0=0.0, sigma_per_m=0.0, specular=True)
    rng = np.random.default_rng(0)
    ideal = sonar.read(POSE, corridor, None, EXACT, rng)
    real = sonar.read(POSE, corridor, None, specular, rng)
    assert ideal[2] == pytest.approx(0.597, abs=0.002)          # 30 deg: grazing rays
    assert real[2] == sonar.MAX_RANGE                           # ... reflected away
    assert real[0] == pytest.approx(2.5 - 2.136, abs=0.002)     # head-on still echoes


def test_hybrid_sonar_is_the_nearer_of_real_and_virtual_and_the_real_part_ignores_virtual(
        world_of: WorldMaker) -> None:
    world = world_of(size=(10, 8), seed=4)
    world.add_wall((6, 0), (6, 8))                              # real
    world.add_wall((4, 0), (4, 8), virtual=True)                # only in the world model
    robot = world.add_robot("hw", POSE, backend="hardware")
    world.step(0.5)                                             # every transducer fired
    real = robot._body.real_sonar()
    hybrid = robot.sonar()
    assert min(real[3], real[4]) == pytest.approx(_expected(3, 6.0), abs=0.15)
    assert min(hybrid[3], hybrid[4]) == pytest.approx(_expected(3, 4.0), abs=0.05)
    assert (hybrid <= real).all()
    far = world_of(size=(10, 8), seed=4)
    far.add_wall((6, 0), (6, 8))
    far.add_wall((7, 0), (7, 8), virtual=True)                  # behind the real wall
    robot = far.add_robot("hw", POSE, backend="hardware")
    far.step(0.5)
    np.testing.assert_array_equal(robot.sonar()[:8], robot._body.real_sonar()[:8])


def test_a_simulated_robot_stops_at_a_virtual_wall_that_a_hardware_robot_passes(
        world_of: WorldMaker) -> None:
    world = world_of(size=(10, 8), seed=1)
    world.add_wall((4, 0), (4, 8), virtual=True)
    sim = world.add_robot("sim", (2.0, 2.0, 0.0), backend="sim")
    hw = world.add_robot("hw", (2.0, 5.0, 0.0), backend="hardware")
    world.step(0.5)
    sensed = min(hw.sonar()[3:5])          # its hybrid sonar does see the virtual wall
    for robot in (sim, hw):
        robot.drive(0.5, 0.0)
    world.step(8.0)
    assert sensed == pytest.approx(_expected(3, 4.0, (2.0, 5.0, 0.0)), abs=0.05)
    assert world.pose("sim")[0] == pytest.approx(4.0 - 0.02 - 0.25, abs=0.02)
    assert world.pose("hw")[0] > 5.0                            # its body passed


def test_step_response_is_immediate_in_simulation_and_second_order_on_hardware(
        world_of: WorldMaker) -> None:
    world = world_of(size=(40, 8), seed=2)
    sim = world.add_robot("sim", (1.0, 2.0, 0.0), backend="sim")
    hw = world.add_robot("hw", (1.0, 6.0, 0.0), backend="hardware")
    sim.drive(0.5, 0.0)
    hw.drive(0.5, 0.0)
    speeds = []
    for _ in range(400):
        world.step(0.01)
        speeds.append((sim.velocity()[0], hw.velocity()[0]))
    sim_v, hw_v = np.array(speeds).T
    assert np.allclose(sim_v, 0.5)                              # from the first step
    assert hw_v[9] < 0.05                                       # 0.1 s: barely started
    assert np.all(np.diff(hw_v[:150]) <= 0.3 * 0.01 * 1.1)      # acceleration limit (+slip)
    assert hw_v[-1] == pytest.approx(0.5, rel=0.03)              # settles, slip aside
    assert hw_v.max() <= 0.5 + 1e-9                              # no overshoot


def test_motors_off_leaves_the_robot_still_while_odometry_and_commands_go_on(
        world_of: WorldMaker) -> None:
    world = world_of(size=(20, 8), seed=3)
    robot = world.add_robot("hw", (1.0, 4.0, 0.0), backend="hardware")
    robot.drive(0.4, 0.0)
    world.step(3.0)
    robot.inject("motors_off")
    world.step(0.05)                        # (the step it is injected in still moves)
    still, odometry = world.pose("hw"), robot.odometry()
    robot.drive(0.6, 0.2)                   # commands are still taken
    world.step(2.0)
    assert world.pose("hw") == pytest.approx(still, abs=1e-6)
    assert robot.odometry() == pytest.approx(odometry, abs=1e-6)
    assert len(robot.sonar()) == 16
    robot.clear("motors_off")
    world.step(2.0)
    assert world.pose("hw")[0] > still[0] + 0.3                 # the last command resumes
    with pytest.raises(ValueError, match="unknown fault 'smoke'"):
        robot.inject("smoke")
    with pytest.raises(ValueError, match="faults are injected into hardware robots"):
        world.add_robot("sim", (5.0, 2.0, 0.0)).inject("motors_off")


def test_a_hardware_robot_is_emulated_in_a_process_of_its_own_that_goes_with_it(
        world_of: WorldMaker) -> None:
    world = world_of(size=(10, 8), seed=1)
    robot = world.add_robot("hw", POSE, backend="hardware")
    first = robot._body.emulator.pid
    assert psutil.Process(first).ppid() == os.getpid()
    robot.drive(0.5, 0.0)
    world.step(2.0)
    assert world.pose("hw")[0] > POSE[0] + 0.4                 # it answers the world
    robot.swap("sim")
    eventually(lambda: not alive(first), timeout=5, what="the emulator to stop on swap")
    robot.swap("hardware")
    second = robot._body.emulator.pid
    os.kill(second, signal.SIGKILL)                              # the "robot" dies
    with pytest.raises(RuntimeError, match=r"emulator of robot hw is gone .*exited with -9"):
        world.step(0.1)
    robot.swap("sim")                                            # ... and is replaced
    world.step(0.1)
    other = world.add_robot("hw2", (6.0, 2.0, 0.0), backend="hardware")
    third = other._body.emulator.pid
    world.close()
    assert not alive(third)


def test_other_hardware_robots_do_not_run_ahead_of_a_world_that_cannot_step(
        world_of: WorldMaker) -> None:
    """While one emulator is gone the world cannot step; before, each try still
    advanced the other hardware robots, which then jumped ahead of the world."""
    world = world_of(size=(10, 8), seed=1)
    mover = world.add_robot("mover", POSE, backend="hardware")
    lost = world.add_robot("lost", (6.0, 6.0, 0.0), backend="hardware")
    mover.drive(0.5, 0.0)
    world.step(0.5)
    os.kill(lost._body.emulator.pid, signal.SIGKILL)
    with pytest.raises(RuntimeError, match="emulator of robot lost"):
        world.step(0.1)                # (the others may have stepped, its death unseen)
    x = world.pose("mover")[0]
    for _ in range(10):
        with pytest.raises(RuntimeError, match="emulator of robot lost is gone"):
            world.step(0.1)
    assert world.pose("mover")[0] == x                  # its emulator waited too
    lost.swap("sim")
    world.step(0.1)
    assert 0 < world.pose("mover")[0] - x <= 0.05        # 0.1 s at 0.5 m/s at most, not 1.1 s


def test_an_emulator_starts_beside_a_file_named_as_a_standard_module(
        world_of: WorldMaker, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The emulator's child starts with ``python -c``, which put the current directory
    first on its path: a user's ``random.py`` or ``json.py`` there was imported for
    Python's, and no hardware robot could start in that directory."""
    for name in ("random", "json", "tempfile"):
        (tmp_path / f"{name}.py").write_text(f"raise SystemExit('the user\'s {name}.py')\n")
    monkeypatch.chdir(tmp_path)
    world = world_of(size=(10, 8), seed=1)
    robot = world.add_robot("hw", POSE, backend="hardware")
    robot.drive(0.5, 0.0)
    world.step(2.0)
    assert world.pose("hw")[0] > POSE[0] + 0.4                 # it answers the world


def test_an_emulator_outlives_no_world_process_even_killed() -> None:
    parent = subprocess.Popen(
        [sys.executable, "-c", "from rave import World; import sys, time;"
         "w = World(); r = w.add_robot('hw', (2, 2, 0), backend='hardware');"
         "print(r._body.emulator.pid, flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE, text=True)
    try:
        emulator = int(parent.stdout.readline())
        assert alive(emulator)
        parent.kill()
        parent.wait(5)
        eventually(lambda: not alive(emulator), timeout=5, what="the orphan to stop")
    finally:
        parent.kill()
        parent.wait(5)
        parent.stdout.close()


@pytest.mark.parametrize("backend", ["sim", "hardware"])
def test_the_odometer_errs_by_the_same_share_whichever_way_the_robot_faces(
        world_of: WorldMaker, backend: str) -> None:
    """Its error was applied along the world's x and y axes: the same robot driving
    east or north read 2.05 m or 1.96 m for 2.0 m, and its track turned from its own
    heading on a diagonal."""
    read = {}
    for heading in (0.0, math.pi / 4, math.pi / 2):
        world = world_of(size=(20, 20), seed=10)
        robot = world.add_robot("r", (10.0, 10.0, heading), backend=backend)
        robot.drive(0.5, 0.0)
        world.step(4.0)
        start, (x, y, _) = (10.0, 10.0), robot.odometry()
        true = math.dist(start, world.pose("r")[:2])
        read[heading] = math.dist(start, (x, y)) / true
        assert math.atan2(y - 10.0, x - 10.0) == pytest.approx(heading, abs=0.02)
    assert max(read.values()) - min(read.values()) < 0.002, read


def test_dead_sonars_and_odometry_bias_are_injected_and_cleared(world_of: WorldMaker) -> None:
    world = world_of(size=(10, 8), seed=3)
    world.add_wall((4, 0), (4, 8))
    robot = world.add_robot("hw", POSE, backend="hardware")
    world.step(0.5)
    robot.inject("sonar_dead", sonars=[3, 4])
    assert robot.sonar()[3] == robot.sonar()[4] == sonar.MAX_RANGE
    assert robot.sonar()[2] < sonar.MAX_RANGE
    robot.inject("odometry_bias", bias=0.2)
    robot.drive(0.5, 0.0)
    world.step(2.0)
    assert abs(robot.odometry()[2] - world.pose("hw")[2]) > 0.1  # heading drifts per metre
    robot.clear()
    assert robot.sonar()[3] < sonar.MAX_RANGE
    # a wrong transducer number is refused before it reaches the robot (16 broke every
    # later step, even after clear(); -1 silently killed transducer 15)
    for wrong in ([16], [-1], [2.5], [True]):
        with pytest.raises(ValueError, match=r"sonars must be transducer numbers 0-15"):
            robot.inject("sonar_dead", sonars=wrong)
    with pytest.raises(ValueError, match="bias must be a finite number"):
        robot.inject("odometry_bias", bias=math.nan)
    world.step(0.5)
    assert robot.sonar()[3] < sonar.MAX_RANGE and not robot._body.faults


def test_a_swap_leaves_no_fault_of_the_old_hardware_robot_behind(world_of: WorldMaker) -> None:
    world = world_of(size=(10, 8), seed=3)
    robot = world.add_robot("hw", POSE, backend="hardware")
    robot.inject("odometry_bias", bias=0.3)
    robot.swap("sim")
    robot.swap("hardware")                      # a fresh robot: no fault listed, none acting
    assert robot._body.faults == {}
    robot.drive(0.5, 0.0)
    world.step(3.0)                             # (before, the bias drifted it 0.3 rad per m)
    assert robot.odometry()[2] == pytest.approx(world.pose("hw")[2], abs=0.05)


def test_a_back_end_swap_mid_run_leaves_the_controller_untouched(world_of: WorldMaker) -> None:
    world = world_of(size=(20, 20), seed=5)
    robot = world.add_robot("r", (10.0, 10.0, 0.0), backend="sim")

    def controller(seconds: float) -> None:              # knows only its Robot handle
        for _ in range(int(seconds * 10)):
            robot.drive(0.3, 0.3 if min(robot.sonar()[2:6]) > 1.0 else 1.0)
            world.step(0.1)

    controller(2.0)
    before = world.pose("r")
    robot.swap("hardware")
    assert robot.backend == "hardware" and world.pose("r") == pytest.approx(before)
    controller(2.0)
    moved = world.pose("r")
    robot.swap("sim")
    controller(1.0)
    assert robot.backend == "sim"
    assert math.dist(before[:2], moved[:2]) > 0.3
    assert math.dist(moved[:2], world.pose("r")[:2]) > 0.1
    with pytest.raises(ValueError, match="backend must be one of sim, hardware"):
        robot.swap("quantum")


def test_a_hardware_robot_inside_a_virtual_obstacle_is_not_swapped_to_sim(
        world_of: WorldMaker) -> None:
    """It passes through a virtual box; swapped to "sim" there, it stood boxed in."""
    world = world_of(size=(10, 10), seed=1)
    world.add_box(center=(5.0, 5.0), size=(2.0, 2.0), virtual=True)
    robot = world.add_robot("h", (4.5, 5.0, 0.0), backend="hardware")
    with pytest.raises(ValueError, match=r"robot h: at \(4.50, 5.00\) a sim robot would "
                                         r"overlap obstacle 0 .*; drive it clear first"):
        robot.swap("sim")
    assert robot.backend == "hardware"
    robot.drive(0.0, 0.0)
    world.step(0.1)                                      # its emulator serves it still
    assert world.pose("h")[:2] == pytest.approx((4.5, 5.0), abs=0.01)


def test_the_camera_finds_a_coloured_robot_at_its_bearing_unless_hidden() -> None:
    world = World(size=(10, 8), seed=6)
    watcher = world.add_robot("watcher", POSE, color="red")
    world.add_robot("target", (4.0, 3.0, 0.0), color="blue")
    (blob,) = watcher.camera()
    assert blob.bearing == pytest.approx(math.atan2(1.0, 2.0), abs=1e-9)
    assert blob.hue == pytest.approx(240.0)
    assert blob.size == pytest.approx(2 * math.asin(0.25 / math.hypot(2.0, 1.0)))
    assert watcher.camera(hue=240.0) == [blob] and watcher.camera(hue=0.0) == []
    world.add_wall((3.0, 2.0), (3.0, 4.0))
    assert watcher.camera() == []                               # behind a wall
    assert watcher.others()["target"][:2] == pytest.approx((4.0, 3.0))


def test_a_robot_behind_another_robot_is_hidden_from_the_camera() -> None:
    """Only walls hid a robot: one wholly behind another was seen through it."""
    world = World(size=(10, 8), seed=6)
    watcher = world.add_robot("a", (1.0, 4.0, 0.0), color="red")
    world.add_robot("b", (2.0, 4.0, 0.0), color="green")
    world.add_robot("c", (3.5, 4.0, 0.0), color="blue")
    (blob,) = watcher.camera()
    assert blob.hue == pytest.approx(120.0) and blob.distance == pytest.approx(0.75)
    world.add_robot("d", (3.5, 5.0, 0.0), color="yellow")      # beside b: in sight
    assert [round(b.hue) for b in watcher.camera()] == [120, 60]


def test_the_same_seed_gives_the_same_run_and_another_seed_other_noise() -> None:
    def run(seed: int) -> np.ndarray:
        readings = []
        with World.load("rave/worlds/arena.toml", seed=seed) as world:  # one hardware robot
            for i in range(30):
                for robot in world.robots.values():
                    robot.drive(0.4, 0.5 if i % 10 < 5 else -0.5)
                    readings.append(robot.sonar())
                world.step(0.1)
                readings.append(np.array([c for r in world.robots for c in world.pose(r)]))
        return np.concatenate(readings)

    assert np.array_equal(run(5), run(5))
    assert not np.array_equal(run(5), run(6))


def test_bundled_worlds_load_and_a_bad_world_file_reports_every_problem(
        tmp_path, monkeypatch) -> None:
    """A bundled world loads by its name as ``rave start`` takes it, from any directory
    (its path relative to the repository worked from the repository's root only)."""
    monkeypatch.chdir(tmp_path)
    for name in ("arena", "lab"):
        with World.load(name, robots=False) as world:
            assert world.obstacles and any(o.virtual for o in world.obstacles)
        with World.load(REPO / "rave" / "worlds" / f"{name}.toml") as world:
            assert world.obstacles and world.robots
    with pytest.raises(WorldError, match="no world 'arean': the bundled worlds are arena,"):
        World.load("arean")
    bad = tmp_path / "bad.toml"
    bad.write_text("""
name = 5
size = [10, -1]
colour = "red"
[[walls]]
from = [0, 0]
[[walls]]
from = [1, 1]
to = [1, 1]
[[boxes]]
center = [1, 1]
size = [1, 1]
color = "mauve"
[[robots]]
name = "r1"
pose = [1, 1]
backend = "holographic"
[[robots]]
name = "r1"
pose = [2, 2, 0]
color = 3
""")
    with pytest.raises(WorldError) as error:
        World.load(bad)
    problems = error.value.problems
    for expected in ("unknown key 'colour'", "size must be [width, height]",
                     "walls[0]: to must be [x, y]", "boxes[0]: unknown colour 'mauve'",
                     "robots[0]: pose must be [x, y, heading in degrees]",
                     "robots[0]: backend must be one of sim, hardware",
                     "robots[1]: a robot named 'r1' comes earlier",
                     "walls[1]: from and to are the same point: a wall needs a length",
                     # (an int colour failed with AttributeError, a traceback)
                     "name must be a non-empty string",
                     "robots[1]: color must be a name or \"#rrggbb\", not 3"):
        assert any(expected in p for p in problems), (expected, problems)


def test_a_closed_world_says_so_and_a_heading_starts_wrapped() -> None:
    """Stepped after ``close``, a world with a hardware robot said its emulator was
    gone and to swap the robot to 'sim'; a robot placed at 4 pi read 4 pi on its
    odometer (0 by GPS) until it moved."""
    world = World(seed=1)
    robot = world.add_robot("a", (1.0, 1.0, 4 * math.pi))
    assert robot.gps()[2] == robot.odometry()[2] == 0.0
    world.close()
    for call in (lambda: world.step(0.1), lambda: world.add_robot("b", (3.0, 3.0, 0.0))):
        with pytest.raises(RuntimeError, match="world 'world' is closed"):
            call()


def test_a_world_file_placing_a_robot_in_an_obstacle_or_another_robot_names_each(
        tmp_path) -> None:
    placed = tmp_path / "placed.toml"
    placed.write_text("""
size = [10.0, 8.0]
[[walls]]
from = [3.0, 0.0]
to = [3.0, 8.0]
[[boxes]]
center = [6.0, 4.0]
size = [2.0, 2.0]
[[boxes]]
center = [8.5, 6.5]
size = [1.0, 1.0]
virtual = true
[[robots]]
name = "across"
pose = [3.1, 4.0, 0.0]
[[robots]]
name = "boxed"
pose = [6.0, 4.0, 0.0]
[[robots]]
name = "a"
pose = [1.0, 1.0, 0.0]
[[robots]]
name = "b"
pose = [1.3, 1.0, 0.0]
[[robots]]
name = "ghost"
pose = [8.5, 6.5, 0.0]
backend = "hardware"
[[robots]]
name = "fine"
pose = [1.0, 6.0, 0.0]
""")
    with pytest.raises(WorldError) as error:       # (before, they ran stuck or pushed through)
        World.load(placed)
    problems = error.value.problems
    assert len(problems) == 3, problems       # not 'ghost': a hardware robot passes virtual
    for expected in ("robots[0] 'across': at (3.1, 4.0) it overlaps walls[0]",
                     "robots[1] 'boxed': at (6.0, 4.0) it overlaps boxes[0]",
                     "robots[3] 'b': at (1.3, 1.0) it overlaps robot 'a'"):
        assert any(expected in p for p in problems), (expected, problems)
    assert "0.25 m clear" in problems[0]


def test_the_batched_scan_of_a_crowd_equals_casting_every_ray_against_everything(
        world_of: WorldMaker) -> None:
    """Also after the robots have wandered (the neighbour lists are kept from scan to
    scan), with a concave polygon, a hardware robot among them, and a robot hugging a
    box (where no side of it may be skipped)."""
    world = world_of(size=(12, 12), seed=8)
    for i in range(4):
        world.add_box(center=(2.0 + 3 * i, 6.0), size=(0.5, 1.5), angle=0.3 * i,
                      virtual=i % 2 == 0)
    world.add_polygon([(1, 1), (4, 1), (4, 3), (3, 2), (1, 3)])          # concave
    world.add_wall((0, 0), (12, 0))
    world.add_robot("hugger", (2.0, 4.975, 0.0))     # 5 mm off a box
    world.add_robot("h", (6.0, 9.0, 1.0), backend="hardware")
    rng = np.random.default_rng(8)
    while len(world.robots) < 26:               # (a pose that overlaps is refused)
        with contextlib.suppress(ValueError):
            world.add_robot(f"r{len(world.robots)}",
                            (*rng.uniform(0.5, 11.5, 2), rng.uniform(-3, 3)))
    fleet = world.fleet
    start = fleet.pose.copy()
    for tick in range(30):
        world.step(0.1)
        blocked = fleet.sonar_all()[:, 1:7].min(axis=1) < 0.8
        fleet.drive_all(0.8, np.where(blocked, 2.0, rng.uniform(-0.5, 0.5, len(blocked))))
        if tick in (0, 14, 29):
            _assert_scan_equals_casting_every_ray(world)
    moved = np.hypot(*(fleet.pose[:, 0:2] - start[:, 0:2]).T)
    assert np.median(moved) > 1.0                # well past the lists' skin


def _assert_scan_equals_casting_every_ray(world: World) -> None:
    poses = world.fleet.pose
    batched = world.fleet.ranges().reshape(len(poses), sonar.COUNT, sonar.RAYS)
    for slot, name in enumerate(world.fleet.names):
        o, d = sonar.rays(tuple(poses[slot]))
        each = raycast.cast(o, d, sonar.MAX_RANGE, world.segments(),
                            world.discs(exclude=name)).ranges.reshape(16, sonar.RAYS)
        np.testing.assert_allclose(batched[slot], each, rtol=1e-9, err_msg=name)
    assert np.isfinite(batched).mean() > 0.2          # the crowd does see things


def test_the_fleet_reads_and_drives_every_simulated_robot_at_once() -> None:
    world = World(size=(10, 10), seed=2)
    world.add_wall((6, 0), (6, 10))
    for i in range(3):
        world.add_robot(f"r{i}", (2.0, 2.0 + 2 * i, 0.0))
    fleet = world.fleet
    assert fleet.names == ["r0", "r1", "r2"]
    fleet.drive_all([0.5, 9.0, -9.0], 0.0)                    # clipped as drive() clips
    assert fleet.command[:, 0].tolist() == [0.5, 1.5, -1.5]
    with pytest.raises(ValueError, match="read-only"):          # commands go through drive
        fleet.command[0] = (0.0, 0.0)
    world.step(1.0)
    speeds = [world.robot(n).velocity()[0] for n in fleet.names]
    assert speeds == pytest.approx([0.5, 1.5, -1.5], abs=0.01)
    readings = fleet.sonar_all()
    assert readings.shape == (3, 16)
    np.testing.assert_array_equal(readings[1], world.robot("r1").sonar())
    ahead = [6.0 - world.robot(n).gps()[0] - 0.166 for n in fleet.names]   # transducer 3
    assert readings[:, 3] == pytest.approx([ahead[0], ahead[1], 5.0], abs=0.05)
    with pytest.raises(ValueError, match="finite"):
        fleet.drive_all(np.nan, 0.0)
    with pytest.raises(ValueError, match="3 values each"):
        fleet.drive_all([1.0, 2.0], 0.0)


def test_robots_leaving_and_joining_mid_run_leave_the_others_driving_as_commanded() -> None:
    world = World(size=(20, 8), seed=3)
    for i in range(3):
        world.add_robot(f"r{i}", (2.0 + 4 * i, 3.0, 0.0)).drive(0.5, 0.0)
    world.step(1.0)
    world.remove_robot("r1")                     # the fleet's rows close up behind it
    world.add_robot("r3", (2.0, 6.0, 0.0)).drive(0.0, 1.0)
    world.robot("r2").drive(0.0, -1.0)
    world.step(1.0)
    assert list(world.robots) == ["r0", "r2", "r3"] and world.fleet.names == ["r0", "r2", "r3"]
    assert world.pose("r0") == pytest.approx((3.0, 3.0, 0.0), abs=0.01)
    assert world.pose("r2") == pytest.approx((10.5, 3.0, -1.0), abs=0.01)
    assert world.pose("r3") == pytest.approx((2.0, 6.0, 1.0), abs=0.01)
    for name in world.fleet.names:                 # each row still stands for its robot
        body = world.robot(name)._body.body
        assert world.pose(name)[:2] == pytest.approx(tuple(body.position), abs=1e-9)
    assert world.robot("r0").sonar()[3] == pytest.approx(5.0)    # r1 gone: nothing ahead


def test_a_pose_or_a_point_that_is_not_finite_is_refused_naming_it() -> None:
    world = World(seed=3)
    seer = world.add_robot("a", (2.0, 4.0, 0.0))
    world.add_robot("b", (3.0, 4.0, 0.0))
    with pytest.raises(ValueError, match=r"robot n: pose must be finite .*\(nan, 1.0, 0.0\)"):
        world.add_robot("n", (math.nan, 1.0, 0.0))       # (it hid every robot from sonars)
    world.step(0.1)
    assert seer.sonar()[3] < 1.0 and list(world.robots) == ["a", "b"]
    with pytest.raises(ValueError, match=r"wall: points must be finite .*\(nan, 0.0\)"):
        world.add_wall((math.nan, 0.0), (1.0, 1.0))
    with pytest.raises(ValueError, match=r"wall: both its ends are \(1.0, 1.0\)"):
        world.add_wall((1, 1), (1.0, 1.0))                # (a numpy warning at every scan)
    with pytest.raises(ValueError, match=r"polygon: points must be finite"):
        world.add_polygon([(0, 0), (1, 0), (math.inf, 1)])
    with pytest.raises(ValueError, match=r"box: size must be \(width, height\), both > 0"):
        world.add_box((5.0, 5.0), (-1.0, 1.0))
    with pytest.raises(ValueError, match=r"step\(inf\): dt must be a finite"):
        world.step(math.inf)
    assert not world.obstacles


def test_a_robot_added_after_another_left_draws_randomness_of_its_own() -> None:
    world = World(seed=3)
    world.add_robot("a", (1.0, 1.0, 0.0))
    kept = world.add_robot("b", (3.0, 1.0, 0.0))
    world.remove_robot("a")
    added = world.add_robot("c", (5.0, 1.0, 0.0))        # (it had b's stream: b's errors)
    assert not np.allclose(added.odometer.scale, kept.odometer.scale)
    assert added.rng.random() != kept.rng.random()


def test_a_simulated_robot_turning_steadily_drives_a_circle_back_to_its_start() -> None:
    world = World(size=(10, 10), seed=1)
    robot = world.add_robot("r", (5.0, 3.0, 0.0))
    robot.drive(0.5, 0.5)                                   # a 1 m radius, 4 pi s round
    world.step(2 * math.pi)
    assert world.pose("r")[:2] == pytest.approx((5.0, 5.0), abs=0.03)   # half way: top
    assert robot.odometry()[:2] == pytest.approx((5.0, 5.0), abs=0.3)  # (it drifts)
    world.step(2 * math.pi)
    assert world.pose("r")[:2] == pytest.approx((5.0, 3.0), abs=0.05)


def test_a_perfect_odometer_follows_the_true_path_however_seldom_it_is_read() -> None:
    """The fleet writes bodies only when commands change and reads them only when
    asked, dead-reckoning each stretch between reads: reading changes no motion,
    and an odometer without error stays on the true path."""
    plan = [(0.5, 0.0), (0.5, 0.8), (0.0, -2.0), (-0.3, 0.4), (1.2, -0.2)]

    def run(read_every: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
        world = World(size=(20, 20), seed=4)
        robot = world.add_robot("r", (10.0, 10.0, 0.3))
        world.fleet.odometry_scale[:] = 1.0                        # no odometry error
        for tick in range(60):
            robot.drive(*plan[tick // 12])
            world.step(0.1)
            if tick % read_every == 0:
                robot.velocity()
        return world.pose("r"), robot.odometry()

    pose, reckoned = run(read_every=1)
    seldom = run(read_every=7)
    assert seldom[0] == pose                                    # bit for bit
    # A stretch is taken for equal steps; the first step after a command change
    # still moves as the one before did: some millimetres over 4.5 m of path.
    assert seldom[1] == pytest.approx(reckoned, abs=3e-3)
    assert reckoned == pytest.approx(pose, abs=0.02)


def test_dead_reckoning_runs_of_equal_steps_in_closed_form_equals_step_by_step() -> None:
    rng = np.random.default_rng(1)
    start = rng.uniform(-3.0, 3.0, (5, 3))
    scale = rng.uniform(0.95, 1.05, (5, 3))
    distance, rotation = rng.uniform(-0.02, 0.02, 5), rng.uniform(-0.05, 0.05, 5)
    rotation[0] = 0.0                                           # straight
    by_steps, closed = start.copy(), start.copy()
    odometry.dead_reckon(by_steps, scale, np.tile(distance, (40, 1)), np.tile(rotation, (40, 1)))
    odometry.dead_reckon_arcs(closed, scale, distance, rotation, 40)
    np.testing.assert_allclose(closed, by_steps, rtol=0, atol=1e-12)


def test_a_turning_robot_keeps_its_turn_rate_when_another_robot_shoves_it() -> None:
    world = World(size=(10, 10), seed=2)
    turner = world.add_robot("turner", (5.0, 5.0, 0.0))
    world.add_robot("pusher", (3.0, 5.0, 0.0)).drive(1.0, 0.0)
    turner.drive(0.0, 1.0)                                      # turning on the spot
    world.step(2.0)                                             # shoved from 1.5 s on
    assert world.pose("turner")[0] > 5.2                        # it was pushed
    assert turner.velocity()[2] == pytest.approx(1.0, abs=1e-9)
    assert world.pose("turner")[2] == pytest.approx(2.0, abs=0.011)


@pytest.mark.parametrize("changing", [3, 30])
def test_new_commands_move_robots_alike_set_one_by_one_or_in_one_batch(
        monkeypatch: pytest.MonkeyPatch, changing: int) -> None:
    def run(one_by_one: int) -> np.ndarray:
        monkeypatch.setattr(fleet_module, "ONE_BY_ONE", one_by_one)
        world = World(size=(30, 30), seed=5)
        for i in range(30):
            world.add_robot(f"r{i}", (3.0 + 4 * (i % 6), 3.0 + 4 * (i // 6), i / 5))
        rng = np.random.default_rng(1)
        v, w = np.zeros(30), np.zeros(30)
        for _ in range(30):
            chosen = rng.choice(30, changing, replace=False)
            v[chosen], w[chosen] = rng.uniform(-1, 1, changing), rng.uniform(-2, 2, changing)
            world.fleet.drive_all(v, w)
            world.step(0.1)
        return np.array([world.pose(name) for name in world.fleet.names])

    one_by_one, batched = run(one_by_one=1000), run(one_by_one=0)
    np.testing.assert_array_equal(one_by_one, batched)
    assert np.ptp(one_by_one[:, 0]) > 15                        # they did move


def test_an_emulator_that_fails_to_start_leaves_no_process_behind() -> None:
    before = {child.pid for child in psutil.Process().children()}
    with pytest.raises(RuntimeError, match="the emulator of robot r9 failed") as failed:
        EmulatorProcess("r9", np.zeros((1, 3)), (0.0, 0.0, 0.0), seed=1)   # not segments
    # the error (and through its traceback the failed handle) is still held here
    assert failed.value is not None
    started = {child.pid for child in psutil.Process().children()} - before
    assert not [pid for pid in started if alive(pid)]


def _failing_emulators(monkeypatch: pytest.MonkeyPatch, after: int = 0) -> None:
    """Every emulator started after the first ``after`` fails to start (its child exits)."""
    real, started = rave_emulator._CHILD, []
    start = EmulatorProcess.__init__

    def init(self: EmulatorProcess, *args: Any, **kwargs: Any) -> None:
        started.append(1)
        monkeypatch.setattr(rave_emulator, "_CHILD",
                            real if len(started) <= after else "import sys; sys.exit(3)")
        start(self, *args, **kwargs)
    monkeypatch.setattr(EmulatorProcess, "__init__", init)


def test_a_swap_whose_emulator_fails_to_start_leaves_the_robot_as_it_was(
        world_of: WorldMaker, monkeypatch: pytest.MonkeyPatch) -> None:
    """The old body was closed first: the robot then drove another robot's row."""
    world = world_of(size=(10, 8), seed=1)
    a = world.add_robot("a", POSE)
    b = world.add_robot("b", (6.0, 6.0, 0.0))
    _failing_emulators(monkeypatch)
    with pytest.raises(RuntimeError, match="emulator of robot a is gone"):
        a.swap("hardware")
    assert a.backend == "sim" and a.gps() == pytest.approx(POSE)
    a.drive(1.0, 0.0)
    world.step(1.0)
    assert a.gps()[0] > POSE[0] + 0.5 and b.gps() == pytest.approx((6.0, 6.0, 0.0))
    assert sorted(world.fleet.names) == ["a", "b"]


def test_a_reversing_robot_swapped_to_hardware_goes_on_reversing(world_of: WorldMaker) -> None:
    world = world_of(size=(10, 8), seed=1)
    robot = world.add_robot("r", (5.0, 4.0, 0.0))
    robot.drive(-0.5, 0.0)
    world.step(1.0)
    x = world.pose("r")[0]
    robot.swap("hardware")
    world.step(0.2)
    assert world.pose("r")[0] < x              # (it went 0.2 m forward first, at +0.35 m/s)


def test_a_silent_emulator_is_said_to_be_so_and_a_long_step_waits_for_its_steps(
        world_of: WorldMaker, monkeypatch) -> None:
    """The step that finds an emulator silent is taken by the world and the other
    hardware robots, which have stepped (they stayed that step ahead for good)."""
    def world_with_two() -> tuple[World, Any]:
        world = world_of(size=(20, 10), seed=1)
        robot = world.add_robot("hw", POSE, backend="hardware")
        world.add_robot("live", (1.0, 6.0, 0.0), backend="hardware").drive(0.3, 0.0)
        world.step(120.0)               # 12,000 physics steps: more than 5 s on a slow day
        return world, robot

    world, robot = world_with_two()
    os.kill(robot._body.emulator.pid, signal.SIGSTOP)
    # (the silent one waited for 2 s, not the 5 s of an answer's timeout: the long step
    # above was given those, and what is told of a silent one is the same)
    with monkeypatch.context() as quick:
        quick.setattr(rave_emulator, "ANSWER_TIMEOUT", 2.0)
        with pytest.raises(TimeoutError, match="emulator of robot hw did not answer within"):
            world.step(1.0)             # (before: "is gone ... exited with -9")
    assert world.time == pytest.approx(121.0)
    robot.swap("sim")
    world.step(1.0)
    control, _ = world_with_two()       # the same run, nothing silent
    control.step(2.0)
    assert world.pose("live") == pytest.approx(control.pose("live"), abs=1e-9)
    assert world.robot("live").odometry() == pytest.approx(
        control.robot("live").odometry(), abs=1e-9)


def test_a_real_obstacle_is_not_added_while_a_hardware_robot_is_gone(
        world_of: WorldMaker) -> None:
    """Before, it went into the world and the emulators before the dead one, not into
    those after it: a hardware robot drove through the new wall."""
    world = world_of(size=(10, 8), seed=1)
    dead = world.add_robot("dead", (2.0, 6.0, 0.0), backend="hardware")
    live = world.add_robot("live", (4.0, 2.0, 0.0), backend="hardware")
    os.kill(dead._body.emulator.pid, signal.SIGKILL)
    with pytest.raises(RuntimeError, match="emulator of robot dead is gone"):
        world.step(0.1)                 # (its death seen)
    with pytest.raises(RuntimeError, match="emulator of robot dead is gone"):
        world.add_wall((5.0, 0.0), (5.0, 8.0))
    assert world.obstacles == []        # (before: in the world, not in "live"'s emulator)
    world.robot("dead").swap("sim")
    world.add_wall((5.0, 0.0), (5.0, 8.0))
    live.drive(0.5, 0.0)
    world.step(4.0)
    assert world.pose("live")[0] < 5.0 - 0.2


def test_a_box_angle_that_is_not_a_finite_number_is_refused(world_of: WorldMaker,
                                                             tmp_path) -> None:
    world = world_of(size=(10, 8), seed=1)
    for angle in (math.nan, math.inf, "thirty"):
        with pytest.raises(ValueError, match="box: angle must be a finite number"):
            world.add_box((8.0, 2.0), (1.0, 1.0), angle=angle)
    assert world.obstacles == []
    for angle in ("nan", "inf", '"thirty"'):
        path = tmp_path / "box.toml"
        path.write_text(f"[[boxes]]\ncenter = [8.0, 2.0]\nsize = [1.0, 1.0]\nangle = {angle}\n")
        with pytest.raises(WorldError, match=r"boxes\[0\]: angle must be a finite number"):
            World.load(path)


def test_a_world_file_whose_robot_fails_to_start_leaves_no_emulator_running(
        tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "two.toml"
    path.write_text('[[robots]]\nname = "a"\npose = [2.0, 2.0, 0.0]\nbackend = "hardware"\n'
                    '[[robots]]\nname = "b"\npose = [6.0, 6.0, 0.0]\nbackend = "hardware"\n')
    before = {child.pid for child in psutil.Process().children()}
    _failing_emulators(monkeypatch, after=1)
    with pytest.raises(RuntimeError, match="emulator of robot b is gone") as failed:
        World.load(path, seed=1)
    assert failed.value is not None         # (held: the world is not collected yet)
    started = {child.pid for child in psutil.Process().children()} - before
    assert not [pid for pid in started if alive(pid)]


def test_a_robot_added_over_an_obstacle_or_a_robot_is_refused(world_of: WorldMaker) -> None:
    """As a world file's robot is: it ran stuck, or backwards (the docs' own example
    put one inside a box)."""
    world = world_of(size=(10, 8), seed=1)
    world.add_box((2.5, 2.0), (0.8, 0.8), virtual=True)
    with pytest.raises(ValueError, match=r"robot r: at \(2, 2\) it overlaps obstacle 0"):
        world.add_robot("r", (2.0, 2.0, 0.0))
    world.add_robot("hw", (2.0, 2.0, 0.0), backend="hardware")      # it passes virtual ones
    with pytest.raises(ValueError, match="it overlaps robot 'hw'"):
        world.add_robot("s", (2.0, 2.4, 0.0), backend="hardware")
    # a wall is 0.04 m thick: its centre line 0.26 m off is 0.24 m from its face
    world.add_wall((6.0, 1.0), (6.0, 7.0))
    with pytest.raises(ValueError, match=r"robot w: at \(6.26, 4\) it overlaps obstacle 1"):
        world.add_robot("w", (6.26, 4.0, 0.0))
    assert list(world.robots) == ["hw"]
    world.add_robot("w", (6.28, 4.0, 0.0))


def test_the_camera_sees_a_coloured_obstacle_at_its_nearest_point(world_of: WorldMaker) -> None:
    """It took an obstacle for the disc round its corners: a 3 m bench 1.3 m ahead was
    not seen at all, and 1.8 m ahead it was 0.49 m away. Near, the bench fills the
    view: it spans the field of view, not more."""
    world = world_of(size=(10, 8), seed=1)
    world.add_box(center=(5.0, 4.0), size=(3.0, 0.4), color="orange")
    for y, face in ((0.8, 3.0), (2.0, 1.8), (2.5, 1.3), (3.0, 0.8)):
        robot = world.add_robot(f"r{y}", (5.0, y, math.pi / 2))
        blob, = robot.camera()
        assert blob.distance == pytest.approx(face) and blob.bearing == pytest.approx(0.0)
        assert blob.size == pytest.approx(min(2 * math.atan2(1.5, face), camera.FOV))
        world.remove_robot(robot.name)


def test_the_camera_sees_the_part_of_an_obstacle_in_its_view(world_of: WorldMaker) -> None:
    """Of a U-shaped obstacle it saw the disc round its corners: inside the pocket,
    facing the back, nothing (the middle of the corners was behind); between the arms,
    an arm 1.2 m to the side, out of view, spanning 260 degrees."""
    world = world_of(size=(10, 8), seed=1)
    world.add_polygon([(3.5, 3.0), (3.8, 3.0), (3.8, 5.7), (6.2, 5.7), (6.2, 3.0),
                       (6.5, 3.0), (6.5, 6.0), (3.5, 6.0)], color="orange")
    for (y, heading), seen in {(5.0, math.pi / 2): (0.7, 0.0, camera.FOV),   # the back
                               (4.0, math.pi / 2): (1.7, 0.0, camera.FOV),
                               (2.0, math.pi / 2): (math.hypot(1.2, 1.2 / math.tan(camera.FOV / 2)),
                                                    0.0, camera.FOV),    # the arms' insides
                               # into its corner: the back and an arm at the view's edges
                               (4.5, math.pi / 4): (1.2 / math.cos(math.pi / 4 - camera.FOV / 2),
                                                    0.0, camera.FOV),
                               (5.0, -math.pi / 2): None}.items():      # facing out of it
        robot = world.add_robot(f"r{y}-{heading:.2f}", (5.0, y, heading))
        blobs = robot.camera()
        if seen is None:
            assert blobs == []
        else:
            blob, = blobs
            assert blob.distance == pytest.approx(seen[0])
            assert abs(blob.bearing) + blob.size / 2 <= camera.FOV / 2 + 1e-9   # in view
            assert blob.bearing == pytest.approx(seen[1], abs=1e-9)
            assert blob.size == pytest.approx(seen[2])
        world.remove_robot(robot.name)


def test_a_robot_backed_against_another_senses_it_behind(world_of: WorldMaker) -> None:
    """The rear transducers sit just off the rim (0.256 m from the centre): touching
    another robot they are inside its disc, and their rays, cast from outside only,
    read no echo (5 m) from a robot pressed against them."""
    world = world_of(size=(10, 8), seed=1)
    backing = world.add_robot("a", (5.0, 4.0, 0.0))
    world.add_robot("b", (4.3, 4.0, 0.0))
    backing.drive(-0.3, 0.0)
    world.step(3.0)                                  # it backs into b and stays there
    assert world.pose("a")[0] - world.pose("b")[0] < 2 * 0.256
    rear = backing.sonar()[11:13]                    # the two pointing straight back
    assert (rear <= 0.15).all(), rear
    _assert_scan_equals_casting_every_ray(world)     # the same, cast one by one
