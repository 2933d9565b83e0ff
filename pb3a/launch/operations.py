"""``Operations``: every live operation on a running system, implemented once.

The program (``Running``), another process (``pb3a.connect`` and the command line,
through the launcher's control server) and agents (``self.runtime``) all end here.
Each operation that changes the configuration, or reads what a change may be
halfway through, holds the configuration lock, whose wait is bounded by the
operation's ``timeout`` (the system's default when None) and names what holds it
when it runs out; a module's answer (``state``, ``set_state``) is awaited for what
is left of that timeout, one deadline for both. Each change is recorded as an event.
The looks at the system (``stats``, ``where``, ``nodes``, ``topology``) wait for no
change: they read a copy of the launcher's tables, and ``stats`` names the change in
progress that acts on each module (a stuck system is when one wants to look).

A change that starts modules (``add``, ``migrate``, ``swap``, ``restart``) lends the
lock to them while it waits for their ``setup`` (``ConfigurationLock``): an agent
may then read from its ``setup`` (and set another module's state) as its guest; a
change it asks for there would wait for itself, and is refused at once, saying so.
"""

from __future__ import annotations

import contextlib
import contextvars
import itertools
import logging
import threading
import time
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from pb3a.config import checks
from pb3a.config.compiler import plan_addition
from pb3a.config.description import ModuleSpec, SystemSpec
from pb3a.config.folding import fold
from pb3a.config.plan import FlatLink, FlatModule
from pb3a.deadline import bounding, lifted, spoken
from pb3a.errors import (
    ConfigError,
    ModuleNotFound,
    PB3AError,
    RuntimeFailure,
    RuntimeTimeout,
    SystemStopped,
    bounded_wait,
)
from pb3a.launch.configuration_lock import change_to
from pb3a.launch.migration import MigrationReport, MovedLate, migrate
from pb3a.loading import trial
from pb3a.loading.references import (
    ImportRefused,
    changed_since_import,
    class_ref,
    resolve_class,
)
from pb3a.loading.served import forget, reload_problem
from pb3a.model.agent import own_target
from pb3a.model.environment import PREFIX as ENV_PREFIX
from pb3a.model.environment import Environment
from pb3a.model.macro import Macro
from pb3a.model.module import Module
from pb3a.model.ports import Policy
from pb3a.node.workers import REQUEST_TIMEOUT
from pb3a.pending import DONE, FAILED, RUNNING
from pb3a.topology import Topology, topology_of
from pb3a.transport import pickling
from pb3a.transport.control import UnknownOperation

if TYPE_CHECKING:
    from collections.abc import Callable, Collection, Iterator

    from pb3a.events import Event
    from pb3a.launch.env_keeper import EnvKeeper
    from pb3a.launch.launcher import Launcher
    from pb3a.logbook import LogEntry
    from pb3a.stats import NodeStats, SystemStats

log = logging.getLogger("pb3a")

DEFAULT_TIMEOUT = 30.0      # seconds an operation may wait, unless told otherwise

# What may be asked from outside the launcher's process (the command line, a
# connection, an agent on a remote node): the public operations, nothing else.
PUBLIC = frozenset({"state", "set_state", "swap", "relink", "link", "add", "remove",
                    "restart", "migrate", "begin_migration", "migration", "reload", "stats",
                    "where", "nodes", "topology", "configuration", "events", "logs"})
_HISTORY = frozenset({"events", "logs"})      # what a stopped system still answers
# What an agent may ask through ``self.runtime`` (it spawns with "add"); and what a
# worker asks besides, for its modules (``pb3a.worker.periods``).
FOR_AGENTS = PUBLIC - {"reload"}
FROM_WORKERS = FOR_AGENTS | {"learn_period"}
KEEP_JOBS = 1000            # background operations whose outcome is kept for asking
STATE_THEN_S = 1.0          # how long a restart waits for the state to put back on failure
KILLED_START_S = 2.0        # the start of a module restarted by killing its worker, at least
CHANGE_LONGER = "give the change a longer timeout"     # (an import that took too long)
# The agent whose request runs on this thread, and whether it asks from its setup.
_ASKER: contextvars.ContextVar[tuple[str, bool] | None] = contextvars.ContextVar(
    "pb3a_asker", default=None)


class Operations:
    """The live operations of one launched system."""

    def __init__(self, launcher: Launcher, env: EnvKeeper,
                 timeout: float = DEFAULT_TIMEOUT) -> None:
        self.launcher, self.env = launcher, env
        self.plan = launcher.plan
        self.lock = launcher.lock
        self.event_log = launcher.events
        self.timeout = timeout
        self._jobs: dict[int, tuple[threading.Event, list[Any]]] = {}   # background moves
        self._job_ids = itertools.count(1)

    @contextlib.contextmanager
    def _held(self, what: str, timeout: float | None, *, lend: Collection[str] = (),
              changes: bool = True, acts_on: Collection[str] | None = None,
              ) -> Iterator[Callable[[], float]]:
        """Hold the configuration lock for ``what``, waiting at most ``timeout``; gives
        what is left of it then, for the operation's own waits (one deadline for all).
        ``lend``: the modules it starts (see the module's docstring); ``changes``: False
        for what changes no configuration, which such a module may ask as a guest;
        ``acts_on``: the modules it changes (default: ``lend``), which ``stats`` marks."""
        wait = self._call_timeout(timeout)
        deadline = time.monotonic() + wait
        asker = _ASKER.get()
        if asker is not None and asker[1] and self.lock.lends_to(asker[0]):
            if changes:
                raise RuntimeFailure(
                    f"{what}: asked by agent {asker[0]!r} from its setup, which "
                    f"{self.lock.doing()} waits for while it holds "
                    "the system's configuration lock, so it would wait for itself: ask "
                    "for changes from step() (reads, and setting another module's state, "
                    "may be asked from setup)")
            with self.lock.guest(what, wait):
                yield lambda: max(0.0, deadline - time.monotonic())
            return
        with self.lock.held(what, wait, lend=lend, acts_on=acts_on):
            yield lambda: max(0.0, deadline - time.monotonic())

    def _call_timeout(self, timeout: float | None) -> float:
        """The seconds a call may wait: its own, checked, else the system's default."""
        return self.timeout if timeout is None else bounded_wait(timeout, "the call")

    # -- state -------------------------------------------------------------------
    def state(self, name: str, *, timeout: float | None = None) -> dict[str, Any]:
        """The module's state. Its node is looked up under the configuration lock if a
        change in progress acts on it, else at once (another module's long move held
        this read up until it ended), and asked without it: a module stuck in a long
        call holds up this read only, not every request to the system for the read's
        timeout. Moved or removed meanwhile, it is asked once more under the lock; its
        worker dead, once its restart is done (which takes that lock, so it is waited
        for without)."""
        spec = self.launcher.specs.get(name)
        if spec is not None and change_to(name, self.lock.changing()) is None:
            node = self.launcher.nodes[spec.node]
            deadline = time.monotonic() + self._call_timeout(timeout)
        else:
            with self._held(f"state {name}", timeout, changes=False) as left:
                node = self.launcher.node_of(name)
                deadline = time.monotonic() + left()        # (one deadline for all)
        try:
            return node.call_module(name, "get_state", _left(deadline))
        except (RuntimeFailure, ModuleNotFound):
            node.await_restart(name, _left(deadline))
            with self._held(f"state {name}", _left(deadline), changes=False) as still:
                return self.launcher.call(name, "get_state", still())

    def set_state(self, name: str, values: dict[str, Any], *,
                  timeout: float | None = None) -> None:
        """Set fields of the module's state, under the configuration lock (a move must
        not capture the state before it and land it after). Its worker dead, the state
        is set once its restart is done, in the new process, within the same timeout.
        ``period``, the runtime's, may be set among them (``retime``)."""
        if "period" in values:
            values = dict(values)
            self.retime(name, values.pop("period"), timeout=timeout)
            if not values:
                return
        with self._held(f"set_state {name}", timeout, changes=False,
                        acts_on=[name]) as left:
            node = self.launcher.node_of(name)
            try:
                node.call_module(name, "set_state", left(), state=values)
                return
            except RuntimeFailure as exc:
                failure = exc
        if not node.await_restart(name, left()):
            raise failure
        with self._held(f"set_state {name}", left(), changes=False) as still:
            self.launcher.call(name, "set_state", still(), state=values)

    def retime(self, name: str, period: Any, *, timeout: float | None = None) -> None:
        """Step module ``name`` every ``period`` seconds from its next step on (it sleeps
        that long after each), kept across its restarts, moves and swaps, as if the
        configuration had given it: a module's rate could only be changed by removing
        it and adding it again, links and all."""
        with self._held(f"set_state {name} period", timeout, acts_on=[name]) as left:
            spec = self.launcher.specs.get(name)
            if spec is None:
                self.launcher.node_of(name)           # raises ModuleNotFound
            problems = (checks.period(period) or checks.stepped(spec.cls, period)
                        if period is not None else ["period must be a number of seconds"])
            if problems:
                raise ConfigError([f"set_state {name}: {problem}" for problem in problems])
            retimed = replace(spec, period=float(period), own_period=True)
            self.launcher.node_of(name).retime(name, retimed.period, left())
            self.launcher.specs[name] = retimed
            # (nothing said it: a page showed the period it had until it was read anew)
            self.event_log.record("module_retimed", name, period=retimed.period)

    def learn_period(self, name: str, *, timeout: float | None = None) -> None:
        """Module ``name`` assigned itself a period (``self.period = ...``), at which it
        steps already: the launcher's record of it and its executor's learn the one it
        steps at now, read where it runs (``Node.learn_period``), so that a move, a
        restart and a swap keep it. Its worker asks (``pb3a.worker.periods``), not
        waiting for it. No event: as its state's fields, a module's own period is its
        own doing, which ``stats`` shows (one that adapts its rate at every step was an
        event at each, and the manager's pages got the whole structure again at each)."""
        with self._held(f"learn the period of {name}", timeout, changes=False) as left:
            node = self.launcher.node_of(name)          # (raises ModuleNotFound)
            period = node.learn_period(name, left())
            spec = self.launcher.specs[name]
            if period is not None and period != spec.period:
                self.launcher.specs[name] = replace(spec, period=period, own_period=True)

    # -- moving, swapping, reloading ----------------------------------------------------
    def migrate(self, name: str, to: str, *, state: dict[str, dict[str, Any]] | None = None,
                timeout: float | None = None) -> MigrationReport:
        with self._held(f"migrate {name} to {to}", timeout, lend=[name]) as left:
            if to not in self.plan.nodes:
                raise ConfigError([f"migrate {name}: no node {to!r}; nodes: "
                                   f"{', '.join(self.plan.nodes)}"])
            specs = self.launcher.specs
            names = [name] if name in specs else [
                child for child in specs if child.startswith(f"{name}/")]
            if not names:
                self.launcher.node_of(name)           # raises ModuleNotFound
            sources = {child: specs[child].node for child in names}
            late: MovedLate | None = None
            try:        # (a macro's: one pause) every step within what the lock left
                reports = migrate(self.launcher, names, to, state, left())
            except ValueError:                  # refused (a ConfigError too): nothing tried
                raise
            except MovedLate as exc:            # moved, its setup there not returned yet
                late, reports = exc, exc.reports
            except Exception as exc:            # tried, and failed: said, as a move is
                for child, source in sources.items():
                    if source != to:
                        self.event_log.record("migration_failed", child, source=source,
                                              destination=to, error=str(exc) or
                                              type(exc).__name__)
                raise
            moved = {report.module for report in reports if report.source != to}
            for report in reports:
                if report.module in moved:
                    self.event_log.record("module_moved", report.module, source=report.source,
                                       destination=report.destination, pause_s=report.pause_s)
            rewired = sum(1 for link in self.launcher.links.values()
                          if moved & {link.src, link.dst})
            self.env.update()          # the moves and the workers, for agents
        if late is not None:        # (a plain RuntimeTimeout: the same through connect)
            raise RuntimeTimeout(str(late)) from None
        if len(reports) == 1:
            return reports[0]
        longest = max(reports, key=lambda r: r.pause_s)       # its phases stand for all
        return MigrationReport(name, ",".join(sorted({r.source for r in reports})), to,
                               longest.pause_s, sum(r.state_bytes for r in reports),
                               rewired, longest.phases, longest.prepare_s, longest.wait_s,
                               moved=bool(moved))

    def begin_migration(self, name: str, to: str, *,
                        state: dict[str, dict[str, Any]] | None = None,
                        timeout: float | None = None) -> int:
        """Start ``migrate`` on another thread; the number to ask ``migration`` about. An
        agent moving itself must not wait: the move pauses it once its body returns."""
        job = next(self._job_ids)
        done, outcome = threading.Event(), [RUNNING, None]
        self._jobs[job] = (done, outcome)
        while len(self._jobs) > KEEP_JOBS:
            del self._jobs[next(iter(self._jobs))]

        def move() -> None:
            try:
                outcome[:] = [DONE, self.migrate(name, to, state=state, timeout=timeout)]
            except Exception as exc:
                log.warning("migrate %s to %s failed: %s", name, to, exc)
                # (a PB3A error as it is: a ConfigError, say, is told from a failure)
                outcome[:] = [FAILED, exc if isinstance(exc, PB3AError) else
                              f"{type(exc).__name__}: {exc}"]
            done.set()
        threading.Thread(target=move, name=f"pb3a-migrate-{name}", daemon=True).start()
        return job

    def migration(self, id: int, *, timeout: float | None = 0.0) -> tuple[str, Any]:
        """How background migration ``id`` went: ``("running", None)``, ``("done",
        report)`` or ``("failed", error)`` (the PB3A error it raised, else a message),
        waiting up to ``timeout`` for it to end (None: the system's default)."""
        entry = self._jobs.get(id)
        if entry is None:
            raise ValueError(f"no migration {id} (only the last {KEEP_JOBS} are kept)")
        done, outcome = entry
        wait = self._call_timeout(timeout)
        asker = _ASKER.get()
        if wait and not done.is_set() and asker is not None and asker[1] \
                and self.lock.lends_to(asker[0]):
            # (the move waits for the lock that the change starting this agent holds,
            # which waits for this very setup: both sat out their timeouts)
            raise RuntimeFailure(
                f"migration {id}: waited for by agent {asker[0]!r} from its setup, which "
                f"{self.lock.doing()} waits for while it holds the system's configuration "
                "lock, and the move needs that lock: it would wait for itself; leave the "
                "move to run (its event module_moved says when), or wait for it in step()")
        done.wait(wait)
        status, value = outcome             # (set before ``done``: never half written)
        return status, value

    def reload(self, module: str, *, timeout: float | None = None) -> None:
        problem = reload_problem(module)
        if problem is not None:
            raise ConfigError([f"reload {module}: {problem}; nothing was reloaded"])
        with self._held(f"reload {module}", timeout):
            forget(module)
            trial.forget(module)
            for node in self.launcher.nodes.values():
                node.forget(module)

    def swap(self, name: str, cls: type | str, *, timeout: float | None = None) -> list[str]:
        """Run module ``name`` as class ``cls`` from now on, keeping its ports and the
        state names the new class has (the names kept). A module file not imported yet
        is tried in a child process first (``_resolved``), within the timeout.

        ``cls`` a reference ("module:Class") whose module's file changed since it was
        imported here: that module is reloaded first (``reload``), saying so in the log
        and in the event (a swap after an edit ran the code imported before it, while it
        said the new class was in). A class object is swapped in as it is, and an agent's
        swap takes the code imported here (agents reload nothing)."""
        wait = self._call_timeout(timeout)
        deadline = time.monotonic() + wait
        reloaded = self._reload_if_changed(f"swap {name}", cls, wait)
        # (the whole timeout, unless a reload took some: an import refused for hanging
        # is refused again at once only for a timeout no longer than it had)
        new_cls, unresolved = _resolved(cls, _left(deadline) if reloaded else wait)
        if new_cls is None:
            raise ConfigError([f"swap {name}: {unresolved}"])
        with self._held(f"swap {name}", _left(deadline), lend=[name]):
            launcher = self.launcher
            node = launcher.node_of(name)
            spec = launcher.specs[name]
            problems = _swap_problems(name, spec.cls, new_cls, launcher.links, launcher.specs)
            if problems:
                raise ConfigError(problems)
            # its configured state (what a fresh restart starts from, what configuration()
            # writes): only the keys the new class takes; its period the new class's,
            # unless the configuration gave the module one of its own
            spec = replace(spec, cls=new_cls, state={
                key: value for key, value in spec.state.items()
                if not checks.state(new_cls, {key: value})},
                period=spec.period if spec.own_period else new_cls.period)
            kept, dropped = node.swap(name, spec)
            launcher.specs[name] = spec
        if dropped:         # (values set live, tuned gains say, that the swap let go)
            log.warning("swap %s: state dropped, %s has no such fields: %s", name,
                        new_cls.__qualname__, ", ".join(dropped))
        self.event_log.record("module_swapped", name, cls=f"{new_cls.__module__}:"
                           f"{new_cls.__qualname__}", kept=kept, dropped=dropped,
                           **({"reloaded": reloaded} if reloaded else {}))
        return kept

    def _reload_if_changed(self, doing: str, cls: type | str, timeout: float) -> str | None:
        """Reload the module of class reference ``cls`` if its file changed since it was
        imported here (``changed_since_import``), before a swap or an add (``doing``, as
        the log says it); the module reloaded, else None. One that may not be reloaded
        (``reload_problem``: an installed package) is left, and so is an agent's call:
        agents reload nothing (``FOR_AGENTS``)."""
        if not isinstance(cls, str) or ":" not in cls or _ASKER.get() is not None:
            return None
        module = cls.partition(":")[0]
        if not changed_since_import(module) or reload_problem(module) is not None:
            return None
        self.reload(module, timeout=timeout)
        log.warning("%s: module %s changed since it was imported: reloaded", doing, module)
        return module

    # -- links -------------------------------------------------------------------------
    def relink(self, src: str, dst: str, *, policy: str | None = None,
               timeout: float | None = None) -> None:
        with self._held(f"relink {src} -> {dst}", timeout, acts_on=_ends(src, dst)):
            env = self._unstarted_env(src)
            link = self._new_link(src, dst, policy, env)
            launcher = self.launcher
            olds = [old for old in launcher.links.values()
                    if (old.dst, old.dst_port) == (link.dst, link.dst_port)]
            if policy is None and olds:          # the link's own, not the input's declared
                link = replace(link, policy=olds[0].policy)
            if env is not None:
                self._start(env, [])
            try:
                # Writers pause so that nothing is written while the input changes
                # source; the reader drains the old link before the new one opens.
                with launcher.paused([link.src, *(old.src for old in olds)]):
                    for old in olds:
                        launcher.disconnect(old.key)
                    launcher.connect(link)
            except BaseException:
                if env is not None:
                    self._drop(env.name)
                raise
        if env is not None:
            self.event_log.record("module_added", env.name, node=env.node)
        for old in olds:
            self.event_log.record("link_removed", old.key)
        self.event_log.record("link_added", link.key, policy=str(link.policy))

    def link(self, src: str, dst: str, *, policy: str | None = None,
             timeout: float | None = None) -> None:
        with self._held(f"link {src} -> {dst}", timeout, acts_on=_ends(src, dst)):
            env = self._unstarted_env(src)
            link = self._new_link(src, dst, policy, env)
            for old in self.launcher.links.values():
                if (old.dst, old.dst_port) == (link.dst, link.dst_port):
                    raise ConfigError([f"input {dst} is fed by {old.src}.{old.src_port} "
                                       "already; use relink() to replace its source"])
            if env is None:
                self.launcher.connect(link)
            else:                       # (wired as it starts: one that fails, dropped)
                self._start(env, [link])
        if env is not None:
            self.event_log.record("module_added", env.name, node=env.node)
        self.event_log.record("link_added", link.key, policy=str(link.policy))

    def _unstarted_env(self, src: str) -> FlatModule | None:
        """The built-in env module that ``src`` ("env-NODE.port") reads, of a node of the
        system, if it does not run: a link reading it starts it, as one in the
        configuration does at launch (it said "no module 'env-a'")."""
        module = src.rpartition(".")[0]
        node = module[len(ENV_PREFIX):]
        if (not module.startswith(ENV_PREFIX) or module in self.launcher.specs
                or node not in self.launcher.nodes):
            return None
        return FlatModule(module, Environment, node, Environment.period, {},
                          Environment.restart)

    def _new_link(self, src: str, dst: str, policy: str | None,
                  env: FlatModule | None = None) -> FlatLink:
        """The link ``src`` -> ``dst`` checked (``ConfigError`` naming every problem); its
        source may be ``env``, an env module to start with it (``_unstarted_env``)."""
        problems = []
        ends = []
        for text, side in ((src, "outputs"), (dst, "inputs")):
            module, _, port = text.rpartition(".")
            shown = module
            exports = self.plan.exports.get(module)
            if exports is not None and module not in self.launcher.specs:
                if port not in exports:        # (a macro instance's: its exports lead in)
                    problems.append(f"link {src} -> {dst}: macro instance {module!r} exports "
                                    f"no port {port!r}{checks.did_you_mean(port, exports)}; "
                                    f"it exports: {checks.listing(exports)}")
                    continue
                module, port = exports[port]
                shown = f"{module} (where {text} leads)"
            spec = env if env is not None and module == env.name else \
                self.launcher.specs.get(module)
            if spec is None:
                problems.append(f"link {src} -> {dst}: no module {module!r}; "
                                + self.launcher.which_modules(module))
            elif port not in getattr(spec.cls, side):
                names = ", ".join(getattr(spec.cls, side)) or "(none)"
                problems.append(f"link {src} -> {dst}: {shown} has no {side[:-1]} {port!r}; "
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

    # -- modules -----------------------------------------------------------------------
    def add(self, name: str, cls: type | str, *, state: dict[str, Any] | None = None,
            period: float | None = None, fixed_rate: bool | None = None,
            restart: str | None = None, group: str | None = None, node: str | None = None,
            fallback: list[str] | None = None, timeout: float | None = None) -> None:
        """Start a new module, or a macro instance (``cls`` a ``Macro``: see
        ``_add_macro``). It is checked as the compiler checks a configuration's entry
        first (name, period, fixed rate, restart, state, group, node, fallback): one
        ``ConfigError`` naming every problem, and nothing started. A module file not
        imported yet is tried in a child process first (``_resolved``), within the
        timeout.

        ``cls`` a reference whose module's file changed since it was imported here: that
        module is reloaded first, as a swap does (``_reload_if_changed``), saying so in
        the log and in the ``module_added`` event (``reloaded``): a class written into
        the file after launch was said not to be in it, and an edited one ran as it was
        before the edit."""
        wait = self._call_timeout(timeout)
        deadline = time.monotonic() + wait
        reloaded = self._reload_if_changed(f"add {name}", cls, wait)
        module_cls, unresolved = _resolved(cls, _left(deadline) if reloaded else wait)
        said = {"reloaded": reloaded} if reloaded else {}
        if isinstance(module_cls, type) and issubclass(module_cls, Macro) \
                and module_cls is not Macro:
            self._add_macro(name, module_cls, state=state, period=period,
                            fixed_rate=fixed_rate, restart=restart, group=group, node=node,
                            fallback=fallback, deadline=deadline, wait=wait, said=said)
            return
        with self._held(f"add {name}", _left(deadline), lend=[name]) as left:
            launcher = self.launcher
            node = node or checks.env_home(name, launcher.nodes) or next(iter(self.plan.nodes))
            problems = [unresolved] if module_cls is None else []
            problems += _add_problems(name, module_cls, state, period, restart, group, node,
                                      fallback, launcher.specs, list(launcher.nodes),
                                      fixed_rate)
            if problems:
                raise ConfigError([f"module {name}: {problem}" for problem in problems])
            spec = FlatModule(name, module_cls, node,
                              float(period) if period is not None else module_cls.period,
                              dict(state or {}), restart or module_cls.restart, group,
                              list(fallback or []), own_period=period is not None,
                              fixed_rate=fixed_rate)
            budget = left()
            try:
                with bounding(budget):          # (a construction that blocks, say)
                    self._start(spec, [])       # (one that cannot start is not added)
            except RuntimeFailure as exc:
                late = _set_up_late(exc, wait, budget)
                if late is None:
                    raise
                raise RuntimeTimeout(f"{name}'s setup did not finish within {late[1]} s; it "
                                     f"was not added: {late[2]}") from None
        self.event_log.record("module_added", name, node=node, **said)

    def _add_macro(self, name: str, macro: type[Macro], *, state: Any, period: Any,
                   fixed_rate: Any, restart: Any, group: Any, node: str | None, fallback: Any,
                   deadline: float, wait: float, said: dict[str, Any]) -> None:
        """Start a macro instance: its modules as ``name/child`` paths, on ``node`` (the
        first node by default) unless a child names its own, and the links inside it,
        expanded and checked by the compiler as a configuration's entry is, then against
        the running modules (a name taken, a group on another node): one ``ConfigError``,
        nothing started. If a module of it cannot start, those added are removed again.
        Links made at run time reach it through its exports (``"f2.x"``), as in a
        configuration, or join its modules' own ports (``"f2/gain.x"``); ``migrate``,
        ``remove`` and ``configuration()`` find it by its paths. ``wait``: the add's
        timeout, which ends at ``deadline``; ``said``: what its ``module_added`` events
        add (``reloaded``)."""
        refused = _refused_imports(macro, deadline)
        with self._held(f"add {name}", _left(deadline), lend=[name]) as left:
            launcher = self.launcher
            node = node or next(iter(self.plan.nodes))
            known = isinstance(node, str) and node in launcher.nodes
            problems = _name_problems(name, launcher.specs) + refused
            expanded = None
            # (a name that is no path has no expansion to check; a module file refused
            # must not be imported here by the compiler: it hung, or ended the launcher)
            if not problems:
                parent, _, leaf = name.rpartition("/")
                entry = ModuleSpec(leaf, cls=macro, state={} if state is None else state,
                                   period=period, fixed_rate=fixed_rate, restart=restart,
                                   fallback=fallback,
                                   node=node if known else None)
                spec = SystemSpec(self.plan.name, nodes=dict(self.plan.nodes),
                                  modules={leaf: entry})
                expanded, found = plan_addition(spec, f"{parent}/" if parent else "",
                                                group if isinstance(group, str) else None)
                top = f"{spec.origin} [modules.{leaf}]: "       # (said as "macro NAME: ")
                problems += [problem.removeprefix(top) for problem in found]
            if not known:
                problems.append(f"no node {node!r}{checks.did_you_mean(node, launcher.nodes)}"
                                f"; nodes: {checks.listing(launcher.nodes)}")
            if group is not None:
                problems += checks.path(group, "group")
            if expanded is not None:
                problems += [problem for module in expanded.modules.values()
                             for problem in checks.group_apart(module.name, module.group,
                                                               module.node,
                                                               launcher.specs.values())]
            if problems or expanded is None:
                raise ConfigError([f"macro {name}: {problem}" for problem in problems])
            specs, links = list(expanded.modules.values()), expanded.links
            budget = left()
            try:
                with bounding(budget):
                    self._start_all(specs, links)
            except RuntimeFailure as exc:
                late = _set_up_late(exc, wait, budget)
                if late is None:
                    raise
                raise RuntimeTimeout(
                    f"macro {name}: the setup of {', '.join(late[0])} did not finish within "
                    f"{late[1]} s; no module of {name} was added: {late[2]}") from None
            self.plan.exports.update(expanded.exports)
        for spec in specs:
            self.event_log.record("module_added", spec.name, node=spec.node, macro=name,
                                  **said)
        for link in links:
            self.event_log.record("link_added", link.key, policy=str(link.policy))

    def remove(self, name: str, *, timeout: float | None = None, force: bool = False) -> None:
        """Stop a module (its ``teardown``), drop its links and free its process, all
        within ``timeout``: a module that does not answer its stop by then (frozen in
        ``step`` or ``teardown``) is left as it was, and ``RuntimeTimeout`` says so (its
        stop waited a fixed 6 s). With ``force`` its worker is killed (SIGKILL) instead,
        its teardown unfinished, and it is dropped with its links all the same, a moment
        past ``timeout`` (its ``module_removed`` event says ``killed``); not a worker
        that runs other modules too, which would be lost with it: ``RuntimeFailure``
        names them, the module left as it was.

        A macro instance's name removes every module of it, in reverse order, with
        their links; one that is left as it was (its stop not answered) ends the removal
        there, and the error names the modules removed and those left (remove it
        again, with ``force`` if need be)."""
        with self._held(f"remove {name}", timeout, acts_on=[name]) as left:
            launcher = self.launcher
            names = [name] if name in launcher.specs else [
                child for child in launcher.specs if child.startswith(f"{name}/")]
            if not names:
                launcher.node_of(name)                # raises ModuleNotFound
            asker = _ASKER.get()
            # (its RuntimeClient refuses it first, a ValueError in the same words)
            refused = None if asker is None else own_target(asker[0], "remove", name)
            if refused is not None:
                raise ConfigError([refused])
            removed: list[str] = []
            try:
                with bounding(left()):
                    for child in reversed(names):
                        links = [key for key, link in launcher.links.items()
                                 if child in (link.src, link.dst)]
                        killed = launcher.remove_module(child, force=force)
                        removed.append(child)
                        self._removed(child, links, killed)
            except (RuntimeTimeout, RuntimeFailure) as exc:
                if not removed:
                    raise
                self._forget_exports(name)
                left_there = [child for child in names if child not in removed]
                raise type(exc)(f"remove {name}: {exc}; removed: {', '.join(removed)}; "
                                f"left running: {', '.join(left_there)}") from exc
            self._forget_exports(name)

    def _forget_exports(self, name: str) -> None:
        """A removed macro instance's exports (and its inner instances'), which no link
        made later may name (a module of it left running is still named by its path)."""
        for instance in [path for path in self.plan.exports
                         if path == name or path.startswith(f"{name}/")]:
            del self.plan.exports[instance]

    def _removed(self, name: str, links: list[str], killed: int | None) -> None:
        """Record the removal of module ``name`` and of its ``links`` (``killed``: the
        process id of its worker, if it was killed)."""
        for key in links:       # (a reader of the events kept a link to nowhere)
            self.event_log.record("link_removed", key)
        if killed is None:
            self.event_log.record("module_removed", name)
        else:
            self.event_log.record("module_removed", name, killed=True, pid=killed,
                                  reason="it did not answer its stop: its worker was "
                                         "killed (its teardown did not finish)")

    def restart(self, name: str, *, timeout: float | None = None, force: bool = False) -> None:
        """Stop a module (also a failed one) and start it again with its configured state
        in a new worker; its links are wired again. Values queued in its inputs go with
        the old instance. Its configuration is checked before anything stops
        (``ConfigError``); if it cannot start again, it is put back with the state it had
        and its links, and ``RuntimeFailure`` says why (the module is lost only if that
        fails too, and the error then says so). Its stop and its new start are bounded
        by ``timeout`` (a stop not answered by then leaves it as it was, as ``remove``
        does, or with ``force`` kills its worker: its event says ``killed``); putting it
        back takes what it takes."""
        with self._held(f"restart {name}", timeout, lend=[name]) as left:
            launcher = self.launcher
            launcher.node_of(name)                # ModuleNotFound for an unknown name
            spec = launcher.specs[name]
            problems = (checks.state(spec.cls, spec.state) + checks.period(spec.period)
                        + checks.restart(spec.restart))
            if problems:
                raise ConfigError([f"restart {name}: {problem}" for problem in problems])
            links = [link for link in launcher.links.values() if name in (link.src, link.dst)]
            was = self._state_then(name)
            with bounding(left()):
                killed = launcher.remove_module(name, restarting=True, force=force)
            said = {} if killed is None else {"killed": True, "pid": killed}
            # (a stop that waited out the time, then killed the worker, left the start
            # none: it has some of its own then, as the kill's removal has)
            start_s = left() if killed is None else max(left(), KILLED_START_S)
            try:
                with lifted(), bounding(start_s):   # (a construction that blocks, say)
                    self._start(spec, links)
            except Exception as exc:
                with lifted():                  # putting it back runs to its end
                    raise self._put_back(spec, links, was, exc, said) from exc
        self.event_log.record("module_restarted", name, node=spec.node, reason="asked", **said)

    def _state_then(self, name: str) -> bytes | None:
        """The module's state now, to put it back with should its restart fail, pickled:
        its own, restored in full (its fields made at run time too; as a dict they were
        refused); None if it cannot say (its worker is gone, it is stuck in a call, its
        state does not pickle): then its configured state."""
        try:
            return pickling.dumps(self.launcher.call(name, "get_state", STATE_THEN_S))
        except Exception:           # (whatever it is, the restart goes on without it)
            return None

    def _start(self, spec: FlatModule, links: list[FlatLink],
               state: dict[str, Any] | bytes | None = None) -> None:
        """Add, wire and start a module (with ``state``, else its configured one); what
        of it was done is undone if a step fails."""
        launcher = self.launcher
        launcher.add_module(spec, state=state)
        try:
            launcher.connect(*links)
            launcher.node_of(spec.name).start_modules([spec.name])
        except BaseException:
            self._drop(spec.name)
            raise

    def _start_all(self, specs: list[FlatModule], links: list[FlatLink]) -> None:
        """Add, wire and start modules (a macro instance's), each node's in one request
        in their order; if a step fails, every one of them added is removed again."""
        launcher = self.launcher
        added: list[str] = []
        try:
            for spec in specs:
                launcher.add_module(spec)
                added.append(spec.name)
            launcher.connect(*links)
            for node in dict.fromkeys(spec.node for spec in specs):
                launcher.nodes[node].start_modules([spec.name for spec in specs
                                                    if spec.node == node])
        except BaseException:
            for name in reversed(added):
                self._drop(name)
            raise

    def _drop(self, name: str) -> None:
        """Remove what there is of a module that failed to start, each step whatever the
        one before did."""
        launcher = self.launcher
        node = launcher.nodes[launcher.specs[name].node]
        for key in [key for key, link in launcher.links.items() if name in (link.src, link.dst)]:
            with contextlib.suppress(Exception):
                launcher.detach(launcher.links[key])
            del launcher.links[key]
        with contextlib.suppress(Exception):
            node.stop_module(name, 5.0)
        with contextlib.suppress(Exception):
            node.remove_module(name)
        del launcher.specs[name]
        launcher.checkpoints.pop(name, None)

    def _put_back(self, spec: FlatModule, links: list[FlatLink], was: bytes | None,
                  failure: Exception, said: dict[str, Any]) -> RuntimeFailure:
        """After a failed restart: the module as it ran (``was``) and its links; the
        error to raise, saying whether it is back. ``said``: what its events say of the
        restart's stop (its worker killed, and its pid)."""
        name = spec.name
        try:
            self._start(spec, links, state=was)
        except Exception as exc:
            log.warning("restart %s failed (%s), and putting it back failed too: %s",
                        name, failure, exc)
            # (the restart kept its spec: left there, the module could be neither added
            # again, "runs already", nor removed, KeyError)
            self.launcher.specs.pop(name, None)
            self.launcher.checkpoints.pop(name, None)
            for link in links:
                self.event_log.record("link_removed", link.key)
            self.event_log.record("module_removed", name, reason="restart failed", **said)
            return RuntimeFailure(f"restart {name} failed ({failure}), and putting it back "
                                  f"failed too ({exc}): it and its links are no longer in the "
                                  "system; add it again")
        self.event_log.record("module_restarted", name, node=spec.node,
                              reason="put back as it ran: the restart failed", **said)
        return RuntimeFailure(f"restart {name} failed ({failure}); it was put back as it ran, "
                              f"with {'its state' if was is not None else 'its configured state'}"
                              " and its links")

    # -- where things are, figures, events ---------------------------------------------------
    def where(self, name: str, *, timeout: float | None = None) -> str:
        """The node module ``name`` runs on, as the launcher has it now, waiting for no
        change (a move says the new node once the module is captured). One found in
        none that a change in progress acts on (being restarted, or added) is looked
        up once that change is done, under the configuration lock."""
        spec = self.launcher.specs.get(name)
        if spec is not None:
            return spec.node
        if change_to(name, self.lock.changing()) is None:
            self.launcher.node_of(name)           # ModuleNotFound for an unknown name
        with self._held(f"where {name}", timeout, changes=False):
            self.launcher.node_of(name)
            return self.launcher.specs[name].node

    def nodes(self, *, timeout: float | None = None) -> dict[str, NodeStats]:
        """Every node's health, waiting for no change (the heartbeats' own figures)."""
        self._call_timeout(timeout)                     # (checked all the same)
        return self.launcher.node_table()

    def topology(self, *, timeout: float | None = None) -> Topology:
        """The structure, waiting for no change: the modules of a copy of the launcher's
        table, and the links between them (one made meanwhile, to a module not in that
        copy, is left out: nothing shows a link to nowhere)."""
        self._call_timeout(timeout)
        launcher = self.launcher
        specs = dict(launcher.specs)            # (modules first: a new link's come first)
        links = [link for link in dict(launcher.links).values()
                 if link.src in specs and link.dst in specs]
        return topology_of(self.plan.name, self.plan.nodes, specs.values(), links,
                           launcher.node_table(), self.plan.code.module_servers)

    def configuration(self, *, timeout: float | None = None) -> dict[str, Any]:
        """The system as it is now, as the tables of a configuration file:
        ``{"system": tables, "problems": [what could not be written]}``."""
        with self._held("configuration", timeout, changes=False):
            plan = self.plan
            folded = fold(plan.name, plan.nodes, self.launcher.specs.values(),
                          self.launcher.links.values(), plan.code.module_servers, plan.timeout)
        return {"system": folded.tables, "problems": folded.problems}

    def stats(self, *, timeout: float | None = None) -> SystemStats:
        """The figures, within ``timeout``, waiting for no change (``Launcher.stats``):
        a change in progress shows on the modules it acts on (``ModuleStats.change``)."""
        return self.launcher.stats(self._call_timeout(timeout))

    def events(self, since: int = 0, *, timeout: float | None = 0.0,
               last: int | None = None) -> list[Event]:
        return self._history("events", lambda wait: self.event_log.since(since, wait, last),
                             timeout)

    def logs(self, since: int = 0, *, module: str | None = None,
             timeout: float | None = 0.0) -> list[LogEntry]:
        launcher = self.launcher
        if module is not None and not self._ever_ran(module):
            # a misspelt name read nothing, and a follower waited for it for good
            raise ModuleNotFound(f"no module {module!r} in system {launcher.plan.name!r} "
                                 f"nor in its log; {launcher.which_modules(module)}")
        return self._history("logs", lambda wait: self.launcher.logbook.since(
            since, wait, module), timeout)

    def _ever_ran(self, name: str) -> bool:
        """Whether module ``name`` is in the system, or was: in its configuration, added
        since (one being restarted is briefly in neither list of the modules), or named
        in its log. Read without the configuration lock, which a reader must not wait for."""
        return (name in self.launcher.specs or name in self.plan.modules
                or any(event.subject == name for event in self.event_log.since(0))
                or bool(self.launcher.logbook.since(0, 0.0, name)))

    def _history(self, what: str, read: Callable[[float], list[Any]],
                 timeout: float | None) -> list[Any]:
        """The events or log entries ``read`` gives, waiting up to ``timeout`` for a
        first new one. A stopped system's are still read, without waiting; one asked to
        wait for a new one there is told that none will come (a follower ends, rather
        than asking again and again): ``SystemStopped``, also when the system stops
        while it waits."""
        wait = self._call_timeout(timeout)
        entries = read(0.0 if self.launcher.stopped else wait)
        if entries or not wait or not self.launcher.stopped:
            return entries
        raise SystemStopped(f"{what}: system {self.launcher.plan.name!r} is stopped: "
                            "no new entry will come")

    # -- requests from outside --------------------------------------------------------
    def apply(self, op: str, args: dict[str, Any], allowed: frozenset[str] = PUBLIC, *,
              asker: tuple[str, bool] | None = None) -> Any:
        """Run operation ``op`` with ``args`` (from a connection, the CLI or an agent:
        ``asker``, its name and whether it asks from its setup)."""
        if op not in allowed:
            raise UnknownOperation(op, allowed)
        if self.launcher.stopped and op not in _HISTORY:   # (an add waited for dead workers)
            raise SystemStopped(f"{op}: system {self.launcher.plan.name!r} is stopped "
                                "(its events and log can still be read)")
        token = _ASKER.set(asker)
        try:
            return getattr(self, op)(**args)
        finally:
            _ASKER.reset(token)


def _ends(src: str, dst: str) -> list[str]:
    """The modules of a link's ends ("module.port"), which a change of it acts on."""
    return [src.rpartition(".")[0], dst.rpartition(".")[0]]


def _left(deadline: float) -> float:
    """The seconds left until ``deadline`` (of ``time.monotonic()``), none if past."""
    return max(0.0, deadline - time.monotonic())


def _set_up_late(failure: RuntimeFailure, wait: float,
                 budget: float) -> tuple[list[str], str, str] | None:
    """If an add's start ``failure`` is only that the ``setup`` of its modules outlasted
    the start's time (``Executor.start_modules``: halted, then dropped by the add, their
    worker stopped if it hosts nothing else): those modules, that time in seconds (the
    add's ``wait`` if what it had left, ``budget``, bounded the start, else the start's
    own ``REQUEST_TIMEOUT``) and what to do about it. None if a module failed for
    another reason, which is said as it is. (It was a ``RuntimeFailure`` blaming a
    module stuck in "its worker", which did not say that the module was not added.)"""
    late = getattr(failure, "timed_out", [])
    if not late or set(late) != set(getattr(failure, "failed", ())):
        return None
    if budget < REQUEST_TIMEOUT:
        return late, spoken(wait), "give the call a longer timeout"
    return late, f"{REQUEST_TIMEOUT:g}", (f"a module's setup may take {REQUEST_TIMEOUT:g} s at "
                                          "most (open what takes longer in its first step)")


def _resolved(cls: type | str, timeout: float) -> tuple[type | None, str]:
    """The class ``cls`` names and "", or None and why it names none (a problem the
    operation reports with the others, in a ``ConfigError``). A module file this process
    has not imported is imported in a child process first, within ``timeout``: one that
    loops as it is imported, ends the process or crashes it is refused, saying so,
    instead of holding up or taking down the launcher (``pb3a.loading.trial``)."""
    try:
        return resolve_class(cls, watch=trial.tried_first(timeout, CHANGE_LONGER)), ""
    except (ValueError, ImportError, LookupError, TypeError) as exc:
        return None, str(exc)


def _add_problems(name: Any, cls: Any, state: Any, period: Any, restart: Any, group: Any,
                  node: str, fallback: Any, modules: dict[str, FlatModule],
                  nodes: list[str], fixed_rate: Any = None) -> list[str]:
    """What keeps a new module from being added, in the compiler's words (a module
    instance's name, or a group's, may be a macro path: each of its parts is checked)."""
    # (a module named as a running macro instance hid it: configuration() dropped it)
    problems = _name_problems(name, modules, "module instance")
    if cls is not None:                         # (None names no class: the caller says why)
        if not (isinstance(cls, type) and issubclass(cls, Module) and cls is not Module):
            problems.append(f"{cls!r} is not a pb3a.Module subclass")
        else:
            given = {} if state is None else state
            said = checks.state(cls, given)
            problems += said + checks.module_class(cls) + checks.stepped(cls, period)
            if isinstance(given, dict):
                problems += checks.defaults_refused(cls, given, said)
    known = cls if isinstance(cls, type) and issubclass(cls, Module) else None
    problems += checks.fixed_rate(known, fixed_rate, period)
    problems += checks.fallback_used(fallback, restart, known)
    problems += checks.period(period) + checks.restart(restart)
    if node not in nodes:
        problems.append(f"no node {node!r}{checks.did_you_mean(node, nodes)}; nodes: "
                        f"{checks.listing(nodes)}")
    problems += checks.fallback(fallback, nodes) + checks.env_placed(name, node, nodes)
    if group is not None:
        problems += checks.path(group, "group") \
            + checks.group_apart(name, group, node, modules.values())
    return problems


def _name_problems(name: Any, modules: dict[str, FlatModule],
                   what: str = "macro instance") -> list[str]:
    """What keeps ``name`` from being a new module's or macro instance's: not a path, or
    taken (by a module, or by a macro instance's modules), or inside a module."""
    problems = checks.path(name, what)
    if problems:
        return problems
    if name in modules:
        return ["a module of that name runs already"]
    inner = [module for module in modules if module.startswith(f"{name}/")]
    if inner:
        return [f"a macro instance of that name runs already: {', '.join(inner)}"]
    parts = name.split("/")
    above = next((path for path in ("/".join(parts[:depth]) for depth in range(1, len(parts)))
                  if path in modules), None)
    if above is not None:
        return [f"{above} is a module, not a macro instance: it cannot hold others"]
    return []


def _refused_imports(macro: type[Macro], deadline: float) -> list[str]:
    """Why module files that the children of ``macro`` (and of the macros in it) name as
    ``"module:Class"`` may not be imported here: each not imported yet is tried in a
    child process first, until ``deadline``, and one that hung, exited or crashed there
    is refused, saying so. Those that import, or raise, are left to the compiler, which
    imports them and names their problems."""
    refused: list[str] = []
    seen: set[type] = set()
    todo = [macro]
    while todo:
        current = todo.pop()
        if current in seen:
            continue
        seen.add(current)
        entries = current.modules.values() if isinstance(current.modules, dict) else []
        for entry in entries:
            ref = entry.get("class", entry.get("macro")) if isinstance(entry, dict) else entry
            if isinstance(ref, str) and ":" in ref:
                try:
                    ref = resolve_class(ref, watch=trial.tried_first(_left(deadline),
                                                                     CHANGE_LONGER))
                except ImportRefused as exc:
                    refused.append(str(exc))
                    continue
                except Exception:           # (the compiler says it in its own words)
                    continue
            if isinstance(ref, type) and issubclass(ref, Macro):
                todo.append(ref)
    return refused


def _swap_problems(name: str, old: type, new: type, links: dict[str, FlatLink],
                   modules: dict[str, FlatModule]) -> list[str]:
    """Why module ``name`` of class ``old`` cannot become one of class ``new``: what
    ``new`` declares wrong of itself, the ports of ``old`` it lacks, the links whose
    types it breaks; and, when its ports do not fit, the way that works (it was refused
    with no way out): a module of ``new`` added beside it, linked, ``name`` removed."""
    if not (isinstance(new, type) and issubclass(new, Module)):
        return [f"swap {name}: {new!r} is not a pb3a.Module subclass"]
    class_problems = [f"swap {name}: {problem}" for problem in checks.module_class(new)]
    problems = list(class_problems)
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
    if len(problems) > len(class_problems):     # (its ports do not fit: say what does)
        problems.append(f"swap {name}: a swap keeps the module's ports and links; to run "
                        f"{class_ref(new)} in its place, add it beside {name} (pb3a add ADDR "
                        f"NEWNAME {class_ref(new)}, or add()), feed its inputs and read its "
                        "outputs (pb3a relink ADDR FROM TO for each, or link() and relink()), "
                        f"then remove {name} (pb3a remove ADDR {name}, or remove())")
    return problems
