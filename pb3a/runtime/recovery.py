"""What an executor does when a worker process dies: the ``restart`` policies.

``never`` leaves the module failed and unhooks writers that fed it; ``fresh``
starts it again with its configured state; ``last-state`` with the state of its
last checkpoint. Links keep their rings, so a restarted reader resumes where
the dead one stopped; a restarted writer of a remote link publishes again under a
new incarnation, and the executor's ``republished`` hook has the reader's node
follow it. More than ``RESTART_INTENSITY`` restarts of one worker
in its window gives up (Erlang's MaxR/MaxT), so a crash loop cannot spin.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import cloudpickle

from pb3a.errors import RuntimeFailure, RuntimeTimeout

if TYPE_CHECKING:
    from pb3a.runtime.executor import Executor, WorkerHandle

log = logging.getLogger("pb3a.executor")

RESTART_INTENSITY = (5, 30.0)   # at most 5 restarts of one worker in 30 s (Erlang's MaxR/MaxT)


def recover(executor: Executor, handle: WorkerHandle, code: int | None) -> None:
    """Apply the restart policy of every module that ran in the dead worker."""
    limit, window = RESTART_INTENSITY
    now = time.monotonic()
    handle.restarts.append(now)
    while handle.restarts and now - handle.restarts[0] > window:
        handle.restarts.popleft()
    names = list(handle.modules)
    revive = [n for n in names if executor.modules[n].spec.restart != "never"]
    if len(handle.restarts) > limit and revive:
        executor.failures.append(
            f"worker {handle.key} died {len(handle.restarts)} times in {window:.0f} s; "
            f"gave up restarting {', '.join(revive)}")
        log.error(executor.failures[-1])
        revive = []
    for name in names:
        if name not in revive:
            _fail(executor, name, code)
    if not revive:
        return
    try:
        executor.spawn(handle)
        for name in revive:
            record = executor.modules[name]
            state = record.spec.state
            if record.spec.restart == "last-state" and record.checkpoint is not None:
                state = cloudpickle.loads(record.checkpoint)
            executor.instantiate(record, state)
            record.restarts += 1
        revived = set(revive)
        links = list(executor.links.values())
        for link in links:
            if link.dst in revived and executor.modules[link.src].status != "failed":
                executor.attach_reader(link)
        for link in links:
            if link.src in revived and executor.modules[link.dst].status != "failed":
                executor.attach_writer(link)
        for link in list(executor.inbound.values()):
            if link.dst in revived:
                executor.open_inbound(link, None)          # the ring is kept: no size needed
        for link in list(executor.outbound.values()):
            if link.src in revived:
                endpoint = executor.publish(link)
                if executor.republished is not None:
                    executor.republished(link, endpoint)
        executor.start_modules(revive)
        log.warning("restarted %s (exit code %s)", ", ".join(revive), code)
    except (RuntimeFailure, RuntimeTimeout) as exc:
        executor.failures.append(f"restart of worker {handle.key} failed: {exc}")
        log.error(executor.failures[-1])


def _fail(executor: Executor, name: str, code: int | None) -> None:
    record = executor.modules[name]
    record.status = "failed"
    executor.failures.append(f"module {name} failed (worker exit code {code}); restart=never")
    log.error(executor.failures[-1])
    # Writers into a dead reader would only fill its ring: unhook them.
    for link in list(executor.links.values()):
        src = executor.modules.get(link.src)
        if link.dst == name and src is not None and executor.workers[src.worker].alive:
            executor.unhook_writer(link)
    for link in list(executor.inbound.values()):
        if link.dst == name:
            executor.bridge.close(link.key)
