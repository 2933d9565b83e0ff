"""The manager's websocket feed: hello, stats twice a second, events as they happen,
the structure after a change, and the watched module's state."""

from __future__ import annotations

import asyncio
import itertools
import threading
import time
from collections.abc import Iterator

import pytest

pytest.importorskip("starlette", reason="the manager needs the 'ui' extra")

from conftest import frozen
from sample_modules import Journal
from starlette.websockets import WebSocketDisconnect
from test_manager_api import managed, manager_client

from pb3a import Running
from pb3a.manager import live
from pb3a.manager.document import Document
from pb3a.manager.live import CLIENT_BACKLOG, CLIENT_MOST, Feed, Message, _enqueue
from pb3a.manager.session import Session

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def run() -> Iterator[Running]:
    with managed().launch() as running:
        yield running


def test_hello_then_stats_at_least_twice_a_second(run) -> None:
    with manager_client(Session(Document.empty(), run)) as client, \
            client.websocket_connect("/api/live") as socket:
        hello = socket.receive_json()
        assert hello["type"] == "hello"
        assert set(hello["system"]["modules"]) == {"src", "scale", "map"}
        assert set(hello["layout"]["modules"]) == {"src", "scale", "map"}
        times = []
        while len(times) < 7:
            message = socket.receive_json()
            assert message["type"] == "stats"
            assert set(message["stats"]["modules"]) == {"src", "scale", "map"}
            assert message["cost_ms"] > 0
            times.append(time.monotonic())
        # one every 0.5 s; a worker starved of CPU may hold one up, a second at most
        # (the feed's wait for a worker's figures: STATS_WAIT_S)
        gaps = [later - earlier for earlier, later in itertools.pairwise(times)]
        assert sum(gaps) / len(gaps) < 0.7 and max(gaps) < 0.5 + 1.0, gaps


def test_figures_keep_their_pace_with_a_worker_frozen_which_is_shown_silent(
        run, tmp_path) -> None:
    """With one worker frozen (SIGSTOP, stuck), each stats call of the feed waited half
    its 10 s deadline for it: the figures of every module came every 5 s, not every
    0.5 s. The feed waits a second at most, once: the frozen module is shown silent,
    with its process, and the others' figures keep their pace. A change that holds the
    system longer than that second (an add whose setup takes 2.5 s) is waited for, no
    error."""
    pid = run.stats().modules["map"].pid
    with manager_client(Session(Document.empty(), run)) as client, \
            client.websocket_connect("/api/live") as socket:
        assert socket.receive_json()["type"] == "hello"
        while socket.receive_json()["type"] != "stats":
            pass
        times, shown = [], []
        with frozen(pid):
            started = time.monotonic()
            while len(times) < 6 and time.monotonic() - started < 40:
                message = socket.receive_json()
                if message["type"] == "stats":
                    times.append(time.monotonic())
                    shown.append(message["stats"]["modules"])
        adding = threading.Thread(target=run.add, args=("slow", Journal), kwargs={
            "state": {"path": str(tmp_path / "journal"), "setup_s": 2.5}, "timeout": 30})
        adding.start()
        kinds: list[str] = []
        while (adding.is_alive() or kinds[-2:] != ["stats", "stats"]) and len(kinds) < 100:
            kinds.append(socket.receive_json()["type"])
        adding.join(30)
    gaps = [later - earlier for earlier, later in itertools.pairwise([started, *times])]
    assert max(gaps[:2]) < 2.0 and max(gaps[2:]) < 1.0, [round(gap, 2) for gap in gaps]
    assert (shown[-1]["map"]["silent"], shown[-1]["map"]["pid"]) == (True, pid)
    assert not any(shown[-1][name]["silent"] for name in ("src", "scale"))
    assert shown[-1]["src"]["steps"] > shown[1]["src"]["steps"]       # live, not the last
    assert "error" not in kinds and kinds[-2:] == ["stats", "stats"], kinds


def test_a_migration_arrives_as_an_event_then_as_the_new_structure(run) -> None:
    with manager_client(Session(Document.empty(), run)) as client, \
            client.websocket_connect("/api/live") as socket:
        assert socket.receive_json()["type"] == "hello"
        mover = threading.Thread(target=run.migrate, args=("map", "a"))    # as an agent would
        mover.start()
        mover.join(30)
        kinds = []
        deadline = time.monotonic() + 10
        while "system" not in kinds and time.monotonic() < deadline:
            message = socket.receive_json()
            kinds.append(message["type"])
            if message["type"] == "event":
                event = message["event"]
                assert (event["kind"], event["subject"]) == ("module_moved", "map")
                assert event["detail"]["destination"] == "a" and event["detail"]["pause_s"] > 0
            if message["type"] == "system":
                assert message["system"]["modules"]["map"]["node"] == "a"
                assert "map" in message["layout"]["modules"]
        assert "event" in kinds and kinds.index("event") < kinds.index("system")


def test_a_period_set_live_is_an_event_then_the_new_structure(run) -> None:
    """The manager refused a period ("module src has no state 'period'"), which
    ``set_state`` and ``pb3a set`` take; and a page did not show one set elsewhere: no
    event said it, so the structure was not sent again."""
    with manager_client(Session(Document.empty(), run)) as client, \
            client.websocket_connect("/api/live") as socket:
        assert socket.receive_json()["type"] == "hello"
        for body, status, words in (({"period": "fast"}, 422, "period takes a number"),
                                    ({"period": -1.0}, 409, "period"),
                                    ({"period": 0.2, "perod": 1}, 404, "(and its period)")):
            refused = client.post("/api/modules/src/state", json=body)
            assert refused.status_code == status and words in refused.json()["error"], body
        assert run.topology().modules["src"].period != 0.2
        changed = client.post("/api/modules/src/state", json={"period": 0.2})
        assert changed.status_code == 200, changed.text
        assert "period" not in changed.json()["fields"]
        assert run.topology().modules["src"].period == 0.2
        kinds = []
        deadline = time.monotonic() + 10
        while "system" not in kinds and time.monotonic() < deadline:
            message = socket.receive_json()
            if message["type"] == "event":
                assert (message["event"]["kind"], message["event"]["subject"]) == (
                    "module_retimed", "src")
                assert message["event"]["detail"] == {"period": 0.2}
            if message["type"] == "system":
                assert message["system"]["modules"]["src"]["period"] == 0.2
            kinds.append(message["type"])
        assert "event" in kinds and kinds.index("event") < kinds.index("system")


class _HeldEvents:
    """The running system, but the feed's first look at its events (the one that waits)
    is held until the page has its hello: events older than the hello come after it."""

    def __init__(self, run: Running, hello: threading.Event) -> None:
        self._run, self._hello = run, hello

    def __getattr__(self, name: str) -> object:
        return getattr(self._run, name)

    def events(self, since: int = 0, timeout: float = 0.0, last: int | None = None) -> list:
        if timeout:
            self._hello.wait(10)
        return self._run.events(since, timeout=timeout, last=last)


def test_a_page_gets_no_structure_again_for_changes_its_hello_showed(run) -> None:
    run.migrate("map", to="a")                          # a change before the page opens
    hello = threading.Event()
    with manager_client(Session(Document.empty(), _HeldEvents(run, hello))) as client, \
            client.websocket_connect("/api/live") as socket:
        first = socket.receive_json()
        hello.set()
        assert first["type"] == "hello" and first["system"]["modules"]["map"]["node"] == "a"
        kinds = []
        while kinds.count("stats") < 3:                 # 1 s of the feed after the move's
            kinds.append(socket.receive_json()["type"])    # event was read
        assert "event" in kinds and "system" not in kinds, kinds


def test_a_lagging_page_loses_stats_and_states_never_an_event_until_it_is_let_go() -> None:
    """Before, with 64 messages queued and no stats among them, new events were dropped
    in silence; the page is now sent away (it reconnects) only 10,000 behind."""
    queue: asyncio.Queue[Message] = asyncio.Queue()
    for seq in range(CLIENT_BACKLOG + 10):
        _enqueue(queue, Message("event", str(seq)))
    _enqueue(queue, Message("stats", "s1"))             # nothing of its kind to give way
    assert queue.qsize() == CLIENT_BACKLOG + 10
    for kind in ("stats", "state"):
        while not queue.empty():
            queue.get_nowait()
        for index in range(CLIENT_BACKLOG):
            _enqueue(queue, Message(kind if index == 3 else "event", str(index)))
        _enqueue(queue, Message(kind, "newest"))         # takes the oldest one's place
        queued = [queue.get_nowait() for _ in range(queue.qsize())]
        assert len(queued) == CLIENT_BACKLOG and queued[-1] == Message(kind, "newest")
        assert [m.text for m in queued if m.type == "event"] == [
            str(i) for i in range(CLIENT_BACKLOG) if i != 3]
    for seq in range(CLIENT_MOST + 1):
        _enqueue(queue, Message("event", str(seq)))
    assert [queue.get_nowait().type for _ in range(queue.qsize())] == ["behind"]


def test_a_binary_frame_from_a_page_is_ignored(run) -> None:
    """It ended the page's connection with a traceback (KeyError: 'text')."""
    with manager_client(Session(Document.empty(), run)) as client, \
            client.websocket_connect("/api/live") as socket:
        assert socket.receive_json()["type"] == "hello"
        socket.send_bytes(b'{"watch": "map"}')
        socket.send_json({"watch": "map"})
        while (message := socket.receive_json())["type"] != "state":
            pass
        assert message["module"] == "map" and "state" in message


def test_the_watched_module_s_state_comes_while_it_runs(run) -> None:
    with manager_client(Session(Document.empty(), run)) as client, \
            client.websocket_connect("/api/live") as socket:
        assert socket.receive_json()["type"] == "hello"
        socket.send_json({"watch": "map"})
        cells = []
        while len(cells) < 2:
            message = socket.receive_json()
            if message["type"] == "state":
                assert message["module"] == "map"
                cells.append(message["state"]["fields"]["cells"]["value"])
        assert cells[1] > cells[0]                    # live: it stepped in between
        socket.send_json({"watch": "ghost"})
        while True:
            message = socket.receive_json()
            if message["type"] == "state" and message["module"] == "ghost":
                assert "no module 'ghost'" in message["error"]
                break


class _GoneBeforeHello:
    """A page that closed while its hello was being gathered: every send fails as
    Starlette's ``send`` fails once the peer has gone (uvicorn: WebSocketDisconnect)."""

    def __init__(self) -> None:
        self.sent: list[str] = []

    async def accept(self) -> None:
        pass

    async def send_text(self, text: str) -> None:
        self.sent.append(text)
        raise WebSocketDisconnect(code=1006)

    async def receive(self) -> dict:
        return {"type": "websocket.disconnect", "code": 1006}

    async def close(self, code: int = 1000) -> None:
        pass


def test_a_page_that_leaves_before_its_hello_leaves_nothing_behind(run) -> None:
    feed = Feed(Session(Document.empty(), run), refresh=0.1)
    pages = [_GoneBeforeHello() for _ in range(3)]

    async def serve_all() -> None:
        for page in pages:
            await asyncio.wait_for(feed.serve(page), timeout=20)    # returns, raises nothing

    asyncio.run(serve_all())
    assert all(len(page.sent) == 1 and '"hello"' in page.sent[0] for page in pages)
    # no queue left to fill, nor stats gathered for a page that is not there
    assert not feed._clients


class _Failing:
    """The running system, but its next calls to ``stats`` (or ``events`` with a wait,
    the feed's) raise what ``failures[name]`` holds, one each, before it answers again."""

    def __init__(self, run: Running, failures: dict[str, list[Exception]]) -> None:
        self._run, self._failures = run, failures

    def __getattr__(self, name: str) -> object:
        return getattr(self._run, name)

    def stats(self, timeout: float | None = None) -> object:
        if self._failures["stats"]:
            raise self._failures["stats"].pop(0)
        return self._run.stats(timeout=timeout)

    def events(self, since: int = 0, timeout: float = 0.0, last: int | None = None) -> list:
        if timeout and self._failures["events"]:
            raise self._failures["events"].pop(0)
        return self._run.events(since, timeout=timeout, last=last)


class _EventsWaited:
    """The running system; ``waiting`` is set once an events call waits (the feed's)."""

    def __init__(self, run: Running) -> None:
        self._run, self.waiting = run, threading.Event()

    def __getattr__(self, name: str) -> object:
        return getattr(self._run, name)

    def events(self, since: int = 0, timeout: float = 0.0, last: int | None = None) -> list:
        if timeout:
            self.waiting.set()
        return self._run.events(since, timeout=timeout, last=last)


def test_a_manager_s_end_is_not_held_up_by_the_feed_s_events_call(monkeypatch) -> None:
    """The feed's events call, under way whenever a system runs, ends as the session
    closes (its system stops): the app's end waited for the call before closing the
    session, EVENT_WAIT_S at every stop (0.5 s; made 30 here, the wait's bound, 5 s)."""
    monkeypatch.setattr(live, "EVENT_WAIT_S", 30.0)
    with managed().launch() as run:
        handle = _EventsWaited(run)
        client = manager_client(Session(Document.empty(), handle, owns_handle=True))
        with client:
            assert handle.waiting.wait(10), "the feed made no events call"
            ended = time.monotonic()
        took = time.monotonic() - ended
        assert took < 2.0, f"the app took {took:.2f} s to end"
        assert not run.running                          # (the session stopped it)


def test_the_feed_reports_an_unexpected_failure_and_goes_on(run) -> None:
    # a dropped connection, a bad reply: not PB3AErrors, they once ended the feed's loop
    # in silence and the page was never updated again
    failures: dict[str, list[Exception]] = {"stats": [], "events": []}
    with manager_client(Session(Document.empty(), _Failing(run, failures)),
                        refresh=0.1) as client, \
            client.websocket_connect("/api/live") as socket:
        assert socket.receive_json()["type"] == "hello"
        # armed once the page is there (the events loop reads with no page too)
        failures["events"].append(KeyError("seq"))
        failures["stats"] += [OSError("connection reset by peer"), ValueError("a bad reply")]
        socket.send_json({"watch": "map"})      # state messages come even if the rest stop
        errors, after = [], []
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not (len(errors) == 3 and after):
            message = socket.receive_json()
            if message["type"] == "error":
                errors.append(message)
            elif message["type"] == "stats" and len(errors) == 3:
                after.append(message)
        assert sorted(e["source"] for e in errors) == ["events", "stats", "stats"], errors
        assert any("OSError: connection reset by peer" in e["error"] for e in errors)
        assert any("KeyError" in e["error"] for e in errors)
        assert after, "no stats after the failures"
        # the events loop goes on too: a move made now arrives
        mover = threading.Thread(target=run.migrate, args=("map", "a"))
        mover.start()
        mover.join(30)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            message = socket.receive_json()
            if message["type"] == "event":
                assert message["event"]["kind"] == "module_moved"
                break
        else:
            pytest.fail("no event after the events loop failed")


def test_a_page_open_while_another_launches_is_told_the_system_runs(tmp_path) -> None:
    """A launch records no event, so a page open in editing mode was never told: its
    State Editor went on editing the document of a system that ran (the page showed the
    edits applied; the running modules never changed)."""
    from test_manager_document import PIPELINE
    from test_manager_failures import receive_until

    path = tmp_path / "pipeline.toml"
    path.write_text(PIPELINE.read_text())
    session = Session(Document.open(path))
    try:
        with manager_client(session, refresh=0.2) as client, \
                client.websocket_connect("/api/live") as socket:
            assert socket.receive_json()["system"]["mode"] == "editing"
            assert client.post("/api/document/launch", json={}).status_code == 200
            told = receive_until(socket, lambda m: m["type"] == "system", "the structure")
            assert told[-1]["system"]["mode"] == "running"
    finally:
        session.close()


def test_a_system_launched_again_is_followed_from_its_first_event_and_a_stop_is_no_failure(
        tmp_path) -> None:
    """Each system numbers its events from 1, but after Stop and Launch the feed asked the
    new one for the events after the last of the old one: the new system's first events
    and the structure after them never came (a page whose hello came after the old
    events was not sent the new structure either), and each Stop came to every page as
    an error of the live events."""
    from test_manager_document import PIPELINE
    from test_manager_failures import event_of, receive_until

    path = tmp_path / "pipeline.toml"
    path.write_text(PIPELINE.read_text())
    session = Session(Document.open(path))
    scale = {"class": "examples.pipeline:Scale"}

    def running(message: dict) -> bool:
        return message["type"] == "system" and message["system"]["mode"] == "running"

    def shows_three(message: dict) -> bool:
        return message["type"] == "system" and "three" in message["system"]["modules"]

    try:
        with manager_client(session, refresh=0.2) as client, \
                client.websocket_connect("/api/live") as first:
            assert first.receive_json()["type"] == "hello"
            assert client.post("/api/document/launch", json={}).status_code == 200
            for name in ("one", "two"):                 # events 1 and 2 of the first run
                assert client.post("/api/modules", json={"name": name, **scale}).status_code \
                    == 201
            receive_until(first, event_of("module_added", "two"), "the second add")
            with client.websocket_connect("/api/live") as second:
                hello = second.receive_json()
                assert [e["seq"] for e in hello["events"]][-1] == 2
                assert client.post("/api/system/stop", json={}).status_code == 200
                seen = receive_until(first, lambda m: m["type"] == "system"
                                     and m["system"]["mode"] == "editing", "the stop")
                assert client.post("/api/document/launch", json={}).status_code == 200
                seen += receive_until(first, running, "the launch")
                receive_until(second, running, "the launch")
                assert client.post("/api/modules", json={"name": "three", **scale}) \
                    .status_code == 201                 # event 1 of the second run
                seen += receive_until(first, shows_three, "the structure after the add")
                assert any(event_of("module_added", "three")(m) for m in seen)
                receive_until(second, shows_three, "the structure after the add")
                assert [m["error"] for m in seen if m["type"] == "error"] == []
    finally:
        session.close()


def test_a_stop_is_told_as_it_begins_and_editing_only_once_its_workers_are_gone(
        tmp_path) -> None:
    """The feed told every page ``editing`` as soon as Stop began, while the modules'
    teardown and the workers' exit were still to come: a page (or a test) that acted on
    it found the system's processes running. Now the mode is ``stopping`` until the stop
    is done, then ``editing``."""
    from conftest import alive
    from test_manager_failures import receive_until

    hold = tmp_path / "hold"
    hold.touch()                            # the module's teardown waits while it exists
    path = tmp_path / "held.toml"
    path.write_text('name = "held"\n[modules.held]\nclass = "sample_modules:Journal"\n'
                    f'state = {{ path = "{tmp_path / "journal"}", hold = "{hold}" }}\n')
    session = Session(Document.open(path))

    def mode_is(mode: str):
        return lambda m: m["type"] == "system" and m["system"]["mode"] == mode

    try:
        with manager_client(session, refresh=0.1) as client, \
                client.websocket_connect("/api/live") as socket:
            assert client.post("/api/document/launch", json={}).status_code == 200
            running = receive_until(socket, mode_is("running"), "the launch")[-1]
            pid = client.get("/api/stats").json()["modules"]["held"]["pid"]
            stopped: list[int] = []
            stop = threading.Thread(target=lambda: stopped.append(
                client.post("/api/system/stop", json={}).status_code), daemon=True)
            stop.start()
            seen = receive_until(socket, mode_is("stopping"), "the stop beginning")
            assert not any(mode_is("editing")(m) for m in seen)
            assert client.get("/api/system").json()["mode"] == "stopping"
            hold.unlink()
            edited = receive_until(socket, mode_is("editing"), "the stop done")[-1]
            assert not alive(pid)
            stop.join(20.0)
            assert stopped == [200]
            answer = client.get("/api/system").json()
            assert answer["mode"] == "editing"
            # each mode newer than the one before, so a page can drop one that comes late
            changes = [m["system"]["mode_change"] for m in (running, seen[-1], edited)]
            assert changes == sorted(set(changes)) and answer["mode_change"] == changes[-1]
    finally:
        session.close()
