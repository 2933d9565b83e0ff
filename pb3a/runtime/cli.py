"""The ``pb3a`` command line: one entry point, one subcommand per task.

    pb3a check FILE               validate; print every problem; exit 1 on any
    pb3a graph FILE [-o OUT]      draw the configuration (DOT, and SVG/PNG/PDF via Graphviz)
    pb3a run FILE [--for SECONDS] launch, show live status, stop on Ctrl-C or after SECONDS
    pb3a scenario NAME [ARGS...]  run one of the bundled applications (``scenarios/``)
    pb3a status|state|migrate|swap ADDR ...  act on a running system through its launcher
    pb3a modules serve DIR [--listen ADDR]   serve module code to the nodes (until signalled)
    pb3a node start --name N [--listen ADDR] run a node controller (until signalled)

Each subcommand is a function taking the parsed arguments and returning the
exit code; heavy imports (the runtime) happen inside the function that needs them.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from pb3a.errors import ConfigError
from pb3a.kernel.config import Plan
from pb3a.kernel.drawing import plan_to_dot
from pb3a.system import System


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with ``argv`` (default: ``sys.argv[1:]``); returns the exit code."""
    parser = _parser()
    args = parser.parse_args(argv)
    handler: Callable[[argparse.Namespace], int] | None = getattr(args, "handler", None)
    if handler is None:
        parser.print_help()
        return 2
    return handler(args)


def check_command(args: argparse.Namespace) -> int:
    """``pb3a check FILE``: every problem on its own line (exit 1), or a one-line summary."""
    plan = _load_plan(args.file, "check")
    if plan is None:
        return 1
    print(f"ok: {len(plan.modules)} modules, {len(plan.links)} links")
    return 0


def graph_command(args: argparse.Namespace) -> int:
    """``pb3a graph FILE [-o OUT]``: write DOT, then render OUT with Graphviz unless it is .dot."""
    plan = _load_plan(args.file, "graph")
    if plan is None:
        return 1
    text = plan_to_dot(plan)
    if args.output == "-":
        sys.stdout.write(text)
        return 0
    out = Path(args.output) if args.output else Path(Path(args.file).stem + ".svg")
    dot_path = out if out.suffix == ".dot" else out.with_suffix(".dot")
    try:
        dot_path.write_text(text)
    except OSError as exc:
        print(f"pb3a graph: cannot write {dot_path}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    if out == dot_path:
        print(f"wrote {dot_path}")
        return 0
    dot = shutil.which("dot")
    if dot is None:
        print(f"pb3a graph: wrote {dot_path}, but Graphviz's 'dot' program is not on PATH, so "
              f"no {out.name}: install Graphviz (e.g. apt-get install graphviz), or ask for DOT "
              "only with -o FILE.dot", file=sys.stderr)
        return 1
    fmt = out.suffix.lstrip(".") or "svg"
    done = subprocess.run([dot, f"-T{fmt}", str(dot_path), "-o", str(out)],
                          capture_output=True, text=True, timeout=120, check=False)
    if done.returncode != 0:
        print(f"pb3a graph: dot could not write {out}: {done.stderr.strip()}", file=sys.stderr)
        return 1
    print(f"wrote {dot_path} and {out}")
    return 0


def run_command(args: argparse.Namespace) -> int:
    """``pb3a run FILE [--for SECONDS]``: launch with a live status display."""
    from pb3a.runtime.status import run_with_status

    try:
        system = System.load(args.file)
        return run_with_status(system, args.seconds, listen=args.listen)
    except OSError as exc:
        print(f"pb3a run: cannot read {args.file}: {exc.strerror or exc}", file=sys.stderr)
    except ConfigError as exc:
        for problem in exc.problems:
            print(problem)
    return 1


def launcher_command(args: argparse.Namespace) -> int:
    """``pb3a status / state / migrate / swap ADDR ...``: one request to a launcher."""
    import json

    from pb3a.errors import RuntimeFailure, RuntimeTimeout
    from pb3a.runtime.status import format_table
    from pb3a.transport.auth import ClusterKey
    from pb3a.transport.control import ControlClient

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


def _load_plan(file: str, command: str) -> Plan | None:
    """The plan of ``file``, or None after printing why there is none."""
    try:
        return System.load(file).plan()
    except OSError as exc:
        print(f"pb3a {command}: cannot read {file}: {exc.strerror or exc}", file=sys.stderr)
    except ConfigError as exc:
        for problem in exc.problems:
            print(problem)
        count = len(exc.problems)
        print(f"pb3a {command}: {count} problem{'s' if count != 1 else ''} in {file}",
              file=sys.stderr)
    return None


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pb3a", description="Port-based modules that run, swap and move while they run.")
    commands = parser.add_subparsers(title="commands", metavar="COMMAND")

    check = commands.add_parser("check", help="validate a configuration file; exit 1 on errors")
    check.add_argument("file", metavar="FILE", help="a system description (.toml)")
    check.set_defaults(handler=check_command)

    graph = commands.add_parser("graph", help="draw a configuration: nodes, modules, ports, links")
    graph.add_argument("file", metavar="FILE", help="a system description (.toml)")
    graph.add_argument("-o", "--output", metavar="OUT",
                       help="output file: .svg (default: FILE's name with .svg), .png, .pdf, "
                            "or .dot for DOT only; '-' prints DOT")
    graph.set_defaults(handler=graph_command)

    run = commands.add_parser("run", help="launch a system and show its live status")
    run.add_argument("file", metavar="FILE", help="a system description (.toml)")
    run.add_argument("--for", dest="seconds", type=float, metavar="SECONDS",
                     help="stop after this many seconds (default: until Ctrl-C)")
    run.add_argument("--listen", default="tcp://127.0.0.1:0", metavar="ADDR",
                     help="where the launcher takes `pb3a status ADDR` etc. (default: any port)")
    run.set_defaults(handler=run_command)

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

    scenario = commands.add_parser("scenario", help="run a bundled application",
                                   description="Bundled applications: " + ", ".join(SCENARIOS))
    scenario.add_argument("name", metavar="NAME", help=", ".join(SCENARIOS))
    scenario.add_argument("args", nargs=argparse.REMAINDER,
                          help="the scenario's own options (NAME --help lists them)")
    scenario.set_defaults(handler=scenario_command)

    modules = commands.add_parser("modules", help="the module server")
    modules_commands = modules.add_subparsers(title="commands", metavar="COMMAND")
    serve = modules_commands.add_parser("serve", help="serve the Python modules under DIR")
    serve.add_argument("dir", metavar="DIR", help="the directory of module files")
    serve.add_argument("--listen", default="tcp://127.0.0.1:7300", metavar="ADDR",
                       help="address to listen on (default tcp://127.0.0.1:7300; port 0: any)")
    serve.set_defaults(handler=modules_serve_command)

    node = commands.add_parser("node", help="the node controller")
    node_commands = node.add_subparsers(title="commands", metavar="COMMAND")
    start = node_commands.add_parser("start", help="run this machine's node controller")
    start.add_argument("--name", required=True, help="the node's name in configurations")
    start.add_argument("--listen", default="tcp://127.0.0.1:7100", metavar="ADDR",
                       help="address to listen on (default tcp://127.0.0.1:7100; port 0: any)")
    start.add_argument("--max-cpu", type=float, default=90.0, metavar="PERCENT",
                       help="refuse work while the CPU is busier than this (default 90)")
    start.add_argument("--min-memory", type=int, default=256, metavar="MIB",
                       help="refuse work that would leave less memory available (default 256)")
    start.set_defaults(handler=node_start_command)
    return parser


SCENARIOS = {"self-migration": "scenarios.self_migration"}


def modules_serve_command(args: argparse.Namespace) -> int:
    """``pb3a modules serve DIR --listen ADDR``: serve until SIGINT or SIGTERM."""
    from pb3a.runtime.daemon import serve_until_signalled
    from pb3a.runtime.module_server import ModuleServer

    def start(key: Any, host: str, port: int) -> Any:
        server = ModuleServer(args.dir, key, host, port)
        return server, f"serving {server.root} at {server.address}"
    return serve_until_signalled("pb3a modules serve", args.listen, start)


def node_start_command(args: argparse.Namespace) -> int:
    """``pb3a node start --name N --listen ADDR``: a node controller until signalled."""
    from pb3a.runtime.daemon import serve_until_signalled
    from pb3a.runtime.node import Limits, NodeController

    def start(key: Any, host: str, port: int) -> Any:
        limits = Limits(args.max_cpu, args.min_memory << 20)
        controller = NodeController(args.name, key, host, port, limits)
        return controller, f"node {args.name} at {controller.address}"
    return serve_until_signalled("pb3a node start", args.listen, start)


def scenario_command(args: argparse.Namespace) -> int:
    """``pb3a scenario NAME [ARGS]``: hand over to the scenario's own ``main``."""
    module = SCENARIOS.get(args.name)
    if module is None:
        print(f"pb3a scenario: no scenario {args.name!r}; the scenarios: "
              f"{', '.join(SCENARIOS)}", file=sys.stderr)
        return 2
    import importlib

    return int(importlib.import_module(module).main(args.args) or 0)
