"""``pb3a manager``: it prints its URL with a token, serves, launches a system from the
page, and stops it with itself on Ctrl-C; mistakes get one sentence."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest
from conftest import alive

from pb3a.cli.main import main

pytestmark = pytest.mark.timeout(60)

REPO = Path(__file__).resolve().parent.parent


def _call(url: str, token: str, method: str = "GET") -> dict:
    request = urllib.request.Request(url, method=method,
                                     headers={"Authorization": f"Bearer {token}"})
    with urllib.request.urlopen(request, timeout=10) as answer:
        return json.load(answer)


def test_the_command_serves_launches_and_stops_everything_on_ctrl_c() -> None:
    pytest.importorskip("uvicorn", reason="the manager needs the 'ui' extra")
    process = subprocess.Popen([sys.executable, "-m", "pb3a", "manager",
                                str(REPO / "examples" / "pipeline.toml"),
                                "--listen", "127.0.0.1:0"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        banner = process.stdout.readline()
        assert banner.startswith("PB3A manager: http://127.0.0.1:"), banner
        base, _, token = banner.split()[-1].partition("/?token=")
        assert len(token) >= 43
        assert _call(f"{base}/api/system", token)["mode"] == "editing"
        assert _call(f"{base}/api/document/launch", token, "POST")["mode"] == "running"
        pids = [m["pid"] for m in _call(f"{base}/api/stats", token)["modules"].values()]
        assert pids and all(alive(pid) for pid in pids)
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=20) == 130
        assert not any(alive(pid) for pid in pids)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(5)
        process.stdout.close()
        process.stderr.close()


@pytest.mark.parametrize(("args", "words"), [
    (["no-such.toml"], "no file 'no-such.toml'"),
    (["--listen", "nowhere"], "--listen 'nowhere': give HOST:PORT"),
    (["tcp://127.0.0.1:1"], "no PB3A launcher answered at tcp://127.0.0.1:1"),
])
def test_a_mistake_gets_one_sentence_and_exit_status_1(args, words, capsys) -> None:
    pytest.importorskip("uvicorn", reason="the manager needs the 'ui' extra")
    assert main(["manager", *args]) == 1
    error = capsys.readouterr().err
    assert words in error and error.count("\n") == 1, error


def test_without_the_ui_extra_it_says_what_to_install(monkeypatch, capsys) -> None:
    monkeypatch.setitem(sys.modules, "starlette", None)      # as if not installed
    assert main(["manager"]) == 1
    assert "pip install 'pb3a[ui]'" in capsys.readouterr().err
