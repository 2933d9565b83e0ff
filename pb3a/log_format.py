"""How every PB3A process writes a log line: one format, for reading the logs of several
machines side by side.

``2026-12-05 09:40:29.599 ERROR   [executor lab@b] pb3a.module: module 'f' raised ...``:
the date and the time to the millisecond (lines of several machines sort by it), the
level, the process that wrote it (``launcher``, ``controller@b``, ``executor lab@b``,
``module server``, ``manager``; ``@NODE`` the node it is about), the logger, the
message. The launcher, the node controllers, their executors (which log what their
workers send them), the module server, the manager and ``pb3a logs`` all write it.

Under systemd (stderr is the journal's stream, ``JOURNAL_STREAM``) the journal stamps
each line itself, so the time is left out and the line starts with the level's
syslog priority (``<3>``), which the journal takes as the entry's priority
(``journalctl -p err`` then finds the errors).
"""

from __future__ import annotations

import logging
import os
from time import localtime, strftime
from typing import IO, Any

DATE_FORMAT = "%Y-%m-%d %H:%M:%S"          # then ".mmm"
# syslog's priorities, which the journal reads from a line's "<N>" prefix
_PRIORITIES = {"CRITICAL": 2, "ERROR": 3, "WARNING": 4, "INFO": 6, "DEBUG": 7}

_role = "launcher"          # what this process is (a program that launches, by default)
_node = ""                  # the node it is, if it is one node's


def name_process(role: str, node: str = "") -> None:
    """Say what this process is in its log lines: ``role`` (``controller``, ``executor
    lab``, ``module server``) and the node it belongs to, if any."""
    global _role, _node
    _role, _node = role, node


def process_label(node: str = "") -> str:
    """This process as its lines name it, ``@node`` the node a record is about (this
    process's own node when it is one node's)."""
    node = node or _node
    return f"{_role}@{node}" if node else _role


def line(time: float, level: str, process: str, logger: str, message: str, *,
         dated: bool = True) -> str:
    """One log line (a traceback in ``message`` goes on the lines below it)."""
    head = f"{level:<7} [{process}] {logger}: {message}"
    if not dated:
        return head
    return f"{strftime(DATE_FORMAT, localtime(time))}.{int(time % 1 * 1000):03d} {head}"


def under_journal(stream: IO[Any]) -> bool:
    """Whether ``stream`` is the systemd journal's (``JOURNAL_STREAM`` names its device
    and inode; a child that inherited the variable but writes elsewhere is not)."""
    named = os.environ.get("JOURNAL_STREAM", "")
    try:
        status = os.fstat(stream.fileno())
    except (AttributeError, OSError, ValueError):       # no file behind it
        return False
    return named == f"{status.st_dev}:{status.st_ino}"


class LineFormatter(logging.Formatter):
    """Formats a record as ``line`` does; ``journal``: for the systemd journal (no time,
    the syslog priority first)."""

    def __init__(self, journal: bool = False) -> None:
        super().__init__()
        self.journal = journal

    def format(self, record: logging.LogRecord) -> str:
        message = record.getMessage()
        if record.exc_info:
            message += "\n" + self.formatException(record.exc_info)
        if record.stack_info:
            message += "\n" + self.formatStack(record.stack_info)
        text = line(record.created, record.levelname,
                    process_label(getattr(record, "pb3a_node", "")), record.name, message,
                    dated=not self.journal)
        if self.journal:
            return f"<{_PRIORITIES.get(record.levelname, 6)}>{text}"
        return text


def log_to(stream: IO[Any], level: int = logging.WARNING) -> None:
    """Print records of ``level`` and above on ``stream`` in the one format, unless
    logging is set up already (an application's own choice stays)."""
    root = logging.getLogger()
    if root.handlers:
        return
    handler = logging.StreamHandler(stream)
    handler.setFormatter(LineFormatter(journal=under_journal(stream)))
    root.addHandler(handler)
    root.setLevel(level)
