"""The executor process of one node share: an ``Executor`` behind an authenticated
control server.

A node controller starts one per configuration on its node; the launcher then talks
to it directly. The process exits when told to (``shutdown``), when its controller
stops it (SIGTERM: modules stop in reverse start order first), or when its
controller dies (its parent-death pipe closes), so it never outlives its owner.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from typing import Any

from pb3a.runtime.executor import Executor
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlServer

log = logging.getLogger("pb3a.node")


class NodeExecutor:
    """What the launcher may ask of a node share (the control server's handler)."""

    def __init__(self, config: str, node: str, workers: int = 0,
                 cpus: list[int] | None = None) -> None:
        self.config, self.node = config, node
        self.executor = Executor(workers={node: workers}, cpus={node: cpus} if cpus else {})
        self.stopped = threading.Event()

    def handle(self, op: str, args: dict[str, Any]) -> Any:
        ex = self.executor
        if op == "add_module":
            with ex.lock:
                ex.expect([args["spec"]])
                ex.add_module(args["spec"], state=args.get("state"))
            return None
        if op == "start_modules":
            with ex.lock:
                ex.start_modules(args["names"])
            return None
        if op == "state":
            return ex.call(ex.modules[args["name"]].worker, "get_state", name=args["name"])
        if op == "set_state":
            with ex.lock:
                return ex.call(ex.modules[args["name"]].worker, "set_state",
                               name=args["name"], state=args["state"])
        if op == "stats":
            from pb3a.runtime.stats import collect
            return collect(ex)
        if op == "describe":
            return {"config": self.config, "node": self.node, "modules": sorted(ex.modules)}
        if op == "shutdown":
            self.stopped.set()
            return None
        raise ValueError(f"a node executor has no operation {op!r}")


def executor_main(config: str, node: str, workers: int, cpus: list[int] | None,
                  host: str, conn: Any, level: int = logging.WARNING) -> None:
    """Entry point of an executor process: serve until shut down, signalled or orphaned."""
    logging.basicConfig(level=level, format=f"%(asctime)s pb3a[{config}@{node}] "
                                            "%(levelname)s %(message)s")
    share = NodeExecutor(config, node, workers, cpus)
    server = ControlServer(ClusterKey.load(), share.handle, host, name="pb3a-node-executor")
    signal.signal(signal.SIGTERM, lambda *_: share.stopped.set())
    signal.signal(signal.SIGINT, signal.SIG_IGN)         # the controller decides
    conn.send(server.address)
    orphaned = threading.Thread(target=_watch_parent, args=(conn, share.stopped), daemon=True)
    orphaned.start()
    try:
        while not share.stopped.wait(1.0):      # (a timed wait lets signal handlers run)
            pass
    finally:
        server.close()
        share.executor.shutdown()


def _watch_parent(conn: Any, stopped: threading.Event) -> None:
    with contextlib.suppress(EOFError, OSError):
        conn.recv()                                      # nothing is ever sent: EOF on death
    stopped.set()
