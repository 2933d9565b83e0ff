"""The ``pb3a`` command line's grammar: every command, its arguments and help, and the
function that runs it, named as ``"module:function"`` (``set_defaults(handler=...)``),
and what its process is in its log lines (``log_role``; by default ``launcher``).

Nothing here imports a command's implementation: ``main`` imports the one function it
names once the arguments have parsed. So ``pb3a --help``, ``pb3a COMMAND --help`` and a
mistaken argument are answered without the runtime (ZeroMQ, numpy, the launcher: a
third of a second), and each command imports only what it uses.
"""

from __future__ import annotations

import argparse
from typing import Any

from pb3a.cli import arguments, stress_options

MANAGER_LISTEN = "127.0.0.1:0"      # pb3a manager's default: loopback, any free port
IMPORT_TIMEOUT_S = 10.0             # check's and graph's: one module file's import, at most


def parser() -> argparse.ArgumentParser:
    """The whole command line, each command's handler named, not imported."""
    top = argparse.ArgumentParser(
        prog="pb3a", description="Port-based modules that run, swap and move while they run.")
    commands = top.add_subparsers(title="commands", metavar="COMMAND")
    for add in (_files, _running_system, _stress, _scenario, _daemons, _key, _manager):
        add(commands)
    return top


def _files(commands: argparse._SubParsersAction) -> None:
    """``check``, ``graph`` and ``run``: commands on a configuration file."""
    check = commands.add_parser("check", help="validate a configuration file; exit 1 on errors")
    check.add_argument("file", metavar="FILE", help="a system description (.toml)")
    _import_timeout(check)
    check.set_defaults(handler="pb3a.cli.files:check_command", log_role="pb3a check")

    graph = commands.add_parser("graph", help="draw a configuration: nodes, modules, ports, links")
    graph.add_argument("file", metavar="FILE", help="a system description (.toml)")
    graph.add_argument("-o", "--output", metavar="OUT",
                       help="output file: .svg (default: FILE's name with .svg), .png, .pdf, "
                            "or .dot for DOT only; '-' prints DOT")
    _import_timeout(graph)
    graph.set_defaults(handler="pb3a.cli.files:graph_command", log_role="pb3a graph")

    run = commands.add_parser("run", help="launch a system and show its live status")
    run.add_argument("file", metavar="FILE", help="a system description (.toml)")
    run.add_argument("--for", dest="seconds", type=arguments.seconds, metavar="SECONDS",
                     help="stop after this many seconds (default: until Ctrl-C)")
    run.add_argument("--listen", metavar="ADDR",
                     help="where the launcher takes `pb3a status ADDR` etc. and remote nodes "
                          "call it back (default: any port on the interface that reaches "
                          "the remote nodes; loopback without)")
    _import_timeout(run)
    run.set_defaults(handler="pb3a.cli.files:run_command")


def _import_timeout(command: argparse.ArgumentParser) -> None:
    command.add_argument("--import-timeout", type=arguments.seconds, default=IMPORT_TIMEOUT_S,
                         metavar="SECONDS",
                         help="longest the import of one module file may take; one that takes "
                              f"longer is reported as hanging (default {IMPORT_TIMEOUT_S:g})")


def _running_system(commands: argparse._SubParsersAction) -> None:
    """One command per operation on a running system, through its launcher's address
    (``pb3a.cli.running_system.OPERATIONS`` has what each does)."""
    def command(name: str, helptext: str, *positionals: tuple[str, str],
                timeout: str = "how long the operation may wait (default: the system's)"
                ) -> argparse.ArgumentParser:
        sub = commands.add_parser(name, help=f"{helptext}, through its launcher")
        sub.add_argument("address", metavar="ADDR",
                         help="the launcher's address, tcp://HOST:PORT (pb3a run prints it)")
        for arg, text in positionals:
            sub.add_argument(arg, metavar=arg.upper(), help=text)
        sub.add_argument("--json", action="store_true", help="print JSON, for scripts")
        # (above 0: at 0 no launcher could answer in time, and the message blamed the
        # address)
        sub.add_argument("--timeout", type=arguments.seconds, default=None,
                         metavar="SECONDS", help=timeout)
        sub.set_defaults(handler="pb3a.cli.running_system:operation_command", operation=name,
                         log_role=f"pb3a {name}")
        return sub

    command("status", "the live status table of a running system")
    command("state", "a module's live state", ("module", "the module's name"))
    set_ = command("set", "set state attributes of a running module",
                   ("module", "the module's name"))
    set_.add_argument("values", nargs="+", metavar="NAME=VALUE",
                      help="VALUE is read as JSON when it is (5, 2.5, true, [1, 2], "
                           "\"text\"), else as text")
    command("migrate", "move a module (or macro) to another node",
            ("module", "the module's (or macro's) name"), ("node", "the node to move it to"))
    command("swap", "swap a module's class",
            ("module", "the module's name"), ("cls", "the new class, module:Class"))
    reload = command("reload", "drop a Python module's cached code everywhere",
                     ("module", "the Python module, as in module:Class (filt, pkg.mod)"))
    reload.description = (
        "Drop the cached copies of a Python module and its submodules in the launcher and "
        "every worker, so that the next swap or add naming one of its classes gets its "
        "file as it is now; running modules keep their code until swapped. A swap given "
        "'module:Class' reloads that module by itself when its file changed; reload by "
        "hand a file that module imports, or a module server's module.")
    relink = command("relink", "feed an input from another output",
                     ("src", "the output, module.port"), ("dst", "the input, module.port"))
    relink.add_argument("--policy", help="the input's policy on the new link (latest, "
                                         "queue:N ...)")
    add = command("add", "start a new module, or a macro",
                  ("module", "the new module's (or macro instance's) name"),
                  ("cls", "its class, module:Class (a Module or a Macro)"))
    add.add_argument("--node", help="where it runs (default: the first node)")
    add.add_argument("--period", type=arguments.wait_seconds, metavar="SECONDS",
                     help="its step period (0: as fast as it can)")
    add.add_argument("--fixed-rate", action="store_true", default=None,
                     help="its steps due a period after the last one began, not after it "
                          "ended (default: its class's fixed_rate)")
    add.add_argument("--state", nargs="*", default=[], metavar="NAME=VALUE",
                     type=arguments.state_pair,
                     help="its initial state, as for `pb3a set` (after the class); a "
                          "macro's, MODULE={...} per module of it")
    remove = command("remove", "stop and remove a module, or every module of a macro",
                     ("module", "the module's (or macro instance's) name"))
    remove.add_argument("--force", action="store_true",
                        help="kill its worker if it does not answer its stop within the "
                             "timeout (frozen in step or teardown); refused for a worker "
                             "that runs other modules too")
    restart = command("restart", "start a module again (also a failed one) with its "
                      "configured state", ("module", "the module's name"))
    restart.add_argument("--force", action="store_true",
                         help="kill its worker if it does not answer its stop within the "
                              "timeout (stuck in step, on_input or teardown); refused for a "
                              "worker that runs other modules too")
    command("nodes", "every node's health")
    # (they print what there is at once, or with --follow what comes until Ctrl-C:
    # their --timeout bounds the connection only)
    answer = "how long the launcher may take to answer (default 5)"
    logs = command("logs", "the system's log, from every node", timeout=answer)
    logs.add_argument("--module", help="only what is about this module")
    logs.add_argument("--follow", action="store_true", help="keep printing new entries "
                                                            "until Ctrl-C")
    events = command("events", "what happened: moves, swaps, restarts, failures, lost nodes",
                     timeout=answer)
    events.add_argument("--follow", action="store_true", help="keep printing new events "
                                                              "until Ctrl-C")


def _stress(commands: argparse._SubParsersAction) -> None:
    """``stress FILE``."""
    stress = commands.add_parser(
        "stress", help="run a configuration under CPU load and faults; report per link "
                       "and node (JSON and PNG)")
    stress.add_argument("file", metavar="FILE", help="a system description (.toml)")
    stress.add_argument("--for", dest="seconds", type=arguments.seconds, default=30.0,
                        metavar="SECONDS", help="how long to run (default 30)")
    stress.add_argument("--load", action="append", default=[], type=stress_options.load,
                        metavar="CPUS:PERCENT[@T[+D]]",
                        help="hold CPUs at a level, e.g. 0,1:80, or 0:90@10+20 (from 10 s "
                             "for 20 s); repeatable")
    stress.add_argument("--kill-worker-every", dest="kill_every", type=arguments.seconds,
                        metavar="SECONDS", help="SIGKILL a random worker this often")
    stress.add_argument("--kill-among", type=stress_options.names, default=frozenset(),
                        metavar="M1,M2", help="kill only the workers of these modules")
    stress.add_argument("--migrate-every", dest="migrate_every", type=arguments.seconds,
                        metavar="SECONDS", help="move a random module to another node "
                                                "this often")
    stress.add_argument("--migrate-among", type=stress_options.names, default=frozenset(),
                        metavar="M1,M2", help="move only these modules")
    stress.add_argument("--cut-node", dest="cuts", action="append", default=[],
                        type=stress_options.cut, metavar="NAME@T[+D]",
                        help="freeze node NAME (on this machine) at T s for D s (default "
                             "to the end), as if its cable were cut; repeatable")
    stress.add_argument("--sample", dest="sample_s", type=arguments.seconds, default=1.0,
                        metavar="SECONDS", help="how often to record figures (default 1)")
    stress.add_argument("--out", default=".", metavar="DIR",
                        help="where stress.json and stress.png go (default: here)")
    stress.add_argument("--seed", type=int, help="seed of the random choices")
    _import_timeout(stress)
    stress.set_defaults(handler="pb3a.cli.stress:stress_command")


def _scenario(commands: argparse._SubParsersAction) -> None:
    """``scenario NAME [ARGS]``. The scenarios installed are looked up for its help
    alone (``ScenarioHelp``): reading every distribution's entry points takes tens of
    milliseconds that no other answer needs."""
    scenario = commands.add_parser("scenario", help="run a bundled application",
                                   add_help=False)
    name = scenario.add_argument("name", metavar="NAME")
    scenario.add_argument("args", nargs=argparse.REMAINDER,
                          help="the scenario's own options (NAME --help lists them)")
    scenario.add_argument("-h", "--help", action=ScenarioHelp, names=name)
    scenario.set_defaults(handler="pb3a.cli.scenarios:scenario_command")


class ScenarioHelp(argparse.Action):
    """``pb3a scenario --help``: argparse's help, with the scenarios installed named in
    the description and as the help of the argument ``names``."""

    def __init__(self, option_strings: list[str], dest: str, names: argparse.Action) -> None:
        super().__init__(option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                         nargs=0, help="show this help message and exit")
        self.names = names

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        from pb3a.cli.scenarios import scenarios

        listed = ", ".join(sorted(scenarios())) or "(none installed)"
        parser.description = f"Bundled applications: {listed}"
        self.names.help = listed
        parser.print_help()
        parser.exit()


def _daemons(commands: argparse._SubParsersAction) -> None:
    """``modules serve`` and ``node start``."""
    modules = commands.add_parser("modules", help="the module server")
    modules_commands = modules.add_subparsers(title="commands", metavar="COMMAND",
                                               required=True)
    serve = modules_commands.add_parser("serve", help="serve the Python modules under DIR")
    serve.add_argument("dir", metavar="DIR", help="the directory of module files")
    serve.add_argument("--listen", default="tcp://127.0.0.1:7300", metavar="ADDR",
                       help="address to listen on (default tcp://127.0.0.1:7300; port 0: any)")
    serve.set_defaults(handler="pb3a.cli.daemons:modules_serve_command", log_role="module server")

    node = commands.add_parser("node", help="the node controller")
    node_commands = node.add_subparsers(title="commands", metavar="COMMAND",
                                         required=True)
    start = node_commands.add_parser("start", help="run this machine's node controller")
    start.add_argument("--name", required=True,
                       help=("this machine's node name, as configurations name it: a label "
                             "of the controller's log and refusals (its executors run as the "
                             "node a configuration names; a launcher that names its address "
                             "otherwise warns of it)"))
    start.add_argument("--listen", default="tcp://127.0.0.1:7100", metavar="ADDR",
                       help="address to listen on (default tcp://127.0.0.1:7100; port 0: any)")
    start.add_argument("--max-cpu", type=arguments.percent, default=90.0, metavar="PERCENT",
                       help="refuse work while the CPU is busier than this (default 90)")
    start.add_argument("--min-memory", type=arguments.mebibytes, default=256, metavar="MIB",
                       help="refuse work that would leave less memory available (default 256)")
    start.set_defaults(handler="pb3a.cli.daemons:node_start_command", log_role="controller")


def _key(commands: argparse._SubParsersAction) -> None:
    """``key new PATH``."""
    key = commands.add_parser("key", help="the cluster key")
    key_commands = key.add_subparsers(title="commands", metavar="COMMAND",
                                       required=True)
    new = key_commands.add_parser("new", help="write a new cluster key to PATH (mode 0600)")
    new.add_argument("path", metavar="PATH", help="the key file to create (it must not exist)")
    new.set_defaults(handler="pb3a.cli.keys:key_new_command", log_role="pb3a key")


def _manager(commands: argparse._SubParsersAction) -> None:
    """``manager [FILE | ADDR]``."""
    manager = commands.add_parser(
        "manager", help="the ModuleManager and State Editor: a web app to build, see and "
                        "change a system live")
    manager.add_argument("target", nargs="?", metavar="FILE | ADDR",
                         help="a configuration (.toml) to edit and launch, or the address "
                              "[tcp://]HOST:PORT of a running system's launcher (default: a "
                              "new, empty document)")
    manager.add_argument("--listen", default=MANAGER_LISTEN, metavar="HOST:PORT",
                         help=f"where the app listens (default {MANAGER_LISTEN}: loopback, "
                              "any free port)")
    manager.add_argument("--refresh", type=arguments.seconds, default=0.5, metavar="S",
                         help="seconds between live updates of the page (default 0.5)")
    manager.add_argument("--timeout", type=arguments.seconds, default=10.0, metavar="S",
                         help="seconds a call to the system may take (default 10)")
    _import_timeout(manager)
    manager.set_defaults(handler="pb3a.cli.manager:manager_command", log_role="manager")
