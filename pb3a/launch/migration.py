"""Live migration: a module moves to another node with its state and its unconsumed
inputs, and no value on any of its links is lost, duplicated or reordered.

The hand-over, under the global configuration lock:

1. Prepare the destination first: a worker on the destination node with the
   module's code loaded (instantiated, not started). Nothing has paused yet.
2. Pause the writers of the module's inputs, then the module itself (its lock is
   held: no step or event is running or will start).
3. Detach every link of the module. Each writer stops first; each reader then takes
   in everything still on the way (a ring is drained, a remote stream is awaited up
   to the sequence number its sender reached), so values already written end up in
   the module's input queues, or, for its outputs, at their readers.
4. Retire the module at the source: ``teardown``, then its state and every input's
   unconsumed values are captured (cloudpickle, protocol 5). From here on it runs
   nowhere: the fence. The captured bytes travel source node -> launcher ->
   destination node over authenticated control.
5. Restore them at the destination, re-attach every link (a link becomes shared
   memory or ZeroMQ by where its ends now are; a remote reader follows the new
   sender incarnation and refuses the old one), start the module (``setup``), then
   let the writers go on.

``pause_s`` is the time from step 2 (the module's pause) to its start at the
destination. If step 5 fails (the destination worker died, say), the module is put
back on its source node the same way, with what was captured, and the migration
raises ``RuntimeFailure``: the module is never lost.
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


@dataclass(frozen=True)
class MigrationReport:
    """What a migration did and what it cost."""

    module: str
    source: str               # node it left
    destination: str          # node it runs on now
    pause_s: float            # module paused at the source until started at the destination
    state_bytes: int          # captured state and unconsumed inputs, pickled
    links: int                # links re-wired


def migrate(launcher: Launcher, name: str, node: str) -> MigrationReport:
    """Move module ``name`` to ``node`` (the caller holds the configuration lock)."""
    home = launcher.specs[name]
    source = home.node
    if source == node:
        return MigrationReport(name, source, node, 0.0, 0, 0)
    links = [link for link in launcher.links.values() if name in (link.src, link.dst)]
    writers = sorted({link.src for link in links if link.dst == name and link.src != name})

    # 1. the destination, ready before anything pauses
    moved = replace(home, node=node)
    launcher.nodes[node].add_module(moved, state={})
    with launcher.paused(writers):
        # 2. and 3. pause the module, unwire it
        try:
            launcher.nodes[source].pause(name, 5.0)
            paused_at = time.monotonic()
            for link in links:
                launcher.detach(link)
            # 4. the fence: retired at the source
            captured = launcher.nodes[source].retire(name)
        except BaseException:
            launcher.nodes[node].remove_module(name)
            raise
        launcher.specs[name] = moved
        # 5. restored, re-wired, started (or, failing that, the same back home)
        try:
            _land(launcher, name, captured, links)
        except (RuntimeFailure, RuntimeTimeout) as exc:
            for link in links:
                _quietly(launcher.detach, link)
            _quietly(launcher.nodes[node].remove_module, name)
            launcher.specs[name] = home
            launcher.nodes[source].add_module(home, state={})
            _land(launcher, name, captured, links)
            raise RuntimeFailure(f"migration of {name} to node {node} failed ({exc}); it runs "
                                 f"on node {source} again, with its state") from exc
        pause = time.monotonic() - paused_at
    return MigrationReport(name, source, node, pause, len(captured), len(links))


def _land(launcher: Launcher, name: str, captured: bytes, links: list[FlatLink]) -> None:
    """Restore what was captured in the module's (new) worker, re-wire it, start it."""
    node = launcher.node_of(name)
    node.land(name, captured)
    for link in links:
        launcher.attach(link)
    node.start_modules([name])


def _quietly(action: Callable[..., Any], *args: Any) -> None:
    with contextlib.suppress(RuntimeFailure, RuntimeTimeout):   # its node may be gone
        action(*args)
