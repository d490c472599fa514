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

"""Joint-trajectory goals: interpolation, validation, limits from the stage model."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
import re

import numpy as np
from piezo_stage_ros.core.config.loader import load_config, LoopConfig
from piezo_stage_ros.core.contracts.wire import JOINT_NAME
from piezo_stage_ros.core.loop.goals import (
    AxisLimits,
    build_spline,
    JointTolerance,
    JointTrajectoryGoal,
    ResultCode,
    TrajectoryPoint,
    validate_goal,
)
from piezo_stage_ros.core.loop.splines import segment_coefficients, Spline
from piezo_stage_ros.core.loop.trajectories import make_trajectory
from piezo_stage_ros.core.model.stage import PlantParams, Stage, StageParams
from piezo_stage_ros.core.signals.shapes import s_curve
import pytest
from tolerances import EPS

T = 1e-4
CONFIG_DIR = Path(__file__).resolve().parents[1] / 'config'
J = (JOINT_NAME,)
LIMITS = AxisLimits.from_stage(StageParams())


def _poly(c: np.ndarray, tau: float, order: int) -> np.ndarray:
    """Evaluate derivative ``order`` of sum c_j tau^j directly (the reference, not Horner)."""
    out = np.zeros(c.shape[1:])
    for j in range(order, 6):
        out = out + math.factorial(j) / math.factorial(j - order) * c[j] * tau ** (j - order)
    return out


def test_result_codes_are_control_msgs_values() -> None:
    # control_msgs/action/FollowJointTrajectory.action, Result
    assert {c.name: int(c) for c in ResultCode} == {
        'SUCCESSFUL': 0, 'INVALID_GOAL': -1, 'INVALID_JOINTS': -2, 'OLD_HEADER_TIMESTAMP': -3,
        'PATH_TOLERANCE_VIOLATED': -4, 'GOAL_TOLERANCE_VIOLATED': -5}


@pytest.mark.parametrize('order', [0, 1, 2])
@pytest.mark.parametrize('seed', range(5))
def test_segment_meets_its_boundary_conditions(order: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    duration = float(rng.uniform(1e-3, 0.1))
    start = [rng.uniform(0, 30e-6, 3), rng.uniform(-1e-3, 1e-3, 3),
             rng.uniform(-1.0, 1.0, 3)][:order + 1]
    end = [rng.uniform(0, 30e-6, 3), rng.uniform(-1e-3, 1e-3, 3),
           rng.uniform(-1.0, 1.0, 3)][:order + 1]
    c = segment_coefficients(duration, start, end)
    # each coefficient is a sum of at most six terms, each at most 30 S / T^j (the largest
    # factor of the formulas), S the boundary values scaled to metres; the evaluation adds
    # six roundings of terms of the same size
    scale = sum(np.abs(s) * duration ** j for j, s in enumerate(start)) + \
        sum(np.abs(e) * duration ** j for j, e in enumerate(end))
    for d in range(order + 1):
        bound = 400 * EPS * scale / duration ** d
        assert np.all(np.abs(_poly(c, 0.0, d) - start[d]) <= bound)
        assert np.all(np.abs(_poly(c, duration, d) - end[d]) <= bound)


@pytest.mark.parametrize('seed', range(5))
def test_linear_interpolation_is_exact(seed: int) -> None:
    rng = np.random.default_rng(seed)
    duration = float(rng.uniform(1e-3, 0.1))
    x0, x1 = rng.uniform(0, 30e-6, 3), rng.uniform(0, 30e-6, 3)
    spline = Spline(0.0, (x0, np.zeros(3), np.zeros(3)), [duration], x1[None, :])
    u = rng.uniform(0.0, 1.0, 50)
    x, v, a = spline.sample(u * duration)
    # x0 + (x1 - x0) tau / T: a few roundings of terms no larger than |x0| + |x1|
    expect = x0 + np.multiply.outer(u, x1 - x0)
    assert np.all(np.abs(x - expect) <= 8 * EPS * (np.abs(x0) + np.abs(x1)))
    slope = (x1 - x0) / duration
    assert np.all(np.abs(v - slope) <= 4 * EPS * np.abs(slope))
    assert np.all(a == 0.0)


def test_quintic_from_rest_to_rest_is_the_minimum_jerk_s_curve() -> None:
    x0, x1, duration = 3.8e-6, 21.0e-6, 0.02
    spline = Spline(0.0, (np.array([x0]), np.zeros(1), np.zeros(1)), [duration], [[x1]],
                    [[0.0]], [[0.0]])
    t = np.linspace(0.0, duration, 201)
    x, v, _ = spline.sample(t)
    q, dq = s_curve(t / duration)
    d = x1 - x0
    assert np.max(np.abs(x[:, 0] - (x0 + d * q))) <= 200 * EPS * x1
    assert np.max(np.abs(v[:, 0] - d * dq / duration)) <= 200 * EPS * x1 / duration


def test_spline_holds_before_the_start_and_after_the_end() -> None:
    start = (np.array([5e-6]), np.array([1e-4]), np.array([2.0]))
    spline = Spline(1.0, start, [1.01, 1.02], [[6e-6], [7e-6]], [[1e-4], [0.0]])
    x, v, a = spline.sample(np.array([0.5, 1.0, 1.02, 3.0]))
    assert x[0, 0] == 5e-6 and v[0, 0] == 1e-4 and a[0, 0] == 2.0
    assert x[1, 0] == 5e-6 and v[1, 0] == 1e-4
    assert x[2, 0] == 7e-6 and v[2, 0] == 0.0 and a[2, 0] == 0.0
    assert x[3, 0] == 7e-6 and v[3, 0] == 0.0


def test_spline_block_evaluation_equals_sample_by_sample() -> None:
    rng = np.random.default_rng(3)
    times = np.cumsum(rng.uniform(1e-3, 5e-3, 40))
    pos = rng.uniform(5e-6, 25e-6, (40, 2))
    vel = rng.uniform(-1e-3, 1e-3, (40, 2))
    vel[-1] = 0.0
    spline = Spline(0.0, (pos[0] * 0 + 5e-6, np.zeros(2), np.zeros(2)), times, pos, vel,
                    np.zeros((40, 2)))
    grid = np.arange(int(times[-1] / T) + 20) * T
    block = spline.sample(grid)
    for k in range(0, grid.size, 37):
        one = spline.sample(grid[k:k + 1])
        for b, o in zip(block, one):
            assert np.array_equal(b[k], o[0])


def _goal(*points: TrajectoryPoint, names: tuple[str, ...] = J, **kw: object
          ) -> JointTrajectoryGoal:
    return JointTrajectoryGoal(names, tuple(points), **kw)  # type: ignore[arg-type]


def _check(goal: JointTrajectoryGoal, at_m: float = 3.8e-6) -> tuple[ResultCode, str]:
    verdict = validate_goal(goal, J, [LIMITS], start_s=0.0,
                            start_state=(np.array([at_m]), np.zeros(1), np.zeros(1)),
                            sample_time_s=T)
    return verdict.code, verdict.reason


P = TrajectoryPoint


@pytest.mark.parametrize('goal, code, match', [
    (_goal(P(0.02, (10e-6,)), names=('x',)), ResultCode.INVALID_JOINTS,
     r"joint 'x' is not a joint of this stage; allowed: the stage's joints \['stage'\]"),
    (_goal(P(0.02, (10e-6, 10e-6)), names=J + J), ResultCode.INVALID_JOINTS,
     "joint 'stage' is named twice"),
    (_goal(P(0.02, ()), names=()), ResultCode.INVALID_JOINTS, r"joints \['stage'\] are missing"),
    (_goal(), ResultCode.INVALID_GOAL, 'the trajectory has no points'),
    (_goal(P(0.02, (10e-6,)), P(0.02, (11e-6,))), ResultCode.INVALID_GOAL,
     r'point 1: time_from_start = 0.02 s after 0.02 s; allowed: strictly increasing'),
    (_goal(P(-0.01, (10e-6,))), ResultCode.INVALID_GOAL,
     r'point 0: time_from_start = -0.01 s; allowed: a finite time >= 0'),
    (_goal(P(0.02, (math.nan,))), ResultCode.INVALID_GOAL,
     r'point 0: positions holds nan; allowed: finite numbers'),
    (_goal(P(0.02, (10e-6,), (math.inf,))), ResultCode.INVALID_GOAL,
     r'point 0: velocities holds inf'),
    (_goal(P(0.02, (10e-6, 11e-6))), ResultCode.INVALID_GOAL,
     r'point 0: 2 positions; allowed: 1 values, one per joint'),
    (_goal(P(0.01, (10e-6,), (1e-4,)), P(0.02, (11e-6,))), ResultCode.INVALID_GOAL,
     r'point 1: 0 velocities; allowed: 1 values'),
    (_goal(P(0.02, (10e-6,), (1e-4,))), ResultCode.INVALID_GOAL,
     r'the last point has velocities \[0.0001\] m/s; allowed: 0'),
    (_goal(P(0.02, (39e-6,))), ResultCode.INVALID_GOAL,
     r"point 0: position of 'stage' = 3.9e-05 m; allowed: \[0, 2.88\d*e-05\] m"),
    (_goal(P(0.02, (-1e-6,))), ResultCode.INVALID_GOAL,
     r"point 0: position of 'stage' = -1e-06 m; allowed: \[0, "),
    (_goal(P(0.0, (10e-6,))), ResultCode.INVALID_GOAL,
     r'point 0 due now puts .* 6.2e-06 m from the present reference'),
    # 20 um in 0.1 ms: the velocity term alone asks more than the amplifier span
    (_goal(P(1e-4, (23.8e-6,))), ResultCode.INVALID_GOAL,
     r"'stage' reaches velocity 0.2 m/s at 0 s; allowed: \|velocity\| <= 0.144"),
    # a quintic of 10 um in 0.4 ms: within the velocity, beyond the command at the top
    (_goal(P(4e-4, (27e-6,), (0.0,), (0.0,))), ResultCode.INVALID_GOAL,
     r"'stage' would need 1\d.\d+ V at .* allowed: the amplifier input \[-2, 10\] V"),
    (_goal(P(0.02, (10e-6,)), goal_tolerance=(JointTolerance('y', 1e-9),)),
     ResultCode.INVALID_JOINTS, "goal_tolerance names joint 'y'"),
    (_goal(P(0.02, (10e-6,)), goal_time_tolerance_s=-1.0), ResultCode.INVALID_GOAL,
     'goal_time_tolerance = -1.0 s; allowed: a finite time >= 0'),
])
def test_bad_goals_are_refused_naming_the_value(goal: JointTrajectoryGoal, code: ResultCode,
                                                match: str) -> None:
    got, reason = _check(goal)
    assert got == code
    assert reason and re.search(match, reason), reason


@pytest.mark.parametrize('goal', [
    _goal(P(0.02, (10e-6,))),
    _goal(P(0.02, (10e-6,), (0.0,))),
    _goal(P(0.01, (8e-6,), (1e-4,), (0.0,)), P(0.02, (10e-6,), (0.0,), (0.0,))),
    _goal(P(0.0, (3.8e-6,)), P(0.02, (28e-6,))),
    _goal(P(0.0, (3.8e-6 + 1e-9,))),       # within the sensor's 1.16 nm
])
def test_good_goals_are_accepted(goal: JointTrajectoryGoal) -> None:
    assert _check(goal) == (ResultCode.SUCCESSFUL, '')


def test_a_stamp_in_the_past_drops_the_points_due_and_refuses_a_trajectory_over() -> None:
    goal = _goal(P(0.01, (5e-6,)), P(0.02, (6e-6,)), P(0.03, (7e-6,)))
    state = (np.array([3.8e-6]), np.zeros(1), np.zeros(1))
    common = dict(start_s=1.0, start_state=state, sample_time_s=T)
    old = validate_goal(goal, J, [LIMITS], origin_s=0.96, **common)  # type: ignore[arg-type]
    assert old.code == ResultCode.OLD_HEADER_TIMESTAMP
    assert 'the last point is due at 0.99 s; allowed: not before now (1 s)' in old.reason
    late = validate_goal(goal, J, [LIMITS], origin_s=0.985, **common)  # type: ignore[arg-type]
    assert late.accepted
    spline = build_spline(goal, J, 1.0, state, T, origin_s=0.985)
    # the points due at 0.995 s and before are gone; the next one is reached from the state
    assert np.allclose(spline.knots_s, [1.0, 1.005, 1.015], rtol=0, atol=1e-12)
    assert spline.sample(np.array([1.0]))[0][0, 0] == 3.8e-6
    # a stamp in the future: the reference moves to the first point due then
    ahead = build_spline(goal, J, 1.0, state, T, origin_s=1.5)
    assert ahead.knots_s[1] == pytest.approx(1.51, abs=1e-12)


def test_limits_of_a_first_order_stage_are_its_time_constant() -> None:
    # 1/G = (1 + tau s)/g exactly: the velocity term is tau, no acceleration term
    params = StageParams(plant=PlantParams(model='reduced'))
    lim = AxisLimits.from_stage(params)
    tau = params.plant.reduced.tau_s
    assert abs(lim.tau1_s - tau) <= 64 * EPS * tau
    assert abs(lim.tau2_s2) <= 64 * EPS * tau * tau
    # so the acceleration limit, the span over that term, is beyond any goal's
    span = params.chain.amplifier_max_v - params.chain.amplifier_min_v
    assert lim.acceleration_max_mps2 >= lim.gain_m_per_v * span / (64 * EPS * tau * tau)


def test_the_static_reach_is_reached_at_the_amplifier_limit() -> None:
    # the stage held at the highest input settles at or above the highest position a goal may
    # ask for (the reach takes the hysteresis bound off), and the lowest input below the lowest
    params = dataclasses.replace(StageParams(),
                                 chain=dataclasses.replace(StageParams().chain, quantize=False))
    lim = AxisLimits.from_stage(params, travel_min_m=-1.0, travel_max_m=1.0)
    for volts, check in ((params.chain.amplifier_max_v, lambda x: x >= lim.position_max_m),
                         (params.chain.amplifier_min_v, lambda x: x <= lim.position_min_m)):
        stage = Stage(params)
        stage.reset(3.8e-6)
        for _ in range(3000):       # 0.3 s, many times the slowest time constant
            stage.step(volts)
        assert check(stage.position_m), (volts, stage.position_m, lim)


def test_the_hold_scenario_holds_the_start_position() -> None:
    files = [CONFIG_DIR / 'default.yaml', CONFIG_DIR / 'hold.yaml']
    config = LoopConfig.from_config(load_config(files))
    trajectory = make_trajectory(config.trajectory)
    x, v = trajectory.evaluate(np.arange(5) * T)
    assert trajectory.kind == 'hold' and trajectory.period_s is None
    assert np.all(x == config.stage.initial_position_m) and np.all(v == 0.0)


def test_a_long_goal_is_checked_to_its_end() -> None:
    # the limits are checked in blocks of samples: a violation 9 s in is found
    code, reason = _check(_goal(P(5.0, (10e-6,)), P(9.0, (10e-6,)), P(9.0001, (28e-6,)),
                                P(10.0, (28e-6,))))
    assert code == ResultCode.INVALID_GOAL
    assert re.search(r"'stage' reaches velocity 0.18 m/s at 9 s", reason), reason
