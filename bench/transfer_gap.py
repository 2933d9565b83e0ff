"""What a policy learnt on the simulated robot is worth on the emulated hardware robot,
in one process: the sim-to-real application's learner without its processes.

Per seed: a ``ReactiveLearner`` with the goals and parameters of
``scenarios/sim_to_real.toml`` learns in the scenario's world on the ``--train`` back
end (``sim``: zeroth-order, the scenario's simulation) until the transfer agent's rule
there holds (300 episodes at most), one decision per ``decision_s`` of world time. Its
table then goes on, with the agent's ``learner_state`` for the robot, for
``--hardware-s`` on the hardware robot (second-order motors, sonar noise, dropouts and
specular reflection), each command reaching the robot ``--lag`` s after the readings
it answers; ``--guard`` gives every learner another speed guard than the file's
(``guard_range``; 0: none). The baselines (``--baselines``, 3 as in the full
scenario, seeds ``seed + 1`` on) learn on hardware robots from nothing for as long.
Per run: the episodes in training, collisions and successes on the robot, the hardware
s from which the success rate over 10 episodes stays at 70 % or more to the end (the
scenario's measure; None: never) for each learner, and the speed-up over the
baselines' median as the scenario reports it ("at least" when the median was not seen
kept: a baseline that was not is counted from where it last came up to 70 % if it
ended there, else from the end).
Without the scenario's processes, the figures are those of a full run with no latency
between modules. Ten seeds take about seven minutes on two cores.

Run it: ``.venv/bin/python bench/transfer_gap.py [--seeds 1-10] [--lag 0.1]
[--train hardware] [--guard 0] [--baselines 1]``.
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
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import parse_seeds  # noqa: E402

from agents.learner import SUCCESS, Parameters, ReactiveLearner  # noqa: E402
from agents.transfer import success_rate  # noqa: E402
from rave import worldfile  # noqa: E402
from rave.world import World  # noqa: E402
from rave.worldfile import world_file  # noqa: E402
from scenarios.sim_to_real import (  # noqa: E402
    CONFIG,
    GOALS,
    WORLD,
    at_target_since,
    baseline_time,
    median_time,
    speed_up,
    time_to_target,
)

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


def on_robot(learner: ReactiveLearner, seed: int, hardware_s: float, lag: float,
             ) -> dict[str, Any]:
    """``learner`` on a hardware robot for ``hardware_s`` (the episode under way then
    is not counted, as in the scenario): its outcomes there and when it kept the target."""
    with room("hardware", seed) as world:
        ended = drive(learner, world, lambda _: world.time >= hardware_s, lag)
    kept, since = time_to_target(ended, 0.0), at_target_since(ended, 0.0)
    outcomes = [e["outcome"] for e in ended]
    return {"successes": outcomes.count(SUCCESS), "collisions": outcomes.count("collision"),
            "episodes": len(outcomes), "kept_70_from_s": None if kept is None else round(kept, 1),
            "at_70_since_s": None if since is None else round(since, 1)}


def run(seed: int, train: str, hardware_s: float, lag: float, baselines: int,
        guard: float | None) -> dict[str, Any]:
    started = time.monotonic()
    goals = LEARNER["goals"]

    def parameters(given: dict[str, Any]) -> Parameters:
        return Parameters.of(given if guard is None else {**given, "guard_range": guard})

    learner = ReactiveLearner(goals, parameters(LEARNER["parameters"]), seed=seed)
    with room(train, seed) as world:
        drive(learner, world, trained, 0.0)
    there = TRANSFER["learner_state"]
    transferred = ReactiveLearner(goals, parameters(there["parameters"]), seed=seed,
                                  q=learner.q.copy(), epsilon=there["epsilon"])
    result = {"seed": seed, "training_episodes": len(learner.episodes),
              "transferred": on_robot(transferred, seed, hardware_s, lag)}
    if baselines:       # as the scenario's: other seeds, each robot in a world of its own
        result["alone"] = alone = [
            on_robot(ReactiveLearner(goals, parameters(LEARNER["parameters"]), seed=other),
                     other, hardware_s, lag)
            for other in range(seed + 1, seed + 1 + baselines)]
        value, kind = speed_up(result["transferred"]["kept_70_from_s"], median_time([
            baseline_time(a["kept_70_from_s"], a["at_70_since_s"], hardware_s) for a in alone]))
        result["speedup"] = {"value": None if value is None else round(value, 1), "kind": kind}
    result["wall_s"] = round(time.monotonic() - started, 1)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="1-10", help="e.g. 1-10 or 1,4,7")
    parser.add_argument("--hardware-s", type=float, default=840.0,
                        help="on each hardware robot (the full run gives the baseline about "
                             "840: 720 after the transfer, and its time in simulation)")
    parser.add_argument("--lag", type=float, default=0.0,
                        help="s from the readings to their command reaching the robot")
    parser.add_argument("--train", choices=("sim", "hardware"), default="sim")
    parser.add_argument("--guard", type=float, metavar="RANGE",
                        help="every learner's speed guard, instead of the scenario's "
                             "(its guard_range, m; 0: none)")
    parser.add_argument("--baselines", type=int, default=3,
                        help="baseline learners per seed, as in the full scenario (0: the "
                             "transferred learner only)")
    args = parser.parse_args()
    if not 0 <= args.lag < DECISION_S:
        parser.error(f"--lag must be at least 0 and below the decision period {DECISION_S}")
    seeds = parse_seeds(args.seeds)
    n = len(seeds)
    with ProcessPoolExecutor(max_workers=2) as pool:
        runs = list(pool.map(run, seeds, [args.train] * n, [args.hardware_s] * n,
                             [args.lag] * n, [args.baselines] * n, [args.guard] * n))
    moved = [r["transferred"] for r in runs]
    guard = (Parameters.of(LEARNER["parameters"]).guard_range if args.guard is None
             else args.guard)
    # kept by then, the goal is met against a baseline that never keeps the target
    by = args.hardware_s / GOALS["speedup"]
    summary = {"train": args.train, "lag_s": args.lag, "guard_range": guard,
               "hardware_s": args.hardware_s, "seeds": n,
               "collisions": sum(m["collisions"] for m in moved),
               "episodes": sum(m["episodes"] for m in moved),
               "kept_70_by_s": by,
               "kept_70_by_then": sum(m["kept_70_from_s"] is not None
                                      and m["kept_70_from_s"] <= by for m in moved)}
    if args.baselines:
        summary["speedup_met"] = sum(r["speedup"]["value"] is not None
                                     and r["speedup"]["value"] >= GOALS["speedup"]
                                     for r in runs)
    print(json.dumps({**summary, "runs": runs}, indent=2))


if __name__ == "__main__":
    main()
