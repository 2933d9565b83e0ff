"""The plan: what the runtime runs, after the compiler expanded and checked a description.

Macros are expanded into instance paths, classes resolved, links rewired through
macro exports onto leaf module ports, and every value checked.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from pb3a.config.description import NodeSpec
from pb3a.loading.sources import CodeSources
from pb3a.model.ports import Policy

DEFAULT_NODE = "local"      # the node of a system that declares none


@dataclass
class FlatModule:
    """One module instance to run, after macro expansion."""

    name: str                 # instance path, e.g. "robot/mapper/grid"
    cls: type                 # resolved Module subclass
    node: str                 # node name ("local" when the system names no nodes)
    period: float | None      # config override or the class's period
    state: dict[str, Any]     # initial state overrides from the config
    restart: str              # "never" | "fresh" | "last-state"
    group: str | None = None  # modules with the same group share one worker process
    fallback: list[str] = field(default_factory=list)   # failover nodes, in order
    own_period: bool = False  # the configuration gave the period (a swap keeps it)


@dataclass
class FlatLink:
    """One link between two module ports, after export resolution."""

    src: str
    src_port: str
    dst: str
    dst_port: str
    policy: Policy            # the link override, else the input's declared policy

    @property
    def key(self) -> str:
        return f"{self.src}.{self.src_port}->{self.dst}.{self.dst_port}"


@dataclass
class Plan:
    """What the executor runs: nodes, modules in start order, links."""

    name: str
    nodes: dict[str, NodeSpec]            # always at least one node; "local" if none declared
    modules: dict[str, FlatModule]        # declaration order, macro children in place
    links: list[FlatLink]
    code: CodeSources = field(default_factory=CodeSources)   # the file's directory, servers
    timeout: float | None = None          # the file's default for operations, if it sets one
