"""Your first robot (docs/first_robot.md): controllers for a RAVE robot, and an agent
that makes the robot more careful each time it comes too close to something.

Run with ``examples/first_robot.toml``, against a world served by ``rave start``.
"""

import numpy as np

from pb3a import Agent, Input, InputPort, Module, Output

# The sonar ring, as a Pioneer's: 0 looks left (+90 deg), 1-6 sweep round the front
# to 7, right (-90 deg); 8-15 look back. Ranges in metres, 5 m when nothing is seen.
FRONT = slice(2, 6)          # +30 to -30 deg
LEFT, RIGHT = slice(0, 3), slice(5, 8)


class Wanderer(Module):
    """Drives ahead at ``speed``; turns on the spot, away from the nearer side, while
    something is within ``clearance`` metres in front."""

    sonar = Input(np.ndarray, shape=(16,), dtype="float64")
    command = Output(np.ndarray, shape=(2,), dtype="float64")   # v (m/s), w (rad/s)
    speed = 0.3
    clearance = 0.6
    turn = 1.0

    def on_input(self, port: InputPort) -> None:
        ranges = port.read()
        if ranges[FRONT].min() < self.clearance:
            away = self.turn if ranges[LEFT].min() > ranges[RIGHT].min() else -self.turn
            self.command.write(np.array([0.0, away]))
        else:
            self.command.write(np.array([self.speed, 0.0]))


class WallFollower(Module):
    """Keeps a wall on its right ``distance`` metres away (turning in proportion to the
    error, by ``gain``), and turns left on the spot at a corner. The same ports and
    most of the same state as ``Wanderer``, so either can be swapped for the other."""

    sonar = Input(np.ndarray, shape=(16,), dtype="float64")
    command = Output(np.ndarray, shape=(2,), dtype="float64")
    speed = 0.3
    clearance = 0.6
    turn = 1.0
    distance = 0.5
    gain = 2.0

    def on_input(self, port: InputPort) -> None:
        ranges = port.read()
        if ranges[FRONT].min() < self.clearance:
            self.command.write(np.array([0.0, self.turn]))
        else:
            steer = np.clip(self.gain * (self.distance - ranges[7]), -self.turn, self.turn)
            self.command.write(np.array([self.speed, steer]))


class Cautious(Agent):
    """Watches the sonar; each time something comes within ``too_close`` metres of the
    robot's front, it slows the controller ``pilot`` down by ``slow_by`` (not below
    ``min_speed``), live, through the running system."""

    sonar = Input(np.ndarray, shape=(16,), dtype="float64")
    pilot = "pilot"
    too_close = 0.35
    slow_by = 0.8
    min_speed = 0.1
    near_misses = 0
    close = False               # within too_close at the last reading

    def on_input(self, port: InputPort) -> None:
        close = port.read()[FRONT].min() < self.too_close
        if close and not self.close:            # a new near miss, not the same one
            self.near_misses += 1
            speed = self.runtime.state(self.pilot)["speed"]
            self.runtime.set_state(self.pilot, speed=max(self.min_speed, speed * self.slow_by))
        self.close = close
