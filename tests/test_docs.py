"""docs/guarantees.md names a test for each promise: every named test must exist."""

from __future__ import annotations

import ast
import functools
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@functools.cache                # (a file is named hundreds of times: parsed once)
def _tests_in(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    return {node.name for node in ast.walk(tree)
            if isinstance(node, ast.FunctionDef)
            and node.name.startswith(("test_", "no_", "pytest_session"))}


def test_every_test_named_in_the_guarantees_exists() -> None:
    text = (ROOT / "docs" / "guarantees.md").read_text()
    missing, named, current = [], 0, None
    for file, name in re.findall(r"`(?:(\w+\.py))?::(\w+)(?:\[[^\]]*\])?`", text):
        current = file or current
        assert current is not None, f"::{name} names no file"
        named += 1
        if name not in _tests_in(ROOT / "tests" / current):
            missing.append(f"{current}::{name}")
    assert named >= 30
    assert not missing, f"guarantees.md names tests that do not exist: {missing}"


BENCHES = sorted(path.name for path in (ROOT / "bench").glob("*.py")
                 if not path.name.startswith("_"))


@pytest.mark.parametrize("bench", BENCHES)
def test_every_bench_says_what_it_measures_on_help_and_runs_nothing(bench: str) -> None:
    """``bench/README.md`` and ``docs/performance.md`` give the benches' commands; five of
    them ran the whole bench on ``--help`` (and on a mistaken option) instead."""
    done = subprocess.run([sys.executable, str(ROOT / "bench" / bench), "--help"],
                          cwd=ROOT, capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage:"), done.stdout       # (not the JSON of a run)


def test_the_readme_tells_every_event_kind() -> None:
    """Event kinds were listed nowhere but in the code, and the adaptive loop example
    waited for a kind that does not exist ("swap")."""
    from pb3a.events import KINDS
    table = (ROOT / "README.md").read_text().split("**Events.**", 1)[1].split("**", 1)[0]
    told = set(re.findall(r"`([a-z_]+)`", table))
    assert set(KINDS) <= told, sorted(set(KINDS) - told)
    example = (ROOT / "examples" / "adaptive_loop.py").read_text()
    assert set(re.findall(r'kind == "([a-z_]+)"', example)) <= set(KINDS)
