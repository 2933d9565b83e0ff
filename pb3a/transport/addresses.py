"""Addresses: where a socket binds, and the address that peers are told to use.

A node hands addresses out (its publications, its executor's control server, the
launcher's call-back), and each must be reachable by the peers that use it, which on
another host excludes loopback. ``bind_advertised`` binds a socket on the host it
is to be reached at when that is one of this machine's addresses, else on every
interface (a host name, or an address a NAT maps to this machine), and returns the
address to hand out: ``tcp://HOST:PORT`` with that host.
"""

from __future__ import annotations

import contextlib
import errno
import ipaddress
import itertools
import logging
import socket
import threading
import time
from typing import TYPE_CHECKING, TypeVar

import psutil
import zmq
from zmq.utils.monitor import recv_monitor_message

if TYPE_CHECKING:
    from collections.abc import Callable

T = TypeVar("T")

log = logging.getLogger("pb3a.addresses")
_CLOSINGS = itertools.count()        # names the monitor of each socket close_bound closes
_UNSTOPPED: list[zmq.Socket] = []    # monitors of sockets close_bound gave up waiting for
_UNSTOPPED_LOCK = threading.Lock()


def bind_advertised(sock: zmq.Socket, host: str, port: int = 0) -> str:
    """Bind ``sock`` for peers that reach this machine at ``host`` (port 0: any free
    port); the address to hand them. Bound to every interface (``0.0.0.0``, ``*``,
    ``::``), that is this machine's address on its default route, as a launcher's
    (``tcp://0.0.0.0:PORT``, handed out before, is refused by every client as naming
    no host to reach)."""
    try:
        sock.bind(f"tcp://{host}:{port or '*'}")
    except zmq.ZMQError as exc:
        if exc.errno not in (errno.EADDRNOTAVAIL, errno.ENODEV, errno.EINVAL):
            raise
        sock.bind(f"tcp://*:{port or '*'}")       # not an address of ours: all interfaces
    bound = sock.getsockopt_string(zmq.LAST_ENDPOINT)
    reached = default_route_host() if host in EVERY_INTERFACE else host
    return f"tcp://{reached}:{bound.rpartition(':')[2]}"


EVERY_INTERFACE = ("*", "0.0.0.0", "[::]", "::")   # hosts that mean: every interface
_ROUTED = "198.51.100.1"        # (TEST-NET-2: an address only the default route leads to)
RESOLVE_S = 2.0                 # how long ``numeric`` waits for the resolver
_RESOLVED: dict[str, str] = {}  # each host name's address when ``numeric`` last resolved it


def default_route_host() -> str:
    """This machine's address on the interface of its default route (no packet is sent);
    with no route out, its one address on a network if it has only one (a robot's LAN
    with no gateway: loopback's, printed as the node's, was what a user then gave
    other machines), else loopback's."""
    try:
        return reachable_from(f"tcp://{_ROUTED}:9")
    except OSError:                     # no route out of this machine
        own = network_addresses()
        return own[0] if len(own) == 1 else "127.0.0.1"


def network_addresses() -> list[str]:
    """This machine's IPv4 addresses on interfaces that are up, loopback's left out."""
    up = {name for name, stats in psutil.net_if_stats().items() if stats.isup}
    return sorted(entry.address for name, entries in psutil.net_if_addrs().items()
                  if name in up for entry in entries if entry.family == socket.AF_INET
                  and not ipaddress.ip_address(entry.address).is_loopback)


def launcher_address(text: str) -> str:
    """``tcp://HOST:PORT``, also from ``HOST:PORT`` (a launcher's control server, as
    ``pb3a run`` prints it); ValueError saying what is wrong."""
    address = text if "://" in text else f"tcp://{text}"
    host, colon, port = address.removeprefix("tcp://").rpartition(":")
    if not address.startswith("tcp://") or not colon or not host or not port.isdigit():
        raise ValueError(f"{text!r} is not a launcher's address: give tcp://HOST:PORT (or "
                         "HOST:PORT), as pb3a run prints it")
    if not _a_port(port):       # (it waited, then said nothing listened there)
        raise ValueError(f"{text!r} is not a launcher's address: its port {port} is out "
                         "of range (1-65535); give the port pb3a run prints")
    return address


def _a_port(port: str) -> bool:
    """Whether ``port`` (digits) names a TCP port one may connect to."""
    return 0 < int(port) <= 65535


def host_of(address: str) -> str:
    """The host of ``[tcp://]HOST:PORT`` as written (an IPv6 host in its brackets, as
    an address is composed again from it); ``.strip("[]")`` for the bare host."""
    return address.removeprefix("tcp://").rpartition(":")[0]


def unresolved(address: str) -> str:
    """Why the host of ``address`` ("tcp://HOST:PORT") does not resolve; "" if it does.
    It asks the system's resolver, which may take its time: see ``unknown_host``."""
    try:
        socket.getaddrinfo(host_of(address).strip("[]"), None)
    except (socket.gaierror, UnicodeError) as exc:
        return getattr(exc, "strerror", None) or str(exc)
    return ""


def _within(resolve: Callable[[], T], timeout: float) -> list[T]:
    """What ``resolve()`` gives, on a thread of its own, waited for ``timeout`` at most
    (the system's resolver may take its time): in a list, empty if it did not answer."""
    answer: list[T] = []
    resolver = threading.Thread(target=lambda: answer.append(resolve()),
                                name="pb3a-resolve", daemon=True)
    resolver.start()
    resolver.join(timeout)
    return answer


def unknown_host(address: str, timeout: float) -> str | None:
    """Why the host of ``address`` ("tcp://HOST:PORT") has no address, if the resolver
    says so within ``timeout``; None if it has one, or the resolver did not answer in
    time (the connection's own deadline then tells). A misspelt host was waited for to
    the end of that deadline, and named only as "no answer"."""
    answer = _within(lambda: unresolved(address), timeout)
    if not answer or not answer[0]:
        return None
    return (f"no address is known for host {host_of(address).strip('[]')!r} of {address}: "
            f"{answer[0]}")


def connection_failure(address: str, timeout: float) -> OSError | None:
    """What a plain TCP connection to ``address`` ("tcp://HOST:PORT") meets within
    ``timeout``: None if it is accepted, else the error (``ConnectionRefusedError``:
    nothing listens on that port at that host; ``TimeoutError``: no answer; another
    ``OSError``: no route ...). ZeroMQ retries a connection on its own and tells nobody
    why it failed; this tells a port nothing listens on from a host out of reach."""
    host, _, port = address.removeprefix("tcp://").rpartition(":")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as exc:
        return exc
    return None


def numeric(address: str, timeout: float = RESOLVE_S) -> str:
    """``address`` ("tcp://HOST:PORT") with a host name replaced by its IPv4 address,
    resolved here within ``timeout``: connect ZeroMQ sockets to that. ZeroMQ resolves a
    name again at every reconnection, in the one I/O thread all the process's sockets
    share, so a peer's name that stopped resolving promptly stalled every socket (the
    heartbeats to healthy nodes too, which were then lost: libzmq #2961). A name the
    resolver does not answer for in time has the address it last resolved to here, if
    any: a peer whose name server went silent is reconnected to (a rejoin asks again
    and again) without handing ZeroMQ the name, which stalled every socket of the
    launcher for as long, and had a healthy node declared lost. An address already
    numeric, or a name never resolved, is given back as it is."""
    host = host_of(address).strip("[]")
    with contextlib.suppress(ValueError):
        ipaddress.ip_address(host)
        return address
    def resolve() -> list[tuple]:
        try:
            return socket.getaddrinfo(host, None, socket.AF_INET, socket.SOCK_STREAM)
        except (OSError, UnicodeError):
            return []

    answer = _within(resolve, timeout)
    found = answer[0] if answer else []
    if found:
        _RESOLVED[host] = found[0][4][0]         # (family, type, proto, name, (ip, port))
    elif answer or host not in _RESOLVED:        # (no such name now, or never known)
        return address
    return f"tcp://{_RESOLVED[host]}:{address.rpartition(':')[2]}"


def tcp_address_problems(value: object, what: str, otherwise: str = "") -> list[str]:
    """Why ``value`` is not an address to connect to, ``tcp://HOST:PORT``, naming
    ``what`` it is (``otherwise``: what else it may be); none if it is one."""
    if isinstance(value, str) and value.startswith("tcp://"):
        host, _, port = value.removeprefix("tcp://").rpartition(":")
        if host in EVERY_INTERFACE:     # (what a listener binds, not where it is reached)
            return [f"{what} must be an address to connect to: {value!r} names every "
                    "interface; give the host's name or one of its addresses"]
        if host and not any(c in host for c in " /") and port.isdigit():
            if _a_port(port):
                return []
            return [f"{what} {value!r}: its port {port} is out of range (1-65535)"]
    return [f"{what} must be a string tcp://HOST:PORT such as 'tcp://10.0.0.7:7100'"
            f"{otherwise}, got {value!r}"]


def check_bindable(listen: str, host: str, port: int) -> None:
    """ValueError saying why a daemon or a launcher cannot listen on ``host:port``: the
    host is not one of this machine's addresses (the socket would otherwise bind every
    interface, and the address printed would name a host nobody reaches it at), or the
    port is taken."""
    try:
        found = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror:
        raise ValueError(f"cannot listen on {listen}: {host!r} is not a host name this "
                         "machine can resolve; give one of its addresses, or 0.0.0.0 for "
                         "every interface") from None
    family, kind, proto, _, sockaddr = found[0]
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)    # (as ZeroMQ binds)
        try:
            probe.bind(sockaddr)
        except OSError as exc:
            if exc.errno == errno.EADDRNOTAVAIL:
                raise ValueError(f"cannot listen on {listen}: {host} is not an address of "
                                 "this machine; give one of its addresses (`ip -brief "
                                 "address` lists them), or 0.0.0.0 for every interface"
                                 ) from None
            if exc.errno == errno.EADDRINUSE:
                raise ValueError(f"cannot listen on {listen}: port {port} is in use "
                                 "(is it running already?); stop what listens "
                                 "there (`ss -ltnp` shows it), or choose another port"
                                 ) from None
            raise


def close_bound(sock: zmq.Socket, timeout: float = 2.0, linger_ms: int = 0) -> None:
    """Close a bound ``sock`` and wait (at most ``timeout`` seconds) until its ports are
    free: ZeroMQ closes listeners on its own thread, after ``close`` has returned, so a
    server started at once on the same port could otherwise find it still in use.
    Messages sent and not yet delivered are given ``linger_ms`` to go. Given up on, its
    monitor stays open until ZeroMQ has said it stopped (a later call closes it)."""
    # (a name of its own: pyzmq's default names the socket's descriptor, which a socket
    # closed a moment ago may still hold as its monitor's address: "in use")
    try:
        monitor = sock.get_monitor_socket(zmq.EVENT_MONITOR_STOPPED,
                                          addr=f"inproc://pb3a-closing-{next(_CLOSINGS)}")
    except zmq.ZMQError:
        sock.close(linger_ms)                  # closed all the same, not waited for
        raise
    stopped = False
    try:
        sock.close(linger_ms)
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0 and monitor.poll(left * 1000):
            if recv_monitor_message(monitor)["event"] == zmq.EVENT_MONITOR_STOPPED:
                stopped = True
                return
        log.warning("a socket's ports were not free %.0f s after it was closed", timeout)
    finally:
        with _UNSTOPPED_LOCK:
            if not stopped:
                # ZeroMQ still sends it MONITOR_STOPPED, blocking (its reaper thread, for
                # good: no socket of the process was ever freed again) if it is closed
                _UNSTOPPED.append(monitor)
            else:
                monitor.close(0)
            _close_stopped_locked()


def _close_stopped_locked() -> None:
    """Close the monitors of ``_UNSTOPPED`` whose MONITOR_STOPPED has come."""
    for monitor in list(_UNSTOPPED):
        while monitor.poll(0):
            if recv_monitor_message(monitor)["event"] == zmq.EVENT_MONITOR_STOPPED:
                _UNSTOPPED.remove(monitor)
                monitor.close(0)
                break


def bind_address(address: str) -> tuple[str, int]:
    """The host and port a server binds for ``"[tcp://][host]:[port]"``: by default
    the loopback interface and any free port."""
    host, _, port = address.removeprefix("tcp://").rpartition(":")
    if (port and not (port.isdigit() and int(port) <= 65535)) or "://" in host:
        raise ValueError(f"{address!r} is not an address to listen on: give tcp://HOST:PORT "
                         "(PORT 0: any free port)")
    return host or "127.0.0.1", int(port or 0)


def loopback(host: str) -> bool:
    """Whether ``host`` (a name or an address) is this machine's loopback; False if it
    does not resolve."""
    try:
        return ipaddress.ip_address(socket.gethostbyname(host.strip("[]"))).is_loopback
    except (OSError, UnicodeError, ValueError):
        return False


def elsewhere(peer: str) -> bool:
    """Whether ``peer`` ("tcp://HOST:PORT") is on another machine: this machine reaches
    it through an interface of another address (one of its own addresses it reaches
    through itself). False if its host does not resolve."""
    try:
        return reachable_from(peer) != socket.gethostbyname(host_of(peer).strip("[]"))
    except (OSError, UnicodeError):
        return False


def reachable_from(peer: str) -> str:
    """The host of this machine that ``peer`` ("tcp://HOST:PORT") can reach it at: the
    address of the interface this machine reaches the peer through (no packet is sent)."""
    host = host_of(peer)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect((host, 9))
        except socket.gaierror as exc:
            raise OSError(f"no address is known for host {host!r} of {peer}: "
                          f"{exc.strerror}") from None
        return probe.getsockname()[0]
