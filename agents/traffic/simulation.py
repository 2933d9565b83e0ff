"""``Simulation``: one SUMO simulation in this process, through libsumo.

It starts SUMO on a built network and its demand, advances it, reads the detectors
of every signalized junction (the halting, approaching and delayed vehicles, their
waiting time and the new arrivals per incoming lane, the vehicles on each outgoing
lane), sets the lights,
and at the end gives the figures the traffic-signal benchmarks report, per vehicle:
SUMO's tripinfo ``timeLoss + departDelay``, over every vehicle, also those still on
the roads at the end and those still waiting to enter.

libsumo runs SUMO inside the calling process, which is fast (no socket, a few
microseconds a call) but allows one simulation per process: a second ``Simulation``
while one runs is refused, so each driver needs its own worker.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

from agents.traffic.messages import JunctionLayout, NetworkReading
from agents.traffic.networks import SumoMissing, sumo_home
from agents.traffic.signals import SignalPlan, is_green_phase

STEP_S = 1.0                   # SUMO's step: one simulated second
SEED_MAX = 2**31 - 1           # SUMO reads its --seed as a C int
APPROACH_S = 4.0               # "approaching": due at the stop line within this, at
                               # the speed it has (an actuated signal's passage time)
MOVING_MPS = 1.0
DELAY_RANGE_M = 100.0          # "delayed": within this of the stop line, and ...
MIN_TIME_LOSS_S = 1.0          # ... this much time lost since it came onto the lane
                               # (SUMO's delay_based defaults, detectorRange, minTimeLoss)


def _libsumo() -> Any:
    try:
        import libsumo
    except ImportError:
        raise SumoMissing("libsumo is not installed: install the project's traffic extra "
                          "(pip install -e '.[traffic]', or make)") from None
    return libsumo


def check_installed() -> None:
    """``SumoMissing`` naming what to install unless this process can build networks
    and run simulations: SUMO (the eclipse-sumo package, its programs) and libsumo,
    which the first ``Simulation`` would only find missing once it started."""
    sumo_home()
    _libsumo()


class Simulation:
    """A running SUMO simulation of ``net`` with the flows in ``routes``."""

    _running: Simulation | None = None      # libsumo's one simulation in this process

    def __init__(self, net: Path, routes: Path, *, seed: int, end_s: float,
                 workdir: Path) -> None:
        if Simulation._running is not None:
            raise RuntimeError("libsumo runs one SUMO simulation per process and one runs "
                               "here already: give each traffic driver its own worker")
        self._sumo = _libsumo()
        self.tripinfo = workdir / "tripinfo.xml"
        self._sumo.start([
            "sumo", "--net-file", str(net), "--route-files", str(routes),
            "--seed", str(int(seed)), "--step-length", str(STEP_S), "--end", str(end_s),
            "--tripinfo-output", str(self.tripinfo),
            "--tripinfo-output.write-unfinished", "true",
            "--no-step-log", "true", "--no-warnings", "true",
            "--duration-log.disable", "true"])
        Simulation._running = self
        try:
            self._read_signals()
        except BaseException:
            # (the one simulation a process may run stayed taken: every later one was
            # refused, told to use a worker of its own)
            self.close()
            raise

    def _read_signals(self) -> None:
        """Each signalized junction's program and layout, and what the readings need."""
        self.layouts: dict[str, JunctionLayout] = {}
        self.plans: dict[str, SignalPlan] = {}
        tls = self._sumo.trafficlight
        for junction in sorted(tls.getIDList()):
            logic = tls.getAllProgramLogics(junction)[0]
            plan = SignalPlan.from_program([(p.state, p.duration) for p in logic.phases])
            links = tuple((group[0][0], group[0][1]) if group else ("", "")
                          for group in tls.getControlledLinks(junction))
            self.plans[junction] = plan
            self.layouts[junction] = JunctionLayout(
                junction, links, plan.greens,
                tuple(dict.fromkeys(i for i, _ in links if i)),
                tuple(dict.fromkeys(o for _, o in links if o)))
        # per incoming lane, the vehicles on it at the last reading, each with its time
        # loss when it came onto the lane
        self._entered: dict[str, dict[str, float]] = {
            lane: {} for layout in self.layouts.values() for lane in layout.lanes_in}
        self._signals: dict[str, str] = {}
        self._lengths: dict[str, float] = {}
        self.departed = self.arrived = self.teleports = 0
        self._halting_sum = 0
        self._readings = 0

    @property
    def time(self) -> float:
        """Simulated seconds since the start."""
        return float(self._sumo.simulation.getTime())

    def set_signal(self, junction: str, state: str) -> None:
        """Show ``state`` at ``junction`` from the next step on (SUMO's program for it
        is set aside for good)."""
        if self._signals.get(junction) != state:
            self._sumo.trafficlight.setRedYellowGreenState(junction, state)
            self._signals[junction] = state

    def signal(self, junction: str) -> str:
        """The state ``junction`` shows now."""
        return str(self._sumo.trafficlight.getRedYellowGreenState(junction))

    def advance(self, steps: int) -> None:
        """Run ``steps`` SUMO steps, counting departures, arrivals and teleports."""
        simulation = self._sumo.simulation
        for _ in range(steps):
            self._sumo.simulationStep()
            self.departed += simulation.getDepartedNumber()
            self.arrived += simulation.getArrivedNumber()
            self.teleports += simulation.getStartingTeleportNumber()

    def junction_detectors(self, junction: str) -> dict[str, dict[str, Any]]:
        """``queues``, ``waiting``, ``arrivals``, ``vehicles`` per incoming lane and
        ``outgoing`` per outgoing lane of ``junction``, now. Arrivals are the vehicles on a lane now
        that were on none of the junction's incoming lanes at the previous reading."""
        lane = self._sumo.lane
        layout = self.layouts[junction]
        queues, waiting, arrivals, vehicles, approaching, delayed = {}, {}, {}, {}, {}, {}
        arriving_in: dict[str, float] = {}
        # on any of its incoming lanes at the last reading: a vehicle that changed lanes
        # there is no new arrival at the junction
        there_before = set().union(*(self._entered[name].keys() for name in layout.lanes_in))
        for name in layout.lanes_in:
            queues[name] = int(lane.getLastStepHaltingNumber(name))
            waiting[name] = float(lane.getWaitingTime(name))
            present = set(lane.getLastStepVehicleIDs(name))
            vehicles[name] = len(present)
            approaching[name], nearest, delayed[name] = self._on_lane(name, present)
            if nearest is not None:
                arriving_in[name] = nearest
            arrivals[name] = len(present - there_before)
        outgoing = {name: int(lane.getLastStepVehicleNumber(name)) for name in layout.lanes_out}
        return {"queues": queues, "waiting": waiting, "arrivals": arrivals,
                "outgoing": outgoing, "vehicles": vehicles, "approaching": approaching,
                "arriving_in": arriving_in, "delayed": delayed}

    def _on_lane(self, lane: str, present: set[str]) -> tuple[int, float | None, int]:
        """On ``lane``: the moving vehicles due at its end within ``APPROACH_S``, the
        seconds until the nearest of all moving ones gets there (None: none moves), and
        the vehicles delayed near its end (``DELAY_RANGE_M``, ``MIN_TIME_LOSS_S``)."""
        vehicle = self._sumo.vehicle
        length = self._lengths.get(lane)
        if length is None:
            length = self._lengths[lane] = float(self._sumo.lane.getLength(lane))
        on_entry = self._entered[lane]          # (left as the vehicles present now)
        for gone in on_entry.keys() - present:
            del on_entry[gone]
        due, nearest, delayed = 0, None, 0
        for name in present:
            speed = vehicle.getSpeed(name)
            distance = length - vehicle.getLanePosition(name)
            loss = vehicle.getTimeLoss(name)         # since it entered the network
            lost_here = loss - on_entry.setdefault(name, loss)
            if distance <= DELAY_RANGE_M and lost_here > MIN_TIME_LOSS_S:
                delayed += 1
            if speed >= MOVING_MPS:
                if distance <= speed * APPROACH_S:
                    due += 1
                seconds = distance / speed
                if nearest is None or seconds < nearest:
                    nearest = seconds
        return due, nearest, delayed

    def network_reading(self, step: int, halting: int) -> NetworkReading:
        """The network's totals now; ``halting`` (the vehicles standing at the
        signals, summed by the caller from its junction readings) is kept for the
        mean queue of the run's summary."""
        self._halting_sum += halting
        self._readings += 1
        return NetworkReading(
            step=step, time=self.time, running=int(self._sumo.vehicle.getIDCount()),
            waiting_to_enter=len(self._sumo.simulation.getPendingVehicles()),
            departed=self.departed, arrived=self.arrived, teleports=self.teleports,
            halting=halting)

    def describe_signal(self, junction: str) -> tuple[int, str]:
        """(green phase index or -1, stage) of what SUMO's own program shows now."""
        state = self.signal(junction)
        greens = self.plans[junction].greens
        if state in greens:
            return greens.index(state), "green"
        if is_green_phase(state):
            return -1, "green"
        return -1, "yellow" if any(c in "yY" for c in state) else "all_red"

    def finish(self, window_s: float = 60.0,
               periods: list[tuple[str, float, float]] | None = None) -> dict[str, Any]:
        """End the simulation; the run's figures (see ``summarize``)."""
        pending = [float(self._sumo.vehicle.getDepartDelay(v))
                   for v in self._sumo.simulation.getPendingVehicles()]
        end = self.time
        self.close()
        summary = summarize(self.tripinfo, pending, end, window_s, periods)
        summary["teleports"] = self.teleports
        summary["mean_halting"] = self._halting_sum / max(self._readings, 1)
        return summary

    def close(self) -> None:
        """Stop SUMO (it writes the tripinfo of the vehicles still running); a SUMO
        that fails to stop leaves the process free for another simulation all the same."""
        if Simulation._running is self:
            try:
                self._sumo.close()
            finally:
                Simulation._running = None


def summarize(tripinfo: Path, pending_delays: list[float], end_s: float,
              window_s: float = 60.0,
              periods: list[tuple[str, float, float]] | None = None) -> dict[str, Any]:
    """Per-vehicle figures from a tripinfo file written with ``write-unfinished`` and
    the depart delays of the vehicles that never entered.

    ``mean_delay_s`` is the mean of ``timeLoss + departDelay`` over every vehicle;
    ``delay_by_window`` gives, per ``window_s`` of simulated time, the end of the
    window, the mean delay of the vehicles that left the network in it (those still
    in it at the end count in the last window) and their number. ``delay_by_period``
    gives the same for each ``(name, begin_s, end_s)`` of ``periods`` (the demand's
    schedule), so that a controller's delay can be told per kind of traffic.
    """
    delays: list[tuple[float, float]] = []       # (when it left, its delay)
    finished = unfinished = 0
    time_loss = depart_delay = 0.0
    for _, element in ET.iterparse(tripinfo):
        if element.tag != "tripinfo":
            continue
        loss, delay = float(element.get("timeLoss", 0)), float(element.get("departDelay", 0))
        arrival = float(element.get("arrival", -1))
        if arrival < 0:
            unfinished += 1
            arrival = end_s
        else:
            finished += 1
        time_loss += loss
        depart_delay += delay
        delays.append((arrival, loss + delay))
        element.clear()
    delays.extend((end_s, d) for d in pending_delays)
    depart_delay += sum(pending_delays)
    count = len(delays)
    windows: dict[int, list[float]] = {}
    for left, delay in delays:
        windows.setdefault(min(int(left // window_s), int(max(end_s - 1e-9, 0) // window_s)),
                           []).append(delay)
    return {
        "end_s": end_s,
        "vehicles": count,
        "finished": finished,
        "unfinished": unfinished,
        "never_entered": len(pending_delays),
        "mean_delay_s": sum(d for _, d in delays) / count if count else 0.0,
        "mean_time_loss_s": time_loss / count if count else 0.0,
        "mean_depart_delay_s": depart_delay / count if count else 0.0,
        "throughput": finished,
        "delay_by_window": [[(w + 1) * window_s, sum(v) / len(v), len(v)]
                            for w, v in sorted(windows.items())],
        "delay_by_period": _by_period(delays, periods or []),
    }


def _by_period(delays: list[tuple[float, float]],
               periods: list[tuple[str, float, float]]) -> list[dict[str, Any]]:
    """Per period, the mean delay of the vehicles that left in it and their number;
    the last period also takes those that left at or after its end (still in the
    network, or never let in)."""
    found = []
    for index, (name, begin, end) in enumerate(periods):
        last = index == len(periods) - 1
        chosen = [d for left, d in delays if left >= begin and (left < end or last)]
        found.append({"period": name, "begin_s": begin, "end_s": end, "vehicles": len(chosen),
                      "mean_delay_s": sum(chosen) / len(chosen) if chosen else None})
    return found
