"""Definitions: the system itself and each macro, as the compiler reads them.

A definition keeps its entries as written (modules, links, exports) beside what
they resolve to (``children``: a leaf class or another definition; ``resolved``:
its checked links), and knows how to name its own tables in messages.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from pb3a.config import checks
from pb3a.model.ports import Input

if TYPE_CHECKING:
    from pb3a.config.description import LinkSpec, ModuleSpec
    from pb3a.model.module import Module
    from pb3a.model.ports import Output, Policy


@dataclass(frozen=True)
class PortRef:
    """A leaf module port, its module's path relative to the definition that names it."""

    path: str                   # "lp", or "inner/lp" through a child macro
    cls: type[Module]
    port: str
    spec: Input | Output

    @property
    def is_input(self) -> bool:
        return isinstance(self.spec, Input)


@dataclass
class Child:
    """A resolved module entry: a leaf class, another definition, or neither (broken)."""

    spec: ModuleSpec
    label: str
    cls: type[Module] | None = None
    macro: Definition | None = None
    said: list[str] = field(default_factory=list)   # what its class refuses of its state


@dataclass(eq=False)
class Definition:
    """The system itself or one macro: its entries as written and what they resolve to."""

    title: str                       # "system 'x'", "macro 'filter'", "macro mod:Filter"
    origin: str                      # the file, or "system 'x'", or "macro mod:Filter"
    prefix: str                      # where its tables are: "" or "macros.filter."
    modules: dict[str, ModuleSpec]
    links: list[LinkSpec]
    exports: dict[str, object]
    children: dict[str, Child] = field(default_factory=dict)
    resolved: list[tuple[str, PortRef, PortRef, Policy]] = field(default_factory=list)
    exported: dict[str, PortRef] = field(default_factory=dict)    # its exports, resolved
    name: str = ""                   # what a plan's ``macros`` calls it: "Filter" (a Macro
                                     # class), "[macros.filter]"; "" for the system

    def label(self, table: str, key: str) -> str:
        """``origin [prefix.table.key]``, the key quoted as TOML would need it."""
        return f"{self.origin} [{self.prefix}{table}.{toml_key(key)}]"


def written(label: str, at: str | None) -> str:
    """``label`` led by the file and line of the program that wrote the entry, if a
    program built it (``wiring.py:14: system 'demo' [[links]] #1 ...``), the way a
    compiler names a place an editor can open."""
    return label if at is None else f"{at}: {label}"


def toml_key(key: object) -> str:
    """``key`` as written in a TOML table header: bare when it can be, else quoted."""
    text = str(key)
    return text if checks.NAME.match(text) else '"' + text.replace('"', '\\"') + '"'
