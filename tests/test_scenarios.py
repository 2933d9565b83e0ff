"""The bundled applications: the self-migration experiment, shortened."""

from __future__ import annotations

import os

import pytest

from pb3a.cli.main import main
from scenarios import self_migration


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one CPU per node needs two CPUs")
def test_the_agent_moves_compute_off_the_loaded_node_while_it_is_loaded() -> None:
    # What it decides and when; the throughput it buys is a figure for the scenario's
    # report (a shared 2-core host's steal makes rates too noisy for a test).
    adaptive = self_migration.run_once(True, (1.5, 3.0, 1.0))
    moves = list(zip(adaptive["moved_at"], adaptive["moved_to"], strict=True))
    assert any(adaptive["load_on"] < at < adaptive["load_off"] and to == "b"
               for at, to in moves), moves
    assert all(at > adaptive["load_on"] for at, _ in moves), moves   # none while quiet
    assert len(moves) == 1, moves        # its own load on b does not send it back to a
    assert adaptive["arrivals"][-1] > adaptive["load_off"]           # values still flow


def test_the_scenario_command_names_the_scenarios(capsys) -> None:
    assert main(["scenario", "no-such-thing"]) == 2
    assert "the scenarios: self-migration" in capsys.readouterr().err
