"""``Bridge``: a node's receiving end of remote links.

Each remote output this node reads is followed once (one ``Follower`` for the node,
one subscription per output), however many local inputs read it; the bridge then
writes every value into the shared-memory ring of each such input, as a local
writer would, so the reading worker cannot tell a remote link from a local one.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from pb3a.errors import RuntimeTimeout
from pb3a.transport.auth import ClusterKey
from pb3a.transport.replication import Follower
from pb3a.transport.ring import ShmRing

READY_TIMEOUT = 10.0


class Bridge:
    """Follows remote outputs and fans their values out into local rings."""

    def __init__(self, key: ClusterKey, epoch: int = 0) -> None:
        self.key = key
        self._lock = threading.Lock()
        self._rings: dict[str, dict[str, ShmRing]] = {}     # topic -> link key -> ring
        self._topics: dict[str, str] = {}                   # link key -> topic
        self._senders: dict[str, bytes] = {}                # topic -> incarnation followed
        self._follower = Follower(key, self._deliver, epoch=epoch)

    def open(self, link: str, topic: str, ring: str, bell: int) -> None:
        """Write ``topic``'s values into ``ring`` (the link's, read by a local worker
        whose doorbell is ``bell``). Opening an open link does nothing."""
        with self._lock:
            if link in self._topics:
                return
            writer = ShmRing.attach(ring)
            writer.set_bell(bell)
            self._rings.setdefault(topic, {})[link] = writer
            self._topics[link] = topic

    def follow(self, topic: str, data: str, control: str, incarnation: bytes,
               timeout: float = READY_TIMEOUT) -> None:
        """Receive ``topic`` from this sender incarnation (a new one after the writer
        restarted or moved); returns once nothing it writes from now on can be missed.
        A topic already followed from that sender is left as it is."""
        if self._senders.get(topic) == incarnation:
            return
        self._senders[topic] = incarnation
        self._follower.follow(topic, data, control, incarnation=incarnation)
        if not self._follower.wait_ready(topic, timeout):
            raise RuntimeTimeout(f"no hand-shake with the sender of {topic} at {data} "
                                 f"within {timeout} s")

    def close(self, link: str, reached: int = 0, timeout: float = READY_TIMEOUT) -> None:
        """Stop feeding ``link`` once the values before sequence number ``reached``
        (the sender's position when it stopped) are in; the output is unfollowed when
        no local input reads it."""
        topic = self._topics.get(link)
        if topic is not None and not self._follower.wait_delivered(topic, reached, timeout):
            raise RuntimeTimeout(f"values of {topic} still in flight after {timeout} s")
        with self._lock:
            topic = self._topics.pop(link, None)
            if topic is None:
                return
            ring = self._rings[topic].pop(link)
            orphaned = not self._rings[topic]
            if orphaned:
                del self._rings[topic]
        if orphaned:
            self._senders.pop(topic, None)
            self._follower.unfollow(topic)
        ring.close()

    def followed(self) -> dict[str, list[str]]:
        """Each followed topic and the local links it feeds."""
        with self._lock:
            return {topic: sorted(rings) for topic, rings in self._rings.items()}

    def link_failures(self, topic: str) -> int:
        """Values of ``topic`` lost for good (gone from the sender's replay buffer)."""
        return self._follower.link_failures[topic]

    @property
    def rejected(self) -> Any:
        return self._follower.rejected

    def _deliver(self, topic: str, values: list[Any], sent_at: float) -> None:
        # the sender's wall clock, as this node's monotonic clock (rings keep that)
        sent = sent_at - time.time() + time.monotonic()
        with self._lock:                         # (close waits: no write to a closed ring)
            for ring in self._rings.get(topic, {}).values():
                ring.write_many(values, sent_at=sent)

    def shutdown(self) -> None:
        self._follower.close()
        with self._lock:
            for rings in self._rings.values():
                for ring in rings.values():
                    ring.close()
            self._rings.clear()
            self._topics.clear()
