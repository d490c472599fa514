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
Goals on a stage of several axes without ROS: per-axis interpolation and limits, partial goals,
tolerances naming the joint, preemption, cancel, bad input; the lockstep node logic with goals
gives the offline twin's samples bit for bit.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np
from piezo_stage_ros.cli import read_config
from piezo_stage_ros.core.config.axes import axes_loop_config, AxesLoopConfig
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.control.axes import AxesController
from piezo_stage_ros.core.loop.follow import (
    binds_goals,
    FollowParams,
    GoalFollower,
    GoalStatus,
    PREEMPTED,
    run_axes_goals,
    take_over_state,
)
from piezo_stage_ros.core.loop.goals import (
    AxisLimits,
    JointTolerance,
    JointTrajectoryGoal,
    ResultCode,
    TrajectoryPoint,
)
from piezo_stage_ros.core.model.axes import AxesStage
from piezo_stage_ros.nodes.axes_logic import (
    announce_axes_goal,
    axes_follower,
    AxesControllerLogic,
    AxesPlantLogic,
    AxesTrajectoryLogic,
    parse_axes_goal,
)
import pytest

T = 1e-4
X, Y, Z = 'stage_x', 'stage_y', 'stage_z'
P = TrajectoryPoint
#: An XY stage that holds: xy_stage.yaml (2 % X-to-Y coupling) with the hold scenario.
HOLD = ['xy_stage.yaml', 'xy_hold.yaml']


def loop_of(names: Sequence[str], params: Sequence[str] = ()) -> AxesLoopConfig:
    return axes_loop_config(read_config(list(names), list(params)))


def goal(names: Sequence[str], *points: P, **kw: Any) -> JointTrajectoryGoal:
    return JointTrajectoryGoal(tuple(names), tuple(points), **kw)


def tol(name: str, position_m: float) -> JointTolerance:
    return JointTolerance(name, position_m)


def xy_follower(y_max_m: float = 38e-6, **kw: Any) -> GoalFollower:
    """Two axes with their own limits (y's travel shorter when asked), at rest at 10 and 5 um."""
    stage = loop_of(HOLD).stage.axes[0]
    limits = [AxisLimits.from_stage(stage), AxisLimits.from_stage(stage, travel_max_m=y_max_m)]
    return GoalFollower((X, Y), limits, [10e-6, 5e-6],
                        FollowParams(sample_time_s=T, partial_joints=True, **kw))


def step_on_reference(f: GoalFollower, first: int, last: int,
                      offset_m: Sequence[float] = (0.0, 0.0)) -> list[Any]:
    """Step the follower with measurements at its reference plus an offset per axis."""
    results = []
    for k in range(first, last):
        x = f.reference(np.array([k * T]))[0][0]
        result, _ = f.step(k * T, (x + np.asarray(offset_m)).tolist())
        if result is not None:
            results.append(result)
    return results


# -- interpolation, limits, partial goals, per axis -------------------------------------------

@pytest.mark.parametrize('fields', ['linear', 'cubic', 'quintic'])
def test_every_axis_is_interpolated_from_its_present_reference(fields: str) -> None:
    f = xy_follower()
    vel = {'linear': (), 'cubic': (0.0, 0.0), 'quintic': (0.0, 0.0)}[fields]
    acc = (0.0, 0.0) if fields == 'quintic' else ()
    # the message names y first: every array of the follower is in the stage's order
    verdict, gid = f.accept(goal((Y, X), P(0.02, (7e-6, 12e-6), vel, acc)), 0.0)
    assert verdict.accepted and gid == 1
    assert f.spline.kind == fields
    t = np.arange(0, 201) * T
    x, v, a = f.reference(t)
    assert x[0].tolist() == [10e-6, 5e-6] and x[-1].tolist() == [12e-6, 7e-6]
    # each axis its own polynomial: at mid-time the linear one is half way, the cubic and
    # quintic from rest to rest are symmetric about it, so half way too
    np.testing.assert_allclose(x[100], [11e-6, 6e-6], rtol=0, atol=1e-18)
    if fields == 'linear':
        np.testing.assert_allclose(v[50], [2e-6 / 0.02, 2e-6 / 0.02], rtol=1e-12)
    else:
        assert v[0].tolist() == [0.0, 0.0] and v[-1].tolist() == [0.0, 0.0]
    if fields == 'quintic':
        assert np.abs(a[0]).max() == 0.0


def test_a_partial_goal_moves_the_axes_it_names_and_the_others_hold_exactly() -> None:
    f = xy_follower()
    verdict, _ = f.accept(goal((Y,), P(0.01, (8e-6,), (0.0,))), 0.0)
    assert verdict.accepted
    x, v, _ = f.reference(np.arange(0, 150) * T)
    assert np.all(x[:, 0] == 10e-6) and np.all(v[:, 0] == 0.0)      # x holds, bit for bit
    assert x[-1, 1] == 8e-6
    # partial goals refused where not allowed (joint_trajectory_controller's default)
    strict = GoalFollower((X, Y), f.limits, [10e-6, 5e-6], FollowParams(sample_time_s=T))
    refused = strict.check(goal((Y,), P(0.01, (8e-6,))), 0.0)
    assert refused.code == ResultCode.INVALID_JOINTS and "['stage_x'] are missing" in \
        refused.reason
    empty = f.check(goal((), P(0.01, ())), 0.0)
    assert empty.code == ResultCode.INVALID_JOINTS and 'names no joint' in empty.reason


def test_a_partial_goal_in_motion_holds_the_unnamed_axis_where_its_reference_is() -> None:
    # x moves, then a goal for y alone: x holds the position its reference has then (jtc:
    # the last command), coming to rest within the segment
    f = xy_follower()
    f.accept(goal((X, Y), P(0.02, (20e-6, 5e-6))), 0.0)
    x_then = f.reference(np.array([0.01]))[0][0]
    verdict, _ = f.accept(goal((Y,), P(0.01, (6e-6,))), 0.01)
    assert verdict.accepted
    x = f.reference(np.array([0.01, 0.015, 0.02, 0.03]))[0]
    assert x[0, 0] == x_then[0] and x[-1, 0] == x_then[0] and x[-1, 1] == 6e-6


def test_each_axis_is_checked_against_its_own_limits_naming_the_joint() -> None:
    f = xy_follower(y_max_m=12e-6)
    ok = f.check(goal((X, Y), P(0.02, (20e-6, 11e-6))), 0.0)
    assert ok.accepted
    beyond = f.check(goal((X, Y), P(0.02, (20e-6, 13e-6))), 0.0)
    assert beyond.code == ResultCode.INVALID_GOAL
    assert "'stage_y' = 1.3e-05 m; allowed: [" in beyond.reason and '1.2e-05] m' in beyond.reason
    # too fast for the stage: named per axis, with the bound
    lim = f.limits[1].velocity_max_mps
    fast = f.check(goal((Y,), P(0.5 * 5e-6 / lim, (10e-6,))), 0.0)
    assert fast.code == ResultCode.INVALID_GOAL
    assert fast.reason.startswith(f"'stage_y' reaches velocity {2.0 * lim:.4g} m/s")
    assert f'allowed: |velocity| <= {lim:.4g} m/s' in fast.reason


@pytest.mark.parametrize('bad, code, words', [
    (goal((X, 'stage_q'), P(0.01, (1e-5, 1e-5))), ResultCode.INVALID_JOINTS,
     "joint 'stage_q' is not a joint of this stage; allowed: the stage's joints "
     "['stage_x', 'stage_y']"),
    (goal((X, X), P(0.01, (1e-5, 1e-5))), ResultCode.INVALID_JOINTS,
     "joint 'stage_x' is named twice"),
    (goal((X, Y), P(0.02, (1e-5, 1e-5)), P(0.01, (1e-5, 1e-5))), ResultCode.INVALID_GOAL,
     'point 1: time_from_start = 0.01 s after 0.02 s; allowed: strictly increasing'),
    (goal((X, Y), P(0.01, (1e-5, math.nan))), ResultCode.INVALID_GOAL,
     'point 0: positions holds nan; allowed: finite numbers'),
    (goal((X, Y), P(0.01, (1e-5, 1e-5), (0.0, math.inf))), ResultCode.INVALID_GOAL,
     'point 0: velocities holds inf; allowed: finite numbers'),
    (goal((X, Y), P(0.01, (1e-5,))), ResultCode.INVALID_GOAL,
     'point 0: 1 positions; allowed: 2 values, one per joint'),
    (goal((Y,), P(0.01, (40e-6,))), ResultCode.INVALID_GOAL,
     "point 0: position of 'stage_y' = 4e-05 m; allowed: [0, "),
    (goal((X, Y), P(0.01, (1e-5, 1e-5)), path_tolerance=(tol(Z, 1e-9),)),
     ResultCode.INVALID_JOINTS, "path_tolerance names joint 'stage_z'"),
])
def test_bad_input_is_refused_naming_the_value_and_what_is_allowed(bad, code, words) -> None:
    f = xy_follower()
    verdict, gid = f.accept(bad, 0.0)
    assert (verdict.code, gid) == (code, 0)
    assert words in verdict.reason, verdict.reason
    assert f.phase == 'hold' and f.reference(np.array([0.05]))[0][0].tolist() == [10e-6, 5e-6]


# -- tolerances, preemption, cancel -----------------------------------------------------------

def test_a_path_tolerance_names_the_joint_that_left_it_and_every_axis_stops() -> None:
    f = xy_follower()
    f.accept(goal((X, Y), P(0.02, (14e-6, 9e-6)), path_tolerance=(tol(X, 1e-9), tol(Y, 2e-9))),
             0.0)
    # y 3 nm off its path (beyond its 2 nm), x on it
    results = step_on_reference(f, 0, 60, offset_m=(0.0, 3e-9))
    assert len(results) == 1 and results[0].code == ResultCode.PATH_TOLERANCE_VIOLATED
    assert results[0].reason.startswith("joint 'stage_y': path error -3e-09 m")
    assert 'allowed: |error| <= 2e-09 m' in results[0].reason
    _, v, _ = f.reference(np.array([0.5]))
    assert np.all(v == 0.0) and f.phase == 'hold' and f.active_goal is None


def test_a_goal_tolerance_names_the_joint_outside_it_after_the_goal_time() -> None:
    f = xy_follower()
    f.accept(goal((X, Y), P(0.01, (12e-6, 6e-6)), goal_tolerance=(tol(X, 5e-9), tol(Y, 5e-9)),
                  goal_time_tolerance_s=0.005), 0.0)
    results = step_on_reference(f, 0, 200, offset_m=(1e-9, 8e-9))
    assert [r.code for r in results] == [ResultCode.GOAL_TOLERANCE_VIOLATED]
    assert results[0].reason.startswith("joint 'stage_y': error -8e-09 m")
    assert 'within goal_time_tolerance 0.005 s' in results[0].reason
    # inside on every axis: success after the settle time
    g = xy_follower()
    g.accept(goal((X, Y), P(0.01, (12e-6, 6e-6)), goal_tolerance=(tol(X, 5e-9),
                                                                   tol(Y, 5e-9))), 0.0)
    ok = step_on_reference(g, 0, 200, offset_m=(1e-9, -4e-9))
    assert [(r.status, r.code) for r in ok] == [(GoalStatus.SUCCEEDED, ResultCode.SUCCESSFUL)]


def test_a_new_goal_preempts_from_every_axis_present_state_without_a_jump() -> None:
    f = xy_follower()
    f.accept(goal((X, Y), P(0.02, (20e-6, 15e-6), (0.0, 0.0))), 0.0)
    before = [a[0] for a in f.reference(np.array([0.008]))]
    verdict, gid = f.accept(goal((X, Y), P(0.02, (12e-6, 6e-6), (0.0, 0.0))), 0.008)
    assert verdict.accepted and gid == 2
    assert f.results[-1].reason == PREEMPTED and f.results[-1].status == GoalStatus.CANCELED
    after = [a[0] for a in f.reference(np.array([0.008]))]
    # position and velocity of both axes go on from where they were (cubic: no acceleration
    # continuity asked)
    assert after[0].tolist() == before[0].tolist() and after[1].tolist() == before[1].tolist()


def test_cancel_brings_every_axis_to_rest_within_the_stop_acceleration() -> None:
    f = xy_follower()
    f.accept(goal((X, Y), P(0.02, (20e-6, 6e-6), (0.0, 0.0), (0.0, 0.0))), 0.0)
    step_on_reference(f, 0, 100)
    x0, v0, _ = (a[0] for a in f.reference(np.array([0.01])))
    assert np.all(v0 != 0.0)
    f.cancel(0.01)
    results = step_on_reference(f, 100, 2000)
    assert [(r.status, r.code) for r in results] == [(GoalStatus.CANCELED,
                                                      ResultCode.SUCCESSFUL)]
    x, v, a = f.reference(np.arange(100, 2000) * T)
    assert x[0].tolist() == x0.tolist() and v[0].tolist() == v0.tolist()
    assert np.all(v[-1] == 0.0) and np.max(np.abs(a)) <= f.params.stop_acceleration_mps2
    assert np.all((x[-1] > x0) & (x[-1] < [20e-6, 6e-6]))    # short of the targets, each axis


def test_feedback_carries_every_joint_at_its_rate() -> None:
    f = xy_follower()
    f.accept(goal((Y,), P(0.05, (7e-6,))), 0.0)
    feedback = []
    for k in range(0, 500):
        x = f.reference(np.array([k * T]))[0][0]
        _, fb = f.step(k * T, (x + [1e-9, -2e-9]).tolist())
        if fb is not None:
            feedback.append(fb)
    assert [round(fb.time_s / T) for fb in feedback] == [0, 200, 400]
    assert all(fb.desired_m.shape == (2,) for fb in feedback)
    np.testing.assert_allclose(feedback[1].error_m, [-1e-9, 2e-9], rtol=1e-6)


# -- the lockstep node logic with goals against the offline twin ------------------------------

def nodes_in_lockstep(loop: AxesLoopConfig, duration_s: float,
                      requests: Sequence[tuple[float, Any]]) -> tuple[dict[str, Any], Any]:
    """The three logics wired as the nodes wire them, goals submitted at their times."""
    rate = loop.stage.axes[0].sample_rate_hz
    plant = AxesPlantLogic(AxesStage(loop.stage), sample_rate_hz=rate, duration_s=duration_s)
    trajectory = AxesTrajectoryLogic(loop.trajectories(), sample_rate_hz=rate,
                                     chunk_s=loop.base.trajectory_node.chunk_s,
                                     names=loop.stage.names)
    trajectory.attach_goals(axes_follower(loop))
    controller = AxesControllerLogic(
        AxesController.build(loop.controllers, loop.stage, compensate=loop.compensate),
        loop.trajectories())
    # the goals' reference announced as on stage/trajectory: JSON text, before the reference
    # of the sample it changes at
    trajectory.on_reference_change = lambda spline, stamp: controller.request_goal(
        *reversed(parse_axes_goal(announce_axes_goal(stamp, spline))))
    positions, references, commands = [], [], []
    pending = list(requests)
    token = 0
    sample = plant.start(0.0)
    while sample is not None:
        while pending and pending[0][0] <= sample.index * T + 0.5 * T:
            what = pending.pop(0)[1]
            if isinstance(what, JointTrajectoryGoal):
                token += 1
                trajectory.goal(token, what)
            elif what == 'hold':
                trajectory.hold()
            else:
                trajectory.cancel(int(what))
        positions.append(sample.positions_m)
        ref, vel = trajectory.on_position(sample.stamp_ns, sample.positions_m)
        references.append(ref)
        assert controller.on_reference(sample.stamp_ns, ref, vel) is None
        command = controller.on_position(sample.stamp_ns, sample.positions_m)
        assert command is not None
        commands.append(command.commands_v)
        sample = plant.on_command(command.commands_v, 0.0)
    assert controller.late_goals == 0
    return ({k: np.array(v) for k, v in (('position', positions), ('reference', references),
                                         ('command', commands))}, trajectory)


def twin(loop: AxesLoopConfig, duration_s: float, trajectory: AxesTrajectoryLogic) -> Any:
    events = [*trajectory.started, *((t, 'cancel') for t in trajectory.cancelled)]
    return run_axes_goals(AxesStage(loop.stage), AxesController.build(
        loop.controllers, loop.stage, compensate=loop.compensate), loop.trajectories(),
        axes_follower(loop), events, duration_s=duration_s,
        chunk_s=loop.base.trajectory_node.chunk_s)


@pytest.mark.parametrize('ff', ['none', 'inverse'])
def test_goals_through_the_lockstep_logic_give_the_offline_twins_samples(ff: str) -> None:
    # feedback alone, and the model inverse bound to the goals' reference at each change
    loop = loop_of(HOLD, [f'controller_node:feedforward.mode={ff}'])
    assert binds_goals(AxesController.build(loop.controllers, loop.stage)) == (ff == 'inverse')
    five = dict(goal_tolerance=(tol(X, 5e-9), tol(Y, 5e-9)), goal_time_tolerance_s=0.02)
    requests = [
        (0.005, goal((X, Y), P(0.02, (14e-6, 9e-6)), **five)),
        (0.06, goal((Y,), P(0.02, (12e-6,), (0.0,)), **five)),          # y alone: x holds
        # preempted at 0.12 s by a move back
        (0.10, goal((Y, X), P(0.03, (6e-6, 18e-6), (0.0, 0.0), (0.0, 0.0)))),
        (0.12, goal((X, Y), P(0.02, (11e-6, 8e-6)), **five)),
        (0.17, goal((X,), P(0.02, (39e-6,)))),                          # beyond: refused
        (0.18, goal((X, Y), P(0.05, (16e-6, 14e-6)))),
        (0.20, 6),                                      # its token: cancelled half way
    ]
    got, logic = nodes_in_lockstep(loop, 0.3, requests)
    run = twin(loop, 0.3, logic)
    assert [round(t / T) for t, _ in logic.started] == [50, 600, 1000, 1200, 1800]
    assert [round(t / T) for t in logic.cancelled] == [2000]
    for key, mine in (('position', run.position_m), ('reference', run.reference_m),
                      ('command', run.command_v)):
        assert np.array_equal(got[key], mine), key
    # what the goals did, as the action server reports it
    results = [e[1] for e in logic.events if e[0] == 'result']
    assert [(r.goal_id, r.status, r.code) for r in results] == [
        (1, GoalStatus.SUCCEEDED, ResultCode.SUCCESSFUL),
        (2, GoalStatus.SUCCEEDED, ResultCode.SUCCESSFUL),
        (3, GoalStatus.CANCELED, ResultCode.INVALID_GOAL),
        (4, GoalStatus.SUCCEEDED, ResultCode.SUCCESSFUL),
        (5, GoalStatus.CANCELED, ResultCode.SUCCESSFUL)]
    refused = [e[2] for e in logic.events if e[0] == 'verdict' and not e[3]]
    assert len(refused) == 1 and "'stage_x' = 3.9e-05 m" in refused[0].reason
    # the moves were followed: each axis settled at its targets, and held after the cancel
    ref = got['reference']
    assert ref[590].tolist() == [14e-6, 9e-6] and ref[990].tolist() == [14e-6, 12e-6]
    assert np.all(ref[2500:] == ref[-1]) and 11e-6 < ref[-1, 0] < 16e-6
    feedback = [e[1] for e in logic.events if e[0] == 'feedback']
    assert feedback and all(fb.error_m.shape == (2,) for fb in feedback)


def test_before_any_goal_the_logic_with_goals_is_the_scan_bit_for_bit() -> None:
    # the raster of xy_stage.yaml with its feed-forward: goals attached change nothing
    loop = loop_of(['xy_stage.yaml'])
    got, logic = nodes_in_lockstep(loop, 0.02, [])
    run = twin(loop, 0.02, logic)
    assert np.array_equal(got['command'], run.command_v)
    assert np.array_equal(got['reference'], run.reference_m)
    assert np.ptp(got['reference'][:, 0]) > 1e-6


def test_a_goal_takes_the_raster_over_in_motion_and_the_feed_forward_leaves_it_to_the_feedback(
        ) -> None:
    # the raster of xy_stage.yaml (inverse learning, coupling compensation): a goal at 10 ms
    # takes both axes over from their state in motion; the feed-forward, bound to the raster,
    # finds the reference changed and leaves the samples to the feedback, in the nodes as in
    # the twin
    loop = loop_of(['xy_stage.yaml'])
    assert not binds_goals(AxesController.build(loop.controllers, loop.stage))  # it learns
    move = goal((X, Y), P(0.02, (12e-6, 8e-6), (0.0, 0.0), (0.0, 0.0)),
                goal_tolerance=(tol(X, 5e-9), tol(Y, 5e-9)), goal_time_tolerance_s=0.02)
    got, logic = nodes_in_lockstep(loop, 0.06, [(0.01, move)])
    run = twin(loop, 0.06, logic)
    for key, mine in (('position', run.position_m), ('reference', run.reference_m),
                      ('command', run.command_v)):
        assert np.array_equal(got[key], mine), key
    # no jump where the goal takes over: at its sample the reference is the raster's own, and
    # its velocity too (the goal starts from the raster's state there)
    k = round(logic.started[0][0] / T)
    assert k == 100
    scan, _ = nodes_in_lockstep(loop, 0.02, [])
    assert np.array_equal(got['reference'][:k + 1], scan['reference'][:k + 1])
    assert abs(scan['reference'][k + 1, 0] - scan['reference'][k, 0]) > 1e-7  # x in motion
    results = [e[1] for e in logic.events if e[0] == 'result']
    assert [(r.status, r.code) for r in results] == [(GoalStatus.SUCCEEDED,
                                                      ResultCode.SUCCESSFUL)]
    commands = got['command']
    for j, chain in enumerate(a.chain for a in loop.stage.axes):
        assert np.all((commands[:, j] >= chain.amplifier_min_v)
                      & (commands[:, j] <= chain.amplifier_max_v))


def test_three_axes_take_goals_of_one_axis_and_of_all_bit_for_bit_as_the_twin() -> None:
    # xyz_stage.yaml scanning its raster, z holding: a goal of z alone takes every axis over
    # (x and y, not named, come back to rest where their reference was: cubic from their state
    # in motion to that position), then one of all three, in any order
    loop = loop_of(['xyz_stage.yaml'])
    assert loop.stage.names == ('x', 'y', 'z')
    requests = [(0.004, goal((Z,), P(0.01, (12e-6,), (0.0,)))),
                (0.02, goal((Z, X, Y), P(0.01, (8e-6, 11e-6, 7e-6)),
                            goal_tolerance=(tol(Z, 5e-9),), goal_time_tolerance_s=0.02))]
    got, logic = nodes_in_lockstep(loop, 0.05, requests)
    run = twin(loop, 0.05, logic)
    for key, mine in (('position', run.position_m), ('reference', run.reference_m),
                      ('command', run.command_v)):
        assert np.array_equal(got[key], mine), key
    ref = got['reference']
    k = round(logic.started[0][0] / T)
    # x and y at rest where their reference was (the raster's position at the goal's sample)
    assert np.all(ref[k + 100:200, :2] == ref[k, :2]) and ref[150, 2] == 12e-6
    assert ref[-1].tolist() == [11e-6, 7e-6, 8e-6]
    results = [e[1] for e in logic.events if e[0] == 'result']
    assert [r.code for r in results] == [ResultCode.SUCCESSFUL] * 2


def test_each_axis_travel_comes_from_its_own_trajectory_parameters() -> None:
    # trajectory_node axes.y.travel_max_m narrows y's travel alone: the node's follower checks
    # each axis against its own
    loop = loop_of(HOLD, ['trajectory_node:axes.y.travel_max_m=1.2e-05'])
    f = axes_follower(loop)
    assert f.joints == (X, Y) and f.params.partial_joints
    assert f.limits[1].position_max_m == 12e-6 and f.limits[0].position_max_m > 20e-6
    state = (np.array([10e-6, 5e-6]), np.zeros(2), np.zeros(2))
    assert f.check(goal((X,), P(0.02, (20e-6,))), 0.0, start_state=state).accepted
    refused = f.check(goal((Y,), P(0.02, (13e-6,))), 0.0, start_state=state)
    assert refused.code == ResultCode.INVALID_GOAL
    assert "'stage_y' = 1.3e-05 m; allowed: [0, 1.2e-05] m" in refused.reason


def test_a_goal_announcement_builds_the_spline_again_bit_for_bit_and_refuses_garbage() -> None:
    f = xy_follower()
    f.accept(goal((X, Y), P(0.0123, (12.345e-6, 6.789e-6), (0.0, 0.0), (0.0, 0.0)),
                  P(0.03, (11e-6, 8e-6))), 0.001)
    stamp, again = parse_axes_goal(announce_axes_goal(123_456_789, f.spline))
    assert stamp == 123_456_789
    t = np.linspace(0.0, 0.04, 401)
    for mine, theirs in zip(f.spline.sample(t), again.sample(t)):
        assert np.array_equal(mine, theirs)
    for text in ('', '{"stamp_ns": 1}', '{"stamp_ns": 1, "axes_goal": {"start_s": 0}}'):
        with pytest.raises(ParameterError, match='axes_goal'):
            parse_axes_goal(text)


def test_the_goals_benchmark_runs_the_moves_of_several_axes(capsys):
    # the command the results page quotes: every move ends SUCCESSFUL with and without the
    # feed-forward (what the twin tests above hold sample for sample)
    from piezo_stage_ros.bench import goals
    assert goals.main(['--config', 'config/xy_stage.yaml', '--config',
                       'config/xy_hold.yaml']) == 0
    out = capsys.readouterr().out
    assert out.count('SUCCESSFUL') == 10 and "axes ['x', 'y']" in out


@pytest.mark.parametrize('what', ['trajectories', 'follower.joints', 'controller'])
def test_the_twin_refuses_a_count_that_is_not_one_per_axis_naming_it(what: str) -> None:
    # each of the three counts named with its own value, not the trajectories' for all
    loop = loop_of(HOLD)
    trajectories = loop.trajectories()
    follower = axes_follower(loop)
    controller = AxesController.build(loop.controllers, loop.stage, compensate=False)
    if what == 'trajectories':
        trajectories = trajectories[:1]
    elif what == 'follower.joints':
        follower = GoalFollower((X, Y, Z), [AxisLimits.from_stage(loop.stage.axes[0])] * 3,
                                [10e-6, 5e-6, 0.0], FollowParams(sample_time_s=T))
    else:
        controller = AxesController(controller.controllers[:1], compensate=False)
    with pytest.raises(ParameterError, match=rf"'{what}' = [1-3] .*allowed: 2, one per axis"):
        run_axes_goals(AxesStage(loop.stage), controller, trajectories, follower, [],
                       duration_s=T)


class _Sine:
    """x = A sin(w t + phase) [m] and its velocity, exactly."""

    def __init__(self, amplitude_m: float, omega_rad_s: float, phase: float) -> None:
        self.a, self.w, self.phase = amplitude_m, omega_rad_s, phase

    def evaluate(self, time_s: Any) -> tuple[np.ndarray, np.ndarray]:
        arg = self.w * np.asarray(time_s, dtype=np.float64) + self.phase
        return self.a * np.sin(arg), self.a * self.w * np.cos(arg)


def test_the_state_a_goal_takes_over_is_the_trajectories_with_their_acceleration() -> None:
    # x_d'' by the central difference of x_d' over the samples around the index: for a sine,
    # -A w^2 sin(w t) sin(w T) / (w T), within (w T)^2 / 6 of A w^2; rounding: the sines'
    # argument (up to ~10^3 rad, a few 1e-13 rad absolute) over 2 w T
    sines = [_Sine(10e-6, 2 * math.pi * 10.0, 0.3), _Sine(5e-6, 2 * math.pi * 170.0, -1.1)]
    for index in (1, 240, 7001):
        x, v, a = take_over_state(sines, index, T)
        for j, s in enumerate(sines):
            xs, vs = s.evaluate(np.array([index * T]))
            assert x[j] == xs[0] and v[j] == vs[0]
            exact = -s.a * s.w ** 2 * math.sin(s.w * index * T + s.phase)
            wt = s.w * T
            assert abs(a[j] - exact) <= s.a * s.w ** 2 * (wt ** 2 / 6 + 1e-12 / wt)
    # at the first sample nothing came before: at rest in acceleration
    assert take_over_state(sines, 0, T)[2].tolist() == [0.0, 0.0]
