"""The lab's node controllers: ``pb3a node start``, ending when the lab's process does.

The lab starts them out of the terminal's session, as another machine's daemons are,
so that a Ctrl-C at the terminal is the launcher's to act on. Out of it, one would
outlive a launcher killed outright (``kill -9 -- -PGID``, a Ctrl-C repeated through
the lab's close) and serve on with nobody to stop it. So each asks Linux for a signal
when the process that started it ends (``PR_SET_PDEATHSIG``), before anything else, and
ends at once if that process is gone already. Linux sends it when the *thread* that
started it ends, though: a lab made on a thread that then ended lost its node
controllers, the launcher alive. So the signal is SIGUSR1, on which it stops (SIGTERM
to itself, its clean stop) only if its parent is another process now.

    python -m scenarios.lab_node LAUNCHER_PID node start --name r1 ...
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

PR_SET_PDEATHSIG = 1
PARENT_ENDED = signal.SIGUSR1


def main(argv: list[str]) -> int:
    """Run ``pb3a argv[1:]`` as a child of process ``argv[0]`` that ends with it."""
    launcher, *command = argv
    if sys.platform == "linux":
        parent = int(launcher)

        def parent_ended(*_: object) -> None:
            # (a thread of the launcher that ended: its child now, the launcher lives on;
            # the signal comes again when that one ends)
            if os.getppid() != parent:
                os.kill(os.getpid(), signal.SIGTERM)

        signal.signal(PARENT_ENDED, parent_ended)
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, PARENT_ENDED)
        if os.getppid() != parent:              # it ended before the signal was asked
            return 0
    from pb3a.cli.main import main as pb3a
    return pb3a(command)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
