"""``LogForwarder``: a worker's log records, logged in its executor's process, where the
user's handlers and the launch's log book are."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Callable


class LogForwarder(logging.Handler):
    """Sends the worker's log records (PB3A's and its modules' own) to its executor.
    Records from before the worker is set up (``send`` is None) are not sent."""

    def __init__(self, level: int) -> None:
        super().__init__(level)
        self.send: Callable[[Any], None] | None = None

    def emit(self, record: logging.LogRecord) -> None:
        if self.send is None:
            return
        try:
            message = record.getMessage()
            if record.exc_info:
                message += "\n" + logging.Formatter().formatException(record.exc_info)
            self.send((None, "log", {"level": record.levelno, "logger": record.name,
                                     "message": message}))
        except Exception:
            self.handleError(record)
