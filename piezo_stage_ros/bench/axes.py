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
Multi-axis benchmark: what the controllers of 1 and 3 axes cost per sample.

The closed loop of ``config/xy_stage.yaml`` (one axis: its fast axis alone, as a one-axis
stage runs today) and of ``config/xyz_stage.yaml`` (three axes) runs offline; after the
learning has started on every axis (its first period passed), each sample's controller work is
timed on its own: every axis' step (feedback, model inverse, coupling compensation, learning)
and its commands ahead (``predict(ahead)``, turned into an array as the servo hands them on).
The stage is stepped between samples but not timed. Cases:

- ``today``: the one-axis controller (:func:`build_controller`) stepped directly, as the servo
  steps it now;
- ``axes-1``: the same through :class:`~piezo_stage_ros.core.control.axes.AxesController`
  (:meth:`~piezo_stage_ros.core.control.axes.AxesController.step_ahead`);
- ``axes-3``: three axes, in the one call a servo makes per sample
  (:meth:`~piezo_stage_ros.core.control.axes.AxesController.step_ahead`: the steps, then the
  commands ahead of the axes together); ``axes-3 per-axis``: the same with each axis'
  ``predict`` called on its own;
- the same without learning (``inverse``);
- ``servo-1``: the whole sample of the one-axis servo as deployed
  (:class:`~piezo_stage_ros.nodes.servo.ServoLoop` of the fast axis' one-axis configuration on
  the core model, ``servo.commands_ahead`` ahead): the guard's write and the model's step,
  the reference, the controller, the commands ahead, the queue to the ROS side;
  ``servo-axes-1`` / ``servo-axes-3``: the same for :class:`~piezo_stage_ros.nodes.servo_axes.
  AxesServoLoop` with one axis / the three axes (the model of three coupled axes stepped in the
  sample, as a real-time target's I/O would be); each sample is one ``step()`` of the loop on
  a clock that is always on time;
- ``batch-3`` against ``scalar-3``: the feedback alone (RAC and notch) of three axes, once
  with the numpy batch of :mod:`piezo_stage_ros.core.loop.batch` and once as three scalar
  controllers: why the axes are stepped as scalars.

Median and p99 per sample [us] (the run of the lowest median, and the lowest p99 of the runs),
in wall time and in the thread's CPU time (which a preemption by another process does not
count: on a shared machine the wall p99 is the scheduler's time slice). Timings are those of
a shared machine: compare them with each other.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable, Sequence

import numpy as np
from piezo_stage_ros import cli
from piezo_stage_ros.core.config.axes import axes_loop_config, AxesLoopConfig
from piezo_stage_ros.core.control.axes import AxesController
from piezo_stage_ros.core.control.controllers import build_controller
from piezo_stage_ros.core.model.axes import AxesStage
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant

__all__ = ['run_axes_benchmark']


def _loop(config: str, mode: str) -> AxesLoopConfig:
    return axes_loop_config(cli.read_config([config], [
        f'controller_node:feedforward.mode={mode}']))


def _percentiles(ns: list[int], cpu_ns: list[int] | None = None) -> dict[str, float]:
    a = np.asarray(ns, dtype=np.float64) / 1e3
    out = {'median_us': round(float(np.median(a)), 2),
           'p99_us': round(float(np.percentile(a, 99)), 2),
           'max_us': round(float(np.max(a)), 1)}
    if cpu_ns is not None:
        c = np.asarray(cpu_ns, dtype=np.float64) / 1e3
        out.update({'cpu_median_us': round(float(np.median(c)), 2),
                    'cpu_p99_us': round(float(np.percentile(c, 99)), 2)})
    return out


def _time_loop(loop: AxesLoopConfig, ctrl_step: Callable[[list[float], list[float],
                                                          list[float]], list[float]],
               predict: Callable[[], Any], bind: Callable[[Any], None],
               reset: Callable[[list[float], list[float]], None], *, warm_s: float,
               samples: int, axes: int | None = None) -> tuple[list[int], list[int]]:
    """Run the loop, timing step + predict of every sample after ``warm_s`` (wall, CPU)."""
    stage_params = loop.stage
    trajectories = list(loop.trajectories())
    stage = AxesStage(stage_params)
    if axes is not None:
        trajectories = trajectories[:axes]
    bind(trajectories)
    dt = stage_params.sample_time_s
    warm = int(round(warm_s / dt))
    total = warm + samples
    t = np.arange(total) * dt
    refs = np.column_stack([np.asarray(tr.evaluate(t)[0]) for tr in trajectories]).tolist()
    vels = np.column_stack([np.asarray(tr.evaluate(t)[1]) for tr in trajectories]).tolist()
    y = stage.reset()[:len(trajectories)]
    reset(y, refs[0])
    clock, cpu = time.perf_counter_ns, time.thread_time_ns
    out: list[int] = []
    out_cpu: list[int] = []
    pad = [0.0] * (stage.n - len(trajectories))
    for k in range(total):
        c0 = cpu()
        t0 = clock()
        u = ctrl_step(y, refs[k], vels[k])
        predict()
        t1 = clock()
        c1 = cpu()
        if k >= warm:
            out.append(t1 - t0)
            out_cpu.append(c1 - c0)
        y = stage.step(u + pad)[:len(trajectories)]
    return out, out_cpu


def _axes_case(loop: AxesLoopConfig, ahead: int, warm_s: float, samples: int, *,
               batched: bool = True) -> dict[str, float]:
    ctrl = AxesController.build(loop.controllers, loop.stage, compensate=loop.compensate)
    if not batched:
        predicts = [c.predict for c in ctrl.controllers]

        def predict() -> None:
            for p in predicts:
                np.asarray(p(ahead))
        return _percentiles(*_time_loop(loop, ctrl.step, predict, ctrl.bind, ctrl.reset,
                                        warm_s=warm_s, samples=samples))
    step_ahead = ctrl.step_ahead

    def step(y: list[float], r: list[float], v: list[float]) -> list[float]:
        return step_ahead(y, r, v, ahead)[0]
    return _percentiles(*_time_loop(loop, step, lambda: None, ctrl.bind, ctrl.reset,
                                    warm_s=warm_s, samples=samples))


def _per_axis_case(loop: AxesLoopConfig, ahead: int, warm_s: float, samples: int
                   ) -> dict[str, float]:
    return _axes_case(loop, ahead, warm_s, samples, batched=False)


def _today_case(loop: AxesLoopConfig, ahead: int, warm_s: float, samples: int
                ) -> dict[str, float]:
    sp = loop.stage.axes[0]
    c = build_controller(loop.controllers[0], sp.sample_time_s, linear_plant(sp.plant),
                         make_hysteresis(sp.hysteresis))
    step = c.step

    def one(y: list[float], r: list[float], v: list[float]) -> list[float]:
        return [step(y[0], r[0], v[0])]

    def bind(trs: Any) -> None:
        c.bind(trs[0])  # type: ignore[union-attr]

    def reset(y: list[float], r: list[float]) -> None:
        c.reset(y[0], r[0])
    predict = c.predict  # type: ignore[union-attr]
    return _percentiles(*_time_loop(loop, one, lambda: np.asarray(predict(ahead)), bind,
                                    reset, warm_s=warm_s, samples=samples, axes=1))


class _OnTime:
    """A clock at each sample's due time when read: the loop never waits, never skips."""

    def __init__(self, period_ns: int) -> None:
        self.period_ns = period_ns
        self.pacer: Any = None

    def __call__(self) -> int:
        pacer = self.pacer
        return int(pacer.t0_ns + (pacer.index + 1) * self.period_ns) if pacer.index >= 0 \
            else 0


def _servo_case(loop: AxesLoopConfig, ahead: int, warm_s: float, samples: int, *,
                axes: bool = True) -> dict[str, float]:
    """Time each whole sample (``step()``) of the servo loop after ``warm_s``."""
    from piezo_stage_ros.hardware.pacing import Pacer
    from piezo_stage_ros.nodes.servo import servo_from_config
    from piezo_stage_ros.nodes.servo_axes import axes_servo_from_config

    dt = loop.stage.sample_time_s
    warm = int(round(warm_s / dt))
    servo: Any
    if axes:
        servo = axes_servo_from_config(loop, 0.0, capacity=4096)
    else:
        # the one-axis configuration of the (first) axis, as a one-axis stage runs today
        one = dataclasses.replace(loop.base, stage=loop.stage.axes[0],
                                  controller=loop.controllers[0], trajectory=loop.lines[0])
        servo = servo_from_config(one, 0.0, capacity=4096)
    servo.commands_ahead = ahead
    clock = _OnTime(servo.pacer.period_ns)
    servo.pacer = clock.pacer = Pacer(clock.period_ns, clock=clock, sleep=lambda s: None)
    servo.warm_up()
    servo.start()
    wall, cpu = time.perf_counter_ns, time.thread_time_ns
    # the backend's step (the model's) timed inside the sample, to take it out as well: what
    # the sample costs with a backend whose I/O costs nothing
    bridge = servo.plant.bridge
    name = 'read_positions' if axes else 'read_position'
    read = getattr(bridge, name)
    spent = [0]

    def timed_read() -> Any:
        b0 = cpu()
        out = read()
        spent[0] += cpu() - b0
        return out
    setattr(bridge, name, timed_read)
    out: list[int] = []
    out_cpu: list[int] = []
    own_cpu: list[int] = []
    step, queue = servo.step, servo.samples
    for k in range(warm + samples):
        spent[0] = 0
        c0 = cpu()
        t0 = wall()
        step()
        t1 = wall()
        c1 = cpu()
        if k >= warm:
            out.append(t1 - t0)
            out_cpu.append(c1 - c0)
            own_cpu.append(c1 - c0 - spent[0])
        if len(queue) > 2048:
            queue.clear()  # the ROS side's drain, outside the timed sample
    servo.plant.stop()
    result = _percentiles(out, out_cpu)
    own = _percentiles(own_cpu)
    result['cpu_no_backend_median_us'] = own['median_us']
    result['cpu_no_backend_p99_us'] = own['p99_us']
    # the rare long samples (a period's end, a full collection) the p99 does not show
    result['cpu_p999_us'] = round(float(np.percentile(out_cpu, 99.9)) / 1e3, 1)
    result['cpu_max_us'] = round(max(out_cpu) / 1e3, 1)
    return result


def _servo_today_case(loop: AxesLoopConfig, ahead: int, warm_s: float, samples: int
                      ) -> dict[str, float]:
    return _servo_case(loop, ahead, warm_s, samples, axes=False)


def _feedback_cases(loop: AxesLoopConfig, samples: int) -> dict[str, dict[str, float]]:
    from piezo_stage_ros.core.loop.batch import ControllerBatch
    params = loop.controllers[0].with_flat({'feedforward.mode': 'none'})
    sp = loop.stage.axes[0]
    plant = linear_plant(sp.plant)
    batch = ControllerBatch(params, sp.sample_time_s, plant)
    y = np.full(3, 5e-6)
    batch.reset(y)
    ref, vel = np.full(3, 5e-6), np.zeros(3)
    clock = time.perf_counter_ns
    times_b = []
    for _ in range(samples):
        t0 = clock()
        batch.step(y, ref, vel)
        times_b.append(clock() - t0)
    scalars = [build_controller(params, sp.sample_time_s, plant) for _ in range(3)]
    for c in scalars:
        c.reset(5e-6, 5e-6)
    steps = [c.step for c in scalars]
    times_s = []
    for _ in range(samples):
        t0 = clock()
        [s(5e-6, 5e-6, 0.0) for s in steps]
        times_s.append(clock() - t0)
    return {'batch-3': _percentiles(times_b), 'scalar-3': _percentiles(times_s)}


def run_axes_benchmark(*, samples: int = 20000, ahead: int = 128, repeats: int = 3,
                       cases: Sequence[str] = ()) -> dict[str, Any]:
    """
    Run the cases of the module docstring and print one line each.

    Parameters
    ----------
    samples : int
        Timed samples per case (after the learning has started).
    ahead : int
        Commands ahead per axis and sample.
    repeats : int
        Runs per case; the one with the lowest median counts.
    cases : sequence of str
        Only these cases (names as printed, without the mode); empty: all.

    Returns
    -------
    dict
        {case: {median_us, p99_us, max_us}}.

    """
    out: dict[str, Any] = {'ahead': ahead, 'samples': samples}
    only = set(cases)
    for mode in ('inverse_learning', 'inverse'):
        xy, xyz = _loop('xy_stage.yaml', mode), _loop('xyz_stage.yaml', mode)
        # the learning starts after each axis' first period (1.28 s for the slow ones)
        warm = 1.3 if mode == 'inverse_learning' else 0.1
        all_cases: tuple[tuple[str, Callable[..., dict[str, float]], AxesLoopConfig], ...] = (
            ('today', _today_case, xy), ('axes-1', _axes_case, _one_axis(xy)),
            ('axes-3', _axes_case, xyz), ('axes-3 per-axis', _per_axis_case, xyz),
            ('servo-1', _servo_today_case, _one_axis(xy)),
            ('servo-axes-1', _servo_case, _one_axis(xy)), ('servo-axes-3', _servo_case, xyz))
        for name, case, loop in all_cases:
            if only and name not in only:
                continue
            runs = [case(loop, ahead, warm, samples) for _ in range(repeats)]
            best = dict(min(runs, key=lambda r: r['median_us']))
            # a shared machine preempts the loop now and then: the quietest run's p99 too
            best['p99_best_us'] = min(r['p99_us'] for r in runs)
            key = f'{name} {mode}'
            out[key] = best
            print(f'{key:36s} median {best["median_us"]:7.2f} us  p99 {best["p99_us"]:7.2f} us'
                  f' (quietest run {best["p99_best_us"]:7.2f} us)  max {best["max_us"]:8.1f} us;'
                  f' CPU time median {best["cpu_median_us"]:7.2f} us  p99 '
                  f'{best["cpu_p99_us"]:7.2f} us'
                  + ('; without the backend step: CPU median '
                     f'{best["cpu_no_backend_median_us"]:7.2f} us  p99 '
                     f'{best["cpu_no_backend_p99_us"]:7.2f} us; CPU p99.9 '
                     f'{best["cpu_p999_us"]:8.1f} us  max {best["cpu_max_us"]:8.1f} us'
                     if 'cpu_no_backend_median_us' in best else ''))
    if only and not only & {'batch-3', 'scalar-3'}:
        return out
    fb = _feedback_cases(_loop('xyz_stage.yaml', 'none'), samples)
    for key, best in fb.items():
        out[f'{key} feedback'] = best
        print(f'{key + " feedback":28s} median {best["median_us"]:7.2f} us  p99 '
              f'{best["p99_us"]:7.2f} us  max {best["max_us"]:8.1f} us')
    return out


def _one_axis(loop: AxesLoopConfig) -> AxesLoopConfig:
    """Return the fast axis of a loop alone, as a one-axis stage."""
    stage = loop.stage
    one = type(stage)(names=stage.names[:1], axes=stage.axes[:1])
    return loop.replace(stage=one, controllers=loop.controllers[:1], lines=loop.lines[:1],
                        scan=loop.scan.with_flat({'kind': 'each'}))
