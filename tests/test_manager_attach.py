"""The manager attached to a system launched elsewhere (``pb3a manager tcp://...``):
its module browser and swap picker ask the system's own module servers."""

from __future__ import annotations

import os
import signal
import textwrap
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("starlette", reason="the manager needs the 'ui' extra")

from conftest import eventually
from test_manager_api import manager_client

from pb3a import System, connect
from pb3a.daemons.module_server import ModuleServer
from pb3a.loading import served as served_code
from pb3a.manager.catalog import Catalog
from pb3a.manager.document import Document
from pb3a.manager.session import Session
from pb3a.transport.auth import ClusterKey

pytestmark = pytest.mark.timeout(60)

SERVED = '''
"""Classes only the module server has."""
from pb3a import Input, Module, Output

class Emitter(Module):
    """Writes its value."""
    out = Output(float)
    period = 0.01
    value = 1.0

    def step(self):
        self.out.write(self.value)

class Halver(Module):
    """Halves what it reads."""
    x = Input(float)
    y = Output(float)

    def on_input(self, port):
        self.y.write(port.read() / 2)

class Thirder(Halver):
    """Divides by three: the same ports as Halver."""

    def on_input(self, port):
        self.y.write(port.read() / 3)

class Worder(Module):
    """Reads text: does not fit where Halver is."""
    x = Input(str)
    y = Output(float)
'''


@pytest.fixture
def server(tmp_path: Path) -> Iterator[ModuleServer]:
    root = tmp_path / "code"
    root.mkdir()
    (root / "pb3a_manager_served.py").write_text(textwrap.dedent(SERVED))
    served = ModuleServer(root, ClusterKey.load())
    yield served
    served.close()


def test_attached_the_catalog_and_swaps_come_from_the_system_s_module_servers(server) -> None:
    system = System("served", module_servers=[server.address])
    system.add("emit", "pb3a_manager_served:Emitter")
    system.add("half", "pb3a_manager_served:Halver")
    system.link("emit.out", "half.x")
    with system.launch(listen="tcp://127.0.0.1:0") as run:
        document = Document.empty()       # attached: the document names no module server
        session = Session(document, connect(run.address), owns_handle=True,
                          catalog=Catalog(document, roots=[]))
        with manager_client(session) as client:
            assert client.get("/api/system").json()["module_servers"] == [server.address]
            catalog = client.get("/api/classes").json()
            found = {entry["class"]: entry for entry in catalog["classes"]}
            assert set(found) == {f"pb3a_manager_served:{name}"
                                  for name in ("Emitter", "Halver", "Thirder", "Worder")}
            assert found["pb3a_manager_served:Halver"]["origin"] == server.address
            assert found["pb3a_manager_served:Halver"]["inputs"] == {
                "x": {"type": "float", "policy": "latest"}}
            fitting = client.get("/api/modules/half/swaps").json()["classes"]
            assert fitting == ["pb3a_manager_served:Thirder"]
            swapped = client.post("/api/modules/half/swap",
                                  json={"class": "pb3a_manager_served:Thirder"})
            assert swapped.status_code == 200, swapped.json()
            assert run.topology().modules["half"].cls == "pb3a_manager_served:Thirder"
        assert run.topology().modules["emit"].node == "local"    # still runs: attached only


GAIN = '''
"""A gain whose code the test changes on the module server."""
from pb3a import Input, Module, Output

class Gain(Module):
    """Multiplies what it reads by {factor}."""
    x = Input(float)
    y = Output(float)
{extra}
    def on_input(self, port):
        self.y.write(port.read() * {factor})
'''


def _serve(path: Path, factor: float, extra: str = "") -> None:
    """Write the served file, with a new mtime whatever the clock's grain."""
    path.write_text(textwrap.dedent(GAIN).format(factor=factor, extra=extra))
    later = path.stat().st_mtime + 2
    os.utime(path, (later, later))


def test_reload_through_the_manager_runs_the_served_code_as_changed_and_the_browser_sees_it(
        server) -> None:
    from sample_modules import FloatSource, Last
    from test_manager_browser import ManagerProcess

    served = server.root / "pb3a_manager_reloaded.py"
    _serve(served, 2.0)
    system = System("reloading", module_servers=[server.address])
    system.add("src", FloatSource)
    system.add("gain", "pb3a_manager_reloaded:Gain")
    system.add("sink", Last)
    system.link("src.out", "gain.x")
    system.link("gain.y", "sink.x")
    try:
        with system.launch() as run:
            eventually(lambda: run.state("sink")["value"] == 2.0, what="the served gain, x2")
            # the manager in a process of its own, as a user starts it: attached, it
            # imports the served module itself, apart from the launcher's copy
            manager = ManagerProcess(run.listen())
            try:
                def gain_class() -> dict:
                    classes = manager.api("GET", "/api/classes")["classes"]
                    return next(c for c in classes
                                if c["class"] == "pb3a_manager_reloaded:Gain")

                before = gain_class()
                assert before["origin"] == server.address and set(before["outputs"]) == {"y"}
                _serve(served, 3.0, extra="    z = Output(float)\n")
                assert manager.api("POST", "/api/reload", {"module": "pb3a_manager_reloaded"}) \
                    == {"reloaded": "pb3a_manager_reloaded"}
                # as the page's Reload code does: the module swapped to its class anew
                assert manager.api("POST", "/api/modules/gain/swap",
                                   {"class": "pb3a_manager_reloaded:Gain"}) == {"kept": []}
                eventually(lambda: run.state("sink")["value"] == 3.0,
                           what="the changed code, x3, running")
                after = gain_class()
                assert set(after["outputs"]) == {"y", "z"}, after
                assert after["doc"] == "Multiplies what it reads by 3.0."
                assert set(manager.api("GET", "/api/system")["modules"]["gain"]["outputs"]) \
                    == {"y", "z"}
            finally:
                manager.stop()
            assert manager.process.returncode in (0, 130, -signal.SIGINT)
            assert run.state("sink")["seen"] > 0            # attached only: it still runs
    finally:
        served_code.forget("pb3a_manager_reloaded")


def test_attached_as_the_command_does_stop_is_refused_and_the_system_stays_followed() -> None:
    """`pb3a manager tcp://...` owns its connection (it closes it at the end), and that
    was taken for a system it launched: the page offered Stop, whose 200 left the system
    running and the manager let go of it (an empty document, nothing to show)."""
    from sample_modules import FloatSource, Last

    system = System("attached")
    system.add("src", FloatSource)
    system.add("sink", Last)
    system.link("src.out", "sink.x")
    with system.launch(listen="tcp://127.0.0.1:0") as run:
        session = Session(Document.empty(), connect(run.address), owns_handle=True)
        with manager_client(session) as client:
            shown = client.get("/api/system").json()
            assert shown["mode"] == "running" and shown["stoppable"] is False
            refused = client.post("/api/system/stop")
            assert refused.status_code == 409, refused.text
            assert "stop it where it runs" in refused.json()["error"]
            kept = client.post("/api/modules/sink/keep")
            assert kept.status_code == 409 and "attached" in kept.json()["error"]
            assert client.get("/api/system").json()["mode"] == "running"
            assert set(client.get("/api/stats").json()["modules"]) == {"src", "sink"}
        assert set(run.topology().modules) == {"src", "sink"}    # still runs: attached only
