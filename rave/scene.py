"""``Scene``: a world as what moves and senses in it sees it.

``World`` builds the fleet, the robots and their bodies, so they do not import it:
they take their world as a ``Scene`` (``World`` is the one there is), or as a
protocol that adds what they alone can name (``HardwareHost``, ``RobotHost``).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import pymunk

from rave.camera import Target


class Scene(Protocol):
    """The world model's physics and clock, and what sensors sense in it."""

    space: pymunk.Space
    seed: int
    time: float                     # simulated seconds

    def segments(self, real: bool = True, virtual: bool = True) -> np.ndarray:
        """Every obstacle edge of the chosen layers, shape (n, 4)."""

    def depths(self, real: bool = True, virtual: bool = True) -> np.ndarray:
        """How far each of ``segments()`` has its obstacle behind it."""

    def all_discs(self) -> np.ndarray:
        """Every robot as (x, y, radius): the fleet's in slot order, then the hardware
        ones."""

    def discs(self, exclude: str | None = None) -> np.ndarray:
        """Every robot but ``exclude`` as (x, y, radius), shape (m, 3)."""

    def targets(self, exclude: str | None = None) -> list[Target]:
        """What cameras may see: every other robot, and coloured obstacles."""
