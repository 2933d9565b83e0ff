"""The figures of a running system, as typed records: what ``Running.stats()`` returns.

Each record is a frozen dataclass (Trio's ``statistics()`` style): attributes with
types and docs instead of nested dicts keyed by strings. ``SystemStats.to_json()``
gives the same figures as plain JSON types, for scripts and ``--json`` output (NaN,
which JSON cannot carry, becomes ``null``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

FAILURES_KEPT = 100             # lines of stats().failures a launcher or node keeps


class FailureLog:
    """What went wrong in a launcher or on a node, for ``stats().failures``: the newest
    ``FAILURES_KEPT`` lines, each dated, so a long-running system's list does not grow
    without end and a line says when, not only what (it outlives a node's rejoining)."""

    def __init__(self, log: logging.Logger) -> None:
        self._lines: deque[str] = deque(maxlen=FAILURES_KEPT)
        self._log = log

    def add(self, text: str) -> str:
        """Keep ``text``, prefixed with the local date and time, and log it as an
        error; ``text`` back, undated."""
        self._lines.append(f"{time.strftime('%Y-%m-%d %H:%M:%S')} {text}")
        self._log.error(text, stacklevel=2)     # (the record names the caller's line)
        return text

    def lines(self) -> list[str]:
        """The lines kept, oldest first."""
        return list(self._lines)


@dataclass(frozen=True)
class InputStats:
    """One input port's counters."""

    policy: str                 # "latest", "queue:N" or "lossless:N"
    received: int = 0           # values delivered to the port
    drops: int = 0              # values lost to queue overflow (or on the link)
    pending: int = 0            # values not read yet
    latency: float = math.nan   # smoothed seconds from write to delivery
    rate: float = 0.0           # values per second, recently
    link_failures: int = 0      # values lost because a link or its peer failed
    # values delivered, per latency bucket (``pb3a.latencies``; only the buckets used)
    latency_counts: dict[int, int] = field(default_factory=dict)


@dataclass(frozen=True)
class WaitStats:
    """Writes that waited for room: a full ring or input (on a lossless link, the writer
    waits until the reader takes a value; on a dropping one, briefly)."""

    waits: int = 0              # writes that waited (or wait now)
    wait_s: float = 0.0         # seconds spent waiting, in all


@dataclass(frozen=True)
class ModuleStats:
    """One module: where it runs, how it is doing, what it did."""

    cls: str                    # "package.module:Class"
    node: str
    worker: str                 # the worker process's key
    status: str                 # starting | running | failed | stopped
    pid: int | None = None      # the worker process (None while it has none)
    running: bool = False       # stepping or dispatching now
    silent: bool = False        # its worker or its node did not answer within the
                                # report's deadline (frozen, starved, stuck, cut off): the
                                # figures are its node's last report's (none if its
                                # worker alone is silent), not now's
    calling: str = ""           # the body or hook it is in now ("step", "on_input", ...)
    calling_s: float = 0.0      # for how long: a stuck call shows here
    # the change in progress that acts on it ("migrate slow to b": its node is where
    # the launcher has it now; "restart the modules of worker b/w-3": its node's own
    # restart of a worker that died), and for how long ("" and 0: none)
    change: str = ""
    change_s: float = 0.0
    restarts: int = 0           # times its worker was restarted under it
    checkpoints: int = 0        # checkpoints taken (restart = "last-state")
    steps: int = 0
    events: int = 0             # on_input calls
    errors: int = 0             # exceptions raised by its bodies
    last_error: str = ""
    # when it was raised (wall clock, seconds since the epoch: a module's node may be
    # another machine), so that an error long past is told from one raised just now
    last_error_at: float | None = None
    cpu: float = 0.0            # CPU seconds (its whole worker's when it runs alone)
    inputs: dict[str, InputStats] = field(default_factory=dict)
    outputs: dict[str, int] = field(default_factory=dict)    # values written, per output
    output_waits: dict[str, WaitStats] = field(default_factory=dict)   # per output
    link_waits: dict[str, WaitStats] = field(default_factory=dict)     # per link it writes
    # the period it steps at, seconds (None: only on events, its class's period too if
    # it has no step()), as set live too (by set_state, or the module assigning
    # self.period)
    period: float | None = None
    fixed_rate: bool = False    # its steps due a period after the last one began
    # (with fixed_rate) the periods it skipped: each step that began a whole period or
    # more after it was due adds the whole periods it was late by (``pb3a.worker.rate``);
    # a pause of the runtime's (a move, a swap) counts none
    overruns: int = 0


@dataclass(frozen=True)
class LinkStats:
    """One link, as its reader sees it (``waits`` and ``wait_s``: as its writer does)."""

    src: str                    # "module.port"
    dst: str
    policy: str
    transport: str              # memory (one process) | shm (one node) | zmq (two nodes)
    values: int = 0
    drops: int = 0
    pending: int = 0
    latency: float = math.nan
    rate: float = 0.0
    link_failures: int = 0
    ring_bytes_used: int = 0
    latency_p50: float = math.nan   # seconds, over every value delivered (to a bucket's 9 %)
    latency_p90: float = math.nan
    latency_p99: float = math.nan
    latency_counts: dict[int, int] = field(default_factory=dict)   # as in InputStats
    waits: int = 0              # writes that waited (or wait now) for room on this link
    wait_s: float = 0.0         # seconds they waited
    # its reader is silent (``ModuleStats.silent``: its worker or its node did not
    # answer): values, pending, rate and latency are not known now, shown as its
    # reader's node last reported them (0 and NaN if its worker alone is silent)
    silent: bool = False


@dataclass(frozen=True)
class NodeStats:
    """One node's health as the launcher's heartbeats see it."""

    up: bool
    rtt: float                  # seconds; 0 for embedded nodes, NaN before the first beat
    #                             and while lost (none measured: it showed the last one)
    address: str | None         # None: embedded in the launcher's process
    controller: bool | None = None   # its node controller answers (remote nodes)
    epoch: int = 1              # its admission: one more each time it rejoins after a loss
    silent_s: float = 0.0       # since its executor last answered a heartbeat (remote
    #                             nodes, lost ones too: it said 0.0 for those)
    # the node's resources as its executor last measured them (None: not asked, or lost)
    cpu: float | None = None                # percent busy of its CPUs (its pinned ones)
    memory_available: int | None = None     # bytes
    memory_total: int | None = None         # bytes
    spare_workers: int | None = None        # booted idle workers (its ``spares`` setting)
    # why its controller refuses the launcher (another cluster key, clocks apart), which
    # keeps a lost node from rejoining; "" if it does not
    refused: str = ""


@dataclass(frozen=True)
class NodeResources:
    """A node's machine as its executor measures it: CPU since the last look, memory."""

    cpu: float                  # percent busy of the node's CPUs (its pinned ones), 0-100
    memory_available: int       # bytes
    memory_total: int           # bytes


@dataclass(frozen=True)
class NodeReport:
    """What one node tells the launcher: its modules, rings and remote-link losses."""

    modules: dict[str, ModuleStats]
    ring_bytes_used: dict[str, int]     # link key -> bytes in its ring
    link_failures: dict[str, int]       # link key -> values lost for good on the way in
    failures: list[str]
    resources: NodeResources | None = None   # the machine's CPU and memory
    spare_workers: int = 0              # booted idle workers, for modules that arrive
    link_drops: dict[str, int] = field(default_factory=dict)   # link key -> values its
                                        # sender did not send, the link slower than its writer


@dataclass(frozen=True)
class SystemStats:
    """A whole system: every module, link and node, and what went wrong."""

    system: str
    modules: dict[str, ModuleStats]
    links: dict[str, LinkStats]         # keyed "src.port->dst.port"
    nodes: dict[str, NodeStats]
    failures: list[str]                 # the newest of the launcher's and every node's,
                                        # dated ("YYYY-MM-DD HH:MM:SS what"), oldest first

    def to_json(self) -> dict[str, Any]:
        """The figures as JSON types (NaN as None)."""
        return plain(dataclasses.asdict(self))


def plain(value: Any, finite: bool = True, arrays: bool = True) -> Any:
    """``value`` in JSON's terms: NaN and the infinities as None (as JavaScript writes
    them: JSON has no such numbers; kept with ``finite=False``, for people to read),
    tuples as lists, keys as strings, numpy's numbers as Python's and its arrays as
    lists (kept with ``arrays=False``, for people to read as numpy abbreviates them).
    A module's state is mostly numpy: its arrays came out as their abbreviated repr,
    a string, and ``np.int64(7)`` as that text."""
    numpy = hasattr(value, "dtype") and hasattr(value, "tolist")    # (not imported)
    if numpy and (arrays or getattr(value, "ndim", 0) == 0):
        value = value.tolist()
    if finite and isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {str(key): plain(item, finite, arrays) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(item, finite, arrays) for item in value]
    return value
