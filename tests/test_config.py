"""The configuration layer: loading classes, TOML and Python descriptions, macros, validation."""

from __future__ import annotations

import importlib.machinery
import os
import re
import shutil
import subprocess
import sys
import textwrap
import tomllib
import types
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from sample_modules import DeviceReader, Pump

import examples.pipeline
from agents.robot_driver import RobotDriver
from examples.pipeline import FastScale, Scale, Ticker
from pb3a.config.compiler import build_plan, validate
from pb3a.config.description import NodeSpec, SystemSpec, load_toml
from pb3a.config.plan import FlatLink, Plan
from pb3a.errors import ConfigError
from pb3a.loading.references import resolve_class
from pb3a.loading.sources import launcher_paths
from pb3a.model.macro import Macro
from pb3a.model.module import Module
from pb3a.model.ports import Policy
from pb3a.model.state_edits import class_state
from pb3a.node.class_check import searched
from pb3a.system import System

PIPELINE = Path(examples.pipeline.__file__).with_name("pipeline.toml")

# A module of parts the TOML fixtures name as "parts_cfg:Class"; written to a temporary
# directory on sys.path so that it is importable by reference, as user code would be.
PARTS = '''
from pb3a.model.macro import Macro
from pb3a.model.module import Module
from pb3a.model.ports import Input, Output


class Src(Module):
    out = Output(float)
    period = 0.1
    value = 1.0

    def step(self):
        self.out.write(self.value)


class Words(Module):
    out = Output(str)


class Sink(Module):
    x = Input(float)
    y = Output(float)
    seen = 0

    def step(self):             # (steps when given a period: a macro's "gain" is)
        self.y.write(float(self.seen))


class Queued(Module):
    x = Input(float, policy="queue:4")


class Custom(Module):
    x = Input(float)

    def get_state(self):
        return {"anything": 1}

    def set_state(self, state):
        pass


class NotAModule:
    pass


def helper():
    return 1


class Filter(Macro):
    modules = {"lp": Sink,
               "gain": {"class": "parts_cfg:Sink", "state": {"seen": 2}, "period": 0.01},
               "tail": "parts_cfg:Sink"}
    links = [("lp.y", "gain.x"), {"from": "gain.y", "to": "tail.x", "policy": "queue:8"}]
    exports = {"x": "lp.x", "y": "tail.y"}


class Twice(Macro):
    modules = {"first": Filter, "second": {"class": Filter}}
    links = [("first.y", "second.x")]
    exports = {"x": "first.x", "y": "second.y"}


class BadMacro(Macro):
    modules = {"s": {"class": Sink, "perod": 1}}
    links = [("s.y", "s.nope")]
    exports = {"x": "s.x"}
'''


@pytest.fixture(scope="module", autouse=True)
def parts(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    folder = tmp_path_factory.mktemp("parts")
    (folder / "parts_cfg.py").write_text(PARTS)
    (folder / "parts_boom.py").write_text("raise RuntimeError('boom')\n")
    (folder / "parts_needs.py").write_text("import math\nimport no_such_dependency\n")
    (folder / "parts_names.py").write_text("from parts_cfg import no_such_name\n")
    (folder / "parts_exits.py").write_text("import sys\nsys.exit(4)\n")
    sys.path.insert(0, str(folder))
    yield
    sys.path.remove(str(folder))
    sys.modules.pop("parts_cfg", None)
    sys.modules.pop("parts_boom", None)
    sys.modules.pop("parts_needs", None)
    sys.modules.pop("parts_names", None)
    sys.modules.pop("parts_exits", None)


def write(tmp_path: Path, text: str, name: str = "sys.toml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def problems_of(tmp_path: Path, text: str) -> list[str]:
    """The problems of a description, its file named as if given relative to its folder."""
    problems = validate(load_toml(write(tmp_path, text)))
    return [p.replace(f"{tmp_path}/", "") for p in problems]


def only(problems: list[str], *needles: str) -> str:
    """The one problem containing every needle (fails listing all problems otherwise)."""
    found = [p for p in problems if all(n in p for n in needles)]
    assert len(found) == 1, f"expected one problem with {needles}, got:\n" + "\n".join(problems)
    return found[0]


TWO = """
    [modules.src]
    class = "parts_cfg:Src"
    [modules.sink]
    class = "parts_cfg:Sink"
"""


# -- resolve_class ------------------------------------------------------------
def test_resolve_class_accepts_a_class_or_a_colon_reference() -> None:
    assert resolve_class(Scale) is Scale
    assert resolve_class("examples.pipeline:FastScale") is FastScale


def test_a_misspelt_installed_package_gets_a_did_you_mean_from_anywhere(
        tmp_path: Path) -> None:
    """A misspelt top-level package was matched against the import path's directories
    alone: run from another directory, an editable install's packages (this project's
    `agents`, `rave`) are on none of them, and no "did you mean" came."""
    done = subprocess.run(
        [sys.executable, "-c", "from pb3a.loading.references import resolve_class\n"
         "resolve_class('agentz.monitor:Monitor')"],
        cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert "No module named 'agentz' (did you mean 'agents'?)" in done.stderr, done.stderr
    # a distribution whose metadata is not UTF-8 (an old sdist's) takes the suggestion
    # away, not the error it is for (its UnicodeDecodeError was said instead)
    latin = tmp_path / "site" / "latin-1.0.dist-info"
    latin.mkdir(parents=True)
    (latin / "METADATA").write_bytes(b"Metadata-Version: 2.1\nName: latin\nVersion: 1.0\n"
                                     b"Author: Jos\xe9\n")
    (latin / "RECORD").write_bytes(b"latin/__init__.py,,\nJos\xe9.py,,\n")
    done = subprocess.run(
        [sys.executable, "-c", "from pb3a.loading.references import resolve_class\n"
         "resolve_class('agentz.monitor:Monitor')"],
        cwd=tmp_path, capture_output=True, text=True, timeout=60,
        env={**os.environ, "PYTHONPATH": str(tmp_path / "site")})
    assert "ImportError: cannot import module 'agentz.monitor' for 'agentz.monitor:Monitor'" \
        in done.stderr, done.stderr


def test_a_system_is_built_where_the_current_directory_was_removed(
        tmp_path: Path, monkeypatch) -> None:
    """The place an entry was written at is named from the current directory; with that
    directory removed, every ``add`` raised FileNotFoundError."""
    gone = tmp_path / "gone"
    gone.mkdir()
    monkeypatch.chdir(gone)
    gone.rmdir()
    problems = System("homeless").add("tick", Ticker, period=-1).check()
    assert len(problems) == 1 and problems[0].startswith(f"{__file__}:"), problems


def test_a_class_a_module_lacks_is_said_with_where_the_module_was_imported_from(
        tmp_path, monkeypatch) -> None:
    """"module 'probe' has no class 'Probe'" named no file: a copy other than the one
    meant (a directory of that name, imported as a namespace package, an older file
    elsewhere on the path) was not to be told from a typo."""
    (tmp_path / "as_a_directory").mkdir()
    (tmp_path / "as_a_file.py").write_text("class Other:\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(LookupError) as raised:
        resolve_class("as_a_directory:Probe")
    assert str(raised.value) == (
        f"module 'as_a_directory' has no class 'Probe'; it was imported from "
        f"{tmp_path / 'as_a_directory'}, a directory with no __init__.py (a namespace "
        "package): rename it, or move it off the import path")
    with pytest.raises(LookupError) as raised:
        resolve_class("as_a_file:Probe")
    assert str(raised.value) == (f"module 'as_a_file' has no class 'Probe'; it has: Other; "
                                 f"it was imported from {tmp_path / 'as_a_file.py'}")


def test_a_system_built_in_python_is_imported_from_its_script_s_directories(
        tmp_path, monkeypatch) -> None:
    """A system built in Python hands its nodes the directories its script imports from,
    as Python has them: ``sys.path[0]`` (``''``: the current directory, for ``python
    -c``, the REPL, a notebook), unless Python leaves it off, and ``PYTHONPATH``; those
    that exist, once each. It was handed none, and its nodes could not import a class of
    a file beside the script (a TOML's directory is handed)."""
    here, lib = tmp_path / "here", tmp_path / "lib"
    here.mkdir()
    lib.mkdir()
    monkeypatch.chdir(here)
    monkeypatch.setattr(sys, "path", ["", *sys.path])
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(lib), str(tmp_path / "gone"), "",
                                                      str(here)]))
    plan = System("scripted").add("t", Ticker).plan()
    assert plan.code.paths == (str(here), str(lib))
    assert sys.path[:2] == [str(here), str(lib)]          # (installed here too, first)


def test_a_configuration_file_hands_its_nodes_its_directory_then_the_pythonpath_s(
        tmp_path, monkeypatch) -> None:
    """A configuration file's system (``pb3a run FILE``, ``System.load``) hands its nodes
    the file's directory, then its launcher's ``PYTHONPATH``'s, as a script's system
    hands its own: those that exist, once each. It handed the file's directory alone,
    and a node started without that ``PYTHONPATH`` could not import a class of it."""
    conf, lib = tmp_path / "conf", tmp_path / "lib"
    conf.mkdir()
    lib.mkdir()
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))          # (the plan installs its own)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(lib), str(tmp_path / "gone"), "",
                                                      str(conf)]))
    (conf / "system.toml").write_text('name = "filed"\n[modules.t]\n'
                                      'class = "examples.pipeline:Ticker"\n')
    plan = System.load(conf / "system.toml").plan()
    assert plan.code.paths == (str(conf), str(lib))
    assert sys.path[:2] == [str(conf), str(lib)]


def test_a_script_that_put_a_directory_first_hands_its_own_directory_too(
        tmp_path, monkeypatch) -> None:
    """``sys.path.insert(0, lib)`` in a script handed its nodes ``lib`` alone: a class of
    a file beside the script was found nowhere on them. Its own directory (its file's)
    comes next; a module run with ``python -m`` has none of its own."""
    scripts, lib = tmp_path / "scripts", tmp_path / "lib"
    scripts.mkdir()
    lib.mkdir()
    monkeypatch.delenv("PYTHONPATH", raising=False)
    monkeypatch.setattr(sys, "path", [str(lib), *sys.path])
    main = types.ModuleType("__main__")
    main.__file__ = str(scripts / "run.py")
    monkeypatch.setitem(sys.modules, "__main__", main)
    assert launcher_paths() == (str(lib), str(scripts))
    main.__spec__ = importlib.machinery.ModuleSpec("run", None)       # (python -m run)
    assert launcher_paths() == (str(lib),)


def test_the_path_a_node_searched_marks_the_launcher_s_directory_under_python_s_prefix(
        tmp_path, monkeypatch) -> None:
    """A launcher's directory under Python's prefix (/usr/local/lab with a system
    Python) was said as Python's own, unmarked, and Python's own was said twice."""
    prefix, other = tmp_path / "usr", tmp_path / "other"
    lab = prefix / "local" / "lab"
    for name in ("prefix", "base_prefix", "exec_prefix", "base_exec_prefix"):
        monkeypatch.setattr(sys, name, str(prefix))
    monkeypatch.setattr(sys, "path", [str(prefix / "lib" / "python3.11"), str(lab), str(other),
                                      str(prefix / "lib" / "site-packages")])
    monkeypatch.chdir(tmp_path)
    assert searched((str(lab),)) == (f"Python's standard library and installed packages, "
                                     f"{lab} (the launcher's), {other}")


def test_resolve_class_errors_say_what_to_change() -> None:
    with pytest.raises(LookupError, match=r"module 'examples\.pipeline' has no class 'Tickr'"):
        resolve_class("examples.pipeline:Tickr")
    with pytest.raises(ValueError, match=r"use 'module:Class'.*'examples\.pipeline:Ticker'"):
        resolve_class("examples.pipeline.Ticker")
    with pytest.raises(ImportError, match=r"cannot import module 'no_such_pkg\.mod'"):
        resolve_class("no_such_pkg.mod:Thing")
    # a misspelt module of a package is named as a misspelt class is; a module's list of
    # classes is its own (it named pb3a's Input, InputPort, Module and Output too)
    with pytest.raises(ImportError, match=r"'examples\.pipline' \(did you mean "
                                          r"'examples\.pipeline'\?\); check the module path"):
        resolve_class("examples.pipline:Ticker")
    with pytest.raises(LookupError, match=r"no class .Nope.; it has: FastScale, Scale, Ticker; "
                                          r"it was imported from \S+pipeline\.py$"):
        resolve_class("examples.pipeline:Nope")
    with pytest.raises(TypeError, match="not a class"):
        resolve_class("parts_cfg:helper")
    with pytest.raises(ImportError, match=r"importing module 'parts_boom' for 'parts_boom:"
                                          r"Thing' failed at .*parts_boom\.py, line 1: "
                                          r"RuntimeError: boom"):
        resolve_class("parts_boom:Thing")
    # found, but an import of its own failed: that import is named, not the module path
    with pytest.raises(ImportError, match=r"importing module 'parts_needs' for 'parts_needs:"
                                          r"Thing' failed at .*parts_needs\.py, line 2: No "
                                          r"module named 'no_such_dependency'; install "
                                          r"'no_such_dependency' or correct that import"):
        resolve_class("parts_needs:Thing")
    with pytest.raises(ImportError, match=r"importing module 'parts_names' for 'parts_names:"
                                          r"Thing' failed at .*parts_names\.py, line 1: "
                                          r"cannot import name 'no_such_name' from 'parts_cfg'"):
        resolve_class("parts_names:Thing")


def test_a_module_that_calls_sys_exit_as_it_is_imported_is_an_import_error() -> None:
    """A module file's sys.exit() as resolve_class imported it went through: it ended the
    process that loaded the class (`pb3a check` with the file's status and not a word, a
    launcher); it is an import error naming the file and line, and the fix."""
    with pytest.raises(ImportError, match=r"importing module 'parts_exits' for 'parts_exits:"
                                          r"Thing' failed at .*parts_exits\.py, line 2: it "
                                          r"calls sys\.exit\(4\) as it is imported; a module "
                                          r"must not exit when imported \(put that code under "
                                          r"if __name__ == '__main__':\)"):
        resolve_class("parts_exits:Thing")


# -- valid descriptions -------------------------------------------------------
def test_the_pipeline_example_becomes_a_plan() -> None:
    plan = build_plan(load_toml(PIPELINE))
    assert isinstance(plan, Plan)
    assert plan.name == "pipeline"
    assert list(plan.nodes) == ["local"]
    assert plan.nodes["local"].workers == 0
    assert list(plan.modules) == ["tick", "scale"]
    tick, scale = plan.modules["tick"], plan.modules["scale"]
    assert (tick.cls, tick.node, tick.period, tick.state, tick.restart, tick.group) == (
        Ticker, "local", 0.005, {"count": 0}, "never", None)
    assert (scale.cls, scale.period, scale.state) == (Scale, None, {"gain": 3.0})
    assert plan.links == [FlatLink("tick", "out", "scale", "x", Policy("queue", 64))]
    assert plan.links[0].key == "tick.out->scale.x"


def test_a_link_without_policy_takes_the_inputs_own(tmp_path: Path) -> None:
    plan = build_plan(load_toml(write(tmp_path, """
        [modules.src]
        class = "parts_cfg:Src"
        [modules.q]
        class = "parts_cfg:Queued"
        [modules.s]
        class = "parts_cfg:Sink"
        [[links]]
        from = "src.out"
        to = "q.x"
        [[links]]
        from = "src.out"
        to = "s.x"
        policy = "queue"
    """)))
    assert [str(link.policy) for link in plan.links] == ["queue:4", "queue:64"]


def test_nodes_workers_and_the_default_node(tmp_path: Path) -> None:
    plan = build_plan(load_toml(write(tmp_path, """
        module_servers = ["tcp://127.0.0.1:7300"]
        [nodes.a]
        workers = 2
        [nodes.b]
        address = "tcp://10.0.0.7:7100"
        [modules.src]
        class = "parts_cfg:Src"
        node = "b"
        period = 0
        restart = "last-state"
        [modules.sink]
        class = "parts_cfg:Sink"
        group = "g"
    """)))
    assert plan.nodes == {"a": NodeSpec("a", None, 2), "b": NodeSpec("b", "tcp://10.0.0.7:7100")}
    assert plan.modules["src"].node == "b"
    assert plan.modules["src"].period == 0
    assert plan.modules["src"].restart == "last-state"
    assert plan.modules["sink"].node == "a"          # no node: the first declared one
    assert plan.modules["sink"].group == "g"
    assert plan.code.module_servers == ("tcp://127.0.0.1:7300",)
    local = build_plan(load_toml(write(tmp_path, "workers = 3\n" + TWO, "w.toml")))
    assert local.nodes == {"local": NodeSpec("local", None, 3)}


FILE_MACROS = """
    name = "nested"
    [nodes.a]
    [nodes.b]

    [macros.pair]
    modules = { a = { class = "parts_cfg:Sink", node = "a" }, b = { class = "parts_cfg:Sink" } }
    links = [ { from = "a.y", to = "b.x" } ]
    exports = { in = "a.x", out = "b.y" }

    [macros.outer]
    modules = { first = { macro = "pair" }, last = { class = "parts_cfg:Sink", group = "g" } }
    exports = { in = "first.in", out = "last.y" }
    [[macros.outer.links]]
    from = "first.out"
    to = "last.x"
    policy = "queue:8"

    [modules.src]
    class = "parts_cfg:Src"
    [modules.m]
    macro = "outer"
    node = "b"
    [modules.sink]
    class = "parts_cfg:Sink"

    [[links]]
    from = "src.out"
    to = "m.in"
    [[links]]
    from = "m.out"
    to = "sink.x"
"""


def test_file_macros_expand_in_place_and_links_resolve_through_exports(tmp_path: Path) -> None:
    plan = build_plan(load_toml(write(tmp_path, FILE_MACROS)))
    assert list(plan.modules) == ["src", "m/first/a", "m/first/b", "m/last", "sink"]
    assert plan.macros == {"m": "[macros.outer]", "m/first": "[macros.pair]"}
    assert {link.key: str(link.policy) for link in plan.links} == {
        "m/first/a.y->m/first/b.x": "latest",
        "m/first/b.y->m/last.x": "queue:8",
        "src.out->m/first/a.x": "latest",
        "m/last.y->sink.x": "latest",
    }


def test_macro_children_inherit_node_and_group_unless_they_set_their_own(tmp_path: Path) -> None:
    modules = build_plan(load_toml(write(tmp_path, FILE_MACROS))).modules
    assert modules["m/first/a"].node == "a"          # its own
    assert modules["m/first/b"].node == "b"          # from the macro instance m
    assert modules["m/last"].node == "b"
    assert modules["src"].node == "a"
    # a group named inside a macro is scoped by the macro instance
    assert modules["m/last"].group == "m/g"
    assert modules["m/first/a"].group is None


def test_python_macro_subclasses_expand_like_file_macros() -> None:
    import parts_cfg

    system = (System("py").add("src", "parts_cfg:Src").add("f", parts_cfg.Twice, group="w")
              .add("sink", parts_cfg.Sink).link("src.out", "f.x").link("f.y", "sink.x"))
    assert system.check() == []
    plan = system.plan()
    assert list(plan.modules) == ["src", "f/first/lp", "f/first/gain", "f/first/tail",
                                  "f/second/lp", "f/second/gain", "f/second/tail", "sink"]
    gain = plan.modules["f/second/gain"]
    assert (gain.cls, gain.state, gain.period) == (parts_cfg.Sink, {"seen": 2}, 0.01)
    keys = {link.key: str(link.policy) for link in plan.links}
    assert keys["f/first/gain.y->f/first/tail.x"] == "queue:8"
    assert keys["f/first/tail.y->f/second/lp.x"] == "latest"
    assert keys["src.out->f/first/lp.x"] == "latest"
    assert keys["f/second/tail.y->sink.x"] == "latest"
    assert len(keys) == 7
    # a group given to a macro instance is inherited by all its modules
    assert {m.group for name, m in plan.modules.items() if name.startswith("f/")} == {"w"}
    assert plan.modules["src"].group is None


def test_a_macro_instance_sets_the_state_of_its_modules() -> None:
    import sample_modules as sm

    system = (System("two").add("left", sm.Outer, state={"chain/b": {"gain": 5.0}})
              .add("right", sm.Outer, state={"tail": {"gain": 7.0, "setups": 1}}))
    assert system.check() == []
    state = {name: module.state for name, module in system.plan().modules.items()}
    assert state["left/chain/b"] == {"gain": 5.0}          # over the macro's own 3.0
    assert state["right/chain/b"] == {"gain": 3.0}         # each instance its own
    assert state["right/tail"] == {"gain": 7.0, "setups": 1}
    assert state["left/tail"] == state["left/chain/a"] == {}


def test_an_integer_for_a_float_state_field_becomes_a_float() -> None:
    import sample_modules as sm

    state = System("w").add("s", sm.Scale, state={"gain": 4, "setups": 1}).plan().modules["s"].state
    assert state == {"gain": 4.0, "setups": 1}
    assert type(state["gain"]) is float and type(state["setups"]) is int


def test_whole_numbers_in_a_float_list_or_table_field_become_floats() -> None:
    from pb3a import Module

    class Limited(Module):
        limits = [-1.0, 1.0]
        gains = {"kp": 1.0, "steps": 3}
        counts = [1, 2]

    state = System("w").add("m", Limited, state={
        "limits": [-2, 2], "gains": {"kp": 4, "steps": 5}, "counts": [3, 4]}
    ).plan().modules["m"].state
    assert state == {"limits": [-2.0, 2.0], "gains": {"kp": 4.0, "steps": 5},
                     "counts": [3, 4]}
    assert [type(v) for v in state["limits"]] == [float, float]
    assert type(state["gains"]["kp"]) is float and type(state["gains"]["steps"]) is int
    assert [type(v) for v in state["counts"]] == [int, int]


def test_a_macro_instance_naming_a_module_it_lacks_or_bad_state_is_reported() -> None:
    import sample_modules as sm

    problems = (System("bad").add("m", sm.Outer, state={"chain/c": {"gain": 1.0},
                                                         "tail": {"gian": 1.0},
                                                         "chain": {"gain": 1.0}}).check())
    assert len(problems) == 3
    only(problems, "[modules.m]: state names 'chain/c', which is not a module of macro",
         "its modules: a, b")
    only(problems, "[modules.m]: state names 'chain', which is not a module of macro",
         "its modules: tail", "'macro/module'")
    only(problems, "[modules.m]: state of 'tail': ", "has no state 'gian' (did you mean 'gain'?)")


def test_macro_subclasses_own_their_tables_and_may_be_given_as_macro() -> None:
    import parts_cfg

    class Wider(parts_cfg.Filter):
        pass

    Wider.modules["extra"] = parts_cfg.Sink
    assert "extra" not in parts_cfg.Filter.modules
    plan = System("w").add("a", "parts_cfg:Src").add("f", Wider).link("a.out", "f.x").plan()
    assert "f/extra" in plan.modules

    class Holder(parts_cfg.Macro):
        modules = {"inner": {"macro": parts_cfg.Filter}}
        exports = {"x": "inner.x"}

    held = System("k").add("a", "parts_cfg:Src").add("h", Holder).link("a.out", "h.x").plan()
    assert held.links[-1].key == "a.out->h/inner/lp.x"


def test_a_python_macro_can_be_the_class_of_a_toml_entry(tmp_path: Path) -> None:
    plan = build_plan(load_toml(write(tmp_path, """
        [modules.src]
        class = "parts_cfg:Src"
        [modules.f]
        class = "parts_cfg:Filter"
        [[links]]
        from = "src.out"
        to = "f.x"
    """)))
    assert list(plan.modules) == ["src", "f/lp", "f/gain", "f/tail"]
    assert plan.links[-1].key == "src.out->f/lp.x"


def test_the_system_builder_chains_and_refuses_duplicate_names() -> None:
    system = System("demo")
    assert system.node("a", workers=2).add("t", Ticker, node="a") is system
    with pytest.raises(ValueError, match="already has a module 't'"):
        system.add("t", Scale)
    with pytest.raises(ValueError, match="already has a node 'a'"):
        system.node("a")
    system.add("s", "examples.pipeline:Scale", node="a", state={"gain": 4.0},
               restart="fresh", group="g").link("t.out", "s.x", policy="queue:2")
    plan = system.plan()
    assert plan.modules["s"].state == {"gain": 4.0}
    assert plan.modules["s"].restart == "fresh"
    assert plan.links[0].policy == Policy("queue", 2)


def test_to_dot_draws_nodes_modules_ports_and_links() -> None:
    dot = (System("drawn").node("a").node("b", address="tcp://10.0.0.7:7100")
           .add("tick", Ticker, node="a").add("scale", Scale, node="b")
           .add("fast", FastScale, node="b")
           .link("tick.out", "scale.x", policy="queue:64").link("scale.y", "fast.x").to_dot())
    assert dot.startswith('digraph "drawn" {')
    assert 'subgraph "cluster_a"' in dot
    assert 'subgraph "cluster_b"' in dot
    assert "tcp://10.0.0.7:7100" in dot
    assert '"scale" [label="{{<i_x> x}|scale\\nScale|{<o_y> y}}"];' in dot
    assert '"tick":"o_out" -> "scale":"i_x" [label="queue:64"];' in dot
    assert '"scale":"o_y" -> "fast":"i_x";' in dot           # default policy: no label


def clusters_of(dot: str) -> tuple[dict[str, list[str]], dict[str, str]]:
    """Each module the DOT text draws, with the clusters it is in (outermost first), and
    each cluster's label."""
    inside: list[str] = []
    modules: dict[str, list[str]] = {}
    labels: dict[str, str] = {}
    for line in dot.splitlines():
        line = line.strip()
        if opened := re.fullmatch(r'subgraph "(.+)" \{', line):
            inside.append(opened[1])
        elif line == "}" and inside:
            inside.pop()
        elif (label := re.fullmatch(r'label="(.*)";', line)) and inside:
            labels[inside[-1]] = label[1]
        elif module := re.match(r'"([^"]+)" \[label=', line):
            modules[module[1]] = list(inside)
    return modules, labels


def test_to_dot_nests_macros_in_their_node_and_draws_a_macro_on_two_nodes_on_each() -> None:
    import sample_modules as sm

    class Brain(Macro):
        """A nested macro (Outer holds Chain), a module of its own, and one on node b."""

        modules = {"sensor": Scale, "arm": sm.Outer, "far": {"class": Scale, "node": "b"}}
        links = [("sensor.y", "arm.x"), ("arm.y", "far.x")]
        exports = {"x": "sensor.x", "y": "far.y"}

    dot = (System("robot").node("a").node("b").add("tick", Ticker, node="a")
           .add("brain", Brain, node="a").add("sink", Scale, node="b")
           .link("tick.out", "brain.x").link("brain.y", "sink.x").to_dot())
    modules, labels = clusters_of(dot)
    a, b = "cluster_a", "cluster_b"
    brain, arm, chain = f"{a}/brain", f"{a}/brain/arm", f"{a}/brain/arm/chain"
    assert modules == {"tick": [a], "brain/sensor": [a, brain],
                       "brain/arm/tail": [a, brain, arm],
                       "brain/arm/chain/a": [a, brain, arm, chain],
                       "brain/arm/chain/b": [a, brain, arm, chain],
                       "sink": [b], "brain/far": [b, f"{b}/brain"]}
    assert labels[arm] == "brain/arm\\lOuter\\l"
    assert labels[chain] == "brain/arm/chain\\lChain\\l"
    # the macro's part on each node, labelled alike, each naming where the rest runs
    assert labels[brain] == "brain\\lBrain\\l(part: the rest on node b)\\l"
    assert labels[f"{b}/brain"] == "brain\\lBrain\\l(part: the rest on node a)\\l"
    assert '"brain/arm/tail":"o_y" -> "brain/far":"i_x";' in dot
    if shutil.which("dot"):
        drawn = subprocess.run(["dot", "-Tsvg"], input=dot, text=True, capture_output=True,
                               timeout=60, check=False)
        assert drawn.returncode == 0 and not drawn.stderr, drawn.stderr
        drawn_clusters = re.findall(r'class="cluster">\s*<title>(.+?)</title>', drawn.stdout)
        assert sorted(drawn_clusters) == sorted(labels)         # all six, none lost


# -- every problem, with its place and its fix --------------------------------
def test_unknown_class_import_error_and_not_a_module(tmp_path: Path) -> None:
    problems = problems_of(tmp_path, """
        [modules.a]
        class = "examples.pipeline:Tickr"
        [modules.b]
        class = "no_such_pkg.mod:Thing"
        [modules.c]
        class = "parts_cfg:NotAModule"
        [modules.d]
        class = "examples.pipeline.Ticker"
    """)
    assert len(problems) == 4
    only(problems, "sys.toml [modules.a]:", "has no class 'Tickr'", "did you mean 'Ticker'")
    only(problems, "sys.toml [modules.b]:", "cannot import module 'no_such_pkg.mod'")
    only(problems, "sys.toml [modules.c]:", "not a Module or Macro subclass",
         "subclasses pb3a.Module")
    only(problems, "sys.toml [modules.d]:", "use 'module:Class'", "'examples.pipeline:Ticker'")


def test_an_env_module_of_a_node_the_system_lacks_is_named_with_the_nodes_it_has(
        tmp_path: Path) -> None:
    # env-NODE modules exist for the system's nodes only: "env-c" (no node c), or
    # "env-local" once nodes are declared, named "its modules: src, sink", none of them
    # an env module, and not what to change
    problems = problems_of(tmp_path, """
        [nodes.a]
        [nodes.b]
        [modules.src]
        class = "parts_cfg:Src"
        node = "a"
        [modules.sink]
        class = "parts_cfg:Sink"
        node = "b"
        [[links]]
        from = "env-c.cpu"
        to = "sink.x"
    """)
    only(problems, "[[links]] #1 (env-c.cpu -> sink.x):", "no module 'env-c'",
         "no node 'c'", "env-NODE", "env-a, env-b")
    problems = problems_of(tmp_path, TWO + """
        [[links]]
        from = "env-a.cpu"
        to = "sink.x"
    """)
    only(problems, "[[links]] #1 (env-a.cpu -> sink.x):", "no node 'a'", "env-local")


def test_a_declared_env_module_runs_on_its_own_node(tmp_path: Path) -> None:
    """``env-b`` declared to set its period, with no node, ran on the first node and
    gave that node's readings under node b's name."""
    text = """
        [nodes.a]
        [nodes.b]
        [modules.env-b]
        class = "pb3a:Environment"
        period = 0.2
        {node}
        [modules.sink]
        class = "parts_cfg:Sink"
        node = "a"
        [[links]]
        from = "env-b.cpu"
        to = "sink.x"
    """
    plan = build_plan(load_toml(write(tmp_path, text.format(node=""))))
    assert (plan.modules["env-b"].node, plan.modules["env-b"].period) == ("b", 0.2)
    assert problems_of(tmp_path, text.format(node='node = "a"')) == [
        "sys.toml [modules.env-b]: env-b is node b's env module, and an env module measures "
        "the node it runs on, but it is placed on node 'a': leave 'node' out (it runs on b), "
        "or read env-a for node a's readings"]


def test_unknown_ports_modules_and_malformed_endpoints(tmp_path: Path) -> None:
    problems = problems_of(tmp_path, TWO + """
        [[links]]
        from = "src.outt"
        to = "sink.x"
        [[links]]
        from = "snk.y"
        to = "sink"
        [[links]]
        from = "src.out.x"
    """)
    assert len(problems) == 5
    only(problems, "sys.toml [[links]] #1 (src.outt -> sink.x):", "module 'src' (parts_cfg:Src)",
         "has no port 'outt'", "did you mean 'out'", "its ports: out (output)")
    only(problems, "[[links]] #2 (snk.y -> sink):", "has no module 'snk'",
         "did you mean 'sink'", "its modules: src, sink")
    only(problems, "[[links]] #2 (snk.y -> sink):", "'to' must be \"module.port\"")
    only(problems, "[[links]] #3 (src.out.x -> ?):", "'from' must be \"module.port\"")
    only(problems, "[[links]] #3 (src.out.x -> ?):", "'to' is missing")


def test_wrong_direction(tmp_path: Path) -> None:
    problems = problems_of(tmp_path, TWO + """
        [[links]]
        from = "sink.x"
        to = "src.out"
    """)
    assert len(problems) == 2
    only(problems, "[[links]] #1 (sink.x -> src.out):", "'from' = 'sink.x' is an input",
         "swap 'from' and 'to'")
    only(problems, "[[links]] #1 (sink.x -> src.out):", "'to' = 'src.out' is an output")


def test_an_input_fed_twice(tmp_path: Path) -> None:
    problems = problems_of(tmp_path, TWO + """
        [[links]]
        from = "src.out"
        to = "sink.x"
        [[links]]
        from = "sink.y"
        to = "sink.x"
    """)
    assert problems == [
        "sys.toml [[links]] #2 (sink.y -> sink.x): input sink.x is fed twice: it is already fed "
        "by sys.toml [[links]] #1 (src.out -> sink.x); an input takes at most one link, so "
        "remove one of them or feed another input"]


def test_a_link_with_a_bad_policy_still_counts_for_the_input_it_feeds(tmp_path: Path) -> None:
    """Its input's other problems were hidden until the policy was mended."""
    problems = problems_of(tmp_path, TWO + """
        [[links]]
        from = "src.out"
        to = "sink.x"
        policy = "queue:abc"
        [[links]]
        from = "sink.y"
        to = "sink.x"
    """)
    assert len(problems) == 2
    only(problems, "[[links]] #1 (src.out -> sink.x):", "queue:abc")
    only(problems, "[[links]] #2 (sink.y -> sink.x):", "input sink.x is fed twice")


def test_incompatible_types(tmp_path: Path) -> None:
    problems = problems_of(tmp_path, """
        [modules.w]
        class = "parts_cfg:Words"
        [modules.sink]
        class = "parts_cfg:Sink"
        [[links]]
        from = "w.out"
        to = "sink.x"
    """)
    assert len(problems) == 1
    only(problems, "[[links]] #1 (w.out -> sink.x): incompatible types", "gives str",
         "takes float", "change one port's type")


def test_unknown_node(tmp_path: Path) -> None:
    problems = problems_of(tmp_path, """
        [nodes.a]
        [nodes.b]
        [modules.src]
        class = "parts_cfg:Src"
        node = "c"
    """)
    assert problems == ["sys.toml [modules.src]: unknown node 'c'; declared nodes: a, b "
                        "(add a [nodes.c] table or use one of them)"]
    problems = problems_of(tmp_path, TWO.replace('Src"', 'Src"\nnode = "a"'))
    only(problems, "[modules.src]: unknown node 'a'", "declares no nodes", "add a [nodes.a]")


def test_a_node_named_in_another_case_is_suggested(tmp_path: Path) -> None:
    """``node = "B"`` for a declared ``b`` got no suggestion (``bb`` did)."""
    problems = problems_of(tmp_path, """
        [nodes.b]
        [modules.src]
        class = "parts_cfg:Src"
        node = "B"
    """)
    only(problems, "[modules.src]: unknown node 'B' (did you mean 'b'?)")


# Module classes with a misspelled hook, and some whose names are no hook's near miss.
HOOK_TYPOS = """
from pb3a import Input, Module, Output

class Sensor(Module):
    z = Output(float)
    period = 0.02

    def stpe(self):
        self.z.write(1.0)

class Filt(Module):
    z = Input(float)

    def on_inputs(self, port):
        pass

class Careful(Module):
    def setpu(self):
        pass

    def teardwon(self):
        pass

class Subclassed(Filt):             # its base's near miss, said of it too
    pass

class Fine(Module):
    z = Input(float)
    period = 0.1                    # (a period of its own without step() is allowed)

    def on_input(self, port):
        self._step()

    def on_inputs(self):            # on_input is defined: a helper, left alone
        pass

    def _step(self):                # private: left alone
        pass

    def stop(self):
        pass

    def reset(self):
        pass
"""


def test_a_misspelled_hook_is_named_with_the_hook_it_misses(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A class defining ``on_inputs`` (meant ``on_input``), ``stpe``, ``setpu`` or
    ``teardwon`` passed the check and ran doing nothing (0 steps, 0 events), no word
    said. Each is named now, with the hook it misses; a method whose class defines that
    hook, a private one and a name not close to a hook's are not."""
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "hook_typos", raising=False)
    (tmp_path / "hook_typos.py").write_text(HOOK_TYPOS)
    entries = "".join(f'[modules.{name.lower()}]\nclass = "hook_typos:{name}"\n'
                      for name in ("Sensor", "Filt", "Careful", "Subclassed", "Fine"))
    problems = problems_of(tmp_path, entries)
    try:
        only(problems, "[modules.sensor]: hook_typos:Sensor defines stpe(): did you mean "
             "step()? a module's hooks are setup(), step(), on_input(), teardown()")
        only(problems, "[modules.filt]: hook_typos:Filt defines on_inputs(): did you mean "
             "on_input()?")
        only(problems, "[modules.careful]:", "setpu(): did you mean setup()?")
        only(problems, "[modules.careful]:", "teardwon(): did you mean teardown()?")
        only(problems, "[modules.subclassed]: hook_typos:Subclassed defines on_inputs(): "
             "did you mean on_input()?")
        assert not [p for p in problems if "[modules.fine]" in p], problems
        assert len(problems) == 5, problems
    finally:
        sys.modules.pop("hook_typos", None)


def test_an_unknown_node_is_named_in_the_words_the_system_was_described_in() -> None:
    """A system described in Python was told to add a TOML table."""
    problems = System("py").add("src", Scale, node="zzz").check()
    only(problems, "unknown node 'zzz'", "declares no nodes", "add system.node('zzz') or leave "
         "'node' out")
    problems = System("py").node("a").add("src", Scale, node="zzz").check()
    only(problems, "unknown node 'zzz'", "declared nodes: a (add system.node('zzz') or use one "
         "of them)")


def test_a_dotted_class_reference_suggests_both_readings() -> None:
    with pytest.raises(ValueError, match=re.escape(
            "here probably 'examples:pipeline', or 'examples.pipeline:Class' if "
            "examples.pipeline is the module")):
        resolve_class("examples.pipeline")


def test_fallback_names_declared_nodes_in_order(tmp_path: Path) -> None:
    nodes = "[nodes.a]\n[nodes.b]\n[nodes.c]\n"
    plan = build_plan(load_toml(write(tmp_path, nodes + TWO.replace(
        'Src"', 'Src"\nnode = "a"\nrestart = "fresh"\nfallback = ["c", "b"]'))))
    assert plan.modules["src"].fallback == ["c", "b"] and plan.modules["sink"].fallback == []
    problems = problems_of(tmp_path, nodes + TWO.replace(
        'Src"', 'Src"\nrestart = "fresh"\nfallback = ["b", "d"]'))
    assert problems == ["sys.toml [modules.src]: fallback names unknown node 'd'; declared "
                        "nodes: a, b, c"]
    problems = problems_of(tmp_path, nodes + TWO.replace('Src"', 'Src"\nfallback = "b"'))
    assert problems == ["sys.toml [modules.src]: fallback must be a list of node names, got 'b'"]


class RestartsFresh(Module):
    """A class whose modules restart afresh unless told otherwise."""

    restart = "fresh"


class NeverRestarts(RestartsFresh):
    """A class that says its modules go with their node."""

    restart = "never"


def test_a_fallback_of_a_module_never_restarted_is_refused_naming_the_fix(
        tmp_path: Path) -> None:
    """A fallback is used only by a module restarted elsewhere when its node is lost: with
    restart "never", given or its class's, it never is (pb3a check said ok, and the module
    went with its node, its fallback named in the module_lost event). Judged on the
    policy the module runs with, its class's if the entry gives none."""
    fix = ('is used only when the module is restarted elsewhere, and {}: the module goes '
           'with its node. Give restart = "fresh" or "last-state", or remove fallback')
    nodes = "[nodes.a]\n[nodes.b]\n"
    problems = problems_of(tmp_path, nodes + TWO.replace(
        'Src"', 'Src"\nnode = "b"\nfallback = ["a"]'))
    assert problems == ['sys.toml [modules.src]: fallback = ["a"] '
                        + fix.format('restart is "never" by default')]
    problems = problems_of(tmp_path, nodes + TWO.replace(
        'Src"', 'Src"\nnode = "b"\nrestart = "never"\nfallback = ["a"]'))
    assert problems == ['sys.toml [modules.src]: fallback = ["a"] '
                        + fix.format('restart = "never" is given')]
    assert problems_of(tmp_path, nodes + TWO.replace(
        'Src"', 'Src"\nnode = "b"\nrestart = "last-state"\nfallback = ["a"]')) == []
    assert problems_of(tmp_path, nodes + TWO.replace('Src"', 'Src"\nfallback = []')) == []

    def check(cls: type[Module], **options: object) -> list[str]:
        return System("py").node("a").node("b").add("m", cls, node="b", **options).check()

    only(check(Scale, fallback=["a"]), '[modules.m]: fallback = ["a"] ',
         fix.format('restart is "never" by default'))
    assert check(RestartsFresh, fallback=["a"]) == []
    only(check(RestartsFresh, fallback=["a"], restart="never"),
         fix.format('restart = "never" is given'))
    only(check(NeverRestarts, fallback=["b", "a"]), 'fallback = ["b", "a"] ',
         fix.format('test_config:NeverRestarts has restart = "never"'))
    assert check(NeverRestarts, fallback=["a"], restart="fresh") == []


def test_bad_policy(tmp_path: Path) -> None:
    problems = problems_of(tmp_path, TWO + """
        [[links]]
        from = "src.out"
        to = "sink.x"
        policy = "queue:0"
    """)
    assert len(problems) == 1
    only(problems, "[[links]] #1 (src.out -> sink.x): bad policy 'queue:0'",
         "use 'latest', 'queue' or 'queue:N'")


def test_unknown_macro(tmp_path: Path) -> None:
    problems = problems_of(tmp_path, """
        [macros.pair]
        modules = { a = { class = "parts_cfg:Sink" } }
        [modules.m]
        macro = "piar"
    """)
    assert problems == ["sys.toml [modules.m]: unknown macro 'piar' (did you mean 'pair'?); "
                        "defined macros: pair (define [macros.piar] or fix the name)"]


def test_recursive_macros_and_export_cycles(tmp_path: Path) -> None:
    problems = problems_of(tmp_path, """
        [macros.ra]
        modules = { inner = { macro = "rb" } }
        exports = { x = "inner.x" }
        [macros.rb]
        modules = { inner = { macro = "ra" } }
        exports = { x = "inner.x" }
        [macros.self]
        modules = { me = { macro = "self" } }
        [modules.r]
        macro = "ra"
    """)
    assert len(problems) == 3
    only(problems, "sys.toml [macros.ra.exports.x]: export chain macro 'ra'.x -> macro 'rb'.x "
         "-> macro 'ra'.x is a cycle", "must lead to a port of a module")
    only(problems, "sys.toml [macros.rb.modules.inner]: recursive macro: macro 'ra' -> "
         "macro 'rb' -> macro 'ra'", "cannot contain itself")
    only(problems, "sys.toml [macros.self.modules.me]: recursive macro: macro 'self' -> "
         "macro 'self'")


def test_exports_naming_unknown_children_or_ports(tmp_path: Path) -> None:
    problems = problems_of(tmp_path, """
        [macros.f]
        modules = { a = { class = "parts_cfg:Sink" } }
        exports = { x = "a.x", y = "b.y", z = "a.q", w = "a" }
        [modules.src]
        class = "parts_cfg:Src"
        [modules.m]
        macro = "f"
        [[links]]
        from = "src.out"
        to = "m.v"
    """)
    assert len(problems) == 4
    only(problems, "[macros.f.exports.y]: macro 'f' has no module 'b'", "its modules: a")
    only(problems, "[macros.f.exports.z]: module 'a' (parts_cfg:Sink) has no port 'q'")
    only(problems, "[macros.f.exports.w]: the export must be \"module.port\"")
    only(problems, "[[links]] #1 (src.out -> m.v): macro 'm' (macro 'f') exports no port 'v'",
         "it exports: x, y, z, w", "add it to the macro's exports")


def test_bad_period_restart_and_state(tmp_path: Path) -> None:
    problems = problems_of(tmp_path, """
        [modules.a]
        class = "examples.pipeline:Scale"
        period = "fast"
        restart = "always"
        state = { gian = 2.0 }
        [modules.b]
        class = "examples.pipeline:Ticker"
        period = -1
        state = 3
        [modules.c]
        class = "parts_cfg:Custom"
        state = { anything = 1, whatever = 2 }
        [modules.d]
        class = "examples.pipeline:Ticker"
        restart = "last_state"
    """)
    assert len(problems) == 6
    only(problems, "[modules.a]: period must be a number of seconds from 0 to 1e+07", "'fast'")
    only(problems, "[modules.a]: restart must be one of 'never', 'fresh', 'last-state'",
         "'always'")
    only(problems, "[modules.d]: restart must be one of", "got 'last_state' (did you mean "
         "'last-state'?)")
    only(problems, "[modules.a]: examples.pipeline:Scale has no state 'gian'",
         "did you mean 'gain'", "its state is: gain")
    only(problems, "[modules.b]: period must be a number of seconds from 0", "got -1")
    # (a period past 1e308 s overflowed the step thread's clock: it died, "running")
    assert problems_of(tmp_path, """
        [modules.t]
        class = "examples.pipeline:Ticker"
        period = 1e308
    """) == ["sys.toml [modules.t]: period must be a number of seconds from 0 to 1e+07 (0 = "
             "as fast as possible; leave it out to keep the class's), got 1e+308"]
    only(problems, "[modules.b]: state must be a table")


def test_a_module_option_given_in_its_state_says_to_give_it_as_the_entry_s_key(
        tmp_path: Path) -> None:
    """``state = { period = 0.05 }`` got "has no state 'period'", though ``pb3a set
    ... period=`` and ``set_state(name, period=...)`` take it among a running module's
    fields: the refusal says to give it as the entry's own key, as for fixed_rate and
    restart."""
    problems = problems_of(tmp_path, """
        [modules.t]
        class = "examples.pipeline:Ticker"
        state = { period = 0.05, fixed_rate = true, restart = "fresh" }
    """)
    assert problems == [
        "sys.toml [modules.t]: period is not state: use the entry's own `period = 0.05`, "
        "beside its class (add(..., period=...) in Python); a running module's is set by "
        "pb3a set ADDR NAME period=... or set_state(NAME, period=...)",
        "sys.toml [modules.t]: fixed_rate is not state: use the entry's own `fixed_rate = "
        "true`, beside its class (add(..., fixed_rate=...) in Python)",
        "sys.toml [modules.t]: restart is not state: use the entry's own `restart = "
        "\"fresh\"`, beside its class (add(..., restart=...) in Python)"], problems


def test_a_period_may_be_numpy_s_and_an_int_no_float_can_hold_is_refused() -> None:
    """``set_state(name, period=10**400)`` (or ``add``'s) raised OverflowError from the
    check meant to refuse it, naming nothing; a period computed with numpy was refused
    as no number."""
    from pb3a.config import checks

    assert checks.period(10**400) and checks.period(-(10**400))
    # a numpy number is a number (``add(period=np.float32(0.5))`` was refused); its bool not
    assert checks.period(np.True_) and not checks.period(np.float32(0.5))
    assert System("np").add("t", Ticker, period=np.int64(2)).plan().modules["t"].period == 2.0
    with pytest.raises(ConfigError, match=r"\[modules\.t\]: period must be a number of "
                                          r"seconds .*, got 1\d{59}$"):
        System("huge").add("t", Ticker, period=10**400).plan()


def test_unknown_keys_everywhere(tmp_path: Path) -> None:
    problems = problems_of(tmp_path, """
        modulez = 1
        [nodes.a]
        adress = "tcp://x:1"
        [macros.m]
        modules = { s = { class = "parts_cfg:Sink" } }
        export = { x = "s.x" }
        [modules.src]
        class = "parts_cfg:Src"
        node = "a"
        perod = 0.1
        [modules.m]
        macro = "m"
        [[links]]
        from = "src.out"
        to = "m.x"
        polcy = "latest"
    """)
    only(problems, "sys.toml: unknown top-level key 'modulez' (did you mean 'modules'?)",
         "allowed keys: name, module_servers, nodes, modules, links, macros, workers, timeout")
    only(problems, "[nodes.a]: unknown key 'adress' (did you mean 'address'?)")
    only(problems, "[macros.m]: unknown key 'export' (did you mean 'exports'?)")
    only(problems, "[modules.src]: unknown key 'perod' (did you mean 'period'?); allowed keys: "
         "class, macro, node, period, fixed_rate, state, restart, group")
    only(problems, "[[links]] #1 (src.out -> m.x): unknown key 'polcy' (did you mean 'policy'?)")
    only(problems, "[[links]] #1 (src.out -> m.x): macro 'm' (macro 'm') exports no port 'x'")
    assert len(problems) == 6


def test_bad_instance_names_and_class_macro_choice(tmp_path: Path) -> None:
    problems = problems_of(tmp_path, """
        [macros.pair]
        modules = { a = { class = "parts_cfg:Sink" } }
        [modules."my.tick"]
        class = "parts_cfg:Src"
        [modules."a b"]
        class = "parts_cfg:Src"
        [modules."probe\\n"]
        class = "parts_cfg:Src"
        [modules.both]
        class = "parts_cfg:Src"
        macro = "pair"
        [modules.neither]
        period = 1
        [modules.m]
        macro = "pair"
        period = 1
        state = { x = 1 }
    """)
    assert len(problems) == 7
    only(problems, 'sys.toml [modules."my.tick"]: bad module instance name', "letters, digits")
    only(problems, 'sys.toml [modules."a b"]: bad module instance name')
    only(problems, 'sys.toml [modules."probe\n"]: bad module instance name')   # ("$" took it)
    only(problems, "[modules.both]: give exactly one of 'class'", "it has both")
    only(problems, "[modules.neither]: give exactly one of 'class'", "'macro' (the name of")
    only(problems, "[modules.m]: 'period' applies to modules, not to a macro")
    only(problems, "[modules.m]: a macro instance's state is a table of its modules",
         "got {'x': 1}")


def _line() -> int:
    """The line of the caller's statement (what a problem of an entry it wrote names)."""
    return sys._getframe(1).f_lineno


def test_a_problem_of_an_entry_a_program_wrote_names_its_file_and_line() -> None:
    """A system built in Python named its wrong entries as a file's (``system 'x'
    [[links]] #7 (...)``): with dozens of links, which call was it? The program's file
    and line lead each problem, as a compiler's do; the ``timeout`` of the system, which
    no entry holds, is named as before."""
    system = System("placed", timeout=-1)
    node_at = _line() + 1
    system.node("a", workers=-1)
    system.add("tick", Ticker, node="a")
    system.add("scale", Scale, period=0)
    system.link("tick.outt", "scale.x")
    tick_at, scale_at, link_at = node_at + 1, node_at + 2, node_at + 3
    problems = system.check()
    for at, label in ((node_at, "[nodes.a]: "), (tick_at, None),
                      (scale_at, "[modules.scale]: "), (link_at, "[[links]] #1 (tick.outt")):
        if label is not None:
            assert any(p.startswith(f"tests/test_config.py:{at}: system 'placed' {label}")
                       for p in problems), (at, label, problems)
    assert not any(f":{tick_at}: " in p for p in problems), problems   # (nothing wrong)
    assert any(p.startswith("system 'placed': ") and "timeout" in p for p in problems), \
        problems


def test_a_name_with_an_accent_is_refused_for_asking_ascii() -> None:
    """'ó' is a letter: "use only letters" refused 'módulo' without saying why."""
    problems, line = System("accents").add("módulo", Ticker).check(), _line()
    assert problems == [(f"tests/test_config.py:{line}: system 'accents' [modules.\"módulo\"]: bad "
                         "module instance name 'módulo': use only ASCII letters, digits, '_' "
                         "and '-' (no accents, '.', '/' or spaces)")]


def test_bad_workers_and_node_values(tmp_path: Path) -> None:
    problems = problems_of(tmp_path, """
        workers = 2
        [nodes.a]
        workers = -1
        [nodes.b]
        workers = "two"
        [nodes."c.d"]
        address = 7
    """)
    assert len(problems) == 5
    only(problems, "[nodes.a]: workers must be a whole number >= 0", "got -1")
    only(problems, "[nodes.b]: workers must be a whole number >= 0", "got 'two'")
    only(problems, '[nodes."c.d"]: bad node name')
    only(problems, '[nodes."c.d"]: address must be a string')
    only(problems, "sys.toml: top-level workers = 2 is for the default node 'local'",
         "set workers in their [nodes.NAME] tables")
    bad = problems_of(tmp_path, "workers = true\n" + TWO)
    assert bad == [("sys.toml: top-level workers must be a whole number >= 0 (0 = one process "
                    "per module, N = pack the node's modules into N processes), got True")]
    # two nodes behind one controller: the run failed, the node "already working for"
    # the launcher itself
    shared = problems_of(tmp_path, """
        [nodes.r1]
        address = "tcp://10.0.0.7:7100"
        [nodes.r2]
        address = "tcp://10.0.0.7:7100"
    """)
    only(shared, "[nodes.r2]: address 'tcp://10.0.0.7:7100' is node r1's too",
         "one node controller serves one node")


def test_a_group_cannot_span_nodes(tmp_path: Path) -> None:
    problems = problems_of(tmp_path, """
        [nodes.a]
        [nodes.b]
        [modules.src]
        class = "parts_cfg:Src"
        group = "g"
        node = "a"
        [modules.sink]
        class = "parts_cfg:Sink"
        group = "g"
        node = "b"
    """)
    assert len(problems) == 1
    only(problems, "[modules.sink]: group 'g' would span nodes 'a' (src) and 'b' (sink)",
         "give them the same node or different groups")


def test_every_problem_is_reported_at_once(tmp_path: Path) -> None:
    path = write(tmp_path, """
        [modules.tick]
        class = "examples.pipeline:Ticker"
        perod = 0.1
        [modules.scale]
        class = "examples.pipeline:Scale"
        node = "far"
        [[links]]
        from = "tick.out"
        to = "scale.z"
        policy = "lifo"
    """, "pipeline.toml")
    with pytest.raises(ConfigError) as caught:
        build_plan(load_toml(path))
    problems = caught.value.problems
    assert len(problems) == 4
    assert all(p.startswith(f"{path} [") for p in problems)
    assert problems == validate(load_toml(path))
    assert "4 problems" in str(caught.value)


def test_python_systems_and_macros_name_themselves_in_problems() -> None:
    import parts_cfg

    system = (System("demo").add("t", "examples.pipeline:Tickr").add("b", parts_cfg.BadMacro)
              .add("s", Scale, period=-2).link("t.out", "s.x"))
    problems = system.check()
    assert len(problems) == 4
    only(problems, "system 'demo' [modules.t]: module 'examples.pipeline' has no class 'Tickr'")
    only(problems, "system 'demo' [modules.s]: period must be a number of seconds from 0")
    only(problems, "macro parts_cfg:BadMacro [modules.s]: unknown key 'perod'")
    only(problems, "macro parts_cfg:BadMacro [[links]] #1 (s.y -> s.nope): module 's' "
         "(parts_cfg:Sink) has no port 'nope'")
    with pytest.raises(ConfigError) as caught:
        system.plan()
    assert caught.value.problems == problems


def test_a_file_that_is_not_toml(tmp_path: Path) -> None:
    path = write(tmp_path, "[modules.tick\nclass = 1\n", "broken.toml")
    with pytest.raises(ConfigError, match=r"broken\.toml: not valid TOML"):
        load_toml(path)


def test_structural_mistakes_in_the_file_are_reported(tmp_path: Path) -> None:
    spec = load_toml(write(tmp_path, 'modules = 3\nlinks = "a.b"\nnodes = { a = 1 }\n'))
    assert isinstance(spec, SystemSpec)
    assert spec.name == "sys"
    problems = validate(spec)
    assert len(problems) == 3
    only(problems, "sys.toml: 'modules' must be a table")
    only(problems, "sys.toml [[links]]: must be an array of tables")
    only(problems, "sys.toml [nodes.a]: must be a table")


def test_a_file_sets_the_default_timeout_of_operations(tmp_path: Path) -> None:
    plan = build_plan(load_toml(write(tmp_path, "timeout = 2.5\n" + TWO)))
    assert plan.timeout == 2.5
    assert build_plan(load_toml(write(tmp_path, TWO))).timeout is None
    for written, shown in (("0", "0"), ("-1", "-1"), ("'soon'", "'soon'"), ("true", "True"),
                           ("1e308", "1e+308")):
        assert problems_of(tmp_path, f"timeout = {written}\n" + TWO) == [
            "sys.toml: timeout must be a positive number of seconds, at most 1e+07 (how long "
            f"an operation on the running system may wait), got {shown}"]


def test_a_node_may_say_where_other_nodes_reach_it(tmp_path: Path) -> None:
    plan = build_plan(load_toml(write(tmp_path, '[nodes.a]\nadvertise = "10.0.0.5"\n' + TWO)))
    assert plan.nodes["a"].advertise == "10.0.0.5"
    for written in ("tcp://10.0.0.5", "10.0.0.5:7100", "", "two words"):
        assert problems_of(tmp_path, f'[nodes.a]\nadvertise = "{written}"\n' + TWO) == [
            f"sys.toml [nodes.a]: advertise must be the host other nodes reach this node at, "
            f"a name or an IP address such as '10.0.0.7' (no tcp://, no port), got {written!r}"]


def test_a_node_keeps_the_spare_workers_it_is_given_and_a_bad_count_is_named(
        tmp_path: Path) -> None:
    plan = build_plan(load_toml(write(tmp_path, "[nodes.a]\nspares = 0\n[nodes.b]\n" + TWO)))
    assert (plan.nodes["a"].spares, plan.nodes["b"].spares) == (0, 2)
    assert System("s").node("a", spares=5).add("x", "parts_cfg:Src", node="a").plan(
        ).nodes["a"].spares == 5
    for written in ("-1", "17", "true", '"2"', "1.5"):
        assert problems_of(tmp_path, f"[nodes.a]\nspares = {written}\n" + TWO) == [
            "sys.toml [nodes.a]: spares must be a whole number from 0 to 16 (the worker "
            "processes the node keeps booted for modules that arrive; 0 = none), got "
            f"{tomllib.loads('v = ' + written)['v']!r}"]


def test_a_description_read_by_a_program_and_filled_in_becomes_a_system() -> None:
    data = tomllib.loads(PIPELINE.read_text())
    data["modules"]["scale"]["state"] = {"gain": 5.0}      # what the program knows
    plan = System.from_dict(data, source="pipeline, filled in").plan()
    assert plan.modules["scale"].state == {"gain": 5.0}
    assert set(plan.modules) == set(System.load(PIPELINE).plan().modules)
    data["links"].append({"from": "nowhere.out", "to": "scale.x"})
    problems = System.from_dict(data, source="pipeline, filled in").check()
    assert any(p.startswith("pipeline, filled in") and "nowhere" in p for p in problems), problems


def test_a_plan_names_the_modules_its_classes_live_in_for_nodes_to_preload() -> None:
    plan = System.load(PIPELINE).plan()
    assert plan.code.preload == ("examples.pipeline",)
    macro_plan = System("m").add("twice", "parts_cfg:Twice").plan()
    assert macro_plan.code.preload == ("parts_cfg",)


def test_displays_are_configuration_and_a_bad_table_is_reported() -> None:
    from pb3a import Module, System
    from pb3a.model.displays import Display, declared_displays

    class Shown(Module):
        level = 0.5
        displays = {"level": ("gauge", 0, 1)}

    class Garbled(Module):
        level = 0.5
        displays = {"level": ("gauge", 1, 0), "other": "picture"}

    assert Shown.state_names() == ["level"]
    assert declared_displays(Shown) == {"level": Display("gauge", 0.0, 1.0)}
    system = System("shown")
    system.add("good", Shown)
    system.add("bad", Garbled)
    problems = system.check()
    assert len(problems) == 1 and "[modules.bad]" in problems[0], problems
    assert "displays['level'] = ('gauge', 1, 0)" in problems[0]
    assert "displays['other'] = 'picture'" in problems[0]
    assert 'use "image", "plot" or ("gauge", MIN, MAX) with MIN < MAX' in problems[0]


def test_nested_macro_instances_each_set_state_and_the_outer_wins_key_by_key(
        tmp_path: Path) -> None:
    """The outer instance's entry replaced the inner one's for the module: the inner's
    other keys were gone, and a mistake in them was never said."""
    problems = problems_of(tmp_path, """
        [macros.inner.modules.a]
        class = "parts_cfg:Src"
        [macros.outer.modules.inner]
        macro = "inner"
        state = { a = { value = 2.0, valu = 1.0 } }
        [modules.o]
        macro = "outer"
        state = { "inner/a" = { value = 3.0 } }
    """)
    only(problems, "[macros.outer.modules.inner]: state of 'a'", "no state 'valu'")
    plan = build_plan(load_toml(write(tmp_path, """
        [macros.inner.modules.a]
        class = "parts_cfg:Sink"
        [macros.outer.modules.inner]
        macro = "inner"
        state = { a = { seen = 2 } }
        [modules.o]
        macro = "outer"
        state = { "inner/a" = { seen = 3 } }
        [modules.p]
        macro = "outer"
    """)))
    assert plan.modules["o/inner/a"].state == {"seen": 3}
    assert plan.modules["p/inner/a"].state == {"seen": 2}


def test_a_class_that_does_not_resolve_hides_none_of_the_entry_s_other_mistakes(
        tmp_path: Path) -> None:
    problems = problems_of(tmp_path, """
        [modules.t]
        class = "parts_cfg:Srcc"
        period = -1
        restart = "sometimes"
        state = "value"
    """)
    assert len(problems) == 4, problems
    only(problems, "[modules.t]: module 'parts_cfg' has no class 'Srcc'")
    only(problems, "[modules.t]: period must be")
    only(problems, "[modules.t]: restart")
    only(problems, "[modules.t]: state must be a table")


def test_addresses_must_be_tcp_host_port_and_a_remote_node_s_cpus_are_its_own(
        tmp_path: Path) -> None:
    """A node address or module server without tcp:// passed pb3a check, and the launch
    (or the check itself, for a server) ended in a ZeroMQ traceback; a remote node's
    cpus were checked against this machine's."""
    problems = problems_of(tmp_path, """
        module_servers = ["localhost:7300", "tcp://127.0.0.1:7300"]
        [nodes.a]
        address = "127.0.0.1:7199"
        [nodes.b]
        address = "tcp://machine-b:7100"
        cpus = [4, 5, 6, 7, 64]
        [nodes.c]
        address = "tcp://machine-c:99999"
        [nodes.d]
        cpus = [4096]
    """ + TWO)
    assert len(problems) == 4, problems
    only(problems, "each of module_servers must be a string tcp://HOST:PORT", "'localhost:7300'")
    only(problems, "[nodes.a]: address must be a string tcp://HOST:PORT", "'127.0.0.1:7199'")
    only(problems, "[nodes.c]: address 'tcp://machine-c:99999': its port 99999 is out of "
                   "range (1-65535)")
    only(problems, "[nodes.d]: cpus must be a non-empty list of CPU numbers among this "
                   "machine's")
    wrong = System("s", module_servers="tcp://127.0.0.1:7300").check()  # not 't', 'c' ...
    assert len(wrong) == 1 and "module_servers must be a list of addresses" in wrong[0]


def test_a_file_that_is_not_utf8_is_a_config_error(tmp_path: Path) -> None:
    path = tmp_path / "latin.toml"
    path.write_bytes(b'name = "caf\xe9"\n')
    with pytest.raises(ConfigError, match=r"latin.toml: not UTF-8 text \(byte 11\)"):
        System.load(path)


def test_a_file_beginning_with_a_byte_order_mark_is_read(tmp_path: Path) -> None:
    """Windows editors write one: it was "not valid TOML: Invalid statement (at line 1,
    column 1)"; a byte past it that is not UTF-8 is still named where it is in the file."""
    path = tmp_path / "marked.toml"
    path.write_bytes(b'\xef\xbb\xbfname = "marked"\n' + TWO.encode())
    system = System.load(path)
    assert system.name == "marked" and system.check() == []
    path.write_bytes(b'\xef\xbb\xbfname = "caf\xe9"\n')
    with pytest.raises(ConfigError, match=r"marked.toml: not UTF-8 text \(byte 14\)"):
        System.load(path)


def test_an_export_name_must_be_a_port_s_name(tmp_path: Path) -> None:
    """'in-put' passed, and a link to it was then refused as not "module.port"."""
    problems = problems_of(tmp_path, """
        [macros.m]
        modules = { s = { class = "parts_cfg:Sink" } }
        exports = { in-put = "s.x" }
    """)
    only(problems, "export name 'in-put' names a port: use letters, digits and '_' only")


def test_a_link_to_a_path_inside_a_macro_says_to_link_through_its_exports(
        tmp_path: Path) -> None:
    """``f/child.y``, as a running system names the module, was refused as not
    "module.port", which did not say how to reach it: through the macro's exports."""
    problems = problems_of(tmp_path, """
        [macros.filter]
        modules = { child = { class = "parts_cfg:Sink" }, other = { class = "parts_cfg:Sink" } }
        exports = { in = "child.x", out = "other.y" }
        [modules.src]
        class = "parts_cfg:Src"
        [modules.f]
        macro = "filter"
        [modules.sink]
        class = "parts_cfg:Sink"
        [modules.sink2]
        class = "parts_cfg:Sink"
        [[links]]
        from = "f/child.y"
        to = "sink.x"
        [[links]]
        from = "f/other.y"
        to = "sink2.x"
        [[links]]
        from = "src.out"
        to = "f/child.x"
    """)
    assert problems == [
        "sys.toml [[links]] #1 (f/child.y -> sink.x): 'from' = 'f/child.y' is a port inside "
        "macro instance 'f', which a link reaches only through the macro's exports: add "
        "y = \"child.y\" to the exports of macro 'filter' and link \"f.y\"",
        "sys.toml [[links]] #2 (f/other.y -> sink2.x): 'from' = 'f/other.y' is a port inside "
        "macro instance 'f', which a link reaches only through the macro's exports: macro "
        "'filter' exports it as 'out', so link \"f.out\"",
        "sys.toml [[links]] #3 (src.out -> f/child.x): 'to' = 'f/child.x' is a port inside "
        "macro instance 'f', which a link reaches only through the macro's exports: macro "
        "'filter' exports it as 'in', so link \"f.in\""]


class NeedsGain(Ticker):
    def __init__(self, gain: float, *, limit: int) -> None:
        super().__init__()
        self.gain, self.limit = gain, limit


class TakesDefaults(Ticker):
    def __init__(self, gain: float = 1.0, *rest: object, **options: object) -> None:
        super().__init__()
        self.gain = gain


def test_a_class_that_cannot_be_made_with_no_arguments_is_refused_by_the_check() -> None:
    """Every module is made with none: its launch failed in the worker, naming only the
    worker ("worker 'local-p0': TypeError: ... missing 1 required positional argument")."""
    system, line = System("made").add("needs", NeedsGain).add("takes", TakesDefaults), _line()
    assert system.check() == [
        f"tests/test_config.py:{line}: system 'made' [modules.needs]: {__name__}:NeedsGain "
        "cannot be made with no arguments, as every module is: its __init__ needs gain, "
        "limit; give them a default, or make them state (a class attribute, which the "
        "entry's state sets)"]


def test_a_description_from_tables_is_imported_from_its_script_s_directories() -> None:
    """Its default source, "a description", was taken for a file in the current
    directory, which every process then imported from first: the directories it is
    imported from are its script's, as a system's built in Python."""
    plan = System.from_dict({"name": "d", "modules": {
        "t": {"class": "examples.pipeline:Ticker"}}}).plan()
    assert plan.code.paths == launcher_paths()


KINDS = '''
import numpy as np
from pb3a.model.module import Module


class Kinds(Module):
    gain = 2.0
    count = 0
    on = True
    label = "a"
    weights = np.zeros(4)
    limits = (-1.0, 1.0)

    def __init__(self):
        super().__init__()
        self.kp = 1.0                   # state only an instance holds
        self._pid = Kinds.__new__(Kinds)
        self._pid.ki = 2.0              # (another object's)
        self.speed = 1.0                # (through a property: no field)

    @property
    def speed(self):
        return self._speed

    @speed.setter
    def speed(self, value):
        self._speed = value
'''


@pytest.fixture
def kinds(tmp_path: Path) -> Iterator[None]:
    (tmp_path / "parts_kinds.py").write_text(KINDS)
    sys.path.insert(0, str(tmp_path))
    yield
    sys.path.remove(str(tmp_path))
    sys.modules.pop("parts_kinds", None)


def test_a_state_value_of_another_kind_than_the_class_declares_is_refused_by_name(
        tmp_path: Path, kinds: None) -> None:
    """``gain = "3.0"`` passed every check; the module then failed at every step, and
    refused the number that would mend it, judged by the text it held."""
    problems = problems_of(tmp_path, """
        [modules.m]
        class = "parts_kinds:Kinds"
        state = { gain = "3.0", count = "zero", on = 1, label = 5, weights = [1, "x"] }
    """)
    assert len(problems) == 5, problems
    only(problems, "[modules.m]: state 'gain' takes a number (parts_kinds:Kinds declares it "
                   "2.0), got '3.0'")
    only(problems, "state 'count' takes a number", "got 'zero'")
    only(problems, "state 'on' takes true or false", "got 1")
    only(problems, "state 'label' takes text", "got 5")
    only(problems, "state 'weights' takes a nested list of float64 values")
    # what fits is taken: a whole number for a float, any shape of numbers for an array,
    # a list for a tuple, and what the class's __init__ sets; a typo there is still named
    assert problems_of(tmp_path, """
        [modules.m]
        class = "parts_kinds:Kinds"
        state = { gain = 3, weights = [[1, 2], [3, 4.5]], limits = [0, 2], kp = 2.5 }
    """) == []
    only(problems_of(tmp_path, """
        [modules.m]
        class = "parts_kinds:Kinds"
        state = { kpp = 2.5 }
    """), "has no state 'kpp' (did you mean 'kp'?)", "its state is: gain, count, on, label, "
          "weights, limits, kp")
    # what __init__ sets on another object, or through a property, is no field of it
    assert len(problems_of(tmp_path, """
        [modules.m]
        class = "parts_kinds:Kinds"
        state = { ki = 1.0, speed = 2.0 }
    """)) == 2
    # the same from a program, before anything runs
    system = System("s")
    system.add("m", "parts_kinds:Kinds", state={"gain": "3.0"})
    assert any("state 'gain' takes a number" in problem for problem in system.check())


def test_a_driver_s_state_is_checked_as_any_module_s(tmp_path: Path) -> None:
    """``Driver`` overrides ``set_state`` (to refuse a resource that is not an address),
    and the check took every class with its own to know its fields alone: a driver's
    ``timout = 2.0``, or a ``RobotDriver``'s ``silent_after = "5"``, passed ``pb3a check``
    and failed only at launch, with a KeyError. Both mark theirs ``reflective``."""
    problems = problems_of(tmp_path, """
        [modules.robot]
        class = "agents.robot_driver:RobotDriver"
        state = { resorce = "tcp://127.0.0.1:7400", timout = 2.0, silent_after = "5" }
        [modules.reader]
        class = "sample_modules:DeviceReader"
        state = { asked = "x" }
    """)
    assert len(problems) == 4, problems
    only(problems, "[modules.robot]: agents.robot_driver:RobotDriver has no state 'resorce' "
                   "(did you mean 'resource'?)")
    only(problems, "[modules.robot]", "has no state 'timout' (did you mean 'timeout'?)")
    only(problems, "[modules.robot]: state 'silent_after' takes a number")
    only(problems, "[modules.reader]: state 'asked' takes a number")
    system = System("s")                    # the same from a program, before anything runs
    system.add("m", "sample_modules:DeviceReader", state={"timout": 2.0})
    assert any("has no state 'timout'" in problem for problem in system.check())
    # a new driver's state given as JSON is made its fields' types, as a module's
    assert class_state(RobotDriver)["silent_after"] == 5 and class_state(DeviceReader)
    assert class_state(resolve_class("parts_cfg:Custom")) == {}     # (its own set_state)


def test_what_a_robot_driver_refuses_of_its_state_is_a_problem(tmp_path: Path) -> None:
    """``RobotDriver``'s ``set_state`` refused a ``silent_after`` of 0 (a silent robot was
    never said), and ``pb3a check`` passed it: the launch failed on it. The driver says
    so in ``state_problems``, which the check, ``add`` and its ``set_state`` ask."""
    problems = problems_of(tmp_path, """
        [modules.robot]
        class = "agents.robot_driver:RobotDriver"
        state = { silent_after = 0, timeout = 2 }
        [modules.fine]
        class = "agents.robot_driver:RobotDriver"
        state = { silent_after = 3 }
    """)
    assert len(problems) == 1, problems
    only(problems, "[modules.robot]: RobotDriver's silent_after must be a whole number of "
                   "requests, 1 or more, got 0")
    added = System("s").add("m", RobotDriver, state={"silent_after": -2})
    assert any("silent_after must be a whole number" in p for p in added.check())


class NeedsAPort(Module):
    """A placeholder default its hook refuses: each entry must give its own."""

    port = 0

    @classmethod
    def state_problems(cls, state):
        if "port" in state and not 1 <= state["port"] <= 65535:
            return [f"NeedsAPort's port must be 1-65535, got {state['port']}"]
        return []


def test_a_default_every_entry_overrides_is_not_refused_and_one_left_is() -> None:
    """The class's defaults were judged alone: a placeholder its hook refuses (a port
    that each entry must give) was refused however the entry set it, and the class
    could never be launched. They are judged against each module's whole state, its
    macro instance's overrides included."""

    class Pair(Macro):
        modules = {"m": NeedsAPort}

    assert System("given").add("m", NeedsAPort, state={"port": 7400}).check() == []
    system = System("overridden").add("p", Pair, state={"m": {"port": 7400}})
    assert system.check() == []
    problems = System("left").add("m", NeedsAPort).check()
    assert any("NeedsAPort's port must be 1-65535, got 0 (its class's own default)" in p
               for p in problems), problems


def test_a_rule_relating_fields_is_judged_across_a_macro_s_entry_and_an_override(
        tmp_path: Path) -> None:
    """A junction controller's maximum green below its minimum, the minimum given by the
    macro's entry and the maximum by an instance's override, is a problem of that
    instance; the same maximum above it is not. (Judged apart, each table passed, the
    rule having only one of its fields; judged against the class's default for the
    other, an override was refused for a value the entry had changed.)"""
    problems = problems_of(tmp_path, """
        [macros.junction.modules.control]
        class = "agents.traffic.gap_out:GapOut"
        state = { min_green_s = 20.0 }
        [modules.north]
        macro = "junction"
        state = { control = { max_green_s = 15.0 } }
        [modules.south]
        macro = "junction"
        state = { control = { max_green_s = 30.0 } }
    """)
    assert problems == ["sys.toml [modules.north]: state of 'control': GapOut's max_green_s "
                        "(15.0) must be at least min_green_s (20.0)"], problems


def test_a_rule_a_macro_s_entry_breaks_is_said_of_it_not_of_each_instance(
        tmp_path: Path) -> None:
    """A rule the macro's entry breaks by itself was pinned on every instance that
    overrode another field of the module (and said of the entry too: three problems for
    one), and an outer macro's override that broke it on each instance of the outer."""
    problems = problems_of(tmp_path, """
        [macros.junction.modules.control]
        class = "agents.traffic.gap_out:GapOut"
        state = { min_green_s = 50.0 }
        [modules.north]
        macro = "junction"
        state = { control = { passage_s = 3.0 } }
        [modules.south]
        macro = "junction"
        state = { control = { passage_s = 2.0 } }
    """)
    assert problems == ["sys.toml [macros.junction.modules.control]: GapOut's max_green_s "
                        "(40.0) must be at least min_green_s (50.0)"], problems
    problems = problems_of(tmp_path, """
        [macros.junction.modules.control]
        class = "agents.traffic.gap_out:GapOut"
        state = { min_green_s = 20.0 }
        [macros.corridor.modules.a]
        macro = "junction"
        state = { control = { max_green_s = 15.0 } }
        [modules.c1]
        macro = "corridor"
        state = { "a/control" = { passage_s = 1.0 } }
        [modules.c2]
        macro = "corridor"
    """)
    assert problems == ["sys.toml [macros.corridor.modules.a]: state of 'control': GapOut's "
                        "max_green_s (15.0) must be at least min_green_s (20.0)"], problems


ASKED: list[dict] = []       # each state Asked's hook was given


class Asked(Module):
    """A class whose hook notes each state it is asked about, refusing none."""

    rate = 1.0
    ceiling = 5.0

    @classmethod
    def state_problems(cls, state):
        ASKED.append(dict(state))
        return []


def test_the_checks_ask_a_class_once_per_table_and_once_of_the_whole_state() -> None:
    """The checks asked a class's ``state_problems`` four times for a module's entry (its
    state twice, its defaults alone, the whole state) and as often for a macro's module
    an instance overrides: a hook that reads files or judges a large table did it all
    again for each. Each table is judged once, the whole state once, and the defaults
    alone only when the whole state is refused something (to say which are its own)."""

    class Pair(Macro):
        modules = {"m": Asked}

    ASKED.clear()
    assert System("entry").add("m", Asked, state={"rate": 2.0}).check() == []
    assert ASKED == [{"rate": 2.0}, {"rate": 2.0, "ceiling": 5.0}]
    ASKED.clear()
    assert System("override").add("p", Pair, state={"m": {"rate": 3.0}}).check() == []
    assert ASKED == [{"rate": 3.0}, {"rate": 3.0, "ceiling": 5.0}]


def test_a_rule_relating_fields_is_judged_for_a_class_with_a_set_state_of_its_own() -> None:
    """A user's subclass of a library controller whose ``set_state`` logs each edit and
    calls the base's (not marked ``reflective``) passed the check with a minimum green
    above its class's maximum, and its launch failed: such a class keeps ``Module``'s
    ``get_state``, so its defaults are its state, judged with the entry's."""
    from agents.traffic.gap_out import GapOut

    class LoggedGapOut(GapOut):
        edits = 0

        def set_state(self, state: dict) -> None:
            super().set_state(state)
            self.edits += 1

    problems = System("sub").add("ctl", LoggedGapOut, state={"min_green_s": 50.0}).check()
    assert any("LoggedGapOut's max_green_s (40.0) must be at least min_green_s (50.0)" in p
               for p in problems), problems


def test_a_state_problems_that_fails_is_a_problem_naming_its_class() -> None:
    """A class's ``state_problems`` is the user's code: one that raises, or answers with
    a text rather than a list, is said as a problem of the class, not a failed check."""

    class Raising(Module):
        rate = 1.0

        @classmethod
        def state_problems(cls, state):
            return [f"rate {state['rate'] / 0}"]

    class Texting(Module):
        rate = 1.0

        @classmethod
        def state_problems(cls, state):
            return "no"

    problems = System("s").add("r", Raising).add("t", Texting, state={"rate": 2.0}).check()
    assert any("Raising.state_problems raised ZeroDivisionError: float division by zero "
               "(given {'rate': 1.0})" in p for p in problems), problems
    assert any("Texting.state_problems must return a list of texts, one per value it "
               "refuses ([] for none), got 'no'" in p for p in problems), problems


def test_a_state_problems_that_is_no_classmethod_or_misspelt_is_named() -> None:
    """``state_problems`` is asked of the class: a plain method failed at each asking,
    said only as "raised TypeError: ... missing 1 required positional argument", and one
    misspelt (``state_problem``) was never asked, no word said. Each is named now, with
    the fix, a plain one of a mixin too (passed over: no Module); a classmethod, or a
    helper whose class defines the hook, is not."""

    class Plain(Module):
        rate = 1.0

        def state_problems(self, state):
            return []

    class Misspelt(Module):
        rate = 1.0

        @classmethod
        def state_problem(cls, state):
            return [f"Misspelt's rate must be above 0, got {state['rate']}"]

    class Helped(Pump):
        @classmethod
        def state_problem(cls, state):      # (Pump's state_problems is the hook: a helper)
            return []

    class Limits:                           # a mixin, no Module
        def state_problems(self, state):
            return []

    class Mixed(Limits, Module):
        rate = 1.0

    problems = System("s").add("p", Plain).add("m", Misspelt).add("h", Helped).add(
        "x", Mixed).check()
    only(problems, "Limits defines state_problems as a plain method")
    only(problems, "test_config:test_a_state_problems_that_is_no_classmethod_or_misspelt_is_"
                   "named.<locals>.Plain defines state_problems as a plain method: it is asked "
                   "of the class, before any instance is made, so make it a classmethod "
                   "(@classmethod, def state_problems(cls, state), returning a list of texts)")
    only(problems, "Misspelt defines state_problem(): did you mean state_problems()? a "
                   "module's hooks are setup(), step(), on_input(), teardown() and the "
                   "classmethod state_problems(), and only they are called")
    assert not [p for p in problems if "Helped" in p], problems


def test_a_driver_s_timeout_it_cannot_go_by_is_a_problem(tmp_path: Path) -> None:
    """A driver's ``timeout`` of 0, -1, NaN or inf passed the check; every request then
    failed, blaming the device (inf: OverflowError at each). Given or its class's."""
    problems = problems_of(tmp_path, """
        [modules.robot]
        class = "agents.robot_driver:RobotDriver"
        state = { timeout = 0, resource = "10.0.0.7:7400" }
        [modules.reader]
        class = "sample_modules:DeviceReader"
        state = { timeout = "2" }
        [modules.fine]
        class = "agents.robot_driver:RobotDriver"
        state = { timeout = 2 }
    """)
    assert len(problems) == 3, problems
    only(problems, "[modules.robot]: RobotDriver's timeout must be a positive number of "
                   "seconds, at most 1e+07 (each request's deadline), got 0")
    only(problems, "[modules.robot]: RobotDriver's resource must be a string tcp://HOST:PORT")
    only(problems, "[modules.reader]: state 'timeout' takes a number")   # (said once)
    system = System("s")
    system.add("m", "sample_modules:DeviceReader", state={"timeout": float("inf")})
    assert any("timeout must be a positive number" in problem for problem in system.check())
    (tmp_path / "parts_driver.py").write_text(textwrap.dedent("""
        from pb3a import Driver

        class Impatient(Driver):
            timeout = -1.0
    """))
    sys.path.insert(0, str(tmp_path))
    try:
        assert any("Impatient's timeout must be a positive number" in problem
                   for problem in System("s").add("m", "parts_driver:Impatient").check())
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("parts_driver", None)
