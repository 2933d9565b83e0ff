"""The websocket feed ``/api/live``: the system as it changes, pushed to every page.

One ``Feed`` serves every client: it gathers the stats every ``refresh`` seconds
(one ``stats()`` call however many pages are open) and follows the events
(``events(since, timeout=...)`` in a worker thread), and hands each message to every
client's queue. After an event that changes the structure it sends the structure
and its layout again, and so it does when the session's mode changes (a launch from
another page, or from the API; an attached system that stopped, or is reached again).
Each client also gets, every ``refresh``, the state of the one module it watches
(``{"watch": name}``). A client that cannot keep up loses the oldest stats and
states, never an event; one that falls ``CLIENT_MOST`` messages
behind is disconnected (its page reconnects, and reads the system anew), so that it
holds no more memory. Blocking calls run in worker threads, never on the event loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import sys
import time
from collections.abc import Callable
from dataclasses import asdict
from typing import Any, NamedTuple, TypeVar

from starlette.concurrency import run_in_threadpool
from starlette.websockets import WebSocket, WebSocketDisconnect

from pb3a.errors import PB3AError, RuntimeTimeout, SystemStopped
from pb3a.manager.api import encode, error_response
from pb3a.manager.session import Session
from pb3a.stats import plain

log = logging.getLogger("pb3a.manager")
T = TypeVar("T")

REFRESH_S = 0.5             # stats and watched state, by default
STATS_WAIT_S = 1.0          # the stats wait this long (or a refresh, if longer) for a worker:
# one frozen (SIGSTOP, stuck) is shown silent and its figures come without it (the call
# waited half the session's 10 s, so figures came every 5 s with one worker frozen)
EVENT_WAIT_S = 0.5          # one events() call waits this long for the next event
STOP_WAIT_S = 5.0           # at the end, how long a call to the system still under way may take
CLIENT_BACKLOG = 64         # messages queued for a client before stats are dropped
CLIENT_MOST = 10_000        # ... before it is disconnected, to catch up from a new hello
BEHIND = 4013               # the close code then: try again (the page reconnects)
MOST_BACKOFF_S = 5.0        # a loop that keeps failing tries again this often at least
RECENT_EVENTS = 100         # the events a page is sent as it connects (a reload kept none)
# events after which the structure (modules, links, nodes) is sent again
STRUCTURAL = frozenset({"module_added", "module_removed", "module_moved", "module_swapped",
                        "module_failed_over", "module_failed", "module_lost", "link_added",
                        "link_removed", "node_lost", "node_joined", "module_retimed"})


class Feed:
    """What every open page gets: stats, events, structure after a change."""

    def __init__(self, session: Session, refresh: float = REFRESH_S) -> None:
        self.session = session
        self.refresh = refresh
        self._clients: set[asyncio.Queue[Message]] = set()
        self._tasks: list[asyncio.Task[None]] = []
        self._calls: set[asyncio.Future[Any]] = set()     # blocking calls under way
        self._seen = 0                      # the last event sent, of the system followed
        self._system = session.running      # the system the pages were last told of
        self._mode = session.mode           # and its mode (a stop ends in two steps)
        self._epoch = 0                     # one more at each system followed (a launch,
        # a stop): each numbers its events from 1, so a structure is (epoch, event)

    # -- life cycle (the app's lifespan) ---------------------------------------------
    def start(self) -> None:
        self._tasks = [asyncio.create_task(self._stats(), name="pb3a-manager-stats"),
                       asyncio.create_task(self._events(), name="pb3a-manager-events")]

    async def stop(self) -> None:
        """Stop producing. A call to the system under way goes on: ``settle`` waits for
        it once the session has closed."""
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._tasks = []

    async def settle(self) -> None:
        """Wait for the calls to the system still under way (STOP_WAIT_S at most), once
        the session has closed: its close ends them (a system it launched ends its events
        as it stops; a closed connection fails the calls waiting on it). Waited for
        before the close, the events call, always under way while a system runs, held
        every stop up to EVENT_WAIT_S; it still may with a handle the session does not
        own, which its close leaves running."""
        if self._calls:
            await asyncio.wait(list(self._calls), timeout=STOP_WAIT_S)

    async def _blocking(self, work: Callable[..., T], *args: Any) -> T:
        """``work(*args)`` in a worker thread, kept in ``_calls`` until it returns (a
        cancelled task does not stop the thread)."""
        call = asyncio.ensure_future(run_in_threadpool(work, *args))
        self._calls.add(call)
        call.add_done_callback(_settled(self._calls))
        return await asyncio.shield(call)

    # -- producing --------------------------------------------------------------------
    def publish(self, message: dict[str, Any] | Message) -> None:
        """Queue ``message`` for every client, encoded once (the oldest stats give way
        when one lags)."""
        if isinstance(message, dict):
            message = Message(message["type"], encode(message))
        for queue in list(self._clients):
            _enqueue(queue, message)

    async def _stats(self) -> None:
        failures = 0
        busy_since: float | None = None     # since when the stats wait for a change
        while True:
            started = time.monotonic()
            wait = self.refresh
            handle = self.session.running
            if self._clients and handle is not None:
                try:
                    message = await self._blocking(stats_message, self.session,
                                                   max(STATS_WAIT_S, self.refresh))
                    self.publish(message)
                    failures, busy_since = 0, None
                except Exception as exc:
                    # stats time out only waiting for a change that holds the system (a
                    # move, an add): the figures wait for it, up to the session's timeout
                    # (as when each call waited that long), before that is an error
                    busy = isinstance(exc, RuntimeTimeout)
                    busy_since = (busy_since or started) if busy else None
                    # (a system stopped meanwhile is no error: the mode says it)
                    if self.session.running is handle and not isinstance(exc, SystemStopped):
                        if busy_since is not None and \
                                started - busy_since < self.session.timeout:
                            log.debug("manager: the stats wait for a change: %s", exc)
                        else:
                            failures += 1
                            wait = self._failed("stats", exc, failures)
            await asyncio.sleep(max(0.0, wait - (time.monotonic() - started)))

    async def _events(self) -> None:
        failures = 0
        while True:
            handle, mode = self.session.running, self.session.mode
            if handle is not self._system or mode != self._mode:
                # a launch or a stop (or both) since the last look: a page that did not
                # launch would edit the document of a running system (past every hello:
                # no event tells of it); a system launched again numbers its events from
                # 1. A stop is told twice: as it begins (stopping) and once it is done.
                self._system, self._mode, self._seen = handle, mode, 0
                self._epoch += 1
                await self._send_structure(sys.maxsize)
            if handle is None:
                if mode == "stopped":       # attached, and it stopped: is it back there?
                    with contextlib.suppress(Exception):
                        await self._blocking(self.session.reattach)
                await asyncio.sleep(self.refresh)
                continue
            try:
                events = await self._blocking(self._next_events, handle)
                failures = 0
            except Exception as exc:
                if self.session.running is not handle:   # stopped from here: no failure
                    continue
                if isinstance(exc, SystemStopped):
                    # its launcher says so as it stops, before its connection ends: the
                    # session's mode says it then (shown as an error, it stayed on the page)
                    await asyncio.sleep(self.refresh)
                    continue
                failures += 1
                await asyncio.sleep(self._failed("events", exc, failures))
                continue
            for event in events:
                self._seen = max(self._seen, event.seq)
                self.publish({"type": "event", "event": plain(asdict(event))})
            changes = [event.seq for event in events if event.kind in STRUCTURAL]
            if changes:
                await self._send_structure(max(changes))

    async def _send_structure(self, seq: int) -> None:
        """Send the structure (and the mode) as it is now, after event ``seq``."""
        try:
            now = await self._blocking(structure, self.session)
            self.publish(Message("system", encode({"type": "system", **now}),
                                 (self._epoch, seq)))
        except Exception as exc:
            self._failed("structure", exc, 1)

    def _failed(self, source: str, exc: Exception, failures: int) -> float:
        """Log ``exc`` and tell every page (``{"type": "error", "source", "error"}``): a
        failure ends no loop, whatever it is. Returns how long to wait before trying
        again, longer after each failure in a row (to ``MOST_BACKOFF_S``)."""
        if isinstance(exc, PB3AError):
            log.warning("manager: reading the %s failed: %s", source, exc)
            reason = str(exc)
        else:       # a bug, or what the system's client let through: with its traceback
            log.error("manager: reading the %s failed", source, exc_info=exc)
            reason = f"{type(exc).__name__}: {exc}"
        self.publish({"type": "error", "source": source,
                      "error": f"the live {source} could not be read: {reason}"})
        return min(self.refresh * 2 ** (failures - 1), MOST_BACKOFF_S)

    def _next_events(self, handle: Any) -> list[Any]:
        return handle.events(self._seen, timeout=EVENT_WAIT_S)

    # -- one client --------------------------------------------------------------------
    async def serve(self, socket: WebSocket) -> None:
        """Talk to one page until it goes: hello, then everything published, and the
        state of the module it watches."""
        await socket.accept()
        queue: asyncio.Queue[Message] = asyncio.Queue()       # (bounded by _enqueue)
        watched: list[str | None] = [None]
        running = self.session.mode == "running"
        epoch = self._epoch                 # (a later one: the structure is sent again)
        try:
            # the last events first: the structure read after them shows what they did
            recent = await run_in_threadpool(self._recent_events) if running else []
            at = recent[-1]["seq"] if recent else 0
            hello = await run_in_threadpool(structure, self.session)
        except PB3AError as exc:
            with contextlib.suppress(WebSocketDisconnect, RuntimeError):    # it went
                await socket.send_text(json.dumps({"type": "error", **_error(exc)}))
                await socket.close()
            return
        self._seen = self._seen or at
        self._clients.add(queue)
        tasks: list[asyncio.Task[None]] = []
        try:
            # the page may have gone while its hello was gathered: its queue goes too
            await socket.send_text(encode({"type": "hello", **hello, "events": recent}))
            tasks = [asyncio.create_task(self._send(socket, queue, (epoch, at))),
                     asyncio.create_task(self._watch(queue, watched)),
                     asyncio.create_task(_listen(socket, watched))]
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        except WebSocketDisconnect:
            pass
        finally:
            self._clients.discard(queue)
            for task in tasks:
                task.cancel()
            for task in tasks:
                with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect,
                                         RuntimeError):
                    await task

    def _recent_events(self) -> list[dict[str, Any]]:
        """The last ``RECENT_EVENTS`` events, oldest first, as the feed sends them."""
        return [plain(asdict(event))
                for event in self.session.handle.events(0, last=RECENT_EVENTS)]

    async def _send(self, socket: WebSocket, queue: asyncio.Queue[Message],
                    hello_at: tuple[int, int]) -> None:
        """Send what is published, but not the structure after events the hello (read
        after event ``hello_at``) showed already: a page redrawn for nothing loses what
        is being typed into it."""
        while True:
            message = await queue.get()
            if message.type == "behind":
                await socket.close(BEHIND, "too far behind: reconnect")
                return
            if message.type == "system" and message.seq <= hello_at:
                continue
            await socket.send_text(message.text)

    async def _watch(self, queue: asyncio.Queue[Message],
                     watched: list[str | None]) -> None:
        while True:
            name = watched[0]
            if name is not None and self.session.mode == "running":
                try:
                    state = await run_in_threadpool(self.session.state, name)
                    message: dict[str, Any] = {"type": "state", "module": name, "state": state}
                except Exception as exc:        # reported to the page, which shows it
                    message = {"type": "state", "module": name, **_error(exc)}
                if watched[0] == name:
                    _enqueue(queue, Message("state", encode(message)))
            await asyncio.sleep(self.refresh)


async def _listen(socket: WebSocket, watched: list[str | None]) -> None:
    """Read the page's messages (``{"watch": name | null}``) until it closes; what is
    not such a message (binary, not JSON) is ignored."""
    while True:
        received = await socket.receive()
        if received["type"] == "websocket.disconnect":
            return
        try:
            message = json.loads(received.get("text") or "")
        except ValueError:
            continue
        if isinstance(message, dict) and "watch" in message:
            name = message["watch"]
            watched[0] = name if isinstance(name, str) else None


class Message(NamedTuple):
    """A message as sent: its type and its JSON text, encoded once for every client;
    for the structure, the last event it follows."""

    type: str
    text: str
    seq: tuple[int, int] = (0, 0)            # (the feed's epoch, the event)


def stats_message(session: Session, timeout: float | None = None) -> Message:
    """``{"type": "stats", "time", "cost_ms", "stats"}``, its text built once, gathered
    within ``timeout`` (see ``Session.stats``); ``cost_ms`` is what gathering the figures
    and encoding them took (the server's share of the cost of one update)."""
    started = time.perf_counter()
    stats = encode(session.stats(timeout))
    cost_ms = (time.perf_counter() - started) * 1e3
    return Message("stats", f'{{"type":"stats","time":{time.time()!r},'
                            f'"cost_ms":{cost_ms:.3f},"stats":{stats}}}')


def structure(session: Session) -> dict[str, Any]:
    """``{"system", "layout"}``, from one look at the structure."""
    topology = session.topology()
    return {"system": session.system(topology), "layout": session.layout(topology)}


def _error(exc: BaseException) -> dict[str, Any]:
    return json.loads(error_response(exc).body)


def _settled(calls: set[asyncio.Future[Any]]) -> Callable[[asyncio.Future[Any]], None]:
    """A done callback: the call is no longer under way; its outcome is taken (a call
    whose caller was cancelled may have failed, unheard)."""
    def done(call: asyncio.Future[Any]) -> None:
        calls.discard(call)
        if not call.cancelled():
            call.exception()
    return done


_FRESHEST_ONLY = frozenset({"stats", "state"})     # what a lagging client may miss


def _enqueue(queue: asyncio.Queue[Message], message: Message) -> None:
    """Queue ``message`` for one client. With ``CLIENT_BACKLOG`` queued, a stats or
    state message takes the place of the oldest such (or is dropped, if there is
    none); events and the structure always go in, until ``CLIENT_MOST``: then the
    queue is emptied for one message telling the client's sender to disconnect."""
    if queue.qsize() >= CLIENT_MOST:
        while not queue.empty():
            queue.get_nowait()
        queue.put_nowait(Message("behind", ""))
        return
    if (queue.qsize() >= CLIENT_BACKLOG and message.type in _FRESHEST_ONLY
            and not _drop_oldest(queue, _FRESHEST_ONLY)):
        return                               # (nothing of its kind to give way)
    queue.put_nowait(message)


def _drop_oldest(queue: asyncio.Queue[Message], types: frozenset[str]) -> bool:
    """Take the oldest message of one of ``types`` out of ``queue`` (the others stay,
    in order); False if there was none."""
    kept = []
    dropped = False
    while not queue.empty():
        message = queue.get_nowait()
        if not dropped and message.type in types:
            dropped = True
            continue
        kept.append(message)
    for message in kept:
        queue.put_nowait(message)
    return dropped
