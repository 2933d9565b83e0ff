"""``LineClient``: a plain TCP connection to a program that speaks text lines.

A ``Driver`` whose device knows nothing of PB3A (a legacy controller, an instrument,
a robot's own server) talks to it this way: a request is one line sent, its answer
the next line that comes back (``Driver.ask``). A reader thread takes the lines in,
so the body waiting for an answer waits in the module's ``RuntimeWait`` and gives
way as a PB3A request does: a move, swap or stop cancels the wait rather than sit
out its deadline.

A request given up (its deadline passed, or cancelled) closes the connection: the
device's late answer would otherwise be read as the answer to the next request.
The driver connects anew at its next request.
"""

from __future__ import annotations

import contextlib
import errno
import selectors
import socket
import threading
import time
from typing import Any, Protocol

from pb3a.errors import PB3AError, RuntimeCancelled, RuntimeFailure, RuntimeTimeout
from pb3a.transport.control import Waiting

MAX_LINE = 1 << 20            # an answer longer than this is no line: the peer is not one
_SLICE_S = 0.1                # how often a connect in progress looks for a cancellation


class RuntimeWait(Waiting, Protocol):
    """A module body's wait (``pb3a.worker.waits.RuntimeWait``): told of the answer, and
    cancelled by the runtime that needs the module stopped."""

    @property
    def cancelled(self) -> str: ...


class LineClient:
    """A connection to the line-speaking program at ``address`` ("tcp://HOST:PORT");
    ``ask`` one request at a time. ``closed`` once either side ended it (``why``)."""

    def __init__(self, address: str, timeout: float, wait: RuntimeWait | None = None) -> None:
        self.address = address
        self.why = ""
        self.unsolicited = 0          # lines that came with no request waiting (a banner)
        host, _, port = address.removeprefix("tcp://").rpartition(":")
        self._sock = _connect(host.strip("[]"), int(port), timeout, wait)
        self._sock.settimeout(None)
        self._cond = threading.Condition()
        self._waiting: RuntimeWait | _Answer | None = None
        self._reader = threading.Thread(target=self._read, name="pb3a-line-device",
                                        daemon=True)
        self._reader.start()

    @property
    def closed(self) -> bool:
        return bool(self.why)

    def ask(self, text: str, timeout: float, wait: RuntimeWait | None = None,
            answer: bool = True) -> str | None:
        """Send ``text`` as a line; the next line back (without its line end), or None
        when no ``answer`` is asked for. ``RuntimeTimeout`` after ``timeout`` seconds,
        ``RuntimeCancelled`` when ``wait`` is cancelled, ``RuntimeFailure`` when the
        connection is gone; the connection is closed after each of them."""
        if "\n" in text or "\r" in text:
            raise ValueError(f"one line is sent at a time, without its line end: {text!r}")
        waiter = wait if wait is not None else _Answer()
        with self._cond:
            if self.why:
                raise RuntimeFailure(self.why)
            if answer:
                self._waiting = waiter
        try:
            self._send(f"{text}\n".encode(), timeout)
            if not answer:
                return None
            return waiter.result(timeout)
        except RuntimeCancelled:
            self.close("a request was cancelled: its answer may still come, and would be "
                       "read as the next one's")
            raise
        except RuntimeTimeout:
            self.close("a request got no answer in time: a late one would be read as the "
                       "next one's")
            raise RuntimeTimeout(f"no answer to {text!r} within {timeout:g} s") from None
        finally:
            with self._cond:
                if self._waiting is waiter:
                    self._waiting = None

    def close(self, why: str = "closed") -> None:
        """End the connection; a request waiting fails with ``why``."""
        self._ended(why)
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)     # (wakes the reader)
        self._reader.join(timeout=1.0)
        self._sock.close()

    def _send(self, data: bytes, timeout: float) -> None:
        """All of ``data`` within ``timeout`` (a device that reads nothing fills the
        socket's buffer: then the connection is given up)."""
        deadline = time.monotonic() + timeout
        view = memoryview(data)
        with selectors.DefaultSelector() as selector:
            selector.register(self._sock, selectors.EVENT_WRITE)
            while view:
                if not selector.select(max(0.0, deadline - time.monotonic())):
                    self.close("the device read nothing of a request")
                    raise RuntimeTimeout(f"the device at {self.address} read nothing of "
                                         f"a request within {timeout:g} s")
                try:
                    view = view[self._sock.send(view, socket.MSG_DONTWAIT):]
                except BlockingIOError:
                    continue
                except OSError as exc:
                    self.close(f"the connection broke: {exc.strerror or exc}")
                    raise RuntimeFailure(self.why) from None

    def _read(self) -> None:
        """The reader thread: each line in goes to the request waiting for it."""
        buffer = b""
        why = "the device closed the connection"
        try:
            while True:
                chunk = self._sock.recv(65536)
                if not chunk:
                    break
                buffer += chunk
                *lines, buffer = buffer.split(b"\n")
                for line in lines:
                    self._deliver(line.rstrip(b"\r").decode("utf-8", "replace"))
                if len(buffer) > MAX_LINE:
                    why = (f"the device sent more than {MAX_LINE} bytes without a line "
                           "end: it does not speak lines")
                    break
        except OSError as exc:
            why = f"the connection broke: {exc.strerror or exc}"
        self._ended(why)

    def _ended(self, why: str) -> None:
        """The connection is over (the first ``why`` given is kept): a request waiting
        fails with it."""
        with self._cond:
            if not self.why:
                self.why = why
            waiting, self._waiting = self._waiting, None
        if waiting is not None:
            waiting.answer(False, self.why)

    def _deliver(self, line: str) -> None:
        with self._cond:
            waiting, self._waiting = self._waiting, None
            if waiting is None:
                self.unsolicited += 1
                return
        waiting.answer(True, line)


class _Answer:
    """What a request waits in when its caller is no module body."""

    def __init__(self) -> None:
        self._event = threading.Event()
        self._box: tuple[bool, Any] = (False, None)

    def answer(self, ok: bool, result: Any) -> None:
        self._box = (ok, result)
        self._event.set()

    def result(self, timeout: float) -> Any:
        if not self._event.wait(timeout):
            raise RuntimeTimeout("no answer")
        ok, result = self._box
        if not ok:
            raise RuntimeFailure(result)
        return result


def _connect(host: str, port: int, timeout: float, wait: RuntimeWait | None) -> socket.socket:
    """A TCP connection to ``host:port`` within ``timeout``, given up at once if ``wait``
    is cancelled meanwhile (a connection to a host that does not answer takes the whole
    timeout, which a move of the driver must not sit out)."""
    try:
        family, kind, proto, _, where = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except socket.gaierror as exc:
        raise RuntimeFailure(f"no address is known for host {host!r}: {exc.strerror}") from None
    sock = socket.socket(family, kind, proto)
    sock.setblocking(False)
    deadline = time.monotonic() + timeout
    try:
        code = sock.connect_ex(where)
        if code not in (0, errno.EINPROGRESS):
            raise OSError(code, errno.errorcode.get(code, str(code)))
        with selectors.DefaultSelector() as selector:
            selector.register(sock, selectors.EVENT_WRITE)
            while not selector.select(min(_SLICE_S, max(0.0, deadline - time.monotonic()))):
                if wait is not None and wait.cancelled:
                    raise RuntimeCancelled(f"connecting to tcp://{host}:{port} cancelled: "
                                           f"{wait.cancelled}")
                if time.monotonic() >= deadline:
                    raise RuntimeTimeout(f"tcp://{host}:{port} did not take a connection "
                                         f"within {timeout:g} s: check that the host is up "
                                         "and reachable")
        code = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        if code == errno.ECONNREFUSED:
            raise RuntimeFailure(f"nothing listens on port {port} at {host} (the "
                                 "connection was refused): start the device's program, or "
                                 "fix the port")
        if code:
            raise RuntimeFailure(f"cannot connect to tcp://{host}:{port}: "
                                 f"{errno.errorcode.get(code, code)}")
    except PB3AError:
        sock.close()
        raise
    except OSError as exc:
        sock.close()
        raise RuntimeFailure(f"cannot connect to tcp://{host}:{port}: "
                             f"{exc.strerror or exc}") from None
    return sock
