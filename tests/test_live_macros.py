"""A macro added to a running system, and removed from it, whole: from the program, an
agent and the command line (``Operations.add`` refused it as no Module subclass, and
``remove`` of a macro instance as no module)."""

from __future__ import annotations

import re

import pytest
from conftest import eventually
from sample_modules import (
    Chain,
    Counter,
    DeviceKit,
    FloatSource,
    FreezerPair,
    Last,
    Outer,
    Scale,
    SpawnerKit,
)

from pb3a import ConfigError, ModuleNotFound, RuntimeFailure, RuntimeTimeout, System

pytestmark = pytest.mark.timeout(90)


def _two_nodes(name: str) -> System:
    system = System(name).node("a").node("b")
    system.add("src", FloatSource, node="a", state={"value": 1.5})
    system.add("sink", Last, node="a")
    return system


def test_a_macro_is_added_whole_runs_moves_and_is_removed_whole() -> None:
    with _two_nodes("live-macro").launch() as run:
        run.add("c2", Chain, node="b", state={"b": {"gain": 5}})
        assert run.where("c2/a") == run.where("c2/b") == "b"
        assert run.state("c2/b")["gain"] == 5.0 and type(run.state("c2/b")["gain"]) is float
        assert "c2/a.y->c2/b.x" in run.topology().links            # its inner link
        # links reach it through its exports, as a launched macro's do (they were refused:
        # only its modules' own ports were linked at run time), or join those ports
        with pytest.raises(ConfigError, match="macro instance 'c2' exports no port 'q'; it "
                           "exports: x, y"):
            run.link("src.out", "c2.q")
        with pytest.raises(ConfigError, match=r"c2/b \(where c2.y leads\) has no input 'y'"):
            run.link("src.out", "c2.y")
        run.link("src.out", "c2.x")
        run.link("c2/b.y", "sink.x")
        assert "src.out->c2/a.x" in run.topology().links
        eventually(lambda: run.state("sink")["value"] == 15.0, what="1.5 * 2 * 5 at the sink")
        folded = run.configuration()
        assert folded["problems"] == []
        tables = folded["system"]
        assert tables["modules"]["c2"] == {"macro": "c2"}
        macro = tables["macros"]["c2"]
        assert set(macro["modules"]) == {"a", "b"} and macro["modules"]["b"]["state"] == {
            "gain": 5.0}
        assert macro["links"] == [{"from": "a.y", "to": "b.x"}]
        # a module may not take its name, nor one inside one of its modules (one named
        # "c2" hid the macro instance: configuration() dropped it)
        with pytest.raises(ConfigError, match="a macro instance of that name runs already: "
                                              "c2/a, c2/b"):
            run.add("c2", Counter)
        with pytest.raises(ConfigError, match="c2/a is a module, not a macro instance"):
            run.add("c2/a/x", Counter)
        report = run.migrate("c2", to="a")                          # it moves as one
        assert report.destination == "a" and run.where("c2/a") == run.where("c2/b") == "a"
        since = run.events()[-1].seq
        run.remove("c2")
        assert not [name for name in run.topology().modules if name.startswith("c2")]
        assert not [key for key in run.topology().links if "c2/" in key]
        gone = [(event.kind, event.subject) for event in run.events(since)]
        assert [subject for kind, subject in gone if kind == "module_removed"] == [
            "c2/b", "c2/a"]                                          # last first
        assert {subject for kind, subject in gone if kind == "link_removed"} == {
            "c2/a.y->c2/b.x", "c2/b.y->sink.x", "src.out->c2/a.x"}
        with pytest.raises(ModuleNotFound, match="no module 'c2'"):
            run.remove("c2")
        with pytest.raises(ConfigError, match="no module 'c2'"):    # nor its exports
            run.link("src.out", "c2.x")
        run.add("kit/o2", Outer)                # nested, and inside a path: as a file's
        assert {"kit/o2/chain/a", "kit/o2/chain/b", "kit/o2/tail"} <= set(
            run.topology().modules)
        run.link("src.out", "kit/o2.x")         # (through the exports of both macros)
        run.link("kit/o2/chain.y", "sink.x")
        assert {"src.out->kit/o2/chain/a.x", "kit/o2/chain/b.y->sink.x"} <= set(
            run.topology().links)
        added = [(event.kind, event.subject) for event in run.events()
                 if event.subject.startswith("kit/")]
        assert ("link_added", "kit/o2/chain/a.y->kit/o2/chain/b.x") in added
        assert ("module_added", "kit/o2/tail") in added


def test_adding_a_macro_refuses_what_cannot_work_and_starts_nothing() -> None:
    system = _two_nodes("macro-refused")
    system.add("c", Chain, node="a")
    system.add("grouped", Scale, node="a", group="g")
    with system.launch() as run:
        before = run.topology()
        for name, options, words in [
                ("c", {}, "macro c: a macro instance of that name runs already: c/a, c/b"),
                ("sink", {}, "macro sink: a module of that name runs already"),
                ("sink/c3", {}, "macro sink/c3: sink is a module, not a macro instance"),
                ("c3", {"node": "zz"}, "macro c3: no node 'zz'; nodes: a, b"),
                ("c3", {"period": 1.0}, "macro c3: 'period' applies to modules, not to a macro"),
                ("c3", {"state": {"b": {"gian": 1.0}}}, "macro c3: state of 'b': "),
                ("c3", {"state": {"d": {"gain": 1.0}}}, "state names 'd', which is not a "
                                                        "module of macro"),
                ("c3", {"group": "g", "node": "b"}, "group 'g' would span nodes 'a' (grouped) "
                                                    "and 'b' (c3/a)"),
                ("bad.name", {}, "bad macro instance name 'bad.name'")]:
            with pytest.raises(ConfigError) as caught:
                run.add(name, Chain, **options)
            assert any(words in problem for problem in caught.value.problems), \
                (words, caught.value.problems)
        after = run.topology()
        assert (set(after.modules), set(after.links)) == (set(before.modules),
                                                          set(before.links))
        assert [event.kind for event in run.events()] == []


def test_a_macro_one_of_whose_modules_cannot_start_is_not_added() -> None:
    system = System("macro-setup")
    system.add("other", Counter, period=0.05)
    with system.launch() as run:
        with pytest.raises(RuntimeFailure, match=r"module 'kit/cam' raised in setup: "
                           r"RuntimeError: device /dev/video7 not found"):
            run.add("kit", DeviceKit, state={"cam": {"missing": True}})
        topology = run.topology()
        assert set(topology.modules) == {"other"} and not topology.links
        assert set(run.stats().modules) == {"other"}
        assert [event.kind for event in run.events()] == []
        run.add("kit", DeviceKit)                       # mended, it may be added
        eventually(lambda: run.state("kit/cam")["handled"] > 3, what="kit/tick feeds kit/cam")


def test_a_macro_is_removed_last_module_first_and_one_left_is_named() -> None:
    system = System("macro-remove-frozen")
    with system.launch() as run:
        run.add("pair", FreezerPair, state={"freezer": {"freeze_in": "teardown"}})
        eventually(lambda: run.state("pair/freezer")["steps"] > 0, what="the freezer steps")
        # (stuck in its teardown: it was said to be stuck in "step, on_input, setup")
        with pytest.raises(RuntimeTimeout, match=r"remove pair: .*did not answer 'stop'.*"
                           r"stuck in a long call \(its teardown, .*; "
                           r"removed: pair/steady; left running: pair/freezer"):
            run.remove("pair", timeout=1)
        assert set(run.topology().modules) == {"pair/freezer"}
        run.remove("pair", timeout=1, force=True)
        assert not run.topology().modules


def test_an_agent_spawns_and_removes_a_macro_but_not_its_own() -> None:
    system = System("agent-macro")
    system.add("src", FloatSource, state={"value": 1.5})
    system.add("scale", Scale)
    system.link("src.out", "scale.x")
    system.add("kit", SpawnerKit)
    system.add("trigger", Counter, state={"limit": 1}, period=0.05)
    system.link("trigger.out", "kit.go")
    with system.launch() as run:
        eventually(lambda: "c2/b" in run.topology().modules, what="the spawned macro")
        assert run.state("c2/b")["gain"] == 5.0
        eventually(lambda: run.stats().modules["c2/b"].events > 0, what="values through c2")
        # (its try at removing its own macro comes after the link: wait for its answer)
        refused = eventually(lambda: run.state("kit/agent")["refused"], what="the refusal")
        assert refused == ("ValueError: remove kit: agent 'kit/agent' is in it: an agent "
                           "cannot remove itself or the macro it is in (the stop would wait "
                           "for the very call that asks it; it may migrate itself)")
        # (the launcher refuses it too, in the same words, should a request get past it)
        with pytest.raises(ConfigError, match=re.escape(refused.removeprefix("ValueError: "))):
            run._operations.apply("remove", {"name": "kit"}, asker=("kit/agent", False))
        assert "kit/agent" in run.topology().modules
        run.set_state("trigger", limit=2)
        eventually(lambda: not [name for name in run.topology().modules
                                if name.startswith("c2/")], what="the macro removed")
