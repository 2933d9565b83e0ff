"""``pb3a.connect``: the same API as ``launch()`` returns, from another process."""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
import pytest
from conftest import eventually, unused_port
from sample_modules import Chain, Counter, Doubler, FastScale, Last, Mapper, Relay, Scale

import pb3a
from pb3a import ConfigError, ModuleNotFound, RuntimeFailure, RuntimeTimeout, System
from pb3a.launch import running
from pb3a.model.displays import Display
from pb3a.stats import SystemStats
from pb3a.topology import NodeInfo, PortInfo
from pb3a.transport import control

REPO = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.timeout(90)

ANOTHER_PROCESS = """
import sys
import pb3a
with pb3a.connect(sys.argv[1]) as run:
    run.set_state("scale", gain=7.0)
    report = run.migrate("relay", to="b")
    print(run.name, run.state("scale")["gain"], report.destination, run.where("relay"),
          run.stats().modules["relay"].node)
"""


def _system() -> System:
    system = System("connected")
    system.node("a")
    system.node("b")
    system.add("src", Counter, node="a", period=0.002)
    system.add("relay", Relay, node="a")
    system.add("scale", Scale, node="a")
    system.link("src.out", "relay.x")
    return system


def test_another_process_drives_the_system_through_connect() -> None:
    with _system().launch() as run:
        address = run.listen()
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), str(REPO)])}
        done = subprocess.run([sys.executable, "-c", ANOTHER_PROCESS, address], env=env,
                              capture_output=True, text=True, timeout=60, check=False)
        assert done.returncode == 0, done.stderr
        assert done.stdout.split() == ["connected", "7.0", "b", "b", "b"]
        assert run.where("relay") == "b" and run.state("scale")["gain"] == 7.0


def test_a_connection_offers_what_launch_offers_with_the_same_errors() -> None:
    with _system().launch() as run, pb3a.connect(run.listen()) as far:
        assert far.name == "connected" and isinstance(far.stats(), SystemStats)
        assert far.swap("scale", FastScale) == ["gain", "setups"]
        far.add("probe", Last, node="b", state={"value": 2.5})
        far.link("scale.y", "probe.x")
        assert far.state("probe")["value"] == 2.5 and far.where("probe") == "b"
        far.restart("probe")
        far.remove("probe")
        assert "probe" not in run.stats().modules
        assert set(far.nodes()) == {"a", "b"}
        kinds = [event.kind for event in far.events()]
        assert kinds == ["module_swapped", "module_added", "link_added", "module_restarted",
                         "link_removed", "module_removed"]      # its link goes with it
        with pytest.raises(ModuleNotFound, match="no module 'ghost'"):
            far.state("ghost")
        with pytest.raises(ConfigError, match="no node 'mars'") as caught:
            far.migrate("relay", to="mars")
        assert caught.value.problems == ["migrate relay: no node 'mars'; nodes: a, b"]
        started = time.monotonic()
        assert far.events(far.events()[-1].seq, timeout=0.3) == []     # waited, then none
        assert time.monotonic() - started >= 0.3


def test_a_class_object_is_not_sent_to_a_system_on_another_python(monkeypatch) -> None:
    """A class sent by value is bytecode for one Python (pickled by 3.12, it crashed a
    3.13 worker): through a connection to a system on another version, a class object
    is refused naming both versions and the way round it, a "module:Class" it imports."""
    monkeypatch.setattr(running, "PYTHON", "3.99")             # the launcher's, as it says
    with _system().launch() as run, pb3a.connect(run.listen()) as far:
        with pytest.raises(RuntimeFailure, match=r"add probe: the system runs Python 3\.99 "
                                                 r"and this process Python \d+\.\d+, so a "
                                                 r"class object cannot be sent to it: name the "
                                                 r"class as 'module:Class'"):
            far.add("probe", Last)
        far.add("probe", "sample_modules:Last", state={"value": 2.5})
        assert far.state("probe")["value"] == 2.5


def test_connect_tells_no_answer_a_wrong_key_and_a_bad_address_apart() -> None:
    with pytest.raises(ValueError, match="give tcp://HOST:PORT \\(or HOST:PORT\\)"):
        pb3a.connect("127.0.0.1")
    started = time.monotonic()
    with pytest.raises(RuntimeTimeout, match=r"no PB3A launcher answered at tcp://127\.0\.0\.1:1 "
                                             r"within 0\.3 s"):
        pb3a.connect("127.0.0.1:1", timeout=0.3)       # (as the command line takes it too)
    assert time.monotonic() - started < 2
    with _system().launch() as run:
        with pytest.raises(RuntimeFailure, match="runs with another cluster key"):
            pb3a.connect(run.listen(), key=os.urandom(32).hex())
        eventually(lambda: run.state("relay")["relayed"] > 0, what="the system unharmed")


def test_a_port_nothing_listens_on_is_told_within_2_s_and_a_late_launcher_still_reached(
        monkeypatch) -> None:
    """A connection to a system that has ended (its port refuses connections) waited
    the whole 5 s, then said only that nothing answered. It says the port refuses
    connections within about 1.5 s; a launcher that begins to listen within that
    second is reached as before."""
    port = unused_port()
    started = time.monotonic()
    with pytest.raises(RuntimeTimeout, match=rf"no PB3A launcher answered at tcp://127\.0\.0\.1:"
                                             rf"{port}: nothing listens on port {port} at "
                                             r"127\.0\.0\.1 \(the connection was refused\): "
                                             r"the system has stopped"):
        pb3a.connect(f"127.0.0.1:{port}", timeout=10.0)
    assert time.monotonic() - started < 2.5
    # (refused a while longer than 1 s, so that a loaded machine cannot make the
    # listener come only after the connection gave up)
    monkeypatch.setattr(control, "REFUSED_S", 8.0)
    with _system().launch() as run:
        listening = threading.Timer(1.0, run.listen, [f"tcp://127.0.0.1:{port}"])
        listening.start()
        try:
            with pb3a.connect(f"127.0.0.1:{port}", timeout=10.0) as far:
                assert "gain" in far.state("scale")
        finally:
            listening.join(10)


def test_a_connection_to_a_system_that_stopped_says_so_at_once() -> None:
    """Each call waited out its deadline (35 s by default) and then said nothing listens
    there: a monitoring script hung 35 s per call once the system had stopped. It is told
    ``SystemStopped`` about a second after the launcher closed its end, and ``wait()``
    returns then (a connection had no ``wait``)."""
    run = System("stopping").add("scale", Scale).launch()
    try:
        connection = pb3a.connect(run.listen())
        assert "gain" in connection.state("scale")
        assert not connection.wait(0.2) and connection.running
    finally:
        run.close()
    with connection:
        assert connection.wait(5) and not connection.running      # as Running.wait does
        for _ in range(2):                  # (the second knows at once)
            started = time.monotonic()
            with pytest.raises(pb3a.SystemStopped, match=r"'stopping' at tcp://.* has stopped"):
                connection.state("scale")
            assert time.monotonic() - started < 5
    connection.close()                      # (again: nothing more, as Running.close)
    assert connection.wait(None)            # (closed: at once)


def test_a_connection_does_not_go_on_with_another_system_at_the_same_address(
        monkeypatch) -> None:
    """A system launched again on the fixed port of one that stopped, within the second
    that counts a launcher gone, was taken for it: the connection went on reading and
    changing the new system as if it were the one it had connected to. It says
    ``SystemStopped`` instead (the second widened here, so the new system is surely
    there before the first is counted gone)."""
    monkeypatch.setattr(control, "GONE_S", 30.0)
    first = System("first").add("scale", Scale).launch()
    second = System("second").add("scale", Scale).launch()
    try:
        address = first.listen()
        connection = pb3a.connect(address)
        assert "gain" in connection.state("scale")
        first.close()
        assert second.listen(address) == address
        started = time.monotonic()
        with pytest.raises(pb3a.SystemStopped,
                           match=r"'first' at tcp://.* has stopped: another process"):
            connection.set_state("scale", gain=5.0)
        assert time.monotonic() - started < 5
        assert connection.wait(0) and not connection.running
        assert second.state("scale")["gain"] != 5.0             # (it did not reach it)
        connection.close()
    finally:
        first.close()
        second.close()


KILLED_LAUNCHER = """
import sys, time
from sample_modules import Scale
from pb3a import System
with System("killed").add("scale", Scale).launch() as run:
    print(run.listen(), flush=True)
    time.sleep(120)
"""


LISTENING_LAUNCHER = """
import sys
from sample_modules import Scale
from pb3a import System
with System("listening").add("scale", Scale).launch(listen="tcp://127.0.0.1:0") as run:
    print(run.address, flush=True)
    sys.stdin.readline()                     # (until the test is done: closed cleanly)
"""


def test_a_call_waiting_when_the_launcher_dies_fails_soon_with_system_stopped() -> None:
    """The launcher killed with SIGKILL answers nothing: a follower waiting for events
    (up to 30 s) is told ``SystemStopped`` within seconds, not at its deadline."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), str(REPO)])}
    launcher = subprocess.Popen([sys.executable, "-c", KILLED_LAUNCHER], env=env,
                                stdout=subprocess.PIPE, text=True)
    try:
        address = launcher.stdout.readline().strip()
        assert address.startswith("tcp://"), address
        with pb3a.connect(address) as connection:
            workers = [m.pid for m in connection.stats().modules.values()]
            outcome: list[object] = []

            def follow() -> None:
                began = time.monotonic()
                try:
                    connection.events(10**6, timeout=30.0)
                except Exception as exc:
                    outcome[:] = [exc, time.monotonic() - began]
            follower = threading.Thread(target=follow)
            follower.start()
            time.sleep(0.3)                 # (its request waiting at the launcher)
            launcher.kill()
            follower.join(15)
            assert not follower.is_alive(), "the follower waited on"
            error, took = outcome
            assert isinstance(error, pb3a.SystemStopped), error
            assert took < 8, took
        eventually(lambda: not any(psutil.pid_exists(pid) for pid in workers), timeout=15,
                   what="the killed launcher's workers ended")
    finally:
        if launcher.poll() is None:
            launcher.kill()
        launcher.wait(10)
        launcher.stdout.close()


def test_a_connection_dropped_unclosed_gives_back_its_thread_and_descriptors() -> None:
    """A connection dropped without ``close`` (a notebook cell ``run = pb3a.connect(...)``
    run again) kept its thread and six file descriptors for good, its system running or
    not: after some 170 re-runs the process could open no more files. It is closed as
    it is collected, at once as its last reference goes."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), str(REPO)])}
    launcher = subprocess.Popen([sys.executable, "-c", LISTENING_LAUNCHER], env=env,
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        address = launcher.stdout.readline().strip()
        assert address.startswith("tcp://"), address
        pb3a.connect(address).close()        # (ZeroMQ's own threads and files, made once)
        me = psutil.Process()
        files, threads = me.num_fds(), set(threading.enumerate())
        gc.disable()                # (no collection needed: nothing holds it in a cycle)
        try:
            for _ in range(5):
                connection = pb3a.connect(address)           # the cell, run again
                assert "gain" in connection.state("scale")
            del connection
            eventually(lambda: me.num_fds() <= files and set(threading.enumerate()) <= threads,
                       what="the dropped connections' threads and files given back",
                       context=lambda: (me.num_fds(), files,
                                        [t.name for t in set(threading.enumerate()) - threads]))
        finally:
            gc.enable()
    finally:
        launcher.stdin.close()
        try:
            launcher.wait(30)
        finally:
            if launcher.poll() is None:
                launcher.kill()
                launcher.wait(10)
            launcher.stdout.close()


def test_a_connection_kept_after_its_system_stopped_gives_back_its_thread() -> None:
    """A connection kept once its system stopped held its thread and sockets until it was
    closed (a monitoring script's connections to systems long gone). They go when the
    launcher is known gone; its calls still say ``SystemStopped`` at once, and closing
    it still does nothing more."""
    run = System("stopping").add("scale", Scale).launch(listen="tcp://127.0.0.1:0")
    try:
        connection = pb3a.connect(run.address)
        assert "gain" in connection.state("scale")
        thread = connection._client._loop._thread
    finally:
        run.close()
    assert connection.wait(5) and not connection.running
    eventually(lambda: not thread.is_alive(), what="the connection's thread ended")
    assert connection._client._dealer.closed
    for _ in range(2):
        started = time.monotonic()
        with pytest.raises(pb3a.SystemStopped, match=r"'stopping' at tcp://.* has stopped"):
            connection.state("scale")
        assert time.monotonic() - started < 1
    connection.close()
    connection.close()
    assert connection.wait(None)


def test_topology_describes_the_structure_alike_through_launch_and_connect() -> None:
    system = _system()
    system.add("chain", Chain, node="b")
    system.add("map", Mapper, node="b")
    system.add("boss", Doubler, node="a")
    system.link("scale.y", "chain.x")
    with system.launch() as run, pb3a.connect(run.listen()) as far:
        topology = run.topology()
        assert far.topology() == topology
        assert set(topology.modules) == {"src", "relay", "scale", "chain/a", "chain/b", "map",
                                         "boss"}
        chained = topology.modules["chain/b"]
        assert (chained.cls, chained.node, chained.macro, chained.kind) == (
            "sample_modules:Scale", "b", "chain", "module")
        assert topology.modules["boss"].kind == "agent"
        assert chained.inputs["x"] == PortInfo("float", "latest")
        assert chained.outputs["y"] == PortInfo("float")
        assert set(chained.state) == {"gain", "setups"}
        assert topology.modules["map"].displays == {
            "grid": Display("image"), "cells": Display("plot"), "speed": Display("gauge", 0, 1)}
        assert "displays" not in run.state("map")                  # configuration, not state
        assert topology.macros == {"chain": ["chain/a", "chain/b"]}
        assert set(topology.links) == {"src.out->relay.x", "scale.y->chain/a.x",
                                       "chain/a.y->chain/b.x"}
        assert topology.nodes["a"] == NodeInfo(None, 0, True, 0.0)
        shown = json.loads(json.dumps(topology.to_json()))          # plain JSON types only
        assert shown["modules"]["map"]["displays"]["speed"] == {"kind": "gauge", "min": 0.0,
                                                                "max": 1.0}
        assert {"key": "src.out->relay.x", "src": "src.out", "dst": "relay.x",
                "policy": "queue:100000"} in shown["links"]
        far.migrate("map", to="a")
        assert far.topology().modules["map"].node == "a"


def test_stats_report_each_nodes_cpu_and_memory() -> None:
    with _system().launch() as run, pb3a.connect(run.listen()) as far:
        for stats in (run.stats(), far.stats()):
            for node in stats.nodes.values():
                assert node.cpu is not None and 0.0 <= node.cpu <= 100.0
                assert 0 < node.memory_available <= node.memory_total
                assert node.memory_total == psutil.virtual_memory().total
        assert far.nodes()["a"].cpu is None          # health only: nothing was measured


def test_a_call_without_a_timeout_waits_as_long_as_the_system_s_default(monkeypatch) -> None:
    """A connection's call without ``timeout=`` waits the system's default (here longer
    than the library's), as the launcher does: it does not give up first, saying nobody
    answered, while the operation goes on there."""
    monkeypatch.setattr("pb3a.launch.connection.DEFAULT_TIMEOUT", 0.5)  # the library's
    monkeypatch.setattr("pb3a.launch.connection._MARGIN", 0.5)
    held, release = threading.Event(), threading.Event()
    with _system().launch(timeout=30.0) as run, pb3a.connect(run.listen()) as far:
        def hold() -> None:
            with run._launcher.lock.held("a long reconfiguration", 30.0):
                held.set()
                release.wait(30.0)
        holder = threading.Thread(target=hold)
        holder.start()
        try:
            assert held.wait(10.0)
            threading.Timer(2.0, release.set).start()       # the lock comes back in 2 s
            assert far.where("relay") == "a"                # waited for it, as told
        finally:
            release.set()
            holder.join(10.0)


def test_a_timeout_that_is_not_seconds_is_refused_at_once_the_same_through_connect() -> None:
    """-1 waited for the lock for good, NaN spun (events) or broke every later call
    (launch), inf and text were bare built-in errors, and a launch timeout of 0 became
    30 s."""
    system = System("timeouts").add("count", Counter, period=0.01)
    for bad in (float("nan"), -1.0):
        with pytest.raises(ValueError, match="launch: timeout must be a finite number"):
            system.launch(timeout=bad)
    with system.launch(timeout=0.0) as run, pb3a.connect(run.listen()) as connection:
        assert run._operations.timeout == 0.0
        for bad in (-1, -0.5, float("nan"), float("inf"), "1", True):
            errors = []
            for handle in (run, connection):
                started = time.monotonic()
                for op, args in (("state", ("count",)), ("events", (0,))):
                    with pytest.raises((ValueError, TypeError)) as refused:
                        getattr(handle, op)(*args, timeout=bad)
                    errors.append((type(refused.value), str(refused.value)))
                assert time.monotonic() - started < 1.0
            assert errors[:2] == errors[2:], errors            # the same, both ways
            assert all("timeout must be a" in message for _, message in errors)
            # connecting and closing too (NaN and inf failed in time arithmetic's words, -1
            # was waited as 0, True as 1; a close given NaN or -5 ran no teardown)
            with pytest.raises((ValueError, TypeError), match="connect: timeout must be a"):
                pb3a.connect(run.listen(), timeout=bad)
            with pytest.raises((ValueError, TypeError), match="close: timeout must be a"):
                run.close(timeout=bad)
            assert run.running


def test_a_class_that_does_not_resolve_is_one_config_error_with_the_rest_both_ways() -> None:
    """add() raised the bare LookupError of the class alone (a RuntimeFailure through
    connect), hiding the entry's other mistakes, which pb3a check lists."""
    system = System("unresolved").add("scale", Scale)
    with system.launch() as run, pb3a.connect(run.listen()) as connection:
        for handle in (run, connection):
            with pytest.raises(ConfigError) as add:
                handle.add("bad name!", "sample_modules:Nope", node="zz", period=-1)
            assert len(add.value.problems) == 4
            assert "module 'sample_modules' has no class 'Nope'" in add.value.problems[0]
            with pytest.raises(ConfigError, match="swap scale: bad class reference"):
                handle.swap("scale", "sample_modules.Nope")
        assert set(run.stats().modules) == {"scale"}                # nothing added


def test_one_connection_waiting_for_events_holds_up_no_other() -> None:
    """The launcher's server ran requests one at a time: a follower's events(timeout=3)
    (as `pb3a events --follow` and the manager poll) made another connection's
    state(timeout=1) wait for it, past its own timeout."""
    with System("busy-lane").add("scale", Scale).launch() as run:
        address = run.listen()
        with pb3a.connect(address) as follower, pb3a.connect(address) as other:
            waiting = threading.Thread(target=lambda: follower.events(10**6, timeout=5.0))
            waiting.start()
            try:
                time.sleep(0.2)          # (its request in the server before ours)
                started = time.monotonic()
                other.state("scale", timeout=2.5)      # (held up: 4.8 s)
                assert time.monotonic() - started < 2.5
            finally:
                waiting.join(10)


@pytest.mark.parametrize("every", ["*", "0.0.0.0", "[::]"])
def test_a_launcher_listening_on_every_interface_hands_out_an_address_of_this_machine(
        every: str) -> None:
    # (it handed out tcp://*:PORT, which `pb3a status` and another host cannot use)
    with System("everywhere").add("scale", Scale).launch() as run:
        address = run.listen(f"tcp://{every}:0")
        host, _, port = address.removeprefix("tcp://").rpartition(":")
        ours = {entry.address for entries in psutil.net_if_addrs().values()
                for entry in entries}
        assert host in ours and host not in ("*", "0.0.0.0", "[::]"), address
        with pb3a.connect(f"tcp://127.0.0.1:{port}") as far:      # every interface: here too
            assert far.name == "everywhere"


def test_a_launcher_on_loopback_is_refused_when_a_node_is_on_another_machine(
        monkeypatch) -> None:
    """``pb3a run --listen tcp://127.0.0.1:PORT`` with a node on a robot started, and
    the robot called the launcher back at its own loopback: a ``last-state`` module
    failed over from nothing, nothing said (an operator's review, on network
    namespaces). It is refused before anything starts, naming the node; nodes of this
    machine (loopback controllers, as in the tests) are not "far"."""
    from pb3a.transport.addresses import elsewhere
    assert not elsewhere("tcp://127.0.0.1:7100") and not elsewhere("tcp://localhost:7100")
    robot = "tcp://127.0.0.2:7100"           # (taken for a robot: loopback, should it be tried)
    monkeypatch.setattr(running, "elsewhere", lambda towards: towards == robot)
    system = System("far").add("scale", Scale)
    system.node("robot1", address=robot)
    started = time.monotonic()
    with pytest.raises(ValueError, match=r"cannot listen on tcp://127\.0\.0\.1:0: node "
                                         r"robot1 runs on another machine, which calls the "
                                         r"launcher back at this address"):
        system.launch(listen="tcp://127.0.0.1:0", timeout=5)
    assert time.monotonic() - started < 3.0
