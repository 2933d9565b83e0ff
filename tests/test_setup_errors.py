"""A module whose ``setup`` raises does not run: the launch, add, swap, restart or move
that started it fails, naming the module and the error, and the system is left as it
was (it ran, stepping against a device that never opened, the error only in the log)."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import alive, eventually
from sample_modules import NoDevice, OnFlag, OpensDevice, Steady

from pb3a import Agent, Module, RuntimeFailure, RuntimeTimeout, System

pytestmark = pytest.mark.timeout(60)

SAID = r"module '{}' raised in setup: RuntimeError: device /dev/video7 not found"


def test_a_launch_whose_module_raises_in_setup_fails_naming_it() -> None:
    system = System("setup-launch")
    system.add("ok", Steady)
    system.add("cam", OpensDevice, state={"missing": True})
    with pytest.raises(RuntimeFailure, match=SAID.format("cam")):
        system.launch()


def test_an_added_module_that_raises_in_setup_is_not_added() -> None:
    system = System("setup-add")
    system.add("ok", Steady)
    with system.launch() as run:
        with pytest.raises(RuntimeFailure, match=SAID.format("cam")):
            run.add("cam", OpensDevice, state={"missing": True})
        assert "cam" not in run.stats().modules
        # refused, not failed: no module_failed, no failure kept (it said both)
        assert "module_failed" not in [event.kind for event in run.events()]
        assert run.stats().failures == []
        run.add("cam", OpensDevice)                     # mended, it may be added
        eventually(lambda: run.state("cam")["steps"] > 3, what="it steps")


class NotesTeardown(OpensDevice):
    """Notes its ``label`` in the file ``noted`` as it is torn down (its own count goes
    with it once the module is out of the system)."""

    noted = ""
    label = ""

    def teardown(self) -> None:
        super().teardown()
        with open(self.noted, "a") as noted:
            noted.write(f"{self.label}\n")


@pytest.mark.parametrize("how", ["launch", "add"])
def test_a_module_whose_setup_raised_is_not_torn_down(tmp_path: Path, how: str) -> None:
    """As a test's tearDown after a failed setUp: what ``setup`` did not open, its
    ``teardown`` must not close. The module started beside it is torn down as the
    system stops (the note is seen to work)."""
    noted = tmp_path / "torn_down"
    system = System(f"setup-{how}-teardown")
    system.add("ok", NotesTeardown, state={"noted": str(noted), "label": "ok"})
    failing = {"missing": True, "noted": str(noted), "label": "cam"}
    if how == "launch":
        system.add("cam", NotesTeardown, state=failing)
        with pytest.raises(RuntimeFailure, match=SAID.format("cam")):
            system.launch()
    else:
        with system.launch() as run, pytest.raises(RuntimeFailure,
                                                   match=SAID.format("cam")):
            run.add("cam", NotesTeardown, state=failing)
    assert noted.read_text() == "ok\n"


class Missing(OpensDevice):
    def setup(self) -> None:
        raise RuntimeError("device /dev/video7 not found")


class Refuses(OpensDevice):
    """Its own ``set_state`` wants a field ``OpensDevice`` has not."""

    def set_state(self, state: dict[str, Any]) -> None:
        self.config = dict(state["config"])


@pytest.mark.parametrize(("new", "why"), [
    (Missing, r"Missing raised in setup: RuntimeError: device .*"),
    # (its set_state raised: the old instance ran on after its teardown, its setup not
    # run again; what its teardown closed stayed closed, and every call raised)
    (Refuses, r"Refuses did not take OpensDevice's state: KeyError: 'config';")])
def test_a_swap_whose_new_class_cannot_start_leaves_the_old_one_set_up_again(new, why) -> None:
    system = System("setup-swap")
    system.add("cam", OpensDevice)
    with system.launch() as run:
        eventually(lambda: run.state("cam")["steps"] > 3, what="steps")
        with pytest.raises(RuntimeFailure, match=rf"module 'cam': {why} not swapped, "
                                                 r"OpensDevice runs on"):
            run.swap("cam", new)
        figures = run.stats().modules["cam"]
        assert figures.cls.endswith(":OpensDevice") and figures.status == "running"
        state = run.state("cam")
        assert (state["teardowns"], state["setups"]) == (1, 2)     # set up again after it
        eventually(lambda: run.state("cam")["steps"] > state["steps"],
                   what="the old one steps on")
        assert "module_swapped" not in [event.kind for event in run.events()]
        assert "module_swapped" not in [event.kind for event in run.events()]


def test_a_move_whose_setup_raises_at_the_destination_runs_at_the_source_again() -> None:
    system = System("setup-move")
    system.node("a")
    system.node("b")
    system.add("cam", OpensDevice, node="a")
    with system.launch() as run:
        eventually(lambda: run.state("cam")["steps"] > 3, what="steps")
        with pytest.raises(RuntimeFailure, match=r"migration of cam to node b failed .*"
                                                 r"raised in setup.*it runs on node a again"):
            run.migrate("cam", to="b", state={"cam": {"missing": True}})
        assert run.where("cam") == "a"
        steps = run.state("cam")["steps"]
        eventually(lambda: run.state("cam")["steps"] > steps, what="it steps on at a")


def test_a_move_whose_setup_raises_at_both_ends_leaves_the_module_failed_and_said(
        tmp_path: Path) -> None:
    """Its device unplugged, the module's setup raised at the destination and again at the
    source, where the failed move put it back: it was left "starting" for good, running
    nowhere, with no event and no failure said (and the error did not say so)."""
    unplugged = tmp_path / "unplugged"
    system = System("setup-move-both").node("a").node("b")
    system.add("cam", OpensDevice, node="a", state={"unplugged": str(unplugged)})
    with system.launch() as run:
        eventually(lambda: run.state("cam")["steps"] > 3, what="steps")
        unplugged.touch()
        with pytest.raises(RuntimeFailure, match=r"migration of cam to node b failed .*"
                                                 r"putting it back on node a failed too"):
            run.migrate("cam", to="b")
        assert run.where("cam") == "a"
        assert run.stats().modules["cam"].status == "failed"
        assert [e.subject for e in run.events() if e.kind == "module_failed"] == ["cam"]
        unplugged.unlink()
        run.restart("cam")
        steps = run.state("cam")["steps"]
        eventually(lambda: run.state("cam")["steps"] > steps, what="it steps again at a")


def test_a_value_that_came_during_a_failed_swap_is_handled_by_the_old_class(
        tmp_path: Path) -> None:
    """The new class handles no events: a value that came while it was set up waited,
    undispatched, for the next one after the old class was back."""
    flag, ready = tmp_path / "send", tmp_path / "ready"
    system = System("setup-swap-value")
    system.add("src", OnFlag, state={"flag": str(flag)})
    system.add("cam", OpensDevice, state={"ready": str(ready)})
    system.link("src.out", "cam.x")
    with system.launch() as run:
        eventually(lambda: run.state("cam")["steps"] > 3, what="steps")
        failed: list[BaseException] = []

        def swap() -> None:
            try:
                run.swap("cam", NoDevice)
            except RuntimeFailure as exc:
                failed.append(exc)
        swapping = threading.Thread(target=swap)
        swapping.start()
        eventually(ready.exists, what="NoDevice setting up")
        flag.touch()                              # one value, while NoDevice sets up
        swapping.join(20)
        assert failed and "NoDevice raised in setup" in str(failed[0])
        eventually(lambda: run.state("cam")["handled"] == 1, what="the value handled")


def test_a_setup_error_in_a_restarted_worker_fails_that_module_only(tmp_path: Path) -> None:
    """Two modules of one worker restart after it dies; one's setup raises (its device
    unplugged meanwhile): it fails, the other runs (both failed, the worker halted); and
    each restarts when asked, the failed one once its device is back."""
    unplugged = tmp_path / "unplugged"
    system = System("setup-crash-restart")
    system.add("cam", OpensDevice, restart="fresh", group="g",
               state={"unplugged": str(unplugged)})
    system.add("other", Steady, restart="fresh", group="g")
    with system.launch() as run:
        eventually(lambda: run.state("other")["count"] > 3, what="steps")
        unplugged.touch()
        os.kill(run.stats().modules["cam"].pid, signal.SIGKILL)
        modules = eventually(lambda: (m := run.stats().modules)["cam"].status == "failed"
                             and m["other"].status == "running" and m, what="the restart")
        assert modules["other"].restarts == 1
        count = run.state("other")["count"]
        eventually(lambda: run.state("other")["count"] > count, what="the other steps on")
        reason = [e for e in run.events() if e.kind == "module_failed"][-1].detail["reason"]
        assert "module 'cam' raised in setup: RuntimeError: device" in reason
        run.restart("other")
        unplugged.unlink()
        run.restart("cam")
        eventually(lambda: run.state("cam")["steps"] > 3, what="the mended module steps")


def test_a_module_whose_setup_outlasts_its_add_never_runs(tmp_path: Path,
                                                          monkeypatch) -> None:
    """An ``add`` whose start runs out of time (setup still going) removes the module:
    it does not start stepping once its setup returns, unknown to the system (it did,
    in the worker it shared)."""
    from pb3a.node.executor import Executor
    real = Executor.call

    def call(self, worker, op, timeout=10.0, /, **args):
        return real(self, worker, op, 1.0 if op == "start" else timeout, **args)
    monkeypatch.setattr(Executor, "call", call)
    steps = tmp_path / "steps"
    system = System("setup-outlasts")
    system.add("other", Steady, group="g")
    with system.launch() as run:
        with pytest.raises(RuntimeTimeout, match=r"slow's setup did not finish .* not added"):
            run.add("slow", SlowToOpen, group="g", state={"steps_to": str(steps)})
        assert "slow" not in run.stats().modules
        # its setup ends 2 s after it began: a step would follow within 10 ms
        eventually(lambda: SlowToOpen.done(steps), timeout=10,
                   what="the removed module's setup over")
        count = run.state("other")["count"]     # (10 ms steps: a while after its setup)
        eventually(lambda: run.state("other")["count"] > count + 10, what="time passing")
        assert "step" not in steps.read_text()
    assert steps.read_text().endswith("set up\nclosed\n")     # what it opened, closed


def test_an_add_whose_setup_outlasts_its_timeout_is_a_timeout_and_adds_nothing(
        tmp_path: Path) -> None:
    """An ``add`` (an agent's ``spawn`` too) whose module's ``setup`` outlasts its
    timeout raises ``RuntimeTimeout`` saying that the module was not added: no event,
    its worker stopped, and the same add with time enough adds it once (it raised a
    ``RuntimeFailure`` blaming a module stuck in "worker 'local/m-helper'", which did
    not say whether it was added)."""
    system = System("setup-times-out")
    system.add("agent", SpawnsSlowly, state={"pid_to": str(tmp_path / "spawned")})
    with system.launch() as run:
        began = time.monotonic()
        with pytest.raises(RuntimeTimeout) as raised:
            run.add("helper", SetsUpSlowly, state={"pid_to": str(tmp_path / "helper")},
                    timeout=1.0)
        assert time.monotonic() - began < 4.0          # (not the start's 10 s)
        assert str(raised.value) == ("helper's setup did not finish within 1 s; it was not "
                                     "added: give the call a longer timeout")
        said = eventually(lambda: run.state("agent")["said"], what="the agent's spawn")
        assert said == ("RuntimeTimeout: spawned's setup did not finish within 1 s; it was "
                        "not added: give the call a longer timeout")
        assert not {"helper", "spawned"} & set(run.topology().modules)
        assert not {"helper", "spawned"} & set(run.stats().modules)
        assert [event.kind for event in run.events()] == []
        for worker in ("helper", "spawned"):       # (the process its setup ran in)
            pid = int((tmp_path / worker).read_text())
            eventually(lambda pid=pid: not alive(pid), what=f"{worker}'s worker stopped")
        run.add("helper", SetsUpSlowly, timeout=10.0)
        assert [(event.kind, event.subject) for event in run.events()] == [
            ("module_added", "helper")]
        assert run.state("helper")["set_up"]


class SetsUpSlowly(Module):
    """Its ``setup`` notes its process id (in the file ``pid_to``, if given), then takes
    2 s."""

    period = 0.05
    pid_to = ""
    set_up = False

    def setup(self) -> None:
        if self.pid_to:
            Path(self.pid_to).write_text(str(os.getpid()))
        time.sleep(2.0)
        self.set_up = True


class SpawnsSlowly(Agent):
    """At its first step spawns a ``SetsUpSlowly`` as ``spawned``, giving it 1 s:
    ``said``, what that raised ("added" if nothing)."""

    period = 0.05
    pid_to = ""
    said = ""

    def step(self) -> None:
        if self.said:
            return
        try:
            self.runtime.spawn("spawned", SetsUpSlowly, state={"pid_to": self.pid_to},
                               timeout=1.0)
            self.said = "added"
        except Exception as exc:
            self.said = f"{type(exc).__name__}: {exc}"


class SlowToOpen(OpensDevice):
    """Its setup takes 2 s, then notes that it returned (in ``steps_to``)."""

    def setup(self) -> None:
        import time
        time.sleep(2.0)
        with open(self.steps_to, "a") as notes:
            notes.write("set up\n")

    def teardown(self) -> None:
        with open(self.steps_to, "a") as notes:
            notes.write("closed\n")

    @staticmethod
    def done(path: Path) -> bool:
        return path.exists() and "set up" in path.read_text()


class NoCamera(Steady):
    def __init__(self) -> None:
        raise RuntimeError("no camera on this machine")


class OwnState(Steady):
    """Its own state, taken by a key of its own (``kp``)."""

    def get_state(self) -> dict[str, int]:
        return {"kp": self.count}

    def set_state(self, state: dict[str, int]) -> None:
        self.count = int(state["kp"])


def test_a_module_that_cannot_be_made_or_given_its_state_is_named_with_the_step() -> None:
    """Its error named only the worker ("worker 'local-p0': KeyError: 'kp'"): not the
    module, its class, nor what was being done."""
    made = System("unmade").add("ok", Steady).add("cam", NoCamera)
    with pytest.raises(RuntimeFailure) as failure:
        made.launch()
    assert str(failure.value) == (
        f"module 'cam': making its class {__name__}:NoCamera with no arguments failed: "
        "RuntimeError: no camera on this machine")
    given = System("unset").add("ctl", OwnState, state={"kpp": 2})
    with pytest.raises(RuntimeFailure) as failure:
        given.launch()
    assert str(failure.value) == (f"module 'ctl' ({__name__}:OwnState): setting its state "
                                  "(kpp) failed: KeyError: 'kp'")
