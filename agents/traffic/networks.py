"""Road networks and their demand, built by SUMO's own tools from files in the repo.

A network is described by a TOML file (``scenarios/traffic/ring.toml`` is one): how
to build it (``netconvert`` from plain ``.nod.xml``/``.edg.xml`` files beside it, or
``netgenerate`` with its arguments) and its demand (streams of vehicles from one road
to another, in groups, and a schedule of periods giving each group's rate).
``Network.load(path)`` reads and checks it; ``network.build(signals)`` runs the tool
into a cache directory once, again only when the description, its files, the signal
type or SUMO's version change; ``network.write_demand(duration_s, path)`` writes the
schedule as SUMO flows compressed into ``duration_s`` (a quick run keeps the shape of
the demand), with Poisson arrivals that SUMO draws from its ``--seed``.

Nothing is fetched: SUMO comes from the project's ``traffic`` extra.
"""

from __future__ import annotations

import hashlib
import math
import os
import subprocess
import tempfile
import tomllib
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

from agents.limits import finite

SIGNAL_TYPES = ("static", "actuated", "delay_based")   # netconvert's --tls.default-type
BUILD_TIMEOUT_S = 120.0
_BUILD_OPTIONS = ("--no-turnarounds", "true")           # U-turns at junctions only
                                                        # confuse the signal phases


class SumoMissing(RuntimeError):
    """SUMO (the ``traffic`` extra) is not installed in this Python environment."""


class BuildFailed(RuntimeError):
    """SUMO's tool could not build a network from its description (its files, its
    arguments), or took too long: the error says which and what the tool said."""


def sumo_home() -> Path:
    """Where the ``eclipse-sumo`` package keeps SUMO's binaries and data."""
    try:
        import sumo  # the eclipse-sumo wheel
    except ImportError:
        raise SumoMissing("SUMO is not installed: install the project's traffic extra "
                          "(pip install -e '.[traffic]', or make)") from None
    return Path(sumo.SUMO_HOME)


def sumo_binary(name: str) -> Path:
    """The path of SUMO's program ``name`` (``sumo``, ``netconvert``, ``netgenerate``)."""
    path = sumo_home() / "bin" / name
    if not path.is_file():
        raise SumoMissing(f"SUMO's {name} is missing from {path.parent}: reinstall the "
                          "project's traffic extra (pip install -e '.[traffic]')")
    return path


def sumo_version() -> str:
    """SUMO's version, as its package gives it."""
    from importlib.metadata import version
    try:
        return version("eclipse-sumo")
    except Exception:               # not installed as a distribution: the binary decides
        return "unknown"


def default_cache() -> Path:
    """Where built networks are kept: ``$PB3A_TRAFFIC_CACHE``, else the user's cache."""
    if os.environ.get("PB3A_TRAFFIC_CACHE"):
        return Path(os.environ["PB3A_TRAFFIC_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "pb3a" / "traffic"


@dataclass(frozen=True)
class Stream:
    """Vehicles from road ``origin`` to road ``destination`` (SUMO edge ids), at the
    rate its ``group`` has in each period."""

    name: str
    origin: str
    destination: str
    group: str


@dataclass(frozen=True)
class Period:
    """A part of the demand schedule: ``share`` of the run, with ``rates`` (vehicles
    per hour per stream) by group."""

    name: str
    share: float
    rates: dict[str, float]


@dataclass(frozen=True)
class Network:
    """A road network's description, as read from its TOML file."""

    name: str
    path: Path                       # the description file
    netconvert: dict[str, str] | None
    netgenerate: tuple[str, ...] | None
    streams: tuple[Stream, ...]
    periods: tuple[Period, ...]

    @classmethod
    def load(cls, path: str | Path) -> Network:
        """Read and check the description at ``path``; ``ValueError`` says what to fix."""
        path = Path(path).resolve()
        if not path.is_file():
            raise ValueError(f"no network description at {path}: give the path of a "
                             "network's .toml file (e.g. scenarios/traffic/ring.toml)")
        try:
            doc = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{path}: not valid TOML: {exc}") from None
        return cls._from_doc(path, doc)

    @classmethod
    def _from_doc(cls, path: Path, doc: dict[str, Any]) -> Network:
        def fail(what: str) -> ValueError:
            return ValueError(f"{path}: {what}")

        title = doc.get("name", path.stem)
        if not (isinstance(title, str) and title.strip() and "/" not in title
                and "\\" not in title and title not in (".", "..")):
            raise fail(f"name must be text that can name a file (no '/'), got {title!r}: "
                       "built networks are kept under it")
        build = doc.get("build", {})
        if not isinstance(build, dict):
            raise fail(f"[build] must be a table, got {build!r}")
        netconvert, netgenerate = build.get("netconvert"), build.get("netgenerate")
        if (netconvert is None) == (netgenerate is None):
            raise fail("[build] needs exactly one of netconvert = { nodes = ..., edges = "
                       "... } or netgenerate = [arguments]")
        if netconvert is not None:
            if not (isinstance(netconvert, dict) and set(netconvert) == {"nodes", "edges"}
                    and all(isinstance(v, str) for v in netconvert.values())):
                raise fail("[build] netconvert needs nodes and edges (file names beside "
                           "the description) and nothing else")
            for key in ("nodes", "edges"):
                if not (path.parent / netconvert[key]).is_file():
                    raise fail(f"[build] netconvert {key}: no file "
                               f"{path.parent / netconvert[key]}")
        elif not (isinstance(netgenerate, list) and all(isinstance(a, str) for a in netgenerate)):
            raise fail("[build] netgenerate must be a list of strings (its arguments)")

        demand = doc.get("demand", {})
        if not isinstance(demand, dict):
            raise fail(f"[demand] must be a table of streams and periods, got {demand!r}")
        if not isinstance(demand.get("streams", {}), dict):
            raise fail("[demand.streams] must be a table of streams "
                       "(name = { from = EDGE, to = EDGE, group = G })")
        streams = []
        for name, stream in demand.get("streams", {}).items():
            missing = {"from", "to", "group"} - set(stream if isinstance(stream, dict) else ())
            if missing:
                raise fail(f"[demand.streams] {name} lacks {', '.join(sorted(missing))}")
            wrong = [key for key in ("from", "to", "group") if not isinstance(stream[key], str)]
            if wrong:
                raise fail(f"[demand.streams] {name}: {', '.join(wrong)} must be text (an "
                           f"edge's id, a group's name), got "
                           f"{', '.join(repr(stream[key]) for key in wrong)}")
            streams.append(Stream(name, stream["from"], stream["to"], stream["group"]))
        if not streams:
            raise fail("[demand.streams] is empty: name at least one stream "
                       "(name = { from = EDGE, to = EDGE, group = G })")
        groups = {s.group for s in streams}
        periods = []
        listed = demand.get("periods", [])
        if not (isinstance(listed, list) and all(isinstance(p, dict) for p in listed)):
            raise fail("[[demand.periods]] must be tables, each with a name, a share and "
                       f"rates, got {listed!r}")
        names = [str(period.get("name", number + 1)) for number, period in enumerate(listed)]
        twice = sorted({name for name in names if names.count(name) > 1})
        if twice or "*" in names:       # (a scale by name took both, or every period)
            raise fail(f"[[demand.periods]]: each period needs a name of its own, not "
                       f"{', '.join(map(repr, twice or ['*']))}"
                       + (" ('*' means every period to --scale)" if "*" in names else ""))
        for number, period in enumerate(listed):
            label = f"[[demand.periods]] {period.get('name', number + 1)}"
            rates = period.get("rates", {})
            if not isinstance(rates, dict) or set(rates) != groups:
                given = ", ".join(sorted(rates)) if isinstance(rates, dict) else repr(rates)
                raise fail(f"{label}: rates must give every group ({', '.join(sorted(groups))}), "
                           f"got {given or 'none'}")
            share = period.get("share", 0)
            if not (finite(share) and share > 0):
                raise fail(f"{label}: share must be a number above 0")
            for group, rate in sorted(rates.items()):
                # (SUMO takes a rate of NaN or inf as vehicles without end, at once)
                if not (finite(rate) and rate >= 0):
                    raise fail(f"{label}: the rate of group {group} must be a finite number "
                               f"of vehicles per hour, 0 or more, got {rate!r}")
            periods.append(Period(str(period.get("name", number + 1)), float(share),
                                  {g: float(r) for g, r in rates.items()}))
        if not periods:
            raise fail("[[demand.periods]] is missing: give at least one period")
        if abs(sum(p.share for p in periods) - 1.0) > 1e-6:
            raise fail("the periods' shares must add up to 1")
        return cls(title, path, netconvert,
                   tuple(netgenerate) if netgenerate is not None else None,
                   tuple(streams), tuple(periods))

    # -- building -------------------------------------------------------------------
    def build(self, signals: str = "static", cache: Path | None = None) -> Path:
        """The built ``.net.xml`` with ``signals`` programs (SUMO's ``static``,
        ``actuated`` or ``delay_based``), built into ``cache`` if it is not there."""
        if signals not in SIGNAL_TYPES:
            raise ValueError(f"signals must be one of {', '.join(SIGNAL_TYPES)}, "
                             f"got {signals!r}")
        cache = cache or default_cache()
        target = cache / f"{self.name}-{signals}-{self._fingerprint(signals)}.net.xml"
        if target.is_file():
            return target
        cache.mkdir(parents=True, exist_ok=True)
        # built beside its final name and renamed: two workers building the same
        # network at once each get a whole file
        fd, partial = tempfile.mkstemp(dir=cache, prefix=f".{self.name}-", suffix=".net.xml")
        os.close(fd)
        try:
            self._run_tool(signals, Path(partial))
            os.replace(partial, target)
        finally:
            Path(partial).unlink(missing_ok=True)
        return target

    def _command(self, signals: str, output: Path) -> list[str]:
        common = ["--tls.default-type", signals, *_BUILD_OPTIONS, "--output-file", str(output)]
        if self.netconvert is not None:
            here = self.path.parent
            return [str(sumo_binary("netconvert")),
                    "--node-files", str(here / self.netconvert["nodes"]),
                    "--edge-files", str(here / self.netconvert["edges"]), *common]
        return [str(sumo_binary("netgenerate")), *self.netgenerate, *common]

    def _run_tool(self, signals: str, output: Path) -> None:
        command = self._command(signals, output)
        try:
            done = subprocess.run(command, capture_output=True, text=True,
                                  timeout=BUILD_TIMEOUT_S, check=False)
        except subprocess.TimeoutExpired:
            raise BuildFailed(f"building network {self.name} ({self.path}) took more "
                              f"than {BUILD_TIMEOUT_S:.0f} s: {' '.join(command)}") from None
        if done.returncode != 0 or not output.stat().st_size:
            raise BuildFailed(f"building network {self.name} from {self.path} failed "
                              f"({Path(command[0]).name} exit {done.returncode}): "
                              f"{(done.stderr or done.stdout).strip()[-2000:]}")

    def _fingerprint(self, signals: str) -> str:
        """A digest of everything the built network depends on."""
        digest = hashlib.sha256()
        digest.update(self.path.read_bytes())
        if self.netconvert is not None:
            for key in ("nodes", "edges"):
                digest.update((self.path.parent / self.netconvert[key]).read_bytes())
        digest.update(f"{signals} {sumo_version()} {_BUILD_OPTIONS}".encode())
        return digest.hexdigest()[:12]

    def signalized(self, net_file: Path) -> list[str]:
        """The ids of the built network's traffic lights (its signalized junctions, as
        SUMO and the driver name them), sorted."""
        found = set()
        for _, element in ET.iterparse(net_file):
            if element.tag == "tlLogic":
                found.add(element.get("id", ""))
            element.clear()
        return sorted(found)

    def check_streams(self, net_file: Path) -> None:
        """``ValueError`` naming the first stream the built network ``net_file`` cannot
        carry: a road it does not have, or no way from the stream's origin to its
        destination. SUMO would fail on it only when the stream's first vehicle is
        loaded, which may be late in a run."""
        roads: set[str] = set()
        leads_to: dict[str, set[str]] = {}
        for _, element in ET.iterparse(net_file):
            if element.tag == "edge" and element.get("function") != "internal":
                roads.add(element.get("id", ""))
            elif element.tag == "connection" and not element.get("from", ":").startswith(":"):
                leads_to.setdefault(element.get("from", ""), set()).add(element.get("to", ""))
            element.clear()
        for stream in self.streams:
            for road in (stream.origin, stream.destination):
                if road not in roads:
                    raise ValueError(f"{self.path}: stream {stream.name}: no edge {road!r} "
                                     f"in the built network (its edges: "
                                     f"{', '.join(sorted(roads)[:20])}"
                                     f"{', ...' if len(roads) > 20 else ''})")
            reached, frontier = {stream.origin}, [stream.origin]
            while frontier and stream.destination not in reached:
                frontier = [n for road in frontier for n in leads_to.get(road, ())
                            if n not in reached]
                reached.update(frontier)
            if stream.destination not in reached:
                raise ValueError(f"{self.path}: stream {stream.name}: no route from edge "
                                 f"{stream.origin} to edge {stream.destination} in the "
                                 "built network")

    # -- demand ---------------------------------------------------------------------
    def scaled(self, factors: Mapping[str, float]) -> Network:
        """This network with the rates of some periods multiplied: ``factors`` maps a
        period's name (or ``*``, every period) to its factor, for example
        ``{"surge": 2.0}`` for a surge twice as heavy. Builds are unchanged."""
        if not isinstance(factors, Mapping):
            raise ValueError(f"{self.path}: a demand scale is a table of period name (or *) "
                             f"to factor, e.g. {{ surge = 2.0 }}, got {factors!r}")
        names = [period.name for period in self.periods]
        unknown = set(factors) - {*names, "*"}
        if unknown:
            raise ValueError(f"{self.path}: no period {', '.join(sorted(unknown))} to scale; "
                             f"its periods are {', '.join(names)} (or * for all)")
        for name, factor in factors.items():
            if not (finite(factor) and factor > 0):
                raise ValueError(f"{self.path}: the factor of period {name} must be a number "
                                 f"above 0, got {factor!r}")
        periods = tuple(replace(period, rates={
            group: rate * factors.get("*", 1.0) * factors.get(period.name, 1.0)
            for group, rate in period.rates.items()}) for period in self.periods)
        for period in periods:
            for group, rate in period.rates.items():
                if not math.isfinite(rate):
                    raise ValueError(f"{self.path}: scaled by {dict(factors)}, period "
                                     f"{period.name}'s rate "
                                     f"of group {group} would be infinite")
        return replace(self, periods=periods)

    def schedule(self, duration_s: float) -> list[tuple[Period, float, float]]:
        """Each period with its begin and end (s) in a run of ``duration_s``."""
        if not duration_s > 0:
            raise ValueError(f"duration_s must be above 0, got {duration_s}")
        spans, begin = [], 0.0
        for period in self.periods:
            end = begin + period.share * duration_s
            spans.append((period, begin, end))
            begin = end
        return spans

    def write_demand(self, duration_s: float, path: Path) -> Path:
        """Write the demand of a ``duration_s`` run to ``path`` as SUMO flows: each
        stream in each period departs as a Poisson process of the period's rate."""
        lines = ["<routes>",
                 '    <vType id="car" accel="2.6" decel="4.5" sigma="0.5" length="5"/>']
        for number, (period, begin, end) in enumerate(self.schedule(duration_s)):
            for stream in self.streams:
                rate = period.rates[stream.group]
                if rate <= 0:
                    continue
                lines.append(
                    f"    <flow id={quoteattr(f'{stream.name}.{number}')} type=\"car\" "
                    f"from={quoteattr(stream.origin)} to={quoteattr(stream.destination)} "
                    f'begin="{begin:.2f}" end="{end:.2f}" period="exp({rate / 3600:.6f})" '
                    'departLane="best" departSpeed="max"/>')
        lines.append("</routes>")
        path.write_text("\n".join(lines) + "\n")
        return path
