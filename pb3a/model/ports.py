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

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable, Sequence

_MISSING: Any = object()

# PEP 484's numeric promotion: an int output may feed a float input (and int or float a
# complex one), so that the SPEC's Ticker (Output(int)) may feed Scale (Input(float)).
_NUMERIC_PROMOTION: dict[type, tuple[type, ...]] = {float: (int,), complex: (int, float)}
_RATE_WINDOW = 0.5   # seconds over which an input's rate is counted


@dataclass(frozen=True)
class Policy:
    """How an input keeps values: ``latest`` (newest only) or ``queue:N`` (FIFO of N)."""

    kind: str
    size: int = 1

    @classmethod
    def parse(cls, text: str | Policy) -> Policy:
        """Parse ``"latest"``, ``"queue"`` (64 deep) or ``"queue:N"``; ValueError otherwise."""
        if isinstance(text, Policy):
            return text
        if not isinstance(text, str):
            raise ValueError(
                f"policy must be a string such as 'latest' or 'queue:64', got {text!r}")
        if text == "latest":
            return cls("latest", 1)
        if text == "queue":
            return cls("queue", 64)
        kind, sep, size = text.partition(":")
        if kind == "queue" and sep and size.isdigit() and int(size) > 0:
            return cls("queue", int(size))
        raise ValueError(
            f"bad policy {text!r}: use 'latest', 'queue' or 'queue:N' with N a positive integer"
        )

    def __str__(self) -> str:
        return "latest" if self.kind == "latest" else f"queue:{self.size}"


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

    def check(self, value: Any) -> None:
        """Raise TypeError unless ``value`` is an instance of the port's type (and shape/dtype)."""
        if not isinstance(value, self.type):
            raise TypeError(
                f"port {self.name!r} carries {self.describe()}, got {type(value).__name__}"
            )
        if self.shape is not None and value.shape != self.shape:
            raise TypeError(f"port {self.name!r} needs shape {self.shape}, got {value.shape}")
        if self.dtype is not None and value.dtype != self.dtype:
            raise TypeError(f"port {self.name!r} needs dtype {self.dtype}, got {value.dtype}")


class Input(_Port):
    """An input port: ``Input(float)``, ``Input(np.ndarray, shape=(16,), dtype="float32")``.

    ``policy`` is ``"latest"`` (default) or ``"queue:N"``; a link may override it.
    """

    def __init__(self, type_: type = object, *, shape: tuple[int, ...] | None = None,
                 dtype: str | np.dtype | None = None, policy: str = "latest") -> None:
        super().__init__(type_, shape=shape, dtype=dtype)
        self.policy = Policy.parse(policy)

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


class InputPort:
    """An input bound to one module instance: holds received values by its policy.

    ``deliver`` may be called from any thread; ``read`` from the module's own calls.
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
        self.rate = 0.0              # smoothed values per second
        self._values: collections.deque[Any] = collections.deque()
        self._latest: Any = _MISSING
        self._fresh = False
        self._undispatched = 0
        self._last_arrival = math.nan
        self._window_start = -math.inf
        self._window_count = 0
        self._lock = threading.Lock()
        self._notify: Callable[[InputPort], None] | None = None

    # -- the module's side -------------------------------------------------
    @property
    def has_value(self) -> bool:
        """True when ``read()`` would return a value."""
        if self.policy.kind == "queue":
            return bool(self._values)
        return self._latest is not _MISSING

    @property
    def pending(self) -> int:
        """Values not yet read: the queue length, or 1 if the latest value is unread."""
        if self.policy.kind == "queue":
            return len(self._values)
        return 1 if self._fresh else 0

    def read(self, default: Any = _MISSING) -> Any:
        """The newest value (``latest``) or the next one in order (``queue``).

        Without a value, returns ``default`` if given, else raises LookupError.
        """
        self._lock.acquire()
        try:
            if self.policy.kind == "queue":
                if self._values:
                    return self._values.popleft()
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
        """Every value pending, oldest first (``queue``), or ``[latest]`` if unread."""
        with self._lock:
            if self.policy.kind == "queue":
                values = list(self._values)
                self._values.clear()
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
        """Accept values in link order; ``sent_at`` is when the newest was written."""
        count = len(values)
        now = time.monotonic()
        self._lock.acquire()
        try:
            self.received += count
            if sent_at is not None:
                lat = now - sent_at if now > sent_at else 0.0
                old = self.latency
                self.latency = lat if old != old else old + 0.1 * (lat - old)  # NaN: the first
            # rate: values counted over windows of at least _RATE_WINDOW seconds; the
            # first arrival only opens the first window (it started at -inf: rate 0)
            self._window_count += count
            self._last_arrival = now
            if now - self._window_start >= _RATE_WINDOW:
                self.rate = self._window_count / (now - self._window_start)
                self._window_start, self._window_count = now, 0
            if self.policy.kind == "queue":
                held = self._values
                held.extend(values)
                overflow = len(held) - self.policy.size
                if overflow > 0:
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

    def take_events(self, most: int) -> int:
        """Claim up to ``most`` ``on_input`` calls for this port; returns how many."""
        self._lock.acquire()
        claimed = most if most < self._undispatched else self._undispatched
        self._undispatched -= claimed
        self._lock.release()
        return claimed

    @property
    def owes_calls(self) -> bool:
        """True while values are waiting for their ``on_input`` call."""
        return self._undispatched > 0

    def take_event(self) -> bool:
        """Claim one ``on_input`` call for this port; False if nothing is left to dispatch."""
        return self.take_events(1) == 1

    def current_rate(self) -> float:
        """Values per second over the last window; decays once values stop arriving."""
        if math.isnan(self._last_arrival):
            return 0.0
        now = time.monotonic()
        if self.rate == 0.0 and now - self._window_start > 0:
            return self._window_count / (now - self._window_start) if self._window_count else 0.0
        idle = now - self._last_arrival
        return min(self.rate, 1.0 / idle) if idle > _RATE_WINDOW else self.rate

    def set_policy(self, policy: Policy) -> None:
        """Change the policy (a link may override the declared one); held values carry over."""
        with self._lock:
            if policy.kind == self.policy.kind:
                while len(self._values) > policy.size:
                    self._values.popleft()
                    self.drops += 1
            elif policy.kind == "latest":              # queue -> latest: keep the newest
                if self._values:
                    self._latest, self._fresh = self._values[-1], True
                self._values.clear()
            elif self._fresh:                           # latest -> queue: the unread value
                self._values.append(self._latest)
            self._undispatched = min(self._undispatched, self._pending_for(policy))
            self.policy = policy

    def export(self) -> dict[str, Any]:
        """Unconsumed values and counters, for a migration (see ``restore``)."""
        with self._lock:
            return {"values": list(self._values), "fresh": self._fresh,
                    "latest": None if self._latest is _MISSING else (self._latest,),
                    "undispatched": self._undispatched, "received": self.received,
                    "drops": self.drops, "link_failures": self.link_failures}

    def restore(self, held: dict[str, Any]) -> None:
        """Take over an exported port: its values come before anything delivered later."""
        with self._lock:
            self._values.extend(held["values"])
            if held["latest"] is not None:
                self._latest, self._fresh = held["latest"][0], held["fresh"]
            self._undispatched = min(held["undispatched"], self._pending_for(self.policy))
            self.received += held["received"]
            self.drops += held["drops"]
            self.link_failures += held["link_failures"]
            owed = self._undispatched > 0
        if owed and self._notify is not None:
            self._notify(self)

    def _pending_for(self, policy: Policy) -> int:
        return len(self._values) if policy.kind == "queue" else int(self._fresh)


class OutputPort:
    """An output bound to one module instance. ``write`` checks the type, then fans out.

    Each link is a pair of sinks: ``one(value)`` for ``write`` and ``many(values)``
    for ``write_many``, which saves the per-value cost of the transport.
    """

    def __init__(self, spec: Output, owner: str = "") -> None:
        self.spec = spec
        self.name = spec.name
        self.owner = owner
        self.written = 0
        self._sinks: dict[str, tuple[Callable[[Any], Any], Callable[[Sequence[Any]], Any]]] = {}
        self._ones: tuple[Callable[[Any], Any], ...] = ()     # the write() path, prebuilt
        self._lock = threading.Lock()

    def write(self, value: Any) -> None:
        """Send ``value`` on every link; TypeError (and nothing sent) if it does not fit."""
        if type(value) is not self.spec.plain_type:
            self.spec.check(value)
        self._lock.acquire()            # (not ``with``: half the cost, paid per value)
        try:
            self.written += 1
            for one in self._ones:
                one(value)
        finally:
            self._lock.release()

    def write_many(self, values: Iterable[Any]) -> None:
        """Send values in order, as repeated ``write`` would, but faster; all are checked first."""
        batch = list(values)
        check = self.spec.check
        for value in batch:
            check(value)
        if not batch:
            return
        with self._lock:
            self.written += len(batch)
            for _, many in self._sinks.values():
                many(batch)

    def connect(self, key: str, one: Callable[[Any], Any],
                many: Callable[[Sequence[Any]], Any] | None = None) -> None:
        """Add a link: ``one(value)`` / ``many(values)`` are called in write order."""
        if many is None:
            def many(values: Sequence[Any]) -> None:
                for value in values:
                    one(value)
        with self._lock:
            self._sinks[key] = (one, many)
            self._ones = tuple(pair[0] for pair in self._sinks.values())

    def disconnect(self, key: str) -> bool:
        """Remove a link; False if there was none. No write is in progress on return."""
        with self._lock:
            found = self._sinks.pop(key, None) is not None
            self._ones = tuple(pair[0] for pair in self._sinks.values())
            return found

    @property
    def links(self) -> list[str]:
        """Keys of the links this output feeds."""
        return list(self._sinks)
