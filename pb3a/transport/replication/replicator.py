"""The sending side of remote links (see the package's docstring): ``Replicator``
publishes the outputs of one process and answers hand-shakes and repairs; each output
it publishes is a ``Stream`` (``pb3a.transport.replication.stream``: its batch being
filled, its replay buffer, its followers' acknowledgements, flow control, the flight,
and the followers served on their own)."""

from __future__ import annotations

import collections
import logging
import math
import pickle
import secrets
import threading
import time
from typing import TYPE_CHECKING, Any

import zmq

from pb3a.errors import link_stuck
from pb3a.transport.addresses import bind_advertised
from pb3a.transport.auth import PAYLOAD_TAG, ClusterKey, Opener, Payloads, Rejected, Sealer
from pb3a.transport.heap import keep_freed_buffers
from pb3a.transport.loop import SocketLoop
from pb3a.transport.replication.stream import Direct, Sent, Stream
from pb3a.transport.replication.wire import (
    ACK,
    ANSWER,
    ASK,
    ASKED_MAX,
    BATCH,
    BATCH_BYTES,
    BATCH_VALUES,
    DIRECT,
    DRAIN_BATCH,
    FLIGHT_START,
    FOLLOWER_TIMEOUT,
    FRESH_S,
    HEARTBEAT_S,
    HELLO,
    INFO,
    LIVE,
    LOSSLESS,
    MAX_MESSAGE,
    NOBODY,
    PLAIN,
    REPAIR,
    REPLAYED,
    RESUME,
    SCALAR_BYTES,
    SCALARS,
    SERVED_DIRECT,
    SKIPPED,
    SYNC,
    VALUE,
    VALUES,
    WAITING,
    WELCOME,
    WINDOW,
    WINDOW_BYTES,
    WINDOW_WAIT,
    batch_entry,
    receive_message,
    sealed_as,
    sealed_message,
    secured_socket,
    send_message,
    topic_bytes,
    topic_text,
)
from pb3a.transport.ring import RingSize

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

log = logging.getLogger("pb3a.replication")


class Replicator:
    """Publishes the outputs of one process (PUB) and answers hand-shakes and repairs
    (ROUTER) on its own thread. ``publish`` and ``offer`` may be called from any thread."""

    def __init__(self, key: ClusterKey, host: str = "127.0.0.1", *, epoch: int = 0,
                 max_bytes: int = MAX_MESSAGE) -> None:
        keep_freed_buffers()                     # (the copies of large values: see heap)
        self.incarnation = secrets.token_bytes(16)
        self._max_bytes = max_bytes
        self._batch_bytes = min(BATCH_BYTES, max_bytes // 2)
        self._context = zmq.Context.instance()
        # (their limit is on what they take in: what they send is the values' own)
        self._pub = secured_socket(self._context.socket(zmq.PUB), ASKED_MAX, sender=True)
        self._router = secured_socket(self._context.socket(zmq.ROUTER), ASKED_MAX,
                                      sender=True)
        # a follower keeps its id across reconnections (see Follower): the new
        # connection takes the id over from the old one, which may not be seen gone yet
        self._router.setsockopt(zmq.ROUTER_HANDOVER, 1)
        # (host: where the readers' nodes reach this one; see ``addresses``)
        self.data_address = bind_advertised(self._pub, host)
        self.control_address = bind_advertised(self._router, host)
        self._pub_sealer = Sealer(key, epoch)
        self._router_sealer = Sealer(key, epoch)
        self._payloads = Payloads(key, self.incarnation)
        self._opener = Opener(key, epoch=epoch, max_bytes=max_bytes)
        self._streams: dict[bytes, Stream] = {}      # by name (bytes) ...
        self._topics: dict[str, Stream] = {}         # ... and by topic
        # the PUB socket (used by the loop's thread and, for large values, by the
        # publishing thread: never both at once), the streams, the outbox
        self._lock = threading.Lock()
        self._acked = threading.Condition(self._lock)
        self._outbox: list[tuple[bytes, Sent]] = []     # ready, not sent yet
        self._filling: set[bytes] = set()                # topics with a batch being filled
        self._flush_due = False                          # a flush is queued on the loop
        self._loop = SocketLoop("pb3a-replicator", self._context)
        self._loop.register(self._router, self._on_request)
        self._loop.every(HEARTBEAT_S, self._heartbeat)

    @property
    def rejected(self) -> collections.Counter[str]:
        """Messages refused on the control socket, by reason."""
        return self._opener.rejected

    def add(self, topic: str, next_seq: int = 0, room: RingSize | None = None) -> None:
        """Start publishing ``topic``; ``next_seq`` continues a migrated stream; ``room``:
        the rings its readers take values into (a value that fits none is refused)."""
        with self._lock:
            if topic not in self._topics:
                stream = Stream(topic_bytes(topic), next_seq, room=room)
                self._streams[stream.name] = self._topics[topic] = stream

    def sequence(self, topic: str) -> int:
        """The sequence number the next value on ``topic`` will get."""
        with self._lock:
            return self._topics[topic].next_seq

    def forget(self, topic: str, follower: bytes) -> int:
        """The follower ``follower`` (``follower_id``) of ``topic`` went with its lost node:
        how many values it never acknowledged (0 if it never said anything here). It is
        forgotten: it holds nothing back, and what it says from now on is ignored; asked
        again (another link of that node reading ``topic``), counted from the same
        acknowledgement."""
        with self._lock:
            stream = self._topics.get(topic)
            if stream is None:
                return 0
            if follower not in stream.gone:
                acked = stream.drop_follower(follower)
                stream.gone[follower] = stream.next_seq if acked is None else acked[0]
                self._acked.notify_all()         # (a write it held back goes on)
            return max(0, stream.next_seq - stream.gone[follower])

    def counter(self, topic: str) -> Any:
        """What counts the publishes of ``topic`` that waited (``waits``, ``wait_s``)."""
        with self._lock:
            return self._topics[topic]

    def release(self, topic: str, silent_for: float = 0.0) -> None:
        """Stop waiting for the lossless followers of ``topic`` that have been silent
        for ``silent_for`` seconds or more, a link to them being cut; with 0 (its last
        reader gone), forget every follower, also what they did not acknowledge. (A
        silent follower's acknowledgement is kept otherwise: it may be a live one's, late;
        a lost node's is dropped by ``forget``.)"""
        with self._lock:
            stream = self._topics.get(topic)
            if stream is None:
                return
            now = time.monotonic()
            for peer in list(stream.holds):
                if now - stream.acks.get(peer, (0, -math.inf))[1] >= silent_for:
                    del stream.holds[peer]
            if not silent_for:
                stream.acks.clear()
                stream.direct.clear()
                stream.joined.clear()
                stream.resumed.clear()
            self._acked.notify_all()

    def publish(self, topic: str, value: Any, timeout: float = WINDOW_WAIT) -> int:
        """Send one value; returns its sequence number. RuntimeTimeout (and nothing sent)
        when a lossless follower leaves no room within ``timeout``: see ``offer``."""
        if not self.offer(topic, (value,), timeout):
            raise link_stuck(topic, timeout)
        return self.sequence(topic) - 1

    def sink(self, topic: str, stuck: Callable[[float], Exception]) -> Callable[[Any, float], None]:
        """What an output's ``write`` calls to publish one value on ``topic``:
        ``one(value, timeout)``, as ``offer``, raising ``stuck(timeout)`` if the value
        did not go. The most common value (an immutable scalar joining a batch of such
        values that flow control has already cleared) takes a short path: the lock
        and an append, about a third of ``offer``'s cost. Such scalars count against
        the ``WINDOW`` of values, not the ``WINDOW_BYTES`` (their 9 bytes each, 18 KiB
        in a full window, are not worth the count)."""
        with self._lock:
            stream = self._topics[topic]
        lock, offer = self._lock, self.offer
        last, full = BATCH_VALUES - 1, self._batch_bytes - SCALAR_BYTES

        def one(value: Any, timeout: float) -> None:
            if type(value) in SCALARS:
                lock.acquire()          # (not ``with``: this path is paid per value)
                pending = stream.pending
                if (pending and stream.next_seq < stream.clear_until and stream.kinds is None
                        and len(pending) < last and stream.pending_bytes < full):
                    pending.append(value)           # a flush is due: see offer
                    stream.next_seq += 1
                    stream.pending_bytes += SCALAR_BYTES
                    lock.release()
                    return
                lock.release()
            if not offer(topic, (value,), timeout):
                raise stuck(timeout)
        return one

    def offer(self, topic: str, values: Sequence[Any], timeout: float = WINDOW_WAIT) -> int:
        """Send values in order; returns how many went (all but when a lossless follower
        holds the publisher back: see below). ValueError, and nothing sent, if one is
        larger than the message limit.

        Flow control: a publisher more than ``WINDOW`` values or ``WINDOW_BYTES`` bytes
        ahead of its slowest follower waits for it (up to ``WINDOW_WAIT``, then goes on
        and lets the repair or the link-failure count deal with it), so a burst never
        overruns the high-water marks; those waits end at ``timeout`` too, counted
        from the first (they took 0.1 s per value: 20 values given 0.3 s took 2 s).
        A lossless follower holds it back up to ``timeout`` (the writer's) in all;
        the values that found no room by then are not sent.

        Values are taken as they are now (see ``batch_entry``). Small ones go out as soon as
        the replicator's thread gets to them (those published meanwhile go with them);
        a large one goes at once, from this thread: batching gains nothing for it, and
        a hand-over to the other thread costs a thread switch per value."""
        max_bytes, room = self._max_bytes, self._topics[topic].room
        entries = [(PLAIN, value, SCALAR_BYTES) if type(value) in SCALARS
                   else batch_entry(value, max_bytes, room) for value in values]
        deadline = None
        went, large = 0, False
        with self._lock:
            stream = self._topics[topic]
            pending = stream.pending
            for kind, entry, size in entries:
                if stream.next_seq >= stream.clear_until or size > stream.credit:
                    if deadline is None:
                        deadline = time.monotonic() + timeout
                    if not self._admit(stream, size, deadline):
                        break
                stream.credit -= size
                if kind == PLAIN and pending and stream.kinds is None:   # most values
                    pending.append(entry)
                    stream.pending_bytes += size
                    stream.next_seq += 1
                else:
                    self._add(stream, kind, entry, size)
                    large = large or kind < 0
                went += 1
                if len(pending) >= BATCH_VALUES or stream.pending_bytes >= self._batch_bytes:
                    self._close_batch(stream)
            if large:                        # sent now: see above
                self._flush_locked()
            elif not self._flush_due:
                self._flush_due = True
                self._loop.submit(self._flush)
        return went

    def _add(self, stream: Stream, kind: int, entry: Any, size: int) -> None:
        """Publish one value (lock held): into the batch being filled, or, if large, as
        a message of its own. A large one's number is taken once the batch before it
        is closed (which numbers its values back from ``next_seq``) and once it is
        sealed: a seal that fails leaves no gap that no repair could fill."""
        if kind < 0:
            self._close_batch(stream)
            seq = stream.next_seq
            if self._too_slow(stream, size):     # (not sealed: it does not go)
                stream.next_seq = seq + 1
                stream.skip(seq, seq + 1)
                return
            meta, payload = entry
            bound = sealed_as(stream.name, self.incarnation, seq, -kind, meta)
            nonce, sealed = self._payloads.seal(payload, bound)
            stream.next_seq = seq + 1
            info = INFO.pack(self.incarnation, seq, time.time(), -kind, nonce,
                              sealed[-PAYLOAD_TAG:].tobytes())
            # one frame for every send (repairs too): ZeroMQ shares it by reference
            self._send_soon(stream, Sent(seq, seq + 1, VALUE,
                                          [info, meta, zmq.Frame(sealed, copy=False)], size,
                                          time.monotonic()))
            return
        stream.next_seq += 1
        pending = stream.pending
        if not pending:
            stream.pending_at = time.time()
            self._filling.add(stream.name)
        if kind != PLAIN and stream.kinds is None:
            stream.kinds = bytearray(len(pending))
        pending.append(entry)
        if stream.kinds is not None:
            stream.kinds.append(kind)
        stream.pending_bytes += size

    def _admit(self, stream: Stream, size: int, deadline: float) -> bool:
        """Flow control for the next value (lock held, released while waiting): False if
        a lossless follower left no room by ``deadline``. Sets how far values may go
        from here on without asking again."""
        started = None          # a wait is counted as it begins: a writer stuck now shows
        while stream.holds and not stream.room_for(size):
            now = time.monotonic()
            if started is None:
                started = now
                stream.waits += 1
            if now >= deadline:
                stream.wait_s += now - started
                return False
            self._acked.wait(deadline - now)
        while not stream.holds and not stream.slow:
            # the lead follower has its flight of bytes on the way: wait for it while
            # they are fresh (see "Slow links"); past that, what does not fit does not go
            now = time.monotonic()
            oldest = stream.over_flight(stream.pending_bytes + size)
            if oldest is None:
                break
            late = min(oldest + FRESH_S, deadline)
            if now >= late:
                break
            if started is None:
                started = now
                stream.waits += 1
            self._acked.wait(late - now)
        window_end = None
        while not (stream.slow and not stream.holds) \
                and (acked := stream.acknowledged(time.monotonic())) is not None \
                and (stream.next_seq - acked >= WINDOW or not stream.fits(acked, size)):
            if window_end is None:           # (never past the writer's deadline)
                window_end = min(time.monotonic() + WINDOW_WAIT, deadline)
                if started is None:
                    started = time.monotonic()
                    stream.waits += 1
            if not self._acked.wait(window_end - time.monotonic()) \
                    and time.monotonic() >= window_end:
                break
        if started is not None:
            stream.wait_s += time.monotonic() - started
        acked = stream.acknowledged(time.monotonic())
        if stream.holds or started is not None or stream.slow:
            stream.clear_until = stream.next_seq + 1    # ask again for the next value
        elif acked is None:
            stream.clear_until = stream.credit = math.inf
        else:            # (only a new follower brings the window's end closer: see ACK)
            stream.clear_until = acked + WINDOW
            lead = stream.flight_lead(time.monotonic())
            on_way = (stream.on_the_way(lead)[0] if lead is not None
                      and stream.replay_bytes > stream.flight else stream.replay_bytes)
            stream.credit = min(WINDOW_BYTES - stream.ahead(acked),
                                stream.flight - on_way - stream.pending_bytes)
        return True

    def _close_batch(self, stream: Stream) -> None:
        """The values being gathered become one message, ready to send (lock held)."""
        pending = stream.pending
        if not pending:
            return
        first = stream.next_seq - len(pending)
        sent = None
        if self._too_slow(stream, stream.pending_bytes):
            stream.skip(first, stream.next_seq)
        else:
            kinds = bytes(stream.kinds) if stream.kinds is not None else b""
            parts = [BATCH.pack(self.incarnation, first, len(pending), stream.pending_at),
                     kinds, pickle.dumps(pending, protocol=5)]
            sent = Sent(first, stream.next_seq, VALUES, parts, stream.pending_bytes,
                         time.monotonic())
        pending.clear()                          # (the same list: offer holds it)
        stream.kinds, stream.pending_bytes = None, 0
        self._filling.discard(stream.name)
        if sent is not None:
            self._send_soon(stream, sent)

    def _send_soon(self, stream: Stream, sent: Sent) -> None:
        """Keep a message for repairs and put it in the outbox (lock held), after the
        notice of the values not sent before it, if any: its followers count them
        dropped, and do not ask for them."""
        if stream.skip_from >= 0:
            first, count = stream.skip_from, sent.first - stream.skip_from
            stream.skips.append((first, sent.first))
            notice = ANSWER.pack(self.incarnation, first, count)
            self._outbox.append((stream.name, Sent(first, sent.first, SKIPPED, [notice], 0)))
            stream.skip_from = -1
        stream.keep(sent)
        self._outbox.append((stream.name, sent))

    def _too_slow(self, stream: Stream, size: int) -> bool:
        """Whether a message of ``size`` bytes must not go (lock held): no lossless
        follower, the lead follower has more than ``flight`` bytes on the way, and it is
        slow (it became so if the oldest of them went ``FRESH_S`` ago)."""
        oldest = None if stream.holds else stream.over_flight(size)
        if oldest is None:
            return False
        if not stream.slow and time.monotonic() - oldest >= FRESH_S:
            stream.slow, stream.flight = True, 0
        return stream.slow

    def _pace(self, stream: Stream, before: int | None, now: float) -> None:
        """An acknowledgement came (lock held): if it moves the lead follower on, the
        age of the newest message it acknowledges (from when it went) says whether
        the link keeps up: FRESH_S or more, it is slow (one message on the way at a
        time); under half of it, a slow link is not any more, and the bytes that may be
        on the way double."""
        lead = stream.flight_lead(now)
        if stream.holds or lead is None or (before is not None and lead <= before):
            return
        on_way, _, went = stream.on_the_way(lead)
        age = now - went
        if age >= FRESH_S:
            stream.slow, stream.flight = True, 0
        elif stream.slow:
            if age < FRESH_S / 2 and not on_way:
                stream.slow, stream.flight = False, FLIGHT_START
        elif age < FRESH_S / 2:
            stream.flight = min(WINDOW_BYTES, max(FLIGHT_START, 2 * stream.flight))

    # -- slow followers beside fast ones (see "Slow followers") ---------------------
    def _find_slow(self, stream: Stream, now: float) -> None:
        """Serve over the control connection each live dropping follower served over PUB
        that is behind another one and whose oldest message on the way went ``FRESH_S``
        ago, once it has taken in what its hand-shake replayed (a reader that moved
        there, say, with values from before) (lock held, on the loop's thread)."""
        if stream.holds or len(stream.acks) - len(stream.direct) < 2:
            return
        lead = stream.lead(now)
        for peer, (acked, when) in list(stream.acks.items()):
            if (peer in stream.direct or now - when >= FOLLOWER_TIMEOUT or lead is None
                    or acked >= lead or acked < stream.joined.get(peer, 0)):
                continue             # (nor one still taking in a replay: those went long ago)
            if now - stream.on_the_way(acked)[1] >= FRESH_S:
                self._go_direct(stream, peer)

    def _go_direct(self, stream: Stream, peer: bytes) -> None:
        """From the next value on, send ``peer`` the values of ``stream`` over the control
        connection, one message on the way at a time; it stops taking them over PUB
        (DIRECT: it closes its SUB connection, which frees what PUB still queues for
        it) and counts those it misses before then dropped (lock held, loop thread)."""
        self._flush_locked()                     # (what was published went over PUB)
        start = stream.next_seq
        stream.direct[peer] = Direct(start, start, time.monotonic())
        stream.resumed.pop(peer, None)           # (its start says it now)
        self._send_router(peer, DIRECT, [stream.name, ANSWER.pack(self.incarnation, start,
                                                                   start)])
        stream.clear_until = 0                   # (flow control no longer counts it)
        self._acked.notify_all()
        log.info("remote link %s: a follower too slow beside a faster one is served on its "
                 "own from value %d", topic_text(stream.name), start)

    def _resume(self, stream: Stream, peer: bytes, now: float, start: int | None = None) -> None:
        """A follower served on its own keeps up again: back to PUB from ``start`` (None:
        the next value; the values before it are not sent to it, and it counts them
        dropped), with RESUME (lock held, on the loop's thread). A follower that became
        lossless resumes from where it is, and says HELLO to have the rest replayed.
        One no ACK said knew it was served on its own (``told``) may never have taken
        the DIRECT in (lost on the way): it is where its ACKs say, on PUB, and ignores
        the RESUME (which goes all the same, behind a DIRECT still on its way); taken
        to be at ``start``, it had a repair of a gap before it answered SKIPPED."""
        self._flush_locked()
        direct = stream.direct.pop(peer)
        if start is None:
            start = stream.next_seq
            if direct.told:
                stream.acks[peer] = (start, now)     # (so it is not found slow for them)
                stream.resumed[peer] = start     # (a repair crossing the RESUME: see _replay)
        self._send_router(peer, RESUME, [stream.name, ANSWER.pack(self.incarnation, start, 0)])
        stream.clear_until = 0

    def _resume_again(self, stream: Stream, peer: bytes, acked: int) -> None:
        """A follower served over PUB says it is served on its own: the RESUME sent to
        it was lost on the way (a ROUTER drops what it sends to a peer whose connection
        is down), and it waits on its control connection, its SUB connection closed,
        for values that all go to PUB. Say it again, from where the last one said (one
        it took in already, crossing its acknowledgement, then says nothing new), or,
        a lossless follower's, from where it is (``acked``) (lock held, loop thread)."""
        start = stream.resumed.get(peer, acked)
        self._send_router(peer, RESUME, [stream.name, ANSWER.pack(self.incarnation, start, 0)])

    def _resume_alone(self, stream: Stream, now: float) -> None:
        """No live follower is served over PUB any more (the fast one unfollowed, was
        forgotten with its lost node, or has been silent for ``FOLLOWER_TIMEOUT``): the
        most advanced live follower served on its own goes back to PUB, where it leads
        and the flight serves it as a lone slow link (one message on the way at a time,
        until a lone one is acknowledged in time). Left on its own, every value went to
        PUB for nobody and was kept, up to the replay buffer's bound. Another one served
        on its own stays so, beside it; a silent one stays so until it is live again (a
        RESUME to a cut link may be lost, and is said again only at its next ACK: see
        ``_resume_again``) (lock held, on the loop's thread)."""
        if not stream.direct or stream.holds or stream.lead(now) is not None:
            return               # (a lossless follower: no flight, PUB would queue it all)
        live = [(stream.acks[peer][0], peer) for peer in stream.direct
                if peer in stream.acks and now - stream.acks[peer][1] < FOLLOWER_TIMEOUT]
        if not live:
            return
        _, peer = max(live)
        self._resume(stream, peer, now)
        # its link was slower than the writer when it went on its own, and no lone message
        # crossed in time since (it would have resumed then): a flight that a fast follower
        # had doubled would queue seconds of values for it over PUB before it showed slow
        stream.slow, stream.flight = True, 0
        log.info("remote link %s: a follower served on its own is the only one now: back "
                 "on PUB from value %d", topic_text(stream.name), stream.next_seq)

    def _serve_direct(self, stream: Stream) -> None:
        """Send each follower served on its own the newest message it has not had, if
        nothing sent to it is on the way; the values before it that it did not get are
        announced (SKIPPED) (lock held, on the loop's thread). Only once an ACK says it
        knows it is served so (``told``): one whose DIRECT was lost on the way still
        takes every value over PUB, and each sent here too crossed its slow link twice
        (the DIRECT is said again at the next heartbeat). Nor a message its ACK shows it
        has (PUB carried it before it took the DIRECT in)."""
        now = time.monotonic()
        for peer, direct in stream.direct.items():
            sent = direct.latest
            acked = stream.acks.get(peer, (-1, 0.0))[0]
            if sent is None or not direct.told or not direct.idle(acked):
                continue
            direct.latest = None
            direct.sent = max(direct.sent, acked)    # (what PUB carried: not announced)
            if sent.end <= direct.sent:
                continue
            if sent.first > direct.sent:
                direct.skips.append((direct.sent, sent.first))
                self._send_router(peer, SKIPPED, [stream.name, ANSWER.pack(
                    self.incarnation, direct.sent, sent.first - direct.sent)])
            self._send_router(peer, sent.kind, [stream.name, *sent.parts])
            direct.sent, direct.went = sent.end, now

    def flush(self) -> None:
        """Send everything published so far now (it goes soon anyway); waits for it."""
        self._loop.call(self._flush)

    def _flush(self) -> None:
        with self._lock:
            self._flush_locked()

    def _flush_locked(self) -> None:
        """Send what was published, in order (lock held, on the loop's thread)."""
        self._flush_due = False
        for name in list(self._filling):
            self._close_batch(self._streams[name])
        outbox, self._outbox = self._outbox, []
        direct = False
        for name, sent in outbox:
            self._send_pub(name, sent.kind, sent.parts)
            if sent.kind != SKIPPED and (followers := self._streams[name].direct):
                for one in followers.values():   # (the newest message: see "Slow followers")
                    if sent.end > one.sent:
                        one.latest = sent
                direct = True
        if self._loop.on_loop:                   # (the ROUTER is the loop thread's alone)
            for stream in self._streams.values():
                if stream.direct:
                    self._serve_direct(stream)
        elif direct and not self._flush_due:
            self._flush_due = True
            self._loop.submit(self._flush)

    def _send_pub(self, name: bytes, kind: int, parts: list[Any]) -> None:
        # topic first (SUB filters on it), then the sealed message, which holds the
        # topic again so that it is authenticated too
        send_message(self._pub, [name, *sealed_message(self._pub_sealer, kind, [name, *parts])])

    def _on_request(self, router: zmq.Socket) -> None:
        for _ in range(DRAIN_BATCH):
            try:
                peer, *frames = receive_message(router)
            except zmq.Again:
                return
            try:
                message = self._opener.open(frames)
            except Rejected:
                continue                         # counted by the opener
            try:
                self._answer(peer, message)
            except Rejected as exc:              # authentic, but refused all the same
                self._opener.rejected[exc.reason] += 1

    def _heartbeat(self) -> None:
        """Announce every topic's next sequence number: a follower that missed the last
        values of a burst learns of them here and asks for a repair."""
        with self._lock:
            self._flush_locked()                 # (what it announces has gone out first)
            now = time.monotonic()
            for name, stream in self._streams.items():
                # (before its DIRECT below: one sent after a RESUME would undo it)
                self._resume_alone(stream, now)  # (the fast one silent, or forgotten)
                self._send_pub(name, SYNC, [self._sync(stream)])
                # Their SYNC, and their mode. One silent for a while (its link cut, its
                # node frozen) is still served on its own: it has closed its SUB
                # connection and takes nothing over PUB until told RESUME, so forgotten
                # here it got nothing more, nor was anything counted, unless found slow
                # again (which takes a faster follower beside it). It leaves by saying
                # so (an ACK of -1), by a HELLO, or with its lost node (``forget``), and
                # goes back to PUB when told RESUME (in time again, or live and alone).
                for peer, direct in stream.direct.items():
                    self._send_router(peer, DIRECT, [name, ANSWER.pack(
                        self.incarnation, direct.start, direct.sent)])

    def _sync(self, stream: Stream) -> bytes:
        """A SYNC's body: the next sequence number, and how many values before it were
        not sent (a follower counts them dropped; it does not ask for them)."""
        skipped = stream.next_seq - stream.skip_from if stream.skip_from >= 0 else 0
        return ANSWER.pack(self.incarnation, stream.next_seq, skipped)

    def _answer(self, peer: Any, message: Any) -> None:
        if message.kind not in (HELLO, REPAIR, ACK) or len(message.frames) != 2 \
                or memoryview(message.frames[1]).nbytes != ASK.size:
            raise Rejected("unexpected")
        name = bytes(message.frames[0])
        first, last, to = ASK.unpack(message.frames[1])
        if to != self.incarnation and to != NOBODY:
            raise Rejected("other instance")    # meant for another replicator: a copy
        with self._lock:
            stream = self._streams.get(name)
            if stream is None:
                return                           # not (yet) published here: they retry
            if to == NOBODY:                    # who we are, and nothing else
                if message.kind == HELLO:
                    self._send_router(peer, WELCOME,
                                      [name, ANSWER.pack(self.incarnation, stream.next_seq, 0)])
                return
            peer_id = bytes(peer)
            if peer_id in stream.gone:           # its node was lost: see ``forget``
                raise Rejected("lost follower")
            if message.kind == ACK:
                now = time.monotonic()
                before = stream.flight_lead(now)
                direct = stream.direct.get(peer_id)
                if first < 0:                    # unfollowed: it holds nothing back now
                    stream.drop_follower(peer_id)
                else:
                    # (never back: an ACK sent before a RESUME came says less than it)
                    known = stream.acks.get(peer_id)
                    if known is None and peer_id not in stream.joined:
                        # Heard of first by an ACK: live before it knew whom to name (its
                        # HELLO named nobody), it repairs what its subscription missed;
                        # PUB carries to it what goes from here on (see ``flight_lead``).
                        self._flush_locked()
                        stream.joined[peer_id] = stream.next_seq
                    stream.acks[peer_id] = (max(first, known[0]) if known else first, now)
                    stream.hold(peer_id, first, last)
                    if direct is None:
                        if last & SERVED_DIRECT:     # its RESUME was lost on the way
                            self._resume_again(stream, peer_id, first)
                        if known is not None:        # (one heard of first here has had
                            self._pace(stream, before, now)   # nothing over PUB yet)
                        self._find_slow(stream, now)
                    elif last & LOSSLESS:            # (it must not drop now)
                        self._resume(stream, peer_id, now, first)
                    else:
                        if last & SERVED_DIRECT and first >= direct.start:
                            direct.told = True       # it took the DIRECT in: see Direct
                        if direct.sent > direct.start and first >= direct.sent \
                                and now - direct.went < FRESH_S / 2:
                            self._resume(stream, peer_id, now)   # a lone message, in time
                        else:
                            self._serve_direct(stream)
                self._resume_alone(stream, now)  # (the fast one may have unfollowed)
                stream.clear_until = 0           # (a lossless follower may have come)
                self._acked.notify_all()
            elif message.kind == HELLO:
                self._flush_locked()             # (all it may need is in the buffer)
                nxt = stream.next_seq
                # A HELLO repeated until its subscription is live, the replay an earlier
                # one asked for on its way: that is not sent again behind itself (on a
                # slow link each copy took the backlog's time again). One from a peer
                # never answered here (its first HELLO lost) is answered in full.
                again = bool(last & WAITING) and peer_id in stream.joined
                stream.direct.pop(peer_id, None)  # (subscribed: it follows over PUB again)
                stream.resumed.pop(peer_id, None)  # (it says what it needs)
                if not again:
                    stream.joined[peer_id] = nxt
                stream.acks[peer_id] = (first if first >= 0 else nxt, time.monotonic())
                stream.hold(peer_id, first if first >= 0 else nxt, last)
                stream.clear_until = 0           # a new follower: the window moved back
                # (an empty replay still says so; one whose subscription is live already
                # repairs what it missed: PUB carries the rest to it)
                replays = first >= 0 and not again and not last & LIVE
                self._send_router(peer, WELCOME,
                                  [name, ANSWER.pack(self.incarnation, nxt, int(replays))])
                self._send_pub(name, SYNC, [self._sync(stream)])
                if replays:
                    self._replay(peer, name, stream, first, nxt - 1)
            else:
                self._flush_locked()
                self._replay(peer, name, stream, first, last)

    def _replay(self, peer: Any, name: bytes, stream: Stream, first: int, last: int) -> None:
        """The messages holding values ``first..last`` from the buffer, then how many of
        those values are gone."""
        oldest = stream.replay[0].first if stream.replay else stream.next_seq
        gone = max(0, min(last + 1, oldest) - first)
        runs = list(stream.skips)
        if stream.skip_from >= 0:
            runs.append((stream.skip_from, stream.next_seq))
        direct = stream.direct.get(bytes(peer))
        resumed = stream.resumed.get(bytes(peer))
        if direct is not None:       # a follower served on its own: nor what it was not sent
            runs += [(min(first, direct.start), direct.start), *direct.skips]
        elif resumed is not None:    # back on PUB from there: the RESUME, ahead of this
            runs.append((min(first, resumed), resumed))     # answer, had it count those dropped
        for start, end in runs:                  # (not sent: never replayed, nor gone)
            if start <= last and end > first:
                self._send_router(peer, SKIPPED,
                                  [name, ANSWER.pack(self.incarnation, start, end - start)])
        own = direct is not None or resumed is not None
        for sent in stream.replay:
            if sent.first <= last and sent.end > first and not (
                    own and any(start <= sent.first and sent.end <= end for start, end in runs)):
                self._send_router(peer, sent.kind, [name, *sent.replayable()])
        self._send_router(peer, REPLAYED, [name, ANSWER.pack(self.incarnation, first, gone)])

    def _send_router(self, peer: Any, kind: int, parts: list[Any]) -> None:
        send_message(self._router, [peer, *sealed_message(self._router_sealer, kind, parts)])

    def close(self) -> None:
        """Send what is still queued, then close."""
        self._loop.close()
        with self._lock:
            self._flush_locked()
            self._pub.close(0)
        self._router.close(0)
