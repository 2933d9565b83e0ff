"""Planning a configuration file in a child process, so the user's code cannot harm the check.

``pb3a check`` and ``pb3a graph`` import every module class a file names, and an
import runs the module file's top level: one that loops, waits for input, exits or
crashes took the command with it (it hung, or ended silently with the file's exit
status), and what it printed was mixed into the command's output. Here a fresh
Python process plans the file instead (the same compiler, so the same problems in
the same words) and answers with the plan's figures, its DOT text or its problems.

The child (a ``pb3a.loading.import_child.Child``) tells its parent which module it is
importing before each import (the hook ``watch_imports``). When it stops answering
during one (``import_timeout``), exits, or is killed by a signal, the parent blames
that import and plans the file again in a new child that refuses to import that
module, with a sentence saying what happened; so the file's other problems are still
reported, all at once. A hang names where the import was stuck (its stack), and the
module file whose top level waited there, a file several classes' modules import (a
driver's), is refused too: each import of it fails at once, naming it, instead of
waiting the timeout again, once for each class. What the user's code prints goes to
the check's stderr, not among the answers on stdout.
"""

from __future__ import annotations

import contextlib
import importlib.abc
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, NoReturn

from pb3a.config.description import refuse_a_script
from pb3a.errors import ConfigError
from pb3a.loading.import_child import Child, Stuck, answering, exit_status, hung

PLANNING_TIMEOUT_S = 30.0   # longest the child may say nothing outside imports (its start)
EXIT_WAIT_S = 5.0           # how long a child that answered may take to exit
MOST_CHILDREN = 16          # modules that may hang or end a child before the check gives up
LONGER = "give a longer --import-timeout"    # how to give an import more time

_ENTRY = "pb3a.config.isolated:answer"       # what the child runs


@dataclass(frozen=True)
class Checked:
    """What a valid file plans: its number of modules and links, its notes (what it
    likely leaves undone: ``Plan.notes``), and its DOT if asked for."""

    modules: int
    links: int
    dot: str | None = None
    notes: tuple[str, ...] = ()


def check_file(file: str, *, import_timeout: float, dot: bool = False) -> Checked:
    """Plan ``file`` in a child process; raises as ``System.load(file).plan()`` would
    (``OSError``, ``ConfigError`` listing every problem, ``ClusterKeyError``), an import
    that hung (past ``import_timeout`` seconds) or ended the child being one more problem
    of the entry that names it. This process imports neither the runtime nor the file's
    classes."""
    # a script, or a file that cannot be read, is said at once, as the child would say
    # it: a child started for it took 0.3-0.7 s to (a mistyped name, at every command)
    refuse_a_script(file)
    with open(file, "rb"):
        pass
    refused: dict[str, str] = {}
    stuck: dict[str, str] = {}          # a module file whose import hung -> how
    for _ in range(MOST_CHILDREN):
        ended = _planned(file, refused, stuck, import_timeout, dot)
        if ended.answer is not None:
            return _result(ended.answer)
        if not ended.importing:
            raise ConfigError([f"{file}: the process that checks it {ended.how}"
                               f"{' before it began' if not ended.ready else ''} (its error, "
                               "if it wrote one, is above)"])
        module, ref = ended.importing[-1]
        refused[module] = ended.how
        if ended.stuck is not None and ended.stuck.module_file is not None:
            stuck[ended.stuck.module_file] = hung(
                import_timeout, LONGER, f" as {ref!r} imported it{ended.stuck}")
    raise ConfigError([*(f"{file}: importing module {module!r} {how}"
                         for module, how in refused.items()),
                       f"{file}: checking stopped after {MOST_CHILDREN} module files hung or "
                       "ended the process that imports them: fix these, then check again"])


def _result(answer: dict[str, Any]) -> Checked:
    if "problems" in answer:
        raise ConfigError(answer["problems"])
    if "os_error" in answer:
        raise OSError(*answer["os_error"])
    if "key_error" in answer:
        from pb3a.transport.auth import ClusterKeyError  # (numpy, cryptography: rare)

        raise ClusterKeyError(answer["key_error"])
    return Checked(answer["modules"], answer["links"], answer.get("dot"),
                   tuple(answer.get("notes", ())))


@dataclass
class _Ended:
    """How one child ended: its answer, or how it ended without one (``how``) and the
    imports it was in then, innermost last."""

    answer: dict[str, Any] | None = None
    how: str = ""
    ready: bool = False
    importing: list[tuple[str, str]] = field(default_factory=list)
    stuck: Stuck | None = None          # where an import that hung was


def _planned(file: str, refused: dict[str, str], stuck: dict[str, str], import_timeout: float,
             dot: bool) -> _Ended:
    """Plan ``file`` in one child, reading its messages until it answers or ends; then
    end its process group."""
    child = Child(_ENTRY, {"file": file, "refused": refused, "stuck": stuck, "dot": dot})
    ended, finished = _Ended(), False
    try:
        _read(child, ended, import_timeout)
        finished = not ended.how
    finally:               # (an answer, or an end: it exits, or is exiting, by itself)
        child.end(EXIT_WAIT_S if finished else 0)
    if ended.answer is None and not ended.how:
        ended.how = exit_status(child.returncode, bool(ended.importing))
    return ended


def _read(child: Child, ended: _Ended, import_timeout: float) -> None:
    while True:
        wait = import_timeout if ended.importing else PLANNING_TIMEOUT_S
        try:
            said = child.next(wait)
        except TimeoutError:
            if ended.importing:
                ended.stuck = child.stuck_at()
                ended.how = hung(wait, LONGER, ended.stuck)
            else:
                ended.how = f"said nothing for {wait:g} s"
            return
        if said is None:
            return
        if "importing" in said:
            ended.importing.append(tuple(said["importing"]))
        elif "imported" in said and ended.importing:
            ended.importing.pop()
        elif "ready" in said:
            ended.ready = True
        else:
            ended.answer = said
            return


# -- the child ------------------------------------------------------------------------
def answer(request: dict[str, Any]) -> NoReturn:
    """In the child: plan ``request["file"]`` and write the answer, one JSON line on
    stdout after the import messages; then exit at once (a thread the user's code left
    running does not hold the child up). Run in the child ``_planned`` starts, never by
    a user."""
    send = answering()

    from pb3a.config.compiler import build_plan  # (the parent needs none of it)
    from pb3a.config.description import load_toml
    from pb3a.config.dot import plan_to_dot
    from pb3a.loading.references import ImportRefused, importing_for, watch_imports
    from pb3a.transport.auth import ClusterKeyError

    refused: dict[str, str] = request["refused"]
    stuck: dict[str, str] = request["stuck"]

    class RefuseStuck(importlib.abc.MetaPathFinder):
        """Refuses a module file whose import hung before (in another child)."""

        def find_spec(self, name: str, path: Any, target: Any = None) -> Any:
            for finder in sys.meta_path:
                find = getattr(finder, "find_spec", None)
                spec = None if finder is self or find is None else find(name, path, target)
                if spec is not None:
                    break
            else:
                return None
            if spec.origin not in stuck:
                return spec
            ref = importing_for()
            module = "" if ref is None else f" {ref.partition(':')[0]!r} for {ref!r}"
            raise ImportRefused(f"importing module{module} imports {spec.origin}, which "
                                f"{stuck[spec.origin]}")

    if stuck:
        sys.meta_path.insert(0, RefuseStuck())

    @contextlib.contextmanager
    def watched(module: str, ref: str) -> Iterator[None]:
        if module in refused:          # (it hung or ended the child before: how)
            raise ImportRefused(f"importing module {module!r} for {ref!r} {refused[module]}")
        send(importing=[module, ref])
        try:
            yield
        finally:
            send(imported=ref)

    watch_imports(watched)
    send(ready=True)
    try:
        plan = build_plan(load_toml(request["file"]))
        said: dict[str, Any] = {"modules": len(plan.modules), "links": len(plan.links),
                                "dot": plan_to_dot(plan) if request["dot"] else None,
                                "notes": plan.notes}
    except ConfigError as exc:
        said = {"problems": exc.problems}
    except ClusterKeyError as exc:
        said = {"key_error": str(exc)}
    except OSError as exc:
        said = {"os_error": [exc.errno, exc.strerror, exc.filename]}
    sys.stdout.flush()
    sys.stderr.flush()
    send(**said)
    os._exit(0)

