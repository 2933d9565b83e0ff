"""Imported by the workers' forkserver alone, first in its preload list: it ignores
SIGTERM, SIGINT and SIGHUP, marks the process as PB3A's own, so that a module it
preloads cannot launch a system there (and start another forkserver, for good), and
ends the process if its owner goes while it is still preloading.

A SIGTERM to the whole process group (``timeout``, ``kill -- -PGID``, systemd's
default ``KillMode``) reached the forkserver too, which died of it; the exit codes of
the workers it had started were lost with it (255), and the executor took each for a
crash, marking every module failed. A Ctrl-C, or the terminal closing (SIGHUP), as it
loaded its preload printed tracebacks or killed it the same way (Python ignores
SIGINT there only once the preload is done). And one as its interpreter started,
before this module: it starts with them held off (``pb3a.processes.
terminal_signals_held``), and takes them here, ignored. Each worker sets its own
handlers (it stops, exit 0); the forkserver ends with the process that started it.

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

Once preloaded, the thread goes on watching the owner alone, and ends the workers when
it ends. Each worker holds a write end of the pipe too, so the forkserver outlived a
dead owner as long as one did, and nothing ended a worker that does not read its own
pipe's end (stopped, frozen, stuck in a ``teardown`` or a module's construction):
it ran on for good, with the forkserver, after its node's executor was SIGKILLed or
its launcher exited with its stop still under way. Now the forkserver SIGTERMs every
process it started (their modules stop and are torn down, as when a node stops),
SIGKILLs those still there ``ORPHAN_GRACE_S`` later, and exits. (The owner's death,
not the thread that started the forkserver, is what counts: ``PR_SET_PDEATHSIG`` in
the forkserver would fire as the owner's thread that happened to start it ended, and
in a worker only as the forkserver ended, which the workers themselves held off.)
A worker inherits the thread's pidfd of the owner, which holds nothing open.

An owner that ends normally removes the directory that holds the forkserver's socket
(multiprocessing's ``pymp-*`` under the temporary directory) as it exits; one killed
left both behind, a socket in /tmp for every launcher killed with SIGKILL. A
forkserver that ends with its owner removes its socket, and the directory once empty.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import select
import signal
import socket
import sys
import threading
import time
import warnings
from multiprocessing import forkserver

from pb3a.node.forkserver_owner import ORPHAN_GRACE_S, OWNER_MARK
from pb3a.processes import mark_as, restore_the_user_s_path_setting, take_terminal_signals

mark_as("the forkserver that starts a node's workers")
restore_the_user_s_path_setting()      # (the workers' own children get the user's)

for _signal in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
    signal.signal(_signal, signal.SIG_IGN)
take_terminal_signals()     # (held off since it started: ``workers._start_forkserver``)

# Python 3.12 warns of each fork in a process with threads: a thread holding a lock as
# the process forks leaves it held for good in the child. The one thread here, the
# owner's watch below, holds none (it waits in poll() on file descriptors), so the
# warning, printed once a forkserver with -X dev or PYTHONWARNINGS, says nothing true.
warnings.filterwarnings("ignore", r"This process \(pid=\d+\) is multi-threaded",
                        DeprecationWarning, r"multiprocessing\.forkserver\Z")

# How long ``preloaded`` waits for the watch to let go of the pipes it closes.
SWITCH_WAIT_S = 5.0
# How long a forkserver whose pipe has closed waits, as it exits, to see its owner end.
OWNER_END_WAIT_S = 1.0


def _preloading() -> tuple[int, list[str], int] | None:
    """The read end of the forkserver's "alive" pipe, its preload list and its listening
    socket, from the frame of ``multiprocessing.forkserver.main`` importing this module;
    None if this process is not a forkserver preloading it."""
    frame = sys._getframe(1)
    while frame is not None:
        if frame.f_code is forkserver.main.__code__:
            found = frame.f_locals
            return found["alive_r"], found["preload"], found["listener_fd"]
        frame = frame.f_back
    return None


def _socket_path(listener_fd: int) -> str | None:
    """The file the forkserver's socket is bound to; None for an abstract address or
    one that cannot be read."""
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM,
                           fileno=os.dup(listener_fd)) as listener:
            address = listener.getsockname()
    except OSError:
        return None
    return address if isinstance(address, str) and address.startswith("/") else None


def _remove_socket(path: str | None) -> None:
    """Remove the socket at ``path``, and its directory if that is now empty (its owner,
    gone, cannot): what the owner's exit would have removed, and nothing else."""
    if path is None:
        return
    with contextlib.suppress(OSError):
        os.unlink(path)
    directory = os.path.dirname(path)
    if os.path.basename(directory).startswith("pymp-"):      # (multiprocessing's own)
        with contextlib.suppress(OSError):
            os.rmdir(directory)     # (fails, as it should, if anything is left in it)


def _remove_socket_of_gone_owner(owner: int, path: str | None) -> None:
    """``_remove_socket`` if the owner (a pidfd) has ended. An owner that is ending
    closes its files (the alive pipe's end: multiprocessing's loop exits) a moment before
    its pidfd says it has ended, so that moment is waited for (``OWNER_END_WAIT_S``)."""
    if select.select([owner], [], [], OWNER_END_WAIT_S)[0]:
        _remove_socket(path)


def _named_owner(preload: list[str]) -> int | None:
    """The process id of the forkserver's owner, as its preload list names it
    (``forkserver_owner.OWNER_MARK``: ``os.getppid`` gives a reaper instead if the
    owner ended as this process started); None if it is not named."""
    for name in preload:
        if name.startswith(OWNER_MARK):
            return int(name[len(OWNER_MARK):])
    return None


def _end_with_owner(alive_r: int, owner: int, preloaded_r: int, path: str | None) -> None:
    """While the preload runs, end the process once its owner (``owner``, a pidfd) ends
    or ``alive_r`` reads its end (the owner closed it: no worker has been started yet
    to hold one). Once ``preloaded_r`` says the preload is done (multiprocessing's
    loop watches the pipe from then on), end the workers when the owner ends. An owner
    that ended leaves its socket (``path``) to this process to remove."""
    poller = select.poll()
    for fd in (alive_r, owner, preloaded_r):
        poller.register(fd, select.POLLIN)
    while True:
        ready = {fd for fd, _ in poller.poll(1000)}
        if preloaded_r in ready:
            break
        if owner in ready:
            _remove_socket(path)
        if ready:
            os._exit(0)        # (the main thread is in an import that may never end)
    # From here the forkserver forks workers beside this thread: it holds no lock, and
    # polls nothing a worker would need closed (a fork copies the calling thread alone)
    poller.unregister(alive_r)
    poller.unregister(preloaded_r)
    _switched.set()
    while not (events := dict(poller.poll())):
        pass
    if not events.get(owner, 0) & select.POLLIN:
        return                 # (its pidfd was closed: nothing is watched any more)
    _remove_socket(path)       # (first: the last worker's end lets the main thread exit)
    _end_workers()
    os._exit(0)                # (nothing is left to serve: its owner is gone)


def _end_workers() -> None:
    """SIGTERM every process this forkserver started, and SIGKILL those that have not
    ended ``ORPHAN_GRACE_S`` later."""
    workers = [fd for fd in map(_child_pidfd, _children()) if fd is not None]
    for fd in workers:
        with contextlib.suppress(ProcessLookupError):
            signal.pidfd_send_signal(fd, signal.SIGTERM)
    left = set(workers)
    poller = select.poll()
    for fd in workers:
        poller.register(fd, select.POLLIN)     # (readable once it has ended)
    deadline = time.monotonic() + ORPHAN_GRACE_S
    while left and (wait := deadline - time.monotonic()) > 0:
        for fd, _ in poller.poll(wait * 1000):
            left.discard(fd)
            poller.unregister(fd)
    for fd in left:
        with contextlib.suppress(ProcessLookupError):
            signal.pidfd_send_signal(fd, signal.SIGKILL)
    for fd in workers:
        os.close(fd)


def _children() -> list[int]:
    """The process ids of this process's children (from /proc)."""
    return [int(entry) for entry in os.listdir("/proc")
            if entry.isdigit() and _parent_of(entry) == os.getpid()]


def _parent_of(pid: str) -> int | None:
    """The parent of process ``pid``, None if it cannot be read (it ended)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as stat:
            # "pid (name) state ppid ...": the name may hold spaces and parentheses
            return int(stat.read().rpartition(b")")[2].split()[1])
    except (OSError, ValueError, IndexError):
        return None


def _child_pidfd(pid: int) -> int | None:
    """A pidfd of ``pid`` if it is still this process's child (its number may have been
    given to another process since it was listed), else None."""
    try:
        fd = os.pidfd_open(pid)
    except OSError:
        return None
    if _parent_of(str(pid)) != os.getpid():
        os.close(fd)
        return None
    return fd


_watch: threading.Thread | None = None
_switched = threading.Event()          # the watch no longer polls the preload's pipes
if (_started := _preloading()) is not None \
        and (_owner_pid := _named_owner(_started[1])) is not None:
    _path = _socket_path(_started[2])
    try:
        _owner_fd = os.pidfd_open(_owner_pid)
    except ProcessLookupError:
        _remove_socket(_path)
        os._exit(0)            # (its owner is gone: nobody will ask it for a worker)
    if os.getppid() != _owner_pid:
        _remove_socket(_path)
        os._exit(0)            # (the same: this process was handed to a reaper)
    # multiprocessing's loop exits (SystemExit) as its pipe closes, which an owner that
    # ended with no worker left does as the watch hears of it.
    atexit.register(_remove_socket_of_gone_owner, _owner_fd, _path)
    _preloaded_r, _preloaded_w = os.pipe()
    _watch = threading.Thread(target=_end_with_owner,
                              args=(_started[0], _owner_fd, _preloaded_r, _path),
                              name="pb3a-forkserver-owner", daemon=True)
    _watch.start()


def preloaded() -> None:
    """The preload is done: the watch lets go of the preload's pipe, which is closed
    before the forkserver forks any worker (the worker would hold it), and watches the
    owner alone from now on."""
    if _watch is None:
        return
    os.write(_preloaded_w, b"\x01")
    _switched.wait(SWITCH_WAIT_S)
    for fd in (_preloaded_r, _preloaded_w):
        os.close(fd)
