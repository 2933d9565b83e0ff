"""``agents.occupancy``: the sonar inverse model, maps learnt by simulated and hardware
robots on the lab world scored against its truth, and the ``Mapper`` module on its own."""

from __future__ import annotations

import itertools
import math
import statistics
import time
from dataclasses import asdict
from pathlib import Path

import cloudpickle
import numpy as np
import pytest

from agents.grid import FREE, OCCUPIED, UNKNOWN, UNSEEN, Grid, classify
from agents.map_truth import MapScore, reachable, score, truth
from agents.occupancy import Mapper, OccupancyGrid, SonarModel
from pb3a.testing import ModuleHarness
from rave import World, sonar
from rave.robot import Robot

LAB = Path(__file__).resolve().parent.parent / "rave" / "worlds" / "lab.toml"
START = (1.0, 1.5, 0.0)
# A tour of the lab in four legs, each ending where the next begins: the middle room,
# the west room and back to the corridor, the corridor's east end, the east room.
TOUR = [[(5.0, 1.5), (6.0, 2.0), (6.0, 5.5), (6.0, 7.6)],
        [(3.4, 7.6), (3.4, 4.2), (2.0, 4.0), (2.0, 1.8)],
        [(9.0, 1.5), (10.0, 2.2), (10.0, 3.8)],
        [(8.6, 4.0), (8.6, 7.6), (11.0, 7.6)]]
EXACT = sonar.SonarNoise(sigma0=0.0, sigma_per_m=0.0)


def _lab(seed: int) -> World:
    """The lab's walls and furniture without the robots its file places (one of them
    a hardware robot, with an emulator process this test does not want)."""
    return World.load(LAB, seed, robots=False)


def _map_the_tour(world: World, robot: Robot, grid: OccupancyGrid) -> list[MapScore]:
    """Drive ``robot`` round ``TOUR`` (a proportional controller, one reading per 0.1 s
    step folded into ``grid`` at the robot's gps pose); the map's score after each leg."""
    occupied = truth(world, grid.grid)
    free_space = reachable(occupied, grid.grid, START[:2])
    scores = []
    for leg in TOUR:
        for goal_x, goal_y in leg:
            for _ in range(300):
                x, y, theta = robot.gps()
                if math.hypot(goal_x - x, goal_y - y) < 0.2:
                    break
                error = math.remainder(math.atan2(goal_y - y, goal_x - x) - theta, math.tau)
                robot.drive(0.5 * max(0.0, math.cos(error)) ** 2, max(-1.5, min(1.5, 2 * error)))
                world.step(0.1)
                grid.update(robot.gps(), robot.sonar())
            else:
                pytest.fail(f"the robot did not reach {goal_x, goal_y}; it is at {robot.gps()}")
        scores.append(score(grid.probabilities(), occupied, free_space))
    return scores


def _assert_converges(scores: list[MapScore], accuracy: float, coverage: float) -> None:
    figures = [(round(s.accuracy, 3), round(s.coverage, 3)) for s in scores]
    assert all(s.accuracy >= accuracy for s in scores), figures
    assert all(a.coverage < b.coverage for a, b in itertools.pairwise(scores)), figures
    assert scores[-1].coverage >= coverage, figures


def test_a_simulated_robot_touring_the_lab_maps_it_accurately() -> None:
    # measured: accuracy 0.95-0.97 throughout, coverage 0.45, 0.63, 0.77, 0.89 (the
    # parameters of the notes, occupied 0.85 and free -0.4, give 0.91-0.93 and 0.80).
    # A simulated ring hears every echo, at any angle: no specular reflection to
    # allow for (the default model's, for hardware, keeps 0.94-0.96 and 0.87)
    with _lab(seed=1) as world:
        robot = world.add_robot("r", START, backend="sim")
        grid = OccupancyGrid(Grid.of(world.size), SonarModel(specular_deg=90.0))
        _assert_converges(_map_the_tour(world, robot, grid), accuracy=0.94, coverage=0.85)


def test_a_hardware_robot_with_noise_and_specular_dropouts_maps_it_too() -> None:
    # measured: accuracy 0.96, 0.94, 0.94, 0.94, coverage 0.48, 0.69, 0.83, 0.96. No
    # echo clearing as much as an echo (-0.4) gives 0.93: grazing beams clear walls;
    # folding in the ring's repeated echoes gives 0.92-0.93. Leaving out every repeat
    # of no echo too (as once) gave 0.95-0.96 but only 0.43 ... 0.95 here, and left a
    # robot that stands in a corridor blind to the space ahead of it (below); letting
    # grazing beams clear walls the map holds gives 0.93-0.94. The boxes' insides,
    # which no echo comes from, are most of what is still wrong.
    with _lab(seed=1) as world:
        robot = world.add_robot("r", START, backend="hardware")
        grid = OccupancyGrid(Grid.of(world.size))
        scores = _map_the_tour(world, robot, grid)
        _assert_converges(scores, accuracy=0.93, coverage=0.9)
    # and it finds the walls it passes (measured 0.40, 0.50, 0.63, 0.76)
    assert all(a.walls < b.walls for a, b in itertools.pairwise(scores))
    assert scores[-1].walls >= 0.7


def _wall_ahead(pose: tuple[float, float, float] = (2.0, 4.5, 0.0),
                rng: np.random.Generator | None = None) -> np.ndarray:
    """The ring's reading at ``pose`` of a long wall across x = 4 m, nothing else."""
    noise = EXACT if rng is None else sonar.MODEL_NOISE
    return sonar.read(pose, np.array([[4.0, -10.0, 4.0, 20.0]]), None, noise,
                      rng or np.random.default_rng(0))


def test_a_wall_ahead_is_occupied_at_its_range_free_before_it_and_unknown_behind() -> None:
    grid = OccupancyGrid(Grid(12.0, 9.0))
    grid.update((2.0, 4.5, 0.0), _wall_ahead())
    row = grid.log_odds[45]                                  # y = 4.5-4.6, the robot's axis
    assert (row[25:37] < 0).all()                            # x = 2.5-3.7: the beam passed
    assert np.argmax(row) in (39, 40) and row.max() > 0      # the wall, x = 3.9-4.1
    assert (grid.log_odds[:, 41:] == 0).all()                # behind it: nothing learnt
    assert grid.log_odds.min() >= -SonarModel().clamp


def test_no_echo_clears_free_space_weakly_out_to_its_limit_and_marks_nothing() -> None:
    model = SonarModel()
    grid = OccupancyGrid(Grid(12.0, 9.0), model)
    grid.update((6.0, 4.5, 0.0), np.full(16, sonar.MAX_RANGE))
    assert grid.log_odds.max() == 0
    assert model.free < grid.log_odds.min() < 0             # weaker than one echo's beam
    xs, ys = grid.grid.centers()
    beyond = np.hypot(xs - 6.0, ys - 4.5) > model.max_free_range + 0.3   # + the ring
    assert (grid.log_odds[beyond] == 0).all()
    assert (grid.log_odds[~beyond] < 0).sum() > 1000


def test_a_robot_standing_still_reaches_the_clamp_and_a_repeated_reading_counts_once() -> None:
    model = SonarModel()
    grid = OccupancyGrid(Grid(12.0, 9.0), model)
    reading = _wall_ahead()
    grid.update((2.0, 4.5, 0.0), reading)
    once = grid.log_odds.copy()
    grid.update((2.0, 4.5, 0.0), reading)                    # the ring has not fired again
    assert np.array_equal(grid.log_odds, once)
    rng = np.random.default_rng(3)
    for _ in range(100):                                     # fresh, noisy readings
        grid.update((2.0, 4.5, 0.0), _wall_ahead(rng=rng))
    assert grid.log_odds.max() == model.clamp and grid.log_odds.min() == -model.clamp
    classes = classify(grid.probabilities())
    assert classes[45, 39] == OCCUPIED and (classes[45, 25:37] == FREE).all()


def test_a_beam_that_keeps_hearing_nothing_clears_the_space_ahead_as_it_fires() -> None:
    # The live failure: a robot at the start of the lab's corridor, whose walls
    # reflect its forward beams away, hears no echo ahead; each report repeats the
    # last (MAX_RANGE, the same number whether a transducer fired again or not), and
    # with every repeat left out the corridor ahead stayed unknown however long the
    # robot looked, so the explorer found no frontier it could resolve.
    grid = OccupancyGrid(Grid(12.0, 9.0))
    silence = np.full(16, sonar.MAX_RANGE)
    ahead = np.s_[14:16, 21:36]                              # y 1.4-1.6, x 2.1-3.6
    grid.update((1.0, 1.5, 0.0), silence)
    once = grid.log_odds.copy()
    grid.update((1.0, 1.5, 0.0), silence)                    # 100 ms on: not fired again
    assert np.array_equal(grid.log_odds, once)
    for _ in range(38):                                      # 4 s of reports in all
        grid.update((1.0, 1.5, 0.0), silence)
    folded = once[ahead] / grid.log_odds[ahead]
    assert np.allclose(folded, 1 / 14, rtol=0.01)            # once per 3 reports: 14 firings
    assert (classify(grid.probabilities())[ahead] == FREE).all()
    stale = OccupancyGrid(Grid(12.0, 9.0), refire_every=10**9)   # every repeat left out
    for _ in range(40):
        stale.update((1.0, 1.5, 0.0), silence)
    assert (classify(stale.probabilities())[ahead] == UNSEEN).all()


def test_a_beam_that_grazes_a_mapped_wall_does_not_clear_it() -> None:
    # A wall along y = 3 m the map holds; a robot driving along it 0.6 m off, its
    # forward beams meeting the wall at a grazing angle and echoing from far beyond
    # (or not at all), as on hardware. A beam square to the wall still clears it.
    def drive(model: SonarModel, heading: float, ranges: np.ndarray) -> np.ndarray:
        grid = OccupancyGrid(Grid(12.0, 9.0), model, skip_repeats=False)
        grid.log_odds[29:31, 20:80] = 2.0                    # y 2.9-3.1, x 2-8
        for step in range(40):
            grid.update((2.0 + 0.1 * step, 2.4, heading), ranges)
        return classify(grid.probabilities())[29:31, 30:70]
    far = np.full(16, 4.0)                                   # echoes from 4 m off
    assert (drive(SonarModel(), 0.0, far) == OCCUPIED).all()
    assert (drive(SonarModel(specular_deg=90.0), 0.0, far) != OCCUPIED).any()
    square = np.full(16, sonar.MAX_RANGE)
    square[[2, 3, 4, 5]] = 2.0                               # facing it, hearing beyond
    assert (drive(SonarModel(), math.pi / 2, square) != OCCUPIED).any()


def test_one_update_of_the_ring_takes_a_few_milliseconds() -> None:
    # measured: about 1.5 ms with every reading long (the widest window), on a busy core
    grid = OccupancyGrid(Grid(12.0, 9.0))
    rng = np.random.default_rng(0)
    times = []
    for _ in range(30):
        ranges = rng.uniform(3.0, sonar.MAX_RANGE, 16)
        start = time.perf_counter()
        grid.update((6.0, 4.5, rng.uniform(-math.pi, math.pi)), ranges)
        times.append(time.perf_counter() - start)
    assert statistics.median(times) < 0.02


def _readings(count: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` (sonar, pose) pairs of a robot creeping along the wall-ahead scene."""
    rng = np.random.default_rng(seed)
    pairs = []
    for step in range(count):
        pose = (1.0 + 0.05 * step, 4.5, 0.1 * math.sin(step))
        pairs.append((_wall_ahead(pose, rng), np.array(pose)))
    return pairs


def test_the_mapper_writes_maps_once_it_has_a_pose() -> None:
    harness = ModuleHarness(Mapper, state={"publish_every": 2})
    readings = _readings(3, seed=1)
    harness.feed("sonar", readings[0][0])                    # no pose yet: nothing to do
    assert harness.written["map"] == [] and harness.state["updates"] == 0
    for reading, pose in readings:
        harness.feed("pose", pose)
        assert len(harness.written["map"]) <= 1              # a pose alone maps nothing
        harness.feed("sonar", reading)
    state = harness.state
    assert state["updates"] == 3 and time.time() - state["last_update"] < 60
    assert len(harness.written["map"]) == 1                  # every second update
    published = harness.last("map")
    assert published.dtype == np.float32 and published.shape == (90, 120)
    assert np.argmax(published[45]) in (39, 40) and published[45].max() > UNKNOWN
    assert published[45, 30] < UNKNOWN                       # the wall, the space before it
    updates = harness.written["updated"]                     # each update: when, and where
    assert [list(u[1:]) for u in updates] == [list(pose) for _, pose in readings]
    assert updates[0][0] <= updates[-1][0] == state["last_update"]


def test_a_reading_whose_pose_is_not_finite_is_skipped_and_counted() -> None:
    """A NaN pose (a localization that lost the robot) failed the mapper in int()'s
    words, after the reading was counted as folded in."""
    harness = ModuleHarness(Mapper)
    (reading, pose), = _readings(1, seed=1)
    harness.feed("pose", np.array([math.nan, pose[1], pose[2]]))
    harness.feed("sonar", reading)
    assert (harness.state["unplaced"], harness.state["updates"]) == (1, 0)
    assert np.isnan(harness.state["last_ranges"]).all()      # nothing folded in
    harness.feed("pose", pose)
    harness.feed("sonar", reading)
    assert (harness.state["unplaced"], harness.state["updates"]) == (1, 1)
    core = OccupancyGrid(Grid.of([12.0, 9.0], 0.1))
    with pytest.raises(ValueError, match="a reading's pose must be finite"):
        core.update((1.0, math.inf, 0.0), reading)
    assert np.isnan(core.last_ranges).all() and not core.unfolded.any()


def test_a_point_on_a_cell_border_is_in_the_cell_above_it_and_its_centre_in_its_own() -> None:
    grid = Grid(12.0, 9.0, 0.1)
    assert grid.cell(0.3, 0.7) == (7, 3)                     # 0.3 / 0.1 = 2.9999999999999996
    rows, cols = grid.cell(np.arange(90) * 0.1, np.arange(90) * 0.1)
    assert (rows == np.arange(90)).all() and (cols == np.arange(90)).all()
    xs, ys = grid.centers()
    rows, cols = grid.cell(xs, ys)
    assert (rows == np.arange(90)[:, None]).all() and (cols == np.arange(120)[None, :]).all()


def test_the_mapper_fits_its_grid_to_the_size_and_resolution_it_is_given() -> None:
    harness = ModuleHarness(Mapper, state={"size": [10.0, 8.0], "resolution": 0.05,
                                           "model": {"cone_deg": 20.0}})
    state = harness.state
    assert state["log_odds"].shape == (160, 200) and state["log_odds"].dtype == np.float32
    assert state["model"]["cone_deg"] == 20.0
    assert state["model"]["clamp"] == SonarModel().clamp     # the rest from the defaults
    with pytest.raises(ValueError, match="no parameter cone; its parameters: cone_deg, "):
        ModuleHarness(Mapper, state={"model": {"cone": 20.0}})


def test_the_mapper_state_survives_pickling_and_the_next_update_continues_the_map() -> None:
    readings = _readings(12, seed=2)
    original = ModuleHarness(Mapper)
    for reading, pose in readings[:10]:
        original.feed("pose", pose)
        original.feed("sonar", reading)
    moved = ModuleHarness(Mapper, state=cloudpickle.loads(cloudpickle.dumps(original.state)))
    assert moved.state["updates"] == 10
    assert np.array_equal(moved.state["log_odds"], original.state["log_odds"])
    assert np.array_equal(moved.state["last_ranges"], original.state["last_ranges"])
    assert np.array_equal(moved.state["unfolded"], original.state["unfolded"])
    for reading, pose in readings[10:]:
        for harness in (original, moved):
            harness.feed("pose", pose)
            harness.feed("sonar", reading)
    assert np.array_equal(moved.last("map"), original.last("map"))
    assert (moved.last("map") != 0.5).sum() > 500


def test_a_map_set_while_the_mapper_runs_is_the_one_it_updates() -> None:
    harness = ModuleHarness(Mapper)
    (reading, pose), (second, _) = _readings(2, seed=3)
    harness.feed("pose", pose)
    harness.feed("sonar", reading)
    handed_over = np.full((90, 120), 2.0, dtype=np.float32)  # e.g. another robot's map,
    handed_over.flags.writeable = False                      # read-only off a port
    harness.module.set_state({"log_odds": handed_over})      # no setup() follows
    harness.feed("sonar", second)
    updated = harness.state["log_odds"]
    assert (updated[:, 60:] == 2.0).all() and (updated[:, :45] < 2.0).any()
    assert (handed_over == 2.0).all()                        # copied, not written into


def test_a_model_or_grid_setup_would_refuse_set_while_it_runs_is_refused_by_name() -> None:
    """Taken, a sonar model or grid the mapper cannot map with failed every reading from
    then on; it is refused as setup refuses it, nothing is set, and it maps on."""
    harness = ModuleHarness(Mapper)
    (reading, pose), (second, _) = _readings(2, seed=4)
    harness.feed("pose", pose)
    harness.feed("sonar", reading)
    for wrong, named in (({"model": {"cone": 20.0}}, "no parameter cone"),
                         ({"model": {"cone_deg": 200.0}}, "cone_deg=200.0"),
                         ({"resolution": 0.0}, "positive size and resolution"),
                         # (an infinite size, a NaN publish_every failed every reading)
                         ({"size": [math.inf, 8.0]}, "positive size and resolution"),
                         # (a number alone said "'float' object is not subscriptable")
                         ({"size": 10.0}, r"size is \[width, height\] in metres, not 10.0"),
                         ({"publish_every": math.nan}, "publish_every must be a whole")):
        with pytest.raises(ValueError, match=named):
            harness.module.set_state({"publish_every": 5, **wrong})
    assert harness.state["model"] == asdict(SonarModel()) and harness.state["publish_every"] == 1
    harness.feed("sonar", second)
    assert harness.state["updates"] == 2 and len(harness.written["map"]) == 2


def test_a_map_that_knows_no_wall_scores_no_walls() -> None:
    """Accuracy alone does not ask for walls: a map calling every cell free is right
    about most cells of the lab (0.88) and covers all its free space."""
    with _lab(seed=1) as world:
        grid = Grid.of(world.size)
        occupied = truth(world, grid)
    free_space = reachable(occupied, grid, START[:2])
    blind = score(np.full(grid.shape, 0.1, dtype=np.float32), occupied, free_space)
    assert blind.accuracy > 0.85 and blind.coverage == 1.0 and blind.walls == 0.0
    exact = score(np.where(occupied, 0.9, 0.1).astype(np.float32), occupied, free_space)
    assert (exact.accuracy, exact.coverage, exact.walls) == (1.0, 1.0, 1.0)
