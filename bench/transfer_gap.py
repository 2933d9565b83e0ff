"""What a policy learnt on the simulated robot is worth on the emulated hardware robot,
in one process: the sim-to-real application's learner without its processes.

Per seed: a ``ReactiveLearner`` with the scenario's actions learns in the ``room``
world on the ``--train`` back end (``sim``: zeroth-order, the scenario's simulation)
until 18 of its last 20 episodes succeed (40 episodes at least, 300 at most), one
decision per 0.2 s of world time. Its table then goes on, at the scenario's settings
on the robot (alpha 0.1, epsilon 0.02), for ``--episodes`` episodes on the hardware
robot (second-order motors, sonar noise, dropouts and specular reflection), each
command reaching the robot ``--lag`` s after the readings it answers. Per run: the
episodes in training, collisions and successes on the robot, and the hardware s from
which the success rate over 10 episodes stays at 70 % or more to the end (the
scenario's measure; None: never). Ten seeds take about two minutes on two cores.

Run it: ``.venv/bin/python bench/transfer_gap.py [--seeds 1-10] [--lag 0.1]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from agents.learner import SUCCESS, Parameters, ReactiveLearner  # noqa: E402
from rave import worldfile  # noqa: E402
from rave.world import World  # noqa: E402
from scenarios.sim_to_real import time_to_target  # noqa: E402

DECISION_S = 0.2
ACTIONS = [[0.3, 0.0], [0.3, 0.6], [0.3, -0.6], [0.0, 1.2], [0.0, -1.2]]
GOALS = [[1.0, 1.0], [6.0, 4.0], [6.0, 1.0], [1.0, 4.0]]
ON_ROBOT = {"alpha": 0.1}


def room(backend: str, seed: int) -> World:
    """The scenario's world (its box virtual) with one robot on ``backend``."""
    plan = worldfile.read(ROOT / "rave" / "worlds" / "room.toml")
    world = World(size=plan.size, seed=seed)
    for wall in plan.walls:
        world.add_wall(**wall)
    for box in plan.boxes:
        world.add_box(**box)
    world.add_robot("r", (1.0, 1.0, 0.0), backend=backend)
    return world


def drive(learner: ReactiveLearner, world: World, enough: Any, lag: float,
          ) -> list[dict[str, Any]]:
    """Decide and drive until ``enough(learner)``; the episodes ended meanwhile."""
    robot, ended = world.robot("r"), []
    while not enough(learner):
        command, episode = learner.decide(np.asarray(robot.sonar()), np.asarray(robot.gps()),
                                          world.time)
        if episode is not None:
            ended.append({"success": episode.outcome == SUCCESS, "outcome": episode.outcome,
                          "clock": world.time})
        if lag:
            world.step(lag)           # the command is on its way
        robot.drive(*command)
        world.step(DECISION_S - lag)
    return ended


def trained(learner: ReactiveLearner) -> bool:
    episodes = learner.episodes
    return len(episodes) >= 300 or (len(episodes) >= 40 and sum(
        outcome == SUCCESS for outcome, _, _ in episodes[-20:]) >= 18)


def run(seed: int, train: str, episodes: int, lag: float) -> dict[str, Any]:
    started = time.monotonic()
    parameters = {"actions": ACTIONS}
    learner = ReactiveLearner(GOALS, Parameters.of(parameters), seed=seed)
    with room(train, seed) as world:
        drive(learner, world, trained, 0.0)
    on_robot = ReactiveLearner(GOALS, Parameters.of({**parameters, **ON_ROBOT}), seed=seed,
                               q=learner.q.copy(), epsilon=0.02)
    with room("hardware", seed) as world:
        ended = drive(on_robot, world, lambda it: len(it.episodes) >= episodes, lag)
    kept = time_to_target(ended, 0.0)
    outcomes = [e["outcome"] for e in ended]
    return {"seed": seed, "training_episodes": len(learner.episodes),
            "successes": outcomes.count(SUCCESS), "collisions": outcomes.count("collision"),
            "kept_70_from_s": None if kept is None else round(kept, 1),
            "wall_s": round(time.monotonic() - started, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="1-10", help="e.g. 1-10 or 1,4,7")
    parser.add_argument("--episodes", type=int, default=40, help="on the hardware robot")
    parser.add_argument("--lag", type=float, default=0.0,
                        help="s from the readings to their command reaching the robot")
    parser.add_argument("--train", choices=("sim", "hardware"), default="sim")
    args = parser.parse_args()
    if not 0 <= args.lag < DECISION_S:
        parser.error(f"--lag must be at least 0 and below the decision period {DECISION_S}")
    if "-" in args.seeds:
        first, last = args.seeds.split("-")
        seeds = list(range(int(first), int(last) + 1))
    else:
        seeds = [int(s) for s in args.seeds.split(",")]
    with ProcessPoolExecutor(max_workers=2) as pool:
        runs = list(pool.map(run, seeds, [args.train] * len(seeds),
                             [args.episodes] * len(seeds), [args.lag] * len(seeds)))
    print(json.dumps({
        "train": args.train, "lag_s": args.lag, "seeds": len(runs),
        "collisions": sum(r["collisions"] for r in runs),
        "episodes": args.episodes * len(runs),
        "kept_70_within_210_s": sum(r["kept_70_from_s"] is not None
                                    and r["kept_70_from_s"] <= 210 for r in runs),
        "runs": runs}, indent=2))


if __name__ == "__main__":
    main()
