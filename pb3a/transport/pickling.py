"""``dumps``: objects pickled to travel between pb3a's processes, with cloudpickle, which
sends by value what the far side cannot import (a module class defined in the
launching script), keeping the file its code was written in.

cloudpickle names every code object it sends by value ``<dynamic-code>``, so that a
payload does not depend on where the code was written. A script's module class then
failed in its worker with a traceback that named no file. Here each such code object
keeps its ``co_filename``: the traceback names the script and the line, and shows the
line where the file is on that machine. The far side needs nothing but pb3a.
"""

from __future__ import annotations

import collections
import io
import pickle
import sys
import types
from collections.abc import Callable, Mapping
from typing import Any

import cloudpickle
import numpy as np

_DYNAMIC = "<dynamic-code>"         # (what cloudpickle names code it sends by value)
_reduce_code = cloudpickle.Pickler.dispatch_table[types.CodeType]
_CLOUDPICKLE_OWN, *_COPYREG = cloudpickle.Pickler.dispatch_table.maps


def _code_with_its_file(code: types.CodeType) -> Any:
    """The reduction of ``code``: cloudpickle's, of a copy named as cloudpickle names it,
    and the file's name beside it, put back on arrival (``_located``)."""
    if code.co_filename == _DYNAMIC:
        return _reduce_code(code)           # (the copy: its nested code comes back here)
    return _located, (code.replace(co_filename=_DYNAMIC), code.co_filename)


def _located(code: types.CodeType, filename: str) -> types.CodeType:
    return code.replace(co_filename=filename)


# The Python every process of a system runs (major.minor): a class sent by value is
# pickled bytecode, which another version reads wrongly or crashes on (3.12's in 3.13:
# a segfault).
PYTHON = f"{sys.version_info.major}.{sys.version_info.minor}"


def _refuse_open_file(file: io.TextIOWrapper) -> Any:
    """An open text file is refused, as a binary one is. cloudpickle sends one open for
    reading as an in-memory copy of what it holds (read whole at every checkpoint): a
    module's log file, moved or restored, was then written to memory, never to disk,
    and nothing said so. (The standard streams stay cloudpickle's: the far side's own.)"""
    if file is sys.stdout or file is sys.stderr:
        return _CLOUDPICKLE_OWN[io.TextIOWrapper](file)
    raise pickle.PicklingError(f"cannot pickle the open file {getattr(file, 'name', '?')!r}"
                               " (a file stays on its machine)")


def _array_in_order(array: np.ndarray) -> Any:
    """numpy's own reduction of ``array``, made contiguous first if it is not: numpy
    pickles a non-contiguous array by its values in native order, so a big-endian one
    (``>f4``, a strided view of a device's buffer) came back little-endian, and copied
    in the pickle instead of sent as an out-of-band buffer."""
    if not (array.flags.c_contiguous or array.flags.f_contiguous):
        array = np.ascontiguousarray(array)
    return array.__reduce_ex__(5)


class _Pickler(cloudpickle.Pickler):
    """cloudpickle's pickler; code by value is sent with its file's name beside it, an
    open file is refused, and an array keeps its dtype. (Dispatch table entries, not a
    ``reducer_override``: that runs for every object.)"""

    dispatch_table = collections.ChainMap(    # (as deep as cloudpickle's; copyreg's live)
        {**_CLOUDPICKLE_OWN, types.CodeType: _code_with_its_file,
         io.TextIOWrapper: _refuse_open_file, np.ndarray: _array_in_order}, *_COPYREG)


def dumps(obj: Any, *,
          buffer_callback: Callable[[pickle.PickleBuffer], Any] | None = None) -> bytes:
    """``obj`` pickled (protocol 5; ``buffer_callback`` takes its out-of-band buffers);
    read with ``pickle.loads`` or ``cloudpickle.loads``."""
    with io.BytesIO() as file:
        _Pickler(file, protocol=5, buffer_callback=buffer_callback).dump(obj)
        return file.getvalue()


# what pickling a value that cannot be pickled raises (a lock: TypeError; a local
# function under plain pickle: AttributeError)
PICKLING_ERRORS = (TypeError, AttributeError, pickle.PicklingError)


class Unpicklable(TypeError):
    """A module's state that cannot be pickled; the message is ``unpicklable_reason``'s."""


def unpicklable_reason(exc: Exception, items: Any) -> str:
    """``exc``, raised pickling ``items`` (a module's state, an answer), in words that
    name the fields that cannot be pickled and what to do (pickle's own error names
    only the type: "cannot pickle '_thread.lock' object")."""
    fields = unpicklable(items) if isinstance(items, Mapping) else []
    return f"{type(exc).__name__}: {exc}" + (
        f" (in {', '.join(map(repr, fields))}: state that holds a lock, a file or a socket "
        "cannot leave its module; a name beginning with '_' keeps it out of the state)"
        if fields else "")


def unsendable_class_reason(cls: type, exc: Exception) -> str:
    """Why ``cls``, a class that goes by value (defined in a script or a function),
    could not be pickled (``exc``): pickle's error, and the class attributes that hold
    what cannot travel with it."""
    names = unpicklable({name: value for name, value in vars(cls).items()
                         if not name.startswith("__")})
    return (f"its class {cls.__qualname__} cannot be sent to its worker: "
            f"{type(exc).__name__}: {exc}" + (
                f" (class attributes {', '.join(map(repr, names))}: make what holds a "
                "lock, a file or a socket in setup(), under a name beginning with '_')"
                if names else ""))


def unpicklable(items: Mapping[str, Any]) -> list[str]:
    """The names of ``items`` whose values cannot be pickled: what to name when a whole
    state or class could not be (pickle's own error names only the type, such as
    ``'_thread.lock'``)."""
    names = []
    for name, value in items.items():
        try:
            dumps(value)
        except Exception:
            names.append(name)
    return names
