"""``Node``: what the launcher may ask of a node, wherever its executor runs.

One declared interface, two implementations: ``Executor`` (an embedded node, in
the launcher's process) and ``RemoteNode`` (the executor process a node controller
started on this machine or another, each operation one authenticated request).
The launcher only ever talks to a ``Node``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

if TYPE_CHECKING:
    from pb3a.config.plan import FlatLink, FlatModule
    from pb3a.node.ring_sizes import RingSize
    from pb3a.stats import NodeReport
    from pb3a.transport.snapshot import Snapshot

Endpoint = tuple[str, str, bytes]   # a published output: data address, control address, sender
# where a link's sender stopped: the sequence number it reached, and which sender (its
# incarnation; None if none published it: its worker is gone)
Reached = tuple[int, bytes | None]


@runtime_checkable
class Node(Protocol):
    """The operations of one node's supervisor; each has a deadline of its own, and
    keeps the deadline of the call in progress if that comes first (``pb3a.deadline``:
    a move bounded by its caller's timeout)."""

    # -- modules
    def expect(self, specs: list[FlatModule]) -> None:
        """Size packed workers for the modules about to be added, in their order."""

    def spawn_workers(self, specs: list[FlatModule]) -> None:
        """Start the processes of the modules about to be added that get a worker of
        their own, so that they boot side by side rather than one per ``add_module``."""

    def release_workers(self, specs: list[FlatModule]) -> None:
        """Stop the workers ``spawn_workers`` started for ``specs`` that host nothing:
        what was spawned for modules that are not coming after all."""

    def add_module(self, spec: FlatModule, *,
                   state: dict[str, Any] | bytes | None = None) -> None:
        """Instantiate a module in its worker (not started); ``state`` overrides the spec's
        (as bytes: the module's own, a checkpoint say, unpickled in the worker, where the
        module's code is, and restored in full: ``restore_state``)."""

    def start_modules(self, names: list[str], failing: bool = False,
                      leave_late: bool = False) -> None:
        """Run ``setup`` and start the modules, in order; ``RuntimeFailure`` naming those
        that did not start (its ``failed``), failed here too with ``failing``. With
        ``leave_late``, those whose ``setup`` outlasts the deadline of the call in
        progress (``pb3a.deadline``) are left to finish, not halted: ``RuntimeTimeout``
        naming them (its ``late``)."""

    def call_module(self, name: str, op: str, timeout: float, /, **args: Any) -> Any:
        """One request about module ``name`` to its worker (state, set_state, ...)."""

    def await_restart(self, name: str, timeout: float) -> bool:
        """Wait up to ``timeout``, without the node's lock, while module ``name``'s
        worker is dead and its restart is to come or under way; whether it waited."""

    def swap(self, name: str, spec: FlatModule) -> tuple[list[str], list[str]]:
        """Replace a module's class in place; the state names kept, and those dropped."""

    def retime(self, name: str, period: float, timeout: float) -> None:
        """Step the module every ``period`` seconds from now on, and after its restarts."""

    def learn_period(self, name: str, timeout: float) -> float | None:
        """The period the module steps at now, read where it runs, which its record
        takes as given (a restart keeps it) if the module set it itself; nothing is set
        where it runs."""

    def pause(self, name: str, timeout: float, rewire: bool = False) -> bool:
        """Hold the module's lock until ``resume``; False if it does not run here. A
        worker of it that dies meanwhile is restarted once it is let go of (resumed,
        retired, stopped or removed), not before. With ``rewire`` (only its links
        change, not the module), a body waiting in a runtime call is held where it
        waits rather than cancelled."""

    def resume(self, name: str) -> None:
        """Release a paused module."""

    def stop_module(self, name: str, timeout: float) -> None:
        """Stop stepping and dispatching, then run ``teardown``."""

    def kill_module(self, name: str) -> int:
        """SIGKILL the worker of a module that did not answer its stop (a ``remove`` with
        ``force``), no restart following; the module is then stopped, to be removed. The
        worker's process id; ``RuntimeFailure`` naming them if it runs other modules."""

    def remove_module(self, name: str) -> None:
        """Drop a stopped module whose links are gone; one whose worker does not answer
        in time is dropped all the same (the worker, left empty, stopped), and it raises."""

    def fail_module(self, name: str, reason: str) -> None:
        """Module ``name``, not started, will not run: failed for ``reason`` (a
        ``module_failed`` event), what feeds it unhooked; one whose worker died is left
        to its restart policy."""

    def memory_domain(self) -> str:
        """Where the node's shared-memory segments can be seen: nodes of one domain hand
        each other a migrating module's snapshot by name."""

    def reserve(self, name: str, timeout: float) -> str:
        """Before a migration pauses module ``name``: a segment the size of its snapshot
        (measured without waiting for a call in progress; the answer waited for up to
        ``timeout``)."""

    def retire(self, name: str, segment: str, carry: bool) -> Snapshot:
        """The migration fence: capture a paused module's state and inputs into the
        reserved ``segment`` (with ``carry``, into the snapshot itself, for another
        domain), drop the module here."""

    def land(self, name: str, snapshot: Snapshot) -> float:
        """Restore what ``retire`` captured into an instantiated, unstarted module; the
        seconds its worker took."""

    def read_snapshot(self, segment: str, offset: int, size: int) -> bytes:
        """``size`` bytes from ``offset`` of a snapshot ``retire`` captured here: a piece
        of what a remote node carries to another domain, each within one control
        message (a 66 MiB state in one answer broke the connection)."""

    def write_snapshot(self, segment: str, size: int, offset: int, data: bytes) -> str:
        """Write a piece of a snapshot coming from another domain at ``offset`` of
        ``segment``, a new segment of ``size`` bytes made here if ``segment`` is "";
        the segment's name (``land`` a ``staged`` snapshot of it, which unlinks it)."""

    def release(self, segment: str) -> None:
        """After a migration from this node: unlink its segment, stop any worker left empty."""

    def forget(self, module: str) -> None:
        """Drop cached copies of Python module ``module`` here and in every worker."""

    # -- links with both ends on this node
    def connect(self, links: list[FlatLink]) -> None:
        """Wire links: in memory inside a worker, else through a new ring; in one
        request however many they are."""

    def detach(self, links: list[FlatLink]) -> None:
        """Unwire links: the writers stop, then the readers take in what is on the way;
        in one request however many they are."""

    # -- remote links, one half on each node; each call takes any number of links
    def ready_to_publish(self, name: str) -> None:
        """Bind module ``name``'s publishing sockets now, not when a link first needs them."""

    def publish(self, links: list[FlatLink]) -> list[Endpoint]:
        """The writing half: publish each link's output; the endpoints to follow."""

    def unpublish(self, links: list[FlatLink]) -> list[Reached]:
        """Stop publishing for each link; the sequence number its sender reached, and
        that sender's incarnation."""

    def unacknowledged(self, link: FlatLink, reader: bytes) -> int:
        """How many values of ``link``'s output the follower ``reader`` (``follower_id``
        of the reader's node, lost) has not acknowledged: what it never confirmed. The
        writer forgets that follower: it holds nothing back from then on."""

    def open_inbound(self, links: list[tuple[FlatLink, RingSize | None]]) -> None:
        """The reading half: a ring of the size given (None: the one kept) into each
        link's reader, which the bridge fills."""

    def follow(self, links: list[tuple[FlatLink, Endpoint]]) -> None:
        """Receive each link's output from the sender at its endpoint."""

    def close_inbound(self, links: list[tuple[FlatLink, Reached]]) -> list[int]:
        """Stop receiving each link once the values before the sequence number given are
        in, if they come from the sender followed (one the reader does not follow, a
        writer restarted since, sends it nothing); per link, how many values its sender
        announced that never came (its node was lost)."""

    # -- figures and the end
    def report(self, timeout: float) -> NodeReport:
        """This node's figures; a worker that has not answered within ``timeout`` is
        reported silent."""

    def worker_pids(self) -> list[int]:
        """The process ids of the node's running workers (its env module's own load)."""

    def shutdown(self, timeout: float) -> None:
        """Stop every module (reverse start order), every worker, free every segment."""


# What a launcher may ask of a node executor process over the wire, one at a time (its
# shutdown goes through the node controller, which owns the process; its start, and a
# wait for a restart, which takes the lock, are requests of their own, taken beside these).
REMOTE_OPERATIONS = frozenset(
    name for name, member in vars(Node).items()
    if callable(member) and not name.startswith("_")) - {"shutdown", "start_modules",
                                                         "await_restart", "report"}
