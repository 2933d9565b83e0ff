"""``ModuleActor``: one module instance as an actor inside a worker process.

The actor owns the module's lock. Its thread (when the module has a period)
calls ``step``; a dispatch task, run by the worker's ``EventPool`` or inline by
its receiver, calls ``on_input``; state capture and swaps take the same lock,
so none of them ever overlap.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import queue
import sysconfig
import threading
import time
import traceback
from collections import deque
from typing import TYPE_CHECKING, Any

from pb3a import latencies
from pb3a.config import checks
from pb3a.errors import RuntimeCancelled
from pb3a.model.module import (
    Module,
    can_hold,
    fixed_rate_of,
    give_period,
    restore_state,
    stepped_period,
)
from pb3a.model.ports import InputPort, OutputPort
from pb3a.model.state_edits import checked
from pb3a.transport import pickling
from pb3a.worker.rate import FixedRate
from pb3a.worker.waits import RuntimeWait, run_posted

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator

    from pb3a.model.module import Module

log = logging.getLogger("pb3a.module")
# Frames in these are not the user's: where an error of theirs was raised is the
# innermost frame outside them (Python's own library, the installed packages, PB3A).
_NOT_THE_USERS = tuple({sysconfig.get_path(name) for name in ("stdlib", "platstdlib",
                                                               "purelib", "platlib")}
                       | {os.path.dirname(os.path.dirname(__file__))})


def raised_at(exc: BaseException) -> str:
    """Where the user's code raised ``exc``, as " (at file.py:12 in step)": its last
    line alone ("ZeroDivisionError: division by zero") named no place, and the
    traceback, logged once, was soon pushed out of the log by what came after."""
    found = None
    tb = exc.__traceback__
    while tb is not None:
        if not tb.tb_frame.f_code.co_filename.startswith(_NOT_THE_USERS):
            found = tb
        tb = tb.tb_next
    if found is None:
        return ""
    code = found.tb_frame.f_code
    return f" (at {os.path.basename(code.co_filename)}:{found.tb_lineno} in {code.co_name})"


_running = threading.local()      # .name: the module whose hook this thread runs now


def running_module() -> str:
    """The name of the module whose hook (``setup``, ``step``, ``on_input``,
    ``teardown``) runs on this thread now, "" outside one: what a worker's log record is
    about, so that ``pb3a logs --module`` finds what a module logs on a logger of its
    own. (A thread the module started itself runs none.)"""
    return getattr(_running, "name", "")


_BODIES = ("step", "on_input")   # hooks that run only while the module runs
_EVENT_BUDGET = 256  # events handled per dispatch task before yielding to other modules
_HAND_OVER_S = 0.01  # longest a step loop waits for a waiter to take the lock it left
_WAIT_SLICE = 0.02   # a request waiting for a module lock looks this often for a body that
                     # has started waiting for the runtime (then runs on its thread)


class SetupError(Exception):
    """A module's ``setup`` raised, or a swapped-in class refused the state: it does not
    run (its start, its swap, fails)."""


class HandOverLock:
    """The module lock: a plain lock whose step loop can hand it to waiting threads.

    Locks are not fair: a module with period 0 releases its lock after a step and
    takes it again before a waiting state request, swap or event has even woken up,
    starving them for hundreds of steps; so does a dispatch task with more events to
    run. Every taker counts itself in ``waiters`` while it waits, and a request (a state
    read or edit, a pause, swap or stop) in ``requests`` too; the step loop hands over
    between two steps, and a dispatch task ends its batch for a request (not for the
    module's own step thread, which waits there all the time when its period is 0).
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.waiters: list[None] = []     # one entry per waiting thread (append/pop are atomic)
        self.requests: list[None] = []    # ... per waiting request
        self.release = self._lock.release
        self.locked = self._lock.locked
        # the per-value path: one C call when the lock is free (then nobody waits)
        self.try_acquire = functools.partial(self._lock.acquire, False)

    def acquire(self, timeout: float = -1, request: bool = False) -> bool:
        waiting = self.waiters
        waiting.append(None)
        if request:
            self.requests.append(None)
        try:
            return self._lock.acquire(timeout=timeout)
        finally:
            waiting.pop()
            if request:
                self.requests.pop()

    def __enter__(self) -> HandOverLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self._lock.release()

    def hand_over(self) -> None:
        """Called without the lock: let the threads waiting for it take it first."""
        if not self.waiters:
            return
        deadline = time.monotonic() + _HAND_OVER_S
        while self.waiters and time.monotonic() < deadline:
            time.sleep(0)             # (releases the GIL: the waiter can run)


class EventPool:
    """The per-process worker pool that runs event-driven bodies."""

    def __init__(self, threads: int = 4) -> None:
        self._tasks: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._threads = [threading.Thread(target=self._run, name=f"pb3a-event-{i}", daemon=True)
                         for i in range(threads)]
        for thread in self._threads:
            thread.start()

    def submit(self, task: Callable[[], None]) -> None:
        self._tasks.put(task)

    def _run(self) -> None:
        while (task := self._tasks.get()) is not None:
            try:
                task()
            except BaseException:           # a thread of every module here: never die
                log.exception("event pool: unexpected error; going on")

    def close(self, timeout: float = 2.0) -> None:
        for _ in self._threads:
            self._tasks.put(None)
        deadline = time.monotonic() + timeout
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()))


def _always() -> bool:
    return True


def _same(assigned: Any, period: float | None) -> bool:
    """Whether a period ``assigned`` is ``period`` (None, or a number equal to it)."""
    return assigned is period or (isinstance(assigned, (int, float)) and assigned == period)


def let_go(module: Module) -> None:
    """Drop the attributes of an instance no longer run, as Python's own exit would: its
    open files are closed, their buffers written. Every instance is in a reference cycle
    (it holds its actor's callbacks), which only a garbage collection frees: one that
    closes a file's layers in no set order, losing what they buffered (CPython's
    bpo-17852), or none at all, as the worker ends with ``os._exit``: a recorder that
    opened its file in ``setup()`` and had no ``teardown()`` lost every line it had not
    flushed. Values a new instance took (a swap's state) live on in it. Those its
    class keeps in ``__slots__``, outside its ``__dict__``, are dropped too."""
    vars(module).clear()
    for cls in type(module).__mro__:
        slots = getattr(cls, "__slots__", ())
        for slot in (slots,) if isinstance(slots, str) else slots:
            if slot in ("__dict__", "__weakref__"):
                continue
            if slot.startswith("__") and not slot.endswith("__"):     # (name-mangled)
                slot = f"_{cls.__name__.lstrip('_')}{slot}"
            with contextlib.suppress(AttributeError):     # (never set)
                delattr(module, slot)


class ModuleActor:
    """Runs one module: its lock, its step thread, its event dispatch and counters."""

    def __init__(self, name: str, module: Module, schedule: Callable[[Callable[[], None]], None],
                 period: float | None,
                 on_error: Callable[[ModuleActor, str, str], None] | None = None,
                 on_period: Callable[[str], None] | None = None,
                 fixed_rate: bool | None = None) -> None:
        """``on_period``: told the module's name when it assigns itself a period
        (``assign_period``), for the runtime's record to learn it (its worker tells the
        launcher: ``pb3a.worker.periods``). ``fixed_rate``: the configuration's (None:
        the class's own), whether its steps are due a period after the last began
        (``pb3a.worker.rate``) rather than a period after it ended."""
        self.name = name
        self.on_error = on_error
        self.on_period = on_period
        self.module = module
        module.__dict__["_pb3a_giving_way"] = self.waiting   # (see Driver.request)
        self.period = period
        self._give_period(module, period)
        self._fixed_rate_given = fixed_rate
        self._rate = FixedRate()      # (with fixed_rate) when its next step is due
        self.lock = HandOverLock()
        self.steps = self.events = self.errors = 0
        self.cut = False         # a batch of events ended early for a request (see call_many)
        self.cpu = 0.0
        # Per-call CPU timing costs two system calls; a worker hosting one module
        # turns it off and reports its whole process's CPU time instead.
        self.timed = True
        self.last_error = ""
        self.last_error_at: float | None = None     # (wall clock: ModuleStats')
        self.running = False
        self.in_setup = False         # its setup runs (its agent's requests say so)
        self._schedule = schedule     # runs a dispatch task: the event pool, or inline
        self._pending: deque[InputPort] = deque()
        self._scheduled = False
        self._sched_lock = threading.Lock()
        # the step thread sleeps on it; a stop and a period set anew wake it
        self._wake = threading.Condition(self._sched_lock)
        self._step_clock: int | None = None
        self._step_cpu = 0.0
        self._stepped_at: float | None = None  # when its last step ended (monotonic)
        self._torn_down = False                 # its teardown ran, or runs now (once)
        # from its teardown on (stopped, retired, swapped out), a period the module
        # assigns is its instance's alone; and while a swap's new instance sets up,
        # whether it assigned one (told once the swap succeeds; None: no swap)
        self._quiet = False
        self._owed: bool | None = None
        self._teardown_once = threading.Lock()  # held while its teardown runs
        self._halted = False                    # stopping: it does not start any more
        # whether its bodies may run now (its worker's lease holds: Lease.holds)
        self.may_run: Callable[[], bool] = _always
        self._thread: threading.Thread | None = None
        self._holder = 0                        # the thread running a body now (0: none)
        self._calling: tuple[str, float] | None = None   # the hook called now, since when
        self._wait: RuntimeWait | None = None   # its runtime call in progress, if any
        self._stopping_for = ""                 # why someone waits to stop it, if anyone
        self._setup_failed = False              # its setup raised: it never ran
        self.ports = module._pb3a_bind_ports(name)
        self._read_class()
        for port in self.inputs.values():
            port._notify = self._on_port_event

    def _read_class(self) -> None:
        """What the runtime reads of the module's class, once per instance (the step and
        event paths ask it at every call): whether it handles events, and whether its
        steps keep a fixed rate (the configuration's option, else its class's: a swap's
        new class's, unless the configuration gave one)."""
        cls = type(self.module)
        self._event_driven = cls.is_event_driven()
        self.fixed_rate = fixed_rate_of(cls, self._fixed_rate_given)

    @property
    def inputs(self) -> dict[str, InputPort]:
        return {n: p for n, p in self.ports.items() if isinstance(p, InputPort)}

    @property
    def outputs(self) -> dict[str, OutputPort]:
        return {n: p for n, p in self.ports.items() if isinstance(p, OutputPort)}

    # -- life cycle --------------------------------------------------------
    def start(self) -> None:
        """Run ``setup``, then start stepping (threaded) and dispatching (event-driven);
        ``SetupError`` if ``setup`` raised: the module never runs (a driver whose device
        did not open would otherwise step against it, the error only in the log)."""
        with self._setting_up():
            set_up = self.call("setup")
        with self._sched_lock:
            halted = self._halted
            if not halted and set_up:
                self.running = True
                # (under the lock, as a period set anew starts one: one its setup
                # assigned started a second step thread)
                if self._steps(self.period):
                    self._start_stepping()
            elif not halted:
                self._halted = self._setup_failed = True
        if halted:                              # stopped while it set up: it never runs,
            if set_up:                          # and what its setup opened is closed
                self._tear_down()
            return
        if not set_up:
            raise SetupError(f"module {self.name!r} raised in setup: {self.last_error}")
        if not self._steps(self.period) and type(self.module).step is not Module.step:
            # (not an error: a base class may step for subclasses that set a period)
            log.warning("module %r: %s defines step() but has no period, so step() is "
                        "never called: give the class or the module a period (0 = as fast "
                        "as possible)", self.name, type(self.module).__qualname__)
        with self._sched_lock:   # values that arrived before start
            kick = bool(self._pending) and not self._scheduled
            self._scheduled = self._scheduled or kick
        if kick:
            self._schedule(self._dispatch)

    def stop(self, timeout: float = 5.0) -> bool:
        """Stop stepping and dispatching, then run ``teardown`` (once). False if a body
        overran: the module has not stopped, and a stop asked again waits for it again
        (a second remove of a module stuck in its step was taken for stopped: it was
        dropped, its teardown never run). ``timeout`` bounds the whole stop (the step
        thread's join and the lock's wait each took it: a stuck step answered after
        twice the time, past its caller's wait). A stop asked while the teardown runs
        (a close a Ctrl-C interrupted, finished by the next) waits for it, within
        ``timeout``: answered at once, its worker was told to exit meanwhile, which cut
        the teardown short."""
        if self._torn_down:
            if not self._teardown_once.acquire(timeout=timeout):
                return False
            self._teardown_once.release()
            return True
        self.halt()
        deadline = time.monotonic() + timeout
        finished = True
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            # (through the join: a second wait the step starts is cancelled too, and a
            # write waiting for a reader stopped before it goes in)
            with self._giving_way("the module is stopping"):
                thread.join(timeout)
            finished = not thread.is_alive()
            if finished:
                self._thread = None
        if self.acquire_stopped(max(0.0, deadline - time.monotonic()),
                                "the module is stopping"):
            self.lock.release()
            if not self._setup_failed:      # (as a test's tearDown after a failed setUp)
                self._tear_down()
        else:
            finished = False
        return finished

    def let_go(self) -> None:
        """Drop the module's attributes once it is gone from here (stopped, removed,
        moved away): see ``let_go``."""
        let_go(self.module)

    @property
    def torn_down(self) -> bool:
        """Whether its ``teardown`` ran (or runs now)."""
        return self._torn_down

    @property
    def tearing_down(self) -> bool:
        """Whether its ``teardown`` runs now."""
        return self._teardown_once.locked()

    def busy_in(self) -> str:
        """What the module is busy in now, for an error ("in on_input for 4.2 s"); ""
        if nothing runs (any more)."""
        calling = self._calling
        if calling is None:
            return ""
        return f"in {calling[0]} for {time.monotonic() - calling[1]:.1f} s"

    def _tear_down(self) -> None:
        """Run ``teardown``, once, whoever asks (a stop, or a start halted during its
        setup, may ask at the same time): one that asks while it runs waits for it."""
        with self._teardown_once:
            torn_down, self._torn_down = self._torn_down, True
            if not torn_down:
                self._quiet = True
                self.call("teardown")

    @contextlib.contextmanager
    def _setting_up(self) -> Iterator[None]:
        """``in_setup`` while its ``setup`` runs."""
        self.in_setup = True
        try:
            yield
        finally:
            self.in_setup = False

    def halt(self) -> None:
        """Stop stepping and dispatching now, without waiting for a body in progress;
        ``stop`` then waits for it and runs ``teardown``. One halted during its
        ``setup`` does not start after it."""
        with self._sched_lock:
            self._halted = True
            self.running = False
            self._wake.notify_all()             # (a step thread between two steps)

    def _start_stepping(self) -> None:
        """The step thread (the caller holds ``_sched_lock``); one stepping already, if
        any (a start after a failed move), ends at its next turn."""
        self._thread = threading.Thread(target=self._loop, name=f"pb3a-step-{self.name}",
                                        daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        # The step thread is the module's own: its CPU clock is the module's step
        # CPU time, read without a system call per step (see ``statistics``).
        clock = time.pthread_getcpuclockid(threading.get_ident())
        self._step_clock = clock
        mine = threading.current_thread()
        try:
            while self._due(mine):
                try:
                    self._step()
                finally:
                    self._stepped_at = time.monotonic()
                self.lock.hand_over()
        finally:
            self._step_cpu += time.clock_gettime(clock)
            if self._step_clock == clock:
                self._step_clock = None

    def _step(self) -> None:
        """One step, under the module lock; with a fixed rate, noted as it begins, once
        it has the lock (``FixedRate.begun``: a step that waited for a pause to end is
        no overrun)."""
        lock = self.lock
        if not lock.try_acquire():
            lock.acquire()
        try:
            if self.fixed_rate:
                with self._sched_lock:
                    self._rate.begun(time.monotonic(), self.period or 0.0)
            if self._call_held("step", 1, timed=False):
                self.steps += 1
        finally:
            lock.release()

    def _next_due(self) -> float | None:
        """When the next step is due (None: at once): ``self.period`` after the last one
        ended, or with a fixed rate its slot (``FixedRate.due``). The caller holds
        ``_sched_lock``."""
        if self.fixed_rate:
            return self._rate.due(self.period or 0.0)
        last = self._stepped_at
        return None if last is None else last + (self.period or 0.0)

    def _due(self, mine: threading.Thread) -> bool:
        """Wait until the next step is due (``_next_due``): ``self.period`` after the
        last one ended, or with a fixed rate its slot; False once the module is to step
        no more on this thread (stopped, retired, or another thread stepping it). The
        period is read anew whenever it is set (by ``set_state``, a swap, the module
        itself), on this same thread: one set anew is slept after the last step, as
        every period is (with a fixed rate, it is due a new period after the last step
        began), not at once (its first step came at once, a controller's ``dt =
        self.period`` then integrating a whole period over a few milliseconds), and a
        module that sets its own at every step started a thread each time. No period
        any more (a swap to a class with no ``step()``), the thread ends, and a period
        given later starts another."""
        last, period = self._stepped_at, self.period
        if (last is None or period == 0) and self.running and self._thread is mine \
                and self._steps(period):
            # (due now: its first step does not wait for the lock, which its start holds
            # as it starts this thread: a request sent once the start returned came first)
            return True
        with self._sched_lock:
            while self.running and self._thread is mine:
                if not self._steps(self.period):
                    self._thread = None
                    return False
                due = self._next_due()
                wait = 0.0 if due is None else due - time.monotonic()
                if wait <= 0:
                    return True
                self._wake.wait(wait)
            return False

    # -- calls under the lock ---------------------------------------------
    def call(self, hook: str, *args: Any) -> bool:
        """Call a module hook by name under the module lock; log and count what it raises.

        The hook is looked up after the lock is taken, so a call that waited for a
        swap runs on the new instance.
        """
        return self.call_many(hook, 1, *args) == 1

    def call_many(self, hook: str, times: int, *args: Any, timed: bool | None = None,
                  claim: InputPort | None = None) -> int:
        """Call a hook ``times`` times under one hold of the lock; returns the calls that
        returned normally. Taking the lock (and the CPU clock) once per batch is what
        lets a busy input run at hundreds of thousands of values per second.

        With ``claim``, the calls are first claimed from that port's owed ``on_input``
        calls (at most ``times``), under the lock: a module paused for migration has
        no claimed-but-unrun call, so what it owes travels with it. Such a batch ends
        early when a request waits for the lock (a state read or edit, a pause, a
        swap), the calls it did not make given back to the port (``cut``): a module
        whose events come faster than it handles them would otherwise hold its lock for
        the whole batch (256 events, each as long as the module takes)."""
        lock = self.lock
        if not lock.try_acquire():
            lock.acquire()
        try:
            return self._call_held(hook, times, args, timed, claim)
        finally:
            lock.release()

    def _call_held(self, hook: str, times: int, args: tuple[Any, ...] = (),
                   timed: bool | None = None, claim: InputPort | None = None) -> int:
        """``call_many`` for a caller that holds the module lock already."""
        done = 0
        timed = self.timed if timed is None else timed
        self._holder = threading.get_ident()
        self._calling = (hook, time.monotonic())
        outer, _running.name = running_module(), self.name
        try:
            if hook in _BODIES and not (self.running and self.may_run()):
                return 0                        # stopped or migrated while waiting, or
                                                # its worker's lease ran out (fenced)
            if claim is not None:
                times = claim.take_events(times)
            start = time.thread_time() if timed else 0.0
            fn = getattr(self.module, hook)
            requests = self.lock.requests if claim is not None else ()
            # its worker's lease may run out within a batch (a remote node's): asked
            # before each call (a batch of 256 values at 5 ms each ran on 1.75 s past the
            # lease's end, beside the module's failed-over copy)
            leased = claim is not None and self.may_run is not _always
            for made in range(times):
                if requests:                    # (one list's truth: the per-value path)
                    claim.give_back(times - made)
                    self.cut = True
                    break
                if leased and not (self.running and self.may_run()):
                    claim.give_back(times - made)   # (owed still: they travel with it)
                    break
                try:
                    fn(*args)
                    done += 1
                except RuntimeCancelled as exc:     # the runtime ended the body's wait
                    log.debug("module %r: %s ended: %s", self.name, hook, exc)   # (by design)
                except BaseException as exc:    # SystemExit, CancelledError too: counted,
                    self.errors += 1            # never the end of a shared thread
                    self.last_error = f"{type(exc).__name__}: {exc}{raised_at(exc)}"
                    self.last_error_at = time.time()
                    if self.on_error is not None:
                        self.on_error(self, hook, traceback.format_exc())
                    else:
                        log.error("module %r raised in %s:\n%s", self.name, hook,
                                  traceback.format_exc())
            if timed:
                self.cpu += time.thread_time() - start
        finally:
            self._holder, self._calling, _running.name = 0, None, outer
        return done

    # On the per-value path (a port's event, its dispatch, the call) locks are taken
    # with explicit acquire/release around bodies that cannot raise: half the cost
    # of ``with`` here, paid several times per value.
    def _on_port_event(self, port: InputPort) -> None:
        if not self._event_driven:
            return
        self._sched_lock.acquire()
        if port not in self._pending:
            self._pending.append(port)
        start = self.running and not self._scheduled
        self._scheduled = self._scheduled or start
        self._sched_lock.release()
        if start:
            self._schedule(self._dispatch)

    def _dispatch(self, inline: bool = False) -> None:
        """Run the ``on_input`` calls the inputs owe, a batch at a time. ``inline`` (on
        its worker's receiver, which feeds every ring of the worker): the module's lock
        is taken only if free at once, else the dispatch ends, scheduled again (to the
        pool while the lock is held). The receiver's look at the lock before it called
        this left a moment in which a pause could take it: the receiver then waited
        for the whole pause, taking in nothing, and a move's drain of a remote lossless
        link into the module never ended."""
        budget = _EVENT_BUDGET
        lock, pending = self._sched_lock, self._pending
        while budget > 0:
            lock.acquire()
            if not pending or not self.running:
                self._scheduled = False
                lock.release()
                return
            port = pending.popleft()
            lock.release()
            if not self.lock.try_acquire():
                if inline:                      # (held: a pause, a step; never waited for)
                    with self._sched_lock:
                        if port not in pending:
                            pending.appendleft(port)
                    break
                self.lock.acquire()
            try:
                done = self._call_held("on_input", budget, (port,), claim=port)
            finally:
                self.lock.release()
            self.events += done
            budget -= max(done, 1)
            if port.owes_calls and self.running:
                with self._sched_lock:
                    if port not in self._pending:
                        self._pending.append(port)
            if self.cut:                        # (a request waits: let it in first)
                self.cut = False
                self.lock.hand_over()
            if self.lock.locked():      # held by another (a pause, say): go on once
                break                       # scheduled again (not waiting here: see above)
        self._schedule(self._dispatch)   # more to do: let other modules have a turn

    # -- a body waiting for the runtime, or a device (see ``waits``) ----------
    @contextlib.contextmanager
    def waiting(self, what: str, takes_edits: bool = True) -> Iterator[RuntimeWait]:
        """A body of this module waits for ``what`` (a runtime call, a device's answer).
        If the waiting thread holds the lock (a body), a request that needs the module
        stopped cancels the wait, and requests that need the lock for a moment (reads,
        and edits if it ``takes_edits``) run on that thread meanwhile."""
        wait, outer = RuntimeWait(what, takes_edits), self._wait
        if self._holder == threading.get_ident():
            # (one wait inside another: a read posted to a driver's request that asks the
            # device too; the outer one is the wait again after it)
            self._wait = wait
            if self._stopping_for:              # asked again after a cancellation
                wait.cancel(self._stopping_for)
        try:
            yield wait
        finally:
            if self._wait is wait:
                self._wait = outer
                if outer is not None and self._stopping_for:
                    outer.cancel(self._stopping_for)
            wait.close()

    def _cancel_wait(self, reason: str) -> None:
        wait = self._wait
        if wait is not None:
            wait.cancel(reason)

    def with_lock(self, work: Callable[[], Any], timeout: float, edit: bool = False) -> Any:
        """Run ``work`` under the module lock, or on the thread of a body that holds it
        while it waits (see ``waiting``; ``edit``: work that sets the module's state);
        TimeoutError after ``timeout``."""
        deadline = time.monotonic() + timeout
        while True:
            wait = self._wait
            if wait is not None and (future := wait.post(work, edit)) is not None:
                ran, result = run_posted(future, max(0.0, deadline - time.monotonic()))
                if ran:
                    return result
            # in slices: a body may start waiting for the runtime meanwhile
            if self.lock.acquire(timeout=min(_WAIT_SLICE, max(0.0, deadline - time.monotonic())),
                                 request=True):
                try:
                    return work()
                finally:
                    self.lock.release()
            if time.monotonic() >= deadline:
                # (what it is in, as `pb3a status` says it: the wait alone, a caller's
                # time left, read "busy in a call for 0.18 s" after 5 s)
                busy = self.busy_in()
                raise TimeoutError(f"module {self.name!r} was busy in a call for "
                                   f"{timeout:.3g} s{f' ({busy})' if busy else ''}: nothing "
                                   "was done")

    def hold_waiting(self, timeout: float) -> threading.Event | None:
        """If a body waits in a runtime call (holding the module's lock), pause it where it
        waits, for a change that only rewires the module's links: work run on its thread
        that holds until the event returned is set (the runtime's answer is taken after
        it). None when no body waits: then pause as usual. ``TimeoutError`` if the hold
        has not begun within ``timeout`` (the thread busy with other posted work)."""
        wait = self._wait
        if wait is None:
            return None
        holding, release = threading.Event(), threading.Event()

        def hold() -> None:
            holding.set()
            release.wait()

        future = wait.post(hold)
        if future is None:                      # (the call ended meanwhile)
            return None
        future.add_done_callback(lambda _: holding.set())     # (ended unrun: see below)
        if not holding.wait(timeout) and future.cancel():
            raise TimeoutError(f"module {self.name!r} was not paused within {timeout:g} s: "
                               "the call it waits in was busy")
        holding.wait()              # (begun, or ended unrun, as it was given up on)
        # done before it was let go: never run, its call having ended first (pause as usual)
        return None if future.done() else release

    def acquire_stopped(self, timeout: float, why: str) -> bool:
        """Take the module lock with no body running (see ``_giving_way``); False after
        ``timeout``."""
        with self._giving_way(why):
            return self.lock.acquire(timeout=timeout, request=True)

    @contextlib.contextmanager
    def _giving_way(self, why: str) -> Iterator[None]:
        """While a pause or a stop waits for the body running (``why``): a runtime call
        it waits in is cancelled (it raises there, see ``waits``), and its writes waiting
        for room on a lossless link go through (``letting_through``)."""
        self._stopping_for = why
        try:
            with self.letting_through():
                self._cancel_wait(why)
                yield
        finally:
            self._stopping_for = ""

    @contextlib.contextmanager
    def letting_through(self) -> Iterator[None]:
        """While a pause or a stop waits for the module's call: its writes on lossless
        links take no heed of room in their inputs, in this process or through a ring
        (not to another node: see ``OutputPort.let_through``), so a call waiting for a
        slow, stopped or paused reader ends, nothing lost."""
        outputs = self.outputs.values()
        for port in outputs:
            port.let_through(True)
        try:
            yield
        finally:
            for port in outputs:
                port.let_through(False)

    # -- state and swap ----------------------------------------------------
    def capture(self, timeout: float = 10.0) -> dict[str, Any]:
        """The module's state, taken under its lock."""
        return self.with_lock(self.module.get_state, timeout)

    def checkpoint(self, timeout: float = 10.0) -> bytes:
        """The module's state, pickled under its lock: a body cannot change a list or an
        array halfway through (the state names the module's objects, not copies). A
        state that cannot be pickled is ``Unpicklable``, naming its fields."""
        def pickled() -> bytes:
            state = self.module.get_state()
            try:
                return pickling.dumps(state)
            except pickling.PICKLING_ERRORS as exc:
                raise pickling.Unpicklable(pickling.unpicklable_reason(exc, state)) from None
        return self.with_lock(pickled, timeout)

    def retire(self) -> dict[str, Any]:
        """Leave this process (migration); the caller holds the module lock (paused).

        Runs ``teardown``, then captures the state and every input's unconsumed values.
        No body of this instance runs after it: a step or event waiting for the lock
        finds the module no longer running and returns.
        """
        with self._sched_lock:
            self.running = False
            self._wake.notify_all()             # the step thread leaves its loop
        self._quiet = self._torn_down = True
        try:
            self.module.teardown()
        except Exception:
            log.exception("module %r raised in teardown before migrating", self.name)
        return self.holdings()

    def paused_over(self) -> None:
        """A pause (to move it, to rewire its links) is over, its lock about to be let
        go: a fixed rate starts again from its next step, which the pause held back
        (``FixedRate.restart``): no burst of steps, no overrun of the module's."""
        with self._sched_lock:
            self._rate.restart()

    def reinstate(self) -> None:
        """Undo ``retire`` (a move that failed after it): ``start`` sets it up again, at
        the period it ran at (not one its teardown assigned)."""
        self._torn_down = self._quiet = False
        self.module.__dict__["period"] = self.period

    def holdings(self) -> dict[str, Any]:
        """What a migration captures: the state, the period it runs at, every input's
        unconsumed values, and the module's counters (the caller holds the module lock,
        and pickles them before letting it go). The counters go too: an agent reading a
        rate or an error trend from ``stats()`` saw steps fall from 148 to 6 at every
        move; and the period, which the module may have set itself a moment before,
        before the runtime's record learned it (``restore``)."""
        return {"state": self.module.get_state(), "period": self.period,
                "inputs": {name: port.export() for name, port in self.inputs.items()},
                "counters": {"steps": self.steps, "events": self.events,
                             "overruns": self._rate.overruns,
                             "errors": self.errors, "last_error": self.last_error,
                             "last_error_at": self.last_error_at,
                             "written": {name: port.written
                                         for name, port in self.outputs.items()}}}

    def join(self, timeout: float) -> bool:
        """Wait until the step thread has ended (after ``retire``); False on time-out."""
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)
            return not thread.is_alive()
        return True

    def restore(self, captured: dict[str, Any]) -> None:
        """Take over what ``retire`` captured elsewhere (before ``start``): all of its
        state, made at run time or not (``restore_state``), and the period it ran at,
        which is told (``on_period``) if it is not the one the record gave it here: one
        the module set itself a moment before its move, which the record had yet to
        learn (``pb3a.worker.periods``: up to a second), was lost."""
        with self.lock:
            restore_state(self.module, captured["state"])
        period = captured["period"]
        if period is not None and period != self.period:
            with self._sched_lock:
                self.module.__dict__["period"] = period
                self._step_every(period)
            if self.on_period is not None:
                self.on_period(self.name)
        for name, held in captured["inputs"].items():
            port = self.inputs.get(name)
            if port is not None:
                port.restore(held)
        counters = captured["counters"]
        self.steps += counters["steps"]
        self.events += counters["events"]
        self.errors += counters["errors"]
        self._rate.overruns += counters["overruns"]
        if not self.last_error:
            self.last_error = counters["last_error"]
            self.last_error_at = counters["last_error_at"]
        for name, written in counters["written"].items():
            if name in self.outputs:
                self.outputs[name].written += written

    def apply(self, state: dict[str, Any], timeout: float = 10.0) -> None:
        """Set state under the module lock: a live edit, each value checked against the
        kind of the field's value now (``checked``: TypeError, nothing set); the module's
        ``set_state`` raises KeyError for names it lacks, ``StateRefused`` for values its
        class refuses (``Module.state_problems``)."""
        def edit() -> None:
            try:
                now = self.module.get_state()
            except Exception:           # (one that cannot say its state: set as given)
                now = {}
            self.module.set_state({name: checked(name, now[name], value) if name in now
                                   else value for name, value in state.items()})
        # An edit that takes no turn in a body's wait (a driver's request) waits for it
        # to end, but one of the fields a class says end such a wait (a driver's device)
        # ends it: a driver re-pointed away from a device that hangs waited its request.
        ending = [name for name in getattr(type(self.module), "_pb3a_edits_end_waits", ())
                  if name in state and state[name] != getattr(self.module, name, None)]
        if ending:
            self._cancel_wait(f"its {ending[0]} is set anew")
        self.with_lock(edit, timeout, edit=True)

    def swap(self, new: Module, period: float | None,
             timeout: float = 10.0) -> tuple[list[str], list[str]]:
        """Replace the module by ``new`` keeping ports, queued values and matching state,
        stepping it every ``period`` seconds (None: only on events) from then on.
        Returns the names of the state attributes carried over, and of those dropped
        (the new class has no such field: tuned gains a user took for kept).
        """
        if not self.acquire_stopped(timeout, "the module is being swapped"):
            raise TimeoutError(f"module {self.name!r} was busy in a call for {timeout} s")
        try:
            old, before = self.module, self.period
            self._quiet = True                  # (a period its teardown assigns: its own)
            try:
                old.teardown()
            except Exception:
                log.exception("module %r raised in teardown during swap", self.name)
            specs = {name: port.spec for name, port in self.ports.items()}
            self._give_period(new, period)
            with self._sched_lock:
                self._quiet, self._owed = False, False
            try:
                state = old.get_state()
                kept = self._take(new, state)
            except Exception as exc:
                # its set_state refused the state (the old instance ran on, torn down,
                # its setup not run again)
                why = (f"{type(new).__name__} did not take {type(old).__name__}'s state: "
                       f"{type(exc).__name__}: {exc}")
            else:
                # under the same hold: a step thread waiting for the lock would otherwise
                # step the new instance before its setup, and an agent's step asking the
                # runtime there would wait for the configuration lock this swap's
                # operation holds while the swap waited for the lock: no answer until
                # the operation's timeout
                with self._setting_up():
                    if self._call_held("setup", 1) == 1:
                        self._dispatch_owed()
                        with self._sched_lock:
                            # (the swap's period, or one its setup assigned: the later)
                            self._step_every(new.__dict__["period"])
                            owed, self._owed = self._owed, None
                        if owed and self.on_period is not None:
                            self.on_period(self.name)
                        let_go(old)
                        return sorted(kept), sorted(set(state) - set(kept))
                why = f"{type(new).__name__} raised in setup: {self.last_error}"
            # the new class cannot start: the old instance back, set up again, at its
            # period before (a period the new one's setup assigned is told to no one: the
            # old instance ran on at it, and the record learned it)
            for name in [name for name in self.ports if name not in specs]:
                del self.ports[name]                    # (the one dict both instances hold)
            for name, spec in specs.items():
                self.ports[name].spec = spec
            self.module = old
            self._read_class()
            old.__dict__["period"] = before
            with self._sched_lock:
                self._owed = None
                self._step_every(before)
            with self._setting_up():
                self._call_held("setup", 1)
            self._dispatch_owed()
            raise SetupError(f"module {self.name!r}: {why}; not swapped, "
                             f"{type(old).__name__} runs on")
        finally:
            self.lock.release()

    def _steps(self, period: float | None) -> bool:
        """Whether the module is stepped at ``period``: a period, and a class with a
        ``step()`` (an empty one, stepped at period 0, took most of a core)."""
        return stepped_period(type(self.module), period) is not None

    def _step_every(self, period: float | None) -> None:
        """Step at ``period`` from now on (None: no more), if the module (the new
        instance of a swap) has a ``step()``; the caller holds ``_sched_lock``. The step
        thread takes it at its next turn (``_due``: a step under way, or one waiting for
        the module's lock, comes first, on the new instance of a swap); a module that
        stepped at no period is given a step thread."""
        self.period = period
        self._rate.restart()        # (a fixed rate: from the step after the last one)
        if self._steps(period) and self.running and self._thread is None:
            self._start_stepping()
        self._wake.notify_all()

    def retime(self, period: float) -> None:
        """Step every ``period`` seconds from now on, from the step thread's next turn
        (``_due``). The module's ``self.period`` says it at once."""
        with self._sched_lock:
            self.module.__dict__["period"] = period
            self._step_every(period)

    def assign_period(self, module: Module, value: Any) -> None:
        """``self.period = value`` in ``module`` as it runs (in a body, its ``setup``, a
        thread of its own): checked (``checks.assigned_period``: ``ValueError`` there,
        nothing changed), stepped at from the step thread's next turn (an event-driven
        module with a ``step()`` is stepped from then on, as by ``set_state``), and told
        to the runtime (``on_period``), which does not wait for it, for its record to
        learn it, so that a move, a restart and a swap keep it. Under ``_sched_lock``:
        of two threads assigning at once, the one stepped at is the last.

        From its teardown on, the instance's ``self.period`` alone is set (a removal or
        a move was told of its teardown's, and a move took the period its teardown reset
        for the module's own); from a swap's new instance it is told once the swap has
        succeeded, and stepped at from then on (one that failed left the old instance at
        the period the new one's setup assigned, and a step thread it woke or started
        stepped the old instance early, or an event-driven one once); an instance that
        is no longer this actor's (a swap's old one, or its new one before the swap
        makes it the module) sets its own alone."""
        period = checks.assigned_period(self.name, type(module), value)
        with self._sched_lock:
            module.__dict__["period"] = period
            if self._quiet or module is not self.module or period == self.period:
                return
            if self._owed is not None:          # (stepped at once the swap succeeds)
                self._owed = True
                return
            self._step_every(period)
        if self.on_period is not None:
            self.on_period(self.name)

    def _give_period(self, module: Module, period: float | None) -> None:
        """Give ``module`` (this actor's, or a swap's new instance) the period it runs
        at, on the instance (``dt = self.period`` read its class's while the
        configuration, ``add`` or ``swap`` gave it another; a framework name, it is no
        state: ``Module.get_state`` leaves it out), and make its assignment set it live
        (``assign_period``). One it assigned before it ran (in ``__init__``, or its
        ``set_state`` given its configured state) is replaced: a warning says so, unless
        it is the one given or its class's (it is no period given to the module, which
        the configuration, ``add`` or the class gives)."""
        assigned = module.__dict__.get("period", period)
        if not _same(assigned, period) and not _same(assigned, type(module).period):
            log.warning("module %r: self.period = %.60r was assigned before it ran (in "
                        "__init__ or its state), which sets nothing: the module runs at the "
                        "period given to it (%s s: the configuration's, add's or swap's, "
                        "else its class's); give its class that period, or assign "
                        "self.period in setup()", self.name, assigned, period)
        give_period(module, period, functools.partial(self.assign_period, module))

    def _dispatch_owed(self) -> None:
        """Schedule the calls its inputs owe: values that came while an instance that
        handles no events held the ports (the swap's) were not dispatched."""
        for port in self.inputs.values():
            if port.owes_calls:
                self._on_port_event(port)

    def _take(self, new: Module, state: dict[str, Any]) -> dict[str, Any]:
        """Make ``new`` the module, on these ports (those it adds made), with the part of
        ``state`` it takes (``_kept``); that part."""
        for name, spec in (*type(new).inputs.items(), *type(new).outputs.items()):
            port = self.ports.get(name)
            if port is None:
                kind = InputPort if name in type(new).inputs else OutputPort
                port = self.ports[name] = kind(spec, self.name)
                if isinstance(port, InputPort):
                    port._notify = self._on_port_event
            port.spec = spec
        new._pb3a_adopt_ports(self.ports)
        new.__dict__["_pb3a_giving_way"] = self.waiting
        kept = self._kept(new, state)
        restore_state(new, kept)
        self.module = new
        self._read_class()
        return kept

    def _kept(self, new: Module, state: dict[str, Any]) -> dict[str, Any]:
        """The part of the old instance's ``state`` a swap gives ``new``: the fields its
        class has, and those the old instance made at run time (a new version of the
        same module keeps its map; they were dropped, silently), but a name ``new``'s
        class declares as no state (a port, a method). A class with its own
        ``get_state`` alone knows its fields: those a new instance of it reports."""
        cls = type(new)
        has = set(cls.state_names()) | set(new.get_state())
        if cls.get_state is not Module.get_state:
            return {name: value for name, value in state.items() if name in has}
        declared = set(type(self.module).state_names())     # (the rest it made)
        return {name: value for name, value in state.items()
                if name in has or (name not in declared and can_hold(cls, name))}

    def _step_thread_cpu(self) -> float:
        clock = self._step_clock
        if clock is not None:
            try:
                return self._step_cpu + time.clock_gettime(clock)
            except OSError:                     # the thread ended just now
                pass
        return self._step_cpu

    def statistics(self) -> dict[str, Any]:
        """Counters of the module, of its inputs, and of its outputs (values written;
        writes that waited for room, per output and per link)."""
        inputs = {}
        for name, port in self.inputs.items():
            inputs[name] = {"received": port.received, "drops": port.drops,
                            "pending": port.pending, "latency": port.latency,
                            "latency_counts": latencies.used(port.latency_counts),
                            "rate": port.rate, "link_failures": port.link_failures,
                            "policy": str(port.policy)}
        outputs = {name: port.written for name, port in self.outputs.items()}
        waits = {name: port.wait_figures() for name, port in self.outputs.items()}
        calling = self._calling
        return {"calling": calling and (calling[0], time.monotonic() - calling[1]),
                "class": f"{type(self.module).__module__}:{type(self.module).__qualname__}",
                "steps": self.steps, "events": self.events, "errors": self.errors,
                "cpu": self.cpu + self._step_thread_cpu(), "last_error": self.last_error,
                "last_error_at": self.last_error_at,
                "running": self.running,
                "period": stepped_period(type(self.module), self.period),
                "fixed_rate": self.fixed_rate, "overruns": self._rate.overruns,
                "inputs": inputs, "outputs": outputs, "waits": waits}
