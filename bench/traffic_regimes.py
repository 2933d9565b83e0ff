"""Does a traffic controller have a regime an agent could swap into?

Each variant (a controller class and its state) runs alone at every signalized
junction, over the whole demand schedule of each network and seed, in one process
(the scenario's ``run_alone``: its driver and lock-step, no agents). Per period of
the demand it takes the mean delay of the vehicles that left in it (the driver's
``delay_by_period``). The first variant is the baseline; for every other one the
report gives, per seed, its mean delay less the baseline's, over the run and in each
period, and the periods it ``wins``: less delay than the baseline there on every seed.
A period won by one variant and lost by it elsewhere is a regime: swapping into that
variant for that period could beat both. On one run, differences of less than about
half a second are the simulation's own noise (``docs/applications.md``), so only a
sign that holds on every seed counts.

Without ``--variant``, the variants are the controllers the scenario's agents choose
among (``scenarios/traffic.toml``), gap-out first. Run it::

    .venv/bin/python bench/traffic_regimes.py [--networks ring,grid] [--seeds 1-4]
        [--duration 3600] [--variant 'NAME=module:Class{"param": value}' ...]
        [--scale [PERIOD=]FACTOR ...]

for example ``--variant gap_out=agents.traffic.gap_out:GapOut --variant
'p5=agents.traffic.gap_out:GapOut{"passage_s": 5.0}'``. Four seeds of both networks
take about 280 s with the scenario's six controllers, on two cores.
``--scale surge=2.2`` makes the surge heavier (the driver's ``demand_scale``), to see
which controller a saturated network favours.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, main_guard, parse_seeds  # noqa: E402

from scenarios.traffic import controllers, network_path, parse_scale, run_alone  # noqa: E402


def parse_variant(text: str) -> tuple[str, dict[str, Any]]:
    """``NAME=module:Class`` with an optional JSON object of its state after it."""
    name, _, rest = text.partition("=")
    reference, brace, state = rest.partition("{")
    if not name or ":" not in reference:
        raise ValueError(f"--variant {text!r}: give NAME=module:Class, optionally followed "
                         "by its state as a JSON object")
    return name, {"class": reference, "state": json.loads(brace + state) if brace else {}}


def run_one(network: str, seed: int, spec: dict[str, Any], duration_s: float,
            demand_scale: dict[str, float]) -> dict[str, Any]:
    """One variant alone on one network and seed: its mean delay, overall and per period."""
    result = run_alone(network_path(network), seed, duration_s, spec,
                       demand_scale=demand_scale)
    return {"mean_delay_s": result["mean_delay_s"], "teleports": result["teleports"],
            "periods": [(p["period"], p["mean_delay_s"]) for p in result["delay_by_period"]]}


def compare(variants: dict[str, dict[str, Any]], runs: dict[tuple, dict[str, Any]],
            network: str, seeds: list[int]) -> dict[str, Any]:
    """Each variant against the first, per seed and per period, on ``network``."""
    baseline = next(iter(variants))
    names = [name for name, _ in runs[(network, seeds[0], baseline)]["periods"]]
    found: dict[str, Any] = {"periods": names, "variants": {}}
    for variant in variants:
        mine = {seed: runs[(network, seed, variant)] for seed in seeds}
        base = {seed: runs[(network, seed, baseline)] for seed in seeds}
        by_period = [[_less(mine[seed]["periods"][index][1], base[seed]["periods"][index][1])
                      for seed in seeds] for index in range(len(names))]
        found["variants"][variant] = {
            "mean_delay_s": {seed: round(mine[seed]["mean_delay_s"], 2) for seed in seeds},
            "minus_baseline_s": {seed: round(mine[seed]["mean_delay_s"]
                                             - base[seed]["mean_delay_s"], 2) for seed in seeds},
            "by_period_minus_baseline_s": dict(zip(names, by_period, strict=True)),
            "wins": [name for name, diffs in zip(names, by_period, strict=True)
                     if variant != baseline and all(d is not None and d < 0 for d in diffs)],
            "teleports": sum(mine[seed]["teleports"] for seed in seeds)}
    return found


def _less(value: float | None, baseline: float | None) -> float | None:
    """``value - baseline``, rounded; None when a period had no vehicle leave in it."""
    return None if value is None or baseline is None else round(value - baseline, 2)


def body(result: dict[str, Any], args: argparse.Namespace) -> None:
    variants = dict(parse_variant(text) for text in args.variant) if args.variant else \
        dict(sorted(controllers().items(), key=lambda item: item[0] != "gap_out"))
    networks, seeds = args.networks.split(","), parse_seeds(args.seeds)
    demand_scale = parse_scale(args.scale)
    result.update(benchmark="traffic_regimes", machine=machine(), seeds=seeds,
                  duration_s=args.duration, demand_scale=demand_scale, variants=variants,
                  baseline=next(iter(variants)))
    jobs = [(network, seed, name) for network in networks for seed in seeds
            for name in variants]
    started = time.monotonic()
    with ProcessPoolExecutor(args.processes) as pool:      # (libsumo: one per process)
        futures = {job: pool.submit(run_one, job[0], job[1], variants[job[2]], args.duration,
                                    demand_scale) for job in jobs}
        runs = {job: future.result() for job, future in futures.items()}
    result["wall_s"] = round(time.monotonic() - started, 1)
    result["networks"] = {network: compare(variants, runs, network, seeds)
                          for network in networks}


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--networks", default="ring,grid",
                        help="bundled names or description paths, comma-separated")
    parser.add_argument("--seeds", default="1-4", help="e.g. 1-4 or 1,5,9")
    parser.add_argument("--duration", type=float, default=3600.0, help="simulated seconds")
    parser.add_argument("--variant", action="append",
                        help='NAME=module:Class{"param": value}; the first is the baseline')
    parser.add_argument("--scale", action="append", default=[], metavar="[PERIOD=]FACTOR",
                        help="multiply the demand's rates in one period (surge=2) or all")
    parser.add_argument("--processes", type=int, default=2)
    main_guard(lambda result: body(result, parser.parse_args()))
