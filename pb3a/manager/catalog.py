"""The module browser's catalog: the module classes a user can place, with their ports.

Classes come from two places: the project's own directories (the document's
directory, the current one and the directories on ``sys.path`` outside the Python
installation),
and module servers (each lists what it serves): those the document names
(``module_servers``) and, when the manager is attached to a running system, those
that system's nodes import from (its topology's ``module_servers``). A Python file
is imported only if its top level merely defines things (imports, classes,
functions, assignments, an ``if __name__ == "__main__"`` block):
a script that does its work when imported (``examples/quickstart.py`` launches a
system) is left out, and said so in ``problems``, as is a file Python cannot parse.
A file not imported yet is imported in a child process first, each with a deadline
(``import_timeout``): one that loops, exits or crashes as it is imported all the same
(in a class body, a module it imports) is left out and said so too, instead of
holding the catalog (and the manager's requests behind it) for good, or ending the
manager and the system it launched (``pb3a.loading.trial``). What one import finds
is kept until ``forget`` (after a reload).
"""

from __future__ import annotations

import ast
import importlib
import inspect
import logging
import sys
import sysconfig
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pb3a.errors import PB3AError
from pb3a.loading import trial
from pb3a.loading.references import class_ref, resolve_class
from pb3a.loading.served import forget as forget_module
from pb3a.loading.served import use_module_servers
from pb3a.model.macro import Macro
from pb3a.model.module import Module
from pb3a.model.state_edits import is_plain
from pb3a.topology import class_kind, displays_of, ports
from pb3a.transport.addresses import tcp_address_problems
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient

if TYPE_CHECKING:
    from pb3a.manager.document import Document
    from pb3a.topology import Topology

log = logging.getLogger("pb3a.manager")

LIST_TIMEOUT = 3.0           # seconds a module server may take to list its modules
IMPORT_TIMEOUT = 10.0        # seconds the import of one module file may take (in a child)
LONGER = "give pb3a manager a longer --import-timeout"    # (to an import that hung)
MOST_FILE_BYTES = 256_000    # larger files are not looked into
MOST_DEPTH = 4               # package levels looked into below a directory
_SKIPPED_DIRS = {"build", "dist", "node_modules", "site-packages", "venv", "tests", "test",
                 "docs", "pb3a"}       # pb3a: its own classes are bases, not parts
_SAFE_STATEMENTS = (ast.Import, ast.ImportFrom, ast.ClassDef, ast.FunctionDef,
                    ast.AsyncFunctionDef, ast.Assign, ast.AnnAssign, ast.AugAssign, ast.Pass,
                    *((ast.TypeAlias,) if hasattr(ast, "TypeAlias") else ()))  # (3.12's `type`)
REPR_CHARS = 200
# calls that act on the world (by their qualified name; or, for methods, by their own
# name, whatever they are called on): an assignment of what one returns, directly or
# through a function of the file, is a script's work
_ACTIONS = frozenset({
    "subprocess.run", "subprocess.call", "subprocess.check_call", "subprocess.check_output",
    "subprocess.Popen", "os.system", "os.remove", "os.unlink", "os.mkdir", "os.makedirs",
    "os.rmdir", "os.rename", "os.replace", "shutil.rmtree", "shutil.copy", "shutil.copyfile",
    "shutil.move", "urllib.request.urlopen", "requests.get", "requests.post",
    "socket.create_connection"})
_ACTING_METHODS = frozenset({"write_text", "write_bytes", "mkdir", "unlink", "rmdir",
                             "touch", "launch", "serve_forever"})


class Catalog:
    """The classes on the project's path and on module servers."""

    def __init__(self, document: Document, roots: list[Path] | None = None, *,
                 import_timeout: float = IMPORT_TIMEOUT) -> None:
        self.document = document
        self._roots = roots                 # None: the project's directories on sys.path
        self.import_timeout = import_timeout
        self._lock = threading.Lock()
        self._found: dict[str, Any] | None = None
        self._servers: tuple[str, ...] = ()   # the servers asked for ``_found``
        self._files: dict[str, tuple[Path, int, int]] = {}   # ... and the files: name ->
                                                            # (path, mtime_ns, size)
        self._classes: dict[str, type] = {}

    def classes(self, servers: Sequence[str] = ()) -> dict[str, Any]:
        """``GET /api/classes``: ``{"classes": [...], "problems": [...]}``; ``servers``:
        module servers to ask besides the document's (a running system's). Looked at
        again when a file on the path was added, changed or removed since (a class
        written while the manager ran was not listed until a module was reloaded);
        a changed module is imported afresh."""
        wanted = self._servers_with(servers)
        with self._lock:
            found = [(root, _candidates(root)) for root in self._directories()]
            files: dict[str, tuple[Path, int, int]] = {}
            for _, candidates in found:               # (the first of a name is imported)
                for name, path in candidates:
                    files.setdefault(name, (path, *_stamp(path)))
            if self._found is None or self._servers != wanted or files != self._files:
                for name, seen in self._files.items():
                    if files.get(name) != seen and name in sys.modules:
                        forget_module(name)
                self._classes.clear()
                self._found = self._scan(wanted, found)
                self._servers, self._files = wanted, files
            return self._found

    def forget(self, module: str | None = None) -> None:
        """Look again at the next ``classes`` (after ``module`` was reloaded). The
        manager's own imported copy of ``module`` goes too: attached to a system that runs
        in another process, its reload dropped the copies there, not this one, and the
        catalog would show the old classes."""
        with self._lock:
            if module is not None:
                forget_module(module)
                trial.forget(module)
            self._found = None
            self._classes.clear()

    def fitting(self, topology: Topology, name: str) -> list[str]:
        """The catalog's classes (the topology's module servers asked too) that could
        replace module ``name``'s: every port it has, of a type each link on it accepts
        (as ``swap`` checks)."""
        self.classes(topology.module_servers)
        module = topology.modules[name]
        links = [link for link in topology.links.values()
                 if link.src.rpartition(".")[0] == name or link.dst.rpartition(".")[0] == name]
        peers: dict[str, type] = {}
        for link in links:
            for end in (link.src, link.dst):
                other = end.rpartition(".")[0]
                if other != name and other not in peers:
                    try:
                        peers[other] = resolve_class(topology.modules[other].cls)
                    except (ImportError, LookupError, TypeError, ValueError):
                        return []              # a peer the manager cannot load: cannot tell
        fits = []
        for ref, cls in sorted(self._classes.items()):
            if ref == module.cls or not set(module.inputs) <= set(cls.inputs) \
                    or not set(module.outputs) <= set(cls.outputs):
                continue
            if all(_link_fits(link.src, link.dst, name, cls, peers) for link in links):
                fits.append(ref)
        return fits

    # -- looking ------------------------------------------------------------------
    def _servers_with(self, servers: Sequence[str]) -> tuple[str, ...]:
        """The document's module servers, then ``servers``, each once."""
        named = self.document.data().get("module_servers", [])
        named = [s for s in named if isinstance(s, str)] if isinstance(named, list) else []
        return tuple(dict.fromkeys([*named, *servers]))

    def _scan(self, servers: tuple[str, ...],
              found: list[tuple[Path, list[tuple[str, Path]]]]) -> dict[str, Any]:
        """The catalog of the candidate files ``found`` under each root and of the
        module servers ``servers``."""
        problems: list[str] = []
        modules: dict[str, str] = {}            # dotted name -> origin
        for root, candidates in found:
            names = _module_names(candidates, problems)
            if names and str(root) not in sys.path:
                # imported by the names found there, as `pb3a run` imports a file's
                # classes: the document's directory goes on the import path
                sys.path.append(str(root))
            for name in names:
                modules.setdefault(name, "path")
        if servers:
            modules.update({name: origin for name, origin in self._served(servers, problems)
                            .items() if name not in modules})
        entries = []
        harmful = trial.import_problems(sorted(modules), self.import_timeout, longer=LONGER)
        for name, origin in sorted(modules.items()):
            if name in harmful:
                problems.append(f"{name}: not imported: importing it {harmful[name]}")
                continue
            try:
                module = importlib.import_module(name)
            except Exception as exc:               # whatever a user's module raises
                problems.append(f"{name}: not imported: {type(exc).__name__}: {exc}")
                continue
            for _, cls in inspect.getmembers(module, inspect.isclass):
                if (issubclass(cls, Module) and not issubclass(cls, Macro)
                        and cls.__module__ == name and not cls.__name__.startswith("_")):
                    ref = class_ref(cls)
                    self._classes[ref] = cls
                    entries.append(describe_class(cls, origin))
        return {"classes": entries, "problems": problems}

    def _directories(self) -> list[Path]:
        if self._roots is not None:
            roots = list(self._roots)
        else:
            installed = {Path(p).resolve() for p in (sys.prefix, sys.base_prefix,
                                                     sysconfig.get_paths()["stdlib"])}
            roots = [Path(entry or ".").resolve() for entry in sys.path]
            roots = [root for root in roots if root.is_dir()
                     and not any(root.is_relative_to(base) for base in installed)]
            roots.insert(0, Path.cwd())      # (a console script's path does not have it)
        if self.document.path is not None:
            roots.insert(0, self.document.path.resolve().parent)
        return list(dict.fromkeys(roots))

    def _served(self, servers: tuple[str, ...], problems: list[str]) -> dict[str, str]:
        """The modules each server lists (whose source only defines things), importable
        through the served finder from now on."""
        found: dict[str, str] = {}
        key = ClusterKey.load()
        for address in servers:
            # (ZeroMQ's "Invalid argument" for one without tcp://, as pb3a manager takes a
            # launcher's: every class request was a 500, the browser empty)
            wrong = tcp_address_problems(address, "a module server's address")
            if wrong:
                problems.extend(wrong)
                continue
            client = ControlClient(key, address)
            try:
                for name in client.call("list", LIST_TIMEOUT):
                    served = client.call("find", LIST_TIMEOUT, name=name)
                    if served and _defines_classes(served["source"], f"{address} {name}",
                                                   problems):
                        found.setdefault(name, address)
            except PB3AError as exc:
                problems.append(f"module server {address}: {exc}")
            finally:
                client.close()
        if found:
            use_module_servers(servers, key)
        return found


def describe_class(cls: type[Module], origin: str) -> dict[str, Any]:
    """One catalog entry: the class, its kind, doc, ports, state with defaults, origin."""
    doc = inspect.getdoc(cls) or ""
    state = {}
    for name in cls.state_names():
        value = getattr(cls, name, None)
        default = value if is_plain(value) else _short_repr(value)
        state[name] = {"type": type(value).__name__, "default": default}
    return {"class": class_ref(cls), "kind": class_kind(cls),
            "doc": doc.split("\n\n")[0].replace("\n", " "),
            "inputs": {n: p.to_json() for n, p in ports(cls.inputs).items()},
            "outputs": {n: p.to_json() for n, p in ports(cls.outputs).items()},
            "state": state, "period": cls.period, "fixed_rate": cls.fixed_rate is True,
            "displays": {n: d.to_json() for n, d in displays_of(cls).items()},
            "origin": origin}


def _module_names(candidates: list[tuple[str, Path]], problems: list[str]) -> list[str]:
    """The dotted names of the ``candidates`` (``_candidates``' files under a root) that
    define module classes and nothing else at their top level."""
    names = []
    for name, path in candidates:
        try:
            if path.stat().st_size > MOST_FILE_BYTES:
                continue
            source = path.read_bytes()
        except OSError:
            continue
        if _defines_classes(source, str(path), problems):
            names.append(name)
    return names


def _stamp(path: Path) -> tuple[int, int]:
    """(mtime in ns, size) of ``path``; (0, 0) for one gone meanwhile."""
    try:
        found = path.stat()
    except OSError:
        return 0, 0
    return found.st_mtime_ns, found.st_size


def _candidates(root: Path) -> list[tuple[str, Path]]:
    """The Python files under ``root`` the catalog looks into, with their dotted names:
    public modules at its top and in its packages (not tests, at most ``MOST_DEPTH``
    down)."""
    found = []

    def walk(directory: Path, prefix: str, depth: int) -> None:
        try:
            entries = sorted(directory.iterdir())
        except OSError:
            return
        for path in entries:
            stem = path.stem if path.suffix == ".py" else path.name
            if not stem.isidentifier() or stem.startswith(("_", "test")) or stem == "conftest":
                continue
            if path.is_dir() and not path.is_symlink() and depth < MOST_DEPTH \
                    and stem not in _SKIPPED_DIRS and (path / "__init__.py").is_file():
                walk(path, f"{prefix}{stem}.", depth + 1)
            elif path.suffix == ".py" and path.is_file() and (prefix or depth == 0):
                found.append((prefix + stem, path))

    walk(root, "", 0)
    return found


def _defines_classes(source: bytes, where: str, problems: list[str]) -> bool:
    """Whether ``source`` has a class with a base and, at its top level, only statements
    that define things (so importing it runs nothing else). Source Python cannot read
    is said in ``problems`` (it was left out without a word)."""
    try:
        tree = ast.parse(source)
    except SyntaxError as exc:
        problems.append(f"{where}: not imported: line {exc.lineno}: {exc.msg}")
        return False
    except ValueError as exc:                   # (a null byte)
        problems.append(f"{where}: not imported: {exc}")
        return False
    has_class = any(isinstance(node, ast.ClassDef) and node.bases for node in tree.body)
    if not has_class:
        return False
    own: dict[str, ast.AST] = {node.name: node for node in tree.body
                               if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))}
    imported = _imported(tree)
    for node in tree.body:
        if (isinstance(node, _SAFE_STATEMENTS) and not _does_work(node, own, imported)) \
                or _docstring(node) or _guarded(node) or _optional_import(node):
            continue
        problems.append(f"{where}: not imported: line {node.lineno} runs code at import "
                        "(move it under if __name__ == \"__main__\":)")
        return False
    return True


def _does_work(node: ast.stmt, own: dict[str, ast.AST], imported: dict[str, str]) -> bool:
    """Whether an assignment's value is a call that does a script's work: one that acts
    on the world (``_ACTIONS``: writes a file, starts a process or a system), directly
    or through the file's own functions (``results = run_experiment()``). A value built
    by a library or a helper of the file (``np.array(...)``, ``_gaussian(5)``,
    ``Path(__file__).with_name(...)``, ``platform.system()``) defines a constant."""
    value = getattr(node, "value", None)
    return isinstance(node, (ast.Assign, ast.AnnAssign, ast.AugAssign)) \
        and isinstance(value, ast.Call) and _acts(value, own, imported, set())


def _acts(call: ast.Call, own: dict[str, ast.AST], imported: dict[str, str],
          seen: set[str]) -> bool:
    func = call.func
    if isinstance(func, ast.Attribute) and func.attr in _ACTING_METHODS:
        return True
    name = _dotted(func, imported)
    if name in _ACTIONS:
        return True
    if isinstance(func, ast.Name) and func.id in own and func.id not in seen:
        seen.add(func.id)
        return any(_acts(inner, own, imported, seen) for inner in ast.walk(own[func.id])
                   if isinstance(inner, ast.Call))
    return False


def _dotted(func: ast.expr, imported: dict[str, str]) -> str:
    """``subprocess.run`` for ``sp.run`` (``import subprocess as sp``) or ``run`` (``from
    subprocess import run``); "" for what is not a plain name or attribute chain."""
    if isinstance(func, ast.Name):
        return imported.get(func.id, func.id)
    if isinstance(func, ast.Attribute):
        head = _dotted(func.value, imported)
        return f"{head}.{func.attr}" if head else ""
    return ""


def _imported(tree: ast.Module) -> dict[str, str]:
    """Each name the file's imports bind, to what it names (``sp`` -> ``subprocess``)."""
    names = {}
    for node in tree.body:
        if isinstance(node, ast.Import):
            for alias in node.names:
                names[alias.asname or alias.name.partition(".")[0]] = \
                    alias.name if alias.asname else alias.name.partition(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module:
            for alias in node.names:
                names[alias.asname or alias.name] = f"{node.module}.{alias.name}"
    return names


def _docstring(node: ast.stmt) -> bool:
    return isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)


def _guarded(node: ast.stmt) -> bool:
    """``if __name__ == "__main__":`` or ``if TYPE_CHECKING:``."""
    if not isinstance(node, ast.If):
        return False
    test = ast.unparse(node.test)
    return test in ("TYPE_CHECKING", "typing.TYPE_CHECKING") or "__name__" in test


def _optional_import(node: ast.stmt) -> bool:
    """``try: import x`` ``except ImportError: ...`` (imports and assignments only)."""
    if not isinstance(node, ast.Try):
        return False
    body = [*node.body, *(s for h in node.handlers for s in h.body)]
    return all(isinstance(s, (ast.Import, ast.ImportFrom, ast.Assign, ast.Pass)) for s in body)


def _link_fits(src: str, dst: str, name: str, cls: type[Module],
               peers: dict[str, type]) -> bool:
    source, _, out_port = src.rpartition(".")
    target, _, in_port = dst.rpartition(".")
    writer = cls if source == name else peers[source]
    reader = cls if target == name else peers[target]
    return reader.inputs[in_port].accepts(writer.outputs[out_port]) is None


def _short_repr(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= REPR_CHARS else text[:REPR_CHARS - 3] + "..."
