"""A published topic as its sender keeps it (``Stream``): the batch being filled, the
replay buffer of messages as sent (``Sent``), the followers' acknowledgements, flow
control, the flight toward the lead follower, and the followers served on their own
(``Direct``). ``Replicator`` owns the streams and their sockets; this module holds what
one stream knows and decides, without sockets (see the package's docstring)."""

from __future__ import annotations

import collections
import math
import pickle
import time
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from pb3a.transport.replication.wire import (
    BATCH,
    FLIGHT_START,
    FOLLOWER_TIMEOUT,
    LOSSLESS,
    REPLAY_BYTES,
    REPLAY_VALUES,
    SKIP_RUNS,
    VALUES,
    WINDOW,
    WINDOW_BYTES,
)
from pb3a.transport.ring import RingSize


class Sent(NamedTuple):
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
        incarnation, first, count, sent_at = BATCH.unpack(header)
        gone = self.first - first
        if not gone:
            return self.parts
        return [BATCH.pack(incarnation, self.first, count - gone, sent_at), kinds[gone:],
                pickle.dumps(pickle.loads(body)[gone:], protocol=5)]


@dataclass
class Direct:
    """A slow follower of a topic that has (or had) a fast one too, served over the
    control connection (see "Slow followers"): one message on the way to it at a time."""

    start: int                          # the first value it gets here (the older ones went
                                        # over PUB, or it counts them dropped)
    sent: int                           # values before this one were sent to it or announced
                                        # not sent (SKIPPED)
    went: float = 0.0                   # when the last message to it went (monotonic)
    told: bool = False                  # an ACK of it says it is served so (SERVED_DIRECT,
                                        # from start on): nothing is sent to it here before
                                        # (its DIRECT lost, it still takes values over PUB)
    latest: Sent | None = None         # the newest message not sent to it yet
    skips: collections.deque[tuple[int, int]] = field(
        default_factory=lambda: collections.deque(maxlen=SKIP_RUNS))   # (first, end) not sent

    def idle(self, acked: int) -> bool:
        """Whether nothing sent to it is on the way, it having acknowledged ``acked``."""
        return acked >= self.sent


@dataclass
class Stream:
    """One published output: its next sequence number, the values published but not
    sent yet (one batch), and its replay buffer."""

    name: bytes                         # the topic on the wire
    next_seq: int = 0
    pending: list[Any] = field(default_factory=list)    # entries of the batch being filled
    kinds: bytearray | None = None      # ... their codec kinds, once one is not PLAIN
    pending_at: float = 0.0             # ... when the first of them was written (unix)
    pending_bytes: int = 0
    replay: collections.deque[Sent] = field(default_factory=collections.deque)
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
    # a dropping link slower than its writer (see "Slow links" in the package's docstring)
    flight: int = FLIGHT_START          # bytes that may be on the way to the lead follower
    slow: bool = False                  # it is slower than the writer: what does not fit
                                        # is not sent, without waiting
    skip_from: int = -1                 # the first of the values not sent since the last
                                        # message that went (-1: none)
    skips: collections.deque[tuple[int, int]] = field(
        default_factory=lambda: collections.deque(maxlen=SKIP_RUNS))   # (first, end) not sent
    dropped: int = 0                    # values not sent, in all
    direct: dict[bytes, Direct] = field(default_factory=dict)   # slow followers served over
                                        # the control connection, not PUB (nor counted by
                                        # flow control and the flight)
    joined: dict[bytes, int] = field(default_factory=dict)  # peer -> the next sequence number
                                        # at its last HELLO, or at its first ACK if heard of
                                        # so first (what it has replayed, or repairs from
                                        # before it was live, ends there; PUB carries on)
    resumed: dict[bytes, int] = field(default_factory=dict)  # peer -> where it went back to
                                        # PUB from a DIRECT (it counts the values before
                                        # dropped: a repair over them replays none)

    def _live(self, now: float) -> dict[bytes, int]:
        """Where each live follower served over PUB is, by its id."""
        direct = self.direct
        return {peer: seq for peer, (seq, when) in self.acks.items()
                if now - when < FOLLOWER_TIMEOUT and peer not in direct}

    def acknowledged(self, now: float) -> int | None:
        """Where the slowest live follower is (None: nobody follows)."""
        return min(self._live(now).values(), default=None)

    def lead(self, now: float) -> int | None:
        """Where the most advanced live follower is (None: nobody follows)."""
        return max(self._live(now).values(), default=None)

    def flight_lead(self, now: float) -> int | None:
        """Where the lead follower is, for its flight (None: nobody follows): one still
        taking in what its hand-shake replayed (or repairing what its subscription
        missed before it knew whom to name) is where PUB began to carry values to it
        (``joined``). The values before went over PUB long ago, before it subscribed,
        and come to it over its control connection: their age is not its link's. Taken
        for it, a follower that joined with more than a flight of values to take in made
        its link slow, and the next values were not sent (see "Slow links")."""
        joined = self.joined
        return max((max(seq, joined.get(peer, seq)) for peer, seq in self._live(now).items()),
                   default=None)

    def over_flight(self, size: int) -> float | None:
        """When the oldest of the bytes on the way to the lead follower went, if ``size``
        more would not fit in ``flight`` beside them; None if they fit, or none follows."""
        if self.replay_bytes + size <= self.flight:
            return None                          # (no scan: all kept fits, small values)
        lead = self.flight_lead(time.monotonic())
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
        self.resumed.pop(peer, None)
        return self.acks.pop(peer, None)

    def hold(self, peer: bytes, seq: int, flags: int) -> None:
        """A follower said how far it is and whether it is lossless."""
        if flags & LOSSLESS:
            self.holds[peer] = seq
        else:
            self.holds.pop(peer, None)

    def keep(self, sent: Sent) -> None:
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
