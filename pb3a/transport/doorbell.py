"""Doorbells: how a writer wakes a sleeping reader process.

Each worker process has one doorbell, an eventfd that its executor creates and
hands over the worker's control pipe (SCM_RIGHTS); its receiver sleeps on it in
``ring.sleep``, and writers get a duplicate
of the same descriptor for each link into that worker. An eventfd is the
cheapest wake-up Linux offers (a counter in the kernel: half the cost of a
datagram here), and it outlives a worker's restart, so writers keep ringing
the same bell. A writer rings only when the reader said it is going to sleep,
so a busy link costs no system calls.
"""

from __future__ import annotations

import os


def new_bell() -> int:
    """A fresh eventfd for a worker's doorbell (the executor owns and closes it)."""
    return os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)


class BellPull:
    """The writer's end: ``ring`` never blocks (an eventfd write only adds to a counter)."""

    def __init__(self, fd: int) -> None:
        self._fd = fd

    def ring(self) -> None:
        os.eventfd_write(self._fd, 1)

    def fileno(self) -> int:
        return self._fd

    def close(self) -> None:
        os.close(self._fd)
