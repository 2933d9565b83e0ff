"""Commands that act on a running system through its launcher's address:
``pb3a status / state / migrate / swap ADDR ...``, authenticated with the cluster key."""

from __future__ import annotations

import argparse
import json
import sys

from pb3a.cli.status import format_table
from pb3a.errors import RuntimeFailure, RuntimeTimeout
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient


def register(commands: argparse._SubParsersAction) -> None:
    """Add one subcommand per operation on a running system."""
    for name, extra, helptext in (
            ("status", (), "the live status table of a running system"),
            ("state", ("module",), "a module's live state"),
            ("migrate", ("module", "node"), "move a module (or macro) to another node"),
            ("swap", ("module", "cls"), "swap a module's class ('module:Class')")):
        sub = commands.add_parser(name, help=f"{helptext}, through its launcher")
        sub.add_argument("address", metavar="ADDR", help="the launcher's address "
                         "(`pb3a run` prints it)")
        for arg in extra:
            sub.add_argument(arg, metavar=arg.upper())
        sub.set_defaults(handler=launcher_command, op=name)


def launcher_command(args: argparse.Namespace) -> int:
    """``pb3a status / state / migrate / swap ADDR ...``: one request to a launcher."""


    client = ControlClient(ClusterKey.load(), args.address)
    try:
        if args.op == "status":
            print(format_table(client.call("stats")))
        elif args.op == "state":
            print(json.dumps(client.call("state", name=args.module), indent=2, default=repr))
        elif args.op == "migrate":
            report = client.call("migrate", timeout=60.0, name=args.module, to=args.node)
            print(f"{report['module']}: {report['source']} -> {report['destination']}, paused "
                  f"{report['pause_s'] * 1e3:.1f} ms, {report['state_bytes']} bytes of state, "
                  f"{report['links']} links re-wired")
        else:
            kept = client.call("swap", timeout=60.0, name=args.module, cls=args.cls)
            print(f"{args.module} is now {args.cls}; state kept: {', '.join(kept) or '(none)'}")
        return 0
    except (RuntimeFailure, RuntimeTimeout) as exc:
        print(f"pb3a {args.op}: {exc}", file=sys.stderr)
        return 1
    finally:
        client.close()
