"""``Running``: the handle ``System.launch()`` returns, and the live operations.

Every change to the running configuration (state edits, swaps, relinks,
additions, removals) goes through one configuration lock, so changes from the
API, the command line and agents are applied one at a time and each sees the
configuration the previous one left.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import replace
from typing import Any

from pb3a.config.plan import FlatLink, FlatModule, Plan
from pb3a.errors import ConfigError
from pb3a.launch.launcher import Launcher
from pb3a.launch.migration import MigrationReport, migrate
from pb3a.loading.references import resolve_class
from pb3a.loading.served import forget
from pb3a.model.module import RESTART_POLICIES, Module
from pb3a.model.ports import Policy
from pb3a.stats import SystemStats
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlServer, bind_address, reachable_from

log = logging.getLogger("pb3a")


def launch(plan: Plan, **options: Any) -> Running:
    """Start every module of ``plan`` on this machine and return the running handle."""
    running = Running(plan, **options)
    running.start()
    return running


class Running:
    """A launched system. Use it as a context manager: leaving the block stops everything."""

    def __init__(self, plan: Plan, *, checkpoint_s: float = 1.0,
                 log_level: int = logging.WARNING) -> None:
        self.plan = plan
        self.name = plan.name
        self._launcher = Launcher(plan, checkpoint_s=checkpoint_s, log_level=log_level)
        self._lock = self._launcher.lock         # the global configuration lock
        self._launcher.handler = self._agent_request
        self._stopped = threading.Event()
        self._server: ControlServer | None = None
        self.address: str | None = None       # where `pb3a status ADDR` etc. reach it

    # -- life cycle ------------------------------------------------------------
    def start(self) -> None:
        """Start every node's executor, instantiate every module, wire every link, then
        run ``setup`` in order."""
        launcher = self._launcher
        try:
            with self._lock.held(f"start system {self.name!r}"):
                remote = [node.address for node in self.plan.nodes.values() if node.address]
                launcher.start_nodes(self.listen(reachable_from(remote[0])) if remote else None)
                launcher.expect(list(self.plan.modules.values()))
                for spec in self.plan.modules.values():
                    launcher.add_module(spec)
                for link in self.plan.links:
                    launcher.connect(link)
                for name in self.plan.modules:
                    launcher.node_of(name).start_modules([name])
                launcher.update_env()
        except BaseException:
            self.close()
            raise

    def close(self, timeout: float = 10.0) -> None:
        """Stop every module (reverse start order) and worker; free every segment."""
        if not self._stopped.is_set():
            self._stopped.set()
            self._launcher.shutdown(timeout)
            if self._server is not None:
                self._server.close()

    def listen(self, address: str = "tcp://127.0.0.1:0") -> str:
        """Take authenticated requests (``pb3a status / state / migrate / swap``) at
        ``address``; returns the address bound."""
        if self._server is None:
            self._server = ControlServer(ClusterKey.load(), self._remote_request,
                                         *bind_address(address), name="pb3a-launcher")
            self.address = self._server.address
        return self.address

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

    # -- state -------------------------------------------------------------------
    def state(self, name: str) -> dict[str, Any]:
        """The module's live state (taken under its lock)."""
        with self._lock.held(f"state {name}"):
            return self._launcher.call(name, "get_state")

    def set_state(self, name: str, **state: Any) -> None:
        """Set state attributes of a running module, between two of its calls."""
        with self._lock.held(f"set_state {name}"):
            self._launcher.call(name, "set_state", state=state)

    # -- migration -------------------------------------------------------------------
    def migrate(self, name: str, to: str) -> MigrationReport:
        """Move a module, or every module of a macro, to node ``to`` while it runs.

        State, unconsumed inputs and links go with it; no value on any link is
        lost, duplicated or reordered. A macro's modules move one after another; its
        report sums their state and links and gives the longest single pause.
        """
        with self._lock.held(f"migrate {name} to {to}"):
            if to not in self.plan.nodes:
                raise ConfigError([f"migrate {name}: no node {to!r}; nodes: "
                                   f"{', '.join(self.plan.nodes)}"])
            specs = self._launcher.specs
            names = [name] if name in specs else [
                child for child in specs if child.startswith(f"{name}/")]
            if not names:
                self._launcher.node_of(name)           # raises ModuleNotFound
            reports = [migrate(self._launcher, child, to) for child in names]
        if len(reports) == 1:
            return reports[0]
        return MigrationReport(name, ",".join(sorted({r.source for r in reports})), to,
                               max(r.pause_s for r in reports),
                               sum(r.state_bytes for r in reports),
                               sum(r.links for r in reports))

    def reload(self, module: str) -> None:
        """Drop every cached copy of Python module ``module`` (and its submodules), here
        and in every worker: the next load or ``swap`` naming one of its classes gets
        the file as it is now (from a module server, or the local path). Running
        instances keep their code until swapped."""
        with self._lock.held(f"reload {module}"):
            forget(module)
            for node in self._launcher.nodes.values():
                node.forget(module)

    # -- reconfiguration -----------------------------------------------------------
    def swap(self, name: str, cls: type | str) -> list[str]:
        """Replace a module's class, keeping its ports, queued inputs and matching state.

        ``setup`` runs again on the new instance. Returns the state names carried over.
        """
        new_cls = resolve_class(cls)
        with self._lock.held(f"swap {name}"):
            launcher = self._launcher
            node = launcher.node_of(name)
            spec = launcher.specs[name]
            problems = _swap_problems(name, spec.cls, new_cls, launcher.links, launcher.specs)
            if problems:
                raise ConfigError(problems)
            spec = replace(spec, cls=new_cls)
            kept = node.swap(name, spec)
            launcher.specs[name] = spec
            return kept

    def relink(self, src: str, dst: str, *, policy: str | None = None) -> None:
        """Feed input ``dst`` ("module.port") from output ``src``, replacing its old source."""
        with self._lock.held(f"relink {src} -> {dst}"):
            link = self._new_link(src, dst, policy)
            launcher = self._launcher
            olds = [old for old in launcher.links.values()
                    if (old.dst, old.dst_port) == (link.dst, link.dst_port)]
            # Writers pause so that nothing is written while the input changes
            # source; the reader drains the old link before the new one opens.
            with launcher.paused([link.src, *(old.src for old in olds)]):
                for old in olds:
                    launcher.disconnect(old.key)
                launcher.connect(link)

    def link(self, src: str, dst: str, *, policy: str | None = None) -> None:
        """Add a link while running; the input must not be fed yet."""
        with self._lock.held(f"link {src} -> {dst}"):
            link = self._new_link(src, dst, policy)
            for old in self._launcher.links.values():
                if (old.dst, old.dst_port) == (link.dst, link.dst_port):
                    raise ConfigError([f"input {dst} is fed by {old.src}.{old.src_port} "
                                       "already; use relink() to replace its source"])
            self._launcher.connect(link)

    def _new_link(self, src: str, dst: str, policy: str | None) -> FlatLink:
        problems = []
        ends = []
        for text, side in ((src, "outputs"), (dst, "inputs")):
            module, _, port = text.rpartition(".")
            spec = self._launcher.specs.get(module)
            if spec is None:
                problems.append(f"link {src} -> {dst}: no module {module!r}")
            elif port not in getattr(spec.cls, side):
                names = ", ".join(getattr(spec.cls, side)) or "(none)"
                problems.append(f"link {src} -> {dst}: {module} has no {side[:-1]} {port!r}; "
                                f"its {side}: {names}")
            ends.append((module, port, spec))
        if problems:
            raise ConfigError(problems)
        (smod, sport, sspec), (dmod, dport, dspec) = ends
        out_spec, in_spec = sspec.cls.outputs[sport], dspec.cls.inputs[dport]
        why = in_spec.accepts(out_spec)
        if why:
            raise ConfigError([f"link {src} -> {dst}: incompatible types: {why}"])
        try:
            parsed = Policy.parse(policy) if policy is not None else in_spec.policy
        except ValueError as exc:
            raise ConfigError([f"link {src} -> {dst}: {exc}"]) from None
        return FlatLink(smod, sport, dmod, dport, parsed)

    def add(self, name: str, cls: type | str, *, state: dict[str, Any] | None = None,
            period: float | None = None, restart: str | None = None, group: str | None = None,
            node: str | None = None) -> None:
        """Start a new module while the system runs (link it with ``link``)."""
        module_cls = resolve_class(cls)
        if not (isinstance(module_cls, type) and issubclass(module_cls, Module)):
            raise ConfigError([f"module {name}: {module_cls!r} is not a pb3a.Module subclass"])
        restart = restart or module_cls.restart
        if restart not in RESTART_POLICIES:
            raise ConfigError([f"module {name}: restart must be one of {RESTART_POLICIES}"])
        with self._lock.held(f"add {name}"):
            if name in self._launcher.specs:
                raise ConfigError([f"module {name}: a module of that name runs already"])
            node = node or next(iter(self.plan.nodes))
            if node not in self._launcher.nodes:
                raise ConfigError([f"module {name}: no node {node!r}; nodes: "
                                   f"{', '.join(self._launcher.nodes)}"])
            spec = FlatModule(name, module_cls, node,
                              period if period is not None else module_cls.period,
                              dict(state or {}), restart, group)
            self._launcher.add_module(spec)
            self._launcher.node_of(name).start_modules([name])

    def remove(self, name: str) -> None:
        """Stop a module (``teardown`` runs), drop its links, free its process."""
        with self._lock.held(f"remove {name}"):
            self._launcher.remove_module(name)

    def _agent_request(self, op: str, args: dict[str, Any]) -> Any:
        """Apply a request an agent made through ``self.runtime``."""
        if op not in ("state", "set_state", "swap", "relink", "link", "add", "remove", "stats",
                      "migrate", "migrate_self"):
            raise ValueError(f"unknown runtime operation {op!r}")
        if op == "set_state":
            return self.set_state(args["name"], **args["state"])
        if op == "migrate_self":
            # The agent waits for this answer inside its own step, holding its lock;
            # the move has to pause it, so it happens once the step has returned.
            threading.Thread(target=self._migrate_quietly, args=(args["name"], args["to"]),
                             name="pb3a-self-migration", daemon=True).start()
            return None
        return getattr(self, op)(**args)

    def _remote_request(self, op: str, args: dict[str, Any]) -> Any:
        """A request from the command line (``pb3a status ADDR`` ...)."""
        if op == "migrate":
            return vars(self.migrate(args["name"], args["to"]))
        if op == "agent":                      # an agent on a remote node
            return self._agent_request(args["request"], args["args"])
        if op == "republished":                # a writer restarted on a remote node
            threading.Thread(target=self._launcher.republished, daemon=True,
                             args=(args["link"], args["endpoint"])).start()
            return None
        if op in ("state", "stats", "swap", "set_state", "relink"):
            return self._agent_request(op, args)
        raise ValueError(f"the launcher has no operation {op!r}")

    def _migrate_quietly(self, name: str, to: str) -> None:
        try:
            report = self.migrate(name, to)
            log.info("agent %s moved to %s (paused %.1f ms)", name, to, report.pause_s * 1e3)
        except Exception:
            log.exception("agent %s could not move to %s", name, to)

    # -- figures ---------------------------------------------------------------------
    def stats(self) -> SystemStats:
        """Per module: steps, events, CPU time, errors; per link: values, drops, latency,
        rate; per node: health (see ``pb3a.stats``)."""
        with self._lock.held("stats"):
            return self._launcher.stats()


def _swap_problems(name: str, old: type, new: type, links: dict[str, FlatLink],
                   modules: dict[str, FlatModule]) -> list[str]:
    problems = []
    if not (isinstance(new, type) and issubclass(new, Module)):
        return [f"swap {name}: {new!r} is not a pb3a.Module subclass"]
    for side in ("inputs", "outputs"):
        missing = sorted(set(getattr(old, side)) - set(getattr(new, side)))
        if missing:
            problems.append(f"swap {name}: {new.__name__} lacks the {side} "
                            f"{', '.join(missing)} that {old.__name__} has")
    for link in links.values():
        if link.dst == name and link.dst_port in new.inputs:
            feeder = modules[link.src].cls.outputs[link.src_port]
            why = new.inputs[link.dst_port].accepts(feeder)
            if why:
                problems.append(f"swap {name}: input {link.dst_port} fed by {link.src}: {why}")
        if link.src == name and link.src_port in new.outputs:
            reader = modules[link.dst].cls.inputs[link.dst_port]
            why = reader.accepts(new.outputs[link.src_port])
            if why:
                problems.append(f"swap {name}: output {link.src_port} feeds {link.dst}: {why}")
    return problems
