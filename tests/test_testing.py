"""``pb3a.testing.ModuleHarness``: a module tested on its own, through its ports."""

from __future__ import annotations

import pytest

from examples.pipeline import Scale, Ticker
from pb3a import Agent, Input, InputPort
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


def test_a_wrong_port_or_type_is_named() -> None:
    harness = ModuleHarness(Scale)
    with pytest.raises(KeyError, match="no input 'z'; its inputs: x"):
        harness.feed("z", 1.0)
    with pytest.raises(TypeError, match="port 'x' carries"):
        harness.feed("x", "one")
    assert harness.written["y"] == []


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
