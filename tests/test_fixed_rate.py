"""A module with ``fixed_rate`` steps every period from its first step's start (drift-free,
as an OROCOS periodic activity or a ROS 2 timer), where by default it sleeps its period
after each step, so that the step's own time slows it. Rates are measured from the step
start times the module records itself, over about a second, with tolerances that hold
on a loaded machine of two cores."""

from __future__ import annotations

import itertools
import re
import time
from pathlib import Path

import pytest
from conftest import eventually
from sample_modules import Chain

from pb3a import ConfigError, Module, System
from pb3a.cli.main import main
from pb3a.cli.status import format_table
from pb3a.config.folding import fold
from pb3a.worker.rate import FixedRate

PERIOD = 0.02


class Controller(Module):
    """A control loop at 50 Hz whose step takes about 5 ms (a sleep: the time a step
    takes, not the CPU it uses, is what slows a period slept after it); ``began``:
    when each step began, as the module saw it. Step number ``long_step`` (from 1)
    takes three periods."""

    period = PERIOD
    work = 0.005
    long_step = 0
    began: list[float] = []

    def step(self) -> None:
        self.began.append(time.monotonic())
        time.sleep(3 * self.period if len(self.began) == self.long_step else self.work)


class FixedController(Controller):
    """A ``Controller`` whose class asks for a fixed rate."""

    fixed_rate = True


class Overruns(FixedController):
    """A fixed-rate ``Controller`` whose tenth step takes three periods."""

    long_step = 10


class Retuned(Controller):
    """A new version of ``Controller``, for a swap (its class asks for no fixed rate)."""


class Unpaced(Module):
    """A ``step()`` and no period."""

    def step(self) -> None:
        pass


class SaysYes(Controller):
    fixed_rate = "yes"          # (no bool: refused)


def _intervals(began: list[float], skip: int = 5,
               period: float = PERIOD) -> tuple[float, int]:
    """The mean time from one step's start to the next, over the intervals that held no
    skipped period, and how many did (those of two periods or more: the next step is due
    a period after the last began at the latest, so it began a whole period late), the
    first ``skip`` steps (the start) left out. A loaded machine starves a step thread
    now and then (at a load of 10 on 2 cores, 9 or 10 periods of 60), and a fixed rate
    skips the periods it missed, counted (``overruns``): those skips are the load's;
    the steps between them keep the period (and a period slept after each step, the
    default, gives no gap of two periods here: a step takes 5 ms)."""
    gaps = [b - a for a, b in itertools.pairwise(began[skip:])]
    kept = [gap for gap in gaps if gap < 2 * period]
    return sum(kept) / len(kept), len(gaps) - len(kept)


def test_the_schedule_is_drift_free_skips_whole_late_periods_and_restarts_on_request() -> None:
    """``FixedRate`` alone: a step due at t0 + k * period whatever the last one took; a
    step late by less than a period keeps the slots (the next due at its slot); one late
    by whole periods skips them, counts them, and the next is a period after it; a
    restart (a period set anew, a pause over) counts nothing."""
    rate = FixedRate()
    assert rate.due(0.1) is None                    # the first: at once
    rate.begun(10.0, 0.1)
    assert rate.due(0.1) == pytest.approx(10.1)
    rate.begun(10.103, 0.1)                         # 3 ms late: the slot keeps its phase
    assert rate.due(0.1) == pytest.approx(10.2)
    rate.begun(10.29, 0.1)                          # late by 0.09: at once, slots kept
    assert (rate.due(0.1), rate.overruns) == (pytest.approx(10.3), 0)
    rate.begun(10.55, 0.1)                          # late by 0.25: two slots skipped
    assert (rate.due(0.1), rate.overruns) == (pytest.approx(10.65), 2)
    rate.restart()                                  # (a pause of 2 s: not the module's)
    assert rate.due(0.5) == pytest.approx(11.05)    # a new period after the last began
    rate.begun(12.6, 0.5)
    assert (rate.due(0.5), rate.overruns) == (pytest.approx(13.1), 2)
    rate.begun(13.1, 0)                             # period 0: as fast as it can
    assert rate.due(0) == pytest.approx(13.1)
    assert rate.overruns == 2


def test_a_fixed_rate_keeps_its_period_where_a_period_slept_after_each_step_is_slower(
        ) -> None:
    """A controller of period 0.02 s whose step takes 5 ms ran at 40 Hz, not 50: its
    period was slept after each step. With ``fixed_rate`` (here ``System.add``'s) its
    steps begin every 0.02 s; ``fixed_rate=False`` given to a class that asks for it
    wins, as a period given wins over the class's. ``stats()`` and ``pb3a status`` say
    which modules keep a fixed rate; ``add`` refuses a fixed_rate that is no bool,
    naming the module, and ``pb3a add --fixed-rate`` gives one."""
    system = System("rates").add("fixed", Controller, fixed_rate=True)
    system.add("slept", FixedController, fixed_rate=False)
    with system.launch() as run:
        eventually(lambda: min(len(run.state(name)["began"]) for name in ("fixed", "slept"))
                   >= 60, timeout=20, what="60 steps of each")
        (fixed, skipped), (slept, _) = (_intervals(run.state(name)["began"])
                                        for name in ("fixed", "slept"))
        stats = run.stats()
        with pytest.raises(ConfigError, match="module late: fixed_rate must be true or false"):
            run.add("late", Controller, fixed_rate="yes")
        assert main(["add", run.listen(), "late", f"{__name__}:Controller",
                     "--fixed-rate"]) == 0
        assert run.stats().modules["late"].fixed_rate
    assert abs(fixed - PERIOD) <= 0.1 * PERIOD, \
        f"fixed rate: {fixed * 1e3:.2f} ms a step, {skipped} skipped"
    assert slept >= 0.024, f"a period slept after each step: {slept * 1e3:.2f} ms a step"
    assert stats.modules["fixed"].fixed_rate and not stats.modules["slept"].fixed_rate
    table = format_table(stats)
    assert re.search(r"^fixed +local +\d+ +running( \(overruns \d+\))? +0\.02 fixed +\d+ ",
                     table, re.M), table
    assert re.search(r"^slept +local +\d+ +running +0\.02 +\d+ ", table, re.M), table


def test_an_overrunning_step_skips_the_periods_it_missed_with_no_burst_and_counts_them(
        ) -> None:
    """A fixed-rate step that takes three periods (its class's ``fixed_rate``) is not made
    up by a burst of steps: the next begins at once, the one after it a period later,
    and the two periods missed are counted as ``overruns``. A period set live then is
    kept from the next step on (due the new period after the last step began), at a
    fixed rate still."""
    with System("overrun").add("ctl", Overruns).launch() as run:
        eventually(lambda: len(run.state("ctl")["began"]) >= 25, timeout=20,
                   what="25 steps")
        began = run.state("ctl")["began"]
        stats = run.stats().modules["ctl"]
        run.set_state("ctl", period=0.05)
        changed = time.monotonic()

        def since() -> list[float]:
            return [stamp for stamp in run.state("ctl")["began"] if stamp > changed]
        eventually(lambda: len(since()) >= 15, timeout=20, what="15 steps at 0.05 s")
        retimed = since()
        table = format_table(run.stats())
    after = began[Overruns.long_step:]              # the steps after the long one
    assert after[0] - began[Overruns.long_step - 1] >= 3 * PERIOD
    assert after[1] - after[0] >= PERIOD / 2, after[:3]
    # slots after[0] + k * period: no more than four steps begin in 3.5 periods (a burst
    # made up the missed two: six)
    assert sum(after[0] <= stamp <= after[0] + 3.5 * PERIOD for stamp in after) <= 4, after
    assert stats.fixed_rate and stats.overruns >= 2, stats
    assert re.search(r"^ctl +local +\d+ +running \(overruns [1-9]\d*\) +0\.05 fixed ", table,
                     re.M), table
    interval, skipped = _intervals(retimed, skip=1, period=0.05)
    assert abs(interval - 0.05) <= 0.005, f"{interval * 1e3:.2f} ms a step, {skipped} skipped"


def test_a_fixed_rate_is_read_from_a_file_and_refused_where_it_cannot_apply(
        tmp_path: Path) -> None:
    """``fixed_rate`` sits beside ``period`` in a file's module entry (and a running
    system's ``configuration()`` writes it there); one that is no bool, one given to a
    class with no ``step()``, to a module with no period, or to a macro, and a class's
    own that is no bool are refused naming the module."""
    path = tmp_path / "rates.toml"
    path.write_text(f"""
name = "rates"

[modules.ctl]
class = "{__name__}:Controller"
fixed_rate = true

[modules.free]
class = "{__name__}:FixedController"
fixed_rate = false

[modules.own]
class = "{__name__}:FixedController"
""")
    plan = System.load(path).plan()
    assert [plan.modules[name].fixed_rate for name in ("ctl", "free", "own")] == [
        True, False, None]                          # (None: the class's own, True here)
    folded = fold(plan.name, plan.nodes, plan.modules.values(), plan.links)
    assert [folded.tables["modules"][name].get("fixed_rate") for name in (
        "ctl", "free", "own")] == [True, False, None]   # (configuration() writes it)
    system = System("refused")
    system.add("yes", Controller, fixed_rate="yes")
    system.add("scale", "examples.pipeline:Scale", fixed_rate=True)
    system.add("unpaced", Unpaced, fixed_rate=True)
    system.add("says", SaysYes)
    system.add("chain", Chain, fixed_rate=True)
    problems = "\n".join(system.check())
    assert "[modules.yes]: fixed_rate must be true or false" in problems, problems
    assert ("[modules.scale]: fixed_rate = true is given, but examples.pipeline:Scale has "
            "no step() for it to time") in problems, problems
    assert (f"[modules.unpaced]: fixed_rate = true is given, but neither the module nor "
            f"{__name__}:Unpaced has a period") in problems, problems
    assert (f"[modules.says]: {__name__}:SaysYes has fixed_rate = 'yes': a class's "
            "fixed_rate is True or False") in problems, problems
    assert ("[modules.chain]: 'fixed_rate' applies to modules, not to a macro: set it on "
            "the macro's children") in problems, problems


def test_a_moved_fixed_rate_module_keeps_its_rate() -> None:
    """A fixed rate goes with its module when it moves, as its period does: it steps
    every period on its new node (a new schedule there, from its first step); a swap
    keeps the one given to the module, whatever the new class says."""
    system = System("moved").node("a").node("b")
    system.add("ctl", Controller, node="a", fixed_rate=True)
    with system.launch() as run:
        eventually(lambda: len(run.state("ctl")["began"]) >= 10, timeout=20,
                   what="10 steps on a")
        run.migrate("ctl", to="b")
        moved = time.monotonic()

        def since() -> list[float]:
            return [stamp for stamp in run.state("ctl")["began"] if stamp > moved]
        eventually(lambda: len(since()) >= 55, timeout=20, what="55 steps on b")
        stamps = since()
        stats = run.stats().modules["ctl"]
        run.swap("ctl", Retuned)
        swapped = run.stats().modules["ctl"]
    assert stats.node == "b" and stats.fixed_rate, stats
    assert swapped.cls.endswith(":Retuned") and swapped.fixed_rate, swapped
    interval, skipped = _intervals(stamps)
    assert abs(interval - PERIOD) <= 0.1 * PERIOD, \
        f"{interval * 1e3:.2f} ms a step after the move, {skipped} skipped"

