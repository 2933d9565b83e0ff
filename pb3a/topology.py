"""The structure of a system, as typed records: what ``run.topology()`` returns.

Where ``pb3a.stats`` says how a system is doing, a ``Topology`` says what it is:
each module with its class, node, macro, ports and their types, state names and
custom displays; each link; each node with its health. Tools draw it (the
ModuleManager, ``pb3a.manager``); ``to_json()`` gives it as plain JSON types.
The same records describe a plan that is not running yet (``plan_topology``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from pb3a.loading.references import class_ref
from pb3a.model.agent import Agent
from pb3a.model.displays import Display, declared_displays
from pb3a.model.driver import Driver

if TYPE_CHECKING:
    from pb3a.config.description import NodeSpec
    from pb3a.config.plan import FlatLink, FlatModule, Plan
    from pb3a.model.ports import Input, Output
    from pb3a.stats import NodeStats


@dataclass(frozen=True)
class PortInfo:
    """One port: its type as error messages write it, and (inputs) its declared policy."""

    type: str                        # e.g. "float", "ndarray[(16,), float64]"
    policy: str | None = None        # inputs only: "latest", "queue:N", "lossless:N"

    def to_json(self) -> dict[str, Any]:
        return {"type": self.type} if self.policy is None else {"type": self.type,
                                                                 "policy": self.policy}


@dataclass(frozen=True)
class ModuleInfo:
    """One module instance: what it is and where it runs."""

    name: str                        # instance path, e.g. "robot/mapper"
    cls: str                         # "package.module:Class"
    node: str
    macro: str | None                # the macro instance it belongs to ("robot"), if any
    period: float | None
    restart: str
    kind: str                        # "module" | "agent" | "driver"
    # its steps due a period after the last one began (the configuration's, else its
    # class's), not a period after the last one ended
    fixed_rate: bool = False
    inputs: dict[str, PortInfo] = field(default_factory=dict)
    outputs: dict[str, PortInfo] = field(default_factory=dict)
    state: tuple[str, ...] = ()      # the class's state names (found by reflection)
    displays: dict[str, Display] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"class": self.cls, "node": self.node, "macro": self.macro,
                "period": self.period, "fixed_rate": self.fixed_rate,
                "restart": self.restart, "kind": self.kind,
                "inputs": {name: port.to_json() for name, port in self.inputs.items()},
                "outputs": {name: port.to_json() for name, port in self.outputs.items()},
                "state": list(self.state),
                "displays": {name: shown.to_json() for name, shown in self.displays.items()}}


@dataclass(frozen=True)
class LinkInfo:
    """One link from an output to an input."""

    key: str                         # "src.port->dst.port"
    src: str                         # "module.port"
    dst: str
    policy: str

    def to_json(self) -> dict[str, Any]:
        return {"key": self.key, "src": self.src, "dst": self.dst, "policy": self.policy}


@dataclass(frozen=True)
class NodeInfo:
    """One node: where it runs and, for a running system, its health."""

    address: str | None              # None: embedded in the launcher's process
    workers: int = 0                 # packed worker processes (0: one per module)
    up: bool | None = None           # None: not running
    rtt: float | None = None         # seconds (None: not known)

    def to_json(self) -> dict[str, Any]:
        rtt = None if self.rtt is None or math.isnan(self.rtt) else self.rtt
        return {"address": self.address, "workers": self.workers, "up": self.up, "rtt": rtt}


@dataclass(frozen=True)
class Topology:
    """A whole system's structure."""

    system: str
    modules: dict[str, ModuleInfo]
    links: dict[str, LinkInfo]       # keyed "src.port->dst.port"
    nodes: dict[str, NodeInfo]
    module_servers: tuple[str, ...] = ()     # where its nodes import code the path lacks

    @property
    def macros(self) -> dict[str, list[str]]:
        """Each macro instance and every module below it (also in nested macros)."""
        found: dict[str, list[str]] = {}
        for name in self.modules:
            parts = name.split("/")
            for depth in range(1, len(parts)):
                found.setdefault("/".join(parts[:depth]), []).append(name)
        return found

    def to_json(self) -> dict[str, Any]:
        """The structure as JSON types."""
        return {"name": self.system,
                "nodes": {name: node.to_json() for name, node in self.nodes.items()},
                "modules": {name: module.to_json() for name, module in self.modules.items()},
                "links": [link.to_json() for link in self.links.values()],
                "macros": self.macros, "module_servers": list(self.module_servers)}


def topology_of(system: str, nodes: dict[str, NodeSpec], modules: Iterable[FlatModule],
                links: Iterable[FlatLink],
                health: dict[str, NodeStats] | None = None,
                module_servers: Iterable[str] = ()) -> Topology:
    """The topology of modules and links placed on ``nodes``; ``health`` (a running
    system's ``node_table``) says which are up; ``module_servers``: the system's."""
    health = health or {}
    return Topology(
        system,
        {module.name: module_info(module) for module in modules},
        {link.key: LinkInfo(link.key, f"{link.src}.{link.src_port}",
                            f"{link.dst}.{link.dst_port}", str(link.policy))
         for link in links},
        {name: NodeInfo(node.address, node.workers,
                        health[name].up if name in health else None,
                        health[name].rtt if name in health else None)
         for name, node in nodes.items()},
        tuple(module_servers))


def plan_topology(plan: Plan) -> Topology:
    """The topology of a plan before it runs."""
    return topology_of(plan.name, plan.nodes, plan.modules.values(), plan.links,
                       module_servers=plan.code.module_servers)


def module_info(module: FlatModule) -> ModuleInfo:
    """One placed module's record."""
    cls = module.cls
    parent = module.name.rpartition("/")[0] or None
    # (a class's own that is no bool is no fixed rate: `pb3a check` refuses it)
    fixed_rate = module.fixed_rate if module.fixed_rate is not None \
        else getattr(cls, "fixed_rate", False) is True
    return ModuleInfo(module.name, class_ref(cls), module.node, parent, module.period,
                      module.restart, class_kind(cls), fixed_rate, ports(cls.inputs),
                      ports(cls.outputs), tuple(cls.state_names()), displays_of(cls))


def class_kind(cls: type) -> str:
    """``"agent"``, ``"driver"`` or ``"module"``."""
    return "agent" if issubclass(cls, Agent) else "driver" if issubclass(cls, Driver) else "module"


def ports(declared: dict[str, Input] | dict[str, Output]) -> dict[str, PortInfo]:
    """Port records of a class's ``inputs`` or ``outputs`` table."""
    return {name: PortInfo(spec.describe(), str(getattr(spec, "policy", "")) or None)
            for name, spec in declared.items()}


def displays_of(cls: type) -> dict[str, Display]:
    """The class's displays; none when its table is malformed (``pb3a check`` says why)."""
    try:
        return declared_displays(cls)
    except ValueError:
        return {}
