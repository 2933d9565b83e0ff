"""A module whose ``setup`` raises does not run: the launch, add, swap, restart or move
that started it fails, naming the module and the error, and the system is left as it
was (it ran, stepping against a device that never opened, the error only in the log)."""

from __future__ import annotations

import pytest
from conftest import eventually
from sample_modules import OpensDevice, Steady

from pb3a import RuntimeFailure, System

pytestmark = pytest.mark.timeout(60)

SAID = r"SetupError: module '{}' raised in setup: RuntimeError: device /dev/video7 not found"


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
        run.add("cam", OpensDevice)                     # mended, it may be added
        eventually(lambda: run.state("cam")["steps"] > 3, what="it steps")


class Missing(OpensDevice):
    def setup(self) -> None:
        raise RuntimeError("device /dev/video7 not found")


def test_a_swap_to_a_class_that_raises_in_setup_leaves_the_old_one_running() -> None:
    system = System("setup-swap")
    system.add("cam", OpensDevice)
    with system.launch() as run:
        eventually(lambda: run.state("cam")["steps"] > 3, what="steps")
        with pytest.raises(RuntimeFailure, match=r"module 'cam': Missing raised in setup: "
                                                 r"RuntimeError: device .* not swapped, "
                                                 r"OpensDevice runs on"):
            run.swap("cam", Missing)
        figures = run.stats().modules["cam"]
        assert figures.cls.endswith(":OpensDevice") and figures.status == "running"
        steps = run.state("cam")["steps"]
        eventually(lambda: run.state("cam")["steps"] > steps, what="the old one steps on")
        assert run.state("cam")["setups"] == 2      # its own, and again after the swap
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
