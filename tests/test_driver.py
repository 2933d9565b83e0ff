"""``Driver`` on its own, against devices served in this process (``serve_device``):
what its errors say, what its state takes, and how it lets a device go."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

from pb3a import Driver, Input, RuntimeFailure, RuntimeTimeout, serve_device
from pb3a.testing import ModuleHarness
from pb3a.transport.control import ControlServer

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
    impatient = type("Impatient", (Reader,), {"timeout": timeout})    # (no set_state saw it)
    harness = ModuleHarness(impatient, state={"resource": a.address})
    harness.step()
    assert "Impatient's timeout must be a positive number" in harness.module.last_error


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
