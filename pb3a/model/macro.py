"""``Macro``: a module made of modules, declared in Python like a ``[macros.X]`` table.

A macro is a description, not a running thing: the configuration layer expands
it into its children (instance paths ``outer/inner/leaf``) and rewires links
to its exported ports onto the inner ports they name. ``Macro``'s docstring says
how to write one.
"""

from __future__ import annotations

import copy
from typing import Any, ClassVar


class Macro:
    """A module made of modules, in Python: subclass it and fill in three tables.

        class Filter(Macro):
            modules = {"lp": LowPass,
                       "gain": {"class": Scale, "state": {"gain": 2.0}, "period": 0.01},
                       "inner": OtherMacro}
            links = [("lp.y", "gain.x"), {"from": "gain.y", "to": "inner.x",
                                          "policy": "queue:8"}]
            exports = {"x": "lp.x", "y": "gain.y"}

    ``modules`` values: a Module class, a ``"module:Class"`` string, a Macro subclass,
    or a dict with the keys of a TOML module entry (``class`` or ``macro``, ``node``,
    ``period``, ``state``, ``restart``, ``group``). ``links``: ``(from, to)`` or
    ``(from, to, policy)`` tuples, or dicts with ``from``, ``to`` and optional
    ``policy``. ``exports``: external port name to ``"child.port"``. Add it to a
    system like a module (``System.add("f", Filter)``); its modules run as ``f/lp``,
    ``f/gain``, ... and move together (``run.migrate("f", to=...)``). Mistakes are
    reported by ``System.check()``/``pb3a check`` with every other problem.
    """

    modules: ClassVar[dict[str, Any]] = {}
    links: ClassVar[list[Any]] = []
    exports: ClassVar[dict[str, str]] = {}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        # Own copies, so that a subclass editing its tables never changes its parent's.
        for name in ("modules", "links", "exports"):
            setattr(cls, name, copy.copy(getattr(cls, name)))
