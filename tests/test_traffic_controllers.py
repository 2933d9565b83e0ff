"""The junction controllers, each on its own: against synthetic readings of a
two-phase crossing (what it asks for, when), then against the driver on the
crossing in SUMO, and swapped for one another mid-phase."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from traffic_legality import illegal_steps

from agents.traffic.fixed_time import FixedTime
from agents.traffic.gap_out import GapOut
from agents.traffic.learning import QLearning, state_key
from agents.traffic.longest_queue import LongestQueueFirst
from agents.traffic.max_pressure import MaxPressure
from agents.traffic.messages import JunctionLayout, JunctionReading, NeighbourQueues
from agents.traffic.time_loss import TimeLoss
from pb3a.testing import ModuleHarness

# north-south (phase 0) and east-west (phase 1), one lane each way
LAYOUT = JunctionLayout(
    "J", links=(("n_in", "s_out"), ("s_in", "n_out"), ("e_in", "w_out"), ("w_in", "e_out")),
    greens=("GGrr", "rrGG"), lanes_in=("n_in", "s_in", "e_in", "w_in"),
    lanes_out=("s_out", "n_out", "w_out", "e_out"))
NS, EW = 0, 1
LANES = {"ns": ("n_in", "s_in"), "ew": ("e_in", "w_in")}


def reading(green: int = NS, elapsed: float = 0.0, *, step: int = 0, stage: str = "green",
            target: int | None = None, queues: dict[str, int] | None = None,
            vehicles: dict[str, int] | None = None, approaching: dict[str, int] | None = None,
            outgoing: dict[str, int] | None = None,
            arriving_in: dict[str, float] | None = None,
            delayed: dict[str, int] | None = None) -> JunctionReading:
    """A reading of the crossing; counts per lane group (``ns``/``ew``) or per lane. A
    lane with vehicles ``approaching`` has its nearest due in 2 s unless ``arriving_in``
    says otherwise."""
    def per_lane(counts: dict[str, int] | None, lanes: tuple[str, ...]) -> dict[str, int]:
        out = dict.fromkeys(lanes, 0)
        for name, count in (counts or {}).items():
            for lane in LANES.get(name, (name,)):
                out[lane] = count
        return out

    queue = per_lane(queues, LAYOUT.lanes_in)
    coming = per_lane(approaching, LAYOUT.lanes_in)
    due = {lane: 2.0 for lane, count in coming.items() if count}
    for name, seconds in (arriving_in or {}).items():
        due |= dict.fromkeys(LANES.get(name, (name,)), seconds)
    return JunctionReading(
        "J", step, float(step), LAYOUT, green, green if target is None else target, stage,
        elapsed, LAYOUT.greens[green], queue, dict.fromkeys(queue, 0.0),
        dict.fromkeys(queue, 0), per_lane(outgoing, LAYOUT.lanes_out),
        per_lane(vehicles if vehicles is not None else queues, LAYOUT.lanes_in), coming, due,
        per_lane(delayed, LAYOUT.lanes_in))


def asks(cls: type, state: dict[str, Any] | None = None, **fields: Any) -> int:
    """The green ``cls`` asks for after one reading."""
    harness = ModuleHarness(cls, state=state)
    harness.feed("reading", reading(**fields))
    request = harness.last("request")
    assert (request.junction, request.step) == ("J", fields.get("step", 0))
    return request.green


@pytest.mark.parametrize("cls", [FixedTime, MaxPressure, LongestQueueFirst, GapOut, TimeLoss,
                                 QLearning])
def test_every_controller_lets_a_transition_finish(cls: type) -> None:
    # mid-yellow from north-south to east-west, with everybody waiting north-south
    assert asks(cls, green=NS, target=EW, stage="yellow", elapsed=1.0,
                queues={"ns": 9}) == EW


def test_fixed_time_holds_each_green_for_its_time_whatever_the_queues() -> None:
    assert asks(FixedTime, {"green_s": 20.0}, green=NS, elapsed=19.0, queues={"ew": 30}) == NS
    assert asks(FixedTime, {"green_s": 20.0}, green=NS, elapsed=20.0, queues={"ns": 30}) == EW
    assert asks(FixedTime, {"green_s": 20.0}, green=EW, elapsed=25.0) == NS


def test_max_pressure_weighs_the_queues_against_what_stands_downstream() -> None:
    assert asks(MaxPressure, green=NS, elapsed=4.0, queues={"ew": 8}) == NS     # holding
    assert asks(MaxPressure, green=NS, elapsed=10.0, queues={"ns": 3, "ew": 8}) == EW
    # east-west's exits are full: its pressure is lower though its queue is longer
    assert asks(MaxPressure, green=NS, elapsed=10.0, queues={"ns": 3, "ew": 8},
                outgoing={"w_out": 12, "e_out": 12}) == NS


def test_max_pressure_takes_the_downstream_queue_from_its_neighbour() -> None:
    harness = ModuleHarness(MaxPressure)
    busy = reading(NS, 10.0, queues={"ns": 3, "ew": 8}, outgoing={"w_out": 12, "e_out": 12})
    harness.feed("reading", busy)
    assert harness.last("request").green == NS          # the driver's counts: all on them
    # the neighbours say those cars are moving: none halts on its incoming lanes
    harness.feed("neighbour_1", NeighbourQueues("K", 10.0, {"w_out": 0, "e_out": 0}))
    harness.feed("reading", busy)
    assert harness.last("request").green == EW and harness.state["decisions"] == 2


def test_longest_queue_first_keeps_minimum_and_maximum_greens() -> None:
    state = {"min_green_s": 8.0, "max_green_s": 40.0, "switch_ratio": 2.0}
    assert asks(LongestQueueFirst, state, green=NS, elapsed=7.0, queues={"ew": 20}) == NS
    assert asks(LongestQueueFirst, state, green=NS, elapsed=8.0, queues={"ew": 20}) == EW
    # its own queue still long, the other not twice as long: hold, until the maximum
    assert asks(LongestQueueFirst, state, green=NS, elapsed=30.0,
                queues={"ns": 6, "ew": 9}) == NS
    assert asks(LongestQueueFirst, state, green=NS, elapsed=40.0,
                queues={"ns": 6, "ew": 2}) == EW
    assert asks(LongestQueueFirst, state, green=NS, elapsed=30.0) == NS   # nobody: stay


def test_gap_out_holds_while_vehicles_come_and_gives_way_when_they_stop() -> None:
    state = {"min_green_s": 5.0, "max_green_s": 40.0}
    assert asks(GapOut, state, green=NS, elapsed=12.0, vehicles={"ew": 5},
                approaching={"n_in": 1}) == NS
    assert asks(GapOut, state, green=NS, elapsed=12.0, vehicles={"ew": 5}) == EW   # a gap
    assert asks(GapOut, state, green=NS, elapsed=40.0, vehicles={"ew": 5},
                approaching={"ns": 3}) == EW                           # the maximum
    assert asks(GapOut, state, green=NS, elapsed=12.0) == NS           # nobody at red
    # a car braking for the red (not yet halting) counts as waiting there
    assert asks(GapOut, state, green=NS, elapsed=12.0, queues={},
                vehicles={"e_in": 1}) == EW
    # the passage time: a vehicle 3 s from its stop line holds the green at 4 s, not at 2
    for passage, asked in ((4.0, NS), (2.0, EW)):
        assert asks(GapOut, {**state, "passage_s": passage}, green=NS, elapsed=12.0,
                    vehicles={"ew": 5}, arriving_in={"s_in": 3.0}) == asked


def test_time_loss_holds_while_its_vehicles_lose_time_then_serves_the_most_delayed() -> None:
    state = {"min_green_s": 5.0, "max_green_s": 50.0}
    # a queue still starting up holds the green however long it has been shown ...
    assert asks(TimeLoss, state, green=NS, elapsed=35.0, delayed={"ns": 4, "ew": 6}) == NS
    # ... a stream at full speed does not (nobody on it delayed), unlike gap-out
    assert asks(TimeLoss, state, green=NS, elapsed=12.0, approaching={"ns": 3},
                delayed={"ew": 2}) == EW
    assert asks(TimeLoss, state, green=NS, elapsed=50.0, delayed={"ns": 4, "ew": 1}) == EW
    assert asks(TimeLoss, state, green=NS, elapsed=4.0, delayed={"ew": 9}) == NS    # minimum
    assert asks(TimeLoss, state, green=NS, elapsed=12.0, vehicles={"ew": 3}) == NS  # none lose
    assert asks(TimeLoss, {"max_green_s": 60.0}, green=EW, elapsed=20.0,
                delayed={"n_in": 1, "w_in": 2}) == EW


def test_q_learning_acts_on_its_table_which_is_its_state() -> None:
    seen = reading(NS, 12.0, vehicles={"ew": 5}, approaching={"n_in": 1})
    key = state_key(seen)
    hold = ModuleHarness(QLearning, state={"table": {key: [-1.0, -5.0]}, "learning": False})
    give_way = ModuleHarness(QLearning, state={"table": {key: [-5.0, -1.0]},
                                               "learning": False})
    for harness in (hold, give_way):
        harness.feed("reading", seen)
    assert (hold.last("request").green, give_way.last("request").green) == (NS, EW)
    assert give_way.state["table"] == {key: [-5.0, -1.0]}


def test_q_learning_learns_from_the_halting_that_follows_and_starts_as_gap_out() -> None:
    harness = ModuleHarness(QLearning, state={"table_file": "", "alpha": 0.5})
    assert harness.state["table"] == {}
    asked = []
    for second in range(12, 16):
        harness.feed("reading", reading(NS, float(second), step=second, queues={"ew": 4},
                                        approaching={"n_in": 1}))
        asked.append(harness.last("request").green)
    assert asked[:2] == [NS, NS]          # nothing to tell the actions apart: as GapOut
    table = harness.state["table"]
    assert harness.state["updates"] == 3 and len(table) >= 1
    assert all(values[0] < 0 for values in table.values())   # four halting: a cost


def test_q_learning_starts_from_the_trained_table(tmp_path: Path) -> None:
    shipped = ModuleHarness(QLearning)
    trained = json.loads(Path(shipped.state["table_file"]).read_text())
    assert shipped.state["table"] == trained["table"] and len(trained["table"]) > 50
    assert trained["how"]["command"].startswith("python -m agents.traffic.training")
    own = tmp_path / "table.json"
    own.write_text(json.dumps({"table": {"k": [1.0, 2.0]}}))
    assert ModuleHarness(QLearning, state={"table_file": str(own)}).state["table"] == {
        "k": [1.0, 2.0]}


@pytest.mark.parametrize(("cls", "wrong", "named"), [
    (FixedTime, {"green_s": -5.0}, "green_s must be a number of seconds, 1 or more"),
    (FixedTime, {"green_s": float("nan")}, "green_s must be"),
    (MaxPressure, {"hold_s": True}, "hold_s must be a number of seconds, 0 or more"),
    (LongestQueueFirst, {"max_green_s": 4.0}, "max_green_s (4.0) must be at least "
                                              "min_green_s (8.0)"),
    (GapOut, {"passage_s": -1.0, "switch_ratio": "2"}, "passage_s must be a number of "
                                                       "seconds, 0 or more, got -1.0; GapOut's "
                                                       "switch_ratio must be a number"),
    (TimeLoss, {"max_green_s": 0.5}, "max_green_s must be a number of seconds, 1 or more"),
    (QLearning, {"alpha": 1.5}, "alpha must be a number from 0 to 1, got 1.5"),
    # a table it could not act on raised at every reading (no request: the lock-step
    # waited out its timeout each step); a learning of "no" learnt
    (QLearning, {"table": {"0|0|0|0": [1.0]}}, "table['0|0|0|0'] must be [value of "
                                                "holding, value of giving way], two finite"),
    (QLearning, {"table": {"k": ["a", "b"]}}, "table['k'] must be [value of holding"),
    (QLearning, {"table": {"k": [float("nan"), 0.0]}}, "table['k'] must be"),
    (QLearning, {"table": []}, "table must be a table of state key = [value of holding"),
    (QLearning, {"learning": "no"}, "learning must be true or false, got 'no'"),
    (QLearning, {"seed": [1]}, "seed must be a whole number, 0 or more, got [1]"),
    (QLearning, {"table_file": "/nowhere/table.json"},
     "table_file /nowhere/table.json: it holds no table (FileNotFoundError"),
])
def test_a_controller_refuses_a_setting_out_of_range_by_name(cls: type, wrong: dict[str, Any],
                                                             named: str) -> None:
    """At setup (from the configuration) and when set while it runs; nothing is set.
    Before, a green of -5 s ran, the signal head quietly stretching it."""
    with pytest.raises(ValueError, match="^" + cls.__name__) as refused:
        ModuleHarness(cls, state=wrong)
    assert named in str(refused.value)
    harness = ModuleHarness(cls)
    before = harness.state
    with pytest.raises(ValueError, match="^" + cls.__name__) as refused:
        harness.module.set_state(wrong)
    assert named in str(refused.value)
    assert harness.state == before


def test_q_learning_goes_by_a_table_file_given_once_it_is_set_up(tmp_path: Path) -> None:
    """A performance agent gives a controller its state after the swap's setup, and a
    table_file read only at setup was not read then: the learner swapped in with a
    table file of its own went by the trained table (so did one set while it ran),
    though its state named the file. A file that holds no table is refused by name."""
    own = tmp_path / "table.json"
    own.write_text(json.dumps({"table": {"k": [1.0, 2.0]}}))
    learner = ModuleHarness(QLearning)                  # set up on the trained table
    assert len(learner.state["table"]) > 50
    learner.module.set_state({"min_green_s": 5.0, "table_file": str(own)})
    assert learner.state["table"] == {"k": [1.0, 2.0]}
    learner.module.set_state({"table_file": str(own), "table": {"j": [0.0, 1.0]}})
    assert learner.state["table"] == {"j": [0.0, 1.0]}  # a table given goes first
    own.write_text("{not json")
    with pytest.raises(ValueError, match=f"QLearning: table_file {own}: it holds no table "
                                         r"\(JSONDecodeError"):
        learner.module.set_state({"table_file": str(own)})
    assert learner.state["table"] == {"j": [0.0, 1.0]}      # nothing set


@pytest.mark.parametrize("failed", [
    {"vehicles": {"ns": -1}}, {"vehicles": {"ns": 300}}, {"approaching": {"ew": -2}},
    {"delayed": {"ns": 500}}, {"outgoing": {"ew": -1}},
    {"approaching": {"ns": 1}, "arriving_in": {"ns": -3.0}},
    {"approaching": {"ns": 1}, "arriving_in": {"ns": float("nan")}}])
def test_the_detectors_gap_out_and_time_loss_decide_by_are_judged_too(failed) -> None:
    """Only the queues, arrivals and waiting times were judged: a failed detector of the
    vehicles due or delayed, what gap-out and time loss decide by, went unseen, and no
    fallback came."""
    from agents.traffic.sensors import JunctionSensors

    sensors = ModuleHarness(JunctionSensors)
    sensors.feed("reading", reading(queues={"ns": 3}, approaching={"ew": 2},
                                    delayed={"ns": 3}, outgoing={"ew": 4}))
    sensors.feed("reading", reading(queues={"ns": 3}, **failed))
    assert [m.plausible for m in sensors.written["measures"]] == [True, False]
    assert sensors.state["implausible"] == 1


def test_the_sensors_judge_plausibility_by_a_lane_capacity_they_check() -> None:
    """A lane_capacity below 1 (or not a number) was taken: every reading was judged a
    failed detector (or raised), and each junction's agent ran fixed time for good,
    blaming its detectors."""
    from agents.traffic.sensors import JunctionSensors

    sensors = ModuleHarness(JunctionSensors, state={"lane_capacity": 8})
    sensors.feed("reading", reading(queues={"ns": 8}))
    sensors.feed("reading", reading(queues={"ns": 9}))
    assert [m.plausible for m in sensors.written["measures"]] == [True, False]
    assert sensors.written["measures"][0].queue == 16
    for bad in (0, -1, 2.5, float("nan"), "200", True):
        with pytest.raises(ValueError, match="JunctionSensors's lane_capacity must be a "
                                             "whole number of vehicles, 1 or more"):
            ModuleHarness(JunctionSensors, state={"lane_capacity": bad})
        with pytest.raises(ValueError, match="lane_capacity must be"):
            sensors.module.set_state({"lane_capacity": bad})
        assert sensors.state["lane_capacity"] == 8


def test_q_learning_draws_its_explorations_from_a_seed_set_while_it_runs() -> None:
    def explorations(harness: ModuleHarness) -> list[int]:
        asked = []
        for second in range(6, 30):
            harness.feed("reading", reading(NS, float(second), step=second,
                                            vehicles={"ew": 3}, approaching={"n_in": 1}))
            asked.append(harness.last("request").green)
        return asked

    settings = {"table_file": "", "epsilon": 1.0, "learning": False}
    fresh = explorations(ModuleHarness(QLearning, state={**settings, "seed": 7}))
    reseeded = ModuleHarness(QLearning, state={**settings, "seed": 1})
    assert explorations(reseeded) != fresh           # (another seed, other draws)
    reseeded.module.set_state({"seed": 7})
    assert explorations(reseeded) == fresh           # before: seed 1's draws went on


# -- against the driver, on the crossing in SUMO --------------------------------------
NETWORKS = Path(__file__).resolve().parent.parent / "scenarios" / "traffic"


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("libsumo", reason="SUMO (the traffic extra) is not installed: "
                                          "pip install -e '.[traffic]'")
    return tmp_path_factory.mktemp("traffic-cache")


def test_training_learns_one_table_every_junction_shares(cache: Path) -> None:
    """Each junction's controller gets a copy of the state it is given: the table it was
    given stayed empty, and the training wrote an empty table (it ran all the same)."""
    from agents.traffic.training import train

    table, history = train(networks=("ring",), episodes=2, duration_s=300.0, cache=cache)
    assert 20 < history[0]["states"] < history[1]["states"] == len(table), history
    assert all(len(values) == 2 for values in table.values())


@pytest.mark.parametrize("count", ["0", "-3", "101", "two"])
def test_training_refuses_a_number_of_episodes_it_has_no_seeds_for(
        tmp_path: Path, capsys, count: str) -> None:
    """--episodes 0 wrote an empty table over the trained one; 101 trained 100 episodes
    (about seven minutes), then failed (IndexError) before writing anything."""
    from agents.traffic.training import main, train

    out = tmp_path / "table.json"
    with pytest.raises(SystemExit) as ended:
        main(["--episodes", count, "--out", str(out)])
    assert ended.value.code == 2 and not out.exists()
    assert ("give a whole number of episodes from 1 to 100 (one seed of its own each), "
            f"got {count!r}") in capsys.readouterr().err
    with pytest.raises(ValueError, match="episodes must be from 1 to 100"):
        train(episodes=101)


@pytest.mark.parametrize(("cls", "worst_delay_s"), [
    (FixedTime, 60.0), (MaxPressure, 40.0), (LongestQueueFirst, 40.0), (GapOut, 25.0),
    (TimeLoss, 30.0), (QLearning, 30.0)])
def test_each_controller_runs_the_crossing_through_the_driver(cache: Path, cls: type,
                                                              worst_delay_s: float) -> None:
    from agents.traffic.lockstep import run_in_process

    result, controllers = run_in_process(NETWORKS / "cross.toml", lambda _: (cls, {}),
                                         seed=3, duration_s=600.0, cache=cache)
    assert controllers["C"].state["decisions"] == 600           # one answer a step
    assert result["late"] == 0 and result["rejected"] == 0 and result["teleports"] == 0
    assert result["finished"] > 100 and 0 < result["mean_delay_s"] < worst_delay_s, result


@pytest.mark.timeout(60)
def test_a_network_without_signalized_junctions_runs_to_its_end_in_process(
        cache: Path, tmp_path: Path) -> None:
    """Its driver runs free, and nothing stepped it: run_in_process looped for good at
    full CPU (pb3a scenario traffic on such a network never ended)."""
    from agents.traffic.lockstep import run_in_process

    network = tmp_path / "plain.toml"
    network.write_text(
        '[build]\nnetgenerate = ["--grid", "--grid.number", "2", "--grid.attach-length", '
        '"100"]\n[demand.streams]\na = { from = "left0A0", to = "A0bottom0", group = "g" }'
        '\n[[demand.periods]]\nshare = 1.0\nrates = { g = 600 }\n')
    result, controllers = run_in_process(network, lambda _: (GapOut, {}), seed=1,
                                         duration_s=120.0, cache=cache)
    assert controllers == {} and result["end_s"] == 120.0 and result["vehicles"] > 5


def test_gap_out_beats_fixed_time_on_the_crossing(cache: Path) -> None:
    from agents.traffic.lockstep import run_in_process

    delays = {cls: run_in_process(NETWORKS / "cross.toml", lambda _, c=cls: (c, {}), seed=4,
                                  duration_s=600.0, cache=cache)[0]["mean_delay_s"]
              for cls in (FixedTime, GapOut)}
    assert delays[GapOut] < 0.7 * delays[FixedTime], delays


def test_a_controller_swapped_mid_phase_carries_on_from_the_phase_shown(cache: Path) -> None:
    """Fixed time on the crossing; mid-green of east-west, swapped for max-pressure
    (a fresh instance, as ``run.swap`` makes): it asks for the green in progress,
    does not start over from phase 0, and the lights stay legal throughout."""
    from agents.traffic.driver import TrafficDriver

    driver = ModuleHarness(TrafficDriver, state={
        "resource": str(NETWORKS / "cross.toml"), "cache_dir": str(cache),
        "duration_s": 300.0, "seed": 2})
    try:
        controller = ModuleHarness(FixedTime, state={"green_s": 20.0})
        shown = []

        def one_step() -> JunctionReading:
            controller.feed("reading", driver.last("reading_0"))
            driver.feed("request_0", controller.last("request"))
            shown.append(driver.last("reading_0").signal)
            return driver.last("reading_0")

        now = one_step()
        while not (now.green == EW and now.stage == "green" and now.elapsed >= 3):
            now = one_step()
        controller = ModuleHarness(MaxPressure, state={"hold_s": 10.0})   # swapped in
        controller.feed("reading", now)
        assert controller.last("request").green == EW                     # carries on
        driver.feed("request_0", controller.last("request"))
        for _ in range(200):
            one_step()
        greens = driver.last("reading_0").layout.greens
        assert illegal_steps(shown, greens, yellow_s=3) == []
        assert {r.green for r in driver.written["reading_0"][-200:]} == {NS, EW}
        assert driver.state["rejected"] == 0
    finally:
        driver.close()
