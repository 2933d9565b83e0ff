"""Trying a module file's import in a child process before this process imports it.

A running system's launcher imports the class a live change names (``add``, ``swap``:
from the program, the command line, an agent or the manager), and the manager imports
the files its module browser lists and the classes its document names. Importing a
module file runs its top level: one that looped held the change for good (and, with
it, the launcher's lane of requests, or the manager's catalog), and one that ended the
process or crashed took the whole running system down. So a module this process has
not imported yet is imported in a child process first (``pb3a.loading.import_child``),
each import with a deadline; only if the child's import returned, or raised (this
process's own import then says why, in the usual words), is it imported here. A
module imported already costs nothing more: a traffic agent swapping among the
controllers it knows starts no process.
"""

from __future__ import annotations

import contextlib
import math
import sys
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

from pb3a.deadline import spoken
from pb3a.loading.import_child import IMPORT_EACH, Child, exit_status, hung
from pb3a.loading.references import ImportRefused, ImportWatch, file_of
from pb3a.loading.served import module_servers

START_TIMEOUT_S = 10.0      # a child may take this long to begin, or half an import's timeout
EXIT_WAIT_S = 1.0           # how long a child that ended its answers may take to exit
WROTE_CHARS = 300           # of what a child wrote last, in the sentence saying how it ended


def tried_first(timeout: float, longer: str) -> ImportWatch:
    """An import watch (``resolve_class``'s ``watch``) that tries a module this process
    has not imported yet in a child process first, one ``timeout`` (seconds) for all of
    it: ``ImportRefused`` saying what happened and what to do if it did not finish then,
    or ended the child; ``longer``: how to give it more time ("give the change a longer
    timeout")."""
    @contextlib.contextmanager
    def watch(module: str, ref: str) -> Iterator[None]:
        try_import(module, ref, timeout, longer)
        yield

    return watch


def try_import(module: str, ref: str, timeout: float, longer: str) -> None:
    """Try to import ``module`` (for the class ``ref``) in a child process, if this process
    has not imported it, within ``timeout`` seconds: ``ImportRefused`` saying what
    happened and what to do if it did not finish then, or ended the child."""
    how = import_problems([module], timeout, longer=longer,
                          deadline=time.monotonic() + timeout).get(module)
    if how is not None:
        raise ImportRefused(f"importing module {module!r} for {ref!r} {how}")


def import_problems(modules: Iterable[str], timeout: float, *, longer: str,
                    deadline: float | None = None) -> dict[str, str]:
    """How importing each of ``modules`` that this process has not imported went wrong,
    tried one after another in child processes: for each that did not finish within
    ``timeout`` seconds, or ended the child (an exit, a crash), what happened and what to
    do ("did not finish within 10 s: ..."; ``longer``: how to give it more time). A
    module that imported, or raised, is not among them. ``deadline`` (of
    ``time.monotonic()``) bounds the whole; a child that cannot begin by then (or within
    ``START_TIMEOUT_S``, or half of ``timeout`` if that is longer) leaves the modules it
    did not try with that problem.

    A module refused is refused again at once, saying the same, while its file is
    unchanged and until ``forget``: one that ended the child always, one that hung for
    a timeout no longer than the one it had (the manager plans its document at every
    edit, and an agent may retry a swap at every step)."""
    problems: dict[str, str] = {}
    waiting = []
    for module in dict.fromkeys(modules):
        if module not in sys.modules:
            known = _refused_before(module, timeout)
            if known is not None:
                problems[module] = known
            else:
                waiting.append(module)
    files = {module: file_of(module) for module in waiting}    # (as they are tried)
    while waiting:
        culprit, how, hanging = _tried(waiting, timeout, longer, deadline)
        if culprit is None:                  # all tried, or none could be: how, if so
            problems.update(dict.fromkeys(waiting, how) if how else {})
            break
        problems[culprit] = how
        file = files[culprit]
        if file is not None:                 # (a module server's: tried each time)
            with _lock:
                _refusals[culprit] = _Refusal(file, timeout if hanging else math.inf, how)
        waiting = waiting[waiting.index(culprit) + 1:]
    return problems


def forget(module: str) -> None:
    """Try ``module`` and its submodules again at their next import (they were
    reloaded), even if their files are unchanged: what they import may have changed."""
    with _lock:
        for name in [name for name in _refusals
                     if name == module or name.startswith(f"{module}.")]:
            del _refusals[name]


@dataclass(frozen=True)
class _Refusal:
    """A module refused: its file then (path, mtime, size), the timeout it had (``inf``:
    it ended the child, whatever the time), and what was said."""

    file: tuple[str, int, int]
    within: float
    how: str


_refusals: dict[str, _Refusal] = {}
_lock = threading.Lock()


def _refused_before(module: str, timeout: float) -> str | None:
    with _lock:
        refusal = _refusals.get(module)
    if refusal is None or timeout > refusal.within or file_of(module) != refusal.file:
        return None
    return refusal.how


def _tried(modules: list[str], timeout: float, longer: str,
           deadline: float | None) -> tuple[str | None, str, bool]:
    """Import ``modules`` in one child: (None, "", False) if it imported them all; the
    module it did not finish or ended in, how, and whether it did not finish (it hung);
    or (None, how, ...) if it ended or stayed silent outside an import (no module is to
    blame)."""
    child = Child(IMPORT_EACH, {"modules": modules, "servers": module_servers()},
                  keep_output=True)
    importing: str | None = None        # the module it is importing now, if any
    how, finished = "", False
    try:
        while True:
            # a slow start is the machine's, not the module's: a short timeout gets
            # ``START_TIMEOUT_S`` for it, a long one half of itself, the other half
            # left to the import (a swap given 30 s was refused after 10 beside a full
            # test run on two busy cores)
            wait = timeout if importing is not None else max(timeout / 2, START_TIMEOUT_S)
            if deadline is not None:
                wait = max(0.0, min(wait, deadline - time.monotonic()))
            try:
                said = child.next(wait)
            except TimeoutError:
                how = hung(timeout, longer, child.stuck_at()) if importing is not None else (
                    f"could not be tried: the process that tries imports did not begin "
                    f"within {spoken(wait)} s (is this machine overloaded?); try again, or "
                    f"{longer}")
                break
            if said is not None and "done" in said:
                return None, "", False
            if said is None:                 # it ended: how, once it has exited
                finished = True
                break
            importing = said.get("importing")
    finally:
        child.end(EXIT_WAIT_S if finished else 0)
    hanging = bool(how)
    if not hanging:
        how = exit_status(child.returncode, importing is not None)
        if importing is None:
            how = f"could not be tried: the process that tries imports {how}"
    return importing, how + _wrote(child.output), hanging


def _wrote(output: str) -> str:
    """What a child wrote last, to say with how it ended; "" if nothing."""
    last = output.splitlines()[-1].strip() if output else ""
    if len(last) > WROTE_CHARS:
        last = "..." + last[-WROTE_CHARS:]
    return f" (it wrote last: {last!r})" if last else ""
