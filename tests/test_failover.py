"""Failover and rejoin: the modules of a lost node start again on a surviving one within
1 s (``fresh``, or ``last-state`` from a checkpoint kept off the lost node), their links
are wired again and what was lost counted; the node, once back, is admitted under a
new epoch and modules can be moved back; a fenced executor's word is refused."""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import math
import os
import re
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NoReturn

import cloudpickle
import psutil
import pytest
from conftest import Daemon, eventually, frozen
from sample_modules import (
    AsksInSetup,
    Collector,
    Counter,
    HoldsTheGil,
    Join,
    Journal,
    Last,
    MoveLog,
    OpensDevice,
    Relay,
    RobotPose,
    SlowerToMake,
    SlowToMake,
    SlowToStop,
    Steady,
    StepStamps,
)

from pb3a import RuntimeFailure, RuntimeTimeout, System
from pb3a.cli.main import main
from pb3a.cli.status import format_nodes, format_table
from pb3a.daemons.node_controller import Limits, NodeController
from pb3a.events import EventLog
from pb3a.launch.failover import Failover
from pb3a.stats import FailureLog
from pb3a.transport.auth import ClusterKey, Rejected
from pb3a.transport.control import ControlClient
from pb3a.transport.replication import ACK_EVERY

pytestmark = pytest.mark.timeout(120)


def _started(*names: str) -> Iterator[dict[str, Daemon]]:
    made = Daemon.several(*names)
    try:
        yield made
    finally:
        for daemon in made.values():
            daemon.stop()


@pytest.fixture
def daemons() -> Iterator[dict[str, Daemon]]:
    """Node controllers b and c, each in a process of its own."""
    yield from _started("b", "c")


@pytest.fixture
def node_b() -> Iterator[Daemon]:
    """Node controller b alone, for a test that needs no other (c's, started and stopped
    for nothing, cost each of them half a second of CPU)."""
    for made in _started("b"):
        yield made["b"]


def _events(run, kind: str) -> list:
    return [event for event in run.events() if event.kind == kind]


@pytest.mark.parametrize("victim", ["executor", "controller"])
def test_modules_of_a_lost_node_fail_over_within_1_s_and_the_node_rejoins(
        daemons, victim) -> None:
    b, c = daemons["b"], daemons["c"]
    system = System("failover").node("a").node("b", address=b.address)
    system.node("c", address=c.address)
    system.add("src", Counter, node="a", period=0.001)
    system.add("relay", Relay, node="b", restart="last-state", fallback=["c", "a"])
    system.add("far", Collector, node="b", restart="fresh")
    system.add("gone", Collector, node="b", restart="never")
    system.add("near", Collector, node="a")
    system.link("src.out", "relay.x")
    system.link("src.out", "far.x")
    system.link("src.out", "gone.x")
    system.link("relay.out", "near.x")
    system.add("moves", MoveLog, node="a")
    system.link("env-a.module_moved", "moves.moved")
    with system.launch(checkpoint_s=0.2) as run:
        launcher = run._launcher
        eventually(lambda: run.state("near")["received"] > 100, timeout=30,
                   what="values through the relay on b")
        eventually(lambda: "relay" in launcher.checkpoints, what="a checkpoint off node b")
        kept = cloudpickle.loads(launcher.checkpoints["relay"])
        if victim == "executor":
            os.kill(b.executor_pid(), signal.SIGKILL)
        else:
            b.kill()
        assert launcher.wait_health("b", up=False, timeout=10)
        moved = eventually(lambda: len(_events(run, "module_failed_over")) == 2
                           and _events(run, "module_failed_over"), what="two failovers")
        stats = run.stats()
        before = {name: run.state(name)["received"] for name in ("near", "far")}
        eventually(lambda: all(run.state(name)["received"] > before[name] + 50
                               for name in before), timeout=15,
                   what="values through the restarted modules")
        relay = run.state("relay")
        told = eventually(lambda: len(run.state("moves")["moves"]) == 2
                          and run.state("moves")["moves"], what="the env module's moves")
        if victim == "controller":
            b.start()                           # the machine's daemon comes back
        joined = eventually(lambda: _events(run, "node_joined"), timeout=20,
                            what="node b admitted again")
        assert run.stats().nodes["b"].up and run.stats().nodes["b"].epoch == 2
        assert run.migrate("relay", to="b").destination == "b"
        relayed = run.state("relay")["relayed"]
        eventually(lambda: run.state("relay")["relayed"] > relayed + 50
                   and run.state("near")["received"] > before["near"] + 200, timeout=15,
                   what="values through the relay moved back to b")
        lost_event = _events(run, "node_lost")[0]
        lost_modules = _events(run, "module_lost")
    assert lost_event.detail["modules"] == ["far", "gone", "relay"]
    if victim == "executor":        # its controller said so, and it was lost then
        assert lost_event.detail["executor"].startswith("was killed by SIGKILL")
        assert lost_event.detail["silent_s"] < 1.5, lost_event.detail
    else:                           # nobody said so: lost once silent for LOSS_S
        assert lost_event.detail["executor"] is None
        assert lost_event.detail["silent_s"] >= 2.0, lost_event.detail
    where = {event.subject: event.detail for event in moved}
    assert where["relay"]["destination"] == "c"                   # its first fallback
    assert where["relay"]["from_checkpoint"] and not where["far"]["from_checkpoint"]
    assert where["far"]["destination"] in ("a", "c")              # the least loaded
    assert all(detail["restart_s"] < 1.0 for detail in where.values()), where
    assert relay["setups"] == kept["setups"] + 1 >= 2             # its checkpoint, restored
    assert "gone" not in stats.modules and "src.out->gone.x" not in stats.links
    (gone,) = lost_modules                                        # said, with what it was
    assert gone.subject == "gone" and gone.detail["node"] == "b"
    assert gone.detail["reason"] == "its restart policy is never"
    assert gone.detail["cls"] == "sample_modules:Collector"
    assert gone.detail["links"] == [                              # (Collector's own policy)
        {"from": "src.out", "to": "gone.x", "policy": "queue:1000000"}]
    assert stats.modules["relay"].node == "c" and stats.modules["far"].node in ("a", "c")
    # what src wrote while nobody on b read it is counted, never silently gone (1000 a
    # second, b silent for 0.5-0.8 s when its executor died, 2 s when its controller did)
    assert stats.links["src.out->relay.x"].link_failures > 100
    (row,) = [line.split() for line in format_table(stats).splitlines()
              if line.startswith("src.out -> relay.x ")]
    assert int(row[8]) == stats.links["src.out->relay.x"].link_failures   # `pb3a status`: lost
    assert stats.links["src.out->far.x"].link_failures > 100
    assert joined[0].detail["epoch"] == 2
    assert {(move["module"], move["destination"]) for move in told} == {
        (name, detail["destination"]) for name, detail in where.items()}


def _relayed_over_c(name: str, b: str, c: str) -> System:
    """src -> relay -> near: src and near on a, the relay on b (at ``b``), failing over
    to c (at ``c``), then a."""
    system = System(name).node("a").node("b", address=b).node("c", address=c)
    system.add("src", Counter, node="a", period=0.001)
    system.add("relay", Relay, node="b", restart="fresh", fallback=["c", "a"])
    system.add("near", Collector, node="a")
    system.link("src.out", "relay.x")
    system.link("relay.out", "near.x")
    return system


def _accounted(run, link: str) -> int:
    """Values of ``link`` its reader received or was told were not sent (counted as
    drops): on a dropping remote link, every value written is one or the other."""
    figures = run.stats().links[link]
    return figures.values + figures.drops


def test_a_reader_node_lost_after_another_counts_only_what_it_did_not_acknowledge(
        daemons) -> None:
    """Readers of one output on nodes b and c; b lost; 1000 more values, which c
    acknowledges; c lost: its link said 1000 values lost (b's acknowledgement, left at the
    writer while c still read, was the least advanced, and counted for c). The links drop
    (queue): a follower that fell behind the other one for half a second (its node
    loaded) is served on its own, and goes back to PUB once b is forgotten; either
    switch counts some values dropped, not received, and c acknowledges past them."""
    b, c = daemons["b"], daemons["c"]
    system = System("stale-ack").node("a").node("b", address=b.address)
    system.node("c", address=c.address)
    system.add("src", Counter, node="a", period=0.001, state={"limit": 100})
    system.add("on_b", Collector, node="b", restart="never")
    system.add("on_c", Collector, node="c", restart="fresh", fallback=["a"])
    system.link("src.out", "on_b.x")
    system.link("src.out", "on_c.x")
    with system.launch() as run:
        eventually(lambda: _accounted(run, "src.out->on_b.x") == _accounted(
            run, "src.out->on_c.x") == 100, timeout=30, what="the first 100 values on b and c")
        os.kill(b.executor_pid(), signal.SIGKILL)
        eventually(lambda: _events(run, "module_lost"), timeout=20, what="b's reader lost")
        run.set_state("src", limit=1100)
        eventually(lambda: _accounted(run, "src.out->on_c.x") == 1100, timeout=20,
                   what="1000 more values on c, received or counted dropped", context=lambda: (
                       run.state("on_c"), run.stats().links["src.out->on_c.x"]))
        os.kill(c.executor_pid(), signal.SIGKILL)
        eventually(lambda: _events(run, "module_failed_over"), timeout=20,
                   what="c's reader failed over")
        lost = run.stats().links["src.out->on_c.x"].link_failures
    # c acknowledges at least every ACK_EVERY values: it confirmed all but its last few
    assert lost < ACK_EVERY, f"{lost} values counted lost for c"


def test_a_fenced_executors_word_is_refused_and_placement_follows_admission() -> None:
    b = NodeController("b", ClusterKey.load(), limits=Limits(max_cpu_percent=101.0))
    c = NodeController("c", ClusterKey.load(), limits=Limits(max_cpu_percent=101.0))
    try:
        with _relayed_over_c("fenced", b.address, c.address).launch() as run:
            launcher = run._launcher
            eventually(lambda: run.state("near")["received"] > 10, timeout=30,
                       what="values through b")
            for controller in (b, c):                     # both refuse any work for now
                controller.limits.max_cpu_percent = -1.0
            os.kill(b._executors["fenced"][0].pid, signal.SIGSTOP)   # cut off, not dead
            assert launcher.wait_health("b", up=False, timeout=10)
            moved = eventually(lambda: _events(run, "module_failed_over"),
                               what="relay restarted")
            callback = ControlClient(ClusterKey.load(), run.address)
            try:      # what the old executor says, were it to wake up, is refused
                with pytest.raises(RuntimeFailure, match="stale: node b's executor of epoch 1"
                                                         " was fenced"):
                    callback.call("event", 5.0, kind="module_failed", subject="relay",
                                  detail={}, node="b", node_epoch=1)
            finally:
                callback.close()
            eventually(lambda: any("could not be admitted" in entry.message
                                   for entry in run.logs()), what="b's controller refusing")
            assert not _events(run, "node_joined")
            b.limits.max_cpu_percent = 101.0              # a later attempt gets in
            joined = eventually(lambda: _events(run, "node_joined"), timeout=20,
                                what="b admitted again (its controller never went)")
            with pytest.raises(RuntimeFailure, match="stale: node b's executor of epoch 1"):
                launcher.check_node_epoch("b", 1)
            launcher.check_node_epoch("b", 2)
            failures = run.stats().failures
    finally:
        b.close()
        c.close()
    assert moved[0].detail["destination"] == "a"          # c, its first fallback, refused
    assert joined[0].detail["epoch"] == 2
    assert not any("module_failed" in failure for failure in failures)


def test_a_module_no_node_takes_is_said_lost_with_what_it_takes_to_add_it_again() -> None:
    """A module whose failover no node admitted was taken out of the system with its
    links, said only in ``stats().failures``: no event an agent could act on, and what
    it was (class, state, links) gone with it. The event ``module_lost`` says why, and
    holds what it takes to add it again."""
    b = NodeController("b", ClusterKey.load(), limits=Limits(max_cpu_percent=101.0))
    c = NodeController("c", ClusterKey.load(), limits=Limits(max_cpu_percent=101.0))
    system = System("unplaced").node("a").node("b", address=b.address)
    system.node("c", address=c.address)
    system.add("src", Counter, node="a", period=0.005)
    system.add("relay", Relay, node="b", restart="fresh", fallback=["c"],
               state={"relayed": 0})
    system.add("sink", Collector, node="a")
    system.add("tick", Counter, node="b", period=0.02,        # (restart never: it goes)
               fixed_rate=True)
    system.link("src.out", "relay.x")
    system.link("relay.out", "sink.x", policy="queue:32")
    try:
        with system.launch() as run:
            eventually(lambda: run.state("sink")["received"] > 10, timeout=30,
                       what="values through b")
            c.limits.max_cpu_percent = -1.0           # its only fallback refuses it
            os.kill(b._executors["unplaced"][0].pid, signal.SIGKILL)
            eventually(lambda: len(_events(run, "module_lost")) == 2, timeout=15,
                       what="the relay and tick said lost")
            lost, ticker = sorted(_events(run, "module_lost"),
                                  key=lambda event: event.subject != "relay")
            assert "relay" not in run.stats().modules
            assert {event.subject for event in _events(run, "link_removed")} == {
                "src.out->relay.x", "relay.out->sink.x"}      # its links went with it
            detail = lost.detail                      # enough to add it again, elsewhere
            run.add("relay", detail["cls"], node="a", state=detail["state"])
            for link in detail["links"]:
                run.link(link["from"], link["to"], policy=link["policy"])
            received = run.state("sink")["received"]
            eventually(lambda: run.state("sink")["received"] > received + 10,
                       what="values through the relay added again")
    finally:
        b.close()
        c.close()
    assert lost.subject == "relay" and lost.detail["node"] == "b"
    assert lost.detail["reason"] == "no surviving node of its fallback admits it"
    assert lost.detail["links"] == [
        {"from": "src.out", "to": "relay.x", "policy": "queue:100000"},    # (Relay's own)
        {"from": "relay.out", "to": "sink.x", "policy": "queue:32"}]
    # its configured fallback, and a configured period (None: the class's own), which
    # were left out: one added again from the event ran at its class's rate, and went
    # for good with its next node
    assert (lost.detail["fallback"], lost.detail["period"]) == (["c"], None)
    assert ticker.subject == "tick"
    assert (ticker.detail["fallback"], ticker.detail["period"]) == ([], 0.02)
    # and its configured fixed rate (None: the class's own)
    assert (lost.detail["fixed_rate"], ticker.detail["fixed_rate"]) == (None, True)


def _relayed(name: str, b: Daemon, relay_on: str, restart: str) -> System:
    """src -> relay -> sink, src and sink on a, b behind its node controller."""
    system = System(name).node("a").node("b", address=b.address)
    system.add("src", Counter, node="a", period=0.005)
    system.add("relay", Relay, node=relay_on, restart=restart)
    system.add("sink", Collector, node="a")
    system.link("src.out", "relay.x")
    system.link("relay.out", "sink.x")
    return system


def test_a_node_lost_while_a_change_holds_the_lock_long_still_fails_over(node_b,
                                                                        monkeypatch) -> None:
    """The failover's wait for the configuration lock ran out (60 s by default) inside
    the watchdog's thread, which died of it: no node was ever lost, failed over or let
    back in again. It looks for the lock again every ``WATCH_S``: once the lock is free,
    the failover follows within a second."""
    b = node_b
    monkeypatch.setattr("pb3a.launch.failover.FAIL_OVER_WAIT_S", 0.2)
    with _relayed("patient", b, relay_on="b", restart="fresh").launch() as run:
        launcher = run._launcher
        eventually(lambda: run.state("sink")["received"] > 20, timeout=30, what="values")
        with launcher.lock.held("a long change"):
            os.kill(b.executor_pid(), signal.SIGKILL)
            assert launcher.wait_health("b", up=False, timeout=10)
            eventually(lambda: any(e.kind == "node_lost" for e in run.events()),
                       what="the loss")
            # held past b's fencing and a look at the lock that failed: from then on
            # only the lock holds the failover back
            looked = launcher.remotes["b"].fenced_by() + 0.5
            eventually(lambda: time.monotonic() > looked, what="b fenced, a look failed")
            assert not _events(run, "module_failed_over")       # (the lock is held)
            freed = time.time()
        moved = eventually(lambda: _events(run, "module_failed_over"), timeout=10,
                           what="the failover once the lock is free")
        received = run.state("sink")["received"]
        eventually(lambda: run.state("sink")["received"] > received + 20, timeout=15,
                   what="values through the relay failed over")
        eventually(lambda: _events(run, "node_joined"), timeout=20, what="b back")
    assert moved[0].subject == "relay" and moved[0].detail["destination"] == "a"
    assert moved[0].time - freed < 1.0, f"failed over {moved[0].time - freed:.2f} s after"


def test_a_module_put_back_by_a_move_that_its_destination_s_loss_failed_is_left_alone(
        node_b) -> None:
    """The failover read which modules were on the lost node before it took the lock,
    while the move still had the module there: once the move had put it back where it
    ran, the failover dropped it (restart never; its worker ran on) or restarted it. The
    loss names it as arriving, not as one of the node's."""
    b = node_b
    with _relayed("put-back", b, relay_on="a", restart="never").launch() as run:
        launcher = run._launcher
        eventually(lambda: run.state("relay")["relayed"] > 20, timeout=30, what="values")
        node_b, land = launcher.nodes["b"], launcher.nodes["b"].land

        def land_as_b_dies(name: str, snapshot: object) -> float:
            os.kill(b.executor_pid(), signal.SIGKILL)          # b dies as it lands there
            return land(name, snapshot)
        node_b.land = land_as_b_dies
        with pytest.raises(RuntimeFailure, match="it runs on node a again"):
            run.migrate("relay", to="b")
        (lost,) = eventually(lambda: _events(run, "node_lost"), timeout=10, what="b lost")
        # (it was said to be on b, lost with it, while the move put it back)
        assert lost.detail["modules"] == [] and lost.detail["arriving"] == ["relay"]
        relayed = run.state("relay")["relayed"]
        eventually(lambda: run.state("relay")["relayed"] > relayed + 20, timeout=10,
                   what="the relay running on a")
        assert run.where("relay") == "a" and not _events(run, "module_failed_over")
        assert run.state("sink")["received"] > relayed


def test_a_move_that_a_writer_s_node_loss_failed_leaves_the_rest_running(node_b) -> None:
    """The move's undoing wired the module's links again in one go: the link from the
    lost node failed it, and the module, put back, was never started; the writer on a
    surviving node resumed after the pause only if it came first."""
    b = node_b
    system = System("undone").node("a").node("b", address=b.address).node("c")
    system.add("alpha", Counter, node="a", period=0.01)
    system.add("beta", Counter, node="b", period=0.01)
    system.add("join", Join, node="a")
    system.link("alpha.out", "join.x")
    system.link("beta.out", "join.y")
    with system.launch() as run:
        launcher = run._launcher
        eventually(lambda: run.state("join")["ys"] > 20, timeout=30, what="values from b")
        node_a, retire = launcher.nodes["a"], launcher.nodes["a"].retire

        def retire_as_b_dies(*args: object) -> object:
            os.kill(b.executor_pid(), signal.SIGKILL)           # b dies during the move
            return retire(*args)
        node_a.retire = retire_as_b_dies
        with pytest.raises(RuntimeFailure, match="it runs on node a again"):
            run.migrate("join", to="c")
        node_a.retire = retire
        assert run.stats().modules["join"].status == "running"
        counted = run.state("join")["xs"]
        eventually(lambda: run.state("join")["xs"] > counted + 20, timeout=10,
                   what="values from alpha into join, put back on a")


def test_a_module_whose_node_is_lost_as_it_lands_elsewhere_lands_with_its_state(
        node_b) -> None:
    """The move from b had captured the relay when b was lost (its executor killed as the
    relay landed on a): wiring its link to its reader on b failed, and the move put it
    back on b, where it went with the node, the state it had captured with it (restart
    never: said lost; otherwise started afresh elsewhere). It lands, and runs on, on a."""
    b = node_b
    system = System("source-lost").node("a").node("b", address=b.address)
    system.add("src", Counter, node="a", period=0.005)
    system.add("relay", Relay, node="b", restart="never")
    system.add("sink", Collector, node="b")
    system.link("src.out", "relay.x")
    system.link("relay.out", "sink.x")
    with system.launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 20, timeout=30, what="values")
        node_a, land = run._launcher.nodes["a"], run._launcher.nodes["a"].land

        def land_as_b_dies(name: str, snapshot: object) -> float:
            os.kill(b.executor_pid(), signal.SIGKILL)
            return land(name, snapshot)
        node_a.land = land_as_b_dies
        report = run.migrate("relay", to="a", state={"relay": {"setups": 100}})
        node_a.land = land
        assert report.source == "b" and run.where("relay") == "a"
        relayed = run.state("relay")["relayed"]
        assert relayed > 20                             # its state came with it
        assert run.state("relay")["setups"] >= 100      # and what the move set on arrival
        eventually(lambda: run.state("relay")["relayed"] > relayed + 20, timeout=10,
                   what="the relay relaying on a")
        eventually(lambda: _events(run, "module_lost"), timeout=10, what="b's loss handled")
        assert [e.subject for e in _events(run, "module_lost")] == ["sink"]


def test_a_lost_node_shows_no_round_trip_and_its_real_silence(node_b, capsys) -> None:
    """A lost node showed the last round-trip time measured, unchanged (``pb3a nodes``),
    ``silent_s`` 0.0 however long it had been silent, and its controller answering after
    it was gone: it shows no round trip ("-"; NaN, null in JSON), the seconds since its
    executor last answered, and whether its controller answers now."""
    b = node_b
    system = System("silent").node("a").node("b", address=b.address)
    system.add("far", Collector, node="b")
    with system.launch() as run:
        address = run.listen()
        eventually(lambda: run.stats().nodes["b"].rtt > 0, what="a round trip to b")
        executor = b.executor_pid()
        b.kill()                        # (its controller first: b is not admitted again)
        os.kill(executor, signal.SIGKILL)
        assert run._launcher.wait_health("b", up=False, timeout=10)
        time.sleep(1.0)
        node = eventually(lambda: (n := run.stats().nodes["b"]).controller is False and n,
                          what="b's controller said gone")
        capsys.readouterr()
        assert main(["nodes", address]) == 0
        shown = capsys.readouterr().out
        assert main(["nodes", address, "--json"]) == 0
        as_json = json.loads(capsys.readouterr().out, parse_constant=_no_constant)["b"]
    assert not node.up and math.isnan(node.rtt)
    assert node.silent_s > 2.9            # lost after 2 s of silence, looked at 1 s later
    assert re.search(r"^b +tcp://\S+ +LOST +-$", shown, re.M), shown
    assert as_json["rtt"] is None and as_json["up"] is False and as_json["silent_s"] > 2.9
    assert as_json["controller"] is False


def test_a_silent_node_s_modules_show_silent_until_it_is_lost(node_b) -> None:
    """Node b frozen whole for less than the loss timeout (a 1 s freeze changes nothing):
    its module was absent from ``stats()`` and ``pb3a status`` from its second missed
    heartbeat on (``stats().modules["ctl"]`` raised KeyError) while b showed up, and the
    link into it showed as shm with 0 values. It shows silent, on b, as b's last report
    had it, its figures that report's (they were zeros: 0 events, no inputs), and its
    link crosses nodes still, its count the last known, shown unknown ("-") in the
    table; b shows its silence ("up (silent 0.6 s)"; it showed "up")."""
    b = node_b
    system = System("late").node("a").node("b", address=b.address)
    system.add("driver", Counter, node="a", period=0.01)
    system.add("ctl", Collector, node="b")
    system.link("driver.out", "ctl.x")
    key = "driver.out->ctl.x"
    with system.launch() as run:
        eventually(lambda: run.stats().links[key].values > 5, timeout=30,
                   what="values reaching b")
        before = run.stats()
        pid = before.modules["ctl"].pid
        controller = psutil.Process(b.process.pid)
        stopped = [controller, *controller.children(recursive=True)]
        for process in stopped:
            process.suspend()
        try:
            eventually(lambda: run._launcher.silent("b"), timeout=5, what="b silent")
            stats = run.stats(timeout=1)
        finally:
            for process in reversed(stopped):
                with contextlib.suppress(psutil.NoSuchProcess):
                    process.resume()
        eventually(lambda: not run.stats().modules["ctl"].silent, timeout=10,
                   what="ctl answering again")
        lost = _events(run, "node_lost")
    assert not lost, lost                  # (else the freeze outlasted the loss timeout)
    assert stats.nodes["b"].up, stats.nodes["b"]
    ctl = stats.modules["ctl"]
    assert ctl.silent and ctl.node == "b" and ctl.status == "running" and ctl.pid == pid, ctl
    assert not ctl.running and ctl.events >= before.modules["ctl"].events > 0, ctl
    assert ctl.inputs["x"].received >= before.links[key].values, ctl
    link = stats.links[key]
    assert link.silent and link.transport == "zmq", link
    assert link.values >= before.links[key].values, link
    table = format_table(stats)
    assert re.search(rf"^ctl +b +{pid} +running \(silent\) +- +\d+ +[1-9]\d* ", table, re.M), \
        table
    assert re.search(r"^driver\.out -> ctl\.x +zmq +\S+ +- +- ", table, re.M), table
    assert re.search(r"^b +tcp://\S+ +up \(silent \d\.\d s\) +\d", table, re.M), table


def _no_constant(name: str) -> NoReturn:
    raise AssertionError(f"{name} in JSON, which has no such number")


def test_two_nodes_lost_at_once_fail_over_to_the_node_that_lives(daemons) -> None:
    """Node c, dead too but not yet declared lost when b was, was given b's relay (its
    controller still admitted it): the add waited 60 s for c's dead executor, on the
    watchdog's thread, which alone could declare c lost; then the relay was dropped
    and its next fallback never tried."""
    b, c = daemons["b"], daemons["c"]
    with _relayed_over_c("two-lost", b.address, c.address).launch() as run:
        eventually(lambda: run.state("near")["received"] > 100, timeout=30,
                   what="values through the relay on b")
        os.kill(b.executor_pid(), signal.SIGKILL)
        c.kill()                        # (its controller too: c cannot come back meanwhile)
        moved = eventually(lambda: _events(run, "module_failed_over"), timeout=20,
                           what="the relay failed over")
        received = run.state("near")["received"]
        eventually(lambda: run.state("near")["received"] > received + 100, timeout=15,
                   what="values through the relay on a")
        # (c's executor outlives its killed controller a moment: under load, c was
        # declared lost after the relay's values came on a)
        eventually(lambda: {event.subject for event in _events(run, "node_lost")}
                   == {"b", "c"}, timeout=10, what="both nodes lost")
    assert moved[0].detail["destination"] == "a" and moved[0].detail["restart_s"] < 3.0


def test_a_node_that_hears_the_heartbeats_but_whose_answers_are_lost_stops_before_its_module_runs_elsewhere(  # noqa: E501
        node_b, tmp_path: Path) -> None:
    """Its executor renewed its lease on every heartbeat it heard; the launcher, hearing
    no answer for 2 s (a saturated uplink: its answers dropped here for 4 s), failed
    its module over while the old copy stepped on for 1.2 s more. A renewal runs the
    lease on now only from the newest answer the launcher heard."""
    b, stamps = node_b, tmp_path / "steps"
    with _stamping_on_b("uplink", b, stamps).launch() as run:
        eventually(lambda: stamps.exists() and stamps.read_text().count("\n") > 20,
                   what="steps on b")
        remote = run._launcher.remotes["b"]
        _lose_answers_of(remote, 4.0)
        _wait_for_the_copy_on_a(run, stamps)
    _assert_one_copy_at_a_time(stamps)


def test_a_node_whose_renewals_are_read_late_stops_before_its_module_runs_elsewhere(
        node_b, tmp_path: Path) -> None:
    """The executor dated its lease from when it read a renewal, the launcher from when
    it sent it: a renewal read 0.6 s late (a slow downlink, the executor starved) ran
    the lease past the end the launcher counted on, and the old copy stepped on for
    0.2-0.3 s beside its failed-over copy. The executor dates it from the newest of its
    answers the launcher had heard as it renewed."""
    b, stamps = node_b, tmp_path / "steps"
    with _stamping_on_b("late-renewals", b, stamps).launch() as run:
        eventually(lambda: stamps.exists() and stamps.read_text().count("\n") > 20,
                   what="steps on b")
        remote = run._launcher.remotes["b"]
        until = _lose_answers_of(remote, 6.0)
        call = remote.heart.call

        def late(op: str, timeout: float = 10.0, **args: Any) -> Any:
            if time.monotonic() < until:
                time.sleep(0.6)                    # ... and each renewal reaches it late
            return call(op, timeout, **args)
        remote.heart.call = late
        _wait_for_the_copy_on_a(run, stamps)
    _assert_one_copy_at_a_time(stamps)


def _lose_answers_of(remote: Any, seconds: float) -> float:
    """Drop everything the node of ``remote`` (its executor, its controller) answers
    for ``seconds`` (a saturated uplink); when that ends (monotonic)."""
    until = time.monotonic() + seconds
    for client in (remote.client, remote.heart, remote.controller):
        def dropped(frames, opened=client._opener.open):
            if time.monotonic() < until:
                raise Rejected("the uplink lost it")
            return opened(frames)
        client._opener.open = dropped
    return until


def _stamping_on_b(name: str, b: Daemon, stamps: Path) -> System:
    """A module on b stamping each step, with its pid, in ``stamps``; failing over to a."""
    system = System(name).node("a").node("b", address=b.address)
    system.add("stepper", StepStamps, node="b", restart="fresh", fallback=["a"],
               state={"path": str(stamps)})
    return system


def _wait_for_the_copy_on_a(run, stamps: Path) -> None:
    eventually(lambda: _events(run, "module_failed_over"), timeout=15, what="failover")

    def stepping_on_a() -> bool:
        # (by its pid: b's worker, starved past its own lease, may have been restarted
        # there first, a copy of its own)
        pid = run.where("stepper") == "a" and run.stats().modules["stepper"].pid
        return bool(pid) and str(pid) in {line.split()[0]
                                          for line in stamps.read_text().splitlines()}
    eventually(stepping_on_a, what="steps of the copy on a")


def _assert_one_copy_at_a_time(stamps: Path) -> None:
    """Each copy's last step came before the next copy's first."""
    steps = [line.split() for line in stamps.read_text().splitlines()]
    copies = list(dict.fromkeys(pid for pid, _ in steps))
    assert len(copies) >= 2, copies
    for old, new in itertools.pairwise(copies):
        assert max(float(at) for pid, at in steps if pid == old) \
            < min(float(at) for pid, at in steps if pid == new), (old, new)


@pytest.mark.parametrize("lost", ["request", "answer"])
def test_a_slow_node_that_loses_one_heartbeat_keeps_its_lease(node_b, lost: str) -> None:
    """With heartbeats renewing the lease only while the answers were fresh, a 0.3 s
    round trip and one heartbeat (or its answer) lost made the next one a mere ping, and
    the node fenced itself: declared lost, its module failed over. Two heartbeats, each
    with its own wait, keep the pace whatever befalls one."""
    b = node_b
    system = System("slow-link").node("a").node("b", address=b.address)
    system.add("far", Counter, node="b", restart="fresh", fallback=["a"])
    with system.launch() as run:
        eventually(lambda: run.state("far")["count"] > 5, timeout=30, what="steps on b")
        launcher, once = run._launcher, threading.Event()
        remote = launcher.remotes["b"]
        call = remote.heart.call

        def over_a_slow_link(op: str, timeout: float = 10.0, **args: Any) -> Any:
            if once.is_set():                       # this one is lost
                once.clear()
                if lost == "answer":
                    call(op, timeout, **args)       # (it arrives; its answer does not)
                time.sleep(timeout)
                raise RuntimeTimeout("lost")
            time.sleep(0.15)                        # 0.3 s there and back
            answer = call(op, timeout, **args)
            time.sleep(0.15)
            return answer
        remote.heart.call = over_a_slow_link
        assert not launcher.wait_health("b", up=False, timeout=2.0)     # slow, not lost
        once.set()
        assert not launcher.wait_health("b", up=False, timeout=4.0)
        assert not _events(run, "node_lost") and run.where("far") == "b"


def test_a_cut_shorter_than_the_lease_restarts_nothing(node_b) -> None:
    """A cut of 0.6 s, half the lease (everything the launcher and the node's executor
    send each other lost), restarted the node's modules or got it fenced and declared
    lost: once its answers were 0.75 s old the launcher only pinged it, the first
    renewal through carried the answer heard before the cut and extended the lease
    little, and its workers were granted the new end up to 0.25 s later. Every
    heartbeat renews now, one that carried an old answer is followed at once by one
    from its own, and the workers read a renewal's end as soon as it is written."""
    b = node_b
    system = System("short-cuts").node("a").node("b", address=b.address)
    system.add("far", Counter, node="b", restart="fresh", fallback=["a"])
    with system.launch() as run:
        eventually(lambda: run.state("far")["count"] > 5, timeout=30, what="steps on b")
        launcher = run._launcher
        remote, pid = launcher.remotes["b"], run.stats().modules["far"].pid
        call, cut = remote.heart.call, {"start": threading.Event(), "end": -math.inf}

        def through_a_cut_cable(op: str, timeout: float = 10.0, **args: Any) -> Any:
            if cut["start"].is_set():               # (it begins as a heartbeat goes)
                cut["start"].clear()
                cut["end"] = time.monotonic() + 0.6
            if time.monotonic() < cut["end"]:
                time.sleep(timeout)                 # (lost: its wait runs out)
                raise RuntimeTimeout("the cable is cut")
            answer = call(op, timeout, **args)
            if time.monotonic() < cut["end"]:       # (its answer lost)
                time.sleep(timeout)
                raise RuntimeTimeout("the cable is cut")
            return answer
        remote.heart.call = through_a_cut_cable
        for _ in range(3):
            count = run.state("far")["count"]
            cut["start"].set()
            # (the lease, the loss timeout and a look of the watchdog, from the cut)
            assert not launcher.wait_health("b", up=False, timeout=3.0), "b declared lost"
            assert run.state("far")["count"] > count
        changed = [event for event in run.events()
                   if event.kind in ("module_restarted", "node_lost", "module_failed_over")]
        assert not changed, changed
        assert run.where("far") == "b" and run.stats().modules["far"].pid == pid


def test_a_slow_node_that_missed_two_heartbeats_still_takes_a_failing_over_module(
        daemons) -> None:
    """Placement passed over every node silent for 0.5 s (two heartbeats): a node with a
    slow link often is, and a module whose only fallback it was, was dropped. Only a
    node silent half the loss timeout is passed over now."""
    b, c = daemons["b"], daemons["c"]
    system = System("slow-fallback").node("a").node("b", address=b.address)
    system.node("c", address=c.address)
    system.add("far", Counter, node="b", restart="fresh", fallback=["c"])
    with system.launch() as run:
        eventually(lambda: run.state("far")["count"] > 5, timeout=30, what="steps on b")
        slow = run._launcher.remotes["c"]
        answered = slow.silent_s
        slow.silent_s = lambda: max(0.7, answered())     # its answers 0.7 s old, always
        os.kill(b.executor_pid(), signal.SIGKILL)
        moved = eventually(lambda: _events(run, "module_failed_over"), timeout=15,
                           what="the failover")
    assert moved[0].detail["destination"] == "c"


def test_a_checkpoint_only_the_robots_can_read_still_fails_over(tmp_path: Path) -> None:
    """The launcher read the checkpoint itself: a state holding an object of a class
    installed on the robots only (as docs/deploy.md allows) failed the whole failover
    there, and no module of the lost node restarted, the others neither."""
    robot_path = tmp_path / "robot_path"
    robot_path.mkdir()
    (robot_path / "robot_types.py").write_text("class Pose:\n    x = 0.0\n")
    b, c = Daemon.several("b", "c", path=(str(robot_path),)).values()
    try:
        system = System("robot-types").node("a").node("b", address=b.address)
        system.node("c", address=c.address)
        system.add("src", Counter, node="a", period=0.001)
        system.add("pose", RobotPose, node="b", restart="last-state", fallback=["c"])
        system.add("tally", Last, node="a")
        system.add("relay", Relay, node="b", restart="fresh", fallback=["c"])
        system.add("near", Collector, node="a")
        system.link("src.out", "pose.x")
        system.link("pose.count", "tally.x")
        system.link("src.out", "relay.x")
        system.link("relay.out", "near.x")
        with system.launch(checkpoint_s=0.2) as run:
            launcher = run._launcher
            eventually(lambda: run.state("tally")["value"] > 500
                       and "pose" in launcher.checkpoints, timeout=30,
                       what="a checkpoint of the pose off node b")
            with pytest.raises(ModuleNotFoundError):
                cloudpickle.loads(launcher.checkpoints["pose"])   # (not here: on the robots)
            os.kill(b.executor_pid(), signal.SIGKILL)
            moved = eventually(lambda: len(_events(run, "module_failed_over")) == 2
                               and _events(run, "module_failed_over"), what="both failed over")
            seen = run.state("tally")["seen"]
            eventually(lambda: run.state("tally")["seen"] > seen + 100, timeout=15,
                       what="counts from the pose on c")
            received = run.state("near")["received"]
            eventually(lambda: run.state("near")["received"] > received + 100, timeout=15,
                       what="values through the relay on c")
            tally = run.state("tally")
    finally:
        b.stop()
        c.stop()
    assert {event.subject: event.detail["destination"] for event in moved} == {
        "pose": "c", "relay": "c"}
    assert next(e for e in moved if e.subject == "pose").detail["from_checkpoint"]
    # counting on from its checkpoint (taken at some 300 or more), not from 0
    assert tally["value"] >= tally["seen"] - seen + 50


@contextlib.contextmanager
def _frozen(*daemons: Daemon) -> Iterator[None]:
    """Node controllers and their executors stopped (SIGSTOP), as machines that hang or
    are cut off; let run again on the way out."""
    with frozen(*(pid for daemon in daemons
                  for pid in (daemon.process.pid, daemon.executor_pid()))):
        yield


def test_close_keeps_its_timeout_with_machines_that_do_not_answer(daemons) -> None:
    """close(3) took 13-24 s with two machines hung (their controllers and executors
    stopped): the modules and then the nodes were stopped one after another, each call
    waiting 5 s past its own deadline."""
    b, c = daemons["b"], daemons["c"]
    system = System("hung").node("a").node("b", address=b.address)
    system.node("c", address=c.address)
    system.add("src", Counter, node="a", period=0.001)
    for node in ("b", "c"):
        system.add(f"far-{node}", Collector, node=node)
        system.link("src.out", f"far-{node}.x")
    with system.launch() as run:
        eventually(lambda: all(run.state(f"far-{node}")["received"] > 100 for node in "bc"),
                   timeout=30, what="values on b and c")
        with _frozen(b, c):
            started = time.monotonic()
            run.close(timeout=3.0)
            took = time.monotonic() - started
    assert took < 4.0, took
    assert sorted(run.unconfirmed) == ["b", "c"]   # (said "stopped cleanly" all the same)


def test_a_stop_with_a_node_lost_does_not_wait_for_it(node_b) -> None:
    """A node lost for good (its machine cut off: controller and executor silent) held
    the stop of the rest for the whole of close's time, 10 s, waiting for its controller
    to kill an executor that had fenced itself. A lost node's controller is asked
    briefly; the stop is said unconfirmed for it."""
    b = node_b
    system = System("lost-then-stopped").node("a").node("b", address=b.address)
    system.add("near", Collector, node="a")
    system.add("far", Collector, node="b")
    with system.launch() as run:
        eventually(lambda: run.stats().nodes["b"].rtt > 0, what="a round trip to b")
        with _frozen(b):                        # the machine cut off: nothing answers
            assert run._launcher.wait_health("b", up=False, timeout=10)
            started = time.monotonic()
            run.close()                         # (timeout 10 s)
            took = time.monotonic() - started
    assert took < 3.0, took
    assert run.unconfirmed == ["b"]


def test_a_module_whose_node_freezes_as_it_stops_leaves_the_others_their_teardowns(
        node_b, tmp_path: Path) -> None:
    """Node b hangs (its controller and executor stopped) while the close waits for the
    ``teardown`` of its module, stopped first: that stop waited until the close's time
    ran out, and the two modules of this machine stopped after it were killed, their
    teardowns unrun. A module whose node has not answered its heartbeats for as long as
    a lost node (2 s: its workers have stopped on their own by then) is not waited for
    any longer: the two tear down, in order, within the close's time, and the one on b
    is named as unreached (its worker stops it on its own), its node unconfirmed."""
    b = node_b
    journal, hold, began = tmp_path / "journal", tmp_path / "hold", tmp_path / "began"
    system = System("frozen-as-it-stops").node("a").node("b", address=b.address)
    for label in ("first", "second"):
        system.add(label, Journal, node="a", state={"path": str(journal), "label": label,
                                                    "teardown_s": 0.2})
    system.add("far", Journal, node="b", state={"path": str(journal), "label": "far",
                                                "hold": str(hold), "began": str(began)})
    hold.touch()                                  # (its teardown waits while it is there)
    run = system.launch(timeout=30)
    try:
        closing = threading.Thread(target=run.close, kwargs={"timeout": 6.0}, daemon=True)
        started = time.monotonic()
        closing.start()
        eventually(began.exists, what="the teardown of the module on b under way")
        with _frozen(b):
            closing.join(30)
            took = time.monotonic() - started
            lines = journal.read_text().splitlines()
    finally:
        hold.unlink()
        run.close()                               # (nothing, once closed)
    assert not closing.is_alive()
    assert [line for line in lines if line.startswith("stop")] == [
        "stop second", "stop first"], lines
    assert run.not_torn_down == []
    assert run.unreached == {"b": ["far"]} and run.unconfirmed == ["b"]
    assert took < 7.0, took


def test_a_node_slow_to_answer_as_the_close_reaches_its_module_is_waited_for(
        node_b, tmp_path: Path) -> None:
    """Node b answers nothing for about 0.6 s (a loaded machine), less than its lease
    (1.25 s) and than a lost node's silence (2 s), as the close goes on to its module:
    it was taken for lost after 0.5 s, its executor killed, its module's teardown run
    by its worker on its own and said not to have run. It is waited for: its module is
    torn down in turn, and the node's stop is confirmed."""
    b = node_b
    journal, hold, began = tmp_path / "journal", tmp_path / "hold", tmp_path / "began"
    system = System("slow-as-it-stops").node("a").node("b", address=b.address)
    system.add("far", Journal, node="b", state={"path": str(journal), "label": "far"})
    system.add("near", Journal, node="a", state={"path": str(journal), "label": "near",
                                                 "hold": str(hold), "began": str(began)})
    hold.touch()                                  # (near's teardown waits while it is there)
    run = system.launch(timeout=30)
    try:
        closing = threading.Thread(target=run.close, kwargs={"timeout": 10.0}, daemon=True)
        closing.start()
        eventually(began.exists, what="the teardown of the module on a under way")
        with frozen(b.executor_pid()):
            eventually(lambda: run._launcher.remotes["b"].silent_s() > 0.6,
                       what="b silent for 0.6 s")
            hold.unlink()                         # (the close goes on to far's stop)
            eventually(lambda: "stop near" in journal.read_text(), what="near torn down")
        closing.join(30)
    finally:
        hold.unlink(missing_ok=True)
        run.close()                               # (nothing, once closed)
    assert not closing.is_alive()
    assert journal.read_text().splitlines()[-2:] == ["stop near", "stop far"]
    assert run.not_torn_down == []
    assert run.unconfirmed == []


def test_a_slow_teardown_on_a_remote_node_is_waited_for_in_turn(node_b,
                                                                 tmp_path: Path) -> None:
    """A module of node b whose ``teardown`` takes 2.2 s, longer than the silence that
    makes a node's module not waited for (2 s) and than a fair share of the close
    (1.5 s of 6 s for four modules), is torn down before the modules started before it
    begin theirs: its node answers its heartbeats as it stops it. (With the fair
    shares, e93ca55, reverted, the module of this machine stopped next was torn down
    beside it.)"""
    b = node_b
    journal = tmp_path / "journal"
    system = System("slow-far").node("a").node("b", address=b.address)
    for label in ("first", "second", "third"):
        system.add(label, Journal, node="a", state={"path": str(journal), "label": label})
    system.add("far", Journal, node="b", state={"path": str(journal), "label": "far",
                                                "teardown_s": 2.2})
    run = system.launch(timeout=30)
    run.close(timeout=6.0)
    lines = journal.read_text().splitlines()
    assert [line for line in lines if line.startswith("stop")] == [
        "stop far", "stop third", "stop second", "stop first"], lines
    assert run.not_torn_down == []


def test_a_close_out_of_time_still_stops_a_remote_node_s_executor(node_b,
                                                                    tmp_path: Path) -> None:
    """A slow teardown spent close's time; the executor's stop then went with no time
    to wait, and a request with none was never sent: the executor ran on, and the same
    system launched again at once found node b working for the old launch."""
    b = node_b

    def system(teardown_s: float) -> System:
        made = System("again").node("a").node("b", address=b.address)
        made.add("slow", Journal, node="b", state={"path": str(tmp_path / "journal"),
                                                   "teardown_s": teardown_s})
        return made
    run = system(2.5).launch()
    executor = psutil.Process(b.executor_pid())
    run.close(timeout=2.0)
    executor.wait(5.0)                  # psutil.TimeoutExpired if it ran on
    assert run.unconfirmed == []
    # (the same system again, but for a teardown its close then waited 2.5 s for)
    with system(0.0).launch() as again:
        assert again.where("slow") == "b"


def test_the_watchdog_goes_on_after_a_look_that_fails(node_b, monkeypatch) -> None:
    """A look that raised (another node's failover thread changed the specs while the
    loss of a node read them) ended the watchdog: no node was declared lost any more."""
    b = node_b
    system = System("watched").node("a").node("b", address=b.address)
    system.add("far", Counter, node="b")
    with system.launch() as run:
        launcher, failover, looks = run._launcher, run._failover, []
        look = failover._look

        def failing_once(next_rejoin: float) -> float:
            looks.append(next_rejoin)
            if len(looks) == 1:
                raise RuntimeError("dictionary changed size during iteration")
            return look(next_rejoin)
        monkeypatch.setattr(failover, "_look", failing_once)
        eventually(lambda: len(looks) > 1, what="a look after the one that failed")
        os.kill(b.executor_pid(), signal.SIGKILL)
        assert launcher.wait_health("b", up=False, timeout=10)


def test_a_second_launch_of_a_running_configuration_is_refused_and_leaves_the_first(
        node_b) -> None:
    """The second launch, refused by node b ("already works for" the first launcher),
    stopped b's executor on its way out, the first system's: b was lost to it, its
    module gone for good."""
    b = node_b
    system = System("twice").node("a").node("b", address=b.address)
    system.add("far", Counter, node="b")
    with system.launch() as first:
        eventually(lambda: first.state("far")["count"] > 5, timeout=30, what="steps on b")
        with pytest.raises(RuntimeFailure, match=r"node b already works for .*: stop that "
                                                 r"system first"):
            system.launch()
        assert not first._launcher.wait_health("b", up=False, timeout=3.0)
        count = first.state("far")["count"]
        eventually(lambda: first.state("far")["count"] > count + 5, what="steps on b go on")


def test_a_launch_interrupted_as_a_node_starts_its_executor_leaves_none(
        node_b, monkeypatch) -> None:
    """A Ctrl-C while the launcher bound the executor it had a node start left that
    executor running, with no lease, until its controller stopped."""
    b = node_b
    call = ControlClient.call

    def interrupted(self, op: str, timeout: float = 10.0, **args):
        if op == "bind":
            raise KeyboardInterrupt
        return call(self, op, timeout, **args)
    monkeypatch.setattr(ControlClient, "call", interrupted)
    system = System("interrupted").node("a").node("b", address=b.address)
    system.add("far", Counter, node="b")
    with pytest.raises(KeyboardInterrupt):
        system.launch()
    monkeypatch.undo()
    controller = psutil.Process(b.process.pid)
    eventually(lambda: not [child for child in controller.children()
                            if "resource_tracker" not in " ".join(child.cmdline())],
               what="no executor under b's controller")


def test_a_frozen_executor_s_workers_stop_before_their_modules_run_elsewhere(
        node_b, tmp_path: Path) -> None:
    """A frozen executor (SIGSTOP) cannot fence itself: its workers stepped on beside
    their modules' failed-over copies until it ran again. Workers hold a lease of their
    own from a remote node's executor now, which lapses first."""
    b, stamps = node_b, tmp_path / "steps"
    with _stamping_on_b("frozen", b, stamps).launch() as run:
        eventually(lambda: stamps.exists() and stamps.read_text().count("\n") > 20,
                   what="steps on b")
        executor = b.executor_pid()
        os.kill(executor, signal.SIGSTOP)
        try:
            _wait_for_the_copy_on_a(run, stamps)
        finally:
            os.kill(executor, signal.SIGCONT)
    _assert_one_copy_at_a_time(stamps)


def test_a_module_that_holds_the_gil_past_the_lease_is_not_stopped_for_it(node_b) -> None:
    """A step of one C call that holds the GIL for 1.5 s (past a worker's 1.25 s lease)
    starved the worker's threads, its grants unread: it stopped itself as the call let
    go ("frozen past its lease while its executor ran"), its module restarted at every
    step and failed for good after six. The worker reads its lease's end where its
    executor writes it: as the call lets go, the end read is ahead."""
    system = System("gil").node("a").node("b", address=node_b.address)
    system.add("hog", HoldsTheGil, node="b", restart="fresh", state={"hold_s": 1.5})
    with system.launch() as run:
        eventually(lambda: run.state("hog", timeout=5.0)["steps"] >= 4, timeout=30,
                   what="four steps of 1.5 s")
        figures = run.stats().modules["hog"]
        kinds = {event.kind for event in run.events()}
    assert figures.restarts == 0 and figures.status == "running", figures
    assert not kinds & {"module_restarted", "module_failed", "node_lost"}, kinds


def test_a_module_whose_construction_outlasts_the_lease_starts_on_a_remote_node(
        node_b) -> None:
    """A worker's thread that read its lease grants also made its modules: one whose
    construction took 2.5 s held the grants unread past the lease, and the worker
    stopped itself ("worker 'b/m-slow' died"); the launch failed, as it did whenever it
    was tried. No thread of the worker carries its lease now."""
    system = System("slow-made").node("a").node("b", address=node_b.address)
    system.add("slow", SlowToMake, node="b", restart="fresh")
    with system.launch(timeout=30) as run:
        eventually(lambda: run.state("slow", timeout=5.0)["count"] > 20, timeout=30,
                   what="steps")
        figures = run.stats().modules["slow"]
    assert figures.restarts == 0 and figures.status == "running", figures


def test_a_worker_held_in_a_long_request_runs_its_modules_on(node_b) -> None:
    """A worker's thread that reads its requests, held in one (a module of its group
    being made, 5 s), read none of the lease grants its executor sent meanwhile: once
    the lease had been out 2 s the worker stopped itself, its executor running, and its
    other module, stepping all along, was restarted without its state; the add failed
    with the worker. Its lease's end is read where its executor writes it now: the
    module steps on through the add, nothing restarted."""
    system = System("held").node("a").node("b", address=node_b.address)
    system.add("steady", Steady, node="b", group="pair", restart="fresh")
    with system.launch() as run:
        before = eventually(lambda: (count := run.state("steady", timeout=5.0)["count"]) > 20
                            and count, timeout=30, what="steps on b")
        pid = run.stats().modules["steady"].pid
        run.add("slow", SlowerToMake, node="b", group="pair", restart="fresh", timeout=30)
        after = run.state("steady", timeout=5.0)["count"]
        figures = run.stats().modules
        kinds = {event.kind for event in run.events()}
    assert after > before + 100, (before, after)      # (5 s at 100 steps a second)
    steady = figures["steady"]
    assert (steady.status, steady.pid, steady.restarts) == ("running", pid, 0), steady
    assert figures["slow"].pid == pid
    assert not kinds & {"module_restarted", "module_failed", "node_lost"}, kinds


def test_a_frozen_node_let_run_again_steps_nothing_beside_its_failed_over_copies(
        node_b, tmp_path: Path) -> None:
    """A whole node frozen (its controller, executor and workers SIGSTOPped, as
    ``pb3a stress`` cuts a node) and let run again after its module failed over: its
    worker, let run first, stepped its module at once, beside the copy, before it
    looked at its lease (and a lease grant or a heartbeat read late, queued while the
    node was stopped, counted as a fresh one). No body runs once the lease is out; the
    workers' lease is the executor's; an executor frozen past its lease fences itself
    whatever heartbeats it reads then."""
    b, stamps = node_b, tmp_path / "steps"
    with _stamping_on_b("thawed", b, stamps).launch() as run:
        eventually(lambda: stamps.exists() and stamps.read_text().count("\n") > 20,
                   what="steps on b")
        _frozen_until_the_copy_runs_on_a(b, run, stamps)
    _assert_one_copy_at_a_time(stamps)


def test_a_node_frozen_as_its_module_begins_to_step_steps_nothing_beside_its_copy(
        node_b, tmp_path: Path) -> None:
    """... frozen as soon as its module stepped: its worker took the module before its
    first lease grant (up to 0.25 s later; a spare has none), so it held no lease and,
    let run again, stepped beside the copy until its executor fenced it (a step begun
    after the thaw). A worker takes its node's lease with its first module."""
    b, stamps = node_b, tmp_path / "steps"
    with _stamping_on_b("begun", b, stamps).launch() as run:
        deadline = time.monotonic() + 30
        while not (stamps.exists() and "\n" in stamps.read_text()):   # (at its first step)
            assert time.monotonic() < deadline, "no step on b"
            time.sleep(0.001)
        _frozen_until_the_copy_runs_on_a(b, run, stamps)
    _assert_one_copy_at_a_time(stamps)


def test_a_fenced_worker_s_slow_teardown_does_not_run_beside_its_copy(
        node_b, tmp_path: Path) -> None:
    """A worker whose lease ran out (its executor frozen) tore its modules down however
    long that took: a teardown of 1.5 s ran on beside the copy the launcher started
    elsewhere 0.5 s after the lease's end. A fenced worker is gone by ``GONE_BY_S``
    after that end, its teardowns cut short."""
    b, stamps = node_b, tmp_path / "steps"
    with _slow_to_stop_on(b, stamps, "slow-stop") as run:
        old = psutil.Process(run.stats().modules["stepper"].pid)
        executor = psutil.Process(b.executor_pid())
        executor.suspend()
        try:
            _wait_for_the_copy_on_a(run, stamps)
            eventually(lambda: _gone(old), timeout=10, what="b's worker gone")
        finally:
            with contextlib.suppress(psutil.NoSuchProcess):    # (its controller killed it)
                executor.resume()
    _assert_one_copy_at_a_time(stamps)


def test_a_node_whose_executor_dies_is_lost_at_once_its_teardowns_cut_before_the_copy(
        node_b, tmp_path: Path) -> None:
    """A node whose executor was killed was taken for lost only once it had been silent
    for ``LOSS_S`` (2 s), though its controller saw the death at once: a control loop
    ran open that long (|error| 0.84 against 0.15, a reviewer's PID loop). Its
    controller is asked once the node has missed two heartbeats, and says how the
    executor ended once every process it started has ended too (those still alive
    killed then: the worker tearing its module down, which the forkserver had told to
    stop); the node is lost then, and the module's copy steps with no old step beside it."""
    b, stamps = node_b, tmp_path / "steps"
    with _slow_to_stop_on(b, stamps, "killed") as run:
        old = psutil.Process(run.stats().modules["stepper"].pid)
        os.kill(b.executor_pid(), signal.SIGKILL)
        _wait_for_the_copy_on_a(run, stamps)
        assert _gone(old)
        (lost,) = _events(run, "node_lost")
        failures = run.stats().failures
    assert lost.detail["executor"].startswith("was killed by SIGKILL"), lost.detail
    assert lost.detail["silent_s"] < 1.5, lost.detail         # (LOSS_S: 2 s)
    assert any("its controller says its executor was killed by SIGKILL" in failure
               for failure in failures), failures
    _assert_one_copy_at_a_time(stamps)


def test_a_node_whose_controller_is_stopped_says_so_and_is_lost_at_once(capfd) -> None:
    """A node controller stopped (SIGTERM, as ``systemctl stop`` sends) with a module on
    it looked to the launcher like a cut cable: the node was lost after 2 s (``LOSS_S``)
    with no reason (executor None), and the controller logged nothing of its stop. It
    logs that it stops and which executors stop with it, and answers, as it stops, that
    each was stopped as it did: the node is lost then, saying so. (b is started here,
    not by a fixture: its log then goes where ``capfd`` reads.)"""
    b = Daemon("b")
    try:
        system = System("controller-stopped").node("a").node("b", address=b.address)
        system.add("far", Collector, node="b", restart="fresh", fallback=["a"])
        with system.launch() as run:
            b.process.send_signal(signal.SIGTERM)
            # (its health goes down first, its event is recorded a moment after)
            (lost,) = eventually(lambda: _events(run, "node_lost"), timeout=10,
                                 what="node b lost")
        b.process.wait(10)
    finally:
        b.stop()
    assert lost.detail["executor"] == (
        "was stopped: its node controller stopped (SIGTERM)"), lost.detail
    assert lost.detail["silent_s"] < 1.5, lost.detail             # (LOSS_S: 2 s)
    assert "node b: stopping (SIGTERM): executors for 'controller-stopped' stop" in (
        capfd.readouterr().err)


@contextlib.contextmanager
def _slow_to_stop_on(b: Daemon, stamps: Path, name: str) -> Iterator[Any]:
    """System ``name`` running, once it has stepped: its module on node ``b`` stamps each
    step in ``stamps`` and takes 1.5 s to tear down, and fails over to node a."""
    system = System(name).node("a").node("b", address=b.address)
    system.add("stepper", SlowToStop, node="b", restart="fresh", fallback=["a"],
               state={"path": str(stamps), "teardown_s": 1.5})
    with system.launch() as run:
        eventually(lambda: stamps.exists() and stamps.read_text().count("\n") > 20,
                   what="steps on b")
        yield run


def _gone(process: psutil.Process) -> bool:
    """Whether ``process`` has ended (a zombie no one reaps yet counts)."""
    try:
        return process.status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def _frozen_until_the_copy_runs_on_a(b: Daemon, run, stamps: Path) -> None:
    """Node b frozen whole (SIGSTOP: its controller, executor and workers) until its
    module's copy steps on a, then let run again (the workers first, as Freeze) for 1 s."""
    controller = psutil.Process(b.process.pid)
    frozen = [controller, *controller.children(recursive=True)]
    for process in frozen:
        process.suspend()
    try:
        _wait_for_the_copy_on_a(run, stamps)
    finally:
        for process in reversed(frozen):
            with contextlib.suppress(psutil.NoSuchProcess):
                process.resume()
    time.sleep(1.0)                                     # what the thawed node does


def test_a_module_whose_setup_raises_where_it_fails_over_is_failed_not_failed_over(
        node_b, tmp_path: Path) -> None:
    """Node b is lost; its three modules fail over to a, where one's setup raises (its
    device is not there either): that one is failed (``module_failed``, not
    ``module_failed_over``, and the env modules are not told it moved), the other two
    run there (they were left "starting", never started)."""
    unplugged = tmp_path / "unplugged"
    b = node_b
    system = System("failover-setup").node("a").node("b", address=b.address)
    system.add("cam", OpensDevice, node="b", restart="fresh", fallback=["a"],
               state={"unplugged": str(unplugged)})
    for name in ("one", "two"):
        system.add(name, Steady, node="b", restart="fresh", fallback=["a"])
    system.add("moves", MoveLog, node="a")
    system.link("env-a.module_moved", "moves.moved")
    with system.launch() as run:
        eventually(lambda: run.state("cam")["steps"] > 3, timeout=20, what="steps on b")
        unplugged.touch()
        os.kill(b.executor_pid(), signal.SIGKILL)
        def failed_over() -> dict | None:
            modules = run.stats().modules      # (read during the failover too: it says so;
            # and before b is lost, its modules silent on b)
            return modules if all(name in modules and modules[name].status == "running"
                                  and modules[name].node == "a" for name in ("one", "two")) \
                and not any(module.change for module in modules.values()) else None
        modules = eventually(failed_over, timeout=30, what="the failover")
        assert (modules["cam"].node, modules["cam"].status) == ("a", "failed")
        eventually(lambda: run.state("two")["count"] > 3, what="two steps on a")
        assert sorted(e.subject for e in _events(run, "module_failed_over")) == ["one", "two"]
        failed, = [e for e in _events(run, "module_failed") if e.subject == "cam"]
        assert "raised in setup" in failed.detail["reason"]
        assert "cam" not in [move["module"] for move in run.state("moves")["moves"]]


def test_an_agent_that_reads_the_runtime_from_its_setup_fails_over(node_b) -> None:
    """The failover held the configuration lock without lending it to the modules it
    starts: an agent asking the runtime from its setup (the shipped agents check the
    modules their settings name) waited for it, its start ran out of time after 10 s,
    and it was failed, not failed over."""
    b = node_b
    system = System("asking").node("a").node("b", address=b.address)
    system.add("other", Counter, node="a", period=0.01)
    system.add("agent", AsksInSetup, node="b", restart="fresh", fallback=["a"])
    with system.launch() as run:
        eventually(lambda: run.state("agent")["steps"] > 0, timeout=30, what="the agent on b")
        b.kill()
        moved = eventually(lambda: _events(run, "module_failed_over"), timeout=15,
                           what="the agent failed over")
        assert moved[0].detail["restart_s"] < 3.0 and not _events(run, "module_failed")
        state = eventually(lambda: (s := run.state("agent"))["steps"] > 0 and s,
                           what="the agent stepping on a")
        assert run.where("agent") == "a" and state["asked"] >= 0


def test_a_rejoin_that_cannot_take_the_lock_stops_the_executor_it_started(node_b) -> None:
    """A lost node's controller answering again gets a new executor, then the launcher
    takes its lock to admit it. When the lock was not free in time, the new executor
    and the heartbeats that renewed its lease were left running for good, one pair per
    attempt. It is stopped, and the node is admitted at the next attempt."""
    b = node_b
    system = System("rejoin-lock").node("a").node("b", address=b.address)
    system.add("tick", Counter, node="a")
    with system.launch() as run:
        launcher = run._launcher
        started, start = [], launcher.start_remote_node
        launcher.start_remote_node = lambda *a, **k: started.append(start(*a, **k)) or started[-1]
        acquire, refused = launcher.lock._acquire, []

        def busy_once(what: str, timeout: float | None, *rest) -> None:
            if what.startswith("admit node b") and not refused:
                refused.append(what)
                raise RuntimeTimeout(f"{what}: the lock is busy")
            acquire(what, timeout, *rest)
        launcher.lock._acquire = busy_once
        os.kill(b.executor_pid(), signal.SIGKILL)
        eventually(lambda: _events(run, "node_joined"), timeout=30, what="node b admitted again")
        assert refused and len(started) == 2
        assert started[0]._closed.is_set() and not started[1]._closed.is_set()
        assert launcher.remotes["b"] is started[1]


def test_a_lost_node_whose_controller_comes_back_with_another_key_says_why_it_stays_lost(
        node_b, caplog) -> None:
    """A robot whose controller came back with another key copy stayed LOST, and
    nothing on the workstation said why: `pb3a nodes` showed it lost, the launcher's
    log and the events said nothing (an operator's review). The launcher logs it once,
    and `pb3a nodes` shows the refusal and what to do."""
    system = System("rekeyed").node("a").node("b", address=node_b.address)
    system.add("far", Steady, node="b", restart="fresh", fallback=["a"])
    with caplog.at_level(logging.WARNING, logger="pb3a.launcher"), \
            system.launch() as run:
        node_b.kill()
        assert run._launcher.wait_health("b", up=False, timeout=10)
        node_b.start(key=os.urandom(32).hex())
        refused = eventually(lambda: run.nodes()["b"].refused, timeout=15,
                             what="the refusal seen by the rejoin")
        assert "runs with another cluster key" in refused, refused
        table = format_nodes(run.nodes())
        assert "LOST (refuses us: see below)" in table and f"b: {refused}" in table, table
        run.wait(2.5)                           # (two more attempts to rejoin)
        said = [record.getMessage() for record in caplog.records
                if "cannot rejoin" in record.getMessage()]
        assert len(said) == 1 and "another cluster key" in said[0], said


class _Admission:
    """A stand-in for one admission of a remote node (a ``RemoteNode``), silent since
    ``answered_ago`` seconds."""

    def __init__(self, answered_ago: float, lost: bool) -> None:
        self.lost, self.ended, self.rtt, self.node_epoch = lost, None, 0.001, 1
        self._answered = time.monotonic() - answered_ago

    def silent_s(self) -> float:
        return time.monotonic() - self._answered

    def lose(self) -> None:
        self.lost = True


class _Launcher:
    """What the watchdog reads of a launcher, with remote node r, its admission ``old``
    silent for 30 s."""

    def __init__(self, old: _Admission) -> None:
        self.stopping, self.changed = threading.Event(), threading.Condition()
        self.failures = FailureLog(logging.getLogger("pb3a.test"))
        self.events, self.started = EventLog(), []
        self.specs: dict = {}
        self.arriving: dict = {}
        self.nodes, self.remotes = {"r": old}, {"r": old}

    def start_background(self, thread: threading.Thread) -> None:
        self.started.append(thread.name)


@pytest.mark.parametrize("old_lost", [True, False], ids=["its loss said", "its loss not said"])
def test_a_node_admitted_again_as_the_watchdog_looks_is_not_lost_again(old_lost: bool) -> None:
    """The watchdog took its list of remote nodes, then read each one's health: a rejoin
    in between (another thread) put in the new admission and said it up, and the
    watchdog measured the old admission's silence (lost long ago) against it: the node
    just let in was said lost (node_lost, its env module failed over, a second rejoin).
    Here the rejoin runs as the watchdog reads the health; with the old admission's
    loss not said, the loss itself is what finds the node admitted anew."""
    old, new = _Admission(30.0, lost=old_lost), _Admission(0.0, lost=False)
    launcher = _Launcher(old)

    class RejoinedAsRead(dict):
        """Node r's health, which a rejoin changes as the watchdog first reads it."""

        def __getitem__(self, key: str) -> Any:
            if key == "up" and launcher.remotes["r"] is old:
                with launcher.changed:
                    launcher.nodes["r"] = launcher.remotes["r"] = new
                    self.update(up=True, rtt=new.rtt, controller=True, epoch=2)
            return dict.__getitem__(self, key)

    launcher.health = {"r": RejoinedAsRead(up=False, rtt=math.nan, address="x", epoch=1)}
    failover = Failover(launcher, env=None)     # type: ignore[arg-type]
    failover._look(time.monotonic() + 10)
    assert not new.lost and launcher.health["r"]["up"]
    assert launcher.events.since(0) == [] and launcher.started == []
