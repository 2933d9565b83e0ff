"""``pb3a run`` as a user runs it: a live table, a bounded run, a clean stop on SIGTERM."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import psutil
import pytest
from conftest import alive, eventually, unused_port

from pb3a.transport.shm import live_segments

REPO = Path(__file__).resolve().parent.parent
PIPELINE = REPO / "examples" / "pipeline.toml"

pytestmark = pytest.mark.timeout(90)


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    return env


def _in_its_own_group(*argv: str, cwd: Path) -> subprocess.Popen[str]:
    """``pb3a ARGV`` started as a terminal starts it (a process group of its own)."""
    return subprocess.Popen([sys.executable, "-m", "pb3a", *argv], cwd=cwd, env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


@contextlib.contextmanager
def _killed_if_left(proc: subprocess.Popen[str]) -> Iterator[None]:
    """Kill ``proc`` on the way out if it still runs (a test that failed midway)."""
    try:
        yield
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def _workers_of(launcher: psutil.Process) -> list[int]:
    """Worker processes are the children of the launcher's forkserver."""
    return [child.pid for server in launcher.children()
            if "forkserver" in " ".join(server.cmdline()) for child in server.children()]


def test_run_for_seconds_shows_the_table_and_stops_cleanly(tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, "-m", "pb3a", "run", str(PIPELINE), "--for", "2"],
                          cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=60,
                          check=False)
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert "tick" in out and "scale" in out and "tick.out -> scale.x" in out
    assert "stopped cleanly" in out


def test_run_says_the_file_s_notes_before_it_launches(tmp_path: Path) -> None:
    """A run is often started unchecked: the notes ``pb3a check`` prints (a step with no
    period, a link forgotten) come on its stderr too, once, and the run goes on."""
    (tmp_path / "idle.py").write_text(textwrap.dedent("""
        from pb3a import Input, Module, Output

        class Ctl(Module):
            command = Output(float)

            def step(self):
                self.command.write(1.0)

        class Drv(Module):
            command = Input(float)

            def on_input(self, port):
                pass
        """))
    (tmp_path / "idle.toml").write_text(textwrap.dedent("""
        name = "idle"
        [modules.ctl]
        class = "idle:Ctl"
        [modules.driver]
        class = "idle:Drv"
        """))
    done = subprocess.run([sys.executable, "-m", "pb3a", "run", "idle.toml", "--for", "0.5"],
                          cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=60,
                          check=False)
    assert done.returncode == 0, done.stderr
    notes = [line for line in done.stderr.splitlines() if ": note: " in line]
    assert notes == [
        "idle.toml [modules.ctl]: note: ctl (idle:Ctl) defines step() but has no period: "
        "its step() never runs (give it period = SECONDS in its entry or on its class), "
        "unless its period is set as it runs (pb3a set ADDR ctl period=..., an agent's "
        "set_state)",
        "idle.toml [modules.driver]: note: driver.command is fed by nothing, and "
        'ctl.command is read by nothing: a link forgotten? ([[links]] from = '
        '"ctl.command", to = "driver.command")'], done.stderr
    assert "stopped cleanly" in done.stdout


def test_a_run_whose_module_does_not_stop_does_not_say_it_stopped_cleanly(
        tmp_path: Path) -> None:
    """A module stuck in ``on_input`` as the run ended had its worker killed, its
    ``teardown`` not run, and ``pb3a run`` said "stopped cleanly". Now a warning names
    it and what it is busy in, and the last line says its teardown did not run."""
    (tmp_path / "stuck.py").write_text(textwrap.dedent("""\
        import time
        from pb3a import Input, Module, Output

        class Src(Module):
            out = Output(float)
            period = 0.02

            def step(self):
                self.out.write(1.0)

        class Slow(Module):
            z = Input(float, policy="queue:8")

            def on_input(self, port):
                port.read()
                time.sleep(1000)       # (a serial read without a timeout)
        """))
    (tmp_path / "stuck.toml").write_text(textwrap.dedent("""\
        name = "stuck"
        [modules.src]
        class = "stuck:Src"
        [modules.slow]
        class = "stuck:Slow"
        [[links]]
        from = "src.out"
        to = "slow.z"
        """))
    done = subprocess.run([sys.executable, "-m", "pb3a", "run", "stuck.toml", "--for", "2"],
                          cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=60,
                          check=False)
    assert done.returncode == 0, done.stderr
    assert "stopped cleanly" not in done.stdout
    assert done.stdout.splitlines()[-1] == (
        "pb3a: stopped; module slow did not stop in time: its worker was killed, teardown "
        "not run (see the warnings above)")
    assert "module 'slow' was not stopped (its worker is killed)" in done.stderr
    assert "busy in on_input for" in done.stderr


# The script pip writes for the ``pb3a`` console entry point (setup.cfg).
CONSOLE_SCRIPT = """\
import sys
from pb3a.cli.main import main
if __name__ == '__main__':
    sys.argv[0] = sys.argv[0].removesuffix('.exe')
    sys.exit(main())
"""


def test_the_pb3a_script_imports_from_the_current_directory_as_python_m_does(
        tmp_path: Path) -> None:
    """``python -m pb3a`` had the current directory on its import path, the ``pb3a``
    script its own directory there instead: a class beside the user ("mods:Sink",
    named by a file in a subdirectory) was found by one and not by the other, and a
    run's workers must find it too."""
    script = tmp_path / "bin" / "pb3a"
    script.parent.mkdir()
    script.write_text(CONSOLE_SCRIPT)
    work = tmp_path / "work"
    (work / "sub").mkdir(parents=True)
    stepped = tmp_path / "stepped"
    (work / "here_mods.py").write_text(textwrap.dedent(f"""
        import os

        from pb3a import Module, Output

        class Src(Module):
            out = Output(int)
            period = 0.05

            def step(self):
                with open({str(stepped)!r}, "w") as seen:
                    seen.write(os.environ.get("PYTHONSAFEPATH", "unset"))
                self.out.write(1)
        """))
    (work / "sub" / "rel.toml").write_text('name = "rel"\n[modules.src]\n'
                                           'class = "here_mods:Src"\n')
    def pb3a(program: list[str], *command: str) -> None:
        done = subprocess.run([sys.executable, *program, *command], cwd=work, env=_env(),
                              capture_output=True, text=True, timeout=60, check=False)
        assert done.returncode == 0, (program, done.stdout + done.stderr)

    for program in ([str(script)], ["-m", "pb3a"]):
        stepped.unlink(missing_ok=True)
        pb3a(program, "check", "sub/rel.toml")
        pb3a(program, "run", "sub/rel.toml", "--for", "1")
        assert stepped.exists(), program     # (a worker imported it, and it stepped)
    # the directory comes after the standard library: a file of the user's named as a
    # standard module shadows nothing (put first, it broke every command of the script:
    # "module 'random' has no attribute 'Random'"; then the check's import child and the
    # workers' forkserver, which start with ``python -c``, imported a json.py or
    # random.py there)
    for name in ("random", "json", "tempfile"):
        (work / f"{name}.py").write_text(f"raise SystemExit(\"the user's {name}.py\")\n")
    for program in ([str(script)], ["-m", "pb3a"]):
        stepped.unlink(missing_ok=True)
        pb3a(program, "check", "sub/rel.toml")
        pb3a(program, "run", "sub/rel.toml", "--for", "1")
        # (and the worker's own children get the environment the user had)
        assert stepped.read_text() == "unset", program


@pytest.mark.parametrize("how", ["SIGTERM", "Ctrl-C", "SIGTERM to the group",
                                 "the terminal closed"])
def test_a_signal_stops_everything_and_leaves_nothing_behind(tmp_path: Path, how: str) -> None:
    """The group's SIGTERM is what timeout, kill -- -PGID and systemd send: it killed
    the workers' forkserver too, and every module was then reported failed. It also
    stopped the workers before the launcher asked for its last table, which read zeros
    with a warning per worker; the workers tell their figures as they stop. A closing
    terminal (an ssh session cut) sends the group SIGHUP: it killed the launcher at once,
    a segment left behind, and the resource tracker, whose successor printed tracebacks."""
    proc = _in_its_own_group("run", str(PIPELINE), cwd=tmp_path)
    with _killed_if_left(proc):
        assert "running" in proc.stdout.readline()
        launcher = psutil.Process(proc.pid)
        workers = eventually(lambda: _workers_of(launcher), what="worker processes")
        assert live_segments(proc.pid)
        while not proc.stdout.readline().startswith("tick.out -> scale.x"):
            pass                                          # a first table: values went
        if how == "SIGTERM":
            proc.send_signal(signal.SIGTERM)
        elif how == "Ctrl-C":     # a terminal's Ctrl-C: SIGINT to the whole process group
            os.killpg(proc.pid, signal.SIGINT)
        elif how == "the terminal closed":
            os.killpg(proc.pid, signal.SIGHUP)
        else:
            os.killpg(proc.pid, signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "stopped cleanly" in out
    assert "Traceback" not in err and "died" not in err and "failed" not in err
    assert "WARNING" not in err, err
    last_table = out.rpartition("module  ")[2].splitlines()
    (tick,) = [line.split() for line in last_table if line.startswith("tick ")]
    (link,) = [line.split() for line in last_table if line.startswith("tick.out -> scale.x")]
    assert int(tick[5]) > 0 and int(link[6]) > 0, out        # its steps, the values sent
    assert not live_segments(proc.pid)
    assert not [p for p in workers if alive(p)]


def _child_taking_ctrl_c(parent: psutil.Process, named: str, timeout: float = 30.0) -> int:
    """The pid of the first child of ``parent`` whose command line holds ``named``, the
    moment its interpreter has set Python's own SIGINT handler (KeyboardInterrupt), as it
    does first: polled without pause, as a tenth of a second later, once it has imported
    PB3A's code, it has its own."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for child in parent.children():
            with contextlib.suppress(psutil.Error, OSError):  # (one that ended meanwhile)
                if named in " ".join(child.cmdline()) \
                        and _signal_mask(child.pid, "SigCgt") & _bit(signal.SIGINT):
                    return child.pid
    pytest.fail(f"no child naming {named} took SIGINT within {timeout:g} s")


def _signal_mask(pid: int, which: str) -> int:
    """Process ``pid``'s signal mask ``which`` ("SigIgn", "SigCgt", "SigBlk"), from /proc."""
    with open(f"/proc/{pid}/status") as status:
        (mask,) = [line.split()[1] for line in status if line.startswith(f"{which}:")]
    return int(mask, 16)


def _bit(signum: int) -> int:
    return 1 << (signum - 1)


def test_a_ctrl_c_as_the_workers_forkserver_starts_ends_the_run_with_one_line(
        tmp_path: Path) -> None:
    """A Ctrl-C in the first second of `pb3a run` came, once in ten, as the workers'
    forkserver started its interpreter, before it ignored SIGINT: it died of it, and
    "Fatal Python error: init_import_site" or a KeyboardInterrupt traceback came out
    above "pb3a: interrupted". It starts with the terminal's signals held off until it
    ignores them. The Ctrl-C is sent the moment its interpreter would raise
    KeyboardInterrupt for it."""
    for _ in range(5):          # (a test starved of CPU may send it too late: again)
        proc = _in_its_own_group("run", str(PIPELINE), cwd=tmp_path)
        with _killed_if_left(proc):
            server = _child_taking_ctrl_c(psutil.Process(proc.pid),
                                          "multiprocessing.forkserver")
            early = not _signal_mask(server, "SigIgn") & _bit(signal.SIGINT)
            os.killpg(proc.pid, signal.SIGINT)       # a terminal's Ctrl-C, to the group
            out, err = proc.communicate(timeout=30)
        if early:
            break
    assert early, "the forkserver ignored SIGINT already: each Ctrl-C came too late"
    assert proc.returncode == 130 and err.strip() == "pb3a: interrupted", err
    assert "running" not in out
    assert not live_segments(proc.pid)
    eventually(lambda: not alive(server), what="the forkserver to end")


def test_a_ctrl_c_as_a_node_starts_an_executor_stops_it_with_no_traceback(
        tmp_path: Path) -> None:
    """`pb3a node start` at its terminal: a Ctrl-C as a launcher's system arrived came
    as the executor's interpreter started, before it ignored SIGINT, and it died of it,
    a crash dump or a KeyboardInterrupt traceback on the node's terminal. It starts
    with the terminal's signals held off until its handlers are set."""
    node = _in_its_own_group("node", "start", "--name", "far", "--listen",
                             "tcp://127.0.0.1:0", "--max-cpu", "100", cwd=tmp_path)
    with _killed_if_left(node):
        address = node.stdout.readline().split(" at ")[-1].strip()
        (tmp_path / "far.toml").write_text(
            f'name = "far"\n[nodes.far]\naddress = "{address}"\n[modules.scale]\n'
            'class = "examples.pipeline:Scale"\nnode = "far"\n')
        launcher = _in_its_own_group("run", str(tmp_path / "far.toml"), cwd=tmp_path)
        with _killed_if_left(launcher):
            executor = _child_taking_ctrl_c(psutil.Process(node.pid), "multiprocessing.spawn")
            early = not _signal_mask(executor, "SigIgn") & _bit(signal.SIGINT)
            os.killpg(node.pid, signal.SIGINT)       # a Ctrl-C at the node's terminal
            _, err = node.communicate(timeout=30)
            launcher.send_signal(signal.SIGTERM)
            launcher.communicate(timeout=30)
    assert early, "the executor ignored SIGINT already: the Ctrl-C came too late"
    assert node.returncode == 0, err
    assert "Traceback" not in err and "Fatal Python error" not in err, err
    eventually(lambda: not alive(executor), what="the executor to end")


def test_a_second_ctrl_c_while_it_stops_lets_the_stop_finish(tmp_path: Path) -> None:
    """An impatient second Ctrl-C cut the clean stop short: exit 130 after "stopping",
    and BufferError and "leaked shared_memory objects" on the terminal. It is answered
    with a line, and the stop goes on (a third would leave it unfinished). The module's
    teardown takes a second, so that the second Ctrl-C comes while it stops."""
    (tmp_path / "lingering.py").write_text(textwrap.dedent("""
        import time
        from pb3a import Module

        class Lingers(Module):
            period = 0.05

            def step(self):
                pass

            def teardown(self):
                time.sleep(1.0)
        """))
    (tmp_path / "lingering.toml").write_text(
        'name = "lingering"\n[modules.lingers]\nclass = "lingering:Lingers"\n')
    proc = _in_its_own_group("run", str(tmp_path / "lingering.toml"), cwd=tmp_path)
    with _killed_if_left(proc):
        assert "running" in proc.stdout.readline()
        os.killpg(proc.pid, signal.SIGINT)
        while "stopping" not in (line := proc.stdout.readline()):
            assert line, "pb3a run ended without saying it stops"
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "still stopping" in out and "stopped cleanly" in out
    assert err == "" and not live_segments(proc.pid)


def test_a_third_ctrl_c_while_it_stops_leaves_the_stop_unfinished(tmp_path: Path) -> None:
    """A third Ctrl-C as the stop waits for a long teardown leaves the stop unfinished,
    as the second's line says: `pb3a run` ends at once (130, one line), its workers
    ending with it. The close it interrupts is not finished as the program exits
    (seconds more, a warning for each module it gave up on), as a program's close is."""
    (tmp_path / "stuck.py").write_text(textwrap.dedent("""
        import time
        from pb3a import Module

        class StuckInTeardown(Module):
            period = 0.05

            def step(self):
                pass

            def teardown(self):
                print("tearing down", flush=True)
                time.sleep(3.0)
        """))
    (tmp_path / "stuck.toml").write_text(
        'name = "stuck"\n[modules.a]\nclass = "stuck:StuckInTeardown"\n'
        '[modules.b]\nclass = "stuck:StuckInTeardown"\n')
    proc = _in_its_own_group("run", str(tmp_path / "stuck.toml"), cwd=tmp_path)
    with _killed_if_left(proc):
        assert "running" in proc.stdout.readline()
        workers = eventually(lambda: _workers_of(psutil.Process(proc.pid)),
                             what="the workers")
        for said in ("tearing down", "still stopping"):
            os.killpg(proc.pid, signal.SIGINT)
            while said not in (line := proc.stdout.readline()):
                assert line, f"pb3a run ended without saying {said!r}"
        os.killpg(proc.pid, signal.SIGINT)
        began = time.monotonic()
        proc.wait(timeout=30)
        took = time.monotonic() - began
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130 and err == "pb3a: interrupted\n", err
    assert took < 2.0, f"it ended {took:.1f} s after the third Ctrl-C"
    eventually(lambda: not [pid for pid in workers if alive(pid)], what="the workers' end")
    assert not live_segments(proc.pid)


def test_ctrl_c_once_the_stop_is_over_changes_nothing(tmp_path: Path) -> None:
    """Two quick Ctrl-Cs stopped the system cleanly, and then `pb3a run` exited 130 or
    was killed by SIGINT (3 runs in 5): the first reaches the workers too, so the stop
    is over within a tenth of a second, and the second came as the run exited, Python's
    own handler given back. Once the stop is over, signals change nothing: it exits 0.
    They are sent as soon as it says it stopped cleanly."""
    proc = _in_its_own_group("run", str(PIPELINE), cwd=tmp_path)
    with _killed_if_left(proc):
        assert "running" in proc.stdout.readline()
        launcher = psutil.Process(proc.pid)
        workers = eventually(lambda: _workers_of(launcher), what="worker processes")
        os.killpg(proc.pid, signal.SIGINT)
        while "stopped cleanly" not in (line := proc.stdout.readline()):
            assert line, "pb3a run ended without saying it stopped cleanly"
        for signum in (signal.SIGINT, signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            with contextlib.suppress(ProcessLookupError):        # (it has exited)
                os.killpg(proc.pid, signum)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert err == "" and "still stopping" not in out
    assert not live_segments(proc.pid)
    assert not [p for p in workers if alive(p)]


def test_a_signal_once_the_stop_is_over_still_ends_an_exit_that_hangs(tmp_path: Path) -> None:
    """Once its stop was over, `pb3a run` ignored Ctrl-C, SIGTERM and SIGHUP for good: an
    exit held up by a thread a module file started as it was imported (a vendor SDK's
    poller, which Python's exit waits for) could only be killed. A signal now ends it
    at once, with the status it had decided."""
    (tmp_path / "sdk.py").write_text(textwrap.dedent("""
        import threading, time
        from pb3a import Module

        def _poll():
            while True:
                time.sleep(0.5)

        if threading.current_thread() is threading.main_thread():
            threading.Thread(target=_poll, name="sdk-poller").start()   # (not a daemon)

        class Tick(Module):
            period = 0.05

            def step(self):
                pass
        """))
    (tmp_path / "sdk.toml").write_text('name = "sdk"\n[modules.tick]\nclass = "sdk:Tick"\n')
    proc = _in_its_own_group("run", str(tmp_path / "sdk.toml"), cwd=tmp_path)
    with _killed_if_left(proc):
        assert "running" in proc.stdout.readline()
        os.killpg(proc.pid, signal.SIGINT)
        while "stopped cleanly" not in (line := proc.stdout.readline()):
            assert line, "pb3a run ended without saying it stopped cleanly"
        with pytest.raises(subprocess.TimeoutExpired):     # (held up by the poller)
            proc.wait(timeout=1.0)
        os.kill(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert not live_segments(proc.pid)


def test_ctrl_c_as_an_interrupted_start_exits_changes_nothing(tmp_path: Path) -> None:
    """Two quick Ctrl-Cs as `pb3a run` started: it said "pb3a: interrupted", and the
    second, coming as it exited, killed it by SIGINT instead of exit status 130. The
    first is sent as it checks the file (its child imports a module file that takes
    seconds to), the others once it has said it was interrupted."""
    (tmp_path / "slow.py").write_text(textwrap.dedent("""
        import time
        from pb3a import Module

        time.sleep(5.0)

        class Slow(Module):
            period = 0.05

            def step(self):
                pass
        """))
    (tmp_path / "slow.toml").write_text('name = "slow"\n[modules.slow]\nclass = "slow:Slow"\n')
    proc = _in_its_own_group("run", str(tmp_path / "slow.toml"), cwd=tmp_path)
    launcher = psutil.Process(proc.pid)

    def checking() -> bool:
        with contextlib.suppress(psutil.Error):       # (one that ended meanwhile)
            return any("sys.path[:] = json.loads" in " ".join(child.cmdline())
                       for child in launcher.children())      # (``import_child._BOOT``)
        return False

    with _killed_if_left(proc):
        eventually(checking, what="the import child")
        os.killpg(proc.pid, signal.SIGINT)
        while "pb3a: interrupted" not in (line := proc.stderr.readline()):
            assert line, "pb3a run ended without saying it was interrupted"
        for signum in (signal.SIGINT, signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            with contextlib.suppress(ProcessLookupError):        # (it has exited)
                os.killpg(proc.pid, signum)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130 and err == "", err
    assert out == "" and not live_segments(proc.pid)


def test_a_run_whose_output_has_no_reader_runs_its_time(tmp_path: Path) -> None:
    """`pb3a run F | head -1` stopped the system at its next table, saying it could not
    reach or listen where F says (a BrokenPipeError); with stdout closed (`>&-`, some
    supervisors) it failed at once on stdout.isatty()."""
    command = [sys.executable, "-m", "pb3a", "run", str(PIPELINE), "--for", "2"]
    reader_gone = subprocess.Popen(command, cwd=tmp_path, env=_env(), stdout=subprocess.PIPE,
                                   stderr=subprocess.PIPE, text=True)
    try:
        assert "running" in reader_gone.stdout.readline()
        reader_gone.stdout.close()                   # as head does after its line
        err = reader_gone.stderr.read()
        assert reader_gone.wait(30) == 0, err
    finally:
        if reader_gone.poll() is None:
            reader_gone.kill()
            reader_gone.wait()
        reader_gone.stderr.close()
    assert "cannot reach" not in err and "Traceback" not in err
    closed = subprocess.run(command, cwd=tmp_path, env=_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, timeout=60,
                            preexec_fn=lambda: os.close(1))       # (stdout closed)
    assert closed.returncode == 0, closed.stderr
    assert "Traceback" not in closed.stderr


def test_a_scenario_whose_terminal_closes_stops_and_leaves_nothing_behind(
        tmp_path: Path) -> None:
    """`pb3a scenario` took no signal but Ctrl-C: a closing terminal (SIGHUP to the
    group) killed it, its segments left in /dev/shm."""
    proc = _in_its_own_group("scenario", "self-migration", "--quick", "--out", str(tmp_path),
                             cwd=tmp_path)
    with _killed_if_left(proc):
        eventually(lambda: live_segments(proc.pid), timeout=30, what="the scenario running")
        os.killpg(proc.pid, signal.SIGHUP)
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130 and err.strip() == "pb3a: interrupted", err
    assert not live_segments(proc.pid)


@pytest.mark.timeout(120)
def test_a_robot_scenario_interrupted_at_its_terminal_ends_at_once(tmp_path: Path) -> None:
    """Ctrl-C reached the robots' node controllers too (another machine's daemons, in the
    terminal's process group): they stopped under the running system, which took 12 s to
    end, saying its nodes were lost."""
    proc = _in_its_own_group("scenario", "mapping", "--quick", "--out", str(tmp_path),
                             cwd=tmp_path)
    launcher = psutil.Process(proc.pid)

    def node_controllers() -> int:
        found = 0
        for child in launcher.children():
            with contextlib.suppress(psutil.Error):       # (one that ended meanwhile)
                found += "scenarios.lab_node" in child.cmdline()
        return found

    with _killed_if_left(proc):
        eventually(lambda: node_controllers() == 2, timeout=60,
                   what="the robots' node controllers")
        eventually(lambda: live_segments(proc.pid), timeout=60, what="the system running")
        os.killpg(proc.pid, signal.SIGINT)
        interrupted = time.monotonic()
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and err.strip() == "pb3a: interrupted", err
    assert time.monotonic() - interrupted < 6.0
    assert not live_segments(proc.pid)


@pytest.mark.timeout(120)
def test_a_robot_scenario_killed_with_its_group_leaves_no_node_controller(
        tmp_path: Path) -> None:
    """The robots' node controllers, in sessions of their own (out of the terminal's
    Ctrl-C), outlived a launcher killed with its group (kill -9 -- -PGID; a Ctrl-C
    repeated through the lab's close too): they served on, nobody to stop them."""
    log = tmp_path / "stderr.txt"           # (a file, not a pipe: the orphans held those)
    with log.open("w") as stderr:
        proc = subprocess.Popen([sys.executable, "-m", "pb3a", "scenario", "mapping",
                                 "--quick", "--out", str(tmp_path)], cwd=tmp_path,
                                env=_env(), stdout=subprocess.DEVNULL, stderr=stderr,
                                start_new_session=True)
    launcher = psutil.Process(proc.pid)

    def launcher_seen() -> str:
        return f"launcher exit status {proc.poll()}, its stderr: {log.read_text()[-2000:]!r}"

    controllers: list[psutil.Process] = []
    sockets: set[Path] = set()

    def node_controllers() -> list[psutil.Process]:
        found = []
        for child in launcher.children():
            with contextlib.suppress(psutil.Error):       # (one that ended meanwhile)
                if "scenarios.lab_node" in child.cmdline():
                    found.append(child)
        return found if len(found) == 2 else []

    try:
        controllers = eventually(node_controllers, timeout=60,
                                 what="the robots' node controllers", context=launcher_seen)
        eventually(lambda: live_segments(proc.pid), timeout=60, what="the system running",
                   context=launcher_seen)
        theirs = [*controllers, *(p for c in controllers for p in c.children(recursive=True))]
        sockets = {Path(connection.laddr).parent for child in launcher.children()
                   if "forkserver" in " ".join(child.cmdline())
                   for connection in child.net_connections(kind="unix") if connection.laddr}
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
        eventually(lambda: not [p.pid for p in theirs if alive(p.pid)], timeout=20,
                   what="the node controllers (and what they run) ending with their launcher")
    finally:
        for controller in controllers:
            with contextlib.suppress(psutil.Error):
                for process in [*controller.children(recursive=True), controller]:
                    process.kill()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for name in live_segments(proc.pid):    # (the launcher's, SIGKILLed: nobody's)
            with contextlib.suppress(OSError):
                os.unlink(f"/dev/shm/{name}")
        for directory in sockets:   # (its forkserver's, SIGKILLed with it: nobody's)
            shutil.rmtree(directory, ignore_errors=True)


_LAB_NODE_ON_A_THREAD = """
import threading, time
from scenarios.lab import NodeControllerProcess

made = []
thread = threading.Thread(target=lambda: made.append(NodeControllerProcess("r1")))
thread.start()
thread.join()
print(made[0].process.pid, flush=True)
time.sleep(60)
"""


@pytest.mark.timeout(60)
def test_a_lab_node_made_on_a_thread_that_ends_serves_on_until_its_launcher_ends(
        tmp_path: Path) -> None:
    """PR_SET_PDEATHSIG fires when the *thread* that started the child ends: a lab's
    node controller made on a thread that then ended stopped at once, its launcher
    alive."""
    script = tmp_path / "launcher.py"
    script.write_text(_LAB_NODE_ON_A_THREAD)
    proc = subprocess.Popen([sys.executable, str(script)], env=_env(), cwd=tmp_path,
                            stdout=subprocess.PIPE, text=True)
    controller = None
    try:
        controller = psutil.Process(int(proc.stdout.readline()))
        time.sleep(2.0)
        assert alive(controller.pid), "it stopped, its launcher alive"
        proc.kill()                                 # the launcher's end still ends it
        proc.wait(10)
        eventually(lambda: not alive(controller.pid), timeout=20,
                   what="the node controller ending with its launcher")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if controller is not None:
            with contextlib.suppress(psutil.Error):
                for process in [*controller.children(recursive=True), controller]:
                    process.kill()
        proc.stdout.close()


def test_run_reports_an_invalid_file_and_starts_nothing(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "bad"\n[modules.x]\nclass = "examples.pipeline:Nope"\n')
    done = subprocess.run([sys.executable, "-m", "pb3a", "run", str(bad), "--for", "1"],
                          cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=60,
                          check=False)
    assert done.returncode == 1
    assert "Nope" in done.stdout + done.stderr


def test_the_readme_quickstart_runs_as_a_plain_script(tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, str(REPO / "examples" / "quickstart.py")],
                          cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=60,
                          check=False)
    assert done.returncode == 0, done.stderr
    assert "'gain': 10.0" in done.stdout and "tick.out" in done.stdout


def test_the_adaptive_loop_example_retunes_then_swaps_its_filter(tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, str(REPO / "examples" / "adaptive_loop.py")],
                          cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=90,
                          check=False)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    settled = re.fullmatch(r"settled at ([\d.]+), jitter ([\d.]+), 0 actions", lines[0])
    assert settled, lines                                # nothing done while quiet
    assert 0.8 < float(settled[1]) < 1.2, lines         # the PI holds the setpoint, 1.0
    assert float(settled[2]) < 0.02, lines
    assert lines[1:4] == ["retuned alpha to 0.25", "retuned alpha to 0.125",
                          "swapped LowPass for Average"], lines
    after = re.fullmatch(r"filter now __main__:Average, jitter ([\d.]+)", lines[4])
    assert after and float(after[1]) < 0.02, lines       # the swap brought it under


MODULES_BESIDE_THE_FILE = '''
from pb3a import Input, Module, Output


class Tick(Module):
    out = Output(int)
    period = 0.01
    count = 0

    def step(self):
        self.count += 1
        self.out.write(self.count)


class Tally(Module):
    x = Input(int, policy="queue:64")
    seen = 0

    def on_input(self, port):
        port.read()
        self.seen += 1
'''


def _run_tick_far_tally_here(module: str, project: Path, elsewhere: Path,
                             env: dict[str, str]) -> None:
    """``pb3a run project/system.toml --for 2`` from ``elsewhere`` with ``env``, the
    classes of ``module`` on two nodes: its Tick on a node controller started in
    ``elsewhere`` with the tests' environment alone, its Tally in the launcher; it must
    run, and values cross from far to here."""
    node = subprocess.Popen([sys.executable, "-m", "pb3a", "node", "start", "--name", "far",
                             "--listen", "tcp://127.0.0.1:0", "--max-cpu", "100"],
                            cwd=elsewhere, env=_env(),
                            stdout=subprocess.PIPE, text=True)
    try:
        address = node.stdout.readline().split(" at ")[-1].strip()
        (project / "system.toml").write_text(f'''
name = "beside"
[nodes.here]
[nodes.far]
address = "{address}"
[modules.tick]
class = "{module}:Tick"
node = "far"
[modules.tally]
class = "{module}:Tally"
node = "here"
[[links]]
from = "tick.out"
to = "tally.x"
''')
        # --listen holds although a remote node also calls the launcher back there
        port = unused_port()
        done = subprocess.run([sys.executable, "-m", "pb3a", "run", "../project/system.toml",
                               "--for", "2", "--listen", f"tcp://127.0.0.1:{port}"],
                              cwd=elsewhere, env=env, capture_output=True, text=True,
                              timeout=60, check=False)
    finally:
        node.send_signal(signal.SIGTERM)
        node.wait(10)
        node.stdout.close()
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"launcher at tcp://127.0.0.1:{port}" in done.stdout
    link = next(line for line in done.stdout.splitlines()[::-1] if "tick.out -> tally.x" in line)
    assert int(link.split()[5]) > 0, done.stdout          # values crossed from far to here


def test_a_module_next_to_its_configuration_file_imports_on_every_node(tmp_path: Path) -> None:
    project, elsewhere = tmp_path / "project", tmp_path / "elsewhere"
    project.mkdir()
    elsewhere.mkdir()
    (project / "beside.py").write_text(MODULES_BESIDE_THE_FILE)
    # neither the launcher's nor the node's working directory or PYTHONPATH has it
    _run_tick_far_tally_here("beside", project, elsewhere, _env())


def test_a_module_on_the_launcher_s_pythonpath_imports_on_a_node_started_without_it(
        tmp_path: Path) -> None:
    """``pb3a run FILE`` handed its nodes the file's directory alone, where a system built
    in a script hands them its ``PYTHONPATH``'s directories too: a class the launcher
    imported from its ``PYTHONPATH`` was not found on a node started without it ("cannot
    import module 'onpath' ... put it in the launcher's directory on this machine")."""
    project, lib, elsewhere = tmp_path / "project", tmp_path / "lib", tmp_path / "elsewhere"
    for directory in (project, lib, elsewhere):
        directory.mkdir()
    (lib / "onpath.py").write_text(MODULES_BESIDE_THE_FILE)
    env = _env()
    env["PYTHONPATH"] = os.pathsep.join([str(lib), env["PYTHONPATH"]])
    _run_tick_far_tally_here("onpath", project, elsewhere, env)
