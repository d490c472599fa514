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
``simulate``: the closed loop of stage, controller and trajectory offline, without ROS.

Parameters come from ROS 2 parameter files, in order: the package's ``config/default.yaml``,
then every ``--config FILE``, then ``--param NODE:NAME=VALUE``, then the short flags
(``--plant``, ``--controller``, ``--trajectory``, ``--frequency`` ...). The same files configure
the ROS nodes (``plant_node``, ``controller_node``, ``trajectory_node`` sections).

Before every closed-loop run the controller's stability on the configured plant model is
checked (:mod:`piezo_stage_ros.core.control.stability`): an unstable verdict is printed loudly, or
the run is refused with ``--refuse-unstable`` (or ``controller_node: stability.action: refuse``).

Examples::

    simulate --controller rac --trajectory sine --frequency 100 --json
    simulate --plant reduced --controller pi --frequency 50
    simulate --trajectory multisine --frequency 10 --frequency 100 --amplitude 1.9e-6
    simulate --experiment table3          # the paper's Table III, project beside paper
    simulate --bag run1 --duration 2      # write the run as a rosbag2 bag (MCAP)
    simulate --feedforward learning --duration 10 --steady-state-start 9   # a late window
    simulate --feedforward learning --duration 1 --save-table sine100.npz  # keep the table

Exit status: 0 on success, 1 on a bad parameter, configuration or refused run, 2 on bad
command-line usage; the error is one line on stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from typing import Any
import warnings

from piezo_stage_ros import cli
from piezo_stage_ros.core.config.loader import Config, LoopConfig
from piezo_stage_ros.core.contracts.errors import ConfigError, ParameterError
from piezo_stage_ros.core.contracts.wire import STORAGE_IDS
from piezo_stage_ros.core.control.controllers import ControllerParams
from piezo_stage_ros.core.control.feedforward import TABLE_META_KEY, write_learned_table
from piezo_stage_ros.core.loop.experiments import EXPERIMENTS
from piezo_stage_ros.core.loop.trajectories import TrajectoryParams
from piezo_stage_ros.core.model.hysteresis import HysteresisParams
from piezo_stage_ros.core.model.stage import PlantParams

__all__ = ['build_config', 'build_parser', 'load_loop', 'main']

PROG = 'simulate'

def build_parser() -> argparse.ArgumentParser:
    """Return the command-line parser of ``simulate``."""
    p = cli.Parser(prog=PROG, description='Run the piezo stage closed loop offline (no ROS) '
                   "and print its tracking metrics, or run one of the paper's experiments.")
    cli.add_config_options(p)
    p.add_argument('--plant', choices=cli.choices(PlantParams, 'model'),
                   help='Linear plant model (plant_node plant.model).')
    p.add_argument('--hysteresis', choices=cli.choices(HysteresisParams, 'model'),
                   help='Hysteresis model (plant_node hysteresis.model).')
    p.add_argument('--controller', choices=cli.choices(ControllerParams, 'type'),
                   help='Controller (controller_node type).')
    cli.add_feedforward_option(p)
    p.add_argument('--trajectory', choices=cli.choices(TrajectoryParams, 'kind'),
                   help='Desired trajectory (trajectory_node kind).')
    p.add_argument('--frequency', action='append', type=float, metavar='HZ',
                   help='Frequency of sine/triangle; repeat for the multisine components.')
    p.add_argument('--amplitude', type=float, metavar='M',
                   help='Amplitude [m] (sine, triangle, each multisine component; square: peak '
                   'to peak; staircase: step height; step: final level).')
    p.add_argument('--offset', type=float, metavar='M',
                   help='Offset [m] (sine, triangle, multisine; square: low level; '
                   'staircase: start level; step: initial level).')
    p.add_argument('--csv', metavar='FILE', help='Table for --trajectory csv '
                   '(columns time_s, position_m).')
    p.add_argument('--duration', type=float, metavar='S',
                   help='Simulated time [s] (default: transient plus two periods, >= 1 s).')
    p.add_argument('--steady-state-start', type=float, metavar='S', dest='steady_state_start_s',
                   help='Start of the steady-state window of e_m and e_rms, seconds after the '
                   'first sample, in [0, duration) (default: the reference period decides; '
                   'see docs/howto/simulate.md). Stored in a bag, so analyze uses the same '
                   'window.')
    cli.add_line_options(p, 'Measure')
    p.add_argument('--seed', type=int, metavar='N', help='Seed of the sensor noise.')
    p.add_argument('--noise', type=float, metavar='M',
                   help='Sensor noise standard deviation [m] (plant_node '
                   'chain.sensor_noise_std_m).')
    p.add_argument('--experiment', choices=(*EXPERIMENTS, 'all'),
                   help="Run one of the paper's experiments and print project vs paper.")
    p.add_argument('--refuse-unstable', action='store_true',
                   help='Refuse to run a controller the stability check finds unstable on the '
                   'configured model (default: warn loudly and run).')
    p.add_argument('--json', action='store_true',
                   help='Print one JSON object on stdout instead of the readable summary.')
    p.add_argument('--bag', metavar='DIR', help='Write the run as a rosbag2 bag.')
    p.add_argument('--storage', choices=STORAGE_IDS, default=STORAGE_IDS[0],
                   help='Bag storage plugin (default mcap).')
    p.add_argument('--overwrite', action='store_true', help='Replace an existing bag.')
    p.add_argument('--save-table', metavar='FILE', dest='save_table',
                   help="Write the learning feed-forward's table at the end of the run to FILE "
                   '(.npz, docs/explanation/feedforward.md); controller_node '
                   'feedforward.table_file loads it. A bag of the run holds it too (analyze '
                   '--export-table).')
    p.add_argument('--line-rate-change', metavar='S:HZ', dest='line_rate_change',
                   help='Change the line rate of a sine or triangle to HZ at S seconds (a '
                   'whole number of its periods): the new line starts at its own t = 0 and '
                   'the feed-forward binds it there (the model inverse from its first sample, '
                   'the learning afresh).')
    p.add_argument('--bag-topics', choices=('samples', 'block', 'both'), default='samples',
                   help='What the bag holds: the per-sample topics (default), the block topic '
                   'stage/block (many samples per message, as a real-time loop records them; '
                   'docs/reference/bags.md), or both.')
    return p


def build_config(args: argparse.Namespace) -> Config:
    """Return the parameters of the parsed ``args``: files, then ``--param``, then short flags."""
    return cli.loop_overrides(
        cli.read_config(args.config, args.param), plant=args.plant, hysteresis=args.hysteresis,
        controller=args.controller, trajectory=args.trajectory, frequencies=args.frequency,
        amplitude=args.amplitude, offset=args.offset, csv=args.csv, seed=args.seed,
        noise=args.noise, feedforward=args.feedforward)


def load_loop(args: argparse.Namespace) -> LoopConfig:
    """
    Build the loop configuration from files, ``--param`` and the short flags.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed command line of ``simulate``.

    Returns
    -------
    LoopConfig
        With ``stability.action`` set to ``'refuse'`` by ``--refuse-unstable``.

    """
    loop = cli.offline_loop(PROG, build_config(args))
    if args.refuse_unstable:
        loop = loop.replace(stability=loop.stability.replace(action='refuse'))
    return loop


def _check_window(start_s: float | None, duration_s: float) -> None:
    if start_s is not None and not (0.0 <= start_s < duration_s):
        raise ParameterError('--steady-state-start', start_s, f'[0, {duration_s:g}) s',
                             'is outside the run')


def _clean(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _enforce(report: Any, action: str) -> None:
    """Warn loudly on stderr or refuse (raises StabilityError)."""
    from piezo_stage_ros.core.control.stability import enforce
    with warnings.catch_warnings():
        # the warning is printed here, once, as a readable line instead of a Python warning
        warnings.simplefilter('ignore')
        text = enforce(report, action)
    if not report.stable:
        print(f'{PROG}: WARNING: UNSTABLE CONFIGURATION: {text}', file=sys.stderr)
    adaptation = getattr(report, 'adaptation', None)
    if adaptation is not None and not adaptation.ok:
        print(f'{PROG}: WARNING: ADAPTATION GAIN ABOVE THE DISCRETE BOUND: {adaptation.text()}',
              file=sys.stderr)
    learning = getattr(report, 'learning', None)
    if learning is not None and not learning.design_ok:
        print(f'{PROG}: WARNING: LEARNING NOT MONOTONE ON THE DESIGN MODEL: {learning.text()}',
              file=sys.stderr)


def _line_rate_change(text: str, params: Any, first: Any) -> Any:
    """Return the trajectory of ``--line-rate-change S:HZ``: ``first``, then at S the new rate."""
    from piezo_stage_ros.core.loop.switched import LineRateChange
    from piezo_stage_ros.core.loop.trajectories import make_trajectory
    try:
        at_text, hz_text = text.split(':')
        at_s, hz = float(at_text), float(hz_text)
    except ValueError:
        raise ParameterError('--line-rate-change', text, 'S:HZ, two numbers') from None
    if params.kind not in ('sine', 'triangle'):
        raise ParameterError('--line-rate-change', text, 'a sine or triangle trajectory',
                             f'cannot change the rate of a {params.kind}')
    if not (hz > 0.0 and math.isfinite(hz)):
        raise ParameterError('--line-rate-change', hz, '(0, inf) Hz')
    second = make_trajectory(params.with_flat({f'{params.kind}.frequency_hz': hz}))
    return LineRateChange(first, second, at_s)


def _limits_text(controller: Any, samples: int) -> str:
    """Return the run's report of the limits a feed-forward met ('' when none was active)."""
    clipped = getattr(controller, 'clipped_samples', 0)
    limited = getattr(controller, 'limited_updates', 0)
    if not (clipped or limited):
        return ''
    learning = bool(getattr(getattr(controller, 'params', None), 'learning', False))
    text = (f'LIMIT ACTIVE: the amplifier range clipped {clipped} commands '
            f'({100.0 * clipped / max(samples, 1):.2f} % of the samples)')
    if learning:
        text += ('; the learning check assumed none: the errors after each clip were not '
                 'learned, and what the range clipped off the table was taken out of it')
        if limited:
            text += f'; learning_limit_v scaled the table down in {limited} updates'
    return text + '.'


def _run_single(args: argparse.Namespace, loop: LoopConfig) -> int:
    from piezo_stage_ros.core.control.stability import check_stability
    from piezo_stage_ros.core.loop import metrics
    from piezo_stage_ros.core.loop.experiments import default_duration_s, run_one
    from piezo_stage_ros.core.loop.trajectories import make_trajectory

    stage, ctrl, traj = loop.stage, loop.controller, loop.trajectory
    trajectory: Any = make_trajectory(traj)
    report = check_stability(ctrl, loop.design_plant, stage.sample_time_s,
                             options=loop.stability, period_s=trajectory.period_s, stage=stage)
    if args.line_rate_change is not None:
        trajectory = _line_rate_change(args.line_rate_change, traj, trajectory)
        # the learning after the change: its own period's check
        after = check_stability(ctrl, loop.design_plant, stage.sample_time_s,
                                options=loop.stability, period_s=trajectory.second.period_s,
                                stage=stage).learning
    text = report.text()
    _enforce(report, loop.stability.action)
    duration = args.duration if args.duration is not None else default_duration_s(trajectory,
                                                                                  traj)
    if not (duration > 0.0 and math.isfinite(duration)):
        raise ParameterError('--duration', duration, '(0, inf) s')
    window = args.steady_state_start_s
    _check_window(window, duration)
    learning = ctrl.feedforward.learning
    if args.save_table is not None and not learning:
        raise ConfigError(f'--save-table: feed-forward mode {ctrl.feedforward.mode!r} learns no '
                          'table (use --feedforward learning or inverse_learning)')
    # the bag of a feed-forward run holds its diagnostics every sample: the signal u_ff (ff_u_v)
    # whole (25-50 % more wall time: not without a bag)
    every = 1 if ctrl.feedforward.mode != 'none' and args.bag is not None else 10
    controllers: list[Any] = []
    meta: dict[str, Any] = {'stable': bool(report.stable), 'stability': text,
                            'config_files': [str(p) for p in loop.sources]}
    if window is not None:
        # analyze of the bag takes the window from here
        meta['steady_state_start_s'] = window
    start = time.perf_counter()
    if args.bag is not None:
        from piezo_stage_ros.analysis.bagwrite import RunBagWriter
        with RunBagWriter(args.bag, storage=args.storage, overwrite=args.overwrite,
                          topics=args.bag_topics) as writer:
            def stream(chunk: Any) -> None:
                writer.set_meta(chunk.meta)
                writer.write_chunk(chunk)
            record = run_one(stage, ctrl, traj, duration_s=duration, chunk_callback=stream,
                             meta=meta, design_plant=loop.design_plant,
                             diagnostics_every=every, built=controllers.append,
                             trajectory=trajectory)
            if learning:
                writer.set_meta({**writer.meta,
                                 TABLE_META_KEY: controllers[0].learned().fields()})
    else:
        record = run_one(stage, ctrl, traj, duration_s=duration, meta=meta,
                         design_plant=loop.design_plant, diagnostics_every=every,
                         built=controllers.append, trajectory=trajectory)
    wall = time.perf_counter() - start
    if args.save_table is not None:
        table = controllers[0].learned()
        write_learned_table(args.save_table, table)
    summary = metrics.summarize(record, steady_state_start_s=window,
                                lines=metrics.LineOptions.asked(args.line_middle, args.pixels))
    sim = float(record.meta['duration_s'])
    out: dict[str, Any] = summary.as_dict()
    out.update({'sim_seconds': sim, 'wall_seconds': wall,
                'realtime_factor': sim / wall if wall > 0 else math.inf,
                'stable': bool(report.stable), 'plant': stage.plant.model,
                'hysteresis': stage.hysteresis.model, 'controller': ctrl.type,
                'trajectory': traj.kind, 'seed': stage.seed,
                'trajectory_period_s': record.meta.get('trajectory_period_s'),
                'bag': args.bag, 'learned_table_file': args.save_table})
    if report.learning is not None:
        worst = report.learning.worst_member
        out.update({'learning_ratio_design': report.learning.design_ratio,
                    'learning_ratio_max': report.learning.ratio,
                    'learning_worst_member': worst[0] if worst else None})
    limits = _limits_text(controllers[0] if controllers else None, summary.samples)
    if limits:
        out['ff_clipped_samples'] = controllers[0].clipped_samples
        out['ff_limited_updates'] = controllers[0].limited_updates
    if args.json:
        print(json.dumps({k: _clean(v) for k, v in out.items()}, sort_keys=True))
        return 0
    period = record.meta.get('trajectory_period_s')
    print(f'{ctrl.type} on the {stage.plant.model} plant with {stage.hysteresis.model} '
          f'hysteresis, trajectory {traj.kind}'
          + (f' (period {period:g} s)' if period else ''))
    print(f'stability check: {"stable" if report.stable else "UNSTABLE"} over the box with '
          f'the parameters frozen, at {report.delay_samples:g} samples of computational delay '
          '(the simulated loop applies each command at its sample; not a proof for the '
          'running loop)')
    if report.learning is not None:
        print(f'learning check: {report.learning.text()}')
    if args.line_rate_change is not None and after is not None:
        print(f'learning check after the line-rate change: {after.text()}')
    print(f'simulated {sim:g} s ({summary.samples} samples) in {wall:.3f} s wall '
          f'({out["realtime_factor"]:.1f}x real time)')
    print(f'steady state from {summary.steady_state_start_s:g} s '
          f'({summary.steady_state_samples} samples):')
    print(f'  e_m   = {summary.e_max_m * 1e9:10.2f} nm')
    print(f'  e_rms = {summary.e_rms_m * 1e9:10.2f} nm')
    if summary.e_rms_true_m is not None and summary.e_max_true_m is not None:
        print(f'  true position (no sensor noise, no ADC): e_m = '
              f'{summary.e_max_true_m * 1e9:.2f} nm, e_rms = {summary.e_rms_true_m * 1e9:.2f} nm')
    if math.isfinite(summary.loop_width_pct):
        print(f'  loop width (x vs x_d) = {summary.loop_width_pct:.2f} % of range')
    if summary.line is not None:
        print('\n'.join(summary.line.text()))
    print(f'whole run: e_m = {summary.e_max_all_m * 1e9:.2f} nm, e_rms = '
          f'{summary.e_rms_all_m * 1e9:.2f} nm')
    print(f'command range: {summary.command_min_v:.3f} ... {summary.command_max_v:.3f} V')
    if limits:
        print(limits)
    for name in ('theta_hat', 'phi_hat'):
        if name in summary.diagnostic_ranges:
            low, high = summary.diagnostic_ranges[name]
            print(f'{name}: {low:.6g} ... {high:.6g}')
    if args.bag is not None:
        print(f'bag written: {args.bag} ({args.storage})')
    if args.save_table is not None:
        print(f'learned table written: {args.save_table} ({table.samples} samples, '
              f'{table.periods_learned} periods learned, last period '
              f'{table.period_rms_m * 1e9:.2f} nm rms)')
    return 0


def _run_experiments(args: argparse.Namespace, loop: LoopConfig) -> int:
    from piezo_stage_ros.core.config.loader import design_plant
    from piezo_stage_ros.core.control.stability import check_stability
    from piezo_stage_ros.core.loop import experiments as ex

    stage, ctrl, opts = loop.stage, loop.controller, loop.stability
    plants: tuple[str, ...] = (args.plant,) if args.plant else ('reduced', 'third_order')
    shown = cli.Progress(PROG)
    progress = shown.line

    warned: set[tuple[str, str]] = set()

    def stability(sp: Any, cp: Any) -> tuple[bool | None, str]:
        report = check_stability(cp, design_plant(opts, sp.plant), sp.sample_time_s,
                                 options=opts)
        key = (sp.plant.model, cp.type)
        if not report.stable and key not in warned:
            warned.add(key)
            print(f'{PROG}: WARNING: UNSTABLE CONFIGURATION: {report.text()}', file=sys.stderr,
                  flush=True)
        return bool(report.stable), report.text()

    rac = ctrl.replace(type='rac') if ctrl.type != 'rac' and args.controller is None else ctrl
    controllers = {'rac': ctrl.replace(type='rac'), 'pi': ctrl.replace(type='pi')}
    if args.controller is not None:
        controllers = {args.controller: ctrl}
    names = ex.EXPERIMENTS if args.experiment == 'all' else (args.experiment,)
    if opts.action == 'refuse':
        # refuse up front, before any run, naming the first unstable configuration
        for plant in plants:
            sp = stage.with_flat({'plant.model': plant})
            for cp in ({rac.type: rac} | controllers).values():
                if names != ('fig6',):
                    report = check_stability(cp, design_plant(opts, sp.plant),
                                             sp.sample_time_s, options=opts)
                    _enforce(report, 'refuse')
    results = []
    for name in names:
        progress(f'experiment {name}')
        if name == 'table3':
            results.append(ex.run_table3(stage, controllers, plants=plants,
                                         stability=stability, progress=progress))
        elif name == 'square':
            results.append(ex.run_square(stage, rac, plants=plants, stability=stability,
                                         progress=progress))
        elif name == 'staircase':
            results.append(ex.run_staircase(stage, rac, plants=plants, stability=stability,
                                            progress=progress))
        elif name == 'multisine':
            results.append(ex.run_multisine(stage, rac, ctrl.replace(type='open_loop'),
                                            plants=plants, stability=stability,
                                            progress=progress))
        else:
            sp = stage.with_flat({'plant.model': args.plant}) if args.plant else stage
            results.append(ex.run_fig6(sp, progress=progress))
    progress(f'done in {shown.elapsed():.1f} s')
    if args.json:
        print(json.dumps({'experiments': [r.to_json() for r in results],
                          'wall_seconds': shown.elapsed()}, sort_keys=True))
    else:
        print('\n\n'.join(ex.format_result(r) for r in results))
    return 0


def _main(args: argparse.Namespace) -> int:
    from piezo_stage_ros.core.config.axes import has_axes
    config = build_config(args)
    if has_axes(config):
        # a multi-axis stage (plant_node axes.names): the multi-axis loop, the flags setting
        # the base of every axis
        from piezo_stage_ros.simulate_axes import from_simulate
        return from_simulate(args, config)
    loop = load_loop(args)
    if args.experiment is not None:
        if args.bag is not None:
            raise ConfigError('--bag records one run; it cannot be used with --experiment')
        if args.save_table is not None:
            raise ConfigError('--save-table keeps the table of one run; it cannot be used '
                              'with --experiment')
        if args.steady_state_start_s is not None:
            raise ConfigError('--steady-state-start measures one run; each experiment has its '
                              "own window (the paper's); it cannot be used with --experiment")
        return _run_experiments(args, loop)
    return _run_single(args, loop)


main = cli.command_main(PROG, build_parser, _main,
                        '0 success, 1 bad parameter / configuration / refused run, 2 bad usage')


if __name__ == '__main__':
    sys.exit(main())
