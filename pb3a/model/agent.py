"""``Agent``: a module that adapts the system it runs in.

``self.runtime`` offers the launcher's operations (read or set another
module's state, swap, relink, spawn, remove, figures). Each request travels
to the executor and is applied under the global configuration lock, one at a
time with every other change. A request blocks the agent's call until answered
(30 s at most). Meanwhile the agent gives way (``pb3a.worker.waits``): its
state may be read or set on its own thread, and if the runtime must pause it
(to move or swap it) the call raises ``RuntimeFailure`` ("... cancelled: ...").
An agent must not target itself (except to migrate): it owns its own state.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pb3a.model.module import Module
from pb3a.pending import Pending

if TYPE_CHECKING:
    from collections.abc import Callable

    from pb3a.events import Event
    from pb3a.stats import SystemStats


class RuntimeClient:
    """What ``Agent.runtime`` returns: the running system, seen from inside."""

    def __init__(self, agent: str, request: Callable[[str, dict[str, Any]], Any]) -> None:
        self._agent = agent
        self._request = request

    @property
    def name(self) -> str:
        """This agent's instance name in the system (e.g. to move itself)."""
        return self._agent

    def _call(self, op: str, target: str | None = None, **args: Any) -> Any:
        if target is not None:
            if target == self._agent:
                raise ValueError(f"agent {self._agent!r} cannot {op} itself; "
                                 "change its own attributes directly")
            args["name"] = target
        return self._request(op, args)

    def state(self, name: str) -> dict[str, Any]:
        """Another module's live state."""
        return self._call("state", name)

    def set_state(self, name: str, values: dict[str, Any] | None = None, /,
                  **fields: Any) -> None:
        """Set state attributes of another module (as ``Running.set_state``)."""
        self._call("set_state", name, values={**(values or {}), **fields})

    def swap(self, name: str, cls: type | str) -> list[str]:
        """Swap another module for ``cls``, keeping ports and matching state."""
        return self._call("swap", name, cls=cls)

    def relink(self, src: str, dst: str, *, policy: str | None = None) -> None:
        """Feed input ``dst`` from output ``src`` instead of its old source."""
        self._call("relink", src=src, dst=dst, policy=policy)

    def link(self, src: str, dst: str, *, policy: str | None = None) -> None:
        """Add a link to an input that has no source yet."""
        self._call("link", src=src, dst=dst, policy=policy)

    def spawn(self, name: str, cls: type | str, **options: Any) -> None:
        """Start a new module (options as for ``System.add``)."""
        self._call("add", name, cls=cls, **options)

    def remove(self, name: str) -> None:
        """Stop and remove another module."""
        self._call("remove", name)

    def stats(self) -> SystemStats:
        """The figures of the whole system, as ``Running.stats()``."""
        return self._call("stats")

    def where(self, name: str) -> str:
        """The node module ``name`` (this agent too) runs on now."""
        return self._request("where", {"name": name})

    def events(self, since: int = 0) -> list[Event]:
        """The system's events after sequence number ``since`` (as ``Running.events``);
        an agent does not wait for them: it looks again at its next step."""
        return self._request("events", {"since": since})

    def migrate(self, name: str, to: str, *, wait: bool = True,
                state: dict[str, dict[str, Any]] | None = None) -> Any:
        """Move a module (or macro) to node ``to``; its ``MigrationReport``. ``state``
        (module name -> fields) is set on arrival, before the module runs there. With
        ``wait=False``, or when an agent moves itself (or its own macro: the move can
        only pause it once its body returns), a ``Pending`` instead: the agent goes on,
        and ``pending.done()`` / ``pending.result()`` or the ``module_moved`` event of
        its ``env`` port tell it when the move ended."""
        if wait and not (name == self._agent or self._agent.startswith(f"{name}/")):
            return self._call("migrate", name, to=to, state=state)
        job = self._request("begin_migration", {"name": name, "to": to, "state": state})
        return Pending(f"migrate {name} to {to}",
                       lambda wait_s: self._request("migration", {"id": job, "timeout": wait_s}))


class Agent(Module):
    """A port-based agent: a module that measures itself and adapts the system."""

    @property
    def runtime(self) -> RuntimeClient:
        client = self.__dict__.get("_pb3a_runtime")
        if client is None:
            raise RuntimeError(f"{type(self).__name__} is not running in a PB3A system; "
                               "self.runtime exists only inside a launched system")
        return client
