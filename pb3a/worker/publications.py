"""``Publications``: the outputs a worker process replicates to other nodes.

One ``Replicator`` per worker, created when the first remote link appears. Each
output is published under one topic (``"module.port"``) however many remote
links read it: the output gets one sink, and a topic stays until its last link goes.
The sink takes the writer's timeout: a lossless reader on another node holds the
writer back up to it (the publish then fails, naming the links of the topic).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pb3a.errors import link_stuck
from pb3a.transport.auth import ClusterKey
from pb3a.transport.replication import SILENT_S, Replicator

if TYPE_CHECKING:
    from pb3a.model.ports import OutputPort
    from pb3a.transport.ring import RingSize


# removed links whose last position a worker remembers (an undo asks within its move)
REMEMBERED = 1024


class Publications:
    """Remote links out of one worker process."""

    def __init__(self) -> None:
        self.replicator: Replicator | None = None
        self._readers: dict[str, set[str]] = {}      # topic -> keys of the links reading it
        self._ports: dict[str, OutputPort] = {}
        # link key -> where its topic was when the link stopped being published here (the
        # newest REMEMBERED: an agent that links and unlinks ever new modules grew it)
        self._removed: dict[str, tuple[int, bytes]] = {}

    def open(self, secret: bytes, host: str, epoch: int = 0) -> Replicator:
        """The worker's replicator, made (its sockets bound) if it is not yet: ahead of
        time, it keeps milliseconds out of a migration's pause."""
        if self.replicator is None:
            self.replicator = Replicator(ClusterKey(secret), host, epoch=epoch)
        return self.replicator

    def add(self, key: str, topic: str, port: OutputPort, secret: bytes, host: str,
            epoch: int = 0, room: RingSize | None = None) -> tuple[str, str, bytes]:
        """Publish ``port`` for the link ``key``; the addresses and incarnation to follow.
        Messages carry the system's ``epoch``; older ones are refused as stale. ``room``:
        the ring the link's reader takes values into (a value it cannot take is refused
        as it is written)."""
        replicator = self.open(secret, host, epoch)
        readers = self._readers.setdefault(topic, set())
        if not readers:
            replicator.add(topic, room=room)
            offer = replicator.offer
            one = replicator.sink(topic, lambda timeout: link_stuck(", ".join(sorted(readers)),
                                                                    timeout))

            def many(values: Any, timeout: float) -> None:
                went = offer(topic, values, timeout)
                if went < len(values):
                    raise link_stuck(", ".join(sorted(readers)), timeout, len(values) - went)
            port.connect(_sink(topic), one, many, lossless=True)
            self._ports[topic] = port
        readers.add(key)
        self._removed.pop(key, None)
        self._ports[topic].track(key, replicator.counter(topic))
        return replicator.data_address, replicator.control_address, replicator.incarnation

    def remove(self, key: str) -> tuple[int, bytes | None]:
        """The link ``key`` no longer reads; unhook its output if nothing else does.
        Returns the sequence number its topic had reached (what the reader must
        have received before the link may close) and the incarnation of the sender
        that reached it (None if the link was never published here). A link removed
        already answers as it did then: a move whose unwiring failed after this half
        unwires the link again to undo, and its reader must still wait for those
        values (told 0, its bridge closed the link at once, the values it still held
        back lost with it)."""
        if key in self._removed:
            return self._removed[key]
        reached, incarnation = 0, None
        for topic, readers in list(self._readers.items()):
            if key not in readers:
                continue
            assert self.replicator is not None
            readers.discard(key)
            self._ports[topic].untrack(key)
            # A lossless reader gone with the link no longer holds the writer back
            # (one that unfollowed said so; a lost node's went silent).
            self.replicator.release(topic, SILENT_S if readers else 0.0)
            if not readers:
                del self._readers[topic]
                self._ports.pop(topic).disconnect(_sink(topic))
            reached = self.replicator.sequence(topic)
            incarnation = self.replicator.incarnation
            self._removed[key] = (reached, incarnation)
            while len(self._removed) > REMEMBERED:      # (the oldest first: dicts keep order)
                del self._removed[next(iter(self._removed))]
        return reached, incarnation

    def unacknowledged(self, key: str, reader: bytes) -> int:
        """Values of the output the link ``key`` reads that the follower ``reader`` of a
        lost node has not acknowledged; it is forgotten (``Replicator.forget``)."""
        for topic, readers in self._readers.items():
            if key in readers and self.replicator is not None:
                return self.replicator.forget(topic, reader)
        return 0

    def close(self) -> None:
        if self.replicator is not None:
            self.replicator.close()
            self.replicator = None


def _sink(topic: str) -> str:
    return f"publish:{topic}"
