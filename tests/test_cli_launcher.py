"""``pb3a status / state / migrate / swap ADDR``: acting on a running system through
its launcher's authenticated address."""

from __future__ import annotations

from conftest import eventually
from sample_modules import Counter, FastScale, Relay, Scale

from pb3a import System
from pb3a.cli.main import main


def test_the_command_line_reads_and_changes_a_running_system(capsys) -> None:
    system = System("cli-launcher")
    system.node("a")
    system.node("b")
    system.add("src", Counter, node="a", period=0.002)
    system.add("relay", Relay, node="a")
    system.add("scale", Scale, node="a")
    system.link("src.out", "relay.x")
    with system.launch() as run:
        address = run.listen()
        eventually(lambda: run.state("relay")["relayed"] > 5, what="values flowing")
        assert main(["status", address]) == 0
        table = capsys.readouterr().out
        assert "relay" in table and "src.out -> relay.x" in table
        assert main(["state", address, "scale"]) == 0
        assert '"gain": 2.0' in capsys.readouterr().out
        assert main(["migrate", address, "relay", "b"]) == 0
        assert "relay: a -> b, paused" in capsys.readouterr().out
        assert run.stats().modules["relay"].node == "b"
        ref = f"{FastScale.__module__}:FastScale"
        assert main(["swap", address, "scale", ref]) == 0
        assert "state kept: gain, setups" in capsys.readouterr().out
        assert main(["state", address, "ghost"]) == 1
        assert "no module 'ghost'" in capsys.readouterr().err
