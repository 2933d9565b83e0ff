"""Live migration: a module moves to another node with its state and its unconsumed
inputs, and no value on any of its links is lost, duplicated or reordered.

The hand-over, under the global configuration lock:

1. Prepare first: room for the module's snapshot at the source (a segment the size
   of its state now), and a worker on the destination node with the module's code
   loaded (instantiated, not started), its publishing sockets bound if its outputs
   will cross nodes from there. Nothing has paused yet.
2. Pause the writers of the module's inputs, then the module itself (its lock is
   held: no step or event is running or will start).
3. Detach every link of the module. Each writer stops first; each reader then takes
   in everything still on the way (a ring is drained, a remote stream is awaited up
   to the sequence number its sender reached), so values already written end up in
   the module's input queues, or, for its outputs, at their readers.
4. Retire the module at the source: ``teardown``, then its state and every input's
   unconsumed values are captured (cloudpickle, protocol 5) into that segment, numpy
   arrays as out-of-band buffers (``Snapshot``). From here on it runs
   nowhere: the fence. Only the segment's name goes source node -> launcher ->
   destination node; between memory domains (other machines) the snapshot's parts
   travel in it over authenticated control.
5. Restore them at the destination (the arrays map the segment's pages: no copy),
   re-attach every link (a link becomes shared memory or ZeroMQ by where its ends now
   are; a remote reader follows the new sender incarnation and refuses the old one),
   start the module (``setup``), then let the writers go on. Only then are the
   segment and the worker the module left freed.

``pause_s`` is the time from step 2 (the module's pause) to its start at the
destination; ``phases`` says where it went. If step 5 fails (the destination worker
died, say), the module is put back on its source node the same way, with what was
captured, and the migration raises ``RuntimeFailure``: the module is never lost.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

from pb3a.errors import RuntimeFailure, RuntimeTimeout

if TYPE_CHECKING:
    from collections.abc import Callable

    from pb3a.config.plan import FlatLink
    from pb3a.launch.launcher import Launcher
    from pb3a.transport.snapshot import Snapshot


@dataclass(frozen=True)
class MigrationPhases:
    """Where a migration's pause went, in seconds; they add up to ``pause_s``."""

    unwire_s: float = 0.0     # links detached, everything on the way taken in
    capture_s: float = 0.0    # at the source: teardown, state and inputs pickled into a segment
    transfer_s: float = 0.0   # the requests to both nodes, and the state between machines
    restore_s: float = 0.0    # at the destination: state and inputs taken over
    rewire_s: float = 0.0     # links attached where the module runs now
    start_s: float = 0.0      # ``setup``, and the module running again


@dataclass(frozen=True)
class MigrationReport:
    """What a migration did and what it cost."""

    module: str
    source: str               # node it left
    destination: str          # node it runs on now
    pause_s: float            # module paused at the source until started at the destination
    state_bytes: int          # captured state and unconsumed inputs, pickled
    links: int                # links re-wired
    phases: MigrationPhases = MigrationPhases()


def migrate(launcher: Launcher, name: str, node: str) -> MigrationReport:
    """Move module ``name`` to ``node`` (the caller holds the configuration lock)."""
    home = launcher.specs[name]
    source = home.node
    if source == node:
        return MigrationReport(name, source, node, 0.0, 0, 0)
    links = [link for link in launcher.links.values() if name in (link.src, link.dst)]
    writers = sorted({link.src for link in links if link.dst == name and link.src != name})
    leaving, arriving = launcher.nodes[source], launcher.nodes[node]
    carry = leaving.memory_domain() != arriving.memory_domain()
    moved = replace(home, node=node)
    with contextlib.ExitStack() as afterwards:      # (called once the writers go on)
        # 1. room for the snapshot and the destination, ready before anything pauses
        segment = leaving.reserve(name)
        afterwards.callback(_quietly, leaving.release, segment)
        arriving.add_module(moved, state={})
        if any(link.src == name and launcher.specs[link.dst].node != node for link in links):
            arriving.ready_to_publish(name)         # (its sockets take milliseconds)
        with launcher.paused(writers):
            # 2. and 3. pause the module, unwire it
            try:
                leaving.pause(name, 5.0)
                laps = _Laps()
                for link in links:
                    launcher.detach(link)
                laps.mark("unwire")
                # 4. the fence: retired at the source
                snapshot = leaving.retire(name, segment, carry)
                laps.mark("retire")
            except BaseException:
                arriving.remove_module(name)
                raise
            launcher.specs[name] = moved
            # 5. restored, re-wired, started (or, failing that, the same back home)
            try:
                restore_s = _land(launcher, name, snapshot, links, laps)
            except (RuntimeFailure, RuntimeTimeout) as exc:
                for link in links:
                    _quietly(launcher.detach, link)
                _quietly(arriving.remove_module, name)
                launcher.specs[name] = home
                leaving.add_module(home, state={})
                _land(launcher, name, snapshot, links, _Laps())
                raise RuntimeFailure(f"migration of {name} to node {node} failed ({exc}); "
                                     f"it runs on node {source} again, with its state") from exc
    lap = laps.seconds
    phases = MigrationPhases(
        lap["unwire"], snapshot.capture_s,
        lap["retire"] - snapshot.capture_s + lap["land"] - restore_s, restore_s,
        lap["rewire"], lap["start"])
    return MigrationReport(name, source, node, sum(lap.values()), snapshot.nbytes, len(links),
                           phases)


def _land(launcher: Launcher, name: str, snapshot: Snapshot, links: list[FlatLink],
          laps: _Laps) -> float:
    """Restore what was captured in the module's (new) worker, re-wire it, start it; the
    seconds the worker took to restore."""
    node = launcher.node_of(name)
    restore_s = node.land(name, snapshot)
    laps.mark("land")
    for link in links:
        launcher.attach(link)
    laps.mark("rewire")
    node.start_modules([name])
    laps.mark("start")
    return restore_s


class _Laps:
    """Seconds between successive marks, by the name of the step each ends."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._last = time.perf_counter()

    def mark(self, step: str) -> None:
        now = time.perf_counter()
        self.seconds[step], self._last = now - self._last, now


def _quietly(action: Callable[..., Any], *args: Any) -> None:
    with contextlib.suppress(RuntimeFailure, RuntimeTimeout):   # its node may be gone
        action(*args)
