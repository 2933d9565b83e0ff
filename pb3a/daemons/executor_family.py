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


def new_mark() -> str:
    """A mark no other executor's family carries."""
    return secrets.token_hex(8)


def take_mark(mark: str) -> None:
    """Mark this process (an executor, before it starts any) and, through the
    environment they inherit, every process it starts from now on."""
    os.environ[MARK] = mark


def members(mark: str) -> list[psutil.Process]:
    """The live processes that carry ``mark`` (a zombie runs nothing: left out)."""
    wanted = f"{MARK}={mark}".encode()
    found = []
    for pid in psutil.pids():
        try:
            with open(f"/proc/{pid}/environ", "rb") as environ:
                if wanted not in environ.read().split(b"\0"):
                    continue
            process = psutil.Process(pid)
            if process.status() != psutil.STATUS_ZOMBIE:
                found.append(process)
        except (OSError, psutil.Error):        # gone meanwhile, or another user's
            continue
    return found


def end(mark: str, timeout: float) -> bool:
    """SIGKILL every live process that carries ``mark``, looking again until none is
    left (one forked as the first look was made is found by the next); whether none was
    left within ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        alive = members(mark)
        if not alive:
            return True
        for process in alive:
            with contextlib.suppress(psutil.Error):      # (gone meanwhile)
                process.send_signal(signal.SIGKILL)
        if time.monotonic() >= deadline:
            return False
        time.sleep(_SCAN_S)
