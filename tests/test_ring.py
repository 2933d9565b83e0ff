"""ShmRing on its own: wrap-around, gaps, zero-copy leases, limits, ownership."""

from __future__ import annotations

import gc
import logging
import os
import sys
import threading
import time

import numpy as np
import pytest
from conftest import eventually

from pb3a import Output, RuntimeTimeout
from pb3a.transport import codec
from pb3a.transport import ring as ring_module
from pb3a.transport.doorbell import new_bell
from pb3a.transport.ring import WRITE_TIMEOUT, ShmRing, sleep
from pb3a.transport.shm import live_segments, segment_name


def _ends(slots: int = 0, slot_bytes: int = 0, lossless: bool = False):
    """A 64 KiB ring (with a pool, if asked) and its writer and reader ends."""
    owner = ShmRing.create(segment_name("ring"), 64 * 1024, slots, slot_bytes, lossless)
    reader = ShmRing.attach(owner.name)
    writer = ShmRing.attach(owner.name)
    yield owner, writer, reader
    gc.collect()                      # views first: their callbacks touch the ring
    reader.close()
    writer.close()
    owner.close()


@pytest.fixture
def ring():
    yield from _ends()


def _drain(reader: ShmRing) -> tuple[list, int]:
    got: list = []
    total_gaps = 0
    while True:
        values, _, gaps = reader.drain()
        got += values
        total_gaps += gaps
        if not values:
            return got, total_gaps


def test_values_wrap_around_in_order(ring) -> None:
    _, writer, reader = ring
    expected = []
    for i in range(5000):                       # many times the ring's capacity
        value = ("x" * (i % 300), i) if i % 7 else b"raw bytes %d" % i
        assert writer.write(value, timeout=0.0) or _drain(reader)
        expected.append(value)
        if i % 50 == 0:
            got, gaps = _drain(reader)
            assert gaps == 0
            assert got == expected
            expected.clear()
    got, gaps = _drain(reader)
    assert got == expected and gaps == 0


def test_a_full_ring_drops_the_value_and_the_reader_counts_the_gap(ring) -> None:
    _, writer, reader = ring
    sent = 0
    while writer.write(sent, timeout=0.0):
        sent += 1
    assert not writer.write("dropped", timeout=0.0)
    got, _ = _drain(reader)
    assert got == list(range(sent))
    assert writer.write("after", timeout=0.0)
    got, gaps = _drain(reader)
    assert got == ["after"] and gaps == 2        # the failed probe and "dropped"


def test_large_arrays_are_zero_copy_views_held_until_released() -> None:
    owner = ShmRing.create(segment_name("ring"), 4 << 20)
    reader, writer = ShmRing.attach(owner.name), ShmRing.attach(owner.name)
    try:
        array = np.arange(1 << 17, dtype=np.float64)           # 1 MiB
        while writer.write(array, timeout=0.0):
            pass
        views, _, _ = reader.drain()
        assert len(views) >= 3
        assert not views[0].flags.writeable and not views[0].flags.owndata
        assert all(np.array_equal(v, array) for v in views)
        assert not writer.write(array, timeout=0.0)             # views still hold the space
        views.clear()
        gc.collect()
        assert writer.write(array, timeout=0.0)                 # released
    finally:
        views = None
        gc.collect()
        reader.close()
        writer.close()
        owner.close()


def test_oversized_value_names_the_fix(ring) -> None:
    """The advice names a port that takes it: an Output(object) carrying a large array
    was told to declare shape= and dtype= on it, which only an np.ndarray output takes."""
    _, writer, _ = ring
    with pytest.raises(ValueError, match=r"declare the output as Output\(np.ndarray, "
                       r"shape=\.\.\., dtype=\.\.\.\)"):
        writer.write(np.zeros(1 << 20))
    with pytest.raises(TypeError, match="shape and dtype may only be given"):
        Output(object, shape=(1 << 20,), dtype="float64")   # (what it was told to do)
    Output(np.ndarray, shape=(1 << 20,), dtype="float64")     # (what it is told now)


def test_attach_refuses_a_segment_that_is_not_a_ring() -> None:
    from pb3a.transport.shm import create_segment, unlink_segment
    segment = create_segment(segment_name("other"), 4096)
    try:
        with pytest.raises(ValueError, match="not a PB3A ring"):
            ShmRing.attach(segment.name.lstrip("/"))
    finally:
        unlink_segment(segment)


def test_owner_unlinks_and_readers_only_detach() -> None:
    owner = ShmRing.create(segment_name("ring"), 4096)
    name = owner.name
    reader = ShmRing.attach(name)
    reader.close()
    assert name in live_segments()
    owner.close()
    assert name not in live_segments()


def test_write_many_publishes_in_order_and_counts_what_did_not_fit(ring) -> None:
    _, writer, reader = ring
    assert writer.write_many(list(range(100))) == 100
    got, gaps = _drain(reader)
    assert got == list(range(100)) and gaps == 0
    fitted = writer.write_many(list(range(5000)), timeout=0.0)
    assert 0 < fitted < 5000
    got, gaps = _drain(reader)
    assert got == list(range(fitted))
    writer.write("next")
    got, gaps = _drain(reader)
    assert got == ["next"] and gaps == 5000 - fitted


def test_a_batch_into_a_stalled_reader_waits_once_in_all_then_drops_and_counts(ring) -> None:
    _, writer, reader = ring
    sent = 0
    while writer.write(sent, timeout=0.0):               # the reader is stalled: ring full
        sent += 1                                        # (the last write dropped)
    waits = writer.waits
    batch = [i if i % 2 else str(i) for i in range(50)]  # scalars and pickled values
    started = time.monotonic()
    assert writer.write_many(batch) == 0                 # the default wait, as a port's
    took = time.monotonic() - started
    assert writer.waits == waits + 1                     # one wait for the batch, not 50
    assert 0.9 * WRITE_TIMEOUT <= took < 3 * WRITE_TIMEOUT          # (it was 50 x WRITE_TIMEOUT)
    got, _ = _drain(reader)
    assert got == list(range(sent))
    assert writer.write("next")
    assert _drain(reader) == (["next"], 1 + 50)          # every dropped value counted


def test_scalars_keep_their_exact_type_and_value(ring) -> None:
    _, writer, reader = ring
    values = [0, -1, 2**63 - 1, -(2**63), 2**63, 10**30, True, False, 1.5, -0.0,
              float("inf"), 3 + 4j, None, "text"]
    assert writer.write_many(values) == len(values)
    got, gaps = _drain(reader)
    assert gaps == 0
    assert [type(v) for v in got] == [type(v) for v in values]
    assert got == values
    writer.write(float("nan"))
    (nan,), _ = _drain(reader)
    assert nan != nan


def test_arrays_of_any_plain_dtype_and_shape_survive(ring) -> None:
    _, writer, reader = ring
    values = [np.float32(1.5) * np.ones((3, 4), dtype="float32"), np.array(7),
              np.arange(5, dtype=">i4"), np.array(["2024-01-01"], dtype="datetime64[D]"),
              np.zeros(2, dtype=[("x", "f8"), ("n", "i2")]), np.ones((2, 3))[:, 1]]
    assert writer.write_many(values) == len(values)
    got, _ = _drain(reader)
    # again one by one: the writer now knows each array's record layout
    assert all(writer.write(value) for value in values)
    again, _ = _drain(reader)
    for sent, received in zip(values * 2, got + again, strict=True):
        assert received.dtype == sent.dtype and received.shape == sent.shape
        assert np.array_equal(received, sent)
        assert received.flags.writeable == (sent.dtype.names is not None)   # pickled: a copy


def test_the_reader_sleeps_until_rung_and_not_when_data_is_there(ring) -> None:
    _, writer, reader = ring
    bell = new_bell()
    try:
        writer.set_bell(bell)
        assert not sleep(bell, [reader.core], 0.01)        # nothing written: times out
        writer.write(1)                                    # nobody asleep: no ring
        assert sleep(bell, [reader.core], 5.0)             # data there: returns at once
        assert reader.drain()[0] == [1]

        woke = threading.Event()

        def sleeper() -> None:
            if sleep(bell, [reader.core], 5.0):
                woke.set()
        thread = threading.Thread(target=sleeper)
        thread.start()
        # The writer rings only once the reader has announced its sleep; whichever
        # order the two take, the sleeper must wake (Dekker's hand-shake).
        writer.write(2)
        assert woke.wait(5.0)
        thread.join(5.0)
        assert reader.drain()[0] == [2]
    finally:
        os.close(bell)


def test_sleep_skips_a_ring_closed_meanwhile() -> None:
    owner = ShmRing.create(segment_name("ring"), 4096)
    reader = ShmRing.attach(owner.name)
    core = reader.core
    reader.close()
    owner.close()
    bell = new_bell()
    try:
        assert not sleep(bell, [core], 0.01)
        assert not core.has_data()
        with pytest.raises(ValueError, match="closed"):
            core.drain(10, None)
    finally:
        os.close(bell)


def test_a_corrupt_record_is_reported_not_followed(ring) -> None:
    owner, writer, reader = ring
    writer.write(1)
    owner._data[0:4] = b"\x00\x00\x00\x00"        # record length 0: a broken writer
    with pytest.raises(RuntimeError, match="corrupt ring record"):
        reader.drain()


class _Refusal(Exception):
    """Pickles, but does not unpickle: ``_Refusal(message)`` lacks an argument."""

    def __init__(self, code: int, why: str) -> None:
        super().__init__(f"{code}: {why}")


def test_a_value_the_reader_cannot_decode_is_logged_counted_and_skipped(
        ring, caplog, monkeypatch) -> None:
    _, writer, reader = ring
    reader.label = "w.out->r.x"
    monkeypatch.setattr(ring_module, "UNDECODABLE_REPORT_S", 3600.0)
    caplog.set_level(logging.ERROR, logger="pb3a.ring")
    writer.write_many([1, _Refusal(7, "arm"), "two", _Refusal(8, "leg"), 3.0])
    values, _, gaps = reader.drain()
    assert (values, gaps) == ([1, "two", 3.0], 2)
    writer.write_many([_Refusal(9, "hand"), 4])
    values, _, gaps = reader.drain()                     # the link goes on: nothing retried
    assert (values, gaps) == ([4], 1)
    assert not reader.has_data()
    (record,) = [r for r in caplog.records if r.name == "pb3a.ring"]   # once per burst
    message = record.getMessage()
    assert "link w.out->r.x: 2 value(s) could not be decoded" in message
    assert "TypeError" in message and "missing 1 required positional argument" in message


@pytest.fixture(params=[False, True], ids=["dropping", "lossless"])
def either(request):
    """A 64 KiB ring of each kind."""
    yield from _ends(lossless=request.param)


def test_a_record_over_half_the_ring_goes_at_any_offset_while_the_reader_keeps_up(
        either) -> None:
    """Where the record would straddle the end, the pad to the end and the record
    together may not fit the ring even when it is empty: the pad goes first, the
    reader takes it, then the record goes at the start."""
    _, writer, reader = either
    bell = new_bell()
    writer.set_bell(bell)
    got: list = []
    gaps: list[int] = []
    stop = threading.Event()

    def receive() -> None:                               # a reader that keeps up
        while not stop.is_set():
            values, _, dropped = reader.drain()
            got.extend(values)
            gaps.append(dropped)
            sleep(bell, [reader.core], 0.5)

    receiver = threading.Thread(target=receive)
    receiver.start()
    try:
        big = b"x" * (48 * 1024)                         # the ring holds 64 KiB
        sent = []
        for small in (100, 20_000, 40_000, 60_000, 10):  # so its record starts anywhere
            for value in (b"s" * small, big):
                assert writer.write(value, timeout=2.0)
                sent.append(value)
        eventually(lambda: len(got) == len(sent), what="every value read")
    finally:
        stop.set()
        os.write(bell, (1).to_bytes(8, "little"))
        receiver.join(5)
        os.close(bell)
    assert got == sent and sum(gaps) == 0


def test_a_pad_to_the_end_written_for_a_record_that_then_has_no_room_is_harmless(
        ring) -> None:
    _, writer, reader = ring
    big = b"x" * (48 * 1024)
    assert writer.write(b"s" * 20_000, timeout=0.0)      # unread, at offset 0
    assert writer.core.head + len(big) > writer.capacity  # big would straddle the end
    assert not writer.write(big, timeout=0.0)            # padded to the end; no room after
    assert writer.core.head == writer.capacity
    assert not writer.write(big, timeout=0.0)            # no room at offset 0 either
    assert _drain(reader) == ([b"s" * 20_000], 0)
    assert writer.write(big, timeout=0.0)
    assert _drain(reader) == ([big], 2)                  # the two dropped, counted


def test_a_writer_waiting_for_room_publishes_the_pad_it_writes_meanwhile(either) -> None:
    """The pad to the end may find room only while the writer waits: the reader must
    see it then, or the record after it never has room (the wait runs out)."""
    _, writer, reader = either
    bell = new_bell()
    writer.set_bell(bell)
    assert writer.write(b"a" * 50_000, timeout=0.0)
    assert _drain(reader) == ([b"a" * 50_000], 0)
    unread = [b"b" * 10_000, b"c" * 3_000, b"d" * 17_000]   # the last one wraps around
    assert all(writer.write(value, timeout=0.0) for value in unread)
    big = b"x" * (48 * 1024)            # would straddle the end: a pad first, no room yet
    got: list = []
    stop = threading.Event()

    def receive() -> None:              # takes the values only once the writer waits
        eventually(lambda: writer.waits or stop.is_set(), what="the writer waiting")
        while not stop.is_set():
            got.extend(reader.drain()[0])
            sleep(bell, [reader.core], 0.5)

    receiver = threading.Thread(target=receive)
    receiver.start()
    try:
        assert writer.write(big, timeout=2.0)
        eventually(lambda: len(got) == 4, what="every value read")
    finally:
        stop.set()
        os.write(bell, (1).to_bytes(8, "little"))
        receiver.join(5)
        os.close(bell)
    assert got == [*unread, big] and writer.waits == 1


@pytest.fixture
def pool():
    """A ring with a pool of four 1 MiB slots, as a link of pinned 1 MiB arrays gets."""
    yield from _ends(slots=4, slot_bytes=1 << 20)


def _slot_of(view: np.ndarray, ring: ShmRing) -> int:
    pool = np.frombuffer(ring._pool, dtype=np.uint8)
    return (view.__array_interface__["data"][0] - pool.ctypes.data) // ring.core.stride


def test_pinned_arrays_travel_in_slots_freed_in_any_order_lowest_first(pool) -> None:
    _, writer, reader = pool
    arrays = [np.full(1 << 17, float(i)) for i in range(6)]
    assert all(writer.write(a, timeout=0.0) for a in arrays[:4])
    assert writer.statistics()["used"] >= 4 << 20      # the bytes sit in the slots
    views, _, _ = reader.drain()
    assert [v[7] for v in views] == [0.0, 1.0, 2.0, 3.0]
    assert not views[0].flags.writeable and not views[0].flags.owndata
    assert [_slot_of(v, reader) for v in views] == [0, 1, 2, 3]
    assert not writer.write(arrays[4], timeout=0.0)      # every slot viewed: dropped
    del views[2]                                        # slot 2 first, then slot 0
    del views[0]
    gc.collect()
    assert writer.write(arrays[4], timeout=0.0) and writer.write(arrays[5], timeout=0.0)
    fresh, _, gaps = reader.drain()
    assert gaps == 1                                    # the dropped array, counted
    assert [v[0] for v in fresh] == [4.0, 5.0]
    assert [_slot_of(v, reader) for v in fresh] == [0, 2]   # the lowest free slot first
    assert [v[9] for v in views] == [1.0, 3.0]          # held views were not overwritten


def test_a_writer_waits_for_a_slot_until_a_view_goes(pool) -> None:
    _, writer, reader = pool
    array = np.ones(1 << 17)
    for _ in range(4):
        writer.write(array)
    views, _, _ = reader.drain()
    released = threading.Timer(0.05, views.clear)
    released.start()
    try:
        assert writer.write(array, timeout=5.0)          # a slot comes back meanwhile
    finally:
        released.join()
    assert len(reader.drain()[0]) == 1


def test_a_new_reader_gets_back_the_slots_a_dead_one_held_but_not_unread_ones(pool) -> None:
    owner, writer, reader = pool
    array = np.ones(1 << 17)
    for _ in range(2):
        writer.write(array)
    held, _, _ = reader.drain()               # the reader "dies" holding two views
    writer.write(array * 3)                   # ... and one array it never read
    successor = ShmRing.attach(owner.name)
    try:
        successor.resume_reader()
        assert successor.core.slots_used() == 1
        (unread,), _, _ = successor.drain()
        assert unread[0] == 3.0
    finally:
        unread = None
        gc.collect()
        successor.close()
    assert len(held) == 2


def test_a_new_reader_counts_what_the_writer_dropped_while_none_read(pool) -> None:
    owner, writer, reader = pool
    reader.resume_reader()                    # a new ring's first reader: no gap yet
    array = np.ones(1 << 17)
    assert all(writer.write(array, timeout=0.0) for _ in range(4))
    held, _, gaps = reader.drain()            # the reader "dies" holding all four views
    assert len(held) == 4 and gaps == 0
    assert not any(writer.write(array, timeout=0.0) for _ in range(3))   # no slot: dropped
    successor = ShmRing.attach(owner.name)
    try:
        successor.resume_reader()             # as a restarted worker's link does
        assert writer.write(array * 2, timeout=0.0)
        (value,), _, gaps = successor.drain()
        assert value[0] == 2.0 and gaps == 3
    finally:
        value = None
        gc.collect()
        successor.close()


@pytest.mark.parametrize("died", ["before publishing", "between its two publishing stores"])
def test_a_new_writer_gets_back_slots_a_dead_one_took_but_never_published(pool, died) -> None:
    owner, writer, reader = pool
    array = np.ones(1 << 17)
    writer.write(array)
    kind, meta, body, length = writer._layout(codec.ARRAY, b"<f8;131072", array.nbytes)
    assert kind == codec.SLOT
    # a second array staged in a slot, and the writer dies before publishing it
    assert writer.core.stage_record(kind, meta, array, body, length, 0.0)
    if died == "between its two publishing stores":     # the count out, the head not
        words = owner._seg.buf[:512].cast("Q")
        words[32] = writer.core.seq                      # W_SEQ (see _ringcore.c)
        words.release()
    assert writer.core.slots_used() == 2
    successor = ShmRing.attach(owner.name)
    try:
        successor.resume_writer()
        assert successor.core.slots_used() == 1    # the published one stays taken
        assert successor.write(array * 5, timeout=0.0)
        views, _, gaps = reader.drain()
        assert [v[0] for v in views] == [1.0, 5.0]
        assert gaps == (died != "before publishing")   # a lost value that was counted
    finally:
        views = []
        successor.close()


def test_a_record_naming_a_slot_that_is_not_there_is_reported_and_skipped(
        pool, caplog) -> None:
    """Not followed: logged and counted as a drop; the records after it still go, and
    the slot of one whose array cannot be read is free again."""
    owner, writer, reader = pool
    caplog.set_level(logging.ERROR, logger="pb3a.ring")
    writer.write(np.ones(1 << 17))
    body = 40                                 # after the header and "<f8;131072", 8-aligned
    owner._data[body:body + 8] = (99).to_bytes(8, "little")
    writer.write(np.ones(1 << 17))            # a slot too small for its array ...
    second = writer.core.head - 64
    owner._data[second + 24:second + 34] = b"<f8;999999"
    writer.write(2.5)                         # ... and a value after them
    assert writer.core.slots_used() == 2
    values, _, gaps = reader.drain()
    assert values == [2.5] and gaps == 2
    assert "slot 99 of 4" in caplog.text
    assert writer.core.slots_used() == 1      # the second's slot is free (not the lost one)


@pytest.fixture
def lossless():
    """A lossless 64 KiB ring: its writer waits for room, then fails; it never drops."""
    yield from _ends(lossless=True)


def test_a_full_lossless_ring_makes_the_writer_fail_and_sends_nothing(lossless) -> None:
    _, writer, reader = lossless
    assert writer.lossless and reader.lossless
    writer.label = "w.out->r.x"
    sent = 0
    while writer.offer([sent]):                          # what fits, without waiting
        sent += 1
    with pytest.raises(RuntimeTimeout, match=r"lossless link w.out -> r.x timed out"):
        writer.write("no room", timeout=0.05)
    with pytest.raises(RuntimeTimeout, match=r"\(3 values were not sent\)"):
        writer.write_many(["a", "b", "c"], timeout=0.05)
    assert writer.waits == 2 and writer.wait_s >= 0.1
    got, gaps = _drain(reader)
    assert got == list(range(sent)) and gaps == 0       # nothing dropped: no gap
    assert writer.write("after", timeout=0.0)
    assert _drain(reader) == (["after"], 0)


def test_a_lossless_writer_waits_until_the_reader_takes_values(lossless) -> None:
    _, writer, reader = lossless
    sent = 0
    while writer.offer([sent]):
        sent += 1
    taken: list = []
    drained = threading.Timer(0.05, lambda: taken.extend(reader.drain(10)[0]))
    drained.start()
    try:
        assert writer.write_many([sent, sent + 1], timeout=5.0) == 2   # room comes back
    finally:
        drained.join()
    rest, gaps = _drain(reader)
    assert taken + rest == list(range(sent + 2)) and gaps == 0
    assert writer.waits >= 1


def test_a_lossless_writer_let_through_asks_for_a_flush_until_the_last_pause_ends(
        lossless) -> None:
    # A pause of the writer waits for its call: a write waiting for room asks the reader
    # to take the whole ring (its receiver then does, room in the input or not). The
    # flag must not outlive the pauses: left set, the ring would never hold back again.
    _, writer, reader = lossless
    sent = 0
    while writer.offer([sent]):
        sent += 1
    writer.let_through(True)
    writer.let_through(True)                     # (two pauses at once)
    taken: list = []

    def receiver() -> None:                      # (as a worker's receiver does)
        eventually(lambda: reader.flush_requested, what="the flush asked for")
        taken.extend(reader.drain(sent)[0])
    flushed = threading.Thread(target=receiver)
    flushed.start()
    try:
        assert writer.write(sent, timeout=5.0)     # the reader took it all: room
    finally:
        flushed.join()
    writer.let_through(False)
    assert reader.flush_requested                # one pause is still under way
    writer.let_through(False)
    assert not reader.flush_requested
    rest, gaps = _drain(reader)
    assert taken + rest == list(range(sent + 1)) and gaps == 0


@pytest.fixture
def lossless_pool():
    yield from _ends(slots=4, slot_bytes=1 << 20, lossless=True)


def test_a_lossless_writer_waits_for_a_slot_while_the_reader_holds_every_view(
        lossless_pool) -> None:
    _, writer, reader = lossless_pool
    array = np.ones(1 << 17)
    for _ in range(4):
        writer.write(array)
    views, _, _ = reader.drain()                         # the input holds four views
    with pytest.raises(RuntimeTimeout):
        writer.write(array, timeout=0.05)                # no slot: no drop either
    released = threading.Timer(0.05, views.pop)
    released.start()
    try:
        assert writer.write(array * 2, timeout=5.0)      # a slot comes back meanwhile
    finally:
        released.join()
    fresh, _, gaps = reader.drain()
    assert gaps == 0 and [v[0] for v in fresh] == [2.0]


def test_a_closing_lossless_link_asks_its_reader_to_take_everything(lossless) -> None:
    owner, writer, reader = lossless
    bell = new_bell()
    try:
        writer.set_bell(bell)
        assert not reader.flush_requested
        writer.request_flush()
        assert reader.flush_requested and owner.flush_requested
        assert sleep(bell, [], 0.0)                       # and its doorbell rang
    finally:
        os.close(bell)


def test_a_writer_waiting_for_room_gives_up_when_its_link_is_cut(lossless) -> None:
    _, writer, _ = lossless
    while writer.offer([0]):
        pass
    threading.Timer(0.05, writer.cancel).start()
    with pytest.raises(RuntimeTimeout):
        writer.write(1, timeout=10.0)
    assert writer.wait_s < 5


def _interrupted(*args: object, **kwargs: object) -> None:
    raise KeyboardInterrupt


def test_a_ring_interrupted_as_it_is_made_leaves_no_segment(monkeypatch) -> None:
    # (a Ctrl-C or SIGHUP that came as `pb3a scenario` made its first ring left that
    # segment behind, for the resource tracker to unlink after the process was gone)
    from types import SimpleNamespace

    from pb3a.node.wiring import Wiring

    before = live_segments(os.getpid())
    monkeypatch.setattr(ring_module, "RingCore", _interrupted)       # inside create
    with pytest.raises(KeyboardInterrupt):
        ShmRing.create(segment_name("ring"), 4096)
    assert live_segments(os.getpid()) == before
    monkeypatch.undo()
    create, made = ShmRing.create, []

    def made_then_interrupted(*args: object) -> ShmRing:
        made.append(create(*args))        # as if the signal came as create returned
        raise KeyboardInterrupt

    monkeypatch.setattr(ShmRing, "create", made_then_interrupted)
    wiring = SimpleNamespace(rings={})
    with pytest.raises(KeyboardInterrupt):
        Wiring._ring(wiring, "a.out->b.x", ring_module.RingSize(4096, 0, 0))
    assert live_segments(os.getpid()) == before and wiring.rings == {}
    made[0].close()                       # (this process's mapping, the name gone already)


def test_a_ring_whose_name_is_taken_leaves_that_segment_alone() -> None:
    # (the node unlinked whatever held the name, a segment it had not made)
    from types import SimpleNamespace

    from pb3a.node.wiring import Wiring
    from pb3a.transport import shm

    taken = segment_name("ring")
    other = shm.create_segment(taken, 4096)
    try:
        wiring = SimpleNamespace(rings={})
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr("pb3a.node.wiring.segment_name", lambda kind: taken)
            with pytest.raises(FileExistsError):
                Wiring._ring(wiring, "a.out->b.x", ring_module.RingSize(4096, 0, 0))
        assert taken in live_segments(os.getpid())
    finally:
        shm.unlink_segment(other)


def test_a_segment_whose_views_outlive_its_close_goes_quietly() -> None:
    """A segment closed while a view of it lives is left to the garbage collector, whose
    ``__del__`` closed it again and printed "Exception ignored ... BufferError" (at an
    interrupted launcher's exit: `pb3a scenario` stopped by a SIGHUP said so); and so
    is one never closed, a view of it alive (a ring made or attached as the interrupt
    came, before anyone could close it: the full suite saw the SIGHUP test say so)."""
    from pb3a.transport.shm import close_segment, create_segment

    segment = create_segment(segment_name("ring"), 4096)
    part = segment.buf[:16]
    close_segment(segment)                     # (the view: it cannot close yet)
    segment.unlink()
    unclosed = create_segment(segment_name("ring"), 4096)
    other = unclosed.buf[:16]
    unclosed.unlink()
    unraisable = []
    hook, sys.unraisablehook = sys.unraisablehook, unraisable.append
    try:
        del segment, unclosed
        gc.collect()
        assert bytes(part[:2]) == b"\0\0"      # the view still reads its mapping
        del part, other
        gc.collect()
    finally:
        sys.unraisablehook = hook
    assert unraisable == []
