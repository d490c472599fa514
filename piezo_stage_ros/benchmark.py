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
``benchmark``: speed figures of the simulation and of the bag tools (a command, not a test).

``--suite sim`` (default): simulated seconds per wall second of one stage + RAC at 10 kHz per
plant model, the per-sample cost split into stage / controller / loop, stage-steps per second
of a batch of 1000 stages, controller step median and p99
(:mod:`piezo_stage_ros.bench.sim`). ``--suite bags``: bag write / read / analysis throughput
(:mod:`piezo_stage_ros.bench.bags`, when installed). ``--suite servo``: how well the real-time
servo loop and the target-paced UDP bridge hold 10 kHz here, without ROS
(:mod:`piezo_stage_ros.bench.servo`). ``--suite recording``: what a sample costs on the block
topic and as per-sample messages, in the executor and in a bag
(:mod:`piezo_stage_ros.bench.recording`). ``--suite axes``: what the controllers of one and
of three axes cost per sample, learning and commands ahead included
(:mod:`piezo_stage_ros.bench.axes`). ``--suite ros``: the nodes on a ROS 2 install
(:mod:`piezo_stage_ros.bench.ros`). ``--suite all``: every one available. ``--json`` prints
one JSON object on stdout (the readable lines then go to stderr).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.util
import json
import math
import sys
from typing import Any

from piezo_stage_ros import cli

__all__ = ['main']

PROG = 'benchmark'


def _positive(kind: type) -> Any:
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
        if not (value > 0 and math.isfinite(value)):
            raise argparse.ArgumentTypeError(f'{text!r} must be positive')
        return value
    return parse


def _parser() -> argparse.ArgumentParser:
    p = cli.Parser(prog=PROG, description='Print speed figures of the simulation and bag tools.')
    p.add_argument('--suite', choices=('sim', 'bags', 'servo', 'recording', 'axes', 'ros',
                                         'all'),
                   default='sim',
                   help='What to measure (default sim).')
    p.add_argument('--realtime-s', type=_positive(float), default=10.0, metavar='S',
                   help='Wall time of each real-time run of the servo suite (default 10).')
    p.add_argument('--fifo-priority', type=int, default=0, metavar='P',
                   help='Servo suite: SCHED_FIFO priority of the loops (default 0: none).')
    p.add_argument('--nice', type=int, default=None, metavar='N',
                   help='Servo suite: nice value of the loops (default: servo.nice as '
                   'configured, -20).')
    p.add_argument('--duration', type=_positive(float), default=2.0, metavar='S',
                   help='Simulated seconds per closed-loop measurement (default 2).')
    p.add_argument('--batch', type=_positive(int), default=1000, metavar='N',
                   help='Stages in the batch measurement (default 1000).')
    p.add_argument('--repeats', type=_positive(int), default=3, metavar='N',
                   help='Measurements per figure; the fastest counts (default 3).')
    p.add_argument('--controller-steps', type=_positive(int), default=200_000, metavar='N',
                   help='Controller steps timed one by one (default 200000).')
    p.add_argument('--bag-duration', type=_positive(float), default=60.0, metavar='S',
                   help='Length of the run of the bag benchmark (default 60 s).')
    p.add_argument('--case', action='append', default=[], metavar='NAME',
                   help='Axes suite: only this case, as printed without its mode, e.g. '
                   "'servo-axes-3' (repeatable; default: all).")
    p.add_argument('--json', action='store_true', help='Print one JSON object on stdout.')
    return p




def _bench(args: argparse.Namespace) -> int:
    result: dict[str, Any] = {}
    # with --json the readable lines go to stderr so stdout holds only the JSON object
    lines = sys.stderr if args.json else sys.stdout
    try:
        with contextlib.redirect_stdout(lines):
            if args.suite in ('sim', 'all'):
                from piezo_stage_ros.bench.sim import run_sim_benchmark
                result['sim'] = run_sim_benchmark(duration_s=args.duration, batch=args.batch,
                                                  controller_steps=args.controller_steps,
                                                  repeats=args.repeats)
            if args.suite in ('bags', 'all'):
                try:
                    bags = importlib.import_module('piezo_stage_ros.bench.bags')
                except ImportError as exc:
                    print(f'{PROG}: error: the bag benchmark is not available ({exc})',
                          file=sys.stderr)
                    return 1
                result['bags'] = bags.run_bag_benchmark(args.bag_duration)
            if args.suite in ('servo', 'all'):
                from piezo_stage_ros.bench import servo
                result['servo'] = servo.run_servo_benchmark(
                    duration_s=args.realtime_s, fifo_priority=args.fifo_priority,
                    nice=args.nice)
                print(servo.format_table(result['servo']))
            if args.suite in ('recording', 'all'):
                from piezo_stage_ros.bench.recording import run_recording_benchmark
                result['recording'] = run_recording_benchmark(args.bag_duration)
            if args.suite in ('axes', 'all'):
                from piezo_stage_ros.bench.axes import run_axes_benchmark
                result['axes'] = run_axes_benchmark(repeats=args.repeats, cases=args.case)
            if args.suite == 'ros' or (args.suite == 'all' and _rclpy_available()):
                if not _rclpy_available():
                    print(f'{PROG}: error: the ROS benchmark needs rclpy (a sourced ROS 2 Jazzy '
                          'install)', file=sys.stderr)
                    return 1
                from piezo_stage_ros.bench.ros import format_table, run_ros_benchmark
                result['ros'] = run_ros_benchmark()
                print(format_table(result['ros']))
    except KeyboardInterrupt:
        print(f'{PROG}: error: interrupted', file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - a benchmark reports any failure in one line
        print(f'{PROG}: error: {type(exc).__name__}: {exc}', file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(result, sort_keys=True, default=str))
    return 0


def _rclpy_available() -> bool:
    """Return whether rclpy can be imported (ROS 2 sourced)."""
    return importlib.util.find_spec('rclpy') is not None


main = cli.command_main(PROG, _parser, _bench,
                        '0 success, 1 a suite unavailable or failed, 2 bad usage')


if __name__ == '__main__':
    sys.exit(main())
