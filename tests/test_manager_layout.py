"""The schematic's layout: every node a region (an empty one too), module boxes sized for
what the page draws in them, macro frames nested with room for their titles, and every
link leaving an output side and entering an input side, back edges included."""

from __future__ import annotations

import itertools
import shutil
from typing import Any

import pytest
from sample_modules import Chain, FloatSource, Outer, Scale

from pb3a import Input, Module, Output, System
from pb3a.manager import layout as layouts
from pb3a.topology import Topology, plan_topology


class Wide(Module):
    """Many ports with long names: a box taller and wider than the least one."""

    left_hand_input = Input(float)
    second = Input(float)
    third = Input(float)
    fourth = Input(float)
    right_hand_output = Output(float)


def topology() -> Topology:
    system = System("shapes").node("a").node("b").node("spare")
    system.add("src", FloatSource, node="a")
    system.add("pair", Chain, node="a")
    system.add("outer", Outer, node="b")
    system.add("wide", Wide, node="b")
    system.add("loop", Scale, node="b")
    system.link("src.out", "pair.x")
    system.link("pair.y", "outer.x")
    system.link("outer.y", "loop.x")
    system.link("loop.y", "wide.left_hand_input")
    system.add("echo", Scale, node="a")
    system.link("wide.right_hand_output", "echo.x")
    system.link("echo.y", "wide.second")                  # a cycle: one of them goes back
    return plan_topology(system.plan())


def inside(inner: dict[str, float], outer: dict[str, float], top: float = 0.0) -> bool:
    """``inner`` lies in ``outer``, at least ``top`` below its top edge."""
    return (outer["x"] <= inner["x"] and inner["x"] + inner["w"] <= outer["x"] + outer["w"]
            and outer["y"] + top <= inner["y"]
            and inner["y"] + inner["h"] <= outer["y"] + outer["h"])


def overlap(a: dict[str, float], b: dict[str, float]) -> bool:
    return (a["x"] < b["x"] + b["w"] and b["x"] < a["x"] + a["w"]
            and a["y"] < b["y"] + b["h"] and b["y"] < a["y"] + a["h"])


def check(found: dict[str, Any], shapes: Topology, frames: bool) -> None:
    assert found["scaled"] == 1                 # page pixels: the page scales nothing
    assert set(found["clusters"]) == {"a", "b", "spare"}
    spare = found["clusters"]["spare"]
    assert spare["empty"] is True and spare["w"] >= layouts.EMPTY_W
    assert "empty" not in found["clusters"]["a"]
    boxes = found["modules"]
    assert set(boxes) == set(shapes.modules)
    for name, module in shapes.modules.items():
        box = boxes[name]
        assert (box["w"], box["h"]) == layouts.module_size(name, module), name
        assert inside(box, found["clusters"][module.node], top=layouts.NODE_HEADER_H), name
    for a, b in itertools.combinations(boxes, 2):
        assert not overlap(boxes[a], boxes[b]), (a, b)
    wide, least = boxes["wide"], boxes["src"]
    assert (least["w"], least["h"]) == (layouts.MIN_W, layouts.MIN_H)
    assert wide["h"] >= layouts.HEADER_H + layouts.FOOTER_H + 4 * layouts.PORT_PITCH
    # both long port names fit on one row (10 px monospace: about 6 px a letter)
    assert wide["w"] >= 6 * len("left_hand_input" + "right_hand_output") + 2 * 12
    for key, link in shapes.links.items():
        points = found["links"][key]["points"]
        src, dst = boxes[link.src.rpartition(".")[0]], boxes[link.dst.rpartition(".")[0]]
        # leaves the source's output side, enters the target's input side
        assert abs(points[0][0] - (src["x"] + src["w"])) <= 2, (key, points[0], src)
        assert abs(points[-1][0] - dst["x"]) <= 2, (key, points[-1], dst)
    if not frames:
        return
    macros = found["macros"]
    assert set(macros) == {"pair", "outer", "outer/chain"}
    assert inside(macros["pair"]["a"], found["clusters"]["a"])
    assert inside(macros["outer/chain"]["b"], macros["outer"]["b"], top=16)
    for macro, members in shapes.macros.items():
        for name in members:
            frame = macros[macro][shapes.modules[name].node]
            assert inside(boxes[name], frame, top=22), (macro, name)  # the frame's title


@pytest.mark.skipif(shutil.which("dot") is None, reason="Graphviz (dot) is not installed")
def test_graphviz_places_every_node_sized_box_nested_frame_and_link() -> None:
    shapes = topology()
    found = layouts.layout(shapes)
    assert found["macros"], "Graphviz failed: the grid stood in"
    check(found, shapes, frames=True)
    cycle = [found["links"][key]["points"] for key in ("wide.right_hand_output->echo.x",
                                                       "echo.y->wide.second")]
    assert any(points[0][0] > points[-1][0] for points in cycle)   # one goes back


def test_without_graphviz_a_grid_keeps_the_same_promises(monkeypatch) -> None:
    monkeypatch.setattr(layouts.shutil, "which", lambda name: None)
    shapes = topology()
    found = layouts.layout(shapes)
    assert found["macros"] == {}
    check(found, shapes, frames=False)
