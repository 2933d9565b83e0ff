"""``Bridge``: a node's receiving end of remote links.

Each remote output this node reads is followed once (one ``Follower`` for the node,
one subscription per output), however many local inputs read it; the bridge then
writes every value into the shared-memory ring of each such input, as a local
writer would, so the reading worker cannot tell a remote link from a local one.

Values arrive on the follower's socket thread, which must never block for long. A
dropping link's ring is written as a local writer would (a brief wait, then a counted
drop). A lossless link's ring takes what fits; the rest waits in the link's backlog,
retried every ``RETRY_S`` while there is one, and the follower acknowledges to the
sender only what went into the rings: so a reader that does not keep up holds the
remote writer back through the sender's flow control, and nothing is dropped.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from pb3a.errors import RuntimeTimeout
from pb3a.transport.addresses import RESOLVE_S, unknown_host
from pb3a.transport.auth import ClusterKey
from pb3a.transport.replication import Follower
from pb3a.transport.ring import WRITE_TIMEOUT, Landed, ShmRing

READY_TIMEOUT = 10.0
RETRY_S = 0.001            # how often a lossless link's backlog is offered to its ring again


class NoHandshake(RuntimeTimeout):
    """A node could not begin to receive a link's values: the sender, on another node,
    did not answer its hand-shake in time. The node does not reach where that sender
    publishes (the launcher names both nodes and what to open or set)."""


@dataclass
class _Feed:
    """One local input's ring fed by a followed topic and, on a lossless link, the
    values that did not fit yet, oldest first: ``(values, sent at)``."""

    ring: ShmRing
    bell: int = -1                    # the bridge's own duplicate of the reader's doorbell
    backlog: deque[tuple[list[Any], float]] = field(default_factory=deque)
    waiting: int = 0                  # values in the backlog
    # a dropping ring that was full after its wait: its reader is stalled (frozen,
    # gone), and the next writes do not wait, for every link's values wait behind them
    stalled: bool = False

    def close(self) -> None:
        """Close the ring and the bridge's duplicate of its reader's doorbell."""
        self.ring.set_bell(-1)
        self.ring.close()
        if self.bell >= 0:
            with contextlib.suppress(OSError):
                os.close(self.bell)
            self.bell = -1

    def offer(self) -> None:
        """Put as much of the backlog into the ring as fits now."""
        backlog = self.backlog
        while backlog:
            values, sent = backlog[0]
            went = self.ring.offer(values, sent)
            self.waiting -= went
            if went < len(values):
                backlog[0] = (values[went:], sent)
                return
            backlog.popleft()


class Bridge:
    """Follows remote outputs and fans their values out into local rings."""

    def __init__(self, key: ClusterKey, epoch: int = 0, identity: bytes | None = None) -> None:
        """``identity``: the follower's id at the writers (``follower_id`` of the node)."""
        self.key = key
        self._lock = threading.Lock()
        self._rings: dict[str, dict[str, _Feed]] = {}       # topic -> link key -> its ring
        self._topics: dict[str, str] = {}                   # link key -> topic
        self._senders: dict[str, bytes] = {}                # topic -> incarnation followed
        self._retrying = False                              # a retry is due on the loop
        self._follower = Follower(key, self._deliver, land=self._land, epoch=epoch,
                                  identity=identity)

    def open(self, link: str, topic: str, ring: str, bell: int) -> None:
        """Write ``topic``'s values into ``ring`` (the link's, read by a local worker
        whose doorbell is ``bell``). Opening an open link does nothing. The bridge rings
        a duplicate of ``bell`` of its own: the reader's worker may be stopped before the
        link is closed (a failed move drops the module at its destination first), and
        its doorbell closed then (ringing that number failed with EBADF, or woke another
        file that took the number)."""
        with self._lock:
            if link in self._topics:
                return
            writer = ShmRing.attach(ring)
            own = os.dup(bell) if bell >= 0 else -1
            writer.set_bell(own)
            writer.label = link
            self._rings.setdefault(topic, {})[link] = _Feed(writer, own)
            self._topics[link] = topic
            lossless = self._lossless(topic)
        self._follower.set_lossless(topic, lossless)

    def follow(self, senders: list[tuple[str, str, str, bytes]],
               timeout: float = READY_TIMEOUT) -> None:
        """Receive each ``(topic, data address, control address, sender incarnation)``
        (a new incarnation after the writer restarted or moved); returns once nothing
        they write from now on can be missed. The hand-shakes run side by side, all
        within ``timeout``. A topic already followed from that sender is left as it is."""
        started = []
        for topic, data, control, incarnation in senders:
            if self._senders.get(topic) != incarnation:
                self._senders[topic] = incarnation
                self._follower.follow(topic, data, control, incarnation=incarnation)
                started.append((topic, data))
        deadline = time.monotonic() + timeout
        for topic, data in started:
            if not self._follower.wait_ready(topic, max(0.0, deadline - time.monotonic())):
                # (a sender's host name this machine does not resolve: said so)
                unknown = unknown_host(data, RESOLVE_S)
                raise NoHandshake(f"no hand-shake with the sender of {topic} at {data} "
                                  f"within {timeout:g} s"
                                  + (f" ({unknown}, on this node's machine)" if unknown else ""))

    def close(self, link: str, reached: int = 0, timeout: float = READY_TIMEOUT,
              sender: bytes | None = None) -> int:
        """Stop feeding ``link`` once the values before sequence number ``reached``
        (the position of ``sender``, an incarnation, when it stopped) are in; the output
        is unfollowed when no local input reads it. Returns how many values the sender
        announced that never came (it is gone: they are lost). A ``sender`` other than
        the one followed (a writer restarted on another node since, whose new
        incarnation is not followed yet) sends this bridge nothing: not waited for (the
        sequence numbers are not the followed one's; the wait ran out after
        ``timeout``, saying values were still in flight)."""
        topic = self._topics.get(link)
        missing = 0
        if topic is not None:
            with self._lock:
                feed = self._rings.get(topic, {}).get(link)
            if feed is not None and feed.ring.lossless:
                feed.ring.request_flush()        # its reader may be paused: take it all
            if sender is not None and self._senders.get(topic) != sender:
                reached = 0              # (the one followed is gone: no more comes)
            if not self._follower.wait_delivered(topic, reached, timeout):
                raise RuntimeTimeout(f"values of {topic} still in flight after {timeout} s")
            missing = self._follower.missing(topic)
        with self._lock:
            topic = self._topics.pop(link, None)
            if topic is None:
                return missing
            feed = self._rings[topic].pop(link)
            orphaned = not self._rings[topic]
            if orphaned:
                del self._rings[topic]
            lossless = self._lossless(topic)
            held_back = max((other.waiting for other in self._rings.get(topic, {}).values()),
                            default=0)
        if orphaned:
            self._senders.pop(topic, None)
            self._follower.unfollow(topic)
        else:
            self._follower.set_lossless(topic, lossless)
            self._follower.release(topic, held_back)   # (its backlog held the rest back)
        feed.close()
        return missing

    def followed(self) -> dict[str, list[str]]:
        """Each followed topic and the local links it feeds."""
        with self._lock:
            return {topic: sorted(rings) for topic, rings in self._rings.items()}

    def link_failures(self, topic: str) -> int:
        """Values of ``topic`` lost for good (gone from the sender's replay buffer)."""
        return self._follower.link_failures[topic]

    def drops(self, topic: str) -> int:
        """Values of ``topic`` its sender did not send: the link was slower than its
        writer (see "Slow links")."""
        return self._follower.dropped[topic]

    @property
    def rejected(self) -> Any:
        return self._follower.rejected

    def _lossless(self, topic: str) -> bool:
        return any(feed.ring.lossless for feed in self._rings.get(topic, {}).values())

    def _land(self, topic: str, meta: bytes, nbytes: int) -> Landed | None:
        """A claimed slot of the ring ``topic`` feeds, for a large array to be decrypted
        into (on the follower's thread): so it lands with no copy of its own. Only for
        a topic that feeds one ring (a slot staged in one ring may be reused while
        another ring's backlog would still copy from it), and not while that ring's
        backlog waits: a slot freed by the reader must go to the backlog's oldest
        value, not to a newer one."""
        with self._lock:
            feeds = self._rings.get(topic)
            if feeds is None or len(feeds) != 1:
                return None
            (feed,) = feeds.values()
            return None if feed.backlog else feed.ring.claim(meta, nbytes)

    def _deliver(self, topic: str, values: list[Any], sent_at: float) -> int:
        """Write values into every ring that reads ``topic`` (on the follower's thread);
        returns how many of the topic's newest values some lossless ring still lacks."""
        # the sender's wall clock, as this node's monotonic clock (rings keep that)
        sent = sent_at - time.time() + time.monotonic()
        held_back = 0
        with self._lock:                         # (close waits: no write to a closed ring)
            for feed in self._rings.get(topic, {}).values():
                if not feed.ring.lossless:
                    went = feed.ring.write_many(values, 0.0 if feed.stalled else WRITE_TIMEOUT,
                                                sent_at=sent)
                    feed.stalled = went < len(values)
                    continue
                went = 0 if feed.backlog else feed.ring.offer(values, sent)
                if went < len(values):
                    feed.backlog.append((values[went:], sent))
                    feed.waiting += len(values) - went
                held_back = max(held_back, feed.waiting)
        if held_back and not self._retrying:
            self._retrying = True
            self._follower.later(RETRY_S, self._retry)
        return held_back

    def _retry(self) -> None:
        """Offer every backlog to its ring again; tell the follower what went through."""
        moved: dict[str, int] = {}
        with self._lock:
            for topic, feeds in self._rings.items():
                if any(feed.backlog for feed in feeds.values()):
                    for feed in feeds.values():
                        feed.offer()
                    moved[topic] = max(feed.waiting for feed in feeds.values())
        for topic, held_back in moved.items():
            self._follower.release(topic, held_back)
        self._retrying = any(moved.values())
        if self._retrying:
            self._follower.later(RETRY_S, self._retry)

    def shutdown(self) -> None:
        self._follower.close()
        with self._lock:
            for feeds in self._rings.values():
                for feed in feeds.values():
                    feed.close()
            self._rings.clear()
            self._topics.clear()
