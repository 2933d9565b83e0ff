"""Ports: the typed inputs and outputs a module declares as class attributes.

``Input`` and ``Output`` are descriptors. On a module instance they give the
bound port (``InputPort`` / ``OutputPort``) that the runtime wires to links.
A module instantiated outside the runtime gets unconnected bound ports, so it
can be unit-tested by calling ``port.deliver(value)`` and reading what it writes.
"""

from __future__ import annotations

import collections
import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from pb3a import latencies
from pb3a.errors import RuntimeTimeout, bounded_wait, link_stuck

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Sequence

_MISSING: Any = object()

# PEP 484's numeric promotion: an int output may feed a float input (and int or float a
# complex one), so that the SPEC's Ticker (Output(int)) may feed Scale (Input(float)).
_NUMERIC_PROMOTION: dict[type, tuple[type, ...]] = {float: (int,), complex: (int, float)}
_RATE_WINDOW = 0.5   # seconds over which an input's rate is counted
WRITE_WAIT_S = 10.0  # how long a write waits for room on a lossless link, by default


@dataclass(frozen=True)
class Policy:
    """How an input keeps values: ``latest`` (newest only), ``queue:N`` (FIFO of N: when
    full, the oldest is dropped and counted) or ``lossless:N`` (FIFO of N: when full,
    nothing is dropped; the writer waits for room, up to its timeout)."""

    kind: str
    size: int = 1

    @classmethod
    def parse(cls, text: str | Policy) -> Policy:
        """Parse ``"latest"``, ``"queue"``/``"lossless"`` (64 deep), ``"queue:N"`` or
        ``"lossless:N"``; ValueError otherwise."""
        if isinstance(text, Policy):
            return text
        if not isinstance(text, str):
            raise ValueError(
                f"policy must be a string such as 'latest' or 'queue:64', got {text!r}")
        if text == "latest":
            return cls("latest", 1)
        kind, sep, size = text.partition(":")
        if kind in ("queue", "lossless"):
            if not sep:
                return cls(kind, 64)
            if size.isdigit() and int(size) > 0:
                return cls(kind, int(size))
        raise ValueError(
            f"bad policy {text!r}: use 'latest', 'queue' or 'queue:N' (the oldest value is "
            "dropped when full), or 'lossless' or 'lossless:N' (the writer waits for room), "
            "with N a positive integer"
        )

    @property
    def lossless(self) -> bool:
        """True when a full input makes its writers wait instead of dropping."""
        return self.kind == "lossless"

    def __str__(self) -> str:
        return "latest" if self.kind == "latest" else f"{self.kind}:{self.size}"


class _Port:
    """What ``Input`` and ``Output`` share: a type, optional array shape and dtype."""

    def __init__(self, type_: type = object, *, shape: tuple[int, ...] | None = None,
                 dtype: str | np.dtype | None = None) -> None:
        if not isinstance(type_, type):
            raise TypeError(f"a port's type must be a class, got {type_!r}")
        if (shape is not None or dtype is not None) and not issubclass(type_, np.ndarray):
            raise TypeError("shape and dtype may only be given for np.ndarray ports")
        self.type = type_
        self.shape = tuple(shape) if shape is not None else None
        self.dtype = np.dtype(dtype) if dtype is not None else None
        self.name = ""
        # values of exactly this type need no further check (the writer's fast path)
        self.plain_type = type_ if self.shape is None and self.dtype is None else None

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, instance: Any, owner: type | None = None) -> Any:
        if instance is None:
            return self
        ports = instance.__dict__.get("_pb3a_ports")
        if ports is None:
            ports = instance._pb3a_bind_ports()
        return ports[self.name]

    def __set__(self, instance: Any, value: Any) -> None:
        raise AttributeError(f"port {self.name!r} cannot be assigned; use .write() on outputs")

    def describe(self) -> str:
        """The port's type as written in error messages, e.g. ``ndarray[(16,), float32]``."""
        text = self.type.__name__
        if self.shape is not None or self.dtype is not None:
            text += f"[{self.shape}, {self.dtype}]"
        return text

    def fit(self, value: Any) -> Any:
        """``value`` as the port carries it, else TypeError (``check``): a number of
        another numeric type made the port's, as a link promotes an int output to a
        float input. A float output takes an int or a numpy number (a ``float32``, or
        the ``int64`` that ``np.clip`` of an int gives) as a float; an int output a
        numpy integer as an int. A value of the port's type (a subclass too) is kept as
        it is, and a bool stays no number here."""
        if not isinstance(value, (self.type, bool, np.bool_)):
            if self.type is float and isinstance(value, (int, np.integer, np.floating)):
                return float(value)
            if self.type is int and isinstance(value, np.integer):
                return int(value)
        self.check(value)
        return value

    def check(self, value: Any) -> None:
        """Raise TypeError unless ``value`` is an instance of the port's type (and shape/dtype)."""
        if not isinstance(value, self.type):
            kind = type(value)          # (numpy's bool said "bool", as if True were refused)
            got = kind.__name__ if kind.__module__ == "builtins" else \
                f"{kind.__module__}.{kind.__qualname__}"
            raise TypeError(f"port {self.name!r} carries {self.describe()}, got {got}")
        if self.shape is not None and value.shape != self.shape:
            raise TypeError(f"port {self.name!r} needs shape {self.shape}, got {value.shape}")
        if self.dtype is not None and value.dtype != self.dtype:
            raise TypeError(f"port {self.name!r} needs dtype {self.dtype}, got {value.dtype}")


class Input(_Port):
    """An input port: ``Input(float)``, ``Input(np.ndarray, shape=(16,), dtype="float32")``.

    ``policy`` is ``"latest"`` (default), ``"queue:N"`` or ``"lossless:N"``; a link may
    override it.
    """

    def __init__(self, type_: type = object, *, shape: tuple[int, ...] | None = None,
                 dtype: str | np.dtype | None = None, policy: str = "latest") -> None:
        super().__init__(type_, shape=shape, dtype=dtype)
        self.policy = Policy.parse(policy)

    def check_fed(self, value: Any) -> None:
        """``check``, as for a value some output that may feed this input wrote: an int
        on a float input passes (the promotion ``accepts`` allows links)."""
        if not isinstance(value, _NUMERIC_PROMOTION.get(self.type, ())):
            self.check(value)

    def accepts(self, output: Output) -> str | None:
        """Why ``output`` cannot feed this input, or None when it can."""
        promoted = _NUMERIC_PROMOTION.get(self.type, ())
        if not issubclass(output.type, self.type) and not issubclass(output.type, promoted):
            return (f"{output.describe()} is not {self.describe()} or a subclass of it")
        if self.shape is not None and output.shape != self.shape:
            return f"shape {output.shape} does not match {self.shape}"
        if self.dtype is not None and output.dtype != self.dtype:
            return f"dtype {output.dtype} does not match {self.dtype}"
        return None


class Output(_Port):
    """An output port: ``Output(int)``. ``write()`` type-checks in the writer."""

    def __init__(self, type_: type = object, *, shape: tuple[int, ...] | None = None,
                 dtype: str | np.dtype | None = None, **other: Any) -> None:
        if other:       # (Python named _Port.__init__, which no user wrote)
            hint = ("; a policy is the input's (Input(float, policy=...)) or the link's"
                    if "policy" in other else "")
            raise TypeError(f"Output() takes no {', '.join(map(repr, other))}: its type, "
                            f"and shape and dtype for an np.ndarray{hint}")
        super().__init__(type_, shape=shape, dtype=dtype)


class InputPort:
    """An input bound to one module instance: holds received values by its policy.

    ``deliver`` may be called from any thread; ``read`` from the module's own calls.
    A ``lossless`` queue never drops: its feeders take only what it has room for
    (``claim_room``, ``put``), and a read that makes room wakes whoever waits for it.
    """

    def __init__(self, spec: Input, owner: str = "") -> None:
        self.spec = spec
        self.name = spec.name
        self.owner = owner
        self.policy = spec.policy
        self.received = 0            # values delivered to this port
        self.drops = 0               # values lost to queue overflow (or on the link)
        self.link_failures = 0       # values lost because a link or its peer failed
        self.latency = math.nan      # smoothed seconds from write to delivery
        self.latency_counts = [0] * latencies.BUCKETS   # values per latency bucket
        self._rate = 0.0             # values per second over the last closed window
        self.source = ""             # the link its counters are of (kept once unlinked)
        self.linked: set[str] = set()  # the links that feed it now (an unlink drops one)
        self._values: collections.deque[Any] = collections.deque()
        self._latest: Any = _MISSING
        self._fresh = False
        self._undispatched = 0
        self._last_arrival = math.nan
        self._window_start = -math.inf
        self._window_count = 0
        self._fifo = self.policy.kind != "latest"     # queue or lossless (the read path)
        self._lossless = self.policy.lossless
        self._lock = threading.Lock()
        self._room = threading.Condition(self._lock)  # lossless: a read made room
        self._room_wanted = False    # lossless: a feeder found it full; the next read tells
        self._notify: Callable[[InputPort], None] | None = None
        # lossless: called (from the reading thread) when a read makes room that a ring's
        # receiver waits for; the worker sets it to ring its own doorbell
        self._on_room: Callable[[], None] | None = None

    # -- the module's side -------------------------------------------------
    @property
    def has_value(self) -> bool:
        """True when ``read()`` would return a value."""
        if self._fifo:
            return bool(self._values)
        return self._latest is not _MISSING

    @property
    def pending(self) -> int:
        """Values not yet read: the queue length, or 1 if the latest value is unread."""
        if self._fifo:
            return len(self._values)
        return 1 if self._fresh else 0

    def read(self, default: Any = _MISSING) -> Any:
        """The newest value (``latest``) or the next one in order (``queue``, ``lossless``).

        Without a value, returns ``default`` if given, else raises LookupError.
        """
        self._lock.acquire()
        try:
            if self._fifo:
                if self._values:
                    value = self._values.popleft()
                    if self._room_wanted and len(self._values) < self.policy.size:
                        self._made_room()
                    return value
            elif self._latest is not _MISSING:
                self._fresh = False
                return self._latest
        finally:
            self._lock.release()
        if default is not _MISSING:
            return default
        raise LookupError(
            f"input {self.name!r} of module {self.owner!r} has no value yet; "
            "check .has_value or pass read(default=...)"
        )

    def read_all(self) -> list[Any]:
        """Every value pending, oldest first (``queue``, ``lossless``), or ``[latest]`` if
        unread."""
        with self._lock:
            if self._fifo:
                values = list(self._values)
                self._values.clear()
                if values and self._room_wanted:
                    self._made_room()
                return values
            if self._fresh:
                self._fresh = False
                return [self._latest]
            return []

    # -- the runtime's side ------------------------------------------------
    def deliver(self, value: Any, sent_at: float | None = None) -> None:
        """Accept one value from the link (or a test). Thread-safe."""
        self.deliver_many((value,), sent_at)

    def deliver_many(self, values: Sequence[Any], sent_at: float | None = None) -> None:
        """Accept values in link order; ``sent_at`` is when the newest was written.

        A ``queue`` drops its oldest values beyond its size; a ``lossless`` queue keeps
        them all (its feeders respect its room, but two at once may overfill it briefly).
        """
        count = len(values)
        now = time.monotonic()
        self._lock.acquire()
        try:
            self.received += count
            if sent_at is not None:
                lat = now - sent_at if now > sent_at else 0.0
                old = self.latency
                self.latency = lat if old != old else old + 0.1 * (lat - old)  # NaN: the first
                # every value of a batch counts at the newest one's latency (a lower bound)
                self.latency_counts[latencies.bucket(lat)] += count
            # rate: values counted over windows of at least _RATE_WINDOW seconds; the
            # first arrival only opens the first window (it started at -inf: rate 0)
            self._window_count += count
            self._last_arrival = now
            if now - self._window_start >= _RATE_WINDOW:
                self._rate = self._window_count / (now - self._window_start)
                self._window_start, self._window_count = now, 0
            if self._fifo:
                held = self._values
                held.extend(values)
                overflow = len(held) - self.policy.size
                if overflow > 0 and not self._lossless:
                    for _ in range(overflow):
                        held.popleft()
                    self.drops += overflow
                self._undispatched = min(self._undispatched + count, len(held))
                notify = True
            else:
                self._latest = values[-1]
                self._fresh = True
                # One undispatched call is enough: it will read the newest value.
                notify = self._undispatched == 0
                self._undispatched = 1
        finally:
            self._lock.release()
        if notify and self._notify is not None:
            self._notify(self)

    def claim_room(self) -> int:
        """How many more values a ``lossless`` queue takes now (0 or less when full; then
        the next read calls ``_on_room``). For the receiver of a ring that feeds it."""
        with self._lock:
            room = self.policy.size - len(self._values)
            if room <= 0:
                self._room_wanted = True
            return room

    def put(self, values: Sequence[Any], timeout: float, link: str,
            counter: WaitCounter | None = None) -> None:
        """Deliver values into a ``lossless`` queue, waiting for room whenever it is full
        (at most ``timeout`` seconds in all; ``counter`` counts the wait). Raises
        RuntimeTimeout (naming ``link``) when the reader made no room in time, or at once
        when the link is cut meanwhile (``counter.cancel()``, as ``OutputPort.disconnect``
        calls it); the values not in yet are not delivered. For a writer in this process:
        it waits without holding the reader's module lock, so the reader can read and wake
        it. While the writer is being paused (``counter.let_through``) they go in, room or
        not."""
        waited, done, total = 0.0, 0, len(values)
        try:
            while done < total:
                with self._lock:
                    room = self._room_for(total - done, counter)
                    if room <= 0:
                        if not waited and counter is not None:
                            counter.begin()
                        start = time.monotonic()
                        deadline = start + timeout - waited
                        if counter is not None:
                            counter.waiting_on = self      # (before it looks at cancelled)
                        try:
                            while room <= 0:
                                left = deadline - time.monotonic()
                                if counter is not None and counter.cancelled:
                                    raise link_cut(link, total - done)
                                if left <= 0:
                                    raise link_stuck(link, timeout, total - done)
                                self._room_wanted = True
                                self._room.wait(left)
                                room = self._room_for(total - done, counter)
                        finally:
                            waited += time.monotonic() - start
                chunk = values[done:done + room]
                self.deliver_many(chunk, time.monotonic())
                done += len(chunk)
        finally:
            if waited and counter is not None:
                counter.wait_s += waited

    def _room_for(self, want: int, counter: WaitCounter | None) -> int:
        """How many values ``put`` may deliver now (under the lock): the queue's room, or
        all ``want`` while its writer is let through."""
        if counter is not None and counter.through:
            return want
        return self.policy.size - len(self._values)

    def _made_room(self) -> None:
        """A read made room in a full lossless queue: wake its feeders (under the lock)."""
        self._room_wanted = False
        self._room.notify_all()
        if self._on_room is not None:
            self._on_room()

    def take_events(self, most: int) -> int:
        """Claim up to ``most`` ``on_input`` calls for this port; returns how many."""
        self._lock.acquire()
        claimed = most if most < self._undispatched else self._undispatched
        self._undispatched -= claimed
        self._lock.release()
        return claimed

    def give_back(self, calls: int) -> None:
        """Return ``calls`` claimed by ``take_events`` and not made: they are owed again."""
        self._lock.acquire()
        self._undispatched += calls
        self._lock.release()

    @property
    def owes_calls(self) -> bool:
        """True while values are waiting for their ``on_input`` call."""
        return self._undispatched > 0

    def take_event(self) -> bool:
        """Claim one ``on_input`` call for this port; False if nothing is left to dispatch."""
        return self.take_events(1) == 1

    @property
    def rate(self) -> float:
        """Values per second over the last window; decays once values stop arriving (at
        most 1 / the seconds since the last one), as ``stats()`` reports it: a module or
        agent acting on it sees a writer that stopped (computed when read: delivery only
        counts)."""
        if math.isnan(self._last_arrival):
            return 0.0
        now = time.monotonic()
        rate = self._rate
        if rate == 0.0 and now - self._window_start > 0:
            return self._window_count / (now - self._window_start) if self._window_count else 0.0
        idle = now - self._last_arrival
        return min(rate, 1.0 / idle) if idle > _RATE_WINDOW else rate

    def set_policy(self, policy: Policy) -> None:
        """Change the policy (a link may override the declared one); held values carry over.

        Values beyond a smaller ``queue`` size are dropped (counted); a ``lossless``
        queue keeps them all and takes new ones once it is read below its size."""
        with self._lock:
            fifo = policy.kind != "latest"
            if fifo and self._fifo:
                while len(self._values) > policy.size and not policy.lossless:
                    self._values.popleft()
                    self.drops += 1
            elif not fifo:                             # queue -> latest: keep the newest
                if self._values:
                    self._latest, self._fresh = self._values[-1], True
                self._values.clear()
            elif self._fresh:                           # latest -> queue: the unread value
                self._values.append(self._latest)
            self._undispatched = min(self._undispatched, self._pending_for(policy))
            self.policy = policy
            self._fifo, self._lossless = fifo, policy.lossless
            if self._room_wanted and len(self._values) < policy.size:   # a larger queue
                self._made_room()

    def fed_by(self, link: str) -> None:
        """``link`` feeds the port from now on. Its counters are its link's: a new link
        (a relink) starts them again, so that the link's figures are its own (the old
        writer's values were counted as the new one's); the same link (a move of the
        reader, which carried the counters) keeps them."""
        with self._lock:
            if self.source and link != self.source:
                self.received = self.drops = self.link_failures = self._window_count = 0
                self.latency_counts = [0] * latencies.BUCKETS
                self.latency = self._last_arrival = math.nan
                self._rate, self._window_start = 0.0, -math.inf
            self.source = link
            self.linked.add(link)

    def unfed_by(self, link: str) -> None:
        """``link`` feeds the port no more (it was unlinked). Its counters stay, and
        ``source`` with them: a new link starts them again (``fed_by``); ``linked``
        says whether any link feeds it now (``source`` said so after an unlink too)."""
        with self._lock:
            self.linked.discard(link)

    def export(self) -> dict[str, Any]:
        """Unconsumed values and counters, for a migration (see ``restore``)."""
        with self._lock:
            return {"values": list(self._values), "fresh": self._fresh,
                    "latest": None if self._latest is _MISSING else (self._latest,),
                    "undispatched": self._undispatched, "received": self.received,
                    "drops": self.drops, "link_failures": self.link_failures,
                    "latency_counts": list(self.latency_counts), "source": self.source}

    def restore(self, held: dict[str, Any]) -> None:
        """Take over an exported port: its values come before anything delivered later
        (a lossless queue keeps them all, even beyond its size)."""
        with self._lock:
            self._values.extend(held["values"])
            if held["latest"] is not None:
                self._latest, self._fresh = held["latest"][0], held["fresh"]
            self._undispatched = min(held["undispatched"], self._pending_for(self.policy))
            self.received += held["received"]
            self.drops += held["drops"]
            self.link_failures += held["link_failures"]
            for index, count in enumerate(held["latency_counts"]):
                self.latency_counts[index] += count
            self.source = self.source or held.get("source", "")
            owed = self._undispatched > 0
        if owed and self._notify is not None:
            self._notify(self)

    def _pending_for(self, policy: Policy) -> int:
        return len(self._values) if policy.kind != "latest" else int(self._fresh)


class OutputPort:
    """An output bound to one module instance. ``write`` checks the type, then fans out.

    Each link is a pair of sinks: ``one(value)`` for ``write`` and ``many(values)``
    for ``write_many``, which saves the per-value cost of the transport. The sinks of a
    ``lossless`` link take the writer's timeout too: ``one(value, timeout)``, and wait
    for room up to it (then raise RuntimeTimeout); one write's lossless links share its
    timeout (see ``_send_waiting``). Each link may have a counter of the writes that
    waited for room (attributes ``waits`` and ``wait_s``).
    """

    def __init__(self, spec: Output, owner: str = "") -> None:
        self.spec = spec
        self.name = spec.name
        self.owner = owner
        self.written = 0
        self._sinks: dict[str, tuple[Callable[..., Any], Callable[..., Any], bool]] = {}
        self._ones: tuple[Callable[[Any], Any], ...] = ()     # the write() path, prebuilt
        self._waiting: tuple[tuple[str, Callable[[Any, float], Any]], ...] = ()  # lossless
        self._lone: Callable[[Any, float], Any] | None = None   # ... if there is one only
        self._manys: tuple[Callable[[Sequence[Any]], Any], ...] = ()   # write_many's, prebuilt
        self._waiting_many: tuple[tuple[str, Callable[[Sequence[Any], float], Any]], ...] = ()
        self._counters: dict[str, Any] = {}    # link key -> its waits and wait_s
        self._lock = threading.Lock()

    def write(self, value: Any, timeout: float | None = None) -> None:
        """Send ``value`` on every link; TypeError (and nothing sent) if it does not fit.

        On a ``lossless`` link a full reader makes the write wait; its lossless links
        wait ``timeout`` seconds in all (None: ``WRITE_WAIT_S``), then it raises
        RuntimeTimeout: the value did not go on that link, nor on the links after it,
        nor on the dropping links (served after the lossless ones); it did go on the
        lossless links before it (the error names them). Dropping links (``latest``,
        ``queue``) never wait long."""
        if type(value) is not self.spec.plain_type:
            value = self.spec.fit(value)
        self._lock.acquire()            # (not ``with``: half the cost, paid per value)
        try:
            if self._waiting:
                if timeout is None and self._lone is not None:
                    # one lossless link and the default wait (every remote link's write):
                    # no deadline to share, no timeout to check (0.8 us of 1.3 per value)
                    self._lone(value, WRITE_WAIT_S)
                else:
                    _send_waiting(self._waiting, value,
                                  WRITE_WAIT_S if timeout is None else timeout)
            for one in self._ones:
                one(value)
            self.written += 1
        finally:
            self._lock.release()

    def write_many(self, values: Iterable[Any], timeout: float | None = None) -> None:
        """Send values in order, as repeated ``write`` would, but faster; all are checked
        first. ``timeout`` bounds the whole batch's waits on all lossless links together;
        the batch goes on each link in turn, so one that times out on a link went whole
        on the links before it and partly on that one (the error says how many did not)."""
        fit, plain = self.spec.fit, self.spec.plain_type
        batch = [value if type(value) is plain else fit(value) for value in values]
        if not batch:
            return
        with self._lock:
            if self._waiting_many:                     # lossless links first, as in write
                _send_waiting(self._waiting_many, batch,
                              WRITE_WAIT_S if timeout is None else timeout)
            for many in self._manys:
                many(batch)
            self.written += len(batch)

    def connect(self, key: str, one: Callable[..., Any], many: Callable[..., Any] | None = None,
                *, lossless: bool = False, counter: Any = None) -> None:
        """Add a link: ``one(value)`` / ``many(values)`` are called in write order (with
        ``lossless``, ``one(value, timeout)`` / ``many(values, timeout)``). ``counter``
        counts the link's writes that waited for room (see ``track``); if it has a
        ``cancel()`` (a ring does), ``disconnect`` calls it first, so that a write
        waiting for room on the link gives up instead of holding the port."""
        if many is None:
            def many(values: Sequence[Any], *timeout: float) -> None:
                for value in values:
                    one(value, *timeout)
        with self._lock:
            self._sinks[key] = (one, many, lossless)
            self._prebuild()
        if counter is not None:
            self.track(key, counter)

    def disconnect(self, key: str) -> bool:
        """Remove a link; False if there was none. No write is in progress on return.

        A write waiting for room on that link gives up at once (RuntimeTimeout)."""
        cancel = getattr(self._counters.get(key), "cancel", None)
        if cancel is not None:
            cancel()
        self.untrack(key)
        with self._lock:
            found = self._sinks.pop(key, None) is not None
            self._prebuild()
            return found

    def _prebuild(self) -> None:
        sinks = self._sinks.values()
        self._ones = tuple(one for one, _, lossless in sinks if not lossless)
        self._waiting = tuple((key, one) for key, (one, _, lossless) in self._sinks.items()
                              if lossless)
        self._lone = self._waiting[0][1] if len(self._waiting) == 1 else None
        self._manys = tuple(many for _, many, lossless in sinks if not lossless)
        self._waiting_many = tuple((key, many) for key, (_, many, lossless)
                                   in self._sinks.items() if lossless)

    def track(self, key: str, counter: Any) -> None:
        """Count the waits of link ``key`` with ``counter`` (``waits``, ``wait_s``; one
        counter may serve several links, as one remote publication does)."""
        self._counters = {**self._counters, key: counter}    # replaced: readers iterate

    def untrack(self, key: str) -> None:
        self._counters = {k: c for k, c in self._counters.items() if k != key}

    def wait_figures(self) -> dict[str, Any]:
        """Writes that waited for room and seconds spent waiting: for the output (each
        counter once) and per link key."""
        counters = self._counters
        links = {key: (c.waits, c.wait_s) for key, c in counters.items()}
        distinct = {id(c): c for c in counters.values()}.values()
        return {"waits": sum(c.waits for c in distinct),
                "wait_s": sum(c.wait_s for c in distinct), "links": links}

    @property
    def links(self) -> list[str]:
        """Keys of the links this output feeds."""
        return list(self._sinks)

    def let_through(self, on: bool) -> None:
        """While ``on``, writes on this output's lossless links take no heed of room in
        the input: inside its process they go into it, on a ring the reader takes the
        ring's all, and the input holds more than its size for a while (see
        ``WaitCounter.let_through``, ``ShmRing.let_through``). A remote link's are not."""
        for counter in self._counters.values():
            let_through = getattr(counter, "let_through", None)
            if let_through is not None:
                let_through(on)


def _send_waiting(sinks: tuple[tuple[str, Callable[[Any, float], Any]], ...], payload: Any,
                  timeout: float) -> None:
    """Give ``payload`` to each lossless link's sink in turn, all within ``timeout``: one
    deadline for the write, not one per link. A link that times out (or is cut) raises
    RuntimeTimeout; the links before it have the payload, and the error says so: a
    write is not taken back."""
    timeout = bounded_wait(timeout, "write on a lossless link")
    deadline = time.monotonic() + timeout if len(sinks) > 1 else 0.0
    left = timeout
    for done, (_, sink) in enumerate(sinks):
        if done:
            left = max(0.0, deadline - time.monotonic())
        try:
            sink(payload, left)
        except RuntimeTimeout as exc:
            if not done:
                raise
            went = ", ".join(key.replace("->", " -> ") for key, _ in sinks[:done])
            raise RuntimeTimeout(f"{exc}; the write's {timeout:g} s were for all its lossless "
                                 f"links, and it went on {went} already (a write is not "
                                 "taken back)") from None


def link_cut(link: str, unsent: int) -> RuntimeTimeout:
    """The error of a write that waited for room on a lossless link when it was cut."""
    what = "the value was" if unsent == 1 else f"{unsent} values were"
    return RuntimeTimeout(f"write on lossless link {link.replace('->', ' -> ')} gave up: the "
                          f"link was cut while the write waited for room ({what} not sent)")


class WaitCounter:
    """How many writes on a link waited for room, counted as each wait begins (so that
    a writer stuck now shows), and how long in all those that ended waited. For a
    lossless link inside one process (``InputPort.put``), ``cancel()`` cuts the link: a
    write waiting for room on it gives up at once, as one waiting on a ring does; and
    ``let_through`` lets writes in without room while the writer is being paused."""

    __slots__ = ("cancelled", "through", "wait_s", "waiting_on", "waits")

    def __init__(self) -> None:
        self.waits = 0
        self.wait_s = 0.0
        self.cancelled = False
        self.through: list[None] = []   # one per pause of the writer under way (append
                                        # and pop are atomic: pauses may overlap)
        self.waiting_on: InputPort | None = None    # the input a write last waited on

    def cancel(self) -> None:
        """The link is being cut: a write waiting for room on it gives up now."""
        self.cancelled = True
        self._wake()

    def let_through(self, on: bool) -> None:
        """A pause of the writer begins (``on``) or ends. A pause waits for the writer's
        call, which may be a write waiting for a reader in the same process, and that
        reader may be slow, or paused next (a move): while the pause waits, writes go in
        room or not, so the call ends and nothing is lost (as a closing ring's flush)."""
        if on:
            self.through.append(None)
        else:
            self.through.pop()
        self._wake()

    def _wake(self) -> None:
        port = self.waiting_on
        if port is not None:
            with port._lock:
                port._room.notify_all()

    def begin(self) -> None:
        self.waits += 1
