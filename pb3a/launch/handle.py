"""``SystemHandle``: the API of a running system, written once.

Two implementations carry each call to the system's ``Operations``: ``Running`` (the
system was launched in this process: a direct call) and ``Connection`` (it runs
elsewhere: one authenticated request to its launcher, from ``pb3a.connect``). A
script written against one works against the other.

Every call that waits takes ``timeout=`` in seconds (None: the system's default,
``launch(timeout=...)``); one that runs out raises ``RuntimeTimeout`` saying what it
waited for.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any

from pb3a.errors import bounded_wait, values_to_set
from pb3a.pending import Pending

if TYPE_CHECKING:
    from pb3a.events import Event
    from pb3a.launch.migration import MigrationReport
    from pb3a.logbook import LogEntry
    from pb3a.stats import NodeStats, SystemStats
    from pb3a.topology import Topology


class SystemHandle(ABC):
    """The live operations on a system; subclasses say how a call reaches it."""

    name: str

    def _request(self, op: str, args: dict[str, Any]) -> Any:
        """Check the call's ``timeout`` here (the same error embedded and through
        ``pb3a.connect``), then carry it."""
        if args.get("timeout") is not None:
            bounded_wait(args["timeout"], op)
        return self._carry(op, args)

    @abstractmethod
    def _carry(self, op: str, args: dict[str, Any]) -> Any:
        """Carry operation ``op`` with ``args`` to the system's ``Operations``."""

    # -- state -------------------------------------------------------------------
    def state(self, name: str, *, timeout: float | None = None) -> dict[str, Any]:
        """The module's live state (taken under its lock)."""
        return self._request("state", {"name": name, "timeout": timeout})

    def set_state(self, name: str, values: dict[str, Any] | None = None, /, *,
                  timeout: float | None = None, **fields: Any) -> None:
        """Set state attributes of a running module, between two of its calls:
        ``set_state("scale", gain=5.0)``, or with a dict for names such as ``timeout``.
        Nothing to set is a ``ValueError`` (``set_state("m", timeout=3.0)`` meant to set
        the module's ``timeout`` and set nothing)."""
        values = values_to_set(name, values, fields)
        self._request("set_state", {"name": name, "values": values, "timeout": timeout})

    # -- moving, swapping, reloading ---------------------------------------------------
    def migrate(self, name: str, to: str, *, wait: bool = True,
                state: dict[str, dict[str, Any]] | None = None,
                timeout: float | None = None) -> MigrationReport | Pending:
        """Move a module, or every module of a macro, to node ``to`` while it runs.

        State, unconsumed inputs and links go with it; no value on any link is lost,
        duplicated or reordered. A macro's modules move one after another; its report
        sums their state and links and gives the longest single pause. ``state``
        (module name -> fields) is set on arrival, before the module runs there
        (``{"brain/driver": {"resource": ...}}``: a driver that starts on the robot's
        node already pointed at that robot); a move that fails leaves it unset. With
        ``wait=False`` the move goes on in the background: a ``Pending`` whose
        ``result()`` is the report (and the event ``module_moved`` says when). A module
        that runs on ``to`` already is left where it is, its ``state`` set there: its
        report says ``moved`` False (source and destination ``to``, nothing paused or
        carried), and there is no event; a macro's says ``moved`` if any of its modules
        moved.

        ``timeout`` bounds the whole move, the wait for the configuration lock and every
        step after it: one that runs out raises ``RuntimeTimeout`` naming the step, the
        module running where it was, or, once its ``setup`` has begun at ``to``, there
        (see ``pb3a.launch.migration``).
        """
        args = {"name": name, "to": to, "state": state, "timeout": timeout}
        if wait:
            return self._request("migrate", args)
        job = self._request("begin_migration", args)
        return Pending(f"migrate {name} to {to}",
                       lambda wait_s: self._request("migration", {"id": job, "timeout": wait_s}))

    def swap(self, name: str, cls: type | str, *, timeout: float | None = None) -> list[str]:
        """Replace a module's class, keeping its ports, queued inputs and matching state.

        ``setup`` runs again on the new instance. Returns the state names carried over.
        """
        return self._request("swap", {"name": name, "cls": cls, "timeout": timeout})

    def reload(self, module: str, *, timeout: float | None = None) -> None:
        """Drop every cached copy of Python module ``module`` (and its submodules), in the
        launcher and every worker: the next load or ``swap`` naming one of its classes
        gets the file as it is now (from a module server, or the local path). Running
        instances keep their code until swapped."""
        self._request("reload", {"module": module, "timeout": timeout})

    # -- links and modules -----------------------------------------------------------------
    def relink(self, src: str, dst: str, *, policy: str | None = None,
               timeout: float | None = None) -> None:
        """Feed input ``dst`` ("module.port") from output ``src``, replacing its old source;
        nothing on the old link is lost."""
        self._request("relink", {"src": src, "dst": dst, "policy": policy, "timeout": timeout})

    def link(self, src: str, dst: str, *, policy: str | None = None,
             timeout: float | None = None) -> None:
        """Add a link while running; the input must not be fed yet."""
        self._request("link", {"src": src, "dst": dst, "policy": policy, "timeout": timeout})

    def add(self, name: str, cls: type | str, *, state: dict[str, Any] | None = None,
            period: float | None = None, fixed_rate: bool | None = None,
            restart: str | None = None, group: str | None = None, node: str | None = None,
            fallback: list[str] | None = None, timeout: float | None = None) -> None:
        """Start a new module while the system runs (link it with ``link``);
        ``fixed_rate``: as ``System.add``'s; ``fallback``: the nodes to restart it on, in
        order, if its node is lost.

        ``cls`` may be a ``Macro`` (as for ``System.add``): its modules start as
        ``name/child`` on ``node`` (unless a child names its own), with the links inside
        it, and ``state`` is per module of it (``{"smooth": {"alpha": 0.5}}``); if one of
        them cannot start, none is left. It is then a macro instance as one of the
        configuration is: ``migrate`` and ``remove`` take it whole, links at run time
        join its modules' own ports, ``configuration()`` writes it as a macro."""
        self._request("add", {"name": name, "cls": cls, "state": state, "period": period,
                              "fixed_rate": fixed_rate,
                              "restart": restart, "group": group, "node": node,
                              "fallback": fallback, "timeout": timeout})

    def remove(self, name: str, *, timeout: float | None = None, force: bool = False) -> None:
        """Stop a module (``teardown`` runs), drop its links, free its process. One that
        does not answer its stop within ``timeout`` (frozen in ``step`` or ``teardown``)
        is left as it was (``RuntimeTimeout``); with ``force`` its worker is killed
        instead, and it goes with its links all the same (not a worker that runs other
        modules too: ``RuntimeFailure`` names them). A macro instance's name removes
        every module of it, last first, with their links."""
        self._request("remove", {"name": name, "timeout": timeout, "force": force})

    def restart(self, name: str, *, timeout: float | None = None, force: bool = False) -> None:
        """Start a module again (also one that failed) with its configured state, its
        links wired again; values queued in its inputs go with the old instance. One
        that does not answer its stop within ``timeout`` (stuck in a call) is left as it
        was (``RuntimeTimeout``); with ``force`` its worker is killed instead, as
        ``remove`` does, and it starts again all the same."""
        self._request("restart", {"name": name, "timeout": timeout, "force": force})

    # -- where things are, figures, events -----------------------------------------------
    def where(self, name: str, *, timeout: float | None = None) -> str:
        """The node module ``name`` runs on now."""
        return self._request("where", {"name": name, "timeout": timeout})

    def nodes(self, *, timeout: float | None = None) -> dict[str, NodeStats]:
        """Every node's health: up or lost, its address, its round-trip time."""
        return self._request("nodes", {"timeout": timeout})

    def topology(self, *, timeout: float | None = None) -> Topology:
        """The system's structure now: every module with its class, node, ports and their
        types, state names and displays; every link; every node with its health (typed
        records, see ``pb3a.topology``)."""
        return self._request("topology", {"timeout": timeout})

    def configuration(self, *, timeout: float | None = None) -> dict[str, Any]:
        """The system as it is now (after moves, swaps, adds, relinks) as the tables of a
        configuration file that launches it again: ``{"system": tables, "problems":
        [...]}``, ``problems`` naming what TOML cannot hold (such as an initial state
        that is an array). Each macro instance comes back as a ``[macros.X]`` of its own."""
        return self._request("configuration", {"timeout": timeout})

    def stats(self, *, timeout: float | None = None) -> SystemStats:
        """Per module: steps, events, CPU time, errors; per link: values, drops, latency,
        rate; per node: health (typed records, see ``pb3a.stats``)."""
        return self._request("stats", {"timeout": timeout})

    def logs(self, since: int = 0, *, module: str | None = None,
             timeout: float | None = 0.0) -> list[LogEntry]:
        """The system's log entries after sequence number ``since`` (about ``module`` only,
        if given), from the launcher and every node, oldest first; waits up to
        ``timeout`` for one if there is none (0: not at all; None: the system's default,
        as for every call)."""
        return self._request("logs", {"since": since, "module": module, "timeout": timeout})

    def events(self, since: int = 0, *, timeout: float | None = 0.0,
               last: int | None = None) -> list[Event]:
        """The events after sequence number ``since`` (moves, swaps, restarts, failures,
        lost nodes ...), oldest first; waits up to ``timeout`` for one if there is none
        (0: not at all; None: the system's default, as for every call). ``last``: only
        the newest ``last`` of them (``events(last=1)``: the newest event, whose ``seq``
        a program reads on from, without fetching the whole log)."""
        # (``last`` only when given: a launcher older than it refuses the keyword)
        given = {"last": last} if last is not None else {}
        return self._request("events", {"since": since, "timeout": timeout, **given})
