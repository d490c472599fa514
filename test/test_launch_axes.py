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
launch_testing: a multi-axis file through closed_loop.launch.py, one process per node, lockstep.

``config/xy_stage.yaml`` (inverse learning, coupling compensation) for 0.05 s: what the three
processes publish is the offline runner's run, sample for sample. Needs a ROS 2 Jazzy
environment where this package is installed; skipped with the reason otherwise.
"""

from __future__ import annotations

import threading
import time
import unittest

from launch_support import closed_loop
import launch_testing.asserts
import numpy as np
from piezo_stage_ros.cli import read_config
from piezo_stage_ros.core.config.axes import axes_loop_config
from piezo_stage_ros.core.control.axes import AxesController
from piezo_stage_ros.core.loop.axes import run_axes
from piezo_stage_ros.core.model.axes import AxesStage
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

SAMPLES = 500
PROBE_QOS = QoSProfile(depth=5 * SAMPLES, reliability=ReliabilityPolicy.RELIABLE)


@pytest.mark.launch_test
def generate_test_description():
    return closed_loop({'config': 'xy_stage.yaml', 'mode': 'lockstep',
                        'duration_s': str(SAMPLES / 10_000), 'composed': 'false'})


class TestAxesLoop(unittest.TestCase):

    def test_three_processes_run_the_xy_stage_as_the_offline_runner(self):
        context = rclpy.context.Context()
        rclpy.init(context=context)
        node = rclpy.create_node('launch_probe', context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        got = {'position': [], 'reference': [], 'command': []}
        lock = threading.Lock()

        def keep(key, values):
            def cb(msg):
                with lock:
                    got[key].append(values(msg))
            return cb
        node.create_subscription(JointState, '/stage/position', keep(
            'position', lambda m: (list(m.name), list(m.position))), PROBE_QOS)
        node.create_subscription(JointState, '/stage/reference', keep(
            'reference', lambda m: list(m.position)), PROBE_QOS)
        node.create_subscription(Float64MultiArray, '/stage/command', keep(
            'command', lambda m: ([(d.label, d.size, d.stride) for d in m.layout.dim],
                                  list(m.data))), PROBE_QOS)
        try:
            deadline = time.monotonic() + 180.0
            while time.monotonic() < deadline and len(got['command']) < SAMPLES:
                executor.spin_once(timeout_sec=0.05)
        finally:
            executor.shutdown()
            node.destroy_node()
            rclpy.try_shutdown(context=context)
        self.assertEqual([len(v) for v in got.values()], [SAMPLES] * 3)
        self.assertEqual({tuple(n) for n, _ in got['position']}, {('stage_x', 'stage_y')})
        self.assertEqual({tuple(d) for d, _ in got['command']}, {(('axes', 2, 2),)})
        loop = axes_loop_config(read_config(['xy_stage.yaml']))
        ctrl = AxesController.build(loop.controllers, loop.stage, compensate=loop.compensate)
        records = run_axes(AxesStage(loop.stage), ctrl, loop.trajectories(),
                           duration_s=SAMPLES / 10_000)
        for name, want in (('position', 'position_m'), ('reference', 'reference_m'),
                           ('command', 'command_v')):
            values = np.array([v[-1] if name != 'reference' else v for v in got[name]])
            for j, rec in enumerate(records):
                self.assertTrue(np.array_equal(values[:, j], getattr(rec, want)), (name, j))


@launch_testing.post_shutdown_test()
class TestExit(unittest.TestCase):

    def test_every_process_exits_cleanly(self, proc_info):
        launch_testing.asserts.assertExitCodes(proc_info, allowable_exit_codes=[0, -2, -15])
