"""The plan: what the runtime runs, after the compiler expanded and checked a description.

Macros are expanded into instance paths, classes resolved, links rewired through
macro exports onto leaf module ports, and every value checked. Each macro instance's
path is kept with the macro it is (``macros``), for drawings, and with where its
exports lead (``exports``), for links made at run time.
"""

from __future__ import annotations

from collections.abc import Iterable
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
    fixed_rate: bool | None = None   # the configuration's (None: the class's own)


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
    """What the executor runs: nodes, modules in start order, links; and, for drawings,
    the macro instances the modules came from."""

    name: str
    nodes: dict[str, NodeSpec]            # always at least one node; "local" if none declared
    modules: dict[str, FlatModule]        # declaration order, macro children in place
    links: list[FlatLink]
    code: CodeSources = field(default_factory=CodeSources)   # the file's directory, servers
    timeout: float | None = None          # the file's default for operations, if it sets one
    macros: dict[str, str] = field(default_factory=dict)   # macro instance path -> its macro:
                                          # the Macro class's name, or "[macros.NAME]"
    # macro instance path -> its exports, each the leaf port it leads to (module path, port):
    # what a link made at run time to "f.x" joins
    exports: dict[str, dict[str, tuple[str, str]]] = field(default_factory=dict)
    # what the plan likely leaves undone, valid as it is (a step with no period, an input
    # fed by nothing): ``pb3a.config.notes``, printed by ``pb3a check`` and ``pb3a run``
    notes: list[str] = field(default_factory=list)


def split_by_macro(names: Iterable[str],
                   prefix: str = "") -> tuple[list[str], dict[str, list[str]]]:
    """Of the instance paths ``names``, all below macro instance path ``prefix`` (``""``
    for the system, ``"robot/"``): those directly in it, and the others by the child
    macro instance that holds them (``"robot/arm"``), in order of first appearance.
    Every ``/`` in a path is a macro's: a name cannot hold one."""
    direct: list[str] = []
    below: dict[str, list[str]] = {}
    for name in names:
        head, slash, _ = name.removeprefix(prefix).partition("/")
        if slash:
            below.setdefault(prefix + head, []).append(name)
        else:
            direct.append(name)
    return direct, below
