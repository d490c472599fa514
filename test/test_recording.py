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
The recording path of a real-time loop (nodes/recording.py), on a scripted clock.

The servo serves samples on a fake clock; a scripted executor takes them in batches (small
ones, and a large one after a stall of its own), hands them to :class:`Handover` as the plant
node does, and the block messages go into a real bag in ``tmp_path`` that ``read_run`` reads.
"""

from __future__ import annotations

import math

from fake_clock import FakeClock
import numpy as np
from piezo_stage_ros import cli
from piezo_stage_ros.analysis.bagread import read_axes, read_run
from piezo_stage_ros.core.config.axes import axes_loop_config
from piezo_stage_ros.core.config.nodes import RecordingParams
from piezo_stage_ros.core.contracts import cdr, wire
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.stage import StageParams
from piezo_stage_ros.hardware.bridge import ModelBridge
from piezo_stage_ros.hardware.pacing import Pacer
from piezo_stage_ros.hardware.safety import GuardedPlant
from piezo_stage_ros.nodes.logic import ControllerLogic, run_verdict, TrajectoryLogic
from piezo_stage_ros.nodes.recording import (
    AxesBlockRecorder,
    backlog_samples,
    BlockRecorder,
    Handover,
    live_share,
    SampleBatch,
)
from piezo_stage_ros.nodes.servo import (
    batch_of,
    SampleRing,
    samples_of,
    ServoLoop,
    ServoSample,
)
from piezo_stage_ros.nodes.servo_axes import axes_servo_from_config
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

PERIOD = 100_000  # ns, 10 kHz
STORE = get_typestore(Stores.ROS2_JAZZY)
T0 = 1_700_000_000_123_456_700  # stamps since the epoch: must stay exact


def servo(duration_s: float, diagnostics_every: int = 10) -> tuple[ServoLoop, FakeClock]:
    clock = FakeClock(per_read=300)
    params = StageParams.from_flat({'plant.model': 'reduced', 'chain.sensor_noise_std_m': 1e-9,
                                    'seed': 3})
    ctrl = build_controller(ControllerParams.from_flat({'type': 'rac'}), 1e-4)
    traj = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine',
                                                       'sine.frequency_hz': 50.0}))
    loop = ServoLoop(GuardedPlant(ModelBridge(params), params.chain, 0.01),
                     TrajectoryLogic(traj, sample_rate_hz=1e4, chunk_s=1.0),
                     ControllerLogic(ctrl, mode='realtime', diagnostics_every=diagnostics_every),
                     sample_rate_hz=1e4, duration_s=duration_s, capacity=100_000,
                     pacer=Pacer(PERIOD, clock=clock, sleep=clock.sleep))
    return loop, clock


def write_blocks(path, messages):
    # the bag a recorder of stage/block holds: each message as it came
    with Writer(path, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection('/stage/block', wire.BLOCK_TYPE, typestore=STORE)
        for i, raw in enumerate(messages):
            w.write(conn, T0 + i, raw)


def test_live_share_leaves_out_the_oldest_beyond_the_limit():
    assert [live_share(n, 1000) for n in (0, 20, 1000, 1001, 50_000)] == [0, 0, 0, 1, 49_000]
    assert live_share(5, 0) == 4  # at least the newest sample goes out


def test_the_recording_parameters_size_the_ring_and_the_live_share():
    recording = RecordingParams(backlog_s=10.0, live_backlog_s=0.1, block_samples=50)
    assert backlog_samples(recording, 1e4) == 100_000  # 10 s at 10 kHz
    assert backlog_samples(RecordingParams(backlog_s=0.01), 10.0) == 1
    handover = Handover.from_params(recording, 1e4)
    assert handover.live_limit == 1000 and handover.blocks.block_samples == 50
    with pytest.raises(ParameterError, match='live_backlog_s'):
        RecordingParams(live_backlog_s=0.0)


def test_batch_columns_give_back_the_samples():
    loop, _ = servo(0.01)
    loop.run(start_ns=T0)
    items = list(loop.samples)
    batch = batch_of(items)
    assert batch.number.tolist() == list(range(100))
    got = samples_of(batch)
    assert got == [s for _, s in items]  # every field, diagnostics and names included
    assert samples_of(batch, 95) == [s for _, s in items[95:]]


def test_scripted_overload_per_sample_topics_drop_but_the_blocks_keep_every_sample(tmp_path):
    # 1 s of servo samples; the executor comes every 2 ms (20 samples), except once when it
    # stalls for 0.6 s: 6 000 samples wait, more than the per-sample topics may publish at once
    loop, _ = servo(1.0)
    served = []
    loop.on_sample = served.append
    handover = Handover(block_samples=100, live_limit=1000)
    messages, published, stamps_published = [], 0, []
    loop.start(start_ns=T0)
    batches = 0
    while True:
        going = loop.step()
        waiting = len(loop.samples)
        if waiting >= (6000 if batches == 10 else 20) or not going:
            batch = loop.take_batch()
            batches += 1
            done, first = handover.take(batch)
            messages += done
            live = samples_of(batch, first)
            published += len(live)
            stamps_published += [s.stamp_ns for s in live]
        if not going:
            break
    messages += handover.finish(loop.held_v)
    n = len(served)
    assert n == 10_000 and loop.stats()['queue_overruns'] == 0
    # the per-sample topics left out the oldest 5 000 of the large batch, and said so
    assert handover.live_dropped == 5000 and published == n - 5000
    assert stamps_published == sorted(stamps_published)
    stats = handover.stats()
    assert stats == {'live_dropped': 5000, 'block_messages': 100, 'block_samples': n}
    level, reasons = run_verdict(stats)
    assert level == 'warn' and any('5000 left out of the per-sample topics' in r
                                   for r in reasons)
    # the blocks hold every sample, exactly
    write_blocks(tmp_path / 'bag', messages)
    rec = read_run(tmp_path / 'bag', relative_time=True)
    align = rec.meta['alignment']
    assert align['samples'] == n and align['missing_samples'] == 0 and not align['warnings']
    # stamps since the epoch, exact: the times from the first one, in integer nanoseconds
    stamps = np.array([s.stamp_ns for s in served], dtype=np.int64)
    np.testing.assert_array_equal(rec.time_s, (stamps - stamps[0]) / 1e9)
    assert rec.meta['time_origin_ns'] == served[0].stamp_ns
    np.testing.assert_array_equal(rec.position_m, [s.position_m for s in served])
    np.testing.assert_array_equal(rec.reference_m, [s.reference_m for s in served])
    np.testing.assert_array_equal(rec.reference_velocity_mps, [s.velocity_mps for s in served])
    # the command of a block bag is the input held over [t_k, t_k+1): what sample k+1 says the
    # plant held, and for the last sample what it held until the stop
    np.testing.assert_array_equal(rec.command_v[:-1], [s.applied_v for s in served[1:]])
    assert rec.command_v[-1] == loop.held_v
    # the model backend passes each command through: the applied input is the command
    np.testing.assert_array_equal(rec.command_v, [s.command_v for s in served])
    # the servo on the model knows the true position behind each y_k, and the blocks carry it
    truth = np.array([s.true_position_m for s in served])
    assert np.isfinite(truth).all() and not np.array_equal(truth, rec.position_m)
    np.testing.assert_array_equal(rec.true_position_m, truth)
    # diagnostics every 10th sample, NaN in between, named as the controller names them
    with_diag = [i for i, s in enumerate(served) if s.diagnostics is not None]
    assert len(with_diag) == n // 10
    names = served[with_diag[0]].diagnostic_names
    assert sorted(rec.diagnostics) == sorted(names)
    for j, name in enumerate(names):
        values = rec.diagnostics[name]
        np.testing.assert_array_equal(values[with_diag],
                                      [served[i].diagnostics[j] for i in with_diag])
        assert np.isnan(np.delete(values, with_diag)).all()


def test_samples_the_ring_overwrote_show_as_missing_in_the_bag(tmp_path):
    # the servo process's ring: a reader that came too late misses the oldest rows; their
    # numbers are a gap in the blocks, counted by read_run, and the sample before the gap has
    # no known applied input
    ring = SampleRing(capacity=64, diagnostics=2)
    reader = SampleRing(capacity=64, name=ring.name, diagnostics=2)
    try:
        handover = Handover(block_samples=25, live_limit=10)
        messages = []

        def serve(ks):
            for k in ks:
                ring.append(ServoSample(k, T0 + k * PERIOD, 1e-9 * k, 2e-9 * k, 0.0, 0.1 * k,
                                        0.1 * (k - 1), 0, None))

        def take():
            start, ints, floats, missed = reader.take_numbered()
            batch = SampleBatch(np.arange(start, start + ints.shape[0]), ints, floats, {})
            messages.extend(handover.take(batch)[0])
            return missed

        serve(range(0, 50))
        assert take() == 0
        serve(range(50, 150))  # 100 rows into 64: the 36 oldest are gone
        assert take() == 36
        serve(range(150, 170))
        assert take() == 0
        messages.extend(handover.finish(0.1 * 169))
    finally:
        reader.close()
        ring.close(unlink=True)
    write_blocks(tmp_path / 'bag', messages)
    rec = read_run(tmp_path / 'bag')
    align = rec.meta['alignment']
    assert align['missing_samples'] == 36 and align['samples'] == 170 - 36
    assert any('36 samples missing' in w for w in align['warnings'])
    assert np.isnan(rec.command_v[49]) and np.isnan(rec.command_v).sum() == 1
    assert rec.true_position_m is None  # a backend without one: no column
    np.testing.assert_array_equal(rec.command_v[:49], 0.1 * np.arange(49))
    np.testing.assert_array_equal(rec.position_m[50:], 1e-9 * np.arange(86, 170))


def test_a_change_of_diagnostics_starts_a_new_block():
    def sample(k, names):
        diag = tuple(float(k + i) for i in range(len(names))) if names else None
        return ServoSample(k, T0 + k * PERIOD, 0.0, 0.0, 0.0, 1.0, 1.0, 0, diag,
                           names or None)

    items = [(k, sample(k, ('b', 'a'))) for k in range(7)] + \
        [(k, sample(k, ('c',) if k % 2 else None)) for k in range(7, 12)]
    recorder = BlockRecorder(block_samples=100)
    out = recorder.add(batch_of(items)) + recorder.finish(2.0)
    decoded = [cdr.decode_block(raw) for raw in out]
    assert [names[len(wire.BLOCK_COLUMNS) + 1:] for names, _ in decoded] == [
        ('diagnostics.a', 'diagnostics.b'), ('diagnostics.c',)]
    first, second = decoded[0][1], decoded[1][1]
    # the rows of the first names, up to the first sample of the new ones; values sorted by name
    assert first[:, 0].tolist() == list(range(7)) and second[:, 0].tolist() == list(range(7, 12))
    np.testing.assert_array_equal(first[:, -2:], [[k + 1.0, float(k)] for k in range(7)])
    assert np.isnan(second[1::2, -1]).all() and second[0::2, -1].tolist() == [7.0, 9.0, 11.0]
    assert second[-1, len(wire.BLOCK_COLUMNS)] == 2.0 and recorder.rows == 12


@pytest.mark.parametrize('size', [1, 3, 100])
def test_blocks_are_whole_until_the_end(size):
    items = [(k, ServoSample(k, T0 + k * PERIOD, 0.0, 0.0, 0.0, 1.0, 1.0, 0, None))
             for k in range(250)]
    recorder = BlockRecorder(block_samples=size)
    out = []
    for lo in range(0, 250, 37):  # batches that do not line up with the blocks
        out += recorder.add(batch_of(items[lo:lo + 37]))
    rows = [cdr.decode_block(raw)[1].shape[0] for raw in out]
    # the last sample waits for the next one (its applied input): 249 rows at most so far
    assert all(r == size for r in rows) and sum(rows) == 249 // size * size
    rest = [cdr.decode_block(raw)[1] for raw in recorder.finish()]
    assert sum(r.shape[0] for r in rest) == 250 - sum(rows)
    assert math.isnan(rest[-1][-1, len(wire.BLOCK_COLUMNS)])  # held_v unknown: NaN


# --- several axes --------------------------------------------------------------------------


def axes_run(duration_s: float = 0.03):
    """The XY file's servo on an on-time clock: its batch and the offline loop's records."""
    loop = axes_loop_config(cli.read_config(['xy_stage.yaml']))
    loop_servo = axes_servo_from_config(loop, duration_s)
    clock = FakeClock(per_read=300)
    loop_servo.pacer = Pacer(PERIOD, clock=clock, sleep=clock.sleep)
    loop_servo.run(start_ns=T0)
    assert loop_servo.error is None
    return loop, loop_servo.take_batch()


def rows_of(batch, rows):
    return batch._replace(**{f: getattr(batch, f)[rows] for f in batch._fields if f != 'axes'})


@pytest.mark.parametrize('size', [100, 7])
def test_blocks_of_several_axes_carry_every_sample_and_the_input_held_over_it(tmp_path, size):
    loop, batch = axes_run()
    n = batch.size
    recorder = AxesBlockRecorder(batch.axes, block_samples=size)
    messages = []
    for lo in range(0, n, 37):  # batches that do not line up with the blocks
        messages += recorder.add(rows_of(batch, slice(lo, lo + 37)))
    held = batch.command_v[-1] + 0.25
    messages += recorder.finish(held)
    assert recorder.rows == n and recorder.messages == len(messages)
    assert all(cdr.decode_block(raw)[1].shape[0] == size for raw in messages[:-1])
    write_blocks(tmp_path / 'b', messages)
    read = read_axes(tmp_path / 'b')
    assert [r.meta['axis'] for r in read] == list(loop.stage.names)
    assert read[0].meta['alignment']['command_source'] == 'applied'
    for j, r in enumerate(read):
        np.testing.assert_array_equal(r.position_m, batch.position_m[:, j])
        np.testing.assert_array_equal(r.reference_m, batch.reference_m[:, j])
        np.testing.assert_array_equal(r.reference_velocity_mps, batch.velocity_mps[:, j])
        np.testing.assert_array_equal(r.true_position_m, batch.true_position_m[:, j])
        # row k: what the plant held over [t_k, t_k+1): the next sample's applied input, and
        # after the last one what finish() was told
        np.testing.assert_array_equal(r.command_v[:-1], batch.applied_v[1:, j])
        assert r.command_v[-1] == held[j]
    origin = read[0].meta['time_origin_ns']
    assert origin == batch.stamp_ns[0]
    relative = read_axes(tmp_path / 'b', relative_time=True)[0].time_s
    assert (origin + np.rint(relative * 1e9).astype(np.int64)).tolist() == \
        batch.stamp_ns.tolist()


def test_a_gap_in_the_samples_of_several_axes_leaves_the_input_unknown_and_shows(tmp_path):
    _, batch = axes_run(0.02)
    kept = np.r_[0:80, 120:batch.size]        # the ring lost 40 samples
    part = rows_of(batch, kept)
    part = part._replace(true_position_m=np.full_like(part.true_position_m, np.nan))
    recorder = AxesBlockRecorder(batch.axes)
    messages = recorder.add(part) + recorder.finish()
    # hardware (no true position): no such columns
    names = cdr.decode_block(messages[0])[0]
    assert not [c for c in names if c.endswith('true_position_m')]
    write_blocks(tmp_path / 'b', messages)
    read = read_axes(tmp_path / 'b')
    assert read[0].meta['alignment']['missing_samples'] == 40
    for j, r in enumerate(read):
        assert math.isnan(r.command_v[79]) and math.isnan(r.command_v[-1])
        np.testing.assert_array_equal(r.command_v[80:-1], part.applied_v[81:, j])
        assert r.true_position_m is None
