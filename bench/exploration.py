"""How fast the mapping application explores on an emulated hardware robot, in one
process: coverage of the reachable free space and map accuracy over simulated time.

What is measured: the loop of ``scenarios/mapping.toml`` without its processes. The
world's first two robots are swapped to the hardware back end (second-order motors,
a sonar ring with noise, dropouts and specular reflection), an ``OccupancyGrid``
takes the first robot's ring and pose every 0.1 s, and a ``FrontierExplorer`` drives
it, seeing pose, map and sonar ``--delay`` ticks late, its command reaching the
robot ``--delay`` ticks later, the world advancing 0.1 s +- ``--jitter`` per tick (as
the live pipeline's ports, periods and scheduling do). With ``--hand-over-at`` the
explorer, its memory pickled, moves to the second robot then (the remedy agent's
move). Per run: coverage and accuracy every 10 s (``agents.map_truth``), when the
explorer was done, what it set aside, and how near the robot's centre came to a real
wall (contact below 0.27 m). A run of 90 simulated s takes a few seconds.

Goals (per run): coverage >= 0.5 by 60 s, accuracy >= 0.9 from 30 s on, no contact.
Run it: ``.venv/bin/python bench/exploration.py [--world lab] [--seeds 1,2,3]``.
"""

from __future__ import annotations

import argparse
import math
import pickle
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import machine, main_guard

from agents.explorer import FrontierExplorer
from agents.grid import Grid
from agents.map_truth import reachable, score, truth
from agents.occupancy import OccupancyGrid
from rave import World
from rave.layers import WALL_RADIUS
from rave.pioneer import RADIUS
from rave.worldfile import world_file

TICK = 0.1
CONTACT = RADIUS + WALL_RADIUS


def _nearest_wall(x: float, y: float, segments: np.ndarray) -> float:
    start, along = segments[:, 0:2], segments[:, 2:4] - segments[:, 0:2]
    t = np.clip(((x - start[:, 0]) * along[:, 0] + (y - start[:, 1]) * along[:, 1])
                / (along ** 2).sum(axis=1), 0.0, 1.0)
    return float(np.hypot(x - start[:, 0] - t * along[:, 0],
                          y - start[:, 1] - t * along[:, 1]).min())


def run(world_name: str, seed: int, seconds: float, delay: int, jitter: float,
        hand_over_at: float | None) -> dict[str, Any]:
    """One run; its figures."""
    world = World.load(world_file(world_name), seed=seed)
    started = time.perf_counter()
    try:
        names = list(world.robots)
        for name in names[:2]:
            world.robot(name).swap("hardware")
        robot = world.robot(names[0])
        grid = Grid.of(world.size)
        occupied = truth(world, grid)
        free_space = np.zeros(grid.shape, dtype=bool)
        for name in names[:2]:
            free_space |= reachable(occupied, grid, world.pose(name)[:2])
        mapper, explorer = OccupancyGrid(grid), FrontierExplorer(grid)
        rng = np.random.default_rng(seed)
        segments = world.segments(virtual=False)
        seen: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        commands = [(0.0, 0.0)] * delay
        over_time, closest, contact_s, done_at, set_aside = [], math.inf, 0.0, None, []
        tick = 0
        while world.time < seconds:
            if hand_over_at is not None and world.time >= hand_over_at:
                hand_over_at = None
                explorer.restore(pickle.loads(pickle.dumps(explorer.memory())))
                robot.stop()
                robot = world.robot(names[1])
                seen.clear()
            sonar, pose = robot.sonar(), np.array(robot.gps())
            mapper.update(pose, sonar)
            seen.append((mapper.probabilities(), pose, sonar))
            before = len(explorer.blacklist)
            commands.append(explorer.step(*seen[max(0, len(seen) - 1 - delay)], TICK))
            if len(explorer.blacklist) > before:
                set_aside.append(round(world.time, 1))
            robot.drive(*commands.pop(0))
            world.step(TICK + (rng.uniform(-jitter, jitter) if jitter else 0.0))
            gap = _nearest_wall(*robot.gps()[:2], segments)
            closest = min(closest, gap)
            contact_s += TICK if gap < CONTACT + 0.005 else 0.0
            done_at = (done_at or round(world.time, 1)) if explorer.done else None
            tick += 1
            if tick % 100 == 0:
                figures = score(mapper.probabilities(), occupied, free_space)
                over_time.append({"t": round(world.time), "coverage": round(figures.coverage, 3),
                                  "accuracy": round(figures.accuracy, 3)})
    finally:
        world.close()
    by_60 = max((q["coverage"] for q in over_time if q["t"] <= 60), default=0.0)
    accuracy = min((q["accuracy"] for q in over_time if q["t"] >= 30), default=0.0)
    return {"world": world_name, "seed": seed, "over_time": over_time,
            "done_at_s": done_at, "set_aside_at_s": set_aside, "stuck": explorer.stuck,
            "closest_m": round(closest, 3), "contact_s": round(contact_s, 1),
            "wall_clock_s": round(time.perf_counter() - started, 1),
            "goal": {"text": "coverage >= 0.5 by 60 s, accuracy >= 0.9 from 30 s, no contact",
                     "measured": [by_60, accuracy, round(closest, 3)],
                     "met": by_60 >= 0.5 and accuracy >= 0.9 and contact_s == 0}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--world", default="lab")
    parser.add_argument("--seeds", default="1,2,3")
    parser.add_argument("--seconds", type=float, default=90.0)
    parser.add_argument("--delay", type=int, default=1, help="ticks each way (default 1)")
    parser.add_argument("--jitter", type=float, default=0.03, help="s per tick (default 0.03)")
    parser.add_argument("--hand-over-at", type=float, default=None)
    args = parser.parse_args()

    def body(result: dict[str, Any]) -> None:
        result.update(benchmark="exploration", machine=machine(), runs=[
            run(args.world, int(seed), args.seconds, args.delay, args.jitter,
                args.hand_over_at) for seed in args.seeds.split(",")])

    main_guard(body)


if __name__ == "__main__":
    main()
