"""A live change naming a class whose module file harms whoever imports it: the running
system's launcher tries the import in a child process first, refuses the change saying
what happened, and runs on; a class it has imported already costs no process."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
import urllib.error
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import alive, eventually
from sample_modules import ChangesToAClass, Counter, FloatSource, Scale

from pb3a import ConfigError, RuntimeFailure, System, connect

pytestmark = pytest.mark.timeout(120)

REPO = Path(__file__).resolve().parent.parent

# Module files that harm whoever imports them, each ending in a class ``Bad`` that could
# replace ``Scale``; ``imported_hangs`` starts a process first and writes its pid to
# ``started.pid``; ``launcher_hangs`` hangs only where PB3A_TEST_HANG_HERE is set.
HARMFUL = {
    "imported_hangs": """
        import pathlib, subprocess
        started = subprocess.Popen(["sleep", "600"])
        pathlib.Path("started.pid").write_text(str(started.pid))
        while True:
            pass
        """,
    "imported_ends": "import os\nos._exit(3)\n",
    "imported_crashes": "import ctypes\nctypes.string_at(0)\n",
    "launcher_hangs": """
        import os
        while os.environ.get("PB3A_TEST_HANG_HERE"):
            pass
        """,
    "imported_fine": "",
}
BAD = """
    from pb3a import Input, Module, Output

    class Bad(Module):
        x = Input(float)
        y = Output(float)
        gain = 1.0
    """

# The launcher: a source feeding a Scale, listening; it prints its address, then runs
# until its stdin closes. Its operations wait 2 s unless told otherwise.
LAUNCHER = """
import sys
from sample_modules import FloatSource, Scale
from pb3a import System
system = System("harmed").add("src", FloatSource).add("scale", Scale).link("src.out", "scale.x")
with system.launch(timeout=2.0) as run:
    print(run.listen(), flush=True)
    sys.stdin.read()
"""


def _harmful_files(directory: Path) -> None:
    for name, head in HARMFUL.items():
        (directory / f"{name}.py").write_text(textwrap.dedent(head) + textwrap.dedent(BAD))


def _env(directory: Path, **more: str) -> dict[str, str]:
    path = os.pathsep.join([str(directory), str(REPO / "tests"), str(REPO)])
    return {**os.environ, "PYTHONPATH": path, **more}


@pytest.fixture
def launcher(tmp_path: Path) -> Iterator[str]:
    """A running system's launcher in a process of its own (a crash there must not end
    the test), beside the harmful module files; its address."""
    _harmful_files(tmp_path)
    process = subprocess.Popen([sys.executable, "-c", LAUNCHER], cwd=tmp_path, text=True,
                               env=_env(tmp_path, PB3A_TEST_HANG_HERE="1"),
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        address = _first_line(process, 30)
        assert address.startswith("tcp://"), address
        yield address
    finally:
        _pid_file_killed(tmp_path)
        with contextlib.suppress(OSError):
            process.stdin.close()
        try:
            process.wait(20)
        except subprocess.TimeoutExpired:           # (the old launcher: its import hangs)
            process.kill()
            process.wait(5)
        process.stdout.close()


def _first_line(process: subprocess.Popen[str], timeout: float) -> str:
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.append(process.stdout.readline()),
                              daemon=True)
    reader.start()
    reader.join(timeout)
    return lines[0].strip() if lines else ""


def _pid_file_killed(directory: Path) -> int | None:
    """The pid ``imported_hangs`` wrote, its process killed if it still runs (the old
    launcher left it running)."""
    pid_file = directory / "started.pid"
    started = int(pid_file.read_text()) if pid_file.exists() else None
    with contextlib.suppress(ProcessLookupError):
        if started is not None and alive(started):
            os.kill(started, signal.SIGKILL)
    return started


def pb3a(*args: str, cwd: Path) -> tuple[subprocess.CompletedProcess[str], float]:
    """The command line in a process of its own, run from ``cwd`` (where the harmful files
    are: ``pb3a add`` imports the class there too); and how long it took."""
    began = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "pb3a", *args], cwd=cwd, env=_env(cwd),
                          capture_output=True, text=True, timeout=60, check=False)
    return done, time.monotonic() - began


def test_swap_and_add_to_a_module_file_that_hangs_ends_or_crashes_as_imported_are_refused(
        launcher: str, tmp_path: Path) -> None:
    """The launcher imported the class a change names in its own process: a module file
    that looped as it was imported held the request for good (and the launcher's lane
    behind it: every later `pb3a status` went unanswered), one that called os._exit() or
    crashed ended the launcher and the whole system, without a word. Each change is now
    refused within its timeout, naming the module and what happened, nothing changed,
    and the system answers the next request. `pb3a add --state` imported the class in
    its own process too, and hung there."""
    said = []
    for args, took_at_most in (
            (["swap", launcher, "scale", "imported_hangs:Bad", "--timeout", "2"], 6),
            # (10 s: with the system's 2 s, a start slowed by two busy loops beside the
            # test run left the crash too little time, and it was taken to hang)
            (["swap", launcher, "scale", "imported_ends:Bad", "--timeout", "10"], 9),
            (["add", launcher, "extra", "imported_crashes:Bad", "--timeout", "10"], 9),
            (["add", launcher, "extra", "imported_hangs:Bad", "--state", "gain=3",
              "--timeout", "2"], 9)):
        done, took = pb3a(*args, cwd=tmp_path)
        assert done.returncode == 1, (args, done.stdout, done.stderr)
        assert took < took_at_most, (args, took)
        said.append(done.stderr)
        status, _ = pb3a("status", launcher, "--timeout", "5", cwd=tmp_path)
        assert status.returncode == 0, (args, status.stderr)
    hangs = ("importing module 'imported_hangs' for 'imported_hangs:Bad' did not finish "
             "within")
    assert said[0].startswith(f"pb3a swap: 1 problem in the configuration:\n  swap scale: "
                              f"{hangs}"), said[0]
    assert ("it loops or waits (for input, a lock, the network) as it is imported; make it "
            "return, or give the change a longer timeout") in said[0]
    assert ("swap scale: importing module 'imported_ends' for 'imported_ends:Bad' exited "
            "with status 3: it ends the process as it is imported (os._exit()?)") in said[1]
    assert ("module extra: importing module 'imported_crashes' for 'imported_crashes:Bad' "
            "was killed by signal SIGSEGV (a crash in native code it runs as it is "
            "imported?)") in said[2]
    assert f"module extra: {hangs}" in said[3], said[3]
    with connect(launcher) as system:
        modules = system.topology(timeout=5).modules
        assert {name: m.cls for name, m in modules.items()} == {
            "src": "sample_modules:FloatSource", "scale": "sample_modules:Scale"}
        swapped = system.swap("scale", "imported_fine:Bad", timeout=10)
        assert swapped == ["gain"]
    started = int((tmp_path / "started.pid").read_text())
    eventually(lambda: not alive(started), what="the end of the process the import started")


def test_a_macro_whose_module_names_a_file_that_hangs_as_imported_is_refused(
        launcher: str, tmp_path: Path) -> None:
    """A macro added while the system runs names its modules' classes as ``module:Class``
    too: the launcher tries each file it has not imported in a child process first, as
    for the class of a module added, and refuses the macro saying which hangs."""
    (tmp_path / "harm_kit.py").write_text(textwrap.dedent("""
        from pb3a import Macro

        class Kit(Macro):
            modules = {"fine": "imported_fine:Bad", "bad": "imported_hangs:Bad"}
        """))
    done, took = pb3a("add", launcher, "kit", "harm_kit:Kit", "--timeout", "2", cwd=tmp_path)
    assert done.returncode == 1 and took < 9, (done.stdout, done.stderr, took)
    assert ("macro kit: importing module 'imported_hangs' for 'imported_hangs:Bad' did not "
            "finish within") in done.stderr, done.stderr
    with connect(launcher) as system:
        assert set(system.topology(timeout=5).modules) == {"src", "scale"}


def test_a_class_sent_by_reference_whose_module_hangs_in_the_launcher_is_refused(
        launcher: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A program's connection that passes a class object sends it by reference, and the
    launcher imported its module to read the request: one that loops there (not in the
    program) held the launcher's lane of requests for good. The request is now refused
    within the system's timeout, and the next one is answered."""
    monkeypatch.syspath_prepend(str(tmp_path))
    # (it loops only in the launcher; imported here, it goes when the test is done)
    monkeypatch.setitem(sys.modules, "launcher_hangs", None)
    del sys.modules["launcher_hangs"]
    from launcher_hangs import Bad

    with connect(launcher) as system:
        began = time.monotonic()
        with pytest.raises(RuntimeFailure) as refused:
            system.swap("scale", Bad, timeout=5)
        assert time.monotonic() - began < 6
        assert ("importing module 'launcher_hangs' for 'launcher_hangs:Bad' did not finish "
                "within 2 s") in str(refused.value)
        assert system.topology(timeout=5).modules["scale"].cls == "sample_modules:Scale"


def test_in_the_program_a_change_to_a_module_that_hangs_returns_within_its_timeout(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``run.swap`` waited for good for a module file that loops as it is imported (its
    timeout did not bound it); it is refused within its timeout now, the process the
    import started is gone, the system is as it was and takes the next change; asked
    again, it is refused at once (its file unchanged)."""
    _harmful_files(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    system = System("in-program").add("src", FloatSource).add("scale", Scale)
    system.link("src.out", "scale.x")
    with system.launch() as run:
        for took_at_most in (5.0, 0.5):
            outcome: list[Any] = []
            caller = threading.Thread(target=_swap_into, daemon=True,
                                      args=(run, "imported_hangs:Bad", outcome))
            caller.start()
            caller.join(20)
            assert not caller.is_alive(), "the swap did not return within 20 s"
            error, took = outcome
            assert isinstance(error, ConfigError), error
            assert "importing module 'imported_hangs' for 'imported_hangs:Bad' did not " \
                   "finish within" in str(error)
            assert took < took_at_most, took
        started = int((tmp_path / "started.pid").read_text())
        eventually(lambda: not alive(started), what="the end of the process the import started")
        assert run.topology().modules["scale"].cls == "sample_modules:Scale"
        run.swap("scale", "imported_fine:Bad", timeout=10)
        assert "imported_hangs" not in sys.modules


def test_an_agent_s_swap_and_spawn_of_a_class_whose_module_hangs_are_refused(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An agent's ``self.runtime.swap`` and ``spawn`` are changes as the program's are:
    a class whose module file loops as it is imported is refused within the change's
    timeout, then at once (its file unchanged), nothing changed, the process the import
    started gone, and the system takes the agent's next request."""
    _harmful_files(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    system = System("agent-harmed").add("src", FloatSource).add("scale", Scale)
    system.link("src.out", "scale.x")
    system.add("agent", ChangesToAClass, state={"cls": "imported_hangs:Bad"})
    system.add("trigger", Counter, state={"limit": 1}, period=0.05)
    system.link("trigger.out", "agent.go")
    with system.launch() as run:
        state = eventually(lambda: len((s := run.state("agent"))["said"]) == 2 and s,
                           timeout=30, what="the agent's swap and spawn answered")
        hangs = ("ConfigError: 1 problem in the configuration:\n  {} importing module "
                 "'imported_hangs' for 'imported_hangs:Bad' did not finish within")
        swapped, spawned = state["said"]
        assert swapped.startswith(hangs.format("swap scale:")), swapped
        assert spawned.startswith(hangs.format("module extra:")), spawned
        assert state["took"][0] < 5.0 and state["took"][1] < 0.5, state["took"]
        modules = run.topology().modules
        assert {name: m.cls for name, m in modules.items() if name != "agent"} == {
            "src": "sample_modules:FloatSource", "scale": "sample_modules:Scale",
            "trigger": "sample_modules:Counter"}
        started = int((tmp_path / "started.pid").read_text())
        eventually(lambda: not alive(started), what="the end of the process the import started")
        run.set_state("agent", cls="imported_fine:Bad", said=[], took=[])
        run.set_state("trigger", limit=2)
        state = eventually(lambda: len((s := run.state("agent"))["said"]) == 2 and s,
                           timeout=30, what="the agent's next swap and spawn answered")
        assert state["said"] == ["", ""], state["said"]
        assert run.topology().modules["extra"].cls == "imported_fine:Bad"
    assert "imported_hangs" not in sys.modules


def test_the_manager_refuses_a_swap_or_add_of_a_class_whose_module_hangs(
        launcher: str, tmp_path: Path) -> None:
    """``pb3a manager`` attached to a running system imports the class a swap or an add
    names in its own process, to check it, before the system is asked: a module file
    that loops as it is imported is tried in a child process first and refused (404)
    within ``--import-timeout``, then at once (its file unchanged); the manager answers
    on, the system is as it was, and the process the import started is gone."""
    pytest.importorskip("uvicorn", reason="the manager needs the 'ui' extra")
    from test_manager_browser import ManagerProcess

    manager = ManagerProcess(launcher, "--import-timeout", "2", beside=tmp_path)
    try:
        for path, body, took_at_most in (
                ("/api/modules/scale/swap", {"class": "imported_hangs:Bad"}, 6.0),
                ("/api/modules", {"name": "extra", "class": "imported_hangs:Bad"}, 0.5)):
            began = time.monotonic()
            with pytest.raises(urllib.error.HTTPError) as refused:
                manager.api("POST", path, body)
            took = time.monotonic() - began
            error = json.loads(refused.value.read())["error"]
            assert refused.value.code == 404, error
            assert error.startswith("importing module 'imported_hangs' for "
                                    "'imported_hangs:Bad' did not finish within 2 s"), error
            assert error.endswith("give pb3a manager a longer --import-timeout"), error
            assert took < took_at_most, (path, took)
        shown = manager.api("GET", "/api/system")["modules"]
        assert {name: m["class"] for name, m in shown.items()} == {
            "src": "sample_modules:FloatSource", "scale": "sample_modules:Scale"}
        swapped = manager.api("POST", "/api/modules/scale/swap", {"class": "imported_fine:Bad"})
        assert swapped == {"kept": ["gain"]}
    finally:
        manager.stop()
    started = int((tmp_path / "started.pid").read_text())
    eventually(lambda: not alive(started), what="the end of the process the import started")


def _swap_into(run: Any, cls: str, outcome: list[Any]) -> None:
    began = time.monotonic()
    try:
        run.swap("scale", cls, timeout=2.0)
        outcome[:] = [None, time.monotonic() - began]
    except Exception as exc:
        outcome[:] = [exc, time.monotonic() - began]


def test_the_process_that_tries_an_import_may_take_half_the_import_s_timeout_to_begin(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Its start is the machine's doing, not the module's: a swap given 30 s was refused
    once its child had not begun within ``START_TIMEOUT_S`` (10 s), beside a full test
    run on two busy cores. It may take half the import's timeout, if that is longer
    (the other half is the import's own: a start that took it all had the module
    blamed for the time its import did not get)."""
    import pb3a.loading.trial as trial

    (tmp_path / "begins_late.py").write_text("VALUE = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(trial, "START_TIMEOUT_S", 0.0)     # as if it began after that
    assert trial.import_problems(["begins_late"], 20.0, longer="wait longer") == {}
    problem = trial.import_problems(["begins_late"], 0.0, longer="wait longer")
    assert "the process that tries imports did not begin within 0 s" in problem["begins_late"]


def test_a_change_to_a_class_imported_already_starts_no_process(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A module the launcher has imported is not tried again (a traffic agent swapping
    among the controllers it knows costs nothing more); a new one is, once."""
    import pb3a.loading.trial as trial

    started: list[Any] = []
    real = trial.Child
    monkeypatch.setattr(trial, "Child", lambda *a, **k: started.append(a) or real(*a, **k))
    system = System("known").add("src", FloatSource).add("scale", Scale)
    system.link("src.out", "scale.x")
    with system.launch() as run:
        run.swap("scale", "sample_modules:FastScale")
        run.add("probe", "sample_modules:Last")
        run.swap("scale", "sample_modules:Scale")
        assert started == []
        with pytest.raises(ConfigError, match="cannot import module 'no_such_module_here'"):
            run.add("ghost", "no_such_module_here:Ghost")
        assert len(started) == 1
