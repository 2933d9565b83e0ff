"""How a value becomes bytes in a ring record, and back.

numpy arrays of plain dtypes travel as raw bytes plus dtype and shape, so a
reader can map them without unpickling (structured arrays are pickled);
``bytes`` travel raw; 64-bit ``int`` and ``float`` are packed into the record
header by the ring itself; everything else is pickled (protocol 5). Local
rings live in segments only this user can open, so pickling is safe here;
remote links authenticate before they decode.
"""

from __future__ import annotations

import functools
import math
import pickle
from typing import Any

import numpy as np

PAD, PICKLE, ARRAY, BYTES, INT, FLOAT = 0, 1, 2, 3, 4, 5
SLOT = 6        # an ARRAY record whose bytes are in the ring's slot pool (ring.py)


def encode(value: Any) -> tuple[int, bytes, Any]:
    """Return ``(kind, meta, payload)``; payload supports the buffer protocol."""
    if type(value) is np.ndarray and value.dtype.names is None and not value.dtype.hasobject:
        array = np.ascontiguousarray(value)     # (makes 0-d arrays 1-d: keep value.shape)
        return ARRAY, _array_meta_bytes(array.dtype.str, value.shape), array
    if type(value) is bytes:
        return BYTES, b"%d" % len(value), value
    return PICKLE, b"", pickle.dumps(value, protocol=5)


def payload_size(kind: int, payload: Any) -> int:
    """Bytes the payload takes in the ring."""
    return payload.nbytes if kind == ARRAY else len(payload)


@functools.lru_cache(maxsize=256)       # a link carries few distinct dtypes and shapes
def _array_meta_bytes(dtype: str, shape: tuple[int, ...]) -> bytes:
    return f"{dtype};{','.join(map(str, shape))}".encode()


@functools.lru_cache(maxsize=256)
def array_meta(meta: bytes) -> tuple[np.dtype, tuple[int, ...], int]:
    """dtype, shape and element count from an ARRAY record's meta."""
    dtype, _, text = meta.decode().partition(";")
    shape = tuple(int(n) for n in text.split(",") if n)
    return np.dtype(dtype), shape, math.prod(shape)


def decode_small(kind: int, meta: bytes, payload: memoryview) -> Any:
    """Decode into a value that owns its memory (the ring slot may be reused at once)."""
    if kind == PICKLE:
        return pickle.loads(payload)
    if kind == BYTES:
        return bytes(payload[:int(meta)])
    dtype, shape, count = array_meta(meta)
    array = np.frombuffer(payload, dtype=dtype, count=count).reshape(shape).copy()
    array.flags.writeable = False
    return array


def decode_owned(kind: int, meta: bytes, payload: Any) -> Any:
    """Decode a value that may keep its bytes (a received ZeroMQ frame): an array
    becomes a read-only view of them, no copy."""
    if kind == ARRAY:
        dtype, shape, count = array_meta(meta)
        array = np.frombuffer(payload, dtype=dtype, count=count).reshape(shape)
        array.flags.writeable = False
        return array
    return decode_small(kind, meta, memoryview(payload))


def local_copy(value: Any) -> Any:
    """What a reader in the same process gets: the same isolation a ring gives.

    Immutable scalars pass as they are; arrays are copied read-only; other
    objects are copied through pickle, exactly as across processes.
    """
    if value is None or type(value) in (int, float, bool, str, bytes, complex):
        return value
    if type(value) is np.ndarray and not value.dtype.hasobject:
        array = value.copy()
        array.flags.writeable = False
        return array
    return pickle.loads(pickle.dumps(value, protocol=5))
