"""The executor's ends of a worker's pipe: what the outbox sends is read by a plain
``Connection``, in order, and no ``put`` waits for a reader that reads nothing; the
inbox hands out whole messages only, and never waits for the rest of one."""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import pickle
import queue
import struct
import threading
import time
from collections.abc import Iterator
from multiprocessing import reduction
from multiprocessing.connection import Connection

import psutil
import pytest
from conftest import eventually

from pb3a.node.watched_process import WatchedProcess
from pb3a.node.workers import WorkerHandle, WorkerPool, WorkerSettings
from pb3a.transport import pickling
from pb3a.transport.pipe import Inbox, Outbox

BIG = 4 * 1024 * 1024       # far more than a socket pair's buffers hold


@pytest.fixture
def pipe() -> Iterator[tuple[Outbox, Connection]]:
    ours, theirs = multiprocessing.Pipe()
    outbox = Outbox(ours.fileno())
    ours.close()               # the outbox holds its own descriptor
    yield outbox, theirs
    outbox.close()
    theirs.close()


def _open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def test_what_it_sends_reads_as_a_connection_sends_it(pipe, tmp_path) -> None:
    outbox, theirs = pipe
    path = tmp_path / "passed"
    path.write_text("through the pipe")
    with open(path) as file:
        outbox.put([b"small", bytes(range(256)) * 100], fd=file.fileno())
    outbox.put([b""])
    assert theirs.recv_bytes() == b"small"
    assert theirs.recv_bytes() == bytes(range(256)) * 100     # (over 16 KiB: a header alone)
    with os.fdopen(reduction.recv_handle(theirs)) as passed:  # the caller closed its own
        assert passed.read() == "through the pipe"
    assert theirs.recv_bytes() == b""


def test_a_full_pipe_never_holds_a_put_and_the_rest_follows_in_order(pipe) -> None:
    outbox, theirs = pipe
    big = os.urandom(BIG)
    started = time.monotonic()
    outbox.put([big])
    outbox.put([b"after"])
    assert time.monotonic() - started < 2.0            # (a held put waits for good)
    assert outbox.waiting() == 2
    assert theirs.recv_bytes() == big               # read: the drain writes the rest
    assert theirs.recv_bytes() == b"after"
    eventually(lambda: outbox.waiting() == 0, what="the outbox drained")


def test_a_message_none_of_which_went_is_withdrawn_and_never_read(pipe) -> None:
    outbox, theirs = pipe
    began = outbox.put([os.urandom(BIG)])
    behind = outbox.put([b"withdrawn"])
    last = outbox.put([b"kept"])
    assert not outbox.withdraw(began)               # half gone: the stream needs the rest
    assert outbox.withdraw(behind)
    assert not outbox.withdraw(behind)
    assert len(theirs.recv_bytes()) == BIG
    assert theirs.recv_bytes() == b"kept"
    eventually(lambda: outbox.waiting() == 0, what="the outbox drained")
    assert not outbox.withdraw(last)                # gone whole


def test_closing_drops_what_waits_and_the_reader_sees_the_end(pipe, tmp_path) -> None:
    outbox, theirs = pipe
    fds = _open_fds()
    outbox.put([os.urandom(BIG)])
    with open(tmp_path / "f", "w") as file:
        outbox.put([b"with a descriptor"], fd=file.fileno())
    assert _open_fds() == fds + 1                   # our duplicate, until it goes
    outbox.close()
    assert _open_fds() == fds - 1                   # and the pipe's
    with pytest.raises(OSError, match="closed"):
        outbox.put([b"late"])
    with pytest.raises(OSError, match="end of file during message"):   # (cut short)
        theirs.recv_bytes()


def test_a_pipe_whose_reader_is_gone_fails_the_put(pipe) -> None:
    outbox, theirs = pipe
    theirs.close()
    with pytest.raises(BrokenPipeError):
        outbox.put([b"to nobody"])
    assert outbox.waiting() == 0


def test_wait_sent_and_a_closing_wait_end_when_the_reader_has_it_or_the_time_is_up(
        pipe) -> None:
    """A stopping worker waits for its last words to go, within a deadline: its
    executor may be frozen."""
    outbox, theirs = pipe
    big = outbox.put([os.urandom(BIG)])
    started = time.monotonic()
    assert not outbox.wait_sent(big, 0.2)             # nobody reads
    assert 0.2 <= time.monotonic() - started < 2.0
    got: queue.Queue[bytes] = queue.Queue()
    reader = threading.Thread(target=lambda: [got.put(theirs.recv_bytes()) for _ in "ab"])
    reader.start()
    assert outbox.wait_sent(big, 10)
    outbox.put([os.urandom(BIG)])
    outbox.close(timeout=10)                          # once the reader has it all
    reader.join(10)
    assert [len(got.get_nowait()) for _ in "ab"] == [BIG, BIG]
    ours, unread = multiprocessing.Pipe()             # another, which nobody reads
    with ours, unread:
        other = Outbox(ours.fileno())
        first, second = other.put([os.urandom(BIG)]), other.put([b"never"])
        assert other.withdraw(second) and not other.wait_sent(second, 10)
        started = time.monotonic()
        other.close(timeout=0.2)                      # gives up on the rest
        assert time.monotonic() - started < 1 and first.done and not first.sent


class _Alarm(Exception):
    """A signal handler's own exception (an alarm bounding a call)."""


def _interrupting(outbox: Outbox, exc_type: type[BaseException]) -> None:
    """Make ``outbox``'s writes raise ``exc_type`` as they return, as a signal's handler
    does when the signal comes then."""
    real = outbox._socket

    class Interrupted:
        fileno, close, shutdown = real.fileno, real.close, real.shutdown

        def sendmsg(self, *args):
            real.sendmsg(*args)
            raise exc_type

    outbox._socket = Interrupted()


@pytest.mark.parametrize("exc_type", [KeyboardInterrupt, _Alarm])
def test_an_interrupt_as_a_write_returns_sends_nothing_more(pipe, exc_type) -> None:
    """A signal's exception (a worker's SIGTERM, a Ctrl-C, a handler's own) raised as a
    write returned leaves how much went unknown: what is still queued, sent again, or a
    message after it, would be read out of step (a handler's own exception had the
    drain send the message again: the request ran twice), so nothing more goes."""
    outbox, theirs = pipe
    _interrupting(outbox, exc_type)
    with pytest.raises(exc_type):
        outbox.put([b"sent", b"unrecorded"])
    with pytest.raises(BrokenPipeError):
        outbox.put([b"out of step"])
    outbox.close()
    assert [theirs.recv_bytes(), theirs.recv_bytes()] == [b"sent", b"unrecorded"]
    with pytest.raises(EOFError):                     # not sent again, nor what followed
        theirs.recv_bytes()


def test_a_ctrl_c_as_a_request_is_written_leaves_no_unreachable_worker() -> None:
    """The executor's outbox broken by a Ctrl-C, its worker reads the end of its pipe
    and exits, its death seen (it waited for good, alive to its pool, every request to
    it failing, its modules running on, never restarted)."""
    deaths: list[WorkerHandle] = []
    pool = WorkerPool(WorkerSettings(spares=0), on_notice=lambda *_: None,
                      on_death=deaths.append)
    try:
        handle = pool.ensure("a/m", "a")
        pool.call("a/m", "stats", 10)
        _interrupting(handle.outbox, KeyboardInterrupt)
        with pytest.raises(KeyboardInterrupt):
            pool.call("a/m", "stats", 2)
        eventually(lambda: deaths == [handle] and not handle.alive, what="the worker's exit")
    finally:
        pool.close(5.0)


def test_a_drain_that_cannot_start_leaves_the_next_put_to_start_one(pipe, monkeypatch) -> None:
    """A drain thread whose start failed (a signal's exception, no thread to be had)
    left the outbox sure one ran: nothing more was ever written."""
    outbox, theirs = pipe
    start = threading.Thread.start
    monkeypatch.setattr(threading.Thread, "start", lambda self: (_ for _ in ()).throw(
        RuntimeError("can't start new thread")))
    with pytest.raises(RuntimeError):
        outbox.put([os.urandom(BIG)])
    monkeypatch.setattr(threading.Thread, "start", start)
    outbox.put([b"after"])
    assert len(theirs.recv_bytes()) == BIG and theirs.recv_bytes() == b"after"


def test_the_inbox_hands_out_whole_messages_only(tmp_path) -> None:
    ours, theirs = multiprocessing.Pipe()
    inbox = Inbox(ours.fileno())
    try:
        big = os.urandom(100_000)                            # (what the pipe holds)
        assert inbox.read() == []                            # nothing came: no wait
        theirs.send_bytes(b"first")
        os.write(theirs.fileno(), struct.pack("!i", len(big)) + big[:1000])   # a part
        assert inbox.read() == [b"first"]
        os.write(theirs.fileno(), big[1000:2000])
        assert inbox.read() == []
        os.write(theirs.fileno(), big[2000:] + struct.pack("!iQ", -1, 3) + b"xyz")
        assert inbox.read() == [big, b"xyz"]                 # (and the long header)
        theirs.send_bytes(b"last")
        theirs.close()
        assert inbox.read() == [b"last"]
        with pytest.raises(EOFError):
            inbox.read()
    finally:
        inbox.close()
        ours.close()
        theirs.close()


class _ThisProcess:
    """The test's own process, as the pool's stand-in worker (it never ends)."""

    pid = os.getpid()


@contextlib.contextmanager
def _pool(keys: list[str], on_notice) -> Iterator[tuple[WorkerPool, dict[str, Connection]]]:
    """A pool whose workers ``keys`` are stand-ins: the test writes their messages."""
    pool = WorkerPool(WorkerSettings(spares=0), on_notice=on_notice,
                      on_death=lambda handle: None)
    workers: dict[str, Connection] = {}
    try:
        for key in keys:
            ours, workers[key] = multiprocessing.Pipe()
            pool.handles[key] = WorkerHandle(
                key, "a", conn=ours, outbox=Outbox(ours.fileno()), inbox=Inbox(ours.fileno()),
                alive=True, pid=os.getpid(), process=WatchedProcess(_ThisProcess()))
        pool._poke()                               # the monitor sees them
        yield pool, workers
    finally:
        handles = list(pool.handles.values())
        pool.handles.clear()                       # (the stand-in must not be stopped)
        pool.close(1.0)
        for handle in handles:
            handle.close_pipe()
        for worker in workers.values():
            worker.close()


def _notice(worker: Connection, kind: str, payload: object) -> None:
    worker.send((None, kind))
    worker.send_bytes(pickling.dumps(payload))


def test_a_worker_frozen_halfway_through_a_message_holds_up_no_other_worker() -> None:
    """One monitor thread reads every worker of a node. A worker frozen halfway through
    a large message (a checkpoint) held it waiting for the rest, and with it every other
    worker's answers and deaths. The rest is read when it comes."""
    notices: queue.Queue[tuple[str, str, object]] = queue.Queue()
    with _pool(["frozen", "other"], lambda handle, kind, payload: notices.put(
            (handle.key, kind, payload))) as (_, workers):
        checkpoint = pickling.dumps({"state": os.urandom(BIG)})
        workers["frozen"].send((None, "checkpoint"))
        writing = workers["frozen"].fileno()
        os.write(writing, struct.pack("!i", len(checkpoint)) + checkpoint[:100_000])
        _notice(workers["other"], "checkpoint", {"state": "small"})
        assert notices.get(timeout=5) == ("other", "checkpoint", {"state": "small"})
        for start in range(100_000, len(checkpoint), 100_000):   # (read as it goes)
            os.write(writing, checkpoint[start:start + 100_000])
        assert notices.get(timeout=5) == ("frozen", "checkpoint", pickle.loads(checkpoint))


def test_a_message_that_fails_where_it_is_taken_loses_none_after_it() -> None:
    """The monitor takes a worker's messages a read at a time: one whose handling
    raised (a notice's handler, a head that cannot be read) lost the rest of that read,
    and a head lost made every later payload be taken for a head."""
    taken: queue.Queue[object] = queue.Queue()

    def on_notice(handle, kind, payload) -> None:
        if payload == "raises":
            raise RuntimeError("a handler's fault")
        taken.put(payload)

    with _pool(["w"], on_notice) as (_, workers):
        worker = workers["w"]
        _notice(worker, "log", "raises")
        worker.send_bytes(b"not a pickle")                # a head that cannot be read
        worker.send_bytes(pickling.dumps("its payload"))
        for index in range(3):
            _notice(worker, "log", index)
        assert [taken.get(timeout=5) for _ in range(3)] == [0, 1, 2]
        assert taken.empty()


def test_a_drain_waits_for_room_whatever_its_descriptor_number(pipe) -> None:
    """A drain waits for room with poll(): select() fails for a descriptor numbered
    1024 or more, and the drain, its failure suppressed, spun a CPU for as long as the
    worker read nothing (146,625 passes a second)."""
    _, theirs = pipe
    taken = [os.dup(theirs.fileno()) for _ in range(1100)]   # (the numbers below 1024)
    try:
        outbox = Outbox(theirs.fileno())
        threads = set(threading.enumerate())
        outbox.put([os.urandom(BIG)])
        (drain,) = set(threading.enumerate()) - threads

        def cpu() -> float:
            (times,) = [t for t in psutil.Process().threads() if t.id == drain.native_id]
            return times.user_time + times.system_time

        before = cpu()
        time.sleep(0.5)                 # (its CPU time over half a second: no event to await)
        assert cpu() - before < 0.03        # (spinning: 0.13 s and more)
        outbox.close()
    finally:
        for fd in taken:
            os.close(fd)
