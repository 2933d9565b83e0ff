"""Faults to inject into a running system whose nodes run on this machine: a worker
killed, a node frozen as if its cable were cut. ``pb3a stress`` and the soak use them.

Both act on processes by id, so they refuse anything not on this machine: a worker is
killed only if it runs here and is one of PB3A's (started from a forkserver); a node
is frozen only if its node controller listens on an address of this machine.
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
import random
import signal
from collections.abc import Collection
from dataclasses import dataclass

import psutil

from pb3a.config.plan import Plan
from pb3a.launch.handle import SystemHandle
from pb3a.transport.addresses import host_of


@dataclass(frozen=True)
class Kill:
    """A worker killed: which, where, and the modules it ran."""

    worker: str
    pid: int
    node: str
    modules: tuple[str, ...]


def kill_worker(system: SystemHandle, plan: Plan, rng: random.Random,
                among: Collection[str]) -> Kill | None:
    """SIGKILL the worker of a module picked at random from ``among``, on a node of this
    machine; None when no such worker runs now. Its modules come back by their
    ``restart`` policy."""
    local = {name for name, node in plan.nodes.items() if node_is_here(node.address)}
    stats = system.stats()
    candidates = sorted(name for name, module in stats.modules.items()
                        if name in among and module.pid and module.node in local)
    while candidates:
        name = candidates.pop(rng.randrange(len(candidates)))
        module = stats.modules[name]
        if _forked_by_pb3a(module.pid):
            with contextlib.suppress(ProcessLookupError):
                os.kill(module.pid, signal.SIGKILL)
                return Kill(module.worker, module.pid, module.node,
                            tuple(sorted(m for m, s in stats.modules.items()
                                         if s.worker == module.worker)))
    return None


class Freeze:
    """A node's controller, executor and workers stopped with SIGSTOP until ``thaw()``:
    to the other nodes, its cable is cut (nothing answers; its TCP connections stay
    open, as they do until a timeout across a cut cable). A context manager: leaving
    the block thaws it."""

    def __init__(self, plan: Plan, node: str) -> None:
        spec = plan.nodes.get(node)
        if spec is None:
            raise ValueError(f"there is no node {node!r}; the nodes: {', '.join(plan.nodes)}")
        if not spec.address:
            raise ValueError(f"node {node!r} has no address: it runs inside the launcher, "
                             "which cannot be cut from itself; give it a node controller "
                             "(pb3a node start) on this machine")
        if not node_is_here(spec.address):
            raise ValueError(f"node {node!r} is at {spec.address}, not on this machine: only "
                             "a node on this machine can be cut")
        self.node = node
        self._address = spec.address
        self._frozen: list[psutil.Process] = []

    @property
    def frozen(self) -> bool:
        """True from ``freeze`` to ``thaw``."""
        return bool(self._frozen)

    def freeze(self) -> list[int]:
        """Stop the node's processes (the controller first, so it starts nothing new);
        returns their ids."""
        controller = _listening(self._address)
        if controller is None:
            raise ValueError(f"no process on this machine listens at {self._address} "
                             f"(node {self.node!r}'s controller)")
        for process in [controller, *controller.children(recursive=True)]:
            with contextlib.suppress(psutil.NoSuchProcess):
                process.send_signal(signal.SIGSTOP)
                self._frozen.append(process)
        return [process.pid for process in self._frozen]

    def thaw(self) -> None:
        """Let the node's processes run again."""
        for process in reversed(self._frozen):
            with contextlib.suppress(psutil.NoSuchProcess):
                process.send_signal(signal.SIGCONT)
        self._frozen.clear()

    def __enter__(self) -> Freeze:
        self.freeze()
        return self

    def __exit__(self, *exc: object) -> None:
        self.thaw()


def node_is_here(address: str | None) -> bool:
    """True for a node in the launcher (no address) or at an address of this machine."""
    if not address:
        return True
    host = host_of(address).strip("[]")
    if host in ("localhost", "*"):
        return True
    with contextlib.suppress(ValueError):
        if ipaddress.ip_address(host).is_loopback:
            return True
    return any(entry.address == host for entries in psutil.net_if_addrs().values()
               for entry in entries)


def _listening(address: str) -> psutil.Process | None:
    port = int(address.rpartition(":")[2])
    for connection in psutil.net_connections(kind="tcp"):
        if connection.status == psutil.CONN_LISTEN and connection.laddr.port == port \
                and connection.pid:
            return psutil.Process(connection.pid)
    return None


def _forked_by_pb3a(pid: int) -> bool:
    """A worker is the child of a multiprocessing forkserver (and has its command line)."""
    with contextlib.suppress(psutil.Error):
        return "forkserver" in " ".join(psutil.Process(pid).cmdline())
    return False
