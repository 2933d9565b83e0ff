"""Starting PB3A's own processes (workers, node executors) from any script, and
serving in one as the child of its owner."""

from __future__ import annotations

import contextlib
import signal
import threading
from multiprocessing import spawn as mp_spawn
from typing import Any

_start_lock = threading.Lock()


def start_without_main(process: Any) -> None:
    """Start a worker without re-running the user's ``__main__`` in it.

    multiprocessing re-imports the main script in every child, which breaks
    scripts without an ``if __name__ == "__main__"`` guard. Workers never need
    it: module classes travel with cloudpickle (by value when defined in main).
    """
    original = mp_spawn.get_preparation_data

    def preparation(name: str) -> dict[str, Any]:
        data = original(name)
        data.pop("init_main_from_path", None)
        data.pop("init_main_from_name", None)
        return data

    with _start_lock:
        mp_spawn.get_preparation_data = preparation
        try:
            process.start()
        finally:
            mp_spawn.get_preparation_data = original


def stop_on_sigterm(stopped: threading.Event) -> None:
    """From now on SIGTERM sets ``stopped``; SIGINT and SIGHUP are ignored (a terminal's:
    the parent decides). A child calls it first, before it makes anything it must
    close."""
    signal.signal(signal.SIGTERM, lambda *_: stopped.set())
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)


def serve_as_child(conn: Any, address: str, stopped: threading.Event) -> None:
    """In a child that serves at ``address`` (an executor, a robot server): tell the
    parent where (over ``conn``), then block until ``stopped`` is set, which SIGTERM
    and the parent's death (its end of ``conn`` closing) both do. Stopped already (a
    SIGTERM as it started), it returns at once: the parent reads no address."""
    stop_on_sigterm(stopped)
    if stopped.is_set():
        return
    conn.send(address)
    threading.Thread(target=_watch_parent, args=(conn, stopped), daemon=True,
                     name="pb3a-parent-watch").start()
    while not stopped.wait(1.0):                  # (a timed wait lets signal handlers run)
        pass


def _watch_parent(conn: Any, stopped: threading.Event) -> None:
    with contextlib.suppress(EOFError, OSError):
        conn.recv()                               # nothing is ever sent: EOF on death
    stopped.set()
