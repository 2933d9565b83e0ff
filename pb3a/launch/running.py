"""``Running``: the handle ``System.launch()`` returns; the system runs in this process.

It owns the launch: starting every node and module, the watch over the remote nodes
(``Failover``), the launcher's control server (``listen``: where ``pb3a.connect`` and
the command line reach it), and stopping everything. Its live operations are
``SystemHandle``'s, applied here directly.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import sys
import threading
from typing import Any

from pb3a.config.plan import Plan
from pb3a.errors import ConfigError, ModuleNotFound, RuntimeFailure, bounded_wait
from pb3a.launch.env_keeper import EnvKeeper
from pb3a.launch.failover import Failover
from pb3a.launch.handle import SystemHandle
from pb3a.launch.launcher import Launcher
from pb3a.launch.operations import CHANGE_LONGER, DEFAULT_TIMEOUT, FROM_WORKERS, Operations
from pb3a.loading.references import importing_for
from pb3a.loading.trial import try_import
from pb3a.processes import role
from pb3a.transport.addresses import (
    EVERY_INTERFACE,
    bind_address,
    check_bindable,
    default_route_host,
    elsewhere,
    host_of,
    loopback,
    reachable_from,
    unresolved,
)
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlServer
from pb3a.transport.pickling import PYTHON

log = logging.getLogger("pb3a")
_ASIDE = frozenset({"agent", "event", "checkpoint", "republished", "events", "logs", "migration"})


def launch(plan: Plan, **options: Any) -> Running:
    """Start every module of ``plan`` on this machine and return the running handle."""
    _refuse_inside_own_process(plan.name)
    _refuse_in_an_imported_class_file(plan)
    running = Running(plan, **options)
    try:
        running.start()
    finally:
        # (a start that failed too, whose close a Ctrl-C cut short: nothing else could
        # finish it. Set after the start's own exit hooks, it runs before them, while
        # the workers and their forkserver still serve)
        if not running._closed:
            atexit.register(running.close_at_exit)
    return running


def _refuse_inside_own_process(name: str) -> None:
    """Refuse a launch in a process PB3A started (a worker, a node's executor), or made
    while PB3A imports a module to load a class of a configuration. The usual cause is
    a file that launches a system when imported and also defines module classes: a
    worker imports it to load one, which launched the system again, whose forkserver
    imported it again, and so on, for good; `pb3a check` of a configuration naming one
    of its classes launched that system, and then the same for good."""
    inside = role()
    if inside is None and importing_for() is None:
        return
    how = (f"inside {inside} to load a module class it defines" if inside is not None
           else f"to load its class {importing_for()!r}")
    frame = sys._getframe(1)                   # the file whose top level launched, if any
    while frame is not None and frame.f_code.co_name != "<module>":
        frame = frame.f_back
    if frame is None:
        where = f"inside {inside}" if inside is not None else f"as {importing_for()!r} loads"
        raise ConfigError([f"system {name!r} is launched {where}: a module's "
                           "code does not launch systems; it adds modules to the one it "
                           "runs in (an agent's `self.runtime.spawn`)"])
    raise ConfigError([
        f"{frame.f_code.co_filename} launches system {name!r} when it is imported (line "
        f"{frame.f_lineno}), and it was imported {how}: each such import would "
        "launch the system again. Launch it under "
        '`if __name__ == "__main__":`, or from a file other than the classes\''])


def _refuse_in_an_imported_class_file(plan: Plan) -> None:
    """Refuse, before any process starts, a launch made as a file is imported (not run)
    that holds the plan's module classes or is the package of their module: workers
    import that file to load them, which would launch the system again, and each was
    refused there at length (the forkserver's traceback, then the worker's, through the
    launcher's frames)."""
    importing: dict[str, set[str]] = {}         # file being imported -> classes it holds
    for module in plan.modules.values():
        home = _mid_import(module.cls.__module__)
        if home is not None:
            importing.setdefault(home, set()).add(module.cls.__qualname__)
    frame = sys._getframe(1)
    while frame is not None:                    # (its import is in this thread's stack)
        if frame.f_code.co_name == "<module>" and frame.f_globals.get("__name__") in importing:
            classes = sorted(importing[frame.f_globals["__name__"]])
            raise ConfigError([
                f"{frame.f_code.co_filename} launches system {plan.name!r} when it is "
                f"imported (line {frame.f_lineno}), and the workers import it to load "
                f"module class{'es' * (len(classes) > 1)} {', '.join(classes)}: each such "
                "import would launch the system again. Launch it under "
                '`if __name__ == "__main__":`, or from a file other than the classes\''])
        frame = frame.f_back


def _mid_import(name: str) -> str | None:
    """The module ``name`` or the package above it that is being imported now, if one
    is (``__main__``, a script run, is not: its classes travel by value). (``_initializing``
    is importlib's own mark, set while a module's code runs: the frame alone does not
    tell an import from code run in a module's namespace, a doctest or a console.)"""
    parts = name.split(".")
    for end in range(1, len(parts) + 1):
        prefix = ".".join(parts[:end])
        spec = getattr(sys.modules.get(prefix), "__spec__", None)
        if prefix != "__main__" and getattr(spec, "_initializing", False):
            return prefix
    return None


class Running(SystemHandle):
    """A launched system. Use it as a context manager: leaving the block stops everything."""

    def __init__(self, plan: Plan, *, checkpoint_s: float = 1.0,
                 log_level: int = logging.WARNING, timeout: float | None = None,
                 listen: str | None = None) -> None:
        self.plan = plan
        self.name = plan.name
        default = plan.timeout if timeout is None else bounded_wait(timeout, "launch")
        self._launcher = Launcher(plan, checkpoint_s=checkpoint_s, log_level=log_level)
        self._env = EnvKeeper(self._launcher)
        self._failover = Failover(self._launcher, self._env)
        self._operations = Operations(self._launcher, self._env,
                                      DEFAULT_TIMEOUT if default is None else default)
        self._launcher.handler = self._agent_request
        self._stopped = threading.Event()     # set as the close begins
        self._closed = False                  # a close has run to its end
        self._closing = threading.Lock()      # held by the close under way
        self._owner = os.getpid()             # (a forked child inherits this handle)
        self._server: ControlServer | None = None
        self._bound_host = ""               # the host it listens on, as asked to bind
        self.address: str | None = None       # where `pb3a status ADDR` etc. reach it
        self._listen_at = listen

    def _carry(self, op: str, args: dict[str, Any]) -> Any:
        return self._operations.apply(op, args)

    # -- life cycle ------------------------------------------------------------
    def start(self) -> None:
        """Start every node's executor, instantiate every module, wire every link, then
        run ``setup`` in order.

        ``setup`` runs without the configuration lock: an agent may call
        ``self.runtime`` from it (where is that module? move it ...), which takes the
        lock, while the start waits for that ``setup`` to return."""
        launcher = self._launcher
        try:
            with launcher.lock.held(f"start system {self.name!r}"):
                # remote nodes call the launcher back where they reach each other
                remote = self._remote_nodes()
                if self._listen_at is not None or remote:
                    self.listen(self._listen_at or f"tcp://{self._here_towards_nodes()}:0")
                launcher.start_nodes(self.address if remote else None, self._operations.timeout)
                self._env.start()
                self._failover.start()
                launcher.check_classes(self._operations.timeout)
                launcher.expect(list(self.plan.modules.values()))
                for spec in self.plan.modules.values():
                    launcher.add_module(spec)
                launcher.connect(*self.plan.links)
            for name in self.plan.modules:
                with contextlib.suppress(ModuleNotFound):     # an agent removed it meanwhile
                    launcher.node_of(name).start_modules([name])
            with launcher.lock.held(f"start system {self.name!r}"):
                self._env.update()
        except BaseException:
            self.close()
            raise

    def close(self, timeout: float = 10.0) -> None:
        """Stop every module (reverse start order) and worker; free every segment. A
        timeout that is not seconds is refused, the system left running (NaN or -5 was
        taken for 0: no module's teardown ran).

        A close interrupted (a Ctrl-C: KeyboardInterrupt) is finished by the next one,
        within its own ``timeout``: another ``close()``, the ``with`` block's end, or the
        exit's (``close_at_exit``); the modules it stopped are not stopped again. Until
        then ``not_torn_down`` names the modules it has not stopped. (It did nothing:
        the system was taken for stopped, its modules left running, never torn down,
        and their workers and segments kept until the process ended.) A close called
        while another thread's is under way returns at once, as before."""
        timeout = bounded_wait(timeout, "close")
        if not self._closing.acquire(blocking=False):
            return
        try:
            if self._closed:
                return
            self._stopped.set()
            try:
                self._launcher.shutdown(timeout)
            finally:
                if self._server is not None:
                    self._server.close()
            self._closed = True
            atexit.unregister(self.close_at_exit)
        finally:
            self._closing.release()

    def close_at_exit(self) -> None:
        """``close``, as the script that launched the system exits without having
        closed it (no `with`, no `close()`): left to the interpreter's exit, the workers
        went with their segments, and the resource tracker warned of leaked shared
        memory. Not in a child the script forked, which would stop its parent's system."""
        if os.getpid() == self._owner:
            self.close()

    def _remote_nodes(self) -> list[str]:
        """Where the remote nodes are reached (an address on their hosts)."""
        return [f"tcp://{node.advertise}:0" if node.advertise else node.address
                for node in self.plan.nodes.values() if node.address]

    def _here_towards_nodes(self) -> str:
        """The host of this machine that the first remote node on another machine (else
        the first) reaches it at (the interface this machine reaches that node
        through). A node whose address (or ``advertise``) names a host that does not
        resolve is named, as ``RemoteNode`` names it: found here first, it failed the
        launch with "cannot reach or listen where FILE or --listen says", naming no
        node."""
        nodes = [node for node in self.plan.nodes.values() if node.address]
        addresses = self._remote_nodes()
        # (one on another machine first, if any: towards a node on this machine's
        # loopback it was 127.0.0.1, which the other machines' nodes cannot call back
        # at, and the launch was refused, naming an address nobody gave)
        first = next((i for i, towards in enumerate(addresses) if elsewhere(towards)), 0)
        node, towards = nodes[first], addresses[first]
        try:
            return reachable_from(towards)
        except OSError as exc:
            field, value = (("advertise", host_of(towards)) if node.advertise
                            else ("address", towards))
            raise RuntimeFailure(f"node {node.name}: its {field} {value} names a host that "
                                 f"does not resolve ({unresolved(towards) or exc}): fix the "
                                 f"node's {field} (a name the launcher's machine resolves, "
                                 "or an IP address)") from None

    def _refuse_loopback_with_far_nodes(self, address: str, host: str) -> None:
        """ValueError if ``host`` is a loopback address while a node runs on another
        machine: nodes call the launcher back at the address it listens at (checkpoints,
        events, agents' requests), and there it is that machine's own loopback, so a
        ``last-state`` module failed over from nothing, and nothing said so."""
        nodes = [node.name for node in self.plan.nodes.values() if node.address]
        far = [name for name, towards in zip(nodes, self._remote_nodes(), strict=True)
               if elsewhere(towards)]
        if far and loopback(host):
            where = ("runs on another machine, which calls" if len(far) == 1 else
                     "run on other machines, which call")
            raise ValueError(f"cannot listen on {address}: node{'s' * (len(far) > 1)} "
                             f"{', '.join(far)} {where} the launcher back at this address, "
                             f"and {host} there is that machine itself: listen on an address "
                             "of this machine the nodes reach (or 0.0.0.0 for every "
                             "interface)")

    def listen(self, address: str | None = None) -> str:
        """Take authenticated requests (``pb3a.connect``, ``pb3a status ADDR`` ...) at
        ``address`` (by default ``tcp://127.0.0.1:0``: the loopback, any free port);
        returns the address to reach it at. Bound to every interface (``tcp://*:0``,
        ``tcp://0.0.0.0:0``), that is the host the remote nodes reach this machine at,
        else the one of its default route: ``tcp://*:PORT`` reaches nobody, and it was
        handed to the nodes to call the launcher back at. A host that is not one of this
        machine's addresses is refused (ValueError), as ``pb3a node start`` refuses it:
        it bound every interface and handed out an address nobody reaches. Once it
        listens (always, with remote nodes), it listens there: ``listen()`` says where,
        and another address is refused (ValueError; it was ignored, and a connection to
        it was told nothing listens there: ``launch(listen=...)`` chooses)."""
        if self._server is not None:
            if address is not None:
                self._listens_at(address)
            return self.address
        address = address or "tcp://127.0.0.1:0"
        host, port = bind_address(address)
        if host not in EVERY_INTERFACE:
            check_bindable(address, host, port)
            self._refuse_loopback_with_far_nodes(address, host)
        # Not in the lane of operations, one at a time: an agent's request from a remote
        # node (the operation in progress may wait for it: the setup of the module it
        # starts), what nodes report, and the reads that wait for news (a follower's
        # events held the lane 1 s in 1.2, and other callers' waits). A class a request
        # names by reference (a program's connection passing a class object) is
        # imported here to read the request: tried in a child process first, as a
        # change naming it does (Operations._resolved).
        self._server = ControlServer(ClusterKey.load(), self._remote_request,
                                     host, port, name="pb3a-launcher", aside=_ASIDE,
                                     import_first=self._import_first,
                                     title=f"the launcher of system {self.name!r}")
        self.address, self._bound_host = self._server.address, host
        if host in EVERY_INTERFACE:
            remote = self._remote_nodes()
            here = self._here_towards_nodes() if remote else default_route_host()
            self.address = f"tcp://{here}:{self.address.rpartition(':')[2]}"
        return self.address

    def _listens_at(self, address: str) -> None:
        """ValueError unless ``address`` is where this launcher listens (port 0: any;
        bound to every interface: any host meaning so, the one it gives out, and any of
        this machine's that the bind takes in)."""
        host, port = bind_address(address)
        bound_port = int(self.address.rpartition(":")[2])
        hosts = {self._bound_host, host_of(self.address)}
        if self._bound_host in EVERY_INTERFACE:
            hosts |= set(EVERY_INTERFACE)
            with contextlib.suppress(ValueError):   # (one of this machine's own hosts:
                check_bindable(address, host, 0)    # reached there too)
                hosts.add(host)
        if host not in hosts or port not in (0, bound_port):
            raise ValueError(f"system {self.name!r} listens at {self.address} already, "
                             f"not at {address}: it listens at one address, chosen as it "
                             "starts (launch(listen=...), pb3a run --listen)")

    stop = close

    def __enter__(self) -> Running:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until ``timeout`` seconds pass or the system stops; True if it stopped."""
        return self._stopped.wait(timeout)

    @property
    def running(self) -> bool:
        return not self._stopped.is_set()

    @property
    def unconfirmed(self) -> list[str]:
        """After ``close``: the remote nodes that did not confirm their executor stopped
        (gone, frozen, or out of time); each stops itself when its lease runs out."""
        return list(self._launcher.unconfirmed)

    @property
    def unreached(self) -> dict[str, list[str]]:
        """After ``close``: by remote node, the modules whose stop did not reach it (it did
        not answer: cut off, frozen, lost). Nothing here killed their workers: each stops
        on its own as its node's lease runs out, its ``teardown`` run (cut short if
        long; the node's log says how it went), and its node is ``unconfirmed``."""
        return {node: list(names) for node, names in self._launcher.unreached.items()}

    @property
    def not_torn_down(self) -> list[str]:
        """After ``close``: the modules that did not stop in time (stuck in a body), each
        named in a warning; their workers were killed, their ``teardown`` not run (not
        those of a node that did not answer: ``unreached``). After
        a close that was interrupted, the modules it had not stopped too, until a close
        finishes the stop."""
        return self._launcher.not_torn_down

    # -- requests from elsewhere ----------------------------------------------------
    def _import_first(self, module: str, name: str) -> None:
        """Before a request's class ``name`` is imported from ``module`` to read the
        request: the import tried in a child process, within the system's timeout."""
        try_import(module, f"{module}:{name}", self._operations.timeout, CHANGE_LONGER)

    def _agent_request(self, op: str, args: dict[str, Any]) -> Any:
        """Apply a request an agent made through ``self.runtime``: its worker adds who
        asks and whether from its setup (``_asker``); or one a worker makes for its
        modules (``FROM_WORKERS``)."""
        asker = args.pop("_asker", None)
        return self._operations.apply(op, args, FROM_WORKERS, asker=asker)

    def _remote_request(self, op: str, args: dict[str, Any]) -> Any:
        """A request to the launcher's address: a connection or the command line, an
        agent on a remote node, a node telling what happened there (refused if its
        executor belongs to an earlier admission of the node: it was fenced)."""
        if op == "describe":
            return {"name": self.name, "nodes": list(self.plan.nodes), "python": PYTHON,
                    "timeout": self._operations.timeout}     # a connection's default wait
        if op in ("agent", "republished", "event", "checkpoint"):
            self._launcher.check_node_epoch(args["node"], args["node_epoch"])
        if op == "agent":                      # an agent on a remote node
            return self._agent_request(args["request"], args["args"])
        if op == "republished":                # a writer restarted on a remote node
            threading.Thread(target=self._launcher.republished, daemon=True,
                             args=(args["link"], args["endpoint"], args["node"])).start()
            return None
        if op == "event":                      # a restart or failure on a remote node
            self._launcher.events.record(args["kind"], args["subject"], **args["detail"])
            return None
        if op == "checkpoint":                 # kept here, off the module's node
            self._launcher.checkpoints[args["module"]] = args["state"]
            return None
        return self._operations.apply(op, args)
