"""``Driver``: a module that talks to a program outside PB3A (a robot, a simulator, a
legacy program) through that program's resource port.

The port's address is the state attribute ``resource``, so a running driver is
re-pointed at another device with ``run.set_state(name, resource=ADDR)`` (or by an
agent): its next request goes to the new device, after ``release`` let go of the
old one. Requests are authenticated with the cluster key (the program serves them
with a ``ControlServer``), have a deadline, and fail with an error naming the
device; a driver whose device does not answer keeps running and says so. A request
in progress does not hold up a move, swap or stop of the driver: they cancel it
(``RuntimeCancelled``, "cancelled: ...") rather than wait out its deadline; a read of
its state runs meanwhile (an edit waits for the request's end).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any

import zmq

from pb3a.errors import MOST_SECONDS, RuntimeCancelled, RuntimeFailure, RuntimeTimeout
from pb3a.model.displays import finite
from pb3a.model.module import Module, reflective
from pb3a.transport.addresses import tcp_address_problems
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient, ControlServer


class Driver(Module):
    """A module that talks to a device (a robot, a simulator, a legacy program): subclass
    it, declare ports, and call ``request(op, **args)`` from ``step`` or ``on_input``.

        class PlantDriver(Driver):
            u = Input(float)
            y = Output(float)
            period = 0.01
            resource = "tcp://127.0.0.1:7400"

            def step(self) -> None:
                self.y.write(self.request("read"))

            def on_input(self, port) -> None:
                self.request("apply", u=port.read())

    The device serves the requests with ``pb3a.serve_device(handler, host, port)``,
    which calls ``handler(op, args)`` and sends back what it returns (what it raises
    fails the request, naming the device); its ``address`` is the driver's
    ``resource``. ``timeout`` is each request's deadline, a positive number of seconds
    (``RuntimeTimeout`` names the device).
    """

    resource = ""            # the device's resource port, e.g. "tcp://10.0.0.7:7400"
    timeout = 1.0            # seconds a request may take

    def request(self, op: str, **args: Any) -> Any:
        """Ask the device to do ``op``; its answer, or ``RuntimeFailure``/``RuntimeTimeout``
        naming the device."""
        wrong = state_problems(type(self), {"timeout": self.timeout})
        if wrong:                   # (a class default, not set through set_state)
            raise RuntimeFailure(wrong[0])
        client = self._client()
        giving_way = self.__dict__.get("_pb3a_giving_way")     # (set by its worker)
        try:
            if giving_way is None:
                return client.call(op, self.timeout, **args)
            with giving_way(f"request {op!r}", takes_edits=False) as wait:
                if wait.cancelled:      # (the runtime stops the driver: nothing is sent)
                    raise RuntimeCancelled(f"request {op!r} cancelled: {wait.cancelled}")
                return client.request(op, args, self.timeout, wait=wait)
        except (RuntimeFailure, RuntimeTimeout) as exc:
            raise type(exc)(self._blamed(str(exc), self.resource)) from None

    @reflective                 # (it takes the fields Module's does: they are checked)
    def set_state(self, state: dict[str, Any]) -> None:
        """Set state; a ``resource`` or a ``timeout`` the driver cannot go by is refused
        (``state_problems``), naming it, and nothing is set."""
        wrong = state_problems(type(self), state)
        if wrong:
            raise ValueError("; ".join(wrong))
        super().set_state(state)

    def release(self, client: ControlClient) -> None:
        """Called with the old device's connection before the driver is re-pointed or
        stopped: override to leave the device safe (stop a robot, say)."""

    def _blamed(self, said: str, address: str) -> str:
        """``said`` of a request to the device at ``address``, after the driver's name,
        and the address where ``said`` does not name it already ("MotorDriver at
        tcp://...: tcp://... did not answer" named it twice)."""
        return f"{type(self).__name__}{'' if address in said else f' at {address}'}: {said}"

    def teardown(self) -> None:
        self._disconnect()

    def _client(self) -> ControlClient:
        if not self.resource:
            raise RuntimeFailure(f"{type(self).__name__} has no resource port: set its "
                                 "'resource' state to the device's address")
        current = self.__dict__.get("_pb3a_device")
        if current is not None and current[0] == self.resource:
            return current[1]
        self._disconnect()
        wrong = tcp_address_problems(self.resource, f"{type(self).__name__}'s resource")
        if wrong:                   # (a class default, not set through set_state)
            raise RuntimeFailure(wrong[0])
        try:
            client = ControlClient(ClusterKey.load(), self.resource)
        except zmq.ZMQError as exc:     # (a request's failure, as any: a driver counts it)
            raise RuntimeFailure(f"{type(self).__name__} cannot connect to "
                                 f"{self.resource}: {exc}") from None
        self.__dict__["_pb3a_device"] = (self.resource, client)
        return client

    def _disconnect(self) -> None:
        current = self.__dict__.pop("_pb3a_device", None)
        if current is not None:
            with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
                self.release(current[1])
            current[1].close()


def state_problems(cls: type[Driver], state: dict[str, Any]) -> list[str]:
    """What of ``state``, given to a driver of class ``cls``, it refuses, each naming the
    field and what it takes: a ``resource`` that is not an address to connect to
    (``tcp://HOST:PORT``, or "" for none: it was kept, and every request failed with
    ZeroMQ's "Invalid argument"), a ``timeout`` that is not a positive, finite number of
    seconds up to ``MOST_SECONDS`` (0, -1 or NaN failed every request, blaming the
    device; inf overflowed the clock at each)."""
    problems = []
    if state.get("resource", "") != "":
        problems += tcp_address_problems(state["resource"], f"{cls.__name__}'s resource")
    timeout = state.get("timeout", 1.0)
    if not (finite(timeout) and 0 < timeout <= MOST_SECONDS):
        problems.append(f"{cls.__name__}'s timeout must be a positive number of seconds, at "
                        f"most {MOST_SECONDS:g} (each request's deadline), got {timeout!r}")
    return problems


def serve_device(handler: Callable[[str, dict[str, Any]], Any], host: str = "127.0.0.1",
                 port: int = 0) -> ControlServer:
    """Serve a device's side of its ``Driver``: ``handler(op, args)`` answers each request,
    one at a time, in order; what it raises fails the driver's request with its message.
    Requests are authenticated with this machine's cluster key (``pb3a key``), as the
    system's own. ``address`` (``tcp://HOST:PORT``; port 0: a free one) is what the
    driver's ``resource`` is set to; ``close()``, or leaving a ``with`` block, stops it.

        with pb3a.serve_device(lambda op, args: plant.call(op, **args), port=7400):
            ...                                 # the device runs; drivers reach it
    """
    return ControlServer(ClusterKey.load(), handler, host, port, name="pb3a-device")
