"""Imported by the workers' forkserver alone (in its preload list): it ignores SIGTERM.

A SIGTERM to the whole process group (``timeout``, ``kill -- -PGID``, systemd's
default ``KillMode``) reached the forkserver too, which died of it; the exit codes of
the workers it had started were lost with it (255), and the executor took each for a
crash, marking every module failed. Each worker sets its own handler (it stops, exit
0); the forkserver ends with the process that started it.
"""

import signal

signal.signal(signal.SIGTERM, signal.SIG_IGN)
