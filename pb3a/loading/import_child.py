"""A child Python process that imports a user's module files for a process they must not harm.

Importing a module file runs its top level, which may loop, wait (for input, a lock,
the network), end the process (``os._exit()``) or crash it (a segfault in native code).
A process that imports a user's files on someone's behalf (``pb3a check``, a running
system's launcher, the manager) has a fresh Python process import them first: a
``Child`` runs a function of PB3A's in a new interpreter with this process's import
path, and reads what it says, one JSON object a line, each with a deadline. Before
each import the child says which module it imports (``importing``); so an import that
takes too long (``hung``), or a child that ends during one (``exit_status``), is blamed
on that module, in words that say what to do; one that takes too long is asked where it
is (``stuck_at``: its stack, which Python's ``faulthandler`` writes on a signal), since a
module file that waits in a file it imports (a driver's, shared by several) hung in
that file, which the module's name did not say.

The child reads nothing (its stdin is ``/dev/null``: ``input()`` ends at once), what the
user's code prints goes to its stderr (this process's, or a pipe whose last lines are
kept, ``output``), it ends when its parent dies, and its process group is killed when
it is done: a process an import started does not outlive it. This module needs only
the standard library, so that ``pb3a check``'s own process imports nothing else.
"""

from __future__ import annotations

import collections
import contextlib
import faulthandler
import importlib
import json
import os
import re
import selectors
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NoReturn

OUTPUT_KEPT = 2000          # bytes of a child's output kept, when it is kept: the last ones

# (what the child runs: the parent's import path first, as pb3a itself may be on it only;
# run with -P, as -c put the current directory first, and a user's json.py there
# was imported for the standard library's)
_BOOT = ("import json, sys; sys.path[:] = json.loads(sys.argv[1]); "
         "from {module} import {function}; {function}(json.loads(sys.argv[2]))")
_CRASHES = {"SIGSEGV", "SIGBUS", "SIGILL", "SIGFPE", "SIGABRT"}
# A child writes its threads' stacks on this signal to the pipe this variable names.
# (a real-time one: a module file that handles SIGUSR1 for its own ends took it over,
# and the stacks never came)
_STACK_SIGNAL = signal.SIGRTMIN + 7
_STACK_FD = "PB3A_STACK_FD"
STACK_WAIT_S = 1.0        # how long a stuck child's stacks are waited for, at most
_FRAME = re.compile(r'^\s*File "(.*)", line (\d+) in (.*)$', re.MULTILINE)


class Child:
    """A fresh Python process running ``entry`` (``"pb3a.x:function"``, given ``request``
    as JSON), its messages read with a deadline each; ``keep_output``: its stderr (and
    what its user code prints) is read into ``output`` instead of going to ours."""

    def __init__(self, entry: str, request: Any, *, keep_output: bool = False) -> None:
        module, _, function = entry.partition(":")
        path = [str(entry) for entry in sys.path if isinstance(entry, (str, os.PathLike))]
        self._stacks, stacks = os.pipe()
        try:
            self.process = subprocess.Popen(
                [sys.executable, "-P", "-c", _BOOT.format(module=module, function=function),
                 json.dumps(path), json.dumps(request)],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                stderr=subprocess.PIPE if keep_output else None, start_new_session=True,
                pass_fds=(stacks,), env={**os.environ, _STACK_FD: str(stacks)})
        except BaseException:
            os.close(self._stacks)
            raise
        finally:
            os.close(stacks)
        self._pidfd = os.pidfd_open(self.process.pid)   # (readable once it has exited)
        self._selector = selectors.DefaultSelector()
        for pipe in (self.process.stdout, self.process.stderr):
            if pipe is not None:
                self._selector.register(pipe, selectors.EVENT_READ)
        self._pending = b""
        self._lines: collections.deque[bytes] = collections.deque()
        self._said_all = False
        self._output = b""

    def next(self, wait: float) -> dict[str, Any] | None:
        """The child's next message; None once it has closed its end (it ended, or is
        ending); ``TimeoutError`` if none came within ``wait`` seconds."""
        answers = self.process.stdout
        assert answers is not None
        deadline = time.monotonic() + wait
        while not self._lines:
            if self._said_all:
                return None
            ready = self._selector.select(max(0.0, deadline - time.monotonic()))
            if not ready:
                raise TimeoutError
            for key, _ in ready:
                chunk = os.read(key.fd, 65536)
                if key.fileobj is not answers:
                    if not chunk:
                        self._selector.unregister(key.fileobj)
                    self._output = (self._output + chunk)[-OUTPUT_KEPT:]
                elif not chunk:
                    self._said_all = True
                else:
                    *lines, self._pending = (self._pending + chunk).split(b"\n")
                    self._lines.extend(lines)
        return json.loads(self._lines.popleft())

    def stuck_at(self, wait: float = STACK_WAIT_S) -> Stuck | None:
        """Where the child's import is now, for one that said it is importing and then
        nothing; None if its stacks did not come within ``wait`` seconds or show no
        import. They are read until the importing thread's stack is whole: it comes
        last, after the other threads', in many small writes (read until a tenth of a
        second went by without one, a child starved of CPU halfway through gave the
        others' alone, and no place was named)."""
        with contextlib.suppress(ProcessLookupError):
            os.kill(self.process.pid, _STACK_SIGNAL)
        dump, deadline = b"", time.monotonic() + wait
        with selectors.DefaultSelector() as selector:
            selector.register(self._stacks, selectors.EVENT_READ)
            while (left := deadline - time.monotonic()) > 0 and selector.select(left):
                chunk = os.read(self._stacks, 65536)
                if not chunk:
                    break
                dump += chunk
                if _stuck_at(dump.decode(errors="replace"), whole=True) is not None:
                    break
        return _stuck_at(dump.decode(errors="replace"))

    @property
    def output(self) -> str:
        """The last lines it wrote on its stderr (``keep_output``), stripped."""
        return self._output.decode(errors="replace").strip()

    @property
    def returncode(self) -> int:
        """How it exited (``end`` first): its status, or minus the signal that killed it."""
        code = self.process.returncode
        assert code is not None, "end() the child first"
        return code

    def end(self, wait: float) -> None:
        """Give the child ``wait`` seconds to exit, then kill its process group (the
        child, if it still runs, and whatever the user's code started) and reap it.
        Killed before it is reaped, its group id is still its own."""
        with selectors.DefaultSelector() as selector:
            selector.register(self._pidfd, selectors.EVENT_READ)
            selector.select(wait)
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait()
        os.close(self._pidfd)
        os.close(self._stacks)
        self._selector.close()
        for pipe in (self.process.stdin, self.process.stdout, self.process.stderr):
            if pipe is not None:
                pipe.close()


def hung(wait: float, longer: str, where: Stuck | str | None = None) -> str:
    """How an import that gave no sign of life for ``wait`` seconds went, in words;
    ``longer``: how to give it more time ("give a longer --import-timeout"); ``where``:
    where it was then (``Child.stuck_at``)."""
    return (f"did not finish within {wait:.3g} s{where or ''}: it loops or waits (for "
            f"input, a lock, the network) as it is imported; make it return, or {longer}")


@dataclass(frozen=True)
class Stuck:
    """Where an import that does not finish is: the innermost frame of the thread that
    imports, and the module file whose top level led there (the file that loops or
    waits as it is imported: a class's module, or a file it imports)."""

    file: str
    line: int
    function: str
    module_file: str | None = None
    module_line: int = 0

    def __str__(self) -> str:
        """``", stuck at FILE, line N"``, and the module file's line that called it."""
        where = f", stuck at {self.file}, line {self.line}"
        if self.module_file is not None and (self.module_file, self.module_line) != (
                self.file, self.line):
            where += (f" (in {self.function}), called from {self.module_file}, line "
                      f"{self.module_line}")
        return where


def _stuck_at(dump: str, whole: bool = False) -> Stuck | None:
    """Where the thread that imports is, in ``faulthandler``'s stacks (each thread's
    frames innermost first, threads apart by a blank line); None if no thread imports,
    or, ``whole``, if its stack has not come down to the child's own code yet."""
    for stack in dump.split("\n\n"):
        frames = _FRAME.findall(stack)
        if not any(file.startswith("<frozen importlib") for file, _, _ in frames):
            continue
        if whole and frames[-1][0::2] != ("<string>", "<module>"):    # (``_BOOT``)
            return None
        file, line, function = frames[0]
        top = next(((f, int(n)) for f, n, name in frames
                    if name == "<module>" and not f.startswith("<frozen ")), (None, 0))
        return Stuck(file, int(line), function, *top)
    return None


def exit_status(code: int, importing: bool) -> str:
    """How a child that gave no answer ended, in words; with what to do, when it was
    importing a module."""
    if code >= 0:
        return f"exited with status {code}" + (
            ": it ends the process as it is imported (os._exit()?); a module must not exit "
            "when imported (put that code under if __name__ == '__main__':)"
            if importing else "")
    name = signal.Signals(-code).name if -code in signal.valid_signals() else str(-code)
    return f"was killed by signal {name}" + (
        " (a crash in native code it runs as it is imported?): fix or remove that code"
        if importing and name in _CRASHES else "")


# -- the child's side --------------------------------------------------------------------
def answering() -> Callable[..., None]:
    """In the child, first: set its files up (see the module's docstring) and give the
    function that sends its parent one message (keyword arguments, as JSON)."""
    stacks = os.environ.pop(_STACK_FD, None)
    if stacks is not None:               # (where an import is stuck: see ``stuck_at``)
        faulthandler.register(_STACK_SIGNAL, file=int(stacks), all_threads=True)
    answers = os.dup(1)                  # ours alone: what the user's code prints
    os.dup2(2, 1)                        # goes to stderr, never among the answers
    parent = os.dup(0)                   # EOF when the parent is gone
    devnull = os.open(os.devnull, os.O_RDONLY)
    os.dup2(devnull, 0)                  # input() at import ends at once
    os.close(devnull)
    sys.stdout.reconfigure(line_buffering=True)   # (printed before a crash is not lost)
    threading.Thread(target=_exit_with, args=(parent,), daemon=True,
                     name="pb3a-parent-watch").start()

    def send(**message: Any) -> None:
        data = (json.dumps(message) + "\n").encode()
        while data:
            data = data[os.write(answers, data):]

    return send


def import_each(request: dict[str, Any]) -> NoReturn:
    """In the child: import ``request["modules"]`` one after another (from the module
    servers ``request["servers"]`` too), saying ``importing`` and ``imported`` around
    each, then ``done``; then exit at once. A module that raises is imported all the same:
    the parent's own import says why, in its words. Run as ``IMPORT_EACH``, never by a
    user."""
    send = answering()
    from pb3a.processes import mark_as

    mark_as("a process that tries imports")    # (a launch as it is imported: refused)
    if request["servers"]:
        from pb3a.loading.served import use_module_servers

        with contextlib.suppress(Exception):    # (then the import says what is missing)
            use_module_servers(request["servers"])
    send(ready=True)
    for module in request["modules"]:
        send(importing=module)
        with contextlib.suppress(BaseException):
            importlib.import_module(module)
        send(imported=module)
    sys.stdout.flush()
    sys.stderr.flush()
    send(done=True)
    os._exit(0)


IMPORT_EACH = "pb3a.loading.import_child:import_each"


def _exit_with(parent: int) -> None:
    """End this child when its parent's end of ``parent`` closes (the parent died)."""
    with contextlib.suppress(OSError):
        while os.read(parent, 1):
            pass
    os._exit(1)
