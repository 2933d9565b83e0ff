"""What every entry point does first: show the library's log on stderr.

PB3A, as a library, installs no handler that prints (logging's convention: the
application decides). A command is the application: ``pb3a run``, ``scenario``,
``node start``, ``modules serve``, ``manager`` and ``rave`` install one, so that a
module's exception appears where the user looks (its name and traceback once, then
one line with how many more), in the format every PB3A process writes
(``pb3a.log_format``).
"""

from __future__ import annotations

import logging
import sys

from pb3a.log_format import log_to, name_process


def show_logs(level: int = logging.WARNING, role: str = "launcher") -> None:
    """Print records of ``level`` and above on stderr, unless logging is set up already;
    the lines name this process ``role``."""
    name_process(role)
    log_to(sys.stderr, level)
