"""``CodeSources``: where a system's module classes come from, beside installed packages.

A configuration file's own directory comes first on the import path, so a module
written next to the file imports without ``PYTHONPATH`` (as a script's directory
does for the script), then the launcher's ``PYTHONPATH`` (``file_paths``); a system
built in Python has its launching script's directory and ``PYTHONPATH`` there instead
(``launcher_paths``): those its launcher imported its classes from. Module servers
are asked last, after every local finder. The launcher installs the sources before
it resolves the configuration's classes, and every worker and node share process it
starts installs them too, before it imports any of them (``import_path``: one order
for all).
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING

from pb3a.loading.served import use_module_servers
from pb3a.processes import runs_a_script

if TYPE_CHECKING:
    from pb3a.transport.auth import ClusterKey


@dataclass(frozen=True)
class CodeSources:
    """Directories put first on the import path, and module servers asked last; and the
    Python modules the configuration's classes live in (``preload``), which a node
    imports once, in the process its workers are forked from, so that a worker started
    later (a migration's destination, a restart, a spawn) does not import them in the
    critical path."""

    paths: tuple[str, ...] = ()
    module_servers: tuple[str, ...] = ()
    preload: tuple[str, ...] = ()

    def install(self, key: ClusterKey | None = None) -> None:
        """Make this process import from these sources (idempotent)."""
        sys.path[:] = import_path(self.paths, sys.path)
        use_module_servers(self.module_servers, key)


def import_path(paths: tuple[str, ...], current: list[str]) -> list[str]:
    """The import path of a process that imports a system's classes: ``paths`` (the
    configuration's directory, or a script's) first, then the process's ``current``
    path without them. Moved, not only added: a node controller started in that
    directory had it last, behind the installed packages. The node's executor, its
    check of a launch's classes and its workers all take their path from this."""
    return [*paths, *(entry for entry in current if entry not in paths)]


def launcher_paths() -> tuple[str, ...]:
    """The directories a system built in Python in this process is imported from, as
    Python has them, to be handed to its nodes: the first on its path (``sys.path[0]``:
    the script's directory, the current one for ``python -m``, ``-c``, a notebook or
    the REPL, whose ``''`` means it; or one the script put first), then the script's own
    directory (``__main__``'s file: a script that put a directory first still imports
    the files beside it), unless Python was told to leave it off (``-P``,
    ``PYTHONSAFEPATH``); then the directories of ``PYTHONPATH`` (unless ignored, ``-E``);
    those that exist, each once, absolute, in that order."""
    found: list[str] = []
    if runs_a_script() and not sys.flags.safe_path and sys.path:
        found.append(sys.path[0])
        main = sys.modules.get("__main__")
        script = getattr(main, "__file__", None)
        if isinstance(script, str) and getattr(main, "__spec__", None) is None:
            found.append(os.path.dirname(os.path.abspath(script)))      # (not python -m)
    return _existing([*found, *_python_path()])


def file_paths(directory: str) -> tuple[str, ...]:
    """The directories a system described in a configuration file is imported from, to
    be handed to its nodes: the file's ``directory``, then those of this process's
    ``PYTHONPATH`` (unless ignored, ``-E``), as ``launcher_paths`` hands a script's; those
    that exist, each once, absolute. A class ``pb3a run`` imported from its
    ``PYTHONPATH`` was looked for on a node started without it in the file's directory
    alone, and not found there."""
    return _existing([directory, *_python_path()])


def _python_path() -> list[str]:
    """The entries of ``PYTHONPATH`` as this process's Python took them (none with
    ``-E``), empty ones left out."""
    if sys.flags.ignore_environment:
        return []
    return [entry for entry in os.environ.get("PYTHONPATH", "").split(os.pathsep) if entry]


def _existing(found: list[str]) -> tuple[str, ...]:
    """The directories of ``found`` that exist, each once, absolute (``''``: the current
    one), in that order."""
    paths: list[str] = []
    for entry in found:
        try:
            path = os.path.abspath(entry or os.getcwd())
        except OSError:                     # (the current directory removed under it)
            continue
        if os.path.isdir(path) and path not in paths:
            paths.append(path)
    return tuple(paths)
