"""Lossless links: a full reader makes its writer wait (up to the writer's timeout),
locally, inside one process and between nodes; nothing is dropped, duplicated or
reordered, also across migrations and swaps; dropping links behave as before."""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import signal
import threading
import time
from collections.abc import Iterator

import cloudpickle
import pytest
from conftest import eventually
from sample_modules import Burst, Collector, Oversize, Pusher, Sipper, SipperV2, Sizes

from pb3a import Input, Module, RuntimeTimeout, System
from pb3a.config.plan import FlatLink
from pb3a.model.ports import InputPort
from pb3a.node import bridge
from pb3a.node.executor import Executor
from pb3a.node.wiring import Wiring
from pb3a.node.workers import WorkerRequest
from pb3a.transport.doorbell import new_bell
from pb3a.transport.replication import Follower
from pb3a.transport.ring import ShmRing
from pb3a.transport.shm import segment_name
from pb3a.worker.actor import ModuleActor
from pb3a.worker.inbound import InboundLink
from pb3a.worker.process import Worker

pytestmark = pytest.mark.timeout(120)

KEY = "src.out->dst.x"
SIP = 0.0005           # the slow reader's period: at most 8 values (its queue) per step


def _system(name: str, n: int, *, sip: int = 50, remote: bool = False, workers: int = 0,
            timeout: float = 0.0) -> System:
    """src (Pusher, ``n`` values) -> dst (Sipper, lossless:8), on nodes a and b if
    ``remote``, packed into ``workers`` processes if given."""
    system = System(name, workers=workers)
    if remote:
        system.node("a")
        system.node("b")
    system.add("dst", Sipper, period=SIP, state={"sip": sip}, node="b" if remote else None)
    system.add("src", Pusher, state={"limit": n, "timeout": timeout},
               node="a" if remote else None)
    system.link("src.out", "dst.x", policy="lossless:8")
    return system


def _every_value(run, n: int, timeout: float = 90) -> dict:
    return eventually(lambda: (s := run.state("dst"))["received"] >= n and s, timeout=timeout,
                      what=f"{n} values at the reader")


def _in_order(state: dict, n: int) -> bool:
    return (state["received"] == n and state["last"] == n and state["out_of_order"] == 0
            and state["duplicates"] == 0)


def test_a_slow_reader_behind_a_local_lossless_queue_gets_every_value_in_order() -> None:
    n = 20_000             # more than the ring holds (16,384 ints): the writer must wait
    with _system("lossless-local", n).launch() as run:
        state = _every_value(run, n)
        stats = run.stats()
    link, writer = stats.links[KEY], stats.modules["src"]
    assert _in_order(state, n)
    assert link.transport == "shm" and link.policy == "lossless:8"
    assert link.values == n and link.drops == 0 and link.link_failures == 0
    assert link.waits > 0 and link.wait_s > 0
    assert writer.output_waits["out"].waits == link.waits and writer.outputs["out"] == n
    assert writer.errors == 0


def test_a_slow_reader_behind_a_lossless_queue_on_another_node_gets_every_value() -> None:
    n = 20_000             # ring (16,384) + window (2,048) + queue (8) < n: the writer waits
    # the reader sips only once the writer waits (on a loaded machine a writer may be
    # no faster than a reader that sips from the start)
    with _system("lossless-remote", n, sip=0, remote=True).launch() as run:
        eventually(lambda: run.stats().links[KEY].waits > 0, what="the writer waiting")
        run.set_state("dst", sip=50)
        state = _every_value(run, n)
        stats = run.stats()
    link = stats.links[KEY]
    assert _in_order(state, n)
    assert link.transport == "zmq" and link.policy == "lossless:8"
    assert link.values == n and link.drops == 0 and link.link_failures == 0
    assert link.waits > 0 and stats.modules["src"].errors == 0


def test_a_lossless_link_inside_one_process_waits_without_deadlock() -> None:
    n = 3000
    with _system("lossless-memory", n, workers=1).launch() as run:
        state = _every_value(run, n)
        stats = run.stats()
    link = stats.links[KEY]
    assert _in_order(state, n)
    assert link.transport == "memory" and link.drops == 0
    assert link.waits > 0 and stats.modules["src"].errors == 0


@pytest.mark.parametrize("where", ["shm", "memory", "zmq"])
def test_a_write_to_a_reader_that_never_reads_times_out_naming_the_link(where: str) -> None:
    system = _system(f"lossless-stuck-{where}", 0, sip=0, timeout=0.5, remote=where == "zmq",
                     workers=1 if where == "memory" else 0)
    with system.launch() as run:
        writer = eventually(lambda: (m := run.stats().modules["src"]).errors and m,
                            timeout=30, what="a write that timed out")
        sent = run.state("src")["sent"]
        run.set_state("dst", sip=50)                 # the reader wakes up: the writer goes on
        state = eventually(lambda: (s := run.state("dst"))["received"] > sent + 100 and s,
                           what="values after the reader woke up")
        link = run.stats().links[KEY]
    assert writer.last_error.startswith("RuntimeTimeout: write on lossless link "
                                        "src.out -> dst.x timed out")
    assert "has not taken a value for 0.5 s: it is stuck, too slow, or gone" in writer.last_error
    assert link.transport == where and link.drops == 0 and link.link_failures == 0
    # the value that timed out was not sent; the writer sent it again: no gap, no duplicate
    assert state["out_of_order"] == 0 and state["duplicates"] == 0
    assert state["last"] == state["received"]



def test_removing_a_stuck_reader_inside_one_process_ends_its_writer_s_wait_at_once() -> None:
    # the writer waits for room in the reader's input itself (no ring): cutting the link
    # must end that wait as it ends one on a ring, not leave the removal to time out
    system = _system("lossless-cut-memory", 0, sip=0, timeout=60.0, workers=1)
    with system.launch() as run:
        eventually(lambda: run.stats().links[KEY].waits > 0, timeout=30,
                   what="the writer waiting for room")
        start = time.monotonic()
        run.remove("dst", timeout=5.0)
        took = time.monotonic() - start
        writer = eventually(lambda: (m := run.stats().modules["src"]).errors and m,
                            what="the write that gave up")
        assert "dst" not in run.stats().modules
    assert took < 3.0
    assert writer.last_error.startswith("RuntimeTimeout: write on lossless link src.out -> "
                                        "dst.x gave up: the link was cut")


@pytest.mark.parametrize("where", ["shm", "memory"])
def test_closing_stops_a_writer_waiting_for_its_reader_at_once(
        where: str, caplog: pytest.LogCaptureFixture) -> None:
    # The writer is added first, so the shutdown stops its slow reader first; the
    # writer's write, waiting for room in an input nobody reads any more, held the
    # writer's stop: on a ring 6 s (two stops of 3 s, each logged as if the writer were
    # stuck), inside one process 2 s (its grace). Now the write goes in, room or not.
    system = System(f"lossless-close-{where}", workers=1 if where == "memory" else 0)
    system.add("src", Pusher, state={"timeout": 60.0})
    system.add("dst", Sipper, period=0.01, state={"sip": 1})
    system.link("src.out", "dst.x", policy="lossless:8")
    with caplog.at_level(logging.WARNING):
        with system.launch() as run:
            eventually(lambda: run.stats().links[KEY].waits > 0, timeout=30,
                       what="the writer waiting for room")
            assert run.stats().links[KEY].transport == where
            start = time.monotonic()
        took = time.monotonic() - start
    assert took < 1.8                     # (it waited out 6 s on a ring, 2 s in a worker)
    assert not [record.getMessage() for record in caplog.records
                if "src" in record.getMessage()]


@pytest.mark.parametrize("where", ["shm", "memory", "zmq"])
def test_a_writer_stuck_on_a_lossless_link_shows_in_stats_while_it_waits(where: str) -> None:
    system = _system(f"lossless-waiting-{where}", 0, sip=0, timeout=60.0, remote=where == "zmq",
                     workers=1 if where == "memory" else 0)
    with system.launch() as run:
        link = eventually(lambda: (found := run.stats().links[KEY]).waits and found,
                          timeout=30, what="the writer's wait, in stats while it waits")
        assert run.stats().modules["src"].errors == 0      # no write has timed out
        run.set_state("dst", sip=50)                        # the wait ends: its seconds count
        eventually(lambda: run.stats().links[KEY].wait_s > 0, what="the wait's seconds")
    assert link.transport == where


def test_a_lossless_link_stays_lossless_across_migrations_and_a_swap() -> None:
    n = 60_000                 # enough that the four moves happen mid-stream even when a
                               # loaded machine makes each take seconds (20,000 did not)
    system = System("lossless-moves")
    system.node("a")
    system.node("b")
    system.add("dst", Sipper, period=SIP, state={"sip": 50}, node="a")
    system.add("src", Pusher, state={"limit": n}, node="a")
    system.link("src.out", "dst.x", policy="lossless:8")
    with system.launch() as run:
        transports = []
        for module, node in (("dst", "b"), ("src", "b"), ("dst", "a"), ("src", "a")):
            before = run.state("dst")["received"]
            eventually(lambda before=before: run.state("dst")["received"] >= before + 500,
                       what="values flowing")
            run.migrate(module, to=node)
            link = run.stats().links[KEY]
            transports.append(link.transport)
            assert link.policy == "lossless:8", (module, node, link.policy)
        run.swap("dst", SipperV2)
        state = _every_value(run, n)
        stats = run.stats()
    link = stats.links[KEY]
    assert transports == ["zmq", "shm", "zmq", "shm"]
    assert _in_order(state, n) and state["swapped_in"] == 1
    assert link.policy == "lossless:8" and link.drops == 0 and link.link_failures == 0
    assert stats.modules["dst"].inputs["x"].drops == 0


def test_a_stuck_lossless_reader_migrates_with_everything_on_the_way() -> None:
    # The writer fills the reader's ring, the sender's window and the bridge's backlog;
    # the reader, paused for the move, takes in all of it (the bridge asks it to).
    n = 25_000
    with _system("lossless-stuck-move", n, sip=0, remote=True, timeout=1.0).launch() as run:
        eventually(lambda: run.stats().links[KEY].waits > 0, what="the writer held back")
        run.migrate("dst", to="a")
        assert run.stats().links[KEY].transport == "shm"
        run.set_state("dst", sip=50)
        state = _every_value(run, n)
        link = run.stats().links[KEY]
    assert _in_order(state, n)
    assert link.policy == "lossless:8" and link.drops == 0 and link.link_failures == 0


@pytest.mark.parametrize("failing", ["the reader's half", "the writer's answer",
                                     "the reader's worker"])
def test_a_move_whose_unwiring_fails_loses_no_value_of_a_remote_lossless_link(
        failing: str, monkeypatch: pytest.MonkeyPatch) -> None:
    # The move unpublished the writer's half (its sender knew how far it had got), then
    # closing the reader's half failed, or the writer's answer was lost on the way; the
    # undo unwired the link again, the second unpublish said "not published here"
    # (position 0), and the reader's bridge closed the link at once, with the values
    # still in its backlog (lost in some runs: those the reader had not made room for
    # by then). Here the backlog goes into the ring only once someone waits for it.
    # (The reader's worker failing as it lets go of the ring, after the bridge closed
    # its half, lost nothing before: the undo's unwiring takes in what the ring holds.)
    n = 25_000
    waited = threading.Event()
    offer, wait_delivered = bridge._Feed.offer, Follower.wait_delivered

    def held(feed: bridge._Feed) -> None:
        if waited.is_set():
            offer(feed)

    def waiting(follower: Follower, topic: str, seq: int, timeout: float) -> bool:
        if seq > 0:
            waited.set()
        return wait_delivered(follower, topic, seq, timeout)
    failed: list[str] = []
    close_inbound, unpublish = Executor.close_inbound, Executor.unpublish
    unlink_request = Wiring._unlink_request

    def reader_fails(executor: Executor, links: list) -> list[int]:
        if not failed:
            failed.append(executor.node)
            raise RuntimeTimeout("values of src.out still in flight after 10 s")
        return close_inbound(executor, links)

    def answer_lost(executor: Executor, links: list) -> list:
        reached = unpublish(executor, links)
        if not failed:
            failed.append(executor.node)
            raise RuntimeTimeout("no answer from the worker of src in time")
        return reached

    def worker_fails(wiring: Wiring, link: FlatLink, module: str,
                     op: str) -> WorkerRequest | None:
        if op == "unlink_in" and not failed:
            failed.append(wiring._node.node)
            raise RuntimeTimeout("no answer from the worker of dst in time")
        return unlink_request(wiring, link, module, op)
    with _system("lossless-unwiring-fails", n, sip=0, remote=True, timeout=1.0).launch() as run:
        # (the ring and the input's queue full, the rest waits in the bridge's backlog)
        eventually(lambda: run.state("src")["sent"] > 16_384 + 8 + 1000,
                   what="the writer beyond what the reader's ring holds")
        monkeypatch.setattr(bridge._Feed, "offer", held)
        monkeypatch.setattr(Follower, "wait_delivered", waiting)
        if failing == "the reader's half":
            monkeypatch.setattr(Executor, "close_inbound", reader_fails)
        elif failing == "the writer's answer":
            monkeypatch.setattr(Executor, "unpublish", answer_lost)
        else:
            monkeypatch.setattr(Wiring, "_unlink_request", worker_fails)
        with pytest.raises(RuntimeTimeout, match="nothing moved"):
            run.migrate("dst", to="a", timeout=30)
        assert failed == ["a" if failing == "the writer's answer" else "b"]
        assert run.where("dst") == "b" and run.stats().links[KEY].transport == "zmq"
        run.set_state("dst", sip=50)
        state = _every_value(run, n, timeout=60)
        link = run.stats().links[KEY]
    assert _in_order(state, n)
    assert link.drops == 0 and link.link_failures == 0


@pytest.mark.parametrize("op", ["unlink_out", "unlink_in"])
def test_a_move_whose_unwiring_fails_loses_no_value_of_a_lossless_ring(
        op: str, monkeypatch: pytest.MonkeyPatch) -> None:
    # The writer's or the reader's worker fails to let go of the ring as the move
    # unwires the link: the undo unwires it again, the reader taking in what the ring
    # holds, and wires it anew where it was.
    n = 40_000                     # more than the ring (16,384) and the input hold
    system = System(f"lossless-ring-unwiring-fails-{op.replace('_', '-')}")
    system.node("a")
    system.node("b")
    system.add("dst", Sipper, period=SIP, state={"sip": 0}, node="a")
    system.add("src", Pusher, state={"limit": n, "timeout": 1.0}, node="a")
    system.link("src.out", "dst.x", policy="lossless:8")
    unlink_request, failed = Wiring._unlink_request, []

    def fails(wiring: Wiring, link: FlatLink, module: str, asked: str) -> WorkerRequest | None:
        if asked == op and not failed:
            failed.append(module)
            raise RuntimeTimeout(f"no answer from the worker of {module} in time")
        return unlink_request(wiring, link, module, asked)
    with system.launch() as run:
        eventually(lambda: run.stats().links[KEY].waits > 0, what="the writer held back")
        monkeypatch.setattr(Wiring, "_unlink_request", fails)
        with pytest.raises(RuntimeTimeout, match="nothing moved"):
            run.migrate("dst", to="b", timeout=30)
        assert failed == ["src" if op == "unlink_out" else "dst"]
        assert run.where("dst") == "a" and run.stats().links[KEY].transport == "shm"
        run.set_state("dst", sip=50)
        state = _every_value(run, n, timeout=60)
        link = run.stats().links[KEY]
    assert _in_order(state, n)
    assert link.drops == 0 and link.link_failures == 0


class Handler(Module):
    """A slow reader that handles each value as it comes (``on_input``: run by its
    worker's receiver when it is the worker's only module), ``sip_s`` each, checking
    they are 1, 2, 3, ... in order."""

    x = Input(int, policy="lossless:8")
    sip_s = 0.001
    received = 0
    last = 0
    out_of_order = 0
    duplicates = 0

    def on_input(self, port) -> None:
        value = port.read()
        if value == self.last:
            self.duplicates += 1
        elif value != self.last + 1:
            self.out_of_order += 1
        self.last = value
        self.received += 1
        time.sleep(self.sip_s)


def test_a_reader_handling_each_value_moves_from_behind_a_lossless_link_at_once() -> None:
    # A reader whose on_input its worker's receiver runs, behind a remote lossless link
    # that holds its writer back, moved to the writer's node: the receiver, between
    # two batches of calls, waited for the module's lock, which the move's pause held,
    # so it took in nothing of the link, and the move waited for the link's values on
    # the way until its time ran out (every time in some runs: "values of src.out
    # still in flight"). Three moves there and back, each well within its 10 s.
    system = System("lossless-handler-moves")
    system.node("a")
    system.node("b")
    system.add("dst", Handler, node="b")
    system.add("src", Pusher, node="a", state={"timeout": 1.0})
    system.link("src.out", "dst.x", policy="lossless:8")
    with system.launch() as run:
        for node in ("a", "b", "a"):
            before = run.stats().links[KEY].waits
            eventually(lambda before=before: run.stats().links[KEY].waits > before,
                       what="the writer held back")
            started = time.monotonic()
            run.migrate("dst", to=node, timeout=10)
            assert time.monotonic() - started < 5, node
        run.set_state("src", limit=run.state("src")["sent"])
        run.set_state("dst", sip_s=0.0)
        sent = run.state("src")["sent"]
        state = eventually(lambda: (s := run.state("dst"))["received"] >= sent and s,
                           timeout=60, what="every value at the reader")
        link = run.stats().links[KEY]
    assert state["received"] == state["last"] == sent
    assert state["out_of_order"] == state["duplicates"] == 0
    assert link.drops == 0 and link.link_failures == 0


class _Gated(Handler):
    """``Handler`` whose first call, while ``_gate`` holds ``(inside, go)``, says so
    (``inside``) and waits for ``go``."""

    def on_input(self, port) -> None:
        gate = self.__dict__.pop("_gate", None)
        if gate is not None:
            inside, go = gate
            inside.set()
            go.wait(5)
        super().on_input(port)


@contextlib.contextmanager
def _solo_reader(cls: type[Handler]) -> Iterator[tuple[Worker, ShmRing, ModuleActor]]:
    """A worker in this process whose only module, ``dst`` (``cls``), reads a local
    lossless ring (``KEY``, lossless:8): the worker, the ring's writer, the actor."""
    owner = ShmRing.create(segment_name("ring"), 64 * 1024, lossless=True)
    writer = ShmRing.attach(owner.name)
    ours, theirs = multiprocessing.Pipe()
    sigterm = signal.getsignal(signal.SIGTERM)   # (a worker's shutdown ignores it after)
    worker = Worker(ours, "key", new_bell(), 3600.0)
    try:
        worker.op_add("dst", cloudpickle.dumps(cls), None, "never", {})
        worker.op_start(["dst"])
        worker.op_link_in(KEY, "dst", "x", owner.name, "lossless:8")
        writer.set_bell(worker._bell_fd)
        yield worker, writer, worker.actors["dst"]
    finally:
        if "dst" in worker._paused:
            worker.op_resume("dst")          # (a receiver waiting for it is let go)
        worker.shutdown()
        signal.signal(signal.SIGTERM, sigterm)
        ours.close()
        theirs.close()
        writer.close()
        owner.close()


def _pause_after_look(worker: Worker, actor: ModuleActor, look: int,
                      after: threading.Event | None = None) -> threading.Event:
    """Make the move's pause take ``actor``'s lock right after the receiver's ``look``-th
    look at it (once ``after`` is set, if given), which found it free: the interleaving
    that held the receiver. The event returned is set once the pause holds the lock."""
    lock_free, looks, paused = actor.lock.locked, [], threading.Event()

    def looked() -> bool:
        if threading.current_thread().name != "pb3a-receiver":
            return lock_free()
        looks.append(None)
        if len(looks) != look:
            return lock_free()
        assert after is None or after.wait(5)
        free = lock_free()
        threading.Thread(target=lambda: (worker.op_pause("dst", 10.0), paused.set()),
                         daemon=True).start()
        assert paused.wait(5), "the pause did not take the lock"
        return free
    actor.lock.locked = looked
    return paused


def _takes_in_the_flushed_ring(worker: Worker, writer: ShmRing, actor: ModuleActor,
                               paused: threading.Event, n: int) -> None:
    """Once paused, the move's drain asks for the ring's values (``request_flush``, as
    the bridge closing the link does): the receiver takes them all into the input;
    once resumed, the module handles each once, in order."""
    assert paused.wait(10), "the receiver never looked at the lock"
    writer.request_flush()
    port = actor.inputs["x"]
    eventually(lambda: port.received == n, timeout=5,
               what="the flushed ring taken in while the reader is paused")
    assert actor.module.received < n         # (paused: taken in, not handled)
    worker.op_resume("dst")
    eventually(lambda: actor.module.received == n, what="every value handled")
    assert actor.module.last == n
    assert actor.module.out_of_order == actor.module.duplicates == 0


def test_a_receiver_whose_reader_is_paused_as_it_dispatches_takes_in_a_flushed_ring() -> None:
    # The receiver runs its only module's on_input itself when it finds the module's
    # lock free; a move's pause that took the lock right after that look (forced here)
    # held the receiver in the dispatch's wait for it, so it took in nothing of any
    # ring, flushed or not, for as long as the move held the module: the move waited
    # for the link's values on the way until its time ran out (rarely, in the test
    # above on a loaded machine: "values of src.out still in flight after 9.57 s").
    n = 200                                  # more than the input holds (8)
    with _solo_reader(Handler) as (worker, writer, actor):
        paused = _pause_after_look(worker, actor, 1)
        assert writer.offer(list(range(1, n + 1))) == n
        _takes_in_the_flushed_ring(worker, writer, actor, paused, n)


def test_a_receiver_whose_reader_is_paused_between_two_batches_takes_in_a_flushed_ring(
        ) -> None:
    # The same between two batches of calls the receiver runs: a batch cut short for a
    # request (a state read), the pause taking the lock once the read has let it go,
    # right after the receiver looked at it before its next batch.
    n = 200
    with _solo_reader(_Gated) as (worker, writer, actor):
        inside, go, read = threading.Event(), threading.Event(), threading.Event()
        actor.module._gate = (inside, go)
        paused = _pause_after_look(worker, actor, 2, after=read)
        assert writer.offer(list(range(1, n + 1))) == n
        assert inside.wait(5), "no batch of calls began"
        reading = threading.Thread(target=lambda: (worker.op_get_state("dst"), read.set()),
                                   daemon=True)
        reading.start()
        eventually(lambda: actor.lock.requests, what="the read waiting for the lock")
        go.set()                             # the batch ends for the read
        _takes_in_the_flushed_ring(worker, writer, actor, paused, n)
        reading.join(5)


def test_a_link_closed_as_the_receiver_drains_it_delivers_every_value_in_order() -> None:
    # A move unwires a link (its close takes in the rest of the ring) while the
    # receiver drains it too: each took its batch in turn, but delivered it after
    # letting the link go, and a batch the receiver took, delivered after the close
    # delivered the next, reached the module out of order (a full run: 3 values out of
    # order, an adjacent pair swapped, in the move test above).
    owner = ShmRing.create(segment_name("ring"), 64 * 1024, lossless=True)
    writer = ShmRing.attach(owner.name)
    link = InboundLink(ShmRing.attach(owner.name), InputPort(Handler.x, "dst"))
    deliver, inside, go = link.port.deliver_many, threading.Event(), threading.Event()

    def held_first(values, sent_at=None) -> None:     # the receiver, stopped as it delivers
        if not inside.is_set():
            inside.set()
            go.wait(5)
        deliver(values, sent_at)
    link.port.deliver_many = held_first
    try:
        assert writer.offer(list(range(1, 11))) == 10
        receiver = threading.Thread(target=link.drain, args=(3,), daemon=True)
        receiver.start()
        assert inside.wait(5)
        closing = threading.Thread(target=link.close, daemon=True)   # (the move's unwiring)
        closing.start()
        closing.join(0.5)                           # (delivered meanwhile, before the fix)
        go.set()
        receiver.join(5)
        closing.join(5)
        assert not receiver.is_alive() and not closing.is_alive()
        assert [link.port.read() for _ in range(10)] == list(range(1, 11))
    finally:
        go.set()
        writer.close()
        owner.close()


def test_a_reader_moves_away_from_a_writer_in_its_process_that_waits_for_it() -> None:
    # writer and slow reader share a worker; the writer's step writes more than the
    # reader takes in the pause's wait (10 s), each write waiting for room in the input.
    # The move pauses the writer first: the pause waited for that step, which waited for
    # the reader, and the move failed. Now the writes go into the input, room or not,
    # while the pause waits: the step ends, and the reader moves with all of them.
    n = 20_000                           # 40 s of the reader's 500 values a second
    system = System("lossless-move-away")
    system.node("a", workers=1)
    system.node("b")
    system.add("dst", Sipper, period=0.002, state={"sip": 1}, node="a")
    system.add("src", Burst, state={"limit": n}, node="a")
    system.link("src.out", "dst.x", policy="lossless:8")
    with system.launch() as run:
        eventually(lambda: run.stats().links[KEY].waits > 0, what="the writer waiting")
        assert run.stats().links[KEY].transport == "memory"
        run.migrate("dst", to="b")
        assert run.where("dst") == "b" and run.stats().links[KEY].transport == "zmq"
        run.set_state("dst", sip=50)
        state = _every_value(run, n)
        stats = run.stats()
    link = stats.links[KEY]
    assert _in_order(state, n)
    assert link.policy == "lossless:8" and link.drops == 0 and link.link_failures == 0
    assert stats.modules["src"].errors == 0


def test_a_writer_waiting_for_room_on_a_lossless_ring_moves_at_once() -> None:
    # The reader takes nothing while the writer moves. The move first measured the
    # writer's state under its lock, which waited for its write: 10 s, the write's
    # timeout, after which the value was not sent and an error was counted. Now the
    # write goes into the reader's input, room or not, before the writer is captured.
    n = 40_000                         # more than the ring (16,384) and the input hold
    system = System("lossless-writer-moves")
    system.node("a")
    system.node("b")
    system.add("dst", Sipper, period=SIP, state={"sip": 0}, node="a")
    system.add("src", Pusher, state={"limit": n}, node="a")
    system.link("src.out", "dst.x", policy="lossless:8")
    with system.launch() as run:
        eventually(lambda: run.stats().links[KEY].waits > 0, timeout=30,
                   what="the writer waiting for room")
        start = time.monotonic()
        run.migrate("src", to="b")
        took = time.monotonic() - start
        assert run.where("src") == "b" and run.stats().links[KEY].transport == "zmq"
        run.set_state("dst", sip=50)
        state = _every_value(run, n)
        stats = run.stats()
    assert took < 3.0
    assert _in_order(state, n)
    link = stats.links[KEY]
    assert link.policy == "lossless:8" and link.drops == 0 and link.link_failures == 0
    assert stats.modules["src"].errors == 0


def test_relink_may_make_a_dropping_link_lossless() -> None:
    n = 20_000
    system = System("lossless-relink")
    system.add("dst", Sipper, period=SIP, state={"sip": 50})
    system.add("src", Pusher, state={"limit": n})
    system.link("src.out", "dst.x", policy="queue:8")
    with system.launch() as run:
        eventually(lambda: run.stats().links[KEY].drops > 0, what="drops on queue:8")
        run.relink("src.out", "dst.x", policy="lossless:8")
        dropped = run.stats().links[KEY].drops
        eventually(lambda: run.state("dst")["last"] == n, timeout=90, what="the last value")
        link = run.stats().links[KEY]
    assert link.policy == "lossless:8" and link.drops == dropped     # none since


def test_a_dropping_queue_still_drops_its_oldest_and_its_writer_does_not_wait() -> None:
    n = 2000
    system = System("dropping-queue")
    system.add("dst", Collector, state={"delay": 0.002})
    system.add("src", Burst, state={"limit": n})
    system.link("src.out", "dst.x", policy="queue:10")
    with system.launch() as run:
        link = eventually(lambda: (lk := run.stats().links[KEY]).values == n
                          and lk.pending == 0 and lk, timeout=30, what="every value handled")
        state = run.state("dst")
    assert link.drops > 0 and state["received"] + link.drops == n and state["last"] == n
    assert link.waits == 0 and link.wait_s == 0.0


def test_a_latest_input_still_gives_the_newest_and_its_writer_does_not_wait() -> None:
    n = 2000
    system = System("dropping-latest")
    system.add("dst", Collector, state={"delay": 0.002})
    system.add("src", Burst, state={"limit": n})
    system.link("src.out", "dst.x", policy="latest")
    with system.launch() as run:
        state = eventually(lambda: (s := run.state("dst"))["last"] == n and s, timeout=30,
                           what="the newest value")
        link = run.stats().links[KEY]
    assert state["received"] < n and state["out_of_order"] == 0
    assert link.drops == 0 and link.waits == 0


@pytest.mark.parametrize("where", ["shm", "zmq"])
def test_a_value_too_large_for_the_reader_s_ring_is_refused_as_it_is_written(where) -> None:
    """Between nodes the writer once sent it, and the reader's node could only drop it
    (logged), lossless link or not: the writer now checks it against the reader's ring."""
    system = System(f"oversize-{where}")
    if where == "zmq":
        system.node("a")
        system.node("b")
    system.add("sink", Sizes, node="b" if where == "zmq" else None)
    system.add("src", Oversize, node="a" if where == "zmq" else None)
    system.link("src.out", "sink.x", policy="lossless:8")
    with system.launch() as run:
        sizes = eventually(lambda: len(s := run.state("sink")["sizes"]) >= 3 and s,
                           what="the small values after the large one")
        refused = run.state("src")["refused"]
        transport = run.stats().links["src.out->sink.x"].transport
    assert transport == where
    assert refused.startswith("a value of 2097152 bytes does not fit this link's")
    assert "need an output of type object" in refused
    assert set(sizes) == {5}
