"""Running a daemon from the command line: start it, print where it listens, serve
until SIGINT or SIGTERM, then close it (``pb3a node start``, ``rave start`` ...)."""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Callable
from typing import Any

from pb3a.transport.auth import ClusterKey, ClusterKeyError
from pb3a.transport.control import bind_address


def serve_until_signalled(command: str, listen: str,
                           start: Callable[[Any, str, int], tuple[Any, str]]) -> int:
    """Start a daemon on ``listen``, print where, and run until SIGINT or SIGTERM."""
    try:
        daemon, banner = start(ClusterKey.load(), *bind_address(listen))
    except (OSError, ValueError, ClusterKeyError) as exc:
        print(f"{command}: {exc}", file=sys.stderr)
        return 1
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    print(banner, flush=True)
    try:
        while not stop.wait(1.0):
            pass
    finally:
        daemon.close()
    return 0
