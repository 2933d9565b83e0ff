"""Real failures as the manager's page sees them, through the API and the websocket: a
module that raises in its body, a module whose worker is killed (left failed, or
restarted), a module that does not answer its remove, and a remote node (``pb3a node
start``) that is lost and then comes back."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import time
from collections.abc import Callable
from typing import Any

import pytest

pytest.importorskip("starlette", reason="the manager needs the 'ui' extra")

from conftest import Daemon, alive, eventually
from sample_modules import Collector, Counter, Faulty, Steady
from test_manager_api import manager_client

from pb3a import System, connect
from pb3a.manager.document import Document
from pb3a.manager.session import Session

pytestmark = pytest.mark.timeout(120)


def receive_until(socket: Any, wanted: Callable[[dict[str, Any]], bool], what: str,
                  timeout: float = 20.0) -> list[dict[str, Any]]:
    """The messages the feed sends until one is ``wanted`` (that one last); fail after
    ``timeout`` seconds. The feed sends stats every refresh, so each wait is short."""
    seen: list[dict[str, Any]] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        message = socket.receive_json()
        seen.append(message)
        if wanted(message):
            return seen
    pytest.fail(f"the feed sent no {what} within {timeout} s; it sent "
                f"{[m['type'] for m in seen]}")


def event_of(kind: str, subject: str) -> Callable[[dict[str, Any]], bool]:
    return lambda m: (m["type"] == "event" and m["event"]["kind"] == kind
                      and m["event"]["subject"] == subject)


def stats_where(check: Callable[[dict[str, Any]], bool]) -> Callable[[dict[str, Any]], bool]:
    return lambda m: m["type"] == "stats" and check(m["stats"])


def test_a_module_that_raises_and_one_whose_worker_dies_are_seen_failing() -> None:
    system = System("failing")
    system.add("boom", Faulty)
    system.add("steady", Steady, restart="never")
    with system.launch() as run, manager_client(Session(Document.empty(), run)) as client, \
            client.websocket_connect("/api/live") as socket:
        assert socket.receive_json()["type"] == "hello"
        # raising in its body: counted, the last error shown, the module goes on
        seen = receive_until(socket, stats_where(
            lambda s: s["modules"]["boom"]["errors"] > 0), "errors of boom")
        boom = seen[-1]["stats"]["modules"]["boom"]
        assert "ValueError: odd step" in boom["last_error"] and boom["status"] == "running"
        # its worker killed: failed, as an event, in the stats and in the structure's feed
        pid = client.get("/api/stats").json()["modules"]["steady"]["pid"]
        assert pid and pid != os.getpid()
        os.kill(pid, signal.SIGKILL)
        seen = receive_until(socket, event_of("module_failed", "steady"), "module_failed")
        assert seen[-1]["event"]["detail"]["exit_code"] == -signal.SIGKILL
        receive_until(socket, stats_where(
            lambda s: s["modules"]["steady"]["status"] == "failed"), "steady failed")
        stats = client.get("/api/stats").json()
        assert stats["modules"]["steady"]["status"] == "failed"
        assert any("module steady failed" in failure for failure in stats["failures"])
        assert stats["modules"]["boom"]["status"] == "running"
        # a swap of it is refused as any other change is: of the module, with the fix
        # (it said "worker 'local/m-steady' is not running")
        for method, path, body in (("POST", "swap", {"class": "sample_modules:Steady"}),
                                   ("POST", "state", {"count": 3})):
            refused = client.request(method, f"/api/modules/steady/{path}", json=body)
            assert refused.status_code == 502, (path, refused.text)
            assert "module 'steady' is not running: it failed" in refused.json()["error"]
            assert "a restart runs it again" in refused.json()["error"], path
        # restarted from the page (it had no way to: `pb3a restart` alone)
        assert client.post("/api/modules/steady/restart").status_code == 200
        receive_until(socket, stats_where(
            lambda s: s["modules"]["steady"]["status"] == "running"
            and s["modules"]["steady"]["pid"] not in (None, pid)), "steady running again")
        assert client.post("/api/modules/nope/restart").status_code == 404
        # a page that connects now (a reload) is told what happened before it (it was not)
        with client.websocket_connect("/api/live") as later:
            hello = later.receive_json()
        told = [(event["kind"], event["subject"]) for event in hello["events"]]
        assert ("module_failed", "steady") in told, told


def test_a_restart_appears_on_the_feed_as_it_happens() -> None:
    system = System("restarting")
    system.add("victim", Steady, restart="fresh", state={"count": 1000})
    with system.launch() as run, manager_client(Session(Document.empty(), run)) as client, \
            client.websocket_connect("/api/live") as socket:
        assert socket.receive_json()["type"] == "hello"
        first = receive_until(socket, stats_where(
            lambda s: s["modules"]["victim"]["status"] == "running"
            and s["modules"]["victim"]["pid"]), "victim running")[-1]
        pid = first["stats"]["modules"]["victim"]["pid"]
        assert pid != os.getpid()
        socket.send_json({"watch": "victim"})
        receive_until(socket, lambda m: m["type"] == "state" and m["state"]["fields"]["count"][
            "value"] > 1000, "victim's state counting on from 1000")
        # its worker killed: restarted fresh, as an event, then running in a new worker
        os.kill(pid, signal.SIGKILL)
        seen = receive_until(socket, event_of("module_restarted", "victim"), "module_restarted")
        detail = seen[-1]["event"]["detail"]
        assert detail["reason"] == "its worker died" and detail["policy"] == "fresh"
        assert detail["exit_code"] == -signal.SIGKILL
        assert not any(m["type"] == "event" and m["event"]["kind"] == "module_failed"
                       for m in seen)
        again = receive_until(socket, stats_where(
            lambda s: s["modules"]["victim"]["status"] == "running"
            and s["modules"]["victim"]["pid"] not in (None, pid)
            and s["modules"]["victim"]["restarts"] == 1), "victim running in a new worker")
        new_pid = again[-1]["stats"]["modules"]["victim"]["pid"]
        # the State Editor's feed follows it into its new worker
        receive_until(socket, lambda m: m["type"] == "state"
                      and m["state"]["fields"]["pid"]["value"] == new_pid,
                      "victim's state from its new worker")
        assert client.get("/api/stats").json()["modules"]["victim"]["restarts"] == 1
        # a restart asked for elsewhere (as by an agent, or `pb3a` on the command line)
        run.restart("victim")
        seen = receive_until(socket, event_of("module_restarted", "victim"),
                             "the asked-for restart")
        assert seen[-1]["event"]["detail"]["reason"] == "asked"


def test_a_module_that_does_not_answer_its_remove_is_killed_by_a_forced_one() -> None:
    """``DELETE /api/modules/NAME`` of a module that does not answer (its worker stopped,
    SIGSTOP: as a hung one) answered ``504`` and left it as it was, and the page had no
    way to get rid of it but stopping the system. The ``504`` names force; ``?force=1``
    kills its worker once the stop has had the manager's timeout and removes the module
    with its links, the rest running on; a ``force`` that is neither 1 nor 0 is ``400``
    and changes nothing."""
    system = System("remove-forced").node("a")
    system.add("c", Counter, node="a", period=0.01)
    system.add("f", Collector, node="a")
    system.add("d", Collector, node="a")
    system.link("c.out", "f.x")
    system.link("c.out", "d.x")
    run = system.launch(timeout=30)
    pid = run.stats().modules["f"].pid
    os.kill(pid, signal.SIGSTOP)
    try:
        with manager_client(Session(Document.empty(), run, timeout=1)) as client:
            unclear = client.delete("/api/modules/f?force=yes")
            assert unclear.status_code == 400 and "'force'" in unclear.json()["error"]
            refused = client.delete("/api/modules/f")
            assert refused.status_code == 504, refused.json()
            assert "module f was left as it was" in refused.json()["error"]
            assert "force" in refused.json()["error"]
            assert "f" in run.topology().modules and alive(pid)
            began = time.monotonic()
            removed = client.delete("/api/modules/f?force=1")
            took = time.monotonic() - began
            assert removed.status_code == 200, removed.json()
            assert took < 3.0, f"the forced remove took {took:.2f} s"
            assert "f" not in removed.json()["modules"] and not alive(pid)
            assert set(run.topology().links) == {"c.out->d.x"}
            killed = [e for e in run.events() if e.kind == "module_removed"]
            assert killed and killed[-1].subject == "f" and killed[-1].detail["killed"]
            received = run.state("d")["received"]
            eventually(lambda: run.state("d")["received"] > received + 20,
                       what="values still flowing from c to d")
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGCONT)
        run.close(timeout=5)


def test_a_lost_remote_node_is_seen_lost_then_rejoined() -> None:
    node = Daemon("b")
    try:
        system = System("remote").node("a").node("b", address=node.address)
        system.add("src", Counter, node="a", period=0.01)
        system.add("far", Collector, node="b", restart="fresh", fallback=["a"])
        system.link("src.out", "far.x")
        with system.launch() as run, \
                manager_client(Session(Document.empty(), run)) as client, \
                client.websocket_connect("/api/live") as socket:
            assert socket.receive_json()["type"] == "hello"
            before = client.get("/api/system").json()
            assert before["nodes"]["b"]["up"] is True
            assert before["nodes"]["b"]["address"] == node.address
            assert before["modules"]["far"]["node"] == "b"
            node.kill()                     # the machine's daemon and its executor go
            seen = receive_until(socket, lambda m: m["type"] == "system"
                                 and m["system"]["nodes"]["b"]["up"] is False,
                                 "the structure with node b lost")
            lost = [m["event"] for m in seen if m["type"] == "event"
                    and m["event"]["kind"] == "node_lost"]
            assert lost and lost[0]["subject"] == "b" and lost[0]["detail"]["modules"] == [
                "far"]
            assert client.get("/api/system").json()["nodes"]["b"]["up"] is False
            stats = client.get("/api/stats").json()
            assert stats["nodes"]["b"]["up"] is False
            assert any("node b lost" in failure for failure in stats["failures"])
            receive_until(socket, event_of("module_failed_over", "far"), "far failed over")
            assert client.get("/api/system").json()["modules"]["far"]["node"] == "a"
            node.start()                    # the daemon comes back at the same address
            receive_until(socket, event_of("node_joined", "b"), "node b joined", timeout=30)
            receive_until(socket, stats_where(lambda s: s["nodes"]["b"]["up"] is True),
                          "stats with node b up")
            assert client.get("/api/system").json()["nodes"]["b"]["up"] is True
            assert client.get("/api/stats").json()["nodes"]["b"]["up"] is True
    finally:
        node.stop()


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_an_attached_system_that_stops_shows_stopped_and_one_run_again_there_is_reached(
        ) -> None:
    address = f"tcp://127.0.0.1:{_free_port()}"
    system = System("again")
    system.add("count", Counter, period=0.05)
    run = system.launch(listen=address)
    try:
        session = Session(Document.empty(), connect(address), owns_handle=True)
        with manager_client(session) as client, \
                client.websocket_connect("/api/live") as socket_:
            assert socket_.receive_json()["system"]["mode"] == "running"
            run.close()
            # the page is told it stopped, and why; no error for the stats or events
            seen = receive_until(socket_, lambda m: m["type"] == "system"
                                 and m["system"]["mode"] == "stopped", "mode stopped")
            assert [m for m in seen if m["type"] == "error"] == []
            shown = client.get("/api/system").json()
            assert shown["mode"] == "stopped" and shown["address"] == address
            assert "'again'" in shown["stopped"] and "has stopped" in shown["stopped"]
            assert "count" in shown["modules"]          # what it was
            refused = client.get("/api/stats")
            assert refused.status_code == 409 and "has stopped" in refused.json()["error"]
            # run again at the address: reached (it said 502 "nothing has listened
            # there" for good, the connection closed and the mode running)
            run = system.launch(listen=address)
            receive_until(socket_, lambda m: m["type"] == "system"
                          and m["system"]["mode"] == "running", "mode running again")
            assert client.get("/api/system").json()["stopped"] is None
            eventually(lambda: client.get("/api/stats").json()["modules"]["count"]["steps"] > 0,
                       timeout=10)
    finally:
        run.close()
