"""The receiving side of remote links (see the package's docstring): ``Follower`` takes
in the topics one node follows and delivers each in order, once; ``_Follow`` is what it
knows of one topic."""

from __future__ import annotations

import collections
import logging
import secrets
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import zmq

from pb3a.transport import codec
from pb3a.transport.addresses import numeric
from pb3a.transport.auth import PAYLOAD_TAG, ClusterKey, Opener, Payloads, Rejected, Sealer
from pb3a.transport.heap import keep_freed_buffers
from pb3a.transport.loop import SocketLoop
from pb3a.transport.replication.wire import (
    ACK,
    ACK_BYTES,
    ACK_EVERY,
    ACK_IDLE_S,
    ANSWER,
    ASK,
    BATCH,
    DIRECT,
    DRAIN_BATCH,
    HELLO,
    HELLO_EVERY,
    INFO,
    LINGER_MS,
    LIVE,
    LOSSLESS,
    MAX_MESSAGE,
    NOBLOCK,
    NOBODY,
    REPAIR,
    REPAIR_RETRY_MAX_S,
    REPAIR_RETRY_S,
    REPLAYED,
    RESUME,
    SERVED_DIRECT,
    SKIPPED,
    SYNC,
    VALUE,
    VALUES,
    WAITING,
    WELCOME,
    batch_entries,
    receive_message,
    sealed_as,
    secured_socket,
    send_message,
    topic_bytes,
    topic_text,
)

if TYPE_CHECKING:
    from collections.abc import Callable

    from pb3a.transport.ring import Landed

log = logging.getLogger("pb3a.replication")


@dataclass
class _Follow:
    """What a follower knows of one topic."""

    topic: bytes
    data: zmq.Socket | None                   # SUB to the topic's replicator (None: direct)
    control: zmq.Socket                       # DEALER to the topic's replicator
    next_seq: int                             # the next sequence number to deliver (-1: any)
    incarnation: bytes | None                 # the accepted sender (None: the first to answer)
    live: bool = False                        # a SYNC or value came through the SUB socket
    # runs of values beyond a gap, or waiting for delivery: first sequence number ->
    # (values, sent at, bytes)
    held: dict[int, tuple[list[Any], float, int]] = field(default_factory=dict)
    skips: dict[int, int] = field(default_factory=dict)   # values the sender did not send:
                                                          # first -> end
    asked: float = 0.0                        # when we last asked for a replay (HELLO or
                                              # REPAIR), or a message of its answer came
    hello_at: float = 0.0                     # when we last sent HELLO (any)
    hello_for: bytes | None = None            # the incarnation our last HELLO named
    repairing: bool = False
    asked_from: int = -1                      # the first value the last replay asked for
    # before asking the repair again (read as it is made: a test may set it longer)
    repair_wait: float = field(default_factory=lambda: REPAIR_RETRY_S)
    announced: int = -1                       # the sender's next sequence number, as last heard
    acked: int = -1                           # what we last acknowledged
    acked_at: float = 0.0
    held_back: int = 0                        # delivered values the receiver holds back
    moved_bytes: int = 0                      # bytes delivered ...
    acked_bytes: int = 0                      # ... as of the last acknowledgement
    data_address: str = ""                    # where its SUB connects
    direct: bool = False                      # its values come over the control connection,
                                              # not PUB (see "Slow followers")
    joining: bool = False                     # back on PUB: what was published before the
                                              # first message that comes there is not asked

    @property
    def through(self) -> int:
        """The sequence number up to which the receiver has put values through."""
        return self.next_seq - self.held_back
    ready: threading.Event = field(default_factory=threading.Event)   # live, start known


class Follower:
    """Receives the topics one node follows and delivers each in order, once.

    ``land(topic, meta, nbytes)``, if given, offers a claimed ring slot for a large
    array of ``topic`` (``ShmRing.claim``; None: none), into which its payload is
    decrypted; the value delivered is then that ``Landed``, for the ring to stage
    without a copy.
    ``deliver(topic, values, sent_at)`` is called on the follower's thread; ``sent_at``
    is when the newest value was written, in the sender's wall-clock seconds. It may
    return how many of the topic's newest values it holds back, not put through yet (a
    full lossless receiver), and report later with ``release``; acknowledgements cover
    only what it put through.
    ``identity``: its id at the replicators (``follower_id`` of its node; None: one
    drawn at random, for a follower no launcher needs to name).
    Counters: ``link_failures`` (values lost for good, per topic), ``fenced`` (values
    from a sender that is not the accepted one), ``duplicates`` (dropped), ``dropped``
    (values the sender did not send: the link was slower than its writer)."""

    def __init__(self, key: ClusterKey, deliver: Callable[[str, list[Any], float], None], *,
                 land: Callable[[str, bytes, int], Landed | None] | None = None,
                 epoch: int = 0, max_bytes: int = MAX_MESSAGE,
                 identity: bytes | None = None) -> None:
        keep_freed_buffers()                     # (ZeroMQ's receive buffers: see heap)
        self._key = key
        self._identity = identity or b"f" + secrets.token_bytes(15)
        self._deliver = deliver
        self._land = land
        self._payloads = Payloads(key)
        self._max_bytes = max_bytes
        self._context = zmq.Context.instance()
        self._opener = Opener(key, epoch=epoch, max_bytes=max_bytes)
        self._sealer = Sealer(key, epoch)        # used only on the follower's thread
        self._follows: dict[bytes, _Follow] = {}
        self._lossless: set[bytes] = set()       # topics whose receiver must not drop
        self._subs: dict[str, zmq.Socket] = {}       # data address -> SUB
        self._controls: dict[str, zmq.Socket] = {}   # control address -> DEALER
        self.link_failures: collections.Counter[str] = collections.Counter()
        self.fenced: collections.Counter[str] = collections.Counter()
        self.duplicates: collections.Counter[str] = collections.Counter()
        self.dropped: collections.Counter[str] = collections.Counter()
        self.unsent = 0                          # requests dropped, their queue full
        self._progress = threading.Condition()   # notified after every delivery
        self._loop = SocketLoop("pb3a-follower", self._context)
        self._loop.every(HELLO_EVERY, self._retry)

    @property
    def rejected(self) -> collections.Counter[str]:
        """Messages refused on any socket of this follower, by reason."""
        return self._opener.rejected

    def follow(self, topic: str, data_address: str, control_address: str, *,
               from_seq: int = -1, incarnation: bytes | None = None) -> None:
        """Receive ``topic`` from the replicator at these addresses, starting at
        ``from_seq`` (-1: whatever comes next). With ``incarnation``, only that sender
        is accepted (a hand-over after migration); following again re-points."""
        data, control = numeric(data_address), numeric(control_address)   # (not on the loop)
        self._loop.call(lambda: self._follow(topic_bytes(topic), data, control, from_seq,
                                             incarnation))

    def wait_ready(self, topic: str, timeout: float) -> bool:
        """Block until the hand-shake for ``topic`` is done: from then on nothing
        written is missed. False if it did not finish within ``timeout``."""
        follow = self._follows.get(topic_bytes(topic))
        return follow is not None and follow.ready.wait(timeout)

    def wait_delivered(self, topic: str, seq: int, timeout: float) -> bool:
        """Block until every value of ``topic`` before ``seq`` has been delivered (and put
        through by the receiver)."""
        name = topic_bytes(topic)
        with self._progress:
            return self._progress.wait_for(
                lambda: (f := self._follows.get(name)) is None or f.through >= seq, timeout)

    def unfollow(self, topic: str) -> None:
        self._loop.call(lambda: self._unfollow(topic_bytes(topic)))

    def missing(self, topic: str) -> int:
        """How many values of ``topic`` the sender announced, or sent beyond a gap, that
        were not delivered: what is lost if it is gone for good."""
        def count() -> int:
            follow = self._follows.get(topic_bytes(topic))
            if follow is None or follow.next_seq < 0:
                return 0
            newest = max(follow.announced, max(follow.held, default=-1) + 1)
            skipped = sum(max(0, min(end, newest) - max(first, follow.next_seq))
                          for first, end in follow.skips.items())
            return max(0, newest - follow.next_seq - skipped)
        return self._loop.call(count)

    def set_lossless(self, topic: str, lossless: bool) -> None:
        """Whether ``topic``'s receiver must not drop: then the sender is told (HELLO,
        ACK) to wait for it and to keep what it has not acknowledged."""
        self._loop.call(lambda: self._set_lossless(topic_bytes(topic), lossless))

    def release(self, topic: str, held_back: int) -> None:
        """The receiver put values through: it now holds back ``held_back`` of ``topic``'s
        newest ones."""
        self._loop.call(lambda: self._release(topic_bytes(topic), held_back))

    def _release(self, name: bytes, held_back: int) -> None:
        follow = self._follows.get(name)
        if follow is None:
            return
        with self._progress:
            follow.held_back = held_back
            self._progress.notify_all()
        if follow.through > follow.acked:
            self._acknowledge(follow)

    def later(self, delay: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the follower's thread in ``delay`` seconds (call it there)."""
        self._loop.later(delay, fn)

    def _follow(self, name: bytes, data: str, control: str, from_seq: int,
                incarnation: bytes | None) -> None:
        sub = self._sub(data)
        dealer = self._controls.get(control)
        if dealer is None:
            dealer = secured_socket(self._context.socket(zmq.DEALER), self._max_bytes, sender=False)
            # One id for good (its node's: see ``follower_id``): the replicator keys
            # acknowledgements and lossless holds by it. Drawn by ZeroMQ at each
            # reconnection, it left the old hold behind, never released, until it
            # stopped the writer for good.
            dealer.setsockopt(zmq.ROUTING_ID, self._identity)
            dealer.connect(control)
            self._controls[control] = dealer
            self._loop.register(dealer, self._on_control)
        old = self._follows.get(name)
        if old is None or old.data is not sub:
            sub.setsockopt(zmq.SUBSCRIBE, name)
        if old is not None and old.data is not sub and old.data is not None:
            old.data.setsockopt(zmq.UNSUBSCRIBE, name)
        if old is not None and from_seq < 0 and incarnation in (None, old.incarnation):
            from_seq = old.next_seq               # the same sender: go on where we are
        self._follows[name] = _Follow(name, sub, dealer, from_seq, incarnation,
                                      data_address=data)
        self._hello(self._follows[name])
        self._drop_unused()

    def _sub(self, data: str) -> zmq.Socket:
        """The SUB socket to the replicator publishing at ``data`` (made if none)."""
        sub = self._subs.get(data)
        if sub is None:
            sub = self._subs[data] = secured_socket(self._context.socket(zmq.SUB), self._max_bytes,
                                             sender=False)
            sub.connect(data)
            self._loop.register(sub, self._on_data)
        return sub

    def _go_direct(self, follow: _Follow) -> None:
        """The sender serves this topic over the control connection now: stop taking it
        over PUB. Its SUB socket is closed, which frees what the sender's PUB socket still
        queues for it (unsubscribing would not: that queue would take the slow link's
        time for tens of seconds); the other topics it carried get a new one (what they
        miss meanwhile is repaired)."""
        old, follow.data, follow.direct, follow.joining = follow.data, None, True, False
        if old is None:
            return
        others = [other for other in self._follows.values() if other.data is old]
        self._loop.unregister(old)
        old.close(0)
        self._subs.pop(follow.data_address, None)
        if others:
            sub = self._sub(follow.data_address)
            for other in others:
                sub.setsockopt(zmq.SUBSCRIBE, other.topic)
                other.data = sub

    def _resume(self, follow: _Follow) -> None:
        """The sender serves this topic over PUB again: subscribe. What it publishes
        before the subscription reaches it is not asked for (a hand-shake would have it
        replayed over the slow link that just caught up): the first message that comes
        over PUB says where the follower joins, and the values before it are counted
        dropped (``_joined``)."""
        follow.direct, follow.joining = False, True
        follow.data = self._sub(follow.data_address)
        follow.data.setsockopt(zmq.SUBSCRIBE, follow.topic)

    def _joined(self, follow: _Follow, first: int) -> None:
        """The first message of a topic back on PUB concerns values from ``first`` on:
        the ones before it were published before the subscription was live."""
        follow.joining = False
        self._not_sent_before(follow, first)

    @staticmethod
    def _not_sent_before(follow: _Follow, start: int) -> None:
        """Values before ``start`` not held nor delivered will not come (they went over
        PUB, or not at all): they are passed over, counted dropped, never asked for."""
        seq = follow.next_seq
        if seq < 0:
            return
        for first in sorted(follow.held):
            if first >= start:
                break
            if first > seq:
                Follower._skipped(follow, seq, first)
            seq = max(seq, first + len(follow.held[first][0]))
        if seq < start:
            Follower._skipped(follow, seq, start)

    def _drop_unused(self) -> None:
        """Close the sockets to senders no followed topic comes from any more (they
        moved, restarted or stopped): each holds file descriptors, and a SUB socket
        would go on reconnecting to a sender that is gone. (Each sender has a SUB socket
        of its own because closing a socket is safe where disconnecting a SUB socket
        from one of its publishers while a message is half taken in aborts libzmq:
        zeromq/libzmq#2163.)"""
        used = {id(sock) for follow in self._follows.values()
                for sock in (follow.data, follow.control) if sock is not None}
        for sockets, linger in ((self._subs, 0), (self._controls, LINGER_MS)):
            for address, sock in list(sockets.items()):
                if id(sock) not in used:
                    self._loop.unregister(sock)
                    sock.close(linger=linger)     # (a DEALER's last ACK may be on its way)
                    del sockets[address]

    def _unfollow(self, name: bytes) -> None:
        follow = self._follows.pop(name, None)
        if follow is not None:
            if follow.data is not None:
                follow.data.setsockopt(zmq.UNSUBSCRIBE, name)
            self._ask(follow, ACK, -1, 0)        # the sender forgets us: no waiting for
                                                 # us, nothing we did not see counted lost
        self._lossless.discard(name)
        self._drop_unused()

    def _set_lossless(self, name: bytes, lossless: bool) -> None:
        if lossless == (name in self._lossless):
            return
        if lossless:
            self._lossless.add(name)
        else:
            self._lossless.discard(name)
        follow = self._follows.get(name)
        if follow is not None and follow.live and follow.next_seq >= 0:
            self._acknowledge(follow)            # the sender learns it now

    def _flags(self, follow: _Follow) -> int:
        return LOSSLESS if follow.topic in self._lossless else 0

    def _hello(self, follow: _Follow, waiting: bool = False) -> None:
        """Say HELLO: the sender answers WELCOME, publishes a SYNC (the first that comes
        through the SUB socket makes the follow live) and replays what we miss, unless
        ``waiting`` (a repeat while that replay is on its way: see ``_retry``), or the
        follow is live already (it names the sender only now: see "Slow joiners")."""
        follow.hello_at = time.monotonic()
        flags = self._flags(follow)
        if waiting:
            flags |= WAITING
        elif follow.live and follow.incarnation is not None:
            # What its subscription carried since it went live is not replayed (behind
            # itself on a slow link, each value went twice), nor what came before, which
            # a repair fetches as for any gap (``_advance``): only who it is is said.
            flags |= LIVE
            follow.hello_for = follow.incarnation
        else:
            follow.asked = follow.hello_at
            # (the answer replays what we miss; to one naming nobody, nothing)
            follow.repairing = follow.next_seq >= 0 and follow.incarnation is not None
            follow.asked_from = follow.next_seq
            follow.hello_for = follow.incarnation
        self._ask(follow, HELLO, follow.next_seq, flags)

    def _ask(self, follow: _Follow, kind: int, first: int, last: int) -> None:
        """Send HELLO, REPAIR or ACK to the replicator of ``follow``, naming it (nobody,
        before it said who it is: then only a HELLO is answered, with a WELCOME)."""
        to = follow.incarnation or NOBODY
        frames = self._sealer.seal(kind, [follow.topic, ASK.pack(first, last, to)])
        try:           # never blocks the follower's one thread (every topic it follows)
            send_message(follow.control, frames, NOBLOCK)
        except zmq.Again:       # a replicator out of reach, its queue full: asked again
            self.unsent += 1

    # -- the follower's thread --------------------------------------------------
    def _on_data(self, sock: zmq.Socket) -> None:
        self._drain(sock, live=True)

    def _on_control(self, sock: zmq.Socket) -> None:
        self._drain(sock, live=False)

    def _drain(self, sock: zmq.Socket, live: bool) -> None:
        """Take in what has arrived (a bounded batch), then deliver per topic at once."""
        if sock.closed:
            return                  # (a SUB closed by a DIRECT taken in just before it)
        touched: dict[bytes, _Follow] = {}
        for _ in range(DRAIN_BATCH):
            try:
                frames = receive_message(sock)
            except zmq.Again:
                break
            if live:
                if len(frames) < 2:
                    self._opener.rejected["frame count"] += 1
                    continue
                frames = frames[1:]              # the topic prefix (authenticated inside)
            try:
                message = self._opener.open(frames)
            except Rejected:
                continue                         # (counted by the opener)
            try:
                follow = self._handle(message, live)
            except Rejected as exc:              # authentic, but refused all the same
                self._opener.rejected[exc.reason] += 1
                continue
            except Exception:
                log.exception("follower: a message could not be handled")
                continue
            if follow is None:
                continue
            touched[follow.topic] = follow
        for follow in touched.values():
            self._advance(follow)

    def _handle(self, message: Any, live: bool) -> _Follow | None:
        """Take one message in; the follow it touched (its values are delivered later)."""
        if not message.frames:
            raise Rejected("unexpected")
        follow = self._follows.get(bytes(message.frames[0]))
        if follow is None:
            return None                          # unfollowed meanwhile
        if message.kind in (SYNC, WELCOME):
            # (the third field: a SYNC's values skipped before nxt; a WELCOME's 1 if
            # a replay follows it)
            incarnation, nxt, third = ANSWER.unpack(message.frames[1])
            if not self._accept(follow, incarnation):
                return None
            if live and follow.joining:
                self._joined(follow, nxt)
            skipped = third if message.kind == SYNC else 0
            if 0 < skipped <= nxt:
                self._skipped(follow, nxt - skipped, nxt)
            if follow.next_seq < 0:             # from now on: what came earlier goes
                follow.next_seq = nxt
                for first in [first for first in follow.held if first < nxt]:
                    values, sent_at, nbytes = follow.held.pop(first)
                    if first + len(values) > nxt:
                        follow.held[nxt] = (values[nxt - first:], sent_at, nbytes)
            if live:
                self._goes_live(follow, nxt)
            if live or not follow.live or follow.direct:
                # (a WELCOME to a live follow crosses the control connection ahead of
                # values PUB still carries to it: not a gap; a SYNC behind them says so)
                follow.announced = max(follow.announced, nxt)
            if message.kind == WELCOME and third and follow.repairing:
                follow.asked = time.monotonic()  # its replay is coming (see ``_drain``)
            if follow.hello_for is None and message.kind == WELCOME:
                self._hello(follow)              # naming it now: see "Destinations"
            return follow
        if message.kind == VALUE:
            if (len(message.frames) != 3 or message.payload is None
                    or memoryview(message.frames[1]).nbytes != INFO.size):
                raise Rejected("malformed")
            info, meta = message.frames[1:]
            incarnation, seq, sent_at, kind, nonce, tag = INFO.unpack(info)
            if not self._accept(follow, incarnation):
                return None
            if not live:
                self._answer_coming(follow)
            if live and follow.joining:
                self._joined(follow, seq)
                self._advance(follow)            # (so that it lands in order: below)
            if self._delivered(follow, seq):     # (a repair re-sent it: not decrypted again)
                self.duplicates[topic_text(follow.topic)] += 1
                return None
            # Only the next value in order lands in a ring slot, and is delivered at once:
            # a slot claimed by a value held beyond a gap (or behind one that waits for
            # a free slot) could leave a lossless ring with every slot claimed by values
            # that cannot be staged before the one that waits. Those go to memory.
            in_order = seq == follow.next_seq and not follow.held
            payload = memoryview(message.payload)
            value = self._unseal(follow, incarnation, seq, kind, bytes(meta), nonce, tag,
                                 payload, in_order)
            nbytes = payload.nbytes - PAYLOAD_TAG
            if not self._take(follow, seq, [value], sent_at, nbytes, live):
                return None
            if in_order:
                self._advance(follow)
            return follow
        if message.kind == VALUES:
            if len(message.frames) != 4 or memoryview(message.frames[1]).nbytes != BATCH.size:
                raise Rejected("malformed")
            header, kinds, body = message.frames[1:]
            incarnation, first, count, sent_at = BATCH.unpack(header)
            if not self._accept(follow, incarnation):
                return None
            if not live:
                self._answer_coming(follow)
            if live and follow.joining:
                self._joined(follow, first)
            values = batch_entries(body, bytes(kinds), count)
            nbytes = memoryview(body).nbytes
            return follow if self._take(follow, first, values, sent_at, nbytes, live) else None
        if message.kind == SKIPPED:
            incarnation, first, count = ANSWER.unpack(message.frames[1])
            if not self._accept(follow, incarnation):
                return None
            if first < 0 or count <= 0:
                raise Rejected("malformed")
            if not live:
                self._answer_coming(follow)
            if live and follow.joining:
                self._joined(follow, first)
            self._skipped(follow, first, first + count)
            return follow
        if message.kind in (DIRECT, RESUME):
            incarnation, start, nxt = ANSWER.unpack(message.frames[1])
            if not self._accept(follow, incarnation):
                return None
            if live or start < 0 or follow.next_seq < 0:
                raise Rejected("malformed")
            if message.kind == RESUME:
                # (only while served on its own: one whose DIRECT was lost took every
                # value over PUB, and those still on the way were counted dropped, then
                # arrived as duplicates; a RESUME said again is taken in already)
                if follow.direct:
                    self._not_sent_before(follow, start)
                    self._resume(follow)
                    if follow.topic in self._lossless:   # (nothing may be dropped: the
                        follow.joining = False           # hand-shake replays the rest)
                        follow.live = False
                        self._hello(follow)
            else:
                self._not_sent_before(follow, start)
                if not follow.direct:
                    self._go_direct(follow)
                follow.announced = max(follow.announced, nxt)
            return follow
        if message.kind == REPLAYED:
            incarnation, first, gone = ANSWER.unpack(message.frames[1])
            if not self._accept(follow, incarnation):
                return None
            if first == follow.asked_from:       # (not the end of an earlier copy's)
                follow.repairing, follow.repair_wait = False, REPAIR_RETRY_S
            if gone and follow.next_seq < first + gone:
                lost = first + gone - follow.next_seq - self._pass_skips(follow, first + gone)
                if lost:
                    self.link_failures[topic_text(follow.topic)] += lost
                    log.error("remote link %s lost %d values (gone from the sender's replay "
                              "buffer)", topic_text(follow.topic), lost)
                follow.next_seq = first + gone
            return follow
        raise Rejected("unexpected")

    @staticmethod
    def _goes_live(follow: _Follow, first: int) -> None:
        """A message came through the subscription, about values from ``first`` on (a
        SYNC's next sequence number, or its first value). The first one makes the follow
        live, and PUB carries to it every value from ``first`` on: what the WELCOMEs
        answering its repeated HELLOs announced beyond that (sent after the subscription
        took, they crossed the control connection ahead of values PUB was still carrying)
        is no gap. Taken for one, it was repaired: over a slow link each of those values
        crossed twice, and each answer, beaten by PUB, came in a duplicate, which did not
        restart the repair's wait, so it was asked again at 1, 2, 4 s (a frame sent four
        times over the control connection)."""
        if not follow.live:
            follow.live = True
            follow.announced = min(follow.announced, first)

    @staticmethod
    def _answer_coming(follow: _Follow) -> None:
        """A value or notice of the accepted sender came over the control connection: the
        answer of a hand-shake or repair coming in (or of an earlier copy of it, ahead of
        it), duplicates too. While answers come, the repair is not asked again: on a slow
        link a large value takes seconds to cross, and a request asked again sends the
        whole rest again, behind what is still coming. (Not while served on its own:
        its values come there anyway.)"""
        if follow.repairing and not follow.direct:
            follow.asked = time.monotonic()

    def _unseal(self, follow: _Follow, incarnation: bytes, seq: int, kind: int, meta: bytes,
                nonce: int, tag: bytes, payload: memoryview, land: bool) -> Any:
        """The value of a sealed payload, decrypted and checked in one pass: an array
        straight into the slot the receiver offers (``land``, if asked), else into
        memory of its own. ``Rejected`` if its tag fails (never delivered)."""
        size = payload.nbytes - PAYLOAD_TAG
        if size < 0 or not secrets.compare_digest(payload[size:], tag):
            raise Rejected("bad payload tag")
        bound = sealed_as(follow.topic, incarnation, seq, kind, meta)
        if kind != codec.ARRAY:
            out = bytearray(size)
            self._payloads.open_into(incarnation, nonce, bound, payload, out)
            return codec.decode_owned(kind, meta, out)
        try:
            dtype, _, count = codec.array_meta(meta)
        except (ValueError, TypeError, UnicodeDecodeError):
            raise Rejected("malformed") from None
        if count * dtype.itemsize != size:
            raise Rejected("malformed")
        landed = self._land(topic_text(follow.topic), meta, size) if land and self._land else None
        if landed is None:
            out = np.empty(size, np.uint8)
            self._payloads.open_into(incarnation, nonce, bound, payload, out)
            return codec.decode_owned(kind, meta, out)
        try:
            self._payloads.open_into(incarnation, nonce, bound, payload, landed.buffer)
        except Rejected:
            landed.abandon()                     # (the slot holds unchecked bytes)
            raise
        return landed

    @staticmethod
    def _skipped(follow: _Follow, first: int, end: int) -> None:
        """The sender did not send values ``first..end - 1``: they are passed over when
        delivery gets there, counted as dropped, never asked for."""
        if follow.next_seq < 0 or end > follow.next_seq:
            follow.skips[first] = max(end, follow.skips.get(first, end))

    def _pass_skips(self, follow: _Follow, until: int) -> int:
        """Count as dropped the values not sent before ``until`` from ``next_seq`` on,
        and forget those runs (a repair says the values before them are gone): how
        many."""
        passed = 0
        for first in [first for first in follow.skips if first < until]:
            end = follow.skips.pop(first)
            passed += max(0, min(end, until) - max(first, follow.next_seq))
            if end > until:
                follow.skips[until] = end
        self.dropped[topic_text(follow.topic)] += passed
        return passed

    @staticmethod
    def _delivered(follow: _Follow, seq: int) -> bool:
        """Whether the value ``seq`` was delivered or is held already."""
        return (0 <= seq < follow.next_seq) or seq in follow.held

    def _take(self, follow: _Follow, first: int, values: list[Any], sent_at: float,
              nbytes: int, live: bool) -> bool:
        """Hold a run of values (sequence numbers from ``first`` on) for in-order
        delivery; False if all of them are duplicates."""
        if live:
            self._goes_live(follow, first)
        # (joined "from now": values wait until the hand-shake says where now is)
        old = max(0, follow.next_seq - first) if follow.next_seq >= 0 else 0
        if old:
            self.duplicates[topic_text(follow.topic)] += min(old, len(values))
            if old >= len(values):
                return False
            first, values = first + old, values[old:]
        known = follow.held.get(first)
        if known is not None:                   # (a repair raced the live message)
            self.duplicates[topic_text(follow.topic)] += min(len(known[0]), len(values))
            if len(known[0]) >= len(values):
                return False
        follow.held[first] = (values, sent_at, nbytes)
        return True

    def _accept(self, follow: _Follow, incarnation: bytes) -> bool:
        if follow.incarnation is None:
            follow.incarnation = incarnation
        if incarnation != follow.incarnation:
            self.fenced[topic_text(follow.topic)] += 1
            return False
        return True

    def _advance(self, follow: _Follow) -> None:
        """Deliver what is in order; ask for a repair when a gap blocks the rest."""
        if follow.live and follow.next_seq >= 0 and not follow.ready.is_set():
            follow.ready.set()                   # (set takes a lock: once is enough)
        values, sent_at, size, seq = [], 0.0, 0, follow.next_seq
        held, skips = follow.held, follow.skips
        while seq >= 0 and (held or skips):
            passed = [first for first in skips if first <= seq] if skips else None
            if passed:                           # values the sender did not send
                for first in passed:
                    end = skips.pop(first)
                    if end > seq:
                        self.dropped[topic_text(follow.topic)] += end - seq
                        seq = end
                continue
            first = seq if seq in held else next((k for k in held if k < seq), None)
            if first is None:
                break
            run, sent_at, nbytes = held.pop(first)
            if first < seq:                      # runs that overlap: the rest of this one
                self.duplicates[topic_text(follow.topic)] += min(seq - first, len(run))
                run = run[seq - first:]
            values = run if not values else values + run
            size += nbytes
            seq += len(run)
        if values:
            held_back = 0
            try:
                held_back = self._deliver(topic_text(follow.topic), values, sent_at) or 0
            except Exception:      # (a value too large for a reader's ring: not promised)
                log.exception("remote link %s: values could not be handed to its readers",
                              topic_text(follow.topic))
            finally:
                with self._progress:             # (one step: see wait_delivered)
                    follow.next_seq, follow.held_back = seq, held_back
                    self._progress.notify_all()
            follow.moved_bytes += size
            if self._ack_due(follow):
                self._acknowledge(follow)
        elif seq != follow.next_seq:             # (only values not sent were passed)
            with self._progress:
                follow.next_seq = seq
                self._progress.notify_all()
        # a gap before held values or values not sent, or behind what the sender
        # announced (values lost at the end of a burst show up only in its heartbeat)
        starts = [*follow.held, *follow.skips]
        last = min(starts) - 1 if starts else follow.announced - 1
        if follow.live and not follow.repairing and 0 <= follow.next_seq <= last:
            follow.repairing, follow.asked_from = True, follow.next_seq
            follow.asked = time.monotonic()
            self._ask(follow, REPAIR, follow.next_seq, last)

    def _ack_due(self, follow: _Follow) -> bool:
        """Every ACK_EVERY values or ACK_BYTES bytes (the sender's window counts both,
        and a lossless follower's unacknowledged values stay in a replay buffer of
        bounded bytes)."""
        through = follow.through
        if through - follow.acked >= ACK_EVERY:
            return True
        return through > follow.acked and follow.moved_bytes - follow.acked_bytes >= ACK_BYTES

    def _acknowledge(self, follow: _Follow) -> None:
        """Tell the publisher how far we are (it may run at most its window ahead), and
        whether it serves us on our own: a RESUME lost on the way is then said again."""
        follow.acked, follow.acked_at = follow.through, time.monotonic()
        follow.acked_bytes = follow.moved_bytes
        flags = self._flags(follow) | (SERVED_DIRECT if follow.direct else 0)
        self._ask(follow, ACK, follow.acked, flags)

    def _retry(self) -> None:
        now = time.monotonic()
        for follow in self._follows.values():
            if follow.live and follow.next_seq >= 0 and (
                    follow.through != follow.acked or now - follow.acked_at > ACK_IDLE_S):
                self._acknowledge(follow)
            if follow.repairing and now - follow.asked > follow.repair_wait:
                # nothing of the answer came for that long: a lost request or answer, or
                # one value of it slower to cross than the wait (a large value on a slow
                # link): each time asked again, the whole rest is sent again behind the
                # first, so the wait doubles (until answered)
                follow.repair_wait = min(2 * follow.repair_wait, REPAIR_RETRY_MAX_S)
                if follow.live:
                    follow.repairing = False
                    self._advance(follow)
                else:
                    self._hello(follow)          # the hand-shake's replay, asked again
            elif not follow.live and now - follow.hello_at >= HELLO_EVERY:
                # the slow-joiner hand-shake, until a SYNC comes through the SUB socket;
                # what the last HELLO asked to be replayed is not asked again here (each
                # repeat replayed the whole backlog again over the link, behind the first)
                self._hello(follow, waiting=True)

    def close(self) -> None:
        self._loop.close()
        for sock in [*self._subs.values(), *self._controls.values()]:
            sock.close(0)
