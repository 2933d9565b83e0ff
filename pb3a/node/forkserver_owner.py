"""This process's side of its workers' forkserver (multiprocessing keeps one per
process): whether the one running now has started a process, which it does only once
its preload is imported, and stopping it when it has not.

The forkserver ignores SIGTERM (``pb3a.node.forkserver_signals``) and ends when the
write ends of its "alive" pipe close, which its owner's exit does. One stuck in its
preload, a module file that hangs as it is imported, would otherwise stay until this
process exits, and every worker start would wait for it: a node stops such a
forkserver as it shuts down, and a worker start that it left unanswered stops it too.
"""

from __future__ import annotations

import ast
import contextlib
import os
import select
import signal
from multiprocessing import forkserver, util
from typing import Any

# How long a forkserver asked to stop (its alive pipe closed) has to end before it is
# killed: one preloading ends at once (``forkserver_signals``' watch), unless a start
# request is queued for it, which holds a write end of that pipe too.
STOP_GRACE_S = 0.5
# How long a killed forkserver is waited for, to reap it.
KILL_WAIT_S = 5.0

# How long the workers of an owner that has ended have, once its forkserver told them
# to stop (SIGTERM), to tear their modules down and exit before it kills them
# (``pb3a.node.forkserver_signals``): a node's shutdown gives a module's stop 2 s, and
# a worker stops its modules one after another.
ORPHAN_GRACE_S = 5.0

# An entry of the preload list that names this process to the forkserver (it imports
# nothing): ``pb3a.node.forkserver_signals`` ends the forkserver as its owner does.
OWNER_MARK = "pb3a.node.forkserver_owner_pid_"

_answered: int | None = None        # the process id of the forkserver that last started one


# multiprocessing's own, not a public API (as of CPython 3.11-3.13): the stop below
# needs its forkserver's process, pipe and socket. Where they are named otherwise, a
# forkserver still preloading is left to end with this process, as it was before.
_INTERNALS = ("_lock", "_forkserver_pid", "_forkserver_alive_fd", "_forkserver_address")


def _server() -> object | None:
    """multiprocessing's forkserver record, if it has the fields this module uses."""
    server = getattr(forkserver, "_forkserver", None)
    return server if all(hasattr(server, name) for name in _INTERNALS) else None


def running() -> int | None:
    """The process id of this process's forkserver, if one was started (and not seen
    ended)."""
    server = _server()
    return None if server is None else server._forkserver_pid   # type: ignore[attr-defined]


def owner_mark() -> str:
    """The preload list's entry that names this process as the forkserver's owner."""
    return f"{OWNER_MARK}{os.getpid()}"


def answered() -> None:
    """Note that the forkserver running now started a process: its preload is done."""
    global _answered
    _answered = running()


def preload_of(pid: int) -> list[str]:
    """What forkserver ``pid`` was told to preload, as its command line says it (for
    messages); empty if it cannot be read."""
    with contextlib.suppress(OSError, ValueError, SyntaxError):
        with open(f"/proc/{pid}/cmdline", "rb") as cmdline:
            words = cmdline.read().decode(errors="replace")
        start, end = words.find("["), words.find("]")
        if 0 <= start < end:
            return [str(name) for name in ast.literal_eval(words[start:end + 1])]
    return []


def stop_if_preloading(grace: float = STOP_GRACE_S) -> int | None:
    """Stop this process's forkserver if it has started no process yet (it is still
    importing its preload, perhaps hung there): ask it to end (its alive pipe closed),
    kill it (SIGKILL) if it has not within ``grace`` seconds, and reap it; the next
    start starts a new one. Its process id if it was stopped, else None. Every worker
    it started (none, if it answered nothing) is left as it is."""
    server: Any = _server()
    if server is None:
        return None
    with server._lock:
        pid = server._forkserver_pid
        if pid is None or pid == _answered:
            return None
        os.close(server._forkserver_alive_fd)
        if not _reaped_within(pid, grace):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
            _reaped_within(pid, KILL_WAIT_S)
        address = server._forkserver_address
        server._forkserver_pid = None
        server._forkserver_alive_fd = None
        server._forkserver_address = None
        if address is not None and not util.is_abstract_socket_namespace(address):
            with contextlib.suppress(OSError):
                os.unlink(address)
    return pid


def _reaped_within(pid: int, timeout: float) -> bool:
    """Wait up to ``timeout`` seconds for child ``pid`` to end, and reap it if it did."""
    try:
        pidfd = os.pidfd_open(pid)
    except ProcessLookupError:
        pidfd = None                                 # (ended and reaped already)
    if pidfd is not None:
        try:
            select.select([pidfd], [], [], timeout)  # (readable once it has ended)
        finally:
            os.close(pidfd)
    try:
        ended, _ = os.waitpid(pid, os.WNOHANG)
    except ChildProcessError:
        return True
    return ended != 0
