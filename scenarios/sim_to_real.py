"""Simulation to real: a learner learns on a simulated robot, faster than real time,
then moves with what it learnt to the hardware robot and finishes learning there.

``scenarios/sim_to_real.toml``: the ``brain`` macro (a ``PolicyLearner`` and the
``RobotDriver`` of the robot it learns on) starts on the workstation against a
simulated robot in the ``room`` world, served in lock-step: the world advances one
decision at a time, as fast as the learner decides. The ``TransferAgent`` watches its
episodes; once 90 % of the last 20 succeed (or, on a machine too slow for that
within the run's budget for simulation, at the next episode after it), it moves
the brain to the hardware robot's on-board computer (a node behind its own node
controller) and re-points the driver at the emulated hardware robot (second-order
dynamics, sonar noise and specular dropouts), where learning goes on at a lower
learning rate. The baseline, ``alone``, is the same brain learning on another
hardware robot (in a world of its own) from the start; the full run has three of
them, with other seeds, and compares with their median, so that one learner's luck
does not decide the comparison. The hardware robot's world is held (``pace`` 0: no
time passes there) until the learner arrives, so that learning in simulation has the
CPU.

Measured in the run: the transfer time (the agent's decision to the driver
re-pointed at the hardware robot, with the learner on its node), the success rate at
the end for each learner, and the hardware time each needs to reach ``TARGET`` (a
success rate over the last episodes) and keep it. Goals: transfer at most 0.25 s; at
least 3x less hardware time with transfer than the baselines' median without. A
``--quick`` run serves the hardware worlds at 8x real time to fit in two minutes
(hardware time is the hardware world's own clock either way, and the report gives the
pace each world kept), and gives the learner a coarser view of the world, which it can
learn within the quick budget (``QUICK_VIEW``); the full run serves them in real time.

Run it: ``pb3a scenario sim-to-real [--quick] [--world W] [--seed N] [--baselines N]
[--out DIR]`` (or ``python -m scenarios.sim_to_real``). It prints the report as JSON and
writes ``sim_to_real.json`` and ``sim_to_real.png`` to DIR. The learner's goals are the
file's, in the world's frame: a world they do not fit is refused before anything runs.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import math
import sys
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from agents.grid import Grid
from agents.learner import Parameters
from agents.map_truth import truth
from pb3a import Input, InputPort, Module, System
from pb3a.cli.arguments import seed
from pb3a.cli.log_output import show_logs
from rave import World, worldfile
from scenarios import output_directory, summary
from scenarios.lab import Lab, wait_until

CONFIG = Path(__file__).with_name("sim_to_real.toml")
WORLD = "room"                # the default world (--world)
# wall seconds at most for learning in simulation, then on the hardware robot; and the
# hardware worlds' speed (simulated seconds per wall second). The target needs ten
# episodes (~180 hardware s) to be seen at all, so the baseline needs more than three
# times that on its robot for a 3x speed-up to be measurable: the full run gives it
# the simulation's time and 720 s after (about 14 minutes in all).
# How many baseline robots learn alone: the time a learner takes to the target varies
# from seed to seed (one of the full run's baselines kept it from 294 s, most not within
# 840 s), so the full run compares with the median of three. A quick run, too short to
# measure the speed-up, has one.
BUDGETS = {"quick": {"simulation": 30.0, "hardware": 55.0, "rate": 8.0, "baselines": 1},
           "full": {"simulation": 120.0, "hardware": 720.0, "rate": 1.0, "baselines": 3}}
# A --quick run's learner sees the world as the library's learner does by default (two
# ranges per sonar sector and eight goal bearings: 128 situations, not the file's
# 1,296) and may move after 30 episodes: the finer view needs 120 in simulation, six
# times what the quick budget gets through in lock-step beside a hardware world at 8x.
# So the quick run shows the mechanism; the full run measures the speed-up.
QUICK_VIEW = {"thresholds": list(Parameters.thresholds), "bearings": Parameters.bearings}
QUICK_MIN_EPISODES = 30
TARGET = (0.7, 10)            # learnt: this success rate over the last this many episodes
SIMULATION_WINDOW = 20        # episodes of the simulation's success rate (the agent's window)
GOALS = {"transfer_s": 0.25, "speedup": 3.0}
SPEEDUP_GOAL = ("hardware time to the target at least 3x less with transfer than the "
                "baselines' median")
POLL_S = 0.1                  # how often the scenario looks for the transfer
EPISODES_EVERY_S = 1.0        # how often it counts episodes, when a number of them ends a run
LAST_EPISODE_S = 15.0         # wall s for the episode under way once the budget is spent


class EpisodeRecorder(Module):
    """Keeps every episode a learner reports."""

    episode = Input(dict, policy="queue:100000")
    episodes: list[dict[str, Any]] = []

    def on_input(self, port: InputPort) -> None:
        self.episodes.extend(port.read_all())


def baselines(count: int) -> list[tuple[str, str]]:
    """The module and node of each baseline robot: the file's ``alone`` on ``other``,
    then copies of them (``alone_2`` on ``other_2``, ...)."""
    return [("alone", "other")] + [(f"alone_{i}", f"other_{i}") for i in range(2, count + 1)]


def learning_robot(world: str | Path) -> str:
    """The robot a learner learns on in each lab of ``world``: its file's first."""
    robots = worldfile.read(worldfile.world_file(str(world))).robots
    if not robots:
        raise ValueError(f"the sim-to-real scenario needs a world with a robot; {world} "
                         "declares none (add a [[robots]] entry)")
    return robots[0]["name"]


def goals() -> list[list[float]]:
    """The goals the learners visit in turn: ``sim_to_real.toml``'s, in the world's frame."""
    data = tomllib.loads(CONFIG.read_text())
    return data["macros"]["brain"]["modules"]["learner"]["state"]["goals"]


def goal_problems(goals: list[list[float]], world: str | Path) -> list[str]:
    """A sentence for each goal ``world`` has no place for: outside its bounds, or inside
    an obstacle. (On a 4 x 3 m world, three of the room's four goals lay outside it: the
    run learnt to a success rate of 0.25 and said nothing of why.)"""
    path = worldfile.world_file(str(world))
    with World.load(path) as loaded:
        described, size = loaded.describe(), loaded.size
    grid = Grid.of(size, 0.1)
    occupied = truth(described, grid)
    width, height = size
    problems = []
    for x, y in goals:
        if not (0.0 < x < width and 0.0 < y < height):
            problems.append(f"goal [{x:g}, {y:g}] lies outside world {path.stem!r} ({path}: "
                            f"{width:g} x {height:g} m)")
        elif occupied[grid.cell(x, y)]:
            problems.append(f"goal [{x:g}, {y:g}] lies inside an obstacle of world "
                            f"{path.stem!r} ({path})")
    return problems


def configuration(simulated: Lab, hardware: Lab, baseline_labs: list[Lab], rate: float,
                  seed: int, quick: bool = False, robot: str = "r1") -> System:
    """``sim_to_real.toml`` with this run's addresses (``robot``'s in each lab), the
    driver's period for the hardware worlds' rate, the seeds, a copy of the baseline
    (its node, module, recorder and link) for each of ``baseline_labs``, and for a
    quick run its learner's coarser view."""
    data = tomllib.loads(CONFIG.read_text())
    data["nodes"]["robot"]["address"] = hardware.nodes["robot"].address
    brain = data["macros"]["brain"]["modules"]
    brain["driver"]["period"] = brain["driver"].get("period", 0.1) / rate
    brain["driver"]["state"]["resource"] = simulated.robots[robot]
    brain["learner"]["state"]["seed"] = seed
    node, alone, recorder = (data["nodes"]["other"], data["modules"]["alone"],
                             data["modules"]["alone_recorder"])
    data["links"] = [link for link in data["links"] if link["from"] != "alone.episode"]
    for offset, ((name, on), lab) in enumerate(
            zip(baselines(len(baseline_labs)), baseline_labs, strict=True), 1):
        data["nodes"][on] = {**node, "address": lab.nodes[on].address}
        copied = data["modules"][name] = copy.deepcopy({**alone, "node": on})
        copied["state"]["driver"]["resource"] = lab.robots[robot]
        copied["state"]["learner"]["seed"] = seed + offset
        data["modules"][f"{name}_recorder"] = dict(recorder)
        data["links"].append({"from": f"{name}.episode", "to": f"{name}_recorder.episode"})
    transfer = data["modules"]["transfer"]["state"]
    transfer["to_resource"] = hardware.robots[robot]
    if quick:
        brain["learner"]["state"]["parameters"].update(QUICK_VIEW)
        transfer["learner_state"]["parameters"].update(QUICK_VIEW)
        transfer["min_episodes"] = QUICK_MIN_EPISODES
    return System.from_dict(data, source=str(CONFIG))


def run(seed: int = 1, quick: bool = False, baseline_count: int | None = None,
        world: str | Path = WORLD, *, hardware_episodes: int | None = None) -> dict[str, Any]:
    """One run in ``world``, with ``baseline_count`` baseline robots (the budget's by
    default); what happened, for ``report``. ValueError, before anything runs, for a
    world with no robot or no place for a goal (``goal_problems``). With
    ``hardware_episodes``, learning on the hardware robots ends once every learner has
    had that many episodes on its robot (at the budget's end at the latest): all a check
    of the mechanism needs (the tests), short of the learning the report measures."""
    budget = BUDGETS["quick" if quick else "full"]
    rate = budget["rate"]
    names = baselines(baseline_count or budget["baselines"])
    robot = learning_robot(world)
    wrong = goal_problems(goals(), world)
    if wrong:
        raise ValueError("; ".join(wrong) + f": set the learner's goals in {CONFIG} to "
                         "places in the world")
    with contextlib.ExitStack() as labs:
        simulated = labs.enter_context(simulation(world, seed, robot))
        # the robot the learner moves to is held until then: no hardware time passes
        # for it, and learning in simulation has the CPU its world would take
        hardware = labs.enter_context(Lab(world, seed=seed, onboard=("robot",),
                                          hardware=(robot,), rate=0.0))
        alone = [labs.enter_context(Lab(world, seed=seed + offset, onboard=(node,),
                                        hardware=(robot,), rate=rate))
                 for offset, (_, node) in enumerate(names, 1)]
        running = labs.enter_context(
            configuration(simulated, hardware, alone, rate, seed, quick, robot).launch())
        started, alone_from = time.time(), [lab.time() for lab in alone]
        deadline = time.monotonic() + budget["simulation"]
        _until_moved(running, deadline)
        # The simulation's budget is spent before the agent's threshold was reached (a
        # slow machine): what it learnt goes to the robot as it is, at the next episode.
        agent = running.state("transfer")
        threshold, forced_at = agent["threshold"], math.inf
        if not agent["decided_at"]:
            forced_at = time.time()
            running.set_state("transfer", {"threshold": 0.0, "min_episodes": 0})
        _until_moved(running, time.monotonic() + LAST_EPISODE_S)
        transfer = running.state("transfer")
        ended_by = simulation_ended_by(transfer, forced_at)
        simulated_s = simulated.time()
        simulation_wall_s = time.time() - started
        transferred_from, resumed = None, 0.0
        # the table each learner began with on its robot: the moved one's as it arrived
        # (its robot held until now, it has learnt nothing there yet), a baseline's blank
        brought = running.state("brain/learner")["q"]
        if transfer["moved_at"]:         # the hardware world's clock from here on
            transferred_from, resumed = hardware.pace(rate), time.time()
            _until_learnt(running, names, transfer["moved_at"], hardware_episodes,
                          time.monotonic() + budget["hardware"])
        episodes = {name: running.state(f"{name}_recorder")["episodes"] for name, _ in names}
        episodes["with_transfer"] = running.state("recorder")["episodes"]
        clocks = {"with_transfer": (transferred_from, hardware.time()),
                  **{name: (start, lab.time())
                     for (name, _), start, lab in zip(names, alone_from, alone, strict=True)}}
        ended = time.time()
        walls = {"with_transfer": ended - resumed if resumed else 0.0,
                 **{name: ended - started for name, _ in names}}
        where = running.where("brain/learner")
        table = running.state("brain/learner")["q"]
        situations = len(table)
        learnt = {"with_transfer": _changed(brought, table) if transfer["moved_at"] else 0,
                  **{name: _changed(None, running.state(f"{name}/learner")["q"])
                     for name, _ in names}}
    return {"world": worldfile.world_file(str(world)).stem, "seed": seed, "quick": quick,
            "rate": rate, "clocks": clocks, "walls": walls,
            "transfer": transfer, "threshold": threshold, "ended_by": ended_by,
            "simulated_s": simulated_s,
            "simulation_wall_s": simulation_wall_s, "episodes": episodes,
            "baselines": [name for name, _ in names],
            "learner_node_at_end": where, "situations": situations, "learnt": learnt}


def _changed(before: Any, after: Any) -> int:
    """How many of a learner's table values differ in ``after`` from ``before`` (None:
    a blank table, all zeros; a table of another shape, remade, is new throughout)."""
    after = np.asarray(after)
    before = np.zeros_like(after) if before is None else np.asarray(before)
    return int(np.count_nonzero(after != before)) if before.shape == after.shape \
        else after.size


def simulation(world: str | Path, seed: int, robot: str) -> Lab:
    """The lab the learner starts in: ``world`` in lock-step, ``robot`` served in
    simulation whatever the world file says (the lab world's first robot is a hardware
    one, and the learner learnt on the emulator in both phases)."""
    lab = Lab(world, seed=seed, lockstep=True)
    try:
        lab.robot(robot, "swap", backend="sim")
    except BaseException:
        lab.close()
        raise
    return lab


def simulation_ended_by(transfer: dict[str, Any], forced_at: float) -> str:
    """What ended learning in simulation, from the transfer agent's state: its
    ``threshold``, the ``budget`` (the move ``forced_at`` that time), or ``no
    transfer``. (Without a move, its ``decided_at`` is the 0 of an agent that never
    decided or whose move failed, and the report said the threshold was reached.)"""
    if not transfer["moved_at"]:
        return "no transfer"
    return "budget" if transfer["decided_at"] >= forced_at else "threshold"


def _until_moved(running: Any, deadline: float) -> None:
    """Wait until the agent has moved the learner and its driver, re-pointed at the
    hardware robot as they arrived, or ``deadline`` (monotonic)."""
    while time.monotonic() < deadline and not running.state("transfer")["moved_at"]:
        wait_until(min(deadline, time.monotonic() + POLL_S))


def _until_learnt(running: Any, names: list[tuple[str, str]], moved_at: float,
                  episodes: int | None, deadline: float) -> None:
    """Let the learners learn on their robots until ``deadline`` (monotonic) or, looked
    at each ``EPISODES_EVERY_S``, until each has had ``episodes`` there (None: no
    number ends it): the moved learner since ``moved_at``, each baseline since it
    began."""
    while time.monotonic() < deadline:
        if episodes is not None:
            moved = [e for e in running.state("recorder")["episodes"] if e["at"] > moved_at]
            if len(moved) >= episodes and all(
                    len(running.state(f"{name}_recorder")["episodes"]) >= episodes
                    for name, _ in names):
                return
        wait_until(min(deadline, time.monotonic() + EPISODES_EVERY_S))


def rolling(episodes: list[dict[str, Any]], window: int) -> list[float]:
    """The success rate over the last ``window`` episodes, after each episode."""
    outcomes = [bool(e["success"]) for e in episodes]
    return [sum(outcomes[max(0, i + 1 - window):i + 1]) / min(window, i + 1)
            for i in range(len(outcomes))]


def time_to_target(episodes: list[dict[str, Any]], since: float, *,
                   held: bool = True) -> float | None:
    """Hardware seconds from the hardware world's time ``since`` until the success rate
    over the last ``TARGET[1]`` episodes reaches ``TARGET[0]`` for good: it never falls
    below again, and a window of episodes or more follow to show it (None: it did not).
    With ``held`` False, until it first reaches it: a learner that succeeds half the
    time gets there on a lucky streak, which is why the speed-up uses the other."""
    rate_needed, window = TARGET
    rates = rolling(episodes, window)
    if not held:
        reached = next((i for i in range(window - 1, len(rates)) if rates[i] >= rate_needed),
                       None)
    else:
        reached = _last_reached(rates)
        if reached is not None and reached > len(episodes) - 1 - window:
            reached = None               # at the target at the end, but not for a window yet
    return None if reached is None else episodes[reached]["clock"] - since


def at_target_since(episodes: list[dict[str, Any]], since: float) -> float | None:
    """Hardware seconds from ``since`` to where the success rate came up to the target
    for the last time, if it is still there at the end (None: it ended below it). The
    soonest ``time_to_target`` can turn out to be, once more episodes confirm it."""
    reached = _last_reached(rolling(episodes, TARGET[1]))
    return None if reached is None else episodes[reached]["clock"] - since


def _last_reached(rates: list[float]) -> int | None:
    """The index from which ``rates`` stay at or above the target to their end (None: the
    last is below it), counting only full windows."""
    rate_needed, window = TARGET
    reached = None
    for index in range(window - 1, len(rates)):
        if rates[index] < rate_needed:
            reached = None
        elif reached is None:
            reached = index
    return reached


def report(record: dict[str, Any]) -> dict[str, Any]:
    """The figures of one run, and whether they meet the goals."""
    transfer, episodes, clocks = record["transfer"], record["episodes"], record["clocks"]
    moved = transfer["moved_at"] or None
    in_simulation = [e for e in episodes["with_transfer"] if not moved or e["at"] <= moved]
    by_learner = {"with_transfer": [e for e in episodes["with_transfer"]
                                    if moved and e["at"] > moved],
                  **{name: episodes[name] for name in record["baselines"]}}
    hardware_s = {name: (end - start) if start is not None else 0.0
                  for name, (start, end) in clocks.items()}
    reached, first = ({name: time_to_target(episodes, clocks[name][0], held=held)
                       if clocks[name][0] is not None else None
                       for name, episodes in by_learner.items()} for held in (True, False))
    window = TARGET[1]
    figures: dict[str, Any] = {
        "scenario": "sim-to-real", "world": record["world"], "seed": record["seed"],
        "quick": record["quick"], "hardware_rate": record["rate"],
        "learner_situations": record["situations"],      # the rows of its table
        "simulation": {"episodes": len(in_simulation),
                       "success_rate_last_20": _rate(in_simulation, SIMULATION_WINDOW),
                       "transfer_threshold": record["threshold"],
                       # "threshold": the agent's success rate was reached; "budget":
                       # the wall time for learning in simulation ran out first; "no
                       # transfer": the learner never moved
                       "ended_by": record["ended_by"],
                       "simulated_s": round(record["simulated_s"], 1),
                       "wall_s": round(record["simulation_wall_s"], 1),
                       "times_real_time": round(record["simulated_s"]
                                                / max(record["simulation_wall_s"], 1e-9), 1)},
        # the driver is re-pointed and the learner set as they arrive: the move is the
        # transfer
        "transfer_s": round(transfer["moved_at"] - transfer["decided_at"], 3)
        if moved else None,
        # of which: the brain paused, and its workers readied on the robot's node before
        "move_pause_s": _rounded(transfer["move"].get("pause_s"), 3),
        "move_prepare_s": _rounded(transfer["move"].get("prepare_s"), 3),
        "move_phases": {phase: round(seconds, 4) for phase, seconds
                        in transfer["move"].get("phases", {}).items()},
        "learner_node_at_end": record["learner_node_at_end"],
        "target": {"success_rate": TARGET[0], "over_last_episodes": window,
                   "kept_to_the_end": True},
        "hardware": {name: {"episodes": len(episodes),
                            "success_rate_at_end": _rate(episodes, window),
                            # its table's values it changed on its robot (learning there
                            # from what the robot did; a baseline's from a blank table)
                            "table_values_learnt": record.get("learnt", {}).get(name),
                            "hardware_s": round(hardware_s[name], 1),
                            # the world's own pace: whether it kept the rate it was served at
                            "times_real_time": round(hardware_s[name]
                                                     / max(record["walls"][name], 1e-9), 1),
                            "hardware_s_to_target": _rounded(reached[name]),
                            "hardware_s_first_at_target": _rounded(first[name]),
                            # where its last stretch at the target began, confirmed or not
                            "hardware_s_at_target_since": _rounded(at_target_since(
                                episodes, clocks[name][0] or 0.0))}
                     for name, episodes in by_learner.items()},
    }
    alone = [baseline_time(reached[name], figures["hardware"][name]["hardware_s_at_target_since"],
                           hardware_s[name]) for name in record["baselines"]]
    median = median_time(alone)
    speedup, bound = speed_up(reached["with_transfer"], median)
    figures["speedup"] = {"value": round(speedup, 2) if speedup else None, "kind": bound,
                          "baselines": len(alone), "baselines_median_s": _rounded(median[0]),
                          "baselines_median_measured": median[1]}
    # (null: not measured, the transferred learner not seen keeping the target; a quick
    # run, too short to tell, reported false: a goal missed)
    figures["goals"] = {
        "transfer_s <= 0.25": figures["transfer_s"] is not None
        and figures["transfer_s"] <= GOALS["transfer_s"],
        SPEEDUP_GOAL: None if speedup is None else speedup >= GOALS["speedup"],
    }
    figures["curves"] = {"simulation": rolling(in_simulation, SIMULATION_WINDOW)}
    for name, episodes in by_learner.items():
        start = clocks[name][0] or 0.0
        figures["curves"][name] = [[round(e["clock"] - start, 2), r]
                                   for e, r in zip(episodes, rolling(episodes, window),
                                                   strict=True)]
    return figures


def baseline_time(kept: float | None, since: float | None, had: float) -> tuple[float, bool]:
    """A baseline's hardware time to the target, and whether it was measured. One not
    seen keeping the target (``kept`` None) took at least ``since`` (``at_target_since``:
    where it came up to the target for the last time, if it ended there), or else the
    ``had`` s it had."""
    if kept is not None:
        return kept, True
    return (had if since is None else since), False


def median_time(alone: list[tuple[float, bool]]) -> tuple[float, bool]:
    """The baselines' median hardware time to the target (``baseline_time`` each; the
    lower median of an even count), and whether it was measured. The median of lower
    bounds is a lower bound of the median, and exact when it and every time below it
    were measured."""
    ranked = sorted(alone)
    middle = (len(ranked) - 1) // 2
    return ranked[middle][0], all(exact for _, exact in ranked[:middle + 1])


def speed_up(with_transfer: float | None, alone: tuple[float, bool],
             ) -> tuple[float | None, str | None]:
    """The baselines' time to the target (``median_time``) over the transferred
    learner's, and whether it is "measured" or "at least" (None, None: the transferred
    learner never got there)."""
    if with_transfer is None:
        return None, None
    seconds, measured = alone
    return seconds / max(with_transfer, 1e-9), "measured" if measured else "at least"


def _rounded(seconds: float | None, digits: int = 1) -> float | None:
    return round(seconds, digits) if seconds is not None else None


def _rate(episodes: list[dict[str, Any]], window: int) -> float | None:
    recent = episodes[-window:]
    return round(sum(bool(e["success"]) for e in recent) / len(recent), 3) if recent else None


def partial_and_full(points: list[Any], window: int) -> tuple[list[Any], list[Any]]:
    """A rolling rate's points over fewer than ``window`` episodes (with the first full
    one, so the two lines meet) and those over a full window. (Plotted as one, a
    learner's first lucky episodes stood at 1.00 long before it was at the target.)"""
    return points[:window], points[window - 1:]


def _plot_rates(axes: Any, xs: list[float], rates: list[float], window: int, colour: Any,
                label: str | None = None, **style: Any) -> None:
    """``rates`` against ``xs``: over a full ``window`` as ``style`` says, and before it
    thin and dotted (labelled only if no window is full)."""
    partial, full = partial_and_full(list(zip(xs, rates, strict=True)), window)
    if len(partial) > 1:
        axes.plot([x for x, _ in partial], [r for _, r in partial], color=colour,
                  linewidth=0.8, linestyle=":", label=None if full else label)
    if full:
        axes.plot([x for x, _ in full], [r for _, r in full], color=colour, label=label,
                  **style)


def unmeasured(figures: dict[str, Any]) -> str | None:
    """Why the speed-up goal was not measured (None: it was)."""
    if figures["goals"][SPEEDUP_GOAL] is not None:
        return None
    why = ("the transferred learner was not seen keeping the target (a rate of "
           f"{TARGET[0]:.0%} over {TARGET[1]} episodes, then {TARGET[1]} more)")
    if figures["quick"]:
        why += ": a --quick run's hardware time is too short to tell; run it in full"
    return f"speed-up goal not measured: {why}"


def plot(figures: dict[str, Any], path: Path) -> None:
    """Learning in simulation by episode; on the hardware robots against their time. A
    rate over fewer episodes than its window is drawn dotted."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5))
    curves = figures["curves"]
    _plot_rates(left, list(range(1, len(curves["simulation"]) + 1)), curves["simulation"],
                SIMULATION_WINDOW, "tab:purple")
    left.axhline(figures["simulation"]["transfer_threshold"], color="0.7", linewidth=0.8)
    left.set_title(f"in simulation (lock-step): {figures['simulation']['simulated_s']:.0f} "
                   f"simulated s in {figures['simulation']['wall_s']:.0f} s", fontsize=10)
    left.set_xlabel("episode")
    left.set_ylabel(f"success rate, last {SIMULATION_WINDOW} episodes "
                    "(dotted: fewer yet)")
    left.set_ylim(0, 1.02)
    alone = [name for name in figures["hardware"] if name != "with_transfer"]
    reds = plt.get_cmap("Reds")
    lines = [("with_transfer", "tab:blue", "after transfer", 2.0)] + [
        (name, reds(0.85 - 0.45 * i / max(len(alone) - 1, 1)),
         f"learning on the robot alone ({name})", 1.0) for i, name in enumerate(alone)]
    for name, colour, label, width in lines:
        points = curves[name]
        _plot_rates(right, [p[0] for p in points], [p[1] for p in points], TARGET[1],
                    colour, label=label, marker=".", markersize=3, linewidth=width)
        kept_from = figures["hardware"][name]["hardware_s_to_target"]
        if kept_from is not None:        # where the target was reached for good
            right.axvline(kept_from, color=colour, linewidth=0.8, linestyle=":")
    right.axhline(TARGET[0], color="0.7", linewidth=0.8, label=f"target ({TARGET[0]:.0%})")
    speedup = figures["speedup"]
    since = figures["hardware"]["with_transfer"]["hardware_s_at_target_since"]
    if speedup["value"] is not None:
        against = (f"the median of {speedup['baselines']} baselines"
                   if speedup["baselines"] > 1 else "the baseline")
        gained = f"speed-up {speedup['kind']} {speedup['value']}x over {against}"
    elif since is not None:          # a quick run's robot time is often too short to tell
        gained = f"at target from {since:.0f} s, unconfirmed"
    else:
        gained = "not at the target at the end"
    right.set_title(f"on the hardware robot: transfer {figures['transfer_s']} s,\n{gained}",
                    fontsize=10)
    served = figures["hardware_rate"]
    right.set_xlabel("hardware time (s)" + (f", served at {served:g}x" if served != 1 else ""))
    right.set_ylabel(f"success rate, last {TARGET[1]} episodes (dotted: fewer yet)")
    right.set_ylim(0, 1.02)
    right.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pb3a scenario sim-to-real",
                                     description=summary(__doc__))
    parser.add_argument("--quick", action="store_true",
                        help="at most 30 s in simulation and 55 s on the hardware robots, "
                             "whose worlds run at 8x real time, with a coarser learner")
    parser.add_argument("--world", default=WORLD,
                        help="a bundled world (lab, arena, room) or a world file (default "
                             f"{WORLD}); the learner's goals must lie in it")
    parser.add_argument("--seed", type=seed, default=1, help="0 or more (default 1)")
    parser.add_argument("--baselines", type=int, metavar="N",
                        help="baseline robots learning alone (default: 3, and 1 with --quick)")
    parser.add_argument("--out", default=".",
                        help="directory for sim_to_real.json and .png (default: this one)")
    args = parser.parse_args(argv)
    if args.baselines is not None and args.baselines < 1:
        parser.error("--baselines must be at least 1")
    show_logs()
    try:
        out = output_directory(args.out)
    except ValueError as exc:
        print(f"sim_to_real: {exc}", file=sys.stderr)
        return 2
    try:
        record = run(args.seed, args.quick, args.baselines, args.world)
    except ValueError as exc:
        print(f"sim_to_real: {exc}", file=sys.stderr)
        return 2
    figures = report(record)
    plot(figures, out / "sim_to_real.png")
    figures["plot"] = str(out / "sim_to_real.png")
    (out / "sim_to_real.json").write_text(json.dumps(figures, indent=2))
    print(json.dumps({k: v for k, v in figures.items() if k != "curves"}, indent=2))
    if unmeasured(figures):
        print(f"sim_to_real: {unmeasured(figures)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
