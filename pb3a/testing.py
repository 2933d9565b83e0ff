"""``ModuleHarness``: one module run by a test, in the test's thread, with no system.

A port-based module is meant to be testable on its own: its ports are its whole
interface. The harness binds a module's ports, sets its state, calls ``setup``, and
lets a test feed inputs (each fed value runs ``on_input`` at once, as a dispatch
would) and call ``step``; everything the module writes is kept per output. Values
cross the harness as they cross a link: the module gets a copy of what it is fed
(arrays read-only), each written value is kept as it was when written, and the
module gets its own copy of ``state``. An ``Agent`` gets the ``runtime`` the test
passes (any object with the methods the agent calls, e.g. a recording fake).

    harness = ModuleHarness(Scale, state={"gain": 2.0})
    harness.feed("x", 1.5)
    assert harness.written["y"] == [3.0]
"""

from __future__ import annotations

import copy
from collections import deque
from typing import Any

from pb3a.config import checks
from pb3a.model.module import Module, give_period
from pb3a.model.ports import InputPort, OutputPort
from pb3a.transport.codec import local_copy


class ModuleHarness:
    """A module of class ``cls`` with ``state``, ready to be fed and stepped."""

    def __init__(self, cls: type[Module], state: dict[str, Any] | None = None, *,
                 runtime: Any = None, name: str = "", keep: int | None = None,
                 period: float | None = None) -> None:
        """``keep``: how many of the newest values to keep per output (all by default;
        a long run that only looks at ``last`` keeps 1, and its memory stays flat).
        ``period``: the one a configuration would give it, which the module sees as
        ``self.period`` (``dt = self.period``), as when launched; its class's if None.
        The module's own assignment of ``self.period`` is checked as a launched one's
        (``ValueError``, nothing changed), and sets what it sees (``"fast"`` passed here,
        and raised once launched)."""
        if keep is not None and keep < 1:
            raise ValueError(f"keep must be at least 1 (or None, for all), not {keep!r}")
        if period is not None and not (isinstance(period, (int, float)) and period >= 0):
            raise ValueError(f"period must be a number of seconds, 0 or more, not {period!r}")
        if not (isinstance(cls, type) and issubclass(cls, Module)):
            raise TypeError(f"ModuleHarness takes a pb3a.Module subclass, got {cls!r}: a "
                            "macro is tested launched (System(...).add(name, TheMacro)), or "
                            "each of its modules in a harness of its own")
        self.module = cls()
        given = cls.period if period is None else period
        self.module.__dict__["period"] = given
        if state:       # its own copy, as a launched module's comes through a pipe
            self.module.set_state(copy.deepcopy(state))
        self.name = name or cls.__name__
        # (as a worker gives it: a period assigned before it ran is replaced)
        give_period(self.module, given, self._assign_period)
        ports = self.module._pb3a_bind_ports(self.name)
        self.inputs = {n: p for n, p in ports.items() if isinstance(p, InputPort)}
        self.written: dict[str, list[Any] | deque[Any]] = {}
        for port_name, port in ports.items():
            if isinstance(port, OutputPort):
                self.written[port_name] = kept = [] if keep is None else deque(maxlen=keep)
                port.connect("harness", lambda value, kept=kept: kept.append(local_copy(value)))
        if runtime is not None:
            self.module.__dict__["_pb3a_runtime"] = runtime
        self.module.setup()

    def _assign_period(self, value: Any) -> None:
        """``self.period = value`` in the module: checked as in a launched module, and
        then what it sees (a test steps it: there is no period to sleep)."""
        period = checks.assigned_period(self.name, type(self.module), value)
        self.module.__dict__["period"] = period

    def feed(self, port: str, value: Any) -> None:
        """Deliver ``value`` to input ``port``; an event-driven module handles it now."""
        try:
            target = self.inputs[port]
        except KeyError:
            raise KeyError(f"{type(self.module).__name__} has no input {port!r}; its "
                           f"inputs: {', '.join(self.inputs) or '(none)'}") from None
        target.spec.check_fed(value)             # (an int may feed a float input)
        target.deliver(local_copy(value))        # what a link delivers: a copy, read-only
        if type(self.module).is_event_driven():
            self.module.on_input(target)

    def step(self, times: int = 1) -> None:
        """Call the module's ``step`` ``times`` times."""
        for _ in range(times):
            self.module.step()

    def last(self, output: str, default: Any = None) -> Any:
        """The newest value written on ``output`` (``default`` if none yet)."""
        try:
            values = self.written[output]
        except KeyError:
            raise KeyError(f"{type(self.module).__name__} has no output {output!r}; its "
                           f"outputs: {', '.join(self.written) or '(none)'}") from None
        return values[-1] if values else default

    @property
    def state(self) -> dict[str, Any]:
        """The module's state now (as ``get_state``)."""
        return self.module.get_state()

    def close(self) -> None:
        """Call the module's ``teardown``."""
        self.module.teardown()
