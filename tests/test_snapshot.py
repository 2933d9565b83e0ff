"""A snapshot lays a captured value out in shared memory, its arrays out of band, and
gives it back with the arrays mapped, not copied, and private to whoever restores it."""

from __future__ import annotations

import mmap
import time

import numpy as np
import pytest
from conftest import assert_same_arrays

from pb3a.transport.shm import live_segments, segment_name, unlink_name
from pb3a.transport.snapshot import Snapshot, make_room


def _value() -> dict:
    return {"c": np.arange(300_000, dtype=np.float64).reshape(600, 500),
            "fortran": np.asfortranarray(np.ones((64, 32), dtype=np.int16)),
            "strided": np.arange(1000, dtype=np.int32)[::3],     # not contiguous
            # (a strided view of a device's big-endian buffer: numpy's own pickle gave it
            # back little-endian, copied in band)
            "big_endian": np.arange(24, dtype=">f4").reshape(6, 4)[:, ::2],
            "empty": np.zeros(0, dtype=np.uint8),
            "raw": bytearray(b"x" * 5000), "small": {"count": 3, "name": "hoard"}}


def _memory_under(array: np.ndarray) -> object:
    """What holds the array's bytes in the end (past the views of views)."""
    while isinstance(array, np.ndarray):
        array = array.base
    return array.obj if isinstance(array, memoryview) else array


@pytest.fixture
def snapshot():
    segment = segment_name("state")
    make_room(segment, 4096)                  # too small: the capture makes it fit
    yield Snapshot.capture(_value(), segment, since=time.perf_counter())
    unlink_name(segment)


def test_a_value_comes_back_equal_with_its_arrays_mapped_from_the_segment(snapshot) -> None:
    value, want = snapshot.restore(), _value()
    for strided in ("strided", "big_endian"):
        want[strided] = want[strided].copy()         # (it comes back contiguous)
    assert_same_arrays(value, {k: want[k] for k in ("c", "fortran", "strided", "big_endian",
                                                    "empty")})
    assert value["big_endian"].dtype == np.dtype(">f4")
    assert value["raw"] == want["raw"] and value["small"] == want["small"]
    for mapped in ("c", "strided", "big_endian"):    # mapped, not copied
        assert isinstance(_memory_under(value[mapped]), mmap.mmap), mapped
    assert snapshot.nbytes > want["c"].nbytes and snapshot.capture_s > 0
    assert Snapshot.measure(_value()) >= snapshot.nbytes            # the room it takes


def test_what_a_restorer_writes_stays_its_own(snapshot) -> None:
    first = snapshot.restore()
    first["c"][:] = -1.0                        # writable, copy-on-write
    assert np.array_equal(snapshot.restore()["c"], _value()["c"])


def test_a_carried_snapshot_is_laid_out_again_elsewhere(snapshot) -> None:
    carried = snapshot.carry()
    assert carried.segment == "" and carried.nbytes == snapshot.nbytes
    with pytest.raises(ValueError, match="lay_out"):
        carried.restore()
    here = carried.lay_out(segment_name("state"))
    try:
        assert np.array_equal(here.restore()["c"], _value()["c"])
    finally:
        unlink_name(here.segment)
    assert here.segment not in live_segments()
