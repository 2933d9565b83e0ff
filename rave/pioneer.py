"""The robot every RAVE robot is, a Pioneer 3-DX: its size, mass and speed limits,
shared by both back ends, the world model and ``Robot.drive``."""

import math

RADIUS = 0.25                       # m
MASS = 9.0                          # kg
MAX_SPEED = 1.5                     # m/s (a Pioneer 3-DX does 1.2 with a margin)
MAX_TURN = math.radians(300.0)      # rad/s
