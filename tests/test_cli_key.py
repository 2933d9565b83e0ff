"""The cluster key file on the command line: ``pb3a key new`` makes one every command
accepts, and every command refuses one other users could read, with one sentence."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pb3a.cli.main import main
from pb3a.transport.auth import ClusterKey

pytestmark = pytest.mark.timeout(60)

REPO = Path(__file__).resolve().parent.parent


def test_key_new_says_to_set_the_whole_path_of_a_key_made_here(tmp_path, capsys,
                                                                  monkeypatch) -> None:
    """It said to set PB3A_KEY_FILE=k.key, which names no file from another directory."""
    monkeypatch.chdir(tmp_path)
    assert main(["key", "new", "k.key"]) == 0
    assert f"set PB3A_KEY_FILE={tmp_path / 'k.key'}" in capsys.readouterr().out


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


def test_a_daemon_without_a_key_refuses_to_start_and_makes_none(tmp_path) -> None:
    """`pb3a node start` and `pb3a modules serve` with no key set and none in ~/.pb3a
    made one there that no other machine had, served with it, and only the launcher's
    side said, later, that the node "runs with another cluster key" (the deploy
    walkthrough). `pb3a run` still makes one for its own machine's nodes."""
    home = tmp_path / "home"
    home.mkdir()
    env = {**{k: v for k, v in os.environ.items() if k not in ("PB3A_KEY", "PB3A_KEY_FILE")},
           "HOME": str(home), "PYTHONPATH": str(REPO)}
    where = home / ".pb3a" / "cluster.key"
    for command, args in (("node start", ["--name", "n", "--listen", "tcp://127.0.0.1:0"]),
                          ("modules serve", [str(tmp_path)])):
        began = time.monotonic()
        done = subprocess.run([sys.executable, "-m", "pb3a", *command.split(), *args],
                              env=env, capture_output=True, text=True, timeout=10, check=False)
        took = time.monotonic() - began
        assert (done.returncode, done.stdout) == (2, ""), (command, done.stderr)
        assert done.stderr == (
            f"pb3a {command}: no cluster key: $PB3A_KEY and $PB3A_KEY_FILE are not set, and "
            f"{where} does not exist; a daemon makes no key of its own, which no other "
            f"machine would have: copy the cluster's key file here (`pb3a key new PATH` "
            f"makes the first one), then set PB3A_KEY_FILE=PATH or put it at {where} "
            f"(mode 0600)\n"), command
        assert took < 5.0, (command, took)          # (about 0.25 s: the interpreter's start)
        assert not (home / ".pb3a").exists(), command
    done = subprocess.run([sys.executable, "-m", "pb3a", "run",
                           str(REPO / "examples" / "pipeline.toml"), "--for", "0.5"],
                          env=env, capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert stat.S_IMODE(where.stat().st_mode) == 0o600          # made on first use, as before


def test_a_command_that_connects_without_a_key_makes_none_and_says_where_to_get_it(
        tmp_path) -> None:
    """`pb3a status ADDR` (and every command that connects to a running system) with no
    key set and none in ~/.pb3a made one there, said nothing of it, and was told the
    launcher "runs with another cluster key": a key made here is one no launcher has.
    It makes none and says where the cluster's is, at once; `pb3a run` still makes one
    (checked above)."""
    home = tmp_path / "home"
    home.mkdir()
    env = {**{k: v for k, v in os.environ.items() if k not in ("PB3A_KEY", "PB3A_KEY_FILE")},
           "HOME": str(home), "PYTHONPATH": str(REPO)}
    where = home / ".pb3a" / "cluster.key"
    for command, args in (("status", ["tcp://127.0.0.1:1"]),
                          ("set", ["tcp://127.0.0.1:1", "scale", "gain=2"])):
        done = subprocess.run([sys.executable, "-m", "pb3a", command, *args], env=env,
                              capture_output=True, text=True, timeout=10, check=False)
        assert (done.returncode, done.stdout) == (1, ""), (command, done.stderr)
        assert done.stderr == (
            f"pb3a {command}: no cluster key: $PB3A_KEY and $PB3A_KEY_FILE are not set, and "
            f"{where} does not exist; a running system's launcher has its cluster's key, "
            "and one made here would be refused: copy that key file here (the launcher "
            "machine's ~/.pb3a/cluster.key, or the file its $PB3A_KEY_FILE names), then "
            f"set PB3A_KEY_FILE=PATH or put it at {where} (mode 0600)\n"), command
        assert not (home / ".pb3a").exists(), command
