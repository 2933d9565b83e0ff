"""Planning a configuration file in a child process, so the user's code cannot harm the check.

``pb3a check`` and ``pb3a graph`` import every module class a file names, and an
import runs the module file's top level: one that loops, waits for input, exits or
crashes took the command with it (it hung, or ended silently with the file's exit
status), and what it printed was mixed into the command's output. Here a fresh
Python process plans the file instead (the same compiler, so the same problems in
the same words) and answers with the plan's figures, its DOT text or its problems.

The child tells its parent which module it is importing before each import (the
hook ``watch_imports``). When it stops answering during one (``import_timeout``),
exits, or is killed by a signal, the parent blames that import and plans the file
again in a new child that refuses to import that module, with a sentence saying
what happened; so the file's other problems are still reported, all at once. The
child reads nothing (its stdin is ``/dev/null``: ``input()`` ends at once), prints
what the user's code prints on stderr, not among the answers on stdout, and dies
with its parent. Its process group is killed when it is done, so a process started
as a module was imported does not outlive the check.
"""

from __future__ import annotations

import contextlib
import json
import os
import selectors
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, NoReturn

from pb3a.errors import ConfigError

PLANNING_TIMEOUT_S = 30.0   # longest the child may say nothing outside imports (its start)
EXIT_WAIT_S = 5.0           # how long a child that answered may take to exit
MOST_CHILDREN = 16          # modules that may hang or end a child before the check gives up

# (what the child runs: the parent's import path first, as pb3a itself may be on it only)
_CHILD = ("import json, sys; sys.path[:] = json.loads(sys.argv[1]); "
          "from pb3a.config.isolated import answer; answer(json.loads(sys.argv[2]))")


@dataclass(frozen=True)
class Checked:
    """What a valid file plans: its number of modules and links, and its DOT if asked for."""

    modules: int
    links: int
    dot: str | None = None


def check_file(file: str, *, import_timeout: float, dot: bool = False) -> Checked:
    """Plan ``file`` in a child process; raises as ``System.load(file).plan()`` would
    (``OSError``, ``ConfigError`` listing every problem, ``ClusterKeyError``), an import
    that hung (past ``import_timeout`` seconds) or ended the child being one more problem
    of the entry that names it. This process imports neither the runtime nor the file's
    classes."""
    refused: dict[str, str] = {}
    for _ in range(MOST_CHILDREN):
        ended = _Child(file, refused, import_timeout, dot).run()
        if ended.answer is not None:
            return _result(ended.answer)
        if not ended.importing:
            raise ConfigError([f"{file}: the process that checks it {ended.how}"
                               f"{' before it began' if not ended.ready else ''} (its error, "
                               "if it wrote one, is above)"])
        module, _ = ended.importing[-1]
        refused[module] = ended.how
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
    return Checked(answer["modules"], answer["links"], answer.get("dot"))


@dataclass
class _Ended:
    """How one child ended: its answer, or how it ended without one (``how``) and the
    imports it was in then, innermost last."""

    answer: dict[str, Any] | None = None
    how: str = ""
    ready: bool = False
    importing: list[tuple[str, str]] = field(default_factory=list)


class _Child:
    """One child process planning the file, watched until it answers or ends."""

    def __init__(self, file: str, refused: dict[str, str], import_timeout: float,
                 dot: bool) -> None:
        self.import_timeout = import_timeout
        request = {"file": file, "refused": refused, "dot": dot}
        self.process = subprocess.Popen(
            [sys.executable, "-c", _CHILD, json.dumps(sys.path), json.dumps(request)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, start_new_session=True)
        self.pidfd = os.pidfd_open(self.process.pid)   # (readable once it has exited)

    def run(self) -> _Ended:
        """Read the child's messages until it answers or ends; then end its process group."""
        ended, finished = _Ended(), False
        try:
            self._read(ended)
            finished = not ended.how
        finally:               # (an answer, or an end: it exits, or is exiting, by itself)
            self._end(EXIT_WAIT_S if finished else 0)
        if ended.answer is None and not ended.how:
            ended.how = _exit_status(self.process.returncode, bool(ended.importing))
        return ended

    def _read(self, ended: _Ended) -> None:
        stdout = self.process.stdout
        assert stdout is not None
        pending = b""
        with selectors.DefaultSelector() as selector:
            selector.register(stdout, selectors.EVENT_READ)
            while True:
                wait = self.import_timeout if ended.importing else PLANNING_TIMEOUT_S
                if not selector.select(wait):
                    ended.how = (f"did not finish within {wait:g} s: it loops or waits (for "
                                 "input, a lock, the network) as it is imported; make it "
                                 "return, or give a longer --import-timeout"
                                 if ended.importing else f"said nothing for {wait:g} s")
                    return
                chunk = os.read(stdout.fileno(), 65536)
                if not chunk:
                    return
                *lines, pending = (pending + chunk).split(b"\n")
                for line in lines:
                    said = json.loads(line)
                    if "importing" in said:
                        ended.importing.append(tuple(said["importing"]))
                    elif "imported" in said and ended.importing:
                        ended.importing.pop()
                    elif "ready" in said:
                        ended.ready = True
                    else:
                        ended.answer = said
                        return

    def _end(self, wait: float) -> None:
        """Give the child ``wait`` seconds to exit, then kill its process group (the
        child, if it still runs, and whatever the user's code started) and reap it.
        Killed before it is reaped, its group id is still its own."""
        with selectors.DefaultSelector() as selector:
            selector.register(self.pidfd, selectors.EVENT_READ)
            selector.select(wait)
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait()
        os.close(self.pidfd)
        for pipe in (self.process.stdin, self.process.stdout):
            if pipe is not None:
                pipe.close()


def _exit_status(code: int, importing: bool) -> str:
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


_CRASHES = {"SIGSEGV", "SIGBUS", "SIGILL", "SIGFPE", "SIGABRT"}


# -- the child ------------------------------------------------------------------------
def answer(request: dict[str, Any]) -> NoReturn:
    """In the child: plan ``request["file"]`` and write the answer, one JSON line on
    stdout after the import messages; then exit at once (a thread the user's code left
    running does not hold the child up). Run by ``_CHILD``, never by a user."""
    answers = os.dup(1)                  # ours alone: what the user's code prints
    os.dup2(2, 1)                        # goes to stderr, never among the answers
    parent = os.dup(0)                   # EOF when the parent is gone
    devnull = os.open(os.devnull, os.O_RDONLY)
    os.dup2(devnull, 0)                  # input() at import ends at once
    os.close(devnull)
    sys.stdout.reconfigure(line_buffering=True)   # (printed before a crash is not lost)
    threading.Thread(target=_exit_with, args=(parent,), daemon=True,
                     name="pb3a-parent-watch").start()

    from pb3a.config.compiler import build_plan  # (the parent needs none of it)
    from pb3a.config.description import load_toml
    from pb3a.config.dot import plan_to_dot
    from pb3a.loading.references import ImportRefused, watch_imports
    from pb3a.transport.auth import ClusterKeyError

    def send(**message: Any) -> None:
        data = (json.dumps(message) + "\n").encode()
        while data:
            data = data[os.write(answers, data):]

    refused: dict[str, str] = request["refused"]

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
                                "dot": plan_to_dot(plan) if request["dot"] else None}
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


def _exit_with(parent: int) -> None:
    """End this child when its parent's end of ``parent`` closes (the parent died)."""
    with contextlib.suppress(OSError):
        while os.read(parent, 1):
            pass
    os._exit(1)
