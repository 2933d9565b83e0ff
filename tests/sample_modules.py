"""Modules the runtime tests launch (importable, so workers load them by reference)."""

from __future__ import annotations

import ctypes
import logging
import os
import time

import numpy as np

from agents.traffic.max_pressure import MaxPressure
from agents.traffic.messages import JunctionReading, PhaseRequest
from pb3a import Agent, Driver, Input, Macro, Module, Output, RuntimeFailure, RuntimeTimeout


class Counter(Module):
    """Writes 1, 2, 3, ... every period until it has written ``limit`` values (0: forever)."""

    out = Output(int)
    period = 0.0
    count = 0
    limit = 0

    def step(self) -> None:
        if self.limit and self.count >= self.limit:
            return
        self.count += 1
        self.out.write(self.count)


class FailsOnce(Module):
    """Raises ``RuntimeError("once")`` in its third step, and never again."""

    steps = 0

    def step(self) -> None:
        self.steps += 1
        if self.steps == 3:
            raise RuntimeError("once")


class Burst(Module):
    """Writes ``limit`` values as fast as it can in one step, then idles."""

    out = Output(int)
    period = 0.01
    limit = 0
    sent = 0

    def step(self) -> None:
        while self.sent < self.limit:
            self.sent += 1
            self.out.write(self.sent)


class SlowState(Module):
    """A state that takes ``slow_s`` seconds to read (a large one, say)."""

    slow_s = 0.0

    def get_state(self) -> dict:
        time.sleep(self.slow_s)
        return super().get_state()


class Collector(Module):
    """Checks the values it receives are 1, 2, 3, ... in order, counting any violation."""

    x = Input(int, policy="queue:1000000")
    received = 0
    last = 0
    out_of_order = 0
    duplicates = 0
    delay = 0.0

    def on_input(self, port) -> None:
        value = port.read()
        if value == self.last:
            self.duplicates += 1
        elif value < self.last:
            self.out_of_order += 1
        self.last = value
        self.received += 1
        if self.delay:
            time.sleep(self.delay)


class Scale(Module):
    x = Input(float)
    y = Output(float)
    gain = 2.0
    setups = 0

    def setup(self) -> None:
        self.setups += 1

    def on_input(self, port) -> None:
        self.y.write(port.read() * self.gain)


class FastScale(Scale):
    """Same ports and state as Scale, a different body: adds one."""

    def on_input(self, port) -> None:
        self.y.write(port.read() * self.gain + 1.0)


class PlainScale(Module):
    """Scale's ports and gain, without its count of setups."""

    x = Input(float)
    y = Output(float)
    gain = 2.0

    def on_input(self, port) -> None:
        self.y.write(port.read() * self.gain)


class Offset(Module):
    """Incompatible with Scale: its input carries str."""

    x = Input(str)
    y = Output(float)


class FloatSource(Module):
    out = Output(float)
    period = 0.005
    value = 1.0

    def step(self) -> None:
        self.out.write(float(self.value))


class Last(Module):
    """Keeps the latest float it received."""

    x = Input(float)
    value = 0.0
    seen = 0

    def on_input(self, port) -> None:
        self.value = port.read()
        self.seen += 1


class Pid(Module):
    """Reports the process it runs in."""

    period = 0.05
    pid = 0

    def step(self) -> None:
        self.pid = os.getpid()


class Faulty(Module):
    """Raises in every other step; counts the steps that went through."""

    period = 0.005
    calls = 0
    good = 0

    def step(self) -> None:
        self.calls += 1
        if self.calls % 2:
            raise ValueError("odd step")
        self.good += 1


class Idle(Module):
    """An event-driven module that never receives anything."""

    x = Input(int)

    def on_input(self, port) -> None:
        port.read()


class Doubler(Agent):
    """An agent that raises another module's gain each time it is told to."""

    go = Input(int)
    target = "scale"

    def on_input(self, port) -> None:
        port.read()
        gain = self.runtime.state(self.target)["gain"]
        self.runtime.set_state(self.target, gain=gain * 2)


class ArraySource(Module):
    out = Output(np.ndarray, shape=(1024, 128), dtype="float64")
    period = 0.01
    n = 0

    def step(self) -> None:
        self.n += 1
        self.out.write(np.full((1024, 128), float(self.n)))


class ArrayReuser(ArraySource):
    """Writes one buffer again and again, scribbling over it (-1) right after each write."""

    period = 0.002

    def setup(self) -> None:
        self._buffer = np.zeros((1024, 128))

    def step(self) -> None:
        self.n += 1
        self._buffer[:] = float(self.n)
        self.out.write(self._buffer)
        self._buffer[:] = -1.0


class ArraySink(Module):
    x = Input(np.ndarray, shape=(1024, 128), dtype="float64")
    sums_ok = 0
    scribbled = 0          # arrays holding what the writer put in after writing them
    owned = 0              # arrays that own their memory (copies, not views of a ring)
    writable = False

    def on_input(self, port) -> None:
        arr = port.read()
        self.writable = bool(arr.flags.writeable)
        self.owned += bool(arr.flags.owndata)
        if float(arr[0, 0]) * arr.size == float(arr.sum()):
            self.sums_ok += 1
        if float(arr.min()) < 0:
            self.scribbled += 1


class Chain(Macro):
    """scale -> scale, exporting the first input and the last output."""

    modules = {"a": Scale, "b": {"class": Scale, "state": {"gain": 3.0}}}
    links = [("a.y", "b.x")]
    exports = {"x": "a.x", "y": "b.y"}


class Outer(Macro):
    """A macro holding a macro: x -> chain -> last."""

    modules = {"chain": Chain, "tail": Scale}
    links = [("chain.y", "tail.x")]
    exports = {"x": "chain.x", "y": "tail.y"}


class Steady(Module):
    """Counts its steps; restart tests read ``count`` to see which state came back."""

    period = 0.01
    count = 0
    pid = 0

    def step(self) -> None:
        self.pid = os.getpid()
        self.count += 1


class MapMaker(Module):
    """Makes its state as it runs, as a mapper makes its map: ``grid`` in ``setup``
    (only when absent: a move, a swap or a restart brings it back first), ``updates``
    at its first step. Neither is declared on the class."""

    period = 0.005
    setups = 0
    pid = 0

    def setup(self) -> None:
        self.setups += 1
        if not hasattr(self, "grid"):
            self.grid = np.zeros((20, 20))

    def step(self) -> None:
        self.pid = os.getpid()
        self.updates = getattr(self, "updates", 0) + 1
        self.grid[0, 0] += 1


class MapMakerV2(MapMaker):
    """A new version of ``MapMaker`` (another body), for swaps."""

    def step(self) -> None:
        super().step()
        self.grid[1, 1] += 1


class SlowTeardown(Module):
    """A module whose teardown never finishes in time."""

    period = 0.05

    def teardown(self) -> None:
        time.sleep(60)


class CollectorV2(Collector):
    """Collector with another body, for swaps in the middle of a stream."""

    swapped_in = 0

    def setup(self) -> None:
        self.swapped_in += 1


class Overlap(Module):
    """Both threaded and event-driven; counts any overlap of its two bodies."""

    x = Input(int, policy="queue:100000")
    period = 0.0
    busy = False
    overlaps = 0
    steps = 0
    events = 0

    def step(self) -> None:
        self._enter()
        self.steps += 1
        time.sleep(0.0002)
        self.busy = False

    def on_input(self, port) -> None:
        self._enter()
        port.read()
        self.events += 1
        time.sleep(0.0001)
        self.busy = False

    def _enter(self) -> None:
        if self.busy:
            self.overlaps += 1
        self.busy = True


class Busy(Module):
    """Period 0: steps back to back, each step holding the module lock for 5 ms."""

    period = 0.0
    steps = 0

    def step(self) -> None:
        self.steps += 1
        time.sleep(0.005)


class Journal(Module):
    """Appends its name to ``path`` in ``setup`` and ``teardown`` (start and stop order);
    its setup takes ``setup_s`` seconds after its note, its teardown ``teardown_s``
    before, and waits while the file ``hold`` exists (up to 30 s); its teardown makes
    the file ``began`` (if named) as it begins."""

    period = 0.05
    path = ""
    label = ""
    setup_s = 0.0
    teardown_s = 0.0
    hold = ""
    began = ""

    def setup(self) -> None:
        self._note("start")
        time.sleep(self.setup_s)

    def teardown(self) -> None:
        if self.began:
            open(self.began, "w").close()
        time.sleep(self.teardown_s)
        until = time.monotonic() + 30.0
        while self.hold and os.path.exists(self.hold) and time.monotonic() < until:
            time.sleep(0.01)
        self._note("stop")

    def _note(self, what: str) -> None:
        with open(self.path, "a") as journal:
            journal.write(f"{what} {self.label}\n")


class HeldInTeardown(Journal):
    """A ``Journal`` whose teardown notes "stopping LABEL" as it begins, then waits while
    ``hold`` exists and ``after_s`` more before its "stop": a test acts while the
    teardown is under way, and sees whether it ran to its end."""

    after_s = 0.0

    def teardown(self) -> None:
        self._note("stopping")
        until = time.monotonic() + 30.0
        while self.hold and os.path.exists(self.hold) and time.monotonic() < until:
            time.sleep(0.01)
        time.sleep(self.after_s)
        self._note("stop")


class Spawner(Agent):
    """On its first value spawns a probe, links it, then removes it on the next one."""

    go = Input(int, policy="queue:8")
    seen = 0
    error = ""

    def on_input(self, port) -> None:
        port.read()
        self.seen += 1
        if self.seen == 1:
            self.runtime.spawn("probe", Last)
            self.runtime.link("scale.y", "probe.x")
            try:
                self.runtime.set_state("agent", seen=0)
            except ValueError as exc:
                self.error = str(exc)
        elif self.seen == 2:
            self.runtime.remove("probe")


class ChangesToAClass(Agent):
    """On its first value swaps ``scale`` for the class ``cls`` names, then spawns one as
    ``extra``, each given 2 s: ``said``, what each call raised ("" if nothing), and
    ``took``, how long each took."""

    go = Input(int)
    cls = "sample_modules:FastScale"
    said: list[str] = []
    took: list[float] = []

    def on_input(self, port) -> None:
        port.read()
        for change in (lambda: self.runtime.swap("scale", self.cls, timeout=2.0),
                       lambda: self.runtime.spawn("extra", self.cls, timeout=2.0)):
            began = time.monotonic()
            try:
                change()
                self.said.append("")
            except Exception as exc:
                self.said.append(f"{type(exc).__name__}: {exc}")
            self.took.append(time.monotonic() - began)


class Crasher(Module):
    """Kills its own worker process on its first step: a crash loop."""

    period = 0.01

    def step(self) -> None:
        os._exit(3)


class CrashesWhileFlagged(Module):
    """Kills its own worker process on its first step while the file ``flag`` exists;
    steps and counts once it is gone."""

    period = 0.01
    flag = ""
    steps = 0

    def step(self) -> None:
        if os.path.exists(self.flag):
            os._exit(3)
        self.steps += 1


class ArrayHolder(Module):
    """Keeps up to 10 arrays as zero-copy views and never reads them."""

    x = Input(np.ndarray, shape=(1024, 128), dtype="float64", policy="queue:10")


class Hoard(Module):
    """Event-driven, with 6 MiB of numpy state: ``grid`` (float32) and ``marks`` (int16,
    Fortran order); the n-th value it gets goes into ``grid.flat[n - 1]`` (the module
    the big-state migration tests move)."""

    x = Input(int, policy="queue:1000")
    shape = (1024, 1024)
    grid: np.ndarray | None = None
    marks: np.ndarray | None = None
    stored = 0

    def setup(self) -> None:
        if self.grid is None:                   # (a moved module keeps what it brought)
            self.grid, self.marks = self.expected(0)

    def on_input(self, port) -> None:
        self.grid.flat[self.stored] = port.read()
        self.stored += 1

    @classmethod
    def expected(cls, stored: int) -> tuple[np.ndarray, np.ndarray]:
        """``grid`` and ``marks`` after values 1, 2, ... ``stored``."""
        grid = np.linspace(-1.0, 1.0, cls.shape[0] * cls.shape[1], dtype=np.float32)
        grid[:stored] = np.arange(1, stored + 1)
        marks = np.arange(grid.size, dtype=np.int16).reshape(cls.shape, order="F")
        return grid.reshape(cls.shape), marks


class Relay(Module):
    """Passes every value on, counting them (the module the migration tests move)."""

    x = Input(int, policy="queue:100000")
    out = Output(int)
    relayed = 0
    setups = 0

    def setup(self) -> None:
        self.setups += 1

    def on_input(self, port) -> None:
        self.out.write(port.read())
        self.relayed += 1



class FailingRelay(Relay):
    """A relay whose every call raises, once its value is passed on, while ``failing``."""

    failing = False

    def on_input(self, port) -> None:
        super().on_input(port)
        if self.failing:
            raise RuntimeError("told to fail")


class RelayPair(Macro):
    """relay -> relay: a macro the migration tests move under a steady flow."""

    modules = {"first": Relay, "second": Relay}
    links = [("first.out", "second.x")]
    exports = {"x": "first.x", "out": "second.out"}

class Wanderer(Agent):
    """An agent that moves itself to node ``to`` once it has seen ``after`` values."""

    x = Input(int, policy="queue:100000")
    seen = 0
    after = 20
    to = "b"
    asked = False

    def on_input(self, port) -> None:
        port.read()
        self.seen += 1
        if self.seen >= self.after and not self.asked:
            self.asked = True
            self.runtime.migrate(self.runtime.name, self.to)


class LossWatcher(Agent):
    """Records the nodes its env module reports lost (the failure event)."""

    lost = Input(str, policy="queue:10")
    seen: list = []

    def on_input(self, port) -> None:
        self.seen.append(port.read())


class NodeTable(Module):
    """Keeps the last node table an env module sent (health and round-trip times)."""

    nodes = Input(dict)
    table: dict = {}

    def on_input(self, port) -> None:
        self.table = port.read()


class Cruise(Module):
    """Drives straight at ``speed`` and counts the sonar scans it receives."""

    sonar = Input(np.ndarray, shape=(16,), dtype="float64")
    command = Output(np.ndarray, shape=(2,), dtype="float64")
    period = 0.05
    speed = 0.3
    scans = 0

    def step(self) -> None:
        if self.sonar.pending:
            self.sonar.read()
            self.scans += 1
        self.command.write(np.array([self.speed, 0.0]))


class Spin(Module):
    """Turns a robot in place at ``turn`` rad/s: writes its command every step, or with
    ``once`` only at its first (a controller that writes only on change)."""

    command = Output(np.ndarray, shape=(2,), dtype="float64")
    period = 0.05
    turn = 0.5
    once = False
    written = 0

    def step(self) -> None:
        if not (self.once and self.written):
            self.command.write(np.array([0.0, self.turn]))
            self.written += 1


class Busybody(Agent):
    """An agent that, every step, asks the runtime about its peers in turn: their state,
    the system's figures, an edit of their state, a swap (to its own class, keeping
    state), or a move of the first peer to the next node. It counts what it asked and
    what was refused, and keeps the first unexpected error."""

    period = 0.001
    peers: list = []
    nodes: list = []
    asked = 0
    refused = 0          # requests cancelled because the runtime had to pause this agent
    # ... what they said of running later: "withdrawn", "may run" (each kind once)
    cancels_said: list = []
    poked = 0            # set by the others
    unexpected = ""

    def step(self) -> None:
        peer = self.peers[self.asked % len(self.peers)]
        try:
            match self.asked % 5:
                case 0:
                    self.runtime.state(peer)
                case 1:
                    self.runtime.stats()
                case 2:
                    self.runtime.set_state(peer, poked=self.asked)
                case 3:
                    self.runtime.swap(peer, type(self))
                case _:
                    if self.nodes:
                        self.runtime.migrate(peer, self.nodes[self.asked % len(self.nodes)])
        except Exception as exc:
            if "cancelled" in str(exc):
                self.refused += 1
                said = ("withdrawn" if str(exc).endswith("it was withdrawn and will not run")
                        else "may run" if "may still be carried out" in str(exc) else str(exc))
                if said not in self.cancels_said:
                    self.cancels_said = [*self.cancels_said, said]
            elif not self.unexpected:
                self.unexpected = f"{type(exc).__name__}: {exc}"
        self.asked += 1


class Sipper(Module):
    """A slow reader: each step reads at most ``sip`` values (0: none, a stuck reader),
    checking they are 1, 2, 3, ... in order."""

    x = Input(int, policy="lossless:8")
    period = 0.002
    sip = 0
    received = 0
    last = 0
    out_of_order = 0
    duplicates = 0

    def step(self) -> None:
        for _ in range(self.sip):
            value = self.x.read(None)
            if value is None:
                return
            if value == self.last:
                self.duplicates += 1
            elif value != self.last + 1:
                self.out_of_order += 1
            self.last = value
            self.received += 1


class Pusher(Module):
    """Writes 1, 2, 3, ... as fast as it can, up to ``limit`` (0: forever), each write
    waiting at most ``timeout`` seconds (0: the default); a write that fails is tried
    again with the same value at the next step, so ``sent`` counts values that went."""

    out = Output(int)
    period = 0.0
    limit = 0
    timeout = 0.0
    sent = 0

    def step(self) -> None:
        if self.limit and self.sent >= self.limit:
            time.sleep(0.005)
            return
        self.out.write(self.sent + 1, timeout=self.timeout or None)
        self.sent += 1


class SipperV2(Sipper):
    """Sipper with another body, for swaps in the middle of a lossless stream."""

    swapped_in = 0

    def setup(self) -> None:
        self.swapped_in += 1


class Spinner(Module):
    """Burns CPU while ``spinning``: the node's own load."""

    period = 0.0
    spinning = True

    def step(self) -> None:
        if not self.spinning:
            time.sleep(0.01)
            return
        end = time.thread_time() + 0.01
        while time.thread_time() < end:
            pass


class Shepherd(Agent):
    """Moves ``flock`` to ``to`` without waiting, then follows the move through its
    pending result, ``runtime.where`` and its env port's ``module_moved`` event."""

    moved = Input(dict, policy="queue:64")
    flock = "relay"
    to = "b"
    period = 0.05
    asked = False
    done_before = None
    report: dict = {}
    where = ""
    seen_moves: list = []

    def step(self) -> None:
        if not self.asked:
            self.asked = True
            self._pending = self.runtime.migrate(self.flock, self.to, wait=False)
            self.done_before = self._pending.done()
        elif not self.report and self._pending.done():
            self.report = vars(self._pending.result(1.0))
            self.where = self.runtime.where(self.flock)

    def on_input(self, port) -> None:
        self.seen_moves.append(port.read())


class Paced(Module):
    """Counts its steps and notes the period it sees (``self.period``) at each."""

    period = 0.01
    count = 0
    seen_period = 0.0

    def step(self) -> None:
        self.count += 1
        self.seen_period = self.period


class SetsItsPeriod(Module):
    """Notes when each of its last steps began (``time.monotonic()``); at the step after
    ``to`` is set, assigns itself that period (``self.period = to``), once, noting when
    (``assigned_at``), and ``to`` goes back to 0."""

    period = 0.01
    to = 0.0
    assigned_at = 0.0
    stamps: list = []
    seen_period = 0.0

    def step(self) -> None:
        self.stamps = [*self.stamps[-9:], time.monotonic()]
        self.seen_period = self.period
        if self.to:
            self.period, self.to = self.to, 0.0
            self.assigned_at = time.monotonic()


class AssignsThenFails(Module):
    """Its setup assigns itself a period of 1.5 s, then raises: a swap to it fails."""

    period = 0.01

    def setup(self) -> None:
        self.period = 1.5
        raise RuntimeError("cannot start")

    def step(self) -> None:
        pass


class Reassigns(Module):
    """At the step after ``go`` is set: assigns itself 0.03, then 0.04, watches its
    period for up to 1 s, until it changes by itself, then assigns itself 0.03, its last
    word; notes the period it sees at each of its steps from then on (``after``)."""

    period = 0.02
    go = False
    done = False
    after: list = []

    def step(self) -> None:
        if self.done:
            self.after = [*self.after[-50:], self.period]
        if self.go:
            self.go = False
            self.period = 0.03
            self.period = 0.04
            deadline = time.monotonic() + 1.0
            while self.period == 0.04 and time.monotonic() < deadline:
                time.sleep(0.0002)
            self.period = 0.03
            self.done = True


class AdaptsItsRate(Module):
    """Assigns itself another period at every step (an adaptive rate)."""

    period = 0.01
    count = 0

    def step(self) -> None:
        self.count += 1
        self.period = 0.01 if self.count % 2 else 0.011


class SlowsTwiceResets(Module):
    """Steps every 0.02 s; at its 3rd step assigns itself 0.1, at its 4th 0.25; its
    teardown puts its class's period back (``self.period = type(self).period``). Notes
    when its last steps began (``stamps``) and the period it saw (``seen_period``)."""

    period = 0.02
    count = 0
    stamps: list = []
    seen_period = 0.0

    def step(self) -> None:
        self.count += 1
        self.stamps = [*self.stamps[-9:], time.monotonic()]
        self.seen_period = self.period
        if self.count in (3, 4):
            self.period = 0.1 if self.count == 3 else 0.25

    def teardown(self) -> None:
        self.period = type(self).period


class AssignsNoPeriods(Module):
    """At each step, assigns itself each of ``tried`` as its period, noting what each
    assignment raised (or "" if none) and the period it then sees."""

    period = 0.02
    tried: list = []
    raised: list = []
    seen: list = []

    def step(self) -> None:
        for value in self.tried:
            try:
                self.period = value
                self.raised.append("")
            except Exception as exc:
                self.raised.append(f"{type(exc).__name__}: {exc}")
            self.seen.append(self.period)
        self.tried = []


class ListensOnly(Module):
    """Handles its input's values only (no ``step()``); its setup assigns itself
    ``period``, noting what that raised."""

    x = Input(int)
    raised = ""

    def setup(self) -> None:
        try:
            self.period = 0.05
        except Exception as exc:
            self.raised = f"{type(exc).__name__}: {exc}"

    def on_input(self, port) -> None:
        port.read()


class StepsOnceSetUp(Module):
    """Handles its input's values and has a ``step()`` but no period: its setup gives it
    one (``self.period = 0.05``), and it steps from then on, counting its steps."""

    x = Input(int)
    count = 0

    def setup(self) -> None:
        self.period = 0.05

    def step(self) -> None:
        self.count += 1

    def on_input(self, port) -> None:
        port.read()


class Drifter(Module):
    """Counts its steps; its class refuses a ``count`` above 3, which its steps pass."""

    period = 0.01
    count = 0
    gain = 1.0

    @classmethod
    def state_problems(cls, state: dict) -> list[str]:
        problems = super().state_problems(state)
        if state.get("count", 0) > 3:
            problems.append(f"Drifter's count must be at most 3, got {state['count']!r}")
        return problems

    def step(self) -> None:
        self.count += 1


class SlowsItself(Agent):
    """Notes when each of its last steps began (``time.monotonic()``); at its third step,
    sets its own period to ``to`` seconds."""

    period = 0.2
    to = 1.0
    stamps: list = []

    def step(self) -> None:
        self.stamps = [*self.stamps[-9:], time.monotonic()]
        if len(self.stamps) == 3:
            self.runtime.set_state(self.runtime.name, period=self.to)


class Retimer(Agent):
    """Once, from its step, slows ``target`` to a period of ``to`` seconds."""

    target = "paced"
    to = 0.25
    period = 0.05
    done = ""

    def step(self) -> None:
        if not self.done:
            self.runtime.set_state(self.target, period=self.to)
            self.done = "yes"


class Commander(Agent):
    """Writes a setpoint to ``target`` at every step, and once, from that step, moves it
    to ``to`` (waiting for the move), then relinks its command to ``then`` and back:
    what each request answered, or raised."""

    command = Output(int)
    target = "relay"
    to = "b"
    then = "other.x"
    period = 0.05
    asked = False
    answers: list = []

    def step(self) -> None:
        self.command.write(1)
        if self.asked:
            return
        self.asked = True
        for request in (lambda: self.runtime.migrate(self.target, self.to),
                        lambda: self.runtime.relink("commander.command", self.then),
                        lambda: self.runtime.relink("commander.command", f"{self.target}.x")):
            try:
                self.answers.append(type(request()).__name__)
            except Exception as exc:
                self.answers.append(f"{type(exc).__name__}: {exc}")


class Locator(Agent):
    """Asks the runtime where ``other`` runs from its ``setup``, as the system starts."""

    other = "src"
    found = ""

    def setup(self) -> None:
        self.found = self.runtime.where(self.other)


class Watcher(Agent):
    """Each step, looks at module ``other`` through the runtime: where it runs, the
    change in progress its figures name, and the longest the two answers took."""

    period = 0.05
    other = "src"
    seen_node = ""
    seen_change = ""
    took_s = 0.0
    failed = ""

    def step(self) -> None:
        started = time.monotonic()
        try:
            change = self.runtime.stats(timeout=5.0).modules[self.other].change
            node = self.runtime.where(self.other, timeout=5.0)
        except RuntimeFailure as exc:
            self.failed = str(exc)
            return
        self.took_s = max(self.took_s, time.monotonic() - started)
        self.seen_node, self.seen_change = node, change


class LocatorToo(Locator):
    """A ``Locator`` to swap in; it also reads ``other``'s state from its ``setup``."""

    peers: list = []

    def setup(self) -> None:
        super().setup()
        self.peers = self.runtime.state(self.other)["peers"]


class RemovesInSetup(Agent):
    """Tries to remove ``other`` from its ``setup``; keeps what the runtime said."""

    other = "src"
    refused = ""

    def setup(self) -> None:
        try:
            self.runtime.remove(self.other)
        except RuntimeFailure as exc:
            self.refused = str(exc)


class Chatty(Module):
    """Logs a warning of its own at its first step."""

    period = 0.05
    said = False

    def step(self) -> None:
        if not self.said:
            self.said = True
            import logging

            logging.getLogger("chatty").warning("hello from a module's own logger")


class Stamped(Module):
    """Writes ``"COPY:N"`` every period. COPY names this copy of the module: new when it
    starts fresh, kept when it moves (it is state). Its teardown notes when this copy
    stopped, in ``stopped_file``."""

    out = Output(str)
    period = 0.002
    copy = ""
    n = 0
    stopped_file = ""

    def setup(self) -> None:
        self.copy = self.copy or f"{os.getpid()}-{time.monotonic_ns()}"

    def step(self) -> None:
        self.n += 1
        self.out.write(f"{self.copy}:{self.n}")

    def teardown(self) -> None:
        if self.stopped_file:
            with open(self.stopped_file, "a") as notes:
                notes.write(f"{self.copy} {time.time()}\n")


class Copies(Module):
    """Which copy of a ``Stamped`` writer each value came from: the copies in the order
    of their first value and when it came; ``stale`` counts values of a copy that came
    after a newer copy's."""

    x = Input(str, policy="queue:100000")
    copies: list = []
    first_at: list = []
    received = 0
    stale = 0

    def on_input(self, port) -> None:
        copy = port.read().partition(":")[0]
        self.received += 1
        if copy not in self.copies:
            self.copies = [*self.copies, copy]
            self.first_at = [*self.first_at, time.time()]
        elif copy != self.copies[-1]:
            self.stale += 1


class MoveLog(Module):
    """Keeps every move its env module reports (migrations and failovers)."""

    moved = Input(dict, policy="queue:100")
    moves: list = []

    def on_input(self, port) -> None:
        self.moves = [*self.moves, port.read()]


class Mapper(Module):
    """Fills an occupancy-like grid, one cell per step; declares custom displays."""

    x = Input(float)
    period = 0.01
    grid = np.zeros((8, 8))
    cells = 0
    speed = 0.5
    label = "map"
    displays = {"grid": "image", "cells": "plot", "speed": ("gauge", 0.0, 1.0)}

    def step(self) -> None:
        self.grid[divmod(self.cells % 64, 8)] += self.speed
        self.cells += 1


class PhaseAlternator(Module):
    """A traffic junction's controller for the driver's tests: answers every reading
    at once, asking for each green phase in turn for ``hold`` steps."""

    reading = Input(JunctionReading, policy="queue:8")
    request = Output(PhaseRequest)
    hold = 10
    answered = 0

    def on_input(self, port) -> None:
        for reading in port.read_all():
            green = (reading.step // self.hold) % len(reading.layout.greens)
            self.request.write(PhaseRequest(reading.junction, reading.step, green,
                                            reading.run))
            self.answered += 1


class SlowToSwapIn(MaxPressure):
    """Max-pressure whose setup takes ``SETUP_S`` (a swap to it takes that long); it
    keeps the step of the first reading it answers."""

    SETUP_S = 0.3
    first_step = -1

    def setup(self) -> None:
        time.sleep(self.SETUP_S)
        super().setup()

    def choose(self, reading: JunctionReading) -> int:
        if self.first_step < 0:
            self.first_step = reading.step
        return super().choose(reading)


class Shift(Module):
    """Scale's ports with other state (no ``gain``): what a swap may bring in."""

    x = Input(float)
    y = Output(float)
    offset = 1.0

    def on_input(self, port) -> None:
        self.y.write(port.read() + self.offset)


class AsksInSetup(Agent):
    """Asks the runtime for module ``other``'s state from its ``setup`` (as agents may),
    once ``ask`` is set."""

    period = 0.02
    other = "other"
    ask = True
    asked = -1
    steps = 0
    pid = 0

    def setup(self) -> None:
        if self.ask:
            self.asked = self.runtime.state(self.other)["count"]

    def step(self) -> None:
        self.pid = os.getpid()
        self.steps += 1


class Join(Module):
    """Counts what comes in on each of two inputs."""

    x = Input(int, policy="queue:100000")
    y = Input(int, policy="queue:100000")
    xs = 0
    ys = 0

    def on_input(self, port) -> None:
        port.read_all()
        if port.name == "x":
            self.xs += 1
        else:
            self.ys += 1


class Staller(Module):
    """Counts up like ``Counter``; a step stalls for ``stall_s`` seconds once it is set."""

    out = Output(int)
    period = 0.01
    count = 0
    stall_s = 0.0

    def step(self) -> None:
        if self.stall_s:
            time.sleep(self.stall_s)
        self.count += 1
        self.out.write(self.count)


class StepStamps(Module):
    """Appends its pid and the time (``time.monotonic``, one clock for every process) of
    each step to ``path``: when a module (or a copy of it) last stepped, read after its
    process is gone. Its setup writes its pid to ``path``.pid and then takes ``setup_s``."""

    period = 0.01
    path = ""
    setup_s = 0.0

    def setup(self) -> None:
        if self.setup_s:
            with open(f"{self.path}.pid", "w") as pid:
                pid.write(str(os.getpid()))
            time.sleep(self.setup_s)

    def step(self) -> None:
        began = time.monotonic()    # (a step frozen in its open() began before the freeze)
        with open(self.path, "a") as stamps:
            stamps.write(f"{os.getpid()} {began}\n")


class SlowToStop(StepStamps):
    """``StepStamps`` whose teardown takes ``teardown_s`` and then stamps as a step does:
    a copy's teardown that ran beside its next copy shows as a step out of turn."""

    teardown_s = 1.5

    def teardown(self) -> None:
        time.sleep(self.teardown_s)
        self.step()


class BlocksInInit(Module):
    """Its construction, which runs on its worker's control thread, writes the worker's
    pid to ``pid_file`` (set on a subclass) and then blocks for ``BLOCK_S``."""

    BLOCK_S = 30.0
    pid_file = ""

    def __init__(self) -> None:
        super().__init__()
        with open(self.pid_file, "w") as pid:
            pid.write(str(os.getpid()))
        time.sleep(self.BLOCK_S)


class BlocksOnceInInit(Module):
    """Its construction blocks for ``BLOCK_S`` if ``flag`` (a path, set on a subclass)
    exists, which it removes first, writing its worker's pid to ``pid_file``: one
    construction blocks, the next does not."""

    BLOCK_S = 30.0
    flag = ""
    pid_file = ""

    def __init__(self) -> None:
        super().__init__()
        if os.path.exists(self.flag):
            os.remove(self.flag)
            with open(self.pid_file, "w") as pid:
                pid.write(str(os.getpid()))
            time.sleep(self.BLOCK_S)


class HoldsInSetup(Module):
    """Its ``setup`` waits (up to 30 s) while the file ``hold`` exists; it steps."""

    period = 0.01
    hold = ""
    steps = 0

    def setup(self) -> None:
        waited_until = time.monotonic() + 30.0
        while self.hold and os.path.exists(self.hold) and time.monotonic() < waited_until:
            time.sleep(0.01)

    def step(self) -> None:
        self.steps += 1


class FailsToMake(Steady):
    """Its construction raises while the file ``flag`` (a path, set on a subclass) is
    there."""

    flag = ""

    def __init__(self) -> None:
        super().__init__()
        if self.flag and os.path.exists(self.flag):
            raise RuntimeError("the device this module opens is gone")


class SlowToMake(Steady):
    """Its construction takes ``make_s`` (past a worker's 1.25 s lease), the GIL let go."""

    make_s = 2.5

    def __init__(self) -> None:
        super().__init__()
        time.sleep(self.make_s)


class SlowerToMake(SlowToMake):
    """... 5 s: past the lease and the 2 s more a worker's lease was once let be out while
    the thread that reads its requests was held."""

    make_s = 5.0


class HoldsTheGil(Module):
    """Each step is one C call that holds the GIL for ``hold_s`` (as a pickle of a large
    list does, or a solver that does not let go of it): no other thread of its worker
    runs meanwhile."""

    period = 0.01
    hold_s = 1.5
    steps = 0

    def step(self) -> None:
        ctypes.PyDLL(None).usleep(int(self.hold_s * 1e6))
        self.steps += 1


class Oversize(Module):
    """Tries to write ``size`` bytes once (keeping the error in ``refused``), then writes
    a small value each step."""

    out = Output(bytes)
    period = 0.01
    size = 2 << 20
    refused = ""
    sent = 0

    def step(self) -> None:
        if self.sent == 0 and not self.refused:
            try:
                self.out.write(b"x" * self.size)
            except ValueError as exc:
                self.refused = str(exc)
        self.out.write(b"small")
        self.sent += 1


class Sizes(Module):
    """Keeps the sizes of the byte strings it receives."""

    x = Input(bytes, policy="queue:1000")
    sizes: list[int] = []

    def on_input(self, port) -> None:
        self.sizes = [*self.sizes, *(len(value) for value in port.read_all())]


class LongStep(Module):
    """Each step takes ``step_s`` seconds (a long computation), holding its lock."""

    period = 0.01
    step_s = 1.0
    steps = 0
    gain = 1.0

    def step(self) -> None:
        time.sleep(self.step_s)
        self.steps += 1


class DeviceReader(Driver):
    """Asks its device for a reading every period, waiting up to 30 s for each; counts
    what it asked and why a request failed."""

    period = 0.05
    timeout = 30.0
    asked = 0
    answered = 0
    last_error = ""

    def step(self) -> None:
        self.asked += 1
        try:
            self.request("read")
            self.answered += 1
        except (RuntimeFailure, RuntimeTimeout) as exc:
            self.last_error = str(exc)


class DeviceReaderV2(DeviceReader):
    """The same, another class (to swap to)."""


class RobotPose(Module):
    """Counts the values it is given in ``seen`` (written on ``count``) and in its
    ``pose``, an object of a class installed on the robots only (``robot_types``, on the
    path of the nodes' daemons, not the launcher's, which cannot read its state):
    restart ``last-state`` puts that object in its checkpoints."""

    x = Input(int, policy="queue:100000")
    count = Output(float)
    pose = None
    seen = 0

    def setup(self) -> None:
        if self.pose is None:
            from robot_types import Pose
            self.pose = Pose()

    def on_input(self, port) -> None:
        port.read()
        self.seen += 1
        self.pose.x += 1.0
        self.count.write(float(self.seen))


class ListScribbler(Module):
    """Writes one list again and again, scribbling over it (-1) right after each write."""

    out = Output(list)
    period = 0.002
    n = 0

    def setup(self) -> None:
        self._items = [0, 0, 0]

    def step(self) -> None:
        self.n += 1
        self._items[:] = [self.n] * 3
        self.out.write(self._items)
        self._items[:] = [-1] * 3


class ListSink(Module):
    """Counts lists whose items differ (scribbled over after they were written)."""

    x = Input(list, policy="queue:1000")
    received = 0
    scribbled = 0

    def on_input(self, port) -> None:
        for items in port.read_all():
            self.received += 1
            self.scribbled += len(set(items)) != 1 or items[0] < 0


class OpensDevice(Module):
    """Its ``setup`` opens a device: it raises while ``missing`` or while the file
    ``unplugged`` exists; counts its steps (in the file ``steps_to`` too, if given, so
    that steps can be seen once it is out of the system); notes its teardowns."""

    x = Input(int, policy="queue:100")
    period = 0.01
    missing = False
    unplugged = ""
    steps_to = ""
    ready = ""              # (for NoDevice, which a swap gives it to)
    steps = 0
    setups = 0
    teardowns = 0
    handled = 0

    def setup(self) -> None:
        self.setups += 1
        if self.missing or (self.unplugged and os.path.exists(self.unplugged)):
            raise RuntimeError("device /dev/video7 not found")

    def step(self) -> None:
        self.steps += 1
        if self.steps_to:
            with open(self.steps_to, "a") as steps:
                steps.write("step\n")

    def on_input(self, port) -> None:
        self.handled += len(port.read_all())

    def teardown(self) -> None:
        self.teardowns += 1


class Fussy(Module):
    """Its own ``set_state`` refuses every state while the file ``refuse`` exists (a
    state it cannot take back); counts its steps."""

    period = 0.01
    refuse = ""
    steps = 0

    def set_state(self, state: dict) -> None:
        refuse = state.get("refuse", self.refuse)
        if refuse and os.path.exists(refuse):
            raise ValueError(f"state refused while {refuse} exists")
        super().set_state(state)

    def step(self) -> None:
        self.steps += 1


class OnFlag(Module):
    """Writes one value each time the file ``flag`` appears (and removes it)."""

    out = Output(int)
    period = 0.01
    flag = ""
    sent = 0

    def step(self) -> None:
        if self.flag and os.path.exists(self.flag):
            os.remove(self.flag)
            self.sent += 1
            self.out.write(self.sent)


class NoDevice(Module):
    """Handles no events; its ``setup`` waits (5 s at most) for a value on ``x``, then
    raises: what ``OpensDevice`` is swapped for, to fail with a value come meanwhile."""

    x = Input(int, policy="queue:100")
    period = 0.01
    ready = ""              # a file it makes as its setup begins

    def setup(self) -> None:
        if self.ready:
            open(self.ready, "a").close()
        deadline = time.monotonic() + 5.0
        while not self.x.owes_calls and time.monotonic() < deadline:
            time.sleep(0.01)
        raise RuntimeError("device /dev/video7 not found")


class Chatterbox(Agent):
    """Once file ``go`` exists: logs 300 long warnings, then asks the runtime to spawn
    ``late`` within ``ask_s``, and writes how that ended (and how long it took) to file
    ``told``."""

    period = 0.01
    go = ""
    told = ""
    ask_s = 0.5

    def step(self) -> None:
        if not os.path.exists(self.go) or os.path.exists(self.told):
            return
        for i in range(300):
            logging.getLogger("chatterbox").warning("chatter %d %s", i, "x" * 4000)
        started = time.monotonic()
        try:
            self.runtime.spawn("late", Steady, timeout=self.ask_s)
            outcome = "spawned"
        except RuntimeTimeout as exc:
            outcome = str(exc)
        with open(self.told + ".part", "w") as told:     # (whole when it appears)
            told.write(f"{time.monotonic() - started}\n{outcome}")
        os.replace(self.told + ".part", self.told)


class Frames(Module):
    """A camera: writes ``limit`` frames of ``size`` bytes, one every period, each
    numbered 1, 2, 3, ... in its first 8 bytes and with when it was written (unix) in
    the next 8; ``sent`` counts them, ``first_at`` and ``last_at`` are when the first
    and the last were written, ``longest_write_s`` the longest a write took."""

    out = Output(np.ndarray)
    period = 0.05
    size = 64 * 1024
    limit = 0
    sent = 0
    first_at = 0.0
    last_at = 0.0
    longest_write_s = 0.0

    def step(self) -> None:
        if self.sent >= self.limit:
            return
        frame = np.zeros(self.size, np.uint8)
        frame[:8].view(np.int64)[0] = self.sent + 1
        frame[8:16].view(np.float64)[0] = now = time.time()
        self.out.write(frame)
        self.longest_write_s = max(self.longest_write_s, time.time() - now)
        self.first_at = self.first_at or now
        self.last_at = now
        self.sent += 1


class FrameSink(Module):
    """Reads ``Frames``: the numbers it got, in order, how old each was on arrival
    (``ages``, seconds), and any that came again or late."""

    x = Input(np.ndarray, policy="queue:1000")
    numbers: list[int] = []
    ages: list[float] = []
    out_of_order = 0
    duplicates = 0

    def on_input(self, port) -> None:
        for frame in port.read_all():
            number = int(frame[:8].view(np.int64)[0])
            self.ages = [*self.ages, round(time.time() - float(frame[8:16].view(np.float64)[0]),
                                           3)]
            last = self.numbers[-1] if self.numbers else 0
            if number in self.numbers:
                self.duplicates += 1
            elif number < last:
                self.out_of_order += 1
            self.numbers = [*self.numbers, number]


class Freezer(Module):
    """Passes what it reads on, each step; once ``freeze_in`` is ``"step"`` its next step
    never returns, once it is ``"teardown"`` its teardown never does (as a module stuck
    in a call it cannot leave)."""

    x = Input(int)
    out = Output(int)
    period = 0.01
    freeze_in = ""
    steps = 0

    def step(self) -> None:
        if self.freeze_in == "step":
            time.sleep(1000)
        self.steps += 1
        self.out.write(self.steps)

    def teardown(self) -> None:
        if self.freeze_in == "teardown":
            time.sleep(1000)


class InputFreezer(Module):
    """``Freezer`` driven by its input: once ``freeze_in`` is ``"on_input"`` the next
    value it handles never lets it return."""

    x = Input(int, policy="queue:8")
    out = Output(int)
    freeze_in = ""
    handled = 0

    def on_input(self, port) -> None:
        port.read()
        if self.freeze_in == "on_input":
            time.sleep(1000)
        self.handled += 1
        self.out.write(self.handled)


class DeviceKit(Macro):
    """A counter feeding a device opener, whose ``setup`` raises with ``state={"cam":
    {"missing": True}}``: a macro added to a running system, one of whose modules may
    not start."""

    modules = {"tick": {"class": Counter, "period": 0.01}, "cam": OpensDevice}
    links = [("tick.out", "cam.x")]
    exports = {"count": "tick.out"}


class FreezerPair(Macro):
    """A freezer, then a steady module: removed last first, the steady one goes before
    a frozen freezer is reached."""

    modules = {"freezer": Freezer, "steady": Steady}


class MacroSpawner(Agent):
    """On its first value spawns the macro ``Chain`` as ``c2`` (its second gain 5) fed by
    ``scale.y``, and tries to remove the macro it is in itself (``refused``: why not); on
    its second, removes ``c2``."""

    go = Input(int, policy="queue:8")
    seen = 0
    refused = ""

    def on_input(self, port) -> None:
        port.read()
        self.seen += 1
        if self.seen == 1:
            self.runtime.spawn("c2", Chain, state={"b": {"gain": 5.0}})
            self.runtime.link("scale.y", "c2/a.x")
            try:
                self.runtime.remove(self.runtime.name.partition("/")[0])
            except ValueError as exc:
                self.refused = f"{type(exc).__name__}: {exc}"
        elif self.seen == 2:
            self.runtime.remove("c2")


class SpawnerKit(Macro):
    """``MacroSpawner`` inside a macro of its own."""

    modules = {"agent": MacroSpawner}
    exports = {"go": "agent.go"}


PUMP_MOST_L_S = 5.0


class Pump(Module):
    """A user's module that refuses some values of its state (``state_problems``): a
    rate its pump cannot run at, a valve position it has not got."""

    rate = 1.0                  # l/s, from 0 to PUMP_MOST_L_S
    valve = "closed"            # "open" or "closed"

    @classmethod
    def state_problems(cls, state: dict) -> list[str]:
        problems = super().state_problems(state)
        if "rate" in state and not 0 <= state["rate"] <= PUMP_MOST_L_S:
            problems.append(f"{cls.__name__}'s rate must be from 0 to {PUMP_MOST_L_S:g} l/s, "
                            f"got {state['rate']!r}")
        if "valve" in state and state["valve"] not in ("open", "closed"):
            problems.append(f"{cls.__name__}'s valve is 'open' or 'closed', "
                            f"got {state['valve']!r}")
        return problems


class Fragile(Module):
    """A user's module whose ``state_problems`` has a bug: a rate of 0 divides by zero."""

    rate = 1.0

    @classmethod
    def state_problems(cls, state: dict) -> list[str]:
        problems = super().state_problems(state)
        if "rate" in state and 1 / state["rate"] > 10:
            problems.append(f"{cls.__name__}'s rate must be above 0.1, got {state['rate']!r}")
        return problems
