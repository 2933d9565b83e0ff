"""Importing modules from module servers: a finder at the end of ``sys.meta_path``.

Once ``use_module_servers`` has run in a process (the launcher when it plans a
configuration that names ``module_servers``, every worker at start), an import that
the local path cannot satisfy asks each server in turn. ``forget`` drops cached
modules so that the next import (or a ``swap`` naming the class) gets the new code.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import sysconfig
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pb3a.errors import RuntimeFailure, RuntimeTimeout
from pb3a.transport.addresses import RESOLVE_S, unknown_host
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient, add_import_hint

if TYPE_CHECKING:
    from collections.abc import Sequence
    from importlib.machinery import ModuleSpec
    from types import ModuleType

FIND_TIMEOUT = 5.0
SILENT_FOR_S = 30.0         # a server that did not answer is not asked again for this long
_lock = threading.Lock()


class ServedModuleFinder(importlib.abc.MetaPathFinder):
    """Finds modules on module servers (after every local finder failed)."""

    def __init__(self, key: ClusterKey) -> None:
        self._key = key
        self.clients: dict[str, ControlClient] = {}
        self._silent_until: dict[str, float] = {}    # address -> when to ask it again
        self._refused: dict[str, str] = {}            # address -> why it refused, lately
        self._lacking: dict[str, list[str]] = {}      # module -> servers that have it not

    def add(self, address: str) -> None:
        if address not in self.clients:
            self.clients[address] = ControlClient(self._key, address)

    def refused(self) -> dict[str, str]:
        """The servers that refused their last request, and why (another cluster key,
        clocks apart ...): an import that fails may have needed one of them."""
        return dict(self._refused)

    def lacking(self, module: str) -> list[str]:
        """The servers that answered, when last asked, that they have no ``module``."""
        return list(self._lacking.get(module, []))

    def silent(self) -> list[str]:
        """The servers not asked now, since they did not answer lately."""
        now = time.monotonic()
        return [address for address, until in self._silent_until.items() if now < until]

    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> ModuleSpec | None:
        lacking = self._lacking[fullname] = []
        for address, client in list(self.clients.items()):
            if time.monotonic() < self._silent_until.get(address, 0.0):
                continue              # it did not answer lately: no import waits for it
            try:
                # (a server whose port refuses connections is said silent in about
                # 1.5 s: an add or swap waited its whole 5 s, and the check before it 5 more)
                found = client.call_if_listened("find", FIND_TIMEOUT, name=fullname)
            except RuntimeTimeout:
                self._silent_until[address] = time.monotonic() + SILENT_FOR_S
                continue
            except RuntimeFailure as exc:         # it refused: say why, try the next
                self._refused[address] = str(exc)
                continue
            self._refused.pop(address, None)
            if found is None:
                lacking.append(address)
            else:
                self._lacking.pop(fullname, None)
                loader = _SourceLoader(found["source"], found["origin"])
                return importlib.util.spec_from_loader(
                    fullname, loader, origin=found["origin"], is_package=found["package"])
        return None


class _SourceLoader(importlib.abc.Loader):
    def __init__(self, source: bytes, origin: str) -> None:
        self._source, self._origin = source, origin

    def create_module(self, spec: ModuleSpec) -> ModuleType | None:
        return None                                # the default module object

    def exec_module(self, module: ModuleType) -> None:
        module.__file__ = self._origin
        if module.__spec__ is not None and module.__spec__.submodule_search_locations is not None:
            module.__path__ = []                   # a package: submodules come from servers
        exec(compile(self._source, self._origin, "exec"), module.__dict__)


def server_trouble() -> str:
    """What a failed import's error adds about this process's module servers, one of
    which it may have needed: "; module server ADDRESS did not answer: ..." for those
    that did not answer lately, and the reason each that refused its last request gave
    (another cluster key, clocks apart); "" when all answered."""
    finders = [finder for finder in sys.meta_path if isinstance(finder, ServedModuleFinder)]
    silent = [address for finder in finders for address in finder.silent()]
    # (a name only some machines resolve: the workstation's /etc/hosts has it, a robot's not)
    unknown = {address: why for address in silent
               if (why := unknown_host(address, RESOLVE_S)) is not None}
    silent = [address for address in silent if address not in unknown]
    said = (f"; module server {', '.join(silent)} did not answer: start it, or check its "
            "address and that its port is open" if silent else "")
    said += "".join(f"; module server {address} is not reached from this machine: {why} "
                    "(give module_servers a name every node's machine resolves, or an IP "
                    "address)" for address, why in unknown.items())
    return said + "".join(f"; module server {why}" for finder in finders
                          for why in finder.refused().values())


def _not_given(module: str) -> str:
    """Why the module servers did not give ``module`` (see ``add_import_hint``)."""
    return not_served(module) + server_trouble()


def not_served(module: str) -> str:
    """What a failed import of ``module`` adds about the module servers that answered
    without it: "; module server ADDRESS has no module 'a.b' either: put ..." ("" if
    none did). The error said only to check this machine's path, where a module meant
    to be served was never to be."""
    finders = [finder for finder in sys.meta_path if isinstance(finder, ServedModuleFinder)]
    lacking = [address for finder in finders for address in finder.lacking(module)]
    if not lacking:
        return ""
    path = module.replace(".", "/")
    return (f"; module server{'s' if len(lacking) > 1 else ''} {', '.join(lacking)} "
            f"{'have' if len(lacking) > 1 else 'has'} no module {module!r} either: put "
            f"{path}.py (or {path}/__init__.py) in the directory it serves")


def use_module_servers(addresses: Sequence[str], key: ClusterKey | None = None) -> None:
    """Let this process import from these servers (idempotent)."""
    if not addresses:
        return
    with _lock:
        finder = next((f for f in sys.meta_path if isinstance(f, ServedModuleFinder)), None)
        if finder is None:
            finder = ServedModuleFinder(key or ClusterKey.load())
            sys.meta_path.append(finder)
            add_import_hint(_not_given)
        for address in addresses:
            finder.add(address)


def module_servers() -> list[str]:
    """The module servers this process imports from (``use_module_servers``), in order."""
    return [address for finder in sys.meta_path if isinstance(finder, ServedModuleFinder)
            for address in finder.clients]


def reload_problem(module: str) -> str | None:
    """Why ``module`` may not be reloaded everywhere (dropped from every process's
    cache), or None. Only a system's own code may be: Python's standard library, an
    installed package (numpy, once dropped, cannot be imported again in that
    process) and PB3A itself are what the launcher and its workers run on."""
    top = module.partition(".")[0]
    if top in sys.builtin_module_names or top in sys.stdlib_module_names:
        return f"{module} is part of Python's standard library"
    if top == "pb3a":
        return f"{module} is part of PB3A itself"
    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError):
        spec = None
    origin = spec.origin if spec is not None else None
    installed = {Path(sysconfig.get_paths()[key]).resolve() for key in ("purelib", "platlib")}
    if origin and any(Path(origin).resolve().is_relative_to(p) for p in installed):
        return (f"{module} is an installed package ({origin}): reload reloads your "
                "system's code (install it editable, pip install -e, to change it live)")
    return None


def forget(module: str) -> list[str]:
    """Drop ``module`` and its submodules from this process's cache; the names dropped."""
    dropped = [name for name in list(sys.modules)
               if name == module or name.startswith(f"{module}.")]
    for name in dropped:
        del sys.modules[name]
    importlib.invalidate_caches()
    return dropped
