"""Control RPC: answers, errors, time-outs, concurrency, and forged frames refused
before anything is unpickled."""

from __future__ import annotations

import collections
import contextlib
import gc
import importlib
import logging
import os
import pickle
import re
import socket
import struct
import sys
import threading
import time
import types
import warnings
from typing import Any

import pytest
import zmq
from conftest import eventually

from pb3a import RuntimeFailure, RuntimeTimeout
from pb3a.errors import RuntimeCancelled
from pb3a.transport import control
from pb3a.transport.addresses import bind_advertised, close_bound, numeric
from pb3a.transport.auth import ClusterKey, Opener, Sealer
from pb3a.transport.control import REQUEST, ControlClient, ControlServer
from pb3a.transport.loop import SocketLoop

KEY = ClusterKey.load({"PB3A_KEY": "c" * 40})
WAITS_10_S = struct.pack("<d", 10.0)       # how long a hand-made request's caller waits
release = threading.Event()


def handler(op: str, args: dict[str, Any]) -> Any:
    if op == "add":
        return args["a"] + args["b"]
    if op == "fail":
        raise ValueError("no such module 'x'")
    if op == "block":
        release.wait(10.0)
        return "released"
    if op == "elsewhere":
        return _Elsewhere()
    raise KeyError(op)


@pytest.fixture
def rpc():
    server = ControlServer(KEY, handler)
    client = ControlClient(KEY, server.address)
    yield server, client
    release.set()
    client.close()
    server.close()
    release.clear()


def test_calls_return_results_and_errors_name_the_operation(rpc) -> None:
    _, client = rpc
    assert client.call("add", a=2, b=3) == 5
    with pytest.raises(RuntimeFailure, match=r"fail at tcp://.* failed: ValueError: no such"):
        client.call("fail")


def test_a_slow_operation_times_out_and_pings_still_get_through(rpc) -> None:
    _, client = rpc
    blocked = threading.Thread(target=lambda: client.call("block", timeout=10.0))
    blocked.start()
    assert client.call("ping", timeout=5.0) == "pong"       # answered on the I/O thread
    with pytest.raises(RuntimeTimeout, match=r"did not answer .add. within 0\.2 s"):
        client.call("add", timeout=0.2, a=1, b=1)            # queued behind "block"
    release.set()
    blocked.join(10.0)
    assert client.call("add", a=1, b=1) == 2


@pytest.mark.parametrize("expires", [True, False])
def test_a_request_not_begun_within_its_caller_s_wait_is_dropped_by_a_server_that_expires(
        expires: bool) -> None:
    """A server made with ``expires`` (a device's) drops a request it has not begun
    within the time its caller waits, counted from when it came, answering that it was
    not done; the system's own servers run it late (their operations carry deadlines of
    their own, and some must be done however late)."""
    began, go, ran = threading.Event(), threading.Event(), []

    def busy(op: str, args: dict[str, Any]) -> None:
        if op == "block":
            began.set()
            go.wait(10.0)
        ran.append(op)

    server = ControlServer(KEY, busy, expires=expires, title="the device")
    client = ControlClient(KEY, server.address)
    sender = zmq.Context.instance().socket(zmq.DEALER)
    sender.setsockopt(zmq.LINGER, 0)
    sender.connect(server.address)
    blocked = threading.Thread(target=client.call, args=("block",), daemon=True)
    blocked.start()
    try:
        assert began.wait(5.0)
        # its caller waits 0 s: gone by the time the server is free
        sender.send_multipart(Sealer(KEY).seal(REQUEST, [
            b"\1" * 8, server.instance, struct.pack("<d", 0.0), pickle.dumps(("move", {}))]))
        go.set()
        assert sender.poll(5000)
        ok, answer = pickle.loads(Opener(KEY).open(sender.recv_multipart()).frames[1])
    finally:
        go.set()
        blocked.join(5.0)
        sender.close(0)
        client.close()
        server.close()
    if expires:
        assert not ok and isinstance(answer, control.Expired) and ran == ["block"]
        assert str(answer) == (f"the device at {server.address} dropped 'move', not begun "
                               "within the time its caller waits (busy with earlier "
                               "requests): it was not done")
    else:
        assert ok and ran == ["block", "move"]


class _HeldAfterTaking(dict):
    """A client's table of requests to send whose ``get`` on the socket thread (``_send``
    taking a request's entry) waits, once it is taken, until ``go`` is set: as a switch
    of threads there does, between taking the entry and counting it sent."""

    def __init__(self, taken: threading.Event, go: threading.Event) -> None:
        super().__init__()
        self.taken, self.go = taken, go

    def get(self, key, default=None):
        value = super().get(key, default)
        if threading.current_thread().name == "pb3a-control-client" and value is not None:
            self.taken.set()
            assert self.go.wait(10.0)
        return value


class _CancelledOnceTaken:
    """A body's wait (``pb3a.worker.waits``) cancelled once its request was taken to be
    sent: the driver's move, while the socket thread sends it."""

    def __init__(self, taken: threading.Event) -> None:
        self.taken = taken

    def answer(self, ok: bool, result: Any) -> None:
        pass

    def result(self, timeout: float) -> None:
        assert self.taken.wait(10.0)
        raise RuntimeCancelled("request 'move' cancelled: module 'd' is being moved")


def test_a_request_cancelled_while_it_is_being_sent_is_withdrawn() -> None:
    """The caller read whether its request had been sent on its own thread: one the
    socket thread was sending then was not counted yet, so nothing was withdrawn, and
    the device carried it out once free."""
    release, moves = threading.Event(), []

    def device(op: str, args: dict[str, Any]) -> None:
        if op == "block":
            release.wait(10.0)
        else:
            moves.append(op)

    server = ControlServer(KEY, device, expires=True)
    busy, driver = ControlClient(KEY, server.address), ControlClient(KEY, server.address)
    blocked = threading.Thread(target=busy.call, args=("block", 10.0), daemon=True)
    try:
        blocked.start()
        assert driver.call("ping", 5.0) == "pong"
        taken, go = threading.Event(), threading.Event()
        driver._sent = _HeldAfterTaking(taken, go)
        with pytest.raises(RuntimeCancelled):
            driver.request("move", {}, 5.0, wait=_CancelledOnceTaken(taken))
        go.set()                                # (the send goes on, then the withdrawal)
        # (a ping on the same connection, answered once the server has read what went
        # before it: the device is freed with the withdrawal read, as a busy one is)
        assert driver.call("ping", 5.0) == "pong"
        release.set()
        assert busy.call("after", 5.0) is None   # (queued behind the move, if kept)
    finally:
        release.set()
        blocked.join(10.0)
        busy.close()
        driver.close()
        server.close()
    assert moves == ["after"], moves


class _SlowDownlink:
    """A TCP proxy to ``address`` whose bytes back to the client take ``delay`` s (a
    satellite or a congested radio link); ``address``: the proxy's."""

    def __init__(self, address: str, delay: float) -> None:
        self._to = address.removeprefix("tcp://").rsplit(":", 1)
        self._delay, self._sockets = delay, []
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.address = f"tcp://127.0.0.1:{self._listener.getsockname()[1]}"
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        with contextlib.suppress(OSError):
            while True:
                near, _ = self._listener.accept()
                far = socket.create_connection((self._to[0], int(self._to[1])), timeout=5)
                self._sockets += [near, far]
                for src, dst, delay in ((near, far, 0.0), (far, near, self._delay)):
                    threading.Thread(target=self._pump, args=(src, dst, delay),
                                     daemon=True).start()

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket, delay: float) -> None:
        with contextlib.suppress(OSError):
            while data := src.recv(65536):
                time.sleep(delay)           # (the link's own slowness, not a wait)
                dst.sendall(data)

    def close(self) -> None:
        self._listener.close()
        for sock in self._sockets:
            sock.close()


def test_a_pb3a_server_behind_a_slow_link_is_not_taken_for_another_program() -> None:
    """A device whose greeting was 0.4 s away was said to speak another protocol by a
    request of 0.3 s ("does not speak PB3A's protocol"), and its driver told to speak
    lines; a connection is taken for another program only once it has gone a second
    ungreeted."""
    server = ControlServer(KEY, lambda op, args: "ok", expires=True)
    link = _SlowDownlink(server.address, 0.4)
    client = ControlClient(KEY, link.address, watch_greeting=True)
    try:
        with pytest.raises(RuntimeTimeout) as timed_out:
            client.call("read", 0.3)
        assert "nothing listens there, it is cut off, or it is busy" in str(timed_out.value)
        assert not client.ungreeted
        assert client.call("read", 5.0) == "ok"
    finally:
        client.close()
        link.close()
        server.close()


def test_closing_the_client_fails_a_waiting_call_at_once_and_any_later_one(rpc) -> None:
    server, _ = rpc
    client = ControlClient(KEY, server.address)
    errors: list[Exception] = []

    def wait_for_block() -> None:
        try:
            client.call("block", timeout=10.0)
        except RuntimeFailure as exc:
            errors.append(exc)
    waiting = threading.Thread(target=wait_for_block)
    waiting.start()
    eventually(lambda: client._waiting, what="the call waiting for its answer")
    started = time.monotonic()
    client.close()
    waiting.join(5.0)
    assert time.monotonic() - started < 2.0 and not waiting.is_alive()
    assert len(errors) == 1 and "closed while it waited" in str(errors[0])
    with pytest.raises(RuntimeFailure, match=r"'add' to tcp://.*: this client is closed"):
        client.call("add", a=1, b=2)


def test_many_threads_share_one_client(rpc) -> None:
    _, client = rpc
    results: dict[int, list[int]] = {}

    def caller(n: int) -> None:
        results[n] = [client.call("add", a=n, b=i) for i in range(50)]
    threads = [threading.Thread(target=caller, args=(n,)) for n in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30.0)
    assert results == {n: [n + i for i in range(50)] for n in range(4)}


class Bomb:
    """Unpickling this would append to ``exploded``: proof of deserialization."""

    def __reduce__(self) -> tuple[Any, ...]:
        return (exploded.append, ("boom",))


exploded: list[str] = []


def test_forged_and_garbage_requests_are_never_unpickled(rpc) -> None:
    server, client = rpc
    bomb = pickle.dumps(("add", Bomb()))
    attacker = zmq.Context.instance().socket(zmq.DEALER)
    attacker.setsockopt(zmq.LINGER, 0)
    attacker.connect(server.address)
    wrong = Sealer(ClusterKey.load({"PB3A_KEY": "w" * 40}))
    attacker.send_multipart([b"garbage"])
    attacker.send_multipart([b"\0" * 8, bomb])
    attacker.send_multipart(wrong.seal(REQUEST, [b"\0" * 8, bomb]))
    attacker.send_multipart([bomb] * 200)
    genuine = Sealer(KEY).seal(REQUEST, [b"\1" * 8, server.instance, WAITS_10_S,
                                         pickle.dumps(("add", {"a": 1, "b": 2}))])
    attacker.send_multipart(genuine)
    attacker.send_multipart(genuine)                         # a replay
    assert client.call("add", a=40, b=2) == 42
    # the attacker's frames come from another peer: they may still be on their way
    eventually(lambda: sum(server.rejected.values()) >= 5 and server.rejected["replay"] == 1,
               what="every forged frame refused")
    assert exploded == []
    assert server.rejected["replay"] == 1
    attacker.close(0)


class _Elsewhere:
    """Unpickles as an import of a module the server's process does not have."""

    def __reduce__(self) -> tuple:
        return importlib.import_module, ("pb3a_not_installed_here",)


def test_a_request_naming_a_module_the_server_cannot_import_is_answered_at_once(rpc) -> None:
    server, client = rpc
    started = time.monotonic()
    with pytest.raises(RuntimeFailure, match="names Python module 'pb3a_not_installed_here',"
                                             f" which the process at {server.address} "
                                             "cannot import: install it"):
        client.call("add", 10.0, a=_Elsewhere(), b=1)
    assert time.monotonic() - started < 2.0
    assert client.call("add", a=1, b=2) == 3            # the server goes on


def test_an_answer_naming_a_module_the_client_cannot_import_fails_at_once(rpc) -> None:
    """Such as a module's state holding a class only the server's process can import:
    the caller is told so, not left to wait for its deadline."""
    server, client = rpc
    started = time.monotonic()
    with pytest.raises(RuntimeFailure, match=f"the answer of {server.address} names Python "
                                             "module 'pb3a_not_installed_here', which this "
                                             "process cannot import: install it"):
        client.call("elsewhere", 10.0)
    assert time.monotonic() - started < 2.0
    assert client.call("add", a=1, b=2) == 3            # the client goes on


def test_a_request_naming_a_module_not_imported_yet_waits_for_the_decode_lock() -> None:
    """A node's executor imports the configuration's modules in the background; a
    request naming a class of a module not imported yet waits for that, never importing
    beside it (two threads importing through a circular import can get each other's
    half-made modules). A request that names no new module, such as a node's lease
    heartbeat, is decoded at once, also while a background import runs, and also while
    a request that names one waits."""
    importing = threading.Lock()
    server = ControlServer(KEY, handler, decode_lock=importing)
    client = ControlClient(KEY, server.address)
    fresh = "pb3a_test_decoded_later"
    answers: list[Any] = []
    try:
        with importing:                                    # a background import runs
            assert client.call("add", timeout=2.0, a=1, b=2) == 3
            assert client.ping(2.0) is not None
            # a module that another thread is still importing, as the server sees it
            module = sys.modules[fresh] = types.ModuleType(fresh)
            module.__spec__ = importlib.machinery.ModuleSpec(fresh, None)
            module.__spec__._initializing = True
            module.Point = collections.namedtuple("Point", "x", module=fresh)
            with pytest.raises(RuntimeTimeout):
                client.call("add", timeout=0.3, a=module.Point(5), b=0)
            assert client.ping(1.0) is not None            # heartbeats are not held up
            waiting = threading.Thread(target=lambda: answers.append(
                client.call("add", timeout=5.0, a=module.Point(7), b=(1,))))
            waiting.start()
            assert client.ping(1.0) is not None
        module.__spec__._initializing = False              # (imported since)
        waiting.join(5.0)
        assert answers == [(7, 1)]                         # the waiting one, answered
        assert client.call("add", timeout=2.0, a=(1,), b=(2,)) == (1, 2)
    finally:
        client.close()
        server.close()
        sys.modules.pop(fresh, None)




def test_a_request_naming_a_module_not_imported_yet_is_imported_off_the_socket_thread(
        tmp_path, monkeypatch) -> None:
    """A request that needs an import is handed to the handler thread unread, also when
    no background import holds the lock: an import on the socket thread would hold up
    the heartbeats behind it for as long as it takes."""
    name = "pb3a_test_slow_import"
    importing = tmp_path / "importing"
    (tmp_path / f"{name}.py").write_text(
        f"import pathlib, time\npathlib.Path({str(importing)!r}).touch()\ntime.sleep(1.5)\n"
        "class Thing:\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    # the request's pickle names the class, which this process has not imported
    fake = types.ModuleType(name)
    fake.Thing = type("Thing", (), {"__module__": name})
    monkeypatch.setitem(sys.modules, name, fake)
    blob = pickle.dumps(("add", {"a": fake.Thing, "b": 0}))
    del sys.modules[name]
    server = ControlServer(KEY, handler, decode_lock=threading.Lock())
    client = ControlClient(KEY, server.address)
    sender = zmq.Context.instance().socket(zmq.DEALER)
    sender.setsockopt(zmq.LINGER, 0)
    sender.connect(server.address)
    try:
        sender.send_multipart(Sealer(KEY).seal(REQUEST, [b"\2" * 8, server.instance,
                                                         WAITS_10_S, blob]))
        eventually(importing.exists, what="the module's import under way")
        assert client.ping(0.5) is not None                # answered meanwhile
        assert sender.poll(5000)                           # the request's answer, later
    finally:
        sender.close(0)
        client.close()
        server.close()
        sys.modules.pop(name, None)


def test_a_captured_request_runs_only_at_the_server_instance_it_was_for() -> None:
    """Replayed to another server of the cluster, or to the same address after its
    server started anew, a request is refused; a client learns the new instance by
    itself and goes on."""
    ran: dict[str, list[str]] = {"a": [], "b": [], "again": []}

    def recorder(name: str) -> Any:
        return lambda op, args: ran[name].append(op)

    def send(server: ControlServer, frames: list[Any]) -> None:
        wire = zmq.Context.instance().socket(zmq.DEALER)
        wire.setsockopt(zmq.LINGER, 1000)
        wire.connect(server.address)
        wire.send_multipart(frames)
        wire.close()

    a, b = ControlServer(KEY, recorder("a")), ControlServer(KEY, recorder("b"))
    client = ControlClient(KEY, a.address)
    again = None
    try:
        assert client.call("stop") is None and ran["a"] == ["stop"]
        captured = Sealer(KEY).seal(REQUEST, [b"\1" * 8, a.instance, WAITS_10_S,
                                              pickle.dumps(("stop", {}))])
        send(a, captured)                                  # as it went on the wire
        eventually(lambda: ran["a"] == ["stop", "stop"], what="the request run")
        send(a, captured)
        send(b, captured)
        eventually(lambda: a.rejected["replay"] == 1 and b.rejected["other instance"] == 1,
                   what="the copies refused")
        port = int(a.address.rpartition(":")[2])
        a.close()
        again = ControlServer(KEY, recorder("again"), port=port)     # started anew
        send(again, captured)
        eventually(lambda: again.rejected["other instance"] == 1, what="the copy refused")
        assert client.call("stop") is None                 # the client learnt who it is
        assert ran == {"a": ["stop", "stop"], "b": [], "again": ["stop"]}
    finally:
        client.close()
        for server in (b, again):
            if server is not None:
                server.close()


def test_a_closed_socket_frees_its_port_before_close_bound_returns() -> None:
    """ZeroMQ closes a listener on its own thread, after ``close``: under load a server
    started at once on the same port found it still in use (about a third of the time
    with the busy threads below, on a plain ``close``). ``ControlServer.close`` waits."""
    stop = threading.Event()

    def busy() -> None:
        while not stop.is_set():
            pass
    hogs = [threading.Thread(target=busy, daemon=True) for _ in range(2)]
    for hog in hogs:
        hog.start()
    sock = zmq.Context.instance().socket(zmq.ROUTER)
    try:
        port = bind_advertised(sock, "127.0.0.1").rpartition(":")[2]
        for _ in range(100):
            close_bound(sock)
            sock = zmq.Context.instance().socket(zmq.ROUTER)
            sock.bind(f"tcp://127.0.0.1:{port}")
    finally:
        stop.set()
        close_bound(sock)
        for hog in hogs:
            hog.join(5.0)
    server = ControlServer(KEY, handler, port=int(port))     # and a server's close does
    server.close()
    ControlServer(KEY, handler, port=int(port)).close()


def test_a_close_a_ctrl_c_cut_short_is_finished_by_the_next() -> None:
    """A Ctrl-C as a server's close waited for its thread (a request under way) left its
    port bound, its thread and its sockets open, until the process ended: closing again
    did nothing, and a server started again there found the port in use."""
    server = ControlServer(KEY, handler)
    port = int(server.address.rpartition(":")[2])
    serving = server._worker

    class CutShort:
        def join(self, timeout: float | None = None) -> None:
            server._worker = serving
            raise KeyboardInterrupt
    server._worker = CutShort()
    with pytest.raises(KeyboardInterrupt):
        server.close()
    server.close()
    assert not serving.is_alive()
    ControlServer(KEY, handler, port=port).close()


def test_a_close_bound_that_gave_up_waiting_leaves_later_closes_unharmed(caplog) -> None:
    """A ``close_bound`` that gives up waiting (2 s, under heavy load) keeps its monitor
    until ZeroMQ has said it stopped: closed at once, ZeroMQ's reaper thread blocked for
    good sending it that, and every socket the process closed after it kept its port and
    descriptors (each later ``close_bound`` waited its 2 s: "ports were not free")."""
    context = zmq.Context.instance()
    sock = context.socket(zmq.ROUTER)
    bind_advertised(sock, "127.0.0.1")
    close_bound(sock, timeout=0.0)                   # (gives up at once)
    for _ in range(3):
        sock = context.socket(zmq.ROUTER)
        bind_advertised(sock, "127.0.0.1")
        caplog.clear()
        started = time.monotonic()
        close_bound(sock, timeout=5.0)
        assert time.monotonic() - started < 4.0, "a socket closed later is never freed"
        assert "not free" not in caplog.text


def test_a_server_on_a_port_in_use_is_refused_and_leaves_no_socket_behind() -> None:
    server = ControlServer(KEY, handler)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with pytest.raises(zmq.ZMQError, match="Address already in use"):
                ControlServer(KEY, handler, port=int(server.address.rpartition(":")[2]))
            gc.collect()                   # (an unclosed socket warns when collected)
        assert [w for w in caught if issubclass(w.category, ResourceWarning)] == []
    finally:
        server.close()


def test_a_call_submitted_to_a_socket_loop_before_it_closes_still_runs() -> None:
    """A server's answer is such a call: the answer to a request that closes the server
    (a node executor's "shutdown") was dropped when the close came before the loop's
    next turn, and its caller waited out its deadline for a request that had been done."""
    context = zmq.Context.instance()
    reader, writer = context.socket(zmq.PAIR), context.socket(zmq.PAIR)
    reader.bind("inproc://loop-closing")
    writer.connect("inproc://loop-closing")
    loop, ran = SocketLoop("pb3a-test-loop", context), threading.Event()

    def on_message(sock: zmq.Socket) -> None:     # on the loop's thread, after its calls
        sock.recv()
        loop.submit(ran.set)                      # the answer to send...
        loop.close()                              # ...and the server closing at once
    try:
        loop.register(reader, on_message)
        writer.send(b"bye")
        assert ran.wait(5.0), "the call submitted before the close never ran"
    finally:
        loop.close()
        reader.close(0)
        writer.close(0)


def test_a_server_closed_right_after_answering_still_delivers_the_answer() -> None:
    """As a node executor does on "shutdown": the handler answers and another thread
    closes the server at once. An answer still on its way when the socket closes (here
    16 MB, more than the loopback's socket buffers take in one go) must still arrive: a
    socket closed without lingering dropped it, and the caller waited out its deadline
    (on a busy executor, one small answer in eight)."""
    size = 16 * 1024 * 1024

    def answer_and_close() -> None:
        told = threading.Event()

        def shutdown(op: str, args: dict[str, Any]) -> Any:
            told.set()                             # (the executor's ``stopped``)
            return b"x" * size
        server = ControlServer(KEY, shutdown)
        closer = threading.Thread(target=lambda: (told.wait(5.0), server.close()))
        closer.start()
        client = ControlClient(KEY, server.address)
        try:
            assert len(client.call("shutdown", timeout=3.0)) == size, "answer cut short"
        finally:
            closer.join(5.0)
            client.close()
            server.close()
    for _ in range(10):
        answer_and_close()


def test_closing_a_server_twice_does_nothing_the_second_time() -> None:
    """A second ``close`` (an owner's, then a fixture's) raised ZeroMQ's error."""
    server = ControlServer(KEY, lambda op, args: op)
    server.close()
    server.close()


def test_a_client_of_a_server_that_reads_nothing_never_blocks_its_thread() -> None:
    """Requests to a server that reads nothing (frozen: a node controller SIGSTOPped,
    pinged once a second by the launcher's keepers) queue up; once ZeroMQ's queue was
    full, the client's thread blocked in its send, and from then on every call, ping
    and close raised ``zmq.Again`` (the launcher's keeper threads died of it). A
    request that cannot go now is dropped, and times out as any unanswered one."""
    context = zmq.Context.instance()
    deaf = context.socket(zmq.ROUTER)                 # binds, never reads
    deaf.setsockopt(zmq.RCVHWM, 10)
    deaf.setsockopt(zmq.LINGER, 0)
    port = deaf.bind_to_random_port("tcp://127.0.0.1")
    client = ControlClient(ClusterKey(b"k" * 32), f"tcp://127.0.0.1:{port}")
    try:
        pad = b"x" * 16384
        for _ in range(1500):                          # past every queue on the way
            with pytest.raises(RuntimeTimeout):
                client.call("ping", 0.001, pad=pad)
        assert client._loop.call(lambda: "on its thread", timeout=1.0) == "on its thread"
        assert client.ping(0.05) is None               # (it raised zmq.Again)
    finally:
        started = time.monotonic()
        client.close()
        deaf.close()
    assert time.monotonic() - started < 3.0


def test_a_name_whose_resolver_goes_silent_keeps_the_address_it_resolved_to(
        monkeypatch) -> None:
    """A robot's name server that stopped answering left ``numeric`` 2 s and then the
    name itself, which ZeroMQ resolved again in its one I/O thread at every reconnection
    of a rejoin: every socket of the launcher stalled, a healthy node was declared lost
    and no command was answered for as long as the name hung. The address it last
    resolved to is used instead; a name never resolved is given back as it was."""
    assert numeric("tcp://localhost:7100") == "tcp://127.0.0.1:7100"
    silent = threading.Event()

    def hangs(*args, **kwargs):
        silent.wait(5.0)                # (a resolver that does not answer)
        raise socket.gaierror(socket.EAI_AGAIN, "Temporary failure in name resolution")
    monkeypatch.setattr(socket, "getaddrinfo", hangs)
    try:
        started = time.monotonic()
        assert numeric("tcp://localhost:7200", timeout=0.3) == "tcp://127.0.0.1:7200"
        assert numeric("tcp://robot9.lab:7200", timeout=0.3) == "tcp://robot9.lab:7200"
        assert time.monotonic() - started < 2.0
    finally:
        silent.set()


def test_sockets_connect_to_a_name_by_its_address_resolved_once() -> None:
    """ZeroMQ resolves a host name again at every reconnection, in the one I/O thread
    all the process's sockets share: a peer's name that stopped resolving promptly
    stalled every socket, heartbeats to healthy nodes too (libzmq #2961). A name is
    resolved here, once, within a deadline, and the socket connects to the address."""
    assert numeric("tcp://localhost:7100") == "tcp://127.0.0.1:7100"
    assert numeric("tcp://10.0.0.7:7100") == "tcp://10.0.0.7:7100"
    assert numeric("tcp://[::1]:7100") == "tcp://[::1]:7100"
    unknown = "tcp://no-such-host.invalid:7100"       # (left to ZeroMQ, as before)
    assert numeric(unknown, timeout=5.0) == unknown
    server = ControlServer(ClusterKey(b"k" * 32), lambda op, args: op)
    port = server.address.rpartition(":")[2]
    client = ControlClient(ClusterKey(b"k" * 32), f"tcp://localhost:{port}")
    try:
        assert client.call("hello", 5.0) == "hello"
        assert client._dealer.getsockopt(zmq.LAST_ENDPOINT) == f"tcp://127.0.0.1:{port}".encode()
        assert client.address == f"tcp://localhost:{port}"     # (said as given)
    finally:
        client.close()
        server.close()


class _Gone(RuntimeFailure):
    """What ``when_gone`` makes in these tests."""


def test_a_client_told_of_a_gone_server_fails_its_calls_once_nothing_listens_there() -> None:
    """``when_gone``: a server that closed the connection, with nothing taking one there
    within ``GONE_S``, fails the call waiting and the next; one that comes back on the
    same port within that second, while the client's loop was too busy to read the
    reconnection before its timer (the loop runs timers first), is not taken for gone."""
    server = ControlServer(KEY, handler)
    client = ControlClient(KEY, server.address, when_gone=_Gone)
    try:
        assert client.call("add", a=1, b=1) == 2
        port, instance = int(server.address.rpartition(":")[2]), server.instance
        server.close()
        server = ControlServer(KEY, handler, port=port)         # back at once ...
        server.instance = instance          # ... the same server (a connection cut, say)
        client._loop.submit(lambda: time.sleep(1.3))            # the loop held busy
        assert client.call("add", timeout=5, a=2, b=2) == 4     # not gone
        assert not client.gone.is_set()
        server.close()
        started = time.monotonic()
        with pytest.raises(_Gone):
            client.call("block", timeout=10)
        assert time.monotonic() - started < 5
        with pytest.raises(_Gone):
            client.call("add", a=1, b=1)                         # at once
    finally:
        release.set()
        client.close()
        client.close()                                           # (again: nothing more)
        server.close()
        release.clear()


def test_a_client_told_of_a_gone_server_takes_no_other_server_for_it() -> None:
    """``when_gone``: another server started at the address of one that closed (another
    system's launcher on the same fixed port, within the second that counts it gone)
    fails the client's calls, then and for good; it was taken for the one the client had
    talked to, and a connection went on with another system as if nothing had happened."""
    server = ControlServer(KEY, handler)
    client = ControlClient(KEY, server.address, when_gone=_Gone)
    try:
        assert client.call("add", a=1, b=1) == 2
        port = int(server.address.rpartition(":")[2])
        server.close()
        server = ControlServer(KEY, handler, port=port)         # another, at once
        for _ in range(2):                                      # (the second at once)
            started = time.monotonic()
            with pytest.raises(_Gone, match="another process has listened there since"):
                client.call("add", timeout=5, a=2, b=2)
            assert time.monotonic() - started < 2
        assert client.gone.is_set()         # (and stays so, connected to the other one)
    finally:
        client.close()
        server.close()


def test_a_server_closed_as_it_notes_a_request_aside_closes_whole() -> None:
    """The socket thread notes a request run aside, then starts its thread: a close
    between the two joined a thread not started yet, which raised, and the close was
    left half done (its port held; a flaky test that closed a server with a request
    just in hand)."""
    server = ControlServer(KEY, handler, aside={"block"})
    noted = threading.Thread(target=lambda: None)       # (noted, never started)
    server._asides.add(noted)
    server.close()
    with socket.socket() as probe:                       # its port free again
        probe.bind(("127.0.0.1", int(server.address.rpartition(":")[2])))


def test_a_call_waiting_as_its_server_is_replaced_fails_then_not_at_its_deadline() -> None:
    """``when_gone``: a server that closes with a call's request in hand, and another
    started at its address within the second that counts it gone (a node controller
    killed as it started an executor, restarted at once), was told apart only by the
    client's next request: the call waiting waited out its deadline (10 s here). It
    fails as the client connects to the other one, saying so (``replaced``)."""
    server = ControlServer(KEY, handler, aside={"block"})   # (closed unanswered: see close)
    client = ControlClient(KEY, server.address, when_gone=_Gone)
    failed: list[BaseException] = []

    def waiting() -> None:
        try:
            client.call("block", timeout=10)
        except BaseException as exc:                     # (the test's to judge)
            failed.append(exc)
    call = threading.Thread(target=waiting, daemon=True)
    try:
        assert client.call("add", a=1, b=1) == 2
        port = int(server.address.rpartition(":")[2])
        call.start()
        eventually(lambda: server._asides, what="the request in the server's hands")
        server.close()
        server = ControlServer(KEY, handler, port=port)         # another, at once
        replaced = time.monotonic()
        call.join(10)
        assert time.monotonic() - replaced < 2, "the call waited out its deadline"
        assert len(failed) == 1 and isinstance(failed[0], _Gone), failed
        assert "another process has listened there since" in str(failed[0])
        assert client.replaced and client.gone.is_set()
    finally:
        release.set()
        call.join(10)
        client.close()
        server.close()
        release.clear()


def test_a_client_dropped_unclosed_is_closed_whichever_thread_collects_it() -> None:
    """A client nobody closed (a node's, a module server's, a connection's) was kept by
    its loop's thread for good, with its sockets. Once collected it is closed, also when
    the last reference goes on the loop's own thread, or on a thread that holds the
    loop's wake-up lock (as ``submit`` does): neither may wait for the other."""
    server = ControlServer(KEY, handler)
    try:
        for drop in ("on its loop", "with the lock held"):
            client = ControlClient(KEY, server.address, when_gone=_Gone)
            assert client.call("add", a=1, b=1) == 2
            loop, dealer, monitor = client._loop, client._dealer, client._monitor
            if drop == "on its loop":
                held = [client]
                del client
                loop.submit(held.clear)             # (the last reference, there)
            else:
                with loop._wake_lock:
                    # (collected here, at once, or on the loop's thread once a handler
                    # it was running lets go of it: either way, while the lock is held)
                    del client
                    eventually(lambda closing=loop: closing._closing,
                               what=f"the client dropped {drop}")
            loop._thread.join(5.0)
            assert not loop._thread.is_alive(), f"the loop of a client dropped {drop} goes on"
            assert dealer.closed and monitor.closed, drop
    finally:
        server.close()


def _refused_on_new_connections(address: str, wrong: ClusterKey, count: int) -> None:
    """``count`` requests with the ``wrong`` key, each on a connection of its own, each
    told why it was refused."""
    for _ in range(count):
        client = ControlClient(wrong, address)
        try:
            with pytest.raises(RuntimeFailure, match="runs with another cluster key"):
                client.call("add", timeout=5.0, a=1, b=2)
        finally:
            client.close()


def test_wrong_key_requests_on_new_connections_are_logged_a_bounded_number_of_times(
        caplog, monkeypatch) -> None:
    """Refusals were logged at most once a second per connection: a client that connected
    anew for each request had each logged (2000 warnings in 0.9 s). One is logged, and
    the rest counted in a summary line; each client is still told why at once."""
    monkeypatch.setattr(control, "_REFUSALS_COUNTED_S", 0.5, raising=False)
    caplog.set_level(logging.WARNING, logger="pb3a.control")
    wrong = ClusterKey(os.urandom(32))
    started = time.monotonic()
    with ControlServer(KEY, handler) as server:
        _refused_on_new_connections(server.address, wrong, 40)
        took = time.monotonic() - started
        logged = [r.getMessage() for r in caplog.records
                  if "refused a request from 127.0.0.1" in r.getMessage()]
        assert len(logged) == 1, f"{len(logged)} lines logged"
        counted = re.compile(r"refused (\d+) more requests? \(another cluster key\)")
        def summed() -> int:
            return sum(int(m.group(1)) for r in caplog.records
                       if (m := counted.search(r.getMessage())))
        eventually(lambda: summed() == 39, what="the refusals not logged counted")
    lines = [r.getMessage() for r in caplog.records if r.name == "pb3a.control"]
    assert len(lines) <= 2 + took / 0.5, lines


def test_refusals_counted_for_a_summary_are_told_when_the_server_closes(caplog) -> None:
    """A server closed before its summary was due lost the count of what it refused."""
    caplog.set_level(logging.WARNING, logger="pb3a.control")
    wrong = ClusterKey(os.urandom(32))
    with ControlServer(KEY, handler) as server:
        _refused_on_new_connections(server.address, wrong, 3)
    said = [r.getMessage() for r in caplog.records if r.name == "pb3a.control"]
    assert len(said) == 2, said
    assert re.search(r"refused 2 more requests \(another cluster key\) in the last \d+ s",
                     said[1]), said
