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

"""The simulate command, in process: flags, JSON, configs, errors, stability, bags."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from piezo_stage_ros import cli, simulate
from piezo_stage_ros.core.control.controllers import ControllerParams
from piezo_stage_ros.core.loop import experiments as ex
from piezo_stage_ros.core.loop import metrics
from piezo_stage_ros.core.loop.trajectories import TrajectoryParams
from piezo_stage_ros.core.model.stage import StageParams
import pytest

REQUIRED = ('e_max_m', 'e_rms_m', 'command_min_v', 'command_max_v', 'samples', 'sim_seconds',
            'wall_seconds', 'stable')


def run_json(capsys: pytest.CaptureFixture[str], *argv: str) -> dict[str, Any]:
    assert simulate.main([*argv, '--json']) == 0
    out = capsys.readouterr().out
    assert len(out.strip().splitlines()) == 1
    return dict(json.loads(out))


def test_json_has_the_required_keys_and_matches_the_core(
        capsys: pytest.CaptureFixture[str]) -> None:
    d = run_json(capsys, '--plant', 'reduced', '--controller', 'pi', '--frequency', '50',
                 '--duration', '0.2')
    for key in REQUIRED:
        assert key in d
    assert d['samples'] == 2000 and d['sim_seconds'] == pytest.approx(0.2)
    assert d['stable'] is True
    assert (d['plant'], d['controller'], d['trajectory']) == ('reduced', 'pi', 'sine')
    # the same run through the core gives the same numbers
    sp = StageParams().with_flat({'plant.model': 'reduced'})
    tp = TrajectoryParams.from_flat({'sine.frequency_hz': 50.0})
    rec = ex.run_one(sp, ControllerParams(type='pi'), tp, duration_s=0.2)
    s = metrics.summarize(rec)
    assert d['e_rms_m'] == s.e_rms_m and d['e_max_m'] == s.e_max_m


def test_readable_summary(capsys: pytest.CaptureFixture[str]) -> None:
    assert simulate.main(['--plant', 'reduced', '--duration', '0.05']) == 0
    out = capsys.readouterr().out
    assert 'e_rms =' in out and 'stability check: stable' in out
    assert 'command range' in out


def test_config_files_then_params_then_flags(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / 'mine.yaml'
    cfg.write_text('plant_node:\n  ros__parameters:\n    plant:\n      model: reduced\n'
                   'controller_node:\n  ros__parameters:\n    type: pi\n')
    d = run_json(capsys, '--config', str(cfg), '--duration', '0.02')
    assert (d['plant'], d['controller']) == ('reduced', 'pi')
    d = run_json(capsys, '--config', str(cfg), '--param', 'controller_node:type=open_loop',
                 '--duration', '0.02')
    assert d['controller'] == 'open_loop'
    d = run_json(capsys, '--config', str(cfg), '--param', 'controller_node:type=open_loop',
                 '--controller', 'rac', '--duration', '0.02')
    assert d['controller'] == 'rac'


@pytest.mark.parametrize('name', ['table3_rac', 'table3_pi', 'table3_third_order', 'square',
                                  'staircase', 'multisine'])
def test_shipped_scenarios_load(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = Path(__file__).resolve().parents[1] / 'config' / f'{name}.yaml'
    d = run_json(capsys, '--config', str(cfg), '--duration', '0.01')
    assert d['samples'] == 100


def test_multisine_frequencies_and_amplitude(capsys: pytest.CaptureFixture[str]) -> None:
    d = run_json(capsys, '--trajectory', 'multisine', '--frequency', '10', '--frequency', '20',
                 '--frequency', '40', '--amplitude', '1e-6', '--duration', '0.02')
    assert d['trajectory_period_s'] == pytest.approx(0.1)


@pytest.mark.parametrize('argv, code, match', [
    (['--frequency', '-3'], 1, "'sine.frequency_hz' = -3.0"),
    (['--amplitude', '5e-6'], 1, 'stage travel'),
    (['--plant', 'quartic'], 2, "invalid choice: 'quartic'"),
    (['--bogus'], 2, 'unrecognized arguments: --bogus'),
    (['--duration', 'abc'], 2, "invalid float value: 'abc'"),
    (['--duration', '-1'], 1, "'--duration' = -1.0"),
    (['--param', 'controller_node:rac.epsilon=3'], 1, "'rac.epsilon' = 3 is not a parameter"),
    (['--param', 'nonsense'], 1, 'expected NODE:NAME=VALUE'),
    (['--config', '/nonexistent/x.yaml'], 1, 'cannot read parameter file'),
    (['--trajectory', 'square', '--frequency', '3'], 1, 'does not apply'),
    (['--trajectory', 'csv'], 1, "'csv.path'"),
    (['--experiment', 'table3', '--bag', 'x'], 1, '--bag records one run'),
    (['--trajectory', 'csv', '--csv', 'x.csv', '--amplitude', '1e-6'], 1,
     "does not apply to trajectory 'csv'"),
])
def test_bad_input_is_one_line_and_nonzero(argv: list[str], code: int, match: str,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    assert simulate.main(argv) == code
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith('simulate: error: ')
    assert match in lines[0]
    assert 'Traceback' not in captured.err and captured.out == ''


def test_identification_excitations_run_with_their_amplitude(
        capsys: pytest.CaptureFixture[str]) -> None:
    errors = []
    for amplitude in ('2e-8', '4e-8'):
        assert simulate.main(['--trajectory', 'noise', '--amplitude', amplitude, '--duration',
                              '0.05', '--json']) == 0
        out = json.loads(capsys.readouterr().out)
        assert out['samples'] == 500
        errors.append(out['e_rms_m'])
    # the noise reaches 5 kHz, beyond the loop bandwidth, so the error is of the order of the
    # excitation; at these small amplitudes the loop is nearly linear: twice the amplitude,
    # about twice the error (the --amplitude flag reaches the excitation)
    assert errors[1] / errors[0] == pytest.approx(2.0, rel=0.15)
    # the logarithmic chirp starts at 10 Hz: its first 50 ms are tracked to the ADC step
    assert simulate.main(['--trajectory', 'chirp', '--amplitude', '1e-6', '--duration', '0.05',
                          '--json']) == 0
    assert json.loads(capsys.readouterr().out)['e_rms_m'] < 2e-9


def test_paper_adaptation_rates_are_warned_about(capsys: pytest.CaptureFixture[str]) -> None:
    # the paper's rates without the normalisation (the paper's law has none)
    assert simulate.main(['--param', 'controller_node:rac.gamma=3000', '--param',
                          'controller_node:rac.eta=0.01', '--param',
                          'controller_node:rac.normalisation=0', '--duration', '0.05',
                          '--json']) == 0
    err = capsys.readouterr().err
    assert 'WARNING: ADAPTATION GAIN ABOVE THE DISCRETE BOUND' in err
    assert simulate.main(['--duration', '0.05', '--json']) == 0
    assert 'ADAPTATION' not in capsys.readouterr().err


def test_unstable_configuration_warns_or_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    # the paper's epsilon = 0.005 gives a boundary-layer gain k*/epsilon = 40: unstable at 10 kHz
    unstable = ['--plant', 'reduced', '--param', 'controller_node:rac.epsilon_v=0.005',
                '--duration', '0.01']
    d = run_json(capsys, *unstable)
    assert d['stable'] is False
    assert simulate.main([*unstable, '--json']) == 0
    assert 'WARNING: UNSTABLE CONFIGURATION' in capsys.readouterr().err
    assert simulate.main([*unstable, '--refuse-unstable']) == 1
    captured = capsys.readouterr()
    assert captured.err.startswith('simulate: error: ') and 'UNSTABLE' in captured.err
    assert len(captured.err.strip().splitlines()) == 1 and captured.out == ''


def test_experiment_fig6_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert simulate.main(['--experiment', 'fig6', '--plant', 'reduced', '--json']) == 0
    captured = capsys.readouterr()
    d = json.loads(captured.out)
    rows = d['experiments'][0]['rows']
    assert [r['frequency_hz'] for r in rows] == [1.0, 10.0, 50.0, 100.0]
    widths = [r['loop_width_pct'] for r in rows]
    assert widths == sorted(widths) and widths[0] < 2.0
    assert 'fig6' in captured.err  # progress goes to stderr


def test_bag_is_written_and_reads_back_the_same_metrics(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip('rosbags')
    from piezo_stage_ros.analysis.bagread import read_run
    bag = tmp_path / 'run'
    d = run_json(capsys, '--plant', 'reduced', '--duration', '0.05', '--bag', str(bag))
    assert (bag / 'metadata.yaml').is_file()
    record = read_run(bag)
    s = metrics.summarize(record)
    assert s.samples == d['samples']
    assert s.e_rms_m == pytest.approx(d['e_rms_m'], rel=1e-12)
    # no overwrite without --overwrite; with it, fine
    assert simulate.main(['--duration', '0.01', '--bag', str(bag)]) == 1
    capsys.readouterr()
    assert simulate.main(['--duration', '0.01', '--bag', str(bag), '--overwrite',
                          '--storage', 'sqlite3']) == 0


def test_param_values_read_as_ros_yaml(capsys: pytest.CaptureFixture[str]) -> None:
    # YAML 1.2 as ROS 2: 'off' stays a string, '1e-9' is a float (PyYAML alone gives a bool
    # and a string)
    d = run_json(capsys, '--plant', 'reduced', '--duration', '0.01',
                 '--param', 'controller_node:notch.mode=off',
                 '--param', 'plant_node:chain.sensor_noise_std_m=1e-9')
    assert d['samples'] == 100
    assert cli.parse_param('controller_node:notch.mode=off')[2] == 'off'
    assert cli.parse_param('plant_node:chain.sensor_noise_std_m=1e-9')[2] == 1e-9
    assert cli.parse_param('plant_node:chain.quantize=false')[2] is False


def test_true_position_error_in_json_and_summary(capsys: pytest.CaptureFixture[str]) -> None:
    # the simulated stage knows x(t_k): the JSON has e_max_true_m and e_rms_true_m beside the
    # measured figures, equal to summarize of the same run through the core
    argv = ['--plant', 'reduced', '--duration', '0.3', '--noise', '3e-9', '--seed', '2']
    d = run_json(capsys, *argv)
    sp = StageParams().with_flat({'plant.model': 'reduced', 'chain.sensor_noise_std_m': 3e-9,
                                  'seed': 2})
    rec = ex.run_one(sp, ControllerParams(), TrajectoryParams(), duration_s=0.3)
    s = metrics.summarize(rec)
    assert s.e_rms_true_m is not None
    assert (d['e_rms_true_m'], d['e_max_true_m']) == (s.e_rms_true_m, s.e_max_true_m)
    assert simulate.main(argv) == 0
    assert 'true position (no sensor noise, no ADC): e_m =' in capsys.readouterr().out


def test_steady_state_start_sets_the_window(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip('rosbags')
    from piezo_stage_ros.analysis.replay import analyze_bag
    bag = tmp_path / 'run'
    d = run_json(capsys, '--plant', 'reduced', '--duration', '0.3', '--steady-state-start',
                 '0.25', '--bag', str(bag))
    assert d['steady_state_start_s'] == 0.25
    # 0.25 s to the end of the last whole 10 ms period: 5 periods of 100 samples
    assert d['steady_state_samples'] == 500
    sp = StageParams().with_flat({'plant.model': 'reduced'})
    rec = ex.run_one(sp, ControllerParams(), TrajectoryParams(), duration_s=0.3)
    s = metrics.summarize(rec, steady_state_start_s=0.25)
    assert (d['e_rms_m'], d['e_max_m']) == (s.e_rms_m, s.e_max_m)
    assert d['e_rms_true_m'] == s.e_rms_true_m
    # the bag keeps the window: analyze measures the same samples without being told
    analysis = analyze_bag(bag)
    assert analysis.metrics['steady_state_samples'] == 500
    assert analysis.metrics['e_rms_m'] == d['e_rms_m']
    assert analysis.metrics['e_rms_true_m'] == d['e_rms_true_m']


@pytest.mark.parametrize('argv, match', [
    (['--steady-state-start', '0.3'], "'--steady-state-start' = 0.3 is outside the run; "
     'allowed: [0, 0.3) s'),
    (['--steady-state-start', '-0.1'], "'--steady-state-start' = -0.1 is outside the run"),
    (['--steady-state-start', 'nan'], "'--steady-state-start' = nan is outside the run"),
    (['--experiment', 'table3', '--steady-state-start', '0.1'],
     '--steady-state-start measures one run'),
])
def test_bad_steady_state_start(argv: list[str], match: str,
                                capsys: pytest.CaptureFixture[str]) -> None:
    assert simulate.main(['--duration', '0.3', *argv]) == 1
    err = capsys.readouterr().err
    assert err.startswith('simulate: error: ') and match in err


def test_feedforward_flag_is_the_feedforward_mode_parameter() -> None:
    # the flag must set exactly what --param sets, and win over it
    parser = simulate.build_parser()
    modes = cli.choices(ControllerParams, 'feedforward.mode')
    assert modes == ('none', 'inverse', 'learning', 'inverse_learning')
    for mode in modes:
        by_flag = simulate.build_config(parser.parse_args(['--feedforward', mode]))
        by_param = simulate.build_config(parser.parse_args(
            ['--param', f'controller_node:feedforward.mode={mode}']))
        assert by_flag.node('controller_node')['feedforward.mode'] == mode
        assert by_flag.sections == by_param.sections
    other = 'learning' if mode != 'learning' else 'inverse'
    both = simulate.build_config(parser.parse_args(
        ['--param', f'controller_node:feedforward.mode={other}', '--feedforward', mode]))
    assert both.node('controller_node')['feedforward.mode'] == mode
    with pytest.raises(cli.UsageError, match="invalid choice: 'bogus'"):
        parser.parse_args(['--feedforward', 'bogus'])

