"""``TrafficDriver``: a SUMO simulation as PB3A ports, stepped in lock-step with the
junctions' controllers.

SUMO is the legacy program here, and the driver owns it: one simulation, run in the
driver's own process through libsumo (which allows one per process, so the driver
needs a worker of its own). Its ``resource`` is the path of a network description
(``scenarios/traffic/ring.toml``); the driver builds the network if needed
(``agents.traffic.networks``), writes the demand for ``duration_s`` and starts SUMO
with ``seed``, its periods' rates scaled by ``demand_scale`` (period name, or ``*``
for all, to a factor). Setting ``resource`` (or ``seed``, ``signals``, ``duration_s``,
``own_programs``, ``demand_scale``) while it runs finishes the simulation it has,
keeping its figures
in ``result``, and starts the new one at once: like ``RobotDriver``, it is re-pointed
while the system runs. A new simulation that could not start (a mistake in its
network or demand scale, a signalized junction no controller is linked to answer) is
refused before anything changes, naming what is wrong, and the running one goes on.

Each signalized junction has a slot: the i-th junction (in ``junctions``, sorted by
id) writes a ``JunctionReading`` on ``reading_i`` at the start of every control step
and takes ``PhaseRequest``s on ``request_i``. The simulation advances one control
step (``control_step_s``) when every junction has answered that step's reading, or
when ``lockstep_timeout_s`` has passed since the readings went out; the junctions
that had not answered are counted in ``late`` (and ``late_by_junction``) and keep the
phase they last asked for. So a scenario runs as fast as its controllers decide, and
a stuck controller slows it down but does not stop it.

A slot's ``done_i``, where a link feeds it, brings the rest of the junction into the
lock-step: the simulated time of the last reading its other modules (its performance
agent) have dealt with. The step then also waits for that time to be the step's (or
for the timeout, counted late the same way). So a controller swapped on a step's
measures runs from the next step on, however loaded the machine: the run's figures
depend on its seed alone.

The driver, not the controllers, makes the lights legal: each junction's
``SignalHead`` holds a green for ``min_green_s`` and puts yellow (and all-red, where
the program has it) before any new green, so a controller swapped mid-phase cannot
show conflicting greens or skip a yellow. With ``own_programs`` the lights run SUMO's
own programs (``signals``: static, actuated or delay_based, the baselines), the driver
takes no requests and runs the simulation as fast as it goes.

``traffic`` carries the network's totals each step and ``clock`` the simulated time;
at ``duration_s`` the simulation ends and ``summary`` (also ``result``) carries the
run's figures: mean delay per vehicle (SUMO's tripinfo ``timeLoss + departDelay``,
over every vehicle, also those still in the network or waiting to enter at the end),
throughput, teleports, the mean number of vehicles standing at the signals, and the
delay over time.
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from agents.limits import SECONDS, SPAN, out_of_limits, whole
from agents.traffic.messages import JunctionReading, NetworkReading, PhaseRequest
from agents.traffic.networks import BuildFailed, Network, SumoMissing
from agents.traffic.signals import SignalHead
from agents.traffic.simulation import SEED_MAX, STEP_S, Simulation
from pb3a import Input, InputPort, Module, Output
from pb3a.model.module import reflective

MAX_JUNCTIONS = 16          # junction slots: ports are declared with the class
_SIMULATION_KEYS = ("resource", "seed", "signals", "duration_s", "own_programs",
                    "demand_scale")
_PREPARED_BY = (*_SIMULATION_KEYS, "cache_dir")    # what a simulation's network needs
_LIMITS = {"control_step_s": SPAN, "duration_s": SPAN, "min_green_s": SECONDS,
           "lockstep_timeout_s": SECONDS,
           # ("false", a string, was true: SUMO's programs ran the lights)
           "own_programs": ("true or false", lambda value: isinstance(value, bool))}


def _junction_ports() -> dict[str, Input | Output]:
    ports: dict[str, Input | Output] = {}
    for slot in range(MAX_JUNCTIONS):
        ports[f"reading_{slot}"] = Output(JunctionReading)
        ports[f"request_{slot}"] = Input(PhaseRequest, policy="queue:8")
        ports[f"done_{slot}"] = Input(float, policy="queue:8")
    return ports


# The slots' ports, one pair per junction, declared once for the class below.
_JunctionSlots = type("_JunctionSlots", (), _junction_ports())


def _said(exc: Exception) -> str:
    """``exc`` as a sentence: its own words, naming its type where they may not say
    what it is (a ``TypeError`` from a value of the wrong kind, say)."""
    if isinstance(exc, ValueError | BuildFailed | SumoMissing):
        return str(exc)
    return f"{type(exc).__name__}: {exc}"


class TrafficDriver(_JunctionSlots, Module):
    """A SUMO simulation: junction readings out, phase requests in, in lock-step."""

    traffic = Output(NetworkReading)
    clock = Output(float)           # simulated seconds of the readings just written
    summary = Output(dict)          # the run's figures, once, when it ends
    period = 0.005                  # how often the lock-step timeout is checked

    resource = ""                   # the network description (.toml) to simulate
    seed = 1                        # SUMO's random seed: the demand's arrivals
    duration_s = 3600.0             # simulated length of the run (the demand fits in it)
    demand_scale: dict[str, float] = {}     # period name (or "*") -> factor of its rates
    signals = "static"              # SUMO's program type for the lights: static,
                                    # actuated or delay_based (used with own_programs)
    own_programs = False            # True: SUMO's programs run the lights (baselines)
    control_step_s = 1.0            # simulated seconds between two readings
    min_green_s = 5.0
    lockstep_timeout_s = 2.0        # wall seconds to wait for a junction's request
    cache_dir = ""                  # where networks are built ("": the user's cache)
    out_dir = ""                    # where SUMO writes its files ("": a temporary one)

    # read-outs
    status = "idle"                 # idle | running | finished | failed
    junctions: list[str] = []       # the signalized junctions, in slot order
    step_count = 0                  # control steps done in this simulation
    time_s = 0.0
    late = 0                        # answers (requests, done) not come by the timeout
    late_by_junction: dict[str, int] = {}
    rejected = 0                    # requests that could not be applied
    run = 0                         # simulations begun: this one's number, which its
                                    # readings carry and its requests echo
    last_error = ""
    result: dict[str, Any] = {}     # the figures of the last simulation that ended

    def setup(self) -> None:
        self._clock = time.monotonic
        self._simulation: Simulation | None = None
        self._heads: dict[str, SignalHead] = {}
        self._awaiting: set[str] = set()        # junctions whose request is to come
        self._unsettled: set[str] = set()       # junctions whose done is to come
        self._published_at = 0.0
        self._workdir: Path | None = None
        self._periods: list[tuple[str, float, float]] = []   # the demand's, in this run
        if self.resource:
            self._begin()

    @classmethod
    def state_problems(cls, state: dict[str, Any]) -> list[str]:
        """A control step, minimum green, duration, lock-step timeout or seed out of
        range, ``own_programs`` not true or false, each naming the setting."""
        problems = super().state_problems(state)
        wrong = out_of_limits(_LIMITS, state)
        seed = state.get("seed", 0)
        if not (whole(seed) and seed <= SEED_MAX):
            wrong.append(f"seed must be a whole number from 0 to {SEED_MAX} (SUMO's "
                         f"--seed), got {seed!r}")
        return problems + [f"{cls.__name__}'s {problem}" for problem in wrong]

    @reflective                 # (it takes the fields Module's does: they are checked)
    def set_state(self, state: dict[str, Any]) -> None:
        """Set state (what ``state_problems`` refuses is refused, nothing set); a change
        of ``resource``, ``seed``, ``signals``, ``duration_s``, ``own_programs`` or
        ``demand_scale`` in a driver set up ends its simulation and starts the new one at
        once; a ``min_green_s`` holds from the green shown now. ``ValueError`` (nothing
        set, the simulation running on) for a new simulation that could not start: its
        network, demand scale or signals wrong, or a signalized junction of it without a
        controller (see ``_prepare``)."""
        changed = any(k in state and state[k] != getattr(self, k) for k in _SIMULATION_KEYS)
        prepared = None
        if changed and "_heads" in vars(self):
            settings = {key: state.get(key, getattr(self, key)) for key in _PREPARED_BY}
            if settings["resource"]:
                try:
                    prepared = self._prepare(settings)
                except Exception as exc:      # whatever it is, the new one cannot start
                    raise ValueError(f"{_said(exc)} (nothing was set: the simulation it "
                                     f"has goes on)") from exc
        super().set_state(state)
        for head in vars(self).get("_heads", {}).values():
            head.min_green_s = self.min_green_s
        if changed and "_heads" in vars(self):
            self._end(keep=True)
            if prepared is not None:
                self._begin(prepared)

    def teardown(self) -> None:
        self._end(keep=False)

    # -- the lock-step ------------------------------------------------------------
    def step(self) -> None:
        if self.status != "running":
            return
        if self.own_programs or not self.junctions:
            deadline = self._clock() + 0.02        # free run, a slice at a time
            while self.status == "running" and self._clock() < deadline:
                self._advance()
            return
        if self._unsettled:                         # (one unlinked since: not waited for)
            self._unsettled &= self._done_linked()
        if not self._awaiting and not self._unsettled:
            self._advance()
        elif self._clock() - self._published_at >= self.lockstep_timeout_s:
            for junction in self._awaiting | self._unsettled:
                self.late_by_junction[junction] = self.late_by_junction.get(junction, 0) + 1
            self.late += len(self._awaiting) + len(self._unsettled)
            self._advance()

    def on_input(self, port: InputPort) -> None:
        kind, _, slot = port.name.rpartition("_")
        if kind == "done":
            # (a time not this step's is of a step gone by, counted late, or of a run
            # that has ended)
            if self.time_s in port.read_all():
                self._unsettled.discard(self._junction(int(slot)))
        else:
            for request in port.read_all():
                self._take(int(slot), request)
        if (self.status == "running" and not self.own_programs and not self._awaiting
                and not self._unsettled):
            self._advance()

    def _junction(self, slot: int) -> str | None:
        return self.junctions[slot] if slot < len(self.junctions) else None

    def _done_linked(self) -> set[str]:
        """The junctions whose ``done_i`` a link feeds: in the lock-step."""
        return {junction for slot, junction in enumerate(self.junctions)
                if getattr(self, f"done_{slot}").linked}

    def _take(self, slot: int, request: PhaseRequest) -> None:
        """Apply a junction's request; a wrong one is counted and said in last_error."""
        if self.status != "running" or self.own_programs:
            return
        if request.run and request.run != self.run:
            return          # an answer to a simulation that has ended (re-pointed since)
        junction = self._junction(slot)
        problem = None
        if request.junction != junction:
            problem = (f"request_{slot} is junction {junction!r}'s slot, but the request "
                       f"names {request.junction!r}")
        elif request.step > self.step_count:
            problem = (f"{junction}: a request for step {request.step}, which has not "
                       f"begun (now {self.step_count})")
        else:
            try:
                self._heads[junction].request(request.green)
            except ValueError as exc:
                problem = f"{junction}: {exc}"
            if request.step == self.step_count:
                # its answer to this step, applied or not: a green it lacks is refused
                # and the one it asked before stands, and no other answer is coming
                self._awaiting.discard(junction)
        if problem is not None:
            self.rejected += 1
            self.last_error = problem
        # (an older step's request came after its step was counted late: it still
        # stands as the junction's wish)

    def _advance(self) -> None:
        """Show each junction's next legal state, run one control step, write what
        came of it (or end the run at ``duration_s``). If SUMO fails doing so, the run
        ends as ``failed``, saying why in ``last_error``, and the error is raised."""
        try:
            self._run_step()
        except Exception as exc:
            self.last_error = (f"{self.resource}: SUMO failed at {self.time_s:g} of "
                               f"{self.duration_s:g} simulated s: {type(exc).__name__}: {exc}")
            with contextlib.suppress(Exception):      # (what is left of it)
                self._end(keep=False)
            self._simulation, self._heads = None, {}
            self._awaiting, self._unsettled = set(), set()
            self._remove_workdir()
            self.status = "failed"
            raise

    def _run_step(self) -> None:
        simulation = self._simulation
        assert simulation is not None
        # SUMO advances in whole steps: the heads count the time it really runs, so a
        # control step of 2.5 s (two steps) cannot cut a green short of min_green_s
        steps = max(1, round(self.control_step_s / STEP_S))
        if not self.own_programs:
            for junction, head in self._heads.items():
                simulation.set_signal(junction, head.show(steps * STEP_S))
        simulation.advance(steps)
        self.step_count += 1
        self.time_s = simulation.time
        if self.time_s >= self.duration_s:
            self._end(keep=True)
        else:
            self._publish()

    def _publish(self) -> None:
        simulation = self._simulation
        assert simulation is not None
        halting = 0
        for slot, junction in enumerate(self.junctions):
            detectors = simulation.junction_detectors(junction)
            halting += sum(detectors["queues"].values())
            head = self._heads.get(junction)
            if head is not None and not self.own_programs:
                green, target, stage, elapsed = head.green, head.target, head.stage, head.elapsed
            else:
                green, stage = simulation.describe_signal(junction)
                target, elapsed = green, 0.0
            getattr(self, f"reading_{slot}").write(JunctionReading(
                junction=junction, step=self.step_count, time=simulation.time,
                layout=simulation.layouts[junction], green=green, target=target,
                stage=stage, elapsed=elapsed, signal=simulation.signal(junction),
                run=self.run, **detectors))
        self.traffic.write(simulation.network_reading(self.step_count, halting))
        self.clock.write(simulation.time)
        self._awaiting = set() if self.own_programs else set(self.junctions)
        self._unsettled = self._done_linked() & self._awaiting
        self._published_at = self._clock()

    # -- a simulation's life ---------------------------------------------------------
    def _prepare(self, settings: dict[str, Any]) -> tuple[Network, Path]:
        """The network of a simulation with ``settings`` (``_PREPARED_BY``), built and
        checked, before anything of the running one changes: ``ValueError`` (or the
        build's ``BuildFailed``, ``SumoMissing``) says what keeps it from starting. That
        is a description or demand scale with a mistake, a stream it cannot carry, more
        signalized junctions than the slots and, in lock-step, a junction whose slot's
        ``request_i`` no link feeds while others are fed: no controller would answer it,
        and every step would wait ``lockstep_timeout_s`` for it. (In a harness no slot is
        fed by a link, and none is asked about.)"""
        resource = settings["resource"]
        network = Network.load(resource).scaled(settings["demand_scale"])
        net = network.build(settings["signals"],
                            Path(settings["cache_dir"]) if settings["cache_dir"] else None)
        network.check_streams(net)
        junctions = network.signalized(net)
        if len(junctions) > MAX_JUNCTIONS:
            raise ValueError(f"{resource} has {len(junctions)} signalized junctions; the "
                             f"driver has slots for {MAX_JUNCTIONS}")
        if not settings["own_programs"]:
            fed = [bool(getattr(self, f"request_{slot}").linked)
                   for slot in range(MAX_JUNCTIONS)]
            alone = [f"{junction} (request_{slot})" for slot, junction in enumerate(junctions)
                     if not fed[slot]]
            if any(fed) and alone:
                raise ValueError(
                    f"{resource}: no controller answers {len(alone)} of its {len(junctions)} "
                    f"signalized junctions: {', '.join(alone)}; no link feeds their slots' "
                    f"requests, and each step would wait lockstep_timeout_s for them (link a "
                    f"controller to each, or run SUMO's programs: own_programs)")
        return network, net

    def _begin(self, prepared: tuple[Network, Path] | None = None) -> None:
        """Build the network and demand (unless ``prepared`` already), start SUMO, write
        the first readings."""
        try:
            network, net = prepared or self._prepare(
                {key: getattr(self, key) for key in _PREPARED_BY})
            if self.out_dir:
                self._workdir = Path(self.out_dir)
                self._workdir.mkdir(parents=True, exist_ok=True)
            else:
                self._workdir = Path(tempfile.mkdtemp(prefix="pb3a-traffic-"))
            routes = network.write_demand(self.duration_s, self._workdir / "demand.rou.xml")
            self._periods = [(period.name, begin, end)
                             for period, begin, end in network.schedule(self.duration_s)]
            self._simulation = Simulation(net, routes, seed=self.seed, end_s=self.duration_s,
                                          workdir=self._workdir)
        except Exception as exc:
            self.status, self.last_error = "failed", f"{self.resource}: {exc}"
            self._remove_workdir()
            raise
        layouts = self._simulation.layouts
        # what this simulation is, for its figures (state may change before it ends)
        self._identity = {key: getattr(self, key) for key in _SIMULATION_KEYS}
        self.junctions = list(layouts)
        self.run += 1
        self._heads = {} if self.own_programs else {
            j: SignalHead(self._simulation.plans[j], self.min_green_s) for j in self.junctions}
        self.status, self.step_count, self.time_s = "running", 0, 0.0
        self.late, self.late_by_junction, self.rejected = 0, {}, 0
        self._publish()

    def _end(self, keep: bool) -> None:
        """Stop the simulation; with ``keep``, its figures go to ``result`` and out on
        ``summary``."""
        simulation, self._simulation = self._simulation, None
        if simulation is None:
            return
        if keep:
            self.result = {**self._identity, "late": self.late, "rejected": self.rejected,
                           **simulation.finish(periods=self._periods)}
            self.status = "finished"
            self.summary.write(self.result)
        else:
            simulation.close()
            self.status = "idle"
        self._heads, self._awaiting, self._unsettled = {}, set(), set()
        self._remove_workdir()

    def _remove_workdir(self) -> None:
        if self._workdir is not None and not self.out_dir:
            shutil.rmtree(self._workdir, ignore_errors=True)
        self._workdir = None
