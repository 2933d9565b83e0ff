"""Launching a system over several node controllers: how the launch time grows with
the nodes, and how long a launch with unreachable nodes takes to fail.

Each node is a ``pb3a node start`` process on this machine (loopback), started once
for the whole run; each launch runs one event-driven ``Gain`` on every remote node
and a ``Clock`` on the launcher's embedded node ``a``. Measured:

- ``healthy``: for 1, 3 and 6 remote nodes, ``launch()`` to its return, split into the
  launch's steps (``start_nodes``: an executor started on every node;
  ``check_classes``; ``expect``; ``add_module``, summed over the modules; ``connect``
  and the rest: links and module starts), then ``close()``;
- ``unreachable``: 6 nodes of which 1 or 2 are a port nothing listens on, or a node
  controller frozen by SIGSTOP: the time until ``launch()`` raises, which nodes its
  error names, and whether every executor that did start was stopped again (each
  controller's running executors, asked afterwards).

On this 2-core VM every executor starts on the same two CPUs, so side-by-side starts
gain less here than on robots that each start their own.
"""

from __future__ import annotations

import argparse
import os
import re
import select
import signal
import socket
import subprocess
import sys
import time
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
os.environ.setdefault("PB3A_KEY", os.urandom(32).hex())   # a throw-away cluster key

from _common import machine, main_guard, steal_report, steal_seconds, summary
from _modules import Clock, Gain

from pb3a import PB3AError, System
from pb3a.launch.launcher import Launcher
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient

if TYPE_CHECKING:
    from collections.abc import Iterator

SIZES = (1, 3, 6)
REPS = 3
READY_S = 30.0          # a node controller prints where it listens within this
LAUNCH_TIMEOUT = 10.0   # the systems' timeout (the launch's checks are bounded by it)
STEPS = ("start_nodes", "check_classes", "expect", "add_module", "connect")
ROOT = Path(__file__).resolve().parent


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Controller:
    """``pb3a node start`` in a process of its own, on loopback."""

    def __init__(self, name: str) -> None:
        self.name, self.address = name, f"tcp://127.0.0.1:{free_port()}"
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT.parent)])}
        self.process = subprocess.Popen(
            [sys.executable, "-m", "pb3a", "node", "start", "--name", name, "--listen",
             self.address, "--max-cpu", "101"], stdout=subprocess.PIPE, text=True, env=env)

    def ready(self, timeout: float) -> None:
        ready, _, _ = select.select([self.process.stdout], [], [], timeout)
        line = self.process.stdout.readline().strip() if ready else ""
        if line != f"node {self.name} at {self.address}":
            raise TimeoutError(f"node controller {self.name} did not come up within "
                               f"{timeout:g} s (it said {line!r})")

    def executors(self) -> dict[str, str]:
        """The configurations it runs an executor for, asked within 5 s."""
        client = ControlClient(ClusterKey.load(), self.address)
        try:
            return client.call("status", 5.0)["executors"]
        finally:
            client.close()

    def stop(self) -> None:
        self.process.send_signal(signal.SIGCONT)       # (if frozen)
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(15)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(5)
        self.process.stdout.close()


@contextmanager
def controllers(count: int) -> Iterator[list[Controller]]:
    made: list[Controller] = []
    try:
        for i in range(count):
            made.append(Controller(f"n{i + 1}"))
        for controller in made:
            controller.ready(READY_S)
        yield made
    finally:
        for controller in made:
            controller.stop()


@contextmanager
def step_times() -> Iterator[dict[str, float]]:
    """Seconds spent in each of the launcher's ``STEPS`` (summed over its calls)."""
    spent = dict.fromkeys(STEPS, 0.0)
    originals = {step: getattr(Launcher, step) for step in STEPS}

    def timed(step: str) -> Any:
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            began = time.monotonic()
            try:
                return originals[step](*args, **kwargs)
            finally:
                spent[step] += time.monotonic() - began
        return wrapper
    for step in STEPS:
        setattr(Launcher, step, timed(step))
    try:
        yield spent
    finally:
        for step, original in originals.items():
            setattr(Launcher, step, original)


def system(name: str, addresses: dict[str, str]) -> System:
    built = System(name, timeout=LAUNCH_TIMEOUT).node("a")
    built.add("clock", Clock, node="a", period=0.1)
    for node, address in addresses.items():
        built.node(node, address=address)
        built.add(f"gain_{node}", Gain, node=node)
    return built


def healthy(pool: list[Controller], sizes: tuple[int, ...]) -> dict[str, Any]:
    """Launch and close over each of ``sizes`` nodes, ``REPS`` times each, round robin."""
    rows: dict[int, list[dict[str, float]]] = {n: [] for n in sizes}
    for rep in range(REPS):
        for n in sizes:
            with step_times() as spent:
                began = time.monotonic()
                run = system(f"launch-{n}-{rep}",
                             {c.name: c.address for c in pool[:n]}).launch()
                launch_s = time.monotonic() - began
            began = time.monotonic()
            run.close()
            rows[n].append({"launch_s": launch_s, **{f"{s}_s": t for s, t in spent.items()},
                            "close_s": time.monotonic() - began})
    return {f"{n}_nodes": {key: summary([row[key] for row in rows[n]]) for key in rows[n][0]}
            for n in sizes}


def failing(pool: list[Controller], dead: list[str], how: str) -> dict[str, Any]:
    """A launch over ``pool`` with nodes ``dead`` unreachable (``how``: a port nothing
    listens on, or their controller frozen): how long until it fails, what it names."""
    addresses = {c.name: c.address for c in pool}
    with ExitStack() as frozen:
        for controller in pool:
            if controller.name in dead:
                if how == "refused":
                    addresses[controller.name] = f"tcp://127.0.0.1:{free_port()}"
                else:
                    controller.process.send_signal(signal.SIGSTOP)
                    frozen.callback(controller.process.send_signal, signal.SIGCONT)
        began = time.monotonic()
        try:
            system(f"failing-{how}-{len(dead)}", addresses).launch().close()
            said = "(it started)"
        except PB3AError as exc:
            said = str(exc)
        took = time.monotonic() - began
    named = sorted(set(re.findall(r"\bnode (n\d+)", said)))
    left = {c.name: c.executors() for c in pool if c.name not in dead}
    return {"unreachable": dead, "how": how, "error_after_s": round(took, 2),
            "named": named, "names_every_unreachable_node": set(dead) <= set(named),
            "executors_left": {node: configs for node, configs in left.items() if configs},
            "error": said}


def body(result: dict[str, Any], sizes: tuple[int, ...]) -> None:
    result["machine"] = machine()
    result["settings"] = {"sizes": list(sizes), "reps": REPS, "timeout_s": LAUNCH_TIMEOUT}
    steal0, began = steal_seconds(), time.monotonic()
    with controllers(max(sizes)) as pool:
        result["healthy"] = healthy(pool, sizes)
        six = pool[:6]
        result["unreachable"] = [failing(six, dead, how) for how in ("refused", "frozen")
                                 for dead in (["n3"], ["n2", "n5"])]
    result["steal"] = steal_report(steal_seconds() - steal0, time.monotonic() - began)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reps", type=int, default=REPS)
    options = parser.parse_args()
    REPS = options.reps
    main_guard(lambda result: body(result, SIZES))
