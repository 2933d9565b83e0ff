"""The module server: code on demand (``pb3a modules serve DIR --listen ADDR``).

Nodes import a module class from their own import path first, then from the module
servers the configuration names (``module_servers``). The server answers ``find``
requests for dotted module names with the source of ``DIR/a/b.py`` or
``DIR/a/b/__init__.py``, read at each request, so new and overwritten files are
served without a restart; ``list`` gives every dotted name it can serve (for module
browsers such as the ModuleManager's). Requests are authenticated (``ControlServer``); names
are identifiers only, and a file whose real path (symbolic links resolved) leaves DIR
is never served.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlServer, UnknownOperation

log = logging.getLogger("pb3a.modules")


class ModuleServer:
    """Serves the Python modules under ``root``."""

    def __init__(self, root: str | Path, key: ClusterKey, host: str = "127.0.0.1",
                 port: int = 0) -> None:
        try:
            self.root = Path(root).resolve()
        except (OSError, RuntimeError) as exc:      # (a symlink loop: its traceback)
            raise ValueError(f"no directory {root} to serve modules from ({exc}); give the "
                             "directory that holds the modules' packages") from None
        if not self.root.is_dir():      # (resolve(strict=True) said only "[Errno 2] ...")
            raise ValueError(f"no directory {root} to serve modules from"
                             + (": it is a file" if self.root.exists() else "")
                             + "; give the directory that holds the modules' packages")
        self._server = ControlServer(key, self._handle, host, port, name="pb3a-modules",
                                     title="a module server")
        self.address = self._server.address

    def find(self, name: str) -> dict[str, Any] | None:
        """The source of module ``name`` and whether it is a package; None if not here."""
        parts = name.split(".")
        if not name or not all(part.isidentifier() for part in parts):
            return None
        base = self.root.joinpath(*parts)
        for path, package in ((base / "__init__.py", True), (base.with_suffix(".py"), False)):
            try:
                real = path.resolve(strict=True)
            except (FileNotFoundError, RuntimeError):
                continue
            if not real.is_relative_to(self.root) or not real.is_file():
                log.warning("refused %s: %s is outside %s", name, real, self.root)
                return None
            return {"source": real.read_bytes(), "package": package,
                    "origin": f"{self.address}/{real.relative_to(self.root)}"}
        return None

    def names(self) -> list[str]:
        """Every dotted module name ``find`` serves, sorted: the ``.py`` files under the
        root whose path is made of identifiers, packages by their ``__init__.py``
        (symbolic links leading out of the root are left out, as ``find`` refuses them)."""
        names = set()
        for path in self.root.rglob("*.py"):
            parts = path.relative_to(self.root).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            if not parts or not all(part.isidentifier() for part in parts):
                continue
            try:
                real = path.resolve(strict=True)
            except (FileNotFoundError, RuntimeError):
                continue
            if real.is_relative_to(self.root) and real.is_file():
                names.add(".".join(parts))
        return sorted(names)

    def _handle(self, op: str, args: dict[str, Any]) -> Any:
        if op == "find":
            return self.find(str(args.get("name", "")))
        if op == "list":
            return self.names()
        raise UnknownOperation(op, ("find", "list"))

    @property
    def rejected(self) -> Any:
        return self._server.rejected

    def close(self, why: str = "closed") -> None:
        """Stop serving; ``why``: what stops it (a signal's name), logged."""
        log.info("module server at %s: stopping (%s)", self.address, why)
        self._server.close()
