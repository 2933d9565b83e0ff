"""``FixedRate``: when the steps of a module with ``fixed_rate`` are due.

By default a module sleeps its period after each step, so a step that takes time
slows its rate (0.02 s and 5 ms of work: 40 Hz, not 50). With a fixed rate, as an
OROCOS periodic activity or a ROS 2 timer keeps it, step k is due at t0 + k * period,
t0 when the schedule's first step began: the work does not drift the rate.

A step that begins late (its due time passed: the last step overran, the CPU was
busy) begins at once; one late by a whole period or more has missed slots. Those are
skipped, never made up by a burst of steps, and counted (``overruns``: each whole
period a step began late by); the schedule starts again from that step (the next due
a period after it began), not at its old phase: a controller's next step comes a whole
period after this one. The schedule also starts again, counting nothing, from the
step after a period is set anew (the next due a new period after the last step
began) and from the step after the runtime held the module (a pause to move or
rewire it, a swap): the time it held it is no overrun of the module's.
"""

from __future__ import annotations


class FixedRate:
    """The due time of a module's next step, and the slots it skipped so far (the
    caller serializes the calls: the actor's ``_sched_lock``)."""

    def __init__(self) -> None:
        self.overruns = 0               # slots skipped: whole periods steps began late by
        self._began: float | None = None    # when the last step began (monotonic)
        self._slot: float | None = None     # the time that step was due at
        self._fresh = True              # the next step starts the schedule anew

    def due(self, period: float) -> float | None:
        """When the next step is due at ``period`` (None: at once, none has begun)."""
        if self._began is None:
            return None
        if self._fresh or self._slot is None:
            return self._began + period
        return self._slot + period

    def begun(self, now: float, period: float) -> None:
        """A step begins at ``now`` (``time.monotonic()``), at ``period``: note its
        slot, counting the whole periods it began late by, if any (those slots are
        skipped, and the schedule starts again from it); one that starts the schedule
        anew counts nothing."""
        due = None if self._fresh else self.due(period)
        self._began, self._fresh, self._slot = now, False, now
        if due is None or period <= 0:              # (0: as fast as it can)
            return
        if now - due >= period:
            self.overruns += int((now - due) // period)
        else:
            self._slot = due

    def restart(self) -> None:
        """Start the schedule again from the next step (a period set anew, a pause
        over): it is due a period after the last step began, and counts nothing."""
        self._fresh = True
