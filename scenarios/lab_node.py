"""The lab's node controllers: ``pb3a node start``, ending when the lab's process does.

The lab starts them out of the terminal's session, as another machine's daemons are,
so that a Ctrl-C at the terminal is the launcher's to act on. Out of it, one would
outlive a launcher killed outright (``kill -9 -- -PGID``, a Ctrl-C repeated through
the lab's close) and serve on with nobody to stop it. So each asks Linux for SIGTERM,
its clean stop, when the process that started it ends (``PR_SET_PDEATHSIG``), before
anything else, and ends at once if that process is gone already.

    python -m scenarios.lab_node LAUNCHER_PID node start --name r1 ...
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

PR_SET_PDEATHSIG = 1


def main(argv: list[str]) -> int:
    """Run ``pb3a argv[1:]`` as a child of process ``argv[0]`` that ends with it."""
    launcher, *command = argv
    if sys.platform == "linux":
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != int(launcher):       # it ended before the signal was asked
            return 0
    from pb3a.cli.main import main as pb3a
    return pb3a(command)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
