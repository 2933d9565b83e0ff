"""``scenarios.lab``: the processes a robot application runs against, on one machine."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from conftest import eventually

from pb3a import System
from scenarios.lab import NodeControllerProcess

REPO = Path(__file__).resolve().parent.parent

CHATTY = '''
from pb3a import Module


class Chatty(Module):
    """Prints a kilobyte at every step, as a module being debugged might."""

    period = 0.002
    steps = 0

    def step(self):
        print(f"step {self.steps} " + "x" * 1000, flush=True)
        self.steps += 1
'''


@pytest.mark.timeout(90)
def test_what_a_module_on_a_lab_node_prints_reaches_stderr_and_never_blocks_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capfd: pytest.CaptureFixture[str]) -> None:
    # The node controller's output was read for its banner only: a module that printed
    # 64 KiB on a robot's node filled the pipe, and its next print hung it for good
    # (the launcher then said the module "was busy in a call for 29.7 s").
    (tmp_path / "chatty.py").write_text(CHATTY)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(
        filter(None, [str(tmp_path), str(REPO), os.environ.get("PYTHONPATH")])))
    monkeypatch.syspath_prepend(str(tmp_path))
    node = NodeControllerProcess("r1")
    try:
        system = System("chatty")
        system.node("r1", address=node.address)
        system.add("chatty", "chatty:Chatty", node="r1")
        with system.launch() as running:
            eventually(lambda: running.state("chatty", timeout=5.0)["steps"] >= 300,
                       timeout=30.0, what="300 steps, 300 KB printed")
    finally:
        node.close()
    assert not node._relay.is_alive()
    assert "step 299 " + "x" * 1000 in capfd.readouterr().err
