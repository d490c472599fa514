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

"""Bags of multi-axis runs: written, read back by name, analysed as the run was, drawn."""

import json
from pathlib import Path
import struct

import numpy as np
from piezo_stage_ros import analyze, simulate, simulate_axes
from piezo_stage_ros.analysis.bagread import bag_axes, bag_info, read_axes, read_run
from piezo_stage_ros.analysis.bagwrite import RunBagWriter, write_axes
from piezo_stage_ros.core.contracts.errors import BagError
from piezo_stage_ros.core.loop.axes import grating_image
from piezo_stage_ros.core.loop.record import RunRecord
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

FIELDS = ('position_m', 'reference_m', 'reference_velocity_mps', 'command_v', 'true_position_m')
DT = 1e-4
# a short raster whose frames are whole within 0.3 s: 8 lines of 10 ms a frame
SHORT = ['--config', 'config/xy_stage.yaml', '--duration', '0.3',
         '--param', 'trajectory_node:scan.raster.lines=8']


def records(axes, n=257, seed=0, diagnostics=True):
    """Random per-axis samples (every bit pattern of a float64 is a fair test of the codec)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    out = []
    for a in axes:
        values = [rng.standard_normal(n) * 1e-5 for _ in FIELDS]
        diag = {'ff_u_v': rng.standard_normal(n), 'theta_hat': rng.standard_normal(n)} \
            if diagnostics else {}
        out.append(RunRecord(t, *values[:4], diag, {'axis': a}, values[4]))
    return out


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
@pytest.mark.parametrize('axes', [('x', 'y'), ('x', 'y', 'z'), ('y',)])
def test_a_multi_axis_run_comes_back_bit_for_bit(tmp_path, storage, axes):
    written = records(axes)
    write_axes(written, tmp_path / 'b', storage=storage, meta={'scan': 'raster'})
    read = read_axes(tmp_path / 'b')
    assert [r.meta['axis'] for r in read] == list(axes)
    for w, r in zip(written, read):
        for name in FIELDS:
            assert np.array_equal(getattr(w, name), getattr(r, name)), name
        assert np.array_equal(np.rint(w.time_s * 1e9), np.rint(r.time_s * 1e9))
        assert r.diagnostics.keys() == w.diagnostics.keys()
        for key, values in w.diagnostics.items():
            assert np.array_equal(values, r.diagnostics[key])
        assert r.meta['scan'] == 'raster' and r.meta['axes'] == list(axes)
        assert r.meta['alignment']['dropped_position'] == 0
    # every message took the bulk path: the reader's layouts are the writer's own
    decoding = read[0].meta['decoding']
    assert len(decoding) == 5
    assert all(d['messages'] == d['bulk'] == len(written[0]) for d in decoding.values())


def test_the_messages_are_what_ros_tools_read(tmp_path):
    from rosbags.rosbag2 import Reader
    written = records(('x', 'y'), n=3, diagnostics=False)
    write_axes(written, tmp_path / 'b')
    store = get_typestore(Stores.ROS2_JAZZY)
    seen = {}
    with Reader(tmp_path / 'b') as reader:
        for conn, _, raw in reader.messages():
            seen.setdefault(conn.topic, store.deserialize_cdr(raw, conn.msgtype))
    assert list(seen['/stage/position'].name) == ['stage_x', 'stage_y']
    assert list(seen['/stage/reference'].velocity) == [written[0].reference_velocity_mps[0],
                                                        written[1].reference_velocity_mps[0]]
    command = seen['/stage/command']
    assert [(d.label, d.size, d.stride) for d in command.layout.dim] == [('axes', 2, 2)]
    assert command.layout.data_offset == 0
    assert list(command.data) == [written[0].command_v[0], written[1].command_v[0]]


def test_bags_of_the_two_kinds_refuse_each_others_reader(tmp_path):
    write_axes(records(('x', 'y')), tmp_path / 'axes')
    with pytest.raises(BagError, match='several axes.*read_axes'):
        read_run(tmp_path / 'axes')
    one = records(('x',))[0]
    with RunBagWriter(tmp_path / 'one') as writer:
        writer.write_chunk(one)
    with pytest.raises(BagError, match='one-axis run.*read_run'):
        read_axes(tmp_path / 'one')


def test_the_writer_refuses_what_a_multi_axis_bag_cannot_hold(tmp_path):
    with pytest.raises(BagError, match="axis names .*'x,y'.*without ','"):
        write_axes(records(('x,y', 'z')), tmp_path / 'b', topics='block')
    with pytest.raises(BagError, match=r"records of the axes \['y', 'x'\]"):
        _write_in_order(tmp_path / 'c', records(('y', 'x')), ('x', 'y'))
    with pytest.raises(BagError, match='shape'):
        with RunBagWriter(tmp_path / 'd', axes=('x', 'y')) as writer:
            writer.write_samples([0.0], [[1.0, 2.0, 3.0]], [[0.0, 0.0]], [[0.0, 0.0]],
                                 [[0.0, 0.0]])
    assert not (tmp_path / 'd').exists()      # a failed bag is removed


def _write_in_order(path, recs, axes):
    with RunBagWriter(path, axes=axes) as writer:
        writer.write_axes_chunk(recs)


# A bag as another recorder may write it: joints in another order (and a joint of something
# else), no run description, messages serialized by rosbags itself.


def foreign_bag(path, *, position_names=('stage_y', 'stage_x', 'gripper'),
                command_values=2, n=20):
    store = get_typestore(Stores.ROS2_JAZZY)
    JointState = store.types['sensor_msgs/msg/JointState']
    Header = store.types['std_msgs/msg/Header']
    Time = store.types['builtin_interfaces/msg/Time']
    Array = store.types['std_msgs/msg/Float64MultiArray']
    Layout = store.types['std_msgs/msg/MultiArrayLayout']
    Dim = store.types['std_msgs/msg/MultiArrayDimension']
    x = 1e-6 * np.arange(n)            # axis x's values, axis y's are their negatives
    value = {'stage_x': x, 'stage_y': -x, 'gripper': np.full(n, 7.0)}
    with Writer(path, version=Writer.VERSION_LATEST) as writer:
        conns = {topic: writer.add_connection(topic, msgtype, typestore=store) for topic, msgtype
                 in (('/stage/position', JointState.__msgtype__),
                     ('/stage/reference', JointState.__msgtype__),
                     ('/stage/command', Array.__msgtype__))}
        for k in range(n):
            stamp_ns = 5_000_000_000 + k * 100_000
            header = Header(stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
                            frame_id='')
            pos = JointState(header=header, name=list(position_names),
                             position=np.array([value[j][k] + 1e-9 for j in position_names]),
                             velocity=np.zeros(0), effort=np.zeros(0))
            ref_names = ['stage_x', 'stage_y']        # the reference lists them otherwise
            ref = JointState(header=header, name=ref_names,
                             position=np.array([value[j][k] for j in ref_names]),
                             velocity=np.array([1.0, -1.0]), effort=np.zeros(0))
            # the command in the stage's axis order (x, y)
            cmd = Array(layout=Layout(dim=[Dim(label='axes', size=command_values,
                                               stride=command_values)], data_offset=0),
                        data=np.array([0.5 + k, -0.5 - k, 9.0][:command_values]))
            for topic, msg in (('/stage/position', pos), ('/stage/reference', ref),
                               ('/stage/command', cmd)):
                writer.write(conns[topic], stamp_ns + 1000, store.serialize_cdr(
                    msg, msg.__msgtype__))
    return x


def test_a_foreign_bag_is_read_by_joint_name(tmp_path):
    x = foreign_bag(tmp_path / 'f')
    rx, ry = read_axes(tmp_path / 'f', axes=('x', 'y'), relative_time=True)
    assert np.array_equal(rx.position_m, x + 1e-9) and np.array_equal(ry.position_m, -x + 1e-9)
    assert np.array_equal(rx.reference_m, x) and np.array_equal(ry.reference_m, -x)
    assert np.all(rx.reference_velocity_mps == 1.0) and np.all(ry.reference_velocity_mps == -1.0)
    assert np.array_equal(rx.command_v, 0.5 + np.arange(20))
    assert np.array_equal(ry.command_v, -0.5 - np.arange(20))
    assert rx.true_position_m is None and rx.time_s[1] == pytest.approx(1e-4, abs=1e-15)
    # without a description the axis order is the position message's (the stage publishes
    # its joints in its axis order), the joints of anything else left out
    assert bag_axes(bag_info(tmp_path / 'f')) == ('y', 'x')


def test_a_bag_without_an_axis_or_with_another_axis_count_is_refused(tmp_path):
    foreign_bag(tmp_path / 'missing', position_names=('stage_x', 'gripper'))
    with pytest.raises(BagError, match=r"position has the joints \['stage_x', 'gripper'\]; "
                                       r"missing: \['stage_y'\]"):
        read_axes(tmp_path / 'missing', axes=('x', 'y'))
    foreign_bag(tmp_path / 'three', command_values=3)
    with pytest.raises(BagError, match=r'/stage/command has the layout .* and 3 values; '
                                       r'expected 2 values, one per axis'):
        read_axes(tmp_path / 'three', axes=('x', 'y'))
    with pytest.raises(BagError, match='3 values; expected 2 values'):
        read_axes(tmp_path / 'three')            # no description: the joints name the axes


def test_analyze_reports_a_bad_multi_axis_bag_in_one_line(tmp_path, capsys):
    foreign_bag(tmp_path / 'missing', position_names=('stage_y', 'gripper'))
    foreign_bag(tmp_path / 'good')
    # the good bag is analysed all the same; the bad one fails with one line naming it
    assert analyze.main([str(tmp_path / 'missing'), str(tmp_path / 'good')]) == 1
    captured = capsys.readouterr()
    # no description: the position's joints give the axes (y alone), the command has two
    assert captured.err.count('\n') == 1 and '/missing:' in captured.err
    assert '2 values; expected 1 values, one per axis' in captured.err
    assert 'good: 20 samples, 2 axes (y, x)' in captured.out
    assert 'no run description in the bag' in captured.out


# The run, its bag and analyze.


def run_json(main, argv, capsys):
    assert main(argv) == 0
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


@pytest.mark.parametrize('command, topics', [('simulate', 'samples'),
                                             ('simulate_axes', 'samples'),
                                             ('simulate', 'block'), ('simulate_axes', 'both')])
def test_analyze_of_the_bag_gives_the_figures_of_the_run(tmp_path, capsys, command, topics):
    main = simulate.main if command == 'simulate' else simulate_axes.main
    bag = tmp_path / 'run'
    run = run_json(main, SHORT + ['--json', '--bag', str(bag), '--bag-topics', topics], capsys)
    got = run_json(analyze.main, ['--json', str(bag)], capsys)
    assert got['window_s'] == run['window_s'] and set(got['axes']) == set(run['axes'])
    for name, m in run['axes'].items():
        # the same samples, bit for bit, through the same function: the same numbers
        for key in ('e_rms_m', 'e_max_m', 'e_rms_true_m', 'e_max_true_m', 'samples', 'window'):
            assert got['axes'][name][key] == m[key], (name, key)
    assert got['fast_axis'] == 'x' and got['lines'] == 8


def png_size(path):
    head = Path(path).read_bytes()[:24]
    assert head[:8] == b'\x89PNG\r\n\x1a\n'
    return struct.unpack('>II', head[16:24])


def test_analyze_draws_the_frame_and_the_grating(tmp_path, capsys):
    bag = tmp_path / 'run'
    run_json(simulate_axes.main, SHORT + ['--json', '--bag', str(bag)], capsys)
    assert analyze.main(['--plots', str(tmp_path / 'figs'), str(bag)]) == 0
    text = capsys.readouterr().out
    assert 'grating of 1 um pitch imaged over the last frame' in text
    for name in ('error_x', 'error_y', 'frame_error', 'grating'):
        width, height = png_size(tmp_path / 'figs' / f'{name}.png')
        assert 300 <= width <= 3000 and 200 <= height <= 3000, name


def test_analyze_refuses_a_one_axis_option_for_a_multi_axis_bag(tmp_path, capsys):
    write_axes(records(('x', 'y')), tmp_path / 'b')
    assert analyze.main(['--export-table', str(tmp_path / 't.npz'), str(tmp_path / 'b')]) == 1
    assert 'takes one-axis bags' in capsys.readouterr().err


# The block topic of several axes: every axis in a row, as a real-time loop records them.


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
@pytest.mark.parametrize('axes', [('x', 'y'), ('x', 'y', 'z'), ('y',)])
def test_a_multi_axis_block_bag_reads_back_as_the_per_sample_bag(tmp_path, storage, axes):
    written = records(axes)
    write_axes(written, tmp_path / 's', storage=storage)
    write_axes(written, tmp_path / 'b', storage=storage, topics='block')
    write_axes(written, tmp_path / 'both', storage=storage, topics='both')
    assert set(bag_info(tmp_path / 'b').topics) == {'/stage/block'}
    per_sample = read_axes(tmp_path / 's')
    for path in ('b', 'both'):
        read = read_axes(tmp_path / path)
        assert read[0].meta['alignment']['source'] == 'block'
        assert read[0].meta['alignment']['missing_samples'] == 0
        for w, r, s in zip(written, read, per_sample):
            assert r.meta['axis'] == w.meta['axis']
            for name in FIELDS:
                assert np.array_equal(getattr(w, name), getattr(r, name)), name
            assert np.array_equal(r.time_s, s.time_s)
            assert list(r.diagnostics) == list(s.diagnostics) == sorted(w.diagnostics)
            for key, values in w.diagnostics.items():
                assert np.array_equal(values, r.diagnostics[key])


def test_a_multi_axis_block_is_one_row_a_sample_named_by_axis(tmp_path):
    from rosbags.rosbag2 import Reader
    written = records(('x', 'y'), n=3)
    write_axes(written, tmp_path / 'b', topics='block', meta={})
    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(tmp_path / 'b') as reader:
        (conn, _, raw), = list(reader.messages())
    msg = store.deserialize_cdr(raw, conn.msgtype)
    rows, cols = msg.layout.dim
    names = cols.label.split(',')
    assert (rows.label, rows.size, cols.size) == ('samples', 3, len(names))
    assert names[:3] == ['sample', 'stamp_sec', 'stamp_nanosec']
    assert names[3:13] == [f'{a}.{c}' for a in 'xy' for c in
                           ('position_m', 'reference_m', 'velocity_mps', 'command_v',
                            'true_position_m')]
    assert names[13:] == [f'diagnostics.{a}.{k}' for a in 'xy' for k in ('ff_u_v', 'theta_hat')]
    data = np.asarray(msg.data).reshape(3, len(names))
    assert data[1, names.index('y.command_v')] == written[1].command_v[1]
    assert data[2, names.index('diagnostics.x.theta_hat')] == \
        written[0].diagnostics['theta_hat'][2]


def test_the_readers_of_one_axis_and_of_several_refuse_each_others_blocks(tmp_path):
    write_axes(records(('x', 'y')), tmp_path / 'axes', topics='block')
    with pytest.raises(BagError, match='not of one axis.*read_axes'):
        read_run(tmp_path / 'axes')
    one = records(('x',))[0]
    with RunBagWriter(tmp_path / 'one', topics='block') as writer:
        writer.write_chunk(one)
    with pytest.raises(BagError, match='blocks of one axis.*read_run'):
        read_axes(tmp_path / 'one')


def foreign_block_bag(path, rows, label):
    """Blocks as another recorder writes them: no run description, rosbags' own CDR."""
    store = get_typestore(Stores.ROS2_JAZZY)
    Array = store.types['std_msgs/msg/Float64MultiArray']
    Layout = store.types['std_msgs/msg/MultiArrayLayout']
    Dim = store.types['std_msgs/msg/MultiArrayDimension']
    with Writer(path, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection('/stage/block', 'std_msgs/msg/Float64MultiArray',
                                     typestore=store)
        n, c = rows.shape
        for lo in range(0, n, 10):
            part = rows[lo:lo + 10]
            msg = Array(layout=Layout(dim=[Dim(label='samples', size=len(part),
                                               stride=len(part) * c),
                                           Dim(label=label, size=c, stride=c)],
                                      data_offset=0),
                        data=np.ascontiguousarray(part).reshape(-1))
            stamp = int(part[-1, 1]) * 1_000_000_000 + int(part[-1, 2])
            writer.write(conn, stamp, store.serialize_cdr(msg, conn.msgtype))


def test_a_recorded_block_bag_of_several_axes_is_read_by_its_columns(tmp_path):
    # a real-time recording: applied_v (what the plant held) is the command; a block lost on
    # the way shows as missing samples
    n, axes = 40, ('x', 'y')
    k = np.arange(n, dtype=float)
    stamp_ns = 1_700_000_000_000_000_000 + np.arange(n) * 100_000
    cols = ['sample', 'stamp_sec', 'stamp_nanosec']
    sec, nanosec = np.divmod(stamp_ns, 1_000_000_000)
    values = [k, sec.astype(float), nanosec.astype(float)]
    for j, a in enumerate(axes):
        for c, scale in (('position_m', 1e-6), ('reference_m', 1e-6), ('velocity_mps', 1e-3),
                         ('command_v', 1.0), ('applied_v', 1.0)):
            cols.append(f'{a}.{c}')
            values.append(scale * (j + 1) + k * 1e-9 + (0.5 if c == 'applied_v' else 0.0))
    rows = np.column_stack(values)
    keep = np.r_[0:10, 20:40]                 # the second block lost
    foreign_block_bag(tmp_path / 'rt', rows[keep], ','.join(cols))
    read = read_axes(tmp_path / 'rt')
    assert [r.meta['axis'] for r in read] == list(axes)
    alignment = read[0].meta['alignment']
    assert alignment['missing_samples'] == 10 and alignment['command_source'] == 'applied'
    assert any('10 samples missing' in w for w in alignment['warnings'])
    for j, r in enumerate(read):
        assert np.array_equal(r.command_v, rows[keep, cols.index(f'{axes[j]}.applied_v')])
        assert np.array_equal(r.position_m, rows[keep, cols.index(f'{axes[j]}.position_m')])
        assert r.true_position_m is None


# The grating: where its lines show against where they are.


def raster_records(offset_x_m=0.0, offset_y_m=0.0, lines=4, per_line=100, frames=2):
    """A triangle fast axis and a staircase slow axis, reached with constant offsets."""
    n = lines * per_line * frames
    k = np.arange(n)
    phase = (k % per_line) / per_line
    xd = 10e-6 + 4e-6 * (1.0 - 4.0 * np.abs(phase - 0.5))      # low end at the line's start
    vd = np.where(phase < 0.5, 1.0, -1.0) * 4e-6 * 4.0 / (per_line * DT)
    line = k // per_line
    level = np.where((line // lines) % 2 == 0, line % lines, lines - 1 - line % lines)
    yd = 5e-6 + 0.25e-6 * level
    t = k * DT
    meta = {'sample_time_s': DT}
    fast = RunRecord(t, xd + offset_x_m, xd, vd, np.zeros(n), {},
                     {**meta, 'axis': 'x', 'trajectory_period_s': per_line * DT},
                     xd + offset_x_m)
    slow = RunRecord(t, yd + offset_y_m, yd, np.zeros(n), np.zeros(n), {},
                     {**meta, 'axis': 'y'}, yd + offset_y_m)
    return fast, slow


def test_a_stage_that_reaches_its_positions_images_the_grating_undistorted():
    g = grating_image(*raster_records(), lines=4, pitch_m=1e-6)
    assert g.rms_x_m == (0.0, 0.0) and g.rms_y_m == (0.0, 0.0)
    for k in range(2):
        assert np.array_equal(g.desired[k], g.imaged[k])
        assert np.isfinite(g.imaged[k]).all() and g.imaged[k].shape[0] == 4


def test_an_offset_shifts_the_grating_lines_by_minus_the_offset():
    # reached x = x_d + 3 nm: the line x = m p is reached at x_d = m p - 3 nm, so it shows
    # there; the interpolation is of straight lines, exact to rounding of the positions
    g = grating_image(*raster_records(3e-9, -2e-9), lines=4, pitch_m=1e-6)
    for k in range(2):
        shifts = g.shift_x_m[k][np.isfinite(g.shift_x_m[k])]
        assert shifts.size >= 4 * 6
        # a few roundings of positions up to 14 um
        np.testing.assert_allclose(shifts, -3e-9, rtol=0, atol=16 * np.finfo(float).eps * 14e-6)
        assert g.rms_x_m[k] == pytest.approx(3e-9, rel=1e-9)
        assert g.rms_y_m[k] == pytest.approx(2e-9, rel=1e-9)
    assert not np.array_equal(g.imaged[0], g.desired[0])


def test_frame_rows_can_begin_at_the_low_turn_around():
    from piezo_stage_ros.core.loop.axes import frame_images, line_start
    fast, slow = raster_records(lines=4, frames=3)
    # the same run seen from 30 samples later: its lines begin mid-trace
    late = [RunRecord(r.time_s[30:] - r.time_s[30], r.position_m[30:] + 1e-9 * np.arange(
        len(r) - 30), r.reference_m[30:], r.reference_velocity_mps[30:], r.command_v[30:], {},
        r.meta) for r in (fast, slow)]
    start = line_start(late[0])
    assert start == 70                          # the next low end
    x_img, _ = frame_images(late[0], late[1], lines=4, frame=0, start=start)
    assert np.array_equal(x_img[0], late[0].error_m[70:170])
    assert np.argmin(late[0].reference_m[70:170]) == 0
    assert np.array_equal(frame_images(late[0], late[1], lines=4, frame=0)[0][0],
                          late[0].error_m[:100])          # start 0: as before


def test_an_existing_bag_is_refused_before_the_run(tmp_path, capsys):
    (tmp_path / 'b').mkdir()
    (tmp_path / 'b' / 'keep.txt').write_text('mine')
    assert simulate_axes.main(SHORT + ['--bag', str(tmp_path / 'b')]) == 1
    captured = capsys.readouterr()
    assert 'exists already' in captured.err and 'simulated' not in captured.out
    assert (tmp_path / 'b' / 'keep.txt').read_text() == 'mine'


def test_a_bag_with_neither_command_nor_blocks_is_refused_naming_both(tmp_path):
    # a recording of the positions alone, read with its namespace given
    written = records(('x', 'y'), n=5, diagnostics=False)
    write_axes(written, tmp_path / 'b')
    from rosbags.rosbag2 import Reader
    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(tmp_path / 'b') as reader, \
            Writer(tmp_path / 'p', version=Writer.VERSION_LATEST,
                   storage_plugin=StoragePlugin.MCAP) as writer:
        conns = [c for c in reader.connections if c.topic == '/stage/position']
        out = writer.add_connection('/stage/position', conns[0].msgtype, typestore=store)
        for _, stamp, raw in reader.messages(connections=conns):
            writer.write(out, stamp, raw)
    with pytest.raises(BagError, match='neither /stage/command nor /stage/block'):
        read_axes(tmp_path / 'p', namespace='/stage')
