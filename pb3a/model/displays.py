"""Custom displays: how a module asks tools (the State Editor) to show some of its state.

A module declares them with a class attribute, which is configuration, not state::

    displays = {"grid": "image", "error": "plot", "speed": ("gauge", 0.0, 1.0)}

``"image"`` shows a 2-D array as a picture, ``"plot"`` a number (or a small 1-D
array) over time, ``("gauge", min, max)`` a number between two bounds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

KINDS = ("image", "plot", "gauge")


@dataclass(frozen=True)
class Display:
    """How one state field is shown; ``low`` and ``high`` bound a gauge."""

    kind: str
    low: float | None = None
    high: float | None = None

    @classmethod
    def parse(cls, field: str, value: Any) -> Display:
        """Read one entry of a ``displays`` table; ValueError saying what it takes."""
        if value in ("image", "plot"):
            return cls(value)
        if (isinstance(value, (tuple, list)) and len(value) == 3 and value[0] == "gauge"
                and all(finite(bound) for bound in value[1:]) and value[1] < value[2]):
            return cls("gauge", float(value[1]), float(value[2]))
        raise ValueError(f"displays[{field!r}] = {value!r}: use \"image\", \"plot\" or "
                         "(\"gauge\", MIN, MAX) with MIN < MAX")

    def to_json(self) -> dict[str, Any]:
        """``{"kind": ...}``, with ``min`` and ``max`` for a gauge."""
        if self.kind == "gauge":
            return {"kind": self.kind, "min": self.low, "max": self.high}
        return {"kind": self.kind}


def declared_displays(cls: type) -> dict[str, Display]:
    """The displays class ``cls`` declares; ValueError naming each bad entry."""
    table = getattr(cls, "displays", None) or {}
    if not isinstance(table, dict):
        raise ValueError(f"{cls.__name__}.displays must be a dict of state name -> display, "
                         f"got {table!r}")
    found, problems = {}, []
    for field, value in table.items():
        try:
            found[str(field)] = Display.parse(str(field), value)
        except ValueError as exc:
            problems.append(str(exc))
    if problems:
        raise ValueError(f"{cls.__name__}: {'; '.join(problems)}")
    return found


def finite(value: Any) -> bool:
    """True for a finite int or float (a TOML ``true`` is neither, nor is NaN, nor an int
    no float can hold: ``10**400`` raised OverflowError where a refusal was due)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False
