"""The ModuleManager's HTTP API on a running system: every endpoint, its errors, and
that a refused request changes nothing."""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import struct
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from agents.traffic.gap_out import GapOut

pytest.importorskip("starlette", reason="the manager needs the 'ui' extra")

from conftest import eventually
from manager_modules import FileNamed, Holder
from sample_modules import Drifter, FloatSource, Mapper, Pump, Scale, SlowState
from starlette.testclient import TestClient

from pb3a import Running, System
from pb3a.errors import RuntimeFailure
from pb3a.manager.access import Access, new_token
from pb3a.manager.app import create_app
from pb3a.manager.catalog import Catalog
from pb3a.manager.document import Document
from pb3a.manager.session import Session

pytestmark = pytest.mark.timeout(60)

TESTS = Path(__file__).resolve().parent


def managed() -> System:
    system = System("managed").node("a").node("b")
    system.add("src", FloatSource, node="a")
    system.add("scale", Scale, node="a")
    system.add("map", Mapper, node="b")
    system.link("src.out", "scale.x")
    system.link("scale.y", "map.x")
    return system


@pytest.fixture
def run() -> Iterator[Running]:
    with managed().launch() as running:
        yield running


def manager_client(session: Session, refresh: float = 0.5) -> TestClient:
    """A test client of a manager app serving ``session``, with the token in its headers
    (``client.token``)."""
    token = new_token()
    client = TestClient(create_app(session, Access(token, {"testserver"}), refresh),
                        headers={"Authorization": f"Bearer {token}"})
    client.token = token                        # type: ignore[attr-defined]
    return client


@pytest.fixture
def client(run: Running) -> Iterator[TestClient]:
    # (the session owns the system, which stops with the app as a system the manager
    # launched does: the app's end then waits out no events call of its feed, 0.4 s)
    document = Document.empty()
    session = Session(document, run, owns_handle=True,
                      catalog=Catalog(document, roots=[TESTS]))
    with manager_client(session) as client:
        yield client


# -- access ----------------------------------------------------------------------------
def test_without_the_right_token_nothing_is_served_and_nothing_changes(client, run) -> None:
    bare = TestClient(client.app)
    for path in ("/api/system", "/api/stats", "/api/modules/scale/state"):
        refused = bare.get(path)
        assert refused.status_code == 401 and "token" in refused.json()["error"], path
        assert refused.json()["problems"] == []            # (as every error, the docs say)
    assert bare.get("/api/stats", headers={"Authorization": "Bearer wrong"}).status_code == 401
    assert bare.get(f"/api/stats?token={client.token}").status_code == 401   # not in URLs
    page = bare.get("/")
    assert page.status_code == 401 and "pb3a manager" in page.text
    assert page.headers["content-type"].startswith("text/html")
    assert bare.get("/static/app.js").status_code == 401
    assert bare.post("/api/modules/scale/state", json={"gain": 99.0}).status_code == 401
    assert bare.post("/api/modules/map/migrate", json={"to": "a"}).status_code == 401
    assert run.state("scale")["gain"] == 2.0 and run.where("map") == "b"


# every route that changes something: (method, path, body)
MUTATING = {
    "add": ("POST", "/api/modules", {"name": "probe", "class": "sample_modules:Last",
                                     "node": "b"}),
    "remove": ("DELETE", "/api/modules/map", None),
    "link": ("POST", "/api/links", {"src": "src.out", "dst": "map.x", "replace": True}),
    "reload": ("POST", "/api/reload", {"module": "sample_modules"}),
    "document": ("PUT", "/api/document", {"system": {"name": "other", "modules": {
        "probe": {"class": "sample_modules:Last"}}}}),
    "open": ("POST", "/api/document/open", {"name": "other.toml",
                                            "toml": 'name = "other"\n'}),
    "save": ("POST", "/api/document/save", {"path": "SAVED"}),
    "launch": ("POST", "/api/document/launch", {}),
    "state": ("POST", "/api/modules/scale/state", {"gain": 99.0}),
    "migrate": ("POST", "/api/modules/map/migrate", {"to": "a"}),
    "swap": ("POST", "/api/modules/scale/swap", {"class": "sample_modules:FastScale"}),
}


@pytest.mark.parametrize("route", MUTATING)
def test_a_change_without_the_right_token_is_refused_and_changes_nothing(
        route, client, run, tmp_path) -> None:
    import sys

    method, path, body = MUTATING[route]
    if route == "save":
        body = {"path": str(tmp_path / "saved.toml")}

    def everything() -> tuple:
        topology = run.topology()
        return ({name: (m.cls, m.node) for name, m in topology.modules.items()},
                {key: link.policy for key, link in topology.links.items()},
                run.state("scale")["gain"], client.get("/api/document").json(),
                client.get("/api/system").json()["mode"], sys.modules.get("sample_modules"))

    before = everything()
    assert before[0]["scale"] == ("sample_modules:Scale", "a") and before[2] == 2.0
    bare = TestClient(client.app)
    for refusal, headers, query in (
            ("no token", {}, ""),
            ("a wrong token", {"Authorization": "Bearer wrong"}, ""),
            ("a wrong cookie", {"Cookie": "pb3a_token=wrong"}, ""),
            ("the token in the URL", {}, f"?token={client.token}")):
        refused = bare.request(method, path + query, json=body, headers=headers)
        assert refused.status_code == 401, (refusal, refused.text)
        assert "token" in refused.json()["error"], refusal
    assert everything() == before
    assert not (tmp_path / "saved.toml").exists()
    # with the token the same request changes what was compared (so the check can fail);
    # launch only is refused then too: a system runs already
    allowed = client.request(method, path, json=body)
    if route == "launch":
        assert allowed.status_code == 409 and "runs already" in allowed.json()["error"]
    else:
        assert allowed.status_code in (200, 201), allowed.text
        assert everything() != before or (tmp_path / "saved.toml").exists()


def test_a_foreign_host_is_refused_even_with_the_token(client, run) -> None:
    rebound = client.post("/api/modules/scale/state", json={"gain": 99.0},
                          headers={"Host": "evil.example:8080"})
    assert rebound.status_code == 403 and "host" in rebound.json()["error"]
    assert run.state("scale")["gain"] == 2.0


def test_the_token_in_the_first_url_becomes_a_cookie_and_leaves_the_address_bar(client) -> None:
    browser = TestClient(client.app, follow_redirects=False)
    signed_in = browser.get(f"/?token={client.token}")
    assert signed_in.status_code == 303 and signed_in.headers["location"] == "/"
    cookie = signed_in.headers["set-cookie"]
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie and "Path=/" in cookie
    assert browser.get("/api/system").status_code == 200          # the cookie does it now
    assert TestClient(client.app, follow_redirects=False).get("/?token=nope").status_code == 401


def test_each_manager_has_a_cookie_of_its_own_and_host_names_ignore_case() -> None:
    """Cookies are not kept apart by port: two managers on one host overwrote each
    other's (one page then got 401 for good). A host name with capitals was refused,
    browsers sending it in lower case; on port 80 they leave the port out."""
    one, other = Access("token-one"), Access("token-two")
    one.serve_at("MyHost", 8001)
    other.serve_at("127.0.0.1", 80)
    assert one.cookie != other.cookie
    both = {"cookie": f"{one.cookie}=token-one; {other.cookie}=token-two"}
    assert one.authenticated(both) and other.authenticated(both)
    assert not one.authenticated({"cookie": f"{other.cookie}=token-one"})
    assert one.host_allowed("myhost:8001") and one.host_allowed("MyHost:8001")
    assert other.host_allowed("127.0.0.1") and other.host_allowed("localhost:80")
    assert not one.host_allowed("myhost")


def test_a_page_of_another_origin_cannot_use_the_cookie(client, run) -> None:
    # the cookie is SameSite=Strict, but a page served by anything else on this host (any
    # other port: the same site) still sends it along with a form or a no-cors fetch
    browser = TestClient(client.app, follow_redirects=False)
    assert browser.get(f"/?token={client.token}").status_code == 303
    for origin in ("http://testserver:9999", "http://evil.example", "null"):
        for method, path, body in (("POST", "/api/modules/scale/state", {"gain": 99.0}),
                                   ("POST", "/api/modules/map/migrate", {"to": "a"}),
                                   ("DELETE", "/api/modules/src", None)):
            forged = browser.request(method, path, json=body, headers={"Origin": origin})
            assert forged.status_code == 403, (origin, path, forged.text)
            assert "origin" in forged.json()["error"]
    assert run.state("scale")["gain"] == 2.0 and run.where("map") == "b"
    assert "src" in run.topology().modules
    own = browser.post("/api/modules/scale/state", json={"gain": 3.0},
                       headers={"Origin": "http://testserver"})
    assert own.status_code == 200 and run.state("scale")["gain"] == 3.0

def test_a_websocket_needs_the_token_and_the_page_s_origin(client) -> None:
    from starlette.websockets import WebSocketDisconnect

    with pytest.raises(WebSocketDisconnect), TestClient(client.app).websocket_connect(
            "/api/live"):
        pass
    with pytest.raises(WebSocketDisconnect), client.websocket_connect(
            "/api/live", headers={"Origin": "http://evil.example"}):
        pass
    with client.websocket_connect("/api/live",
                                  headers={"Origin": "http://testserver"}) as socket:
        assert socket.receive_json()["type"] == "hello"


# -- structure and figures -------------------------------------------------------------------
def test_system_and_layout_show_every_module_on_its_node(client) -> None:
    system = client.get("/api/system").json()
    assert system["mode"] == "running" and system["name"] == "managed"
    assert {name: m["node"] for name, m in system["modules"].items()} == {
        "src": "a", "scale": "a", "map": "b"}
    scale = system["modules"]["scale"]
    assert scale["class"] == "sample_modules:Scale" and scale["kind"] == "module"
    assert scale["inputs"] == {"x": {"type": "float", "policy": "latest"}}
    assert scale["outputs"] == {"y": {"type": "float"}} and scale["state"] == ["gain", "setups"]
    assert system["modules"]["map"]["displays"]["speed"] == {"kind": "gauge", "min": 0.0,
                                                             "max": 1.0}
    assert {link["key"] for link in system["links"]} == {"src.out->scale.x", "scale.y->map.x"}
    assert system["nodes"]["a"]["up"] is True
    layout = client.get("/api/layout").json()
    for name, module in system["modules"].items():
        box, region = layout["modules"][name], layout["clusters"][module["node"]]
        assert region["x"] <= box["x"] and box["x"] + box["w"] <= region["x"] + region["w"]
        assert region["y"] <= box["y"] and box["y"] + box["h"] <= region["y"] + region["h"]
    assert all(len(layout["links"][key]["points"]) >= 2 for key in layout["links"])


def test_stats_carry_modules_links_and_each_node_s_resources(client) -> None:
    stats = client.get("/api/stats").json()
    assert set(stats["modules"]) == {"src", "scale", "map"}
    assert stats["modules"]["scale"]["status"] in ("starting", "running")
    assert set(stats["links"]) == {"src.out->scale.x", "scale.y->map.x"}
    for node in stats["nodes"].values():
        assert 0 <= node["cpu"] <= 100 and 0 < node["memory_available"] <= node["memory_total"]


# -- the State Editor ------------------------------------------------------------------
def test_state_views_drill_down_and_draw_2d_arrays(client) -> None:
    view = client.get("/api/modules/map/state").json()
    assert view["module"] == "map" and view["class"] == "sample_modules:Mapper"
    fields = view["fields"]
    assert fields["speed"] == {"type": "float", "value": 0.5, "editable": True}
    assert fields["label"] == {"type": "str", "value": "map", "editable": True}
    grid = fields["grid"]
    assert grid["type"] == "ndarray" and grid["shape"] == [8, 8] and grid["dtype"] == "float64"
    assert grid["editable"] and len(grid["value"]) == 8
    assert grid["image"] == "/api/modules/map/image?path=grid"
    assert set(grid["summary"]) == {"min", "max", "mean"}
    row = client.get("/api/modules/map/state?path=grid.0").json()
    assert row["path"] == "grid.0" and row["fields"]["0"]["shape"] == [8]
    image = client.get(grid["image"])
    assert image.status_code == 200 and image.headers["content-type"] == "image/png"
    assert image.content.startswith(b"\x89PNG\r\n\x1a\n")
    width, height = struct.unpack(">II", image.content[16:24])
    assert (width, height) == (256, 256)                     # 8x8 scaled up by 32
    assert client.get("/api/modules/map/state?path=nothing").status_code == 404
    assert client.get("/api/modules/map/image?path=speed").status_code == 400
    missing = client.get("/api/modules/ghost/state")
    assert missing.status_code == 404 and "no module 'ghost'" in missing.json()["error"]


def test_an_edit_is_coerced_applied_and_used_and_a_bad_one_changes_nothing(client, run) -> None:
    changed = client.post("/api/modules/scale/state", json={"gain": 5})
    assert changed.status_code == 200
    assert changed.json()["fields"]["gain"] == {"type": "float", "value": 5.0, "editable": True}
    assert run.state("scale")["gain"] == 5.0 and isinstance(run.state("scale")["gain"], float)
    grid = [[float(i * 8 + j) for j in range(8)] for i in range(8)]
    assert client.post("/api/modules/map/state", json={"grid": grid, "speed": 0.0}).status_code \
        == 200
    assert run.state("map")["grid"][7][7] == 63.0          # speed 0: stepping adds nothing
    for body, status, words in (
            ({"gain": "x"}, 422, "state 'gain' takes a number, got 'x'"),
            ({"gain": 1.0, "setups": 2.5}, 422, "state 'setups' takes a whole number"),
            ({"gian": 1.0}, 404, "has no state 'gian'"),
            ({}, 400, "send an object of state fields"),
            ([1, 2], 400, "send an object of state fields")):
        refused = client.post("/api/modules/scale/state", json=body)
        assert refused.status_code == status and words in refused.json()["error"], body
    wrong_shape = client.post("/api/modules/map/state", json={"grid": [[1.0, 2.0]]})
    assert wrong_shape.status_code == 422 and "shape [8, 8]" in wrong_shape.json()["error"]
    not_json = client.post("/api/modules/scale/state", content=b"{gain: 1",
                           headers={"content-type": "application/json"})
    assert not_json.status_code == 400 and "not JSON" in not_json.json()["error"]
    assert run.state("scale")["gain"] == 5.0 and run.state("map")["grid"][7][7] == 63.0


def test_an_edit_the_module_s_class_refuses_is_refused_naming_it_and_nothing_set() -> None:
    """The State Editor asks the module's class what it refuses of an edit
    (``state_problems``), as ``pb3a check`` does, before sending it: a value only the
    class's own ``set_state`` refused reached the module (a rate its pump cannot run
    at was set), or came back as a worker's failure."""
    system = System("plant").add("p", Pump)
    with system.launch() as run, manager_client(Session(Document.empty(), run)) as client:
        refused = client.post("/api/modules/p/state", json={"rate": 9, "valve": "ajar"})
        assert refused.status_code == 422, refused.text
        assert refused.json()["error"] == ("module p: Pump's rate must be from 0 to 5 l/s, "
                                           "got 9.0; module p: Pump's valve is 'open' or "
                                           "'closed', got 'ajar'")
        assert run.state("p") == {"rate": 1.0, "valve": "closed"}
        changed = client.post("/api/modules/p/state", json={"rate": 4, "valve": "open"})
        assert changed.status_code == 200, changed.text
        assert run.state("p") == {"rate": 4.0, "valve": "open"}


def test_an_edit_is_judged_with_the_module_s_other_fields_as_they_are() -> None:
    """The State Editor judges an edit as the module's ``set_state`` does, with its other
    fields as they are: a junction controller's maximum green below its minimum was
    sent (the class refused it only in its own ``set_state``: a worker's failure, 502),
    and, judged alone, an edit was held against the class's default for the other."""
    system = System("junction").add("control", GapOut)
    with system.launch() as run, manager_client(Session(Document.empty(), run)) as client:
        run.set_state("control", min_green_s=2.0)
        changed = client.post("/api/modules/control/state", json={"max_green_s": 3})
        assert changed.status_code == 200, changed.text      # (the class's minimum is 5 s)
        refused = client.post("/api/modules/control/state", json={"min_green_s": 4})
        assert refused.status_code == 422, refused.text
        assert refused.json()["error"] == ("module control: GapOut's max_green_s (3.0) must be "
                                           "at least min_green_s (4.0)")
        state = run.state("control")
        assert (state["min_green_s"], state["max_green_s"]) == (2.0, 3.0)


def test_an_edit_of_a_module_past_its_class_s_rule_is_refused_only_what_it_brings() -> None:
    """A module whose steps took a field past its class's rule (a count): the State
    Editor refused every edit of another field, naming that count, where the module's
    own ``set_state`` takes it; an edit that breaks the rule itself is refused."""
    system = System("drifting").add("d", Drifter)
    with system.launch() as run, manager_client(Session(Document.empty(), run)) as client:
        eventually(lambda: run.state("d")["count"] > 3, what="the count past 3")
        changed = client.post("/api/modules/d/state", json={"gain": 2.0})
        assert changed.status_code == 200, changed.text
        refused = client.post("/api/modules/d/state", json={"count": 1000})
        assert refused.status_code == 422, refused.text
        assert refused.json()["error"] == ("module d: Drifter's count must be at most 3, got "
                                           "1000")


def test_a_float_field_takes_inf_and_nan_and_an_int_field_refuses_them(client, run) -> None:
    """JSON has no inf or nan, so the page could not set one (it wrote null). Sent as
    ``{"$float": "inf"}`` it is set on a float field; an int field refuses it by name."""
    for word in ("inf", "-inf", "nan"):
        changed = client.post("/api/modules/scale/state", json={"gain": {"$float": word}})
        assert changed.status_code == 200, changed.text
        assert changed.json()["fields"]["gain"] == {"type": "float", "value": None,
                                                    "text": word, "editable": True}
        assert repr(run.state("scale")["gain"]) == word
    refused = client.post("/api/modules/scale/state", json={"setups": {"$float": "inf"}})
    assert refused.status_code == 422
    assert "state 'setups' takes a whole number, got inf" in refused.json()["error"]
    assert run.state("scale")["setups"] == 1


def test_values_keep_their_types_and_a_value_that_does_not_fit_is_refused() -> None:
    """An int8 array set to [300, -200, 5] was stored as [44, 56, 5] and a float32 of
    1e300 as inf; "Edit as JSON" turned untouched floats into ints and float pairs into
    int lists (JSON has no tuples and writes 1.0 as 1); a grid whose mean overflows made
    every read of the module a bare 500, after the edit it answered was made."""
    system = System("held").add("h", Holder)
    with system.launch() as run, manager_client(Session(Document.empty(), run)) as client:
        view = client.get("/api/modules/h/state")
        assert view.status_code == 200, view.text
        assert view.json()["fields"]["cost"]["summary"]["mean"] is None      # (overflows)
        assert client.post("/api/modules/h/state", json={
            "settings": {"decay": 1, "brush": 3.5},                 # as the page sends them
            "waypoints": [[0, 0], [1, 2], [3, 4]]}).status_code == 200
        state = run.state("h")
        assert state["settings"] == {"decay": 1.0, "brush": 3.5}
        assert isinstance(state["settings"]["decay"], float)
        assert state["waypoints"] == [(0.0, 0.0), (1.0, 2.0), (3.0, 4.0)]
        assert all(isinstance(x, float) for pair in state["waypoints"] for x in pair)
        for body, words in (({"small": [300, -200, 5]}, "each from -128 to 127"),
                            ({"narrow": [1e300, 0.0]}, "each within"),
                            ({"level": 1e300}, "a number a float32 holds")):
            refused = client.post("/api/modules/h/state", json=body)
            assert refused.status_code == 422 and words in refused.json()["error"], body
        state = run.state("h")
        assert state["small"].tolist() == [0, 0, 0] and state["narrow"].tolist() == [0, 0]
        assert state["level"] == 1.0


def test_an_item_of_the_wrong_kind_inside_a_dict_or_list_is_refused_naming_its_path() -> None:
    """A dict item of another kind (``{"cal": {"offset": "z"}}`` for a float) was set as
    sent, where a top-level field of that kind is refused, and the module then failed at
    its next step. Each item is made its type, or refused by its path; nothing is set.
    A program's ``set_state`` judges a dict's items the same way."""
    system = System("held").add("h", Holder)
    with system.launch() as run, manager_client(Session(Document.empty(), run)) as client:
        for body, words in (
                ({"settings": {"decay": "z", "brush": 2.0}},
                 "state 'settings.decay' takes a number, got 'z'"),
                ({"settings": {"decay": 1.0, "brush": True}}, "state 'settings.brush'"),
                ({"waypoints": [[0.0, 0.0], [1.0, "x"]]}, "state 'waypoints.1.1'")):
            refused = client.post("/api/modules/h/state", json={**body, "level": 5.0})
            assert refused.status_code == 422, refused.text
            assert words in refused.json()["error"], body
        state = run.state("h")
        assert state["settings"] == {"decay": 1.0, "brush": 2.5} and state["level"] == 1.0
        with pytest.raises(RuntimeFailure, match=r"state 'settings.decay' takes a number"):
            run.set_state("h", settings={"decay": "z", "brush": 2.0})
        run.set_state("h", settings={"decay": 3, "brush": 2.0})
        assert run.state("h")["settings"] == {"decay": 3.0, "brush": 2.0}
        assert isinstance(run.state("h")["settings"]["decay"], float)


def test_a_state_string_that_is_not_text_is_answered_escaped_and_its_change_made_once() -> None:
    """A file name that is not UTF-8 in a module's state made every read of it a bare
    500, and so the answer to a change of another field, made all the same: the page
    said it failed, and a retry made it again."""
    system = System("named").add("f", FileNamed)
    with system.launch() as run, manager_client(Session(Document.empty(), run)) as client:
        view = client.get("/api/modules/f/state")
        assert view.status_code == 200, view.text
        assert view.json()["fields"]["last_file"]["value"] == "caf\udce9.txt"
        changed = client.post("/api/modules/f/state", json={"level": 0.75})
        assert changed.status_code == 200, changed.text
        assert run.state("f")["level"] == 0.75


# -- changing the system -------------------------------------------------------------------
def test_migrate_answers_the_report_and_refuses_an_unknown_node(client, run) -> None:
    refused = client.post("/api/modules/map/migrate", json={"to": "mars"})
    assert refused.status_code == 404 and "no node 'mars'" in refused.json()["error"]
    assert client.post("/api/modules/map/migrate", json={}).status_code == 400
    assert run.where("map") == "b"
    report = client.post("/api/modules/map/migrate", json={"to": "a"}).json()
    assert (report["module"], report["source"], report["destination"]) == ("map", "b", "a")
    assert report["pause_s"] > 0 and report["links"] == 1 and "capture_s" in report["phases"]
    assert run.where("map") == "a"


def test_swap_offers_the_classes_whose_ports_fit_and_refuses_the_others(client, run) -> None:
    fitting = client.get("/api/modules/scale/swaps").json()["classes"]
    assert "sample_modules:FastScale" in fitting and "sample_modules:Scale" not in fitting
    assert "sample_modules:Counter" not in fitting          # no input x
    unfit = client.post("/api/modules/scale/swap", json={"class": "sample_modules:Counter"})
    assert unfit.status_code == 409 and "lacks the inputs x" in unfit.json()["error"]
    unknown = client.post("/api/modules/scale/swap", json={"class": "sample_modules:Nope"})
    assert unknown.status_code == 404
    assert client.post("/api/modules/scale/swap", json={"class": 3}).status_code == 400
    module = client.post("/api/modules/scale/swap", json={"class": "os:path"}).json()
    assert module["error"].startswith("'os:path' is a module, not a class"), module
    assert run.topology().modules["scale"].cls == "sample_modules:Scale"
    swapped = client.post("/api/modules/scale/swap", json={"class": "sample_modules:FastScale"})
    assert swapped.json() == {"kept": ["gain", "setups"]}
    assert run.topology().modules["scale"].cls == "sample_modules:FastScale"


def test_add_link_and_remove_modules_with_the_words_of_pb3a_check(client, run) -> None:
    added = client.post("/api/modules", json={"name": "probe", "class": "sample_modules:Last",
                                              "node": "b", "state": {"value": 1.5}})
    assert added.status_code == 201 and added.json()["modules"]["probe"]["node"] == "b"
    assert run.state("probe")["value"] == 1.5
    taken = client.post("/api/modules", json={"name": "probe", "class": "sample_modules:Last"})
    assert taken.status_code == 409 and "runs already" in taken.json()["error"]
    assert client.post("/api/modules", json={"name": "p2", "class": "sample_modules:Last",
                                             "node": "mars"}).status_code == 404
    assert client.post("/api/modules", json={"name": "bad name", "class":
                                             "sample_modules:Last"}).status_code == 400
    # "$" matches before a final newline: "probe\n" was taken as a name, and a DELETE
    # of it removed probe
    assert client.post("/api/modules", json={"name": "probe\n", "class":
                                             "sample_modules:Last"}).status_code == 400
    newline = client.delete("/api/modules/probe%0A")
    assert newline.status_code == 400 and "line break" in newline.json()["error"]
    assert "probe" in run.topology().modules
    twice = client.post("/api/links", json={"src": "src.out", "dst": "map.x"})
    assert twice.status_code == 409 and "is fed by scale.y already" in twice.json()["error"]
    backwards = client.post("/api/links", json={"src": "probe.x", "dst": "scale.x"})
    assert backwards.status_code == 409 and "has no output 'x'" in backwards.json()["error"]
    assert client.post("/api/links", json={"src": "ghost.y", "dst": "probe.x"}).status_code \
        == 404
    assert client.post("/api/links", json={"src": "scale.y", "dst": "probe.x",
                                           "policy": "sometimes"}).status_code == 409
    assert set(run.topology().links) == {"src.out->scale.x", "scale.y->map.x"}
    linked = client.post("/api/links", json={"src": "scale.y", "dst": "probe.x",
                                             "policy": "queue:8"})
    assert linked.status_code == 200
    assert {"key": "scale.y->probe.x", "src": "scale.y", "dst": "probe.x",
            "policy": "queue:8"} in linked.json()["links"]
    relinked = client.post("/api/links", json={"src": "src.out", "dst": "probe.x",
                                               "replace": True})
    assert {link["key"] for link in relinked.json()["links"]} >= {"src.out->probe.x"}
    assert client.delete("/api/modules/probe").status_code == 200
    assert "probe" not in run.topology().modules
    assert client.delete("/api/modules/probe").status_code == 404


def test_an_add_or_link_with_a_field_of_the_wrong_kind_is_a_400_and_changes_nothing(
        client, run) -> None:
    for node in (["a"], {"a": 1}, 5):
        refused = client.post("/api/modules", json={"name": "probe", "node": node,
                                                    "class": "sample_modules:Last"})
        assert refused.status_code == 400 and "'node'" in refused.json()["error"], node
    assert "probe" not in run.topology().modules
    # "false" as a string is not false: the input's link is not replaced
    for replace in ("false", 0, "no", [True]):
        refused = client.post("/api/links", json={"src": "src.out", "dst": "map.x",
                                                  "replace": replace})
        assert refused.status_code == 400 and "'replace'" in refused.json()["error"], replace
    assert set(run.topology().links) == {"src.out->scale.x", "scale.y->map.x"}
    kept = client.post("/api/links", json={"src": "src.out", "dst": "map.x", "replace": False})
    assert kept.status_code == 409 and "is fed by scale.y already" in kept.json()["error"]
    assert set(run.topology().links) == {"src.out->scale.x", "scale.y->map.x"}

def test_a_new_module_s_state_takes_the_types_of_its_class_s_defaults(client, run) -> None:
    """``{"gain": 5}`` gave Scale's float gain an int (``pb3a add --state`` converts),
    and the State Editor then refused any fraction for it; a value that does not fit is
    refused, naming it, and nothing is added."""
    added = client.post("/api/modules", json={"name": "s2", "class": "sample_modules:Scale",
                                              "state": {"gain": 5, "setups": 0}})
    assert added.status_code == 201, added.text
    assert type(run.state("s2")["gain"]) is float and run.state("s2")["gain"] == 5.0
    assert client.post("/api/modules/s2/state", json={"gain": 2.5}).status_code == 200
    refused = client.post("/api/modules", json={"name": "s3", "class": "sample_modules:Scale",
                                                "state": {"gain": "much"}})
    assert refused.status_code == 422, refused.text
    assert refused.json()["error"] == "module s3: state 'gain' takes a number, got 'much'"
    assert "s3" not in run.topology().modules


def test_reload_drops_a_module_s_code_everywhere(client) -> None:
    assert client.post("/api/reload", json={"module": "sample_modules"}).json() == {
        "reloaded": "sample_modules"}
    assert client.post("/api/reload", json={"module": "../etc"}).status_code == 400


@pytest.mark.parametrize(("module", "why"), [
    ("numpy", "numpy is an installed package"), ("json", "standard library"),
    ("os.path", "standard library"), ("pb3a.system", "part of PB3A itself")])
def test_reload_refuses_what_the_processes_run_on(client, module: str, why: str) -> None:
    """Before, numpy was dropped from the launcher's cache (200), and could not be
    imported there again."""
    import sys

    before = sys.modules.get(module)
    refused = client.post("/api/reload", json={"module": module})
    assert refused.status_code == 409 and why in refused.json()["error"], refused.text
    assert "nothing was reloaded" in refused.json()["error"]
    assert sys.modules.get(module) is before


def test_a_body_that_is_not_plain_json_text_is_a_400_and_changes_nothing(client, run) -> None:
    """A lone surrogate (which JSON allows) was taken, and then every answer carrying
    it failed with a 500; a deep nesting was a 500 too."""
    before = client.get("/api/document").json()
    for body in (b'{"system": {"name": "s\\ud800"}}', b"[" * 100_000):
        refused = client.put("/api/document", content=body,
                             headers={"Content-Type": "application/json"})
        assert refused.status_code == 400, refused.text
    refused = client.post("/api/modules/scale/state", content=b'{"label": "x\\udfff"}',
                          headers={"Content-Type": "application/json"})
    assert refused.status_code == 400 and "not text" in refused.json()["error"]
    assert client.get("/api/document").json() == before
    huge = client.post("/api/modules/scale/state", content=b'{"gain": 1' + b"0" * 400 + b"}",
                       headers={"Content-Type": "application/json"})
    assert huge.status_code == 422 and "a number a float holds" in huge.json()["error"]
    assert run.state("scale")["gain"] == 2.0
    too_big = client.put("/api/document", content=b" " * 9_000_000,
                         headers={"Content-Type": "application/json"})
    assert too_big.status_code == 400 and "more than" in too_big.json()["error"]


def test_a_number_no_float_holds_and_the_constants_json_lacks_are_refused_by_field(
        client, run) -> None:
    """``1e400`` was read as inf and set, and ``NaN``, ``-Infinity`` (not JSON) were set
    as floats, though a float that is not finite travels only as ``{"$float": "inf"}``."""
    for body, status, words in (
            (b'{"gain": 1e400}', 422, "'gain': 1e400 is a number no float holds"),
            (b'{"gain": -2.5e999}', 422, "'gain': -2.5e999 is a number no float holds"),
            (b'{"gain": NaN}', 400, "'gain': NaN is no JSON number"),
            (b'{"gain": -Infinity}', 400, '{"$float": "-inf"}'),
            (b'{"gain": 3.0, "grid": [[1.0, Infinity]]}', 400, "'grid.0.1': Infinity")):
        refused = client.post("/api/modules/scale/state", content=body,
                              headers={"Content-Type": "application/json"})
        assert refused.status_code == status, refused.text
        assert words in refused.json()["error"], body
    assert run.state("scale")["gain"] == 2.0
    kept = client.post("/api/modules/scale/state", json={"gain": {"$float": "-inf"}})
    assert kept.status_code == 200 and run.state("scale")["gain"] == float("-inf")


def test_an_edit_made_on_an_old_copy_of_the_document_is_refused(client) -> None:
    """Two pages editing: before, the last put won, and the other page's work was gone."""
    first = client.get("/api/document").json()
    second = client.get("/api/document").json()           # another page, the same copy
    first["system"]["modules"] = {"p": {"class": "sample_modules:Last"}}
    done = client.put("/api/document", json={"system": first["system"],
                                             "revision": first["revision"]})
    assert done.status_code == 200 and done.json()["revision"] == first["revision"] + 1
    second["system"]["modules"] = {"q": {"class": "sample_modules:Last"}}
    stale = client.put("/api/document", json={"system": second["system"],
                                              "revision": second["revision"]})
    assert stale.status_code == 412 and "changed since" in stale.json()["error"]
    assert set(client.get("/api/document").json()["system"]["modules"]) == {"p"}


def test_classes_list_the_catalog_with_ports_state_and_origin(client) -> None:
    catalog = client.get("/api/classes").json()
    mapper = next(c for c in catalog["classes"] if c["class"] == "sample_modules:Mapper")
    assert mapper["kind"] == "module" and mapper["origin"] == "path"
    assert mapper["doc"].startswith("Fills an occupancy-like grid")
    assert mapper["inputs"] == {"x": {"type": "float", "policy": "latest"}}
    assert mapper["state"]["speed"] == {"type": "float", "default": 0.5}
    assert mapper["state"]["grid"]["type"] == "ndarray"
    doubler = next(c for c in catalog["classes"] if c["class"] == "sample_modules:Doubler")
    assert doubler["kind"] == "agent"


def test_the_catalog_lists_the_classes_beside_the_document(tmp_path, monkeypatch) -> None:
    """They were found there but imported by a name nothing could import (the document's
    directory was not on the import path, as it is for `pb3a run`): the list was empty."""
    project = tmp_path / "project_catalog"
    project.mkdir()
    (project / "controllers_beside.py").write_text(
        "from pb3a import Module, Output\n\n\n"
        "class Beside(Module):\n    out = Output(float)\n")
    (project / "robot.toml").write_text('name = "robot"\n')
    monkeypatch.setattr("sys.path", list(sys.path))         # (the test's own, restored)
    document = Document.open(project / "robot.toml")
    listed = Catalog(document).classes()
    assert "controllers_beside:Beside" in [c["class"] for c in listed["classes"]]
    assert not [p for p in listed["problems"] if p.startswith("controllers_beside")]


def test_a_module_server_named_without_tcp_is_a_problem_and_the_rest_is_listed(
        tmp_path) -> None:
    """``127.0.0.1:7100`` (as pb3a manager takes a launcher's address) made ZeroMQ raise
    in the catalog: every class request was a 500, and the browser empty."""
    (tmp_path / "served.toml").write_text('name = "served"\nmodule_servers = ["127.0.0.1:7100"]\n')
    listed = Catalog(Document.open(tmp_path / "served.toml"), roots=[TESTS]).classes()
    assert "sample_modules:Mapper" in [entry["class"] for entry in listed["classes"]]
    assert ("a module server's address must be a string tcp://HOST:PORT such as "
            "'tcp://10.0.0.7:7100', got '127.0.0.1:7100'") in listed["problems"]


def test_the_catalog_sees_a_class_file_written_changed_or_removed_while_it_runs(
        tmp_path, monkeypatch) -> None:
    """The catalog was read once: a class written while the manager ran was not in the
    module browser until a module was reloaded, nor was a port added to one."""
    project = tmp_path / "project_growing"
    project.mkdir()
    (project / "lab.toml").write_text('name = "lab"\n')
    monkeypatch.setattr("sys.path", list(sys.path))
    monkeypatch.setattr("sys.modules", dict(sys.modules))
    catalog = Catalog(Document.open(project / "lab.toml"))
    first = catalog.classes()
    assert catalog.classes() is first                      # nothing changed: not read again

    def later() -> dict | None:
        return next((c for c in catalog.classes()["classes"] if c["class"] == "later:Later"),
                    None)

    head = "from pb3a import Input, Module, Output\n\n\nclass Later(Module):\n"
    source = project / "later.py"
    source.write_text(head + "    out = Output(float)\n")
    assert later()["inputs"] == {} and set(later()["outputs"]) == {"out"}
    source.write_text(head + "    out = Output(float)\n    x = Input(float)\n")
    stamp = source.stat().st_mtime_ns + 1_000_000_000      # (a change within the second)
    os.utime(source, ns=(stamp, stamp))
    assert later()["inputs"] == {"x": {"type": "float", "policy": "latest"}}
    source.unlink()
    assert later() is None


def test_the_catalog_leaves_out_a_file_whose_assignment_does_a_script_s_work(
        tmp_path, monkeypatch) -> None:
    """Any assignment counted as defining a constant, so opening the module browser ran
    ``results = run_experiment()`` and wrote the file of ``done = path.write_text(...)``.
    A constant a library or a helper of the file builds is still fine (a first version
    of the rule left out ``KERNEL = _gaussian(5)`` and ``platform.system()``)."""
    project = tmp_path / "project_scripts"
    project.mkdir()
    head = "from pathlib import Path\nfrom pb3a import Module\n\n"
    (project / "experiment.py").write_text(
        head + "def run_experiment():\n    Path(__file__).with_name('RAN').write_text('x')\n\n"
        "results = run_experiment()\n\nclass Trial(Module):\n    pass\n")
    (project / "writer.py").write_text(
        head + "done = Path(__file__).with_name('RAN').write_text('x')\n\n"
        "class Writer(Module):\n    pass\n")
    (project / "constants.py").write_text(
        head + "import logging\nimport platform\nLOG = logging.getLogger(__name__)\n"
        "CONFIG = Path(__file__).with_name('x.toml')\nSYSTEM = platform.system()\n\n"
        "def _gaussian(n):\n    return [1.0] * n\n\nKERNEL = _gaussian(5)\n\n"
        "class Steady(Module):\n    pass\n")
    (project / "lab.toml").write_text('name = "lab"\n')
    monkeypatch.setattr("sys.path", list(sys.path))
    listed = Catalog(Document.open(project / "lab.toml")).classes()
    classes = [c["class"] for c in listed["classes"]]
    assert "constants:Steady" in classes
    assert "experiment:Trial" not in classes and "writer:Writer" not in classes
    assert not (project / "RAN").exists()
    for name, line in (("experiment.py", 7), ("writer.py", 4)):
        said = f"{project / name}: not imported: line {line} runs code at import"
        assert any(p.startswith(said) for p in listed["problems"]), listed["problems"]


def test_the_catalog_names_a_file_with_a_syntax_error_in_its_problems(
        tmp_path, monkeypatch) -> None:
    """A file Python cannot parse was left out of the module browser without a word
    (``problems`` empty, though they list "files not imported, and why"): it is named
    there, with the line and Python's message."""
    project = tmp_path / "project_typos"
    project.mkdir()
    (project / "typo.py").write_text("from pb3a import Input, Module\n"
                                     "class Typo(Module)\n    x = Input(float)\n")
    (project / "lab.toml").write_text('name = "lab"\n')
    monkeypatch.setattr("sys.path", list(sys.path))
    listed = Catalog(Document.open(project / "lab.toml")).classes()
    assert not [c for c in listed["classes"] if c["class"].startswith("typo:")]
    assert f"{project / 'typo.py'}: not imported: line 2: expected ':'" in listed["problems"], \
        listed["problems"]


def test_the_catalog_leaves_out_a_file_that_loops_as_imported_and_names_it(
        tmp_path, monkeypatch) -> None:
    """A file whose top level only defines things may still loop as it is imported (in a
    class body, or a module it imports): opening the module browser hung for good, and
    every later look waited for the catalog behind it. It is tried in a child process
    first now, for ``import_timeout`` seconds: left out, named in ``problems`` with what
    to do, and not tried again while the file is unchanged; the rest is listed."""
    project = tmp_path / "project_loops"
    project.mkdir()
    head = "from pb3a import Module, Output\n\n\n"
    (project / "loops_in_body.py").write_text(
        head + "class Looping(Module):\n    out = Output(float)\n    while True:\n"
        "        pass\n")
    (project / "fine_beside.py").write_text(head + "class Fine(Module):\n    out = Output(float)\n")
    (project / "lab.toml").write_text('name = "lab"\n')
    monkeypatch.setattr("sys.path", list(sys.path))
    monkeypatch.setattr("sys.modules", dict(sys.modules))
    catalog = Catalog(Document.open(project / "lab.toml"), roots=[project], import_timeout=1.0)
    listed = _bounded(catalog.classes, 30)
    assert [c["class"] for c in listed["classes"]] == ["fine_beside:Fine"]
    [problem] = listed["problems"]
    assert problem.startswith("loops_in_body: not imported: importing it did not finish "
                              f"within 1 s, stuck at {project / 'loops_in_body.py'}, line ")
    assert problem.endswith(": it loops or waits (for input, a lock, the network) as it is "
                            "imported; make it return, or give pb3a manager a longer "
                            "--import-timeout"), problem
    catalog.forget()                                  # (looked at again: not tried again)
    again = _bounded(catalog.classes, 0.9)
    assert again["problems"] == listed["problems"]


def _bounded(call: Any, timeout: float) -> Any:
    """What ``call()`` returns, failing the test if it takes longer than ``timeout``."""
    outcome: list[Any] = []
    caller = threading.Thread(target=lambda: outcome.append(call()), daemon=True)
    caller.start()
    caller.join(timeout)
    assert outcome, f"it did not return within {timeout} s"
    return outcome[0]


def test_an_unknown_route_is_a_json_404(client) -> None:
    missing = client.get("/api/nothing")
    assert missing.status_code == 404 and "docs/manager.md" in missing.json()["error"]


# -- macros --------------------------------------------------------------------------------
def test_a_macro_moves_as_a_whole_and_an_unknown_name_says_what_there_is() -> None:
    from sample_modules import Chain

    system = System("macros").node("a").node("b")
    system.add("src", FloatSource, node="a")
    system.add("pair", Chain, node="a")
    system.link("src.out", "pair.x")
    with system.launch() as run, manager_client(Session(Document.empty(), run)) as client:
        assert client.get("/api/system").json()["macros"] == {"pair": ["pair/a", "pair/b"]}
        report = client.post("/api/modules/pair/migrate", json={"to": "b"})
        assert report.status_code == 200, report.json()
        body = report.json()
        assert (body["module"], body["source"], body["destination"]) == ("pair", "a", "b")
        assert body["links"] == 2 and body["pause_s"] > 0     # src->a and a->b, each once
        assert run.where("pair/a") == run.where("pair/b") == "b" and run.where("src") == "a"
        missing = client.post("/api/modules/pai/migrate", json={"to": "a"})
        assert missing.status_code == 404
        assert "no module or macro 'pai'" in missing.json()["error"]
        assert "macros: pair" in missing.json()["error"]
        # the operations that take a module only still say "module"
        assert "no module 'pair'" in client.get("/api/modules/pair/state").json()["error"]


# -- saving a system changed live ----------------------------------------------------------
def test_the_running_system_saved_as_toml_checks_and_launches_the_same_system(
        tmp_path) -> None:
    import os
    import subprocess
    import sys

    from sample_modules import Chain

    system = managed()
    system.add("feed", FloatSource, node="b", state={"value": 0.25})
    system.add("pair", Chain, node="a")
    system.link("feed.out", "pair.x")
    with system.launch() as run, manager_client(Session(Document.empty(), run)) as client:
        # changed live: a macro's module moved, a class swapped, a module added and linked
        assert client.post("/api/modules/pair/b/migrate", json={"to": "b"}).status_code == 200
        assert client.post("/api/modules/scale/swap",
                           json={"class": "sample_modules:FastScale"}).status_code == 200
        assert client.post("/api/modules", json={"name": "probe", "class": "sample_modules:Last",
                                                 "node": "b", "state": {"value": 1.5}}
                           ).status_code == 201
        assert client.post("/api/links", json={"src": "pair/b.y", "dst": "probe.x",
                                               "policy": "queue:8"}).status_code == 200
        saved = client.get("/api/system/toml")
        assert saved.status_code == 200 and saved.headers["content-type"].startswith(
            "application/toml")
        text = saved.text
        assert text.startswith("# The system 'managed' as it ran")
        path = tmp_path / "saved.toml"
        path.write_text(text)
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS.parent), str(TESTS)])}
        check = subprocess.run([sys.executable, "-m", "pb3a", "check", str(path)], env=env,
                               capture_output=True, text=True, timeout=60)
        assert check.returncode == 0, check.stdout + check.stderr + text
        before = run.topology()
    with System.load(path).launch() as again:
        after = again.topology()
        assert {n: (m.cls, m.node) for n, m in after.modules.items()} == {
            n: (m.cls, m.node) for n, m in before.modules.items()}
        assert {k: link.policy for k, link in after.links.items()} == {
            k: link.policy for k, link in before.links.items()}
        assert after.modules["scale"].cls == "sample_modules:FastScale"
        assert after.modules["pair/b"].node == "b" and after.modules["pair/a"].node == "a"
        assert after.links["pair/b.y->probe.x"].policy == "queue:8"
        assert again.state("probe")["value"] == 1.5          # the state it was added with


def test_nothing_running_has_no_system_to_save() -> None:
    with manager_client(Session(Document.empty())) as client:
        refused = client.get("/api/system/toml")
        assert refused.status_code == 409 and "nothing runs" in refused.json()["error"]


def test_a_body_over_the_limit_is_refused_as_it_comes_on_every_route() -> None:
    """The keep and save routes (whose body may be left out) read the whole body before
    they looked at it: a client sending 20 MB, or declaring 100 MB, was buffered in full
    before it got its 400."""
    import asyncio

    token = new_token()
    app = create_app(Session(Document.empty()), Access(token, {"testserver"}))

    async def post(path: str) -> tuple[int, int]:
        chunks = 0

        async def receive() -> dict:
            nonlocal chunks
            chunks += 1
            return {"type": "http.request", "body": b" " * 1_000_000, "more_body": chunks < 20}

        sent: list[dict] = []

        async def send(message: dict) -> None:
            sent.append(message)

        await app({"type": "http", "http_version": "1.1", "method": "POST", "scheme": "http",
                   "path": path, "raw_path": path.encode(), "root_path": "",
                   "query_string": b"", "server": ("testserver", 80),
                   "client": ("127.0.0.1", 1),
                   "headers": [(b"host", b"testserver"), (b"content-type", b"application/json"),
                               (b"authorization", f"Bearer {token}".encode())]},
                  receive, send)
        return sent[0]["status"], chunks

    for path in ("/api/modules/scale/state", "/api/modules/scale/keep", "/api/document/save"):
        status, chunks = asyncio.run(post(path))
        assert status == 400 and chunks <= 9, (path, chunks)


def test_a_save_whose_body_is_not_an_object_is_a_400_and_writes_nothing(tmp_path) -> None:
    """A bare JSON string (the path, not {"path": ...}) was taken as no body: the
    document was written over its own file, not where it was asked."""
    own = tmp_path / "system.toml"
    own.write_text('name = "s"\n')
    with manager_client(Session(Document.open(own))) as client:
        revision = client.get("/api/document").json()["revision"]
        assert client.put("/api/document", json={"system": {"name": "renamed"},
                                                 "revision": revision}).status_code == 200
        for body in (str(tmp_path / "copy.toml"), ["x"], 5):
            refused = client.post("/api/document/save", json=body)
            assert refused.status_code == 400 and "\"path\"" in refused.json()["error"], body
        assert own.read_text() == 'name = "s"\n' and not (tmp_path / "copy.toml").exists()
        assert client.post("/api/document/save").status_code == 200      # no body: its file
        assert "renamed" in own.read_text()


class _Records(logging.Handler):
    """The log records of ``pb3a.manager`` and uvicorn; ``came`` is set at the first."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []
        self.came = threading.Event()

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)
        self.came.set()


@contextlib.contextmanager
def served(app: Any, access: Access) -> Iterator[int]:
    """``app`` served by uvicorn (as ``pb3a manager`` serves it) on a port of its own,
    in a thread, until the end; the port. The socket listens before uvicorn runs: a
    connection made at once waits to be taken."""
    import uvicorn

    from pb3a.manager.app import bind

    sock = bind("127.0.0.1", 0)
    port = sock.getsockname()[1]
    access.serve_at("127.0.0.1", port)
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", access_log=False,
                                           lifespan="on"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]},
                              name="test-manager-server")
    thread.start()
    try:
        yield port
    finally:
        server.should_exit = True
        thread.join(20)
        sock.close()
        assert not thread.is_alive(), "the server did not stop"


def test_a_client_gone_in_the_middle_of_its_body_is_one_line_and_changes_nothing(
        tmp_path) -> None:
    """A client that closed its connection halfway through a request's body (a page
    closed as it saved) was logged as the manager failing, with the whole traceback of
    Starlette's ClientDisconnect. It is one line, no traceback, and nothing changed."""
    pytest.importorskip("uvicorn", reason="the manager needs the 'ui' extra")
    own = tmp_path / "system.toml"
    own.write_text('name = "s"\n')
    document = Document.open(own)
    token = new_token()
    access = Access(token)
    records = _Records()
    watched = [logging.getLogger(name) for name in ("pb3a.manager", "uvicorn.error")]
    for logger in watched:
        logger.addHandler(records)
    level, watched[0].level = watched[0].level, logging.INFO
    body = b'{"system": {"name": "renamed"}, "revision": 0, "path": "elsewhere.toml"}'
    try:
        with served(create_app(Session(document), access), access) as port:
            for method, path in (("POST", "/api/document/save"), ("PUT", "/api/document"),
                                 ("POST", "/api/modules/scale/keep"),
                                 ("POST", "/api/modules/scale/state")):
                records.records.clear()
                records.came.clear()
                with socket.create_connection(("127.0.0.1", port), timeout=10) as client:
                    client.sendall(f"{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
                                   f"Authorization: Bearer {token}\r\n"
                                   "Content-Type: application/json\r\n"
                                   f"Content-Length: {len(body)}\r\n\r\n".encode()
                                   + body[:len(body) // 2])
                assert records.came.wait(10), f"{method} {path}: nothing logged"
                lines = [(r.levelno, r.getMessage(), r.exc_info) for r in records.records]
                assert len(lines) == 1 and lines[0][0] <= logging.INFO, lines
                assert "\n" not in lines[0][1] and lines[0][2] is None, lines
                assert path in lines[0][1] and "went" in lines[0][1], lines
    finally:
        watched[0].level = level
        for logger in watched:
            logger.removeHandler(records)
    assert document.revision == 0 and document.data()["name"] == "s"
    assert own.read_text() == 'name = "s"\n' and not (tmp_path / "elsewhere.toml").exists()


def test_an_edit_made_whose_read_back_times_out_answers_what_was_set() -> None:
    """The module took the edit, then did not answer the read of its state in time: the
    answer was a 504 saying nothing was done, though it was."""
    system = System("slow-read")
    system.add("slow", SlowState)
    with system.launch() as run, \
            manager_client(Session(Document.empty(), run, timeout=1.0)) as client:
        # (each read then takes 2 s, twice the manager's wait: 3 s made the test 3 s longer)
        answer = client.post("/api/modules/slow/state", json={"slow_s": 2.0})
        assert answer.status_code == 200, answer.json()
        view = answer.json()
        assert view["read_back"] is False and "slow" in view["read_back_error"]
        assert view["fields"]["slow_s"]["value"] == 2.0
        assert run.state("slow", timeout=10)["slow_s"] == 2.0         # it was set
        run.set_state("slow", slow_s=0.0, timeout=10)
        read = client.post("/api/modules/slow/state", json={"slow_s": 0.0})
        assert read.status_code == 200 and "read_back" not in read.json()
