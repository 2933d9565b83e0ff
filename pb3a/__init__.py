"""PB3A: self-adaptive software from port-based modules.

Modules with typed ports run in parallel as actors in worker processes; a
running system can be inspected, retuned, rewired and have modules swapped
while it runs. See README.md for a tour and docs/architecture.md for how.

The public names below are imported when first used (PEP 562), so that a command
or a robot server that needs only part of PB3A starts without the rest.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# public name -> the module that defines it
_HOME = {
    "Agent": "pb3a.model.agent",
    "ConfigError": "pb3a.errors",
    "Connection": "pb3a.launch.connection",
    "Driver": "pb3a.model.driver",
    "Environment": "pb3a.model.environment",
    "Input": "pb3a.model.ports",
    "InputPort": "pb3a.model.ports",
    "Macro": "pb3a.model.macro",
    "MigrationReport": "pb3a.launch.migration",
    "Module": "pb3a.model.module",
    "ModuleNotFound": "pb3a.errors",
    "Output": "pb3a.model.ports",
    "OutputPort": "pb3a.model.ports",
    "PB3AError": "pb3a.errors",
    "Running": "pb3a.launch.running",
    "RuntimeCancelled": "pb3a.errors",
    "RuntimeFailure": "pb3a.errors",
    "RuntimeTimeout": "pb3a.errors",
    "StateRefused": "pb3a.model.module",
    "System": "pb3a.system",
    "SystemStopped": "pb3a.errors",
    "connect": "pb3a.launch.connection",
    "serve_device": "pb3a.model.driver",
}

__all__ = sorted(_HOME, key=lambda name: (name[0].islower(), name))


def __getattr__(name: str) -> Any:
    home = _HOME.get(name)
    if home is None:
        raise AttributeError(f"module 'pb3a' has no attribute {name!r}")
    value = getattr(importlib.import_module(home), name)
    globals()[name] = value                  # imported once
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})


if TYPE_CHECKING:                 # what type checkers see: the same names, eagerly
    from pb3a.errors import ConfigError as ConfigError
    from pb3a.errors import ModuleNotFound as ModuleNotFound
    from pb3a.errors import PB3AError as PB3AError
    from pb3a.errors import RuntimeCancelled as RuntimeCancelled
    from pb3a.errors import RuntimeFailure as RuntimeFailure
    from pb3a.errors import RuntimeTimeout as RuntimeTimeout
    from pb3a.errors import SystemStopped as SystemStopped
    from pb3a.launch.connection import Connection as Connection
    from pb3a.launch.connection import connect as connect
    from pb3a.launch.migration import MigrationReport as MigrationReport
    from pb3a.launch.running import Running as Running
    from pb3a.model.agent import Agent as Agent
    from pb3a.model.driver import Driver as Driver
    from pb3a.model.driver import serve_device as serve_device
    from pb3a.model.environment import Environment as Environment
    from pb3a.model.macro import Macro as Macro
    from pb3a.model.module import Module as Module
    from pb3a.model.module import StateRefused as StateRefused
    from pb3a.model.ports import Input as Input
    from pb3a.model.ports import InputPort as InputPort
    from pb3a.model.ports import Output as Output
    from pb3a.model.ports import OutputPort as OutputPort
    from pb3a.system import System as System
