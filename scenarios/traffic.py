"""Traffic control on SUMO: every signalized junction run by an intersection macro
whose performance agent swaps its controller as traffic changes, against each
controller alone and against SUMO's own actuated programs.

``scenarios/traffic.toml`` is the system: the ``TrafficDriver`` (SUMO, in lock-step)
and, per junction, the ``junction`` macro: its sensors, its controller and its
``PerformanceAgent``, with each junction's queues sent to its neighbours upstream.
The scenario fills in the network, the seed and the length of the run, one
instance per signalized junction and the links between neighbours.

On the same network, demand and seed it runs:

- the swapping agents: that system, launched (one process for SUMO and one for the
  junctions' modules);
- each controller of the agents' ``controllers`` alone, with the parameters the
  file gives it, at every junction (in one process, ``run_in_process``: the same
  driver and classes in the same lock-step, without the agents);
- SUMO's ``actuated`` and ``delay_based`` programs (the driver's ``own_programs``),
  as outside baselines.

Figures per run (the driver's): mean delay per vehicle (tripinfo ``timeLoss +
departDelay`` over every vehicle, counting those still in the network or never let
in), mean vehicles halting at the signals, throughput, teleports, swaps made, the
delay over time, and the delay per period of the demand with the best controller in
each. Goals: the swapping agents have less mean delay than every controller alone,
than SUMO's ``delay_based`` and than max-pressure.

Run it: ``pb3a scenario traffic [--quick] [--network ring|grid] [--seed N] [--out DIR]
[--scale [PERIOD=]FACTOR]`` (or ``python -m scenarios.traffic``); ``--network`` also
takes the path of another network description, ``--scale`` makes the demand heavier
or lighter, in one period or all. It prints the report as JSON and writes ``traffic_NETWORK.json``
and ``traffic_NETWORK.png`` to DIR.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from agents.traffic import lockstep
from agents.traffic.driver import MAX_JUNCTIONS
from agents.traffic.lockstep import run_in_process
from agents.traffic.messages import JunctionLayout
from agents.traffic.networks import BuildFailed, Network, SumoMissing
from agents.traffic.simulation import check_installed
from pb3a import System
from pb3a.cli.log_output import show_logs
from pb3a.config.checks import NAME
from pb3a.loading.references import resolve_class
from scenarios import SUMO_SEED_MAX, output_directory, summary, sumo_seed

CONFIG = Path(__file__).with_name("traffic.toml")
NETWORKS = Path(__file__).with_name("traffic")
DURATION_S = {"quick": 900.0, "full": 3600.0}
BASELINES = ("actuated", "delay_based")
RUN_TIMEOUT_S = {"quick": 120.0, "full": 600.0}    # wall seconds for the agents' run
POLL_S = 0.2
SETTLE_S = 10.0                 # wall seconds for the swaps in flight at the end to be
                                # recorded by their agents
# what the scenario fills in of the driver's state, whatever the file says
FILLED_IN = ("resource", "seed", "duration_s", "cache_dir", "demand_scale", "signals",
             "own_programs")
# (late and rejected: answers in the lock-step that came after its timeout, and requests
# the driver could not apply; a run with either no longer depends on its seed alone)
FIGURES = ("mean_delay_s", "mean_halting", "throughput", "teleports", "vehicles",
           "mean_time_loss_s", "mean_depart_delay_s", "late", "rejected")


def network_path(network: str) -> Path:
    """A bundled network by name (``ring``, ``grid``), or a description's path."""
    path = Path(network)
    if path.suffix == ".toml":
        return path
    bundled = NETWORKS / f"{network}.toml"
    if not bundled.is_file():
        names = sorted(p.stem for p in NETWORKS.glob("*.toml"))
        raise ValueError(f"no network {network!r}: the bundled networks are "
                         f"{', '.join(names)} (or give the path of a .toml description)")
    return bundled


def check_network(network: Network, cache: Path | None = None) -> None:
    """``ValueError`` saying what keeps ``network`` from the scenario, found before
    anything runs: a stream its built network cannot carry, no signalized junction (no
    controller to compare), more than the driver has slots for, a junction whose id
    cannot name its modules (the system's configuration refused it after every run
    alone). (A failed build raises ``BuildFailed``, no SUMO ``SumoMissing``.)"""
    net_file = network.build(cache=cache)
    network.check_streams(net_file)
    junctions = network.signalized(net_file)
    if not junctions:
        raise ValueError(f"{network.path}: the built network has no signalized junction, "
                         "so there is nothing for the controllers to run: mark the junctions "
                         "to signalize (type=\"traffic_light\" in the nodes for netconvert, "
                         "--tls.set or --default-junction-type traffic_light for netgenerate)")
    if len(junctions) > MAX_JUNCTIONS:
        raise ValueError(f"{network.path}: the built network has {len(junctions)} signalized "
                         f"junctions; the traffic driver has slots for {MAX_JUNCTIONS}")
    taken = [name for name, module in tomllib.loads(CONFIG.read_text())["modules"].items()
             if module.get("macro") != "junction"]
    unnamable = [junction for junction in junctions
                 if not NAME.match(junction) or junction in taken]
    if unnamable:
        raise ValueError(f"{network.path}: the scenario names each signalized junction's "
                         f"modules after it, and {', '.join(map(repr, unnamable))} cannot "
                         "name them: a module's name has only letters, digits, '_' and '-', "
                         f"and is not that of another module of {CONFIG.name} "
                         f"({', '.join(taken)}); rename the junction in the network's nodes")


def layouts(resource: Path, cache: Path | None = None) -> dict[str, JunctionLayout]:
    """The network's signalized junctions, in the driver's slot order."""
    simulation = lockstep.driver(resource, cache, duration_s=10.0)
    try:
        return {junction: simulation.last(f"reading_{slot}").layout
                for slot, junction in enumerate(simulation.state["junctions"])}
    finally:
        simulation.close()


def neighbours(found: dict[str, JunctionLayout]) -> dict[str, list[str]]:
    """Per junction, the junctions its outgoing lanes lead into."""
    return {junction: [other for other, theirs in found.items() if other != junction
                       and set(layout.lanes_out) & set(theirs.lanes_in)]
            for junction, layout in found.items()}


def configuration(resource: Path, seed: int, duration_s: float,
                  found: dict[str, JunctionLayout], cache: Path | None = None,
                  agent_state: dict[str, Any] | None = None,
                  demand_scale: Mapping[str, float] | None = None) -> System:
    """``traffic.toml`` with this run's network, seed, length and demand scale, one
    ``junction`` instance per signalized junction (the file's own, if it has one by
    the junction's name; its agent's state over ``agent_state``), and the links
    between neighbours."""
    data = tomllib.loads(CONFIG.read_text())
    macro = data["macros"]["junction"]["modules"]
    agent = macro["agent"].get("state", {})
    _check_running(macro["controller"], agent)
    data["modules"]["sumo"].setdefault("state", {}).update(
        resource=str(resource), seed=seed, duration_s=duration_s,
        cache_dir=str(cache) if cache else "", demand_scale=dict(demand_scale or {}))
    links = data.setdefault("links", [])
    for slot, junction in enumerate(found):
        # an instance the file has for this junction keeps its own state
        instance = data["modules"].setdefault(junction, {"macro": "junction"})
        state = instance.setdefault("state", {})
        state["agent"] = {**(agent_state or {}), **state.get("agent", {}),
                          "controller": f"{junction}/controller"}
        if state.get("controller"):
            # the junction's own settings of its controller are given again when its
            # agent swaps back to it (they held only until the first swap)
            chosen = {**agent.get("controllers", {}), **state["agent"].get("controllers", {})}
            running = state["agent"].get("running", agent.get("running"))
            spec = chosen[running]
            state["agent"]["controllers"] = {**chosen, running: {
                **spec, "state": {**spec.get("state", {}), **state["controller"]}}}
        links += [{"from": f"sumo.reading_{slot}", "to": f"{junction}.reading"},
                  {"from": f"sumo.reading_{slot}", "to": f"{junction}.control"},
                  {"from": f"{junction}.request", "to": f"sumo.request_{slot}"},
                  {"from": f"{junction}.done", "to": f"sumo.done_{slot}"},
                  {"from": "sumo.clock", "to": f"{junction}.clock"}]
    for junction, downstream in neighbours(found).items():
        for slot, other in enumerate(downstream[:4]):
            links.append({"from": f"{other}.queues", "to": f"{junction}.neighbour_{slot}"})
    return System.from_dict(data, source=str(CONFIG))


def _check_running(controller: dict[str, Any], agent: dict[str, Any]) -> None:
    """ValueError unless the junction's controller is the agent's ``running`` one, class
    and state (the agents' run is then gap-out's alone until a swap)."""
    running = agent.get("running", "")
    spec = agent.get("controllers", {}).get(running)
    if spec is None:
        raise ValueError(f"{CONFIG}: the agent's running = {running!r} is none of its "
                         f"controllers ({', '.join(agent.get('controllers', {}))})")
    if (spec["class"], spec.get("state", {})) != (controller["class"],
                                                   controller.get("state", {})):
        raise ValueError(f"{CONFIG}: the junction's controller ({controller['class']}, "
                         f"{controller.get('state', {})}) is not the agent's running one, "
                         f"{running} ({spec['class']}, {spec.get('state', {})}): make them "
                         "the same")


def controllers() -> dict[str, dict[str, Any]]:
    """The controllers the agents choose among (name -> class and state), from the file."""
    data = tomllib.loads(CONFIG.read_text())
    return data["macros"]["junction"]["modules"]["agent"]["state"]["controllers"]


def run_agents(resource: Path, seed: int, duration_s: float, found: dict[str, JunctionLayout],
               timeout_s: float, cache: Path | None = None,
               demand_scale: Mapping[str, float] | None = None) -> dict[str, Any]:
    """The swapping agents' run: its figures, its swaps and the system's swap events.
    ``swaps`` has one record per swap the system made (``swap_events``): an agent's, or,
    for a swap its agent had not recorded when the system stopped, one made from the
    system's event (``"unrecorded": true``)."""
    system = configuration(resource, seed, duration_s, found, cache,
                           demand_scale=demand_scale)
    with system.launch() as running:
        started = time.monotonic()
        deadline = started + timeout_s
        while not (driver := running.state("sumo"))["result"]:
            if driver["status"] == "failed":
                raise RuntimeError(f"the agents' run of {resource.name} failed: "
                                   f"{driver['last_error']}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"the agents' run of {resource.name} did not end in "
                                   f"{timeout_s:.0f} s (at {running.state('sumo')['time_s']:.0f} "
                                   f"of {duration_s:.0f} simulated s)")
            time.sleep(POLL_S)
        wall_s = time.monotonic() - started
        result = running.state("sumo")["result"]
        swaps = recorded_swaps(running, list(found), time.monotonic() + SETTLE_S)
    # stopped: every swap the system made is among its events now, also one cut short
    events = [e for e in running.events(since=0, timeout=0) if e.kind == "module_swapped"]
    swaps = with_unrecorded(swaps, events, result["end_s"])
    return {**result, "swaps": swaps, "swap_events": len(events), "wall_s": round(wall_s, 1)}


def recorded_swaps(running: Any, junctions: list[str], settle_by: float) -> list[dict[str, Any]]:
    """The junctions' agents' swap records, in time order, once they record every swap
    the system has made: an agent records a swap after the system has made it and the
    new controller has its state, so one swapping as the run ends is waited for, until
    ``settle_by`` (``time.monotonic()``)."""
    while True:
        swaps = sorted((swap for junction in junctions
                        for swap in running.state(f"{junction}/agent")["swaps"]),
                       key=lambda swap: swap["time"])
        made = sum(e.kind == "module_swapped" for e in running.events(since=0, timeout=0))
        if len(swaps) >= made or time.monotonic() >= settle_by:
            return swaps
        time.sleep(POLL_S)


def with_unrecorded(swaps: list[dict[str, Any]], events: list[Any],
                    end_s: float) -> list[dict[str, Any]]:
    """``swaps`` and, per controller the system swapped more often than its agent's
    records say (a swap made as the system stopped, whose record was made too late to
    be read, or not at all), a record of each of its last swaps made from the system's
    event: at ``end_s``, ``from`` the controller recorded before (None: none was)."""
    names = {spec["class"]: name for name, spec in controllers().items()}
    added = []
    for controller in dict.fromkeys(e.subject for e in events):
        made = [e for e in events if e.subject == controller]
        recorded = [s for s in swaps if s["controller"] == controller]
        before = recorded[-1]["to"] if recorded else None
        for event in made[len(recorded):]:
            to = names.get(event.detail.get("cls", ""), event.detail.get("cls", ""))
            added.append({"time": end_s, "controller": controller, "from": before, "to": to,
                          "reason": "made by the system as the run ended; its agent's "
                                    "record was not read", "unrecorded": True})
            before = to
    return sorted([*swaps, *added], key=lambda swap: swap["time"])


def driver_settings() -> dict[str, Any]:
    """The driver's settings in the file (``[modules.sumo]``: its minimum green, control
    step, lock-step timeout), which every run takes, the agents' and those without;
    the scenario's own (network, seed, length, cache, demand scale) left out. The runs
    without agents took the driver's defaults, whatever the file said."""
    state = tomllib.loads(CONFIG.read_text())["modules"]["sumo"].get("state", {})
    return {key: value for key, value in state.items() if key not in FILLED_IN}


def run_alone(resource: Path, seed: int, duration_s: float, spec: dict[str, Any],
              cache: Path | None = None, demand_scale: Mapping[str, float] | None = None,
              ) -> dict[str, Any]:
    """One controller at every junction, no agents."""
    cls = resolve_class(spec["class"])
    result, _ = run_in_process(resource, lambda _junction: (cls, dict(spec.get("state", {}))),
                               seed=seed, duration_s=duration_s, cache=cache,
                               demand_scale=demand_scale, settings=driver_settings())
    return result


def run_sumo(resource: Path, seed: int, duration_s: float, signals: str,
             cache: Path | None = None, demand_scale: Mapping[str, float] | None = None,
             ) -> dict[str, Any]:
    """SUMO's own programs of type ``signals`` drive the lights."""
    simulation = lockstep.driver(resource, cache, **{
        **driver_settings(), "seed": seed, "duration_s": duration_s, "signals": signals,
        "own_programs": True, "demand_scale": dict(demand_scale or {})})
    try:
        while simulation.module.status == "running":
            simulation.step()
        return simulation.state["result"]
    finally:
        simulation.close()


def run(network: str = "ring", seed: int = 1, quick: bool = False,
        cache: Path | None = None, demand_scale: Mapping[str, float] | None = None,
        ) -> dict[str, Any]:
    """Every run on ``network`` with ``seed``, its demand scaled by ``demand_scale``
    (period name, or ``*``, to a factor); the report (``report``)."""
    resource = network_path(network)
    Network.load(resource).scaled(demand_scale or {})     # a bad scale named at once
    mode = "quick" if quick else "full"
    duration_s = DURATION_S[mode]
    found = layouts(resource, cache)
    runs: dict[str, dict[str, Any]] = {}
    for name, spec in controllers().items():
        runs[name] = run_alone(resource, seed, duration_s, spec, cache, demand_scale)
    for signals in BASELINES:
        runs[f"sumo_{signals}"] = run_sumo(resource, seed, duration_s, signals, cache,
                                           demand_scale)
    runs["agents"] = run_agents(resource, seed, duration_s, found, RUN_TIMEOUT_S[mode], cache,
                                demand_scale)
    return report(resource, seed, quick, runs)


def report(resource: Path, seed: int, quick: bool,
           runs: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The figures of every run, and whether the agents meet the goals."""
    table = {name: {key: _round(result[key]) for key in FIGURES}
             | {"swaps": len(result.get("swaps", []))} for name, result in runs.items()}
    agents = runs["agents"]["mean_delay_s"]
    own = [name for name in runs if name != "agents" and not name.startswith("sumo_")]
    goals = {f"less delay than {name} alone": agents < runs[name]["mean_delay_s"]
             for name in own}
    goals["less delay than SUMO's delay_based"] = agents < runs["sumo_delay_based"]["mean_delay_s"]
    goals["no teleports"] = runs["agents"]["teleports"] == 0
    return {"scenario": "traffic", "network": resource.stem, "seed": seed, "quick": quick,
            "demand_scale": runs["agents"].get("demand_scale", {}),
            "duration_s": runs["agents"]["end_s"], "runs": table,
            "best_alone": min(own, key=lambda n: runs[n]["mean_delay_s"]),
            "agents_wall_s": runs["agents"]["wall_s"],
            "swap_events": runs["agents"]["swap_events"],
            "swaps": runs["agents"]["swaps"], "goals": goals,
            "periods": periods(runs, own),
            "delay_over_time": {name: result["delay_by_window"] for name, result in runs.items()}}


def periods(runs: dict[str, dict[str, Any]], own: list[str]) -> list[dict[str, Any]]:
    """Per period of the demand: its span, each run's mean delay (s) of the vehicles
    that left in it, and the agents' controller with the least. Where the best differs
    from period to period, swapping has something to gain; where it does not, the
    agents can at best equal that controller."""
    found = []
    for index, period in enumerate(runs["agents"]["delay_by_period"]):
        delays = {name: _round(result["delay_by_period"][index]["mean_delay_s"])
                  for name, result in runs.items()}
        measured = [name for name in own if delays[name] is not None]
        found.append({"period": period["period"], "begin_s": period["begin_s"],
                      "end_s": period["end_s"], "mean_delay_s": delays,
                      "best_alone": min(measured, key=lambda n: delays[n]) if measured else None})
    return found


def _round(value: Any) -> Any:
    return round(value, 2) if isinstance(value, float) else value


def same_as_agents(delay_over_time: dict[str, list[Any]]) -> list[str]:
    """The runs whose delay over time is the agents' own, minute for minute (the agents
    kept that controller all along)."""
    agents = delay_over_time.get("agents")
    return [name for name, windows in delay_over_time.items()
            if name != "agents" and windows == agents]


def plot(figures: dict[str, Any], path: Path) -> None:
    """Mean delay of the vehicles that left in each minute, per run; swaps and
    the demand's periods marked."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(figsize=(11, 5))
    same = same_as_agents(figures["delay_over_time"])
    for name, windows in figures["delay_over_time"].items():
        # the agents' thick line under the others: a controller it ran all along (on
        # the ring, gap-out) vanished under it, drawn on top
        style = {"linewidth": 2.4, "color": "black", "zorder": 1.5} if name == "agents" \
            else {"linewidth": 1.0, "linestyle": "--" if name.startswith("sumo_") else "-"}
        delay = figures["runs"][name]["mean_delay_s"]
        label = f"{name}: {delay:.1f} s"
        if name == "agents" and same:
            label += f" (= {', '.join(same)}, drawn inside it)"
        axes.plot([w[0] for w in windows], [w[1] for w in windows], label=label, **style)
    for index, swap in enumerate(figures["swaps"]):
        axes.axvline(swap["time"], color="tab:red", alpha=0.25, linewidth=0.8,
                     label="a swap by an agent" if index == 0 else None)
    for period in figures["periods"]:              # the demand's periods, named on top
        if period["begin_s"] > 0:
            axes.axvline(period["begin_s"], color="grey", linestyle=":", linewidth=1.0)
        axes.text((period["begin_s"] + period["end_s"]) / 2, 1.0, period["period"],
                  transform=axes.get_xaxis_transform(), ha="center", va="bottom",
                  fontsize=8, color="dimgrey")
    axes.set_xlim(0, figures["duration_s"])
    axes.set_xlabel("simulated time (s)")
    axes.set_ylabel("mean delay of the vehicles that left in the minute (s)")
    scale = "".join(f", {period} x{factor:g}" for period, factor in
                    figures.get("demand_scale", {}).items())
    axes.set_title(f"{figures['network']}, seed {figures['seed']}{scale}: mean delay per "
                   f"vehicle over the run (legend); {len(figures['swaps'])} swaps",
                   fontsize=10, pad=16)
    axes.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def parse_scale(texts: list[str]) -> dict[str, float]:
    """``--scale`` values (``surge=2``, or ``1.5`` for every period) as the driver's
    ``demand_scale``."""
    scale: dict[str, float] = {}
    for text in texts:
        period, equals, factor = text.rpartition("=")
        try:
            if equals and not period:
                raise ValueError(text)
            value = float(factor)
        except ValueError:
            raise ValueError(f"--scale {text!r}: give PERIOD=FACTOR (surge=2) or a "
                             "FACTOR for every period (1.5)") from None
        if (period or "*") in scale:          # (the last was taken, silently)
            raise ValueError(f"--scale {text!r}: {period or 'every period'} is scaled "
                             "twice: give it once")
        scale[period or "*"] = value
    return scale


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pb3a scenario traffic",
                                     description=summary(__doc__))
    parser.add_argument("--quick", action="store_true",
                        help="15 simulated minutes (the demand's four periods shortened) "
                             "instead of an hour")
    parser.add_argument("--network", default="ring",
                        help="ring, grid, or the path of a network description (.toml)")
    parser.add_argument("--seed", type=sumo_seed, default=1,
                        help=f"0 to {SUMO_SEED_MAX} (default 1)")
    parser.add_argument("--out", default=".",
                        help="directory for the JSON and the PNG (default: this one)")
    parser.add_argument("--scale", action="append", default=[], metavar="[PERIOD=]FACTOR",
                        help="multiply the demand's rates: in one period (surge=2), or "
                             "in all (1.5); may be given for several periods")
    args = parser.parse_args(argv)
    try:
        resource = network_path(args.network)
        demand_scale = parse_scale(args.scale)
        network = Network.load(resource).scaled(demand_scale)
        check_installed()            # (libsumo missing was a traceback as the runs began)
        check_network(network)
    except (ValueError, BuildFailed, SumoMissing) as exc:
        print(f"traffic: {exc}", file=sys.stderr)
        return 2
    show_logs()
    try:
        out = output_directory(args.out)
    except ValueError as exc:
        print(f"traffic: {exc}", file=sys.stderr)
        return 2
    figures = run(str(resource), args.seed, args.quick, demand_scale=demand_scale)
    png = out / f"traffic_{figures['network']}.png"
    plot(figures, png)
    figures["plot"] = str(png)
    (out / f"traffic_{figures['network']}.json").write_text(json.dumps(figures, indent=2))
    print(json.dumps({k: v for k, v in figures.items() if k != "delay_over_time"}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
