"""A module's state set from JSON (the State Editor, ``pb3a set``): each value made the
type of the field's current value, or refused saying what the field takes; and set from
a program, checked against the field's kind (``checked``).

JSON writes 4.0 as 4 and has no tuples, numpy scalars or arrays, so a value sent as
JSON is not yet the value to set: ``coerce`` makes an int a float for a float field (a
numpy one of the same dtype), a nested list an array of the field's shape and dtype,
a list of int pairs the list of float pairs it replaces, and refuses what does not fit
(text for a number, 300 for an int8, 1e300 for a float32). ``floats_as_declared``
does the part of this that keeps a value TOML can write (3 for a float field is 3.0);
``configured`` the rest a configuration needs.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from pb3a.model.module import Module, reflective_state


def class_state(cls: Any) -> dict[str, Any]:
    """The class-level state of module class ``cls`` (its fields and their defaults),
    which a new module's state given as JSON is made the type of; nothing for a class
    that is no ``Module`` or defines its own ``get_state``, or a ``set_state`` not
    marked ``reflective`` (it alone knows its fields)."""
    if not (isinstance(cls, type) and issubclass(cls, Module)) or not reflective_state(cls):
        return {}
    return {name: getattr(cls, name) for name in cls.state_names()}


def is_plain(value: Any) -> bool:
    """Whether ``value`` is made of JSON types only (so it can be edited as JSON)."""
    if value is None or isinstance(value, (bool, int, str)):
        return True
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, (list, tuple)):
        return all(is_plain(item) for item in value)
    if isinstance(value, dict):
        return all(isinstance(key, str) and is_plain(item) for key, item in value.items())
    return False


def coerce(field: str, current: Any, new: Any) -> Any:
    """``new`` (from JSON) as the type of the field's ``current`` value; ValueError
    naming the field and what it takes."""
    def refuse(takes: str) -> ValueError:
        return ValueError(f"state {field!r} takes {takes}, got {new!r}")

    if isinstance(current, (bool, np.bool_)):
        if not isinstance(new, bool):
            raise refuse("true or false")
        return type(current)(new) if isinstance(current, np.bool_) else new
    if isinstance(current, (int, np.integer)):
        if isinstance(new, float) and new.is_integer():
            new = int(new)
        if not isinstance(new, int) or isinstance(new, bool):
            raise refuse("a whole number")
        try:
            return type(current)(new) if isinstance(current, np.integer) else new
        except OverflowError:
            raise refuse(f"a whole number a {type(current).__name__} holds") from None
    if isinstance(current, (float, np.floating)):
        if not isinstance(new, (int, float)) or isinstance(new, bool):
            raise refuse("a number")
        try:
            with np.errstate(over="ignore"):
                number = type(current)(new)
        except OverflowError:
            raise refuse(f"a number a {type(current).__name__} holds") from None
        if math.isfinite(new) and not math.isfinite(number):    # (1e300 as a float32: inf)
            raise refuse(f"a number a {type(current).__name__} holds")
        return number
    if isinstance(current, str):
        if not isinstance(new, str):
            raise refuse("a string")
        return new
    if current is None:
        return new
    if isinstance(current, np.ndarray):
        return _coerce_array(field, current, new)
    if isinstance(current, (list, tuple, dict)) and is_plain(current):
        want = dict if isinstance(current, dict) else list
        if not isinstance(new, want):
            raise refuse("an object ({...})" if want is dict else "a list ([...])")
        # (an item of the wrong kind was set as sent, and the module then failed at its
        # next step: each is made as a field is, and refused by its path, cal.offset)
        return _item_by_item(current, new,
                             lambda key, was, item: coerce(f"{field}.{key}", was, item))
    raise ValueError(f"state {field!r} is a {type(current).__name__}, which cannot be set "
                     "from JSON: set it from a program (run.set_state)")


def _item_by_item(current: dict[str, Any] | list[Any] | tuple[Any, ...],
                  new: dict[str, Any] | list[Any],
                  each: Callable[[Any, Any, Any], Any]) -> Any:
    """``new`` made item by item against ``current``: ``each(key, its item, the new
    item)`` for a key ``current`` has, or a list's index (an item beyond ``current``'s
    against its last); a key it does not have, and any item of an empty list, as sent;
    a tuple for a tuple."""
    if isinstance(current, dict):
        return {key: each(key, current[key], item) if key in current else item
                for key, item in new.items()}
    last = len(current) - 1
    items = [each(index, current[min(index, last)], item) if current else item
             for index, item in enumerate(new)]
    return tuple(items) if isinstance(current, tuple) else items


def checked(field: str, current: Any, new: Any, *, held: str = "it is") -> Any:
    """``new``, set from a program (``run.set_state``), checked against the kind of the
    field's ``current`` value: a number for a number (an int made a float for a float
    field, as an output's write does), true or false for a flag, text for text, a dict's
    items each so against the item it replaces; a field of another kind, or None, takes
    anything. ``TypeError`` naming the field (or the item's path: ``cal.offset``):
    ``kp="2.5"`` was set, and the module then failed at every step."""
    def refuse(takes: str) -> TypeError:
        return TypeError(f"state {field!r} takes {takes} ({held} {current!r}), got {new!r}")

    number = (int, float, np.integer, np.floating)
    if isinstance(current, (bool, np.bool_)):
        if not isinstance(new, (bool, np.bool_)):
            raise refuse("true or false")
    elif isinstance(current, number):
        if not isinstance(new, number) or isinstance(new, (bool, np.bool_)):
            raise refuse("a number")
        if isinstance(current, (float, np.floating)) and not isinstance(new, type(current)):
            return type(current)(new)
    elif isinstance(current, str) and not isinstance(new, str):
        raise refuse("text")
    elif isinstance(current, dict) and isinstance(new, dict):
        return {key: checked(f"{field}.{key}", current[key], item, held=held)
                if key in current else item for key, item in new.items()}
    return new


def configured(field: str, declared: Any, value: Any, *, owner: str = "its class") -> Any:
    """``value``, given to a module by its configuration (a system file, ``run.add``'s
    state), as the kind of the field's ``declared`` value (its class's default), as
    ``checked`` judges it; and made its type where the file's TOML cannot say it: a
    whole number a float for a float field, a list of numbers an array of the field's
    dtype (of any shape: the class's may be a placeholder), a list a tuple. ``owner``
    names the class in the message. TypeError or
    ValueError naming the field: ``kp = "2.5"`` passed every check, and the module then
    failed at every step (and refused the number that would mend it, judged by the text
    it then held)."""
    if isinstance(declared, np.ndarray) and isinstance(value, list):
        if declared.dtype.kind not in "biuf":      # (an array of objects: as it is given)
            return value
        return _coerce_array(field, declared, value, any_shape=True)
    if isinstance(declared, tuple) and isinstance(value, list):
        return _like(declared, value)
    return checked(field, declared, floats_as_declared(declared, value),
                   held=f"{owner} declares it")


def floats_as_declared(declared: Any, value: Any) -> Any:
    """``value`` (read from JSON or TOML) with each whole number made a float where the
    field's ``declared`` value (its class's default) holds a float: item by item in a list
    or tuple (an item beyond ``declared``'s takes the kind of its last), every item of a
    float array, key by key in a dict; anything else as it is. JSON writes 3.0 as 3: a
    configuration written from it gave a float field an int."""
    if type(value) is int and isinstance(declared, (float, np.floating)):
        return float(value)
    if isinstance(value, list) and isinstance(declared, np.ndarray):
        return _all_floats(value) if declared.dtype.kind == "f" else value
    if isinstance(value, list) and isinstance(declared, (list, tuple)) and declared:
        last = len(declared) - 1
        return [floats_as_declared(declared[min(index, last)], item)
                for index, item in enumerate(value)]
    if isinstance(value, dict) and isinstance(declared, dict):
        return {key: floats_as_declared(declared[key], item) if key in declared else item
                for key, item in value.items()}
    return value


def _all_floats(value: Any) -> Any:
    """Nested lists with every whole number in them made a float."""
    if isinstance(value, list):
        return [_all_floats(item) for item in value]
    return float(value) if type(value) is int else value


def _coerce_array(field: str, current: np.ndarray, new: Any,
                  any_shape: bool = False) -> np.ndarray:
    shape = "" if any_shape else f" of shape {list(current.shape)}"
    what = f"a nested list{shape} of {current.dtype} values"
    if current.dtype.kind not in "biuf":
        raise ValueError(f"state {field!r} is an array of {current.dtype}, which cannot be "
                         "set from JSON: set it from a program (run.set_state)")
    if not isinstance(new, list):
        raise ValueError(f"state {field!r} takes {what}, got {new!r}")
    try:
        array = np.asarray(new, dtype=np.float64 if current.dtype.kind == "f" else None)
    except (ValueError, TypeError):
        raise ValueError(f"state {field!r} takes {what}; the lists given are ragged or "
                         "hold something else than numbers") from None
    if array.shape != current.shape and not any_shape:
        raise ValueError(f"state {field!r} takes {what}, got shape {list(array.shape)}")
    if array.dtype.kind not in "biuf":
        raise ValueError(f"state {field!r} takes {what}, got {array.dtype} values")
    if current.dtype.kind in "iu" and not np.array_equal(array, np.round(array)):
        raise ValueError(f"state {field!r} takes {what}: whole numbers only")
    # (astype wraps what does not fit: 300 as an int8 was 44, 1e300 as a float32 inf)
    if current.dtype.kind in "iu" and array.size:
        held = np.iinfo(current.dtype)
        if array.min() < held.min or array.max() > held.max:
            raise ValueError(f"state {field!r} takes {what}: each from {held.min} to "
                             f"{held.max}")
    with np.errstate(over="ignore"):
        converted = array.astype(current.dtype)
    if current.dtype.kind == "f" and not np.isfinite(converted[np.isfinite(array)]).all():
        raise ValueError(f"state {field!r} takes {what}: each within "
                         f"±{float(np.finfo(current.dtype).max):g}")
    return converted


def _like(current: Any, new: Any) -> Any:
    """``new`` (from JSON) in the types of ``current``, item by item: JSON has no
    tuples and writes 1.0 as 1, so an edited list of float pairs came back a list of
    int lists. An item beyond ``current``'s takes the type of its last item; a value of
    another kind is kept as sent."""
    if isinstance(current, bool) or current is None:
        return new
    if isinstance(current, float) and isinstance(new, int) and not isinstance(new, bool):
        return float(new)
    if isinstance(current, int) and isinstance(new, float) and new.is_integer():
        return int(new)
    if ((isinstance(current, dict) and isinstance(new, dict))
            or (isinstance(current, (list, tuple)) and isinstance(new, list))):
        return _item_by_item(current, new, lambda _, was, item: _like(was, item))
    return new
