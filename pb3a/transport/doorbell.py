"""Doorbells: how a writer wakes a sleeping reader process.

Each worker process owns one ``Doorbell``, a Unix datagram socket in the
abstract namespace (no file to clean up; it vanishes with the process). A
writer rings it only when the reader has said it is going to sleep, so a busy
link costs no system calls.
"""

from __future__ import annotations

import socket


def bell_address(name: str) -> str:
    """The abstract-namespace address of the doorbell called ``name``."""
    return "\0" + name


class Doorbell:
    """The reader's end: ``wait`` blocks until rung or until the timeout."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.bind(bell_address(name))
        self._timeout: float | None = None

    def wait(self, timeout: float) -> bool:
        """Block up to ``timeout`` seconds; True if rung.

        One ring is consumed per wake-up: a second pending ring only makes the
        next wait return at once, which costs less than emptying the socket.
        """
        if timeout != self._timeout:
            self._sock.settimeout(timeout)
            self._timeout = timeout
        try:
            self._sock.recv(64)
        except TimeoutError:
            return False
        return True

    def close(self) -> None:
        self._sock.close()


class BellPull:
    """The writer's end: ``ring`` never blocks and ignores a reader that is gone."""

    def __init__(self, name: str) -> None:
        self.address = bell_address(name)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.setblocking(False)

    def ring(self) -> None:
        # A full buffer means rings are pending already; a refused or missing address
        # means the reader died and will be restarted. Neither concerns the writer.
        try:
            self._sock.sendto(b"\x01", self.address)
        except (BlockingIOError, ConnectionRefusedError, FileNotFoundError):
            return

    def close(self) -> None:
        self._sock.close()
