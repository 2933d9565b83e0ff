"""Live state kept in the document: what **Keep in document** writes.

A user tunes a running module (a PID's ``kp``, ``ki``, ``kd``) in the State Editor;
``proposal`` compares the module's live state with what the document gives it now
(its entry's ``state``, over the macro's own and the instances' overrides, else the
class's default) and ``write`` puts the values that differ into the document's
tables: into the module's ``state`` table, or for a module inside a macro instance
(``inst/child``) as that instance's override (``state = { child = { gain = 4.0 } }``),
as the page writes an edit of such a module.

Only *settings* are kept: a field the class declares as a class attribute whose
default TOML can hold (a number, a string, a flag, a list or table of them), and whose
live value TOML can hold too. Fields a module makes in ``setup`` or a step (not on
the class), arrays, objects and ``None`` are read-outs the document cannot hold, and
are named in ``not_kept`` with the reason. A counter declared on the class (``steps =
0``) is a setting by this rule: the module advances it itself, so it differs too;
``tuned`` (the fields set through the manager since the launch) tells the page which
to offer ticked, and a request may name the fields to keep.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from pb3a.config.folding import toml_value
from pb3a.errors import ConfigError
from pb3a.loading.references import class_ref
from pb3a.manager.document import check_data
from pb3a.model.module import Module


@dataclass
class Proposal:
    """What keeping module ``module``'s live state would write: for each setting that
    differs, the document's value and the live one (``changes``); the settings that are
    the same already (``same``); every other field and why it is not kept
    (``not_kept``); where it goes in the document (``where``, a dotted path of keys)."""

    module: str
    where: list[str]
    changes: dict[str, tuple[Any, Any]] = field(default_factory=dict)
    same: list[str] = field(default_factory=list)
    not_kept: dict[str, str] = field(default_factory=dict)


def proposal(data: dict[str, Any], source: str, name: str, running_cls: str,
             live: dict[str, Any]) -> Proposal:
    """What keeping ``live`` (module ``name``'s state now; it runs as ``running_cls``)
    writes into the document ``data`` (its tables); ConfigError when the document has
    no place for it (the module was added while it runs, or the document changed since
    the launch, or it runs as another class than the document gives it)."""
    plan = check_data(data, source)[0]
    given = plan.modules.get(name)
    if given is None:
        raise ConfigError([f"module {name} runs, but the document has no such module (it was "
                           "added while the system runs, or the document changed since the "
                           "launch): there is no entry to keep its state in"])
    ref = class_ref(given.cls)
    if ref != running_cls:
        raise ConfigError([f"module {name} runs as {running_cls}, but the document gives it "
                           f"{ref} (swapped while it runs): set its class in the document "
                           "first, then keep its state"])
    where = _place(data, name)
    found = Proposal(name, where)
    for key, value in live.items():
        why = _not_a_setting(given.cls, key, value)
        if why:
            found.not_kept[key] = why
            continue
        now = toml_value(value)
        held = toml_value(given.state[key] if key in given.state else getattr(given.cls, key))
        if _same(held, now):
            found.same.append(key)
        else:
            found.changes[key] = (held, now)
    return found


def write(data: dict[str, Any], found: Proposal, fields: list[str]) -> dict[str, Any]:
    """``data`` (changed in place, and answered) with the live values of ``fields`` (of
    ``found.changes``) in the module's ``state`` table or its instance's override."""
    entry_name, key = found.where[1], found.where[3] if len(found.where) > 3 else None
    modules = data["modules"]
    entry = modules[entry_name]
    if not isinstance(entry, dict):                 # `name = "pkg.mod:Class"`: a table now
        entry = modules[entry_name] = {"class": entry}
    state = entry.setdefault("state", {})
    table = state if key is None else state.setdefault(key, {})
    for name in fields:
        table[name] = found.changes[name][1]
    return data


def _place(data: dict[str, Any], name: str) -> list[str]:
    """Where module ``name``'s kept state goes: ``["modules", name, "state"]``, or for a
    module inside a macro instance ``["modules", instance, "state", "rest/of/path"]``
    (the outermost instance's override wins over the macro's and inner instances')."""
    instance, _, rest = name.partition("/")
    modules = data.get("modules")
    entry = modules.get(instance) if isinstance(modules, dict) else None
    if entry is None:
        raise ConfigError([f"module {name}: the document has no entry {instance!r} to keep "
                           "its state in (it changed since the launch)"])
    state = entry.get("state") if isinstance(entry, dict) else None
    if state is not None and not isinstance(state, dict):
        raise ConfigError([f"module {name}: the state of the document's entry {instance!r} "
                           f"is not a table ({state!r}): fix it first"])
    if rest and state is not None and not isinstance(state.get(rest, {}), dict):
        raise ConfigError([f"module {name}: instance {instance!r} sets its state as "
                           f"{state[rest]!r}, not a table: fix it first"])
    return ["modules", instance, "state", rest] if rest else ["modules", instance, "state"]


def _not_a_setting(cls: type[Module], key: str, value: Any) -> str:
    """Why field ``key`` (now ``value``) is not one the document keeps; "" when it is."""
    if key not in cls.state_names():
        return (f"not declared on {cls.__name__} (made while the module runs): a read-out, "
                "not a setting")
    default = getattr(cls, key)
    if toml_value(default) is None:
        return (f"its class's default ({type(default).__name__}) is no value TOML holds: a "
                "read-out, not a setting")
    if toml_value(value) is None:
        return f"its value now ({type(value).__name__}) is no value TOML holds"
    return ""


def _same(a: Any, b: Any) -> bool:
    """Whether two TOML values are the same setting: 2 and 2.0 are, True and 1 are not,
    NaN is NaN."""
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return type(a) is type(b) and a == b
