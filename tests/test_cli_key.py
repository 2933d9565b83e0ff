"""The cluster key file on the command line: ``pb3a key new`` makes one every command
accepts, and every command refuses one other users could read, with one sentence."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from pb3a.cli.main import main
from pb3a.transport.auth import ClusterKey

pytestmark = pytest.mark.timeout(60)

REPO = Path(__file__).resolve().parent.parent


def test_key_new_writes_a_private_key_once(tmp_path, capsys) -> None:
    path = tmp_path / "cluster.key"
    assert main(["key", "new", str(path)]) == 0
    assert f"wrote a new cluster key to {path} (mode 0600)" in capsys.readouterr().out
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    written, named = path.read_bytes(), {"PB3A_KEY_FILE": str(path)}
    key = ClusterKey.load(named)
    assert main(["key", "new", str(path)]) == 1                # never over a key in use
    assert f"{path} exists" in capsys.readouterr().err
    assert path.read_bytes() == written and ClusterKey.load(named) == key
    assert main(["key", "new", str(tmp_path / "nowhere" / "k")]) == 1
    assert "No such file or directory" in capsys.readouterr().err
    for where, said in (("", "'' is empty"), (str(tmp_path), "is a directory")):
        assert main(["key", "new", where]) == 1
        assert said in capsys.readouterr().err                  # not ". exists"


def test_every_command_refuses_a_key_file_others_can_read(tmp_path) -> None:
    # (each in a process of its own: a command may start helper processes that keep
    # the environment they were started with)
    path = tmp_path / "cluster.key"
    path.write_text("s" * 64)
    path.chmod(0o640)
    env = {**os.environ, "PB3A_KEY_FILE": str(path), "PYTHONPATH": str(REPO)}
    del env["PB3A_KEY"]
    refusal = (f"the cluster key file {path} has mode 0640, so other users can read or "
               f"change it; make it private with `chmod 600 {path}`")
    for command, args in (("status", ["tcp://127.0.0.1:1"]),
                          ("node start", ["--name", "n", "--listen", "tcp://127.0.0.1:0"]),
                          ("modules serve", [str(tmp_path)]),
                          ("run", [str(REPO / "examples" / "pipeline.toml"), "--for", "1"])):
        done = subprocess.run([sys.executable, "-m", "pb3a", *command.split(), *args],
                              env=env, capture_output=True, text=True, timeout=30, check=False)
        assert (done.returncode, done.stderr) == (1, f"pb3a {command}: {refusal}\n"), command
