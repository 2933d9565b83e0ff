"""Failure on one node: exceptions in bodies, killed workers, bounded shutdown, no leaks."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import importlib
import inspect
import json
import logging
import multiprocessing
import os
import re
import signal
import subprocess
import sys
import textwrap
import threading
import time
import types
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import pytest
import sample_modules
from conftest import alive, asked_as_it_restarts, eventually, frozen, restart_after_kill
from sample_modules import (
    ArrayHolder,
    ArraySource,
    AsksInSetup,
    BlocksInInit,
    BlocksOnceInInit,
    Chatterbox,
    Collector,
    Counter,
    Crasher,
    CrashesWhileFlagged,
    Faulty,
    FloatSource,
    Freezer,
    HeldInTeardown,
    Hoard,
    InputFreezer,
    Journal,
    Last,
    MapMaker,
    Scale,
    SlowTeardown,
    Steady,
    StepStamps,
)

import examples.pipeline
from pb3a import (
    ConfigError,
    Input,
    InputPort,
    Module,
    Output,
    RuntimeFailure,
    RuntimeTimeout,
    System,
    processes,
)
from pb3a.cli.status import format_table
from pb3a.config.plan import FlatLink, FlatModule
from pb3a.deadline import bounding
from pb3a.launch.launcher import _link_table, _silenced
from pb3a.loading.sources import CodeSources
from pb3a.model.module import restore_state
from pb3a.model.ports import Policy
from pb3a.node.executor import Executor
from pb3a.node.forkserver_owner import ORPHAN_GRACE_S
from pb3a.node.restarts import RESTART_INTENSITY, RestartBudget, Restarts
from pb3a.stats import ModuleStats, NodeReport, SystemStats
from pb3a.transport.doorbell import new_bell
from pb3a.transport.ring import ShmRing
from pb3a.transport.shm import live_segments, segment_name
from pb3a.worker.inbound import GUARD_TIMEOUT, InboundLink
from pb3a.worker.process import Worker

pytestmark = pytest.mark.timeout(120)


def test_exception_in_step_is_logged_counted_and_contained(caplog) -> None:
    caplog.set_level(logging.ERROR, logger="pb3a.module")
    system = System("faults")
    system.add("faulty", Faulty)
    system.add("src", FloatSource)
    system.add("scale", Scale)
    system.add("sink", Last)
    system.link("src.out", "scale.x")
    system.link("scale.y", "sink.x")
    with system.launch() as run:
        state = eventually(lambda: (s := run.state("faulty"))["good"] >= 10 and s, what="steps")
        eventually(lambda: run.state("sink")["value"] == 2.0, what="others unaffected")
        figures = eventually(lambda: (f := run.stats().modules["faulty"]).errors >= 5 and f,
                             what="errors counted")
        eventually(lambda: "odd step" in caplog.text, what="the error in the log")
    # where it was raised, too: the traceback is logged once, and a chatty module beside
    # it soon pushed it out of the log, leaving "ValueError: odd step" and no place
    raised = next(number for number, text in enumerate(
        inspect.getsource(sample_modules).splitlines(), 1) if '"odd step"' in text)
    assert figures.last_error == f"ValueError: odd step (at sample_modules.py:{raised} in step)"
    assert figures.status == "running"
    assert state["calls"] >= state["good"] * 2 - 1
    assert "'faulty'" in caplog.text and "step" in caplog.text


def _kill_worker(run, name: str) -> int:
    pid = eventually(lambda: run.stats().modules[name].pid, what="a worker pid")
    os.kill(pid, signal.SIGKILL)
    return pid


def test_a_worker_s_restart_shows_on_its_modules_and_a_read_of_one_waits_for_it(
        monkeypatch) -> None:
    """On an embedded node a worker's restart holds the configuration lock while it
    revives its modules (held here): ``stats()`` answers meanwhile, naming it on the
    modules it restarts, not on the others, and a read of such a module's state waits
    for it (the figures named no change; a read came back before the restart was done
    and said)."""
    system = System("restart-shown")
    system.add("victim", Steady, restart="fresh")
    system.add("other", Steady)
    with system.launch() as run:
        eventually(lambda: run.state("victim")["count"] > 3, what="steps")
        reviving, go, real = threading.Event(), threading.Event(), Restarts._revive

        def revive(self, handle, code):
            reviving.set()
            assert go.wait(30.0)
            return real(self, handle, code)
        monkeypatch.setattr(Restarts, "_revive", revive)
        _kill_worker(run, "victim")
        try:
            assert reviving.wait(10.0)
            stats = run.stats(timeout=1.0)
            with pytest.raises(RuntimeTimeout, match="restart the modules of worker"):
                run.state("victim", timeout=0.2)
            assert run.state("other", timeout=1.0)["count"] > 0
        finally:
            go.set()
        eventually(lambda: (m := run.stats().modules["victim"]).restarts == 1
                   and not m.change, what="the restart done")
    assert stats.modules["victim"].change.startswith("restart the modules of worker ")
    assert stats.modules["other"].change == ""


def _restarted_after_a_checkpoint(run, name: str, counter: str) -> dict:
    """Once module ``name``'s ``counter`` passed 40 and a checkpoint was taken after,
    SIGKILL its worker; its state once restarted, read in the new process."""
    eventually(lambda: run.state(name).get(counter, 0) > 40, what="steps")
    taken = run.stats().modules[name].checkpoints
    eventually(lambda: run.stats().modules[name].checkpoints > taken,
               what="a checkpoint taken after 40 steps")
    old = _kill_worker(run, name)
    eventually(lambda: run.stats().modules[name].restarts == 1, what="restart")
    return eventually(lambda: (s := run.state(name))["pid"] not in (0, old) and s,
                      what="steps in the new process")


def test_a_request_in_the_restart_window_waits_for_the_restart() -> None:
    """Asked just as its worker died, a module's state is set and read in the restarted
    process (both failed at once, on the dead worker's broken pipe); with ``never``,
    the request fails saying the module failed, not that a pipe broke."""
    system = System("window")
    system.add("victim", Steady, restart="fresh")
    system.add("never", Steady, restart="never")
    with system.launch() as run:
        eventually(lambda: run.state("victim")["count"] > 3, what="steps")
        old, state = asked_as_it_restarts(run, "victim")
        assert state["count"] >= 10**6 and state["pid"] not in (0, old), state
        assert run.stats().modules["victim"].restarts == 1
        with pytest.raises(RuntimeFailure, match=r"^module 'never' is not running: it failed"):
            asked_as_it_restarts(run, "never")


def test_sigkill_with_restart_never_leaves_module_failed_and_others_running() -> None:
    system = System("never")
    system.add("victim", Steady, restart="never")
    system.add("other", Steady)
    with system.launch() as run:
        eventually(lambda: run.state("victim")["count"] > 3, what="steps")
        _kill_worker(run, "victim")
        figures = eventually(lambda: (m := run.stats().modules)["victim"].status == "failed"
                             and m, what="failure detected")
        before = run.state("other")["count"]
        eventually(lambda: run.state("other")["count"] > before, what="the other module goes on")
        assert any(re.match(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d module victim failed", f)
                   for f in run.stats().failures)
        failed = [e for e in run.events() if e.kind == "module_failed"]
        with pytest.raises(RuntimeFailure,
                           match=r"^module 'victim' is not running: it failed \(`pb3a status`"):
            run.state("victim")                 # (said of the module, not of its worker)
        run.restart("victim")                   # asked: it runs again, fresh
        eventually(lambda: run.state("victim")["count"] > 3, what="the restarted victim steps")
        assert run.stats().modules["victim"].status == "running"
        assert run.events()[-1].kind == "module_restarted"
    assert figures["victim"].restarts == 0
    assert [e.subject for e in failed] == ["victim"]
    assert failed[0].detail["reason"] == "restart = 'never'"


def test_a_module_left_failed_beside_a_restarted_one_restarts_when_asked() -> None:
    """A worker of two modules dies: the ``fresh`` one comes back in a new process, the
    ``never`` one stays failed; asked, it restarts, its link wired again (it was lost:
    its worker had no such module to remove)."""
    system = System("never-beside-fresh")
    system.add("src", FloatSource, restart="fresh", group="pair")
    system.add("victim", Last, restart="never", group="pair")
    system.link("src.out", "victim.x")
    with system.launch() as run:
        eventually(lambda: run.state("victim")["value"] == 1.0, what="a value")
        _kill_worker(run, "victim")
        eventually(lambda: (m := run.stats().modules)["victim"].status == "failed"
                   and m["src"].status == "running", what="src restarted, victim failed")
        run.restart("victim")
        run.set_state("src", value=2.0)
        eventually(lambda: run.state("victim")["value"] == 2.0, what="values through again")
        assert set(run.stats().links) == {"src.out->victim.x"}


def test_a_group_whose_modules_all_stay_failed_takes_them_back_and_new_ones() -> None:
    """A worker of two ``never`` modules dies: both stay failed; asked, each restarts,
    and a module added to their group runs (the dead worker was not replaced, so it was
    'not running' to both)."""
    system = System("never-pair")
    system.add("a", Steady, restart="never", group="pair")
    system.add("b", Steady, restart="never", group="pair")
    with system.launch() as run:
        eventually(lambda: run.state("a")["count"] > 3, what="steps")
        _kill_worker(run, "a")
        eventually(lambda: {m.status for m in run.stats().modules.values()} == {"failed"},
                   what="both failed")
        run.restart("a")
        run.add("c", Steady, group="pair")
        eventually(lambda: run.state("a")["count"] > 3 and run.state("c")["count"] > 3,
                   what="the restarted and the added module step")
        assert run.stats().modules["b"].status == "failed"


def test_a_module_whose_restarts_ran_out_restarts_when_asked(tmp_path: Path) -> None:
    flag = tmp_path / "crash"
    flag.touch()
    system = System("ran-out")
    system.add("crasher", CrashesWhileFlagged, restart="fresh", state={"flag": str(flag)})
    with system.launch() as run:
        eventually(lambda: run.stats().modules["crasher"].status == "failed", timeout=30,
                   what="giving up")
        flag.unlink()                               # mended: asked, it runs again
        run.restart("crasher")
        eventually(lambda: run.state("crasher")["steps"] > 3, what="the restarted module steps")
        assert run.stats().modules["crasher"].status == "running"


def test_sigkill_with_restart_fresh_starts_from_the_configured_state() -> None:
    system = System("fresh")
    system.add("victim", Steady, restart="fresh", state={"count": 1000})
    with system.launch() as run:
        eventually(lambda: run.state("victim")["count"] > 1100, what="steps")
        old = _kill_worker(run, "victim")
        figures = eventually(lambda: (m := run.stats().modules["victim"]).restarts == 1
                             and m.status == "running" and m, what="restart")
        state = eventually(lambda: (s := run.state("victim"))["pid"] not in (0, old) and s,
                           what="steps in the new process")
        restarted = [(e.kind, e.subject, e.detail["policy"], "from_checkpoint" in e.detail)
                     for e in run.events()]
    assert figures.pid != old
    assert 1000 < state["count"] < 1100       # from the configured state, not from 1100
    assert restarted == [("module_restarted", "victim", "fresh", False)]


def test_sigkill_with_restart_last_state_resumes_from_a_checkpoint() -> None:
    system = System("last")
    system.add("victim", Steady, restart="last-state")
    with system.launch(checkpoint_s=0.1) as run:
        state = _restarted_after_a_checkpoint(run, "victim", "count")
        restarted = eventually(lambda: [e.detail for e in run.events()], what="the restart said")
    assert state["count"] > 40            # resumed from the checkpoint, not from 0
    assert [(e["policy"], e["from_checkpoint"]) for e in restarted] == [("last-state", True)]


class Guarded(Module):
    """Steps with a lock in its state: no checkpoint of it can be taken."""

    period = 0.01
    count = 0
    guard = None

    def setup(self) -> None:
        self.guard = threading.Lock()

    def step(self) -> None:
        self.count += 1


def test_a_last_state_module_restarted_with_no_checkpoint_says_it_lost_its_state(
        caplog) -> None:
    """Its state could not be pickled: it came back with its configured state, and the
    restart said nothing of it (only its first checkpoint's error, at its start)."""
    caplog.set_level(logging.WARNING)
    system = System("no-checkpoint")
    system.add("guarded", Guarded, restart="last-state")
    with system.launch(checkpoint_s=0.05) as run:
        eventually(lambda: any("cannot checkpoint module 'guarded'" in e.message
                               for e in run.logs()), what="the failed checkpoint said")
        eventually(lambda: run.stats().modules["guarded"].steps > 20, what="steps")
        _kill_worker(run, "guarded")
        restarted = eventually(lambda: [e.detail for e in run.events()], what="the restart said")
    assert [(e["policy"], e["from_checkpoint"]) for e in restarted] == [("last-state", False)]
    assert "module 'guarded' restarted with its configured state, not its last one" \
        in caplog.text


def test_a_last_state_restart_brings_back_the_state_the_module_made_as_it_ran() -> None:
    """State made in ``setup`` and ``step`` (``grid``, ``updates``) is in the checkpoint:
    the restart refused it (a name the new instance lacks) and failed the module."""
    system = System("last-made")
    system.add("mapper", MapMaker, restart="last-state")
    with system.launch(checkpoint_s=0.1) as run:
        state = _restarted_after_a_checkpoint(run, "mapper", "updates")
        # (said as the restart ends, which a read of the module's state does not wait for)
        kinds = eventually(lambda: [event.kind for event in run.events()],
                           what="the restart said")
    assert state["updates"] > 40 and state["grid"][0, 0] > 40     # its checkpoint's
    assert state["setups"] == 2 and kinds == ["module_restarted"]


class Smoother(Module):
    """A later version of a module whose field ``smooth`` it made a method."""

    made = 0

    def smooth(self, value: float) -> float:
        return value


def test_a_state_given_back_to_a_class_that_made_a_field_a_method_keeps_the_method() -> None:
    """A checkpoint taken before a swap, restored by a restart into the new class, set
    the old class's ``smooth = 0.5`` over the new class's method: the module ran on,
    failing at every step ("'float' object is not callable")."""
    module = Smoother()
    restore_state(module, {"smooth": 0.5, "made": 3, "grid": [1, 2]})
    assert module.smooth(2.0) == 2.0
    assert module.made == 3 and module.grid == [1, 2]     # the rest, made as it ran too


class NotReady(Module):
    """A module whose own ``get_state`` raises while ``failing`` is set."""

    period = 0.01
    failing = False
    steps = 0

    def step(self) -> None:
        self.steps += 1

    def get_state(self) -> dict:
        if self.failing:
            raise RuntimeError("state not ready")
        return super().get_state()


def test_a_checkpoint_that_fails_once_stops_no_checkpoint_of_its_worker() -> None:
    """Its error was named by asking for the state again, which raised in turn and ended
    the worker's checkpoint thread: no module of that worker was checkpointed again."""
    system = System("checkpoints-go-on")
    system.add("flaky", NotReady, restart="last-state", group="g")
    system.add("good", Steady, restart="last-state", group="g")
    with system.launch(checkpoint_s=0.05) as run:
        run.set_state("flaky", failing=True)
        eventually(lambda: [e for e in run.logs() if "cannot checkpoint module 'flaky'" in
                            e.message and "RuntimeError: state not ready" in e.message],
                   what="the failed checkpoint said")
        run.set_state("flaky", failing=False)
        taken = {name: run.stats().modules[name].checkpoints for name in ("flaky", "good")}
        eventually(lambda: all(run.stats().modules[name].checkpoints > taken[name] + 3
                               for name in taken), what="checkpoints of both going on")


def test_links_survive_a_restart_of_the_reading_worker() -> None:
    system = System("relinked")
    system.add("src", FloatSource, state={"value": 2.0})
    system.add("sink", Last, restart="fresh")
    system.link("src.out", "sink.x")
    with system.launch() as run:
        eventually(lambda: run.state("sink")["value"] == 2.0, what="first value")
        _kill_worker(run, "sink")
        eventually(lambda: run.stats().modules["sink"].restarts == 1, what="restart")
        eventually(lambda: run.state("sink")["value"] == 2.0, what="values after restart")


def test_a_restarted_reader_gets_back_the_array_slots_its_predecessor_held() -> None:
    system = System("held")
    system.add("src", ArraySource)
    system.add("hold", ArrayHolder, restart="fresh")   # holds ten views, never reads
    system.link("src.out", "hold.x")                   # a pool of twelve 1 MiB slots
    with system.launch() as run:
        def held() -> int | None:
            # (none while its worker is being restarted: the figures do not wait for it)
            port = run.stats().modules["hold"].inputs.get("x")
            return None if port is None else port.pending
        eventually(lambda: held() == 10, timeout=30, what="ten views held")
        _kill_worker(run, "hold")
        eventually(lambda: run.stats().modules["hold"].restarts == 1, what="restart")
        # ten slots would still be taken by the dead reader, leaving two
        eventually(lambda: held() == 10, timeout=30, what="ten views held again")


def test_shutdown_is_bounded_even_when_teardown_hangs() -> None:
    system = System("slow")
    system.add("slow", SlowTeardown)
    system.add("ok", Steady)
    run = system.launch()
    eventually(lambda: run.state("ok")["count"] > 2, what="steps")
    started = time.monotonic()
    run.close(timeout=3.0)
    assert time.monotonic() - started < 10.0


_CRASHING_LAUNCHER = textwrap.dedent("""
    import sys, time
    from pb3a import System, Module, Output, Input

    class Tick(Module):
        out = Output(int)
        period = 0.01
        n = 0
        def step(self):
            self.n += 1
            self.out.write(self.n)

    class Sink(Module):
        x = Input(int)
        def on_input(self, port):
            port.read()

    system = System("orphans")
    system.add("tick", Tick)
    system.add("sink", Sink)
    system.link("tick.out", "sink.x")
    run = system.launch()
    pids = [m.pid for m in run.stats().modules.values()]
    print(" ".join(map(str, pids)), flush=True)
    from multiprocessing import util
    print(util.get_temp_dir(), flush=True)      # (where its forkserver's socket is)
    time.sleep(120)
""")


def test_no_processes_segments_or_sockets_survive_a_killed_launcher(tmp_path: Path) -> None:
    """A launcher killed with SIGKILL cannot clean up: its workers end with it, its
    segments are unlinked, and its forkserver removes the socket it listened on, with
    the directory multiprocessing made for it (left in /tmp by every such kill before)."""
    script = tmp_path / "launcher.py"
    script.write_text(_CRASHING_LAUNCHER)
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        pids = [int(p) for p in proc.stdout.readline().split()]
        assert len(pids) == 2
        sockets = Path(proc.stdout.readline().strip())
        assert [entry.name for entry in sockets.iterdir() if entry.is_socket()]
        assert live_segments(proc.pid)
        proc.kill()
        proc.wait(10)
        eventually(lambda: not any(alive(p) for p in pids), timeout=15, what="workers to exit")
        eventually(lambda: not live_segments(proc.pid), timeout=15, what="segments unlinked")
        eventually(lambda: not sockets.exists(), timeout=15,
                   what=f"the forkserver's socket and {sockets} removed")
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stdout.close()


_STUCK_LAUNCHER = textwrap.dedent("""
    import json, sys, time
    sys.path.insert(0, sys.argv[1])
    from sample_modules import Freezer
    from pb3a import System

    system = System("stuck-orphans")
    for name in ("in_teardown", "stopped", "plain"):
        system.add(name, Freezer)
    run = system.launch(timeout=30)
    run.set_state("in_teardown", freeze_in="teardown")
    print(json.dumps({name: m.pid for name, m in run.stats().modules.items()}), flush=True)
    time.sleep(120)
""")


def test_workers_that_do_not_read_their_pipe_end_with_their_killed_owner(
        tmp_path: Path) -> None:
    """A node's process (here a launcher, as a node's executor) killed with SIGKILL
    while a worker of it is stopped (SIGSTOP), and another's module never returns from
    its ``teardown``: neither reads the end of its pipe to the end, and both ran on for
    good, with the forkserver, which each kept alive (a worker holds a write end of the
    forkserver's pipe). The forkserver, which watches its owner, now ends them (SIGTERM,
    then SIGKILL ``ORPHAN_GRACE_S`` later), and then itself."""
    script = tmp_path / "launcher.py"
    script.write_text(_STUCK_LAUNCHER)
    proc = subprocess.Popen([sys.executable, str(script), str(Path(__file__).parent)],
                            stdout=subprocess.PIPE, text=True)
    pids: dict[str, int] = {}
    try:
        pids = json.loads(proc.stdout.readline())
        assert set(pids) == {"in_teardown", "stopped", "plain"}
        (forkserver,) = {psutil.Process(pid).ppid() for pid in pids.values()}
        os.kill(pids["stopped"], signal.SIGSTOP)
        proc.kill()
        proc.wait(10)
        eventually(lambda: not any(alive(pid) for pid in pids.values()),
                   timeout=ORPHAN_GRACE_S + 5, what="every worker of the killed owner ended")
        eventually(lambda: not alive(forkserver), what="its forkserver ended")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        proc.stdout.close()
        for pid in pids.values():                       # (left by a failure)
            with contextlib.suppress(psutil.Error):
                psutil.Process(pid).kill()


def test_a_close_kills_a_worker_it_retired_in_the_background(tmp_path: Path) -> None:
    """A worker retired without waiting (``retire(wait=False)``: an add that ran out of
    time, a worker a move left empty) is stopped by a thread of its own: told to exit,
    2 s; SIGTERM, 1 s; SIGKILL. A close waited for that thread until its deadline only,
    so the worker outlived it (by seconds) and, if the closing process exited then, the
    thread that was to kill it went with it. Now the close kills it once its time is up."""
    cls = type("Blocker", (BlocksInInit,), {"pid_file": str(tmp_path / "pid")})
    executor = Executor("n1", code=CodeSources())
    try:
        with bounding(1.0), pytest.raises(RuntimeTimeout):    # (its __init__ blocks 30 s)
            executor.add_module(FlatModule("blocker", cls, "n1", 0.1, {}, "never"))
        pid = int((tmp_path / "pid").read_text())
        assert alive(pid)
    finally:
        began = time.monotonic()
        executor.shutdown(timeout=0.5)
        took = time.monotonic() - began
    assert not alive(pid)
    assert took < 3.0, f"the close took {took:.2f} s"      # (not the module's 30 s)


def test_an_add_whose_module_blocks_in_its_construction_keeps_its_timeout(
        tmp_path: Path) -> None:
    """``add(timeout=1)`` of a module whose construction does not end gives up after 1 s
    (it waited for the worker's usual 10 s), adds nothing, and the rest runs on; the
    close kills the worker it left."""
    cls = type("Blocker", (BlocksInInit,), {"pid_file": str(tmp_path / "pid")})
    system = System("add-blocks")
    system.add("tick", Counter, period=0.01)
    with system.launch() as run:
        began = time.monotonic()
        with pytest.raises(RuntimeTimeout, match="did not answer 'add' within 1 s"):
            run.add("blocker", cls, timeout=1)
        took = time.monotonic() - began
        pid = int((tmp_path / "pid").read_text())
        assert "blocker" not in run.configuration()["system"]["modules"]
        steps = run.state("tick")["count"]
        eventually(lambda: run.state("tick")["count"] > steps, what="tick steps on")
    assert took < 4.0, f"the add took {took:.2f} s"        # (not the module's 30 s)
    assert not alive(pid)


def test_a_worker_timeout_says_its_seconds_as_a_person_would() -> None:
    """What is left of a caller's deadline, 0.999 s of 1 s, was said "0.999 s", and,
    written to two figures, 120 s was "1.2e+02 s"."""
    from pb3a.deadline import spoken

    assert [spoken(s) for s in (0.999, 0.3, 2.5, 10.0, 99.6, 120.0, 0.05)] == [
        "1", "0.3", "2.5", "10", "100", "120", "0.05"]


def test_a_restart_whose_new_construction_blocks_keeps_its_timeout(tmp_path: Path) -> None:
    """``restart(timeout=1)`` of a module whose new construction does not end gives up
    on it after 1 s (it waited the worker's usual 10 s) and puts the module back as it
    ran; the close kills the worker it left."""
    flag = tmp_path / "block"
    cls = type("BlocksOnce", (BlocksOnceInInit,), {
        "flag": str(flag), "pid_file": str(tmp_path / "pid")})
    system = System("restart-blocks")
    system.add("tick", Counter, period=0.01)
    system.add("once", cls)
    with system.launch() as run:
        flag.touch()
        began = time.monotonic()
        with pytest.raises(RuntimeFailure, match=r"did not answer 'add' within .*; it was "
                                                 r"put back as it ran"):
            run.restart("once", timeout=1)
        took = time.monotonic() - began
        pid = int((tmp_path / "pid").read_text())
        assert run.stats().modules["once"].status == "running"
        steps = run.state("tick")["count"]
        eventually(lambda: run.state("tick")["count"] > steps, what="tick steps on")
    assert took < 4.5, f"the restart took {took:.2f} s"    # (not the module's 30 s)
    assert not alive(pid)


def test_a_restarted_agent_may_ask_the_runtime_from_setup() -> None:
    """A restart runs ``setup`` without the configuration lock, as a launch does: an
    agent whose ``setup`` calls ``self.runtime`` restarts at once (not when its start
    request times out, 10 s later), is reported running and its restart is an event."""
    system = System("restart-asks")
    system.add("other", Steady)
    system.add("asker", AsksInSetup, restart="fresh")
    with system.launch() as run:
        eventually(lambda: run.state("asker")["steps"] > 2, what="the agent steps")
        events, state, took = restart_after_kill(run, "asker")
        figures = run.stats().modules["asker"]
        failures = run.stats().failures
    assert [(e.kind, e.subject, e.detail["policy"]) for e in events] == [
        ("module_restarted", "asker", "fresh")]
    assert took < 5.0, took
    assert state["asked"] > 0                          # its setup was answered
    assert (figures.status, figures.running, figures.restarts) == ("running", True, 1)
    assert failures == []


def test_a_restart_that_fails_leaves_the_module_failed_saying_why(tmp_path: Path) -> None:
    """A restart that fails halfway (here the new instance cannot be made) fails the
    module, with the reason, as a status and a ``module_failed`` event, and stops the
    worker it had started (its pid gone once the event is told)."""
    refuse, refused_in = tmp_path / "refuse", tmp_path / "refused_in"

    class Fragile(Steady):
        def __init__(self) -> None:
            if refuse.exists():
                refused_in.write_text(str(os.getpid()))    # the restart's new worker
                raise RuntimeError("no second instance")
            super().__init__()

    system = System("restart-fails")
    system.add("fragile", Fragile, restart="fresh")
    system.add("other", Steady)
    with system.launch() as run:
        eventually(lambda: run.state("fragile")["count"] > 2, what="steps")
        since = max((event.seq for event in run.events()), default=0)
        refuse.touch()
        _kill_worker(run, "fragile")
        events = run.events(since, timeout=5.0)        # waits for the first one
        new_worker = int(refused_in.read_text())
        assert not alive(new_worker), "the worker of the failed restart runs on"
        figures = run.stats().modules["fragile"]
        before = run.state("other")["count"]
        eventually(lambda: run.state("other")["count"] > before, what="the other goes on")
    assert [(e.kind, e.subject) for e in events] == [("module_failed", "fragile")]
    assert "its restart failed" in events[0].detail["reason"]
    assert "no second instance" in events[0].detail["reason"]
    assert (figures.status, figures.running, figures.pid) == ("failed", False, None)


def test_a_worker_stopped_by_sigterm_is_stopped_not_restarted(
        caplog: pytest.LogCaptureFixture) -> None:
    """... with what its module did kept (its worker tells it as it stops), and a
    warning, since its node does not stop (a SIGTERM to the whole group stops both: no
    warning then, see test_cli_run.py)."""
    system = System("terminated")
    system.add("victim", Steady, restart="fresh")
    system.add("other", Steady)
    with caplog.at_level(logging.WARNING, logger="pb3a.executor"), system.launch() as run:
        pid = eventually(lambda: run.stats().modules["victim"].pid, what="a pid")
        eventually(lambda: run.stats().modules["victim"].steps > 0, what="steps")
        os.kill(pid, signal.SIGTERM)
        figures = eventually(lambda: (m := run.stats().modules["victim"]).status
                             == "stopped" and m, what="the stop seen")
        before = run.state("other")["count"]
        eventually(lambda: run.state("other")["count"] > before, what="the other goes on")
        eventually(lambda: any("its modules victim are stopped" in record.getMessage()
                               for record in caplog.records), what="the warning")
    assert figures.restarts == 0 and figures.steps > 0 and figures.pid is None


def test_a_sigterm_stops_every_module_of_a_worker_at_once_then_tears_them_down(
        tmp_path: Path) -> None:
    """A fenced node signals its workers: one module's slow teardown must not leave
    the others of its worker stepping (they would run beside their failed-over copies)."""
    stamps, journal = tmp_path / "steps", tmp_path / "journal"
    system = System("halted")
    system.add("stepper", StepStamps, group="g", state={"path": str(stamps)})
    system.add("slow", Journal, group="g",
               state={"path": str(journal), "label": "slow", "teardown_s": 1.0})
    with system.launch() as run:
        pid = eventually(lambda: run.stats().modules["stepper"].pid, what="a pid")
        eventually(stamps.exists, what="steps")
        signalled = time.monotonic()
        os.kill(pid, signal.SIGTERM)
        eventually(lambda: not alive(pid), timeout=10, what="the worker gone")
        gone = time.monotonic()
    last_step = max(float(line.split()[1]) for line in stamps.read_text().splitlines())
    assert gone - signalled >= 1.0                     # the slow teardown ran, whole
    assert journal.read_text().split("\n")[-2] == "stop slow"
    assert last_step - signalled < 0.25, "the stepper stepped during the other's teardown"


def test_a_module_signalled_to_stop_during_its_setup_never_steps(tmp_path: Path) -> None:
    """Halted as its setup ran, it was torn down and then started stepping all the
    same (97 steps, until its worker exited), beside its failed-over copy on a fence."""
    stamps = tmp_path / "steps"
    system = System("halted-in-setup")
    system.add("other", Journal, group="g", state={"path": str(tmp_path / "journal"),
                                                  "label": "other", "teardown_s": 1.0})
    with system.launch() as run:
        adding = threading.Thread(target=_quietly, args=(lambda: run.add(
            "late", StepStamps, group="g", state={"path": str(stamps), "setup_s": 0.6}),),
            daemon=True)
        adding.start()
        pid_file = Path(f"{stamps}.pid")
        pid = int(eventually(lambda: pid_file.exists() and pid_file.read_text(),
                             what="its setup running"))
        os.kill(pid, signal.SIGTERM)
        eventually(lambda: not alive(pid), timeout=10, what="the worker gone")
        adding.join(15)
    assert not stamps.exists(), "it stepped after it was stopped"


def _quietly(change: Callable[[], object]) -> None:
    with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
        change()


def test_modules_start_in_order_and_stop_in_reverse_order(tmp_path: Path) -> None:
    journal = tmp_path / "journal.txt"
    system = System("order")
    for name in ("a", "b", "c"):
        system.add(name, Journal, state={"path": str(journal), "label": name})
    with system.launch():
        pass
    assert journal.read_text().split("\n")[:-1] == [
        "start a", "start b", "start c", "stop c", "stop b", "stop a"]


def test_a_crash_loop_gives_up_after_the_restart_intensity() -> None:
    system = System("crash-loop")
    system.add("crasher", Crasher, restart="fresh")
    system.add("other", Steady)
    with system.launch() as run:
        figures = eventually(lambda: (m := run.stats().modules["crasher"]).status
                             == "failed" and m, timeout=30, what="giving up")
        failures = run.stats().failures
        before = run.state("other")["count"]
        eventually(lambda: run.state("other")["count"] > before, what="the other goes on")
        said = [entry.message for entry in run.logs(since=0)]
    assert figures.restarts == 5
    assert any("gave up" in failure and "crasher" in failure for failure in failures)
    # (it exits 3, which was the code of a worker whose lease lapsed: each death was
    # said to be a worker frozen past its lease)
    assert not [line for line in said if "its lease had been out" in line], said


def test_the_restart_budget_forgets_deaths_older_than_its_window(monkeypatch) -> None:
    """Only deaths within the window count (a module that crashed once an hour was
    failed for good on its sixth crash, had they all been kept). The budget's clock is
    set per death, so no time need pass."""
    now = [0.0]
    monkeypatch.setattr("pb3a.node.restarts.time", types.SimpleNamespace(monotonic=lambda: now[0]))
    limit, window = RESTART_INTENSITY
    hourly = RestartBudget()
    for hour in range(3 * limit):
        now[0] = 3600.0 * hour
        assert hourly.spend(), f"death {hour + 1}, an hour after the one before"
        assert hourly.deaths == 1
    spree = RestartBudget()
    for second in range(limit):                 # as many as it allows, a second apart ...
        now[0] = float(second)
        assert spree.spend()
    now[0] = window + 0.5                       # ... the first now older than the window
    assert spree.spend() and spree.deaths == limit
    now[0] = window + 0.6                       # one more within it is over the budget
    assert not spree.spend()


class CancelledOnce(Steady):
    """Its fifth step raises what is not an ``Exception``."""

    def step(self) -> None:
        super().step()
        if self.count == 5:
            raise asyncio.CancelledError("a task of mine was cancelled")


class ExitsOnce(Module):
    x = Input(int, policy="queue:64")
    seen = 0

    def on_input(self, port: InputPort) -> None:
        port.read()
        self.seen += 1
        if self.seen == 5:
            raise SystemExit("sys.exit() in a handler")


def test_a_body_raising_what_is_not_an_exception_is_counted_and_runs_on() -> None:
    """SystemExit or CancelledError from a body is an error of that body, like any
    other: it must not end the thread that runs it (its step thread, the worker's
    receiver), which would stop the module, or a whole worker's inputs, silently."""
    system = System("base-exceptions")
    system.add("stepper", CancelledOnce)
    system.add("src", Counter, period=0.01)
    system.add("sink", ExitsOnce)
    system.link("src.out", "sink.x")
    with system.launch() as run:
        eventually(lambda: run.state("stepper")["count"] > 10
                   and run.state("sink")["seen"] > 10, what="both go on after raising")
        figures = run.stats().modules
        assert figures["stepper"].errors == 1 and "CancelledError" in figures["stepper"].last_error
        assert figures["sink"].errors == 1 and "SystemExit" in figures["sink"].last_error


class Refusal(Exception):
    """Pickles, but does not unpickle: ``Refusal(message)`` lacks an argument."""

    def __init__(self, code: int, why: str) -> None:
        super().__init__(f"{code}: {why}")


class HoldsUnreadable(Steady):
    def step(self) -> None:
        super().step()
        self.last_refusal = Refusal(503, "busy")


class HoldsLock(Steady):
    def setup(self) -> None:
        self.guard = threading.Lock()           # a public attribute: part of its state


def test_a_state_that_cannot_cross_to_the_launcher_fails_at_once_and_harms_nothing() -> None:
    """A state that cannot be pickled in its worker, or read in the launcher, fails
    that one request at once, saying why; the node still reads its workers and
    restarts a killed one."""
    system = System("unsendable")
    system.add("unreadable", HoldsUnreadable)
    system.add("locked", HoldsLock)
    system.add("other", Steady, restart="fresh")
    with system.launch() as run:
        eventually(lambda: run.state("other")["count"] > 3 and run.stats().modules[
            "unreadable"].steps > 2, what="steps")
        for name, why in (("unreadable", "could not be read here: TypeError"),
                          ("locked", "could not be pickled: TypeError: cannot pickle "
                                     "'_thread.lock' object \\(in 'guard': state that")):
            started = time.monotonic()
            with pytest.raises(RuntimeFailure, match=why):
                run.state(name, timeout=10.0)
            assert time.monotonic() - started < 2.0
        assert run.state("other")["count"] > 3               # the node still answers
        pid = run.stats().modules["other"].pid
        os.kill(pid, signal.SIGKILL)
        eventually(lambda: run.stats().modules["other"].restarts == 1,
                   what="the killed worker restarted")


def test_a_class_whose_attribute_cannot_travel_to_its_worker_is_named_by_check() -> None:
    """A class defined in a script goes to its worker by value, with its attributes: one
    holding a lock failed the launch with pickle's bare ``TypeError``, which named
    neither the module nor the attribute, and then ``check()`` passed it, the launch
    alone refusing it. ``check()``, the launch and an ``add`` to a running system now
    name both."""
    class Guarded(Steady):
        guard = threading.Lock()

    why = (r"its class .*Guarded cannot be sent to its worker: .* \(class attributes "
           r"'guard': make what holds a lock")
    system = System("guarded").add("g", Guarded)
    assert [problem for problem in system.check() if re.search(why, problem)], \
        system.check()
    with pytest.raises(ConfigError, match=r"\[modules\.g\]: " + why):
        system.launch(timeout=10)
    with System("steady").add("s", Steady).launch(timeout=10) as run, \
            pytest.raises(ConfigError, match=why):
        run.add("g", Guarded)


class _CountsPickles:
    """A class attribute that counts how often it is pickled."""

    count = 0

    def __reduce__(self):
        type(self).count += 1
        return (_CountsPickles, ())


def test_a_script_class_used_by_many_entries_is_judged_once_per_check() -> None:
    """``check()`` pickled a script's class for each entry that used it, to see it could
    be sent (a class whose code pulls in large globals was pickled as often)."""
    class Many(Steady):
        counted = _CountsPickles()

    system = System("many")
    for index in range(5):
        system.add(f"m{index}", Many)
    _CountsPickles.count = 0
    assert system.check() == []
    assert _CountsPickles.count == 1


class Tuned(Steady):
    gains: object = None


class _Elsewhere:
    """Unpickles as an import of a module no worker has."""

    def __reduce__(self) -> tuple:
        return importlib.import_module, ("pb3a_not_installed_anywhere",)


def test_a_value_of_the_launcher_s_code_arrives_and_one_a_worker_cannot_read_fails_alone(
        ) -> None:
    """A state value of a class the launcher's script defines (here, in a function)
    travels by value and comes back; one that names a module the worker lacks fails
    that request, saying so, and the worker and its module go on."""

    @dataclasses.dataclass
    class Gains:
        p: float

    system = System("values-by-value")
    system.add("m", Tuned)
    with system.launch() as run:
        run.set_state("m", {"gains": Gains(2.5)})
        assert run.state("m")["gains"].p == 2.5
        with pytest.raises(RuntimeFailure, match=r"could not be read in worker .*"
                                                 r"pb3a_not_installed_anywhere"):
            run.set_state("m", {"gains": _Elsewhere()})
        count = run.state("m")["count"]
        eventually(lambda: run.state("m")["count"] > count, what="it steps on")
        assert run.stats().modules["m"].restarts == 0


class ReportsRefusal(Module):
    """Writes 1, 2, 3 ... and, as its 5th value, one its reader cannot unpickle."""

    out = Output(object)
    period = 0.01
    count = 0

    def step(self) -> None:
        self.count += 1
        self.out.write(Refusal(self.count, "busy") if self.count == 5 else self.count)


class TwoInputs(Module):
    """Counts what arrives on each of two unrelated inputs."""

    a = Input(object, policy="queue:1000")
    b = Input(int, policy="queue:1000")
    got_a = 0
    got_b = 0

    def on_input(self, port: InputPort) -> None:
        port.read()
        if port.name == "a":
            self.got_a += 1
        else:
            self.got_b += 1


@pytest.mark.parametrize("policy", [None, "lossless:8"])
def test_a_value_its_reader_cannot_decode_is_logged_counted_and_skipped(policy,
                                                                        caplog) -> None:
    """One value that pickles in its writer but does not unpickle in its reader is
    dropped there, logged naming its link and counted in the link's drops (a lossless
    link's too: it cannot be delivered); that link and the reader's others go on, and
    the reader does not spin."""
    caplog.set_level(logging.ERROR, logger="pb3a.ring")
    system = System("undecodable")
    system.add("rep", ReportsRefusal)
    system.add("tick", Counter, period=0.01)
    system.add("sink", TwoInputs)
    system.link("rep.out", "sink.a", policy=policy)
    system.link("tick.out", "sink.b")
    with system.launch() as run:
        pid = eventually(lambda: run.stats().modules["sink"].pid, what="the reader's pid")
        reader = psutil.Process(pid)
        eventually(lambda: run.state("sink")["got_a"] >= 10, what="values after the bad one")
        cpu, started = sum(reader.cpu_times()[:2]), time.monotonic()
        eventually(lambda: (s := run.state("sink"))["got_a"] >= 60 and s["got_b"] >= 60,
                   what="both links go on")
        busy = (sum(reader.cpu_times()[:2]) - cpu) / (time.monotonic() - started)
        link = eventually(lambda: (f := run.stats().links["rep.out->sink.a"]).drops and f,
                          what="the bad value counted")
        eventually(lambda: "rep.out->sink.a" in caplog.text, what="the bad value logged")
    assert link.drops == 1
    assert "1 value(s) could not be decoded" in caplog.text and "TypeError" in caplog.text
    assert busy < 0.5, f"the reader's worker is busy {busy:.0%} of the time"


def test_a_link_the_receiver_cannot_read_is_set_aside_while_the_others_flow(caplog) -> None:
    """A ring whose drain fails (a record its writer broke) is logged and left alone for
    a while: the worker's other inputs go on and its receiver does not spin on it."""
    caplog.set_level(logging.ERROR, logger="pb3a.worker")
    owners = [ShmRing.create(segment_name("ring"), 64 * 1024) for _ in range(2)]
    writers = [ShmRing.attach(owner.name) for owner in owners]
    ours, theirs = multiprocessing.Pipe()
    worker = Worker(ours, "key", new_bell(), 3600.0)
    attempts = []
    try:
        writers[0].write(1)
        owners[0]._data[0:4] = bytes(4)            # its length 0: a broken writer
        bad, good = (InboundLink(ShmRing.attach(owner.name), InputPort(TwoInputs.b, "sink"))
                     for owner in owners)
        bad.ring.label = "w.out->sink.bad"
        real_drain = bad.drain
        bad.drain = lambda: attempts.append(time.monotonic()) or real_drain()
        worker.inbound = {"bad": bad, "good": good}
        worker._inbound_changed()
        writers[1].set_bell(worker._bell_fd)
        receiver = worker._threads[0].native_id

        def receiver_cpu() -> float:
            return sum(t.user_time + t.system_time for t in psutil.Process().threads()
                       if t.id == receiver)

        cpu, started = receiver_cpu(), time.monotonic()
        for i in range(100):
            assert writers[1].write(i)
        eventually(lambda: good.port.received == 100, what="the good link's values")
        eventually(lambda: len(attempts) >= 3, what="the bad link tried again")
        elapsed = time.monotonic() - started
        busy = (receiver_cpu() - cpu) / elapsed
    finally:
        worker.shutdown()
        ours.close()
        theirs.close()
        for ring in (*writers, *owners):
            ring.close()
    assert len(attempts) <= elapsed / GUARD_TIMEOUT + 2     # once a guard's sleep
    assert busy < 0.5, f"the receiver is busy {busy:.0%} of the time"
    assert "cannot read link w.out->sink.bad" in caplog.text
    assert "corrupt ring record" in caplog.text


def test_a_start_interrupted_as_it_waits_kills_the_process_that_comes_later(
        monkeypatch) -> None:
    """A Ctrl-C while a worker's start waited for the forkserver left the start going on
    beside it, and the process it made was nobody's: it is killed once it comes."""
    release, killed = threading.Event(), threading.Event()

    class Started:
        def kill(self) -> None:
            killed.set()

        def join(self, timeout: float) -> None:
            pass

    class Interrupted(Exception):
        pass

    def interrupt(*_: object) -> None:
        raise Interrupted

    monkeypatch.setattr(processes, "_start", lambda process: release.wait(10))
    previous = signal.signal(signal.SIGUSR1, interrupt)     # (a Ctrl-C's stand-in)
    try:
        threading.Timer(0.2, signal.pthread_kill,
                        (threading.main_thread().ident, signal.SIGUSR1)).start()
        with pytest.raises(Interrupted):
            processes.start_without_main(Started(), timeout=30)
    finally:
        signal.signal(signal.SIGUSR1, previous)
    assert not killed.is_set()
    release.set()                                   # the forkserver answers, late
    assert killed.wait(5)


def test_overlapping_starts_leave_multiprocessing_s_preparation_as_it_was(monkeypatch) -> None:
    """A start read what it would put back before it took the start lock: a start that
    overlapped another put that one's stand-in back for good, and each overlap (a node's
    spares and its modules' workers start side by side) chained one more; some 300
    launches in one process, and no process could be started (RecursionError)."""
    from multiprocessing import spawn

    real = spawn.get_preparation_data
    monkeypatch.setattr(spawn, "get_preparation_data", real)    # (put back if it fails)
    waiting = threading.Event()               # the second start waits for the lock

    class Lock:
        def __init__(self) -> None:
            self._lock = threading.Lock()

        def __enter__(self) -> None:
            if self._lock.locked():
                waiting.set()
            self._lock.acquire()

        def __exit__(self, *exc: object) -> None:
            self._lock.release()

    class Held:                               # (a start the forkserver answers late)
        def start(self) -> None:
            second.start()
            assert waiting.wait(10)

    class Quick:
        def start(self) -> None:
            pass

    monkeypatch.setattr(processes, "_start_lock", Lock())
    second = threading.Thread(target=processes._start, args=(Quick(),))
    processes._start(Held())
    second.join(10)
    assert spawn.get_preparation_data is real


def test_an_add_whose_worker_the_frozen_forkserver_cannot_start_fails_within_its_deadline(
        monkeypatch) -> None:
    """A forkserver that is frozen (SIGSTOP, hung) answers no request for a worker: the
    add that needs one raised nothing and held the configuration lock for good (every
    later change waited behind it); it fails with ``RuntimeTimeout`` saying why, and the
    node starts workers again once the forkserver runs."""
    import pb3a.node.workers as workers
    monkeypatch.setattr(workers, "SPAWN_TIMEOUT_S", 2.0, raising=False)
    system = System("frozen-forkserver").node("a", spares=0)
    system.add("first", Steady, node="a")
    with system.launch(timeout=5) as run:
        (forkserver,) = [child for child in psutil.Process().children()
                         if "forkserver" in " ".join(child.cmdline()) and child.children()]
        outcome: list[object] = []
        adding = threading.Thread(target=lambda: outcome.append(_outcome(
            lambda: run.add("second", Steady, node="a", timeout=5))), daemon=True)
        forkserver.suspend()
        try:
            started = time.monotonic()
            adding.start()
            adding.join(10)
            took = time.monotonic() - started
        finally:
            forkserver.resume()
        adding.join(30)
        assert took < 10 and isinstance(outcome[0], RuntimeTimeout), outcome
        assert "forkserver" in str(outcome[0])
        assert "second" not in run.stats().modules
        run.add("second", Steady, node="a", timeout=30)       # it starts workers again
        eventually(lambda: run.state("second")["count"] > 0, what="the added module's steps")


def _outcome(call: Callable[[], object]) -> object:
    try:
        return call()
    except Exception as exc:        # (what the call raised, for the test to judge)
        return exc


def test_stats_with_several_frozen_workers_keeps_the_callers_timeout() -> None:
    """A node's report asks all its workers at once, but waited for each answer in turn
    for the whole report timeout: with three workers frozen (SIGSTOP), ``stats()`` (and
    ``pb3a status``) took three times it, 15 s; and it waited that 5 s whatever the
    caller's ``timeout``. One deadline, the caller's, covers them all; the others'
    figures come."""
    system = System("frozen-workers").node("a")
    for index in range(4):
        system.add(f"m{index}", Steady, node="a")
    with system.launch() as run:
        pids = [eventually(lambda i=index: run.stats().modules[f"m{i}"].pid,
                           what="a worker pid") for index in range(3)]
        with frozen(*pids):
            started = time.monotonic()
            stats = run.stats(timeout=1)
            took = time.monotonic() - started
    assert took < 1.5, f"stats took {took:.1f} s"
    assert stats.modules["m3"].steps > 0 and stats.modules["m3"].pid
    assert not stats.modules["m3"].silent
    # a frozen worker's modules are named silent, with their process (shown as running
    # with no process, as if they had none)
    stopped = [stats.modules[f"m{index}"] for index in range(3)]
    assert [(m.pid, m.silent, m.status) for m in stopped] == [
        (pid, True, "running") for pid in pids]
    assert "running (silent)" in format_table(stats)


def test_a_frozen_worker_is_waited_for_once_not_at_every_report() -> None:
    """Each report asked every worker again and waited its whole deadline for one that
    was frozen (SIGSTOP, stuck): every ``stats()`` took its timeout, and the manager's
    live figures, asked twice a second, came every 5 s. A worker that has not answered
    a report's request is silent in the next at once, not asked again; once it answers
    (let run), its figures come again. Meanwhile it shows the figures of its last
    answer (it showed zeros: a module that had stepped a thousand times, none)."""
    system = System("frozen-reports").node("a")
    for name in ("frozen", "steady"):
        system.add(name, Steady, node="a")
    with system.launch() as run:
        before = eventually(lambda: (m := run.stats().modules["frozen"]).steps > 5 and m,
                            what="the module stepping")
        pid = before.pid
        with frozen(pid):
            first = _timed(lambda: run.stats(timeout=1))
            later = [_timed(lambda: run.stats(timeout=1)) for _ in range(3)]
        for _, stats in [first, *later]:
            shown = stats.modules["frozen"]
            assert shown.silent and shown.pid == pid and not shown.running
            assert shown.steps >= before.steps and shown.cpu >= before.cpu, shown
            assert not stats.modules["steady"].silent and stats.modules["steady"].steps > 0
        assert first[0] < 1.5, f"the first report took {first[0]:.1f} s"
        assert max(took for took, _ in later) < 0.5, [round(took, 2) for took, _ in later]
        assert later[-1][1].modules["steady"].steps > first[1].modules["steady"].steps
        answered = eventually(lambda: not (m := run.stats().modules["frozen"]).silent and m,
                              what="the frozen worker's figures once it runs")
        assert answered.pid == pid and answered.steps >= before.steps


def test_a_worker_asked_for_a_report_as_it_stops_is_shown_by_its_last_figures() -> None:
    """A SIGTERM to the whole process group (``timeout``, ``kill -- -PGID``) stops the
    workers as ``pb3a run`` asks for its last table. A worker that had told its last
    figures and ended, but not been seen to (the node's monitor busy), failed the
    table's request at once (its pipe broken), and showed silent: "-" for its links'
    values in that last table. The request waits for the monitor, and the figures the
    worker told answer it."""
    system = System("stopping-reports").node("a")
    system.add("steady", Steady, node="a")
    with system.launch() as run:
        pid = eventually(lambda: (m := run.stats().modules["steady"]).steps and m.pid,
                         what="the worker stepping")
        pool = run._launcher.nodes["a"].workers
        (handle,) = pool.handles.values()
        asked: list[SystemStats] = []
        with handle.read_lock:                   # (the monitor reads nothing of it)
            os.kill(pid, signal.SIGTERM)
            eventually(lambda: not psutil.pid_exists(pid), what="the worker ended")
            asking = threading.Thread(target=lambda: asked.append(run.stats(timeout=5)))
            asking.start()
            eventually(lambda: any(getattr(f, "pb3a_op", "") == "stats"
                                   for f in list(pool._futures.values())) or asked,
                       what="the report waiting")
        asking.join(10)
        (last,) = [stats.modules["steady"] for stats in asked]
        assert not last.silent and last.steps > 0, last


class _RefusesToTravel:
    def __reduce__(self) -> tuple:
        raise ValueError("this object cannot travel")


@pytest.mark.parametrize("value", [_RefusesToTravel(), threading.Lock()],
                         ids=["ValueError", "TypeError"])
def test_a_request_whose_arguments_cannot_be_pickled_fails_at_once_saying_so(
        value: object) -> None:
    """A value that refuses pickling with a ValueError (its own ``__reduce__``) was
    taken for a broken pipe: the request said the worker "is gone", and, once a request
    on a broken pipe was left for the worker's monitor, waited out its whole timeout
    for an answer that never came, then said the module was stuck. Nothing is sent,
    and the request fails at once, saying the arguments cannot be pickled."""
    system = System("unpicklable").node("a")
    system.add("steady", Steady, node="a")
    with system.launch() as run:
        began = time.monotonic()
        with pytest.raises(RuntimeFailure, match="its arguments cannot be pickled"):
            run.set_state("steady", count=value, timeout=6.0)
        assert time.monotonic() - began < 2.0
        assert run._launcher.nodes["a"].workers._futures == {}
        assert run.stats().modules["steady"].running


def _timed(call: Callable[[], object]) -> tuple[float, object]:
    started = time.monotonic()
    result = call()
    return time.monotonic() - started, result


def test_a_killed_forkserver_takes_no_worker_with_it() -> None:
    """The executor watched each worker through the status pipe of the forkserver that
    started it: a forkserver killed (SIGKILL, the OOM killer) closed them all, so every
    worker of the node was taken for dead (exit code 255), its modules restarted or
    failed by their policy, and the live processes stopped. Each worker is watched
    through a pidfd of its own: the modules run on in the same processes, a worker
    killed later is still seen and restarted, and new workers start from a new
    forkserver."""
    system = System("forkserver-killed").node("a", spares=0)
    system.add("kept", Steady, node="a", restart="never")
    system.add("restarted", Steady, node="a", restart="fresh")
    with system.launch(timeout=5) as run:
        pids = {name: eventually(lambda n=name: run.state(n)["pid"], what=f"{name} steps")
                for name in ("kept", "restarted")}
        (forkserver,) = [child for child in psutil.Process().children()
                         if "forkserver" in " ".join(child.cmdline()) and child.children()]
        since = max((event.seq for event in run.events()), default=0)
        forkserver.kill()               # (not reaped here: its owner reaps it, as it restarts it)
        eventually(lambda: forkserver.status() == psutil.STATUS_ZOMBIE, what="its death")
        for name in pids:
            before = run.state(name)["count"]
            eventually(lambda n=name, b=before: run.state(n)["count"] > b + 20,
                       what=f"{name} stepping on")
        assert {name: run.state(name)["pid"] for name in pids} == pids
        assert {m.status for m in run.stats().modules.values()} == {"running"}
        assert [e.kind for e in run.events(since)] == []
        run.add("added", Steady, node="a", timeout=30)         # from a new forkserver
        eventually(lambda: run.state("added")["count"] > 0, what="the added module's steps")
        since = max((event.seq for event in run.events()), default=0)
        os.kill(pids["restarted"], signal.SIGKILL)           # a death is still seen
        assert [e.kind for e in run.events(since, timeout=5.0)] == ["module_restarted"]
        eventually(lambda: run.state("restarted")["pid"] not in (0, pids["restarted"]),
                   what="the restarted module steps in a new process")
        assert run.state("kept")["pid"] == pids["kept"]
    for pid in pids.values():
        eventually(lambda p=pid: not alive(p), what=f"worker {pid} stopped")


def test_a_worker_killed_while_its_forkserver_is_frozen_is_seen_dead(monkeypatch) -> None:
    """Its death was known only from the forkserver's report, which a frozen forkserver
    never sent: the module showed ``running`` with no process behind it. Its own pidfd
    says it ended; its restart needs the forkserver, so it fails within the start's
    deadline, naming the forkserver, and the module runs again once asked."""
    import pb3a.node.workers as workers
    monkeypatch.setattr(workers, "SPAWN_TIMEOUT_S", 2.0)
    system = System("forkserver-frozen-kill").node("a", spares=0)
    system.add("victim", Steady, node="a", restart="fresh")
    with system.launch(timeout=5) as run:
        pid = eventually(lambda: run.state("victim")["pid"], what="victim steps")
        (forkserver,) = [child for child in psutil.Process().children()
                         if "forkserver" in " ".join(child.cmdline()) and child.children()]
        since = max((event.seq for event in run.events()), default=0)
        forkserver.suspend()
        try:
            os.kill(pid, signal.SIGKILL)
            (failed,) = run.events(since, timeout=10.0)
        finally:
            forkserver.resume()
        assert failed.kind == "module_failed" and failed.subject == "victim", failed
        assert "forkserver" in failed.detail["reason"], failed.detail
        run.restart("victim")
        eventually(lambda: run.state("victim")["pid"] not in (0, pid), what="victim again")


def _import_in_a_new_process(tmp_path: Path, module: str, source: str | None,
                             env: dict[str, str] | None = None,
                             then: str = "") -> tuple[int, str, float]:
    """Write ``module`` (unless ``source`` is None: it is written already), import it in a
    new interpreter (a forkserver of its own), run ``then`` there, and return its exit
    code, stderr and time taken; every process whose command line names the module (a
    forkserver preloading it) is killed after, whatever happened."""
    if source is not None:
        (tmp_path / f"{module}.py").write_text(textwrap.dedent(source))
    environment = {**os.environ, **(env or {}),
                   "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path])}
    began = time.monotonic()
    try:
        done = subprocess.run([sys.executable, "-c", f"import {module}\n{then}"], env=environment,
                              capture_output=True, text=True, timeout=60)
        return done.returncode, done.stderr, time.monotonic() - began
    finally:
        left = _kill_every_process_naming(module)
        assert not left, f"processes left behind: {left}"


def _kill_every_process_naming(word: str) -> list[psutil.Process]:
    """SIGKILL every process whose command line holds ``word``, again until none is
    left (a chain of them may start new ones as it is killed); those found first."""
    first: list[psutil.Process] | None = None
    for _ in range(20):
        found = [p for p in psutil.process_iter(["cmdline"])
                 if word in " ".join(p.info["cmdline"] or ())]
        first = found if first is None else first
        if not found:
            break
        for process in found:
            with contextlib.suppress(psutil.Error):
                process.kill()
        psutil.wait_procs(found, timeout=1.0)
    return first or []


def test_a_forkserver_that_hangs_preloading_a_module_is_stopped_with_its_node(
        tmp_path: Path) -> None:
    """A module file that hangs as PB3A's processes import it (waiting for a device, a
    ``sleep``), imported at once by the launcher: the forkserver that preloads it hung
    there, ignoring SIGTERM, every worker start waiting for it; it stayed after the
    system was closed, and after the launcher exited, re-parented to init. A start left
    unanswered stops it (its launch fails, naming what it preloads) and so does the
    node's shutdown: no process of it is left once the system is closed."""
    module = f"hangs_in_the_forkserver_{os.getpid()}"
    code, stderr, took = _import_in_a_new_process(tmp_path, module, """
        import sys
        import time

        import psutil

        import pb3a.node.workers as workers
        from pb3a import Module, RuntimeTimeout, System
        from pb3a.processes import role

        if role() is not None:          # the forkserver preloading this file
            time.sleep(1000)

        class Sink(Module):
            period = 0.1

        def main():                     # (once imported: a launch as it is, refused)
            workers.SPAWN_TIMEOUT_S = 2.0
            system = System("hangs-preloading").node("a", spares=0)
            system.add("sink", Sink, node="a")
            try:
                system.launch(timeout=10).close()
            except RuntimeTimeout as exc:
                print(f"launch failed: {exc}", file=sys.stderr)
            deadline = time.monotonic() + 5
            while [p for p in psutil.Process().children(recursive=True)
                   if __name__ in " ".join(p.cmdline()) and p.status() != "zombie"]:
                if time.monotonic() > deadline:
                    print("the forkserver is left", file=sys.stderr)
                    sys.exit(3)
                time.sleep(0.05)
        """, then=f"{module}.main()")
    assert code == 0, stderr
    assert "launch failed: " in stderr and "does not answer" in stderr, stderr
    assert f"it had not finished importing the modules it preloads ({module}): one of " \
           "them hangs as it is imported? It was stopped" in stderr, stderr
    assert took < 30


def test_a_file_that_launches_a_system_when_imported_fails_naming_it(tmp_path: Path) -> None:
    """A file that defines module classes and launches a system when imported (no
    ``__main__`` guard), imported rather than run: the forkserver preloads the classes'
    file and so launched the system again, whose forkserver imported it again, without
    end (a chain of processes that ignored SIGTERM and outlived the script). A launch
    inside PB3A's own processes is refused. And the launch is refused before anything
    starts: the error came from the forkserver and then from the worker, two tracebacks
    through the launcher's frames; it is said once now, naming the file, its line, the
    class the workers would import it for and the guard, within seconds, and leaves no
    process behind."""
    module = f"launches_at_import_{os.getpid()}"
    code, stderr, took = _import_in_a_new_process(tmp_path, module, """
        from pb3a import Module, System

        class Counter(Module):
            period = 0.05
            count = 0

            def step(self):
                self.count += 1

        system = System("launched-at-import")
        system.add("counter", Counter)
        with system.launch(timeout=10) as run:
            run.wait(0.2)
        """)
    assert code == 1, stderr
    assert f"{module}.py launches system 'launched-at-import' when it is imported " \
           "(line 13), and the workers import it to load module class Counter" in stderr
    assert 'under `if __name__ == "__main__":`' in stderr
    assert stderr.count("Traceback") == 1 and "forkserver" not in stderr \
        and "worker '" not in stderr, stderr
    assert took < 30


def test_a_package_that_launches_as_imported_and_a_console_in_a_class_module_are_told_apart(
        tmp_path: Path) -> None:
    """A launch is refused when the file that makes it is being imported and the workers
    would import it again: the package above the classes' module too (its
    ``__init__`` ran again in every worker, the forkserver's and the worker's tracebacks
    said it at length). Code run in a class module's namespace once it is imported (a
    doctest, a console, pdb), whose frame looks the same, launches as before."""
    package = tmp_path / f"plugin_{os.getpid()}"
    package.mkdir()
    (package / "modules.py").write_text(textwrap.dedent("""
        from pb3a import Module

        class Beat(Module):
            period = 0.05
        """))
    (package / "__init__.py").write_text(textwrap.dedent(f"""
        from pb3a import System
        from {package.name}.modules import Beat

        with System("plugin").add("beat", Beat).launch(timeout=10) as run:
            run.wait(0.1)
        """))
    code, stderr, took = _import_in_a_new_process(tmp_path, package.name, None)
    assert code == 1 and f"{package.name}/__init__.py launches system 'plugin' when it is " \
        "imported (line 5), and the workers import it to load module class Beat" in stderr, \
        stderr
    assert stderr.count("Traceback") == 1 and took < 30, stderr
    console = compile("with System('console').add('tick', Ticker, period=0.05).launch("
                      "timeout=10) as run:\n    ran = run.state('tick')\n", "<console>", "exec")
    namespace = {**vars(examples.pipeline), "System": System}
    exec(console, namespace)
    assert "count" in namespace["ran"], namespace["ran"]


def test_a_class_file_that_raises_only_in_the_forkserver_fails_its_module_naming_it(
        tmp_path: Path) -> None:
    """The forkserver imports the configuration's class files as it starts; one that
    raised there (anything but an ImportError) killed it, and every worker start failed
    with a bare ``EOFError: unexpected EOF``. A new forkserver is started without them:
    the worker imports the file itself, and the module's start fails with the file's own
    error."""
    module = f"raises_in_forkserver_{os.getpid()}"
    code, stderr, took = _import_in_a_new_process(tmp_path, module, """
        import os
        from pb3a import Module, System

        if os.environ.pop("CLASSES_IMPORTABLE", None) is None:
            raise RuntimeError("this file needs CLASSES_IMPORTABLE")

        class Counter(Module):
            period = 0.05

            def step(self):
                pass

        def main():                     # (once imported: a launch as it is, refused)
            system = System("raises-in-forkserver")
            system.add("counter", Counter)
            system.launch(timeout=10).stop()
        """, env={"CLASSES_IMPORTABLE": "1"}, then=f"{module}.main()")
    assert code == 1, stderr
    assert "RuntimeError: this file needs CLASSES_IMPORTABLE" in stderr.splitlines()[-1]
    assert took < 30


def test_two_starts_that_meet_the_same_dying_preloading_forkserver_both_retry(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """A module's worker and a spare can start at once from a forkserver that dies
    preloading the configuration. The first to see it die stopped the preload and
    retried; the second then found the preload already stopped and failed its start
    with "the forkserver ... ended as it started" (seen once in six suite runs). Both
    retry now, and the preload is stopped (and said) once."""
    from pb3a.node import workers

    both_started = threading.Barrier(2, timeout=10)
    first_retried = threading.Event()
    calls: list[str] = []
    lock = threading.Lock()

    def start(process: object, timeout: float) -> None:
        with lock:
            calls.append(str(process))
            attempt = len(calls)
        if attempt <= 2:                       # both meet the forkserver as it dies
            both_started.wait()
            if attempt == 2:                   # ... and this one hears of it late
                assert first_retried.wait(10)
            raise EOFError
        first_retried.set()                    # a retry, from a new forkserver

    monkeypatch.setattr(workers, "start_without_main", start)
    workers._preload(("a_module_that_raises_as_it_is_imported",))
    failures: list[BaseException] = []

    def start_one(name: str) -> None:
        try:
            workers._start_forkserver_child(name)
        except BaseException as exc:           # asserted below, in the test's thread
            failures.append(exc)

    try:
        with caplog.at_level(logging.WARNING, logger="pb3a.executor"):
            threads = [threading.Thread(target=start_one, args=(name,))
                       for name in ("module", "spare")]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join(15)
    finally:
        workers._preload(())
    assert not failures
    assert len(calls) == 4
    assert not workers._preloading_configuration.is_set()
    assert sum("preloaded the configuration" in record.message
               for record in caplog.records) == 1


def test_a_retry_that_meets_a_second_dying_preloading_forkserver_tries_again(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A start made before the preload was dropped may have started a second forkserver
    with it, which dies as the first did: the retry met that one, and the module's start
    failed with "the forkserver ... ended as it started" (one run in three of a loaded
    subset). A start is tried until a forkserver started without the preload answers,
    four times at most."""
    from pb3a.node import workers

    calls: list[str] = []

    def start(process: object, timeout: float) -> None:
        calls.append(str(process))
        if process == "dies" or len(calls) <= 2:    # the first, then the second, die
            raise EOFError

    monkeypatch.setattr(workers, "start_without_main", start)
    workers._preload(("a_module_that_raises_as_it_is_imported",))
    try:
        workers._start_forkserver_child("module")
    finally:
        workers._preload(())
    assert calls == ["module"] * 3
    with pytest.raises(RuntimeFailure, match="ended as it started, 4 times"):
        workers._start_forkserver_child("dies")


def test_a_script_that_never_closes_its_system_stops_it_as_it_exits(tmp_path: Path) -> None:
    """``run = System(...).launch()`` without ``with`` or ``close()``: at the script's
    end the workers went with the interpreter, and the resource tracker warned of leaked
    shared memory. The system is stopped in order as the script exits: its modules'
    teardowns run, and nothing is left. Not by a child the script forks, as it exits."""
    (tmp_path / "never_closed.py").write_text(textwrap.dedent("""
        import os
        from pb3a import Input, Module, Output, System
        from pb3a.transport.shm import live_segments

        class Ticks(Module):
            out = Output(int)
            period = 0.01

            def step(self):
                self.out.write(1)

        class Counts(Module):
            x = Input(int)

            def on_input(self, port):
                port.read()

            def teardown(self):
                print("torn down", flush=True)

        if __name__ == "__main__":
            system = System("never-closed").add("ticks", Ticks).add("counts", Counts)
            run = system.link("ticks.out", "counts.x").launch(timeout=10)
            assert live_segments(os.getpid())
            child = os.fork()              # a child that ends as scripts do: not its to stop
            if child == 0:
                raise SystemExit(0)
            os.waitpid(child, 0)
            assert run.stats().modules["counts"].status == "running"
            print("launched", os.getpid(), run.stats().modules["counts"].pid, flush=True)
        """))
    done = subprocess.run([sys.executable, str(tmp_path / "never_closed.py")], cwd=tmp_path,
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert "leaked" not in done.stderr and "Traceback" not in done.stderr, done.stderr
    launched, torn_down = done.stdout.splitlines()
    assert torn_down == "torn down"
    launcher, worker = (int(pid) for pid in launched.split()[1:])
    eventually(lambda: not alive(worker), what="the worker's end")
    assert not live_segments(launcher)


def test_a_child_the_program_forks_keeps_none_of_its_parents_workers() -> None:
    """A worker is on multiprocessing's list of children from its start until
    ``WatchedProcess`` takes it off; a script that forked in that moment (its system's
    spare workers booting) had its child join that worker as it exited, which failed
    ('can only join a child process') with a traceback: the test above, once, in a
    loaded run. A child the program forks now starts with the list empty."""
    import pb3a.node.watched_process  # noqa: F401  (what pb3a imports: the fork hook)

    worker = multiprocessing.get_context("forkserver").Process(target=time.sleep,
                                                               args=(30,))
    worker.start()                      # on the list, as a worker being started is
    try:
        child = os.fork()
        if child == 0:                  # (nothing else: a fork of a threaded process)
            os._exit(len(multiprocessing.process._children))
        _, status = os.waitpid(child, 0)
        assert os.waitstatus_to_exitcode(status) == 0, "the child had its parent's list"
    finally:
        worker.kill()
        worker.join(5)


def test_check_of_a_file_whose_classes_launch_a_system_as_imported_says_so_at_once(
        tmp_path: Path) -> None:
    """`pb3a check` imports the classes a configuration names: one whose file launches a
    system when imported launched that system inside the check, whose workers then
    refused it, with a forkserver's traceback and the error wrapped three times. The
    launch is refused as the class is loaded, naming the file, its line and the fix."""
    module = f"launches_when_checked_{os.getpid()}"
    (tmp_path / f"{module}.py").write_text(textwrap.dedent("""
        from pb3a import Module, System

        class Counter(Module):
            period = 0.05

        System("launched-when-checked").add("counter", Counter).launch(timeout=10).close()
        """))
    (tmp_path / "checked.toml").write_text(f'[modules.c]\nclass = "{module}:Counter"\n')
    try:
        began = time.monotonic()
        done = subprocess.run([sys.executable, "-m", "pb3a", "check", "checked.toml"],
                              cwd=tmp_path, capture_output=True, text=True, timeout=60,
                              check=False)
        took = time.monotonic() - began
    finally:
        left = _kill_every_process_naming(module)
    assert done.returncode == 1 and not left, (done.stderr, left)
    assert f"{module}.py launches system 'launched-when-checked' when it is imported " \
           f"(line 7), and it was imported to load its class '{module}:Counter'" in done.stdout
    assert "Traceback" not in done.stderr and "forkserver" not in done.stderr, done.stderr
    assert took < 10


def _unread(pid: int) -> int:
    """The most bytes waiting to be read on a Unix socket of process ``pid`` (`ss`)."""
    listing = subprocess.run(["ss", "-xpn"], capture_output=True, text=True, timeout=10,
                             check=True).stdout
    return max([int(line.split()[2]) for line in listing.splitlines()[1:]
                if f"pid={pid}," in line] or [0])


def _pipe_full(pid: int, settled_s: float = 0.25) -> Callable[[], bool]:
    """A check that process ``pid`` has a Unix socket with over 150 kB unread, the same
    for ``settled_s`` seconds (what the writer sends meanwhile waits for room)."""
    seen = {"unread": -1, "since": 0.0}

    def full() -> bool:
        unread, now = _unread(pid), time.monotonic()
        if unread != seen["unread"]:
            seen.update(unread=unread, since=now)
        return unread > 150_000 and now - seen["since"] >= settled_s
    return full


def test_a_worker_stopped_while_its_executor_is_frozen_still_tears_down_and_exits(
        tmp_path: Path) -> None:
    """A stopping worker tells its executor its last figures. With the executor frozen
    and the worker's socket to it full (checkpoints of a large state), that send waited
    for good: the worker stopped by SIGTERM never ran its teardowns nor exited. No send
    of a worker waits for room now, and it gives up on the figures after half a
    second, and on what still waits to go after another half."""
    mark = tmp_path / "torn_down"
    (tmp_path / "frozen_executor.py").write_text(textwrap.dedent(f"""
        import time
        from pb3a import Module, System

        class Big(Module):
            period = 0.01
            restart = "last-state"
            blob = "x" * 150_000          # checkpointed every 50 ms: the socket fills

            def step(self):
                pass

            def teardown(self):
                open({str(mark)!r}, "w").write("torn down")

        if __name__ == "__main__":
            with System("frozen").add("big", Big).launch(checkpoint_s=0.05,
                                                         timeout=10) as run:
                print(run.stats().modules["big"].pid, flush=True)
                while True:
                    time.sleep(1)
        """))
    proc = subprocess.Popen([sys.executable, str(tmp_path / "frozen_executor.py")],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        worker = int(proc.stdout.readline())
        os.kill(proc.pid, signal.SIGSTOP)                      # the executor freezes
        # (full: its last figures will not fit, the stopping worker waits for room)
        eventually(_pipe_full(proc.pid), timeout=10,
                   what="the worker's socket to its frozen executor full")
        stopped = time.monotonic()
        os.kill(worker, signal.SIGTERM)
        eventually(lambda: not alive(worker), timeout=5, what="the worker's exit")
        took = time.monotonic() - stopped
        assert mark.read_text() == "torn down"
        # half a second for the figures, half for what waits as its pipe closes
        assert took < 2.0, f"the worker exited {took:.2f} s after its SIGTERM"
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(proc.pid, signal.SIGCONT)
            os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert not live_segments(proc.pid)


def _bounded(call: Callable[[], object], timeout: float) -> tuple[object, float]:
    """What ``call`` returned or raised, and how long it took; a call still running
    after ``timeout`` is what it returned (a hang)."""
    outcome: list[object] = []
    caller = threading.Thread(target=lambda: outcome.append(_outcome(call)), daemon=True)
    started = time.monotonic()
    caller.start()
    caller.join(timeout)
    return (outcome[0] if outcome else "still waiting"), time.monotonic() - started


def test_a_request_to_a_worker_that_reads_nothing_keeps_its_deadline() -> None:
    """A worker frozen (SIGSTOP, starved, its reader stuck) reads nothing from its pipe.
    A request bigger than the pipe's room (a 4 MiB state) waited for room for good,
    past its timeout and holding the system's lock, and the system's close hung behind
    it. Now: the request that began to go times out, and runs when the worker wakes;
    one that could not begin is withdrawn at its timeout, and never runs; a close with
    the worker still frozen ends."""
    system = System("reads-nothing").node("a")
    system.add("h", Hoard, node="a")
    run = system.launch(timeout=30)
    try:
        pid = eventually(lambda: run.stats().modules["h"].pid, what="the worker's pid")
        zeros = np.zeros(Hoard.shape, np.float32)
        with frozen(pid):
            began, took = _bounded(lambda: run.set_state("h", grid=zeros, timeout=1), 10)
            assert isinstance(began, RuntimeTimeout) and "did not answer" in str(began), began
            assert took < 2, f"the request that began to go took {took:.1f} s"
            queued, took = _bounded(lambda: run.set_state(
                "h", marks=zeros.astype(np.int16), timeout=1), 10)
            assert isinstance(queued, RuntimeTimeout) and "withdrawn" in str(queued), queued
            assert took < 2, f"the request that could not go took {took:.1f} s"
        state = run.state("h", timeout=10)               # (behind the first, which runs)
        assert not state["grid"].any()
        assert np.array_equal(state["marks"], Hoard.expected(0)[1])
        os.kill(pid, signal.SIGSTOP)                     # frozen for good this time
        assert isinstance(_bounded(lambda: run.set_state("h", grid=zeros + 1, timeout=1),
                                   10)[0], RuntimeTimeout)
    finally:
        closed, took = _bounded(lambda: run.close(timeout=2), 30)
    assert closed is None and took < 15, f"close: {closed!r} after {took:.1f} s"
    assert not alive(pid)


def test_a_close_with_a_frozen_worker_keeps_its_timeout() -> None:
    """``close(timeout=1)`` with a worker frozen (SIGSTOP) took 4.6 s: the module's stop
    waited 1 s past its grace, the node's shutdown asked it again (at least 0.5 s, and
    1 s more), and the SIGTERM a stopped process ignores was waited for 1 s before the
    SIGKILL. Now the close ends within its timeout and a moment (0.1 s per worker that
    did not exit), the frozen worker killed, no segment or thread of it left."""
    threads = set(threading.enumerate())
    system = System("close-frozen").node("a")
    system.add("c", Counter, node="a", period=0.01)
    run = system.launch(timeout=30)
    try:
        eventually(lambda: run.stats().modules["c"].steps > 0, what="the module steps")
        pid = run.stats().modules["c"].pid
        os.kill(pid, signal.SIGSTOP)                     # frozen for good
        closed, took = _bounded(lambda: run.close(timeout=1), 30)
    finally:
        run.close()                                      # (nothing, once closed)
    assert closed is None and took < 1.5, f"close: {closed!r} after {took:.2f} s"
    assert not alive(pid)
    assert not live_segments(os.getpid())
    assert [thread.name for thread in set(threading.enumerate()) - threads
            if thread.name.startswith("pb3a")] == []


def test_a_remove_of_a_frozen_module_keeps_its_timeout_and_leaves_it_as_it_was() -> None:
    """``remove(name, timeout=1)`` of a module whose worker is frozen (SIGSTOP) waited a
    fixed 6 s for its stop whatever its timeout. Now it fails within the timeout, saying
    which worker did not answer, and nothing was taken away: the module, its link and
    the other modules are as they were, and it is removed once its worker goes on."""
    system = System("remove-frozen").node("a")
    system.add("c", Counter, node="a", period=0.01)
    system.add("d", Collector, node="a")
    system.link("c.out", "d.x")
    run = system.launch(timeout=30)
    try:
        eventually(lambda: run.stats().modules["c"].steps > 0, what="the module steps")
        pid = run.stats().modules["c"].pid
        os.kill(pid, signal.SIGSTOP)
        try:
            began = time.monotonic()
            with pytest.raises(RuntimeTimeout, match=r"worker 'a/m-c' did not answer "
                               r"'stop' within (1|0\.9\d*) s.*module c was left as it "
                               r"was: remove\('c', force=True\) \(`pb3a remove ADDR c "
                               r"--force`\) kills its worker"):
                run.remove("c", timeout=1)
            took = time.monotonic() - began
        finally:
            os.kill(pid, signal.SIGCONT)
        assert took < 1.5, f"remove took {took:.2f} s"
        topology = run.topology()
        assert set(topology.modules) >= {"c", "d"} and "c.out->d.x" in topology.links
        run.remove("c", timeout=10)
        assert "c" not in run.topology().modules
    finally:
        run.close()


def _frozen_in(run, name: str, where: str) -> int:
    """Module ``name`` (a ``Freezer``) frozen in ``where``: its ``step``, its
    ``teardown`` (the stop a removal asks runs it), or its whole worker stopped
    (SIGSTOP); its worker's pid."""
    pid = run.stats().modules[name].pid
    if where == "stopped":
        os.kill(pid, signal.SIGSTOP)
    else:
        run.set_state(name, freeze_in=where)
    if where in ("step", "on_input"):
        eventually(lambda: run.stats().modules[name].calling == where
                   and run.stats().modules[name].calling_s > 0.1, what=f"a frozen {where}")
    return pid


@pytest.mark.parametrize("where", ["step", "teardown", "stopped"])
def test_a_forced_remove_kills_a_module_that_does_not_answer_and_the_rest_runs_on(
        where: str) -> None:
    """``remove(name, timeout=1)`` of a module frozen in its ``step`` or its ``teardown``
    (or its worker stopped) raised ``RuntimeTimeout`` and left it as it was, with no way
    to get rid of it but closing the system. With ``force=True`` its worker is killed
    once the stop has had its timeout, and the module goes with its links within the
    timeout and a moment; an event says it was killed; the rest of the system runs on,
    its values flowing."""
    system = System("remove-forced").node("a")
    system.add("c", Counter, node="a", period=0.01)
    system.add("d", Collector, node="a")
    system.add("f", Freezer, node="a")
    system.add("g", Collector, node="a")
    system.link("c.out", "d.x")
    system.link("c.out", "f.x")
    system.link("f.out", "g.x")
    run = system.launch(timeout=30)
    try:
        eventually(lambda: run.state("g")["received"] > 0, what="values through f")
        seen = run.events()[-1].seq if run.events() else 0
        pid = _frozen_in(run, "f", where)
        began = time.monotonic()
        run.remove("f", timeout=1, force=True)
        took = time.monotonic() - began
        assert took < 2.0, f"the forced remove took {took:.2f} s"
        assert not alive(pid)
        topology = run.topology()
        assert "f" not in topology.modules and set(topology.links) == {"c.out->d.x"}
        events = run.events(seen)
        assert [(e.kind, e.subject) for e in events] == [
            ("link_removed", "c.out->f.x"), ("link_removed", "f.out->g.x"),
            ("module_removed", "f")]
        assert events[-1].detail["killed"] is True and events[-1].detail["pid"] == pid
        received = run.state("d")["received"]
        eventually(lambda: run.state("d")["received"] > received + 20,
                   what="values still flowing from c to d")
        assert run.stats().modules["c"].status == "running"
    finally:
        closed, took = _bounded(lambda: run.close(timeout=5), 30)
    assert closed is None and took < 10, f"close: {closed!r} after {took:.1f} s"


@pytest.mark.parametrize("where", ["step", "on_input"])
def test_a_remove_asked_again_of_a_module_stuck_in_its_step_waits_for_it_again(
        where: str) -> None:
    """A second plain ``remove`` after one that timed out (the module frozen in its
    ``step``) answered at once, and the module was dropped with its links, its worker
    retired, its ``teardown`` never run, and no word of a kill: it was taken for
    stopped, as the first had asked it to stop. Now it waits for it again and fails the
    same way, leaving it as it was; ``force`` then kills its worker. A module stuck in
    ``on_input`` is told apart the same way (even its first remove killed its worker,
    unsaid), and the error says what it is busy in."""
    system = System("remove-again").node("a")
    system.add("c", Counter, node="a", period=0.01)
    system.add("f", Freezer if where == "step" else InputFreezer, node="a")
    system.link("c.out", "f.x")
    run = system.launch(timeout=30)
    try:
        pid = _frozen_in(run, "f", where)
        for _ in range(2):
            began = time.monotonic()
            with pytest.raises(RuntimeTimeout, match=rf"module 'f' did not stop within .* "
                                                     rf"busy in {where} for .*module f "
                                                     r"was left as it was"):
                run.remove("f", timeout=1)
            took = time.monotonic() - began
            assert took < 1.5, f"remove took {took:.2f} s"
            topology = run.topology()
            assert "f" in topology.modules and "c.out->f.x" in topology.links
            assert alive(pid)
        run.remove("f", timeout=1, force=True)
        assert not alive(pid) and "f" not in run.topology().modules
        assert run.events()[-1].detail["killed"] is True
    finally:
        closed, took = _bounded(lambda: run.close(timeout=5), 30)
    assert closed is None and took < 10, f"close: {closed!r} after {took:.1f} s"


def test_a_close_names_a_module_stuck_in_on_input_whose_teardown_did_not_run(
        caplog: pytest.LogCaptureFixture) -> None:
    """A module stuck in ``on_input`` was stopped at close by killing its worker, its
    ``teardown`` never run, nothing said (its stop answered False, taken for stopped).
    Now the close names it in one warning, saying what it is busy in, and
    ``not_torn_down`` lists it (``pb3a run`` then does not say "stopped cleanly")."""
    caplog.set_level(logging.WARNING)
    system = System("close-stuck").node("a")
    system.add("c", Counter, node="a", period=0.01)
    system.add("f", InputFreezer, node="a")
    system.link("c.out", "f.x")
    run = system.launch(timeout=30)
    try:
        pid = _frozen_in(run, "f", "on_input")
    finally:
        closed, took = _bounded(lambda: run.close(timeout=5), 30)
    assert closed is None and took < 10, f"close: {closed!r} after {took:.1f} s"
    assert not alive(pid)
    assert run.not_torn_down == ["f"]
    said = [record.getMessage() for record in caplog.records
            if record.levelno >= logging.WARNING and "'f'" in record.getMessage()]
    assert len(said) == 1, said
    assert re.search(r"module 'f' was not stopped \(its worker is killed\).*busy in "
                     r"on_input for .*its teardown has not run", said[0]), said[0]


def _interrupting_close(run, journal: Path) -> None:
    """A close of ``run`` that a Ctrl-C (SIGINT to the main thread) interrupts as module
    b's teardown has begun, and that teardown still waits (``HeldInTeardown.hold``)."""
    main = threading.main_thread().ident

    def ctrl_c_once_b_tears_down() -> None:
        eventually(lambda: "stopping b" in _journal(journal), timeout=30,
                   what="b's teardown")
        signal.pthread_kill(main, signal.SIGINT)

    interrupter = threading.Thread(target=ctrl_c_once_b_tears_down, daemon=True)
    interrupter.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            run.close(timeout=30)
    finally:
        interrupter.join(35)


def _journal(path: Path) -> list[str]:
    return path.read_text().splitlines() if path.exists() else []


def test_a_close_a_ctrl_c_interrupts_is_finished_by_the_next(tmp_path: Path) -> None:
    """A Ctrl-C as a close waited for a module's teardown left the system half stopped:
    the close had taken the system for stopped as it began, so the next close (the
    ``with`` block's end, the exit's) did nothing. The modules it had not reached ran
    on, their teardowns never run, their workers and segments kept until the process
    ended, and ``not_torn_down`` named none of them. Now they are named until the stop
    is finished, and the next close finishes it: the modules left are stopped in order,
    the one whose teardown the Ctrl-C came in finishes it, those stopped already are not
    stopped again, and every worker and segment is freed."""
    journal, hold = tmp_path / "journal", tmp_path / "hold"
    hold.touch()
    system = System("interrupted-close")
    system.add("tick", Counter, period=0.01)
    for name in ("a", "b", "c"):
        system.add(name, HeldInTeardown, state={
            "path": str(journal), "label": name, "hold": str(hold) if name == "b" else "",
            "after_s": 0.5 if name == "b" else 0.0})
    system.add("sink", Collector)
    system.link("tick.out", "sink.x")
    run = system.launch(timeout=30)
    try:
        pids = [module.pid for module in run.stats().modules.values()]
        eventually(lambda: run.stats().modules["sink"].inputs["x"].received > 0,
                   what="values over the link")
        _interrupting_close(run, journal)
        assert not run.running
        assert run.not_torn_down == ["b", "a", "tick"]
        assert all(alive(pid) for pid in pids) and live_segments(os.getpid())
        hold.unlink()
        run.close(timeout=30)
    finally:
        hold.unlink(missing_ok=True)
        run.close()                                      # (nothing, once closed)
    assert _journal(journal) == ["start a", "start b", "start c", "stopping c", "stop c",
                                 "stopping b", "stop b", "stopping a", "stop a"]
    assert run.not_torn_down == []
    assert not [pid for pid in pids if alive(pid)]
    assert not live_segments(os.getpid())


def test_a_close_a_ctrl_c_interrupts_as_it_ends_the_workers_is_finished_by_the_next() -> None:
    """... also when the Ctrl-C comes once every module is stopped, as the node's
    workers are told to exit, the first just ended: the next close ends the others, the
    spare workers among them, and frees the rings, asking no module to stop again. (The
    spares were taken off the pool's list before they were stopped: one the Ctrl-C left
    ended only once its handle was collected, and a console, which keeps the last
    traceback and the close's frames with it, kept it running.)"""
    system = System("interrupted-workers")
    system.add("tick", Counter, period=0.01)
    system.add("sink", Collector)
    system.link("tick.out", "sink.x")
    run = system.launch(timeout=30)
    try:
        eventually(lambda: run.stats().modules["sink"].inputs["x"].received > 0,
                   what="values over the link")
        (node,) = run._launcher.nodes.values()
        pids = eventually(lambda: len(p := [*node.worker_pids(), *node.workers.spare_pids()])
                          == 4 and p, what="its two modules' workers and two spares")
        stop, stops = node.workers._stop, []

        def interrupted_after_the_first(handle, timeout, until=None):
            stop(handle, timeout, until)
            stops.append(handle.pid)
            raise KeyboardInterrupt

        node.workers._stop = interrupted_after_the_first
        with pytest.raises(KeyboardInterrupt) as interrupted:   # (kept, as by a console)
            run.close(timeout=30)
        node.workers._stop = stop
        assert len(stops) == 1 and run.not_torn_down == []
        assert live_segments(os.getpid())
        run.close(timeout=30)
    finally:
        run.close()                                      # (nothing, once closed)
    assert not [pid for pid in pids if alive(pid)], interrupted
    assert not live_segments(os.getpid())


def test_a_close_a_ctrl_c_interrupts_is_finished_as_the_script_exits(tmp_path: Path) -> None:
    """A script whose close a Ctrl-C interrupted, and that went on to its end: the close
    had let go of the exit's hook as it began, so the modules it had not reached were
    never torn down, and the resource tracker warned of leaked shared memory. The exit
    finishes the stop. The Ctrl-C comes as the close is to stop module b."""
    (tmp_path / "interrupted.py").write_text(textwrap.dedent("""
        import os
        from pb3a import Input, Module, Output, System

        class Noted(Module):
            out = Output(int)
            x = Input(int)
            period = 0.01
            label = ""

            def step(self):
                self.out.write(1)

            def on_input(self, port):
                port.read()

            def teardown(self):
                print("torn down", self.label, flush=True)

        if __name__ == "__main__":
            system = System("interrupted-at-exit")
            for name in ("a", "b", "c"):
                system.add(name, Noted, state={"label": name})
            run = system.link("a.out", "b.x").link("b.out", "c.x").launch(timeout=30)
            print("pids", os.getpid(), *(m.pid for m in run.stats().modules.values()),
                  flush=True)
            (node,) = run._launcher.nodes.values()
            stop_module = node.stop_module

            def interrupted(name, timeout):
                if name == "b":
                    raise KeyboardInterrupt
                stop_module(name, timeout)

            node.stop_module = interrupted
            try:
                run.close()
            except KeyboardInterrupt:
                print("interrupted", *run.not_torn_down, flush=True)
            node.stop_module = stop_module
        """))
    done = subprocess.run([sys.executable, str(tmp_path / "interrupted.py")], cwd=tmp_path,
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert "leaked" not in done.stderr and "Traceback" not in done.stderr, done.stderr
    pids, *said = done.stdout.splitlines()
    assert said == ["torn down c", "interrupted b a", "torn down b", "torn down a"], done.stderr
    launcher, *workers = (int(pid) for pid in pids.split()[1:])
    eventually(lambda: not [pid for pid in workers if alive(pid)], what="the workers' end")
    assert not live_segments(launcher)


def test_the_close_of_a_failed_launch_a_ctrl_c_interrupts_is_finished_as_the_script_exits(
        tmp_path: Path) -> None:
    """A launch that failed (module c's setup raised) closes what it started; a Ctrl-C
    in that close left the modules it had not reached running until the script's end,
    with no handle to close them by (the exit's hook was set once the launch had
    returned), and then their workers' own ends tore them down in no order (a, whose
    teardown is quicker, before b). The exit finishes that close, in order."""
    (tmp_path / "failed.py").write_text(textwrap.dedent("""
        import os
        import time
        from pb3a import Module, System
        from pb3a.node.executor import Executor

        class Noted(Module):
            label = ""

            def setup(self):
                if self.label == "c":
                    raise ValueError("c cannot start")
                print("set up", self.label, os.getpid(), flush=True)

            def teardown(self):
                if self.label == "b":       # (slower: torn down in no order, a is first)
                    time.sleep(0.3)
                print("torn down", self.label, flush=True)

        if __name__ == "__main__":
            system = System("failed-then-interrupted")
            for name in ("a", "b", "c"):
                system.add(name, Noted, state={"label": name})
            stop_module = Executor.stop_module

            def interrupted(node, name, timeout=5.0):
                if name == "b":
                    raise KeyboardInterrupt
                stop_module(node, name, timeout)

            Executor.stop_module = interrupted
            try:
                system.launch(timeout=30)
            except KeyboardInterrupt:
                print("interrupted", flush=True)
            Executor.stop_module = stop_module
            print("launcher", os.getpid(), flush=True)
        """))
    done = subprocess.run([sys.executable, str(tmp_path / "failed.py")], cwd=tmp_path,
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert "leaked" not in done.stderr, done.stderr
    lines = done.stdout.splitlines()
    workers = [int(line.split()[3]) for line in lines if line.startswith("set up")]
    launcher = int(next(line for line in lines if line.startswith("launcher")).split()[1])
    said = [line for line in lines if not line.startswith(("set up", "launcher"))]
    assert len(workers) == 2, done.stdout
    assert said == ["interrupted", "torn down b", "torn down a"], (done.stdout, done.stderr)
    eventually(lambda: not [pid for pid in workers if alive(pid)], what="the workers' end")
    assert not live_segments(launcher)


def test_a_forced_remove_kills_no_worker_that_runs_other_modules() -> None:
    """Killing a worker a module shares with others (a group, packed workers) would lose
    them too: a forced remove of such a module that does not answer is refused, naming
    them and what to do, and everything is left as it was, the others running."""
    system = System("remove-forced-group").node("a")
    system.add("f", Freezer, node="a", group="pair")
    system.add("c", Counter, node="a", period=0.01, group="pair")
    system.add("d", Collector, node="a")
    system.link("c.out", "d.x")
    run = system.launch(timeout=30)
    try:
        eventually(lambda: run.state("d")["received"] > 0, what="values from c")
        pid = _frozen_in(run, "f", "step")
        with pytest.raises(RuntimeFailure, match=r"remove f with force: .*its worker "
                           r"'a/g-pair' was not killed: it also runs c, which would be "
                           r"lost with it .*remove c first, and force then kills it"):
            run.remove("f", timeout=1, force=True)
        assert alive(pid)
        assert set(run.topology().modules) == {"f", "c", "d"}
        received = run.state("d")["received"]
        eventually(lambda: run.state("d")["received"] > received + 20,
                   what="c still running beside the frozen module")
        run.remove("c", timeout=5)
        run.remove("f", timeout=1, force=True)
        assert not alive(pid) and set(run.topology().modules) == {"d"}
    finally:
        closed, took = _bounded(lambda: run.close(timeout=5), 30)
    assert closed is None and took < 10, f"close: {closed!r} after {took:.1f} s"


@contextlib.contextmanager
def _reading_nothing(run: Any, node: str) -> Iterator[None]:
    """Node ``node``'s monitor reads no worker's pipe while inside (as a frozen executor
    would not), then reads on."""
    pool, reading = run._launcher.nodes[node].workers, threading.Event()
    read = pool._read

    def stuck(handle: Any) -> None:
        reading.wait(30)
        read(handle)

    pool._read = stuck
    try:
        yield
    finally:
        pool._read = read
        reading.set()


def test_a_worker_whose_executor_reads_nothing_never_waits_to_send(tmp_path, caplog) -> None:
    """A worker's sends to its executor went through a plain pipe: with the executor
    frozen (for an embedded node, the launcher itself) or its reader stuck, the pipe
    filled, and then a module that logged, or raised, blocked holding its lock, and an
    agent's request hung past its deadline. Now nothing a worker sends waits: log
    records and error reports past a backlog are dropped and counted in a warning once
    the executor reads again, and an agent's request none of which went is withdrawn at
    its timeout and never runs."""
    caplog.set_level(logging.WARNING)
    go, told = tmp_path / "go", tmp_path / "told"
    system = System("executor-reads-nothing").node("a")
    system.add("chatter", Chatterbox, node="a", state={"go": str(go), "told": str(told)})
    with system.launch(timeout=30) as run:
        eventually(lambda: run.stats().modules["chatter"].steps > 0, what="the agent runs")
        with _reading_nothing(run, "a"):
            go.touch()
            eventually(told.exists, timeout=15, what="the agent's request ended")
            took, outcome = told.read_text().split("\n", 1)
        assert "withdrawn and will not run" in outcome, outcome
        assert float(took) < 2.5, f"the request took {float(took):.1f} s"
        eventually(lambda: "log records and error reports of this worker were dropped"
                   in caplog.text, what="the count of what was dropped")
        run.state("chatter", timeout=10)           # (everything sent before it is read)
        assert "late" not in run.stats().modules
    dropped = int(re.search(r"(\d+) log records and error reports", caplog.text)[1])
    chattered = len(re.findall(r"chatter \d+ x", caplog.text))
    assert dropped > 0 and dropped + chattered == 300, (dropped, chattered)


class BigState(Module):
    """A state of 150 kB: two checkpoints fill the pipe to the executor."""

    period = 0.01
    restart = "last-state"
    blob = "x" * 150_000

    def step(self) -> None:
        pass


def test_checkpoints_taken_while_the_executor_reads_nothing_replace_each_other() -> None:
    """While the executor reads nothing, a module's checkpoint replaces its last one
    that waits to go: once it reads again, what reaches it is what was in the pipe and
    the newest (and one or two fresh ones), not every checkpoint taken meanwhile (each
    then went, stale, one after another: a frozen second of a 150 kB state every 50 ms
    was 3 MB to read; half a second, ten more checkpoints)."""
    system = System("checkpoints-replaced").node("a")
    system.add("big", BigState, node="a")
    with system.launch(checkpoint_s=0.05, timeout=30) as run:
        record = run._launcher.nodes["a"].modules["big"]
        eventually(lambda: record.checkpoints > 2, what="checkpoints")
        with _reading_nothing(run, "a"):
            eventually(_pipe_full(os.getpid()), what="the worker's pipe full")
            # (ten checkpoints more are taken while nothing is read)
            before = record.checkpoints
            time.sleep(0.5)
        run.state("big", timeout=10)       # (everything sent before it is read)
        arrived = record.checkpoints - before
    assert arrived <= 6, f"{arrived} checkpoints arrived once the executor read again"


def test_a_silent_node_s_last_figures_leave_out_links_read_elsewhere_since() -> None:
    """A silent node is shown with its last report's figures, but not those of a link
    whose reader has moved off it since: that report's 7 values lost and full ring were
    added to the figures of the node that reads the link now (it lost none)."""
    link = FlatLink("drv", "out", "ctl", "x", Policy.parse("queue"))
    before = NodeReport({"ctl": ModuleStats("m:C", "b", "w1", "running")},
                        {link.key: 65536}, {link.key: 7}, ["12:00:00 ctl failed once"])
    now = NodeReport({"ctl": ModuleStats("m:C", "a", "w2", "running"),
                      "drv": ModuleStats("m:D", "a", "w3", "running")},
                     {link.key: 0}, {link.key: 0}, [])
    silent = _silenced(before, "b", [], read=set())
    (shown,) = _link_table({link.key: link}, dict(now.modules), [now, silent], {}).values()
    assert (shown.ring_bytes_used, shown.link_failures) == (0, 0)
    assert silent.failures == before.failures
    still = _silenced(before, "b", [], read={link.key})
    assert (still.ring_bytes_used, still.link_failures) == ({link.key: 65536}, {link.key: 7})


def test_a_node_whose_report_is_late_shows_its_modules_silent() -> None:
    """``stats(timeout=...)`` waits for each node's report within the caller's timeout;
    a node whose report is late (its executor busy, its link slow) has its modules as
    its last report had them, silent, not dropped from the figures, and with that
    report's figures (they were zeros: 0 steps, 0.0 s of CPU); one that came to it
    since that report (added, moved or failed over there) is shown too (it was left
    out: a failover test beside two busy loops found its module missing), with none."""
    system = System("late-node").node("a").node("b")
    system.add("here", Steady, node="a")
    system.add("late", Steady, node="b")
    with system.launch() as run:
        before = eventually(lambda: (m := run.stats().modules["late"]).steps > 5
                            and m.cpu > 0 and m, what="b's report of a few steps")
        run.add("newcomer", Steady, node="b")
        node = run._launcher.nodes["b"]
        answered, report = threading.Event(), node.report
        node.report = lambda timeout: answered.wait(10) and report(timeout)
        try:
            started = time.monotonic()
            stats = run.stats(timeout=1)
            took = time.monotonic() - started
        finally:
            answered.set()
    assert took < 1.5, f"stats took {took:.1f} s"
    late = stats.modules["late"]
    assert (late.silent, late.running, late.pid, late.node, late.status) == (
        True, False, before.pid, "b", "running")
    # (b's last report, which gave ``before``, or one after it: they grow)
    assert late.steps >= before.steps and late.cpu >= before.cpu > 0, (before, late)
    newcomer = stats.modules["newcomer"]
    assert (newcomer.silent, newcomer.pid, newcomer.node, newcomer.cls) == (
        True, None, "b", "sample_modules:Steady")
    assert stats.modules["here"].steps > 0 and not stats.modules["here"].silent
