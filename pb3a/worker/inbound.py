"""``InboundLink``: one ring a worker's receiver drains into the input it feeds.

A dropping or queue link is drained as fast as values come; a lossless one
(``LosslessInboundLink``) only as fast as its input has room, so that its writer waits.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

from pb3a.model.ports import InputPort
from pb3a.transport.ring import ShmRing

log = logging.getLogger("pb3a.worker")

GUARD_TIMEOUT = 0.5      # longest sleep of the receiver (a guard; wake-ups are not lost)
FAILURE_LOG_S = 1.0      # a link whose drain fails is logged at most this often


@dataclass
class InboundLink:
    """One inbound ring and the input it feeds; closed under its lock."""

    ring: ShmRing
    port: InputPort
    lock: threading.Lock = field(default_factory=threading.Lock)
    closed: bool = False
    resume_at: float = 0.0       # its drain failed: the receiver leaves it alone until then
    report_at: float = 0.0       # when its next failure may be logged

    def drain(self, limit: int = 1024) -> int:
        """Take up to ``limit`` values from the ring into the input. Taken and delivered
        under the link's lock: the receiver and the link's ``close`` (a move unwiring
        it) drain side by side, and a batch one of them took, delivered after the other
        took and delivered the next, reached the module out of order."""
        self.lock.acquire()
        try:
            if self.closed:
                return 0
            values, sent_at, gaps = self.ring.drain(limit)
            if gaps:
                self.port.drops += gaps
            if values:
                self.port.deliver_many(values, sent_at)
        finally:
            self.lock.release()
        return len(values)

    def wanted(self) -> bool:
        """Whether the receiver should drain this ring now (look at it before sleeping)."""
        return True

    def set_aside(self) -> None:
        """Its drain raised (a record its writer broke, say): the receiver logs it (at most
        once a second) and leaves the link alone for a while, so that it neither keeps
        the other links waiting nor makes the receiver spin; then it tries again."""
        now = time.monotonic()
        self.resume_at = now + GUARD_TIMEOUT
        if now >= self.report_at:
            self.report_at = now + FAILURE_LOG_S
            log.exception("receiver: cannot read link %s; tried again every %.1f s",
                          self.ring.label, GUARD_TIMEOUT)

    def close(self) -> int:
        """Deliver everything left in the ring (room in the input or not), then detach
        (also when that fails)."""
        drained = 0
        try:
            drained += InboundLink.drain(self)
            while self.ring.has_data():          # (a batch may hold no decodable value)
                drained += InboundLink.drain(self)
        finally:
            with self.lock:
                self.closed = True
                self.ring.close()
        return drained


class LosslessInboundLink(InboundLink):
    """A lossless link: the receiver takes from the ring only what the input has room
    for and leaves the rest, so a full input fills the ring and its writer waits. A
    read that makes room rings the worker's doorbell (the port's ``_on_room``); a
    writer that closes the link asks for everything at once (``request_flush``)."""

    def drain(self, limit: int = 1024) -> int:
        if not self.ring.flush_requested:
            limit = min(limit, self.port.claim_room())
            if limit <= 0:
                return 0
        return super().drain(limit)

    def wanted(self) -> bool:
        return self.ring.flush_requested or self.port.claim_room() > 0
