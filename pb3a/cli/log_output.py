"""What every entry point does first: show the library's log on stderr.

PB3A, as a library, installs no handler that prints (logging's convention: the
application decides). A command is the application: ``pb3a run``, ``scenario``,
``node start``, ``modules serve`` and ``rave`` install one, so that a module's
exception appears where the user looks (its name and traceback once, then one line
with how many more).
"""

from __future__ import annotations

import logging
import sys

FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def show_logs(level: int = logging.WARNING) -> None:
    """Print records of ``level`` and above to stderr, unless logging is set up already."""
    root = logging.getLogger()
    if not root.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter(FORMAT, "%H:%M:%S"))
        root.addHandler(handler)
        root.setLevel(level)
