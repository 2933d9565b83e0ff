"""The executor process of one node share: an ``Executor`` behind an authenticated
control server.

A node controller starts one per configuration on its node; the launcher then
talks to it directly (``RemoteNode``): ``bind`` says where the launcher is, then
every ``executor`` request applies one ``Executor`` operation under the executor's
lock. Agents' requests and restarted writers go back to the launcher. The process
exits when told to (``shutdown``), when its controller stops it (SIGTERM: modules
stop in reverse start order first), when its controller dies (its parent-death
pipe closes), or when its launcher has not answered a ping for ``ORPHAN_S``: it
never outlives its owners.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from typing import Any

from pb3a.errors import RuntimeFailure, RuntimeTimeout
from pb3a.loading.sources import CodeSources
from pb3a.logbook import LogBook
from pb3a.node.executor import Executor
from pb3a.node.protocol import REMOTE_OPERATIONS
from pb3a.processes import serve_as_child
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient, ControlServer
from pb3a.worker.process import AGENT_REQUEST_TIMEOUT

log = logging.getLogger("pb3a.node")

ORPHAN_S = 10.0           # a launcher silent this long is gone: stop


class NodeShare:
    """One configuration's share of a node: the handler of its control server."""

    def __init__(self, config: str, node: str, workers: int = 0,
                 cpus: list[int] | None = None, host: str = "127.0.0.1") -> None:
        self.config, self.node = config, node
        self.key = ClusterKey.load()
        self.executor = Executor(node, workers=workers, cpus=cpus, host=host)
        self.executor.handler = self._agent_request
        self.executor.republished = self._republished
        self.executor.on_event = self._tell_event
        self.launcher: ControlClient | None = None
        self.server: ControlServer | None = None
        self.peers: dict[str, ControlClient] = {}     # other nodes, pinged for their RTT
        self.rtts: dict[str, float] = {}
        self.stopped = threading.Event()
        self.logbook = LogBook()                       # the launcher merges it into its own
        logging.getLogger().addHandler(self.logbook)

    def handle(self, op: str, args: dict[str, Any]) -> Any:
        ex = self.executor
        if op == "executor":
            if args["method"] not in REMOTE_OPERATIONS:
                raise ValueError(f"a node executor has no operation {args['method']!r}")
            with ex.lock:
                return getattr(ex, args["method"])(*args["args"], **args["kwargs"])
        if op == "bind":
            self.bind(args["launcher"], args["checkpoint_s"], args["log_level"],
                      args["code"], args.get("orphan_s", ORPHAN_S), args.get("epoch", 0))
            return None
        if op == "peers":
            self.meet(args["peers"])
            return None
        if op == "rtts":
            return dict(self.rtts)
        if op == "logs":
            return self.logbook.since(args["since"])
        if op == "describe":
            return {"config": self.config, "node": self.node, "modules": sorted(ex.modules)}
        if op == "shutdown":
            self.stopped.set()
            return None
        raise ValueError(f"a node executor has no operation {op!r}")

    def bind(self, launcher: str, checkpoint_s: float, log_level: int, code: CodeSources,
             orphan_s: float = ORPHAN_S, epoch: int = 0) -> None:
        """Work for the launcher at ``launcher`` (before any module is added), in its
        system's ``epoch``: older requests and replication are refused from now on."""
        if self.launcher is not None:
            raise RuntimeFailure(f"node {self.node} already works for {self.launcher.address}")
        self.executor.configure(checkpoint_s=checkpoint_s, log_level=log_level, code=code,
                                epoch=epoch)
        if self.server is not None:
            self.server.advance_epoch(epoch)
        code.install(self.key)
        self.launcher = ControlClient(self.key, launcher)
        threading.Thread(target=self._watch_launcher, args=(orphan_s,),
                         name="pb3a-launcher-watch", daemon=True).start()

    def meet(self, peers: dict[str, str]) -> None:
        """Measure the round-trip time to each other node (name -> control address) from
        now on; the launcher stands for the nodes embedded in it."""
        for client in self.peers.values():
            client.close()
        self.peers = {name: ControlClient(self.key, address, epoch=self.executor.epoch)
                      for name, address in peers.items()}
        self.rtts = {}

    def _agent_request(self, op: str, args: dict[str, Any]) -> Any:
        if self.launcher is None:
            raise RuntimeFailure(f"node {self.node} has no launcher to ask")
        return self.launcher.call("agent", AGENT_REQUEST_TIMEOUT, request=op, args=args)

    def _republished(self, link: Any, endpoint: tuple[str, str, bytes]) -> None:
        self._tell_launcher("republished", link=link, endpoint=endpoint)

    def _tell_event(self, kind: str, subject: str, **detail: Any) -> None:
        """A restart or failure here goes into the launcher's events."""
        self._tell_launcher("event", kind=kind, subject=subject, detail=detail)

    def _tell_launcher(self, op: str, **args: Any) -> None:
        """Tell the launcher what a restart did, from another thread: a restart runs
        under the executor's lock, which the launcher may be waiting for."""
        def tell() -> None:
            if self.launcher is not None:
                with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
                    self.launcher.call(op, **args)
        threading.Thread(target=tell, name=f"pb3a-{op}", daemon=True).start()

    def _watch_launcher(self, orphan_s: float) -> None:
        """Ping the launcher (stop when it stays silent) and every peer (their RTTs)."""
        last = time.monotonic()
        while not self.stopped.wait(min(1.0, orphan_s / 4)) and self.launcher is not None:
            if self.launcher.ping(1.0) is not None:
                last = time.monotonic()
            elif time.monotonic() - last > orphan_s:
                log.error("launcher at %s silent for %.0f s: stopping",
                          self.launcher.address, orphan_s)
                self.stopped.set()
            for name, client in list(self.peers.items()):
                rtt = client.ping(1.0)
                if rtt is not None:
                    self.rtts[name] = rtt

    def close(self) -> None:
        self.executor.shutdown()
        for client in [*self.peers.values(), *filter(None, [self.launcher])]:
            client.close()


def executor_main(config: str, node: str, workers: int, cpus: list[int] | None,
                  host: str, conn: Any, level: int = logging.WARNING) -> None:
    """Entry point of an executor process: serve until shut down, signalled or orphaned."""
    logging.basicConfig(level=level, format=f"%(asctime)s pb3a[{config}@{node}] "
                                            "%(levelname)s %(message)s")
    share = NodeShare(config, node, workers, cpus, host)
    server = share.server = ControlServer(ClusterKey.load(), share.handle, host,
                                          name="pb3a-node-executor")
    try:
        serve_as_child(conn, server.address, share.stopped)
    finally:
        server.close()
        share.close()
