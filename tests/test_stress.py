"""``pb3a stress`` as a user runs it: a small system under CPU load with a worker killed;
the report's figures are real (values counted, the kill and the restart recorded, the
load read by the node's env port near the level asked)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import pytest
from conftest import Daemon

from pb3a.cli.main import main
from pb3a.cli.stress import Stress, summary_text
from pb3a.stats import LinkStats

pytestmark = pytest.mark.timeout(90)

REPO = Path(__file__).resolve().parent.parent
LEVEL = 70.0


def _configuration(tmp: Path, cpu: int) -> Path:
    path = tmp / "stressed.toml"
    path.write_text(f'''
name = "stressed"
[nodes.a]
cpus = [{cpu}]
[modules.tick]
class = "examples.pipeline:Ticker"
period = 0.002
restart = "fresh"
[modules.scale]
class = "examples.pipeline:Scale"
restart = "fresh"
[[links]]
from = "tick.out"
to = "scale.x"
policy = "queue:64"
''')
    return path


@pytest.mark.serial     # alone: it loads a CPU and reads its load (the Makefile's test target)
def test_stress_reports_values_kills_and_the_load_the_env_port_reads(tmp_path, capsys,
                                                                      monkeypatch) -> None:
    monkeypatch.chdir(REPO)                      # (the file names examples.pipeline)
    cpu = max(os.sched_getaffinity(0))
    argv = ["stress", str(_configuration(tmp_path, cpu)), "--for", "7", "--sample", "0.5",
            "--load", f"{cpu}:{LEVEL:g}@1", "--kill-worker-every", "3",
            "--kill-among", "scale", "--out", str(tmp_path), "--seed", "1"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "values/s" in out and "wrote" in out
    report = json.loads((tmp_path / "stress.json").read_text())
    assert report["schema"] == "pb3a-stress/1"
    link = report["summary"]["links"]["tick.out->scale.x"]
    assert link["values"] > 500 and link["values_per_s"] > 100
    assert 0 < link["latency_p50_s"] <= link["latency_p99_s"] < 1.0
    kills = [mark for mark in report["marks"] if mark["kind"] == "kill"]
    assert kills and all(mark["modules"] == ["scale"] for mark in kills)
    assert report["summary"]["kills"] == len(kills)
    assert report["summary"]["restarts"] >= 1                 # "fresh": it came back
    late = [s for s in report["samples"] if s["t"] > report["samples"][-1]["t"] - 1]
    assert any(s["links"]["tick.out->scale.x"]["values_per_s"] > 0 for s in late)
    loaded = [s["nodes"]["a"]["cpu"] for s in report["samples"]
              if 2.5 <= s["t"] <= 6.5 and s["nodes"]["a"]["cpu"] is not None]
    assert loaded and abs(sum(loaded) / len(loaded) - LEVEL) < 20, loaded
    assert (tmp_path / "stress.png").stat().st_size > 10_000


def test_stress_cuts_a_node_whose_module_fails_over_and_which_rejoins(tmp_path,
                                                                      monkeypatch) -> None:
    monkeypatch.chdir(REPO)
    daemon = Daemon("b")
    try:
        path = tmp_path / "cut.toml"
        path.write_text(f'''
name = "cut"
[nodes.a]
[nodes.b]
address = "{daemon.address}"
[modules.tick]
class = "examples.pipeline:Ticker"
node = "a"
period = 0.002
[modules.scale]
class = "examples.pipeline:Scale"
node = "b"
restart = "fresh"
[[links]]
from = "tick.out"
to = "scale.x"
policy = "queue:64"
''')
        # (cut for 4 s: the launcher loses a node silent for 2 s)
        assert main(["stress", str(path), "--for", "10", "--sample", "0.5",
                     "--cut-node", "b@1+4", "--out", str(tmp_path)]) == 0
    finally:
        daemon.stop()
    report = json.loads((tmp_path / "stress.json").read_text())
    summary = report["summary"]
    assert (summary["cuts"], summary["nodes_lost"], summary["failovers"],
            summary["nodes_joined"]) == (1, 1, 1, 1), summary
    # lost while cut, failed over, and back after the cut; the failover may finish
    # before or after the uncut (it restarts the module on a: a slow host takes > 1 s)
    at = {mark["kind"]: mark["t"] for mark in report["marks"]}
    assert at["cut"] < at["node_lost"] < at["uncut"] < at["node_joined"], report["marks"]
    assert at["node_lost"] <= at["module_failed_over"] < at["node_joined"], report["marks"]
    late = [s for s in report["samples"] if s["t"] > report["samples"][-1]["t"] - 2]
    assert any(s["links"]["tick.out->scale.x"]["values_per_s"] > 0 for s in late)


def test_the_summary_line_counts_the_failed_moves_too() -> None:
    """A move that met a kill failed, and the line said "moves 4" while the report said
    one had failed."""
    summary = {"duration_s": 12.0, "values_per_s": 480.0, "kills": 2, "restarts": 2,
               "migrations": 4, "migrations_failed": 1, "cuts": 0, "nodes_lost": 0,
               "failovers": 0, "nodes_joined": 0, "links": {}, "nodes": {}}
    line = summary_text({"system": "two", "summary": summary}).splitlines()[0]
    assert "moves 4 (1 failed), cuts 0" in line, line
    summary["migrations_failed"] = 0
    assert "moves 4, cuts 0" in summary_text({"system": "two", "summary": summary})


def test_a_link_whose_reader_goes_silent_is_counted_once_and_its_rate_is_a_gap() -> None:
    """A silent reader's link said 0 values, which the sampling took for a counter
    started anew: once its node answered again, its whole count came back on top of
    the totals (150 values counted 250). Its figures are not known meanwhile: the totals
    stand, its rate is a gap (null in the report), and the next known count goes on
    from the last."""
    stress = Stress.__new__(Stress)              # (the sampling alone: no system)
    stress._links = {}

    def sample(values: int, at: float, silent: bool = False) -> dict:
        link = LinkStats("a.out", "b.x", "latest", "zmq", values=values, silent=silent)
        return stress._link_sample("a.out->b.x", link, at)

    assert sample(100, 1.0)["values"] == 100
    silent = sample(0, 2.0, silent=True)
    assert silent["values"] == 100 and math.isnan(silent["values_per_s"])
    back = sample(150, 3.0)
    assert back["values"] == 150 and back["values_per_s"] == 25.0     # (50 over 2 s)
