"""The ``pb3a`` command line: one entry point, one subcommand per task.

    pb3a check FILE               validate; print every problem; exit 1 on any
    pb3a graph FILE [-o OUT]      draw the configuration (DOT, and SVG/PNG/PDF via Graphviz)
    pb3a run FILE [--for SECONDS] launch, show live status, stop on Ctrl-C or after SECONDS
    pb3a status|state|set|migrate|swap|reload|relink|add|remove|restart|nodes|events|logs ADDR ...
                                  act on a running system through its launcher
    pb3a stress FILE [--load CPUS:PCT] [--kill-worker-every N] [--cut-node NAME@T+D] ...
                                  run under CPU load and faults; report per link and node
    pb3a scenario NAME [ARGS...]  run an application (a ``pb3a.scenarios`` entry point)
    pb3a modules serve DIR [--listen ADDR]   serve module code to the nodes (until signalled)
    pb3a node start --name N [--listen ADDR] run a node controller (until signalled)
    pb3a key new PATH             write a new cluster key file (mode 0600)
    pb3a manager [FILE | ADDR]    the ModuleManager web app (needs the 'ui' extra)

``pb3a.cli.commands`` declares every subcommand's arguments and names the function
that runs it (``"module:function"``: it takes the parsed arguments and returns the
exit code); ``main`` imports that function only once the arguments have parsed, so
``--help`` and a mistaken argument are answered without importing the runtime. The
command's module is imported inside ``main``, so that a Ctrl-C at any moment ends the
command with exit status 130 and one line, not a traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import sys
from collections.abc import Callable, Sequence

from pb3a.cli.standard_output import BROKEN_PIPE, output_gone
from pb3a.processes import (
    INTERRUPTED,
    children_skip_the_current_directory,
    end_on_signals,
    runs_a_command,
)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with ``argv`` (default: ``sys.argv[1:]``, the command run as
    a program, which imports from the current directory); returns the exit code."""
    if argv is None:
        import_from_here()
    try:
        from pb3a.cli.commands import parser as command_line
        from pb3a.cli.log_output import show_logs

        parser = command_line()
        args = parser.parse_args(argv)
        # (the pb3a program: its process ends once the command returns)
        args.whole_process = argv is None
        # the process its log lines name: a command that launches is the launcher
        show_logs(role=getattr(args, "log_role", "launcher"))
        handler: str | None = getattr(args, "handler", None)
        if handler is None:
            parser.print_help()
            return 2
        return handler_of(handler)(args)
    except KeyboardInterrupt:
        if argv is None:   # (the pb3a program: its status is decided as it exits)
            end_on_signals(INTERRUPTED)
        print("pb3a: interrupted", file=sys.stderr)
        return INTERRUPTED
    except BrokenPipeError:            # its reader went: quietly, as a Unix tool
        output_gone()
        return BROKEN_PIPE


def import_from_here() -> None:
    """Put the current directory on the import path, after the standard library and the
    installed packages, for the ``pb3a`` script and ``python -m pb3a`` alike: the script
    had its own directory there instead (a class beside the user imported with one
    command and not the other), and put first, a ``logging.py`` or ``random.py`` of the
    user's broke every command. The processes the command starts (the check's import
    child, the nodes' workers) take the path from it, and start without the directory
    first (``-P``: the workers' forkserver starts with ``python -c``)."""
    with contextlib.suppress(OSError):          # (a directory removed under the shell)
        here = os.getcwd()
        sys.path[:] = [*(entry for entry in sys.path if entry not in ("", here)), here]
    children_skip_the_current_directory()
    runs_a_command()            # (its own directory is no script's of the user's)


def handler_of(name: str) -> Callable[[argparse.Namespace], int]:
    """The function ``name`` (``"module:function"``) names, its module imported now."""
    module, _, function = name.partition(":")
    return getattr(importlib.import_module(module), function)
