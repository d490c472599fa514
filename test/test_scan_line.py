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

"""The raster scan line: linear part, smooth turnarounds, validation, the command line."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.interfaces import Trajectory
from piezo_stage_ros.core.loop.trajectories import (
    make_trajectory,
    ScanLineParams,
    TrajectoryBase,
    TrajectoryParams,
)
from piezo_stage_ros.core.signals.shapes import smoothstep
from piezo_stage_ros.simulate import main as simulate_main
import pytest

REPO = Path(__file__).resolve().parents[1]


def line(**kw: object) -> tuple[TrajectoryBase, ScanLineParams]:
    flat = {'kind': 'scan_line', **{f'scan_line.{k}': v for k, v in kw.items()}}
    params = TrajectoryParams.from_flat(flat)
    return make_trajectory(params, sample_rate_hz=1e4), params.scan_line


def junctions(p: ScanLineParams, lines: int = 2) -> list[tuple[float, int]]:
    """Return (time, +1 linear part starts / -1 it ends) of every junction of a few lines."""
    period = 1.0 / p.frequency_hz
    linear = p.linear_fraction * period / 2
    start = -linear / 2  # a trace's linear part starts here (t = 0 is its middle)
    out = []
    for j in range(lines):
        for half in (0.0, 0.5):
            t0 = start + (j + half) * period
            out += [(t0 + period, 1), (t0 + period + linear, -1)]
    return out


@pytest.mark.parametrize('fraction', [0.5, 0.8, 0.95])
@pytest.mark.parametrize('order', [1, 2, 3, 4])
def test_linear_part_has_the_set_speed_range_and_fraction(fraction: float, order: int) -> None:
    traj, p = line(linear_fraction=fraction, continuity_order=order, frequency_hz=125.0)
    assert isinstance(traj, Trajectory)
    n = 100_000
    t = (np.arange(n) + 0.5) / n / p.frequency_hz  # one line, cell centres
    x, v = traj.evaluate(t)
    speed = 4 * p.amplitude_m * p.frequency_hz / fraction
    # inside the linear part |v| is the speed exactly; a turnaround leaves it as v (1 - 2 S(s)),
    # which rounds to the speed while 2 S(s) < 1e-9, i.e. s below s9 = (0.5e-9 / c)^(1/order)
    q, _, _ = smoothstep(order - 1)
    s9 = (0.5e-9 / q.coef[order]) ** (1.0 / order)
    at_speed = np.abs(v) >= speed * (1 - 1e-9)
    assert np.all(np.abs(v) <= speed * (1 + 1e-12))  # 1 - 2 S(s) rounds past -1 near s = 1
    turn_cells = (1 - fraction) / 2 * n
    assert fraction - 4.0 / n <= at_speed.mean() <= fraction + (4 * s9 * turn_cells + 4) / n
    exact = np.abs(v) == speed
    assert exact.mean() >= fraction - 4.0 / n
    lo, hi = p.offset_m - p.amplitude_m, p.offset_m + p.amplitude_m
    # within the range on the linear part: one grid cell of travel, or the rounded-off start
    # of a turnaround (its excursion v T_turn s9^(order+1) at most)
    slack = speed / p.frequency_hz / n + speed * p.turn_s * s9
    assert x[exact].min() >= lo - slack and x[exact].max() <= hi + slack
    assert x[exact].min() <= lo + slack and x[exact].max() >= hi - slack
    # outside the linear range during the turnarounds
    assert np.all((x[~at_speed] > hi - slack) | (x[~at_speed] < lo + slack))
    # trace up, retrace down: half the linear time each
    assert abs(np.mean(v[exact] > 0) - 0.5) <= 4.0 / exact.sum()
    # the reach beyond the range is the stated overshoot
    assert x.max() == pytest.approx(hi + p.overshoot_m, rel=1e-9)
    assert x.min() == pytest.approx(lo - p.overshoot_m, rel=1e-9)
    # rising through the offset at t = 0, like the triangle
    x0, v0 = traj.evaluate(np.zeros(1))
    assert x0[0] == pytest.approx(p.offset_m, abs=1e-18) and v0[0] == speed


@pytest.mark.parametrize('order', [1, 2, 3, 4, 5])
def test_turnarounds_are_continuous_to_the_stated_order_and_no_further(order: int) -> None:
    # On each side of a junction x_d is a polynomial (degree 1, or 2N + 2 in the turnaround):
    # a one-sided least-squares fit of v on 2N + 4 points recovers it up to rounding, and its
    # derivatives at the junction are compared left against right. The tolerance is the fit's
    # own amplification of the rounding of v: the j-th derivative at 0 is j! times row j of
    # the pseudo-inverse applied to v, so it moves by at most j! sum|row j| times the rounding
    # of v: a few eps |v|, plus the rounding of the time t (eps t) seen through dv/dt, at most
    # 2 v max S' / T_turn.
    traj, p = line(continuity_order=order, linear_fraction=0.8, frequency_hz=100.0)
    n_coef = 2 * (order - 1) + 2            # degree of v in the turnaround, plus one
    points = n_coef + 2
    turn = p.turn_s
    h = turn / points * np.arange(1, points + 1)
    eps = np.finfo(float).eps
    _, dq, _ = smoothstep(order - 1)
    scale = [p.speed_mps / turn ** j for j in range(order + 1)]
    for t_j, _ in junctions(p):
        sides = []
        tol = np.zeros(order + 1)
        for sign in (-1.0, 1.0):
            _, v = traj.evaluate(t_j + sign * h)
            u = sign * h / turn
            pinv = np.linalg.pinv(u[:, None] ** np.arange(n_coef))
            coef = pinv @ v
            fact = np.array([math.factorial(j) for j in range(order + 1)])
            sides.append(fact * coef[:order + 1] / turn ** np.arange(order + 1))
            noise = 4 * eps * p.speed_mps * (1 + 2 * dq(0.5) * (t_j + turn) / turn)
            tol += (fact * np.abs(pinv[:order + 1]).sum(axis=1) * noise
                    / turn ** np.arange(order + 1))
        left, right = sides
        for j in range(order):               # x', ..., x^(order) continuous
            assert abs(left[j] - right[j]) <= tol[j], (t_j, j)
            assert tol[j] < 1e-3 * scale[j]  # far below a jump (>= 0.1 scale, below)
        # x^(order + 1) jumps: the stated order is the exact one
        assert abs(left[order] - right[order]) >= 0.1 * scale[order], (t_j, order)
    # x itself: the two sides meet within the travel of a 1e-12 s step
    for t_j, _ in junctions(p):
        x, _ = traj.evaluate(np.array([t_j - 1e-12, t_j + 1e-12]))
        assert abs(x[1] - x[0]) <= 2.1e-12 * p.speed_mps + 8 * np.spacing(p.offset_m)


@pytest.mark.parametrize('order', [1, 3])
def test_velocity_is_the_exact_derivative(order: int) -> None:
    traj, p = line(continuity_order=order)
    t = np.linspace(0.00013, 0.03, 2997)
    h = 1e-8
    xp, _ = traj.evaluate(t + h)
    xm, _ = traj.evaluate(t - h)
    _, v = traj.evaluate(t)
    # central differences: truncation (h^2/6) |x'''| and rounding eps |x| / h; x''' is largest
    # (order 1: an acceleration step, not differentiable) within h of a junction, skipped
    near = np.zeros(t.shape, dtype=bool)
    for t_j, _ in junctions(p, lines=4):
        near |= np.abs(t - t_j) < 2 * h
    fd = (xp - xm) / (2 * h)
    tol = 1e-16 * p.offset_m * 4 / h + (h ** 2) * p.speed_mps * 40 / p.turn_s ** 2
    np.testing.assert_allclose(v[~near], fd[~near], rtol=0, atol=tol)


def test_smoothstep_has_its_order() -> None:
    for order in range(6):
        q, dq, integral = smoothstep(order)
        assert q(0.0) == 0.0 and q(1.0) == pytest.approx(1.0, abs=1e-12)
        assert integral(1.0) == pytest.approx(0.5, abs=1e-12)
        for j in range(1, order + 1):
            assert q.deriv(j)(0.0) == pytest.approx(0.0, abs=1e-9)
            assert q.deriv(j)(1.0) == pytest.approx(0.0, abs=1e-9)
        assert abs(q.deriv(order + 1)(0.0)) > 0.5
        s = np.linspace(0, 1, 101)
        np.testing.assert_allclose(q(s) + q(1 - s), 1.0, atol=1e-12)
    np.testing.assert_allclose(smoothstep(2)[0].coef, [0, 0, 0, 10, -15, 6])


@pytest.mark.parametrize('flat, name, allowed', [
    ({'scan_line.linear_fraction': 1.0}, 'scan_line.linear_fraction', r'\(0, 1\)'),
    ({'scan_line.linear_fraction': 0.0}, 'scan_line.linear_fraction', r'\(0, 1\)'),
    ({'scan_line.amplitude_m': 18.5e-6}, 'scan_line.amplitude_m',
     r'stage travel \[0, 3\.8e-05\] m'),
    ({'scan_line.offset_m': 1e-6}, 'scan_line.amplitude_m', r'stage travel'),
    ({'scan_line.continuity_order': 0}, 'scan_line.continuity_order', r'\[1, 6\]'),
])
def test_bad_parameters_are_refused_naming_value_and_range(flat: dict[str, object], name: str,
                                                           allowed: str) -> None:
    with pytest.raises(ParameterError, match=rf"'{name}'.*{allowed}"):
        TrajectoryParams.from_flat({'kind': 'scan_line', **flat})


def test_a_line_rate_the_sample_rate_cannot_draw_is_refused() -> None:
    # 80 % linear at 10 kHz: a turnaround of one sample at 1 kHz, less above
    line(frequency_hz=1000.0, amplitude_m=1e-6)
    with pytest.raises(ParameterError, match=r"'scan_line.frequency_hz' = 1001.*\(0, 1000\] Hz"):
        line(frequency_hz=1001.0, amplitude_m=1e-6)
    # a short linear part binds below 50 %
    with pytest.raises(ParameterError, match=r'\(0, 1000\] Hz'):
        line(frequency_hz=1100.0, linear_fraction=0.2, amplitude_m=1e-7)


def test_simulate_refuses_a_line_rate_too_high_and_runs_the_scenario(capsys) -> None:
    assert simulate_main(['--trajectory', 'scan_line', '--frequency', '2000']) == 1
    err = capsys.readouterr().err
    assert 'scan_line.frequency_hz' in err and '(0, 1000] Hz' in err
    assert simulate_main(['--config', str(REPO / 'config' / 'scan_line.yaml'),
                          '--duration', '0.05', '--json']) == 0
    out = json.loads(capsys.readouterr().out)
    assert out['trajectory'] == 'scan_line'
    assert out['trajectory_period_s'] == pytest.approx(0.01)
    assert math.isfinite(out['line_trace_e_rms_m']) and math.isfinite(out['line_retrace_e_rms_m'])
