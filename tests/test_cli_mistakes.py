"""Every command of ``pb3a`` given a wrong argument answers with a sentence and a non-zero
exit status, never a traceback (a user's ordinary mistakes, walked one by one)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pb3a import System
from pb3a.cli.main import main

pytestmark = pytest.mark.timeout(120)

REPO = Path(__file__).resolve().parent.parent


def _mistakes(tmp: Path) -> list[tuple[list[str], int, str]]:
    (tmp / "broken.toml").write_text("name = 'x\n")
    (tmp / "far.toml").write_text('[nodes.far]\naddress = "tcp://127.0.0.1:1"\n'
                                  '[modules.t]\nclass = "examples.pipeline:Ticker"\n'
                                  'node = "far"\n')
    (tmp / "latin1.toml").write_bytes(b'name = "\xff\xfe"\n')
    (tmp / "script.py").write_text("print('a script')\n")
    (tmp / "nowhere.toml").write_text(
        '[nodes.far]\naddress = "tcp://no-such-host.invalid:7100"\n'
        '[modules.t]\nclass = "examples.pipeline:Ticker"\nnode = "far"\n')
    missing = str(tmp / "missing.toml")
    pipeline = str(REPO / "examples" / "pipeline.toml")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        busy = taken.getsockname()[1]        # (free again: another test may take it)
    return [
        # each of these was a traceback
        (["check", str(tmp / "latin1.toml")], 1, "latin1.toml: not UTF-8 text (byte 8)"),
        (["run", str(tmp / "nowhere.toml"), "--for", "1"], 1,
         "node far: its address tcp://no-such-host.invalid:7100 names a host that does not "
         "resolve"),
        (["run", pipeline, "--for", "1", "--listen", "nonsense"], 1,
         "is not an address to listen on"),
        (["status", "tcp://a b:5"], 1, "pb3a status: no address is known for host 'a b'"),
        # --timeout bounds the connection too (it waited 5 s whatever it said)
        (["status", f"tcp://127.0.0.1:{busy}", "--timeout", "0.2"], 1,
         "within 0.2 s: check the address"),
        (["check", missing], 1, "cannot read"),
        (["check", str(tmp / "broken.toml")], 1, "not valid TOML"),
        # a script given where a configuration goes: it said "not valid TOML"
        (["run", str(tmp / "script.py")], 1,
         "a Python script, not a configuration (a TOML file): run it with python"),
        # a misspelt host: it waited 5 s, then said that no launcher answered
        (["status", "tcp://no-such-host.invalid:7000"], 1,
         "no address is known for host 'no-such-host.invalid'"),
        (["graph", missing], 1, "cannot read"),
        (["run", missing], 1, "cannot read"),
        # (the node's wait for its controller is cut short by the test: see below)
        (["run", str(tmp / "far.toml"), "--for", "1"], 1,
         "no node controller answered at tcp://127.0.0.1:1"),
        (["status", "nonsense"], 1, "is not a launcher's address"),
        (["status", "127.0.0.1:1", "--timeout", "0.5"], 1, "no PB3A launcher answered"),
        (["state", "tcp://127.0.0.1:1", "m", "--timeout", "0.3"], 1,
         "no PB3A launcher answered at tcp://127.0.0.1:1 within 0.3 s"),
        (["node", "start", "--name", "n", "--listen", "nonsense"], 1,
         "is not an address to listen on"),
        (["node", "start", "--name", "n", "--listen", "tcp://127.0.0.1:http"], 1,
         "is not an address to listen on"),
        (["node", "start", "--name", "", "--listen", "tcp://127.0.0.1:0"], 1,
         "bad node name '': use only ASCII letters"),       # (no configuration could name it)
        (["node", "start", "--name", "a b", "--listen", "tcp://127.0.0.1:0"], 1,
         "bad node name 'a b'"),
        (["modules", "serve", str(tmp / "nowhere")], 1, "nowhere"),
        (["modules", "serve", str(tmp / "broken.toml")], 1, "to serve modules from: it is a file"),
        (["scenario", "nope"], 2,
         "no scenario 'nope'; the scenarios: mapping, self-migration, sim-to-real"),
        (["stress", missing], 1, "cannot read"),
        (["stress", pipeline, "--cut-node", "local@1"], 1,
         "--cut-node: node 'local' has no address"),
        (["stress", pipeline, "--cut-node", "b@1"], 1, "--cut-node: there is no node 'b'"),
        (["stress", pipeline, "--kill-among", "tick,nope"], 1,
         "--kill-among: there is no module 'nope'"),
        (["stress", pipeline, "--load", "9999:50"], 1, "--load: cannot load CPU 9999"),
        (["stress", pipeline, "--migrate-every", "1"], 1,
         "--migrate-every: the system has one node"),
        # (it never ran, and the report said nothing of it)
        (["stress", pipeline, "--for", "3", "--load", "0:80@10"], 1,
         "--load: it starts at 10 s, not before the run's end at 3 s (--for)"),
    ]


def test_every_command_answers_a_mistake_with_a_sentence(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.chdir(REPO)                      # (far.toml names examples.pipeline)
    # Nothing listens at 127.0.0.1:1: a node's controller is waited for 0.5 s, not the
    # 5 s a real one may take to answer (the same sentence, 4.5 s sooner)
    monkeypatch.setattr("pb3a.node.remote.CONNECT_TIMEOUT", 0.5)
    for argv, status, said in _mistakes(tmp_path):
        assert main(argv) == status, argv
        out, err = capsys.readouterr()
        assert said in err or said in out, (argv, out, err)
        assert "Traceback" not in out + err, (argv, err)


@pytest.mark.parametrize("argv", [["check"], ["key"], ["node"], ["modules"],
                                  ["run", "x.toml", "--for", "soon"],
                                  ["run", "x.toml", "--for", "-1"],
                                  ["run", "x.toml", "--for", "nan"],
                                  ["status", "tcp://h:1", "--timeout", "inf"],
                                  ["state", "tcp://h:1", "m", "--timeout", "1e300"],
                                  ["state", "tcp://h:1", "m", "--timeout", "-5"],
                                  # (no launcher answers within 0 s: it blamed the address)
                                  ["status", "tcp://h:1", "--timeout", "0"],
                                  # (a NaN or negative limit switched the node's check off)
                                  ["node", "start", "--name", "n", "--max-cpu", "nan"],
                                  ["node", "start", "--name", "n", "--max-cpu", "-1"],
                                  ["node", "start", "--name", "n", "--min-memory", "-5"],
                                  ["stress", "x.toml", "--for", "nan"],
                                  ["stress", "x.toml", "--load", "0:50@nan"],
                                  ["node", "start"], ["migrate", "tcp://h:1", "m"],
                                  ["stress", "x.toml", "--load", "lots"],
                                  ["stress", "x.toml", "--load", "0:80@soon"],
                                  ["stress", "x.toml", "--cut-node", "b"],
                                  ["stress", "x.toml", "--for", "-1"],
                                  # (a step thread's clock overflowed: it died, "running")
                                  ["add", "tcp://h:1", "t", "m:C", "--period", "1e308"],
                                  ["manager", "x.toml", "--refresh", "1e308"]])
def test_arguments_that_do_not_parse_get_the_usage(argv, capsys) -> None:
    with pytest.raises(SystemExit) as stopped:
        main(argv)
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: pb3a") and "error:" in err


def test_state_given_before_the_positionals_says_where_it_goes(capsys) -> None:
    """`--state` took ADDR, NAME and the class as its pairs, and argparse then said they
    were missing, though they were given."""
    with pytest.raises(SystemExit) as stopped:
        main(["add", "--state", "gain=7", "tcp://h:1", "m", "m:C"])
    assert stopped.value.code == 2
    assert ("argument --state: 'tcp://h:1' is not NAME=VALUE: --state takes the words after "
            "it up to the next option, so give it after the command's ADDR, NAME and class"
            ) in capsys.readouterr().err


def test_a_key_of_the_wrong_length_is_a_sentence(tmp_path, capsys, monkeypatch) -> None:
    """... said before anything starts: `pb3a run` started its nodes' workers (and the
    process's forkserver, which every later worker inherits the bad key from) first."""
    monkeypatch.setenv("PB3A_KEY", "short")
    launched = []
    monkeypatch.setattr("pb3a.launch.running.Launcher", lambda *a, **k: launched.append(a))
    for argv in (["status", "tcp://127.0.0.1:1"],
                 ["node", "start", "--name", "n", "--listen", "tcp://127.0.0.1:0"],
                 ["run", str(REPO / "examples" / "pipeline.toml"), "--for", "1"]):
        assert main(argv) == 1, argv
        err = capsys.readouterr().err
        assert "the cluster key from $PB3A_KEY is 5 bytes; use at least 32" in err, (argv, err)
        assert "Traceback" not in err
    assert launched == []


def test_a_daemon_refuses_an_address_it_cannot_listen_on_saying_why(capsys) -> None:
    """A port in use is a sentence (not a traceback), a port beyond 65535 is not wrapped
    round to another, and a host that is not this machine's is not replaced by every
    interface under a banner naming the host: each exits 1 at once, nothing listens."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        mistakes = [(f"tcp://127.0.0.1:{port}", f"port {port} is in use"),
                    (f"tcp://127.0.0.1:{port + 65536}", "is not an address to listen on"),
                    ("tcp://192.0.2.1:0", "192.0.2.1 is not an address of this machine")]
        for daemon in (["node", "start", "--name", "n"],
                       ["modules", "serve", str(REPO / "examples")]):
            for listen, said in mistakes:
                assert main([*daemon, "--listen", listen]) == 1, (daemon, listen)
                out, err = capsys.readouterr()
                assert said in err and "Traceback" not in err, (daemon, listen, err)
                assert out == ""                            # no banner: it never served


def test_a_launcher_refuses_a_listen_address_that_is_not_this_machines(
        tmp_path: Path, capsys) -> None:
    """``pb3a run --listen`` (and ``System.launch(listen=...)``, ``Running.listen``) with a
    host no name server knows, or one that is not this machine's, bound every interface
    and printed "launcher at tcp://nowhere.invalid:7200", which nobody reaches: it is
    refused at once as ``pb3a node start`` refuses it, naming the address and what to
    give instead."""
    pipeline = str(REPO / "examples" / "pipeline.toml")
    mistakes = [("tcp://nowhere.invalid:7200",
                 "'nowhere.invalid' is not a host name this machine can resolve"),
                ("tcp://10.255.255.1:7200", "10.255.255.1 is not an address of this machine")]
    for listen, said in mistakes:
        started = time.monotonic()
        assert main(["run", pipeline, "--for", "5", "--listen", listen]) == 1, listen
        out, err = capsys.readouterr()
        assert f"pb3a run: cannot listen on {listen}: {said}" in err, err
        assert "0.0.0.0 for every interface" in err and "Traceback" not in err
        assert "launcher at" not in out and time.monotonic() - started < 4
    (tmp_path / "empty.toml").write_text('name = "empty"\n')
    with pytest.raises(ValueError, match=r"10\.255\.255\.1 is not an address of this machine"):
        System.load(tmp_path / "empty.toml").launch(listen="tcp://10.255.255.1:0")
    with System.load(tmp_path / "empty.toml").launch() as run:
        with pytest.raises(ValueError, match=r"'nowhere\.invalid' is not a host name"):
            run.listen("tcp://nowhere.invalid:0")
        assert run.listen("tcp://*:0").rpartition(":")[0] != "tcp://*"    # (still taken)


def test_modules_serve_names_a_directory_that_is_not_there(tmp_path: Path, capsys) -> None:
    """It said only "[Errno 2] No such file or directory: ..."."""
    (tmp_path / "a_file.py").write_text("")
    for root, said in ((tmp_path / "nowhere", "no directory"), (tmp_path / "a_file.py",
                                                               "it is a file")):
        assert main(["modules", "serve", str(root), "--listen", "tcp://127.0.0.1:0"]) == 1
        out, err = capsys.readouterr()
        assert f"pb3a modules serve: no directory {root} to serve modules from" in err, err
        assert said in err and "Errno" not in err and out == ""


def test_modules_serve_names_a_symlink_loop(tmp_path: Path, capsys) -> None:
    """A DIR that is a symlink to itself ended in a RuntimeError traceback."""
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    assert main(["modules", "serve", str(loop), "--listen", "tcp://127.0.0.1:0"]) == 1
    out, err = capsys.readouterr()
    assert f"pb3a modules serve: no directory {loop} to serve modules from" in err, err
    assert out == ""


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGHUP], ids=["Ctrl-C", "hangup"])
def test_stress_interrupted_writes_its_report_then_exits_130(tmp_path: Path,
                                                             signum: int) -> None:
    """It exited 0, as if it had run its whole time. Its terminal closing (SIGHUP to the
    group) killed the resource tracker its CPU load had started, whose successor
    printed a traceback for each segment freed."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "pb3a", "stress", str(REPO / "examples" / "pipeline.toml"),
         "--for", "60", "--sample", "0.5", "--load", "0:20", "--out", str(tmp_path)],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True)
    try:
        assert "values/s" in proc.stdout.readline()          # it runs
        os.killpg(proc.pid, signum)                            # a terminal's Ctrl-C, closing
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err
    assert "the report covers the run until it was interrupted" in err and "Traceback" not in err
    report = json.loads((tmp_path / "stress.json").read_text())
    assert "interrupted" in [m["kind"] for m in report["marks"]]     # (then the load's end)


def test_stress_that_cannot_write_its_report_says_so_after_its_summary(tmp_path: Path,
                                                                       capsys,
                                                                       monkeypatch) -> None:
    """It ended in a traceback, and the run's figures were lost with it."""
    monkeypatch.chdir(REPO)
    (tmp_path / "stress.json").mkdir()
    argv = ["stress", str(REPO / "examples" / "pipeline.toml"), "--for", "1", "--out",
            str(tmp_path)]
    assert main(argv) == 1
    out, err = capsys.readouterr()
    assert "values/s" in out                                  # the summary, first
    assert f"pb3a stress: cannot write the report to {tmp_path}" in err
    assert "Traceback" not in err


def test_a_second_ctrl_c_while_stress_stops_its_loads_leaves_no_node_frozen() -> None:
    """The loads stopped first (up to seconds each): a Ctrl-C then ended the clean-up
    before the frozen nodes were thawed, which stayed stopped (SIGSTOP) for good."""
    from pb3a.cli.stress import Stress

    thawed: list[str] = []

    def stop_load(load: str, on: bool) -> None:
        raise KeyboardInterrupt               # the second Ctrl-C, as a load stops

    stress = Stress.__new__(Stress)
    stress.loads, stress.freezes = [("load", None)], [("node b", None), ("node c", None)]
    stress._go = lambda: None                                   # type: ignore[method-assign]
    stress._load = stop_load                                    # type: ignore[method-assign]
    stress._cut = lambda freeze, on: thawed.append(freeze)      # type: ignore[method-assign]
    with pytest.raises(KeyboardInterrupt):
        stress.run_on(None)                                     # type: ignore[arg-type]
    assert thawed == ["node b", "node c"]
