"""``Session``: what one manager manages, and everything the app asks of it.

A session has a document (the configuration being edited; empty when the manager
attached to a running system) and, while a system runs, a ``SystemHandle``: a
``Running`` it launched from the document (it owns it and closes it) or a
``Connection`` to a system launched elsewhere (closing the session leaves that
system running). Every method here may block: the app calls them from a thread pool,
each call to the system with a deadline.

The methods answer in JSON types, as the HTTP API and the websocket send them; a
request that cannot be served raises ``Malformed`` (the request is wrong),
``NotFound`` (no such module, node, class or field), ``Unfit`` (a value that does
not fit a state field), or PB3A's own errors (``ConfigError``: refused by the
configuration rules or nothing runs; ``RuntimeTimeout``; ``RuntimeFailure``).
Each checks before it changes anything, so a refused request changes nothing.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from typing import TYPE_CHECKING, Any

from pb3a.config.checks import NAME
from pb3a.errors import ConfigError, ModuleNotFound, PB3AError, RuntimeFailure, RuntimeTimeout
from pb3a.launch.connection import CONNECT_TIMEOUT, connect
from pb3a.loading.references import resolve_class
from pb3a.manager import keeping, reflection
from pb3a.manager.catalog import IMPORT_TIMEOUT, Catalog
from pb3a.manager.document import Document, as_json, check_data, toml_text
from pb3a.manager.layout import layout
from pb3a.model.module import edit_refusals
from pb3a.model.ports import Policy
from pb3a.model.state_edits import class_state, coerce
from pb3a.system import System
from pb3a.topology import Topology, plan_topology

if TYPE_CHECKING:
    from pb3a.launch.handle import SystemHandle
    from pb3a.launch.running import Running

log = logging.getLogger("pb3a.manager")

CALL_TIMEOUT = 10.0         # seconds a call to the system may take (--timeout) ...
MOVE_TIMES = 3              # ... and a move or restart, which stops and starts a module
REATTACH_S = 2.0            # an attached system that stopped: how often to try its address
NOTHING_RUNS = ("nothing runs: launch the document first (POST /api/document/launch), or "
                "start the manager with the address of a running system")


class Malformed(ValueError):
    """The request itself is wrong: not JSON, a field missing or of the wrong kind."""


class NotFound(LookupError):
    """The request names a module, node, class or state field that does not exist."""


class Unfit(ValueError):
    """A value that does not fit the state field it is for; ``problems``: one per field."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("; ".join(problems))
        self.problems = problems


def _refused(ref: str, current: dict[str, Any], edit: dict[str, Any]) -> list[str]:
    """What class ``ref`` refuses of ``edit`` to a module whose state is ``current``, as
    its ``set_state`` judges it (``edit_refusals``); nothing when the manager cannot
    import the class (a module running elsewhere, by a file it has not got): the
    module's own ``set_state`` then judges the edit."""
    if not edit:
        return []
    try:
        cls = resolve_class(ref)
    except Exception:
        return []
    return edit_refusals(cls, current, edit)


class Session:
    """A document and the system that runs (if one does); thread-safe."""

    def __init__(self, document: Document, handle: SystemHandle | None = None, *,
                 owns_handle: bool = False, timeout: float = CALL_TIMEOUT,
                 catalog: Catalog | None = None, import_timeout: float = IMPORT_TIMEOUT
                 ) -> None:
        """``owns_handle``: close ``handle`` when the session closes (a ``Running``: the
        system stops; a ``Connection``: only the connection closes); ``import_timeout``:
        the catalog's, for each module file it imports (see ``Catalog``)."""
        self.document = document
        self._handle = handle
        self._owns_handle = owns_handle
        # the handle is a system this session launched (Stop stops it, Keep keeps into the
        # document it came from); one it was given and owns is a connection it closes
        self._launched = False
        self._stopping: SystemHandle | None = None    # a system this session is stopping
        # one more at each change of mode: a page takes no structure older than the one
        # it shows (a feed's "stopping" may reach it after Stop's own "editing")
        self._mode_changes = 0
        self._launches = 0          # systems launched here: each numbers its events from 1
        self.timeout = timeout
        self.catalog = catalog or Catalog(document, import_timeout=import_timeout)
        self._lock = threading.Lock()       # launching and closing
        self._layouts: dict[Any, dict[str, Any]] = {}     # structure -> its layout
        self._tuned: dict[str, set[str]] = {}     # module -> fields set here since the launch
        # an attached system that has stopped: its address (connected to again on a later
        # request: a system run there again is reached) and what its connection said
        self._address: str | None = getattr(handle, "address", None)
        self._stopped_why: str | None = None
        self._last_topology: Topology | None = None     # what it was, shown when stopped
        self._tried_at = 0.0                # the last attempt to reach it again
        self._trying = threading.Lock()     # (one attempt at a time)

    # -- what runs ----------------------------------------------------------------
    @property
    def mode(self) -> str:
        """``running``, ``stopping`` (Stop has begun; its modules and workers may still
        run), ``stopped`` (the system the session attached to has stopped where it ran:
        ``system()`` says why), or ``editing`` (nothing of a system this session launched
        is left)."""
        if self._look() is not None:
            return "running"
        if self._stopped_why is not None:
            return "stopped"
        return "stopping" if self._stopping is not None else "editing"

    @property
    def running(self) -> SystemHandle | None:
        """The running system's handle, None when nothing runs (each launch: a new one)."""
        return self._look()

    @property
    def handle(self) -> SystemHandle:
        """The running system's handle; ConfigError when nothing runs. An attached
        system that has stopped is connected to again first (see ``reattach``)."""
        handle = self._look() or self.reattach()
        if handle is None:
            raise ConfigError([self._stopped_why or NOTHING_RUNS])
        return handle

    def _look(self) -> SystemHandle | None:
        """The handle, or None once the attached system behind it has stopped (its
        connection says so): it is dropped, and the mode is ``stopped``. (Held, it kept
        the mode ``running`` with a connection that had closed itself for good: every
        request failed, and a system run again at the address was never reached.)"""
        handle = self._handle
        why = getattr(handle, "stopped_why", None)
        if handle is None or why is None or self._launched:
            return handle
        with self._lock:
            if self._handle is handle:
                self._handle, self._stopped_why = None, why
                self._mode_changes += 1
                log.warning("manager: %s", why)
        handle.close()
        return self._handle

    def reattach(self, every: float = REATTACH_S) -> SystemHandle | None:
        """Connect again to the address of an attached system that has stopped, at most
        once in ``every`` seconds: the handle of the system that runs there now, None
        if none answers (or the session is not one whose system stopped)."""
        if self._stopped_why is None or self._address is None \
                or time.monotonic() - self._tried_at < every \
                or not self._trying.acquire(blocking=False):
            return self._handle
        try:
            self._tried_at = time.monotonic()
            try:
                handle = connect(self._address, timeout=min(CONNECT_TIMEOUT, self.timeout))
            except PB3AError as exc:
                log.debug("manager: %s is not there yet: %s", self._address, exc)
                return None
            with self._lock:
                if self._handle is not None or self._stopped_why is None:  # (closed)
                    handle.close()
                    return self._handle
                self._handle, self._stopped_why, self._tuned = handle, None, {}
                self._launches += 1         # (it numbers its events from 1)
                self._mode_changes += 1
            log.warning("manager: connected again to the system at %s", self._address)
            return handle
        finally:
            self._trying.release()

    def launch(self) -> dict[str, Any]:
        """Launch the document (checked first: ConfigError with its problems); the session
        owns the system and stops it when it closes."""
        with self._lock:
            if self._handle is not None:
                raise ConfigError(["a system runs already in this manager: one at a time"])
            data = self.document.data()
            system = System.from_dict(data, self.document.source)
            problems = system.check()
            if problems:
                raise ConfigError(problems)
            running: Running = system.launch(listen="tcp://127.0.0.1:0")
            self._handle, self._owns_handle, self._launched = running, True, True
            self._stopped_why = self._address = None    # (this one is its own)
            self._launches += 1
            self._mode_changes += 1
            self._tuned = {}
        return self.system()

    def stop(self) -> dict[str, Any]:
        """``POST /api/system/stop``: stop the system this session launched and go back
        to editing its document; ConfigError when nothing runs, or when the system is
        one this manager attached to (it stops where it runs)."""
        with self._lock:
            if self._handle is None:
                raise ConfigError([NOTHING_RUNS])
            if not self._launched:
                raise ConfigError(["this manager did not launch the system it shows (it "
                                   "attached to it): stop it where it runs"])
            # from here nothing reads the system, but it is not stopped until close returns
            handle, self._handle, self._launched = self._handle, None, False
            self._stopping, self._tuned = handle, {}
            self._mode_changes += 1
            try:
                handle.close()
            finally:
                self._stopping = None
                self._mode_changes += 1
        return self.system()

    def close(self) -> None:
        """Close the handle if the session owns it (a system it launched stops)."""
        with self._lock:
            handle, self._handle = self._handle, None
            self._mode_changes += handle is not None
            self._stopped_why = self._address = None      # (nothing to connect to again)
            if handle is not None and self._owns_handle:
                handle.close()

    # -- structure ----------------------------------------------------------------
    def topology(self) -> Topology:
        """The running system's structure, or the document's so far; an attached system
        that has stopped: the structure it last had (and the session tries to reach the
        address again, see ``reattach``)."""
        handle = self._look() or self.reattach()
        if handle is None:
            if self._stopped_why is not None and self._last_topology is not None:
                return self._last_topology
            return plan_topology(self.document.sketch()[0])
        topology = handle.topology(timeout=self.timeout)
        if not self._launched:
            self._last_topology = topology
        return topology

    def system(self, topology: Topology | None = None) -> dict[str, Any]:
        """``GET /api/system``; ``stopped``: why, when the mode is ``stopped``."""
        topology = topology or self.topology()
        changes = self._mode_changes         # (read before the mode: never newer than it)
        mode, handle = self.mode, self._handle
        return {**topology.to_json(), "mode": mode, "mode_change": changes,
                "address": getattr(handle, "address", None) if handle is not None
                else self._address if mode == "stopped" else None,
                "stoppable": handle is not None and self._launched,
                # which launch (a page that saw no Stop between two tells them apart by it)
                "launch": self._launches if handle is not None else None,
                "stopped": self._stopped_why if mode == "stopped" else None}

    def system_toml(self) -> str:
        """``GET /api/system/toml``: the running system as it is now, as a configuration
        file that launches it again; what TOML cannot hold is named in comments on top."""
        written = self.handle.configuration(timeout=self.timeout)
        comments = [f"The system {written['system'].get('name')!r} as it ran when saved by "
                    "the PB3A manager (GET /api/system/toml)."]
        comments += [f"Not written: {problem}" for problem in written["problems"]]
        return toml_text(written["system"], comments)

    def layout(self, topology: Topology | None = None) -> dict[str, Any]:
        """``GET /api/layout``: Graphviz's, computed once per structure."""
        topology = topology or self.topology()
        shape = (tuple((name, m.cls, m.node, tuple(m.inputs), tuple(m.outputs))
                       for name, m in topology.modules.items()),
                 tuple(topology.links), tuple(topology.nodes))
        found = self._layouts.get(shape)
        if found is None:
            found = layout(topology)
            if len(self._layouts) > 16:
                self._layouts.clear()
            self._layouts[shape] = found
        return found

    def classes(self) -> dict[str, Any]:
        """``GET /api/classes``: the catalog, with the running system's module servers
        asked too (attached to a system, they are where its code comes from)."""
        servers = self.topology().module_servers if self._handle is not None else ()
        return self.catalog.classes(servers)

    def read_classes_ahead(self) -> None:
        """Read the catalog in the background (``pb3a manager`` does as it starts): an
        editing page asks for it first thing, and waits for it to draw, and the imports
        tried first in a child process take a second or more. A page that asks sooner
        waits for this read instead of starting its own."""
        def read() -> None:
            try:
                self.classes()
            except Exception:           # (the page's own request says it, in its words)
                log.debug("reading the module browser's catalog ahead failed", exc_info=True)

        threading.Thread(target=read, name="pb3a-catalog-ahead", daemon=True).start()

    def stats(self, timeout: float | None = None) -> dict[str, Any]:
        """``GET /api/stats``; within ``timeout`` (default: the session's), a module whose
        worker has not answered by then shown ``silent``."""
        return self.handle.stats(timeout=self.timeout if timeout is None else timeout
                                 ).to_json()

    # -- state --------------------------------------------------------------------
    def state(self, name: str, path: str = "") -> dict[str, Any]:
        """``GET /api/modules/{name}/state``: the State Editor's view."""
        topology = self.topology_of(name)
        state = self.handle.state(name, timeout=self.timeout)
        try:
            return reflection.state_view(name, topology.modules[name].cls, state, path)
        except reflection.FieldNotFound as exc:
            raise NotFound(f"module {name}: {exc}") from None

    def image(self, name: str, path: str) -> bytes:
        """``GET /api/modules/{name}/image``: a 2-D array of its state as PNG."""
        self.topology_of(name)
        state = self.handle.state(name, timeout=self.timeout)
        try:
            value = reflection.find(state, path)
        except reflection.FieldNotFound as exc:
            raise NotFound(f"module {name}: {exc}") from None
        try:
            return reflection.png_of(value)
        except ValueError as exc:
            raise Malformed(f"module {name}, state {path!r}: {exc}") from None

    def set_state(self, name: str, values: Any) -> dict[str, Any]:
        """``POST /api/modules/{name}/state``: set top-level fields, each coerced to the
        type of its current value, and ``period`` (the runtime's, not in the state: the
        module steps so from its next step on, as ``pb3a set`` sets it); nothing is set
        unless every field fits, and its class takes them all (``Module.state_problems``:
        a driver's timeout of 0 reached the module, which refused it as a worker's
        failure). Answers the state read back; when that read fails once the fields are
        set (a module in a long call answers no read in time), the state read before with
        what was set in it, ``"read_back": false`` and why (``read_back_error``)."""
        if not isinstance(values, dict) or not values:
            raise Malformed("send an object of state fields to set, e.g. {\"gain\": 5.0}")
        topology = self.topology_of(name)
        current = self.handle.state(name, timeout=self.timeout)
        # (the period is the runtime's, not in the state: set_state takes it, as pb3a set)
        unknown = sorted(set(values) - set(current) - {"period"})
        if unknown:
            raise NotFound(f"module {name} has no state {', '.join(map(repr, unknown))}; its "
                           f"state: {', '.join(current) or '(none)'} (and its period)")
        problems, fitted = [], {}
        for field, value in values.items():
            if field not in current:            # its period
                if not isinstance(value, (int, float)) or isinstance(value, bool):
                    problems.append(f"module {name}: its period takes a number of seconds "
                                    f">= 0, got {value!r}")
                fitted[field] = value
                continue
            try:
                fitted[field] = coerce(field, current[field], value)
            except ValueError as exc:
                problems.append(f"module {name}: {exc}")
        fields = {field: value for field, value in fitted.items() if field in current}
        if not problems:
            # (with its other fields as they are, as the module's set_state judges it: a
            # rule relating an edited field to another read the class's default, and a
            # field the module had moved past a rule refused every edit of another)
            problems = [f"module {name}: {problem}" for problem in
                        _refused(topology.modules[name].cls, current, fields)]
        if problems:
            raise Unfit(problems)
        self.handle.set_state(name, fitted, timeout=self.timeout)
        self._tuned.setdefault(name, set()).update(fields)
        try:
            return self.state(name)
        except (RuntimeTimeout, RuntimeFailure) as exc:
            # (the edit is made: a 504 from this read said "nothing was done")
            cls = self.topology_of(name).modules[name].cls
            return {**reflection.state_view(name, cls, {**current, **fields}),
                    "read_back": False, "read_back_error": str(exc)}

    # -- keeping live state in the document -------------------------------------------
    def keep_offer(self, name: str) -> dict[str, Any]:
        """``GET /api/modules/{name}/keep``: what **Keep in document** would write (see
        ``keep``), nothing written: ``{"module", "where", "changes": {field: {"document",
        "live", "tuned"}}, "same": [...], "not_kept": {field: why}, "revision"}``."""
        revision = self.document.revision
        live, running = self._live(name)
        found = keeping.proposal(self.document.data(), self.document.source, name, running,
                                 live)
        return {**self._answer(found), "revision": revision}

    def keep(self, name: str, body: Any) -> dict[str, Any]:
        """``POST /api/modules/{name}/keep``: write the module's live values of its
        settings that differ from what the document gives it into the document (its
        entry's ``state``, or its macro instance's override); ``{"fields": [...]}``: only
        those, ``{"revision": N}``: refused (``Stale``) if the document changed since.
        ConfigError when nothing runs, when the system is one the manager attached to
        (there is no document it came from) or when the document has no place for the
        module. Answers ``{"module", "where", "kept": {field: value}, "same", "not_kept",
        "revision"}``."""
        body = {} if body is None else body
        if not isinstance(body, dict):
            raise Malformed("send {\"fields\"?: [\"kp\", ...], \"revision\"?: N} or nothing")
        fields, revision = body.get("fields"), body.get("revision")
        if fields is not None and not (isinstance(fields, list)
                                       and all(isinstance(f, str) for f in fields)):
            raise Malformed(f"'fields' must be a list of state field names, got {fields!r}")
        if revision is not None and (not isinstance(revision, int) or isinstance(revision, bool)):
            raise Malformed(f"'revision' must be the document's revision, got {revision!r}")
        live, running = self._live(name)
        kept: dict[str, Any] = {}
        answer: dict[str, Any] = {}

        def change(system: dict[str, Any]) -> bool:
            found = keeping.proposal(system, self.document.source, name, running, live)
            chosen = list(found.changes) if fields is None else [
                f for f in dict.fromkeys(fields) if f not in found.same]   # (kept already)
            unknown = [f for f in chosen if f not in live]
            if unknown:
                raise NotFound(f"module {name} has no state {', '.join(map(repr, unknown))}; "
                               f"its state: {', '.join(live) or '(none)'}")
            wrong = [f for f in chosen if f not in found.changes]
            if wrong:
                raise Unfit([f"module {name}: state {f!r} is not kept: {found.not_kept[f]}"
                             for f in wrong])
            answer.update(self._answer(found))
            if not chosen:
                return False
            before = set(check_data(system, self.document.source)[1])
            keeping.write(system, found, chosen)
            added = [p for p in check_data(system, self.document.source)[1] if p not in before]
            if added:
                raise ConfigError(added)
            kept.update({f: found.changes[f][1] for f in chosen})
            return True

        try:
            self.document.edit(change, revision)
        except (Unfit, Malformed):
            raise
        except ValueError as exc:                   # TOML cannot hold it: nothing changed
            raise Unfit([f"module {name}: {exc}"]) from None
        answer.pop("changes", None)
        return {**answer, "kept": as_json(kept), "revision": self.document.revision}

    def _live(self, name: str) -> tuple[dict[str, Any], str]:
        """Module ``name``'s live state and the class it runs as; refused (see ``keep``)
        when nothing runs, the system is not the document's, or there is no such module."""
        handle = self.handle
        if not self._launched:
            raise ConfigError(["this manager attached to the system it shows: there is no "
                               "document it was launched from to keep its state in (GET "
                               "/api/system/toml writes the running system as a file)"])
        topology = self.topology_of(name)
        return handle.state(name, timeout=self.timeout), topology.modules[name].cls

    def _answer(self, found: keeping.Proposal) -> dict[str, Any]:
        tuned = self._tuned.get(found.module, set())
        return {"module": found.module, "where": ".".join(found.where),
                "changes": {f: {"document": as_json(held), "live": as_json(now),
                                "tuned": f in tuned}
                            for f, (held, now) in found.changes.items()},
                "same": found.same, "not_kept": found.not_kept}

    # -- changes ------------------------------------------------------------------
    def migrate(self, name: str, to: Any) -> dict[str, Any]:
        """``POST /api/modules/{name}/migrate``: the migration report. ``name`` may be a
        macro: its modules move one after another (as ``migrate`` on the control surface
        does), and the report sums them."""
        topology = self.topology_of(name, macros=True)
        if not isinstance(to, str):
            raise Malformed("send the node to move to: {\"to\": \"NODE\"}")
        if to not in topology.nodes:
            raise NotFound(f"no node {to!r}; nodes: {', '.join(topology.nodes)}")
        report = self.handle.migrate(name, to=to, timeout=self.timeout * MOVE_TIMES)
        return dataclasses.asdict(report)

    def swap(self, name: str, cls: Any) -> dict[str, Any]:
        """``POST /api/modules/{name}/swap``: the state names carried over."""
        self.topology_of(name)
        ref = self._class(cls)
        return {"kept": self.handle.swap(name, ref, timeout=self.timeout)}

    def swaps(self, name: str) -> dict[str, Any]:
        """``GET /api/modules/{name}/swaps``: the catalog's classes whose ports fit."""
        topology = self.topology_of(name)
        return {"classes": self.catalog.fitting(topology, name)}

    def add(self, body: Any) -> dict[str, Any]:
        """``POST /api/modules``: start a module (then link it)."""
        if not isinstance(body, dict):
            raise Malformed("send {\"name\", \"class\", \"node\"?, \"state\"?, \"period\"?, "
                            "\"fixed_rate\"?}")
        name, cls = body.get("name"), body.get("class")
        if not isinstance(name, str) or not all(NAME.match(part) for part in name.split("/")):
            raise Malformed(f"a new module needs a 'name' of letters, digits, '_' and '-', "
                            f"got {name!r}")
        state, period, node = body.get("state"), body.get("period"), body.get("node")
        if state is not None and not isinstance(state, dict):
            raise Malformed(f"'state' must be an object of field values, got {state!r}")
        if period is not None and (not isinstance(period, (int, float))
                                   or isinstance(period, bool) or period < 0):
            raise Malformed(f"'period' must be a number of seconds >= 0, got {period!r}")
        fixed_rate = body.get("fixed_rate")
        if fixed_rate is not None and not isinstance(fixed_rate, bool):
            raise Malformed(f"'fixed_rate' must be true or false, got {fixed_rate!r}")
        if node is not None and not isinstance(node, str):
            raise Malformed(f"a new module's 'node' must be the name of a node, got {node!r}")
        topology = self.topology()
        if name in topology.modules:
            raise ConfigError([f"module {name}: a module of that name runs already"])
        if node is not None and node not in topology.nodes:
            raise NotFound(f"no node {node!r}; nodes: {', '.join(topology.nodes)}")
        ref = self._class(cls)
        if state:
            state = self._fitted(name, resolve_class(ref), state)
        self.handle.add(name, ref, state=state, period=period, fixed_rate=fixed_rate,
                        node=node, timeout=self.timeout)
        return self.system()

    @staticmethod
    def _fitted(name: str, cls: Any, state: dict[str, Any]) -> dict[str, Any]:
        """A new module's ``state`` (JSON) made the type of its class's defaults, as
        ``pb3a add --state`` makes it (``{"gain": 5}`` gave a float field an int, and
        the State Editor then refused any fraction for it); ``Unfit`` naming each value
        that does not fit."""
        like, fitted, problems = class_state(cls), dict(state), []
        for field in [field for field in state if field in like]:
            try:
                fitted[field] = coerce(field, like[field], state[field])
            except ValueError as exc:
                problems.append(f"module {name}: {exc}")
        if problems:
            raise Unfit(problems)
        return fitted

    def restart(self, name: str) -> dict[str, Any]:
        """``POST /api/modules/{name}/restart``: start the module afresh, a failed one too
        (its configured state, its links wired again), as ``pb3a restart`` does."""
        self.topology_of(name)
        self.handle.restart(name, timeout=self.timeout * MOVE_TIMES)
        return self.system()

    def remove(self, name: str, force: bool = False) -> dict[str, Any]:
        """``DELETE /api/modules/{name}`` (``?force=1``: a module that does not answer its
        stop in time has its worker killed, as ``pb3a remove --force``)."""
        self.topology_of(name)
        self.handle.remove(name, timeout=self.timeout, force=force)
        return self.system()

    def link(self, body: Any) -> dict[str, Any]:
        """``POST /api/links``: a new link, or with ``replace`` a new source for an input."""
        if not isinstance(body, dict) or not all(isinstance(body.get(k), str)
                                                 for k in ("src", "dst")):
            raise Malformed("send {\"src\": \"module.output\", \"dst\": \"module.input\", "
                            "\"policy\"?: \"queue:8\", \"replace\"?: false}")
        policy, replace = body.get("policy"), body.get("replace")
        if replace is not None and not isinstance(replace, bool):
            raise Malformed(f"a link's 'replace' must be true or false, got {replace!r}")
        if policy is not None:
            try:
                Policy.parse(policy)
            except ValueError as exc:
                raise ConfigError([f"link {body['src']} -> {body['dst']}: {exc}"]) from None
        topology = self.topology()
        for end in (body["src"], body["dst"]):
            module = end.rpartition(".")[0]
            if module not in topology.modules:
                raise NotFound(f"link {body['src']} -> {body['dst']}: no module {module!r}")
        act = self.handle.relink if replace else self.handle.link
        act(body["src"], body["dst"], policy=policy, timeout=self.timeout)
        return self.system()

    def reload(self, body: Any) -> dict[str, Any]:
        """``POST /api/reload``: drop the cached copies of a Python module everywhere."""
        module = body.get("module") if isinstance(body, dict) else None
        if not isinstance(module, str) or not all(p.isidentifier() for p in module.split(".")):
            raise Malformed(f"send the dotted module name to reload: {{\"module\": "
                            f"\"pkg.mod\"}}, got {module!r}")
        self.handle.reload(module, timeout=self.timeout)
        self.catalog.forget(module)
        return {"reloaded": module}

    # -- helpers ------------------------------------------------------------------
    def topology_of(self, name: str, *, macros: bool = False) -> Topology:
        """The structure, checked to have module ``name`` (or, with ``macros``, macro
        ``name``); ModuleNotFound otherwise."""
        topology = self.topology()
        if name in topology.modules or (macros and name in topology.macros):
            return topology
        known = f"modules: {', '.join(topology.modules) or '(none)'}"
        if macros and topology.macros:
            known += f"; macros: {', '.join(topology.macros)}"
        raise ModuleNotFound(f"no {'module or macro' if macros else 'module'} {name!r} in "
                             f"system {topology.system!r}; {known}")

    @staticmethod
    def _class(ref: Any) -> str:
        """A class reference the manager can import ("pkg.mod:Class")."""
        if not isinstance(ref, str):
            raise Malformed(f"'class' must be a reference such as \"pkg.mod:Class\", got {ref!r}")
        try:
            resolve_class(ref)
        except ValueError as exc:
            raise Malformed(str(exc)) from None
        except (ImportError, LookupError, TypeError) as exc:
            raise NotFound(str(exc)) from None
        return ref

