"""The executor on one node: execution modes, links, live operations."""

from __future__ import annotations

import collections
import copy
import dataclasses
import gc
import inspect
import itertools
import json
import logging
import os
import pickle
import re
import signal
import sys
import threading
import time
import types

import numpy as np
import psutil
import pytest
from conftest import eventually
from sample_modules import (
    AdaptsItsRate,
    ArrayHolder,
    ArrayReuser,
    ArraySink,
    ArraySource,
    AssignsNoPeriods,
    AssignsThenFails,
    Burst,
    Busy,
    Chain,
    Collector,
    CollectorV2,
    Counter,
    DeviceReader,
    Doubler,
    Drifter,
    FailsToMake,
    FastScale,
    FloatSource,
    Fragile,
    Last,
    ListensOnly,
    ListScribbler,
    ListSink,
    MapMaker,
    MapMakerV2,
    Offset,
    Outer,
    Overlap,
    Paced,
    Pid,
    Pump,
    Reassigns,
    Retimer,
    Scale,
    SetsItsPeriod,
    Shift,
    SlowsItself,
    SlowsTwiceResets,
    Spawner,
    Steady,
    StepsOnceSetUp,
)

from agents.traffic.gap_out import GapOut
from agents.traffic.sensors import JunctionSensors
from pb3a import (
    ConfigError,
    Driver,
    Environment,
    Input,
    Module,
    ModuleNotFound,
    Output,
    RuntimeFailure,
    RuntimeTimeout,
    System,
    serve_device,
)
from pb3a.cli.status import format_table
from pb3a.config.compiler import validate
from pb3a.config.description import read_description
from pb3a.model.agent import RuntimeClient
from pb3a.model.module import StateRefused, reflective
from pb3a.node import resources
from pb3a.stats import (
    FAILURES_KEPT,
    FailureLog,
    InputStats,
    LinkStats,
    ModuleStats,
    NodeStats,
    SystemStats,
)
from pb3a.testing import ModuleHarness
from pb3a.worker.actor import EventPool, ModuleActor, SetupError
from pb3a.worker.periods import PeriodTeller

pytestmark = pytest.mark.timeout(90)


def pipeline(workers: int = 0) -> System:
    system = System("pipe", workers=workers)
    system.add("src", FloatSource, state={"value": 1.5})
    system.add("scale", Scale)
    system.add("sink", Last)
    system.link("src.out", "scale.x")
    system.link("scale.y", "sink.x")
    return system


@pytest.mark.parametrize("workers", [0, 1, 2])
def test_modules_run_in_either_execution_mode(workers: int) -> None:
    system = System("modes", workers=workers)
    for i in range(3):
        system.add(f"p{i}", Pid)
    with system.launch() as run:
        pids = [eventually(lambda i=i: run.state(f"p{i}")["pid"], what="a step") for i in range(3)]
        figures = run.stats().modules
    distinct = len(set(pids))
    assert distinct == (3 if workers == 0 else workers)
    assert {figures[f"p{i}"].pid for i in range(3)} == set(pids)


@pytest.mark.parametrize("workers", [0, 1])
def test_values_flow_through_threaded_and_event_driven_modules(workers: int) -> None:
    with pipeline(workers).launch() as run:
        eventually(lambda: run.state("sink")["value"] == 3.0, what="1.5 * 2 at the sink")
        stats = eventually(lambda: (s := run.stats()).links["scale.y->sink.x"].values >= 5
                           and s, what="a few values")
    assert stats.modules["src"].steps > 0
    assert stats.modules["scale"].events > 0
    assert stats.modules["src"].cpu > 0 and stats.modules["scale"].cpu > 0
    link = stats.links["scale.y->sink.x"]
    assert link.transport == ("shm" if workers == 0 else "memory")
    assert link.values > 0 and link.rate > 0
    assert 0 <= link.latency < 0.5


def test_a_link_inside_one_process_gives_the_reader_a_copy() -> None:
    """A writer that changes a list or an array right after writing it changes nothing
    its reader in the same process got (the reader's array is read-only too)."""
    system = System("one-process", workers=1)
    system.add("lists", ListScribbler)
    system.add("list_sink", ListSink)
    system.add("arrays", ArrayReuser)
    system.add("array_sink", ArraySink)
    system.link("lists.out", "list_sink.x")
    system.link("arrays.out", "array_sink.x")
    with system.launch() as run:
        eventually(lambda: run.state("list_sink")["received"] >= 50
                   and run.state("array_sink")["sums_ok"] >= 20, what="values in")
        assert {link.transport for link in run.stats().links.values()} == {"memory"}
        assert run.state("list_sink")["scribbled"] == 0
        array_sink = run.state("array_sink")
    assert array_sink["scribbled"] == 0 and array_sink["writable"] is False


def test_stats_are_typed_records_with_a_json_form() -> None:
    with pipeline().launch() as run:
        # each worker answers for itself, a moment apart: wait for both counts
        stats = eventually(lambda: (s := run.stats()).links["scale.y->sink.x"].values >= 2
                           and s.modules["src"].outputs.get("out", 0) >= 2 and s,
                           what="a few values")
    assert isinstance(stats, SystemStats) and stats.system == "pipe"
    assert isinstance(stats.modules["scale"], ModuleStats)
    assert stats.modules["scale"].cls == f"{Scale.__module__}:Scale"
    assert isinstance(stats.modules["scale"].inputs["x"], InputStats)
    assert stats.modules["src"].inputs == {} and set(stats.modules["src"].outputs) == {"out"}
    assert isinstance(stats.links["src.out->scale.x"], LinkStats)
    node = stats.nodes["local"]
    assert node == NodeStats(up=True, rtt=0.0, address=None, cpu=node.cpu,
                             memory_available=node.memory_available,
                             memory_total=node.memory_total, spare_workers=node.spare_workers)
    assert node.cpu is not None and node.memory_total is not None
    assert node.spare_workers in (0, 1, 2)          # (the two booting in the background)
    plain = stats.to_json()
    text = json.dumps(plain, allow_nan=False)          # NaN (no latency yet) is null
    assert json.loads(text)["links"]["scale.y->sink.x"]["values"] >= 2
    assert plain["modules"]["src"]["inputs"] == {} and plain["failures"] == []


def test_a_nodes_cpu_is_its_busy_share_over_the_last_second_whoever_asks(
        monkeypatch) -> None:
    """A node's CPU reading (``stats().nodes[n].cpu``) is its busy share over the last
    whole second, sampled by the node whoever asks: two callers asking in turn, 10 ms
    apart, both read a load busy 50 ms of every 100 ms as half. Before, each reading
    covered the time since the previous one, by anyone: they read 0 or 100 (an agent
    polling it read a steady half load as 86, 0, 0, 100, 0 ... when another client
    asked too)."""
    began = time.monotonic()
    times = collections.namedtuple("times", "user idle")

    def cpu_times(percpu: bool = False) -> list[tuple[float, float]]:
        """CPU 0 busy the first half of every 0.1 s since ``began``."""
        elapsed = time.monotonic() - began
        periods, into = divmod(elapsed, 0.1)
        busy = periods * 0.05 + min(into, 0.05)
        return [times(busy, elapsed - busy)]
    monkeypatch.setattr(resources.psutil, "cpu_times", cpu_times)
    meter = resources.ResourceMeter([0])
    readings: dict[str, list[float]] = {"agent": [], "command line": []}
    while time.monotonic() - began < 1.6:
        for asker in readings:
            if time.monotonic() - began > 1.1:      # (a whole second measured by then)
                readings[asker].append(meter.sample().cpu)
            time.sleep(0.01)
    assert all(45.0 <= cpu <= 55.0 for said in readings.values() for cpu in said), readings
    meter.close()


def test_the_failures_kept_are_the_newest_each_dated(caplog: pytest.LogCaptureFixture) -> None:
    """Before, a launcher's or node's failures were kept for good, undated: a long run
    with a flapping node grew its list (sent with every report) without end, and a
    line said what went wrong but not when."""
    failures = FailureLog(logging.getLogger("test"))
    with caplog.at_level(logging.ERROR, logger="test"):
        for number in range(FAILURES_KEPT + 5):
            assert failures.add(f"failure {number}") == f"failure {number}"
    lines = failures.lines()
    assert len(lines) == FAILURES_KEPT
    assert [line.split(" ", 2)[2] for line in lines[:2]] == ["failure 5", "failure 6"]
    assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d failure 104", lines[-1])
    assert caplog.messages[-1] == "failure 104"          # the log has its own time


def test_stats_failures_merge_the_launchers_and_every_nodes_lines_in_the_order_they_happened(
        monkeypatch) -> None:
    """The launcher's lines and each node's are one history, oldest first (a merge
    that only joined the lists put the launcher's first, whenever they happened). The
    clock the lines are dated by is set per line, so no second need pass."""
    stamp = ["2030-01-01 10:00:00"]
    monkeypatch.setattr("pb3a.stats.time", types.SimpleNamespace(strftime=lambda _: stamp[0]))
    system = System("dated").node("a").node("b")
    system.add("sink", Last, node="a")
    with system.launch() as run:
        launcher, nodes = run._launcher, run._launcher.nodes
        for second, log, text in [(1, nodes["a"].failures, "on a, first"),
                                  (2, launcher.failures, "at the launcher, second"),
                                  (3, nodes["b"].failures, "on b, third"),
                                  (4, launcher.failures, "at the launcher, fourth"),
                                  (5, nodes["a"].failures, "on a, fifth")]:
            stamp[0] = f"2030-01-01 10:00:0{second}"
            log.add(text)
        lines = run.stats().failures
    assert [line.split(" ", 2)[2] for line in lines] == [
        "on a, first", "at the launcher, second", "on b, third", "at the launcher, fourth",
        "on a, fifth"], lines


@pytest.mark.parametrize("workers", [0, 1])
def test_queue_link_keeps_order_without_loss_or_duplicates(workers: int) -> None:
    n = 100_000
    system = System("bulk", workers=workers)
    system.add("src", Burst, state={"limit": n})
    system.add("dst", Collector)
    system.link("src.out", "dst.x", policy=f"queue:{n}")
    with system.launch() as run:
        state = eventually(lambda: (s := run.state("dst"))["received"] == n and s, timeout=60,
                           what=f"{n} values")
        link = run.stats().links["src.out->dst.x"]
    assert state["last"] == n
    assert state["out_of_order"] == 0 and state["duplicates"] == 0
    assert link.drops == 0 and link.values == n


def test_queue_overflow_drops_oldest_and_counts_it() -> None:
    system = System("overflow")
    system.add("src", Burst, state={"limit": 2000})
    system.add("dst", Collector, state={"delay": 0.002})
    system.link("src.out", "dst.x", policy="queue:10")
    with system.launch() as run:
        def settled():
            link = run.stats().links["src.out->dst.x"]
            return link.values == 2000 and link.pending == 0 and link
        link = eventually(settled, timeout=30, what="all values handled")
        state = run.state("dst")
    assert link.drops > 0
    assert state["received"] + link.drops == 2000
    assert state["out_of_order"] == 0 and state["duplicates"] == 0
    assert state["last"] == 2000          # the newest value survives; the oldest were dropped


def test_latest_policy_gives_the_newest_value() -> None:
    system = System("latest")
    system.add("src", Counter, state={"limit": 500}, period=0.0)
    system.add("dst", Collector)
    system.link("src.out", "dst.x", policy="latest")
    with system.launch() as run:
        state = eventually(lambda: (s := run.state("dst"))["last"] == 500 and s, what="500")
    assert state["out_of_order"] == 0 and state["duplicates"] == 0
    assert state["received"] <= 500


def test_large_arrays_arrive_read_only_and_intact() -> None:
    system = System("arrays")
    system.add("src", ArraySource)
    system.add("dst", ArraySink)
    system.link("src.out", "dst.x")
    with system.launch() as run:
        state = eventually(lambda: (s := run.state("dst"))["sums_ok"] >= 20 and s, what="arrays")
    assert state["writable"] is False and state["owned"] == 0     # views of the ring


def test_state_read_and_live_edit() -> None:
    with pipeline().launch() as run:
        assert run.state("scale")["gain"] == 2.0
        run.set_state("scale", gain=5.0)
        assert run.state("scale")["gain"] == 5.0
        eventually(lambda: run.state("sink")["value"] == 7.5, what="1.5 * 5 at the sink")
        with pytest.raises(Exception, match=r"no state 'gian' \(did you mean 'gain'\?\); "
                           r"its state is: gain, setups"):
            run.set_state("scale", gian=1.0)
        with pytest.raises(ModuleNotFound, match="nope"):
            run.state("nope")
        with pytest.raises(ValueError, match=r"nothing to set.*\{'timeout': 3.0\}"):
            run.set_state("scale", timeout=3.0)         # (the call's deadline, no field)


def test_a_live_edit_of_the_wrong_kind_is_refused_and_an_int_for_a_float_is_made_one() -> None:
    """``set_state("scale", gain="2.5")`` from a program was set as given, and the module
    then failed at every value (the command line refused it). A value not of its field's
    kind is a failure naming the field, nothing set; an int for a float field is made a
    float, as an output's write makes it."""
    with pipeline().launch() as run:
        run.set_state("scale", gain=5.0)
        # said as the module says it, with no worker's name or exception's in front
        with pytest.raises(RuntimeFailure) as refused:
            run.set_state("scale", gain="2.5", setups=7)
        assert str(refused.value) == ("module 'scale': state 'gain' takes a number (it is "
                                      "5.0), got '2.5'; nothing was set")
        assert run.state("scale")["setups"] == 1                  # nothing was set
        with pytest.raises(RuntimeFailure) as refused:
            run.set_state("scale", gian=3.0)
        assert str(refused.value).startswith("module 'scale': Scale has no state 'gian' "
                                             "(did you mean 'gain'?); its state is: ")
        run.set_state("scale", gain=4)
        gain = run.state("scale")["gain"]
        assert gain == 4.0 and type(gain) is float
        eventually(lambda: run.state("sink")["value"] == 6.0, what="1.5 * 4 at the sink")
        assert run.stats().modules["scale"].errors == 0


def test_a_value_its_class_refuses_is_refused_live_naming_the_module_and_nothing_set() -> None:
    """A class says what it refuses of its state (``state_problems``), and ``set_state``
    asks it before setting anything: only a ``set_state`` of the class's own could refuse
    a value, and ``pb3a check`` and the State Editor knew nothing of it. From a program
    the refusal names the module, as the module says it; on the instance it is a
    ``StateRefused`` (a ValueError) listing each value."""
    pump = Pump()
    with pytest.raises(StateRefused) as refused:
        pump.set_state({"rate": 9.0, "valve": "ajar"})
    assert refused.value.problems == ["Pump's rate must be from 0 to 5 l/s, got 9.0",
                                      "Pump's valve is 'open' or 'closed', got 'ajar'"]
    assert isinstance(refused.value, ValueError)
    assert (pump.rate, pump.valve) == (1.0, "closed")             # nothing was set
    with System("plant").add("p", Pump).launch() as run:
        with pytest.raises(RuntimeFailure) as refused:
            run.set_state("p", rate=2.0, valve="ajar")
        assert str(refused.value) == ("module 'p': Pump's valve is 'open' or 'closed', got "
                                      "'ajar'; nothing was set")
        assert run.state("p") == {"rate": 1.0, "valve": "closed"}
        run.set_state("p", rate=2, valve="open")                   # what it takes is set
        assert run.state("p") == {"rate": 2.0, "valve": "open"}


def test_a_state_problems_that_fails_live_is_a_refusal_naming_it_and_nothing_set() -> None:
    """A class's ``state_problems`` is the user's code: one that raised as a live
    ``set_state`` asked it came back as the worker's failure ("worker ...:
    ZeroDivisionError: ..."), where ``pb3a check`` says it as a problem of the class. It is
    a refusal now, in the check's words: naming the class, the hook and what it raised,
    nothing set, and the module runs on and takes what its hook passes."""
    with pytest.raises(StateRefused, match=r"Fragile.state_problems raised ZeroDivisionError"):
        Fragile().set_state({"rate": 0.0})
    with System("plant").add("f", Fragile).launch() as run:
        with pytest.raises(RuntimeFailure) as refused:
            run.set_state("f", rate=0.0)
        assert str(refused.value) == (
            "module 'f': sample_modules:Fragile.state_problems raised ZeroDivisionError: float "
            "division by zero (given {'rate': 0.0}): fix it to return what it refuses, as a "
            "list of texts; nothing was set")
        assert run.state("f") == {"rate": 1.0}
        run.set_state("f", rate=2.0)
        assert run.state("f") == {"rate": 2.0}
        assert run.stats().modules["f"].errors == 0


def test_a_module_past_its_class_s_rule_is_still_edited_moved_and_restarted() -> None:
    """A module's own state, given back (a move, a ``last-state`` restart), is no edit
    for its class to judge, and an edit is refused only what it brings: a module whose
    steps had taken a field past its class's rule could not be moved (put back where it
    ran, started fresh, its state lost), nor restarted (failed), and every edit of
    another field was refused naming that field."""
    system = System("drifting")
    system.node("a")
    system.node("b")
    system.add("d", Drifter, node="a", restart="last-state")
    with system.launch(checkpoint_s=0.2) as run:
        eventually(lambda: run.state("d")["count"] > 3, what="the count past 3")
        run.set_state("d", gain=2.0)
        with pytest.raises(RuntimeFailure, match=r"count must be at most 3, got 1000; "):
            run.set_state("d", count=1000)
        before = run.state("d")["count"]
        run.migrate("d", to="b")
        assert run.state("d")["count"] >= before and run.state("d")["gain"] == 2.0
        eventually(lambda: run.state("d")["count"] > before + 200, timeout=10,
                   what="two seconds of steps, checkpointed")
        pid, at_kill = run.stats().modules["d"].pid, run.state("d")["count"]
        os.kill(pid, signal.SIGKILL)
        # (its new worker's pid is known as it starts, before the module runs again)
        eventually(lambda: run.stats().modules["d"].pid not in (None, pid)
                   and run.stats().modules["d"].status == "running", timeout=20,
                   what="d restarted")
        assert run.state("d")["count"] > at_kill - 100      # (a checkpoint, not 0)


def test_what_a_library_module_refuses_is_refused_live_and_on_add_and_nothing_set() -> None:
    """The library's modules refused values in a ``set_state`` of their own: live, the
    refusal came back as the worker's failure ("worker ...: ValueError: ..."), and an
    ``add`` with such a value started the module, whose setup failed. Their classes say
    it in ``state_problems`` now: a refusal naming the module and the value, nothing set,
    the module running on; an ``add`` refused before anything starts. A rule relating
    two fields judges an edit against the value the module has of the other."""
    system = System("junction").add("sensors", JunctionSensors).add("control", GapOut)
    with system.launch() as run:
        with pytest.raises(RuntimeFailure) as refused:
            run.set_state("sensors", lane_capacity=0)
        assert str(refused.value) == ("module 'sensors': JunctionSensors's lane_capacity must "
                                      "be a whole number of vehicles, 1 or more, got 0; "
                                      "nothing was set")
        run.set_state("control", min_green_s=2.0)
        run.set_state("control", max_green_s=3.0)    # (against its 2 s, not the class's 5)
        with pytest.raises(RuntimeFailure) as refused:
            run.set_state("control", min_green_s=4.0, passage_s=1.0)
        assert str(refused.value) == ("module 'control': GapOut's max_green_s (3.0) must be "
                                      "at least min_green_s (4.0); nothing was set")
        state = run.state("control")
        assert (state["min_green_s"], state["max_green_s"], state["passage_s"]) == (2.0, 3.0, 4.0)
        with pytest.raises(ConfigError, match="JunctionSensors's lane_capacity must be a whole "
                                              "number of vehicles, 1 or more, got -1"):
            run.add("more", JunctionSensors, state={"lane_capacity": -1})
        assert set(run.stats().modules) == {"sensors", "control"}
        assert run.state("sensors")["lane_capacity"] == 200
        assert run.stats().modules["sensors"].errors == 0


def test_swap_keeps_ports_and_state_and_runs_setup_again() -> None:
    with pipeline().launch() as run:
        run.set_state("scale", gain=4.0)
        eventually(lambda: run.state("sink")["value"] == 6.0, what="1.5 * 4")
        kept = run.swap("scale", FastScale)
        assert "gain" in kept
        eventually(lambda: run.state("sink")["value"] == 7.0, what="1.5 * 4 + 1 after swap")
        state = run.state("scale")
        assert state["gain"] == 4.0 and state["setups"] == 2
        with pytest.raises(ConfigError, match="str"):
            run.swap("scale", Offset)
        assert run.stats().modules["scale"].cls.endswith("FastScale")
        run.add("off", Offset)                  # a new link is checked as a swap is
        links = set(run.stats().links)
        for change in (run.link, run.relink):
            with pytest.raises(ConfigError, match="incompatible types"):
                change("src.out", "off.x")
        assert set(run.stats().links) == links


class TextPeriod(Module):
    period = "0.01"

    def step(self) -> None:
        pass


class TextCounter(Counter):
    period = "0.01"


def test_a_swap_to_a_class_with_other_ports_says_the_way_that_works() -> None:
    """A swap to a class without the module's ports was refused with no way out ("Counter
    lacks the inputs x that Scale has"); the refusal says the way that works, which
    does: a module of the new class added beside it, linked, the old one removed."""
    with pipeline().launch() as run:
        with pytest.raises(ConfigError) as refused:
            run.swap("scale", Counter)
        assert refused.value.problems[0] == (
            "swap scale: Counter lacks the inputs x that Scale has")
        assert refused.value.problems[-1] == (
            "swap scale: a swap keeps the module's ports and links; to run "
            "sample_modules:Counter in its place, add it beside scale (pb3a add ADDR "
            "NEWNAME sample_modules:Counter, or add()), feed its inputs and read its outputs "
            "(pb3a relink ADDR FROM TO for each, or link() and relink()), then remove scale "
            "(pb3a remove ADDR scale, or remove())")
        assert run.stats().modules["scale"].cls.endswith(":Scale")
        run.add("counter", Counter, state={"limit": 3})
        run.relink("counter.out", "sink.x")
        run.remove("scale")
        eventually(lambda: run.state("sink")["value"] == 3.0, what="the counter's 3")
        with pytest.raises(ConfigError) as refused:     # (a class refused of itself, its
            run.swap("counter", TextCounter)            # ports fitting: no way about them)
        assert len(refused.value.problems) == 1 and "period = '0.01'" in str(refused.value)


class NegativePeriod(TextPeriod):
    period = -1
    restart = "always"


def test_a_class_s_own_period_and_restart_are_checked_too() -> None:
    """Checked only where the configuration gave them: a class's own ``period = "0.01"``
    or ``-1`` passed, and its step thread died after one step (or waited for good),
    the module shown running with no error; ``restart = "always"`` passed too."""
    system = System("class-values").add("text", TextPeriod).add("negative", NegativePeriod)
    problems, at = system.check(), f"tests/test_runtime.py:{sys._getframe().f_lineno - 1}"
    text, negative = f"{__name__}:TextPeriod", f"{__name__}:NegativePeriod"
    assert problems == [
        f"{at}: system 'class-values' [modules.text]: {text} has period = '0.01': a class's "
        "period is None (no steps, only on_input) or a number of seconds from 0 to 1e+07",
        f"{at}: system 'class-values' [modules.negative]: {negative} has period = -1: a "
        "class's period is None (no steps, only on_input) or a number of seconds from 0 to "
        "1e+07",
        f"{at}: system 'class-values' [modules.negative]: {negative} has restart = 'always': "
        "a class's restart is one of 'never', 'fresh', 'last-state'"], problems
    ticking = System("swap-to-bad").add("tick", Counter, period=0.01)
    with ticking.launch() as run:
        with pytest.raises(ConfigError, match=r"swap tick: .*TextPeriod has period = '0\.01'"):
            run.swap("tick", TextPeriod)
        with pytest.raises(ConfigError, match="NegativePeriod has period = -1"):
            run.add("late", NegativePeriod)
        assert set(run.stats().modules) == {"tick"}


class EventsOnly(Module):
    """A period of its class's own, and no step() for it (the check leaves a class's own
    period be: a base class may set one for subclasses that step)."""

    x = Input(int, policy="queue:1000")
    period = 0
    heard = 0

    def on_input(self, port) -> None:
        self.heard += len(port.read_all())


def test_a_period_for_a_class_with_no_step_is_refused_and_none_is_stepped() -> None:
    """``period = 0`` on an event-driven module passed, and it stepped an empty step()
    as fast as it could: 3 million steps in 3 s, most of a core, and its input's latency
    from 60 µs to 5 ms."""
    refused = System("needless").add("src", Counter, period=0.01).add(
        "scale", "examples.pipeline:Scale", period=0).link("src.out", "scale.x")
    assert refused.check() == [
        f"tests/test_runtime.py:{sys._getframe().f_lineno - 3}: system 'needless' "
        "[modules.scale]: period = 0 is given, but examples.pipeline:Scale has no step() for "
        "it to call: leave period out, and it runs on_input as values come"]
    system = System("no-steps").add("src", Counter, period=0.002).add("ear", EventsOnly)
    system.link("src.out", "ear.x")
    with system.launch() as run:
        with pytest.raises(ConfigError, match=r"module late: period = 0\.5 is given, but "
                                              r"examples\.pipeline:Scale has no step\(\)"):
            run.add("late", "examples.pipeline:Scale", period=0.5)
        eventually(lambda: run.state("ear")["heard"] > 100, what="values at ear")
        figures = run.stats().modules["ear"]
    assert figures.steps == 0, figures          # (no step thread: nothing to call)


class Silent(Module):
    """Counter's output, and no step()."""

    out = Output(int)
    count = 0


def test_a_swap_to_a_class_with_no_step_stops_stepping_at_the_same_period() -> None:
    """The step thread went on at the module's own period after a swap to a class with
    no step(), calling its empty step() (at period 0, most of a core)."""
    with System("swapped-still").add("c", Counter, period=0.001).launch() as run:
        eventually(lambda: run.stats().modules["c"].steps > 10, what="steps")
        run.swap("c", Silent)
        before = run.stats().modules["c"].steps
        run.wait(0.3)                           # (300 steps, had it gone on)
        assert run.stats().modules["c"].steps <= before + 1


class Weights(Module):
    """State of the kinds a file cannot write: an array, a tuple, a float32."""

    weights = np.zeros(4)
    limits = (-1.0, 1.0)
    gain = np.float32(1.0)

    def setup(self) -> None:
        self.weights += 1                     # (a list: TypeError at every setup)
        self.kinds = [type(self.weights).__name__, str(self.weights.dtype),
                      type(self.limits).__name__, type(self.gain).__name__]


def test_a_configured_state_is_given_to_the_module_as_the_types_its_class_holds(
        tmp_path) -> None:
    """A file's list for an array field reached the module a list (``self.weights +=
    1`` failed at once), a list for a tuple a list, a number for a float32 a Python
    float: TOML has no arrays, tuples or float32s."""
    (tmp_path / "weighed.toml").write_text(
        'name = "weighed"\n[modules.w]\nclass = "test_runtime:Weights"\n'
        "state = { weights = [[1, 2], [3, 4]], limits = [0, 2], gain = 3 }\n")
    with System.load(tmp_path / "weighed.toml").launch() as run:
        state = run.state("w")
    assert state["kinds"] == ["ndarray", "float64", "tuple", "float32"]
    assert state["weights"].tolist() == [[2.0, 3.0], [4.0, 5.0]]
    assert state["limits"] == (0.0, 2.0) and state["gain"] == 3.0


def test_a_module_that_defines_step_but_has_no_period_is_told_it_never_steps(
        caplog) -> None:
    """The newcomer's trap: ``step`` written, ``period`` forgotten. The module showed
    running, 0 steps, and nothing said why."""
    class Forgetful(Module):
        def step(self) -> None:
            pass

    with System("forgetful").add("idle", Forgetful).launch() as run:
        eventually(lambda: "never called" in caplog.text, what="the warning")
        assert run.stats().modules["idle"].status == "running"
    assert "module 'idle': Forgetful defines step() but has no period, so step() is " \
        "never called: give the class or the module a period" in caplog.text


def test_a_swapped_in_class_steps_at_its_own_period_unless_the_module_was_given_one(
        ) -> None:
    # (the old period was kept: an event-driven module swapped for a class that steps
    # every 10 ms never stepped, and the remedy agent's swap of a consumer failed)
    class Listener(Module):
        x = Input(int, policy="queue:1000")
        heard = steps_run = 0

        def on_input(self, port) -> None:
            self.heard += len(port.read_all())

        def step(self) -> None:
            self.steps_run += 1

    class Stepper(Listener):
        period = 0.01

    system = System("periods")
    system.add("src", Counter, period=0.002)
    system.add("ear", Listener)
    system.add("own", Listener, period=0.02)          # a period of its own
    system.add("given", Stepper, period=0.01)         # given, as its class's
    system.link("src.out", "ear.x")
    system.link("src.out", "own.x")
    with system.launch() as run:
        run.swap("ear", Stepper)
        eventually(lambda: run.state("ear")["steps_run"] > 10, what="the new class stepping")
        assert run.topology().modules["ear"].period == 0.01
        run.swap("ear", Listener)                       # steps no more: events only
        run.swap("own", Stepper)                        # keeps its own 20 ms
        before = run.state("ear")                       # (its state kept: its count)
        eventually(lambda: run.state("ear")["heard"] > before["heard"] + 100,
                   what="values at ear")
        assert run.state("ear")["steps_run"] <= before["steps_run"] + 1   # (one begun)
        eventually(lambda: run.state("own")["steps_run"] > 10, what="own stepping")
        assert run.topology().modules["own"].period == 0.02
        run.swap("given", Listener)                     # (it was taken for the class's)
        assert run.topology().modules["given"].period == 0.01
        assert run.configuration()["system"]["modules"]["given"]["period"] == 0.01
        run.restart("ear")                              # the swapped class's period
        eventually(lambda: run.state("ear")["heard"] > 100, what="values after the restart")
        assert run.state("ear")["steps_run"] == 0


def test_a_swap_keeps_the_configured_state_the_new_class_has_and_a_restart_uses_it() -> None:
    system = System("swap-restart")
    system.add("src", FloatSource, state={"value": 1.5})
    system.add("scale", Scale, state={"gain": 3.0})
    system.add("sink", Last)
    system.link("src.out", "scale.x")
    system.link("scale.y", "sink.x")
    with system.launch() as run:
        eventually(lambda: run.state("sink")["value"] == 4.5, what="1.5 * 3")
        run.swap("scale", FastScale)                    # a subclass: 'gain' stays configured
        assert run.configuration()["system"]["modules"]["scale"]["state"] == {"gain": 3.0}
        run.swap("scale", Shift)                        # no 'gain': it is configured no more
        eventually(lambda: run.state("sink")["value"] == 2.5, what="1.5 + 1 after the swap")
        folded = run.configuration()
        assert "state" not in folded["system"]["modules"]["scale"] and not folded["problems"]
        assert validate(read_description(folded["system"], "configuration()")) == []
        run.set_state("scale", offset=2.0)
        eventually(lambda: run.state("sink")["value"] == 3.5, what="1.5 + 2")
        run.restart("scale")                            # fresh: the class's offset again
        eventually(lambda: run.state("sink")["value"] == 2.5, what="1.5 + 1 after restart")
        assert {"src.out->scale.x", "scale.y->sink.x"} <= set(run.stats().links)


class Tallies(Module):
    """Not ``MapMaker``: ``updates`` is a method here, no state to set on it."""

    period = 0.005

    def updates(self) -> int:
        return 0


def test_a_swap_keeps_the_state_the_module_made_as_it_ran() -> None:
    """State made in ``setup`` and ``step`` (``grid``, ``updates``, which ``state()``
    reports) was dropped by a swap to a new version, silently (kept: the class's
    fields only). It is kept, but where the new class declares the name as something
    else (a method)."""
    with System("swap-made").add("mapper", MapMaker).launch() as run:
        eventually(lambda: run.state("mapper").get("updates", 0) > 20, what="steps")
        before = run.state("mapper")
        kept = run.swap("mapper", MapMakerV2)
        after = run.state("mapper")
        eventually(lambda: run.state("mapper")["grid"][1, 1] > 0, what="the new body")
        assert kept == ["grid", "pid", "setups", "updates"]
        assert after["updates"] >= before["updates"] > 20 and after["setups"] == 2
        assert after["grid"][0, 0] >= before["grid"][0, 0] > 20
        assert sorted(run.swap("mapper", Tallies)) == ["grid"]      # not its method
        assert sorted(run.state("mapper")) == ["grid"]


def test_a_restart_put_back_keeps_the_state_the_module_made_as_it_ran(monkeypatch) -> None:
    """A restart that cannot start the module again puts it back as it ran: its state
    made at run time was refused there (a name the new instance lacks), and it was
    lost, links and all."""
    with System("restart-made").add("mapper", MapMaker).launch() as run:
        eventually(lambda: run.state("mapper").get("updates", 0) > 20, what="steps")
        executor = run._launcher.nodes["local"]
        real_call = type(executor).call
        failures: list[str] = []

        def flaky(self, worker, op, *args, **kwargs):   # the new instance cannot start
            if op == "start" and "mapper" in worker and not failures:
                failures.append(worker)
                raise RuntimeFailure(f"worker {worker!r} died")
            return real_call(self, worker, op, *args, **kwargs)
        monkeypatch.setattr(type(executor), "call", flaky)
        with pytest.raises(RuntimeFailure, match="put back as it ran, with its state"):
            run.restart("mapper")
        state = run.state("mapper")
        assert failures and state["updates"] > 20 and state["grid"][0, 0] > 20
        eventually(lambda: run.state("mapper")["updates"] > state["updates"],
                   what="steps again")


def test_a_module_being_restarted_is_still_listed_by_a_look_at_the_system(
        monkeypatch) -> None:
    """Looks wait for no change, and a restart dropped the module from the launcher's
    tables between its stop and its new start: ``stats()`` then left it out, and
    ``topology()`` with it, as if it had been removed."""
    with pipeline().launch() as run:
        eventually(lambda: run.state("sink")["value"] is not None, what="values")
        executor = run._launcher.nodes["local"]
        real_add = type(executor).add_module
        held, go = threading.Event(), threading.Event()

        def slow(self, spec, **kwargs):     # the new instance, held as it is made
            if spec.name == "scale":
                held.set()
                assert go.wait(30.0)
            return real_add(self, spec, **kwargs)
        monkeypatch.setattr(type(executor), "add_module", slow)
        restarting = threading.Thread(target=run.restart, args=("scale",), daemon=True)
        restarting.start()
        try:
            assert held.wait(10.0)
            stats, topology = run.stats(timeout=2.0), run.topology(timeout=2.0)
        finally:
            go.set()
            restarting.join(30.0)
        assert stats.modules["scale"].change == "restart scale", stats.modules
        assert "scale" in topology.modules
        assert run.stats().modules["scale"].change == ""


def test_a_restart_whose_put_back_fails_too_leaves_no_trace_of_the_module(tmp_path) -> None:
    """A restart keeps the module's spec from its stop to its new start; when neither
    the new instance nor the one put back could be made, the spec stayed: the module,
    said to be no longer in the system, could be neither added again ("runs already")
    nor removed (KeyError)."""
    flag = tmp_path / "gone"
    cls = type("Gone", (FailsToMake,), {"flag": str(flag), "__module__": __name__})
    with System("ghost").add("frag", cls).launch() as run:
        eventually(lambda: run.state("frag")["count"] > 3, what="steps")
        flag.touch()
        with pytest.raises(RuntimeFailure, match="putting it back failed too"):
            run.restart("frag")
        with pytest.raises(ModuleNotFound):
            run.where("frag")
        assert "frag" not in run.stats().modules
        flag.unlink()
        run.add("frag", cls)
        eventually(lambda: run.state("frag")["count"] > 3, what="steps again")


def test_a_restart_that_cannot_start_the_module_again_puts_it_back_as_it_ran(
        monkeypatch) -> None:
    with pipeline().launch() as run:
        run.set_state("scale", gain=5.0)
        eventually(lambda: run.state("sink")["value"] == 7.5, what="1.5 * 5")
        launcher = run._launcher
        spec = launcher.specs["scale"]
        # a configured state the class lacks is refused before anything stops
        launcher.specs["scale"] = dataclasses.replace(spec, state={"gian": 1.0})
        pid = run.stats().modules["scale"].pid
        with pytest.raises(ConfigError, match=r"restart scale: .*has no state 'gian'"):
            run.restart("scale")
        launcher.specs["scale"] = spec
        assert run.stats().modules["scale"].pid == pid
        executor = launcher.nodes["local"]
        real_call = type(executor).call
        failures: list[str] = []

        def flaky(self, worker, op, *args, **kwargs):   # the new instance cannot start
            if op == "start" and "scale" in worker and len(failures) < limit:
                failures.append(worker)
                raise RuntimeFailure(f"worker {worker!r} died")
            return real_call(self, worker, op, *args, **kwargs)
        monkeypatch.setattr(type(executor), "call", flaky)
        limit = 1
        with pytest.raises(RuntimeFailure, match="put back as it ran, with its state and "
                                                 "its links"):
            run.restart("scale")
        assert failures and run.state("scale")["gain"] == 5.0      # as it ran, not fresh
        assert {"src.out->scale.x", "scale.y->sink.x"} <= set(run.stats().links)
        seen = run.state("sink")["seen"]
        eventually(lambda: run.state("sink")["seen"] > seen + 5, what="values through again")
        assert run.stats().modules["scale"].status == "running"
        limit = 3                                       # putting it back fails too
        with pytest.raises(RuntimeFailure, match="no longer in the system"):
            run.restart("scale")
        modules, links = run.stats().modules, run.stats().links
        assert "scale" not in modules and not [key for key in links if "scale" in key]
        assert run.events()[-1].kind == "module_removed"
        monkeypatch.undo()
        run.add("scale", Scale)                         # it may be added again
        run.link("src.out", "scale.x")
        run.link("scale.y", "sink.x")
        eventually(lambda: run.state("sink")["value"] == 3.0, what="1.5 * 2 again")


def test_relink_moves_an_input_to_another_output() -> None:
    system = pipeline()
    system.add("other", FloatSource, state={"value": 10.0})
    with system.launch() as run:
        eventually(lambda: run.state("sink")["value"] == 3.0, what="3.0")
        run.relink("other.out", "scale.x")
        eventually(lambda: run.state("sink")["value"] == 20.0, what="10 * 2 after relink")
        links = run.stats().links
        assert "other.out->scale.x" in links and "src.out->scale.x" not in links
        with pytest.raises(ConfigError, match="no output"):
            run.relink("src.nope", "scale.x")


def test_relink_of_a_queue_link_keeps_order_and_loses_nothing() -> None:
    n = 20_000
    system = System("relink-order")
    system.add("a", Burst, state={"limit": n})
    system.add("dst", Collector)
    system.add("b", Counter, state={"limit": 0}, period=None)
    system.link("a.out", "dst.x", policy=f"queue:{n}")
    with system.launch() as run:
        eventually(lambda: run.state("dst")["received"] >= n // 4, what="some values")
        run.relink("a.out", "dst.x", policy=f"queue:{n}")     # re-wire the same pair live
        state = eventually(lambda: (s := run.state("dst"))["received"] == n and s, timeout=60,
                           what="every value")
    assert state["out_of_order"] == 0 and state["duplicates"] == 0 and state["last"] == n


def test_add_and_remove_modules_while_running() -> None:
    with pipeline().launch() as run:
        run.add("probe", Last)
        run.link("scale.y", "probe.x")
        eventually(lambda: run.state("probe")["value"] == 3.0, what="value at the new module")
        with pytest.raises(ConfigError, match="relink"):
            run.link("src.out", "probe.x")
        run.remove("sink")
        assert "sink" not in run.stats().modules
        with pytest.raises(ModuleNotFound):
            run.state("sink")
        seen = run.state("probe")["seen"]
        eventually(lambda: run.state("probe")["seen"] > seen, what="flow goes on")


def test_add_refuses_what_a_configuration_may_not_say_and_starts_nothing() -> None:
    """``add`` (also an agent's spawn and ``pb3a add``) checks as the compiler does: every
    problem in one ``ConfigError``, before anything starts."""
    system = System("add-checked").node("a").node("b")
    system.add("src", FloatSource, node="a", group="g")
    with system.launch() as run:
        before = set(run.stats().modules)
        with pytest.raises(ConfigError) as caught:
            run.add("bad.name", Last, period=-1.0, restart="sometimes", group=5,
                    state={"valu": 1.0})
        problems = caught.value.problems
        for words in ("bad module instance name 'bad.name'",
                      "period must be a number of seconds from 0",
                      "restart must be one of", "bad group name 5", "has no state 'valu' "
                      "(did you mean 'value'?)"):
            assert [p for p in problems if words in p and p.startswith("module bad.name: ")], \
                (words, problems)
        for options, words in [({"period": "fast"}, "period must be"),
                               ({"group": "g", "node": "b"},
                                "group 'g' would span nodes 'a' (src) and 'b' (probe)"),
                               ({"group": "a.b"}, "bad group name 'a.b'"),
                               ({"state": [1]}, "state must be a table"),
                               ({"fallback": ["b"]}, 'fallback = ["b"] is used only when the '
                                'module is restarted elsewhere, and restart is "never" by '
                                'default')]:
            with pytest.raises(ConfigError) as caught:
                run.add("probe", Last, **options)
            assert any(words in p for p in caught.value.problems), caught.value.problems
        assert set(run.stats().modules) == before
        assert run.configuration()["problems"] == []
        run.add("kit/probe", Last, node="a", group="g")       # a macro path is fine
        # node b's env module runs on b, given no node (it ran on the first node, a)
        with pytest.raises(ConfigError, match=r"module env-b: env-b is node b's env module"
                                              r".*placed on node 'a'"):
            run.add("env-b", Environment, node="a")
        run.add("env-b", Environment)
        assert run.where("env-b") == "b"
        run.link("src.out", "kit/probe.x")
        eventually(lambda: run.state("kit/probe")["seen"] > 0, what="values at kit/probe")


def test_nested_macros_run_with_exported_ports() -> None:
    system = System("macros")
    system.add("src", FloatSource, state={"value": 1.0})
    system.add("m", Outer)
    system.add("sink", Last)
    system.link("src.out", "m.x")
    system.link("m.y", "sink.x")
    with system.launch() as run:
        eventually(lambda: run.state("sink")["value"] == 12.0, what="1 * 2 * 3 * 2")
        names = set(run.stats().modules)
    assert {"m/chain/a", "m/chain/b", "m/tail"} <= names


def test_macro_class_exports_resolve_in_single_use() -> None:
    system = System("chain")
    system.add("src", FloatSource, state={"value": 2.0})
    system.add("c", Chain)
    system.add("sink", Last)
    system.link("src.out", "c.x")
    system.link("c.y", "sink.x")
    with system.launch() as run:
        eventually(lambda: run.state("sink")["value"] == 12.0, what="2 * 2 * 3")
        # at run time the macro's own name is not a module (the error names its modules),
        # but a link reaches it through its exports as in the configuration
        with pytest.raises(ModuleNotFound, match="it is a macro instance: name one of its "
                           "modules, c/a, c/b"):
            run.state("c")
        run.relink("c.y", "sink.x", policy="queue:4")
        assert str(run.topology().links["c/b.y->sink.x"].policy) == "queue:4"
        run.relink("c/b.y", "sink.x")


def test_an_agent_adapts_another_module_through_its_runtime() -> None:
    system = pipeline()
    system.add("agent", Doubler)
    system.add("trigger", Counter, state={"limit": 3}, period=0.05)
    system.link("trigger.out", "agent.go", policy="queue:8")
    with system.launch() as run:
        eventually(lambda: run.state("scale")["gain"] == 16.0, what="gain doubled 3 times")
        eventually(lambda: run.state("sink")["value"] == 24.0, what="the new gain in effect")


def test_swap_in_the_middle_of_a_stream_keeps_order_and_loses_nothing() -> None:
    n = 30_000
    system = System("swap-stream")
    system.add("src", Burst, state={"limit": n})
    system.add("dst", Collector, state={"delay": 0.00002})
    system.link("src.out", "dst.x", policy=f"queue:{n}")
    with system.launch() as run:
        eventually(lambda: run.state("dst")["received"] >= 1000, what="some values")
        kept = run.swap("dst", CollectorV2)
        assert {"received", "last"} <= set(kept)
        state = eventually(lambda: (s := run.state("dst"))["received"] == n and s, timeout=60,
                           what="every value")
    assert state["swapped_in"] == 1 and state["last"] == n
    assert state["out_of_order"] == 0 and state["duplicates"] == 0


def test_step_and_on_input_of_one_module_never_overlap() -> None:
    system = System("exclusive")
    system.add("src", Burst, state={"limit": 3000})
    system.add("both", Overlap)
    system.link("src.out", "both.x")
    with system.launch() as run:
        state = eventually(lambda: (s := run.state("both"))["events"] >= 100
                           and s["steps"] >= 100 and s, timeout=30, what="steps and events")
    assert state["overlaps"] == 0


def test_a_module_stepping_back_to_back_still_lets_state_requests_in() -> None:
    # Each request should wait for about one 5 ms step. Without the lock's
    # hand-over the step thread takes the lock again before a waiting request
    # wakes up: requests waited up to 50 steps, about 13 on average.
    system = System("busy")
    system.add("busy", Busy)
    with system.launch() as run:
        seen = [run.state("busy")["steps"] for _ in range(20)]
        after_edit = []
        for _ in range(20):
            run.set_state("busy", steps=0)
            after_edit.append(run.state("busy")["steps"])
    between = [b - a for a, b in itertools.pairwise(seen)]
    assert sum(between) <= 2 * len(between), between
    assert sum(after_edit) <= 2 * len(after_edit), after_edit


def test_a_module_flooded_with_events_still_lets_state_requests_in() -> None:
    """A dispatch task ran a batch of up to 256 queued events under one hold of the
    lock: with 20 ms per event a state request waited 5 s. The batch now ends when a
    request waits, and the events it did not run are run after it, none lost."""
    system = System("flooded")
    system.add("burst", Burst, state={"limit": 300})
    system.add("sink", Collector, state={"delay": 0.02})
    system.link("burst.out", "sink.x")
    with system.launch() as run:
        eventually(lambda: run.state("burst")["sent"] == 300, what="the values written")
        waits, received = [], []
        for _ in range(5):
            started = time.monotonic()
            received.append(run.state("sink", timeout=1.0)["received"])
            waits.append(time.monotonic() - started)
        assert max(waits) < 0.5 and received[-1] < 200, (waits, received)
        state = eventually(lambda: (s := run.state("sink"))["received"] == 300 and s,
                           timeout=30, what="every value handled")
    assert state["last"] == 300 and state["out_of_order"] == state["duplicates"] == 0


class _StepsAndEvents(Module):
    """Steps back to back (period 0, 1 ms each) and handles events (0.2 ms each)."""

    x = Input(int, policy="queue:100000")
    handled = 0
    steps = 0

    def step(self) -> None:
        self.steps += 1
        time.sleep(0.001)

    def on_input(self, port) -> None:
        port.read()
        time.sleep(0.0002)
        self.handled += 1


def test_a_module_stepping_back_to_back_handles_its_events_in_batches() -> None:
    """Its own step thread always waits for the lock; a batch of events ended for it
    too, so the module handled one event per step (3000 events took 3000 steps)."""
    pool = EventPool(2)
    actor = ModuleActor("both", _StepsAndEvents(), pool.submit, period=0.0)
    actor.start()
    try:
        actor.inputs["x"].deliver_many(list(range(3000)))
        eventually(lambda: actor.module.handled == 3000, timeout=30, what="every event")
        assert actor.module.steps < 1500, actor.module.steps
    finally:
        actor.stop(5.0)
        pool.close()


class _Timed(Module):
    """Notes the period it sees as it steps; a step takes ``work_s`` (a device read)."""

    period = 0.02
    work_s = 0.005
    seen = 0.0

    def step(self) -> None:
        self.seen = self.period
        time.sleep(self.work_s)


def test_a_module_sees_the_period_it_runs_at_as_its_period_and_keeps_it_out_of_its_state(
        ) -> None:
    """``self.period`` was its class's: a module given 0.1 s integrated with 0.02."""
    class Faster(_Timed):
        period = 0.01

    system = System("dt")
    system.add("given", _Timed, period=0.05, state={"work_s": 0.0})
    system.add("own", _Timed, state={"work_s": 0.0})
    with system.launch() as run:
        eventually(lambda: run.state("given")["seen"] == 0.05, what="the period given")
        eventually(lambda: run.state("own")["seen"] == 0.02, what="its class's period")
        run.swap("given", Faster)                      # keeps the period it was given
        run.set_state("given", seen=0.0)
        run.swap("own", Faster)                        # steps at the new class's
        eventually(lambda: run.state("given")["seen"] == 0.05, what="the period given")
        eventually(lambda: run.state("own")["seen"] == 0.01, what="the new class's period")
        assert "period" not in run.state("given")
    actor = ModuleActor("m", _Timed(), lambda task: task(), 0.05)
    assert actor.module.period == 0.05 and _Timed.period == 0.02
    assert "period" not in actor.module.get_state()
    assert "period" not in actor.holdings()["state"]


def test_relink_may_change_the_input_policy() -> None:
    system = System("policy")
    system.add("src", Counter, state={"limit": 0}, period=0.001)
    system.add("dst", Collector)
    system.link("src.out", "dst.x", policy="queue:1000")
    with system.launch() as run:
        eventually(lambda: run.state("dst")["received"] > 10, what="values")
        run.relink("src.out", "dst.x", policy="latest")
        link = run.stats().links["src.out->dst.x"]
        assert link.policy == "latest"
        figures = eventually(lambda: (m := run.stats().modules["dst"]).inputs["x"]
                             .policy == "latest" and m, what="the new policy in the worker")
        before = run.state("dst")["received"]
        eventually(lambda: run.state("dst")["received"] > before, what="values after relink")
    assert figures.errors == 0


def test_relink_without_a_policy_keeps_the_link_s_own() -> None:
    """It once took the input's declared policy: a lossless link relinked to another
    source became lossy without a word."""
    system = System("policy-kept")
    system.add("src", Counter, state={"limit": 0}, period=0.001)
    system.add("other", Counter, state={"limit": 0}, period=0.001)
    system.add("dst", Collector)                  # declares queue:1000000
    system.link("src.out", "dst.x", policy="lossless:8")
    with system.launch() as run:
        run.relink("other.out", "dst.x")
        assert run.stats().links["other.out->dst.x"].policy == "lossless:8"
        run.relink("src.out", "dst.x", policy="latest")        # (a policy given wins)
        assert run.stats().links["src.out->dst.x"].policy == "latest"


@pytest.mark.parametrize("workers", [0, 1])
def test_a_relinked_input_s_figures_are_its_new_link_s(workers: int) -> None:
    """They were the input's since it started: the new link showed the values of the old
    writer (903 values from a writer that wrote none), and written less received went
    negative. A move of the reader keeps them (the same link)."""
    system = System(f"relinked-figures-{workers}")
    system.node("a", workers=workers).node("b")
    system.add("src", Counter, state={"limit": 0}, period=0.001, node="a")
    system.add("quiet", Counter, state={"limit": 1, "count": 1}, node="a")   # writes none
    system.add("dst", Collector, node="a")
    system.link("src.out", "dst.x")
    with system.launch() as run:
        eventually(lambda: run.stats().links["src.out->dst.x"].values > 100, what="values")
        run.relink("quiet.out", "dst.x")
        link = run.stats().links["quiet.out->dst.x"]
        assert (link.values, link.drops, link.latency_counts) == (0, 0, {})
        run.relink("src.out", "dst.x")
        eventually(lambda: run.stats().links["src.out->dst.x"].values > 50, what="values")
        run.migrate("dst", "b")
        before = run.stats().links["src.out->dst.x"].values
        assert before > 50                        # (carried with the reader)


def test_packed_modules_fill_workers_in_declaration_order() -> None:
    system = System("packed", workers=2)
    for chain in range(4):
        system.add(f"src{chain}", FloatSource, state={"value": 1.0})
        for i in range(9):
            system.add(f"c{chain}s{i}", Scale, state={"gain": 1.0})
        system.link(f"src{chain}.out", f"c{chain}s0.x")
        for i in range(8):
            system.link(f"c{chain}s{i}.y", f"c{chain}s{i + 1}.x")
    system.add("tail", Last)
    system.link("c3s8.y", "tail.x")
    with system.launch() as run:
        eventually(lambda: run.state("tail")["value"] == 1.0, what="the end of the last chain")
        stats = run.stats()
    assert len({m.pid for m in stats.modules.values()}) == 2
    transports = [link.transport for link in stats.links.values()]
    assert transports.count("shm") <= 1            # only a chain cut by the split


def test_an_agent_spawns_links_and_removes_modules() -> None:
    system = pipeline()
    system.add("agent", Spawner)
    system.add("trigger", Counter, state={"limit": 1}, period=0.05)
    system.link("trigger.out", "agent.go")
    with system.launch() as run:
        eventually(lambda: "probe" in run.stats().modules, what="the spawned module")
        eventually(lambda: run.state("probe")["value"] == 3.0, what="values at the probe")
        assert "cannot set_state itself" in run.state("agent")["error"]
        run.set_state("trigger", limit=2)
        eventually(lambda: "probe" not in run.stats().modules, what="the probe removed")


def test_an_agent_s_spawn_takes_the_options_of_add_and_no_other() -> None:
    """``self.runtime.spawn`` took ``**options``: a misspelt one (``nod="b"``) went to
    the launcher and came back as ``Operations.add()``'s ``TypeError``. It names them,
    as ``run.add`` does, so a misspelling fails at the agent's own call."""
    from pb3a.launch.operations import Operations
    from pb3a.model.agent import RuntimeClient

    def options(function: object) -> dict[str, inspect.Parameter]:
        return {name: parameter for name, parameter in
                inspect.signature(function).parameters.items() if name != "self"}
    assert options(RuntimeClient.spawn) == options(Operations.add)
    with pytest.raises(TypeError, match="nod"):
        RuntimeClient.spawn(None, "helper", "sample_modules:Last", nod="b")


def test_an_input_may_hold_its_whole_queue_of_zero_copy_arrays() -> None:
    system = System("held")
    system.add("src", ArraySource)
    system.add("hold", ArrayHolder)
    system.link("src.out", "hold.x")
    with system.launch() as run:
        figures = eventually(lambda: (i := run.stats().modules["hold"].inputs["x"])
                             .received >= 25 and i, timeout=30, what="25 arrays")
    assert figures.pending == 10                   # ten views held in the ring at once
    assert figures.drops == figures.received - 10   # only queue overflow, no ring gaps


def test_a_driver_talks_to_a_device_served_with_serve_device() -> None:
    """The device's side of a ``Driver`` is one public call: ``serve_device(handler)``
    answers each request with what the handler returns, and what the handler raises
    fails the driver's request, naming the device and the error (it took
    ``pb3a.transport.control.ControlServer`` and ``ClusterKey.load()``, found only in a
    docstring)."""
    broken = threading.Event()

    def handler(op: str, args: dict) -> float:
        if broken.is_set():
            raise ValueError("sensor unplugged")
        return 0.5

    with serve_device(handler) as device:
        system = System("device").add("reader", DeviceReader,
                                      state={"resource": device.address})
        with system.launch() as run:
            eventually(lambda: run.state("reader")["answered"] >= 3, what="answers")
            broken.set()
            error = eventually(lambda: run.state("reader")["last_error"], what="a failure")
    assert error.startswith("DeviceReader: ") and "sensor unplugged" in error
    assert error.count(device.address) == 1, error


def test_a_request_its_driver_gave_up_on_while_the_device_was_busy_is_not_carried_out(
        ) -> None:
    """A relative move that timed out while its device was busy with an earlier request,
    asked again, was made twice: the device ran every request it had taken in, however
    long after its driver gave up on it. It drops one it has not begun within the
    driver's timeout of its coming; the driver's error says one sent may still be carried
    out."""
    moves: list[int] = []
    homing, home = threading.Event(), threading.Event()

    def handler(op: str, args: dict) -> int:
        if op == "home":
            homing.set()
            home.wait(10.0)
        else:
            moves.append(args["by"])
        return sum(moves)

    with serve_device(handler) as device:
        homer, stepper = Driver(), Driver()
        homer.resource = stepper.resource = device.address
        homer.timeout, stepper.timeout = 10.0, 0.3
        asked = threading.Thread(target=homer.request, args=("home",), daemon=True)
        asked.start()
        try:
            assert homing.wait(5.0)
            with pytest.raises(RuntimeTimeout) as timed_out:
                stepper.request("move", by=1)
            # (the device counts the 0.3 s from when the request came, a moment after
            # it was sent)
            time.sleep(0.2)
            home.set()
            asked.join(10.0)
            stepper.timeout = 5.0
            assert stepper.request("move", by=1) == 1          # asked again: moved once
        finally:
            home.set()
            homer.teardown()
            stepper.teardown()
    assert moves == [1]
    said = str(timed_out.value)
    assert said.startswith(f"Driver: {device.address} did not answer ") and "within 0.3 s" in said
    assert said.endswith("; it was sent, so the device may have begun it and carry it out "
                         "still (one it has not begun it drops): look before "
                         "asking again")


def test_a_driver_whose_device_host_does_not_resolve_says_so_at_once() -> None:
    """A ``resource`` whose host no resolver knows fails the request at once, saying so:
    each request waited its whole deadline and said the device "did not answer"."""
    harness = ModuleHarness(DeviceReader, state={
        "resource": "tcp://no-such-host.invalid:7400", "timeout": 5.0})
    try:
        started = time.monotonic()
        harness.step()
        assert time.monotonic() - started < 4.0
        error = harness.module.last_error
    finally:
        harness.close()
    assert error.startswith("DeviceReader cannot connect to tcp://no-such-host.invalid:7400: "
                            "no address is known for host 'no-such-host.invalid'"), error


def test_a_device_served_on_every_interface_gives_an_address_its_driver_takes() -> None:
    """Served on every interface (as a robot's computer reached from the LAN is), a
    device's ``address`` is one of this machine's, its default route's: it was
    ``tcp://0.0.0.0:PORT``, which the driver refused as naming every interface, and
    the launch failed."""
    ours = {entry.address for entries in psutil.net_if_addrs().values()
            for entry in entries}
    for every in ("*", "[::]"):
        with serve_device(lambda op, args: 0.5, host=every) as device:
            assert device.address.removeprefix("tcp://").rpartition(":")[0] in ours, \
                device.address
    with serve_device(lambda op, args: 0.5, host="0.0.0.0") as device:
        assert device.address.removeprefix("tcp://").rpartition(":")[0] in ours, \
            device.address
        system = System("everywhere").add("reader", DeviceReader,
                                          state={"resource": device.address})
        with system.launch() as run:
            eventually(lambda: run.state("reader")["answered"] >= 3, what="answers")


def test_an_agent_s_runtime_call_carries_its_timeout_and_refuses_a_bad_one() -> None:
    """As the launcher's calls, each of ``self.runtime``'s takes a ``timeout``: the
    operation's deadline, which the request carries, and the agent's wait for it."""
    asked = []
    client = RuntimeClient("me", lambda op, args, timeout: asked.append((op, args, timeout)))
    client.state("other", timeout=2)
    client.set_state("other", {"timeout": 3.0}, timeout=1)       # (a field named so)
    client.spawn("new", "pkg:Cls", period=0.1)
    assert asked == [
        ("state", {"name": "other", "timeout": 2.0}, 2),
        ("set_state", {"values": {"timeout": 3.0}, "name": "other", "timeout": 1.0}, 1),
        ("add", {"cls": "pkg:Cls", "period": 0.1, "name": "new"}, None)]
    for bad in (-1, float("nan"), "1", float("inf")):
        with pytest.raises((TypeError, ValueError), match=r"runtime\.state: timeout must be"):
            client.state("other", timeout=bad)
    assert len(asked) == 3


def test_an_agent_s_set_state_with_nothing_to_set_is_refused_as_the_api_s() -> None:
    """``self.runtime.set_state("drv", timeout=0.25)``, meant to set the driver's
    ``timeout``, set nothing and raised nothing, where the API's same call is refused."""
    asked = []
    client = RuntimeClient("me", lambda op, args, timeout: asked.append((op, args, timeout)))
    with pytest.raises(ValueError, match=r"set_state\('drv'\): nothing to set.*"
                       r"\{'timeout': 3.0\}"):
        client.set_state("drv", timeout=0.25)
    with pytest.raises(ValueError, match="nothing to set"):
        client.set_state("drv", {})
    assert asked == []


def test_an_agent_naming_itself_or_the_macro_it_is_in_is_refused_in_one_way() -> None:
    """An agent cannot read, set, swap or remove itself, nor remove the macro it is in:
    each is a ``ValueError`` at its own call, nothing sent, in the same words; it may
    migrate both, ask where it runs and set its own period. Before, removing itself
    was a ``ValueError`` ("change its own attributes directly") and removing its macro
    a ``RuntimeFailure`` from the launcher."""
    asked = []
    client = RuntimeClient("kit/agent", lambda op, args, timeout: asked.append(op))
    for call, said in (
            (lambda: client.remove("kit"), "remove kit: agent 'kit/agent' is in it: an agent "
             "cannot remove itself or the macro it is in (the stop would wait for the very "
             "call that asks it; it may migrate itself)"),
            (lambda: client.remove("kit/agent"), "remove kit/agent: agent 'kit/agent' is it: "
             "an agent cannot remove itself or the macro it is in (the stop would wait for "
             "the very call that asks it; it may migrate itself)"),
            (lambda: client.swap("kit/agent", Scale), "swap kit/agent: agent 'kit/agent' is "
             "it: an agent cannot swap itself (the swap would wait for the very call that "
             "asks it; it may migrate itself)"),
            (lambda: client.set_state("kit/agent", seen=0, period=1.0), "set_state "
             "kit/agent: agent 'kit/agent' is it: an agent cannot set_state itself (it "
             "sets its own attributes directly; of the runtime's, only its period, alone)"),
            (lambda: client.state("kit/agent"), "state kit/agent: agent 'kit/agent' is it: "
             "an agent cannot state itself (it reads its own attributes directly)")):
        with pytest.raises(ValueError, match=f"^{re.escape(said)}$") as refused:
            call()
        assert type(refused.value) is ValueError
    assert asked == []
    client.migrate("kit", "b")
    client.where("kit/agent")
    client.set_state("kit/agent", period=1.0)   # (the step asking is not held by it)
    client.remove("kit2")                   # (another macro whose name begins as its own)
    client.swap("kit/other", Scale)
    assert asked == ["begin_migration", "where", "set_state", "remove", "swap"]


def test_the_figures_of_a_node_without_remote_links_make_no_bridge() -> None:
    """A report read every remote link's losses from the node's bridge, which it made on
    first use even with none: a thread, sockets, and the cluster key loaded (one that
    another user could read failed the report, and stats() showed no module)."""
    with System("no-bridge").add("scale", Scale).launch() as run:
        assert "scale" in run.stats().modules
        assert run._launcher.nodes["local"]._bridge is None


def test_a_closed_system_leaves_nothing_open_in_the_process_that_launched_it() -> None:
    """A process that launches and closes one system after another (a notebook, a test
    harness, a controller) kept two descriptors of the forkserver's and a pidfd for each
    worker, a restarted one's and a spare's too, until its garbage collector happened to
    run: with it off, or little garbage made meanwhile, they piled up. Each close gives
    back every descriptor and thread its system had in this process."""
    def launched_and_closed(restart: bool) -> None:
        system = System("closed-clean")
        system.add("steady", Steady, restart="fresh")
        system.add("other", Steady)
        with system.launch() as run:
            eventually(lambda: run.stats().nodes["local"].spare_workers == 2,
                       what="the spare workers booted")
            if restart:
                pid = eventually(lambda: run.stats().modules["steady"].pid, what="a pid")
                os.kill(pid, signal.SIGKILL)
                eventually(lambda: run.state("steady")["pid"] not in (0, pid),
                           what="steady restarted in a new worker")

    me = psutil.Process()
    launched_and_closed(restart=False)         # (what the first launch sets up stays)
    files, threads = me.num_fds(), set(threading.enumerate())
    gc.disable()
    try:
        for restart in (False, True, False):
            launched_and_closed(restart)
            assert me.num_fds() <= files, f"{me.num_fds()} open descriptors, {files} before"
            eventually(lambda: set(threading.enumerate()) <= threads,
                       what="the system's threads ended",
                       context=lambda: [t.name for t in set(threading.enumerate()) - threads])
    finally:
        gc.enable()


def test_a_period_set_live_is_slept_after_the_last_step_not_stepped_at_once() -> None:
    """A period set anew is slept after the last step, as every period is: the step
    thread at the new period stepped at once, here right after the step that set it (a
    controller's ``dt = self.period`` integrated a whole second over a few ms). A
    shorter one, already due, steps at once."""
    system = System("repaced").add("slow", SlowsItself)
    with system.launch() as run:
        eventually(lambda: len(run.state("slow")["stamps"]) >= 4, timeout=10,
                   what="a step at the period the agent set")
        third, fourth = run.state("slow")["stamps"][2:4]
        assert fourth - third >= 0.95, f"{fourth - third:.3f} s after the step that set it"
        run.set_state("slow", period=0.05)
        changed = time.monotonic()
        last = run.state("slow")["stamps"][-1]
        eventually(lambda: run.state("slow")["stamps"][-1] > last, timeout=5,
                   what="a step at the shorter period")
        assert time.monotonic() - changed < 0.9     # (not at the 1 s period's turn)


def test_a_module_s_period_is_set_live_and_kept_across_a_move_and_a_restart() -> None:
    """A running module's rate could not be changed (``set_state(period=...)`` was "no
    state 'period'"): an agent that slows a sensor under load had to remove it and add
    it again, links and all. It steps at the new period from then on, sees it as
    ``self.period``, and keeps it when moved and when its worker is restarted."""
    system = System("retimed")
    system.node("a")
    system.node("b")
    system.add("paced", Paced, node="a", restart="fresh")
    # (1 s: a period set live is taken at the module's next turn, a period after its
    # last step, and self.period then seen; at 10 s the test waited 10 s for it)
    system.add("retimer", Retimer, node="a", state={"to": 1.0})

    def steps_in(run, seconds: float) -> int:
        before = run.stats().modules["paced"].steps
        run.wait(seconds)
        return run.stats().modules["paced"].steps - before

    with system.launch() as run:
        eventually(lambda: run.state("retimer")["done"] == "yes", what="the agent's change")
        assert run.topology().modules["paced"].period == 1.0
        assert run.stats().modules["paced"].period == 1.0
        table = format_table(run.stats())                       # (pb3a status, pb3a run)
        assert re.search(r"^paced +a +\d+ +running +1 ", table, re.M), table
        eventually(lambda: run.state("paced")["seen_period"] == 1.0, timeout=15,
                   what="self.period")
        assert steps_in(run, 0.5) <= 1                      # (at 0.01 s: about 50)
        with pytest.raises(ConfigError, match="period must be a number of seconds"):
            run.set_state("paced", period=-1.0)
        with pytest.raises(ConfigError, match="period must be a number of seconds"):
            run.set_state("paced", period="fast")
        with pytest.raises(ConfigError, match="period must be a number of seconds"):
            run.set_state("paced", period=np.True_)
        run.set_state("paced", period=np.float32(0.5))     # (computed with numpy: refused)
        assert type(run.topology().modules["paced"].period) is float
        run.set_state("paced", period=0.2, count=0)         # with a field: both set
        assert run.state("paced")["count"] <= 1
        run.migrate("paced", to="b")
        assert run.topology().modules["paced"].period == 0.2
        assert steps_in(run, 1.0) <= 7                      # (at 0.01 s: about 100)
        pid = run.stats().modules["paced"].pid
        os.kill(pid, signal.SIGKILL)
        eventually(lambda: (m := run.stats().modules["paced"]).pid not in (None, pid)
                   and m.steps > 0, timeout=20, what="the restarted module stepping")
        assert steps_in(run, 1.0) <= 7
        assert run.state("paced")["seen_period"] == 0.2


def _gaps_after(stamps: list[float], since: float) -> list[float]:
    """The time between the steps that began after ``since``, one to the next."""
    after = [stamp for stamp in stamps if stamp > since]
    return [b - a for a, b in itertools.pairwise(after)]


def test_a_module_that_assigns_its_own_period_steps_at_it_and_keeps_it_moved_and_restarted(
        ) -> None:
    """``self.period = 0.3`` in a running module's step changed nothing the runtime
    stepped by: it slept its old period (0.01 s) on, nothing said. It steps at the new
    one from its next sleep on, as at a period set live with ``set_state``; the
    launcher's record of it learns it, so that a move and a restart of its worker keep
    it; ``stats`` and `pb3a status` show it."""
    system = System("self-retimed")
    system.node("a")
    system.node("b")
    system.add("paced", SetsItsPeriod, node="a", restart="fresh")

    def gaps_after(run, since: float) -> list[float]:
        return eventually(lambda: len(gaps := _gaps_after(run.state("paced")["stamps"],
                                                          since)) >= 2 and gaps,
                          timeout=15, what="three steps")

    with system.launch() as run:
        run.set_state("paced", to=0.3)
        assigned = eventually(lambda: run.state("paced")["assigned_at"], what="the assignment")
        gaps = gaps_after(run, assigned)
        assert min(gaps) >= 0.25, f"steps {gaps} s apart after self.period = 0.3 (0.01 before)"
        eventually(lambda: run.topology().modules["paced"].period == 0.3,
                   what="the launcher's record of the period")
        assert run.stats().modules["paced"].period == 0.3
        table = format_table(run.stats())
        assert re.search(r"^paced +a +\d+ +running +0\.3 ", table, re.M), table
        run.migrate("paced", to="b")
        moved = time.monotonic()
        assert run.topology().modules["paced"].period == 0.3
        gaps = gaps_after(run, moved)
        assert min(gaps) >= 0.25, f"steps {gaps} s apart on node b (0.01 s: its old period)"
        assert run.stats().modules["paced"].node == "b"
        pid = run.stats().modules["paced"].pid
        os.kill(pid, signal.SIGKILL)
        eventually(lambda: (m := run.stats().modules["paced"]).pid not in (None, pid)
                   and m.steps > 0, timeout=20, what="the restarted module stepping")
        restarted = time.monotonic()
        gaps = gaps_after(run, restarted)
        assert min(gaps) >= 0.25, f"steps {gaps} s apart once restarted (fresh)"
        assert run.state("paced")["seen_period"] == 0.3
        assert run.stats().modules["paced"].period == 0.3


def test_a_period_a_module_assigns_itself_that_is_no_period_raises_value_error() -> None:
    """An assignment of ``self.period`` is checked as ``set_state(period=...)`` checks
    it, but raises ``ValueError`` at the assignment, naming the module and the value
    (it was taken as it was: a period of "fast" was no step rate, nothing said); a
    period for a module whose class has no ``step()`` is refused as set_state refuses it.
    Nothing changes: the module steps at its period before."""
    system = System("no-periods")
    system.add("m", AssignsNoPeriods, state={
        "tried": ["fast", -1.0, None, True, float("nan"), 1e300, 0.2]})
    system.add("listens", ListensOnly)
    with system.launch() as run:
        raised = eventually(lambda: len(r := run.state("m")["raised"]) == 7 and r,
                            what="the assignments")
        for said, value in zip(raised[:6], ("'fast'", "-1.0", "None", "True", "nan", "1e+300"),
                               strict=True):
            assert said.startswith(f"ValueError: module 'm': self.period = {value} is no "
                                   "period: a period is a number of seconds from 0 to 1e+07 "
                                   "(0: as fast as it can)"), said
        assert raised[6] == "", raised[6]
        assert run.state("m")["seen"] == [0.02] * 6 + [0.2]
        assert run.state("listens")["raised"] == (
            "ValueError: module 'listens': self.period = 0.05, but sample_modules:ListensOnly "
            "has no step() for a period to call (it runs on_input as values come)")
        assert run.stats().modules["listens"].period is None
        eventually(lambda: run.topology().modules["m"].period == 0.2, what="its period kept")


def test_an_event_driven_module_that_assigns_itself_a_period_is_stepped_at_it() -> None:
    """A module run on its input's values, whose class has a ``step()`` but no period,
    that gives itself one in its ``setup`` is stepped from then on, as ``set_state(name,
    period=...)`` makes it (it was never stepped: "defines step() but has no period")."""
    system = System("stepped-after-all")
    system.add("m", StepsOnceSetUp)
    with system.launch() as run:
        eventually(lambda: run.state("m")["count"] >= 3, timeout=5, what="steps")
        assert run.stats().modules["m"].period == 0.05
        eventually(lambda: run.topology().modules["m"].period == 0.05,
                   what="the launcher's record of the period")


def test_the_runtime_learns_a_module_s_periods_one_request_at_a_time_once_a_second_at_most(
        ) -> None:
    """A module's worker tells the runtime that the module assigned itself a period with
    one request under way at a time per module, one per ``every`` (a second) at most,
    however often the module assigns (an adaptive rate: each assignment was a request,
    an event and a round trip to the worker, 56 a second); an assignment made meanwhile
    is told once both allow, and none is told for nothing."""
    asked: list[tuple[str, float]] = []
    answers: list = []

    def ask(name: str, answered) -> bool:
        asked.append((name, time.monotonic()))
        answers.append(answered)
        return True

    teller = PeriodTeller(ask, every=0.3)
    for _ in range(100):
        teller.tell("a")
    teller.tell("b")                        # (another module's goes at once)
    assert [name for name, _ in asked] == ["a", "b"]
    eventually(lambda: time.monotonic() - asked[0][1] > 0.4, what="a's time again")
    assert len(asked) == 2                  # (a's first is still under way)
    answers.pop(0)(True, None)
    assert asked[-1][0] == "a" and len(asked) == 3      # (its time passed: at once)
    teller.tell("a")
    answers.pop(0)(True, None)              # (b's)
    answers.pop(0)(False, "refused")        # (said in a warning)
    assert len(asked) == 3                  # (a's next waits for its time)
    eventually(lambda: len(asked) == 4, timeout=5, what="a's last assignment told")
    assert asked[3][0] == "a" and asked[3][1] - asked[2][1] >= 0.3
    answers.pop(0)(True, None)
    time.sleep(0.5)                         # (nothing owed: nothing more)
    assert len(asked) == 4


def test_a_failed_swap_leaves_the_module_at_its_period_whatever_the_new_one_assigned(
        ) -> None:
    """A swap to a class whose ``setup`` assigns itself a period, then raises, fails, and
    the old instance runs on at its own period: it was left at the new one's (1.5 s for
    0.01 s), and the launcher's record learned it too."""
    with System("swap-fails").add("m", SetsItsPeriod).launch() as run:
        with pytest.raises(RuntimeFailure, match="cannot start"):
            run.swap("m", AssignsThenFails)
        steps = run.stats().modules["m"].steps
        eventually(lambda: run.stats().modules["m"].steps >= steps + 20, timeout=5,
                   what="steps at 0.01 s again")
        assert run.topology().modules["m"].period == 0.01
        assert run.stats().modules["m"].period == 0.01
        assert run.state("m")["seen_period"] == 0.01


def test_a_failed_swap_whose_new_setup_assigned_a_period_steps_the_old_instance_not() -> None:
    """A swap whose new class's ``setup`` assigns a period and then raises leaves the
    old instance as it was: the assignment woke (or started) a step thread, which then
    stepped the event-driven module put back once, where it never steps."""
    class OnEvents(Module):
        x = Input(float)

        def on_input(self, port: str) -> None:
            pass
    actor = ModuleActor("m", OnEvents(), lambda task: task(), None)
    actor.start()
    try:
        with pytest.raises(SetupError):
            actor.swap(AssignsThenFails(), None)
        for thread in [t for t in threading.enumerate() if t.name == "pb3a-step-m"]:
            thread.join(5)                    # (a step thread woken: done with its step)
        assert (type(actor.module), actor.period, actor.steps) == (OnEvents, None, 0)
    finally:
        assert actor.stop(1.0)


def test_a_module_s_last_assignment_of_its_period_is_what_it_and_its_record_keep() -> None:
    """A module that assigns itself 0.03, then 0.04, then 0.03 again steps at 0.03 and
    its record says 0.03: the request telling 0.03 was carried out after the module had
    assigned 0.04, and set it back to 0.03, which its assignment of 0.03 then took for
    nothing new, and the request telling 0.04 came last (kept at 0.04)."""
    with System("reassigned").add("m", Reassigns).launch() as run:
        run.set_state("m", go=True)
        eventually(lambda: len(run.state("m")["after"]) >= 20, timeout=10,
                   what="steps after its last assignment")
        assert set(run.state("m")["after"]) == {0.03}, run.state("m")["after"]
        eventually(lambda: run.topology().modules["m"].period == 0.03,
                   what="the record of its period")
        assert run.stats().modules["m"].period == 0.03


def test_a_module_that_sets_its_period_at_every_step_is_no_event_and_no_flood() -> None:
    """An adaptive rate, a new period at every step, is learned by the launcher's record
    once a second at most and is no event (each assignment was a ``module_retimed``
    event, 56 a second, and the manager's pages got the whole structure at each; the
    event log kept three minutes); ``stats`` shows the period."""
    with System("adaptive").add("m", AdaptsItsRate).launch() as run:
        eventually(lambda: run.state("m")["count"] >= 100, what="100 steps")
        assert not [event for event in run.events(0) if event.kind == "module_retimed"]
        assert run.stats().modules["m"].period in (0.01, 0.011)
        eventually(lambda: run.topology().modules["m"].period == 0.011,
                   what="the record learning the period")


def test_a_moved_module_keeps_the_period_it_set_itself_not_its_teardown_s(caplog) -> None:
    """A module that set its own period (0.25) a moment before it was moved steps at it
    on its new node, and its record learns it; what its teardown assigns (its class's
    period, in a move and in a removal) is its instance's alone: the runtime was told,
    and the move kept the teardown's period, and a removal logged that the module was
    not found."""
    system = System("moved-self-timed")
    system.node("a")
    system.node("b")
    system.add("m", SlowsTwiceResets, node="a")
    with system.launch() as run:
        eventually(lambda: run.state("m")["seen_period"] == 0.25, what="its own 0.25")
        run.migrate("m", to="b")
        moved = time.monotonic()
        gaps = eventually(lambda: len(gaps := _gaps_after(run.state("m")["stamps"],
                                                          moved)) >= 2 and gaps,
                          timeout=15, what="three steps on node b")
        assert min(gaps) >= 0.2, f"steps {gaps} s apart on node b (0.25 s, its own)"
        eventually(lambda: run.topology().modules["m"].period == 0.25,
                   what="the record of its period")
        assert run.stats().modules["m"].period == 0.25
        with caplog.at_level(logging.DEBUG, logger="pb3a.module"):
            run.remove("m")
            run.wait(1.5)
        assert not [r for r in caplog.records if r.levelno >= logging.WARNING
                    and "period" in r.getMessage()], caplog.text
        assert not [event for event in run.events(0) if event.kind == "module_retimed"]


class _AdaptsEveryStep(Module):
    """Assigns itself another period at each step, noting the thread each step ran on."""

    period = 0.002
    count = 0
    threads: set = set()

    def step(self) -> None:
        self.count += 1
        self.threads.add(threading.current_thread())
        self.period = 0.002 if self.count % 2 else 0.003


def test_a_module_that_sets_its_period_at_every_step_is_stepped_on_one_thread() -> None:
    """A period set anew, here by the module itself at every step, is taken by its step
    thread at its next turn: a new step thread was started for each (an OS thread per
    assignment, 128 for 128), the one before ending when it woke."""
    actor = ModuleActor("adapts", _AdaptsEveryStep(), lambda task: task(), 0.002)
    actor.start()
    try:
        eventually(lambda: actor.module.count >= 50, what="50 steps")
    finally:
        assert actor.stop()
    assert len(actor.module.threads) == 1, f"{len(actor.module.threads)} step threads"


class _InitSetsPeriod(Module):
    """Assigns itself a period in its ``__init__``, before anything runs it."""

    def __init__(self) -> None:
        super().__init__()
        self.period = 0.5

    def step(self) -> None:
        pass


class _InitCopiesClassPeriod(Module):
    """Its ``__init__`` assigns itself its class's period (a dataclass's field does)."""

    period = 0.1

    def __init__(self) -> None:
        super().__init__()
        self.period = type(self).period

    def step(self) -> None:
        pass


class _Rated(Module):
    """Its ``set_state`` derives its period from its state's ``rate``."""

    period = 0.1
    rate = 10.0

    @reflective
    def set_state(self, state: dict) -> None:
        super().set_state(state)
        if "rate" in state:
            self.period = 1.0 / state["rate"]

    def step(self) -> None:
        pass


def test_a_period_assigned_before_the_module_runs_is_said_to_set_nothing(caplog) -> None:
    """A period a module assigns itself before it runs (its ``__init__``, its
    ``set_state`` given its configured state) is replaced by the one the runtime runs it
    at, the configuration's or its class's (a period given to the module): it was,
    silently. A warning says so, and what to do instead; not for the period given, nor
    for its class's (``self.period = type(self).period``, a dataclass's field: it warned
    at every add)."""
    rated = _Rated()
    rated.set_state({"rate": 50.0})                 # (as its worker gives its state)
    with caplog.at_level(logging.WARNING, logger="pb3a.module"):
        actor = ModuleActor("early", _InitSetsPeriod(), lambda task: task(), 0.1)
        ModuleActor("rated", rated, lambda task: task(), 0.1)
    assert actor.module.period == 0.1 and rated.period == 0.1
    assert [r.getMessage() for r in caplog.records] == [
        "module 'early': self.period = 0.5 was assigned before it ran (in __init__ or its "
        "state), which sets nothing: the module runs at the period given to it (0.1 s: the "
        "configuration's, add's or swap's, else its class's); give its class that period, "
        "or assign self.period in setup()",
        "module 'rated': self.period = 0.02 was assigned before it ran (in __init__ or its "
        "state), which sets nothing: the module runs at the period given to it (0.1 s: the "
        "configuration's, add's or swap's, else its class's); give its class that period, "
        "or assign self.period in setup()"]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pb3a.module"):
        ModuleActor("same", _InitSetsPeriod(), lambda task: task(), 0.5)
        ModuleActor("copies", _InitCopiesClassPeriod(), lambda task: task(), 0.5)
    assert not caplog.records


class _ListensWithAPeriod(Module):
    """Handles its input's values only (no ``step()``), though its class sets a period."""

    period = 0.5
    x = Input(int)

    def on_input(self, port) -> None:
        port.read()


def test_a_class_with_a_period_but_no_step_shows_no_period_in_the_stats() -> None:
    """A period its class sets steps nothing in a module with no ``step()``: ``stats()``
    says None and the status table "-", as for any module run on events only (they
    showed 0.5, and no step thread stepped it)."""
    with System("listens").add("m", _ListensWithAPeriod).launch() as run:
        assert run.stats().modules["m"].period is None
        table = format_table(run.stats())
        assert re.search(r"^m +local +\d+ +running +- ", table, re.M), table


class _PeriodMixin:
    """A period from a class that is no ``Module``."""

    period = 0.05


class _MixedIn(_PeriodMixin, Module):
    def step(self) -> None:
        pass


def test_a_period_from_a_mixin_or_set_on_the_class_later_is_set_live_when_assigned() -> None:
    """A class whose period comes from a class that is no ``Module`` (a mixin), or is set
    on the class once it is made, has its assignment of ``self.period`` set it live and
    checked as any: it set a plain attribute, and the module stepped at its old one."""
    class Later(Module):
        def step(self) -> None:
            pass

    Later.period = 0.02
    for cls, given in ((_MixedIn, 0.05), (Later, 0.02)):
        told: list[str] = []
        actor = ModuleActor("m", cls(), lambda task: task(), given, on_period=told.append)
        actor.module.period = 0.5
        assert (actor.period, actor.module.period, told) == (0.5, 0.5, ["m"]), cls
        with pytest.raises(ValueError, match="'fast' is no period"):
            actor.module.period = "fast"
        assert cls.period == given


class CopiesItself(Module):
    """Takes a deep copy and a pickle of itself at each step, as a snapshot."""

    period = 0.02
    out = Output(int)
    count = 0
    copied = ""

    def step(self) -> None:
        self.count += 1
        self.out.write(self.count)
        twin, thawed = copy.deepcopy(self), pickle.loads(pickle.dumps(self))
        self.copied = f"{twin.count} {thawed.count}"


def test_a_running_module_may_copy_and_pickle_itself_and_runs_on() -> None:
    """A copy is the module and its state, bound to nothing: a ``copy.deepcopy`` of a
    running module copied its worker's connections and rings, whose copies closed their
    ends as they were collected, and the worker died ("module 'c' is not running")."""
    system = System("copies")
    system.add("c", CopiesItself)
    with system.launch() as run:
        eventually(lambda: run.state("c")["count"] > 20, what="20 steps, each copying")
        count, copied = run.state("c")["count"], run.state("c")["copied"]
        assert copied and copied.split()[0] == copied.split()[1]
        eventually(lambda: run.state("c")["count"] > count + 10, what="steps go on")
        assert run.stats().modules["c"].restarts == 0


class _InterruptedAsItStarts(threading.Thread):
    def start(self) -> None:
        raise KeyboardInterrupt


def test_a_ctrl_c_as_a_background_thread_starts_leaves_the_close_clean() -> None:
    """A background thread (the watchdog, the env keeper) a Ctrl-C left unstarted was
    listed all the same, and the close's join of it raised "cannot join thread before it
    is started": ``pb3a run`` exited 1 with a traceback."""
    system = System("interrupted-start")
    system.add("c", Counter, period=0.05)
    run = system.launch()
    try:
        with pytest.raises(KeyboardInterrupt):
            run._launcher.start_background(_InterruptedAsItStarts(target=lambda: None))
    finally:
        run.close()
    assert not run.running


class Recorder(Module):
    """Writes each value it gets on a line of ``path``, a file it opens in ``setup()``
    and never closes: no ``teardown()``, as a plain Python script would have it."""

    x = Input(int, policy="queue:1000")
    path = ""
    lines = 0

    def setup(self) -> None:
        self._file = open(self.path, "a")           # noqa: SIM115 (closed as it goes)

    def on_input(self, port) -> None:
        self._file.write(f"{port.read()}\n")
        self.lines += 1


class Recorder2(Recorder):
    """``Recorder``'s next version."""


class SlottedRecorder(Recorder):
    """``Recorder`` that keeps its file in a slot, outside its ``__dict__``."""

    __slots__ = ("_file",)


def test_a_file_a_module_keeps_in_a_slot_is_written_out_as_the_system_closes(
        tmp_path) -> None:
    """The instance's attributes were dropped as it was let go, closing its files, but
    not those its class keeps in ``__slots__``: lines buffered there were lost."""
    path = tmp_path / "values.csv"
    system = System("slotted")
    system.add("src", Burst, state={"limit": 100})
    system.add("rec", SlottedRecorder, state={"path": str(path)})
    system.link("src.out", "rec.x")
    with system.launch() as run:
        eventually(lambda: run.state("rec")["lines"] == 100, what="the values written")
    assert path.read_text().split() == [str(i) for i in range(1, 101)]


def test_a_file_a_module_leaves_open_is_written_out_as_the_system_closes(tmp_path) -> None:
    """Its worker ended with os._exit, which finalizes nothing: every line it had
    buffered was lost (0 of 200 in a reviewer's run; a collection of the instance's
    cycles closes the file's layers in no set order, and lost them too). So did the
    instance a move or a swap left behind: each instance's lines are in the file."""
    path = tmp_path / "values.csv"
    system = System("left-open").node("a").node("b")
    system.add("src", Burst, state={"limit": 100}, node="a")
    system.add("rec", Recorder, state={"path": str(path)}, node="a")
    system.link("src.out", "rec.x")
    with system.launch() as run:
        eventually(lambda: run.state("rec")["lines"] == 100, what="the first values written")
        run.migrate("rec", to="b")
        run.set_state("src", limit=150)
        eventually(lambda: run.state("rec")["lines"] == 150, what="values written after")
        run.swap("rec", Recorder2)
        run.set_state("src", limit=200)
        eventually(lambda: run.state("rec")["lines"] == 200, what="every value written")
        run.add("rec2", Recorder, state={"path": str(tmp_path / "more.csv")}, node="a")
        run.link("src.out", "rec2.x")
        run.set_state("src", limit=300)
        eventually(lambda: run.state("rec2")["lines"] == 100, what="the next values written")
        run.remove("rec2")                          # (a removal, the system going on)
        assert (tmp_path / "more.csv").read_text().split() == [str(i) for i in range(201, 301)]
    assert sorted(map(int, path.read_text().split())) == list(range(1, 301))
