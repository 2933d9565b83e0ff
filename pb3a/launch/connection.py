"""``pb3a.connect``: the API of a system launched by another process, or on another host.

A ``Connection`` is a ``SystemHandle`` whose calls go as authenticated requests to
the launcher's control server (``Running.listen``; ``pb3a run`` prints its address).
Closing it closes the connection only: the system goes on.
"""

from __future__ import annotations

import functools
import time
from typing import Any

from pb3a.errors import RuntimeFailure, RuntimeTimeout, SystemStopped, bounded_wait
from pb3a.launch.handle import SystemHandle
from pb3a.launch.operations import DEFAULT_TIMEOUT
from pb3a.transport.addresses import launcher_address, unknown_host
from pb3a.transport.auth import (
    DEFAULT_KEY_FILE,
    KEY_ENV,
    KEY_FILE_ENV,
    ClusterKey,
    ClusterKeyMissing,
)
from pb3a.transport.control import ControlClient, NotListening
from pb3a.transport.pickling import PYTHON

CONNECT_TIMEOUT = 5.0       # a launcher answers a ping at once, or is not there
_MARGIN = 5.0               # the wire's deadline beyond the operation's own


def connect(address: str, *, key: ClusterKey | bytes | str | None = None,
            timeout: float = CONNECT_TIMEOUT) -> Connection:
    """The running system whose launcher listens at ``address`` ("tcp://HOST:PORT", as
    ``pb3a run`` prints it, or "HOST:PORT").

    ``key`` is the cluster key material (as ``PB3A_KEY`` holds it) or a ``ClusterKey``;
    by default the one ``PB3A_KEY``, ``PB3A_KEY_FILE`` or ``~/.pb3a/cluster.key`` gives,
    never made here (``ClusterKeyMissing`` when there is none, saying where to get the
    cluster's: the launcher has one, which a key made here would not be). Raises
    ``RuntimeTimeout`` when nothing answers within ``timeout`` (sooner, about 1.5 s,
    when nothing listens there: connections refused), and ``RuntimeFailure``
    when the launcher refuses the key, each saying what to check. Once connected, a
    launcher whose process ends fails the calls waiting for it and every later one
    with ``SystemStopped``, about a second after it closed the connection, or at once
    when another launcher listens at the address by then (another system, or the same
    one launched again: a connection is to one run of a system).
    """
    return Connection(address, key=key, timeout=timeout)


class Connection(SystemHandle):
    """A system running elsewhere; use it as a context manager to close the connection."""

    def __init__(self, address: str, *, key: ClusterKey | bytes | str | None = None,
                 timeout: float = CONNECT_TIMEOUT) -> None:
        # (NaN and inf failed in time arithmetic's words, -1 was waited as 0, True as 1)
        timeout = bounded_wait(timeout, "connect")
        address = launcher_address(address)
        deadline = time.monotonic() + timeout
        unknown = unknown_host(address, timeout)
        if unknown is not None:
            raise RuntimeFailure(f"{unknown}: check the address (pb3a run prints it)")
        self.address = address
        named = ["?"]                       # the system's name, once it has said it
        self._named = named
        # (not a method of the connection: the two held each other, so one dropped
        # unclosed waited for the cycle collector, not its last reference, to be closed)
        self._client = ControlClient(_key(key), address,
                                     when_gone=functools.partial(_stopped, named, address))
        try:
            described = _describe(self._client, address, deadline)
        except RuntimeTimeout as exc:
            self.close()
            raise RuntimeTimeout(f"no PB3A launcher answered at {address} within "
                                 f"{timeout:g} s: check the address (pb3a run prints it), "
                                 "that the system still runs, and that the port is open"
                                 if not exc.args else exc.args[0]) from None
        except RuntimeFailure as exc:
            self.close()
            raise RuntimeFailure(f"cannot connect: {exc}") from None
        self.name: str = described["name"]
        named[0] = self.name
        # what a call without ``timeout=`` waits there: the system's default, which its
        # file or launch() may set longer than the library's
        self.timeout: float = described.get("timeout", DEFAULT_TIMEOUT)
        self._python: str | None = described.get("python")      # (None: an older launcher)

    def _carry(self, op: str, args: dict[str, Any]) -> Any:
        if isinstance(args.get("cls"), type) and self._python not in (None, PYTHON):
            # (a class defined here travels as bytecode, which another Python reads
            # wrongly or crashes on)
            raise RuntimeFailure(
                f"{op} {args.get('name')}: the system runs Python {self._python} and this "
                f"process Python {PYTHON}, so a class object cannot be sent to it: name "
                "the class as 'module:Class' (in a file the system can import), or run this "
                f"on Python {self._python}")
        wait = args.get("timeout")
        deadline = (self.timeout if wait is None else wait) + _MARGIN
        return self._client.request(op, args, deadline)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until ``timeout`` seconds pass or the system stops (its launcher closed
        the connection for good: calls raise ``SystemStopped`` from then on); True if it
        stopped. A closed connection sees nothing more: it answers at once."""
        if self._client.closed:
            return self._client.gone.is_set()
        return self._client.gone.wait(timeout)

    @property
    def running(self) -> bool:
        """False once the system has stopped, as ``wait`` sees it."""
        return not self._client.gone.is_set()

    @property
    def stopped_why(self) -> str | None:
        """Once the system has stopped (``running`` is False): what a call says then,
        how it is known included; None while it runs."""
        if not self._client.gone.is_set():
            return None
        return str(_stopped(self._named, self.address, self._client.gone_why))

    def close(self) -> None:
        """Close the connection (the system goes on)."""
        self._client.close()

    def __enter__(self) -> Connection:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Connection({self.name!r} at {self.address})"


def _describe(client: ControlClient, address: str, deadline: float) -> dict[str, Any]:
    """The launcher's description of its system; a port nothing listens on is said
    within about 1.5 s (a system that has ended, a wrong port): the whole timeout was
    waited, to say less. ``RuntimeTimeout`` without words when the deadline passes."""
    try:
        return client.call_if_listened("describe", max(0.0, deadline - time.monotonic()))
    except NotListening as exc:
        raise RuntimeTimeout(f"no PB3A launcher answered at {address}: {exc}: the system "
                             "has stopped, or the address is wrong (pb3a run prints it)"
                             ) from None
    except RuntimeTimeout:
        raise RuntimeTimeout() from None


def _stopped(named: list[str], address: str, why: str) -> SystemStopped:
    """What a call says once the launcher has gone for good (``why``: how it is known)."""
    return SystemStopped(f"system {named[0]!r} at {address} has stopped: {why}")


def _key(key: ClusterKey | bytes | str | None) -> ClusterKey:
    """The key to connect with: ``key``, else the one this user has (``ClusterKey.load``),
    never one made now: a running system's launcher has a key already, and one made
    here would be refused by it (a connecting command, ``pb3a status`` say, made
    ``~/.pb3a/cluster.key`` on a machine that had none, said nothing of it, and was told
    the launcher "runs with another cluster key"); ``ClusterKeyMissing`` says where to
    get the cluster's."""
    if key is None:
        try:
            return ClusterKey.load(create=False)
        except ClusterKeyMissing:
            path = DEFAULT_KEY_FILE.expanduser()
            raise ClusterKeyMissing(
                f"no cluster key: ${KEY_ENV} and ${KEY_FILE_ENV} are not set, and {path} "
                "does not exist; a running system's launcher has its cluster's key, and "
                "one made here would be refused: copy that key file here (the launcher "
                f"machine's ~/.pb3a/cluster.key, or the file its ${KEY_FILE_ENV} names), "
                f"then set {KEY_FILE_ENV}=PATH or put it at {path} (mode 0600)") from None
    if isinstance(key, ClusterKey):
        return key
    return ClusterKey.from_material(key, "connect(key=...)")
