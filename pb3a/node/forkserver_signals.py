"""Imported by the workers' forkserver alone, first in its preload list: it ignores
SIGTERM, SIGINT and SIGHUP, marks the process as PB3A's own, so that a module it
preloads cannot launch a system there (and start another forkserver, for good), and
ends the process if its owner goes while it is still preloading.

A SIGTERM to the whole process group (``timeout``, ``kill -- -PGID``, systemd's
default ``KillMode``) reached the forkserver too, which died of it; the exit codes of
the workers it had started were lost with it (255), and the executor took each for a
crash, marking every module failed. A Ctrl-C, or the terminal closing (SIGHUP), as it
loaded its preload printed tracebacks or killed it the same way (Python ignores
SIGINT there only once the preload is done). Each worker sets its own handlers (it
stops, exit 0); the forkserver ends with the process that started it.

multiprocessing ends it when the write ends of its "alive" pipe close (its owner's
exit, and each worker's it started), but looks at that pipe only once every module of
the preload is imported: a module file that hangs as it is imported (waiting for a
device, a ``sleep``) left the forkserver stuck there for good, ignoring SIGTERM,
re-parented to init once its owner had gone. Until ``pb3a.node.forkserver_preloaded``,
imported last, says the preload is done, a thread watches its owner (a pidfd of the
process the preload list names: the pipe alone is not enough, as a start request
queued on the forkserver's socket, which it reads only once preloaded, carries a write
end of its own) and the pipe (the owner closes its end to stop it,
``pb3a.node.forkserver_owner``), and ends the process as either ends.
"""

from __future__ import annotations

import os
import select
import signal
import sys
import threading
from multiprocessing import forkserver

from pb3a.node.forkserver_owner import OWNER_MARK
from pb3a.processes import mark_as

mark_as("the forkserver that starts a node's workers")

for _signal in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
    signal.signal(_signal, signal.SIG_IGN)


def _preloading() -> tuple[int, list[str]] | None:
    """The read end of the forkserver's "alive" pipe and its preload list, from the frame
    of ``multiprocessing.forkserver.main`` importing this module; None if this process
    is not a forkserver preloading it."""
    frame = sys._getframe(1)
    while frame is not None:
        if frame.f_code is forkserver.main.__code__:
            return frame.f_locals["alive_r"], frame.f_locals["preload"]
        frame = frame.f_back
    return None


def _named_owner(preload: list[str]) -> int | None:
    """The process id of the forkserver's owner, as its preload list names it
    (``forkserver_owner.OWNER_MARK``: ``os.getppid`` gives a reaper instead if the
    owner ended as this process started); None if it is not named."""
    for name in preload:
        if name.startswith(OWNER_MARK):
            return int(name[len(OWNER_MARK):])
    return None


def _end_with_owner(alive_r: int, owner: int, preloaded_r: int) -> None:
    """End the process once its owner (``owner``, a pidfd) ends or ``alive_r`` reads its
    end (the owner closed it: no worker has been started yet to hold one), unless
    ``preloaded_r`` says the preload is done first: multiprocessing's loop watches the
    pipe from then on."""
    poller = select.poll()
    for fd in (alive_r, owner, preloaded_r):
        poller.register(fd, select.POLLIN)
    while True:
        ready = {fd for fd, _ in poller.poll(1000)}
        if preloaded_r in ready:
            return
        if ready:
            os._exit(0)        # (the main thread is in an import that may never end)


_watch: threading.Thread | None = None
if (_started := _preloading()) is not None \
        and (_owner_pid := _named_owner(_started[1])) is not None:
    try:
        _owner_fd = os.pidfd_open(_owner_pid)
    except ProcessLookupError:
        os._exit(0)            # (its owner is gone: nobody will ask it for a worker)
    if os.getppid() != _owner_pid:
        os._exit(0)            # (the same: this process was handed to a reaper)
    _preloaded_r, _preloaded_w = os.pipe()
    _watch = threading.Thread(target=_end_with_owner,
                              args=(_started[0], _owner_fd, _preloaded_r),
                              name="pb3a-forkserver-owner", daemon=True)
    _watch.start()


def preloaded() -> None:
    """The preload is done: the watch ends, before the forkserver forks any worker (a
    fork copies the calling thread alone, and the watch's pipe would be the worker's)."""
    if _watch is None:
        return
    os.write(_preloaded_w, b"\x01")
    _watch.join(5.0)
    for fd in (_owner_fd, _preloaded_r, _preloaded_w):
        os.close(fd)
