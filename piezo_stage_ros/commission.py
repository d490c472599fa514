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
``commission``: commission a simulated stage without leaving closed loop.

Holds the stage at a safe position under a conservative PI, adds a small periodic multisine to
its reference (at most 1 um from the hold, at most 10 s), identifies the stage in closed loop
with 95 % bounds, designs the notch and gains on the identified model, checks them with the
frozen-parameter stability check over the bounds, runs a 100 Hz verification sine, and writes

- a ROS 2 parameter file (``--output``, default ``commissioned.yaml``): the identified stage in
  ``plant_node`` (as ``identify`` writes it) and the commissioned controller in
  ``controller_node``; ``simulate --config`` and the nodes read it;
- a report (``--report DIR``, default ``commission_report``): ``report.json`` and the figures.

The stage is a member of the ``robustness`` family (``--stage``, default
``gain_hi_zeta_lo_noise``: the worst-margin corner with 3 nm of sensor noise), unlike the
configured model. The steps are in
:mod:`piezo_stage_ros.core.identification.commission`. Examples::

    commission
    commission --stage random_0002 --output stage.yaml --report rep
    commission --survey                   # several members, a Markdown table, no files
    commission --write-excitation DIR     # the excitation for the ROS nodes (a table and
                                          # their parameters); record it, then
    commission --bag BAG                  # commission from the recorded run

A multi-axis parameter file (``plant_node axes.names``, e.g. ``config/xy_stage.yaml``) is
commissioned axis by axis on its configured stage, each axis in closed loop while the others
hold their rest voltages
(:func:`~piezo_stage_ros.core.identification.per_axis.commission_axis`), and with the coupling
compensation the controller will apply to the held axes where it is configured
(``axes.coupling_compensation`` and a model-inverse feed-forward); each axis is printed as
a one-axis run is, and the parameter file holds, per axis, the identified values and the
commissioned controller values that differ from the configuration (``axes.<name>.*`` in
``plant_node`` and ``controller_node``, the layout ``identify_axes`` writes), read on top of
it. The coupling comes from ``identify_axes``: commission into the file it wrote, whose
coupling and other axes are kept::

    identify_axes --config config/xy_stage.yaml --coupling-only --output xy.yaml
    commission --config config/xy_stage.yaml --output xy.yaml          # every axis
    commission --config config/xy_stage.yaml --axis y --output xy.yaml  # y again
    simulate --config config/xy_stage.yaml --config xy.yaml

Exit status: 0 when the controller is certified and the verification is within its limit
(every axis of a multi-axis file); 1 when the excitation cannot support the model, no tuning
is certified, or the verification fails (one line on stderr, no parameter file); 2 on bad
usage.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import replace
import math
from pathlib import Path
import sys
from typing import Any, Mapping, Sequence

from piezo_stage_ros import cli
from piezo_stage_ros.core.config.axes import axes_loop_config, AxesLoopConfig, has_axes
from piezo_stage_ros.core.config.loader import Config, load_config, LoopConfig, nest
from piezo_stage_ros.core.contracts.errors import ConfigError
from piezo_stage_ros.core.control.controllers import ControllerParams
from piezo_stage_ros.core.identification.commission import (
    commission,
    commission_record,
    CommissionParams,
    CommissionRefusedError,
    CommissionResult,
    comparison,
    excitation_table,
    ros_overrides,
)
from piezo_stage_ros.core.identification.per_axis import axis_overrides, commission_axis
from piezo_stage_ros.core.model.family import (
    default_family,
    member_params,
    sample_family,
    StageVariation,
)
from piezo_stage_ros.core.model.stage import StageParams
from piezo_stage_ros.identify import controller_values, parameter_file_text
import yaml

__all__ = ['axes_parameter_text', 'build_parser', 'main', 'member', 'parameter_text',
           'result_lines', 'write_excitation']

PROG = 'commission'
DEFAULT_STAGE = 'gain_hi_zeta_lo_noise'
#: Sensor noise given to a member that has none [m rms].
DEFAULT_NOISE_M = 2e-9
#: The members of ``--survey``.
SURVEY = ('nominal', 'gain_lo', 'gain_hi', 'omega_n_lo', 'omega_n_hi', 'zeta_lo', 'zeta_hi',
          'tau_lo', 'tau_hi', 'alpha_lo', 'alpha_hi', 'gain_hi_zeta_lo_noise',
          'gain_hi_wn_lo_zeta_lo', 'gain_lo_tau_hi', 'random_0000', 'random_0001',
          'random_0002', 'random_0003')


def member(name: str, *, seed: int = 0, noise_m: float | None = None) -> StageVariation:
    """
    Return a member of the stage family by name.

    Parameters
    ----------
    name : str
        A name of :func:`default_family`, or ``random_N`` (the N-th of
        :func:`sample_family` with ``seed``).
    seed : int
        Seed of the random members.
    noise_m : float, optional
        Sensor noise [m rms]; default the member's own, or :data:`DEFAULT_NOISE_M` when it has
        none.

    Returns
    -------
    StageVariation

    Raises
    ------
    cli.UsageError
        For an unknown name.

    """
    known = {m.name: m for m in default_family()}
    if name in known:
        found = known[name]
    elif name.startswith('random_') and name[7:].isdigit():
        index = int(name[7:])
        found = sample_family(index + 1, seed)[index]
    else:
        raise cli.UsageError(f'unknown stage {name!r}: one of {", ".join(known)} or random_N')
    if noise_m is not None:
        return replace(found, noise_m=noise_m)
    return found if found.noise_m > 0.0 else replace(found, noise_m=DEFAULT_NOISE_M)


def build_parser() -> argparse.ArgumentParser:
    """Return the command-line parser of ``commission``."""
    p = cli.Parser(prog=PROG, description='Commission a simulated stage in closed loop: hold, '
                   'excite, identify, design, certify, verify; write a parameter file and a '
                   'report.')
    p.add_argument('--stage', action='append', default=[], metavar='NAME',
                   help=f'Family member to commission (default {DEFAULT_STAGE}); a name of '
                   'robustness --list-family or random_N; repeatable with --survey.')
    p.add_argument('--seed', type=int, default=0, help='Seed of the random_N members.')
    p.add_argument('--noise', type=float, metavar='M', help='Sensor noise of the stage [m rms] '
                   f"(default: the member's own, {DEFAULT_NOISE_M:g} when it has none; a "
                   'multi-axis file: every axis, default as configured).')
    cli.add_config_options(p)
    p.add_argument('--output', default='commissioned.yaml', metavar='FILE',
                   help='Parameter file to write (default: commissioned.yaml).')
    p.add_argument('--report', default='commission_report', metavar='DIR',
                   help='Directory for report.json and the figures (DIR/<axis>/ for each '
                   "axis of a multi-axis file); 'none' to skip.")
    d = CommissionParams()
    p.add_argument('--hold', type=float, default=d.hold_m, metavar='M',
                   help=f'Hold position [m] (default {d.hold_m:g}).')
    p.add_argument('--duration', type=float, default=d.duration_s, metavar='S',
                   help=f'Excitation length [s], at most 10 (default {d.duration_s:g}).')
    p.add_argument('--multisine-rms', type=float, default=d.multisine_rms_m, metavar='M',
                   help=f'Rms of the multisine [m] (default {d.multisine_rms_m:g}).')
    p.add_argument('--slow-amplitude', type=float, default=d.slow_amplitude_m, metavar='M',
                   help=f'Amplitude of the slow sine [m] (default {d.slow_amplitude_m:g}).')
    p.add_argument('--band', nargs=2, type=float, default=(d.band_low_hz, d.band_high_hz),
                   metavar=('LOW_HZ', 'HIGH_HZ'), help='Band of the multisine (default '
                   f'{d.band_low_hz:g} {d.band_high_hz:g}).')
    p.add_argument('--verify-duration', type=float, default=d.verify_duration_s, metavar='S',
                   help=f'Length of the verification run [s] (default {d.verify_duration_s:g}).')
    p.add_argument('--bag', metavar='BAG',
                   help='Commission from a recorded hold-and-excitation run instead of '
                   'simulating one (launch/commission.launch.py records it); the verification '
                   'then runs on the identified model.')
    p.add_argument('--write-excitation', metavar='DIR',
                   help='Write the excitation table (excitation.csv) and the node parameters '
                   'that run it (overrides.yaml) into DIR for the ROS nodes, and exit.')
    p.add_argument('--coverage', type=int, metavar='N',
                   help='Measure how often the 95 %% bounds of the identification hold the '
                   'truth: N cases of random family members under loops the package did not '
                   'write (integral + feed-forward, PI + feed-forward, lead-lag), 0.5 to 3 nm '
                   'of noise, some with a sensor offset or a sample of delay; prints a line '
                   'per case and a Markdown table; writes no file.')
    p.add_argument('--open-loop', action='store_true',
                   help="With --coverage: the package's open-loop runs (noise, step, sine) "
                   'instead of the foreign loops.')
    p.add_argument('--jobs', type=int, default=1, metavar='J',
                   help='Processes for --coverage (default 1).')
    p.add_argument('--axis', metavar='NAME',
                   help='A multi-axis file (plant_node axes.names, e.g. config/xy_stage.yaml) '
                   'commissions every axis in turn, each in closed loop while the others hold; '
                   '--axis NAME that axis only. The output then holds axes.<name>.* values, '
                   'read on top of the configuration; an existing --output of the same axes '
                   'is updated, keeping its other axes and the coupling identify_axes wrote '
                   'there.')
    p.add_argument('--survey', action='store_true',
                   help='Commission every --stage (default: a list of members) and print a '
                   'Markdown table of recovered vs true, certification and verification; '
                   'writes no file.')
    return p


def _params(args: argparse.Namespace) -> CommissionParams:
    return CommissionParams(hold_m=args.hold, duration_s=args.duration,
                            multisine_rms_m=args.multisine_rms,
                            slow_amplitude_m=args.slow_amplitude, band_low_hz=args.band[0],
                            band_high_hz=args.band[1], verify_duration_s=args.verify_duration)


def parameter_text(result: CommissionResult, loop: LoopConfig, header: Sequence[str]) -> str:
    """
    Return the parameter file of a commissioning run.

    Parameters
    ----------
    result : CommissionResult
        The run.
    loop : LoopConfig
        The configuration it started from.
    header : sequence of str
        Comment lines.

    Returns
    -------
    str
        YAML: ``plant_node`` as ``identify`` writes it; ``controller_node`` every value of the
        commissioned controller and the slope range it was certified over.

    """
    text = parameter_file_text(result.identified, header=header,
                               reference=loop.controller.to_flat(), reference_stage=loop.stage)
    doc = yaml.safe_load(text)
    lo, hi = result.design.certification.slope_range
    flat: dict[str, Any] = dict(result.design.controller.to_flat())
    # the check the node runs at start-up then holds the delay this one was certified at
    flat.update({'stability.slope_min': lo, 'stability.slope_max': hi,
                 'stability.delay_samples': result.design.certification.nominal.delay_samples})
    doc['controller_node'] = {'ros__parameters': nest(flat)}
    lines = [f'# {line}' for line in header]
    return '\n'.join(lines + [yaml.safe_dump(doc, sort_keys=False, default_flow_style=False)])


def result_lines(result: CommissionResult, true: StageParams | None,
                 params: CommissionParams) -> list[str]:
    """
    Return the lines the command prints about a run, from the excitation to the notes.

    Parameters
    ----------
    result : CommissionResult
        The run.
    true : StageParams or None
        The simulated stage (its values are compared with the identified ones); None for a
        recorded run.
    params : CommissionParams
        The settings of the run (the verification's limit).

    Returns
    -------
    list of str

    """
    s = result.checked.result.summary()
    cert = result.design.certification
    ver = result.verification
    length = result.excited.time_s.size * result.identified.sample_time_s
    out = [f'excitation: {length:g} s, reference within '
           f'{result.excitation_peak_m * 1e6:.3f} um of the hold, position within '
           f'{result.position_peak_m * 1e6:.3f} um; loop closed throughout',
           f'identified: static gain {s["static_gain_m_per_v"]:.6g} m/V, w_n '
           f'{s["omega_n_rad_s"]:.6g} rad/s, zeta {s["zeta"]:.5g}, tau {s["tau_s"]:.6g} s, '
           f'alpha {s["alpha"]:.5g}, B1 {s["b1"]:.5g}']
    for key, (value, inside) in (comparison(result, true).items() if true else ()):
        out.append(f'  {key}: {100 * value:+.2f} % from the truth, '
                   f'{"inside" if inside else "OUTSIDE"} its 95 % bounds')
    out.append(f'design: {result.design.label}, notch '
               f'{result.design.controller.notch.frequency_hz:.1f} Hz (zero damping '
               f'{result.design.controller.notch.zero_damping:.4g})')
    out.append(f'stability check (parameters frozen, {cert.nominal.delay_samples:g} samples of '
               'computational delay): '
               f'{"stable over the box" if cert.certified else "NOT stable over the box"} on '
               f'{cert.corners} plants (identified model and the corners of its 95 % bounds), '
               f'slopes {cert.slope_range[0]:.4g} ... {cert.slope_range[1]:.4g}; smallest gain '
               f'margin {cert.gain_margin_db:.1f} dB, phase margin '
               f'{cert.phase_margin_deg:.0f} deg')
    where = 'on the stage' if ver.on_stage else 'on the identified model'
    out.append(f'verification {where}: {ver.frequency_hz:g} Hz sine, e_rms '
               f'{ver.e_rms_m * 1e9:.2f} nm (limit {params.verify_max_m * 1e9:g} nm; the '
               f'identified model predicted {ver.predicted_e_rms_m * 1e9:.2f} nm), e_max '
               f'{ver.e_max_m * 1e9:.1f} nm')
    out += [f'note: {note}' for note in result.notes]
    return out


def _run_one(args: argparse.Namespace, loop: LoopConfig, name: str,
             progress: cli.Progress) -> tuple[CommissionResult, StageParams | None]:
    def derive(stage: StageParams) -> dict[str, Any]:
        return controller_values(stage, loop.controller.to_flat(), loop.stage)

    if args.bag is not None:
        from piezo_stage_ros.analysis.bagread import read_run
        if not Path(args.bag).exists():
            raise ConfigError(f'bag {args.bag!r} does not exist')
        record = read_run(args.bag)
        return commission_record(record, loop.stage, loop.controller, derive, _params(args),
                                 stability=loop.stability, progress=progress.line), None
    true = member_params(loop.stage, member(name, seed=args.seed, noise_m=args.noise))
    result = commission(true, loop.stage, loop.controller, derive, _params(args),
                        stability=loop.stability, progress=progress.line)
    return result, true


def write_excitation(params: CommissionParams, sample_rate_hz: float, folder: str | Path
                     ) -> tuple[Path, Path, float]:
    """
    Write the excitation table and the node parameters that run it.

    Parameters
    ----------
    params : CommissionParams
        Hold, excitation, hold controller.
    sample_rate_hz : float
        Loop rate of the nodes [Hz].
    folder : str or Path
        Directory (created).

    Returns
    -------
    table, overrides : Path
        ``excitation.csv`` (columns time_s, position_m) and ``overrides.yaml`` (a parameter
        file for ``closed_loop.launch.py overrides:=`` or ``simulate --config``).
    length_s : float
        Hold plus excitation [s], the run length to record.

    Raises
    ------
    ParameterError
        If the excitation leaves the allowed distance from the hold (nothing is written).

    """
    t, r = excitation_table(params, sample_rate_hz)
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    table = out / 'excitation.csv'
    rows = ''.join(f'{float(a)!r},{float(b)!r}\n' for a, b in zip(t, r))
    table.write_text('time_s,position_m\n' + rows, encoding='utf-8')
    doc = {node: {'ros__parameters': nest(values)}
           for node, values in ros_overrides(params, str(table.resolve())).items()}
    overrides = out / 'overrides.yaml'
    overrides.write_text(yaml.safe_dump(doc, sort_keys=False), encoding='utf-8')
    return table, overrides, float(t[-1])


def _write_excitation(args: argparse.Namespace, loop: LoopConfig) -> int:
    table, overrides, length = write_excitation(_params(args), loop.stage.sample_rate_hz,
                                                args.write_excitation)
    print(f'excitation table: {table} ({length:g} s)')
    print(f'node parameters: {overrides}')
    print(f'run: ros2 launch piezo_stage_ros closed_loop.launch.py overrides:={overrides} '
          f'record:=true bag:=commission_bag duration_s:={length:g}')
    print('then: commission --bag commission_bag')
    return 0


def _single(args: argparse.Namespace, loop: LoopConfig) -> int:
    if len(args.stage) > 1:
        raise cli.UsageError('one --stage at a time (or --survey)')
    if args.bag is not None and args.stage:
        raise cli.UsageError('--bag commissions the recorded stage: no --stage')
    name = args.stage[0] if args.stage else DEFAULT_STAGE
    progress = cli.Progress(PROG)
    result, true = _run_one(args, loop, name, progress)
    cert = result.design.certification
    ver = result.verification
    report = args.report.lower() != 'none'
    if report:
        from piezo_stage_ros.analysis.commission_report import write_commission_report
        progress.line('write the report')
        files = write_commission_report(result, args.report, true_stage=true,
                                        extra={'stage': name, 'parameter file': args.output
                                               if result.accepted else None})
    if true is None:
        print(f'recorded run: {args.bag}')
    else:
        print(f'stage: {name} ({member(name, seed=args.seed, noise_m=args.noise).describe()})')
    for line in result_lines(result, true, _params(args)):
        print(line)
    if report:
        print(f'report: {files[-1]}')
    if not result.accepted:
        cli.error(PROG, '; '.join(result.refused or ['not accepted'])
                  + ': no parameter file written')
        return 1
    header = ['Commissioned by: commission ' + ' '.join(sys.argv[1:] if args.argv is None
                                                        else args.argv),
              f'Certified on {cert.corners} plants (the identified model and the corners of '
              'its 95 % bounds); verification '
              f'{ver.frequency_hz:g} Hz e_rms {ver.e_rms_m * 1e9:.2f} nm.',
              'Review the report before using these values on a stage.']
    Path(args.output).write_text(parameter_text(result, loop, header), encoding='utf-8')
    print(f'parameter file: {args.output}')
    return 0


def _survey(args: argparse.Namespace, loop: LoopConfig) -> int:
    names = args.stage or list(SURVEY)
    progress = cli.Progress(PROG)
    heads = ['stage', 'DC gain', 'w_n', 'tau', 'zeta', 'alpha', 'in bounds', 'tuning',
             'GM / PM', 'ref / pos peak [um]', '100 Hz e_rms [nm] (predicted)']
    print('| ' + ' | '.join(heads) + ' |')
    print('|' + ' --- |' * len(heads))
    for name in names:
        progress.line(f'{name}: start')
        try:
            result, true = _run_one(args, loop, name, progress)
        except CommissionRefusedError as exc:
            print(f'| {name} | refused: {exc} |' + ' |' * (len(heads) - 2), flush=True)
            continue
        assert true is not None
        cmp = comparison(result, true)
        cells = [f'{100 * cmp[k][0]:+.2f} %' for k in ('static_gain_m_per_v', 'omega_n_rad_s',
                                                        'tau_s', 'zeta', 'alpha')]
        inside = sum(v[1] for v in cmp.values())
        outside = [k for k, v in cmp.items() if not v[1]]
        cert = result.design.certification
        ver = result.verification
        cells += [f'{inside}/{len(cmp)}' + (f' ({", ".join(outside)} outside)' if outside
                                             else ''),
                  f'{result.design.label}' + ('' if cert.certified else ' NOT certified'),
                  f'{cert.gain_margin_db:.1f} dB / {cert.phase_margin_deg:.0f} deg',
                  f'{result.excitation_peak_m * 1e6:.2f} / {result.position_peak_m * 1e6:.2f}',
                  f'{ver.e_rms_m * 1e9:.1f} ({ver.predicted_e_rms_m * 1e9:.1f})']
        print('| ' + ' | '.join([name] + cells) + ' |', flush=True)
    print(f'\n(survey took {progress.elapsed():.0f} s; {math.ceil(args.duration):g} s '
          'excitation each)')
    return 0


def _coverage(args: argparse.Namespace, loop: LoopConfig) -> int:
    from concurrent.futures import ProcessPoolExecutor

    from piezo_stage_ros.core.identification.coverage import (
        COMPARED,
        coverage_cases,
        run_case,
        summarize,
    )
    cases = coverage_cases(args.coverage, args.seed, loop.stage, open_loop=args.open_loop)
    progress = cli.Progress(PROG)
    results: list[dict[str, Any]] = []
    units = {'sensor_offset_m': 'nm'}

    def report(res: dict[str, Any]) -> None:
        results.append(res)
        if not res['accepted']:
            what = 'refused: ' + '; '.join(res['refused'])
        else:
            outside = [k for k, v in res['parameters'].items() if not v['inside']]
            what = (f'{res["loop"]} loop, delay {res["delay"]:.3g} (true '
                    f'{res["true_delay"]:g}); ' + ('all inside' if not outside else
                                                    'OUTSIDE: ' + ', '.join(outside)))
        progress.line(f'{len(results)}/{len(cases)} case {res["index"]} '
                      f'({res["label"]}): {what}')

    if args.jobs == 1:
        for case in cases:
            report(run_case(case, loop.stage))
    else:
        with ProcessPoolExecutor(max_workers=args.jobs) as pool:
            for res in pool.map(run_case, cases, [loop.stage] * len(cases)):
                report(res)
    table = summarize(results)
    accepted = sum(1 for r in results if r['accepted'])
    print(f'| quantity | runs | truth inside the 95 % bounds | median half-width | '
          f'median error | largest error |  ({accepted}/{len(results)} accepted)')
    print('| --- | --- | --- | --- | --- | --- |')
    for name in COMPARED:
        if name not in table:
            continue
        row = table[name]
        if units.get(name) == 'nm':
            cells = [f'{row["median_half_width"] * 1e9:.3g} nm',
                     f'{row["median_abs_error"] * 1e9:.3g} nm',
                     f'{row["max_abs_error"] * 1e9:.3g} nm']
        else:
            cells = [f'{100 * row[k]:.3g} %' for k in ('median_half_width',
                                                       'median_abs_error', 'max_abs_error')]
        print(f'| {name} | {row["runs"]:.0f} | {100 * row["inside"]:.1f} % | '
              + ' | '.join(cells) + ' |')
    delays = [r for r in results if r['accepted']]
    found = sum(1 for r in delays if abs(r['delay'] - r['true_delay']) < 0.5)
    print(f'\nloop delay found (within half a sample) in {found} of {len(delays)} accepted '
          f'runs; study took {progress.elapsed():.0f} s with {args.jobs} process(es)')
    return 0


def _commission(args: argparse.Namespace) -> int:
    config = cli.read_config(args.config, args.param)
    if has_axes(config):
        return _axes(args, config)
    if args.axis is not None:
        raise cli.UsageError(f'--axis {args.axis!r}: the configuration is a one-axis stage (no '
                             'plant_node axes.names); --axis needs a multi-axis file such as '
                             'config/xy_stage.yaml')
    loop = cli.offline_loop(PROG, config)
    if args.write_excitation is not None:
        return _write_excitation(args, loop)
    if args.coverage is not None:
        if args.coverage < 1 or args.jobs < 1:
            raise cli.UsageError('--coverage and --jobs need a positive count')
        return _coverage(args, loop)
    if args.survey:
        if args.bag is not None:
            raise cli.UsageError('--survey simulates the family: no --bag')
        return _survey(args, loop)
    return _single(args, loop)


def _kept(path: Path, names: Sequence[str]) -> dict[str, dict[str, Any]]:
    """Return the flat sections of an existing multi-axis output file of the same axes."""
    if not path.exists():
        return {}
    why = (f'--output {str(path)!r} exists and is not a parameter file of the axes '
           f'{list(names)} (as identify_axes and commission write them): give another file or '
           'remove it')
    try:
        old = load_config([path])
    except ConfigError as exc:
        raise ConfigError(f'{why} ({exc})') from exc
    nodes = ('plant_node', 'controller_node')
    if old.sections.get('plant_node', {}).get('axes.names') != list(names) or \
            set(old.sections) - set(nodes):
        raise ConfigError(why)
    return {node: dict(old.sections.get(node, {})) for node in nodes}


def axes_parameter_text(results: Mapping[str, CommissionResult], loop: AxesLoopConfig,
                        header: Sequence[str],
                        kept: Mapping[str, Mapping[str, Any]] | None = None) -> str:
    """
    Return the parameter file of a multi-axis commissioning, read on top of the configuration.

    Parameters
    ----------
    results : Mapping of str to CommissionResult
        The commissioned axes by name.
    loop : AxesLoopConfig
        The configuration they started from.
    header : sequence of str
        Comment lines.
    kept : Mapping, optional
        Flat ``plant_node`` and ``controller_node`` sections of an earlier file of the same
        axes (``identify_axes`` or ``commission``): kept, but for the commissioned axes' own
        ``axes.<name>.*`` entries, which this run replaces.

    Returns
    -------
    str
        YAML in the layout ``identify_axes`` writes: ``plant_node axes.names``, per commissioned
        axis the identified values that differ from the configured axis as
        ``axes.<name>.*`` in ``plant_node`` and the commissioned controller's values that differ
        from the configured axis controller as ``axes.<name>.*`` in ``controller_node``.

    """
    names = loop.stage.names
    flat = {node: {k: v for k, v in (kept or {}).get(node, {}).items()
                   if not any(k.startswith(f'axes.{n}.') for n in results)}
            for node in ('plant_node', 'controller_node')}
    flat['plant_node']['axes.names'] = list(names)
    for name, result in results.items():
        k = names.index(name)
        configured = loop.stage.axes[k]
        identified = result.identified.replace(sample_rate_hz=configured.sample_rate_hz,
                                               seed=configured.seed)
        for key, value in axis_overrides(identified, configured).items():
            flat['plant_node'][f'axes.{name}.{key}'] = value
        before = loop.controllers[k].to_flat()
        for key, value in result.design.controller.to_flat().items():
            if before.get(key) != value:
                flat['controller_node'][f'axes.{name}.{key}'] = value
    doc = {}
    for node, values in flat.items():
        # axes.names first, then the axes in the stage's order, then the rest (the coupling)
        order = ['axes.names'] + [f'axes.{n}.' for n in names]
        ranked = sorted(values, key=lambda key: next(
            (i for i, head in enumerate(order) if key == head or key.startswith(head)),
            len(order)))
        if ranked:
            doc[node] = {'ros__parameters': nest({key: values[key] for key in ranked})}
    lines = [f'# {line}' for line in header]
    return '\n'.join(lines + [yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)])


def _axes(args: argparse.Namespace, config: Config) -> int:
    one_axis = {'--bag': args.bag is not None, '--survey': args.survey,
                '--coverage': args.coverage is not None,
                '--write-excitation': args.write_excitation is not None,
                '--stage': bool(args.stage)}
    for option, given in one_axis.items():
        if given:
            raise cli.UsageError(f'{option} is for a one-axis stage: a multi-axis file '
                                 'commissions its configured axes (--axis NAME for one)')
    loop = axes_loop_config(config)
    for text in loop.base.offline_notes():
        cli.note(PROG, text)
    names = loop.stage.names
    if args.axis is not None and args.axis not in names:
        raise cli.UsageError(f'--axis {args.axis!r} is not an axis of this stage; allowed: '
                             f'{", ".join(names)}')
    chosen = [args.axis] if args.axis is not None else list(names)
    output = Path(args.output)
    kept = _kept(output, names)
    true = loop.stage
    if args.noise is not None:
        true = dataclasses.replace(true, axes=tuple(
            p.replace(chain=p.chain.replace(sensor_noise_std_m=args.noise)) for p in true.axes))
    params = _params(args)
    progress = cli.Progress(PROG)
    report = args.report.lower() != 'none'
    print(f'stage: the configured axes {", ".join(names)} and their coupling'
          + ('' if args.noise is None else f', sensor noise {args.noise:g} m rms')
          + f'; commissioning {", ".join(chosen)}, the other axes holding')
    results: dict[str, CommissionResult] = {}
    refused: list[str] = []
    for count, name in enumerate(chosen, 1):
        k = names.index(name)
        progress.line(f'axis {name} ({count}/{len(chosen)}): start')
        configured, controller = loop.stage.axes[k], loop.controllers[k]

        def derive(stage: StageParams, controller: ControllerParams = controller,
                   configured: StageParams = configured) -> dict[str, Any]:
            return controller_values(stage, controller.to_flat(), configured)

        def say(text: str, name: str = name) -> None:
            progress.line(f'axis {name}: {text}')

        try:
            # the axis runs as the multi-axis controller will run it: that controller
            # compensates the coupling where its feed-forward has the model inverse
            result = commission_axis(true, k, configured, controller, derive, params,
                                     stability=loop.base.stability, progress=say,
                                     design=loop.stage, compensate=(
                                         loop.compensate and controller.feedforward.inverse))
        except CommissionRefusedError as exc:
            raise CommissionRefusedError(f'axis {name}: {exc}') from exc
        results[name] = result
        print(f'axis {name}:')
        for line in result_lines(result, true.axes[k], params):
            print(f'  {line}')
        if not result.accepted:
            refused.append(f'axis {name}: ' + '; '.join(result.refused or ['not accepted']))
    if report:
        from piezo_stage_ros.analysis.commission_report import write_commission_report
        for name, result in results.items():
            progress.line(f'axis {name}: write the report')
            files = write_commission_report(
                result, Path(args.report) / name, true_stage=true.axes[names.index(name)],
                extra={'axis': name, 'parameter file': None if refused else args.output})
            print(f'report of axis {name}: {files[-1]}')
    if refused:
        cli.error(PROG, '; '.join(refused) + ': no parameter file written')
        return 1
    header = ['Commissioned by: commission ' + ' '.join(sys.argv[1:] if args.argv is None
                                                        else args.argv),
              'Read on top of the configuration: simulate --config <configuration> '
              '--config <this>.']
    for name, result in results.items():
        cert, ver = result.design.certification, result.verification
        header.append(f'axis {name}: certified on {cert.corners} plants (the identified model '
                      'and the corners of its 95 % bounds), slopes '
                      f'{cert.slope_range[0]:.6g} ... {cert.slope_range[1]:.6g}, '
                      f'{cert.nominal.delay_samples:g} samples of delay; verification '
                      f'{ver.frequency_hz:g} Hz e_rms {ver.e_rms_m * 1e9:.2f} nm.')
    if kept:
        header.append(f'Kept from the earlier {output.name}: its other entries (the coupling, '
                      'other axes).')
    header.append('Review the report before using these values on a stage.')
    output.write_text(axes_parameter_text(results, loop, header, kept), encoding='utf-8')
    print(f'parameter file: {args.output}')
    return 0


main = cli.command_main(PROG, build_parser, _commission,
                        '0 commissioned, 1 refused or failed, 2 bad usage', keep_argv=True)


if __name__ == '__main__':
    sys.exit(main())
