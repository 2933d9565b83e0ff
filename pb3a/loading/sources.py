"""``CodeSources``: where a system's module classes come from, beside installed packages.

A configuration file's own directory comes first on the import path, so a module
written next to the file imports without ``PYTHONPATH`` (as a script's directory
does for the script); module servers are asked last, after every local finder. The
launcher installs the sources before it resolves the configuration's classes, and
every worker and node share process it starts installs them too.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING

from pb3a.loading.served import use_module_servers

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
        for path in reversed(self.paths):
            if path not in sys.path:
                sys.path.insert(0, path)
        use_module_servers(self.module_servers, key)
