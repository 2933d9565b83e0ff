"""``RemoteNode``: a node whose executor runs elsewhere, started by its node controller.

It offers the launcher the same operations as an in-process ``Executor`` and
forwards each as one authenticated request to the executor process
(``node_executor.py``), which applies it to its own ``Executor``.
"""

from __future__ import annotations

import contextlib
from typing import Any

from pb3a.errors import RuntimeFailure, RuntimeTimeout
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import ControlClient

START_TIMEOUT = 60.0       # an executor process imports numpy and friends first
CALL_TIMEOUT = 60.0        # the executor's own requests to its workers have deadlines

# The Executor operations a launcher may ask of a remote node.
OPERATIONS = ("expect", "add_module", "start_modules", "stop_module", "remove_module", "swap",
              "pause", "resume", "retire", "land", "call_module", "forget", "connect",
              "detach", "publish", "unpublish", "open_inbound", "follow", "close_inbound",
              "report")


class RemoteNode:
    """The executor of node ``name``, reached through the controller at ``address``."""

    def __init__(self, name: str, address: str, *, config: str, launcher: str,
                 workers: int = 0, cpus: list[int] | None = None, checkpoint_s: float = 1.0,
                 log_level: int = 30, module_servers: list[str] | None = None,
                 epoch: int = 0) -> None:
        self.name, self.config = name, config
        key = ClusterKey.load()
        self.controller = ControlClient(key, address)
        self.client: ControlClient | None = None
        self.lost = False
        host = address.removeprefix("tcp://").rpartition(":")[0]
        try:
            executor = self.controller.call("start_executor", START_TIMEOUT, config=config,
                                            workers=workers, cpus=cpus, host=host)
            self.client = ControlClient(key, executor, epoch=epoch)
            self.client.call("bind", launcher=launcher, checkpoint_s=checkpoint_s,
                             log_level=log_level, module_servers=list(module_servers or []),
                             epoch=epoch)
        except (RuntimeFailure, RuntimeTimeout) as exc:
            self.close()
            raise RuntimeFailure(f"node {name} at {address} did not start an executor for "
                                 f"{config!r}: {exc}") from None
        self.address = executor

    def _forward(self, op: str, *args: Any, **kwargs: Any) -> Any:
        if self.lost or self.client is None:
            raise RuntimeFailure(f"node {self.name} is lost")
        return self.client.call("executor", CALL_TIMEOUT, method=op, args=args, kwargs=kwargs)

    def ping(self, timeout: float) -> float | None:
        """The executor's round-trip time, or None without an answer in ``timeout``."""
        return None if self.client is None else self.client.ping(timeout)

    def controller_answers(self, timeout: float) -> bool:
        """True if the node's controller answered within ``timeout`` seconds."""
        return self.controller.ping(timeout) is not None

    def meet(self, peers: dict[str, str]) -> None:
        """Have the node measure its RTT to each peer (name -> control address)."""
        if self.client is not None and not self.lost:
            self.client.call("peers", peers=peers)

    def rtts(self) -> dict[str, float]:
        """The node's last measured round-trip times to its peers."""
        if self.client is None or self.lost:
            return {}
        return self.client.call("rtts", 2.0)

    def lose(self) -> None:
        """The node is gone: every waiting call fails now, and every later one at once."""
        self.lost = True
        if self.client is not None:
            self.client.fail_pending(f"node {self.name} is lost")

    def shutdown(self, timeout: float = 10.0) -> None:
        """Have the controller stop the executor (modules stop in reverse order), or kill
        it if the node was lost; then close the connections."""
        with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
            self.controller.call("stop_executor", timeout + 5.0, config=self.config,
                                 force=self.lost)
        self.close()

    def close(self) -> None:
        self.controller.close()
        if self.client is not None:
            self.client.close()


def _forwarding(op: str) -> Any:
    def method(self: RemoteNode, *args: Any, **kwargs: Any) -> Any:
        return self._forward(op, *args, **kwargs)
    method.__name__ = method.__qualname__ = op
    method.__doc__ = f"``Executor.{op}`` at the remote node."
    return method


for _op in OPERATIONS:
    setattr(RemoteNode, _op, _forwarding(_op))
