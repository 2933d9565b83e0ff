"""The traffic networks: described in the repo, built by SUMO's tools into a cache
(again only when something they depend on changes), with demand SUMO accepts."""

from __future__ import annotations

import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from agents.traffic.networks import Network, SumoMissing, sumo_binary

NETWORKS = Path(__file__).resolve().parent.parent / "scenarios" / "traffic"


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("sumo", reason="SUMO (the traffic extra) is not installed: "
                                       "pip install -e '.[traffic]'")
    return tmp_path_factory.mktemp("traffic-cache")


@pytest.mark.parametrize(("name", "junctions"), [("ring", 6), ("grid", 9), ("cross", 1)])
def test_each_network_builds_and_sumo_runs_its_demand(cache: Path, tmp_path: Path,
                                                      name: str, junctions: int) -> None:
    import sumolib

    network = Network.load(NETWORKS / f"{name}.toml")
    net_file = network.build("static", cache)
    net = sumolib.net.readNet(str(net_file))
    assert len(net.getTrafficLights()) == junctions
    for stream in network.streams:                  # every stream's roads exist
        assert net.hasEdge(stream.origin) and net.hasEdge(stream.destination), stream
    routes = network.write_demand(240.0, tmp_path / "demand.rou.xml")
    done = subprocess.run(
        [str(sumo_binary("sumo")), "-n", str(net_file), "-r", str(routes), "--end", "240",
         "--no-step-log", "true", "--seed", "3", "--duration-log.statistics", "true"],
        capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert "Inserted: 0 " not in done.stdout and "Inserted:" in done.stdout


def test_the_signal_type_is_built_in(cache: Path) -> None:
    network = Network.load(NETWORKS / "cross.toml")
    actuated = network.build("actuated", cache)
    assert ET.parse(actuated).find("tlLogic").get("type") == "actuated"
    with pytest.raises(ValueError, match="signals must be one of static, actuated"):
        network.build("smart", cache)


def test_a_network_is_built_once_and_again_when_its_files_change(cache: Path,
                                                                 tmp_path: Path) -> None:
    for suffix in (".toml", ".nod.xml", ".edg.xml"):
        shutil.copy(NETWORKS / f"cross{suffix}", tmp_path / f"cross{suffix}")
    first = Network.load(tmp_path / "cross.toml").build("static", cache)
    built_at = first.stat().st_mtime_ns
    assert Network.load(tmp_path / "cross.toml").build("static", cache) == first
    assert first.stat().st_mtime_ns == built_at
    edges = tmp_path / "cross.edg.xml"
    edges.write_text(edges.read_text().replace('speed="13.89"', 'speed="8.33"'))
    second = Network.load(tmp_path / "cross.toml").build("static", cache)
    assert second != first and 'speed="8.33"' in second.read_text()


def test_the_demand_keeps_its_shape_in_a_shorter_run(tmp_path: Path) -> None:
    network = Network.load(NETWORKS / "ring.toml")
    spans = [(period.name, begin, end) for period, begin, end in network.schedule(900.0)]
    assert spans == [("west heavy", 0.0, 225.0), ("east heavy", 225.0, 450.0),
                     ("balanced", 450.0, 675.0), ("surge", 675.0, 900.0)]
    flows = ET.parse(network.write_demand(900.0, tmp_path / "d.rou.xml")).findall("flow")
    assert len(flows) == len(network.streams) * 4
    first = {f.get("id"): f for f in flows}["west_to_east.0"]
    assert (first.get("begin"), first.get("end")) == ("0.00", "225.00")
    assert first.get("period") == f"exp({420 / 3600:.6f})"     # Poisson, seeded by SUMO


def test_a_period_s_demand_scales_and_a_bad_scale_is_named(tmp_path: Path) -> None:
    network = Network.load(NETWORKS / "ring.toml")
    rates = {p.name: p.rates for p in network.scaled({"surge": 2.0, "*": 0.5}).periods}
    assert rates["surge"] == {"west": 380.0, "east": 380.0}     # 380 x 2 x 0.5
    assert rates["west heavy"] == {"west": 210.0, "east": 50.0}
    assert network.scaled({}) == network
    flows = ET.parse(network.scaled({"surge": 3.0}).write_demand(
        900.0, tmp_path / "d.rou.xml")).findall("flow")
    assert {f.get("id"): f for f in flows}["west_to_east.3"].get("period") == (
        f"exp({3 * 380 / 3600:.6f})")
    with pytest.raises(ValueError, match="no period rush to scale; its periods are west "
                                         "heavy, east heavy, balanced, surge"):
        network.scaled({"rush": 2.0})
    with pytest.raises(ValueError, match="period surge's rate of group west would be "
                                         "infinite"):
        network.scaled({"surge": 1e308})
    for bad in (0.0, -1.0, float("nan"), "2"):
        with pytest.raises(ValueError, match="the factor of period surge must be a number "
                                             "above 0"):
            network.scaled({"surge": bad})


@pytest.mark.parametrize(("text", "complaint"), [
    ("", "needs exactly one of netconvert"),
    ('[build]\nnetgenerate = ["--grid"]\n', r"\[demand.streams\] is empty"),
    ('[build]\nnetgenerate = ["--grid"]\n[demand.streams]\na = { from = "x", to = "y", '
     'group = "g" }\n[[demand.periods]]\nshare = 1.0\nrates = { h = 1 }\n',
     "rates must give every group"),
    ('[build]\nnetgenerate = ["--grid"]\n[demand.streams]\na = { from = "x", to = "y", '
     'group = "g" }\n[[demand.periods]]\nshare = 0.5\nrates = { g = 1 }\n',
     "shares must add up to 1"),
    ('[build]\nnetconvert = { nodes = "no.nod.xml", edges = "no.edg.xml" }\n',
     "netconvert nodes: no file"),
    ('[build]\nnetgenerate = ["--grid"]\n[demand]\nstreams = ["a"]\n',
     r"\[demand.streams\] must be a table"),
    ('[build]\nnetgenerate = ["--grid"]\n[demand.streams]\na = { from = "x", to = "y", '
     'group = "g" }\n[[demand.periods]]\nshare = true\nrates = { g = 1 }\n',
     "share must be a number above 0"),
    *[('[build]\nnetgenerate = ["--grid"]\n[demand.streams]\na = { from = "x", to = "y", '
       f'group = "g" }}\n[[demand.periods]]\nshare = 1.0\nrates = {{ g = {rate} }}\n',
       "rate of group g must be a finite number of vehicles per hour, 0 or more")
      for rate in ("nan", "inf", "-60", '"many"')],
    # a table of the wrong shape was an AttributeError or TypeError traceback
    ("build = 3\n", r"\[build\] must be a table, got 3"),
    ('[build]\nnetconvert = 3\n', "netconvert needs nodes and edges"),
    ('demand = 3\n[build]\nnetgenerate = ["--grid"]\n', r"\[demand\] must be a table"),
    ('[build]\nnetgenerate = ["--grid"]\n[demand]\nperiods = [3]\n[demand.streams]\n'
     'a = { from = "x", to = "y", group = "g" }\n', r"\[\[demand.periods\]\] must be tables"),
    ('[build]\nnetgenerate = ["--grid"]\n[demand.streams]\na = { from = "x", to = "y", '
     'group = "g" }\n[[demand.periods]]\nshare = 1.0\nrates = 3\n',
     "rates must give every group \\(g\\), got 3"),
    ('[build]\nnetgenerate = ["--grid"]\n[demand.streams]\na = { from = 3, to = "y", '
     'group = "g" }\n', r"\[demand.streams\] a: from must be text"),
    ('name = "west/ring"\n', "name must be text that can name a file"),
    # (a scale by name took both, and the report's periods could not be told apart)
    *[('[build]\nnetgenerate = ["--grid"]\n[demand.streams]\na = { from = "x", to = "y", '
       f'group = "g" }}\n[[demand.periods]]\nname = "{first}"\nshare = 0.5\nrates = {{ g = 1 }}'
       f'\n[[demand.periods]]\nname = "{second}"\nshare = 0.5\nrates = {{ g = 2 }}\n',
       complaint) for first, second, complaint in [
           ("rush", "rush", "each period needs a name of its own, not 'rush'"),
           ("*", "rush", r"not '\*' \('\*' means every period to --scale\)")]],
])
def test_a_bad_description_is_refused_saying_what_to_fix(tmp_path: Path, text: str,
                                                         complaint: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=complaint) as caught:
        Network.load(path)
    assert str(path) in str(caught.value)
    with pytest.raises(ValueError, match="no network description at"):
        Network.load(tmp_path / "missing.toml")


@pytest.mark.parametrize(("stream", "complaint"), [
    ('from = "nowhere", to = "C_e"', "stream west_east: no edge 'nowhere' in"),
    ('from = "C_e", to = "w_C"', "stream west_east: no route from edge C_e to edge w_C"),
])
def test_a_stream_the_built_network_cannot_carry_is_refused_by_name(
        cache: Path, tmp_path: Path, stream: str, complaint: str) -> None:
    """Before, SUMO failed on it: at start, or (a stream of a later period with no
    route) mid-run, the driver then failing every step without end."""
    for suffix in (".nod.xml", ".edg.xml"):
        shutil.copy(NETWORKS / f"cross{suffix}", tmp_path / f"cross{suffix}")
    path = tmp_path / "cross.toml"
    path.write_text((NETWORKS / "cross.toml").read_text().replace(
        'from = "w_C", to = "C_e"', stream))
    network = Network.load(path)
    with pytest.raises(ValueError, match=complaint) as caught:
        network.check_streams(network.build("static", cache))
    assert str(path) in str(caught.value)
    original = Network.load(NETWORKS / "cross.toml")
    original.check_streams(original.build("static", cache))    # the bundled one is fine


def test_without_sumo_the_error_says_how_to_install_it(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "sumo", None)          # import sumo fails
    with pytest.raises(SumoMissing, match=r"pip install -e '\.\[traffic\]'"):
        sumo_binary("netconvert")
