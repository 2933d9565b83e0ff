"""Where the schematic draws each node, module and link: Graphviz's layout, in pixels.

The topology becomes DOT (one cluster per node, each module a record with its inputs
on the left and outputs on the right, as ``pb3a graph`` draws it); ``dot -Tjson``
places everything; the result is turned to y-down pixels: clusters and modules as
boxes, links as polylines through their spline's points. Without Graphviz (or when
it fails or takes too long) a plain grid stands in: a column per node.
"""

from __future__ import annotations

import json
import logging
import re
import shutil
import subprocess
from typing import Any

from pb3a.topology import Topology

log = logging.getLogger("pb3a.manager")

DOT_TIMEOUT = 10.0          # seconds dot may take (200 modules take well under one)
POINTS_PER_INCH = 72.0
_RECORD_SPECIAL = re.compile(r"([{}|<> \"\\])")

# the grid that stands in for Graphviz, in pixels
GRID_W, GRID_H, GRID_GAP, GRID_ROWS = 160.0, 60.0, 30.0, 8


def layout(topology: Topology) -> dict[str, Any]:
    """``{"width", "height", "clusters": {node: box}, "modules": {name: box},
    "links": {key: {"points": [[x, y], ...]}}}``, boxes as ``{"x","y","w","h"}`` (the
    top-left corner), y down."""
    dot = shutil.which("dot")
    if dot is not None and topology.modules:
        try:
            done = subprocess.run([dot, "-Tjson"], input=to_dot(topology), text=True,
                                  capture_output=True, timeout=DOT_TIMEOUT, check=True)
            return _from_graphviz(json.loads(done.stdout), topology)
        except (subprocess.SubprocessError, OSError, ValueError, KeyError) as exc:
            log.warning("Graphviz could not lay the system out (%s); a grid stands in", exc)
    return grid(topology)


def to_dot(topology: Topology) -> str:
    """DOT of the topology: a cluster per node, a record per module, an edge per link
    from output port to input port."""
    lines = [f"digraph {_quote(topology.system)} {{", "  rankdir=LR;",
             '  node [shape=Mrecord, fontname="Helvetica", fontsize=10];']
    for node in topology.nodes:
        lines += [f"  subgraph {_quote('cluster_' + node)} {{", f"    label={_quote(node)};"]
        for name, module in topology.modules.items():
            if module.node == node:
                label = _record(name, module.inputs, module.outputs)
                lines.append(f"    {_quote(name)} [label={_quote(label)}];")
        lines.append("  }")
    for link in topology.links.values():
        src, _, src_port = link.src.rpartition(".")
        dst, _, dst_port = link.dst.rpartition(".")
        lines.append(f"  {_quote(src)}:{_quote('o_' + src_port)} -> "
                     f"{_quote(dst)}:{_quote('i_' + dst_port)};")
    lines.append("}")
    return "\n".join(lines) + "\n"


def _record(name: str, inputs: dict[str, Any], outputs: dict[str, Any]) -> str:
    fields = []
    if inputs:
        fields.append("{" + "|".join(f"<i_{p}> {_escape(p)}" for p in inputs) + "}")
    fields.append(_escape(name))
    if outputs:
        fields.append("{" + "|".join(f"<o_{p}> {_escape(p)}" for p in outputs) + "}")
    return "{" + "|".join(fields) + "}"


def _from_graphviz(graph: dict[str, Any], topology: Topology) -> dict[str, Any]:
    """Graphviz's JSON (points, y up, centres) as y-down pixel boxes and polylines."""
    _, _, width, height = (float(v) for v in graph["bb"].split(","))
    clusters, modules = {}, {}
    names: dict[int, str] = {}
    for item in graph.get("objects", []):
        name = item.get("name", "")
        if "bb" in item and name.startswith("cluster_"):
            left, bottom, right, top = (float(v) for v in item["bb"].split(","))
            clusters[name.removeprefix("cluster_")] = _box(left, height - top, right - left,
                                                           top - bottom)
        elif "pos" in item and name in topology.modules:
            x, y = (float(v) for v in item["pos"].split(","))
            w = float(item["width"]) * POINTS_PER_INCH
            h = float(item["height"]) * POINTS_PER_INCH
            modules[name] = _box(x - w / 2, height - y - h / 2, w, h)
            names[item["_gvid"]] = name
    links = {}
    for edge in graph.get("edges", []):
        src, dst = names.get(edge.get("tail")), names.get(edge.get("head"))
        key = (f"{src}.{edge.get('tailport', '').removeprefix('o_')}->"
               f"{dst}.{edge.get('headport', '').removeprefix('i_')}")
        if key in topology.links:
            links[key] = {"points": _edge_points(edge.get("pos", ""), height)}
    return {"width": width, "height": height, "clusters": clusters, "modules": modules,
            "links": links}


def _edge_points(pos: str, height: float) -> list[list[float]]:
    """An edge's spline (``e,x,y s,x,y x,y ...``): start, control points, end, y down."""
    start, end, middle = None, None, []
    for token in pos.split():
        if token.startswith("e,"):
            end = token[2:]
        elif token.startswith("s,"):
            start = token[2:]
        else:
            middle.append(token)
    points = [p for p in (start, *middle, end) if p is not None]
    return [[round(float(x), 1), round(height - float(y), 1)]
            for x, y in (p.split(",") for p in points)]


def grid(topology: Topology) -> dict[str, Any]:
    """A column of clusters per node, modules in rows of ``GRID_ROWS``; links straight."""
    clusters, modules = {}, {}
    left = GRID_GAP
    tallest = 0.0
    for node in topology.nodes:
        names = [name for name, module in topology.modules.items() if module.node == node]
        columns = max(1, -(-len(names) // GRID_ROWS))
        rows = min(len(names), GRID_ROWS) or 1
        for number, name in enumerate(names):
            column, row = divmod(number, GRID_ROWS)
            modules[name] = _box(left + GRID_GAP / 2 + column * (GRID_W + GRID_GAP),
                                 2 * GRID_GAP + row * (GRID_H + GRID_GAP), GRID_W, GRID_H)
        w = columns * (GRID_W + GRID_GAP)
        h = rows * (GRID_H + GRID_GAP) + GRID_GAP
        clusters[node] = _box(left, GRID_GAP, w, h)
        left += w + GRID_GAP
        tallest = max(tallest, h)
    links = {}
    for key, link in topology.links.items():
        src = modules.get(link.src.rpartition(".")[0])
        dst = modules.get(link.dst.rpartition(".")[0])
        if src and dst:
            links[key] = {"points": [[src["x"] + src["w"], src["y"] + src["h"] / 2],
                                     [dst["x"], dst["y"] + dst["h"] / 2]]}
    return {"width": left, "height": tallest + 2 * GRID_GAP, "clusters": clusters,
            "modules": modules, "links": links}


def _box(x: float, y: float, w: float, h: float) -> dict[str, float]:
    return {"x": round(x, 1), "y": round(y, 1), "w": round(w, 1), "h": round(h, 1)}


def _escape(text: str) -> str:
    return _RECORD_SPECIAL.sub(r"\\\1", text)


def _quote(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'
