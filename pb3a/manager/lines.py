"""Where comments and blank lines go when an edit of a TOML document adds, removes or
moves one of its entries (a module's table, a link, a key).

A comment directly above an entry (no blank line between) is the entry's and goes with
it; one separated by a blank line is the section's and stays. tomlkit keeps the lines
before a table header at the end of the table before it: ``drop``, ``place`` and
``Carried`` work on the file's lines in order (``_tokens``), whatever tables hold them
(a table written in pieces, ``[macros.m]`` here and ``[macros.m.modules.a]`` there,
is several). ``pb3a.manager.document`` merges an edit into the document with them.
"""

from __future__ import annotations

import copy
from typing import Any

import tomlkit
from tomlkit.items import AoT, Comment, InlineTable, Null, Table, Whitespace


def _tokens(container: Any) -> list[tuple[str, Any, int, Any]]:
    """The document's items in the order they are written: ``("trivia", container,
    index, item)`` for a comment or blank line, ``("solid", container, index, item)`` for
    a key and value or a header (index -1 in its table's own body), and ``"start"`` and
    ``"end"`` marks around each table and array of tables."""
    tokens: list[tuple[str, Any, int, Any]] = []
    for index, (key, item) in enumerate(container.body):
        if key is None:
            if isinstance(item, (Comment, Whitespace)):
                tokens.append(("trivia", container, index, item))
        elif isinstance(item, AoT):
            tokens.append(("start", container, index, item))
            for table in item.body:
                tokens.extend(_table_tokens(table, True))
            tokens.append(("end", container, index, item))
        elif isinstance(item, Table) and not key.is_dotted():
            tokens.extend(_table_tokens(item, not item.is_super_table()))
        elif not isinstance(item, Null):
            tokens.append(("start", container, index, item))
            tokens.append(("solid", container, index, item))
            tokens.append(("end", container, index, item))
    return tokens


def _table_tokens(table: Table, header: bool) -> list[tuple[str, Any, int, Any]]:
    return [("start", None, 0, table), *([("solid", table.value, -1, table)] if header else []),
            *_tokens(table.value), ("end", None, 0, table)]


def _span(tokens: list[tuple[str, Any, int, Any]], item: Any) -> tuple[int, int]:
    """Where ``item`` starts and ends in ``tokens`` (-1, -1: not there, in an inline
    table or an array)."""
    marks = [at for at, token in enumerate(tokens) if token[3] is item and token[0] in (
        "start", "end")]
    return (marks[0], marks[-1]) if marks else (-1, -1)


def _run(tokens: list[tuple[str, Any, int, Any]], at: int, step: int) -> list[int]:
    """The comments and blank lines next to ``tokens[at]`` (before it with step -1, after
    with +1), in the file's order, the marks skipped."""
    found, at = [], at + step
    while 0 <= at < len(tokens) and tokens[at][0] != "solid":
        if tokens[at][0] == "trivia":
            found.append(at)
        at += step
    return found[::-1] if step < 0 else found


def _split(tokens: list[tuple[str, Any, int, Any]], run: list[int], kind: type) -> int:
    """How many of ``run`` are ``kind`` (comment or blank line) at its end."""
    count = 0
    while count < len(run) and isinstance(tokens[run[-1 - count]][3], kind):
        count += 1
    return count


def drop(root: Any, items: list[Any], delete: Any) -> None:
    """``delete()`` ``items`` from the document ``root`` (an entry, or each piece of a
    table written in pieces), each with the comments directly above it and, for a
    table, those directly below its last line (the table's own, followed by a blank
    line or the end of the file). Comments after a blank line stay where they are in the
    file, and so one blank line, not two or none, is left where it was."""
    tokens = _tokens(root)
    spans = sorted(span for span in (_span(tokens, item) for item in items) if span[0] >= 0)
    gone = {at for start, end in spans for at in range(start, end + 1)}
    stays: dict[int, list[Any]] = {}        # the line they go after -> the lines kept
    found = []
    for start, end in spans:        # (none in an inline table: no lines of their own)
        lead, blank, own, kept, last = _lines(tokens, tokens[start][3], start, end)
        if (kept and isinstance(tokens[kept[0]][3], Whitespace)) or (not kept and last):
            lead = blank + lead                 # what follows has its own blank line
        found.append((start, end, [*lead, *own], kept))
    # (a line inside one piece that is the next one's, `[modules.a.state]` then the
    # comment above `[modules.a]`, goes with that one: not kept as well)
    taken = {at for _, _, theirs, _ in found for at in theirs}
    for start, end, theirs, kept in found:
        for at in theirs:
            _, container, index, _ = tokens[at]
            container.body[index] = (None, Null())
        anchor = next((at for at in reversed(range(start)) if at not in gone
                       and tokens[at][0] in ("solid", "trivia")), -1)
        stays.setdefault(anchor, []).extend(tokens[at][3] for at in kept
                                            if start < at < end and at not in taken)
    delete()
    for anchor, inside in sorted(stays.items(), reverse=True):
        _, container, index, _ = tokens[anchor] if anchor >= 0 else ("solid", root, -1, None)
        _insert(container, index + 1, inside)     # (later ones first: each its index)


def _lines(tokens: list[tuple[str, Any, int, Any]], item: Any, start: int, end: int
           ) -> tuple[list[int], list[int], list[int], list[int], bool]:
    """The comments and blank lines around ``item`` (``tokens[start:end + 1]``), as
    ``drop`` takes them: the comments directly above it, the blank lines above those,
    its own below its last line (a table's, up to a blank line or the end of the file),
    the others after it, and whether it is the last entry of the file."""
    before = _run(tokens, start, -1)
    lead = before[len(before) - _split(tokens, before, Comment):]
    blank = before[:len(before) - len(lead)]
    blank = blank[len(blank) - _split(tokens, blank, Whitespace):]
    after = [*_run(tokens, end + 1, -1), *_run(tokens, end, 1)]
    last = not any(token[0] == "solid" for token in tokens[end:])
    first_blank = next((n for n, at in enumerate(after)
                        if isinstance(tokens[at][3], Whitespace)), None)
    if not isinstance(item, (Table, AoT)):              # a key: no comment below is its
        own = 0
    elif first_blank is None:
        own = len(after) if last else 0
    else:
        own = first_blank
    return lead, blank, after[:own], after[own:], last


def place(root: Any, item: Any, array: AoT | None = None) -> None:
    """Put a new table, array of tables, or entry of ``array``, ``item``, before the
    comments that belong to what follows it: those directly above the next entry of the
    same array, else all after the first blank line (the next section's)."""
    if not isinstance(item, (Table, AoT)) or isinstance(item, InlineTable):
        return
    tokens = _tokens(root)
    start, end = _span(tokens, item)
    if start < 0:
        return
    before = _run(tokens, start, -1)
    following = next((token[3] for token in tokens[end:] if token[0] == "solid"), None)
    blank = next((n for n, at in enumerate(before)
                  if isinstance(tokens[at][3], Whitespace)), None)
    if array is not None and any(entry is following for entry in array.body):
        moved = before[len(before) - _split(tokens, before, Comment):]
    elif blank is None:                 # no blank line: all directly above what follows
        moved = before if following is not None else []
    else:                               # the first blank line (or lines) stays before it
        while blank < len(before) and isinstance(tokens[before[blank]][3], Whitespace):
            blank += 1
        moved = before[blank:]
    for at in moved:
        _, container, index, _ = tokens[at]
        container.body[index] = (None, Null())
    last = _last_table(item)
    _insert(last.value, len(last.value.body), [tokens[at][3] for at in moved])
    stays = before[:len(before) - len(moved)]
    if stays and _split(tokens, stays, Whitespace):     # a blank line before it already:
        first = item if isinstance(item, Table) else item.body[0]    # not tomlkit's too
        first.trivia.indent = first.trivia.indent.lstrip("\n")


def _last_table(item: Table | AoT) -> Table:
    """The table whose lines end where ``item`` ends in the file: its last table (and
    that one's, ...; an array's last entry). Lines put at the end of a table that holds
    only tables gave it a header of its own (``[macros.stage]`` over
    ``[macros.stage.modules.scale]``)."""
    table = item if isinstance(item, Table) else item.body[-1]
    while True:                     # (lines after its last table end it: there)
        name, last = next(((name, line) for name, line in reversed(table.value.body)
                           if not isinstance(line, Null)), (None, None))
        if name is None or name.is_dotted() or not isinstance(last, (Table, AoT)) \
                or (isinstance(last, AoT) and not last.body):
            return table
        table = last if isinstance(last, Table) else last.body[-1]


def add_key(container: Table | tomlkit.TOMLDocument, key: str, item: Any) -> None:
    """Add ``key`` = ``item`` to a table (or the document) that has no ``key``, right
    after the keys it has: tomlkit puts it after the comments and blank lines that end
    the table, which are the next entry's (a module given a ``state`` or a ``node`` had
    it written under the next module's comment, no blank line before that module's
    header), and gives what follows a line break of its own. With no key there, it
    goes before the first blank line."""
    body = container.value.body if isinstance(container, Table) else container.body
    indents = [(line, line.trivia.indent) for _, line in body
               if not isinstance(line, (Whitespace, Null))]
    container[key] = item
    for line, indent in indents:
        line.trivia.indent = indent
    at = next((n for n, (name, _) in enumerate(body) if name is not None and name.key == key),
              None)
    if at is None:
        return
    last = next((n for n in reversed(range(at))
                 if not isinstance(body[n][1], (Comment, Whitespace, Null))), None)
    if last is not None and isinstance(body[last][1], (Table, AoT)):
        return                                  # (a key after a table is the table's)
    to = last + 1 if last is not None else next(
        (n for n in range(at) if isinstance(body[n][1], Whitespace)), at)
    if to < at:
        body.insert(to, body.pop(at))
        _reindex(container.value if isinstance(container, Table) else container,
                 lambda n: to if n == at else n + 1 if to <= n < at else n)


def rename(container: Table | tomlkit.TOMLDocument, old: str, new: str) -> None:
    """Give table ``old`` of a table (or the document) the name ``new`` where it is, its
    comments and blank lines kept around it (tomlkit has no call for it: removed and
    added anew, it lost them and went to the end of its table)."""
    body = container.value.body if isinstance(container, Table) else container.body
    at = next(n for n, (name, _) in enumerate(body) if name is not None and name.key == old)
    item = body[at][1]
    indent = item.trivia.indent
    del container[old]                  # (its place is left as tomlkit leaves it: empty)
    container[new] = item               # (tomlkit puts it last)
    item.trivia.indent = indent
    item.invalidate_display_name()      # (a header as written names it: [modules.old])
    end = next(n for n, (name, _) in enumerate(body) if name is not None and name.key == new)
    body[at], body[end] = body[end], body[at]
    _reindex(container.value if isinstance(container, Table) else container,
             lambda n: at if n == end else n)


def _insert(container: Any, index: int, items: list[Any]) -> None:
    """Put comments and blank lines ``items`` at ``index`` of a tomlkit container's body
    (tomlkit inserts only keys there)."""
    if not items:
        return
    container.body[index:index] = [(None, item) for item in items]
    _reindex(container, lambda n: n + len(items) if n >= index else n)


def _reindex(container: Any, moved: Any) -> None:
    """Tell a tomlkit container that the lines of its body moved: ``moved`` gives the
    new place of each line at an old one. tomlkit finds a key's line through an index
    of its own (``_map``) and has no public call to move a line or put one between two
    others: this is the one place that knows it (setup.cfg pins the versions it was
    tested on)."""
    index = container._map
    for key, at in index.items():
        index[key] = tuple(moved(n) for n in at) if isinstance(at, tuple) else moved(at)


class Carried:
    """Entries an edit moves from one place of the document to another, as the user wrote
    them (``take``): each with its own lines, as ``drop`` takes them, a copy of its table
    (or array entry, or inline table) with the comments in it and on its keys, and the
    comments directly above it. The copy is put in at the new place (``table``,
    ``brought``) instead of one made anew from the values (grouping modules into a macro
    lost every comment on them); ``lead_in`` then puts the comments above it there. A
    table renamed where it is (``rename``) is noted in ``renamed``."""

    def __init__(self) -> None:
        self.tables: dict[tuple[str, ...], Any] = {}             # new place -> the copy
        self.entries: dict[tuple[tuple[str, ...], str], list[Any]] = {}  # (array, value)
        self.away: list[Any] = []             # array entries taken elsewhere (originals)
        self.leads: dict[int, tuple[Any, str]] = {}   # id(copy) -> (copy, comments above)
        self.placed: list[Any] = []           # the copies put in
        self.renamed: list[str] = []          # tables given another name where they are

    def take(self, root: Any, item: Any, where: tuple[str, ...], text: str | None = None
             ) -> None:
        """Take ``item`` of document ``root`` to put at ``where``: a table (or the list
        of the pieces a table is written in, ``pieces``), or with ``text`` (what it
        says) an entry of the array of tables there."""
        carried = self._lift_pieces(root, item) if isinstance(item, list) \
            else self._lift(root, item)
        if text is None:
            self.tables[where] = carried
        else:
            self.entries.setdefault((where, text), []).append(carried)
            self.away.append(item)

    def table(self, where: tuple[str, ...]) -> Any:
        """The copy to put at ``where``, or None."""
        carried = self.tables.pop(where, None)
        if carried is not None:
            self.placed.append(carried)
        return carried

    def brought(self, where: tuple[str, ...], texts: list[str]) -> dict[int, Any]:
        """The copies to put in the array of tables at ``where``, which is to hold entries
        that say ``texts``, by index."""
        found = {}
        for index, text in enumerate(texts):
            waiting = self.entries.get((where, text))
            if waiting:
                found[index] = waiting.pop(0)
                self.placed.append(found[index])
        return found

    def gone(self, entry: Any) -> bool:
        """Whether array entry ``entry`` of the document moved elsewhere."""
        return any(entry is away for away in self.away)

    def lead_in(self) -> None:
        """Put the comments that were directly above each copy above it where it is now:
        before its header or key, after the blank lines there (as the file has them, in
        the copy's indent: the text is read again as a file's once written)."""
        for carried in self.placed:
            comments = self.leads.get(id(carried), (None, ""))[1]
            indent = carried.trivia.indent
            blank = indent[:len(indent) - len(indent.lstrip("\n"))]
            carried.trivia.indent = blank + comments + indent[len(blank):]

    @staticmethod
    def pieces(root: Any, items: list[Any]) -> bool:
        """Whether ``items`` are the pieces of one table of document ``root`` under
        headers of their own (``[modules.a]``, other tables, then ``[modules.a.state]``),
        which ``take`` moves together; not a table in dotted keys (``a.class = ...``)."""
        tokens = _tokens(root)
        for item in items:
            start = _span(tokens, item)[0] if isinstance(item, Table) \
                and not isinstance(item, InlineTable) else -1
            if start < 0 or tokens[start][1] is not None:       # (a dotted key's: inline)
                return False
        # one piece under the table's own header, the others holding its tables only
        return sum(not item.is_super_table() for item in items) == 1

    def _lift_pieces(self, root: Any, pieces: list[Any]) -> Any:
        """One copy of a table written in ``pieces`` (see ``pieces``), to put in elsewhere
        whole: the first one's copy (``_lift``), then each later one's lines, the
        comments directly above it before its first line (grouped into a macro, such a
        module was made anew from its values, every comment on it lost). The piece
        under the table's header comes first wherever it was: the keys it holds go
        before the tables of the others."""
        first, *rest = sorted(pieces, key=lambda piece: piece.is_super_table())
        carried = self._lift(root, first)
        for piece in rest:
            part = self._lift(root, piece)
            lead = self.leads.pop(id(part))[1]
            body = [(name, line) for name, line in part.value.body if not isinstance(line, Null)]
            head = next((line for name, line in body if name is not None), None)
            if head is not None and lead:       # (as lead_in puts them above a header)
                indent = head.trivia.indent
                blank = indent[:len(indent) - len(indent.lstrip("\n"))]
                head.trivia.indent = blank + lead + indent[len(blank):]
            # a blank line after its last table (the one _lift gives it) is one too
            # many when that table ends with its own; the last one is seen to below
            while len(body) > 1 and isinstance(body[-1][1], Whitespace) \
                    and isinstance(body[-2][1], Table):
                body.pop()
            for name, line in body:
                carried.value.append(name, line)
        last = _last_table(carried)     # a blank line before what follows, one
        if not any(isinstance(line, Whitespace) for _, line in last.value.body[-1:]):
            last.add(tomlkit.nl())
        return carried

    def _lift(self, root: Any, item: Any) -> Any:
        """A copy of ``item`` with its own lines (``_lines``), to put in elsewhere; the
        comments directly above it kept for ``lead_in``."""
        carried = copy.deepcopy(item)
        tokens = _tokens(root)
        start, end = _span(tokens, item)
        if start < 0:                             # in an inline table: no lines its own
            return carried
        lead, _, _, kept, _ = _lines(tokens, item, start, end)
        if isinstance(item, Table):
            header = tokens[start + 1][0] == "solid" and tokens[start + 1][3] is item
            inside = _table_tokens(carried, header)        # (the copy's, token for token)
            for at in kept:
                if start < at < end:                       # the next section's lines
                    _, container, index, _ = inside[at - start]
                    container.body[index] = (None, Null())
            carried.invalidate_display_name()      # (a header as written: [modules.scale])
            if not any(isinstance(line, Whitespace) for _, line in carried.value.body[-1:]):
                carried.add(tomlkit.nl())          # a blank line before what follows
        self.leads[id(carried)] = (carried, "".join(tokens[at][3].as_string() for at in lead))
        return carried
