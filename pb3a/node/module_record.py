"""``ModuleRecord``: what a node's executor knows of one module it runs."""

from __future__ import annotations

from dataclasses import dataclass

from pb3a.config.plan import FlatModule


@dataclass
class ModuleRecord:
    """What the executor knows of one module it runs."""

    spec: FlatModule
    worker: str
    blob: bytes                       # the class, cloudpickled once
    status: str = "starting"          # starting | running | failed | stopped
    checkpoint: bytes | None = None
    checkpoints: int = 0              # checkpoints received (restart = "last-state")
    restarts: int = 0                 # restarts of its worker tried
    # paused by a change (a move, a relink): a restart of its worker waits until the
    # change lets go of it (``Lives.await_let_go``)
    held: bool = False
    # its last stop was not answered (busy in a body): it is not torn down, and the
    # executor's shutdown, asking again, has this said already
    unstopped: bool = False
