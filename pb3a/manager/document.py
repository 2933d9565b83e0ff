"""The configuration being edited: a TOML document that keeps what the user wrote.

The document is held as a ``tomlkit`` document, not as plain dicts: an edit from
the page (the whole system as JSON) is merged into it key by key (an array of values
item by item), so entries that did not change keep their comments, order and
formatting, and a file opened and saved unchanged is the same file (the round trip);
the comments and blank lines around an entry added, removed, renamed or moved go as
``pb3a.manager.lines`` says. A table
written in pieces (its headers apart in the file, or dotted keys) is edited piece by
piece where each is (``_holders``). Problems are found
as ``pb3a check`` finds them, with the same words: the document is read as a
description and compiled; a half-built system is kept, its problems listed.
"""

from __future__ import annotations

import contextlib
import copy
import datetime
import decimal
import difflib
import json
import math
import threading
import tomllib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import tomlkit
from tomlkit.exceptions import TOMLKitError
from tomlkit.items import AoT, Array, InlineTable, Table
from tomlkit.parser import Parser

from pb3a.atomic_write import write_text_atomically
from pb3a.config.compiler import sketch_plan
from pb3a.config.definitions import toml_key
from pb3a.config.description import read_description
from pb3a.config.plan import Plan
from pb3a.errors import ConfigError
from pb3a.manager import lines
from pb3a.model.state_edits import floats_as_declared

# dicts at these places are written as [tables]; every other dict inline ({...})
_TABLES = (("nodes",), ("modules",), ("macros",), ("macros", "*"), ("macros", "*", "modules"))
_TABLE_ARRAYS = (("links",), ("macros", "*", "links"))   # lists of dicts as [[tables]]
# levels of tables and arrays a document may nest: the TOML reader (tomlkit's) refuses a
# value nested deeper, so such a file would not open again
MOST_NESTING = Parser.MAX_NESTING_DEPTH
BOM = "\ufeff"           # a byte order mark, as text: what a UTF-8 file may begin with


class Stale(Exception):
    """An edit made on a copy of the document older than the document now."""


class ChangedOnDisk(Exception):
    """A save would overwrite a file that says something this document never read there
    (it was edited on disk since, or it is another file)."""


class Document:
    """One system description being edited (thread-safe). Each change counts its
    ``revision``: an edit sent with the revision it was made on is refused (``Stale``)
    if another came in between (two pages, each editing its own copy, would otherwise
    each overwrite the other's work)."""

    def __init__(self, text: str = "", path: Path | None = None) -> None:
        self.path = path
        self.name: str | None = None     # the file's name when opened in the page (no path)
        # the file's line ends, kept on save (a file written on Windows came back all LF,
        # every line changed for its version control); the text is edited with "\n"
        # (its most lines': one CRLF pasted into a file of LF lines made them all CRLF)
        self.newline = "\r\n" if 2 * text.count("\r\n") > text.count("\n") else "\n"
        # ... and its byte order mark, which Windows editors write (tomlkit refuses it:
        # the file did not open, "Empty key at line 1 col 0")
        self.bom = text.startswith(BOM)
        text = text.removeprefix(BOM).replace("\r\n", "\n")
        try:
            self._doc = tomlkit.parse(text)
            # the text it says: tomlkit writes some files otherwise than it reads them
            # (an array of tables in two runs with a table between, it writes as one run)
            self._text = text
        except TOMLKitError as exc:
            where = path if path is not None else "the document"
            raise ConfigError([f"{where}: not valid TOML: {exc}"]) from None
        self._lock = threading.Lock()
        self.revision = 0
        self._on_disk = text if path is not None else None   # what ``path`` said, last seen

    @classmethod
    def open(cls, path: str | Path) -> Document:
        """The document in file ``path``; OSError if it cannot be read, ConfigError if it
        is not TOML."""
        path = Path(path)
        with path.open(encoding="utf-8", newline="") as file:     # (its line ends as written)
            return cls(file.read(), path)

    @classmethod
    def empty(cls, name: str = "system") -> Document:
        """A new document with a name and nothing else."""
        return cls(f'name = "{name}"\n')

    # -- reading ------------------------------------------------------------------
    def data(self) -> dict[str, Any]:
        """The document as plain JSON-like values."""
        with self._lock:
            return self._doc.unwrap()

    def toml(self) -> str:
        """The document's TOML text."""
        with self._lock:
            return self._text

    @property
    def source(self) -> str:
        """How problems name the document: its file, the name of the file opened in the
        page, or ``the document``."""
        if self.path is not None:
            return str(self.path)
        return self.name or "the document"

    def sketch(self) -> tuple[Plan, list[str]]:
        """What the document would run so far, and every problem ``pb3a check`` reports."""
        return check_data(self.data(), self.source)

    def problems(self) -> list[str]:
        return self.sketch()[1]

    def to_json(self) -> dict[str, Any]:
        """``{"path", "system", "problems", "revision"}`` as ``GET /api/document``
        answers (the revision read first: a change after it makes an edit on this
        copy stale, never the other way round)."""
        revision = self.revision
        return {"path": None if self.path is None else str(self.path),
                "system": as_json(self.data()), "problems": self.problems(),
                "revision": revision}

    # -- changing -----------------------------------------------------------------
    def replace(self, system: dict[str, Any], revision: int | None = None) -> None:
        """Make the document say ``system`` (the tables as JSON), keeping the comments and
        layout of everything that did not change. ``null`` values leave a key out. What
        TOML cannot hold (a ``null`` inside an array) is a ValueError, and then nothing
        changes: the edit is made on a copy, which replaces the document only once its
        text reads back as what it holds. With ``revision``, ``Stale`` if the document
        has changed since that revision."""
        if not isinstance(system, dict):
            raise ValueError(f"'system' must be an object of TOML tables, got {system!r}")
        with self._lock:
            self._current(revision)
            self._replace(system)

    def edit(self, change: Callable[[dict[str, Any]], bool], revision: int | None = None
             ) -> None:
        """Change the document as ``change`` changes its tables (as plain values, changed
        in place; it answers whether it changed anything), with no other change in
        between: as ``replace`` does, comments and layout kept, ``Stale`` with a
        ``revision`` that is not the document's. What ``change`` raises changes nothing."""
        with self._lock:
            self._current(revision)
            system = self._doc.unwrap()
            if change(system):
                self._replace(system)

    def _current(self, revision: int | None) -> None:
        if revision is not None and revision != self.revision:
            raise Stale(f"the document changed since this copy of it was read "
                        f"(revision {revision}, now {self.revision}), in another page "
                        "or by an open: read it again and make the change there")

    def _replace(self, system: dict[str, Any]) -> None:
        """``replace``'s work, the lock held."""
        deep = _too_deep(system, MOST_NESTING)
        if deep is not None:
            # (taken, the file would not open again, and every later edit failed copying
            # the document: RecursionError, a 500)
            raise ValueError(f"TOML cannot hold this document: {'.'.join(deep[:6])}... nests "
                             f"more than {MOST_NESTING} levels of tables and arrays")
        draft = copy.deepcopy(self._doc)
        held = draft.unwrap()
        system = _floats_declared(_moves_resolved(held, system), self.source)
        try:
            moves = _carried(draft, held, system)
            _merge(draft, system, (), moves=moves)
            moves.lead_in()
            text = tomlkit.dumps(draft)
            same = _same(tomllib.loads(text), draft.unwrap())
            if moves.placed:            # (its comments above a header: read as a file's)
                draft = tomlkit.parse(text)
            elif moves.renamed:         # (tomlkit keeps the keys in the order they came)
                again = tomlkit.parse(text)
                if tomlkit.dumps(again) == text:    # (not so for every file: see _text)
                    draft = again
        except (TOMLKitError, tomllib.TOMLDecodeError, TypeError, ValueError) as exc:
            raise ValueError(f"TOML cannot hold this document: {exc}") from None
        if not same:
            raise ValueError("TOML cannot hold this document: written, it would not "
                             "read back as sent")
        if not _same(held, draft.unwrap()):     # (nothing changed: the text as it was)
            self._text = text
        self._doc = draft
        self.revision += 1

    def open_text(self, text: str, name: str) -> None:
        """Make the document the TOML ``text`` of a file called ``name`` (one the page
        read from the user's disk), if ``pb3a check`` accepts it: ConfigError with its
        problems, in ``pb3a check``'s words and naming ``name``, otherwise, and then
        nothing changes. The page sends no path, so the document has none: Save needs
        one."""
        opened = Document(text, Path(name))          # ConfigError if it is not TOML
        problems = check_data(opened.data(), name)[1]
        if problems:
            raise ConfigError(problems)
        with self._lock:
            self._doc, self._text = opened._doc, opened._text
            self.newline, self.bom = opened.newline, opened.bom
            self.path, self.name = None, name
            self.revision += 1

    def check_link(self, src: str, dst: str) -> tuple[bool, str]:
        """Whether a link ``src -> dst`` added to the document would be fine, and if not
        the words ``pb3a check`` would use."""
        data = self.data()
        before = set(check_data(data, self.source)[1])
        links = list(data.get("links", [])) if isinstance(data.get("links"), list) else []
        data["links"] = [*links, {"from": src, "to": dst}]
        after = [problem for problem in check_data(data, self.source)[1]
                 if problem not in before]
        return (not after, "; ".join(after) or f"{src} -> {dst} fits")

    def save(self, path: str | Path | None = None, *, overwrite: bool = False) -> Path:
        """Write the TOML to ``path`` (default: where it came from); the path written.
        ``ChangedOnDisk``, nothing written, if the file there says something this
        document did not read or write there (edited in another editor since it was
        opened: a save overwrote those edits without a word), unless ``overwrite``."""
        target = Path(path) if path is not None else self.path
        if target is None:
            raise ValueError("the document has no file yet: give the path to save it to")
        text = self.toml()
        known = self._on_disk if self.path is not None and target == self.path else None
        if not overwrite:
            try:
                there = target.read_text(encoding="utf-8-sig")     # (its mark aside)
            except FileNotFoundError:
                there = known
            except (OSError, UnicodeDecodeError):
                there = ""                  # (unreadable: not what this document wrote)
            if there != known and there != text:
                raise ChangedOnDisk(
                    f"{target} changed on disk since it was opened here" if known is not None
                    else f"{target} is another file, which a save would overwrite")
        # (whole or not at all: written in place, a full disk left the file cut off,
        # no longer TOML, and the next save said it had changed on disk)
        write_text_atomically(target, BOM * self.bom + text, newline=self.newline)
        self.path, self._on_disk = target, text
        return target


def _too_deep(value: Any, most: int, where: tuple[str, ...] = ()) -> tuple[str, ...] | None:
    """Where ``value`` nests more than ``most`` levels of dicts and lists (the keys and
    indexes on the way), or None; it looks no deeper than that."""
    items = value.items() if isinstance(value, dict) else enumerate(value) \
        if isinstance(value, list) else ()
    for key, item in items:
        if isinstance(item, (dict, list)):
            if most <= 0:
                return (*where, str(key))
            found = _too_deep(item, most - 1, (*where, str(key)))
            if found is not None:
                return found
    return None


def toml_text(tables: dict[str, Any], comments: Sequence[str] = ()) -> str:
    """A new configuration file saying ``tables``: tables and arrays of tables where a
    configuration has them, inline tables elsewhere; ``comments`` first, one a line."""
    doc = tomlkit.document()
    for line in comments:
        doc.add(tomlkit.comment(line))
    if comments:
        doc.add(tomlkit.nl())
    _merge(doc, tables, ())
    return tomlkit.dumps(doc)


def check_data(data: dict[str, Any], source: str) -> tuple[Plan, list[str]]:
    """The plan so far and the problems of a description given as tables."""
    return sketch_plan(read_description(data, source))


def _merge(parts: Any, new: dict[str, Any], where: tuple[str, ...],
           root: Any = None, moves: lines.Carried | None = None) -> None:
    """Update a tomlkit table in place to hold ``new``: unchanged values keep their
    formatting, changed ones are replaced, missing ones removed (with the comment right
    above them, see ``lines.drop``), new tables placed before the comments of what
    follows (``lines.place``), a new key right after its table's keys
    (``lines.add_key``); ``moves``: what came from elsewhere in the document, put in as
    it was written. ``parts``: the table, or the tables it is written as in the file
    (``_holders``); ``root``: the document they are in (the table itself at the top)."""
    parts = parts if isinstance(parts, list) else [parts]
    root = parts[0] if root is None else root
    for old, name in _renamed(parts, new).items():
        lines.rename(_holders(parts, old)[0][0], old, name)
        if moves is not None:
            moves.renamed.append(name)
    for key in [key for key in dict.fromkeys(key for part in parts for key in part)
                if key not in new or new[key] is None]:
        _drop(root, _holders(parts, key), key)
    for key, value in new.items():
        if value is None:
            continue
        place = (*where, key)
        holders = _holders(parts, key)
        olds = [item for _, item in holders]
        if olds:
            held = _joined([_plain(item) for item in olds])
            value = _resolved(held, value)
            if value is held or value == held:          # (nan is not == nan)
                continue
        if isinstance(value, dict) and olds and all(isinstance(old, (Table, InlineTable))
                                                    for old in olds):
            _merge(olds, value, place, root, moves)
            if not value and all(isinstance(old, Table) and old.is_super_table() and not old
                                 for old in olds):
                # (a table emptied that had no header, [modules] of [modules.a]..., is
                # not written at all: the edit was refused as one TOML cannot hold; its
                # lines went with what it held, the ones above it are the next one's)
                for part in {id(part): part for part, _ in holders}.values():
                    del part[key]
                _add(root, parts, key, _item(value, place))
        elif (isinstance(value, list) and value and olds
              and all(isinstance(old, AoT) for old in olds)
              and all(isinstance(item, dict) for item in value)):
            _merge_array(holders, value, place, root, moves)
        elif isinstance(value, list) and len(olds) == 1 and isinstance(olds[0], Array):
            _merge_values(olds[0], value, place, root)
        else:
            made = _item(value, place, any(isinstance(part, InlineTable) for part in parts),
                         moves)
            if len(holders) == 1 and (isinstance(made, (Table, AoT)) or not isinstance(
                    olds[0], (Table, AoT))):
                holders[0][0][key] = made
                continue
            # (a table or array of tables that is now a value, `links = []`, goes where a
            # new key would: set in its place it was written after the tables, at the top
            # of the file or in the table before it; one written in pieces goes whole)
            if holders:
                _drop(root, holders, key)
            _add(root, parts, key, made)


def _add(root: Any, parts: list[Any], key: str, made: Any) -> None:
    """Put new key ``key`` = ``made`` in a table written as ``parts`` (``_part_for``):
    a value right after the keys there (``lines.add_key``), a table before the comments
    of what follows it (``lines.place``)."""
    container = _part_for(parts, made)
    if not isinstance(made, (Table, AoT)) \
            and isinstance(container, (Table, tomlkit.TOMLDocument)):
        lines.add_key(container, key, made)
    else:
        container[key] = made
        lines.place(root, container.item(key))


def _renamed(parts: list[Any], new: dict[str, Any]) -> dict[str, str]:
    """The tables of a table written as ``parts`` that ``new`` gives another name, as it
    was (a module renamed in the page): each old name with its new one. Removed and
    added, such a table lost its comments and went to the end of the file."""
    keys = dict.fromkeys(key for part in parts for key in part)
    gone = [key for key in keys if key not in new or new[key] is None]
    renamed: dict[str, str] = {}
    for name in [name for name, value in new.items() if value is not None and name not in keys]:
        for old in gone:
            holders = _holders(parts, old)
            if old in renamed or len(holders) != 1 or not isinstance(holders[0][1], Table) \
                    or isinstance(holders[0][1], InlineTable):
                continue
            held = _plain(holders[0][1])
            value = _resolved(held, new[name])
            if value is held or value == held:
                renamed[old] = name
                break
    return renamed


def _holders(parts: list[Any], key: str) -> list[tuple[Any, Any]]:
    """Each place ``key`` is written in a table written as ``parts``: ``(part, item)``.
    A table is written in pieces when its headers are apart in the file
    (``[macros.stage]``, other tables, then ``[macros.stage.modules.scale]``), or in
    dotted keys (``scale.class = ...``, ``scale.node = ...``); tomlkit reads such a table
    as a proxy, and a value set through it rebuilt the whole table (every comment in
    it lost), so each piece is edited where it is."""
    found = []
    for part in parts:
        body = part.body if isinstance(part, tomlkit.TOMLDocument) else part.value.body
        found.extend((part, item) for name, item in body
                     if name is not None and name.key == key)
    return found


def _holders_at(root: Any, keys: tuple[str, ...]) -> list[Any]:
    """Each place the value at ``keys`` of document ``root`` is written (``_holders``)."""
    found = [root]
    for key in keys:
        found = [item for _, item in _holders(
            [table for table in found
             if isinstance(table, (Table, InlineTable, tomlkit.TOMLDocument))], key)]
    return found


def _joined(values: list[Any]) -> Any:
    """The value of a table or array of tables written in pieces, from its pieces'
    values: the tables' keys together, the arrays' entries one after the other."""
    if len(values) == 1:
        return values[0]
    if all(isinstance(value, dict) for value in values):
        keys = dict.fromkeys(key for value in values for key in value)
        return {key: _joined([value[key] for value in values if key in value])
                for key in keys}
    if all(isinstance(value, list) for value in values):
        return [item for value in values for item in value]
    return values[-1]


def _part_for(parts: list[Any], made: Any) -> Any:
    """Which piece of a table written in pieces a new key goes in: a table or array of
    tables in the last (after what the file wrote last in it), a value in the first
    with a header (a piece without one holds tables only)."""
    if isinstance(made, (Table, AoT)):
        return parts[-1]
    return next((part for part in parts
                 if not (isinstance(part, Table) and part.is_super_table())), parts[0])


def _drop(root: Any, holders: list[tuple[Any, Any]], key: str) -> None:
    """Remove ``key`` from each piece of a table that holds it, with its lines."""
    pieces = list({id(part): part for part, _ in holders}.values())
    lines.drop(root, [item for _, item in holders],
               lambda: [part.__delitem__(key) for part in pieces])


def _merge_array(holders: list[tuple[Any, AoT]], new: list[dict[str, Any]],
                 where: tuple[str, ...], root: Any, moves: lines.Carried | None = None
                 ) -> None:
    """An array of tables entry by entry, matched by what they say (not by place: with
    the first link removed, each link took the next one's values and the first one's
    comments stayed on what became the second); an entry edited in place keeps its
    comments. Entries that ``moves`` takes elsewhere go, and those it brings come in as
    they were written, before the others are matched (an entry that moved away was
    edited into one that stayed, its comments on it). ``holders``: the array, or the
    pieces it is written in (``_holders``: ``[[macros.stage.links]]`` apart in the
    file), each with the table it is in; a new entry goes after the one before it."""
    def entries() -> list[tuple[AoT, int]]:
        return [(array, index) for _, array in holders for index in range(len(array))]

    def remove(array: AoT, index: int) -> None:
        lines.drop(root, [array[index]], lambda: array.__delitem__(index))

    def insert(at: int, entry: Any) -> None:
        array, index = (holders[0][1], 0) if at == 0 else entries()[at - 1]
        index = 0 if at == 0 else index + 1
        array.insert(index, entry)
        lines.place(root, array[index], array)

    if moves is not None:
        for array, index in reversed(entries()):
            if moves.gone(array[index]):
                remove(array, index)
    brought = _brought(moves, where, new)
    rest = [value for index, value in enumerate(new) if index not in brought]
    held = [array[index] for array, index in entries()]
    for i1, i2, j1, j2, edited in _edits(held, rest):
        at = entries()
        for index in range(edited):
            array, inside = at[i1 + index]
            _merge(array[inside], rest[j1 + index], where, root, moves)
        for index in reversed(range(i1 + edited, i2)):
            remove(*at[index])
        for offset, value in enumerate(rest[j1 + edited:j2]):
            insert(i1 + edited + offset, _table(value, where, tomlkit.table(), moves))
    for index, entry in sorted(brought.items()):        # (each after those before it)
        insert(index, entry)
    if any(len(array) for _, array in holders):         # (a piece left empty: gone)
        for part, array in holders:
            if not len(array):
                part.__delitem__(where[-1])


def _edits(held: list[Any], new: list[Any]) -> list[tuple[int, int, int, int, int]]:
    """How the items ``held`` in the document become the ``new`` ones the page sent,
    matched by what they say: ``(i1, i2, j1, j2, edited)`` for each run that differs,
    the later ones first (so that the indices of those before stay true); its first
    ``edited`` items are edited in place, the rest of ``held[i1:i2]`` removed and the
    rest of ``new[j1:j2]`` inserted."""
    matcher = difflib.SequenceMatcher(None, [_text(_as_shown(_plain(item))) for item in held],
                                      [_text(_as_sent(value)) for value in new], autojunk=False)
    return [(i1, i2, j1, j2, min(i2 - i1, j2 - j1))
            for tag, i1, i2, j1, j2 in reversed(matcher.get_opcodes()) if tag != "equal"]


def _merge_values(array: Array, new: list[Any], where: tuple[str, ...], root: Any) -> None:
    """An array of values (``[...]``, inline tables in it too) item by item, matched by
    what they say, in place: the comment on an item's line stays with it, and the array
    stays written on one line or on several, as it was (made anew from the values, an
    edit of one item lost the comments of all and put the array on one line). An item
    edited is set where it is (an inline table or array in it merged likewise)."""
    for i1, i2, j1, j2, edited in _edits(list(array), new):
        for index in range(edited):
            old, value = array[i1 + index], new[j1 + index]
            if isinstance(old, InlineTable) and isinstance(value, dict):
                _merge(old, value, where, root)
            elif isinstance(old, Array) and isinstance(value, list):
                _merge_values(old, value, where, root)
            else:
                array[i1 + index] = _plain_item(value)
        for index in reversed(range(i1 + edited, i2)):
            del array[index]
        for offset, value in enumerate(new[j1 + edited:j2]):
            array.insert(i1 + edited + offset, _plain_item(value))


def _brought(moves: lines.Carried | None, where: tuple[str, ...], values: list[Any]
             ) -> dict[int, Any]:
    """The entries ``moves`` brings into the array of tables at ``where``, which is to
    say ``values``, by index."""
    return {} if moves is None else moves.brought(where, [_text(_as_sent(value))
                                                          for value in values])


def _text(value: Any) -> str:
    """A value as text, to compare array entries by what they say."""
    return json.dumps(value, sort_keys=True, default=str)


def _carried(root: Any, held: dict[str, Any], new: dict[str, Any]) -> lines.Carried:
    """What an edit moves from ``held`` (the values of document ``root``) to ``new``, as
    written (``lines.Carried``): module entries grouped into a macro or out of one
    (``_moved``), and the links among them, from ``[[links]]`` to a macro's ``links`` or
    back. Each module entry is first made what ``new`` says where it is (a key dropped
    takes its comment, as it would in place), then taken."""
    moves = lines.Carried()
    after = _entries(new)
    for there, here in _moved(held, new).items():
        if here in after:                       # copied, not moved: its lines stay
            continue
        found = _holders_at(root, here)
        if not isinstance(after[there], dict):
            continue
        if len(found) == 1 and isinstance(found[0], (Table, InlineTable)):
            _merge(found[0], after[there], there, root)
            moves.take(root, found[0], there)
        elif len(found) > 1 and lines.Carried.pieces(root, found):
            # ([modules.a] and [modules.a.state] apart: taken together, each piece's
            # comments with it; one in dotted keys is made anew there)
            _merge(found, after[there], there, root)
            moves.take(root, found, there)
    for there, text, item in _moved_entries(root, held, new):
        moves.take(root, item, there, text)
    return moves


def _moved_entries(root: Any, held: dict[str, Any], new: dict[str, Any]
                   ) -> list[tuple[tuple[str, ...], str, Any]]:
    """The links (entries of ``[[links]]`` and of the macros' ``links``) that moved from
    one of these arrays to another, unchanged: ``(new array, the value as text, the
    entry in document root)``."""
    def arrays(system: dict[str, Any], form: Callable[[Any], Any]
               ) -> dict[tuple[str, ...], list[str]]:
        found = {("links",): system.get("links")}
        macros = system.get("macros")
        for name, body in (macros.items() if isinstance(macros, dict) else ()):
            found[("macros", name, "links")] = body.get("links") if isinstance(
                body, dict) else None
        return {where: [_text(form(item)) for item in items] for where, items
                in found.items() if isinstance(items, list)
                and all(isinstance(item, dict) for item in items)}
    before, after = arrays(held, _as_shown), arrays(new, _as_sent)
    left = {where: _count_out(texts, after.get(where, [])) for where, texts in before.items()}
    moved: list[tuple[tuple[str, ...], str, Any]] = []
    for there, texts in after.items():
        for text in _count_out(texts, before.get(there, [])):
            here = next((where for where, texts in left.items()
                         if where != there and text in texts), None)
            pieces = [array for array in _holders_at(root, here) if isinstance(array, AoT)
                      ] if here is not None else []
            if here is None or not pieces:
                continue
            left[here].remove(text)
            entry = next((entry for array in pieces for entry in array.body
                          if not any(entry is taken for _, _, taken in moved)
                          and _text(_as_shown(_plain(entry))) == text), None)
            if entry is not None:
                moved.append((there, text, entry))
    return moved


def _count_out(texts: list[str], others: list[str]) -> list[str]:
    """``texts`` without as many of each as ``others`` has."""
    rest = list(texts)
    for text in others:
        if text in rest:
            rest.remove(text)
    return rest


def _item(value: Any, where: tuple[str, ...], inline: bool = False,
          moves: lines.Carried | None = None) -> Any:
    """A new tomlkit value: tables where a configuration has them, inline otherwise (and
    always inside an inline table, ``inline``: the file wrote ``modules = {...}``); what
    ``moves`` brings to ``where`` as it was written."""
    if isinstance(value, dict):
        carried = moves.table(where) if moves is not None and not inline else None
        if carried is not None:
            return carried
        tabled = not inline and (_matches(where, _TABLES) or _matches(where[:-1], _TABLES))
        return _table(value, where, tomlkit.table() if tabled else tomlkit.inline_table(),
                      moves)
    if isinstance(value, list) and value and all(isinstance(item, dict) for item in value) \
            and _matches(where, _TABLE_ARRAYS) and not inline:
        array = tomlkit.aot()
        brought = _brought(moves, where, value)
        for index, item in enumerate(value):
            entry = brought.get(index)
            array.append(entry if entry is not None else
                         _table(item, where, tomlkit.table(), moves))
        return array
    if isinstance(value, list):
        return tomlkit.item([_plain_item(item) for item in value])
    return tomlkit.item(value)


def _table(value: dict[str, Any], where: tuple[str, ...], table: Any,
           moves: lines.Carried | None = None) -> Any:
    for key, item in value.items():
        if item is not None:
            table[key] = _item(item, (*where, key), isinstance(table, InlineTable), moves)
    inner = [item for _, item in table.value.body] if isinstance(table, Table) else []
    if isinstance(table, Table) and not (inner and all(isinstance(item, (Table, AoT))
                                                       for item in inner)):
        table.add(tomlkit.nl())     # a blank line before the next table (a table of
                                    # tables has its last one's: two blank lines)
    return table


def _plain_item(value: Any) -> Any:
    if isinstance(value, dict):
        table = tomlkit.inline_table()
        table.update({key: _plain_item(item) for key, item in value.items() if item is not None})
        return table
    return value


def _matches(where: tuple[str, ...], patterns: tuple[tuple[str, ...], ...]) -> bool:
    return any(len(where) == len(pattern) and all(p in ("*", w) for p, w in zip(
        pattern, where, strict=True)) for pattern in patterns)


def _same(read: Any, held: Any) -> bool:
    """Whether two documents' values are the same (NaN equal to NaN)."""
    def text(value: Any) -> str:
        return json.dumps(value, sort_keys=True, default=str)
    return text(read) == text(held)


def _plain(item: Any) -> Any:
    return item.unwrap() if hasattr(item, "unwrap") else item


def _entries(system: dict[str, Any]) -> dict[tuple[str, ...], Any]:
    """Every module entry of ``system`` by where it is: ``("modules", NAME)`` or
    ``("macros", MACRO, "modules", NAME)``."""
    found: dict[tuple[str, ...], Any] = {}
    if isinstance(system.get("modules"), dict):
        found.update({("modules", name): entry for name, entry in system["modules"].items()})
    macros = system.get("macros")
    for macro, body in (macros.items() if isinstance(macros, dict) else ()):
        if isinstance(body, dict) and isinstance(body.get("modules"), dict):
            found.update({("macros", macro, "modules", name): entry
                          for name, entry in body["modules"].items()})
    return found


def _moves_resolved(held: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    """``new`` with each module entry that moved (grouped into a macro, or out of one)
    resolved against the entry it was (``_resolved``): the page holds it as JSON, so
    ``gain = 1.0`` came back ``1`` in its new place, where nothing held it to compare."""
    before, moved = _entries(held), _moved(held, new)
    if not moved:
        return new
    new = copy.deepcopy(new)
    for where, was in moved.items():
        table = new
        for key in where[:-1]:
            table = table[key]
        table[where[-1]] = _resolved(before[was], table[where[-1]])
    return new


def _moved(held: dict[str, Any], new: dict[str, Any]) -> dict[tuple[str, ...], tuple[str, ...]]:
    """The module entries of ``new`` at a place ``held`` does not have whose name
    ``held`` has at one place only (grouped into a macro, or out of one): each new place
    with the place it had."""
    before = _entries(held)
    by_name: dict[str, list[tuple[str, ...]]] = {}
    for where in before:
        by_name.setdefault(where[-1], []).append(where)
    return {where: by_name[where[-1]][0] for where in _entries(new)
            if where not in before and len(by_name.get(where[-1], ())) == 1}


def _floats_declared(system: dict[str, Any], source: str) -> dict[str, Any]:
    """``system`` with each whole number in a module's state a float where the module's
    class declares a float for that field (``floats_as_declared``), as ``pb3a check``
    resolves the classes: in a module entry's state, a macro's module's, and an instance's
    overrides of its modules. JSON writes 3.0 as 3, and in a field the document did not
    set yet nothing held a float to compare with (``_resolved``): 3 typed there was saved
    ``gain = 3``. A whole number the document holds as it is stays as written."""
    if not any(isinstance(entry, dict) and _whole_numbers(entry.get("state"))
               for entry in _entries(system).values()):
        return system
    plan = check_data(system, source)[0]
    instances: dict[str, str] = {}       # a file macro's name in the plan -> an instance's path
    for path, macro in plan.macros.items():
        instances.setdefault(macro, path)
    system = copy.deepcopy(system)
    for where, entry in _entries(system).items():
        state = entry.get("state") if isinstance(entry, dict) else None
        if not isinstance(state, dict):
            continue
        if where[0] == "modules":
            path: str | None = where[-1]
        else:                                   # a macro's module: as in one of its instances
            instance = instances.get(f"[macros.{toml_key(where[1])}]")
            path = None if instance is None else f"{instance}/{where[-1]}"
        if path is None:
            continue
        if "macro" in entry and "class" not in entry:      # its modules' state, by path
            entry["state"] = {key: _as_declared(plan, f"{path}/{key}", fields)
                              for key, fields in state.items()}
        else:
            entry["state"] = _as_declared(plan, path, state)
    return system


def _as_declared(plan: Plan, path: str, state: Any) -> Any:
    """The state table ``state`` of module ``path`` of ``plan`` with its whole numbers
    floats where its class declares a float (as it is when there is no such module)."""
    module = plan.modules.get(path)
    if module is None or not isinstance(state, dict):
        return state
    return {name: floats_as_declared(getattr(module.cls, name, None), value)
            for name, value in state.items()}


def _whole_numbers(value: Any) -> bool:
    """Whether ``value`` is or holds an int (not a bool)."""
    if isinstance(value, dict):
        return any(_whole_numbers(item) for item in value.values())
    if isinstance(value, list):
        return any(_whole_numbers(item) for item in value)
    return type(value) is int


def _resolved(held: Any, new: Any, rewritten: bool = False) -> Any:
    """What to store for ``new`` (from the page) where the document holds ``held``. The
    page holds the document as JSON: a date as its text, a whole number beyond 2**53 as
    the nearest double (JavaScript's numbers). So ``held`` itself where ``new`` says
    what it says as the page shows it, item by item in a list or table (1700000000123456789
    was saved ...800, though nobody touched it); a date again where ``held`` was one and
    ``new`` is such text (an edited date was saved as a string); a float where ``held``
    was one and ``new`` is a whole number (7 typed into a float field was saved 7);
    else ``new``. In a list, which is written anew whole (``rewritten``), a float sent for
    a whole number held stays a float: the page never sends one, a field declared float
    does (``_floats_declared``; ``[-1, 1]`` edited was saved ``[-1, 2.0]``)."""
    if rewritten and type(held) is int and type(new) is float:
        return new
    shown, sent = _as_shown(held), _as_sent(new)
    if shown == sent or (isinstance(held, float) and _same(shown, sent)):   # nan too
        return held
    if isinstance(held, list) and isinstance(new, list):
        return [_resolved(held[index], item, True) if index < len(held) else item
                for index, item in enumerate(new)]
    if isinstance(held, dict) and isinstance(new, dict):
        return {key: _resolved(held[key], item, rewritten) if key in held else item
                for key, item in new.items()}
    if isinstance(held, (datetime.date, datetime.time)) and isinstance(new, str):
        with contextlib.suppress(ValueError):
            return type(held).fromisoformat(new)
    if isinstance(held, float) and type(new) is int:     # (JSON writes 7.0 as 7)
        return float(new)
    return new


def _as_shown(value: Any) -> Any:
    """``value`` as the page holds it (see ``_resolved``)."""
    if isinstance(value, dict):
        return {key: _as_shown(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_as_shown(item) for item in value]
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > 2 ** 53:
        return float(value)
    return _dates_as_text(value)


def _as_sent(value: Any) -> Any:
    """``value`` (from the page) as a double where it is how a browser writes one: the
    shortest decimal of that double. Any other whole number is a script's, exact (an
    exact change of a big number is an edit, not the page's rounding)."""
    if isinstance(value, dict):
        return {key: _as_sent(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_as_sent(item) for item in value]
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > 2 ** 53:
        double = float(value)
        return double if int(decimal.Decimal(repr(double))) == value else value
    return value


# JSON has no inf or nan: the page and the API carry such a float as {"$float": "inf"}
# ("-inf", "nan"), TOML's own words for it (an object that says exactly this is read as
# the float)
NON_FINITE = "$float"


def as_json(value: Any) -> Any:
    """``value`` as JSON can carry it: TOML's dates and times as their ISO text, a float
    that is not finite as ``{"$float": "inf"}`` (a document holding ``inf`` made
    ``GET /api/document`` a 500)."""
    if isinstance(value, dict):
        return {key: as_json(item) for key, item in value.items()}
    if isinstance(value, list):
        return [as_json(item) for item in value]
    if isinstance(value, float) and not math.isfinite(value):
        return {NON_FINITE: repr(value)}
    return _dates_as_text(value)


def float_of_json(pairs: list[tuple[str, Any]]) -> Any:
    """A JSON object read (``json.loads``'s ``object_pairs_hook``): the float it stands
    for if it is ``{"$float": "inf" | "-inf" | "nan"}``, else a dict."""
    if len(pairs) == 1 and pairs[0][0] == NON_FINITE and pairs[0][1] in ("inf", "-inf", "nan"):
        return float(pairs[0][1])
    return dict(pairs)


def _dates_as_text(value: Any) -> Any:
    """``value`` with TOML's dates and times as their ISO text, which JSON can carry
    (a date in a module's state made ``GET /api/document`` a 500)."""
    if isinstance(value, dict):
        return {key: _dates_as_text(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_dates_as_text(item) for item in value]
    if isinstance(value, (datetime.date, datetime.time)):       # (a datetime is a date)
        return value.isoformat()
    return value
