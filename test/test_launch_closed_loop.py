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
launch_testing: the closed loop from closed_loop.launch.py, one process per node, lockstep.

Checks the wiring (who publishes and subscribes what, with which type) and that a lockstep run
of 0.1 s produces 1000 position samples, 1000 references and 1000 commands. Needs a ROS 2 Jazzy
environment where this package is installed (``colcon build``; the launch file starts the
installed executables); skipped with the reason otherwise.
"""

from __future__ import annotations

import threading
import time
import unittest

from launch_support import closed_loop
import launch_testing.asserts
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64

SAMPLES = 1000
# the probe reads slower than the loop runs: a queue that holds the whole run loses nothing
PROBE_QOS = QoSProfile(depth=5 * SAMPLES, reliability=ReliabilityPolicy.RELIABLE)


@pytest.mark.launch_test
def generate_test_description():
    return closed_loop({'mode': 'lockstep', 'duration_s': '0.1', 'composed': 'false',
                        'scenario': 'table3_pi.yaml'})


class TestClosedLoop(unittest.TestCase):

    @classmethod
    def setUpClass(cls):
        cls.context = rclpy.context.Context()
        rclpy.init(context=cls.context)
        cls.node = rclpy.create_node('launch_probe', context=cls.context)
        cls.executor = SingleThreadedExecutor(context=cls.context)
        cls.executor.add_node(cls.node)

    @classmethod
    def tearDownClass(cls):
        cls.executor.shutdown()
        cls.node.destroy_node()
        rclpy.try_shutdown(context=cls.context)

    def spin_until(self, done, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if done():
                return True
            self.executor.spin_once(timeout_sec=0.05)
        return done()

    def test_wiring_and_a_tenth_of_a_second_of_lockstep(self):
        got = {'position': [], 'reference': 0, 'command': 0}
        lock = threading.Lock()

        def position(msg):
            with lock:
                got['position'].append(msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec)

        def count(key):
            def cb(msg):
                with lock:
                    got[key] += 1
            return cb

        node = self.node
        node.create_subscription(JointState, '/stage/reference', count('reference'), PROBE_QOS)
        node.create_subscription(Float64, '/stage/command', count('command'), PROBE_QOS)
        node.create_subscription(JointState, '/stage/position', position, PROBE_QOS)

        def nodes_on(topic, publishers):
            infos = node.get_publishers_info_by_topic(topic) if publishers else \
                node.get_subscriptions_info_by_topic(topic)
            return {i.node_name for i in infos}

        def wired():
            # the plant's endpoints are part of it: the probe may learn of them (discovery is
            # asynchronous) after the plant has seen its three subscribers and started, and
            # they are gone once its 1000 samples are done; so they are waited for here, not
            # asserted after
            return {'controller_node', 'trajectory_node', 'launch_probe'} <= \
                nodes_on('/stage/position', False) and \
                nodes_on('/stage/command', True) == {'controller_node'} and \
                nodes_on('/stage/reference', True) == {'trajectory_node'} and \
                nodes_on('/stage/reference', False) - {'launch_probe'} == {'controller_node'} and \
                nodes_on('/stage/position', True) == {'plant_node'} and \
                nodes_on('/clock', True) == {'plant_node'} and \
                'plant_node' in nodes_on('/stage/command', False)
        self.assertTrue(self.spin_until(wired, 60.0), 'the closed loop never wired up')
        names = dict(node.get_topic_names_and_types())
        self.assertEqual(names['/stage/position'], ['sensor_msgs/msg/JointState'])
        self.assertEqual(names['/stage/reference'], ['sensor_msgs/msg/JointState'])
        self.assertEqual(names['/stage/command'], ['std_msgs/msg/Float64'])
        self.assertEqual(names['/clock'], ['rosgraph_msgs/msg/Clock'])
        self.assertTrue(self.spin_until(lambda: len(got['position']) >= SAMPLES
                                        and got['command'] >= SAMPLES, 120.0),
                        f'only {len(got["position"])} samples arrived')
        # the run is over: nothing more comes
        self.spin_until(lambda: False, 0.5)
        self.assertEqual(len(got['position']), SAMPLES)
        self.assertEqual(got['position'], [k * 100_000 for k in range(SAMPLES)])
        self.assertEqual(got['reference'], SAMPLES)
        self.assertEqual(got['command'], SAMPLES)


@launch_testing.post_shutdown_test()
class TestExit(unittest.TestCase):

    def test_every_process_exits_cleanly(self, proc_info):
        launch_testing.asserts.assertExitCodes(proc_info, allowable_exit_codes=[0, -2, -15])

