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
FollowJointTrajectory under rclpy: an action client against the composed nodes.

Skipped where rclpy or control_msgs (ROS 2 Jazzy) cannot be imported; the goal logic is
tested without them in test_goal_logic.py.
"""

from __future__ import annotations

from pathlib import Path
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not importable here; '
                                            'the goal logic is tested in test_goal_logic.py')
pytest.importorskip('control_msgs.action', reason='control_msgs (FollowJointTrajectory) is not '
                                                  'importable here')

from builtin_interfaces.msg import Duration  # noqa: E402
from control_msgs.action import FollowJointTrajectory  # noqa: E402
from control_msgs.msg import JointTolerance  # noqa: E402
from piezo_stage_ros.core.config.loader import load_config, LoopConfig  # noqa: E402
from piezo_stage_ros.core.contracts.wire import JOINT_NAME  # noqa: E402
from piezo_stage_ros.core.control.controllers import bound_controller  # noqa: E402
from piezo_stage_ros.core.loop.follow import FollowParams, GoalFollower, run_goals  # noqa: E402
from piezo_stage_ros.core.loop.goals import AxisLimits  # noqa: E402
from piezo_stage_ros.core.model.hysteresis import make_hysteresis  # noqa: E402
from piezo_stage_ros.core.model.stage import linear_plant, Stage, StageParams  # noqa: E402
from piezo_stage_ros.nodes import stage_servo  # noqa: E402
from piezo_stage_ros.nodes.controller_node import ControllerNode  # noqa: E402
from piezo_stage_ros.nodes.plant_node import PlantNode  # noqa: E402
from piezo_stage_ros.nodes.runner import make_executor  # noqa: E402
from piezo_stage_ros.nodes.trajectory_node import TrajectoryNode  # noqa: E402
from rclpy.action import ActionClient  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
import test_nodes_ros  # noqa: E402
from trajectory_msgs.msg import JointTrajectoryPoint  # noqa: E402

CONFIG_DIR = Path(__file__).resolve().parents[1] / 'config'
CONFIG = load_config([CONFIG_DIR / 'default.yaml', CONFIG_DIR / 'hold.yaml'])
T = 1e-4


# the nodes' context, as the node tests make it
context = test_nodes_ros.context


def params(node: str, **extra) -> list[Parameter]:
    values = {**CONFIG.node(node), **extra}
    return [Parameter(k, value=list(v) if isinstance(v, tuple) else v)
            for k, v in values.items()]


class Client(Node):
    def __init__(self, context: Context, positions: bool) -> None:
        super().__init__('goal_client', context=context)
        self.action = ActionClient(self, FollowJointTrajectory,
                                   '/stage/follow_joint_trajectory')
        self.feedback: list = []
        self.positions: list[tuple[int, float]] = []
        if not positions:
            # in real time 10 000 messages a second would keep the executor behind; in
            # lockstep the plant waits for this subscriber (lockstep.subscribers)
            return
        self.create_subscription(JointState, '/stage/position', lambda m: self.positions.append(
            (m.header.stamp.sec * 10 ** 9 + m.header.stamp.nanosec, m.position[0])), 10000)


def duration(s: float) -> Duration:
    return Duration(sec=int(s), nanosec=round((s - int(s)) * 1e9))


def goal_msg(points: list[tuple[float, float, float | None]], path_m: float = 0.0,
             goal_m: float = 0.0, goal_time_s: float = 0.0) -> FollowJointTrajectory.Goal:
    goal = FollowJointTrajectory.Goal()
    goal.trajectory.joint_names = [JOINT_NAME]
    goal.trajectory.points = [JointTrajectoryPoint(
        positions=[x], velocities=[] if v is None else [v], time_from_start=duration(t))
        for t, x, v in points]
    if path_m:
        goal.path_tolerance = [JointTolerance(name=JOINT_NAME, position=path_m)]
    if goal_m:
        goal.goal_tolerance = [JointTolerance(name=JOINT_NAME, position=goal_m)]
    goal.goal_time_tolerance = duration(goal_time_s)
    return goal


def five_moves() -> list[FollowJointTrajectory.Goal]:
    rng = np.random.default_rng(28)
    reach = AxisLimits.from_stage(StageParams.from_flat(CONFIG.node('plant_node'))).position_max_m
    return [goal_msg([(0.02, float(x), None)], goal_m=5e-9, goal_time_s=0.02)
            for x in rng.uniform(3e-6, min(28e-6, reach), 5)]


def scan_goal() -> FollowJointTrajectory.Goal:
    """1000 points: 10 trace/retrace lines 5-15 um, cubic (slope velocities, 0 at the turns)."""
    points = []
    half, lo, hi, dt = 50, 5e-6, 15e-6, 1e-3
    slope = (hi - lo) / (half * dt)
    for k in range(1000):
        j = k % 100
        phase = j / half if j < half else 2.0 - j / half
        v = 0.0 if j in (0, half) or k == 999 else (slope if j < half else -slope)
        points.append(((k + 1) * dt, lo + (hi - lo) * phase, v))
    return goal_msg(points, path_m=10e-9, goal_m=5e-9, goal_time_s=0.02)


def composed(context: Context, mode: str, duration_s: float, process: bool = False,
             feedforward: str = 'none', autostart: bool = True, direct: bool = True):
    plant = PlantNode(autostart=autostart, context=context, parameter_overrides=params(
        'plant_node', mode=mode, duration_s=duration_s, **{'lockstep.subscribers': 3,
                                                           'servo.process': process}))
    controller = ControllerNode(context=context, parameter_overrides=params(
        'controller_node', mode=mode, **{'feedforward.mode': feedforward}))
    trajectory = TrajectoryNode(context=context, parameter_overrides=params(
        'trajectory_node', mode=mode))
    if direct:
        stage_servo.connect_direct(plant, controller, trajectory)
    return plant, [plant, controller, trajectory]


class Session:
    """The nodes and a client on one executor, goal by goal, for the tests below."""

    def __init__(self, context, nodes, positions: bool) -> None:
        self.client = Client(context, positions)
        self.executor = make_executor('events', context)
        self.nodes = [*nodes, self.client]
        for node in self.nodes:
            self.executor.add_node(node)
        assert self.client.action.wait_for_server(timeout_sec=10.0)

    def spin(self, until, timeout_s: float = 120.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not until() and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)

    def send(self, goal, timeout_s: float = 120.0):
        """Return the goal's handle once accepted, with its result's future."""
        sent = self.client.action.send_goal_async(
            goal, feedback_callback=lambda fb: self.client.feedback.append(fb.feedback))
        self.spin(sent.done, timeout_s)
        handle = sent.result()
        assert handle is not None and handle.accepted
        return handle, handle.get_result_async()

    def result(self, done, timeout_s: float = 120.0):
        self.spin(done.done, timeout_s)
        assert done.done(), f'no result within {timeout_s} s'
        return done.result()

    def close(self) -> None:
        for node in self.nodes:
            self.executor.remove_node(node)
            node.destroy_node()
        self.executor.shutdown()


def run_client(context, nodes, plant, goals, *, spacing_s: float = 0.0, timeout_s: float = 30.0,
               positions: bool = False):
    """Send the goals one after the other (each after the last ended); return the results."""
    run = Session(context, nodes, positions)
    out = []
    try:
        for goal in goals:
            _, done = run.send(goal, timeout_s)
            out.append(run.result(done, timeout_s))
            run.spin(lambda: False, spacing_s)
        return out, run.client
    finally:
        # destroying the plant stops its servo (a real-time run goes on until then)
        run.close()


def test_lockstep_five_moves_a_refusal_and_the_same_samples_as_the_offline_runner(context):
    plant, nodes = composed(context, 'lockstep', 0.0)
    goals = five_moves()
    beyond = goal_msg([(0.02, 39e-6, None)], goal_m=5e-9)
    results, client = run_client(context, nodes, plant, [*goals, beyond], positions=True)
    codes = [(r.status, r.result.error_code) for r in results]
    assert codes == [(4, 0)] * 5 + [(6, -1)], [(c, r.result.error_string) for c, r in
                                               zip(codes, results)]
    assert '3.9e-05' in results[-1].result.error_string
    assert 'allowed' in results[-1].result.error_string
    assert client.feedback, 'no feedback'
    # the goals' status for /diagnostics: OK, one refusal, the last goal succeeded
    status = dict(nodes[2].goals_status().values)
    assert nodes[2].goals_status().level == 0 and status['refused_goals'] == '1'
    assert status['last_result_code'] == '0 SUCCESSFUL' and status['active_goal'] == ''
    # the same goals at the samples they started, offline: identical samples
    loop = LoopConfig.from_config(CONFIG)
    stage = loop.stage
    follower = GoalFollower((JOINT_NAME,), [AxisLimits.from_stage(stage)],
                            [nodes[2].logic.hold_m * 0 + 3.8e-6], FollowParams(sample_time_s=T))
    controller = bound_controller(loop.controller, T, linear_plant(loop.design_plant),
                                  make_hysteresis(stage.hysteresis), None)
    events = [(t, g) for t, g in nodes[2].logic.started]
    n = len(client.positions)
    run = run_goals(Stage(stage), controller, follower, events, duration_s=n * T)
    got = np.array([p for _, p in sorted(client.positions)])
    assert len(events) == 5
    np.testing.assert_array_equal(got[:n - 100], run.position_m[:n - 100])


def test_lockstep_a_thousand_scan_points_with_the_inverse_feed_forward(context):
    plant, nodes = composed(context, 'lockstep', 0.0, feedforward='inverse')
    # from the scan's first point (5 um), then the scan
    start = goal_msg([(0.02, 5e-6, 0.0)], goal_m=5e-9, goal_time_s=0.02)
    results, _ = run_client(context, nodes, plant, [start, scan_goal()], positions=True)
    assert [(r.status, r.result.error_code) for r in results] == [(4, 0), (4, 0)], \
        [r.result.error_string for r in results]


@pytest.mark.parametrize('process', [
    True,
    pytest.param(False, marks=pytest.mark.xfail(
        reason='servo thread (servo.process false) on a 2-core machine: the results reach the '
               'client, but the servo skips samples while the executor takes its turns at the '
               'interpreter lock, and a move now and then misses its 5 nm within the 20 ms '
               'goal time tolerance (GOAL_TOLERANCE_VIOLATED)',
        strict=False))], ids=['process', 'thread'])
def test_realtime_direct_five_moves(context, process):
    plant, nodes = composed(context, 'realtime', 0.0, process=process)
    # a loaded machine keeps the executor seconds behind the servo: generous time per goal
    results, client = run_client(context, nodes, plant, five_moves(), spacing_s=0.05,
                                 timeout_s=120.0)
    codes = [(r.status, r.result.error_code, r.result.error_string) for r in results]
    assert [c[:2] for c in codes] == [(4, 0)] * 5, codes
    assert client.feedback
    status = nodes[2].goals_status()
    assert status.level == 0 and dict(status.values)['last_result_code'] == '0 SUCCESSFUL'


def test_lockstep_joint_trajectory_topic_moves_and_an_empty_one_holds(context):
    from trajectory_msgs.msg import JointTrajectory
    plant, nodes = composed(context, 'lockstep', 0.0)
    client = Client(context, True)
    pub = client.create_publisher(JointTrajectory, '/stage/joint_trajectory', 10)
    executor = make_executor('events', context)
    for node in [*nodes, client]:
        executor.add_node(node)
    logic = nodes[2].logic
    try:
        msg = JointTrajectory(joint_names=[JOINT_NAME], points=[
            JointTrajectoryPoint(positions=[12e-6], time_from_start=duration(0.02))])
        deadline = time.monotonic() + 30.0
        while not logic.started and time.monotonic() < deadline:
            pub.publish(msg) if pub.get_subscription_count() and not logic.goal_active else None
            executor.spin_once(timeout_sec=0.01)
        t_start = logic.started[0][0]
        while logic._index * T < t_start + 0.05 and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.01)
        assert logic.hold_m == 12e-6 and logic.follower.active_goal is None
        # a second move, stopped half way by an empty message: at rest short of 20 um
        pub.publish(JointTrajectory(joint_names=[JOINT_NAME], points=[
            JointTrajectoryPoint(positions=[20e-6], time_from_start=duration(0.05))]))
        while len(logic.started) < 2 and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.01)
        pub.publish(JointTrajectory())
        t_hold = logic._index * T
        while logic._index * T < t_hold + 0.1 and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.01)
        x, v, _ = logic.follower.reference(np.array([logic._index * T]))
        assert 12e-6 < x[0, 0] < 20e-6 and v[0, 0] == 0.0
    finally:
        for node in [*nodes, client]:
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()


# a long move from the hold (3.8 um): still under way when the client has seen it start and
# reacted, however far behind a loaded machine keeps the executor (seconds in real time)
LONG_MOVE_S = 10.0


def long_move():
    return goal_msg([(LONG_MOVE_S, 25e-6, 0.0)], goal_m=5e-9)


@pytest.mark.parametrize('mode, direct, process', [
    ('lockstep', True, False), ('lockstep', False, False), ('realtime', True, True),
    ('realtime', True, False)],
    ids=['lockstep-direct', 'lockstep-topics', 'realtime-process', 'realtime-thread'])
def test_goals_follow_the_plant_lifecycle(context, mode, direct, process):
    """Refused while the plant is not active; a deactivate ends the running goal, ABORTED."""
    from rclpy.lifecycle import TransitionCallbackReturn
    plant, nodes = composed(context, mode, 0.0, process=process, autostart=False,
                            direct=direct)
    trajectory = nodes[2]
    run = Session(context, nodes, positions=mode == 'lockstep')
    try:
        # the trajectory node learns the plant's state: by call in one process, else from
        # its get_state service (the transition events before it are not heard)
        run.spin(lambda: trajectory.gate.state is not None, 30.0)
        assert trajectory.gate.state == 'unconfigured'
        _, done = run.send(five_moves()[0])
        result = run.result(done)
        assert (result.status, result.result.error_code) == (6, -1)
        assert 'plant node is unconfigured' in result.result.error_string
        assert plant.trigger_configure() == TransitionCallbackReturn.SUCCESS
        assert plant.trigger_activate() == TransitionCallbackReturn.SUCCESS
        run.spin(lambda: trajectory.gate.state == 'active', 30.0)
        assert trajectory.gate.state == 'active'
        # under way (feedback comes from the loop), then the deactivate
        run.client.feedback.clear()
        handle, done = run.send(long_move())
        run.spin(lambda: len(run.client.feedback) >= 3 or done.done())
        assert not done.done() and run.client.feedback, 'the move did not get under way'
        assert plant.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
        result = run.result(done)
        assert (result.status, result.result.error_code) == (6, -1), result.result
        assert 'left the active state (deactivating)' in result.result.error_string
        # the stage is the plant's: the ramp, within the slew, to the safe voltage
        assert plant.ramp['max_step_v'] <= plant.ramp['slew_step_v'] * (1.0 + 1e-9)
        # and the goals' status says so
        status = dict(trajectory.goals_status().values)
        assert status['active_goal'] == '' and 'INVALID_GOAL' in status['last_result_code']
        # inactive now: a new goal is refused at once, with the state
        run.spin(lambda: trajectory.gate.state == 'inactive', 30.0)
        _, done = run.send(five_moves()[1])
        result = run.result(done)
        assert (result.status, result.result.error_code) == (6, -1)
        assert 'plant node is inactive' in result.result.error_string
    finally:
        run.close()


@pytest.mark.parametrize('mode, process', [
    ('lockstep', False), ('realtime', True), ('realtime', False)],
    ids=['lockstep', 'realtime-process', 'realtime-thread'])
def test_a_cancel_through_the_action_client_decelerates_to_a_hold(context, mode, process):
    """A cancel mid-move: CANCELED, SUCCESSFUL, at rest short of the target."""
    plant, nodes = composed(context, mode, 0.0, process=process)
    run = Session(context, nodes, positions=mode == 'lockstep')
    try:
        handle, done = run.send(long_move())
        run.spin(lambda: len(run.client.feedback) >= 5 or done.done())
        assert not done.done() and run.client.feedback, 'the move did not get under way'
        # under way from the hold (3.8 um) toward 25 um
        assert run.client.feedback[-1].desired.positions[0] > 3.8e-6
        cancel = handle.cancel_goal_async()
        run.spin(cancel.done)
        assert cancel.result() is not None and len(cancel.result().goals_canceling) == 1, \
            run.result(done).result
        result = run.result(done)
        # as joint_trajectory_controller: CANCELED, error code SUCCESSFUL
        assert (result.status, result.result.error_code) == (5, 0), result.result
        text = result.result.error_string
        assert text.startswith('cancelled: the stage decelerated to a hold at [')
        held = float(text.split('[')[1].split(']')[0])
        # at rest between where it was when cancelled and the target it no longer goes to
        assert run.client.feedback[-1].desired.positions[0] <= held + 1e-12
        assert 3.8e-6 < held < 25e-6
        if not process:
            # the reference (this process's logic) is at rest there
            logic = nodes[2].logic
            x, v, _ = logic.follower.reference(np.array([logic._index * T]))
            assert x[0, 0] == pytest.approx(held, abs=1e-12) and v[0, 0] == 0.0
    finally:
        run.close()


def test_lockstep_goals_by_topics_keep_the_feed_forward_on(context):
    # the nodes talking by topics: the trajectory node announces each goal's reference (the
    # follower's spline) before the reference of the sample it changes at, and the controller
    # binds the spline built again from it; a reference the controller did not bind would
    # count as a mismatch and turn its feed-forward off
    plant, nodes = composed(context, 'lockstep', 0.0, feedforward='inverse', direct=False)
    results, _ = run_client(context, nodes, plant, five_moves()[:3], positions=True)
    assert [(r.status, r.result.error_code) for r in results] == [(4, 0)] * 3
    ff = nodes[1].logic.controller
    assert ff.mismatches == 0


def test_lockstep_goals_composed_keep_the_feed_forward_on(context):
    # the nodes composed (direct calls): the trajectory logic hands each change of a goal's
    # reference to the controller's logic by call, before the reference of the sample it
    # changes at; a reference the controller did not bind would count as a mismatch
    plant, nodes = composed(context, 'lockstep', 0.0, feedforward='inverse')
    results, _ = run_client(context, nodes, plant, five_moves()[:3], positions=True)
    assert [(r.status, r.result.error_code) for r in results] == [(4, 0)] * 3
    ff = nodes[1].logic.controller
    assert ff.mismatches == 0


def test_composed_nodes_of_one_file_bind_nothing_more(context):
    # both nodes read the trajectory from the same file (as the launch files give it): the
    # controller's feed-forward has the trajectory played already and nothing is bound again;
    # an override on the trajectory node alone is bound at the first sample
    files = ['--ros-args', '--params-file', str(CONFIG_DIR / 'default.yaml'),
             '--params-file', str(CONFIG_DIR / 'scan_line.yaml')]
    controller = ControllerNode(context=context, cli_args=files, parameter_overrides=params(
        'controller_node', **{'feedforward.mode': 'inverse'}))
    for extra, bound in (({}, False), ({'scan_line.frequency_hz': 50.0}, True)):
        trajectory = TrajectoryNode(context=context, cli_args=files,
                                    parameter_overrides=[Parameter(k, value=v)
                                                         for k, v in extra.items()])
        stage_servo.bind_what_plays(controller, trajectory)
        queued = [t for _, t, _ in controller.logic._trajectories]
        assert queued == ([trajectory.logic.trajectory] if bound else [])
        controller.logic._trajectories.clear()
        trajectory.destroy_node()
    controller.destroy_node()
