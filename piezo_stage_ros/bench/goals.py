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
Joint-trajectory goals through the offline closed loop: the figures of the action's targets.

``python -m piezo_stage_ros.bench.goals [--config FILE] [--param ...] [--seed N]`` runs the
configured stage and controller (default: the paper's stage, the RAC) with goals followed by
:class:`~piezo_stage_ros.core.loop.follow.GoalFollower` and prints:

- five moves to random positions in 3-30 um, 20 ms each, goal tolerance 5 nm (a target the
  amplifier cannot reach is refused and named): the result of each, when it settled, the
  largest error while held;
- a goal beyond the travel: the refusal and its reason;
- 1 000 scan-line points (ten trace-and-retrace lines, 10 um, 1 ms apart), path tolerance
  10 nm: the path error reached with positions only (linear) and with velocities (cubic),
  without and with the inverse feed-forward;
- a quintic move of 16 um in 20 ms, alone, preempted and cancelled half-way, without and with
  the inverse feed-forward: the largest sample-to-sample change of the reference and of the
  command, beside the watchdog's slew, and the largest tracking error;
- what following costs a sample: ``GoalFollower.step`` with the reference given (as the loop
  has it from its block) and evaluating it itself, a block of 50 references, and preparing
  the 1 000 scan points (check and spline; the best of three timings, the machine may be
  shared).

A stage of several axes (``--config config/xy_stage.yaml --config config/xy_hold.yaml``) gets
its own case instead: five moves of every axis at once to random positions in 3-28 um, 20 ms
each, goal tolerance 5 nm on every joint, through the lockstep nodes' offline twin
(:func:`~piezo_stage_ros.core.loop.follow.run_axes_goals`), with the feed-forward as
configured and with the feedback alone: when each settled, and the largest error of the true
position on each axis from the first goal on.
"""

from __future__ import annotations

import argparse
import time
from typing import Any, Sequence

import numpy as np
from piezo_stage_ros import cli
from piezo_stage_ros.core.config.axes import has_axes
from piezo_stage_ros.core.config.loader import LoopConfig
from piezo_stage_ros.core.config.nodes import WatchdogParams
from piezo_stage_ros.core.contracts.wire import axis_joint_names, JOINT_NAME
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.loop.follow import FollowParams, GoalFollower, GoalRun, run_goals
from piezo_stage_ros.core.loop.goals import (
    AxisLimits,
    JointTolerance,
    JointTrajectoryGoal,
    TrajectoryPoint,
)
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant, Stage

__all__ = ['main', 'scan_lines']

PROG = 'bench.goals'
J = (JOINT_NAME,)


def scan_lines(lines: int = 10, per_line: int = 100, spacing_s: float = 1e-3,
               low_m: float = 5e-6, high_m: float = 15e-6, *, velocities: bool = True
               ) -> tuple[TrajectoryPoint, ...]:
    """
    Return trace-and-retrace scan lines as trajectory points.

    Parameters
    ----------
    lines : int
        Number of trace-and-retrace pairs.
    per_line : int
        Points per pair.
    spacing_s : float
        Time between points [s].
    low_m, high_m : float
        Ends of a line [m].
    velocities : bool
        Give each point the line's slope as velocity (0 at the turns and the end): cubic
        segments; False: positions only, linear segments.

    Returns
    -------
    tuple of TrajectoryPoint

    """
    half = per_line // 2
    slope = (high_m - low_m) / (half * spacing_s)
    points = []
    last = lines * per_line - 1
    for k in range(lines * per_line):
        j = k % per_line
        phase = j / half if j < half else 2.0 - j / half
        x = (low_m + (high_m - low_m) * phase,)
        v = 0.0 if j in (0, half) or k == last else (slope if j < half else -slope)
        points.append(TrajectoryPoint((k + 1) * spacing_s, x, (v,) if velocities else ()))
    return tuple(points)


def _loop(loop: LoopConfig, feedforward: str, x0: float) -> tuple[Stage, Any, GoalFollower]:
    stage_params = loop.stage
    cp = loop.controller if feedforward == 'none' else ControllerParams.from_flat(
        {**loop.controller.to_flat(), 'feedforward.mode': feedforward})
    controller = build_controller(cp, stage_params.sample_time_s,
                                  linear_plant(loop.design_plant),
                                  make_hysteresis(stage_params.hysteresis))
    limits = AxisLimits.from_stage(stage_params, travel_min_m=loop.trajectory.travel_min_m,
                                   travel_max_m=loop.trajectory.travel_max_m)
    follower = GoalFollower(J, [limits], [x0],
                            FollowParams(sample_time_s=stage_params.sample_time_s))
    return Stage(stage_params), controller, follower


def _moves(loop: LoopConfig, seed: int) -> None:
    rng = np.random.default_rng(seed)
    targets = rng.uniform(3e-6, 30e-6, 5)
    tol = (JointTolerance(JOINT_NAME, 5e-9),)
    gap_s = 0.05
    events = [(gap_s * i, JointTrajectoryGoal(J, (TrajectoryPoint(0.02, (float(x),)),),
                                              goal_tolerance=tol, goal_time_tolerance_s=0.02))
              for i, x in enumerate(targets)]
    run = run_goals(*_loop(loop, 'none', loop.stage.initial_position_m), events,
                    duration_s=gap_s * len(targets))
    dt = loop.stage.sample_time_s
    ended = {r.goal_id: r for r in run.results}
    print(f'five moves, 20 ms each, goal tolerance 5 nm (seed {seed}):')
    for (start, _), x, (_, verdict, gid) in zip(events, targets, run.verdicts):
        if not verdict.accepted:
            print(f'  {x * 1e6:6.2f} um  refused {verdict.code.name}: {verdict.reason}')
            continue
        r = ended[gid]
        k0, k1 = int(round(r.time_s / dt)), int(round((start + gap_s) / dt))
        held = float(np.max(np.abs(run.reference_m[k0:k1] - run.position_m[k0:k1])))
        print(f'  {x * 1e6:6.2f} um  {r.code.name} {(r.time_s - start - 0.02) * 1e3:.1f} ms '
              f'after the last point; largest |error| held after it: {held * 1e9:.2f} nm')


def _beyond(loop: LoopConfig) -> None:
    _, _, follower = _loop(loop, 'none', loop.stage.initial_position_m)
    for x in (30e-6, 39e-6):
        goal = JointTrajectoryGoal(J, (TrajectoryPoint(0.02, (x,)),))
        verdict = follower.check(goal, 0.0)
        print(f'goal to {x * 1e6:g} um: {verdict.code.name}: {verdict.reason}')


def _scan(loop: LoopConfig) -> None:
    print('1 000 scan points (10 lines of 10 um, 1 ms apart), path tolerance 10 nm:')
    for velocities in (False, True):
        for ff in ('none', 'inverse'):
            points = scan_lines(velocities=velocities)
            tol = (JointTolerance(JOINT_NAME, 10e-9),)
            goal = JointTrajectoryGoal(J, points, path_tolerance=tol,
                                       goal_tolerance=(JointTolerance(JOINT_NAME, 5e-9),),
                                       goal_time_tolerance_s=0.02)
            run = run_goals(*_loop(loop, ff, 5e-6), [(0.0, goal)], duration_s=1.02)
            free = run_goals(*_loop(loop, ff, 5e-6), [(0.0, JointTrajectoryGoal(J, points))],
                             duration_s=1.02)
            error = free.reference_m - free.position_m
            kind = 'cubic ' if velocities else 'linear'
            r = run.results[0]
            print(f'  {kind} feed-forward {ff:8s}: {r.code.name} at {r.time_s:.4f} s; '
                  f'unchecked run: max |path error| {np.max(np.abs(error)) * 1e9:.2f} nm, '
                  f'rms {np.sqrt(np.mean(error ** 2)) * 1e9:.2f} nm')


def _steps(run: GoalRun) -> tuple[float, float]:
    return (float(np.max(np.abs(np.diff(run.reference_m)))),
            float(np.max(np.abs(np.diff(run.command_v)))))


def _interrupt(loop: LoopConfig) -> None:
    first = JointTrajectoryGoal(J, (TrajectoryPoint(0.02, (20e-6,), (0.0,), (0.0,)),))
    other = JointTrajectoryGoal(J, (TrajectoryPoint(0.02, (8e-6,), (0.0,), (0.0,)),))
    slew = WatchdogParams().slew_v_per_s * loop.stage.sample_time_s
    print(f'quintic move 3.8 -> 20 um in 20 ms; stop acceleration '
          f'{FollowParams().stop_acceleration_mps2:g} m/s^2; watchdog slew {slew * 1e3:.0f} mV '
          'a sample:')
    cases = (('alone', [(0.0, first)]), ('preempted at 10 ms', [(0.0, first), (0.01, other)]),
             ('cancelled at 10 ms', [(0.0, first), (0.01, 'cancel')]))
    for ff in ('none', 'inverse'):
        for name, events in cases:
            run = run_goals(*_loop(loop, ff, loop.stage.initial_position_m), events,
                            duration_s=0.05)
            dx, du = _steps(run)
            error = float(np.max(np.abs(run.reference_m - run.position_m)))
            ends = ', '.join(f'{r.status.name}/{r.code.name}' for r in run.results)
            print(f'  feed-forward {ff:7s} {name:19s} largest step: reference '
                  f'{dx * 1e9:6.1f} nm, command {du * 1e3:6.1f} mV; max |error| '
                  f'{error * 1e9:7.1f} nm; {ends}')


def _cost(loop: LoopConfig) -> None:
    _, _, follower = _loop(loop, 'none', loop.stage.initial_position_m)
    dt = loop.stage.sample_time_s
    goal = JointTrajectoryGoal(J, (TrajectoryPoint(10.0, (20e-6,), (0.0,), (0.0,)),),
                               path_tolerance=(JointTolerance(JOINT_NAME, 1e-3),))
    follower.accept(goal, 0.0)
    n = 5000

    def best(body: Any) -> float:
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            body()
            times.append(time.perf_counter() - t0)
        return min(times) / n * 1e6

    given = best(lambda: [follower.step(k * dt, (5e-6,), (5e-6,)) for k in range(n)])
    itself = best(lambda: [follower.step(k * dt, (5e-6,)) for k in range(n)])
    block = best(lambda: [follower.reference(np.arange(k, k + 50) * dt) for k in range(n)])
    scan = JointTrajectoryGoal(J, scan_lines())
    prepare = []
    for _ in range(3):
        t0 = time.perf_counter()
        follower.prepare(scan, 0.0)
        prepare.append(time.perf_counter() - t0)
    print(f'cost: step {given:.1f} us a sample with the reference given, {itself:.1f} us '
          f'evaluating it; a block of 50 references {block:.1f} us '
          f'({block / 50:.2f} us a sample); preparing the 1 000 scan points '
          f'{min(prepare) * 1e3:.1f} ms')


def _axes_moves(config: Any, seed: int) -> None:
    from piezo_stage_ros.core.config.axes import axes_loop_config
    from piezo_stage_ros.core.control.axes import AxesController
    from piezo_stage_ros.core.loop.follow import run_axes_goals
    from piezo_stage_ros.core.model.axes import AxesStage
    from piezo_stage_ros.nodes.axes_logic import axes_follower
    base = axes_loop_config(config)
    joints = axis_joint_names(base.stage.names)
    rng = np.random.default_rng(seed)
    gap_s, move_s = 0.1, 0.02
    events = []
    for i in range(5):
        targets = rng.uniform(3e-6, 28e-6, len(joints))
        events.append((0.01 + gap_s * i, JointTrajectoryGoal(
            joints, (TrajectoryPoint(move_s, tuple(float(x) for x in targets)),),
            goal_tolerance=tuple(JointTolerance(j, 5e-9) for j in joints),
            goal_time_tolerance_s=0.02)))
    modes = [m.feedforward.mode for m in base.controllers]
    print(f'five moves of the axes {list(base.stage.names)} at once, {move_s * 1e3:g} ms each, '
          f'goal tolerance 5 nm on every joint (seed {seed}):')
    for label, loop in ((f'feed-forward {"/".join(modes)}', base),
                        ('feedback alone', axes_loop_config(config.with_overrides(
                            'controller_node', {'feedforward.mode': 'none'})))):
        ctrl = AxesController.build(loop.controllers, loop.stage, compensate=loop.compensate)
        run = run_axes_goals(AxesStage(loop.stage), ctrl, loop.trajectories(),
                             axes_follower(loop), events, duration_s=0.01 + gap_s * 5)
        settled = ', '.join(f'{r.code.name} {(r.time_s - t - move_s) * 1e3:.1f} ms'
                            for (t, _), r in zip(events, run.results))
        assert run.true_position_m is not None
        first = int(round(events[0][0] / loop.stage.sample_time_s))  # the start's own offset
        worst = np.max(np.abs(run.reference_m - run.true_position_m)[first:], axis=0)
        print(f'  {label}: {settled} after the last point; largest |error| of the true '
              'position from the first goal on: ' + ', '.join(f'{a} {w * 1e9:.1f} nm'
                                       for a, w in zip(loop.stage.names, worst)))


def main(argv: Sequence[str] | None = None) -> int:
    """Run the goal cases and print their figures; return the exit status."""
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split('\n\n')[0].strip())
    cli.add_config_options(parser)
    parser.add_argument('--seed', type=int, default=28, help='Seed of the five targets.')

    def body(args: argparse.Namespace) -> int:
        config = cli.read_config(args.config, args.param)
        if has_axes(config):
            _axes_moves(config, args.seed)
            return 0
        loop = cli.offline_loop(PROG, config)
        _moves(loop, args.seed)
        _beyond(loop)
        _scan(loop)
        _interrupt(loop)
        _cost(loop)
        return 0
    return cli.run_command(PROG, parser, body, argv)


if __name__ == '__main__':
    raise SystemExit(main())
