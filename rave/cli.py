"""The rave command: serve a world and its robots, inject faults, render.

    rave start WORLD [--seed N] [--listen HOST] [--port PORT] [--rate R | --lockstep]
               [--watchdog SECONDS]   step WORLD in real time (or R times it, or
                                      when its controller asks) and start one robot
                                      server per robot; prints every address (with
                                      --port, the world's at PORT and robot i's at
                                      PORT + i, the same at every start)
    rave fault ROBOT_ADDR FAULT [--sonars I ...] [--bias B] [--clear]
                                      inject (or clear) a fault in a hardware robot
    rave render WORLD [-o FILE]       draw the world (PNG, SVG or PDF by suffix)
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

from pb3a.cli.arguments import port, seed, wait_seconds
from pb3a.cli.log_output import show_logs

# A robot none of whose requests came for this long (the world's time) is stopped, as
# a Pioneer's controller stops when its client falls silent (its communication
# watchdog, nominally 2 s): one whose server or controller died drove on with its last
# command for good.
WATCHDOG_S = 2.0


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    show_logs(role="rave")
    return int(args.handler(args))


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rave", description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(required=True, metavar="COMMAND")
    start = commands.add_parser("start", help="serve a world and one server per robot")
    start.add_argument("world", help="a world file (TOML), or a bundled world's name (lab ...)")
    start.add_argument("--seed", type=seed, default=0, help="0 or more (default 0)")
    start.add_argument("--listen", default="127.0.0.1", metavar="HOST",
                       help="the interface to serve on (default 127.0.0.1)")
    start.add_argument("--port", type=port, default=0, metavar="PORT",
                       help="the world server's port, and robot i's (in the world file's "
                            "order, from 1) PORT + i: addresses a configuration can keep "
                            "(default: free ports, others at every start)")
    start.add_argument("--rate", type=float, default=1.0,
                       help="simulated seconds per wall-clock second (default 1)")
    start.add_argument("--lockstep", action="store_true",
                       help="step only when the controller asks (a driver's `advance`): "
                            "as fast as it decides, never ahead of it")
    start.add_argument("--watchdog", type=wait_seconds, default=None, metavar="SECONDS",
                       help="stop a robot none of whose requests came for SECONDS of "
                            f"the world's time (default {WATCHDOG_S:g}, times R with "
                            f"--rate R: {WATCHDOG_S:g} s by the wall clock; 0: never)")
    start.set_defaults(handler=start_command)
    fault = commands.add_parser("fault", help="inject or clear a fault in a hardware robot")
    fault.add_argument("robot", metavar="ROBOT_ADDR", help="the robot server's address")
    fault.add_argument("fault", choices=("motors_off", "sonar_dead", "odometry_bias"))
    fault.add_argument("--sonars", type=int, nargs="+", help="for sonar_dead (default all)")
    fault.add_argument("--bias", type=float, default=0.05, help="odometry_bias, rad per m")
    fault.add_argument("--clear", action="store_true", help="clear the fault instead")
    fault.add_argument("--timeout", type=wait_seconds, default=5.0, metavar="SECONDS",
                       help="how long to wait for the robot server (default 5)")
    fault.set_defaults(handler=fault_command)
    render = commands.add_parser("render", help="draw a world to an image")
    render.add_argument("world", help="a world file (TOML), or a bundled world's name")
    render.add_argument("-o", "--output", default=None, help="image file (default WORLD.png)")
    render.set_defaults(handler=render_command)
    return parser


def start_command(args: argparse.Namespace) -> int:
    from pb3a.cli.daemons import serve_until_signalled
    from pb3a.transport.addresses import check_bindable
    from rave.server import RobotServers, WorldServer
    from rave.world import World
    from rave.worldfile import WorldError, world_file

    try:
        world = World.load(world_file(args.world), seed=args.seed)
    except WorldError as exc:
        print(f"rave start: {exc}", file=sys.stderr)
        return 1

    watchdog_s = args.watchdog
    if watchdog_s is None:      # (in world time: at --rate 32, 2 s of it bit between
        # two requests of a driver asking every 0.1 s of the wall clock)
        watchdog_s = WATCHDOG_S * (1.0 if args.lockstep else max(1.0, args.rate))

    def start(key: Any, host: str, port: int) -> tuple[Any, str]:
        ports = [port + i for i in range(1, len(world.robots) + 1)] if port else None
        for robot_port in ports or ():      # (said at once, before anything starts)
            check_bindable(f"tcp://{host}:{robot_port}", host, robot_port)
        served = _Served(WorldServer(world, host, port, rate=args.rate,
                                      lockstep=args.lockstep, watchdog_s=watchdog_s))
        served.robots = RobotServers(served.world.address, list(world.robots), host, ports)
        lines = [f"world {world.name} at {served.world.address}"]
        lines += [f"robot {name} at {address}"
                  for name, address in served.robots.addresses.items()]
        return served, "\n".join(lines)
    # (the simulator serves the launchers of its own machine, which share its
    # ~/.pb3a/cluster.key: it may make that key on first use, as they do)
    # (closed however it ends: a port in use left the hardware robots' emulators running)
    with world:
        if args.port and args.port + len(world.robots) > 65535:
            print(f"rave start: --port {args.port} leaves no port for robot "
                  f"{len(world.robots)} of {len(world.robots)} (each robot i is served at "
                  "PORT + i, up to 65535): choose a lower port", file=sys.stderr)
            return 1
        return serve_until_signalled("rave start", f"tcp://{args.listen}:{args.port}", start,
                                     create_key=True)


class _Served:
    """A world server and its robot servers, closed together (robots first)."""

    def __init__(self, world: Any) -> None:
        self.world, self.robots = world, None

    def close(self, why: str = "closed") -> None:
        """Stop serving (``why``: the signal that stops it, as every daemon is told)."""
        if self.robots is not None:
            self.robots.close()
        self.world.close()


def fault_command(args: argparse.Namespace) -> int:
    from pb3a.errors import RuntimeFailure, RuntimeTimeout
    from pb3a.transport.addresses import tcp_address_problems
    from pb3a.transport.auth import ClusterKey, ClusterKeyError
    from pb3a.transport.control import ControlClient

    wrong = tcp_address_problems(args.robot, "ROBOT_ADDR, the robot server's address,")
    if wrong:                           # (ZeroMQ's "Invalid argument" traceback, before)
        print(f"rave fault: {wrong[0]}", file=sys.stderr)
        return 1
    try:
        client = ControlClient(ClusterKey.load(), args.robot)
    except ClusterKeyError as exc:
        print(f"rave fault: {exc}", file=sys.stderr)
        return 1
    try:
        if args.clear:
            client.call("clear", args.timeout, fault=args.fault)
        else:
            params = {"sonar_dead": {"sonars": args.sonars} if args.sonars else {},
                      "odometry_bias": {"bias": args.bias}}.get(args.fault, {})
            client.call("inject", args.timeout, fault=args.fault, params=params)
    except (RuntimeFailure, RuntimeTimeout) as exc:
        print(f"rave fault: {exc}", file=sys.stderr)
        return 1
    finally:
        client.close()
    print(f"{'cleared' if args.clear else 'injected'} {args.fault} at {args.robot}")
    return 0


def render_command(args: argparse.Namespace) -> int:
    from pathlib import Path

    from matplotlib.backend_bases import FigureCanvasBase

    from rave.render import render
    from rave.world import World
    from rave.worldfile import WorldError, world_file

    output = Path(args.output or Path(args.world).with_suffix(".png").name)
    formats = FigureCanvasBase.get_supported_filetypes()
    # (no suffix: matplotlib wrote NAME.png, beside it; one it has no format for, or a
    # directory's: its ValueError's traceback, once the world was loaded)
    if output.is_dir() or output.suffix[1:].lower() not in formats:
        print(f"rave render: -o {output}: give an image file, its suffix the format "
              f"(.png, .svg, .pdf; the formats: {', '.join(sorted(formats))})",
              file=sys.stderr)
        return 1
    try:
        world = World.load(world_file(args.world))
    except WorldError as exc:
        print(f"rave render: {exc}", file=sys.stderr)
        return 1
    with world:
        try:
            render(world, output)
        except OSError as exc:          # (a directory that is not there, or read-only)
            print(f"rave render: -o {output}: cannot be written ({exc.strerror or exc}); "
                  "give a file in a directory you can write in", file=sys.stderr)
            return 1
    print(f"wrote {output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
