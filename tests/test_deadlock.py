"""No deadlock between agents and the API, by design: agents reading, editing, swapping
and moving each other while the program does the same to them."""

from __future__ import annotations

import contextlib
import itertools
import os
import signal
import threading
import time
from collections.abc import Iterator

import pytest
from conftest import alive, eventually, unused_port
from sample_modules import (
    Busybody,
    Commander,
    DeviceReader,
    DeviceReaderV2,
    Journal,
    Locator,
    LocatorToo,
    LongStep,
    Relay,
    RemovesInSetup,
    Scale,
    SlowState,
    Steady,
    Watcher,
)

import pb3a
from pb3a import Agent, Driver, Module, RuntimeFailure, RuntimeTimeout, System, SystemStopped
from pb3a.node.executor import Executor
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlServer
from pb3a.worker.actor import ModuleActor

pytestmark = pytest.mark.timeout(120)

AGENTS = ("a0", "a1", "a2")


@pytest.mark.parametrize("workers", [0, 1], ids=["one-process-each", "packed"])
def test_agents_and_the_program_act_on_each_other_without_deadlock(workers: int) -> None:
    system = System("busy")
    for node in ("n1", "n2"):
        system.node(node, workers=workers)
    for name in AGENTS:
        system.add(name, Busybody, node="n1",
                   state={"peers": [p for p in AGENTS if p != name], "nodes": ["n1", "n2"]})
    program = 0
    deadline = time.monotonic() + 90
    with system.launch() as run:
        seen: dict[str, dict] = {}
        for i in itertools.count():
            agent = AGENTS[i % len(AGENTS)]
            match i % 5:
                case 0:
                    run.state(agent)
                case 1:
                    run.stats()
                case 2:
                    run.set_state(agent, poked=-i)
                case 3:
                    run.swap(agent, Busybody)
                case _:
                    run.migrate(agent, to="n2" if i % 2 else "n1")
            program += 1
            # one agent's counts read each turn, in turn (they only grow: the sum of the
            # latest reads is at most what the agents have answered by now)
            reader = AGENTS[(i + 1) % len(AGENTS)]
            seen[reader] = run.state(reader)
            answered = sum(s["asked"] - s["refused"] for s in seen.values())
            if (program >= 500 and answered >= 1000) or time.monotonic() > deadline:
                break
        states = [run.state(name) for name in AGENTS]
        answered = sum(s["asked"] - s["refused"] for s in states)
    # every request of the program was answered (else it raised); the agents' were too,
    # except those cut short because their agent had to be paused (to move or swap it):
    # never a time-out, never another error
    assert [s["unexpected"] for s in states] == ["", "", ""]
    assert program >= 500 and answered >= 1000, (program, answered)
    # and each cancelled request said whether it may still be carried out (one that had
    # reached the runtime ran once the change ended: asked again, it was made twice)
    said = {kind for s in states for kind in s["cancels_said"]}
    assert said and said <= {"withdrawn", "may run"}, said


class WaitsForItsOwnMove(Agent):
    """Moves itself from its setup and waits there for the move; says how it went."""

    result = ""

    def setup(self) -> None:
        if self.result:                     # (moved: set up again at b)
            return
        began = time.monotonic()
        try:
            self.runtime.migrate(self.runtime.name, "b").result()
            self.result = "moved"
        except RuntimeFailure as exc:
            self.result = f"{time.monotonic() - began:.1f} s: {exc}"


def test_an_agent_added_that_waits_in_its_setup_for_its_own_move_is_told_at_once() -> None:
    """The move waited for the configuration lock that the add holds, and the add for
    the agent's setup, which waited for the move: the add failed when its timeout ran
    out ('did not answer start within 2.7 s: a module there is stuck'). The wait is
    refused at once, saying why, and the move goes on once the add is done."""
    system = System("own-move").node("a").node("b")
    with system.launch() as run:
        started = time.monotonic()
        run.add("m", WaitsForItsOwnMove, node="a", timeout=3.0)
        assert time.monotonic() - started < 2.0
        result = run.state("m")["result"]
        assert "from its setup" in result and "it would wait for itself" in result, result
        eventually(lambda: run.where("m") == "b", what="the move, done after the add")


def test_an_agent_may_ask_the_runtime_from_setup_as_the_system_starts() -> None:
    system = System("locating").node("a").node("b")
    system.add("src", Busybody, node="b", period=1.0, state={"peers": ["src"]})
    system.add("locator", Locator, node="a")
    with system.launch(timeout=10) as run:
        assert run.state("locator")["found"] == "b"


def test_an_agent_may_read_the_runtime_from_setup_inside_a_change() -> None:
    """``add``, ``migrate``, ``swap`` and ``restart`` hold the configuration lock while
    they wait for the ``setup`` of the module they start, and lend it to that module:
    its ``setup`` may read. Before, each waited for the other until the worker's 10 s
    deadline, and the change failed with ``RuntimeTimeout``."""
    system = System("locating").node("a").node("b")
    system.add("src", Busybody, node="b", period=1.0, state={"peers": ["src"]})
    with system.launch(timeout=10) as run:
        started = time.monotonic()
        run.add("locator", Locator, node="a")
        assert run.state("locator")["found"] == "b"
        for change in (lambda: run.migrate("locator", "b"),
                       lambda: run.swap("locator", LocatorToo),
                       lambda: run.restart("locator")):
            run.set_state("locator", found="")
            change()
            assert run.state("locator")["found"] == "b"      # its setup asked again
        assert run.state("locator")["peers"] == ["src"]
        assert time.monotonic() - started < 8.0


def test_a_change_asked_from_setup_inside_a_change_is_refused_at_once() -> None:
    """It would wait for the change waiting for that setup: refused, saying why."""
    system = System("refusing")
    system.add("src", Busybody, period=1.0, state={"peers": ["src"]})
    with system.launch(timeout=10) as run:
        started = time.monotonic()
        run.add("remover", RemovesInSetup)
        assert time.monotonic() - started < 3.0
        refused = run.state("remover")["refused"]
        assert "remove src: asked by agent 'remover' from its setup" in refused
        assert "'add remover' waits for" in refused and "from step()" in refused
        assert run.where("src") == "local"                 # nothing was removed


def test_a_call_that_waits_too_long_names_what_it_waited_for() -> None:
    system = System("waiting", timeout=0.3)        # as `timeout = 0.3` in a file
    system.add("src", Busybody, period=1.0, state={"peers": ["src"]})
    with system.launch() as run:
        held, release = threading.Event(), threading.Event()

        def hold() -> None:
            with run._launcher.lock.held("migrate src to b", acts_on=["src"]):
                held.set()
                release.wait(10)
        holder = threading.Thread(target=hold)
        holder.start()
        try:
            held.wait(5)
            started = time.monotonic()
            with pytest.raises(RuntimeTimeout, match=r"state src: waited 0.3 s for the system's "
                                                     r"configuration lock, which 'migrate src "
                                                     r"to b' has held for"):
                run.state("src")                       # the system's default: 0.3 s
            with pytest.raises(RuntimeTimeout, match=r"set_state src: waited 0.1 s"):
                run.set_state("src", {"timeout": 1}, timeout=0.1)   # a field named timeout
            assert time.monotonic() - started < 2
        finally:
            release.set()
            holder.join(5)
        run.set_state("src", {"poked": 7})
        assert run.state("src")["poked"] == 7


def test_events_and_logs_without_a_timeout_wait_the_system_s_default() -> None:
    """``events``/``logs`` with ``timeout=None`` wait the system's default, as every other
    call does (they waited forever), also through a connection; the launcher's own event
    log and log book refuse a wait without a deadline."""
    system = System("patient", timeout=0.3)
    system.add("scale", Scale)
    with system.launch() as run, pb3a.connect(run.listen()) as far:
        for handle in (run, far):
            last = run._launcher.events.last
            answers: list = []

            def ask(handle=handle, last=last, answers=answers) -> None:
                answers.append(handle.events(last, timeout=None))
                answers.append(handle.logs(10**9, timeout=None))
            asking = threading.Thread(target=ask, daemon=True)
            started = time.monotonic()
            asking.start()
            asking.join(5.0)
            assert not asking.is_alive(), f"{handle!r}: events/logs(timeout=None) still waiting"
            assert answers == [[], []]
            assert 0.5 <= time.monotonic() - started < 3.0      # 0.3 s each, not 0
        for pool in (run._launcher.events, run._launcher.logbook):
            with pytest.raises(TypeError, match="timeout"):
                pool.since(0, None)


def test_one_deadline_covers_the_wait_for_the_lock_and_the_module_s_answer() -> None:
    """An operation given ``timeout`` T returns or raises within about T: the wait for the
    configuration lock and the wait for the module's answer share it (the call got the
    whole T again once it had the lock, so it took nearly 2 T)."""
    system = System("one-deadline")
    system.add("slow", SlowState, state={"slow_s": 3.0})       # its answer takes 3 s
    with system.launch() as run:
        held, release = threading.Event(), threading.Event()

        def hold() -> None:
            with run._launcher.lock.held("a long reconfiguration", 10.0):
                held.set()
                release.wait(1.2)                      # most of the state call's 1.5 s
        holder = threading.Thread(target=hold)
        holder.start()
        try:
            assert held.wait(10.0)
            started = time.monotonic()
            with pytest.raises(RuntimeTimeout, match="get_state"):
                run.state("slow", timeout=1.5)
            took = time.monotonic() - started
        finally:
            release.set()
            holder.join(10.0)
    assert 1.2 <= took < 2.5, took                   # (held up: 2.7 s)


class _Stepper(Module):
    """Steps as fast as it can, so its step thread always waits for the lock a swap holds."""

    period = 0.0

    def step(self) -> None:
        pass


class _Asker(Module):
    """What the stepper is swapped for: its step stands for an agent's runtime request,
    which waits for the configuration lock the swap's operation holds (``_asked``, set
    once the swap returns, stands for that lock let go), at most ``WAIT_S``."""

    WAIT_S = 3.0
    set_up = False
    steps_before_setup = 0

    def __init__(self) -> None:
        super().__init__()
        self._asked = threading.Event()

    def setup(self) -> None:
        self.set_up = True

    def step(self) -> None:
        if not self.set_up:
            self.steps_before_setup += 1
        self._asked.wait(self.WAIT_S)


def test_a_swapped_module_runs_setup_before_its_step_can_take_the_lock() -> None:
    """The swap keeps the module lock from the old instance's teardown to the new one's
    ``setup``. It let the lock go in between: a step thread waiting for it stepped the
    new instance before its ``setup``, and, an agent asking the runtime there, waited for
    the configuration lock the swap's operation held while the swap waited for it: no
    answer to the swap until the executor gave up (10 s; seen once in the agents' deadlock
    test). Here the lock is handed to the waiting step thread whenever the swap lets it go."""
    actor = ModuleActor("m", _Stepper(), lambda task: task(), 0.0)
    actor.start()
    lock, release, swapping = actor.lock, actor.lock.release, threading.current_thread()

    def hand_over_at_once() -> None:          # as the scheduler may, on another core
        deadline = time.monotonic() + 2.0
        while not lock.waiters and time.monotonic() < deadline:
            time.sleep(0.0005)
        release()
        while not lock.locked() and time.monotonic() < deadline:
            time.sleep(0.0005)

    new = _Asker()
    try:
        lock.release = lambda: (hand_over_at_once() if threading.current_thread() is swapping
                                else release())
        started = time.monotonic()
        actor.swap(new, 0.0, timeout=5.0)
        took = time.monotonic() - started
    finally:
        lock.release = release
        new._asked.set()
        assert actor.stop(5.0)
    assert new.set_up and new.steps_before_setup == 0
    assert took < _Asker.WAIT_S / 2, took


def test_close_keeps_its_timeout_with_a_change_in_progress_and_later_calls_are_refused(
        tmp_path) -> None:
    """close(timeout=1) waited for the configuration lock up to 60 s; calls on a closed
    system waited for dead workers (an add 10 s, a restart 20 s)."""
    journal = tmp_path / "journal"
    system = System("closing").add("steady", Steady)
    run = system.launch()
    run.add("early", Steady)            # (an event the history below holds for sure: the
                                        # slow add's own may come after the close, or not)

    def add() -> None:                  # (it fails as the system stops under it)
        with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
            run.add("slow", Journal,
                    state={"path": str(journal), "label": "slow", "setup_s": 8.0})
    adding = threading.Thread(target=add, daemon=True)
    adding.start()
    eventually(lambda: journal.exists() and "start slow" in journal.read_text(),
               what="the add holding the configuration lock")
    started = time.monotonic()
    run.close(timeout=1.0)
    assert time.monotonic() - started < 4.0
    started = time.monotonic()
    for call in (lambda: run.state("steady"), lambda: run.add("late", Steady),
                 lambda: run.restart("steady")):
        with pytest.raises(SystemStopped, match="system 'closing' is stopped"):
            call()
    history = run.events(0, timeout=5.0)        # still read, and no new one waited for
    assert time.monotonic() - started < 1.0
    assert history and history == run.events(0)
    # a follower asking for newer ones is told none will come (it asked again at once,
    # thousands of times a second)
    with pytest.raises(SystemStopped, match="is stopped: no new entry will come"):
        run.events(history[-1].seq, timeout=1.0)
    adding.join(15)


def test_a_state_edit_that_runs_out_of_time_was_not_done() -> None:
    """It raised RuntimeTimeout and was applied later all the same, when the module's
    step ended: a caller who took the error for "not done" was wrong."""
    system = System("edit-in-time").add("slow", LongStep, state={"step_s": 1.5})
    with system.launch() as run:
        with pytest.raises(RuntimeTimeout, match=r"busy in a call .*: nothing was done"):
            run.set_state("slow", gain=42.0, timeout=0.5)
        steps = run.state("slow", timeout=5.0)["steps"]
        state = eventually(lambda: (s := run.state("slow", timeout=5.0))["steps"] > steps
                           and s, timeout=10, what="a step after the edit's time ran out")
    assert state["gain"] == 1.0


def test_a_read_of_a_module_stuck_in_a_step_holds_up_no_other_request(monkeypatch) -> None:
    """A state read waiting for a module in a long step runs out as ``RuntimeTimeout``
    (a ``TimeoutError``: it was a ``RuntimeFailure``), and meanwhile every other request
    is answered at once: it held the configuration lock, so ``stats()``, ``where()``
    and another module's state waited out its timeout (``pb3a status`` said no launcher
    answered, Ctrl-C waited 30 s)."""
    system = System("stuck-read")
    system.add("slow", LongStep, state={"step_s": 3.0})
    system.add("ok", Steady)
    with system.launch() as run:
        node = run._launcher.node_of("slow")
        asking, real = threading.Event(), type(node).call_module

        def call_module(self, name, op, *args, **kwargs):
            if (name, op) == ("slow", "get_state"):
                asking.set()
            return real(self, name, op, *args, **kwargs)
        monkeypatch.setattr(type(node), "call_module", call_module)
        eventually(lambda: run.state("ok")["count"] > 2, what="steps")
        outcome: list[BaseException] = []

        def read() -> None:
            try:
                run.state("slow", timeout=2.0)
            except BaseException as exc:       # (checked below)
                outcome.append(exc)
        reader = threading.Thread(target=read)
        reader.start()
        try:
            assert asking.wait(5.0)
            started = time.monotonic()
            assert run.stats().modules["ok"].status == "running"
            assert run.where("ok") == "local" and run.state("ok")["count"] > 0
            answered = time.monotonic() - started
        finally:
            reader.join(10.0)
    assert answered < 0.5, answered
    assert len(outcome) == 1 and isinstance(outcome[0], RuntimeTimeout), outcome
    assert isinstance(outcome[0], TimeoutError) and "busy in a call" in str(outcome[0])


def test_an_agent_looks_at_the_system_while_a_move_is_stuck(monkeypatch) -> None:
    """An agent's ``self.runtime.stats()`` and ``where()`` answer at once while another
    module's move holds the configuration lock (held here as it pauses that module), the
    figures naming the move, and a read of the agent's state is not held up either (they
    waited for the lock: each look failed after its 5 s, and the move's end)."""
    system = System("look-from-an-agent")
    system.node("a")
    system.node("b")
    system.add("mover", Steady, node="a")
    system.add("watcher", Watcher, node="a", state={"other": "mover"})
    go, pausing = threading.Event(), threading.Event()
    real = Executor.pause

    def pause(self, name, *args, **kwargs):
        if name == "mover":
            pausing.set()
            assert go.wait(30.0)
        return real(self, name, *args, **kwargs)
    with system.launch() as run:
        eventually(lambda: run.state("watcher")["seen_node"] == "a", what="a first look")
        monkeypatch.setattr(Executor, "pause", pause)
        moving = threading.Thread(target=lambda: run.migrate("mover", to="b", timeout=60))
        moving.start()
        try:
            assert pausing.wait(10.0)
            seen = eventually(
                lambda: (s := run.state("watcher", timeout=2.0))["seen_change"] and s,
                what="the agent seeing the move")
        finally:
            go.set()
            moving.join(30.0)
        after = eventually(lambda: (s := run.state("watcher"))["seen_node"] == "b"
                           and not s["seen_change"] and s,
                           what="the agent seeing the module moved, the move done")
    assert seen["seen_change"] == "migrate mover to b" and seen["seen_node"] == "a", seen
    assert seen["took_s"] < 1.5 and seen["failed"] == "", seen
    assert after["failed"] == "", after


def test_close_without_the_lock_stops_everything_though_a_change_removes_a_module(
        tmp_path) -> None:
    """close(timeout) goes on without the configuration lock after half its timeout; a
    remove in progress then took a module from under it: close raised ModuleNotFound,
    shut no node down, and left the workers running."""
    journal = tmp_path / "journal"
    system = System("closing-remove")
    system.add("victim", Journal, state={"path": str(journal), "label": "victim",
                                         "teardown_s": 2.5})
    # stopped before it, for long enough that the remove ends meanwhile
    system.add("other", Journal, state={"path": str(journal), "label": "other",
                                        "teardown_s": 1.8})
    system.add("steady", Steady)
    run = system.launch()
    pids = [module.pid for module in run.stats().modules.values()]
    removing = threading.Thread(target=_removes, args=(run, "victim"), daemon=True)
    removing.start()
    eventually(lambda: run._launcher.lock.doing() != "nothing", what="the remove under way")
    run.close(timeout=2.0)
    removing.join(15)
    eventually(lambda: not any(map(alive, pids)), timeout=10, what="every worker gone")


def _removes(run: pb3a.Running, name: str) -> None:
    with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
        run.remove(name)


def test_a_state_edit_given_up_on_while_a_body_waits_for_the_runtime_is_not_done() -> None:
    """Posted to a body that waits for the runtime, an edit whose time ran out said
    TimeoutError('') and then ran all the same."""
    actor = ModuleActor("a", Scale(), lambda task: task(), None)
    waiting, done = threading.Event(), threading.Event()

    def body() -> None:                 # holds the module lock, waiting for the runtime
        actor.lock.acquire()
        actor._holder = threading.get_ident()      # (as a body's call marks it)
        with actor.waiting("events") as wait:
            waiting.set()
            with contextlib.suppress(RuntimeTimeout):
                wait.result(0.5)
        actor.lock.release()
        done.set()
    threading.Thread(target=body, daemon=True).start()
    assert waiting.wait(5)
    with pytest.raises(TimeoutError, match=r"busy in a call .*: nothing was done"):
        actor.apply({"gain": 5.0}, 0.0)
    assert done.wait(5) and actor.module.gain == 2.0


def test_a_short_timeout_still_reads_a_module_between_its_steps() -> None:
    """The worker's share of a call's time was the timeout less 0.25 s: none at all for
    0.2 s, and every such read of a module stepping every 50 ms failed. (Most, not all:
    on a loaded machine a 0.1 s read may miss its deadline now and then.)"""
    system = System("short-reads").add("slow", LongStep, state={"step_s": 0.05})
    with system.launch() as run:
        for timeout in (0.1, 0.2):
            read = 0
            for _ in range(5):
                with contextlib.suppress(RuntimeTimeout):
                    read += run.state("slow", timeout=timeout)["step_s"] == 0.05
            assert read >= 3, f"{read} of 5 reads within {timeout} s"


def test_a_restart_that_cannot_take_the_lock_reports_its_modules_failed(monkeypatch) -> None:
    """It left them 'running', with no event, for good."""
    monkeypatch.setattr(Executor.held, "__defaults__", (1.0,))     # (60 s)
    system = System("late-restart").add("dies", Steady, restart="fresh")
    with system.launch() as run:
        pid = eventually(lambda: run.stats().modules["dies"].pid, what="its worker")
        with run._launcher.lock.held("a long operation", 5.0):
            os.kill(pid, signal.SIGKILL)
            event = eventually(lambda: [e for e in run.events(0)
                                        if e.kind == "module_failed"], timeout=10,
                               what="the failure said")
        assert run.stats().modules["dies"].status == "failed"
    assert "could not take the node's lock" in event[0].detail["reason"]


def test_a_driver_waiting_for_its_device_holds_up_no_read_swap_or_stop() -> None:
    """A driver's request to a device that does not answer held its module's lock for
    the request's whole deadline (30 s here): a read of its state, a swap, a move or a
    stop waited for it, or failed ("busy in a call"); a robot driver whose server died
    could not be moved to the standby robot. Now a read runs while it waits, and a swap
    or a stop cancels the request."""
    resource = f"tcp://127.0.0.1:{unused_port()}"            # nothing listens there
    system = System("device").add("reader", DeviceReader, state={"resource": resource})
    with system.launch() as run:
        eventually(lambda: run.state("reader", timeout=2.0)["asked"] == 1,
                   what="the first request under way")
        started = time.monotonic()
        assert run.state("reader", timeout=1.0)["answered"] == 0
        run.swap("reader", DeviceReaderV2, timeout=5.0)
        state = run.state("reader", timeout=1.0)
        assert time.monotonic() - started < 2.0
        assert "request 'read' cancelled: the module is being swapped" in state["last_error"]
        eventually(lambda: run.state("reader", timeout=2.0)["asked"] == 2,
                   what="the new instance's request under way")
        started = time.monotonic()
    assert time.monotonic() - started < 5.0


@pytest.fixture
def device() -> Iterator[ControlServer]:
    """A device in this process: each op sleeps ``sleep`` seconds, then answers its name."""
    def handler(op: str, args: dict) -> str:
        time.sleep(args.get("sleep", 0.0))
        return op
    server = ControlServer(ClusterKey.load(), handler, aside=("slow", "battery"))
    yield server
    server.close()


class _Meter(Driver):
    """Its step waits 8 s for its device; its state holds a reading it asks the device."""

    timeout = 8.0
    errors = ""

    def step(self) -> None:
        try:
            self.request("slow", sleep=8.0)
        except RuntimeFailure as exc:
            self.errors = f"{type(exc).__name__}: {exc}"

    def get_state(self) -> dict:
        return {**super().get_state(), "battery": self.request("battery")}


def test_a_read_that_asks_the_device_inside_a_driver_s_request_leaves_it_cancellable(
        device) -> None:
    """The read ran on the waiting thread, and its own request's wait replaced the
    outer one, then cleared it: a pause could no longer cancel the step's request and
    waited out its 8 s deadline."""
    actor = ModuleActor("meter", _Meter(), lambda task: task(), 0.05)
    actor.module.resource = device.address
    actor.start()
    try:
        eventually(lambda: actor._wait is not None, what="the step's request waiting")
        assert actor.capture(2.0)["battery"] == "battery"        # read while it waits
        started = time.monotonic()
        assert actor.acquire_stopped(2.0, "the module is being paused")
        actor.lock.release()
        assert time.monotonic() - started < 1.0
        eventually(lambda: actor.module.errors.startswith("RuntimeCancelled: ") and
                   "cancelled: the module is being paused" in actor.module.errors,
                   what="the step's request cancelled")
    finally:
        assert actor.stop(5.0)


class _TwoReads(Driver):
    """Each step reads two slow sensors, each in a try of its own."""

    timeout = 10.0

    def step(self) -> None:
        for _ in range(2):
            with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
                self.request("slow", sleep=10.0)


def test_stop_cancels_every_request_a_step_makes_after_the_first(device) -> None:
    """It cancelled the first; the step's second request waited its deadline, and stop
    gave up, saying a body overran."""
    actor = ModuleActor("reads", _TwoReads(), lambda task: task(), 0.05)
    actor.module.resource = device.address
    actor.start()
    eventually(lambda: actor._wait is not None, what="the step's first request waiting")
    started = time.monotonic()
    assert actor.stop(3.0)
    assert time.monotonic() - started < 1.0


class _TwoReadsSaying(_TwoReads):
    """The same, keeping what each request's failure said."""

    def __init__(self) -> None:
        super().__init__()
        self.said: list[str] = []

    def step(self) -> None:
        for _ in range(2):
            try:
                self.request("slow", sleep=10.0)
            except RuntimeFailure as exc:
                self.said.append(str(exc))


def test_a_driver_s_cancelled_request_says_whether_the_device_may_still_carry_it_out(
        device) -> None:
    """A request cancelled once sent may still be carried out by its device (it said
    only "cancelled", and a driver asked again what was done); one cancelled before it
    went was not sent."""
    actor = ModuleActor("reads", _TwoReadsSaying(), lambda task: task(), 0.05)
    actor.module.resource = device.address
    actor.start()
    eventually(lambda: actor._wait is not None, what="the step's first request waiting")
    assert actor.stop(3.0)
    where = f"_TwoReadsSaying at {device.address}: request 'slow' cancelled: "
    sent, unsent = actor.module.said
    assert sent.startswith(where) and sent.endswith(
        "; it was sent, so the device may have begun it and carry it out still (one it "
        "has not begun it drops): look before asking again")
    assert unsent.startswith(where) and unsent.endswith("; it was not sent")


def test_a_body_whose_runtime_call_the_runtime_cancels_is_not_counted_as_failing() -> None:
    """An agent waiting on the runtime as it was swapped, moved or stopped raised
    ``RuntimeCancelled`` out of its step, by design: it was logged with its traceback
    ("raised in step") and counted among its errors at every stop."""
    class Sleeper(Module):
        period = 0.01
        busy = False

        def step(self) -> None:
            if self.busy:
                time.sleep(3.0)             # holds its lock: a read of it waits

    class Asker(pb3a.Agent):
        period = 0.01
        asked = 0

        def step(self) -> None:
            self.asked += 1
            self.runtime.state("sleeper")

    class Quiet(pb3a.Agent):
        asked = 0

    system = System("cancelled").add("sleeper", Sleeper).add("asker", Asker)
    with system.launch() as run:
        eventually(lambda: run.state("asker")["asked"] > 3, what="the agent asking")
        run.set_state("sleeper", busy=True)
        time.sleep(0.3)                     # the sleeper in its step, the agent's read
        asked = run.state("asker")["asked"]     # of it waiting
        time.sleep(0.2)
        assert run.state("asker")["asked"] == asked
        run.swap("asker", Quiet, timeout=5.0)   # cancels that wait
        assert run.stats().modules["asker"].errors == 0
        assert not [e for e in run.logs() if e.module == "asker" and e.level == "ERROR"]


def test_an_agent_moves_and_relinks_a_module_it_writes_to_and_is_answered() -> None:
    """A move or relink of a module pauses the modules that write to it, and the agent
    that asked was one: its own request was cancelled ("module 'commander' is being
    paused ... may still be carried out"), though the change went on, and the rest of
    its step was skipped without a word. A writer waiting in a runtime call is now held
    where it waits while its links change, and is answered after."""
    system = System("commanding")
    system.node("a")
    system.node("b")
    system.add("relay", Relay, node="a")
    system.add("other", Relay, node="a")
    system.add("commander", Commander, node="a")
    system.link("commander.command", "relay.x")
    with system.launch() as run:
        answers = eventually(lambda: len(a := run.state("commander")["answers"]) == 3 and a,
                             timeout=30, what="the commander's three answers")
        assert answers == ["MigrationReport", "NoneType", "NoneType"], answers
        assert run.where("relay") == "b"
        assert run.stats().modules["commander"].errors == 0
        eventually(lambda: run.state("relay")["relayed"] > 0, what="the setpoint relayed")
