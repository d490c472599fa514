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

"""Commands ahead: the controller's predictions, played over samples the servo loop misses."""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
from piezo_stage_ros.bench.servo import loop_config, make_servo
from piezo_stage_ros.core.control.ahead import Ahead, CommandPredictor
from piezo_stage_ros.core.control.controllers import (
    build_controller,
    ControllerParams,
    SENSOR_GAIN_V_PER_M,
)
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.stage import StageParams
from piezo_stage_ros.hardware.bridge import ModelBridge
from piezo_stage_ros.hardware.pacing import Pacer
from piezo_stage_ros.nodes.logic import TrajectoryLogic
import pytest

T = 1e-4
PERIOD_NS = 100_000


def test_commands_ahead_move_the_model_part_along_the_reference_and_stay_in_range():
    x = np.array([1e-6, 2e-6, 60e-6])
    v = np.array([1e-3, 0.0, 0.0])
    # u_k = 1 V at x_d,k = 0.5 um, at rest: computed when read
    lazy = Ahead(x, v, 0, 3, 1.0 - 2e5 * 0.5e-6, (2e5, 1e2), -2.0, 10.0)
    out = list(lazy)
    expected = 1.0 + 2e5 * (x - 0.5e-6) + 1e2 * v
    np.testing.assert_allclose(out[:2], expected[:2], rtol=1e-12)
    assert out[2] == 10.0  # clipped to the command range
    # values, views, a narrower range, finiteness
    np.testing.assert_allclose(lazy.to_array(), out, rtol=1e-12)
    assert len(lazy[1:]) == 2 and lazy[1:][0] == lazy[1] and lazy[-1] == 10.0
    assert len(lazy[5:]) == 0 and lazy.clamped(0.0, 5.0)[2] == 5.0 and lazy.finite()
    assert not Ahead(x, v, 0, 3, math.nan, (1.0, 0.0)).finite()
    with pytest.raises(IndexError):
        lazy[3]


def test_the_trend_of_the_feedback_part_is_fitted_and_vanishes_at_rest():
    # a feedback part that is exactly f0 + alpha x + beta v along a sine: the fit finds them
    predictor = CommandPredictor(SENSOR_GAIN_V_PER_M, T)
    t = np.arange(2000) * T
    x = 3.8e-6 + 3.8e-6 * np.sin(2 * math.pi * 100 * t)
    v = 3.8e-6 * 2 * math.pi * 100 * np.cos(2 * math.pi * 100 * t)
    alpha, beta = 4e4, 30.0
    for xk, vk in zip(x, v):
        got = predictor.trend(0.1 + alpha * xk + beta * vk, xk, vk)
    # the ridge (1e-3 of each variance) biases each coefficient by about as much, relatively
    np.testing.assert_allclose(got, (alpha, beta), rtol=2e-3)
    # a reference at rest excites nothing: no trend, the feedback part is held
    rest = CommandPredictor(SENSOR_GAIN_V_PER_M, T)
    for k in range(500):
        trend = rest.trend(0.2 + 1e-3 * math.sin(k), 3.8e-6, 0.0)
    assert trend == (0.0, 0.0)


def test_the_reference_ahead_is_the_one_the_trajectory_plays():
    trajectory = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine'}))
    logic = TrajectoryLogic(trajectory, sample_rate_hz=1e4, chunk_s=0.005)
    played = TrajectoryLogic(trajectory, sample_rate_hz=1e4, chunk_s=0.005)
    logic.on_position(0)
    played.on_position(0)
    for k in (0, 40, 45, 300):
        logic.on_position(k * PERIOD_NS)
        x, v = logic.window(k * PERIOD_NS, 32)
        expected = [played.on_position(j * PERIOD_NS) for j in range(k + 1, k + 33)]
        np.testing.assert_array_equal(x, [e[0] for e in expected])
        np.testing.assert_array_equal(v, [e[1] for e in expected])
    logic.stop()
    logic.on_position(301 * PERIOD_NS)
    x, v = logic.window(301 * PERIOD_NS, 4)
    assert np.all(x == logic.hold_m) and np.all(v == 0.0) and len(x) == len(v) == 4


def test_the_simulated_stage_plays_its_queue_over_skipped_samples_then_holds():
    params = StageParams.from_flat({'plant.model': 'reduced'})
    bridge, model = ModelBridge(params), ModelBridge(params)
    bridge.safe_start(0.0)
    model.safe_start(0.0)
    bridge.write_commands(1.0, [2.0, 3.0])
    bridge.read_position()
    bridge.advance(3)
    expected = [model.stage.step(v) for v in (1.0, 2.0, 3.0, 3.0)]
    assert bridge.stage.position_m == model.stage.position_m and bridge.steps == 4
    # a plain write replaces the queue: the voltage is held
    bridge.write_voltage(0.5)
    bridge.read_position()
    bridge.advance(2)
    for _ in range(3):
        expected.append(model.stage.step(0.5))
    assert bridge.stage.position_m == model.stage.position_m


def test_a_missed_sample_goes_on_in_the_integral_with_the_error_it_most_likely_had():
    # the RAC: the last error relaxing to its recent mean, e_n = m + (e - m) r^n summed over
    # the n missed samples (r = exp(-1/10)); a short stall is nearly the last error carried, a
    # long one nearly the mean
    ctrl = build_controller(ControllerParams.from_flat({'type': 'rac', 'notch.mode': 'off'}),
                            T)
    ctrl.reset(0.0, 0.0)
    for y in (1e-8, 3e-8, -2e-8, 2e-8):
        ctrl.step(y, 0.0, 0.0)
    error = ctrl._e
    mean = 0.0
    for y in (1e-8, 3e-8, -2e-8, 2e-8):
        mean += (y * ctrl._k - mean) / 100.0  # from the reset's error, 0
    assert ctrl._e_mean == pytest.approx(mean, rel=1e-12) and mean != error
    r = math.exp(-0.1)
    for n in (1, 3, 60):
        before = ctrl._i
        ctrl.missed(n)
        expected = sum(mean + (error - mean) * r ** j for j in range(1, n + 1))
        assert ctrl._i == pytest.approx(before + T * expected, rel=1e-12)
    # the PI: the last error (its predictions hold its command)
    pi = build_controller(ControllerParams.from_flat({'type': 'pi', 'notch.mode': 'off'}), T)
    pi.reset(0.0, 0.0)
    pi.step(1e-8, 0.0, 0.0)
    before, error = pi._i, pi._e
    pi.missed(2)
    assert pi._i == pytest.approx(before + 2 * T * error, rel=1e-12)


def test_a_notch_after_missed_samples_filters_the_way_there_not_a_jump():
    # the notched controller's output after a gap equals a notch that was fed the same inner
    # commands with the gap filled in equal steps
    params = ControllerParams.from_flat({'type': 'open_loop'})
    ctrl = build_controller(params, T)
    plain = build_controller(params, T)
    ctrl.reset(0.0, 0.0)
    plain.reset(0.0, 0.0)
    refs = [0.0, 1e-6, 2e-6]
    for r in refs:
        assert ctrl.step(0.0, r, 0.0) == plain.step(0.0, r, 0.0)
    ctrl.missed(2)
    got = ctrl.step(0.0, 5e-6, 0.0)
    for r in (3e-6, 4e-6):
        plain.step(0.0, r, 0.0)
    assert got == pytest.approx(plain.step(0.0, 5e-6, 0.0), rel=1e-12)


def test_the_feed_forward_predicts_its_next_commands_from_its_tables():
    # inverse feed-forward around the RAC on its design model: the commands it predicts for the
    # next 32 samples against those it then gives; holding would be off by the reference's
    # whole change
    loop = loop_config()
    ctrl_params = dataclasses.replace(
        loop.controller, feedforward=dataclasses.replace(loop.controller.feedforward,
                                                         mode='inverse'))
    loop = dataclasses.replace(loop, controller=ctrl_params)
    predictions, commands, _ = servo_predictions(loop, 0.1, (700, 725, 750))
    for k, predicted in predictions.items():
        actual = commands[k + 1:k + 33]
        held = np.abs(actual - commands[k]).max()
        assert np.abs(predicted - actual).max() < 0.05 * held


def servo_predictions(loop, duration_s, at):
    """Run the servo with 32 commands ahead; return those predicted at ``at``, the commands."""
    servo = make_servo(loop, duration_s)
    servo.commands_ahead = 32
    clock = _Clock()
    servo.pacer = Pacer(PERIOD_NS, clock=clock, sleep=clock.sleep, spin_ns=0)
    predictions = {}
    servo.start()
    while servo.step():
        if servo.index in at:
            predictions[servo.index] = np.array(servo.plant._ahead)
    return predictions, np.array([s.command_v for s in servo.drain()]), servo


class _Clock:
    """A scripted monotonic clock [ns]: each sleep moves it to where it was asked."""

    def __init__(self) -> None:
        self.now = 10**9

    def __call__(self) -> int:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += round(seconds * 1e9)


CONFIGS = {
    'rac': {},  # Table III RAC, notched
    'pi': {'type': 'pi'},
    'rac_inverse': {'feedforward': {'mode': 'inverse'}},
}


def _stall_errors(config: str, at: int, skip: int, ahead: int) -> dict[int, float]:
    loop = loop_config()
    change = CONFIGS[config]
    params = loop.controller
    if 'type' in change:
        params = dataclasses.replace(params, type=change['type'])
    if 'feedforward' in change:
        params = dataclasses.replace(params, feedforward=dataclasses.replace(
            params.feedforward, **change['feedforward']))
    loop = dataclasses.replace(loop, controller=params)
    servo = make_servo(loop, (at + 250) * T)
    servo.commands_ahead = ahead
    clock = _Clock()
    servo.pacer = Pacer(PERIOD_NS, clock=clock, sleep=clock.sleep, spin_ns=0)
    servo.start()
    while servo.step():
        if servo.index == at and skip:
            # the next sample is taken (skip + 0.2) periods late: skip samples pass
            clock.now += (skip + 1) * PERIOD_NS + PERIOD_NS // 5
    got = servo.drain()
    assert servo.pacer.stats.skipped == skip
    return {s.k: s.position_m - s.reference_m for s in got if s.k > at}


def _stall_costs(config: str, at: int, skip: int) -> tuple[float, float]:
    # what the stall costs, the largest departure of the error from that of the same run
    # without it (200 samples after it), with the commands ahead and with the command held
    steady = _stall_errors(config, at, 0, 0)

    def cost(ahead: int) -> float:
        errors = _stall_errors(config, at, skip, ahead)
        return max(abs(e - steady[k]) for k, e in errors.items())

    return cost(loop_config().plant_node.servo.commands_ahead), cost(0)


@settings(max_examples=8, deadline=None, derandomize=True)
@given(at=st.integers(300, 400), skip=st.integers(1, 90))
def test_a_missed_sample_is_never_worse_with_the_commands_ahead_than_held(at, skip):
    # the RAC, a stall anywhere on the sine, up to 9 ms (the queue holds 12.8 ms; the command
    # timeout is 10 ms). Not claimed: a stall of a whole period of the reference (100 samples),
    # after which the held command happens to be right again, and the PI, whose predictions
    # (the trend of its command, no model part) cost up to a quarter more than holding at some
    # phases (docs/explanation/realtime.md)
    ahead, held = _stall_costs('rac', at, skip)
    assert ahead <= held


@pytest.mark.parametrize('at, skip', [(3, 30), (5, 60), (30, 60)])
def test_a_stall_in_the_start_costs_less_with_the_commands_ahead_than_held(at, skip):
    # a stall while the RAC still catches up with the reference (a loaded machine's start):
    # the trend of the feedback part is not taken from the few samples there are (its fit of a
    # transient cost up to 24 um at sample 5 against 4.9 um held), the model part moves on
    ahead, held = _stall_costs('rac', at, skip)
    assert ahead <= held


def test_a_stall_costs_the_feed_forward_less_with_its_predictions_than_held():
    # the same for the inverse feed-forward (its tables take seconds to build: one stall)
    ahead, held = _stall_costs('rac_inverse', 333, 20)
    assert ahead <= held


@pytest.mark.parametrize('change', [{}, {'notch.mode': 'off'}, {'type': 'pi'},
                                    {'feedforward.mode': 'inverse'}])
def test_the_trend_is_fitted_in_the_controllers_own_sensor_volts(change):
    # wrapped or not (notch, feed-forward), the fit's regressors are in the controller's k:
    # in metres they would fall below the at-rest floor and the trend would be lost
    loop = loop_config()
    params = ControllerParams.from_flat({**loop.controller.to_flat(), **change,
                                         'sensor_gain_v_per_m': 2e5})
    servo = make_servo(dataclasses.replace(loop, controller=params), 0.001)
    predictor = CommandPredictor(1.0, T)
    predictor.predict(servo.controller.controller, 4, 0.0, 0.0, 0.0,
                      lambda n: (np.zeros(n), np.zeros(n)))
    assert predictor._kx == 2e5 and predictor._kv == pytest.approx(2e5 * T, rel=1e-15)


def test_the_commands_ahead_at_once_are_the_ones_read_one_by_one():
    # what the UDP host packs (to_array) is what the simulated stage reads sample by sample,
    # bit for bit, clipped alike
    x = np.linspace(2e-6, 6e-6, 140)
    v = np.cos(np.linspace(0.0, 3.0, 140)) * 2e-3
    ahead = Ahead(x, v, 7, 135, 0.31, (4.7e5, 21.0), -2.0, 2.6)
    values = ahead.to_array()
    assert values.shape == (128,) and values.tolist() == list(ahead)
    assert values.max() == 2.6 and values.min() > -2.0  # the clip bites at the top
    assert ahead[10:20].to_array().tolist() == list(ahead)[10:20]


def test_a_predictor_that_only_observes_some_samples_predicts_as_one_that_predicts_all():
    # the UDP host skips the commands ahead of a late answer (observe): the trend's fit
    # must still take every sample, so that its next prediction is the same, bit for bit

    class Controller:
        _k = SENSOR_GAIN_V_PER_M

        def reference_gains(self) -> tuple[float, float]:
            return 2.5e5, 12.0

    controller = Controller()
    every, some = CommandPredictor(SENSOR_GAIN_V_PER_M, T), CommandPredictor(
        SENSOR_GAIN_V_PER_M, T)
    t = np.arange(400) * T
    x = 3.8e-6 + 3.8e-6 * np.sin(2 * math.pi * 100 * t)
    v = 3.8e-6 * 2 * math.pi * 100 * np.cos(2 * math.pi * 100 * t)
    u = 2.5e5 * x + 12.0 * v + 0.05 * np.sin(2 * math.pi * 300 * t)

    def window(k: int) -> Callable[[int], tuple[np.ndarray, np.ndarray]]:
        return lambda n: (x[k + 1:k + 1 + n], v[k + 1:k + 1 + n])

    for k in range(300):
        args = (float(u[k]), float(x[k]), float(v[k]))
        expected = every.predict(controller, 8, *args, window(k))
        if k % 3:
            some.observe(controller, *args)
        else:
            assert list(some.predict(controller, 8, *args, window(k))) == list(expected)
    assert every.trend(0.0, 0.0, 0.0) == some.trend(0.0, 0.0, 0.0) != (0.0, 0.0)
