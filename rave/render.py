"""Pictures of a world: a PNG (or SVG/PDF) of its obstacles and robots, and an
animated GIF of a recorded run, for READMEs and reports (matplotlib, headless).

Real obstacles are drawn solid and dark; virtual ones dashed and light blue (they
exist only in the world model). Robots are discs in their colour with a heading
line, hardware robots ringed in black; sonar readings can be drawn as their cones'
axes, and an occupancy map (probabilities in [0, 1]) laid under everything.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rave import sonar
from rave.camera import rgb
from rave.pioneer import RADIUS

if TYPE_CHECKING:
    from rave.world import World

REAL_COLOR, VIRTUAL_COLOR = "#333333", "#4a90d9"


@dataclass
class Frame:
    """What one picture shows: the world's description, and optionally sonar
    readings per robot and an occupancy map (array, extent x0, x1, y0, y1)."""

    world: dict[str, Any]
    sonar: dict[str, np.ndarray] = field(default_factory=dict)
    occupancy: tuple[np.ndarray, tuple[float, float, float, float]] | None = None


def snapshot(world: World, with_sonar: bool = True,
             occupancy: tuple[np.ndarray, tuple[float, float, float, float]] | None = None,
             ) -> Frame:
    """The world as it is now, as a frame."""
    readings = {name: robot.sonar() for name, robot in world.robots.items()} if with_sonar \
        else {}
    return Frame(world.describe(), readings, occupancy)


def render(world: World, path: str | Path, *, with_sonar: bool = True,
           occupancy: tuple[np.ndarray, tuple[float, float, float, float]] | None = None,
           dpi: int = 120) -> Path:
    """Draw ``world`` now to ``path`` (the suffix picks the format)."""
    plt = _pyplot()
    frame = snapshot(world, with_sonar, occupancy)
    figure, axes = _canvas(plt, frame.world)
    _draw(axes, frame)
    path = Path(path)
    figure.savefig(path, dpi=dpi, bbox_inches="tight")
    plt.close(figure)
    return path


def animate(frames: list[Frame], path: str | Path, fps: int = 10, dpi: int = 80) -> Path:
    """An animated GIF of recorded ``frames``."""
    plt = _pyplot()
    from matplotlib.animation import FuncAnimation, PillowWriter

    if not frames:
        raise ValueError("animate needs at least one frame")
    figure, axes = _canvas(plt, frames[0].world)

    def show(i: int) -> list[Any]:
        axes.clear()
        _frame_axes(axes, frames[i].world)
        _draw(axes, frames[i])
        return []
    animation = FuncAnimation(figure, show, frames=len(frames), blit=False)
    path = Path(path)
    animation.save(path, writer=PillowWriter(fps=fps), dpi=dpi)
    plt.close(figure)
    return path


def _pyplot() -> Any:
    try:
        import matplotlib
    except ImportError:
        raise RuntimeError("rendering needs matplotlib: pip install 'pb3a[plot]'") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _canvas(plt: Any, world: dict[str, Any]) -> tuple[Any, Any]:
    width, height = world["size"]
    scale = 6.0 / max(width, height)
    figure, axes = plt.subplots(figsize=(max(3.0, width * scale) + 0.5,
                                         max(3.0, height * scale) + 0.5))
    _frame_axes(axes, world)
    return figure, axes


def _frame_axes(axes: Any, world: dict[str, Any]) -> None:
    width, height = world["size"]
    axes.set_xlim(-0.2, width + 0.2)
    axes.set_ylim(-0.2, height + 0.2)
    axes.set_aspect("equal")
    axes.set_title(f"{world['name']}  t = {world['time']:.1f} s", fontsize=9)
    axes.tick_params(labelsize=7)


def _draw(axes: Any, frame: Frame) -> None:
    from matplotlib.patches import Circle, Polygon

    if frame.occupancy is not None:
        grid, extent = frame.occupancy
        axes.imshow(1.0 - grid, cmap="gray", origin="lower", extent=extent, vmin=0, vmax=1,
                    alpha=0.6, zorder=0)
    for obstacle in frame.world["obstacles"]:
        color = VIRTUAL_COLOR if obstacle["virtual"] else REAL_COLOR
        style = "--" if obstacle["virtual"] else "-"
        points = np.asarray(obstacle["points"])
        if obstacle["closed"]:
            fill = rgb(obstacle["color"]) if obstacle["color"] else color
            axes.add_patch(Polygon(points, closed=True, facecolor=fill,
                                   alpha=0.35 if obstacle["virtual"] else 0.8,
                                   edgecolor=color, linestyle=style, zorder=2))
        else:
            axes.plot(points[:, 0], points[:, 1], style, color=color,
                      linewidth=2.5 if not obstacle["virtual"] else 2.0, zorder=2)
    for name, robot in frame.world["robots"].items():
        x, y, theta = robot["pose"]
        readings = frame.sonar.get(name)
        if readings is not None:
            _cones(axes, (x, y, theta), readings, rgb(robot["color"]))
        hardware = robot["backend"] == "hardware"
        axes.add_patch(Circle((x, y), RADIUS, facecolor=rgb(robot["color"]),
                              edgecolor="black" if hardware else "none",
                              linewidth=1.5, zorder=4))
        axes.plot([x, x + RADIUS * 1.4 * math.cos(theta)],
                  [y, y + RADIUS * 1.4 * math.sin(theta)], color="black", linewidth=1.2,
                  zorder=5)
        axes.annotate(name, (x, y + RADIUS * 1.3), ha="center", fontsize=7, zorder=5)


def _cones(axes: Any, pose: tuple[float, float, float], readings: np.ndarray,
           color: tuple[float, float, float]) -> None:
    """Each transducer's reading as a thin wedge of its cone (echoes only)."""
    from matplotlib.patches import Wedge

    origins, headings, _ = sonar.ring_rays(np.asarray([pose]))
    for (ox, oy), heading, reading in zip(origins[0], headings[0], readings, strict=True):
        if reading >= sonar.MAX_RANGE:
            continue
        half = math.degrees(sonar.CONE) / 2
        axes.add_patch(Wedge((ox, oy), reading, math.degrees(heading) - half,
                             math.degrees(heading) + half, facecolor=color, alpha=0.12,
                             edgecolor="none", zorder=3))
