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
The managed stage and its /diagnostics content without rclpy.

The lifecycle rule, the deactivate ramp through the guard (lockstep and the real-time servo
loop, on the fake clock), and the statuses' levels computed from counters and from the
diagnostics a real controller reports.
"""

from __future__ import annotations

import math

from fake_clock import FakeClock
import numpy as np
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.stage import StageParams
from piezo_stage_ros.hardware.bridge import ModelBridge
from piezo_stage_ros.hardware.pacing import Pacer
from piezo_stage_ros.hardware.safety import GuardedPlant
from piezo_stage_ros.nodes.health import (
    controller_statuses,
    ERROR,
    estimates_status,
    GoalGate,
    goals_of,
    hardware_id,
    learning_status,
    loop_status,
    OK,
    stability_status,
    StageLifecycle,
    WARN,
    watchdog_status,
)
from piezo_stage_ros.nodes.logic import ControllerLogic, TrajectoryLogic
from piezo_stage_ros.nodes.servo import apply_change, ServoLoop
import pytest

PERIOD = 100_000
STAGE = {'plant.model': 'reduced', 'chain.sensor_noise_std_m': 1e-9, 'seed': 3}
TRAJ = {'kind': 'sine', 'sine.frequency_hz': 50.0}
SLEW = 500.0  # V/s: 0.05 V a sample at 10 kHz
STEP = SLEW * 1e-4


# --- the lifecycle rule ------------------------------------------------------------------------

def test_a_run_is_activated_once_and_a_cleanup_allows_a_new_one():
    life = StageLifecycle()
    assert life.activate() == 'not configured'
    assert life.configure() is None
    life.configured_ok()
    assert life.configure() == 'already configured'
    assert life.activate() is None
    life.activated()
    assert life.active and life.ran
    life.deactivated()
    assert not life.active
    assert 'not resumed' in life.activate()
    life.cleaned_up()
    assert not life.configured and life.configure() is None
    life.configured_ok()
    assert life.activate() is None


def test_goals_run_only_while_the_plant_is_active_and_end_when_it_leaves():
    gate = GoalGate()
    # no plant heard of (none managed, or not found yet): goals are taken
    assert gate.refusal() is None
    # heard inactive first: goals taken meanwhile end, new ones are refused with the state
    ended = gate.update('inactive')
    assert ended is not None and '(inactive)' in ended
    assert 'plant node is inactive' in gate.refusal()
    assert gate.update('activating') is None and 'is activating' in gate.refusal()
    assert gate.update('active') is None and gate.refusal() is None
    assert gate.update('active') is None
    for state in ('deactivating', 'shuttingdown', 'errorprocessing', 'faulted'):
        gate.update('active')
        ended = gate.update(state)
        assert ended is not None and f'left the active state ({state})' in ended
        assert 'slew' in ended and f'plant node is {state}' in gate.refusal()
    # the rest of a transition out of active ends nothing more
    gate.update('deactivating')
    for state in ('inactive', 'cleaningup', 'unconfigured', 'finalized'):
        assert gate.update(state) is None and f'is {state}' in gate.refusal()


# --- the deactivate ramp -----------------------------------------------------------------------

def test_the_lockstep_ramp_steps_to_the_safe_voltage_within_the_slew():
    params = StageParams.from_flat(STAGE)
    guard = GuardedPlant(ModelBridge(params), params.chain, 0.01, slew_v_per_s=SLEW,
                         sample_period_s=1e-4)
    guard.start(0.0)
    for _ in range(20):
        guard.step(7.3)
    applied = [guard.applied_v]
    stepped = guard.step

    def record(command_v: float) -> float:
        y = stepped(command_v)
        applied.append(guard.applied_v)
        return y

    guard.step = record  # type: ignore[method-assign]
    samples, largest = guard.ramp_to_safe()
    steps = np.abs(np.diff(applied))
    # 7.3 V at 0.05 V a sample: 146 samples, each a whole step (the last lands on 0 V)
    assert samples == math.ceil(7.3 / STEP - 1e-9) == len(applied) - 1
    assert np.all(steps <= STEP * (1 + 1e-9)) and largest == pytest.approx(STEP)
    assert applied[-1] == guard.safe_v and guard.phase == 'safe'
    # already at the safe voltage: nothing to step
    assert guard.ramp_to_safe() == (0, 0.0)


def servo(clock: FakeClock, kind: str = 'rac') -> ServoLoop:
    params = StageParams.from_flat(STAGE)
    ctrl = build_controller(ControllerParams.from_flat({'type': kind}), 1e-4)
    guard = GuardedPlant(ModelBridge(params), params.chain, 0.01, slew_v_per_s=SLEW,
                         sample_period_s=1e-4)
    return ServoLoop(guard, TrajectoryLogic(make_trajectory(TrajectoryParams.from_flat(TRAJ)),
                                            sample_rate_hz=1e4, chunk_s=1.0),
                     ControllerLogic(ctrl, mode='realtime'), sample_rate_hz=1e4,
                     pacer=Pacer(PERIOD, clock=clock, sleep=clock.sleep))


@pytest.mark.parametrize('kind', ['rac', 'pi'])
def test_the_servo_winds_down_within_the_slew_and_ends_at_the_safe_voltage(kind):
    loop = servo(FakeClock(per_read=300), kind)
    loop.start()
    for _ in range(60):  # into the sine: the command is volts away from the safe voltage
        loop.step()
    guard = loop.plant
    from_v = guard.applied_v
    assert abs(from_v - guard.safe_v) > 10 * STEP
    apply_change(loop, 'wind_down', None)  # as the servo process takes it
    steps = 0
    while loop.step():
        steps += 1
        assert steps < 10_000, 'the wind-down never ended'
    got = loop.drain()
    applied = np.array([s.applied_v for s in got])
    # each step() served a sample, the last (False: the run ended) too
    first = len(got) - (steps + 1)  # the first sample wound down
    ramp = applied[first - 1:]
    assert ramp[0] == pytest.approx(from_v)
    # no step beyond the slew, monotone toward the safe voltage, ending on it
    assert np.all(np.abs(np.diff(ramp)) <= STEP * (1 + 1e-9))
    assert np.all(np.diff(ramp) * np.sign(from_v - guard.safe_v) <= 0.0)
    assert guard.applied_v == guard.safe_v and loop.done
    want = math.ceil(abs(from_v - guard.safe_v) / STEP - 1e-9)
    assert guard.ramp_samples == want and guard.watchdog.trips == 0
    # the controller is not asked during the wind-down
    assert all(math.isnan(s.command_v) for s in got[first:])
    assert not any(math.isnan(s.command_v) for s in got[:first])
    assert loop.stats()['watchdog_max_step_v'] <= STEP * (1 + 1e-9)


def test_a_wind_down_during_a_watchdog_trip_is_a_ramp_of_its_own():
    params = StageParams.from_flat(STAGE)
    clock = FakeClock(per_read=300)
    guard = GuardedPlant(ModelBridge(params), params.chain, 0.01, slew_v_per_s=SLEW,
                         sample_period_s=1e-4)
    loop = ServoLoop(guard, None, None, sample_rate_hz=1e4,
                     pacer=Pacer(PERIOD, clock=clock, sleep=clock.sleep))
    loop.start()
    guard.command(9.0, clock.now / 1e9)  # then silence: the watchdog trips and ramps
    while guard.phase != 'ramp':
        loop.step()
    for _ in range(20):
        loop.step()
    from_v = guard.applied_v
    guard.wind_down()
    steps = 0
    while loop.step():
        steps += 1
        assert steps < 10_000, 'the wind-down never ended'
    guard.stop()
    silence, wound = loop.take_trips()
    assert silence.ended == 'wind down' and not silence.wind_down
    assert wound.wind_down and wound.from_v == pytest.approx(from_v)
    assert wound.ramp_samples == math.ceil(abs(from_v - guard.safe_v) / STEP - 1e-9)
    assert wound.max_step_v <= STEP * (1 + 1e-9) and guard.applied_v == guard.safe_v


# --- the statuses -------------------------------------------------------------------------------

def test_the_loop_warns_on_counters_that_grew_and_errs_after_a_fault():
    first = {'index': 99, 'late': 0, 'skipped': 0}
    ok = loop_status('plant_node', 'piezo_stage', first, None, 'active')
    assert ok.level == OK and ok.name == 'plant_node: loop' and ok.hardware_id == 'piezo_stage'
    assert dict(ok.values)['state'] == 'active' and ok.message == 'active: 100 samples'
    grew = loop_status('plant_node', 'x', {**first, 'index': 199, 'skipped': 3}, first, 'active')
    assert grew.level == WARN and 'skipped +3' in grew.message
    # the same counter no longer growing: OK again
    same = {**first, 'skipped': 3}
    assert loop_status('plant_node', 'x', same, same, 'active').level == OK
    bad = loop_status('plant_node', 'x', {**first, 'error': 'boom'}, first, 'active')
    assert bad.level == ERROR and 'boom' in bad.message


def test_the_watchdog_errs_while_tripped_and_warns_after_a_recovered_trip():
    stats = {'watchdog_trips': 1, 'ramp_samples': 10, 'watchdog_max_step_v': 0.05}
    assert watchdog_status('p', 'h', stats, {'watchdog_trips': 0}, 0.0, 'ramp').level == ERROR
    assert watchdog_status('p', 'h', stats, {'watchdog_trips': 0}, 0.0, 'safe').level == ERROR
    recovered = watchdog_status('p', 'h', stats, {'watchdog_trips': 0}, 1.2, 'track')
    assert recovered.level == WARN and dict(recovered.values)['applied_v'] == '1.2'
    assert watchdog_status('p', 'h', stats, stats, 1.2, 'track').level == OK


def test_the_estimates_of_a_real_rac_warn_at_a_projection_bound():
    params = ControllerParams.from_flat({'type': 'rac'})
    rac = params.rac
    ctrl = build_controller(params, 1e-4)
    names = ctrl.diagnostic_names
    bounds = {'theta_hat': (rac.theta_min, rac.theta_max), 'phi_hat': (rac.phi_min, rac.phi_max)}
    values = list(ctrl.diagnostic_values())
    status = estimates_status('controller_node', 'h', names, values, bounds)
    assert status is not None and status.level == OK  # the initial estimates are inside
    values[names.index('theta_hat')] = rac.theta_max
    at = estimates_status('controller_node', 'h', names, values, bounds)
    assert at is not None and at.level == WARN and 'theta_hat at upper bound' in at.message
    values[names.index('phi_hat')] = math.nan
    assert estimates_status('controller_node', 'h', names, values, bounds).level == ERROR
    # a PI has no estimates: no status
    pi = build_controller(ControllerParams.from_flat({'type': 'pi'}), 1e-4)
    assert estimates_status('c', 'h', pi.diagnostic_names, pi.diagnostic_values(),
                            bounds) is None


def test_the_learning_warns_when_the_period_error_grows():
    names = ('ff_active', 'ff_mismatches', 'ff_periods_learned', 'ff_period_rms_m', 'ff_u_v')
    good = learning_status('c', 'h', names, (1.0, 0.0, 5.0, 2e-9, 0.1), 3e-9)
    assert good is not None and good.level == OK and good.message == '5 periods learned'
    worse = learning_status('c', 'h', names, (1.0, 0.0, 6.0, 9e-9, 0.1), 3e-9)
    assert worse is not None and worse.level == WARN and 'not converging' in worse.message
    unmatched = learning_status('c', 'h', names, (0.0, 1.0, 6.0, 2e-9, 0.1), 3e-9)
    assert unmatched is not None and unmatched.level == WARN
    assert learning_status('c', 'h', ('theta_hat',), (1.5,), None) is None


def test_the_stability_verdict_and_the_controller_statuses():
    assert stability_status('c', 'h', 'STABLE ...', True, False).level == OK
    assert stability_status('c', 'h', 'STABLE ...', True, True).level == WARN
    assert stability_status('c', 'h', 'UNSTABLE ...', False, False).level == ERROR
    ctrl = build_controller(ControllerParams.from_flat({'type': 'rac'}), 1e-4)
    bounds = {'theta_hat': (1.05, 2.0), 'phi_hat': (2e-4, 9e-4)}
    only = controller_statuses('controller_node', 'h', None, bounds, 'STABLE', True, False,
                               None)
    assert [s.name for s in only] == ['controller_node: stability']
    every = controller_statuses('controller_node', 'h',
                                (ctrl.diagnostic_names, ctrl.diagnostic_values()), bounds,
                                'STABLE', True, False, None)
    assert [s.name for s in every] == ['controller_node: stability',
                                       'controller_node: estimates']


def test_one_hardware_id_per_stage_namespace():
    assert hardware_id('/') == hardware_id('') == 'piezo_stage'
    assert hardware_id('/left') == 'piezo_stage/left' != hardware_id('/right')


def test_the_goals_warn_after_a_violated_tolerance_under_the_trajectory_node_name():
    from piezo_stage_ros.core.loop.follow import GoalResult, goals_status, GoalStatus
    from piezo_stage_ros.core.loop.goals import ResultCode
    hw = hardware_id('/stage')
    calm = goals_of('trajectory_node', hw, goals_status('hold', None, None, 0, now_s=1.0))
    assert (calm.level, calm.name, calm.hardware_id) == (OK, 'trajectory_node: goals', hw)
    violated = GoalResult(3, GoalStatus.ABORTED, ResultCode.PATH_TOLERANCE_VIOLATED,
                          "path tolerance of 'stage' violated", 2.0)
    warn = goals_of('trajectory_node', hw, goals_status('hold', None, violated, 1, now_s=3.0))
    assert warn.level == WARN and 'PATH_TOLERANCE_VIOLATED' in warn.message
    assert dict(warn.values)['refused_goals'] == '1'
    later = goals_of('trajectory_node', hw, goals_status('hold', None, violated, 1, now_s=20.0))
    assert later.level == OK
