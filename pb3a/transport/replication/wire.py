"""The wire of remote links (see the package's docstring): the message kinds and their
layouts, the numbers the protocol runs by, and how a message is sent, received and
sealed, and its values encoded and decoded. Both sides import from here; a number is
read by the module that imports it (a test patches that module, not this one, unless
the number is read here: the sockets' limits)."""

from __future__ import annotations

import hashlib
import pickle
import struct
from typing import Any

import zmq

from pb3a.transport import codec
from pb3a.transport.auth import Rejected, Sealer
from pb3a.transport.ring import RingSize, check_fits

# message kinds
VALUE, SYNC, HELLO, REPAIR, WELCOME, REPLAYED, ACK, VALUES, SKIPPED = 1, 2, 3, 4, 5, 6, 7, 8, 9
DIRECT, RESUME = 10, 11                 # a slow follower beside a fast one: see "Slow followers"
INFO = struct.Struct("<16sQdBQ16s")    # VALUE: incarnation, sequence number, sent at (unix),
                                        # codec kind, payload nonce counter, payload tag
BATCH = struct.Struct("<16sQId")       # VALUES: incarnation, first sequence number, count,
                                        # sent at (unix: when the first was written)
ASK = struct.Struct("<qq16s")          # HELLO: first needed (-1: from now), flags; REPAIR:
                                        # first, last; ACK: delivered up to (exclusive, -1:
                                        # unfollowed), flags; then the incarnation of the
                                        # replicator it is for (NOBODY: not known yet)
NOBODY = bytes(16)
LOSSLESS = 1                            # flag of HELLO and ACK: hold the publisher back
WAITING = 2                             # flag of HELLO: the replay an earlier one asked for
                                        # is on its way: answer WELCOME and SYNC only
SERVED_DIRECT = 4                       # flag of ACK: it is served on its own (DIRECT); a
                                        # sender serving it over PUB says RESUME again, and
                                        # one serves it on its own only once told so
LIVE = 8                                # flag of HELLO: its subscription is live already (it
                                        # learned whom to name after a SYNC or value came
                                        # through it): replay nothing (it repairs what its
                                        # subscription missed; PUB carries the rest to it)
ANSWER = struct.Struct("<16sqq")       # WELCOME: incarnation, next, a replay follows (1)
                                        # or not (0); REPLAYED: first, gone;
                                        # SKIPPED: first, count; SYNC: next, skipped before it;
                                        # DIRECT: from, next; RESUME: from, 0
PLAIN = 0                               # a VALUES entry that is the value itself
BATCH_VALUES = 1024                     # small values of one topic sent as one message, at most
BATCH_BYTES = 1 << 20                   # ... and at most this many bytes of them
HWM = 10_000                            # messages queued per peer before ZeroMQ drops
MAX_MESSAGE = 256 * 1024 * 1024         # bytes; larger frames are refused by ZeroMQ itself
ASKED_MAX = 16 * 1024                   # what a sender takes in (a subscription, HELLO, REPAIR,
                                        # ACK: a topic and a few numbers), at most: anyone who
                                        # reaches its ports may send, key or not, and ZeroMQ
                                        # keeps a subscription at some 75 bytes per byte (two
                                        # of 16 MB took a publisher to 2.5 GB for good)
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
                                        # this long (see ``secured_socket``)
DRAIN_BATCH = 1024                      # messages taken in before delivering them
ZERO_COPY_MIN = 64 * 1024               # frames at least this large are sent without a copy
FLIGHT_START = 256 * 1024               # bytes on the way to a dropping link at first (it doubles
                                        # at each timely acknowledgement, up to WINDOW_BYTES)
FRESH_S = 0.5                           # a value not acknowledged this long after it went: the
                                        # link is slower than its writer (see "Slow links")
SKIP_RUNS = 256                         # runs of values not sent, kept to answer repairs
SCALARS = frozenset({int, float, bool, complex, type(None)})   # immutable: kept as they are
SCALAR_BYTES = 9                        # what a scalar counts for in a batch's bytes
TEXT = frozenset({str, bytes})         # immutable too, when small


def follower_id(node: str, node_epoch: int) -> bytes:
    """The id a node's follower has at every replicator (see "Followers of lost nodes"):
    one per admission of the node (``node_epoch``), so the launcher can name it, and an
    executor of an earlier admission is not taken for the node's current one."""
    digest = hashlib.blake2b(f"{node}\0{node_epoch}".encode(), digest_size=15).digest()
    return b"f" + digest                 # (a routing id must not begin with a zero byte)


def topic_bytes(topic: str) -> bytes:
    """A topic on the wire: NUL-terminated, because SUB sockets match prefixes."""
    return topic.encode() + b"\0"


def topic_text(name: bytes) -> str:
    return name[:-1].decode()


MORE, NOBLOCK = int(zmq.SNDMORE), int(zmq.NOBLOCK)   # (plain ints: an enum's ``|`` costs
                                                        # about a microsecond per frame)


def send_message(sock: zmq.Socket, frames: list[Any], flags: int = 0) -> None:
    """Send a multipart message: small frames copied (cheaper than a frame object),
    large ones zero-copy. (``send_multipart`` costs microseconds more per frame.) With
    ``NOBLOCK``, ``zmq.Again`` at the first frame if the queue is full (a message
    goes whole or not at all)."""
    last = len(frames) - 1
    for index, frame in enumerate(frames):
        big = type(frame) is not bytes and memoryview(frame).nbytes >= ZERO_COPY_MIN
        sock.send(frame, (MORE | flags) if index < last else flags, copy=not big)


def receive_message(sock: zmq.Socket) -> list[Any]:
    """The next message's frames (zero-copy), or ``zmq.Again`` if none has come: one
    call where ``poll(0)`` and ``recv_multipart`` cost a poller and an option read
    per frame (about 5 us per message). A message arrives whole, so the frames after
    its first are there."""
    frame = sock.recv(NOBLOCK, copy=False)
    frames = [frame]
    while frame.more:
        frame = sock.recv(copy=False)
        frames.append(frame)
    return frames


def sealed_message(sealer: Sealer, kind: int, parts: list[Any]) -> list[Any]:
    """A message's frames; a VALUE's last part is its sealed payload, which travels
    outside the message's tag (the message covers its nonce and tag)."""
    if kind == VALUE:
        return sealer.seal(kind, parts[:-1], parts[-1])
    return sealer.seal(kind, parts)


def secured_socket(sock: zmq.Socket, max_bytes: int = MAX_MESSAGE, *, sender: bool) -> zmq.Socket:
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


def batch_entry(value: Any, max_bytes: int, room: RingSize | None) -> tuple[int, Any, int]:
    """``(kind, entry, bytes)`` of one value, taken when it is written (the writer may
    change a mutable value right after): an immutable small value is its own entry
    (``PLAIN``), pickled later with the rest of its batch; anything else is encoded
    now, to ``(meta, payload)``. A payload of ``ZERO_COPY_MIN`` bytes or more is sent
    on its own (``kind`` negative): an array's is still the writer's memory here, and
    is sealed (copied and authenticated in one pass) before ``offer`` returns. A value
    the readers' rings (``room``) cannot take is refused here, as a local ring's writer
    refuses it: the reader's node could only drop it."""
    cls = type(value)
    if cls in SCALARS:
        return PLAIN, value, SCALAR_BYTES
    if cls in TEXT and len(value) < ZERO_COPY_MIN:
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


def sealed_as(name: bytes, incarnation: bytes, seq: int, kind: int, meta: bytes) -> bytes:
    """What a sealed payload is, as its associated data: a payload moved into another
    message, as another value, fails its tag."""
    return b"".join((name, incarnation, seq.to_bytes(8, "little"), bytes((kind,)), meta))


def batch_entries(body: Any, kinds: bytes, count: int) -> list[Any]:
    """The values of an authenticated VALUES message (checked all the same)."""
    values = pickle.loads(body)
    if type(values) is not list or len(values) != count or len(kinds) not in (0, count):
        raise Rejected("malformed")
    if kinds:
        values = [entry if kind == PLAIN else codec.decode_owned(kind, bytes(entry[0]), entry[1])
                  for kind, entry in zip(kinds, values, strict=True)]
    return values
