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
FollowJointTrajectory on a stage of several axes under rclpy: the XY stage holding
(xy_hold.yaml), goals of both axes and of one, a refusal, a preemption and a cancel, the
lockstep samples against the offline twin.

Skipped where rclpy or control_msgs (ROS 2 Jazzy) cannot be imported; the logic is tested
without them in test_axes_goals.py.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not importable here; '
                                            'the multi-axis goal logic is tested in '
                                            'test_axes_goals.py')
pytest.importorskip('control_msgs.action', reason='control_msgs (FollowJointTrajectory) is not '
                                                  'importable here')

from control_msgs.action import FollowJointTrajectory  # noqa: E402
from control_msgs.msg import JointTolerance  # noqa: E402
from piezo_stage_ros.cli import read_config  # noqa: E402
from piezo_stage_ros.core.config.axes import axes_loop_config  # noqa: E402
from piezo_stage_ros.core.control.axes import AxesController  # noqa: E402
from piezo_stage_ros.core.loop.follow import run_axes_goals  # noqa: E402
from piezo_stage_ros.core.model.axes import AxesStage  # noqa: E402
from piezo_stage_ros.nodes.axes_logic import axes_follower  # noqa: E402
from piezo_stage_ros.nodes.axes_nodes import (  # noqa: E402
    AxesControllerNode,
    AxesPlantNode,
    AxesTrajectoryNode,
    connect_axes,
)
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
import test_goals_ros  # noqa: E402
from test_goals_ros import duration  # noqa: E402
import test_nodes_ros  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

CONFIG_DIR = Path(__file__).resolve().parents[1] / 'config'
FILES = [str(CONFIG_DIR / n) for n in ('default.yaml', 'xy_stage.yaml', 'xy_hold.yaml')]
T = 1e-4
X, Y = 'stage_x', 'stage_y'

# the nodes' context, as the node tests make it
context = test_nodes_ros.context


def goal_msg(names: list[str], t: float, positions: list[float], goal_m: float = 0.0,
             goal_time_s: float = 0.0, path_m: float = 0.0) -> Any:
    goal = FollowJointTrajectory.Goal()
    goal.trajectory.joint_names = names
    goal.trajectory.points = [JointTrajectoryPoint(positions=positions,
                                                   time_from_start=duration(t))]
    goal.goal_tolerance = [JointTolerance(name=n, position=goal_m) for n in names if goal_m]
    goal.path_tolerance = [JointTolerance(name=n, position=path_m) for n in names if path_m]
    goal.goal_time_tolerance = duration(goal_time_s)
    return goal


def nodes_of(ctx, mode: str = 'lockstep', direct: bool = False):
    args = ['--ros-args'] + [a for f in FILES for a in ('--params-file', f)]

    def make(cls, values):
        return cls(context=ctx, cli_args=args, direct=direct, parameter_overrides=[
            Parameter(k, value=v) for k, v in {'mode': mode, **values}.items()])
    # the plant waits for the trajectory node, the controller and the client's subscription
    plant = make(AxesPlantNode, {'duration_s': 0.0, 'lockstep.subscribers': 3})
    return plant, [plant, make(AxesControllerNode, {}), make(AxesTrajectoryNode, {})]


class Session(test_goals_ros.Session):
    """The nodes and a client on one executor (test_goals_ros), every axis' positions kept."""

    def __init__(self, ctx, nodes, positions: bool = True) -> None:
        super().__init__(ctx, nodes, positions=False)
        self.action = self.client.action
        self.feedback = self.client.feedback
        self.topic = self.client.create_publisher(JointTrajectory, '/stage/joint_trajectory',
                                                  10)
        self.positions: list[tuple[int, list[float]]] = []
        if positions:
            # the plant waits for this third subscriber before its first sample
            self.client.create_subscription(JointState, '/stage/position', lambda m: (
                self.positions.append((m.header.stamp.sec * 10 ** 9 + m.header.stamp.nanosec,
                                       list(m.position)))), 10000)


def twin(logic, samples: int):
    loop = axes_loop_config(read_config(['xy_stage.yaml', 'xy_hold.yaml']))
    events = [*logic.started, *((t, 'cancel') for t in logic.cancelled)]
    return run_axes_goals(AxesStage(loop.stage), AxesController.build(
        loop.controllers, loop.stage, compensate=loop.compensate), loop.trajectories(),
        axes_follower(loop), events, duration_s=samples * T,
        chunk_s=loop.base.trajectory_node.chunk_s)


def test_goals_on_the_xy_stage_in_lockstep_give_the_offline_twins_samples(context):
    plant, nodes = nodes_of(context)
    logic = nodes[2].logic
    run = Session(context, nodes)
    five = dict(goal_m=5e-9, goal_time_s=0.02)
    try:
        # both axes, the message naming y first; then y alone (x holds); then beyond y's reach
        codes = []
        for goal in (goal_msg([Y, X], 0.02, [9e-6, 14e-6], **five),
                     goal_msg([Y], 0.02, [12e-6], **five),
                     goal_msg([X, Y], 0.02, [12e-6, 39e-6], **five)):
            _, done = run.send(goal)
            result = run.result(done)
            codes.append((result.status, result.result.error_code, result.result.error_string))
        assert [c[:2] for c in codes] == [(4, 0), (4, 0), (6, -1)], codes
        assert "'stage_y' = 3.9e-05 m; allowed: [" in codes[2][2]
        # a long move preempted by a new goal, which is then cancelled half way
        _, first = run.send(goal_msg([X, Y], 0.5, [18e-6, 6e-6]))
        run.spin(lambda: len(logic.started) >= 3)
        handle, second = run.send(goal_msg([X, Y], 0.5, [8e-6, 14e-6]))
        preempted = run.result(first)
        assert (preempted.status, preempted.result.error_code) == (6, -1)
        assert 'cancelled due to new incoming action' in preempted.result.error_string
        run.spin(lambda: len(logic.started) >= 4)
        asked = handle.cancel_goal_async()
        run.spin(asked.done)
        cancelled = run.result(second)
        assert cancelled.status == 5 and cancelled.result.error_code == 0
        assert 'decelerated to a hold' in cancelled.result.error_string
        # a topic message (fire and forget) moves x alone
        run.topic.publish(JointTrajectory(joint_names=[X], points=[
            JointTrajectoryPoint(positions=[11e-6], time_from_start=duration(0.02))]))
        run.spin(lambda: len(logic.started) >= 5)
        stop = logic._index + 400
        run.spin(lambda: len(run.positions) > stop)
        assert logic.follower.phase == 'hold'
        # feedback: every joint, in the stage's order
        assert run.feedback and all(list(fb.joint_names) == [X, Y] and
                                    len(fb.actual.positions) == 2 for fb in run.feedback)
    finally:
        run.close()
    assert len(logic.started) == 5 and len(logic.cancelled) == 1
    # the controller bound each goal's reference before the sample it changed at
    assert nodes[1].logic.late_goals == 0
    # by stamp (a sample the plant sent again is the same sample)
    got = np.array([p for _, p in sorted(dict(run.positions).items())])
    n = len(got) - 100
    offline = twin(logic, len(got))
    assert np.array_equal(got[:n], offline.position_m[:n])
    # the moves were made: each axis went where the goals sent it
    assert np.ptp(got[:, 0]) > 3e-6 and np.ptp(got[:, 1]) > 3e-6


def test_goals_in_real_time_with_several_axes_are_refused_with_the_reason(context):
    plant, nodes = nodes_of(context, 'realtime', direct=True)
    connect_axes(*nodes)
    run = Session(context, nodes, positions=False)
    try:
        _, done = run.send(goal_msg([X, Y], 0.02, [12e-6, 6e-6]))
        result = run.result(done)
        assert (result.status, result.result.error_code) == (6, -1)
        assert "mode 'realtime'" in result.result.error_string
        assert 'lockstep' in result.result.error_string
    finally:
        run.close()
