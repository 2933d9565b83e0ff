"""``System``: build a system description in Python (or load one from TOML), check it, draw it.

The builder only records what it is told (as a ``SystemSpec``); problems are
found all at once by ``check()``/``plan()``, exactly as for a file, except for
a duplicate module name, which ``add`` refuses at once. ``launch()`` hands
the plan to the runtime.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from pathlib import Path
from typing import Any

from pb3a.config.compiler import build_plan, validate
from pb3a.config.description import (
    DEFAULT_SPARES,
    LinkSpec,
    ModuleSpec,
    NodeSpec,
    SystemSpec,
    load_toml,
    read_description,
)
from pb3a.config.dot import plan_to_dot
from pb3a.config.plan import Plan
from pb3a.launch.running import Running, launch


class System:
    """A system under construction: nodes, modules (or macros) and links between their ports."""

    def __init__(self, name: str, *, module_servers: list[str] | None = None,
                 workers: int = 0, timeout: float | None = None) -> None:
        """``timeout``: how long an operation on the running system may wait by default
        (as ``timeout = ...`` at the top of a file; ``launch(timeout=...)`` wins)."""
        servers = module_servers if isinstance(module_servers, str) else list(
            module_servers or [])       # (a string alone is refused as the file's would be)
        self._spec = SystemSpec(name, module_servers=servers, workers=workers,
                                timeout=timeout)

    @classmethod
    def load(cls, path: str | Path) -> System:
        """Read a TOML system description (see ``pb3a check`` for its problems)."""
        system = cls.__new__(cls)
        system._spec = load_toml(path)
        return system

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "a description") -> System:
        """A system from the tables a TOML description holds, as ``tomllib`` reads them
        (a program may read a file, fill in what it knows only when it runs, such as
        addresses, and build the system from the result); ``source`` names it in
        messages."""
        system = cls.__new__(cls)
        system._spec = read_description(data, source)
        return system

    @property
    def name(self) -> str:
        return self._spec.name

    def node(self, name: str, *, address: str | None = None, workers: int = 0,
             cpus: list[int] | None = None, advertise: str | None = None,
             spares: int = DEFAULT_SPARES) -> System:
        """Declare a node; without any, everything runs on ``"local"``. ``cpus`` pins
        the node's workers to those CPUs (nodes sharing a machine then share no core);
        ``advertise`` is the host other nodes reach it at (by default: a remote node's
        address, and for a node started here the interface that reaches the remote ones);
        ``spares`` is how many idle workers it keeps booted for modules that arrive (a
        move, a restart, a spawn), 0 for none on a machine short of memory."""
        if name in self._spec.nodes:
            raise ValueError(f"system {self.name!r} already has a node {name!r}")
        self._spec.nodes[name] = NodeSpec(name, address, workers, cpus=cpus, advertise=advertise,
                                          spares=spares, written_at=_written_here())
        return self

    def add(self, name: str, cls: type | str, *, node: str | None = None,
            state: dict[str, Any] | None = None, period: float | None = None,
            fixed_rate: bool | None = None, restart: str | None = None,
            group: str | None = None, fallback: list[str] | None = None) -> System:
        """Add a module (a class or ``"module:Class"``) or a Python ``Macro`` subclass;
        ``fixed_rate``: its steps due a period after the last one began, not after it
        ended (None: its class's ``fixed_rate``); ``fallback``: the nodes to restart it
        on, in order, if its node is lost."""
        if name in self._spec.modules:
            raise ValueError(f"system {self.name!r} already has a module {name!r}; "
                             "choose another instance name")
        self._spec.modules[name] = ModuleSpec(name, cls=cls, node=node, period=period,
                                             fixed_rate=fixed_rate,
                                             state=dict(state or {}), restart=restart,
                                             group=group, fallback=fallback,
                                             written_at=_written_here())
        return self

    def link(self, src: str, dst: str, *, policy: str | None = None) -> System:
        """Link output ``src`` (``"module.port"``) to input ``dst``; ``policy`` overrides."""
        self._spec.links.append(LinkSpec(src, dst, policy, written_at=_written_here()))
        return self

    def check(self) -> list[str]:
        """Every problem of the configuration, each naming the entry and the fix; empty if valid."""
        return validate(self._spec)

    def plan(self) -> Plan:
        """The flat plan the runtime executes; ConfigError listing every problem if invalid."""
        return build_plan(self._spec)

    def to_dot(self) -> str:
        """Graphviz DOT: a cluster per node, modules with their ports, links between them."""
        return plan_to_dot(self.plan())

    def launch(self, *, checkpoint_s: float = 1.0, log_level: int = logging.WARNING,
               timeout: float | None = None, listen: str | None = None) -> Running:
        """Validate, then start every module; use it as a context manager.

        ``checkpoint_s`` is how often ``restart = "last-state"`` modules are
        checkpointed; ``log_level`` applies to the worker processes' logs; ``timeout``
        is how long an operation on the running system may wait unless it says
        otherwise (default: the file's ``timeout``, else 30 s); ``listen``
        ("tcp://HOST:PORT") is where the launcher takes ``pb3a.connect`` and the
        command line (see ``Running.listen``).
        """
        return launch(self.plan(), checkpoint_s=checkpoint_s, log_level=log_level,
                      timeout=timeout, listen=listen)

    def __repr__(self) -> str:
        return (f"System({self.name!r}, {len(self._spec.modules)} modules, "
                f"{len(self._spec.links)} links)")


def _written_here() -> str:
    """Where the program called the builder (``wiring.py:14``, from the current directory
    if the file is below it): the problems ``check()`` and ``launch()`` find in an entry
    name it, as they name a file's entry."""
    caller = sys._getframe(2)
    path = Path(caller.f_code.co_filename)
    # (not below it, or the current directory removed: the path as it is)
    with contextlib.suppress(ValueError, OSError):
        path = path.relative_to(Path.cwd())
    return f"{path}:{caller.f_lineno}"
