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
import threading
import time
from collections.abc import Iterator

from pb3a.loading.import_child import hung
from pb3a.loading.references import resolve_class
from pb3a.loading.served import module_servers


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


def unloadable(refs: dict[str, str], lane: ImportLane, timeout: float,
               longer: str) -> dict[str, str]:
    """Which of ``refs`` (module name -> ``"module:Class"``) this process cannot load,
    each with why and what to do; within ``timeout`` seconds: one not loaded by then is
    said to be waiting for the import under way (``longer``: how to give it more time).
    The imports run in a thread of their own, left to finish if they ever do."""
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
                    problems[name] = str(exc) + _where_to_put(exc)
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


def _where_to_put(exc: Exception) -> str:
    """What to add to a module file not found on this machine, when no module server
    is asked: it is found elsewhere (the launcher's machine), not here."""
    if not str(exc).startswith("cannot import module") or module_servers():
        return ""
    return ("; this node's machine lacks it: install it there (or put it on its "
            "PYTHONPATH), or serve it (pb3a modules serve DIR, and module_servers in the "
            "configuration)")
