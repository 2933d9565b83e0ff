"""Loading code by reference: turn ``"package.module:Class"`` into the class.

Configurations name module classes as strings so that a TOML file, a running
system and a module server can all refer to the same code. Only the colon form
is accepted: it says unambiguously where the importable module ends and the
attribute path inside it begins (``"pkg.mod:Outer.Inner"`` works too).
"""

from __future__ import annotations

import contextlib
import difflib
import functools
import importlib
import importlib.metadata
import os
import pkgutil
import re
import sys
import sysconfig
import threading
import traceback
import weakref
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path
from types import ModuleType

from pb3a.errors import ConfigError
from pb3a.loading import served

_REF = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_][\w.]*$")


def class_ref(cls: type) -> str:
    """The ``"module:QualName"`` reference that ``resolve_class`` turns back into ``cls``."""
    return f"{cls.__module__}:{cls.__qualname__}"


def by_reference(cls: type) -> bool:
    """Whether ``cls`` travels to another process by reference (its ``class_ref``, which
    the far side imports), not by value: a class of an importable module's top level,
    not of a script run as ``__main__`` nor defined inside a function (those are
    pickled whole, code and all; see ``pb3a.transport.pickling``)."""
    return cls.__module__ != "__main__" and "<locals>" not in cls.__qualname__


def resolve_class(ref: str | type, *, watch: ImportWatch | None = None) -> type:
    """The class ``ref`` names: a class is returned as is, a ``"module:Class"`` is imported.

    Raises ValueError for a malformed reference, ImportError when the module cannot
    be imported, LookupError when it has no such attribute and TypeError when the
    attribute is not a class; each message says what to change. The import runs inside
    ``watch`` (see ``watch_imports``), else the process's watch.
    """
    if isinstance(ref, type):
        return ref
    if not isinstance(ref, str):
        raise TypeError(f"a class reference must be a class or a 'module:Class' string, "
                        f"got {ref!r}")
    if not _REF.match(ref):
        hint = "e.g. 'examples.pipeline:Ticker'"
        if ":" not in ref and "." in ref:
            module, _, name = ref.rpartition(".")
            hint = f"here probably '{module}:{name}', or '{ref}:Class' if {ref} is the module"
        raise ValueError(f"bad class reference {ref!r}: use 'module:Class', {hint}")
    module_name, _, attr_path = ref.partition(":")
    before, _importing.ref = importing_for(), ref
    try:
        with (watch or _watch)(module_name, ref):
            module = importlib.import_module(module_name)
        _note_file(module_name, module)
    except ImportRefused:                       # said in full by whoever refused it
        raise
    except ImportError as exc:
        missing = exc.name if isinstance(exc, ModuleNotFoundError) else None
        if missing and (module_name == missing or module_name.startswith(f"{missing}.")):
            raise ImportError(f"cannot import module {module_name!r} for {ref!r}: {exc}"
                              f"{_nearest_module(missing)}; "
                              "check the module path and that it is installed or on "
                              f"sys.path{served.not_served(missing)}"
                              f"{served.server_trouble()}") from exc
        # found, but an import of its own failed: the path is not what to check
        fix = ("" if missing is None else "; correct that import" if _top(missing) ==
               _top(module_name) else f"; install {missing!r} or correct that import")
        raise ImportError(f"importing module {module_name!r} for {ref!r} failed"
                          f"{_where_it_failed(exc)}: {exc}{fix}"
                          f"{served.server_trouble()}") from exc
    except ConfigError as exc:  # it launched a system as it was imported: said in full
        raise ImportError(f"importing module {module_name!r} for {ref!r} failed: "
                          f"{'; '.join(exc.problems)}") from None
    except SystemExit as exc:   # a script's exit, run as it is imported: not this process's
        raise ImportError(f"importing module {module_name!r} for {ref!r} failed"
                          f"{_where_it_failed(exc)}: it calls sys.exit({exc.code!r}) as it is "
                          "imported; a module must not exit when imported (put that code "
                          "under if __name__ == '__main__':)") from exc
    except Exception as exc:  # a module that fails while importing: say which and why
        raise ImportError(f"importing module {module_name!r} for {ref!r} failed"
                          f"{_where_it_failed(exc)}: {type(exc).__name__}: {exc}") from exc
    finally:
        _importing.ref = before
    target: object = module
    where = f"module {module_name!r}"
    for part in attr_path.split("."):
        if not hasattr(target, part):
            raise LookupError(f"{where} has no class {part!r}{_suggest(target, part)}"
                              f"{_imported_from(module)}")
        target = getattr(target, part)
        where = f"class {part!r}"
    if not isinstance(target, type):
        raise TypeError(f"{ref!r} is a {type(target).__name__}, not a class")
    return target


def changed_since_import(module: str) -> bool:
    """Whether the file of ``module`` (imported in this process) has changed since
    ``resolve_class`` first saw it imported here: its mtime or size differs, or it is
    gone. False for a module not imported, one that has no file here (a module server's),
    or one no class was resolved from."""
    with _files_lock:
        then = _files.get(module)
    loaded = sys.modules.get(module)
    if then is None or loaded is None:
        return False
    return _file_now(loaded) != then


def _note_file(name: str, module: ModuleType) -> None:
    """Remember the file ``module`` was imported from as it is now, unless it is noted
    already for this very module object (a module imported again after ``forget`` is a
    new object: its file is noted anew)."""
    with _files_lock:
        if _noted.get(name) is not module:
            _noted[name], _files[name] = module, _file_now(module)


def _file_now(module: ModuleType) -> tuple[str, int, int] | None:
    """The file ``module`` was imported from, its mtime and size now; None if it has no
    file on this machine (a module server's, a built-in) or it is gone."""
    path = getattr(module, "__file__", None)
    if not isinstance(path, str):
        return None
    try:
        found = os.stat(path)
    except OSError:
        return None
    return path, found.st_mtime_ns, found.st_size


def file_of(module: str) -> tuple[str, int, int] | None:
    """The file ``module`` imports from on ``sys.path``, its mtime and size, found without
    importing anything (its packages neither); None if there is none."""
    parts = module.split(".")
    for entry in sys.path:
        if not isinstance(entry, str):
            continue
        base = os.path.join(entry or ".", *parts)
        for path in (f"{base}.py", os.path.join(base, "__init__.py")):
            with contextlib.suppress(OSError):
                found = os.stat(path)
                return path, found.st_mtime_ns, found.st_size
    return None


# Each module resolve_class imported from, and its file then (``changed_since_import``);
# the module object noted, held weakly (a module dropped from the cache is not kept).
_files: dict[str, tuple[str, int, int] | None] = {}
_noted: weakref.WeakValueDictionary[str, ModuleType] = weakref.WeakValueDictionary()
_files_lock = threading.Lock()


class ImportRefused(ImportError):
    """An import that the process's import watcher refused (see ``watch_imports``); its
    message is the whole sentence to show, naming the module and the reference."""


ImportWatch = Callable[[str, str], AbstractContextManager[object]]


def _unwatched(module: str, ref: str) -> AbstractContextManager[object]:
    return contextlib.nullcontext()


_watch: ImportWatch = _unwatched


def watch_imports(watch: ImportWatch | None) -> ImportWatch:
    """From now on, ``resolve_class`` imports a class's module inside ``watch(module,
    ref)`` (None: none), which may raise ``ImportRefused`` instead; gives the watch
    before it. A process that imports classes on another's behalf tells it so which
    import it is in when it hangs or dies, and refuses one that did so before (``pb3a
    check``'s, see ``pb3a.config.isolated``), or tries each in a child process first
    (the manager's, see ``pb3a.loading.trial``)."""
    global _watch
    before, _watch = _watch, watch or _unwatched
    return before


# While resolve_class imports a class's module, the reference it imports for: a system
# launched then is launched by that module as it is imported (pb3a.launch refuses it).
_importing = threading.local()


def importing_for() -> str | None:
    """The class reference this thread imports a module for, if it is doing so now."""
    return getattr(_importing, "ref", None)


def _where_it_failed(exc: BaseException) -> str:
    """`` at FILE, line N``: the line of the user's code the import failed on (the
    deepest frame outside Python's own library and PB3A), or nothing if there is none
    (a failure a worker reported: its frames are PB3A's)."""
    frames = [frame for frame in traceback.extract_tb(exc.__traceback__)
              if not frame.filename.startswith(("<frozen ", *_NOT_THE_USERS))]
    return f" at {frames[-1].filename}, line {frames[-1].lineno}" if frames else ""


# (the folders of Python's own library, of installed packages, and PB3A's own)
_NOT_THE_USERS = tuple(os.path.join(folder, "") for folder in {
    *(sysconfig.get_paths()[kind] for kind in ("stdlib", "platstdlib", "purelib", "platlib")),
    str(Path(__file__).resolve().parent.parent)})


def _top(module: str) -> str:
    """The top-level package of a dotted module name."""
    return module.partition(".")[0]


def _nearest_module(missing: str) -> str:
    """" (did you mean 'examples.pipeline'?)" for a module path whose last part is
    misspelt, if its package (or, for a top-level one, the import path or an installed
    distribution) has one near."""
    package, _, leaf = missing.rpartition(".")
    try:
        where = importlib.import_module(package).__path__ if package else None
    except (ImportError, AttributeError):      # (no package there: nothing beside it)
        return ""
    names = {m.name for m in pkgutil.iter_modules(where)}
    if where is None:       # an editable install's packages are on no directory of the path
        names.update(_installed_packages())
    close = difflib.get_close_matches(leaf, sorted(names), n=1)
    return f" (did you mean {'.'.join(filter(None, (package, close[0])))!r}?)" if close else ""


@functools.cache
def _installed_packages() -> frozenset[str]:
    """The top-level packages of the installed distributions, read once (a large
    environment takes a second); none if one of them cannot be read (a distribution's
    metadata not in UTF-8 failed the suggestion and hid the error it was for)."""
    try:
        return frozenset(importlib.metadata.packages_distributions())
    except Exception:
        return frozenset()


def _imported_from(module: ModuleType) -> str:
    """Where ``module`` was imported from, for a class it lacks: "; it was imported from
    FILE", or from a directory with no ``__init__.py`` (a namespace package, which any
    directory of that name on the path makes: one beside a node controller shadowed the
    configuration's file). A copy other than the one meant is the likely cause."""
    path = getattr(module, "__file__", None)
    if isinstance(path, str):
        return f"; it was imported from {path}"
    where = [str(entry) for entry in getattr(module, "__path__", ())]
    if not where:
        return ""
    return (f"; it was imported from {', '.join(where)}, a directory with no __init__.py "
            "(a namespace package): rename it, or move it off the import path")


def _suggest(namespace: object, name: str) -> str:
    # (a module's own classes, not those it imports: "it has: ..., Input, InputPort,
    # Module, Output, ..." named pb3a's own among them)
    home = getattr(namespace, "__name__", None) if isinstance(namespace, ModuleType) else None
    classes = sorted(k for k, v in vars(namespace).items()
                     if isinstance(v, type) and not k.startswith("_")
                     and (home is None or v.__module__ == home))
    close = difflib.get_close_matches(name, classes, n=1)
    if close:
        return f" (did you mean {close[0]!r}?)"
    if classes:
        return f"; it has: {', '.join(classes)}"
    return ""
