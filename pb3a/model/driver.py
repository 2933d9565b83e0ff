"""``Driver``: a module that talks to a program outside PB3A (a robot, a simulator, a
legacy program) through that program's resource port.

The port's address is the state attribute ``resource``, so a running driver is
re-pointed at another device with ``run.set_state(name, resource=ADDR)`` (or by an
agent): ``release`` lets go of the old one then and there, and the next request goes
to the new device. Requests are authenticated with the cluster key (the program serves them
with a ``ControlServer``), have a deadline, and fail with an error naming the
device; a driver whose device does not answer keeps running and says so. A request
in progress does not hold up a move, swap or stop of the driver: they cancel it
(``RuntimeCancelled``, "cancelled: ...") rather than wait out its deadline; a read of
its state runs meanwhile (an edit waits for the request's end).

A request is carried out at most once, and one whose call failed may not have been:
the device drops a request it has not begun within the driver's ``timeout`` of its
coming (its driver gave up on it, and may ask again), but one it had begun runs on.
So a request that timed out or was cancelled once sent may still be carried out, and
its error says so: look at the device before asking again what must not be done twice
(a relative move).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any

import zmq

from pb3a.errors import MOST_SECONDS, RuntimeCancelled, RuntimeFailure, RuntimeTimeout
from pb3a.model.displays import finite
from pb3a.model.module import Module, reflective
from pb3a.transport.addresses import RESOLVE_S, tcp_address_problems, unknown_host
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import DEFAULT_TIMEOUT, ControlClient, ControlServer, Expired
from pb3a.transport.lines import LineClient

# What becomes of a request sent, when its call failed without the device's answer
_MAY_STILL_RUN = ("it was sent, so the device may have begun it and carry it out still (one "
                  "it has not begun it drops): look before asking again")
_LINE_MAY_STILL_RUN = ("it was sent, so the device may carry it out still; the connection "
                       "is made anew at the next request: look before asking again")
_NOT_PB3A = ("a device that reads lines of text takes protocol = 'lines' in its driver, "
             "and ask() and tell() in place of request()")
PROTOCOLS = ("pb3a", "lines")


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
    (``RuntimeTimeout`` names the device); the device drops a request it has not begun
    that long after it came.

    ``release`` runs as the driver lets go of a device: as ``set_state`` sets a new
    ``resource``, and at its stop, move or swap. Override it to leave the device safe:

        def release(self, client) -> None:
            self.request("set_vel", v=0.0)      # to the device let go of

    Its requests go to that device, each waiting at most ``timeout``.

    A program that knows nothing of PB3A (a legacy controller, an instrument) is reached
    with ``protocol = "lines"``: ``ask(line)`` sends a line of text over a plain TCP
    connection and returns the line the program answers; ``tell(line)`` sends one and
    waits for none. They give way, time out and name the device as ``request`` does.

        class MotorDriver(Driver):
            protocol = "lines"
            resource = "tcp://10.0.0.9:7611"

            def step(self) -> None:
                self.position.write(float(self.ask("GET pos").split()[1]))
    """

    resource = ""            # the device's resource port, e.g. "tcp://10.0.0.7:7400"
    timeout = 1.0            # seconds a request may take
    protocol = "pb3a"        # what the device speaks: "pb3a" (serve_device) or "lines"
    # an edit of these ends a request in progress rather than wait for it (the runtime's)
    _pb3a_edits_end_waits = ("resource", "protocol")

    def request(self, op: str, **args: Any) -> Any:
        """Ask the device to do ``op``; its answer, or ``RuntimeFailure``/``RuntimeTimeout``
        naming the device, and saying whether it may still carry ``op`` out."""
        self._check_own("pb3a", "request()")
        address, client = self._device()
        giving_way = self.__dict__.get("_pb3a_giving_way")     # (set by its worker)
        try:
            if giving_way is None:
                return client.call(op, self.timeout, **args)
            with giving_way(f"request {op!r}", takes_edits=False) as wait:
                if wait.cancelled:      # (the runtime stops the driver: nothing is sent)
                    raise RuntimeCancelled(f"request {op!r} cancelled: {wait.cancelled}; "
                                           "it was not sent")
                try:
                    return client.request(op, args, self.timeout, wait=wait)
                except RuntimeCancelled as exc:
                    raise RuntimeCancelled(f"{exc}; {_MAY_STILL_RUN}") from None
        except Expired as exc:
            raise Expired(self._blamed(str(exc), address)) from None
        except RuntimeTimeout as exc:
            # (a legacy program's port was "nothing listens there", though it did)
            then = _NOT_PB3A if client.ungreeted else _MAY_STILL_RUN
            raise RuntimeTimeout(self._blamed(f"{exc}; {then}", address)) from None
        except RuntimeFailure as exc:
            raise type(exc)(self._blamed(str(exc), address)) from None

    def ask(self, line: str) -> str:
        """Send ``line`` to a device that speaks text lines (``protocol = "lines"``): the
        line it answers, without its line end. Errors as ``request``'s; the connection is
        made anew after one (a late answer would be read as the next request's)."""
        return self._exchange(line, answer=True)

    def tell(self, line: str) -> None:
        """Send ``line`` to a device that speaks text lines, waiting for no answer."""
        self._exchange(line, answer=False)

    def _exchange(self, line: str, answer: bool) -> Any:
        self._check_own("lines", "ask() and tell()")
        releasing = self.__dict__.get("_pb3a_releasing")
        address = releasing[0] if releasing is not None else self.resource
        giving_way = self.__dict__.get("_pb3a_giving_way")     # (set by its worker)
        what = f"{'ask' if answer else 'tell'} {line!r}"
        try:
            if giving_way is None:
                return self._lines(None).ask(line, self.timeout, None, answer)
            with giving_way(what, takes_edits=False) as wait:
                if wait.cancelled:      # (the runtime stops the driver: nothing is sent)
                    raise RuntimeCancelled(f"{what} cancelled: {wait.cancelled}; it was "
                                           "not sent")
                client = self._lines(wait)
                try:
                    return client.ask(line, self.timeout, wait, answer)
                except RuntimeCancelled as exc:
                    raise RuntimeCancelled(f"{exc}; {_LINE_MAY_STILL_RUN}") from None
        except RuntimeTimeout as exc:
            raise RuntimeTimeout(self._blamed(f"{exc}; {_LINE_MAY_STILL_RUN}", address)) \
                from None
        except RuntimeFailure as exc:
            raise type(exc)(self._blamed(str(exc), address)) from None

    def _check_own(self, protocol: str, calls: str) -> None:
        """Refuse a call of the other protocol's, and a class's own timeout or protocol
        the driver cannot go by (one not set through ``set_state``)."""
        # (Driver's own rules: a subclass's hook judges a whole state, not these two)
        wrong = _device_problems(type(self).__name__, {"timeout": self.timeout,
                                                       "protocol": self.protocol})
        if wrong:
            raise RuntimeFailure(wrong[0])
        if self.protocol != protocol:
            raise RuntimeFailure(f"{type(self).__name__}'s device speaks {self.protocol!r}, "
                                 f"so {calls} cannot reach it: "
                                 + ("use ask() and tell(), or set protocol = 'pb3a'"
                                    if self.protocol == "lines" else
                                    "use request(), or set protocol = 'lines'"))

    @classmethod
    def state_problems(cls, state: dict[str, Any]) -> list[str]:
        """What of ``state`` the driver refuses, each naming the field and what it takes:
        a ``resource`` that is not an address to connect to (``tcp://HOST:PORT``, or ""
        for none: it was kept, and every request failed with ZeroMQ's "Invalid
        argument"), a ``protocol`` it does not speak, a ``timeout`` that is not a positive,
        finite number of seconds up to ``MOST_SECONDS`` (0, -1 or NaN failed every
        request, blaming the device; inf overflowed the clock at each)."""
        return super().state_problems(state) + _device_problems(cls.__name__, state)

    @reflective                 # (it takes the fields Module's does: they are checked)
    def set_state(self, state: dict[str, Any]) -> None:
        """Set state; a ``resource``, ``protocol`` or ``timeout`` the driver cannot go by is
        refused (``state_problems``, asked by ``Module.set_state``), naming it, and nothing
        is set. A new ``resource`` lets go of the old device now (``release``): it waited
        for the driver's next request, and an event-driven driver re-pointed left its motor
        running until the next input."""
        current = self.__dict__.get("_pb3a_device")
        super().set_state(state)
        if current is not None and not self._speaking(current):
            self._disconnect()

    def release(self, client: Any) -> None:
        """Called as the driver lets go of a device: re-pointed (as ``set_state`` sets a
        new ``resource``), stopped, moved or swapped (``teardown``). Override to leave the
        device safe (stop a robot, say): ``self.request(op, **args)`` here, and
        ``client.call(op, timeout, **args)`` (a line device's: ``self.tell(line)``,
        ``client.ask(line)``), go to that device, and each waits at most
        the driver's ``timeout``; a request that fails or times out is let be (the driver
        lets go all the same)."""

    def _blamed(self, said: str, address: str) -> str:
        """``said`` of a request to the device at ``address``, after the driver's name,
        and the address where ``said`` does not name it already ("MotorDriver at
        tcp://...: tcp://... did not answer" named it twice)."""
        return f"{type(self).__name__}{'' if address in said else f' at {address}'}: {said}"

    def teardown(self) -> None:
        self._disconnect()

    def _device(self) -> tuple[str, ControlClient]:
        """The address and connection a request goes to: the device being let go of,
        inside ``release`` (its requests went to the new device, the old one running
        on), else the ``resource`` (connected to first, the old one let go of)."""
        releasing = self.__dict__.get("_pb3a_releasing")
        if releasing is not None:
            return releasing
        if not self.resource:
            raise RuntimeFailure(f"{type(self).__name__} has no resource port: set its "
                                 "'resource' state to the device's address")
        current = self.__dict__.get("_pb3a_device")
        if current is not None and self._speaking(current):
            return current
        self._disconnect()          # (a resource set otherwise than through set_state)
        self._check_resource()
        unknown = unknown_host(self.resource, RESOLVE_S)
        if unknown:                 # (each request said only "did not answer", at its end)
            raise RuntimeFailure(f"{type(self).__name__} cannot connect to "
                                 f"{self.resource}: {unknown}")
        try:
            client = ControlClient(ClusterKey.load(), self.resource, watch_greeting=True)
        except zmq.ZMQError as exc:     # (a request's failure, as any: a driver counts it)
            raise RuntimeFailure(f"{type(self).__name__} cannot connect to "
                                 f"{self.resource}: {exc}") from None
        self.__dict__["_pb3a_device"] = current = (self.resource, client)
        return current

    def _lines(self, wait: Any) -> LineClient:
        """The connection to a line-speaking device: the one being let go of inside
        ``release``, else one to ``resource``, connected to now if there is none open
        (a connect that ``wait``'s cancellation cuts short)."""
        releasing = self.__dict__.get("_pb3a_releasing")
        if releasing is not None:
            if releasing[1].closed:     # (its last request failed: the release must go)
                releasing = (releasing[0], LineClient(releasing[0], self.timeout, wait))
                self.__dict__["_pb3a_releasing"] = releasing
            return releasing[1]
        current = self.__dict__.get("_pb3a_device")
        if current is not None and self._speaking(current):
            if not current[1].closed:
                return current[1]
            del self.__dict__["_pb3a_device"]   # (the same device, its last request failed)
        else:
            self._disconnect()
        self._check_resource()
        client = LineClient(self.resource, self.timeout, wait)
        self.__dict__["_pb3a_device"] = (self.resource, client)
        return client

    def _speaking(self, current: tuple[str, Any]) -> bool:
        """Whether connection ``current`` is to ``resource`` in the driver's protocol."""
        kind = LineClient if self.protocol == "lines" else ControlClient
        return current[0] == self.resource and isinstance(current[1], kind)

    def _check_resource(self) -> None:
        if not self.resource:
            raise RuntimeFailure(f"{type(self).__name__} has no resource port: set its "
                                 "'resource' state to the device's address")
        wrong = tcp_address_problems(self.resource, f"{type(self).__name__}'s resource")
        if wrong:                   # (a class default, not set through set_state)
            raise RuntimeFailure(wrong[0])

    def _disconnect(self) -> None:
        """Let go of the device connected to, if any: ``release`` it, then close."""
        current = self.__dict__.pop("_pb3a_device", None)
        if current is None:
            return
        self.__dict__["_pb3a_releasing"] = current
        try:
            with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
                self.release(_Bounded(current[1], self.timeout))
        finally:
            current[1].close()
            self.__dict__.pop("_pb3a_releasing")[1].close()     # (one made for release)


class _Bounded:
    """A device's connection as ``release`` is given it: each call waits at most the
    driver's ``timeout`` (a release asking for longer held a re-point, a move or a stop
    for as long)."""

    def __init__(self, client: ControlClient | LineClient, most: float) -> None:
        self.address = client.address
        self._client, self._most = client, most

    def call(self, op: str, timeout: float = DEFAULT_TIMEOUT, **args: Any) -> Any:
        """``ControlClient.call``, waiting at most the driver's timeout."""
        return self._client.call(op, min(timeout, self._most), **args)

    def ask(self, line: str) -> str | None:
        """``LineClient.ask``, waiting at most the driver's timeout."""
        return self._client.ask(line, self._most)

    def tell(self, line: str) -> None:
        """``LineClient.ask`` without an answer, waiting at most the driver's timeout."""
        self._client.ask(line, self._most, answer=False)


def serve_device(handler: Callable[[str, dict[str, Any]], Any], host: str = "127.0.0.1",
                 port: int = 0) -> ControlServer:
    """Serve a device's side of its ``Driver``: ``handler(op, args)`` answers each request,
    one at a time, in order; what it raises fails the driver's request with its message.
    A request not begun within its driver's ``timeout`` of coming is dropped, not done.
    Requests are authenticated with this machine's cluster key (``pb3a key``), as the
    system's own. ``address`` (``tcp://HOST:PORT``; port 0: a free one) is what the
    driver's ``resource`` is set to; ``close()``, or leaving a ``with`` block, stops it.

        with pb3a.serve_device(lambda op, args: plant.call(op, **args), port=7400):
            ...                                 # the device runs; drivers reach it
    """
    # (a request its driver no longer waits for is dropped: a relative move retried
    # after a timeout was made twice)
    return ControlServer(ClusterKey.load(), handler, host, port, name="pb3a-device",
                         title="the device", expires=True)


def _device_problems(name: str, state: dict[str, Any]) -> list[str]:
    """``Driver.state_problems``'s own rules, for class ``name``."""
    problems = []
    if state.get("resource", "") != "":
        problems += tcp_address_problems(state["resource"], f"{name}'s resource")
    protocol = state.get("protocol", "pb3a")
    if protocol not in PROTOCOLS:
        problems.append(f"{name}'s protocol is what its device speaks, one of "
                        f"{', '.join(map(repr, PROTOCOLS))}, got {protocol!r}")
    timeout = state.get("timeout", 1.0)
    if not (finite(timeout) and 0 < timeout <= MOST_SECONDS):
        problems.append(f"{name}'s timeout must be a positive number of seconds, at most "
                        f"{MOST_SECONDS:g} (each request's deadline), got {timeout!r}")
    return problems
