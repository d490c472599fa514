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
``identify_axes``: identification of a multi-axis stage, per axis and of the coupling, offline.

Runs the experiments on the configured stage (the true stage of the simulation; ``--member
SEED`` draws one unlike it from the multi-axis stage family instead) and identifies:

- each axis with the one-axis procedure of ``identify`` (its three open-loop runs on that axis
  while the others hold their rest voltages), unless ``--coupling-only``;
- every coupling path i -> j, one axis excited at a time by a periodic band-limited noise while
  the others hold (:mod:`piezo_stage_ros.core.identification.coupling`).

Prints per axis and per path the estimates with their 95 % bounds and the truth, and writes a
parameter file (``--output``) holding ``plant_node axes.coupling.*`` and, per axis, the
identified values that differ from the configuration as ``axes.<name>.*``. It is read on top of
the configuration::

    identify_axes --config config/xy_stage.yaml --output xy_identified.yaml
    simulate --config config/xy_stage.yaml --config xy_identified.yaml

A path whose gain the data does not show (95 % bounds around zero) is written as zero.

``--bags DIR`` records each coupling run as a bag ``DIR/coupling_<axis>`` (the excited axis;
one message a sample for all axes, as a multi-axis run is recorded); ``--from-bags BAG ...``
fits the coupling from such bags instead of running the experiments, e.g. bags recorded on a
real stage with one axis driven by a periodic signal and the others held. The axes' own models
are then the configured ones::

    identify_axes --config config/xy_stage.yaml --coupling-only --bags runs/
    identify_axes --config config/xy_stage.yaml --from-bags runs/coupling_x runs/coupling_y

Exit status: 0 on success, 1 on bad parameters or a failed identification, 2 on bad usage.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
import sys
from typing import Any, Sequence

import numpy as np
from piezo_stage_ros import cli
from piezo_stage_ros.core.config.axes import axes_loop_config
from piezo_stage_ros.core.config.loader import nest
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.identification.coupling import (
    AxesRun,
    CouplingPlan,
    excitation_runs,
    fit_coupling,
    identified_coupling,
    PathFit,
    rest_voltages,
)
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.model.axes import AxesStageParams, CouplingParams
import yaml

__all__ = ['build_parser', 'coupling_file_text', 'main', 'records_run', 'run_records']

PROG = 'identify_axes'


def build_parser() -> argparse.ArgumentParser:
    """Return the command-line parser of ``identify_axes``."""
    p = cli.Parser(prog=PROG, description='Identify a multi-axis stage offline: each axis with '
                   'the one-axis procedure while the others hold, and every coupling path with '
                   'one axis excited at a time; write the parameter file.')
    cli.add_config_options(p)
    p.add_argument('--output', default='identified_axes.yaml', metavar='FILE',
                   help='Parameter file to write (default: identified_axes.yaml), read on top '
                   'of the configuration.')
    p.add_argument('--coupling-only', action='store_true',
                   help='Identify the coupling only (the configured axes as the model).')
    p.add_argument('--member', type=int, metavar='SEED',
                   help='The true stage is a member of the multi-axis stage family drawn from '
                   'SEED (each axis unlike the configured one, every coupling path a gain of '
                   '0.5-5 %%) instead of the configured stage.')
    p.add_argument('--sensor-noise', type=float, metavar='M',
                   help="Every axis' sensor noise [m rms] in the experiments (default: as "
                   'configured).')
    defaults = CouplingPlan()
    p.add_argument('--rms', type=float, default=defaults.rms_v, metavar='V',
                   help=f'Excitation of the coupling runs [V rms] (default {defaults.rms_v:g}).')
    p.add_argument('--period', type=float, default=defaults.period_s, metavar='S',
                   help='Period of the coupling excitation [s] (default '
                   f'{defaults.period_s:g}): a longer one resolves smaller paths.')
    p.add_argument('--periods', type=int, default=defaults.periods, metavar='N',
                   help='Periods of the coupling runs, the first left out (default '
                   f'{defaults.periods}).')
    p.add_argument('--bags', metavar='DIR',
                   help='Record each coupling run as a bag DIR/coupling_<excited axis>.')
    p.add_argument('--from-bags', nargs='+', metavar='BAG',
                   help='Fit the coupling from these bags (one axis excited by a periodic '
                   'signal in each, the others held) instead of running the experiments; the '
                   'configured axes are the model.')
    p.add_argument('--json', action='store_true', help='Print one JSON object last.')
    return p


def run_records(run: AxesRun, stage: AxesStageParams) -> list[RunRecord]:
    """
    Return a coupling run as one run record per axis, the samples as a bag records them.

    Row k holds y_k measured at t_k and u_k held over [t_k, t_k+1): y_0 is the rest before the
    first command, and a last row holds y_N with the axes back at their rest voltages. An
    open-loop run has no reference: it is recorded as not a number.

    Parameters
    ----------
    run : AxesRun
        A run of :func:`~piezo_stage_ros.core.identification.coupling.excitation_runs` (with
        its ``initial_m``).
    stage : AxesStageParams
        The stage it ran on (axis names, rest voltages).

    Returns
    -------
    list of RunRecord
        One per axis, in axis order, each with ``meta['axis']``.

    """
    if run.initial_m is None:
        raise ParameterError('initial_m', None, 'the measured rest positions y_0 of the run')
    n = len(run.time_s)
    time_s = np.arange(n + 1, dtype=np.float64) * stage.sample_time_s
    positions = np.vstack([run.initial_m, run.positions_m])
    commands = np.vstack([run.commands_v, rest_voltages(stage)])
    none = np.full(n + 1, np.nan)
    return [RunRecord(time_s=time_s, position_m=positions[:, k].copy(), reference_m=none,
                      reference_velocity_mps=none, command_v=commands[:, k].copy(),
                      meta={'axis': name, 'experiment': 'coupling, open loop',
                            'excited_axis': stage.names[run.source]})
            for k, name in enumerate(stage.names)]


def records_run(records: Sequence[RunRecord], stage: AxesStageParams) -> AxesRun:
    """
    Return the arrays of a coupling run from its records (the inverse of :func:`run_records`).

    Parameters
    ----------
    records : sequence of RunRecord
        One per axis of ``stage``, in its axis order (as a bag is read back).
    stage : AxesStageParams
        The configured stage.

    Returns
    -------
    AxesRun
        Positions row k measured at the end of command row k's sample; the excited axis is
        the one whose command varies (``source`` -1 until the fit finds it).

    """
    names = [str(rec.meta.get('axis', '')) for rec in records]
    if names != list(stage.names):
        raise ParameterError('axes', names, f'the configured axes {list(stage.names)} in '
                             'that order')
    time_s = np.asarray(records[0].time_s, dtype=np.float64)
    positions = np.column_stack([rec.position_m for rec in records])
    commands = np.column_stack([rec.command_v for rec in records])
    return AxesRun(time_s=time_s[:-1] - time_s[0], commands_v=commands[:-1],
                   positions_m=positions[1:], source=-1, initial_m=positions[0])


def coupling_file_text(stage: AxesStageParams, coupling: CouplingParams,
                       overrides: dict[str, dict[str, Any]], *, header: Sequence[str] = ()
                       ) -> str:
    """
    Return the parameter file of an identification, read on top of the configuration.

    Parameters
    ----------
    stage : AxesStageParams
        The configured stage (its axis names).
    coupling : CouplingParams
        The identified coupling.
    overrides : dict of str to dict
        Per axis name, the identified values as flat names (without ``axes.<name>.``).
    header : sequence of str
        Comment lines put at the top.

    Returns
    -------
    str
        YAML text with a ``plant_node`` section.

    """
    flat: dict[str, Any] = {'axes.names': list(stage.names)}
    for name in stage.names:
        for key, value in overrides.get(name, {}).items():
            flat[f'axes.{name}.{key}'] = value
    for key in ('gain', 'resonance_hz', 'damping'):
        flat[f'axes.coupling.{key}'] = [float(v) for v in getattr(coupling, key)]
    doc = {'plant_node': {'ros__parameters': nest(flat)}}
    lines = [f'# {line}' for line in header]
    return '\n'.join(lines + [yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)])


def _path_line(stage: AxesStageParams, fit: PathFit, true: AxesStageParams,
               label: str = 'true') -> str:
    # label: 'true' for a simulated stage, 'configured' where the truth is not known (bags)
    gain, res, damp, _ = true.matrices()
    i, j = fit.source, fit.target
    lo, hi = fit.bounds['gain']
    text = (f'{stage.names[i]} -> {stage.names[j]}: gain {fit.gain:.6g} [{lo:.6g}, {hi:.6g}] '
            f'({label} {gain[i, j]:.6g}')
    if gain[i, j] != 0.0:
        word = 'error' if label == 'true' else 'differs by'
        text += f', {word} {(fit.gain / gain[i, j] - 1.0) * 100.0:+.3f} %'
    text += ')'
    if fit.static:
        text += ', static' + ('' if fit.shown else ' (not shown: written as zero)')
    else:
        for key, name, value in (('resonance_hz', 'resonance', res[i, j]),
                                 ('damping', 'damping', damp[i, j])):
            lo, hi = fit.bounds[key]
            text += (f', {name} {getattr(fit, key):.6g} [{lo:.6g}, {hi:.6g}] '
                     f'({label} {value:.6g})')
    return text + f'; {fit.lines} lines, {fit.periods} periods, chi2/dof {fit.chi2_per_dof:.3g}'


def _run(args: argparse.Namespace) -> int:
    from piezo_stage_ros.analysis.identification_report import comparison_rows, format_table
    from piezo_stage_ros.core.identification.per_axis import axis_overrides, identify_axis
    from piezo_stage_ros.core.model.axes import sample_axes_family
    from piezo_stage_ros.identify import _bound_lines, _summary_lines
    config = cli.read_config(args.config, args.param)
    loop = axes_loop_config(config)
    configured = loop.stage
    true = configured
    if args.member is not None:
        text, true = sample_axes_family(configured, 1, args.member)[0]
        print(f'true stage: family member of seed {args.member}: {text}')
    if args.sensor_noise is not None:
        true = dataclasses.replace(true, axes=tuple(
            p.replace(chain=p.chain.replace(sensor_noise_std_m=args.sensor_noise))
            for p in true.axes))
    model = configured
    overrides: dict[str, dict[str, Any]] = {}
    report: dict[str, Any] = {'axes': {}, 'coupling': []}
    if not (args.coupling_only or args.from_bags):
        axes = list(configured.axes)
        for k, name in enumerate(configured.names):
            checked = identify_axis(true, k, configured.axes[k])
            result = checked.result
            print(f'axis {name}:')
            for line in _summary_lines(result) + _bound_lines(result):
                print(f'  {line}')
            print('  ' + format_table(comparison_rows(result, true.axes[k])).replace(
                '\n', '\n  '))
            axes[k] = result.stage.replace(sample_rate_hz=configured.axes[k].sample_rate_hz,
                                           seed=configured.axes[k].seed)
            overrides[name] = axis_overrides(axes[k], configured.axes[k])
            report['axes'][name] = {key: [lo, hi] for key, (lo, hi) in result.bounds.items()}
        model = dataclasses.replace(configured, axes=tuple(axes))
    plan = CouplingPlan(rms_v=args.rms, period_s=args.period, periods=args.periods)
    fits: list[PathFit] = []
    label, shown = 'true', true
    if args.from_bags:
        from piezo_stage_ros.analysis.bagread import read_axes
        # recorded elsewhere (a real stage): the truth is not known, the configuration is shown
        label, shown = 'configured', configured
        runs = [records_run(read_axes(bag), configured) for bag in args.from_bags]
    else:
        runs = excitation_runs(true, plan)
    if args.bags:
        from piezo_stage_ros.analysis.bagwrite import write_axes
        for run in runs:
            path = Path(args.bags) / f'coupling_{configured.names[run.source]}'
            write_axes(run_records(run, true), path,
                       meta={'command': 'identify_axes', 'experiment': 'coupling, open loop'})
            print(f'bag: {path}')
    print('coupling (95 % bounds):')
    for run in runs:
        for fit in fit_coupling(run.time_s, run.commands_v, run.positions_m, model):
            fits.append(fit)
            print(f'  {_path_line(configured, fit, shown, label)}')
            report['coupling'].append({
                'source': configured.names[fit.source], 'target': configured.names[fit.target],
                'gain': fit.gain, 'resonance_hz': fit.resonance_hz, 'damping': fit.damping,
                'bounds': {k: list(v) for k, v in fit.bounds.items()}, 'static': fit.static,
                'shown': fit.shown})
    coupling = identified_coupling(configured, fits)
    header = ['Identified by: identify_axes ' + ' '.join(
        sys.argv[1:] if args.argv is None else args.argv),
        'Read on top of the configuration: simulate --config <configuration> --config <this>.']
    Path(args.output).write_text(coupling_file_text(configured, coupling, overrides,
                                                    header=header), encoding='utf-8')
    print(f'parameter file: {args.output}')
    if args.json:
        report['output'] = args.output
        print(json.dumps(report, default=float))
    return 0


main = cli.command_main(PROG, build_parser, _run,
                        '0 success, 1 bad parameters or failed identification, 2 bad usage',
                        keep_argv=True)


if __name__ == '__main__':
    sys.exit(main())
