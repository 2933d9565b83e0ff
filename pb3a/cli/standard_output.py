"""When the reader of the command line's output has gone (``pb3a status --json | head``,
a script that closed its end): its output goes nowhere from then on, as to a closed
terminal, instead of a ``BrokenPipeError`` traceback at the next write or at exit."""

from __future__ import annotations

import os
import sys

BROKEN_PIPE = 141            # the status of a Unix tool that SIGPIPE ended (128 + 13)


def output_gone() -> None:
    """Send standard output to ``/dev/null`` (Python's flush at exit too)."""
    nowhere = os.open(os.devnull, os.O_WRONLY)
    os.dup2(nowhere, sys.stdout.fileno())
    os.close(nowhere)
