"""Large payloads of remote links, sealed on their own (AES-GCM at write time) and
decrypted straight into the reader's ring slot: tampering and replays refused and
counted, never delivered; value semantics; nonces that never repeat; slots that never
leak."""

from __future__ import annotations

import gc
import itertools
import threading
from typing import Any

import numpy as np
import pytest
from conftest import eventually
from test_replication import KEY, TIMEOUT, Inbox, _follow

from pb3a.transport import codec, replication
from pb3a.transport.auth import PAYLOAD_TAG, Payloads, Rejected
from pb3a.transport.replication import Follower, Replicator
from pb3a.transport.ring import Landed, ShmRing
from pb3a.transport.shm import segment_name

N = 1 << 17                                  # float64s: 1 MiB


def test_a_payload_opens_only_as_what_it_was_sealed_for() -> None:
    owner = b"o" * 16
    sealer, opener = Payloads(KEY, owner), Payloads(KEY)
    data = np.arange(N, dtype=np.float64)
    nonce, frame = sealer.seal(data, b"bound")
    out = np.empty(N)
    opener.open_into(owner, nonce, b"bound", frame, memoryview(out).cast("B"))
    assert np.array_equal(out, data)
    assert not np.array_equal(frame[:-PAYLOAD_TAG].view(np.float64), data)   # encrypted
    for owner_, nonce_, bound in ((b"p" * 16, nonce, b"bound"), (owner, nonce + 1, b"bound"),
                                  (owner, nonce, b"other")):
        with pytest.raises(Rejected, match="bad payload tag"):
            opener.open_into(owner_, nonce_, bound, frame, memoryview(out).cast("B"))


def test_payload_keys_are_neither_message_keys_nor_shared_by_incarnations() -> None:
    first, second = Replicator(KEY), Replicator(KEY)
    try:
        keys = {KEY.derive(r.incarnation, payload=True) for r in (first, second)}
        keys |= {KEY.derive(r.incarnation) for r in (first, second)}
        assert len(keys) == 4
    finally:
        first.close()
        second.close()


class Wire:
    """The VALUE messages a replicator publishes, seen (and changed) on their way."""

    def __init__(self, replicator: Replicator, monkeypatch: Any) -> None:
        self.sent: list[list[Any]] = []          # parts of every VALUE: info, meta, frame
        self.change = None                       # parts -> parts, once
        self._send = replicator._send_pub
        monkeypatch.setattr(replicator, "_send_pub", self._intercept)

    def _intercept(self, name: bytes, kind: int, parts: list[Any]) -> None:
        if kind == replication.VALUE:
            self.sent.append(list(parts))
            if self.change is not None:
                parts, self.change = self.change(list(parts)), None
        self._send(name, kind, parts)

    def send(self, name: bytes, parts: list[Any]) -> None:
        """A new genuine message (the sender's own key and next counter) of ``parts``."""
        self._send(name, replication.VALUE, parts)


def _info(parts: list[Any], **fields: Any) -> list[Any]:
    """``parts`` with fields of the VALUE info changed."""
    names = ("incarnation", "seq", "sent_at", "kind", "nonce", "tag")
    info = dict(zip(names, replication.INFO.unpack(parts[0]), strict=True))
    info.update(fields)
    return [replication.INFO.pack(*info.values()), *parts[1:]]


def _flip_ciphertext(parts: list[Any]) -> list[Any]:
    frame = bytearray(parts[2])
    frame[1000] ^= 0x01
    return [*parts[:2], bytes(frame)]


def _flip_tag(parts: list[Any]) -> list[Any]:
    frame = bytearray(parts[2])
    frame[-1] ^= 0x01                            # the frame's tag and the info's agree ...
    tag = bytes(frame[-PAYLOAD_TAG:])
    return _info([*parts[:2], bytes(frame)], tag=tag)   # ... and are both wrong


def _other_nonce(parts: list[Any]) -> list[Any]:
    return _info(parts, nonce=replication.INFO.unpack(parts[0])[4] + 1)


class RingReader:
    """A follower landing a topic's arrays in a ring with a slot pool, as a node's
    bridge does, and the reader's end of that ring."""

    def __init__(self, slots: int = 4) -> None:
        self.owner = ShmRing.create(segment_name("sealed"), 64 * 1024, slots, N * 8)
        self.writer = ShmRing.attach(self.owner.name)
        self.reader = ShmRing.attach(self.owner.name)
        self.landed = 0
        self.arrived = threading.Semaphore(0)
        self.follower = Follower(KEY, self._deliver, land=self._land)

    def _land(self, topic: str, meta: bytes, nbytes: int) -> Landed | None:
        landed = self.writer.claim(meta, nbytes)
        self.landed += landed is not None
        return landed

    def _deliver(self, topic: str, values: list[Any], sent_at: float) -> None:
        self.writer.write_many(values)
        for _ in values:
            self.arrived.release()

    def take(self, count: int) -> list[np.ndarray]:
        """``count`` values from the ring, as copies (their slots go back at once)."""
        got: list[np.ndarray] = []
        while len(got) < count:
            assert self.arrived.acquire(timeout=TIMEOUT), f"{len(got)} of {count} arrived"
            while self.reader.has_data():
                values, _, gaps = self.reader.drain()
                assert not gaps
                got += [value.copy() for value in values]
        return got

    def close(self) -> None:
        self.follower.close()
        gc.collect()                             # (views and landings first)
        for ring in (self.reader, self.writer, self.owner):
            ring.close()


@pytest.fixture
def landing():
    replicator, receiver = Replicator(KEY), RingReader()
    replicator.add("t")
    _follow(receiver.follower, replicator, "t", from_seq=0)
    assert receiver.follower.wait_ready("t", TIMEOUT)
    yield replicator, receiver
    receiver.close()
    replicator.close()


@pytest.mark.parametrize("tamper", [_flip_ciphertext, _flip_tag, _other_nonce],
                         ids=["ciphertext", "tag", "nonce"])
def test_a_tampered_payload_is_refused_counted_never_delivered_and_repaired(
        landing, monkeypatch, tamper) -> None:
    replicator, receiver = landing
    wire = Wire(replicator, monkeypatch)
    wire.change = tamper
    arrays = [np.full(N, float(i)) for i in range(3)]
    for array in arrays:
        replicator.publish("t", array)
    got = receiver.take(3)                       # the first one repaired, untampered
    assert [value[0] for value in got] == [0.0, 1.0, 2.0]
    assert all(np.array_equal(value, array) for value, array in zip(got, arrays, strict=True))
    assert receiver.follower.rejected == {"bad payload tag": 1}
    assert receiver.landed >= 1                  # the refused one was decrypted into a
                                                 # slot of the ring (it came in order) ...
    gc.collect()
    eventually(lambda: receiver.writer.core.slots_used() == 0,
               what="every slot back, the refused one too")    # ... and none leaked


def test_a_payload_replayed_in_a_new_message_is_refused(landing, monkeypatch) -> None:
    replicator, receiver = landing
    wire = Wire(replicator, monkeypatch)
    replicator.publish("t", np.full(N, 0.0))
    assert receiver.take(1)[0][0] == 0.0
    captured = wire.sent[0]
    wire.send(b"t\0", _info(captured, seq=1))        # as the next value: refused
    replicator.publish("t", np.full(N, 1.0))
    wire.send(b"t\0", captured)                      # as itself again: a duplicate
    replicator.publish("t", np.full(N, 2.0))
    assert [value[0] for value in receiver.take(2)] == [1.0, 2.0]
    eventually(lambda: receiver.follower.duplicates["t"] == 1, what="the duplicate counted")
    assert receiver.follower.rejected == {"bad payload tag": 1}
    assert not receiver.reader.has_data()            # nothing else was delivered


def test_the_reader_sees_the_value_written_not_what_the_writer_did_next(link) -> None:
    replicator, follower, inbox = link
    replicator.add("t")
    _follow(follower, replicator, "t", from_seq=0)
    array = np.zeros(N)
    replicator.publish("t", array)
    array[:] = 7.0                               # right after write
    replicator.publish("t", array)
    array[:] = 9.0
    got = inbox.wait("t", 2)
    assert not got[0].any() and (got[1] == 7.0).all()


def test_the_reader_sees_the_value_written_when_it_lands_in_a_slot(landing) -> None:
    replicator, receiver = landing
    array = np.zeros(N)
    replicator.publish("t", array)
    array[:] = 7.0
    assert not receiver.take(1)[0].any()
    assert receiver.landed == 1


def test_payload_nonces_never_repeat_across_a_senders_incarnations(monkeypatch) -> None:
    seen: list[tuple[bytes, int]] = []
    for _ in range(3):                           # a writer restarted twice
        replicator = Replicator(KEY)
        try:
            wire = Wire(replicator, monkeypatch)
            for topic in ("a", "b"):
                replicator.add(topic)
            for i, topic in zip(range(6), itertools.cycle("ab")):
                replicator.publish(topic, np.full(N // 8, float(i)))
            replicator.flush()
            for parts in wire.sent:
                incarnation, _, _, _, nonce, _ = replication.INFO.unpack(parts[0])
                seen.append((incarnation, nonce))
        finally:
            replicator.close()
    assert len(seen) == 18 and len(set(seen)) == 18       # (key, nonce) pairs
    assert len({incarnation for incarnation, _ in seen}) == 3   # a key per incarnation


@pytest.fixture
def link():
    replicator, inbox = Replicator(KEY), Inbox()
    follower = Follower(KEY, inbox)
    yield replicator, follower, inbox
    follower.close()
    replicator.close()


# -- the ring's side -----------------------------------------------------------------
@pytest.fixture
def pool():
    owner = ShmRing.create(segment_name("claim"), 64 * 1024, 2, N * 8)
    writer, reader = ShmRing.attach(owner.name), ShmRing.attach(owner.name)
    yield owner, writer, reader
    gc.collect()
    for ring in (reader, writer, owner):
        ring.close()


def _meta() -> bytes:
    return codec.encode(np.zeros(N))[1]


def test_a_landed_array_is_staged_without_a_copy_and_read_from_its_slot(pool) -> None:
    _, writer, reader = pool
    landed = writer.claim(_meta(), N * 8)
    np.frombuffer(landed.buffer, np.float64)[:] = 5.0
    slot = landed.slot
    assert writer.write(landed, timeout=0.0)
    (view,), _, _ = reader.drain()
    assert (view == 5.0).all() and not view.flags.writeable
    start = np.frombuffer(reader._pool, np.uint8).ctypes.data + slot * reader.core.stride
    assert view.__array_interface__["data"][0] == start          # the slot itself
    del view, landed
    gc.collect()
    eventually(lambda: writer.core.slots_used() == 0, what="the slot freed by the reader")


def test_a_claimed_slot_is_freed_when_abandoned_or_dropped_and_never_read(pool) -> None:
    _, writer, reader = pool
    assert writer.write(np.zeros(N), timeout=0.0)
    assert len(reader.drain()[0]) == 1                   # (read, and its slot back)
    gc.collect()
    first, second = writer.claim(_meta(), N * 8), writer.claim(_meta(), N * 8)
    assert writer.claim(_meta(), N * 8) is None          # both slots claimed
    assert writer.write(np.ones(N), timeout=0.0) is False   # no slot: dropped (a gap)
    first.abandon()                                      # its tag failed
    del second                                           # dropped on its way
    gc.collect()
    assert writer.core.slots_used() == 0
    assert writer.write(np.full(N, 2.0), timeout=0.0)
    values, _, gaps = reader.drain()
    assert [value[0] for value in values] == [2.0] and gaps == 1   # neither claim read
    del values
    reader.resume_reader()                               # (a reader restart ...)
    third = writer.claim(_meta(), N * 8)
    reader.resume_reader()
    assert writer.core.slots_used() == 1                 # ... leaves a claim alone)
    third.abandon()


def test_a_landed_array_staged_in_another_ring_is_copied(pool) -> None:
    _, writer, _ = pool
    other = ShmRing.create(segment_name("other"), 64 * 1024, 1, N * 8)
    reader = ShmRing.attach(other.name)
    try:
        landed = writer.claim(_meta(), N * 8)
        np.frombuffer(landed.buffer, np.float64)[:] = 3.0
        assert other.write(landed, timeout=0.0)
        (view,), _, _ = reader.drain()
        assert (view == 3.0).all()
        del landed, view
        gc.collect()
        assert writer.core.slots_used() == 0             # its own claim was let go
    finally:
        gc.collect()
        reader.close()
        other.close()
