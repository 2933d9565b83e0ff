"""The layout shows the design: dependencies point one way, and nothing runs in a circle.

Every import counts, also one inside a function or under ``TYPE_CHECKING``: either
ties the two modules together. The layers are the ones ``docs/architecture.md``
draws, lowest first.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# Each layer may import the layers before it; inside a layer, a package imports only
# itself (launch and daemons, say, know nothing of each other).
LAYERS: list[set[str]] = [
    {"pb3a.errors", "pb3a.log_format"},                 # the exception tree and the log
                                                        # line's format, under all
    {"pb3a.atomic_write", "pb3a.deadline", "pb3a.events", "pb3a.latencies", "pb3a.logbook",
     "pb3a.pending", "pb3a.processes", "pb3a.stats", "pb3a.throttle"},
    {"pb3a.transport"},                                 # how bytes move
    {"pb3a.model", "pb3a.loading"},                     # what users write; code by reference
    {"pb3a.config"},                                    # description -> checked plan
    {"pb3a.topology"},                                  # a system's structure, as records
    {"pb3a.worker"},                                    # the worker process
    {"pb3a.node"},                                      # one node's supervisor
    {"pb3a.cpu_load"},                                  # load for experiments, from the
                                                        # workers' forkserver
    {"pb3a.launch", "pb3a.daemons"},                    # the whole system; the daemons
    {"pb3a.system", "pb3a.testing"},                    # the builder users start from; a
                                                        # module tested on its own
    {"pb3a.manager"},                                   # the ModuleManager web app
    {"pb3a.cli"},                                       # the command line
    {"pb3a", "pb3a.__main__"},                          # the public API
]
# What RAVE, a user of PB3A, takes from it: the cluster key and control channel for
# its robot servers, child processes, and the daemon runner of its command line.
RAVE_USES = {"pb3a.errors", "pb3a.processes", "pb3a.transport", "pb3a.cli"}


def _modules(top: str) -> dict[str, Path]:
    found = {}
    for path in (ROOT / top).rglob("*.py"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        found[".".join(parts[:-1] if path.name == "__init__.py" else parts)] = path
    return found


def _imports(name: str, path: Path) -> set[str]:
    """Every dotted name ``name``'s file imports: ``from x import y`` is x.y when y is a
    module (the package x only runs first), else x."""
    targets: set[str] = set()
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join([*parent, *([node.module] if node.module else [])])
            names = {f"{base}.{alias.name}" for alias in node.names}
            submodules = {n for n in names if _is_module(n)}
            targets.update(submodules)
            if names - submodules:
                targets.add(base)
    return targets


def _is_module(dotted: str) -> bool:
    path = ROOT.joinpath(*dotted.split("."))
    return (path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()
            or path.with_suffix(".c").is_file())      # a C extension, built beside its source


def _graph(tops: tuple[str, ...]) -> dict[str, set[str]]:
    modules = {name: path for top in tops for name, path in _modules(top).items()}
    return {name: {t for t in _imports(name, path) if t in modules and t != name}
            for name, path in modules.items()}


def _unit(module: str) -> str:
    return ".".join(module.split(".")[:2])


def _layer(module: str) -> int:
    unit = _unit(module)
    for number, layer in enumerate(LAYERS):
        if unit in layer:
            return number
    raise AssertionError(f"{module} is in no layer: add {unit} to LAYERS and to the docs")


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected groups of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while (w := stack.pop()) != v:
                group.append(w)
            group.append(v)
            if len(group) > 1:
                groups.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return groups


@pytest.mark.parametrize("tops", [("pb3a",), ("rave",), ("agents", "scenarios")])
def test_no_module_imports_itself_through_others(tops: tuple[str, ...]) -> None:
    assert _cycles(_graph(tops)) == []


def test_pb3a_imports_only_downward() -> None:
    upward = [f"{name} ({_unit(name)}) imports {target} ({_unit(target)})"
              for name, targets in _graph(("pb3a",)).items() for target in sorted(targets)
              if _unit(target) != _unit(name) and _layer(target) >= _layer(name)]
    assert upward == []


def test_pb3a_knows_nothing_of_its_users() -> None:
    users = ("rave", "agents", "scenarios", "examples", "bench", "tests")
    found = [f"{name} imports {target}" for name, path in _modules("pb3a").items()
             for target in _imports(name, path) if target.split(".")[0] in users]
    assert found == []


@pytest.mark.parametrize(("top", "users"), [("rave", ("agents", "scenarios")),
                                             ("agents", ("scenarios",))])
def test_the_libraries_know_nothing_of_their_users(top: str, users: tuple[str, ...]) -> None:
    """RAVE knows nothing of the agents library or the applications, and the library
    nothing of the applications built from it (docs/architecture.md)."""
    found = [f"{name} imports {target}" for name, path in _modules(top).items()
             for target in _imports(name, path) if target.split(".")[0] in users]
    assert found == []


def test_rave_uses_only_what_pb3a_offers_its_users() -> None:
    found = {_unit(target) for name, path in _modules("rave").items()
             for target in _imports(name, path) if target.split(".")[0] == "pb3a"}
    assert found <= RAVE_USES, found - RAVE_USES


def test_embedded_and_remote_nodes_implement_one_node_interface() -> None:
    import inspect

    from pb3a.node.executor import Executor
    from pb3a.node.protocol import Node
    from pb3a.node.remote import RemoteNode

    declared = {name: member for name, member in vars(Node).items()
                if callable(member) and not name.startswith("_")}
    assert len(declared) >= 20
    for cls in (Executor, RemoteNode):
        assert issubclass(cls, Node)
        for name, member in declared.items():
            own = vars(cls).get(name)           # written out in the class, not generated
            assert own is not None, f"{cls.__name__} does not implement Node.{name}"
            wanted = [(p.name, p.kind) for p in inspect.signature(member).parameters.values()]
            got = [(p.name, p.kind) for p in inspect.signature(own).parameters.values()]
            assert got == wanted, f"{cls.__name__}.{name}{got} differs from Node.{name}{wanted}"
