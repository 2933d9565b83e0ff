"""Doorbells: how a writer wakes a sleeping reader process.

Each worker process has one ``Doorbell``, an eventfd that its executor creates
and hands over the worker's control pipe (SCM_RIGHTS); writers get a duplicate
of the same descriptor for each link into that worker. An eventfd is the
cheapest wake-up Linux offers (a counter in the kernel: half the cost of a
datagram here), and it outlives a worker's restart, so writers keep ringing
the same bell. A writer rings only when the reader said it is going to sleep,
so a busy link costs no system calls.
"""

from __future__ import annotations

import contextlib
import os
import select


def new_bell() -> int:
    """A fresh eventfd for a worker's doorbell (the executor owns and closes it)."""
    return os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)


class Doorbell:
    """The reader's end: ``wait`` blocks until rung or until the timeout."""

    def __init__(self, fd: int) -> None:
        self._fd = fd

    def wait(self, timeout: float) -> bool:
        """Block up to ``timeout`` seconds; True if rung. Clears every pending ring."""
        ready, _, _ = select.select([self._fd], [], [], timeout)
        if not ready:
            return False
        with contextlib.suppress(BlockingIOError):   # another waiter took it first
            os.eventfd_read(self._fd)
        return True

    def close(self) -> None:
        os.close(self._fd)


class BellPull:
    """The writer's end: ``ring`` never blocks (an eventfd write only adds to a counter)."""

    def __init__(self, fd: int) -> None:
        self._fd = fd

    def ring(self) -> None:
        os.eventfd_write(self._fd, 1)

    def close(self) -> None:
        os.close(self._fd)
