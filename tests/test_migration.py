"""Live migration between embedded nodes: state and queued inputs move, links follow
(shared memory <-> ZeroMQ), and no value is lost, duplicated or reordered."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import alive, assert_same_arrays, eventually
from sample_modules import (
    Collector,
    Counter,
    FailingRelay,
    Fussy,
    Hoard,
    MapMaker,
    Relay,
    RelayPair,
    Shepherd,
    Staller,
    Wanderer,
)

from pb3a import ConfigError, Input, Module, ModuleNotFound, RuntimeFailure, RuntimeTimeout, System
from pb3a.cli.main import main
from pb3a.node.executor import Executor


def _nodes(system: System, *names: str) -> System:
    for name in names:
        system.node(name)
    return system


def _through(name: str, middle: str, cls: type) -> System:
    """src -> ``middle`` (a ``cls``: a relay, or a macro of two) -> sink, all on node a
    of nodes a and b."""
    system = _nodes(System(name), "a", "b")
    system.add("src", Counter, node="a", period=0.001)
    system.add(middle, cls, node="a")
    system.add("sink", Collector, node="a")
    system.link("src.out", f"{middle}.x")
    system.link(f"{middle}.out", "sink.x")
    return system


def test_a_module_moves_with_its_state_and_its_links_follow() -> None:
    with _through("move-one", "relay", Relay).launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 20, what="values through relay")
        before = run.state("relay")["relayed"]
        report = run.migrate("relay", to="b")
        after = run.stats()
        eventually(lambda: run.state("relay")["relayed"] > before + 20, what="values after it")
        state = run.state("relay")
        sink = run.state("sink")
    assert (report.module, report.source, report.destination) == ("relay", "a", "b")
    assert 0 < report.pause_s < 5 and report.state_bytes > 0 and report.links == 2
    assert after.modules["relay"].node == "b"
    assert {key: link.transport for key, link in after.links.items()} == {
        "src.out->relay.x": "zmq", "relay.out->sink.x": "zmq"}
    assert state["relayed"] >= before and state["setups"] == 2       # setup again after it
    assert sink["out_of_order"] == 0 and sink["duplicates"] == 0
    assert sink["last"] == sink["received"]                          # 1, 2, 3, ... no gap


def test_a_moved_module_keeps_its_counters() -> None:
    """Its steps, calls, errors and values written started from 0 in the new process:
    an agent reading a rate or an error trend from ``stats()`` saw them fall at every
    move (steps from 148 to 6). They go with it, as its inputs' counters did."""
    with _through("move-counters", "relay", FailingRelay).launch() as run:
        eventually(lambda: run.stats().modules["relay"].events > 500, what="calls")
        run.set_state("relay", failing=True)                # its calls raise
        eventually(lambda: run.stats().modules["relay"].errors > 500, what="errors")
        before = run.stats().modules["relay"]
        run.migrate("relay", to="b")
        after = run.stats().modules["relay"]
    # (a new process's counts in the moment since could not reach them)
    assert after.node == "b" and after.events >= before.events > 500
    assert after.errors >= before.errors and after.last_error == before.last_error
    assert after.outputs["out"] >= before.outputs["out"] > 0


def test_state_a_module_made_as_it_ran_moves_with_it() -> None:
    """State made in ``setup`` and ``step`` (``grid``, ``updates``, which ``state()``
    reports) was refused at the destination (a name the new instance lacks), and again
    at the source by the move's undo: the module was left "starting", running
    nowhere, with only ``migration_failed`` said."""
    system = _nodes(System("move-made"), "a", "b")
    system.add("mapper", MapMaker, node="a")
    with system.launch() as run:
        eventually(lambda: run.state("mapper").get("updates", 0) > 20, what="steps")
        for there in ("b", "a"):
            before = run.state("mapper")
            run.migrate("mapper", to=there)
            after = run.state("mapper")
            assert run.where("mapper") == there
            assert after["updates"] >= before["updates"] > 20
            assert after["grid"][0, 0] >= before["grid"][0, 0] > 20
        eventually(lambda: run.state("mapper")["updates"] > after["updates"],
                   what="steps at a again")
        assert run.state("mapper")["setups"] == 3           # its own, and after each move
        assert [event.kind for event in run.events()] == ["module_moved"] * 2


def test_a_module_whose_state_cannot_be_put_back_after_a_failed_move_is_failed(
        tmp_path: Path) -> None:
    """Its state refused at the destination and again at the source, where the failed
    move put it back: it was left "starting" for good, running nowhere, with only
    ``migration_failed`` said, and only a restart ran it again."""
    refuse = tmp_path / "refuse"
    system = _nodes(System("move-unrestored"), "a", "b")
    system.add("fussy", Fussy, node="a", state={"refuse": str(refuse)})
    system.add("other", Counter, node="a", period=0.01)
    with system.launch() as run:
        eventually(lambda: run.state("fussy")["steps"] > 3, what="steps")
        refuse.touch()
        with pytest.raises(RuntimeFailure, match=r"migration of fussy to node b failed .*"
                                                 r"putting it back on node a failed too "
                                                 r"\(.*state refused while"):
            run.migrate("fussy", to="b")
        figures = run.stats().modules["fussy"]
        assert run.where("fussy") == "a" and figures.status == "failed"
        failed = [event for event in run.events() if event.kind == "module_failed"]
        assert [event.subject for event in failed] == ["fussy"]
        assert "its state could not be put back where it ran" in failed[0].detail["reason"]
        assert run.stats().modules["other"].status == "running"
        refuse.unlink()
        run.restart("fussy")
        eventually(lambda: run.state("fussy")["steps"] > 3, what="it steps again at a")


@pytest.mark.parametrize("policy", ["queue:1000000", "lossless:64"])
def test_100_migrations_under_a_steady_flow_lose_duplicate_and_reorder_nothing(
        policy: str) -> None:
    """Every value arrives once, in order. A ``queue`` link may not send some, counted
    in its drops: one judged slow (a message not acknowledged within 0.5 s, which an
    overloaded machine's scheduling makes) sends only the newest (see "Slow links" in
    ``pb3a.transport.replication``); a ``lossless`` one sends every value."""
    n = 4000
    system = _nodes(System("move-many"), "a", "b", "c")
    system.add("src", Counter, node="a", period=0.0005, state={"limit": n})
    system.add("relay", Relay, node="a")
    system.add("direct", Collector, node="c")          # fan-out of src to another node
    system.link("src.out", "relay.x", policy=policy)
    system.link("src.out", "direct.x", policy=policy)
    readers = {"direct": "src.out->direct.x"}
    for name, node in (("on_a", "a"), ("on_b", "b"), ("on_c", "c")):
        system.add(name, Collector, node=node)          # fan-out of relay to every node
        system.link("relay.out", f"{name}.x", policy=policy)
        readers[name] = f"relay.out->{name}.x"
    with system.launch() as run:
        nodes = ["b", "c", "a"]
        pauses = []
        for i in range(100):
            pauses.append(run.migrate("relay", to=nodes[i % 3]).pause_s)
        assert run.stats().modules["relay"].node == nodes[99 % 3]

        def seen() -> dict[str, Any]:
            links = run.stats().links
            return {name: (run.state(name), links[key])
                    for name, key in (*readers.items(), ("relay", "src.out->relay.x"))}

        def written(name: str, now: dict[str, Any]) -> int:
            """What the reader's writer wrote: relay's readers get what came to it."""
            return n if name == "direct" else now["relay"][0]["relayed"]

        def came_or_counted(now: dict[str, Any]) -> dict[str, int]:
            return {name: state["relayed" if name == "relay" else "received"] + link.drops
                    for name, (state, link) in now.items()}

        def every_value_came_or_was_counted() -> bool:
            now = seen()
            got = came_or_counted(now)
            return got["relay"] >= n and all(got[name] >= written(name, now)
                                              for name in readers)

        eventually(every_value_came_or_was_counted, timeout=60,
                   what=f"{n} values at each reader, received or counted dropped",
                   context=seen)
        final = seen()
    got = came_or_counted(final)
    assert got["relay"] == n
    for name in readers:
        state, link = final[name]
        assert got[name] == written(name, final) and link.link_failures == 0, name
        assert state["out_of_order"] == state["duplicates"] == 0, name
        if policy.startswith("lossless"):
            assert state["received"] == state["last"] == n and link.drops == 0, name
    assert final["relay"][1].link_failures == 0
    assert len(pauses) == 100 and max(pauses) < 5


@pytest.mark.parametrize("machines", ["one", "two"])
def test_megabytes_of_numpy_state_move_intact(machines, monkeypatch) -> None:
    if machines == "two":       # as if b were another machine: the state goes in requests
        monkeypatch.setattr(Executor, "memory_domain", lambda self: self.node)
    n = 300
    system = _nodes(System(f"move-arrays-{machines}"), "a", "b")
    system.add("src", Counter, node="a", period=0.002, state={"limit": n})
    system.add("hoard", Hoard, node="a")
    system.link("src.out", "hoard.x")
    with system.launch() as run:
        eventually(lambda: run.state("hoard")["stored"] > 20, what="values at the hoard")
        reports = [run.migrate("hoard", to=to) for to in ("b", "a", "b")]
        state = eventually(lambda: (s := run.state("hoard"))["stored"] >= n and s,
                           what=f"{n} values at the hoard")
    grid, marks = Hoard.expected(n)
    assert state["stored"] == n
    assert_same_arrays(state, {"grid": grid, "marks": marks})   # written to after each move
    for report in reports:
        assert report.state_bytes > grid.nbytes + marks.nbytes
        assert sum(dataclasses.astuple(report.phases)) == pytest.approx(report.pause_s)


def test_a_macro_moves_as_one_under_a_steady_flow() -> None:
    with _through("move-macro", "pair", RelayPair).launch() as run:
        eventually(lambda: run.state("sink")["received"] > 20, what="values through the pair")
        there = run.migrate("pair", to="b")
        inside = run.stats().links["pair/first.out->pair/second.x"].transport
        back = run.migrate("pair", to="a")
        moved = [e for e in run.events() if e.kind == "module_moved"]
        n = run.state("src")["count"]
        state = eventually(lambda: (s := run.state("sink"))["received"] >= n and s,
                           timeout=30, what="every value through the pair")
    assert [(e.subject, e.detail["destination"]) for e in moved] == [
        ("pair/first", "b"), ("pair/second", "b"), ("pair/first", "a"), ("pair/second", "a")]
    # its modules paused once, together, each way; the link between them stayed inside
    assert moved[0].detail["pause_s"] == moved[1].detail["pause_s"] == there.pause_s
    assert moved[2].detail["pause_s"] == moved[3].detail["pause_s"] == back.pause_s
    assert there.destination == "b" and there.links == 3 and inside == "shm"
    # booting b's workers came before the pause, and is reported apart from it
    assert there.prepare_s > 0 and back.prepare_s > 0
    assert state["out_of_order"] == 0 and state["duplicates"] == 0
    assert state["last"] == state["received"]                        # 1, 2, 3, ... no gap


def test_state_given_on_arrival_is_set_before_the_module_starts_there_or_not_at_all() -> None:
    with _through("move-arrive", "pair", RelayPair).launch() as run:
        eventually(lambda: run.state("sink")["received"] > 20, what="values through the pair")
        with pytest.raises(ValueError, match="state on arrival for 'sink', which does not "
                                             "move; what moves: pair/first, pair/second"):
            run.migrate("pair", to="b", state={"sink": {"received": 0}})
        # a field the module lacks: the move fails after the fence and is put back whole
        with pytest.raises(RuntimeFailure, match=r"has no state 'gian'.*they run on node a "
                                                 r"again, with their state"):
            run.migrate("pair", to="b", state={"pair/first": {"gian": 2.0}})
        back = run.stats().modules
        relayed = run.state("pair/second")["relayed"]
        report = run.migrate("pair", to="b", state={"pair/second": {"setups": 100}})
        second, first = run.state("pair/second"), run.state("pair/first")
        n = run.state("src")["count"]
        sink = eventually(lambda: (s := run.state("sink"))["received"] >= n and s,
                          timeout=30, what="every value through the pair")
    assert {back["pair/first"].node, back["pair/second"].node} == {"a"}
    assert report.destination == "b"
    # set on arrival, then setup() ran on it (100 + 1); the rest of its state came along
    assert second["setups"] == 101 and second["relayed"] >= relayed
    assert first["setups"] == 3          # a, put back on a (the failed move), then b
    assert sink["out_of_order"] == 0 and sink["duplicates"] == 0
    assert sink["last"] == sink["received"]


def test_an_agent_moves_itself_and_goes_on_where_it_was() -> None:
    system = _nodes(System("wander"), "a", "b")
    system.add("src", Counter, node="a", period=0.001)
    system.add("wanderer", Wanderer, node="a")
    system.link("src.out", "wanderer.x")
    with system.launch() as run:
        eventually(lambda: run.stats().modules["wanderer"].node == "b",
                   what="the agent on node b")
        seen = run.state("wanderer")["seen"]
        eventually(lambda: run.state("wanderer")["seen"] > seen + 10, what="values at b")
        assert run.state("wanderer")["asked"] is True


def test_a_node_makes_one_bridge_for_its_remote_links_however_many_ask_at_once(
        monkeypatch) -> None:
    """A node makes the bridge its remote links come in by when one is first needed. A
    report (``stats()``) that asked for it as a move opened the node's first remote
    link made a second one: the move put the link's ring in one and followed the
    link's sender with the other, which dropped every value from then on (an agent
    that moved itself, as ``stats()`` was asked in a loop, got no value at its new node
    once in three). It is made once."""
    made: list[object] = []
    both = threading.Barrier(2, timeout=1.0)

    class Meeting:                          # (a second one made meanwhile meets it here)
        def __init__(self, *args: object) -> None:
            made.append(self)
            with contextlib.suppress(threading.BrokenBarrierError):
                both.wait()

        def shutdown(self) -> None:
            pass
    monkeypatch.setattr("pb3a.node.executor.Bridge", Meeting)
    executor = Executor("n1")
    try:
        given: list[object] = []
        askers = [threading.Thread(target=lambda: given.append(executor.bridge))
                  for _ in range(2)]
        for asker in askers:
            asker.start()
        for asker in askers:
            asker.join(5)
        assert len(made) == 1 and given == made * 2
    finally:
        executor.shutdown(timeout=1.0)


def test_migration_to_an_unknown_node_or_of_an_unknown_module_is_refused() -> None:
    system = _nodes(System("move-bad"), "a", "b")
    system.add("relay", Relay, node="a")
    with system.launch() as run:
        with pytest.raises(ConfigError, match="no node 'z'; nodes: a, b"):
            run.migrate("relay", to="z")
        with pytest.raises(ModuleNotFound, match="no module 'ghost'"):
            run.migrate("ghost", to="b")
        assert run.stats().modules["relay"].node == "a"


def test_a_move_failed_as_its_destination_is_prepared_says_where_the_module_runs(
        monkeypatch) -> None:
    """A destination lost as it was prepared failed the move saying only that (its
    executor "failed: node b is lost"), not where the module was; as a move that runs
    out of time there does, it says nothing moved and where the module runs."""
    with _through("move-prepare-fails", "relay", Relay).launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 20, what="values through relay")
        b = run._launcher.nodes["b"]

        def lost(*args, **kwargs):
            raise RuntimeFailure("node b is lost")
        monkeypatch.setattr(b, "add_module", lost)
        with pytest.raises(RuntimeFailure, match=r"^node b is lost; nothing moved: relay "
                           r"runs on node a as before$"):
            run.migrate("relay", to="b")
        monkeypatch.undo()
        assert run.where("relay") == "a"
        relayed = run.state("relay")["relayed"]
        eventually(lambda: run.state("relay")["relayed"] > relayed + 20, what="values on")


class Heavy(Module):
    """40 MiB of state, made in ``setup``."""

    period = 0.1

    def setup(self) -> None:
        if not hasattr(self, "weights"):
            self.weights = np.ones(5 * 2**20)

    def step(self) -> None:
        self.weights[0] += 1


def test_a_move_given_too_little_time_does_not_blame_a_stuck_module() -> None:
    """A move given 30 ms for 40 MiB ran out preparing the destination, and the error
    went on to say the worker "did not answer 'add' within 0 s: a module there is stuck
    in a long call ... or its machine is overloaded", which nothing was."""
    system = _nodes(System("move-hurried"), "a", "b")
    system.add("heavy", Heavy, node="a")
    with system.launch() as run:
        eventually(lambda: run.stats().modules["heavy"].status == "running", what="running")
        with pytest.raises(RuntimeTimeout) as raised:
            run.migrate("heavy", to="b", timeout=0.03)
        assert "ran out while" in str(raised.value) and "nothing moved" in str(raised.value)
        assert "stuck" not in str(raised.value) and "within 0 s" not in str(raised.value)
        assert run.where("heavy") == "a"


class HoldsALock(Relay):
    """A module that keeps a lock in a public field: state that cannot be pickled."""

    def setup(self) -> None:
        self.guard = threading.Lock()


def test_state_that_cannot_be_pickled_is_named_by_a_move_and_by_a_checkpoint_once() -> None:
    """pickle's own error names only the type ("cannot pickle '_thread.lock' object"):
    a move said no more, and a checkpoint logged a traceback every time, not naming the
    field either."""
    system = _nodes(System("move-lock"), "a", "b")
    system.add("held", HoldsALock, node="a", restart="last-state")
    with system.launch(checkpoint_s=0.05) as run:
        def said() -> list[str]:
            return [e.message for e in run.logs() if "cannot checkpoint" in e.message]

        eventually(said, what="a checkpoint refused")
        with pytest.raises(RuntimeFailure, match=r"module 'held' cannot move: its state cannot "
                           r"be pickled: .*lock.* \(in 'guard': state that holds a lock"):
            run.migrate("held", to="b")
        assert run.stats().modules["held"].node == "a"
        assert run.stats().modules["held"].status == "running"
        mark = run.logs()[-1].seq
        run.wait(0.5)                         # ten checkpoints more
        assert len(said()) == 1 and "in 'guard'" in said()[0], said()
        assert not [e for e in run.logs(mark) if "Traceback" in e.message]


class KeepsALog(Module):
    """A module that writes what it reads to a log file it keeps open in its state."""

    x = Input(int, policy="queue:100000")
    path = ""

    def setup(self) -> None:
        self.log = open(self.path, "a+")        # noqa: SIM115 (open while it runs)

    def on_input(self, port) -> None:
        self.log.write(f"{port.read()}\n")
        self.log.flush()


def test_a_module_keeping_an_open_file_in_its_state_is_not_moved_with_a_copy_of_it(
        tmp_path) -> None:
    """cloudpickle sent a file open for reading as an in-memory copy of what it held: the
    module moved, and wrote its log to memory from then on, nothing said. An open file is
    refused as a lock is, by name, and the module runs on writing to it."""
    log = tmp_path / "relayed.log"
    system = _nodes(System("move-file"), "a", "b")
    system.add("src", Counter, node="a", period=0.002)
    system.add("logger", KeepsALog, node="a", state={"path": str(log)})
    system.link("src.out", "logger.x")
    with system.launch() as run:
        eventually(lambda: log.stat().st_size > 0, what="lines in the log")
        with pytest.raises(RuntimeFailure, match=r"module 'logger' cannot move: its state "
                           r"cannot be pickled: .*open file .*relayed.log.* \(in 'log'"):
            run.migrate("logger", to="b")
        assert run.where("logger") == "a"
        size = log.stat().st_size
        eventually(lambda: log.stat().st_size > size, what="the log written on")


def test_a_failed_landing_puts_the_module_back_where_it_was(monkeypatch) -> None:
    with _through("move-fail", "relay", Relay).launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 20, what="values through relay")
        executor = run._launcher.nodes["b"]
        real_call = type(executor).call
        failures = []

        def flaky(self, worker, op, *args, **kwargs):
            if op == "migrate_in" and worker.startswith("b/") and not failures:
                failures.append(worker)
                raise RuntimeFailure(f"worker {worker!r} died")
            return real_call(self, worker, op, *args, **kwargs)
        monkeypatch.setattr(type(executor), "call", flaky)
        before = run.state("relay")["relayed"]
        with pytest.raises(RuntimeFailure, match="runs on node a again, with its state"):
            run.migrate("relay", to="b")
        assert run.stats().modules["relay"].node == "a"
        assert run.state("relay")["relayed"] >= before
        eventually(lambda: run.state("relay")["relayed"] > before + 20, what="values again")
        sink = run.state("sink")
    assert failures and sink["out_of_order"] == 0 and sink["duplicates"] == 0
    assert sink["last"] == sink["received"]


def test_a_failed_landing_puts_a_whole_macro_back_where_it_was(monkeypatch) -> None:
    with _through("move-macro-fail", "pair", RelayPair).launch() as run:
        eventually(lambda: run.state("sink")["received"] > 20, what="values through the pair")
        executor = run._launcher.nodes["b"]
        real_call = type(executor).call
        failures = []

        def flaky(self, worker, op, *args, **kwargs):   # the second one fails to land
            if op == "migrate_in" and worker.endswith("second") and not failures:
                failures.append(worker)
                raise RuntimeFailure(f"worker {worker!r} died")
            return real_call(self, worker, op, *args, **kwargs)
        monkeypatch.setattr(type(executor), "call", flaky)
        with pytest.raises(RuntimeFailure, match=r"pair/first, pair/second to node b failed.*"
                                                 r"they run on node a again, with their state"):
            run.migrate("pair", to="b")
        modules = run.stats().modules
        n = run.state("src")["count"]
        state = eventually(lambda: (s := run.state("sink"))["received"] >= n and s,
                           timeout=30, what="every value through the pair")
    assert failures and {modules["pair/first"].node, modules["pair/second"].node} == {"a"}
    assert state["out_of_order"] == 0 and state["duplicates"] == 0
    assert state["last"] == state["received"]


@pytest.mark.parametrize(("op", "which"), [("pause", "second"), ("migrate_out", "first")])
def test_a_macro_move_that_fails_before_landing_leaves_nothing_paused_or_unwired(
        op, which, monkeypatch) -> None:
    """The second module cannot be paused (its call outlasts the wait), or the first
    cannot be captured: the modules already paused go on, the links unwired are wired
    again, and no value is lost, duplicated or reordered."""
    with _through(f"move-macro-{op}", "pair", RelayPair).launch() as run:
        eventually(lambda: run.state("sink")["received"] > 20, what="values through the pair")
        executor = run._launcher.nodes["a"]
        real_call = type(executor).call
        failures = []

        def flaky(self, worker, op_, *args, **kwargs):
            if op_ == op and worker.startswith("a/") and worker.endswith(which) \
                    and not failures:
                failures.append(worker)
                raise RuntimeFailure(f"module 'pair/{which}' did not finish its call")
            return real_call(self, worker, op_, *args, **kwargs)
        monkeypatch.setattr(type(executor), "call", flaky)
        with pytest.raises(RuntimeFailure, match="did not finish its call"):
            run.migrate("pair", to="b")
        assert failures and {run.where("pair/first"), run.where("pair/second")} == {"a"}
        relayed = {name: run.state(name)["relayed"] for name in ("pair/first", "pair/second")}
        eventually(lambda: all(run.state(name)["relayed"] > count + 20
                               for name, count in relayed.items()),
                   what="both modules of the pair relaying again")
        n = run.state("src")["count"]
        state = eventually(lambda: (s := run.state("sink"))["received"] >= n and s,
                           timeout=30, what="every value through the pair")
        assert set(run.stats().links) >= {"src.out->pair/first.x",
                                          "pair/first.out->pair/second.x",
                                          "pair/second.out->sink.x"}
    assert state["out_of_order"] == 0 and state["duplicates"] == 0
    assert state["last"] == state["received"]


def test_a_macro_that_cannot_be_readied_stays_and_leaves_no_worker_behind(monkeypatch) -> None:
    with _through("move-macro-unready", "pair", RelayPair).launch() as run:
        eventually(lambda: run.state("sink")["received"] > 20, what="values through the pair")
        executor = run._launcher.nodes["b"]
        real_call = type(executor).call

        def flaky(self, worker, op, *args, **kwargs):   # the first cannot be made at b
            if op == "add" and worker.startswith("b/") and worker.endswith("first"):
                raise RuntimeFailure(f"worker {worker!r} died")
            return real_call(self, worker, op, *args, **kwargs)
        monkeypatch.setattr(type(executor), "call", flaky)
        with pytest.raises(RuntimeFailure, match="died"):
            run.migrate("pair", to="b")
        # the worker booted for the second, which never came, was stopped too
        assert not [key for key in executor.workers.handles if "pair" in key]
        assert {run.where("pair/first"), run.where("pair/second")} == {"a"}
        n = run.state("src")["count"]
        state = eventually(lambda: (s := run.state("sink"))["received"] >= n and s,
                           timeout=30, what="every value through the pair")
    assert state["out_of_order"] == 0 and state["duplicates"] == 0
    assert state["last"] == state["received"]


def test_a_module_that_arrives_takes_a_booted_spare_and_a_dead_spare_is_only_forgotten(
        ) -> None:
    with _through("move-spare", "relay", Relay).launch() as run:
        pool = run._launcher.nodes["b"].workers
        spares = eventually(lambda: len(pids := pool.spare_pids()) == 2 and pids,
                            what="two spare workers booted at b")
        os.kill(spares[0], signal.SIGKILL)
        eventually(lambda: pool.spare_pids() == spares[1:], what="the dead spare forgotten")
        run.migrate("relay", to="b")
        taken = pool["b/m-relay"]
        assert taken.pid == spares[1] and taken.key == "b/m-relay"
        booted = eventually(lambda: len(pids := pool.spare_pids()) == 2 and pids,
                            what="b's spares booted again")
        before = run.state("relay")["relayed"]
        state = eventually(lambda: (s := run.state("sink"))["received"] > before + 20 and s,
                           what="values through the relay at b")
        assert not [e for e in run.events() if e.kind in ("module_failed", "module_restarted")]
    assert spares[1] not in booted and state["out_of_order"] == 0 and state["duplicates"] == 0
    assert not [pid for pid in booted if alive(pid)]                # stopped with node b


def test_a_move_without_waiting_returns_a_pending_result_and_is_an_event() -> None:
    system = System("pending").node("a").node("b")
    system.add("src", Counter, node="a", period=0.002)
    system.add("relay", Relay, node="a")
    system.add("sink", Collector, node="a")
    system.link("src.out", "relay.x")
    system.link("relay.out", "sink.x")
    with system.launch() as run:
        pending = run.migrate("relay", to="b", wait=False)
        assert pending.wait(30) and pending.done()
        report = pending.result(0)
        assert report.destination == "b" and run.where("relay") == "b"
        moved = [e for e in run.events() if e.kind == "module_moved"]
        assert [(e.subject, e.detail["source"], e.detail["destination"]) for e in moved] == [
            ("relay", "a", "b")] and moved[0].detail["pause_s"] == report.pause_s
        with pytest.raises(ConfigError, match="migrate relay: no node 'mars'"):
            run.migrate("relay", to="mars", wait=False).result(10)
        n = run.state("relay")["relayed"] + 100
        state = eventually(lambda: (s := run.state("sink"))["received"] >= n and s, timeout=30,
                           what="values after the move")
    assert state["out_of_order"] == 0 and state["duplicates"] == 0


def test_a_move_that_fails_is_an_event_and_one_refused_is_not(capsys) -> None:
    """A move that failed (the module put back where it ran) recorded no event, where one
    that succeeds is ``module_moved`` and a module that fails ``module_failed``: it is
    ``migration_failed``, naming the module, its source and destination and the error,
    in ``run.events()`` and ``pb3a events``, waited for or not. A move refused before
    anything was tried (no such node, state for a module that does not move) is none."""
    system = _nodes(System("failed-move-event"), "a", "b")
    system.add("relay", Relay, node="a")
    with system.launch() as run:
        address = run.listen()
        with pytest.raises(ConfigError, match="no node 'mars'"):
            run.migrate("relay", to="mars")
        with pytest.raises(ValueError, match="which does not move"):
            run.migrate("relay", to="b", state={"elsewhere": {"x": 1}})
        with pytest.raises(RuntimeFailure, match="it runs on node a again") as failed:
            run.migrate("relay", to="b", state={"relay": {"no_such_field": 1}})
        pending = run.migrate("relay", to="b", state={"relay": {"no_such_field": 2}},
                              wait=False)
        with pytest.raises(RuntimeFailure) as failed_later:
            pending.result(30)
        assert run.where("relay") == "a"
        moves = [e for e in run.events() if e.kind in ("module_moved", "migration_failed")]
        assert [(e.kind, e.subject, e.detail["source"], e.detail["destination"])
                for e in moves] == [("migration_failed", "relay", "a", "b")] * 2
        assert [e.detail["error"] for e in moves] == [str(failed.value),
                                                      str(failed_later.value)]
        assert main(["events", address]) == 0
        listed = [line.split() for line in capsys.readouterr().out.splitlines()]
        assert [(seq, kind, subject) for _, seq, kind, subject, *_ in listed
                if kind == "migration_failed"] == [(str(e.seq), e.kind, "relay") for e in moves]


def test_an_agent_moves_a_module_without_waiting_and_sees_where_it_went() -> None:
    system = System("shepherd").node("a").node("b")
    system.add("src", Counter, node="a", period=0.002)
    system.add("relay", Relay, node="a")
    system.add("shepherd", Shepherd, node="a")
    system.link("src.out", "relay.x")
    system.link("env-a.module_moved", "shepherd.moved")
    with system.launch() as run:
        state = eventually(lambda: (s := run.state("shepherd"))["seen_moves"] and s["report"]
                           and s, timeout=30, what="the move done, and seen on env-a")
    assert state["done_before"] is False                  # the agent did not wait for it
    assert state["report"]["destination"] == "b" and state["where"] == "b"
    assert state["seen_moves"][0]["module"] == "relay"
    assert state["seen_moves"][0]["destination"] == "b"


def test_a_move_whose_writer_will_not_pause_leaves_nothing_at_the_destination() -> None:
    """The writers are paused after the destination is prepared, outside what undoes
    a failed move: a writer busy past its pause's deadline (the move's) left the
    prepared instance and its worker at the destination (moving there and back later
    left it running)."""
    system = System("stalled").node("a").node("b")
    system.add("src", Staller, node="a")
    system.add("relay", Relay, node="a")
    system.add("sink", Collector, node="a")
    system.link("src.out", "relay.x")
    system.link("relay.out", "sink.x")
    with system.launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 20, what="values")
        b = run._launcher.nodes["b"]
        run.set_state("src", stall_s=2.5)

        def stalled() -> bool:                  # (a read runs out: it is in its long step)
            try:
                run.state("src", timeout=0.3)
            except RuntimeTimeout:
                return True
            return False
        eventually(stalled, what="the writer in its long step")
        with pytest.raises(RuntimeTimeout, match="ran out while pausing the writers src"):
            run.migrate("relay", to="b", timeout=1.0)
        assert run.where("relay") == "a"
        assert list(b.modules) == []
        assert not [h for h in b.workers.handles.values() if "relay" in h.modules]
        run.set_state("src", stall_s=0.0)
        relayed = run.state("relay")["relayed"]
        eventually(lambda: run.state("relay")["relayed"] > relayed + 20, what="it goes on")


def test_a_move_whose_module_s_worker_dies_on_the_way_stops_before_anything_is_unwired(
        ) -> None:
    """The move went on with a module it could not pause: it unwired its links, could
    not retire it, and put it back with its writer's side never wired again; once the
    worker restarted, nothing reached it, and nothing said so."""
    system = System("died-on-the-way").node("a").node("b")
    system.add("src", Counter, node="a", period=0.005)
    system.add("relay", Relay, node="a", restart="fresh")
    system.add("sink", Collector, node="a")
    system.link("src.out", "relay.x")
    system.link("relay.out", "sink.x")
    with system.launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 20, what="values")
        a, b = run._launcher.nodes["a"], run._launcher.nodes["b"]
        add = b.add_module

        def add_as_the_worker_dies(spec, **options) -> None:
            add(spec, **options)
            handle = a.workers[a.modules["relay"].worker]
            os.kill(handle.pid, signal.SIGKILL)
            eventually(lambda: not handle.alive, what="the worker seen dead")
        b.add_module = add_as_the_worker_dies
        with pytest.raises(RuntimeFailure, match=r"its worker is not running.*nothing moved"):
            run.migrate("relay", to="b")
        b.add_module = add
        assert run.where("relay") == "a" and list(b.modules) == []
        eventually(lambda: run.stats().modules["relay"].status == "running", timeout=15,
                   what="relay restarted")
        received = run.state("sink")["received"]
        eventually(lambda: run.state("sink")["received"] > received + 20, timeout=10,
                   what="values through the restarted relay")


def test_a_landing_that_fails_as_remote_links_are_wired_again_is_undone(monkeypatch) -> None:
    """The failed landing dropped the module at its destination, closing that worker's
    doorbell, then closed its remote link there: the bridge rang the closed descriptor,
    the undo ended in a bare OSError (EBADF) and the module was gone from the system
    (found by a chaos run: a reader killed as its writer moved)."""
    system = System("wired-again").node("a").node("b").node("c")
    system.add("src", Counter, node="a", period=0.002)
    system.add("relay", Relay, node="a")
    system.add("sink", Collector, node="b")
    system.link("src.out", "relay.x", policy="lossless:64")
    system.link("relay.out", "sink.x", policy="lossless:64")
    with system.launch(timeout=10) as run:
        eventually(lambda: run.state("sink")["received"] > 5, what="values at the sink")
        reader = run._launcher.nodes["b"]
        real_open = type(reader).open_inbound
        failures = []

        def flaky(self, links):       # (node c's link into relay is opened first)
            if self is reader and not failures:
                failures.append(links)
                raise RuntimeFailure("worker 'b/m-sink' is not running")
            return real_open(self, links)
        monkeypatch.setattr(type(reader), "open_inbound", flaky)
        with pytest.raises(RuntimeFailure, match="runs on node a again"):
            run.migrate("relay", to="c")
        monkeypatch.setattr(type(reader), "open_inbound", real_open)
        assert failures and run.where("relay") == "a"
        assert run.stats().modules["relay"].status == "running"
        received = run.state("sink")["received"]
        eventually(lambda: run.state("sink")["received"] > received + 20,
                   what="values through the relay put back")
        sink = run.state("sink")
    assert sink["out_of_order"] == 0 and sink["duplicates"] == 0


@pytest.mark.parametrize("policy", ["queue:64", "lossless:64"])
def test_a_module_whose_reader_has_failed_moves_and_the_reader_restarts_wired(policy) -> None:
    """A link into a failed module (restart = "never", its worker killed) is not wired
    where its writer lands, as it is unhooked when the module fails; a restart wires it
    (the move asked the dead worker to attach the link, and was undone, wherever the
    writer went: 'worker 'b/m-sink' is not running')."""
    system = System("dead-reader").node("a").node("b").node("c")
    system.add("src", Counter, node="a", period=0.002)
    system.add("relay", Relay, node="a")
    system.add("sink", Collector, node="b")             # restart = never: it stays failed
    system.link("src.out", "relay.x", policy=policy)
    system.link("relay.out", "sink.x", policy=policy)
    with system.launch(timeout=10) as run:
        eventually(lambda: run.state("sink")["received"] > 5, what="values at the sink")
        os.kill(run.stats().modules["sink"].pid, signal.SIGKILL)
        eventually(lambda: run.stats().modules["sink"].status == "failed", what="sink failed")
        for node in ("c", "b", "a"):            # another node, the reader's, the first
            run.migrate("relay", to=node)
            assert run.where("relay") == node
        relayed = run.state("relay")["relayed"]
        eventually(lambda: run.state("relay")["relayed"] > relayed + 20,
                   what="values through the moved relay")
        run.restart("sink")
        eventually(lambda: run.state("sink")["received"] > 20, what="values at the restarted sink")
        assert {"relay.out->sink.x", "src.out->relay.x"} <= set(run.stats().links)


def test_a_move_whose_pause_a_frozen_worker_reads_late_leaves_the_module_running(
        monkeypatch) -> None:
    """The module's worker is frozen (SIGSTOP) as the move asks to pause it, and runs again
    after the move gave the pause up: it took the module's lock then, and nobody ever let
    it go (the module stayed paused for good, every read of it 'busy in a call')."""
    with _through("move-frozen-pause", "relay", Relay).launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 20, what="values through relay")
        pid = run.stats().modules["relay"].pid
        real_pause = Executor.pause
        thaw = threading.Timer(3.5, os.kill, (pid, signal.SIGCONT))

        def freezing(self, name, timeout=10.0, rewire=False):
            if name == "relay" and not thaw.is_alive():
                os.kill(pid, signal.SIGSTOP)
                thaw.start()                    # (after the pause's 1 s + 1 s)
                # (the move gives its pause 5 s; 1 s here: the same give-up, sooner)
                timeout = min(timeout, 1.0)
            return real_pause(self, name, timeout, rewire)
        monkeypatch.setattr(Executor, "pause", freezing)
        try:
            with pytest.raises(RuntimeTimeout, match="pause"):
                run.migrate("relay", to="b")
        finally:
            thaw.join()
        monkeypatch.setattr(Executor, "pause", real_pause)
        assert run.where("relay") == "a"
        relayed = eventually(lambda: run.state("relay", timeout=2)["relayed"],
                             what="a read of relay")
        eventually(lambda: run.state("relay", timeout=2)["relayed"] > relayed + 20,
                   what="relay relaying again")


class LeavesSlowly(Relay):
    """A relay whose ``teardown`` takes ``linger`` seconds."""

    linger = 0.0

    def teardown(self) -> None:
        time.sleep(self.linger)


@pytest.mark.parametrize("late", ["frozen", "teardown"])
def test_a_move_whose_capture_comes_too_late_leaves_the_module_running_where_it_was(
        late, monkeypatch) -> None:
    """The move gave up on the capture after 10 s: the module's worker was frozen
    (SIGSTOP) as it was asked, or the module's teardown overran. The worker retired it
    all the same once it got there, and the module ran nowhere: the system had it on node
    a, "running", every request to it a KeyError, its links not wired again, and no
    event or error said so. (The capture's 10 s, ``REQUEST_TIMEOUT``, is 3 s here: the
    same give-up, and the worker as late after it.)"""
    with _through(f"move-late-{late}", "relay", LeavesSlowly).launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 20, what="values through relay")
        executor = run._launcher.nodes["a"]
        real_call = type(executor).call
        pid = run.stats().modules["relay"].pid
        thaw = threading.Timer(3.5, os.kill, (pid, signal.SIGCONT))

        def freezing(self, worker, op, *args, **kwargs):
            if op == "migrate_out" and not thaw.is_alive():
                os.kill(pid, signal.SIGSTOP)
                thaw.start()                    # (after the capture's 3 s)
            return real_call(self, worker, op, *args, **kwargs)
        if late == "frozen":
            monkeypatch.setattr(type(executor), "call", freezing)
        else:
            run.set_state("relay", linger=3.5)
        try:
            with monkeypatch.context() as capture:
                capture.setattr("pb3a.node.executor.REQUEST_TIMEOUT", 3.0)
                with pytest.raises(RuntimeTimeout, match="migrate_out"):
                    run.migrate("relay", to="b")
        finally:
            if thaw.is_alive():
                thaw.join()
        monkeypatch.setattr(type(executor), "call", real_call)
        assert run.where("relay") == "a"
        run.set_state("relay", {"linger": 0.0}, timeout=5)
        relayed = run.state("relay")["relayed"]
        eventually(lambda: run.state("relay")["relayed"] > relayed + 20,
                   what="relay relaying again where it was")
        n = run.state("src")["count"]
        state = eventually(lambda: (s := run.state("sink"))["received"] >= n and s,
                           timeout=30, what="every value through relay")
    assert state["out_of_order"] == 0 and state["duplicates"] == 0
    assert state["last"] == state["received"]


@pytest.mark.parametrize("ends", ["a", "c"])
def test_a_module_whose_worker_dies_as_its_move_captures_it_restarts_with_its_links(
        ends, monkeypatch) -> None:
    """The module's worker dies (SIGKILL) once the move has paused it and unwired its links,
    as it is captured. The move put its links back while its worker was dead: the wiring
    of each failed at the dead end, and its live end was never wired; the module restarted
    (``module_restarted``, "running"), and nothing reached it again. Its links' other ends
    on its node (``a``) or on another (``c``: ZeroMQ)."""
    system = _nodes(System(f"dies-in-capture-{ends}"), "a", "b", "c")
    system.add("src", Counter, node=ends, period=0.005)
    system.add("relay", Relay, node="a", restart="fresh")
    system.add("sink", Collector, node=ends)
    system.link("src.out", "relay.x")
    system.link("relay.out", "sink.x")
    with system.launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 20, what="values through relay")
        executor = run._launcher.nodes["a"]
        real_call = type(executor).call
        old = run.stats().modules["relay"].pid

        def dying(self, worker, op, *args, **kwargs):
            if op == "migrate_out":
                os.kill(old, signal.SIGKILL)
                eventually(lambda: not self.workers[worker].serving, what="the death seen")
            return real_call(self, worker, op, *args, **kwargs)
        monkeypatch.setattr(type(executor), "call", dying)
        with pytest.raises(RuntimeFailure):
            run.migrate("relay", to="b")
        monkeypatch.setattr(type(executor), "call", real_call)
        assert run.where("relay") == "a"

        def restarted() -> dict | None:
            try:
                state = run.state("relay", timeout=2.0)
            except RuntimeFailure:                 # (not restarted yet)
                return None
            return state if run.stats().modules["relay"].pid not in (None, old) else None
        eventually(restarted, timeout=15, what="relay restarted")
        eventually(lambda: run.state("relay")["relayed"] > 20, timeout=10,
                   what="values through the restarted relay")
        received = run.state("sink")["received"]
        eventually(lambda: run.state("sink")["received"] > received + 20,
                   what="values at the sink again")
        assert not [line for line in run.stats().failures if "not wired again" in line]


class ArrivesSlowly(Relay):
    """A relay whose ``setup`` takes ``arrive_s`` seconds from its second on (on arrival)."""

    arrive_s = 0.0

    def setup(self) -> None:
        super().setup()
        if self.setups > 1:
            time.sleep(self.arrive_s)


# A move's timeout bounds the whole call: what a test allows beyond it (the landing's
# floor, LANDING_FLOOR_S, and the bookkeeping once the time is up)
MOVE_SLACK_S = 0.75


def _move_timed(run, name: str, to: str, timeout: float) -> tuple[BaseException, float]:
    """``run.migrate(name, to, timeout=timeout)``, which must fail: its error, and the
    seconds the call took."""
    started = time.monotonic()
    with pytest.raises(RuntimeTimeout) as raised:
        run.migrate(name, to=to, timeout=timeout)
    return raised.value, time.monotonic() - started


def _every_value_once_in_order(run) -> None:
    n = run.state("src")["count"]
    state = eventually(lambda: (s := run.state("sink"))["received"] >= n and s,
                       timeout=30, what="every value through relay")
    assert state["out_of_order"] == 0 and state["duplicates"] == 0
    assert state["last"] == state["received"]


def test_a_move_whose_setup_outlasts_its_timeout_returns_in_time_and_runs_there() -> None:
    """The module's ``setup`` at the destination takes 5 s, the move's timeout is 2 s: the
    call waited for the setup (5 s and more: the timeout bounded only the wait for the
    configuration lock). Past its point of no return (the start), it returns within its
    timeout, saying the setup had not returned, and the module runs there once it has,
    with every value. (With 1 s, preparing the destination alone ran out once, beside
    two busy loops and two other test workers.)"""
    with _through("move-slow-setup", "relay", ArrivesSlowly).launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 20, what="values through relay")
        run.set_state("relay", arrive_s=5.0)
        error, took = _move_timed(run, "relay", "b", 2.0)
        assert took < 2.0 + MOVE_SLACK_S, took
        assert "ran out while starting relay at node b" in str(error)
        assert "runs there once its setup returns" in str(error)
        assert run.where("relay") == "b"
        moved = [e for e in run.events() if e.kind in ("module_moved", "migration_failed")]
        assert [(e.kind, e.detail["destination"]) for e in moved] == [("module_moved", "b")]
        eventually(lambda: run.stats().modules["relay"].status == "running", timeout=10,
                   what="relay running at b once its setup returned")
        relayed = run.state("relay")["relayed"]
        eventually(lambda: run.state("relay")["relayed"] > relayed + 20,
                   what="relay relaying at b")
        _every_value_once_in_order(run)


def test_a_move_to_a_frozen_node_returns_in_time_and_leaves_the_module_where_it_was(
        ) -> None:
    """The destination's workers are frozen (SIGSTOP): the move waited 10 s for the
    module's instance there, then 3 s more for the worker to stop (13 s for a 1 s
    timeout). It returns within its timeout, naming the step, and nothing moved."""
    with _through("move-frozen-node", "relay", Relay).launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 20, what="values through relay")
        b = run._launcher.nodes["b"]
        spares = eventually(lambda: len(pids := b.workers.spare_pids()) == 2 and pids,
                            what="two spare workers booted at b")
        for pid in spares:
            os.kill(pid, signal.SIGSTOP)
        try:
            error, took = _move_timed(run, "relay", "b", 1.0)
        finally:
            for pid in spares:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGCONT)
        assert took < 1.0 + MOVE_SLACK_S, took
        assert "ran out while preparing node b" in str(error)
        assert "nothing moved: relay runs on node a as before" in str(error)
        assert run.where("relay") == "a" and list(b.modules) == []
        relayed = run.state("relay")["relayed"]
        eventually(lambda: run.state("relay")["relayed"] > relayed + 20,
                   what="relay relaying where it was")
        _every_value_once_in_order(run)


def test_a_move_whose_pause_outlasts_its_timeout_returns_in_time_where_it_was(
        monkeypatch) -> None:
    """The module's worker is frozen (SIGSTOP) as the move pauses it: the move waited the
    pause's own 5 s, whatever its timeout. It gives up with what is left of its 1 s,
    naming the step, and the module goes on where it was (the pause the worker reads
    late is not taken), with every value."""
    with _through("move-pause-in-time", "relay", Relay).launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 20, what="values through relay")
        pid = run.stats().modules["relay"].pid
        thaw = threading.Timer(1.5, os.kill, (pid, signal.SIGCONT))
        real_pause = Executor.pause

        def freezing(self, name, timeout=10.0, rewire=False):
            if name == "relay" and not thaw.is_alive():
                os.kill(pid, signal.SIGSTOP)
                thaw.start()
            return real_pause(self, name, timeout, rewire)
        monkeypatch.setattr(Executor, "pause", freezing)
        try:
            error, took = _move_timed(run, "relay", "b", 1.0)
        finally:
            thaw.join()
        monkeypatch.setattr(Executor, "pause", real_pause)
        assert took < 1.0 + MOVE_SLACK_S, took
        assert "ran out while pausing relay at node a" in str(error), str(error)
        # (undoing the move, which drops the instance prepared at b and its worker, is
        # done by the call's end, or goes on a moment after it on a loaded machine)
        assert ("nothing moved: relay runs on node a as before" in str(error)
                or "nothing moved: relay stays on node a" in str(error)), str(error)
        assert run.where("relay") == "a"
        relayed = eventually(lambda: run.state("relay", timeout=2)["relayed"],
                             what="a read of relay")
        eventually(lambda: run.state("relay")["relayed"] > relayed + 20,
                   what="relay relaying where it was")
        _every_value_once_in_order(run)


def test_a_move_whose_own_wait_runs_out_before_its_time_says_nothing_moved_and_where(
        monkeypatch) -> None:
    """A wait of the move's own that ran out before the move's time was up (a worker's
    answer waited its 10 s of a move given 25; values of a remote link still in flight
    after the drain's 10 s) came out as it was, saying neither that nothing moved nor
    where the module runs, as every other failure before the capture does. (Here the
    pause's answer is made to run out so, once.)"""
    with _through("move-own-wait", "relay", Relay).launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 20, what="values through relay")
        real, failed = Executor.pause, []

        def unanswered(self, name, timeout=10.0, rewire=False):
            if name == "relay" and not failed:
                failed.append(timeout)
                raise RuntimeTimeout("worker 'a/m-relay' did not answer 'pause' within 10 s")
            return real(self, name, timeout, rewire)
        monkeypatch.setattr(Executor, "pause", unanswered)
        with pytest.raises(RuntimeTimeout) as error:
            run.migrate("relay", to="b", timeout=25)
        assert str(error.value) == ("worker 'a/m-relay' did not answer 'pause' within 10 s; "
                                    "nothing moved: relay runs on node a as before")
        assert failed and run.where("relay") == "a"
        relayed = run.state("relay")["relayed"]
        eventually(lambda: run.state("relay")["relayed"] > relayed + 20,
                   what="relay relaying where it was")
        _every_value_once_in_order(run)


class Plodder(Module):
    """Steps quickly, but once ``slow`` exists takes one step of ``step_s`` seconds
    (a planner's), saying it began by the file ``began``."""

    period = 0.01
    slow = ""
    began = ""
    step_s = 6.0
    steps = 0

    def step(self) -> None:
        self.steps += 1
        if os.path.exists(self.slow):
            os.unlink(self.slow)
            open(self.began, "w").close()
            time.sleep(self.step_s)


def test_a_module_in_a_step_longer_than_five_seconds_moves_within_the_move_s_timeout(
        tmp_path) -> None:
    """The move waited at most 5 s for the module's step to end, whatever its timeout:
    a module whose step runs longer (a planner's) could never be moved ("busy in a call
    for 5 s"). The pause waits as long as the move may take."""
    slow, began = tmp_path / "slow", tmp_path / "began"
    system = _nodes(System("move-plodder"), "a", "b")
    system.add("plodder", Plodder, node="a", state={"slow": str(slow), "began": str(began)})
    with system.launch() as run:
        eventually(lambda: run.state("plodder")["steps"] > 3, what="steps")
        slow.touch()
        eventually(began.exists, what="the long step begun")
        started = time.monotonic()
        report = run.migrate("plodder", to="b", timeout=20.0)
        assert time.monotonic() - started > 4.0          # (it waited for the step)
        assert report.destination == "b" and run.where("plodder") == "b"
        steps = run.state("plodder")["steps"]
        eventually(lambda: run.state("plodder")["steps"] > steps, what="steps at b")


class Planner(Module):
    """Every step takes ``step_s`` (a planner's), each noted as it begins and as it ends
    in the file ``notes``: the worker's process, the time, which."""

    period = 0.0
    notes = ""
    step_s = 2.0

    def step(self) -> None:
        self._note("began")
        time.sleep(self.step_s)
        self._note("ended")

    def _note(self, what: str) -> None:
        with open(self.notes, "a") as notes:
            notes.write(f"{os.getpid()} {time.time()} {what}\n")


def test_a_module_whose_every_step_is_long_moves_once_the_step_in_progress_ends(
        tmp_path) -> None:
    """Moved as a 2 s step begins, with T = 3.5 s: the move's measure of its state waited
    for that step to end, the module began another, and the pause waited for that one
    too, so the move ran out (a 3 s step, T = 4.5 s: every attempt). Now one step's end
    suffices, and ``pause_s`` is what the module's own steps saw, from its last step at
    the source to its first at the destination (the wait for the step is ``wait_s``:
    ``pause_s`` said 3 s, the steps' gap 4 ms)."""
    notes = tmp_path / "notes"
    system = _nodes(System("move-planner"), "a", "b")
    system.add("planner", Planner, node="a", state={"notes": str(notes)})

    def seen() -> list[tuple[int, float, str]]:
        lines = notes.read_text().splitlines() if notes.exists() else []
        return [(int(pid), float(when), what) for pid, when, what in map(str.split, lines)]
    with system.launch() as run:
        eventually(lambda: sum(what == "began" for _, _, what in seen()) >= 2,
                   what="a second step begun")
        started = time.monotonic()
        report = run.migrate("planner", to="b", timeout=3.5)
        took = time.monotonic() - started
        source = seen()[0][0]
        eventually(lambda: any(pid != source for pid, _, _ in seen()), what="a step at b")
    assert report.destination == "b" and took < 3.5, took
    # (the step's rest, about 2 s, went in preparing the destination, then waiting)
    assert report.prepare_s + report.wait_s > 1.5 and report.wait_s > 0, report
    noted = seen()
    last_there = max(when for pid, when, what in noted if pid == source and what == "ended")
    first_here = min(when for pid, when, _ in noted if pid != source)
    gap = first_here - last_there
    assert report.pause_s < 1.0 and report.pause_s <= gap + 0.05, (report.pause_s, gap)
    assert gap - report.pause_s < 0.5, (report.pause_s, gap)


def test_a_move_whose_undo_waits_for_a_busy_worker_returns_in_time_and_finishes_after(
        ) -> None:
    """The module's ``teardown`` takes 4 s, the move's timeout is 2 s: the capture runs
    out, and the move waited for the module's worker to take its undo (its links wired
    again, its pause let go) once the teardown ended (3.2 s for a 1 s timeout). It
    returns within its timeout saying the undo goes on; a later change waits for that
    (and says what it waits for), and the module runs where it was, set up again, with
    every value once, in order. (With 1 s, preparing the destination alone ran out
    once, beside two busy loops and two other test workers.)"""
    with _through("move-busy-undo", "relay", LeavesSlowly).launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 20, what="values through relay")
        run.set_state("relay", linger=4.0)
        error, took = _move_timed(run, "relay", "b", 2.0)
        assert took < 2.0 + MOVE_SLACK_S, took
        assert "ran out while capturing relay at node a" in str(error), str(error)
        assert "nothing moved: relay stays on node a" in str(error)
        assert "a later change waits for it" in str(error)
        with pytest.raises(RuntimeTimeout, match="'undo migrate relay to b' has held"):
            run.migrate("relay", to="b", timeout=0.5)       # (the teardown has 2 s left)
        run.set_state("relay", {"linger": 0.0}, timeout=10)
        assert run.where("relay") == "a"
        relayed = run.state("relay")["relayed"]
        eventually(lambda: run.state("relay")["relayed"] > relayed + 20,
                   what="relay relaying where it was")
        assert run.state("relay")["setups"] == 2            # set up again after its teardown
        _every_value_once_in_order(run)
        assert run.migrate("relay", to="b", timeout=10).destination == "b"
        _every_value_once_in_order(run)


def test_a_move_whose_destination_freezes_after_the_capture_returns_in_time_where_it_was(
        monkeypatch) -> None:
    """The destination's worker is frozen (SIGSTOP) right after the module is captured:
    the restore there runs out, and putting the module back waited 10 s for each request
    to the frozen worker (its two links unwired there, the module removed: 31 s for a
    1 s timeout). It returns within its timeout and the landing's floor, the module
    running where it was with its state and every value once, in order; the frozen
    worker is stopped."""
    with _through("move-frozen-landing", "relay", Relay).launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 20, what="values through relay")
        b = run._launcher.nodes["b"]
        real_retire = Executor.retire
        frozen: list[int] = []

        def captured_then_frozen(self, name, segment, carry):
            snapshot = real_retire(self, name, segment, carry)
            frozen.append(b.workers[b.modules[name].worker].pid)
            os.kill(frozen[-1], signal.SIGSTOP)
            return snapshot
        monkeypatch.setattr(Executor, "retire", captured_then_frozen)
        relayed = run.state("relay")["relayed"]
        try:                                    # (frozen until it is stopped)
            error, took = _move_timed(run, "relay", "b", 1.0)
            monkeypatch.setattr(Executor, "retire", real_retire)
            assert took < 1.0 + MOVE_SLACK_S, took
            assert "ran out while restoring relay at node b" in str(error), str(error)
            # (put back in its time, or, on a loaded machine, just after: said so)
            assert ("it runs on node a again, with its state" in str(error)
                    or "it is being put back on node a with its state" in str(error))
            assert run.where("relay", timeout=5) == "a" and "relay" not in b.modules
            assert run.state("relay")["relayed"] >= relayed        # its state, not anew
            eventually(lambda: run.state("relay")["relayed"] > relayed + 20,
                       what="relay relaying where it was")
            _every_value_once_in_order(run)
            eventually(lambda: not alive(frozen[0]), what="the frozen worker stopped")
        finally:
            for pid in frozen:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGCONT)


@pytest.mark.parametrize("held_at", ["pause", "retire", "between", "land"])
def test_a_look_at_the_system_waits_for_no_move_and_shows_it_in_progress(
        monkeypatch, capsys, held_at: str) -> None:
    """While a move holds the configuration lock (held here at one of its steps: the
    module's pause, its capture done, its landing), ``stats()``, ``where()``,
    ``nodes()``, ``topology()``, another module's state and ``pb3a status`` answer at
    once, every module shown once (the one moving too, between its nodes' reports:
    ``between``, its destination's report taken before it came, shows it silent),
    and the moving one's figures and the table name the move; once it is done, no
    more. (They waited for the lock: a stuck move left ``pb3a status`` failing after
    its timeout, "waited 3 s for the system's configuration lock, which 'migrate slow
    to b' has held for 4.8 s", just when one wanted to look.)"""
    system = _through("look-during-move", "relay", Relay)
    go, there = threading.Event(), threading.Event()
    report = None
    if held_at == "between":                # captured at a, and b reports it not
        held_at, report = "retire", Executor.report

        def before_it_came(self, *args, **kwargs):
            figures = report(self, *args, **kwargs)
            if self.node == "b" and there.is_set() and not go.is_set():
                figures.modules.pop("relay", None)
            return figures
        monkeypatch.setattr(Executor, "report", before_it_came)
    real = getattr(Executor, held_at)

    def held(self, name, *args, **kwargs):
        if name != "relay":
            return real(self, name, *args, **kwargs)
        if held_at == "retire":               # (captured: the node has it no more)
            result = real(self, name, *args, **kwargs)
            there.set()
            assert go.wait(30.0)
            return result
        there.set()
        assert go.wait(30.0)
        return real(self, name, *args, **kwargs)
    with system.launch() as run:
        eventually(lambda: run.state("relay")["relayed"] > 5, what="values through relay")
        monkeypatch.setattr(Executor, held_at, held)
        moving = threading.Thread(target=lambda: run.migrate("relay", to="b", timeout=60))
        moving.start()
        try:
            assert there.wait(10.0)
            started = time.monotonic()
            stats = run.stats(timeout=1.0)
            where = run.where("relay", timeout=1.0), run.where("src", timeout=1.0)
            nodes, topology = run.nodes(timeout=1.0), run.topology(timeout=1.0)
            sink = run.state("sink", timeout=1.0)
            assert main(["status", run.listen(), "--timeout", "1"]) == 0
            answered = time.monotonic() - started
        finally:
            go.set()
            moving.join(30.0)
        table = capsys.readouterr().out
        after = run.stats()
    assert answered < 1.5, answered
    assert set(stats.modules) == {"src", "relay", "sink"}
    moved = stats.modules["relay"]
    assert moved.change == "migrate relay to b" and moved.change_s > 0, moved
    assert moved.node == ("b" if held_at == "land" else "a"), moved
    assert moved.silent == (report is not None), moved
    assert stats.modules["src"].change == "" and stats.modules["sink"].change == ""
    assert where == ("b" if held_at == "land" else "a", "a")
    assert set(nodes) == {"a", "b"} and set(topology.modules) == {"src", "relay", "sink"}
    assert sink["received"] >= 0
    row = next(line for line in table.splitlines() if line.startswith("relay "))
    assert "(migrate relay to b for " in row, table
    assert after.modules["relay"].node == "b" and after.modules["relay"].change == ""
