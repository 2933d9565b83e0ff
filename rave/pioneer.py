"""The robot every RAVE robot is, a Pioneer 3-DX: its size, mass, speed limits and how
its motors answer a command, shared by both back ends, the world model, ``Robot.drive``
and the agents that judge a robot's response."""

import math

RADIUS = 0.25                       # m
MASS = 9.0                          # kg
MAX_SPEED = 1.5                     # m/s (a Pioneer 3-DX does 1.2 with a margin)
MAX_TURN = math.radians(300.0)      # rad/s
MOTOR_LAG_S = 0.25                  # s: first-order lag of the motors
ACCEL = 0.3                         # m/s^2, as ARIA limits it
ANGULAR_ACCEL = math.radians(100.0)   # rad/s^2
