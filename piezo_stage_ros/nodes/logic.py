# Copyright 2026 piezo_stage_ros maintainers
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""
What the nodes do, without rclpy: lockstep sequencing, real-time sampling, pairing, watchdogs.

Each class here is the whole behaviour of one node in plain values (nanosecond stamps, floats);
the rclpy node only turns messages into calls and return values into messages. The loop order
is the one of :mod:`piezo_stage_ros.core.contracts.interfaces`, as in
:func:`piezo_stage_ros.core.loop.closed_loop.run`:

1. :class:`PlantLogic` publishes y_k stamped t_k (and ``/clock`` = t_k in lockstep);
2. :class:`TrajectoryLogic` answers x_d(t_k), x_d'(t_k) with the same stamp;
3. :class:`ControllerLogic`, holding y_k and x_d for the same stamp, steps the controller once
   and publishes u_k;
4. the plant holds u_k over one sample: in lockstep it steps on receiving u_k, in real time it
   samples on its own clock with the last command received.

Lockstep start-up. The plant publishes sample 0 only once enough subscribers matched, and
publishes the current sample again after ``resend_s`` without its command (a message sent while
the graph was still matching can be lost). Duplicates are harmless: the trajectory's answer
depends on the stamp only, and the controller steps at most once per stamp and never publishes
twice for one stamp, so the plant receives exactly one command per sample.
"""

from __future__ import annotations

from collections import deque
import dataclasses
from dataclasses import dataclass
import json
import math
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError, PiezoStageError
from piezo_stage_ros.core.contracts.interfaces import Controller, Trajectory
from piezo_stage_ros.core.contracts.wire import diagnostic_reader, NS_PER_S
from piezo_stage_ros.core.control.feedforward import check_learning_period, FeedForwardController
from piezo_stage_ros.core.loop.follow import (
    GoalFollower,
    GoalTrajectory,
    PreparedGoal,
    SplineTrajectory,
    State,
    take_over_state,
)
from piezo_stage_ros.core.loop.goals import (
    finish,
    GoalVerdict,
    JointTrajectoryGoal,
    ResultCode,
    Steps,
)
from piezo_stage_ros.core.loop.splines import Spline
from piezo_stage_ros.core.loop.trajectories import TrajectoryParams
from piezo_stage_ros.hardware.safety import GuardedPlant, Trip, Watchdog

__all__ = ['ControllerLogic', 'Gate', 'GoalDesk', 'LATE_COMMAND_LIMIT', 'LATE_HALF_LIMIT',
           'PlantLogic', 'Sample', 'TrajectoryLogic', 'TripLog', 'realtime_warning', 'run_verdict',
           'announce_goal', 'announce_trajectory', 'parse_announcement', 'parse_trajectory',
           'rebuild_or_learn_afresh',
           'sample_count', 'save_learned_table']

#: Checks of a goal in a row that may find the reference changed before it is refused (each
#: retry checks twice as far ahead as the last).
GOAL_RETRIES = 6

#: A goal checked ahead whose start sample the real-time servo skipped starts at the next
#: sample served, when that is at most this much later [s]: on its own sample of the grid, as
#: if the ones between were skipped within it (a new check would find the same state again
#: when the stage holds, and on a loaded machine keeps missing its sample too).
GOAL_LATE_START_S = 0.002

#: A goal checked in slices (:meth:`GoalDesk.work`): points read, and samples checked against
#: the limits, per slice; each slice is short against a sample period.
GOAL_POINTS_PER_SLICE = 32
GOAL_SAMPLES_PER_SLICE = 128

#: Samples of a goal's reference the real-time loop computes ahead per slice of its idle time.
GOAL_CHUNK_PIECE = 10

#: End of a run: more than this fraction of the samples taken late by more than T/2 makes the
#: end-of-run line a warning (docs/reference/ros-interface.md, "Status counters").
LATE_HALF_LIMIT = 0.001
#: End of a run: more than this fraction of the samples served with the previous command (no
#: new one had come: a controller in another node that answers late) makes it a warning.
LATE_COMMAND_LIMIT = 0.001
#: Counters of which any at all makes the end-of-run line a warning: samples the servo never
#: took, samples taken but lost on the way to the ROS side, samples left out of the per-sample
#: topics (the block topic has them), samples the UDP bridge or its target lost, and watchdog
#: trips.
ANY_COUNTS = (('skipped', 'skipped'), ('ring_missed', 'lost between the servo process and '
                                                     'the node (ring_missed)'),
              ('queue_overruns', 'lost in the servo queue (queue_overruns)'),
              ('live_dropped', 'left out of the per-sample topics by an executor that fell '
                               'behind (live_dropped; stage/block has them)'),
              ('bridge_lost', 'replies lost by the UDP bridge'),
              ('bridge_target_missing', 'commands the target found missing'),
              ('watchdog_trips', 'watchdog trips'))


def realtime_warning(mode: str, direct: bool, sample_rate_hz: float) -> str | None:
    """
    Return the warning for a real-time plant without the direct composition, else None.

    Parameters
    ----------
    mode : str
        The plant node's ``mode``.
    direct : bool
        Whether the plant's servo loop runs trajectory and controller itself
        (``stage_servo --direct``); otherwise each command comes by message.
    sample_rate_hz : float
        The loop's rate [Hz].

    """
    if mode != 'realtime' or direct:
        return None
    return (f'real time at {sample_rate_hz:g} Hz with the commands coming by message: a '
            'message between nodes (separate processes, or stage_servo without --direct) '
            'cannot make the period (measured on a 2-core machine at 10 kHz: 87 % of the '
            'samples served with the previous command, 773 watchdog trips a minute); for real '
            'time run the loop in one process with samples handed on by call: '
            '`ros2 launch piezo_stage_ros closed_loop.launch.py mode:=realtime direct:=true` '
            'or `ros2 run piezo_stage_ros stage_servo --direct`')


def run_verdict(stats: Mapping[str, Any]) -> tuple[str, list[str]]:
    """
    Return how the end-of-run line is logged, and why: ``('warn', reasons)`` or ``('info', [])``.

    A warning when more than :data:`LATE_HALF_LIMIT` of the samples taken were late by more
    than half a period, more than :data:`LATE_COMMAND_LIMIT` of them were served with the
    previous command, or any count of :data:`ANY_COUNTS` is not zero (a lockstep run has none
    of these). The reasons name each figure against its threshold.
    """
    reasons = []
    taken = int(stats.get('paced_samples') or 0)
    late_half = int(stats.get('late_half_period') or 0)
    if taken and late_half > LATE_HALF_LIMIT * taken:
        reasons.append(f'{late_half} samples ({100.0 * late_half / taken:.2g} %) late by more '
                       f'than T/2 (threshold {100.0 * LATE_HALF_LIMIT:g} %)')
    served = int(stats.get('samples') or 0)
    late = int(stats.get('late') or 0)
    if served and late > LATE_COMMAND_LIMIT * served:
        reasons.append(f'{late} samples ({100.0 * late / served:.3g} %) served with the '
                       f'previous command (threshold {100.0 * LATE_COMMAND_LIMIT:g} %)')
    for key, what in ANY_COUNTS:
        count = stats.get(key) or 0
        if count:
            reasons.append(f'{count} {what}')
    if stats.get('error'):
        reasons.append(f'error {stats["error"]}')
    return ('warn', reasons) if reasons else ('info', [])


class TripLog:
    """
    The log lines about the plant's watchdog trips: each trip, at most one line per interval.

    A trip that ends within ``interval_s`` of the last line is counted, and the counts go out
    with the next line (a loop whose commands come late can trip many times a second; the
    counters on ``stage/status`` have every one).

    Parameters
    ----------
    safe_v : float
        The safe voltage [V] (named in the lines).
    interval_s : float
        Least time between two lines [s].

    """

    def __init__(self, safe_v: float, interval_s: float = 1.0) -> None:
        self.safe_v = safe_v
        self.interval_s = interval_s
        self._last_s: float | None = None
        self._held = 0
        self._held_samples = 0
        self._held_step_v = 0.0

    def describe(self, trip: Trip, slew_v_per_s: float, period_s: float) -> str:
        """Return the line of one trip (its length in samples and time, its largest step)."""
        ended = {'commands': 'the commands reached again',
                 'tripped again': 'commands stopped again while being followed back',
                 'stop': 'the run stopped during it'}.get(trip.ended, trip.ended or 'going on')
        return (f'watchdog trip: no command for {trip.silence_s * 1e3:.3g} ms; '
                f'{trip.samples} samples over {trip.duration_s * 1e3:.4g} ms: '
                f'{trip.ramp_samples} ramping from {trip.from_v:.4g} V toward the safe '
                f'{self.safe_v:g} V, {trip.safe_samples} at it, {trip.recovery_samples} '
                f'following the commands back; largest step {trip.max_step_v:.4g} V '
                f'(watchdog.slew_v_per_s {slew_v_per_s:g} allows '
                f'{slew_v_per_s * period_s:.4g} V a sample); ended: {ended}')

    def _held_back(self) -> str:
        text = (f'{self._held} more trips since the last line: {self._held_samples} samples, '
                f'largest step {self._held_step_v:.4g} V')
        self._held = self._held_samples = 0
        self._held_step_v = 0.0
        return text

    def lines(self, trips: Sequence[Trip], now_s: float, *, slew_v_per_s: float,
              period_s: float, final: bool = False) -> list[str]:
        """
        Return the lines to log now for the trips that ended since the last call.

        ``now_s``: any monotonic clock [s]; ``final``: the run is over, the counts held back
        go out now.
        """
        out = []
        for trip in trips:
            if self._last_s is None or now_s - self._last_s >= self.interval_s:
                line = self.describe(trip, slew_v_per_s, period_s)
                out.append(f'{line} (and {self._held_back()})' if self._held else line)
                self._last_s = now_s
            else:
                self._held += 1
                self._held_samples += trip.samples
                self._held_step_v = max(self._held_step_v, trip.max_step_v)
        if self._held and (final or self._last_s is None
                           or now_s - self._last_s >= self.interval_s):
            out.append(f'watchdog: {self._held_back()}')
            self._last_s = now_s
        return out


def rebuild_or_learn_afresh(build: Callable[[Any], Controller], params: Any,
                            warn: Callable[[str], Any] | None = None) -> Controller:
    """
    Rebuild the controller for a change at run time; without the learned table if it must.

    A change (a notch, a gain) that ``feedforward.table_file`` was not learned with would
    refuse the table and stop the loop at a sample: the new controller learns afresh instead.

    Parameters
    ----------
    build : callable
        ``build(params)``: the controller of ControllerParams ``params``.
    params : ControllerParams
        The changed parameters.
    warn : callable, optional
        Told why the table was not loaded.

    Returns
    -------
    Controller

    Raises
    ------
    ParameterError
        If the parameters are refused for another reason than the table.

    """
    try:
        return build(params)
    except ParameterError as err:
        if not params.feedforward.table_file:
            raise
        if warn is not None:
            warn(f'learned table not loaded after the change: {err}')
        return build(params.replace(feedforward=params.feedforward.replace(table_file='')))


def save_learned_table(controller: Controller, path: str) -> str | None:
    """
    Write the table a learning feed-forward learned to ``path`` (``feedforward.save_table_file``).

    Parameters
    ----------
    controller : Controller
        The controller that ran (whichever process ran it).
    path : str
        File to write; empty: nothing is written.

    Returns
    -------
    str or None
        The line to log, or ``None`` when nothing was to be written.

    Raises
    ------
    PiezoStageError
        If the file cannot be written.

    """
    if not path or not isinstance(controller, FeedForwardController):
        return None
    table = controller.learned()
    controller.save_table_file(path)
    return (f'learned table written: {path} ({table.samples} samples, '
            f'{table.periods_learned} periods learned)')


def sample_count(duration_s: float, sample_rate_hz: float) -> int:
    """Return the samples of a run of ``duration_s`` [s] at ``sample_rate_hz`` [Hz], 0: endless."""
    if duration_s <= 0.0:
        return 0
    # the offline runner's rule: round(duration / T), at least one
    return max(int(round(duration_s / (1.0 / sample_rate_hz))), 1)


@dataclass(frozen=True)
class Sample:
    """
    One measured sample, ready to publish.

    Attributes
    ----------
    index : int
        k, from 0.
    stamp_ns : int
        t_k [ns] (simulation time in lockstep, ROS time in real time).
    position_m : float
        y_k [m].

    """

    index: int
    stamp_ns: int
    position_m: float


class PlantLogic:
    """
    The plant node's behaviour in lockstep: owns simulation time, one sample per command.

    In real time the plant node samples with the paced servo loop
    (:class:`piezo_stage_ros.nodes.servo.ServoLoop`) instead; this object then only holds the
    mode, the rate and the run length.

    Parameters
    ----------
    plant : GuardedPlant
        The backend behind the safety rules.
    mode : str
        ``'lockstep'`` or ``'realtime'``.
    sample_rate_hz : float
        Sample rate [Hz].
    duration_s : float
        Stop after ``round(duration_s * rate)`` samples; 0 runs on.
    resend_s : float
        Lockstep: publish the waiting sample again after this long without its command [s].

    """

    def __init__(self, plant: GuardedPlant, *, mode: str, sample_rate_hz: float,
                 duration_s: float = 0.0, resend_s: float = 0.5) -> None:
        if mode not in ('lockstep', 'realtime'):
            raise ParameterError('mode', mode, "one of 'lockstep', 'realtime'")
        self.plant = plant
        self.mode = mode
        self.lockstep = mode == 'lockstep'
        self.rate_hz = float(sample_rate_hz)
        self.period_s = 1.0 / self.rate_hz
        self.total = sample_count(duration_s, self.rate_hz)
        self.resend_s = resend_s
        self.start_ns = 0
        self.index = -1
        self.done = False
        self.waiting = False
        self._last: Sample | None = None
        self._last_publish_s = 0.0
        self._t0_s = 0.0
        self.resends = 0
        self.unexpected = 0

    @property
    def last_sample(self) -> Sample | None:
        """Return the sample published last (the one waiting for its command in lockstep)."""
        return self._last

    def stamp_ns(self, index: int) -> int:
        """Return t_k [ns] of sample ``index`` (rounded to whole nanoseconds)."""
        return self.start_ns + round(index * NS_PER_S / self.rate_hz)

    def _sample(self, position_m: float) -> Sample:
        self.index += 1
        sample = Sample(self.index, self.stamp_ns(self.index), position_m)
        self._last = sample
        return sample

    def start(self, now_s: float, start_ns: int = 0) -> Sample:
        """
        Start the backend and return sample 0.

        Parameters
        ----------
        now_s : float
            Monotonic wall time [s] (watchdog, resend and real-time schedule).
        start_ns : int
            t_0 [ns]: 0 in lockstep (simulation time starts at zero, as offline), the ROS time
            of the start in real time.

        """
        self.start_ns = int(start_ns)
        y0 = self.plant.start(now_s)
        self._t0_s = now_s
        self._last_publish_s = now_s
        self.waiting = self.lockstep
        sample = self._sample(y0)
        if self.total == 1:
            self.done = True
            self.waiting = False
        return sample

    def on_command(self, command_v: float, now_s: float) -> Sample | None:
        """
        Take the command for the current sample.

        Parameters
        ----------
        command_v : float
            u_k [V].
        now_s : float
            Monotonic wall time of arrival [s].

        Returns
        -------
        Sample or None
            Lockstep: the next sample to publish (None once the run is complete, or for a
            command nobody waits for, counted in ``unexpected``). Real time: always None (the
            command is held from the next sample on).

        """
        if not self.lockstep:
            if not self.done and self.index >= 0:
                self.plant.command(command_v, now_s)
            else:
                self.unexpected += 1
            return None
        if not self.waiting:
            self.unexpected += 1
            return None
        position = self.plant.step(command_v)
        self._last_publish_s = now_s
        if self.total and self.index + 1 >= self.total:
            # the command of the last sample is applied (as offline) but y_N is not a sample
            self.waiting = False
            self.done = True
            return None
        return self._sample(position)

    def resend_due(self, now_s: float) -> Sample | None:
        """Lockstep: return the waiting sample again if its command is overdue, else None."""
        if not (self.lockstep and self.waiting and self._last is not None):
            return None
        if now_s - self._last_publish_s < self.resend_s:
            return None
        self._last_publish_s = now_s
        self.resends += 1
        return self._last

    def stop(self) -> None:
        """Drive the safe voltage and release the backend."""
        self.done = True
        self.waiting = False
        self.plant.stop()

    def stats(self) -> dict[str, Any]:
        """Return the counters: samples, late, resends, watchdog trips, bridge losses."""
        out = self.plant.stats()
        out.update({'index': self.index, 'resends': self.resends,
                    'unexpected_commands': self.unexpected})
        return out


class GoalDesk:
    """
    The goals' requests of a trajectory logic, of one axis or several, and their events.

    Goals are taken for a :class:`~piezo_stage_ros.core.loop.follow.GoalFollower`
    (:meth:`attach_goals`); :meth:`goal`, :meth:`cancel` and :meth:`hold` may be called from
    any thread, and the sample's call serves them (:meth:`_serve_goals`). A goal that may run
    takes the reference over from whatever plays, without a jump, from the state the subclass
    gives (:meth:`_take_over_state`). Verdicts, results and feedback go to :attr:`events`.
    The subclass sets ``rate_hz`` and ``period_s`` and keeps ``_origin_ns`` (the stamp of the
    first sample: the goals' loop time is 0 there) and ``_index`` (the last sample served).
    """

    rate_hz: float
    period_s: float

    def _init_goals(self) -> None:
        self.follower: GoalFollower | None = None
        self._lead = 0
        self._late_s = 0.0
        self._origin_ns: int | None = None
        self._index = -1
        self._epoch = 0
        self._requests: deque[tuple[Any, ...]] = deque()
        self._starts: deque[tuple[Any, ...]] = deque()
        self._tokens: dict[int, int] = {}
        self._retries: dict[int, int] = {}
        #: Check goals a slice at a time in :meth:`work` (the real-time loop's own thread, in
        #: the time its samples leave free) instead of in the thread that calls :meth:`goal`.
        self.check_in_slices = False
        self._checks: deque[tuple[Any, ...]] = deque()
        self._check: tuple[int, Steps[tuple[Any, ...] | None]] | None = None
        #: (loop time [s], goal) of the goals started, the last thousand: a run to replay
        #: offline (:func:`~piezo_stage_ros.core.loop.follow.run_goals`), with the loop times
        #: of the cancels (:attr:`cancelled`).
        self.started: deque[tuple[float, JointTrajectoryGoal]] = deque(maxlen=1000)
        #: Loop times [s] at which a cancel or a hold brought the reference to rest.
        self.cancelled: deque[float] = deque(maxlen=1000)
        #: What the goals did, oldest first, for the side that answers the client (taken
        #: with ``popleft`` from another thread): ``('verdict', token, GoalVerdict, goal_id)``,
        #: ``('result', GoalResult)``, ``('feedback', Feedback)``, ``('retry', token, goal,
        #: tracked, stamp_ns)`` (the reference changed while it was checked: check it again
        #: with :meth:`goal`), ``('cancelled', token)`` (cancelled before it started).
        self.events: deque[tuple[Any, ...]] = deque()

    @property
    def goal_active(self) -> bool:
        """Return whether the reference is the follower's (a goal took it over)."""
        raise NotImplementedError

    def _take_over_state(self, index: int) -> State:
        """Return the state at grid sample ``index`` of what plays (no goal active)."""
        raise NotImplementedError

    def _take_over(self) -> None:
        """Make the follower's reference the one played, from the goal's sample on."""
        raise NotImplementedError

    def _cancel_at(self, index: int) -> None:
        assert self.follower is not None
        self.follower.cancel(index * self.period_s)
        self.cancelled.append(index * self.period_s)

    def attach_goals(self, follower: GoalFollower, lead_s: float = 0.0) -> None:
        """
        Take goals for ``follower`` (its joints the stage's axes); ``lead_s`` [s]: check ahead.

        0 (lockstep): a goal is checked and started at the next sample, in the sample's own
        call. More (real time): :meth:`goal` checks it in the caller's thread for the sample
        ``lead_s`` after the last one, and that sample only starts it.
        """
        self.follower = follower
        self._lead = max(0, int(round(lead_s * self.rate_hz)))
        self._late_s = GOAL_LATE_START_S if self._lead else 0.0

    def goal(self, token: int, goal: JointTrajectoryGoal, *, tracked: bool = True,
             stamp_ns: int | None = None) -> None:
        """
        Submit a goal (any thread); its verdict comes as ``('verdict', token, ...)``.

        Parameters
        ----------
        token : int
            The caller's number for it (> 0).
        goal : JointTrajectoryGoal
            The goal.
        tracked : bool
            An action goal (results, feedback) or a topic message.
        stamp_ns : int, optional
            Its header stamp [ns] on the samples' clock, when not zero (times count from it).

        """
        if self.follower is None:
            self.events.append(('verdict', token, GoalVerdict(
                ResultCode.INVALID_GOAL, 'this trajectory node takes no goals'), 0))
        elif self._lead == 0:
            self._requests.append(('goal', token, goal, tracked, stamp_ns))
        elif self.check_in_slices:
            self._checks.append((token, goal, tracked, stamp_ns))
        else:
            # each retry checks twice as far ahead: a check slower than the lead (a long
            # trajectory) gets a sample it can reach
            lead = self._lead << self._retries.get(token, 0)
            self._prepare(token, goal, tracked, stamp_ns, self._index + 1 + lead)

    def cancel(self, token: int) -> None:
        """Cancel the goal submitted as ``token`` (any thread): the reference decelerates."""
        self._requests.append(('cancel', token))

    def hold(self) -> None:
        """Bring whatever goal moves the reference to rest (an empty JointTrajectory)."""
        self._requests.append(('hold',))

    def stamp_of(self, time_s: float) -> int:
        """Return the stamp [ns] of the sample at loop time ``time_s`` (the goals' time)."""
        k = round(time_s * self.rate_hz)
        return (self._origin_ns or 0) + round(k * NS_PER_S / self.rate_hz)

    @property
    def checking(self) -> bool:
        """Return whether a goal's check waits for :meth:`work`."""
        return self._check is not None or bool(self._checks)

    @property
    def has_work(self) -> bool:
        """Return whether :meth:`work` has something to do (a check, a reference ahead)."""
        return self.check_in_slices and (self.checking or self._ahead_due())

    def _ahead_due(self) -> bool:
        """Return whether the subclass can compute something ahead (:meth:`_work_ahead`)."""
        return False

    def _work_ahead(self) -> bool:
        """Do a slice of what the subclass computes ahead; return whether more is left."""
        return False

    def work(self) -> bool:
        """
        Do one slice of the check of the goals submitted (:attr:`check_in_slices`).

        Called by the loop's thread between samples, over and over while it waits for the
        next; the check of a goal is for the sample the lead puts it at, counted from the
        sample served when its first slice runs. Without a check, a slice of what the
        subclass computes ahead. Returns whether work is left.
        """
        if self._check is None:
            if not self._checks:
                return self._work_ahead()
            token, goal, tracked, stamp_ns = self._checks.popleft()
            lead = self._lead << self._retries.get(token, 0)
            self._check = (token, self._preparing(
                token, goal, tracked, stamp_ns, self._index + 1 + lead,
                GOAL_POINTS_PER_SLICE, GOAL_SAMPLES_PER_SLICE))
        token = self._check[0]
        try:
            next(self._check[1])
        except StopIteration:
            self._check = None
            return bool(self._checks)
        except Exception as exc:  # noqa: BLE001 -- the goal is refused, the loop goes on
            self._check = None
            self._retries.pop(token, None)
            self.events.append(('verdict', token, GoalVerdict(
                ResultCode.INVALID_GOAL, f'the check failed: {type(exc).__name__}: {exc}'), 0))
            return bool(self._checks)
        return True

    def _prepare(self, token: int, goal: JointTrajectoryGoal, tracked: bool,
                 stamp_ns: int | None, index: int) -> tuple[Any, ...] | None:
        return finish(self._preparing(token, goal, tracked, stamp_ns, index, 0, 0))

    def _preparing(self, token: int, goal: JointTrajectoryGoal, tracked: bool,
                   stamp_ns: int | None, index: int, points: int, samples: int
                   ) -> Steps[tuple[Any, ...] | None]:
        follower = self.follower
        assert follower is not None
        epoch = self._epoch
        t = index * self.period_s
        # taking over from another trajectory: the goal starts from its state there; the
        # follower is seeded with it only at the start, in the loop's thread (this may run in
        # another, beside a goal the loop starts meanwhile)
        state = None if self.goal_active else self._take_over_state(index)
        origin = None if stamp_ns is None or self._origin_ns is None else \
            (stamp_ns - self._origin_ns) / NS_PER_S
        options: dict[str, Any] = {'tracked': tracked, 'origin_s': origin, 'start_state': state}
        if points or samples:
            verdict, prepared = yield from follower.preparing(
                goal, t, points_per_step=points, samples_per_step=samples, **options)
        else:
            verdict, prepared = follower.prepare(goal, t, **options)
        if prepared is None:
            self._retries.pop(token, None)
            self.events.append(('verdict', token, verdict, 0))
            return None
        item: tuple[Any, ...] = ('start', token, prepared, state, epoch, verdict, goal,
                                 stamp_ns, None)
        if self._lead:
            yield from self._ahead_of_start(prepared, index)
            if state is not None:
                # the reference the start seeds the follower with, built here
                yield
                item = item[:-1] + (follower.seed_spline(t, *state),)
            self._starts.append(item)
        return item

    def _ahead_of_start(self, prepared: PreparedGoal, index: int) -> Steps[None]:
        """Compute what the start of a goal checked ahead can take ready (the subclass)."""
        return
        yield

    def _start(self, item: tuple[Any, ...], index: int, served: int = -1) -> None:
        _, token, prepared, state, epoch, verdict, goal, stamp_ns, seed = item
        follower = self.follower
        assert follower is not None and isinstance(prepared, PreparedGoal)
        seeded = state is not None
        goal_id = 0
        # the goal's own sample: this one, or in real time one the servo skipped shortly before
        # (after ``served``, the sample served last); a check that ended after its sample was
        # served is made again further ahead: started late, the goal's reference would jump
        # by the way it should have gone meanwhile
        late = index * self.period_s - prepared.time_s
        t = prepared.time_s
        own = round(t / self.period_s)
        # on its own sample (served again: a lockstep resend), or late over skipped ones only
        on_grid = index <= own or served < own
        if epoch == self._epoch and seeded != self.goal_active and on_grid and \
                -0.5 * self.period_s <= late <= self._late_s + 0.5 * self.period_s:
            if seeded:
                if seed is None:
                    follower.seed(t, *state)
                else:
                    follower.take_seed(seed)
                prepared = dataclasses.replace(prepared, version=follower.version)
            goal_id = follower.start(prepared, t)
        if goal_id == 0:
            # the reference changed since the check (or the sample passed): check it again,
            # a bounded number of times
            retries = self._retries.get(token, 0) + 1
            if retries > GOAL_RETRIES:
                self._retries.pop(token, None)
                self.events.append(('verdict', token, GoalVerdict(
                    ResultCode.INVALID_GOAL, f'the goal could not be started: {retries} checks '
                    'in a row found the reference changed or their sample passed before they '
                    'ended (goals or trajectory changes arriving faster than a goal is '
                    'checked)'), 0))
                return
            self._retries[token] = retries
            self.events.append(('retry', token, goal, prepared.tracked, stamp_ns))
            return
        self._retries.pop(token, None)
        if seeded:
            self._take_over()
        if prepared.tracked:
            # a topic message has no result and cannot be cancelled by its token
            self._tokens[token] = goal_id
        self.started.append((t, goal))
        self.events.append(('verdict', token, verdict, goal_id))

    def _serve_goals(self, index: int, served: int = -1) -> None:
        """
        Apply the goal requests due at grid sample ``index``.

        ``served``: the grid sample served before it (a goal checked ahead starts late only
        over samples the servo skipped, never over one it served without it).
        """
        follower = self.follower
        assert follower is not None
        requests = self._requests
        while requests:
            item = requests.popleft()
            kind = item[0]
            if kind == 'goal':
                started = self._prepare(item[1], item[2], item[3], item[4], index)
                if started is not None:
                    self._start(started, index, served)
            elif kind == 'cancel':
                goal_id = self._tokens.pop(item[1], None)
                if goal_id is None:
                    if any(r[1] == item[1] for r in self._starts):
                        self._starts = deque(r for r in self._starts if r[1] != item[1])
                        self.events.append(('cancelled', item[1]))
                    elif self._drop_check(item[1]):
                        self.events.append(('cancelled', item[1]))
                elif self.goal_active and follower.active_goal == goal_id:
                    self._cancel_at(index)
            elif self.goal_active:
                self._cancel_at(index)
        starts = self._starts
        # goals checked ahead, each for its own sample (in the order they were checked)
        while starts and round(starts[0][2].time_s / self.period_s) <= index:
            self._start(starts.popleft(), index, served)

    def _drop_check(self, token: int) -> bool:
        """Drop the check of goal ``token`` if it is waiting or under way; return whether."""
        dropped = False
        if self._check is not None and self._check[0] == token:
            self._check = None
            dropped = True
        elif any(c[0] == token for c in self._checks):
            self._checks = deque(c for c in self._checks if c[0] != token)
            dropped = True
        if dropped:
            self._retries.pop(token, None)
        return dropped

    def _take_results(self) -> None:
        assert self.follower is not None
        results = self.follower.results
        while results:
            result = results.pop(0)
            for token in [k for k, v in self._tokens.items() if v == result.goal_id]:
                del self._tokens[token]
            self.events.append(('result', result))

    def _step_goal(self, index: int, positions_m: Sequence[float],
                   desired_m: Sequence[float],
                   desired_velocity_mps: Sequence[float] | None = None) -> None:
        follower = self.follower
        assert follower is not None
        _, feedback = follower.step(index * self.period_s, positions_m, desired_m,
                                    desired_velocity_mps)
        if follower.results:
            self._take_results()
        if feedback is not None:
            self.events.append(('feedback', feedback))


class TrajectoryLogic(GoalDesk):
    """
    The trajectory node's behaviour: x_d(t_k) and x_d'(t_k) for each sample stamp.

    Parameters
    ----------
    trajectory : Trajectory
        The trajectory to stream; its t = 0 is the first sample after a start.
    sample_rate_hz : float
        Sample rate [Hz]: stamps are turned into sample indices, and times into k / rate
        exactly as the offline runner computes them.
    chunk_s : float
        Evaluate this much at a time [s], chunks aligned at the start as offline.
    active : bool
        Stream from the first sample (else hold x_d(0) with zero velocity until started).

    Notes
    -----
    Inactive, the reference is held with zero velocity: x_d(0) of the trajectory before its
    first start, the last reference after a stop. A start, or a new trajectory, takes effect at
    the next sample and begins at its t = 0 there.

    Goals (:meth:`attach_goals`, :meth:`goal`, :meth:`cancel`): a goal that may run takes the
    reference over from whatever plays, without a jump, at the next sample (``lead_s`` later
    in real time, where it is checked outside the sample); the reference is then the
    follower's (:class:`~piezo_stage_ros.core.loop.follow.GoalTrajectory`), on the loop's own
    time: t = 0 at the first sample this logic answered. Verdicts, results and feedback go to
    :attr:`events`. A new trajectory or a stop ends a goal (CANCELED).

    """

    def __init__(self, trajectory: Trajectory, *, sample_rate_hz: float, chunk_s: float = 1.0,
                 active: bool = True) -> None:
        self.rate_hz = float(sample_rate_hz)
        self.period_s = 1.0 / self.rate_hz
        self.chunk = max(int(round(chunk_s / self.period_s)), 1)
        self.trajectory = trajectory
        self.active = active
        self._start_ns: int | None = None
        self._pending: Trajectory | None = None
        self._chunk_index = -1
        self._ref: list[float] = []
        self._vel: list[float] = []
        first, _ = trajectory.evaluate(np.zeros(1))
        self.hold_m = float(first[0])
        self.answered = 0
        self._ahead_sent = -1
        self._ahead_asked: int | None = None
        self._grid_ns: int | None = None
        self._switched = False
        self._switch_ns: int | None = None
        self._window: tuple[int, Any, int, Any, Any] = (0, None, -1, np.zeros(0),
                                                         np.zeros(0))
        self._init_goals()
        self._view: GoalTrajectory | None = None
        self._version = -1
        # chunks of a goal's reference computed ahead, each (spline, chunk, x_d, x_d'): the
        # first of a goal checked ahead (with its check), the next of the one that plays
        # (a piece at a time, in the loop's idle time: :meth:`work`)
        self._first_chunk: tuple[Spline, int, list[float], list[float]] | None = None
        self._next_chunk: tuple[Spline, int, list[float], list[float]] | None = None
        # x_d that went out ahead per sample, with x_d' and the spline they came from
        self._sent: dict[int, tuple[float, float, Spline | None]] = {}
        #: Called with (trajectory, stamp of its t = 0) when a goal changes the reference, at
        #: the sample it does: a controller that reads the reference ahead binds it again
        #: (:meth:`ControllerLogic.request_trajectory`).
        self.on_reference_change: Callable[[Trajectory, int], None] | None = None

    def __getstate__(self) -> dict[str, Any]:
        """Return the state to copy, without the hook to the controller (the servo's warm-up)."""
        state = dict(self.__dict__)
        state['on_reference_change'] = None
        return state

    def start(self) -> None:
        """Stream from the next sample on, from t = 0 (:meth:`take_switch` tells its stamp)."""
        self.active = True
        self._start_ns = None
        self._switched = True
        self._epoch += 1

    def stop(self) -> None:
        """Hold the last reference with zero velocity from the next sample on."""
        self.active = False
        self._epoch += 1

    def switch(self, trajectory: Trajectory) -> None:
        """Replace the trajectory at the next sample (it starts at its t = 0 there)."""
        self._pending = trajectory
        self._epoch += 1

    # -- goals ------------------------------------------------------------------------------

    def attach_goals(self, follower: GoalFollower, lead_s: float = 0.0) -> None:
        """Take goals for ``follower`` (one axis); ``lead_s`` [s]: as :class:`GoalDesk`'s."""
        super().attach_goals(follower, lead_s)
        self._view = GoalTrajectory(follower)

    @property
    def goal_active(self) -> bool:
        """Return whether the reference is the follower's (a goal took it over)."""
        return self.active and self._view is not None and self.trajectory is self._view

    def _take_over_state(self, index: int) -> State:
        x, v, a = self._state_at(index)
        return np.array([x]), np.array([v]), np.array([a])

    def _take_over(self) -> None:
        assert self._view is not None
        self.trajectory = self._view
        self._start_ns = self._origin_ns
        self.active = True

    def _ahead_of_start(self, prepared: PreparedGoal, index: int) -> Steps[None]:
        # the chunk the goal's start sample reads, as _evaluate computes it once the goal's
        # spline is the follower's
        yield
        chunk = index // self.chunk
        ref, vel = self._piece(prepared.spline, chunk * self.chunk, self.chunk)
        self._first_chunk = (prepared.spline, chunk, ref, vel)

    def _piece(self, spline: Spline, first: int, count: int) -> tuple[list[float], list[float]]:
        """Return x_d, x_d' of samples ``first`` .. ``first + count - 1`` of a goal's spline."""
        time_s = np.arange(first, first + count, dtype=np.float64) * self.period_s
        ref, vel = SplineTrajectory(spline).evaluate(time_s)
        return (np.asarray(ref, dtype=np.float64).tolist(),
                np.asarray(vel, dtype=np.float64).tolist())

    def _ahead_due(self) -> bool:
        follower = self.follower
        if follower is None or not self.goal_active or self._chunk_index < 0 or \
                self._version != follower.version:
            return False
        ahead = self._next_chunk
        return ahead is None or ahead[0] is not follower.spline or \
            ahead[1] != self._chunk_index + 1 or len(ahead[2]) < self.chunk

    def _work_ahead(self) -> bool:
        # the next chunk of the goal's reference, a piece at a time: the floats the sample
        # that needs it would compute (the spline evaluates every time on its own)
        if not self._ahead_due():
            return False
        assert self.follower is not None
        spline, chunk = self.follower.spline, self._chunk_index + 1
        ahead = self._next_chunk
        if ahead is None or ahead[0] is not spline or ahead[1] != chunk:
            ahead = self._next_chunk = (spline, chunk, [], [])
        done = len(ahead[2])
        count = min(GOAL_CHUNK_PIECE, self.chunk - done)
        ref, vel = self._piece(spline, chunk * self.chunk + done, count)
        ahead[2].extend(ref)
        ahead[3].extend(vel)
        return len(ahead[2]) < self.chunk

    def _state_at(self, index: int) -> tuple[float, float, float]:
        """Return x_d, x_d', x_d'' of what plays now, at grid sample ``index``."""
        if not self.active:
            return self.hold_m, 0.0, 0.0
        start = index - self._index - 1 if self._start_ns is None or self._origin_ns is None \
            else index - round((self._start_ns - self._origin_ns) * self.rate_hz / NS_PER_S)
        x, v, a = take_over_state((self.trajectory,), start, self.period_s)
        return float(x[0]), float(v[0]), float(a[0])

    def _end_goal(self, index: int) -> None:
        """End the goal (CANCELED): a new trajectory or a stop takes the reference from it."""
        assert self.follower is not None
        if self.follower.active_goal is not None:
            self.follower.hold(index * self.period_s)
        self._take_results()

    def observe(self, stamp_ns: int, position_m: float) -> None:
        """
        Account the measured position of a sample whose reference went out ahead.

        Lockstep with references ahead (:meth:`ahead`): the goals' tolerances and feedback
        take y_k when it comes, against the x_d that went out for it.
        """
        if self._origin_ns is None or not self.goal_active:
            return
        index = round((stamp_ns - self._origin_ns) * self.rate_hz / NS_PER_S)
        sent = self._sent.pop(index, None)
        if sent is not None:
            desired, velocity, spline = sent
            assert self.follower is not None
            # the feedback takes x_d' with x_d if they came from the reference as it is
            self._step_goal(index, (position_m,), (desired,),
                            (velocity,) if spline is not None and spline is self.follower.spline
                            else None)

    def take_switch(self) -> int | None:
        """
        Return the stamp [ns] where the last t = 0 fell, once; else None.

        A t = 0 after a start, or of a new trajectory (inactive, that of a new trajectory falls
        at the start); not the first sample's of a trajectory streamed from it. For a
        controller that predicts from its own copy of the trajectory: it binds
        :attr:`trajectory` at that sample (:meth:`ControllerLogic.request_trajectory`), the
        line it has again after a start of the same one.
        """
        stamp, self._switch_ns = self._switch_ns, None
        return stamp

    def _evaluate(self, index: int) -> tuple[float, float]:
        chunk = index // self.chunk
        if self._view is not None and self.follower is not None and \
                self.follower.version != self._version:
            # a goal changed the reference: what was evaluated ahead is stale
            self._version = self.follower.version
            self._chunk_index = -1
        if chunk != self._chunk_index and self.trajectory is self._view and \
                self.follower is not None:
            # a chunk of the goal's spline computed ahead, whole
            for ahead in (self._next_chunk, self._first_chunk):
                if ahead is not None and ahead[1] == chunk and len(ahead[2]) == self.chunk \
                        and ahead[0] is self.follower.spline:
                    self._ref, self._vel = ahead[2], ahead[3]
                    self._chunk_index = chunk
                    break
        if chunk != self._chunk_index:
            k0 = chunk * self.chunk
            time_s = np.arange(k0, k0 + self.chunk, dtype=np.float64) * self.period_s
            ref, vel = self.trajectory.evaluate(time_s)
            self._ref = np.asarray(ref, dtype=np.float64).tolist()
            self._vel = np.asarray(vel, dtype=np.float64).tolist()
            self._chunk_index = chunk
        i = index - chunk * self.chunk
        return self._ref[i], self._vel[i]

    def ahead(self, stamp_ns: int, count: int) -> list[tuple[int, float, float]]:
        """
        Lockstep: return the references up to ``count`` samples after ``stamp_ns`` not sent yet.

        The reference does not depend on the position, so it can go out ahead and the
        controller pairs it with its position by stamp. The stamps are the plant's, computed by
        the same rule (t_0 + round(k 10^9 / rate) ns) from the first position's stamp.

        Returns
        -------
        list of (stamp_ns, position_m, velocity_mps)
            Oldest first; the sample ``stamp_ns`` itself when it was not sent yet.

        """
        first = self._grid_ns is None
        if self._grid_ns is None:
            self._grid_ns = stamp_ns
        # the plant's stamp grid, from the first sample: a start or a new trajectory moves the
        # trajectory's t = 0, not the stamps, nor what was sent already
        grid = self._grid_ns
        index = round((stamp_ns - grid) * self.rate_hz / NS_PER_S)
        if first or (self.active and self._start_ns is None):
            # a first sample, or t = 0 at this one after a start: what went out ahead of it
            # held the reference, and goes again from the new start
            out = [(stamp_ns, *self.on_position(stamp_ns))]
            self._ahead_sent = index
        elif stamp_ns == self._ahead_asked:
            # the same sample again (a lockstep resend: something of it was lost, perhaps its
            # reference): its reference goes again
            out = [(stamp_ns, *self.on_position(stamp_ns))]
        else:
            out = []
        self._ahead_asked = stamp_ns
        for k in range(max(self._ahead_sent + 1, index), index + count + 1):
            stamp = grid + round(k * NS_PER_S / self.rate_hz)
            out.append((stamp, *self.on_position(stamp)))
            self._ahead_sent = k
        return out

    def window(self, stamp_ns: int, count: int) -> tuple[Any, Any]:
        """
        Return x_d and x_d' [m, m/s] of the ``count`` samples after ``stamp_ns`` (array views).

        For commands ahead, after :meth:`on_position` of the same stamp: the trajectory as it
        plays now (held while inactive; a switch not yet made is not in it). Evaluated in
        windows of its own, so the chunks :meth:`on_position` plays are untouched.
        """
        if not self.active or self._start_ns is None:
            return np.full(count, self.hold_m), np.zeros(count)
        index = round((stamp_ns - self._start_ns) * self.rate_hz / NS_PER_S) + 1
        first, trajectory, version, ref, vel = self._window
        now = self.follower.version if self.follower is not None else -1
        if trajectory is not self.trajectory or version != now or index < first or \
                index + count > first + len(ref):
            first = max(index, 0)
            size = count + max(self.chunk, 256)
            time_s = np.arange(first, first + size, dtype=np.float64) * self.period_s
            x, v = self.trajectory.evaluate(time_s)
            ref = np.asarray(x, dtype=np.float64)
            vel = np.asarray(v, dtype=np.float64)
            self._window = (first, self.trajectory, now, ref, vel)
        i = index - first
        return ref[i:i + count], vel[i:i + count]

    def on_position(self, stamp_ns: int, position_m: float | None = None
                    ) -> tuple[float, float]:
        """
        Return the reference for the sample stamped ``stamp_ns`` [ns].

        Parameters
        ----------
        stamp_ns : int
            The sample's stamp [ns].
        position_m : float, optional
            y_k [m], for the goals' tolerances and feedback; None: a reference that goes out
            ahead of its position (:meth:`observe` takes the position later).

        Returns
        -------
        position_m, velocity_mps : float
            x_d [m] and x_d' [m/s].

        """
        if self._origin_ns is None:
            self._origin_ns = stamp_ns
        if self.follower is not None:
            index = round((stamp_ns - self._origin_ns) * self.rate_hz / NS_PER_S)
            served = self._index
            if index > self._index:
                self._index = index
            if self._pending is not None or (self.trajectory is self._view
                                             and not self.active):
                # a new trajectory or a stop takes the reference from the goal
                if self.follower.active_goal is not None:
                    self._end_goal(index)
            else:
                if self._requests or self._starts:
                    self._serve_goals(index, served)
                if self.goal_active:
                    return self._goal_reference(stamp_ns, index, position_m)
        if self._pending is not None:
            self.trajectory = self._pending
            self._pending = None
            self._start_ns = None
            self._chunk_index = -1
            self._switched = True
        self.answered += 1
        if not self.active:
            return self.hold_m, 0.0
        if self._start_ns is None:
            self._start_ns = stamp_ns
            self._chunk_index = -1
            if self._switched:
                self._switched = False
                self._switch_ns = stamp_ns
        index = round((stamp_ns - self._start_ns) * self.rate_hz / NS_PER_S)
        if index < 0:
            # a sample older than the start (reordered): the start value
            index = 0
        ref, vel = self._evaluate(index)
        self.hold_m = ref
        return ref, vel

    def _goal_reference(self, stamp_ns: int, index: int, position_m: float | None
                        ) -> tuple[float, float]:
        """Return the follower's reference at grid sample ``index`` and account y_k."""
        assert self.follower is not None and self._view is not None
        self.answered += 1
        self._switched = False
        if self.follower.version != self._version and self.on_reference_change is not None:
            assert self._origin_ns is not None
            self.on_reference_change(self._view, self._origin_ns)
        ref, vel = self._evaluate(max(index, 0))
        self.hold_m = ref
        # x_d, x_d' of this sample's time from the follower's spline (a sample before the
        # origin plays the first one's)
        spline = self.follower.spline if index >= 0 else None
        if position_m is None:
            self._sent[index] = (ref, vel, spline)
            while len(self._sent) > 4096:
                self._sent.pop(next(iter(self._sent)))
        elif math.isfinite(position_m):
            self._step_goal(index, (position_m,), (ref,), (vel,) if spline is not None else None)
        return ref, vel


def _learning_refuses(controller: Controller, trajectory: Trajectory) -> str | None:
    """Return why a learning feed-forward cannot take ``trajectory`` (no period), else None."""
    if not isinstance(controller, FeedForwardController) or not controller.params.learning:
        return None
    period = controller.params.period_s or getattr(trajectory, 'period_s', None) or 0.0
    try:
        check_learning_period(period, controller.sample_time_s)
    except ParameterError as err:
        return str(err)
    return None


#: Samples of a period :func:`line_print` compares at most.
LINE_PRINT_SAMPLES = 100_000


def line_print(trajectory: Trajectory, sample_time_s: float) -> tuple[Any, ...] | None:
    """
    Return what tells a periodic line from another at the loop's samples (None: aperiodic).

    Its kind, its period and x_d, x_d' at every sample of one period from t = 0 (at most
    ``LINE_PRINT_SAMPLES``): lines with equal prints play the same reference at every
    sample, so a feed-forward bound to one plays the other as it is, its table included.
    """
    period = getattr(trajectory, 'period_s', None)
    if not period:
        return None
    count = min(int(math.ceil(period / sample_time_s)) + 1, LINE_PRINT_SAMPLES)
    x, v = trajectory.evaluate(np.arange(count, dtype=np.float64) * sample_time_s)
    return (getattr(trajectory, 'kind', ''), float(period),
            np.asarray(x, dtype=np.float64).tobytes(), np.asarray(v, dtype=np.float64).tobytes())


def announce_trajectory(stamp_ns: int, params: TrajectoryParams) -> str:
    """
    Return the announcement of a new trajectory whose t = 0 is the sample ``stamp_ns``.

    JSON text (the ``data`` of a ``std_msgs/msg/String``): ``stamp_ns`` and ``trajectory``,
    the trajectory's parameters by their dotted names, as the trajectory node declares them.
    """
    return json.dumps({'stamp_ns': int(stamp_ns), 'trajectory': params.to_flat()})


def announce_goal(stamp_ns: int, view: SplineTrajectory) -> str:
    """
    Return the announcement of a goal's reference whose t = 0 is the sample ``stamp_ns``.

    JSON text as :func:`announce_trajectory`'s, with ``goal``: the follower's spline as it stood
    (:meth:`~piezo_stage_ros.core.loop.splines.Spline.record`) and ``axis``, so that a controller
    in another process binds the reference the trajectory node plays, bit for bit.
    """
    return json.dumps({'stamp_ns': int(stamp_ns), 'goal': view.spline.record(),
                       'axis': view.axis})


def parse_announcement(text: str) -> tuple[int, TrajectoryParams | SplineTrajectory]:
    """
    Return the stamp [ns] and what an announcement binds.

    A trajectory's parameters (:func:`announce_trajectory`) or a goal's reference
    (:func:`announce_goal`).

    Raises
    ------
    ParameterError
        If the text is neither, or a trajectory parameter is bad.

    """
    try:
        data = json.loads(text)
        if isinstance(data, dict) and 'goal' in data:
            return int(data['stamp_ns']), SplineTrajectory(Spline.from_record(data['goal']),
                                                           int(data['axis']))
    except (ValueError, TypeError, KeyError, PiezoStageError) as exc:
        raise ParameterError('goal announcement', text[:80],
                             'JSON {"stamp_ns": int, "goal": spline record, "axis": int}',
                             f'is not one ({exc})') from None
    return parse_trajectory(text)


def parse_trajectory(text: str) -> tuple[int, TrajectoryParams]:
    """
    Return the stamp [ns] and the trajectory of an announcement (:func:`announce_trajectory`).

    Raises
    ------
    ParameterError
        If the text is not an announcement, or a trajectory parameter is bad.

    """
    try:
        data = json.loads(text)
        stamp, values = int(data['stamp_ns']), dict(data['trajectory'])
    except (ValueError, TypeError, KeyError) as exc:
        raise ParameterError('trajectory announcement', text[:80],
                             'JSON {"stamp_ns": int, "trajectory": {name: value}}',
                             f'is not one ({exc})') from None
    return stamp, TrajectoryParams.from_flat(values)


@dataclass(frozen=True)
class Command:
    """
    A command to publish.

    Attributes
    ----------
    stamp_ns : int
        Stamp of the sample it answers [ns] (-1 for a watchdog command).
    voltage_v : float
        u_k [V].
    diagnostics : tuple of float or None
        Controller internals to publish with it (every ``diagnostics_every`` samples).
    diagnostic_names : tuple of str or None
        The names of ``diagnostics`` (those of the controller that computed them: a structural
        change rebuilds it, possibly of another kind with other names); None: the names the
        publisher knows.

    """

    stamp_ns: int
    voltage_v: float
    diagnostics: Sequence[float] | None = None
    diagnostic_names: tuple[str, ...] | None = None


class ControllerLogic:
    """
    The controller node's behaviour: pair position and reference by stamp, step once per stamp.

    Parameters
    ----------
    controller : Controller
        The controller.
    mode : str
        ``'lockstep'`` or ``'realtime'`` (the position watchdog runs in real time only: in
        lockstep positions stop only when the plant has stopped time).
    safe_voltage_v : float
        Command published while positions have stopped [V].
    position_timeout_s : float
        Silence of the position topic after which the safe command goes out [s].
    diagnostics_every : int
        Return the diagnostics with every this-many-th command.
    rebuild : callable, optional
        ``rebuild(params) -> Controller`` for :meth:`request_change` when the controller has
        no ``update_params(params) -> bool`` or it returns False (a structural change: another
        type, notch, sensor gain or output limits).
    on_refused : callable, optional
        ``on_refused(reason)`` when a feed-forward cannot take a new trajectory (learning on
        an aperiodic one): it keeps the one it has, which no longer matches the reference,
        and the loop runs on feedback alone.
    on_bound : callable, optional
        ``on_bound(trajectory)`` when a new trajectory is bound (at the sample of its t = 0):
        the one a rebuild must bind from then on (not a refused one, nor one still to come).
    trajectory : Trajectory, optional
        The trajectory ``controller`` is bound to: a request of the same line (a start after
        a stop) restarts it instead of binding it afresh.

    """

    def __init__(self, controller: Controller, *, mode: str = 'lockstep',
                 safe_voltage_v: float = 0.0, position_timeout_s: float = 0.01,
                 diagnostics_every: int = 10,
                 rebuild: Callable[[Any], Controller] | None = None,
                 on_refused: Callable[[str], None] | None = None,
                 on_bound: Callable[[Any], None] | None = None,
                 trajectory: Any = None) -> None:
        self.controller = controller
        self._on_refused = on_refused
        self._on_bound = on_bound
        self.lockstep = mode == 'lockstep'
        self.safe_voltage_v = safe_voltage_v
        self.watchdog = Watchdog(position_timeout_s)
        self.diagnostics_every = max(1, diagnostics_every)
        self._rebuild = rebuild
        self.names, self._read = diagnostic_reader(controller)
        self._bind_skip()
        # positions and references by stamp: a reference may come ahead of its position
        # (lockstep_ahead), and in real time positions may come in a burst ahead of their
        # references; each sample is stepped once it has both
        self._positions: dict[int, float] = {}
        self._refs: dict[int, tuple[float, float]] = {}
        self._last_stamp: int | None = None
        self._index = 0  # samples since the first, skipped ones included
        self._pending: Any = None
        # new trajectories to bind, oldest first: (stamp of their t = 0, or None for the next
        # sample; the trajectory; its line_print); the stamps increase (request_trajectory)
        self._trajectories: list[tuple[int | None, Any, Any]] = []
        self._bound: tuple[Any, Any] = (trajectory, self._print(trajectory))
        self._prepared: tuple[Any, Any] | None = None
        self._needs_reset = True
        self._safe = False
        self.steps = 0
        self.duplicates = 0
        self.safe_commands = 0
        self.changes = 0

    def __getstate__(self) -> dict[str, Any]:
        """
        Return the state to copy, without the hooks to its node (the servo's warm-up).

        The hooks are a node's methods: a copy would copy the node, which holds locks.
        """
        state = dict(self.__dict__)
        state['_on_refused'] = state['_on_bound'] = state['_rebuild'] = None
        return state

    def _bind_skip(self) -> None:
        self._skip: Callable[[int], None] | None = getattr(self.controller, 'skip', None)
        self._missed: Callable[[int], None] | None = getattr(self.controller, 'missed', None)
        self._period_ns = max(1, round(self.controller.sample_time_s * NS_PER_S))
        self._gap_ns = self._period_ns * 3 // 2  # consecutive samples are one period apart

    def _restart(self, position_m: float, reference_m: float) -> None:
        """Reset the controller at this sample; a feed-forward goes on at its reference."""
        self.controller.reset(position_m, reference_m)
        if self._skip is not None:
            self._skip(self._index)

    def request_change(self, params: Any) -> None:
        """Apply validated new controller parameters at the next sample boundary."""
        self._pending = params

    def request_trajectory(self, trajectory: Any, stamp_ns: int | None = None) -> None:
        """
        Bind a new trajectory at the sample where its t = 0 falls.

        What :meth:`TrajectoryLogic.switch` does to the reference: a feed-forward (its
        ``switch``) takes the new line from that sample on, its model inverse at once and its
        learning afresh; another controller just follows the new reference.

        Parameters
        ----------
        trajectory : Trajectory
            The new trajectory.
        stamp_ns : int, optional
            The stamp [ns] of its t = 0 (:meth:`TrajectoryLogic.take_switch`, announced by a
            trajectory node in another process); None: the next sample. A stamp already
            stepped (an announcement that came late) binds it at the next sample, that many
            samples into it.

        Notes
        -----
        The latest request says what plays from its stamp on: requests still queued for that
        stamp or later are dropped (with references ahead, a stop and a start announce a t = 0
        before one announced earlier). The same line as the one bound before that stamp (a
        start after a stop: equal references at every sample of a period) restarts the
        feed-forward (its ``restart``: the learned table kept) instead of binding it afresh.
        That comparison, and whatever the feed-forward can compute of the new line ahead (its
        ``prepare``), run here, in the caller's thread, not in the sample's step.

        """
        queue = self._trajectories
        while queue and (stamp_ns is None
                         or (queue[-1][0] is not None and queue[-1][0] >= stamp_ns)):
            queue.pop()
        prepared = self._prepared
        if prepared is not None and prepared[0] is trajectory:
            self._prepared = None
            line = prepared[1]
        elif self._bound[0] is trajectory:
            line = self._bound[1]
        else:
            line = self._print(trajectory)
            if line is None or line != (queue[-1][2] if queue else self._bound[1]):
                self._prepare(trajectory)
        queue.append((stamp_ns, trajectory, line))

    def prepare_trajectory(self, trajectory: Any) -> None:
        """
        Compute now what a later :meth:`request_trajectory` of ``trajectory`` would compute.

        For a caller that knows the trajectory before its t = 0 has a stamp (the servo, between
        samples): the request, in the sample, then finds it done.
        """
        line = self._print(trajectory)
        self._prepare(trajectory)
        self._prepared = (trajectory, line)

    def _prepare(self, trajectory: Any) -> None:
        prepare = getattr(self.controller, 'prepare', None)
        if prepare is not None:
            prepare(trajectory)

    def _print(self, trajectory: Any) -> Any:
        """Return :func:`line_print` of ``trajectory`` at this controller's sample time."""
        return None if trajectory is None else \
            line_print(trajectory, self.controller.sample_time_s)

    def _apply_pending(self, position_m: float, reference_m: float) -> None:
        params, self._pending = self._pending, None
        update = getattr(self.controller, 'update_params', None)
        if callable(update) and update(params):
            pass  # applied in place: the integral and the adapted estimates are kept
        elif self._rebuild is not None:
            # a structural change (type, notch, limits): a new controller, started afresh
            self.controller = self._rebuild(params)
            self.names, self._read = diagnostic_reader(self.controller)
            self._bind_skip()
            self._restart(position_m, reference_m)
        else:
            raise PiezoStageError('controller: a parameter change needs update_params() or a '
                                  'rebuild function')
        self.changes += 1

    def on_position(self, stamp_ns: int, position_m: float, now_s: float) -> Command | None:
        """Take y_k stamped ``stamp_ns`` [ns] (``now_s``: monotonic arrival time [s])."""
        self.watchdog.feed(now_s)
        if self._safe:
            self._safe = False
            self._needs_reset = True
        return self._try(stamp_ns, self._positions, position_m)

    def on_reference(self, stamp_ns: int, reference_m: float,
                     reference_velocity_mps: float) -> Command | None:
        """Take x_d and x_d' [m, m/s] for the sample stamped ``stamp_ns`` [ns]."""
        return self._try(stamp_ns, self._refs, (reference_m, reference_velocity_mps))

    def _try(self, stamp: int, into: dict[int, Any], value: Any) -> Command | None:
        into[stamp] = value
        if len(into) > 100_000:
            # halves that never found their other half (a node that stopped): keep the newest
            for old in list(into)[:50_000]:
                del into[old]
        y = self._positions.get(stamp)
        ref = self._refs.get(stamp)
        if y is None or ref is None:
            return None
        for pending in (self._positions, self._refs):
            while True:
                # halves older than this sample are of no use any more (kept: this one, for a
                # sample sent again)
                first = next(iter(pending))
                if first >= stamp:
                    break
                del pending[first]
        if stamp == self._last_stamp:
            # a sample published again (lockstep resend): its command is already out
            self.duplicates += 1
            return None
        if self._last_stamp is not None and stamp < self._last_stamp:
            self.duplicates += 1
            return None
        xd, vd = ref
        if self._last_stamp is not None and stamp - self._last_stamp > self._gap_ns:
            # real time: samples the servo skipped; a feed-forward keeps its reference index
            gap = round((stamp - self._last_stamp) / self._period_ns) - 1
            self._index += gap
            if self._skip is not None:
                self._skip(gap)
            if self._missed is not None:
                self._missed(gap)
        while self._trajectories and (self._trajectories[0][0] is None
                                      or self._trajectories[0][0] <= stamp):
            self._bind_trajectory(stamp)
        if self._pending is not None:
            self._apply_pending(y, xd)
        if self._needs_reset:
            self._restart(y, xd)
            self._needs_reset = False
        u = self.controller.step(y, xd, vd)
        self._index += 1
        self._last_stamp = stamp
        diagnostics = None
        if self.steps % self.diagnostics_every == 0 and self.names:
            diagnostics = self._read()
        self.steps += 1
        return Command(stamp, u, diagnostics, self.names if diagnostics is not None else None)

    def _bind_trajectory(self, stamp: int) -> None:
        """Bind the oldest requested trajectory before stepping the sample ``stamp``."""
        at, trajectory, line = self._trajectories.pop(0)
        if self._trajectories and self._trajectories[0][0] is not None \
                and self._trajectories[0][0] <= stamp:
            return  # a newer one has started by this sample already
        switch = getattr(self.controller, 'switch', None)
        # the line it has, from a new t = 0 (a start after a stop): the table stays
        restart = getattr(self.controller, 'restart', None) \
            if line is not None and line == self._bound[1] else None
        refused = _learning_refuses(self.controller, trajectory)
        if refused is not None:
            # the trajectory node plays it already: the feed-forward, on the one it has, finds
            # the reference mismatched and leaves each sample to the feedback
            if self._on_refused is not None:
                self._on_refused(f'feed-forward: the new trajectory cannot be learned '
                                 f'({refused}); feedback alone until one it can take')
            return
        if restart is not None:
            restart()
        elif switch is not None:
            switch(trajectory)
        self._bound = (trajectory, line)
        if self._on_bound is not None:
            self._on_bound(trajectory)
        # a restart goes on from the new trajectory's t = 0, or as far into it as the samples
        # already stepped with it (an announcement that came late)
        late = 0 if at is None else round((stamp - at) / self._period_ns)
        self._index = late
        if late and self._skip is not None:
            self._skip(late)

    def on_check(self, now_s: float) -> Command | None:
        """
        Real time: return the safe command while positions have stopped, else None.

        After the silence the controller is reset from the first new sample (its history
        belongs to a loop that was interrupted).
        """
        if self.lockstep or not self.watchdog.expired(now_s):
            return None
        self._safe = True
        self.safe_commands += 1
        return Command(-1, self.safe_voltage_v, None)

    def stats(self) -> dict[str, int]:
        """Return the counters."""
        return {'steps': self.steps, 'duplicates': self.duplicates,
                'safe_commands': self.safe_commands, 'watchdog_trips': self.watchdog.trips,
                'changes': self.changes}


class Gate:
    """
    Whether anyone listens on a topic, looked at every ``every`` calls only.

    Serializing a message for nobody costs a noticeable part of a sample, and asking the
    middleware for the subscription count costs about as much; at 10 kHz once every 1000
    samples (0.1 s) is often enough to notice a recorder that joined.

    Parameters
    ----------
    count : callable
        Returns the number of matched subscriptions now.
    every : int
        Calls between two looks.

    """

    def __init__(self, count: Callable[[], int], every: int = 1000) -> None:
        self._count = count
        self._every = max(1, every)
        self._calls = 0
        self._open = True

    def __call__(self) -> bool:
        """Return whether to publish."""
        if self._calls % self._every == 0:
            self._open = self._count() > 0
        self._calls += 1
        return self._open
