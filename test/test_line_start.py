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
Starts, stops and line changes on the nodes' logic: the feed-forward follows the t = 0 played.

A trajectory node moves the trajectory's t = 0 at a start and at a new trajectory; a controller
that predicts from its own copy must bind the line at that stamp (a start of the same line keeps
what was learned), whatever the order its announcements come in.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

from fake_clock import FakeClock
import numpy as np
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.control.feedforward import FeedForwardController
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.hysteresis import HysteresisParams, make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant, Stage, StageParams
from piezo_stage_ros.hardware.pacing import Pacer
from piezo_stage_ros.nodes.logic import (
    announce_trajectory,
    ControllerLogic,
    line_print,
    parse_trajectory,
    TrajectoryLogic,
)
from piezo_stage_ros.nodes.servo import apply_change, servo_from_config
import pytest

T_S = 1e-4
PERIOD_NS = 100_000
LINE_100 = TrajectoryParams.from_flat({'kind': 'sine'})
LINE_137 = TrajectoryParams.from_flat({'kind': 'sine', 'sine.frequency_hz': 137.0})


def _feedforward(mode: str, trajectory: Any) -> FeedForwardController:
    ctrl = build_controller(ControllerParams().with_flat({'feedforward.mode': mode}), T_S,
                            linear_plant(StageParams().plant), make_hysteresis(HysteresisParams()))
    assert isinstance(ctrl, FeedForwardController)
    ctrl.bind(trajectory)
    return ctrl


class ThreeNodes:
    """
    Plant, trajectory node and controller node in lockstep, as three processes exchange them.

    Each sample: the trajectory node takes y_k (its references ahead when ``ahead``), publishes
    the announcement of a t = 0 first, then the references; the controller node takes the
    announcement (a trajectory built again from its parameters, as the node builds it), the
    references, then y_k, and the model stage takes its command.
    """

    def __init__(self, mode: str, *, ahead: int = 0) -> None:
        first = make_trajectory(LINE_100)
        self.params = {id(first): LINE_100}
        self.refs = TrajectoryLogic(first, sample_rate_hz=1.0 / T_S)
        self.ctrl = _feedforward(mode, make_trajectory(LINE_100))
        self.logic = ControllerLogic(self.ctrl, trajectory=self.ctrl._trajectory)
        self.stage = Stage(StageParams())
        self.y = self.stage.reset()
        self.ahead = ahead
        self.k = 0
        self.errors: list[float] = []
        self.estimates: list[tuple[float, float]] = []

    def switch(self, params: TrajectoryParams) -> None:
        trajectory = make_trajectory(params)
        self.params[id(trajectory)] = params
        self.refs.switch(trajectory)

    def run(self, samples: int, events: dict[int, Callable[[], None]] | None = None) -> None:
        for _ in range(samples):
            stamp = self.k * PERIOD_NS
            if events and self.k in events:
                events[self.k]()
            if self.ahead:
                out = self.refs.ahead(stamp, self.ahead)
            else:
                out = [(stamp, *self.refs.on_position(stamp, self.y))]
            at = self.refs.take_switch()
            if at is not None:
                text = announce_trajectory(at, self.params[id(self.refs.trajectory)])
                at_ns, params = parse_trajectory(text)
                self.logic.request_trajectory(make_trajectory(params), at_ns)
            for k_stamp, x, v in out:
                self.logic.on_reference(k_stamp, x, v)
            command = self.logic.on_position(stamp, self.y, self.k * T_S)
            assert command is not None
            x_d = self.logic._refs[stamp][0]
            self.errors.append(self.stage.position_m - x_d)
            d = self.ctrl.diagnostics()
            self.estimates.append((d['theta_hat'], d['phi_hat']))
            self.y = self.stage.step(command.voltage_v)
            self.k += 1


def test_a_line_print_tells_lines_apart_at_the_samples():
    assert line_print(make_trajectory(LINE_100), T_S) == \
        line_print(make_trajectory(LINE_100), T_S)
    assert line_print(make_trajectory(LINE_100), T_S) != \
        line_print(make_trajectory(LINE_137), T_S)
    shifted = TrajectoryParams.from_flat({'kind': 'sine', 'sine.offset_m': 15.1e-6})
    assert line_print(make_trajectory(shifted), T_S) != \
        line_print(make_trajectory(LINE_100), T_S)
    assert line_print(make_trajectory(TrajectoryParams.from_flat({'kind': 'step'})), T_S) \
        is None


def test_a_later_request_drops_what_was_queued_at_or_after_its_stamp():
    ctrl = _feedforward('inverse_learning', make_trajectory(LINE_100))
    logic = ControllerLogic(ctrl)
    first, second, third = (make_trajectory(LINE_137) for _ in range(3))
    logic.request_trajectory(first, 10 * PERIOD_NS)
    logic.request_trajectory(second, 20 * PERIOD_NS)
    logic.request_trajectory(third, 15 * PERIOD_NS)
    assert [(at, t) for at, t, _ in logic._trajectories] == \
        [(10 * PERIOD_NS, first), (15 * PERIOD_NS, third)]
    logic.request_trajectory(second)  # the next sample: before anything queued
    assert [(at, t) for at, t, _ in logic._trajectories] == [(None, second)]


@pytest.mark.parametrize('ahead', [0, 8])
def test_a_stop_and_start_inside_the_ahead_window_bind_the_line_that_plays(ahead):
    # lockstep_ahead: a new line announced at the first sample not yet sent (k + 8), then a
    # stop and a start before that stamp: the start's t = 0 comes earlier than the line's and
    # is announced after it. The controller must bind the line at the start's stamp alone (the
    # trajectory node streams it from there); binding both mismatches every sample after.
    nodes = ThreeNodes('inverse_learning', ahead=ahead)
    nodes.run(1000)
    assert nodes.ctrl.mismatches == 0
    nodes.run(2000, {1000: lambda: nodes.switch(LINE_137), 1002: nodes.refs.stop,
                     1004: nodes.refs.start})
    ctrl = nodes.ctrl
    assert ctrl.period_s == pytest.approx(1 / 137.0)
    # while stopped (a held reference the line does not play) the feed-forward is off; at
    # most those samples
    assert ctrl.mismatches <= 4
    assert ctrl.diagnostics()['ff_active'] == 1.0
    # and it learned the new line: the last period at the converter floor's order
    assert np.sqrt(np.mean(np.square(nodes.errors[-73:]))) < 5e-9


@pytest.mark.parametrize('mode', ['learning', 'inverse_learning'])
def test_a_start_after_a_stop_keeps_the_learned_table_from_the_new_t0(mode):
    nodes = ThreeNodes(mode)
    nodes.run(3000)
    learned = nodes.ctrl.learned().table_v.copy()
    periods = nodes.ctrl.periods_learned
    assert periods > 10 and np.max(np.abs(learned)) > 0.0
    # stopped less than a period: the held reference is no sample of the line (a stop of
    # whole periods holds x_d of a sample the line plays again: that one is learned)
    nodes.run(60, {3000: nodes.refs.stop, 3040: nodes.refs.start})
    ctrl = nodes.ctrl
    # bound again from the start's t = 0 with the table it had (nothing learned while the
    # reference was held), and matched from there on
    np.testing.assert_array_equal(ctrl.learned().table_v, learned)
    assert ctrl.diagnostics()['ff_active'] == 1.0
    assert ctrl.mismatches == 40
    mismatched = ctrl.mismatches
    nodes.run(300)
    assert ctrl.mismatches == mismatched
    assert ctrl.periods_learned >= periods  # not learned afresh
    if mode == 'learning':
        # the lines after the start play the table: far better than the run's first line
        first_line = np.sqrt(np.mean(np.square(nodes.errors[100:200])))
        again = np.sqrt(np.mean(np.square(nodes.errors[3140:3240])))
        assert again < 0.2 * first_line


def test_a_start_after_a_stop_holds_the_estimates_of_the_inverse_alone_over_its_start():
    nodes = ThreeNodes('inverse')
    hold = nodes.ctrl.start_hold
    assert hold > 0
    nodes.run(2000)
    nodes.run(400, {2000: nodes.refs.stop, 2200: nodes.refs.start})
    assert nodes.ctrl.diagnostics()['ff_active'] == 1.0
    # held from the start's sample over the start hold, as at the run's start
    held = nodes.estimates[2200:2200 + hold - 1]
    assert all(e == held[0] for e in held)
    assert nodes.estimates[0:hold - 1] == [nodes.estimates[0]] * (hold - 1)


# --- the servo (one process runs the three) ------------------------------------------------

def _servo(mode: str, duration_s: float) -> Any:
    from piezo_stage_ros.bench.servo import loop_config
    loop = loop_config()
    ff = loop.controller.feedforward.replace(mode=mode)
    loop = dataclasses.replace(loop, controller=loop.controller.replace(feedforward=ff),
                               trajectory=LINE_100)
    servo = servo_from_config(loop, duration_s)
    clock = FakeClock(per_read=300)
    servo.pacer = Pacer(PERIOD_NS, clock=clock, sleep=clock.sleep)
    servo.warm_up = lambda samples=0: 'skipped: off'
    return servo, loop


def _run_servo(servo: Any, changes: dict[int, list[tuple[str, Any]]]) -> None:
    def boundary() -> bool:
        for kind, value in changes.get(servo.index, []):
            apply_change(servo, kind, value)
        return True
    servo.boundary = boundary
    servo.run()
    assert servo.error is None


@pytest.mark.parametrize('together', [True, False])
def test_the_servo_binds_a_new_line_at_the_start_that_plays_it(together):
    # stopped, a new line, then a start: in one call, or the start later. The line's t = 0 is
    # the start's sample; the feed-forward must bind it there, not at the change
    servo, _ = _servo('inverse_learning', 0.3)
    start = 1000 if together else 1500
    changes = {500: [('active', False)], 1000: [('trajectory', LINE_137)]}
    changes.setdefault(start, []).append(('active', True))
    _run_servo(servo, changes)
    ctrl = servo.controller.controller
    assert ctrl.period_s == pytest.approx(1 / 137.0)
    assert ctrl.diagnostics()['ff_active'] == 1.0
    # only the stopped samples (held reference) were fed back alone
    assert ctrl.mismatches <= start - 500
    samples = servo.drain()
    tail = [s.position_m - s.reference_m for s in samples[-146:]]
    assert np.sqrt(np.mean(np.square(tail))) < 5e-9


def test_the_servo_restarts_the_same_line_with_its_table():
    servo, _ = _servo('learning', 0.4)
    _run_servo(servo, {2000: [('active', False)], 2040: [('active', True)]})
    ctrl = servo.controller.controller
    assert ctrl.diagnostics()['ff_active'] == 1.0 and ctrl.mismatches <= 40
    samples = servo.drain()
    after = [s.position_m - s.reference_m for s in samples[2141:2241]]
    first = [s.position_m - s.reference_m for s in samples[100:200]]
    assert np.sqrt(np.mean(np.square(after))) < 0.2 * np.sqrt(np.mean(np.square(first)))


def test_a_structural_change_in_the_servo_after_a_new_line_binds_that_line():
    # a changed learning gain rebuilds the feed-forward: it must be bound to the line that
    # plays, not to the one the servo started with
    servo, loop = _servo('inverse_learning', 0.3)
    ff = loop.controller.feedforward
    changed = loop.controller.replace(feedforward=ff.replace(
        learning_gain=0.5 * ff.learning_gain))
    _run_servo(servo, {500: [('trajectory', LINE_137)], 1500: [('controller', changed)]})
    ctrl = servo.controller.controller
    assert servo.controller.changes == 1 and ctrl.params.learning_gain == 0.5 * ff.learning_gain
    assert ctrl.period_s == pytest.approx(1 / 137.0)
    assert ctrl.diagnostics()['ff_active'] == 1.0 and ctrl.mismatches == 0


def test_the_servo_refuses_a_line_its_sample_rate_cannot_draw_before_the_servo_sees_it():
    from piezo_stage_ros.core.contracts.errors import ParameterError
    from piezo_stage_ros.nodes.servo import ServoProcess
    _, loop = _servo('none', 0.01)
    process = ServoProcess(loop, 0.01)
    try:
        fast = TrajectoryParams.from_flat({'kind': 'scan_line',
                                           'scan_line.frequency_hz': 1500.0})
        with pytest.raises(ParameterError, match='scan_line.frequency_hz'):
            process.change('trajectory', fast)
    finally:
        process.close()


# --- a new line rate, offline -----------------------------------------------------------------

def test_a_new_line_rate_holds_the_estimates_of_the_inverse_alone_over_its_start():
    # the new line's start moves the stage as a run's start does: adapting through it, the
    # estimates of `inverse` alone were left where that transient put them, and every line
    # after it paid for that (at the converter floor's scale: several times a run's own lines)
    from piezo_stage_ros.core.loop import experiments
    from test_feedforward import _controller, LOOP
    from test_feedforward_anyperiod import _rate_change
    changed = _rate_change('inverse', 100.0, 137.0, 0.5, 50)
    tp = TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(), 'kind': 'sine',
                                     'sine.frequency_hz': 137.0})
    rec = experiments.run_one(LOOP.stage, _controller('inverse'), tp,
                              duration_s=0.5 + 50 / 137.0, design_plant=LOOP.design_plant)
    assert rec.true_position_m is not None
    t = rec.time_s - rec.time_s[0]
    e = rec.true_position_m - rec.reference_m
    line = np.floor((t - 0.5) * 137.0 + 1e-9).astype(int)
    fresh = [float(np.sqrt(np.mean(e[line == j] ** 2))) for j in range(10, 50)]
    assert np.mean(changed[10:]) <= 1.5 * np.mean(fresh)


def test_the_seed_of_learning_alone_is_computed_at_the_request_not_in_the_sample():
    # learning alone seeds a new line's table from the model inverse's command; its inverse
    # hysteresis runs over periods of the line: in the sample's step it stalls the loop. Asked
    # for at the request, the step only adds the loop's own terms, to the same table
    def run(prepare: bool) -> tuple[Any, int]:
        first, new = make_trajectory(LINE_100), make_trajectory(LINE_137)
        ctrl = _feedforward('learning', first)
        if not prepare:
            ctrl.prepare = lambda trajectory: None  # type: ignore[method-assign]
        logic = ControllerLogic(ctrl, trajectory=first)
        refs = TrajectoryLogic(first, sample_rate_hz=1.0 / T_S)
        stage = Stage(StageParams())
        y = stage.reset()
        inverses = [0]
        inverse = ctrl._periodic_hysteresis_inverse

        def counted(w: Any) -> Any:
            inverses[0] += 1
            return inverse(w)
        ctrl._periodic_hysteresis_inverse = counted  # type: ignore[method-assign]
        for k in range(300):
            stamp = k * PERIOD_NS
            if k == 150:
                refs.switch(new)
            x, v = refs.on_position(stamp)
            at = refs.take_switch()
            if at is not None:
                logic.request_trajectory(new, at)
                in_request = inverses[0]
            logic.on_reference(stamp, x, v)
            command = logic.on_position(stamp, y, k * T_S)
            assert command is not None
            y = stage.step(command.voltage_v)
        assert ctrl.period_s == pytest.approx(1 / 137.0) and ctrl.mismatches == 0
        return ctrl.learned_table(), inverses[0] - in_request

    prepared, in_sample = run(True)
    inline, in_sample_inline = run(False)
    assert in_sample == 0 and in_sample_inline == 1
    np.testing.assert_array_equal(prepared, inline)
    assert np.max(np.abs(prepared)) > 0.0
