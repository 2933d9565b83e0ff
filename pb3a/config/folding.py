"""A system's flat structure folded back into the tables of a configuration file.

The plan a system runs is flat: macros were expanded into instance paths
(``robot/arm/grip``) and links rewired onto leaf ports. ``fold`` turns modules,
links and nodes as a running system has them *now* (after moves, swaps, adds and
relinks) back into the tables of a TOML file that ``pb3a check`` accepts and that
expands to the same plan: each macro instance becomes a ``[macros.X]`` definition
of its own (the parts of the paths give the nesting), each link is written in the
innermost definition holding both its ends, and a port that a link reaches from
outside a macro is exported by each macro on the way. Which instances shared one
definition is no longer known after expansion, so none share one.
"""

from __future__ import annotations

import datetime
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pb3a.config.checks import NAME
from pb3a.config.description import DEFAULT_SPARES, NodeSpec
from pb3a.config.plan import DEFAULT_NODE, FlatLink, FlatModule
from pb3a.loading.references import class_ref
from pb3a.model.environment import Environment, env_name

_NOT_IDENTIFIER = re.compile(r"\W")
_TOML_SCALARS = (bool, int, float, str, datetime.datetime, datetime.date, datetime.time)


@dataclass
class Folded:
    """The tables of a configuration (``tables``, as ``tomllib`` would read them), and
    what could not be written in them (``problems``: one sentence each)."""

    tables: dict[str, Any]
    problems: list[str] = field(default_factory=list)


@dataclass
class _Definition:
    """The system's tables, or one macro's: its modules, links and exports."""

    name: str                                       # "" for the system
    modules: dict[str, Any] = field(default_factory=dict)
    links: list[dict[str, Any]] = field(default_factory=list)
    exports: dict[str, str] = field(default_factory=dict)      # export -> "child.port"
    exported: dict[str, str] = field(default_factory=dict)     # "child.port" -> export


def fold(name: str, nodes: dict[str, NodeSpec], modules: Iterable[FlatModule],
         links: Iterable[FlatLink], module_servers: Iterable[str] = (),
         timeout: float | None = None) -> Folded:
    """The configuration that launches these ``modules`` (instance paths), ``links`` and
    ``nodes`` as they are."""
    return _Folder(nodes, list(modules), list(links)).fold(name, list(module_servers), timeout)


class _Folder:
    def __init__(self, nodes: dict[str, NodeSpec], modules: list[FlatModule],
                 links: list[FlatLink]) -> None:
        self.nodes = nodes
        self.modules = {module.name: module for module in modules}
        self.links = links
        self.problems: list[str] = []
        # the default node of a system that declares none is written as no nodes at all,
        # but only when a top-level key can say all it has (``workers``): a declared
        # "local" node with an address, cpus, advertise or other spares keeps its table
        only = nodes.get(DEFAULT_NODE)
        self.implicit_node = (list(nodes) == [DEFAULT_NODE] and only is not None
                              and (only.address, only.cpus, only.advertise) == (None,) * 3
                              and only.spares == DEFAULT_SPARES)
        self.definitions: dict[str, _Definition] = {"": _Definition("")}
        taken: set[str] = set()
        for module in modules:
            parts = module.name.split("/")
            for depth in range(1, len(parts)):
                path = "/".join(parts[:depth])
                if path not in self.definitions:
                    self.definitions[path] = _Definition(_unique(path.replace("/", "-"), taken))

    def fold(self, name: str, module_servers: list[str], timeout: float | None) -> Folded:
        tables: dict[str, Any] = {"name": name}
        if module_servers:
            tables["module_servers"] = module_servers
        if timeout is not None:
            tables["timeout"] = timeout
        if self.implicit_node:
            workers = self.nodes[DEFAULT_NODE].workers
            if workers:
                tables["workers"] = workers
        else:
            tables["nodes"] = {node.name: _node_table(node) for node in self.nodes.values()}
        self.instance_groups = self._instance_groups()
        for module in self.modules.values():
            if not self._automatic(module):
                self._place(module)
        for link in self.links:
            self._link(link)
        system = self.definitions[""]
        tables["modules"] = system.modules
        if system.links:
            tables["links"] = system.links
        macros = {definition.name: _macro_table(definition)
                  for path, definition in self.definitions.items() if path}
        if macros:
            tables["macros"] = macros
        return Folded(tables, self.problems)

    # -- modules ---------------------------------------------------------------------
    def _automatic(self, module: FlatModule) -> bool:
        """A node's env module that the compiler adds again, as it would add it (a
        top-level link reads it; no settings of its own, which would be lost)."""
        return (module.cls is Environment and module.name == env_name(module.node)
                and any(link.src == module.name for link in self.links)
                and module.period == Environment.period and not module.state
                and module.restart == Environment.restart and module.group is None
                and not module.fallback)

    def _instance_groups(self) -> dict[str, str]:
        """Macro instance path -> the group its entry says, for a group that every module
        under it has and that no entry inside it can say (one set on the instance: its
        modules' group is the instance's prefix plus it, never their macro's)."""
        found: dict[str, str] = {}
        for module in self.modules.values():
            group, parts = module.group, module.name.split("/")
            if group is None or group.startswith(f"{'/'.join(parts[:-1])}/"):
                continue                                  # none, or written inside
            for depth in range(1, len(parts)):
                path, above = "/".join(parts[:depth]), "/".join(parts[:depth - 1])
                said = group.removeprefix(f"{above}/") if above else group
                if (group.startswith(f"{above}/") or not above) and NAME.match(said) and all(
                        other.group == group for other in self.modules.values()
                        if other.name.startswith(f"{path}/")):
                    found[path] = said
                    break
        return found

    def _place(self, module: FlatModule) -> None:
        """The module's entry in its macro's definition (and each macro's in its parent's)."""
        parent, _, own = module.name.rpartition("/")
        self.definitions[parent].modules[own] = self._entry(module, parent)
        while parent:
            above, _, macro = parent.rpartition("/")
            entry = self.definitions[above].modules.setdefault(
                macro, {"macro": self.definitions[parent].name})
            if parent in self.instance_groups:
                entry["group"] = self.instance_groups[parent]
            parent = above

    def _entry(self, module: FlatModule, parent: str) -> dict[str, Any]:
        cls = module.cls
        entry: dict[str, Any] = {"class": class_ref(cls)}
        if cls.__module__ == "__main__" or "<locals>" in cls.__qualname__:
            self.problems.append(
                f"module {module.name}: its class {class_ref(cls)} is defined in a script "
                "(or a function), which no file can name: `pb3a check` will refuse it; move "
                "the class into a module that can be imported")
        if not self.implicit_node:
            entry["node"] = module.node
        if module.own_period or (module.period != cls.period and module.period is not None):
            entry["period"] = module.period
        if module.fixed_rate is not None:
            entry["fixed_rate"] = module.fixed_rate
        if module.restart != cls.restart:
            entry["restart"] = module.restart
        state = {}
        for key, value in module.state.items():
            written = toml_value(value)
            if written is None:
                self.problems.append(
                    f"module {module.name}: its configured state {key!r} "
                    f"({type(value).__name__}) has no TOML form, left out: it starts with "
                    "its class's value")
            else:
                state[key] = written
        if state:
            entry["state"] = state
        inherited = any(module.name.startswith(f"{path}/") for path in self.instance_groups)
        if module.group is not None and not inherited:
            prefix = f"{parent}/" if parent else ""
            group = module.group.removeprefix(prefix) if module.group.startswith(prefix) \
                else None
            if group is not None and NAME.match(group):
                entry["group"] = group
            else:
                self.problems.append(f"module {module.name}: its group {module.group!r} "
                                     "cannot be written inside its macro, left out: it gets a "
                                     "worker of its own")
        if module.fallback:
            entry["fallback"] = list(module.fallback)
        return entry

    # -- links -----------------------------------------------------------------------
    def _link(self, link: FlatLink) -> None:
        """Written in the innermost definition that holds both ends."""
        src_parts, dst_parts = link.src.split("/")[:-1], link.dst.split("/")[:-1]
        common: list[str] = []
        for a, b in zip(src_parts, dst_parts, strict=False):
            if a != b:
                break
            common.append(a)
        level = "/".join(common)
        entry = {"from": self._endpoint(level, link.src, link.src_port),
                 "to": self._endpoint(level, link.dst, link.dst_port)}
        reader = self.modules.get(link.dst)
        declared = reader.cls.inputs[link.dst_port].policy if reader is not None else None
        if declared is None or str(link.policy) != str(declared):
            entry["policy"] = str(link.policy)
        self.definitions[level].links.append(entry)

    def _endpoint(self, level: str, module: str, port: str) -> str:
        """``"child.port"`` as the definition at ``level`` names ``module``'s ``port``:
        through the exports of the macros between them."""
        rest = module.removeprefix(f"{level}/") if level else module
        child, _, below = rest.partition("/")
        if not below:
            return f"{child}.{port}"
        path = f"{level}/{child}" if level else child
        inner = self._endpoint(path, module, port)
        macro = self.definitions[path]
        export = macro.exported.get(inner)
        if export is None:
            export = _unique(_NOT_IDENTIFIER.sub("_", inner.replace(".", "_")), macro.exports)
            if not export.isidentifier():
                export = _unique(f"p_{export}", macro.exports)
            macro.exports[export] = inner
            macro.exported[inner] = export
        return f"{child}.{export}"


def _node_table(node: NodeSpec) -> dict[str, Any]:
    table: dict[str, Any] = {}
    if node.address is not None:
        table["address"] = node.address
    if node.workers:
        table["workers"] = node.workers
    if node.cpus is not None:
        table["cpus"] = list(node.cpus)
    if node.advertise is not None:
        table["advertise"] = node.advertise
    if node.spares != DEFAULT_SPARES:
        table["spares"] = node.spares
    return table


def _macro_table(definition: _Definition) -> dict[str, Any]:
    table: dict[str, Any] = {"modules": definition.modules}
    if definition.links:
        table["links"] = definition.links
    if definition.exports:
        table["exports"] = definition.exports
    return table


def toml_value(value: Any) -> Any:
    """``value`` as TOML can hold it (tuples as lists, numpy scalars as Python's), or None
    when it cannot (None itself, arrays, objects): TOML has no null and no object."""
    if isinstance(value, np.generic):
        value = value.item()
    if type(value) in _TOML_SCALARS:  # (not a subclass: an IntEnum written as 3 would
        return value                  # read back as an int, which the module never had)
    if isinstance(value, (list, tuple)):
        items = [toml_value(item) for item in value]
        return None if any(item is None for item in items) else items
    if isinstance(value, dict) and all(isinstance(key, str) for key in value):
        table = {key: toml_value(item) for key, item in value.items()}
        return None if any(item is None for item in table.values()) else table
    return None


def _unique(name: str, taken: set[str] | dict[str, Any]) -> str:
    """``name`` or, when taken, ``name_2``, ``name_3``... (``-2`` when ``name`` is not an
    identifier); added to ``taken`` when it is a set."""
    found, number = name, 1
    while found in taken:
        number += 1
        found = f"{name}_{number}" if name.isidentifier() else f"{name}-{number}"
    if isinstance(taken, set):
        taken.add(found)
    return found
