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

"""Identification of a multi-axis stage: the coupling paths, each axis, the parameter file."""

import dataclasses

import numpy as np
from piezo_stage_ros import cli, identify_axes
from piezo_stage_ros.core.config.axes import axes_loop_config
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.identification.coupling import (
    CouplingPlan,
    excitation_runs,
    fit_coupling,
)
from piezo_stage_ros.core.identification.experiments import run_experiments
from piezo_stage_ros.core.identification.per_axis import identify_axis
from piezo_stage_ros.core.identification.support import identify_checked
import pytest

XY = 'config/xy_stage.yaml'
#: A short plan: 3 averaged periods of 0.1 s.
SHORT = CouplingPlan(period_s=0.1, periods=4)


def xy_stage(noise_m=None, quantize=None, seed=None):
    stage = axes_loop_config(cli.read_config([XY])).stage
    axes = []
    for k, p in enumerate(stage.axes):
        chain = p.chain
        if noise_m is not None:
            chain = chain.replace(sensor_noise_std_m=noise_m)
        if quantize is not None:
            chain = chain.replace(quantize=quantize)
        axes.append(p.replace(chain=chain, seed=p.seed if seed is None else seed + k))
    return dataclasses.replace(stage, axes=tuple(axes))


def test_noiseless_fit_recovers_gain_resonance_and_damping_to_rounding():
    stage = xy_stage(noise_m=0.0, quantize=False)
    run = excitation_runs(stage, SHORT)[0]
    (fit,) = fit_coupling(run.time_s, run.commands_v, run.positions_m, stage)
    # Without noise the ratio of the lines is exact up to the rounding of the positions (a
    # relative 1e-16 of the source's 10 um against a displacement 50 times smaller, so about
    # 1e-14 per line); the solver stops at a step of 1e-12 in log f and log zeta, which the
    # fit's correlations (condition below 1e3) turn into at most about 1e-9 in any parameter.
    assert not fit.static
    assert fit.gain == pytest.approx(0.02, rel=1e-9)
    assert fit.resonance_hz == pytest.approx(1800.0, rel=1e-9)
    assert fit.damping == pytest.approx(0.05, rel=1e-9)
    assert (fit.source, fit.target) == (0, 1)


def test_noisy_fits_hold_the_truth_in_their_95_percent_bounds():
    # 2 nm sensor noise and the 16-bit ADC; six runs of independent noise and phases. Each bound
    # covers with probability 0.95: 3 of 6 or fewer happens with probability 0.002.
    covered = {'gain': 0, 'resonance_hz': 0, 'damping': 0}
    truth = {'gain': 0.02, 'resonance_hz': 1800.0, 'damping': 0.05}
    runs = 6
    for seed in range(runs):
        stage = xy_stage(noise_m=2e-9, seed=10 * seed)
        plan = dataclasses.replace(SHORT, seed=seed + 1)
        run = excitation_runs(stage, plan)[0]
        (fit,) = fit_coupling(run.time_s, run.commands_v, run.positions_m, stage)
        assert abs(fit.gain / 0.02 - 1.0) < 0.05
        for key, value in truth.items():
            lo, hi = fit.bounds[key]
            covered[key] += int(lo <= value <= hi)
    assert all(c >= 4 for c in covered.values()), covered


def test_a_path_the_data_does_not_show_is_static_zero_within_a_sensor_step():
    stage = xy_stage()
    run = excitation_runs(stage, SHORT)[1]                # y excited: nothing reaches x
    (fit,) = fit_coupling(run.time_s, run.commands_v, run.positions_m, stage)
    assert (fit.source, fit.target, fit.gain, fit.static, fit.shown) == (1, 0, 0.0, True, False)
    lo, hi = fit.bounds['gain']
    assert lo < 0.0 < hi


def test_bad_input_is_refused_with_the_value_and_what_is_allowed():
    stage = xy_stage()
    run = excitation_runs(stage, SHORT)[0]
    t, u, y = run.time_s, run.commands_v, run.positions_m
    with pytest.raises(ParameterError, match=r'commands_v.*\(4000, 3\).*\(4000, 2\)'):
        fit_coupling(t, np.hstack([u, u[:, :1]]), y, stage)
    with pytest.raises(ParameterError, match=r'positions_m.*\(4000,\).*one column per axis'):
        fit_coupling(t, u, y[:, 0], stage)
    with pytest.raises(ParameterError, match=r'source.*1.*was not excited.*varying: \[0\]'):
        fit_coupling(t, u, y, stage, source=1)
    both = u.copy()
    both[:, 1] += 0.01 * np.sin(np.arange(t.size))
    with pytest.raises(ParameterError, match=r'axes \[0, 1\] vary.*exactly one excited axis'):
        fit_coupling(t, both, y, stage)
    with pytest.raises(ParameterError, match=r'time_s.*sample time 0.0002 s.*0.0001 s'):
        fit_coupling(2.0 * t, u, y, stage)
    with pytest.raises(ParameterError, match=r'rms_v.*amplifier range'):
        excitation_runs(stage, dataclasses.replace(SHORT, rms_v=5.0))


def test_an_axis_identifies_as_alone_and_the_coupled_one_within_its_bounds():
    stage = xy_stage()
    # x receives no coupling: its runs are the one-axis stage's, bit for bit
    alone = identify_checked(list(run_experiments(stage.axes[0]).values()), stage.axes[0])
    assert identify_axis(stage, 0, stage.axes[0]).result.summary() == alone.result.summary()
    # y receives 2 % of x held at 10 um: a constant, taken by the sensor offset, not the model
    coupled = identify_axis(stage, 1, stage.axes[1]).result
    own = identify_checked(list(run_experiments(stage.axes[1]).values()), stage.axes[1]).result
    for key in ('static_gain_m_per_v', 'omega_n_rad_s', 'zeta', 'tau_s'):
        lo, hi = coupled.bounds[key]
        assert lo <= own.summary()[key] <= hi, key
    lo, hi = coupled.bounds['sensor_offset_m']
    assert lo <= 0.02 * 10e-6 <= hi


def test_written_file_loads_on_top_and_reproduces_the_coupling(tmp_path, capsys):
    out = tmp_path / 'xy_identified.yaml'
    assert identify_axes.main(['--config', XY, '--coupling-only', '--periods', '4',
                               '--output', str(out), '--json']) == 0
    import json
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    (xy,) = [p for p in report['coupling'] if p['source'] == 'x']
    loaded = axes_loop_config(cli.read_config([XY, str(out)])).stage
    gain, res, damp, _ = loaded.matrices()
    assert gain[0, 1] == xy['gain'] and res[0, 1] == xy['resonance_hz']
    assert damp[0, 1] == xy['damping'] and gain[1, 0] == 0.0
    assert gain[0, 1] == pytest.approx(0.02, rel=0.05)
    from piezo_stage_ros import simulate
    assert simulate.main(['--config', XY, '--config', str(out), '--duration', '0.05']) == 0


def test_an_axis_without_coupling_into_it_commissions_as_the_one_axis_stage():
    from piezo_stage_ros.core.identification.commission import commission
    from piezo_stage_ros.core.identification.per_axis import commission_axis
    from piezo_stage_ros.identify import controller_values
    loop = axes_loop_config(cli.read_config([XY]))
    stage, ctrl = loop.stage, loop.controllers[0]
    ctrl = ctrl.replace(feedforward=ctrl.feedforward.replace(mode='none'))

    def derive(s):
        return controller_values(s, ctrl.to_flat(), stage.axes[0])

    alone = commission(stage.axes[0], stage.axes[0], ctrl, derive, stability=loop.base.stability)
    axis = commission_axis(stage, 0, stage.axes[0], ctrl, derive, stability=loop.base.stability)
    assert axis.accepted and alone.accepted
    assert axis.identified == alone.identified
    assert axis.verification.e_rms_m == alone.verification.e_rms_m


def test_the_coupling_fitted_from_its_bags_is_the_coupling_fitted_from_the_run(tmp_path):
    # The bags hold every sample bit for bit (y_0 at rest, u_k held over [t_k, t_k+1)), so
    # the arrays read back are the run's and the fit is the same to the last bit.
    from piezo_stage_ros.analysis.bagread import read_axes
    from piezo_stage_ros.analysis.bagwrite import write_axes
    stage = xy_stage()
    run = excitation_runs(stage, SHORT)[0]
    write_axes(identify_axes.run_records(run, stage), tmp_path / 'coupling_x')
    back = identify_axes.records_run(read_axes(tmp_path / 'coupling_x'), stage)
    assert np.array_equal(back.commands_v, run.commands_v)
    assert np.array_equal(back.positions_m, run.positions_m)
    assert np.array_equal(back.initial_m, run.initial_m)
    (direct,) = fit_coupling(run.time_s, run.commands_v, run.positions_m, stage)
    (bagged,) = fit_coupling(back.time_s, back.commands_v, back.positions_m, stage)
    assert bagged == direct
    assert bagged.gain == pytest.approx(0.02, rel=0.05)


def test_the_command_identifies_from_the_bags_it_recorded(tmp_path):
    bags = tmp_path / 'runs'
    first, second = tmp_path / 'a.yaml', tmp_path / 'b.yaml'
    common = ['--config', XY, '--coupling-only', '--periods', '4']
    assert identify_axes.main(common + ['--bags', str(bags), '--output', str(first)]) == 0
    assert identify_axes.main(['--config', XY, '--from-bags', str(bags / 'coupling_x'),
                               str(bags / 'coupling_y'), '--output', str(second)]) == 0
    body = [[line for line in path.read_text().splitlines() if not line.startswith('#')]
            for path in (first, second)]
    assert body[0] == body[1]


def test_bags_of_other_axes_are_refused_naming_them(tmp_path):
    stage = xy_stage()
    run = excitation_runs(stage, SHORT)[0]
    records = identify_axes.run_records(run, stage)
    records.reverse()
    with pytest.raises(ParameterError, match=r"\['y', 'x'\]"):
        identify_axes.records_run(records, stage)


def test_analyze_tells_what_an_open_loop_coupling_bag_holds(tmp_path, capsys):
    # No reference, so no error to measure: analyze prints the excitation and each axis'
    # response instead of NaN errors, from the same samples the fit reads.
    import json

    from piezo_stage_ros import analyze
    from piezo_stage_ros.analysis.bagwrite import write_axes
    stage = xy_stage()
    run = excitation_runs(stage, SHORT)[0]
    bag = tmp_path / 'coupling_x'
    write_axes(identify_axes.run_records(run, stage), bag,
               meta={'command': 'identify_axes', 'experiment': 'coupling, open loop'})
    assert analyze.main(['-q', str(bag)]) == 0
    out = capsys.readouterr().out
    assert 'nan' not in out.lower()
    assert 'no reference: open-loop run (coupling, open loop), no tracking error; x excited' \
        in out
    assert '  x (excited): command ' in out and '  y (held): command ' in out
    # its figures: each axis' command and position, no empty error plot
    assert analyze.main(['-q', '--plots', str(tmp_path / 'figs'), str(bag)]) == 0
    capsys.readouterr()
    assert sorted(p.name for p in (tmp_path / 'figs').iterdir()) == ['response_x.png',
                                                                      'response_y.png']
    assert analyze.main(['-q', '--json', '--window', '0.2', str(bag)]) == 0
    doc = json.loads(capsys.readouterr().out)
    ol = doc['open_loop']
    assert ol['excited'] == ['x'] and ol['experiment'] == 'coupling, open loop'
    # over the last 0.2 s of the records the bag holds
    records = identify_axes.run_records(run, stage)
    last = int(round(0.2 / stage.sample_time_s))
    u, moved = records[0].command_v[-last:], records[1].position_m[-last:]
    x, y = ol['axes']['x'], ol['axes']['y']
    assert x['command_rms_v'] == pytest.approx(np.std(u), rel=1e-9)
    assert y['command_rms_v'] == 0.0 and not y['excited']
    assert y['position_rms_m'] == pytest.approx(np.std(moved), rel=1e-9)
    assert y['position_peak_to_peak_m'] == pytest.approx(np.ptp(moved), rel=1e-9)
