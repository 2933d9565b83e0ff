"""PB3A: self-adaptive software from port-based modules.

Modules with typed ports run in parallel as actors in worker processes; a
running system can be inspected, retuned, rewired and have modules swapped
while it runs. See README.md for a tour and docs/architecture.md for how.
"""

from __future__ import annotations

from pb3a.errors import (
    ConfigError,
    ModuleNotFound,
    PB3AError,
    RuntimeFailure,
    RuntimeTimeout,
)
from pb3a.launch.connection import Connection, connect
from pb3a.launch.migration import MigrationReport
from pb3a.launch.running import Running
from pb3a.model.agent import Agent
from pb3a.model.driver import Driver
from pb3a.model.environment import Environment
from pb3a.model.macro import Macro
from pb3a.model.module import Module
from pb3a.model.ports import Input, InputPort, Output, OutputPort
from pb3a.system import System

__all__ = [
    "Agent",
    "ConfigError",
    "Connection",
    "Driver",
    "Environment",
    "Input",
    "InputPort",
    "Macro",
    "MigrationReport",
    "Module",
    "ModuleNotFound",
    "Output",
    "OutputPort",
    "PB3AError",
    "Running",
    "RuntimeFailure",
    "RuntimeTimeout",
    "System",
    "connect",
]

