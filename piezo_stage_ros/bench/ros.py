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
ROS benchmarks (not tests): what the nodes reach on this machine's ROS 2 install.

Run ``python3 -m piezo_stage_ros.bench.ros`` in a sourced Jazzy environment. Cases:

- ``composed-lockstep``: plant, controller and trajectory nodes in this process on one
  ``EventsExecutor``, lockstep, ``--lockstep-s`` of loop time: samples per second and the real-time
  factor (loop time / wall time); once with ``use_sim_time`` on the controller and trajectory
  nodes as the launch file sets it (every ``/clock`` message then also reaches their time
  sources), once without;
- ``composed-realtime``: the same nodes in real time for ``--realtime-s`` of wall time: the
  plant's servo loop samples on its clock and publishes each position at once, the controller
  answers through the executor; the share of late samples (no new command since the previous
  sample), the lateness of the clock, skipped samples;
- ``direct-lockstep``, ``direct-realtime``: the same with the nodes handing each sample to each
  other by call (``stage_servo --direct``; in real time the servo loop runs trajectory and
  controller in its thread), nothing published (nobody outside listens);
- ``cross-lockstep``: the plant here, controller and trajectory in a second process
  (``stage_servo --nodes controller,trajectory``), lockstep; once answering each position, once
  with the reference streamed 50 samples ahead (``lockstep_ahead``);
- ``three-lockstep``: the plant here, controller and trajectory each in a process of its own
  (as ``ros2 run`` of the three nodes), lockstep, both ways;
- ``pingpong``: the yardstick of the machine's state: two nodes in this process bounce a
  ``Float64`` (serialized) on one EventsExecutor; the median round trip in microseconds;
- ``recorded-realtime``: the real-time run with recording, as a user runs it: ``ros2 launch
  piezo_stage_ros closed_loop.launch.py mode:=realtime direct:=true record:=true
  scenario:=table3_rac.yaml duration_s:=<--realtime-s>`` (``stage_servo --direct``, the servo loop
  as a process of its own, ``ros2 bag record`` of every stage topic), then the bag analysed as
  ``analyze`` does: the servo's counters (end-of-run log), the samples in the bag, e_rms over the
  whole run beside the offline runner's (lockstep) on the same configuration and length, and the
  machine's floor measured just before (``bench.servo.machine_floor``: a bare spin as long, the
  periods a loop would lose to the machine alone); once on the idle machine and once with
  ``--load`` CPU-bound processes beside it (``recorded-realtime-loaded``).

The runs use a ROS domain of their own (``--domain-id``) and localhost discovery, so that they
neither see nor disturb other ROS graphs on the machine. Timings are those of a shared machine:
compare them with each other, not with another day's.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
from typing import Any, Sequence

__all__ = ['CASES', 'end_of_run_figures', 'main', 'run_ros_benchmark']

CASES = ('pingpong', 'composed-lockstep', 'composed-realtime', 'direct-lockstep',
         'direct-realtime', 'cross-lockstep', 'three-lockstep', 'recorded-realtime',
         'recorded-realtime-loaded')
#: The scenario of the recorded run (RAC, reduced plant, 100 Hz sine).
RECORDED_SCENARIO = 'table3_rac.yaml'
STAGE = {'plant.model': 'reduced'}
# in-process nodes get no parameter files: the controller is told the plant's model itself
CONTROLLER = {'type': 'rac', 'stability.design_model': 'own',
              'stability.plant.model': 'reduced'}


def _params(values: dict[str, Any]) -> list[Any]:
    from rclpy.parameter import Parameter
    return [Parameter(k, value=v) for k, v in values.items()]


def _composed(mode: str, duration_s: float, sim_time: bool, direct: bool = False
              ) -> dict[str, Any]:
    from piezo_stage_ros.nodes.controller_node import ControllerNode
    from piezo_stage_ros.nodes.plant_node import PlantNode
    from piezo_stage_ros.nodes.runner import make_executor
    from piezo_stage_ros.nodes.trajectory_node import TrajectoryNode
    import rclpy
    from rclpy.context import Context

    context = Context()
    rclpy.init(context=context)
    nodes: list[Any] = []
    try:
        plant = PlantNode(context=context, parameter_overrides=_params(
            {**STAGE, 'mode': mode, 'duration_s': duration_s, 'status_period_s': 3600.0}))
        common = {'mode': mode, 'use_sim_time': sim_time and mode == 'lockstep'}
        nodes = [plant,
                 ControllerNode(context=context,
                                parameter_overrides=_params({**CONTROLLER, **common})),
                 TrajectoryNode(context=context, parameter_overrides=_params(common))]
        if direct:
            from piezo_stage_ros.nodes.stage_servo import connect_direct
            connect_direct(nodes[0], nodes[1], nodes[2])
        executor = make_executor('events', context)
        for node in nodes:
            executor.add_node(node)
        executor.spin_until_future_complete(plant.finished, timeout_sec=duration_s * 50 + 60)
        if not plant.finished.done():
            raise RuntimeError(f'{mode} run did not finish')
        stats = dict(plant.finished.result())
        for node in nodes:
            executor.remove_node(node)
        executor.shutdown()
        return stats
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


def _helper(nodes: str, executor: str, params: dict[str, Any]) -> subprocess.Popen[str]:
    args = [sys.executable, '-m', 'piezo_stage_ros.nodes.stage_servo', '--nodes', nodes,
            '--executor', executor, '--ros-args']
    for k, v in params.items():
        args += ['-p', f'{k}:={v}']
    return subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _cross(duration_s: float, executor: str, three: bool = False, ahead: int = 0
           ) -> dict[str, Any]:
    from piezo_stage_ros.nodes.plant_node import PlantNode
    from piezo_stage_ros.nodes.runner import make_executor
    import rclpy
    from rclpy.context import Context

    if three:
        # the plant here, the controller and the trajectory each in a process of its own
        helpers = [_helper('controller', executor, {**CONTROLLER, 'mode': 'lockstep'}),
                   _helper('trajectory', executor, {'mode': 'lockstep',
                                                    'lockstep_ahead': ahead})]
    else:
        helpers = [_helper('controller,trajectory', executor,
                           {**CONTROLLER, 'mode': 'lockstep', 'lockstep_ahead': ahead})]
    helper = helpers[0]
    context = Context()
    rclpy.init(context=context)
    plant = None
    try:
        plant = PlantNode(context=context, parameter_overrides=_params(
            {**STAGE, 'mode': 'lockstep', 'duration_s': duration_s,
             'status_period_s': 3600.0}))
        ex = make_executor(executor, context)
        ex.add_node(plant)
        ex.spin_until_future_complete(plant.finished, timeout_sec=duration_s * 50 + 60)
        if not plant.finished.done():
            raise RuntimeError('cross-process run did not finish: ' + ' '.join(
                h.stderr.read() for h in helpers
                if h.stderr is not None and h.poll() is not None))
        ex.remove_node(plant)
        ex.shutdown()
        return dict(plant.finished.result())
    finally:
        if plant is not None:
            plant.destroy_node()
        rclpy.try_shutdown(context=context)
        for helper in helpers:
            helper.terminate()
            try:
                helper.wait(10)
            except subprocess.TimeoutExpired:
                helper.kill()


def _pingpong(round_trips: int = 20000) -> dict[str, Any]:
    import time

    from piezo_stage_ros.core.contracts.cdr import encode_float64
    from piezo_stage_ros.nodes import qos
    from piezo_stage_ros.nodes.runner import make_executor
    import rclpy
    from rclpy.context import Context
    from rclpy.task import Future
    from std_msgs.msg import Float64

    context = Context()
    rclpy.init(context=context)
    try:
        ping = rclpy.create_node('bench_ping', context=context)
        pong = rclpy.create_node('bench_pong', context=context)
        ping_pub = ping.create_publisher(Float64, 'bench/ping', qos.LOOP)
        pong_pub = pong.create_publisher(Float64, 'bench/pong', qos.LOOP)
        pong.create_subscription(Float64, 'bench/ping', pong_pub.publish, qos.LOOP, raw=True)
        done = Future()
        times: list[float] = []

        def back(data: bytes) -> None:
            times.append(time.perf_counter())
            if len(times) > round_trips:
                done.set_result(True)
            else:
                ping_pub.publish(data)

        ping.create_subscription(Float64, 'bench/pong', back, qos.LOOP, raw=True)
        executor = make_executor('events', context)
        executor.add_node(ping)
        executor.add_node(pong)
        while pong_pub.get_subscription_count() == 0 or ping_pub.get_subscription_count() == 0:
            executor.spin_once(timeout_sec=0.01)
        start = time.perf_counter()
        ping_pub.publish(encode_float64(0.0))
        executor.spin_until_future_complete(done, timeout_sec=120.0)
        gaps = sorted(b - a for a, b in zip([start] + times, times))
        executor.shutdown()
        ping.destroy_node()
        pong.destroy_node()
        return {'round_trips': len(times), 'median_us': round(gaps[len(gaps) // 2] * 1e6, 1),
                'p99_us': round(gaps[int(len(gaps) * 0.99)] * 1e6, 1)}
    finally:
        rclpy.try_shutdown(context=context)


def _burn() -> None:
    while True:
        pass


def end_of_run_figures(log: str) -> dict[str, Any]:
    """
    Return the figures of the plant's end-of-run line in a launch's output.

    The line is ``run complete: k=v, ...`` or, as a WARN, ``run complete, degraded (reasons):
    k=v, ...``; numbers come back as int or float, the rest as text.

    Raises
    ------
    RuntimeError
        If the output has no such line (with its last 3000 characters).

    """
    found = re.search(r'run complete(?:, degraded \(.*?\))?: (samples=.*)', log)
    if found is None:
        raise RuntimeError('recorded run: no end-of-run line from the plant; the launch '
                           'printed:\n' + log[-3000:])
    out: dict[str, Any] = {}
    for item in found.group(1).split(', '):
        key, _, value = item.partition('=')
        try:
            out[key] = float(value) if '.' in value else int(value)
        except ValueError:
            out[key] = value
    return out


def _recorded(duration_s: float, load: int = 0) -> dict[str, Any]:
    import multiprocessing
    import tempfile

    import numpy as np
    from piezo_stage_ros import cli
    from piezo_stage_ros.analysis.replay import analyze_bag
    from piezo_stage_ros.bench.servo import machine_floor
    from piezo_stage_ros.core.config.loader import LoopConfig
    from piezo_stage_ros.core.control.controllers import build_controller
    from piezo_stage_ros.core.loop.closed_loop import run
    from piezo_stage_ros.core.loop.metrics import error_metrics
    from piezo_stage_ros.core.loop.trajectories import make_trajectory
    from piezo_stage_ros.core.model.stage import linear_plant, Stage

    loop = LoopConfig.from_config(cli.read_config([RECORDED_SCENARIO]))
    period = 1.0 / loop.stage.sample_rate_hz
    reference_period = make_trajectory(loop.trajectory).period_s or 0.0
    burners = [multiprocessing.get_context('spawn').Process(target=_burn, daemon=True)
               for _ in range(load)]
    with tempfile.TemporaryDirectory(prefix='pz_recorded_') as tmp:
        bag = os.path.join(tmp, 'bag')
        cmd = ['ros2', 'launch', 'piezo_stage_ros', 'closed_loop.launch.py', 'mode:=realtime',
               'direct:=true', 'record:=true', f'scenario:={RECORDED_SCENARIO}',
               f'duration_s:={duration_s:g}', f'bag:={bag}']
        for burner in burners:
            burner.start()
        try:
            # the machine's bound under the same conditions: a bare spin as long as the run
            floor = machine_floor(duration_s, loop.plant_node.servo, round(period * 1e9))
            done = subprocess.run(cmd, capture_output=True, text=True,
                                  timeout=duration_s * 3 + 120)
        finally:
            for burner in burners:
                burner.kill()
        log = done.stdout + done.stderr
        out = end_of_run_figures(log)
        out['setup'] = '; '.join(re.findall(r'servo (\w+: [^\n]*)', log))
        out['floor_periods_lost'] = floor['periods_lost']
        out['floor_gaps'] = floor['gaps']
        out['floor_max_gap_us'] = floor['max_gap_us']
        result = analyze_bag(bag, steady_state_start_s=0.0)
        out['bag_samples'] = result.samples
        out['e_rms_nm'] = round(result.metrics['e_rms_m'] * 1e9, 2)
        out['e_max_nm'] = round(result.metrics['e_max_m'] * 1e9, 1)
        # what the stalls cost: the same e_rms without the 300 samples after each gap in the
        # stamps (a diagnostic, not the figure: the stalls are part of the run)
        record = result.record
        gaps = np.flatnonzero(np.diff(record.time_s) > 1.5 * period) + 1
        keep = np.ones(record.time_s.size, dtype=bool)
        for start in gaps:
            keep[start:start + 300] = False
        error = record.position_m[keep] - record.reference_m[keep]
        out['stalls_in_bag'] = int(gaps.size)
        out['longest_gap_in_bag_ms'] = round(float(np.max(np.diff(record.time_s))) * 1e3, 2)
        out['e_rms_away_from_stalls_nm'] = round(error_metrics(error)[1] * 1e9, 2)
        # after the first period of the reference: the start-up transient (in lockstep too,
        # 0.24 um at 0.3 ms) left out, every stall of the run kept
        first = record.time_s >= record.time_s[0] + reference_period
        out['e_max_after_first_period_nm'] = round(float(np.max(np.abs(
            record.position_m[first] - record.reference_m[first]))) * 1e9, 1)
        out['analysis_notes'] = ' | '.join(result.notes)
    rec = run(Stage(loop.stage),
              build_controller(loop.controller, period, linear_plant(loop.design_plant)),
              make_trajectory(loop.trajectory), duration_s=duration_s,
              record_diagnostics=False)
    error = rec.position_m - rec.reference_m
    out['offline_e_rms_nm'] = round(error_metrics(error)[1] * 1e9, 2)
    out['offline_e_max_nm'] = round(float(np.max(np.abs(error))) * 1e9, 1)
    first = rec.time_s >= rec.time_s[0] + reference_period
    out['offline_e_max_after_first_period_nm'] = round(
        float(np.max(np.abs(error[first]))) * 1e9, 1)
    out['load'] = load
    return out


def run_ros_benchmark(cases: Sequence[str] = CASES, *, lockstep_s: float = 5.0,
                      realtime_s: float = 60.0, domain_id: int | None = None,
                      load: int = 2) -> dict[str, Any]:
    """
    Run the ROS benchmark cases and return their figures.

    Parameters
    ----------
    cases : sequence of str
        Among :data:`CASES`.
    lockstep_s : float
        Loop time of each lockstep run [s].
    realtime_s : float
        Wall time of the real-time run [s].
    domain_id : int, optional
        ROS domain of the runs; default 100 + pid % 100.
    load : int
        CPU-bound processes beside ``recorded-realtime-loaded``.

    Returns
    -------
    dict
        Per case: samples, wall time, samples per second, real-time factor, late and skipped
        samples (plant counters).

    """
    os.environ['ROS_DOMAIN_ID'] = str(domain_id if domain_id is not None
                                      else 100 + os.getpid() % 100)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    out: dict[str, Any] = {}
    for case in cases:
        if case == 'pingpong':
            out[case] = _pingpong()
        elif case == 'composed-lockstep':
            out['composed-lockstep (use_sim_time)'] = _composed('lockstep', lockstep_s, True)
            out['composed-lockstep'] = _composed('lockstep', lockstep_s, False)
        elif case == 'composed-realtime':
            out[case] = _composed('realtime', realtime_s, False)
        elif case == 'direct-lockstep':
            out[case] = _composed('lockstep', lockstep_s, False, direct=True)
        elif case == 'direct-realtime':
            out[case] = _composed('realtime', realtime_s, False, direct=True)
        elif case == 'cross-lockstep':
            out[case] = _cross(lockstep_s, 'events')
            out['cross-lockstep (reference 50 samples ahead)'] = _cross(lockstep_s, 'events',
                                                                        ahead=50)
        elif case == 'three-lockstep':
            out[case] = _cross(lockstep_s, 'events', three=True)
            out['three-lockstep (reference 50 samples ahead)'] = _cross(
                lockstep_s, 'events', three=True, ahead=50)
        elif case == 'recorded-realtime':
            out[case] = _recorded(realtime_s)
        elif case == 'recorded-realtime-loaded':
            out[f'recorded-realtime, {load} CPU-bound processes beside'] = _recorded(
                realtime_s, load)
        else:
            raise ValueError(f'unknown case {case!r}; choose among {", ".join(CASES)}')
    return out


def format_table(result: dict[str, Any]) -> str:
    """Return the figures of :func:`run_ros_benchmark` as a Markdown table and notes."""
    lines = ['| case | samples | wall [s] | samples/s | x real time | late [%] | skipped | '
             'lateness p50 / p99 / max [us] | late > T/2 |',
             '| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |']
    notes: list[str] = []
    for case, s in result.items():
        if case == 'pingpong':
            notes.append(f'ping-pong in one process (EventsExecutor): median {s["median_us"]} us, '
                         f'p99 {s["p99_us"]} us per round trip ({s["round_trips"]} round trips)')
            continue
        if 'bag_samples' in s:
            notes.append(f'{case}: {s["paced_samples"]} samples taken, {s["bag_samples"]} in '
                         f'the bag, ring_missed {s.get("ring_missed")}, queue_overruns '
                         f'{s.get("queue_overruns")}, watchdog_trips {s.get("watchdog_trips")}; '
                         f'e_rms {s["e_rms_nm"]} nm over the whole run (offline, lockstep: '
                         f'{s["offline_e_rms_nm"]} nm), e_max {s["e_max_nm"]} nm; '
                         f'{s["stalls_in_bag"]} stalls in the stamps, e_rms without the 300 '
                         f'samples after each: {s["e_rms_away_from_stalls_nm"]} nm; the '
                         f'machine floor just before (a bare spin as long): '
                         f'{s["floor_periods_lost"]} periods lost in {s["floor_gaps"]} gaps; '
                         f'setup: {s["setup"]}')
        samples = s.get('index', -1) + 1
        late = 100.0 * s.get('late', 0) / samples if samples else 0.0
        clock = (f'{s["lateness_p50_us"]} / {s["lateness_p99_us"]} / {s["lateness_max_us"]}'
                 if 'lateness_p50_us' in s else '-')
        lines.append(f'| {case} | {samples} | {s["wall_s"]:.2f} | {s["samples_per_s"]:.0f} | '
                     f'{s["real_time_factor"]:.3f} | {late:.3f} | {s.get("skipped", 0)} | '
                     f'{clock} | {s.get("late_half_period", "-")} |')
    return '\n'.join(lines + [''] + notes)


def main(argv: Sequence[str] | None = None) -> int:
    """
    Run the ROS benchmarks from the command line.

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments (default ``sys.argv[1:]``).

    Returns
    -------
    int
        0 on success, 1 when a run failed, 2 when rclpy is missing.

    """
    parser = argparse.ArgumentParser(prog='python3 -m piezo_stage_ros.bench.ros',
                                     description='Loop rates the ROS nodes reach here.')
    parser.add_argument('--cases', default=','.join(CASES),
                        help=f'comma-separated subset of {", ".join(CASES)}')
    parser.add_argument('--lockstep-s', type=float, default=5.0,
                        help='loop time of each lockstep run [s] (default 5)')
    parser.add_argument('--realtime-s', type=float, default=60.0,
                        help='wall time of the real-time run [s] (default 60)')
    parser.add_argument('--domain-id', type=int, default=None, help='ROS domain of the runs')
    parser.add_argument('--load', type=int, default=2,
                        help='CPU-bound processes beside recorded-realtime-loaded (default 2)')
    parser.add_argument('--json', action='store_true', help='print JSON instead of a table')
    args = parser.parse_args(argv)
    try:
        import rclpy  # noqa: F401
    except ImportError:
        print('bench.ros: rclpy is not importable; source a ROS 2 Jazzy install first',
              file=sys.stderr)
        return 2
    cases = [c.strip() for c in args.cases.split(',') if c.strip()]
    try:
        result = run_ros_benchmark(cases, lockstep_s=args.lockstep_s,
                                   realtime_s=args.realtime_s, domain_id=args.domain_id,
                                   load=args.load)
    except Exception as exc:  # noqa: BLE001 -- a benchmark reports any failure in one line
        print(f'bench.ros: {type(exc).__name__}: {exc}', file=sys.stderr)
        return 1
    print(json.dumps(result, indent=2) if args.json else format_table(result))
    return 0


if __name__ == '__main__':
    sys.exit(main())
