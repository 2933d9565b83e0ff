"""Editing a configuration in the manager: the TOML round trip, problems in the words of
``pb3a check``, links checked as they are drawn, a file opened from the page, save, and
launch from the page."""

from __future__ import annotations

import copy
import errno
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("tomlkit", reason="the manager needs the 'ui' extra")

from conftest import alive
from test_manager_api import manager_client

from pb3a import System
from pb3a.manager.catalog import Catalog
from pb3a.manager.document import Document
from pb3a.manager.session import Session

pytestmark = pytest.mark.timeout(60)

TESTS = Path(__file__).resolve().parent
PIPELINE = TESTS.parent / "examples" / "pipeline.toml"


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


def test_a_file_with_windows_line_ends_keeps_them_when_saved(pipeline: Path,
                                                             tmp_path: Path) -> None:
    """Read with Python's universal newlines and written with "\\n", a file from
    Windows came back with every line changed (its version control showed the whole
    file as edited) though nothing was."""
    crlf = pipeline.read_bytes().replace(b"\n", b"\r\n")
    pipeline.write_bytes(crlf)
    document = Document.open(pipeline)
    document.save()
    assert pipeline.read_bytes() == crlf                        # unchanged: byte for byte
    with manager_client(Session(document)) as client:
        system = client.get("/api/document").json()["system"]
        system["modules"]["scale"]["state"]["gain"] = 4.0
        assert client.put("/api/document", json={"system": system}).status_code == 200
        assert client.post("/api/document/save", json={}).status_code == 200
        # one opened in the page (its text as the browser read it) keeps them too
        opened = client.post("/api/document/open", json={"name": "pipeline.toml",
                                                         "toml": crlf.decode()})
        assert opened.status_code == 200, opened.json()
        saved = client.post("/api/document/save", json={"path": str(tmp_path / "a.toml")})
        assert saved.status_code == 200, saved.json()
    edited = pipeline.read_bytes()
    assert b"gain = 4.0 }\r\n" in edited and b"\n" not in edited.replace(b"\r\n", b"")
    assert (tmp_path / "a.toml").read_bytes() == crlf
    # a file of LF lines with one CRLF pasted in keeps its LF (all were made CRLF)
    mixed = PIPELINE.read_bytes().replace(b"\n", b"\r\n", 1)
    pipeline.write_bytes(mixed)
    Document.open(pipeline).save()
    assert pipeline.read_bytes().count(b"\r\n") <= 1


def test_a_file_with_a_byte_order_mark_opens_and_keeps_it_when_saved(pipeline: Path) -> None:
    """Windows editors begin a UTF-8 file with a byte order mark, which tomlkit refuses:
    such a file did not open ("Empty key at line 1 col 0")."""
    marked = b"\xef\xbb\xbf" + pipeline.read_bytes()
    pipeline.write_bytes(marked)
    document = Document.open(pipeline)
    assert document.problems() == [] and document.data()["name"] == "pipeline"
    document.save()
    assert pipeline.read_bytes() == marked                      # unchanged: byte for byte
    document.edit(lambda system: system["modules"]["scale"]["state"].update(gain=4.0) or True)
    document.save()                  # (what it read there, its mark aside: no ChangedOnDisk)
    edited = pipeline.read_bytes()
    assert edited.startswith(b"\xef\xbb\xbf") and b"gain = 4.0" in edited
    assert edited.count(b"\xef\xbb\xbf") == 1 and System.load(pipeline).check() == []


_SAVE_ON_A_FULL_DISK = """
import resource, signal, sys
from pb3a.manager.document import Document
document = Document.open(sys.argv[1])
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)       # (a file too large: an OSError)
resource.setrlimit(resource.RLIMIT_FSIZE, (100, 100))    # the disk full after 100 bytes
try:
    document.save()
except OSError as exc:
    print(exc.errno)
"""


def test_a_save_that_fails_half_way_leaves_the_file_as_it_was(pipeline: Path) -> None:
    """Written in place, a save on a full disk left the file cut off after what fitted,
    no longer TOML, and the next save said it had changed on disk."""
    original = pipeline.read_text()
    assert len(original) > 100
    done = subprocess.run([sys.executable, "-c", _SAVE_ON_A_FULL_DISK, str(pipeline)],
                          capture_output=True, text=True, timeout=30,
                          env={**os.environ, "PYTHONPATH": str(PIPELINE.parent.parent)})
    assert done.stdout.strip() == str(errno.EFBIG), done.stderr
    assert pipeline.read_text() == original
    assert sorted(p.name for p in pipeline.parent.iterdir()) == ["pipeline.toml"]


def test_a_save_over_edits_made_on_disk_is_refused_unless_asked_to_overwrite(
        pipeline: Path, tmp_path: Path) -> None:
    """A file edited in another editor while the page had it open was overwritten by
    Save without a word (a module and a comment added there were gone). A save over
    what this document never read there, or over another file, is a 409 naming the
    file, nothing written; ``overwrite`` writes it all the same."""
    with manager_client(Session(Document.open(pipeline))) as client:
        system = client.get("/api/document").json()["system"]
        system["modules"]["scale"]["state"]["gain"] = 4.0
        assert client.put("/api/document", json={"system": system}).status_code == 200
        edited_there = pipeline.read_text() + "\n# added in another editor\n"
        pipeline.write_text(edited_there)
        refused = client.post("/api/document/save")
        assert refused.status_code == 409, refused.json()
        assert refused.json()["error"] == f"{pipeline} changed on disk since it was opened here"
        assert pipeline.read_text() == edited_there                       # nothing written
        other = tmp_path / "other.toml"
        other.write_text('name = "other"\n')
        onto = client.post("/api/document/save", json={"path": str(other)})
        assert onto.status_code == 409 and "is another file" in onto.json()["error"]
        assert other.read_text() == 'name = "other"\n'
        assert client.post("/api/document/save", json={"overwrite": True}).status_code == 200
        assert "gain = 4.0" in pipeline.read_text()
        system["modules"]["scale"]["state"]["gain"] = 5.0             # saved again: its own
        assert client.put("/api/document", json={"system": system}).status_code == 200
        assert client.post("/api/document/save").status_code == 200
        assert "gain = 5.0" in pipeline.read_text()
        malformed = client.post("/api/document/save", json={"overwrite": "yes"})
        assert malformed.status_code == 400, malformed.json()


def test_values_the_page_cannot_hold_exactly_come_back_unchanged(tmp_path: Path) -> None:
    """The page holds the document as JSON: a date in a state made GET /api/document a
    500; a whole number beyond 2**53, read by the browser as a double, was written back
    rounded (1700000000123456789 became ...800) though nobody touched it, also when the
    list it is in was edited; an edited date was saved as a string."""
    big = 1700000000123456789
    original = ('name = "stamped"\n\n[modules.stamp]\nclass = "examples.pipeline:Scale"\n'
                f"state = {{ started = 2024-05-01T12:00:00Z, count = {big}, ids = [{big}, 5], "
                "days = [2024-01-01, 2024-02-01] }\n")
    path = tmp_path / "stamped.toml"
    path.write_text(original)

    def as_the_browser_holds(value: object) -> object:      # its numbers are doubles
        if isinstance(value, list):
            return [as_the_browser_holds(item) for item in value]
        return int(float(value)) if isinstance(value, int) and value > 2 ** 53 else value

    with manager_client(Session(Document.open(path))) as client:
        document = client.get("/api/document")
        assert document.status_code == 200, document.text
        system = document.json()["system"]
        state = system["modules"]["stamp"]["state"]
        assert state["started"] == "2024-05-01T12:00:00+00:00"
        state.update({key: as_the_browser_holds(state[key]) for key in ("count", "ids")})
        assert client.put("/api/document", json={"system": system}).status_code == 200
        assert client.get("/api/document/toml").text == original
        state["ids"][1], state["days"][1] = 6, "2024-03-01"          # edits in the page
        client.put("/api/document", json={"system": system})
        text = client.get("/api/document/toml").text
        assert f"ids = [{big}, 6]" in text and "days = [2024-01-01, 2024-03-01]" in text
        state["count"] = big + 22                                    # a script's, exact
        client.put("/api/document", json={"system": system})
        assert f"count = {big + 22}," in client.get("/api/document/toml").text



def test_modules_grouped_into_a_macro_keep_their_floats(pipeline: Path) -> None:
    """Grouping moves module entries into a macro's table, where nothing held them to
    compare with: ``gain = 3.0``, untouched, came back as the page holds it, ``gain = 3``."""
    with manager_client(Session(Document.open(pipeline))) as client:
        system = client.get("/api/document").json()["system"]
        scale = system["modules"].pop("scale")
        scale["state"]["gain"] = 3                        # as the page holds 3.0 (JavaScript)
        system["macros"] = {"stage": {"modules": {"scale": scale}, "exports": {"x": "scale.x"}}}
        system["modules"]["stage"] = {"macro": "stage"}
        system["links"] = [{"from": "tick.out", "to": "stage.x", "policy": "queue:64"}]
        answer = client.put("/api/document", json={"system": system})
        assert answer.status_code == 200 and answer.json()["problems"] == [], answer.json()
        text = client.get("/api/document/toml").text
    assert "gain = 3.0" in text, text


CHAIN = """\
# A chain of scales.
name = "chain"

[nodes.a]
[nodes.b]

# the source
[modules.ticker]
class = "examples.pipeline:Ticker"
node = "a"

# the first scale: doubles
[modules.scale]   # first
class = "examples.pipeline:Scale"  # the class
node = "b"
# found by hand
state = { gain = 2.0 }  # doubles
# end of scale

# the second scale
[modules.scale2]
class = "examples.pipeline:Scale"
node = "b"

[modules.scale2.state]
gain = 0.5  # halves

# ---- links

# scale into scale2
[[links]]
from = "scale.y"
to = "scale2.x"
policy = "queue:8"  # no loss

# ticker into the chain
[[links]]
from = "ticker.out"
to = "scale.x"  # the first input
"""

CHAIN_GROUPED = """\
# A chain of scales.
name = "chain"

[nodes.a]
[nodes.b]

# the source
[modules.ticker]
class = "examples.pipeline:Ticker"
node = "a"

[modules.stage]
macro = "stage"
node = "b"

# ---- links

# ticker into the chain
[[links]]
from = "ticker.out"
to = "stage.x"  # the first input

# the first scale: doubles
[macros.stage.modules.scale]   # first
class = "examples.pipeline:Scale"  # the class
# found by hand
state = { gain = 2.0 }  # doubles
# end of scale

# the second scale
[macros.stage.modules.scale2]
class = "examples.pipeline:Scale"

[macros.stage.modules.scale2.state]
gain = 0.5  # halves

# scale into scale2
[[macros.stage.links]]
from = "scale.y"
to = "scale2.x"
policy = "queue:8"  # no loss

[macros.stage.exports]
x = "scale.x"

"""


def _grouped(system: dict[str, Any]) -> dict[str, Any]:
    """``CHAIN``'s system as the page's Group into macro sends it: scale and scale2 in
    macro stage (their node the instance's), the link between them its own, the one
    from outside ending on its export."""
    system = copy.deepcopy(system)
    modules = system["modules"]
    children = {name: {key: value for key, value in modules.pop(name).items() if key != "node"}
                for name in ("scale", "scale2")}
    modules["stage"] = {"macro": "stage", "node": "b"}
    inner, outer = system["links"]
    system["links"] = [{**outer, "to": "stage.x"}]
    system["macros"] = {"stage": {"modules": children, "links": [inner],
                                  "exports": {"x": "scale.x"}}}
    return system


def test_modules_grouped_into_a_macro_keep_their_comments_and_so_do_their_links(
        tmp_path: Path) -> None:
    """Grouping rebuilt the moved modules' tables from their values: the comments above
    them, on their headers, keys and state, and on the link between them, were lost.
    They move with them into the macro (a key dropped takes its own), the others stay
    where they were, the outside link keeps its own (the link that moved is not taken
    for it), and the file is saved as before; placing the macro again changes none of
    them, nor does moving the modules out of it again."""
    path = tmp_path / "chain.toml"
    path.write_text(CHAIN)
    with manager_client(Session(Document.open(path))) as client:
        original = client.get("/api/document").json()["system"]
        answer = client.put("/api/document", json={"system": _grouped(original)})
        assert answer.status_code == 200 and answer.json()["problems"] == [], answer.text
        assert client.get("/api/document/toml").text == CHAIN_GROUPED
        assert client.post("/api/document/save", json={"overwrite": True}).status_code == 200
        assert path.read_text() == CHAIN_GROUPED
        assert Document.open(path).data() == client.get("/api/document").json()["system"]

        system = client.get("/api/document").json()["system"]
        system["modules"]["stage2"] = {"macro": "stage", "node": "a"}      # placed again
        assert client.put("/api/document", json={"system": system}).status_code == 200
        assert client.get("/api/document/toml").text == CHAIN_GROUPED.replace(
            '# ---- links', '[modules.stage2]\nmacro = "stage"\nnode = "a"\n\n# ---- links')

        del system["modules"]["stage2"]
        assert client.put("/api/document", json={"system": system}).status_code == 200
        assert client.put("/api/document", json={"system": original}).status_code == 200
        ungrouped = client.get("/api/document/toml").text
    # (each node given again after the other keys; the blank line that ended the macro's
    # last table is left at the end, as where any table is removed)
    assert ungrouped == CHAIN.replace(
        'node = "b"\n# found by hand\nstate = { gain = 2.0 }  # doubles\n',
        '# found by hand\nstate = { gain = 2.0 }  # doubles\nnode = "b"\n') + "\n"


def test_a_whole_number_typed_into_a_float_field_is_saved_as_a_float(pipeline: Path) -> None:
    """JSON writes 7.0 as 7: a float field edited in the page to a whole number was
    saved as an int (``gain = 7``), which ``pb3a check`` then took for another type."""
    with manager_client(Session(Document.open(pipeline))) as client:
        system = client.get("/api/document").json()["system"]
        system["modules"]["scale"]["state"]["gain"] = 7
        system["modules"]["tick"]["state"]["count"] = 5             # an int stays one
        assert client.put("/api/document", json={"system": system}).status_code == 200
        text = client.get("/api/document/toml").text
    assert "gain = 7.0" in text and "count = 5" in text, text


UNSET = """\
name = "unset"

[modules.scale]
class = "examples.pipeline:Scale"

[modules.ctl]
class = "manager_modules:Controller"
state = { kp = 3, limits = [-1, 1] }  # written by hand

[modules.held]
class = "manager_modules:Holder"

[modules.loop]
macro = "loop"

[macros.loop.modules.inner]
class = "manager_modules:Controller"
"""


def test_a_whole_number_for_a_float_field_the_document_did_not_set_is_saved_as_a_float(
        tmp_path: Path) -> None:
    """Only a float the document held made a whole number typed over it a float: set in
    a field the document did not set yet, 3 was saved ``gain = 3`` (and ``[-2, 2]`` for a
    pair of floats, an instance's override ``kd = 1``), and the module got an int. The
    class's declared type decides, in a module's state, a macro's module's and an
    instance's overrides, item by item in lists, dicts and float arrays; an edit made by
    the server (``Document.edit``, as Keep writes) too; an int field keeps its int, and
    a whole number the file holds and nobody changed stays as written."""
    path = tmp_path / "unset.toml"
    path.write_text(UNSET)
    document = Document.open(path)
    with manager_client(Session(document)) as client:
        system = client.get("/api/document").json()["system"]
        modules = system["modules"]
        modules["scale"]["state"] = {"gain": 3}
        modules["ctl"]["state"]["ki"] = 2
        modules["held"]["state"] = {"settings": {"decay": 1, "brush": 2}, "narrow": [1, 2],
                                    "small": [1, 2], "waypoints": [[0, 0], [3, 4], [5, 6]]}
        modules["loop"]["state"] = {"inner": {"kd": 1}}
        system["macros"]["loop"]["modules"]["inner"]["state"] = {"ki": 4, "mode": "manual"}
        answer = client.put("/api/document", json={"system": system})
        assert answer.status_code == 200 and answer.json()["problems"] == [], answer.text
        text = client.get("/api/document/toml").text
        assert "state = {gain = 3.0}" in text, text
        assert "state = { kp = 3, limits = [-1, 1], ki = 2.0}  # written by hand" in text
        assert "state = {inner = {kd = 1.0}}" in text
        assert 'state = {ki = 4.0, mode = "manual"}' in text
        held = tomllib.loads(text)["modules"]["held"]["state"]
        assert held == {"settings": {"decay": 1.0, "brush": 2.0}, "narrow": [1.0, 2.0],
                        "small": [1, 2], "waypoints": [[0.0, 0.0], [3.0, 4.0], [5.0, 6.0]]}
        assert [type(number) for number in (*held["settings"].values(), *held["narrow"],
                                            *held["waypoints"][2])] == [float] * 6
        assert [type(number) for number in held["small"]] == [int, int]      # an int8 array
        modules["ctl"]["state"]["limits"] = [-1, 2]          # a list written anew: all floats
        client.put("/api/document", json={"system": system})
        assert "kp = 3, limits = [-1.0, 2.0], ki = 2.0}" in client.get(
            "/api/document/toml").text
    document.edit(lambda tables: tables["modules"]["scale"]["state"].update(gain=5) is None)
    assert "state = {gain = 5.0}" in document.toml()


def test_a_float_that_is_not_finite_travels_as_its_toml_word_and_is_saved_so(
        tmp_path: Path) -> None:
    """JSON has no inf or nan: a document holding ``inf`` made GET /api/document a 500,
    and the page had no way to send one. Both ways it travels as ``{"$float": "inf"}``,
    is written ``inf`` in the TOML, and one left untouched (nan too) keeps its line."""
    original = ('name = "bounds"\n\n[modules.scale]\nclass = "examples.pipeline:Scale"\n'
                "state = { gain = nan, low = -inf }  # not set yet\n")
    path = tmp_path / "bounds.toml"
    path.write_text(original)
    with manager_client(Session(Document.open(path))) as client:
        document = client.get("/api/document")
        assert document.status_code == 200, document.text
        system = document.json()["system"]
        assert system["modules"]["scale"]["state"] == {"gain": {"$float": "nan"},
                                                        "low": {"$float": "-inf"}}
        assert client.put("/api/document", json={"system": system}).status_code == 200
        assert client.get("/api/document/toml").text == original
        system["modules"]["scale"]["state"]["gain"] = {"$float": "inf"}     # typed inf
        answer = client.put("/api/document", json={"system": system})
        assert answer.status_code == 200, answer.text
        assert answer.json()["system"]["modules"]["scale"]["state"]["gain"] == {"$float": "inf"}
        text = client.get("/api/document/toml").text
    assert "state = { gain = inf, low = -inf }  # not set yet" in text, text


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


def test_a_system_launched_from_the_page_stops_from_it_and_its_document_is_edited_again(
        pipeline: Path) -> None:
    """Once launched, the page had no way to stop the system and edit on: Stop stops the
    one it launched (every worker gone) and the document is edited again; a system the
    manager only attached to is not its to stop."""
    with manager_client(Session(Document.open(pipeline))) as client:
        assert client.post("/api/system/stop").status_code == 409          # nothing runs
        launched = client.post("/api/document/launch").json()
        assert launched["mode"] == "running" and launched["stoppable"] is True
        pids = [m["pid"] for m in client.get("/api/stats").json()["modules"].values()]
        stopped = client.post("/api/system/stop")
        assert stopped.status_code == 200, stopped.json()
        assert stopped.json()["mode"] == "editing" and stopped.json()["stoppable"] is False
        assert pids and not any(alive(pid) for pid in pids if pid)
        assert client.get("/api/document").json()["problems"] == []
        assert client.post("/api/document/launch").json()["mode"] == "running"   # again
    with System.load(pipeline).launch() as run, \
            manager_client(Session(Document.empty(), run)) as client:
        attached = client.get("/api/system").json()
        assert attached["mode"] == "running" and attached["stoppable"] is False
        refused = client.post("/api/system/stop")
        assert refused.status_code == 409 and "stop it where it runs" in refused.json()["error"]
        assert run.stats().modules["tick"].status == "running"


FIXED = """\
name = "paced"

[modules.tick]
class = "examples.pipeline:Ticker"
period = 0.05
fixed_rate = true   # a control loop's dt

[modules.pace]
class = "manager_modules:Paced"
state = { work = 0.05 }

[modules.scale]
class = "examples.pipeline:Scale"

[[links]]
from = "tick.out"
to = "scale.x"
"""


def test_a_fixed_rate_is_kept_through_edits_and_shown_as_the_module_s_period_is(
        tmp_path: Path) -> None:
    """The manager knew no fixed rate: its structure said each module's period but not
    whether its steps are due at a fixed rate, nor did the module browser say a class's,
    and an add from the page could not give one. A file's ``fixed_rate`` goes through an
    edit, a save, a launch and a stop as written; the structure says each module's
    (the document's, else its class's), running or not; an add takes one."""
    path = tmp_path / "paced.toml"
    path.write_text(FIXED)
    document = Document.open(path)
    with manager_client(Session(document, catalog=Catalog(document, roots=[TESTS]))) as client:
        system = client.get("/api/document").json()["system"]
        assert system["modules"]["tick"]["fixed_rate"] is True
        system["modules"]["scale"]["state"] = {"gain": 4.0}
        assert client.put("/api/document", json={"system": system}).json()["problems"] == []
        assert client.post("/api/document/save", json={}).status_code == 200
        assert "fixed_rate = true   # a control loop's dt" in path.read_text()
        fixed = {name: m["fixed_rate"] for name, m in client.get("/api/system").json()[
            "modules"].items()}
        assert fixed == {"tick": True, "pace": True, "scale": False}
        classes = {c["class"]: c for c in client.get("/api/classes").json()["classes"]}
        assert classes["manager_modules:Paced"]["fixed_rate"] is True
        assert classes["manager_modules:Controller"]["fixed_rate"] is False
        running = client.post("/api/document/launch").json()
        assert {name: m["fixed_rate"] for name, m in running["modules"].items()} == fixed
        stats = client.get("/api/stats").json()["modules"]
        assert stats["tick"]["fixed_rate"] is True and stats["scale"]["fixed_rate"] is False
        added = client.post("/api/modules", json={"name": "tick2", "period": 0.05,
                                                  "class": "examples.pipeline:Ticker",
                                                  "fixed_rate": True})
        assert added.status_code == 201, added.text
        assert added.json()["modules"]["tick2"]["fixed_rate"] is True
        refused = client.post("/api/modules", json={"name": "tick3", "fixed_rate": "yes",
                                                    "class": "examples.pipeline:Ticker"})
        assert refused.status_code == 400 and "'fixed_rate'" in refused.json()["error"]
        assert client.post("/api/system/stop").status_code == 200
        assert client.get("/api/document").json()["system"]["modules"]["tick"][
            "fixed_rate"] is True
    assert System.load(path).check() == []


def test_nothing_runs_in_an_empty_document_and_saving_needs_a_path() -> None:
    with manager_client(Session(Document.empty())) as client:
        assert client.get("/api/system").json()["modules"] == {}
        nothing = client.get("/api/stats")
        assert nothing.status_code == 409 and "nothing runs" in nothing.json()["error"]
        unsaved = client.post("/api/document/save")
        assert unsaved.status_code == 400 and "give the path" in unsaved.json()["error"]


OPENED = """\
# Two scales in a row, opened from the page.
name = "opened"

[nodes.a]

[modules.tick]
class = "examples.pipeline:Ticker"
node = "a"  # where it runs

[modules.double]
class = "examples.pipeline:Scale"
node = "a"
state = { gain = 2.0 }

[[links]]
from = "tick.out"
to = "double.x"
"""


def test_a_file_opened_from_the_page_is_checked_then_becomes_the_document(
        pipeline: Path, tmp_path: Path) -> None:
    with manager_client(Session(Document.open(pipeline))) as client:
        before = client.get("/api/document/toml").text
        # not TOML, or refused by pb3a check: 409 with the checker's words, nothing changes
        garbled = client.post("/api/document/open", json={"name": "garbled.toml",
                                                          "toml": "name = \n[modules"})
        assert garbled.status_code == 409
        assert garbled.json()["error"].startswith("garbled.toml: not valid TOML")
        bad_text = OPENED.replace("node = \"a\"  #", "perod = 1.0\nnode = \"a\"  #").replace(
            "examples.pipeline:Scale", "examples.pipeline:Nope")
        bad = tmp_path / "bad.toml"
        bad.write_text(bad_text)
        checked = [problem.replace(str(bad), "bad.toml") for problem in System.load(bad).check()]
        assert any("perod" in p for p in checked) and any("Nope" in p for p in checked)
        refused = client.post("/api/document/open", json={"name": "bad.toml", "toml": bad_text})
        assert refused.status_code == 409 and refused.json()["problems"] == checked
        for malformed in ({}, {"toml": 3}, {"name": 3, "toml": OPENED}, ["x"]):
            assert client.post("/api/document/open", json=malformed).status_code == 400
        long = client.post("/api/document/open", json={"name": "x" * 300 + ".toml",
                                                       "toml": OPENED})     # (it was a 500)
        assert long.status_code == 400 and "at most 255 bytes" in long.json()["error"]
        assert client.get("/api/document/toml").text == before
        assert client.get("/api/system").json()["name"] == "pipeline"
        # a good file: the document, as written (comments too), with no path to save to
        opened = client.post("/api/document/open", json={"name": "../elsewhere/opened.toml",
                                                         "toml": OPENED})
        assert opened.status_code == 200, opened.json()
        assert opened.json()["path"] is None and opened.json()["problems"] == []
        assert opened.json()["system"]["modules"]["double"]["state"] == {"gain": 2.0}
        assert client.get("/api/document/toml").text == OPENED
        system = client.get("/api/system").json()
        assert system["name"] == "opened" and system["mode"] == "editing"
        assert {name: m["node"] for name, m in system["modules"].items()} == {
            "tick": "a", "double": "a"}
        # its problems from now on name the file it came from (its name only)
        edited = opened.json()["system"]
        edited["modules"]["double"]["perod"] = 1.0
        problems = client.put("/api/document", json={"system": edited}).json()["problems"]
        assert problems and all(p.startswith("opened.toml") for p in problems), problems
        del edited["modules"]["double"]["perod"]
        assert client.put("/api/document", json={"system": edited}).json()["problems"] == []
        unsaved = client.post("/api/document/save")
        assert unsaved.status_code == 400 and "give the path" in unsaved.json()["error"]
        nameless = client.post("/api/document/save", json={"path": " "})
        assert nameless.status_code == 400, nameless.json()
        assert nameless.json()["error"] == "'path' must be a file name, got ' '"
        saved = tmp_path / "saved.toml"
        assert client.post("/api/document/save", json={"path": str(saved)}).status_code == 200
        assert saved.read_text() == OPENED
        assert not (tmp_path.parent / "elsewhere").exists()
        launched = client.post("/api/document/launch")
        assert launched.status_code == 200 and set(launched.json()["modules"]) == {"tick",
                                                                                  "double"}


def test_an_edit_toml_cannot_hold_is_refused_and_changes_nothing(pipeline: Path) -> None:
    with manager_client(Session(Document.open(pipeline))) as client:
        before = client.get("/api/document/toml").text
        system = client.get("/api/document").json()["system"]
        # a null inside an array (TOML has none): at the top, after keys the merge drops
        # first, and deep in an initial state (the page's Edit as JSON can send one)
        for unfit in ({"name": "renamed", "module_servers": ["tcp://127.0.0.1:1", None]},
                      {**system, "modules": {**system["modules"], "scale": {
                          **system["modules"]["scale"], "state": {"poses": [[1, None]]}}}}):
            refused = client.put("/api/document", json={"system": unfit})
            assert refused.status_code == 400, refused.text
            assert "TOML" in refused.json()["error"]
            assert client.get("/api/document/toml").text == before
        assert client.put("/api/document", json={"system": system}).status_code == 200
        assert client.get("/api/document/toml").text == before



def test_a_value_nested_deeper_than_toml_reads_is_a_400_and_the_document_stays_editable(
        pipeline: Path) -> None:
    """A value nested 200 levels deep (the page's Edit as JSON can send one) was taken:
    every later edit of the document was a 500 (RecursionError, copying it), and the
    file saved would not open again (the TOML reader takes 100 levels); 500 deep, the
    edit itself was a 500. Such an edit is a 400 naming where, nothing changed; 100
    levels are fine, and open again."""
    def nested(levels: int) -> str:
        return '{"k": ' * levels + "1" + "}" * levels

    with manager_client(Session(Document.open(pipeline))) as client:
        before = client.get("/api/document/toml").text
        for levels in (101, 200, 500):
            refused = client.put("/api/document", content='{"system": {"name": "deep", '
                                 f'"state_of_the_art": {nested(levels)}}}}}')
            assert refused.status_code == 400, (levels, refused.text[:300])
            assert "state_of_the_art.k.k" in refused.json()["error"]
            assert "more than 100 levels" in refused.json()["error"]
            assert client.get("/api/document/toml").text == before
        system = client.get("/api/document").json()["system"]
        system["modules"]["scale"]["state"] = {"deep": {"k": 1}}
        for _ in range(100 - 4):            # modules.scale.state.deep: 4 levels of the 100
            system["modules"]["scale"]["state"]["deep"] = {
                "k": system["modules"]["scale"]["state"]["deep"]}
        assert client.put("/api/document", json={"system": system}).status_code == 200
        system["name"] = "renamed"                  # and the next edit is made
        assert client.put("/api/document", json={"system": system}).status_code == 200
        text = client.get("/api/document/toml").text
    assert Document(text).data()["name"] == "renamed"            # it opens again


COMMENTED = '''\
# A commented system.
name = "commented"

# the modules
[modules.tick]
class = "examples.pipeline:Ticker"
period = 0.005  # fast

# the first scale
[modules.a]
class = "examples.pipeline:Scale"

# the second scale
[modules.b]
class = "examples.pipeline:Scale"
# where it runs
node = "n"

# the last scale
[modules.c]
class = "examples.pipeline:Scale"

# ---- links ----

# link one
[[links]]
from = "tick.out"
to = "a.x"

# link two
[[links]]
from = "a.y"
to = "b.x"  # two's to

# link three
[[links]]
from = "b.y"
to = "c.x"
# the last link's own
'''
LINK_ONE = '# link one\n[[links]]\nfrom = "tick.out"\nto = "a.x"\n\n'
LINK_TWO = '# link two\n[[links]]\nfrom = "a.y"\nto = "b.x"  # two\'s to\n\n'
LINK_THREE = '\n# link three\n[[links]]\nfrom = "b.y"\nto = "c.x"\n# the last link\'s own\n'
SCALE = 'class = "examples.pipeline:Scale"\n'
TICK = ('\n# the modules\n[modules.tick]\nclass = "examples.pipeline:Ticker"\n'
        'period = 0.005  # fast\n')
LAST = f'# the last scale\n[modules.c]\n{SCALE}\n'
NEW_LINK = '[[links]]\nfrom = "c.y"\nto = "tick.in"\n\n'


def test_a_module_or_node_added_to_a_file_that_writes_them_inline_stays_inline() -> None:
    """A file with ``modules = { tick = {...} }``: a module (or node) added from the page
    was made a [table] inside that inline table, and the edit refused as one "TOML
    cannot hold"."""
    text = ('name = "s"\nnodes = { a = {} }\n'
            'modules = { tick = { class = "examples.pipeline:Ticker" } }  # the modules\n')
    with manager_client(Session(Document(text))) as client:
        document = client.get("/api/document").json()
        system = document["system"]
        system["modules"]["scale"] = {"class": "examples.pipeline:Scale",
                                      "state": {"gain": 2.0}}
        system["nodes"]["b"] = {}
        put = client.put("/api/document", json={"system": system,
                                                "revision": document["revision"]})
        assert put.status_code == 200, put.text
        written = client.get("/api/document/toml").text
        assert tomllib.loads(written) == system
        assert written.startswith('name = "s"\nnodes = { a = {}, b = {}}\nmodules = { tick = ')
        assert written.rstrip().endswith("# the modules")


def _without(text: str, *parts: str) -> str:
    for part in parts:
        assert text.count(part) == 1, part
        text = text.replace(part, "")
    return text


def _links(edit: Any) -> Any:
    return lambda system: system.__setitem__("links", edit(system["links"]))


@pytest.mark.parametrize(("edit", "expected"), [
    (_links(lambda links: links[1:]), _without(COMMENTED, LINK_ONE)),
    (_links(lambda links: [links[0], links[2]]), _without(COMMENTED, LINK_TWO)),
    (_links(lambda links: links[:2]), _without(COMMENTED, LINK_THREE)),
    (_links(lambda links: links[2:]), _without(COMMENTED, LINK_ONE, LINK_TWO)),
    (lambda system: system.pop("links"), COMMENTED.split("\n# link one")[0]),
    (lambda system: system["modules"].pop("tick"), _without(COMMENTED, TICK)),
    (lambda system: system["modules"].pop("c"), _without(COMMENTED, LAST)),
    (lambda system: system["modules"]["b"].pop("node"),
     _without(COMMENTED, '# where it runs\nnode = "n"\n')),
    (lambda system: system["modules"].__setitem__("d", {"class": "examples.pipeline:Scale"}),
     COMMENTED.replace("# ---- links", f"[modules.d]\n{SCALE}\n# ---- links")),
    (_links(lambda links: [{"from": "c.y", "to": "tick.in"}, *links]),
     COMMENTED.replace("# link one\n", NEW_LINK + "# link one\n")),
    (_links(lambda links: [links[0], {"from": "c.y", "to": "tick.in"}, *links[1:]]),
     COMMENTED.replace("# link two\n", NEW_LINK + "# link two\n")),
    (_links(lambda links: [{**links[0], "to": "b.x"}, *links[1:]]),
     COMMENTED.replace('to = "a.x"', 'to = "b.x"')),
    (lambda system: system["modules"]["a"].__setitem__("state", {"gain": 3.0}),
     COMMENTED.replace(f"[modules.a]\n{SCALE}", f"[modules.a]\n{SCALE}state = {{gain = 3.0}}\n")),
    (lambda system: system["modules"]["tick"].__setitem__("node", "n"),
     COMMENTED.replace("period = 0.005  # fast\n", 'period = 0.005  # fast\nnode = "n"\n')),
    (lambda system: system["modules"]["c"].__setitem__("node", "n"),
     COMMENTED.replace(f"[modules.c]\n{SCALE}", f'[modules.c]\n{SCALE}node = "n"\n')),
    (_links(lambda links: [*links[:2], {**links[2], "policy": "queue:4"}]),
     COMMENTED.replace('to = "c.x"\n', 'to = "c.x"\npolicy = "queue:4"\n')),
    (lambda system: system.__setitem__("timeout", 3.0),
     COMMENTED.replace('name = "commented"\n', 'name = "commented"\ntimeout = 3.0\n')),
], ids=["first link", "middle link", "last link", "first two links", "all links",
        "first module", "last module", "a key", "a new module", "a new first link",
        "a new middle link", "a relinked link", "a new key", "a new key after a comment",
        "a new key in the last module", "a new key in the last link", "a new top key"])
def test_an_entry_removed_or_added_takes_its_own_comments_and_leaves_the_others(
        edit: Any, expected: str) -> None:
    """A comment directly above an entry (a link, a module, a key) is its own: it goes
    with it, and one below a table's last line before a blank line or the end; one after
    a blank line is the section's and stays; one blank line is left where there was one;
    a key added to a table goes right after its keys (it went under the next entry's
    comment, with no blank line before that entry's header).
    Links were merged by place: with the first one removed, each took the next one's
    values under the comments of the one before, and the last one's comments were lost;
    a removed module's comment stayed above the next one, whose own was lost; a new module
    went in below the links' heading comments."""
    document = Document(COMMENTED)
    system = document.data()
    edit(system)
    document.replace(system)
    assert document.toml() == expected
    assert document.data() == system


TUNING = """\
# A controller tuned while it runs.
name = "tuning"

# the loop's controller: its gains were found by hand
[modules.ctl]
class = "manager_modules:Controller"
state = { kp = 2.0, mode = "auto" }   # start gentle

[modules.loop]
macro = "loop"

[macros.loop.modules.inner]
class = "manager_modules:Controller"
state = { kd = 0.1 }
"""


def test_live_tuned_settings_are_kept_in_the_document_and_launch_again(
        tmp_path: Path) -> None:
    """Gains tuned in the State Editor could not be written back: GET /api/system/toml
    gave the configured state and Stop lost them. Keep writes the live values of the
    settings that differ from the document into the module's state (a macro's module:
    its instance's override), comments kept; read-outs and arrays are left out."""
    path = tmp_path / "tuning.toml"
    path.write_text(TUNING)
    with manager_client(Session(Document.open(path))) as client:
        assert client.get("/api/document").json()["problems"] == []
        assert client.post("/api/document/launch").status_code == 200
        assert client.post("/api/modules/ctl/state", json={"kp": 2.5, "ki": 0.25}).status_code \
            == 200
        offer = client.get("/api/modules/ctl/keep").json()
        assert offer["changes"] == {"kp": {"document": 2.0, "live": 2.5, "tuned": True},
                                    "ki": {"document": 0.0, "live": 0.25, "tuned": True}}
        assert set(offer["same"]) == {"kd", "limits", "mode"}
        assert set(offer["not_kept"]) == {"trace", "error", "integral"}
        revision = offer["revision"]
        assert client.get("/api/document").json()["revision"] == revision     # untouched

        kept = client.post("/api/modules/ctl/keep", json={"revision": revision})
        assert kept.status_code == 200, kept.json()
        assert kept.json()["kept"] == {"kp": 2.5, "ki": 0.25}
        assert kept.json()["where"] == "modules.ctl.state"
        assert kept.json()["revision"] == revision + 1
        text = client.get("/api/document/toml").text
        assert "# the loop's controller: its gains were found by hand" in text
        assert "# start gentle" in text and "# A controller tuned while it runs." in text
        ctl = tomllib.loads(text)["modules"]["ctl"]
        assert ctl["state"] == {"kp": 2.5, "mode": "auto", "ki": 0.25}
        # the page's copy of the document is older now: its edit is refused, as any other
        stale = client.post("/api/modules/ctl/keep", json={"revision": revision})
        assert stale.status_code == 412
        # kept again, nothing differs: nothing is written
        again = client.post("/api/modules/ctl/keep").json()
        assert again["kept"] == {} and again["revision"] == revision + 1

        # a module inside a macro instance: the instance's override, the macro untouched
        client.post("/api/modules/loop/inner/state", json={"kd": 0.3, "kp": 4})
        inner = client.post("/api/modules/loop/inner/keep", json={"fields": ["kd"]})
        assert inner.status_code == 200, inner.json()
        assert inner.json()["kept"] == {"kd": 0.3}
        assert inner.json()["where"] == "modules.loop.state.inner"
        saved = tomllib.loads(client.get("/api/document/toml").text)
        assert saved["modules"]["loop"] == {"macro": "loop", "state": {"inner": {"kd": 0.3}}}
        assert saved["macros"]["loop"]["modules"]["inner"]["state"] == {"kd": 0.1}

        # what cannot be kept is refused by name, and nothing changes
        for fields, status, words in ((["trace"], 422, "no value TOML holds"),
                                      (["integral"], 422, "not declared on Controller"),
                                      (["ghost"], 404, "has no state 'ghost'")):
            refused = client.post("/api/modules/ctl/keep", json={"fields": fields})
            assert refused.status_code == status and words in refused.json()["error"], fields
        unknown = client.post("/api/modules/nobody/keep")
        assert unknown.status_code == 404 and "no module 'nobody'" in unknown.json()["error"]
        assert client.post("/api/modules/ctl/keep", json=[1]).status_code == 400
        assert tomllib.loads(client.get("/api/document/toml").text) == saved

        # Stop, Save: the file launches with the tuned values
        assert client.post("/api/system/stop").status_code == 200
        refused = client.post("/api/modules/ctl/keep")
        assert refused.status_code == 409 and "nothing runs" in refused.json()["error"]
        assert client.post("/api/document/save", json={}).status_code == 200
    with System.load(path).launch() as run:
        assert (run.state("ctl")["kp"], run.state("ctl")["ki"]) == (2.5, 0.25)
        assert run.state("loop/inner")["kd"] == 0.3

    # attached to a system it did not launch, the manager has no document it came from
    with System.load(path).launch() as run, \
            manager_client(Session(Document.empty(), run)) as client:
        client.post("/api/modules/ctl/state", json={"kp": 9.0})
        for method in ("GET", "POST"):
            refused = client.request(method, "/api/modules/ctl/keep")
            assert refused.status_code == 409, refused.json()
            assert "attached" in refused.json()["error"]
        assert "ctl" not in client.get("/api/document").json()["system"].get("modules", {})


def test_a_document_whose_macros_are_not_a_table_can_be_mended_from_the_page(
        tmp_path: Path) -> None:
    """``[[macros]]`` (an array of tables where ``[macros.NAME]`` was meant) is listed as
    a problem, but every edit of such a document was a 500, the one that removes it too."""
    path = tmp_path / "system.toml"
    path.write_text('name = "s"\n\n[[macros]]\nname = "stage"\n\n[modules.tick]\n'
                    'class = "examples.pipeline:Ticker"\n')
    with manager_client(Session(Document.open(path))) as client:
        document = client.get("/api/document").json()
        assert any("'macros' must be a table" in p for p in document["problems"])
        for macros in (5, "stage", [1]):
            refused = client.put("/api/document", json={
                "system": {**document["system"], "macros": macros},
                "revision": document["revision"]})
            assert refused.status_code == 200, refused.text
            document = refused.json()
            assert any("'macros' must be a table" in p for p in document["problems"])
        mended = {key: value for key, value in document["system"].items() if key != "macros"}
        put = client.put("/api/document", json={"system": mended,
                                                "revision": document["revision"]})
        assert put.status_code == 200, put.text
        assert put.json()["problems"] == []
        assert "macros" not in client.get("/api/document/toml").text


# macros and modules written in pieces: [macros.junction]'s tables apart, with a module
# between them; [modules.j]'s state at the end of the file, after the links
SPLIT = '''\
# A system whose tables are written in pieces.
name = "split"

[nodes.a]   # the only node

# the junction: two scales in a row
[macros.junction]
# what it shows outside
exports = { x = "s1.x", y = "s2.y" }

# the first scale
[macros.junction.modules.s1]
class = "examples.pipeline:Scale"
state = { gain = 2.0 }  # doubles

# the source
[modules.tick]
class = "examples.pipeline:Ticker"
node = "a"   # here

# the second scale, written after the modules
[macros.junction.modules.s2]
class = "examples.pipeline:Scale"

# s1 into s2
[[macros.junction.links]]
from = "s1.y"
to = "s2.x"   # inside

# the instance
[modules.j]
macro = "junction"
node = "a"

# ---- links

# tick into the junction
[[links]]
from = "tick.out"
to = "j.x"  # in

# the instance's settings, at the end
[modules.j.state]
s2 = { gain = 0.5 }  # halves
'''
INSTANCE = '# the instance\n[modules.j]\nmacro = "junction"\nnode = "a"\n\n'
PROBE = f'\n[modules.probe]\n{SCALE}\n'
INNER_LINK = '# s1 into s2\n[[macros.junction.links]]\nfrom = "s1.y"\nto = "s2.x"   # inside\n\n'


def _replaced(text: str, *pairs: tuple[str, str]) -> str:
    for old, new in pairs:
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    return text


def _junction(system: dict[str, Any]) -> dict[str, Any]:
    return system["macros"]["junction"]


def _renamed(system: dict[str, Any]) -> None:
    """As the page renames a module: the same entries, one under another name."""
    system["modules"] = {("tock" if name == "tick" else name): entry
                         for name, entry in system["modules"].items()}
    system["links"][0]["from"] = "tock.out"


def _grouped_tick(system: dict[str, Any]) -> None:
    """As the page groups module tick into macro src."""
    tick = system["modules"].pop("tick")
    node = tick.pop("node")
    system["macros"]["src"] = {"modules": {"tick": tick}, "exports": {"out": "tick.out"}}
    system["modules"]["src"] = {"macro": "src", "node": node}
    system["links"] = [{"from": "src.out", "to": "j.x"}]


@pytest.mark.parametrize(("edit", "expected"), [
    (lambda system: system["modules"]["tick"].__setitem__("state", {"count": 1}),
     SPLIT.replace('node = "a"   # here\n', 'node = "a"   # here\nstate = {count = 1}\n')),
    (lambda system: _junction(system)["modules"]["s1"]["state"].__setitem__("gain", 4.0),
     SPLIT.replace("gain = 2.0", "gain = 4.0")),
    (lambda system: _junction(system)["modules"]["s2"].__setitem__("state", {"gain": 5.0}),
     _replaced(SPLIT, (f"modules.s2]\n{SCALE}", f"modules.s2]\n{SCALE}state = {{gain = 5.0}}\n"))),
    (lambda system: system["modules"]["j"]["state"]["s2"].__setitem__("gain", 0.25),
     SPLIT.replace("gain = 0.5", "gain = 0.25")),
    (lambda system: system["modules"]["j"]["state"].__setitem__("s1", {"gain": 3.0}),
     SPLIT + "s1 = {gain = 3.0}\n"),
    (lambda system: (system["modules"].__setitem__("probe", {"class": "examples.pipeline:Scale"}),
                     system["links"].append({"from": "j.y", "to": "probe.x"})),
     _replaced(SPLIT, ('to = "j.x"  # in\n\n',
                       'to = "j.x"  # in\n\n[[links]]\nfrom = "j.y"\nto = "probe.x"\n\n'))
     + PROBE),
    (lambda system: _junction(system).pop("links"), _replaced(SPLIT, (INNER_LINK, ""))),
    (lambda system: (_junction(system)["modules"].__setitem__(
        "s3", {"class": "examples.pipeline:Scale"}), _junction(system)["links"].append(
        {"from": "s2.y", "to": "s3.x"})),
     _replaced(SPLIT, (INNER_LINK, f"[macros.junction.modules.s3]\n{SCALE}\n{INNER_LINK}"),
               ('to = "s2.x"   # inside\n', 'to = "s2.x"   # inside\n\n[[macros.junction.'
                'links]]\nfrom = "s2.y"\nto = "s3.x"\n'))),
    (lambda system: _junction(system)["exports"].__setitem__("z", "s1.y"),
     SPLIT.replace('y = "s2.y" }', 'y = "s2.y", z = "s1.y"}')),
    (_renamed, SPLIT.replace("[modules.tick]", "[modules.tock]").replace(
        'from = "tick.out"', 'from = "tock.out"')),
    (_grouped_tick, _replaced(
        SPLIT, ('# the source\n[modules.tick]\nclass = "examples.pipeline:Ticker"\n'
                'node = "a"   # here\n\n', ""),
        ('to = "s2.x"   # inside\n', 'to = "s2.x"   # inside\n\n# the source\n'
         '[macros.src.modules.tick]\nclass = "examples.pipeline:Ticker"\n\n'
         '[macros.src.exports]\nout = "tick.out"\n'),
        ('from = "tick.out"', 'from = "src.out"'))
     + '\n[modules.src]\nmacro = "src"\nnode = "a"\n\n'),
    (lambda system: (system["modules"].pop("j"), system.__setitem__("links", [])),
     _replaced(SPLIT, ('name = "split"\n', 'name = "split"\nlinks = []\n'), (INSTANCE, ""))
     .split("\n# tick into the junction")[0]),
], ids=["a module's new key", "a macro's module's state", "a key new in a macro's module",
        "an instance's override", "a new override", "a new module and link",
        "a macro's links removed", "a new module and link in a macro", "a macro's export",
        "a module renamed", "a module grouped into a macro", "an instance removed"])
def test_tables_written_in_pieces_keep_every_comment_and_their_order_through_an_edit(
        edit: Any, expected: str) -> None:
    """A table written in pieces apart in the file (``[macros.junction]``, a module,
    then ``[macros.junction.modules.s2]``; a module's ``state`` after the links) is a
    proxy in tomlkit, and a value set through it made the whole table anew: any edit of
    a module lost the comments of every module, any edit in a macro those of every
    macro (and the lines of what followed them). Each piece is edited where it is; what
    is added goes in the last piece, a key in its table; a module renamed keeps its
    place and its comments; the file reads as the document and ``pb3a check`` accepts
    it."""
    document = Document(SPLIT)
    system = document.data()
    edit(system)
    document.replace(copy.deepcopy(system))
    assert document.toml() == expected
    assert document.data() == system == tomllib.loads(expected)
    assert Document(expected).problems() == []


DOTTED = '''\
# modules in dotted keys
name = "dotted"

[modules]
# the ticker
tick.class = "examples.pipeline:Ticker"
tick.period = 0.01   # slow
# the scale
scale.class = "examples.pipeline:Scale"
scale.state = { gain = 2.0 }  # doubles

# the link
[[links]]
from = "tick.out"
to = "scale.x"  # into the scale
'''


def test_a_module_written_in_dotted_keys_keeps_its_comments_when_edited() -> None:
    """``tick.class = ...`` then ``tick.period = ...``: each line is a piece of module
    tick, a proxy in tomlkit; an edit of it wrote all the modules anew, without their
    comments."""
    document = Document(DOTTED)
    system = document.data()
    system["modules"]["tick"]["period"] = 0.02
    system["modules"]["scale"]["state"]["gain"] = 3.0
    system["modules"]["scale"]["node"] = "n"
    system["nodes"] = {"n": {}}
    document.replace(copy.deepcopy(system))
    assert document.toml() == _replaced(
        DOTTED, ("0.01   # slow", "0.02   # slow"), ("gain = 2.0", "gain = 3.0"),
        ("scale.class = \"examples.pipeline:Scale\"\n",
         "scale.class = \"examples.pipeline:Scale\"\nscale.node = \"n\"\n")) + "\n[nodes.n]\n\n"
    assert document.data() == system


def test_a_module_renamed_in_the_page_keeps_its_place_and_its_comments(
        tmp_path: Path) -> None:
    """The page renames a module by sending its entry under the new name: it was
    removed, with the comments above it and on its keys, and written anew at the end of
    the modules. It keeps its place and every comment; only its header changes."""
    path = tmp_path / "chain.toml"
    path.write_text(CHAIN)
    with manager_client(Session(Document.open(path))) as client:
        system = client.get("/api/document").json()["system"]
        system["modules"] = {("first" if name == "scale" else name): entry
                             for name, entry in system["modules"].items()}
        system["links"] = [{**link, **{end: link[end].replace("scale.", "first.")
                                       for end in ("from", "to")}}
                           for link in system["links"]]
        answer = client.put("/api/document", json={"system": system})
        assert answer.status_code == 200 and answer.json()["problems"] == [], answer.text
        assert client.get("/api/document/toml").text == CHAIN.replace(
            "[modules.scale]", "[modules.first]").replace('"scale.', '"first.')
        assert client.get("/api/document").json()["system"] == system     # (in its order)


def test_the_last_module_or_link_removed_is_written_where_a_key_goes(pipeline: Path) -> None:
    """The page removes a module with its links: the last link gone, ``links = []`` was
    written on the first line of the file, above its comments; the last module gone, the
    edit was refused as one TOML "cannot hold" (``[modules]`` emptied is not written at
    all). ``links = []`` goes after the file's keys and an empty ``[modules]`` is
    written, which takes the next module."""
    original = pipeline.read_text()
    with manager_client(Session(Document.open(pipeline))) as client:
        system = client.get("/api/document").json()["system"]
        del system["modules"]["tick"]
        system["links"] = []
        assert client.put("/api/document", json={"system": system}).status_code == 200
        assert client.get("/api/document/toml").text == _replaced(
            original, ('name = "pipeline"\n', 'name = "pipeline"\nlinks = []\n'),
            ('[modules.tick]\nclass = "examples.pipeline:Ticker"\nperiod = 0.005\n'
             'state = { count = 0 }\n\n', "")).split("\n[[links]]")[0]
        del system["modules"]["scale"]
        put = client.put("/api/document", json={"system": system})
        assert put.status_code == 200, put.text
        assert client.get("/api/document").json()["system"] == system
        system["modules"]["probe"] = {"class": "examples.pipeline:Scale"}
        assert client.put("/api/document", json={"system": system}).status_code == 200
        text = client.get("/api/document/toml").text
    assert text.startswith(original.split("[modules.tick]")[0].replace(
        'name = "pipeline"\n', 'name = "pipeline"\nlinks = []\n'))
    assert tomllib.loads(text) == system and Document(text).problems() == []


def test_links_written_in_two_runs_are_saved_unchanged_byte_for_byte(tmp_path: Path) -> None:
    """``[[links]]``, a module's table, ``[[links]]`` again: tomlkit writes what it read
    of such a file with the links together, the table after them (and no blank line
    before it); opened and saved unchanged, or put back as it was, the file was not the
    same file."""
    text = (f'name = "runs"\n\n[modules.a]\n{SCALE}\n[[links]]\nfrom = "a.y"\nto = "b.x"\n\n'
            f'[modules.b]\n{SCALE}\n[[links]]\nfrom = "b.y"\nto = "a.x"\n')
    path = tmp_path / "runs.toml"
    path.write_text(text)
    with manager_client(Session(Document.open(path))) as client:
        assert client.get("/api/document/toml").text == text
        system = client.get("/api/document").json()["system"]
        assert client.put("/api/document", json={"system": system}).status_code == 200
        assert client.post("/api/document/save", json={"overwrite": True}).status_code == 200
    assert path.read_text() == text


# arrays of values written over several lines, a comment on an item's line or on a
# line of its own: a list-valued state field, and links written as an array of inline
# tables
LISTS = '''\
# lists commented item by item
name = "lists"
links = [
    { from = "first.y", to = "second.x" },   # the chain
    # and the way back
    { from = "second.y", to = "first.x" },   # back
]

[modules.first]
class = "examples.pipeline:Scale"

[modules.second]
class = "examples.pipeline:Scale"

[modules.third]
class = "examples.pipeline:Scale"

[modules.held]
class = "manager_modules:Holder"

[modules.held.state]
waypoints = [
    [0.0, 0.0],   # the start
    [1.0,  2.0],  # halfway
    [2.0, 4.0],   # the end
]
'''


def _waypoints(system: dict[str, Any]) -> list[Any]:
    return system["modules"]["held"]["state"]["waypoints"]


@pytest.mark.parametrize(("edit", "expected"), [
    (lambda system: _waypoints(system)[1].__setitem__(1, 3.0),
     LISTS.replace("[1.0,  2.0],  # halfway", "[1.0,  3.0],  # halfway")),
    (lambda system: _waypoints(system).__setitem__(2, [5.0, 6.0]),
     LISTS.replace("[2.0, 4.0],   # the end", "[5.0, 6.0],   # the end")),
    (lambda system: _waypoints(system).pop(1),
     LISTS.replace("    [1.0,  2.0],  # halfway\n", "")),
    (lambda system: _waypoints(system).append([3.0, 6.0]),
     LISTS.replace("# the end\n", "# the end\n    [3.0, 6.0],\n")),
    (lambda system: system["links"][1].__setitem__("to", "third.x"),
     LISTS.replace('{ from = "second.y", to = "first.x" }',
                   '{ from = "second.y", to = "third.x" }')),
    (lambda system: system["links"].pop(0),
     LISTS.replace('    { from = "first.y", to = "second.x" },   # the chain\n', "")),
], ids=["an item of an item", "an item", "an item removed", "an item added",
        "an inline link's end", "an inline link removed"])
def test_an_array_edited_item_by_item_keeps_the_comments_and_lines_of_the_others(
        tmp_path: Path, edit: Any, expected: str) -> None:
    """An array of values edited from the page (a list-valued state field, links written
    as ``links = [{...}, ...]``) was written anew from its values: one item changed, the
    comments on every item's line and on lines of their own were lost, and an array
    written on several lines came back on one. It is edited item by item where each is:
    the others keep their comments, the array its lines, byte for byte."""
    path = tmp_path / "lists.toml"
    path.write_text(LISTS)
    with manager_client(Session(Document.open(path))) as client:
        system = client.get("/api/document").json()["system"]
        edit(system)
        answer = client.put("/api/document", json={"system": system})
        assert answer.status_code == 200 and answer.json()["problems"] == [], answer.text
        assert client.get("/api/document/toml").text == expected
        assert client.get("/api/document").json()["system"] == system
    assert tomllib.loads(expected) == Document(expected).data()


# a module written in pieces under headers of its own, each commented: [modules.tick]
# and its [modules.tick.state] apart, after the links (or before its header)
TICK = '''\
# the source
[modules.tick]
class = "examples.pipeline:Ticker"   # ticks
node = "a"   # here

'''
TICK_STATE = '''\
# where the ticker starts
[modules.tick.state]
count = 5   # not zero
'''
PIECES = f'''\
# a module in pieces
name = "pieces"

[nodes.a]

{TICK}# the scale
[modules.scale]
class = "examples.pipeline:Scale"

# tick into the scale
[[links]]
from = "tick.out"
to = "scale.x"

{TICK_STATE}'''
PIECES_GROUPED = '''\
# a module in pieces
name = "pieces"

[nodes.a]

# the scale
[modules.scale]
class = "examples.pipeline:Scale"

# tick into the scale
[[links]]
from = "src.out"
to = "scale.x"

[modules.src]
macro = "src"
node = "a"

# the source
[macros.src.modules.tick]
class = "examples.pipeline:Ticker"   # ticks

# where the ticker starts
[macros.src.modules.tick.state]
count = 5   # not zero

[macros.src.exports]
out = "tick.out"

'''


INSTANCE_SRC = '[modules.src]\nmacro = "src"\nnode = "a"\n\n'
STATE_FIRST = PIECES.replace(TICK, "").replace(TICK_STATE, "").replace(
    "[nodes.a]\n\n", f"[nodes.a]\n\n{TICK_STATE}\n{TICK}")


@pytest.mark.parametrize(("text", "expected"), [
    (PIECES, PIECES_GROUPED),
    (STATE_FIRST,
     _replaced(PIECES_GROUPED, (INSTANCE_SRC, ""),      # (after the modules' last piece)
               ("# tick into the scale\n", f"{INSTANCE_SRC}# tick into the scale\n")))],
    ids=["its state after the links", "its state before its header"])
def test_a_module_written_in_pieces_grouped_into_a_macro_keeps_the_comments_of_each(
        tmp_path: Path, text: str, expected: str) -> None:
    """A module whose table is written in pieces (``[modules.tick]`` and its
    ``[modules.tick.state]`` apart, each with its comments) grouped into a macro was made
    anew there from its values: every comment on it lost, its state written inline. Its
    pieces go into the macro's table together, the header's first, each with the
    comments above it and on its lines, byte for byte; the file reads back as the
    document and ``pb3a check`` accepts it."""
    path = tmp_path / "pieces.toml"
    path.write_text(text)
    with manager_client(Session(Document.open(path))) as client:
        system = client.get("/api/document").json()["system"]
        system["macros"] = {}
        _grouped_tick(system)
        system["links"] = [{"from": "src.out", "to": "scale.x"}]
        answer = client.put("/api/document", json={"system": system})
        assert answer.status_code == 200 and answer.json()["problems"] == [], answer.text
        assert client.get("/api/document/toml").text == expected
        assert client.get("/api/document").json()["system"] == system
    assert tomllib.loads(expected) == system and Document(expected).problems() == []


def test_a_module_written_in_pieces_removed_takes_the_comments_of_each_piece() -> None:
    """``[modules.tick.state]`` written before ``[modules.tick]``: the comment above the
    header is read as the end of the state's table, and removing the module kept it
    there as the next section's, alone above nothing of its own. Each piece goes with
    the comments directly above it."""
    document = Document(STATE_FIRST)
    system = document.data()
    del system["modules"]["tick"]
    system["links"] = []
    document.replace(copy.deepcopy(system))
    assert document.toml() == _replaced(
        STATE_FIRST, ('name = "pieces"\n', 'name = "pieces"\nlinks = []\n'),
        (f"{TICK_STATE}\n{TICK}", "")).split("\n# tick into the scale")[0] + "\n"
    assert document.data() == system
