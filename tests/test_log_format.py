"""Every PB3A process writes its log lines in one format (``pb3a/log_format.py``): the
date and time to the millisecond, the level, the process, the logger, the message. The
launcher printed ``09:40:26 ERROR pb3a.module: ...`` and a node's executor
``2026-12-05 09:40:29,599 pb3a[lab@b] ERROR ...``: read side by side, the lines of
several machines could not be sorted nor told apart. Under systemd the journal stamps
each line itself: the time is left out, the syslog priority put first."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import end_process, eventually, unused_port
from sample_modules import Chatty

from pb3a import System
from pb3a.cli.main import main
from pb3a.logbook import LogBook, LogEntry
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient

REPO = Path(__file__).resolve().parent.parent
START_TIMEOUT = 30.0        # for a command to print what it prints once it runs
STOP_TIMEOUT = 20.0

pytestmark = pytest.mark.timeout(120)

STAMP = r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3} "      # 2026-12-05 09:40:29.599
# what Chatty's worker logs, as the process that prints it writes it
WORKER_SAYS = (r"WARNING \[{process}\] chatty: \[worker {node}/\S+\] "
               r"hello from a module's own logger")

CHATTY = """\
name = "chat"

[nodes.local]

[modules.chatty]
class = "sample_modules:Chatty"
"""


def _env(**more: str) -> dict[str, str]:
    env = {key: value for key, value in os.environ.items() if key != "JOURNAL_STREAM"}
    return {**env, "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), str(REPO)]), **more}


def _read_until(stream, pattern: str, timeout: float) -> list[str]:
    """The lines ``stream`` gives up to one matching ``pattern`` (all it gave, if none
    did within ``timeout``), read on a thread of its own."""
    lines: list[str] = []
    found = threading.Event()

    def read() -> None:
        for text in stream:
            lines.append(text.rstrip("\n"))
            if re.fullmatch(pattern, lines[-1]):
                found.set()
                return
    threading.Thread(target=read, daemon=True).start()
    found.wait(timeout)
    return list(lines)


def test_the_launcher_prints_a_worker_s_record_dated_to_the_millisecond_with_its_process(
        tmp_path: Path) -> None:
    config = tmp_path / "chat.toml"
    config.write_text(CHATTY)
    run = subprocess.Popen([sys.executable, "-m", "pb3a", "run", str(config)], cwd=tmp_path,
                           env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                           text=True)
    try:
        wanted = STAMP + WORKER_SAYS.format(process="launcher@local", node="local")
        lines = _read_until(run.stderr, wanted, START_TIMEOUT)
        assert lines and re.fullmatch(wanted, lines[-1]), lines
    finally:
        end_process(run, signal.SIGINT, STOP_TIMEOUT)
        run.stderr.close()


@pytest.fixture
def controller(tmp_path: Path, request: pytest.FixtureRequest
               ) -> Iterator[tuple[str, Path, bool]]:
    """``pb3a node start --name b``, its stderr (and its executors') in a file; with
    ``journal``, that file is the journal's stream as systemd names it. Its address, the
    file and whether it is the journal's."""
    address = f"tcp://127.0.0.1:{unused_port()}"
    written = tmp_path / "node-b.log"
    with written.open("w") as stderr:
        status = os.fstat(stderr.fileno())
        env = _env(JOURNAL_STREAM=f"{status.st_dev}:{status.st_ino}") if request.param \
            else _env()
        daemon = subprocess.Popen(
            [sys.executable, "-m", "pb3a", "node", "start", "--name", "b", "--listen",
             address, "--max-cpu", "101"],
            env=env, stdout=subprocess.PIPE, stderr=stderr, text=True)
    try:
        said = _read_until(daemon.stdout, "node b at .*", START_TIMEOUT)
        assert said == [f"node b at {address}"], (said, written.read_text())
        yield address, written, request.param
    finally:
        end_process(daemon, timeout=STOP_TIMEOUT)
        daemon.stdout.close()


@pytest.mark.parametrize("controller", [False, True], ids=["terminal", "journal"],
                         indirect=True)
def test_a_node_controller_and_its_executor_write_the_one_format(
        controller: tuple[str, Path, bool], capsys: pytest.CaptureFixture[str]) -> None:
    """The controller's own records and those its executor logs for its workers name the
    process and the node; under the journal they start with the syslog priority and
    carry no time (the journal's own is more precise). ``pb3a logs`` shows a node's
    record as that node's executor wrote it."""
    address, written, journal = controller
    stamp, priority = ("", "<4>") if journal else (STAMP, "")
    # a request made with another cluster key: the controller logs the refusal
    stranger = ControlClient(ClusterKey.from_material(os.urandom(32)), address)
    try:
        with pytest.raises(Exception, match="another cluster key"):
            stranger.call("ping", 5.0)
    finally:
        stranger.close()
    refused = (f"{priority}{stamp}WARNING \\[controller@b\\] pb3a.control: "
               f"{re.escape(address)} refused a request from .*")
    system = System("chat").node("a").node("b", address=address)
    system.add("chatty", Chatty, node="b")
    with system.launch() as run:
        executor = priority + stamp + WORKER_SAYS.format(process="executor chat@b", node="b")
        eventually(lambda: _matching(written, executor), timeout=30,
                   what=f"the executor's line in the node's log: {written.read_text()!r}")
        assert _matching(written, refused), written.read_text()
        entry = eventually(lambda: next((e for e in run.logs() if e.logger == "chatty"), None),
                           timeout=30, what="node b's record in the launcher's log")
        assert entry.node == "b" and entry.process == "executor chat@b"
        assert main(["logs", run.listen()]) == 0
        shown = capsys.readouterr().out.splitlines()
    # `pb3a logs` writes the record as the executor did, dated (it is read later)
    assert any(re.fullmatch(STAMP + WORKER_SAYS.format(process="executor chat@b", node="b"),
                            line) for line in shown), shown
    assert not journal or not _matching(written, f"(<\\d>)?{STAMP}.*"), written.read_text()


def _matching(written: Path, pattern: str) -> bool:
    return any(re.fullmatch(pattern, line) for line in written.read_text().splitlines())


def test_followers_of_a_quiet_module_cost_a_flood_of_other_entries_little() -> None:
    """Each follower woken by a new entry looked through all 5,000 kept, under the lock
    every record takes: eight following a quiet module beside one logging 8,000 lines a
    second took 60 % of the launcher's core. They look only at what came since."""
    book = LogBook()
    for _ in range(5000):
        book.add(time.time(), "INFO", "chatter", "noise", module="chat")
    done = threading.Event()
    heard: list[list[LogEntry]] = []
    cpu: list[float] = []

    def follow() -> None:
        seq, began = 5000, time.thread_time()
        while not done.is_set():
            if found := book.since(seq, timeout=0.5, module="quiet"):
                heard.append(found)
                break
        cpu.append(time.thread_time() - began)
    followers = [threading.Thread(target=follow) for _ in range(4)]
    for follower in followers:
        follower.start()
    started = time.monotonic()
    for _ in range(2000):                        # (a flood comes over time: each wakes them)
        book.add(time.time(), "INFO", "chatter", "noise", module="chat")
        time.sleep(0.0002)
    flood_s = time.monotonic() - started
    said = book.add(time.time(), "WARNING", "quiet", "at last", module="quiet")
    for follower in followers:
        follower.join(5)
    done.set()
    assert heard == [[said]] * 4
    assert sum(cpu) < 0.3, f"4 followers took {sum(cpu):.2f} s of CPU ({flood_s:.1f} s)"
