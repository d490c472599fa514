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
The nodes of a stage of several axes under rclpy, lockstep and real time, against the offline
runner.

Skipped where rclpy (ROS 2 Jazzy) cannot be imported; CI has no rclpy, the logic these nodes
wrap is tested without it in test_axes_nodes_logic.py.
"""

from __future__ import annotations

from pathlib import Path
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not importable here; '
                                            'the multi-axis node logic is tested without it in '
                                            'test_axes_nodes_logic.py')

from piezo_stage_ros.cli import read_config  # noqa: E402
from piezo_stage_ros.core.config.axes import axes_loop_config  # noqa: E402
from piezo_stage_ros.core.contracts import cdr, wire  # noqa: E402
from piezo_stage_ros.core.control.axes import AxesController  # noqa: E402
from piezo_stage_ros.core.loop.axes import run_axes, run_metrics  # noqa: E402
from piezo_stage_ros.core.model.axes import AxesStage  # noqa: E402
from piezo_stage_ros.hardware.pacing import Pacer  # noqa: E402
from piezo_stage_ros.nodes import stage_servo  # noqa: E402
from piezo_stage_ros.nodes.axes_nodes import (  # noqa: E402
    AxesControllerNode,
    AxesPlantNode,
    AxesTrajectoryNode,
    connect_axes,
)
from piezo_stage_ros.nodes.runner import make_executor  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import (  # noqa: E402
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402
import test_nodes_ros  # noqa: E402

CONFIG_DIR = Path(__file__).resolve().parents[1] / 'config'
FILES = [str(CONFIG_DIR / 'default.yaml'), str(CONFIG_DIR / 'xy_stage.yaml')]
# a recorder's subscription (config/record_qos.yaml): every message of the run kept
RECORD = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10000,
                    reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
TOPICS = {wire.POSITION: JointState, wire.REFERENCE: JointState, wire.COMMAND: Float64MultiArray,
          wire.TRUE_POSITION: JointState}


# the nodes' context, as the node tests make it
context = test_nodes_ros.context


class Recorder(Node):
    """Takes the stage topics as serialized messages with their arrival time, as a recorder."""

    def __init__(self, context: Context, topics: dict | None = None) -> None:
        super().__init__('recorder', context=context)
        self.topics = TOPICS if topics is None else topics
        self.raw: dict[str, list[tuple[int, bytes]]] = {t: [] for t in self.topics}
        for topic, kind in self.topics.items():
            self.create_subscription(kind, topic, lambda data, t=topic: self.raw[t].append(
                (time.time_ns(), data)), RECORD, raw=True)

    def write_bag(self, path: Path, topics=TOPICS) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import get_typestore, Stores
        store = get_typestore(Stores.ROS2_JAZZY)
        with Writer(path, version=Writer.VERSION_LATEST,
                    storage_plugin=StoragePlugin.MCAP) as writer:
            for topic, kind in topics.items():
                msgtype = f'{kind.__module__.split(".")[0]}/msg/{kind.__name__}'
                conn = writer.add_connection('/' + topic, msgtype, typestore=store)
                for stamp, data in self.raw[topic]:
                    writer.write(conn, stamp, data)


def nodes_of(context, duration_s, extra=None):
    common = {'duration_s': duration_s, 'lockstep.subscribers': 3, **(extra or {})}
    args = ['--ros-args'] + [a for f in FILES for a in ('--params-file', f)]

    def make(cls, values):
        return cls(context=context, cli_args=args,
                   parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])
    plant = make(AxesPlantNode, common)
    return plant, [plant, make(AxesControllerNode, {}), make(AxesTrajectoryNode, {})]


def spin(context, nodes, future, until, timeout_s=300.0):
    executor = make_executor('events', context)
    for node in nodes:
        executor.add_node(node)
    try:
        executor.spin_until_future_complete(future, timeout_sec=timeout_s)
        deadline = time.monotonic() + 10.0
        while not until() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
    finally:
        for node in nodes:
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()


def offline(duration_s):
    loop = axes_loop_config(read_config(['xy_stage.yaml']))
    ctrl = AxesController.build(loop.controllers, loop.stage, compensate=loop.compensate)
    return loop, run_axes(AxesStage(loop.stage), ctrl, loop.trajectories(),
                          duration_s=duration_s)


def test_a_lockstep_run_of_the_xy_stage_is_the_offline_runner_bit_for_bit(context, tmp_path):
    from piezo_stage_ros.analysis.bagread import read_axes
    duration_s = 0.3
    n = 3000
    plant, nodes = nodes_of(context, duration_s)
    recorder = Recorder(context)
    spin(context, nodes + [recorder], plant.finished,
         until=lambda: len(recorder.raw[wire.COMMAND]) >= n)
    assert plant.finished.done() and plant.finished.exception() is None
    stats = plant.finished.result()
    assert stats['index'] == n - 1 and stats['resends'] == 0 and stats['malformed'] == 0
    loop, records = offline(duration_s)
    assert loop.controllers[0].feedforward.mode == 'inverse_learning' and loop.compensate
    assert {k: len(v) for k, v in recorder.raw.items()} == dict.fromkeys(TOPICS, n)
    # the recorded run, read as analyze reads a bag: the offline runner's samples, bit for bit
    recorder.write_bag(tmp_path / 'run')
    got = read_axes(tmp_path / 'run')
    assert [r.meta['axis'] for r in got] == ['x', 'y']
    for rec, off in zip(got, records):
        # stamped t_k = k T in whole nanoseconds (the runner's times are k T in floats)
        np.testing.assert_array_equal(np.round(rec.time_s * 1e9), np.arange(n) * 100_000)
        for field in ('position_m', 'reference_m', 'reference_velocity_mps', 'command_v',
                      'true_position_m'):
            assert np.array_equal(getattr(rec, field), getattr(off, field)), field
    # so are the figures analyze prints of it (the raster's fast axis over its lines)
    window = 0.1
    assert run_metrics(got, window_s=window, fast_axis='x') == \
        run_metrics(records, window_s=window, fast_axis='x')


def direct_nodes_of(context, duration_s):
    """The three nodes in real time, composed as ``stage_servo --direct`` composes them."""
    args = ['--ros-args'] + [a for f in FILES for a in ('--params-file', f)]

    def make(cls, values):
        values = {'mode': 'realtime', **values}
        return cls(context=context, cli_args=args, direct=True,
                   parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])
    # two subscribers are the peers the servo calls; the third the recorder, given time to
    # match the other topics
    plant = make(AxesPlantNode, {'duration_s': duration_s, 'lockstep.subscribers': 3,
                                 'lockstep.settle_s': 0.5})
    nodes = [plant, make(AxesControllerNode, {}), make(AxesTrajectoryNode, {})]
    connect_axes(*nodes)
    return plant, nodes


def real_time_run(context, tmp_path, duration_s, clock=None):
    """Run the composed nodes in real time with a recorder; return its bag read, as analyze."""
    from piezo_stage_ros.analysis.bagread import read_axes
    n = round(duration_s * 10_000)
    plant, nodes = direct_nodes_of(context, duration_s)
    if clock is not None:
        plant.servo.pacer = Pacer(plant.servo.pacer.period_ns, clock=clock, sleep=clock.sleep)
    recorder = Recorder(context, {**TOPICS, wire.BLOCK: Float64MultiArray})

    def blocked() -> int:
        return sum(len(cdr.decode_block(raw)[1]) for _, raw in recorder.raw[wire.BLOCK])
    spin(context, nodes + [recorder], plant.finished,
         until=lambda: len(recorder.raw[wire.COMMAND]) >= plant.servo.pushed
         and blocked() >= plant.servo.pushed)
    assert plant.finished.done() and plant.finished.exception() is None
    stats = plant.finished.result()
    served, skipped = plant.servo.pushed, stats['skipped']
    assert stats['queue_overruns'] == 0 and stats['malformed'] == 0
    # every sample of the grid is served or skipped (counted), and every served one recorded
    assert served + skipped == n and served > 0
    assert {k: len(v) for k, v in recorder.raw.items() if k in TOPICS} == \
        dict.fromkeys(TOPICS, served)
    recorder.write_bag(tmp_path / 'run')
    got = read_axes(tmp_path / 'run', relative_time=True)
    # the blocks hold the same samples, every axis in a row (the command there: what the
    # plant held over each sample)
    recorder.write_bag(tmp_path / 'blocks', {wire.BLOCK: Float64MultiArray})
    blocks = read_axes(tmp_path / 'blocks', relative_time=True)
    assert blocks[0].meta['alignment']['missing_samples'] == 0
    for rec, block in zip(got, blocks):
        np.testing.assert_array_equal(block.time_s, rec.time_s)
        for field in ('position_m', 'reference_m', 'reference_velocity_mps', 'true_position_m'):
            np.testing.assert_array_equal(getattr(block, field), getattr(rec, field))
    assert [r.meta['axis'] for r in got] == ['x', 'y'] and got[0].time_s.size == served
    k = np.round(got[0].time_s * 1e4).astype(int)  # on the 10 kHz grid from sample 0
    assert k[0] == 0 and np.all(np.diff(k) >= 1) and k[-1] < n
    assert int(np.sum(np.diff(k) - 1)) + (n - 1 - k[-1]) == skipped
    return stats, got, k, blocks


FIELDS = ('position_m', 'reference_m', 'reference_velocity_mps', 'command_v', 'true_position_m')


def test_a_real_time_run_of_the_xy_stage_on_an_on_time_clock_is_the_offline_runner(
        context, tmp_path):
    from fake_clock import FakeClock
    duration_s = 0.3
    stats, got, k, blocks = real_time_run(context, tmp_path, duration_s,
                                          FakeClock(start=time.monotonic_ns(), per_read=300))
    assert stats['skipped'] == 0 and k.tolist() == list(range(3000))
    _, records = offline(duration_s)
    for rec, off, block in zip(got, records, blocks):
        for field in FIELDS:
            assert np.array_equal(getattr(rec, field), getattr(off, field)), field
        # on time, the input held over each sample is the command computed at it
        np.testing.assert_array_equal(block.command_v[:-1], off.command_v[:-1])
    window = 0.1
    assert run_metrics(got, window_s=window, fast_axis='x') == \
        run_metrics(records, window_s=window, fast_axis='x')


def test_a_real_time_run_of_the_xy_stage_is_the_offline_runner_until_a_skipped_sample(
        context, tmp_path):
    duration_s = 0.5
    stats, got, k, _ = real_time_run(context, tmp_path, duration_s)
    # until the first skipped sample, the servo's samples are the offline runner's bit for bit
    # (after it, the stage played commands planned ahead where the runner had fresh ones)
    gaps = np.flatnonzero(np.diff(k) > 1)
    on_time = int(gaps[0]) + 1 if gaps.size else k.size
    loop, records = offline(duration_s)
    print(f'real time: {k.size} samples served, {stats["skipped"]} skipped, the first '
          f'{on_time} on the grid; lateness p99 {stats["lateness_p99_us"]} us')
    for rec, off in zip(got, records):
        for field in FIELDS:
            np.testing.assert_array_equal(getattr(rec, field)[:on_time],
                                          getattr(off, field)[:on_time], err_msg=field)
    # the commands stay in the amplifier's range however many samples were skipped
    for rec, chain in zip(got, (a.chain for a in loop.stage.axes)):
        assert np.all((rec.command_v >= chain.amplifier_min_v)
                      & (rec.command_v <= chain.amplifier_max_v))


def test_stage_servo_runs_several_axes_in_real_time_composed(capfd):
    code = stage_servo.main(['stage_servo', '--direct', '--ros-args', *[a for f in FILES for a in (
        '--params-file', f)], '-p', 'mode:=realtime', '-p', 'plant_node:duration_s:=0.05'])
    err = capfd.readouterr().err
    assert code == 0, err
    assert 'servo of 2 axes in a thread' in err and 'run complete' in err


def test_real_time_with_several_axes_without_the_direct_composition_is_refused(capsys):
    code = stage_servo.main(['stage_servo', '--ros-args', *[a for f in FILES for a in (
        '--params-file', f)], '-p', 'mode:=realtime'])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "mode 'realtime' without --direct" in err[-1]
    assert 'stage_servo --direct' in err[-1]


def test_the_direct_composition_in_lockstep_with_several_axes_is_refused(capsys):
    code = stage_servo.main(['stage_servo', '--direct', '--ros-args',
                             *[a for f in FILES for a in ('--params-file', f)]])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and '--direct in lockstep' in err[-1]


def test_a_bad_per_axis_value_is_refused_naming_it(capsys):
    code = stage_servo.main(['stage_servo', '--ros-args', *[a for f in FILES for a in (
        '--params-file', f)], '-p', 'plant_node:axes.y.seed:=-3'])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and 'seed' in err[-1] and '-3' in err[-1]


def test_a_scan_given_to_a_node_other_than_the_trajectory_node_is_refused(capsys):
    # the scan is the trajectory node's: given to the plant node it would be read by nothing,
    # and is refused as every name a node does not declare (as the offline loader refuses it)
    code = stage_servo.main(['stage_servo', '--ros-args', *[a for f in FILES for a in (
        '--params-file', f)], '-p', 'plant_node:scan.raster.lines:=32'])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and 'scan.raster.lines' in err[-1] and 'not a parameter' in err[-1]


def test_the_multi_axis_parameters_are_declared_and_take_no_change(context):
    plant, nodes = nodes_of(context, 0.01)
    trajectory = nodes[2]
    try:
        assert list(plant.get_parameter('axes.names').value) == ['x', 'y']
        assert plant.get_parameter('axes.y.seed').value == 1
        assert list(plant.get_parameter('axes.coupling.gain').value) == [0.0, 0.02, 0.0, 0.0]
        assert trajectory.get_parameter('scan.raster.lines').value == 64
        assert trajectory.get_parameter('scan.raster.slow_axis').value == 'y'
        # described as the one-axis parameter they override, read-only
        desc = plant.describe_parameter('axes.y.seed')
        assert desc.read_only and 'seed' in desc.description.lower()
        for node, name, value in ((plant, 'axes.y.seed', 2), (plant, 'seed', 2),
                                  (trajectory, 'scan.raster.lines', 32)):
            [result] = node.set_parameters([Parameter(name, value=value)])
            assert not result.successful, name
        assert plant.get_parameter('seed').value == 0
    finally:
        for node in nodes:
            node.destroy_node()
