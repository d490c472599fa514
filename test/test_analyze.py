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

"""analyze: metrics of a bag equal those of the run that wrote it; figures, reports, bad bags."""

import json
import math
from pathlib import Path
import subprocess
import sys

import numpy as np
from piezo_stage_ros import analyze
from piezo_stage_ros.analysis.bagwrite import RunBagWriter, write_run
from piezo_stage_ros.analysis.replay import analyze_bag
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.loop.closed_loop import run
from piezo_stage_ros.core.loop.metrics import square_wave_metrics, summarize
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.stage import Stage, StageParams
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

SHARED = Path('/work/shared/bags')
if not SHARED.is_dir():
    SHARED = Path(__file__).resolve().parents[2] / 'shared' / 'bags'


def closed_loop_run(kind='sine', controller='rac', duration_s=0.3, chunk_callback=None):
    stage_params = StageParams().with_flat({'plant.model': 'reduced'})
    stage = Stage(stage_params)
    ctrl = build_controller(ControllerParams(type=controller), stage_params.sample_time_s)
    flat = {'kind': kind}
    if kind == 'square':
        flat['square.period_s'] = 0.1
    trajectory = make_trajectory(TrajectoryParams.from_flat(flat))
    return run(stage, ctrl, trajectory, duration_s=duration_s, chunk_s=0.05,
               chunk_callback=chunk_callback,
               meta={'controller': {'type': controller}, 'trajectory': {'kind': kind}})


def assert_metrics_equal(from_run, from_bag):
    assert set(from_run) <= set(from_bag)
    for key, value in from_run.items():
        got = from_bag[key]
        if value is None or (isinstance(value, float) and math.isnan(value)):
            assert got is None or math.isnan(got), key
        elif key in ('samples', 'e_max_m', 'e_rms_m', 'e_max_all_m', 'e_rms_all_m',
                     'steady_state_samples', 'command_min_v', 'command_max_v'):
            # The same samples in the same window: bit for bit.
            assert got == value, key
        else:
            # Times come back as stamp_ns / 1e9: equal to the last bit or two.
            assert got == pytest.approx(value, rel=1e-12, abs=1e-15), key


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
@pytest.mark.parametrize('controller', ['rac', 'pi'])
def test_metrics_of_a_bag_equal_those_of_the_run_that_wrote_it(tmp_path, capsys, storage,
                                                               controller):
    record = closed_loop_run(controller=controller)
    bag = tmp_path / 'run'
    write_run(record, bag, storage=storage)
    assert analyze.main(['--json', str(bag)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    from_bag = json.loads(lines[0])
    assert from_bag['bag'] == str(bag) and from_bag['time_origin_s'] == 0.0
    from_run = summarize(record).as_dict()
    # The default window is the runner's (two periods of 100 Hz, at least 0.1 s).
    assert from_run['steady_state_start_s'] == pytest.approx(0.1)
    assert_metrics_equal(from_run, from_bag)


@pytest.mark.parametrize('kind', ['sine', 'multisine'])
def test_graph_recording_without_meta_gets_simulates_window(tmp_path, kind):
    # A bag recorded from the nodes has no run description: the period is found from x_d.
    record = closed_loop_run(kind=kind, duration_s=0.5)
    bag = tmp_path / 'graph'
    # Stamps from a sim-time origin (float seconds near 1e9 could not hold 100 us steps).
    write_run(RunRecord(record.time_s + 1000.0, record.position_m, record.reference_m,
                        record.reference_velocity_mps, record.command_v), bag)
    analysis = analyze_bag(bag)
    assert analysis.record.meta['trajectory_period_s'] == pytest.approx(
        record.meta['trajectory_period_s'], rel=1e-9)
    expected = summarize(record).as_dict()
    for key in ('steady_state_start_s', 'steady_state_samples', 'e_max_m', 'e_rms_m',
                'loop_width_pct'):
        assert analysis.metrics[key] == pytest.approx(expected[key], rel=1e-9), key
    assert any('found from the samples' in note for note in analysis.notes)


def test_aperiodic_reference_has_no_period(tmp_path):
    record = closed_loop_run(kind='step', controller='pi', duration_s=0.05)
    bag = tmp_path / 'step'
    write_run(RunRecord(record.time_s, record.position_m, record.reference_m,
                        record.reference_velocity_mps, record.command_v), bag)
    analysis = analyze_bag(bag)
    assert 'trajectory_period_s' not in analysis.record.meta
    assert analysis.metrics['steady_state_start_s'] == 0.0


def test_streamed_bag_equals_the_run(tmp_path):
    # How simulate --bag streams a long run: one chunk at a time, never the whole run in memory.
    bag = tmp_path / 'streamed'
    with RunBagWriter(bag) as writer:
        record = closed_loop_run(chunk_callback=writer.write_chunk)
        writer.set_meta(record.meta)
    analysis = analyze_bag(bag)
    assert analysis.samples == len(record) == 3000
    assert_metrics_equal(summarize(record).as_dict(), analysis.metrics)
    assert analysis.record.meta['trajectory_period_s'] == record.meta['trajectory_period_s']


def test_square_wave_bag_has_the_step_figures(tmp_path):
    record = closed_loop_run(kind='square', controller='pi', duration_s=0.4)
    bag = tmp_path / 'square'
    write_run(record, bag)
    analysis = analyze_bag(bag)
    expected = square_wave_metrics(record.time_s, record.position_m, record.reference_m,
                                   period_s=0.1).as_dict()
    for key in ('rise_time_s', 'overshoot_pct', 'settling_time_s', 'ss_e_rms_m'):
        assert analysis.metrics[key] == pytest.approx(expected[key], rel=1e-9, abs=1e-12), key
    assert analysis.metrics['edges'] == expected['edges'] >= 3


def test_explicit_window(tmp_path, capsys):
    record = closed_loop_run()
    bag = tmp_path / 'run'
    write_run(record, bag)
    assert analyze.main(['--json', '--steady-state-start', '0.2', str(bag)]) == 0
    from_bag = json.loads(capsys.readouterr().out)
    assert_metrics_equal(summarize(record, steady_state_start_s=0.2).as_dict(), from_bag)


@pytest.mark.parametrize('name', ['stage_sine5hz_mcap', 'stage_sine5hz_sqlite3'])
def test_shared_jazzy_bag_metrics(capsys, name):
    bag = SHARED / name
    if not bag.is_dir():
        pytest.skip(f'{bag} not present')
    assert analyze.main(['--json', str(bag)]) == 0
    out = json.loads(capsys.readouterr().out)
    # README of the bags: e_rms over the whole run 35.355 nm, e_max 50.000 nm.
    assert out['samples'] == 3000
    assert out['e_rms_all_m'] == pytest.approx(35.355e-9, abs=0.0005e-9)
    assert out['e_max_all_m'] == pytest.approx(50.000e-9, abs=0.0005e-9)
    assert out['time_origin_s'] == 1_600_000_000.0
    # The recorder stores no run description: the 5 Hz period comes from the samples, and
    # with it simulate's window (2 periods skipped, whole periods kept).
    assert out['trajectory_period_s'] == pytest.approx(0.2, abs=1e-12)
    assert out['steady_state_start_s'] == pytest.approx(0.4, abs=1e-12)
    assert out['steady_state_samples'] == 2600
    assert out['e_max_m'] == pytest.approx(50.000e-9, abs=0.0005e-9)


def test_human_summary(tmp_path, capsys):
    bag = tmp_path / 'run'
    write_run(closed_loop_run(), bag)
    assert analyze.main([str(bag)]) == 0
    out = capsys.readouterr().out
    assert f'{bag}: 3000 samples over 0.2999 s (10000 Hz), storage mcap' in out
    assert 'e_rms_m' in out and ' nm' in out and 'controller: rac' in out


def _png_size(path):
    data = path.read_bytes()
    assert data[:8] == b'\x89PNG\r\n\x1a\n', path
    return int.from_bytes(data[16:20], 'big'), int.from_bytes(data[20:24], 'big')


def test_plots_of_a_square_run_and_a_forced_bode(tmp_path):
    bag = tmp_path / 'square'
    write_run(closed_loop_run(kind='square', controller='pi', duration_s=0.4), bag)
    assert analyze.main(['-q', '--bode', '--plots', str(tmp_path / 'png'), str(bag)]) == 0
    names = {p.name for p in (tmp_path / 'png').iterdir()}
    assert {'step_zoom.png', 'bode.png', 'tracking.png'} <= names


def test_bode_estimate_of_a_known_first_order_plant(tmp_path):
    # x = G v with G(s) = K / (tau s + 1), discretized exactly (ZOH), driven by white noise:
    # the estimate must match |G| at low frequency and the -45 deg point near 1/(2 pi tau).
    n, dt, gain, tau = 40000, 1e-4, 2.843e-6, 2.445e-4
    rng = np.random.default_rng(5)
    v = 1.0 + 0.5 * rng.standard_normal(n)
    a = math.exp(-dt / tau)
    x = np.zeros(n)
    for k in range(1, n):
        x[k] = a * x[k - 1] + gain * (1 - a) * v[k - 1]
    t = np.arange(n) * dt
    record = RunRecord(t, x, np.zeros(n), np.zeros(n), v, {},
                       {'trajectory': {'kind': 'noise'}})
    bag = tmp_path / 'noise'
    write_run(record, bag)
    analysis = analyze_bag(bag)
    assert analysis.bode is not None
    est = analysis.bode
    assert est.dc_gain((0, 60)) == pytest.approx(gain, rel=0.01)
    f_c = 1 / (2 * math.pi * tau)
    i = int(np.argmin(np.abs(est.frequency_hz - f_c)))
    # ZOH adds half a sample of delay: -45 deg - 360 f T / 2.
    expected = -45.0 - 180.0 * est.frequency_hz[i] * dt
    assert math.degrees(np.angle(est.response[i])) == pytest.approx(expected, abs=3.0)


def test_report_compares_several_bags(tmp_path, capsys):
    bags = []
    for controller in ('rac', 'pi'):
        bag = tmp_path / 'in' / controller
        write_run(closed_loop_run(controller=controller), bag)
        bags.append(str(bag))
    report_dir = tmp_path / 'report'
    assert analyze.main(['-q', '--report', str(report_dir), *bags]) == 0
    text = (report_dir / 'report.md').read_text()
    assert text.startswith('# Comparison of 2 runs')
    assert '| metric | rac | pi |' in text
    row = next(line for line in text.splitlines() if line.startswith('| `e_rms_m` |'))
    assert row.count(' nm') == 2
    for rel in ('comparison_error.png', 'rac/tracking.png', 'pi/io_curves.png'):
        assert f']({rel})' in text
        _png_size(report_dir / rel)


def test_plots_and_report_of_one_sine_bag(tmp_path):
    bag = tmp_path / 'rac'
    write_run(closed_loop_run(), bag)
    png, rep = tmp_path / 'png', tmp_path / 'r'
    assert analyze.main(['-q', '--plots', str(png), '--report', str(rep), str(bag)]) == 0
    names = sorted(p.name for p in png.iterdir())
    # A sine has no step to zoom on and is no excitation run: no zoom, no Bode; it is periodic
    # (0.3 s of 10 ms periods): a learning curve.
    assert names == ['error.png', 'io_curves.png', 'learning_curve.png', 'tracking.png']
    for name in names:
        width, height = _png_size(png / name)
        assert width >= 600 and height >= 300
    text = (rep / 'report.md').read_text()
    assert text.startswith('# Run report: rac')
    # Figures outside the report directory are linked by relative path.
    assert '](../png/tracking.png)' in text and '"trajectory_period_s": 0.01' in text
    assert '](../png/learning_curve.png)' in text and '*Learning curve: e_rms' in text


# --- bad input: one clear line naming the bag, exit status != 0, no traceback ----------------

STORE = get_typestore(Stores.ROS2_JAZZY)


def _good(path):
    write_run(closed_loop_run(duration_s=0.05), path)
    return path


def _bad_missing_topic(path):
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection('/stage/position', 'sensor_msgs/msg/JointState',
                                     typestore=STORE)
        writer.add_connection('/stage/command', 'std_msgs/msg/Float64', typestore=STORE)
        msg = STORE.types['sensor_msgs/msg/JointState'](
            header=STORE.types['std_msgs/msg/Header'](
                stamp=STORE.types['builtin_interfaces/msg/Time'](sec=0, nanosec=0),
                frame_id=''),
            name=['stage'], position=np.array([0.0]), velocity=np.array([]),
            effort=np.array([]))
        writer.write(conn, 0, STORE.serialize_cdr(msg, 'sensor_msgs/msg/JointState'))


def _bad_empty(path):
    write_run(RunRecord(*(np.zeros(0),) * 5), path)


def _bad_truncated(path):
    _good(path)
    file = next(path.glob('*.mcap'))
    file.write_bytes(file.read_bytes()[:3000])


def _bad_storage(path):
    _good(path)
    meta = path / 'metadata.yaml'
    meta.write_text(meta.read_text().replace('storage_identifier: mcap',
                                             'storage_identifier: rosbag_v1'))


def _bad_type(path):
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        for key, msgtype in (('position', 'std_msgs/msg/String'),
                             ('reference', 'sensor_msgs/msg/JointState'),
                             ('command', 'std_msgs/msg/Float64')):
            conn = writer.add_connection(f'/stage/{key}', msgtype, typestore=STORE)
            if key == 'position':
                writer.write(conn, 0, STORE.serialize_cdr(STORE.types[msgtype](data='x'),
                                                          msgtype))


def _bad_not_a_bag(path):
    path.mkdir()
    (path / 'notes.txt').write_text('hello')


@pytest.mark.parametrize('make, problem', [
    (_bad_missing_topic, 'topic /stage/reference is missing'),
    (_bad_empty, r'bag is empty \(no messages\)'),
    (_bad_truncated, 'cannot open it'),
    (_bad_storage, "Storage plugin 'rosbag_v1' not supported"),
    (_bad_type, 'topic /stage/position has type std_msgs/msg/String, expected'),
    (_bad_not_a_bag, r'not a rosbag2 bag \(no metadata.yaml\)'),
])
def test_bad_bags_give_one_line_and_a_failure_status(tmp_path, capsys, make, problem):
    good = _good(tmp_path / 'good')
    bad = tmp_path / 'bad'
    make(bad)
    status = analyze.main(['--json', str(bad), str(good)])
    captured = capsys.readouterr()
    assert status == 1
    err_lines = captured.err.strip().splitlines()
    assert len(err_lines) == 1, captured.err
    assert err_lines[0].startswith(f'analyze: error: bag {bad}: ')
    assert __import__('re').search(problem, err_lines[0]), err_lines[0]
    assert 'Traceback' not in captured.err
    # The good bag after the bad one is still analysed.
    assert json.loads(captured.out)['bag'] == str(good)


@pytest.mark.parametrize('argv, message', [
    (['--steady-state-start', '-1', 'x'], "argument --steady-state-start: '-1' is out of "
                                          r'range; allowed: \[0, inf\) s'),
    (['--bode', '--no-bode', 'x'], 'not allowed with argument'),
    ([], 'the following arguments are required: BAG'),
])
def test_bad_options(capsys, argv, message):
    assert analyze.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert __import__('re').search(message, err[0]), err[0]


def test_module_entry_point_has_no_traceback(tmp_path):
    # python3 -m piezo_stage_ros.analyze, as a user runs it.
    proc = subprocess.run([sys.executable, '-m', 'piezo_stage_ros.analyze', str(tmp_path / 'no')],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    assert proc.stderr.strip() == f'analyze: error: bag {tmp_path / "no"}: does not exist'


def test_progress_line():
    import io

    from piezo_stage_ros.cli import Progress
    stream = io.StringIO()
    show = Progress('analyze', stream)
    show.fraction('[2/3] rac', 450, 1800)
    show.fraction('[2/3] rac', 1800, 1800)
    text = stream.getvalue()
    assert text.startswith('\ranalyze: [2/3] rac  25.0% (450/1800 messages)')
    assert text.endswith('\ranalyze: [2/3] rac 100.0% (1800/1800 messages)')
    show.end()
    assert stream.getvalue().endswith('\r\033[K')


@pytest.mark.parametrize('period_s, drawn', [(None, False), (0.02, False), (0.01, True)])
def test_learning_curve_only_with_a_period_and_two_whole_periods(tmp_path, period_s, drawn):
    from piezo_stage_ros.analysis.plots import plot_run
    n = 300  # 30 ms: one whole period of 20 ms, three of 10 ms
    t = np.arange(n) * 1e-4
    xd = 1e-6 * np.sin(2 * np.pi * 100 * t)
    meta = {} if period_s is None else {'trajectory_period_s': period_s}
    record = RunRecord(t, xd + 1e-9, xd, np.zeros(n), np.zeros(n), {}, meta,
                       true_position_m=xd + 1e-10)
    files = plot_run(record, tmp_path)
    assert ('learning_curve' in files) == drawn
    assert (tmp_path / 'learning_curve.png').exists() == drawn
    if drawn:
        width, height = _png_size(files['learning_curve'])
        assert width >= 600 and height >= 300
