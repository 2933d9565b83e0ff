"""A system launched again from the same Python process (a notebook, a parameter sweep)
runs its module files as they are then: the process's one forkserver, started by the
first launch, holds the files as they were, and so did the launcher's own cache."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import alive, eventually

pytestmark = pytest.mark.timeout(120)

REPO = Path(__file__).resolve().parent.parent

# A module file that notes each import (the importing process's pid, a line in
# ``NAME.imports``); ``{body}`` ends its class.
NOTED = """
import os
with open(os.path.join(os.path.dirname(__file__), "{name}.imports"), "a") as noted:
    noted.write(f"{{os.getpid()}}\\n")
from pb3a import Module

class {cls}(Module):
    version = 0
{body}
"""
# The edited module: its step says which file it runs (``{version}``); from the second
# edit on, it has a field the first did not.
EDITED = """    {extra}
    def step(self):
        self.version = {version}
"""
STEADY = """    def step(self):
        self.version = 1
"""

# The program: three launches in one process, the module file edited between them (its
# mtime moved on, as an editor's save moves it; the second time its size changes too):
# by reference, then as the class the program reloaded itself. It prints what each
# launch's module read (or how the launch failed), as JSON.
PROGRAM = """
import importlib, json, os, sys, time
from pb3a import System

NOTED, EDITED = sys.argv[1], sys.argv[2]

def edit(version, extra=""):
    path = "edited.py"
    before = os.stat(path).st_mtime_ns if os.path.exists(path) else 0
    with open(path, "w") as out:
        out.write(NOTED.format(name="edited", cls="V",
                               body=EDITED.format(version=version, extra=extra)))
    if before:
        os.utime(path, ns=(before + 10**9, before + 10**9))

def launched(cls, **state):
    system = System("relaunched").add("v", cls, period=0.01, state=state)
    system.add("s", "steady:S", period=0.01)
    try:
        with system.launch(timeout=10) as run:
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                seen = run.state("v")
                if seen["version"] and run.state("s")["version"]:
                    return seen
                time.sleep(0.01)
            return {"timed out": True}
    except Exception as exc:                      # (said, and the next launch tried)
        return {"failed": f"{type(exc).__name__}: {exc}"}

edit(1)
first = launched("edited:V")
edit(2, "extra = 0")
second = launched("edited:V", extra=7)
import edited
edit(33, "extra = 0")
importlib.reload(edited)
third = launched(edited.V, extra=8)
print(json.dumps([first, second, third]), flush=True)
"""


def test_a_system_launched_again_in_one_process_runs_its_edited_module_file(
        tmp_path: Path) -> None:
    """The second launch ran the file from before the edit: its workers came from the
    forkserver the first launch started, which had imported it, and the launcher checked
    the class it had imported then (a field the edit added was refused). Now the
    launcher imports a file edited since anew, and so do the workers, from a reference
    or from the class the program reloaded; a file not edited is imported by no worker."""
    (tmp_path / "steady.py").write_text(NOTED.format(name="steady", cls="S", body=STEADY))
    path = os.pathsep.join([str(tmp_path), str(REPO)])
    done = subprocess.run([sys.executable, "-c", PROGRAM, NOTED, EDITED], cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": path}, capture_output=True,
                          text=True, timeout=90)
    assert done.returncode == 0, done.stderr[-3000:]
    first, second, third = json.loads(done.stdout.splitlines()[-1])
    assert first.get("version") == 1, first
    assert (second.get("version"), second.get("extra")) == (2, 7), \
        f"the second launch did not run the edited file: {second}"
    assert (third.get("version"), third.get("extra")) == (33, 8), \
        f"a launch given the class the program reloaded did not run the edited file: {third}"
    # (the launcher and the forkserver imported it; the workers forked with it)
    steady = (tmp_path / "steady.imports").read_text().split()
    assert len(steady) == 2, f"steady.py imported {len(steady)} times: {steady}"
    every = {int(pid) for name in ("steady", "edited")
             for pid in (tmp_path / f"{name}.imports").read_text().split()}
    eventually(lambda: not any(alive(pid) for pid in every),
               what="the program's forkserver and workers gone")
