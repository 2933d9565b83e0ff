"""A system's flat structure folded back into a configuration's tables: read again,
they make the same plan (modules, their settings, links, nodes), macros included."""

from __future__ import annotations

import numpy as np
import pytest
from sample_modules import Chain, FloatSource, Last, Outer, Scale

from pb3a import System
from pb3a.config.compiler import build_plan, sketch_plan
from pb3a.config.description import read_description
from pb3a.config.folding import fold
from pb3a.config.plan import FlatModule, Plan
from pb3a.loading.references import class_ref


def folded_again(plan: Plan) -> tuple[dict, list[str], Plan]:
    folded = fold(plan.name, plan.nodes, plan.modules.values(), plan.links,
                  plan.code.module_servers, plan.timeout)
    again, problems = sketch_plan(read_description(folded.tables, "the folded tables"))
    assert problems == [], problems
    return folded.tables, folded.problems, again


def shape(plan: Plan) -> tuple[dict, dict, dict]:
    """What must survive: each module's settings, each link's policy, each node.
    (Classes by reference: another test may have reloaded their module meanwhile.)"""
    modules = {m.name: (class_ref(m.cls), m.node, m.period, m.state, m.restart, m.group, m.fallback)
               for m in plan.modules.values()}
    links = {link.key: str(link.policy) for link in plan.links}
    nodes = {n.name: (n.address, n.workers, n.cpus, n.advertise, n.spares)
             for n in plan.nodes.values()}
    return modules, links, nodes


def test_nested_macros_links_through_them_and_every_setting_come_back() -> None:
    system = System("folded", timeout=12.0).node("a", workers=2).node("b", cpus=[0], spares=0)
    system.add("src", FloatSource, node="a", period=0.02, state={"value": 3.0})
    system.add("outer", Outer, node="b")
    system.add("pair", Chain, node="a")
    system.add("last", Last, node="b", restart="fresh", fallback=["a"], group="sinks")
    system.add("tail", Scale, node="b", group="sinks", state={"gain": 0.5})
    system.link("src.out", "outer.x", policy="queue:8")
    system.link("outer.y", "pair.x")
    system.link("pair.y", "last.x")
    system.link("env-a.cpu", "tail.x")
    plan = build_plan(system._spec)
    tables, problems, again = folded_again(plan)
    assert problems == []
    assert shape(again) == shape(plan)
    assert list(again.modules) == list(plan.modules)           # the start order too
    # each macro instance is a definition of its own; links go through their exports
    assert set(tables["macros"]) == {"outer", "outer-chain", "pair"}
    assert tables["modules"]["outer"] == {"macro": "outer"}
    assert tables["macros"]["outer"]["modules"]["chain"] == {"macro": "outer-chain"}
    assert {"from": "src.out", "to": "outer.chain_a_x", "policy": "queue:8"} in tables["links"]
    assert tables["macros"]["outer"]["exports"]["chain_a_x"] == "chain.a_x"
    assert tables["macros"]["outer-chain"]["exports"]["a_x"] == "a.x"
    assert {"from": "a.y", "to": "b.x"} in tables["macros"]["pair"]["links"]
    assert "env-a" not in tables["modules"]        # the compiler adds it again for the link
    assert tables["timeout"] == 12.0 and tables["nodes"]["b"] == {"cpus": [0], "spares": 0}


def test_a_changed_system_and_what_toml_cannot_hold() -> None:
    system = System("plain", workers=3)
    system.add("src", FloatSource)
    system.add("scale", Scale)
    system.link("src.out", "scale.x")
    plan = build_plan(system._spec)
    # as a running system may have it after an add with an array as its state
    plan.modules["held"] = FlatModule("held", Scale, "local", None,
                                      {"gain": np.float64(4.0), "setups": np.zeros(3)},
                                      "never")
    tables, problems, again = folded_again(plan)
    assert "nodes" not in tables and tables["workers"] == 3          # the implicit node
    assert tables["modules"]["held"]["state"] == {"gain": 4.0}
    assert type(tables["modules"]["held"]["state"]["gain"]) is float
    assert problems == ["module held: its configured state 'setups' (ndarray) has no TOML "
                        "form, left out: it starts with its class's value"]
    assert again.modules["held"].state == {"gain": 4.0}
    assert set(again.modules) == {"src", "scale", "held"}


def test_a_declared_local_node_keeps_what_a_top_level_key_cannot_say() -> None:
    """A lone node named "local" is written as no nodes only when it has nothing but
    ``workers``; its cpus, spares and advertise need its table."""
    declared = System("one-node").node("local", cpus=[0], spares=0, advertise="127.0.0.1")
    declared.add("src", FloatSource)
    plan = build_plan(declared._spec)
    tables, problems, again = folded_again(plan)
    assert problems == [] and shape(again) == shape(plan)
    assert tables["nodes"] == {"local": {"cpus": [0], "advertise": "127.0.0.1", "spares": 0}}
    assert tables["modules"]["src"]["node"] == "local"
    only_workers = System("one-node").node("local", workers=2)
    only_workers.add("src", FloatSource)
    plan = build_plan(only_workers._spec)
    tables, problems, again = folded_again(plan)
    assert "nodes" not in tables and tables["workers"] == 2 and shape(again) == shape(plan)


@pytest.mark.parametrize("setting", [{"cpus": [0]}, {"spares": 0}, {"advertise": "127.0.0.1"},
                                     {"address": "tcp://127.0.0.1:7700"}])
def test_a_declared_local_node_keeps_each_such_setting_alone(setting: dict) -> None:
    """... each of them on its own (with all set together, a check that forgot one
    still kept the table for the others)."""
    declared = System("one-node").node("local", **setting)
    declared.add("src", FloatSource)
    plan = build_plan(declared._spec)
    tables, problems, again = folded_again(plan)
    assert problems == [] and shape(again) == shape(plan)
    assert tables["nodes"] == {"local": setting}


def test_a_declared_env_module_keeps_its_settings_and_only_the_compiler_s_own_is_left_out(
        ) -> None:
    """An env module read by a link was always left out as the compiler's own, so a
    period of its own came back as the default, with no problem reported."""
    for period, written in ((0.5, True), (1.0, False)):
        system = System("env").node("a")
        system.add("env-a", "pb3a.model.environment:Environment", node="a", period=period)
        system.add("t", Last, node="a")
        system.link("env-a.cpu", "t.x")
        plan = build_plan(system._spec)
        tables, problems, again = folded_again(plan)
        assert problems == [] and shape(again) == shape(plan)
        assert ("env-a" in tables["modules"]) is written


def test_a_class_defined_in_a_script_is_named_as_a_problem_when_folded() -> None:
    """Folded as __main__:Class, silently: pb3a check then refused the file."""
    import types

    script = types.ModuleType("__main__")
    exec("from pb3a import Module, Output\n"
         "class Ticker(Module):\n    out = Output(float)\n", script.__dict__)
    plan = build_plan(System("script").add("tick", script.Ticker)._spec)
    folded = fold(plan.name, plan.nodes, plan.modules.values(), plan.links,
                  plan.code.module_servers, plan.timeout)
    assert folded.problems == [
        "module tick: its class __main__:Ticker is defined in a script (or a function), which "
        "no file can name: `pb3a check` will refuse it; move the class into a module that can "
        "be imported"]


def test_a_group_set_on_a_macro_instance_comes_back_on_the_instance() -> None:
    """Its modules' group ('g', not 'm/...') cannot be written inside the macro: it was
    left out, with a problem, and each module got a worker of its own."""
    system = System("grp").add("m", Chain, group="g").add("n", Outer, group="h")
    system.add("alone", Scale, group="g")
    plan = build_plan(system._spec)
    tables, problems, again = folded_again(plan)
    assert problems == [] and shape(again) == shape(plan)
    assert tables["modules"]["m"] == {"macro": tables["modules"]["m"]["macro"], "group": "g"}
    assert tables["modules"]["n"]["group"] == "h"


def test_an_enum_in_the_configured_state_is_named_as_having_no_toml_form() -> None:
    """An IntEnum was written as its int, silently: the module then started with an int."""
    import enum

    class Mode(enum.IntEnum):
        FAST = 3

    plan = build_plan(System("e").add("s", Scale, state={"gain": 2.0})._spec)
    plan.modules["s"].state["gain"] = Mode.FAST                 # as a program may set it
    folded = fold(plan.name, plan.nodes, plan.modules.values(), plan.links,
                  plan.code.module_servers, plan.timeout)
    assert "state" not in folded.tables["modules"]["s"]
    assert folded.problems == ["module s: its configured state 'gain' (Mode) has no TOML "
                               "form, left out: it starts with its class's value"]
