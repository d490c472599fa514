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
Simulation benchmark: how fast the offline closed loop, the batch stage and a controller run.

Figures (the issue's targets in brackets):

- simulated seconds per wall second of one stage + RAC at 10 kHz through
  :func:`piezo_stage_ros.core.loop.closed_loop.run`, per plant model (>= 20, aim 100);
- the same loop split into its parts: stage step, controller step, loop overhead [us/sample],
  so that a shortfall names what dominates;
- stage-steps per second of a :class:`~piezo_stage_ros.core.model.stage.StageBatch` of 1000 stages
  (>= 1e7);
- stage-steps per second of the batched closed loop
(:func:`piezo_stage_ros.core.loop.batch.run_batch`:
  RAC with the notch and 1000 stages, each its own member of the stage family, 16-bit
  converters and sensor noise on) (>= 1e7); the same with the feed-forward ``learning``
  (>= 5e6) and ``inverse_learning``;
- median and 99th percentile of one controller step, timed one by one with
  ``time.perf_counter_ns`` (the timer's own cost, measured on an empty call, is reported too).

Every figure is the best of ``repeats`` measurements: the machine is shared, and the best run is
the least disturbed estimate of what the code costs. Speeds are given per wall second and per
CPU second of this process (``time.process_time``, which leaves out the time other processes
take on a shared machine; single-threaded code, so the two agree on an idle machine). Timings
are noisy; treat them as such.
"""

from __future__ import annotations

from collections.abc import Callable
import math
import time
from typing import Any

import numpy as np
from piezo_stage_ros.core.control.controllers import (
    bound_controller,
    build_controller,
    ControllerParams,
)
from piezo_stage_ros.core.loop import closed_loop
from piezo_stage_ros.core.loop.batch import run_batch, StageFamilyBatch
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.family import member_params, sample_family
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant, Stage, StageBatch, StageParams

__all__ = ['batch_loop_speed', 'batch_speed', 'closed_loop_speed', 'controller_step_times',
           'loop_breakdown', 'run_sim_benchmark']


def _best(func: Callable[[], float], repeats: int) -> float:
    return min(func() for _ in range(max(repeats, 1)))


def closed_loop_speed(plant: str = 'third_order', controller: str = 'rac', *,
                      duration_s: float = 2.0, repeats: int = 3,
                      clock: Callable[[], float] = time.perf_counter) -> float:
    """
    Return simulated seconds per wall second of one closed loop at the configured rate.

    Parameters
    ----------
    plant : str
        Plant model (``'reduced'``, ``'third_order'``, ``'electromechanical'``).
    controller : str
        Controller type.
    duration_s : float
        Simulated time per measurement [s].
    repeats : int
        Measurements; the fastest counts.
    clock : callable
        ``time.perf_counter`` (wall time) or ``time.process_time`` (CPU time of this process,
        which leaves out the time other processes of a shared machine take).

    Returns
    -------
    float
        Simulated s / clock s (a 100 Hz sine, diagnostics recorded every 10 samples).

    """
    sp = StageParams().with_flat({'plant.model': plant})
    cp = ControllerParams(type=controller)
    tp = TrajectoryParams.from_flat({'kind': 'sine', 'sine.frequency_hz': 100.0})

    def once() -> float:
        stage = Stage(sp)
        ctrl = build_controller(cp, sp.sample_time_s)
        traj = make_trajectory(tp)
        t0 = clock()
        closed_loop.run(stage, ctrl, traj, duration_s=duration_s)
        return clock() - t0
    return duration_s / _best(once, repeats)


def loop_breakdown(plant: str = 'third_order', controller: str = 'rac', *,
                   steps: int = 100_000, repeats: int = 3) -> dict[str, float]:
    """
    Return the CPU cost of the parts of one loop sample [us] (``time.process_time``).

    Parameters
    ----------
    plant : str
        Plant model.
    controller : str
        Controller type.
    steps : int
        Samples per measurement.
    repeats : int
        Measurements; the fastest counts.

    Returns
    -------
    dict
        ``stage_us`` (``Stage.step`` alone), ``controller_us`` (``step`` alone), ``loop_us``
        (the whole closed loop per sample) and ``overhead_us`` (loop minus both parts:
        reference, recording, diagnostics).

    """
    sp = StageParams().with_flat({'plant.model': plant})
    cp = ControllerParams(type=controller)
    rng = np.random.default_rng(0)
    cmds = (1.3 + 0.5 * rng.standard_normal(steps)).tolist()
    positions = (3.8e-6 + 1e-7 * rng.standard_normal(steps)).tolist()

    def stage_once() -> float:
        step = Stage(sp).step
        t0 = time.process_time()
        for u in cmds:
            step(u)
        return time.process_time() - t0

    def ctrl_once() -> float:
        ctrl = build_controller(cp, sp.sample_time_s)
        ctrl.reset(3.8e-6, 3.8e-6)
        step = ctrl.step
        t0 = time.process_time()
        for y in positions:
            step(y, 3.8e-6, 0.0)
        return time.process_time() - t0

    stage_us = _best(stage_once, repeats) / steps * 1e6
    ctrl_us = _best(ctrl_once, repeats) / steps * 1e6
    loop_us = 1e6 / (closed_loop_speed(plant, controller, duration_s=steps * sp.sample_time_s,
                                       repeats=repeats, clock=time.process_time)
                     * sp.sample_rate_hz)
    return {'stage_us': stage_us, 'controller_us': ctrl_us, 'loop_us': loop_us,
            'overhead_us': loop_us - stage_us - ctrl_us}


def batch_speed(n: int = 1000, steps: int = 2000, *, plant: str = 'third_order',
                repeats: int = 3, clock: Callable[[], float] = time.perf_counter) -> float:
    """
    Return stage-steps per second of a :class:`StageBatch` of ``n`` stages.

    Parameters
    ----------
    n : int
        Stages in the batch.
    steps : int
        Samples per measurement.
    plant : str
        Plant model.
    repeats : int
        Measurements; the fastest counts.
    clock : callable
        Wall (``time.perf_counter``) or CPU (``time.process_time``) clock.

    Returns
    -------
    float
        n * steps / clock seconds.

    """
    sp = StageParams().with_flat({'plant.model': plant})
    rng = np.random.default_rng(0)
    commands = 1.3 + 0.5 * rng.standard_normal((steps, n))

    def once() -> float:
        batch = StageBatch(sp, n)
        step = batch.step
        t0 = clock()
        for row in commands:
            step(row)
        return clock() - t0
    return n * steps / _best(once, repeats)


def batch_loop_speed(n: int = 1000, steps: int = 5000, *, controller: str = 'rac',
                     feedforward: str = 'none', repeats: int = 3,
                     clock: Callable[[], float] = time.perf_counter) -> float:
    """
    Return stage-steps per second of the batched closed loop of ``n`` different stages.

    Parameters
    ----------
    n : int
        Stages: members drawn from the stage family (:func:`piezo_stage_ros.core.model.family.
        sample_family`, seed 0), each with its own gain, resonance, lag, hysteresis and sensor
        noise, on the configured third-order stage.
    steps : int
        Samples per measurement (a 100 Hz sine, nothing recorded).
    controller : str
        Controller type (the notch is on, as configured by default).
    feedforward : str
        ``feedforward.mode``, designed on the configured stage (:class:`~piezo_stage_ros.core.
        loop.batch.FeedForwardBatch`; learning: a table of one 100-sample period per member,
        updated every sample).
    repeats : int
        Measurements; the fastest counts.
    clock : callable
        Wall (``time.perf_counter``) or CPU (``time.process_time``) clock.

    Returns
    -------
    float
        n * steps / clock seconds of :func:`run_batch` (its reset and the feed-forward's design
        included; building the stages, which discretizes each member's plant, is not).

    """
    base = StageParams()
    stages = [member_params(base, m) for m in sample_family(n)]
    cp = ControllerParams(type=controller).with_flat({'feedforward.mode': feedforward})
    traj = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine'}))
    dt = base.sample_time_s
    plant, hysteresis = linear_plant(base.plant), make_hysteresis(base.hysteresis)

    def once() -> float:
        batch = StageFamilyBatch(stages)
        t0 = clock()
        run_batch(batch, cp, traj, duration_s=steps * dt, record=False, plant=plant,
                  hysteresis=hysteresis)
        return clock() - t0
    return n * steps / _best(once, repeats)


def controller_step_times(controller: str = 'rac', *, steps: int = 200_000,
                          feedforward: str = 'none', frequency_hz: float = 100.0
                          ) -> dict[str, float]:
    """
    Return the median and 99th percentile of one controller step [ns].

    Parameters
    ----------
    controller : str
        Controller type.
    steps : int
        Steps timed one by one.
    feedforward : str
        ``feedforward.mode`` (the feed-forward bound to the sine timed: its learning update
        runs at the end of every period, inside the timed steps).
    frequency_hz : float
        The sine's frequency: 100 Hz is a period of 100 samples (the table of samples), 70 Hz
        one of 142.86 (the table on the period's phase).

    Returns
    -------
    dict
        ``median_ns``, ``p99_ns``, ``max_ns`` of the step, and ``timer_ns``, the median of an
        empty timed call (already included in the step figures).

    """
    sp = StageParams()
    cp = ControllerParams(type=controller).with_flat({'feedforward.mode': feedforward})
    ctrl = bound_controller(cp, 1e-4, linear_plant(sp.plant), make_hysteresis(sp.hysteresis),
                            make_trajectory(TrajectoryParams.from_flat(
                                {'kind': 'sine', 'sine.frequency_hz': frequency_hz})))
    ctrl.reset(3.8e-6, 3.8e-6)
    step = ctrl.step
    clock = time.perf_counter_ns
    rng = np.random.default_rng(1)
    t = np.arange(steps) * 1e-4
    ref = (3.8e-6 + 3.8e-6 * np.sin(2 * np.pi * frequency_hz * t)).tolist()
    vel = (3.8e-6 * 2 * np.pi * frequency_hz * np.cos(2 * np.pi * frequency_hz * t)).tolist()
    pos = (np.asarray(ref) + 2e-8 * rng.standard_normal(steps)).tolist()
    out = np.empty(steps, dtype=np.int64)
    for k in range(steps):
        t0 = clock()
        step(pos[k], ref[k], vel[k])
        out[k] = clock() - t0
    empty = np.empty(10_000, dtype=np.int64)
    for k in range(empty.size):
        t0 = clock()
        empty[k] = clock() - t0
    return {'median_ns': float(np.median(out)), 'p99_ns': float(np.percentile(out, 99)),
            'max_ns': float(np.max(out)), 'mean_ns': float(np.mean(out)),
            'timer_ns': float(np.median(empty))}


def run_sim_benchmark(*, duration_s: float = 2.0, batch: int = 1000, batch_steps: int = 2000,
                      controller_steps: int = 200_000, repeats: int = 3,
                      echo: bool = True) -> dict[str, Any]:
    """
    Run every simulation figure and print one line each.

    Parameters
    ----------
    duration_s : float
        Simulated time of each closed-loop measurement [s].
    batch : int
        Stages in the batch measurement.
    batch_steps : int
        Samples of the batch measurement.
    controller_steps : int
        Controller steps timed one by one.
    repeats : int
        Measurements per figure; the fastest counts.
    echo : bool
        Print the figures.

    Returns
    -------
    dict
        ``realtime_<plant>`` (sim s / wall s, RAC), ``realtime_cpu_<plant>`` (per CPU s),
        ``breakdown_<plant>`` (dict, CPU us/sample), ``batch_steps_per_s``,
        ``batch_steps_per_cpu_s``, ``batch_loop_steps_per_s``, ``batch_loop_steps_per_cpu_s``,
        ``batch_loop_<mode>_steps_per_s`` and ``_per_cpu_s`` for ``learning`` and
        ``inverse_learning``,
        ``rac_step`` and ``pi_step`` (dicts, ns), and the targets.

    """
    def say(text: str) -> None:
        if echo:
            print(text, flush=True)

    out: dict[str, Any] = {'targets': {'realtime': 20.0, 'realtime_aim': 100.0,
                                       'batch_steps_per_s': 1e7,
                                       'batch_loop_steps_per_s': 1e7,
                                       'batch_loop_learning_steps_per_s': 5e6}}
    say('simulation benchmark (best of {} runs; the machine is shared, figures are noisy)'
        .format(repeats))
    for plant in ('reduced', 'third_order', 'electromechanical'):
        rt = closed_loop_speed(plant, 'rac', duration_s=duration_s, repeats=repeats)
        cpu = closed_loop_speed(plant, 'rac', duration_s=duration_s, repeats=repeats,
                                clock=time.process_time)
        out[f'realtime_{plant}'] = rt
        out[f'realtime_cpu_{plant}'] = cpu
        verdict = 'met' if rt >= 20 else 'NOT met'
        say(f'  closed loop, RAC + {plant:17s} {rt:6.1f} simulated s per wall s, {cpu:6.1f} per '
            f'CPU s ({rt * 1e4:,.0f} samples/s; target >= 20: {verdict})')
    for plant in ('reduced', 'third_order'):
        b = loop_breakdown(plant, 'rac', steps=max(int(duration_s * 1e4), 100),
                           repeats=repeats)
        out[f'breakdown_{plant}'] = b
        say(f'  per sample, {plant:11s}: stage {b["stage_us"]:.2f} us + RAC '
            f'{b["controller_us"]:.2f} us + loop {b["overhead_us"]:.2f} us = '
            f'{b["loop_us"]:.2f} us (CPU time)')
    bs = batch_speed(batch, batch_steps, repeats=repeats)
    bs_cpu = batch_speed(batch, batch_steps, repeats=repeats, clock=time.process_time)
    out['batch_steps_per_s'] = bs
    out['batch_steps_per_cpu_s'] = bs_cpu
    say(f'  StageBatch of {batch} (third_order): {bs:.3g} stage-steps per wall s, '
        f'{bs_cpu:.3g} per CPU s (target >= 1e7: {"met" if bs >= 1e7 else "NOT met"})')
    bl = batch_loop_speed(batch, repeats=repeats)
    bl_cpu = batch_loop_speed(batch, repeats=repeats, clock=time.process_time)
    out['batch_loop_steps_per_s'] = bl
    out['batch_loop_steps_per_cpu_s'] = bl_cpu
    # both verdicts: on a shared machine the wall figure moves with the others' load
    say(f'  batched closed loop, RAC + notch, {batch} family members (third_order, 16 bit, '
        f'noise): {bl:.3g} stage-steps per wall s, {bl_cpu:.3g} per CPU s (target >= 1e7: '
        f'{"met" if bl >= 1e7 else "NOT met"} per wall s, '
        f'{"met" if bl_cpu >= 1e7 else "NOT met"} per CPU s)')
    for mode in ('learning', 'inverse_learning'):
        fl = batch_loop_speed(batch, feedforward=mode, repeats=repeats)
        fl_cpu = batch_loop_speed(batch, feedforward=mode, repeats=repeats,
                                  clock=time.process_time)
        out[f'batch_loop_{mode}_steps_per_s'] = fl
        out[f'batch_loop_{mode}_steps_per_cpu_s'] = fl_cpu
        verdict = (f'target >= 5e6: {"met" if fl >= 5e6 else "NOT met"} per wall s, '
                   f'{"met" if fl_cpu >= 5e6 else "NOT met"} per CPU s'
                   if mode == 'learning' else 'no target')
        say(f'  the same + feed-forward {mode} (100 Hz sine, 100-sample table per member): '
            f'{fl:.3g} stage-steps per wall s, {fl_cpu:.3g} per CPU s ({verdict})')
    for ctype in ('rac', 'pi'):
        st = controller_step_times(ctype, steps=controller_steps)
        out[f'{ctype}_step'] = st
        say(f'  {ctype.upper():3s} step: median {st["median_ns"]:.0f} ns, p99 '
            f'{st["p99_ns"]:.0f} ns, max {st["max_ns"]:.0f} ns (timer alone '
            f'{st["timer_ns"]:.0f} ns, included)')
    base = out['rac_step']['median_ns']
    for mode in ('inverse', 'inverse_learning'):
        st = controller_step_times('rac', steps=controller_steps, feedforward=mode)
        out[f'rac_{mode}_step'] = st
        ratio = st['median_ns'] / base
        say(f'  RAC + notch + feed-forward {mode}: median {st["median_ns"]:.0f} ns '
            f'({ratio:.2f}x the RAC step; target <= 2x: {"met" if ratio <= 2.0 else "NOT met"}),'
            f' p99 {st["p99_ns"]:.0f} ns, max {st["max_ns"]:.0f} ns (the period-end learning '
            'update inside)')
    whole = out['rac_inverse_learning_step']['median_ns']
    for hz in (70.0, 300.0):
        st = controller_step_times('rac', steps=controller_steps, feedforward='inverse_learning',
                                   frequency_hz=hz)
        out[f'rac_inverse_learning_{hz:g}hz_step'] = st
        ratio = st['median_ns'] / whole
        say(f'  the same at {hz:g} Hz ({1e4 / hz:.2f} samples a period, the table on its '
            f'phase): median {st["median_ns"]:.0f} ns ({ratio:.2f}x the whole-period learning '
            f'step; target <= 1.2x: {"met" if ratio <= 1.2 else "NOT met"}), p99 '
            f'{st["p99_ns"]:.0f} ns, mean {st["mean_ns"]:.0f} ns, max {st["max_ns"]:.0f} ns '
            f'(servo sample 100000 ns)')
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in out.items()}
