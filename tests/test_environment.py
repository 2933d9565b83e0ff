"""The built-in env module of each node, and nodes pinned to CPUs."""

from __future__ import annotations

import multiprocessing
import os
import statistics
import threading

import numpy as np
import pytest
from conftest import eventually
from sample_modules import Spinner

from pb3a import (
    ConfigError,
    Environment,
    Input,
    InputPort,
    Module,
    ModuleNotFound,
    System,
)
from pb3a.node.executor import Executor
from pb3a.testing import ModuleHarness


class Watcher(Module):
    """Keeps the newest environment figures it was sent."""

    cpu = Input(float)
    per_core = Input(np.ndarray)
    memory = Input(float)
    load = Input(np.ndarray)
    seen = 0
    last_cpu = -1.0
    cores = 0
    memory_bytes = 0.0
    pinned_to: list[int] = []

    def setup(self) -> None:
        self.pinned_to = sorted(os.sched_getaffinity(0))

    def on_input(self, port: InputPort) -> None:
        value = port.read()
        if port is self.cpu:
            self.last_cpu, self.seen = value, self.seen + 1
        elif port is self.per_core:
            self.cores = len(value)
        elif port is self.memory:
            self.memory_bytes = value


def test_a_node_s_env_module_starts_when_read_and_reports_its_cpus() -> None:
    system = System("env")
    system.node("a", cpus=[0])
    system.node("b")
    system.add("env-a", Environment, node="a", period=0.05)     # a faster rate than 1 Hz
    system.add("watcher", Watcher, node="b")
    system.link("env-a.cpu", "watcher.cpu")
    system.link("env-a.cpu_per_core", "watcher.per_core")
    system.link("env-a.memory_available", "watcher.memory")
    system.link("env-a.load", "watcher.load")
    with system.launch() as run:
        state = eventually(lambda: (s := run.state("watcher"))["seen"] >= 3 and s,
                           what="three env samples")
        modules = run.stats().modules
    assert 0.0 <= state["last_cpu"] <= 100.0
    assert state["cores"] == 1                       # node a is pinned to one CPU
    assert state["memory_bytes"] > 0
    assert modules["env-a"].node == "a" and "env-b" not in modules
    assert state["pinned_to"] == sorted(os.sched_getaffinity(0))     # b is not pinned


def test_the_env_module_is_there_without_being_declared() -> None:
    system = System("env-implicit")
    system.add("watcher", Watcher)
    system.link("env-local.cpu", "watcher.cpu")
    with system.launch() as run:
        eventually(lambda: run.state("watcher")["seen"] >= 1, timeout=10, what="a sample")
        assert run.stats().modules["env-local"].node == "local"


def test_a_node_s_env_module_linked_at_run_time_starts_with_the_link() -> None:
    # env-a runs once a link reads it; at launch only, it was: linked later, the error
    # said "no module 'env-a'; modules: watcher", as for a misspelt module
    system = System("env-later")
    system.node("a")
    system.node("b")
    system.add("watcher", Watcher, node="b")
    with system.launch() as run:
        with pytest.raises(ModuleNotFound) as unread:
            run.state("env-a")
        assert "node a's env module, which runs once a link reads it" in str(unread.value)
        with pytest.raises(ConfigError, match=r"no node 'c' \(nodes: a, b\)"):
            run.link("env-c.cpu", "watcher.cpu")
        with pytest.raises(ConfigError, match="env-a has no output 'cpus'"):
            run.link("env-a.cpus", "watcher.cpu")
        assert "env-a" not in run.topology().modules          # (a refused link: not started)
        run.link("env-a.cpu", "watcher.cpu")
        assert run.where("env-a") == "a"
        eventually(lambda: run.state("watcher")["seen"] >= 1, timeout=10, what="a sample")
        kinds = [(event.kind, event.subject) for event in run.events()][-2:]
        assert kinds == [("module_added", "env-a"), ("link_added", "env-a.cpu->watcher.cpu")]


def test_workers_of_a_pinned_node_run_on_its_cpus_only() -> None:
    system = System("pinned")
    system.node("a", cpus=[0])
    system.add("watcher", Watcher, node="a")
    with system.launch() as run:
        assert run.state("watcher")["pinned_to"] == [0]


def test_bad_cpu_lists_are_reported() -> None:
    system = System("bad-cpus")
    system.node("a", cpus=[os.cpu_count() + 3])
    system.add("watcher", Watcher, node="a")
    (problem,) = system.check()
    assert "[nodes.a]: cpus must be a non-empty list of CPU numbers" in problem
    with pytest.raises(ConfigError, match="cpus must be"):
        system.plan()


class LoadWatcher(Module):
    """Keeps the CPU figures of a node: all, its own modules', the rest."""

    cpu = Input(float, policy="queue:64")
    own = Input(float, policy="queue:64")
    outside = Input(float, policy="queue:64")
    figures: dict = {"cpu": [], "own": [], "outside": []}

    def on_input(self, port: InputPort) -> None:
        self.figures[port.name].append(port.read())


def _burn(stop) -> None:
    os.sched_setaffinity(0, [0])
    while not stop.is_set():
        pass


@pytest.mark.serial     # alone: it measures CPU 0's load (see the Makefile's test target)
@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="a node pinned to one CPU of two")
def test_the_env_module_tells_the_system_s_own_load_from_outside_load() -> None:
    system = System("own-load")
    system.node("a", cpus=[0])
    system.node("b", cpus=[1])
    system.add("env-a", Environment, node="a", period=0.25)
    system.add("spinner", Spinner, node="a")
    system.add("watcher", LoadWatcher, node="b")
    for port, into in (("cpu", "cpu"), ("cpu_own", "own"), ("cpu_outside", "outside")):
        system.link(f"env-a.{port}", f"watcher.{into}")
    context = multiprocessing.get_context("fork")
    stop = context.Event()
    burner = context.Process(target=_burn, args=(stop,), daemon=True)
    with system.launch() as run:
        def settled(when: str) -> dict:
            """The median of each figure over the next four samples."""
            begun = len(run.state("watcher")["figures"]["cpu"])
            figures = eventually(lambda: min(map(len, (f := run.state("watcher")["figures"])
                                                 .values())) >= begun + 4 and f,
                                 timeout=15, what=f"four samples {when}")
            return {name: statistics.median(values[begun:begun + 4])
                    for name, values in figures.items()}
        # what an earlier test left ending on CPU 0 is outside load too: wait it out
        eventually(lambda: (f := run.state("watcher")["figures"]["outside"]) and f[-1] < 10,
                   timeout=20, what="no outside load on CPU 0 while the module spins")
        spinning = settled("while its own module spins")
        run.set_state("spinner", spinning=False)
        burner.start()
        try:
            settled("after the switch")                    # (a sample spans both)
            burnt = settled("while an outside process burns")
        finally:
            stop.set()
            burner.join(5)
    # all of node a's CPU goes to its own module, then to a process outside the system
    assert spinning["own"] > 60 and spinning["outside"] < 30, spinning
    assert burnt["outside"] > 60 and burnt["own"] < 20, burnt


def test_the_env_module_tells_each_move_and_loss_once_however_many_came_before() -> None:
    """It is given the latest moves and losses, numbered: one that comes when as many
    old ones have been dropped (the event log keeps the last 10,000) is still told."""
    def move(seq: int) -> dict:
        return {"seq": seq, "module": f"m{seq}", "source": "a", "destination": "b"}

    harness = ModuleHarness(Environment, state={"moves": [move(1), move(2)],
                                                "losses": [{"seq": 3, "node": "c"}]})
    try:
        harness.step()
        assert harness.written["module_moved"] == [] == harness.written["node_lost"]
        harness.module.set_state({"moves": [move(2), move(4)],       # as many as before
                                  "losses": [{"seq": 3, "node": "c"}, {"seq": 5, "node": "d"}]})
        harness.step(2)
        assert harness.written["module_moved"] == [
            {"module": "m4", "source": "a", "destination": "b"}]
        assert harness.written["node_lost"] == ["d"]
    finally:
        harness.close()


def test_the_env_keeper_goes_on_past_an_env_module_between_its_removal_and_its_start(
        monkeypatch) -> None:
    """A restart (or removal) of an env module drops it from its node before the
    launcher's spec: the env keeper's pass in between failed with KeyError, which ended
    its thread for good, and the env modules were told nothing more (the nodes' health,
    their own processes; the remote nodes' logs were no longer merged). Here a pass of
    the keeper runs in that window; then the module, started again, is told."""
    system = System("env-kept")
    system.node("a")
    system.add("env-a", Environment, node="a")
    window, in_window, passed = [], threading.Event(), threading.Event()
    with system.launch() as run:
        update, remove = run._env.update, Executor.remove_module

        def watched_update() -> None:
            """The keeper's pass, its error kept if it began in the window."""
            if threading.current_thread().name != "pb3a-env" or not in_window.is_set():
                return update()
            try:
                update()
                window.append(None)
            except Exception as exc:
                window.append(exc)
                raise
            finally:
                passed.set()

        def removed_then_a_pass(self: Executor, name: str) -> None:
            remove(self, name)
            if name == "env-a":
                in_window.set()
                passed.wait(10)
                in_window.clear()

        monkeypatch.setattr(run._env, "update", watched_update)
        monkeypatch.setattr(Executor, "remove_module", removed_then_a_pass)
        eventually(lambda: run.state("env-a")["own_pids"], what="env-a told its processes")
        run.restart("env-a")
        assert window == [None]
        pid = run.stats().modules["env-a"].pid          # (a worker of its own again)
        eventually(lambda: pid in run.state("env-a")["own_pids"], timeout=15,
                   what="env-a told its worker once restarted")
        assert any(t.name == "pb3a-env" and t.is_alive() for t in threading.enumerate())


def test_the_env_keeper_goes_on_after_a_pass_that_fails(monkeypatch) -> None:
    """A pass of the env keeper that raised ended its thread for good: the env modules
    were told nothing more, and the remote nodes' logs were no longer merged."""
    system = System("env-kept-on")
    system.node("a")
    system.add("env-a", Environment, node="a")
    with system.launch() as run:
        update, passes = run._env.update, []

        def failing_once() -> None:
            if threading.current_thread().name == "pb3a-env":
                passes.append(None)
                if len(passes) == 1:
                    raise RuntimeError("dictionary changed size during iteration")
            update()
        monkeypatch.setattr(run._env, "update", failing_once)
        eventually(lambda: len(passes) > 1, what="a pass after the one that failed")
