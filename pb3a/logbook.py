"""``LogBook``: the recent log of a running system, kept for ``run.logs()`` and ``pb3a logs``.

PB3A logs as a library should: to loggers under ``pb3a``, with no handler that
prints (the entry points install one, see ``pb3a.cli.log_output``). A launch also
attaches a ``LogBook`` to the root logger, a handler that only keeps the most
recent records (PB3A's, and what its workers' modules log on loggers of their own,
which each worker sends to its executor), numbered, so that another process can
read them through the launcher; each remote node keeps its own and the launcher
merges them in, marked with the node's name.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from dataclasses import dataclass

from pb3a.errors import bounded_wait
from pb3a.log_format import line, process_label


@dataclass(frozen=True)
class LogEntry:
    """One log record, as plain data."""

    seq: int
    time: float                 # wall clock, seconds since the epoch
    level: str                  # "WARNING", "ERROR" ...
    logger: str
    message: str                # with the traceback, if the record had one
    node: str = ""              # where it was logged ("": the launcher's process)
    module: str = ""            # the PB3A module it is about, if any
    process: str = ""           # the process that logged it, as its log lines name it

    def line(self) -> str:
        """The entry as one line of text (and its traceback below), as the process that
        logged it printed it (``pb3a.log_format``)."""
        # (an entry of a node of an older version names no process: its node's)
        process = self.process or (f"node@{self.node}" if self.node else "launcher")
        return line(self.time, self.level, process, self.logger, self.message)


class LogBook(logging.Handler):
    """Keeps the last ``keep`` records it is given; thread-safe."""

    def __init__(self, keep: int = 5000, level: int = logging.NOTSET) -> None:
        super().__init__(level)
        self._entries: deque[LogEntry] = deque(maxlen=keep)
        self._seq = 0
        self._ended = False
        self._cond = threading.Condition()

    def emit(self, record: logging.LogRecord) -> None:
        # The book must not change what the user sees: with no other handler on the
        # record's way up, Python would have printed it through its last resort.
        if logging.lastResort is not None and record.levelno >= logging.lastResort.level \
                and not _handled_elsewhere(record):
            logging.lastResort.handle(record)
        try:
            message = record.getMessage()
            if record.exc_info:
                message += "\n" + logging.Formatter().formatException(record.exc_info)
            node = getattr(record, "pb3a_node", "")
            self.add(record.created, record.levelname, record.name, message, node,
                     getattr(record, "pb3a_module", ""), process_label(node))
        except Exception:
            self.handleError(record)

    def add(self, time: float, level: str, logger: str, message: str, node: str = "",
            module: str = "", process: str = "") -> LogEntry:
        """Keep one entry (a record of this process, or one a remote node kept)."""
        with self._cond:
            self._seq += 1
            entry = LogEntry(self._seq, time, level, logger, message, node, module, process)
            self._entries.append(entry)
            self._cond.notify_all()
        return entry

    def since(self, seq: int = 0, timeout: float = 0.0, module: str | None = None,
              ) -> list[LogEntry]:
        """The entries after ``seq`` (about ``module`` only, if given), waiting up to
        ``timeout`` for one when there is none yet (None is refused: ``TypeError``)."""
        timeout = bounded_wait(timeout, "log entries since")
        looked = seq            # the newest entry looked at: those up to it did not match

        def found() -> list[LogEntry]:
            # Only the entries added since the last look, from the newest back (a
            # follower of a quiet module rescanned all 5,000 at each of a flood's
            # entries, under the lock every record takes: 8 of them took 60 % of a core).
            nonlocal looked
            new = []
            for entry in reversed(self._entries):
                if entry.seq <= looked:
                    break
                new.append(entry)
            if new:
                looked = new[0].seq
            return [entry for entry in reversed(new)
                    if module is None or entry.module == module]

        with self._cond:
            kept: list[LogEntry] = []
            self._cond.wait_for(lambda: kept.extend(found()) or kept or self._ended, timeout)
            return kept

    def end(self) -> None:
        """The system stopped: every wait for an entry returns now, and later ones at
        once (an entry logged after still comes to a reader who asks)."""
        with self._cond:
            self._ended = True
            self._cond.notify_all()


def _handled_elsewhere(record: logging.LogRecord) -> bool:
    """True if a handler other than a log book sees ``record`` on its way up."""
    logger: logging.Logger | None = logging.getLogger(record.name)
    while logger is not None:
        if any(not isinstance(handler, LogBook) for handler in logger.handlers):
            return True
        logger = logger.parent if logger.propagate else None
    return False

