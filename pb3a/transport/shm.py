"""Shared-memory segments with one owner.

The executor creates and unlinks every segment (``create_segment`` for rings; a
migrating module's snapshot, which its worker writes into, see
``pb3a.transport.snapshot``); workers only attach (``attach_segment``) and never
register with CPython's resource tracker, which would otherwise unlink a segment
another process still uses (cpython#82300). Names carry the owner's pid, so
``reap_orphans`` can remove segments whose owner died without cleaning up.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import sys
from multiprocessing import resource_tracker, shared_memory

import psutil

PREFIX = "pb3a_"
RING = "ring"                   # the kind of the segments ``create_segment`` makes
_SHM_DIR = "/dev/shm"
_counter = itertools.count()


def segment_name(kind: str) -> str:
    """A fresh segment name owned by this process: ``pb3a_<pid>_<kind><n>``."""
    return f"{PREFIX}{os.getpid()}_{kind}{next(_counter)}"


def segment_path(name: str) -> str:
    """Where segment ``name`` is on this machine's shared-memory file system."""
    return os.path.join(_SHM_DIR, name)


def unlink_name(name: str) -> None:
    """Unlink segment ``name`` (owner side) without mapping it; gone already is fine.
    Processes that mapped it keep their mappings."""
    with contextlib.suppress(FileNotFoundError):
        os.unlink(segment_path(name))


def memory_domain() -> str:
    """Where this process's segments can be seen: two processes that report the same
    domain (one boot of one machine, one shared-memory file system) can hand each other
    a segment by name."""
    with open("/proc/sys/kernel/random/boot_id") as boot:
        booted = boot.read().strip()
    return f"{booted}/{os.stat(_SHM_DIR).st_dev}"


class Segment(shared_memory.SharedMemory):
    """A shared-memory segment whose collection says nothing of views that outlived it:
    an interrupted launcher, a ring made or attached but never closed (the interrupt
    came in between), printed "Exception ignored in SharedMemory.__del__ ... BufferError:
    memoryview has 1 exported buffer" as it exited."""

    def __del__(self) -> None:
        with contextlib.suppress(BufferError):
            super().__del__()


def create_segment(name: str, size: int) -> Segment:
    """Create a segment (owner side). The resource tracker unlinks it if we die."""
    try:
        return Segment(name=name, create=True, size=size)
    except FileExistsError:
        raise                           # (not ours to unlink)
    except BaseException:               # an error or a Ctrl-C once it was made: the
        unlink_name(name)               # file may be there, known to nobody
        raise


def attach_segment(name: str) -> Segment:
    """Attach to an existing segment without registering it with the resource tracker."""
    if sys.version_info >= (3, 13):
        return Segment(name=name, track=False)  # type: ignore[call-arg]
    register = resource_tracker.register
    resource_tracker.register = lambda *args, **kwargs: None  # type: ignore[assignment]
    try:
        return Segment(name=name)
    finally:
        resource_tracker.register = register  # type: ignore[assignment]


def close_segment(segment: shared_memory.SharedMemory) -> None:
    """Close our mapping; if array views still use it, leave it to the garbage collector
    (whose ``Segment.__del__`` tries again, quietly)."""
    with contextlib.suppress(BufferError):
        segment.close()


def unlink_segment(segment: shared_memory.SharedMemory) -> None:
    """Close and unlink (owner side); a segment already gone is fine."""
    close_segment(segment)
    with contextlib.suppress(FileNotFoundError):
        segment.unlink()


def reap_orphans() -> list[str]:
    """Unlink PB3A segments whose owning process is gone; returns their names."""
    reaped = []
    try:
        names = os.listdir(_SHM_DIR)
    except FileNotFoundError:
        return reaped
    for name in names:
        if not name.startswith(PREFIX):
            continue
        pid = name[len(PREFIX):].split("_", 1)[0]
        if pid.isdigit() and not psutil.pid_exists(int(pid)):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(segment_path(name))
                reaped.append(name)
    return reaped


def reap_child(pid: int) -> list[str]:
    """Unlink the segments of ``pid``, a dead child that shared this process's resource
    tracker (multiprocessing hands it down), and take them off the tracker's list: left
    on it, they were named "leaked" when this process ended, and the tracker failed to
    unlink each again (a node controller whose executor was killed, fenced)."""
    reaped = []
    for name in live_segments(pid):
        with contextlib.suppress(FileNotFoundError):
            os.unlink(segment_path(name))
            reaped.append(name)
            # Rings (``create_segment``) are on its list; a snapshot's segment is not,
            # and the tracker prints a traceback for a name it does not hold.
            if name.startswith(f"{PREFIX}{pid}_{RING}"):
                resource_tracker.unregister(f"/{name}", "shared_memory")
    return reaped


def live_segments(owner: int | None = None) -> list[str]:
    """Names of PB3A segments in /dev/shm, optionally only those owned by ``owner``."""
    try:
        names = os.listdir(_SHM_DIR)
    except FileNotFoundError:
        return []
    prefix = f"{PREFIX}{owner}_" if owner is not None else PREFIX
    return sorted(n for n in names if n.startswith(prefix))
