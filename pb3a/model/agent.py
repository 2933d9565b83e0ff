"""``Agent``: a module that adapts the system it runs in.

``self.runtime`` offers the launcher's operations (read or set another
module's state, swap, relink, spawn, remove, figures). Each request travels
to the executor and is applied under the global configuration lock, one at a
time with every other change. A request blocks the agent's call until answered,
within its ``timeout`` (30 s at most without one). Meanwhile the agent gives way
(``pb3a.worker.waits``): its state may be read or set on its own thread, and if the
runtime must pause it (to move or swap it) the call raises ``RuntimeFailure``
("... cancelled: ...").
An agent must not target itself (except to migrate, ask where it runs and set its own
``period``): it reads and sets its own state directly, and cannot swap or remove
itself, nor remove the macro it is in (``ValueError``, nothing sent: ``own_target``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pb3a.errors import bounded_wait, values_to_set
from pb3a.model.module import Module
from pb3a.pending import Pending

if TYPE_CHECKING:
    from collections.abc import Callable

    from pb3a.events import Event
    from pb3a.stats import SystemStats


# Why an agent may not name itself in a request, by the request.
_ITSELF = {"state": "it reads its own attributes directly",
           "set_state": "it sets its own attributes directly; of the runtime's, only its "
                        "period, alone",
           "swap": "the swap would wait for the very call that asks it; it may migrate "
                   "itself",
           "remove": "the stop would wait for the very call that asks it; it may migrate "
                     "itself"}


def own_target(agent: str, op: str, target: str) -> str | None:
    """Why ``agent`` may not ask ``op`` of ``target``, if it is the agent itself, or,
    for a removal, the macro instance the agent is in (it may migrate both); None if it
    may. One wording for the agent's own check (``ValueError``) and the launcher's."""
    if op not in _ITSELF or not (target == agent or (op == "remove" and
                                                     agent.startswith(f"{target}/"))):
        return None
    what = "itself or the macro it is in" if op == "remove" else "itself"
    return (f"{op} {target}: agent {agent!r} is {'it' if target == agent else 'in it'}: an "
            f"agent cannot {op} {what} ({_ITSELF[op]})")


class RuntimeClient:
    """What ``Agent.runtime`` returns: the running system, seen from inside.

    Each call takes a ``timeout``, as the launcher's do: the operation's own deadline
    (the configuration lock's wait included), after which it raises ``RuntimeTimeout``;
    the agent waits that long and a second more for the answer to come back. Without
    one, the system's default applies, and the agent waits 30 s at most.
    """

    def __init__(self, agent: str,
                 request: Callable[[str, dict[str, Any], float | None], Any]) -> None:
        self._agent = agent
        self._request = request

    @property
    def name(self) -> str:
        """This agent's instance name in the system (e.g. to move itself)."""
        return self._agent

    def _call(self, op: str, target: str | None = None, *, timeout: float | None = None,
              itself: bool = False, **args: Any) -> Any:
        """Request ``op`` (of ``target``); ``itself``: one it may ask of itself."""
        if target is not None:
            refused = None if itself else own_target(self._agent, op, target)
            if refused is not None:
                raise ValueError(refused)
            args["name"] = target
        if timeout is not None:
            args["timeout"] = bounded_wait(timeout, f"runtime.{op}")
        return self._request(op, args, timeout)

    def state(self, name: str, *, timeout: float | None = None) -> dict[str, Any]:
        """Another module's live state."""
        return self._call("state", name, timeout=timeout)

    def set_state(self, name: str, values: dict[str, Any] | None = None, /, *,
                  timeout: float | None = None, **fields: Any) -> None:
        """Set state attributes of another module (as ``Running.set_state``; a dict for
        names such as ``timeout``). Nothing to set is a ``ValueError``, as there. Its own
        ``period`` alone an agent may set too (an agent that slows itself under load):
        its step thread at the new period sleeps it after the step that asked."""
        values = values_to_set(name, values, fields)
        self._call("set_state", name, values=values, timeout=timeout,
                   itself=set(values) == {"period"})

    def swap(self, name: str, cls: type | str, *, timeout: float | None = None) -> list[str]:
        """Swap another module for ``cls``, keeping ports and matching state (not this
        agent: ``ValueError``, as for ``remove``)."""
        return self._call("swap", name, cls=cls, timeout=timeout)

    def relink(self, src: str, dst: str, *, policy: str | None = None,
               timeout: float | None = None) -> None:
        """Feed input ``dst`` from output ``src`` instead of its old source."""
        self._call("relink", src=src, dst=dst, policy=policy, timeout=timeout)

    def link(self, src: str, dst: str, *, policy: str | None = None,
             timeout: float | None = None) -> None:
        """Add a link to an input that has no source yet."""
        self._call("link", src=src, dst=dst, policy=policy, timeout=timeout)

    def spawn(self, name: str, cls: type | str, *, state: dict[str, Any] | None = None,
              period: float | None = None, fixed_rate: bool | None = None,
              restart: str | None = None, group: str | None = None, node: str | None = None,
              fallback: list[str] | None = None, timeout: float | None = None) -> None:
        """Start a new module, or a macro instance (the options of ``System.add``; see
        ``Running.add``). A misspelt option is a ``TypeError`` here, as there (it went
        to the launcher and came back as its ``Operations.add()``'s)."""
        given = {"state": state, "period": period, "fixed_rate": fixed_rate,
                 "restart": restart, "group": group, "node": node, "fallback": fallback}
        self._call("add", name, cls=cls, timeout=timeout,
                   **{option: value for option, value in given.items() if value is not None})

    def remove(self, name: str, *, timeout: float | None = None, force: bool = False) -> None:
        """Stop and remove another module, or every module of a macro instance but the
        one it is in (``force``: killing its worker if it does not answer, as
        ``Running.remove``). Naming itself or the macro it is in is a ``ValueError``,
        nothing sent: the stop would wait for this very call."""
        self._call("remove", name, timeout=timeout, force=force)

    def stats(self, *, timeout: float | None = None) -> SystemStats:
        """The figures of the whole system, as ``Running.stats()``."""
        return self._call("stats", timeout=timeout)

    def where(self, name: str, *, timeout: float | None = None) -> str:
        """The node module ``name`` (this agent too) runs on now."""
        return self._call("where", timeout=timeout, name=name)

    def events(self, since: int = 0) -> list[Event]:
        """The system's events after sequence number ``since`` (as ``Running.events``);
        an agent does not wait for them: it looks again at its next step."""
        return self._request("events", {"since": since}, None)

    def migrate(self, name: str, to: str, *, wait: bool = True,
                state: dict[str, dict[str, Any]] | None = None,
                timeout: float | None = None) -> Any:
        """Move a module (or macro) to node ``to``; its ``MigrationReport``. ``state``
        (module name -> fields) is set on arrival, before the module runs there. With
        ``wait=False``, or when an agent moves itself (or its own macro: the move can
        only pause it once its body returns), a ``Pending`` instead
        (``pb3a.pending.Pending``): the agent goes on, and ``pending.done()`` (not
        waiting) or ``pending.result(timeout)`` (the report, or the error the move
        raised) tells it when the move ended, as soon as it has (``timeout`` is then the
        move's own, from its start). The ``module_moved`` output of an ``env-NODE``
        module says so too, but only at that module's next sample, up to its period
        (1 s by default) after the move ended. The timeout bounds the whole move, as
        the API's does."""
        if wait and not (name == self._agent or self._agent.startswith(f"{name}/")):
            return self._call("migrate", name, to=to, state=state, timeout=timeout)
        job = self._call("begin_migration", timeout=timeout, name=name, to=to, state=state)
        return Pending(f"migrate {name} to {to}", lambda wait_s: self._request(
            "migration", {"id": job, "timeout": wait_s}, wait_s))


class Agent(Module):
    """A port-based agent: a module that measures itself and adapts the system."""

    @property
    def runtime(self) -> RuntimeClient:
        """The running system, seen from inside (a ``RuntimeClient``, whose calls
        ``help(pb3a.model.agent.RuntimeClient)`` describes): read and set other
        modules' state, ``swap``, ``relink``, ``link``, ``spawn``, ``remove``,
        ``migrate`` (this agent too), ``stats``, ``where`` and ``events``, each under the
        launcher's configuration lock with every other change. Called from a body
        (``step``, ``on_input``); the agent gives way while it waits (see the module's
        docstring). Only inside a launched system."""
        client = self.__dict__.get("_pb3a_runtime")
        if client is None:
            raise RuntimeError(f"{type(self).__name__} is not running in a PB3A system; "
                               "self.runtime exists only inside a launched system (in a "
                               "test, give ModuleHarness a stand-in: runtime=...)")
        return client
