"""Links between nodes (embedded nodes on this machine): they go over ZeroMQ with the
same guarantees as local links."""

from __future__ import annotations

import os
import signal
from typing import Any

import pytest
from conftest import eventually
from sample_modules import ArrayReuser, ArraySink, ArraySource, Burst, Collector, Counter

from pb3a import System
from pb3a.node.executor import Executor


def _two_nodes(name: str) -> System:
    system = System(name)
    system.node("a")
    system.node("b")
    return system


def test_100000_values_cross_nodes_in_order_without_loss_or_duplicates() -> None:
    """On a lossless link: a queue link is a dropping one, and drops what a follower
    slow to acknowledge (starved for half a second) has no room for, counted."""
    n = 100_000
    system = _two_nodes("remote-bulk")
    system.add("src", Burst, node="a", state={"limit": n})
    system.add("dst", Collector, node="b")
    system.link("src.out", "dst.x", policy="lossless:4096")
    with system.launch() as run:
        state = eventually(lambda: (s := run.state("dst"))["received"] == n and s, timeout=90,
                           what=f"{n} values across nodes")
        link = run.stats().links["src.out->dst.x"]
    assert state["last"] == n
    assert state["out_of_order"] == 0 and state["duplicates"] == 0
    assert link.transport == "zmq"
    assert link.values == n and link.drops == 0 and link.link_failures == 0


def test_large_arrays_cross_nodes_intact_and_read_only() -> None:
    system = _two_nodes("remote-arrays")
    system.add("src", ArraySource, node="a")
    system.add("dst", ArraySink, node="b")
    system.link("src.out", "dst.x")
    with system.launch() as run:
        state = eventually(lambda: (s := run.state("dst"))["sums_ok"] >= 20 and s,
                           timeout=30, what="20 arrays across nodes")
        link = run.stats().links["src.out->dst.x"]
    assert state["writable"] is False
    assert link.transport == "zmq" and link.link_failures == 0


def test_an_array_its_writer_changes_right_after_writing_crosses_as_written() -> None:
    system = _two_nodes("remote-reused-array")
    system.add("src", ArrayReuser, node="a")
    system.add("dst", ArraySink, node="b")
    system.link("src.out", "dst.x", policy="queue:64")
    with system.launch() as run:
        state = eventually(lambda: (s := run.state("dst"))["sums_ok"] >= 200 and s,
                           timeout=30, what="200 arrays across nodes")
    assert state["scribbled"] == 0


def test_an_output_crosses_once_per_node_however_many_inputs_read_it_there() -> None:
    n = 5000
    system = _two_nodes("remote-fanout")
    system.add("src", Burst, node="a", state={"limit": n})
    for name, node in (("b1", "b"), ("b2", "b"), ("a1", "a")):
        system.add(name, Collector, node=node)
        system.link("src.out", f"{name}.x")
    with system.launch() as run:
        for name in ("b1", "b2", "a1"):
            state = eventually(lambda name=name: (s := run.state(name))["received"] == n and s,
                               timeout=60, what=f"{n} values at {name}")
            assert state["out_of_order"] == 0 and state["duplicates"] == 0
        followed = run._launcher.nodes["b"].bridge.followed()
        transports = {key: link.transport for key, link in run.stats().links.items()}
    assert followed == {"src.out": ["src.out->b1.x", "src.out->b2.x"]}
    assert transports == {"src.out->b1.x": "zmq", "src.out->b2.x": "zmq",
                          "src.out->a1.x": "shm"}


def test_links_across_nodes_are_wired_in_one_request_per_node_and_step(
        monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[str, str, int]] = []

    def counting(step: str) -> Any:
        wrapped = getattr(Executor, step)

        def counted(node: Executor, links: list) -> Any:
            calls.append((step, node.node, len(links)))
            return wrapped(node, links)
        return counted
    for step in ("open_inbound", "publish", "follow"):
        monkeypatch.setattr(Executor, step, counting(step))
    system = _two_nodes("remote-batch")
    for i in range(6):                        # six links each way, packed in two workers
        for here, there in (("a", "b"), ("b", "a")):
            system.add(f"{here}{i}", Counter, node=here, period=0.01, group=f"w{here}")
            system.add(f"{here}{i}_reader", Collector, node=there, group=f"w{there}")
            system.link(f"{here}{i}.out", f"{here}{i}_reader.x")
    with system.launch() as run:
        for i in range(6):
            for here in "ab":
                eventually(lambda r=f"{here}{i}_reader": run.state(r)["received"] > 5,
                           what=f"values at {here}{i}_reader")
        transports = {link.transport for link in run.stats().links.values()}
    assert transports == {"zmq"}
    assert sorted(calls) == sorted((step, node, 6) for step in ("open_inbound", "publish",
                                                                "follow") for node in "ab")


def test_links_across_nodes_can_be_added_and_removed_while_running() -> None:
    system = _two_nodes("remote-live")
    system.add("src", Counter, node="a", period=0.001)
    system.add("first", Collector, node="b")
    system.link("src.out", "first.x")
    with system.launch() as run:
        eventually(lambda: run.state("first")["received"] > 10, what="values at first")
        run.add("second", Collector, node="b")
        run.link("src.out", "second.x")
        eventually(lambda: run.state("second")["received"] > 10, what="values at second")
        run.remove("first")
        state = run.state("second")
        eventually(lambda: run.state("second")["received"] > state["received"] + 10,
                   what="values go on after the other reader left")
        state = run.state("second")
        followed = run._launcher.nodes["b"].bridge.followed()
    assert state["out_of_order"] == 0 and state["duplicates"] == 0
    assert followed == {"src.out": ["src.out->second.x"]}       # first's subscription gone


def test_a_restarted_writer_feeds_its_remote_readers_again() -> None:
    system = _two_nodes("remote-restart")
    system.add("src", Counter, node="a", period=0.001, restart="fresh")
    system.add("dst", Collector, node="b")
    system.link("src.out", "dst.x")
    with system.launch() as run:
        eventually(lambda: run.state("dst")["received"] > 10, what="first values")
        os.kill(run.stats().modules["src"].pid, signal.SIGKILL)
        eventually(lambda: run.stats().modules["src"].restarts == 1, what="a restart")
        before = run.state("dst")["received"]
        eventually(lambda: run.state("dst")["received"] > before + 10,
                   what="values from the restarted writer")
