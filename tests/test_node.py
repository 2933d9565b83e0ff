"""The node controller: admission by resources, one executor per configuration,
graceful and forced stops, the command line, and frames it must refuse."""

from __future__ import annotations

import collections
import contextlib
import json
import logging
import math
import os
import queue
import re
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import psutil
import pytest
import zmq
from conftest import (
    HeldKey,
    alive,
    daemon_banner_then_clean_exit,
    daemon_signalled_as_it_starts,
    eventually,
    unused_port,
)
from sample_modules import BlocksInInit, Counter, Scale, StepStamps

from pb3a import RuntimeFailure, RuntimeTimeout
from pb3a.config.plan import FlatModule
from pb3a.daemons import executor_family, node_controller
from pb3a.daemons.node_controller import Limits, NodeController, Refused, _context
from pb3a.daemons.node_share import NodeShare, executor_main
from pb3a.loading.sources import CodeSources
from pb3a.node.remote import LEASE_S
from pb3a.processes import start_without_main
from pb3a.transport import control, pickling
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient, ControlServer
from pb3a.transport.shm import live_segments
from pb3a.worker import lease
from pb3a.worker.actor import ModuleActor
from pb3a.worker.lease import LEASE_CHECK_S

KEY = ClusterKey.load()


@pytest.fixture
def node():
    # (no CPU limit: a busy test machine must not make these tests refuse work)
    controller = NodeController("n1", KEY, limits=Limits(max_cpu_percent=101.0))
    client = ControlClient(KEY, controller.address)
    yield controller, client
    client.close()
    controller.close()


def _counter() -> FlatModule:
    return FlatModule("tick", Counter, "n1", 0.001, {}, "never")


def test_one_executor_per_configuration_runs_modules_and_stops_cleanly(node) -> None:
    _, client = node
    address, started = client.call("start_executor", timeout=60, config="demo")
    answered = time.monotonic()          # (its executor started before)
    assert started
    # again: the same, not started now (it may be another launch's: not to be stopped)
    assert tuple(client.call("start_executor", timeout=60, config="demo")) == (address, False)
    executor = ControlClient(KEY, address)

    def apply(op, *args, **kwargs):
        return executor.call("executor", method=op, args=args, kwargs=kwargs)
    try:
        with pytest.raises(RuntimeFailure, match="no operation 'shutdown_everything'"):
            apply("shutdown_everything")
        apply("add_module", _counter())
        executor.call("start", names=["tick"])       # (beside the requests of "executor")
        eventually(lambda: apply("call_module", "tick", "get_state")["count"] > 10,
                   what="the module counting in the node's executor")
        # No launcher bound it, so no lease runs: its worker was given one that nobody
        # renewed, and stopped the module 1.25 s after the executor started. (A wait:
        # what is checked is that nothing happens in it.)
        time.sleep(max(0.0, answered + LEASE_S + 2 * LEASE_CHECK_S - time.monotonic()))
        counted = apply("call_module", "tick", "get_state")["count"]
        eventually(lambda: apply("call_module", "tick", "get_state")["count"] > counted + 10,
                   what="the module counting on past the lease it would have had")
        assert executor.call("describe") == {"config": "demo", "node": "n1",
                                             "modules": ["tick"]}
        assert client.call("status")["executors"] == {"demo": address}
        assert client.call("stop_executor", config="demo") is True
        assert client.call("status")["executors"] == {}
        assert not client.call("stop_executor", config="demo")
    finally:
        executor.close()


def test_a_forced_stop_kills_the_executor(node) -> None:
    controller, client = node
    client.call("start_executor", timeout=60, config="doomed")
    assert client.call("stop_executor", config="doomed", force=True) is True
    assert controller.executors() == {}


_KILLED_OWNER = """
import json, multiprocessing, os, signal
from pb3a.transport.ring import ShmRing
from pb3a.transport.shm import RING, live_segments, reap_child, segment_name
from pb3a.transport.snapshot import make_room

def owner(names):
    ring = ShmRing.create(segment_name(RING), 64, 8, 64)    # on the shared tracker's list
    make_room(segment_name("state"), 4096)                 # a snapshot's: not on it
    names.put(live_segments(os.getpid()))
    signal.pause()

if __name__ == "__main__":
    context = multiprocessing.get_context("spawn")
    names = context.Queue()
    child = context.Process(target=owner, args=(names,))
    child.start()
    made = names.get(timeout=60)
    child.kill()
    child.join(10)
    reaped = reap_child(child.pid)
    print(json.dumps({"made": made, "reaped": sorted(reaped), "left": live_segments(child.pid)}))
"""


def test_a_killed_executors_segments_are_reaped_and_not_called_leaked(tmp_path) -> None:
    """A node controller that had to kill an executor (fenced, frozen) reaped its rings
    but left them on the resource tracker's list, which it shares with its executors:
    when it stopped, the tracker named each "leaked", then failed to unlink it again."""
    script = tmp_path / "owner.py"
    script.write_text(_KILLED_OWNER)
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=60, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    segments = json.loads(done.stdout)
    assert len(segments["made"]) == 2 and segments["reaped"] == segments["made"], segments
    assert segments["left"] == []
    assert "leaked" not in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_a_launcher_on_another_python_is_refused_naming_both_versions(node) -> None:
    """A class sent by value is pickled bytecode: one pickled on 3.12 crashed a 3.13
    worker (a segfault), one from 3.13 failed with an IndexError about its attributes."""
    controller, client = node
    here = f"{sys.version_info.major}.{sys.version_info.minor}"
    with pytest.raises(RuntimeFailure, match=rf"node n1 runs Python {re.escape(here)} and "
                                             r"the launcher Python 2\.7: run one Python "
                                             r"version \(major\.minor\) on every machine"):
        client.call("start_executor", timeout=60, config="old", python="2.7")
    assert controller.executors() == {}
    assert client.call("status", timeout=10)["python"] == here


def test_an_executor_that_dies_as_it_starts_is_reported_at_once(node, monkeypatch) -> None:
    controller, client = node
    monkeypatch.setenv("PB3A_KEY", "too short")          # the executor cannot load its key
    started = time.monotonic()
    with pytest.raises(RuntimeFailure, match="the executor for 'broken' exited with status "
                                             "1 as it started: node n1's log says why"):
        client.call("start_executor", timeout=60, config="broken")
    assert time.monotonic() - started < 15.0                  # not START_TIMEOUT (30 s)
    assert controller.executors() == {}
    monkeypatch.undo()
    address, _ = client.call("start_executor", timeout=60, config="broken")   # it may try again
    assert controller.executors() == {"broken": address}


def test_closing_reaps_an_executor_that_died_on_its_own() -> None:
    controller = NodeController("n1", KEY, limits=Limits(max_cpu_percent=101.0))
    try:
        controller.start_executor("killed")
        process = controller._executors["killed"][0]
        process.kill()
        process.join(5.0)
    finally:
        controller.close()
    assert controller._executors == {}, "its entry and pipe kept"


def test_a_start_served_as_the_controller_closes_starts_nothing() -> None:
    """A start the controller's lane served as it closed (its request came before; close
    waits for the lane) came after close had taken its list of executors to stop: the
    executor it started ran on, stopped by nothing, unbound for 30 s (a test's leak
    check saw it outlive the test)."""
    controller = NodeController("n1", KEY, limits=Limits(max_cpu_percent=101.0))
    controller.close()
    try:
        with pytest.raises(Refused, match=r"node n1's controller is closing: it starts no "
                                          r"executor for 'late'"):
            controller.start_executor("late")
    finally:
        for config in list(controller._executors):     # (what the old code left)
            controller.stop_executor(config)


def test_an_executor_no_launcher_takes_stops() -> None:
    """Its lease begins when a launcher binds it: one whose launcher went as it was being
    started (a Ctrl-C there) ran with no lease, for good."""
    controller = NodeController("n1", KEY, limits=Limits(max_cpu_percent=101.0))
    controller.unbound_s = 1.0
    try:
        controller.start_executor("unbound")
        process = controller._executors["unbound"][0]
        process.join(10.0)
        assert process.exitcode == 0, "it ran on with no launcher"
    finally:
        controller.close()


def test_executors_that_ended_on_their_own_are_forgotten_while_the_controller_runs() -> None:
    """Each executor that ended on its own (its launcher killed, or none took it) kept an
    entry, its pipe and its process's descriptors for as long as the controller ran: a
    node controller up for months ran out of descriptors."""
    controller = NodeController("n1", KEY, limits=Limits(max_cpu_percent=101.0))
    controller.unbound_s = 1.0                       # (none takes them: they end)
    descriptors = psutil.Process().num_fds
    try:
        controller.start_executor("first")           # (what the first start sets up stays)
        eventually(lambda: not controller._executors, timeout=20, what="the first forgotten")
        before = descriptors()
        for name in ("second", "third", "fourth"):
            controller.start_executor(name)
            # (each is asked right after its start: a loaded machine took more than the
            # second it waits unbound to start the next, and the one before had ended)
            assert name in controller._executors
        eventually(lambda: not controller._executors, timeout=20, what="all three forgotten")
        assert descriptors() == before
    finally:
        controller.close()


def test_a_controller_says_its_executor_ended_once_every_process_it_started_has() -> None:
    """A launcher asks a silent node's controller whether its executor ended, to run its
    modules elsewhere at once rather than wait for their lease to run out. The answer is
    how, once the executor and every process it started (its forkserver and workers,
    re-parented as it died: here a process that carries its family's mark) have
    ended, those still alive killed then; nothing while it runs, or for another
    executor's address."""
    controller = NodeController("n1", KEY, limits=Limits(max_cpu_percent=101.0))
    member = None
    try:
        address, _ = controller.start_executor("lab")
        mark = controller._executors["lab"].mark
        member = subprocess.Popen(["sleep", "60"],
                                  env={**os.environ, executor_family.MARK: mark})
        assert [process.pid for process in executor_family.members(mark)] == [member.pid]
        assert controller.executor_ended("lab", address, 1.0) is None      # (it runs)
        assert member.poll() is None
        controller._executors["lab"].process.kill()
        how = eventually(lambda: controller.executor_ended("lab", address, 1.0),
                         timeout=10, what="the executor said ended")
        assert how.startswith("was killed by SIGKILL"), how
        assert member.wait(5) == -signal.SIGKILL and executor_family.members(mark) == []
        assert controller.executor_ended("lab", "tcp://127.0.0.1:1", 1.0) is None
    finally:
        if member is not None and member.poll() is None:
            member.kill()
            member.wait(5)
        controller.close()


def test_a_process_of_the_family_is_found_as_soon_as_it_is_started() -> None:
    """A process in the middle of its ``exec`` shows no environment for a moment, so one
    just started was missed (5 times in 200 on a loaded machine), and left running as
    its family was ended. One just started is looked at again. One whose environment
    is empty for good (``env -i``) is no family's, and once it has run for half a
    second it is not waited for at all (each look waited half a second for it, and a
    family's end, bounded by the launcher's question, gave up)."""
    mark = executor_family.new_mark()
    started: list[subprocess.Popen[bytes]] = []
    try:
        for _ in range(20):
            started.append(subprocess.Popen(["sleep", "60"],
                                            env={**os.environ, executor_family.MARK: mark}))
            assert {p.pid for p in executor_family.members(mark)} == {p.pid for p in started}
        bare = subprocess.Popen(["sleep", "60"], env={})
        started.append(bare)
        # (create_time counts from the boot time in whole seconds: a second more)
        eventually(lambda: time.time() - psutil.Process(bare.pid).create_time() > 1.6,
                   what="the process with no environment running for a while")
        began = time.monotonic()
        assert len(executor_family.members(mark)) == 20
        assert time.monotonic() - began < 0.3
        bare.kill()
        assert executor_family.end(mark, 5.0) and executor_family.members(mark) == []
    finally:
        for process in started:
            process.kill()
            process.wait(5)


def test_an_executor_that_ended_on_its_own_is_logged_with_its_signal_or_status(
        caplog) -> None:
    """An executor the OOM killer killed was forgotten without a word: the node's log,
    where its operator looks first, said nothing, and the launcher only that the node
    went silent, as for a cut cable."""
    controller = NodeController("n1", KEY, limits=Limits(max_cpu_percent=101.0))
    try:
        address, _ = controller.start_executor("lab")
        controller._executors["lab"][0].kill()
        eventually(lambda: not controller._executors, timeout=20, what="the ended forgotten")
    finally:
        controller.close()
    def warnings() -> list[str]:
        return [r.getMessage() for r in caplog.records
                if r.name == "pb3a.node" and r.levelname == "WARNING"]
    assert warnings() == [
        f"node n1: the executor for 'lab' at {address} was killed by SIGKILL, by the "
        "kernel's OOM killer if `journalctl -k` says so; its modules stopped with it"]
    node_controller._log_end("n1", "other", "tcp://127.0.0.1:1", 3)
    node_controller._log_end("n1", "fenced", "tcp://127.0.0.1:2", 0)    # (it said why)
    assert warnings()[1:] == ["node n1: the executor for 'other' at tcp://127.0.0.1:1 "
                              "exited with status 3; its modules stopped with it"]


def test_an_executor_dead_as_its_controller_stops_is_said_as_it_ended(caplog) -> None:
    """An executor killed (the OOM killer) just before its controller stopped was taken
    for a running one: its death went unlogged, and its launcher was told it "was
    stopped: its node controller stopped". It is said as it ended."""
    controller = NodeController("n1", KEY, limits=Limits(max_cpu_percent=101.0))
    try:
        controller.start_executor("lab")
        entry = controller._executors["lab"]
        entry.process.kill()
        entry.process.join(5)                   # (dead before the sampler's next look)
    finally:
        controller.close("SIGTERM")
    assert controller._ended["lab"][1].startswith("was killed by SIGKILL")
    assert any("was killed by SIGKILL" in r.getMessage() for r in caplog.records
               if r.name == "pb3a.node")


def test_work_is_refused_with_the_reason_when_resources_are_short() -> None:
    for limits, reason in ((Limits(max_cpu_percent=101.0, min_memory_bytes=1 << 60),
                            r"of memory available, below .*--min-memory: lower it"),
                           (Limits(max_cpu_percent=-1.0),
                            r"CPU .* busy, above its limit .*--max-cpu: raise it")):
        controller = NodeController("tight", KEY, limits=limits)
        client = ControlClient(KEY, controller.address)
        try:       # as it is said there, with the limit to change (not "... failed: Refused:")
            with pytest.raises(RuntimeFailure, match=f"^node tight refuses .*{reason}"):
                client.call("start_executor", config="demo")
            assert controller.executors() == {}
        finally:
            client.close()
            controller.close()


def test_a_refusal_is_logged_by_the_node_at_most_once_a_minute(monkeypatch, caplog) -> None:
    """A refusal was said only to the launcher: the node's log, where its operator looks
    first, said nothing. It is logged, once a minute, with the refusals not logged since."""
    clock = [1000.0]
    monkeypatch.setattr(node_controller.time, "monotonic", lambda: clock[0])
    controller = NodeController("tight", KEY, limits=Limits(max_cpu_percent=-1.0))
    try:
        for _ in range(3):
            with pytest.raises(Refused):
                controller.admit("an executor for 'demo'")
        clock[0] += 60.0
        with pytest.raises(Refused):
            controller.admit("an executor for 'demo'")
    finally:
        controller.close()
    lines = [r.getMessage() for r in caplog.records
             if r.name == "pb3a.node" and r.levelname == "WARNING" and "refuses" in r.message]
    assert len(lines) == 2, lines
    assert re.fullmatch(r"node tight refuses an executor for 'demo': CPU \d+% busy, above "
                        r"its limit of -1% \(its controller's --max-cpu: raise it, or free "
                        r"the CPU\)", lines[0])
    assert lines[1].endswith("(2 more refused in the last 60 s, not logged)")


def test_admission_judges_the_cpu_over_seconds_not_one_busy_sample(monkeypatch) -> None:
    """The CPU admission looked at was one half-second sample: on a 2-core machine one
    busy moment (94 %) refused launches and failovers at random. It is the mean of the
    last 5 s: a moment's peak is admitted, a load that lasts is refused."""
    readings = iter([20.0] * 9 + [97.0] * 11)
    monkeypatch.setattr(node_controller.psutil, "cpu_percent",
                        lambda interval=None: next(readings))
    monkeypatch.setattr(node_controller, "SAMPLE_S", 3600.0)     # samples taken here only
    controller = NodeController("busy", KEY, limits=Limits(max_cpu_percent=90.0))
    try:
        for _ in range(9):
            controller._cpu = controller._sample_cpu()
        controller.admit("a peak")                    # nine quiet samples and one at 97 %
        for _ in range(10):
            controller._cpu = controller._sample_cpu()
        with pytest.raises(Refused, match=r"CPU 9\d% busy, above its limit of 90%"):
            controller.admit("a load that lasts")
    finally:
        controller.close()


@pytest.mark.parametrize("busy_samples", [2, 3, 4])
def test_admission_admits_a_peak_of_one_or_two_seconds(monkeypatch, busy_samples) -> None:
    """A busy second or two after quiet ones is still a peak: the mean of the last 5 s,
    not of the last one (a window of two samples refused it)."""
    readings = iter([20.0] * 10 + [97.0] * busy_samples)
    monkeypatch.setattr(node_controller.psutil, "cpu_percent",
                        lambda interval=None: next(readings))
    monkeypatch.setattr(node_controller, "SAMPLE_S", 3600.0)     # samples taken here only
    controller = NodeController("busy", KEY, limits=Limits(max_cpu_percent=90.0))
    try:
        for _ in range(9 + busy_samples):          # (its first sample was taken as it began)
            controller._cpu = controller._sample_cpu()
        controller.admit(f"a peak of {busy_samples} samples")
    finally:
        controller.close()


def test_garbage_and_forged_frames_do_not_disturb_the_controller(node) -> None:
    controller, client = node
    attacker = zmq.Context.instance().socket(zmq.DEALER)
    attacker.setsockopt(zmq.LINGER, 0)
    attacker.connect(controller.address)
    attacker.send_multipart([b"garbage"])
    attacker.send_multipart([b"\x00" * 50, b"x", b"y" * 16])
    eventually(lambda: sum(controller.rejected.values()) >= 2, what="the frames refused")
    attacker.close(0)
    assert client.call("status")["node"] == "n1"


def test_the_command_line_runs_a_node_until_signalled() -> None:
    line = daemon_banner_then_clean_exit("node", "start", "--name", "cli",
                                         "--listen", "tcp://127.0.0.1:0")
    assert line.startswith("node cli at tcp://127.0.0.1:")


def test_a_node_signalled_as_it_starts_stops_cleanly(tmp_path) -> None:
    # (its handlers were set once it listened: killed by the signal, it never closed)
    port = unused_port()
    assert daemon_signalled_as_it_starts(tmp_path, "node", "start", "--name", "early",
                                         "--listen", f"tcp://127.0.0.1:{port}") == 0
    with socket.socket() as probe:                     # closed: the port is free again
        probe.bind(("127.0.0.1", port))


def test_an_executor_signalled_as_it_starts_ends_cleanly(tmp_path, monkeypatch) -> None:
    key = HeldKey(tmp_path)
    parent, child = _context.Pipe()
    process = _context.Process(target=executor_main, args=("early", "n1", 0, None,
                                                            "127.0.0.1", child))
    with monkeypatch.context() as env:                 # the child's environment only
        env.delenv("PB3A_KEY")
        env.setenv("PB3A_KEY_FILE", str(key.path))
        start_without_main(process)
    child.close()
    try:
        key.wait_for_reader()
        process.terminate()                            # as its controller stops it
        key.give()
        process.join(20)
        assert process.exitcode == 0
        with pytest.raises(EOFError):                  # it never said it serves
            parent.recv()
        assert not key.users() and not live_segments(process.pid)
    finally:
        if process.is_alive():
            process.kill()
            process.join(5)
        parent.close()


def test_an_executor_whose_lease_is_not_renewed_fences_itself(node) -> None:
    controller, client = node
    address, _ = client.call("start_executor", timeout=60, config="orphan")
    executor = ControlClient(KEY, address)
    try:
        executor.call("bind", launcher="tcp://127.0.0.1:9", checkpoint_s=1.0, log_level=30,
                      code=CodeSources(), lease_s=0.5)        # nobody renews it
        started = time.monotonic()
        assert executor.ping(1.0, op="lease") is not None      # renewed once, at once
        eventually(lambda: controller.executors() == {}, what="the fenced executor gone")
        assert time.monotonic() - started < 3.0
    finally:
        executor.close()


def _blocker(pid_file: Path) -> FlatModule:
    """A module whose construction blocks its worker's control thread (30 s)."""
    cls = type("Blocker", (BlocksInInit,), {"pid_file": str(pid_file)})
    return FlatModule("blocker", cls, "n1", 0.1, {}, "never")


def _executor(client: ControlClient, config: str, lease_s: float) -> ControlClient:
    address, _ = client.call("start_executor", timeout=60, config=config)
    executor = ControlClient(KEY, address)
    executor.call("bind", launcher="tcp://127.0.0.1:9", checkpoint_s=1.0, log_level=30,
                  code=CodeSources(), lease_s=lease_s)
    return executor


def _add_in_background(executor: ControlClient, spec: FlatModule) -> threading.Thread:
    """``add_module`` (which holds the executor's lock until it is answered), in a thread;
    it is expected to fail when the worker or the executor goes."""
    def add() -> None:
        with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
            executor.call("executor", 40.0, method="add_module", args=(spec,), kwargs={})
    thread = threading.Thread(target=add, daemon=True)
    thread.start()
    return thread


def test_a_worker_signalled_in_a_modules_construction_stops(node, tmp_path: Path,
                                                           capfd) -> None:
    """A module's ``__init__`` runs on its worker's control thread: a SIGTERM there once
    failed the request and the worker served on. Its exit is a stop, not a crash (two
    threads reading its exit status at once made one read 255)."""
    _, client = node
    executor = _executor(client, "signalled", lease_s=60.0)
    pid_file = tmp_path / "pid"
    try:
        adding = _add_in_background(executor, _blocker(pid_file))
        pid = int(eventually(lambda: pid_file.exists() and pid_file.read_text(),
                             what="the module being made"))
        os.kill(pid, signal.SIGTERM)
        eventually(lambda: not alive(pid), timeout=5, what="the signalled worker gone")
        adding.join(10)
        assert not adding.is_alive()
    finally:
        executor.call("shutdown")
        executor.close()
    assert "died with exit code" not in capfd.readouterr().err


def test_a_fenced_executor_stops_its_modules_at_once_whatever_holds_its_lock(
        node, tmp_path: Path) -> None:
    """The lease runs out while a request holds the executor's lock (a module being made):
    every module stops stepping within a moment of the fence, not when the request ends."""
    controller, client = node
    lease_s = 1.0
    executor = _executor(client, "fenced-busy", lease_s)
    stamps, pid_file = tmp_path / "steps", tmp_path / "pid"
    renewing, renewed = threading.Event(), [time.monotonic()]

    def renew() -> None:
        while renewing.wait(0.1):
            if executor.ping(0.5, op="lease") is not None:
                renewed.append(time.monotonic())
    renewing.set()
    renewer = threading.Thread(target=renew, daemon=True)
    renewer.start()
    try:
        executor.call("executor", method="add_module",
                      args=(FlatModule("stepper", StepStamps, "n1", 0.01,
                                       {"path": str(stamps)}, "never"),), kwargs={})
        executor.call("start", names=["stepper"])
        eventually(stamps.exists, what="steps")
        adding = _add_in_background(executor, _blocker(pid_file))
        eventually(pid_file.exists, what="the lock held by a module being made")
        renewing.clear()
        renewer.join(2)
        fenced_by = renewed[-1] + lease_s
        eventually(lambda: controller.executors() == {}, timeout=30,
                   what="the fenced executor gone")
        adding.join(10)
    finally:
        renewing.clear()
        executor.close()
    last_step = max(float(line.split()[1]) for line in stamps.read_text().splitlines())
    assert last_step - fenced_by < 0.6, "a module stepped on long after its node was fenced"


def test_a_second_launcher_is_told_when_the_first_is_silent_and_to_try_again() -> None:
    """A launcher run again within a second of the first's SIGKILL was told to stop that
    system first, which no longer existed: its executor was only waiting out its lease.
    One heard from within two heartbeats still runs it: that is said as before."""
    share = NodeShare.__new__(NodeShare)      # (only what a second bind reads)
    share.node, share._lease_s, share.stopped = "b", LEASE_S, threading.Event()
    share.launcher = SimpleNamespace(address="tcp://10.0.0.1:7200")

    def refusal(silent: float) -> str:
        share._leased_at = time.monotonic() - silent
        with pytest.raises(RuntimeFailure) as refused:
            share.bind("tcp://10.0.0.2:7200", 1.0, logging.WARNING, CodeSources())
        return str(refused.value)
    assert refusal(0.9) == (
        "node b already works for tcp://10.0.0.1:7200, last heard from 0.9 s ago: if that "
        "launcher is gone (killed, or cut off), its executor here stops itself once its "
        "lease runs out (1.25 s without it): try again in a moment")
    assert refusal(0.2) == (
        "node b already works for tcp://10.0.0.1:7200: stop that system first, or launch "
        "this one under another name")


def test_a_checkpoint_too_large_to_send_is_not_pickled_again_to_be_refused(
        monkeypatch, caplog) -> None:
    """A module's checkpoint too large for a control message was pickled into a request
    at every checkpoint, only to be refused (a state of 80 MiB: that much copied each
    time on its executor, beside its heartbeats' answers). One no smaller than a refused
    one is refused without that; a smaller one is tried, and sent once it fits. The
    refusal is said once, and again once one was sent since."""
    monkeypatch.setattr(control, "MAX_PAYLOAD", 64 * 1024)        # (small states will do)
    pickled: collections.Counter[str] = collections.Counter()    # requests, by module
    dumps = pickling.dumps

    def counting(obj: Any, **kwargs: Any) -> bytes:
        if isinstance(obj, tuple) and obj[0] == "checkpoint":
            pickled[obj[1]["module"]] += 1
        return dumps(obj, **kwargs)
    monkeypatch.setattr(pickling, "dumps", counting)
    kept: queue.SimpleQueue[tuple[str, int]] = queue.SimpleQueue()
    launcher = ControlServer(KEY, lambda op, args: kept.put((args["module"],
                                                             len(args["state"]))))
    share = NodeShare.__new__(NodeShare)        # (only what sending checkpoints reads)
    share.node, share.node_epoch, share.stopped = "b", 1, threading.Event()
    share._checkpoints, share._checkpointed, share._unsent = {}, threading.Condition(), {}
    share.launcher = ControlClient(KEY, launcher.address)
    sending = threading.Thread(target=share._send_checkpoints, daemon=True)

    def kept_of(size: int) -> int | None:
        """A checkpoint of module big, ``size`` bytes, then one of module small: the size
        of big's the launcher kept (None: it kept none), once small's came."""
        with share._checkpointed:                   # (sent together, in this order)
            share._keep_checkpoint("big", bytes(size))
            share._keep_checkpoint("small", b"s")
        module, kept_size = kept.get(timeout=10)
        if module == "small":
            return None
        assert kept.get(timeout=10) == ("small", 1)
        return kept_size
    sending.start()
    try:
        sizes = [128 << 10] * 3 + [256 << 10, 96 << 10, 1 << 10, 128 << 10]
        kept_sizes = [kept_of(size) for size in sizes]
    finally:
        share.stopped.set()
        with share._checkpointed:
            share._checkpointed.notify()
        sending.join(5)
        share.launcher.close()
        launcher.close()
    assert kept_sizes == [None] * 5 + [1 << 10, None]
    # pickled: the first, the smaller one still too large, the one that fits, and the
    # first too large after it (each was, seven in all)
    assert pickled["big"] == 4, pickled
    said = [record.getMessage() for record in caplog.records
            if "big's checkpoints are not kept" in record.getMessage()]
    assert len(said) == 2, said
    assert said[0].startswith(f"module big's checkpoints are not kept by the launcher "
                              f"('checkpoint' to {launcher.address}: the request is "), said
    assert said[0].endswith("so it was not sent): if node b is lost, the module starts "
                            "afresh where it fails over"), said


def test_a_lapsed_worker_lease_names_both_causes_not_only_a_frozen_executor(
        monkeypatch, caplog) -> None:
    """On a cut cable the executor fences itself and extends its lease no more; the
    worker's line blamed its executor alone ("frozen or hung"), at times before the
    executor's said why. It names both causes, and ends the worker ``GONE_BY_S`` after
    the lease's end whatever its teardowns still do."""
    signals: list[int] = []
    monkeypatch.setattr(lease.os, "kill", lambda pid, number: signals.append(number))
    gone_by: list[float] = []           # (the worker's end, which would end pytest's here)
    monkeypatch.setattr(lease, "_gone_by", gone_by.append)
    board = lease.LeaseBoard.create()
    try:
        end = time.monotonic() - 1.0
        board.write(end)                            # (ran out: the watch finds it at once)
        held = lease.Lease(threading.Event(), lambda: "scale", board)
        held.take()
        # (its line comes last: the stop and the end first, a frozen executor's pipe full)
        eventually(lambda: held.lapsed and gone_by and _said(caplog, "pb3a.worker"),
                   what="the lease lapsed")
    finally:
        board.close()
    assert signals == [signal.SIGTERM]
    assert gone_by == [end + lease.GONE_BY_S]       # gone by then, whatever tears down
    assert [r.getMessage() for r in caplog.records if r.name == "pb3a.worker"] == [
        "the worker of scale: its lease ran out, its executor extending it no more (the "
        "executor fenced itself after losing the launcher, or it is frozen or hung): its "
        "modules stop"]


def test_a_fenced_executor_says_its_lease_to_the_last_digit(caplog) -> None:
    """An executor that fences itself says how long its lease is: it said "(its lease is
    1.2 s)" of a lease of 1.25 s (``LEASE_S``), which the docs give."""
    fenced = threading.Event()
    share = NodeShare.__new__(NodeShare)        # (only what the lease's watch reads)
    share.node, share.stopped, share._lease_s = "b", threading.Event(), LEASE_S
    share._ticked_at = time.monotonic()
    share._leased_at = share._ticked_at - LEASE_S - 0.05         # (ran out just now)
    share.executor = SimpleNamespace(fence=lambda gone_by: fenced.set())
    watch = threading.Thread(target=share._keep_lease, daemon=True)
    watch.start()
    try:
        assert fenced.wait(5), "the executor did not fence itself"
    finally:
        share.stopped.set()
        watch.join(5)
    said = [r.getMessage() for r in caplog.records if "fenced" in r.getMessage()]
    assert len(said) == 1 and re.fullmatch(
        r"node b: no heartbeat from the launcher for \d+\.\d s \(its lease is 1\.25 s\): "
        r"fenced, its modules stop", said[0]), said


def _said(caplog, logger: str) -> bool:
    """Whether ``logger`` has said anything yet."""
    return any(record.name == logger for record in caplog.records)


def test_a_batch_of_on_input_calls_ends_once_its_worker_s_lease_is_out() -> None:
    """Whether the lease holds was asked once per batch of up to 256 ``on_input`` calls:
    a module taking 5 ms a value ran on 1.75 s past its lease's end, beside its
    failed-over copy. It is asked before each call, and the calls not made are owed
    still (they travel with the module)."""
    counted = []

    class Eater(Scale):
        def on_input(self, port) -> None:
            counted.append(port.name)

    actor = ModuleActor("eat", Eater(), lambda task: task(), None)
    actor.running = True
    actor.may_run = lambda: len(counted) < 3        # the lease runs out after 3 calls
    port = actor.inputs["x"]
    port.give_back(10)                              # ten values owed their calls
    assert actor.call_many("on_input", 10, port, claim=port) == 3
    assert port.take_events(100) == 7


def test_a_lease_taken_while_its_executor_is_held_in_a_write_waits_for_the_end(
        monkeypatch) -> None:
    """A worker's first reads of its board met a write under way (its executor preempted
    in it) and got no end (-inf): its modules did not run, and its watch stopped it at
    its first look, its lease a second ahead. Taking the lease waits for an end read
    whole, up to the grace."""
    monkeypatch.setattr(lease.os, "kill", lambda pid, number: None)   # (a lapse)
    monkeypatch.setattr(lease, "_gone_by", lambda deadline: None)
    board = lease.LeaseBoard.create()
    board.write(time.monotonic() + 1.0)
    view = lease.LeaseBoard.opened(os.dup(board.fd))
    board._count += 1                               # a write begun, and held there
    board._store(lease._BEGUN, reversed(range(lease._WIDTH)))
    assert view.end() == -math.inf

    def finish() -> None:
        time.sleep(0.05)                            # (the executor runs again)
        struct.pack_into("d", board._map, lease._END, time.monotonic() + 1.25)
        lease.fence()
        board._store(lease._DONE, range(lease._WIDTH))
    finishing = threading.Thread(target=finish)
    finishing.start()
    closing = threading.Event()
    taken = lease.Lease(closing, lambda: "m", view)
    try:
        taken.take()
        assert taken.holds() and not taken.lapsed
    finally:
        closing.set()
        finishing.join(5)
        view.close()
        board.close()


def test_a_lease_board_read_while_its_executor_writes_never_shows_a_torn_end(
        monkeypatch) -> None:
    """The workers read their lease's end where the executor writes it, with no lock
    between the processes: a read that met a write half done would show an end made of
    two (a far future, say: a lease that never ends). A reader in another process,
    reading while the writer writes as fast as it can two ends that differ in every
    byte, only ever sees one of them, or, while no read has yet found the board between
    two writes, an end long past (``-inf``: a read that keeps meeting writes gets the
    last end read whole). A lease holds while its end is ahead and not after, the end
    it read kept until it passes (every body asks: a read costs about 2 us) and then
    read again; one without a board (an embedded node's workers) or not taken (a
    spare's) always holds."""
    import multiprocessing
    from multiprocessing import reduction

    board = lease.LeaseBoard.create()
    assert board.end() == math.inf                 # no lease before a launcher binds
    context = multiprocessing.get_context("fork")
    ours, theirs = context.Pipe()
    reader = context.Process(target=_read_a_board, args=(theirs,), daemon=True)
    reader.start()
    try:
        reduction.send_handle(ours, board.fd, reader.pid)
        writes = 0
        while not ours.poll():
            board.write(_ENDS[writes % 2])
            writes += 1
        reads, seen = ours.recv()
        assert reads > 1000 and writes > 1000, (reads, writes)
        assert seen <= {math.inf, -math.inf, *_ENDS}, seen
        monkeypatch.setattr(lease.os, "kill", lambda pid, number: None)   # (its lapse)
        monkeypatch.setattr(lease, "_gone_by", lambda deadline: None)
        closing = threading.Event()
        held = lease.Lease(closing, lambda: "m", board)
        assert held.holds()                         # a spare's: not taken
        start = time.monotonic()
        # (ends a second apart: on a loaded machine this thread may wait 0.3 s for the
        # CPU between two lines, and a first end 0.3 s ahead had passed by its check)
        board.write(start + 1.0)
        held.take()
        assert held.holds()                         # (the end read, and kept)
        board.write(start + 2.0)                    # extended: read once the kept end passed
        eventually(lambda: time.monotonic() > start + 1.05, what="the first end passed")
        assert held.holds()
        eventually(lambda: not held.holds(), timeout=5, what="the extended end passed")
        assert time.monotonic() > start + 2.0
        closing.set()
        assert lease.Lease(threading.Event(), lambda: "m").holds()
    finally:
        reader.join(5)
        ours.close()
        theirs.close()
        board.close()


_ENDS = (struct.unpack("d", b"\x11" * 8)[0], struct.unpack("d", b"\x22" * 8)[0])


def _read_a_board(conn) -> None:
    """Read the board sent on ``conn`` for a second; send back how often, and what."""
    from multiprocessing import reduction

    board = lease.LeaseBoard.opened(reduction.recv_handle(conn))
    reads, seen, until = 0, set(), time.monotonic() + 1.0
    while time.monotonic() < until:
        seen.add(board.end())
        reads += 1
    conn.send((reads, seen))


def test_the_sampler_survives_a_turn_that_fails(monkeypatch, caplog) -> None:
    """One burst of idle connections made ``psutil`` fail (EMFILE) in the sampler, and the
    thread died for good: admission judged a frozen CPU figure, and ended executors were
    never forgotten again. The failure is logged once and the sampler goes on."""
    calls: list[float] = []
    real = psutil.cpu_percent

    def cpu_percent(interval=None):
        calls.append(time.monotonic())
        if len(calls) == 2:                          # (the first is the constructor's)
            raise OSError(24, "Too many open files")
        return real(interval=interval)
    monkeypatch.setattr(node_controller.psutil, "cpu_percent", cpu_percent)
    controller = NodeController("n1", KEY, limits=Limits(max_cpu_percent=101.0))
    controller.unbound_s = 1.0                       # (none takes it: it ends)
    try:
        eventually(lambda: len(calls) >= 2, what="the failing sample")
        controller.start_executor("ends")
        eventually(lambda: len(calls) >= 5, what="samples after the failure")
        eventually(lambda: not controller._executors, timeout=20, what="the ended forgotten")
    finally:
        controller.close()
    failures = [r.getMessage() for r in caplog.records if "failed" in r.getMessage()]
    assert failures == ["node n1: sampling its CPU failed (OSError: [Errno 24] Too many "
                        "open files); it tries again every 0.5 s"]


def test_the_command_line_raises_its_open_files_limit_to_the_hard_one() -> None:
    """A daemon under the common soft limit of 1024 descriptors failed every open (EMFILE)
    after one burst of some thousand idle connections."""
    import resource
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard <= 256:
        pytest.skip(f"a hard limit of {hard} descriptors leaves nothing to raise")

    def lowered() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (256, hard))
    process = subprocess.Popen([sys.executable, "-m", "pb3a", "node", "start", "--name", "fd",
                                "--listen", "tcp://127.0.0.1:0"], stdout=subprocess.PIPE,
                               text=True, preexec_fn=lowered)
    try:
        assert process.stdout.readline().startswith("node fd at tcp://")
        raised = psutil.Process(process.pid).rlimit(psutil.RLIMIT_NOFILE)
        assert raised[0] > 256 and raised[1] == hard
        if hard != resource.RLIM_INFINITY:
            assert raised == (hard, hard)
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=10) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(5)
        process.stdout.close()


def test_a_node_controller_asked_as_a_module_server_says_what_it_is(node) -> None:
    """It said only that a node controller has no operation 'find'."""
    controller, client = node
    with pytest.raises(RuntimeFailure, match=(
            f"^{re.escape(controller.address)} is node n1's controller, not a module server: "
            r"give the address its `pb3a modules serve` printed$")):
        client.call("find", name="robot")
    with pytest.raises(RuntimeFailure, match=r"^node n1's controller at .* has no operation "
                                             r"'nothing'; its operations: admit, "
                                             r"executor_ended, start_"):
        client.call("nothing")
