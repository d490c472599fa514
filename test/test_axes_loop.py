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

"""The multi-axis closed loop: one axis as today, coupling compensation, per-axis metrics."""

import numpy as np
from piezo_stage_ros.core.config.loader import load_loop_config
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.control.axes import AxesController, coupled_displacement
from piezo_stage_ros.core.control.controllers import build_controller
from piezo_stage_ros.core.loop import closed_loop
from piezo_stage_ros.core.loop.axes import axis_metrics, middle_of_lines, run_axes
from piezo_stage_ros.core.loop.scan2d import lissajous, raster
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.axes import AxesStage, AxesStageParams, CouplingParams
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant, Stage
import pytest

LOOP = load_loop_config(['config/default.yaml'])
XY_COUPLING = CouplingParams(gain=(0.0, 0.02, 0.0, 0.0), resonance_hz=(0.0, 1800.0, 0.0, 0.0))


def sine(offset=6e-6, amplitude=3e-6, hz=100.0):
    return make_trajectory(TrajectoryParams.from_flat({
        'kind': 'sine', 'sine.offset_m': offset, 'sine.amplitude_m': amplitude,
        'sine.frequency_hz': hz}))


def one_axis(stage_params, controller_params, trajectory, duration_s):
    ctrl = build_controller(controller_params, stage_params.sample_time_s,
                            linear_plant(stage_params.plant),
                            make_hysteresis(stage_params.hysteresis))
    return closed_loop.run(Stage(stage_params), ctrl, trajectory, duration_s=duration_s)


SAMPLES = ('position_m', 'reference_m', 'reference_velocity_mps', 'command_v',
           'true_position_m')


@pytest.mark.parametrize('flat', [
    {'feedforward.mode': 'inverse_learning'},
    {'type': 'pi', 'notch.mode': 'off'},
    {'feedforward.mode': 'inverse'},
])
def test_one_axis_loop_is_the_one_axis_closed_loop_bit_for_bit(flat):
    sp = LOOP.stage.with_flat({'chain.sensor_noise_std_m': 1e-9, 'seed': 4})
    cp = LOOP.controller.with_flat(flat)
    tr = sine()
    want = one_axis(sp, cp, tr, 0.05)
    params = AxesStageParams(names=('x',), axes=(sp,))
    got = run_axes(AxesStage(params), AxesController.build([cp], params), [tr],
                   duration_s=0.05)[0]
    for name in SAMPLES:
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    assert np.array_equal(got.time_s, want.time_s)


def test_two_uncoupled_axes_are_two_one_axis_loops_bit_for_bit():
    sx = LOOP.stage.with_flat({'chain.sensor_noise_std_m': 1e-9, 'seed': 1})
    sy = LOOP.stage.with_flat({'plant.model': 'reduced', 'seed': 2})
    cx = LOOP.controller.with_flat({'feedforward.mode': 'inverse'})
    cy = LOOP.controller.with_flat({'type': 'pi'})
    tx, ty = lissajous(frequencies_hz=[97.0, 103.0], amplitudes_m=[3e-6, 3e-6],
                       offsets_m=[6e-6, 7e-6])
    params = AxesStageParams(names=('x', 'y'), axes=(sx, sy))
    got = run_axes(AxesStage(params), AxesController.build([cx, cy], params), [tx, ty],
                   duration_s=0.04)
    for rec, (sp, cp, tr) in zip(got, ((sx, cx, tx), (sy, cy, ty))):
        want = one_axis(sp, cp, tr, 0.04)
        for name in SAMPLES:
            assert np.array_equal(getattr(rec, name), getattr(want, name)), name


def linear_xy(coupling=XY_COUPLING):
    """The design model itself: no hysteresis, no converters, no noise."""
    sp = LOOP.stage.with_flat({'hysteresis.model': 'none', 'chain.quantize': False})
    return AxesStageParams(names=('x', 'y'), axes=(sp, sp), coupling=coupling)


def test_predicted_coupled_displacement_is_the_stage_steady_state():
    # drive x with the exact periodic model inverse of a sine: its position is the sine, and
    # y's coupled displacement, once the start has decayed (mode: 1/(zeta w) = 1.8 ms, 0.1 s
    # waited), is the harmonic prediction up to rounding
    params = linear_xy()
    stage = AxesStage(params)
    ctrl = build_controller(LOOP.controller.with_flat({'feedforward.mode': 'inverse'}),
                            1e-4, linear_plant(params.axes[0].plant), make_hysteresis(
                                params.axes[0].hysteresis))
    n = 100
    x_d = sine(6e-6, 3e-6, 100.0).evaluate(np.arange(n) * 1e-4)[0]
    w = ctrl.plant_inverse.periodic(x_d)
    rest_y = params.axes[1].initial_position_m / stage._axes[1].stage._core.dc_gain_m_per_v
    alone = Stage(params.axes[1])
    # after step k the stage is at sample k + 1: x_d[(k + 1) mod n]
    got = []
    stage.reset([x_d[0], None])
    alone.reset()
    for k in range(1100 + n):
        stage.step([float(w[k % n]), rest_y])
        alone.step(rest_y)
        if 1100 - 1 <= k < 1100 + n - 1:
            got.append(stage.read_positions_m()[1] - alone.position_m)
    d = coupled_displacement(stage.paths, 1, {0: x_d})
    got_a = np.asarray(got)
    want = np.roll(d, -1100)[:n]
    assert np.max(np.abs(got_a - want)) <= 1e-9 * np.max(np.abs(d))


def test_compensation_removes_the_coupling_on_the_design_model():
    params = linear_xy()
    cp = LOOP.controller.with_flat({'feedforward.mode': 'inverse'})
    tx, ty = lissajous(frequencies_hz=[100.0, 50.0], amplitudes_m=[3e-6, 1e-6],
                       offsets_m=[6e-6, 6e-6])
    errors = {}
    for on in (False, True):
        ctrl = AxesController.build([cp, cp], params, compensate=on)
        recs = run_axes(AxesStage(params), ctrl, [tx, ty], duration_s=0.2)
        errors[on] = axis_metrics(recs[1], last_s=0.1).e_rms_true_m
        assert ctrl.compensated == ((1,) if on else ())
    # without: the 2 % of x's 3 um through the mode, less what y's feedback removes; with:
    # the model inverse is exact on the design model, what is left is y's feedback reacting
    # to the residual of the truncated preview
    assert errors[False] > 1e-9
    assert errors[True] < 0.05 * errors[False]


def test_compensation_needs_the_driving_axis_to_repeat_within_the_period():
    params = linear_xy()
    cp = LOOP.controller.with_flat({'feedforward.mode': 'inverse'})
    # y has a 10 ms period, x a 13 ms one: x does not repeat within y's period
    tx, ty = sine(6e-6, 3e-6, 1000.0 / 13.0), sine(6e-6, 1e-6, 100.0)
    ctrl = AxesController.build([cp, cp], params)
    with pytest.raises(ParameterError,
                       match=r"cannot carry the coupling compensation.*axis 'x' does not"):
        ctrl.bind([tx, ty])


def raster_run(lines, duration_s, controller):
    """A 100 Hz triangle raster of ``lines`` 1 um lines on the coupled XY stage."""
    params = AxesStageParams(names=('x', 'y'), axes=(LOOP.stage, LOOP.stage),
                             coupling=XY_COUPLING)
    line = make_trajectory(TrajectoryParams.from_flat({
        'kind': 'triangle', 'triangle.offset_m': 10e-6, 'triangle.amplitude_m': 5e-6,
        'triangle.frequency_hz': 100.0}))
    fast, slow = raster(line, lines=lines, pitch_m=1e-6, start_m=6e-6)
    return run_axes(AxesStage(params), AxesController.build([controller] * 2, params),
                    [fast, slow], duration_s=duration_s)


def test_raster_on_the_coupled_stage_tracks_both_axes():
    recs = raster_run(8, 0.2, LOOP.controller.with_flat({'feedforward.mode': 'inverse'}))
    assert [r.meta['axis'] for r in recs] == ['x', 'y']
    assert recs[1].meta['trajectory_period_s'] == pytest.approx(0.16)
    mask = middle_of_lines(recs[0].reference_m)
    assert 0.75 < mask.mean() < 0.85   # a triangle spends equal time at every level
    mx = axis_metrics(recs[0], last_s=0.1, mask=mask)
    my = axis_metrics(recs[1], last_s=0.1)
    # tracked: well inside the scan's 10 um and the 1 um line pitch
    assert mx.e_rms_m < 0.1e-6 and my.e_rms_m < 0.02e-6
    assert mx.samples == int(mask[-1000:].sum())


def test_a_trajectory_count_that_is_not_one_per_axis_is_refused():
    params = AxesStageParams(names=('x', 'y'), axes=(LOOP.stage, LOOP.stage))
    with pytest.raises(ParameterError, match=r"'trajectories' = 1.*one per axis \['x', 'y'\]"):
        run_axes(AxesStage(params), AxesController.build([LOOP.controller] * 2, params),
                 [sine()], duration_s=0.01)


def test_axis_metrics_take_the_last_window_and_the_mask():
    from piezo_stage_ros.core.loop.record import RunRecord
    n = 1000
    t = np.arange(n) * 1e-4
    ref = np.zeros(n)
    pos = np.where(np.arange(n) < 500, 1e-6, 2e-9)  # large error first, then 2 nm
    pos[-1] = -4e-9
    rec = RunRecord(t, pos, ref, np.zeros(n), np.zeros(n), {}, {'axis': 'y',
                                                                'sample_time_s': 1e-4},
                    pos.copy())
    m = axis_metrics(rec, last_s=0.05)            # the last 500 samples
    assert m.axis == 'y' and m.samples == 500
    assert m.e_max_m == 4e-9
    assert m.e_rms_m == pytest.approx(np.sqrt((499 * 4e-18 + 16e-18) / 500), rel=1e-12)
    mask = np.ones(n, dtype=bool)
    mask[-1] = False
    assert axis_metrics(rec, last_s=0.05, mask=mask).e_max_true_m == 2e-9
    with pytest.raises(ParameterError, match='fraction'):
        middle_of_lines(ref, 0.0)


def check_for(gain, mode='inverse_learning'):
    from piezo_stage_ros.core.control.axes import coupled_loop_check
    coupling = CouplingParams(gain=gain, resonance_hz=(0.0, 1800.0, 1800.0, 0.0))
    params = AxesStageParams(names=('x', 'y'), axes=(LOOP.stage, LOOP.stage), coupling=coupling)
    cp = LOOP.controller.with_flat({'feedforward.mode': mode})
    return coupled_loop_check(AxesController.build([cp, cp], params), points=800)


def test_one_way_coupling_leaves_the_loops_and_the_learning_as_they_are():
    # P is triangular: M is nilpotent (radius 0) and the learning's iteration triangular with
    # the one-axis ratio 1 - gamma on its diagonal
    r = check_for((0.0, 0.02, 0.0, 0.0))
    assert r.coupling_gain <= 1e-12 and r.certified
    assert r.learning_ratio == pytest.approx(0.5, abs=1e-9)
    assert check_for((0.0, 0.02, 0.0, 0.0), mode='inverse').learning_ratio is None


def test_two_way_coupling_gain_grows_with_the_coupling_and_is_refused_when_too_large():
    # M is linear in the coupling paths: doubling both gains doubles its spectral radius
    small = check_for((0.0, 0.02, 0.01, 0.0))
    large = check_for((0.0, 0.04, 0.02, 0.0))
    assert 0.0 < small.coupling_gain < 1.0
    assert large.coupling_gain == pytest.approx(2.0 * small.coupling_gain, rel=1e-9)
    assert large.coupling_frequency_hz == small.coupling_frequency_hz
    too_much = check_for((0.0, 0.5, 0.5, 0.0))
    assert not too_much.certified and 'not certified' in too_much.text()


def test_the_coupled_learning_check_covers_the_harmonics_q_keeps_above_its_edge():
    # Q keeps a fast line's first harmonics up to BANDWIDTH_STRETCH times its edge (a 300 Hz
    # line's 5th at 1.5 kHz): the check covers every frequency a kept harmonic can lie at.
    # With two-way coupling the ratio grows towards the top of what is learned, so its worst
    # lies above the edge and within the stretch
    from piezo_stage_ros.core.control.feedforward import BANDWIDTH_STRETCH, kept_harmonics
    edge_hz = LOOP.controller.feedforward.learning_bandwidth_hz
    t = LOOP.stage.sample_time_s
    samples = 1.0 / (300.0 * t)
    kept = kept_harmonics(np.ones(int(samples // 2) + 1, dtype=complex), samples, t, edge_hz)
    assert np.flatnonzero(kept)[-1] / (samples * t) > edge_hz
    r = check_for((0.0, 0.02, 0.01, 0.0))
    assert r.learning_frequency_hz is not None
    assert edge_hz < r.learning_frequency_hz <= BANDWIDTH_STRETCH * edge_hz
    assert r.learning_ratio is not None and r.learning_ratio < 1.0


def test_frame_images_put_each_line_in_a_row_low_end_first():
    from piezo_stage_ros.core.loop.axes import frame_images
    recs = raster_run(4, 0.1, LOOP.controller)   # two frames and a half
    x_img, y_img = frame_images(recs[0], recs[1], lines=4, frame=1)
    assert x_img.shape == y_img.shape == (4, 100)
    # frame 1 runs down: its first line (samples 400-499) is the top row, shown last
    assert np.array_equal(x_img[3], recs[0].error_m[400:500])
    assert np.array_equal(y_img[0], recs[1].error_m[700:800])
    up, _ = frame_images(recs[0], recs[1], lines=4, frame=0)
    assert np.array_equal(up[0], recs[0].error_m[:100])
    assert np.array_equal(frame_images(recs[0], recs[1], lines=4)[0], x_img)  # the last whole
    with pytest.raises(ParameterError, match=r"'frame' = 2"):
        frame_images(recs[0], recs[1], lines=4, frame=2)
    with pytest.raises(ParameterError, match='trajectory_period_s'):
        frame_images(recs[1].__class__(recs[1].time_s, recs[1].position_m, recs[1].reference_m,
                                       recs[1].reference_velocity_mps, recs[1].command_v, {},
                                       {'sample_time_s': 1e-4}), recs[1], lines=4)
