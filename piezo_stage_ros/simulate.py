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
checked (:mod:`piezo_stage_ros.core.stability`): an unstable verdict is printed loudly, or the
run is refused with ``--refuse-unstable`` (or ``controller_node: stability.action: refuse``).

Examples::

    simulate --controller rac --trajectory sine --frequency 100 --json
    simulate --plant reduced --controller pi --frequency 50
    simulate --trajectory multisine --frequency 10 --frequency 100 --amplitude 1.9e-6
    simulate --experiment table3          # the paper's Table III, project beside paper
    simulate --bag run1 --duration 2      # write the run as a rosbag2 bag (MCAP)

Exit status: 0 on success, 1 on a bad parameter, configuration or refused run, 2 on bad
command-line usage; the error is one line on stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from typing import Any, Mapping, NoReturn, Sequence
import warnings

from piezo_stage_ros.core.config import Config, find_config, load_config
from piezo_stage_ros.core.errors import ConfigError, ParameterError, PiezoStageError
from piezo_stage_ros.core.params import Params
from piezo_stage_ros.core.trajectories import KINDS
import yaml

__all__ = ['build_parser', 'load_parameters', 'main']

PROG = 'simulate'


class _UsageError(Exception):
    """Bad command-line usage (argparse would otherwise exit with its own message)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        raise _UsageError(message)


def build_parser() -> argparse.ArgumentParser:
    """Return the command-line parser of ``simulate``."""
    p = _Parser(prog=PROG, description='Run the piezo stage closed loop offline (no ROS) and '
                "print its tracking metrics, or run one of the paper's experiments.")
    p.add_argument('--config', action='append', default=[], metavar='FILE',
                   help='ROS 2 parameter file applied on top of config/default.yaml '
                   '(repeatable; later files win).')
    p.add_argument('--param', action='append', default=[], metavar='NODE:NAME=VALUE',
                   help='Set one parameter, e.g. controller_node:rac.epsilon_v=0.05 '
                   '(VALUE is YAML; repeatable).')
    p.add_argument('--plant', choices=('electromechanical', 'third_order', 'reduced'),
                   help='Linear plant model (plant_node plant.model).')
    p.add_argument('--hysteresis', choices=('backlash_like', 'bouc_wen', 'prandtl_ishlinskii',
                                            'none'),
                   help='Hysteresis model (plant_node hysteresis.model).')
    p.add_argument('--controller', choices=('rac', 'pi', 'open_loop'),
                   help='Controller (controller_node type).')
    p.add_argument('--trajectory', choices=KINDS,
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
    p.add_argument('--seed', type=int, metavar='N', help='Seed of the sensor noise.')
    p.add_argument('--noise', type=float, metavar='M',
                   help='Sensor noise standard deviation [m] (plant_node '
                   'chain.sensor_noise_std_m).')
    p.add_argument('--experiment', choices=('table3', 'square', 'staircase', 'multisine',
                                            'fig6', 'all'),
                   help="Run one of the paper's experiments and print project vs paper.")
    p.add_argument('--refuse-unstable', action='store_true',
                   help='Refuse to run a controller the stability check finds unstable on the '
                   'configured model (default: warn loudly and run).')
    p.add_argument('--json', action='store_true',
                   help='Print one JSON object on stdout instead of the readable summary.')
    p.add_argument('--bag', metavar='DIR', help='Write the run as a rosbag2 bag.')
    p.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                   help='Bag storage plugin (default mcap).')
    p.add_argument('--overwrite', action='store_true', help='Replace an existing bag.')
    return p


def _node_params(config: Config, node: str, cls: type[Params],
                 skip_prefixes: Sequence[str] = ()) -> dict[str, Any]:
    """
    Return the values of ``node`` that belong to ``cls``.

    A key belongs when its first dotted part is a field of ``cls``; the group then validates
    it strictly (a misspelt ``rac.epsilon`` is refused). Other keys (wildcard ``/**`` values
    such as ``use_sim_time``, settings of the ROS node itself) are left to the node.
    """
    fields = {s.name.split('.', 1)[0] for s in cls.specs()}
    return {key: value for key, value in config.node(node).items()
            if key.split('.', 1)[0] in fields
            and not any(key.startswith(p) for p in skip_prefixes)}


def _parse_param(text: str) -> tuple[str, str, Any]:
    """Split ``NODE:NAME=VALUE`` (VALUE parsed as YAML)."""
    if ':' not in text or '=' not in text:
        raise ConfigError(f'--param {text!r}: expected NODE:NAME=VALUE, e.g. '
                          'controller_node:rac.epsilon_v=0.05')
    node, rest = text.split(':', 1)
    name, raw = rest.split('=', 1)
    if not node or not name:
        raise ConfigError(f'--param {text!r}: expected NODE:NAME=VALUE')
    text = raw.strip()
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        value = text
    # read as ROS 2 (YAML 1.2) does: 'off'/'yes' stay strings, '1e-6' is a float
    if isinstance(value, bool) and text.lower() not in ('true', 'false'):
        value = text
    elif isinstance(value, str):
        try:
            value = float(text)
        except ValueError:
            pass
    return node.strip(), name.strip(), value


def _flag_overrides(args: argparse.Namespace, config: Config) -> Config:
    """Apply the short flags on top of the configuration."""
    plant: dict[str, Any] = {}
    if args.plant is not None:
        plant['plant.model'] = args.plant
    if args.hysteresis is not None:
        plant['hysteresis.model'] = args.hysteresis
    if args.seed is not None:
        plant['seed'] = args.seed
    if args.noise is not None:
        plant['chain.sensor_noise_std_m'] = args.noise
    if plant:
        config = config.with_overrides('plant_node', plant)
    if args.controller is not None:
        config = config.with_overrides('controller_node', {'type': args.controller})
    traj: dict[str, Any] = {}
    if args.trajectory is not None:
        traj['kind'] = args.trajectory
    kind = traj.get('kind', config.node('trajectory_node').get('kind', 'sine'))
    freqs = args.frequency
    if kind in ('sine', 'triangle'):
        if freqs:
            if len(freqs) > 1:
                raise ParameterError('--frequency', freqs, f'one value for {kind}',
                                     'is repeated; only multisine takes several')
            traj[f'{kind}.frequency_hz'] = freqs[0]
        if args.amplitude is not None:
            traj[f'{kind}.amplitude_m'] = args.amplitude
        if args.offset is not None:
            traj[f'{kind}.offset_m'] = args.offset
    elif kind == 'multisine':
        current = config.node('trajectory_node')
        n = len(freqs) if freqs else len(current.get('multisine.frequencies_hz', [10.0, 100.0]))
        if freqs:
            traj['multisine.frequencies_hz'] = list(freqs)
        if args.amplitude is not None:
            traj['multisine.amplitudes_m'] = [args.amplitude] * n
        elif freqs:
            amps = list(current.get('multisine.amplitudes_m', [1.9e-6, 1.9e-6]))
            if len(amps) != n:
                # keep the total excursion of the configured multisine, shared equally
                traj['multisine.amplitudes_m'] = [sum(amps) / n] * n
        if args.offset is not None:
            traj['multisine.offset_m'] = args.offset
    else:
        if freqs:
            raise ParameterError('--frequency', freqs[0], 'sine, triangle or multisine',
                                 f'does not apply to trajectory {kind!r}')
        names = {'square': ('square.peak_to_peak_m', 'square.low_m'),
                 'staircase': ('staircase.step_m', 'staircase.start_m'),
                 'step': ('step.final_m', 'step.initial_m'),
                 'noise': ('noise.amplitude_m', 'noise.offset_m'),
                 'chirp': ('chirp.amplitude_m', 'chirp.offset_m')}.get(kind, (None, None))
        for flag, name in ((args.amplitude, names[0]), (args.offset, names[1])):
            if flag is not None:
                if name is None:
                    raise ParameterError('--amplitude/--offset', flag,
                                         'not with trajectory ' + repr(kind),
                                         f'does not apply to trajectory {kind!r}')
                traj[name] = flag
    if args.csv is not None:
        traj['csv.path'] = args.csv
    if traj:
        config = config.with_overrides('trajectory_node', traj)
    return config


def load_parameters(args: argparse.Namespace) -> dict[str, Any]:
    """
    Build the validated parameter objects from files, ``--param`` and flags.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed command line.

    Returns
    -------
    dict
        ``stage`` (StageParams), ``controller`` (ControllerParams), ``trajectory``
        (TrajectoryParams), ``stability`` (StabilityParams).

    """
    from piezo_stage_ros.core.controllers import ControllerParams
    from piezo_stage_ros.core.stability import StabilityParams
    from piezo_stage_ros.core.stage import StageParams
    from piezo_stage_ros.core.trajectories import TrajectoryParams

    config = load_config([find_config('default.yaml'), *args.config])
    for text in args.param:
        node, name, value = _parse_param(text)
        config = config.with_overrides(node, {name: value})
    config = _flag_overrides(args, config)
    stage = StageParams.from_flat(_node_params(config, 'plant_node', StageParams),
                                  prefix='')
    controller = ControllerParams.from_flat(
        _node_params(config, 'controller_node', ControllerParams, ('stability.',)))
    ctrl_values = config.node('controller_node')
    stability = StabilityParams.from_flat(
        {k: v for k, v in ctrl_values.items() if k.startswith('stability.')},
        prefix='stability.')
    if args.refuse_unstable:
        stability = stability.replace(action='refuse')
    trajectory = TrajectoryParams.from_flat(
        _node_params(config, 'trajectory_node', TrajectoryParams))
    return {'stage': stage, 'controller': controller, 'trajectory': trajectory,
            'stability': stability, 'config': config}


def _err(message: str) -> None:
    print(f'{PROG}: error: {message}', file=sys.stderr)


def _clean(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _stability(params: Mapping[str, Any]) -> tuple[Any, str]:
    """Run the stability check of the configured controller on the configured plant."""
    from piezo_stage_ros.core.stability import check_stability
    stage = params['stage']
    report = check_stability(params['controller'], stage.plant, stage.sample_time_s,
                             options=params['stability'])
    return report, report.text()


def _enforce(report: Any, action: str) -> None:
    """Warn loudly on stderr or refuse (raises StabilityError)."""
    from piezo_stage_ros.core.stability import enforce
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


def _run_single(args: argparse.Namespace, params: dict[str, Any]) -> int:
    from piezo_stage_ros.core import metrics
    from piezo_stage_ros.core.experiments import default_duration_s, run_one
    from piezo_stage_ros.core.trajectories import make_trajectory

    stage, ctrl, traj = params['stage'], params['controller'], params['trajectory']
    report, text = _stability(params)
    _enforce(report, params['stability'].action)
    trajectory = make_trajectory(traj)
    duration = args.duration if args.duration is not None else default_duration_s(trajectory,
                                                                                  traj)
    if not (duration > 0.0 and math.isfinite(duration)):
        raise ParameterError('--duration', duration, '(0, inf) s')
    meta = {'stable': bool(report.stable), 'stability': text,
            'config_files': [str(p) for p in params['config'].sources]}
    start = time.perf_counter()
    if args.bag is not None:
        from piezo_stage_ros.analysis.bagwrite import RunBagWriter
        with RunBagWriter(args.bag, storage=args.storage, overwrite=args.overwrite) as writer:
            def stream(chunk: Any) -> None:
                writer.set_meta(chunk.meta)
                writer.write_chunk(chunk)
            record = run_one(stage, ctrl, traj, duration_s=duration, chunk_callback=stream,
                             meta=meta)
    else:
        record = run_one(stage, ctrl, traj, duration_s=duration, meta=meta)
    wall = time.perf_counter() - start
    summary = metrics.summarize(record)
    sim = float(record.meta['duration_s'])
    out: dict[str, Any] = dict(summary)
    out.update({'sim_seconds': sim, 'wall_seconds': wall,
                'realtime_factor': sim / wall if wall > 0 else math.inf,
                'stable': bool(report.stable), 'plant': stage.plant.model,
                'hysteresis': stage.hysteresis.model, 'controller': ctrl.type,
                'trajectory': traj.kind, 'seed': stage.seed,
                'trajectory_period_s': record.meta.get('trajectory_period_s'),
                'bag': args.bag})
    if args.json:
        print(json.dumps({k: _clean(v) for k, v in out.items()}, sort_keys=True))
        return 0
    period = record.meta.get('trajectory_period_s')
    print(f'{ctrl.type} on the {stage.plant.model} plant with {stage.hysteresis.model} '
          f'hysteresis, trajectory {traj.kind}'
          + (f' (period {period:g} s)' if period else ''))
    print(f'stability check: {"stable" if report.stable else "UNSTABLE"}')
    print(f'simulated {sim:g} s ({int(summary["samples"])} samples) in {wall:.3f} s wall '
          f'({out["realtime_factor"]:.1f}x real time)')
    print(f'steady state from {summary["steady_state_start_s"]:g} s '
          f'({int(summary["steady_state_samples"])} samples):')
    print(f'  e_m   = {summary["e_max_m"] * 1e9:10.2f} nm')
    print(f'  e_rms = {summary["e_rms_m"] * 1e9:10.2f} nm')
    if math.isfinite(summary['loop_width_pct']):
        print(f'  loop width (x vs x_d) = {summary["loop_width_pct"]:.2f} % of range')
    print(f'whole run: e_m = {summary["e_max_all_m"] * 1e9:.2f} nm, e_rms = '
          f'{summary["e_rms_all_m"] * 1e9:.2f} nm')
    print(f'command range: {summary["command_min_v"]:.3f} ... {summary["command_max_v"]:.3f} V')
    for name in ('theta_hat', 'phi_hat'):
        if f'{name}_min' in summary:
            print(f'{name}: {summary[name + "_min"]:.6g} ... {summary[name + "_max"]:.6g}')
    if args.bag is not None:
        print(f'bag written: {args.bag} ({args.storage})')
    return 0


def _run_experiments(args: argparse.Namespace, params: dict[str, Any]) -> int:
    from piezo_stage_ros.core import experiments as ex
    from piezo_stage_ros.core.stability import check_stability

    stage, ctrl, opts = params['stage'], params['controller'], params['stability']
    plants: tuple[str, ...] = (args.plant,) if args.plant else ('reduced', 'third_order')
    t0 = time.perf_counter()

    def progress(line: str) -> None:
        print(f'[{time.perf_counter() - t0:6.1f} s] {line}', file=sys.stderr, flush=True)

    warned: set[tuple[str, str]] = set()

    def stability(sp: Any, cp: Any) -> tuple[bool | None, str]:
        report = check_stability(cp, sp.plant, sp.sample_time_s, options=opts)
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
                    report = check_stability(cp, sp.plant, sp.sample_time_s, options=opts)
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
    progress(f'done in {time.perf_counter() - t0:.1f} s')
    if args.json:
        print(json.dumps({'experiments': [r.to_json() for r in results],
                          'wall_seconds': time.perf_counter() - t0}, sort_keys=True))
    else:
        print('\n\n'.join(ex.format_result(r) for r in results))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """
    Run ``simulate``.

    Parameters
    ----------
    argv : sequence of str, optional
        Command-line arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    int
        Exit status: 0 success, 1 bad parameter / configuration / refused run, 2 bad usage.

    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except _UsageError as exc:
        _err(f'{exc} (see {PROG} --help)')
        return 2
    try:
        params = load_parameters(args)
        if args.experiment is not None:
            if args.bag is not None:
                raise ConfigError('--bag records one run; it cannot be used with --experiment')
            return _run_experiments(args, params)
        return _run_single(args, params)
    except PiezoStageError as exc:
        _err(str(exc))
        return 1
    except KeyboardInterrupt:
        _err('interrupted')
        return 130


if __name__ == '__main__':
    sys.exit(main())
