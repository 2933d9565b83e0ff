"""World files: a world in TOML, read and checked whole before anything is built.

```toml
name = "arena"
size = [10.0, 8.0]                     # metres

[[walls]]
from = [0.0, 0.0]
to = [10.0, 0.0]                       # virtual = true: only in the world model

[[boxes]]
center = [5.0, 4.0]
size = [1.0, 1.0]                      # width, height in metres
angle = 0.0                            # degrees
virtual = true
color = "orange"                       # seen by cameras

[[polygons]]
points = [[1.0, 1.0], [2.0, 1.0], [1.5, 2.0]]

[[robots]]
name = "r1"
pose = [2.0, 2.0, 0.0]                 # x, y in metres, heading in degrees
backend = "sim"                        # or "hardware"
color = "red"
```

``read`` turns a file into a ``Plan``, plain data that ``World.load`` builds. Every
problem is reported at once (``WorldError``), each naming the entry; ``World.load``
adds those of robots placed where they overlap an obstacle or another robot.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rave.camera import rgb
from rave.robot import BACKENDS

WORLDS = Path(__file__).resolve().parent / "worlds"     # the bundled worlds
TOP = ("name", "size", "walls", "boxes", "polygons", "robots")
KEYS = {"walls": ("from", "to", "virtual"),
        "boxes": ("center", "size", "angle", "virtual", "color"),
        "polygons": ("points", "virtual", "color"),
        "robots": ("name", "pose", "backend", "color")}


class WorldError(ValueError):
    """A world file with problems; ``problems`` lists each one."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = problems
        super().__init__("\n".join(problems))


def world_file(name: str) -> Path:
    """A bundled world by name (``lab``, ``arena``, ...) or a path to a world file;
    ``WorldError`` naming the bundled worlds for a name that is neither."""
    path = Path(name)
    if path.suffix == ".toml" or path.is_file():     # (a directory named lab is not one)
        return path
    bundled = WORLDS / f"{name}.toml"
    if not bundled.exists():
        known = ", ".join(sorted(p.stem for p in WORLDS.glob("*.toml")))
        raise WorldError([f"no world {name!r}: the bundled worlds are {known}, or give the "
                          "path of a world file"])
    return bundled


@dataclass(frozen=True)
class Plan:
    """A checked world file in the API's units (radians): the world's name and size,
    and the keyword arguments of each of its ``add_wall``, ``add_box``,
    ``add_polygon`` and ``add_robot`` calls, in the order they are to be made."""

    name: str
    size: tuple[float, float]
    walls: list[dict[str, Any]]
    boxes: list[dict[str, Any]]
    polygons: list[dict[str, Any]]
    robots: list[dict[str, Any]]


def read(path: Path) -> Plan:
    """Read and check the world file at ``path``."""
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise WorldError([f"{path}: {exc}"]) from None
    problems = check(data, str(path))
    if problems:
        raise WorldError(problems)
    return Plan(
        name=data.get("name", path.stem), size=tuple(data.get("size", (10.0, 8.0))),
        walls=[{"start": wall["from"], "end": wall["to"], "virtual": wall.get("virtual", False)}
               for wall in data.get("walls", [])],
        boxes=[{"center": box["center"], "size": box["size"],
                "angle": math.radians(box.get("angle", 0.0)),
                "virtual": box.get("virtual", False), "color": box.get("color")}
               for box in data.get("boxes", [])],
        polygons=[{"points": polygon["points"], "virtual": polygon.get("virtual", False),
                   "color": polygon.get("color")} for polygon in data.get("polygons", [])],
        robots=[{"name": robot["name"], "pose": _pose(robot["pose"]),
                 "backend": robot.get("backend", "sim"), "color": robot.get("color", "red")}
                for robot in data.get("robots", [])])


def _pose(pose: list[float]) -> tuple[float, float, float]:
    x, y, heading = pose
    return (x, y, math.radians(heading))


def check(data: dict[str, Any], source: str) -> list[str]:
    """Every problem of a parsed world file, each naming its entry and the fix."""
    problems = [f"{source}: unknown key {key!r}; keys: {', '.join(TOP)}"
                for key in data if key not in TOP]
    if "size" in data and not _numbers(data["size"], 2, positive=True):
        problems.append(f"{source}: size must be [width, height] in metres, both > 0")
    if "name" in data and not (isinstance(data["name"], str) and data["name"]):
        problems.append(f"{source}: name must be a non-empty string")
    names: set[str] = set()
    for table, keys in KEYS.items():
        entries = data.get(table, [])
        if not isinstance(entries, list):
            problems.append(f"{source}: {table} must be an array of tables ([[{table}]])")
            continue
        for i, entry in enumerate(entries):
            where = f"{source} {table}[{i}]"
            if not isinstance(entry, dict):
                problems.append(f"{where}: must be a table")
                continue
            problems += [f"{where}: unknown key {key!r}; keys: {', '.join(keys)}"
                         for key in entry if key not in keys]
            problems += _entry(table, entry, where, names)
    return problems


def _entry(table: str, entry: dict[str, Any], where: str, names: set[str]) -> list[str]:
    problems = []
    points = {"walls": ("from", "to"), "boxes": ("center",)}.get(table, ())
    for key in points:
        if not _numbers(entry.get(key), 2):
            problems.append(f"{where}: {key} must be [x, y] in metres")
    if (table == "walls" and not problems and entry["from"] == entry["to"]):
        problems.append(f"{where}: from and to are the same point: a wall needs a length")
    if table == "boxes" and not _numbers(entry.get("size"), 2, positive=True):
        problems.append(f"{where}: size must be [width, height] in metres, both > 0")
    if table == "boxes" and "angle" in entry and not _numbers([entry["angle"]], 1):
        problems.append(f"{where}: angle must be a finite number of degrees")
    if table == "polygons":
        pts = entry.get("points")
        if not (isinstance(pts, list) and len(pts) >= 3 and all(_numbers(p, 2) for p in pts)):
            problems.append(f"{where}: points must be at least 3 [x, y] pairs")
    if "virtual" in entry and not isinstance(entry["virtual"], bool):
        problems.append(f"{where}: virtual must be true or false")
    if "color" in entry:
        try:
            if not isinstance(entry["color"], str):     # (an int failed in str's words)
                raise TypeError(f"color must be a name or \"#rrggbb\", not {entry['color']!r}")
            rgb(entry["color"])
        except (ValueError, TypeError) as exc:
            problems.append(f"{where}: {exc}")
    if table == "robots":
        name = entry.get("name")
        if not isinstance(name, str) or not name:
            problems.append(f"{where}: name must be a non-empty string")
        elif name in names:
            problems.append(f"{where}: a robot named {name!r} comes earlier")
        else:
            names.add(name)
        if not _numbers(entry.get("pose"), 3):
            problems.append(f"{where}: pose must be [x, y, heading in degrees]")
        if entry.get("backend", "sim") not in BACKENDS:
            problems.append(f"{where}: backend must be one of {', '.join(BACKENDS)}")
    return problems


def _numbers(value: Any, count: int, positive: bool = False) -> bool:
    return (isinstance(value, list) and len(value) == count
            and all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                    and (v > 0 or not positive) for v in value))
