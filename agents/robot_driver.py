"""``RobotDriver``: a RAVE robot as PB3A ports.

It lives in ``agents/`` rather than ``rave/`` because it is a PB3A module: RAVE's
simulator core does not depend on PB3A, and the driver is where the two meet. It
talks to the robot's server (``rave start``) through its resource port, so the
controller behind its ports can run on any node; re-pointing ``resource`` moves it
to another robot while it runs (the old one is stopped first). Setting ``enabled`` to
False stops the robot safely: it is told to stop every period and commands are
ignored, while its sensors are still read out.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pb3a import Driver, Input, Output
from rave.server import readings


class RobotDriver(Driver):
    """Velocity command in; sonar, odometry, gps and camera out, every ``period``."""

    command = Input(np.ndarray, shape=(2,), dtype="float64")   # v (m/s), w (rad/s)
    sonar = Output(np.ndarray, shape=(16,), dtype="float64")
    odometry = Output(np.ndarray, shape=(3,), dtype="float64")
    gps = Output(np.ndarray, shape=(3,), dtype="float64")
    camera = Output(list)
    period = 0.1
    with_camera = False          # the camera costs a request more per period
    enabled = True               # False: keep the robot standing, ignore commands
    failures = 0                 # periods in which the robot did not answer
    last_error = ""

    def step(self) -> None:
        try:
            if not self.enabled:
                self.request("stop")
            elif self.command.has_value:
                v, w = self.command.read()
                self.request("drive", v=float(v), w=float(w))
            sensed = readings(self.request("sensors"))
            blobs = self.request("camera") if self.with_camera else None
        except (RuntimeError, OSError) as exc:
            self.failures += 1
            self.last_error = str(exc)
            return
        self.sonar.write(sensed["sonar"])
        self.odometry.write(sensed["odometry"])
        self.gps.write(sensed["gps"])
        if blobs is not None:
            self.camera.write(blobs)

    def release(self, client: Any) -> None:
        client.call("stop", self.timeout)          # leave the robot standing
