"""``LogForwarder``: a worker's log records, logged in its executor's process, where the
user's handlers and the launch's log book are."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Callable


class LogForwarder(logging.Handler):
    """Sends the worker's log records (PB3A's and its modules' own) to its executor,
    each with the module it came from (``module_of``: whose hook the logging thread
    runs, "" for none). Records from before the worker is set up (``send`` is None) are
    not sent."""

    def __init__(self, level: int, module_of: Callable[[], str]) -> None:
        super().__init__(level)
        self.send: Callable[[Any], None] | None = None
        self._module_of = module_of

    def emit(self, record: logging.LogRecord) -> None:
        if self.send is None:
            return
        try:
            message = record.getMessage()
            if record.exc_info:
                message += "\n" + logging.Formatter().formatException(record.exc_info)
            self.send((None, "log", {"level": record.levelno, "logger": record.name,
                                     "message": message, "module": self._module_of()}))
        except Exception:
            self.handleError(record)
