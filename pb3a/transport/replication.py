"""Remote links: an output's values replicated to other nodes over ZeroMQ PUB/SUB.

A ``Replicator`` sends the outputs of one process: each value is published once on
its output's topic, however many nodes (and inputs there) read it, and kept in a
bounded replay buffer. A ``Follower`` receives on one node: per sender, a SUB socket
for the topics it follows from it and a DEALER for the hand-shake and repairs, both
closed once no topic comes from that sender.

Every value carries (sender incarnation, topic, sequence number). Values published
while the previous ones are being sent travel together: small ones as one VALUES
message (first sequence number and count in its header, the values pickled as one
list: one seal, one send and one unpickling for up to ``BATCH_VALUES`` of them),
large ones (``ZERO_COPY_MIN`` bytes and more) each as a VALUE message whose payload
is a zero-copy frame, sealed on its own (below). The follower delivers each topic's
values in sequence order, exactly once:

- Slow joiners. A SUB socket misses what is published before its subscription
  reaches the publisher. So the follower says HELLO (topic, first sequence number
  it needs) on the DEALER until the publisher answers by publishing a SYNC on the
  topic; the first SYNC or value that arrives proves the subscription is live, and
  everything older is fetched from the replay buffer. No sleeping. Its first HELLO
  asks for that replay; the ones it repeats (every ``HELLO_EVERY``) say WAITING and
  are answered with a WELCOME and a SYNC only (in full by a publisher that never
  answered that follower: its first HELLO was lost), so a replay crossing a slow link
  is not sent again behind itself at each repeat. A replay not coming (nothing of it
  for as long as a repair waits, below) is asked again, in full.
- Gaps (the publisher's high-water mark dropped values for a slow follower, or a
  reconnect lost some) are repaired the same way; values beyond a gap wait; a
  heartbeat (SYNC every 0.5 s with the next sequence number) reveals values lost at
  the end of a burst. A repair re-sends whole messages: what of them was delivered
  already is counted as duplicates and dropped. What the replay buffer no longer
  holds is counted as a link failure, loudly. A repair not answered is asked again
  after ``REPAIR_RETRY_S``, then after twice as long each time (on a slow link the
  answer itself takes seconds to cross, and each request sends it again); each value
  of the answer that comes (and a WELCOME saying a replay follows) restarts the wait,
  and only the REPLAYED of the last request ends it.
- Flow control. Followers acknowledge (ACK) how far they are; a publisher more than
  ``WINDOW`` values or ``WINDOW_BYTES`` bytes ahead of its slowest live follower waits
  for it, briefly. The replay buffer holds twice the bytes of that window: everything
  a live follower may still need, and a bounded number of large values alive (the
  fewer, the warmer the memory the next one is copied into).
- Slow links. A dropping link (no lossless follower) slower than its writer must not
  queue at the writer: ZeroMQ counts its queue in messages, so large values piled up
  there by the hundred MiB and arrived ever later (tens of seconds). So the publisher
  keeps at most ``flight`` bytes on the way to its lead follower (the most advanced
  live one: a slower one beside it is not held to it): ``FLIGHT_START`` at first,
  doubled at each acknowledgement of a message that went less than ``FRESH_S / 2``
  ago, up to ``WINDOW_BYTES``. A value that does not fit waits for an acknowledgement
  while what is on the way is fresh; once the oldest of it went ``FRESH_S`` ago, or
  an acknowledgement comes that late, the link is *slow*: a message goes only when
  nothing is on the way, and the others are not sent (nor sealed, nor kept), without
  waiting. The values not sent are announced (SKIPPED before the next message that
  goes, a SYNC's count, a repair's answer): the follower counts them ``dropped`` and
  never asks for them. A link is not slow once a lone message is acknowledged within
  ``FRESH_S / 2``. So a `latest` reader gets a value about one message's crossing
  old, and the writer holds one message for the link.
- Slow followers. The flight follows the lead follower, and a PUB socket sends every
  message to every subscriber, queued per peer in messages: a slower follower beside
  a fast one had every value queued for it (hundreds of MiB, tens of seconds late),
  and flow control held the writer to it. So a live dropping follower behind another
  whose oldest message on the way went ``FRESH_S`` ago (once it has taken in what its
  hand-shake replayed: those went long ago) is served on its own (DIRECT):
  it closes its SUB connection (what PUB still queued for it is freed with it; an
  unsubscription would leave that queue to cross the slow link first) and counts the
  values it did not get before the switch dropped; the publisher sends it the newest
  message over its control connection whenever nothing sent to it there is on the
  way, the values before it announced not sent (SKIPPED), and leaves it out of flow
  control and of the flight. Its queue at the ROUTER is bounded so (one message of
  values, small notices), and a ROUTER never blocks: it drops for a peer at its
  high-water mark (ROUTER_MANDATORY is not set). A DIRECT every heartbeat is its SYNC
  (how far it was sent) and says its mode again, also while it is silent (its link
  cut): it takes nothing over PUB until told RESUME. Once a lone message is acknowledged
  within ``FRESH_S / 2`` it goes back to PUB (RESUME): it subscribes, and what was
  published before its subscription took is counted dropped, not replayed.
- Lossless followers. A follower whose receiver must not drop (a ``lossless`` link)
  says so in its HELLO and ACKs, and acknowledges only what its receiver has put
  through. Such a follower holds the publisher back for as long as the writer's
  timeout allows (then the write fails: ``RuntimeTimeout``), and the replay buffer
  keeps every value it has not acknowledged; it stops holding when it says so, or
  when the link to it is cut (``release``).
- Fencing. A follower accepts one incarnation per topic. Values from any other (a
  sender that was migrated away, or a stale restart) are counted and dropped.
- Followers of lost nodes. A node's follower has one id at every replicator
  (``follower_id``: the node and its admission, its node epoch), by which acknowledgements
  and lossless holds are kept. When a reader's node is lost, the launcher asks the
  writer what that node's follower never acknowledged (``forget``): only its own
  acknowledgement counts (the least advanced follower's, a node lost earlier's left
  behind, said 1000 values lost of a node that had acknowledged them all). The follower
  is forgotten then: it holds nothing back, and what it says later (its node cut off,
  not dead) is refused, counted (``rejected["lost follower"]``). A node that rejoins
  has another id.
- Destinations. HELLO, REPAIR and ACK name the replicator they are for, by its
  incarnation (as control requests name their server's instance), so a copy captured
  on the wire and sent to another replicator within the freshness window is refused
  there (counted, ``rejected["other instance"]``), never taken as a follower's. A
  follower that does not know the incarnation yet (it learns it from the first
  WELCOME, SYNC or value) names nobody; such a HELLO is answered with a WELCOME and
  nothing else, and the follower says HELLO again at once, naming it.

Every message is sealed (``auth``) and opened before anything in it is decoded. A
large payload is sealed on its own at write time (``auth.Payloads``): encrypted with
AES-GCM straight from the writer's memory into the buffer that goes on the wire, one
pass that is both the copy value semantics need and the authentication, bound to what
it is (topic, incarnation, sequence number, kind, meta); its VALUE message carries the
payload's nonce and tag, which the message's own tag covers, so the message tag is
computed over a few dozen bytes instead of the whole payload again. The follower
decrypts it straight into where it lands (the reader's ring slot, when the receiver
offers one: ``land``), so checking and landing are one pass too; a payload whose tag
fails is refused and counted (``rejected["bad payload tag"]``) like any message, the
slot it was decrypted into is freed, and the gap is repaired like any lost message.
Only the next value in order lands in a slot (see ``_handle``). On this 2-core host
that took a 1 MiB array's CPU from about 530 us to about 500 (``bench/link_cpu.py``),
and the link from 0.65x to 0.80x raw pyzmq (``bench/local_link.py --remote``).
"""

from __future__ import annotations

import collections
import hashlib
import logging
import math
import pickle
import secrets
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import zmq

from pb3a.errors import link_stuck
from pb3a.transport import codec
from pb3a.transport.addresses import bind_advertised, numeric
from pb3a.transport.auth import PAYLOAD_TAG, ClusterKey, Opener, Payloads, Rejected, Sealer
from pb3a.transport.heap import keep_freed_buffers
from pb3a.transport.loop import SocketLoop
from pb3a.transport.ring import RingSize, check_fits

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from pb3a.transport.ring import Landed

log = logging.getLogger("pb3a.replication")

# message kinds
VALUE, SYNC, HELLO, REPAIR, WELCOME, REPLAYED, ACK, VALUES, SKIPPED = 1, 2, 3, 4, 5, 6, 7, 8, 9
DIRECT, RESUME = 10, 11                 # a slow follower beside a fast one: see "Slow followers"
_INFO = struct.Struct("<16sQdBQ16s")    # VALUE: incarnation, sequence number, sent at (unix),
                                        # codec kind, payload nonce counter, payload tag
_BATCH = struct.Struct("<16sQId")       # VALUES: incarnation, first sequence number, count,
                                        # sent at (unix: when the first was written)
_ASK = struct.Struct("<qq16s")          # HELLO: first needed (-1: from now), flags; REPAIR:
                                        # first, last; ACK: delivered up to (exclusive, -1:
                                        # unfollowed), flags; then the incarnation of the
                                        # replicator it is for (_NOBODY: not known yet)
_NOBODY = bytes(16)
LOSSLESS = 1                            # flag of HELLO and ACK: hold the publisher back
WAITING = 2                             # flag of HELLO: the replay an earlier one asked for
                                        # is on its way: answer WELCOME and SYNC only
_ANSWER = struct.Struct("<16sqq")       # WELCOME: incarnation, next, a replay follows (1)
                                        # or not (0); REPLAYED: first, gone;
                                        # SKIPPED: first, count; SYNC: next, skipped before it;
                                        # DIRECT: from, next; RESUME: from, 0
PLAIN = 0                               # a VALUES entry that is the value itself
BATCH_VALUES = 1024                     # small values of one topic sent as one message, at most
BATCH_BYTES = 1 << 20                   # ... and at most this many bytes of them
HWM = 10_000                            # messages queued per peer before ZeroMQ drops
MAX_MESSAGE = 256 * 1024 * 1024         # bytes; larger frames are refused by ZeroMQ itself
WINDOW = 2048                           # values a publisher may be ahead of its slowest follower
WINDOW_BYTES = 16 * 1024 * 1024         # ... and bytes of values (see ``Replicator.sink``)
WINDOW_WAIT = 0.1                       # seconds it waits for acknowledgements, then goes on
ACK_EVERY = 256                         # a follower acknowledges after this many values ...
ACK_IDLE_S = 0.5                        # ... or this long after its last acknowledgement
ACK_BYTES = WINDOW_BYTES // 2           # ... or after this many bytes
FOLLOWER_TIMEOUT = 3.0                  # silent this long: no longer holds a publisher back
SILENT_S = 2 * ACK_IDLE_S               # (a lossless follower: when a link to it is cut)
REPLAY_VALUES = 4096                    # per topic, at most ...
REPLAY_BYTES = 2 * WINDOW_BYTES         # ... and at most this many bytes (the newest message
                                        # is always kept, however large)
HELLO_EVERY = 0.05                      # seconds between unanswered HELLOs
REPAIR_RETRY_S = 1.0                    # a repair not answered this long is asked again ...
REPAIR_RETRY_MAX_S = 8.0                # ... after twice as long each time, up to this: a
                                        # repair asked as a link went down is asked again
                                        # within it once the link is back
HEARTBEAT_S = 0.5                       # how often a replicator announces its topics
LINGER_MS = 500                         # a closed DEALER's last messages may still go
PEER_PING_MS = 1000                     # each connection pings its peer this often ...
PEER_TIMEOUT_MS = 5000                  # ... and a sender's is closed when it hears nothing
                                        # this long (see ``_secure``)
DRAIN_BATCH = 1024                      # messages taken in before delivering them
ZERO_COPY_MIN = 64 * 1024               # frames at least this large are sent without a copy
FLIGHT_START = 256 * 1024               # bytes on the way to a dropping link at first (it doubles
                                        # at each timely acknowledgement, up to WINDOW_BYTES)
FRESH_S = 0.5                           # a value not acknowledged this long after it went: the
                                        # link is slower than its writer (see "Slow links")
SKIP_RUNS = 256                         # runs of values not sent, kept to answer repairs
_SCALARS = frozenset({int, float, bool, complex, type(None)})   # immutable: kept as they are
SCALAR_BYTES = 9                        # what a scalar counts for in a batch's bytes
_TEXT = frozenset({str, bytes})         # immutable too, when small


def follower_id(node: str, node_epoch: int) -> bytes:
    """The id a node's follower has at every replicator (see "Followers of lost nodes"):
    one per admission of the node (``node_epoch``), so the launcher can name it, and an
    executor of an earlier admission is not taken for the node's current one."""
    digest = hashlib.blake2b(f"{node}\0{node_epoch}".encode(), digest_size=15).digest()
    return b"f" + digest                 # (a routing id must not begin with a zero byte)


def _name(topic: str) -> bytes:
    """A topic on the wire: NUL-terminated, because SUB sockets match prefixes."""
    return topic.encode() + b"\0"


def _topic(name: bytes) -> str:
    return name[:-1].decode()


_MORE, _NOBLOCK = int(zmq.SNDMORE), int(zmq.NOBLOCK)   # (plain ints: an enum's ``|`` costs
                                                        # about a microsecond per frame)


def _send(sock: zmq.Socket, frames: list[Any], flags: int = 0) -> None:
    """Send a multipart message: small frames copied (cheaper than a frame object),
    large ones zero-copy. (``send_multipart`` costs microseconds more per frame.) With
    ``_NOBLOCK``, ``zmq.Again`` at the first frame if the queue is full (a message
    goes whole or not at all)."""
    last = len(frames) - 1
    for index, frame in enumerate(frames):
        big = type(frame) is not bytes and memoryview(frame).nbytes >= ZERO_COPY_MIN
        sock.send(frame, (_MORE | flags) if index < last else flags, copy=not big)


def _receive(sock: zmq.Socket) -> list[Any]:
    """The next message's frames (zero-copy), or ``zmq.Again`` if none has come: one
    call where ``poll(0)`` and ``recv_multipart`` cost a poller and an option read
    per frame (about 5 us per message). A message arrives whole, so the frames after
    its first are there."""
    frame = sock.recv(_NOBLOCK, copy=False)
    frames = [frame]
    while frame.more:
        frame = sock.recv(copy=False)
        frames.append(frame)
    return frames


def _sealed(sealer: Sealer, kind: int, parts: list[Any]) -> list[Any]:
    """A message's frames; a VALUE's last part is its sealed payload, which travels
    outside the message's tag (the message covers its nonce and tag)."""
    if kind == VALUE:
        return sealer.seal(kind, parts[:-1], parts[-1])
    return sealer.seal(kind, parts)


def _secure(sock: zmq.Socket, max_bytes: int = MAX_MESSAGE, *, sender: bool) -> zmq.Socket:
    """Limits every replication socket sets, and its heartbeats. Every socket pings its
    peers each ``PEER_PING_MS``. A sender's socket (PUB, ROUTER) closes a connection that
    has brought it nothing for ``PEER_TIMEOUT_MS``: its follower is frozen or cut off,
    and what was queued for it is freed (a PUB socket's queue for a peer is counted in
    messages, not bytes: a follower frozen for minutes had up to ``HWM`` large values
    queued for it, gigabytes, long after the replay buffer had let them go); the
    follower reconnects by itself when it can. A follower sends only small messages, so
    its pings, which reset that timeout, never wait behind large ones however slow the
    link. A follower's socket (SUB, DEALER) pings but never closes a connection for
    silence: ZeroMQ counts only whole messages as signs of life, and on a slow link a
    large value takes longer than any fixed timeout to come in whole (1 MiB at 1 Mbit/s:
    8 s); it cut such a link at every value, and nothing ever arrived. (A dead sender's
    host resets its connections; one whose sender closed it while the cable was out
    resets it at the follower's next ping; a sender's node that answers nothing is the
    launcher's to find, as a lost node.)"""
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.MAXMSGSIZE, max_bytes)
    sock.setsockopt(zmq.SNDHWM, HWM)
    sock.setsockopt(zmq.RCVHWM, HWM)
    sock.setsockopt(zmq.HEARTBEAT_IVL, PEER_PING_MS)
    sock.setsockopt(zmq.HEARTBEAT_TIMEOUT, PEER_TIMEOUT_MS if sender else 0)   # 0: never
    return sock


def _entry(value: Any, max_bytes: int, room: RingSize | None) -> tuple[int, Any, int]:
    """``(kind, entry, bytes)`` of one value, taken when it is written (the writer may
    change a mutable value right after): an immutable small value is its own entry
    (``PLAIN``), pickled later with the rest of its batch; anything else is encoded
    now, to ``(meta, payload)``. A payload of ``ZERO_COPY_MIN`` bytes or more is sent
    on its own (``kind`` negative): an array's is still the writer's memory here, and
    is sealed (copied and authenticated in one pass) before ``offer`` returns. A value
    the readers' rings (``room``) cannot take is refused here, as a local ring's writer
    refuses it: the reader's node could only drop it."""
    cls = type(value)
    if cls in _SCALARS:
        return PLAIN, value, SCALAR_BYTES
    if cls in _TEXT and len(value) < ZERO_COPY_MIN:
        return PLAIN, value, len(value) + SCALAR_BYTES
    kind, meta, payload = codec.encode(value)
    nbytes = codec.payload_size(kind, payload)
    if nbytes + 1024 > max_bytes:
        raise ValueError(f"a value of {nbytes} bytes exceeds the {max_bytes}-byte message "
                         "limit of remote links; raise the limit")
    if room is not None:
        check_fits(kind, len(meta), nbytes, room)
    if nbytes >= ZERO_COPY_MIN:
        return -kind, (meta, payload), nbytes + 64
    if kind == codec.ARRAY:
        payload = payload.tobytes()
    return kind, (meta, payload), nbytes + 64


def _bound(name: bytes, incarnation: bytes, seq: int, kind: int, meta: bytes) -> bytes:
    """What a sealed payload is, as its associated data: a payload moved into another
    message, as another value, fails its tag."""
    return b"".join((name, incarnation, seq.to_bytes(8, "little"), bytes((kind,)), meta))


# -- the sending side ---------------------------------------------------------------
class _Sent(NamedTuple):
    """A message of one topic's values, as sent, kept for repairs: those from ``first``
    (the older ones were pushed out of the replay buffer) to ``end - 1``."""

    first: int
    end: int
    kind: int                           # VALUE or VALUES (SKIPPED: a notice, never kept)
    parts: list[Any]
    nbytes: int
    at: float = 0.0                     # when it went (monotonic): see "Slow links"

    def replayable(self) -> list[Any]:
        """The message of the values it still holds: the one sent, or one without the
        values pushed out (re-encoded: only repairs of a full buffer pay for it)."""
        if self.kind != VALUES:
            return self.parts
        header, kinds, body = self.parts
        incarnation, first, count, sent_at = _BATCH.unpack(header)
        gone = self.first - first
        if not gone:
            return self.parts
        return [_BATCH.pack(incarnation, self.first, count - gone, sent_at), kinds[gone:],
                pickle.dumps(pickle.loads(body)[gone:], protocol=5)]


@dataclass
class _Direct:
    """A slow follower of a topic that has a fast one too, served over the control
    connection (see "Slow followers"): one message on the way to it at a time."""

    start: int                          # the first value it gets here (the older ones went
                                        # over PUB, or it counts them dropped)
    sent: int                           # values before this one were sent to it or announced
                                        # not sent (SKIPPED)
    went: float = 0.0                   # when the last message to it went (monotonic)
    latest: _Sent | None = None         # the newest message not sent to it yet
    skips: collections.deque[tuple[int, int]] = field(
        default_factory=lambda: collections.deque(maxlen=SKIP_RUNS))   # (first, end) not sent

    def idle(self, acked: int) -> bool:
        """Whether nothing sent to it is on the way, it having acknowledged ``acked``."""
        return acked >= self.sent


@dataclass
class _Stream:
    """One published output: its next sequence number, the values published but not
    sent yet (one batch), and its replay buffer."""

    name: bytes                         # the topic on the wire
    next_seq: int = 0
    pending: list[Any] = field(default_factory=list)    # entries of the batch being filled
    kinds: bytearray | None = None      # ... their codec kinds, once one is not PLAIN
    pending_at: float = 0.0             # ... when the first of them was written (unix)
    pending_bytes: int = 0
    replay: collections.deque[_Sent] = field(default_factory=collections.deque)
    replay_bytes: int = 0
    clear_until: float = 0              # values before this one need no flow-control check ...
    credit: float = 0                   # ... while they take fewer bytes than this
    acks: dict[bytes, tuple[int, float]] = field(default_factory=dict)  # peer -> (seq, when)
    holds: dict[bytes, int] = field(default_factory=dict)   # lossless followers: peer -> seq
    gone: dict[bytes, int] = field(default_factory=dict)    # lost nodes' followers: peer -> the
                                                            # seq they had acknowledged (kept:
                                                            # a rejoined node has another id)
    room: RingSize | None = None        # the readers' rings: what a value must fit
    waits: int = 0                      # values whose publish waited (or waits) for followers
    wait_s: float = 0.0                 # ... and the seconds those that ended waited
    # a dropping link slower than its writer (see "Slow links" above)
    flight: int = FLIGHT_START          # bytes that may be on the way to the lead follower
    slow: bool = False                  # it is slower than the writer: what does not fit
                                        # is not sent, without waiting
    skip_from: int = -1                 # the first of the values not sent since the last
                                        # message that went (-1: none)
    skips: collections.deque[tuple[int, int]] = field(
        default_factory=lambda: collections.deque(maxlen=SKIP_RUNS))   # (first, end) not sent
    dropped: int = 0                    # values not sent, in all
    direct: dict[bytes, _Direct] = field(default_factory=dict)   # slow followers served over
                                        # the control connection, not PUB (nor counted by
                                        # flow control and the flight)
    joined: dict[bytes, int] = field(default_factory=dict)  # peer -> the next sequence number
                                        # at its last HELLO (what it had replayed ends there)

    def _live(self, now: float) -> list[int]:
        """Where the live followers served over PUB are."""
        direct = self.direct
        return [seq for peer, (seq, when) in self.acks.items()
                if now - when < FOLLOWER_TIMEOUT and peer not in direct]

    def acknowledged(self, now: float) -> int | None:
        """Where the slowest live follower is (None: nobody follows)."""
        live = self._live(now)
        return min(live) if live else None

    def lead(self, now: float) -> int | None:
        """Where the most advanced live follower is (None: nobody follows)."""
        live = self._live(now)
        return max(live) if live else None

    def over_flight(self, size: int) -> float | None:
        """When the oldest of the bytes on the way to the lead follower went, if ``size``
        more would not fit in ``flight`` beside them; None if they fit, or none follows."""
        if self.replay_bytes + size <= self.flight:
            return None                          # (no scan: all kept fits, small values)
        lead = self.lead(time.monotonic())
        if lead is None:
            return None
        on_way, oldest, _ = self.on_the_way(lead)
        return oldest if on_way and on_way + size > self.flight else None

    def on_the_way(self, acked: int) -> tuple[int, float, float]:
        """Bytes of the messages sent from sequence number ``acked`` on, when the oldest
        of them went (inf: none), and when the newest message before them went."""
        total, oldest = 0, math.inf
        for sent in reversed(self.replay):
            if sent.end <= acked:
                return total, oldest, sent.at
            total += sent.nbytes
            oldest = sent.at
        return total, oldest, -math.inf

    def skip(self, first: int, end: int) -> None:
        """Values ``first..end - 1`` are not sent (lock held)."""
        if self.skip_from < 0:
            self.skip_from = first
        self.dropped += end - first

    def ahead(self, acked: int) -> int:
        """Bytes of the values from sequence number ``acked`` on (whole messages)."""
        total = self.pending_bytes
        for sent in reversed(self.replay):
            if sent.end <= acked:
                break
            total += sent.nbytes
        return total

    def fits(self, acked: int, size: int) -> bool:
        """Whether one more value of ``size`` bytes stays within ``WINDOW_BYTES`` of a
        follower at ``acked`` (a larger one goes when nothing is ahead of it)."""
        ahead = self.ahead(acked)
        return not ahead or ahead + size <= WINDOW_BYTES

    def kept(self) -> int:
        """Values in the replay buffer and the batch being filled (all consecutive)."""
        oldest = self.replay[0].first if self.replay else self.next_seq - len(self.pending)
        return self.next_seq - oldest

    def held(self) -> int | None:
        """Where the slowest lossless follower is, live or not (None: there is none)."""
        return min(self.holds.values()) if self.holds else None

    def room_for(self, size: int) -> bool:
        """Whether one more value of ``size`` bytes may go without running ``WINDOW``
        values ahead of a lossless follower, or pushing out of the replay buffer a value
        one has not acknowledged (into an empty buffer, a value of any size may go)."""
        held = self.held()
        if held is None:
            return True
        if self.next_seq - held >= WINDOW:
            return False
        full = (self.kept() >= REPLAY_VALUES
                or self.replay_bytes + self.pending_bytes + size > REPLAY_BYTES)
        oldest = self.replay[0].first if self.replay else self.next_seq - len(self.pending)
        return not (full and self.kept() and oldest >= held)

    def drop_follower(self, peer: bytes) -> tuple[int, float] | None:
        """Forget follower ``peer`` (it unfollowed, or went with its lost node): it holds
        nothing back, nor is it served on its own; its last acknowledgement, if any."""
        self.holds.pop(peer, None)
        self.direct.pop(peer, None)
        self.joined.pop(peer, None)
        return self.acks.pop(peer, None)

    def hold(self, peer: bytes, seq: int, flags: int) -> None:
        """A follower said how far it is and whether it is lossless."""
        if flags & LOSSLESS:
            self.holds[peer] = seq
        else:
            self.holds.pop(peer, None)

    def keep(self, sent: _Sent) -> None:
        """Put a message in the replay buffer; push out the oldest values while it holds
        too many values, or too many bytes (whole messages, but not the newest: a value
        larger than the bound stays replayable until the next one goes), and never what
        a lossless follower has not acknowledged."""
        replay = self.replay
        replay.append(sent)
        self.replay_bytes += sent.nbytes
        held = self.held()
        while replay:
            oldest = replay[0]
            if self.replay_bytes > REPLAY_BYTES and len(replay) > 1:
                cut = oldest.end                 # too many bytes: whole messages
            elif (kept := self.kept()) > REPLAY_VALUES:
                cut = min(oldest.end, oldest.first + kept - REPLAY_VALUES)
            else:
                break
            if held is not None:
                cut = min(cut, held)
            if cut <= oldest.first:
                break                            # a lossless follower still needs it
            if cut < oldest.end:
                replay[0] = oldest._replace(first=cut)
            else:
                replay.popleft()
                self.replay_bytes -= oldest.nbytes


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
        self._pub = _secure(self._context.socket(zmq.PUB), max_bytes, sender=True)
        self._router = _secure(self._context.socket(zmq.ROUTER), max_bytes, sender=True)
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
        self._streams: dict[bytes, _Stream] = {}      # by name (bytes) ...
        self._topics: dict[str, _Stream] = {}         # ... and by topic
        # the PUB socket (used by the loop's thread and, for large values, by the
        # publishing thread: never both at once), the streams, the outbox
        self._lock = threading.Lock()
        self._acked = threading.Condition(self._lock)
        self._outbox: list[tuple[bytes, _Sent]] = []     # ready, not sent yet
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
                stream = _Stream(_name(topic), next_seq, room=room)
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
            if type(value) in _SCALARS:
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

        Values are taken as they are now (see ``_entry``). Small ones go out as soon as
        the replicator's thread gets to them (those published meanwhile go with them);
        a large one goes at once, from this thread: batching gains nothing for it, and
        a hand-over to the other thread costs a thread switch per value."""
        max_bytes, room = self._max_bytes, self._topics[topic].room
        entries = [(PLAIN, value, SCALAR_BYTES) if type(value) in _SCALARS
                   else _entry(value, max_bytes, room) for value in values]
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

    def _add(self, stream: _Stream, kind: int, entry: Any, size: int) -> None:
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
            bound = _bound(stream.name, self.incarnation, seq, -kind, meta)
            nonce, sealed = self._payloads.seal(payload, bound)
            stream.next_seq = seq + 1
            info = _INFO.pack(self.incarnation, seq, time.time(), -kind, nonce,
                              sealed[-PAYLOAD_TAG:].tobytes())
            # one frame for every send (repairs too): ZeroMQ shares it by reference
            self._send_soon(stream, _Sent(seq, seq + 1, VALUE,
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

    def _admit(self, stream: _Stream, size: int, deadline: float) -> bool:
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
            lead = stream.lead(time.monotonic())
            on_way = (stream.on_the_way(lead)[0] if lead is not None
                      and stream.replay_bytes > stream.flight else stream.replay_bytes)
            stream.credit = min(WINDOW_BYTES - stream.ahead(acked),
                                stream.flight - on_way - stream.pending_bytes)
        return True

    def _close_batch(self, stream: _Stream) -> None:
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
            parts = [_BATCH.pack(self.incarnation, first, len(pending), stream.pending_at),
                     kinds, pickle.dumps(pending, protocol=5)]
            sent = _Sent(first, stream.next_seq, VALUES, parts, stream.pending_bytes,
                         time.monotonic())
        pending.clear()                          # (the same list: offer holds it)
        stream.kinds, stream.pending_bytes = None, 0
        self._filling.discard(stream.name)
        if sent is not None:
            self._send_soon(stream, sent)

    def _send_soon(self, stream: _Stream, sent: _Sent) -> None:
        """Keep a message for repairs and put it in the outbox (lock held), after the
        notice of the values not sent before it, if any: its followers count them
        dropped, and do not ask for them."""
        if stream.skip_from >= 0:
            first, count = stream.skip_from, sent.first - stream.skip_from
            stream.skips.append((first, sent.first))
            notice = _ANSWER.pack(self.incarnation, first, count)
            self._outbox.append((stream.name, _Sent(first, sent.first, SKIPPED, [notice], 0)))
            stream.skip_from = -1
        stream.keep(sent)
        self._outbox.append((stream.name, sent))

    def _too_slow(self, stream: _Stream, size: int) -> bool:
        """Whether a message of ``size`` bytes must not go (lock held): no lossless
        follower, the lead follower has more than ``flight`` bytes on the way, and it is
        slow (it became so if the oldest of them went ``FRESH_S`` ago)."""
        oldest = None if stream.holds else stream.over_flight(size)
        if oldest is None:
            return False
        if not stream.slow and time.monotonic() - oldest >= FRESH_S:
            stream.slow, stream.flight = True, 0
        return stream.slow

    def _pace(self, stream: _Stream, before: int | None, now: float) -> None:
        """An acknowledgement came (lock held): if it moves the lead follower on, the
        age of the newest message it acknowledges (from when it went) says whether
        the link keeps up: FRESH_S or more, it is slow (one message on the way at a
        time); under half of it, a slow link is not any more, and the bytes that may be
        on the way double."""
        lead = stream.lead(now)
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
    def _find_slow(self, stream: _Stream, now: float) -> None:
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

    def _go_direct(self, stream: _Stream, peer: bytes) -> None:
        """From the next value on, send ``peer`` the values of ``stream`` over the control
        connection, one message on the way at a time; it stops taking them over PUB
        (DIRECT: it closes its SUB connection, which frees what PUB still queues for
        it) and counts those it misses before then dropped (lock held, loop thread)."""
        self._flush_locked()                     # (what was published went over PUB)
        start = stream.next_seq
        stream.direct[peer] = _Direct(start, start, time.monotonic())
        self._send_router(peer, DIRECT, [stream.name, _ANSWER.pack(self.incarnation, start,
                                                                   start)])
        stream.clear_until = 0                   # (flow control no longer counts it)
        self._acked.notify_all()
        log.info("remote link %s: a follower too slow beside a faster one is served on its "
                 "own from value %d", _topic(stream.name), start)

    def _resume(self, stream: _Stream, peer: bytes, now: float, start: int | None = None) -> None:
        """A follower served on its own keeps up again: back to PUB from ``start`` (None:
        the next value; the values before it are not sent to it, and it counts them
        dropped), with RESUME (lock held, on the loop's thread). A follower that became
        lossless resumes from where it is, and says HELLO to have the rest replayed."""
        self._flush_locked()
        del stream.direct[peer]
        if start is None:
            start = stream.next_seq
            stream.acks[peer] = (start, now)     # (so it is not found slow for them)
        self._send_router(peer, RESUME, [stream.name, _ANSWER.pack(self.incarnation, start, 0)])
        stream.clear_until = 0

    def _serve_direct(self, stream: _Stream) -> None:
        """Send each follower served on its own the newest message it has not had, if
        nothing sent to it is on the way; the values before it that it did not get are
        announced (SKIPPED) (lock held, on the loop's thread)."""
        now = time.monotonic()
        for peer, direct in stream.direct.items():
            sent = direct.latest
            if sent is None or not direct.idle(stream.acks.get(peer, (-1, 0.0))[0]):
                continue
            direct.latest = None
            if sent.first > direct.sent:
                direct.skips.append((direct.sent, sent.first))
                self._send_router(peer, SKIPPED, [stream.name, _ANSWER.pack(
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
        _send(self._pub, [name, *_sealed(self._pub_sealer, kind, [name, *parts])])

    def _on_request(self, router: zmq.Socket) -> None:
        for _ in range(DRAIN_BATCH):
            try:
                peer, *frames = _receive(router)
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
            for name, stream in self._streams.items():
                self._send_pub(name, SYNC, [self._sync(stream)])
                # Their SYNC, and their mode. One silent for a while (its link cut, its
                # node frozen) is still served on its own: it has closed its SUB
                # connection and takes nothing over PUB until told RESUME, so forgotten
                # here it got nothing more, nor was anything counted, unless found slow
                # again (which takes a faster follower beside it). It leaves by saying
                # so (an ACK of -1), by a HELLO, or with its lost node (``forget``).
                for peer, direct in stream.direct.items():
                    self._send_router(peer, DIRECT, [name, _ANSWER.pack(
                        self.incarnation, direct.start, direct.sent)])

    def _sync(self, stream: _Stream) -> bytes:
        """A SYNC's body: the next sequence number, and how many values before it were
        not sent (a follower counts them dropped; it does not ask for them)."""
        skipped = stream.next_seq - stream.skip_from if stream.skip_from >= 0 else 0
        return _ANSWER.pack(self.incarnation, stream.next_seq, skipped)

    def _answer(self, peer: Any, message: Any) -> None:
        if message.kind not in (HELLO, REPAIR, ACK) or len(message.frames) != 2 \
                or memoryview(message.frames[1]).nbytes != _ASK.size:
            raise Rejected("unexpected")
        name = bytes(message.frames[0])
        first, last, to = _ASK.unpack(message.frames[1])
        if to != self.incarnation and to != _NOBODY:
            raise Rejected("other instance")    # meant for another replicator: a copy
        with self._lock:
            stream = self._streams.get(name)
            if stream is None:
                return                           # not (yet) published here: they retry
            if to == _NOBODY:                    # who we are, and nothing else
                if message.kind == HELLO:
                    self._send_router(peer, WELCOME,
                                      [name, _ANSWER.pack(self.incarnation, stream.next_seq, 0)])
                return
            peer_id = bytes(peer)
            if peer_id in stream.gone:           # its node was lost: see ``forget``
                raise Rejected("lost follower")
            if message.kind == ACK:
                now = time.monotonic()
                before = stream.lead(now)
                direct = stream.direct.get(peer_id)
                if first < 0:                    # unfollowed: it holds nothing back now
                    stream.drop_follower(peer_id)
                else:
                    # (never back: an ACK sent before a RESUME came says less than it)
                    known = stream.acks.get(peer_id)
                    stream.acks[peer_id] = (max(first, known[0]) if known else first, now)
                    stream.hold(peer_id, first, last)
                    if direct is None:
                        self._pace(stream, before, now)
                        self._find_slow(stream, now)
                    elif last & LOSSLESS:            # (it must not drop now)
                        self._resume(stream, peer_id, now, first)
                    elif direct.sent > direct.start and first >= direct.sent \
                            and now - direct.went < FRESH_S / 2:
                        self._resume(stream, peer_id, now)   # a lone message, in time
                    else:
                        self._serve_direct(stream)
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
                if not again:
                    stream.joined[peer_id] = nxt
                stream.acks[peer_id] = (first if first >= 0 else nxt, time.monotonic())
                stream.hold(peer_id, first if first >= 0 else nxt, last)
                stream.clear_until = 0           # a new follower: the window moved back
                replays = first >= 0 and not again      # (an empty replay still says so)
                self._send_router(peer, WELCOME,
                                  [name, _ANSWER.pack(self.incarnation, nxt, int(replays))])
                self._send_pub(name, SYNC, [self._sync(stream)])
                if replays:
                    self._replay(peer, name, stream, first, nxt - 1)
            else:
                self._flush_locked()
                self._replay(peer, name, stream, first, last)

    def _replay(self, peer: Any, name: bytes, stream: _Stream, first: int, last: int) -> None:
        """The messages holding values ``first..last`` from the buffer, then how many of
        those values are gone."""
        oldest = stream.replay[0].first if stream.replay else stream.next_seq
        gone = max(0, min(last + 1, oldest) - first)
        runs = list(stream.skips)
        if stream.skip_from >= 0:
            runs.append((stream.skip_from, stream.next_seq))
        direct = stream.direct.get(bytes(peer))
        if direct is not None:       # a follower served on its own: nor what it was not sent
            runs += [(min(first, direct.start), direct.start), *direct.skips]
        for start, end in runs:                  # (not sent: never replayed, nor gone)
            if start <= last and end > first:
                self._send_router(peer, SKIPPED,
                                  [name, _ANSWER.pack(self.incarnation, start, end - start)])
        for sent in stream.replay:
            if sent.first <= last and sent.end > first and not (
                    direct is not None
                    and any(start <= sent.first and sent.end <= end for start, end in runs)):
                self._send_router(peer, sent.kind, [name, *sent.replayable()])
        self._send_router(peer, REPLAYED, [name, _ANSWER.pack(self.incarnation, first, gone)])

    def _send_router(self, peer: Any, kind: int, parts: list[Any]) -> None:
        _send(self._router, [peer, *_sealed(self._router_sealer, kind, parts)])

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
    repair_wait: float = REPAIR_RETRY_S       # before asking the repair again
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
        self._loop.call(lambda: self._follow(_name(topic), data, control, from_seq,
                                             incarnation))

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
            skipped = sum(max(0, min(end, newest) - max(first, follow.next_seq))
                          for first, end in follow.skips.items())
            return max(0, newest - follow.next_seq - skipped)
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
        sub = self._sub(data)
        dealer = self._controls.get(control)
        if dealer is None:
            dealer = _secure(self._context.socket(zmq.DEALER), self._max_bytes, sender=False)
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
            sub = self._subs[data] = _secure(self._context.socket(zmq.SUB), self._max_bytes,
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
        ``waiting`` (a repeat while that replay is on its way: see ``_retry``)."""
        follow.hello_at = time.monotonic()
        flags = self._flags(follow)
        if waiting:
            flags |= WAITING
        else:
            follow.asked = follow.hello_at
            follow.repairing = follow.next_seq >= 0   # the answer replays what we miss
            follow.asked_from = follow.next_seq
            follow.hello_for = follow.incarnation
        self._ask(follow, HELLO, follow.next_seq, flags)

    def _ask(self, follow: _Follow, kind: int, first: int, last: int) -> None:
        """Send HELLO, REPAIR or ACK to the replicator of ``follow``, naming it (nobody,
        before it said who it is: then only a HELLO is answered, with a WELCOME)."""
        to = follow.incarnation or _NOBODY
        frames = self._sealer.seal(kind, [follow.topic, _ASK.pack(first, last, to)])
        try:           # never blocks the follower's one thread (every topic it follows)
            _send(follow.control, frames, _NOBLOCK)
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
                frames = _receive(sock)
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
            if not live and follow.repairing and not follow.direct \
                    and message.kind in (VALUE, VALUES, SKIPPED):
                # the answer of a hand-shake or repair, coming in: not asked again while
                # it comes (on a slow link a large value takes seconds to cross)
                follow.asked = time.monotonic()
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
            incarnation, nxt, third = _ANSWER.unpack(message.frames[1])
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
            follow.announced = max(follow.announced, nxt)
            follow.live = follow.live or live
            if message.kind == WELCOME and third and follow.repairing:
                follow.asked = time.monotonic()  # its replay is coming (see ``_drain``)
            if follow.hello_for is None and message.kind == WELCOME:
                self._hello(follow)              # naming it now: see "Destinations"
            return follow
        if message.kind == VALUE:
            if (len(message.frames) != 3 or message.payload is None
                    or memoryview(message.frames[1]).nbytes != _INFO.size):
                raise Rejected("malformed")
            info, meta = message.frames[1:]
            incarnation, seq, sent_at, kind, nonce, tag = _INFO.unpack(info)
            if not self._accept(follow, incarnation):
                return None
            if live and follow.joining:
                self._joined(follow, seq)
                self._advance(follow)            # (so that it lands in order: below)
            if self._delivered(follow, seq):     # (a repair re-sent it: not decrypted again)
                self.duplicates[_topic(follow.topic)] += 1
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
            if len(message.frames) != 4 or memoryview(message.frames[1]).nbytes != _BATCH.size:
                raise Rejected("malformed")
            header, kinds, body = message.frames[1:]
            incarnation, first, count, sent_at = _BATCH.unpack(header)
            if not self._accept(follow, incarnation):
                return None
            if live and follow.joining:
                self._joined(follow, first)
            values = _entries(body, bytes(kinds), count)
            nbytes = memoryview(body).nbytes
            return follow if self._take(follow, first, values, sent_at, nbytes, live) else None
        if message.kind == SKIPPED:
            incarnation, first, count = _ANSWER.unpack(message.frames[1])
            if not self._accept(follow, incarnation):
                return None
            if first < 0 or count <= 0:
                raise Rejected("malformed")
            if live and follow.joining:
                self._joined(follow, first)
            self._skipped(follow, first, first + count)
            return follow
        if message.kind in (DIRECT, RESUME):
            incarnation, start, nxt = _ANSWER.unpack(message.frames[1])
            if not self._accept(follow, incarnation):
                return None
            if live or start < 0 or follow.next_seq < 0:
                raise Rejected("malformed")
            self._not_sent_before(follow, start)
            if message.kind == RESUME:
                if follow.direct:
                    self._resume(follow)
                    if follow.topic in self._lossless:   # (nothing may be dropped: the
                        follow.joining = False           # hand-shake replays the rest)
                        follow.live = False
                        self._hello(follow)
            else:
                if not follow.direct:
                    self._go_direct(follow)
                follow.announced = max(follow.announced, nxt)
            return follow
        if message.kind == REPLAYED:
            incarnation, first, gone = _ANSWER.unpack(message.frames[1])
            if not self._accept(follow, incarnation):
                return None
            if first == follow.asked_from:       # (not the end of an earlier copy's)
                follow.repairing, follow.repair_wait = False, REPAIR_RETRY_S
            if gone and follow.next_seq < first + gone:
                lost = first + gone - follow.next_seq - self._pass_skips(follow, first + gone)
                if lost:
                    self.link_failures[_topic(follow.topic)] += lost
                    log.error("remote link %s lost %d values (gone from the sender's replay "
                              "buffer)", _topic(follow.topic), lost)
                follow.next_seq = first + gone
            return follow
        raise Rejected("unexpected")

    def _unseal(self, follow: _Follow, incarnation: bytes, seq: int, kind: int, meta: bytes,
                nonce: int, tag: bytes, payload: memoryview, land: bool) -> Any:
        """The value of a sealed payload, decrypted and checked in one pass: an array
        straight into the slot the receiver offers (``land``, if asked), else into
        memory of its own. ``Rejected`` if its tag fails (never delivered)."""
        size = payload.nbytes - PAYLOAD_TAG
        if size < 0 or not secrets.compare_digest(payload[size:], tag):
            raise Rejected("bad payload tag")
        bound = _bound(follow.topic, incarnation, seq, kind, meta)
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
        landed = self._land(_topic(follow.topic), meta, size) if land and self._land else None
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
        self.dropped[_topic(follow.topic)] += passed
        return passed

    @staticmethod
    def _delivered(follow: _Follow, seq: int) -> bool:
        """Whether the value ``seq`` was delivered or is held already."""
        return (0 <= seq < follow.next_seq) or seq in follow.held

    def _take(self, follow: _Follow, first: int, values: list[Any], sent_at: float,
              nbytes: int, live: bool) -> bool:
        """Hold a run of values (sequence numbers from ``first`` on) for in-order
        delivery; False if all of them are duplicates."""
        follow.live = follow.live or live
        # (joined "from now": values wait until the hand-shake says where now is)
        old = max(0, follow.next_seq - first) if follow.next_seq >= 0 else 0
        if old:
            self.duplicates[_topic(follow.topic)] += min(old, len(values))
            if old >= len(values):
                return False
            first, values = first + old, values[old:]
        known = follow.held.get(first)
        if known is not None:                   # (a repair raced the live message)
            self.duplicates[_topic(follow.topic)] += min(len(known[0]), len(values))
            if len(known[0]) >= len(values):
                return False
        follow.held[first] = (values, sent_at, nbytes)
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
                        self.dropped[_topic(follow.topic)] += end - seq
                        seq = end
                continue
            first = seq if seq in held else next((k for k in held if k < seq), None)
            if first is None:
                break
            run, sent_at, nbytes = held.pop(first)
            if first < seq:                      # runs that overlap: the rest of this one
                self.duplicates[_topic(follow.topic)] += min(seq - first, len(run))
                run = run[seq - first:]
            values = run if not values else values + run
            size += nbytes
            seq += len(run)
        if values:
            held_back = 0
            try:
                held_back = self._deliver(_topic(follow.topic), values, sent_at) or 0
            except Exception:      # (a value too large for a reader's ring: not promised)
                log.exception("remote link %s: values could not be handed to its readers",
                              _topic(follow.topic))
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
        """Tell the publisher how far we are: it may run at most its window ahead."""
        follow.acked, follow.acked_at = follow.through, time.monotonic()
        follow.acked_bytes = follow.moved_bytes
        self._ask(follow, ACK, follow.acked, self._flags(follow))

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



def _entries(body: Any, kinds: bytes, count: int) -> list[Any]:
    """The values of an authenticated VALUES message (checked all the same)."""
    values = pickle.loads(body)
    if type(values) is not list or len(values) != count or len(kinds) not in (0, count):
        raise Rejected("malformed")
    if kinds:
        values = [entry if kind == PLAIN else codec.decode_owned(kind, bytes(entry[0]), entry[1])
                  for kind, entry in zip(kinds, values, strict=True)]
    return values
