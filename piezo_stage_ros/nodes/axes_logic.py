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
What the nodes do with a stage of several axes, without rclpy: the lockstep loop over N axes.

The one-axis sequence of :mod:`piezo_stage_ros.nodes.logic`, with every value of a sample one
tuple over the axes (one message a sample and topic: a sample stays atomic):

1. :class:`AxesPlantLogic` publishes y_k (every axis) stamped t_k, and the true positions;
2. :class:`AxesTrajectoryLogic` answers x_d(t_k), x_d'(t_k) of every axis with the same stamp,
   evaluated in the chunks of the offline runner
   (:func:`~piezo_stage_ros.core.loop.axes.axes_references`): the scan's, or the goals' once a
   goal took the axes over;
3. :class:`AxesControllerLogic`, holding y_k and x_d for the same stamp, steps every axis'
   controller in one call and publishes u_k (every axis);
4. the plant steps every axis on receiving u_k.

The samples are those of :func:`~piezo_stage_ros.core.loop.axes.run_axes` bit for bit (with
goals: :func:`~piezo_stage_ros.core.loop.follow.run_axes_goals`): the same stage, the same
controllers bound and reset the same way, the same floats in. In real
time the servo of several axes (:mod:`piezo_stage_ros.nodes.servo_axes`) runs the loop instead,
in the plant node's process; :func:`refuse_axes_mode` names what neither runs.
"""

from __future__ import annotations

from dataclasses import dataclass
import json
from typing import Any, Callable, Sequence

import numpy as np
from piezo_stage_ros.core.config.axes import AxesLoopConfig
from piezo_stage_ros.core.contracts.errors import ParameterError, PiezoStageError
from piezo_stage_ros.core.contracts.interfaces import Trajectory
from piezo_stage_ros.core.contracts.wire import axis_joint_names, NS_PER_S
from piezo_stage_ros.core.control.axes import AxesController
from piezo_stage_ros.core.loop.follow import (
    AxesGoalReference,
    binds_goals,
    FollowParams,
    goal_views,
    GoalFollower,
    State,
)
from piezo_stage_ros.core.loop.goals import AxisLimits
from piezo_stage_ros.core.loop.splines import Spline
from piezo_stage_ros.core.model.axes import AxesStage
from piezo_stage_ros.nodes.logic import GoalDesk, sample_count

__all__ = ['AxesCommand', 'AxesControllerLogic', 'AxesPlantLogic', 'AxesSample',
           'AxesTrajectoryLogic', 'announce_axes_goal', 'axes_follower', 'parse_axes_goal',
           'refuse_axes_mode']


def axes_follower(loop: AxesLoopConfig) -> GoalFollower:
    """
    Return the goals' follower of a stage of several axes, at rest at its scan's start.

    Its joints are the stage's (``stage_x`` ...); each axis is checked against its own limits
    (:meth:`~piezo_stage_ros.core.loop.goals.AxisLimits.from_stage`: its stage model, and the
    travel of its trajectory, ``travel_min_m`` ... ``travel_max_m`` with the
    ``axes.<name>.*`` overrides). Goals may name some of the axes
    (``FollowParams.partial_joints``): a stage whose axes move on their own (focus on z while
    x and y hold) is commanded an axis at a time, as joint_trajectory_controller with
    ``allow_partial_joints_goal``; the axes not named hold where their reference is.
    """
    limits = [AxisLimits.from_stage(sp, travel_min_m=line.travel_min_m,
                                    travel_max_m=line.travel_max_m)
              for sp, line in zip(loop.stage.axes, loop.lines)]
    start = [float(tr.evaluate(np.zeros(1))[0][0]) for tr in loop.trajectories()]
    return GoalFollower(axis_joint_names(loop.stage.names), limits, start,
                        FollowParams(sample_time_s=loop.stage.sample_time_s,
                                     partial_joints=True))


def refuse_axes_mode(node: str, mode: str, backend: str = 'model', direct: bool = False
                     ) -> str | None:
    """
    Return why the nodes cannot run a stage of several axes so configured, else None.

    Parameters
    ----------
    node : str
        The node (for the message).
    mode : str
        Its ``mode``.
    backend : str
        The plant's ``backend``.
    direct : bool
        Whether the composition hands samples on by call (``--direct``, the servo's).

    """
    where = (f'{node}: a stage of several axes (plant_node axes.names) runs on the nodes on the '
             'stage model, in lockstep by topics or in real time with the servo in one process '
             '(mode: realtime, stage_servo --direct)')
    if backend != 'model':
        return f'{where}; backend {backend!r} is not'
    if mode == 'lockstep' and direct:
        return f'{where}; --direct in lockstep is not'
    if mode != 'lockstep' and not direct:
        return (f'{where}; mode {mode!r} without --direct is not (the servo runs every '
                "node's logic in the plant's thread)")
    return None


@dataclass(frozen=True)
class AxesSample:
    """
    One sample of every axis, ready to publish.

    Attributes
    ----------
    index : int
        k, from 0.
    stamp_ns : int
        t_k [ns], simulation time from 0.
    positions_m : tuple of float
        y_k of each axis [m], in the stage's axis order.
    true_positions_m : tuple of float
        x(t_k) of each axis [m] (the model's, behind the sensor).

    """

    index: int
    stamp_ns: int
    positions_m: tuple[float, ...]
    true_positions_m: tuple[float, ...]


class AxesPlantLogic:
    """
    The plant node's behaviour with several axes: owns simulation time, one sample per command.

    Parameters
    ----------
    stage : AxesStage
        The stage model (reset by :meth:`start`).
    sample_rate_hz : float
        Sample rate [Hz].
    duration_s : float
        Stop after ``round(duration_s * rate)`` samples (the offline runner's count); 0 runs on.
    resend_s : float
        Publish the waiting sample again after this long without its command [s].

    """

    def __init__(self, stage: AxesStage, *, sample_rate_hz: float, duration_s: float = 0.0,
                 resend_s: float = 0.5) -> None:
        self.stage = stage
        self.n = stage.n
        self.rate_hz = float(sample_rate_hz)
        self.total = sample_count(duration_s, self.rate_hz)
        self.resend_s = resend_s
        self.index = -1
        self.done = False
        self.waiting = False
        self.last_sample: AxesSample | None = None
        self._last_publish_s = 0.0
        self.resends = 0
        self.unexpected = 0

    def _sample(self, positions_m: Sequence[float]) -> AxesSample:
        self.index += 1
        sample = AxesSample(self.index, round(self.index * NS_PER_S / self.rate_hz),
                            tuple(positions_m), tuple(self.stage.read_positions_m()))
        self.last_sample = sample
        return sample

    def start(self, now_s: float) -> AxesSample:
        """Reset the stage to its rest positions and return sample 0 (``now_s``: wall [s])."""
        y0 = self.stage.reset(None)
        self._last_publish_s = now_s
        self.waiting = True
        sample = self._sample(y0)
        if self.total == 1:
            self.done = True
            self.waiting = False
        return sample

    def on_command(self, commands_v: Sequence[float], now_s: float) -> AxesSample | None:
        """
        Take u_k of every axis [V]; return the next sample, or None.

        None once the run is complete (the last command is applied, as offline, but y_N is
        not a sample) and for a command nobody waits for (counted in ``unexpected``).

        Raises
        ------
        ParameterError
            For a command of another number of axes.

        """
        if len(commands_v) != self.n:
            raise ParameterError('stage/command', len(commands_v),
                                 f'{self.n} entries, one per axis')
        if not self.waiting:
            self.unexpected += 1
            return None
        positions = self.stage.step([float(u) for u in commands_v])
        self._last_publish_s = now_s
        if self.total and self.index + 1 >= self.total:
            self.waiting = False
            self.done = True
            return None
        return self._sample(positions)

    def resend_due(self, now_s: float) -> AxesSample | None:
        """Return the waiting sample again if its command is overdue, else None."""
        if not (self.waiting and self.last_sample is not None) or \
                now_s - self._last_publish_s < self.resend_s:
            return None
        self._last_publish_s = now_s
        self.resends += 1
        return self.last_sample

    def stop(self) -> None:
        """End the run: later commands are counted as unexpected."""
        self.done = True
        self.waiting = False

    def stats(self) -> dict[str, Any]:
        """Return the counters."""
        return {'index': self.index, 'axes': self.n, 'resends': self.resends,
                'unexpected_commands': self.unexpected}


class AxesTrajectoryLogic(GoalDesk):
    """
    The trajectory node's behaviour with several axes: every axis' x_d and x_d' per stamp.

    Parameters
    ----------
    trajectories : sequence of Trajectory
        One per axis (the scan's); t = 0 at the first stamp answered.
    sample_rate_hz : float
        Sample rate [Hz].
    chunk_s : float
        Evaluate this much at a time [s], chunks aligned at the start as the offline runner's.
    names : sequence of str
        The axes, for messages.

    Notes
    -----
    Goals (:meth:`attach_goals`, :meth:`goal`, :meth:`cancel`, :meth:`hold`, as the one-axis
    :class:`~piezo_stage_ros.nodes.logic.TrajectoryLogic` takes them, in lockstep): a goal that
    may run takes every axis over from the scan at the next sample, without a jump, and the
    reference stays the follower's from then on (a hold where the last goal left it). The
    samples are those of :func:`~piezo_stage_ros.core.loop.follow.run_axes_goals` with the
    goals and cancels at the loop times they took effect (:attr:`started`,
    :attr:`cancelled`): both compute the reference with
    :class:`~piezo_stage_ros.core.loop.follow.AxesGoalReference`.

    """

    def __init__(self, trajectories: Sequence[Trajectory], *, sample_rate_hz: float,
                 chunk_s: float = 1.0, names: Sequence[str] = ()) -> None:
        self.trajectories = tuple(trajectories)
        self.names = tuple(names)
        self.rate_hz = float(sample_rate_hz)
        self.period_s = 1.0 / self.rate_hz
        self.chunk = max(int(round(chunk_s / self.period_s)), 1)
        self.reference = AxesGoalReference(self.trajectories, None, self.period_s, self.chunk,
                                           self.names)
        self.answered = 0
        self._init_goals()
        self._announced = -1
        #: Called with (the follower's spline, stamp of this sample) before the reference of
        #: the first sample at which a goal changed it: the controllers bind it there
        #: (:meth:`AxesControllerLogic.request_goal`, by the announcement on
        #: ``stage/trajectory``, :func:`announce_axes_goal`).
        self.on_reference_change: Callable[[Spline, int], None] | None = None

    def attach_goals(self, follower: GoalFollower, lead_s: float = 0.0) -> None:
        """
        Take goals for ``follower``, its joints the axes; lockstep only (``lead_s`` 0).

        Raises
        ------
        ParameterError
            For a lead: goals checked ahead of their sample (real time) are not served here.

        """
        if lead_s:
            raise ParameterError('lead_s', lead_s, '0: goals of several axes run in lockstep')
        super().attach_goals(follower, 0.0)
        self.reference = AxesGoalReference(self.trajectories, follower, self.period_s,
                                           self.chunk, self.names)

    @property
    def goal_active(self) -> bool:
        """Return whether the reference is the follower's (a goal took it over)."""
        return self.reference.taken

    def _take_over_state(self, index: int) -> State:
        return self.reference.state(index)

    def _take_over(self) -> None:
        self.reference.taken = True

    def on_position(self, stamp_ns: int, positions_m: Sequence[float] | None = None
                    ) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """
        Return every axis' x_d [m] and x_d' [m/s] for the sample stamped ``stamp_ns``.

        ``positions_m``: y_k of every axis [m], for the goals' tolerances and feedback.
        """
        if self._origin_ns is None:
            self._origin_ns = stamp_ns
        index = max(round((stamp_ns - self._origin_ns) * self.rate_hz / NS_PER_S), 0)
        if self.follower is not None:
            served, self._index = self._index, max(self._index, index)
            if self._requests or self._starts:
                self._serve_goals(index, served)
        follower = self.follower
        if self.reference.taken and follower is not None and \
                follower.version != self._announced:
            self._announced = follower.version
            if self.on_reference_change is not None:
                self.on_reference_change(follower.spline, stamp_ns)
        ref, vel = self.reference.at(index)
        self.answered += 1
        if positions_m is not None and self.reference.taken:
            self._step_goal(index, positions_m, ref)
        return tuple(ref), tuple(vel)


@dataclass(frozen=True)
class AxesCommand:
    """
    Every axis' command for one sample.

    Attributes
    ----------
    stamp_ns : int
        Stamp of the sample it answers [ns].
    commands_v : tuple of float
        u_k of each axis [V], in the stage's axis order.

    """

    stamp_ns: int
    commands_v: tuple[float, ...]


class AxesControllerLogic:
    """
    The controller node's behaviour with several axes: pair by stamp, step every axis once.

    Parameters
    ----------
    controller : AxesController
        The axes' controllers, bound here to ``trajectories`` (their feed-forwards and the
        coupling compensation read the references ahead).
    trajectories : sequence of Trajectory
        The references the trajectory node plays, one per axis.

    Notes
    -----
    The first sample resets the controllers from y_0 and x_d(0), as the offline runner does.
    A sample is stepped once: a stamp seen again (a resend) or older is counted and dropped.

    """

    def __init__(self, controller: AxesController, trajectories: Sequence[Trajectory]) -> None:
        self.controller = controller
        self.n = controller.n
        controller.bind(trajectories)
        self._binds = binds_goals(controller)
        self._goals: list[tuple[int, Spline]] = []
        #: Goal references bound after the sample they were announced for had been stepped.
        self.late_goals = 0
        self._positions: dict[int, tuple[float, ...]] = {}
        self._refs: dict[int, tuple[tuple[float, ...], tuple[float, ...]]] = {}
        self._last_stamp: int | None = None
        self.steps = 0
        self.duplicates = 0

    def request_goal(self, spline: Spline, stamp_ns: int) -> None:
        """
        Bind the goals' reference ``spline`` before stepping the sample ``stamp_ns`` [ns].

        As the offline twin binds it (:func:`~piezo_stage_ros.core.loop.follow.run_axes_goals`,
        when :func:`~piezo_stage_ros.core.loop.follow.binds_goals`); a learning feed-forward
        keeps the scan (feedback alone along goals). A stamp already stepped (an announcement
        that came late) binds at the next sample, counted in ``late_goals``.
        """
        if not self._binds:
            return
        if self._last_stamp is not None and stamp_ns <= self._last_stamp:
            self.late_goals += 1
        self._goals.append((stamp_ns, spline))
        self._goals.sort(key=lambda g: g[0])

    def on_position(self, stamp_ns: int, positions_m: Sequence[float]) -> AxesCommand | None:
        """Take y_k of every axis [m] stamped ``stamp_ns`` [ns]."""
        self._positions[stamp_ns] = self._check('stage/position', positions_m)
        return self._try(stamp_ns)

    def on_reference(self, stamp_ns: int, references_m: Sequence[float],
                     velocities_mps: Sequence[float]) -> AxesCommand | None:
        """Take x_d and x_d' of every axis [m, m/s] for the sample stamped ``stamp_ns``."""
        self._refs[stamp_ns] = (self._check('stage/reference', references_m),
                                self._check('stage/reference velocity', velocities_mps))
        return self._try(stamp_ns)

    def _check(self, what: str, values: Sequence[float]) -> tuple[float, ...]:
        if len(values) != self.n:
            raise ParameterError(what, len(values), f'{self.n} entries, one per axis')
        return tuple(float(v) for v in values)

    def _try(self, stamp: int) -> AxesCommand | None:
        y = self._positions.get(stamp)
        ref = self._refs.get(stamp)
        if y is None or ref is None:
            return None
        for pending in (self._positions, self._refs):
            # halves older than this sample are of no use any more
            for old in [s for s in pending if s < stamp]:
                del pending[old]
        if self._last_stamp is not None and stamp <= self._last_stamp:
            self.duplicates += 1
            return None
        xd, vd = ref
        if self._last_stamp is None:
            self.controller.reset(list(y), list(xd))
        if self._goals and self._goals[0][0] <= stamp:
            # the newest goal reference due by this sample (after the reset, as offline)
            due = [g for g in self._goals if g[0] <= stamp]
            self._goals = self._goals[len(due):]
            self.controller.bind(goal_views(due[-1][1], self.n))
        u = self.controller.step(list(y), list(xd), list(vd))
        self._last_stamp = stamp
        self.steps += 1
        return AxesCommand(stamp, tuple(u))

    def stats(self) -> dict[str, int]:
        """Return the counters."""
        return {'steps': self.steps, 'duplicates': self.duplicates,
                'late_goals': self.late_goals}


def announce_axes_goal(stamp_ns: int, spline: Spline) -> str:
    """
    Return the announcement of the goals' reference of several axes, bound at ``stamp_ns``.

    JSON text for ``stage/trajectory``: ``stamp_ns`` (the sample before whose step the
    controllers bind it) and ``axes_goal``, the follower's spline
    (:meth:`~piezo_stage_ros.core.loop.splines.Spline.record`), which
    :func:`parse_axes_goal` builds again bit for bit.
    """
    return json.dumps({'stamp_ns': int(stamp_ns), 'axes_goal': spline.record()})


def parse_axes_goal(text: str) -> tuple[int, Spline]:
    """
    Return the stamp [ns] and the spline of an :func:`announce_axes_goal`.

    Raises
    ------
    ParameterError
        If the text is not one.

    """
    try:
        data = json.loads(text)
        return int(data['stamp_ns']), Spline.from_record(data['axes_goal'])
    except (ValueError, TypeError, KeyError, PiezoStageError) as exc:
        raise ParameterError('goal announcement', text[:80],
                             'JSON {"stamp_ns": int, "axes_goal": spline record}',
                             f'is not one ({exc})') from None

