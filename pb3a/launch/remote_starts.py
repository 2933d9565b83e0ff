"""``RemoteStarts``: a launch's remote nodes starting their executors side by side.

Each node's controller is asked on a thread of its own, so a launch over ten robots
takes about as long as the slowest start rather than the sum of them, and a node that
does not answer holds up no other. The launch waits a bounded time (its timeout);
a start still going on then is given up on, and the thread stops the executor it
still starts once it has it, so that none is left running for a launch that failed.
``not_started`` is the error naming every node that did not start one.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING

from pb3a.errors import RuntimeFailure, RuntimeTimeout
from pb3a.node.remote import CONNECT_TIMEOUT, PROBE_S

if TYPE_CHECKING:
    from collections.abc import Callable

    from pb3a.node.remote import RemoteNode

# beyond the launch's timeout: a thread's last step and its answer's way here
SLACK_S = 1.0
# how long each executor started is given to stop when the launch is interrupted
STOP_S = 3.0


class RemoteStarts:
    """The executors of nodes ``names``, started side by side by ``start(name,
    node_epoch=1)`` (a ``RemoteNode``, or an error naming the node) as soon as this is
    made."""

    def __init__(self, start: Callable[..., RemoteNode], names: list[str],
                 addresses: dict[str, str], timeout: float, longer: str) -> None:
        self._start, self._addresses, self._longer = start, addresses, longer
        self._names = list(names)
        # never shorter than a ping and the probe telling why it was not answered: a
        # node not reached is named with that reason, not as one out of time
        self.timeout = max(timeout, CONNECT_TIMEOUT + PROBE_S)
        self._deadline = time.monotonic() + self.timeout + SLACK_S
        self._lock = threading.Lock()
        self._started: dict[str, RemoteNode] = {}
        self._failed: dict[str, BaseException] = {}
        self._given_up = False
        self._threads = [threading.Thread(target=self._run, args=(name,), daemon=True,
                                          name=f"pb3a-start-{name}") for name in names]
        for thread in self._threads:
            thread.start()

    def _run(self, name: str) -> None:
        try:
            node = self._start(name, node_epoch=1)
        except BaseException as exc:       # (each its node's: all are told together)
            with self._lock:
                self._failed[name] = exc
            return
        with self._lock:
            if not self._given_up:
                self._started[name] = node
                return
        node.shutdown()                    # the launch gave up on it: nothing left running

    def settle(self) -> tuple[dict[str, RemoteNode], dict[str, BaseException]]:
        """Wait for every start, until ``timeout`` (and ``SLACK_S``) after they began: the
        nodes whose executor started, and why each other did not, in the order of
        ``names``. A start not done by then is given up on (its thread stops what it
        starts)."""
        try:
            for thread in self._threads:
                thread.join(max(0.0, self._deadline - time.monotonic()))
        except BaseException:
            # a Ctrl-C: the launch has none of them to stop, so those started are stopped
            # here (they fenced themselves once their leases ran out, saying so as an
            # error in their controllers' logs), and later ones stop themselves
            with self._lock:
                self._given_up = True
                started = list(self._started.values())
            for node in started:
                node.shutdown(STOP_S)
            raise
        with self._lock:
            self._given_up = True                  # (late starts stop themselves)
            started, failed = dict(self._started), dict(self._failed)
        names = self._names
        for name in names:
            if name not in started and name not in failed:
                failed[name] = RuntimeTimeout(
                    f"node {name} at {self._addresses[name]} did not start an executor "
                    f"within {self.timeout:g} s (its controller answers, its executor "
                    f"is slow to start or to answer): {self._longer}")
        return ({name: started[name] for name in names if name in started},
                {name: failed[name] for name in names if name in failed})


def not_started(system: str, remote_nodes: int, failed: dict[str, BaseException]
                ) -> BaseException:
    """The error of a launch in which the nodes ``failed`` (of its ``remote_nodes`` remote nodes)
    did not start an executor: a single node's own error, else one naming each node
    and why, a ``RuntimeTimeout`` if none of them answered in time. An interrupt in a
    start (a ``KeyboardInterrupt`` as it bound its executor) is the launch's."""
    interrupts = [exc for exc in failed.values() if not isinstance(exc, Exception)]
    if interrupts:
        return interrupts[0]
    if len(failed) == 1:
        return next(iter(failed.values()))
    kind = (RuntimeTimeout if all(isinstance(exc, RuntimeTimeout) for exc in failed.values())
            else RuntimeFailure)
    lines = [str(exc) if str(exc).startswith(f"node {name}") else f"node {name}: {exc}"
             for name, exc in failed.items()]
    return kind("\n  ".join([
        f"system {system!r} was not started: {len(failed)} of its {remote_nodes} remote nodes "
        "did not start an executor (no module was started):", *lines]))
