"""docs/guarantees.md names a test for each promise: every named test must exist."""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

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
