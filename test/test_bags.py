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

"""Bags written with rosbags in tmp_path and read back: round trips, alignment, bad bags."""

import json
import math
from pathlib import Path
import shutil

import numpy as np
from piezo_stage_ros.analysis import bagread
from piezo_stage_ros.analysis.bagread import bag_info, read_run, read_topics
from piezo_stage_ros.analysis.bagwrite import RunBagWriter, write_run
from piezo_stage_ros.core.contracts import wire
from piezo_stage_ros.core.contracts.errors import BagError
from piezo_stage_ros.core.loop.record import RunRecord
import pytest
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

SHARED = Path(__file__).resolve().parents[1].parent / 'shared' / 'bags'
if not SHARED.is_dir():
    SHARED = Path('/work/shared/bags')
STORE = get_typestore(Stores.ROS2_JAZZY)
JS = 'sensor_msgs/msg/JointState'
F64 = 'std_msgs/msg/Float64'


def make_record(n=2000, start_s=0.0, diagnostics=True, true_position=False):
    k = np.arange(n)
    t = start_s + k * 1e-4
    rng = np.random.default_rng(7)
    diag = {}
    if diagnostics:
        diag = {'theta_hat': 1.29 + 1e-3 * np.sin(k / 50.0),
                'phi_hat': 3.2e-4 + 1e-6 * k,
                'saturated': (k % 7 == 0).astype(float)}
    true = 10e-6 + 5e-6 * np.sin(2 * np.pi * 5 * t) + rng.normal(0, 1e-10, n)
    return RunRecord(
        time_s=t,
        true_position_m=true if true_position else None,
        position_m=10e-6 + 5e-6 * np.sin(2 * np.pi * 5 * t) + rng.normal(0, 1e-9, n),
        reference_m=10e-6 + 5e-6 * np.sin(2 * np.pi * 5 * t),
        reference_velocity_mps=5e-6 * 2 * np.pi * 5 * np.cos(2 * np.pi * 5 * t),
        command_v=2.0 + 1.5 * np.sin(2 * np.pi * 5 * t) + rng.normal(0, 1e-3, n),
        diagnostics=diag,
        meta={'controller': 'rac', 'seed': 3, 'gains': {'k': 1.5}},
    )


def assert_same_run(a, b):
    np.testing.assert_allclose(a.time_s, b.time_s, rtol=0, atol=1e-12)
    # bit for bit: a bag round trip stores the float64 samples as they are (no arithmetic)
    for name in ('position_m', 'reference_m', 'reference_velocity_mps', 'command_v'):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert (a.true_position_m is None) == (b.true_position_m is None)
    if a.true_position_m is not None:
        np.testing.assert_array_equal(a.true_position_m, b.true_position_m)
    assert sorted(a.diagnostics) == sorted(b.diagnostics)
    for key in a.diagnostics:
        np.testing.assert_array_equal(a.diagnostics[key], b.diagnostics[key], err_msg=key)


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_round_trip_every_field(tmp_path, storage):
    rec = make_record()
    bag = tmp_path / 'run'
    write_run(rec, bag, storage=storage)
    back = read_run(bag)
    assert_same_run(rec, back)
    # The run description survives (as JSON) and the reader adds where it came from.
    assert back.meta['controller'] == 'rac' and back.meta['gains'] == {'k': 1.5}
    assert back.meta['storage'] == storage and back.meta['namespace'] == '/stage'
    assert back.meta['alignment']['samples'] == len(rec)
    assert back.meta['alignment']['dropped_command'] == 0


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_stamps_and_log_times_exactly_100us_apart(tmp_path, storage):
    bag = tmp_path / 'run'
    write_run(make_record(n=5000), bag, storage=storage)
    _, _, topics, _ = read_topics(bag)
    for key in ('position', 'reference', 'command', 'diagnostics'):
        log_ns, stamp_ns, _ = topics[key]
        assert log_ns.size == 5000
        assert np.all(np.diff(log_ns) == 100_000), key
        if stamp_ns is not None:
            np.testing.assert_array_equal(stamp_ns, log_ns)
    assert topics['position'][0][0] == 0


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_messages_decode_with_the_generic_rosbags_deserializer(tmp_path, storage):
    # Independent check of the byte templates: rosbags' own deserializer reads what we wrote.
    rec = make_record(n=30)
    bag = tmp_path / 'run'
    write_run(rec, bag, storage=storage)
    seen = {'position': [], 'reference': [], 'command': [], 'diagnostics': []}
    with Reader(bag) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {'/stage/position': JS, '/stage/reference': JS,
                         '/stage/command': F64, '/stage/diagnostics': JS}
        for conn, log_ns, raw in reader.messages():
            seen[conn.topic.rsplit('/', 1)[1]].append((log_ns, STORE.deserialize_cdr(raw,
                                                                                  conn.msgtype)))
    for k in range(30):
        log_ns, msg = seen['position'][k]
        assert log_ns == k * 100_000
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (0, k * 100_000)
        assert list(msg.name) == ['stage'] and msg.position[0] == rec.position_m[k]
        msg = seen['reference'][k][1]
        assert msg.position[0] == rec.reference_m[k]
        assert msg.velocity[0] == rec.reference_velocity_mps[k]
        assert seen['command'][k][1].data == rec.command_v[k]
        msg = seen['diagnostics'][k][1]
        assert list(msg.name) == ['phi_hat', 'saturated', 'theta_hat']
        assert msg.position[2] == rec.diagnostics['theta_hat'][k]


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_true_position_round_trip(tmp_path, storage):
    # a simulation's true position goes on stage/true_position (stamp t_k, name ['stage']) and
    # comes back bit for bit; rosbags' own deserializer reads the same values
    rec = make_record(n=300, true_position=True)
    bag = tmp_path / 'run'
    write_run(rec, bag, storage=storage)
    back = read_run(bag)
    assert_same_run(rec, back)
    values = []
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == '/stage/true_position']
        assert [c.msgtype for c in conns] == [JS]
        for _, log_ns, raw in reader.messages(connections=conns):
            msg = STORE.deserialize_cdr(raw, JS)
            assert list(msg.name) == ['stage']
            assert wire.stamp_to_ns(msg.header.stamp.sec, msg.header.stamp.nanosec) == log_ns
            values.append(msg.position[0])
    np.testing.assert_array_equal(values, rec.true_position_m)
    # a bag of a record without one has no such topic, and reads back without one
    write_run(make_record(n=300), tmp_path / 'bare', storage=storage)
    assert '/stage/true_position' not in bag_info(tmp_path / 'bare').topics
    assert read_run(tmp_path / 'bare').true_position_m is None


def test_streaming_writer_refuses_a_true_position_in_some_chunks_only(tmp_path):
    with pytest.raises(BagError, match='true position is given in some chunks only'):
        with RunBagWriter(tmp_path / 'b') as writer:
            writer.write_chunk(make_record(n=100, true_position=True))
            writer.write_chunk(make_record(n=100, start_s=1.0))
    assert not (tmp_path / 'b').exists()


def test_streaming_writer_equals_write_run(tmp_path):
    rec = make_record(n=3000)
    with RunBagWriter(tmp_path / 'streamed', meta={'controller': 'pi'}) as writer:
        for lo in range(0, 3000, 700):
            sl = slice(lo, lo + 700)
            writer.write_samples(rec.time_s[sl], rec.position_m[sl], rec.reference_m[sl],
                                 rec.reference_velocity_mps[sl], rec.command_v[sl],
                                 diagnostics={k: v[sl] for k, v in rec.diagnostics.items()})
    back = read_run(tmp_path / 'streamed')
    assert_same_run(rec, back)
    assert back.meta['controller'] == 'pi'


def test_streaming_writer_refuses_time_going_back(tmp_path):
    rec = make_record(n=100)
    with pytest.raises(BagError, match='strictly increasing'):
        with RunBagWriter(tmp_path / 'b') as writer:
            writer.write_chunk(rec)
            writer.write_chunk(rec)
    # The incomplete bag is removed, so a bag that exists is always complete.
    assert not (tmp_path / 'b').exists()


def test_streaming_writer_refuses_changed_diagnostic_keys(tmp_path):
    rec = make_record(n=100)
    later = make_record(n=100, start_s=1.0, diagnostics=False)
    with pytest.raises(BagError, match='diagnostic keys changed'):
        with RunBagWriter(tmp_path / 'b') as writer:
            writer.write_chunk(rec)
            writer.write_chunk(later)


def test_refuses_to_overwrite_unless_asked(tmp_path):
    bag = tmp_path / 'run'
    write_run(make_record(n=10), bag)
    with pytest.raises(BagError, match=r'run exists already; refusing to overwrite'):
        write_run(make_record(n=20), bag)
    assert len(read_run(bag)) == 10
    write_run(make_record(n=20), bag, overwrite=True)
    assert len(read_run(bag)) == 20


def test_overwrite_never_deletes_something_that_is_not_a_bag(tmp_path):
    precious = tmp_path / 'home'
    precious.mkdir()
    (precious / 'thesis.tex').write_text('x')
    with pytest.raises(BagError, match='is not a rosbag2 bag directory; refusing to delete'):
        write_run(make_record(n=10), precious, overwrite=True)
    assert (precious / 'thesis.tex').exists()


@pytest.mark.parametrize('kwargs, match', [
    ({'storage': 'hdf5'}, r"storage 'hdf5' is not supported; allowed: 'mcap', 'sqlite3'"),
    ({'namespace': 'bad ns'}, r"namespace 'bad ns' is not a valid ROS namespace"),
])
def test_bad_writer_options(tmp_path, kwargs, match):
    with pytest.raises(BagError, match=match):
        write_run(make_record(n=10), tmp_path / 'b', **kwargs)


def test_bad_sample_values(tmp_path):
    rec = make_record(n=10)
    rec.time_s[0] = -1.0
    with pytest.raises(BagError, match='finite and >= 0'):
        write_run(rec, tmp_path / 'b')


def test_namespace_is_found_or_chosen(tmp_path):
    bag = tmp_path / 'ns'
    write_run(make_record(n=50), bag, namespace='/lab/stage2')
    assert read_run(bag).meta['namespace'] == '/lab/stage2'
    assert len(read_run(bag, namespace='lab/stage2/')) == 50
    with pytest.raises(BagError, match='ns: topic /stage/position is missing'):
        read_run(bag, namespace='/stage')


def test_two_stages_in_one_bag_need_a_namespace(tmp_path):
    bag = tmp_path / 'two'
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        for ns in ('/a', '/b'):
            for key in ('position', 'reference', 'command'):
                writer.add_connection(f'{ns}/{key}', wire.BAG_TOPICS[key], typestore=STORE)
    with pytest.raises(BagError, match=r'several stages recorded \(/a, /b\)'):
        read_run(bag)


@pytest.mark.parametrize('name', ['stage_sine5hz_mcap', 'stage_sine5hz_sqlite3'])
def test_shared_jazzy_bags(name):
    # Recorded by the real Jazzy recorder: log times are receive times, stamps are in 2020.
    bag = SHARED / name
    if not bag.is_dir():
        pytest.skip(f'{bag} not present')
    rec = read_run(bag)
    assert len(rec) == 3000
    t = rec.time_s - 1_600_000_000
    np.testing.assert_allclose(t, np.arange(3000) * 1e-3, atol=1e-6)
    assert rec.meta['time_origin_ns'] == 1_600_000_000 * 10**9
    # Relative times are computed in integer nanoseconds: exact to the last bit.
    relative = read_run(bag, relative_time=True).time_s
    np.testing.assert_array_equal(relative, np.arange(3000) * 1_000_000 / 1e9)
    err = rec.position_m - rec.reference_m
    # The README's numbers: e_rms = 35.355 nm, e_max = 50.000 nm (to the printed digits).
    assert abs(np.sqrt(np.mean(err ** 2)) - 35.355e-9) < 0.0005e-9
    assert abs(np.max(np.abs(err)) - 50.000e-9) < 0.0005e-9
    k = np.arange(3000)
    np.testing.assert_allclose(rec.command_v, 2.0 + 1.5 * np.sin(2 * np.pi * 5 * k * 1e-3),
                               atol=1e-12)
    np.testing.assert_allclose(rec.reference_velocity_mps,
                               5e-6 * 2 * np.pi * 5 * np.cos(2 * np.pi * 5 * k * 1e-3),
                               rtol=1e-9, atol=1e-15)
    assert rec.diagnostics == {}
    # The recorder's messages have the layout the bulk decoder expects: all of them take it.
    assert all(d['bulk'] == d['messages'] == 3000 for d in rec.meta['decoding'].values())


def _js(stamp_ns, position, velocity=(), frame_id='', names=('stage',), effort=()):
    msg = STORE.types[JS](
        header=STORE.types['std_msgs/msg/Header'](
            stamp=STORE.types['builtin_interfaces/msg/Time'](sec=stamp_ns // 10**9,
                                                             nanosec=stamp_ns % 10**9),
            frame_id=frame_id),
        name=list(names), position=np.array(position, dtype=float),
        velocity=np.array(velocity, dtype=float), effort=np.array(effort, dtype=float))
    return STORE.serialize_cdr(msg, JS)


def _f64(value):
    return STORE.serialize_cdr(STORE.types[F64](data=float(value)), F64)


def _write_graph_bag(bag, n=400, *, skip_cmd_start=0, extra_cmd_end=0, jitter_ns=3_000_000,
                     frame_ids=('',), compression=None, cmd_every=1, applied_missing=None):
    """A bag as the ROS graph gives it: receive times jitter, ends a little ragged."""
    rng = np.random.default_rng(1)
    period = 1_000_000
    t0 = 1_700_000_000 * 10**9
    log0 = 1_800_000_000 * 10**9
    writer = Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP)
    if compression:
        writer.set_compression(compression, CompressionFormat.ZSTD)
    with writer:
        keys = ('position', 'reference', 'command') + (
            ('applied',) if applied_missing is not None else ())
        conns = {key: writer.add_connection(f'/stage/{key}', wire.BAG_TOPICS[key],
                                            typestore=STORE)
                 for key in keys}
        # Bursty delivery: a receive time may lag by several periods, never reorders a topic.
        lag = np.maximum.accumulate(rng.uniform(0, jitter_ns, n + extra_cmd_end)
                                    + np.arange(n + extra_cmd_end) * period) - np.arange(
                                        n + extra_cmd_end) * period
        logs = log0 + np.arange(n + extra_cmd_end) * period + lag.astype(np.int64)
        # The command arrives on its own subscription: up to 0.2 ms either side of the position,
        # but a topic is never reordered.
        cmd_logs = np.maximum.accumulate(logs + rng.integers(-200_000, 200_000, logs.size))
        for k in range(n + extra_cmd_end):
            log = int(logs[k])
            if k < n:
                frame = frame_ids[k % len(frame_ids)]
                writer.write(conns['position'], log, _js(t0 + k * period, [k * 1e-9],
                                                          frame_id=frame))
                writer.write(conns['reference'], log + 1000,
                             _js(t0 + k * period, [k * 1e-9 + 1e-8], [2.0], frame_id=frame))
                if applied_missing is not None and k not in applied_missing:
                    # what the plant held over sample k, published after it (as the node does)
                    writer.write(conns['applied'], log + 2000,
                                 _js(t0 + k * period, [], effort=[k * 0.002]))
            if k >= skip_cmd_start and k % cmd_every == 0:
                writer.write(conns['command'], int(cmd_logs[k]), _f64(k * 0.001))


def test_graph_bag_with_jitter_and_ragged_ends(tmp_path):
    bag = tmp_path / 'graph'
    _write_graph_bag(bag, skip_cmd_start=3, extra_cmd_end=2)
    rec = read_run(bag)
    # Samples 0..2 have no command (recorder started late on that topic): dropped.
    assert len(rec) == 397
    k = np.round((rec.time_s - 1.7e9) * 1e3).astype(int)
    np.testing.assert_array_equal(k, np.arange(3, 400))
    np.testing.assert_allclose(rec.command_v, k * 0.001, atol=1e-15)
    np.testing.assert_allclose(rec.position_m - rec.reference_m, -1e-8, atol=1e-20)
    assert rec.meta['alignment']['command_offset'] == -3
    assert rec.meta['alignment']['dropped_command'] == 2


def test_real_time_bag_with_most_commands_missing_is_analysed_with_a_warning(tmp_path, capsys):
    # a real-time run through separate processes: one command recorded for 20 samples (late or
    # lost); the commands carry no stamp, so they cannot be paired, but the tracking error can
    bag = tmp_path / 'sparse'
    _write_graph_bag(bag, cmd_every=20)
    rec = read_run(bag)
    assert len(rec) == 400 and np.isnan(rec.command_v).all()
    np.testing.assert_allclose(rec.position_m - rec.reference_m, -1e-8, atol=1e-20)
    align = rec.meta['alignment']
    assert not align['commands_paired']
    assert '20 commands for 400 positions' in align['warnings'][0]
    from piezo_stage_ros import analyze
    assert analyze.main([str(bag), '--json']) == 0
    out = capsys.readouterr()
    assert 'analyze: warning: bag' in out.err and 'cannot be paired' in out.err
    summary = json.loads(out.out.splitlines()[-1])
    assert summary['samples'] == 400 and summary['command_min_v'] is None
    assert math.isclose(summary['e_rms_all_m'], 1e-8, rel_tol=1e-9)


@pytest.mark.parametrize('taken', [400, 410])
def test_analysis_reports_the_plants_last_status(tmp_path, taken):
    # the bag holds 400 samples; a plant that took 410 lost 10 on the way, and the analysis says
    from piezo_stage_ros.analysis.replay import analyze_bag
    bag = tmp_path / 'status'
    _write_graph_bag(bag, cmd_every=20, applied_missing=())
    # a second bag layer: the plant's counters, twice (the last one holds the totals)
    status = STORE.types['diagnostic_msgs/msg/DiagnosticStatus']
    keyvalue = STORE.types['diagnostic_msgs/msg/KeyValue']
    with_status = tmp_path / 'with_status'
    with Reader(bag) as reader, Writer(with_status, version=9,
                                       storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {c.topic: writer.add_connection(c.topic, c.msgtype, typestore=STORE)
                 for c in reader.connections}
        for c, log, data in reader.messages():
            writer.write(conns[c.topic], log, data)
        sconn = writer.add_connection('/stage/status', wire.STATUS_TYPE, typestore=STORE)
        for log, late in ((1, '3'), (2, '7')):
            msg = status(level=1, name='plant', message='', hardware_id='model',
                         values=[keyvalue(key='late', value=late),
                                 keyvalue(key='paced_samples', value=str(taken)),
                                 keyvalue(key='lateness_p99_us', value='12.0'),
                                 keyvalue(key='other', value='x')])
            writer.write(sconn, 1_800_000_000 * 10**9 + log,
                         STORE.serialize_cdr(msg, wire.STATUS_TYPE))
    assert bagread.read_status(bag) is None
    assert bagread.read_status(with_status) == {'late': '7', 'paced_samples': str(taken),
                                                'lateness_p99_us': '12.0', 'other': 'x'}
    notes = analyze_bag(with_status).notes
    assert (f'the plant at the end of the run (stage/status): paced_samples {taken}, late 7, '
            'lateness_p99_us 12.0') in notes
    lost = [n for n in notes if 'were lost between the plant and the recorder' in n]
    assert lost == ([] if taken == 400 else
                    ['warning: the plant took 410 samples, the bag holds 400 of them: 10 were '
                     'lost between the plant and the recorder, or recorded before the first or '
                     'after the last message of this bag'])


@pytest.mark.parametrize('missing', [(), (5, 6, 399)])
def test_real_time_bag_takes_the_applied_input_by_stamp(tmp_path, missing):
    # stage/applied: what the plant held over each sample, stamped; commands (sparse, no stamp)
    # are not needed; a sample without its applied message gets NaN and a warning
    bag = tmp_path / 'applied'
    _write_graph_bag(bag, cmd_every=20, applied_missing=missing)
    rec = read_run(bag)
    assert len(rec) == 400
    k = np.round((rec.time_s - 1.7e9) * 1e3).astype(int)
    expected = np.where(np.isin(k, missing), np.nan, k * 0.002)
    np.testing.assert_array_equal(rec.command_v, expected)
    align = rec.meta['alignment']
    assert align['command_source'] == 'applied'
    assert align['warnings'] == (['3 of 400 samples have no applied input recorded '
                                  '(stage/applied); their command is NaN'] if missing else [])


def test_mixed_layouts_use_the_generic_decoder_where_needed(tmp_path):
    # Nine frame_ids, eight of the same length: a few byte layouts per size are learnt, the
    # messages beyond them go through rosbags' generic decoder; the values are the same.
    bag = tmp_path / 'mixed'
    _write_graph_bag(bag, n=200, frame_ids=('',) + tuple(f'f{i}' for i in range(8)))
    rec = read_run(bag)
    assert len(rec) == 200
    np.testing.assert_allclose(rec.position_m, np.arange(200) * 1e-9, atol=1e-21)
    np.testing.assert_allclose(rec.reference_velocity_mps, 2.0)
    decoding = rec.meta['decoding']['/stage/position']
    assert decoding['messages'] == 200 and 0 < decoding['bulk'] < 200


def test_two_layouts_of_one_size_are_both_bulk_decoded(tmp_path):
    bag = tmp_path / 'two'
    _write_graph_bag(bag, n=200, frame_ids=('ab', 'cd'))
    rec = read_run(bag)
    np.testing.assert_allclose(rec.position_m, np.arange(200) * 1e-9, atol=1e-21)
    assert rec.meta['decoding']['/stage/position'] == {'messages': 200, 'bulk': 200}


def test_compressed_bag_goes_through_rosbags(tmp_path):
    bag = tmp_path / 'zstd'
    _write_graph_bag(bag, n=100, compression=CompressionMode.MESSAGE)
    rec = read_run(bag)
    assert len(rec) == 100
    np.testing.assert_allclose(rec.command_v, np.arange(100) * 0.001, atol=1e-15)


def test_progress_is_reported(tmp_path):
    bag = tmp_path / 'run'
    write_run(make_record(n=1000), bag)
    calls = []
    read_run(bag, progress=lambda done, total: calls.append((done, total)))
    assert calls[-1] == (4000, 4000)
    assert all(a[0] <= b[0] for a, b in zip(calls, calls[1:]))


# --- bad bags: every failure is a BagError naming the bag and the problem ---------------------

def _copy(tmp_path, storage='mcap', n=3000):
    bag = tmp_path / f'bag_{storage}'
    write_run(make_record(n=n), bag, storage=storage)
    return bag


def _storage_file(bag):
    return next(p for p in bag.iterdir() if p.suffix in ('.mcap', '.db3'))


def _write_bag(bag, topics):
    # an MCAP bag with a connection per (topic, type, message) and that message, if any, at t = 0
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = [(writer.add_connection(topic, msgtype, typestore=STORE), raw)
                 for topic, msgtype, raw in topics]
        for conn, raw in conns:
            if raw is not None:
                writer.write(conn, 0, raw)


def test_missing_topic(tmp_path):
    bag = tmp_path / 'nocmd'
    _write_bag(bag, [('/stage/position', JS, _js(0, [0.0])),
                     ('/stage/reference', JS, _js(0, [0.0], [0.0])),
                     ('/other/command', F64, _f64(1.0))])
    with pytest.raises(BagError, match=r'nocmd: no stage topics found'):
        read_run(bag)
    with pytest.raises(BagError, match=r'nocmd: topic /stage/command is missing'):
        read_run(bag, namespace='/stage')


def test_empty_bag(tmp_path):
    bag = tmp_path / 'empty'
    write_run(make_record(n=0), bag)
    with pytest.raises(BagError, match=r'empty: bag is empty \(no messages\)'):
        read_run(bag)


def test_required_topic_without_messages(tmp_path):
    bag = tmp_path / 'silent'
    _write_bag(bag, [(f'/stage/{k}', wire.BAG_TOPICS[k], raw) for k, raw in (
        ('position', _js(0, [0.0])), ('reference', _js(0, [0.0], [0.0])), ('command', None))])
    with pytest.raises(BagError, match=r'silent: topic /stage/command has no messages'):
        read_run(bag)


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_truncated_file(tmp_path, storage):
    bag = _copy(tmp_path, storage)
    file = _storage_file(bag)
    data = file.read_bytes()
    file.write_bytes(data[:len(data) // 2])
    with pytest.raises(BagError, match=f'bag_{storage}: '):
        read_run(bag)


def test_corrupt_mcap_chunk(tmp_path):
    bag = _copy(tmp_path)
    file = _storage_file(bag)
    data = bytearray(file.read_bytes())
    # Overwrite record headers in the middle of the first chunk with garbage lengths.
    middle = 300_000
    data[middle:middle + 4096] = b'\xff' * 4096
    file.write_bytes(bytes(data))
    with pytest.raises(BagError, match=r'bag_mcap: (corrupt|cannot)'):
        read_run(bag)


def test_corrupt_sqlite_file(tmp_path):
    bag = _copy(tmp_path, 'sqlite3')
    file = _storage_file(bag)
    file.write_bytes(b'this is not a database' * 1000)
    with pytest.raises(BagError, match=r'bag_sqlite3: cannot open it'):
        read_run(bag)


def test_unknown_storage_format(tmp_path):
    bag = _copy(tmp_path, n=10)
    meta = bag / 'metadata.yaml'
    meta.write_text(meta.read_text().replace('storage_identifier: mcap',
                                             'storage_identifier: hdf5'))
    with pytest.raises(BagError, match=r"bag_mcap: cannot open it: Storage plugin 'hdf5' not"):
        read_run(bag)


def test_wrong_type_on_known_topic(tmp_path):
    bag = tmp_path / 'wrongtype'
    _write_bag(bag, [('/stage/position', F64, _f64(1.0)),
                     ('/stage/reference', JS, _js(0, [0.0], [0.0])),
                     ('/stage/command', F64, _f64(1.0))])
    match = (r'wrongtype: topic /stage/position has type std_msgs/msg/Float64, '
             r'expected sensor_msgs/msg/JointState')
    with pytest.raises(BagError, match=match):
        read_run(bag)


@pytest.mark.parametrize('make, match', [
    (lambda p: p, 'does not exist'),
    (lambda p: (p.mkdir(), p)[1], r'not a rosbag2 bag \(no metadata.yaml\)'),
    (lambda p: (p.write_text('hello'), p)[1], 'cannot open it'),
])
def test_not_a_bag(tmp_path, make, match):
    path = make(tmp_path / 'thing')
    with pytest.raises(BagError, match=f'bag {tmp_path / "thing"}: {match}'):
        read_run(path)


def test_metadata_garbage(tmp_path):
    bag = _copy(tmp_path, n=10)
    (bag / 'metadata.yaml').write_text('rosbag2_bagfile_information: [1, 2\n')
    with pytest.raises(BagError, match='bag_mcap: cannot open it'):
        read_run(bag)


def test_missing_storage_file(tmp_path):
    bag = _copy(tmp_path, n=10)
    shutil.move(_storage_file(bag), tmp_path / 'elsewhere.mcap')
    with pytest.raises(BagError, match='bag_mcap: cannot open it: Some database files are'):
        read_run(bag)


def test_single_storage_file_is_accepted(tmp_path):
    bag = _copy(tmp_path, n=10)
    rec = read_run(_storage_file(bag))
    assert len(rec) == 10


@pytest.mark.parametrize('diagnostics, true_position', [(False, False), (True, False),
                                                        (True, True)])
@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_bulk_writing_gives_the_same_bag_as_writer_write(tmp_path, storage, diagnostics,
                                                         true_position):
    # The bulk path appends to rosbags' storage writer itself; it must produce exactly what
    # one Writer.write per message produces (same chunks, same index, same bytes).
    # MCAP: enough samples for several 1 MiB chunks; sqlite3 has no chunks.
    n = 16000 if storage == 'mcap' else 2000
    rec = make_record(n=n, diagnostics=diagnostics, true_position=true_position)
    files = []
    for bulk in (True, False):
        bag = tmp_path / ('bulk' if bulk else 'each') / 'run'
        with RunBagWriter(bag, storage=storage, meta=rec.meta, bulk=bulk) as writer:
            # Uneven pieces: chunk boundaries fall inside pieces and inside samples.
            for lo, hi in ((0, 777), (777, n // 2), (n // 2, n // 2 + 1), (n // 2 + 1, n)):
                sl = slice(lo, hi)
                true = rec.true_position_m
                writer.write_samples(rec.time_s[sl], rec.position_m[sl], rec.reference_m[sl],
                                     rec.reference_velocity_mps[sl], rec.command_v[sl],
                                     diagnostics={k: v[sl] for k, v in rec.diagnostics.items()},
                                     true_position_m=None if true is None else true[sl])
        files.append(_storage_file(bag))
        assert_same_run(rec, read_run(bag))
    if storage == 'mcap':
        assert files[0].stat().st_size > 3 * 2**20  # several chunks
        assert files[0].read_bytes() == files[1].read_bytes()
    else:
        import sqlite3

        def rows(file):
            with sqlite3.connect(file) as con:
                return con.execute('SELECT topic_id, timestamp, data FROM messages '
                                   'ORDER BY id').fetchall()
        assert rows(files[0]) == rows(files[1])
    assert (files[0].parent / 'metadata.yaml').read_text() == (
        files[1].parent / 'metadata.yaml').read_text()


def test_irregular_records_in_chunks(tmp_path):
    # A foreign topic now and then breaks the repeating record pattern the reader predicts;
    # every sample must still come back exactly.
    bag = tmp_path / 'irregular'
    rng = np.random.default_rng(3)
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {key: writer.add_connection(f'/stage/{key}', wire.BAG_TOPICS[key],
                                            typestore=STORE)
                 for key in ('position', 'reference', 'command')}
        other = writer.add_connection('/other', F64, typestore=STORE)
        for k in range(8000):
            t = k * 100_000
            writer.write(conns['position'], t, _js(t, [k * 1e-9]))
            if k % 777 == 5:
                writer.write(other, t, _f64(-1.0))
            writer.write(conns['reference'], t, _js(t, [k * 2e-9], [float(k)]))
            if rng.random() < 0.003:
                writer.write(conns['reference'], t, _js(t, [k * 2e-9], [float(k)],
                                                        frame_id='x' * (k % 13)))
            writer.write(conns['command'], t, _f64(k * 0.5))
    rec = read_run(bag)
    assert len(rec) == 8000
    k = np.arange(8000)
    # bit for bit: the bag holds the very products k * 1e-9 ... written above (no arithmetic)
    np.testing.assert_array_equal(rec.position_m, k * 1e-9)
    np.testing.assert_array_equal(rec.reference_m, k * 2e-9)
    np.testing.assert_array_equal(rec.reference_velocity_mps, k.astype(float))
    np.testing.assert_array_equal(rec.command_v, k * 0.5)


def test_unstamped_messages_are_refused(tmp_path):
    bag = tmp_path / 'nostamp'
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {key: writer.add_connection(f'/stage/{key}', wire.BAG_TOPICS[key],
                                            typestore=STORE)
                 for key in ('position', 'reference', 'command')}
        for k in range(100):
            writer.write(conns['position'], k * 1000, _js(0, [0.0]))
            writer.write(conns['reference'], k * 1000, _js(k * 1000, [0.0], [0.0]))
            writer.write(conns['command'], k * 1000, _f64(0.0))
    with pytest.raises(BagError, match=r'nostamp: topic /stage/position has 100 messages but '
                                       r'only 1 distinct header stamps'):
        read_run(bag)


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_random_damage_gives_a_bag_error_or_a_run(tmp_path, storage):
    # Flipped bytes, overwritten blocks and cut files: read_run either reads a run or raises
    # BagError, never anything else (rosbags writes no CRCs, so damage inside values can go
    # unnoticed; that is the format, not the reader).
    bag = _copy(tmp_path, storage, n=1000)
    file = _storage_file(bag)
    original = file.read_bytes()
    rng = np.random.default_rng(11)
    outcomes = set()
    for trial in range(15):
        data = bytearray(original)
        if trial % 3 == 0:
            for _ in range(int(rng.integers(1, 20))):
                data[int(rng.integers(0, len(data)))] = int(rng.integers(0, 256))
        elif trial % 3 == 1:
            at = int(rng.integers(0, len(data)))
            data[at:at + int(rng.integers(1, 5000))] = b'\x00'
        else:
            data = data[:int(rng.integers(0, len(data)))]
        file.write_bytes(bytes(data))
        try:
            read_run(bag)
            outcomes.add('run')
        except BagError as err:
            assert str(err).startswith(f'bag {bag}: ')
            outcomes.add('error')
    assert 'error' in outcomes


def test_record_qos_file_covers_every_topic():
    # config/record_qos.yaml is what `ros2 bag record` (and the launch file) use: it must name
    # every topic the nodes store a run on (not the simulation-only ones, which only the
    # offline runner writes), reliably and with at least 0.1 s of queue at 10 kHz.
    import yaml
    path = Path(__file__).resolve().parents[1] / 'config' / 'record_qos.yaml'
    profiles = yaml.safe_load(path.read_text())
    assert set(profiles) == {topic for key, topic in wire.topic_names('/stage').items()
                             if key not in wire.SIMULATION_TOPICS} | {wire.block_topic('/stage')}
    for profile in profiles.values():
        assert profile['reliability'] == 'reliable'
        assert profile['history'] == 'keep_last' and profile['depth'] >= 1000
        assert profile['durability'] == 'volatile'


@pytest.mark.parametrize('command_delay_us, next_position_us, expected', [
    (95, 100, 0),     # lockstep: sample k+1 follows command k by 5 us, closer than sample k
    (33, 1000, 0),    # the Jazzy recorder bags: command published just after the position
    (0, 100, 0),      # bags the package writes: log time = stamp on every topic
])
def test_commands_pair_with_the_position_they_answer(command_delay_us, next_position_us,
                                                     expected):
    k = np.arange(2000, dtype=np.int64)
    rng = np.random.default_rng(0)
    position_ns = k * next_position_us * 1000
    command_ns = position_ns + command_delay_us * 1000 + rng.integers(0, 3000, k.size)
    offset, median_ns = bagread._command_offset(position_ns, np.sort(command_ns))
    assert offset == expected
    assert median_ns >= 0.0
