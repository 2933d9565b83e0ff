"""``pb3a manager``: it prints its URL with a token, serves, launches a system from the
page, and stops it with itself on Ctrl-C; attached to a running system it shows and
changes that system and leaves it running; mistakes get one sentence."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from conftest import alive, eventually

from pb3a import System
from pb3a.cli.main import main

pytestmark = pytest.mark.timeout(60)

REPO = Path(__file__).resolve().parent.parent


def _call(url: str, token: str, method: str = "GET") -> dict:
    request = urllib.request.Request(url, method=method,
                                     headers={"Authorization": f"Bearer {token}"})
    with urllib.request.urlopen(request, timeout=10) as answer:
        return json.load(answer)


def _kill_if_left(process: subprocess.Popen[str]) -> None:
    """Kill the manager's process if it still runs (a test that failed midway); close
    its pipes."""
    if process.poll() is None:
        process.kill()
        process.wait(5)
    process.stdout.close()
    process.stderr.close()


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
        _kill_if_left(process)


def test_on_every_interface_it_answers_to_this_machine_s_addresses() -> None:
    """Listening on 0.0.0.0, it refused a request to http://ADDRESS:PORT of this machine
    ("does not serve the host"): only its names were allowed, so another machine could
    not use it, the reason to listen there. (The request goes to loopback, the address
    in its Host header, as a browser elsewhere would send it.)"""
    pytest.importorskip("uvicorn", reason="the manager needs the 'ui' extra")
    import psutil

    own = [a.address for found in psutil.net_if_addrs().values() for a in found
           if a.family == socket.AF_INET and not a.address.startswith("127.")]
    if not own:
        pytest.skip("this machine has no IPv4 address but loopback")
    process = subprocess.Popen([sys.executable, "-m", "pb3a", "manager",
                                str(REPO / "examples" / "pipeline.toml"),
                                "--listen", "0.0.0.0:0"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        base, _, token = process.stdout.readline().split()[-1].partition("/?token=")
        port = base.rpartition(":")[2]
        for host in (f"{own[0]}:{port}", f"127.0.0.1:{port}"):
            request = urllib.request.Request(f"{base}/api/system", headers={
                "Authorization": f"Bearer {token}", "Host": host})
            with urllib.request.urlopen(request, timeout=10) as answer:
                assert json.load(answer)["mode"] == "editing", host
        refused = urllib.request.Request(f"{base}/api/system", headers={
            "Authorization": f"Bearer {token}", "Host": f"elsewhere.example:{port}"})
        with pytest.raises(urllib.error.HTTPError) as error:
            urllib.request.urlopen(refused, timeout=10)
        error.value.close()
        assert error.value.code == 403
    finally:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(20)
        finally:
            _kill_if_left(process)


def test_the_command_attaches_to_a_running_system_shows_it_and_changes_it() -> None:
    pytest.importorskip("uvicorn", reason="the manager needs the 'ui' extra")
    from sample_modules import FloatSource, Last, Scale
    from test_manager_browser import ManagerProcess

    system = System("attached").node("a").node("b")
    system.add("src", FloatSource, node="a")
    system.add("scale", Scale, node="a")
    system.add("sink", Last, node="b")
    system.link("src.out", "scale.x")
    system.link("scale.y", "sink.x")
    with system.launch() as run:
        address = run.listen()
        eventually(lambda: run.state("sink")["value"] == 2.0, what="1.0 x gain 2.0 at sink")
        manager = ManagerProcess(address)            # `pb3a manager tcp://...`
        try:
            shown = manager.api("GET", "/api/system")
            assert (shown["name"], shown["mode"], shown["address"]) == (
                "attached", "running", address)
            assert {name: (m["class"], m["node"]) for name, m in shown["modules"].items()} == {
                "src": ("sample_modules:FloatSource", "a"),
                "scale": ("sample_modules:Scale", "a"), "sink": ("sample_modules:Last", "b")}
            assert {link["key"] for link in shown["links"]} == {"src.out->scale.x",
                                                                 "scale.y->sink.x"}
            assert all(shown["nodes"][node]["up"] for node in ("a", "b"))
            stats = manager.api("GET", "/api/stats")
            assert {name: m["node"] for name, m in stats["modules"].items()} == {
                "src": "a", "scale": "a", "sink": "b"}
            edited = manager.api("POST", "/api/modules/scale/state", {"gain": 5})
            assert edited["fields"]["gain"]["value"] == 5.0
            assert run.state("scale")["gain"] == 5.0
            eventually(lambda: run.state("sink")["value"] == 5.0,
                       what="the running scale using the gain set through the manager")
        finally:
            started = time.monotonic()
            manager.stop()
            stopping = time.monotonic() - started
        assert manager.process.returncode in (0, 130, -signal.SIGINT)
        # Ctrl-C stops the manager at once (it does not wait out a call to the system it
        # has under way) and leaves the system it attached to running
        assert stopping < 4.0, f"pb3a manager took {stopping:.1f} s to stop on Ctrl-C"
        seen = run.state("sink")["seen"]
        eventually(lambda: run.state("sink")["seen"] > seen, what="the system still running")
        assert set(run.topology().modules) == {"src", "scale", "sink"}


@pytest.mark.parametrize(("args", "words"), [
    (["no-such.toml"], "no file 'no-such.toml'"),
    (["--listen", "nowhere"], "--listen 'nowhere': give HOST:PORT"),
    (["tcp://127.0.0.1:1"], "no PB3A launcher answered at tcp://127.0.0.1:1"),
    # HOST:PORT, as pb3a run prints it, is an address too (it was looked for as a file)
    (["127.0.0.1:1"], "no PB3A launcher answered at tcp://127.0.0.1:1"),
    (["system.tom"], "no file 'system.tom'"),
])
def test_a_mistake_gets_one_sentence_and_exit_status_1(args, words, capsys) -> None:
    pytest.importorskip("uvicorn", reason="the manager needs the 'ui' extra")
    # nothing listens at 127.0.0.1:1: --timeout bounds the wait for it, as for pb3a
    # status (it waited a launcher's 5 s whatever --timeout said)
    started = time.monotonic()
    assert main(["manager", "--timeout", "0.5", *args]) == 1
    assert time.monotonic() - started < 3.0
    error = capsys.readouterr().err
    assert words in error and error.count("\n") == 1, error


def test_it_listens_at_host_port_written_as_every_other_listen_of_the_command_line() -> None:
    from pb3a.cli.manager import listen_address

    for text in ("127.0.0.1:8080", "http://127.0.0.1:8080", "tcp://127.0.0.1:8080"):
        assert listen_address(text) == ("127.0.0.1", 8080), text
    assert listen_address("tcp://[::1]:0") == ("::1", 0)


def test_without_the_ui_extra_it_says_what_to_install(monkeypatch, capsys) -> None:
    monkeypatch.setitem(sys.modules, "starlette", None)      # as if not installed
    assert main(["manager"]) == 1
    assert "pip install 'pb3a[ui]'" in capsys.readouterr().err


def test_the_manager_reads_the_module_browser_s_catalog_as_it_starts(tmp_path: Path) -> None:
    """An editing page waits for the catalog (``/api/classes``) to draw, and its first
    reading takes a second or more (each file's import is tried in a child process
    first). The manager reads it as it starts, before any page asks for it: a module file
    beside the document is imported in the manager's own process with no request made."""
    pytest.importorskip("uvicorn", reason="the manager needs the 'ui' extra")
    from test_manager_browser import ManagerProcess

    marks = tmp_path / "imported_by"
    (tmp_path / "browsed_early.py").write_text(
        "import os\nfrom pb3a import Input, Module\n\n"
        "class Early(Module):\n    x = Input(float)\n"
        f"    _mark = open({str(marks)!r}, 'a').write(f'{{os.getpid()}}\\n')\n")
    (tmp_path / "lab.toml").write_text(
        'name = "lab"\n[modules.src]\nclass = "sample_modules:FloatSource"\n')
    manager = ManagerProcess(str(tmp_path / "lab.toml"))
    try:
        eventually(lambda: marks.exists() and str(manager.process.pid) in
                   marks.read_text().split(), timeout=20,
                   what="the manager importing the browser's files, unasked")
        classes = [entry["class"] for entry in manager.api("GET", "/api/classes")["classes"]]
        assert "browsed_early:Early" in classes
    finally:
        manager.stop()


def test_a_module_file_that_ends_or_crashes_as_imported_does_not_end_the_manager(
        tmp_path: Path) -> None:
    """The manager imported the module browser's files and a swap's class in its own
    process, which runs the system it launched: a file that crashed (SIGSEGV) or called
    os._exit() as it was imported (in a class body, or at its top) ended the manager and
    that system, without a word. Each is tried in a child process first now: the browser
    names the file and what happened, the swap is refused saying so, and the manager and
    its system run on."""
    pytest.importorskip("uvicorn", reason="the manager needs the 'ui' extra")
    from test_manager_browser import ManagerProcess

    head = "import ctypes, os\nfrom pb3a import Input, Module, Output\n\n"
    body = "class Bad(Module):\n    x = Input(float)\n    y = Output(float)\n"
    (tmp_path / "browsed_crashes.py").write_text(f"{head}{body}    ctypes.string_at(0)\n")
    (tmp_path / "browsed_ends.py").write_text(f"{head}{body}    os._exit(3)\n")
    (tmp_path / "swapped_ends.py").write_text(f"{head}os._exit(4)\n\n{body}")
    (tmp_path / "lab.toml").write_text(
        'name = "lab"\n[modules.src]\nclass = "sample_modules:FloatSource"\n'
        '[modules.scale]\nclass = "sample_modules:Scale"\n'
        '[[links]]\nfrom = "src.out"\nto = "scale.x"\n')
    manager = ManagerProcess(str(tmp_path / "lab.toml"))
    try:
        problems = manager.api("GET", "/api/classes")["problems"]
        assert "browsed_crashes: not imported: importing it was killed by signal SIGSEGV (a " \
               "crash in native code it runs as it is imported?): fix or remove that code" \
               in problems, problems
        assert "browsed_ends: not imported: importing it exited with status 3: it ends the " \
               "process as it is imported (os._exit()?); a module must not exit when " \
               "imported (put that code under if __name__ == '__main__':)" in problems, problems
        assert manager.api("POST", "/api/document/launch")["mode"] == "running"
        with pytest.raises(urllib.error.HTTPError) as refused:
            manager.api("POST", "/api/modules/scale/swap", {"class": "swapped_ends:Bad"})
        assert refused.value.code == 404
        assert json.loads(refused.value.read())["error"].startswith(
            "importing module 'swapped_ends' for 'swapped_ends:Bad' exited with status 4")
        stats = manager.api("GET", "/api/stats")
        assert stats["modules"]["scale"]["cls"] == "sample_modules:Scale"
        pids = [module["pid"] for module in stats["modules"].values()]
        assert all(alive(pid) for pid in pids)
    finally:
        manager.stop()
    assert manager.process.returncode in (0, 130, -signal.SIGINT)
