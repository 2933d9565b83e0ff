"""``HardwareMonitor``: notices a robot's hardware failing, and says which part failed.

A one-class Gaussian naive Bayes model of normal running (notes §2.3). Every sample
of the robot's streams (command, odometry, sonar and the localization pose, 10 Hz)
gives features in three groups, each the evidence of one kind of fault:

- ``motors``: the motion commanded, passed through the robot's known response (a
  first-order lag with acceleration limits), against the motion odometry measured,
  averaged over 0.5 s. A motor power cut leaves the wheels still under a command.
- ``odometry``: how far odometry's heading drifts from the pose's per metre
  travelled, over 4 s, beside its error in scale on turns (which wanders, as the
  wheels slip) and the pose's latency. A biased odometer drifts; a sound one does not.
- ``sonar``: per transducer, the span of headings the robot has turned through
  since the transducer last heard an echo. A dead one never hears one, however the
  robot turns; a live one among walls seldom turns through half a circle without
  one. The transducers differ only in where they point, so they share one Gaussian.

Each feature is fitted by a Gaussian on normal running only. A fault of a group is
a broad Gaussian (``fault_breadth`` times wider) on one of its units (the motors, the
odometer, one transducer) with a small prior; the log-likelihood ratio of fault to
normal is the group's evidence, its posterior the failure's probability. A group
alarms when its evidence beats the high quantile of what normal running showed by
a margin, and the fault's posterior beats normal's, in k of the last n informative
windows. A failure names its failed units; one more unit failing (a transducer
after others) is one more onset.

Windows that carry no information are left out rather than scored as normal: the
motor residual while the robot is commanded to stand still (the notes' pitfall),
odometry's drift when the robot has not driven straight enough to tell it from a
scale error on turns; so a latched alarm stays latched and an idle robot never
alarms.

``FaultMonitor`` is the numpy core (``FeatureTracker``, ``NormalModel``, a k-of-n
vote); ``HardwareMonitor`` is it as a PB3A module; ``record_normal_running`` records
training features from an in-process RAVE world, driven by a ``Wanderer``.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.special import expit, logsumexp

from agents.limits import SPAN, Limit, finite, out_of_limits, refuse_own_state, whole
from pb3a import Input, InputPort, Module, Output
from pb3a.model.module import reflective
from rave.pioneer import ACCEL, ANGULAR_ACCEL, MOTOR_LAG_S
from rave.sonar import COUNT as SONARS
from rave.sonar import MAX_RANGE

if TYPE_CHECKING:
    from rave import World

log = logging.getLogger("agents.monitor")

GROUPS = ("motors", "odometry", "sonar")
# informative windows of normal running after which a group is watched, by default
READY_WINDOWS = {"motors": 150, "odometry": 300, "sonar": 300}
MOTORS, ODOMETRY, SONAR = range(len(GROUPS))
FEATURES = ("v_residual", "w_residual", "drift_per_m",
            *(f"silent_sweep_{i}" for i in range(SONARS)))
_SWEEPS = slice(3, 3 + SONARS)
# The units a group's fault may strike: the motors, the odometer, each transducer.
# Features of a unit are summed; a group's evidence averages over its units' faults.
_UNIT_COUNT = 2 + SONARS
_UNIT_OF_FEATURE = np.array([0, 0, 1, *range(2, _UNIT_COUNT)])
_UNITS_OF_GROUP = (np.array([0]), np.array([1]), np.arange(2, _UNIT_COUNT))
_GROUP_OF_FEATURE = np.array([MOTORS, MOTORS, ODOMETRY, *[SONAR] * SONARS])
# The smallest spread each feature is believed to have (m/s, rad/s, rad/m, rad; added
# to the variance fitted), so that a feature that barely varied in training does not
# make every later wobble a fault. Odometry's drift gets more: a model learnt on one
# robot watches its standby too, whose odometer has calibration errors of its own (with
# 0.002 rad/m, one quick mapping run in four saw a standby drift 0.019 rad/m, sound).
# So do the silent sweeps: their tail grows with the running seen. A minute of the lab's
# hardware robot wandering put one transducer's limit at 2.5-2.9 rad with 0.1, where
# four minutes reached 2.8 rad, sound (a standby robot's transducer, after a hand-over,
# was read as dead at 2.83 rad); 0.5 puts it at 3.4-3.8 rad, about the half circle a
# live transducer seldom turns through without an echo, and a dead one still gets there
# in 7-15 s of wandering (against 5-13 s).
_LEAST_SPREAD = np.array([0.01, 0.02, 0.005, *[0.5] * SONARS])
# Odometry's heading error per sample is fitted as scale * turn + drift * distance +
# latency * (change of turn rate) + wander * turn * time: a scale error on turns, a
# drift per metre, the pose lagging odometry, and the scale's wander over the window.
#
# The pose lags odometry (RAVE's by one physics step, 0.01 s), whose error is the lag
# times the change of the turn rate from the last reading to this one, however long
# the sample. The rate at a reading is not measured: it is the pose's mean rate over
# the sample, moved by how far the motors' known response (``FeatureTracker.expected``,
# through the commands as they came) ends from its own mean over the sample. (Taken
# as the change of the turn from the sample before, a reading late by 0.2-0.4 s,
# whose turn is twice or thrice a timely one's, made a change of turn that no lag
# gave, and the fit put it on the drift: one in ten readings late gave false
# odometry alarms, 0.026 rad/m. Taken as the change of the mean rates, the same
# readings, late, during the explorer's hard turn reversals, put the lag's error on
# the drift still: where the rate turns round within a long sample, its mean says
# little of where it ends, and false odometry alarms came at 0.031-0.038 rad/m.)
#
# The scale error on turns wanders as the wheels' slip does (RAVE's emulator: a
# random walk of 0.2% in a second): the wander is its change per second, the time
# the sample's middle less the window's. (Fitted as one scale over the window, a
# scale that wandered by 1% between a robot turning on the spot and its driving off
# in an arc, where the turn goes with the distance, was put on the drift: a sound
# odometer read 0.023 rad/m, the alarm's level, among the explorer's turn reversals.)
#
# The ridge keeps the fit solvable when a regressor is idle (rad^2, m^2, (rad/s)^2,
# (rad s)^2). The wander's, against the heading's noise per sample (0.0005 rad),
# holds its slope to about 0.1% a second, what a random walk of 0.2% in a second
# slopes by over a window of 4 s: a slope left free took the drift's information
# with it, and a biased odometer was told up to 1.3 s later.
_RIDGE = np.diag([1e-4, 1e-6, 1e-2, 0.25])


class FeatureTracker:
    """Turns each sample of a robot's streams into the monitor's ``FEATURES``, keeping
    the short history they are computed over (``state`` carries it elsewhere).

    The expected response defaults to a Pioneer's: ``lag_s`` of motor lag and the
    acceleration limits ARIA sets, as RAVE's emulator has them. Speeds are measured
    over the time between two samples by the robot's ``clock`` when given (a driver on
    a loaded machine reads late now and then, and a sample 0.2 s after the last read as
    0.1 s doubles the speed), else over the nominal ``sample_s``. A reading at the last
    one's instant is no sample (``repeats``): no time passed to measure motion over."""

    def __init__(self, sample_s: float = 0.1, lag_s: float = MOTOR_LAG_S, accel: float = ACCEL,
                 angular_accel: float = ANGULAR_ACCEL, motor_window: int = 5,
                 odometry_window: int = 40, min_speed: float = 0.05, min_turn: float = 0.15,
                 heading_noise: float = 0.0005, drift_resolution: float = 0.005) -> None:
        self.sample_s, self.lag_s = sample_s, lag_s
        self.limits = np.array([accel, angular_accel])
        self.min_speed, self.min_turn = min_speed, min_turn
        # the drift is informative when its standard error, for this noise of odometry's
        # heading against the pose's per sample (rad), is within drift_resolution (rad/m)
        self.heading_noise, self.drift_resolution = heading_noise, drift_resolution
        self.expected = np.zeros(2)          # the (v, w) the commands should have given
        self.last_odometry = np.full(3, np.nan)
        self.last_pose = np.full(3, np.nan)
        self.heading = 0.0                   # the pose's heading, unwrapped
        # per transducer: lowest and highest heading since its last echo
        self.quiet = np.zeros((2, SONARS))
        # per sample: v and w residuals, expected |v| and |w|
        self.motions = np.zeros((motor_window, 4))
        # per sample: odometry's heading error; the pose's turn, distance (unsigned) and
        # change of turn rate (rad/s) from the last reading (see _RIDGE)
        self.travel = np.zeros((odometry_window, 4))
        self.last_rate = 0.0                 # the pose's turn rate at the last reading
        # per sample (as travel's rows): its middle in the robot's time since the first
        self.times = np.zeros(odometry_window)
        self.elapsed = 0.0                   # the robot's time since the first sample
        self.last_clock = math.nan           # the robot's time of the last sample
        self.samples = 0

    _STATE = ("expected", "last_odometry", "last_pose", "heading", "quiet", "motions",
              "travel", "last_rate", "times", "elapsed", "last_clock", "samples")

    def state(self) -> dict[str, Any]:
        """The running history (numpy arrays and numbers), for ``restore``."""
        return {name: getattr(self, name) for name in self._STATE}

    def restore(self, state: dict[str, Any]) -> None:
        """Carry on from a ``state`` taken from a tracker with the same windows."""
        for name in self._STATE:
            value = state.get(name, getattr(self, name))   # (a state from before a name)
            setattr(self, name, np.array(value, dtype=np.float64)
                    if isinstance(value, np.ndarray) else value)

    def update(self, command: np.ndarray, odometry: np.ndarray, sonar: np.ndarray,
               pose: np.ndarray, clock: float | None = None, drove: np.ndarray | None = None,
               ) -> tuple[np.ndarray, np.ndarray]:
        """The features now and, per group, whether they carry information (a feature
        of a group that does not is NaN). ``command`` is what drove the robot since the
        last sample (their mean, if several); the other three are read now, at the
        robot's time ``clock``. ``drove``, if given with ``clock``, is the same command
        by command (a ``RobotDriver``'s ``drove``: rows of the robot's time it took
        each, v and w), and the response is followed through them one by one."""
        features = np.full(len(FEATURES), np.nan)
        informative = np.zeros(len(GROUPS), dtype=bool)
        if self.repeats(clock):
            return features, informative
        dt, since = self.sample_s, self.last_clock
        if clock is not None:
            if clock - since > 0.0:                  # (NaN before the first sample)
                dt = clock - since
            self.last_clock = clock
        command = np.asarray(command, dtype=np.float64)
        if drove is not None and clock is not None and clock - since > 0.0:
            expected = self._respond_through(np.asarray(drove, dtype=np.float64), since, clock)
        else:
            expected = self._respond(command, dt)
        if self.samples == 0:
            self.last_odometry[:], self.last_pose[:] = odometry, pose
            self.heading = float(pose[2])
            self.quiet[:] = self.heading
            self.samples = 1
            return features, informative
        odometry_distance, odometry_turn = _forward_and_turn(self.last_odometry, odometry)
        pose_distance, pose_turn = _forward_and_turn(self.last_pose, pose)
        self.last_odometry[:], self.last_pose[:] = odometry, pose
        if self.samples == 1:    # the first motion seen is what the commands gave so far:
            # a tracker started on a robot already moving (another robot handed over)
            # must not read its speed as a response to nothing
            expected = np.array([odometry_distance, odometry_turn]) / dt
            self._settle(command, dt, expected)
        self.motions[self.samples % len(self.motions)] = (
            odometry_distance / dt - expected[0],
            odometry_turn / dt - expected[1], *np.abs(expected))
        # the turn rate at this reading: the mean measured, moved to the sample's end as
        # the response moved from its mean (see _RIDGE)
        rate = pose_turn / dt + self.expected[1] - expected[1]
        self.travel[self.samples % len(self.travel)] = (
            odometry_turn - pose_turn, pose_turn, abs(pose_distance), rate - self.last_rate)
        self.last_rate = rate
        self.elapsed += dt
        self.times[self.samples % len(self.times)] = self.elapsed - dt / 2.0
        self.samples += 1

        if self.samples > len(self.motions):
            v_residual, w_residual, speed, turn = self.motions.mean(axis=0)
            features[0:2] = v_residual, w_residual
            informative[MOTORS] = speed >= self.min_speed or turn >= self.min_turn
        if self.samples > len(self.travel):
            drift, spread = _drift_per_metre(self.travel, self.times)
            if spread * self.heading_noise <= self.drift_resolution:
                features[2] = drift
                informative[ODOMETRY] = True

        self.heading += pose_turn
        heard = np.asarray(sonar) < MAX_RANGE - 1e-6
        self.quiet[:, heard] = self.heading
        np.minimum(self.quiet[0], self.heading, out=self.quiet[0])
        np.maximum(self.quiet[1], self.heading, out=self.quiet[1])
        features[_SWEEPS] = self.quiet[1] - self.quiet[0]
        informative[SONAR] = True
        return features, informative

    def repeats(self, clock: float | None) -> bool:
        """Whether a reading at the robot's time ``clock`` is at the last sample's instant:
        the same readings again, which ``update`` leaves out, changing nothing (a world
        server on a loaded machine that did not step between two of a driver's readings
        answers both at one instant; taken over the nominal ``sample_s``, the second made
        a robot driving at 0.4 m/s seem to stand for 0.1 s, and its residual stayed in
        the motors' 5-sample mean for five windows: a false motors alarm, v residual
        -0.08 m/s)."""
        return clock is not None and clock == self.last_clock

    def _settle(self, command: np.ndarray, elapsed: float, measured: np.ndarray) -> None:
        """Take up the speed the robot has now, from the mean speed it was ``measured``
        at over the last ``elapsed`` seconds under ``command``: the one the robot's
        response reaches from where it must have started. (The mean itself is not it: a
        standby robot speeding up on its first command was taken for half as fast as it
        was, and the gap, kept through the ramp the acceleration limits set, was read
        as 0.17 rad/s of motors failing.)"""
        low, high = np.full(2, -10.0), np.full(2, 10.0)   # where it started, bracketed
        for _ in range(40):      # (the response's mean grows with its starting speed)
            self.expected = (low + high) / 2.0
            fast = self._respond(command, elapsed) > measured
            middle = (low + high) / 2.0
            low, high = np.where(fast, low, middle), np.where(fast, middle, high)
        self.expected = (low + high) / 2.0
        self._respond(command, elapsed)

    def _respond_through(self, drove: np.ndarray, since: float, clock: float) -> np.ndarray:
        """``_respond`` to each of ``drove``'s commands in turn, from the robot's time
        ``since`` to ``clock``, each for as long as it drove the robot (the first from
        ``since`` on: a reading missed in between brought no command of its own); the
        mean expected speed over the whole. Under the acceleration limits the response
        to the commands' mean is not the mean of their responses: a robot turning at
        1 rad/s, told late in a long step to turn the other way, was still turning that
        way at its next reading, and a response to the mean had it slow from the start:
        0.2 rad/s of residual for as long as the limits took to reverse the turn."""
        starts = np.maximum.accumulate(np.clip(drove[:, 0], since, clock))
        starts[0] = since
        total = np.zeros(2)
        for command, lasted in zip(drove[:, 1:], np.diff([*starts, clock]), strict=True):
            if lasted > 0.0:
                total += self._respond(command, lasted) * lasted
        return total / (clock - since)

    def _respond(self, command: np.ndarray, elapsed: float) -> np.ndarray:
        """Advance the expected speed under ``command`` by ``elapsed`` seconds (in ten
        steps: the acceleration limit bites within a sample); its mean over them."""
        steps = 10
        dt = elapsed / steps
        gain = 1.0 - math.exp(-dt / self.lag_s)
        limit = self.limits * dt
        total = np.zeros(2)
        for _ in range(steps):
            self.expected += np.clip((command - self.expected) * gain, -limit, limit)
            total += self.expected
        return total / steps


def _forward_and_turn(before: np.ndarray, after: np.ndarray) -> tuple[float, float]:
    """Distance driven forward (negative backward) and turn from one pose to the next."""
    turn = math.remainder(float(after[2] - before[2]), math.tau)
    middle = float(before[2]) + turn / 2.0
    forward = (after[0] - before[0]) * math.cos(middle) + (after[1] - before[1]) * math.sin(middle)
    return float(forward), turn


def _drift_per_metre(travel: np.ndarray, times: np.ndarray) -> tuple[float, float]:
    """The drift per metre of the least-squares fit of odometry's heading errors (see
    ``_RIDGE``) over ``travel``'s samples, taken at ``times``, and its standard error
    per unit of noise: large when the robot barely moved, or drove one steady arc,
    where a drift and a scale error on turns explain the same errors."""
    wander = travel[:, 1] * (times - times.mean())
    error, regressors = travel[:, 0], np.column_stack([travel[:, 1:], wander])
    covariance = np.linalg.inv(regressors.T @ regressors + _RIDGE)
    return float((covariance @ (regressors.T @ error))[1]), math.sqrt(covariance[1, 1])


@dataclass(frozen=True)
class NormalModel:
    """Normal running as Gaussians per feature (``means``, ``variances``), with the
    alarm ``thresholds`` on each group's evidence; a fault is ``fault_breadth`` times
    wider, with prior probability ``fault_prior`` per group. Only the ``watched``
    groups (all by default) are modelled; the others give no evidence."""

    means: np.ndarray
    variances: np.ndarray
    thresholds: np.ndarray
    fault_prior: float = 0.01
    fault_breadth: float = 10.0
    watched: tuple[str, ...] = GROUPS

    @classmethod
    def fit(cls, features: np.ndarray, informative: np.ndarray, quantile: float = 0.999,
            margin: float = 10.0, fault_prior: float = 0.01, fault_breadth: float = 10.0,
            watched: tuple[str, ...] = GROUPS) -> NormalModel:
        """Fit the ``watched`` groups on normal running: ``features`` (samples,
        len(FEATURES)) with ``informative`` (samples, len(GROUPS)) from
        ``FeatureTracker``. Each group's threshold is the ``quantile`` of its evidence
        over the training samples plus ``margin`` (nats: some features, such as a
        sonar's silent sweep, are heavier tailed than a Gaussian, and a persistent
        one is not thinned by the k-of-n vote), or the evidence at which a fault
        becomes likelier than normal, if higher."""
        features, informative = np.asarray(features), np.asarray(informative, dtype=bool)
        unknown = sorted(set(watched) - set(GROUPS))
        if unknown:
            raise ValueError(f"no fault group {', '.join(unknown)}: the groups are "
                             f"{', '.join(GROUPS)}")
        mask = np.array([group in watched for group in GROUPS])
        short = [GROUPS[g] for g in np.flatnonzero(mask) if informative[:, g].sum() < 10]
        if short:
            raise ValueError(f"too little normal running to train on: fewer than 10 "
                             f"informative samples of {', '.join(short)}")
        informative = informative & mask
        used = informative[:, _GROUP_OF_FEATURE]
        data = np.where(used, features, np.nan)
        means, variances = np.zeros(len(FEATURES)), np.ones(len(FEATURES))
        fitted = used.any(axis=0)
        means[fitted] = np.nanmean(data[:, fitted], axis=0)
        variances[fitted] = np.nanvar(data[:, fitted], axis=0) + _LEAST_SPREAD[fitted] ** 2
        if mask[SONAR]:                                     # the transducers, tied
            means[_SWEEPS] = np.nanmean(data[:, _SWEEPS])
            variances[_SWEEPS] = np.nanvar(data[:, _SWEEPS]) + _LEAST_SPREAD[_SWEEPS] ** 2
        model = cls(means, variances, np.full(len(GROUPS), np.inf), fault_prior,
                    fault_breadth, tuple(group for group in GROUPS if group in watched))
        evidence = model.evidence(features, informative)
        even = math.log((1.0 - fault_prior) / fault_prior)
        thresholds = np.array([
            max(even, float(np.quantile(evidence[informative[:, g], g], quantile)) + margin)
            if mask[g] else np.inf for g in range(len(GROUPS))])
        return replace(model, thresholds=thresholds)

    @property
    def watching(self) -> np.ndarray:
        """Per group, whether it is watched (bool, len(GROUPS))."""
        return np.array([group in self.watched for group in GROUPS])

    def unit_evidence(self, features: np.ndarray) -> np.ndarray:
        """Per unit (the motors, the odometer, each transducer), the log-likelihood
        ratio of its fault to normal running: shape (..., 2 + 16)."""
        z2 = (np.asarray(features) - self.means) ** 2 / self.variances
        per_feature = 0.5 * z2 * (1.0 - self.fault_breadth ** -2) - math.log(self.fault_breadth)
        units = np.zeros((*per_feature.shape[:-1], _UNIT_COUNT))
        np.add.at(units.T, _UNIT_OF_FEATURE, per_feature.T)
        return units

    def evidence(self, features: np.ndarray, informative: np.ndarray) -> np.ndarray:
        """Per group, the log-likelihood ratio of its fault (in any one of its units)
        to normal running; ``-inf`` where the group carries no information or is not
        watched."""
        return self.group_evidence(self.unit_evidence(features), informative & self.watching)

    @staticmethod
    def group_evidence(units: np.ndarray, informative: np.ndarray) -> np.ndarray:
        """``evidence`` from the ``unit_evidence``."""
        groups = np.stack([logsumexp(units[..., members], axis=-1) - math.log(len(members))
                           for members in _UNITS_OF_GROUP], axis=-1)
        return np.where(informative, groups, -np.inf)

    def probability(self, evidence: np.ndarray) -> np.ndarray:
        """Each group's fault probability given its evidence."""
        return expit(np.asarray(evidence) + math.log(self.fault_prior / (1 - self.fault_prior)))

    def health(self, evidence: np.ndarray) -> float:
        """The probability of normal running against every group's fault."""
        odds = np.asarray(evidence) + math.log(self.fault_prior / (1 - self.fault_prior))
        return float(expit(-logsumexp(odds)))

    def state(self) -> dict[str, Any]:
        """The model as plain state (a ``HardwareMonitor``'s trained state)."""
        return {"means": self.means, "variances": self.variances,
                "thresholds": self.thresholds, "fault_prior": self.fault_prior,
                "fault_breadth": self.fault_breadth, "watched": list(self.watched),
                "trained": True}


def check_vote(votes_needed: int, votes_of: int) -> None:
    """ValueError unless an alarm's vote is k of n windows, whole numbers, 1 <= k <= n."""
    if not (whole(votes_needed, 1) and whole(votes_of, 1) and votes_needed <= votes_of):
        raise ValueError(f"an alarm needs votes_needed k of votes_of n windows, with "
                         f"1 <= k <= n, not {votes_needed} of {votes_of}")


class FaultMonitor:
    """A trained ``NormalModel`` watching one robot's streams: ``update`` each sample
    returns the failures that start then, each reported once per onset. A failure
    names its units (which transducers); one more unit failing is one more onset."""

    def __init__(self, model: NormalModel, tracker: FeatureTracker | None = None,
                 votes_needed: int = 3, votes_of: int = 5, rearm: int = 50) -> None:
        check_vote(votes_needed, votes_of)
        self.model = model
        self.tracker = tracker or FeatureTracker()
        self.votes_needed = votes_needed
        # a raised alarm is lowered after this many informative windows in a row within
        # the threshold (longer than the longest feature window, so that a fault does
        # not raise it twice while its evidence fills a window)
        self.rearm = rearm
        self.votes = np.zeros((votes_of, len(GROUPS)), dtype=bool)  # last n informative
        self.counted = np.zeros(len(GROUPS), dtype=np.int64)       # informative windows
        self.raised = np.zeros(len(GROUPS), dtype=bool)            # alarms latched
        self.beyond = np.zeros(len(GROUPS), dtype=bool)    # the last sample's, per group
        self.calm = np.zeros(len(GROUPS), dtype=np.int64)  # normal windows since alarm
        self.named = np.zeros(_UNIT_COUNT, dtype=bool)             # units named failed
        self.health = 1.0

    _STATE = ("votes", "counted", "raised", "calm", "named", "health")

    def state(self) -> dict[str, Any]:
        """The running state (the tracker's history and the votes), for ``restore``."""
        return {"tracker": self.tracker.state(),
                **{name: getattr(self, name) for name in self._STATE}}

    def restore(self, state: dict[str, Any]) -> None:
        """Carry on from a ``state`` taken from a monitor with the same windows."""
        self.tracker.restore(state["tracker"])
        for name in self._STATE:
            setattr(self, name, np.array(state[name]) if name != "health" else state[name])

    def update(self, command: np.ndarray, odometry: np.ndarray, sonar: np.ndarray,
               pose: np.ndarray, clock: float | None = None, drove: np.ndarray | None = None,
               ) -> list[dict[str, Any]]:
        """Take one sample (as ``FeatureTracker.update``); the failures that start now,
        each ``{"fault", "probability", "detail"}``. A reading at the last one's instant
        (``FeatureTracker.repeats``) is no sample: it changes nothing."""
        if self.tracker.repeats(clock):
            return []
        return self.observe(*self.tracker.update(command, odometry, sonar, pose, clock, drove))

    def observe(self, features: np.ndarray, informative: np.ndarray) -> list[dict[str, Any]]:
        """``update`` from a sample's features, taken by the tracker elsewhere."""
        informative = informative & self.model.watching
        units = self.model.unit_evidence(features)
        evidence = self.model.group_evidence(units, informative)
        self.health = self.model.health(evidence)
        probability = self.model.probability(evidence)
        beyond = self.beyond = (evidence > self.model.thresholds) & informative
        failures = []
        for group in np.flatnonzero(informative):
            slot = self.counted[group] % len(self.votes)
            self.votes[slot, group] = beyond[group]
            self.counted[group] += 1
            members = _UNITS_OF_GROUP[group]
            # the units whose own evidence beats the threshold (a group's evidence shares
            # it out among its units, so when the group's does, the likeliest one's does)
            culprits = members[units[members] >= self.model.thresholds[group]]
            if self.raised[group]:
                self.calm[group] = 0 if beyond[group] else self.calm[group] + 1
                if self.calm[group] >= self.rearm:
                    self.raised[group], self.named[members] = False, False
                if not self.raised[group] or self.named[culprits].all():
                    continue
            elif not (beyond[group] and self.votes[:, group].sum() >= self.votes_needed):
                continue
            self.raised[group], self.calm[group] = True, 0
            self.named[culprits] = True
            failures.append({"fault": GROUPS[group], "probability": float(probability[group]),
                             "detail": self._detail(group, features)})
        return failures

    def _detail(self, group: int, features: np.ndarray) -> dict[str, Any]:
        if group == MOTORS:
            return {"v_residual": float(features[0]), "w_residual": float(features[1])}
        if group == ODOMETRY:
            return {"drift_per_m": float(features[2])}
        dead = np.flatnonzero(self.named[_UNITS_OF_GROUP[SONAR]])
        return {"sonars": dead.tolist(), "silent_sweep": features[_SWEEPS][dead].tolist()}


class HardwareMonitor(Module):
    """Watches a robot's command, odometry, sonar and localization pose; writes a
    ``failure`` once per fault onset: ``{"fault": "motors" | "sonar" | "odometry",
    "probability", "at": time.time(), "detail"}``, and ``health`` (the probability
    of normal running) each sample.

    Untrained, it learns normal running as it comes, and watches each group of
    faults as soon as it has seen ``ready_windows`` informative windows of it (the
    motors' residual is informative whenever the robot is told to move; odometry's
    drift only after straight drives): its model is then fitted on all of normal
    running so far, and fitted again as each further group becomes ready and when
    ``training_s`` is up (``trained``; a group still short of windows then stays
    unwatched). A sample that the groups watched already find abnormal is not learnt
    as normal running (a fault while it learns would widen the very model that is to
    catch it). ``watched`` names the groups watched. Or it is given a trained
    model's state (``NormalModel.state()``: ``means``, ``variances``, ``thresholds``,
    ``watched``, ``trained``). A sample is taken when both a new odometry and a new
    pose have arrived (the driver sends them together, every ``sample_s``), and a new
    ``clock`` too once one has come: link the driver's, so that motion is measured
    over the robot's time between samples, not the nominal period (written after the
    reading's odometry, as the driver does: a clock that comes after its reading was
    sampled is that sample's time, not the next one's). Link its ``drove`` too, so that
    the robot's response is followed through the commands as it took them rather than
    taken for the response to their mean. A reading at the same instant of the robot's
    time as the last (its world did not step between the two) is no sample: nothing is
    judged, learnt or written for it.

    A pose that jumps between two samples by more than ``jump_m`` or ``jump_rad`` (no
    robot moves or turns that far in a sample, and no two robots' centres are that
    close: a Pioneer is 0.5 m across) means another robot feeds the monitor now:
    its driver was re-pointed, as when a control system moves to a standby robot. The
    monitor then starts afresh on the new robot (the model and what it learnt stay,
    the history and alarms go: they were the old robot's), rather than read the jump
    as a fault (``robot_changes`` counts them)."""

    # v (m/s), w (rad/s) as the robot was given them: link the driver's ``applied``
    # (RobotDriver), not the controller's command, which the driver may have changed
    command = Input(np.ndarray, shape=(2,), dtype="float64")
    odometry = Input(np.ndarray, shape=(3,), dtype="float64")
    sonar = Input(np.ndarray, shape=(SONARS,), dtype="float64")
    pose = Input(np.ndarray, shape=(3,), dtype="float64")         # localization (gps)
    clock = Input(float)         # the robot's time of the readings (optional, but see
                                 # FeatureTracker: a loaded machine's late samples)
    # the command command by command, with the clock (optional: link the driver's
    # ``drove``, else the response to ``command``, their mean, is taken for theirs)
    drove = Input(np.ndarray, dtype="float64")
    failure = Output(dict)
    health = Output(float)

    sample_s = 0.1
    training_s = 120.0
    # informative windows of normal running after which a group is watched: odometry
    # needs many, as its windows overlap and straight drives are few (with about 160,
    # 4 quick mapping runs in 15 raised a false odometry alarm)
    # (a group the state leaves out keeps this number)
    ready_windows = READY_WINDOWS
    quantile = 0.999             # of normal running's evidence, for the thresholds ...
    margin = 10.0                # ... with this margin (nats)
    fault_prior = 0.01
    fault_breadth = 10.0
    votes_needed = 3             # an alarm needs this many of ...
    votes_of = 5                 # ... the last windows beyond the threshold
    rearm = 50                   # windows within the threshold that lower an alarm
    trained = False
    watched: list[str] = []      # the groups watched so far
    means = np.zeros(0)
    variances = np.zeros(0)
    thresholds = np.zeros(0)
    training = np.zeros((0, len(FEATURES)))        # the samples of normal running so far
    training_informative = np.zeros((0, len(GROUPS)), dtype=bool)
    collected = 0
    running: dict = {}           # FaultMonitor.state(): the tracker's history, the votes
    failures = 0
    last_failure: dict = {}
    jump_m = 0.4
    jump_rad = 1.0
    robot_changes = 0

    def setup(self) -> None:
        refuse_own_state(self)
        self._tracker = FeatureTracker(self.sample_s)
        self._monitor: FaultMonitor | None = None
        if self.running:
            self._tracker.restore(self.running["tracker"])
        if self.trained and not self.watched:    # a model given without: it has them all
            self.watched = list(GROUPS)
        if self.watched:
            self._watch(self._model())
            if "votes" in self.running:
                self._monitor.restore(self.running)
                if len(self._monitor.votes) != self.votes_of:   # a vote of another length
                    self._monitor.votes = np.zeros((self.votes_of, len(GROUPS)), dtype=bool)
        if self.trained:
            return
        wanted = math.ceil(self.training_s / self.sample_s - 1e-9)
        if len(self.training) != wanted:        # first set up, or training_s was changed
            kept = min(self.collected, wanted)
            training = np.full((wanted, len(FEATURES)), np.nan)
            informative = np.zeros((wanted, len(GROUPS)), dtype=bool)
            training[:kept] = self.training[:kept]
            informative[:kept] = self.training_informative[:kept]
            self.training, self.training_informative = training, informative
            self.collected = kept

    @classmethod
    def state_problems(cls, state: dict[str, Any]) -> list[str]:
        """A setting that would blind or break it, each naming it: a limit's (see
        ``_LIMITS``), ``ready_windows``, a vote that is not k of n windows, a model given
        in state that does not fit (each when the state gives all its fields)."""
        return super().state_problems(state) + [
            f"{cls.__name__}'s {problem}" for problem in _settings_problems(state)]

    @reflective                 # (it takes the fields Module's does: they are checked)
    def set_state(self, state: dict[str, Any]) -> None:
        """Set state (what ``state_problems`` refuses is refused, nothing set); a running
        monitor goes by it from its next sample (a threshold, a vote, what it remembers),
        rather than by what it made of its state at setup and writes back over it."""
        super().set_state(state)
        if "_tracker" in vars(self):             # running: made again from the state
            self.setup()

    def _watch(self, model: NormalModel) -> None:
        """Watch by ``model``: a first model starts a ``FaultMonitor``; a later one
        (more groups, more normal running) replaces its model, keeping its votes."""
        if self._monitor is None:
            self._monitor = FaultMonitor(model, self._tracker, self.votes_needed,
                                         self.votes_of, self.rearm)
        else:
            self._monitor.model = model

    def on_input(self, port: InputPort) -> None:
        # one sample per odometry-and-pose pair (and clock, once one has come),
        # whichever came last
        if self.clock.pending and not self.odometry.pending:
            # the clock of the reading sampled last, come after the sample (the driver
            # writes it last, and a first reading is sampled as its odometry comes: no
            # clock is known to come): that sample's time. Left pending, it was taken for
            # the next reading's, and every later sample was measured over the interval
            # before its own (a late reading after a timely one: twice the speed)
            self._tracker.last_clock = self.clock.read()
            return
        timed = self.clock.has_value
        if not (self.odometry.pending and self.pose.pending and self.sonar.has_value
                and (self.clock.pending or not timed)):
            return
        sample = (self.command.read(default=np.zeros(2)), self.odometry.read(),
                  self.sonar.read(), self.pose.read())
        clock = self.clock.read() if timed else None
        drove = self.drove.read() if self.drove.pending else None
        if self._another_robot(sample[3]):
            self._tracker = FeatureTracker(self.sample_s)      # afresh on it
            if self._monitor is not None:
                self._monitor = None
                self._watch(self._model())
            self.robot_changes += 1
        if self._tracker.repeats(clock):
            return               # no time passed: nothing to measure (see the docstring)
        features, informative = self._tracker.update(*sample, clock=clock, drove=drove)
        failures = [] if self._monitor is None else self._monitor.observe(features, informative)
        # what the groups watched already find abnormal is not learnt as normal running
        if not self.trained and (self._monitor is None or not (
                self._monitor.raised.any() or self._monitor.beyond.any())):
            self._learn(features, informative)
        if self._monitor is None:
            self.running = {"tracker": self._tracker.state()}
            return
        self.running = self._monitor.state()
        self.health.write(self._monitor.health)
        for failure in failures:
            failure["at"] = time.time()
            self.failures += 1
            self.last_failure = failure
            self.failure.write(failure)

    def _another_robot(self, pose: np.ndarray) -> bool:
        """Whether ``pose`` jumped from the last sample's (see the class docstring)."""
        last = self._tracker.last_pose
        return bool(np.isfinite(last).all()) and (
            math.dist(last[:2], pose[:2]) > self.jump_m
            or abs(math.remainder(float(pose[2] - last[2]), math.tau)) > self.jump_rad)

    def _model(self) -> NormalModel:
        return NormalModel(np.asarray(self.means), np.asarray(self.variances),
                           np.asarray(self.thresholds), self.fault_prior,
                           self.fault_breadth, tuple(self.watched))

    def _learn(self, features: np.ndarray, informative: np.ndarray) -> None:
        """Keep a sample of normal running; fit the model again when a group has become
        ready, and for the last time when ``training_s`` is up."""
        self.training[self.collected] = features
        self.training_informative[self.collected] = informative
        self.collected += 1
        counts = self.training_informative[:self.collected].sum(axis=0)
        done = self.collected == len(self.training)
        windows = {**READY_WINDOWS, **self.ready_windows}   # (the groups it leaves out)
        ready = tuple(group for g, group in enumerate(GROUPS)
                      if counts[g] >= max(10, windows[group]) or (done and counts[g] >= 10))
        if ready == tuple(self.watched) and not done:
            return
        if ready:
            model = NormalModel.fit(self.training[:self.collected],
                                    self.training_informative[:self.collected],
                                    self.quantile, self.margin, self.fault_prior,
                                    self.fault_breadth, ready)
            vars(self).update(model.state() | {"trained": done})   # (its own: no rebuild)
            self._watch(model)
        if done:
            if len(ready) < len(GROUPS):
                log.warning("HardwareMonitor watches no %s faults: fewer than 10 "
                            "informative windows of them in %g s of normal running",
                            ", ".join(g for g in GROUPS if g not in ready), self.training_s)
            self.trained = True
            self.training = np.zeros((0, len(FEATURES)))
            self.training_informative = np.zeros((0, len(GROUPS)), dtype=bool)
            self.collected = 0


_LIMITS: dict[str, Limit] = {
    # (a negative jump_m took every sample for another robot's: nothing was ever
    # watched; a fault_prior of 0 divided by zero at every sample)
    "sample_s": SPAN,
    "training_s": SPAN,
    "jump_m": ("a distance above 0", lambda v: finite(v) and v > 0),
    "jump_rad": ("an angle above 0", lambda v: finite(v) and v > 0),
    "quantile": ("a share from 0 to 1", lambda v: finite(v) and 0 <= v <= 1),
    "margin": ("a finite number (nats)", finite),
    "fault_prior": ("a probability above 0 and below 1", lambda v: finite(v) and 0 < v < 1),
    "fault_breadth": ("a number above 1", lambda v: finite(v) and v > 1),
    "rearm": ("a whole number of windows, 1 or more",
              lambda v: whole(v, 1)),
}


_VOTE = ("votes_needed", "votes_of")                  # judged together
_MODEL = ("watched", "trained", "means", "variances", "thresholds")     # and these


def _settings_problems(state: dict[str, Any]) -> list[str]:
    """What a ``HardwareMonitor`` could not go by of ``state``, each naming the setting."""
    problems = out_of_limits(_LIMITS, state)
    windows = state.get("ready_windows", {})
    if not isinstance(windows, dict):    # (a list failed with AttributeError)
        problems.append(f"ready_windows must map a fault group to the windows it needs, "
                        f"as {{\"motors\": 150}}, got {windows!r}")
        windows = {}
    unknown = sorted(map(str, set(windows) - set(GROUPS)))
    if unknown:
        problems.append(f"ready_windows names no fault group {', '.join(unknown)}: "
                        f"the groups are {', '.join(GROUPS)}")
    problems += [f"ready_windows[{group!r}] must be a whole number, 0 or more, got {n!r}"
                 for group, n in windows.items() if not whole(n)]
    if set(_VOTE) <= set(state):
        try:
            check_vote(state["votes_needed"], state["votes_of"])
        except ValueError as exc:
            problems.append(f"votes_needed and votes_of: {exc}")
    if set(_MODEL) <= set(state):
        problems += _model_problems(state)
    return problems


def _model_problems(model: dict[str, Any]) -> list[str]:
    """What does not fit of a model given in state (``NormalModel.state()``): a misspelt
    group was never watched, and means of another length failed at the first sample, in
    numpy's words."""
    watched = model["watched"]
    if not isinstance(watched, list | tuple):
        return [f"watched must be a list of fault groups, got {watched!r}"]
    unknown = [group for group in watched if group not in GROUPS]
    if unknown:
        return [f"watched names no fault group {', '.join(map(repr, unknown))}: the groups "
                f"are {', '.join(GROUPS)}"]
    if not (model["trained"] or watched):
        return []                                  # (no model yet: it learns one)
    sizes = {"means": (len(FEATURES), "feature"), "variances": (len(FEATURES), "feature"),
             "thresholds": (len(GROUPS), "fault group")}
    return [f"model given in state does not fit: {name} must hold {size} numbers, one per "
            f"{per}, not {np.shape(model[name])}"
            for name, (size, per) in sizes.items() if np.shape(model[name]) != (size,)]


class Wanderer:
    """A reactive wander-and-avoid controller on the sonar ring: the normal running
    ``record_normal_running`` drives by default. Cruises, veers towards open space,
    wanders at random, and turns on the spot away from anything close ahead."""

    def __init__(self, seed: int = 0, cruise: float = 0.35, clearance: float = 0.7) -> None:
        self.rng = np.random.default_rng(seed)
        self.cruise, self.clearance = cruise, clearance
        self.whim = 0.0              # the random part of the turn rate, a slow walk
        self.escape = 0.0            # the way it turns on the spot, kept until clear

    def __call__(self, sonar: np.ndarray) -> np.ndarray:
        """The command (v m/s, w rad/s) for this sonar ring."""
        # the 50-degree transducers guard the shoulders, which a corner may graze
        ahead = min(float(sonar[2:6].min()), float(sonar[[1, 6]].min()) / 0.6)
        left, right = float(sonar[0:2].min()), float(sonar[6:8].min())
        if ahead < self.clearance:
            if not self.escape:
                self.escape = 0.8 if left >= right else -0.8
            return np.array([0.0, self.escape])
        self.escape = 0.0
        self.whim = float(np.clip(self.whim + self.rng.normal(0.0, 0.1), -0.4, 0.4))
        veer = 0.4 * (min(left, 2.0) - min(right, 2.0))
        speed = self.cruise * min(1.0, (ahead - self.clearance) / 0.8 + 0.3)
        return np.array([speed, float(np.clip(self.whim + veer, -1.0, 1.0))])


def samples(world: World, robot: str, seconds: float,
            controller: Callable[[np.ndarray], np.ndarray] | None = None,
            sample_s: float = 0.1,
            ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Drive ``robot`` of an in-process ``world`` by ``controller`` (a ``Wanderer`` by
    default) for ``seconds`` of simulated time, stepping the world by ``sample_s``;
    yields each sample as (command since the last sample, odometry, sonar, pose), as
    a ``FaultMonitor`` takes them. Faults injected between yields take effect in the
    next step."""
    body = world.robot(robot)
    controller = controller or Wanderer()
    command = np.zeros(2)
    for _ in range(round(seconds / sample_s)):
        sonar = np.asarray(body.sonar(), dtype=np.float64)
        yield (command, np.array(body.odometry()), sonar, np.array(body.gps()))
        command = np.asarray(controller(sonar), dtype=np.float64)
        body.drive(float(command[0]), float(command[1]))
        world.step(sample_s)


def record_normal_running(world: World, robot: str, seconds: float,
                          controller: Callable[[np.ndarray], np.ndarray] | None = None,
                          tracker: FeatureTracker | None = None,
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Features and informative flags (``NormalModel.fit``'s arguments) of ``seconds``
    of ``robot`` running normally in ``world`` (see ``samples``)."""
    tracker = tracker or FeatureTracker()
    rows = [tracker.update(*sample)
            for sample in samples(world, robot, seconds, controller, tracker.sample_s)]
    return np.array([f for f, _ in rows]), np.array([i for _, i in rows])
