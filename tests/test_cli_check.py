"""``pb3a check`` and ``pb3a graph`` as a user runs them: a separate process, exit codes, files."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
import types
from pathlib import Path

import pytest
from conftest import alive, eventually

import examples.pipeline
from pb3a import System
from pb3a.cli.main import main

REPO = Path(examples.pipeline.__file__).resolve().parent.parent
PIPELINE = REPO / "examples" / "pipeline.toml"

BROKEN = """
    name = "broken"
    [modules.tick]
    class = "examples.pipeline:Ticker"
    perod = 0.1
    [modules.scale]
    class = "examples.pipeline:Scael"
    [[links]]
    from = "tick.out"
    to = "scale.x"
    policy = "fifo"
"""


def pb3a(*args: str, cwd: Path, path: str | None = None,
         stdin: int | None = None) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    if path is not None:
        env["PATH"] = path
    return subprocess.run([sys.executable, "-m", "pb3a", *args], cwd=cwd, env=env, stdin=stdin,
                          capture_output=True, text=True, timeout=60, check=False)


# Module files that harm whoever imports them, each ending in a class ``Bad`` with an output
# ``out``; ``imported_hangs`` starts a process first and writes its pid to ``started.pid``.
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
    "imported_exits": "import sys\nsys.exit(2)\n",
    "imported_prints": "print('hello from an import')\n",
    "imported_reads": "answer = input('password? ')\n",
}
GOOD = """
    from pb3a import Input, Module, Output

    class Src(Module):
        out = Output(float)

    class Dst(Module):
        x = Input(float)
    """


def _harmful_files(directory: Path, *names: str) -> None:
    """The module files ``names`` of ``HARMFUL`` and ``imported_good.py`` in ``directory``."""
    (directory / "imported_good.py").write_text(textwrap.dedent(GOOD))
    for name in names:
        (directory / f"{name}.py").write_text(textwrap.dedent(HARMFUL[name]) + textwrap.dedent(
            """
            from pb3a import Module, Output

            class Bad(Module):
                out = Output(float)
            """))


def _system(directory: Path, *names: str) -> Path:
    """A file naming ``imported_good:Dst`` (as ``dst``) and each module ``names`` (its
    ``Bad`` as a module of that name), the first linked to ``dst``."""
    lines = ['name = "harmed"', "[modules.dst]", 'class = "imported_good:Dst"']
    for name in names:
        lines += [f"[modules.{name}]", f'class = "{name}:Bad"']
    lines += ["[[links]]", f'from = "{names[0]}.out"', 'to = "dst.x"']
    path = directory / "harmed.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_check_accepts_the_pipeline_example(tmp_path: Path) -> None:
    done = pb3a("check", str(PIPELINE), cwd=tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout == "ok: 2 modules, 1 link\n"


def test_check_prints_every_problem_on_its_own_line_and_exits_1(tmp_path: Path) -> None:
    (tmp_path / "broken.toml").write_text(textwrap.dedent(BROKEN))
    done = pb3a("check", "broken.toml", cwd=tmp_path)
    assert done.returncode == 1
    lines = done.stdout.splitlines()
    assert len(lines) == 3, done.stdout
    assert lines[0].startswith("broken.toml [modules.tick]: unknown key 'perod'")
    assert "did you mean 'period'" in lines[0]
    assert lines[1].startswith("broken.toml [modules.scale]: module 'examples.pipeline' has no "
                               "class 'Scael' (did you mean 'Scale'?)")
    assert lines[2].startswith("broken.toml [[links]] #1 (tick.out -> scale.x): bad policy 'fifo'")
    assert "3 problems in broken.toml" in done.stderr


def test_check_reports_what_a_user_s_module_refuses_of_its_state_by_file_and_entry(
        tmp_path: Path) -> None:
    """A class says what it refuses of its state (``state_problems``, which its
    ``set_state`` asks); ``pb3a check`` asks it for each entry's state and for the
    class's own defaults. Only a ``set_state`` of the class's own could refuse such a
    value, and the check passed it: the launch failed, or the module ran on it."""
    (tmp_path / "pumps.py").write_text(textwrap.dedent("""
        from pb3a import Module

        class Pump(Module):
            rate = 1.0

            @classmethod
            def state_problems(cls, state):
                problems = super().state_problems(state)
                if "rate" in state and not 0 <= state["rate"] <= 5:
                    problems.append(f"{cls.__name__}'s rate must be from 0 to 5 l/s, "
                                    f"got {state['rate']!r}")
                return problems

        class Leaky(Pump):
            rate = -1.0
        """))
    (tmp_path / "plant.toml").write_text(textwrap.dedent("""
        name = "plant"
        [modules.main]
        class = "pumps:Pump"
        state = { rate = 9 }
        [modules.spare]
        class = "pumps:Pump"
        state = { rate = 4.5 }
        [modules.leak]
        class = "pumps:Leaky"
        """))
    done = pb3a("check", "plant.toml", cwd=tmp_path)
    assert done.returncode == 1, done.stdout + done.stderr
    assert done.stdout.splitlines() == [
        "plant.toml [modules.main]: Pump's rate must be from 0 to 5 l/s, got 9.0",
        "plant.toml [modules.leak]: Leaky's rate must be from 0 to 5 l/s, got -1.0 (its "
        "class's own default)"]
    assert "2 problems in plant.toml" in done.stderr


def test_check_reports_what_the_library_s_modules_refuse_of_their_state(
        tmp_path: Path) -> None:
    """The library's modules refused values in a ``set_state`` or a ``setup`` of their
    own, which ``pb3a check`` never asked: a file with a junction's lane capacity of 0,
    a maximum green below the minimum, a window of 0 episodes passed it, and the launch
    failed on it (or the module ran on it). They say so in ``state_problems`` now: each
    is a problem of its entry, a rule relating fields judged with the class's default
    for the field the entry leaves (and with an instance's override, for a macro's)."""
    (tmp_path / "lab.toml").write_text(textwrap.dedent("""
        name = "lab"
        [modules.sensors]
        class = "agents.traffic.sensors:JunctionSensors"
        state = { lane_capacity = 0 }
        [modules.control]
        class = "agents.traffic.gap_out:GapOut"
        state = { min_green_s = 50.0 }
        [modules.learner]
        class = "agents.traffic.learning:QLearning"
        state = { seed = -1 }
        [modules.transfer]
        class = "agents.transfer:TransferAgent"
        state = { window = 0, to_node = "robot", to_resource = "tcp://10.0.0.7:7400" }
        [modules.monitor]
        class = "agents.monitor:HardwareMonitor"
        state = { votes_needed = 6 }
        [modules.mapper]
        class = "agents.occupancy:Mapper"
        state = { publish_every = 0 }
        [modules.fine]
        class = "agents.traffic.gap_out:GapOut"
        state = { min_green_s = 2.0, max_green_s = 30.0 }
        """))
    done = pb3a("check", "lab.toml", cwd=tmp_path)
    assert done.returncode == 1, done.stdout + done.stderr
    assert done.stdout.splitlines() == [
        "lab.toml [modules.sensors]: JunctionSensors's lane_capacity must be a whole number "
        "of vehicles, 1 or more, got 0",
        "lab.toml [modules.learner]: QLearning's seed must be a whole number, 0 or more, "
        "got -1",
        "lab.toml [modules.transfer]: TransferAgent's window must be a whole number of "
        "episodes, 1 or more, got 0",
        "lab.toml [modules.mapper]: Mapper's publish_every must be a whole number of "
        "readings, 1 or more, got 0",
        # (a rule relating fields, judged with the class's defaults: after the rest)
        "lab.toml [modules.control]: GapOut's max_green_s (40.0) must be at least "
        "min_green_s (50.0)",
        "lab.toml [modules.monitor]: HardwareMonitor's votes_needed and votes_of: an alarm "
        "needs votes_needed k of votes_of n windows, with 1 <= k <= n, not 6 of 5"
    ], done.stdout
    assert "6 problems in lab.toml" in done.stderr


def test_check_accepts_a_lossless_link_and_lists_lossless_when_a_policy_is_bad(
        tmp_path: Path) -> None:
    text = BROKEN.replace("perod", "period").replace("Scael", "Scale")
    (tmp_path / "lossless.toml").write_text(textwrap.dedent(
        text.replace('policy = "fifo"', 'policy = "lossless:8"')))
    done = pb3a("check", "lossless.toml", cwd=tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    (tmp_path / "bad.toml").write_text(textwrap.dedent(text))
    done = pb3a("check", "bad.toml", cwd=tmp_path)
    assert done.returncode == 1
    assert "bad policy 'fifo'" in done.stdout and "'lossless' or 'lossless:N'" in done.stdout


def test_check_reports_unreadable_and_non_toml_files(tmp_path: Path) -> None:
    missing = pb3a("check", "nowhere.toml", cwd=tmp_path)
    assert missing.returncode == 1
    assert "cannot read nowhere.toml" in missing.stderr
    (tmp_path / "bad.toml").write_text("[modules.tick\n")
    bad = pb3a("check", "bad.toml", cwd=tmp_path)
    assert bad.returncode == 1
    assert bad.stdout.startswith("bad.toml: not valid TOML")


def test_a_file_that_cannot_be_read_is_said_at_once_with_no_child_process(
        tmp_path: Path, capsys, monkeypatch) -> None:
    """A mistyped file name (or a directory) was said in the same words after a child
    Python process had started to plan the file and found it missing (0.3-0.7 s); each
    command that checks a file says it at once now."""
    def no_child(*args: object, **kwargs: object) -> None:
        raise AssertionError("a child process was started to read it")
    monkeypatch.setattr("pb3a.config.isolated.Child", no_child)
    for command in ("check", "graph", "run", "stress"):
        for name, why in (("nowhere.toml", "No such file or directory"),
                          ("", "Is a directory")):
            assert main([command, str(tmp_path / name)]) == 1, (command, name)
            said = capsys.readouterr().err
            assert f"pb3a {command}: cannot read {tmp_path / name}: {why}" in said, said
        # and a script, whether it exists or not (a child was started to say so too)
        assert main([command, str(tmp_path / "robot.py")]) == 1, command
        said = "".join(capsys.readouterr())
        assert f"{tmp_path / 'robot.py'}: a Python script, not a configuration" in said, said


def test_graph_writes_dot_and_svg(tmp_path: Path) -> None:
    done = pb3a("graph", str(PIPELINE), "-o", "out.svg", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    dot = (tmp_path / "out.dot").read_text()
    assert dot.startswith('digraph "pipeline" {')
    assert '"tick":"o_out" -> "scale":"i_x" [label="queue:64"];' in dot
    svg = (tmp_path / "out.svg").read_text()
    assert "<svg" in svg
    assert "scale" in svg


def test_graph_to_a_dot_file_writes_only_dot(tmp_path: Path) -> None:
    done = pb3a("graph", str(PIPELINE), "-o", "only.dot", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["only.dot"]
    assert "cluster_local" in (tmp_path / "only.dot").read_text()


def test_graph_without_graphviz_says_so(tmp_path: Path) -> None:
    empty = tmp_path / "bin"
    empty.mkdir()
    done = pb3a("graph", str(PIPELINE), "-o", "out.svg", cwd=tmp_path, path=str(empty))
    assert done.returncode == 1
    assert "Graphviz's 'dot' program is not on PATH" in done.stderr
    assert "-o FILE.dot" in done.stderr
    assert (tmp_path / "out.dot").exists()
    assert not (tmp_path / "out.svg").exists()


def test_graph_of_an_invalid_file_lists_its_problems(tmp_path: Path) -> None:
    (tmp_path / "broken.toml").write_text(textwrap.dedent(BROKEN))
    done = pb3a("graph", "broken.toml", cwd=tmp_path)
    assert done.returncode == 1
    assert len(done.stdout.splitlines()) == 3
    assert not list(tmp_path.glob("*.dot"))


def test_main_in_process(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(PIPELINE)]) == 0
    assert capsys.readouterr().out == "ok: 2 modules, 1 link\n"
    assert main(["graph", str(PIPELINE), "-o", "-"]) == 0
    assert capsys.readouterr().out.startswith('digraph "pipeline"')
    assert main([]) == 2
    assert "check" in capsys.readouterr().out


def test_the_two_node_example_is_valid_and_runs_across_nodes(capsys) -> None:
    example = REPO / "examples" / "two_nodes.toml"
    assert main(["check", str(example)]) == 0
    assert capsys.readouterr().out == "ok: 2 modules, 1 link\n"
    with System.load(example).launch() as run:
        eventually(lambda: run.stats().links["tick.out->scale.x"].values > 5,
                   what="values at node b")
        assert run.stats().links["tick.out->scale.x"].transport == "zmq"


@pytest.mark.parametrize("output", ["drawings", "out", ""])
def test_graph_to_a_directory_or_a_name_without_suffix_is_refused(tmp_path: Path,
                                                                 output: str) -> None:
    """-o DIR wrote DIR.dot beside the directory, then failed in dot's words; -o out
    wrote SVG into a file named out; -o '' was taken for no -o."""
    (tmp_path / "drawings").mkdir()
    done = pb3a("graph", str(PIPELINE), "-o", output, cwd=tmp_path)
    assert done.returncode == 1
    assert f"-o {output!r}: give a file, its suffix the format" in done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["drawings"]
    assert not list((tmp_path / "drawings").iterdir())


@pytest.mark.skipif(shutil.which("dot") is None, reason="needs Graphviz's dot")
def test_graph_to_a_format_graphviz_has_not_writes_nothing(tmp_path: Path) -> None:
    """-o map.v2 wrote map.dot, then failed with dot's list of formats; -o out.DOT ran
    dot -TDOT, which failed."""
    done = pb3a("graph", str(PIPELINE), "-o", "map.v2", cwd=tmp_path)
    assert done.returncode == 1
    assert "dot could not write map.v2" in done.stderr and "not recognized" in done.stderr
    assert list(tmp_path.iterdir()) == []
    done = pb3a("graph", str(PIPELINE), "-o", "out.DOT", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["out.DOT"]
    assert (tmp_path / "out.DOT").read_text().startswith("digraph")


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="the example pins node a to CPU 1")
def test_the_stress_example_of_the_readme_is_valid(capsys) -> None:
    """README's `pb3a stress` example named stressed.toml, which the repository lacked."""
    assert main(["check", str(REPO / "examples" / "stressed.toml")]) == 0
    assert capsys.readouterr().out == "ok: 2 modules, 1 link\n"
    assert "pb3a stress examples/stressed.toml " in (REPO / "README.md").read_text()


@pytest.mark.parametrize("command", [["check"], ["run", "--for", "30"],
                                     ["stress", "--for", "30", "--out", "stressed"]],
                         ids=["check", "run", "stress"])
def test_check_names_a_module_file_that_hangs_ends_or_crashes_as_imported_and_the_rest_too(
        tmp_path: Path, command: list[str]) -> None:
    """`pb3a check` imported the classes in its own process: a module file that looped as
    it was imported hung it for good, one that called os._exit() or sys.exit() ended it
    with that status and not a word (os._exit(0): "valid"), one that crashed killed it
    (SIGSEGV). Each is now a problem of the entry naming it, saying what happened and what
    to do, with the file's other problems, within seconds; the looping import and the
    process it started are gone when check returns. `pb3a run` and `pb3a stress` planned
    the file in their own process and hung there for good; they check it first the same
    way, and start nothing."""
    harmful = ("imported_hangs", "imported_ends", "imported_crashes", "imported_exits")
    _harmful_files(tmp_path, *harmful)
    _system(tmp_path, *harmful)
    with (tmp_path / "harmed.toml").open("a") as file:
        file.write('[modules.typo]\nclass = "imported_good:Dts"\n')
    try:
        began = time.monotonic()
        done = pb3a(*command, "--import-timeout", "1", "harmed.toml", cwd=tmp_path)
        took = time.monotonic() - began
    finally:
        pid_file = tmp_path / "started.pid"
        started = int(pid_file.read_text()) if pid_file.exists() else None
        with contextlib.suppress(ProcessLookupError):
            if started is not None and alive(started):
                os.kill(started, signal.SIGKILL)      # (the old check left it running)
    assert done.returncode == 1, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    hangs = (f"harmed.toml [modules.imported_hangs]: importing module 'imported_hangs' for "
             f"'imported_hangs:Bad' did not finish within 1 s, stuck at "
             f"{tmp_path / 'imported_hangs.py'}, line ")   # (its loop's, 4 or 5)
    assert lines[0].startswith(hangs) and lines[0].endswith(
        ": it loops or waits (for input, a lock, the network) as it is imported; make it "
        "return, or give a longer --import-timeout"), done.stdout
    assert lines[1:] == [
        "harmed.toml [modules.imported_ends]: importing module 'imported_ends' for "
        "'imported_ends:Bad' exited with status 3: it ends the process as it is imported "
        "(os._exit()?); a module must not exit when imported (put that code under if "
        "__name__ == '__main__':)",
        "harmed.toml [modules.imported_crashes]: importing module 'imported_crashes' for "
        "'imported_crashes:Bad' was killed by signal SIGSEGV (a crash in native code it runs "
        "as it is imported?): fix or remove that code",
        f"harmed.toml [modules.imported_exits]: importing module 'imported_exits' for "
        f"'imported_exits:Bad' failed at {tmp_path / 'imported_exits.py'}, line 2: it calls "
        "sys.exit(2) as it is imported; a module must not exit when imported (put that code "
        "under if __name__ == '__main__':)",
        "harmed.toml [modules.typo]: module 'imported_good' has no class 'Dts' (did you mean "
        f"'Dst'?); it was imported from {tmp_path / 'imported_good.py'}"], done.stdout
    assert f"pb3a {command[0]}: 5 problems in harmed.toml" in done.stderr
    assert took < 20, took
    assert not (tmp_path / "stressed").exists()
    assert started is not None
    eventually(lambda: not alive(started), what="the end of the process the import started")


def test_check_names_where_a_shared_import_hangs_and_waits_for_it_once(
        tmp_path: Path) -> None:
    """Four class files each importing a driver file that waits for good as it is
    imported: the check blamed each class file in turn, never the driver's, and waited
    the timeout four times (41 s at the default). It names the driver's file and line,
    and refuses its import at once after the first wait."""
    # (a driver that handles SIGUSR1 for its own ends: the signal the stacks were asked
    # with, which it then took over)
    (tmp_path / "hw.py").write_text("import signal, time\nsignal.signal(signal.SIGUSR1, "
                                    "lambda *_: None)\ntime.sleep(3600)\n")
    lines = ['name = "shared"']
    for number in range(1, 5):
        (tmp_path / f"c{number}.py").write_text(
            "import hw\nfrom pb3a import Module\n\nclass A(Module):\n    pass\n")
        lines += [f"[modules.m{number}]", f'class = "c{number}:A"']
    (tmp_path / "shared.toml").write_text("\n".join(lines) + "\n")
    began = time.monotonic()
    done = pb3a("check", "--import-timeout", "3", "shared.toml", cwd=tmp_path)
    took = time.monotonic() - began
    hw = tmp_path / "hw.py"
    how = (f"did not finish within 3 s{{}}, stuck at {hw}, line 3: it loops or waits (for "
           "input, a lock, the network) as it is imported; make it return, or give a longer "
           "--import-timeout")
    assert done.stdout.splitlines() == [
        "shared.toml [modules.m1]: importing module 'c1' for 'c1:A' " + how.format(""),
        *(f"shared.toml [modules.m{n}]: importing module 'c{n}' for 'c{n}:A' imports {hw}, "
          "which " + how.format(" as 'c1:A' imported it") for n in range(2, 5))]
    assert took < 4 * 3, took               # (one wait of 3 s, not four)


def test_where_an_import_is_stuck_is_read_from_stacks_that_come_slowly(monkeypatch) -> None:
    """A hung import was named without its place now and then in CI: its child's stacks
    come in many small writes, the importing thread's last, and were read until a tenth
    of a second went by without one; a child starved of CPU halfway gave the others'
    alone. They are read until the importing thread's stack is whole."""
    from pb3a.loading import import_child

    others = ('Thread 0x00007f95367ad6c0 (most recent call first):\n'
              '  File "/usr/lib/python3.11/threading.py", line 982 in run\n\n')
    importing = ('Current thread 0x00007f9537444b80 (most recent call first):\n'
                 '  File "/project/hangs.py", line 4 in <module>\n'
                 '  File "<frozen importlib._bootstrap>", line 241 in _call_with_frames_removed\n'
                 '  File "<string>", line 1 in <module>\n')
    child = object.__new__(import_child.Child)
    child.process = types.SimpleNamespace(pid=os.getpid())
    child._stacks, stacks = os.pipe()
    monkeypatch.setattr(os, "kill", lambda pid, signum: None)     # (it writes them here)

    def write_slowly() -> None:
        os.write(stacks, others.encode())
        time.sleep(0.3)                             # (starved of CPU)
        for line in importing.splitlines(keepends=True):
            os.write(stacks, line.encode())

    writer = threading.Thread(target=write_slowly)
    writer.start()
    try:
        stuck = child.stuck_at(wait=5.0)
    finally:
        writer.join()
        os.close(stacks)
        os.close(child._stacks)
    assert (stuck.file, stuck.line, stuck.module_file) == ("/project/hangs.py", 4,
                                                           "/project/hangs.py")


def test_check_and_graph_keep_what_an_import_prints_off_their_output(tmp_path: Path) -> None:
    """What a module file printed as it was imported came first on check's stdout (before
    "ok: ...") and inside graph's DOT (`-o -`); it goes to stderr now, nothing lost."""
    _harmful_files(tmp_path, "imported_prints")
    _system(tmp_path, "imported_prints")
    done = pb3a("check", "harmed.toml", cwd=tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout == "ok: 2 modules, 1 link\n"
    assert "hello from an import" in done.stderr
    drawn = pb3a("graph", "harmed.toml", "-o", "-", cwd=tmp_path)
    assert drawn.returncode == 0, drawn.stderr
    assert drawn.stdout.startswith('digraph "harmed" {') and "hello" not in drawn.stdout
    assert '"imported_prints":"o_out" -> "dst":"i_x"' in drawn.stdout
    assert "hello from an import" in drawn.stderr


def test_check_of_a_module_file_that_reads_input_as_imported_does_not_wait_for_it(
        tmp_path: Path) -> None:
    """A module file that called input() as it was imported made `pb3a check` wait for a
    line on its stdin (a terminal's: for good); the import now reads none, and fails at
    once at its line."""
    _harmful_files(tmp_path, "imported_reads")
    _system(tmp_path, "imported_reads")
    held, open_end = os.pipe()                  # a stdin that never ends, as a terminal's
    try:
        done = pb3a("check", "harmed.toml", cwd=tmp_path, stdin=held)
    finally:
        os.close(held)
        os.close(open_end)
    assert done.returncode == 1, done.stdout + done.stderr
    assert done.stdout.startswith(
        "harmed.toml [modules.imported_reads]: importing module 'imported_reads' for "
        f"'imported_reads:Bad' failed at {tmp_path / 'imported_reads.py'}, line 1: EOFError")


FORGETFUL = """
    from pb3a import Agent, Input, Module, Output

    class Ctl(Module):                  # a step() and no period: never stepped
        pose = Input(float)
        command = Output(float)

        def step(self):
            self.command.write(1.0)

    class Drv(Module):
        period = 0.05
        command = Input(float)
        pose = Output(float)
        spare = Output(float)           # read by nothing, as a spare reading is

        def step(self):
            self.pose.write(0.0)

    class SelfTimed(Module):            # gives itself its period as it sets up
        def setup(self):
            self.period = 0.1

        def step(self):
            pass

    class Alone(Module):                # no link touches it (wired as the system runs)
        x = Input(int)

        def on_input(self, port):
            pass

    class Watcher(Agent):               # an agent's ports are its own business
        seen = Input(str)
        said = Output(str)
    """
FORGOTTEN = """
    name = "robot"
    [modules.ctl]
    class = "forgetful:Ctl"
    [modules.driver]
    class = "forgetful:Drv"
    [modules.timed]
    class = "forgetful:SelfTimed"
    [modules.alone]
    class = "forgetful:Alone"
    [modules.watcher]
    class = "forgetful:Watcher"
    [[links]]
    from = "driver.pose"
    to = "ctl.pose"
"""


def test_check_notes_a_step_with_no_period_and_a_forgotten_link_and_exits_0(
        tmp_path: Path) -> None:
    """A configuration that does nothing passed with a bare "ok": a class with a step()
    and no period is never stepped, an input no link feeds never gets a value (a
    reviewer's robot never moved). Each is a note, the exit status 0; a module that
    gives itself a period, one no link touches, an agent's ports and an output read by
    nothing alone (a spare reading) are no note, and the shipped configurations have
    none."""
    (tmp_path / "forgetful.py").write_text(textwrap.dedent(FORGETFUL))
    (tmp_path / "robot.toml").write_text(textwrap.dedent(FORGOTTEN))
    done = pb3a("check", "robot.toml", cwd=tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.splitlines() == [
        "robot.toml [modules.ctl]: note: ctl (forgetful:Ctl) defines step() but has no "
        "period: its step() never runs (give it period = SECONDS in its entry or on its "
        "class), unless its period is set as it runs (pb3a set ADDR ctl period=..., an "
        "agent's set_state)",
        "robot.toml [modules.driver]: note: driver.command is fed by nothing, and "
        "ctl.command is read by nothing: a link forgotten? ([[links]] from = "
        '"ctl.command", to = "driver.command")',
        "ok: 5 modules, 1 link"], done.stdout
    fixed = textwrap.dedent(FORGOTTEN).replace(       # a period, the link made: no note
        'class = "forgetful:Ctl"', 'class = "forgetful:Ctl"\nperiod = 0.05')
    (tmp_path / "robot.toml").write_text(
        f'{fixed}[[links]]\nfrom = "ctl.command"\nto = "driver.command"\n')
    done = pb3a("check", "robot.toml", cwd=tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout == "ok: 5 modules, 2 links\n"
    for shipped in ("examples/pipeline.toml", "examples/stressed.toml",     # (few notes:
                    "examples/two_nodes.toml", "scenarios/mapping.toml",   # here none)
                    "scenarios/sim_to_real.toml", "scenarios/traffic.toml"):
        done = pb3a("check", str(REPO / shipped), cwd=tmp_path)
        assert done.returncode == 0, done.stdout + done.stderr
        assert done.stdout.startswith("ok: ") and len(done.stdout.splitlines()) == 1, \
            done.stdout


def test_an_input_fed_by_nothing_is_noted_with_the_output_that_alone_could_feed_it(
        tmp_path: Path) -> None:
    """An input fed by nothing, of a module a link touches, is noted though no output
    read by nothing could alone feed it (two could, neither of its name: none is named);
    of two, one of its name is named."""
    (tmp_path / "forgetful.py").write_text(textwrap.dedent(FORGETFUL) + textwrap.dedent("""
        class Turn(Module):
            heading = Input(float)
            x = Input(float)

            def on_input(self, port):
                pass
        """))
    (tmp_path / "robot.toml").write_text(textwrap.dedent("""
        name = "robot"
        [modules.driver]
        class = "forgetful:Drv"
        [modules.ctl]
        class = "forgetful:Ctl"
        period = 0.05
        [modules.turn]
        class = "forgetful:Turn"
        [[links]]
        from = "ctl.command"
        to = "driver.command"
        [[links]]
        from = "ctl.command"
        to = "turn.x"
        """))
    done = pb3a("check", "robot.toml", cwd=tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.splitlines() == [
        "robot.toml [modules.ctl]: note: ctl.pose is fed by nothing, and driver.pose is "
        'read by nothing: a link forgotten? ([[links]] from = "driver.pose", to = '
        '"ctl.pose")',
        "robot.toml [modules.turn]: note: turn.heading is fed by nothing: no link feeds it, "
        "so it never gets a value (link an output to it, unless a link made as the system "
        "runs will)",
        "ok: 3 modules, 2 links"], done.stdout
