"""The daemons' commands, ``pb3a node start`` and ``pb3a modules serve``, and how any
daemon runs from a command line (``rave start`` too): start it, print where it
listens, serve until SIGINT or SIGTERM, then close it."""

from __future__ import annotations

import argparse
import resource
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any, Protocol

import zmq

from pb3a.cli.standard_output import output_gone
from pb3a.transport.addresses import bind_address, check_bindable
from pb3a.transport.auth import ClusterKey, ClusterKeyError, ClusterKeyMissing

KEY_MISSING = 2         # the exit status of a daemon started with no cluster key


class Daemon(Protocol):
    """What ``serve_until_signalled`` serves: closed once, told what stopped it."""

    def close(self, why: str) -> None:
        """Stop serving; ``why``: the signal's name ("SIGTERM"), or "closed"."""


def serve_until_signalled(command: str, listen: str,
                          start: Callable[[Any, str, int], tuple[Daemon, str]],
                          create_key: bool = False) -> int:
    """Start a daemon on ``listen``, print where, and run until SIGINT, SIGTERM or SIGHUP
    (its terminal closed), then close it, naming the signal (its log says why it
    stopped). The handlers come first: a signal while it starts stops it
    once started, closed as after any other signal (it would otherwise die there,
    unclosed). Without a cluster key it exits 2 at once, saying where it looked, unless
    ``create_key`` (it made one in ``~/.pb3a`` that no other machine had, and only their
    refusals said so, later)."""
    raise_open_files_limit()
    stop = threading.Event()
    signalled: list[str] = []

    def stopped_by(signum: int, _frame: Any) -> None:
        signalled.append(signal.Signals(signum).name)
        stop.set()
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, stopped_by)
    try:
        key = ClusterKey.load(create=create_key)
        host, port = bind_address(listen)
        check_bindable(listen, host, port)
        daemon, banner = start(key, host, port)
    except ClusterKeyMissing as exc:
        print(f"{command}: {exc}", file=sys.stderr)
        return KEY_MISSING
    except (OSError, ValueError, ClusterKeyError, zmq.ZMQError) as exc:
        print(f"{command}: {exc}", file=sys.stderr)
        return 1
    if not stop.is_set():
        _announce(banner)
    try:
        while not stop.wait(1.0):
            pass
    finally:
        daemon.close(signalled[0] if signalled else "closed")
    return 0


def raise_open_files_limit() -> None:
    """Raise this process's soft limit of open descriptors to its hard limit, as
    long-running network daemons do (under the common soft limit of 1024, one burst of
    some thousand idle connections made every other open fail, EMFILE)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    for limit in (hard, 65536):     # (an unlimited hard limit is above what Linux allows)
        if limit == resource.RLIM_INFINITY or limit > soft:
            try:
                resource.setrlimit(resource.RLIMIT_NOFILE, (limit, hard))
                return
            except (ValueError, OSError):
                pass


def _announce(banner: str) -> None:
    """Print where the daemon listens. A reader that is gone (a script that closed its
    end, a ``| head`` that has its line) does not end the daemon: its output goes
    nowhere from then on, as it would to a closed terminal."""
    try:
        print(banner, flush=True)
    except BrokenPipeError:
        output_gone()


def modules_serve_command(args: argparse.Namespace) -> int:
    """``pb3a modules serve DIR --listen ADDR``: serve until SIGINT or SIGTERM."""
    from pb3a.daemons.module_server import ModuleServer

    def start(key: Any, host: str, port: int) -> Any:
        server = ModuleServer(args.dir, key, host, port)
        return server, f"serving {server.root} at {server.address}"
    return serve_until_signalled("pb3a modules serve", args.listen, start)


def node_start_command(args: argparse.Namespace) -> int:
    """``pb3a node start --name N --listen ADDR``: a node controller until signalled."""
    from pb3a.daemons.node_controller import Limits, NodeController
    from pb3a.log_format import name_process

    name_process("controller", args.name)        # its log lines: [controller@NAME]
    def start(key: Any, host: str, port: int) -> Any:
        limits = Limits(args.max_cpu, args.min_memory << 20)
        controller = NodeController(args.name, key, host, port, limits)
        return controller, f"node {args.name} at {controller.address}"
    return serve_until_signalled("pb3a node start", args.listen, start)
