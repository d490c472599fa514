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

"""The block topic (stage/block): its bytes, its bags, and analyze/identify on block-only bags."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
from piezo_stage_ros.analysis.bagread import read_run
from piezo_stage_ros.analysis.bagwrite import RunBagWriter, write_run
from piezo_stage_ros.analysis.replay import analyze_bag
from piezo_stage_ros.analyze import main as analyze_main
from piezo_stage_ros.core.contracts import cdr, wire
from piezo_stage_ros.core.contracts.errors import BagError
from piezo_stage_ros.core.identification.experiments import perturbed_stage, run_experiments
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.identify import main as identify_main
from piezo_stage_ros.simulate import main as simulate_main
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

STORE = get_typestore(Stores.ROS2_JAZZY)
T = STORE.types
FMA = wire.BLOCK_TYPE


def make_record(n: int = 2345, diagnostics: bool = True, true_position: bool = True
                ) -> RunRecord:
    k = np.arange(n)
    t = 0.25 + k * 1e-4
    rng = np.random.default_rng(11)
    diag = {'theta_hat': 1.29 + 1e-3 * np.sin(k / 50.0), 'phi_hat': 3.2e-4 + 1e-6 * k,
            'saturated': (k % 7 == 0).astype(float)} if diagnostics else {}
    ref = 10e-6 + 5e-6 * np.sin(2 * np.pi * 5 * t)
    return RunRecord(
        time_s=t, position_m=ref + rng.normal(0, 1e-9, n), reference_m=ref,
        reference_velocity_mps=5e-6 * 2 * np.pi * 5 * np.cos(2 * np.pi * 5 * t),
        command_v=2.0 + 1.5 * np.sin(2 * np.pi * 5 * t) + rng.normal(0, 1e-3, n),
        diagnostics=diag, meta={'controller': 'rac', 'trajectory_period_s': 0.2},
        true_position_m=ref + rng.normal(0, 1e-10, n) if true_position else None)


def reference_block(columns, rows, little_endian=True):
    dim = T['std_msgs/msg/MultiArrayDimension']
    n, c = rows.shape
    msg = T[FMA](layout=T['std_msgs/msg/MultiArrayLayout'](
        dim=[dim(label='samples', size=n, stride=n * c),
             dim(label=','.join(columns), size=c, stride=c)], data_offset=0),
        data=np.ascontiguousarray(rows, dtype=np.float64).ravel())
    return bytes(STORE.serialize_cdr(msg, FMA, little_endian=little_endian))


def assert_same_samples(a: RunRecord, b: RunRecord) -> None:
    # bit for bit: both paths carry the float64 samples and the integer stamps as they are
    for name in ('time_s', 'position_m', 'reference_m', 'reference_velocity_mps', 'command_v',
                 'true_position_m'):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=name)
    assert list(a.diagnostics) == list(b.diagnostics)
    for key in a.diagnostics:
        np.testing.assert_array_equal(a.diagnostics[key], b.diagnostics[key], err_msg=key)


# --- layout and bytes ---------------------------------------------------------------------


@pytest.mark.parametrize('applied, true_position, keys', [
    (False, False, ()), (True, False, ('theta_hat', 'phi_hat')), (True, True, ('s',)),
    (False, True, ())])
def test_block_bytes_equal_the_reference_and_round_trip(applied, true_position, keys):
    columns = wire.block_columns(applied=applied, true_position=true_position, diagnostics=keys)
    assert columns[:len(wire.BLOCK_COLUMNS)] == wire.BLOCK_COLUMNS
    rows = np.random.default_rng(3).normal(size=(37, len(columns)))
    rows[5, -1] = np.nan
    ours = cdr.encode_block(columns, rows)
    assert ours == reference_block(columns, rows)
    for raw in (ours, reference_block(columns, rows, little_endian=False)):
        names, back = cdr.decode_block(raw)
        assert names == columns
        np.testing.assert_array_equal(back, rows)
    parsed = wire.parse_block_columns(','.join(columns))
    assert parsed.diagnostics == tuple(sorted(keys))
    assert (parsed.applied >= 0) == applied and (parsed.true_position >= 0) == true_position


def test_empty_block_round_trips():
    columns = wire.block_columns()
    raw = cdr.encode_block(columns, np.zeros((0, len(columns))))
    assert raw == reference_block(columns, np.zeros((0, len(columns))))
    assert cdr.decode_block(raw)[1].shape == (0, len(columns))


@pytest.mark.parametrize('label', [
    'stamp_sec,sample', 'sample,stamp_sec', ','.join(wire.BLOCK_COLUMNS) + ',speed',
    ','.join(wire.BLOCK_COLUMNS) + ',diagnostics.b,diagnostics.a',
    ','.join(wire.BLOCK_COLUMNS) + ',true_position_m,applied_v'])
def test_bad_column_labels_are_refused(label):
    with pytest.raises(BagError, match='block columns'):
        wire.parse_block_columns(label)


@pytest.mark.parametrize('axes, applied, true_position, keys', [
    (('x', 'y'), False, True, ('x.theta_hat', 'y.theta_hat')), (('x', 'y', 'z'), True, False, ()),
    (('y',), True, True, ('y.s',))])
def test_a_block_of_several_axes_round_trips_and_names_each_axis(axes, applied, true_position,
                                                                  keys):
    columns = wire.axes_block_columns(axes, applied=applied, true_position=true_position,
                                      diagnostics=keys)
    own = wire.AXES_BLOCK_OWN + tuple(name for name, on in zip(wire.BLOCK_OPTIONAL,
                                                               (applied, true_position)) if on)
    assert columns == (wire.AXES_BLOCK_SHARED + tuple(f'{a}.{c}' for a in axes for c in own)
                       + tuple(f'diagnostics.{k}' for k in keys))
    rows = np.random.default_rng(4).normal(size=(11, len(columns)))
    names, back = cdr.decode_block(cdr.encode_block(columns, rows))
    assert names == columns
    np.testing.assert_array_equal(back, rows)
    label = ','.join(columns)
    assert wire.is_axes_block(label) and not wire.is_axes_block(','.join(wire.block_columns()))
    parsed = wire.parse_axes_block_columns(label)
    assert (parsed.axes, parsed.applied, parsed.true_position, parsed.diagnostics) == \
        (axes, applied, true_position, keys)
    assert columns[parsed.column(axes[-1], 'command_v')] == f'{axes[-1]}.command_v'
    # a reader of one axis refuses it by name rather than read one axis of it
    with pytest.raises(BagError, match='a block of several axes.*read_axes'):
        wire.parse_block_columns(label)


@pytest.mark.parametrize('label', [
    'sample,stamp_sec,stamp_nanosec,x.position_m',                    # an axis' columns cut
    'sample,stamp_sec,stamp_nanosec,x.position_m,x.reference_m,x.velocity_mps,x.command_v,'
    'y.position_m,y.reference_m,y.velocity_mps,y.command_v,y.applied_v',  # applied on y only
    'sample,stamp_sec,stamp_nanosec,x.position_m,x.reference_m,x.velocity_mps,x.command_v,'
    'x.position_m,x.reference_m,x.velocity_mps,x.command_v',           # an axis twice
    'sample,stamp_nanosec,stamp_sec,x.position_m,x.reference_m,x.velocity_mps,x.command_v'])
def test_bad_columns_of_several_axes_are_refused(label):
    with pytest.raises(BagError, match='block columns'):
        wire.parse_axes_block_columns(label)


@pytest.mark.parametrize('key', ['a,b', 'a b', ''])
def test_diagnostic_keys_that_cannot_name_a_column_are_refused(key):
    with pytest.raises(BagError, match='cannot name a block column'):
        wire.block_columns(diagnostics=[key])


def test_other_multi_arrays_are_not_blocks():
    columns = wire.block_columns()
    rows = np.ones((3, len(columns)))
    good = cdr.encode_block(columns, rows)
    assert cdr.decode_block(good)[1].shape == (3, len(columns))
    with pytest.raises(cdr.CdrError, match='not a block layout'):
        cdr.decode_block(cdr.encode_multi_array([('rows', 3, 21), (','.join(columns), 7, 7)],
                                                rows))
    with pytest.raises(cdr.CdrError, match='dense row-major'):
        cdr.decode_block(cdr.encode_multi_array([('samples', 3, 99), (','.join(columns), 7, 7)],
                                                rows))
    with pytest.raises(cdr.CdrError, match='truncated'):
        cdr.decode_block(good[:-9])


# --- bags ---------------------------------------------------------------------------------


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
@pytest.mark.parametrize('block_samples', [100, 7, 5000])
def test_block_bag_reads_the_same_samples_as_the_per_sample_bag(tmp_path, storage,
                                                                block_samples):
    rec = make_record()
    write_run(rec, tmp_path / 'samples', storage=storage)
    write_run(rec, tmp_path / 'block', storage=storage, topics='block',
              block_samples=block_samples)
    write_run(rec, tmp_path / 'both', storage=storage, topics='both',
              block_samples=block_samples)
    per_sample, block, both = (read_run(tmp_path / name)
                               for name in ('samples', 'block', 'both'))
    assert_same_samples(per_sample, block)
    assert_same_samples(per_sample, both)
    align = block.meta['alignment']
    assert align['source'] == 'block' and both.meta['alignment']['source'] == 'block'
    assert align['missing_samples'] == 0 and align['samples'] == rec.time_s.size
    assert align['block_messages'] == -(-rec.time_s.size // block_samples)
    assert per_sample.meta['alignment'].get('source') is None
    assert block.meta['controller'] == 'rac'


def test_block_bag_topics_and_log_times(tmp_path):
    rec = make_record(n=250, diagnostics=False, true_position=False)
    write_run(rec, tmp_path / 'b', topics='block', block_samples=100)
    with Reader(tmp_path / 'b') as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == {'/stage/block': FMA}
        messages = [(log, STORE.deserialize_cdr(data, FMA))
                    for _, log, data in reader.messages()]
    # each block is logged at the stamp of its last row; rosbags' own deserializer reads it
    stamps = np.rint(rec.time_s * 1e9).astype(np.int64)
    assert [log for log, _ in messages] == [stamps[99], stamps[199], stamps[249]]
    last = messages[-1][1]
    assert [d.size for d in last.layout.dim] == [50, 7]
    rows = last.data.reshape(50, 7)
    np.testing.assert_array_equal(rows[:, 0], np.arange(200, 250))
    np.testing.assert_array_equal(rows[:, 1] * 1e9 + rows[:, 2], stamps[200:])
    np.testing.assert_array_equal(rows[:, 3], rec.position_m[200:])


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_bulk_block_bag_equals_writer_write(tmp_path, storage):
    # the blocks go through the bulk writer too: the same bytes as one Writer.write each
    # (MCAP: enough samples for several 1 MiB chunks)
    rec = make_record(n=16000 if storage == 'mcap' else 1234)
    files = []
    for bulk in (True, False):
        bag = tmp_path / ('bulk' if bulk else 'each') / 'run'
        with RunBagWriter(bag, storage=storage, topics='both', block_samples=50,
                          meta=rec.meta, bulk=bulk) as writer:
            writer.write_chunk(rec)
        files.append(next(p for p in bag.iterdir() if p.suffix in ('.mcap', '.db3')))
        assert_same_samples(read_run(bag), read_run(tmp_path / 'bulk' / 'run'))
    if storage == 'mcap':
        assert files[0].stat().st_size > 3 * 2**20
        assert files[0].read_bytes() == files[1].read_bytes()
    assert (files[0].parent / 'metadata.yaml').read_text() == (
        files[1].parent / 'metadata.yaml').read_text()


def test_streamed_chunks_give_the_same_blocks_as_one_write(tmp_path):
    rec = make_record(n=1000)
    write_run(rec, tmp_path / 'one' / 'run', topics='block', block_samples=64)
    with RunBagWriter(tmp_path / 'chunks' / 'run', topics='block', block_samples=64,
                      meta=rec.meta) as writer:
        for lo, hi in ((0, 10), (10, 333), (333, 334), (334, 1000)):
            writer.write_chunk(RunRecord(
                rec.time_s[lo:hi], rec.position_m[lo:hi], rec.reference_m[lo:hi],
                rec.reference_velocity_mps[lo:hi], rec.command_v[lo:hi],
                {k: v[lo:hi] for k, v in rec.diagnostics.items()}, rec.meta,
                rec.true_position_m[lo:hi]))
    assert (tmp_path / 'one' / 'run' / 'run.mcap').read_bytes() == \
        (tmp_path / 'chunks' / 'run' / 'run.mcap').read_bytes()


def _write_blocks(path: Path, blocks, topic='/stage/block'):
    # a bag as a recorder holds it: whatever blocks came, in the order given
    with Writer(path, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection(topic, FMA, typestore=STORE)
        for i, (columns, rows) in enumerate(blocks):
            w.write(conn, 1000 + i, cdr.encode_block(columns, rows))


def _rows(numbers, columns, t0_ns=1_600_000_000_000_000_000, extra=None):
    numbers = np.asarray(numbers)
    stamps = t0_ns + numbers * 100_000
    rows = np.zeros((numbers.size, len(columns)))
    rows[:, 0] = numbers
    rows[:, 1], rows[:, 2] = np.divmod(stamps, 1_000_000_000)
    rows[:, 3] = numbers * 1e-9
    rows[:, 4] = numbers * 1e-9 + 1e-10
    rows[:, 6] = 1.0 + numbers * 1e-3
    for j in range(7, len(columns)):
        rows[:, j] = (extra if extra is not None else 0.5) + numbers
    return rows


def test_a_lost_block_is_counted_and_a_repeated_one_counted_once(tmp_path):
    columns = wire.block_columns()
    blocks = [(columns, _rows(range(0, 100), columns)),
              (columns, _rows(range(200, 300), columns)),   # 100..199 never came
              (columns, _rows(range(200, 300), columns)),   # republished
              (columns, _rows(range(300, 350), columns))]
    _write_blocks(tmp_path / 'b', blocks)
    rec = read_run(tmp_path / 'b', relative_time=True)
    align = rec.meta['alignment']
    assert align['samples'] == 250 and align['missing_samples'] == 100
    assert align['dropped_duplicate'] == 100
    assert any('100 samples missing' in w for w in align['warnings'])
    np.testing.assert_array_equal(rec.time_s[:3], [0.0, 1e-4, 2e-4])
    # exact stamps although t is 1.6e9 s (two integer columns, not one float)
    assert rec.meta['time_origin_ns'] == 1_600_000_000_000_000_000


def test_applied_input_and_a_change_of_diagnostics_between_blocks(tmp_path):
    first = wire.block_columns(applied=True, diagnostics=('a',))
    second = wire.block_columns(applied=True, diagnostics=('b', 'c'))
    rows1, rows2 = _rows(range(0, 10), first), _rows(range(10, 20), second, extra=100.0)
    rows2[-1, 7] = np.nan  # the last applied input is not known yet
    _write_blocks(tmp_path / 'b', [(first, rows1), (second, rows2)])
    rec = read_run(tmp_path / 'b')
    assert rec.meta['alignment']['command_source'] == 'applied'
    np.testing.assert_array_equal(rec.command_v[:10], rows1[:, 7])
    assert np.isnan(rec.command_v[-1])
    assert list(rec.diagnostics) == ['a', 'b', 'c']
    np.testing.assert_array_equal(rec.diagnostics['a'][:10], rows1[:, 8])
    assert np.isnan(rec.diagnostics['a'][10:]).all() and np.isnan(rec.diagnostics['b'][:10]).all()
    assert any('1 of 20 samples have no applied input' in w
               for w in rec.meta['alignment']['warnings'])


@pytest.mark.parametrize('damage, match', [
    (lambda rows: rows.__setitem__((0, 2), 0.5), 'not a whole number'),
    (lambda rows: rows.__setitem__((1, 1), np.nan), 'not a whole number'),
    (lambda rows: rows.__setitem__((1, 2), 1e9), 'not a whole number')])
def test_bad_stamps_in_a_block_are_refused(tmp_path, damage, match):
    columns = wire.block_columns()
    rows = _rows(range(5), columns)
    damage(rows)
    _write_blocks(tmp_path / 'b', [(columns, rows)])
    with pytest.raises(BagError, match=match):
        read_run(tmp_path / 'b')


def test_a_block_topic_of_garbage_is_a_bag_error(tmp_path):
    with Writer(tmp_path / 'b', version=Writer.VERSION_LATEST,
                storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection('/stage/block', FMA, typestore=STORE)
        w.write(conn, 1, cdr.encode_multi_array([('x', 2, 2)], np.ones(2)))
    with pytest.raises(BagError, match='cannot be decoded as a block'):
        read_run(tmp_path / 'b')


def test_bad_writer_options_are_refused(tmp_path):
    with pytest.raises(BagError, match="topics 'all' is not supported"):
        RunBagWriter(tmp_path / 'x', topics='all')
    with pytest.raises(BagError, match='block_samples = 0'):
        RunBagWriter(tmp_path / 'x', block_samples=0)


# --- analyze, identify, simulate on block-only bags ---------------------------------------


def test_analyze_gives_the_same_figures_from_a_block_only_bag(tmp_path, capsys):
    rec = make_record(n=6000)
    write_run(rec, tmp_path / 'samples')
    write_run(rec, tmp_path / 'block', topics='block')
    a, b = analyze_bag(tmp_path / 'samples'), analyze_bag(tmp_path / 'block')
    assert a.metrics == b.metrics
    assert analyze_main(['--json', '-q', str(tmp_path / 'samples'),
                         str(tmp_path / 'block')]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    for line in lines:
        line.pop('bag')
    assert lines[0] == lines[1]


def test_identify_gives_the_same_model_from_block_only_bags(tmp_path):
    true, _ = perturbed_stage(5)
    records = run_experiments(true)
    for topics in ('samples', 'block'):
        for name, rec in records.items():
            bare = RunRecord(rec.time_s, rec.position_m, rec.reference_m,
                             rec.reference_velocity_mps, rec.command_v, meta={'name': name})
            write_run(bare, tmp_path / topics / name, topics=topics)
        argv = [str(tmp_path / topics / name) for name in records]
        with contextlib.redirect_stdout(io.StringIO()):
            assert identify_main(argv + ['--output', str(tmp_path / f'{topics}.yaml'),
                                         '--report', str(tmp_path / f'{topics}_report')]) == 0

    def body(name):
        # the first line names the command and its bags
        return (tmp_path / name).read_text(encoding='utf8').splitlines()[1:]
    assert body('samples.yaml') == body('block.yaml')


def test_simulate_writes_a_block_bag_that_analyze_reads_as_the_per_sample_one(tmp_path,
                                                                              capsys):
    base = ['--duration', '0.05', '--json']
    assert simulate_main(base + ['--bag', str(tmp_path / 's')]) == 0
    assert simulate_main(base + ['--bag', str(tmp_path / 'b'), '--bag-topics', 'block']) == 0
    capsys.readouterr()
    with Reader(tmp_path / 'b') as reader:
        assert [c.topic for c in reader.connections] == ['/stage/block']
    assert_same_samples(read_run(tmp_path / 's'), read_run(tmp_path / 'b'))
    assert analyze_bag(tmp_path / 's').metrics == analyze_bag(tmp_path / 'b').metrics
