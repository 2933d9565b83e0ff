"""Offline training of the ``QLearning`` controller on the bundled networks, by the
project's own code: one table shared by every junction, learnt over episodes of the
networks' shortened demand (``run_in_process``: driver and controllers in this
process), with seeds of their own, not those the tests and the scenario use.

    python -m agents.traffic.training            # writes agents/traffic/q_table.json

The same command writes the same table: SUMO and the explorer are seeded, the
junctions are visited in order, and the file is written sorted.
"""

from __future__ import annotations

import argparse
import sys
import zlib
from pathlib import Path
from typing import Any

from agents.traffic.learning import TRAINED, QLearning, save_table
from agents.traffic.lockstep import run_in_process
from agents.traffic.networks import SumoMissing
from agents.traffic.simulation import check_installed

NETWORKS = Path(__file__).resolve().parents[2] / "scenarios" / "traffic"
TRAINING_SEEDS = range(1000, 1100)      # far from the seeds runs use (1..100)


def train(networks: tuple[str, ...] = ("ring", "grid"), episodes: int = 24,
          duration_s: float = 900.0, epsilon: float = 0.1,
          cache: Path | None = None) -> tuple[dict[str, list[float]], list[dict[str, Any]]]:
    """The learnt table, and each episode's figures (``episodes``: 1 to one per
    training seed)."""
    if not 1 <= episodes <= len(TRAINING_SEEDS):
        raise ValueError(f"episodes must be from 1 to {len(TRAINING_SEEDS)} (one training "
                         f"seed each), got {episodes!r}")
    table: dict[str, list[float]] = {}
    history = []
    for episode in range(episodes):
        network = networks[episode % len(networks)]
        seed = TRAINING_SEEDS[episode]

        def make(junction: str, episode: int = episode) -> tuple[type[QLearning], dict]:
            explorer = episode * 101 + zlib.crc32(junction.encode())
            return QLearning, {"table_file": "", "epsilon": epsilon, "learning": True,
                               "seed": explorer}

        def share(_junction: str, controller: QLearning) -> None:
            controller.table = table        # every junction learns into the one table

        result, _ = run_in_process(NETWORKS / f"{network}.toml", make, seed=seed,
                                   duration_s=duration_s, cache=cache, adopt=share)
        history.append({"episode": episode, "network": network, "seed": seed,
                        "mean_delay_s": round(result["mean_delay_s"], 2),
                        "states": len(table)})
        print(history[-1], flush=True)
    return table, history


def episodes(text: str) -> int:
    """``--episodes``: a whole number from 1 to one per training seed. None (0, or
    below) wrote an empty table over the trained one; more than the seeds failed on
    the first episode past them, the training before it lost."""
    try:
        count = int(text)
    except ValueError:
        count = 0
    if not 1 <= count <= len(TRAINING_SEEDS):
        raise argparse.ArgumentTypeError(
            f"give a whole number of episodes from 1 to {len(TRAINING_SEEDS)} (one seed of "
            f"its own each), got {text!r}")
    return count


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=episodes, default=24,
                        help=f"1 to {len(TRAINING_SEEDS)} (default 24)")
    parser.add_argument("--out", type=Path, default=TRAINED)
    args = parser.parse_args(argv)
    try:
        check_installed()           # (before an episode: one line, not a traceback)
    except SumoMissing as exc:
        print(f"training: {exc}", file=sys.stderr)
        return 2
    table, history = train(episodes=args.episodes)
    how = {"command": "python -m agents.traffic.training"
           + (f" --episodes {args.episodes}" if args.episodes != 24 else ""),
           "episodes": history}
    print(save_table(table, args.out, how))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
