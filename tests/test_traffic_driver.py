"""``TrafficDriver`` on its own against one signalized crossing (SUMO through
libsumo, in this process): its readings, requests applied, legal lights through a
controller swapped mid-phase, the lock-step, re-pointing, and the run's figures.
One system test runs it in its own worker with a controller in another."""

from __future__ import annotations

import itertools
import re
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from conftest import eventually
from sample_modules import PhaseAlternator
from traffic_legality import illegal_steps

from agents.traffic.driver import TrafficDriver
from agents.traffic.messages import JunctionLayout, JunctionReading, NetworkReading, PhaseRequest
from agents.traffic.simulation import APPROACH_S, Simulation
from pb3a import System
from pb3a.errors import RuntimeFailure
from pb3a.testing import ModuleHarness

pytest.importorskip("libsumo", reason="SUMO (the traffic extra) is not installed: "
                                      "pip install -e '.[traffic]'")

NETWORKS = Path(__file__).resolve().parent.parent / "scenarios" / "traffic"
CROSS = str(NETWORKS / "cross.toml")
RING = str(NETWORKS / "ring.toml")
NS, EW = 0, 1          # the crossing's green phases: north-south, then east-west


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("traffic-cache")


@pytest.fixture
def driver(cache: Path) -> Iterator[Callable[..., ModuleHarness]]:
    """Makes a driver on the crossing (state overridable), and stops it after."""
    made: list[ModuleHarness] = []

    def make(**state) -> ModuleHarness:
        harness = ModuleHarness(TrafficDriver, state={
            "resource": CROSS, "cache_dir": str(cache), "duration_s": 600.0,
            "min_green_s": 5.0, **state})
        made.append(harness)
        return harness

    yield make
    for harness in made:
        harness.close()


def test_a_simulation_that_fails_as_it_starts_leaves_the_process_free(driver,
                                                                      monkeypatch) -> None:
    """libsumo runs one simulation per process: one that failed as it read its signal
    programs kept the slot, and every later one was refused ("give each traffic driver
    its own worker")."""
    from agents.traffic import simulation

    def no_green(phases: list) -> None:
        raise ValueError("the program has no green phase")

    with monkeypatch.context() as patched:
        patched.setattr(simulation.SignalPlan, "from_program", staticmethod(no_green))
        with pytest.raises(ValueError, match="the program has no green phase"):
            driver()
    assert simulation.Simulation._running is None
    assert driver().state["status"] == "running"


def answer(harness: ModuleHarness, green: int) -> JunctionReading:
    """Answer the newest reading of the crossing with ``green``; the next reading."""
    reading = harness.last("reading_0")
    harness.feed("request_0", PhaseRequest(reading.junction, reading.step, green))
    return harness.last("reading_0")


def test_it_writes_each_junctions_detectors_and_the_networks_totals(driver) -> None:
    harness = driver()
    first = harness.last("reading_0")
    assert harness.state["junctions"] == ["C"] and harness.state["status"] == "running"
    assert (first.junction, first.step, first.time, first.stage) == ("C", 0, 0.0, "green")
    layout = first.layout
    assert len(layout.greens) == 2 and len(layout.links) == 12
    assert set(first.queues) == set(first.waiting) == set(first.arrivals) == set(layout.lanes_in)
    assert set(first.outgoing) == set(layout.lanes_out) and len(layout.lanes_in) == 4
    for _ in range(90):                      # north-south green all along (no yellow asked)
        reading = answer(harness, NS)
    ns_lanes = {i for i, _ in layout.movements(NS)}
    red = sum(q for lane, q in reading.queues.items() if lane not in ns_lanes)
    green = sum(q for lane, q in reading.queues.items() if lane in ns_lanes)
    assert red >= 3 and green <= 1, reading.queues        # queues build up at red only
    assert sum(w for lane, w in reading.waiting.items() if lane not in ns_lanes) > 30
    assert sum(sum(r.arrivals.values()) for r in harness.written["reading_0"]) >= 15
    # a lane whose vehicles approach has its nearest due within the approach time
    readings = harness.written["reading_0"]
    assert any(r.arriving_in for r in readings)
    for r in readings:
        assert set(r.arriving_in) <= set(layout.lanes_in)
        assert all(seconds >= 0 for seconds in r.arriving_in.values())
        assert all(r.arriving_in.get(lane, 1e9) <= APPROACH_S
                   for lane, count in r.approaching.items() if count)
    # a vehicle standing at the red has lost time there: delayed; the green's flow has not
    assert set(reading.delayed) == set(layout.lanes_in)
    assert all(reading.delayed[lane] <= reading.vehicles[lane] for lane in layout.lanes_in)
    assert sum(d for lane, d in reading.delayed.items() if lane not in ns_lanes) >= red
    assert sum(d for lane, d in reading.delayed.items() if lane in ns_lanes) <= 1
    assert reading.signal == layout.greens[NS] and reading.elapsed == 90.0
    traffic = harness.last("traffic")
    assert isinstance(traffic, NetworkReading) and traffic.step == 90
    assert traffic.departed >= 15 and traffic.halting == red + green
    assert harness.written["clock"][:3] == [0.0, 1.0, 2.0]


class ScriptedSumo:
    """libsumo's lane and vehicle calls, answered from ``vehicles``: per vehicle, its
    lane, position (m), speed (m/s) and time loss (s) so far."""

    def __init__(self) -> None:
        self.vehicles: dict[str, tuple[str, float, float, float]] = {}
        on = lambda lane: [v for v, (at, *_) in self.vehicles.items() if at == lane]  # noqa: E731
        self.lane = SimpleNamespace(
            getLastStepVehicleIDs=on, getLastStepHaltingNumber=lambda lane: sum(
                self.vehicles[v][2] < 0.1 for v in on(lane)),
            getWaitingTime=lambda lane: 0.0, getLength=lambda lane: 200.0,
            getLastStepVehicleNumber=lambda lane: len(on(lane)))
        self.vehicle = SimpleNamespace(
            getLanePosition=lambda v: self.vehicles[v][1],
            getSpeed=lambda v: self.vehicles[v][2], getTimeLoss=lambda v: self.vehicles[v][3])


def test_a_vehicle_is_an_arrival_once_and_delayed_by_the_time_it_lost_on_its_lane() -> None:
    """Before, a vehicle that changed lanes on its way in was an arrival again, and the
    demand the agents measured on the ring's two-lane loop was 23-42 % too high."""
    sumo = ScriptedSumo()
    simulation = Simulation.__new__(Simulation)        # no SUMO: its calls are scripted
    simulation._sumo = sumo
    simulation.layouts = {"J": JunctionLayout("J", (("in_0", "out_0"), ("in_1", "out_0")),
                                              ("GG",), ("in_0", "in_1"), ("out_0",))}
    simulation._entered = {"in_0": {}, "in_1": {}}
    simulation._lengths = {}
    sumo.vehicles = {"a": ("in_0", 20.0, 13.0, 5.0)}   # came in having lost 5 s elsewhere
    first = simulation.junction_detectors("J")
    assert first["arrivals"] == {"in_0": 1, "in_1": 0}
    assert first["delayed"] == {"in_0": 0, "in_1": 0}  # near, but lost nothing here yet
    sumo.vehicles = {"a": ("in_1", 120.0, 12.0, 5.5), "b": ("in_0", 30.0, 13.0, 0.0)}
    moved = simulation.junction_detectors("J")
    assert moved["arrivals"] == {"in_0": 1, "in_1": 0}  # a changed lanes: b is the new one
    sumo.vehicles = {"a": ("in_1", 190.0, 0.0, 7.0), "b": ("in_0", 60.0, 13.0, 0.5)}
    braking = simulation.junction_detectors("J")
    assert braking["delayed"] == {"in_0": 0, "in_1": 1}    # a: 1.5 s lost on its lane
    assert braking["arrivals"] == {"in_0": 0, "in_1": 0} and braking["queues"]["in_1"] == 1
    sumo.vehicles = {"b": ("in_0", 10.0, 13.0, 9.0)}       # far from the stop line
    assert simulation.junction_detectors("J")["delayed"] == {"in_0": 0, "in_1": 0}


def test_a_requested_phase_comes_after_the_minimum_green_and_a_yellow(driver) -> None:
    harness = driver(min_green_s=8.0)
    greens = harness.last("reading_0").layout.greens
    shown = [answer(harness, EW).signal for _ in range(13)]
    yellow = "".join("y" if c in "Gg" else c for c in greens[NS])
    assert shown == [greens[NS]] * 8 + [yellow] * 3 + [greens[EW]] * 2
    reading = harness.last("reading_0")
    assert (reading.green, reading.target, reading.stage, reading.elapsed) == (EW, EW, "green", 2.0)


def test_a_minimum_green_set_while_it_runs_holds_from_the_green_shown_now(driver) -> None:
    """Before, the lights went by the minimum green the run began with."""
    harness = driver(min_green_s=5.0)
    greens = harness.last("reading_0").layout.greens
    answer(harness, NS)
    harness.module.set_state({"min_green_s": 8.0})
    shown = [harness.last("reading_0").signal] + [answer(harness, EW).signal
                                                  for _ in range(8)]
    assert shown[:8] == [greens[NS]] * 8 and shown[8] != greens[NS]


def test_a_controller_swapped_mid_phase_keeps_the_lights_legal(driver) -> None:
    """A steady controller, then (mid-green) one that changes its mind every second:
    every step's lights are legal: no conflicting greens, yellow before red."""
    harness = driver(min_green_s=5.0)
    greens = harness.last("reading_0").layout.greens
    shown = [answer(harness, NS).signal for _ in range(3)]      # the first controller
    shown += [answer(harness, step % 2).signal for step in range(150)]   # swapped in
    assert illegal_steps(shown, greens, yellow_s=3) == []
    assert {greens[NS], greens[EW]} <= set(shown)                # and it did switch
    assert harness.state["rejected"] == 0


def green_spans(readings: list[JunctionReading]) -> list[tuple[str, float]]:
    """Each green the lights showed, whole (not the first nor the one the run ends
    in), with the simulated seconds it lasted: a reading's signal is what was shown
    since the reading before."""
    spans: list[list] = []
    for before, reading in itertools.pairwise(readings):
        if spans and spans[-1][0] == reading.signal:
            spans[-1][1] += reading.time - before.time
        else:
            spans.append([reading.signal, reading.time - before.time])
    return [(state, seconds) for state, seconds in spans[1:-1] if "y" not in state]


@pytest.mark.parametrize("control_step_s", [2.5, 1.4])
def test_a_control_step_of_any_length_keeps_the_minimum_green(driver,
                                                              control_step_s: float) -> None:
    harness = driver(min_green_s=5.0, control_step_s=control_step_s, duration_s=120.0)
    while harness.state["status"] == "running":      # a controller that always wants
        reading = harness.last("reading_0")           # the other green
        harness.feed("request_0", PhaseRequest("C", reading.step, 1 - reading.green))
    spans = green_spans(harness.written["reading_0"])
    assert len(spans) >= 5 and all(seconds >= 5.0 for _, seconds in spans), spans


@pytest.mark.parametrize("bad", [{"control_step_s": 0.0}, {"control_step_s": -1.0},
                                 {"control_step_s": float("nan")},
                                 {"min_green_s": -5.0}, {"duration_s": float("inf")},
                                 {"own_programs": "false"}])
def test_a_step_green_or_duration_out_of_range_is_refused_by_name(driver, bad) -> None:
    (name, _), = bad.items()
    with pytest.raises(ValueError, match=f"{name} must be"):
        driver(**bad)
    harness = driver(duration_s=30.0)
    before = harness.state[name]
    with pytest.raises(ValueError, match=f"{name} must be"):
        harness.module.set_state(bad)
    assert harness.state[name] == before and harness.state["status"] == "running"


@pytest.mark.parametrize("bad", [
    {"seed": -1}, {"seed": 2**31}, {"seed": "7"}, {"seed": 1.5}, {"seed": True},
    {"lockstep_timeout_s": float("nan")}, {"lockstep_timeout_s": -1.0},
    {"lockstep_timeout_s": float("inf")}])
def test_a_seed_or_lock_step_timeout_it_cannot_go_by_is_refused_and_the_run_goes_on(
        driver, bad) -> None:
    """A seed SUMO cannot take ended the running simulation, then failed the new one in
    libsumo ("Could not parse commandline options"; "7" in int()); 1.5 and True ran as
    1. A lock-step timeout of NaN never ran out (a stuck controller stopped the run for
    good), a negative one counted every junction late at every step."""
    (name, _), = bad.items()
    with pytest.raises(ValueError, match=f"{name} must be"):
        driver(**bad)
    harness = driver(duration_s=30.0)
    for _ in range(3):
        answer(harness, NS)
    with pytest.raises(ValueError, match=f"{name} must be"):
        harness.module.set_state(bad)
    state = harness.state
    assert state["status"] == "running" and state["step_count"] == 3
    assert state["seed"] == 1 and state["lockstep_timeout_s"] == 2.0 and state["result"] == {}


def test_a_slow_controller_holds_the_simulation_and_a_missing_one_is_late(driver) -> None:
    now = [100.0]
    harness = driver(lockstep_timeout_s=2.0)
    harness.module._clock = lambda: now[0]
    harness.module._published_at = now[0]
    now[0] += 1.5
    harness.step()                           # no request yet, within the timeout
    assert harness.last("reading_0").step == 0 and harness.state["late"] == 0
    answer(harness, NS)                      # the slow controller answers: on it goes
    assert harness.last("reading_0").step == 1
    now[0] += 2.5                            # this time it does not answer in time
    harness.step()
    assert harness.last("reading_0").step == 2
    assert harness.state["late"] == 1 and harness.state["late_by_junction"] == {"C": 1}
    harness.feed("request_0", PhaseRequest("C", 1, EW))         # it answers, too late
    assert harness.last("reading_0").step == 2 and harness.state["late"] == 1
    assert harness.module._heads["C"].requested == EW            # its wish still stands


def test_a_linked_done_holds_the_step_until_the_junction_has_dealt_with_it(driver) -> None:
    """With ``done_0`` fed by a link (a junction's performance agent), a step waits for
    the junction to say it is done with that step's time, as well as for its request;
    a time of another step does not count, and one not said by the timeout is late."""
    now = [100.0]
    harness = driver(lockstep_timeout_s=2.0)
    harness.module._clock = lambda: now[0]
    harness.module.done_0.fed_by("C/agent.done -> sumo.done_0")
    reading = answer(harness, NS)            # (step 0 went out before the link)
    assert reading.step == 1
    harness.feed("request_0", PhaseRequest("C", 1, NS))
    harness.step()
    assert harness.last("reading_0").step == 1          # answered, not done with yet
    harness.feed("done_0", 0.0)                          # a step gone by
    assert harness.last("reading_0").step == 1
    harness.feed("done_0", reading.time)
    reading = harness.last("reading_0")
    assert reading.step == 2 and harness.state["late"] == 0
    harness.feed("done_0", reading.time)                 # done first, then the request
    assert harness.last("reading_0").step == 2
    reading = answer(harness, NS)
    assert reading.step == 3
    harness.feed("request_0", PhaseRequest("C", 3, NS))  # never said done: late
    now[0] += 2.5
    harness.step()
    assert harness.last("reading_0").step == 4
    assert harness.state["late"] == 1 and harness.state["late_by_junction"] == {"C": 1}
    harness.module.done_0.unfed_by("C/agent.done -> sumo.done_0")
    harness.feed("request_0", PhaseRequest("C", 4, NS))
    harness.step()                                       # unlinked: not waited for
    assert harness.last("reading_0").step == 5


def test_requests_it_cannot_apply_are_counted_and_said(driver) -> None:
    harness = driver()
    harness.feed("request_0", PhaseRequest("B1", 0, NS))
    assert "request_0 is junction 'C'" in harness.state["last_error"]
    harness.feed("request_0", PhaseRequest("C", 0, 5))
    assert "no green phase 5" in harness.state["last_error"]
    assert harness.last("reading_0").step == 1      # (its answer, refused: see below)
    harness.feed("request_0", PhaseRequest("C", 7, NS))
    assert "step 7, which has not begun" in harness.state["last_error"]
    assert harness.state["rejected"] == 3 and harness.last("reading_0").step == 1


def test_a_junction_answering_with_a_green_it_lacks_is_refused_and_not_waited_for(
        driver) -> None:
    """The answer was refused and the step waited out the lock-step timeout for another
    that never came (a controller answers each reading once): 2 s a step, each counted
    late as well as rejected. Now the step goes on at once, the green it asked before
    standing."""
    now = [100.0]
    harness = driver(lockstep_timeout_s=2.0)
    harness.module._clock = lambda: now[0]
    answer(harness, EW)
    for _ in range(3):
        reading = harness.last("reading_0")
        harness.feed("request_0", PhaseRequest("C", reading.step, 2))
        assert harness.last("reading_0").step == reading.step + 1     # no wait
    state = harness.state
    assert state["rejected"] == 3 and state["late"] == 0
    assert "C: no green phase 2: this junction has 2 (0..1)" in state["last_error"]
    assert harness.module._heads["C"].requested == EW                 # it stands


def test_sumo_failing_mid_run_ends_the_run_as_failed_saying_why(driver) -> None:
    """Before, the error came back at every request and the run stayed ``running``: a
    scenario waiting for its figures waited out its timeout."""
    harness = driver()
    for _ in range(5):
        answer(harness, NS)

    def broken(steps: int) -> None:
        raise RuntimeError("connection closed by SUMO")
    harness.module._simulation.advance = broken
    with pytest.raises(RuntimeError, match="connection closed"):
        answer(harness, NS)
    state = harness.state
    assert state["status"] == "failed" and state["result"] == {}
    assert state["last_error"] == (f"{CROSS}: SUMO failed at 5 of 600 simulated s: "
                                   "RuntimeError: connection closed by SUMO")
    answer(harness, EW)                        # taken in silence: the run is over
    assert harness.last("reading_0").step == 5
    again = driver()                           # libsumo's one simulation is free again
    assert again.state["status"] == "running"


def test_at_the_end_the_run_s_figures_count_every_vehicle(driver) -> None:
    harness = driver(duration_s=240.0)
    while harness.state["status"] == "running":
        answer(harness, (harness.last("reading_0").step // 30) % 2)
    result = harness.state["result"]
    assert harness.written["summary"] == [result] and harness.state["status"] == "finished"
    assert result["vehicles"] == (result["finished"] + result["unfinished"]
                                  + result["never_entered"])
    assert result["vehicles"] >= 20 and result["finished"] >= 10
    assert result["mean_delay_s"] >= result["mean_time_loss_s"] > 0
    assert result["teleports"] == 0 and result["mean_halting"] > 0
    assert [w[0] for w in result["delay_by_window"]] == [60.0, 120.0, 180.0, 240.0]
    assert sum(w[2] for w in result["delay_by_window"]) == result["vehicles"]
    # per period of the demand (cross.toml: four of a quarter each), every vehicle once
    periods = result["delay_by_period"]
    assert [(p["period"], p["begin_s"], p["end_s"]) for p in periods] == [
        ("east-west heavy", 0.0, 60.0), ("north-south heavy", 60.0, 120.0),
        ("balanced", 120.0, 180.0), ("surge", 180.0, 240.0)]
    assert sum(p["vehicles"] for p in periods) == result["vehicles"]
    assert sum(p["mean_delay_s"] * p["vehicles"] for p in periods) == pytest.approx(
        result["mean_delay_s"] * result["vehicles"])


def test_sumo_s_own_programs_run_free_for_the_baselines(driver) -> None:
    harness = driver(own_programs=True, signals="actuated", duration_s=120.0)
    eventually(lambda: harness.step() or harness.state["status"] == "finished",
               timeout=20, what="the free run to end")
    assert harness.state["result"]["signals"] == "actuated"
    assert harness.state["result"]["own_programs"] is True
    assert len(harness.written["reading_0"]) == 120     # readings each step, for measuring


def test_re_pointed_while_it_runs_it_ends_one_simulation_and_starts_the_other(driver) -> None:
    harness = driver()
    for _ in range(20):
        answer(harness, NS)
    harness.module.set_state({"resource": RING})
    assert harness.state["result"]["resource"] == CROSS        # the crossing's figures kept
    assert harness.state["result"]["end_s"] == 20.0
    junctions = harness.state["junctions"]
    assert junctions == sorted(["N1", "N2", "E", "S2", "S1", "W"])
    assert harness.state["status"] == "running" and harness.state["step_count"] == 0
    firsts = [harness.last(f"reading_{slot}") for slot in range(6)]
    assert [r.junction for r in firsts] == junctions and all(r.step == 0 for r in firsts)
    for slot, junction in enumerate(junctions):                 # every junction answers:
        harness.feed(f"request_{slot}", PhaseRequest(junction, 0, 0))
    assert harness.last("reading_0").step == 1                  # then the ring moves on


@pytest.mark.parametrize(("bad", "named"), [
    ({"resource": str(NETWORKS / "nowhere.toml")}, "no network description at "),
    ({"demand_scale": {"rush": 2.0}}, "no period rush to scale; its periods are"),
    ({"demand_scale": 2.0}, "a demand scale is a table of period name (or *) to factor"),
    ({"signals": "actuatd", "seed": 2}, "signals must be one of static, actuated, "),
    ({"resource": RING, "demand_scale": {"rush": 2.0}}, "ring.toml: no period rush to"),
])
def test_a_new_simulation_that_cannot_start_is_refused_by_name_and_the_run_goes_on(
        driver, bad, named) -> None:
    """A mistyped resource (or demand scale, or signals) set while it ran ended the
    running simulation, then failed: the driver was left failed, its run gone."""
    harness = driver()
    for _ in range(5):
        answer(harness, NS)
    with pytest.raises(ValueError, match=re.escape(named)) as refused:
        harness.module.set_state(bad)
    assert "nothing was set: the simulation it has goes on" in str(refused.value)
    state = harness.state
    assert (state["status"], state["step_count"], state["run"]) == ("running", 5, 1)
    assert (state["resource"], state["demand_scale"], state["signals"], state["seed"]) == (
        CROSS, {}, "static", 1)
    assert state["result"] == {} and state["last_error"] == ""
    assert answer(harness, EW).step == 6                    # and on it goes


def test_answers_to_a_re_pointed_simulation_are_not_taken_for_the_new_one(driver) -> None:
    """A controller's answer to the last reading of the simulation the driver left
    reached it in the new one: counted in the new run's rejected ("a request for step
    20, which has not begun (now 0)"), which no request of its own had made."""
    from agents.traffic.fixed_time import FixedTime

    harness = driver()
    controller = ModuleHarness(FixedTime)
    for _ in range(20):
        controller.feed("reading", harness.last("reading_0"))
        harness.feed("request_0", controller.last("request"))
    controller.feed("reading", harness.last("reading_0"))   # answered, not yet delivered
    harness.module.set_state({"seed": 2})                   # re-pointed meanwhile
    harness.feed("request_0", controller.last("request"))
    state = harness.state
    assert state["step_count"] == 0 and state["rejected"] == 0 and state["last_error"] == ""
    assert harness.state["result"]["seed"] == 1 and harness.state["result"]["end_s"] == 20.0
    for _ in range(10):                                     # the new one's go on as ever
        controller.feed("reading", harness.last("reading_0"))
        harness.feed("request_0", controller.last("request"))
    assert harness.state["step_count"] == 10 and harness.state["rejected"] == 0
    assert harness.state["late"] == 0 and harness.last("reading_0").run == 2


def test_a_stream_without_a_route_is_refused_before_the_run(driver, tmp_path: Path) -> None:
    """A stream with no route, due only in the last period, used to crash SUMO three
    quarters into the run; the driver then failed every step and never finished."""
    for suffix in (".nod.xml", ".edg.xml"):
        shutil.copy(NETWORKS / f"cross{suffix}", tmp_path / f"cross{suffix}")
    text = (NETWORKS / "cross.toml").read_text().replace(
        'from = "w_C", to = "C_e", group = "ew"', 'from = "C_e", to = "w_C", group = "late"')
    for rates in ("ew = 600, ns = 150", "ew = 150, ns = 600", "ew = 300, ns = 300"):
        text = text.replace(rates, rates + ", late = 0")
    (tmp_path / "late.toml").write_text(text.replace("ew = 550, ns = 550",
                                                     "ew = 550, ns = 550, late = 600"))
    with pytest.raises(ValueError, match="stream west_east: no route from edge C_e"):
        driver(resource=str(tmp_path / "late.toml"), own_programs=True)
    harness = driver(own_programs=True, duration_s=30.0)    # and SUMO is free for the next
    eventually(lambda: harness.step() or harness.state["status"] == "finished",
               timeout=20, what="the next run to end")


def test_its_demand_scale_changes_the_vehicles_and_re_points_it(driver) -> None:
    def vehicles(harness) -> int:
        while harness.state["status"] == "running":
            answer(harness, (harness.last("reading_0").step // 20) % 2)
        return harness.state["result"]["vehicles"]

    harness = driver(duration_s=240.0)
    plain = vehicles(harness)
    harness.module.set_state({"demand_scale": {"*": 3.0}})      # a new simulation
    assert harness.state["status"] == "running" and harness.state["step_count"] == 0
    tripled = vehicles(harness)
    assert harness.state["result"]["demand_scale"] == {"*": 3.0}
    assert 2.2 * plain < tripled < 3.8 * plain, (plain, tripled)    # Poisson, same seed


def _driver_and_signal(name: str, sumo: dict[str, Any], signal: dict[str, Any]) -> System:
    """A driver in its own worker (state ``sumo``) and one controller on its first slot."""
    system = System(name)
    system.add("sumo", TrafficDriver, state=sumo)
    system.add("signal", PhaseAlternator, state=signal)
    system.link("sumo.reading_0", "signal.reading")
    system.link("signal.request", "sumo.request_0")
    return system


def test_in_its_own_worker_it_runs_in_lockstep_with_a_controller(cache: Path) -> None:
    system = _driver_and_signal("traffic-lockstep", {
        "resource": CROSS, "cache_dir": str(cache), "duration_s": 300.0}, {"hold": 20})
    with system.launch() as run:
        result = eventually(lambda: run.state("sumo")["result"], timeout=60,
                            what="the 300 s simulation to end")
        state = run.state("sumo")
    assert result["end_s"] == 300.0 and result["vehicles"] > 30
    assert state["late"] == 0 and state["rejected"] == 0


def test_launched_on_a_network_with_junctions_no_controller_answers_it_fails_its_setup(
        cache: Path) -> None:
    system = _driver_and_signal("traffic-too-few",
                                {"resource": RING, "cache_dir": str(cache)}, {})
    with pytest.raises(RuntimeFailure, match=re.escape(
            "ring.toml: no controller answers 5 of its 6 signalized junctions: N1 (request_1)")):
        system.launch().close()


def test_re_pointed_at_a_network_with_junctions_no_controller_answers_it_refuses(
        cache: Path) -> None:
    """A running system's driver re-pointed at a network with more signalized junctions
    than it has controllers waited out lockstep_timeout_s at every step, for the
    junctions whose slots nothing answers."""
    system = _driver_and_signal("traffic-re-pointed", {
        "resource": CROSS, "cache_dir": str(cache), "duration_s": 36000.0}, {"hold": 20})
    with system.launch() as run:
        eventually(lambda: run.state("sumo")["step_count"] > 10, timeout=30,
                   what="the crossing's run to go")
        with pytest.raises(Exception, match=re.escape(
                "ring.toml: no controller answers 5 of its 6 signalized junctions: N1 "
                "(request_1), N2 (request_2), S1 (request_3), S2 (request_4), W "
                "(request_5); no link feeds their slots' requests")):
            run.set_state("sumo", {"resource": RING})
        state = run.state("sumo")
        assert (state["resource"], state["status"], state["run"]) == (CROSS, "running", 1)
        assert state["junctions"] == ["C"] and state["result"] == {}
        steps = state["step_count"]
        eventually(lambda: run.state("sumo")["step_count"] > steps + 100, timeout=30,
                   what="the crossing's run to go on")
        assert run.state("sumo")["late"] == 0
        run.set_state("sumo", {"resource": RING, "own_programs": True})   # SUMO's programs:
        eventually(lambda: run.state("sumo")["junctions"] == sorted(      # nothing to answer
            ["N1", "N2", "E", "S2", "S1", "W"]), timeout=30, what="the ring to start")
        assert run.state("sumo")["result"]["resource"] == CROSS


def test_a_junction_whose_controller_was_removed_is_named_at_the_next_simulation(
        cache: Path) -> None:
    """A controller removed from a running system leaves its junction's slot unfed: the
    next simulation (a new demand scale) is refused, naming that junction. The check
    read the input's ``source``, which its unlink kept, so it took the slot for fed, and
    every step would have waited lockstep_timeout_s for a controller that is gone."""
    system = System("traffic-removed")
    system.add("sumo", TrafficDriver, state={"resource": RING, "cache_dir": str(cache),
                                             "duration_s": 36000.0})
    for slot in range(6):
        system.add(f"signal_{slot}", PhaseAlternator, state={"hold": 20})
        system.link(f"sumo.reading_{slot}", f"signal_{slot}.reading")
        system.link(f"signal_{slot}.request", f"sumo.request_{slot}")
    with system.launch() as run:
        eventually(lambda: run.state("sumo")["step_count"] > 10, timeout=60,
                   what="the ring's run to go")
        run.remove("signal_5")
        with pytest.raises(Exception, match=re.escape(
                "ring.toml: no controller answers 1 of its 6 signalized junctions: W "
                "(request_5); no link feeds their slots' requests")):
            run.set_state("sumo", {"demand_scale": {"*": 2.0}})
        assert run.state("sumo")["status"] == "running"
