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

"""Following goals: tolerances, results, feedback, preemption, cancel; the offline loop."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from piezo_stage_ros.core.config.loader import load_config, LoopConfig
from piezo_stage_ros.core.contracts.wire import JOINT_NAME
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.loop import closed_loop
from piezo_stage_ros.core.loop.follow import (
    FollowParams,
    GoalFollower,
    GoalRun,
    GoalStatus,
    GoalTrajectory,
    PREEMPTED,
    run_goals,
)
from piezo_stage_ros.core.loop.goals import (
    AxisLimits,
    JointTolerance,
    JointTrajectoryGoal,
    ResultCode,
    TrajectoryPoint,
)
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant, Stage
import pytest

T = 1e-4
CONFIG_DIR = Path(__file__).resolve().parents[1] / 'config'
J = (JOINT_NAME,)
P = TrajectoryPoint
CONFIG = LoopConfig.from_config(load_config([CONFIG_DIR / 'default.yaml']))
STAGE = CONFIG.stage
LIMITS = AxisLimits.from_stage(STAGE)


def follower(x0: float = 3.8e-6, **kw: Any) -> GoalFollower:
    return GoalFollower(J, [LIMITS], [x0], FollowParams(sample_time_s=T, **kw))


def move(x: float, duration_s: float = 0.02, *, quintic: bool = False, **kw: Any
         ) -> JointTrajectoryGoal:
    point = P(duration_s, (x,), (0.0,), (0.0,)) if quintic else P(duration_s, (x,))
    return JointTrajectoryGoal(J, (point,), **kw)


def drive(f: GoalFollower, until_s: float, offset_m: float = 0.0, start_s: float = 0.0
          ) -> tuple[list[Any], list[Any]]:
    """Step the follower with the measurement at the reference plus an offset."""
    results, feedback = [], []
    for k in range(int(round(start_s / T)), int(round(until_s / T))):
        t = k * T
        x, _, _ = f.reference(np.array([t]))
        r, fb = f.step(t, x[0] + offset_m)
        if r is not None:
            results.append(r)
        if fb is not None:
            feedback.append(fb)
    return results, feedback


def test_success_waits_for_the_settle_time_and_feedback_comes_at_its_rate() -> None:
    f = follower(settle_s=1e-3, feedback_period_s=0.02)
    verdict, gid = f.accept(move(10e-6, 0.05, goal_tolerance=(JointTolerance(JOINT_NAME, 5e-9),)),
                            0.0)
    assert verdict.accepted and gid == 1
    results, feedback = drive(f, 0.1)
    assert [(r.status, r.code) for r in results] == [(GoalStatus.SUCCEEDED, ResultCode.SUCCESSFUL)]
    # ten samples inside the tolerance from the last point at 50 ms on: 50.9 ms
    assert results[0].time_s == pytest.approx(0.05 + 9 * T, abs=T / 2)
    # feedback at 0, 20 and 40 ms while the goal runs; none after it ended
    assert [round(fb.time_s / T) for fb in feedback] == [0, 200, 400]
    assert all(fb.error_m[0] == 0.0 for fb in feedback)
    assert f.phase == 'hold' and f.active_goal is None


def test_goal_tolerance_violated_after_the_goal_time() -> None:
    f = follower()
    f.accept(move(10e-6, 0.02, goal_tolerance=(JointTolerance(JOINT_NAME, 5e-9),),
                  goal_time_tolerance_s=0.01), 0.0)
    results, _ = drive(f, 0.05, offset_m=-8e-9)
    assert len(results) == 1 and results[0].code == ResultCode.GOAL_TOLERANCE_VIOLATED
    assert results[0].status == GoalStatus.ABORTED
    assert results[0].time_s == pytest.approx(0.03 + T, abs=T / 2)
    assert 'error 8e-09 m' in results[0].reason and '<= 5e-09 m' in results[0].reason


def test_path_tolerance_violated_stops_the_reference() -> None:
    f = follower(stop_acceleration_mps2=5.0)
    f.accept(move(20e-6, 0.02, path_tolerance=(JointTolerance(JOINT_NAME, 10e-9),)), 0.0)
    drive(f, 0.005)
    results, _ = drive(f, 0.03, offset_m=20e-9, start_s=0.005)
    assert results[0].code == ResultCode.PATH_TOLERANCE_VIOLATED
    assert results[0].time_s == pytest.approx(0.005, abs=T / 2)
    assert 'path error -2e-08 m' in results[0].reason
    # the reference stopped short of 20 um and rests
    x, v, a = f.reference(np.arange(50, 300) * T)
    assert x[-1, 0] < 20e-6 and v[-1, 0] == 0.0
    assert np.max(np.abs(a)) <= 5.0


def test_unchecked_tolerances_succeed_at_the_last_point() -> None:
    f = follower()
    f.accept(move(10e-6, 0.02, goal_tolerance=(JointTolerance(JOINT_NAME, -1.0),)), 0.0)
    results, _ = drive(f, 0.03, offset_m=1e-6)
    assert results[0].code == ResultCode.SUCCESSFUL
    assert results[0].time_s == pytest.approx(0.02, abs=T / 2)


def test_preemption_starts_from_the_present_reference_and_cancels_the_old_goal() -> None:
    f = follower()
    f.accept(move(20e-6, 0.02, quintic=True), 0.0)
    before = f.reference(np.array([0.0101]))
    verdict, gid = f.accept(move(8e-6, 0.02, quintic=True), 0.0101)
    assert verdict.accepted and gid == 2
    assert [(r.goal_id, r.status, r.code, r.reason) for r in f.results] == [
        (1, GoalStatus.CANCELED, ResultCode.INVALID_GOAL, PREEMPTED)]
    after = f.reference(np.array([0.0101]))
    # position, velocity and acceleration carry over: the quintic starts where the other was
    for b, a in zip(before, after):
        assert a[0, 0] == b[0, 0]


def test_a_refused_goal_changes_nothing() -> None:
    f = follower()
    f.accept(move(20e-6, 0.02), 0.0)
    version = f.version
    verdict, gid = f.accept(move(39e-6), 0.01)
    assert verdict.code == ResultCode.INVALID_GOAL and gid == 0
    assert f.version == version and f.active_goal == 1 and not f.results


def test_cancel_decelerates_within_the_stop_acceleration_and_then_holds() -> None:
    f = follower(stop_acceleration_mps2=2.0)
    f.accept(move(20e-6, 0.02, quintic=True), 0.0)
    drive(f, 0.01)
    x0, v0, _ = f.reference(np.array([0.01]))
    f.cancel(0.01)
    assert f.phase == 'stopping'
    results, _ = drive(f, 0.03, start_s=0.01)
    assert [(r.status, r.code) for r in results] == [(GoalStatus.CANCELED, ResultCode.SUCCESSFUL)]
    x, v, a = f.reference(np.arange(100, 300) * T)
    assert x[0, 0] == x0[0, 0] and v[0, 0] == v0[0, 0]
    assert np.max(np.abs(a)) <= 2.0
    assert np.all(np.diff(x[:, 0]) >= 0.0)        # it decelerates, it does not turn back
    assert v[-1, 0] == 0.0 and f.phase == 'hold'


def test_a_topic_trajectory_has_no_result_and_no_feedback() -> None:
    f = follower()
    verdict, _ = f.accept(move(10e-6, 0.02), 0.0, tracked=False)
    assert verdict.accepted
    results, feedback = drive(f, 0.03)
    assert not results and not feedback
    assert f.reference(np.array([0.03]))[0][0, 0] == 10e-6


def loop(ff: str = 'none', x0: float = 3.8e-6) -> tuple[Stage, Any, GoalFollower]:
    cp = CONFIG.controller if ff == 'none' else \
        ControllerParams.from_flat({**CONFIG.controller.to_flat(), 'feedforward.mode': ff})
    controller = build_controller(cp, T, linear_plant(STAGE.plant),
                                  make_hysteresis(STAGE.hysteresis))
    return Stage(STAGE), controller, follower(x0)


def test_five_moves_succeed_and_settle_within_5_nm() -> None:
    rng = np.random.default_rng(28)
    # 3 ... 30 um, but not beyond what the amplifier reaches (refused, next test)
    targets = rng.uniform(3e-6, LIMITS.position_max_m, 5)
    goals = [(0.05 * i, move(float(x), 0.02,
                             goal_tolerance=(JointTolerance(JOINT_NAME, 5e-9),),
                             goal_time_tolerance_s=0.02)) for i, x in enumerate(targets)]
    run = run_goals(*loop(), goals, duration_s=0.25)
    assert [(r.goal_id, r.code) for r in run.results] == [
        (i + 1, ResultCode.SUCCESSFUL) for i in range(5)]
    for r, (start, _) in zip(run.results, goals):
        # settled: from the success to the next goal the error stays inside the tolerance
        k0, k1 = int(round(r.time_s / T)), int(round((start + 0.05) / T))
        error = run.reference_m[k0:k1] - run.position_m[k0:k1]
        assert np.max(np.abs(error)) <= 5e-9


def test_a_goal_beyond_the_reach_is_refused_with_the_reason() -> None:
    run = run_goals(*loop(), [(0.0, move(30e-6)), (0.01, move(39e-6))], duration_s=0.02)
    codes = [(v.code, v.reason) for _, v, _ in run.verdicts]
    for code, reason in codes:
        assert code == ResultCode.INVALID_GOAL
        assert 'allowed: [0, 2.88' in reason and "the amplifier's static reach" in reason
    assert np.all(run.reference_m == 3.8e-6)


def scan_lines(lines: int = 10, per_line: int = 100, spacing_s: float = 1e-3,
               low_m: float = 5e-6, high_m: float = 15e-6) -> tuple[TrajectoryPoint, ...]:
    """Trace and retrace ``lines`` times, with the slope as velocity (0 at the turns)."""
    half = per_line // 2
    slope = (high_m - low_m) / (half * spacing_s)
    points = []
    for k in range(lines * per_line):
        j = k % per_line
        phase = j / half if j < half else 2.0 - j / half
        v = 0.0 if j in (0, half) or k == lines * per_line - 1 else \
            (slope if j < half else -slope)
        points.append(P((k + 1) * spacing_s, (low_m + (high_m - low_m) * phase,), (v,)))
    return tuple(points)


def test_a_thousand_scan_points_within_a_10_nm_path_tolerance() -> None:
    points = scan_lines()
    assert len(points) == 1000
    goal = JointTrajectoryGoal(J, points, path_tolerance=(JointTolerance(JOINT_NAME, 10e-9),),
                               goal_tolerance=(JointTolerance(JOINT_NAME, 5e-9),),
                               goal_time_tolerance_s=0.02)
    run = run_goals(*loop('inverse', x0=5e-6), [(0.0, goal)], duration_s=1.02)
    assert [r.code for r in run.results] == [ResultCode.SUCCESSFUL], run.results


def test_a_feed_forward_follows_goals_from_rest() -> None:
    # the goal comes while the loop holds: the feed-forward, bound again, reads the new
    # reference ahead and never falls back to feedback alone
    stage, controller, f = loop('inverse')
    goal = JointTrajectoryGoal(J, (P(0.02, (20e-6,), (0.0,), (0.0,)),))
    run = run_goals(stage, controller, f, [(0.0123, goal)], duration_s=0.05)
    assert controller.mismatches == 0
    assert [r.code for r in run.results] == [ResultCode.SUCCESSFUL]


def _largest_steps(run: GoalRun) -> tuple[float, float]:
    return (float(np.max(np.abs(np.diff(run.reference_m)))),
            float(np.max(np.abs(np.diff(run.command_v)))))


@pytest.mark.parametrize('second', ['preempt', 'cancel'])
def test_preemption_and_cancel_add_no_step(second: str) -> None:
    # quintic moves: the reference stays smooth through a new goal or a cancel, so neither the
    # reference nor the command takes a step larger than the uninterrupted move's own
    first = move(20e-6, 0.02, quintic=True)
    alone = run_goals(*loop(), [(0.0, first)], duration_s=0.05)
    then: Any = move(8e-6, 0.02, quintic=True) if second == 'preempt' else 'cancel'
    cut = run_goals(*loop(), [(0.0, first), (0.01, then)], duration_s=0.05)
    dx_alone, _ = _largest_steps(alone)
    dx_cut, _ = _largest_steps(cut)
    assert dx_cut <= dx_alone
    k = int(round(0.01 / T))
    jumps = np.abs(np.diff(cut.reference_m[k - 5:k + 5]))
    assert np.max(jumps) <= dx_alone
    # from the switch on, the command changes no faster than during the move alone
    _, du_alone = _largest_steps(alone)
    assert np.max(np.abs(np.diff(cut.command_v[k - 1:]))) <= du_alone
    assert cut.results[0].status == GoalStatus.CANCELED


def test_the_offline_runner_and_the_follower_loop_give_identical_samples() -> None:
    # a goal known at t = 0 bound as a trajectory in the offline runner, and the same goal
    # followed sample by sample: the lockstep node does the latter
    goal = JointTrajectoryGoal(J, scan_lines(lines=2))
    stage, controller, f = loop()
    run = run_goals(stage, controller, f, [(0.0, goal)], duration_s=0.25)
    stage, controller, f = loop()
    f.accept(goal, 0.0)
    record = closed_loop.run(stage, controller, GoalTrajectory(f), duration_s=0.25,
                             record_diagnostics=False, chunk_s=0.1)
    assert np.array_equal(record.reference_m, run.reference_m)
    assert np.array_equal(record.command_v, run.command_v)
    assert np.array_equal(record.position_m, run.position_m)


def test_several_axes_follow_in_the_stage_order_whatever_the_goal_order() -> None:
    # two axes (the multi-axis stage to come): the goal names them in the other order
    f = GoalFollower(('x', 'y'), [LIMITS, LIMITS], [3.8e-6, 5e-6], FollowParams(sample_time_s=T))
    goal = JointTrajectoryGoal(('y', 'x'), (P(0.01, (7e-6, 10e-6), (0.0, 0.0), (0.0, 0.0)),),
                               goal_tolerance=(JointTolerance('y', 5e-9),))
    verdict, _ = f.accept(goal, 0.0)
    assert verdict.accepted
    x, v, _ = f.reference(np.array([0.0, 0.01, 0.02]))
    assert x.shape == (3, 2)
    assert x[0].tolist() == [3.8e-6, 5e-6] and x[2].tolist() == [10e-6, 7e-6]
    assert np.all(v[2] == 0.0)
    # y on its target, x 1 um off but unchecked (no tolerance given, default 0): success
    # after the ten samples of settle_s
    results = []
    for k in range(0, 300):
        ref = f.reference(np.array([k * T]))[0][0]
        result, _ = f.step(k * T, ref + np.array([1e-6, 0.0]))
        if result is not None:
            results.append(result)
    assert [r.code for r in results] == [ResultCode.SUCCESSFUL]
    assert results[0].time_s == pytest.approx(0.01 + 9 * T, abs=T / 2)
    missing = JointTrajectoryGoal(('x',), (P(0.01, (7e-6,)),))
    assert f.check(missing, 0.03).code == ResultCode.INVALID_JOINTS


def test_hold_ends_the_goal_at_once_and_stops_the_reference() -> None:
    # deactivation: the goal ends now (jtc's words), the reference still comes to rest smoothly
    f = follower()
    f.accept(move(20e-6, 0.02, quintic=True), 0.0)
    drive(f, 0.01)
    x0, v0, _ = f.reference(np.array([0.01]))
    result = f.hold(0.01)
    assert result is not None and result.status == GoalStatus.CANCELED
    assert result.reason == 'Current goal cancelled during deactivate transition.'
    x, v, a = f.reference(np.arange(100, 200) * T)
    assert x[0, 0] == x0[0, 0] and v[0, 0] == v0[0, 0] and v[-1, 0] == 0.0
    assert np.max(np.abs(a)) <= f.params.stop_acceleration_mps2
    assert f.hold(0.02) is None                    # nothing left to end


def test_a_goal_prepared_ahead_starts_as_if_accepted_then() -> None:
    # a real-time loop checks and builds outside its sample, for a sample a little ahead
    first = move(20e-6, 0.02, quintic=True)
    second = move(8e-6, 0.02, quintic=True)
    f, g = follower(), follower()
    f.accept(first, 0.0)
    g.accept(first, 0.0)
    verdict, prepared = f.prepare(second, 0.012)
    assert verdict.accepted and prepared is not None
    drive(f, 0.012)
    assert f.start(prepared, 0.0121) == 0          # not the sample it was prepared for
    assert f.start(prepared, 0.012) == 2
    g.accept(second, 0.012)
    t = np.arange(100, 400) * T
    for a, b in zip(f.reference(t), g.reference(t)):
        assert np.array_equal(a, b)
    # a reference changed in between (a cancel): prepare again
    _, stale = f.prepare(first, 0.02)
    f.cancel(0.015)
    assert stale is not None and f.start(stale, 0.02) == 0


def test_a_cancel_while_accelerating_harder_than_the_stop_allows_starts_from_that() -> None:
    # 5 um in 2 ms: about 7 m/s^2 a quarter of the way, above the 1 m/s^2 of a stop; the stop
    # starts with the present acceleration (no step) and never exceeds it
    f = follower()
    f.accept(move(8.8e-6, 0.002, quintic=True), 0.0)
    _, v0, a0 = f.reference(np.array([0.0004]))
    assert abs(a0[0, 0]) > 5.0
    f.cancel(0.0004)
    x, v, a = f.reference(np.arange(4, 400) * T)
    assert v[0, 0] == v0[0, 0] and a[0, 0] == a0[0, 0]
    assert np.max(np.abs(a)) <= abs(a0[0, 0])
    assert v[-1, 0] == 0.0
