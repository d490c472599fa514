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
What a real-time sample pays for: no whole feed-forward block, no full garbage collection.

The feed-forward of an aperiodic reference computes its next block a stage a step; these
tests hold it to the tables, commands and predictions of the block computed whole at its first
use (exactly: ``array_equal``), also where the reference changes under it or samples are
skipped. The servo loop freezes the garbage collector's view of what it built before its clock
starts, and gives it back at its end.
"""

from __future__ import annotations

import dataclasses
import gc
from typing import Any

from fake_clock import FakeClock
import numpy as np
from piezo_stage_ros.bench.servo import loop_config, make_servo
from piezo_stage_ros.core.config.loader import load_loop_config
from piezo_stage_ros.core.control.controllers import bound_controller
from piezo_stage_ros.core.control.feedforward import _Block, FeedForwardController
from piezo_stage_ros.core.loop.follow import FollowParams, GoalFollower, GoalTrajectory
from piezo_stage_ros.core.loop.goals import (
    AxisLimits,
    JointTolerance,
    JointTrajectoryGoal,
    TrajectoryPoint,
)
from piezo_stage_ros.core.loop.trajectories import make_trajectory
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant
from piezo_stage_ros.nodes import servo as servo_module
import pytest

T = 1e-4
LOOP = load_loop_config(['config/default.yaml', 'config/staircase.yaml'])
BLOCK = LOOP.controller.feedforward.block_samples


class _WholeBlocks(FeedForwardController):
    """The feed-forward with each block computed whole at its first use (no stage a step)."""

    _whole = False

    def _finish_block(self, work: _Block) -> None:
        self._whole = True
        try:
            super()._finish_block(work)
        finally:
            self._whole = False

    def _block_stage(self, work: _Block) -> None:
        if self._whole:
            super()._block_stage(work)


def _feedforward(trajectory: Any, whole: bool) -> FeedForwardController:
    params = dataclasses.replace(LOOP.controller, feedforward=dataclasses.replace(
        LOOP.controller.feedforward, mode='inverse'))
    ctrl = bound_controller(params, T, linear_plant(LOOP.design_plant),
                            make_hysteresis(LOOP.stage.hysteresis), trajectory)
    assert isinstance(ctrl, FeedForwardController)
    if whole:
        ctrl.__class__ = _WholeBlocks
    return ctrl


def _scan(lines: int) -> JointTrajectoryGoal:
    # triangular scan lines between 5 and 15 um, 10 ms each, as a client sends them
    points = []
    for k in range(100 * lines):
        j = k % 100
        phase = j / 50 if j < 50 else 2.0 - j / 50
        points.append(TrajectoryPoint((k + 1) * 1e-3, (5e-6 + 10e-6 * phase,)))
    return JointTrajectoryGoal(('stage',), tuple(points),
                               path_tolerance=(JointTolerance('stage', -1.0),))


def _follower() -> GoalFollower:
    follower = GoalFollower(('stage',), [AxisLimits.from_stage(LOOP.stage)], [5e-6],
                            FollowParams(sample_time_s=T))
    _, prepared = follower.prepare(_scan(2), 0.0)
    assert prepared is not None
    follower.start(prepared, 0.0)
    return follower


def _run(ctrl: FeedForwardController, trajectory: Any, samples: int, ahead: int,
         skips: dict[int, int], change: tuple[int, GoalFollower] | None
         ) -> tuple[list[float], list[np.ndarray], list[tuple[list[float], ...]], int]:
    """Step ``samples`` samples; return the commands, predictions, tables, staged steps."""
    commands, predictions, tables = [], [], []
    staged = 0
    k = 0
    while k < samples:
        if change is not None and k == change[0]:
            # the reference changes under the feed-forward (a goal's abort in the loop's
            # sample, seen by the controller's binding one sample later): nothing rebinds it
            change[1].hold(k * T)
        x, v = trajectory.evaluate(np.array([k * T]))
        y = float(x[0]) + 2e-9 * np.sin(0.01 * k)
        ahead_work = ctrl._block_ahead
        stage = ahead_work.stage if ahead_work is not None else -1
        commands.append(ctrl.step(y, float(x[0]), float(v[0])))
        if ctrl._block_ahead is ahead_work and ahead_work is not None and \
                ahead_work.stage > stage and not ahead_work.confirmed:
            staged += 1
        if ahead:
            predictions.append(ctrl.predict(ahead))
        tables.append((ctrl._lx_raw, ctrl._lx, ctrl._lv, ctrl._lw))
        gap = skips.get(k, 0)
        if gap:
            ctrl.skip(gap)
        k += 1 + gap
    return commands, predictions, tables, staged


@pytest.mark.parametrize('ahead', [0, 128, 8])
@pytest.mark.parametrize('reference', ['staircase', 'goal', 'goal_changed_at_first_read',
                                       'goal_changed_at_block_start'])
def test_the_blocks_computed_a_stage_a_step_are_the_ones_computed_whole(reference: str,
                                                                        ahead: int) -> None:
    samples = 4 * BLOCK + 37
    # skipped samples: one gap inside a block, one across a block's end
    skips = {BLOCK + 60: 5, 3 * BLOCK - 3: 9}
    runs = []
    for whole in (False, True):
        change = None
        if reference == 'staircase':
            trajectory: Any = make_trajectory(LOOP.trajectory)
        else:
            follower = _follower()
            trajectory = GoalTrajectory(follower)
            if reference == 'goal_changed_at_first_read':
                # the first step whose commands ahead read into the next block (or its start)
                change = (2 * BLOCK - 1 - ahead if ahead else 2 * BLOCK, follower)
            elif reference == 'goal_changed_at_block_start':
                change = (2 * BLOCK, follower)
        ctrl = _feedforward(trajectory, whole)
        runs.append(_run(ctrl, trajectory, samples, ahead, skips, change))
    (commands, predictions, tables, staged), (commands1, predictions1, tables1, staged1) = runs
    assert np.array_equal(commands, commands1)
    assert len(predictions) == len(predictions1)
    assert all(np.array_equal(a, b) for a, b in zip(predictions, predictions1))
    assert all(np.array_equal(np.array(a), np.array(b)) for a, b in zip(tables, tables1))
    # the stages ran in steps of their own (each at most once a step), computed whole never
    assert staged >= 3 * (_Block.STAGES - 1) and staged1 == 0
    # the tables follow the reference where it is the bound one (the model inverse acts)
    assert np.isfinite(commands).all()


def test_a_block_of_an_unchanged_reference_is_taken_from_its_stages() -> None:
    trajectory = make_trajectory(LOOP.trajectory)
    ctrl = _feedforward(trajectory, whole=False)
    whole = _feedforward(trajectory, whole=True)
    for k in range(BLOCK + _Block.STAGES + 1):
        x, v = trajectory.evaluate(np.array([k * T]))
        for c in (ctrl, whole):
            c.step(float(x[0]), float(x[0]), float(v[0]))
    staged, computed = ctrl._block_ahead, whole._block_ahead
    assert staged is not None and staged.done and staged.k == 2 * BLOCK
    assert computed is not None and computed.stage == 0
    # the next block, read ahead: the staged one as it is, the other computed whole now
    first = ctrl._peek_block()
    assert ctrl._block_ahead is staged
    for a, b in zip(first, whole._peek_block()):
        assert np.array_equal(a, b)


def test_the_servo_freezes_the_collector_over_its_run_and_gives_it_back() -> None:
    loop = loop_config()
    servo = make_servo(loop, 0.005)
    frozen = []
    servo.boundary = lambda: frozen.append(gc.get_freeze_count()) is None
    before = gc.get_freeze_count()  # Python 3.12 starts with some of its own frozen
    servo.run()
    assert servo.error is None and frozen and min(frozen) > before
    # given back: gc.unfreeze gives back all (there is no other way), the interpreter's too
    assert gc.get_freeze_count() == 0
    servo = make_servo(loop, 0.005)
    servo.freeze_gc = False
    frozen.clear()
    servo.boundary = lambda: frozen.append(gc.get_freeze_count()) is None
    servo.run()
    assert frozen and max(frozen) == 0


def test_loops_that_overlap_keep_the_collector_frozen_until_the_last_ends() -> None:
    before = gc.get_freeze_count()
    servo_module.freeze_gc()
    try:
        first = gc.get_freeze_count()
        assert first > before
        holder = [object()]  # built after the first froze: the second freezes it too
        servo_module.freeze_gc()
        assert gc.get_freeze_count() > first and holder
        servo_module.unfreeze_gc()
        assert gc.get_freeze_count() > 0
    finally:
        servo_module.unfreeze_gc()
    assert gc.get_freeze_count() == 0


def _servo_goals(ahead_blocks: bool) -> tuple[np.ndarray, list[Any], int]:
    """Hold, a move, then scan lines, on the servo of a process on an on-time clock."""
    loop = load_loop_config(['config/default.yaml', 'config/hold.yaml'])
    loop = dataclasses.replace(loop, controller=dataclasses.replace(
        loop.controller, feedforward=dataclasses.replace(loop.controller.feedforward,
                                                         mode='inverse')))
    servo = servo_module.servo_from_config(loop, 0.2, capacity=0)
    clock = FakeClock()
    servo.pacer = servo_module.Pacer(100_000, clock=clock, sleep=clock.sleep, spin_ns=0)
    logic = servo.trajectory
    assert logic is not None and logic.follower is not None
    if not ahead_blocks:
        # the follower's own: no block computed ahead
        del logic.follower.prepare
        del logic.follower.preparing
    rows: list[tuple[float, ...]] = []
    servo.on_sample = lambda s: rows.append((s.k, s.position_m, s.reference_m, s.command_v))
    events: list[Any] = []
    move = JointTrajectoryGoal(('stage',), (TrajectoryPoint(0.02, (5e-6,), (0.0,)),))
    plan = {100: (1, move), 600: (2, _scan(1))}
    computed = [0]
    ff = servo.controller.controller if servo.controller is not None else None
    assert isinstance(ff, FeedForwardController)

    def counted(self: FeedForwardController, k: int) -> _Block:
        # the blocks computed whole in the loop's own controller (not in a copy ahead)
        computed[0] += self is ff
        return _compute_block(self, k)

    def boundary() -> bool:
        while logic.events:
            events.append(logic.events.popleft()[:2])
        if servo.index in plan:
            # checked here, between samples, for the sample the lead puts it at
            token, goal = plan[servo.index]
            logic.goal(token, goal)
        return True

    servo.boundary = boundary
    FeedForwardController._compute_block = counted  # type: ignore[method-assign]
    try:
        servo.run()
    finally:
        FeedForwardController._compute_block = _compute_block  # type: ignore[method-assign]
    return np.array(rows), events, computed[0]


_compute_block = FeedForwardController._compute_block


def test_a_goals_first_block_computed_at_its_check_is_the_one_its_start_computes() -> None:
    ahead, events, computed = _servo_goals(True)
    at_start, events1, computed1 = _servo_goals(False)
    assert np.array_equal(ahead, at_start)
    assert [e[0] for e in events] == [e[0] for e in events1]
    # both goals accepted, and each one's first block came from its check
    assert [e for e in events if e[0] == 'verdict'] and computed == computed1 - 2
    assert np.isfinite(ahead).all() and ahead.shape[0] == 2000
