"""Expanding and checking a system description into the flat ``Plan`` the executor runs.

The work goes in phases, each collecting problems instead of stopping at one:

1. *definitions*: the system and every macro it can reach (``[macros.X]`` tables
   and Python ``Macro`` subclasses) are read once each; their module entries are
   checked and their children resolved to a Module class or another definition;
2. *exports* of every definition are resolved down to a leaf module port
   (an export chain that comes back to itself is reported as a cycle);
3. *recursion*: a macro that contains itself is reported and the offending
   entry dropped, so that expansion terminates;
4. *links* of every definition are resolved through exports and checked
   (direction, types, policy);
5. *instances*: the tree is expanded from the top into instance paths
   (``robot/mapper/grid``), nodes and groups inherited, each macro instance's
   macro recorded by its path; then inputs fed twice and groups spread over
   nodes are reported.
6. *notes*: a valid plan notes what it likely leaves undone, valid as it is (a step
   with no period, an input fed by nothing: ``pb3a.config.notes``).

A module that names no node runs on the first declared node ("local" when the
system declares none), the system's ``env-NODE`` on NODE. Problems name the file
(or ``system 'name'``) and the entry, e.g. ``pipeline.toml [[links]] #2 (tick.out ->
scale.x): ...``. Identical problems (one macro used twice) are reported once.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pb3a.config import checks
from pb3a.config.definitions import Child, Definition, toml_key, written
from pb3a.config.description import LinkSpec, ModuleSpec, NodeSpec, SystemSpec
from pb3a.config.exports import LinkResolver
from pb3a.config.notes import plan_notes
from pb3a.config.plan import DEFAULT_NODE, FlatLink, FlatModule, Plan
from pb3a.errors import ConfigError
from pb3a.loading import served, trial
from pb3a.loading.references import changed_since_import, class_ref, resolve_class
from pb3a.loading.sources import CodeSources, file_paths, launcher_paths
from pb3a.model.environment import Environment, env_name
from pb3a.model.macro import Macro
from pb3a.model.module import Module
from pb3a.model.state_edits import floats_as_declared

log = logging.getLogger("pb3a")


def plan_system(spec: SystemSpec) -> tuple[Plan | None, list[str]]:
    """The plan of ``spec`` and its problems; the plan is None unless there are none. It
    is for a launch (or its check): a class's module whose file changed since this
    process imported it is imported anew (``_imported_anew``)."""
    return _Planner(spec, anew=True).run()


def sketch_plan(spec: SystemSpec) -> tuple[Plan, list[str]]:
    """What ``spec`` would run so far, and its problems: the modules whose entries
    resolved and the links between them, also when others have problems (an editor
    draws a half-built system). Never launch it: ``build_plan`` is for that."""
    return _Planner(spec).run(partial=True)


def plan_addition(spec: SystemSpec, within: str = "",
                  group: str | None = None) -> tuple[Plan | None, list[str]]:
    """The plan of what ``spec``'s modules (and macros) add to a running system, and its
    problems (the plan None unless there are none): expanded under the macro instance
    path ``within`` (``""``, ``"robot/"``), each in ``group`` unless its entry names one
    (that one under its macro instance's path, as in a file). ``spec`` holds the
    running system's nodes and no links of its own."""
    return _Planner(spec).run(within=within, group=group)


def validate(spec: SystemSpec) -> list[str]:
    """Every problem in ``spec``, each naming its place and what to change; empty if valid."""
    return plan_system(spec)[1]


def build_plan(spec: SystemSpec) -> Plan:
    """The flat plan of ``spec``; ConfigError listing every problem if it is not valid."""
    plan, problems = plan_system(spec)
    if problems or plan is None:
        raise ConfigError(problems)
    return plan


@dataclass(frozen=True)
class Override:
    """State a macro instance's ``state`` table sets on one of the macro's modules."""

    state: dict[str, Any]
    label: str                 # the instance's entry, for messages
    key: str                   # the module's path as that entry wrote it


class _Planner:
    def __init__(self, spec: SystemSpec, anew: bool = False) -> None:
        self.spec = spec
        self.anew = anew            # import anew a class's module edited since imported
        self.problems: list[str] = list(spec.problems)
        self.node_names: list[str] = list(spec.nodes) or [DEFAULT_NODE]
        self.file_defs: dict[str, Definition] = {}
        self.class_defs: dict[type, Definition] = {}
        # what each module class declares wrong of itself, judged once per plan (a class
        # of a script was pickled again for each of its entries, to see it can be sent)
        self.class_problems: dict[type, list[str]] = {}
        self.order: list[Definition] = []
        self.explored: set[Definition] = set()
        self.code = CodeSources()

    def report(self, label: str, problems: list[str]) -> None:
        self.problems.extend(f"{label}: {problem}" for problem in problems)

    def run(self, partial: bool = False, within: str = "",
            group: str | None = None) -> tuple[Any, list[str]]:
        """The plan and the problems; the plan is None when there are problems, unless
        ``partial`` asks for what resolved (``within``, ``group``: see ``plan_addition``)."""
        spec = self.spec
        nodes = self.check_system()
        self.code = self.install_code()
        top = self.define(Definition(f"system {spec.name!r}", spec.origin, "",
                                     {**spec.modules, **self.env_modules(nodes)}, spec.links,
                                     {}))
        for name in spec.macros:
            self.file_macro(name)
        resolver = LinkResolver(self.problems, top, list(nodes))
        for definition in list(self.order):
            for export in definition.exports:
                if (ref := resolver.export(definition, export)) is not None:
                    definition.exported[export] = ref
        for definition in self.order:          # the system first, then unused macros too
            self.break_recursion(definition, [])
        for definition in self.order:
            resolver.links(definition)
        modules: dict[str, FlatModule] = {}
        labels: dict[str, str] = {}
        links: list[tuple[str, FlatLink]] = []
        instances: dict[str, Definition] = {}
        self.instantiate(top, within, None, group, modules, labels, links, instances)
        self.check_inputs(links)
        self.check_groups(modules, labels)
        problems = list(dict.fromkeys(self.problems))
        if problems and not partial:
            return None, problems
        timeout = (None if spec.timeout is None or checks.timeout(spec.timeout)
                   else float(spec.timeout))
        preload = tuple(sorted({m.cls.__module__ for m in modules.values()} - {"__main__"}))
        return Plan(spec.name, nodes, modules, [link for _, link in links],
                    dataclasses.replace(self.code, preload=preload), timeout,
                    {path: macro.name for path, macro in instances.items()},
                    {path: {export: (f"{path}/{ref.path}", ref.port)
                            for export, ref in macro.exported.items()}
                     for path, macro in instances.items()},
                    [] if problems else plan_notes(modules, [link for _, link in links],
                                                   labels)), problems

    # -- the system's own tables ------------------------------------------
    def install_code(self) -> CodeSources:
        """Where the system's classes come from, installed in this process (its finders
        on ``sys.meta_path``): the file's own directory and the module servers it
        names, those that are addresses. The classes checked next may be next to the
        file, or only on a server."""
        spec, origin = self.spec, self.spec.origin
        servers = spec.module_servers
        if not isinstance(servers, list) or not all(isinstance(s, str) for s in servers):
            self.report(origin, [("module_servers must be a list of addresses such as "
                                 f"['tcp://127.0.0.1:7300'], got {servers!r}")])
            servers = []
        wrong = {server: checks.server_address(server) for server in servers}
        self.report(origin, [problem for problems in wrong.values() for problem in problems])
        servers = [server for server in servers if not wrong[server]]
        # a file's own directory, where its modules may be, then the launcher's
        # PYTHONPATH (a node started without it lacked a class imported from it): not
        # that of a source that only names a description (``System.from_dict``'s), which
        # was the current one; that, and a system built in Python, has the directories
        # its script imported from, which its nodes lacked (a class of a file beside the
        # script)
        here = file_paths(str(Path(spec.source).resolve().parent)) \
            if spec.source is not None and Path(spec.source).is_file() else launcher_paths()
        code = CodeSources(here, tuple(servers))
        code.install()
        return code

    def check_system(self) -> dict[str, NodeSpec]:
        """The nodes the system names, its own tables checked (name, workers, timeout,
        nodes)."""
        spec, origin = self.spec, self.spec.origin
        self.report(origin, [p.replace("unknown key", "unknown top-level key")
                             for p in checks.unknown_keys(spec.extra, SystemSpec.KEYS)])
        if not isinstance(spec.name, str) or not spec.name:
            self.report(origin, [f"name must be a non-empty string, got {spec.name!r}"])
        self.report(origin, [f"top-level {p}" for p in checks.workers(spec.workers)])
        self.report(origin, checks.timeout(spec.timeout))
        for name, node in spec.nodes.items():
            label = written(f"{origin} [nodes.{toml_key(name)}]", node.written_at)
            self.report(label, checks.name(name, "node"))
            self.report(label, checks.unknown_keys(node.extra, NodeSpec.KEYS))
            self.report(label, checks.node_address(node.address))
            self.report(label, checks.workers(node.workers))
            self.report(label, checks.cpus(node.cpus, remote=node.address is not None))
            self.report(label, checks.advertise(node.advertise))
            self.report(label, checks.spares(node.spares))
        seen: dict[str, str] = {}
        for name, node in spec.nodes.items():
            if isinstance(node.address, str) and node.address in seen:
                self.report(f"{origin} [nodes.{toml_key(name)}]", [
                    f"address {node.address!r} is node {seen[node.address]}'s too: one "
                    "node controller serves one node of a system; give each its own "
                    "(pb3a node start --listen on another port)"])
            elif isinstance(node.address, str):
                seen[node.address] = name
        if not spec.nodes:
            workers = spec.workers if not checks.workers(spec.workers) else 0
            return {DEFAULT_NODE: NodeSpec(DEFAULT_NODE, None, workers)}
        nodes = {name: NodeSpec(name, node.address, node.workers, cpus=node.cpus,
                                advertise=node.advertise, spares=node.spares)
                 for name, node in spec.nodes.items()}
        if spec.workers and not checks.workers(spec.workers):
            if DEFAULT_NODE in nodes and not nodes[DEFAULT_NODE].workers:
                nodes[DEFAULT_NODE].workers = spec.workers
            elif DEFAULT_NODE not in nodes:
                self.report(origin, [(f"top-level workers = {spec.workers!r} is for the default "
                                     f"node {DEFAULT_NODE!r}, but the system declares nodes "
                                     f"({checks.listing(nodes)}): set workers in their "
                                     "[nodes.NAME] tables instead")])
        return nodes

    def env_modules(self, nodes: dict[str, NodeSpec]) -> dict[str, ModuleSpec]:
        """The built-in ``env-NODE`` modules that some link reads (and that the system
        does not define itself)."""
        wanted = {}
        for node in nodes.values():
            name = env_name(node.name)
            if name in self.spec.modules:
                continue
            if any(isinstance(link.src, str) and link.src.startswith(f"{name}.")
                   for link in self.spec.links):
                wanted[name] = ModuleSpec(name, cls=Environment, node=node.name)
        return wanted

    # -- phase 1: definitions ---------------------------------------------
    def define(self, definition: Definition) -> Definition:
        self.order.append(definition)
        for name, entry in definition.modules.items():
            definition.children[name] = self.child(definition, name, entry)
        return definition

    def file_macro(self, name: str) -> Definition | None:
        if name in self.file_defs:
            return self.file_defs[name]
        macro = self.spec.macros.get(name)
        if macro is None:
            return None
        definition = Definition(f"macro {name!r}", self.spec.origin, f"macros.{toml_key(name)}.",
                                macro.modules, macro.links, macro.exports,
                                name=f"[macros.{toml_key(name)}]")
        self.file_defs[name] = definition
        self.report(f"{self.spec.origin} [macros.{toml_key(name)}]",
                    checks.name(name, "macro") + checks.unknown_keys(macro.extra,
                                                                       ("modules", "links",
                                                                        "exports")))
        return self.define(definition)

    def class_macro(self, cls: type[Macro]) -> Definition:
        if cls in self.class_defs:
            return self.class_defs[cls]
        origin = f"macro {class_ref(cls)}"
        modules, links, exports = cls.modules, cls.links, cls.exports
        problems = []
        if not isinstance(modules, dict):
            problems.append(f"modules must be a dict of name -> class or entry, got {modules!r}")
            modules = {}
        if not isinstance(exports, dict):
            problems.append(f"exports must be a dict of port -> 'child.port', got {exports!r}")
            exports = {}
        specs = []
        for number, entry in enumerate(links if isinstance(links, (list, tuple)) else [], 1):
            try:
                specs.append(LinkSpec.from_entry(entry))
            except ValueError as exc:
                problems.append(f"links #{number}: {exc}")
        if not isinstance(links, (list, tuple)):
            problems.append(f"links must be a list of (from, to[, policy]) tuples, got {links!r}")
        self.report(origin, problems)
        definition = Definition(origin, origin, "",
                                {n: ModuleSpec.from_entry(n, e) for n, e in modules.items()},
                                specs, exports, name=cls.__name__)
        self.class_defs[cls] = definition
        return self.define(definition)

    def child(self, definition: Definition, name: str, entry: ModuleSpec) -> Child:
        child = Child(entry, written(definition.label("modules", name), entry.written_at))
        problems = checks.name(name, "module instance")
        problems += checks.unknown_keys(entry.extra, ModuleSpec.KEYS)
        if entry.node is not None and entry.node not in self.node_names:
            problems.append(self.unknown_node(entry.node))
        problems += checks.fallback(entry.fallback, self.node_names)
        if entry.group is not None:
            problems += checks.name(entry.group, "group")
        if (entry.cls is None) == (entry.macro is None):
            problems.append("give exactly one of 'class' (a Module class, 'module:Class' or a "
                            "Python Macro) and 'macro' (the name of a [macros.NAME] table)"
                            + ("; it has both" if entry.cls is not None else ""))
        elif isinstance(entry.macro, type) and issubclass(entry.macro, Macro):
            child.macro = self.class_macro(entry.macro)
        elif entry.macro is not None:
            child.macro = self.file_macro(entry.macro) if isinstance(entry.macro, str) else None
            if child.macro is None:
                problems.append(f"unknown macro {entry.macro!r}"
                                f"{checks.did_you_mean(entry.macro, self.spec.macros)}; defined "
                                f"macros: {checks.listing(self.spec.macros)} (define "
                                f"[macros.{entry.macro}] or fix the name)")
        else:
            problems += self.resolve(child)
        if child.macro is not None:
            problems += [f"{key!r} applies to modules, not to a macro: set it on the macro's "
                         "children" for key, value in (("period", entry.period),
                                                       ("fixed_rate", entry.fixed_rate),
                                                       ("restart", entry.restart),
                                                       ("fallback", entry.fallback))
                         if value is not None]
            problems += checks.macro_state(entry.state)
        elif child.cls is not None:
            problems += checks.period(entry.period) + checks.restart(entry.restart)
            problems += checks.stepped(child.cls, entry.period)
            problems += checks.fixed_rate(child.cls, entry.fixed_rate, entry.period)
            problems += checks.fallback_used(entry.fallback, entry.restart, child.cls)
            child.said = checks.state(child.cls, entry.state)
            problems += child.said
            if child.cls not in self.class_problems:
                self.class_problems[child.cls] = checks.module_class(child.cls)
            problems += self.class_problems[child.cls]
        elif entry.cls is not None:      # a class that did not resolve: what needs none
            problems += checks.period(entry.period) + checks.restart(entry.restart)
            problems += checks.fixed_rate(None, entry.fixed_rate, entry.period)
            if not isinstance(entry.state, dict):
                problems += checks.state(Module, entry.state)
        self.report(child.label, problems)
        return child

    def resolve(self, child: Child) -> list[str]:
        if self.anew and isinstance(child.spec.cls, str):
            _imported_anew(child.spec.cls)
        try:
            cls = resolve_class(child.spec.cls)
        except (ImportError, LookupError, TypeError, ValueError) as exc:
            return [str(exc)]
        if issubclass(cls, Macro) and cls is not Macro:
            child.macro = self.class_macro(cls)
        elif issubclass(cls, Module) and cls is not Module:
            child.cls = cls
        else:
            return [(f"class {class_ref(cls)} is not a Module or Macro subclass: name a class "
                    "that subclasses pb3a.Module (or pb3a.Macro)")]
        return []

    def unknown_node(self, node: object) -> str:
        # (said in the words of where the system was described: a file, or Python)
        declare = (f"a [nodes.{node}] table" if self.spec.source is not None
                   else f"system.node({node!r})")
        if not self.spec.nodes:
            return (f"unknown node {node!r}: the system declares no nodes, so everything runs on "
                    f"{DEFAULT_NODE!r}; add {declare} or leave 'node' out")
        return (f"unknown node {node!r}{checks.did_you_mean(node, self.node_names)}; declared "
                f"nodes: {checks.listing(self.node_names)} (add {declare} or use one of them)")

    # -- phase 3: recursion ------------------------------------------------
    def break_recursion(self, definition: Definition, stack: list[Definition]) -> None:
        if definition in self.explored:
            return
        stack.append(definition)
        for child in definition.children.values():
            inner = child.macro
            if inner is None:
                continue
            if inner in stack:
                chain = " -> ".join(d.title for d in [*stack[stack.index(inner):], inner])
                self.report(child.label, [(f"recursive macro: {chain}; a macro cannot contain "
                                          "itself, directly or through other macros")])
                child.macro = None
            else:
                self.break_recursion(inner, stack)
        stack.pop()
        self.explored.add(definition)        # acyclic below here now: never walk it again

    # -- phase 5: instances ------------------------------------------------
    def instantiate(self, definition: Definition, prefix: str, node: str | None,
                    group: str | None, modules: dict[str, FlatModule],
                    labels: dict[str, str], links: list[tuple[str, FlatLink]],
                    instances: dict[str, Definition],
                    overrides: dict[str, list[Override]] | None = None) -> None:
        """Expand ``definition`` under ``prefix``, each macro instance's macro kept in
        ``instances`` by its path; ``overrides`` are the state its instance's ``state``
        table (and those of the instances around it) sets on its modules, keyed by their
        paths inside it: per module, the innermost instance's first, each checked under
        its own entry and applied in turn (an outer instance's value wins for the keys it
        sets, the inner one's others stay)."""
        overrides = dict(overrides or {})
        for name, child in definition.children.items():
            entry, path = child.spec, prefix + name
            here = entry.node if entry.node in self.node_names else node
            if not prefix:                  # (the system's own: env-NODE runs on NODE)
                self.report(child.label, checks.env_placed(name, here, self.node_names))
                here = here or checks.env_home(name, self.node_names)
            team = prefix + entry.group if isinstance(entry.group, str) else group
            if child.cls is not None:
                cls = child.cls
                period = entry.period if not checks.period(entry.period) else None
                restart = entry.restart if not checks.restart(entry.restart) else None
                state = dict(entry.state) if isinstance(entry.state, dict) else {}
                parts = [dict(state)]           # (each judged alone where it is written,
                said = [child.said]             # once: what that said, by table)
                extras = overrides.pop(name, [])
                for extra in extras:
                    said.append(checks.state(cls, extra.state))
                    self.report(extra.label, [f"state of {extra.key!r}: {problem}"
                                              for problem in said[-1]])
                    state.update(extra.state)
                    parts.append(extra.state)
                state = _widened(cls, state)
                whole = checks.defaults_refused(cls, state, _flat(said))
                # Each problem of the whole state is said of the entry whose table brought
                # it: the macro's, or an instance's override (the innermost first). Said of
                # the last override, the macro entry's own was pinned on every instance that
                # overrode another field of the module, an outer macro's on its instances.
                blamed: list[tuple[str, str]] = []
                for level in range(len(extras) + 1):
                    if not whole:
                        break
                    if level == len(extras):    # (the whole state: what is left is its)
                        found = set(whole)
                    else:
                        so_far = _widened(cls, {key: value for part in parts[:level + 1]
                                                for key, value in part.items()})
                        found = set(checks.defaults_refused(cls, so_far,
                                                            _flat(said[:level + 1])))
                    for problem in [problem for problem in whole if problem in found]:
                        blamed.append((child.label, problem) if level == 0 else (
                            extras[level - 1].label,
                            f"state of {extras[level - 1].key!r}: {problem}"))
                        whole.remove(problem)
                for label, problem in blamed:
                    self.report(label, [problem])
                modules[path] = FlatModule(
                    path, cls, here or self.node_names[0],
                    float(period) if period is not None else cls.period, state,
                    restart or cls.restart, team,
                    list(entry.fallback or []) if not checks.fallback(
                        entry.fallback, self.node_names) else [],
                    own_period=period is not None,
                    fixed_rate=entry.fixed_rate if isinstance(entry.fixed_rate, bool) else None)
                labels[path] = child.label
            elif child.macro is not None:
                own = entry.state if not checks.macro_state(entry.state) else {}
                inner = {key: [Override(value, child.label, key)] for key, value in own.items()}
                for key in [key for key in overrides if key.startswith(f"{name}/")]:
                    inner.setdefault(key.removeprefix(f"{name}/"), []).extend(
                        overrides.pop(key))             # after the inner one's: it wins
                instances[path] = child.macro
                self.instantiate(child.macro, path + "/", here, team, modules, labels, links,
                                 instances, inner)
        modules_here = [name for name, child in definition.children.items() if child.cls]
        for extra in [extra for layers in overrides.values() for extra in layers]:
            self.report(extra.label, [
                f"state names {extra.key!r}, which is not a module of {definition.title}; its "
                f"modules: {checks.listing(modules_here)} (a child macro's modules as "
                "'macro/module')"])
        for label, src, dst, policy in definition.resolved:
            source, target = prefix + src.path, prefix + dst.path
            if source in modules and target in modules:
                links.append((label, FlatLink(source, src.port, target, dst.port, policy)))

    def check_inputs(self, links: list[tuple[str, FlatLink]]) -> None:
        fed: dict[tuple[str, str], str] = {}
        for label, link in links:
            first = fed.setdefault((link.dst, link.dst_port), label)
            if first != label:
                self.report(label, [(f"input {link.dst}.{link.dst_port} is fed twice: it is "
                                    f"already fed by {first}; an input takes at most one link, "
                                    "so remove one of them or feed another input")])

    def check_groups(self, modules: dict[str, FlatModule], labels: dict[str, str]) -> None:
        first: dict[str, FlatModule] = {}
        for module in modules.values():
            if module.group is None:
                continue
            other = first.setdefault(module.group, module)
            self.report(labels[module.name], checks.group_apart(
                module.name, module.group, module.node, [other]))


def _flat(said: list[list[str]]) -> list[str]:
    """The problems said of each of several tables, as one list."""
    return [problem for problems in said for problem in problems]


def _widened(cls: type[Module], state: dict[str, Any]) -> dict[str, Any]:
    """``state`` with each whole number given where the class default holds a float made
    that float, in lists, tuples and dicts too (``floats_as_declared``): TOML and JSON
    write 4.0 as 4 as often as not, and the module should not get an int it never had."""
    return {name: floats_as_declared(getattr(cls, name, None), value)
            for name, value in state.items()}


def _imported_anew(ref: str) -> None:
    """Drop the module of class reference ``ref`` from this process's cache if its file
    changed since it was imported here (``changed_since_import``) and it may be reloaded
    (``served.reload_problem``), as ``reload`` does in a launcher, so that the class is
    imported from the file as it is now: a second launch in one process (a notebook, a
    sweep) checked, and its launcher ran, the class from before the edit."""
    module = ref.partition(":")[0]
    if ":" in ref and changed_since_import(module) and served.reload_problem(module) is None:
        served.forget(module)
        trial.forget(module)
        log.info("module %s changed since it was imported: imported again", module)
