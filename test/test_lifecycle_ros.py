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
The managed plant node through its lifecycle services, and /diagnostics, under rclpy.

A manager node calls ``<plant>/change_state`` and ``get_state`` as ``ros2 lifecycle set``
does; the plant runs with the controller and trajectory nodes composed (``stage_servo
--direct``) or by topics. Skipped where rclpy (ROS 2 Jazzy) or lifecycle_msgs cannot be
imported; CI has neither, the logic is tested there by test_health.py.
"""

from __future__ import annotations

import math
import time

import pytest

rclpy = pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not importable here; '
                                           'the lifecycle and /diagnostics tests need it')
pytest.importorskip('lifecycle_msgs', reason='lifecycle_msgs (ROS 2 Jazzy) is not importable '
                                             'here; the lifecycle services need it')

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from lifecycle_msgs.msg import Transition  # noqa: E402
from lifecycle_msgs.srv import ChangeState, GetState  # noqa: E402
from piezo_stage_ros.nodes import stage_servo  # noqa: E402
from piezo_stage_ros.nodes.controller_node import ControllerNode  # noqa: E402
from piezo_stage_ros.nodes.plant_node import PlantNode  # noqa: E402
from piezo_stage_ros.nodes.runner import make_executor  # noqa: E402
from piezo_stage_ros.nodes.trajectory_node import TrajectoryNode  # noqa: E402
from rcl_interfaces.msg import Log  # noqa: E402
from rclpy.node import Node  # noqa: E402
import test_nodes_ros  # noqa: E402
from test_nodes_ros import (  # noqa: E402
    CONTROLLER,
    overrides,
    Probe,
    STAGE,
    TRAJECTORY,
)

SLEW_V_PER_S = 500.0
STEP_V = SLEW_V_PER_S * 1e-4  # a sample at 10 kHz
# rounding of the ramp's arithmetic: a part in 10^9 of a step (slew_toward's reach)
TOL = 1.0 + 1e-9


# the nodes' context, as the node tests make it
context = test_nodes_ros.context


class Manager(Node):
    """The lifecycle manager's side: the plant's services, and /diagnostics."""

    def __init__(self, context) -> None:
        super().__init__('manager', context=context)
        self.change = self.create_client(ChangeState, '/plant_node/change_state')
        self.get = self.create_client(GetState, '/plant_node/get_state')
        self.arrays: list[DiagnosticArray] = []
        self.create_subscription(DiagnosticArray, '/diagnostics', self.arrays.append, 100)


class Run:
    """The nodes on one executor, with the manager's calls."""

    def __init__(self, context, nodes) -> None:
        self.executor = make_executor('events', context)
        self.nodes = nodes
        self.manager = Manager(context)
        for node in [*nodes, self.manager]:
            self.executor.add_node(node)
        self.times: dict[str, float] = {}

    def call(self, client, request, timeout_s: float = 60.0):
        assert client.wait_for_service(timeout_sec=timeout_s), 'no lifecycle service'
        future = client.call_async(request)
        self.executor.spin_until_future_complete(future, timeout_sec=timeout_s)
        assert future.done(), 'the lifecycle service did not answer'
        return future.result()

    def transition(self, tid: int, label: str) -> bool:
        request = ChangeState.Request()
        request.transition.id = tid
        started = time.monotonic()
        ok = self.call(self.manager.change, request).success
        self.times[label] = time.monotonic() - started
        return bool(ok)

    def state(self) -> str:
        return str(self.call(self.manager.get, GetState.Request()).current_state.label)

    def spin_for(self, seconds: float, until=None) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end and not (until is not None and until()):
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        for node in [*self.nodes, self.manager]:
            self.executor.remove_node(node)
            node.destroy_node()
        self.executor.shutdown()


def composed(context, mode: str, extra: dict | None = None):
    common = {'mode': mode}
    plant = PlantNode(autostart=False, context=context, parameter_overrides=overrides(
        {**STAGE, **common, 'duration_s': 0.0, 'lockstep.subscribers': 3,
         'watchdog.slew_v_per_s': SLEW_V_PER_S, **(extra or {})}))
    probe = Probe(context)
    trajectory = TrajectoryNode(context=context, parameter_overrides=overrides(
        {**TRAJECTORY, **common}))
    controller = ControllerNode(context=context, parameter_overrides=overrides(
        {**CONTROLLER, **common}))
    return plant, probe, trajectory, controller


def report(run: Run, plant: PlantNode) -> None:
    # the figures of the report: transition round trips through the services, and the ramp
    print('transitions [ms]: ' + ', '.join(f'{k} {v * 1e3:.1f}' for k, v in run.times.items())
          + f'; ramp {plant.ramp}')


@pytest.mark.parametrize('mode, direct, process', [
    ('realtime', True, False), ('realtime', True, True), ('lockstep', True, False),
    ('lockstep', False, False)], ids=['realtime-thread', 'realtime-process',
                                      'lockstep-direct', 'lockstep-topics'])
def test_the_lifecycle_services_run_and_deactivate_within_the_slew(context, mode, direct,
                                                                   process):
    plant, probe, trajectory, controller = composed(context, mode, {'servo.process': process})
    if direct:
        stage_servo.connect_direct(plant, controller, trajectory)
    run = Run(context, [plant, probe, trajectory, controller])
    try:
        assert run.state() == 'unconfigured' and not probe.positions
        assert run.transition(Transition.TRANSITION_CONFIGURE, 'configure')
        assert run.state() == 'inactive'
        run.spin_for(0.5)
        assert not probe.positions, 'an inactive stage took samples'
        assert run.transition(Transition.TRANSITION_ACTIVATE, 'activate')
        assert run.state() == 'active'
        # into the sine: the command is volts away from the safe voltage
        run.spin_for(60.0, until=lambda: len(probe.positions) >= 300)
        assert len(probe.positions) >= 300
        assert run.transition(Transition.TRANSITION_DEACTIVATE, 'deactivate')
        assert run.state() == 'inactive'
        ramp = plant.ramp
        # no step beyond the slew; the stage holds the safe voltage afterwards
        assert ramp['slew_step_v'] == pytest.approx(STEP_V)
        assert ramp['max_step_v'] <= STEP_V * TOL
        # the ramp took the samples the slew needs from where it began (the guard's record)
        assert ramp['samples'] == math.ceil(abs(ramp['from_v'] - plant.guard.safe_v) / STEP_V
                                            - 1e-9)
        if not process:
            assert plant.guard.applied_v == plant.guard.safe_v == 0.0
            # the guard's largest step over the run: the ramp, or a watchdog trip of a loaded
            # machine, both bounded by the slew
            assert plant.guard.stats()['watchdog_max_step_v'] <= STEP_V * TOL
        else:
            assert plant.servo.stats()['stopped_at_v'] == 0.0
        taken = len(probe.positions)
        run.spin_for(0.5)
        assert len(probe.positions) - taken <= 100, 'the loop went on after the deactivate'
        # a stopped run is not resumed
        assert not run.transition(Transition.TRANSITION_ACTIVATE, 'activate again')
        assert run.state() == 'inactive'
        assert run.transition(Transition.TRANSITION_CLEANUP, 'cleanup')
        assert run.state() == 'unconfigured'
        assert run.transition(Transition.TRANSITION_UNCONFIGURED_SHUTDOWN, 'shutdown')
        assert run.state() == 'finalized' and plant.finished.done()
        report(run, plant)
    finally:
        run.close()


def test_a_refused_check_fails_configure_with_the_reason_logged(context):
    plant, probe, trajectory, controller = composed(context, 'realtime')
    stage_servo.connect_direct(plant, controller, trajectory)
    # the controller's own check passed at its start: this one stands for a refusal at
    # configure (gains changed meanwhile)
    plant.check = lambda: 'stability check: UNSTABLE (test)'
    run = Run(context, [plant, probe, trajectory, controller])
    try:
        run.spin_for(1.0)  # the probe's /rosout subscription discovered
        assert not run.transition(Transition.TRANSITION_CONFIGURE, 'configure')
        assert run.state() == 'unconfigured'
        run.spin_for(10.0, until=lambda: any(
            m.name == 'plant_node' and m.level == Log.ERROR
            and 'configure refused: stability check: UNSTABLE (test)' in m.msg
            for m in probe.logs))
        assert any(m.name == 'plant_node' and m.level == Log.ERROR and
                   'configure refused: stability check: UNSTABLE (test)' in m.msg
                   for m in probe.logs)
        # the real check of connect_direct passes: configure then succeeds
        stage_servo.connect_direct(plant, controller, trajectory)
        assert run.transition(Transition.TRANSITION_CONFIGURE, 'configure')
    finally:
        run.close()


def test_diagnostics_report_the_loop_watchdog_and_controller_about_once_a_second(context):
    plant, probe, trajectory, controller = composed(
        context, 'realtime', {'servo.process': False})
    controller.destroy_node()
    controller = ControllerNode(context=context, parameter_overrides=overrides(
        {'type': 'rac', 'stability.design_model': 'own', 'stability.plant.model': 'reduced',
         'mode': 'realtime'}))
    stage_servo.connect_direct(plant, controller, trajectory)
    # no probe on the per-sample topics: the executor serves /diagnostics, not a recorder
    probe.destroy_node()
    run = Run(context, [plant, trajectory, controller])
    names = {'plant_node: loop', 'plant_node: watchdog', 'controller_node: stability',
             'controller_node: estimates', 'trajectory_node: goals'}
    try:
        # unconfigured: the plant reports that, OK
        run.spin_for(30.0, until=lambda: any(
            s.name == 'plant_node: loop' for a in run.manager.arrays for s in a.status))
        first = [s for a in run.manager.arrays for s in a.status if s.name == 'plant_node: loop']
        assert first and dict((k.key, k.value) for k in first[0].values)['state'] == \
            'unconfigured'
        assert first[0].level == b'\x00'
        assert run.transition(Transition.TRANSITION_CONFIGURE, 'configure')
        assert run.transition(Transition.TRANSITION_ACTIVATE, 'activate')
        start = len(run.manager.arrays)

        def since() -> dict:
            return {s.name: s for a in run.manager.arrays[start:] for s in a.status}

        run.spin_for(60.0, until=lambda: names <= set(since()) and 'active' in
                     dict((k.key, k.value) for k in since()['plant_node: loop'].values)
                     .get('state', ''))
        got = since()
        assert names <= set(got)
        for status in got.values():
            assert status.hardware_id == 'piezo_stage'
            assert status.level in (b'\x00', b'\x01', b'\x02')
        loop = dict((k.key, k.value) for k in got['plant_node: loop'].values)
        assert loop['state'] == 'active' and int(loop['index']) > 0
        assert loop['backend'] == 'model'
        assert got['controller_node: stability'].level == b'\x00'
        estimates = dict((k.key, k.value) for k in got['controller_node: estimates'].values)
        assert {'theta_hat', 'phi_hat', 'theta_hat_bounds', 'phi_hat_bounds'} <= set(estimates)
        assert got['controller_node: estimates'].level in (b'\x00', b'\x01')
        run.spin_for(5.0)
        assert run.transition(Transition.TRANSITION_DEACTIVATE, 'deactivate')
        # the report's figure: the plant's arrays' spacing on the steady clock of the sender
        stamps = [a.header.stamp.sec + a.header.stamp.nanosec * 1e-9
                  for a in run.manager.arrays if any(s.name.startswith('plant_node')
                                                     for s in a.status)]
        print('diagnostics spacing [s]: ' + ', '.join(
            f'{b - a:.3f}' for a, b in zip(stamps, stamps[1:])))
    finally:
        run.close()
