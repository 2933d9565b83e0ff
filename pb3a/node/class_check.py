"""Whether a node loads the classes of the modules it is to run, asked before a launch
starts anything anywhere.

A remote node's machine has its own code: a module file missing there (and from the
module servers), an older copy without the class, one whose imports fail there. The
launcher's process resolved every class already; each remote node's executor is asked
to load the classes of its own modules (``unloadable``), all nodes side by side, and
the launch stops before any module is added, naming every class that cannot be loaded,
where, and why (``resolve_class``'s words: the file to put in the module server, the
ImportError raised on that machine). An import that does not finish within the
launch's timeout is named too: the module being imported then, which may be one the
node's preload of the system's classes imports (``ImportLane``).
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time
from collections.abc import Iterator

from pb3a.loading.import_child import hung
from pb3a.loading.references import resolve_class
from pb3a.loading.served import module_servers
from pb3a.loading.sources import CodeSources


class ImportLane:
    """This process's imports of a system's module files, one at a time: ``lock``, held
    by each (the decoding of a request that names a class too), and the module being
    imported under it now, to name when an import does not finish."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.module: str | None = None

    @contextlib.contextmanager
    def importing(self, module: str) -> Iterator[None]:
        """Hold the lock while importing ``module``."""
        with self.lock:
            self.module = module
            try:
                yield
            finally:
                self.module = None


def unloadable(refs: dict[str, str], lane: ImportLane, timeout: float, longer: str,
               code: CodeSources) -> dict[str, str]:
    """Which of ``refs`` (module name -> ``"module:Class"``) this process cannot load,
    each with why and what to do; within ``timeout`` seconds: one not loaded by then is
    said to be waiting for the import under way (``longer``: how to give it more time).
    The imports run in a thread of their own, left to finish if they ever do. This
    process imports from the workers' path (``code``, installed as its executor was
    bound, before any import: ``pb3a.loading.sources.import_path``)."""
    problems: dict[str, str] = {}
    checked: list[str] = []
    done = threading.Event()
    deadline = time.monotonic() + timeout

    def load_each() -> None:
        for name, ref in refs.items():
            with lane.importing(ref.partition(":")[0]):
                try:
                    resolve_class(ref)
                except (ImportError, LookupError, TypeError, ValueError) as exc:
                    problems[name] = str(exc) + _where_to_put(exc, code)
            checked.append(name)
        done.set()

    threading.Thread(target=load_each, name="pb3a-class-check", daemon=True).start()
    done.wait(max(0.0, deadline - time.monotonic()))
    seen = set(checked)                    # (then its problems: each is in before it is)
    said = dict(problems)
    late = [name for name in refs if name not in seen]
    if late:
        module = lane.module or refs[late[0]].partition(":")[0]
        why = f"importing module {module!r} here {hung(timeout, longer)}"
        for name in late:
            said.setdefault(name, f"{refs[name]!r} was not loaded: {why}")
    return said


def _where_to_put(exc: Exception, code: CodeSources) -> str:
    """What to add to a module file not found on this machine, when no module server
    is asked: where it was looked for here (``searched``), and whether the directories
    the launcher handed (``code.paths``: its configuration's, its script's) are on this
    machine. A node on the launcher's own machine, which has them, was said to lack
    the file, and to be the wrong machine."""
    if not str(exc).startswith("cannot import module") or module_servers():
        return ""
    serve = "serve it (pb3a modules serve DIR, and module_servers in the configuration)"
    absent = [path for path in code.paths if not os.path.isdir(path)]
    said = f"; searched here: {searched(code.paths)}"
    if absent or not code.paths:
        gone = (f" ({', '.join(absent)}, the launcher's, {'is' if len(absent) == 1 else 'are'}"
                " not on it)" if absent else "")
        return (f"{said}; this node's machine lacks it{gone}: install it there (or put it "
                f"on its PYTHONPATH), or {serve}")
    where = ("the launcher's directory" if len(code.paths) == 1
             else "one of the launcher's directories")
    return f"{said}; put it in {where} on this machine, or {serve}"


def searched(handed: tuple[str, ...]) -> str:
    """This process's import path, said in short: each directory, those ``handed`` by the
    launcher marked so (also one under Python's prefix: a launcher's /usr/local/lab),
    and the current one (its node controller's, where that was started) too; Python's
    own (the standard library, the installed packages) as one entry, said once."""
    own = {os.path.realpath(prefix) for prefix in
           (sys.prefix, sys.base_prefix, sys.exec_prefix, sys.base_exec_prefix)}
    here = ""
    with contextlib.suppress(OSError):      # (the current directory removed under it)
        here = os.getcwd()
    said: list[str] = []
    for entry in sys.path:
        if not isinstance(entry, str):
            continue
        path = entry or here
        real = os.path.realpath(path)
        if path in handed:
            said.append(f"{path} (the launcher's)")
        elif any(real == prefix or real.startswith(prefix + os.sep) for prefix in own):
            if _PYTHON_S not in said:
                said.append(_PYTHON_S)
        elif path == here:
            said.append(f"{path} (the current directory, its controller's)")
        else:
            said.append(path)
    return ", ".join(said)


_PYTHON_S = "Python's standard library and installed packages"
