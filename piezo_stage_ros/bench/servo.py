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
Real-time benchmark without ROS: how well the paced servo loop holds 10 kHz on this machine.

Cases (each a run of ``duration_s`` wall seconds of ``config/table3_rac.yaml``: RAC, reduced
plant, 100 Hz sine):

- ``floor``: the bound of the machine: a thread that does nothing but read the monotonic clock
  (with the ``servo.*`` options applied), counting the gaps between two reads longer than a
  period and the periods they span. A loop that must take a sample every period skips at least
  that many on this machine in the same time;
- ``servo``: :class:`~piezo_stage_ros.nodes.servo.ServoLoop` on the core model in a thread, the
  main thread playing the ROS side (every 5 ms it drains the queue and encodes each sample's
  position, reference and command into CDR bytes, the work of publishing them), once with
  CPython's default switch interval (5 ms) and once with it lowered to 50 us;
- ``servo-alone``: the servo thread with nothing beside it (the bound of this machine);
- ``servo-process``: the servo loop in a process of its own, as ``stage_servo --direct`` runs
  it (:class:`~piezo_stage_ros.nodes.servo.ServoProcess`: spawned, no rclpy), handing each
  sample over through shared memory to this process, which does the same publishing work: no
  interpreter lock shared with it;
- ``bridge``: the servo process as the host of the UDP bridge (``backend: udp_stream``)
  against the emulator in its own process, the emulator pacing its own 10 kHz clock
  (``stage_emulator --paced``): the host answers each sample; reports the host's answer
  latency and the target's missing commands.

- ``stall``: no wall time: the servo loop on a scripted clock that stalls once, skipping 1, 2,
  5, 10 or 20 samples, where the sine is steepest (t = 0.5 s); the largest error over the 300
  samples after the stall, and after those (the controller's recovery), beside the same run
  without a stall; with the commands ahead configured (``servo.commands_ahead``, the stage
  plays the predictions over the missed samples) and with none (0: the last command held);
- ``ahead-cost``: what the commands ahead cost per sample: the servo loop on a scripted clock
  (no waiting) for ``duration_s`` of samples (at most 2 s) with ``servo.commands_ahead`` and
  with 0, the wall time per sample of each (best of 3) and of the prediction alone.

Per case: lateness p50 / p99 / max [us], samples late by more than half a period, skipped
samples, e_rms in the steady state beside that of the offline runner (lockstep) on the same
configuration. Timings are those of a shared machine: compare them with each other.
"""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
import threading
import time
from typing import Any, Callable

import numpy as np
from piezo_stage_ros import cli
from piezo_stage_ros.core.config.loader import LoopConfig
from piezo_stage_ros.core.config.nodes import ServoParams
from piezo_stage_ros.core.contracts.cdr import encode_float64, JointStateEncoder
from piezo_stage_ros.core.control.controllers import build_controller
from piezo_stage_ros.core.loop.closed_loop import run
from piezo_stage_ros.core.loop.metrics import error_metrics, steady_state_start
from piezo_stage_ros.core.loop.trajectories import make_trajectory
from piezo_stage_ros.core.model.stage import linear_plant, Stage
from piezo_stage_ros.hardware.bridge import Bridge
from piezo_stage_ros.hardware.pacing import Pacer, servo_setup
from piezo_stage_ros.nodes.servo import servo_from_config, ServoLoop, ServoProcess, ServoSample

__all__ = ['CASES', 'loop_config', 'run_servo_benchmark', 'steady_e_rms']

CASES = ('floor', 'servo-alone', 'servo', 'servo-process', 'bridge', 'stall', 'ahead-cost')
CONFIG = 'table3_rac.yaml'


def loop_config() -> LoopConfig:
    """Return the benchmark's loop: ``config/default.yaml`` + ``config/table3_rac.yaml``."""
    return LoopConfig.from_config(cli.read_config([CONFIG]))


def steady_e_rms(index: np.ndarray, position_m: np.ndarray, reference_m: np.ndarray,
                 sample_time_s: float, period_s: float) -> float:
    """Return e_rms [m] over the steady state (from the second period of the reference on)."""
    time_s = index * sample_time_s
    keep = time_s >= steady_state_start(time_s, period_s)
    return error_metrics(position_m[keep] - reference_m[keep])[1]


def make_servo(loop: LoopConfig, duration_s: float, bridge: Bridge | None = None, *,
               capacity: int = 65536,
               on_sample: Callable[[ServoSample], None] | None = None) -> ServoLoop:
    """Return the servo loop of ``loop`` on the model (or on ``bridge``)."""
    return servo_from_config(loop, duration_s, bridge, capacity=capacity, on_sample=on_sample)


def _ros_side_work(encoders: tuple[JointStateEncoder, JointStateEncoder]
                   ) -> Callable[[list[ServoSample]], None]:
    position, reference = encoders

    def publish(batch: list[ServoSample]) -> None:
        for s in batch:
            sec, nanosec = divmod(s.stamp_ns, 1_000_000_000)
            position.encode(sec, nanosec, (s.position_m,))
            reference.encode(sec, nanosec, (s.reference_m,), (s.velocity_mps,))
            encode_float64(s.command_v)
    return publish


def serve(servo: ServoLoop, *, ros_side: bool, opts: ServoParams
          ) -> tuple[dict[str, Any], list[ServoSample]]:
    """
    Run ``servo`` in a thread to its end, draining it here; return stats and samples.

    ``opts``: the servo thread's options (:func:`~piezo_stage_ros.hardware.pacing.servo_setup`,
    as the plant node applies them); the switch interval is restored at the end.
    """
    servo.pacer.spin_ns = round(opts.spin_us * 1000)
    old = sys.getswitchinterval()
    report: dict[str, str] = {}
    publish = _ros_side_work((JointStateEncoder(['stage']),
                              JointStateEncoder(['stage'], with_velocity=True)))
    got: list[ServoSample] = []
    try:
        thread = servo.start_thread(setup=lambda: report.update(
            servo_setup(opts, servo.pacer.period_ns)))
        while thread.is_alive():
            time.sleep(0.005)
            batch = servo.drain()
            if ros_side:
                publish(batch)
            got += batch
        got += servo.drain()
    finally:
        sys.setswitchinterval(old)
    stats = servo.stats()
    stats.update(report)
    return stats, got


def _figures(stats: dict[str, Any], got: list[ServoSample], loop: LoopConfig,
             offline_rms: float) -> dict[str, Any]:
    idx = np.array([x.k for x in got], dtype=np.float64)
    position_m = np.array([x.position_m for x in got])
    reference_m = np.array([x.reference_m for x in got])
    period = 1.0 / loop.stage.sample_rate_hz
    rms = steady_e_rms(idx, position_m, reference_m, period,
                       1.0 / loop.trajectory.sine.frequency_hz)
    keys = ('paced_samples', 'lateness_p50_us', 'lateness_p99_us', 'lateness_max_us',
            'late_half_period', 'skipped', 'queue_overruns', 'ring_missed', 'sched_fifo',
            'nice', 'rt_throttling')
    out = {k: stats.get(k) for k in keys}
    out['e_rms_nm'] = round(rms * 1e9, 2)
    out['offline_e_rms_nm'] = round(offline_rms * 1e9, 2)
    if 'error' in stats:
        out['error'] = stats['error']
    return out


def serve_process(loop: LoopConfig, duration_s: float
                  ) -> tuple[dict[str, Any], list[ServoSample]]:
    """
    Run the servo loop of ``loop`` in a process, as ``stage_servo --direct`` does.

    A :class:`~piezo_stage_ros.nodes.servo.ServoProcess`; this process plays the ROS side on
    what it hands over (:meth:`~piezo_stage_ros.nodes.servo.ServoProcess.drain`, as the plant
    node does, then the publishing work of :func:`serve`). Returns the loop's figures (with
    its real-time setup and ``ring_missed``) and every sample read from the ring.
    """
    publish = _ros_side_work((JointStateEncoder(['stage']),
                              JointStateEncoder(['stage'], with_velocity=True)))
    got: list[ServoSample] = []
    process = ServoProcess(loop, duration_s)
    try:
        process.start()
        while True:
            alive = not process.finished
            time.sleep(0.005)
            batch = process.drain()
            publish(batch)
            got += batch
            if not alive:
                break
        stats = dict(process.stop(timeout_s=30.0))
        stats.update(process.setup_report)
        stats['ring_missed'] = process.missed
    finally:
        process.close()
    return stats, got


def run_bridge(loop: LoopConfig, duration_s: float, offline_rms: float) -> dict[str, Any]:
    """
    Run the servo process as the host of the UDP bridge against a target-paced emulator.

    The emulator (``stage_emulator --paced``) owns the 10 kHz clock in its own process, as a
    real-time target would; the host is the servo loop of ``stage_servo --direct`` with
    ``backend: udp_stream`` in its own process (:func:`serve_process`), answering each sample.
    Returns the host's figures (lateness: arrival of each sample against the grid of the
    first), its answer latency (sample arrived to command sent), the samples it overtook and
    the answers it sent again with their commands ahead, and the target's: missing commands,
    samples that played a command ahead and its own clock's lateness. The target's clock gets
    the same ``servo.*`` options as the host's loop.
    """
    opts = loop.plant_node.servo
    args = [sys.executable, '-m', 'piezo_stage_ros.hardware.emulator', '--config', CONFIG,
            '--paced', '--port', '0', '--idle-timeout-s', '5',
            '--fifo-priority', str(opts.fifo_priority), '--spin-us', f'{opts.spin_us:g}',
            '--nice', str(opts.nice)]
    target = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True)
    lines: list[str] = []
    try:
        assert target.stdout is not None
        while True:
            line = target.stdout.readline()
            if not line:
                raise RuntimeError('stage_emulator ended: ' + ''.join(lines))
            lines.append(line)
            if 'listening on' in line:
                port = int(line.rsplit(':', 1)[1])
                break
        # a generous wait: on a loaded machine the target process may stall; that is counted
        node = dataclasses.replace(
            loop.plant_node, mode='realtime', backend='udp_stream',
            bridge=dataclasses.replace(loop.plant_node.bridge, port=port, timeout_s=1.0))
        stats, got = serve_process(dataclasses.replace(loop, plant_node=node), duration_s)
        lines += target.communicate(timeout=30)[0].splitlines(keepends=True)
    finally:
        if target.poll() is None:
            target.kill()
            target.wait()
    out = _figures(stats, got, loop, offline_rms)
    for key in ('answers', 'answer_p50_us', 'answer_p99_us', 'answer_max_us', 'lost',
                'target_missing', 'target_predicted', 'overtaken', 'resent'):
        out[f'host_{key}' if key == 'lost' else key] = stats.get(f'bridge_{key}')
    out['target'] = ' '.join(line.strip() for line in lines
                             if 'clock' in line or 'stopped' in line or 'sched' in line
                             or 'nice' in line or 'throttling' in line)
    return out


def machine_floor(duration_s: float, opts: ServoParams, period_ns: int) -> dict[str, Any]:
    """
    Spin on the monotonic clock for ``duration_s`` in a thread set up as the servo's; count gaps.

    Returns ``gaps`` (reads more than a period apart), ``periods_lost`` (the whole periods
    inside them: samples a paced loop would have skipped), ``max_gap_us`` and the setup report.
    The spin runs under the default scheduler whatever ``opts.fifo_priority`` says: a FIFO
    thread that never sleeps is throttled by the kernel, which would measure the throttling,
    not the machine.
    """
    out: dict[str, Any] = {}

    def spin() -> None:
        out.update(servo_setup(dataclasses.replace(opts, fifo_priority=0), period_ns))
        clock = time.monotonic_ns
        gaps: list[int] = []
        now = clock()
        end = now + round(duration_s * 1e9)
        while now < end:
            then, now = now, clock()
            if now - then > period_ns:
                gaps.append(now - then)
        out.update({'gaps': len(gaps), 'periods_lost': sum(g // period_ns for g in gaps),
                    'max_gap_us': round(max(gaps, default=0) / 1000, 1)})

    worker = threading.Thread(target=spin, name='floor')
    worker.start()
    worker.join()
    return out


class _ScriptedClock:
    """A monotonic clock [ns] that advances a little per read and by what sleeps ask."""

    def __init__(self, per_read_ns: int = 300) -> None:
        self.now = 10**9
        self.per_read_ns = per_read_ns

    def __call__(self) -> int:
        self.now += self.per_read_ns
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += round(seconds * 1e9)


def stall_response(loop: LoopConfig, skips: tuple[int, ...] = (1, 2, 5, 10, 20),
                   at_s: float = 0.5, duration_s: float = 0.8, *,
                   commands_ahead: int | None = None) -> dict[str, Any]:
    """
    Return the error after one stall of the servo loop, on a scripted clock (no wall time).

    At ``at_s`` the clock jumps so that the loop skips ``n`` samples (for each ``n`` of
    ``skips``; 0: no stall), the amplifier holding the last command meanwhile. Per ``n``:
    ``skipped`` (as counted by the loop), ``e_max_nm`` over the 300 samples after the stall
    and ``after_nm`` from then to the end (the controller's recovery). ``commands_ahead``:
    that many (0: none, the last command held); default ``servo.commands_ahead`` of ``loop``.
    """
    period_ns = round(1e9 / loop.stage.sample_rate_hz)
    at = round(at_s * loop.stage.sample_rate_hz)
    out: dict[str, Any] = {}
    for skip in (0, *skips):
        clock = _ScriptedClock()
        servo = make_servo(loop, duration_s)
        if commands_ahead is not None:
            servo.commands_ahead = commands_ahead
        servo.pacer = Pacer(period_ns, clock=clock, sleep=clock.sleep)
        servo.start()
        while servo.step():
            if servo.index == at and skip:
                # sample at + 1 is then taken (skip + 0.2) periods late: skip samples pass
                clock.now += (skip + 1) * period_ns + period_ns // 5
        got = servo.drain()
        k = np.array([x.k for x in got])
        err = np.abs(np.array([x.position_m - x.reference_m for x in got]))
        near, later = (k > at) & (k <= at + 300), k > at + 300
        out[str(skip)] = {'skipped': servo.pacer.stats.skipped,
                          'e_max_nm': round(float(err[near].max()) * 1e9, 1),
                          'after_nm': round(float(err[later].max()) * 1e9, 1)}
    return out


def ahead_cost(loop: LoopConfig, duration_s: float = 2.0, repeats: int = 3) -> dict[str, Any]:
    """
    Return the wall time per sample [us] of the servo loop with and without commands ahead.

    The loop of ``loop`` on a scripted clock (it never waits), ``duration_s`` of samples, best
    of ``repeats``: ``with_us`` (``servo.commands_ahead``), ``without_us`` (0), their
    difference, and ``predict_us``: the prediction alone (the controller's commands ahead and
    the reference ahead they read), timed around each call.
    """
    m = loop.plant_node.servo.commands_ahead
    period_ns = round(1e9 / loop.stage.sample_rate_hz)
    best: dict[int, float] = {}
    predict_ns: list[float] = []
    for ahead in (m, 0):
        for _ in range(repeats):
            clock = _ScriptedClock()
            servo = make_servo(loop, duration_s, capacity=0)
            servo.commands_ahead = ahead
            # no spinning: each wait is one scripted sleep to the due time
            servo.pacer = Pacer(period_ns, clock=clock, sleep=clock.sleep, spin_ns=0)
            spent = [0]
            predict = servo._predictor.predict

            def timed(*args: Any, predict: Any = predict, spent: list[int] = spent) -> Any:
                t0 = time.perf_counter_ns()
                out = predict(*args)
                spent[0] += time.perf_counter_ns() - t0
                return out

            servo._predictor.predict = timed  # type: ignore[method-assign,assignment]
            t0 = time.perf_counter_ns()
            servo.start()
            while servo.step():
                pass
            per = (time.perf_counter_ns() - t0) / (servo.index + 1) / 1e3
            best[ahead] = min(best.get(ahead, math.inf), per)
            if ahead:
                predict_ns.append(spent[0] / (servo.index + 1))
    return {'commands_ahead': m, 'with_us': round(best[m], 2), 'without_us': round(best[0], 2),
            'difference_us': round(best[m] - best[0], 2),
            'predict_us': round(min(predict_ns, default=0.0) / 1e3, 2)}


def run_servo_benchmark(cases: tuple[str, ...] = CASES, duration_s: float = 10.0,
                        fifo_priority: int = 0, nice: int | None = None) -> dict[str, Any]:
    """
    Run the cases and return their figures (see the module docstring).

    Parameters
    ----------
    cases : tuple of str
        Among :data:`CASES`.
    duration_s : float
        Wall time of each run [s].
    fifo_priority : int
        SCHED_FIFO priority of the servo thread and the emulator (0: the default scheduler;
        with it, the loops sleep to 30 us before each due time instead of spinning, as
        real-time threads wake on time and a spinning one is throttled by the kernel).
    nice : int, optional
        Nice value of the servo thread and the emulator; default ``servo.nice`` as
        configured (-20).

    """
    loop = loop_config()
    period = 1.0 / loop.stage.sample_rate_hz
    ctrl = build_controller(loop.controller, period, linear_plant(loop.design_plant))
    rec = run(Stage(loop.stage), ctrl, make_trajectory(loop.trajectory),
              duration_s=duration_s, record_diagnostics=False)
    offline_rms = steady_e_rms(np.arange(rec.position_m.size, dtype=np.float64),
                               rec.position_m, rec.reference_m, period,
                               1.0 / loop.trajectory.sine.frequency_hz)
    out: dict[str, Any] = {}
    opts = dataclasses.replace(loop.plant_node.servo, fifo_priority=fifo_priority,
                               nice=loop.plant_node.servo.nice if nice is None else nice)
    if fifo_priority:
        opts = dataclasses.replace(opts, spin_us=30.0)
    loop = dataclasses.replace(loop, plant_node=dataclasses.replace(loop.plant_node,
                                                                    servo=opts))
    for case in cases:
        if case == 'floor':
            out['machine floor (bare spin)'] = {'floor': machine_floor(
                duration_s, opts, round(period * 1e9))}
        elif case == 'servo-alone':
            out[case] = _figures(*serve(make_servo(loop, duration_s), ros_side=False,
                                        opts=opts), loop, offline_rms)
        elif case == 'servo':
            for label, interval in (('5 ms', 0.0), ('50 us', 50.0)):
                out[f'servo + ROS side (switch interval {label})'] = _figures(
                    *serve(make_servo(loop, duration_s), ros_side=True,
                           opts=dataclasses.replace(opts, switch_interval_us=interval)),
                    loop, offline_rms)
        elif case == 'servo-process':
            out['servo process + ROS side in another'] = _figures(
                *serve_process(loop, duration_s), loop, offline_rms)
        elif case == 'bridge':
            out['bridge (paced emulator, host servo process)'] = run_bridge(
                loop, duration_s, offline_rms)
        elif case == 'stall':
            m = loop.plant_node.servo.commands_ahead
            skips = (1, 2, 5, 10, 20, 40, 60, 90)
            out[f'stall (scripted clock, {m} commands ahead)'] = {
                'stalls': stall_response(loop, skips)}
            out['stall (scripted clock, last command held)'] = {
                'stalls': stall_response(loop, skips, commands_ahead=0)}
        elif case == 'ahead-cost':
            out['commands ahead, cost per sample (scripted clock)'] = {
                'ahead': ahead_cost(loop, duration_s=min(duration_s, 2.0))}
        else:
            raise ValueError(f'unknown case {case!r}; choose among {", ".join(CASES)}')
    return out


#: Figures in the columns of :func:`format_table` (the others go into notes below it).
TABLE_KEYS = ('paced_samples', 'lateness_p50_us', 'lateness_p99_us', 'lateness_max_us',
              'late_half_period', 'skipped', 'e_rms_nm', 'offline_e_rms_nm')


def format_table(result: dict[str, Any]) -> str:
    """Return the figures of :func:`run_servo_benchmark` as a Markdown table."""
    lines = ['| case | samples | p50 [us] | p99 [us] | max [us] | late > T/2 | skipped | '
             'e_rms [nm] (offline) |',
             '| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |']
    notes = []
    for case, s in result.items():
        if 'floor' in s:
            f = s['floor']
            notes.append(f'{case}: {f["gaps"]} gaps longer than a period in the clock reads, '
                         f'{f["periods_lost"]} periods inside them, the longest '
                         f'{f["max_gap_us"]} us')
            continue
        if 'ahead' in s:
            a = s['ahead']
            notes.append(f'{case}: servo loop {a["with_us"]} us a sample with '
                         f'{a["commands_ahead"]} commands ahead, {a["without_us"]} us without '
                         f'(+{a["difference_us"]} us); the prediction alone {a["predict_us"]} us')
            continue
        if 'stalls' in s:
            notes += [f'{case}: {v["skipped"]} samples skipped: e_max {v["e_max_nm"]} nm over '
                      f'the 300 samples after, {v["after_nm"]} nm after those'
                      for v in s['stalls'].values()]
            continue
        lines.append(f'| {case} | {s["paced_samples"]} | {s["lateness_p50_us"]} | '
                     f'{s["lateness_p99_us"]} | {s["lateness_max_us"]} | '
                     f'{s["late_half_period"]} | {s["skipped"]} | {s["e_rms_nm"]} '
                     f'({s["offline_e_rms_nm"]}) |')
        notes += [f'{case}: {k} = {v}' for k, v in s.items()
                  if v is not None and k not in TABLE_KEYS]
    return '\n'.join(lines + [''] + notes)
