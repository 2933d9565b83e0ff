"""``Wiring``: the links of one node, and the rings that carry them.

A link with both ends here runs in memory inside a worker, or through a ring this node
creates (``connect``). A remote link is wired in halves by the ``Launcher``, which
alone sees every node: ``publish`` at the writer's node, ``open_inbound`` and
``follow`` at the reader's, whose bridge feeds the ring. Every change asks the
workers side by side; a worker that restarts is wired again from these tables
(``rewire``).
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any, Protocol

from pb3a.deadline import left
from pb3a.errors import RuntimeFailure, RuntimeTimeout
from pb3a.node.bridge import READY_TIMEOUT
from pb3a.node.ring_sizes import RingSize, ring_size
from pb3a.node.workers import WorkerRequest
from pb3a.transport.ring import ShmRing
from pb3a.transport.shm import RING, segment_name, unlink_name

if TYPE_CHECKING:
    from collections.abc import Callable

    from pb3a.config.plan import FlatLink
    from pb3a.node.bridge import Bridge
    from pb3a.node.module_record import ModuleRecord
    from pb3a.node.protocol import Endpoint, Reached
    from pb3a.node.workers import WorkerPool

log = logging.getLogger("pb3a.executor")


class WiringHost(Protocol):
    """What the wiring works through: the node's ``Executor``."""

    modules: dict[str, ModuleRecord]
    workers: WorkerPool
    # told (link, endpoint) when a restarted writer publishes anew
    republished: Callable[[FlatLink, Endpoint], None] | None

    @property
    def bridge(self) -> Bridge: ...
    def alive(self, key: str) -> bool: ...
    def restarting(self, record: ModuleRecord) -> bool: ...
    def publishing(self) -> dict[str, Any]: ...
    def call(self, worker: str, op: str, timeout: float = ..., /, **args: Any) -> Any: ...


class Wiring:
    """The links of one executor's node: those with both ends here (``local``), the
    remote ones read here (``inbound``) and written here (``outbound``), and the rings
    of the first two, by link key. Called under the node's lock."""

    def __init__(self, node: WiringHost) -> None:
        self._node = node
        self.local: dict[str, FlatLink] = {}
        self.inbound: dict[str, FlatLink] = {}
        self.outbound: dict[str, FlatLink] = {}
        self.rings: dict[str, ShmRing] = {}

    # -- links with both ends here ---------------------------------------------
    def connect(self, links: list[FlatLink]) -> None:
        """Wire links: in memory inside a worker, else through a new ring. Every
        reader is attached before any writer, and the workers are asked side by side:
        a macro's links are wired at once, not one worker request after another."""
        for link in links:
            self.local[link.key] = link
        side_by_side = self._node.workers.side_by_side
        side_by_side([self._reader_request(link) for link in links])
        side_by_side([self._writer_request(link) for link in links])

    def detach(self, links: list[FlatLink]) -> None:
        """Unwire links: every writer stops first, then every reader takes in everything
        still on the way, so a new wiring cannot overtake it (the workers asked side by
        side, as in ``connect``)."""
        for link in links:
            self.local.pop(link.key, None)
        side_by_side = self._node.workers.side_by_side
        side_by_side([self._unlink_request(link, link.src, "unlink_out") for link in links])
        side_by_side([self._unlink_request(link, link.dst, "unlink_in") for link in links])
        for link in links:
            self._close_ring(link)

    def _reader_request(self, link: FlatLink) -> WorkerRequest | None:
        """The reading side: attach the link's ring (created here) in the reader's worker
        (none for a link inside one worker)."""
        modules = self._node.modules
        src, dst = modules[link.src], modules[link.dst]
        if src.worker == dst.worker:
            return None
        ring = self._ring(link.key, ring_size(src.spec.cls, link.src_port, link.policy))
        if self._node.restarting(dst) or self._failed(dst):
            return None
        return WorkerRequest(dst.worker, "link_in", {
            "key": link.key, "dst": link.dst, "dst_port": link.dst_port, "ring": ring.name,
            "policy": str(link.policy)})

    def _writer_request(self, link: FlatLink) -> WorkerRequest | None:
        """The writing side: connect the output to the ring, or straight to the input."""
        modules = self._node.modules
        src, dst = modules[link.src], modules[link.dst]
        if self._node.restarting(src) or self._failed(dst):
            return None                 # (into a failed reader: unhooked, see ``unhook``)
        if src.worker == dst.worker:
            return WorkerRequest(src.worker, "link_out", {
                "key": link.key, "src": link.src, "src_port": link.src_port, "dst": link.dst,
                "dst_port": link.dst_port, "policy": str(link.policy)})
        return WorkerRequest(src.worker, "link_out", {
            "key": link.key, "src": link.src, "src_port": link.src_port,
            "ring": self.rings[link.key].name}, fd=self._node.workers[dst.worker].bell)

    def _failed(self, record: ModuleRecord) -> bool:
        """Whether the module has failed for good, its worker gone (until it is restarted
        or removed): a link into it is not wired, as ``unhook`` leaves it; its restart
        wires it anew. (Wiring it asked the dead worker: a move of a writer whose reader
        had failed was refused, wherever it went.)"""
        return record.status == "failed" and not self._node.alive(record.worker)

    def _unlink_request(self, link: FlatLink, module: str, op: str) -> WorkerRequest | None:
        """``op`` for ``link`` to the worker of one of its ends (none if it is gone)."""
        record = self._node.modules.get(module)
        if record is None or not self._node.alive(record.worker):
            return None
        return WorkerRequest(record.worker, op, {"key": link.key})

    def _ring(self, key: str, size: RingSize | None) -> ShmRing:
        ring = self.rings.get(key)
        if ring is None:
            if size is None:
                raise RuntimeError(f"link {key} has no ring to reopen")
            name = segment_name(RING)
            try:
                ring = ShmRing.create(name, *size)
            except FileExistsError:
                raise                   # (not ours to unlink)
            except BaseException:       # a Ctrl-C even as it returns: nobody knows of it
                unlink_name(name)
                raise
            self.rings[key] = ring      # (from here ``close`` frees it)
        return ring

    def _close_ring(self, link: FlatLink) -> None:
        ring = self.rings.pop(link.key, None)
        if ring is not None:
            ring.close()

    # -- remote links, one half each ---------------------------------------------------
    def ready_to_publish(self, name: str) -> None:
        """Have module ``name``'s worker ready to publish to other nodes (its sockets
        bound), before a migration that will need it pauses anything."""
        self._node.call(self._node.modules[name].worker, "ready_to_publish",
                        **self._node.publishing())

    def publish(self, links: list[FlatLink]) -> list[Endpoint]:
        """The writing half: publish each link's output (once per output, whoever reads
        it), the workers asked side by side; the endpoints (data address, control
        address, sender incarnation); None for a writer whose worker restarts (it
        publishes anew then: ``republished``)."""
        modules = self._node.modules
        for link in links:
            self.outbound[link.key] = link
        answers = self._node.workers.side_by_side([
            None if self._node.restarting(modules[link.src]) else WorkerRequest(
                modules[link.src].worker, "publish_out",
                {"key": link.key, "src": link.src, "src_port": link.src_port,
                 # the reader's ring, which the writer checks each value against
                 "room": ring_size(modules[link.src].spec.cls, link.src_port, link.policy),
                 **self._node.publishing()}) for link in links])
        return [None if answer is None else tuple(answer) for answer in answers]

    def unpublish(self, links: list[FlatLink]) -> list[Reached]:
        """Stop publishing for each link; the sequence number its sender reached and the
        sender's incarnation ((0, None) if its worker is gone)."""
        for link in links:
            self.outbound.pop(link.key, None)
        answers = self._node.workers.side_by_side(
            [self._unlink_request(link, link.src, "unpublish_out") for link in links])
        return [answer or (0, None) for answer in answers]

    def unacknowledged(self, link: FlatLink, reader: bytes) -> int:
        """How many values of ``link``'s output the follower ``reader`` of a lost node has
        not acknowledged; the writer forgets it (``Replicator.forget``)."""
        src = self._node.modules.get(link.src)
        if link.key not in self.outbound or src is None or not self._node.alive(src.worker):
            return 0
        return self._node.call(src.worker, "unacknowledged_out", key=link.key, reader=reader)

    def open_inbound(self, links: list[tuple[FlatLink, RingSize | None]]) -> None:
        """The reading halves: each link's ring (of ``size``; None: the link's ring
        exists already) attached in its reader's worker, the workers asked side by side,
        then fed by the bridge."""
        modules = self._node.modules
        rings = {}
        for link, size in links:
            self.inbound[link.key] = link
            rings[link.key] = self._ring(link.key, size)
        fed = [link for link, _ in links if not self._failed(modules[link.dst])]
        self._node.workers.side_by_side([
            None if self._node.restarting(modules[link.dst]) else WorkerRequest(
                modules[link.dst].worker, "link_in", {
                    "key": link.key, "dst": link.dst, "dst_port": link.dst_port,
                    "ring": rings[link.key].name, "policy": str(link.policy)})
            for link in fed])
        for link in fed:
            self._node.bridge.open(link.key, topic(link), rings[link.key].name,
                                   self._node.workers[modules[link.dst].worker].bell)

    def follow(self, links: list[tuple[FlatLink, Endpoint]]) -> None:
        """Receive each link's output from the sender at its endpoint (see ``publish``)."""
        modules = self._node.modules
        self._node.bridge.follow([(topic(link), *endpoint) for link, endpoint in links
                                  if not self._failed(modules[link.dst])])

    def close_inbound(self, links: list[tuple[FlatLink, Reached]]) -> list[int]:
        """Stop receiving each link once the values before the sequence number given
        are in (all within one ``READY_TIMEOUT``, or what is left of the call in
        progress, however long: a move's), if they come from the sender the bridge
        follows (see ``Bridge.close``), then detach their rings from the readers side by
        side; per link, how many values its sender announced that never came."""
        # (a lossless link's backlog may take longer than 10 s to come in: a move given
        # 25 s failed after 10, saying its values were still in flight)
        remaining = left()
        deadline = time.monotonic() + (READY_TIMEOUT if remaining is None else remaining)
        missing = []
        for link, (reached, sender) in links:
            self.inbound.pop(link.key, None)
            missing.append(self._node.bridge.close(
                link.key, reached, max(0.0, deadline - time.monotonic()), sender))
        self._node.workers.side_by_side(
            [self._unlink_request(link, link.dst, "unlink_in") for link, _ in links])
        for link, _ in links:
            self._close_ring(link)
        return missing

    # -- what a restart, a failed module and a shutdown need ---------------------------
    def rewire(self, revived: set[str]) -> None:
        """Attach every link of restarted modules again, in the worker that replaced theirs."""
        modules = self._node.modules
        links = list(self.local.values())
        side_by_side = self._node.workers.side_by_side
        side_by_side([self._reader_request(link) for link in links
                      if link.dst in revived and modules[link.src].status != "failed"])
        side_by_side([self._writer_request(link) for link in links
                      if link.src in revived and modules[link.dst].status != "failed"])
        # (a remote link's ring is kept: no size needed)
        self.open_inbound([(link, None) for link in self.inbound.values()
                           if link.dst in revived])
        republishing = [link for link in self.outbound.values() if link.src in revived]
        republished = self._node.republished
        for link, endpoint in zip(republishing, self.publish(republishing), strict=True):
            if republished is not None and endpoint is not None:
                republished(link, endpoint)

    def unhook(self, name: str) -> None:
        """Module ``name`` failed: writers into a dead reader would only fill its ring,
        so they are unhooked, and its remote links are no longer received."""
        modules = self._node.modules
        for link in list(self.local.values()):
            src = modules.get(link.src)
            if link.dst == name and src is not None and self._node.alive(src.worker):
                try:
                    self._node.call(src.worker, "unlink_out", key=link.key)
                except (RuntimeFailure, RuntimeTimeout) as exc:     # (its writer goes on)
                    log.warning("link %s: its writer was not unhooked: %s", link.key, exc)
        for link in list(self.inbound.values()):
            if link.dst == name:
                self._node.bridge.close(link.key)

    def inbound_losses(self) -> tuple[dict[str, int], dict[str, int]]:
        """Per remote link read here: the link failures and the drops its bridge counted."""
        if not self.inbound:
            return {}, {}           # (the bridge is made on first use: not for a report)
        bridge = self._node.bridge
        inbound = list(self.inbound.items())    # (a report runs beside the changes)
        lost = {key: bridge.link_failures(topic(link)) for key, link in inbound}
        drops = {key: bridge.drops(topic(link)) for key, link in inbound}
        return lost, drops

    def close(self) -> None:
        """Free every ring (the node is shutting down, its workers gone)."""
        for ring in list(self.rings.values()):
            ring.close()
        self.rings.clear()


def topic(link: FlatLink) -> str:
    """The topic a remote link's output is published under."""
    return f"{link.src}.{link.src_port}"


