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
Following joint-trajectory goals sample by sample: the bookkeeping of an action server, no ROS.

:class:`GoalFollower` owns the reference of every axis and the goal being followed. It is
stepped with the loop's time and the measured positions; it holds no wall time and no thread,
so the same calls give the same samples offline, in lockstep and in the real-time servo.

- :meth:`~GoalFollower.accept` checks a goal
  (:func:`~piezo_stage_ros.core.loop.goals.validate_goal`) and, if it may run, starts it from
  the present reference (position, velocity and acceleration: no jump). A goal that was
  running ends CANCELED with ``INVALID_GOAL`` and joint_trajectory_controller's words
  ("Current goal cancelled due to new incoming action.").
- :meth:`~GoalFollower.cancel` brings the reference to rest with a quintic from the present
  state whose acceleration stays within ``stop_acceleration_mps2``; the goal ends CANCELED
  (``SUCCESSFUL``) once the axes are at rest.
- :meth:`~GoalFollower.step` checks the path tolerance on every sample before the last point
  (``PATH_TOLERANCE_VIOLATED``: the reference then stops as on a cancel), the goal tolerance
  after it: ``SUCCESSFUL`` once every axis has been inside it for ``settle_s``,
  ``GOAL_TOLERANCE_VIOLATED`` if that has not happened ``goal_time_tolerance`` after the last
  point (0: no time limit, as in joint_trajectory_controller). Feedback (desired, actual,
  error) comes every ``feedback_period_s``.

Only positions are measured, so velocity and acceleration tolerances are not checked; a goal
that sets them runs with its position tolerances. After a goal the last position is held.

:class:`GoalTrajectory` presents one axis of the follower's reference as a trajectory
(:class:`~piezo_stage_ros.core.loop.trajectories.TrajectoryBase`), for the loop and a
feed-forward that reads the reference ahead; :func:`run_goals` is the offline loop with goals
and cancels at given times, in the order of :mod:`piezo_stage_ros.core.loop.closed_loop`.

A stage of several axes follows its goals in lockstep: one follower for every axis (its joints
``stage_x`` ...), each axis interpolated from its own present reference and checked against its
own limits. :class:`AxesGoalReference` gives every axis' reference sample by sample (the scan's
until a goal takes the axes over, :func:`take_over_state`), for the trajectory node and
:func:`run_axes_goals`, the offline loop of :mod:`piezo_stage_ros.core.loop.axes` with goals.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import enum
import math
from typing import Any, Sequence

import numpy as np
from numpy.typing import ArrayLike
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.interfaces import Controller, Trajectory
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.control.axes import AxesController
from piezo_stage_ros.core.loop.axes import axes_references
from piezo_stage_ros.core.loop.closed_loop import Plant
from piezo_stage_ros.core.loop.goals import (
    AxisLimits,
    finish,
    GoalVerdict,
    JointTolerance,
    JointTrajectoryGoal,
    ResultCode,
    Steps,
    validate_goal,
    validation_steps,
)
from piezo_stage_ros.core.loop.splines import Spline
from piezo_stage_ros.core.loop.trajectories import TrajectoryBase
from piezo_stage_ros.core.model.axes import AxesStage

__all__ = ['AxesGoalReference', 'Feedback', 'FollowParams', 'GoalFollower', 'GoalLedger',
           'GoalResult', 'GoalStatus', 'GoalsStatus', 'GoalTrajectory', 'binds_goals',
           'goal_views', 'goals_status',
           'PreparedGoal', 'run_axes_goals', 'run_goals', 'SplineTrajectory', 'take_over_state']

#: How many times a stop's duration grows by 1.25 to keep to the acceleration (1.25^40: 7500x).
_STOP_TRIES = 40

#: joint_trajectory_controller's result string of a goal a new one preempted.
PREEMPTED = 'Current goal cancelled due to new incoming action.'


class GoalStatus(enum.IntEnum):
    """Terminal states of ``action_msgs/GoalStatus``."""

    SUCCEEDED = 4
    CANCELED = 5
    ABORTED = 6


@dataclass(frozen=True)
class GoalResult:
    """How a goal ended: status, ``FollowJointTrajectory`` error code, reason, when [s]."""

    goal_id: int
    status: GoalStatus
    code: ResultCode
    reason: str
    time_s: float


@dataclass(frozen=True)
class Feedback:
    """FollowJointTrajectory feedback: desired, actual and their difference per axis [m]."""

    goal_id: int
    time_s: float
    desired_m: FloatArray
    desired_velocity_mps: FloatArray
    actual_m: FloatArray
    error_m: FloatArray


@dataclass(frozen=True)
class FollowParams:
    """
    How goals are followed; defaults as joint_trajectory_controller's where it has one.

    Attributes
    ----------
    sample_time_s : float
        Loop sample period [s].
    feedback_period_s : float
        Time between feedbacks [s] (0.02: 50 Hz).
    path_position_m : float
        Default path tolerance [m]; 0 checks nothing.
    goal_position_m : float
        Default goal tolerance [m]; 0 checks nothing (success at the last point).
    goal_time_s : float
        Default goal_time_tolerance [s]; 0 waits without limit.
    settle_s : float
        How long every axis must stay inside the goal tolerance before success [s].
    stop_acceleration_mps2 : float
        Largest deceleration of a cancel or a path violation [m/s^2]; 1 stops the fastest
        point-to-point moves of the stage (mm/s) within a few milliseconds and micrometres,
        gently enough that the controller follows the stop about as closely as the move.
    partial_joints : bool
        Take goals that name some of the joints (the others hold the present reference's
        position), as joint_trajectory_controller with ``allow_partial_joints_goal``; False
        refuses them (``INVALID_JOINTS``).

    """

    sample_time_s: float = 1e-4
    feedback_period_s: float = 0.02
    path_position_m: float = 0.0
    goal_position_m: float = 0.0
    goal_time_s: float = 0.0
    settle_s: float = 1e-3
    stop_acceleration_mps2: float = 1.0
    partial_joints: bool = False

    def __post_init__(self) -> None:
        for name in ('sample_time_s', 'feedback_period_s', 'stop_acceleration_mps2'):
            value = getattr(self, name)
            if not (value > 0.0 and math.isfinite(value)):
                raise ParameterError(name, value, '(0, inf)')
        for name in ('path_position_m', 'goal_position_m', 'goal_time_s', 'settle_s'):
            value = getattr(self, name)
            if not (value >= 0.0 and math.isfinite(value)):
                raise ParameterError(name, value, '[0, inf)')


#: Position [m], velocity [m/s] and acceleration [m/s^2] of every axis at one time.
State = tuple[FloatArray, FloatArray, FloatArray]


@dataclass(frozen=True)
class PreparedGoal:
    """A checked goal with its spline, for :meth:`GoalFollower.start` at ``time_s``."""

    goal: JointTrajectoryGoal
    spline: Spline
    time_s: float
    version: int
    tracked: bool


class _Phase(enum.Enum):
    HOLD = 'hold'
    MOVING = 'moving'
    SETTLING = 'settling'
    STOPPING = 'stopping'


def _tolerance(given: Sequence[JointTolerance], joints: Sequence[str], default: float
               ) -> list[float]:
    """Return the position tolerance of each joint: inf where unchecked."""
    out = [default if default > 0.0 else math.inf] * len(joints)
    for tol in given:
        k = list(joints).index(tol.name)
        if tol.position_m < 0.0:
            out[k] = math.inf
        elif tol.position_m > 0.0:
            out[k] = tol.position_m
    return out


class GoalFollower:
    """
    The reference of N axes and the goal it follows, stepped once a sample.

    Parameters
    ----------
    joints : sequence of str
        The stage's joints (axes), in the order of every array here.
    limits : sequence of AxisLimits
        What each axis can follow.
    initial_position_m : array_like
        Where the reference rests at the start [m].
    params : FollowParams
        Tolerance defaults, feedback rate, stop deceleration.

    """

    def __init__(self, joints: Sequence[str], limits: Sequence[AxisLimits],
                 initial_position_m: ArrayLike, params: FollowParams | None = None) -> None:
        self.joints = tuple(joints)
        self.limits = tuple(limits)
        self.params = params if params is not None else FollowParams()
        if len(self.limits) != len(self.joints):
            raise ParameterError('limits', len(self.limits), f'{len(self.joints)}, one per joint')
        x0 = np.asarray(initial_position_m, dtype=np.float64).reshape(len(self.joints))
        self._spline = self._rest(0.0, x0)
        self._phase = _Phase.HOLD
        self._goal_id = 0
        self._tracked = False
        self._path_tol: list[float] = [math.inf] * len(self.joints)
        self._goal_tol: list[float] = [math.inf] * len(self.joints)
        self._unchecked = True
        self._goal_time_s = 0.0
        self._settled_s = 0.0
        self._next_feedback_s = 0.0
        #: bumped whenever the reference changes (a reader ahead must evaluate it again)
        self.version = 0
        self.results: list[GoalResult] = []

    # -- the reference -------------------------------------------------------------------

    @property
    def phase(self) -> str:
        """Return 'hold', 'moving', 'settling' (after the last point) or 'stopping'."""
        return self._phase.value

    @property
    def active_goal(self) -> int | None:
        """Return the id of the goal being followed, or None."""
        return self._goal_id if self._tracked else None

    @property
    def spline(self) -> Spline:
        """Return the present reference: a spline that holds its end."""
        return self._spline

    def reference(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """
        Return the reference at these times, as it stands (no event after now is known).

        Parameters
        ----------
        time_s : array_like
            Loop times [s].

        Returns
        -------
        position_m, velocity_mps, acceleration_mps2 : ndarray
            Shape ``time_s.shape + (axes,)``.

        """
        return self._spline.sample(time_s)

    def _state(self, time_s: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        x, v, a = self._spline.sample(np.array([time_s]))
        return x[0], v[0], a[0]

    def _rest(self, time_s: float, position_m: FloatArray) -> Spline:
        zero = np.zeros_like(position_m)
        return Spline(time_s, (position_m, zero, zero), [time_s + self.params.sample_time_s],
                      position_m[None, :])

    def _stop(self, time_s: float) -> Spline:
        """
        Return a quintic from the present state to rest, within the stop acceleration.

        The stop starts with the present acceleration (no step in it), so its bound is the
        larger of ``stop_acceleration_mps2`` and that; the duration grows until the sampled
        acceleration keeps to it (a bounded number of times: a stop clipped at the end of the
        travel may not get there, and then takes the longest).
        """
        x0, v0, a0 = self._state(time_s)
        dt = self.params.sample_time_s
        if not (np.any(v0) or np.any(a0)):
            return self._rest(time_s, x0)
        limit = max(self.params.stop_acceleration_mps2, float(np.max(np.abs(a0))))
        duration = max(dt, 1.875 * float(np.max(np.abs(v0))) / limit)
        lo = np.array([lim.position_min_m for lim in self.limits])
        hi = np.array([lim.position_max_m for lim in self.limits])
        zero = np.zeros_like(x0)
        for _ in range(_STOP_TRIES):
            x1 = np.clip(x0 + 0.5 * v0 * duration + a0 * duration ** 2 / 12.0, lo, hi)
            spline = Spline(time_s, (x0, v0, a0), [time_s + duration], x1[None, :], zero[None, :],
                            zero[None, :])
            grid = time_s + np.arange(1, int(math.ceil(duration / dt)) + 1) * dt
            _, _, acc = spline.sample(grid)
            if float(np.max(np.abs(acc))) <= limit:
                break
            duration *= 1.25
        return spline

    def _replace(self, spline: Spline) -> None:
        self._spline = spline
        self.version += 1

    def _finish(self, time_s: float, status: GoalStatus, code: ResultCode, reason: str
                ) -> GoalResult | None:
        if not self._tracked:
            return None
        result = GoalResult(self._goal_id, status, code, reason, time_s)
        self.results.append(result)
        self._tracked = False
        return result

    # -- commands ------------------------------------------------------------------------

    def check(self, goal: JointTrajectoryGoal, time_s: float, origin_s: float | None = None,
              start_state: State | None = None) -> GoalVerdict:
        """
        Return whether ``goal`` may start at ``time_s`` from the present reference.

        ``start_state``: the reference's position, velocity and acceleration of every axis at
        ``time_s`` when another trajectory plays it (default: the follower's own).
        """
        return validate_goal(goal, self.joints, self.limits, start_s=time_s,
                             start_state=self._state(time_s) if start_state is None
                             else start_state,
                             sample_time_s=self.params.sample_time_s, origin_s=origin_s,
                             partial_joints=self.params.partial_joints)

    def prepare(self, goal: JointTrajectoryGoal, time_s: float, *, tracked: bool = True,
                origin_s: float | None = None, start_state: State | None = None
                ) -> tuple[GoalVerdict, PreparedGoal | None]:
        """
        Check a goal and build its spline for a start at ``time_s``, changing nothing.

        The expensive half of :meth:`accept` (the check runs over every sample of the
        trajectory, the spline is built over every point): a real-time loop does it outside
        its sample, for a time a little ahead (the reference until then is known), and
        :meth:`start` takes it up at that sample.

        Parameters
        ----------
        goal, time_s, tracked, origin_s
            As :meth:`accept`.
        start_state : tuple of ndarray, optional
            Position, velocity and acceleration of every axis at ``time_s`` of another
            trajectory the goal takes the reference over from (nothing here is changed: the
            loop's thread seeds the follower with it when it starts the goal, :meth:`seed`).

        Returns
        -------
        verdict : GoalVerdict
            SUCCESSFUL, or the code and the reason of the refusal.
        prepared : PreparedGoal or None
            The goal ready to start at ``time_s``; None when refused.

        """
        return finish(self.preparing(goal, time_s, tracked=tracked, origin_s=origin_s,
                                     start_state=start_state))

    def preparing(self, goal: JointTrajectoryGoal, time_s: float, *, tracked: bool = True,
                  origin_s: float | None = None, start_state: State | None = None,
                  points_per_step: int = 0, samples_per_step: int = 0
                  ) -> Steps[tuple[GoalVerdict, PreparedGoal | None]]:
        """
        Do :meth:`prepare` a slice at a time: the same verdict and the same spline.

        Each ``next`` reads ``points_per_step`` of the goal's points or checks
        ``samples_per_step`` of its samples (0: all at once), for a real-time loop that does
        the check in the idle time of its own samples; the return value is :meth:`prepare`'s.
        The reference is read at the first slice.
        """
        # the version before the reference is read: a change made meanwhile (by the loop's
        # thread) makes start() refuse the goal instead of starting it from a stale state
        version = self.version
        state = self._state(time_s) if start_state is None else start_state
        verdict, spline = yield from validation_steps(
            goal, self.joints, self.limits, start_s=time_s, start_state=state,
            sample_time_s=self.params.sample_time_s, origin_s=origin_s,
            partial_joints=self.params.partial_joints, points_per_step=points_per_step,
            samples_per_step=samples_per_step)
        if not verdict.accepted:
            return verdict, None
        assert spline is not None
        return verdict, PreparedGoal(goal, spline, time_s, version, tracked)

    def start(self, prepared: PreparedGoal, time_s: float) -> int:
        """
        Follow a prepared goal from this sample on; the running goal is preempted.

        Parameters
        ----------
        prepared : PreparedGoal
            From :meth:`prepare`.
        time_s : float
            Loop time of this sample [s]: the one the goal was prepared for.

        Returns
        -------
        int
            The id of the goal; 0 if the reference changed since it was prepared or the
            sample is not the one it was prepared for (prepare it again: starting it would
            make the reference jump).

        """
        p = self.params
        if prepared.version != self.version or abs(time_s - prepared.time_s) > 0.5 * \
                p.sample_time_s:
            return 0
        goal = prepared.goal
        self._finish(time_s, GoalStatus.CANCELED, ResultCode.INVALID_GOAL, PREEMPTED)
        self._replace(prepared.spline)
        self._goal_id += 1
        self._tracked = prepared.tracked
        self._phase = _Phase.MOVING
        self._path_tol = _tolerance(goal.path_tolerance, self.joints, p.path_position_m)
        self._goal_tol = _tolerance(goal.goal_tolerance, self.joints, p.goal_position_m)
        self._unchecked = all(math.isinf(tol) for tol in self._goal_tol)
        self._goal_time_s = goal.goal_time_tolerance_s or p.goal_time_s
        self._settled_s = 0.0
        self._next_feedback_s = time_s
        return self._goal_id

    def accept(self, goal: JointTrajectoryGoal, time_s: float, *, tracked: bool = True,
               origin_s: float | None = None, start_state: State | None = None
               ) -> tuple[GoalVerdict, int]:
        """
        Check a goal and, if it may run, follow it from ``time_s`` on.

        Parameters
        ----------
        goal : JointTrajectoryGoal
            The goal (or a JointTrajectory message, ``tracked=False``).
        time_s : float
            Loop time of the first sample that follows it [s].
        tracked : bool
            True for an action goal (results and feedback), False for a topic message.
        origin_s : float, optional
            Loop time ``time_from_start`` counts from (a header stamp that is not zero);
            default ``time_s``.
        start_state : tuple of ndarray, optional
            Position, velocity and acceleration of every axis at ``time_s`` of another
            trajectory the goal takes the reference over from (:func:`take_over_state`): the
            follower is seeded with it (:meth:`seed`) if the goal runs.

        Returns
        -------
        verdict : GoalVerdict
            SUCCESSFUL if it runs, else the code and the reason (nothing changes).
        goal_id : int
            The id of the new goal (its results and feedback carry it); 0 when refused.

        """
        verdict, prepared = self.prepare(goal, time_s, tracked=tracked, origin_s=origin_s,
                                         start_state=start_state)
        if prepared is None:
            return verdict, 0
        if start_state is not None:
            self.seed(time_s, *start_state)
            prepared = dataclasses.replace(prepared, version=self.version)
        return verdict, self.start(prepared, time_s)

    def seed(self, time_s: float, position_m: ArrayLike, velocity_mps: ArrayLike,
             acceleration_mps2: ArrayLike) -> None:
        """
        Take the reference over from another trajectory whose state at ``time_s`` is given.

        A goal prepared or accepted at ``time_s`` then starts from that state (position [m],
        velocity [m/s], acceleration [m/s^2] of every axis): no jump where it takes over. Only
        while no goal is followed; after ``time_s`` the reference comes to rest within a
        sample (a goal is meant to take over there).
        """
        self.take_seed(self.seed_spline(time_s, position_m, velocity_mps, acceleration_mps2))

    def seed_spline(self, time_s: float, position_m: ArrayLike, velocity_mps: ArrayLike,
                    acceleration_mps2: ArrayLike) -> Spline:
        """Return the reference :meth:`seed` takes over, changing nothing (built ahead)."""
        n = len(self.joints)
        x, v, a = (np.asarray(s, dtype=np.float64).reshape(n)
                   for s in (position_m, velocity_mps, acceleration_mps2))
        zero = np.zeros((1, n))
        return Spline(time_s, (x, v, a), [time_s + self.params.sample_time_s], x[None, :],
                      zero, zero)

    def take_seed(self, spline: Spline) -> None:
        """Take over the reference :meth:`seed_spline` built: :meth:`seed` in two halves."""
        self._replace(spline)
        self._phase = _Phase.HOLD

    def cancel(self, time_s: float) -> None:
        """Bring the reference to rest from ``time_s``; the goal ends once it is at rest."""
        if self._phase in (_Phase.MOVING, _Phase.SETTLING):
            self._replace(self._stop(time_s))
            self._phase = _Phase.STOPPING

    def hold(self, time_s: float) -> GoalResult | None:
        """Stop at once where the reference is (a stop first if it moves); end the goal."""
        self._replace(self._stop(time_s))
        self._phase = _Phase.STOPPING
        return self._finish(time_s, GoalStatus.CANCELED, ResultCode.INVALID_GOAL,
                            'Current goal cancelled during deactivate transition.')

    # -- one sample ----------------------------------------------------------------------

    def step(self, time_s: float, measured_m: Sequence[float],
             desired_m: Sequence[float] | None = None,
             desired_velocity_mps: Sequence[float] | None = None
             ) -> tuple[GoalResult | None, Feedback | None]:
        """
        Account for one sample: the reference at ``time_s`` against the measured positions.

        Parameters
        ----------
        time_s : float
            Loop time of the sample [s].
        measured_m : sequence of float
            Measured position of every axis at that sample [m].
        desired_m : sequence of float, optional
            The reference of every axis at that sample, when the caller has it already (the
            loop evaluated it in a block): saves evaluating the spline again.
        desired_velocity_mps : sequence of float, optional
            With ``desired_m``, the reference's velocity at that sample, when both were
            evaluated from the present reference (:attr:`spline`): a feedback takes them
            instead of evaluating the spline again.

        Returns
        -------
        result : GoalResult or None
            The goal that ended at this sample, if any.
        feedback : Feedback or None
            Feedback, when one is due.

        Notes
        -----
        Plain floats per axis: a handful of axes cost less this way than as arrays, which
        matters in the real-time servo's sample.

        """
        phase = self._phase
        if phase is _Phase.HOLD:
            return None, None
        spline = self._spline
        if desired_m is None:
            desired_m = spline.sample(np.array([time_s]))[0][0].tolist()
        error = [float(d) - float(y) for d, y in zip(desired_m, measured_m)]
        result: GoalResult | None = None
        end_s = spline.end_s
        if phase is _Phase.STOPPING:
            if time_s >= end_s:
                self._phase = _Phase.HOLD
                result = self._finish(time_s, GoalStatus.CANCELED, ResultCode.SUCCESSFUL,
                                      'cancelled: the stage decelerated to a hold at '
                                      f'{list(desired_m)} m')
        elif time_s < end_s:
            for k, (e, tol) in enumerate(zip(error, self._path_tol)):
                if abs(e) > tol:
                    self._replace(self._stop(time_s))
                    self._phase = _Phase.STOPPING
                    result = self._finish(
                        time_s, GoalStatus.ABORTED, ResultCode.PATH_TOLERANCE_VIOLATED,
                        f'joint {self.joints[k]!r}: path error {e:.4g} m at {time_s:.6g} s; '
                        f'allowed: |error| <= {tol:.4g} m')
                    break
        else:
            self._phase = _Phase.SETTLING
            inside = all(abs(e) <= tol for e, tol in zip(error, self._goal_tol))
            dt = self.params.sample_time_s
            self._settled_s = self._settled_s + dt if inside else 0.0
            if self._unchecked or self._settled_s >= self.params.settle_s - 0.5 * dt:
                self._phase = _Phase.HOLD
                result = self._finish(time_s, GoalStatus.SUCCEEDED, ResultCode.SUCCESSFUL, '')
            elif self._goal_time_s > 0.0 and time_s - end_s > self._goal_time_s + 0.5 * dt:
                self._phase = _Phase.HOLD
                k = max(range(len(error)), key=lambda i: abs(error[i]) - self._goal_tol[i])
                result = self._finish(
                    time_s, GoalStatus.ABORTED, ResultCode.GOAL_TOLERANCE_VIOLATED,
                    f'joint {self.joints[k]!r}: error {error[k]:.4g} m '
                    f'{time_s - end_s:.6g} s after the last point; allowed: |error| <= '
                    f'{self._goal_tol[k]:.4g} m within goal_time_tolerance '
                    f'{self._goal_time_s:g} s')
        feedback: Feedback | None = None
        if self._tracked and time_s >= self._next_feedback_s - 1e-12:
            if desired_velocity_mps is None:
                x, v, _ = spline.sample(np.array([time_s]))
            else:
                x = np.asarray([desired_m], dtype=np.float64)
                v = np.asarray([desired_velocity_mps], dtype=np.float64)
            feedback = Feedback(self._goal_id, time_s, x[0], v[0],
                                np.asarray(measured_m, dtype=np.float64), np.asarray(error))
            self._next_feedback_s += self.params.feedback_period_s
        return result, feedback


#: ``diagnostic_msgs/DiagnosticStatus`` levels.
OK, WARN = 0, 1

#: Results after which the goals' status warns for a while: the stage did not follow.
_WARNING_CODES = (ResultCode.PATH_TOLERANCE_VIOLATED, ResultCode.GOAL_TOLERANCE_VIOLATED)


@dataclass(frozen=True)
class GoalsStatus:
    """
    The goals' part of the stage's status, as data (a DiagnosticStatus is built from it).

    Attributes
    ----------
    level : int
        0 OK, 1 WARN (``diagnostic_msgs/DiagnosticStatus`` levels).
    message : str
        One line for the status.
    values : tuple of (str, str)
        Key-value pairs: phase, active goal, last result code and text, refused count.

    """

    level: int
    message: str
    values: tuple[tuple[str, str], ...]


def goals_status(phase: str, active_goal: int | None, last: GoalResult | None, refused: int,
                 now_s: float, warn_for_s: float = 10.0) -> GoalsStatus:
    """
    Return the goals' status: WARN for ``warn_for_s`` [s] after a tolerance was violated.

    Parameters
    ----------
    phase : str
        The follower's phase ('hold', 'moving', 'settling', 'stopping').
    active_goal : int or None
        The goal being followed.
    last : GoalResult or None
        How the last goal ended.
    refused : int
        Goals refused so far.
    now_s : float
        Loop time now [s] (the results' time base).
    warn_for_s : float
        How long a violated tolerance keeps the level at WARN [s].

    """
    level, message = OK, f'{phase}'
    if active_goal is not None:
        message = f'{phase}: goal {active_goal}'
    if last is not None and last.code in _WARNING_CODES and now_s - last.time_s <= warn_for_s:
        level = WARN
        message = f'goal {last.goal_id} {last.code.name} {now_s - last.time_s:.3g} s ago'
    values = (('phase', phase),
              ('active_goal', '' if active_goal is None else str(active_goal)),
              ('last_result_code', '' if last is None else f'{int(last.code)} {last.code.name}'),
              ('last_result_text', '' if last is None else last.reason),
              ('refused_goals', str(int(refused))))
    return GoalsStatus(level, message, values)


class GoalLedger:
    """
    The goals' bookkeeping seen from their events, wherever the follower runs.

    Takes the events of :class:`~piezo_stage_ros.nodes.logic.TrajectoryLogic` (verdicts,
    results) in order: the active goal, the last result, the refusals; :meth:`status` gives
    :func:`goals_status`.
    """

    def __init__(self) -> None:
        self.active_goal: int | None = None
        self.last: GoalResult | None = None
        self.refused = 0

    def take(self, event: tuple[Any, ...]) -> None:
        """Account one event: ``('verdict', token, verdict, goal_id)`` or ``('result', r)``."""
        if event[0] == 'verdict':
            if event[3]:
                self.active_goal = int(event[3])
            else:
                self.refused += 1
        elif event[0] == 'result':
            result: GoalResult = event[1]
            self.last = result
            if self.active_goal == result.goal_id:
                self.active_goal = None

    def status(self, now_s: float, phase: str | None = None) -> GoalsStatus:
        """Return the goals' status at loop time ``now_s`` [s]; ``phase`` when known."""
        if phase is None:
            phase = 'hold' if self.active_goal is None else 'moving'
        return goals_status(phase, self.active_goal, self.last, self.refused, now_s)


class GoalTrajectory(TrajectoryBase):
    """
    One axis of a follower's reference as a trajectory (x_d, dx_d/dt), evaluated vectorised.

    Parameters
    ----------
    follower : GoalFollower
        The follower.
    axis : int
        Which axis.

    """

    kind = 'goal'

    def __init__(self, follower: GoalFollower, axis: int = 0) -> None:
        self._follower = follower
        self._axis = axis

    @property
    def axis(self) -> int:
        """Return which axis of the follower this is."""
        return self._axis

    def snapshot(self) -> SplineTrajectory:
        """Return the reference as it stands now, as a trajectory of its own."""
        return SplineTrajectory(self._follower.spline, self._axis)

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        return _axis_of(self._follower.reference(time_s), self._axis)


class SplineTrajectory(TrajectoryBase):
    """
    One axis of a goal's spline as a trajectory: a follower's reference as it stood once.

    What a process that does not follow the goals binds (the controller node told of a goal
    by announcement): evaluated as :class:`GoalTrajectory` evaluates the same spline.

    Parameters
    ----------
    spline : Spline
        The reference.
    axis : int
        Which axis.

    """

    kind = 'goal'

    def __init__(self, spline: Spline, axis: int = 0) -> None:
        self.spline = spline
        self.axis = axis

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        return _axis_of(self.spline.sample(time_s), self.axis)


def _axis_of(sampled: tuple[FloatArray, FloatArray, FloatArray], axis: int
             ) -> tuple[FloatArray, FloatArray]:
    x, v, _ = sampled
    return np.ascontiguousarray(x[..., axis]), np.ascontiguousarray(v[..., axis])


@dataclass
class GoalRun:
    """
    The samples of a run with goals and what happened to the goals.

    :func:`run_goals`: arrays of shape (samples,); :func:`run_axes_goals`: (samples, axes),
    with the true positions.
    """

    time_s: FloatArray
    position_m: FloatArray
    reference_m: FloatArray
    command_v: FloatArray
    results: list[GoalResult]
    feedback: list[Feedback]
    verdicts: list[tuple[float, GoalVerdict, int]]
    true_position_m: FloatArray | None = None


def run_goals(stage: Plant, controller: Controller, follower: GoalFollower,
              events: Sequence[tuple[float, Any]], *, duration_s: float) -> GoalRun:
    """
    Run one axis's closed loop with goals and cancels at given loop times.

    Parameters
    ----------
    stage : Plant
        The stage, reset here to the follower's initial reference.
    controller : Controller
        The controller, reset from y_0 and x_d(0); one with ``bind`` (a feed-forward) is bound
        to the follower's reference (:class:`GoalTrajectory`), which it reads ahead, and bound
        again whenever a goal or a cancel changes that reference (what it read ahead is stale).
        Binding again restarts the feed-forward's inverse filter: exact from rest, a transient
        when a goal preempts one in motion.
    follower : GoalFollower
        The goals' bookkeeping (one axis).
    events : sequence of (time_s, goal or 'cancel')
        What happens when: a :class:`JointTrajectoryGoal` is accepted (or refused) at the first
        sample at or after its time, ``'cancel'`` cancels.
    duration_s : float
        Simulated time [s].

    Returns
    -------
    GoalRun

    """
    dt = float(stage.sample_time_s)
    total = max(int(round(duration_s / dt)), 1)
    x0 = float(follower.reference(np.zeros(1))[0][0, 0])
    bind = getattr(controller, 'bind', None)
    view = GoalTrajectory(follower)
    if callable(bind):
        bind(view)
    bound = follower.version
    y = float(stage.reset(x0))
    controller.reset(y, x0)
    pending = sorted(events, key=lambda e: e[0])
    t_out = np.arange(total, dtype=np.float64) * dt
    pos = np.empty(total)
    ref = np.empty(total)
    cmd = np.empty(total)
    feedback: list[Feedback] = []
    verdicts: list[tuple[float, GoalVerdict, int]] = []
    j = 0
    for k in range(total):
        t = float(t_out[k])
        while j < len(pending) and pending[j][0] <= t + 0.5 * dt:
            what = pending[j][1]
            if isinstance(what, JointTrajectoryGoal):
                verdict, gid = follower.accept(what, t)
                verdicts.append((t, verdict, gid))
            else:
                follower.cancel(t)
            j += 1
        if callable(bind) and follower.version != bound:
            bind(view)
            bound = follower.version
        x, v, _ = follower.reference(np.array([t]))
        xd = float(x[0, 0])
        u = controller.step(y, xd, float(v[0, 0]))
        pos[k] = y
        ref[k] = xd
        cmd[k] = u
        _, fb = follower.step(t, (y,), (xd,))
        if fb is not None:
            feedback.append(fb)
        y = float(stage.step(u))
    return GoalRun(t_out, pos, ref, cmd, list(follower.results), feedback, verdicts)


def take_over_state(trajectories: Sequence[Trajectory], index: int, sample_time_s: float
                    ) -> State:
    """
    Return what the trajectories play at sample ``index``: the state a goal takes over.

    Parameters
    ----------
    trajectories : sequence of Trajectory
        One per axis, t = 0 at sample 0.
    index : int
        The sample, k T its time.
    sample_time_s : float
        T [s].

    Returns
    -------
    position_m, velocity_mps, acceleration_mps2 : ndarray
        One value per axis: x_d and x_d' as played at the sample, and x_d'' by the central
        difference of x_d' over the samples around it (0 at the first sample).

    """
    t = np.maximum(np.array([index - 1, index, index + 1], dtype=np.float64) * sample_time_s,
                   0.0)
    n = len(trajectories)
    x, v, a = np.zeros(n), np.zeros(n), np.zeros(n)
    for j, trajectory in enumerate(trajectories):
        xs, vs = trajectory.evaluate(t)
        x[j], v[j] = float(xs[1]), float(vs[1])
        a[j] = (float(vs[2]) - float(vs[0])) / (2.0 * sample_time_s) if index > 0 else 0.0
    return x, v, a


class AxesGoalReference:
    """
    Every axis' reference sample by sample: the trajectories' until a goal takes it over.

    The one piece that computes the reference of a stage of several axes with goals, for the
    lockstep trajectory node (:class:`~piezo_stage_ros.nodes.axes_logic.AxesTrajectoryLogic`)
    and the offline runner (:func:`run_axes_goals`): the same floats in both. Evaluated in
    chunks aligned at sample 0, as :func:`~piezo_stage_ros.core.loop.axes.run_axes` evaluates;
    the follower's reference (every axis its :class:`GoalTrajectory`) again whenever it
    changed.

    Parameters
    ----------
    trajectories : sequence of Trajectory
        One per axis: what plays before the first goal.
    follower : GoalFollower or None
        The goals of the stage's axes (None: the trajectories alone).
    sample_time_s : float
        T [s].
    chunk : int
        Samples evaluated at a time.
    names : sequence of str
        The axes, for messages.

    """

    def __init__(self, trajectories: Sequence[Trajectory], follower: GoalFollower | None,
                 sample_time_s: float, chunk: int, names: Sequence[str] = ()) -> None:
        self.trajectories = tuple(trajectories)
        self.follower = follower
        self.sample_time_s = float(sample_time_s)
        self.chunk = max(int(chunk), 1)
        self.names = tuple(names)
        self.views = () if follower is None else tuple(
            GoalTrajectory(follower, j) for j in range(len(self.trajectories)))
        #: Whether a goal took the reference over (it stays the follower's from then on).
        self.taken = False
        self._source: tuple[bool, int] = (False, -1)
        self._chunk_index = -1
        self._ref: list[list[float]] = []
        self._vel: list[list[float]] = []

    def state(self, index: int) -> State:
        """Return the state a goal starts from at sample ``index``, if it takes over there."""
        return take_over_state(self.trajectories, index, self.sample_time_s)

    def at(self, index: int) -> tuple[list[float], list[float]]:
        """Return every axis' x_d [m] and x_d' [m/s] at sample ``index``."""
        source = (self.taken, self.follower.version if self.taken and self.follower is not None
                  else -1)
        chunk = index // self.chunk
        if chunk != self._chunk_index or source != self._source:
            ref, vel = axes_references(self.views if self.taken else self.trajectories,
                                       chunk * self.chunk, self.chunk, self.sample_time_s,
                                       self.names)
            self._ref, self._vel = ref.tolist(), vel.tolist()
            self._chunk_index, self._source = chunk, source
        i = index - chunk * self.chunk
        return self._ref[i], self._vel[i]


def goal_views(spline: Spline, axes: int) -> list[Trajectory]:
    """Return every axis of a goals' spline as a trajectory, for the axes' feed-forwards."""
    return [SplineTrajectory(spline, j) for j in range(axes)]


def binds_goals(controller: AxesController) -> bool:
    """
    Return whether the axes' feed-forwards are bound to the goals' reference as it changes.

    True when some axis has a feed-forward (``bind``) and none of them learns or has a period
    of its own (``feedforward.period_s``): a goal's reference has no period, which a learning
    feed-forward needs and a fixed period would misread. Otherwise the feed-forwards stay
    bound to the scan, find a goal's reference changed and leave its samples to the feedback.
    """
    bound = False
    for c in controller.controllers:
        if not callable(getattr(c, 'bind', None)):
            continue
        params = getattr(c, 'params', None)
        if getattr(params, 'learning', False) or getattr(params, 'period_s', 0.0):
            return False
        bound = True
    return bound


def run_axes_goals(stage: AxesStage, controller: AxesController,
                   trajectories: Sequence[Trajectory], follower: GoalFollower,
                   events: Sequence[tuple[float, Any]], *, duration_s: float,
                   chunk_s: float = 1.0) -> GoalRun:
    """
    Run the closed loop of a stage of several axes with goals and cancels at given loop times.

    The offline twin of the lockstep nodes with goals: the trajectories play (as in
    :func:`~piezo_stage_ros.core.loop.axes.run_axes`) until a goal takes every axis over
    from their state at its sample (:func:`take_over_state`). The controllers are bound to
    the goals' reference (every axis' :class:`SplineTrajectory` of the follower's spline as
    it stands) before the first sample at which it changed (a goal, a preemption, a cancel, a
    violated path tolerance) when :func:`binds_goals`; otherwise they stay bound to the
    trajectories, and a feed-forward that finds the reference changed leaves the sample to
    the feedback.

    Parameters
    ----------
    stage : AxesStage
        The stage (reset here to its rest positions).
    controller : AxesController
        Every axis' controller (bound to ``trajectories`` and reset here from y_0, x_d(0)).
    trajectories : sequence of Trajectory
        One per axis, t = 0 at the first sample.
    follower : GoalFollower
        The goals' bookkeeping, its joints the stage's axes.
    events : sequence of (time_s, goal or 'cancel')
        As :func:`run_goals`.
    duration_s : float
        Simulated time [s].
    chunk_s : float
        The references are evaluated per chunk of this length [s].

    Returns
    -------
    GoalRun
        Arrays of shape (samples, axes), the true positions included.

    Raises
    ------
    ParameterError
        A trajectory, joint or controller count that is not one per axis (named with its count).

    """
    n = stage.n
    for name, count in (('trajectories', len(trajectories)),
                        ('follower.joints', len(follower.joints)), ('controller', controller.n)):
        if count != n:
            raise ParameterError(name, count, f'{n}, one per axis {list(stage.names)}')
    dt = float(stage.sample_time_s)
    total = max(int(round(duration_s / dt)), 1)
    reference = AxesGoalReference(trajectories, follower, dt,
                                  max(int(round(chunk_s / dt)), 1), stage.names)
    controller.bind(trajectories)
    rebind = binds_goals(controller)
    bound = -1
    y = stage.reset(None)
    ref, vel = reference.at(0)
    controller.reset(list(y), list(ref))
    pending = sorted(events, key=lambda e: e[0])
    pos, true, refs, cmd = (np.empty((total, n)) for _ in range(4))
    feedback: list[Feedback] = []
    verdicts: list[tuple[float, GoalVerdict, int]] = []
    j = 0
    for k in range(total):
        t = k * dt
        while j < len(pending) and pending[j][0] <= t + 0.5 * dt:
            what = pending[j][1]
            if isinstance(what, JointTrajectoryGoal):
                verdict, gid = follower.accept(
                    what, t, start_state=None if reference.taken else reference.state(k))
                reference.taken = reference.taken or gid != 0
                verdicts.append((t, verdict, gid))
            elif reference.taken:
                follower.cancel(t)
            j += 1
        if rebind and reference.taken and follower.version != bound:
            controller.bind(goal_views(follower.spline, n))
            bound = follower.version
        ref, vel = reference.at(k)
        u = controller.step(list(y), list(ref), list(vel))
        pos[k], true[k], refs[k], cmd[k] = y, stage.read_positions_m(), ref, u
        if reference.taken:
            _, fb = follower.step(t, y, ref)
            if fb is not None:
                feedback.append(fb)
        y = stage.step(u)
    return GoalRun(np.arange(total, dtype=np.float64) * dt, pos, refs, cmd,
                   list(follower.results), feedback, verdicts, true)
