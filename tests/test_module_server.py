"""The module server: code on demand, new and changed files without a restart,
reload with the state kept, and nothing served from outside its directory."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import textwrap
import time
import types
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import (
    daemon_banner_then_clean_exit,
    daemon_signalled_as_it_starts,
    eventually,
    unused_port,
)

from pb3a import RuntimeFailure, System
from pb3a.daemons.module_server import ModuleServer
from pb3a.loading import served as served_code
from pb3a.loading.references import resolve_class
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient

TICKER = '''
from pb3a import Module, Output

class Ticker(Module):
    out = Output(int)
    period = 0.005
    count = 0
    step_size = 1

    def step(self):
        self.count += self.step_size * {factor}     # the code, not the state, changes
'''


@pytest.fixture
def served(tmp_path):
    root = tmp_path / "code"
    root.mkdir()
    server = ModuleServer(root, ClusterKey.load())
    yield root, server
    server.close()


def _write(path: Path, text: str) -> None:
    path.write_text(textwrap.dedent(text))
    os.utime(path)                             # (a new mtime, whatever the clock's grain)


def _served_ticker(root: Path, server: str) -> System:
    """A system of one ticker ``t``, whose class only the module server at ``server``
    has (written into its directory ``root``)."""
    _write(root / "pb3a_served_ticker.py", TICKER.format(factor=1))
    return System("served", module_servers=[server]).add("t", "pb3a_served_ticker:Ticker")


def test_a_class_only_the_server_has_runs_and_a_changed_file_is_swapped_in(served) -> None:
    root, server = served
    with _served_ticker(root, server.address).launch() as run:
        eventually(lambda: run.state("t")["count"] > 5, what="the served class stepping")
        _write(root / "pb3a_served_ticker.py", TICKER.format(factor=1000))
        run.reload("pb3a_served_ticker")
        before = run.state("t")["count"]
        run.swap("t", "pb3a_served_ticker:Ticker")       # the new file, state kept
        eventually(lambda: run.state("t")["count"] >= before + 2000,
                   what="the new code stepping, from the count the old one reached")


def test_new_files_are_served_without_a_restart(served) -> None:
    root, server = served
    assert server.find("pb3a_served_new") is None
    _write(root / "pb3a_served_new.py", "VALUE = 42\n")
    found = server.find("pb3a_served_new")
    assert found is not None and b"VALUE = 42" in found["source"]
    (root / "pkg").mkdir()
    _write(root / "pkg" / "__init__.py", "")
    _write(root / "pkg" / "inner.py", "X = 1\n")
    assert server.find("pkg")["package"] and not server.find("pkg.inner")["package"]


def test_nothing_outside_the_directory_is_served(served, tmp_path) -> None:
    root, server = served
    secret = tmp_path / "secret.py"
    secret.write_text("PASSWORD = 'x'\n")
    (root / "escape.py").symlink_to(secret)
    (root / "escdir").symlink_to(tmp_path)
    for name in ("escape", "escdir.secret", "..secret", "../secret", "/etc/passwd", "",
                 "os.path", "a..b"):
        assert server.find(name) is None, name


def test_list_names_every_module_it_serves_and_nothing_outside(served, tmp_path) -> None:
    root, server = served
    _write(root / "top.py", "")
    (root / "pkg" / "sub").mkdir(parents=True)
    _write(root / "pkg" / "__init__.py", "")
    _write(root / "pkg" / "sub" / "leaf.py", "")
    _write(root / "not-a-name.py", "")                 # no import can name it
    (tmp_path / "secret.py").write_text("")
    (root / "escape.py").symlink_to(tmp_path / "secret.py")
    client = ControlClient(ClusterKey.load(), server.address)
    try:
        assert client.call("list", timeout=5.0) == ["pkg", "pkg.sub.leaf", "top"]
    finally:
        client.close()
    assert all(server.find(name) is not None for name in server.names())


def test_the_command_line_serves_until_signalled(tmp_path) -> None:
    (tmp_path / "m.py").write_text("X = 1\n")
    line = daemon_banner_then_clean_exit("modules", "serve", str(tmp_path),
                                         "--listen", "tcp://127.0.0.1:0")
    assert line.startswith(f"serving {tmp_path.resolve()} at tcp://127.0.0.1:")


def test_a_daemon_whose_reader_is_gone_serves_on_and_stops_cleanly(tmp_path) -> None:
    """A script that starts a daemon and closes its end of the daemon's output (or a
    ``| head`` that has its line) once ended the daemon in a traceback as it printed
    where it listens."""
    port = unused_port()
    process = subprocess.Popen(
        [sys.executable, "-m", "pb3a", "modules", "serve", str(tmp_path),
         "--listen", f"tcp://127.0.0.1:{port}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        process.stdout.close()                       # gone before the daemon's first line
        client = ControlClient(ClusterKey.load(), f"tcp://127.0.0.1:{port}")
        try:
            # (it prints where it listens as its server starts, before it can answer)
            assert client.call("list", timeout=20.0) == []
        finally:
            client.close()
        process.send_signal(signal.SIGTERM)
        assert "Traceback" not in process.stderr.read()
        assert process.wait(timeout=10) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(5)
        process.stderr.close()


def test_a_module_server_signalled_as_it_starts_stops_cleanly(tmp_path) -> None:
    (tmp_path / "served").mkdir()
    assert daemon_signalled_as_it_starts(tmp_path, "modules", "serve", str(tmp_path / "served"),
                                         "--listen", "tcp://127.0.0.1:0") == 0


def test_a_module_server_that_does_not_answer_holds_up_one_import_not_every_one(
        monkeypatch) -> None:
    """The finder's clock runs ahead on demand, so "29 s later" and "31 s later" cost
    no waiting (a window of a fraction of a second had passed unseen)."""
    monkeypatch.setattr(served_code, "FIND_TIMEOUT", 0.3)
    ahead = [0.0]                                       # seconds the finder's clock is ahead
    monkeypatch.setattr(served_code, "time", types.SimpleNamespace(
        monotonic=lambda: time.monotonic() + ahead[0]))
    finder = served_code.ServedModuleFinder(ClusterKey.load())
    finder.add("tcp://127.0.0.1:9")                   # nobody listens there
    try:
        waits = []
        for later in (0.0, 0.0, 0.0, 29.0, 31.0):
            ahead[0] = later
            started = time.monotonic()
            assert finder.find_spec("pb3a_nowhere") is None
            waits.append(time.monotonic() - started)
    finally:
        for client in finder.clients.values():
            client.close()
    assert 0.3 <= waits[0] < 0.6, waits                # the timeout, not a multiple of it
    assert max(waits[1:4]) < 0.05, waits               # not asked again within 30 s ...
    assert waits[4] >= 0.3, waits                      # ... but after them


@contextlib.contextmanager
def _importing_from(address: str, key: ClusterKey, monkeypatch) -> Iterator[None]:
    """This process imports from the module server at ``address`` too, for the test."""
    finder = served_code.ServedModuleFinder(key)
    finder.add(address)
    monkeypatch.setattr(sys, "meta_path", [*sys.meta_path, finder])
    try:
        yield
    finally:
        for client in finder.clients.values():
            client.close()


def test_a_class_that_cannot_be_imported_names_the_module_server_that_did_not_answer(
        monkeypatch) -> None:
    """It said only to check the module path, with the server it needed down."""
    monkeypatch.setattr(served_code, "FIND_TIMEOUT", 0.3)
    with _importing_from("tcp://127.0.0.1:9", ClusterKey.load(), monkeypatch), \
            pytest.raises(ImportError, match=r"module server tcp://127.0.0.1:9 did not "
                                             "answer: start it"):    # (nobody listens there)
        resolve_class("pb3a_nowhere_served:Thing")


def test_a_module_server_whose_port_refuses_connections_is_given_up_on_within_2_s(
        monkeypatch) -> None:
    """With the module server stopped, an add waited the finder's whole 5 s (and the
    check before it in a child process, 5 more: 12.6 s in an operator's review) to say
    that it did not answer, though the connection was refused at once."""
    with _importing_from(f"tcp://127.0.0.1:{unused_port()}", ClusterKey.load(),
                         monkeypatch):
        started = time.monotonic()
        with pytest.raises(ImportError, match=r"did not answer: start it"):
            resolve_class("pb3a_nowhere_served:Thing")
        assert time.monotonic() - started < 2.5


def test_a_class_the_module_server_does_not_have_names_the_server_and_the_file_to_put(
        served, monkeypatch) -> None:
    """A module file missing from the server's directory (copied elsewhere, misspelt)
    said only to check this machine's module path, where a module meant to be served
    was never to be; the server that answered without it is named, and the file it
    needs, a package's module too."""
    root, server = served
    (root / "pb3a_served_pkg").mkdir()
    (root / "pb3a_served_pkg" / "__init__.py").write_text("")
    for name in ("pb3a_served_absent", "pb3a_served_pkg"):    # (imported here: not kept)
        monkeypatch.delitem(sys.modules, name, raising=False)
    with _importing_from(server.address, ClusterKey.load(), monkeypatch):
        with pytest.raises(ImportError, match=rf"No module named 'pb3a_served_absent'; check "
                           rf"the module path .*; module server {server.address} has no module "
                           r"'pb3a_served_absent' either: put pb3a_served_absent\.py \(or "
                           r"pb3a_served_absent/__init__\.py\) in the directory it serves"):
            resolve_class("pb3a_served_absent:Thing")
        with pytest.raises(ImportError, match=rf"module server {server.address} has no module "
                           r"'pb3a_served_pkg\.absent' either: put pb3a_served_pkg/absent\.py"):
            resolve_class("pb3a_served_pkg.absent:Thing")
        (root / "pb3a_served_absent.py").write_text("class Thing:\n    pass\n")
        assert resolve_class("pb3a_served_absent:Thing").__name__ == "Thing"


def test_a_module_server_whose_host_does_not_resolve_here_is_named_so(monkeypatch) -> None:
    """A server named by a host name this machine does not resolve (the workstation's
    /etc/hosts has it, a robot's not) was said not to answer: "start it, or check its
    address and that its port is open", though it ran and answered the workstation."""
    monkeypatch.setattr(served_code, "FIND_TIMEOUT", 0.3)
    with _importing_from("tcp://no-such-host.invalid:7300", ClusterKey.load(), monkeypatch), \
            pytest.raises(ImportError, match=r"module server tcp://no-such-host\.invalid:7300 is "
                                             r"not reached from this machine: no address is "
                                             r"known for host 'no-such-host\.invalid'.*give "
                                             r"module_servers a name every node's machine "
                                             r"resolves, or an IP address"):
        resolve_class("pb3a_nowhere_served:Thing")


def test_a_module_server_whose_host_does_not_resolve_here_is_given_up_on_within_2_s(
        monkeypatch) -> None:
    """An import waited the finder's whole 5 s for a server whose host has no address
    here, though no answer could come (a launch whose node could not import a class
    said so 5 s late)."""
    with _importing_from("tcp://no-such-host.invalid:7300", ClusterKey.load(), monkeypatch):
        started = time.monotonic()
        with pytest.raises(ImportError, match=r"no address is known for host"):
            resolve_class("pb3a_nowhere_served:Thing")
        assert time.monotonic() - started < 2.5


def test_a_class_that_cannot_be_imported_names_the_module_server_that_refused_the_key(
        tmp_path, monkeypatch) -> None:
    """A server with another cluster key has the module, but refuses to say: it said
    only to check the module path, as if no server were involved."""
    root = tmp_path / "code"
    root.mkdir()
    (root / "pb3a_served_elsewhere.py").write_text("class Thing:\n    pass\n")
    server = ModuleServer(root, ClusterKey.from_material(b"k" * 32))
    try:
        with _importing_from(server.address, ClusterKey.from_material(b"j" * 32), monkeypatch), \
                pytest.raises(ImportError, match=rf"module server {server.address} refused "
                                                 "'find': it runs with another cluster key"):
            resolve_class("pb3a_served_elsewhere:Thing")
    finally:
        server.close()


def test_a_class_a_worker_cannot_import_names_the_module_server_that_did_not_answer(
        served) -> None:
    """In a worker too (an add, a restart, a swap): its error said only which module
    was not found, with the server it needed gone."""
    root, server = served
    with _served_ticker(root, server.address).launch() as run:
        eventually(lambda: run.state("t")["count"] > 5, what="the served class stepping")
        server.close()                             # the server's host is gone
        with pytest.raises(RuntimeFailure, match=rf"No module named 'pb3a_served_ticker'; "
                           rf"module server {server.address} did not answer: start it"):
            run.add("t2", "pb3a_served_ticker:Ticker", timeout=30)
