"""RAVE's world stepping speed: real-time factor with 100 and 1,000 simulated robots,
each with its 16-sonar ring read at 10 Hz and physics at 100 Hz, headless.

What is measured: a crowd world (robots on a 3 m grid, walls around, a box at every
third grid point, half of them virtual) where every robot wanders: every 0.1 s of
simulated time each robot's sonar is read and it gets a command (drive, and turn
when its front sonars see something within 0.7 m), then the world steps 0.1 s.
The real-time factor is simulated seconds per wall-clock second. The goal is
measured with the controllers vectorized through the fleet's batch interface
(``sonar_all``, ``drive_all``), so that it times the world; the same run with one
Python controller per robot (``Robot.sonar``, ``Robot.drive``) is reported beside.

Baseline in the same run: the same sonar rays (16 transducers x 5 rays) cast one
by one with pymunk's ``segment_query_first`` against the same obstacles, against
the fleet's ring caster (neighbour lists in numpy, the pair loop in C) on the same
poses, its culling included (rays per second, static obstacles only for both,
since pymunk's query would otherwise hit the robot's own disc).

Goals: >= 50x real time at 100 robots, >= 2x at 1,000 (Stage's published figure is
about 1x at 1,000 robots).
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
import pymunk
from _common import machine, main_guard, steal_report, steal_seconds, summary

from rave import World, sonar
from rave.layers import REAL, VIRTUAL
from rave.neighbours import NeighbourLists

GOALS = {100: 50.0, 1000: 2.0}
SIMULATED_S = {100: 5.0, 1000: 1.0}
REPS = 5


def crowd(n: int, seed: int = 1) -> World:
    """``n`` robots on a 3 m grid in a square world with boxes between them."""
    k = math.ceil(math.sqrt(n))
    side = 3.0 * k + 2.0
    world = World(size=(side, side), seed=seed, name=f"crowd-{n}")
    corners = [(0, 0), (side, 0), (side, side), (0, side)]
    for a, b in zip(corners, corners[1:] + corners[:1], strict=True):
        world.add_wall(a, b)
    for i in range(k):
        for j in range(k):
            if (i + j) % 3 == 0:
                world.add_box(center=(2.5 + 3 * i, 2.5 + 3 * j), size=(0.5, 0.5),
                              virtual=i % 2 == 0)
    rng = np.random.default_rng(seed)
    for index in range(n):
        i, j = divmod(index, k)
        world.add_robot(f"r{index}", (1.0 + 3 * i, 1.0 + 3 * j, rng.uniform(-math.pi, math.pi)))
    return world


def wander(world: World, seconds: float) -> float:
    """Run the crowd for ``seconds`` of simulated time through the fleet's batch
    interface; the wall-clock seconds taken."""
    fleet = world.fleet
    started = time.perf_counter()
    for _ in range(round(seconds / 0.1)):
        blocked = fleet.sonar_all()[:, 2:6].min(axis=1) <= 0.7
        fleet.drive_all(0.4, np.where(blocked, 1.0, 0.0))
        world.step(0.1)
    return time.perf_counter() - started


def wander_each(world: World, seconds: float) -> float:
    """The same, with one Python controller per robot (``Robot.sonar``, ``drive``)."""
    robots = list(world.robots.values())
    started = time.perf_counter()
    for _ in range(round(seconds / 0.1)):
        for robot in robots:
            ranges = robot.sonar()
            robot.drive(0.4, 1.0 if ranges[2:6].min() <= 0.7 else 0.0)
        world.step(0.1)
    return time.perf_counter() - started


def raycasts(world: World, robots: int = 50) -> dict[str, Any]:
    """The same sonar rays cast by pymunk one at a time and by the fleet's ring caster."""
    poses = world.fleet.pose[:robots]
    origins, _, directions = sonar.ring_rays(poses)
    only_static = pymunk.ShapeFilter(mask=REAL | VIRTUAL)
    started = time.perf_counter()
    for o, dirs in zip(origins.reshape(-1, 2), directions.reshape(-1, sonar.RAYS, 2),
                       strict=True):
        for d in dirs:
            world.space.segment_query_first(tuple(o), tuple(o + d * sonar.MAX_RANGE), 0.0,
                                            only_static)
    pymunk_s = time.perf_counter() - started
    started = time.perf_counter()
    no_discs = np.zeros((0, 3))
    segment_pairs, _ = NeighbourLists(sonar.MAX_RANGE + sonar.CASTER.radius).pairs(
        poses[:, 0:2], world.segments(), no_discs)
    sonar.CASTER.cast(poses, world.segments(), segment_pairs, no_discs, _)
    caster_s = time.perf_counter() - started
    rays = origins.shape[0] * origins.shape[1] * sonar.RAYS
    return {"rays": rays, "segments": len(world.segments()),
            "pymunk_rays_per_s": round(rays / pymunk_s), "ring_caster_rays_per_s":
            round(rays / caster_s), "ring_caster_over_pymunk": round(pymunk_s / caster_s, 1)}


def body(result: dict[str, Any]) -> None:
    result.update(benchmark="rave_world", machine=machine())
    steal0, t0 = steal_seconds(), time.monotonic()
    for n, goal in GOALS.items():
        world = crowd(n)
        wander(world, 0.2)                                  # warm: first scans, caches
        factors = [SIMULATED_S[n] / wander(world, SIMULATED_S[n]) for _ in range(REPS)]
        each = [SIMULATED_S[n] / wander_each(world, SIMULATED_S[n]) for _ in range(REPS)]
        median = summary(factors, 2)
        result[f"robots_{n}"] = {
            "real_time_factor": median, "simulated_s_per_rep": SIMULATED_S[n],
            "real_time_factor_one_controller_per_robot": summary(each, 2),
            "goal": {"text": f">= {goal}x real time", "measured": median["median"],
                     "met": median["median"] >= goal}}
        if n == 100:
            result["raycast_baseline"] = raycasts(world)
    result["steal"] = steal_report(steal_seconds() - steal0, time.monotonic() - t0)


if __name__ == "__main__":
    main_guard(body, {})
