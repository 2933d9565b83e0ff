"""RAVE: a mixed real/virtual 2D robot environment.

Simulated robots and (emulated) hardware robots share one world model; virtual
obstacles exist only there, sensed by simulated robots and by hardware robots'
hybrid sensors. ``World`` builds and steps it; ``Robot`` is the one interface to
every robot, whichever back end serves it.
"""

from rave.camera import Blob
from rave.robot import Robot
from rave.world import World
from rave.worldfile import WorldError

__all__ = ["Blob", "Robot", "World", "WorldError"]
