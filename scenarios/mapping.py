"""Fault-tolerant mapping: a robot maps a lab until its motors fail; its whole control
system then moves, map and all, to a standby robot's on-board computer and maps on.

The world's first robot (an emulated hardware robot) runs the control system
(``scenarios/mapping.toml``: driver, occupancy mapper, frontier explorer, hardware
monitor) on its on-board computer, a node behind its own node controller; the second
robot, also emulated hardware, stands by with a node of its own (a world with one
robot gets a standby placed as far from it as its free space allows). Once the map
covers ``FAULT_COVERAGE`` of the free space (or at the end of the first phase), and
for a motor cut once the monitor has learnt the motors' normal running (in the
mission's first seconds), the scenario makes the first robot fail (``FAULTS``): by
default it cuts its motor power (``motors_off``, through its robot server, as ``rave
fault`` would), or with ``--fault robot_link`` it kills its robot server, as a crash
or a cut cable would (the robot's controller then stops it ``WATCHDOG_S`` later, as a
Pioneer's stops a robot whose client fell silent). About half the free space is then
left to map (less in a small world, which the robot maps faster than the monitor
learns its motors). The monitor (dead motors) or the driver (a robot that stopped
answering) reports the failure; the remedy agent (case-based reasoning) moves the
control macro to the standby robot's node and re-points its driver at that robot;
mapping goes on from the map the mapper carried.

Measured in the run: detection time (fault to its failure event), hand-off
time (that event to the first map update made from the standby robot's readings),
and the map against the world's ground truth (accuracy of the classified cells,
coverage of the reachable free space) before the fault, at the hand-off and at the end,
and how far the failed robot went after the fault.

Run it: ``pb3a scenario mapping [--quick] [--world W] [--seed N] [--fault F] [--out DIR]`` (or
``python -m scenarios.mapping``). It prints the report as JSON and writes
``mapping.json`` and ``mapping.png`` to DIR.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time
import tomllib
from collections.abc import Callable, Collection
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from agents.grid import Grid
from agents.map_truth import reachable, score, truth
from pb3a import Input, InputPort, Module, System
from pb3a.cli.arguments import seed
from pb3a.cli.log_output import show_logs
from rave import World
from rave.pioneer import RADIUS
from rave.worldfile import world_file
from scenarios import output_directory, summary
from scenarios.lab import Lab, wait_until

CONFIG = Path(__file__).with_name("mapping.toml")
PHASES = {"full": (150.0, 150.0), "quick": (45.0, 40.0)}   # s: mapping before the fault
                                                            # at the latest, and after it
FAULT_COVERAGE = 0.5         # the fault comes once the map covers this share of the free space
POSE_EVERY_S = 0.5                            # how often the robots' true paths are sampled
DONE_EVERY_S = 1.0                            # how often the map's coverage is looked at
HANDOFF_NEAR_M = 1.0                          # an update this near the standby robot (and
                                              # nearer it than the failed one) is its
CLEARANCE_M = 0.6                             # a standby robot placed by the scenario keeps this
WATCHDOG_S = 2.0             # a robot silent this long (world time) is stopped by its
                             # controller: one whose server died does not run on for good
GOALS = {"handoff_s": 0.5, "accuracy": 0.9}
FAULTS = {                    # what --fault does to the first robot, and who says so
    "motors": "its motor power cut (motors_off); its hardware monitor says so",
    "robot_link": f"its robot server killed (its controller's watchdog stops it "
                  f"{WATCHDOG_S:g} s later); its driver says so once the robot is silent",
}


class MappingRecorder(Module):
    """Keeps what the report needs: a map snapshot every ``snapshot_s``, every map
    update (when, where), every failure (the monitor's and the driver's) and remedy."""

    map = Input(np.ndarray)
    updated = Input(np.ndarray, shape=(4,), dtype="float64", policy="queue:100000")
    failure = Input(dict, policy="queue:1000")
    driver_failure = Input(dict, policy="queue:1000")
    remedy = Input(dict, policy="queue:1000")
    snapshot_s = 2.0
    snapshots: list[tuple[float, np.ndarray]] = []     # (unix time, map)
    updates: list[list[float]] = []                    # [unix time, x, y, heading]
    failures: list[dict[str, Any]] = []
    remedies: list[dict[str, Any]] = []

    def on_input(self, port: InputPort) -> None:
        if port.name == "map":
            now = time.time()
            latest = port.read()
            if not self.snapshots or now - self.snapshots[-1][0] >= self.snapshot_s:
                self.snapshots.append((now, np.array(latest)))
        elif port.name == "updated":
            self.updates.extend(row.tolist() for row in port.read_all())
        elif port.name in ("failure", "driver_failure"):
            self.failures.extend(port.read_all())
        else:
            self.remedies.extend(port.read_all())


def configuration(lab: Lab, robots: tuple[str, str], cases: Path) -> System:
    """``mapping.toml`` with this run's addresses, world size, and the file the remedy
    agent learns its cases into."""
    data = tomllib.loads(CONFIG.read_text())
    first, standby = robots
    data["nodes"]["r1"]["address"] = lab.nodes["r1"].address
    data["nodes"]["r2"]["address"] = lab.nodes["r2"].address
    control = data["macros"]["control"]["modules"]
    control["driver"]["state"]["resource"] = lab.robots[first]
    for name in ("mapper", "explorer"):
        control[name].setdefault("state", {})["size"] = list(lab.size)
    data["modules"]["remedy"]["state"]["standby_resource"] = lab.robots[standby]
    data["modules"]["remedy"]["state"]["cases_path"] = str(cases)
    return System.from_dict(data, source=str(CONFIG))


def run(out: Path, world: str = "lab", seed: int = 1, quick: bool = False,
        fault: str = "motors", *, until_judged: bool = False) -> dict[str, Any]:
    """One run with ``fault`` (one of ``FAULTS``); what happened, for ``report``. The
    remedy agent's learned cases go to ``out``/remedy-cases.toml. With ``until_judged``,
    mapping after the fault ends once the remedy agent has judged its remedy (worked or
    failed; at the phase's end at the latest): all a check of the hand-off needs (the
    tests), short of the mapping on that the report's coverage goal looks at."""
    if fault not in FAULTS:
        raise ValueError(f"no fault {fault!r}: the faults are {', '.join(FAULTS)}")
    before, after = PHASES["quick" if quick else "full"]
    path = world_file(world)
    robots, added = place_robots(path)
    with Lab(path, seed=seed, onboard=("r1", "r2"), hardware=robots, add=added,
             watchdog_s=WATCHDOG_S) as lab:
        size, described = lab.size, lab.described
        starts = [lab.poses()[name] for name in robots]
        with configuration(lab, robots, out / "remedy-cases.toml").launch() as running:
            started = time.time()
            paths: dict[str, list[tuple[float, ...]]] = {name: [] for name in robots}

            def coverage() -> float:
                mapper = running.state("control/mapper")
                grid = Grid.of(size, mapper["resolution"])
                occupied = truth(described, grid)
                return score(_probabilities(mapper["log_odds"]), occupied,
                             _free_space(occupied, grid, starts)).coverage

            def time_for_the_fault() -> bool:
                return fault_due(fault, running.state("control/monitor")["watched"],
                                 coverage)

            _follow(lab, paths, time.monotonic() + before, time_for_the_fault)
            watched = "motors" in running.state("control/monitor")["watched"]
            if fault == "motors":
                lab.robot(robots[0], "inject", fault="motors_off", params={})
            else:
                lab.kill_robot_server(robots[0])
            fault_at = time.time()
            poses = lab.poses()
            failed_at, standby_at = poses[robots[0]], poses[robots[1]]

            def judged() -> bool:
                # (the recorder's, which the report reads: the agent's own history may
                # hold the verdict a moment before the recorder has it)
                return until_judged and any(
                    r["event"] in ("worked", "failed") and r["at"] >= fault_at
                    for r in running.state("recorder")["remedies"])

            _follow(lab, paths, time.monotonic() + after, judged)
            recorder = running.state("recorder")
            remedy = running.state("remedy")
            final = running.state("control/mapper")
            where = running.where("control/mapper")
    return {"world": path.stem, "seed": seed, "quick": quick, "fault": fault, "robots": robots,
            "size": size, "described": described, "started": started,
            "fault_at": fault_at, "failed_at": failed_at, "standby_at": standby_at,
            "ended": time.time(),
            "paths": paths, "recorder": recorder, "remedy": remedy,
            "final_map": _probabilities(final["log_odds"]), "resolution": final["resolution"],
            "mapper_node_at_end": where, "motors_watched_at_fault": watched}


def place_robots(path: Path) -> tuple[tuple[str, str], dict[str, tuple[float, float, float]]]:
    """The robot that maps and the standby: the world's first two robots. A world with
    only one gets a standby ("standby", or "standby-2" when the first has that name)
    placed where it is furthest from the first
    while keeping ``CLEARANCE_M`` from every obstacle and from the first robot's body;
    a world with none is refused."""
    with World.load(path) as world:
        described = world.describe()
        grid = Grid.of(world.size, 0.1)
    declared = list(described["robots"])
    if not declared:
        raise ValueError(f"the mapping scenario needs a world with a robot; {path} declares "
                         "none (add a [[robots]] entry)")
    if len(declared) >= 2:
        return (declared[0], declared[1]), {}
    first = described["robots"][declared[0]]["pose"]
    occupied = truth(described, grid)
    xs, ys = grid.centers()
    # as clear of the first robot's body as of an obstacle: in a small world the
    # furthest roomy place was on top of it, and the world server refused it
    roomy = (ndimage.distance_transform_edt(~occupied) * grid.resolution >= CLEARANCE_M) \
        & (np.hypot(xs - first[0], ys - first[1]) >= CLEARANCE_M + RADIUS) \
        & reachable(occupied, grid, first[:2])
    far = np.where(roomy, np.hypot(xs - first[0], ys - first[1]), -1.0)
    row, col = np.unravel_index(np.argmax(far), far.shape)
    if far[row, col] < 0:
        raise ValueError(f"no room for a standby robot in {path}: add a second [[robots]] "
                         "entry")
    # (a robot of the world's own may have that name: the placed one takes another)
    standby = "standby" if declared[0] != "standby" else "standby-2"
    return (declared[0], standby), {standby: (float(xs[row, col]), float(ys[row, col]), 0.0)}


def fault_due(fault: str, watched: Collection[str], coverage: Callable[[], float]) -> bool:
    """Whether to make the robot fail now: its map's ``coverage()`` has reached
    ``FAULT_COVERAGE``, and for a motor cut the monitor watches the motors (the cut is
    its to see). A dead robot server is the driver's to see, which learns nothing
    first: that fault waited for the motors too, and came late in a small world."""
    if fault == "motors" and "motors" not in watched:
        return False
    return coverage() >= FAULT_COVERAGE


def _follow(lab: Lab, paths: dict[str, list[tuple[float, ...]]], until: float,
            done: Callable[[], bool] = lambda: False) -> None:
    """Sample every robot's true pose until ``until`` (monotonic) or, looked at each
    ``DONE_EVERY_S``, until ``done()``."""
    looked = time.monotonic()
    while time.monotonic() < until:
        now = time.time()
        for name, pose in lab.poses().items():
            if name in paths:
                paths[name].append((now, *pose))
        if time.monotonic() - looked >= DONE_EVERY_S:
            looked = time.monotonic()
            if done():
                return
        wait_until(min(until, time.monotonic() + POSE_EVERY_S))


def _travel(path: list[tuple[float, ...]]) -> float:
    """How far (m) a robot went along its sampled ``path`` ((time, x, y, heading) each)."""
    return float(sum(math.dist(a[1:3], b[1:3]) for a, b in itertools.pairwise(path)))


def _free_space(occupied: np.ndarray, grid: Grid,
                starts: list[tuple[float, ...]]) -> np.ndarray:
    """The free space the robots can reach from where they start."""
    free_space = np.zeros(grid.shape, dtype=bool)
    for start in starts:
        free_space |= reachable(occupied, grid, tuple(start[:2]))
    return free_space


def _remedy_after(remedies: list[dict[str, Any]], fault_at: float
                  ) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """Of the remedy agent's ``remedies`` (its ``remedy`` port's), the verdict ("worked"
    or "failed") on the first move it chose after the fault, and the first stop it chose
    after the fault (a move judged failed is followed by one; so is a later failure on
    the standby, which has no standby of its own): None for either not there. A move
    chosen before the fault (a false alarm's) is not the fault's."""
    after = [r for r in remedies if r["at"] >= fault_at
             and r.get("event") in ("chosen", "worked", "failed")]
    chosen = next((i for i, r in enumerate(after)
                   if r["event"] == "chosen" and r["action"] == "move_macro"), None)
    move = None if chosen is None else next(
        (r for r in after[chosen + 1:] if r["event"] != "chosen"), None)
    stop = next((r for r in after if r["action"] == "stop"), None)
    return move, stop


def _probabilities(log_odds: np.ndarray) -> np.ndarray:
    return (1.0 - 1.0 / (1.0 + np.exp(np.asarray(log_odds, dtype=np.float64)))).astype(np.float32)


def report(record: dict[str, Any]) -> dict[str, Any]:
    """The figures of one run, and whether they meet the goals."""
    grid = Grid.of(record["size"], record["resolution"])
    occupied = truth(record["described"], grid)
    free_space = _free_space(occupied, grid,
                             [record["paths"][name][0][1:] for name in record["robots"]])
    recorder, started, fault_at = record["recorder"], record["started"], record["fault_at"]

    def quality(probabilities: np.ndarray) -> dict[str, float]:
        figures = score(probabilities, occupied, free_space)
        return {"accuracy": round(figures.accuracy, 4), "coverage": round(figures.coverage, 4),
                "walls": round(figures.walls, 4)}

    over_time = [{"t": round(at - started, 2), **quality(snapshot)}
                 for at, snapshot in recorder["snapshots"]]
    detected = next((f for f in recorder["failures"]
                     if f.get("fault") == record["fault"] and f["at"] >= fault_at), None)
    false_alarms = [f for f in recorder["failures"] if f["at"] < fault_at]
    handoff_at = None
    if detected is not None:
        # an update from the standby robot: near where it stands, and nearer it than the
        # failed robot, whose own readings are folded in until the control system moves
        sx, sy = record["standby_at"][:2]
        fx, fy = record["failed_at"][:2]
        handoff_at = next((u[0] for u in recorder["updates"] if u[0] > detected["at"]
                           and math.hypot(u[1] - sx, u[2] - sy)
                           < min(HANDOFF_NEAR_M, math.hypot(u[1] - fx, u[2] - fy))), None)
    move, stop = _remedy_after(recorder["remedies"], fault_at)
    before = [s for at, s in recorder["snapshots"] if at <= fault_at]
    # the first snapshot after the hand-off (the last before it was, snapshots coming
    # every 2 s and hand-offs in 0.1-0.4 s, the one before the fault)
    at_handoff = [s for at, s in recorder["snapshots"] if handoff_at and at >= handoff_at]
    figures: dict[str, Any] = {
        "scenario": "mapping", "world": record["world"], "seed": record["seed"],
        "quick": record["quick"], "fault": record["fault"], "robots": list(record["robots"]),
        "fault_at_s": round(fault_at - started, 2),
        "detection_s": round(detected["at"] - fault_at, 3) if detected else None,
        "detected_fault": detected, "false_alarms": len(false_alarms),
        "failures": [{**f, "after_fault_s": round(f["at"] - fault_at, 3)}
                     for f in recorder["failures"]],
        "handoff_s": round(handoff_at - detected["at"], 3) if handoff_at else None,
        "remedies": [{**r, "after_fault_s": round(r["at"] - fault_at, 3)}
                     for r in recorder["remedies"]],
        # the remedy agent's verdict on the move it chose after the fault (null: none
        # chosen, or not judged by the end), and when after the fault it chose to stop
        # the robot the control system drove (null: never), mapping ending there
        "move_verdict": None if move is None else {
            "worked": move["event"] == "worked", "outcome": move["outcome"],
            "after_fault_s": round(move["at"] - fault_at, 3)},
        "stopped_after_fault_s": None if stop is None else round(stop["at"] - fault_at, 3),
        "mapper_node_at_end": record["mapper_node_at_end"],
        "failed_robot_travel_m": round(_travel(
            [p for p in record["paths"][record["robots"][0]] if p[0] >= fault_at]), 3),
        "map": {"before_fault": quality(before[-1]) if before else None,
                "at_handoff": quality(at_handoff[0]) if at_handoff else None,
                "end": quality(record["final_map"])},
        "map_quality_over_time": over_time,
    }
    if record["fault"] == "motors" and not record.get("motors_watched_at_fault", True):
        # (a small world: mapped, the robot standing, before the monitor had learnt its
        # motors from the windows of driving it needs: the cut was seen by nobody)
        figures["why_undetected"] = (
            "the monitor was not yet watching the motors when they were cut: it learns "
            "them from windows of the robot driving, and had not seen enough of them (a "
            "small world is mapped first, the robot then standing; a busy machine is slow "
            "to learn); use a larger world, or --fault robot_link")
    maps = figures["map"]
    moved = figures["move_verdict"] is not None and figures["move_verdict"]["worked"]
    figures["goals"] = {
        "handoff_s <= 0.5": figures["handoff_s"] is not None
        and figures["handoff_s"] <= GOALS["handoff_s"],
        "accuracy >= 0.9 (before the fault and at the end)": all(
            maps[k] is not None and maps[k]["accuracy"] >= GOALS["accuracy"]
            for k in ("before_fault", "end")),
        # (a hand-off undone, the move judged failed and the standby stopped, is no
        # mapping on: one undone 3 s after it grew the map by 0.002 in that time, and
        # one undone later could have grown it more and met the goal)
        "coverage grows after the hand-off": maps["at_handoff"] is not None
        and maps["end"]["coverage"] > maps["at_handoff"]["coverage"] + 0.01 and moved,
        # (the README gave it as a goal; the report counted them and judged nothing)
        "no false alarm before the fault": figures["false_alarms"] == 0,
        # (a move judged failed, its robot stopped, read as a success by every goal)
        "the move judged to work, the control system not stopped": moved and stop is None,
    }
    return figures


VIRTUAL_TINT = (0.6, 0.75, 0.95)     # a virtual obstacle's colour in the true map


def plot(record: dict[str, Any], figures: dict[str, Any], path: Path) -> None:
    """The true map and the learnt ones with both robots' paths; quality over time."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    grid = Grid.of(record["size"], record["resolution"])
    occupied = truth(record["described"], grid)
    extent = (0, grid.width, 0, grid.height)
    started, fault_at = record["started"], record["fault_at"]
    struck = {"motors": "motors cut", "robot_link": "robot server killed"}[record["fault"]]
    before = [s for at, s in record["recorder"]["snapshots"] if at <= fault_at]
    fig = plt.figure(figsize=(13, 8))
    # a virtual obstacle is mapped as any other (the sonars see it), but a real robot
    # drives through it: drawn black, a path across it read as a collision
    described = record["described"]
    solid = truth({**described, "obstacles": [o for o in described["obstacles"]
                                              if not o.get("virtual")]}, grid)
    tint = np.array(VIRTUAL_TINT)
    true_map = np.ones((*grid.shape, 3))                  # white: free
    true_map[occupied & ~solid] = tint
    true_map[solid] = 0.0
    panels = [("ground truth (blue: virtual, seen but not solid)", true_map),
              (f"map at the fault ({figures['fault_at_s']:.0f} s)",
               before[-1] if before else grid.blank()),
              ("map at the end", record["final_map"])]
    colours = ("tab:red", "tab:blue")
    for column, (title, image) in enumerate(panels):
        axis = fig.add_subplot(2, 3, column + 1)
        axis.imshow(image, origin="lower", extent=extent, cmap="gray_r", vmin=0, vmax=1)
        for colour, name in zip(colours, record["robots"], strict=True):
            samples = [p for p in record["paths"][name]
                       if column == 2 or column == 0 or p[0] <= fault_at]
            if samples:
                xs, ys = [p[1] for p in samples], [p[2] for p in samples]
                axis.plot(xs, ys, color=colour, linewidth=1, label=name)
                axis.plot(xs[0], ys[0], "o", color=colour, markersize=4)
        if column > 0:
            stuck = next((p for p in record["paths"][record["robots"][0]] if p[0] >= fault_at),
                         None)
            if stuck:
                axis.plot(stuck[1], stuck[2], "x", color="black", markersize=9,
                          label=struck)
        axis.set_title(title, fontsize=10)
        axis.set_xticks([])
        axis.set_yticks([])
    fig.axes[2].legend(loc="upper center", bbox_to_anchor=(0.5, -0.01), ncol=3, fontsize=7,
                       frameon=False)
    quality = fig.add_subplot(2, 1, 2)
    over = figures["map_quality_over_time"]
    quality.plot([q["t"] for q in over], [q["accuracy"] for q in over], label="accuracy")
    quality.plot([q["t"] for q in over], [q["coverage"] for q in over], label="coverage")
    quality.axvline(fault_at - started, color="black", linestyle=":", label=struck)
    if figures["detection_s"] is not None:
        quality.axvline(fault_at - started + figures["detection_s"], color="tab:red",
                        linestyle="--", label="failure detected")
    if figures["handoff_s"] is not None:
        quality.axvline(fault_at - started + figures["detection_s"] + figures["handoff_s"],
                        color="tab:green", linestyle="-.", label="mapping from the standby")
    if figures["stopped_after_fault_s"] is not None:
        quality.axvline(fault_at - started + figures["stopped_after_fault_s"], color="black",
                        linestyle="--", label="robot stopped (remedy agent)")
    quality.axhline(GOALS["accuracy"], color="0.7", linewidth=0.8)
    quality.set_ylim(0, 1.02)
    quality.set_xlabel("time (s)")
    quality.set_ylabel("share")
    quality.legend(loc="lower right", fontsize=8)
    quality.set_title(f"{figures['world']}, seed {figures['seed']}: detection "
                      f"{figures['detection_s']} s, hand-off {figures['handoff_s']} s",
                      fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pb3a scenario mapping",
                                     description=summary(__doc__))
    parser.add_argument("--quick", action="store_true",
                        help=f"shorter phases (the fault within {PHASES['quick'][0]:.0f} s, "
                             f"then {PHASES['quick'][1]:.0f} s of mapping after it)")
    parser.add_argument("--world", default="lab",
                        help="a bundled world (lab, arena, room) or a world file (default lab)")
    parser.add_argument("--seed", type=seed, default=1, help="0 or more (default 1)")
    parser.add_argument("--fault", choices=tuple(FAULTS), default="motors",
                        help="how the first robot fails: " + "; ".join(
                            f"{name}: {what}" for name, what in FAULTS.items()))
    parser.add_argument("--out", default=".",
                        help="directory for mapping.json, mapping.png and the remedy "
                             "agent's remedy-cases.toml (default: this one)")
    args = parser.parse_args(argv)
    show_logs()
    try:
        out = output_directory(args.out)
    except ValueError as exc:
        print(f"mapping: {exc}", file=sys.stderr)
        return 2
    try:
        record = run(out, args.world, args.seed, args.quick, args.fault)
    except ValueError as exc:
        print(f"mapping: {exc}", file=sys.stderr)
        return 2
    figures = report(record)
    plot(record, figures, out / "mapping.png")
    figures["plot"] = str(out / "mapping.png")
    (out / "mapping.json").write_text(json.dumps(figures, indent=2, default=_plain))
    print(json.dumps({k: v for k, v in figures.items() if k != "map_quality_over_time"},
                     indent=2, default=_plain))
    if "why_undetected" in figures:
        print(f"mapping: no remedy to measure: {figures['why_undetected']}", file=sys.stderr)
        return 1
    return 0


def _plain(value: Any) -> Any:
    """What JSON cannot say directly: numpy scalars and arrays."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON")


if __name__ == "__main__":
    sys.exit(main())
