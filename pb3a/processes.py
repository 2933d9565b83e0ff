"""Starting PB3A's own processes (workers, node executors) from any script, and
serving in one as the child of its owner."""

from __future__ import annotations

import atexit
import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator
from multiprocessing import resource_tracker
from multiprocessing import spawn as mp_spawn
from typing import Any

from pb3a.errors import RuntimeTimeout

_start_lock = threading.Lock()
# What PB3A started this process as ("a worker", "a node's executor"); None in a process
# of the user's own. Fork copies it: a worker forked from a marked forkserver is marked.
_role: str | None = None


def mark_as(role: str) -> None:
    """Mark this process as one PB3A started, ``role`` saying which (a worker, a
    forkserver, a node's executor): ``System.launch`` refuses to run in it."""
    global _role
    _role = role


def role() -> str | None:
    """What PB3A started this process as; None in a process of the user's own."""
    return _role


# Set, with PYTHONSAFEPATH, by a ``pb3a`` command for the Python processes it starts: the
# workers' forkserver starts with ``python -c``, which puts the current directory first
# on its path, and a user's ``random.py`` there broke its start (multiprocessing imports
# ``tempfile``, which imports ``random``). The forkserver drops both as it preloads, so
# a worker's own children (a driver's legacy program) get the environment the user had.
_SAFE_PATH_SET = "PB3A_SET_PYTHONSAFEPATH"


def children_skip_the_current_directory() -> None:
    """Have the Python processes this one starts from now on leave the current
    directory off the front of their import path (``-P``), unless the user chose."""
    if not sys.flags.safe_path and not os.environ.get("PYTHONSAFEPATH"):
        os.environ.update({"PYTHONSAFEPATH": "1", _SAFE_PATH_SET: "1"})


# Set in the process of a ``pb3a`` command: it runs no script of the user's, and its
# ``sys.path[0]`` is the command's own directory, none that a system's nodes import from.
_a_command = False


def runs_a_command() -> None:
    """Mark this process as a ``pb3a`` command's (``pb3a.loading.sources.launcher_paths``)."""
    global _a_command
    _a_command = True


def runs_a_script() -> bool:
    """Whether ``sys.path[0]`` is the directory of a script of the user's (or their
    current one: ``python -m``, ``-c``, the REPL), as in any process not a command's."""
    return not _a_command


def restore_the_user_s_path_setting() -> None:
    """Undo ``children_skip_the_current_directory`` for this process's children."""
    if os.environ.pop(_SAFE_PATH_SET, None):
        os.environ.pop("PYTHONSAFEPATH", None)


# What a terminal (Ctrl-C, closing) or a supervisor sends the whole process group: a
# Python child that takes one as its interpreter starts, before its own handlers are set,
# dies of it with a crash dump or a traceback on the terminal.
TERMINAL_SIGNALS = frozenset({signal.SIGINT, signal.SIGTERM, signal.SIGHUP})
INTERRUPTED = 130       # the shell's status of a program a Ctrl-C ended (128 + SIGINT)


@contextlib.contextmanager
def terminal_signals_held() -> Iterator[None]:
    """Hold off ``TERMINAL_SIGNALS`` in the calling thread while it starts a Python child:
    the child inherits the block across exec and takes them once its handlers are set
    (``take_terminal_signals``). Only this thread's mask changes, for the block alone:
    this process's handlers stay as they are, and a signal sent to it meanwhile goes to
    another thread or waits for the block's end, never lost."""
    held = signal.pthread_sigmask(signal.SIG_BLOCK, TERMINAL_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)


def take_terminal_signals() -> None:
    """In a child started in ``terminal_signals_held``, its handlers set: take
    ``TERMINAL_SIGNALS`` again (one that came as it started is handled now, by them; an
    ignored one is dropped)."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, TERMINAL_SIGNALS)


def end_on_signals(status: int) -> None:
    """From now on Ctrl-C, SIGTERM or SIGHUP ends this program at once with ``status``,
    decided already (what it wrote flushed first): for a program whose work is done and
    that is only exiting. Ignored, a stuck exit (a thread a module file started, which
    Python's exit waits for) could only be killed; at Python's default, a second Ctrl-C
    killed a clean stop by SIGINT as it exited. Once those threads are joined, the
    signals are ignored for the rest of the exit (Python puts a handler of its own back
    to the default as it ends, and a SIGHUP then killed it)."""
    def end(signum: int, frame: object) -> None:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(status)

    for signum in TERMINAL_SIGNALS:
        signal.signal(signum, end)
    atexit.register(_ignore_terminal_signals)     # (run after the threads are joined)


def _ignore_terminal_signals() -> None:
    for signum in TERMINAL_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)


def start_resource_tracker() -> None:
    """Start multiprocessing's resource tracker, if none runs, with ``TERMINAL_SIGNALS``
    held off: it ignores SIGINT and SIGTERM and takes them back, but keeps SIGHUP held
    (a terminal closing killed it, and the one that replaced it printed a traceback for
    each segment freed that it had not heard of). Call it before a start held off
    (``terminal_signals_held``) that would start the tracker: multiprocessing's own
    start of it gives SIGINT and SIGTERM back to the thread that started it."""
    with terminal_signals_held():
        resource_tracker.ensure_running()


def start_without_main(process: Any, timeout: float | None = None) -> None:
    """Start a worker without re-running the user's ``__main__`` in it.

    multiprocessing re-imports the main script in every child, which breaks
    scripts without an ``if __name__ == "__main__"`` guard. Workers never need
    it: module classes travel with cloudpickle (by value when defined in main).

    With a ``timeout``, a start that has not returned within it raises
    ``RuntimeTimeout``: a forkserver that is frozen (stopped, hung) answers no
    request for a process, and ``Process.start`` would wait for it for good, holding
    whatever its caller holds (a change's configuration lock). The start given up on
    goes on in the background; if a process comes of it, it is killed.
    """
    if timeout is None:
        _start(process)
        return
    done, outcome = threading.Event(), []
    decided = threading.Lock()

    def start() -> None:
        try:
            _start(process)
        except BaseException as exc:          # (given to the caller, if it still waits)
            outcome.append(exc)
        with decided:
            done.set()
            abandoned = given_up.is_set() and not outcome
        if abandoned:
            with contextlib.suppress(OSError, ValueError, AttributeError):
                process.kill()
                process.join(1.0)

    given_up = threading.Event()
    threading.Thread(target=start, daemon=True, name="pb3a-start").start()
    try:
        done.wait(timeout)
    finally:                        # (a Ctrl-C as it waits gives up too: the process,
        with decided:               # if one comes, is nobody's)
            late = not done.is_set()
            if late:
                given_up.set()
    if late:
        raise RuntimeTimeout(f"no process started within {timeout:g} s: the forkserver "
                             "that starts this node's workers does not answer (stopped "
                             "or hung?)")
    if outcome:
        raise outcome[0]


def _start(process: Any) -> None:
    def preparation(name: str) -> dict[str, Any]:
        data = original(name)
        data.pop("init_main_from_path", None)
        data.pop("init_main_from_name", None)
        return data

    with _start_lock:
        # (read under the lock: read before it, as another start had its own put in, it
        # was that one, put back for good once this start ended: each overlap of two
        # starts chained one more, and a process that launched some 300 systems could
        # start none, RecursionError)
        original = mp_spawn.get_preparation_data
        mp_spawn.get_preparation_data = preparation
        try:
            process.start()
        finally:
            mp_spawn.get_preparation_data = original


def stop_on_sigterm(stopped: threading.Event) -> None:
    """From now on SIGTERM sets ``stopped``; SIGINT and SIGHUP are ignored (a terminal's:
    the parent decides). A child calls it first, before it makes anything it must
    close; started held off (``terminal_signals_held``), it takes them from here."""
    signal.signal(signal.SIGTERM, lambda *_: stopped.set())
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    take_terminal_signals()


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
