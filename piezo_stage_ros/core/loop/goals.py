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
Joint-trajectory goals without ROS: the message content, the stage's limits, the checks.

:class:`JointTrajectoryGoal` holds what a ``control_msgs/action/FollowJointTrajectory`` goal
carries (``trajectory_msgs/JointTrajectory``: joint names and points with ``time_from_start``,
positions, optional velocities and accelerations; path and goal tolerances per joint;
``goal_time_tolerance``), in SI units, for any number of joints (the stage's axes).

:func:`validate_goal` decides before acceptance, as joint_trajectory_controller does, and
returns the result code of ``FollowJointTrajectory.Result`` with a reason that names the value
and what is allowed: unknown, repeated or missing joints (``INVALID_JOINTS``; a partial goal,
whose other joints hold, when allowed); an empty
trajectory, times that do not increase or are negative, non-finite values, fields whose
length is not the number of joints, a velocity left at the end, positions outside what the
stage reaches, velocities, accelerations or commands beyond what the amplifier can drive, a
point due now away from the present reference (``INVALID_GOAL``); a header stamp so early that
the last point is already due (``OLD_HEADER_TIMESTAMP``).

The limits come from the stage model (:meth:`AxisLimits.from_stage`): the stage follows a
slow reference x(t) with the command u = (x + tau_1 x' + tau_2 x'') / (g c) to second order
in the frequency (g the plant's static gain, c the hysteresis slope, tau_1 and tau_2 from the
low-frequency series of the plant's inverse). A trajectory is refused when that command leaves
the amplifier input range anywhere on the sample grid, which bounds position, velocity and
acceleration together; the positions are also held inside the travel and inside the static
reach g (c u_max - rho) ... g (c u_min + rho) (rho the hysteresis bound), beyond which the
amplifier saturates and no controller can settle.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import enum
import math
from typing import Generator, Sequence, TypeVar

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.loop.splines import Spline
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant, StageParams

__all__ = ['AxisLimits', 'GoalVerdict', 'JointTolerance', 'JointTrajectoryGoal', 'ResultCode',
           'Steps', 'TrajectoryPoint', 'build_spline', 'finish', 'validate_goal',
           'validation_steps']


#: Samples checked at a time against the limits.
_CHECK_BLOCK = 65536

_T = TypeVar('_T')

#: Work done a slice at a time: each ``next`` does one slice, the return value ends it.
Steps = Generator[None, None, _T]


def finish(steps: Steps[_T]) -> _T:
    """Run the rest of stepped work at once and return its result."""
    while True:
        try:
            next(steps)
        except StopIteration as stop:
            return stop.value  # type: ignore[no-any-return]


class ResultCode(enum.IntEnum):
    """The ``error_code`` values of ``control_msgs/action/FollowJointTrajectory`` Result."""

    SUCCESSFUL = 0
    INVALID_GOAL = -1
    INVALID_JOINTS = -2
    OLD_HEADER_TIMESTAMP = -3
    PATH_TOLERANCE_VIOLATED = -4
    GOAL_TOLERANCE_VIOLATED = -5


@dataclass(frozen=True)
class TrajectoryPoint:
    """
    One ``trajectory_msgs/JointTrajectoryPoint``: values per joint, in the goal's joint order.

    Attributes
    ----------
    time_from_start_s : float
        Time of the point after the trajectory's start [s].
    positions_m : tuple of float
        Position of each joint [m].
    velocities_mps, accelerations_mps2 : tuple of float
        Velocity [m/s] and acceleration [m/s^2] of each joint; empty when not given.

    """

    time_from_start_s: float
    positions_m: tuple[float, ...]
    velocities_mps: tuple[float, ...] = ()
    accelerations_mps2: tuple[float, ...] = ()


@dataclass(frozen=True)
class JointTolerance:
    """
    One ``control_msgs/JointTolerance``: 0 keeps the default, a negative value checks nothing.

    Attributes
    ----------
    name : str
        The joint.
    position_m, velocity_mps, acceleration_mps2 : float
        Largest allowed |error| [m, m/s, m/s^2].

    """

    name: str
    position_m: float = 0.0
    velocity_mps: float = 0.0
    acceleration_mps2: float = 0.0


@dataclass(frozen=True)
class JointTrajectoryGoal:
    """
    A FollowJointTrajectory goal, or a JointTrajectory message (no tolerances).

    Attributes
    ----------
    joint_names : tuple of str
        The joints the points speak of, in their order.
    points : tuple of TrajectoryPoint
        The points, times increasing.
    path_tolerance, goal_tolerance : tuple of JointTolerance
        Per-joint tolerances (joints not named keep the defaults).
    goal_time_tolerance_s : float
        Time after the last point within which the goal tolerance must be met [s]; 0 keeps
        the default.

    """

    joint_names: tuple[str, ...]
    points: tuple[TrajectoryPoint, ...]
    path_tolerance: tuple[JointTolerance, ...] = ()
    goal_tolerance: tuple[JointTolerance, ...] = ()
    goal_time_tolerance_s: float = 0.0


@dataclass(frozen=True)
class GoalVerdict:
    """The decision on a goal: a result code and, unless it is SUCCESSFUL, the reason."""

    code: ResultCode
    reason: str = ''

    @property
    def accepted(self) -> bool:
        """Return True if the goal may run."""
        return self.code == ResultCode.SUCCESSFUL


@dataclass(frozen=True)
class AxisLimits:
    """
    What one axis can follow; :meth:`from_stage` derives it from the stage model.

    Attributes
    ----------
    position_min_m, position_max_m : float
        Lowest and highest position a goal may ask for [m].
    velocity_max_mps : float
        Largest |velocity| [m/s].
    acceleration_max_mps2 : float
        Largest |acceleration| [m/s^2] (checked on cubic and quintic segments; a linear
        segment's corners are velocity steps).
    command_min_v, command_max_v : float
        Amplifier input range [V] the estimated command must stay in.
    gain_m_per_v : float
        g c: static position per volt of command [m/V].
    tau1_s, tau2_s2 : float
        Velocity and acceleration terms of the command estimate [s, s^2].
    resolution_m : float
        How far a first point at time 0 may lie from the present reference [m] (the sensor's
        resolution: closer than that the two cannot be told apart).

    """

    position_min_m: float
    position_max_m: float
    velocity_max_mps: float
    acceleration_max_mps2: float
    command_min_v: float = -math.inf
    command_max_v: float = math.inf
    gain_m_per_v: float = 1.0
    tau1_s: float = 0.0
    tau2_s2: float = 0.0
    resolution_m: float = 0.0

    def __post_init__(self) -> None:
        if not self.position_min_m < self.position_max_m:
            raise ParameterError('position_max_m', self.position_max_m,
                                 f'> position_min_m = {self.position_min_m:g}')
        for name in ('velocity_max_mps', 'acceleration_max_mps2', 'gain_m_per_v'):
            value = getattr(self, name)
            if not value > 0.0:
                raise ParameterError(name, value, '(0, inf]')

    @classmethod
    def from_stage(cls, stage: StageParams, *, travel_min_m: float = 0.0,
                   travel_max_m: float = 38e-6) -> AxisLimits:
        """
        Derive the limits of a stage model's axis.

        Parameters
        ----------
        stage : StageParams
            The stage (:class:`piezo_stage_ros.core.model.stage.StageParams`): its plant,
            hysteresis and amplifier input range.
        travel_min_m, travel_max_m : float
            The travel [m] (the trajectory node's ``travel_min_m``, ``travel_max_m``).

        Returns
        -------
        AxisLimits
            Positions inside both the travel and the static reach; the velocity at which the
            velocity term alone needs the whole amplifier span, and likewise the acceleration.

        """
        plant = linear_plant(stage.plant)
        hyst = make_hysteresis(stage.hysteresis)
        a_inv = np.linalg.inv(plant.a)
        b = plant.b[:, 0]
        # G(s) = m0 + m1 s + m2 s^2 + ... with m_j = -C A^-(j+1) B; 1/G to second order
        m0 = float(-plant.c @ a_inv @ b)
        m1 = float(-plant.c @ a_inv @ a_inv @ b)
        m2 = float(-plant.c @ a_inv @ a_inv @ a_inv @ b)
        tau1 = -m1 / m0
        tau2 = tau1 * tau1 - m2 / m0
        chain = stage.chain
        gain = m0 * hyst.slope
        span = chain.amplifier_max_v - chain.amplifier_min_v
        lo = max(travel_min_m, m0 * (hyst.slope * chain.amplifier_min_v + hyst.bound))
        hi = min(travel_max_m, m0 * (hyst.slope * chain.amplifier_max_v - hyst.bound))
        return cls(position_min_m=lo, position_max_m=hi,
                   velocity_max_mps=gain * span / abs(tau1),
                   acceleration_max_mps2=gain * span / abs(tau2) if tau2 else math.inf,
                   command_min_v=chain.amplifier_min_v, command_max_v=chain.amplifier_max_v,
                   gain_m_per_v=gain, tau1_s=tau1, tau2_s2=tau2,
                   resolution_m=chain.adc_lsb_m if chain.quantize else 0.0)

    def command_v(self, position_m: FloatArray, velocity_mps: FloatArray,
                  acceleration_mps2: FloatArray) -> FloatArray:
        """Return the estimated command that makes the stage follow these states [V]."""
        return np.asarray((position_m + self.tau1_s * velocity_mps
                           + self.tau2_s2 * acceleration_mps2) / self.gain_m_per_v,
                          dtype=np.float64)


@dataclass(frozen=True)
class _Columns:
    """The points of a goal as arrays in the controller's joint order."""

    times_s: FloatArray
    positions_m: FloatArray
    velocities_mps: FloatArray | None
    accelerations_mps2: FloatArray | None = field(default=None)


def _refuse(reason: str) -> GoalVerdict:
    return GoalVerdict(ResultCode.INVALID_GOAL, reason)


def _check_joints(goal: JointTrajectoryGoal, joints: Sequence[str], partial: bool = False
                  ) -> GoalVerdict | None:
    allowed = f"the stage's joints {list(joints)}"
    if partial and not goal.joint_names:
        return GoalVerdict(ResultCode.INVALID_JOINTS,
                           f'the goal names no joint; allowed: one or more of {allowed}')
    seen: set[str] = set()
    for name in goal.joint_names:
        if name not in joints:
            return GoalVerdict(ResultCode.INVALID_JOINTS,
                               f'joint {name!r} is not a joint of this stage; allowed: {allowed}')
        if name in seen:
            return GoalVerdict(ResultCode.INVALID_JOINTS,
                               f'joint {name!r} is named twice; allowed: each of {allowed} once')
        seen.add(name)
    missing = [j for j in joints if j not in seen]
    if missing and not partial:
        return GoalVerdict(ResultCode.INVALID_JOINTS,
                           f'joints {missing} are missing; allowed: all of {allowed}')
    for kind, tolerances in (('path_tolerance', goal.path_tolerance),
                             ('goal_tolerance', goal.goal_tolerance)):
        for tol in tolerances:
            if tol.name not in joints:
                return GoalVerdict(ResultCode.INVALID_JOINTS,
                                   f'{kind} names joint {tol.name!r}; allowed: {allowed}')
            for attr in ('position_m', 'velocity_mps', 'acceleration_mps2'):
                if not math.isfinite(getattr(tol, attr)):
                    return _refuse(f'{kind} of {tol.name!r}: {attr} = {getattr(tol, attr)!r}; '
                                   'allowed: a finite number (0 default, < 0 unchecked)')
    return None


def _columns(goal: JointTrajectoryGoal, joints: Sequence[str], hold_m: FloatArray
             ) -> tuple[_Columns | None, GoalVerdict | None]:
    """Return the goal's points as columns in the stage's joint order, or why they are bad."""
    return finish(_column_steps(goal, joints, hold_m, 0))


def _column_steps(goal: JointTrajectoryGoal, joints: Sequence[str], hold_m: FloatArray,
                  every: int) -> Steps[tuple[_Columns | None, GoalVerdict | None]]:
    """
    Return the goal's points as columns in the stage's joint order, or why they are bad.

    A slice of ``every`` points at a time (0: all at once).

    A joint the goal does not name (a partial goal) holds ``hold_m`` (the present reference's
    position) at every point, at rest where the points give velocities and accelerations, as
    joint_trajectory_controller fills a partial goal.
    """
    if not goal.points:
        return None, _refuse('the trajectory has no points; allowed: at least one point')
    n = len(goal.joint_names)
    order = [goal.joint_names.index(j) if j in goal.joint_names else -1 for j in joints]
    with_vel = bool(goal.points[0].velocities_mps)
    with_acc = bool(goal.points[0].accelerations_mps2)
    for i, p in enumerate(goal.points):
        if every and i and i % every == 0:
            yield
        for name, values, need in (('positions', p.positions_m, n),
                                   ('velocities', p.velocities_mps, n if with_vel else 0),
                                   ('accelerations', p.accelerations_mps2,
                                    n if with_acc else 0)):
            if len(values) != need:
                what = f'{need} values, one per joint' if need else \
                    'none, as in the first point'
                return None, _refuse(f'point {i}: {len(values)} {name}; allowed: {what}')
            bad = [v for v in values if not math.isfinite(v)]
            if bad:
                return None, _refuse(f'point {i}: {name} holds {bad[0]!r}; allowed: finite '
                                     'numbers')
        if not math.isfinite(p.time_from_start_s) or p.time_from_start_s < 0.0:
            return None, _refuse(f'point {i}: time_from_start = {p.time_from_start_s!r} s; '
                                 'allowed: a finite time >= 0')
        if i and p.time_from_start_s <= goal.points[i - 1].time_from_start_s:
            return None, _refuse(
                f'point {i}: time_from_start = {p.time_from_start_s!r} s after '
                f'{goal.points[i - 1].time_from_start_s!r} s; allowed: strictly increasing')
    if with_acc and not with_vel:
        return None, _refuse('points give accelerations without velocities; allowed: '
                             'positions, positions and velocities, or all three')
    times = np.array([p.time_from_start_s for p in goal.points])
    held = [float(x) for x in np.asarray(hold_m, dtype=np.float64).reshape(len(joints))]

    def column(values: tuple[float, ...], k: int, rest: float) -> float:
        return values[k] if k >= 0 else rest
    # arrays of a slice of points at a time, joined: the values of one array of them all
    parts: tuple[list[FloatArray], list[FloatArray], list[FloatArray]] = ([], [], [])
    size = every or len(goal.points)
    for first in range(0, len(goal.points), size):
        if first:
            yield
        points = goal.points[first:first + size]
        parts[0].append(np.array([[column(p.positions_m, k, held[j])
                                   for j, k in enumerate(order)] for p in points]))
        if with_vel:
            parts[1].append(np.array([[column(p.velocities_mps, k, 0.0) for k in order]
                                      for p in points]))
        if with_acc:
            parts[2].append(np.array([[column(p.accelerations_mps2, k, 0.0) for k in order]
                                      for p in points]))
    pos = np.concatenate(parts[0])
    vel = np.concatenate(parts[1]) if with_vel else None
    acc = np.concatenate(parts[2]) if with_acc else None
    if vel is not None and np.any(vel[-1] != 0.0):
        return None, _refuse(f'the last point has velocities {vel[-1].tolist()} m/s; allowed: '
                             '0 (the stage holds at the end)')
    return _Columns(times, pos, vel, acc), None


def build_spline(goal: JointTrajectoryGoal, joints: Sequence[str], start_s: float,
                 start_state: tuple[FloatArray, FloatArray, FloatArray],
                 sample_time_s: float, origin_s: float | None = None) -> Spline:
    """
    Return the spline of a goal that :func:`validate_goal` accepted.

    Parameters
    ----------
    goal : JointTrajectoryGoal
        The goal.
    joints : sequence of str
        The stage's joints, in the order of the spline's axes.
    start_s : float
        Now: the time of the start state [s].
    start_state : tuple of ndarray
        Present reference of every axis: position, velocity, acceleration.
    sample_time_s : float
        Sample period [s]: a lone point due now is reached one sample later.
    origin_s : float, optional
        The time ``time_from_start`` counts from (the header's stamp) [s]; default now.

    Returns
    -------
    Spline
        Points due now or earlier are dropped (a point due now is the start state itself,
        validated to be within the sensor resolution of the present reference); the first
        later point is reached from the present reference.

    """
    cols, verdict = _columns(goal, joints, start_state[0])
    assert cols is not None, verdict
    return _spline_of(cols, start_s, start_state, sample_time_s, origin_s)


def _spline_of(cols: _Columns, start_s: float,
               start_state: tuple[FloatArray, FloatArray, FloatArray], sample_time_s: float,
               origin_s: float | None) -> Spline:
    times = (start_s if origin_s is None else origin_s) + cols.times_s
    keep = times > start_s
    if not np.any(keep):
        times[-1] = start_s + sample_time_s
        keep[-1] = True

    def pick(a: FloatArray | None) -> FloatArray | None:
        return None if a is None else a[keep]
    return Spline(start_s, start_state, times[keep], cols.positions_m[keep],
                  pick(cols.velocities_mps), pick(cols.accelerations_mps2))


class _LimitScan:
    """
    The largest excursion past each limit over a grid that may be sampled a piece at a time.

    Pieces in the grid's order give the excursions, and so the refusal, of the whole grid
    (the first of equal largest, as ``np.argmax`` over the whole).
    """

    def __init__(self, start_s: float, joints: Sequence[str], limits: Sequence[AxisLimits]
                 ) -> None:
        self.start_s = start_s
        self.joints = joints
        self.limits = limits
        # per axis: velocity, acceleration, command; each (score, at [s], values at it)
        self.worst: list[list[tuple[float, float, tuple[float, ...]] | None]] = [
            [None, None, None] for _ in limits]

    def _keep(self, k: int, c: int, score: float, at_s: float, values: tuple[float, ...]
              ) -> None:
        # np.argmax takes the first largest, and a NaN before anything
        best = self.worst[k][c]
        if best is None or score > best[0] or (math.isnan(score) and not math.isnan(best[0])):
            self.worst[k][c] = (score, at_s, values)

    def add(self, spline: Spline, grid: FloatArray) -> None:
        """Take the spline's excursions over the next piece of the grid."""
        pos, vel, acc = spline.sample(grid)
        for k, lim in enumerate(self.limits):
            for c, values in ((0, vel[:, k]), (1, acc[:, k])):
                i = int(np.argmax(np.abs(values)))
                self._keep(k, c, abs(values[i]), float(grid[i]), (float(values[i]),))
            u = lim.command_v(pos[:, k], vel[:, k], acc[:, k])
            margin = np.maximum(u - lim.command_max_v, lim.command_min_v - u)
            i = int(np.argmax(margin))
            self._keep(k, 2, margin[i], float(grid[i]),
                       (float(u[i]), float(pos[i, k]), float(vel[i, k]), float(acc[i, k])))

    def verdict(self) -> GoalVerdict | None:
        """Return the refusal of the first limit broken on the grid so far, or None."""
        joints, start_s = self.joints, self.start_s
        for k, lim in enumerate(self.limits):
            for c, name, bound, unit in ((0, 'velocity', lim.velocity_max_mps, 'm/s'),
                                         (1, 'acceleration', lim.acceleration_max_mps2,
                                          'm/s^2')):
                worst = self.worst[k][c]
                if worst is not None and abs(worst[2][0]) > bound:
                    return _refuse(f'{joints[k]!r} reaches {name} {worst[2][0]:.4g} {unit} at '
                                   f'{worst[1] - start_s:.6g} s; allowed: |{name}| <= '
                                   f'{bound:.4g} {unit} (what the amplifier range drives on '
                                   'this stage)')
            worst = self.worst[k][2]
            if worst is None:
                continue
            u, x, v, a = worst[2]
            if not lim.command_min_v <= u <= lim.command_max_v:
                return _refuse(f'{joints[k]!r} would need {u:.4g} V at {worst[1] - start_s:.6g} s '
                               f'(position {x:.6g} m, velocity {v:.4g} m/s, '
                               f'acceleration {a:.4g} m/s^2); allowed: the amplifier input '
                               f'[{lim.command_min_v:g}, {lim.command_max_v:g}] V')
        return None


def validate_goal(goal: JointTrajectoryGoal, joints: Sequence[str],
                  limits: Sequence[AxisLimits], *, start_s: float,
                  start_state: tuple[FloatArray, FloatArray, FloatArray],
                  sample_time_s: float, origin_s: float | None = None,
                  partial_joints: bool = False) -> GoalVerdict:
    """
    Decide whether a goal may run from the present reference, and why not.

    Parameters
    ----------
    goal : JointTrajectoryGoal
        The goal.
    joints : sequence of str
        The stage's joints (axes).
    limits : sequence of AxisLimits
        One per joint, in the order of ``joints``.
    start_s : float
        Now: when the trajectory would start from the present reference [s].
    start_state : tuple of ndarray
        The present reference: position, velocity, acceleration of every axis.
    sample_time_s : float
        Sample period of the loop [s]: the grid on which the limits are checked.
    origin_s : float, optional
        The time ``time_from_start`` counts from (the header's stamp, in the loop's time) [s];
        default now. Points due before now are dropped; a trajectory whose last point is due
        before now is refused (``OLD_HEADER_TIMESTAMP``).
    partial_joints : bool
        Take a goal that names some of the joints: the others hold the present reference's
        position (joint_trajectory_controller's ``allow_partial_joints_goal``); False refuses
        it (``INVALID_JOINTS``), as that controller does by default.

    Returns
    -------
    GoalVerdict
        SUCCESSFUL, or INVALID_JOINTS / INVALID_GOAL / OLD_HEADER_TIMESTAMP with the reason.

    """
    verdict, _ = finish(validation_steps(
        goal, joints, limits, start_s=start_s, start_state=start_state,
        sample_time_s=sample_time_s, origin_s=origin_s, partial_joints=partial_joints))
    return verdict


def validation_steps(goal: JointTrajectoryGoal, joints: Sequence[str],
                     limits: Sequence[AxisLimits], *, start_s: float,
                     start_state: tuple[FloatArray, FloatArray, FloatArray],
                     sample_time_s: float, origin_s: float | None = None,
                     partial_joints: bool = False, points_per_step: int = 0,
                     samples_per_step: int = 0) -> Steps[tuple[GoalVerdict, Spline | None]]:
    """
    Check a goal as :func:`validate_goal` does, a slice at a time; also return its spline.

    The same operations in the same order, with a pause (``yield``) after each slice of
    ``points_per_step`` points read and of ``samples_per_step`` samples checked (0: no pause
    there), for a real-time loop that does the check in the time its samples leave free.

    Returns
    -------
    verdict : GoalVerdict
        As :func:`validate_goal`'s.
    spline : Spline or None
        The goal's spline (:func:`build_spline`) when it was built: always when accepted.

    """
    verdict = _check_joints(goal, joints, partial_joints)
    if verdict is not None:
        return verdict, None
    cols, verdict = yield from _column_steps(goal, joints, start_state[0], points_per_step)
    if verdict is not None:
        return verdict, None
    assert cols is not None
    for tol, what in ((goal.goal_time_tolerance_s, 'goal_time_tolerance'),):
        if not (math.isfinite(tol) and tol >= 0.0):
            return _refuse(f'{what} = {tol!r} s; allowed: a finite time >= 0'), None
    due = (start_s if origin_s is None else origin_s) + cols.times_s
    if due[-1] < start_s:
        return GoalVerdict(ResultCode.OLD_HEADER_TIMESTAMP,
                           f'the last point is due at {due[-1]:.6g} s; allowed: not before now '
                           f'({start_s:.6g} s)'), None
    for now in np.flatnonzero(due == start_s).tolist():
        i = int(now)
        # a point due now must be where the reference is, or the reference would jump
        jump = np.abs(cols.positions_m[i] - start_state[0])
        step = np.array([lim.resolution_m for lim in limits])
        if np.any(jump > step):
            k = int(np.argmax(jump - step))
            return _refuse(f'point {i} due now puts {joints[k]!r} at '
                           f'{cols.positions_m[i, k]:.6g} m, {jump[k]:.3g} m from the present '
                           f'reference {start_state[0][k]:.6g} m; allowed: a point due now '
                           f'within {step[k]:.3g} m of it (the sensor resolution), or a later '
                           'time'), None
    for k, lim in enumerate(limits):
        column = cols.positions_m[:, k]
        for i in (int(np.argmin(column)), int(np.argmax(column))):
            if not lim.position_min_m <= column[i] <= lim.position_max_m:
                return _refuse(f'point {i}: position of {joints[k]!r} = {column[i]:.6g} m; '
                               f'allowed: [{lim.position_min_m:.6g}, {lim.position_max_m:.6g}] m '
                               "(the travel and the amplifier's static reach)"), None
    yield
    spline = _spline_of(cols, start_s, start_state, sample_time_s, origin_s)
    n = int(math.ceil((spline.end_s - start_s) / sample_time_s)) + 1
    # in blocks, so that a long goal costs time but not memory; a block in pieces, so that
    # each pause comes soon
    piece = samples_per_step or _CHECK_BLOCK
    for first in range(0, n, _CHECK_BLOCK):
        last = min(first + _CHECK_BLOCK, n)
        scan = _LimitScan(start_s, joints, limits)
        for begin in range(first, last, piece):
            yield
            grid = start_s + np.arange(begin, min(begin + piece, last),
                                       dtype=np.float64) * sample_time_s
            if begin + piece >= last:
                grid[-1] = min(grid[-1], spline.end_s)
            scan.add(spline, grid)
        verdict = scan.verdict()
        if verdict is not None:
            return verdict, spline
    return GoalVerdict(ResultCode.SUCCESSFUL), spline
