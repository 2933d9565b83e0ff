"""``pb3a.testing.ModuleHarness``: a module tested on its own, through its ports."""

from __future__ import annotations

import numpy as np
import pytest

from examples.pipeline import Scale, Ticker
from pb3a import Agent, Input, InputPort, Macro, Module, Output
from pb3a.testing import ModuleHarness


def test_a_fed_value_runs_on_input_and_what_it_writes_is_kept() -> None:
    harness = ModuleHarness(Scale, state={"gain": 3.0})
    harness.feed("x", 1.5)
    harness.feed("x", 2.0)
    assert harness.written["y"] == [4.5, 6.0]
    assert harness.last("y") == 6.0


def test_steps_run_the_threaded_body() -> None:
    harness = ModuleHarness(Ticker)
    harness.step(3)
    assert harness.written["out"] == [1, 2, 3]
    assert harness.state["count"] == 3


def test_the_module_sees_the_period_it_is_given_as_a_launched_one_does() -> None:
    """A module tested in a harness saw its class's period, which a configuration may
    change: ``dt = self.period`` was tested with another dt than it ran with."""
    assert ModuleHarness(Ticker).module.period == Ticker.period
    harness = ModuleHarness(Ticker, period=0.5)
    assert harness.module.period == 0.5 and Ticker.period != 0.5
    assert "period" not in harness.state
    with pytest.raises(ValueError, match="period must be a number of seconds"):
        ModuleHarness(Ticker, period=-1)


def test_the_module_s_assignment_of_its_period_is_checked_as_a_launched_one_s() -> None:
    """``self.period = "fast"`` raised ``ValueError`` in a launched module and passed in
    a harness; it raises there too, naming the module, nothing changed, and a period
    the module may set is what it then sees."""
    harness = ModuleHarness(Ticker, period=0.5)
    harness.module.period = 0.25
    assert harness.module.period == 0.25
    with pytest.raises(ValueError, match=r"module 'Ticker': self\.period = 'fast' is no period"):
        harness.module.period = "fast"
    assert harness.module.period == 0.25
    with pytest.raises(ValueError, match=r"module 'scale': self\.period = 0\.1, but .*Scale "
                                         r"has no step"):
        ModuleHarness(Scale, name="scale").module.period = 0.1


def test_keep_holds_only_the_newest_values_of_each_output() -> None:
    harness = ModuleHarness(Ticker, keep=2)
    harness.step(5)
    assert list(harness.written["out"]) == [4, 5] and harness.last("out") == 5
    with pytest.raises(ValueError, match="keep must be at least 1"):
        ModuleHarness(Ticker, keep=0)


def test_a_wrong_port_or_type_is_named() -> None:
    harness = ModuleHarness(Scale)
    with pytest.raises(KeyError, match="no input 'z'; its inputs: x"):
        harness.feed("z", 1.0)
    with pytest.raises(TypeError, match="port 'x' carries"):
        harness.feed("x", "one")
    with pytest.raises(KeyError, match="Scale has no output 'z'; its outputs: y"):
        harness.last("z")                   # (a bare KeyError: 'z')
    assert harness.written["y"] == []
    with pytest.raises(TypeError, match=r"ModuleHarness takes a pb3a\.Module subclass, got "
                       r".*Pair.*: a macro is tested launched"):
        ModuleHarness(Pair)                 # (AttributeError: '_pb3a_bind_ports')


class Pair(Macro):
    modules = {"scale": Scale, "tick": Ticker}


class Asker(Agent):
    x = Input(float)

    def on_input(self, port: InputPort) -> None:
        self.runtime.migrate("worker", "b", wait=False)


def test_an_agent_calls_the_runtime_it_is_given() -> None:
    calls = []

    class Runtime:
        def migrate(self, name: str, to: str, *, wait: bool = True) -> None:
            calls.append((name, to, wait))

    ModuleHarness(Asker, runtime=Runtime()).feed("x", 1.0)
    assert calls == [("worker", "b", False)]
    # given none, it is told how to give one (it was told only that none ran)
    with pytest.raises(RuntimeError, match=r"in a test, give ModuleHarness a stand-in: "
                       r"runtime=\.\.\."):
        ModuleHarness(Asker).feed("x", 1.0)


class Doubler(Module):
    x = Input(np.ndarray)
    y = Output(np.ndarray)

    def on_input(self, port: InputPort) -> None:
        values = port.read()
        values *= 2                  # a value that came over a link is read-only
        self.y.write(values)


class Trail(Module):
    out = Output(list)
    period = 0.01
    trail: list = []

    def step(self) -> None:
        self.trail.append(len(self.trail))
        self.out.write(self.trail)   # the same list each time, as it is now


def test_values_cross_the_harness_as_they_cross_a_link() -> None:
    # a launched module gets a read-only copy of what it is fed, and its readers get
    # each value as it was when written; the harness must not pass what a system refuses
    fed = np.ones(3)
    harness = ModuleHarness(Doubler)
    with pytest.raises(ValueError, match="read-only"):
        harness.feed("x", fed)
    assert list(fed) == [1.0, 1.0, 1.0] and harness.written["y"] == []
    trail = ModuleHarness(Trail)
    trail.step(2)
    assert trail.written["out"] == [[0], [0, 1]]


def test_each_harness_gets_its_own_copy_of_the_state_it_is_given() -> None:
    state = {"trail": [7]}
    first, second = ModuleHarness(Trail, state=state), ModuleHarness(Trail, state=state)
    first.step()
    assert state == {"trail": [7]} and second.state["trail"] == [7]
    assert first.written["out"] == [[7, 1]]


def test_an_int_may_be_fed_to_a_float_input_as_an_int_output_may_feed_it() -> None:
    # in the pipeline Ticker's Output(int) feeds Scale's Input(float): ints arrive there
    harness = ModuleHarness(Scale, state={"gain": 2.0})
    harness.feed("x", 3)
    assert harness.written["y"] == [6.0]
    with pytest.raises(TypeError, match="port 'x' carries float, got str"):
        harness.feed("x", "3")
