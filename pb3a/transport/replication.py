"""Remote links: an output's values replicated to other nodes over ZeroMQ PUB/SUB.

A ``Replicator`` sends the outputs of one process: each value is published once on
its output's topic, however many nodes (and inputs there) read it, and kept in a
bounded replay buffer. A ``Follower`` receives on one node: one SUB socket for all
the topics it follows, and a DEALER per sender for the hand-shake and repairs.

Every value carries (sender incarnation, topic, sequence number). The follower
delivers each topic's values in sequence order, exactly once:

- Slow joiners. A SUB socket misses what is published before its subscription
  reaches the publisher. So the follower says HELLO (topic, first sequence number
  it needs) on the DEALER until the publisher answers by publishing a SYNC on the
  topic; the first SYNC or value that arrives proves the subscription is live, and
  everything older is fetched from the replay buffer. No sleeping.
- Gaps (the publisher's high-water mark dropped values for a slow follower, or a
  reconnect lost some) are repaired the same way; values beyond a gap wait; a
  heartbeat (SYNC every 0.5 s with the next sequence number) reveals values lost at
  the end of a burst. What the replay buffer no longer holds is counted as a link
  failure, loudly.
- Flow control. Followers acknowledge (ACK) how far they are; a publisher more than
  ``WINDOW`` values ahead of its slowest live follower waits for it, briefly.
- Lossless followers. A follower whose receiver must not drop (a ``lossless`` link)
  says so in its HELLO and ACKs, and acknowledges only what its receiver has put
  through. Such a follower holds the publisher back for as long as the writer's
  timeout allows (then the write fails: ``RuntimeTimeout``), and the replay buffer
  keeps every value it has not acknowledged; it stops holding when it says so, or
  when the link to it is cut (``release``).
- Fencing. A follower accepts one incarnation per topic. Values from any other (a
  sender that was migrated away, or a stale restart) are counted and dropped.

Every message is sealed (``auth``) and opened before anything in it is decoded.
"""

from __future__ import annotations

import collections
import logging
import math
import secrets
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import zmq

from pb3a.errors import link_stuck
from pb3a.transport import codec
from pb3a.transport.addresses import bind_advertised
from pb3a.transport.auth import ClusterKey, Opener, Rejected, Sealer
from pb3a.transport.loop import SocketLoop

if TYPE_CHECKING:
    from collections.abc import Callable

log = logging.getLogger("pb3a.replication")

# message kinds
VALUE, SYNC, HELLO, REPAIR, WELCOME, REPLAYED, ACK, VALUES = 1, 2, 3, 4, 5, 6, 7, 8
_INFO = struct.Struct("<16sQdB")        # incarnation, sequence number, sent at (unix), codec kind
_ASK = struct.Struct("<qq")             # HELLO: first needed (-1: from now), flags; REPAIR:
                                        # first, last; ACK: delivered up to (exclusive, -1:
                                        # unfollowed), flags
LOSSLESS = 1                            # flag of HELLO and ACK: hold the publisher back
_ANSWER = struct.Struct("<16sqq")       # WELCOME: incarnation, next; REPLAYED: first, gone
_ENTRY = struct.Struct("<HI")           # VALUES: each entry's meta and payload lengths
BATCH_VALUES = 1024                     # small values of one topic sent as one message, at most
BATCH_BYTES = 1 << 20                   # ... and at most this many bytes of them
HWM = 10_000                            # messages queued per peer before ZeroMQ drops
MAX_MESSAGE = 256 * 1024 * 1024         # bytes; larger frames are refused by ZeroMQ itself
WINDOW = 2048                           # values a publisher may be ahead of its slowest follower
WINDOW_WAIT = 0.1                       # seconds it waits for acknowledgements, then goes on
ACK_EVERY = 256                         # a follower acknowledges after this many values ...
ACK_IDLE_S = 0.5                        # ... or this long after its last acknowledgement
ACK_BYTES = 4 * 1024 * 1024             # a lossless follower also after this many bytes
FOLLOWER_TIMEOUT = 3.0                  # silent this long: no longer holds a publisher back
SILENT_S = 2 * ACK_IDLE_S               # (a lossless follower: when a link to it is cut)
REPLAY_VALUES = 4096                    # per topic, at most ...
REPLAY_BYTES = 64 * 1024 * 1024         # ... and at most this many bytes
HELLO_EVERY = 0.05                      # seconds between unanswered HELLOs
HEARTBEAT_S = 0.5                       # how often a replicator announces its topics
DRAIN_BATCH = 1024                      # messages taken in before delivering them
ZERO_COPY_MIN = 64 * 1024               # frames at least this large are sent without a copy


def _name(topic: str) -> bytes:
    """A topic on the wire: NUL-terminated, because SUB sockets match prefixes."""
    return topic.encode() + b"\0"


def _topic(name: bytes) -> str:
    return name[:-1].decode()


def _send(sock: zmq.Socket, frames: list[Any]) -> None:
    """Send a multipart message: small frames copied (cheaper than a frame object),
    large ones zero-copy. (``send_multipart`` costs microseconds more per frame.)"""
    last = len(frames) - 1
    for index, frame in enumerate(frames):
        big = type(frame) is not bytes and memoryview(frame).nbytes >= ZERO_COPY_MIN
        sock.send(frame, zmq.SNDMORE if index < last else 0, copy=not big)


def _secure(sock: zmq.Socket, max_bytes: int = MAX_MESSAGE) -> zmq.Socket:
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.MAXMSGSIZE, max_bytes)
    sock.setsockopt(zmq.SNDHWM, HWM)
    sock.setsockopt(zmq.RCVHWM, HWM)
    return sock


# -- the sending side ---------------------------------------------------------------
@dataclass
class _Stream:
    """One published output: its next sequence number and its replay buffer."""

    next_seq: int = 0
    replay: collections.deque[tuple[int, list[Any], int]] = field(
        default_factory=collections.deque)      # (seq, [info, meta, payload], bytes)
    replay_bytes: int = 0
    acks: dict[bytes, tuple[int, float]] = field(default_factory=dict)  # peer -> (seq, when)
    holds: dict[bytes, int] = field(default_factory=dict)   # lossless followers: peer -> seq
    waits: int = 0                      # values whose publish waited for followers ...
    wait_s: float = 0.0                 # ... and the seconds they waited

    def acknowledged(self, now: float) -> int | None:
        """Where the slowest live follower is (None: nobody follows)."""
        live = [seq for seq, when in self.acks.values() if now - when < FOLLOWER_TIMEOUT]
        return min(live) if live else None

    def held(self) -> int | None:
        """Where the slowest lossless follower is, live or not (None: there is none)."""
        return min(self.holds.values()) if self.holds else None

    def room_for(self, size: int) -> bool:
        """Whether one more value of ``size`` bytes may go without running ``WINDOW``
        values ahead of a lossless follower, or pushing out of the replay buffer a value
        one has not acknowledged."""
        held = self.held()
        if held is None:
            return True
        if self.next_seq - held >= WINDOW:
            return False
        replay = self.replay
        full = len(replay) >= REPLAY_VALUES or self.replay_bytes + size > REPLAY_BYTES
        return not (full and replay and replay[0][0] >= held)

    def hold(self, peer: bytes, seq: int, flags: int) -> None:
        """A follower said how far it is and whether it is lossless."""
        if flags & LOSSLESS:
            self.holds[peer] = seq
        else:
            self.holds.pop(peer, None)


class Replicator:
    """Publishes the outputs of one process (PUB) and answers hand-shakes and repairs
    (ROUTER) on its own thread. ``publish`` may be called from any thread."""

    def __init__(self, key: ClusterKey, host: str = "127.0.0.1", *, epoch: int = 0,
                 max_bytes: int = MAX_MESSAGE, context: zmq.Context | None = None) -> None:
        self.incarnation = secrets.token_bytes(16)
        self._max_bytes = max_bytes
        self._context = context or zmq.Context.instance()
        self._pub = _secure(self._context.socket(zmq.PUB), max_bytes)
        self._router = _secure(self._context.socket(zmq.ROUTER), max_bytes)
        # (host: where the readers' nodes reach this one; see ``addresses``)
        self.data_address = bind_advertised(self._pub, host)
        self.control_address = bind_advertised(self._router, host)
        self._pub_sealer = Sealer(key, epoch)
        self._router_sealer = Sealer(key, epoch)
        self._opener = Opener(key, epoch=epoch, max_bytes=max_bytes)
        self._streams: dict[bytes, _Stream] = {}
        self._lock = threading.Lock()            # the PUB socket, the streams, the outbox
        self._acked = threading.Condition(self._lock)
        self._outbox: list[tuple[bytes, list[Any]]] = []   # published, not sent yet
        self._loop = SocketLoop("pb3a-replicator", self._context)
        self._loop.register(self._router, self._on_request)
        self._loop.every(HEARTBEAT_S, self._heartbeat)

    @property
    def rejected(self) -> collections.Counter[str]:
        """Messages refused on the control socket, by reason."""
        return self._opener.rejected

    def add(self, topic: str, next_seq: int = 0) -> None:
        """Start publishing ``topic``; ``next_seq`` continues a migrated stream."""
        with self._lock:
            self._streams.setdefault(_name(topic), _Stream(next_seq))

    def sequence(self, topic: str) -> int:
        """The sequence number the next value on ``topic`` will get."""
        with self._lock:
            return self._streams[_name(topic)].next_seq

    def unacknowledged(self, topic: str) -> int:
        """How many values of ``topic`` its least advanced follower, live or silent, has
        not acknowledged (a follower on a lost node: what it never confirmed)."""
        with self._lock:
            stream = self._streams.get(_name(topic))
            if stream is None or not stream.acks:
                return 0
            return max(0, stream.next_seq - min(seq for seq, _ in stream.acks.values()))

    def counter(self, topic: str) -> Any:
        """What counts the publishes of ``topic`` that waited (``waits``, ``wait_s``)."""
        with self._lock:
            return self._streams[_name(topic)]

    def release(self, topic: str, silent_for: float = 0.0) -> None:
        """Stop waiting for the lossless followers of ``topic`` that have been silent
        for ``silent_for`` seconds or more (0: all of them): a link to them was cut."""
        with self._lock:
            stream = self._streams.get(_name(topic))
            if stream is None:
                return
            now = time.monotonic()
            for peer in list(stream.holds):
                if now - stream.acks.get(peer, (0, -math.inf))[1] >= silent_for:
                    del stream.holds[peer]
            self._acked.notify_all()

    def publish(self, topic: str, value: Any, timeout: float = WINDOW_WAIT) -> int:
        """Send one value; returns its sequence number.

        Flow control: a publisher more than ``WINDOW`` values ahead of its slowest
        follower waits for it (up to ``WINDOW_WAIT``, then goes on and lets the repair
        or the link-failure count deal with it), so a burst never overruns the
        high-water marks. A lossless follower holds it back up to ``timeout`` (the
        writer's), and then the publish raises RuntimeTimeout: nothing is sent. An
        array is copied once (the writer may reuse it at once); from there on its
        bytes go out as a zero-copy frame and stay in the replay buffer as they are."""
        kind, meta, payload = codec.encode(value)
        nbytes = codec.payload_size(kind, payload)
        if nbytes + 1024 > self._max_bytes:
            raise ValueError(
                f"a value of {nbytes} bytes exceeds the {self._max_bytes}-byte message "
                "limit of remote links; raise the limit")
        if kind == codec.ARRAY and payload is value:
            payload = payload.copy()
        name = _name(topic)
        size = nbytes + 64
        with self._lock:
            stream = self._streams[name]
            started = self._await_holds(stream, topic, size, timeout) if stream.holds else None
            deadline = None
            while (acked := stream.acknowledged(time.monotonic())) is not None \
                    and stream.next_seq - acked >= WINDOW:
                if deadline is None:
                    deadline = time.monotonic() + WINDOW_WAIT
                    started = started or time.monotonic()
                if not self._acked.wait(deadline - time.monotonic()) \
                        and time.monotonic() >= deadline:
                    break
            if started is not None:
                stream.waits += 1
                stream.wait_s += time.monotonic() - started
            seq = stream.next_seq
            stream.next_seq += 1
            parts = [_INFO.pack(self.incarnation, seq, time.time(), kind), meta, payload]
            stream.replay.append((seq, parts, size))
            stream.replay_bytes += size
            held = stream.held()
            while stream.replay and (len(stream.replay) > REPLAY_VALUES
                                     or stream.replay_bytes > REPLAY_BYTES):
                if held is not None and stream.replay[0][0] >= held:
                    break                        # a lossless follower still needs it
                stream.replay_bytes -= stream.replay.popleft()[2]
            # The loop thread sends: what piles up meanwhile goes as one message.
            self._outbox.append((name, parts))
            wake = len(self._outbox) == 1
        if wake:
            self._loop.submit(self._flush)
        return seq

    def _await_holds(self, stream: _Stream, topic: str, size: int,
                     timeout: float) -> float | None:
        """Wait (lock held, released while waiting) until the lossless followers leave
        room for one more value (``_Stream.room_for``); when it waited, since when.
        RuntimeTimeout after ``timeout`` seconds."""
        started = None
        while not stream.room_for(size):
            now = time.monotonic()
            if started is None:
                started = now
            left = started + timeout - now
            if left <= 0:
                stream.waits += 1
                stream.wait_s += now - started
                raise link_stuck(topic, timeout)
            self._acked.wait(left)
        return started

    def flush(self) -> None:
        """Send everything published so far now (it goes soon anyway); waits for it."""
        self._loop.call(self._flush)

    def _flush(self) -> None:
        with self._lock:
            self._flush_locked()

    def _flush_locked(self) -> None:
        """Send the outbox in order: runs of small values of one topic as one VALUES
        message (a seal and a send for many values), large ones as zero-copy frames."""
        outbox, self._outbox = self._outbox, []
        budget = min(BATCH_BYTES, self._max_bytes // 2)
        name, run, run_bytes = b"", [], 0
        for entry_name, parts in outbox:
            size = memoryview(parts[2]).nbytes
            large = size >= ZERO_COPY_MIN
            if run and (large or entry_name != name or len(run) >= BATCH_VALUES
                        or run_bytes + size > budget):
                self._send_run(name, run)
                run, run_bytes = [], 0
            if large:
                self._send_pub(entry_name, VALUE, parts)
            else:
                name = entry_name
                run.append(parts)
                run_bytes += size
        if run:
            self._send_run(name, run)

    def _send_run(self, name: bytes, run: list[list[Any]]) -> None:
        if len(run) == 1:
            self._send_pub(name, VALUE, run[0])
            return
        blob = []
        for info, meta, payload in run:
            body = memoryview(payload).cast("B")
            blob += (_ENTRY.pack(len(meta), body.nbytes), info, meta, body)
        self._send_pub(name, VALUES, [b"".join(blob)])

    def _send_pub(self, name: bytes, kind: int, parts: list[Any]) -> None:
        # topic first (SUB filters on it), then the sealed message, which holds the
        # topic again so that it is authenticated too
        _send(self._pub, [name, *self._pub_sealer.seal(kind, [name, *parts])])

    def _on_request(self, router: zmq.Socket) -> None:
        for _ in range(DRAIN_BATCH):
            if not router.poll(0):
                return
            peer, *frames = router.recv_multipart(copy=False)
            try:
                self._answer(peer, self._opener.open(frames))
            except Rejected:
                continue                         # counted by the opener

    def _heartbeat(self) -> None:
        """Announce every topic's next sequence number: a follower that missed the last
        values of a burst learns of them here and asks for a repair."""
        with self._lock:
            self._flush_locked()                 # (what it announces has gone out first)
            for name, stream in self._streams.items():
                self._send_pub(name, SYNC, [_ANSWER.pack(self.incarnation, stream.next_seq, 0)])

    def _answer(self, peer: Any, message: Any) -> None:
        if message.kind not in (HELLO, REPAIR, ACK) or len(message.frames) != 2:
            raise Rejected("unexpected")
        name = bytes(message.frames[0])
        first, last = _ASK.unpack(message.frames[1])
        with self._lock:
            stream = self._streams.get(name)
            if stream is None:
                return                           # not (yet) published here: they retry
            peer_id = bytes(peer)
            if message.kind == ACK:
                if first < 0:                    # unfollowed: it holds nothing back now
                    stream.acks.pop(peer_id, None)
                    stream.holds.pop(peer_id, None)
                else:
                    stream.acks[peer_id] = (first, time.monotonic())
                    stream.hold(peer_id, first, last)
                self._acked.notify_all()
            elif message.kind == HELLO:
                self._flush_locked()
                nxt = stream.next_seq
                stream.acks[peer_id] = (first if first >= 0 else nxt, time.monotonic())
                stream.hold(peer_id, first if first >= 0 else nxt, last)
                self._send_router(peer, WELCOME, [name, _ANSWER.pack(self.incarnation, nxt, 0)])
                self._send_pub(name, SYNC, [_ANSWER.pack(self.incarnation, nxt, 0)])
                if first >= 0:                   # (an empty replay still says so)
                    self._replay(peer, name, stream, first, nxt - 1)
            else:
                self._replay(peer, name, stream, first, last)

    def _replay(self, peer: Any, name: bytes, stream: _Stream, first: int, last: int) -> None:
        """Values ``first..last`` from the buffer, then how many of them are gone."""
        oldest = stream.replay[0][0] if stream.replay else stream.next_seq
        gone = max(0, min(last + 1, oldest) - first)
        for seq, parts, _ in stream.replay:
            if first <= seq <= last:
                self._send_router(peer, VALUE, [name, *parts])
        self._send_router(peer, REPLAYED, [name, _ANSWER.pack(self.incarnation, first, gone)])

    def _send_router(self, peer: Any, kind: int, parts: list[Any]) -> None:
        _send(self._router, [peer, *self._router_sealer.seal(kind, parts)])

    def close(self) -> None:
        """Send what is still queued, then close."""
        self._loop.close()
        with self._lock:
            self._flush_locked()
            self._pub.close(0)
        self._router.close(0)


# -- the receiving side -------------------------------------------------------------
@dataclass
class _Follow:
    """What a follower knows of one topic."""

    topic: bytes
    control: zmq.Socket                       # DEALER to the topic's replicator
    next_seq: int                             # the next sequence number to deliver (-1: any)
    incarnation: bytes | None                 # the accepted sender (None: the first to answer)
    live: bool = False                        # a SYNC or value came through the SUB socket
    # (value, sent at, bytes) of values beyond a gap, or waiting for delivery
    held: dict[int, tuple[Any, float, int]] = field(default_factory=dict)
    asked: float = 0.0                        # when we last sent HELLO or REPAIR
    repairing: bool = False
    announced: int = -1                       # the sender's next sequence number, as last heard
    acked: int = -1                           # what we last acknowledged
    acked_at: float = 0.0
    held_back: int = 0                        # delivered values the receiver holds back
    moved_bytes: int = 0                      # bytes delivered ...
    acked_bytes: int = 0                      # ... as of the last acknowledgement

    @property
    def through(self) -> int:
        """The sequence number up to which the receiver has put values through."""
        return self.next_seq - self.held_back
    ready: threading.Event = field(default_factory=threading.Event)   # live, start known


class Follower:
    """Receives the topics one node follows and delivers each in order, once.

    ``deliver(topic, values, sent_at)`` is called on the follower's thread; ``sent_at``
    is when the newest value was written, in the sender's wall-clock seconds. It may
    return how many of the topic's newest values it holds back, not put through yet (a
    full lossless receiver), and report later with ``release``; acknowledgements cover
    only what it put through.
    Counters: ``link_failures`` (values lost for good, per topic), ``fenced`` (values
    from a sender that is not the accepted one), ``duplicates`` (dropped)."""

    def __init__(self, key: ClusterKey, deliver: Callable[[str, list[Any], float], None], *,
                 epoch: int = 0, max_bytes: int = MAX_MESSAGE,
                 context: zmq.Context | None = None) -> None:
        self._key = key
        self._deliver = deliver
        self._max_bytes = max_bytes
        self._context = context or zmq.Context.instance()
        self._sub = _secure(self._context.socket(zmq.SUB), max_bytes)
        self._opener = Opener(key, epoch=epoch, max_bytes=max_bytes)
        self._sealer = Sealer(key, epoch)        # used only on the follower's thread
        self._follows: dict[bytes, _Follow] = {}
        self._lossless: set[bytes] = set()       # topics whose receiver must not drop
        self._controls: dict[str, zmq.Socket] = {}   # control address -> DEALER
        self._connected: set[str] = set()
        self.link_failures: collections.Counter[str] = collections.Counter()
        self.fenced: collections.Counter[str] = collections.Counter()
        self.duplicates: collections.Counter[str] = collections.Counter()
        self._progress = threading.Condition()   # notified after every delivery
        self._loop = SocketLoop("pb3a-follower", self._context)
        self._loop.register(self._sub, self._on_data)
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
        self._loop.call(lambda: self._follow(_name(topic), data_address, control_address,
                                             from_seq, incarnation))

    def wait_ready(self, topic: str, timeout: float) -> bool:
        """Block until the hand-shake for ``topic`` is done: from then on nothing
        written is missed. False if it did not finish within ``timeout``."""
        follow = self._follows.get(_name(topic))
        return follow is not None and follow.ready.wait(timeout)

    def wait_delivered(self, topic: str, seq: int, timeout: float) -> bool:
        """Block until every value of ``topic`` before ``seq`` has been delivered (and put
        through by the receiver)."""
        name = _name(topic)
        with self._progress:
            return self._progress.wait_for(
                lambda: (f := self._follows.get(name)) is None or f.through >= seq, timeout)

    def unfollow(self, topic: str) -> None:
        self._loop.call(lambda: self._unfollow(_name(topic)))

    def missing(self, topic: str) -> int:
        """How many values of ``topic`` the sender announced, or sent beyond a gap, that
        were not delivered: what is lost if it is gone for good."""
        def count() -> int:
            follow = self._follows.get(_name(topic))
            if follow is None or follow.next_seq < 0:
                return 0
            newest = max(follow.announced, max(follow.held, default=-1) + 1)
            return max(0, newest - follow.next_seq)
        return self._loop.call(count)

    def set_lossless(self, topic: str, lossless: bool) -> None:
        """Whether ``topic``'s receiver must not drop: then the sender is told (HELLO,
        ACK) to wait for it and to keep what it has not acknowledged."""
        self._loop.call(lambda: self._set_lossless(_name(topic), lossless))

    def release(self, topic: str, held_back: int) -> None:
        """The receiver put values through: it now holds back ``held_back`` of ``topic``'s
        newest ones."""
        self._loop.call(lambda: self._release(_name(topic), held_back))

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
        if data not in self._connected:
            self._sub.connect(data)
            self._connected.add(data)
        dealer = self._controls.get(control)
        if dealer is None:
            dealer = _secure(self._context.socket(zmq.DEALER), self._max_bytes)
            dealer.connect(control)
            self._controls[control] = dealer
            self._loop.register(dealer, self._on_control)
        old = self._follows.get(name)
        if old is None:
            self._sub.setsockopt(zmq.SUBSCRIBE, name)
        elif from_seq < 0 and incarnation in (None, old.incarnation):
            from_seq = old.next_seq               # the same sender: go on where we are
        self._follows[name] = _Follow(name, dealer, from_seq, incarnation)
        self._hello(self._follows[name])

    def _unfollow(self, name: bytes) -> None:
        follow = self._follows.pop(name, None)
        if follow is not None:
            self._sub.setsockopt(zmq.UNSUBSCRIBE, name)
            if name in self._lossless:           # the sender no longer waits for us
                self._ask(follow, ACK, -1, 0)
        self._lossless.discard(name)

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

    def _hello(self, follow: _Follow) -> None:
        follow.asked = time.monotonic()
        follow.repairing = follow.next_seq >= 0   # the answer replays what we miss
        self._ask(follow, HELLO, follow.next_seq, self._flags(follow))

    def _ask(self, follow: _Follow, kind: int, first: int, last: int) -> None:
        _send(follow.control, self._sealer.seal(kind, [follow.topic, _ASK.pack(first, last)]))

    # -- the follower's thread --------------------------------------------------
    def _on_data(self, sock: zmq.Socket) -> None:
        self._drain(sock, live=True)

    def _on_control(self, sock: zmq.Socket) -> None:
        self._drain(sock, live=False)

    def _drain(self, sock: zmq.Socket, live: bool) -> None:
        """Take in what has arrived (a bounded batch), then deliver per topic at once."""
        touched: dict[bytes, _Follow] = {}
        for _ in range(DRAIN_BATCH):
            if not sock.poll(0):
                break
            frames = sock.recv_multipart(copy=False)
            if live:
                if len(frames) < 2:
                    self._opener.rejected["frame count"] += 1
                    continue
                frames = frames[1:]              # the topic prefix (authenticated inside)
            try:
                follow = self._handle(self._opener.open(frames), live)
            except Rejected:
                continue
            except Exception:
                log.exception("follower: a message could not be handled")
                continue
            if follow is not None:
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
            incarnation, nxt, _ = _ANSWER.unpack(message.frames[1])
            if not self._accept(follow, incarnation):
                return None
            if follow.next_seq < 0:             # from now on: what came earlier goes
                follow.next_seq = nxt
                for seq in [seq for seq in follow.held if seq < nxt]:
                    del follow.held[seq]
            follow.announced = max(follow.announced, nxt)
            follow.live = follow.live or live
            return follow
        if message.kind == VALUE:
            info, meta, payload = message.frames[1:4]
            return follow if self._take(follow, info, bytes(meta), payload, live) else None
        if message.kind == VALUES:
            blob, at, taken = memoryview(message.frames[1]), 0, False
            while at < blob.nbytes:
                if at + _ENTRY.size + _INFO.size > blob.nbytes:
                    raise Rejected("malformed")
                meta_len, size = _ENTRY.unpack_from(blob, at)
                start = at + _ENTRY.size + _INFO.size
                at = start + meta_len + size
                if at > blob.nbytes:
                    raise Rejected("malformed")
                taken |= self._take(follow, blob[start - _INFO.size:start],
                                    bytes(blob[start:start + meta_len]),
                                    blob[start + meta_len:at], live)
            return follow if taken else None
        if message.kind == REPLAYED:
            incarnation, first, gone = _ANSWER.unpack(message.frames[1])
            if not self._accept(follow, incarnation):
                return None
            follow.repairing = False
            if gone and follow.next_seq < first + gone:
                lost = first + gone - follow.next_seq
                self.link_failures[_topic(follow.topic)] += lost
                log.error("remote link %s lost %d values (gone from the sender's replay "
                          "buffer)", _topic(follow.topic), lost)
                follow.next_seq = first + gone
            return follow
        raise Rejected("unexpected")

    def _take(self, follow: _Follow, info: Any, meta: bytes, payload: Any, live: bool) -> bool:
        """Hold one value for in-order delivery; False if it is fenced or a duplicate."""
        incarnation, seq, sent_at, kind = _INFO.unpack(info)
        if not self._accept(follow, incarnation):
            return False
        follow.live = follow.live or live
        # (joined "from now": values wait until the hand-shake says where now is)
        if 0 <= seq < follow.next_seq or seq in follow.held:
            self.duplicates[_topic(follow.topic)] += 1
            return False
        follow.held[seq] = (codec.decode_owned(kind, meta, payload), sent_at,
                            memoryview(payload).nbytes)
        return True

    def _accept(self, follow: _Follow, incarnation: bytes) -> bool:
        if follow.incarnation is None:
            follow.incarnation = incarnation
        if incarnation != follow.incarnation:
            self.fenced[_topic(follow.topic)] += 1
            return False
        return True

    def _advance(self, follow: _Follow) -> None:
        """Deliver what is in order; ask for a repair when a gap blocks the rest."""
        if follow.live and follow.next_seq >= 0:
            follow.ready.set()
        values, sent_at, size, seq = [], 0.0, 0, follow.next_seq
        while seq in follow.held:
            value, sent_at, nbytes = follow.held.pop(seq)
            values.append(value)
            size += nbytes
            seq += 1
        if values:
            held_back = 0
            try:
                held_back = self._deliver(_topic(follow.topic), values, sent_at) or 0
            finally:
                with self._progress:             # (one step: see wait_delivered)
                    follow.next_seq, follow.held_back = seq, held_back
                    self._progress.notify_all()
            follow.moved_bytes += size
            if self._ack_due(follow):
                self._acknowledge(follow)
        # a gap before held values, or behind what the sender announced (values lost
        # at the end of a burst show up only in its heartbeat)
        last = min(follow.held) - 1 if follow.held else follow.announced - 1
        if follow.live and not follow.repairing and 0 <= follow.next_seq <= last:
            follow.repairing = True
            follow.asked = time.monotonic()
            self._ask(follow, REPAIR, follow.next_seq, last)

    def _ack_due(self, follow: _Follow) -> bool:
        """Every ACK_EVERY values; a lossless follower also every ACK_BYTES bytes (the
        sender keeps what it did not acknowledge, in a replay buffer of bounded bytes)."""
        through = follow.through
        if through - follow.acked >= ACK_EVERY:
            return True
        return (follow.topic in self._lossless and through > follow.acked
                and follow.moved_bytes - follow.acked_bytes >= ACK_BYTES)

    def _acknowledge(self, follow: _Follow) -> None:
        """Tell the publisher how far we are: it may run at most WINDOW values ahead."""
        follow.acked, follow.acked_at = follow.through, time.monotonic()
        follow.acked_bytes = follow.moved_bytes
        self._ask(follow, ACK, follow.acked, self._flags(follow))

    def _retry(self) -> None:
        now = time.monotonic()
        for follow in self._follows.values():
            if follow.live and follow.next_seq >= 0 and (
                    follow.through != follow.acked or now - follow.acked_at > ACK_IDLE_S):
                self._acknowledge(follow)
            if now - follow.asked < HELLO_EVERY:
                continue
            if not follow.live:
                self._hello(follow)              # the slow-joiner hand-shake
            elif follow.repairing and now - follow.asked > 1.0:
                follow.repairing = False         # lost request: ask again
                self._advance(follow)

    def close(self) -> None:
        self._loop.close()
        self._sub.close(0)
        for dealer in self._controls.values():
            dealer.close(0)

