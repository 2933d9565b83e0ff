"""The command line reads its arguments without the runtime: ``pb3a --help``, a
command's ``--help`` and a mistaken argument are answered before anything of ZeroMQ,
numpy, the launcher or the nodes is imported (all of it took a third of a second), and
a command imports its own implementation only, once it runs.

Each check runs in a fresh interpreter, whose ``sys.modules`` shows what was imported.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

pytestmark = pytest.mark.timeout(60)

REPO = Path(__file__).resolve().parent.parent

# the runtime, and the commands' implementations
HEAVY = ("zmq", "numpy", "cloudpickle", "psutil", "pb3a.system", "pb3a.launch", "pb3a.node",
         "pb3a.worker", "pb3a.daemons", "pb3a.transport", "pb3a.config", "pb3a.loading",
         "pb3a.model", "pb3a.manager")
IMPLEMENTATIONS = ("pb3a.cli.files", "pb3a.cli.running_system", "pb3a.cli.status",
                   "pb3a.cli.stress", "pb3a.cli.daemons", "pb3a.cli.keys", "pb3a.cli.manager")
COMMANDS = ["check", "graph", "run", "status", "state", "set", "migrate", "swap", "reload",
            "relink", "add", "remove", "restart", "nodes", "logs", "events", "stress", "scenario",
            "modules serve", "node start", "key new", "manager"]

# In a fresh interpreter: run main with each argv of argv[1] (JSON); print, per argv,
# its exit status and the modules of argv[2] (JSON) imported so far.
PROBE = """
import contextlib, io, json, sys
from pb3a.cli.main import main
argvs, watched = json.loads(sys.argv[1]), tuple(json.loads(sys.argv[2]))
found = []
for argv in argvs:
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        try:
            status = main(argv)
        except SystemExit as exc:
            status = exc.code
    loaded = sorted(name for name in sys.modules
                    if any(name == w or name.startswith(w + ".") for w in watched))
    found.append([argv, status, loaded])
print(json.dumps(found))
"""


def _probe(argvs: list[list[str]], watched: tuple[str, ...]) -> list[list]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, "-c", PROBE, json.dumps(argvs), json.dumps(watched)],
                          env=env, cwd=REPO, capture_output=True, text=True, timeout=30,
                          check=True)
    return json.loads(done.stdout)


def test_help_and_mistaken_arguments_import_nothing_of_the_runtime() -> None:
    helps = [["--help"], *([*command.split(), "--help"] for command in COMMANDS)]
    mistakes = [[], ["nosuchcommand"], ["run"], ["node", "start"], ["modules"],
                ["run", "x.toml", "--for", "nan"], ["stress", "x.toml", "--cut-node", "b"],
                ["stress", "x.toml", "--load", "0:lots"],
                ["status", "tcp://h:1", "--timeout", "inf"], ["set", "tcp://h:1", "m"]]
    found = _probe(helps + mistakes, HEAVY + IMPLEMENTATIONS)
    assert len(found) == len(helps) + len(mistakes)
    for argv, status, loaded in found:
        assert status == (0 if "--help" in argv else 2), argv     # (answered, not crashed)
        assert loaded == [], (argv, loaded)


def test_a_command_imports_its_own_implementation_only(tmp_path: Path) -> None:
    [(_, status, loaded)] = _probe([["key", "new", str(tmp_path / "cluster.key")]],
                                   IMPLEMENTATIONS)
    assert status == 0 and (tmp_path / "cluster.key").is_file()
    assert loaded == ["pb3a.cli.keys"]


def test_check_and_graph_import_neither_the_runtime_nor_the_file_s_classes() -> None:
    """`pb3a check` and `pb3a graph` planned the file in their own process, importing the
    runtime and every class the file names (whose module may hang, exit or crash as it is
    imported); a child process plans it now, and theirs imports neither (of
    ``pb3a.loading``, only the standard-library-only module that starts that child)."""
    pipeline = str(REPO / "examples" / "pipeline.toml")
    found = _probe([["check", pipeline], ["graph", pipeline, "-o", "-"]],
                   ("zmq", "numpy", "pb3a.system", "pb3a.launch", "pb3a.node", "pb3a.worker",
                    "pb3a.transport", "pb3a.model", "pb3a.loading", "pb3a.config.compiler",
                    "examples"))
    child = ["pb3a.loading", "pb3a.loading.import_child"]
    assert [(status, loaded) for _, status, loaded in found] == [(0, child), (0, child)], found


def test_every_command_names_a_function_that_runs_it() -> None:
    """Each command's handler is named in the grammar (``"module:function"``): it must
    name a function, and each command on a running system an operation."""
    from pb3a.cli.commands import parser
    from pb3a.cli.main import handler_of
    from pb3a.cli.running_system import OPERATIONS

    def walk(p: argparse.ArgumentParser, words: list[str]) -> list[tuple[str, Any]]:
        subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs:
            return [(" ".join(words), p)]
        return [found for name, sub in subs[0].choices.items()
                for found in walk(sub, [*words, name])]

    commands = walk(parser(), [])
    assert [command for command, _ in commands] == COMMANDS
    for command, sub in commands:
        assert callable(handler_of(sub.get_default("handler"))), command
    assert {command: sub.get_default("operation") for command, sub in commands
            if sub.get_default("operation") is not None} == {name: name for name in OPERATIONS}
