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
The nodes under rclpy, in process, each test on its own context.

Skipped where rclpy (ROS 2 Jazzy) cannot be imported; CI has no rclpy, the logic these nodes
wrap is tested without it in test_nodes_logic.py and test_lockstep.py.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not importable here; '
                                            'the node logic is tested without it elsewhere')

from piezo_stage_ros.core.contracts import wire  # noqa: E402
from piezo_stage_ros.core.contracts.errors import ParameterError  # noqa: E402
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams  # noqa: E402
from piezo_stage_ros.core.loop.closed_loop import run  # noqa: E402
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams  # noqa: E402
from piezo_stage_ros.core.model.stage import linear_plant, Stage, StageParams  # noqa: E402
from piezo_stage_ros.hardware.emulator import TargetEmulator  # noqa: E402
from piezo_stage_ros.nodes import stage_servo  # noqa: E402
from piezo_stage_ros.nodes.controller_node import ControllerNode  # noqa: E402
from piezo_stage_ros.nodes.plant_node import PlantNode  # noqa: E402
from piezo_stage_ros.nodes.runner import make_executor  # noqa: E402
from piezo_stage_ros.nodes.trajectory_node import TrajectoryNode  # noqa: E402
from rcl_interfaces.msg import Log  # noqa: E402
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
from std_msgs.msg import Float64  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

STAGE = {'plant.model': 'reduced', 'chain.sensor_noise_std_m': 1e-9, 'seed': 3}
# in-process nodes get no parameter files: the controller is told the plant's model itself
CONTROLLER = {'type': 'pi', 'stability.design_model': 'own',
              'stability.plant.model': 'reduced'}
TRAJECTORY = {'kind': 'sine', 'sine.frequency_hz': 50.0}


@pytest.fixture
def context():
    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


def overrides(values: dict) -> list[Parameter]:
    return [Parameter(k, value=v) for k, v in values.items()]


# what a recorder subscribes with (config/record_qos.yaml): reliable and deep enough for a whole
# test run, so that a probe that is served late (a loaded machine, a batch of samples published
# in one callback) still gets every message instead of the newest 100
RECORD = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10000,
                    reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


class Probe(Node):
    """Records what goes over the stage topics, as a recorder does."""

    def __init__(self, context: Context) -> None:
        super().__init__('probe', context=context)
        self.positions: list[tuple[int, float]] = []
        self.references: list[float] = []
        self.commands: list[float] = []
        self.diagnostics: list[JointState] = []
        self.logs: list[Log] = []
        self.create_subscription(JointState, wire.POSITION, self._pos, RECORD)
        self.create_subscription(JointState, wire.DIAGNOSTICS, self.diagnostics.append, RECORD)
        self.create_subscription(Log, '/rosout', self.logs.append, RECORD)
        self.create_subscription(JointState, wire.REFERENCE,
                                 lambda m: self.references.append(m.position[0]), RECORD)
        self.create_subscription(Float64, wire.COMMAND,
                                 lambda m: self.commands.append(m.data), RECORD)

    def _pos(self, msg: JointState) -> None:
        stamp = msg.header.stamp
        self.positions.append((stamp.sec * 10 ** 9 + stamp.nanosec, msg.position[0]))


def loop(context: Context, mode: str, duration_s: float, plant_extra: dict | None = None,
         with_controller: bool = True, stage: dict = STAGE, controller: dict = CONTROLLER):
    common = {'mode': mode}
    plant = PlantNode(context=context, parameter_overrides=overrides(
        {**stage, **common, 'duration_s': duration_s, 'lockstep.subscribers': 3,
         **(plant_extra or {})}))
    nodes = [plant, Probe(context),
             TrajectoryNode(context=context, parameter_overrides=overrides(
                 {**TRAJECTORY, **common}))]
    if with_controller:
        nodes.append(ControllerNode(context=context, parameter_overrides=overrides(
            {**controller, **common})))
    return plant, nodes


def spin(context: Context, nodes: list[Node], future, timeout_s: float = 120.0,
         until=None) -> None:
    executor = make_executor('events', context)
    for node in nodes:
        executor.add_node(node)
    try:
        executor.spin_until_future_complete(future, timeout_sec=timeout_s)
        # the plant is done once it has the last command; the probe may not have it yet
        deadline = time.monotonic() + 10.0
        while until is not None and not until() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
    finally:
        for node in nodes:
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()


def offline(duration_s: float, stage: dict = STAGE, controller: dict = CONTROLLER):
    params = StageParams.from_flat(stage)
    cp = ControllerParams.from_flat({k: v for k, v in controller.items()
                                     if not k.startswith('stability.')})
    ctrl = build_controller(cp, params.sample_time_s, linear_plant(params.plant))
    traj = make_trajectory(TrajectoryParams.from_flat(TRAJECTORY))
    return run(Stage(params), ctrl, traj, duration_s=duration_s, record_diagnostics=False)


@pytest.mark.parametrize('stage, controller', [
    (STAGE, CONTROLLER),
    ({'plant.model': 'third_order', 'chain.sensor_noise_std_m': 2e-9, 'seed': 5},
     {'type': 'rac', 'stability.plant.model': 'third_order'}),
], ids=['pi-reduced', 'rac-third-order-noise'])
def test_composed_lockstep_run_equals_the_offline_runner(context, stage, controller):
    plant, nodes = loop(context, 'lockstep', 0.1, stage=stage, controller=controller)
    probe = nodes[1]
    spin(context, nodes, plant.finished, until=lambda: len(probe.commands) >= 1000)
    assert plant.finished.done() and plant.finished.exception() is None
    rec = offline(0.1, stage, controller)
    assert len(probe.positions) == 1000
    stamps = np.array([s for s, _ in probe.positions])
    np.testing.assert_array_equal(stamps, np.arange(1000) * 100_000)
    np.testing.assert_array_equal([p for _, p in probe.positions], rec.position_m)
    np.testing.assert_array_equal(probe.references, rec.reference_m)
    np.testing.assert_array_equal(probe.commands, rec.command_v)
    assert plant.finished.result()['resends'] == 0


@pytest.mark.parametrize('mode', ['lockstep', 'realtime'])
def test_direct_composition_equals_the_offline_runner(context, mode):
    # stage_servo --direct: samples go from node to node by call; the probe is an outside
    # subscriber and still gets every topic
    plant, nodes = loop(context, mode, 0.1)
    stage_servo.connect_direct(plant, nodes[3], nodes[2])
    probe = nodes[1]
    spin(context, nodes, plant.finished, until=lambda: len(probe.commands) >= 1000)
    stats = plant.finished.result()
    assert stats['late'] == 0
    if mode == 'lockstep':
        assert stats['index'] == 999
        rec = offline(0.1)
        np.testing.assert_array_equal([p for _, p in probe.positions], rec.position_m)
        np.testing.assert_array_equal(probe.references, rec.reference_m)
        np.testing.assert_array_equal(probe.commands, rec.command_v)
    else:
        # the servo loop: every sample taken gets its command in the same sample; a loaded
        # machine may make it skip samples (counted, no timing asserted); the samples taken
        # and the skipped ones make up the run
        taken = stats['paced_samples']
        assert stats['commands'] == taken and taken + stats['skipped'] == 1000
        assert 0 < len(probe.positions) <= taken


def test_lockstep_through_the_udp_bridge(context):
    with TargetEmulator(StageParams.from_flat(STAGE)) as emu:
        plant, nodes = loop(context, 'lockstep', 0.02,
                            {'backend': 'udp', 'bridge.port': emu.port,
                             'bridge.timeout_s': 0.5})
        spin(context, nodes, plant.finished, until=lambda: len(nodes[1].positions) >= 200)
    rec = offline(0.02)
    np.testing.assert_array_equal([p for _, p in nodes[1].positions], rec.position_m)
    assert emu.stop_reason == 'stop'


def test_realtime_run_counts_late_samples_and_finishes(context):
    plant, nodes = loop(context, 'realtime', 0.2)
    # after the run, until the probe has every position taken (or 10 s)
    spin(context, nodes, plant.finished, until=lambda: len(nodes[1].positions)
         >= plant.finished.result()['paced_samples'])
    stats = plant.finished.result()
    # sample 0 comes from the start, the others from the servo loop's clock; a loaded machine
    # may make it skip some (counted): taken and skipped make up the run
    assert stats['paced_samples'] + stats['skipped'] == 2000
    assert stats['samples'] == stats['paced_samples'] - 1
    stamps = np.array([st for st, _ in nodes[1].positions])
    # every sample taken is published (the probe queues as a recorder does), on the grid
    assert len(stamps) == stats['paced_samples']
    assert np.all(np.diff(stamps) > 0) and np.all((stamps - stamps[0]) % 100_000 == 0)
    # a sample that is not late used at least one fresh command (the first has none)
    assert stats['late'] + stats['commands'] >= stats['samples'] - 1


def test_realtime_plant_without_controller_drives_the_safe_voltage(context):
    plant, nodes = loop(context, 'realtime', 0.1, with_controller=False)
    spin(context, nodes, plant.finished)
    stats = plant.finished.result()
    # the watchdog trips once, command_timeout_s (10 ms = 100 periods) after the start; every
    # sample taken after that is at the safe voltage. A loaded machine makes the servo skip
    # samples (counted), so count the taken ones: at most 100 + 1 of them come before the trip
    # (the clock paces them no faster than one a period), whatever was skipped
    assert stats['watchdog_trips'] == 1
    assert stats['paced_samples'] + stats['skipped'] == 1000
    assert stats['safe_samples'] >= stats['paced_samples'] - 101


def test_parameters_are_declared_validated_and_refused_with_a_reason(context):
    ctrl = ControllerNode(context=context, parameter_overrides=overrides(CONTROLLER))
    try:
        desc = ctrl.describe_parameter('pi.k_p')
        assert 'V/V' in desc.description and desc.dynamic_typing
        assert ctrl.describe_parameter('type').read_only
        assert list(ctrl.describe_parameter('position_timeout_s').floating_point_range)
        bad = ctrl.set_parameters([Parameter('pi.k_p', value=-1.0)])[0]
        assert not bad.successful and "'pi.k_p' = -1.0 is out of range" in bad.reason
        wrong = ctrl.set_parameters([Parameter('pi.k_p', value='fast')])[0]
        assert not wrong.successful and 'is not a number' in wrong.reason
        ro = ctrl.set_parameters([Parameter('type', value='rac')])[0]
        assert not ro.successful and 'read-only' in ro.reason
        ok = ctrl.set_parameters([Parameter('pi.k_p', value=2)])[0]  # an int for a double
        assert ok.successful and ctrl.logic._pending.pi.k_p == 2.0
        assert ctrl.set_parameters([Parameter('stability.action', value='refuse')])[0].successful
        unstable = ctrl.set_parameters([Parameter('pi.k_i', value=1e7)])[0]
        assert not unstable.successful and 'UNSTABLE' in unstable.reason
        assert ctrl.get_parameter('pi.k_i').value == 1500.0
    finally:
        ctrl.destroy_node()
    with pytest.raises(ParameterError, match="'seed' = -1"):
        PlantNode(context=context, parameter_overrides=overrides({'seed': -1}))


def test_trajectory_services_start_and_stop(context):
    traj = TrajectoryNode(context=context, parameter_overrides=overrides(
        {**TRAJECTORY, 'active': False}))
    client_node = Node('client', context=context)
    executor = make_executor('events', context)
    executor.add_node(traj)
    executor.add_node(client_node)
    try:
        for name, active in (('start', True), ('stop', False)):
            client = client_node.create_client(Trigger, f'/trajectory_node/{name}')
            assert client.wait_for_service(timeout_sec=10.0)
            future = client.call_async(Trigger.Request())
            executor.spin_until_future_complete(future, timeout_sec=10.0)
            assert future.result().success
            assert traj.get_parameter('active').value is active
            assert traj.logic.active is active
        switched = traj.set_parameters([Parameter('kind', value='square')])[0]
        assert switched.successful and traj.logic._pending is not None
        refused = traj.set_parameters([Parameter('square.peak_to_peak_m', value=1.0)])[0]
        assert not refused.successful and 'square' in refused.reason
    finally:
        for node in (traj, client_node):
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()


def test_executable_prints_one_line_and_exits_2_on_a_bad_parameter(capsys):
    code = stage_servo.main(['stage_servo', '--ros-args', '-p', 'seed:=-1'])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err[-1].startswith('stage_servo: ') and "'seed' = -1" in err[-1]
    assert stage_servo.main(['stage_servo', '--nodes', 'plant,nothing']) == 2
    # a ROS argument rcl does not know: one line, no traceback
    capsys.readouterr()
    assert stage_servo.main(['stage_servo', '--ros-args', '--help']) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith('stage_servo: ROS arguments refused')


@pytest.mark.parametrize('process', [True, False])
def test_direct_realtime_takes_a_parameter_change_in_the_servo(context, process):
    # servo.process true: the trajectory node forwards the change to the servo process, which
    # applies it at a sample boundary; false: the servo thread reads the same logic object.
    # Stopped before the run starts: the process takes it at one of its first sample boundaries
    # (when the queue's pipe delivers it), the thread at sample 0; the reference is held from
    # there (an active 100 Hz sine would move over the second half of the 50 ms run)
    plant, nodes = loop(context, 'realtime', 0.05, {'servo.process': process})
    stage_servo.connect_direct(plant, nodes[3], nodes[2])
    assert nodes[2].set_parameters([Parameter('active', value=False)])[0].successful
    probe = nodes[1]
    # the servo (nice -20) may finish before the executor has delivered what it published:
    # spin on until the probe has a reference for every sample taken (at most 10 s more)
    spin(context, nodes, plant.finished, until=lambda: len(probe.references) >=
         plant.finished.result()['paced_samples'])
    stats = plant.finished.result()
    assert 'error' not in stats and stats['paced_samples'] + stats['skipped'] == 500
    refs = probe.references
    assert len(refs) > 100 and np.ptp(refs[len(refs) // 2:]) == 0.0


@pytest.mark.parametrize('process', [True, False])
def test_direct_realtime_publishes_the_controller_diagnostics(context, process):
    # the controller's internals of every diagnostics_every-th step, as in thread mode: from
    # the servo process they come through its ring, named by its controller
    plant, nodes = loop(context, 'realtime', 0.1, {'servo.process': process})
    stage_servo.connect_direct(plant, nodes[3], nodes[2])
    probe = nodes[1]
    every = nodes[3].opts.diagnostics_every
    spin(context, nodes, plant.finished, until=lambda: len(probe.diagnostics) >= -(
        -plant.finished.result()['controller_steps'] // every))
    stats = plant.finished.result()
    assert 'error' not in stats and stats['paced_samples'] + stats['skipped'] == 1000
    steps = stats['controller_steps']
    names = nodes[3].logic.names
    assert len(probe.diagnostics) == -(-steps // every) and len(names) > 1
    assert all(tuple(m.name) == names and len(m.position) == len(names)
               for m in probe.diagnostics)
    # on the sample grid, every-th controller step apart (more than that after a skip)
    stamps = np.array([m.header.stamp.sec * 10 ** 9 + m.header.stamp.nanosec
                       for m in probe.diagnostics])
    assert np.all(np.diff(stamps) >= every * 100_000) and np.all(np.diff(stamps) % 100_000 == 0)
    # the first step is the first sample taken
    assert stamps[0] == probe.positions[0][0]


@pytest.mark.parametrize('process', [True, False])
def test_direct_realtime_reports_an_applied_and_a_refused_option(context, process):
    # a CPU that does not exist is refused (EINVAL), the switch interval applied (5000 us:
    # CPython's default, nothing changes): the plant node logs one as a warning and the other
    # as information (rclpy refuses two severities at one call site: the node faulted) and
    # carries both in its status
    plant, nodes = loop(context, 'realtime', 0.05, {'servo.process': process,
                                                    'servo.cpu': 1000,
                                                    'servo.switch_interval_us': 5000.0})
    stage_servo.connect_direct(plant, nodes[3], nodes[2])
    probe = nodes[1]

    def logged(level: int, start: str) -> bool:
        return any(m.name == 'plant_node' and m.level == level and m.msg.startswith(start)
                   for m in probe.logs)

    spin(context, nodes, plant.finished,
         until=lambda: logged(Log.WARN, 'servo affinity: refused')
         and logged(Log.INFO, 'servo switch_interval: applied'))
    assert plant.finished.exception() is None
    stats = plant.finished.result()
    assert 'error' not in stats and stats['paced_samples'] + stats['skipped'] == 500
    assert stats['servo_affinity'].startswith('refused') and 'Invalid argument' in \
        stats['servo_affinity']
    assert stats['servo_switch_interval'].startswith('applied')
    assert logged(Log.WARN, 'servo affinity: refused')
    assert logged(Log.INFO, 'servo switch_interval: applied')


def test_the_controller_node_writes_its_learned_table_when_it_shuts_down(context, tmp_path):
    from piezo_stage_ros.core.control.feedforward import read_learned_table
    path = tmp_path / 'table.npz'
    ctrl = ControllerNode(context=context, parameter_overrides=overrides({
        **CONTROLLER, 'feedforward.mode': 'learning',
        'feedforward.save_table_file': str(path)}))
    # the start-up check knows the trajectory's period and the stage: the learning's ratio
    # over the slopes and the family is in its verdict
    assert 'harmonics of 0.01 s' in ctrl.verdict and 'over the stage family' in ctrl.verdict
    ctrl.destroy_node()
    # no parameter files: the default trajectory, a 100 Hz sine, 100 samples a period
    table = read_learned_table(path)
    assert table.samples == 100 and table.periods_learned == 0 and table.mode == 'learning'


def switched_run(context, change: dict, ahead: int = 0, controller_change: dict | None = None):
    """
    Run three nodes in lockstep for 0.3 s; ``change`` is set on the trajectory node at 0.1 s.

    ``controller_change``, if given, is set on the controller node at 0.2 s.
    """
    controller = {**CONTROLLER, 'feedforward.mode': 'inverse_learning'}
    plant = PlantNode(context=context, parameter_overrides=overrides(
        {**STAGE, 'mode': 'lockstep', 'duration_s': 0.3, 'lockstep.subscribers': 3}))
    probe = Probe(context)
    # no parameter files: both take the default trajectory, a 100 Hz sine
    traj = TrajectoryNode(context=context, parameter_overrides=overrides(
        {'mode': 'lockstep', 'lockstep_ahead': ahead}))
    ctrl = ControllerNode(context=context, parameter_overrides=overrides(
        {**controller, 'mode': 'lockstep'}))
    switched = []

    def switch_at_a_tenth_of_a_second(msg: JointState) -> None:
        stamp = msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec
        if stamp == 100_000_000 and not switched:
            switched.append(traj.set_parameters(overrides(change))[0].successful)
        if stamp == 200_000_000 and controller_change is not None:
            switched.append(ctrl.set_parameters(overrides(controller_change))[0].successful)

    probe.create_subscription(JointState, wire.POSITION, switch_at_a_tenth_of_a_second, RECORD)
    spin(context, [plant, probe, traj, ctrl], plant.finished,
         until=lambda: len(probe.commands) >= 3000)
    stats = plant.finished.result()
    assert switched == [True] * (1 + (controller_change is not None))
    assert stats['resends'] == 0 and len(probe.commands) == 3000
    return ctrl, probe


@pytest.mark.parametrize('ahead', [0, 8])
def test_the_controller_feedforward_follows_a_trajectory_switched_on_the_trajectory_node(
        context, ahead):
    # a new line rate set on the running trajectory node (ros2 param set): the controller in
    # its own node predicts from its own copy of the trajectory, so it must bind the new one
    # at the sample where it starts (announced on stage/trajectory), else its feed-forward
    # mismatches the reference and switches itself off
    ctrl, _ = switched_run(context, {'sine.frequency_hz': 137.0}, ahead)
    ff = ctrl.logic.controller
    assert ff.mismatches == 0 and ff.diagnostics()['ff_active'] == 1.0
    # the new line rate learned: 137 Hz is 72.99 samples a line, > 20 lines after the switch
    assert ff.learned().period_s == 1 / 137.0 and ff.periods_learned >= 3


def test_a_trajectory_the_learning_cannot_take_is_logged_and_the_loop_goes_on(context):
    # a step has no period to learn: the controller node says so and the run completes on
    # feedback (before, the feed-forward's error would have ended the controller's callback)
    _, probe = switched_run(context, {'kind': 'step'})
    assert any(m.name == 'controller_node' and m.level == Log.ERROR
               and 'cannot be learned' in m.msg for m in probe.logs)
    assert np.all(np.isfinite(probe.commands))


def test_a_rebuild_after_a_refused_trajectory_binds_the_one_the_loop_kept(context):
    # the refused step is not the feed-forward's trajectory: a later structural change (new
    # output limits: a new controller) binds the one kept, and the run completes (binding the
    # step would refuse the rebuild inside the sample callback and end the controller node)
    ctrl, probe = switched_run(context, {'kind': 'step'},
                               controller_change={'output_max_v': 9.5})
    assert np.all(np.isfinite(probe.commands)) and ctrl.logic.changes == 1
    ff = ctrl.logic.controller
    assert ff.output_limits_v[1] == 9.5 and ff.period_s == 1 / 100.0


Path = __import__('pathlib').Path
CONFIG_DIR = Path(__file__).resolve().parents[1] / 'config'


def test_a_misspelt_override_is_refused_before_the_loop_with_the_closest_name(capsys):
    from piezo_stage_ros.nodes import controller_node
    code = controller_node.main(['controller_node', '--ros-args', '-p', 'rac.gama:=100'])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert "'rac.gama'" in err[-1] and '-p rac.gama:=100' in err[-1]
    assert "did you mean 'rac.gamma'?" in err[-1]


def test_a_multi_axis_file_rcl_cannot_read_is_refused_saying_why(capsys, tmp_path):
    # rcl's own parser cannot read bare axis names (it reads y as a boolean): the line says
    # what to quote (the package's files quote them; the nodes run those: test_axes_nodes_ros)
    bare = tmp_path / 'bare.yaml'
    bare.write_text((CONFIG_DIR / 'xy_stage.yaml').read_text().replace("['x', 'y']", '[x, y]'))
    code = stage_servo.main(['stage_servo', '--ros-args', '--params-file',
                             str(CONFIG_DIR / 'default.yaml'), '--params-file', str(bare)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and 'bare.yaml' in err[-1] and "'axes.names'" in err[-1]
    assert 'multi-axis' in err[-1] and "names: ['x', 'y']" in err[-1]
    # a multi-axis key rcl can read given to the one-axis nodes is refused before their loop
    code = stage_servo.main(['stage_servo', '--ros-args', '-p',
                             'controller_node:axes.coupling_compensation:=true'])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "'axes.coupling_compensation'" in err[-1]
    assert 'multi-axis' in err[-1] and 'did you mean' not in err[-1]


def test_a_good_file_and_overrides_for_every_node_still_run(capfd):
    code = stage_servo.main(['stage_servo', '--ros-args', '--params-file',
                             str(CONFIG_DIR / 'default.yaml'), '-p', 'duration_s:=0.01',
                             '-p', 'seed:=4', '-p', 'use_sim_time:=false'])
    err = capfd.readouterr().err
    assert code == 0, err


def test_the_launch_file_runs_a_multi_axis_scenario_in_lockstep_or_composed_real_time():
    import importlib.util

    from launch.actions import DeclareLaunchArgument

    from launch import LaunchContext
    path = CONFIG_DIR.parent / 'launch' / 'closed_loop.launch.py'
    spec = importlib.util.spec_from_file_location('closed_loop_launch', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    context = LaunchContext()
    for action in module.generate_launch_description().entities:
        if isinstance(action, DeclareLaunchArgument):
            action.visit(context)
    context.launch_configurations.update({'config': str(CONFIG_DIR / 'default.yaml'),
                                          'scenario': str(CONFIG_DIR / 'xy_stage.yaml')})
    assert module._launch(context)
    # the merged parameter file ROS reads holds the axis names as strings (rcl reads a bare y
    # as true)
    from piezo_stage_ros.core.config.loader import load_config
    path = module._parameter_file(load_config([CONFIG_DIR / 'default.yaml',
                                               CONFIG_DIR / 'xy_stage.yaml']),
                                  {'plant_node': {}, 'trajectory_node': {}})
    text = Path(path).read_text()
    Path(path).unlink()
    assert "- 'y'" in text and "slow_axis: 'y'" in text
    # real time with several axes runs in the servo's composition only: refused without it
    # before any process starts
    context.launch_configurations['mode'] = 'realtime'
    with pytest.raises(ValueError, match="xy_stage.yaml: .*mode 'realtime' without --direct"):
        module._launch(context)
    context.launch_configurations.update({'direct': 'true', 'record': 'true'})
    assert module._launch(context)
    context.launch_configurations['mode'] = 'lockstep'
    with pytest.raises(ValueError, match='--direct in lockstep'):
        module._launch(context)
    context.launch_configurations.update({'direct': 'false', 'record': 'false'})
    # the one-axis default still gives its processes
    context.launch_configurations['scenario'] = ''
    assert module._launch(context)
