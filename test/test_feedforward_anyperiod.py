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
Learning on a period of any length (core/control/feedforward.py, PhaseLearning): the table on
the period's harmonics, its convergence and its check, the wrapper, table files.
"""

from __future__ import annotations

import json
import math

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.control.feedforward import (
    boundary_weights,
    FeedForwardController,
    kept_harmonics,
    phase_learning_convergence,
    PhaseLearning,
    START_HOLD_DECAY,
    start_hold_samples,
    whole_period,
)
from piezo_stage_ros.core.control.stability import learning_check
from piezo_stage_ros.core.loop import experiments
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.family import default_family, member_params
import pytest
from test_feedforward import _bound, _controller, LOOP, T
from tolerances import EPS

# 300 Hz (33.3 samples), 70 Hz (142.86), a short odd one and a whole one
PERIODS = [1e4 / 300.0, 1e4 / 70.0, 7.3, 40.0]


def _signal(harmonics: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.standard_normal(harmonics.size), rng.standard_normal(harmonics.size)


def _at(phases: np.ndarray, harmonics: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ang = 2.0 * math.pi * np.multiply.outer(phases, harmonics)
    return np.asarray(np.cos(ang) @ a + np.sin(ang) @ b)


@pytest.mark.parametrize('samples', PERIODS)
def test_a_phase_table_plays_a_band_limited_periodic_signal_at_every_sample(samples) -> None:
    # a signal of the kept harmonics, given on the grid of ceil(n) phases, is held exactly:
    # played at the samples of many periods (whatever phase they fall at) it is the signal
    h = np.arange(1.0, min(5, int((samples - 1e-9) // 2)) + 1)
    a, b = _signal(h, 1)
    table = PhaseLearning(np.ones(h.size, dtype=complex), h, samples, 1, 1e3, 0)
    points = int(math.ceil(samples))
    table.load_grid(_at(np.arange(points) / points, h, a, b))
    k = np.arange(int(20 * samples))
    played = np.array([float(table.play(int(i))[0]) for i in k])
    expected = _at(k / samples % 1.0, h, a, b)
    # phases of k/n to ~k EPS, each term's rounding: a few EPS of the amplitude sum
    scale = float(np.sum(np.hypot(a, b)))
    bound = 8 * h.size * EPS * scale * (1 + float(2 * math.pi * h.max() * k.max() / samples))
    assert np.max(np.abs(played - expected)) <= bound
    assert np.allclose(table.on_grid(points)[:, 0], _at(np.arange(points) / points, h, a, b),
                       rtol=0, atol=bound)


def test_the_trapezoid_weights_integrate_linear_functions_over_a_cut_period() -> None:
    # the boundary weights make the sum over a period's samples the integral of the linear
    # interpolant: exact for a linear integrand across both ends, and the plain sum for a
    # whole period
    assert boundary_weights(0.0) == (1.0, 0.0, 0.5, 0.5)
    for samples in (33.3, 142.857, 7.3):
        for a in (0.0, 0.25, 0.9):
            m = int(math.ceil(samples - a - 1e-12))
            t = a + np.arange(-1, m + 1, dtype=float)  # samples -1 .. m, boundary at 0 and n
            w = np.ones(m + 2)
            w[0] = w[-1] = 0.0
            _, back, own_first, _ = boundary_weights(a)
            own_last, _, _, ahead = boundary_weights(a + m - samples)
            w[0], w[1] = back, own_first
            w[m], w[m + 1] = own_last, ahead
            for slope in (0.0, 1.0):
                f = 2.0 + slope * t
                exact = 2.0 * samples + slope * samples ** 2 / 2.0
                assert float(np.dot(w, f)) == pytest.approx(exact, rel=64 * EPS * samples)


@pytest.mark.parametrize('samples', PERIODS)
def test_on_a_unit_process_the_table_converges_at_the_checked_ratio(samples) -> None:
    # e = L - d with the process sensitivity 1 and F = gamma: the table's harmonics move
    # towards d's by the map phase_learning_convergence bounds, period after period, down to
    # rounding
    gamma = 0.5
    h = np.arange(1.0, min(5, int((samples - 1e-9) // 2)) + 1)
    a, b = _signal(h, 2)
    table = PhaseLearning(np.full(h.size, gamma + 0j), h, samples, 1, 1e3, 0)
    ones = np.ones(int(samples // 2) + 1, dtype=complex)
    kept = np.zeros(ones.size)
    kept[h.astype(int)] = 1.0
    ratio = phase_learning_convergence(ones, ones, gamma, kept, samples)
    assert ratio < 1.0
    if samples.is_integer():
        assert ratio == 1.0 - gamma
    target = np.concatenate([a, b])
    gaps = []
    period = 0
    for k in range(int(45 * samples)):
        value = float(table.play(k)[0])
        if table.periods_learned > period:
            period = table.periods_learned
            gaps.append(float(np.linalg.norm(table.coefficients[:, 0] - target)))
        table.record(k, value - float(_at(np.array([k / samples % 1.0]), h, a, b)[0]))
    gaps_a = np.asarray(gaps)
    steps = gaps_a[1:] / gaps_a[:-1]
    # the map is the period's steady state; the table changes one sample after the period
    # ends (the sample after it is in the sums), which perturbs one of ~n weights by at most
    # 1.5 times the change: 1.5 (1 + ratio) / n on top
    slack = 1.5 * (1.0 + ratio) / samples
    live = gaps_a[:-1] > 1e-9 * gaps_a[0]
    assert np.all(steps[live] <= ratio + slack)
    assert gaps_a[-1] <= 1e-9 * gaps_a[0]


@pytest.mark.parametrize('period_s', [1 / 70, 1 / 300, 1 / 137, 1 / 37.3])
def test_the_learning_check_covers_any_period_and_says_it_converges(period_s) -> None:
    check = learning_check(_controller('inverse_learning'), LOOP.design_plant, T, period_s,
                           stage=LOOP.stage)
    assert check is not None and check.ok
    assert check.period_s == period_s and check.harmonics >= 1
    # the design model: gamma's ratio and the leakage of windows that cut the period, and the
    # computational delay the check assumes, whose phase grows with the highest harmonic kept
    top_hz = check.harmonics / period_s
    assert 0.5 - 1e-9 <= check.design_ratio < (0.6 if top_hz <= 1200.0 else 1.0)
    # the text says when Q reached above its edge for a fast line's first harmonics
    assert ('first harmonics to 1500 Hz' in check.text()) == (top_hz > 1200.0)


@pytest.mark.parametrize('frequency_hz,harmonics', [
    (100.0, 12), (137.0, 8), (240.0, 5), (250.0, 5), (300.0, 5), (400.0, 3), (500.0, 3),
    (1000.0, 1)])
def test_q_keeps_a_fast_line_first_harmonics_a_little_above_its_edge(frequency_hz,
                                                                    harmonics) -> None:
    # up to 1.2 kHz as set; beyond it, the first five harmonics of a line as far as 1.5 kHz
    # (a 300 Hz line keeps its 5th, 1.5 kHz; a 400 Hz line's 4th, 1.6 kHz, stays out)
    samples = 1.0 / (frequency_hz * T)
    ps = np.ones(int(samples // 2) + 1, dtype=complex)
    kept = kept_harmonics(ps, samples, T, 1200.0)
    assert int(np.sum(kept)) == harmonics and kept[0] == 0.0
    assert np.array_equal(np.flatnonzero(kept), np.arange(1, harmonics + 1))


def test_whole_periods_keep_the_table_of_samples() -> None:
    assert whole_period(0.01, T) == (100, 100.0)
    assert whole_period(1 / 70, T)[0] == 0
    whole = _bound('learning', {'kind': 'sine', 'sine.frequency_hz': 100.0})
    assert whole.phase_table is None and whole.learned_table().size == 100
    cut = _bound('learning', {'kind': 'sine', 'sine.frequency_hz': 300.0})
    assert cut.phase_table is not None and cut.learned_table().size == 34


@pytest.mark.parametrize('period_s', [3.5e-4, 2.5e-4])
def test_a_period_too_short_to_learn_is_refused_with_the_range(period_s) -> None:
    with pytest.raises(ParameterError, match=r'feedforward.period_s.*at least 4 samples '
                       r'\(>= 0.0004 s, a line rate <= 2500 Hz'):
        _bound('learning', {'kind': 'sine'}, **{'feedforward.period_s': period_s})


def _true_rms_tail(rec: experiments.RunRecord, tail_s: float) -> float:
    assert rec.true_position_m is not None
    sel = rec.time_s - rec.time_s[0] >= rec.time_s[-1] - rec.time_s[0] - tail_s
    return float(np.sqrt(np.mean((rec.true_position_m - rec.reference_m)[sel] ** 2)))


def test_learning_at_300_hz_removes_what_the_inverse_leaves_in_its_band() -> None:
    tp = TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(), 'kind': 'sine',
                                     'sine.frequency_hz': 300.0})
    # a stage with a shorter time constant than the model: the model inverse alone leaves a
    # lag in the learning's band (on the design stage it leaves only the converters' floor)
    fam = {m.name: m for m in default_family()}
    stage = member_params(LOOP.stage, fam['tau_lo'])
    runs = {mode: experiments.run_one(stage, _controller(mode), tp, duration_s=0.5,
                                      design_plant=LOOP.design_plant)
            for mode in ('inverse', 'inverse_learning')}
    inverse = _true_rms_tail(runs['inverse'], 0.1)
    learned = _true_rms_tail(runs['inverse_learning'], 0.1)
    # 150 periods at a ratio of 0.5: the four learned harmonics of the error are gone; what
    # stays lies above Q (1.2 kHz) and under the converters
    assert learned <= 0.5 * inverse
    diag = runs['inverse_learning'].diagnostics
    assert diag['ff_periods_learned'][-1] >= 140


def test_a_table_file_of_a_cut_period_round_trips_and_another_rate_is_refused(tmp_path) -> None:
    sine = {'kind': 'sine', 'sine.frequency_hz': 300.0}
    tp = TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(), **sine})
    kept: list[FeedForwardController] = []
    experiments.run_one(LOOP.stage, _controller('inverse_learning'), tp, duration_s=0.1,
                        design_plant=LOOP.design_plant, built=kept.append)
    path = kept[0].save_table_file(tmp_path / 'table.npz')
    loaded = _bound('inverse_learning', sine, **{'feedforward.table_file': str(path)})
    saved = kept[0].learned()
    assert loaded.learned().period_s == saved.period_s == 1 / 300.0
    # grid -> DFT -> harmonics -> grid: a few rounding steps of the table's size
    bound = 64 * EPS * float(np.sum(np.abs(saved.table_v)))
    assert np.max(np.abs(loaded.learned_table() - saved.table_v)) <= bound
    assert np.max(np.abs(saved.table_v)) > 1e6 * bound  # not a table of zeros
    with pytest.raises(ParameterError, match=r'feedforward.table_file.*learned for a period '
                       r'of 0.00333'):
        _bound('inverse_learning', {'kind': 'sine', 'sine.frequency_hz': 301.0},
               **{'feedforward.table_file': str(path)})


# -- the limits: the amplifier's range and the table's bound ---------------------------------

SATURATING = {'kind': 'sine', 'sine.amplitude_m': 14.3e-6, 'sine.offset_m': 15e-6}


def _saturating(mode: str, frequency: float, duration_s: float,
                **flat: object) -> tuple[experiments.RunRecord, object]:
    tp = TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(), **SATURATING,
                                     'sine.frequency_hz': frequency})
    kept: list[object] = []
    rec = experiments.run_one(LOOP.stage, _controller(mode, **flat), tp,
                              duration_s=duration_s, design_plant=LOOP.design_plant,
                              built=kept.append)
    return rec, kept[0]


@pytest.mark.parametrize('frequency', [50.0, 47.3])  # a whole period and a cut one
def test_at_the_amplifiers_limit_learning_is_no_worse_than_feedback_alone(frequency) -> None:
    # the sine's top needs more than the amplifier's 10 V: no table can follow it there.
    # Feedback alone is the floor a learning that stays right at the limit must not leave
    runs = {mode: _saturating(mode, frequency, 1.5)
            for mode in ('none', 'learning', 'inverse_learning')}
    alone = _true_rms_tail(runs['none'][0], 0.5)
    for mode in ('learning', 'inverse_learning'):
        rec, ctrl = runs[mode]
        assert isinstance(ctrl, FeedForwardController)
        assert ctrl.clipped_samples > 0  # the limit was active, and the run knows it
        assert _true_rms_tail(rec, 0.5) <= alone
        # the table holds no DC: the learning filter has none and the clipped-off part is
        # projected on Q's band
        table = ctrl.learned_table()
        assert abs(float(np.mean(table))) <= 4 * table.size * EPS * float(np.max(np.abs(table)))


def test_the_tables_bound_scales_it_inside_q_and_without_dc() -> None:
    limit = 0.02
    for frequency in (50.0, 47.3):
        _, ctrl = _saturating('learning', frequency, 0.3,
                              **{'feedforward.learning_limit_v': limit})
        assert isinstance(ctrl, FeedForwardController)
        table = ctrl.learned_table()
        assert ctrl.limited_updates > 0
        assert np.max(np.abs(table)) <= limit * (1 + 4 * EPS)
        assert abs(float(np.mean(table))) <= 4 * table.size * EPS * limit


def test_simulate_reports_the_limit_and_the_learning_checks_assumption(capsys) -> None:
    from piezo_stage_ros import simulate
    assert simulate.main(['--trajectory', 'sine', '--frequency', '50', '--amplitude',
                          '14.3e-6', '--offset', '15e-6', '--duration', '0.2',
                          '--feedforward', 'learning']) == 0
    out = capsys.readouterr().out
    assert 'assumes a linear loop: the command inside the amplifier range' in out
    assert 'LIMIT ACTIVE: the amplifier range clipped' in out
    assert simulate.main(['--trajectory', 'sine', '--frequency', '50', '--duration', '0.2',
                          '--feedforward', 'learning']) == 0
    assert 'LIMIT ACTIVE' not in capsys.readouterr().out


# -- references with jumps ------------------------------------------------------------------


@pytest.mark.parametrize('sample_time_s', [1e-5, 1e-4, 1e-3])
def test_the_jump_test_scales_with_the_sampling(sample_time_s) -> None:
    from piezo_stage_ros.core.control.feedforward import shape_jumps
    t = np.arange(4000) * sample_time_s
    fs = 1.0 / sample_time_s
    for fraction in (0.001, 0.03, 0.1, 0.2):  # sines up to a fifth of the sample rate
        w = 2 * math.pi * fraction * fs
        for amplitude in (1e-9, 1e-6, 19e-6):
            x = 19e-6 + amplitude * np.sin(w * t)
            v = amplitude * w * np.cos(w * t)
            assert shape_jumps(x, v, sample_time_s, 10 * sample_time_s)[2] == 0
    # a triangle's corners are turns of the velocity, not jumps of the position
    tri = make_trajectory(TrajectoryParams.from_flat({'kind': 'triangle',
                                                      'triangle.frequency_hz': 0.05 * fs}))
    x, v = tri.evaluate(t)
    assert shape_jumps(np.asarray(x), np.asarray(v), sample_time_s, 10 * sample_time_s)[2] == 0
    # a jump of a reference at rest is found at the tolerance, whatever the sampling
    rest = np.where(t >= t[2000], 4e-6 + 1.01e-9, 4e-6)
    assert shape_jumps(rest, np.zeros_like(t), sample_time_s, 10 * sample_time_s)[2] == 1
    # and one riding on a fast sine (300 Hz at 10 kHz), above the motion's own allowance:
    # 2 T (d2 / 2 + d2 / 12) with d2 = A w (w T)^2 is 7/6 (w T)^3 = 0.8 % of the amplitude
    w = 2 * math.pi * 0.03 * fs
    x = 3.8e-6 * np.sin(w * t) + np.where(t >= t[2000], 0.1e-6, 0.0)
    assert shape_jumps(x, 3.8e-6 * w * np.cos(w * t), sample_time_s,
                       10 * sample_time_s)[2] == 1


@pytest.mark.parametrize('mode', ['learning', 'inverse_learning'])
def test_a_square_wave_is_learned_on_the_shaped_path(mode) -> None:
    # Fig. 10: 7.8 um, 0.5 s. Learning against the path the feedback follows: no overshoot to
    # learn, and nothing to move before an edge (the S-curve starts at it)
    tp = TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(), 'kind': 'square'})
    sq = tp.square
    periods = 3
    rec = experiments.run_one(LOOP.stage, _controller(mode), tp,
                              duration_s=periods * sq.period_s,
                              design_plant=LOOP.design_plant)
    assert rec.true_position_m is not None
    t = rec.time_s - rec.time_s[0]
    y = rec.true_position_m
    low, high = sq.low_m, sq.low_m + sq.peak_to_peak_m
    last = periods - 1
    for edge, before, after in (((last + 1 - sq.duty) * sq.period_s, low, high),
                                (last * sq.period_s, high, low)):
        k = int(np.searchsorted(t, edge - 0.5 * T))
        ahead = y[k - int(0.05 / T):k]
        assert np.max(np.abs(ahead - before)) <= 5e-9
        over = (np.max(y[k:k + 1000]) - high if after > before else low - np.min(y[k:k + 1000]))
        assert over <= 0.02 * sq.peak_to_peak_m


# -- a change of line rate while running -----------------------------------------------------


def _rate_change(mode: str, first_hz: float, second_hz: float, at_s: float,
                 lines: int) -> list[float]:
    from piezo_stage_ros.core.loop.switched import LineRateChange
    tp = TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(), 'kind': 'sine',
                                     'sine.frequency_hz': first_hz})
    traj = LineRateChange(make_trajectory(tp),
                          make_trajectory(tp.with_flat({'sine.frequency_hz': second_hz})), at_s)
    rec = experiments.run_one(LOOP.stage, _controller(mode), tp,
                              duration_s=at_s + lines / second_hz,
                              design_plant=LOOP.design_plant, trajectory=traj)
    assert rec.true_position_m is not None
    assert rec.diagnostics['ff_mismatches'][-1] == 0  # every sample had the feed-forward
    t = rec.time_s - rec.time_s[0]
    e = rec.true_position_m - rec.reference_m
    line = np.floor((t - at_s) * second_hz + 1e-9).astype(int)
    return [float(np.sqrt(np.mean(e[line == j] ** 2))) for j in range(lines)]


def test_a_new_line_rate_starts_from_the_model_inverse_and_learns_again() -> None:
    # 100 Hz (100 samples a line) to 137 Hz (72.99): the second period is not whole
    learned = _rate_change('inverse_learning', 100.0, 137.0, 0.5, 50)
    inverse = _rate_change('inverse', 100.0, 137.0, 0.5, 50)
    # the first new line: the model inverse and a table started afresh at zero, as the inverse
    # alone (the RAC's estimates differ by their history, held or adapting: a few per cent)
    assert learned[0] <= 1.05 * inverse[0]
    # the new sine starts at its t = 0 with another velocity: the first line holds that
    # transient; from then on the new table learns
    assert max(learned[-5:]) <= 1e-9
    # on the design stage the inverse alone, its estimates held over the new start, is at the
    # converter's floor too: the learning is no worse than it beyond the lines' own spread
    # (each line's rms is one draw of the sensor noise, 0.18-0.26 nm)
    assert np.mean(learned[-5:]) <= 1.25 * np.mean(inverse[-5:])


class _Lines:
    """Sine lines whose rate changes every ``every_s``: the segments a line-rate change gives."""

    period_s = None

    def __init__(self, rates_hz: tuple[float, ...], every_s: float) -> None:
        tp = TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(), 'kind': 'sine'})
        self._parts = tuple((every_s * i, make_trajectory(tp.with_flat(
            {'sine.frequency_hz': r}))) for i, r in enumerate(rates_hz))

    @property
    def segments(self) -> tuple[tuple[float, object], ...]:
        return self._parts

    def evaluate(self, time_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(time_s, dtype=np.float64)
        x, v = np.zeros_like(t), np.zeros_like(t)
        for start, traj in self._parts:
            on = t >= start - 1e-12
            if np.any(on):
                x[on], v[on] = traj.evaluate(t[on] - start)
        return x, v


def test_changes_of_line_rate_leave_the_held_estimates_where_they_were() -> None:
    # inverse_learning holds the RAC's estimates and takes their term off the command. Released
    # at each change of line rate under that term, they re-adapted and were held again with
    # both offsets: on a stage with more gain than the model they walked to the box's bound in
    # three changes. Held through a change, they stay, and every line rate is learned.
    stage = member_params(LOOP.stage, {m.name: m for m in default_family()}['gain_hi'])
    rates, every = (100.0, 137.0, 100.0, 137.0), 0.3
    tp = TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(), 'kind': 'sine'})
    rec = experiments.run_one(stage, _controller('inverse_learning'), tp,
                              duration_s=every * len(rates), design_plant=LOOP.design_plant,
                              trajectory=_Lines(rates, every))
    assert rec.true_position_m is not None
    assert rec.diagnostics['ff_mismatches'][-1] == 0
    t = rec.time_s - rec.time_s[0]
    held = np.flatnonzero(t < every)[-1]
    for name in ('theta_hat', 'phi_hat'):
        values = rec.diagnostics[name]
        assert np.all(values[t >= every] == values[held]), name
    e = rec.true_position_m - rec.reference_m
    last = t >= every * len(rates) - 0.05
    assert float(np.sqrt(np.mean(e[last] ** 2))) <= 1e-9


def test_a_line_rate_change_is_refused_by_the_batch_and_checked_at_its_time() -> None:
    from piezo_stage_ros.core.loop.switched import LineRateChange
    sine = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine'}))
    with pytest.raises(ParameterError, match=r'line_rate_change.at_s.*whole number of the '
                       r'first line period \(0.01 s\)'):
        LineRateChange(sine, sine, 0.015)
    with pytest.raises(ParameterError, match=r'line_rate_change.at_s'):
        LineRateChange(sine, sine, 0.0)
    # 73 periods of 137 Hz end between two samples: the new line would start between them
    fast = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine',
                                                       'sine.frequency_hz': 137.0}))
    with pytest.raises(ParameterError, match=r'line_rate_change.at_s.*a whole number of '
                       r'samples \(T = 0.0001 s\)'):
        _bound('inverse', {'kind': 'sine'}).bind(LineRateChange(fast, sine, 73 / 137.0))


def test_the_controller_logic_binds_a_new_trajectory_where_it_starts() -> None:
    from piezo_stage_ros.nodes.logic import ControllerLogic, TrajectoryLogic
    first = make_trajectory(TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(),
                                                        'kind': 'sine'}))
    second = make_trajectory(TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(),
                                                         'kind': 'sine',
                                                         'sine.frequency_hz': 137.0}))
    ctrl = _bound('inverse_learning', {'kind': 'sine'})
    logic = ControllerLogic(ctrl)
    refs = TrajectoryLogic(first, sample_rate_hz=1e4)
    y = 3.8e-6
    for k in range(600):
        if k == 250:
            refs.switch(second)
            logic.request_trajectory(second)
        stamp = k * 100_000
        x, v = refs.on_position(stamp)
        logic.on_reference(stamp, x, v)
        command = logic.on_position(stamp, y, k * 1e-4)
        assert command is not None
        y = x  # a stage that follows: only the reference bookkeeping is checked
    assert ctrl.mismatches == 0
    assert ctrl.learned().period_s == 1 / 137.0
    assert ctrl.periods_learned >= 3


def test_a_line_rate_above_the_nyquist_frequency_is_refused_in_every_mode() -> None:
    for mode in ('inverse', 'learning'):
        # a sine at 5 kHz is two samples a period: drawn at its zero crossings, it is nothing
        with pytest.raises(ParameterError, match=r"'trajectory period'.*is 2 samples.*allowed: "
                           r'> 0.0002 s \(a line rate below the Nyquist frequency, 5000 Hz\)'):
            _bound(mode, {'kind': 'sine', 'sine.frequency_hz': 5000.0})
        with pytest.raises(ParameterError, match=r"'feedforward.period_s'.*1.5 samples"):
            _bound(mode, {'kind': 'sine'}, **{'feedforward.period_s': 1.5e-4})


def test_a_70_hz_triangle_is_learned_in_the_middle_of_its_lines() -> None:
    # 142.86 samples a line pair; its corners are turns of the velocity, not jumps (nothing
    # shaped): the middle 80 % of each line, trace and retrace, within 2 nm
    tp = TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(), 'kind': 'triangle',
                                     'triangle.frequency_hz': 70.0})
    rec = experiments.run_one(LOOP.stage, _controller('inverse_learning'), tp, duration_s=1.0,
                              design_plant=LOOP.design_plant)
    period = 1.0 / 70.0
    t = rec.time_s - rec.time_s[0]
    phase = ((t - period / 4) % (period / 2)) / (period / 2)
    middle = (phase > 0.1) & (phase < 0.9) & (t >= 0.5)
    e = rec.position_m - rec.reference_m
    assert float(np.sqrt(np.mean(e[middle] ** 2))) <= 2e-9
    assert rec.true_position_m is not None  # and the true position everywhere in them
    assert float(np.max(np.abs((rec.true_position_m - rec.reference_m)[middle]))) <= 2e-9


def test_commands_ahead_at_a_period_that_is_not_whole_follow_the_phase_table() -> None:
    # the servo with commands ahead: at 137 Hz the learned table is read ahead on the period's
    # phase; the commands predicted for the next 32 samples against those then given
    import dataclasses

    from piezo_stage_ros.bench.servo import loop_config
    from test_commands_ahead import servo_predictions
    loop = loop_config()
    ff = dataclasses.replace(loop.controller.feedforward, mode='inverse_learning')
    loop = dataclasses.replace(
        loop, controller=dataclasses.replace(loop.controller, feedforward=ff),
        trajectory=loop.trajectory.with_flat({'kind': 'sine', 'sine.frequency_hz': 137.0}))
    predictions, commands, servo = servo_predictions(loop, 0.12, (700, 725, 750, 1100))
    assert servo.controller is not None
    assert servo.controller.controller.phase_table is not None
    for k, predicted in predictions.items():
        actual = commands[k + 1:k + 33]
        held = np.abs(actual - commands[k]).max()
        assert np.abs(predicted - actual).max() < 0.05 * held


def test_simulate_changes_the_line_rate_and_checks_the_new_period(capsys) -> None:
    from piezo_stage_ros import simulate
    # the figure: within 50 lines of the new rate (0.2 + 50 / 137 s), <= 1 nm
    assert simulate.main(['--trajectory', 'sine', '--frequency', '100', '--duration', '0.7',
                          '--feedforward', 'inverse_learning', '--line-rate-change',
                          '0.2:137', '--steady-state-start', '0.565', '--json']) == 0
    out = json.loads(capsys.readouterr().out)
    assert out['e_rms_m'] <= 1e-9 and out['e_rms_true_m'] <= 1e-9
    assert simulate.main(['--trajectory', 'sine', '--frequency', '100', '--duration', '0.4',
                          '--feedforward', 'inverse_learning', '--line-rate-change',
                          '0.2:137']) == 0
    assert 'learning check after the line-rate change: Learning (gamma 0.5, Q to 1200 Hz: 8 ' \
        'harmonics of 0.00729927 s' in capsys.readouterr().out
    assert simulate.main(['--trajectory', 'sine', '--frequency', '100', '--duration', '0.4',
                          '--line-rate-change', '0.205:137']) != 0
    assert 'whole number of the first line period' in capsys.readouterr().err


def test_learning_alone_learns_a_new_line_rate_again() -> None:
    # without the model inverse in the loop, the new table starts at the design model's input
    # for the new reference (in Q's band) and learns the new line to the converter floor
    learned = _rate_change('learning', 100.0, 137.0, 0.5, 50)
    assert max(learned[-5:]) <= 1e-9


def test_learning_alone_first_new_line_no_worse_than_the_inverse_alone() -> None:
    # the new table starts from the model inverse's command (its hysteresis compensation in
    # Q's band), so the first line of the new rate is no worse than the inverse alone, both
    # ways: to a period that is not whole (137 Hz) and to a whole one (100 Hz)
    for first_hz, second_hz, at_s in ((100.0, 137.0, 0.5), (137.0, 100.0, 1.0)):
        learned = _rate_change('learning', first_hz, second_hz, at_s, 2)
        inverse = _rate_change('inverse', first_hz, second_hz, at_s, 2)
        assert learned[0] <= inverse[0]


def test_the_seed_command_is_a_periodic_orbit_of_the_design_hysteresis() -> None:
    # the seed's command v, played period after period through the design hysteresis from
    # rest, settles on the outputs asked (its memory fades within a few periods); the solve's
    # tolerance is 1e-10 V on w and the orbit is taken once it repeats to 1e-9 of its span
    ctrl = _bound('learning', {'kind': 'sine', 'sine.frequency_hz': 137.0})
    w = 3.0 + 2.5 * np.sin(2.0 * math.pi * np.arange(73) / 73.0)
    v = ctrl._periodic_hysteresis_inverse(w)
    model = ctrl._hysteresis_model
    state = model.rest_state(float(v[0]))
    outputs = []
    for _ in range(12):
        out = []
        for value in v:
            state, y = model.step(state, float(value))
            out.append(float(y))
        outputs.append(np.array(out))
    assert np.max(np.abs(outputs[-1] - w)) <= 4e-9 * float(np.ptp(w))
    assert np.max(np.abs(outputs[-1] - outputs[-2])) <= 4e-9 * float(np.ptp(w))
    # backlash-like hysteresis lags: the orbit's input is not the output scaled by the slope
    assert np.max(np.abs(v - w / model.slope)) > 1e-3


def test_a_fast_raster_line_is_learned_to_the_nanometre_on_its_linear_part() -> None:
    # 300 Hz, 80 % linear (33.3 samples a line): the turnarounds' harmonics above Q are the
    # model inverse's alone, so the term the held estimates add there must not stay in the
    # command; on the design stage the linear part is then within the 1 nm
    from piezo_stage_ros.core.loop import metrics
    tp = TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(), 'kind': 'scan_line',
                                     'scan_line.frequency_hz': 300.0})
    box: dict[str, FeedForwardController] = {}
    rec = experiments.run_one(LOOP.stage, _controller('inverse_learning'), tp, duration_s=0.6,
                              design_plant=LOOP.design_plant,
                              built=lambda c: box.setdefault('c', c))
    window = metrics.window_slice(rec.time_s - rec.time_s[0], 0.4, 1.0 / 300.0)
    lm = metrics.line_metrics(rec, window)
    assert lm.trace_e_rms_true_m is not None and lm.retrace_e_rms_true_m is not None
    assert max(lm.trace_e_rms_true_m, lm.retrace_e_rms_true_m) <= 1e-9
    # the estimates were held away from their initial values: the term was there to take off
    ctrl = box['c']
    assert ctrl._drift_gains != (0.0, 0.0)
    # and the table saved for a later run holds none of it (relative to the initial
    # estimates, with which a loaded table starts held)
    assert np.array_equal(ctrl.learned().table_v, ctrl.learned_table())


def _fundamental_rms(rec: experiments.RunRecord, freq_hz: float, tail_s: float) -> float:
    """Return the rms of the true error's component at ``freq_hz`` over the last tail_s."""
    assert rec.true_position_m is not None
    t = rec.time_s - rec.time_s[0]
    sel = t >= t[-1] - tail_s
    w = 2.0 * np.pi * freq_hz * t[sel]
    # least squares on cos, sin and an offset: many periods, so the columns are near
    # orthogonal whether or not the window holds whole periods
    basis = np.column_stack([np.cos(w), np.sin(w), np.ones_like(w)])
    coef = np.linalg.lstsq(basis, (rec.true_position_m - rec.reference_m)[sel], rcond=None)[0]
    return float(np.hypot(coef[0], coef[1]) / np.sqrt(2.0))


@pytest.mark.parametrize('kind', ['sine', 'scan_line'])
def test_inverse_alone_at_1_khz_keeps_its_estimates_and_its_error(kind) -> None:
    # a line near the loop's limits: the adaptation cannot remove what the model inverse
    # leaves there, and the start's transient must not start a drift of the estimates
    tp = TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(), 'kind': kind,
                                     f'{kind}.frequency_hz': 1000.0})
    built: list = []
    rec = experiments.run_one(LOOP.stage, _controller('inverse'), tp, duration_s=0.3,
                              design_plant=LOOP.design_plant, built=built.append)
    frozen = experiments.run_one(LOOP.stage, _controller('inverse', **{'rac.gamma': 0.0,
                                                                      'rac.eta': 0.0}),
                                 tp, duration_s=0.3, design_plant=LOOP.design_plant)
    rac = LOOP.controller.rac
    theta, phi = rec.diagnostics['theta_hat'], rec.diagnostics['phi_hat']
    # a drift runs to the box's bounds (tens of percent); the start alone moves them far less
    assert np.max(np.abs(theta / rac.theta_init - 1.0)) <= 0.01
    assert np.max(np.abs(phi / rac.phi_init - 1.0)) <= 0.01
    # the error stays what the model inverse gives with the estimates frozen at their start
    assert _true_rms_tail(rec, 0.1) <= 1.5 * _true_rms_tail(frozen, 0.1)
    assert built[0].clipped_samples == 0


@pytest.mark.parametrize(('freq_hz', 'target_m'), [(300.0, 1.6e-9), (500.0, 2.4e-9)])
def test_inverse_alone_leaves_no_error_at_the_fundamental(freq_hz, target_m) -> None:
    # a start-up transient adapted on would leave phi_hat off its start inside the dead zone,
    # an error k d_phi x_d' at the fundamental that nothing takes off again
    tp = TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(), 'kind': 'sine',
                                     'sine.frequency_hz': freq_hz})
    rec = experiments.run_one(LOOP.stage, _controller('inverse'), tp, duration_s=0.3,
                              design_plant=LOOP.design_plant)
    # a quarter of the target: the rest is left to the harmonics and the converters
    assert _fundamental_rms(rec, freq_hz, 0.1) <= 0.25 * target_m
    assert _true_rms_tail(rec, 0.1) <= target_m


def test_the_start_hold_lasts_until_the_slowest_mode_has_decayed() -> None:
    # poles 0.5 and 0.9: the slower one decays to START_HOLD_DECAY after ln(d) / ln(0.9)
    den = np.poly([0.5, 0.9])
    n = start_hold_samples(den)
    assert 0.9 ** n <= START_HOLD_DECAY < 0.9 ** (n - 1)
    # nothing to wait for: no dynamics, or a mode that does not decay
    assert start_hold_samples(np.ones(1)) == 0
    assert start_hold_samples(np.poly([1.0, 0.5])) == 0
    # learning modes never hold at the start (their own hold starts after the start periods)
    assert _bound('inverse', {'kind': 'sine'}).start_hold > 0
    assert _bound('inverse_learning', {'kind': 'sine'}).start_hold == 0
