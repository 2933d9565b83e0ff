"""Imported by the workers' forkserver alone, first in its preload list: it ignores
SIGTERM, SIGINT and SIGHUP, and marks the process as PB3A's own, so that a module it
preloads cannot launch a system there (and start another forkserver, for good).

A SIGTERM to the whole process group (``timeout``, ``kill -- -PGID``, systemd's
default ``KillMode``) reached the forkserver too, which died of it; the exit codes of
the workers it had started were lost with it (255), and the executor took each for a
crash, marking every module failed. A Ctrl-C, or the terminal closing (SIGHUP), as it
loaded its preload printed tracebacks or killed it the same way (Python ignores
SIGINT there only once the preload is done). Each worker sets its own handlers (it
stops, exit 0); the forkserver ends with the process that started it.
"""

import signal

from pb3a.processes import mark_as

mark_as("the forkserver that starts a node's workers")

for _signal in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
    signal.signal(_signal, signal.SIG_IGN)
