"""``pb3a check`` and ``pb3a graph`` as a user runs them: a separate process, exit codes, files."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from conftest import eventually

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


def pb3a(*args: str, cwd: Path, path: str | None = None) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    if path is not None:
        env["PATH"] = path
    return subprocess.run([sys.executable, "-m", "pb3a", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=60, check=False)


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
