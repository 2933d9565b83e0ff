"""Ports and modules without a runtime: types, policies, counters, state reflection."""

from __future__ import annotations

import collections
import threading
import time

import numpy as np
import pytest
from conftest import eventually

from pb3a import Input, Module, Output, RuntimeTimeout
from pb3a.model.ports import WRITE_WAIT_S, Policy, WaitCounter


class Sensor(Module):
    ranges = Output(np.ndarray, shape=(16,), dtype="float32")
    label = Output(str)
    anything = Output(object)


class Reader(Module):
    latest = Input(float)
    queued = Input(int, policy="queue:3")
    gain = 2.0
    history: list = []
    _private = 5

    def helper(self) -> int:
        return 1


class Careful(Module):
    x = Input(int, policy="lossless:2")


class Child(Reader):
    extra = Input(float)
    offset = 1


def test_write_type_checks_in_the_writer_and_sends_nothing_on_error() -> None:
    sensor = Sensor()
    seen: list = []
    sensor.label.connect("probe", seen.append)
    with pytest.raises(TypeError, match=r"label.*str.*int"):
        sensor.label.write(3)
    assert seen == [] and sensor.label.written == 0
    sensor.label.write("ok")
    assert seen == ["ok"]


class Numbers(Module):
    level = Output(float)
    count = Output(int)


def test_a_number_of_another_numeric_type_is_written_as_the_port_s() -> None:
    """A float output refused 1 and ``np.float32(0.5)`` (and ``np.clip`` of an int
    gives an ``int64``, which an int output refused), though an int output may feed a
    float input: each is written as the port's own type. A bool is no number here."""
    numbers = Numbers()
    levels: list = []
    counts: list = []
    numbers.level.connect("probe", levels.append, lambda batch: levels.extend(batch))
    numbers.count.connect("probe", counts.append, lambda batch: counts.extend(batch))
    for value in (1, np.float32(0.5), np.int64(3), np.float64(2.5)):
        numbers.level.write(value)
    numbers.level.write_many([2, np.float32(1.5)])
    numbers.count.write(np.int64(7))
    numbers.count.write_many([np.int32(8), 9])
    assert levels == [1.0, 0.5, 3.0, 2.5, 2.0, 1.5]
    assert [type(value) for value in levels] == [float] * 3 + [np.float64] + [float] * 2
    # (a float64 is a float: kept as it is, as any value of the port's type)
    assert counts == [7, 8, 9] and [type(value) for value in counts] == [int] * 3
    for port, value in ((numbers.level, True), (numbers.level, "1"), (numbers.count, 1.0)):
        with pytest.raises(TypeError, match="carries"):
            port.write(value)
    # (numpy's bool was said to be a "bool", as if the port had refused True)
    with pytest.raises(TypeError, match=r"carries int, got numpy\.bool"):
        numbers.count.write(np.True_)
    assert numbers.level.written == 6 and numbers.count.written == 3


def test_write_checks_array_shape_and_dtype() -> None:
    sensor = Sensor()
    sensor.ranges.write(np.zeros(16, dtype="float32"))
    with pytest.raises(TypeError, match="shape"):
        sensor.ranges.write(np.zeros(8, dtype="float32"))
    with pytest.raises(TypeError, match="dtype"):
        sensor.ranges.write(np.zeros(16, dtype="float64"))
    with pytest.raises(TypeError, match="ndarray"):
        sensor.ranges.write([0.0] * 16)
    sensor.anything.write({"any": "thing"})


def test_shape_and_dtype_only_for_arrays() -> None:
    with pytest.raises(TypeError, match=r"np\.ndarray"):
        Output(float, shape=(3,))
    with pytest.raises(TypeError, match="class"):
        Input("float")
    # a policy belongs to the input or the link: it named _Port.__init__, which nobody wrote
    with pytest.raises(TypeError, match=r"Output\(\) takes no 'policy'.*Input\(float, "
                                        r"policy=\.\.\.\)"):
        Output(float, policy="queue:8")


def test_compatibility_follows_subclasses() -> None:
    class Base:
        pass

    class Derived(Base):
        pass

    assert Input(Base).accepts(Output(Derived)) is None
    assert Input(object).accepts(Output(str)) is None
    assert "not" in Input(Derived).accepts(Output(Base))
    assert Input(str).accepts(Output(float)) is not None


def test_latest_policy_keeps_the_newest_value() -> None:
    port = Reader().latest
    assert not port.has_value and port.pending == 0
    with pytest.raises(LookupError, match="has no value"):
        port.read()
    assert port.read(default=None) is None
    for value in (1.0, 2.0, 3.0):
        port.deliver(value)
    assert port.pending == 1 and port.read() == 3.0
    assert port.pending == 0 and port.has_value and port.read() == 3.0
    assert port.received == 3 and port.drops == 0


def test_queue_policy_keeps_order_and_counts_overflow() -> None:
    port = Reader().queued
    for value in range(5):
        port.deliver(value)
    assert port.pending == 3 and port.drops == 2
    assert [port.read(), port.read(), port.read()] == [2, 3, 4]
    assert not port.has_value


def test_one_event_per_queued_value_and_one_per_latest_change() -> None:
    reader = Reader()
    for value in range(5):
        reader.queued.deliver(value)
    events = 0
    while reader.queued.take_event():
        events += 1
    assert events == 3                  # the two dropped values get no call
    for value in (1.0, 2.0):
        reader.latest.deliver(value)
    assert reader.latest.take_event() and not reader.latest.take_event()


def test_policies_parse_and_reject_bad_text() -> None:
    assert Policy.parse("latest") == Policy("latest", 1)
    assert Policy.parse("queue:16") == Policy("queue", 16)
    assert str(Policy.parse("queue")) == "queue:64"
    for bad in ("queue:0", "queue:-1", "fifo", "queue:x", 3):
        with pytest.raises(ValueError, match="latest"):
            Policy.parse(bad)


def test_state_is_reflected_from_public_attributes() -> None:
    reader = Child()
    state = reader.get_state()
    assert state == {"gain": 2.0, "history": [], "offset": 1}
    reader.note = "instance attributes count too"
    assert reader.get_state()["note"] == "instance attributes count too"
    reader.set_state({"gain": 4.0, "offset": 2})
    assert reader.gain == 4.0 and reader.offset == 2
    with pytest.raises(KeyError, match=r"no state 'gian' \(did you mean 'gain'\?\); its "
                                       r"state is: gain, history, note, offset"):
        reader.set_state({"gian": 1.0})
    with pytest.raises(KeyError, match=r"no state 'zzz'; its state is"):
        reader.set_state({"zzz": 1.0})


def test_mutable_defaults_are_not_shared_between_instances() -> None:
    a, b = Reader(), Reader()
    a.history.append(1)
    assert b.history == [] and Reader.history == []


def test_ports_are_collected_through_inheritance_and_cannot_be_assigned() -> None:
    assert set(Child.inputs) == {"latest", "queued", "extra"}
    assert set(Sensor.outputs) == {"ranges", "label", "anything"}
    with pytest.raises(AttributeError, match="cannot be assigned"):
        Child().latest = 3.0


def test_event_driven_is_detected_from_on_input() -> None:
    class Driven(Module):
        def on_input(self, port) -> None:
            pass

    assert Driven.is_event_driven() and not Reader.is_event_driven()


def test_changing_the_policy_carries_held_values_over() -> None:
    port = Reader().queued
    for value in (1, 2, 3):
        port.deliver(value)
    port.set_policy(Policy.parse("queue:2"))
    assert port.pending == 2 and port.drops == 1
    port.set_policy(Policy.parse("latest"))
    assert port.pending == 1 and port.read() == 3
    port.deliver(4)
    port.set_policy(Policy.parse("queue:8"))
    assert port.read() == 4 and not port.has_value


def test_write_many_checks_every_value_before_sending_any() -> None:
    sensor = Sensor()
    seen: list = []
    sensor.label.connect("probe", seen.append)
    with pytest.raises(TypeError, match="label"):
        sensor.label.write_many(["a", "b", 3])
    assert seen == [] and sensor.label.written == 0
    sensor.label.write_many(iter(["a", "b"]))
    assert seen == ["a", "b"] and sensor.label.written == 2


def test_deliver_many_applies_the_policy_once_per_batch() -> None:
    reader = Reader()
    reader.queued.deliver_many(list(range(10)), sent_at=None)
    assert reader.queued.read_all() == [7, 8, 9] and reader.queued.drops == 7
    assert reader.queued.take_events(10) == 3
    reader.latest.deliver_many([1.0, 2.0, 3.0])
    assert reader.latest.read() == 3.0 and reader.latest.take_events(10) == 1


def test_the_rate_a_module_reads_decays_once_values_stop_as_stats_says(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """``self.x.rate``, read inside the module, stayed at 49/s long after its writer was
    removed (set only on delivery), while ``stats()`` said 0.33."""
    clock = [100.0]
    monkeypatch.setattr("pb3a.model.ports.time.monotonic", lambda: clock[0])
    port = Reader().latest
    assert port.rate == 0.0
    for _ in range(101):                         # 50 values/s for two seconds
        port.deliver(1.0)
        clock[0] += 0.02
    assert port.rate == pytest.approx(50.0, rel=0.05)
    clock[0] += 3.0                              # the writer is gone
    assert port.rate == pytest.approx(1 / 3.02, rel=0.01)
    clock[0] += 7.0
    assert port.rate < 0.1


def test_lossless_policies_parse_and_bad_text_lists_them() -> None:
    assert Policy.parse("lossless:8") == Policy("lossless", 8)
    assert str(Policy.parse("lossless")) == "lossless:64"
    assert Policy.parse("lossless:8").lossless and not Policy.parse("queue:8").lossless
    assert str(Careful.inputs["x"].policy) == "lossless:2"
    for bad in ("lossless:0", "lossless:", "lossless:x", "lossy"):
        with pytest.raises(ValueError, match="'lossless' or 'lossless:N'"):
            Policy.parse(bad)


def test_a_lossless_queue_never_drops_and_a_read_wakes_whoever_waits_for_room() -> None:
    port = Careful().x
    woken: list[int] = []
    port._on_room = lambda: woken.append(port.pending)
    port.deliver_many([1, 2, 3])                  # (two feeders at once may overfill it)
    assert port.pending == 3 and port.drops == 0 and port.claim_room() == -1
    assert port.read() == 1 and woken == []       # still full
    assert port.read() == 2 and woken == [1]      # room: the receiver is told, once
    assert port.read() == 3 and woken == [1]
    assert port.claim_room() == 2 and woken == [1]


def test_put_waits_for_a_read_then_times_out_naming_the_link() -> None:
    port, counter = Careful().x, WaitCounter()
    port.put([1, 2], 1.0, "w.out->r.x", counter)
    assert counter.waits == 0                     # there was room
    reader = threading.Timer(0.1, port.read)
    reader.start()
    port.put([3], 5.0, "w.out->r.x", counter)     # waits for the read
    reader.join()
    assert port.read_all() == [2, 3] and counter.waits == 1 and counter.wait_s >= 0.05
    port.put([4, 5], 1.0, "w.out->r.x", counter)
    start = time.monotonic()
    with pytest.raises(RuntimeTimeout, match=r"lossless link w.out -> r.x timed out.*"
                       r"not taken a value for 0.2 s.*\(2 values were not sent\)"):
        port.put([6, 7], 0.2, "w.out->r.x", counter)
    assert 0.15 < time.monotonic() - start < 2 and port.read_all() == [4, 5]
    assert counter.waits == 2


def test_lossless_sinks_get_the_writers_timeout_and_dropping_ones_do_not() -> None:
    sensor = Sensor()
    seen: list = []
    sensor.label.connect("drop", lambda value: seen.append(("drop", value)))
    sensor.label.connect("wait", lambda value, timeout: seen.append(("wait", value, timeout)),
                         lambda values, timeout: seen.append(("many", values, timeout)),
                         lossless=True)
    sensor.label.write("a")
    sensor.label.write("b", timeout=0.5)
    sensor.label.write_many(["c"], timeout=2.0)
    assert seen == [("wait", "a", WRITE_WAIT_S), ("drop", "a"), ("wait", "b", 0.5),
                    ("drop", "b"), ("many", ["c"], 2.0), ("drop", "c")]
    assert WRITE_WAIT_S == 10.0 and sensor.label.written == 3


def test_a_write_that_times_out_is_sent_on_no_link_and_its_wait_is_counted() -> None:
    sensor = Sensor()
    counter, seen = WaitCounter(), []

    def stuck(value: str, timeout: float) -> None:
        counter.begin()
        counter.wait_s += timeout
        raise RuntimeTimeout("no room")
    sensor.label.connect("drop", seen.append)
    sensor.label.connect("stuck", stuck, lossless=True, counter=counter)
    with pytest.raises(RuntimeTimeout):
        sensor.label.write("a", timeout=0.25)
    assert sensor.label.written == 0 and seen == []        # not sent on any link
    sensor.label.disconnect("drop")
    assert sensor.label.wait_figures() == {"waits": 1, "wait_s": 0.25,
                                           "links": {"stuck": (1, 0.25)}}
    sensor.label.disconnect("stuck")
    assert sensor.label.wait_figures() == {"waits": 0, "wait_s": 0, "links": {}}


@pytest.mark.parametrize("timeout", [float("nan"), float("inf"), -1.0, "1"])
def test_a_write_timeout_that_is_not_seconds_is_refused_and_nothing_is_sent(timeout) -> None:
    """NaN made the wait for room spin for good, inf an OverflowError at every write."""
    sensor, seen = Sensor(), []
    sensor.label.connect("waits", lambda value, wait: seen.append(value), lossless=True)
    with pytest.raises((ValueError, TypeError), match="timeout must be a"):
        sensor.label.write("a", timeout=timeout)
    assert seen == [] and sensor.label.written == 0


class Emitter(Module):
    out = Output(int)


def test_cutting_a_lossless_link_inside_one_process_stops_a_write_waiting_on_it() -> None:
    # wired as a worker wires a lossless link inside one process: the write waits for
    # room in the input itself; cutting the link (relink, remove, a move) must not wait
    # for the write's timeout (it did: `remove` of the reader timed out after 10 s)
    emitter, reader, counter = Emitter(), Careful(), WaitCounter()
    target, key = reader.x, "w.out->r.x"
    emitter.out.connect(key, lambda value, timeout: target.put([value], timeout, key, counter),
                        lambda values, timeout: target.put(values, timeout, key, counter),
                        lossless=True, counter=counter)
    emitter.out.write_many([1, 2])
    failures: list[BaseException] = []

    def write() -> None:
        try:
            emitter.out.write(3, timeout=30.0)
        except RuntimeTimeout as exc:
            failures.append(exc)
    writer = threading.Thread(target=write, daemon=True)
    writer.start()
    eventually(lambda: counter.waits == 1, what="the write waiting for room")
    start = time.monotonic()
    assert emitter.out.disconnect(key)
    assert time.monotonic() - start < 2.0
    writer.join(5.0)
    assert not writer.is_alive() and len(failures) == 1
    assert "lossless link w.out -> r.x gave up: the link was cut" in str(failures[0])
    assert target.read_all() == [1, 2] and emitter.out.written == 2   # 3 was not sent
    assert counter.waits == 1 and counter.wait_s > 0


def _lossless_to(output, key: str) -> tuple:
    """A reader wired to ``output`` as a worker wires a lossless link inside one process;
    the reader's input, full (2 values), and the link's counter."""
    target, counter = Careful().x, WaitCounter()
    output.connect(key, lambda value, timeout: target.put([value], timeout, key, counter),
                   lambda values, timeout: target.put(values, timeout, key, counter),
                   lossless=True, counter=counter)
    target.deliver_many([0, 0])
    return target, counter


@pytest.mark.parametrize("many", [False, True], ids=["write", "write_many"])
def test_one_deadline_covers_a_write_on_every_lossless_link(many: bool) -> None:
    # two lossless links, each full: the first reader makes room after a while, the
    # second never does. The write waits its timeout in all (it waited the whole timeout
    # on each link in turn), then says which link it timed out on and that the value
    # went on the one before it (not taken back), and on no dropping link.
    emitter, seen = Emitter(), []
    first, _ = _lossless_to(emitter.out, "w.out->a.x")
    second, _ = _lossless_to(emitter.out, "w.out->b.x")
    emitter.out.connect("w.out->c.x", seen.append, lambda values: seen.extend(values))
    write = (lambda: emitter.out.write_many([7], timeout=2.0)) if many else (
        lambda: emitter.out.write(7, timeout=2.0))
    reader = threading.Timer(1.4, first.read)
    reader.start()
    start = time.monotonic()
    with pytest.raises(RuntimeTimeout, match=r"lossless link w.out -> b.x timed out.*"
                       r"it went on w.out -> a.x already \(a write is not taken back\)"):
        write()
    took = time.monotonic() - start
    reader.join()
    assert 1.9 < took < 3.0, took                    # 2 s in all, not 1.4 + 2
    assert first.read_all() == [0, 7] and second.read_all() == [0, 0] and seen == []
    assert emitter.out.written == 0


class Cells:
    """A mutable default of a class of the module's own."""

    def __init__(self) -> None:
        self.seen: dict = {}


class Keeper(Module):
    recent = collections.deque(maxlen=3)
    cells = Cells()
    table: dict = {}
    grid = np.zeros(3)
    label = "kept"


def test_every_mutable_default_is_copied_per_instance_not_only_lists_and_dicts() -> None:
    a, b = Keeper(), Keeper()
    a.recent.append(1)
    a.cells.seen[(0, 0)] = 1
    a.table["x"] = 1
    a.grid[0] = 1.0
    assert list(b.recent) == [] and b.cells.seen == {} and b.recent.maxlen == 3
    assert b.table == {} and not b.grid.any()
    assert list(Keeper.recent) == [] and Keeper.cells.seen == {}
    assert Keeper.table == {} and not Keeper.grid.any()
    assert a.get_state()["label"] is Keeper.label
