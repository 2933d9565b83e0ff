"""The bundled applications: the self-migration experiment, shortened."""

from __future__ import annotations

import os

import pytest

from pb3a.runtime.cli import main
from scenarios import self_migration


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one CPU per node needs two CPUs")
def test_the_agent_moves_compute_off_the_loaded_node_while_it_is_loaded() -> None:
    adaptive = self_migration.run_once(True, (1.0, 3.0, 0.5))
    assert adaptive["compute_node_at_end"] == "b"
    (moved,) = adaptive["moved_at"]
    assert adaptive["load_on"] < moved < adaptive["load_off"]
    figures = self_migration.phase_figures(adaptive)
    assert figures["after"]["values_per_s"] > 0.7 * self_migration.RATE_HZ   # flowing again


def test_the_scenario_command_names_the_scenarios(capsys) -> None:
    assert main(["scenario", "no-such-thing"]) == 2
    assert "the scenarios: self-migration" in capsys.readouterr().err
