"""Live migration: a module moves to another node with its state and its unconsumed
inputs, and no value on any of its links is lost, duplicated or reordered.

The hand-over, under the global configuration lock:

1. Prepare first: room for the module's snapshot at the source (a segment the size
   of its state now), and a worker on the destination node (the workers of a macro's
   modules boot side by side) with the module's code
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
   set what the caller asked to change on arrival (``state``: a driver re-pointed at
   the robot it drives from there, say), re-attach every link (a link becomes shared
   memory or ZeroMQ by where its ends now are; a remote reader follows the new sender
   incarnation and refuses the old one), start the module (``setup``), then let the
   writers go on. Only then are the segment and the worker the module left freed.

``pause_s`` is the time from step 2 (the module held: its call in progress, if any,
has ended) to its start at the destination; ``phases`` says where it went, and
``wait_s`` how long step 2 waited for the calls in progress before. If step 5 fails
(the destination worker died, say), the module is put back on its source node the
same way, with what was captured, and the migration raises ``RuntimeFailure``: the
module is never lost. If step 2, 3 or 4 fails (a module's call outlasts the pause's
wait, say), the links unwired are wired again and the modules paused go on where they
ran.

A macro's modules move together: each step is taken for all of them before the
next, so they pause once, and a link between two of them is unwired where both ran
and wired again where both run, never across nodes on the way.

The caller's ``timeout`` bounds every step (``_Clock``, ``pb3a.deadline``): before the
capture a step out of time undoes the move as any failure there; once captured, the
landing gets at least ``LANDING_FLOOR_S``; the start at the destination is the point
of no return, and a ``setup`` still running when the time is up is left to finish
there (``MovedLate``). Undoing keeps its own deadlines, not the caller's, on a
thread of its own (``_Undoing``): the call waits for it until its time is up, or
``UNDO_GRACE_S`` if that is later (a move that failed as its time ran out); an undo
still running then (a worker still busy in a ``teardown`` that overran) goes on,
every later change waiting for it (``ConfigurationLock.carry_on``), and the error says
so. A landing's undo drops the modules at the destination first,
waiting for its workers ``DROP_S`` at most: they never started there, and a worker
that does not answer (frozen) is stopped without its answer.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

from pb3a.deadline import bounding, lifted
from pb3a.errors import RuntimeFailure, RuntimeTimeout

log = logging.getLogger("pb3a.launcher")

# Once captured, a module runs nowhere until it lands: its landing (restore, rewire,
# start) gets at least this long, however little is left of the call's timeout, since
# giving it up means putting the module back, which takes as long.
LANDING_FLOOR_S = 0.5
# A step's RuntimeTimeout this close to the end of its time is the call's timeout
# running out (a worker gives up its answer's margin before: ``deadline.before_answer``).
RAN_OUT_SLACK_S = 0.3
# How long a failed move waits for its undo at least, when its time (its timeout, or the
# landing's floor) is up or nearly: one that takes longer (a worker still busy) goes on
# after the call returns. Before that, it waits until its time is up.
UNDO_GRACE_S = 0.25
# How long undoing a landing waits for the destination to drop the modules that did not
# land (never started there): a worker that does not answer is stopped without it.
DROP_S = 0.1

if TYPE_CHECKING:
    from collections.abc import Callable, Iterator

    from pb3a.config.plan import FlatLink, FlatModule
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
    prepare_s: float = 0.0    # before the pause: segments, destination workers, instances
    wait_s: float = 0.0       # then the writers' and the module's calls in progress waited
                              # out (a long step's rest), before the pause
    moved: bool = True        # False: it ran on the destination already, and nothing moved
                              # (no event; state on arrival set where it runs)


class MovedLate(RuntimeTimeout):
    """The call's timeout ran out while the moved modules' ``setup`` ran at the
    destination: past the point of no return, so they stay there, and run once it
    returns. ``reports``: the move's, as if it had ended."""

    def __init__(self, message: str, reports: list[MigrationReport]) -> None:
        super().__init__(message)
        self.reports = reports


def migrate(launcher: Launcher, names: list[str], node: str,
            state: dict[str, dict[str, Any]] | None = None,
            timeout: float = 30.0) -> list[MigrationReport]:
    """Move modules ``names`` to ``node`` together, one report each (the caller holds
    the configuration lock). A macro's modules move as one: prepared together, paused
    together, and its inner links never cross nodes on the way. ``state`` (module name
    -> fields) is set as each arrives, after its state is restored and before it
    starts; a move that fails puts the modules back without it.

    ``timeout`` bounds every step: each gets what is left of it (``_Clock``). A step
    that runs out fails the move with ``RuntimeTimeout`` naming it; before the capture
    the modules are put back where they ran, after it they land all the same (at least
    ``LANDING_FLOOR_S``), or are put back if they cannot; undoing keeps its own
    deadlines. A ``setup`` at the destination still running when the time is up is
    left to finish there: ``MovedLate``."""
    clock = _Clock(f"migrate {', '.join(names)} to {node}", timeout)
    state = state or {}
    strangers = sorted(set(state) - set(names))
    if strangers:
        raise ValueError(f"state on arrival for {', '.join(map(repr, strangers))}, which "
                         f"{'does' if len(strangers) == 1 else 'do'} not move; what moves: "
                         f"{', '.join(names)}")
    moving = [name for name in dict.fromkeys(names) if launcher.specs[name].node != node]
    reports = {name: MigrationReport(name, node, node, 0.0, 0, 0, moved=False)
               for name in names}
    if moving:
        late = _move(launcher, moving, node, state, reports, clock)
        if late is not None:
            raise MovedLate(clock.named(
                f"starting {late} at node {node}",
                f"{late}'s setup had not returned; the move is done otherwise (state, "
                f"inputs and links at node {node}), and {late} runs there once its setup "
                "returns (a setup that raises then, or outlasts its own deadline, fails "
                "it there: module_failed)"), list(reports.values()))
    for name in set(state) - set(moving):           # there already: set once all are
        with clock.step(f"setting the state of {name} at node {node}"):
            launcher.call(name, "set_state", state=state[name])
    return list(reports.values())


def _move(launcher: Launcher, moving: list[str], node: str, state: dict[str, dict[str, Any]],
          reports: dict[str, MigrationReport], clock: _Clock) -> str | None:
    """``migrate`` for the modules not on ``node`` yet, filling in their ``reports``;
    the modules whose ``setup`` was left to finish at ``node``, if any (in words)."""
    homes = {name: launcher.specs[name] for name in moving}
    group = set(moving)
    links = [link for link in launcher.links.values() if group & {link.src, link.dst}]
    writers = sorted({link.src for link in links if link.dst in group} - group)
    arriving = launcher.nodes[node]
    with contextlib.ExitStack() as afterwards:      # (called once the writers go on)
        # 1. room for the snapshots and the destination, ready before anything pauses
        preparing = time.perf_counter()
        try:
            with clock.step(f"preparing node {node} (a worker, the code loaded)"):
                segments = _prepare(launcher, homes, links, node, afterwards, clock.timeout)
        except (RuntimeTimeout, RuntimeFailure) as exc:   # (what was prepared is gone again)
            _unmoved(exc, homes)
            raise
        prepare_s = time.perf_counter() - preparing
        waiting = time.perf_counter()       # (until the first module is held)
        try:            # (let go with the segments, afterwards, as the block ends)
            with clock.step(f"pausing the writers {', '.join(writers)}"):
                afterwards.enter_context(launcher.paused(writers, clock.timeout))
        except BaseException as exc:    # a writer that would not pause: nothing moved,
            for name in moving:         # and the prepared instances and their workers go
                _quietly(arriving.remove_module, name)
            _quietly(arriving.release_workers,
                     [replace(home, node=node) for home in homes.values()])
            _unmoved(exc, homes)
            raise
        # 2. and 3. pause the modules, unwire them; 4. the fence: retired at the source
        laps, snapshots = _Laps(), {}
        paused: list[str] = []                  # what a failure here must undo
        unwiring = unwired = False
        try:
            for name in moving:
                with clock.step(f"pausing {name} at node {homes[name].node}"):
                    # (waits out a step in progress, as long as the move may take:
                    # a fixed 5 s refused to move a planner whose step runs longer)
                    if not launcher.nodes[homes[name].node].pause(name, clock.timeout):
                        raise RuntimeFailure(    # (before anything is unwired)
                            f"migration of {name} to node {node}: its worker is not "
                            "running (it died, and comes back by its restart policy); "
                            "nothing moved")
                if not paused:          # its pause begins (``pause_s``) as its call ends
                    laps.begin()
                paused.append(name)
            unwiring = True
            with clock.step("unwiring the links (taking in what is on the way)"):
                launcher.detach(*links)
            unwired = True
            laps.mark("unwire")
            for name in moving:
                leaving = launcher.nodes[homes[name].node]
                with clock.step(f"capturing {name} at node {homes[name].node}"):
                    carry = leaving.memory_domain() != arriving.memory_domain()
                    snapshots[name] = leaving.retire(name, segments[name], carry)
            laps.mark("retire")
        except BaseException as exc:
            def undo() -> None:
                for name in moving:
                    _quietly(arriving.remove_module, name)
                if unwiring and not unwired:         # (a part may be wired still)
                    for link in links:
                        _quietly(launcher.detach, link)
                _put_back(launcher, homes, snapshots, links, paused, rewire=unwiring)
            if not _Undoing(launcher, clock, undo, afterwards).ended():
                _unmoved_yet(exc, homes)
            _unmoved(exc, homes)
            raise
        for name in moving:
            launcher.specs[name] = replace(homes[name], node=node)
            launcher.arriving[name] = node      # (until it runs there, or is put back)
        # 5. restored, re-wired, started (or, failing that, the same back home)
        landed: list[str] = []
        late: str | None = None
        clock.at_least(LANDING_FLOOR_S)
        try:
            restore_s, late = _land(launcher, snapshots, links, laps, state, landed, clock)
        except (RuntimeFailure, RuntimeTimeout) as exc:
            lost = sorted({home.node for home in homes.values() if home.node in
                           launcher.remotes and launcher.remotes[home.node].lost})
            if not lost:
                _undo(launcher, homes, snapshots, links, moving, node, exc, clock,
                      afterwards)
            with lifted():                      # (it keeps its own deadlines)
                # no way back (put back there, they went with it, captured state and
                # all): they land here all the same, with the links that can be wired
                restore_s = _stay(launcher, snapshots, links, laps, state, landed, lost,
                                  exc)
    for name in moving:
        launcher.arriving.pop(name, None)
    lap = laps.seconds
    capture_s = sum(snapshot.capture_s for snapshot in snapshots.values())
    phases = MigrationPhases(
        lap["unwire"], capture_s, lap["retire"] - capture_s + lap["land"] - restore_s,
        restore_s, lap["rewire"], lap["start"])
    wait_s = laps.began - waiting
    for name in moving:
        reports[name] = MigrationReport(
            name, homes[name].node, node, sum(lap.values()), snapshots[name].nbytes,
            sum(name in (link.src, link.dst) for link in links), phases, prepare_s, wait_s)
    return late


def _undo(launcher: Launcher, homes: dict[str, FlatModule], snapshots: dict[str, Snapshot],
          links: list[FlatLink], moving: list[str], node: str, exc: Exception,
          clock: _Clock, afterwards: contextlib.ExitStack) -> None:
    """A landing at ``node`` that failed (``exc``): the modules back where they ran,
    and the error saying so (or that it goes on after the call: ``_Undoing``, which
    then lets go of the writers and the segments ``afterwards``)."""
    one = len(moving) == 1
    sources = ", ".join(sorted({home.node for home in homes.values()}))

    def undo() -> None:
        # dropped at the destination first, not waiting long for its workers: the
        # modules never started there, and one frozen there held up every request to it
        # (a link's, the removal's: 10 s each)
        arriving = launcher.nodes[node]
        with bounding(DROP_S):
            for name in moving:
                with contextlib.suppress(RuntimeFailure, RuntimeTimeout):
                    arriving.remove_module(name)
        for link in links:
            _quietly(launcher.detach, link)
        try:
            _put_back(launcher, homes, snapshots, links, moving, rewire=True)
        except (RuntimeFailure, RuntimeTimeout) as back:
            raise RuntimeFailure(
                f"migration of {', '.join(moving)} to node {node} failed ({exc}), and "
                f"putting {'it' if one else 'them'} back on node {sources} "
                f"failed too ({back})") from back
    if not _Undoing(launcher, clock, undo, afterwards).ended():
        error = RuntimeTimeout(
            f"migration of {', '.join(moving)} to node {node} failed ({exc}); "
            f"{'it is' if one else 'they are'} being put back on node {sources} with "
            f"{'its' if one else 'their'} state, which goes on after this call (a worker "
            "did not answer in time), and a later change waits for it")
        error.ran_out = True                    # type: ignore[attr-defined]
        raise error from exc
    what = (f"{moving[0]} to node {node} failed ({exc}); it runs on node "
            f"{sources} again, with its state" if one else
            f"{', '.join(moving)} to node {node} failed ({exc}); they run on "
            f"node {sources} again, with their state")
    # (the call's time ran out: said as such, as before the capture)
    failure = RuntimeTimeout if getattr(exc, "ran_out", False) else RuntimeFailure
    raise failure(f"migration of {what}") from exc


def _stay(launcher: Launcher, snapshots: dict[str, Snapshot], links: list[FlatLink],
          laps: _Laps, arriving: dict[str, dict[str, Any]] | None, landed: list[str],
          lost: list[str], exc: Exception) -> float:
    """A landing that failed (``exc``) as the modules' source node was ``lost``: they land
    all the same (``arriving`` set on them), with every link that can be wired (those to
    the lost node's modules are its failover's, which waits for this move); the seconds
    the workers took to restore."""
    log.warning("node %s was lost as modules moved from it landed (%s): they land all "
                "the same", ", ".join(lost), exc)
    restore_s = 0.0
    for name, snapshot in snapshots.items():
        if name not in landed:
            restore_s += _land_one(launcher, name, snapshot, arriving)
    laps.mark("land")
    kept = [link for link in links if not set(lost) & {
        launcher.specs[link.src].node, launcher.specs[link.dst].node}]
    for link in kept:
        _quietly(launcher.detach, link)
    launcher.reattach(kept, f"after node {', '.join(lost)} was lost during a move")
    laps.mark("rewire")
    _start_where(launcher, {name: launcher.specs[name].node for name in snapshots},
                 failing=True)
    laps.mark("start")
    return restore_s


def _prepare(launcher: Launcher, homes: dict[str, FlatModule], links: list[FlatLink],
             node: str, afterwards: contextlib.ExitStack, timeout: float) -> dict[str, str]:
    """Step 1 for each module: a segment at its source, released ``afterwards`` (its
    size measured if no call is in progress, not waiting for one: the pause does), and
    the module instantiated at ``node``, publishing already if its outputs will cross
    nodes from there; the segments. What was added is removed again if one fails."""
    arriving, segments, added = launcher.nodes[node], {}, []
    coming = [replace(home, node=node) for home in homes.values()]
    arriving.spawn_workers(coming)
    try:
        for name, home in homes.items():
            leaving = launcher.nodes[home.node]
            segments[name] = leaving.reserve(name, timeout)
            afterwards.callback(_quietly, leaving.release, segments[name])
            arriving.add_module(replace(home, node=node), state={})
            added.append(name)
            if any(link.src == name and link.dst not in homes
                   and launcher.specs[link.dst].node != node for link in links):
                arriving.ready_to_publish(name)     # (its sockets take milliseconds)
    except BaseException:
        for name in added:
            _quietly(arriving.remove_module, name)
        _quietly(arriving.release_workers, coming)   # (those booted for the rest)
        raise
    return segments


def _put_back(launcher: Launcher, homes: dict[str, FlatModule],
              snapshots: dict[str, Snapshot], links: list[FlatLink], paused: list[str],
              rewire: bool) -> None:
    """A failed move undone: what was captured restored where it ran before, the links
    wired again there (with ``rewire``: they were, or may have been, unwired), then the
    modules ``paused`` and never captured let go (after their links are back, so what
    they write goes somewhere). A link that cannot be wired again (its other end on a
    node lost meanwhile) is a failure of the system, logged; it keeps none of the rest
    from being wired, started and let go. A module that cannot be restored or started
    there is failed (``module_failed``), the others started all the same, and it
    raises, naming why."""
    for name in homes:
        launcher.specs[name] = homes[name]
        launcher.arriving.pop(name, None)
    for name in snapshots:
        launcher.nodes[homes[name].node].add_module(homes[name], state={})
    try:
        if rewire:
            unrestored: dict[str, str] = {}
            for name, snapshot in snapshots.items():
                try:
                    launcher.node_of(name).land(name, snapshot)
                except (RuntimeFailure, RuntimeTimeout) as exc:
                    unrestored[name] = str(exc)
            launcher.reattach(links, "after a failed move")
            try:
                # (one that cannot start is failed, and said so)
                _start_where(launcher, {name: homes[name].node for name in snapshots
                                        if name not in unrestored}, failing=True)
            finally:
                # failed once its links are back, so that what feeds it is unhooked (it
                # was left "starting" for good, unsaid, and the modules after it too)
                for name, error in unrestored.items():
                    _quietly(launcher.node_of(name).fail_module, name,
                             f"its move failed, and its state could not be put back "
                             f"where it ran: {error}")
            if unrestored:
                raise RuntimeFailure("; ".join(dict.fromkeys(unrestored.values())))
    finally:
        for name in paused:
            if name not in snapshots:
                _quietly(launcher.nodes[homes[name].node].resume, name)


def _land_one(launcher: Launcher, name: str, snapshot: Snapshot,
              arriving: dict[str, dict[str, Any]] | None) -> float:
    """Restore module ``name`` from ``snapshot`` in its (new) worker and set what
    ``arriving`` gives it; the seconds that took."""
    restore_s = launcher.node_of(name).land(name, snapshot)
    if arriving and name in arriving:
        started = time.perf_counter()
        launcher.call(name, "set_state", state=arriving[name])
        restore_s += time.perf_counter() - started
    return restore_s


def _land(launcher: Launcher, snapshots: dict[str, Snapshot], links: list[FlatLink],
          laps: _Laps, arriving: dict[str, dict[str, Any]], landed: list[str],
          clock: _Clock) -> tuple[float, str | None]:
    """Restore what was captured in the modules' (new) workers and set ``arriving`` on
    them (each noted in ``landed`` then), re-wire them, start them, each step within
    what is left of the ``clock``; the seconds the workers took to restore, and the
    modules whose ``setup`` was left to finish when the time ran out (in words), if
    any: the point of no return is their start's request, which their worker took."""
    restore_s = 0.0
    nodes = {name: launcher.specs[name].node for name in snapshots}
    for name, snapshot in snapshots.items():
        with clock.step(f"restoring {name} at node {nodes[name]}"):
            restore_s += _land_one(launcher, name, snapshot, arriving)
        landed.append(name)
    laps.mark("land")
    with clock.step("wiring the links where the modules run now"):
        launcher.attach(*links)
    laps.mark("rewire")
    late = None
    try:
        with clock.step(f"starting {', '.join(snapshots)}"):
            _start_where(launcher, nodes, leave_late=True)
    except RuntimeTimeout as exc:
        if not getattr(exc, "late", None):
            raise
        late = ", ".join(exc.late)              # type: ignore[attr-defined]
    laps.mark("start")
    return restore_s, late


def _start_where(launcher: Launcher, nodes: dict[str, str], failing: bool = False,
                 leave_late: bool = False) -> None:
    """Start each module on its node (module -> node), one request per node, in order;
    ``failing``: one that cannot start is failed, and said so; ``leave_late``: one whose
    ``setup`` outlasts the call's deadline is left to finish (``start_modules``)."""
    starting: dict[str, list[str]] = {}
    for name, node in nodes.items():
        starting.setdefault(node, []).append(name)
    for node, names in starting.items():
        launcher.nodes[node].start_modules(names, failing, leave_late)


def _unmoved(exc: BaseException | None, homes: dict[str, FlatModule]) -> None:
    """If the call's time ran out (``exc``) before the capture, or a node failed it
    then, or a wait of its own ran out (a ``RuntimeTimeout`` before the call's time was
    up): the error saying so, and that the modules run where they did, once that is
    true (undone). (A destination lost as it was prepared said only "node b is lost",
    not where the module was; a lossless link's values still in flight after 10 s of a
    move's 25, only that.)"""
    ran_out = isinstance(exc, RuntimeTimeout) and getattr(exc, "ran_out", False)
    if not ran_out and (type(exc) not in (RuntimeFailure, RuntimeTimeout)
                        or "nothing moved" in str(exc)):
        return
    where = ", ".join(sorted({home.node for home in homes.values()}))
    said = (f"{exc}; nothing moved: {', '.join(homes)} "
            f"{'runs' if len(homes) == 1 else 'run'} on node {where} as before")
    timed_out = ran_out or type(exc) is RuntimeTimeout
    error = (RuntimeTimeout if timed_out else RuntimeFailure)(said)
    if ran_out:
        error.ran_out = True                    # type: ignore[attr-defined]
    raise error from exc


def _unmoved_yet(exc: BaseException, homes: dict[str, FlatModule]) -> None:
    """A move that failed before the capture (``exc``) whose undo goes on after the call
    (``_Undoing``): the error saying nothing moved, and that the modules run where they
    did once it ends."""
    one = len(homes) == 1
    where = ", ".join(sorted({home.node for home in homes.values()}))
    error = RuntimeTimeout(
        f"{exc}; nothing moved: {', '.join(homes)} {'stays' if one else 'stay'} on node "
        f"{where}, and {'runs' if one else 'run'} there as before once undoing the move "
        "ends: it goes on after this call (a worker did not answer in time: busy in a "
        "teardown that overran, say), and a later change waits for it")
    error.ran_out = True                        # type: ignore[attr-defined]
    raise error from exc


class _Undoing:
    """A failed move's undo, on a thread of its own that every later change waits for
    (``ConfigurationLock.carry_on``): the call waits for it until the end of its time, or
    ``UNDO_GRACE_S`` from now if that is later, and no longer, since the undo keeps its
    own deadlines (a worker busy in a ``teardown`` that overran is waited for). One that
    goes on after the call has returned then lets go of what the move holds until its
    end (``afterwards``: the writers paused, the snapshots' segments), is logged, and a
    failure of it is one of the system's (``stats().failures``)."""

    def __init__(self, launcher: Launcher, clock: _Clock, undo: Callable[[], None],
                 afterwards: contextlib.ExitStack) -> None:
        self._launcher, self._what, self._undo = launcher, clock.what, undo
        self._afterwards = afterwards
        self._lock = threading.Lock()
        self._outcome: list[BaseException | None] = []      # once it has ended
        self._left: contextlib.ExitStack | None = None       # the call returned before
        thread = launcher.lock.carry_on(f"undo {clock.what}", self._run)
        thread.join(max(clock.end - time.monotonic(), UNDO_GRACE_S))

    def ended(self) -> bool:
        """Whether the undo ended in the call's time (what it raised, raised here); if
        not, it goes on, holding what the move held until its end, and says how it
        ended once it does."""
        with self._lock:
            if not self._outcome:
                self._left = self._afterwards.pop_all()
                return False
        if self._outcome[0] is not None:
            raise self._outcome[0]
        return True

    def _run(self) -> None:
        try:
            with lifted():                          # (it keeps its own deadlines)
                self._undo()
        except BaseException as exc:
            outcome: BaseException | None = exc
        else:
            outcome = None
        with self._lock:
            self._outcome.append(outcome)
            if self._left is None:
                return
        with lifted():                              # (the writers go on: see ``_move``)
            self._left.close()
        if outcome is None:
            log.warning("%s: undone after the call returned", self._what)
        else:
            self._launcher.failures.add(f"{self._what}: undoing it after the call returned "
                                        f"failed: {outcome}")


class _Clock:
    """A move's one deadline, from its caller's ``timeout``: each step runs within what
    is left of it (``pb3a.deadline``: every request the step makes to a node or worker
    waits no longer), and a step that runs out of it is named."""

    def __init__(self, what: str, timeout: float) -> None:
        self.what, self.timeout = what, timeout
        self.end = time.monotonic() + timeout

    def at_least(self, seconds: float) -> None:
        """From now on, ``seconds`` at least, whatever the timeout leaves (a floor)."""
        self.end = max(self.end, time.monotonic() + seconds)

    def named(self, step: str, what_then: str) -> str:
        """The sentence for the call's timeout running out at ``step``."""
        return (f"{self.what}: its timeout ({self.timeout:.3g} s) ran out while {step}; "
                f"{what_then}")

    @contextlib.contextmanager
    def step(self, step: str) -> Iterator[None]:
        """Run ``step`` within what is left; ``RuntimeTimeout`` naming it if nothing is
        left, or if it runs out (its ``ran_out`` set: the caller's time, not a fault)."""
        left = self.end - time.monotonic()
        if left <= 0:
            error = RuntimeTimeout(self.named(step, "it was not begun"))
            error.ran_out = True                # type: ignore[attr-defined]
            raise error
        try:
            with bounding(left):
                yield
        except RuntimeTimeout as exc:
            if getattr(exc, "ran_out", False) or getattr(exc, "late", None) \
                    or self.end - time.monotonic() > RAN_OUT_SLACK_S:
                raise                           # (its own deadline, or said already)
            error = RuntimeTimeout(self.named(step, str(exc)))
            error.ran_out = True                # type: ignore[attr-defined]
            raise error from exc


class _Laps:
    """Seconds between successive marks, by the name of the step each ends."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.began = self._last = time.perf_counter()

    def begin(self) -> None:
        """Count from now (``time.perf_counter()``, kept in ``began``)."""
        self.began = self._last = time.perf_counter()

    def mark(self, step: str) -> None:
        now = time.perf_counter()
        self.seconds[step], self._last = now - self._last, now


def _quietly(action: Callable[..., Any], *args: Any) -> None:
    """``action``, which undoes or frees (with its own deadlines, not the call's), its
    failure ignored: its node may be gone."""
    with lifted(), contextlib.suppress(RuntimeFailure, RuntimeTimeout):
        action(*args)
