"""The bundled applications, shortened (``--quick``): self-migration, fault-tolerant
mapping on two worlds and seeds, simulation to real, and traffic control on both
networks, with their figures checked against the goals."""

from __future__ import annotations

import functools
import importlib.util
import itertools
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pb3a.cli.main import main
from pb3a.testing import ModuleHarness
from scenarios import SUMO_SEED_MAX, mapping, self_migration, sim_to_real, sumo_seed

# The robot applications and self-migration run alone (the Makefile's test target):
# their figures are timed against the wall clock on all the machine's CPUs. Traffic
# runs in lock-step, its figures the same however busy the machine is.
serial = pytest.mark.serial


@serial
@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one CPU per node needs two CPUs")
def test_the_agent_moves_compute_off_the_loaded_node_while_it_is_loaded() -> None:
    # What it decides and when; the throughput it buys is a figure for the scenario's
    # report (a shared 2-core host's steal makes rates too noisy for a test).
    adaptive = self_migration.run_once(True, (1.5, 3.0, 1.0))
    moves = list(zip(adaptive["moved_at"], adaptive["moved_to"], strict=True))
    assert any(adaptive["load_on"] < at < adaptive["load_off"] and to == "b"
               for at, to in moves), moves
    assert all(at > adaptive["load_on"] for at, _ in moves), moves   # none while quiet
    assert len(moves) == 1, moves        # its own load on b does not send it back to a
    assert adaptive["arrivals"][-1] > adaptive["load_off"]           # values still flow


@pytest.mark.parametrize(("seen", "why"), [
    ({"a": 97.0, "b": 91.0}, "something else on this machine keeps CPU 1 busy too"),
    ({"a": 12.0, "b": 3.0}, "the load on CPU 0 did not show"),
    ({"a": 97.0, "b": 4.0}, "it saw that too briefly")])
def test_self_migration_says_why_its_agent_made_no_move(seen, why) -> None:
    """A run with no move said nothing of why: the agent, rightly, saw both CPUs busy."""
    reason = self_migration.no_move_reason(seen)
    assert f"saw a at {seen['a']:.0f} % and b at {seen['b']:.0f} %" in reason
    assert why in reason


def test_the_scenario_command_names_the_scenarios(capsys) -> None:
    assert main(["scenario", "no-such-thing"]) == 2
    assert "the scenarios: mapping, self-migration, sim-to-real, traffic" in capsys.readouterr().err


MOVED = "the move judged to work, the control system not stopped"


def _check_mapping(figures: dict, fault: str = "motors") -> None:
    # The fault was detected, the control system moved, map and all, to the standby
    # robot's node within the test's bound, the remedy agent judged the move to work and
    # stopped nothing, and the standby mapped on. The hand-off's goal (0.5 s) is the
    # report's: on a loaded 2-core machine it passes 0.5 s in some runs
    # (docs/applications.md says how often).
    # The monitor's false alarms, known and rare under load, are the report's to mark:
    # a run with one that moved or stopped the control system ends as an expected
    # failure naming it, not as a pass, once the rest is checked.
    early = [r for r in figures["remedies"] if r["after_fault_s"] < 0]
    if figures["false_alarms"]:
        assert not figures["goals"]["no false alarm before the fault"], figures["goals"]
        if any(r["action"] in ("move_macro", "stop") for r in early):
            # the fault then struck a robot nobody drove: no hand-off over it to check
            pytest.xfail(f"a false alarm before the fault moved or stopped the control "
                         f"system (the report's goal 'no false alarm before the fault' "
                         f"false): {figures['failures']}, {early}")
    assert figures["detected_fault"] is not None, (figures["failures"], figures["remedies"])
    assert figures["detected_fault"]["fault"] == fault, figures["failures"]
    # (a motor cut shows once the robot is told to move: it may be looking round,
    # still; a dead robot server after 5 periods of 1.1 s: each request's deadline)
    assert figures["detection_s"] < {"motors": 3.0, "robot_link": 8.0}[fault], figures
    # (the macro's move is 0.1-0.4 s here, up to 1.0 s under load; a shared CI host
    # once took 1.1 s)
    assert figures["handoff_s"] is not None and figures["handoff_s"] < 2.0, figures["handoff_s"]
    stopped, handed = figures["stopped_after_fault_s"], (figures["detection_s"]
                                                         + figures["handoff_s"])
    # (the standby is sound: a failure it reports is a false alarm)
    alarms = [f for f in figures["failures"] if f["after_fault_s"] > handed]
    assert figures["goals"][MOVED] or (stopped is not None and alarms), (
        figures["move_verdict"], figures["remedies"], figures["failures"])
    assert figures["mapper_node_at_end"] == "r2", figures["remedies"]
    # the failed robot stands (its motors dead, or stopped by its controller's watchdog
    # 2 s after its server died: it ran on with its last command before, up to 5 m in
    # one quick run, into the standby's view, which mapped it as walls that are not there)
    assert figures["failed_robot_travel_m"] < 1.5, figures["failed_robot_travel_m"]
    maps = figures["map"]
    # the fault came with about half of the free space left to map, whatever the world
    # (the fault also waits for the monitor to know normal running, and coverage is
    # looked at once a second: one slow run put it at 0.64)
    assert maps["before_fault"]["coverage"] < mapping.FAULT_COVERAGE + 0.2
    assert maps["before_fault"]["accuracy"] >= 0.9 and maps["end"]["accuracy"] >= 0.9, maps
    # mapped on from the standby: the map at the end covers more than the last one
    # before the hand-off (the one before the fault, unless one came between). Not
    # more than the one after it (``at_handoff``, 0-2 s after it), which holds the
    # standby's first readings, most of what it adds in the lab in the tests' 6 s:
    # measured, +0.002 to +0.06 after it (two of five under 0.003, snapshots wobbling
    # by up to 0.0007), +0.010 to +0.10 after the one before
    handed_at = figures["fault_at_s"] + figures["detection_s"] + figures["handoff_s"]
    before = [q["coverage"] for q in figures["map_quality_over_time"] if q["t"] < handed_at]
    assert maps["end"]["coverage"] > before[-1], (before[-1], maps)
    if not figures["goals"][MOVED]:
        # (one test run of 2026-12-07 on the room, robot_link: the move judged to work,
        # then a stop before the run ended; docs/applications.md counts the standby's
        # false alarms, which stop it where they come)
        pytest.xfail(f"a false alarm on the standby after the hand-off stopped the "
                     f"control system {stopped} s after the fault (the report's goal "
                     f"{MOVED!r} false): {alarms}, {figures['remedies']}")


# The tests' mapping runs map on after the fault until the remedy agent has judged its
# move (the quick run's 40 s at the latest), not for 40 s: what they check is decided
# by then (the detection, the hand-off, the move judged 6 s after it ended, the map
# grown from the standby's first readings, the failed robot standing), and the rest of
# each run mapped what no test looks at.
@pytest.fixture
def mapping_until_judged(monkeypatch) -> None:
    """``mapping.run``, the command's too, with ``until_judged``."""
    monkeypatch.setattr(mapping, "run", functools.partial(mapping.run, until_judged=True))


@serial
@pytest.mark.timeout(300)
@pytest.mark.usefixtures("mapping_until_judged")
def test_mapping_hands_the_control_system_over_to_the_standby_robot(tmp_path) -> None:
    _check_mapping(mapping.report(mapping.run(tmp_path, "lab", seed=1, quick=True)))


@serial
@pytest.mark.timeout(300)
@pytest.mark.usefixtures("mapping_until_judged")
def test_mapping_from_the_command_line_on_another_world_seed_and_fault(tmp_path,
                                                                     capsys) -> None:
    # the first robot's server killed: its driver says so, and the remedy moves the
    # control system away from a robot that does not answer (its move once failed: the
    # driver was always busy in requests to the dead server)
    assert main(["scenario", "mapping", "--quick", "--world", "room", "--seed", "3",
                 "--fault", "robot_link", "--out", str(tmp_path)]) == 0
    figures = json.loads((tmp_path / "mapping.json").read_text())
    _check_mapping(figures, "robot_link")
    assert (tmp_path / "mapping.png").stat().st_size > 10_000
    assert '"handoff_s"' in capsys.readouterr().out


def _mapping_record(**changes: object) -> dict:
    """A lab run's record, made up: the motors cut at 1000 s, detected 1 s later; the
    failed robot stopped 0.8 m from the standby, whose readings come 1.5 s after the
    detection; a blank snapshot before the fault, one calling every cell free after the
    hand-off, and a blank final map (``changes`` replace the record's entries)."""
    from agents.grid import Grid
    from rave import World
    from rave.worldfile import world_file

    with World.load(world_file("lab")) as world:
        described, size = world.describe(), world.size
    blank = Grid.of(size, 0.1).blank()
    fault_at, detected_at = 1000.0, 1001.0
    updates = [[detected_at + 0.1 * i, 10.2, 1.5, 0.0] for i in range(1, 15)]
    updates += [[detected_at + 1.5 + 0.1 * i, 11.0, 1.5, 3.14] for i in range(10)]
    record = {"world": "lab", "seed": 1, "quick": True, "fault": "motors", "robots": ("r1", "r2"),
              "size": size, "described": described, "started": fault_at - 30.0,
              "fault_at": fault_at, "standby_at": (11.0, 1.5, 3.14),
              "failed_at": (10.2, 1.5, 0.0), "ended": fault_at + 40.0,
              "paths": {"r1": [(fault_at - 30.0, 1.0, 1.5, 0.0)],
                        "r2": [(fault_at - 30.0, 11.0, 1.5, 3.14)]},
              "recorder": {"snapshots": [(fault_at - 1.0, blank),
                                         (fault_at + 5.0, np.zeros_like(blank))],
                           "updates": updates, "remedies": [],
                           "failures": [{"fault": "motors", "at": detected_at}]},
              "remedy": {}, "final_map": blank, "resolution": 0.1,
              "mapper_node_at_end": "r2"}
    return {**record, **changes}


def test_mapping_times_the_hand_off_by_the_standby_robots_readings_not_the_failed_ones() -> None:
    # the failed robot stopped 0.8 m from the standby: its own readings, folded in until
    # the control system has moved (1.5 s after the failure was detected), are no hand-off
    record = _mapping_record()
    fault_at = record["fault_at"]
    figures = mapping.report(record)
    assert figures["handoff_s"] == pytest.approx(1.5)
    assert not figures["goals"]["handoff_s <= 0.5"] and "why_undetected" not in figures
    # the map just after the hand-off, not the snapshot before the fault it was
    assert figures["map"]["at_handoff"]["coverage"] > figures["map"]["before_fault"]["coverage"]
    # a small world, mapped before the monitor had learnt the motors: said, not a silent
    # null detection with exit 0
    unseen = mapping.report({**record, "motors_watched_at_fault": False,
                             "recorder": {**record["recorder"], "failures": []}})
    assert unseen["detection_s"] is None
    assert figures["goals"]["no false alarm before the fault"]
    alarmed = mapping.report({**record, "recorder": {**record["recorder"], "failures": [
        {"fault": "motors", "at": fault_at - 20.0}, *record["recorder"]["failures"]]}})
    assert alarmed["false_alarms"] == 1
    assert not alarmed["goals"]["no false alarm before the fault"]
    assert unseen["why_undetected"].startswith("the monitor was not yet watching the motors")


def test_mapping_s_goals_count_no_move_judged_failed_nor_a_robot_stopped_as_a_success() -> None:
    """A standby stopped 3 s after the hand-off (a false motors alarm on it: the remedy
    agent judged its move failed and stopped the robot) read as a success in every goal."""
    from agents.grid import Grid
    from agents.map_truth import truth

    record = _mapping_record()
    fault_at, detected_at = record["fault_at"], record["recorder"]["failures"][0]["at"]
    grid = Grid.of(record["size"], 0.1)
    perfect = np.where(truth(record["described"], grid), 0.95, 0.05).astype(np.float32)
    xs, _ = grid.centers()

    def known_west_of(x: float) -> np.ndarray:
        return np.where(xs < x, perfect, grid.blank())

    def remedy(event: str, after: float, action: str, outcome: str = "") -> dict:
        return {"event": event, "at": detected_at + after, "fault": "motors",
                "action": action, "outcome": outcome}

    moved = [remedy("chosen", 0.01, "move_macro")]
    failed = [*moved, remedy("failed", 9.0, "move_macro", "the motors fault came back"),
              remedy("chosen", 9.0, "stop"), remedy("worked", 9.01, "stop")]
    run = {**record["recorder"], "updates": [[detected_at + 0.3, 11.0, 1.5, 3.14]],
           "snapshots": [(fault_at - 1.0, known_west_of(6.0)),
                         (detected_at + 1.0, known_west_of(6.5))], "remedies": failed}
    stopped = mapping.report({**record, "recorder": run, "final_map": known_west_of(9.0)})
    assert stopped["move_verdict"] == {"worked": False, "outcome": "the motors fault came back",
                                       "after_fault_s": 10.0}
    assert stopped["stopped_after_fault_s"] == 10.0
    goals = stopped["goals"]
    assert not goals[MOVED], goals
    assert not goals["coverage grows after the hand-off"], goals   # grown, then undone
    assert goals["handoff_s <= 0.5"] and goals["no false alarm before the fault"], goals
    assert goals["accuracy >= 0.9 (before the fault and at the end)"], goals
    # the move judged to work, nothing stopped: every goal met
    worked = [*moved, remedy("worked", 7.0, "move_macro", "control/driver is at work")]
    mapped_on = mapping.report({**record, "recorder": {**run, "remedies": worked},
                                "final_map": known_west_of(9.0)})
    assert mapped_on["move_verdict"]["worked"] and mapped_on["stopped_after_fault_s"] is None
    assert all(mapped_on["goals"].values()), mapped_on["goals"]
    # worked, then a later failure on the standby (which has none of its own) stopped it
    # (a false motors alarm 37 s after the fault in a loaded quick run of lab, seed 1)
    later = [*worked, remedy("chosen", 20.0, "stop"), remedy("worked", 20.01, "stop")]
    stopped_later = mapping.report({**record, "recorder": {**run, "remedies": later},
                                    "final_map": known_west_of(9.0)})
    assert stopped_later["stopped_after_fault_s"] == 21.0
    assert not stopped_later["goals"][MOVED]
    assert stopped_later["goals"]["coverage grows after the hand-off"]   # mapped on till then
    # a false alarm's move before the fault, judged after it, is not the fault's
    early = [{**moved[0], "at": fault_at - 3.0}, remedy("worked", 3.0, "move_macro")]
    alarmed = mapping.report({**record, "recorder": {**run, "remedies": early},
                              "final_map": known_west_of(9.0)})
    assert alarmed["move_verdict"] is None
    assert not alarmed["goals"][MOVED]


def test_a_motor_cut_waits_for_the_monitor_to_watch_the_motors_a_dead_server_does_not() -> None:
    half = mapping.FAULT_COVERAGE
    assert not mapping.fault_due("motors", ["sonars"], lambda: half)
    assert mapping.fault_due("motors", ["sonars", "motors"], lambda: half)
    assert not mapping.fault_due("motors", ["motors"], lambda: half - 0.01)
    assert mapping.fault_due("robot_link", [], lambda: half)
    assert not mapping.fault_due("robot_link", [], lambda: half - 0.01)


def test_mapping_names_the_worlds_when_given_one_it_does_not_know(tmp_path, capsys) -> None:
    assert main(["scenario", "mapping", "--world", "moon", "--out", str(tmp_path)]) == 2
    assert "no world 'moon': the bundled worlds are arena, lab, room" in capsys.readouterr().err
    with pytest.raises(ValueError, match="no fault 'wheels': the faults are motors, robot_link"):
        mapping.run(tmp_path, fault="wheels")


# The test's run learns on the hardware robots until each learner has had the episodes
# it checks there (the quick run's 55 s at the latest), not for the quick run's 55 s:
# in the quick runs of 2026-12-06 and -07, the moved learner had them 14-21 s after its
# move, the baseline (learning since the start) by the move or up to 27 s after it.
HARDWARE_EPISODES = 5


@pytest.fixture
def sim_to_real_until_learnt(monkeypatch) -> None:
    """``sim_to_real.run``, the command's, with ``HARDWARE_EPISODES``."""
    monkeypatch.setattr(sim_to_real, "run", functools.partial(
        sim_to_real.run, hardware_episodes=HARDWARE_EPISODES))


@serial
@pytest.mark.timeout(300)
@pytest.mark.usefixtures("sim_to_real_until_learnt")
def test_sim_to_real_learns_in_lock_step_then_moves_the_learner_to_the_robot(tmp_path) -> None:
    assert main(["scenario", "sim-to-real", "--quick", "--seed", "5",
                 "--out", str(tmp_path)]) == 0
    figures = json.loads((tmp_path / "sim_to_real.json").read_text())
    simulation = figures["simulation"]
    if simulation["ended_by"] == "threshold":                 # what the agent waits for
        assert simulation["success_rate_last_20"] >= 0.9, simulation
    else:      # a slow machine spent the simulation's budget first: it learnt, though
        assert simulation["ended_by"] == "budget" and simulation["success_rate_last_20"] >= 0.5
    # lock-step: as fast as it decides, 13-31x real time here, 7.5x on a shared CI host
    # (a world paced by the clock would be at 1x)
    assert simulation["times_real_time"] > 3
    # The transfer was quick, and its parts add up. Its goal (0.25 s) is the report's:
    # on a loaded 2-core machine it is missed now and then (docs/applications.md).
    assert figures["transfer_s"] < 1.0, figures["transfer_s"]
    assert 0 < figures["move_pause_s"] + figures["move_prepare_s"] <= figures["transfer_s"] + 0.002
    assert figures["learner_node_at_end"] == "robot"
    assert figures["learner_situations"] == 128                 # the quick run's coarser view
    assert figures["speedup"]["baselines"] == 1                 # and its one baseline robot
    # too short to see the speed-up: not measured (null), not missed
    speedup_goal = figures["goals"][sim_to_real.SPEEDUP_GOAL]
    assert speedup_goal is None if figures["speedup"]["value"] is None else isinstance(
        speedup_goal, bool)
    # both learn on their robots (how well varies from run to run: see applications.md)
    for name in ("with_transfer", "alone"):
        assert figures["hardware"][name]["episodes"] >= HARDWARE_EPISODES, figures["hardware"]
        assert figures["hardware"][name]["success_rate_at_end"] is not None
        # from what their robots did: each changed its table there (the moved learner
        # 60-77 of its 640 values in its first five to seven episodes, the baseline
        # 196-304 of its blank one's; a success rate over five episodes tells nothing)
        assert figures["hardware"][name]["table_values_learnt"] > 0, figures["hardware"]
        # the hardware worlds ran faster than real time, as served (a loaded machine falls
        # behind the served pace, 0.75-0.8 of it here: hardware time is their own clock)
        assert figures["hardware"][name]["times_real_time"] >= 0.3 * figures["hardware_rate"]
    assert (tmp_path / "sim_to_real.png").stat().st_size > 10_000


def test_sim_to_real_learns_on_the_robots_until_each_learner_had_the_episodes_asked(
        monkeypatch) -> None:
    """Asked for a number of episodes (the tests), learning on the robots ends once the
    moved learner has had them since its move and every baseline has had them; not
    asked, at the budget's end."""
    monkeypatch.setattr(sim_to_real, "EPISODES_EVERY_S", 0.01)

    class Learning:
        """Each look at the moved learner's recorder finds one more episode after its
        move (ten came before it); a baseline has one for every two such looks."""

        looks = 0

        def state(self, name: str) -> dict:
            if name == "recorder":
                self.looks += 1
                return {"episodes": [{"at": float(i)} for i in range(10 + self.looks)]}
            return {"episodes": [{"at": float(i)} for i in range(self.looks // 2)]}

    names = [("alone", "other")]
    running = Learning()
    sim_to_real._until_learnt(running, names, 9.5, 5, time.monotonic() + 30.0)
    assert running.looks == 10          # the baseline's fifth came last
    started, running = time.monotonic(), Learning()
    sim_to_real._until_learnt(running, names, 9.5, None, time.monotonic() + 0.3)
    assert time.monotonic() - started >= 0.3 and running.looks == 0


def test_sim_to_real_counts_a_target_reached_only_when_it_is_kept() -> None:
    from scenarios.sim_to_real import (
        at_target_since,
        baseline_time,
        median_time,
        speed_up,
        time_to_target,
    )

    def episodes(outcomes: str) -> list[dict]:
        return [{"success": o == "s", "clock": 10.0 * (i + 1)} for i, o in enumerate(outcomes)]

    lucky = episodes("fsfsfsssssss" + "fsfsfsfsfsfsfsfs")     # 7 of 10 once, then half
    assert time_to_target(lucky, 0.0, held=False) == 100.0
    assert time_to_target(lucky, 0.0) is None
    learnt = episodes("ffssfsssss" + "s" * 12)
    assert time_to_target(learnt, 5.0) == time_to_target(learnt, 5.0, held=False) == 95.0
    late = episodes("f" * 10 + "s" * 12)                      # kept, but not for a window yet
    assert time_to_target(late, 0.0, held=False) == 170.0
    assert time_to_target(late, 0.0) is None
    assert at_target_since(late, 0.0) == 170.0 and at_target_since(lucky, 0.0) is None

    # a baseline not seen keeping the target is counted as keeping it from where it last
    # came up to it, if it ended there (the soonest it can turn out to be), else from the
    # end of its run
    assert baseline_time(200.0, 150.0, 720.0) == (200.0, True)
    assert baseline_time(None, at_target_since(late, 0.0), 720.0) == (170.0, False)
    assert baseline_time(None, at_target_since(lucky, 0.0), 720.0) == (720.0, False)
    assert speed_up(50.0, (200.0, True)) == (4.0, "measured")
    assert speed_up(50.0, (170.0, False)) == (3.4, "at least")
    assert speed_up(None, (200.0, True)) == (None, None)
    # against several baselines, their median: one lucky learner does not decide it; the
    # median is measured only if it and every time below it were
    assert median_time([(720.0, False), (100.0, True), (600.0, True)]) == (600.0, True)
    assert median_time([(720.0, False), (100.0, True), (400.0, False)]) == (400.0, False)
    assert median_time([(300.0, True), (100.0, True), (400.0, False), (500.0, True)]) == (
        300.0, True)                                          # the lower median of four


def test_sim_to_real_gives_each_baseline_robot_its_node_brain_seed_and_recorder() -> None:
    from types import SimpleNamespace

    from scenarios.sim_to_real import baselines, configuration

    def lab(port: int, *nodes: str) -> SimpleNamespace:
        return SimpleNamespace(robots={"r1": f"tcp://127.0.0.1:{port}"}, nodes={
            node: SimpleNamespace(address=f"tcp://127.0.0.1:{port + 100 + i}")
            for i, node in enumerate(nodes)})

    names = baselines(3)
    assert names == [("alone", "other"), ("alone_2", "other_2"), ("alone_3", "other_3")]
    labs = [lab(7500 + i, node) for i, (_, node) in enumerate(names)]
    plan = configuration(lab(7400), lab(7450, "robot"), labs, 1.0, seed=31).plan()
    for (name, node), offset, place in zip(names, (1, 2, 3), labs, strict=True):
        assert plan.nodes[node].address == place.nodes[node].address
        assert plan.modules[f"{name}/learner"].node == node
        assert plan.modules[f"{name}/learner"].state["seed"] == 31 + offset
        assert plan.modules[f"{name}/driver"].state["resource"] == place.robots["r1"]
        assert plan.modules[f"{name}_recorder"].node == "ws"
    episodes = {(link.src, link.dst) for link in plan.links if link.src_port == "episode"}
    assert episodes == {("brain/learner", "transfer"), ("brain/learner", "recorder")} | {
        (f"{name}/learner", f"{name}_recorder") for name, _ in names}


def test_sim_to_real_learns_in_simulation_on_the_world_s_first_robot_whatever_its_file_says(
        tmp_path) -> None:
    """With ``WORLD = "lab"`` (whose first robot is a hardware one) the learner learnt
    on the emulator in both phases, with no word of it; a world whose robot had
    another name than r1 failed with ``KeyError: 'r1'``."""
    from scenarios.sim_to_real import learning_robot, simulation

    assert learning_robot("lab") == "r1" and learning_robot("room") == "r1"
    named = tmp_path / "named.toml"
    named.write_text('name = "named"\n[[robots]]\nname = "rover"\npose = [2.0, 2.0, 0.0]\n'
                     '[[robots]]\nname = "spare"\npose = [5.0, 5.0, 0.0]\n')
    assert learning_robot(named) == "rover"
    empty = tmp_path / "empty.toml"
    empty.write_text('name = "empty"\n')
    with pytest.raises(ValueError, match=r"needs a world with a robot; .*empty\.toml declares"):
        learning_robot(empty)
    with simulation("lab", 1, "r1") as lab:
        backends = {name: robot["backend"] for name, robot in lab.describe()["robots"].items()}
    assert backends == {"r1": "sim", "r2": "sim"}


def test_sim_to_real_refuses_a_world_its_goals_do_not_fit_before_anything_runs(
        tmp_path, capsys) -> None:
    """On a 4 x 3 m world (set as ``WORLD``: there was no ``--world``) three of the
    room's four goals lay outside it: the run learnt to 0.25 and said nothing of why."""
    from scenarios.sim_to_real import goal_problems, goals

    small = tmp_path / "small.toml"
    small.write_text('name = "small"\nsize = [4.0, 3.0]\n[[boxes]]\ncenter = [2.0, 2.0]\n'
                     'size = [1.0, 1.0]\n[[robots]]\nname = "r1"\npose = [1.0, 1.0, 0.0]\n')
    assert goal_problems(goals(), "room") == []
    assert goal_problems([[1.0, 2.0], [2.0, 2.0], [5.0, 1.0]], small) == [
        f"goal [2, 2] lies inside an obstacle of world 'small' ({small})",
        f"goal [5, 1] lies outside world 'small' ({small}: 4 x 3 m)"]
    assert main(["scenario", "sim-to-real", "--quick", "--world", str(small),
                 "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert f"goal [6, 4] lies outside world 'small' ({small}: 4 x 3 m)" in err
    assert "goal [1, 1]" not in err and "set the learner's goals in" in err
    assert not (tmp_path / "sim_to_real.json").exists()


def test_sim_to_real_plots_a_rate_over_fewer_episodes_than_its_window_apart(
        tmp_path, monkeypatch) -> None:
    """The curve of the last 10 episodes' success rate was drawn from the first episode:
    a learner's first lucky episodes stood at 1.00 long before the title's "at target
    from 241 s"."""
    import matplotlib.pyplot as plt

    from scenarios.sim_to_real import plot

    drawn = []
    monkeypatch.setattr(plt, "close", drawn.append)
    learnt = [[10.0 * i, 1.0] for i in range(1, 16)]          # 15 episodes, all successes
    figures = {
        "curves": {"simulation": [0.0, 0.5, 0.67] + [0.75] * 27, "with_transfer": learnt,
                   "alone": [[20.0 * i, 0.0] for i in range(1, 6)]},
        "simulation": {"transfer_threshold": 0.9, "simulated_s": 600.0, "wall_s": 9.0},
        "hardware": {"with_transfer": {"hardware_s_to_target": None,
                                       "hardware_s_at_target_since": 100.0},
                     "alone": {"hardware_s_to_target": None}},
        "speedup": {"value": None, "kind": None, "baselines": 1},
        "transfer_s": 0.1, "hardware_rate": 8.0}
    plot(figures, tmp_path / "sim_to_real.png")
    left, right = drawn[0].axes

    def lines(axes):
        return [(list(line.get_xdata()), line.get_linestyle()) for line in axes.get_lines()
                if line.get_color() != "0.7"]                 # not the threshold's

    # the transferred learner: dotted over its first 10 episodes, solid from the 10th on
    (partial, dotted), (full, solid) = lines(right)[:2]
    assert (dotted, solid) == (":", "-")
    assert partial == [10.0 * i for i in range(1, 11)] and full == [10.0 * i for i in
                                                                     range(10, 16)]
    # the baseline never had 10 episodes: dotted only, and still in the legend
    assert lines(right)[2] == ([20.0 * i for i in range(1, 6)], ":")
    assert "learning on the robot alone (alone)" in [
        text.get_text() for text in right.get_legend().get_texts()]
    # in simulation, the agent's window of 20
    assert [len(x) for x, _ in lines(left)] == [20, 11]


def test_sim_to_real_reports_a_speed_up_it_did_not_measure_as_not_measured() -> None:
    """A --quick run, too short to see the transferred learner keep the target, said the
    speed-up goal was missed (false) beside a speed-up of null."""
    from scenarios.sim_to_real import SPEEDUP_GOAL, report, unmeasured

    def episodes(outcomes: str, every: float) -> list[dict]:
        return [{"success": o == "s", "clock": every * (i + 1), "at": 100.0 + i}
                for i, o in enumerate(outcomes)]

    def record(transferred: str, alone: str, quick: bool) -> dict:
        return {"seed": 5, "quick": quick, "rate": 8.0, "world": "room", "situations": 128,
                "transfer": {"moved_at": 50.0, "decided_at": 49.9, "move": {}},
                "threshold": 0.9, "ended_by": "threshold", "simulated_s": 600.0,
                "simulation_wall_s": 20.0, "baselines": ["alone"],
                "episodes": {"with_transfer": episodes(transferred, 20.0),
                             "alone": episodes(alone, 20.0)},
                "clocks": {"with_transfer": (0.0, 400.0), "alone": (0.0, 400.0)},
                "walls": {"with_transfer": 50.0, "alone": 50.0},
                "learner_node_at_end": "robot"}

    quick = report(record("s" * 15, "f" * 15, quick=True))    # at target, not confirmed
    assert quick["speedup"]["value"] is None
    assert quick["goals"][SPEEDUP_GOAL] is None
    assert quick["goals"]["transfer_s <= 0.25"] is True
    assert "speed-up goal not measured: the transferred learner was not seen keeping the " \
           "target" in unmeasured(quick) and "--quick run" in unmeasured(quick)
    kept = report(record("s" * 20, "f" * 20, quick=False))   # kept from 200 s, alone not
    assert kept["speedup"] == {"value": 2.0, "kind": "at least", "baselines": 1,
                               "baselines_median_s": 400.0,
                               "baselines_median_measured": False}
    assert kept["goals"][SPEEDUP_GOAL] is False and unmeasured(kept) is None


def test_sim_to_real_says_no_transfer_when_the_learner_never_moved() -> None:
    from scenarios.sim_to_real import simulation_ended_by

    assert simulation_ended_by({"moved_at": 0.0, "decided_at": 0.0}, 100.0) == "no transfer"
    assert simulation_ended_by({"moved_at": 0.0, "decided_at": 0.0}, math.inf) == "no transfer"
    assert simulation_ended_by({"moved_at": 51.0, "decided_at": 50.0}, math.inf) == "threshold"
    assert simulation_ended_by({"moved_at": 151.0, "decided_at": 150.0}, 100.0) == "budget"


OWN_CONTROLLERS = ("fixed_time", "max_pressure", "longest_queue", "gap_out", "time_loss",
                   "q_learning")


def _check_traffic(figures: dict) -> None:
    runs = figures["runs"]
    agents = runs["agents"]["mean_delay_s"]
    assert set(runs) == {*OWN_CONTROLLERS, "sumo_actuated", "sumo_delay_based", "agents"}
    assert all(run["teleports"] == 0 for run in runs.values()), runs
    assert all(run["vehicles"] == runs["agents"]["vehicles"] for run in runs.values())
    goals = figures["goals"]
    assert goals["less delay than SUMO's delay_based"], runs
    for name in ("fixed_time", "max_pressure", "longest_queue", "time_loss"):
        assert goals[f"less delay than {name} alone"], runs
    periods = figures["periods"]
    heavy = {"ring": ["west heavy", "east heavy"],
             "grid": ["east-west heavy", "north-south heavy"]}[figures["network"]]
    assert [p["period"] for p in periods] == [*heavy, "balanced", "surge"]
    for period in periods:
        delays = period["mean_delay_s"]
        assert set(delays) == set(runs), period
        assert period["best_alone"] == min(OWN_CONTROLLERS, key=delays.__getitem__)
    surge = periods[-1]
    if figures["network"] == "grid":
        # The surge saturates the grid, where time_loss beats gap_out: each junction's
        # agent swaps to it once, in the surge, and the agents beat every controller.
        assert all(goals.values()), (goals, runs)
        swapped = {swap["controller"]: swap for swap in figures["swaps"]}
        assert len(swapped) == len(figures["swaps"]) == figures["swap_events"] == 9
        assert all(swap["to"] == "time_loss" and swap["time"] >= surge["begin_s"]
                   for swap in swapped.values()), figures["swaps"]
        assert all(p["mean_delay_s"]["agents"] == p["mean_delay_s"]["gap_out"]
                   for p in periods[:-1])                 # gap_out's run until then
        assert surge["mean_delay_s"]["agents"] < surge["mean_delay_s"]["gap_out"]
    else:
        # No junction of the ring is ever saturated, and gap_out is the best of the
        # agents' controllers there everywhere: nothing calls for a swap, so the system
        # with its agents gives exactly gap_out's run alone. The goal of beating
        # gap_out is not met on the ring.
        assert runs["agents"]["swaps"] == 0 and figures["swap_events"] == 0
        assert agents == runs["gap_out"]["mean_delay_s"], runs
        assert all(p["mean_delay_s"]["agents"] == p["mean_delay_s"]["gap_out"]
                   for p in periods)
    assert figures["agents_wall_s"] < 30          # lock-step: as fast as they decide


@pytest.mark.timeout(120)
def test_traffic_on_the_ring_from_the_command_line(tmp_path, capsys, monkeypatch) -> None:
    pytest.importorskip("libsumo", reason="SUMO (the traffic extra) is not installed")
    monkeypatch.setenv("PB3A_TRAFFIC_CACHE", str(tmp_path / "cache"))
    assert main(["scenario", "traffic", "--quick", "--network", "ring", "--seed", "5",
                 "--out", str(tmp_path)]) == 0
    figures = json.loads((tmp_path / "traffic_ring.json").read_text())
    _check_traffic(figures)
    assert figures["duration_s"] == 900.0 and figures["seed"] == 5
    assert (tmp_path / "traffic_ring.png").stat().st_size > 10_000
    assert '"goals"' in capsys.readouterr().out


@pytest.mark.timeout(120)
def test_traffic_on_the_grid(tmp_path) -> None:
    pytest.importorskip("libsumo", reason="SUMO (the traffic extra) is not installed")
    from scenarios import traffic

    # Seed 3: where a quick run's margin is widest (0.96 s; 0.62 and 0.24 s on seeds 2
    # and 6; on seed 1 the quick surge is too short for time loss to win, see
    # docs/applications.md). The agents are in the driver's lock-step, so the run is the
    # same whatever the load (before, its swaps came later under load, and one junction
    # swapped back in a CI run).
    _check_traffic(traffic.run("grid", seed=3, quick=True, cache=tmp_path))


class _SwappingAsItEnds:
    """A launched traffic system (its ``state`` and ``events``) whose run has ended with
    two swaps still in flight: the system has made them (``module_swapped``), B's agent
    records its own only at the second read of its state, C's never before the system
    stops (its record is made as it stops, and cannot be read)."""

    def __init__(self) -> None:
        from pb3a.events import Event

        def swap(seq: int, junction: str) -> Event:
            return Event(seq, "module_swapped", f"{junction}/controller", 0.0,
                         {"cls": "agents.traffic.time_loss:TimeLoss", "kept": []})

        self.made = [swap(1, "A"), swap(2, "B"), swap(3, "C")]
        self.reads = {"A": 0, "B": 0, "C": 0}
        self.stopped = False

    def launch(self) -> _SwappingAsItEnds:
        return self

    def __enter__(self) -> _SwappingAsItEnds:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stopped = True

    def state(self, name: str) -> dict:
        assert not self.stopped, "a stopped system's state was read"
        if name == "sumo":
            return {"result": {"end_s": 900.0, "mean_delay_s": 20.0}, "status": "finished"}
        junction = name.partition("/")[0]
        self.reads[junction] += 1
        record = {"time": {"A": 700.0, "B": 880.0}.get(junction), "controller":
                  f"{junction}/controller", "from": "gap_out", "to": "time_loss",
                  "reason": "demand 50.0/min, queue 9.0"}
        recorded = junction == "A" or (junction == "B" and self.reads["B"] > 1)
        return {"swaps": [record] if recorded else []}

    def events(self, since: int = 0, *, timeout: float = 0.0) -> list:
        return self.made[since:]


def test_traffic_reports_every_swap_the_system_made_also_those_in_flight_at_the_end(
        monkeypatch) -> None:
    """A swap still in flight as the run ended (made by the system, its agent setting
    the new controller's state) was missing from the report's swaps, though counted
    in swap_events: in about one run in six under load."""
    from scenarios import traffic

    system = _SwappingAsItEnds()
    monkeypatch.setattr(traffic, "configuration", lambda *args, **kwargs: system)
    monkeypatch.setattr(traffic, "POLL_S", 0.01)
    monkeypatch.setattr(traffic, "SETTLE_S", 0.5)     # (C's record never comes)
    run = traffic.run_agents(traffic.network_path("grid"), 1, 900.0,
                             {"A": None, "B": None, "C": None}, timeout_s=5.0)
    assert run["swap_events"] == len(run["swaps"]) == 3, run["swaps"]
    by_junction = {swap["controller"]: swap for swap in run["swaps"]}
    assert by_junction["B/controller"]["time"] == 880.0        # its agent's own record
    assert by_junction["C/controller"] == {
        "time": 900.0, "controller": "C/controller", "from": None, "to": "time_loss",
        "reason": "made by the system as the run ended; its agent's record was not read",
        "unrecorded": True}
    assert [swap["time"] for swap in run["swaps"]] == [700.0, 880.0, 900.0]


@pytest.mark.parametrize(("scale", "complaint"), [
    ("surge=x", "--scale 'surge=x': give PERIOD=FACTOR (surge=2) or a FACTOR for every"),
    ("rush=2", "no period rush to scale; its periods are west heavy, east heavy, balanced"),
    ("surge=0", "the factor of period surge must be a number above 0"),
])
def test_traffic_names_what_is_wrong_with_a_demand_scale(tmp_path, capsys, scale,
                                                         complaint) -> None:
    started = time.monotonic()
    assert main(["scenario", "traffic", "--scale", scale, "--out", str(tmp_path)]) == 2
    assert complaint in capsys.readouterr().err
    assert time.monotonic() - started < 5.0 and not any(tmp_path.iterdir())


def test_traffic_runs_without_agents_take_the_driver_settings_of_the_file(tmp_path,
                                                                          monkeypatch) -> None:
    """Each controller alone and SUMO's programs ran with the driver's defaults, whatever
    ``[modules.sumo]`` said: a minimum green set there changed the agents' run alone."""
    from scenarios import traffic

    own = tmp_path / "traffic.toml"
    own.write_text(traffic.CONFIG.read_text().replace(
        "state = { min_green_s = 5.0, lockstep_timeout_s = 2.0 }",
        "state = { min_green_s = 8.0, control_step_s = 2.0, seed = 99 }"))
    monkeypatch.setattr(traffic, "CONFIG", own)
    assert traffic.driver_settings() == {"min_green_s": 8.0, "control_step_s": 2.0}
    taken: list[dict] = []

    class Stopped(Exception):
        pass

    def run_in_process(*_args, settings=None, seed=None, **_kwargs):
        taken.append({**settings, "seed": seed})
        raise Stopped

    def driver(_resource, _cache, **state):
        taken.append(state)
        raise Stopped

    monkeypatch.setattr(traffic, "run_in_process", run_in_process)
    monkeypatch.setattr(traffic.lockstep, "driver", driver)
    gap_out = traffic.controllers()["gap_out"]
    for run in (lambda: traffic.run_alone(Path("ring.toml"), 3, 60.0, gap_out),
                lambda: traffic.run_sumo(Path("ring.toml"), 3, 60.0, "actuated")):
        with pytest.raises(Stopped):
            run()
    alone, sumo = taken
    assert alone == {"min_green_s": 8.0, "control_step_s": 2.0, "seed": 3}
    assert (sumo["min_green_s"], sumo["control_step_s"], sumo["seed"]) == (8.0, 2.0, 3)
    assert sumo["own_programs"] is True and sumo["signals"] == "actuated"


def test_traffic_refuses_a_period_scaled_twice() -> None:
    """``--scale surge=2 --scale surge=3`` ran with 3, silently."""
    from scenarios.traffic import parse_scale

    assert parse_scale(["surge=2", "1.5"]) == {"surge": 2.0, "*": 1.5}
    for twice in (["surge=2", "surge=3"], ["2", "3"]):
        with pytest.raises(ValueError, match=r"is scaled twice: give it once"):
            parse_scale(twice)


def test_traffic_plot_shows_a_controller_the_agents_ran_all_along(tmp_path,
                                                                  monkeypatch) -> None:
    """On the ring the agents kept gap-out all along: its line vanished under theirs,
    thick and black on top of it."""
    import matplotlib.pyplot as plt

    from scenarios.traffic import plot

    drawn = []
    monkeypatch.setattr(plt, "close", drawn.append)
    same, other = [[60.0, 20.0], [120.0, 25.0]], [[60.0, 30.0], [120.0, 35.0]]
    figures = {"delay_over_time": {"fixed_time": other, "gap_out": same, "agents": same},
               "runs": {"fixed_time": {"mean_delay_s": 32.5}, "gap_out": {"mean_delay_s": 22.5},
                        "agents": {"mean_delay_s": 22.5}},
               "swaps": [], "periods": [], "duration_s": 180.0, "network": "ring",
               "seed": 77}
    plot(figures, tmp_path / "traffic_ring.png")
    (axes,) = drawn[0].axes
    lines = {line.get_label().split(":")[0]: line for line in axes.get_lines()}
    assert lines["agents"].get_zorder() < lines["gap_out"].get_zorder()   # gap-out on top
    labels = [text.get_text() for text in axes.get_legend().get_texts()]
    assert "agents: 22.5 s (= gap_out, drawn inside it)" in labels
    assert "fixed_time: 32.5 s" in labels


def test_traffic_names_the_networks_when_given_one_it_does_not_know(tmp_path, capsys) -> None:
    assert main(["scenario", "traffic", "--network", "moon", "--out", str(tmp_path)]) == 2
    assert "no network 'moon': the bundled networks are cross, grid, ring" in (
        capsys.readouterr().err)


_GRID = ('name = "{name}"\n[build]\nnetgenerate = [{arguments}]\n[demand.streams]\n'
         'a = {{ from = "left0A0", to = "A0bottom0", group = "g" }}\n'
         '[[demand.periods]]\nshare = 1.0\nrates = {{ g = 100 }}\n')


@pytest.mark.parametrize(("arguments", "complaint"), [
    ('"--grid", "--grid.number", "many"',
     "failed (netgenerate exit 1): Error: While processing option 'grid.number'"),
    ('"--grid", "--grid.number", "2", "--grid.attach-length", "100"',
     "the built network has no signalized junction, so there is nothing for the "
     "controllers to run: mark the junctions to signalize"),
    ('"--grid", "--grid.number", "5", "--grid.attach-length", "100", '
     '"--default-junction-type", "traffic_light"',
     "the built network has 25 signalized junctions; the traffic driver has slots for 16"),
    ('"--grid", "--grid.number", "2", "--grid.attach-length", "100", '
     '"--default-junction-type", "traffic_light", "--prefix.junction", "x."',
     "the scenario names each signalized junction's modules after it, and 'x.A0', "
     "'x.A1', 'x.B0', 'x.B1' cannot name them: a module's name has only letters"),
])
def test_traffic_names_what_keeps_a_network_from_it_before_it_runs(
        tmp_path, capsys, monkeypatch, arguments, complaint) -> None:
    """A network its tool could not build ended in a RuntimeError traceback; one with
    more junctions than the driver's slots in a ValueError traceback from the driver's
    setup; one with no signalized junction ran on for good, a loop at full CPU; one
    whose junction ids cannot name modules ('x.A0', or the driver's 'sumo') failed in
    a ConfigError traceback blaming traffic.toml, after every controller's run alone."""
    pytest.importorskip("libsumo", reason="SUMO (the traffic extra) is not installed")
    monkeypatch.setenv("PB3A_TRAFFIC_CACHE", str(tmp_path / "cache"))
    network = tmp_path / "mine.toml"
    network.write_text(_GRID.format(name="mine", arguments=arguments))
    started = time.monotonic()
    assert main(["scenario", "traffic", "--quick", "--network", str(network),
                 "--out", str(tmp_path / "out")]) == 2
    said = capsys.readouterr().err
    assert complaint in said and f"{network}" in said and "Traceback" not in said
    assert time.monotonic() - started < 10 and not (tmp_path / "out").exists()


# A command's main (argv[3], "module:function"; ``pb3a`` by default) given the arguments
# argv[2], in a process that cannot import the modules named in argv[1] (as if they were
# not installed); prints how long its main took
_WITHOUT = """
import importlib, importlib.abc, json, sys, time

class Hidden(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in hidden:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None

hidden = set(json.loads(sys.argv[1]))
sys.meta_path.insert(0, Hidden())
module, _, function = (sys.argv[3] if len(sys.argv) > 3 else "pb3a.cli.main:main").partition(":")
main = getattr(importlib.import_module(module), function)
started = time.monotonic()
code = main(json.loads(sys.argv[2]))
print(time.monotonic() - started)
sys.exit(code)
"""


@pytest.mark.parametrize(("hidden", "missing"), [
    (["sumo", "libsumo", "traci", "sumolib"], "SUMO is not installed"),
    (["libsumo"], "libsumo is not installed")], ids=["no-sumo", "no-libsumo"])
@pytest.mark.parametrize("network", ["ring", "mine.toml"])
def test_traffic_names_sumo_missing_before_it_builds_or_runs(tmp_path, hidden, missing,
                                                             network) -> None:
    """With eclipse-sumo installed but not libsumo, the network was built, then the first
    run ended in a ``SumoMissing`` traceback, exit 1 (with neither, it was said, as here)."""
    if "sumo" not in hidden and importlib.util.find_spec("sumo") is None:
        pytest.skip("eclipse-sumo (the traffic extra) is not installed: SUMO is missing whole")
    (tmp_path / "mine.toml").write_text(_GRID.format(
        name="mine", arguments='"--grid", "--grid.number", "2", "--grid.attach-length", '
        '"100", "--default-junction-type", "traffic_light"'))
    argv = ["scenario", "traffic", "--quick", "--network", network, "--out", "out"]
    repo = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PYTHONPATH": str(repo), "PB3A_TRAFFIC_CACHE": str(tmp_path / "cache")}
    done = subprocess.run([sys.executable, "-c", _WITHOUT, json.dumps(hidden), json.dumps(argv)],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert done.stderr == (f"traffic: {missing}: install the project's traffic extra "
                           "(pip install -e '.[traffic]', or make)\n")
    assert float(done.stdout) < 3.0                        # (about 0.1 s)
    assert not list(tmp_path.glob("cache/*.net.xml"))     # nothing built
    assert not (tmp_path / "out").exists()


def test_training_names_libsumo_missing_before_an_episode(tmp_path) -> None:
    """``python -m agents.traffic.training`` ended in a ``SumoMissing`` traceback at its
    first episode with libsumo missing; it says so in one line, exit 2."""
    if importlib.util.find_spec("sumo") is None:
        pytest.skip("eclipse-sumo (the traffic extra) is not installed: SUMO is missing whole")
    repo = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PYTHONPATH": str(repo), "PB3A_TRAFFIC_CACHE": str(tmp_path / "cache")}
    done = subprocess.run([sys.executable, "-c", _WITHOUT, json.dumps(["libsumo"]),
                           json.dumps(["--episodes", "1", "--out", "table.json"]),
                           "agents.traffic.training:main"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert done.stderr == ("training: libsumo is not installed: install the project's "
                           "traffic extra (pip install -e '.[traffic]', or make)\n")
    assert not (tmp_path / "table.json").exists()


@pytest.mark.parametrize("junction", ["sumo", "C#1"])
def test_traffic_names_a_junction_whose_id_cannot_name_its_modules(tmp_path, capsys,
                                                                  monkeypatch, junction) -> None:
    """The crossing, its junction renamed: the driver's name, or one no module can have
    (netconvert's joined junctions are "cluster_J1_J2_#3more"). The system's
    configuration refused it after every controller's run alone: a ConfigError traceback
    that blamed traffic.toml ('sumo' gave the driver the junction's state)."""
    pytest.importorskip("libsumo", reason="SUMO (the traffic extra) is not installed")
    monkeypatch.setenv("PB3A_TRAFFIC_CACHE", str(tmp_path / "cache"))
    here = Path(__file__).resolve().parent.parent / "scenarios" / "traffic"
    for suffix in (".nod.xml", ".edg.xml"):
        text = (here / f"cross{suffix}").read_text()
        (tmp_path / f"cross{suffix}").write_text(text.replace('id="C"', f'id="{junction}"')
                                                 .replace('"C"', f'"{junction}"'))
    (tmp_path / "cross.toml").write_text((here / "cross.toml").read_text())
    assert main(["scenario", "traffic", "--quick", "--network", str(tmp_path / "cross.toml"),
                 "--out", str(tmp_path / "out")]) == 2
    said = capsys.readouterr().err
    assert f"and {junction!r} cannot name them: a module's name has only letters" in said
    assert "rename the junction in the network's nodes" in said and "Traceback" not in said


def test_traffic_names_a_network_file_its_tool_cannot_read(tmp_path, capsys,
                                                           monkeypatch) -> None:
    """Its nodes file cut short: a RuntimeError traceback, exit 1."""
    pytest.importorskip("libsumo", reason="SUMO (the traffic extra) is not installed")
    monkeypatch.setenv("PB3A_TRAFFIC_CACHE", str(tmp_path / "cache"))
    (tmp_path / "mine.nod.xml").write_text('<nodes><node id="C" x="0" y="0"')
    (tmp_path / "mine.edg.xml").write_text("<edges/>")
    network = tmp_path / "mine.toml"
    network.write_text('[build]\nnetconvert = { nodes = "mine.nod.xml", edges = '
                       '"mine.edg.xml" }\n[demand.streams]\na = { from = "x", to = "y", '
                       'group = "g" }\n[[demand.periods]]\nshare = 1.0\nrates = { g = 1 }\n')
    assert main(["scenario", "traffic", "--network", str(network),
                 "--out", str(tmp_path / "out")]) == 2
    said = capsys.readouterr().err
    assert f"traffic: building network mine from {network} failed (netconvert exit 1)" in said
    assert f"In file '{tmp_path / 'mine.nod.xml'}'" in said and "Traceback" not in said


class _Runtime:
    """Where each module runs, and the moves a ``Mover`` asks for."""

    def __init__(self) -> None:
        self.nodes = {"compute": "a", "other": "b"}
        self.moves: list[tuple[str, str]] = []

    def where(self, name: str) -> str:
        return self.nodes[name]

    def migrate(self, name: str, to: str, *, wait: bool = True) -> None:
        self.moves.append((name, to))


def test_the_mover_judges_the_load_where_a_target_set_while_it_runs_is() -> None:
    """A target set on a running mover is judged by its own node's load: before, by the
    node of the target it had at setup, so it moved ``other`` to where it already ran."""
    runtime = _Runtime()
    mover = ModuleHarness(self_migration.Mover, runtime=runtime,
                          state={"warmup_s": 0.0, "patience": 1})
    mover.module.set_state({"target": "other"})           # on b, which is quiet
    mover.feed("outside_b", 10.0)
    mover.feed("outside_a", 90.0)
    assert runtime.moves == []
    mover.module.set_state({"target": "compute"})         # on a, which is busy
    mover.feed("outside_a", 90.0)
    assert runtime.moves == [("compute", "b")]


@pytest.mark.parametrize("scenario", ["mapping", "sim-to-real", "self-migration", "traffic"])
def test_a_scenario_whose_out_cannot_hold_the_report_says_so_before_it_runs(
        tmp_path, capsys, scenario) -> None:
    """A file for --out ended in a FileExistsError traceback; a directory that cannot be
    written in failed once the run was over, its figures lost."""
    taken = tmp_path / "report.json"
    taken.write_text("{}")
    started = time.monotonic()
    assert main(["scenario", scenario, "--quick", "--out", str(taken)]) == 2
    assert f"--out {taken}: it is a file; give a directory for the report" in \
        capsys.readouterr().err
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    if os.access(locked, os.W_OK) and os.geteuid() == 0:
        locked = tmp_path / "not-a-dir" / "x"       # (root writes anywhere: a file's child)
        (tmp_path / "not-a-dir").write_text("")
    assert main(["scenario", scenario, "--quick", "--out", str(locked)]) == 2
    assert "the report cannot be written there" in capsys.readouterr().err
    if os.geteuid() == 0:   # (a directory even root cannot write in: what the probe finds)
        assert main(["scenario", scenario, "--quick", "--out", "/proc"]) == 2
        assert "--out /proc: the report cannot be written there" in capsys.readouterr().err
    assert time.monotonic() - started < 10


@pytest.mark.parametrize(("name", "standby"), [("r1", "standby"), ("standby", "standby-2")])
def test_a_one_robot_world_gets_a_standby_of_another_name(tmp_path, name, standby) -> None:
    """A world whose one robot was named 'standby' crashed the mapping scenario: the
    standby placed beside it took the same name."""
    world = tmp_path / "room.toml"
    world.write_text(f'name = "room"\nsize = [6.0, 4.0]\n[[robots]]\nname = "{name}"\n'
                     'pose = [1.0, 1.0, 0.0]\n')
    robots, placed = mapping.place_robots(world)
    assert robots == (name, standby) and list(placed) == [standby]


def test_a_world_too_small_for_a_standby_is_refused_by_name_not_crowded_onto_its_robot(
        tmp_path) -> None:
    """In a walled 1.6 m square the standby was placed 0.21 m from the robot, and the
    world server refused it with two tracebacks; in a roomier one it keeps clear."""
    for side, fits in ((1.6, False), (3.0, True)):
        world = tmp_path / f"box{side}.toml"
        corners = [[0.0, 0.0], [side, 0.0], [side, side], [0.0, side], [0.0, 0.0]]
        walls = "".join(f"[[walls]]\nfrom = {a}\nto = {b}\n"
                        for a, b in itertools.pairwise(corners))
        world.write_text(f'name = "box"\nsize = [{side}, {side}]\n{walls}'
                         f'[[robots]]\nname = "r1"\npose = [{side / 2}, {side / 2}, 0.0]\n')
        if not fits:
            with pytest.raises(ValueError, match=r"no room for a standby robot in .*box1\.6"):
                mapping.place_robots(world)
            continue
        _, placed = mapping.place_robots(world)
        x, y, _ = placed["standby"]
        assert math.hypot(x - side / 2, y - side / 2) >= mapping.CLEARANCE_M + 0.25


@pytest.mark.parametrize("scenario", ["mapping", "sim-to-real", "traffic", "self-migration"])
def test_a_seed_numpy_cannot_take_is_refused_as_the_arguments_are_read(capsys,
                                                                       scenario) -> None:
    """--seed -1 started the worlds, whose process died in numpy: two tracebacks, exit 1."""
    started = time.monotonic()
    with pytest.raises(SystemExit) as ended:
        main(["scenario", scenario, "--quick", "--seed", "-1"])
    assert ended.value.code == 2
    assert "'-1' is not a seed: give a whole number, 0 or more" in capsys.readouterr().err
    assert time.monotonic() - started < 10


def test_a_seed_sumo_cannot_take_is_refused_as_the_arguments_are_read(capsys) -> None:
    """SUMO reads --seed as a C int: 2147483648 passed the check, and the traffic
    scenario ended in libsumo's traceback ("Could not parse commandline options")."""
    with pytest.raises(SystemExit) as ended:
        main(["scenario", "traffic", "--quick", "--seed", "2147483648"])
    assert ended.value.code == 2
    assert ("'2147483648' is not a seed: give a whole number, 0 or more and at most "
            "2147483647") in capsys.readouterr().err


def test_the_largest_seed_sumo_takes_is_taken() -> None:
    """The bound is SUMO's own: 2147483647 is a C int, and is read as it was given."""
    assert sumo_seed("2147483647") == SUMO_SEED_MAX == 2**31 - 1


@pytest.mark.parametrize(("scenario", "ends"), [
    ("mapping", "maps on."), ("sim-to-real", "finishes learning there."),
    ("self-migration", "stress processes load."), ("traffic", "actuated programs.")])
def test_a_scenario_s_help_says_its_command_and_its_whole_summary(capsys, scenario,
                                                                    ends) -> None:
    """Its description was the docstring's first line, cut mid-sentence ("... and moves
    a"), under the usage of a program named self_migration."""
    with pytest.raises(SystemExit) as ended:
        main(["scenario", scenario, "--help"])
    assert ended.value.code == 0
    shown = capsys.readouterr().out
    assert shown.startswith(f"usage: pb3a scenario {scenario} ")
    assert " ".join(shown.split()).split(" options:")[0].endswith(ends)
