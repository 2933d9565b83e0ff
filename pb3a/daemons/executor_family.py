"""An executor's family: the executor and every process it starts (its forkserver, its
workers, and what their modules start) carry one mark in their environment, which its
node controller finds them by once the executor has died. By then they are no longer
its descendants (re-parented as it died), and only their mark says whose they were.

The controller ends them (SIGKILL) when a launcher asks whether the executor has
ended: a process sent SIGKILL runs none of its code again, so the launcher may start
their modules elsewhere at once, where it would otherwise wait for their lease to run
out. (Left alone, they stop as their lease runs out, and their forkserver ends them.)
"""

from __future__ import annotations

import contextlib
import os
import secrets
import signal
import time

import psutil

MARK = "PB3A_EXECUTOR_FAMILY"
_SCAN_S = 0.02      # between two looks for a family's processes still alive
_EXEC_S = 0.5       # the longest a process is taken to be in the middle of an exec
_PF_KTHREAD = 0x00200000    # a kernel thread, in /proc/PID/stat's flags
_TICKS_PER_S = os.sysconf("SC_CLK_TCK")     # /proc/PID/stat's unit of time


def new_mark() -> str:
    """A mark no other executor's family carries."""
    return secrets.token_hex(8)


def take_mark(mark: str) -> None:
    """Mark this process (an executor, before it starts any) and, through the
    environment they inherit, every process it starts from now on."""
    os.environ[MARK] = mark


def members(mark: str, until: float | None = None) -> list[psutil.Process]:
    """The live processes that carry ``mark`` (a zombie runs nothing: left out).

    One caught in the middle of an ``exec`` shows no environment for a moment (its
    new one is not in place yet): one started less than ``_EXEC_S`` ago is looked at
    again until it shows one, or is that old, lest a process just started be missed (a
    module's, which would then run on beside its failed-over copy); not past ``until``
    (``time.monotonic()``), if given. One that shows none for longer (``env -i``) is
    no family's: every look waited for it, and the family's end outlasted the
    launcher's question."""
    wanted = f"{MARK}={mark}".encode()
    found = []
    looking = psutil.pids()
    while True:
        unsure = []
        for pid in looking:
            environ = _environ(pid)
            if environ is None:
                continue
            if wanted in environ.split(b"\0"):
                with contextlib.suppress(psutil.Error):     # (gone meanwhile)
                    process = psutil.Process(pid)
                    if process.status() != psutil.STATUS_ZOMBIE:
                        found.append(process)
            elif not environ and _may_be_in_exec(pid):
                unsure.append(pid)
        if not unsure or (until is not None and time.monotonic() >= until):
            return found
        looking = unsure
        time.sleep(_SCAN_S / 4)


def _environ(pid: int) -> bytes | None:
    """Process ``pid``'s environment as it was given at its ``exec``; None if it is gone
    (or another user's)."""
    try:
        with open(f"/proc/{pid}/environ", "rb") as environ:
            return environ.read()
    except OSError:
        return None


def _may_be_in_exec(pid: int) -> bool:
    """Whether process ``pid``, which shows no environment, may be in the middle of an
    ``exec``: started less than ``_EXEC_S`` ago, and neither a zombie nor a kernel
    thread (which show none for good)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as stat:
            fields = stat.read().rpartition(b")")[2].split()
        with open("/proc/uptime", "rb") as uptime:
            now = float(uptime.read().split()[0])
    except OSError:
        return False
    # (after the name: state, ppid, pgrp, session, tty, tpgid, flags; its start, in
    # clock ticks since boot, is the 20th)
    started = int(fields[19]) / _TICKS_PER_S
    return fields[0] not in (b"Z", b"X") and not int(fields[6]) & _PF_KTHREAD \
        and now - started < _EXEC_S


def end(mark: str, timeout: float) -> bool:
    """SIGKILL every live process that carries ``mark``, looking again until none is
    left (one forked as the first look was made is found by the next); whether none was
    left within ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        alive = members(mark, deadline)
        if not alive:
            return True
        for process in alive:
            with contextlib.suppress(psutil.Error):      # (gone meanwhile)
                process.send_signal(signal.SIGKILL)
        if time.monotonic() >= deadline:
            return False
        time.sleep(_SCAN_S)
