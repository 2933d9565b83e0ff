"""Commands on a configuration file: ``pb3a check``, ``pb3a graph``, ``pb3a run``.

``check`` and ``graph`` import none of the runtime nor the file's classes here: a
child process plans the file (``pb3a.config.isolated``). ``run`` (and ``stress``) have a
child check it the same way first, so that a module file that hangs, ends or crashes its
importer is named within ``--import-timeout`` instead of hanging or killing the command;
then they plan the file in this process, which launches it.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from pb3a.config.isolated import check_file
from pb3a.errors import ConfigError, PB3AError

if TYPE_CHECKING:
    from pb3a.config.plan import Plan

T = TypeVar("T")


def check_command(args: argparse.Namespace) -> int:
    """``pb3a check FILE``: every problem on its own line (exit 1), or the notes on what
    the file likely leaves undone (``Plan.notes``), each on its own line, then a one-line
    summary (exit 0: a note is no problem)."""
    checked = _reported(args.file, "check", lambda: check_file(
        args.file, import_timeout=args.import_timeout))
    if checked is None:
        return 1
    for note in checked.notes:
        print(note)
    modules, links = checked.modules, checked.links
    print(f"ok: {modules} module{'s' * (modules != 1)}, {links} link{'s' * (links != 1)}")
    return 0


def graph_command(args: argparse.Namespace) -> int:
    """``pb3a graph FILE [-o OUT]``: write DOT, then render OUT with Graphviz unless it is .dot."""
    checked = _reported(args.file, "graph", lambda: check_file(
        args.file, import_timeout=args.import_timeout, dot=True))
    if checked is None:
        return 1
    text = checked.dot or ""
    if args.output == "-":
        sys.stdout.write(text)
        return 0
    out = Path(args.output) if args.output is not None else Path(Path(args.file).stem + ".svg")
    fmt = out.suffix.lstrip(".").lower()
    if out.is_dir() or not fmt:
        # (a directory got NAME.dot beside it, then dot's own error; a NAME without a
        # suffix got SVG in a file of that name)
        print(f"pb3a graph: -o {args.output!r}: give a file, its suffix the format (.svg, "
              ".png, .pdf; .dot for DOT only; - for DOT on stdout)", file=sys.stderr)
        return 1
    dot_path = out if fmt == "dot" else out.with_suffix(".dot")
    dot = shutil.which("dot")
    if fmt != "dot" and dot is not None:        # drawn first: a format dot has not (.v2)
        done = subprocess.run([dot, f"-T{fmt}", "-o", str(out)], input=text,   # writes
                              capture_output=True, text=True, timeout=120, check=False)
        if done.returncode != 0:                                # nothing, DOT neither
            print(f"pb3a graph: dot could not write {out}: {done.stderr.strip()}",
                  file=sys.stderr)
            return 1
    try:
        dot_path.write_text(text)
    except OSError as exc:
        print(f"pb3a graph: cannot write {dot_path}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    if fmt == "dot":
        print(f"wrote {dot_path}")
        return 0
    if dot is None:
        print(f"pb3a graph: wrote {dot_path}, but Graphviz's 'dot' program is not on PATH, so "
              f"no {out.name}: install Graphviz (e.g. apt-get install graphviz), or ask for DOT "
              "only with -o FILE.dot", file=sys.stderr)
        return 1
    print(f"wrote {dot_path} and {out}")
    return 0


def run_command(args: argparse.Namespace) -> int:
    """``pb3a run FILE [--for SECONDS]``: launch with a live status display, after the
    file's notes (``pb3a check``'s, on stderr: a run is often started unchecked)."""
    import zmq

    from pb3a.cli.daemons import raise_open_files_limit
    from pb3a.cli.status import run_with_status
    from pb3a.transport.auth import ClusterKey, ClusterKeyError

    raise_open_files_limit()        # (the launcher serves its system's clients too)
    plan = load_plan(args.file, "run", args.import_timeout)
    if plan is None:
        return 1
    for note in plan.notes:     # (on stderr: the live table clears the terminal's screen)
        print(note, file=sys.stderr)
    try:
        ClusterKey.load()       # before anything starts (its workers would inherit it)
        return run_with_status(plan, args.seconds, listen=args.listen,
                               final=getattr(args, "whole_process", False))
    except (PB3AError, ClusterKeyError, ValueError) as exc:
        print(f"pb3a run: {exc}", file=sys.stderr)
        return 1
    except (OSError, zmq.ZMQError) as exc:      # an address nobody has, a port in use
        print(f"pb3a run: cannot reach or listen where {args.file} or --listen says "
              f"({exc})", file=sys.stderr)
        return 1


def load_plan(file: str, command: str, import_timeout: float) -> Plan | None:
    """The plan of ``file``, planned in this process once a child has checked it (a
    module file that hangs, ends or crashes its importer is named, not run here), or
    None after printing why there is none."""
    from pb3a.system import System

    if _reported(file, command, lambda: check_file(file, import_timeout=import_timeout)) is None:
        return None
    return _reported(file, command, lambda: System.load(file).plan())


def _reported(file: str, command: str, plan: Callable[[], T]) -> T | None:
    """What ``plan()`` returns, or None after printing why it raised: ``file`` cannot be
    read, is not a valid configuration, or (a ``PB3AError`` saying so) the cluster key
    that its module servers need is unusable."""
    try:
        return plan()
    except OSError as exc:
        print(f"pb3a {command}: cannot read {file}: {exc.strerror or exc}", file=sys.stderr)
    except ConfigError as exc:
        for problem in exc.problems:
            print(problem)
        count = len(exc.problems)
        print(f"pb3a {command}: {count} problem{'s' if count != 1 else ''} in {file}",
              file=sys.stderr)
    except PB3AError as exc:                    # (module servers need the key)
        print(f"pb3a {command}: {exc}", file=sys.stderr)
    return None
