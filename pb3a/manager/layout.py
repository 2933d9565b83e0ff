"""Where the schematic draws each node, macro, module and link: Graphviz's layout, in the
page's pixels.

Each module box is sized for what the page draws in it (``module_size``: its title,
a row per port with the port names left and right, its figures and class below),
so the page draws the layout as it comes, without scaling it. The topology becomes
DOT: a cluster per node, every node included (one that runs nothing holds an
invisible placeholder: a region to drop modules on), a cluster per macro nested in
its node's (the room the page's macro frames take), each module a fixed-size box,
each link an edge from the east side of its source to the west side of its target
(so a back edge too leaves an output and enters an input). ``dot -Tjson`` places
everything; the result is turned into y-down boxes and polylines. Without Graphviz
(or when it fails or takes too long) a plain grid stands in: a column per node.
"""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
from dataclasses import dataclass
from typing import Any

from pb3a.config.plan import split_by_macro
from pb3a.topology import ModuleInfo, Topology

log = logging.getLogger("pb3a.manager")

DOT_TIMEOUT = 10.0          # seconds dot may take (200 modules take well under one)
POINTS_PER_INCH = 72.0      # Graphviz sizes nodes in inches, places them in points (= px)

# What the page (static/schematic.js, style.css) draws in a module box, in pixels
HEADER_H = 24               # the title band
FOOTER_H = 30               # the figures line and the class line below the ports
PORT_PITCH = 18             # the height one port's row takes
MIN_W, MIN_H = 150.0, 84.0  # the least box: room for the figures ("1.2k steps · 3 err")
TITLE_CHAR_W = 7.4          # 12.5 px bold sans
CLASS_CHAR_W = 6.4          # 10.5 px mono
PORT_CHAR_W = 6.1           # 10 px mono
PORT_GAP = 28               # between an input's name and an output's on one row
# A node's region: the page writes the node's name and two lines of figures on top
NODE_HEADER_W, NODE_HEADER_H = 190, 50
EMPTY_W, EMPTY_H = 210, 110            # a node without modules: room to drop one
MACRO_TITLE_H, MACRO_CHAR_W = 16, 7.0  # "▾ robot", 11 px
CLUSTER_MARGIN = 12

# the grid that stands in for Graphviz, in pixels
GRID_GAP, GRID_ROWS = 30.0, 8


@dataclass(frozen=True)
class _Ids:
    """Graphviz names for everything (the names of nodes and modules may hold anything
    DOT would need quoted): module -> id, and each cluster id -> what it stands for."""

    modules: dict[str, str]
    clusters: dict[str, tuple[str, str | None]]      # id -> (node, macro or None)
    links: dict[str, str]                             # edge id -> link key


def module_size(name: str, module: ModuleInfo) -> tuple[float, float]:
    """The box (width, height) the page needs to draw ``module`` without clipping."""
    leaf = name.rpartition("/")[2]
    short = module.cls.rpartition(":")[2] or module.cls
    widest_in = max((len(port) for port in module.inputs), default=0)
    widest_out = max((len(port) for port in module.outputs), default=0)
    width = max(MIN_W, 32 + TITLE_CHAR_W * len(leaf), 24 + CLASS_CHAR_W * len(short),
                16 + PORT_CHAR_W * (widest_in + widest_out) + PORT_GAP)
    rows = max(len(module.inputs), len(module.outputs))
    height = max(MIN_H, HEADER_H + FOOTER_H + PORT_PITCH * rows)
    return round(width), round(height)


def layout(topology: Topology) -> dict[str, Any]:
    """``{"width", "height", "scaled": 1, "clusters": {node: box}, "macros": {macro:
    {node: box}}, "modules": {name: box}, "links": {key: {"points": [[x, y], ...]}}}``;
    boxes as ``{"x","y","w","h"}`` (the top-left corner), y down, in the page's pixels
    (``scaled``: 1, the page scales nothing); a cluster of a node without modules has
    ``"empty": true``."""
    dot = shutil.which("dot")
    if dot is not None and topology.nodes:
        text, ids = to_dot(topology)
        try:
            done = subprocess.run([dot, "-Tjson"], input=text, text=True,
                                  capture_output=True, timeout=DOT_TIMEOUT, check=True)
            return _from_graphviz(json.loads(done.stdout), topology, ids)
        except (subprocess.SubprocessError, OSError, ValueError, KeyError) as exc:
            detail = getattr(exc, "stderr", "") or ""
            log.warning("Graphviz could not lay the system out (%s %s); a grid stands in",
                        exc, detail.strip()[:300])
    return grid(topology)


def to_dot(topology: Topology) -> tuple[str, _Ids]:
    """DOT of the topology, and what its ids stand for."""
    modules = {name: f"m{number}" for number, name in enumerate(topology.modules)}
    clusters: dict[str, tuple[str, str | None]] = {}
    links: dict[str, str] = {}
    lines = ["digraph system {", "  rankdir=LR; nodesep=0.3; ranksep=0.8;",
             '  node [shape=box, fixedsize=true, label=""];',
             "  edge [arrowhead=none];"]
    for node in topology.nodes:
        cluster = f"cluster_n{len(clusters)}"
        clusters[cluster] = (node, None)
        lines += [f"  subgraph {cluster} {{",
                  f"    label={_blank(NODE_HEADER_W, NODE_HEADER_H)}; labeljust=l; "
                  f"margin={CLUSTER_MARGIN};"]
        names = [name for name, module in topology.modules.items() if module.node == node]
        if not names:
            lines.append(f'    e{len(clusters)} [style=invis, width={EMPTY_W / 72:.3f}, '
                         f"height={EMPTY_H / 72:.3f}];")
        lines += _nested(topology, names, "", node, modules, clusters, "    ")
        lines.append("  }")
    for number, (key, link) in enumerate(topology.links.items()):
        src, dst = link.src.rpartition(".")[0], link.dst.rpartition(".")[0]
        if src in modules and dst in modules:
            links[f"l{number}"] = key
            lines.append(f"  {modules[src]}:e -> {modules[dst]}:w [id=l{number}];")
    lines.append("}")
    return "\n".join(lines) + "\n", _Ids(modules, clusters, links)


def _nested(topology: Topology, names: list[str], prefix: str, node: str,
            ids: dict[str, str], clusters: dict[str, tuple[str, str | None]],
            indent: str) -> list[str]:
    """The modules ``names`` (all below macro path ``prefix``) as DOT: those directly
    in it as boxes, those in each child macro inside a cluster of its own."""
    lines = []
    direct, macros = split_by_macro(names, prefix)
    for name in direct:
        width, height = module_size(name, topology.modules[name])
        lines.append(f"{indent}{ids[name]} [width={width / POINTS_PER_INCH:.3f}, "
                     f"height={height / POINTS_PER_INCH:.3f}];")
    for macro, inside in macros.items():
        cluster = f"cluster_m{len(clusters)}"
        clusters[cluster] = (node, macro)
        title_w = 40 + MACRO_CHAR_W * len(macro)
        lines += [f"{indent}subgraph {cluster} {{",
                  f"{indent}  label={_blank(title_w, MACRO_TITLE_H)}; labeljust=l; "
                  f"margin={CLUSTER_MARGIN};",
                  *_nested(topology, inside, macro + "/", node, ids, clusters, indent + "  "),
                  f"{indent}}}"]
    return lines


def _blank(width: float, height: float) -> str:
    """A label of nothing that takes ``width`` x ``height`` points: room for what the
    page writes there itself."""
    return (f'<<TABLE BORDER="0" CELLPADDING="0" CELLSPACING="0"><TR><TD WIDTH="'
            f'{round(width)}" HEIGHT="{round(height)}"> </TD></TR></TABLE>>')


def _from_graphviz(graph: dict[str, Any], topology: Topology, ids: _Ids) -> dict[str, Any]:
    """Graphviz's JSON (points, y up, centres) as y-down pixel boxes and polylines."""
    _, _, width, height = (float(v) for v in graph["bb"].split(","))
    clusters: dict[str, dict[str, Any]] = {}
    macros: dict[str, dict[str, dict[str, float]]] = {}
    modules = {}
    names = {gv_id: name for name, gv_id in ids.modules.items()}
    for item in graph.get("objects", []):
        gv_name = item.get("name", "")
        if "bb" in item and gv_name in ids.clusters:
            left, bottom, right, top = (float(v) for v in item["bb"].split(","))
            box = _box(left, height - top, right - left, top - bottom)
            node, macro = ids.clusters[gv_name]
            if macro is None:
                empty = not any(m.node == node for m in topology.modules.values())
                clusters[node] = {**box, "empty": True} if empty else box
            else:
                macros.setdefault(macro, {})[node] = box
        elif "pos" in item and gv_name in names:
            x, y = (float(v) for v in item["pos"].split(","))
            w = float(item["width"]) * POINTS_PER_INCH
            h = float(item["height"]) * POINTS_PER_INCH
            modules[names[gv_name]] = _box(x - w / 2, height - y - h / 2, w, h)
    links = {}
    for edge in graph.get("edges", []):
        key = ids.links.get(edge.get("id", ""))
        if key is not None:
            links[key] = {"points": _edge_points(edge.get("pos", ""), height)}
    return {"width": width, "height": height, "scaled": 1, "clusters": clusters,
            "macros": macros, "modules": modules, "links": links}


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
    """A column of modules per node (rows of ``GRID_ROWS``), boxes sized as for Graphviz;
    links straight from output side to input side; no macro frames."""
    clusters: dict[str, dict[str, Any]] = {}
    modules = {}
    left = GRID_GAP
    tallest = 0.0
    top = GRID_GAP + NODE_HEADER_H
    for node in topology.nodes:
        names = [name for name, module in topology.modules.items() if module.node == node]
        sizes = {name: module_size(name, topology.modules[name]) for name in names}
        column_w = max((w for w, _ in sizes.values()), default=EMPTY_W)
        row_h = max((h for _, h in sizes.values()), default=EMPTY_H)
        columns = max(1, -(-len(names) // GRID_ROWS))
        rows = min(len(names), GRID_ROWS) or 1
        for number, name in enumerate(names):
            column, row = divmod(number, GRID_ROWS)
            modules[name] = _box(left + GRID_GAP / 2 + column * (column_w + GRID_GAP),
                                 top + GRID_GAP / 2 + row * (row_h + GRID_GAP), *sizes[name])
        w = columns * (column_w + GRID_GAP)
        h = NODE_HEADER_H + rows * (row_h + GRID_GAP) + GRID_GAP
        clusters[node] = {**_box(left, GRID_GAP, w, h), **({} if names else {"empty": True})}
        left += w + GRID_GAP
        tallest = max(tallest, h)
    links = {}
    for key, link in topology.links.items():
        src = modules.get(link.src.rpartition(".")[0])
        dst = modules.get(link.dst.rpartition(".")[0])
        if src and dst:
            links[key] = {"points": [[src["x"] + src["w"], src["y"] + src["h"] / 2],
                                     [dst["x"], dst["y"] + dst["h"] / 2]]}
    return {"width": left, "height": tallest + 2 * GRID_GAP, "scaled": 1,
            "clusters": clusters, "macros": {}, "modules": modules, "links": links}


def _box(x: float, y: float, w: float, h: float) -> dict[str, float]:
    return {"x": round(x, 1), "y": round(y, 1), "w": round(w, 1), "h": round(h, 1)}
