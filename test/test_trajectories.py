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

"""Trajectories: values, exact derivatives, periods, travel limits, CSV tables."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from piezo_stage_ros.core.contracts.errors import ConfigError, ParameterError
from piezo_stage_ros.core.contracts.interfaces import Trajectory
from piezo_stage_ros.core.loop.trajectories import (
    load_table,
    make_trajectory,
    TableTrajectory,
    TrajectoryParams,
)
from piezo_stage_ros.core.signals.shapes import s_curve
import pytest

T = 1e-4


def build(flat: dict[str, object]) -> object:
    return make_trajectory(TrajectoryParams.from_flat(flat))


@pytest.mark.parametrize('kind', ['sine', 'multisine', 'square', 'staircase', 'step',
                                  'triangle'])
def test_every_kind_is_a_trajectory_and_keeps_shape(kind: str) -> None:
    traj = build({'kind': kind})
    assert isinstance(traj, Trajectory)
    t = np.arange(12.0).reshape(3, 4) * 1e-3
    pos, vel = traj.evaluate(t)  # type: ignore[attr-defined]
    assert pos.shape == t.shape and vel.shape == t.shape
    assert pos.dtype == np.float64 and vel.dtype == np.float64


def test_sine_is_the_papers_table3_trajectory() -> None:
    traj = build({'kind': 'sine', 'sine.frequency_hz': 50.0})
    t = np.arange(0, 400) * T
    pos, vel = traj.evaluate(t)  # type: ignore[attr-defined]
    np.testing.assert_allclose(pos, 3.8e-6 + 3.8e-6 * np.sin(2 * np.pi * 50 * t), rtol=1e-14)
    np.testing.assert_allclose(vel, 3.8e-6 * 2 * np.pi * 50 * np.cos(2 * np.pi * 50 * t),
                               rtol=1e-12)
    assert traj.period_s == pytest.approx(0.02)  # type: ignore[attr-defined]


@pytest.mark.parametrize('kind', ['sine', 'multisine', 'triangle'])
def test_derivative_matches_finite_differences(kind: str) -> None:
    # central differences of a smooth (or piecewise linear) signal: error O(h^2)
    traj = build({'kind': kind})
    t = np.linspace(0.0013, 0.2, 997)
    h = 1e-7
    p_plus, _ = traj.evaluate(t + h)  # type: ignore[attr-defined]
    p_minus, _ = traj.evaluate(t - h)  # type: ignore[attr-defined]
    _, vel = traj.evaluate(t)  # type: ignore[attr-defined]
    fd = (p_plus - p_minus) / (2 * h)
    scale = np.max(np.abs(vel))
    if kind == 'triangle':
        # away from the corners the slope is exact
        u = np.mod(t * 10.0, 0.25)
        ok = (u > 1e-4) & (u < 0.25 - 1e-4)
        np.testing.assert_allclose(vel[ok], fd[ok], atol=1e-6 * scale)
    else:
        np.testing.assert_allclose(vel, fd, atol=1e-6 * scale)


def test_triangle_values_and_slope_at_corners() -> None:
    traj = build({'kind': 'triangle', 'triangle.frequency_hz': 10.0})
    t = np.array([0.0, 0.025, 0.05, 0.075, 0.1])
    pos, vel = traj.evaluate(t)  # type: ignore[attr-defined]
    np.testing.assert_allclose(pos, [3.8e-6, 7.6e-6, 3.8e-6, 0.0, 3.8e-6], atol=1e-18)
    slope = 4 * 3.8e-6 * 10.0
    # at a corner, the slope of the piece that starts there
    np.testing.assert_allclose(vel, [slope, -slope, -slope, slope, slope])


def test_multisine_fig12_period_and_start() -> None:
    traj = build({'kind': 'multisine'})
    assert traj.period_s == pytest.approx(0.1)  # type: ignore[attr-defined]
    pos, _ = traj.evaluate([0.0, 0.1])  # type: ignore[attr-defined]
    np.testing.assert_allclose(pos, 3.8e-6, rtol=1e-12)
    odd = build({'kind': 'multisine', 'multisine.frequencies_hz': [10.0, 15.0]})
    assert odd.period_s == pytest.approx(0.2)  # type: ignore[attr-defined]
    incommensurate = build({'kind': 'multisine', 'multisine.frequencies_hz': [1.0, math.pi]})
    assert incommensurate.period_s is None  # type: ignore[attr-defined]


def test_square_fig10_levels_and_exact_edges() -> None:
    traj = build({'kind': 'square'})
    k = np.arange(0, 10001)
    pos, vel = traj.evaluate(k * T)  # type: ignore[attr-defined]
    assert np.all(vel == 0.0)
    assert set(np.unique(pos).round(12)) == {3.8e-6, 11.6e-6}
    edges = np.flatnonzero(np.diff(pos)) + 1
    # edges exactly at k = 2500, 5000, 7500, 10000 samples (0.25 s half periods)
    np.testing.assert_array_equal(edges, [2500, 5000, 7500, 10000])
    assert pos[0] == 3.8e-6 and pos[2500] == pytest.approx(11.6e-6)


def test_staircase_and_step() -> None:
    stairs = build({'kind': 'staircase', 'staircase.steps': 3, 'staircase.dwell_s': 0.01})
    pos, _ = stairs.evaluate(np.array([0.0, 0.0099, 0.01, 0.025, 0.03, 1.0]))  # type: ignore
    np.testing.assert_allclose(pos - 3.8e-6, np.array([0, 0, 1, 2, 3, 3]) * 19e-9, atol=1e-18)
    step = build({'kind': 'step', 'step.time_s': 0.001})
    pos, vel = step.evaluate(np.arange(0, 20) * T)  # type: ignore[attr-defined]
    assert pos[9] == 3.8e-6 and pos[10] == 11.6e-6
    assert step.period_s is None  # type: ignore[attr-defined]


@pytest.mark.parametrize('flat, name', [
    ({'kind': 'sine', 'sine.amplitude_m': 4e-6}, 'sine.amplitude_m'),
    ({'kind': 'sine', 'sine.offset_m': 36e-6}, 'sine.offset_m'),
    ({'kind': 'multisine', 'multisine.amplitudes_m': [3e-6, 3e-6]}, 'multisine.amplitudes_m'),
    ({'kind': 'square', 'square.peak_to_peak_m': 40e-6}, 'square.peak_to_peak_m'),
    ({'kind': 'square', 'square.low_m': -1e-6}, 'square.low_m'),
    ({'kind': 'staircase', 'staircase.steps': 2000, 'staircase.step_m': 1e-7},
     'staircase.step_m'),
    ({'kind': 'step', 'step.final_m': 39e-6}, 'step.final_m'),
    ({'kind': 'triangle', 'triangle.amplitude_m': 5e-6}, 'triangle.amplitude_m'),
])
def test_outside_travel_is_refused_naming_parameter_and_range(flat: dict[str, object],
                                                               name: str) -> None:
    with pytest.raises(ParameterError, match=rf"'{name}'.*stage travel.*\[0, 3\.8e-05\] m"):
        TrajectoryParams.from_flat(flat)


def test_other_bad_parameters() -> None:
    with pytest.raises(ParameterError, match="'kind' = 'zigzag'"):
        TrajectoryParams.from_flat({'kind': 'zigzag'})
    with pytest.raises(ParameterError, match="'sine.frequency_hz'"):
        TrajectoryParams.from_flat({'sine.frequency_hz': 0.0})
    with pytest.raises(ParameterError, match='amplitudes_m.*different length'):
        TrajectoryParams.from_flat({'multisine.amplitudes_m': [1e-6]})
    with pytest.raises(ParameterError, match="'csv.path'.*empty"):
        build({'kind': 'csv'})


def test_table_piecewise_linear_and_constant_slope() -> None:
    table = TableTrajectory([0.0, 1.0, 3.0], [1e-6, 3e-6, 2e-6])
    t = np.array([-1.0, 0.0, 0.5, 1.0, 2.0, 3.0, 4.0])
    pos, vel = table.evaluate(t)
    np.testing.assert_allclose(pos, np.array([1, 1, 2, 3, 2.5, 2, 2]) * 1e-6, rtol=1e-14)
    np.testing.assert_allclose(vel, np.array([0, 2, 2, -0.5, -0.5, 0, 0]) * 1e-6, rtol=1e-14)


def test_csv_file(tmp_path: Path) -> None:
    path = tmp_path / 'path.csv'
    path.write_text('# a comment\nposition_m,time_s\n1e-6,0\n2e-6,0.5\n')
    traj = build({'kind': 'csv', 'csv.path': str(path)})
    pos, vel = traj.evaluate([0.25])  # type: ignore[attr-defined]
    assert pos[0] == pytest.approx(1.5e-6) and vel[0] == pytest.approx(2e-6)
    assert isinstance(load_table(path), TableTrajectory)


@pytest.mark.parametrize('text, match', [
    ('t,position_m\n0,1e-6\n', "no column 'time_s'"),
    ('time_s,position_m\n0,1e-6\n1,abc\n', 'line 3'),
    ('time_s,position_m\n0,1e-6\n0,2e-6\n', 'increase strictly'),
    ('time_s,position_m\n0,1e-6\n', 'at least 2 rows'),
    ('', 'empty'),
])
def test_bad_csv_tables(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / 'bad.csv'
    path.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_table(path)


def test_csv_outside_travel_and_missing_file(tmp_path: Path) -> None:
    path = tmp_path / 'far.csv'
    path.write_text('time_s,position_m\n0,1e-6\n1,40e-6\n')
    with pytest.raises(ParameterError, match='4e-05 m, outside the stage travel'):
        build({'kind': 'csv', 'csv.path': str(path)})
    with pytest.raises(ConfigError, match='cannot read'):
        load_table(tmp_path / 'missing.csv')


# --- shaped transitions (transition_s) ---------------------------------------------------

def test_s_curve_values_and_exact_derivative() -> None:
    u = np.array([-0.5, 0.0, 0.25, 0.5, 0.75, 1.0, 2.0])
    q, dq = s_curve(u)
    np.testing.assert_allclose(q, [0.0, 0.0, 0.103515625, 0.5, 0.896484375, 1.0, 1.0],
                               atol=1e-15)
    # q'(u) = 30 u^2 (1 - u)^2: peak 1.875 at the middle, 0 at both ends and outside
    np.testing.assert_allclose(dq, [0.0, 0.0, 1.0546875, 1.875, 1.0546875, 0.0, 0.0],
                               atol=1e-15)
    # q'' = 60 u (1 - u)(1 - 2u) vanishes at the ends: acceleration is continuous too
    h = 1e-6
    assert abs(s_curve(h)[1] - s_curve(0.0)[1]) / h < 1e-4
    assert abs(s_curve(1.0)[1] - s_curve(1.0 - h)[1]) / h < 1e-4


SHAPED = [
    {'kind': 'square', 'square.transition_s': 2e-3},
    {'kind': 'square', 'square.transition_s': 1e-3, 'square.duty': 0.3},
    {'kind': 'staircase', 'staircase.transition_s': 5e-3, 'staircase.steps': 4},
    {'kind': 'staircase', 'staircase.transition_s': 0.05, 'staircase.step_m': -19e-9},
    {'kind': 'step', 'step.transition_s': 1e-3},
    {'kind': 'step', 'step.transition_s': 3e-3, 'step.initial_m': 30e-6,
     'step.final_m': 4e-6},
]


@pytest.mark.parametrize('flat', SHAPED)
def test_shaped_jumps_are_continuous_with_exact_derivative(flat: dict[str, object]) -> None:
    traj = build(flat)
    t = np.arange(1e-5, 1.2, 1e-5)    # times of a run are >= 0: keep t - h inside
    pos, vel = traj.evaluate(t)  # type: ignore[attr-defined]
    kind = str(flat['kind'])
    tr = float(flat[f'{kind}.transition_s'])  # type: ignore[arg-type]
    jump = {'square': 7.8e-6, 'step': abs(float(flat.get('step.final_m', 11.6e-6))  # type: ignore
                                           - float(flat.get('step.initial_m', 3.8e-6))),  # type: ignore
            'staircase': 19e-9}[kind]
    peak = 1.875 * jump / tr
    assert np.max(np.abs(vel)) == pytest.approx(peak, rel=1e-3)
    # continuity: no sample-to-sample change larger than the peak velocity allows
    assert np.max(np.abs(np.diff(pos))) <= peak * 1e-5 * (1 + 1e-9)
    # the derivative is exact: central differences, O(h^2)
    h = 1e-8
    fd = (traj.evaluate(t + h)[0] - traj.evaluate(t - h)[0]) / (2 * h)  # type: ignore
    np.testing.assert_allclose(vel, fd, atol=1e-4 * peak)
    # the S-curve is monotone: the levels still bound x_d (the travel check stays valid)
    lo, hi = np.min(build({**flat, f'{kind}.transition_s': 0.0}).evaluate(t)[0]), \
        np.max(build({**flat, f'{kind}.transition_s': 0.0}).evaluate(t)[0])  # type: ignore
    assert lo - 1e-18 <= np.min(pos) and np.max(pos) <= hi + 1e-18


def test_shaped_square_starts_where_the_ideal_jump_is_and_reaches_the_level() -> None:
    ideal = build({'kind': 'square'})
    shaped = build({'kind': 'square', 'square.transition_s': 2e-3})
    k = np.arange(0, 10001)
    p0, _ = ideal.evaluate(k * T)  # type: ignore[attr-defined]
    p1, v1 = shaped.evaluate(k * T)  # type: ignore[attr-defined]
    # identical outside [edge, edge + 2 ms); at the edge sample the shaped one has not moved
    moving = np.zeros(k.size, dtype=bool)
    for edge in (2500, 5000, 7500, 10000):
        moving[edge:edge + 20] = True
        assert p1[edge] == pytest.approx(p0[edge - 1], abs=1e-18)
        assert abs(v1[edge]) < 1e-20
    # bit for bit: away from the edges the S-curve is exactly 0 or 1, so both compute the same
    # correctly rounded + and * on the same numbers (no transcendental function involved)
    np.testing.assert_array_equal(p1[~moving], p0[~moving])
    assert p1[2510] == pytest.approx(7.7e-6, abs=1e-15)   # half way at the middle
    assert p1[0] == 3.8e-6 and v1[0] == 0.0               # the run starts at rest, low


def test_transition_zero_is_the_ideal_jump() -> None:
    for kind in ('square', 'staircase', 'step'):
        a = build({'kind': kind})
        b = build({'kind': kind, f'{kind}.transition_s': 0.0})
        t = np.arange(0, 5000) * T
        # bit for bit: transition 0 is the same code path as no transition
        np.testing.assert_array_equal(a.evaluate(t)[0], b.evaluate(t)[0])  # type: ignore
        assert np.all(b.evaluate(t)[1] == 0.0)  # type: ignore[attr-defined]


def test_bad_transitions_are_refused() -> None:
    with pytest.raises(ParameterError, match=r"'square.transition_s' = 0.3 is longer than the "
                                             r'shortest level.*\[0, 0.25\] s'):
        TrajectoryParams.from_flat({'kind': 'square', 'square.transition_s': 0.3})
    with pytest.raises(ParameterError, match=r"'staircase.transition_s' = 0.06 is longer"):
        TrajectoryParams.from_flat({'kind': 'staircase', 'staircase.transition_s': 0.06})
    with pytest.raises(ParameterError, match=r"'step.transition_s' = -0.001"):
        TrajectoryParams.from_flat({'kind': 'step', 'step.transition_s': -1e-3})
    # the travel check applies with a transition as without
    with pytest.raises(ParameterError, match=r"'square.peak_to_peak_m'.*stage travel"):
        TrajectoryParams.from_flat({'kind': 'square', 'square.transition_s': 1e-3,
                                    'square.peak_to_peak_m': 40e-6})
