"""The ``pb3a`` command line: one entry point, one subcommand per task.

    pb3a check FILE               validate; print every problem; exit 1 on any
    pb3a graph FILE [-o OUT]      draw the configuration (DOT, and SVG/PNG/PDF via Graphviz)
    pb3a run FILE [--for SECONDS] launch, show live status, stop on Ctrl-C or after SECONDS
    pb3a status|state|set|migrate|swap|relink|add|remove|restart|nodes|events|logs ADDR ...
                                  act on a running system through its launcher
    pb3a stress FILE [--load CPUS:PCT] [--kill-worker-every N] [--cut-node NAME@T+D] ...
                                  run under CPU load and faults; report per link and node
    pb3a scenario NAME [ARGS...]  run an application (a ``pb3a.scenarios`` entry point)
    pb3a modules serve DIR [--listen ADDR]   serve module code to the nodes (until signalled)
    pb3a node start --name N [--listen ADDR] run a node controller (until signalled)
    pb3a key new PATH             write a new cluster key file (mode 0600)
    pb3a manager [FILE | ADDR]    the ModuleManager web app (needs the 'ui' extra)

Each module of this package registers its subcommands; each subcommand is a function
taking the parsed arguments and returning the exit code. The command modules are
imported inside ``main``, so that a Ctrl-C at any moment ends the command with exit
status 130 and one line, not a traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from pb3a.cli.standard_output import BROKEN_PIPE, output_gone

INTERRUPTED = 130      # the shell's convention for a command ended by SIGINT


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with ``argv`` (default: ``sys.argv[1:]``); returns the exit code."""
    try:
        from pb3a.cli.log_output import show_logs

        parser = _parser()
        args = parser.parse_args(argv)
        show_logs()
        handler: Callable[[argparse.Namespace], int] | None = getattr(args, "handler", None)
        if handler is None:
            parser.print_help()
            return 2
        return handler(args)
    except KeyboardInterrupt:
        print("pb3a: interrupted", file=sys.stderr)
        return INTERRUPTED
    except BrokenPipeError:            # its reader went: quietly, as a Unix tool
        output_gone()
        return BROKEN_PIPE


def _parser() -> argparse.ArgumentParser:
    from pb3a.cli import daemons, files, keys, manager, running_system, scenarios, stress

    parser = argparse.ArgumentParser(
        prog="pb3a", description="Port-based modules that run, swap and move while they run.")
    commands = parser.add_subparsers(title="commands", metavar="COMMAND")
    for group in (files, running_system, stress, scenarios, daemons, keys, manager):
        group.register(commands)
    return parser
