"""Addresses: where a socket binds, and the address that peers are told to use.

A node hands addresses out (its publications, its executor's control server, the
launcher's call-back), and each must be reachable by the peers that use it, which on
another host excludes loopback. ``bind_advertised`` binds a socket on the host it
is to be reached at when that is one of this machine's addresses, else on every
interface (a host name, or an address a NAT maps to this machine), and returns the
address to hand out: ``tcp://HOST:PORT`` with that host.
"""

from __future__ import annotations

import errno
import socket

import zmq


def bind_advertised(sock: zmq.Socket, host: str, port: int = 0) -> str:
    """Bind ``sock`` for peers that reach this machine at ``host`` (port 0: any free
    port); the address to hand them."""
    try:
        sock.bind(f"tcp://{host}:{port or '*'}")
    except zmq.ZMQError as exc:
        if exc.errno not in (errno.EADDRNOTAVAIL, errno.ENODEV, errno.EINVAL):
            raise
        sock.bind(f"tcp://*:{port or '*'}")       # not an address of ours: all interfaces
    bound = sock.getsockopt_string(zmq.LAST_ENDPOINT)
    return f"tcp://{host}:{bound.rpartition(':')[2]}"


def bind_address(address: str) -> tuple[str, int]:
    """The host and port a server binds for ``"[tcp://][host]:[port]"``: by default
    the loopback interface and any free port."""
    host, _, port = address.removeprefix("tcp://").rpartition(":")
    if (port and not (port.isdigit() and int(port) <= 65535)) or "://" in host:
        raise ValueError(f"{address!r} is not an address to listen on: give tcp://HOST:PORT "
                         "(PORT 0: any free port)")
    return host or "127.0.0.1", int(port or 0)


def reachable_from(peer: str) -> str:
    """The host of this machine that ``peer`` ("tcp://HOST:PORT") can reach it at: the
    address of the interface this machine reaches the peer through (no packet is sent)."""
    host = peer.removeprefix("tcp://").rpartition(":")[0]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.connect((host, 9))
        return probe.getsockname()[0]
