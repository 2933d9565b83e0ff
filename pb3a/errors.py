"""The exceptions PB3A raises.

    PB3AError
    ├── ConfigError (ValueError)      a configuration is invalid; lists every problem
    ├── ModuleNotFound (LookupError)  no module of that name in the running system
    ├── RuntimeTimeout (TimeoutError) a runtime request got no answer in time, or a
    │                                 write found no room on a lossless link in time
    └── RuntimeFailure (RuntimeError) a worker or node failed to carry out a request
        └── RuntimeCancelled          a body's wait (a runtime call, a driver's request
                                      to its device) ended by the runtime stopping it

Each subclasses the nearest built-in, so callers may catch either. The checks of a
runtime call's arguments that the API and an agent's ``self.runtime`` share live here
too (``bounded_wait``, ``values_to_set``), so both refuse alike.
"""

from __future__ import annotations

import threading
from numbers import Real
from typing import Any


class PB3AError(Exception):
    """Base class of every error PB3A raises on purpose."""


class ConfigError(PB3AError, ValueError):
    """A configuration is invalid. ``problems`` lists every problem found."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = list(problems)
        count = len(self.problems)
        head = f"{count} problem{'s' if count != 1 else ''} in the configuration:"
        super().__init__("\n  ".join([head, *self.problems]))

    def __reduce__(self) -> tuple[type, tuple[list[str]]]:
        return (type(self), (self.problems,))      # (travels to pb3a.connect intact)


class ModuleNotFound(PB3AError, LookupError):
    """No module with the given instance name runs in the system."""


class RuntimeTimeout(PB3AError, TimeoutError):
    """A request to a worker or node got no answer within its deadline, or a write on a
    ``lossless`` link found no room within its timeout (see ``link_stuck``)."""


class RuntimeFailure(PB3AError, RuntimeError):
    """A worker or node could not carry out a request; the message says why."""


class SystemStopped(RuntimeFailure):
    """The system has stopped: nothing more will happen there (a follower of its events
    or log is told so; what it recorded can still be read)."""


class RuntimeCancelled(RuntimeFailure):
    """A module body's runtime call or device request was cancelled: the runtime needs
    the module stopped (a pause for a move or relink, a swap, a stop). The body should
    return; nothing is wrong with what it asked (a device did not fail)."""


MOST_SECONDS = 1e7       # the longest wait or period taken (about 116 days): clocks overflow
                         # beyond (a step thread's deadline past 1e308 s ended it)


def bounded_wait(timeout: float | None, what: str) -> float:
    """``timeout`` checked to be seconds, for a wait that must end, naming ``what``:
    ``TypeError`` for None (which a ``Condition`` takes for "forever") or what is not a
    number, ``ValueError`` for a negative one, NaN (a ``Condition`` spins on it) or one
    no lock can wait (inf)."""
    if type(timeout) is float and 0.0 <= timeout <= threading.TIMEOUT_MAX:
        return timeout                  # (the common case, on per-value paths: no abc check)
    if timeout is None:
        raise TypeError(f"{what}: timeout must be seconds to wait (0 for none), not None: "
                        "every wait has a deadline")
    if isinstance(timeout, bool) or not isinstance(timeout, Real):
        raise TypeError(f"{what}: timeout must be a number of seconds, not {timeout!r}")
    if not 0 <= timeout <= threading.TIMEOUT_MAX:            # (NaN is neither)
        raise ValueError(f"{what}: timeout must be a finite number of seconds, 0 or more, "
                         f"not {timeout!r}: every wait has a deadline")
    return float(timeout)


def values_to_set(name: str, values: dict[str, Any] | None,
                  fields: dict[str, Any]) -> dict[str, Any]:
    """The state a ``set_state(name, values, **fields)`` call sets; nothing to set is a
    ``ValueError`` (``set_state("m", timeout=3.0)`` meant to set the module's ``timeout``,
    and set nothing: ``timeout=`` is the call's own deadline)."""
    merged = {**(values or {}), **fields}
    if not merged:
        raise ValueError(f"set_state({name!r}): nothing to set; give fields "
                         f"(set_state({name!r}, gain=2.0)) or a dict; timeout= is the "
                         f"call's own deadline, so a field named timeout goes in the "
                         f"dict: set_state({name!r}, {{'timeout': 3.0}})")
    return merged


def link_stuck(link: str, waited: float, unsent: int = 1) -> RuntimeTimeout:
    """The error of a write on a ``lossless`` link that found no room within its timeout.

    ``link`` is the link's key ("writer.port->reader.port", or several joined by ", ");
    ``unsent`` values of the write did not go.
    """
    what = "the value was" if unsent == 1 else f"{unsent} values were"
    return RuntimeTimeout(
        f"write on lossless link {link.replace('->', ' -> ')} timed out: the reader has not "
        f"taken a value for {waited:.1f} s: it is stuck, too slow, or gone ({what} not sent)")
