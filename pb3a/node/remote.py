"""``RemoteNode``: a node whose executor runs elsewhere, started by its node controller.

It implements ``Node`` as the in-process ``Executor`` does, forwarding each
operation as one authenticated request to the node's executor process
(``pb3a.daemons.node_share``), which applies it to its own ``Executor``. Beside the
operations it offers what only a remote node needs: heartbeats, its controller's
health, its measured round-trip times, and being declared lost.

Its heartbeats also renew the executor's lease: an executor that hears none for
``LEASE_S`` fences itself (stops its modules and exits). The launcher declares a node
lost only after ``LOSS_S`` without an answer, and ``LEASE_S`` plus a heartbeat and the
executor's own check interval stay below it, so a cut-off executor has stopped
before its modules are started anywhere else. The heartbeats have a connection of their
own, so that a large state crossing to or from the node (in pieces of ``PIECE``) holds
none of them up.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import threading
import time
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from pb3a.config.description import DEFAULT_SPARES
from pb3a.deadline import before_answer, capped, left, lifted
from pb3a.errors import RuntimeFailure, RuntimeTimeout
from pb3a.loading.sources import CodeSources
from pb3a.transport.addresses import connection_failure, host_of, loopback, unresolved
from pb3a.transport.auth import ClusterKey
from pb3a.transport.control import GONE_S, ControlClient
from pb3a.transport.pickling import PYTHON
from pb3a.worker.lease import GONE_BY_S

if TYPE_CHECKING:
    from pb3a.config.plan import FlatLink, FlatModule
    from pb3a.logbook import LogEntry
    from pb3a.node.protocol import Endpoint, Reached
    from pb3a.node.ring_sizes import RingSize
    from pb3a.stats import NodeReport
    from pb3a.transport.snapshot import Snapshot

log = logging.getLogger("pb3a.launcher")

CONNECT_TIMEOUT = 5.0      # a node controller answers a ping at once, or is not there
PROBE_S = 1.0              # ... and then a plain connection there tells why it did not
# A controller's port refused this long is one nothing listens on (not started, or
# listening elsewhere), said then, not once the ping's CONNECT_TIMEOUT has run out; one
# restarted (by systemd, say) as the launch begins listens again sooner.
REFUSED_S = 2.0
START_TIMEOUT = 60.0       # an executor process imports numpy and friends first
CALL_TIMEOUT = 60.0        # the executor's own requests to its workers have deadlines
MARGIN_S = 5.0             # beyond an operation's own deadline: the way there and back
PIECE = 16 * 2**20         # a snapshot carried to or from another machine goes in pieces
HEARTBEAT_S = 0.25         # how often the launcher's side pings the executor
LEASE_S = 1.25             # an executor that hears no renewal this long fences itself
LOSS_S = 2.0               # no answer for this long: the node is lost (measured 2.0-2.1 s)
SILENT_S = 2 * HEARTBEAT_S  # two heartbeats unanswered: the node is silent (not asked for
#                             figures, its modules shown as its last report had them)
# Every heartbeat renews the lease, but only from the newest answer the launcher heard
# (``NodeShare.renew``): once the node's answers stop, renewals extend nothing, and the
# lease runs out a heartbeat and a lease after its last answer, before the node is
# declared lost, even when heartbeats still reach it but its answers do not (a saturated
# uplink): LOSS_S > HEARTBEAT_S + LEASE_S. (Renewals used to stop once its answers were
# 0.75 s old: after a cut of 0.3 s only pings went, and the lease ran out, or its
# workers', before a renewal from a fresh answer reached it.)
# (a fenced node's workers are gone by GONE_BY_S after the lease's end: before the
# launcher, which declares the node lost LOSS_S after its last answer, starts them)
assert LOSS_S - HEARTBEAT_S - LEASE_S > GONE_BY_S
# What becomes of the modules of a node that does not answer (cut off, frozen) as the
# system stops: said where its stop is not confirmed
ON_THEIR_OWN = (f"within {HEARTBEAT_S + LEASE_S:g} s of its last answer (its lease), a "
                f"teardown still running {GONE_BY_S:g} s later cut short")
# A shutdown out of time still gives the executor this long to stop on its own (SIGTERM:
# it stops its workers, which a kill would leave stepping until their lease ran out) ...
STOP_GRACE_S = 0.25
# ... and its controller this long beyond it to answer that it did: the kill of one that
# did not, the reaping of what it left, and the answer's way back. (It had 0.25 s: on a
# loaded machine the answer came later, up to 0.4 s after the request with two busy CPUs,
# and the close named an executor that had stopped as unconfirmed.) A controller that
# answers takes what it needs, no more: this is paid only for one that does not.
STOP_ANSWER_S = 0.75
STOP_AT_LEAST_S = STOP_GRACE_S + STOP_ANSWER_S
# A lost node's controller is asked (to kill its executor) at least a moment (sent with
# no time at all, the request was never sent) and at most this long: one that answers
# does so at once, and the executor of one that does not has fenced itself (a stop with
# a robot lost waited for its controller the whole shutdown, 10 s)
STOP_LOST_AT_LEAST_S = 0.5
STOP_LOST_S = 1.5


def _start_command(node: str, address: str) -> str:
    """The command that starts node ``node``'s controller at ``address``."""
    return f"pb3a node start --name {node} --listen {address}"


def _gone_during_start(node: str, address: str, reason: str) -> RuntimeFailure:
    """The error of a start whose node controller went away as it was asked (``reason``:
    how its connection ended)."""
    return RuntimeFailure(f"its node controller went away during the start: {reason}; once "
                          f"it runs again ({_start_command(node, address)}), launch again")


def _restarted_again(node: str, address: str, config: str) -> RuntimeFailure:
    """The error of a start whose node controller restarted during it a second time,
    asked again once it had restarted the first time."""
    return RuntimeFailure(
        f"node {node}: its node controller at {address} restarted during the start of "
        f"the executor for {config!r}, and again as it was asked once more (another "
        "process listened there each time): one that ends as it starts an executor and is "
        "started again (by systemd, say) does so; its log (journalctl -u pb3a-node) says "
        "why it ended: once it stays up, launch again")


def _named_otherwise(node: str, address: str, pong: Any) -> str | None:
    """What to say when the node controller at node ``node``'s ``address`` answered its
    ping (``pong``) with another name (its ``--name``), or None. A controller's name is
    a label (of its log and refusals): its executors run as the node the configuration
    names, so a mismatch is no error, but it is how two robots' addresses swapped in a
    file look, each robot's drivers then run on the other (it ran with no word said). A
    controller that answers no name (an older one) is not judged."""
    named = pong.get("node") if isinstance(pong, dict) else None
    if not isinstance(named, str) or named == node:
        return None
    return (f"node {node}'s address {address} is node controller {named!r} (its --name): "
            f"if that machine is not node {node}'s, fix [nodes.{node}] address (two nodes' "
            f"addresses swapped?); if it is, start its controller with --name {node} (its "
            f"executor runs as node {node} either way)")


def _unanswered(node: str, address: str) -> str:
    """What to do about a node controller that did not answer at ``address``, told by a
    plain TCP connection there: refused (nothing listens on that port there: not
    started, or listening elsewhere, 127.0.0.1 say), not answered (the machine off, cut
    off, a firewall, or the wrong address), or accepted (something that is no node
    controller, or one that is frozen). It said "start one there" in all three cases,
    also to someone whose controller ran, on 127.0.0.1 only."""
    host, _, port = address.removeprefix("tcp://").rpartition(":")
    start = _start_command(node, address)
    failure = connection_failure(address, PROBE_S)
    if isinstance(failure, ConnectionRefusedError):
        # (a loopback host is the one address such a controller listens on: "one that
        # listens on 127.0.0.1 is not reached there" was said of 127.0.0.1 itself)
        elsewhere = "" if loopback(host) else (
            "; one that listens on 127.0.0.1, or on another of that machine's addresses, "
            "is not reached there (`ss -ltn` on that machine shows where it listens)")
        return (f"nothing listens on port {port} at {host} (the connection was refused): "
                f"start a node controller there ({start}), or fix the port{elsewhere}")
    if failure is not None:
        why = ("no answer" if isinstance(failure, TimeoutError)
               else failure.strerror or str(failure))
        return (f"{host} did not answer on port {port} ({why}): check that the machine is "
                f"up and on this network, that {host} is its address, and that a firewall "
                f"lets port {port} through")
    return (f"something accepts connections on port {port} at {host}, but does not answer "
            f"as a node controller: check that it is one ({start}), and that it runs "
            "(not stopped or hung)")


class RemoteNode:
    """The executor of node ``name``, reached through the controller at ``address``."""

    def __init__(self, name: str, address: str, *, config: str, launcher: str,
                 workers: int = 0, cpus: list[int] | None = None, checkpoint_s: float = 1.0,
                 log_level: int = 30, code: CodeSources | None = None,
                 advertise: str | None = None,
                 epoch: int = 0, node_epoch: int = 1, spares: int = DEFAULT_SPARES) -> None:
        self.name, self.config = name, config
        self.node_epoch = node_epoch        # 1, then one more each time the node rejoins
        key = self._key = ClusterKey.load()
        self.controller = ControlClient(key, address)
        self.client: ControlClient | None = None
        # the heartbeats' own connection to the executor: over the one the operations
        # use, a heartbeat queued behind each 16 MiB piece of a snapshot, on the way and
        # as the launcher read the answers (over a 100 Mbit/s link, 1.3 s a piece: a 40
        # MiB state moved there had the node lost, and fenced)
        self.heart: ControlClient | None = None
        self.lost = False
        # how its executor ended, once its controller has said that it and every process
        # it started have (``executor_ended``): nothing of it runs a module any more
        self.ended: str | None = None
        self.refusal = ""                   # why its controller refused us last, if it did
        self.rtt = float("nan")             # of the last answered heartbeat
        self._answered = time.monotonic()
        # the newest renewal's answer heard (the executor's clock): what it dates the
        # lease from (``_beat``); when it was heard, and when the one the newest
        # renewal sent carried was (this clock): see fenced_by
        self._heard = -math.inf
        self._heard_at = self._renewed_from = time.monotonic()
        self._renewing = threading.Lock()
        self._closed = threading.Event()
        self._hearts: list[threading.Thread] = []
        self._domain: str | None = None
        self._ends_by = math.inf            # (monotonic) no call waits past it: see wind_down
        self.stopped = False                # its controller confirmed the executor's stop
        self.executor: str | None = None    # its executor's address, once started
        # where the other nodes reach its executor and publications
        host = advertise or host_of(address)
        unknown = unresolved(address)      # (said at once, not after the ping's wait)
        if unknown:
            self.close()
            raise RuntimeFailure(f"node {name}: its address {address} names a host that "
                                 f"does not resolve ({unknown}): fix the node's address (a "
                                 "name the launcher's machine resolves, or an IP address)")
        # The start goes through a connection of its own, watched: a controller that
        # goes away meanwhile (stopped, killed, its machine shut down) fails the start a
        # second after, saying so, where it was waited for until the launch's timeout
        # and said to be slow, or taken for one whose executor cannot be reached. One
        # started again at once at its address (within that second: a supervisor that
        # restarts it with no delay, `systemctl restart` as the launch began) is asked
        # again, once: the executor the one before started ended with it (its parent's
        # pipe closed), or, not bound by any launcher, runs no module and stops on its
        # own (UNBOUND_S), so none of the system's modules runs twice. Its start was lost
        # with it: the launch waited out its timeout and said the executor was slow
        restarted = False
        while True:
            starting = ControlClient(key, address, when_gone=functools.partial(
                self._controller_gone, address))
            try:
                executor = self._start(starting, address, restarted=restarted,
                                       config=config, launcher=launcher, workers=workers,
                                       cpus=cpus, checkpoint_s=checkpoint_s,
                                       log_level=log_level, code=code, host=host,
                                       epoch=epoch, node_epoch=node_epoch, spares=spares)
            finally:
                starting.close()
            if executor is not None:
                break
            restarted = True
            log.warning("node %s: its node controller at %s restarted during the start of "
                        "the executor for %r (another process listens there now): asked "
                        "again", name, address, config)
        self.address = executor
        # (bind renewed the lease; its answer, ``_heard``, came before this)
        self._answered = self._heard_at = self._renewed_from = time.monotonic()
        self._hearts = [threading.Thread(target=self._beat, args=(offset,), daemon=True,
                                         name=f"pb3a-heartbeat-{name}")
                        for offset in (HEARTBEAT_S, 2 * HEARTBEAT_S)]
        for heart in self._hearts:
            heart.start()

    def _start(self, starting: ControlClient, address: str, *, restarted: bool,
               config: str, launcher: str, workers: int, cpus: list[int] | None,
               checkpoint_s: float, log_level: int, code: CodeSources | None, host: str,
               epoch: int, node_epoch: int, spares: int) -> str | None:
        """Have the controller at ``address`` (asked through ``starting``) start the
        executor, reach it and bind it to ``launcher``: its address; ``RuntimeFailure``
        or ``RuntimeTimeout`` saying why not, with nothing of it left running. None if
        the controller restarted meanwhile (``starting.replaced``), unless it had
        restarted during this launch's start before (``restarted``): the start is to
        be asked of it again."""
        name = self.name
        pinged = threading.Event()
        watch = threading.Thread(target=self._fail_if_refused, args=(starting, address, pinged),
                                 name=f"pb3a-refused-{name}", daemon=True)
        watch.start()
        try:
            pong = starting.call("ping", CONNECT_TIMEOUT)
        except RuntimeTimeout:
            self.close()
            raise RuntimeTimeout(f"node {name}: no node controller answered at {address} "
                                 f"within {CONNECT_TIMEOUT:g} s; "
                                 f"{_unanswered(name, address)}") from None
        except RuntimeFailure as exc:
            self.close()
            raise RuntimeFailure(f"node {name}: {exc}") from None
        finally:
            pinged.set()
            watch.join(PROBE_S)
        if (otherwise := _named_otherwise(name, address, pong)) is not None:
            log.warning("%s", otherwise)
        started = False
        try:
            executor, started = starting.call("start_executor", START_TIMEOUT, config=config,
                                              workers=workers, cpus=cpus, host=host,
                                              node=name, python=PYTHON)
            self.executor = executor
            self.client = ControlClient(self._key, executor, epoch=epoch)
            # (both connected, and the heartbeats' told whom it talks to, before the bind
            # starts the lease: made after it, over a far link, the connection and that
            # first exchange took longer than the lease)
            self.heart = ControlClient(self._key, executor, epoch=epoch)
            reached = (not starting.gone.is_set()
                       and self.client.ping(CONNECT_TIMEOUT) is not None
                       and self.heart.ping(CONNECT_TIMEOUT) is not None)
            if reached:
                self._heard = self.client.call("bind", launcher=launcher, checkpoint_s=checkpoint_s,
                                 log_level=log_level, code=code or CodeSources(),
                                 epoch=epoch, node_epoch=node_epoch, lease_s=LEASE_S,
                                 spares=spares)
        except BaseException as exc:       # (Ctrl-C too: nothing started is left running)
            failed = isinstance(exc, (RuntimeFailure, RuntimeTimeout))
            if failed and starting.replaced and not restarted:
                self._drop_executor()       # (it ended with the controller before)
                return None
            # (the controller gone, its executor ended with it: a stop asked through it
            # was waited for by nothing)
            self._let_go(started and not starting.gone.is_set())
            if not failed:
                raise
            if starting.replaced:
                raise _restarted_again(name, address, config) from None
            raise RuntimeFailure(f"node {name} at {address} did not start an executor for "
                                 f"{config!r}: {exc}") from None
        if reached:
            return executor
        # (an executor ends with its controller: one that went once it had answered
        # took its executor with it, which is then reached nowhere). Told by its watched
        # connection, not by a ping that a controller slow to answer (a starved CPU)
        # also leaves unanswered, and which then called it gone with its executor
        gone = starting.gone.wait(GONE_S + PROBE_S)
        if gone and starting.replaced and not restarted:
            self._drop_executor()
            return None
        self._let_go(started and not gone)
        if gone and starting.replaced:
            raise _restarted_again(name, address, config)
        if gone:
            raise RuntimeFailure(
                f"node {name}: its node controller at {address} went away during the start "
                f"(it no longer answers, and the executor it started for {config!r} ended "
                f"with it); once it runs again ({_start_command(name, address)}), launch "
                "again")
        # its controller answers, but the executor is not where it is reached
        raise RuntimeFailure(
            f"node {name}: its executor did not answer within {CONNECT_TIMEOUT:g} s at "
            f"{executor}, on the host other nodes reach node {name} at ({host}); make "
            f"[nodes.{name}] advertise an address of that machine which this one and the "
            "other nodes reach, and open its ports to them")

    def _fail_if_refused(self, starting: ControlClient, address: str,
                         pinged: threading.Event) -> None:
        """Fail the ping that ``starting`` waits for at ``address`` if the port stays
        refused for ``REFUSED_S``, saying so (ZeroMQ tries again and again, and tells
        nobody: a mistaken port was said after the ping's 5 s, and its probe's);
        nothing once the ping is answered, or if the port is not refused (a host that does
        not answer is waited for)."""
        deadline = time.monotonic() + REFUSED_S
        while isinstance(connection_failure(address, PROBE_S), ConnectionRefusedError):
            if time.monotonic() >= deadline:
                starting.fail_pending(RuntimeFailure(
                    f"no node controller at {address}; {_unanswered(self.name, address)}"))
                return
            if pinged.wait(REFUSED_S / 10):
                return

    def _controller_gone(self, address: str, reason: str) -> RuntimeFailure:
        """The error of the start's calls, its node controller gone (``reason``); the
        calls waiting on the executor it started fail with it, the executor having ended
        with its controller: they waited out their deadline (the ping of one that was
        never reached, 5 s) before the launch looked at the controller (socket thread)."""
        error = _gone_during_start(self.name, address, reason)
        for client in filter(None, (self.client, self.heart)):
            client.fail_pending(error)
        return error

    def _drop_executor(self) -> None:
        """Forget the executor of a start whose controller restarted: it ended with the
        controller that started it, and is asked of the new one."""
        for client in filter(None, (self.heart, self.client)):
            client.close()
        self.client = self.heart = self.executor = None

    def _let_go(self, started: bool) -> None:
        """A start that failed: kill the executor if this launch started it (not bound, it
        must not run on); one that ran already is another launch's, and is left alone."""
        if started:
            self.lost = True                           # (shutdown then kills it)
            self.shutdown()
        else:
            self.close()

    def _forward(self, op: str, *args: Any, within: float = CALL_TIMEOUT, **kwargs: Any) -> Any:
        """Apply ``op`` at the executor; an operation with a deadline of its own gets
        that, plus ``MARGIN_S`` for the way there and back. Under the deadline of a
        call in progress (``pb3a.deadline``) no longer than what is left of it, and the
        executor's own waits end ``_way_back`` before."""
        if self.lost or self.client is None:
            raise RuntimeFailure(f"node {self.name} is lost")
        within = self._within(capped(within))
        return self.client.call("executor", within, method=op, args=args, kwargs=kwargs,
                                within=within, **_bound(within))

    def wind_down(self, deadline: float) -> None:
        """No call to this node waits past ``deadline`` (monotonic) from now on: the
        system is being shut down within a time, and a node that does not answer fences
        itself once the heartbeats stop."""
        self._ends_by = deadline

    def _within(self, seconds: float) -> float:
        return max(0.0, min(seconds, self._ends_by - time.monotonic()))

    # -- Node ------------------------------------------------------------------
    def expect(self, specs: list[FlatModule]) -> None:
        self._forward("expect", specs)

    def spawn_workers(self, specs: list[FlatModule]) -> None:
        self._forward("spawn_workers", specs)

    def release_workers(self, specs: list[FlatModule]) -> None:
        self._forward("release_workers", specs)

    def add_module(self, spec: FlatModule, *,
                   state: dict[str, Any] | bytes | None = None) -> None:
        self._forward("add_module", spec, state=state)

    def start_modules(self, names: list[str], failing: bool = False,
                      leave_late: bool = False) -> None:
        # not one of the executor's requests taken one at a time: the modules' setup
        # may ask about this node meanwhile (an agent's ``self.runtime``)
        if self.lost or self.client is None:
            raise RuntimeFailure(f"node {self.name} is lost")
        within = self._within(capped(CALL_TIMEOUT))
        try:
            self.client.call("start", within, names=names, failing=failing,
                             leave_late=leave_late, **_bound(within))
        except RuntimeTimeout as exc:
            if not leave_late or getattr(exc, "late", None) is not None:
                raise
            # no answer in time: the executor may have left the starts to finish (its
            # answer saying so was late), so they are taken to go on there, never put
            # back beside themselves
            exc.late = list(names)              # type: ignore[attr-defined]
            raise

    def call_module(self, name: str, op: str, timeout: float, /, **args: Any) -> Any:
        return self._forward("call_module", name, op, timeout, within=timeout + MARGIN_S,
                             **args)

    def await_restart(self, name: str, timeout: float) -> bool:
        # beside the executor's requests, not one of them: the restart takes its lock
        if self.lost or self.client is None:
            return False
        timeout = self._within(timeout)
        try:
            return self.client.request("await_restart", {"name": name, "timeout": timeout},
                                       timeout + MARGIN_S)
        except (RuntimeFailure, RuntimeTimeout):    # (the request it follows said why)
            return False

    def swap(self, name: str, spec: FlatModule) -> tuple[list[str], list[str]]:
        kept, dropped = self._forward("swap", name, spec)
        return kept, dropped

    def retime(self, name: str, period: float, timeout: float) -> None:
        self._forward("retime", name, period, timeout, within=timeout + MARGIN_S)

    def learn_period(self, name: str, timeout: float) -> float | None:
        return self._forward("learn_period", name, timeout, within=timeout + MARGIN_S)

    def pause(self, name: str, timeout: float, rewire: bool = False) -> bool:
        return self._forward("pause", name, timeout, rewire, within=timeout + MARGIN_S)

    def resume(self, name: str) -> None:
        with lifted():                  # (whatever the call's time: see Executor.resume)
            self._forward("resume", name)

    def stop_module(self, name: str, timeout: float) -> None:
        self._forward("stop_module", name, timeout, within=timeout + MARGIN_S)

    def kill_module(self, name: str) -> int:
        return self._forward("kill_module", name)

    def remove_module(self, name: str) -> None:
        self._forward("remove_module", name)

    def fail_module(self, name: str, reason: str) -> None:
        self._forward("fail_module", name, reason)

    def memory_domain(self) -> str:
        if self._domain is None:                # (it does not change: asked once)
            self._domain = self._forward("memory_domain")
        return self._domain

    def reserve(self, name: str, timeout: float) -> str:
        return self._forward("reserve", name, timeout, within=timeout + MARGIN_S)

    def retire(self, name: str, segment: str, carry: bool) -> Snapshot:
        """The executor captures into ``segment`` on its machine; carried, the parts come
        back in pieces of at most ``PIECE`` bytes: a control message is bounded, and a
        66 MiB state in one answer broke the connection the heartbeats then shared, the
        node was taken for lost and the module with it."""
        snapshot: Snapshot = self._forward("retire", name, segment, False)
        if not carry:
            return snapshot
        # Past the fence: the module runs nowhere, and the launcher must hold its state
        # whatever the caller's time left (a node lost meanwhile fails these at once).
        with lifted():
            carried = tuple(b"".join(self._forward("read_snapshot", segment, at + offset,
                                                   min(PIECE, size - offset))
                                     for offset in range(0, size, PIECE))
                            for at, size in snapshot.parts)
        return replace(snapshot, segment="", carried=carried)

    def land(self, name: str, snapshot: Snapshot) -> float:
        """A carried snapshot goes in pieces (see ``retire``) into a segment staged on the
        executor's machine, which its landing unlinks (or this, if a piece fails)."""
        if not snapshot.carried:
            return self._forward("land", name, snapshot)
        segment = ""
        try:
            for (at, size), part in zip(snapshot.parts, snapshot.carried, strict=True):
                for offset in range(0, size, PIECE):
                    segment = self._forward("write_snapshot", segment, snapshot.end,
                                            at + offset, part[offset:offset + PIECE])
        except BaseException:
            if segment:
                with contextlib.suppress(RuntimeFailure, RuntimeTimeout), lifted():
                    self._forward("release", segment)
            raise
        return self._forward("land", name, replace(snapshot, segment=segment, carried=(),
                                                   staged=True))

    def read_snapshot(self, segment: str, offset: int, size: int) -> bytes:
        return self._forward("read_snapshot", segment, offset, size)

    def write_snapshot(self, segment: str, size: int, offset: int, data: bytes) -> str:
        return self._forward("write_snapshot", segment, size, offset, data)

    def release(self, segment: str) -> None:
        self._forward("release", segment)

    def forget(self, module: str) -> None:
        self._forward("forget", module)

    def connect(self, links: list[FlatLink]) -> None:
        self._forward("connect", links)

    def detach(self, links: list[FlatLink]) -> None:
        self._forward("detach", links)

    def ready_to_publish(self, name: str) -> None:
        self._forward("ready_to_publish", name)

    def publish(self, links: list[FlatLink]) -> list[Endpoint]:
        return self._forward("publish", links)

    def unpublish(self, links: list[FlatLink]) -> list[Reached]:
        return self._forward("unpublish", links)

    def unacknowledged(self, link: FlatLink, reader: bytes) -> int:
        return self._forward("unacknowledged", link, reader)

    def open_inbound(self, links: list[tuple[FlatLink, RingSize | None]]) -> None:
        self._forward("open_inbound", links)

    def follow(self, links: list[tuple[FlatLink, Endpoint]]) -> None:
        self._forward("follow", links)

    def close_inbound(self, links: list[tuple[FlatLink, Reached]]) -> list[int]:
        return self._forward("close_inbound", links)

    def report(self, timeout: float) -> NodeReport:
        # beside the executor's requests, not one of them (as ``start``): a look waits for
        # no change (a move pausing a module here held the node's report up until the
        # pause was done: its modules came silent)
        if self.lost or self.client is None:
            raise RuntimeFailure(f"node {self.name} is lost")
        within = self._within(capped(timeout + MARGIN_S))
        return self.client.request("report", {"timeout": timeout, **_bound(within)}, within)

    def worker_pids(self) -> list[int]:
        return self._forward("worker_pids")

    # -- what only a remote node has ------------------------------------------------
    def _beat(self, offset: float) -> None:
        """One of two heartbeats, each every ``2 * HEARTBEAT_S`` (that long for its
        answer), the second ``HEARTBEAT_S`` after the first: a heartbeat lost, or its
        answer, holds up no other. Each renews the executor's lease; an answer is
        noted. A renewal that carried an answer older than two heartbeats (the first
        through after a cut) extends the lease little: it is renewed again at once,
        from its own answer (a cut of 0.3-0.6 s fenced the node, or restarted its
        modules, before the next heartbeat came)."""
        due = time.monotonic() + offset
        while not self._closed.wait(max(0.0, due - time.monotonic())) and not self.lost:
            due += 2 * HEARTBEAT_S
            stale = self._renew()
            if stale and not self._closed.is_set() and not self.lost:
                self._renew()

    def _renew(self) -> bool:
        """Renew the lease from the newest answer heard; whether it was answered, and
        the answer it carried was more than two heartbeats older than this one's."""
        assert self.heart is not None
        with self._renewing:       # (the two heartbeats: the newest carries the newest)
            since, self._renewed_from = self._heard, self._heard_at
        sent = time.monotonic()
        try:
            # (the executor dates its lease from ``since``, however late it reads this;
            # see NodeShare.renew)
            heard = self.heart.call("lease", 2 * HEARTBEAT_S, since=since)
        except (RuntimeFailure, RuntimeTimeout):
            return False
        self._answered = time.monotonic()
        self.rtt = self._answered - sent
        with self._renewing:
            if heard > self._heard:
                self._heard, self._heard_at = heard, self._answered
        return heard - since > 2 * HEARTBEAT_S

    def fenced_by(self) -> float:
        """When (monotonic) the executor has fenced itself at the latest, if the launcher
        renews its lease from no newer answer: the lease runs at most a heartbeat and a
        lease from the answer the newest renewal carried, which left the executor
        before the launcher heard it (``NodeShare.renew``). Its modules may run
        elsewhere from then on. (Counted from the newest renewal sent, it moved on with
        every heartbeat sent to a node that no longer answered.) Now, once its
        controller has said that the executor ended and its every process with it."""
        if self.ended is not None:
            return -math.inf
        return self._renewed_from + HEARTBEAT_S + LEASE_S

    def silent_s(self) -> float:
        """Seconds since the executor last answered a heartbeat."""
        return time.monotonic() - self._answered

    def executor_ended(self, timeout: float) -> str | None:
        """Ask the node's controller whether the executor has ended (killed, or failed),
        and if it has, to end every process it started: how it ended once they all have
        (also kept in ``ended``); None while it runs, or if the controller does not say
        within ``timeout`` seconds (a node whose machine is gone, or cut off)."""
        if self.executor is None:
            return None
        try:
            how = self.controller.request("executor_ended", {
                "config": self.config, "executor": self.executor,
                "timeout": before_answer(timeout)}, timeout)
        except (RuntimeFailure, RuntimeTimeout):
            return None
        if how is not None:
            self.ended = how
        return how

    def controller_answers(self, timeout: float) -> bool:
        """True if the node's controller answered within ``timeout`` seconds. A lost
        node's is asked on a new connection each time (which its ``stop_executor`` then
        uses): the one made before a cut cable stays in TCP's retransmission backoff
        long after the cable is back, and a node rejoined 8-10 s after it answered."""
        if self.lost:
            stale, self.controller = self.controller, ControlClient(self._key,
                                                                    self.controller.address)
            stale.close()
        answered = self.controller.ping(timeout) is not None
        self.refusal = "" if answered else self.controller.why_refused("ping")
        return answered

    def unloadable(self, refs: dict[str, str], timeout: float, longer: str) -> dict[str, str]:
        """Which of ``refs`` (module name -> ``"module:Class"``) the node's executor cannot
        load, each with why, answered within ``timeout`` seconds (see
        ``pb3a.node.class_check``; ``longer``: how to give it more time)."""
        if self.client is None or self.lost:
            raise RuntimeFailure(f"node {self.name} is lost")
        return self.client.request("unloadable", {
            "refs": refs, "timeout": before_answer(timeout), "longer": longer}, timeout)

    def meet(self, peers: dict[str, str]) -> None:
        """Have the node measure its RTT to each peer (name -> control address)."""
        if self.client is not None and not self.lost:
            self.client.call("peers", peers=peers)

    def rtts(self) -> dict[str, float]:
        """The node's last measured round-trip times to its peers."""
        if self.client is None or self.lost:
            return {}
        return self.client.call("rtts", 2.0)

    def logs(self, since: int) -> list[LogEntry]:
        """What the node logged after its entry ``since``."""
        if self.client is None or self.lost:
            return []
        return self.client.call("logs", 2.0, since=since)

    def lose(self) -> None:
        """The node is gone: every waiting call fails now, and every later one at once."""
        self.lost = True
        for client in filter(None, (self.client, self.heart)):
            client.fail_pending(f"node {self.name} is lost")

    def stop_executor(self, timeout: float = 10.0) -> None:
        """Have the controller stop the executor (modules stop in reverse order), or kill
        it if the node was lost; the controller stays reachable. ``stopped`` says
        whether it confirmed (an executor it could not be told of stops by itself when
        its lease runs out)."""
        # (at least a moment even out of time: sent with no time at all, the request was
        # never sent, and the executor ran on, its node taken for the next launch)
        within = self._within(timeout + 5.0)
        if self.lost:                           # (killed at once: no grace)
            wait = min(max(STOP_LOST_AT_LEAST_S, within), STOP_LOST_S)
            answer = STOP_LOST_AT_LEAST_S / 2
        else:
            wait, answer = max(STOP_AT_LEAST_S, within), STOP_ANSWER_S
        with contextlib.suppress(RuntimeFailure, RuntimeTimeout):   # (killed in time to say so)
            # (naming its executor: a stop delivered late, the machine cut off as it was
            # sent, stops no executor of a later launch)
            self.controller.request("stop_executor", {
                "config": self.config, "force": self.lost, "executor": self.executor,
                "timeout": min(timeout, max(0.0, wait - answer))}, wait)
            self.stopped = True

    def shutdown(self, timeout: float = 10.0) -> None:
        """Stop the executor, then close the connections."""
        self.stop_executor(timeout)
        self.close()

    def close(self) -> None:
        self._closed.set()
        # the clients first: they fail a heartbeat's renewal under way, which an executor
        # stopped a moment ago never answers (the join waited out its 0.5 s at most closes)
        for client in filter(None, (self.heart, self.client)):
            client.close()
        for heart in self._hearts:
            heart.join(1.0)
        self.controller.close()


def _bound(within: float) -> dict[str, float]:
    """What a request under the deadline of a call in progress tells the executor: to end
    its own waits (``bound``) an answer's way back before the launcher stops waiting
    for the answer (``before_answer``); nothing otherwise."""
    if left() is None:
        return {}
    return {"bound": before_answer(within)}
