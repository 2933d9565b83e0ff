"""What a policy learnt on the simulated robot is worth on the emulated hardware robot,
in one process: the sim-to-real application's learner without its processes.

Per seed: a ``ReactiveLearner`` with the goals and parameters of
``scenarios/sim_to_real.toml`` learns in the scenario's world on the ``--train`` back
end (``sim``: zeroth-order, the scenario's simulation) until the transfer agent's
rule there holds (300 episodes at most), one decision per ``decision_s`` of world
time. Its table then goes on, with the agent's ``learner_state`` for the robot, for
``--episodes`` episodes on the hardware
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
import tomllib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from agents.learner import SUCCESS, Parameters, ReactiveLearner  # noqa: E402
from agents.transfer import success_rate  # noqa: E402
from rave import worldfile  # noqa: E402
from rave.world import World  # noqa: E402
from scenarios.lab import world_file  # noqa: E402
from scenarios.sim_to_real import CONFIG, WORLD, time_to_target  # noqa: E402

_SYSTEM = tomllib.loads(CONFIG.read_text())
LEARNER = _SYSTEM["macros"]["brain"]["modules"]["learner"]["state"]
TRANSFER = _SYSTEM["modules"]["transfer"]["state"]
DECISION_S = LEARNER["decision_s"]


def room(backend: str, seed: int) -> World:
    """The scenario's world with its first robot where the file puts it, on ``backend``."""
    path = world_file(WORLD)
    world = World.load(path, seed, robots=False)
    world.add_robot("r", worldfile.read(path).robots[0]["pose"], backend=backend)
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
    """The transfer agent's rule (or 300 episodes: a learner that never gets there)."""
    outcomes = [outcome == SUCCESS for outcome, _, _ in learner.episodes]
    return len(outcomes) >= 300 or (
        len(outcomes) >= TRANSFER["min_episodes"]
        and success_rate(outcomes, TRANSFER["window"]) >= TRANSFER["threshold"])


def run(seed: int, train: str, episodes: int, lag: float) -> dict[str, Any]:
    started = time.monotonic()
    goals = LEARNER["goals"]
    learner = ReactiveLearner(goals, Parameters.of(LEARNER["parameters"]), seed=seed)
    with room(train, seed) as world:
        drive(learner, world, trained, 0.0)
    on_robot_state = TRANSFER["learner_state"]
    on_robot = ReactiveLearner(goals, Parameters.of(on_robot_state["parameters"]), seed=seed,
                               q=learner.q.copy(), epsilon=on_robot_state["epsilon"])
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
