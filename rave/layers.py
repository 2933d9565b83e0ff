"""Collision categories of the world model (pymunk ``ShapeFilter`` bits).

A simulated robot collides with REAL and VIRTUAL obstacles and with robots; the
stand-in for a hardware robot's body in the world model collides with robots only
(its own physical world, in the emulator, has the real obstacles).
"""

REAL = 0b001
VIRTUAL = 0b010
ROBOT = 0b100
SEES_ALL = REAL | VIRTUAL | ROBOT

WALL_RADIUS = 0.02      # m: half the thickness of a wall in the physics
