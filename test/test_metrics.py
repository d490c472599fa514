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

"""Metrics against analytic answers: ellipses, first- and second-order step responses."""

from __future__ import annotations

import math

import numpy as np
from piezo_stage_ros.core.contracts.errors import PiezoStageError
from piezo_stage_ros.core.loop import metrics
from piezo_stage_ros.core.loop.record import RunRecord
import pytest


def _record(t: np.ndarray, x: np.ndarray, xd: np.ndarray, period: float | None = None,
            cmd: np.ndarray | None = None) -> RunRecord:
    meta = {} if period is None else {'trajectory_period_s': period}
    return RunRecord(t, x, xd, np.zeros_like(t), np.zeros_like(t) if cmd is None else cmd,
                     meta=meta)


def test_error_metrics_d1_d2() -> None:
    e_max, e_rms = metrics.error_metrics([3.0, -4.0, 0.0, 0.0])
    assert e_max == 4.0
    assert e_rms == pytest.approx(math.sqrt(25.0 / 4.0), rel=1e-15)
    assert all(math.isnan(v) for v in metrics.error_metrics([]))


@pytest.mark.parametrize('phi_deg', [1.0, 5.0, 10.0, 30.0, 60.0])
def test_loop_width_of_an_ellipse(phi_deg: float) -> None:
    # x = sin t, y = sin(t - phi): vertical width 2 sin(phi) over a range of 2
    phi = math.radians(phi_deg)
    t = np.linspace(0.0, 6 * math.pi, 30001)
    width = metrics.loop_width(np.sin(t), np.sin(t - phi))
    # the grid of 201 levels misses x = 0 by at most 1/100: width error < 1e-4 relative
    assert width == pytest.approx(100.0 * math.sin(phi), rel=2e-3)


def test_loop_width_of_a_line_is_zero_and_sign_free() -> None:
    t = np.linspace(0.0, 4 * math.pi, 4001)
    assert metrics.loop_width(np.sin(t), 2 * np.sin(t) + 1) == pytest.approx(0.0, abs=1e-9)
    # a loop run the other way round (y leads x) has the same width
    w_lead = metrics.loop_width(np.sin(t), np.sin(t + 0.2))
    assert w_lead == pytest.approx(100 * math.sin(0.2), rel=2e-3)


def test_loop_width_rejects_mismatched_lengths() -> None:
    with pytest.raises(PiezoStageError, match='x has 3 samples, y has 2'):
        metrics.loop_width([0.0, 1.0, 2.0], [0.0, 1.0])


@pytest.mark.parametrize('tau', [1e-3, 2.445e-4])
def test_first_order_step(tau: float) -> None:
    # y = 1 - exp(-t/tau): rise 10-90 % = tau ln 9, no overshoot, 2 % settling = tau ln 50
    t = np.arange(0.0, 20 * tau, tau / 2000)
    y = 1.0 - np.exp(-t / tau)
    m = metrics.step_response(t, y, step_time_s=0.0, initial_m=0.0, final_m=1.0)
    assert m.rise_time_s == pytest.approx(tau * math.log(9.0), rel=1e-3)
    assert m.overshoot_pct == 0.0
    assert m.settling_time_s == pytest.approx(tau * math.log(50.0), rel=1e-3)
    assert m.ss_e_max_m <= math.exp(-10.0) * 1.001


def test_second_order_step_overshoot_and_settling() -> None:
    # underdamped: overshoot = exp(-zeta pi / sqrt(1 - zeta^2)); a step down of 2 m from 3 m
    zeta, wn = 0.3, 2 * math.pi * 50.0
    wd = wn * math.sqrt(1 - zeta ** 2)
    t = np.arange(0.0, 0.5, 1e-6)
    unit = 1 - np.exp(-zeta * wn * t) * (np.cos(wd * t)
                                         + zeta / math.sqrt(1 - zeta ** 2) * np.sin(wd * t))
    y = 3.0 - 2.0 * unit
    m = metrics.step_response(t + 0.1, y, step_time_s=0.1, initial_m=3.0, final_m=1.0)
    expected = 100 * math.exp(-zeta * math.pi / math.sqrt(1 - zeta ** 2))
    assert m.overshoot_pct == pytest.approx(expected, rel=1e-4)
    # settling: the last time the envelope-bounded response is outside 2 %; the envelope
    # bound exp(-zeta wn t)/sqrt(1-zeta^2) = 0.02 is an upper limit, one half period below it
    bound = -math.log(0.02 * math.sqrt(1 - zeta ** 2)) / (zeta * wn)
    assert bound - math.pi / wd < m.settling_time_s <= bound
    # 10-90 % rise time of this system (numerically, fine grid): 1.25/wn within 10 %
    assert m.rise_time_s == pytest.approx(1.25 / wn * (1 + 0.0), rel=0.1)


def test_settle_band_in_metres_and_never_settling() -> None:
    t = np.arange(0.0, 1.0, 1e-3)
    y = np.where(t > 0.5, 1.0 + 0.05, 1.0)  # stays 5 % off after 0.5 s
    m = metrics.step_response(t, y, step_time_s=0.0, initial_m=0.0, final_m=1.0)
    assert math.isnan(m.settling_time_s)
    m = metrics.step_response(t, y, step_time_s=0.0, initial_m=0.0, final_m=1.0,
                              settle_band_m=0.06)
    assert m.settle_band_m == 0.06
    assert m.settling_time_s == 0.0
    with pytest.raises(PiezoStageError, match='no step'):
        metrics.step_response(t, y, step_time_s=0.0, initial_m=1.0, final_m=1.0)


def test_square_wave_metrics_of_first_order_edges() -> None:
    tau, period, dt = 1e-3, 0.1, 1e-5
    t = np.arange(0.0, 0.5, dt)
    ref = np.where((t % period) < period / 2, 2.0, 1.0)
    y = np.empty_like(t)
    y[0] = ref[0]
    a = math.exp(-dt / tau)
    for k in range(1, t.size):  # exact ZOH first order following the reference
        y[k] = a * y[k - 1] + (1 - a) * ref[k - 1]
    m = metrics.square_wave_metrics(t, y, ref, period_s=period)
    assert m.edges == 9.0
    # the ZOH samples lag one sample: rise time tau ln 9 within one sample
    assert m.rise_time_s == pytest.approx(tau * math.log(9.0), abs=1.5 * dt)
    assert m.overshoot_pct == 0.0
    assert m.ss_e_max_m < 1e-9


def test_steady_state_window_rules() -> None:
    t = np.arange(0, 10000) * 1e-4  # 1 s
    # 100 Hz: skip max(2 periods, 0.1 s) = 0.1 s, then whole periods to the end
    assert metrics.steady_state_start(t, 0.01) == pytest.approx(0.1)
    # 1 Hz, 1 s run: no whole period after the 2 s transient: last whole period = whole run
    assert metrics.steady_state_start(t, 1.0) == pytest.approx(0.0)
    t4 = np.arange(0, 40000) * 1e-4
    assert metrics.steady_state_start(t4, 1.0) == pytest.approx(2.0)
    # 0.3 s period, 4 s: skip 0.6 s
    assert metrics.steady_state_start(t4, 0.3) == pytest.approx(0.6)
    assert metrics.steady_state_start(t4, None) == 0.0


def test_summarize_sine_error_over_whole_periods() -> None:
    dt, f = 1e-4, 10.0
    t = np.arange(0, 5000) * dt  # 0.5 s
    xd = 3.8e-6 + 3.8e-6 * np.sin(2 * np.pi * f * t)
    err = np.where(t < 0.2, 1e-6, 1e-8 * np.sin(2 * np.pi * f * t))  # transient, then a sine
    cmd = np.linspace(-1.0, 9.0, t.size)
    rec = _record(t, xd + err, xd, period=1 / f, cmd=cmd)
    s = metrics.summarize(rec)
    assert s.steady_state_start_s == pytest.approx(0.2)
    assert s.steady_state_samples == 3000
    assert s.e_max_m == pytest.approx(1e-8, rel=1e-6)
    assert s.e_rms_m == pytest.approx(1e-8 / math.sqrt(2), rel=1e-9)
    assert s.e_max_all_m == pytest.approx(1e-6)
    assert s.command_min_v == -1.0 and s.command_max_v == 9.0
    assert s.samples == 5000
    assert s.duration_s == pytest.approx(0.5)
    # an explicit start wins over the period rule
    s0 = metrics.summarize(rec, steady_state_start_s=0.0)
    assert s0.e_max_m == pytest.approx(1e-6)


def test_summarize_same_numbers_in_an_epoch_time_base() -> None:
    # a bag's stamps are seconds since the epoch: the window is relative to the first sample
    dt = 1e-4
    t = np.arange(0, 3000) * dt
    xd = np.sin(2 * np.pi * 20 * t)
    x = xd + 1e-3 * np.cos(2 * np.pi * 20 * t) + np.where(t < 0.1, 1.0, 0.0)
    a = metrics.summarize(_record(t, x, xd, period=0.05))
    b = metrics.summarize(_record(t + 1.7e9, x, xd, period=0.05))
    for key in ('e_max_m', 'e_rms_m', 'steady_state_samples', 'loop_width_pct'):
        assert a.as_dict()[key] == pytest.approx(b.as_dict()[key], rel=1e-9)


def test_summarize_diagnostic_ranges_and_empty_record() -> None:
    t = np.arange(4) * 1e-4
    rec = RunRecord(t, t, t, t, t, diagnostics={'theta_hat': np.array([1.0, 2.0, np.nan, 0.5])})
    s = metrics.summarize(rec)
    assert s.diagnostic_ranges == {'theta_hat': (0.5, 2.0)}
    assert hash(s) == hash(metrics.summarize(rec)) and s == metrics.summarize(rec)
    assert (s.as_dict()['theta_hat_min'], s.as_dict()['theta_hat_max']) == (0.5, 2.0)
    empty = metrics.summarize(RunRecord(*(np.zeros(0),) * 5))
    assert empty.samples == 0 and math.isnan(empty.e_rms_m)


def test_records_give_the_json_field_names_in_order() -> None:
    # as_dict() is the JSON object of simulate --json and analyze --json: names, order, floats
    t = np.arange(0, 2000) * 1e-4
    xd = np.sin(2 * np.pi * 20 * t)
    diag = {'theta_hat': np.full(t.size, 1.5), 'phi_hat': np.linspace(0.0, 1.0, t.size)}
    rec = _record(t, xd + 1e-3, xd, period=0.05)
    rec = RunRecord(rec.time_s, rec.position_m, rec.reference_m, rec.reference_velocity_mps,
                    rec.command_v, diagnostics=diag, meta=rec.meta)
    s = metrics.summarize(rec)
    d = s.as_dict()
    assert list(d) == ['samples', 'e_max_m', 'e_rms_m', 'e_max_all_m', 'e_rms_all_m',
                       'command_min_v', 'command_max_v', 'duration_s', 'steady_state_start_s',
                       'steady_state_samples', 'loop_width_pct', 'phi_hat_min', 'phi_hat_max',
                       'theta_hat_min', 'theta_hat_max']
    assert all(type(v) is float for v in d.values())
    assert (s.samples, d['samples']) == (2000, 2000.0)
    assert d['e_rms_m'] == s.e_rms_m and d['phi_hat_max'] == 1.0
    step = metrics.step_response(t, np.minimum(t / 0.01, 1.0), step_time_s=0.0, initial_m=0.0,
                                 final_m=1.0)
    assert list(step.as_dict()) == ['rise_time_s', 'overshoot_pct', 'settling_time_s',
                                    'settle_band_m', 'ss_e_max_m', 'ss_e_rms_m']
    ref = np.where((t % 0.05) < 0.025, 1.0, 0.0)
    edges = metrics.square_wave_metrics(t, ref, ref, period_s=0.05)
    assert list(edges.as_dict()) == ['rise_time_s', 'overshoot_pct', 'settling_time_s',
                                     'settling_time_max_s', 'settle_band_m', 'ss_e_max_m',
                                     'ss_e_rms_m', 'edges']
    assert edges.edges == 7 and edges.as_dict()['edges'] == 7.0


# Dyadic signals: the reference is a multiple of 2^-40 m (~1e-12 m) below 2^-17 m and every
# error a multiple of 2^-33 m, so x = x_d + e and x - x_d are exact, and so are e^2, a sum of up
# to 2^20 equal squares, the mean and its square root: the metrics below are exact, compared
# with == on purpose (no rounding anywhere, on any machine).
_Q = 2.0 ** -40


def _dyadic_sine(n: int, samples_per_period: int) -> np.ndarray:
    k = np.arange(n)
    return np.round(3.8e-6 * (1 + np.sin(2 * np.pi * k / samples_per_period)) / _Q) * _Q


def _alternating(n: int) -> np.ndarray:
    return np.where(np.arange(n) % 2 == 0, 1.0, -1.0)


def test_true_position_error_over_the_steady_state_window() -> None:
    t_s, per = 1e-4, 500  # a 20 Hz reference sampled at 10 kHz: 0.05 s per period
    n = 6 * per
    xd = _dyadic_sine(n, per)
    # the true error is 2^-28 m during the first two periods (the transient the window skips:
    # max(2 periods, 0.1 s) = 0.1 s) and 2^-31 m (0.47 nm) after, alternating in sign; the
    # measured position carries 3 nm of sensor noise on top
    amplitude = np.where(np.arange(n) < 2 * per, 2.0 ** -28, 2.0 ** -31)
    true = xd + amplitude * _alternating(n)
    measured = true + 3e-9 * np.random.default_rng(1).standard_normal(n)
    rec = RunRecord(np.arange(n) * t_s, measured, xd, np.zeros(n), np.zeros(n),
                    meta={'trajectory_period_s': per * t_s}, true_position_m=true)
    s = metrics.summarize(rec)
    assert s.steady_state_samples == 4 * per
    assert s.e_rms_true_m == 2.0 ** -31 and s.e_max_true_m == 2.0 ** -31
    # the measured error is the noise: 3 nm rms, far above the true 0.47 nm (2000 samples of a
    # unit normal: the sample rms is within 10 % of 1 with overwhelming probability)
    assert s.e_rms_m == pytest.approx(3e-9, rel=0.1)
    d = s.as_dict()
    assert (d['e_max_true_m'], d['e_rms_true_m']) == (2.0 ** -31, 2.0 ** -31)
    # the true fields follow the declared ones; a run without a true position has none of them
    assert list(d)[list(d).index('loop_width_pct') + 1:] == ['e_max_true_m', 'e_rms_true_m']
    bare = metrics.summarize(RunRecord(rec.time_s, measured, xd, rec.reference_velocity_mps,
                                       rec.command_v, meta=rec.meta))
    assert bare.e_rms_true_m is None and bare.e_max_true_m is None
    assert 'e_rms_true_m' not in bare.as_dict()
    assert {k: v for k, v in d.items() if 'true' not in k} == bare.as_dict()


@pytest.mark.parametrize('with_true', [False, True])
def test_per_period_error_of_a_known_error(with_true: bool) -> None:
    # period j has error +-(j + 1) 2^-30 m (measured) and +-(j + 1) 2^-33 m (true): its rms and
    # its max are exactly those amplitudes; 5.5 periods give 5 rows (the half period dropped)
    t_s, per = 1e-4, 100
    n = 11 * per // 2
    k = np.arange(n)
    xd = _dyadic_sine(n, per)
    j = k // per
    measured = xd + (j + 1) * 2.0 ** -30 * _alternating(n)
    true = xd + (j + 1) * 2.0 ** -33 * _alternating(n) if with_true else None
    rec = RunRecord(k * t_s, measured, xd, np.zeros(n), np.zeros(n), true_position_m=true)
    rows = metrics.per_period_error(rec, per * t_s)
    assert len(rows) == 5
    amplitude = np.arange(1, 6) * 2.0 ** -30
    np.testing.assert_array_equal(rows.e_rms_m, amplitude)
    np.testing.assert_array_equal(rows.e_max_m, amplitude)
    np.testing.assert_array_equal(rows.samples, [per] * 5)
    np.testing.assert_allclose(rows.start_s, np.arange(5) * per * t_s, rtol=1e-15)
    if with_true:
        assert rows.e_rms_true_m is not None and rows.e_max_true_m is not None
        np.testing.assert_array_equal(rows.e_rms_true_m, amplitude / 8)
        np.testing.assert_array_equal(rows.e_max_true_m, amplitude / 8)
    else:
        assert rows.e_rms_true_m is None and rows.e_max_true_m is None


def test_per_period_error_of_a_period_that_is_not_a_whole_number_of_samples() -> None:
    # P = 12.3 samples: each period holds 12 or 13 samples, all of them counted once, and the
    # error of a constant-amplitude run is that amplitude in every period
    n = 1000
    xd = np.zeros(n)
    rec = RunRecord(np.arange(n) * 1e-4, xd + 2.0 ** -30 * _alternating(n), xd, xd, xd)
    rows = metrics.per_period_error(rec, 12.3e-4)
    assert len(rows) == math.floor(n / 12.3)
    assert set(rows.samples.tolist()) == {12, 13}
    assert int(rows.samples.sum()) in range(n - 13, n + 1)
    np.testing.assert_array_equal(rows.e_max_m, np.full(len(rows), 2.0 ** -30))
    np.testing.assert_array_equal(rows.e_rms_m, np.full(len(rows), 2.0 ** -30))


def test_per_period_error_edge_cases() -> None:
    short = _record(np.arange(50) * 1e-4, np.ones(50), np.zeros(50))
    assert len(metrics.per_period_error(short, 0.01)) == 0  # shorter than one period
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(PiezoStageError, match='allowed: a finite number > 0 s'):
            metrics.per_period_error(short, bad)
