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
launch_testing: goals on the XY stage through closed_loop.launch.py, one process per node.

``config:=xy_stage.yaml scenario:=xy_hold.yaml composed:=false``: a client sends goals to the
trajectory node's process (both axes, one axis, a preemption, a refusal); each goal's first
feedback carries the stamp of the sample it started at, and the offline twin with the goals at
those samples gives the positions the plant's process published, sample for sample. Needs a
ROS 2 Jazzy environment where this package is installed; skipped with the reason otherwise.
"""

from __future__ import annotations

import time
from typing import Any
import unittest

from launch_support import closed_loop
import launch_testing.asserts
import numpy as np
from piezo_stage_ros.cli import read_config
from piezo_stage_ros.core.config.axes import axes_loop_config
from piezo_stage_ros.core.control.axes import AxesController
from piezo_stage_ros.core.loop.follow import run_axes_goals
from piezo_stage_ros.core.model.axes import AxesStage
from piezo_stage_ros.nodes import goals_msgs
from piezo_stage_ros.nodes.axes_logic import axes_follower
import pytest
import rclpy

pytest.importorskip('control_msgs.action', reason='control_msgs (FollowJointTrajectory) is not '
                                                  'importable here')

from builtin_interfaces.msg import Duration  # noqa: E402
from control_msgs.action import FollowJointTrajectory  # noqa: E402
from control_msgs.msg import JointTolerance  # noqa: E402
from rclpy.action import ActionClient  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from trajectory_msgs.msg import JointTrajectoryPoint  # noqa: E402

T = 1e-4
X, Y = 'stage_x', 'stage_y'
PROBE_QOS = QoSProfile(depth=100_000, reliability=ReliabilityPolicy.RELIABLE)


@pytest.mark.launch_test
def generate_test_description():
    return closed_loop({'config': 'xy_stage.yaml', 'scenario': 'xy_hold.yaml',
                        'mode': 'lockstep', 'duration_s': '0.0', 'composed': 'false'})


def goal_msg(names: list[str], t: float, positions: list[float], goal_m: float = 0.0) -> Any:
    goal = FollowJointTrajectory.Goal()
    goal.trajectory.joint_names = names
    goal.trajectory.points = [JointTrajectoryPoint(
        positions=positions, time_from_start=Duration(sec=int(t),
                                                      nanosec=round((t - int(t)) * 1e9)))]
    goal.goal_tolerance = [JointTolerance(name=n, position=goal_m) for n in names if goal_m]
    goal.goal_time_tolerance = Duration(nanosec=20_000_000)
    return goal


class TestAxesGoals(unittest.TestCase):

    def test_goals_in_three_processes_give_the_offline_twins_samples(self):
        context = rclpy.context.Context()
        rclpy.init(context=context)
        node = rclpy.create_node('launch_goal_client', context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        positions: dict[int, list[float]] = {}
        node.create_subscription(JointState, '/stage/position', lambda m: positions.__setitem__(
            m.header.stamp.sec * 10 ** 9 + m.header.stamp.nanosec, list(m.position)),
            PROBE_QOS)
        action = ActionClient(node, FollowJointTrajectory, '/stage/follow_joint_trajectory')
        starts: dict[int, int] = {}      # goal number -> stamp of its first feedback [ns]

        def spin(until, timeout_s: float = 120.0) -> None:
            deadline = time.monotonic() + timeout_s
            while not until() and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.01)

        def send(i: int, goal: Any) -> Any:
            def feedback(fb: Any) -> None:
                stamp = fb.feedback.header.stamp
                starts.setdefault(i, stamp.sec * 10 ** 9 + stamp.nanosec)
                self.assertEqual(list(fb.feedback.joint_names), [X, Y])
            started = time.monotonic()
            sent = action.send_goal_async(goal, feedback_callback=feedback)
            spin(sent.done)
            self.assertTrue(sent.done(), f'goal {i}: no answer in '
                            f'{time.monotonic() - started:.1f} s')
            self.assertTrue(sent.result().accepted, f'goal {i}: rejected')
            return sent.result().get_result_async()

        def result(done: Any) -> Any:
            spin(done.done)
            self.assertTrue(done.done(), 'no result')
            return done.result()
        goals = [goal_msg([Y, X], 0.02, [9e-6, 14e-6], 5e-9),
                 goal_msg([Y], 0.02, [12e-6], 5e-9),
                 goal_msg([X, Y], 0.5, [18e-6, 6e-6]),
                 goal_msg([X, Y], 0.03, [11e-6, 8e-6], 5e-9),
                 goal_msg([X], 0.02, [40e-6], 5e-9)]
        try:
            self.assertTrue(action.wait_for_server(timeout_sec=60.0))
            # the run under way (the plant waited for this probe's subscription), and a moment
            # for discovery to settle both ways: an answer sent to a client not yet matched is
            # lost
            spin(lambda: bool(positions))
            wait = time.monotonic() + 1.0
            spin(lambda: time.monotonic() > wait)
            outcome = [result(send(0, goals[0])), result(send(1, goals[1]))]
            long = send(2, goals[2])
            spin(lambda: 2 in starts)
            outcome += [result(send(3, goals[3])), result(long), result(send(4, goals[4]))]
            # the last goal's end, then a little more: the samples the twin is compared on
            last = max(positions)
            spin(lambda: max(positions) > last + 1000 * 100_000)
        finally:
            executor.shutdown()
            node.destroy_node()
            rclpy.try_shutdown(context=context)
        codes = [(r.status, r.result.error_code) for r in outcome]
        self.assertEqual(codes, [(4, 0), (4, 0), (4, 0), (6, -1), (6, -1)],
                         [r.result.error_string for r in outcome])
        self.assertIn('new incoming action', outcome[3].result.error_string)
        self.assertIn("'stage_x' = 4e-05 m", outcome[4].result.error_string)
        self.assertEqual(sorted(starts), [0, 1, 2, 3])
        # the offline twin with each goal at the sample its first feedback names
        loop = axes_loop_config(read_config(['xy_stage.yaml', 'xy_hold.yaml']))
        events = [(starts[i] * 1e-9, goals_msgs.goal_from_msg(goals[i])[0]) for i in range(4)]
        stamps = sorted(positions)
        self.assertEqual(stamps, [k * 100_000 for k in range(len(stamps))])
        got = np.array([positions[s] for s in stamps])
        run = run_axes_goals(AxesStage(loop.stage), AxesController.build(
            loop.controllers, loop.stage, compensate=loop.compensate), loop.trajectories(),
            axes_follower(loop), events, duration_s=len(got) * T,
            chunk_s=loop.base.trajectory_node.chunk_s)
        self.assertTrue(np.array_equal(got, run.position_m))
        self.assertEqual([(r.goal_id, int(r.code)) for r in run.results],
                         [(1, 0), (2, 0), (3, -1), (4, 0)])


@launch_testing.post_shutdown_test()
class TestExit(unittest.TestCase):

    def test_every_process_exits_cleanly(self, proc_info):
        launch_testing.asserts.assertExitCodes(proc_info, allowable_exit_codes=[0, -2, -15])
