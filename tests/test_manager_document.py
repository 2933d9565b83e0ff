"""Editing a configuration in the manager: the TOML round trip, problems in the words of
``pb3a check``, links checked as they are drawn, save, and launch from the page."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

pytest.importorskip("tomlkit", reason="the manager needs the 'ui' extra")

from conftest import alive
from test_manager_api import manager_client

from pb3a import System
from pb3a.manager.document import Document
from pb3a.manager.session import Session

pytestmark = pytest.mark.timeout(60)

PIPELINE = Path(__file__).resolve().parent.parent / "examples" / "pipeline.toml"


@pytest.fixture
def pipeline(tmp_path: Path) -> Path:
    copy = tmp_path / "pipeline.toml"
    shutil.copy(PIPELINE, copy)
    return copy


def test_an_unchanged_document_saves_byte_for_byte_and_an_edit_keeps_the_comments(
        pipeline: Path, tmp_path: Path) -> None:
    original = pipeline.read_text()
    with manager_client(Session(Document.open(pipeline))) as client:
        document = client.get("/api/document").json()
        assert document["path"] == str(pipeline) and document["problems"] == []
        assert client.get("/api/system").json()["mode"] == "editing"
        system = document["system"]
        assert client.put("/api/document", json={"system": system}).json()["problems"] == []
        saved = client.post("/api/document/save", json={"path": str(tmp_path / "same.toml")})
        assert (tmp_path / "same.toml").read_text() == original, saved.json()
        system["modules"]["scale"]["state"]["gain"] = 4.0
        system["modules"]["probe"] = {"class": "examples.pipeline:Scale"}
        system["links"].append({"from": "scale.y", "to": "probe.x"})
        assert client.put("/api/document", json={"system": system}).json()["problems"] == []
        text = client.get("/api/document/toml").text
    comments = [line for line in original.splitlines() if line.lstrip().startswith("#")]
    assert comments and all(comment in text for comment in comments)
    assert "gain = 4.0" in text and "[modules.probe]" in text
    check = tmp_path / "edited.toml"
    check.write_text(text)
    assert System.load(check).check() == []                  # pb3a check accepts it


def test_problems_and_drawn_links_use_the_words_of_pb3a_check(pipeline: Path) -> None:
    with manager_client(Session(Document.open(pipeline))) as client:
        system = client.get("/api/document").json()["system"]
        system["modules"]["scale"]["perod"] = 1.0
        problems = client.put("/api/document", json={"system": system}).json()["problems"]
        broken = pipeline.with_name("broken.toml")
        broken.write_text(client.get("/api/document/toml").text)
        assert [p.replace(str(pipeline), "F") for p in problems] == [
            p.replace(str(broken), "F") for p in System.load(broken).check()]
        assert any("unknown key 'perod'" in p for p in problems)
        good = client.post("/api/document/check-link", json={"src": "scale.y",
                                                              "dst": "tick.out"}).json()
        assert good["ok"] is False and "is an output" in good["message"]
        twice = client.post("/api/document/check-link", json={"src": "tick.out",
                                                               "dst": "scale.x"}).json()
        assert twice["ok"] is False and "is fed twice" in twice["message"]
        assert client.post("/api/document/check-link", json={"src": 1}).status_code == 400
        refused = client.post("/api/document/launch")
        assert refused.status_code == 409 and "perod" in refused.json()["error"]
        assert client.get("/api/system").json()["mode"] == "editing"
        assert client.put("/api/document", json={"nodes": {}}).status_code == 400


def test_a_document_launched_from_the_page_runs_and_stops_with_the_app(pipeline: Path) -> None:
    with manager_client(Session(Document.open(pipeline))) as client:
        launched = client.post("/api/document/launch")
        assert launched.status_code == 200 and launched.json()["mode"] == "running"
        assert launched.json()["address"].startswith("tcp://127.0.0.1:")
        assert set(client.get("/api/stats").json()["modules"]) >= {"tick", "scale"}
        again = client.post("/api/document/launch")
        assert again.status_code == 409 and "runs already" in again.json()["error"]
        pids = [m["pid"] for m in client.get("/api/stats").json()["modules"].values()]
    assert pids and not any(alive(pid) for pid in pids if pid)


def test_nothing_runs_in_an_empty_document_and_saving_needs_a_path() -> None:
    with manager_client(Session(Document.empty())) as client:
        assert client.get("/api/system").json()["modules"] == {}
        nothing = client.get("/api/stats")
        assert nothing.status_code == 409 and "nothing runs" in nothing.json()["error"]
        unsaved = client.post("/api/document/save")
        assert unsaved.status_code == 400 and "give the path" in unsaved.json()["error"]
