"""Wiring: resolving ``"module.port"`` endpoints through macro exports, and checking links.

An endpoint in a definition (the system or a macro) names one of its children
and a port. When the child is a leaf module the port is one of its class's
ports; when it is a macro the port is one of the macro's exports, which names
an endpoint inside that macro, and so on down to a leaf. ``PortRef`` is where
such a chain ends. A link is then checked: from an output, to an input, of
compatible types, with a valid policy.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from pb3a.config import checks
from pb3a.config.definitions import PortRef, written
from pb3a.config.description import LinkSpec
from pb3a.loading.references import class_ref
from pb3a.model.environment import PREFIX as ENV_PREFIX
from pb3a.model.environment import env_name
from pb3a.model.ports import Input, Output, Policy

if TYPE_CHECKING:
    from pb3a.config.definitions import Definition


class LinkResolver:
    """Resolves exports (memoized, cycle-checked) and links, appending problems to a list."""

    def __init__(self, problems: list[str], system: Definition | None = None,
                 nodes: Sequence[str] = ()) -> None:
        self.problems = problems
        self.system = system            # whose links may read the nodes' env modules
        self.nodes = list(nodes)
        self._cache: dict[tuple[int, str], PortRef | None] = {}
        self._trail: list[tuple[Definition, str]] = []

    def export(self, definition: Definition, name: str) -> PortRef | None:
        """Where ``definition``'s export ``name`` leads, or None (problems reported)."""
        key = (id(definition), name)
        if key in self._cache:
            return self._cache[key]
        if (definition, name) in self._trail:
            start = self._trail.index((definition, name))
            chain = " -> ".join(f"{d.title}.{n}" for d, n in
                                [*self._trail[start:], (definition, name)])
            self.problems.append(f"{definition.label('exports', name)}: export chain {chain} "
                                 "is a cycle; an export must lead to a port of a module")
            return None
        self._trail.append((definition, name))
        try:
            label = definition.label("exports", name)
            problems = checks.name(name, "export")
            if not problems and not name.isidentifier():     # it names a port
                problems = [f"export name {name!r} names a port: use letters, digits and "
                            "'_' only, not starting with a digit"]
            ref, found = self.endpoint(definition, definition.exports[name], "the export")
            self.problems.extend(f"{label}: {p}" for p in problems + found)
        finally:
            self._trail.pop()
        self._cache[key] = ref
        return ref

    def endpoint(self, definition: Definition, text: Any,
                 what: str) -> tuple[PortRef | None, list[str]]:
        """Resolve ``"child.port"`` in ``definition``; problems say what to change."""
        if text is None:
            return None, [f"{what} is missing: give it as \"module.port\", e.g. \"tick.out\""]
        child_name, dot, port = text.partition(".") if isinstance(text, str) else ("", "", "")
        if dot and "/" in child_name and port.isidentifier():
            return None, [self.inside_macro(definition, text, what)]
        if not (dot and checks.NAME.match(child_name) and port.isidentifier()):
            return None, [f"{what} must be \"module.port\" (e.g. \"tick.out\"), got {text!r}"]
        child = definition.children.get(child_name)
        if child is None:
            if definition is self.system and child_name.startswith(ENV_PREFIX):
                return None, [self.no_env_module(definition, child_name)]
            return None, [(f"{definition.title} has no module {child_name!r}"
                          f"{checks.did_you_mean(child_name, definition.children)}; its modules: "
                          f"{checks.listing(definition.children)}")]
        if child.cls is not None:
            ports: dict[str, Input | Output] = {**child.cls.inputs, **child.cls.outputs}
            if port not in ports:
                kinds = [f"{n} ({'input' if isinstance(p, Input) else 'output'})"
                         for n, p in ports.items()]
                return None, [(f"module {child_name!r} ({class_ref(child.cls)}) has no port "
                              f"{port!r}{checks.did_you_mean(port, ports)}; its ports: "
                              f"{checks.listing(kinds)}")]
            return PortRef(child_name, child.cls, port, ports[port]), []
        if child.macro is not None:
            exports = child.macro.exports
            if port not in exports:
                return None, [(f"macro {child_name!r} ({child.macro.title}) exports no port "
                              f"{port!r}{checks.did_you_mean(port, exports)}; it exports: "
                              f"{checks.listing(exports)} (add it to the macro's exports)")]
            inner = self.export(child.macro, port)
            if inner is None:
                return None, []
            return PortRef(f"{child_name}/{inner.path}", inner.cls, inner.port, inner.spec), []
        return None, []           # the child itself is broken and already reported

    def inside_macro(self, definition: Definition, text: str, what: str) -> str:
        """A port inside a macro instance (``"f/child.y"``, as a running system names its
        modules), which a link reaches only through the macro's exports: the export that
        leads there if there is one, else the export to add (it said only that the
        endpoint must be "module.port")."""
        path, _, port = text.partition(".")
        outer, _, inner = path.partition("/")
        child = definition.children.get(outer)
        if child is None or child.macro is None:
            kind = ("is a module, not a macro instance" if child is not None and child.cls
                    else f"is not a macro instance of {definition.title}")
            return (f"{what} = {text!r} names a port inside a macro instance, which a link "
                    f"reaches only through the macro's exports, and {outer!r} {kind}; its "
                    f"modules: {checks.listing(definition.children)}")
        macro = child.macro
        for name in macro.exports:
            ref = self.export(macro, name)
            if ref is not None and (ref.path, ref.port) == (inner, port):
                return (f"{what} = {text!r} is a port inside macro instance {outer!r}, which "
                        f"a link reaches only through the macro's exports: {macro.title} "
                        f"exports it as {name!r}, so link \"{outer}.{name}\"")
        name = port if port not in macro.exports else f"{inner.replace('/', '_')}_{port}"
        how = (f"add {name} = \"{inner}.{port}\" to the exports of {macro.title}"
               if "/" not in inner else
               f"export it from each macro on the way in, then from {macro.title}")
        return (f"{what} = {text!r} is a port inside macro instance {outer!r}, which a link "
                f"reaches only through the macro's exports: {how} and link "
                f"\"{outer}.{name}\"")

    def no_env_module(self, definition: Definition, name: str) -> str:
        """``env-X`` read where the system has no node X: the env modules it does have
        (they are made for its nodes, so the list of its modules named none of them)."""
        node = name[len(ENV_PREFIX):]
        envs = [env_name(n) for n in self.nodes]
        return (f"{definition.title} has no module {name!r}: it has no node {node!r}, and "
                f"each node's built-in env module is env-NODE, here {checks.listing(envs)}; "
                f"read one of those, or declare [nodes.{node}]")

    def links(self, definition: Definition) -> None:
        """Check every link of ``definition``; the valid ones go to ``definition.resolved``."""
        for number, link in enumerate(definition.links, 1):
            label = written(f"{definition.origin} [[{definition.prefix}links]] #{number} "
                            f"({link.title})", link.written_at)
            problems = checks.unknown_keys(link.extra, LinkSpec.KEYS)
            src, found = self.endpoint(definition, link.src, "'from'")
            problems += found
            dst, found = self.endpoint(definition, link.dst, "'to'")
            problems += found
            if src is not None and src.is_input:
                problems.append(f"'from' = {link.src!r} is an input; a link goes from an output "
                                "to an input: swap 'from' and 'to', or name an output")
                src = None
            if dst is not None and not dst.is_input:
                problems.append(f"'to' = {link.dst!r} is an output; a link goes from an output "
                                "to an input: swap 'from' and 'to', or name an input")
                dst = None
            if src is not None and dst is not None and isinstance(dst.spec, Input) \
                    and isinstance(src.spec, Output):
                reason = dst.spec.accepts(src.spec)
                if reason:
                    problems.append(
                        f"incompatible types: {link.src} gives {src.spec.describe()} but "
                        f"{link.dst} takes {dst.spec.describe()} ({reason}); link ports of "
                        "matching types, or change one port's type")
            declared = dst.spec.policy if dst is not None and isinstance(dst.spec, Input) \
                else None
            policy, wrong_policy = declared, []
            if link.policy is not None:
                try:
                    policy = Policy.parse(link.policy)
                except ValueError as exc:        # (the link still counts for the
                    wrong_policy = [             # checks of the input it feeds)
                        f"{exc} (or leave 'policy' out to keep the input's own)"]
            self.problems.extend(f"{label}: {p}" for p in problems + wrong_policy)
            if not problems and src is not None and dst is not None and policy is not None:
                definition.resolved.append((label, src, dst, policy))
