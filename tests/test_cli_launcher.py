"""``pb3a status / state / migrate / swap ADDR``: acting on a running system through
its launcher's authenticated address."""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import alive, eventually
from sample_modules import (
    Chain,
    Counter,
    FailsOnce,
    FastScale,
    FloatSource,
    Freezer,
    InputFreezer,
    Last,
    OnFlag,
    PlainScale,
    Relay,
    Scale,
)

import pb3a
from pb3a import Module, System
from pb3a.cli import running_system
from pb3a.cli.main import INTERRUPTED, main
from pb3a.cli.standard_output import BROKEN_PIPE
from pb3a.cli.status import format_table
from pb3a.errors import ConfigError
from pb3a.events import Event
from pb3a.launch.connection import Connection
from pb3a.launch.operations import Operations
from pb3a.stats import ModuleStats, SystemStats

REPO = Path(__file__).resolve().parent.parent


def test_a_launcher_listening_already_refuses_another_address() -> None:
    """``listen(ADDR)`` on a launcher that listens already (always, once it has remote
    nodes; or a second call) returned where it listened, ADDR ignored: a connection to
    ADDR was then told that nothing listens there, the system stopped."""
    with System("listens-once").add("scale", Scale).launch() as run:
        address = run.listen()
        port = int(address.rpartition(":")[2])
        assert run.listen() == run.listen(address) == run.listen("tcp://127.0.0.1:0") == address
        other = f"tcp://127.0.0.1:{port + 1 if port < 65535 else port - 1}"
        with pytest.raises(ValueError, match=rf"listens at {address} already, not at {other}"):
            run.listen(other)
        with pb3a.connect(address) as far:
            assert far.state("scale")["gain"] == 2.0
    with System("listens-everywhere").add("scale", Scale).launch(
            listen="tcp://0.0.0.0:0") as run:
        address = run.listen()
        port = int(address.rpartition(":")[2])
        for same in ("tcp://0.0.0.0:0", f"tcp://*:{port}", f"tcp://127.0.0.1:{port}", address):
            assert run.listen(same) == address, same
        with pytest.raises(ValueError, match=r"listens at \S+ already, not at tcp://0\.0\.0\.0:1"):
            run.listen("tcp://0.0.0.0:1")


def test_the_command_line_reads_and_changes_a_running_system(capsys) -> None:
    system = System("cli-launcher")
    system.node("a")
    system.node("b")
    system.add("src", Counter, node="a", period=0.002)
    system.add("relay", Relay, node="a")
    system.add("scale", Scale, node="a")
    system.link("src.out", "relay.x")
    with system.launch() as run:
        address = run.listen()
        eventually(lambda: run.state("relay")["relayed"] > 5, what="values flowing")
        assert main(["status", address]) == 0
        table = capsys.readouterr().out
        assert "relay" in table and "src.out -> relay.x" in table
        assert main(["state", address, "scale"]) == 0
        assert '"gain": 2.0' in capsys.readouterr().out
        assert main(["migrate", address, "relay", "b"]) == 0
        assert "relay: a -> b, paused" in capsys.readouterr().out
        assert run.stats().modules["relay"].node == "b"
        ref = f"{FastScale.__module__}:FastScale"
        assert main(["swap", address, "scale", ref]) == 0
        assert "state kept: gain, setups" in capsys.readouterr().out
        assert main(["state", address, "ghost"]) == 1
        assert "no module 'ghost'" in capsys.readouterr().err


# A module file edited while its class runs: ``version`` says which edit ran last.
EDITED = """
from pb3a import Input, Module

class Gain(Module):
    x = Input(float)
    version = 0

    def on_input(self, port):
        port.read()
        self.version = {version}
"""


def test_a_swap_after_the_module_file_changed_runs_the_file_as_it_is_now(
        capsys, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`pb3a swap` (and `run.swap`) naming "module:Class" after its file was edited said
    the new class was in but ran the code the launcher had imported before: the module
    is reloaded first now, saying so. `pb3a reload` does it by hand (there was no such
    command: only `run.reload` from Python)."""
    module = "pb3a_edited_gain"
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, module, raising=False)
    source = tmp_path / f"{module}.py"
    source.write_text(EDITED.format(version=1))
    system = System("cli-edited").add("src", FloatSource).add("g", f"{module}:Gain")
    system.link("src.out", "g.x")
    try:
        with system.launch() as run:
            address = run.listen()
            eventually(lambda: run.state("g")["version"] == 1, what="the first file running")
            source.write_text(EDITED.format(version=22))
            assert main(["swap", address, "g", f"{module}:Gain"]) == 0
            assert (f"module {module} changed since it was imported: reloaded; g is now "
                    f"{module}:Gain") in capsys.readouterr().out
            eventually(lambda: run.state("g")["version"] == 22, what="the edited file running")
            source.write_text(EDITED.format(version=333))
            run.swap("g", f"{module}:Gain")                     # the same from Python
            eventually(lambda: run.state("g")["version"] == 333, what="the second edit")
            assert run.events()[-1].detail["reloaded"] == module
            source.write_text(EDITED.format(version=4444))
            assert main(["reload", address, module]) == 0
            assert f"{module} reloaded" in capsys.readouterr().out
            assert main(["swap", address, "g", f"{module}:Gain", "--json"]) == 0
            assert json.loads(capsys.readouterr().out)["reloaded"] is None     # done already
            eventually(lambda: run.state("g")["version"] == 4444, what="the reloaded file")
            run.swap("g", f"{module}:Gain")             # unchanged since: not reloaded
            assert "reloaded" not in run.events()[-1].detail
    finally:
        sys.modules.pop(module, None)


# A class written into a module file after the launch (``name``), beside the rest.
WRITTEN_LATER = """

class {name}(Gain):
    version = {version}
"""


def test_an_add_of_a_class_written_into_its_file_after_launch_finds_it(
        capsys, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`pb3a add` (and `run.add`) of a class written into the module's file after launch
    said "module ... has no class 'PoseProbe'; it has: Gain", though the file had it: the
    add took the module as the launcher had imported it. It reloads a module whose file
    changed since first, as a swap does, saying so."""
    module = "pb3a_grown_gains"
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, module, raising=False)
    source = tmp_path / f"{module}.py"
    source.write_text(EDITED.format(version=1))
    system = System("cli-grown").add("src", FloatSource).add("g", f"{module}:Gain")
    system.link("src.out", "g.x")
    try:
        with system.launch() as run:
            address = run.listen()
            eventually(lambda: run.state("g")["version"] == 1, what="the first file running")
            with source.open("a") as grown:
                grown.write(WRITTEN_LATER.format(name="PoseProbe", version=2))
            capsys.readouterr()
            assert main(["add", address, "probe", f"{module}:PoseProbe"]) == 0
            assert (f"module {module} changed since it was imported: reloaded; probe "
                    f"({module}:PoseProbe) runs on node local") in capsys.readouterr().out
            assert run.state("probe")["version"] == 2
            with source.open("a") as grown:
                grown.write(WRITTEN_LATER.format(name="Later", version=3))
            run.add("later", f"{module}:Later")                  # the same from Python
            assert run.events()[-1].detail["reloaded"] == module
            assert run.state("later")["version"] == 3
            run.add("again", f"{module}:Later")          # unchanged since: not reloaded
            assert "reloaded" not in run.events()[-1].detail
            assert run.state("g")["version"] == 1        # (running modules keep their code)
    finally:
        sys.modules.pop(module, None)


# A program that launches an edited module (written to its working directory), prints
# the launcher's address, and runs until its stdin closes.
LAUNCHES_EDITED = """
import sys
from sample_modules import FloatSource
from pb3a import System
system = System("edited-restart").add("src", FloatSource).add("g", "pb3a_edited_again:Gain")
system.link("src.out", "g.x")
with system.launch() as run:
    print(run.listen(), flush=True)
    sys.stdin.read()
"""


def test_a_module_restarted_after_a_swap_to_its_edited_file_runs_the_edited_file(
        tmp_path: Path) -> None:
    """A worker started after a reload (for a restart, a move) comes from the forkserver,
    which imported the system's module files at launch: a restart after a swap to the
    edited file ran the code from before the edit again, the system saying the module
    ran the new class. The worker drops what was reloaded before it loads a class."""
    source = tmp_path / "pb3a_edited_again.py"
    source.write_text(EDITED.format(version=1))
    path = os.pathsep.join([str(tmp_path), str(REPO / "tests"), str(REPO)])
    launcher = subprocess.Popen([sys.executable, "-c", LAUNCHES_EDITED], cwd=tmp_path,
                                env={**os.environ, "PYTHONPATH": path}, text=True,
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert launcher.stdout is not None and launcher.stdin is not None
        with pb3a.connect(launcher.stdout.readline().strip(), timeout=10) as system:
            eventually(lambda: system.state("g")["version"] == 1, what="the first file")
            source.write_text(EDITED.format(version=22))
            system.swap("g", "pb3a_edited_again:Gain")
            eventually(lambda: system.state("g")["version"] == 22, what="the edited file")
            system.restart("g")                      # (its state the configured one: 0)
            version = eventually(lambda: system.state("g")["version"],
                                 what="a value handled after the restart")
            assert version == 22, "the restart ran the file as it was before the edit"
        launcher.communicate(timeout=30)            # (its stdin closed: it stops)
        assert launcher.returncode == 0
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.communicate()


def test_status_shows_the_cause_of_a_multi_line_error_on_its_row() -> None:
    """An agent whose swap failed showed "ConfigError: 1 problem in the configuration:"
    as its last error, the cause on a line of its own that broke the table. Now the
    lines are joined, the header dropped: the cause shows on the module's row."""
    problem = "swap loop/filter: module 'control' has no class 'LowPas'"
    last = f"ConfigError: {ConfigError([problem])} (at tuner.py:12 in on_input)"
    stats = SystemStats(system="s", links={}, nodes={}, failures=[], modules={
        "t2": ModuleStats(cls="tuner:Tuner", node="local", worker="local/m-t2",
                          status="running", errors=1, last_error=last),
        "m": ModuleStats(cls="m:M", node="local", worker="local/m-m", status="running",
                         errors=1, last_error="ValueError: first\n  second")})
    rows = format_table(stats).splitlines()
    assert len(rows) == 3, rows
    assert rows[1].endswith("ConfigError: swap loop/filter: module 'control' has no cl..."), \
        rows[1]
    assert rows[2].endswith("ValueError: first; second"), rows[2]


def test_status_says_how_long_ago_a_module_s_last_error_was_raised() -> None:
    """A module's last error stayed on its row, with nothing to tell it from a fresh one,
    long after its cause was mended (a first-time user fixed an explorer's setting live,
    and still saw its error): the row says how long ago it was raised. ``stats()`` has
    when (the wall clock), and a move keeps it with the error."""
    system = System("dated").node("a").node("b")
    system.add("flaky", FailsOnce, node="a", period=0.01)
    before = time.time()
    with system.launch() as run:
        eventually(lambda: run.stats().modules["flaky"].errors == 1, what="its one error")
        at = run.stats().modules["flaky"].last_error_at
        run.migrate("flaky", to="b")
        moved = run.stats().modules["flaky"]
    assert before <= at <= time.time(), (before, at)
    assert moved.last_error_at == at and moved.last_error.startswith("RuntimeError: once")
    stats = SystemStats(system="s", links={}, nodes={}, failures=[], modules={
        "m": ModuleStats(cls="m:M", node="local", worker="local/m-m", status="running",
                         errors=1, last_error="ValueError: late", last_error_at=at - 300)})
    assert format_table(stats).splitlines()[1].endswith("5 min ago: ValueError: late")


def test_status_shows_every_node_as_nodes_does(capsys) -> None:
    """`pb3a status` (and `pb3a run`'s table) left the launcher's own, embedded nodes out
    of its node rows, which `pb3a nodes` showed (from the deploy walkthrough)."""
    system = System("cli-every-node").node("a").node("idle")
    system.add("src", Counter, node="a", period=0.002)
    with system.launch() as run:
        address = run.listen()
        assert main(["nodes", address]) == 0
        listed = capsys.readouterr().out.strip().splitlines()
        assert main(["status", address]) == 0
        table = capsys.readouterr().out.splitlines()
    assert [line.split()[:3] for line in listed[1:]] == [
        ["a", "(embedded)", "up"], ["idle", "(embedded)", "up"]]
    assert all(line in table for line in listed), (listed, table)


def test_set_sets_text_as_given_when_the_module_s_state_cannot_be_read(capsys) -> None:
    # (set asks the state to refuse text for a field that holds none; a state it cannot
    # read must not keep it from setting)
    class Unreadable(Module):
        label = "none"

        def get_state(self) -> dict:
            if self.label == "none":
                raise ValueError("this state is not for reading")
            return super().get_state()

    with System("unreadable").add("m", Unreadable).launch() as run:
        assert main(["set", run.listen(), "m", "label=hello"]) == 0
        assert "m: label = 'hello'" in capsys.readouterr().out
        assert run.state("m")["label"] == "hello"


def test_set_on_a_module_busy_in_a_call_keeps_one_timeout_and_says_what_it_is_in(
        capsys) -> None:
    """``pb3a set`` of a module stuck in ``on_input`` took twice the system's timeout
    (the state read's timeout was taken for a state that cannot be read, and the edit
    waited a whole one again), and with ``--timeout 5`` said it was "busy in a call for
    0.18 s" (what was left for the edit). Now a read that runs out ends the command at
    once, saying what the module is busy in and for how long."""
    system = System("cli-set-busy")
    system.add("src", Counter, period=0.01)
    system.add("f", InputFreezer, state={"freeze_in": "on_input"})
    system.link("src.out", "f.x")
    with system.launch(timeout=3) as run:
        address = run.listen()
        eventually(lambda: run.stats().modules["f"].calling == "on_input", what="f stuck")
        began = time.monotonic()
        assert main(["set", address, "f", "handled=0"]) == 1
        took = time.monotonic() - began
        err = capsys.readouterr().err
        assert took < 4.5, f"pb3a set took {took:.1f} s for a timeout of 3 s: {err}"
        assert re.search(r"module 'f' was busy in a call for 2\.\d+ s \(in on_input for "
                         r"\d+\.\d s\): nothing was done", err), err
        assert main(["set", address, "f", "handled=0", "--timeout", "1"]) == 1
        err = capsys.readouterr().err
        assert re.search(r"busy in a call for 0\.[5-9]\d* s \(in on_input for", err), err


def test_set_gives_a_float_field_a_float_for_a_whole_number(capsys) -> None:
    """JSON writes 4.0 as 4: `pb3a set ADDR scale gain=4` set an int, and a Scale whose
    float input took an int then wrote int * int on its float output, refused at each
    value (TypeError: port 'y' carries float, got int)."""
    with System("set-float").add("scale", Scale).add("src", Counter, period=0.002) \
            .link("src.out", "scale.x").launch() as run:
        assert main(["set", run.listen(), "scale", "gain=4", "setups=2"]) == 0
        assert "scale: gain = 4.0, setups = 2" in capsys.readouterr().out
        state = run.state("scale")
        assert type(state["gain"]) is float and type(state["setups"]) is int
        run.wait(0.3)
        assert run.stats().modules["scale"].errors == 0
        # the period is the runtime's, not a state field, and is set all the same (it
        # was "scale has no state 'period'")
        assert main(["set", run.listen(), "src", "period=0.5"]) == 0
        assert "src: period = 0.5" in capsys.readouterr().out
        assert run.topology().modules["src"].period == 0.5


def test_add_gives_a_float_field_a_float_and_names_a_value_that_does_not_fit(capsys) -> None:
    """``pb3a add --state gain=4`` set an int, as ``pb3a set`` did (the CLI had no state
    to follow): each value is made the type of the class's default, and one that does
    not fit is named before anything is added."""
    with System("add-float").add("src", Counter, period=0.002).launch() as run:
        address, ref = run.listen(), f"{Scale.__module__}:Scale"
        assert main(["add", address, "late", ref, "--state", "gain=[1]"]) == 1
        assert "late: state 'gain' takes a number, got [1]; nothing was added" in \
            capsys.readouterr().err
        assert "late" not in run.stats().modules
        assert main(["add", address, "scale", ref, "--state", "gain=4", "setups=2"]) == 0
        state = run.state("scale")
        assert type(state["gain"]) is float and type(state["setups"]) is int


def test_a_swap_names_the_state_it_dropped(capsys, caplog) -> None:
    """``pb3a swap`` listed the state kept, not the fields the new class lacks, whose
    values (gains tuned live, say) were let go of without a word."""
    with System("swap-drops").add("scale", Scale, state={"gain": 3.0}).launch() as run:
        address = run.listen()
        assert main(["swap", address, "scale", f"{PlainScale.__module__}:PlainScale"]) == 0
        assert capsys.readouterr().out.strip().endswith(
            "state kept: gain; dropped (the class has no such fields): setups")
        assert run.state("scale") == {"gain": 3.0}
        swapped = [e.detail for e in run.events() if e.kind == "module_swapped"]
    assert swapped[0]["kept"] == ["gain"] and swapped[0]["dropped"] == ["setups"]
    assert "swap scale: state dropped, PlainScale has no such fields: setups" in caplog.text


def test_a_swap_says_what_its_own_swap_did_not_what_a_later_one_did(
        capsys, monkeypatch: pytest.MonkeyPatch) -> None:
    """``pb3a swap`` said what the newest ``module_swapped`` event of its module held,
    read after the swap: someone else's swap of the same module in between was said as
    its own (here the state it dropped went unsaid). It reads the events after the
    newest one before its call, and takes the first of its module."""
    plain = f"{PlainScale.__module__}:PlainScale"
    swap = Connection.swap

    def then_another(self: Connection, name: str, cls: str, **kwargs: object) -> list[str]:
        kept = swap(self, name, cls, **kwargs)
        run.swap(name, plain)               # another's, before pb3a swap reads its own
        return kept

    monkeypatch.setattr(Connection, "swap", then_another)
    with System("swap-own").add("scale", Scale, state={"gain": 3.0}).launch() as run:
        assert main(["swap", run.listen(), "scale", plain]) == 0
        assert capsys.readouterr().out.strip().endswith(
            "state kept: gain; dropped (the class has no such fields): setups")
        assert [e.detail["dropped"] for e in run.events() if e.kind == "module_swapped"] \
            == [["setups"], []]


def test_events_add_and_swap_work_with_a_launcher_older_than_events_last(
        capsys, monkeypatch: pytest.MonkeyPatch) -> None:
    """A client sent ``last`` with every ``events()``, None too, which a launcher older
    than it refused ("unexpected keyword argument 'last'"): ``pb3a events``, ``swap``,
    ``add`` and the manager's page failed against it. ``last`` goes only when given,
    and ``swap`` and ``add`` read such a launcher's whole log instead."""
    events = Operations.events

    def older(self: Operations, since: int = 0, *, timeout: float | None = 0.0) -> list:
        return events(self, since, timeout=timeout)

    monkeypatch.setattr(Operations, "events", older)
    plain = f"{PlainScale.__module__}:PlainScale"
    with System("older").add("scale", Scale).launch() as run:
        address = run.listen()
        assert main(["events", address]) == 0
        assert main(["swap", address, "scale", plain]) == 0
        assert f"scale is now {plain}" in capsys.readouterr().out
        with pb3a.connect(address) as connection:
            assert [e.kind for e in connection.events()][-1] == "module_swapped"


def test_a_swap_says_what_its_own_swap_did_not_what_one_just_before_did(
        capsys, monkeypatch: pytest.MonkeyPatch) -> None:
    """Another's swap of the same module between ``pb3a swap``'s look at the newest event
    and its own swap was said as its own (the first after that look). The one whose
    state kept is what its swap answered is taken."""
    plain = f"{PlainScale.__module__}:PlainScale"
    newest = running_system._newest_seq

    def then_another(system: Connection) -> int:
        seq = newest(system)
        run.swap("scale", Scale)                # another's, before pb3a swap's own
        return seq

    monkeypatch.setattr(running_system, "_newest_seq", then_another)
    with System("swap-first").add("scale", Scale, state={"gain": 3.0}).launch() as run:
        assert main(["swap", run.listen(), "scale", plain]) == 0
        assert capsys.readouterr().out.strip().endswith(
            "state kept: gain; dropped (the class has no such fields): setups")


def test_add_and_swap_read_no_event_older_than_the_newest_before_their_call(
        capsys, monkeypatch: pytest.MonkeyPatch) -> None:
    """``pb3a add`` and ``pb3a swap`` read the system's whole event log (it keeps 10,000)
    for their own event, at every call: they read the newest event before the call
    (``events(last=1)``) and those after it."""
    read: list[int] = []
    events = Connection.events

    def counted(self: Connection, *args: object, **kwargs: object) -> list[Event]:
        got = events(self, *args, **kwargs)
        read.extend(event.seq for event in got)
        return got

    monkeypatch.setattr(Connection, "events", counted)
    ref = f"{Scale.__module__}:Scale"
    with System("cli-reads").add("scale", Scale).launch() as run:
        address = run.listen()
        for _ in range(3):
            run.swap("scale", PlainScale)
            run.swap("scale", Scale)
        newest = run.events()[-1].seq
        assert newest >= 6
        assert main(["swap", address, "scale", ref]) == 0
        assert main(["add", address, "late", ref]) == 0
        assert "late (" in capsys.readouterr().out
    assert read == [newest, newest + 1, newest + 1, newest + 2]


def test_add_and_remove_take_a_macro_whole(capsys) -> None:
    """``pb3a add ADDR NAME module:Macro`` was refused ("is not a pb3a.Module subclass"),
    and ``pb3a remove`` of a macro instance named no module."""
    system = System("cli-macro").node("a").node("b")
    system.add("src", Counter, node="a", period=0.002)
    with system.launch() as run:
        address, ref = run.listen(), f"{Chain.__module__}:Chain"
        assert main(["add", address, "c2", ref, "--node", "b", "--state", 'b={"gain": 4}',
                     "--json"]) == 0
        assert json.loads(capsys.readouterr().out) == {
            "module": "c2", "class": ref, "modules": {"c2/a": "b", "c2/b": "b"},
            "reloaded": None}
        state = run.state("c2/b")
        assert state["gain"] == 4.0 and type(state["gain"]) is float
        assert main(["remove", address, "c2"]) == 0
        assert "c2 removed" in capsys.readouterr().out
        assert set(run.topology().modules) == {"src"}


class Weighted(Module):
    """Float state of other shapes than a plain float: a numpy float, a list of floats."""

    gain = np.float64(1.5)
    weights = [0.5, 1.5]
    limits = {"low": 0.5}


def test_set_gives_floats_in_numpy_fields_and_lists_and_names_a_number_too_large(
        capsys) -> None:
    """Only a plain float field was converted: a numpy float field or a list of floats
    took ints (the State Editor gives floats, and so does pb3a set now, through the same
    ``coerce``), and a whole number beyond any float ended in OverflowError's
    traceback."""
    with System("set-floats").add("w", Weighted).launch() as run:
        address = run.listen()
        assert main(["set", address, "w", "gain=4", "weights=[1, 2, 3]",
                     "limits={\"low\": 1, \"new\": 2}"]) == 0
        capsys.readouterr()
        state = run.state("w")
        assert type(state["gain"]) is np.float64 and state["gain"] == 4.0
        assert [type(item) for item in state["weights"]] == [float] * 3
        assert state["limits"] == {"low": 1.0, "new": 2} and type(state["limits"]["low"]) \
            is float and type(state["limits"]["new"]) is int
        assert main(["set", address, "w", "weights=[0.5]", "gain=1" + "0" * 400]) == 1
        assert "w: state 'gain' takes a number a float64 holds, got 1000" in \
            capsys.readouterr().err
        assert run.state("w")["gain"] == 4.0 and len(run.state("w")["weights"]) == 3


class Arrays(Module):
    """State as a robot's mostly is: numpy arrays and numbers."""

    big = np.zeros(2000)
    small = np.arange(3)
    count = np.int64(7)
    level = np.float32("nan")


def test_state_json_gives_numpy_state_whole_and_as_json_numbers(capsys) -> None:
    """``--json`` gave a 2000-value array as its 51-character abbreviated repr, ``"np.int64(7)"``
    as text, and a float32 NaN not as null; for people, an array stays abbreviated."""
    with System("numpy-state").add("m", Arrays).launch() as run:
        address = run.listen()
        assert main(["state", address, "m", "--json"]) == 0
        state = json.loads(capsys.readouterr().out, parse_constant=_no_constant)
        assert state["big"] == [0.0] * 2000 and state["small"] == [0, 1, 2]
        assert state["count"] == 7 and state["level"] is None
        assert main(["state", address, "m"]) == 0
        shown = capsys.readouterr().out
        assert "shape=(2000,)" in shown and '"count": 7' in shown and '"level": NaN' in shown
        assert main(["set", address, "m", "count=5"]) == 0
        assert capsys.readouterr().out.strip() == "m: count = 5"
        assert run.state("m")["count"] == 5


def _no_constant(name: str) -> None:
    raise AssertionError(f"--json printed {name}, which JSON has not")


def test_every_command_changes_a_running_system_and_speaks_json(capsys) -> None:
    system = System("cli-more")
    system.node("a")
    system.node("b")
    system.add("src", Counter, node="a", period=0.002)
    system.add("other", Counter, node="b", period=0.002)
    system.add("relay", Relay, node="a")
    system.link("src.out", "relay.x")
    with system.launch() as run:
        address = run.listen()
        bare = address.removeprefix("tcp://")              # HOST:PORT works too
        assert main(["set", bare, "src", "limit=Infinity"]) == 1    # an int field
        assert "src: state 'limit' takes a whole number, got inf; nothing was set" in \
            capsys.readouterr().err
        assert main(["set", bare, "src", "limit=3.0"]) == 0         # (JSON's 3.0 is 3)
        assert "src: limit = 3" in capsys.readouterr().out
        assert type(run.state("src")["limit"]) is int and run.state("src")["limit"] == 3
        # text for a field that holds no text is refused (it was set, as text: a bool's
        # "False" left the module enabled, a float's "0,3" made every step raise)
        assert main(["set", bare, "src", "count=5", "limit=3,5"]) == 1
        assert ("limit=3,5 is not JSON, and src.limit is int (3), not text: give it "
                "as JSON") in capsys.readouterr().err
        assert run.state("src")["limit"] == 3 and run.state("src")["count"] != 5
        assert main(["relink", address, "other.out", "relay.x", "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["from"] == "other.out"
        eventually(lambda: "other.out->relay.x" in run.stats().links, what="the new link")
        assert main(["add", address, "probe", f"{Last.__module__}:Last", "--node", "b",
                     "--state", "value=1.5"]) == 0
        assert "probe" in capsys.readouterr().out and run.where("probe") == "b"
        assert run.state("probe")["value"] == 1.5
        assert main(["set", bare, "probe", "value=Infinity"]) == 0
        capsys.readouterr()
        assert main(["state", bare, "probe"]) == 0                  # for people: as set
        assert '"value": Infinity' in capsys.readouterr().out
        assert main(["state", bare, "probe", "--json"]) == 0        # valid JSON: null
        assert json.loads(capsys.readouterr().out, parse_constant=_no_constant)["value"] \
            is None
        assert main(["add", address, "tag", f"{OnFlag.__module__}:OnFlag",
                     "--state", "flag=nowhere"]) == 0      # text, as text (a str, kept)
        capsys.readouterr()
        assert type(run.state("tag")["flag"]) is str
        assert run.configuration()["system"]["modules"]["tag"]["state"] == {"flag": "nowhere"}
        assert main(["restart", address, "probe", "--json"]) == 0
        assert json.loads(capsys.readouterr().out) == {"module": "probe", "restarted": True}
        assert main(["remove", address, "probe"]) == 0
        assert "probe removed" in capsys.readouterr().out
        assert "probe" not in run.stats().modules
        assert main(["nodes", address, "--json"]) == 0
        nodes = json.loads(capsys.readouterr().out)
        assert set(nodes) == {"a", "b"} and nodes["a"]["up"] is True
        assert main(["status", address, "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["modules"]["relay"]["node"] == "a"
        assert main(["migrate", address, "relay", "b", "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["destination"] == "b"
        assert main(["events", address]) == 0
        lines = [line.split() for line in capsys.readouterr().out.splitlines()]
        assert [kind for _, _, kind, *_ in lines] == [
            "link_removed", "link_added", "module_added", "module_added",
            "module_restarted", "module_removed", "module_moved"]
        assert main(["events", address, "--json"]) == 0
        events = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
        assert [e["seq"] for e in events] == list(range(1, 8))
        assert events[-1]["detail"]["destination"] == "b"
        # each line begins with its event's local time, to the millisecond (it had none)
        assert all(re.fullmatch(r"\d\d:\d\d:\d\d\.\d{3}", clock) for clock, *_ in lines), lines
        assert [clock[:8] for clock, *_ in lines] == [
            time.strftime("%H:%M:%S", time.localtime(e["time"])) for e in events]


def test_a_migrate_to_the_node_a_module_runs_on_says_nothing_moved(capsys) -> None:
    """`pb3a migrate ADDR relay b` with relay on b already printed "relay: b -> b, paused
    0.0 ms, 0 bytes of state, 0 links re-wired", as if it had moved. It says relay runs
    there already and nothing moved; ``run.migrate``'s report says ``moved`` False, there
    is no event, and state given is set where the module runs."""
    system = System("cli-migrate-home").node("a").node("b")
    system.add("src", Counter, node="a", period=0.002)
    system.add("relay", Relay, node="a")
    system.link("src.out", "relay.x")
    with system.launch() as run:
        address = run.listen()
        assert main(["migrate", address, "relay", "b"]) == 0
        assert "relay: a -> b, paused" in capsys.readouterr().out
        assert main(["migrate", address, "relay", "b"]) == 0
        assert capsys.readouterr().out.strip() == "relay already runs on node b; nothing moved"
        assert main(["migrate", address, "relay", "b", "--json"]) == 0
        said = json.loads(capsys.readouterr().out)
        assert (said["moved"], said["source"], said["destination"]) == (False, "b", "b")
        assert run.migrate("relay", "a").moved
        report = run.migrate("relay", "a", state={"relay": {"setups": 7}})
        assert not report.moved and run.state("relay")["setups"] == 7
        assert [e.kind for e in run.events()].count("module_moved") == 2


def test_remove_force_kills_a_module_that_does_not_answer(capsys) -> None:
    """``pb3a remove ADDR NAME`` of a module whose worker is frozen (SIGSTOP) fails
    within ``--timeout``, naming ``--force``; with ``--force`` its worker is killed and
    the module goes with its link."""
    system = System("cli-remove-force")
    system.add("src", Counter, period=0.01)
    system.add("f", Freezer)
    system.link("src.out", "f.x")
    with system.launch(timeout=30) as run:
        address = run.listen()
        pid = run.stats().modules["f"].pid
        os.kill(pid, signal.SIGSTOP)
        try:
            assert main(["remove", address, "f", "--timeout", "1"]) == 1
            assert "(`pb3a remove ADDR f --force`) kills its worker" in capsys.readouterr().err
            assert main(["remove", address, "f", "--timeout", "1", "--force", "--json"]) == 0
            assert json.loads(capsys.readouterr().out) == {"module": "f", "removed": True}
        finally:
            if alive(pid):
                os.kill(pid, signal.SIGCONT)
        assert not alive(pid)
        assert set(run.topology().modules) == {"src"} and not run.topology().links


def test_restart_force_kills_a_stuck_module_and_starts_it_again_with_its_links(capsys) -> None:
    """A module stuck in ``on_input`` could not be restarted, only removed (with
    ``--force``), which lost its links: ``pb3a restart --force`` kills its worker and
    starts it again, wired as it was."""
    system = System("cli-restart-force")
    system.add("src", Counter, period=0.01)
    system.add("f", InputFreezer)
    system.link("src.out", "f.x")
    with system.launch(timeout=30) as run:
        address = run.listen()
        eventually(lambda: run.state("f")["handled"] > 3, what="values handled")
        pid = run.stats().modules["f"].pid
        run.set_state("f", freeze_in="on_input")
        eventually(lambda: run.stats().modules["f"].calling == "on_input"
                   and run.stats().modules["f"].calling_s > 0.2, what="stuck in on_input")
        assert main(["restart", address, "f", "--timeout", "1"]) == 1
        assert "(`pb3a restart ADDR f --force`) kills its worker" in capsys.readouterr().err
        assert main(["restart", address, "f", "--timeout", "1", "--force"]) == 0
        assert capsys.readouterr().out.strip() == "f restarted"
        assert not alive(pid)
        eventually(lambda: run.state("f")["handled"] > 3, what="values handled again")
        restarted = [e.detail for e in run.events() if e.kind == "module_restarted"]
        assert set(run.topology().links) == {"src.out->f.x"}
    assert restarted == [{"node": "local", "reason": "asked", "killed": True, "pid": pid}]


def test_mistakes_on_the_command_line_get_a_sentence_and_exit_1(capsys) -> None:
    with System("cli-mistakes").add("src", Counter).launch() as run:
        address = run.listen()
        for argv, said in (
                (["status", "7300"], "is not a launcher's address: give tcp://HOST:PORT"),
                # (it waited 2 s, then said nothing listened on port 99999)
                (["status", "tcp://127.0.0.1:99999"], "its port 99999 is out of range"),
                (["set", address, "src", "limit"], "'limit' is not NAME=VALUE"),
                (["set", address, "src", "nosuch=1", "limit=2"],      # (not the worker's
                 "pb3a set: src has no state 'nosuch'; its state: "),   # KeyError: nothing set)
                (["swap", address, "src", "nowhere:Nothing"], "cannot import module 'nowhere'"),
                (["migrate", address, "src", "mars"], "no node 'mars'"),
                (["relink", address, "src.out", "src.nope"], "src has no input 'nope'"),
                (["remove", address, "ghost"], "no module 'ghost'"),
                (["migrate", address, "scr", "local"], "no module 'scr' in system "
                 "'cli-mistakes'; modules: src (did you mean 'src'?)")):
            assert main(argv) == 1, argv
            err = capsys.readouterr().err
            assert said in err and "Traceback" not in err and "KeyError" not in err, (argv, err)
        assert run.state("src")["limit"] == 0


@pytest.mark.timeout(90)
def test_ctrl_c_ends_a_command_on_a_running_system_with_status_130() -> None:
    """Ctrl-C on ``pb3a events ADDR --follow`` (as on any command acting through the
    launcher) ends it with 130 and one line, not 0 as if it had done its work."""
    system = System("cli-interrupted")
    system.node("a")
    system.node("b")
    system.add("relay", Relay, node="a")
    with system.launch() as run:
        address = run.listen()
        run.migrate("relay", to="b")                       # one event to follow
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), str(REPO)])}
        follower = subprocess.Popen([sys.executable, "-m", "pb3a", "events", address,
                                     "--follow"], stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True, env=env)
        try:
            assert "module_moved" in follower.stdout.readline()    # connected, following
            follower.send_signal(signal.SIGINT)
            assert follower.wait(timeout=20) == INTERRUPTED
            assert follower.stderr.read().strip() == "pb3a: interrupted"
        finally:
            if follower.poll() is None:
                follower.kill()
                follower.wait(5)
            follower.stdout.close()
            follower.stderr.close()


@pytest.mark.timeout(90)
def test_followers_end_with_status_0_when_the_system_stops() -> None:
    """``events --follow`` and ``logs --follow`` are told the system stopped as it
    stops, and end with 0 (they waited out their timeout for a launcher that had
    gone, and said it did not answer: exit 1, as for a network failure)."""
    system = System("cli-followed").add("steady", Counter, period=0.05)
    run = system.launch()
    followers = []
    try:
        address = run.listen()
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), str(REPO)])}
        for command in ("events", "logs"):
            followers.append(subprocess.Popen(
                [sys.executable, "-m", "pb3a", command, address, "--follow"],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env))
        run.add("late", Counter)
        logging.getLogger("pb3a.test").warning("a line to follow")
        assert "module_added" in followers[0].stdout.readline()    # connected, following
        assert "a line to follow" in followers[1].stdout.readline()
    finally:
        run.close()
    try:
        for follower, what in zip(followers, ("events", "logs"), strict=True):
            assert follower.wait(timeout=10) == 0, follower.stderr.read()
            assert follower.stderr.read().endswith(
                f"pb3a {what}: system 'cli-followed' is stopped: no new entry will come\n")
    finally:
        for follower in followers:
            if follower.poll() is None:
                follower.kill()
                follower.wait(5)
            follower.stdout.close()
            follower.stderr.close()


@pytest.mark.timeout(90)
def test_a_command_whose_reader_has_gone_ends_quietly() -> None:
    """``pb3a status ADDR --json | head -c 300`` ended in a BrokenPipeError traceback."""
    system = System("cli-reader-gone").add("count", Counter)
    with system.launch() as run:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), str(REPO)])}
        command = subprocess.Popen([sys.executable, "-m", "pb3a", "status", run.listen(),
                                    "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                   text=True, env=env)
        try:
            command.stdout.close()                  # gone before the command writes
            assert command.wait(timeout=30) == BROKEN_PIPE
            assert command.stderr.read() == ""
        finally:
            if command.poll() is None:
                command.kill()
                command.wait(5)
            command.stderr.close()


def test_a_follower_that_fell_behind_is_told_how_many_entries_it_missed(capsys) -> None:
    """A follower held up while a module logged thousands of lines a second went on from
    the oldest entry still kept, 20,340 skipped unsaid; a filtered one skips numbers
    anyway (the others' entries), and is told nothing."""
    @dataclasses.dataclass
    class Entry:
        seq: int

    batches = [[Entry(1), Entry(2)], [Entry(6)], []]
    fetched: list[int] = []

    def fetch(seen: int, wait: float) -> list[Entry]:
        fetched.append(seen)
        return batches[len(fetched) - 1]

    def stop_after_three(seen: int, wait: float) -> list[Entry]:
        if len(fetched) == 3:
            raise pb3a.SystemStopped("system 'x' has stopped")
        return fetch(seen, wait)

    args = argparse.Namespace(follow=True, json=False)
    running_system._follow(stop_after_three, lambda entry: str(entry.seq), args)
    out, err = capsys.readouterr()
    assert out.split() == ["1", "2", "6"] and fetched == [0, 2, 6]
    assert "pb3a: 3 entries before 6 are no longer kept by the system" in err
    fetched.clear()
    running_system._follow(stop_after_three, lambda entry: str(entry.seq), args, every=False)
    assert "no longer kept" not in capsys.readouterr().err
