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
Command-line program ``simulate_axes``: the multi-axis closed loop offline, per-axis metrics.

Reads the parameter files of a multi-axis stage (``plant_node axes.names``, see
:mod:`piezo_stage_ros.core.config.axes`), runs every axis' controller on the coupled
stage and prints, per axis, the tracking error over the last ``--window`` seconds: the measured
position (sensor, noise, ADC) and the true one. A raster's fast axis is measured over the middle
80 % of its lines (its turn-arounds left out). ``simulate --config FILE`` runs this for such a
file. ``--bag DIR`` writes the run as a multi-axis bag, which ``analyze`` reads back into the
same figures.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import sys
import time
from typing import Any, Sequence
import warnings

from piezo_stage_ros import cli
from piezo_stage_ros.core.config.axes import axes_loop_config, AxesLoopConfig
from piezo_stage_ros.core.config.loader import Config
from piezo_stage_ros.core.contracts.errors import ConfigError, ParameterError
from piezo_stage_ros.core.contracts.wire import STORAGE_IDS
from piezo_stage_ros.core.loop.axes import LINE_FRACTION
from piezo_stage_ros.core.model.axes import AxesStageParams

__all__ = ['LINE_FRACTION', 'build_parser', 'main', 'run_config', 'simulate_axes']

PROG = 'simulate_axes'


def build_parser() -> argparse.ArgumentParser:
    """Return the command-line parser of ``simulate_axes``."""
    p = cli.Parser(prog=PROG, description='Run the closed loop of a multi-axis stage offline '
                   '(no ROS) and print per-axis tracking metrics.')
    cli.add_config_options(p)
    cli.add_feedforward_option(p)
    p.add_argument('--compensation', choices=('on', 'off'),
                   help='Coupling compensation in the feed-forward (controller_node '
                   'axes.coupling_compensation).')
    p.add_argument('--scan', help='Scan kind (trajectory_node scan.kind).')
    p.add_argument('--duration', type=float, metavar='S',
                   help='Simulated time [s] (default: 8 periods of the longest axis period, '
                   'at least 2 s, or 2 s).')
    p.add_argument('--window', type=float, metavar='S',
                   help='Metrics over the last S seconds (default 1, or the whole run when '
                   'shorter).')
    p.add_argument('--family', type=int, metavar='N',
                   help='Run on N stages unlike the configured one instead (each axis its own '
                   'member of the stage family, every coupling path a gain of 0.5-5 %%), the '
                   'controllers designed on the configured stage; print each and the worst.')
    p.add_argument('--seed', type=int, default=0, metavar='S',
                   help='Seed of the --family draw (default 0).')
    p.add_argument('--json', action='store_true', help='Print one JSON object.')
    p.add_argument('--bag', metavar='DIR', help='Write the run as a rosbag2 bag (every axis in '
                   'one message a sample; analyze reads it).')
    p.add_argument('--storage', choices=STORAGE_IDS, default=STORAGE_IDS[0],
                   help='Bag storage plugin (default mcap).')
    p.add_argument('--overwrite', action='store_true', help='Replace an existing bag.')
    p.add_argument('--bag-topics', choices=('samples', 'block', 'both'), default='samples',
                   help='What the bag holds: the per-sample topics (default), the block topic '
                   'stage/block (every axis in a row, many samples per message, as a real-time '
                   'loop records them; docs/reference/bags.md), or both.')
    return p


def _config(args: argparse.Namespace) -> Config:
    config = cli.read_config(args.config, args.param)
    values: dict[str, dict[str, Any]] = {}
    if args.feedforward is not None:
        values.setdefault('controller_node', {})['feedforward.mode'] = args.feedforward
    if args.compensation is not None:
        values.setdefault('controller_node', {})['axes.coupling_compensation'] = \
            args.compensation == 'on'
    if getattr(args, 'scan', None) is not None:
        values.setdefault('trajectory_node', {})['scan.kind'] = args.scan
    for node, vals in values.items():
        config = config.with_overrides(node, vals)
    return config


def default_duration_s(loop: AxesLoopConfig) -> float:
    """Return 8 periods of the longest axis period (>= 2 s), or 2 s without one."""
    periods = [p for p in (getattr(t, 'period_s', None) for t in loop.trajectories())
               if isinstance(p, float) and p > 0.0]
    return max(8.0 * max(periods), 2.0) if periods else 2.0


def simulate_axes(loop: AxesLoopConfig, *, duration_s: float, window_s: float = 1.0,
                  stage: AxesStageParams | None = None, bag: str | None = None,
                  storage: str = STORAGE_IDS[0], overwrite: bool = False,
                  topics: str = 'samples') -> dict[str, Any]:
    """
    Run the multi-axis loop and return its per-axis metrics.

    Parameters
    ----------
    loop : AxesLoopConfig
        The configuration (its stage is the controllers' design model).
    stage : AxesStageParams, optional
        The stage the loop runs on; default the configured one.
    duration_s : float
        Simulated time [s].
    window_s : float
        Metrics over the last this many seconds, in (0, duration_s].
    bag : str, optional
        Write the run there as a multi-axis bag (its description: :func:`bag_meta`).
    storage : str
        The bag's storage plugin.
    overwrite : bool
        Replace an existing bag.
    topics : {'samples', 'block', 'both'}
        What the bag holds (:class:`~piezo_stage_ros.analysis.bagwrite.RunBagWriter`).

    Returns
    -------
    dict
        ``axes``: per axis name, e_rms / e_max of the measured and the true position [m] and
        the samples in the window; ``compensated``: the axes whose feed-forward carried the
        coupling compensation; the check of the loops with the coupling
        (:func:`coupled_loop_check`); timing.

    """
    from piezo_stage_ros.core.control.axes import AxesController, coupled_loop_check
    from piezo_stage_ros.core.loop.axes import run_axes, run_metrics
    from piezo_stage_ros.core.model.axes import AxesStage

    if not (duration_s > 0.0 and math.isfinite(duration_s)):
        raise ParameterError('--duration', duration_s, '(0, inf) s')
    if not (0.0 < window_s <= duration_s):
        raise ParameterError('--window', window_s, f'(0, {duration_s:g}] s (the run)')
    trajectories = loop.trajectories()
    ctrl = AxesController.build(loop.controllers, loop.stage, compensate=loop.compensate)
    stable = _check_axes(loop, trajectories)
    check = coupled_loop_check(ctrl)
    with contextlib.ExitStack() as stack:
        writer = None
        if bag is not None:
            from piezo_stage_ros.analysis.bagwrite import RunBagWriter
            # opened before the run: an existing path is refused before the run's time is
            # spent, and a run that fails leaves no bag
            writer = stack.enter_context(RunBagWriter(bag, storage=storage, overwrite=overwrite,
                                                      axes=loop.stage.names, topics=topics))
        start = time.perf_counter()
        records = run_axes(AxesStage(loop.stage if stage is None else stage), ctrl, trajectories,
                           duration_s=duration_s)
        wall = time.perf_counter() - start
        fast = loop.scan.raster.fast_axis if loop.scan.kind == 'raster' else None
        axes: dict[str, Any] = {}
        for rec, (name, m) in zip(records, run_metrics(records, window_s=window_s,
                                                       fast_axis=fast).items()):
            axes[name] = {**metrics_fields(m, name == fast),
                          'trajectory_period_s': rec.meta.get('trajectory_period_s'),
                          'feedforward': loop.controllers[loop.stage.index(name)].feedforward.mode,
                          'stable': stable[name]}
        sim = float(records[0].meta['duration_s'])
        out = {'axes': axes, 'scan': loop.scan.kind, 'compensation': loop.compensate,
               'compensated': [loop.stage.names[j] for j in ctrl.compensated],
               'coupling_check': check.text(), 'coupling_gain': check.coupling_gain,
               'learning_ratio': check.learning_ratio,
               'sim_seconds': sim, 'wall_seconds': wall, 'window_s': window_s,
               'config_files': [str(p) for p in loop.base.sources], 'bag': bag}
        bag_start = time.perf_counter()
        if writer is not None:
            writer.set_meta(bag_meta(loop, out, records))
            writer.write_axes_chunk(records)
    if bag is not None:
        out['bag_wall_seconds'] = time.perf_counter() - bag_start
    return out


def metrics_fields(m: Any, fast: bool) -> dict[str, Any]:
    """Return one axis' :class:`~piezo_stage_ros.core.loop.axes.AxisMetrics` as printed."""
    return {'e_rms_m': m.e_rms_m, 'e_max_m': m.e_max_m, 'e_rms_true_m': m.e_rms_true_m,
            'e_max_true_m': m.e_max_true_m, 'samples': m.samples,
            'window': (f'middle {100.0 * LINE_FRACTION:g} % of the lines' if fast else 'all')}


def bag_meta(loop: AxesLoopConfig, out: dict[str, Any], records: Sequence[Any]
             ) -> dict[str, Any]:
    """
    Return the description of a multi-axis run stored with its bag.

    What ``analyze`` needs to measure the bag as ``simulate_axes`` measured the run (the scan,
    a raster's fast axis and lines, the window) and the run's parameters, per axis under
    ``per_axis``.
    """
    raster = loop.scan.raster if loop.scan.kind == 'raster' else None
    per_axis = {}
    for rec, sp, cp, line in zip(records, loop.stage.axes, loop.controllers, loop.lines):
        name = str(rec.meta['axis'])
        per_axis[name] = {
            # what the axis plays: its own trajectory, a raster's line, or its part of the scan
            'trajectory': line.kind if loop.scan.kind == 'each' or (
                raster is not None and name == raster.fast_axis) else loop.scan.kind,
            'trajectory_period_s': rec.meta.get('trajectory_period_s'),
            'plant': sp.plant.model, 'hysteresis': sp.hysteresis.model, 'seed': sp.seed,
            'controller': cp.type, 'feedforward': cp.feedforward.mode,
            'stable': out['axes'][name]['stable']}
    return {'axes': list(loop.stage.names), 'scan': loop.scan.kind,
            'fast_axis': raster.fast_axis if raster else None,
            'slow_axis': raster.slow_axis if raster else None,
            'lines': raster.lines if raster else None, 'line_fraction': LINE_FRACTION,
            'window_s': out['window_s'], 'sample_time_s': loop.stage.sample_time_s,
            'sample_rate_hz': 1.0 / loop.stage.sample_time_s,
            'duration_s': out['sim_seconds'], 'compensation': loop.compensate,
            'compensated': out['compensated'], 'coupling_check': out['coupling_check'],
            'coupling': dataclasses.asdict(loop.stage.coupling),
            'config_files': out['config_files'], 'per_axis': per_axis}


def _check_axes(loop: AxesLoopConfig, trajectories: Sequence[Any]) -> dict[str, bool]:
    """Check each axis' own loop as simulate does (warn on stderr, or refuse on request)."""
    from piezo_stage_ros.core.control.stability import enforce
    out = {}
    for name, report in loop.stability(trajectories).items():
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')  # printed below as one line
            enforce(report, loop.base.stability.action)
        if not report.stable:
            print(f'{PROG}: WARNING: UNSTABLE CONFIGURATION on axis {name}: {report.text()}',
                  file=sys.stderr)
        out[name] = bool(report.stable)
    return out


def run_config(prog: str, config: Config, *, duration_s: float | None,
               window_s: float | None, as_json: bool, bag: str | None = None,
               storage: str = STORAGE_IDS[0], overwrite: bool = False,
               topics: str = 'samples') -> int:
    """Run the loop and print its metrics (window None: the last second, or the run)."""
    loop = axes_loop_config(config)
    for text in loop.base.offline_notes():
        cli.note(prog, text)
    duration = default_duration_s(loop) if duration_s is None else duration_s
    if window_s is None:
        window_s = min(1.0, duration) if duration > 0.0 else 1.0
    out = simulate_axes(loop, duration_s=duration, window_s=window_s, bag=bag,
                        storage=storage, overwrite=overwrite, topics=topics)
    if as_json:
        print(json.dumps(out, sort_keys=True))
        return 0
    names = ', '.join(loop.stage.names)
    print(f'{len(loop.stage.names)} axes ({names}), scan {out["scan"]}, coupling compensation '
          f'{"on" if loop.compensate else "off"} (applied on: '
          f'{", ".join(out["compensated"]) or "none"})')
    print(out['coupling_check'])
    print(f'simulated {out["sim_seconds"]:g} s in {out["wall_seconds"]:.2f} s wall')
    print(f'last {window_s:g} s:')
    for name, m in out['axes'].items():
        print(f'  {name} ({m["feedforward"]}, {m["window"]}, '
              f'{"stable" if m["stable"] else "UNSTABLE"}): e_rms = {m["e_rms_m"] * 1e9:.2f} '
              f'nm, e_m = {m["e_max_m"] * 1e9:.2f} nm; true position: e_rms = '
              f'{m["e_rms_true_m"] * 1e9:.2f} nm, e_m = {m["e_max_true_m"] * 1e9:.2f} nm')
    if bag is not None:
        print(f'bag written: {bag} ({storage}, {out["bag_wall_seconds"]:.2f} s wall)')
    return 0


def from_simulate(args: argparse.Namespace, config: Config) -> int:
    """
    Run ``simulate`` on a multi-axis file (``config``: its files, --param and flags).

    The flags that set one-axis parameters set the base of every axis; the options of one run
    that have no multi-axis counterpart yet are refused.
    """
    for flag, value in (('--save-table', args.save_table),
                        ('--experiment', args.experiment),
                        ('--steady-state-start', args.steady_state_start_s)):
        if value is not None:
            raise ConfigError(f'{flag} is not available for a multi-axis stage yet '
                              '(plant_node axes.names); run without it')
    return run_config('simulate', config, duration_s=args.duration, window_s=None,
                      as_json=args.json, bag=args.bag, storage=args.storage,
                      overwrite=args.overwrite, topics=args.bag_topics)


def simulate_family(loop: AxesLoopConfig, n: int, *, seed: int, duration_s: float,
                    window_s: float) -> dict[str, Any]:
    """
    Run the loop on ``n`` stages unlike the configured one and return each one's metrics.

    Parameters
    ----------
    loop : AxesLoopConfig
        The configuration: the controllers' design model.
    n : int
        Members (:func:`~piezo_stage_ros.core.model.axes.sample_axes_family`), >= 1.
    seed : int
        Seed of the draw.
    duration_s, window_s : float
        As :func:`simulate_axes`.

    Returns
    -------
    dict
        ``members``: description and per-axis metrics of each; ``worst``: per axis the largest
        e_rms and e_max over the members; ``diverged``: members whose error over the window
        is not finite or above :data:`DIVERGED_M`.

    """
    from piezo_stage_ros.core.model.axes import sample_axes_family
    if n < 1:
        raise ParameterError('--family', n, '[1, inf) members')
    members = []
    worst: dict[str, dict[str, float]] = {}
    diverged = []
    for k, (text, stage) in enumerate(sample_axes_family(loop.stage, n, seed)):
        out = simulate_axes(loop, duration_s=duration_s, window_s=window_s, stage=stage)
        members.append({'member': k, 'description': text, 'axes': out['axes']})
        for name, m in out['axes'].items():
            w = worst.setdefault(name, {'e_rms_m': 0.0, 'e_max_m': 0.0, 'e_rms_true_m': 0.0,
                                        'e_max_true_m': 0.0})
            bad = not (math.isfinite(m['e_max_m']) and m['e_max_m'] <= DIVERGED_M)
            if bad and k not in diverged:
                diverged.append(k)
            for key in w:
                w[key] = max(w[key], m[key]) if math.isfinite(m[key]) else math.inf
    return {'members': members, 'worst': worst, 'diverged': diverged, 'seed': seed,
            'scan': loop.scan.kind}


#: An error over the window above this counts as diverged [m] (a tenth of a 10 um scan).
DIVERGED_M = 1e-6


def _run_family(args: argparse.Namespace, config: Config) -> int:
    loop = axes_loop_config(config)
    duration = default_duration_s(loop) if args.duration is None else args.duration
    window = args.window if args.window is not None else min(1.0, duration)
    out = simulate_family(loop, args.family, seed=args.seed, duration_s=duration,
                          window_s=window)
    if args.json:
        print(json.dumps(out, sort_keys=True))
        return 0
    print(f'{args.family} stages unlike the configured one (seed {args.seed}), scan '
          f'{out["scan"]}, last {window:g} s:')
    for m in out['members']:
        errs = ', '.join(f'{name} {a["e_rms_m"] * 1e9:.2f} nm rms ({a["e_max_m"] * 1e9:.1f} '
                         f'max; true {a["e_rms_true_m"] * 1e9:.2f})'
                         for name, a in m['axes'].items())
        print(f'  {m["member"]:3d}: {errs}   [{m["description"]}]')
    print('worst: ' + ', '.join(f'{name} {w["e_rms_m"] * 1e9:.2f} nm rms, '
                                f'{w["e_max_m"] * 1e9:.1f} nm max (true position '
                                f'{w["e_rms_true_m"] * 1e9:.2f} nm rms)'
                                for name, w in out['worst'].items()))
    print(f'diverged: {out["diverged"] or "none"}')
    return 0


def _main(args: argparse.Namespace) -> int:
    if args.family is not None and args.bag is not None:
        raise ConfigError('--bag records one run; it cannot be used with --family')
    if args.family is not None:
        return _run_family(args, _config(args))
    return run_config(PROG, _config(args), duration_s=args.duration, window_s=args.window,
                      as_json=args.json, bag=args.bag, storage=args.storage,
                      overwrite=args.overwrite, topics=args.bag_topics)


main = cli.command_main(PROG, build_parser, _main,
                        '0 success, 1 bad parameter or configuration, 2 bad usage')


if __name__ == '__main__':
    sys.exit(main())
