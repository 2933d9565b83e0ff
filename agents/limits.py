"""What each numeric setting of an agent or module of ``agents`` must be (``Limit``: the
rule in words, and its test), and the check of a state against them: the traffic
driver and controllers, the monitor, the remedy agent and the explorer refuse a
setting out of its limits by name in their ``state_problems`` (so ``pb3a check``, ``add``
and the State Editor refuse it too, and a live ``set_state`` sets nothing).
``refuse_own_state``: the same asked at setup. ``missing_modules``: the modules an
agent's settings name that its system does not have, asked at setup."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from pb3a import Agent, Module
from pb3a.config.checks import finite
from pb3a.errors import ModuleNotFound, PB3AError
from pb3a.model.module import StateRefused, refusals

Limit = tuple[str, Callable[[Any], bool]]
SECONDS: Limit = ("a number of seconds, 0 or more", lambda x: finite(x) and x >= 0)
SPAN: Limit = ("a number of seconds above 0", lambda x: finite(x) and x > 0)
GREEN: Limit = ("a number of seconds, 1 or more (a control step)",
                lambda x: finite(x) and x >= 1)
RATIO: Limit = ("a number, 0 or more", lambda x: finite(x) and x >= 0)
SHARE: Limit = ("a number from 0 to 1", lambda x: finite(x) and 0 <= x <= 1)


def whole(value: Any, least: int = 0) -> bool:
    """True for a whole number (an int, not a bool: TOML's ``true``) of ``least`` or more."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= least


def out_of_limits(limits: dict[str, Limit], settings: dict[str, Any]) -> list[str]:
    """One sentence per setting of ``settings`` out of its limits, naming it and what it
    must be (a setting it lacks is not judged)."""
    return [f"{key} must be {words}, got {settings[key]!r}"
            for key, (words, ok) in limits.items() if key in settings and not ok(settings[key])]


def refuse_own_state(module: Module) -> None:
    """``StateRefused`` (a ValueError) for what the module's class refuses of its whole
    state, asked at setup: a state no ``set_state`` judged (a class's own defaults, a
    module made without a configuration)."""
    problems = refusals(type(module), module.get_state())
    if problems:
        raise StateRefused(problems)


def missing_modules(agent: Agent, named: Iterable[tuple[str, str]]) -> list[str]:
    """``"SETTING: no module ..."`` for each (setting, module name) whose module the
    system does not have, as its runtime says (asked from ``setup``: a misspelt name was
    found only when the agent acted, often after the robot needed it). None when the
    runtime cannot be asked now (none: a ``ModuleHarness`` without one; not answering):
    what the agent does with the module tells then."""
    problems = []
    for setting, module in named:
        if not module:
            continue
        try:
            agent.runtime.where(module)
        except ModuleNotFound as exc:
            problems.append(f"{setting}: {exc}")
        except (PB3AError, RuntimeError, AttributeError):
            return []
    return problems
