"""The description of a system: what the user wrote, in a file or in Python.

It is kept unchecked, on purpose, so that every mistake can be reported at once
with the place it is in; ``pb3a.config.compiler`` turns it into the checked
``Plan`` the runtime runs. ``load_toml`` reads a description from a file.
"""

from __future__ import annotations

import codecs
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from pb3a.errors import ConfigError

# A node keeps this many worker processes booted and idle, so that a module that
# arrives (a migration, a restart, a spawn) finds one and no process starts in its
# critical path; two modules arriving together both find one. Each costs an idle
# process's memory; 0 gives it back and makes every arrival start its process.
DEFAULT_SPARES = 2


# -- the description -------------------------------------------------------
@dataclass
class NodeSpec:
    """A node: a place modules run. ``workers=0``: one process per module; N>0: N processes."""

    name: str
    address: str | None = None
    workers: int = 0
    extra: dict[str, Any] = field(default_factory=dict)  # unknown keys, reported by validation
    cpus: list[int] | None = None     # CPUs the node's workers may run on (None: any)
    advertise: str | None = None      # the host other nodes reach this one at (None: found)
    spares: int = DEFAULT_SPARES      # booted idle workers kept for modules that arrive
    written_at: str | None = field(default=None, compare=False)   # "file.py:14": the
                                      # System call that made it, for messages

    KEYS: ClassVar[tuple[str, ...]] = ("address", "workers", "cpus", "advertise", "spares")


@dataclass
class ModuleSpec:
    """One ``[modules.NAME]`` entry: a module class (``cls``) or a file macro (``macro``)."""

    name: str
    cls: Any = None                 # a class, "module:Class" or a Macro subclass
    macro: str | None = None        # the name of a [macros.X] definition
    node: str | None = None
    period: Any = None              # None: the class's period
    fixed_rate: Any = None          # None: the class's (steps due a period after the
                                    # last began, not after it ended)
    state: Any = field(default_factory=dict)
    restart: str | None = None      # None: the class's restart policy
    group: str | None = None
    fallback: Any = None            # nodes to restart it on, in order, if its node is lost
    extra: dict[str, Any] = field(default_factory=dict)
    written_at: str | None = field(default=None, compare=False)   # "file.py:14": the
                                      # System call that made it, for messages

    KEYS: ClassVar[tuple[str, ...]] = ("class", "macro", "node", "period", "fixed_rate",
                                       "state", "restart", "group", "fallback")

    @classmethod
    def from_entry(cls, name: str, entry: Any) -> ModuleSpec:
        """Read a table (TOML or a dict in a Python macro); anything else is the class."""
        if not isinstance(entry, dict):
            return cls(name, cls=entry)
        known = {key: entry[key] for key in cls.KEYS if key in entry}
        return cls(name, cls=known.get("class"), macro=known.get("macro"),
                   node=known.get("node"), period=known.get("period"),
                   fixed_rate=known.get("fixed_rate"),
                   state=known.get("state", {}), restart=known.get("restart"),
                   group=known.get("group"), fallback=known.get("fallback"),
                   extra={k: v for k, v in entry.items() if k not in cls.KEYS})


@dataclass
class LinkSpec:
    """One ``[[links]]`` entry: ``src`` and ``dst`` are ``"module.port"`` endpoints."""

    src: Any
    dst: Any
    policy: Any = None              # None: the input's declared policy
    extra: dict[str, Any] = field(default_factory=dict)
    written_at: str | None = field(default=None, compare=False)   # "file.py:14": the
                                      # System call that made it, for messages

    KEYS: ClassVar[tuple[str, ...]] = ("from", "to", "policy")

    @classmethod
    def from_entry(cls, entry: Any) -> LinkSpec:
        """Read a table or a ``(from, to[, policy])`` tuple; ValueError for anything else."""
        if isinstance(entry, dict):
            return cls(entry.get("from"), entry.get("to"), entry.get("policy"),
                       extra={k: v for k, v in entry.items() if k not in cls.KEYS})
        if isinstance(entry, (tuple, list)) and len(entry) in (2, 3):
            return cls(*entry)
        raise ValueError(f"a link must be a table with 'from' and 'to' (or a (from, to[, policy]) "
                         f"tuple), got {entry!r}")

    @property
    def title(self) -> str:
        """``from -> to`` as written, for messages."""
        return f"{'?' if self.src is None else self.src} -> {'?' if self.dst is None else self.dst}"


@dataclass
class MacroSpec:
    """A ``[macros.NAME]`` definition: children, inner links, and exported ports."""

    name: str
    modules: dict[str, ModuleSpec] = field(default_factory=dict)
    links: list[LinkSpec] = field(default_factory=list)
    exports: dict[str, Any] = field(default_factory=dict)   # external port -> "child.port"
    extra: dict[str, Any] = field(default_factory=dict)

    KEYS: ClassVar[tuple[str, ...]] = ("modules", "links", "exports")


@dataclass
class SystemSpec:
    """A whole system as described; ``source`` is the file it came from, for messages."""

    name: str
    nodes: dict[str, NodeSpec] = field(default_factory=dict)
    modules: dict[str, ModuleSpec] = field(default_factory=dict)
    links: list[LinkSpec] = field(default_factory=list)
    macros: dict[str, MacroSpec] = field(default_factory=dict)
    module_servers: list[str] = field(default_factory=list)
    workers: Any = 0                 # the workers of the default node "local"
    timeout: Any = None              # seconds an operation may wait (None: the default)
    source: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)  # found while reading the file

    KEYS: ClassVar[tuple[str, ...]] = ("name", "module_servers", "nodes", "modules", "links",
                                       "macros", "workers", "timeout")

    @property
    def origin(self) -> str:
        """How messages name this system: its file, or ``system 'name'``."""
        return self.source if self.source is not None else f"system {self.name!r}"


# -- reading --------------------------------------------------
def refuse_a_script(path: str | Path) -> None:
    """ConfigError if ``path`` is a Python script where a configuration was asked for."""
    if Path(path).suffix == ".py":
        raise ConfigError([f"{path}: a Python script, not a configuration (a TOML file): "
                           f"run it with python {path}"])


def load_toml(path: str | Path) -> SystemSpec:
    """Read a system description from a TOML file.

    Raises OSError when the file cannot be read and ConfigError when it is not
    TOML (UTF-8, with or without a byte order mark); every other mistake is kept for
    ``validate``/``build_plan`` to report.
    """
    path = Path(path)
    refuse_a_script(path)
    raw = path.read_bytes()
    # (a byte order mark, which Windows editors write, was "not valid TOML" at line 1)
    body = raw.removeprefix(codecs.BOM_UTF8)
    try:
        data = tomllib.loads(body.decode("utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError([f"{path}: not valid TOML: {exc}"]) from exc
    except UnicodeDecodeError as exc:
        raise ConfigError([f"{path}: not UTF-8 text (byte {exc.start + len(raw) - len(body)}):"
                           " save it as UTF-8"]) from None
    return _read_system(data, str(path), default_name=path.stem)


def read_description(data: dict[str, Any], source: str) -> SystemSpec:
    """A system description from the tables of a TOML file, already read."""
    return _read_system(data, source, default_name=str(data.get("name", "system")))


def _read_system(data: dict[str, Any], source: str, default_name: str) -> SystemSpec:
    spec = SystemSpec(name=data.get("name", default_name), source=source,
                      module_servers=data.get("module_servers", []),
                      workers=data.get("workers", 0), timeout=data.get("timeout"),
                      extra={k: v for k, v in data.items() if k not in SystemSpec.KEYS})
    for name, entry in _table(data, "nodes", source, spec.problems).items():
        if isinstance(entry, dict):
            spec.nodes[name] = NodeSpec(name, entry.get("address"), entry.get("workers", 0),
                                        {k: v for k, v in entry.items() if k not in NodeSpec.KEYS},
                                        entry.get("cpus"), entry.get("advertise"),
                                        entry.get("spares", DEFAULT_SPARES))
        else:
            spec.problems.append(f"{source} [nodes.{name}]: must be a table (address, workers, "
                                 "cpus, advertise, spares)")
    spec.modules = _read_modules(_table(data, "modules", source, spec.problems))
    spec.links = _read_links(data.get("links", []), f"{source} [[links]]", spec.problems)
    for name, entry in _table(data, "macros", source, spec.problems).items():
        where = f"{source} [macros.{name}]"
        if not isinstance(entry, dict):
            spec.problems.append(f"{where}: must be a table with modules, links and exports")
            continue
        spec.macros[name] = MacroSpec(
            name, _read_modules(_table(entry, "modules", where, spec.problems)),
            _read_links(entry.get("links", []), f"{source} [[macros.{name}.links]]",
                        spec.problems),
            _table(entry, "exports", where, spec.problems),
            {k: v for k, v in entry.items() if k not in MacroSpec.KEYS})
    return spec


def _table(data: dict[str, Any], key: str, where: str, problems: list[str]) -> dict[str, Any]:
    value = data.get(key, {})
    if isinstance(value, dict):
        return value
    problems.append(f"{where}: '{key}' must be a table ([{key}.NAME] sections), "
                    f"got {type(value).__name__}")
    return {}


def _read_modules(table: dict[str, Any]) -> dict[str, ModuleSpec]:
    return {name: ModuleSpec.from_entry(name, entry) for name, entry in table.items()}


def _read_links(entries: Any, where: str, problems: list[str]) -> list[LinkSpec]:
    if not isinstance(entries, list):
        problems.append(f"{where}: must be an array of tables ([[links]] with from, to, policy)")
        return []
    links = []
    for number, entry in enumerate(entries, 1):
        try:
            links.append(LinkSpec.from_entry(entry))
        except ValueError as exc:
            problems.append(f"{where} #{number}: {exc}")
    return links
