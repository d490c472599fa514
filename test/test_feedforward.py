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
Feed-forward (core/control/feedforward.py): exact inverses, the stable preview inversion, jump
shaping, learning, and the issue-16 targets on the default stage in the offline closed loop.
"""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
from piezo_stage_ros.core.config.loader import load_loop_config
from piezo_stage_ros.core.contracts.errors import ParameterError, PiezoStageError
from piezo_stage_ros.core.control.controllers import (
    build_controller,
    ControllerParams,
    RACController,
)
from piezo_stage_ros.core.control.feedforward import (
    FeedForwardController,
    LearnedTable,
    make_hysteresis_inverse,
    PreviewInverse,
    read_learned_table,
    shape_jumps,
    TABLE_FORMAT,
    TABLE_VERSION,
)
from piezo_stage_ros.core.control.stability import (
    check_stability,
    learning_check,
    stability_plant,
)
from piezo_stage_ros.core.loop import closed_loop, experiments
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.family import member_params, StageVariation
from piezo_stage_ros.core.model.hysteresis import (
    BacklashLike,
    BacklashLikeParams,
    HysteresisParams,
    make_hysteresis,
)
from piezo_stage_ros.core.model.stage import linear_plant, Stage, StageParams
import pytest
from scipy.signal import lfilter
from tolerances import EPS

T = 1e-4
LOOP = load_loop_config([])
#: the check without computational delay: the loop the learning filter is designed for, where
#: the ratios below have closed forms
NO_DELAY = LOOP.stability.replace(delay_samples=0.0)


def _controller(mode: str, **flat: object) -> ControllerParams:
    values = {**LOOP.controller.to_flat(), 'feedforward.mode': mode, **flat}
    return ControllerParams.from_flat(values)


def _run(mode: str, trajectory: dict[str, object], duration_s: float,
         **controller: object) -> experiments.RunRecord:
    tp = TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(), **trajectory})
    return experiments.run_one(LOOP.stage, _controller(mode, **controller), tp,
                               duration_s=duration_s, design_plant=LOOP.design_plant)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


# -- inverse hysteresis -----------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-2.0, 10.0), min_size=1, max_size=20), st.floats(-2.5, 11.0))
def test_backlash_inverse_is_exact_from_any_state(history: list[float], target: float) -> None:
    model = BacklashLike(BacklashLikeParams())
    inv = make_hysteresis_inverse(model)
    inv.reset(0.0)
    state = model.rest_state(0.0)
    for v in history:
        inv.commit(v)
        state, _ = model.step(state, v)
    v = inv.invert(target)
    _, w = model.step(state, v)
    # Newton stops within its tolerance; the model's own step adds the rounding of c v + e
    assert abs(w - target) <= inv.tolerance_v + 16 * EPS * (abs(target) + abs(v) + 1.0)


@pytest.mark.parametrize('kind', ['prandtl_ishlinskii', 'bouc_wen'])
def test_iterative_inverse_meets_its_tolerance(kind: str) -> None:
    model = make_hysteresis(HysteresisParams(model=kind))
    inv = make_hysteresis_inverse(model)
    inv.reset(1.0)
    state = model.rest_state(1.0)
    state, _ = model.step(state, 1.0)
    for target in (1.5, 4.0, 2.0, 2.1, -0.5, 8.0, 7.99):
        v = inv.invert(target)
        state, w = model.step(state, v)
        inv.commit(v)
        assert abs(w - target) <= inv.tolerance_v


# -- stable preview inversion ---------------------------------------------------------------


def _reference(n: int) -> np.ndarray:
    t = np.arange(n) * T
    return 5e-6 + 2e-6 * np.sin(2 * math.pi * 100 * t) + 0.5e-6 * np.sin(2 * math.pi * 700 * t)


@pytest.mark.parametrize('model', ['third_order', 'reduced', 'electromechanical'])
def test_preview_inverse_reproduces_the_reference_through_the_model(model: str) -> None:
    plant = linear_plant(StageParams.from_flat({'plant.model': model}).plant)
    inv = PreviewInverse(plant, T, preview=40)
    x = _reference(3000)
    x[:200] = x[200]  # at rest before the motion, as the filter's start state assumes
    w, _ = inv.block(x, inv.start(float(x[0])))
    # w_k for k = back .. len(x) - lead - 1; the model's output one sample later is x_{k+1}
    num = np.concatenate([np.zeros(len(inv.den) - len(inv.num)), inv.num])
    y = lfilter(num, inv.den, np.concatenate([np.full(200, w[0]), w]))[200:]
    k = np.arange(inv.back, len(x) - inv.lead)
    err = y[: len(k) - 1] - x[k[:-1]] if inv.delay == 0 else y[:len(k)] - x[k]
    # truncation of the anti-causal series (its last term bounds the tail: |z_o| > 1) plus
    # rounding amplified by the inverse's gain (sum of |taps|)
    gain = float(np.sum(np.abs(inv.taps)) * abs(inv.dc_gain))
    bound = (inv.truncation * 10 + 1e3 * EPS * gain) * float(np.max(np.abs(x)))
    assert np.max(np.abs(err[300:])) <= bound


def test_periodic_inverse_equals_the_block_inverse_in_steady_state() -> None:
    plant = linear_plant(StageParams().plant)
    inv = PreviewInverse(plant, T, preview=40)
    period = 100
    x = _reference(40 * period)
    block, _ = inv.block(x, inv.start(float(x[0])))
    per = inv.periodic(x[:period])
    k = np.arange(inv.back, len(x) - inv.lead)
    late = k >= 20 * period  # the causal part's start transient has decayed (poles < 0.9)
    gain = float(np.sum(np.abs(inv.taps)))
    assert np.max(np.abs(block[late] - per[k[late] % period])) <= \
        (inv.truncation * 10 + 1e4 * EPS) * gain * float(np.max(np.abs(x)))


# -- jumps ------------------------------------------------------------------------------------


def test_shape_jumps_replaces_each_jump_by_an_s_curve_starting_at_it() -> None:
    x = np.r_[np.full(50, 1e-6), np.full(50, 3e-6), np.full(50, 2e-6)]
    v = np.zeros_like(x)
    xs, vs, jumps = shape_jumps(x, v, T, 1e-3)
    assert jumps == 2
    # untouched before each jump and after each transition (10 samples)
    assert np.array_equal(xs[:50], x[:50])
    assert np.array_equal(xs[61:100], x[61:100]) and np.array_equal(xs[111:], x[111:])
    # monotone between the levels, no overshoot
    assert np.all(np.diff(xs[49:62]) >= 0.0) and xs[49:62].max() <= 3e-6
    # the velocity integrates to the path (trapezoid within the quintic's curvature)
    seg = vs[49:62]
    assert abs(0.5 * T * float(np.sum(seg[1:] + seg[:-1])) - 2e-6) <= 1e-3 * 2e-6


def test_smooth_references_are_not_shaped() -> None:
    t = np.arange(1000) * T
    x = np.sin(2 * math.pi * 100 * t) * 3.8e-6
    v = np.cos(2 * math.pi * 100 * t) * 3.8e-6 * 2 * math.pi * 100
    xs, vs, jumps = shape_jumps(x, v, T, 1e-3)
    assert jumps == 0 and xs is x and vs is v


# -- the wrapper ------------------------------------------------------------------------------


def test_mode_none_builds_the_plain_controller() -> None:
    ctrl = build_controller(_controller('none'), T, linear_plant(LOOP.design_plant))
    assert not isinstance(ctrl, FeedForwardController)


def test_feedforward_needs_a_plant_model() -> None:
    with pytest.raises(ParameterError, match='feedforward.mode'):
        build_controller(_controller('inverse'), T)


def test_learning_refuses_an_aperiodic_reference() -> None:
    ctrl = build_controller(_controller('learning'), T, linear_plant(LOOP.design_plant))
    assert isinstance(ctrl, FeedForwardController)
    step = make_trajectory(TrajectoryParams.from_flat({'kind': 'step'}))
    with pytest.raises(ParameterError, match='period'):
        ctrl.bind(step)


def test_a_reference_that_is_not_the_bound_one_gets_feedback_alone() -> None:
    params = _controller('inverse', **{'notch.mode': 'off'})
    ff = build_controller(params, T, linear_plant(LOOP.design_plant),
                          make_hysteresis(HysteresisParams(model='none')))
    plain = RACController(params.rac, T, sensor_gain_v_per_m=params.sensor_gain_v_per_m)
    assert isinstance(ff, FeedForwardController)
    ff.bind(make_trajectory(TrajectoryParams.from_flat({'kind': 'sine'})))
    ff.reset(4e-6, 4e-6)
    plain.reset(4e-6, 4e-6)
    for k in range(20):
        y, xd = 4e-6 + 1e-9 * k, 9e-6  # far from the bound sine
        plain.hold_estimates(k < ff.start_hold)  # inverse alone holds them at the start
        assert ff.step(y, xd, 0.0) == plain.step(y, xd, 0.0)
    assert ff.mismatches == 20 and ff.diagnostics()['ff_active'] == 0.0


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-1e-5, 5e-5), min_size=5, max_size=60))
def test_commands_never_leave_the_amplifier_range(positions: list[float]) -> None:
    ctrl = build_controller(_controller('inverse_learning'), T, linear_plant(LOOP.design_plant))
    sine = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine', 'sine.frequency_hz': 200}))
    assert isinstance(ctrl, FeedForwardController)
    ctrl.bind(sine)
    ctrl.reset(positions[0], 3.8e-6)
    xd, vd = sine.evaluate(np.arange(len(positions)) * T)
    for y, r, v in zip(positions, xd, vd):
        u = ctrl.step(y, float(r), float(v))
        assert -2.0 <= u <= 10.0


def test_learned_table_round_trip(tmp_path: object) -> None:
    ctrl = build_controller(_controller('learning'), T, linear_plant(LOOP.design_plant))
    assert isinstance(ctrl, FeedForwardController)
    ctrl.bind(make_trajectory(TrajectoryParams.from_flat({'kind': 'sine'})))
    table = np.linspace(-1.0, 1.0, 100)  # default sine: 100 Hz, 100 samples a period
    ctrl.load_table(table)
    assert np.array_equal(ctrl.learned_table(), table)
    with pytest.raises(ParameterError, match='learned table'):
        ctrl.load_table(table[:-1])


def test_learning_update_is_the_circular_convolution_of_the_stepped_errors() -> None:
    # The update is summed in runs of LEARN_CHUNK samples; a stall (samples the caller
    # skipped) across a run's end and the period's end must add nothing for those samples and
    # lose none of the others: the period whose end was skipped is applied with the next one.
    params = _controller('learning', **{'notch.mode': 'off',
                                        'feedforward.learning_limit_v': 100.0})
    ctrl = build_controller(params, T, linear_plant(LOOP.design_plant),
                            make_hysteresis(HysteresisParams(model='none')))
    assert isinstance(ctrl, FeedForwardController)
    sine = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine', 'sine.frequency_hz': 100}))
    ctrl.bind(sine)
    ctrl.reset(3.8e-6, 3.8e-6)
    n = 100
    first_skipped, skipped = 2 * n - 3, 5  # samples 97 .. 99 of one period, 0 .. 1 of the next
    errors = 1e-8 * np.random.default_rng(3).standard_normal(3 * n)
    xd, vd = sine.evaluate(np.arange(3 * n) * T)
    k = 0
    while k < 3 * n:
        if k == first_skipped:
            ctrl.skip(skipped)
            k += skipped
            continue
        ctrl.step(float(xd[k] + errors[k]), float(xd[k]), float(vd[k]))
        k += 1
    # the first period is not learned (start periods 1); the second's end was skipped
    assert ctrl.periods_learned == 1
    # the errors as the controller forms them: position minus its own table of the reference
    measured = xd + errors
    learned = measured - np.tile(ctrl._lx_raw, 3)
    learned[first_skipped:first_skipped + skipped] = 0.0
    learned = learned[n:2 * n] + learned[2 * n:]
    h = ctrl._kernel2[:n]  # the filter's impulse response, designed at bind
    circulant = h[(np.arange(n)[:, None] - np.arange(n)[None, :]) % n]
    expected = -(circulant @ learned)
    # sums of 2 n products, in another order: 2 n rounding steps of the largest partial sum
    bound = 4 * n * EPS * float(np.max(np.abs(circulant) @ np.abs(learned)))
    assert np.max(np.abs(ctrl.learned_table() - expected)) <= bound
    assert np.max(np.abs(expected)) > 1e3 * bound  # the comparison is not of zeros


# -- the closed loop: the issue's targets on the default stage --------------------------------


def test_inverse_tracks_100_hz_at_the_converter_floor_from_the_second_period() -> None:
    rec = _run('inverse', {'kind': 'sine', 'sine.frequency_hz': 100.0}, 0.1)
    e = rec.position_m - rec.reference_m
    # the first 10 ms include the start from rest
    # with the sine's full velocity (an infeasible first sample); the rest sits at the
    # converters' floor (ADC step 1.16 nm, about 0.33 nm rms)
    assert _rms(e[100:]) <= 1.0e-9
    assert _rms(e[:100]) <= 20e-9


@pytest.mark.parametrize('mode,frequency,limit', [('learning', 200.0, 2e-9),
                                                  ('inverse_learning', 100.0, 1e-9)])
def test_learning_converges_to_the_issue_targets(mode: str, frequency: float,
                                                 limit: float) -> None:
    rec = _run(mode, {'kind': 'sine', 'sine.frequency_hz': frequency}, 0.5)
    e = rec.position_m - rec.reference_m
    n = int(round(1.0 / (frequency * T)))
    per_period = [_rms(e[i * n:(i + 1) * n]) for i in range(len(e) // n)]
    assert max(per_period[-10:]) <= limit
    assert rec.diagnostics['ff_periods_learned'][-1] >= len(per_period) - 3


def test_raster_line_with_learning_holds_the_estimates_and_meets_the_target() -> None:
    # 50 Hz triangle, 7.6 um p-p: the corners' error is above the RAC's adaptation dead zone;
    # adapting while learning drove phi_hat to its bound and the learning diverged (4 -> 22 nm
    # a period), so the estimates are held once the table learns
    rec = _run('inverse_learning', {'kind': 'triangle', 'triangle.frequency_hz': 50.0}, 1.0)
    phi = rec.diagnostics['phi_hat']
    theta = rec.diagnostics['theta_hat']
    n = 200  # samples a period
    assert np.all(phi[2 * n:] == phi[2 * n]) and np.all(theta[2 * n:] == theta[2 * n])
    e = rec.position_m - rec.reference_m
    per_period = [_rms(e[i * n:(i + 1) * n]) for i in range(len(e) // n)]
    # converged, not drifting: at the converters' floor each period's rms scatters by some
    # 10 % (the ADC's and DAC's rounding), so the drift is judged on means of ten periods
    assert np.mean(per_period[-10:]) <= 1.1 * np.mean(per_period[2:12])
    # a scan uses the middle 80 % of each line (away from the turnarounds at P/4 + j P/2)
    period = 1.0 / 50.0
    phase = ((rec.time_s - period / 4) % (period / 2)) / (period / 2)
    middle = (phase > 0.1) & (phase < 0.9) & (rec.time_s >= 0.5)
    assert _rms(e[middle]) <= 2e-9


def test_learning_alone_removes_most_of_the_feedback_error() -> None:
    base = _run('none', {'kind': 'multisine'}, 1.0)
    rec = _run('learning', {'kind': 'multisine'}, 1.0)
    last = slice(-1000, None)  # the last 10 + 100 Hz period
    assert _rms((rec.position_m - rec.reference_m)[last]) <= 1.5e-9
    assert _rms((base.position_m - base.reference_m)[last]) >= 5e-9


def test_ideal_jumps_are_followed_without_overshoot() -> None:
    square = TrajectoryParams.from_flat({'kind': 'square'})
    rec = experiments.run_one(LOOP.stage, _controller('inverse'), square, duration_s=1.0,
                              design_plant=LOOP.design_plant)
    m = experiments.square_edge_metrics(rec.time_s, rec.position_m, rec.reference_m,
                                        square.square)
    assert m.overshoot_pct <= 2.0
    assert m.settling_time_s <= 2e-3


def test_the_same_run_twice_is_identical() -> None:
    stage = StageParams()
    tp = TrajectoryParams.from_flat({'kind': 'sine', 'sine.frequency_hz': 100.0})
    runs = []
    for _ in range(2):
        ctrl = build_controller(_controller('inverse_learning'), T, linear_plant(stage.plant))
        runs.append(closed_loop.run(Stage(stage), ctrl, make_trajectory(tp), duration_s=0.05))
    assert np.array_equal(runs[0].command_v, runs[1].command_v)


# -- the learned table in a file --------------------------------------------------------------


def _bound(mode: str, trajectory: dict[str, object], **flat: object) -> FeedForwardController:
    ctrl = build_controller(_controller(mode, **flat), T, linear_plant(LOOP.design_plant),
                            make_hysteresis(LOOP.stage.hysteresis))
    assert isinstance(ctrl, FeedForwardController)
    ctrl.bind(make_trajectory(TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(),
                                                          **trajectory})))
    return ctrl


def _per_period(rec: experiments.RunRecord, n: int) -> list[float]:
    e = rec.position_m - rec.reference_m
    return [_rms(e[i * n:(i + 1) * n]) for i in range(len(e) // n)]


@pytest.mark.parametrize('mode', ['learning', 'inverse_learning'])
def test_a_saved_table_starts_a_run_at_the_learned_error(tmp_path, mode: str) -> None:
    sine = {'kind': 'sine', 'sine.frequency_hz': 100.0}
    tp = TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(), **sine})
    kept: list[FeedForwardController] = []
    learned = experiments.run_one(LOOP.stage, _controller(mode), tp, duration_s=0.3,
                                  design_plant=LOOP.design_plant, built=kept.append)
    path = kept[0].save_table_file(tmp_path / 'table.npz')
    loaded = experiments.run_one(LOOP.stage, _controller(mode, **{
        'feedforward.table_file': str(path)}), tp, duration_s=0.1,
        design_plant=LOOP.design_plant)
    before = _per_period(learned, 100)
    after = _per_period(loaded, 100)
    floor = max(before[-10:])  # the learned level: the converters' floor, ~0.4 nm
    # from the second period on (the first holds the start from rest with the sine's full
    # velocity) at the learned level, where a fresh table needs several periods
    assert max(after[1:]) <= 1.25 * floor
    # the first period is the start from rest, which no table removes; the loaded table adds
    # at most its own correction, of the size of the learned level, to it
    assert after[0] <= before[0] + floor
    if mode == 'learning':  # the inverse alone is at the floor from the second period
        assert before[1] >= 10.0 * floor
    saved = read_learned_table(path)
    assert saved.periods_learned == len(before) - 1
    assert saved.period_rms_m == kept[0].last_period_rms_m


def test_the_table_file_format_is_plain_numpy(tmp_path) -> None:
    ctrl = _bound('learning', {'kind': 'sine'})
    ctrl.load_table(np.linspace(-1.0, 1.0, 100))
    path = ctrl.save_table_file(tmp_path / 'table')  # the name is kept as given
    assert path == tmp_path / 'table' and path.exists()
    with np.load(path, allow_pickle=False) as data:
        assert str(data['format']) == TABLE_FORMAT and int(data['version']) == TABLE_VERSION
        # saved before any step: the estimates are their initial values, nothing folded in
        assert np.array_equal(data['table_v'], np.linspace(-1.0, 1.0, 100))
        assert float(data['period_s']) == pytest.approx(0.01, rel=EPS)
        assert str(data['design_hash']) == ctrl.learned().design_hash
    again = LearnedTable.from_fields(ctrl.learned().fields(), 'json')
    assert np.array_equal(again.table_v, ctrl.learned_table())
    assert again.design == ctrl.design


def test_a_table_file_of_another_version_or_kind_is_refused(tmp_path) -> None:
    ctrl = _bound('learning', {'kind': 'sine'})
    fields = ctrl.learned().fields()
    np.savez(tmp_path / 'v2.npz', **{**fields, 'version': 2})
    np.savez(tmp_path / 'other.npz', table_v=np.zeros(100))
    (tmp_path / 'text.npz').write_text('not a table')
    with pytest.raises(PiezoStageError, match='version 2; this program reads version 1'):
        read_learned_table(tmp_path / 'v2.npz')
    with pytest.raises(PiezoStageError, match='not a learned table'):
        read_learned_table(tmp_path / 'other.npz')
    with pytest.raises(ParameterError, match="'feedforward.table_file'.*cannot be loaded"):
        ctrl.load_table_file(tmp_path / 'text.npz')


@pytest.mark.parametrize('change,message', [
    ({'sine.frequency_hz': 50.0}, r'holds 100 samples of T = 0.0001 s \(period 0.01 s\); '
     r'allowed: a table of 200 samples'),
    # the sines cross at the offset (samples 0 and 50); the peaks differ most
    ({'sine.amplitude_m': 3.0e-6}, 'learned on another reference: 98 of 100 samples differ, '
     'most at sample 25: 7.6e-06 m, expected 6.8e-06 m'),
    ({'rac.k_d': 2.0}, 'was learned on design [0-9a-f]{16}: k_p='),
    ({'feedforward.mode': 'inverse_learning'}, 'mode=learning \\(expected mode=inverse_'),
])
def test_a_table_file_of_another_trajectory_or_design_is_refused(
        tmp_path, change: dict[str, object], message: str) -> None:
    path = _bound('learning', {'kind': 'sine'}).save_table_file(tmp_path / 'table.npz')
    traj = {k: v for k, v in change.items() if k.startswith('sine.')}
    flat = {k: v for k, v in change.items() if not k.startswith('sine.')}
    mode = str(flat.pop('feedforward.mode', 'learning'))
    with pytest.raises(ParameterError, match=message):
        _bound(mode, {'kind': 'sine', **traj}, **flat, **{'feedforward.table_file': str(path)})


def test_a_table_file_needs_a_learning_mode(tmp_path) -> None:
    path = _bound('learning', {'kind': 'sine'}).save_table_file(tmp_path / 'table.npz')
    with pytest.raises(ParameterError, match="mode 'inverse' learns none"):
        _bound('inverse', {'kind': 'sine'}, **{'feedforward.table_file': str(path)})
    with pytest.raises(PiezoStageError, match='no learned table'):
        _bound('inverse', {'kind': 'sine'}).learned()


# -- the learning's convergence in the stability check --------------------------------------


@pytest.mark.parametrize('gain', [0.1, 0.5, 1.0])
@pytest.mark.parametrize('kind', ['rac', 'pi'])
def test_on_the_design_model_the_ratio_is_one_minus_gamma(gain: float, kind: str) -> None:
    params = _controller('inverse_learning', type=kind, **{'feedforward.learning_gain': gain})
    check = learning_check(params, LOOP.design_plant, T, 0.01, stage=LOOP.stage,
                           options=NO_DELAY)
    assert check is not None
    # P_true / P_s = 1 up to the rounding of one complex division
    assert check.design_ratio == pytest.approx(abs(1.0 - gain), abs=4 * EPS)
    # 100 Hz harmonics up to Q's edge
    assert check.harmonics == int(params.feedforward.learning_bandwidth_hz // 100.0)
    assert check.slopes == ()  # the inverse removes the hysteresis


@pytest.mark.parametrize('gain', [0.3, 0.5])
def test_without_feedback_the_ratio_is_one_minus_gamma_times_the_gain_change(
        gain: float) -> None:
    # no feedback: P = c G, so a member that scales K by a (and a hysteresis slope s instead
    # of c) has P_true / P_s = a s / c exactly, on every harmonic
    params = _controller('learning', type='open_loop', **{'feedforward.learning_gain': gain})
    check = learning_check(params, LOOP.design_plant, T, 0.01, stage=LOOP.stage,
                           options=NO_DELAY)
    assert check is not None
    c = make_hysteresis(LOOP.stage.hysteresis).slope  # the design hysteresis' c
    members = dict(check.members)
    slopes = LOOP.stability.slopes()
    z = np.exp(2j * np.pi * np.arange(1, 16) / 100)  # the learned harmonics
    nominal = _response(LOOP.stage, z)
    for name, factor in (('gain_lo', 0.7), ('gain_hi', 1.4)):
        expected = max(abs(1.0 - gain * factor * s / c) for s in slopes)
        # the ZOH numerator of G(z) (state space to transfer function) is not exactly linear
        # in K: the member's G(z) / (a G(z)) - 1, a few 1e-9 here, bounds the ratio's error
        member = _response(member_params(LOOP.stage, StageVariation(name, gain=factor)), z)
        spread = float(np.max(np.abs(member / (factor * nominal) - 1.0)))
        assert abs(members[name] - expected) <= gain * factor * spread + 4 * EPS
    assert [r for _, r in check.slopes] == pytest.approx(
        [abs(1.0 - gain * s / c) for s in slopes], rel=1e-12)


def _response(stage: StageParams, z: np.ndarray) -> np.ndarray:
    num, den = stability_plant(stage.plant).discretize(T).transfer_function()
    return np.asarray(np.polyval(num, z) / np.polyval(den, z))


def test_the_report_names_the_worst_member_and_keeps_its_verdict_apart() -> None:
    params = _controller('inverse_learning')
    report = check_stability(params, LOOP.design_plant, T, options=LOOP.stability,
                             period_s=0.01, stage=LOOP.stage)
    check = report.learning
    assert check is not None and check.design_ok
    name, worst = check.worst_member or ('', 0.0)
    assert worst == max(r for _, r in check.members)
    assert f'worst {worst:.3f} ({name})' in report.text()
    # the learning's verdict does not enter the loops' one
    assert report.stable
    assert check_stability(_controller('none'), LOOP.design_plant, T, period_s=0.01,
                           stage=LOOP.stage).learning is None


def test_no_check_without_a_period_of_four_samples() -> None:
    params = _controller('learning')
    assert learning_check(params, LOOP.design_plant, T, 0.0, stage=LOOP.stage) is None
    assert learning_check(params, LOOP.design_plant, T, 3.9 * T, stage=LOOP.stage) is None
    # a period that is not a whole number of samples is checked (test_feedforward_anyperiod)
    check = learning_check(params, LOOP.design_plant, T, 0.01005, stage=LOOP.stage)
    assert check is not None and check.period_s == 0.01005
    with_own = _controller('learning', **{'feedforward.period_s': 0.02})
    check = learning_check(with_own, LOOP.design_plant, T, 0.0)
    assert check is not None and check.period_s == pytest.approx(0.02, rel=EPS)
    assert check.members == () and 'family is not checked' in check.text()


@pytest.mark.parametrize('every', [1, 7])
def test_the_recorded_feedforward_is_the_one_added_to_the_command(every: int) -> None:
    # learning alone, no notch, inside the range: v = C(...) + L[i], and the RAC keeps C(...)
    ctrl = _bound('learning', {'kind': 'sine'})
    stage = Stage(LOOP.stage)
    traj = make_trajectory(TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(),
                                                       'kind': 'sine'}))
    y = stage.reset(None)
    x, v = traj.evaluate(np.arange(600) * T)
    ctrl.reset(y, float(x[0]))
    checked = 0
    for k in range(600):
        u = ctrl.step(y, float(x[k]), float(v[k]))
        if k % every == 0 or k % 100 == 99:
            feedback = ctrl.inner.output_v  # the RAC's own command
            assert abs(ctrl.feedforward_v() - (u - feedback)) <= 4 * EPS * abs(u)
            checked += k % 100 == 99 and k >= 199  # a period's last sample, after an update
        y = stage.step(u)
    assert ctrl.periods_learned == 5 and checked == 5


@pytest.mark.parametrize('gap', [1, 2, 5])
def test_missed_samples_bridge_the_shares_notch_as_the_inner_notch(gap: int) -> None:
    # Perfect tracking of a triangle's rising side (10 Hz, 3.8 um: 0.15 mm/s): the RAC's
    # model part and the share the model inverse takes off it are linear in the sample, so
    # the equal steps over a gap are what the notches would have been fed. The command after
    # the gap is then the on-time one to the rounding of the notches' recursion (values of a
    # few volts: 1e-12 V is a thousand times that rounding). With the share's notch fed a jump
    # where the inner notch is fed a ramp, their difference rang into the command: millivolts,
    # a kick of several nanometres after one missed sample of a moving stage.
    params = _controller('inverse')
    assert params.notch.mode != 'off'
    line = make_trajectory(TrajectoryParams.from_flat({'kind': 'triangle'}))
    t = np.arange(600) * T
    x, v = line.evaluate(t)

    def make() -> FeedForwardController:
        ff = build_controller(params, T, linear_plant(LOOP.design_plant),
                              make_hysteresis(HysteresisParams(model='none')))
        assert isinstance(ff, FeedForwardController)
        ff.bind(line)
        ff.reset(float(x[0]), float(x[0]))
        return ff
    on_time, stalled = make(), make()
    at = 300  # on the rising side, past the start hold
    ahead = [on_time.step(float(x[k]), float(x[k]), float(v[k])) for k in range(at + 20)]
    for k in range(at):
        assert stalled.step(float(x[k]), float(x[k]), float(v[k])) == ahead[k]
    stalled.skip(gap)
    stalled.missed(gap)
    after = [stalled.step(float(x[k]), float(x[k]), float(v[k]))
             for k in range(at + gap, at + 20)]
    assert stalled.mismatches == on_time.mismatches == 0
    np.testing.assert_allclose(after, ahead[at + gap:], rtol=0.0, atol=1e-12)
