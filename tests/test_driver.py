"""``Driver`` on its own, against devices served in this process (``serve_device``):
what its errors say, what its state takes, and how it lets a device go."""

from __future__ import annotations

import contextlib
import socketserver
import threading
import time
from collections.abc import Iterator

import pytest
from conftest import eventually

from pb3a import Driver, Input, Output, RuntimeFailure, RuntimeTimeout, System, serve_device
from pb3a.testing import ModuleHarness
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient, ControlServer

pytestmark = pytest.mark.timeout(60)


class Reader(Driver):
    """Asks its device for a reading at each step; says why a request failed."""

    period = 0.05
    timeout = 0.3
    last_error = ""

    def step(self) -> None:
        try:
            self.request("read")
        except (RuntimeFailure, RuntimeTimeout) as exc:
            self.last_error = str(exc)


@pytest.fixture
def devices() -> Iterator[tuple[list[tuple[str, str]], ControlServer, ControlServer]]:
    """Two devices, "a" and "b": what each was asked, in order ((device, op)); op
    "fail" raises."""
    asked: list[tuple[str, str]] = []

    def served(name: str) -> ControlServer:
        def handler(op: str, args: dict) -> str:
            asked.append((name, op))
            if op == "fail":
                raise ValueError("sensor unplugged")
            return name
        return serve_device(handler)
    with served("a") as a, served("b") as b:
        yield asked, a, b


def test_an_error_names_the_driver_and_the_device_s_address_once(devices) -> None:
    """"MotorDriver at tcp://...:7899: tcp://...:7899 did not answer ...": the address
    came twice, the driver's prefix adding what the request's error said already."""
    _, a, _ = devices
    harness = ModuleHarness(Reader, state={"resource": a.address})
    with pytest.raises(RuntimeFailure) as failed:
        harness.module.request("fail")
    said = str(failed.value)
    assert said.startswith("Reader: ") and said.count(a.address) == 1, said
    assert "sensor unplugged" in said
    silent = serve_device(lambda op, args: None)
    silent.close()                          # nothing listens there now
    harness.module.set_state({"resource": silent.address})
    harness.step()
    said = harness.module.last_error
    assert said.startswith(f"Reader: {silent.address} did not answer 'read' within 0.3 s")
    assert said.count(silent.address) == 1, said
    harness.close()


@pytest.mark.parametrize("timeout", [0, -1.0, float("nan"), float("inf"), 1e8, True, "2"])
def test_a_timeout_that_is_not_a_positive_finite_number_is_refused_by_name(
        devices, timeout) -> None:
    """0, -1 and NaN were taken, and every request then failed, blaming the device ("did
    not answer 'read' within nan s"); inf raised OverflowError at every request."""
    _, a, _ = devices
    harness = ModuleHarness(Reader, state={"resource": a.address})
    with pytest.raises(ValueError, match=r"Reader's timeout must be a positive number of "
                                         r"seconds, at most 1e\+07 .*got "):
        harness.module.set_state({"timeout": timeout, "resource": ""})
    assert (harness.state["timeout"], harness.state["resource"]) == (0.3, a.address)
    harness.module.set_state({"timeout": 2})                 # a whole number is one
    assert harness.module.request("read") == "a"
    # (no set_state saw it: one would refuse it now, judging the driver's whole state)
    impatient = type("Impatient", (Reader,), {"timeout": timeout, "resource": a.address})
    harness = ModuleHarness(impatient)
    harness.step()
    assert "Impatient's timeout must be a positive number" in harness.module.last_error


class Limited(Reader):
    """A user's hook that relates two of its fields, read by key: it is given the
    module's whole state."""

    most = 5.0
    speed = 1.0

    @classmethod
    def state_problems(cls, state: dict) -> list[str]:
        problems = super().state_problems(state)
        if state["speed"] > state["most"]:
            problems.append(f"Limited's speed must be at most most ({state['most']!r})")
        return problems


def test_a_driver_s_own_check_before_a_request_asks_its_base_s_rules_only(devices) -> None:
    """Before each request a driver checks its timeout and protocol (a class's own,
    which no ``set_state`` saw): it asked the subclass's whole hook with those two
    fields alone, and a user's hook that read another field by key (as it may: it is
    given the whole state) failed every request with KeyError."""
    _, a, _ = devices
    harness = ModuleHarness(Limited, state={"resource": a.address})
    assert harness.module.request("read") == "a"
    with pytest.raises(ValueError, match=r"Limited's speed must be at most most \(5\.0\)"):
        harness.module.set_state({"speed": 9.0})
    harness.close()


class Motor(Driver):
    """Event-driven: sets its motor's speed as each command comes; stops it when let go,
    through ``self.request`` (or, with ``by_client``, the connection it is given)."""

    speed = Input(float)
    timeout = 0.3
    by_client = False

    def on_input(self, port) -> None:
        self.request("set", v=port.read())

    def release(self, client) -> None:
        if self.by_client:
            client.call("stop", 10.0)           # (longer than the driver's timeout)
        else:
            self.request("stop")


def test_a_re_pointed_driver_lets_go_of_its_old_device_at_once(devices) -> None:
    """``release`` ran only at the driver's next request: an event-driven driver
    re-pointed left its old motor running until the next command came. And a
    ``self.request`` in ``release`` went to the new device (the old connection was
    dropped before it ran), so the new motor was stopped and the old one ran on."""
    asked, a, b = devices
    harness = ModuleHarness(Motor, state={"resource": a.address})
    harness.feed("speed", 1.0)
    harness.module.set_state({"resource": b.address})
    assert asked == [("a", "set"), ("a", "stop")]       # then and there, no command since
    harness.module.set_state({"timeout": 0.5})          # (not a re-point: nothing let go)
    harness.feed("speed", 2.0)
    assert asked[2:] == [("b", "set")]
    harness.close()                                     # a stop, a move: let go too
    assert asked[3:] == [("b", "stop")]
    assert "_pb3a_device" not in vars(harness.module)


def test_a_release_waits_at_most_the_driver_s_timeout(devices) -> None:
    """A release's call asking for longer than the driver's ``timeout`` (10 s here, of
    a device that does not answer) held the driver's stop, move or re-point as long."""
    _, a, _ = devices
    silent = serve_device(lambda op, args: None)
    silent.close()                          # nothing listens there now
    harness = ModuleHarness(Motor, state={"resource": silent.address, "by_client": True})
    with pytest.raises(RuntimeTimeout):
        harness.feed("speed", 1.0)          # (connected: the device is one to let go)
    started = time.monotonic()
    harness.close()
    assert time.monotonic() - started < 5.0
    harness = ModuleHarness(Motor, state={"resource": silent.address})
    with pytest.raises(RuntimeTimeout):
        harness.feed("speed", 1.0)
    started = time.monotonic()
    harness.module.set_state({"resource": a.address})      # (self.request: its timeout)
    assert time.monotonic() - started < 5.0
    harness.close()


class LineDevice:
    """A program that knows nothing of PB3A: text lines over plain TCP, as a legacy motor
    controller speaks. "GET pos" answers "pos X"; "SET vel V" answers "ok"; "STEP D"
    moves by D and answers "ok". While ``free`` is clear it holds its answers."""

    def __init__(self) -> None:
        self.heard: list[str] = []
        self.position = 0.0
        self.connections = 0
        self.received = 0
        self.free = threading.Event()
        self.free.set()
        self._server = socketserver.ThreadingTCPServer(("127.0.0.1", 0), self._handler())
        self._server.daemon_threads = True
        self.address = f"tcp://127.0.0.1:{self._server.server_address[1]}"
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)
        self._thread.start()

    def _handler(self) -> type[socketserver.StreamRequestHandler]:
        device = self

        class Handler(socketserver.StreamRequestHandler):
            def handle(self) -> None:
                device.connections += 1
                for raw in self.rfile:
                    line = raw.decode(errors="replace").strip()
                    device.received += 1
                    device.free.wait(10.0)
                    device.heard.append(line)
                    if line == "GET pos":
                        answer = f"pos {device.position}"
                    elif line.startswith("STEP "):
                        device.position += float(line.split()[1])
                        answer = "ok"
                    else:
                        answer = "ok"
                    with contextlib.suppress(OSError):
                        self.wfile.write(f"{answer}\r\n".encode())
        return Handler

    def close(self) -> None:
        self.free.set()
        self._server.shutdown()
        self._server.server_close()


class LineMotor(Driver):
    """A driver of a line-speaking motor: reads its position at each step, sets its speed
    as each command comes, stops it when let go."""

    protocol = "lines"
    period = 0.02
    timeout = 0.5
    speed = Input(float)
    position = Output(float)
    last_error = ""

    def step(self) -> None:
        try:
            self.position.write(float(self.ask("GET pos").split()[1]))
        except (RuntimeFailure, RuntimeTimeout) as exc:
            self.last_error = str(exc)

    def on_input(self, port) -> None:
        self.tell(f"SET vel {port.read()}")

    def release(self, client) -> None:
        self.tell("SET vel 0")


@pytest.fixture
def line_devices() -> Iterator[tuple[LineDevice, LineDevice]]:
    a, b = LineDevice(), LineDevice()
    yield a, b
    a.close()
    b.close()


def test_a_driver_speaks_lines_to_a_program_that_knows_nothing_of_pb3a(line_devices) -> None:
    """A driver reached only programs served with ``serve_device`` (PB3A's own, sealed
    requests): a legacy program on a plain TCP socket, which is what the spec calls a
    driver's resource port, needed an adapter process written for it. A line-speaking
    device is asked and told in lines, re-pointed (the old one told to stop), and a
    request of the other kind is refused, naming what to call."""
    a, b = line_devices
    a.position = 2.5
    harness = ModuleHarness(LineMotor, state={"resource": a.address})
    harness.step()
    assert harness.module.last_error == ""
    assert harness.last("position") == 2.5
    harness.feed("speed", 0.75)
    eventually(lambda: a.heard[-1:] == ["SET vel 0.75"], what="the speed told")
    harness.module.set_state({"resource": b.address})
    eventually(lambda: a.heard[-1:] == ["SET vel 0"], what="the old motor told to stop")
    b.position = -1.0
    harness.step()
    assert harness.last("position") == -1.0
    with pytest.raises(RuntimeFailure, match="LineMotor's device speaks 'lines', so "
                                             r"request\(\) cannot reach it: use ask\(\)"):
        harness.module.request("read")
    harness.close()
    eventually(lambda: b.heard[-1:] == ["SET vel 0"], what="the motor let go at the stop")


def test_a_line_request_that_times_out_is_not_taken_for_the_next_s_answer(
        line_devices) -> None:
    """The answer to a request given up comes late: read as the answer to the next
    request, every reading after it would be one behind. The connection is made anew
    after a request that failed, and the error says the device may still carry it out."""
    a, _ = line_devices
    harness = ModuleHarness(LineMotor, state={"resource": a.address})
    harness.step()
    a.free.clear()                          # the device holds its answers
    started = time.monotonic()
    harness.step()
    assert time.monotonic() - started < 2.0
    assert harness.module.last_error.startswith(f"LineMotor at {a.address}: no answer to "
                                                "'GET pos' within 0.5 s; it was sent, so "
                                                "the device may carry it out still")
    a.position = 7.0
    a.free.set()                            # the late answer, "pos 0.0", comes now
    harness.module.last_error = ""
    harness.step()
    assert harness.module.last_error == ""
    assert harness.last("position") == 7.0
    assert a.connections == 2
    harness.close()


def test_a_line_device_nothing_listens_for_is_named_at_once() -> None:
    device = LineDevice()
    device.close()                          # nothing listens there now
    harness = ModuleHarness(LineMotor, state={"resource": device.address})
    started = time.monotonic()
    harness.step()
    assert time.monotonic() - started < 1.0
    port = device.address.rpartition(":")[2]
    assert harness.module.last_error == (
        f"LineMotor at {device.address}: nothing listens on port {port} at 127.0.0.1 (the "
        "connection was refused): start the device's program, or fix the port")
    harness.close()


def test_a_pb3a_driver_pointed_at_a_line_program_is_told_to_speak_lines(line_devices) -> None:
    """A driver left at ``protocol = "pb3a"`` and pointed at a legacy program's port
    said "nothing listens there ... check that the process runs", though it ran and
    listened. What took the connection never greeted in ZeroMQ's protocol, and the
    error now says so, and what to set; a PB3A device that is slow is still told
    apart (it greets: the request "may have begun")."""
    a, _ = line_devices
    # (connected a second or more and never greeted: a slow link greets within it)
    harness = ModuleHarness(Reader, state={"resource": a.address, "timeout": 1.5})
    harness.step()
    assert harness.module.last_error == (
        f"Reader: {a.address} did not answer 'read' within 1.5 s: something accepts "
        "connections there but does not speak PB3A's protocol (it sent no ZeroMQ greeting): "
        "another program's port, or a PB3A process that is stopped; a device that reads "
        "lines of text takes protocol = 'lines' in its driver, and ask() and tell() in "
        "place of request()")
    harness.close()
    slow = serve_device(lambda op, args: time.sleep(1.0))
    harness = ModuleHarness(Reader, state={"resource": slow.address})
    harness.step()
    assert "may have begun it" in harness.module.last_error
    assert "protocol = 'lines'" not in harness.module.last_error
    harness.close()
    slow.close()


class Stepper(Driver):
    """Asks its device to move by one step at each of its steps."""

    period = 0.05
    timeout = 10.0

    def step(self) -> None:
        self.request("move", by=1)


@pytest.mark.parametrize("change", ["migrate", "remove"])
def test_a_request_its_driver_stops_waiting_for_is_not_carried_out(change: str) -> None:
    """A driver's move (or stop) cancels the request it waits for; the device, busy with
    another's request, began it once free all the same, so a relative move asked again
    from the destination was made twice. The client withdraws what it gives up on, and
    a device drops a withdrawn request it has not begun."""
    began, go, ran = threading.Event(), threading.Event(), []

    def device(op: str, args: dict) -> None:
        if op == "home":
            began.set()
            go.wait(20.0)
        ran.append(op)

    server = serve_device(device)
    other = ControlClient(ClusterKey.load(), server.address)
    homing = threading.Thread(target=other.call, args=("home", 20.0), daemon=True)
    homing.start()
    try:
        assert began.wait(5.0)
        system = System("withdrawn").node("a").node("b").add(
            "stepper", Stepper, node="a", state={"resource": server.address})
        with system.launch(timeout=20) as run:
            eventually(lambda: server._work.qsize() == 1, what="the move queued at the device")
            if change == "migrate":
                run.migrate("stepper", to="b", timeout=10.0)
            run.remove("stepper", timeout=10.0)        # (its next move withdrawn too)
            go.set()
            assert other.call("after", 10.0) is None    # (queued behind the move, if kept)
    finally:
        go.set()
        homing.join(10.0)
        other.close()
        server.close()
    assert ran[:2] == ["home", "after"], ran


def test_a_driver_waiting_for_a_line_device_holds_up_no_read_or_remove(line_devices) -> None:
    """A line device that does not answer (8 s of the driver's timeout) must not hold up
    a read of the driver's state, nor its removal: the wait gives way as a PB3A
    request's does, and the stop tells the device to stop on a connection of its own
    (the one the request waited on is given up)."""
    a, _ = line_devices
    system = System("line-driver").add("motor", LineMotor, state={"resource": a.address,
                                                                  "timeout": 8.0})
    with system.launch(timeout=20) as run:
        eventually(lambda: run.stats().modules["motor"].steps > 2, what="steps")
        a.free.clear()
        held = a.received
        eventually(lambda: a.received > held, what="a request held at the device")
        started = time.monotonic()
        assert run.state("motor")["timeout"] == 8.0
        run.remove("motor", timeout=5.0)
        assert time.monotonic() - started < 3.0
    a.free.set()
    eventually(lambda: "SET vel 0" in a.heard, what="the motor told to stop as let go")


def test_a_protocol_the_driver_does_not_speak_is_refused_by_name() -> None:
    harness = ModuleHarness(LineMotor)
    with pytest.raises(ValueError, match=r"LineMotor's protocol is what its device speaks, "
                                         r"one of 'pb3a', 'lines', got 'line'"):
        harness.module.set_state({"protocol": "line"})
    assert harness.state["protocol"] == "lines"
    problems = System("typo").add("m", LineMotor, state={"protocol": "text"}).check()
    assert any("protocol is what its device speaks" in problem for problem in problems)


def test_a_driver_re_pointed_away_from_a_device_that_hangs_is_re_pointed_at_once() -> None:
    """Re-pointing is what one does to a driver whose device hangs, and the edit waited
    for the request in progress to end (its timeout, 8 s here: a set_state with less
    failed, nothing done). Setting ``resource`` ends that request; the driver asks the
    new device from its next step."""
    hung = threading.Event()
    stuck = serve_device(lambda op, args: hung.wait(20.0))
    fine = serve_device(lambda op, args: "fine")
    try:
        system = System("re-pointed").add("reader", Reader, state={
            "resource": stuck.address, "timeout": 8.0})
        with system.launch(timeout=20) as run:
            eventually(lambda: run.stats().modules["reader"].calling_s > 0.3,
                       what="a request waiting for the device that hangs")
            started = time.monotonic()
            run.set_state("reader", resource=fine.address, timeout=3.0)
            assert time.monotonic() - started < 2.0
            said = eventually(lambda: run.state("reader")["last_error"], what="why")
            assert "cancelled: its resource is set anew" in said, said
            run.set_state("reader", last_error="")
            eventually(lambda: run.stats().modules["reader"].steps > 3, what="steps")
            run.wait(0.3)
            assert run.state("reader")["last_error"] == ""
    finally:
        hung.set()
        stuck.close()
        fine.close()
