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

"""A goal checked a slice at a time: the same verdicts, splines and samples as at once."""

from __future__ import annotations

import dataclasses
from typing import Any

from fake_clock import FakeClock
import numpy as np
from piezo_stage_ros.core.config.loader import load_loop_config
from piezo_stage_ros.core.loop.follow import PreparedGoal
from piezo_stage_ros.core.loop.goals import (
    finish,
    JointTolerance,
    JointTrajectoryGoal,
    validate_goal,
    validation_steps,
)
from piezo_stage_ros.hardware.pacing import Pacer
from piezo_stage_ros.nodes import servo as servo_module
import pytest
from test_follow import follower, J, LIMITS, move, P, scan_lines, T

#: (points, samples) per slice: single ones, odd sizes that cut blocks anywhere, the servo's
SLICES = [(1, 1), (3, 7), (32, 128), (0, 0)]


def _humps(*speeds: float) -> JointTrajectoryGoal:
    """Near the top of the travel, passing a point up and back at each speed [m/s]: a hump."""
    points, t = [], 0.0
    for v in speeds:
        t += 0.01
        points += [P(t, (28.8e-6,), (v,)), P(t + 1e-3, (28.8e-6,), (-v,))]
    return JointTrajectoryGoal(J, (*points, P(t + 0.02, (5e-6,), (0.0,))))


def _goals() -> list[tuple[str, JointTrajectoryGoal, dict[str, Any]]]:
    scan = JointTrajectoryGoal(J, scan_lines(3), path_tolerance=(JointTolerance(J[0], 1e-8),))
    return [
        ('move', move(5e-6), {}),
        ('scan', scan, {}),
        ('scan from another state', scan,
         {'start_state': (np.array([4e-6]), np.array([1e-4]), np.array([0.3]))}),
        # a steeper excursion after a first one: the refusal names the largest, which a
        # piece-wise check finds in a later piece than the first excursion
        ('two excursions', _humps(0.004, 0.006), {}),
        ('one excursion', _humps(0.006), {}),
        ('beyond the travel', move(1.0), {}),
        ('a NaN', JointTrajectoryGoal(J, (P(0.01, (5e-6,)), P(0.02, (float('nan'),)))), {}),
        ('time going back', JointTrajectoryGoal(J, (P(0.02, (5e-6,)), P(0.01, (6e-6,)))), {}),
        ('no points', JointTrajectoryGoal(J, ()), {}),
        ('unknown joint', JointTrajectoryGoal(('elbow',), (P(0.02, (5e-6,)),)), {}),
        ('due before now', move(5e-6), {'origin_s': -1.0}),
        ('a point due now away from the reference',
         JointTrajectoryGoal(J, (P(0.0, (9e-6,)), P(0.02, (5e-6,)))), {}),
    ]


def _run(steps: Any) -> tuple[Any, int]:
    count = 0
    while True:
        try:
            next(steps)
        except StopIteration as stop:
            return stop.value, count
        count += 1


@pytest.mark.parametrize('points, samples', SLICES)
def test_a_goal_prepared_in_slices_is_the_goal_prepared_at_once(points: int, samples: int
                                                                ) -> None:
    refused = 0
    for name, goal, options in _goals():
        f = follower()
        verdict, prepared = f.prepare(goal, 0.004, **options)
        (sliced, prepared_sliced), count = _run(f.preparing(
            goal, 0.004, points_per_step=points, samples_per_step=samples, **options))
        assert sliced == verdict, name
        assert f.version == 0, name  # preparing changes nothing
        if prepared is None:
            refused += 1
            assert prepared_sliced is None, name
            continue
        assert isinstance(prepared_sliced, PreparedGoal), name
        checked = int(round((prepared.spline.end_s - 0.004) / T)) + 1
        grid = 0.004 + np.arange(checked + 5) * T
        for a, b in zip(prepared.spline.sample(grid), prepared_sliced.spline.sample(grid)):
            assert np.array_equal(a, b), name
        assert dataclasses.replace(prepared_sliced, spline=prepared.spline) == prepared, name
        if samples == 1:
            # a slice a sample at least: the work was cut into pieces
            assert count >= checked, name
    assert refused == 9


def test_the_largest_excursion_is_named_whichever_piece_it_falls_in() -> None:
    _, goal, _ = _goals()[3]
    state = (np.array([5e-6]), np.zeros(1), np.zeros(1))
    whole = validate_goal(goal, J, [LIMITS], start_s=0.0, start_state=state, sample_time_s=T)
    # the second hump, the higher: beyond the amplifier's reach, as the first alone is
    assert not whole.accepted and 'V at 0.0203 s' in whole.reason, whole.reason
    first = validate_goal(_humps(0.004), J, [LIMITS], start_s=0.0, start_state=state,
                          sample_time_s=T)
    assert not first.accepted and 'V at 0.0103 s' in first.reason, first.reason
    for samples in (1, 50, 333):
        verdict, spline = finish(validation_steps(
            goal, J, [LIMITS], start_s=0.0, start_state=state, sample_time_s=T,
            samples_per_step=samples))
        assert verdict == whole and spline is not None


def _servo_goals(clock: FakeClock, in_slices: bool) -> tuple[np.ndarray, list[Any], set[int]]:
    """Hold, a move, then scan lines on the servo of the process; goals at given samples."""
    loop = load_loop_config(['config/default.yaml', 'config/hold.yaml'])
    loop = dataclasses.replace(loop, controller=dataclasses.replace(
        loop.controller, feedforward=dataclasses.replace(loop.controller.feedforward,
                                                         mode='inverse')))
    servo = servo_module.servo_from_config(loop, 0.3, capacity=0)
    servo.pacer = Pacer(100_000, clock=clock, sleep=clock.sleep, spin_ns=0)
    logic = servo.trajectory
    assert logic is not None
    logic.check_in_slices = in_slices
    rows: list[tuple[float, ...]] = []
    servo.on_sample = lambda s: rows.append((s.k, s.position_m, s.reference_m, s.command_v))
    events: list[Any] = []
    plan = {100: (1, move(5e-6)), 600: (2, JointTrajectoryGoal(J, scan_lines(3)))}
    worked: set[int] = set()
    slices = logic.work

    def counted() -> bool:
        if logic.checking:
            worked.add(servo.index)
        return slices()
    logic.work = counted  # type: ignore[method-assign]

    def boundary() -> bool:
        while logic.events:
            events.append(logic.events.popleft()[:3])
        if servo.index in plan:
            token, goal = plan[servo.index]
            if in_slices:
                servo_module.apply_change(servo, 'goal', (token, goal, True, None))
            else:
                logic.goal(token, goal)  # checked here, at once
        return True

    servo.boundary = boundary
    servo.run()
    assert servo.error is None
    return np.array(rows), events, worked


def test_the_servo_checks_a_goal_between_samples_and_starts_it_where_a_thread_would() -> None:
    # a clock that moves with every read: the loop has the time of a few slices a sample, so
    # a check spreads over many samples; it still ends within the lead, and the samples are
    # those of the goals checked at once (a check in another thread that ends in time) and
    # of the reference computed in the sample that reads it (here computed ahead, in pieces)
    sliced, events, worked = _servo_goals(FakeClock(per_read=30_000), True)
    whole, events_whole, none = _servo_goals(FakeClock(), False)
    # the checks ran between many samples each, within the lead (200 samples)
    assert not none and len([k for k in worked if k >= 600]) > 20
    assert max(worked) < 600 + 200
    assert np.array_equal(sliced, whole)
    assert events == events_whole
    verdicts = [e for e in events if e[0] == 'verdict']
    assert [e[2].accepted for e in verdicts] == [True, True]
    assert sliced.shape[0] == 3000 and np.isfinite(sliced).all()


def test_a_goal_cancelled_while_it_is_checked_never_starts() -> None:
    loop = load_loop_config(['config/default.yaml', 'config/hold.yaml'])
    servo = servo_module.servo_from_config(loop, 0.05, capacity=0)
    clock = FakeClock()
    servo.pacer = Pacer(100_000, clock=clock, sleep=clock.sleep, spin_ns=0)
    logic = servo.trajectory
    assert logic is not None and logic.follower is not None
    events: list[Any] = []

    def boundary() -> bool:
        while logic.events:
            events.append(logic.events.popleft()[:2])
        if servo.index == 10:
            servo_module.apply_change(servo, 'goal', (7, JointTrajectoryGoal(
                J, scan_lines(1)), True, None))
            logic.work()  # its first slice: under way
            assert logic.checking
            servo_module.apply_change(servo, 'cancel', 7)
        return True

    servo.boundary = boundary
    servo.run()
    assert servo.error is None and not logic.checking
    assert events == [('cancelled', 7)] and logic.follower.version == 0
