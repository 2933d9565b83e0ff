"""Failover and rejoin: the modules of a lost node start again on a surviving one within
1 s (``fresh``, or ``last-state`` from a checkpoint kept off the lost node), their links
are wired again and what was lost counted; the node, once back, is admitted under a
new epoch and modules can be moved back; a fenced executor's word is refused."""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator

import cloudpickle
import pytest
from conftest import Daemon, eventually
from sample_modules import Collector, Counter, Join, MoveLog, Relay

from pb3a import RuntimeFailure, System
from pb3a.daemons.node_controller import Limits, NodeController
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient

pytestmark = pytest.mark.timeout(120)


@pytest.fixture
def daemons() -> Iterator[dict[str, Daemon]]:
    made: dict[str, Daemon] = {}
    try:
        for name in ("b", "c"):
            made[name] = Daemon(name)
        yield made
    finally:
        for daemon in made.values():
            daemon.stop()


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
    assert lost_event.detail["modules"] == ["far", "gone", "relay"]
    where = {event.subject: event.detail for event in moved}
    assert where["relay"]["destination"] == "c"                   # its first fallback
    assert where["relay"]["from_checkpoint"] and not where["far"]["from_checkpoint"]
    assert where["far"]["destination"] in ("a", "c")              # the least loaded
    assert all(detail["restart_s"] < 1.0 for detail in where.values()), where
    assert relay["setups"] == kept["setups"] + 1 >= 2             # its checkpoint, restored
    assert "gone" not in stats.modules and "src.out->gone.x" not in stats.links
    assert stats.modules["relay"].node == "c" and stats.modules["far"].node in ("a", "c")
    # what src wrote while nobody on b read it is counted, never silently gone
    assert stats.links["src.out->relay.x"].link_failures > 500
    assert stats.links["src.out->far.x"].link_failures > 500
    assert joined[0].detail["epoch"] == 2
    assert {(move["module"], move["destination"]) for move in told} == {
        (name, detail["destination"]) for name, detail in where.items()}


def test_a_fenced_executors_word_is_refused_and_placement_follows_admission() -> None:
    b = NodeController("b", ClusterKey.load(), limits=Limits(max_cpu_percent=101.0))
    c = NodeController("c", ClusterKey.load(), limits=Limits(max_cpu_percent=101.0))
    try:
        system = System("fenced").node("a").node("b", address=b.address)
        system.node("c", address=c.address)
        system.add("src", Counter, node="a", period=0.001)
        system.add("relay", Relay, node="b", restart="fresh", fallback=["c", "a"])
        system.add("near", Collector, node="a")
        system.link("src.out", "relay.x")
        system.link("relay.out", "near.x")
        with system.launch() as run:
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


def _relayed(name: str, b: Daemon, relay_on: str, restart: str) -> System:
    """src -> relay -> sink, src and sink on a, b behind its node controller."""
    system = System(name).node("a").node("b", address=b.address)
    system.add("src", Counter, node="a", period=0.005)
    system.add("relay", Relay, node=relay_on, restart=restart)
    system.add("sink", Collector, node="a")
    system.link("src.out", "relay.x")
    system.link("relay.out", "sink.x")
    return system


def test_a_node_lost_while_a_change_holds_the_lock_long_still_fails_over(daemons,
                                                                        monkeypatch) -> None:
    """The failover's wait for the configuration lock ran out (60 s by default) inside
    the watchdog's thread, which died of it: no node was ever lost, failed over or let
    back in again."""
    b = daemons["b"]
    monkeypatch.setattr("pb3a.launch.launcher.FAIL_OVER_WAIT_S", 0.2)
    with _relayed("patient", b, relay_on="b", restart="fresh").launch() as run:
        launcher = run._launcher
        eventually(lambda: run.state("sink")["received"] > 20, timeout=30, what="values")
        with launcher.lock.held("a long change"):
            os.kill(b.executor_pid(), signal.SIGKILL)
            assert launcher.wait_health("b", up=False, timeout=10)
            eventually(lambda: any(e.kind == "node_lost" for e in run.events()),
                       what="the loss")
            assert not _events(run, "module_failed_over")       # (the lock is held)
        moved = eventually(lambda: _events(run, "module_failed_over"), timeout=10,
                           what="the failover once the lock is free")
        received = run.state("sink")["received"]
        eventually(lambda: run.state("sink")["received"] > received + 20, timeout=15,
                   what="values through the relay failed over")
        eventually(lambda: _events(run, "node_joined"), timeout=20, what="b back")
    assert moved[0].subject == "relay" and moved[0].detail["destination"] == "a"


def test_a_module_put_back_by_a_move_that_its_destination_s_loss_failed_is_left_alone(
        daemons) -> None:
    """The failover read which modules were on the lost node before it took the lock,
    while the move still had the module there: once the move had put it back where it
    ran, the failover dropped it (restart never; its worker ran on) or restarted it."""
    b = daemons["b"]
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
        eventually(lambda: any(e.kind == "node_lost" for e in run.events()), timeout=10,
                   what="b lost")
        relayed = run.state("relay")["relayed"]
        eventually(lambda: run.state("relay")["relayed"] > relayed + 20, timeout=10,
                   what="the relay running on a")
        assert run.where("relay") == "a" and not _events(run, "module_failed_over")
        assert run.state("sink")["received"] > relayed


def test_a_move_that_a_writer_s_node_loss_failed_leaves_the_rest_running(daemons) -> None:
    """The move's undoing wired the module's links again in one go: the link from the
    lost node failed it, and the module, put back, was never started; the writer on a
    surviving node resumed after the pause only if it came first."""
    b = daemons["b"]
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
