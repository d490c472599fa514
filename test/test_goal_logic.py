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

"""The trajectory node's goal logic without ROS: the same samples as the offline runner."""

from __future__ import annotations

from types import SimpleNamespace as NS  # noqa: N814
from typing import Any, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.wire import JOINT_NAME, NS_PER_S
from piezo_stage_ros.core.loop.follow import (
    GoalLedger,
    GoalResult,
    goals_status,
    GoalStatus,
    run_goals,
)
from piezo_stage_ros.core.loop.goals import JointTolerance, JointTrajectoryGoal, ResultCode
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.nodes import goals_msgs
from piezo_stage_ros.nodes.logic import TrajectoryLogic
import pytest
from test_follow import follower, J, LIMITS, loop, move, P, scan_lines, T

ORIGIN_NS = 1_700_000_000_000_000_000
TOL5 = (JointTolerance(JOINT_NAME, 5e-9),)


def stamp(k: int) -> int:
    return ORIGIN_NS + round(k * NS_PER_S / 1e4)


def hold_logic(x0: float = 3.8e-6, lead_s: float = 0.0, kind: str = 'hold',
               **flat: Any) -> TrajectoryLogic:
    params = TrajectoryParams.from_flat({'kind': kind, 'hold.position_m': x0, **flat})
    logic = TrajectoryLogic(make_trajectory(params, sample_rate_hz=1e4), sample_rate_hz=1e4,
                            chunk_s=0.005)
    logic.attach_goals(follower(x0), lead_s)
    return logic


def drive(logic: TrajectoryLogic, events: Sequence[tuple[float, Any]], duration_s: float,
          ff: str = 'none', x0: float = 3.8e-6) -> dict[str, Any]:
    """Run the loop sample by sample as the lockstep nodes do, with the logic's goals."""
    stage, controller, _ = loop(ff, x0)
    bind = getattr(controller, 'bind', None)
    if callable(bind):
        logic.on_reference_change = lambda view, _stamp: bind(view)
    y = float(stage.reset(x0))
    controller.reset(y, x0)
    total = int(round(duration_s / T))
    pos, ref, cmd = np.empty(total), np.empty(total), np.empty(total)
    pending = sorted(events, key=lambda e: e[0])
    token, j = 0, 0
    for k in range(total):
        while j < len(pending) and pending[j][0] <= k * T + 0.5 * T:
            what = pending[j][1]
            if isinstance(what, JointTrajectoryGoal):
                token += 1
                logic.goal(token, what)
            elif what == 'hold':
                logic.hold()
            else:
                logic.cancel(int(what))
            j += 1
        xd, vd = logic.on_position(stamp(k), y)
        u = controller.step(y, xd, vd)
        pos[k], ref[k], cmd[k] = y, xd, u
        y = float(stage.step(u))
    events_out = list(logic.events)
    return {'position_m': pos, 'reference_m': ref, 'command_v': cmd, 'events': events_out,
            'results': [e[1] for e in events_out if e[0] == 'result'],
            'verdicts': [e for e in events_out if e[0] == 'verdict'],
            'feedback': [e[1] for e in events_out if e[0] == 'feedback']}


def five_moves() -> list[tuple[float, JointTrajectoryGoal]]:
    rng = np.random.default_rng(28)
    targets = rng.uniform(3e-6, LIMITS.position_max_m, 5)
    return [(0.05 * i + 0.01, move(float(x), 0.02, goal_tolerance=TOL5,
                                   goal_time_tolerance_s=0.02)) for i, x in enumerate(targets)]


@pytest.mark.parametrize('lead_s', [0.0, 0.02])
def test_goals_through_the_logic_give_the_offline_runners_samples(lead_s: float) -> None:
    goals = five_moves()
    logic = hold_logic(lead_s=lead_s)
    got = drive(logic, goals, 0.3)
    # in real time a goal starts lead_s after it came: the runner gets it then
    shift = round(lead_s / T) * T
    run = run_goals(*loop(), [(t + shift, g) for t, g in goals], duration_s=0.3)
    assert np.array_equal(got['reference_m'], run.reference_m)
    assert np.array_equal(got['command_v'], run.command_v)
    assert np.array_equal(got['position_m'], run.position_m)
    assert [(r.goal_id, r.status, r.code, r.time_s) for r in got['results']] == \
        [(r.goal_id, r.status, r.code, r.time_s) for r in run.results]
    assert [r.code for r in got['results']] == [ResultCode.SUCCESSFUL] * 5
    assert [v[1:] for v in got['verdicts']] == [
        (i + 1, v, i + 1) for i, (_, v, _) in enumerate(run.verdicts)]
    assert [(f.goal_id, f.time_s) for f in got['feedback']] == \
        [(f.goal_id, f.time_s) for f in run.feedback]
    # the feedback takes the reference the sample played: the follower's spline's values
    for a, b in zip(got['feedback'], run.feedback):
        for name in ('desired_m', 'desired_velocity_mps', 'actual_m', 'error_m'):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_scan_lines_with_the_inverse_feed_forward_bound_again_at_each_change() -> None:
    goal = JointTrajectoryGoal(J, scan_lines(lines=3), path_tolerance=(
        JointTolerance(JOINT_NAME, 10e-9),), goal_tolerance=TOL5, goal_time_tolerance_s=0.02)
    got = drive(hold_logic(5e-6), [(0.0, goal)], 0.33, ff='inverse', x0=5e-6)
    run = run_goals(*loop('inverse', 5e-6), [(0.0, goal)], duration_s=0.33)
    assert [r.code for r in got['results']] == [ResultCode.SUCCESSFUL]
    assert np.array_equal(got['command_v'], run.command_v)


def test_a_goal_beyond_the_travel_is_refused_with_the_reason_and_nothing_moves() -> None:
    logic = hold_logic()
    got = drive(logic, [(0.0, move(39e-6, 0.02))], 0.01)
    (_, token, verdict, goal_id), = got['verdicts']
    assert (token, goal_id, verdict.code) == (1, 0, ResultCode.INVALID_GOAL)
    assert 'position of' in verdict.reason and '3.9e-05' in verdict.reason
    assert np.all(got['reference_m'] == 3.8e-6)
    assert not logic.goal_active


def test_preemption_and_cancel_through_the_logic() -> None:
    logic = hold_logic()
    first = move(20e-6, 0.02, quintic=True)
    second = move(8e-6, 0.02, quintic=True)
    got = drive(logic, [(0.0, first), (0.01, second), (0.02, '2')], 0.06)
    results = got['results']
    assert [(r.goal_id, r.status, r.code) for r in results] == [
        (1, GoalStatus.CANCELED, ResultCode.INVALID_GOAL),
        (2, GoalStatus.CANCELED, ResultCode.SUCCESSFUL)]
    assert results[0].time_s == pytest.approx(0.01)
    # the reference never jumps: its steps stay those of the moves themselves
    ref = got['reference_m']
    alone = drive(hold_logic(), [(0.0, first)], 0.06)['reference_m']
    assert np.max(np.abs(np.diff(ref))) <= np.max(np.abs(np.diff(alone))) * (1 + 1e-12)
    # cancelled at 20 ms: at rest afterwards, short of 8 um, between the two
    assert ref[-1] == ref[-2] and 8e-6 < ref[-1] < 20e-6


def test_a_goal_cancelled_before_its_start_never_moves() -> None:
    logic = hold_logic(lead_s=0.02)
    logic.on_position(stamp(0), 3.8e-6)
    logic.goal(1, move(10e-6, 0.02))
    logic.cancel(1)
    for k in range(1, 400):
        assert logic.on_position(stamp(k), 3.8e-6) == (3.8e-6, 0.0)
    assert list(logic.events) == [('cancelled', 1)]


def test_a_goal_checked_ahead_is_checked_again_when_the_reference_changed() -> None:
    logic = hold_logic(lead_s=0.02)
    logic.on_position(stamp(0), 3.8e-6)
    logic.goal(1, move(10e-6, 0.02))          # for sample 201
    logic.switch(make_trajectory(TrajectoryParams.from_flat(
        {'kind': 'hold', 'hold.position_m': 5e-6})))
    for k in range(1, 300):
        logic.on_position(stamp(k), 3.8e-6)
    assert [e[0] for e in logic.events] == ['retry']
    assert logic.events[0][1:3] == (1, move(10e-6, 0.02))


@pytest.mark.parametrize('skipped', [1, 5, 20])
def test_a_goal_whose_start_sample_the_servo_skipped_starts_on_its_own_sample(skipped: int
                                                                              ) -> None:
    # real time: the servo skipped the sample the goal was checked for (a loaded machine);
    # the next sample served, at most GOAL_LATE_START_S later, starts it on the grid where it
    # was checked: the reference there is the goal's, as if the samples between were
    # skipped within it, and the same as a goal started on time
    from piezo_stage_ros.nodes.logic import GOAL_LATE_START_S
    on_time, late = hold_logic(lead_s=0.02), hold_logic(lead_s=0.02)
    for logic in (on_time, late):
        logic.on_position(stamp(0), 3.8e-6)
        logic.goal(1, move(10e-6, 0.02))        # checked for sample 201
    for k in range(1, 260):
        on_time.on_position(stamp(k), 3.8e-6)
    ref_late = {}
    for k in [*range(1, 201), *range(201 + skipped, 260)]:
        ref_late[k] = late.on_position(stamp(k), 3.8e-6)
    assert skipped * T <= GOAL_LATE_START_S + 1e-12
    assert late.events[0][0] == 'verdict' and late.events[0][3] > 0
    assert 'retry' not in [e[0] for e in late.events]
    assert [t for t, _ in late.started] == [t for t, _ in on_time.started] == [201 * T]
    x, v, _ = on_time.follower.reference(np.arange(201 + skipped, 260) * T)
    np.testing.assert_array_equal([ref_late[k][0] for k in range(201 + skipped, 260)], x[:, 0])


def test_a_goal_whose_start_sample_passed_long_ago_is_checked_again() -> None:
    from piezo_stage_ros.nodes.logic import GOAL_LATE_START_S
    logic = hold_logic(lead_s=0.02)
    logic.on_position(stamp(0), 3.8e-6)
    logic.goal(1, move(10e-6, 0.02))            # checked for sample 201
    passed = 201 + round(GOAL_LATE_START_S / T) + 2
    for k in [*range(1, 201), *range(passed, passed + 10)]:
        logic.on_position(stamp(k), 3.8e-6)
    assert [e[0] for e in logic.events] == ['retry'] and not logic.goal_active


def test_a_goal_takes_a_sine_over_in_motion_without_a_jump() -> None:
    logic = hold_logic(kind='sine', **{'sine.frequency_hz': 10.0})
    # near the crest (25 ms): a goal from the sine's state moves on from there
    refs = [logic.on_position(stamp(k), 0.0)[0] for k in range(240)]
    logic.goal(1, move(10e-6, 0.05, quintic=True))
    refs += [logic.on_position(stamp(k), 0.0)[0] for k in range(240, 1000)]
    assert logic.goal_active and logic.events[0][3] == 1, logic.events
    steps = np.diff(refs)
    # no jump where the goal takes over: the step there is the sine's own (rising to the
    # crest), and the change of step (the acceleration) stays that of the sine
    assert abs(steps[240] - steps[239]) <= 1.01 * np.max(np.abs(np.diff(steps[:239])))
    assert refs[-1] == 10e-6


def test_commands_ahead_see_a_goal_once_it_changed_the_reference() -> None:
    logic = hold_logic()
    logic.on_position(stamp(0), 3.8e-6)
    ahead, _ = logic.window(stamp(0), 50)
    assert np.all(ahead == 3.8e-6)
    logic.goal(1, move(10e-6, 0.002, quintic=True))
    logic.on_position(stamp(1), 3.8e-6)
    ahead, _ = logic.window(stamp(1), 50)
    assert ahead[-1] == 10e-6 and ahead[0] > 3.8e-6


def test_a_new_trajectory_ends_the_goal() -> None:
    logic = hold_logic()
    logic.on_position(stamp(0), 3.8e-6)
    logic.goal(1, move(10e-6, 0.02))
    logic.on_position(stamp(1), 3.8e-6)
    logic.switch(make_trajectory(TrajectoryParams.from_flat({'kind': 'hold'})))
    logic.on_position(stamp(2), 3.8e-6)
    result = [e[1] for e in logic.events if e[0] == 'result']
    assert [(r.status, r.code) for r in result] == [(GoalStatus.CANCELED,
                                                      ResultCode.INVALID_GOAL)]
    assert not logic.goal_active


def _duration(s: float) -> NS:
    return NS(sec=int(s), nanosec=round((s - int(s)) * 1e9))


def _msg(points: list[NS], **kw: Any) -> NS:
    traj = NS(header=NS(stamp=NS(sec=0, nanosec=0)), joint_names=[JOINT_NAME], points=points)
    base = dict(trajectory=traj, multi_dof_trajectory=NS(points=[]), path_tolerance=[],
                component_path_tolerance=[], goal_tolerance=[], component_goal_tolerance=[],
                goal_time_tolerance=_duration(0.0))
    return NS(**{**base, **kw})


def test_messages_convert_field_by_field() -> None:
    msg = _msg([NS(time_from_start=_duration(0.0205), positions=[1e-5], velocities=[],
                   accelerations=[])],
               goal_tolerance=[NS(name=JOINT_NAME, position=5e-9, velocity=0.0,
                                  acceleration=0.0)],
               goal_time_tolerance=_duration(0.02))
    goal, verdict = goals_msgs.goal_from_msg(msg)
    assert verdict.accepted and goal is not None
    assert goal == JointTrajectoryGoal(J, (P(0.0205, (1e-5,)),), (),
                                       (JointTolerance(JOINT_NAME, 5e-9),), 0.02)
    assert goals_msgs.stamp_ns(msg.trajectory.header) is None
    assert goals_msgs.stamp_ns(NS(stamp=NS(sec=2, nanosec=5))) == 2_000_000_005
    cubic = goals_msgs.trajectory_from_msg(NS(joint_names=['x'], points=[
        NS(time_from_start=_duration(1.0), positions=[1.0], velocities=[0.5],
           accelerations=[])]))
    assert cubic.points[0].velocities_mps == (0.5,) and cubic.points[0].accelerations_mps2 == ()


@pytest.mark.parametrize('field', ['component_path_tolerance', 'component_goal_tolerance'])
def test_component_tolerances_are_refused_with_the_reason(field: str) -> None:
    goal, verdict = goals_msgs.goal_from_msg(_msg([], **{field: [NS()]}))
    assert goal is None and verdict.code == ResultCode.INVALID_GOAL
    assert field in verdict.reason


def test_unknown_joints_reach_the_follower_and_are_refused_there() -> None:
    msg = _msg([NS(time_from_start=_duration(0.02), positions=[1e-5], velocities=[],
                   accelerations=[])])
    msg.trajectory.joint_names = ['x']
    goal, _ = goals_msgs.goal_from_msg(msg)
    assert goal is not None
    logic = hold_logic()
    logic.goal(1, goal)
    logic.on_position(stamp(0), 3.8e-6)
    (_, _, verdict, _), = logic.events
    assert verdict.code == ResultCode.INVALID_JOINTS and "'x'" in verdict.reason


def test_the_goals_status_warns_after_a_violated_tolerance_then_recovers() -> None:
    logic = hold_logic()
    ledger = GoalLedger()
    got = drive(logic, [(0.0, move(39e-6, 0.02)),
                        (0.001, move(10e-6, 0.02, goal_tolerance=TOL5,
                                     goal_time_tolerance_s=0.005))], 0.002)
    for event in got['events']:
        ledger.take(event)
    status = ledger.status(0.002)
    assert status.level == 0 and dict(status.values)['refused_goals'] == '1'
    assert dict(status.values)['active_goal'] == '1' and status.message == 'moving: goal 1'
    # the goal ends GOAL_TOLERANCE_VIOLATED (a measurement 1 um off): WARN for 10 s
    violated = GoalResult(1, GoalStatus.ABORTED, ResultCode.GOAL_TOLERANCE_VIOLATED,
                          "joint 'stage': error 1e-06 m", 0.03)
    ledger.take(('result', violated))
    status = ledger.status(0.03 + 9.9)
    assert status.level == 1 and 'GOAL_TOLERANCE_VIOLATED' in status.message
    assert dict(status.values)['last_result_code'] == '-5 GOAL_TOLERANCE_VIOLATED'
    assert dict(status.values)['active_goal'] == ''
    assert ledger.status(0.03 + 10.1).level == 0
    assert goals_status('hold', None, None, 0, 0.0).values[3] == ('last_result_text', '')


def test_a_goal_whose_checks_keep_missing_their_sample_is_refused_not_retried_forever():
    # every check finds its sample passed (a check slower than the lead): the goal is checked
    # again further ahead a bounded number of times, then refused with the reason
    from piezo_stage_ros.nodes.logic import GOAL_RETRIES
    logic = hold_logic(lead_s=0.02)
    logic.on_position(stamp(0), 3.8e-6)
    k, retries = 0, 0
    logic.goal(1, move(10e-6, 0.05))
    for _ in range(GOAL_RETRIES + 1):
        k += 100000                        # far past the sample it was checked for
        logic.on_position(stamp(k), 3.8e-6)
        events = list(logic.events)
        logic.events.clear()
        kinds = [e[0] for e in events]
        if 'retry' in kinds:
            retries += 1
            _, token, goal, tracked, stamp_ns = events[kinds.index('retry')]
            logic.goal(token, goal, tracked=tracked, stamp_ns=stamp_ns)
    assert retries == GOAL_RETRIES
    (verdict,) = [e for e in events if e[0] == 'verdict']
    assert verdict[3] == 0 and verdict[2].code == ResultCode.INVALID_GOAL
    assert 'could not be started' in verdict[2].reason and not logic.goal_active


def test_a_topic_goal_keeps_no_token_once_started():
    logic = hold_logic(lead_s=0.0)
    logic.on_position(stamp(0), 3.8e-6)
    for token in (1, 2, 3):
        logic.goal(token, move(5e-6 + token * 1e-6, 0.01), tracked=False)
        logic.on_position(stamp(token), 3.8e-6)
    assert [e[3] for e in logic.events if e[0] == 'verdict'] == [1, 2, 3]
    assert logic._tokens == {}


def test_a_goal_announcement_builds_the_reference_again_bit_for_bit():
    # what a controller in another process binds: the follower's spline as it stood, sent as
    # JSON and built again, evaluates to the same floats as the trajectory node's own view
    from piezo_stage_ros.core.contracts.errors import ParameterError
    from piezo_stage_ros.core.loop.follow import GoalTrajectory
    from piezo_stage_ros.core.loop.splines import Spline
    from piezo_stage_ros.nodes.logic import announce_goal, parse_announcement
    f = follower()
    goal = JointTrajectoryGoal(J, (P(0.004, (6e-6,), (1e-3,)), P(0.01, (4e-6,), (0.0,))))
    verdict, prepared = f.prepare(goal, 0.0)
    assert prepared is not None, verdict
    f.start(prepared, 0.0)
    view = GoalTrajectory(f)
    text = announce_goal(123_000, view.snapshot())
    stamp, again = parse_announcement(text)
    assert stamp == 123_000 and again.kind == 'goal'
    t = np.arange(0, 200) * T
    for mine, theirs in zip(view.evaluate(t), again.evaluate(t)):
        np.testing.assert_array_equal(mine, theirs)
    assert again.spline.record() == f.spline.record()
    # a trajectory's announcement still reads as its parameters
    stamp, params = parse_announcement('{"stamp_ns": 5, "trajectory": {"kind": "sine"}}')
    assert stamp == 5 and params.kind == 'sine'
    with pytest.raises(ParameterError, match='goal announcement'):
        parse_announcement('{"stamp_ns": 5, "goal": {"start_s": 0.0}, "axis": 0}')
    from piezo_stage_ros.core.contracts.errors import PiezoStageError
    with pytest.raises(PiezoStageError, match='spline record'):
        Spline.from_record({})


def test_a_goal_whose_check_ended_after_its_sample_was_served_is_checked_again() -> None:
    # checked in slices in the servo's idle time: when the check ends after the sample it was
    # made for has been served (the stage went on holding there), starting it late would make
    # the reference jump by the way the goal had gone meanwhile; it is checked again further
    # ahead instead, and starts from where the stage is, without a jump
    logic = hold_logic(lead_s=0.02)
    logic.check_in_slices = True
    logic.on_position(stamp(0), 3.8e-6)
    logic.goal(1, move(10e-6, 0.02))
    assert logic.work()                         # its first slice: checked for sample 201
    refs = [logic.on_position(stamp(k), 3.8e-6)[0] for k in range(1, 211)]
    while logic.has_work:                       # the check ends at sample 210: 0.9 ms late
        logic.work()
    refs += [logic.on_position(stamp(k), 3.8e-6)[0] for k in range(211, 700)]
    assert 'retry' in [e[0] for e in logic.events]
    assert not logic.started or logic.started[0][0] > 210 * T
    assert np.max(np.abs(np.diff(refs))) < 1e-8  # the move's own steps: 6.2 um in 20 ms


def test_a_goal_served_at_a_sample_sent_again_starts_there() -> None:
    # lockstep: the plant resends a sample whose command did not come; a goal that arrived
    # meanwhile starts at that sample, as at any other (no jump: it is its own sample)
    logic = hold_logic()
    logic.on_position(stamp(0), 3.8e-6)
    logic.on_position(stamp(1), 3.8e-6)
    logic.goal(1, move(10e-6, 0.02))
    logic.on_position(stamp(1), 3.8e-6)         # sample 1 sent again
    assert 'retry' not in [e[0] for e in logic.events]
    assert logic.events[0][0] == 'verdict' and logic.events[0][3] > 0
    assert [t for t, _ in logic.started] == [1 * T]
