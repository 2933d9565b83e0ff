"""Shared fixtures: every test must leave no worker process and no shm segment behind."""

from __future__ import annotations

import collections
import contextlib
import errno
import multiprocessing.forkserver
import os
import random
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import pytest
import zmq

from pb3a.loading.served import ServedModuleFinder
from pb3a.transport.shm import live_segments

# Every process of the test run (workers inherit it) uses a throw-away cluster key,
# never the user's ~/.pb3a/cluster.key.
os.environ.setdefault("PB3A_KEY", os.urandom(32).hex())


def eventually(check: Callable[[], Any], timeout: float = 10.0, what: str = "condition",
               context: Callable[[], Any] | None = None) -> Any:
    """Poll ``check`` until it returns a truthy value; fail after ``timeout`` seconds,
    saying what ``context`` returns then (what to look at when it happens once in a
    hundred runs)."""
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if value:
            return value
        if time.monotonic() > deadline:
            seen = "" if context is None else f"; then {context()!r}"
            pytest.fail(f"timed out after {timeout} s waiting for {what}; last value "
                        f"{value!r}{seen}")
        time.sleep(0.02)


# The ports this worker gave out last (most recent at the end): not given again soon
_GIVEN_PORTS: collections.deque[int] = collections.deque(maxlen=500)


def unused_port() -> int:
    """A loopback port free now, for a process the test starts to listen at. It comes
    from below the kernel's ephemeral range, in a block of this pytest worker's own: a
    port the kernel handed out and took back (``bind(0)``, then close) could be given
    again, meanwhile, to any other worker's listener or connection, and was (a node
    controller answered a module server's test). Nor is a port given twice by one
    worker: two processes started side by side, neither listening yet, could both be
    given the same free port (``Daemon.several``: the second said "port in use")."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    block = int(worker[2:]) + 1 if worker.startswith("gw") else 0
    first = 16000 + 1500 * block                      # (gw0..gw9 end below 32000)
    for port in random.sample(range(first, first + 1500), 1500):
        if port in _GIVEN_PORTS:
            continue
        with socket.socket() as probe:
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                continue
            _GIVEN_PORTS.append(port)
            return port
    raise RuntimeError(f"no free port in {first}..{first + 1499}")


def assert_same_arrays(got: dict[str, Any], want: dict[str, Any]) -> None:
    """Each array in ``want`` is in ``got`` with the same dtype, shape, order and values."""
    for name, expected in want.items():
        array = got[name]
        assert (array.dtype, array.shape) == (expected.dtype, expected.shape), name
        assert array.flags.f_contiguous == expected.flags.f_contiguous, name
        assert np.array_equal(array, expected), name


def restart_after_kill(run: Any, name: str) -> tuple[list[Any], dict[str, Any], float]:
    """SIGKILL module ``name``'s worker and wait for its restart: the events from then
    (waiting for the first), its state once a new process has stepped it a few times,
    and the seconds that took."""
    since = max((event.seq for event in run.events()), default=0)
    old = eventually(lambda: run.stats().modules[name].pid, what="a worker pid")
    os.kill(old, signal.SIGKILL)
    killed = time.monotonic()
    events = run.events(since, timeout=5.0)
    state = eventually(lambda: (s := run.state(name, timeout=2.0))["pid"] not in (0, old)
                       and s["steps"] > 2 and s, timeout=5.0, what=f"the restarted {name} steps")
    return events, state, time.monotonic() - killed


def asked_as_it_restarts(run: Any, name: str) -> tuple[int, dict[str, Any]]:
    """SIGKILL module ``name``'s worker, then at once set its ``count`` and read its
    state (each with a 10 s timeout): the worker's pid before, and the state read."""
    old = eventually(lambda: run.stats().modules[name].pid, what="a worker pid")
    os.kill(old, signal.SIGKILL)
    run.set_state(name, {"count": 10**6}, timeout=10.0)
    return old, run.state(name, timeout=10.0)


def alive(pid: int) -> bool:
    """True while ``pid`` runs (a zombie waiting for its parent counts as gone)."""
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def end_process(process: subprocess.Popen, how: int = signal.SIGTERM,
                timeout: float = 15.0) -> None:
    """Ask ``process`` to end (``how``), wait ``timeout`` seconds for it, then kill it."""
    if process.poll() is None:
        process.send_signal(how)
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5)


def processes_naming(word: str) -> list[psutil.Process]:
    """The live processes whose command line holds ``word`` (a forkserver preloading a
    module file names it, and so do the workers forked from it), but this process's own
    forkserver, which lives as long as this process does, as a launcher's does."""
    own = multiprocessing.forkserver._forkserver._forkserver_pid
    found = []
    for process in psutil.process_iter(["cmdline"]):
        with contextlib.suppress(psutil.Error):
            if word in " ".join(process.info["cmdline"] or ()) and process.pid != own \
                    and process.status() != psutil.STATUS_ZOMBIE:
                found.append(process)
    return found


def kill_processes_naming(word: str) -> list[psutil.Process]:
    """SIGKILL every process ``processes_naming(word)`` finds (what a test that failed
    left behind), waiting for them a moment; those found."""
    found = processes_naming(word)
    for process in found:
        with contextlib.suppress(psutil.Error):
            process.kill()
    psutil.wait_procs(found, timeout=2.0)
    return found


@contextlib.contextmanager
def rave_started(*args: str, robots: int = 2) -> Iterator[list[str]]:
    """``rave start ARGS`` in a process of its own: the lines it prints (its world's,
    then each of its ``robots``'), then a SIGTERM it ends on with status 0."""
    process = subprocess.Popen([sys.executable, "-m", "rave.cli", "start", *args],
                               stdout=subprocess.PIPE, text=True)
    try:
        yield [process.stdout.readline().strip() for _ in range(1 + robots)]
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=15) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(5)
        process.stdout.close()


@contextlib.contextmanager
def frozen(*pids: int) -> Iterator[None]:
    """The processes ``pids`` stopped (SIGSTOP: as a hung or starved one) while inside."""
    for pid in pids:
        os.kill(pid, signal.SIGSTOP)
    try:
        yield
    finally:
        for pid in pids:
            os.kill(pid, signal.SIGCONT)


# Processes a fixture of a wider scope than a test keeps for many tests (the browser
# tests' Chromium, with Playwright's driver): they and their children are no test's
# leak; the fixture ends them itself. See ``shared_processes``.
_SHARED: set[int] = set()


@contextlib.contextmanager
def shared_processes(start: Callable[[], Any]) -> Iterator[Any]:
    """``start()`` (a context manager, entered here), with the child processes of this
    process that it starts kept out of the per-test check for leaks while inside: what
    it yields, for the tests that share it."""
    before = {child.pid for child in psutil.Process().children()}
    with start() as started:
        shared = {child.pid for child in psutil.Process().children()} - before
        _SHARED.update(shared)
        try:
            yield started
        finally:
            _SHARED.difference_update(shared)


def _workers() -> set[int]:
    me = psutil.Process()
    shared = set(_SHARED)
    for pid in _SHARED:
        with contextlib.suppress(psutil.Error):
            shared.update(child.pid for child in psutil.Process(pid).children(recursive=True))
    found = set()
    for child in me.children(recursive=True):
        if child.pid in shared:
            continue
        try:
            cmdline = " ".join(child.cmdline())
            helper = "forkserver" in cmdline or "resource_tracker" in cmdline
            if not helper and child.status() != "zombie":
                found.add(child.pid)
        except psutil.Error:
            continue
    return found


@pytest.fixture(autouse=True)
def no_module_servers_left() -> Iterator[None]:
    """A test that used module servers in this process leaves no finder behind that
    later imports would ask (and wait for, once the servers are gone)."""
    before = list(sys.meta_path)
    yield
    for finder in [f for f in sys.meta_path if f not in before]:
        if isinstance(finder, ServedModuleFinder):
            sys.meta_path.remove(finder)
            for client in finder.clients.values():
                client.close()


@pytest.fixture(autouse=True)
def no_leaks() -> Iterator[None]:
    """Fail a test that leaves worker processes or shared-memory segments behind."""
    before_pids = _workers()
    yield
    deadline = time.monotonic() + 10
    while True:
        leaked_pids = _workers() - before_pids
        leaked_segments = live_segments(os.getpid())
        if not leaked_pids and not leaked_segments:
            return
        if time.monotonic() > deadline:
            for pid in leaked_pids:
                with contextlib.suppress(psutil.Error):
                    psutil.Process(pid).kill()
            pytest.fail(f"leaked processes {sorted(leaked_pids)} / segments {leaked_segments}")
        time.sleep(0.05)


@pytest.fixture(autouse=True)
def zmq_still_carries() -> Iterator[None]:
    """Fails the test after which the process-global ZeroMQ context (every remote link
    and node request of the process) carries nothing any more, rather than every test
    after it. A monitor socket closed while the socket it watches is still monitored
    (no ``disable_monitor`` first) does that: ZeroMQ's I/O thread blocks for good
    sending it the next event (libzmq#3575); a test of the replication left one once,
    and under heavy load every hand-shake of the 23 tests after it timed out."""
    yield
    context = zmq.Context.instance()
    receiver, sender = context.socket(zmq.PAIR), context.socket(zmq.PAIR)
    try:
        for sock in (receiver, sender):
            sock.setsockopt(zmq.LINGER, 0)
        port = receiver.bind_to_random_port("tcp://127.0.0.1")
        sender.connect(f"tcp://127.0.0.1:{port}")
        sender.send(b"?")
        assert receiver.poll(10_000), ("ZeroMQ's process-global context carries nothing "
                                       "any more after this test: its I/O thread is blocked")
    finally:
        receiver.close()
        sender.close()


# The per-test check above sees only the segments of the test's own process; those of
# the processes it started elsewhere (a node controller's executor, its workers) are
# checked once, when the whole run is over: a segment made during the run whose owner
# is gone was left behind. (In pytest-xdist's controller, after every worker is done.)
_SEGMENTS_AT_START: set[str] = set()


def pytest_sessionstart(session: pytest.Session) -> None:
    _SEGMENTS_AT_START.update(live_segments())


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    if hasattr(session.config, "workerinput"):         # an xdist worker
        return
    left = [name for name in live_segments() if name not in _SEGMENTS_AT_START
            and not psutil.pid_exists(int(name.split("_")[1]))]
    if left:
        print(f"\nleft behind by processes of this run, now gone: segments {left}",
              file=sys.stderr)
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


class HeldKey:
    """A cluster key file that is a named pipe: a process started with ``env`` (or under
    it, for a spawned child) blocks in its start as it loads the key, until ``give``
    writes it. A deterministic point to signal a daemon at as it starts."""

    def __init__(self, directory: Path) -> None:
        self.path = directory / "cluster.key"
        os.mkfifo(self.path, 0o600)
        self.env = {**{k: v for k, v in os.environ.items() if k != "PB3A_KEY"},
                    "PB3A_KEY_FILE": str(self.path)}
        self._writer: int | None = None
        self._key = os.environ["PB3A_KEY"]

    def wait_for_reader(self, timeout: float = 30.0) -> None:
        """Return once a process is loading the key (it then waits for ``give``)."""
        deadline = time.monotonic() + timeout
        while self._writer is None:
            try:        # (a writer's open fails while no reader has the pipe open)
                self._writer = os.open(self.path, os.O_WRONLY | os.O_NONBLOCK)
            except OSError as exc:
                if exc.errno != errno.ENXIO or time.monotonic() > deadline:
                    raise
                time.sleep(0.01)

    def give(self) -> None:
        """Write the key and close: the reader goes on (if it is still there)."""
        assert self._writer is not None
        with contextlib.suppress(BrokenPipeError):
            os.write(self._writer, self._key.encode())
        os.close(self._writer)
        self._writer = None

    def users(self) -> list[int]:
        """The live processes started with this key (their children inherit it too), but
        this test process's own helpers (a spawn starts its resource tracker)."""
        workers = _workers()                # (children, but no helpers)
        found = []
        for process in psutil.process_iter():
            with contextlib.suppress(psutil.Error):
                if process.environ().get("PB3A_KEY_FILE") == str(self.path) \
                        and process.status() != psutil.STATUS_ZOMBIE \
                        and (process.ppid() != os.getpid() or process.pid in workers):
                    found.append(process.pid)
        return found


def daemon_signalled_as_it_starts(tmp_path: Path, *args: str) -> int:
    """Run ``pb3a ARGS`` (a daemon), SIGTERM it while it is starting (loading its key),
    and return its exit status, once it is seen to leave no process and no shared-memory
    segment behind. The process is killed if it does not end."""
    key = HeldKey(tmp_path)
    process = subprocess.Popen([sys.executable, "-m", "pb3a", *args],
                               stdout=subprocess.DEVNULL, env=key.env)
    try:
        key.wait_for_reader()
        process.send_signal(signal.SIGTERM)
        key.give()
        status = process.wait(timeout=20)
        assert not key.users() and not live_segments(process.pid)
        return status
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(5)


def daemon_banner_then_clean_exit(*args: str) -> str:
    """Run ``pb3a ARGS`` (a daemon), read the line it prints when ready, SIGTERM it, and
    check it exits 0; returns that line. The process is killed if anything fails."""
    process = subprocess.Popen([sys.executable, "-m", "pb3a", *args],
                               stdout=subprocess.PIPE, text=True)
    try:
        line = process.stdout.readline()
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=10) == 0
        return line
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(5)
        process.stdout.close()


class Daemon:
    """``pb3a node start`` in a process of its own, so that it can be killed and started
    again at the same address."""

    program: tuple[str, ...] = ("-m", "pb3a")     # (what a subclass runs in its place)
    cwd: str | None = None                          # where it is started (None: here)

    def __init__(self, name: str, path: tuple[str, ...] = (), *, ready: bool = True,
                 cwd: str | None = None) -> None:
        self.name, self.address = name, f"tcp://127.0.0.1:{unused_port()}"
        self.path = path            # more directories on its import path (a robot's own)
        self.cwd = cwd
        self.process: subprocess.Popen[str] | None = None
        self.start(ready)

    @classmethod
    def several(cls, *names: str, path: tuple[str, ...] = ()) -> dict[str, Daemon]:
        """Daemons ``names``, started side by side (each takes a moment to import); all
        stopped again if one does not come up."""
        made: dict[str, Daemon] = {}
        try:
            for name in names:
                made[name] = cls(name, path, ready=False)
            for daemon in made.values():
                daemon.ready()
        except BaseException:
            for daemon in made.values():
                daemon.stop()
            raise
        return made

    def start(self, ready: bool = True, key: str | None = None) -> None:
        """Start it; with ``ready``, return once it says where it listens (else ``ready``);
        ``key``: a cluster key of its own (the tests' otherwise)."""
        repo = Path(__file__).resolve().parent.parent
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(repo / "tests"), str(repo),
                                                            *self.path])}
        if key is not None:
            env["PB3A_KEY"] = key
        self.process = subprocess.Popen(
            [sys.executable, *self.program, "node", "start", "--name", self.name,
             "--listen", self.address, "--max-cpu", "101"],
            stdout=subprocess.PIPE, text=True, env=env, cwd=self.cwd)
        if ready:
            self.ready()

    def ready(self) -> None:
        """Wait for the line it prints once it listens."""
        assert self.process.stdout.readline().strip() == f"node {self.name} at {self.address}"

    def executor_pid(self) -> int:
        """The pid of the one executor this controller runs."""
        (executor,) = [child for child in psutil.Process(self.process.pid).children()
                       if "resource_tracker" not in " ".join(child.cmdline())]
        return executor.pid

    def kill(self) -> None:
        self.process.kill()
        self.process.wait(10)
        self.process.stdout.close()

    def stop(self) -> None:
        end_process(self.process)
        self.process.stdout.close()
