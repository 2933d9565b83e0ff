"""Control requests between PB3A processes on different nodes: authenticated RPC.

A ``ControlClient`` sends ``(op, args)`` to a ``ControlServer`` and waits for the
answer. Every request and reply is sealed with the cluster key and opened (``auth``)
before it is unpickled: an unauthenticated frame is never deserialized. The server
takes requests in on its socket loop and runs them one at a time on a handler thread
(in arrival order, so operations never interleave), except its ``aside`` operations,
each run on a thread of its own: a long one that others must get past (a node's
start, during which an agent's ``setup`` asks about that node); ``ping`` and the server's
``instant`` operations (a node's lease) are answered at once on the socket thread,
so heartbeats are not held up by a long operation. Nor by a request that names a
module not imported yet: the socket thread never imports, it hands such a request to
the handler thread to be read there.

A request carries how long its caller waits for the answer (seconds, relative: the
two machines share no clock). A server made with ``expires`` (a device's:
``pb3a.serve_device``) drops a request it has not begun that long after it came,
answering that it was not done (``Expired``): its caller has given up on it, and may
be asking again (a motor's relative move, retried after a timeout, was made twice).
So does it a request whose caller withdrew it (``WITHDRAW``): a client sends that for
each request it stops waiting for unanswered, and a move, swap or stop of the module
that waited for it ends that wait early (a driver's move, cancelled by its migration,
was carried out once the device was free, and asked again at the destination).
The others run every request they take in: their operations carry deadlines of their
own (``within``, ``bound``), and some are worth doing however late (a node's events,
a stop).

A request names the server it is for: a random id each server draws when it starts
(its instance), sealed in with the request. A client learns it from the server's
signed answer to its first request (``INSTANCE``: this is who I am, send it again),
and again after the server restarts. So a request captured on the wire and sent
again is refused by every other server holding the cluster key, and by a server
started anew at the same address, besides the replay check of the one it was for.

A request the server cannot open is answered with a plain refusal that names the
check it failed (another cluster key, clocks apart, an older run), at most once a
second per connection; it carries nothing else and is only ever used to word the
client's error, so that a wrong key is told apart from a server that does not answer at
all. The server logs such a refusal at most once a minute per peer address and once a
second in all, and counts the rest in a summary line every 10 s.
"""

from __future__ import annotations

import collections
import contextlib
import io
import itertools
import logging
import math
import pickle
import queue
import secrets
import socket
import struct
import sys
import threading
import time
import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

import zmq
from zmq.utils.monitor import recv_monitor_message

from pb3a.deadline import spoken
from pb3a.errors import PB3AError, RuntimeFailure, RuntimeTimeout
from pb3a.transport import pickling
from pb3a.transport.addresses import bind_advertised, close_bound, connection_failure, numeric
from pb3a.transport.auth import ClusterKey, Opener, Rejected, Sealer
from pb3a.transport.loop import SocketLoop

if TYPE_CHECKING:
    from collections.abc import Callable, Collection, Mapping

log = logging.getLogger("pb3a.control")

T = TypeVar("T")
REQUEST, REPLY, INSTANCE, WITHDRAW = 10, 11, 12, 13
_NOBODY = bytes(16)                   # the instance a client asks before it knows
_SENDS = 4                            # times a request is sent, to instances it learns
_ID = struct.Struct("<Q")
_WAIT = struct.Struct("<d")            # how long the caller waits for the answer, in s
_REFUSAL = b"PB3A-REFUSED:"            # + the failed check, in plain ASCII
_REFUSAL_EVERY_S = 1.0                # per connection
# A refusal is logged at most this often per peer address, and in all; the refusals not
# logged are counted in a line every _REFUSALS_COUNTED_S (a client that connected anew for
# each request had each logged: 2000 warnings in 0.9 s)
_REFUSAL_LOGGED_PEER_S, _REFUSAL_LOGGED_S, _REFUSALS_COUNTED_S = 60.0, 1.0, 10.0
# What each refusal means to the person who reads the client's error.
_REFUSAL_HINTS = {
    "bad tag": ("it runs with another cluster key: make PB3A_KEY, PB3A_KEY_FILE or "
                "~/.pb3a/cluster.key the same on both machines"),
    "not fresh": "the two machines' clocks differ by more than a minute: synchronise them",
    "stale epoch": "it works for a newer run of this system",
}
_REFUSAL_NAMES = {"bad tag": "another cluster key", "not fresh": "clocks apart"}
# The operations that show which kind of server their sender took an address for, and
# where that one's address is found: a request for one at another kind of server (a
# launcher's address given as a node's) is told so, and where to look
_SENT_TO = {
    **dict.fromkeys(("start_executor", "stop_executor", "admit"),
                    ("a node controller", "give the address its `pb3a node start` printed")),
    "find": ("a module server", "give the address its `pb3a modules serve` printed"),
    "describe": ("a launcher", "give the address `pb3a run` printed"),
}
MAX_MESSAGE = 64 * 1024 * 1024          # control messages carry states and code, not streams
# The largest request or answer sent: the frame's header and tag fit beside it. A frame
# over MAX_MESSAGE makes ZeroMQ drop the connection it came on, which a node's heartbeats
# then shared: reading a module's 66 MiB state had its node declared lost, and the module
# with it. One that large is refused where it is made, saying so, and nothing is dropped.
MAX_PAYLOAD = MAX_MESSAGE - 64 * 1024
DEFAULT_TIMEOUT = 10.0
QUICK_S = 0.5               # a server that is there answers within this, unless far or busy
REFUSED_S = 1.0             # connections refused this long: nothing listens there
_REPROBE_S = 0.1
_WATCHED = zmq.EVENT_CONNECTED | zmq.EVENT_DISCONNECTED | zmq.EVENT_HANDSHAKE_SUCCEEDED
# A server that closed the client's connection, with nothing taking a connection there
# since for this long, is gone (see ``ControlClient``'s ``when_gone``); a server that
# runs takes ZeroMQ's reconnection within milliseconds
GONE_S = 1.0
ANSWER_LINGER_MS = 500                   # how long a closing server gives its last answers
WITHDRAW_LINGER_MS = 200                 # ... and a closing client its last withdrawals
GREET_S = 1.0         # connected this long and never greeted: not a PB3A server
ASIDE_ANSWER_S = 1.0                     # ... and its requests running aside to give theirs


class UnknownOperation(ValueError):
    """A request for an operation the server does not have (raised by its handler): the
    server answers saying what it is, and where such a request goes instead."""

    def __init__(self, op: str, known: Collection[str] = ()) -> None:
        super().__init__(f"unknown operation {op!r}; the operations: {', '.join(sorted(known))}")
        self.op, self.known = op, sorted(known)


def wrong_server(address: str, role: str, op: str) -> str | None:
    """What to say of a request for ``op`` that server ``role`` at ``address`` cannot
    take, if ``op`` shows which kind of server its sender meant; else None."""
    meant = _SENT_TO.get(op)
    if meant is None:
        return None
    return f"{address} is {role}, not {meant[0]}: {meant[1]}"


def _socket(context: zmq.Context, kind: int) -> zmq.Socket:
    sock = context.socket(kind)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.MAXMSGSIZE, MAX_MESSAGE)
    return sock


def _attached(kind: int, attach: Callable[[zmq.Socket], T]) -> tuple[zmq.Socket, T]:
    """A new socket and what ``attach`` (its bind or connect) gives; if that fails (a
    port in use, an address ZeroMQ cannot use), the socket is closed: none left behind."""
    sock = _socket(zmq.Context.instance(), kind)
    try:
        return sock, attach(sock)
    except BaseException:
        sock.close(0)
        raise


class ControlServer:
    """Serves ``handler(op, args) -> result`` on a ROUTER socket bound to ``host``."""

    def __init__(self, key: ClusterKey, handler: Callable[[str, dict[str, Any]], Any],
                 host: str = "127.0.0.1", port: int = 0, *, name: str = "pb3a-control",
                 instant: Mapping[str, Callable[[dict[str, Any]], Any]] | None = None,
                 aside: Collection[str] = (),
                 decode_lock: threading.Lock | None = None, title: str = "the process",
                 import_first: Callable[[str, str], None] | None = None,
                 expires: bool = False) -> None:
        """``decode_lock``: held while a request imports the modules of the classes it
        names (see ``_decode``), by a process that also imports in the background:
        CPython may hand one thread a module another is still importing when the two
        imports go through a circular one. ``title`` is what it is ("node b's
        controller", "the launcher of system 'lab'"): a request it cannot read, for an
        operation it does not have, or of an earlier epoch (from a key holder) is told
        so, to find the mistaken address. ``import_first(module,
        name)``: called before a request imports a module for its class ``name``, to
        refuse it (an ``ImportError``: the request cannot be read) rather than import a
        module that would harm this process (a launcher's, see
        ``pb3a.loading.trial``). ``expires``: a request not begun within the time its
        caller waits, from when it came, is dropped, not done (see above)."""
        self._title = title
        self._expires = expires
        self._handler = handler
        self._aside = frozenset(aside)
        self._asides: set[threading.Thread] = set()     # requests running aside now
        self._decode_lock = decode_lock or contextlib.nullcontext()
        self._import_first = import_first
        # answered on the socket thread, never queued: they must be quick and never block
        self._instant = {"ping": lambda args: "pong", **(instant or {})}
        self._router, self.address = _attached(
            zmq.ROUTER, lambda sock: bind_advertised(sock, host, port))    # (a port in use)
        self._loop = SocketLoop(f"{name}-io", self._router.context)
        # (epoch 0 until ``advance_epoch``: a node share's server moves on with its runs)
        self._sealer = Sealer(key, 0)
        self._opener = Opener(key, epoch=0, max_bytes=MAX_MESSAGE)
        # (whether a request refused for its epoch is a key holder's, told what this is)
        self._any_epoch = Opener(key, epoch=0, max_bytes=MAX_MESSAGE)
        self.instance = secrets.token_bytes(16)      # requests must name it (see above)
        # (peer, request id) of the requests waiting in ``_work``, and those of them their
        # callers withdrew: kept by a server that ``expires`` only
        self._queued: set[tuple[bytes, bytes]] = set()
        self._withdrawn: set[tuple[bytes, bytes]] = set()
        self._queued_lock = threading.Lock()
        # (peer, request id, op, args, when it expires), or with op None the request's
        # pickle, to read
        self._work: queue.SimpleQueue[tuple[Any, bytes, str | None, Any, float] | None] = (
            queue.SimpleQueue())
        self._refused_at: dict[bytes, float] = {}      # peer -> when we last told it
        self._logged_at: dict[str, float] = {}         # peer's address -> when logged
        self._last_logged = -math.inf                  # when a refusal was logged last
        self._unlogged: collections.Counter[str] = collections.Counter()   # by reason
        self._unlogged_since = 0.0             # when the first of them was counted
        self._closed = False
        self._worker = threading.Thread(target=self._serve, name=name, daemon=True)
        self._worker.start()
        self._loop.register(self._router, self._on_request)

    @property
    def rejected(self) -> Any:
        """Frames refused (unauthenticated, malformed, replayed ...), by reason."""
        return self._opener.rejected

    def advance_epoch(self, epoch: int) -> None:
        """Refuse requests of epochs before ``epoch`` from now on; answer in it."""
        self._opener.epoch = max(self._opener.epoch, epoch)
        self._sealer.epoch = self._opener.epoch

    def _on_request(self, router: zmq.Socket) -> None:
        while router.poll(0):
            peer, *frames = router.recv_multipart(copy=False)
            try:
                message = self._opener.open(frames)
                if message.kind == WITHDRAW and len(message.frames) == 1:
                    self._withdraw((bytes(peer), bytes(message.frames[0])))
                    continue
                if message.kind != REQUEST or len(message.frames) != 4 \
                        or len(wait := bytes(message.frames[2])) != _WAIT.size:
                    raise Rejected("unexpected")
            except Rejected as exc:
                self._refuse(peer, exc.reason, frames)
                continue
            request_id, blob = bytes(message.frames[0]), message.frames[3]
            expires = (time.monotonic() + _WAIT.unpack(wait)[0] if self._expires
                       else math.inf)
            if bytes(message.frames[1]) != self.instance:     # for another server, or a
                if bytes(message.frames[1]) != _NOBODY:       # run of this one before:
                    self._opener.rejected["other instance"] += 1      # not run, and
                self._router.send_multipart([peer, *self._sealer.seal(  # who we are said
                    INSTANCE, [request_id, self.instance])])
                continue
            try:
                op, args = _decode(blob, self._decode_lock, may_import=False)
            except _MustImport:
                self._queue(peer, request_id, None, blob, expires)
                continue
            except Exception as exc:
                self._reply_undecodable(peer, request_id, exc)
                continue
            answer = self._instant.get(op)
            if answer is not None:
                self._reply(peer, request_id, True, answer(args))
            elif op in self._aside:
                aside = threading.Thread(target=self._run_aside,
                                         args=(peer, request_id, op, args),
                                         name=f"{self._worker.name}-{op}", daemon=True)
                self._asides.add(aside)
                aside.start()
            else:
                self._queue(peer, request_id, op, args, expires)

    def _queue(self, peer: Any, request_id: bytes, op: str | None, args: Any,
               expires: float) -> None:
        """Hand a request to the handler thread, noting it if it may be withdrawn."""
        if self._expires:
            with self._queued_lock:
                self._queued.add((bytes(peer), request_id))
        self._work.put((peer, request_id, op, args, expires))

    def _withdraw(self, key: tuple[bytes, bytes]) -> None:
        """Its caller gave up on request ``key``: a server that ``expires`` drops it if
        it is still waiting its turn (one begun or answered is not stopped)."""
        with self._queued_lock:
            if key in self._queued:
                self._withdrawn.add(key)

    def _withdrawn_now(self, peer: Any, request_id: bytes) -> bool:
        """Whether the request about to begin was withdrawn (it is no longer queued)."""
        if not self._expires:
            return False
        key = (bytes(peer), request_id)
        with self._queued_lock:
            self._queued.discard(key)
            if key in self._withdrawn:
                self._withdrawn.discard(key)
                return True
        return False

    def _reply_undecodable(self, peer: Any, request_id: bytes, exc: Exception) -> None:
        """A key holder's request that cannot be read still gets an answer, saying why."""
        self._opener.rejected["undecodable"] += 1
        self._loop.submit(lambda: self._reply(
            peer, request_id, False,
            RuntimeFailure(_undecodable(exc, "a request", f"{self._title} at {self.address}"))))

    def _refuse(self, peer: Any, reason: str, frames: list[Any]) -> None:
        """Tell an unauthenticated peer which check failed (rate-limited per peer); a key
        holder refused for its epoch is told what this server is too."""
        if reason not in _REFUSAL_HINTS:
            return                             # garbage gets no answer at all
        who, now = bytes(peer), time.monotonic()
        if now - self._refused_at.get(who, -math.inf) < _REFUSAL_EVERY_S:
            return
        if len(self._refused_at) > 1024:
            self._refused_at.clear()
        self._refused_at[who] = now
        said = reason.encode()
        if reason == "stale epoch" and self._is_authentic(frames):
            said += b":" + self._title.encode()
        self._router.send_multipart([peer, _REFUSAL + said])
        if reason != "stale epoch":         # (a mistake in the set-up, not a fenced peer)
            self._log_refusal(peer, reason, now)

    def _is_authentic(self, frames: list[Any]) -> bool:
        try:
            self._any_epoch.open(frames)
        except Rejected:
            return False
        return True

    def _log_refusal(self, peer: Any, reason: str, now: float) -> None:
        """Log a refusal, or count it for the next summary if one was logged within the
        second, or for this peer's address within the minute."""
        sender = "a peer"
        with contextlib.suppress(zmq.ZMQError, AttributeError, TypeError):
            sender = peer.get("Peer-Address") or sender     # (its IP, on TCP)
        if (now - self._last_logged < _REFUSAL_LOGGED_S
                or now - self._logged_at.get(sender, -math.inf) < _REFUSAL_LOGGED_PEER_S):
            if not self._unlogged:
                self._unlogged_since = now
                self._loop.later(_REFUSALS_COUNTED_S, self._log_unlogged)
            self._unlogged[reason] += 1
            return
        if len(self._logged_at) > 1024:
            self._logged_at.clear()
        self._logged_at[sender], self._last_logged = now, now
        log.warning("%s refused a request from %s: %s", self.address, sender,
                    _REFUSAL_HINTS[reason])

    def _log_unlogged(self) -> None:
        span = math.ceil(time.monotonic() - self._unlogged_since)
        for reason, count in self._unlogged.items():
            log.warning("%s refused %d more request%s (%s) in the last %d s", self.address,
                        count, "s" if count != 1 else "", _REFUSAL_NAMES[reason], span)
        self._unlogged.clear()

    def _serve(self) -> None:
        while (item := self._work.get()) is not None:
            peer, request_id, op, args, expires = item
            if self._withdrawn_now(peer, request_id):
                log.debug("%s dropped a request its caller withdrew", self.address)
                continue                    # (nobody waits for its answer)
            if time.monotonic() >= expires:
                self._drop(peer, request_id, op)
                continue
            if op is None:                 # one the socket thread could not read at once
                try:
                    op, args = _decode(args, self._decode_lock, may_import=True,
                                       first=self._import_first)
                except Exception as exc:
                    self._reply_undecodable(peer, request_id, exc)
                    continue
            self._run(peer, request_id, op, args)

    def _drop(self, peer: Any, request_id: bytes, op: str | None) -> None:
        """Answer a request its caller no longer waits for that it was not done."""
        what = "a request" if op is None else repr(op)
        log.debug("%s dropped %s: not begun within the time its caller waits", self.address,
                  what)
        self._loop.submit(lambda: self._reply(peer, request_id, False, Expired(
            f"{self._title} at {self.address} dropped {what}, not begun within the time its "
            "caller waits (busy with earlier requests): it was not done")))

    def _run_aside(self, peer: Any, request_id: bytes, op: str, args: Any) -> None:
        try:
            self._run(peer, request_id, op, args)
        finally:
            self._asides.discard(threading.current_thread())

    def _run(self, peer: Any, request_id: bytes, op: str, args: Any) -> None:
        """Run one request and send its answer (from the socket thread)."""
        try:
            result, ok = self._handler(op, args), True
        except UnknownOperation as exc:
            result, ok = RuntimeFailure(
                wrong_server(self.address, self._title, op)
                or f"{self._title} at {self.address} has no operation {op!r}"
                + (f"; its operations: {', '.join(exc.known)}" if exc.known else "")), False
        except PB3AError as exc:               # the caller gets the same error
            result, ok = exc, False
        except Exception as exc:
            log.debug("request %s failed", op, exc_info=True)
            result, ok = f"{type(exc).__name__}: {exc}", False
        self._loop.submit(lambda: self._reply(peer, request_id, ok, result, op))

    def _reply(self, peer: Any, request_id: bytes, ok: bool, result: Any,
               op: str = "the request") -> None:
        try:
            blob = pickling.dumps((ok, result))
        except Exception as exc:
            blob = pickling.dumps((False, f"the result could not be pickled: {exc}"))
        if len(blob) > MAX_PAYLOAD:
            blob = pickling.dumps((False, RuntimeFailure(
                f"{op}: its answer is {too_large(len(blob))}, so it was not sent")))
        self._router.send_multipart([peer, *self._sealer.seal(REPLY, [request_id, blob])])

    def __enter__(self) -> ControlServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop serving; on return the port is free, so a server may bind it again.
        Closing again does nothing, but finishes a close a Ctrl-C cut short: it kept
        the port, its thread and sockets until the process ended."""
        if not self._closed:
            self._closed = True
            self._work.put(None)
        if self._router.closed:             # (closed last: the close is over)
            return
        self._worker.join(5.0)
        # a request running aside and about to answer (a follower told the system
        # stopped) gets its answer out; one that goes on longer is left unanswered
        deadline = time.monotonic() + ASIDE_ANSWER_S
        for aside in list(self._asides):
            # (one the socket thread has noted but not started yet is not waited for:
            # joining it raised, and the close was left half done)
            if aside.ident is not None:
                aside.join(max(0.0, deadline - time.monotonic()))
        self._loop.close()                  # (after it sends the answers it was given)
        if self._unlogged:              # (its summary was due later: said now, not lost)
            self._log_unlogged()
        # an answer just sent, such as the one to "shutdown", still reaches its caller
        close_bound(self._router, linger_ms=ANSWER_LINGER_MS)


_import_hints: list[Callable[[str], str]] = []


def too_large(size: int) -> str:
    """``size`` bytes, said against what one control message carries."""
    return (f"{size / 2**20:.1f} MiB, more than one control message carries "
            f"({MAX_PAYLOAD / 2**20:.0f} MiB)")


class TooLarge(RuntimeFailure):
    """A request not sent: it is larger than one control message carries."""


class Expired(RuntimeTimeout):
    """A request its server dropped, not begun within the time its caller waits (a
    server made with ``expires``): it was not done."""


def add_import_hint(hint: Callable[[str], str]) -> None:
    """Have ``hint(module)`` add to what this process says of a request or answer naming
    a module it cannot import (``pb3a.loading.served`` adds why its module servers did
    not give it: one without it, one that did not answer or refused, one whose host
    does not resolve here). Added once."""
    if hint not in _import_hints:
        _import_hints.append(hint)


def _undecodable(exc: Exception, what: str, reader: str) -> str:
    """Why ``what`` (a request, an answer) could not be read by ``reader`` (a
    process), and what to do about it."""
    if isinstance(exc, ModuleNotFoundError):
        return (f"{what} names Python module {exc.name!r}, which {reader} cannot import: "
                "install it on that machine (or put it on its PYTHONPATH), or serve it "
                "from a module server (module_servers in the configuration)"
                + "".join(hint(exc.name or "") for hint in _import_hints))
    return f"{what} could not be read by {reader}: {type(exc).__name__}: {exc}"


class NotListening(RuntimeTimeout):
    """Nothing listens where a server was to be: its port refuses connections, or its
    host has no address here."""


class ControlClient:
    """Calls one ``ControlServer``; ``call`` may be used from any number of threads.

    With ``when_gone``, a server that closes the connection (its process ended, or it
    closed its socket) with nothing taking a connection there again within ``GONE_S``
    fails every call waiting and every later one, with the error ``when_gone`` makes
    of the reason it is given, rather than at each call's deadline; and so does another
    server, started anew at the address (another instance), which the client would
    otherwise have taken for the one it was talking to: asked on each reconnection
    whether it is the same, so that a call whose request went to the one before fails
    then, not at its deadline (``replaced`` says it was another). A server cut off by
    the network closes nothing: its calls still end at their deadlines. A gone server's
    client gives back its thread and sockets then; the calls still fail as said.

    With ``watch_greeting``, a call that times out at an address where something took
    the connection but never greeted in ZeroMQ's protocol says so (``ungreeted``), not
    "nothing listens there": a driver pointed at a legacy program's port.

    A client its owner drops without ``close`` is closed once it is collected (its
    thread holds it only weakly)."""

    def __init__(self, key: ClusterKey, address: str, *, epoch: int = 0,
                 when_gone: Callable[[str], PB3AError] | None = None,
                 watch_greeting: bool = False) -> None:
        self.address = address
        watched = when_gone is not None or watch_greeting

        def connect(dealer: zmq.Socket) -> zmq.Socket | None:
            # (watched before it connects: on loopback the connection was made, and its
            # event gone, before a monitor made after it listened)
            monitor = dealer.get_monitor_socket(_WATCHED) if watched else None
            try:
                dealer.connect(numeric(address))
            except BaseException:
                if monitor is not None:
                    dealer.disable_monitor()
                    monitor.close(0)
                raise
            return monitor
        self._dealer, self._monitor = _attached(zmq.DEALER, connect)
        self._loop = SocketLoop("pb3a-control-client", self._dealer.context)
        self._sealer = Sealer(key, epoch)
        # Replies count only if they answer a request this client is waiting for; the
        # epoch is the server's check (a launcher's server also answers the CLI in 0).
        self._opener = Opener(key, max_bytes=MAX_MESSAGE)
        self._ids = itertools.count(1)
        self._waiting: dict[bytes, tuple[threading.Event, list[Any]]] = {}
        # request id -> [its pickle, times sent, when its caller stops waiting]
        self._sent: dict[bytes, list[Any]] = {}
        self._instance = _NOBODY                    # the server's, once it has said it
        self.refused = ""                    # why the server refused our requests, if it did
        self._refused_by = ""                # what it said it is, with the reason
        self._closed = False
        self._when_gone = when_gone
        self._lost_at: float | None = None   # when the server closed our connection
        self.gone = threading.Event()        # ... and nothing took one there in GONE_S
                                             # (or another server took its place)
        self.gone_why = ""                   # (which of the two, in words)
        self.replaced = False                # (the second: a server started anew there)
        self._greeted = False                       # (told by the monitor, if any)
        self._connected_at: float | None = None     # ... and when it connected
        # The loop holds the client only weakly, and a client dropped unclosed is closed
        # when collected (the loop's thread held its handlers, and through them the
        # client and its sockets, for good: each connection dropped unclosed kept a
        # thread and six descriptors, a notebook's `pb3a.connect` run again until "Too
        # many open files"). Not at exit: the process's exit handlers may still call.
        if self._monitor is not None:       # (before the loop thread uses the dealer)
            self._loop.register(self._monitor, _weakly(self._on_connection))
        self._loop.register(self._dealer, _weakly(self._on_reply))
        self._close_sockets = _closer(self._dealer, self._monitor)
        self._dropped = weakref.finalize(self, self._loop.close, wait=False,
                                         then=self._close_sockets)
        self._dropped.atexit = False

    def call(self, op: str, timeout: float = DEFAULT_TIMEOUT, **args: Any) -> Any:
        """Run ``op`` at the server; its result, or ``RuntimeFailure`` with its error,
        or ``RuntimeTimeout`` when no answer came within ``timeout`` seconds."""
        return self.request(op, args, timeout)

    def request(self, op: str, args: dict[str, Any], timeout: float = DEFAULT_TIMEOUT, *,
                wait: Waiting | None = None) -> Any:
        """``call`` with the arguments as a dict (which may then name one ``timeout``).
        With ``wait`` (a module body's, see ``pb3a.worker.waits``) it waits there, so
        the module's runtime can cancel it (``RuntimeCancelled``)."""
        if self.refused == "bad tag":           # it will not change its mind
            raise RuntimeFailure(self._refusal(op))
        request_id = _ID.pack(next(self._ids))
        blob = pickling.dumps((op, args))
        if len(blob) > MAX_PAYLOAD:
            raise TooLarge(f"{op!r} to {self.address}: the request is "
                           f"{too_large(len(blob))}, so it was not sent")
        done, box = _Done(wait), [False, None]
        self._waiting[request_id] = (done, box)
        self._sent[request_id] = [blob, 0, time.monotonic() + timeout]
        try:
            if self._closed:      # (checked once registered: close fails what it finds)
                raise RuntimeFailure(f"{op!r} to {self.address}: this client is closed")
            if self.gone.is_set() and self._when_gone is not None:     # (the same)
                raise self._when_gone(self.gone_why)
            self._loop.submit(lambda: self._send(request_id))
            if not done.answered(timeout):
                if self.ungreeted:
                    raise RuntimeTimeout(
                        f"{self.address} did not answer {op!r} within {spoken(timeout)} s: "
                        "something accepts connections there but does not speak PB3A's "
                        "protocol (it sent no ZeroMQ greeting): another program's port, or "
                        "a PB3A process that is stopped")
                raise RuntimeTimeout(
                    f"{self.address} did not answer {op!r} within {spoken(timeout)} s: nothing "
                    "listens there, it is cut off, or it is busy; check the address and "
                    "that the process runs and its port is open")
        finally:
            self._waiting.pop(request_id, None)
            sent = self._sent.pop(request_id, None)
            if sent is not None and not done.is_set():      # (given up on)
                # (decided on the socket thread, after any send of it in progress there:
                # read here, a send under way was not counted yet, and went unwithdrawn)
                self._loop.submit(lambda: sent[1] and self._withdraw(request_id))
        ok, result = box
        if ok is None:
            raise RuntimeFailure(self._refusal(op))
        if not ok:
            if isinstance(result, PB3AError):
                raise result
            raise RuntimeFailure(f"{op} at {self.address} failed: {result}")
        return result

    def call_if_listened(self, op: str, timeout: float = DEFAULT_TIMEOUT, **args: Any) -> Any:
        """``call``, to a server that may not be there. One that has not answered within
        ``QUICK_S`` is asked of the OS, and a port that refuses connections for
        ``REFUSED_S`` on end (nothing listens: a process that ended, a wrong port) fails
        then with ``NotListening``, rather than at ``timeout`` ("did not answer", having
        waited it whole); a server that begins to listen meanwhile is asked on. So does
        a host that has no address (a name only other machines resolve), at once: no
        answer could come (a module server's import waited its whole 5 s for it)."""
        deadline = time.monotonic() + timeout
        with contextlib.suppress(RuntimeTimeout):
            return self.call(op, min(QUICK_S, timeout), **args)
        given_up = min(deadline, time.monotonic() + REFUSED_S)
        host, _, port = self.address.removeprefix("tcp://").rpartition(":")
        while isinstance(failure := connection_failure(
                self.address, max(0.0, deadline - time.monotonic())), ConnectionRefusedError):
            if time.monotonic() >= given_up:
                raise NotListening(f"nothing listens on port {port} at {host} (the "
                                   "connection was refused)")
            time.sleep(_REPROBE_S)       # (nothing tells when a listener comes: ask again)
        if isinstance(failure, socket.gaierror):
            raise NotListening(f"no address is known for host {host.strip('[]')!r}: "
                               f"{failure.strerror or failure}")
        return self.call(op, max(0.0, deadline - time.monotonic()), **args)

    def why_refused(self, op: str) -> str:
        """Why the server refused this client's requests (another cluster key, clocks
        apart ...), as a sentence naming ``op`` and what to do; "" if it did not."""
        return self._refusal(op) if self.refused else ""

    def _refusal(self, op: str) -> str:
        if self.refused == "stale epoch" and self._refused_by and not self._sealer.epoch:
            # (a client of no run, such as the command line, at a node's executor)
            return (wrong_server(self.address, self._refused_by, op)
                    or f"{self.address} refused {op!r}: it is {self._refused_by}, which "
                    "answers only the launcher that started it")
        return f"{self.address} refused {op!r}: {_REFUSAL_HINTS.get(self.refused, self.refused)}"

    def _send(self, request_id: bytes) -> None:
        """Send a request (again), to the server instance last heard of (socket thread)."""
        sent = self._sent.get(request_id)
        if sent is None or sent[1] >= _SENDS:
            return                         # answered, given up, or sent often enough
        sent[1] += 1
        # (what is left of the caller's wait: the first request to a server is sent again
        # once it says who it is, and the server counts from when it came)
        wait = _WAIT.pack(max(0.0, sent[2] - time.monotonic()))
        # Never waits: a server that reads nothing (frozen) fills the queue, and a
        # blocking send held this socket's thread, every call's answer, and its close.
        # A request that cannot go now is sent again, or times out.
        with contextlib.suppress(zmq.Again):
            self._dealer.send_multipart(self._sealer.seal(
                REQUEST, [request_id, self._instance, wait, sent[0]]), zmq.NOBLOCK)

    def _withdraw(self, request_id: bytes) -> None:
        """Tell the server that nobody waits for request ``request_id`` any more: a
        device's drops it if it has not begun it (socket thread)."""
        with contextlib.suppress(zmq.Again):
            self._dealer.send_multipart(self._sealer.seal(WITHDRAW, [request_id]),
                                        zmq.NOBLOCK)
            # (a module stopped or moved closes its driver's client right after: with no
            # linger the withdrawal was thrown away unsent, and the request carried out)
            self._dealer.setsockopt(zmq.LINGER, WITHDRAW_LINGER_MS)

    def _on_reply(self, dealer: zmq.Socket) -> None:
        while dealer.poll(0):
            frames = dealer.recv_multipart(copy=False)
            if len(frames) == 1 and bytes(frames[0].buffer[:len(_REFUSAL)]) == _REFUSAL:
                self._refused(bytes(frames[0].buffer[len(_REFUSAL):]).decode("utf-8", "replace"))
                continue
            try:
                message = self._opener.open(frames)
                if message.kind == INSTANCE and len(message.frames) == 2:
                    self._on_instance(bytes(message.frames[0]), bytes(message.frames[1]))
                    continue
                if message.kind != REPLY or len(message.frames) != 2:
                    raise Rejected("unexpected")
                waiter = self._waiting.get(bytes(message.frames[0]))
                if waiter is None:
                    continue                     # answered after its caller gave up
                try:
                    waiter[1][:] = pickle.loads(message.frames[1])   # authenticated: safe
                except Exception as exc:     # the caller hears why now, not at its deadline
                    self._opener.rejected["undecodable"] += 1
                    waiter[1][:] = [False, RuntimeFailure(_undecodable(
                        exc, f"the answer of {self.address}", "this process"))]
                waiter[0].set()
            except Rejected:
                continue
            except Exception:
                self._opener.rejected["undecodable"] += 1

    def _on_instance(self, request_id: bytes, instance: bytes) -> None:
        """The server says who it is (signed: it is a server holding the key), for a
        request that named another: the first answer, or a server started anew at the
        address. Without ``when_gone`` the request goes again to it (a node controller
        that restarted is the same node's); with it, the client was talking to a server
        that has ended, and another one is not it (socket thread)."""
        if self._when_gone is not None and self._instance not in (_NOBODY, instance):
            self.replaced = True
            self._lost("another process has listened there since (connect again to "
                       "reach it)")
            return
        self._instance = instance
        self._send(request_id)

    def _lost(self, reason: str) -> None:
        """The server is gone: every call waiting and every later one fails, and the
        client's thread and sockets are closed as its loop ends (socket thread)."""
        if self.gone.is_set():
            return
        self.gone_why = reason
        self.gone.set()
        self.fail_pending(self._when_gone(reason))
        # (a connection kept after its system stopped held them until closed; a call
        # still fails as above, seeing ``gone`` before it would hand its request over)
        self._loop.close(then=self._close_sockets)

    def _on_connection(self, monitor: zmq.Socket) -> None:
        """The connection to the server was made, or closed by it (socket thread)."""
        while monitor.poll(0):
            event = recv_monitor_message(monitor)["event"]
            if event == zmq.EVENT_HANDSHAKE_SUCCEEDED:
                self._greeted = True
            elif event == zmq.EVENT_CONNECTED:
                if self._lost_at is not None:           # (watched, and connected again)
                    self._ask_who()
                self._lost_at = None
                if self._connected_at is None:
                    self._connected_at = time.monotonic()
            elif event == zmq.EVENT_DISCONNECTED and self._lost_at is None \
                    and self._when_gone is not None:
                self._lost_at = time.monotonic()
                self._loop.later(GONE_S, _weakly(self._look_for_server))

    def _ask_who(self) -> None:
        """Ask the server the client connected to again whether it is the one it talked
        to: a ping naming that one, which another answers by saying who it is
        (``_on_instance``: gone). A request the one before took is not sent again (it
        may have been done, a node's executor started): a call waiting for its answer
        waited out its deadline at another server, which heard nothing of it (a node
        controller restarted as it started a launch's executor: the launch said the
        executor was slow), until a later request told (socket thread)."""
        if self._instance == _NOBODY:       # (none talked to yet: none to tell apart)
            return
        with contextlib.suppress(zmq.Again):
            self._dealer.send_multipart(self._sealer.seal(REQUEST, [
                _ID.pack(next(self._ids)), self._instance, _WAIT.pack(QUICK_S),
                pickling.dumps(("ping", {}))]), zmq.NOBLOCK)

    def _look_for_server(self) -> None:
        """``GONE_S`` after the server closed the connection: if nothing has taken one
        since, it is gone, and the calls waiting for it fail (socket thread)."""
        # the loop runs its timers before it reads its sockets: a reconnection not read
        # yet would have a live server taken for gone
        if self._monitor is not None:
            self._on_connection(self._monitor)
        if self._lost_at is None or time.monotonic() - self._lost_at < GONE_S \
                or self._when_gone is None:
            return
        self._lost(f"it closed the connection and nothing has listened there for "
                   f"{GONE_S:g} s (its process ended)")

    def _refused(self, reason: str) -> None:
        """The server could not open our requests: every one waiting fails now."""
        reason, _, role = reason.partition(":")
        if reason not in _REFUSAL_HINTS:
            return
        self.refused, self._refused_by = reason, role
        for done, box in list(self._waiting.values()):
            box[:] = [None, reason]
            done.set()

    def ping(self, timeout: float, op: str = "ping") -> float | None:
        """The round-trip time of one ping, or of another of the server's instant
        operations (answered by its socket thread, so a long request cannot delay it), or
        None without an answer within ``timeout``."""
        started = time.monotonic()
        try:
            self.call(op, timeout)
        except (RuntimeFailure, RuntimeTimeout):
            return None
        return time.monotonic() - started

    def fail_pending(self, reason: str | PB3AError) -> None:
        """Make every call waiting for an answer fail now with ``reason`` (the server is
        known to be gone: nobody should wait out a deadline for it); an error is raised
        as it is."""
        for done, box in list(self._waiting.values()):
            box[:] = [False, reason]
            done.set()

    @property
    def ungreeted(self) -> bool:
        """Whether, watching its greeting (``watch_greeting``), the client was let connect
        ``GREET_S`` ago or more but has never been greeted in ZeroMQ's protocol: what
        listens at the address is another program (a legacy device that reads lines of
        text, say), or a stopped process. A server that runs greets at once, however busy
        its own threads, and a slow link within the second (a device whose greeting was
        0.4 s away was taken for another program by a request of 0.3 s)."""
        return (self._connected_at is not None and not self._greeted
                and time.monotonic() - self._connected_at >= GREET_S)

    @property
    def closed(self) -> bool:
        """Whether ``close`` was called."""
        return self._closed

    def close(self) -> None:
        """Stop; a call still waiting for its answer fails now, and so does any later.
        Closing again does nothing."""
        if self._closed:
            return
        self._closed = True
        self._dropped.detach()
        self.fail_pending("this client was closed while it waited")
        self._loop.close(then=self._close_sockets)


def _weakly(method: Callable[..., None]) -> Callable[..., None]:
    """``method``, called only while its object lives: what a client's loop holds, so
    that its thread keeps alive no client that its owner dropped."""
    ref = weakref.WeakMethod(method)

    def call(*args: Any) -> None:
        bound = ref()
        if bound is not None:
            bound(*args)
    return call


def _closer(dealer: zmq.Socket, monitor: zmq.Socket | None) -> Callable[[], None]:
    """What closes a client's sockets, holding nothing of the client (its finalizer's)."""
    def close() -> None:
        if monitor is not None:
            dealer.disable_monitor()
            monitor.close(0)
        dealer.close()              # (its LINGER: 0, unless it has withdrawn requests)
    return close


class Waiting(Protocol):
    """What a request may wait in instead of its own event: told of the answer (or the
    client's end), and waited on; its ``result`` may raise to end the wait early."""

    def answer(self, ok: bool, result: Any) -> None: ...

    def result(self, timeout: float) -> Any: ...


class _Done(threading.Event):
    """Set when a request's answer (or its refusal, or the client's end) is in; tells
    the request's ``Waiting`` too, when it has one."""

    def __init__(self, wait: Waiting | None) -> None:
        super().__init__()
        self._in = wait

    def set(self) -> None:
        super().set()
        if self._in is not None:
            self._in.answer(True, None)

    def answered(self, timeout: float) -> bool:
        """Wait up to ``timeout`` for the answer: True once it is in."""
        if self._in is None:
            return self.wait(timeout)
        try:
            self._in.result(timeout)
        except RuntimeTimeout:
            return self.is_set()
        return True


class _MustImport(Exception):
    """A request names a module not imported yet (or still being imported)."""


class _RequestUnpickler(pickle.Unpickler):
    """Unpickles a request, importing a module it names only under ``lock``, and only
    if it ``may_import``: otherwise such a module raises ``_MustImport``. ``first``: see
    ``ControlServer``'s ``import_first``."""

    def __init__(self, data: Any, lock: Any, may_import: bool,
                 first: Callable[[str, str], None] | None) -> None:
        super().__init__(io.BytesIO(data))
        self._lock, self._may_import, self._first = lock, may_import, first

    def find_class(self, module: str, name: str) -> Any:
        loaded = sys.modules.get(module)
        if loaded is None or getattr(getattr(loaded, "__spec__", None), "_initializing",
                                     False):
            if not self._may_import:
                raise _MustImport(module)
            if loaded is None and self._first is not None:
                self._first(module, name)
            with self._lock:                   # (an import, or one under way elsewhere)
                return super().find_class(module, name)
        return super().find_class(module, name)


def _decode(data: Any, lock: Any, *, may_import: bool,
            first: Callable[[str, str], None] | None = None) -> Any:
    """A request's ``(op, args)``. Only a request that names a module not imported yet
    imports it, under ``lock``, after ``first`` (see ``ControlServer``) and never on the
    socket thread (``may_import`` False): an import there, or a wait for a background
    one, held up the heartbeats behind it (under load longer than a node's lease, and
    the node was lost while its launcher was still starting it)."""
    return _RequestUnpickler(data, lock, may_import, first).load()
