"""``run_in_process``: a driver and one controller per junction in this process,
wired as a system wires them, for offline training and quick measurement.

Each junction's reading goes to its controller, its request back to the driver, and
its queues to every controller (a controller keeps only the lanes it leads into).
No worker, no IPC: an hour of the ring takes about 5 s.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from agents.traffic.controller import JunctionController
from agents.traffic.driver import TrafficDriver
from agents.traffic.messages import NeighbourQueues
from pb3a.testing import ModuleHarness

ControllerChoice = Callable[[str], tuple[type[JunctionController], dict[str, Any]]]


def driver(resource: str | Path, cache: Path | None = None, **state: Any) -> ModuleHarness:
    """A ``TrafficDriver`` on ``resource`` in this process, with ``state``; it keeps only
    its newest value per output, so an hour of readings does not pile up."""
    return ModuleHarness(TrafficDriver, state={
        "resource": str(resource), "cache_dir": str(cache) if cache else "", **state},
        keep=1)


def run_in_process(resource: str | Path, make: ControllerChoice, *, seed: int,
                   duration_s: float, cache: Path | None = None,
                   demand_scale: Mapping[str, float] | None = None,
                   adopt: Callable[[str, JunctionController], None] | None = None,
                   settings: Mapping[str, Any] | None = None,
                   ) -> tuple[dict[str, Any], dict[str, ModuleHarness]]:
    """Simulate ``resource`` for ``duration_s`` with, per junction, the controller
    ``make(junction)`` gives (class, state); the run's figures and the controllers.
    ``demand_scale`` is the driver's (period name, or ``*``, to a factor of its rates).
    ``adopt(junction, controller)`` is called once each controller is set up: a harness
    gives a module a copy of its state, so what junctions are to share (the training's
    one table) is handed to them there. ``settings`` are more of the driver's state (its
    minimum green, its control step); what they leave out is the driver's default."""
    simulation = driver(resource, cache, **{
        "seed": seed, "duration_s": duration_s, "demand_scale": dict(demand_scale or {}),
        **(settings or {})})
    try:
        junctions = simulation.state["junctions"]
        controllers = {}
        for junction in junctions:
            cls, state = make(junction)
            controllers[junction] = ModuleHarness(cls, state=state, name=junction, keep=1)
            if adopt is not None:
                adopt(junction, controllers[junction].module)
        seen = dict.fromkeys(range(len(junctions)), -1)
        while simulation.module.status == "running":
            if not junctions:           # nothing to wait for: it runs free, when stepped
                simulation.step()
                continue
            for slot, junction in enumerate(junctions):
                reading = simulation.last(f"reading_{slot}")
                if reading is None or reading.step == seen[slot]:
                    continue
                seen[slot] = reading.step
                queues = NeighbourQueues(junction, reading.time, dict(reading.queues))
                for controller in controllers.values():
                    controller.feed("neighbour_0", queues)
            for slot, junction in enumerate(junctions):
                reading = simulation.last(f"reading_{slot}")
                if simulation.module.status != "running":
                    break
                controllers[junction].feed("reading", reading)
                simulation.feed(f"request_{slot}", controllers[junction].last("request"))
        return simulation.state["result"], controllers
    finally:
        simulation.close()
