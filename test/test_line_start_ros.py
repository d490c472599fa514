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
A line rate changed, and a line stopped and started, on the three nodes in lockstep.

Skipped where rclpy (ROS 2 Jazzy) cannot be imported; the logic is tested without it in
test_line_start.py.
"""

from __future__ import annotations

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not importable here; '
                                            'the logic is tested in test_line_start.py')

from piezo_stage_ros.core.contracts import wire  # noqa: E402
from piezo_stage_ros.nodes import qos  # noqa: E402
from piezo_stage_ros.nodes.controller_node import ControllerNode  # noqa: E402
from piezo_stage_ros.nodes.logic import parse_trajectory  # noqa: E402
from piezo_stage_ros.nodes.plant_node import PlantNode  # noqa: E402
from piezo_stage_ros.nodes.trajectory_node import TrajectoryNode  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import String  # noqa: E402
import test_nodes_ros  # noqa: E402
from test_nodes_ros import overrides, Probe, RECORD, spin  # noqa: E402

# the nodes' context, as the node tests make it
context = test_nodes_ros.context

T_S = 1e-4


def run(context, mode: str, duration_s: float, changes: dict[int, dict]):
    """
    Run the three nodes in lockstep (default stage and gains, a 100 Hz sine).

    ``changes``: trajectory parameters set on the trajectory node once the reference of the
    sample before that stamp is out, so that the change starts at that sample (one executor:
    the next position comes after the reference's callbacks). Returns the controller node, the
    measured error of every sample [m] and the announced t = 0 stamps [ns].
    """
    plant = PlantNode(context=context, parameter_overrides=overrides(
        {'mode': 'lockstep', 'duration_s': duration_s, 'lockstep.subscribers': 3}))
    probe = Probe(context)
    traj = TrajectoryNode(context=context, parameter_overrides=overrides({'mode': 'lockstep'}))
    ctrl = ControllerNode(context=context, parameter_overrides=overrides(
        {'mode': 'lockstep', 'feedforward.mode': mode}))
    done = []
    announced: list[int] = []

    def change(msg: JointState) -> None:
        stamp = msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec + 100_000
        if stamp in changes and stamp not in done:
            done.append(stamp)
            assert traj.set_parameters(overrides(changes[stamp]))[0].successful

    probe.create_subscription(JointState, wire.REFERENCE, change, RECORD)
    probe.create_subscription(String, wire.TRAJECTORY,
                              lambda m: announced.append(parse_trajectory(m.data)[0]),
                              qos.ANNOUNCE)
    samples = round(duration_s / T_S)
    spin(context, [plant, probe, traj, ctrl], plant.finished,
         until=lambda: len(probe.references) >= samples)
    stats = plant.finished.result()
    assert stats['resends'] == 0 and len(probe.references) == samples
    assert len(done) == len(changes)
    y = np.array([p for _, p in probe.positions[:samples]])
    return ctrl, y - np.array(probe.references[:samples]), announced


def line_rms(e: np.ndarray, first: int, rate_hz: float, count: int) -> list[float]:
    """Return the rms of ``e`` over each of ``count`` lines of ``rate_hz`` from ``first``."""
    k = np.arange(len(e)) - first
    line = np.floor(k * T_S * rate_hz + 1e-9).astype(int)
    return [float(np.sqrt(np.mean(e[line == j] ** 2))) for j in range(count)]


def test_a_line_rate_set_on_the_nodes_is_learned_and_its_first_line_is_the_inverses(context):
    # 100 -> 137 Hz set at 0.1 s (ten whole lines), as `ros2 param set` does: the controller
    # node binds the new line at the sample it starts. The first new line is the model
    # inverse's with a table started afresh (the estimates differ by their history: a few per
    # cent), and the learning brings the error to the converter's floor within 50 lines
    change = {100_000_000: {'sine.frequency_hz': 137.0}}
    first = 1000
    ctrl, learned, at = run(context, 'inverse_learning', 0.1 + 52 / 137.0, change)
    ff = ctrl.logic.controller
    assert ff.mismatches == 0 and ff.period_s == 1 / 137.0
    _, inverse, at_inverse = run(context, 'inverse', 0.1 + 52 / 137.0, change)
    _, alone, at_alone = run(context, 'learning', 0.1 + 52 / 137.0, change)
    assert at == at_inverse == at_alone == [100_000_000]
    ours, theirs = line_rms(learned, first, 137.0, 52), line_rms(inverse, first, 137.0, 52)
    assert ours[0] <= 1.05 * theirs[0]
    assert max(ours[49:]) <= 1e-9
    # learning alone starts its table from the model inverse's command for the new line
    assert line_rms(alone, first, 137.0, 1)[0] <= theirs[0]


def test_a_start_after_a_stop_on_the_nodes_keeps_the_line_and_its_table(context):
    # stopped at 0.2 s and started at 0.225 s (less than three lines held): the controller node
    # binds the same line from the start's t = 0 with the table it learned
    ctrl, e, at = run(context, 'inverse_learning', 0.4,
                      {200_000_000: {'active': False}, 225_000_000: {'active': True}})
    assert at == [225_000_000]
    ff = ctrl.logic.controller
    assert ff.diagnostics()['ff_active'] == 1.0 and ff.period_s == 1 / 100.0
    # fed back alone only while the reference was held: 250 samples, or fewer where the held
    # value equals a sample of the line (a sine's)
    assert 0 < ff.mismatches <= 250
    assert ff.periods_learned >= 30
    # the lines after the start's own transient (the reference jumps back to the line's
    # start) are at the level of the lines before the stop
    before = line_rms(e, 1900, 100.0, 1)[0]
    after = line_rms(e, 2250 + 200, 100.0, 10)
    assert max(after) <= 2.0 * before + 0.5e-9
