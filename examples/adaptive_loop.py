"""A control loop that adapts itself: a macro (filter and PI controller) holds a noisy
plant at its setpoint, and an agent that watches the loop's error retunes the filter
and, when retuning is not enough, swaps it for another algorithm, live.

    python examples/adaptive_loop.py
"""

import random
import statistics
import time
from collections import deque
from itertools import pairwise

from pb3a import Agent, Input, Macro, Module, Output, System


class Plant(Module):
    """A first-order plant (time constant ``tau``), measured with Gaussian noise."""

    u = Input(float)
    y = Output(float)
    period = 0.01
    tau = 0.2
    noise = 0.01
    level = 0.0

    def step(self):
        push = self.u.read(default=0.0)
        self.level += (push - self.level) * self.period / self.tau
        self.y.write(self.level + random.gauss(0.0, self.noise))


class LowPass(Module):
    """An exponential moving average: smoother as ``alpha`` falls, and slower."""

    x = Input(float)
    y = Output(float)
    alpha = 0.5
    estimate = 0.0

    def on_input(self, port):
        self.estimate += self.alpha * (port.read() - self.estimate)
        self.y.write(self.estimate)


class Average(Module):
    """A moving average of the last ``window`` values: the same ports, another body."""

    x = Input(float)
    y = Output(float)
    window = 32

    def on_input(self, port):
        if not hasattr(self, "recent"):       # made once; a move or swap brings it back
            self.recent = deque(maxlen=self.window)
        self.recent.append(port.read())
        self.y.write(sum(self.recent) / len(self.recent))


class PI(Module):
    """A PI controller: ``u`` from the filtered measurement ``x`` against ``setpoint``."""

    x = Input(float)
    u = Output(float)
    error = Output(float)
    setpoint = 1.0
    kp, ki = 0.8, 2.0
    integral = 0.0

    def on_input(self, port):
        error = self.setpoint - port.read()
        self.integral += error * 0.01
        self.u.write(self.kp * error + self.ki * self.integral)
        self.error.write(error)


class Loop(Macro):
    """The controller's side of the loop: it moves, swaps and goes as one."""

    modules = {"filter": LowPass, "pi": PI}
    links = [("filter.y", "pi.x")]
    exports = {"x": "filter.x", "u": "pi.u", "error": "pi.error"}


class Tuner(Agent):
    """Watches the jitter of the loop's error over half a second (how much it changes
    from one value to the next: noise, not the loop's own settling): too much, and it
    halves the filter's ``alpha`` (retuning), as long as that stays 0.1 or more; then
    it swaps the filter for a moving average (another algorithm), once."""

    error = Input(float, policy="queue:256")
    period = 0.5
    limit = 0.02
    swapped = False
    jitter = 0.0
    actions = []                              # what it did, in order (its state)

    def step(self):
        errors = self.error.read_all()
        if len(errors) < 10:
            return
        self.jitter = statistics.stdev(b - a for a, b in pairwise(errors))
        if self.swapped or self.jitter <= self.limit:
            return
        alpha = self.runtime.state("loop/filter")["alpha"] / 2
        if alpha >= 0.1:
            self.runtime.set_state("loop/filter", alpha=alpha)
            self.actions.append(f"retuned alpha to {alpha:g}")
        else:
            self.runtime.swap("loop/filter", Average)
            self.swapped = True
            self.actions.append("swapped LowPass for Average")


if __name__ == "__main__":
    system = System("adaptive_loop")
    system.add("plant", Plant)
    system.add("loop", Loop)
    system.add("tuner", Tuner)
    system.link("plant.y", "loop.x")
    system.link("loop.u", "plant.u")
    system.link("loop.error", "tuner.error")
    with system.launch() as run:
        run.wait(2.0)
        tuner = run.state("tuner")
        print(f"settled at {run.state('plant')['level']:.2f}, jitter {tuner['jitter']:.3f}, "
              f"{len(tuner['actions'])} actions")
        run.set_state("plant", noise=0.3)     # the sensor gets noisy
        seen, deadline = 0, time.monotonic() + 20.0
        while time.monotonic() < deadline:   # follow the events until the agent's swap
            events = run.events(since=seen, timeout=deadline - time.monotonic())
            if any(event.kind == "module_swapped" for event in events):
                break
            seen = events[-1].seq if events else seen
        run.wait(1.5)
        tuner = run.state("tuner")
        print(*tuner["actions"], sep="\n")
        print(f"filter now {run.topology().modules['loop/filter'].cls}, "
              f"jitter {tuner['jitter']:.3f}")
