"""A module's state as the State Editor shows it, and an edit turned back into state.

``state_view`` turns the dict ``run.state(name)`` gives into JSON views: numbers,
strings and booleans as they are; lists, tuples and dicts with their first items
(to a bounded depth); numpy arrays with shape, dtype and a summary, small ones with
their values, 2-D numeric ones as a picture (``png_of``); anything else by its class
and ``repr``. A value typed into it is made the field's type by
``pb3a.model.state_edits.coerce``, as ``pb3a set`` does.
"""

from __future__ import annotations

import math
import struct
import zlib
from typing import Any
from urllib.parse import quote

import numpy as np

from pb3a.model.state_edits import is_plain

ITEMS_SHOWN = 50            # items of a list or dict shown at once
DEPTH = 3                   # container levels shown below the path asked for
ARRAY_VALUES = 64           # arrays up to this size come with their values, editable
REPR_CHARS = 200
TEXT_CHARS = 10_000         # a longer string is cut
IMAGE_SHORT_SIDE = 256      # pixels: small arrays are scaled up (nearest neighbour) to this
IMAGE_LONG_SIDE = 4096      # ... but never beyond this


class FieldNotFound(LookupError):
    """A path that names nothing in the state."""


def state_view(module: str, cls: str, state: dict[str, Any], path: str = "") -> dict[str, Any]:
    """The State Editor's view of ``state`` below ``path`` ("" for the whole state; dots
    separate keys and indices): the fields of the container there, or the one value."""
    value = find(state, path)
    if value is state or isinstance(value, (dict, list, tuple)):
        items = _items(value)
        fields = {str(key): view(item, module, _join(path, key), DEPTH)
                  for key, item in items[:ITEMS_SHOWN]}
        shown: dict[str, Any] = {"module": module, "class": cls, "path": path, "fields": fields}
        if len(items) > ITEMS_SHOWN:
            shown["more"] = len(items) - ITEMS_SHOWN
        return shown
    return {"module": module, "class": cls, "path": path,
            "fields": {path.rpartition(".")[2]: view(value, module, path, DEPTH)}}


def find(state: dict[str, Any], path: str) -> Any:
    """The value at ``path`` in ``state``; FieldNotFound saying where the path ends."""
    value: Any = state
    steps = [step for step in path.split(".") if step]
    for number, step in enumerate(steps):
        value = _child(value, step, ".".join(steps[:number]) or "the state")
    return value


def view(value: Any, module: str, path: str, depth: int) -> dict[str, Any]:
    """One value's JSON view (see the module's docstring); ``depth``: container levels
    still shown below it."""
    if isinstance(value, (bool, np.bool_)):
        return {"type": "bool", "value": bool(value), "editable": True}
    if isinstance(value, (int, np.integer)):
        return {"type": "int", "value": int(value), "editable": True}
    if isinstance(value, (float, np.floating)):
        number = float(value)
        if math.isfinite(number):
            return {"type": "float", "value": number, "editable": True}
        return {"type": "float", "value": None, "text": repr(number), "editable": True}
    if isinstance(value, str):
        shown = {"type": "str", "value": value[:TEXT_CHARS], "editable": True}
        if len(value) > TEXT_CHARS:
            shown.update(truncated=True, editable=False, length=len(value))
        return shown
    if value is None:
        return {"type": "none", "value": None, "editable": True}
    if isinstance(value, np.ndarray):
        return _array_view(value, module, path)
    if isinstance(value, (list, tuple, dict)):
        kind = "dict" if isinstance(value, dict) else "tuple" if isinstance(
            value, tuple) else "list"
        shown = {"type": kind, "length": len(value), "editable": is_plain(value)}
        if depth <= 0:
            shown["truncated"] = True
            return shown
        items = _items(value)
        shown["items"] = {str(key): view(item, module, _join(path, key), depth - 1)
                          for key, item in items[:ITEMS_SHOWN]}
        if len(items) > ITEMS_SHOWN:
            shown["more"] = len(items) - ITEMS_SHOWN
        return shown
    return {"type": "object", "class": f"{type(value).__module__}.{type(value).__qualname__}",
            "repr": _short_repr(value), "editable": False}


def _array_view(array: np.ndarray, module: str, path: str) -> dict[str, Any]:
    numeric = array.dtype.kind in "biuf"
    shown: dict[str, Any] = {"type": "ndarray", "shape": list(array.shape),
                             "dtype": str(array.dtype), "summary": None,
                             "editable": numeric and array.size <= ARRAY_VALUES}
    if numeric and array.size:
        finite = array[np.isfinite(array)] if array.dtype.kind == "f" else array
        if finite.size:
            # (the mean of values near the largest float overflows: JSON has no inf)
            with np.errstate(over="ignore"):
                mean = float(finite.mean(dtype=np.float64))
            shown["summary"] = _plain_values({"min": float(finite.min()),
                                              "max": float(finite.max()), "mean": mean})
    if array.size <= ARRAY_VALUES:
        shown["value"] = _plain_values(array.tolist()) if numeric else None
        if not numeric:
            shown["repr"] = _short_repr(array)
        elif array.dtype.kind == "f" and not np.isfinite(array).all():
            # (null in the values: the words say which, so the page shows them and
            # sends an untouched one back as it is, not as 0)
            flat = array.ravel()
            shown["nonfinite"] = {str(i): repr(float(flat[i]))
                                  for i in np.flatnonzero(~np.isfinite(flat))}
    if numeric and array.ndim == 2 and array.size:
        shown["image"] = f"/api/modules/{module}/image?path={quote(path)}"
    return shown


def _plain_values(value: Any) -> Any:
    """Nested lists (or a dict) of numbers with NaN and infinities as None (JSON has
    none)."""
    if isinstance(value, list):
        return [_plain_values(item) for item in value]
    if isinstance(value, dict):
        return {key: _plain_values(item) for key, item in value.items()}
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def png_of(array: Any) -> bytes:
    """A 2-D numeric array as a grey PNG, min to max as black to white (NaN black), scaled
    up by whole pixels until its short side has ``IMAGE_SHORT_SIDE`` pixels."""
    if not isinstance(array, np.ndarray):
        raise ValueError(f"only a 2-D numeric array has an image; this is a "
                         f"{type(array).__name__}")
    if array.ndim != 2 or array.dtype.kind not in "biuf" or not array.size:
        raise ValueError(f"only a non-empty 2-D numeric array has an image; this one is "
                         f"{array.dtype} of shape {list(array.shape)}")
    values = array.astype(np.float64)
    finite = np.isfinite(values)
    low = float(values[finite].min()) if finite.any() else 0.0
    high = float(values[finite].max()) if finite.any() else 0.0
    span = high - low if high > low else 1.0
    grey = np.where(finite, (values - low) * (255.0 / span), 0.0).astype(np.uint8)
    rows, cols = grey.shape
    scale = max(1, min(math.ceil(IMAGE_SHORT_SIDE / min(rows, cols)),
                       IMAGE_LONG_SIDE // max(rows, cols)))
    grey = np.repeat(np.repeat(grey, scale, axis=0), scale, axis=1)
    return _png(grey)


def _png(grey: np.ndarray) -> bytes:
    """PNG bytes of an 8-bit grey image (no filter; zlib), as the PNG specification
    lays them out: signature, IHDR, IDAT, IEND."""
    height, width = grey.shape
    raw = np.zeros((height, width + 1), dtype=np.uint8)     # each row: filter byte 0, pixels
    raw[:, 1:] = grey

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
            + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6)) + chunk(b"IEND", b""))


def _items(value: Any) -> list[tuple[Any, Any]]:
    return list(value.items()) if isinstance(value, dict) else list(enumerate(value))


def _child(value: Any, step: str, where: str) -> Any:
    if isinstance(value, dict):
        for key, item in value.items():
            if str(key) == step:
                return item
        raise FieldNotFound(f"{where} has no key {step!r}")
    if isinstance(value, (list, tuple, np.ndarray)):
        try:
            index = int(step)
            return value[index]
        except (ValueError, IndexError):
            raise FieldNotFound(f"{where} has no item {step!r} (it has {len(value)})") from None
    raise FieldNotFound(f"{where} is a {type(value).__name__}: it has no {step!r} inside")


def _join(path: str, key: Any) -> str:
    return f"{path}.{key}" if path else str(key)


def _short_repr(value: Any) -> str:
    try:
        text = repr(value)
    except Exception as exc:             # a broken __repr__ must not break the view
        text = f"<{type(value).__name__}: repr failed: {exc}>"
    return text if len(text) <= REPR_CHARS else text[:REPR_CHARS - 3] + "..."
