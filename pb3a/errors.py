"""The exceptions PB3A raises.

    PB3AError
    ├── ConfigError (ValueError)      a configuration is invalid; lists every problem
    ├── ModuleNotFound (LookupError)  no module of that name in the running system
    ├── RuntimeTimeout (TimeoutError) a runtime request got no answer in time
    └── RuntimeFailure (RuntimeError) a worker or node failed to carry out a request

Each subclasses the nearest built-in, so callers may catch either.
"""

from __future__ import annotations


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
    """A request to a worker or node got no answer within its deadline."""


class RuntimeFailure(PB3AError, RuntimeError):
    """A worker or node could not carry out a request; the message says why."""
