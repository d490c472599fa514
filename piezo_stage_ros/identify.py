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
``identify``: stage model parameters from recorded bags, section III-D of the paper.

Reads one or more bags (a small-amplitude noise or chirp run, a small step run, a sine run such
as 1 + sin(2 pi 100 t) V), decides what each is for from its command signal (or from
``--noise/--step/--sine``), runs :func:`piezo_stage_ros.core.identification.fit.identify` and
writes

- a ROS 2 parameter file (``--output``, default ``identified.yaml``) with a ``plant_node``
  section (every stage parameter, dotted names as :meth:`StageParams.to_flat` gives them, the
  loop rate excepted) and the model-dependent ``controller_node`` values; ``simulate --config``,
  the plant node and the controller node read it directly;
- a report with the figures (``--report DIR``, default ``identification_report``).

The signal chain of the recordings (DAC, amplifier range) and everything that is not identified
come from ``config/default.yaml`` and ``--config FILE``. Examples::

    identify noise_bag step_bag sine_bag
    identify --sine sine_bag --noise noise_bag --step step_bag --output stage.yaml
    identify --simulate /tmp/idbags --perturb 3     # simulated bags of a perturbed stage,
                                                    # identified, with a recovered-vs-true table
    identify cl_excite cl_sine --json               # last line: one JSON object, every
                                                    # parameter with its 95 % bounds

Exit status: 0 on success, 1 on bad data or parameters (missing bag, no excitation, failed fit),
2 on bad command-line usage; the error is one line on stderr.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import sys
from typing import Any, Mapping, Sequence, TYPE_CHECKING

from piezo_stage_ros import cli
from piezo_stage_ros.core.config.loader import nest
from piezo_stage_ros.core.contracts.errors import ConfigError, PiezoStageError
from piezo_stage_ros.core.identification.fit import (
    IdentificationParams,
    IdentificationResult,
    pscm_gain,
)
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.model.linear import factors_of
from piezo_stage_ros.core.model.stage import StageParams
import yaml

if TYPE_CHECKING:
    from piezo_stage_ros.core.identification.support import CheckedIdentification

__all__ = ['JSON_KEYS', 'build_parser', 'controller_values', 'json_summary', 'main',
           'parameter_file_text']

PROG = 'identify'

def build_parser() -> argparse.ArgumentParser:
    """Return the command-line parser of ``identify``."""
    p = cli.Parser(prog=PROG, description='Identify the stage model (linear plant and hysteresis) '
                'from recorded bags, as in section III-D of the paper, and write a parameter '
                'file and a report.')
    p.add_argument('bags', nargs='*', metavar='BAG',
                   help='Bags to use; each is classified by its command (step: few jumps; sine: '
                   'one frequency; otherwise frequency response).')
    p.add_argument('--noise', action='append', default=[], metavar='BAG',
                   help='Bag of a noise or chirp run (frequency response).')
    p.add_argument('--step', action='append', default=[], metavar='BAG',
                   help='Bag of a step run (transient response).')
    p.add_argument('--sine', action='append', default=[], metavar='BAG',
                   help='Bag of a sine run (hysteresis).')
    p.add_argument('--closed-loop', action='store_true',
                   help='The frequency runs were recorded in closed loop (detected otherwise; '
                   'the verdict is reported, the estimate does not need it): the response is '
                   'averaged over whole periods of the periodic reference whenever it repeats; '
                   'a run that the verdict finds open and whose excitation does not repeat is '
                   'refused.')
    p.add_argument('--drift', action='append', default=[], metavar='BAG',
                   help='Operation bag (ordinary tracking, no added excitation): report the DC '
                   'gain and the lag at the reference frequency against the configured model '
                   '(--config); writes no parameter file.')
    p.add_argument('--drift-threshold', type=float, default=0.05, metavar='FRACTION',
                   help='Relative DC-gain change reported as a change (default 0.05).')
    p.add_argument('--config', action='append', default=[], metavar='FILE',
                   help='Parameter file on top of config/default.yaml: the signal chain of the '
                   'recordings and the values that are not identified.')
    p.add_argument('--output', default='identified.yaml', metavar='FILE',
                   help='Parameter file to write (default: identified.yaml).')
    p.add_argument('--report', default='identification_report', metavar='DIR',
                   help="Directory for the figures and report.md; 'none' to skip.")
    p.add_argument('--model', choices=cli.choices(IdentificationParams, 'hysteresis_model'),
                   default='backlash_like', help='Hysteresis model to fit on the sine run.')
    p.add_argument('--hysteresis-slope', type=float, metavar='C',
                   help='Convention splitting the static gain k_p c: the hysteresis slope (c, '
                   "d_p or p0 + sum p_i); default the configuration's value of the model.")
    p.add_argument('--pscm', nargs=2, type=float, metavar=('X0_M', 'X10_M'),
                   help='Positions [m] where the sensor reads 0 V and 10 V: K_PSCM by eq. (15) '
                   'for the output file.')
    p.add_argument('--free-omega', action='store_true',
                   help='Fit w_n in the step fit too (the paper keeps it from the frequency '
                   'response).')
    p.add_argument('--json', action='store_true',
                   help='Print one JSON object on the last line: every identified parameter '
                   'as {"value", "low", "high"} (95 %%), the loop verdict and which run gave '
                   'what (or the refusals).')
    p.add_argument('--simulate', metavar='DIR',
                   help='First simulate the three identification runs of a stage (the '
                   'configured one, or --perturb) as bags in DIR, then identify them.')
    p.add_argument('--perturb', type=int, metavar='SEED',
                   help="With --simulate: the true stage is the paper's with every identified "
                   'parameter changed by up to +-30 %% (drawn from SEED).')
    p.add_argument('--sensor-noise', type=float, default=2e-9, metavar='M',
                   help='With --simulate: sensor noise [m rms] (default 2e-9).')
    p.add_argument('--sample-rate', type=float, default=20000.0, metavar='HZ',
                   help='With --simulate: rate of the identification runs (default 20000).')
    p.add_argument('--overwrite', action='store_true',
                   help='Replace existing bags in the --simulate directory.')
    return p


def _theta_phi(stage: StageParams) -> tuple[float, float] | None:
    """Return theta = a/(b c) [V/V] and phi = 1/(b c) [s] of the reduced model in sensor volts."""
    if stage.hysteresis.model != 'backlash_like':
        return None
    reduced = stage.plant.third_order.reduced()
    theta = 1.0 / (stage.chain.sensor_gain_v_per_m * reduced.gain_m_per_v
                   * stage.hysteresis.backlash_like.c)
    return theta, theta * reduced.tau_s


def controller_values(stage: StageParams, reference: Mapping[str, Any] | None = None,
                      reference_stage: StageParams | None = None) -> dict[str, Any]:
    """
    Return the controller_node parameters that depend on the identified model.

    Parameters
    ----------
    stage : StageParams
        The identified stage.
    reference : Mapping, optional
        The configured controller_node parameters (flat) whose model-dependent values are
        re-derived for ``stage``; default none (only the values that need no reference).
    reference_stage : StageParams, optional
        The stage ``reference`` was tuned for (the configured plant_node).

    Returns
    -------
    dict
        Flat controller_node values:

        - ``open_loop.gain_v_per_m`` = 1/(k_p c) and ``sensor_gain_v_per_m`` = K_PSCM;
        - ``notch.frequency_hz`` and ``notch.zero_damping`` = w_n/(2 pi) and zeta (the manual
          notch sits on the identified resonance); the identified plant itself is stated once,
          in the plant_node section, and the controller's design model follows it
          (``stability.design_model: plant``);
        - for the backlash-like model: ``rac.rho_v`` = (c - B1)/alpha, ``rac.k_star_v`` raised
          to rho_v/c_min if below it (Theorem 1), ``stability.slope_min/max`` = 2 B1 - c and c;
        - with a reference: the RAC's theta and phi bounds and initial values scaled by the
          ratio of the identified theta = a/(b c) and phi = 1/(b c) to the reference stage's,
          so that they sit where the reference tuning put them relative to the model.

    """
    third = stage.plant.third_order
    h = stage.hysteresis
    factors = factors_of(third)
    out: dict[str, Any] = {
        'sensor_gain_v_per_m': stage.chain.sensor_gain_v_per_m,
        'notch.frequency_hz': factors.omega_n_rad_s / (2.0 * math.pi),
        'notch.zero_damping': min(factors.zeta, 1.0),
    }
    if h.model == 'backlash_like':
        bl = h.backlash_like
        rho = (bl.c - bl.b1) / bl.alpha
        out['open_loop.gain_v_per_m'] = 1.0 / (third.gain / third.a2 * bl.c)
        out['rac.rho_v'] = rho
        c_min = float(reference.get('rac.c_min', 1.0)) if reference else 1.0
        k_star = float(reference.get('rac.k_star_v', 0.2)) if reference else 0.2
        if k_star < rho / c_min:
            out['rac.k_star_v'] = rho / c_min
        out['stability.slope_min'] = max(2.0 * bl.b1 - bl.c, 1e-6)
        out['stability.slope_max'] = bl.c
    new = _theta_phi(stage)
    old = _theta_phi(reference_stage) if reference_stage is not None else None
    if reference and new is not None and old is not None:
        for name, ratio in (('theta', new[0] / old[0]), ('phi', new[1] / old[1])):
            for suffix in ('_min', '_max', '_init'):
                key = f'rac.{name}{suffix}'
                if key in reference:
                    out[key] = float(reference[key]) * ratio
    return out


def parameter_file_text(stage: StageParams, *, header: Sequence[str] = (),
                        reference: Mapping[str, Any] | None = None,
                        reference_stage: StageParams | None = None) -> str:
    """
    Return a ROS 2 parameter file with the identified stage and controller values.

    Parameters
    ----------
    stage : StageParams
        The identified stage; every parameter but ``sample_rate_hz`` (a property of the loop,
        not of the stage) goes into ``plant_node``.
    header : sequence of str
        Comment lines put at the top.
    reference, reference_stage : optional
        Configured controller_node values and the stage they were tuned for, see
        :func:`controller_values`.

    Returns
    -------
    str
        YAML text; :func:`piezo_stage_ros.core.config.loader.load_loop_config` reads it
        and its ``stage`` is ``stage`` (the loop rate aside).

    """
    flat = {k: v for k, v in stage.to_flat().items() if k != 'sample_rate_hz'}
    doc = {'plant_node': {'ros__parameters': nest(flat)},
           'controller_node': {'ros__parameters': nest(
               controller_values(stage, reference, reference_stage))}}
    lines = [f'# {line}' for line in header]
    return '\n'.join(lines + [yaml.safe_dump(doc, sort_keys=False, default_flow_style=False)])


def _read_bags(paths: Sequence[tuple[str, str | None]]) -> list[tuple[RunRecord, str | None]]:
    from piezo_stage_ros.analysis.bagread import read_run
    out = []
    for path, role in paths:
        if not Path(path).exists():
            raise ConfigError(f'bag {path!r} does not exist')
        out.append((read_run(path), role))
    return out


def _simulate(args: argparse.Namespace, base: StageParams) -> tuple[list[str], StageParams]:
    from piezo_stage_ros.analysis.bagwrite import write_run
    from piezo_stage_ros.core.identification.experiments import (
        ExperimentPlan,
        perturbed_stage,
        run_experiments,
    )
    true, _ = perturbed_stage(args.perturb, base=base) if args.perturb is not None else (
        base, None)
    if true.plant.model != 'third_order':
        # the procedure identifies eq. (17); a reduced or general-model stage would make the
        # recovered-vs-true table compare different models
        print(f'note: --simulate uses the third-order plant (configured: {true.plant.model})')
        true = true.replace(plant=true.plant.replace(model='third_order'))
    true = true.replace(chain=true.chain.replace(sensor_noise_std_m=args.sensor_noise))
    runs = run_experiments(true, ExperimentPlan(sample_rate_hz=args.sample_rate))
    out = Path(args.simulate)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, rec in runs.items():
        path = out / name
        write_run(rec, path, overwrite=args.overwrite)
        paths.append(str(path))
    return paths, true


def _true_stage(records: Sequence[RunRecord]) -> StageParams | None:
    """Return the true stage that simulated runs carry in their meta, if they all agree."""
    found = [r.meta.get('true_stage') for r in records]
    first = found[0] if found else None
    if not isinstance(first, dict) or any(f != first for f in found[1:]):
        return None
    try:
        return StageParams.from_flat(first)
    except PiezoStageError:
        return None


def _summary_lines(result: IdentificationResult) -> list[str]:
    s = result.summary()
    lines = [f'static gain k_p c = {s["static_gain_m_per_v"]:.6g} m/V',
             f'k_p = {s["gain_m_per_v"]:.6g} m/V, w_n = {s["omega_n_rad_s"]:.6g} rad/s, '
             f'zeta = {s["zeta"]:.5g}, tau = {s["tau_s"]:.6g} s',
             f'K = {s["K"]:.6g}, a0 = {s["a0"]:.6g}, a1 = {s["a1"]:.6g}, a2 = {s["a2"]:.6g}']
    if 'alpha' in s:
        lines.append(f'alpha = {s["alpha"]:.5g}, c = {s["c"]:.5g} (convention), '
                     f'B1 = {s["b1"]:.5g}')
    if result.hysteresis is not None:
        h = result.hysteresis
        lines.append('sine fit (+- 1 sigma): ' + ', '.join(
            f'{k} = {v:.5g} +- {h.std.get(k, float("nan")):.2g}' for k, v in h.estimates.items()))
    if result.step is not None:
        st = result.step
        lines.append(f'step fit (+- 1 sigma): zeta = {st.factors.zeta:.5g} +- {st.std.zeta:.2g}, '
                     f'tau = {st.factors.tau_s:.5g} +- {st.std.tau_s:.2g} s')
    if result.frequency is not None:
        fr = result.frequency
        lines.append(f'frequency fit (+- 1 sigma): w_n = {fr.factors.omega_n_rad_s:.6g} +- '
                     f'{fr.std.omega_n_rad_s:.2g} rad/s, small-signal k_p = '
                     f'{fr.factors.gain_m_per_v:.5g} m/V')
    return lines


def _bound_lines(result: IdentificationResult) -> list[str]:
    if not result.bounds:
        return []
    names = {'static_gain_m_per_v': 'static gain k_p c [m/V]', 'omega_n_rad_s': 'w_n [rad/s]',
             'zeta': 'zeta', 'tau_s': 'tau [s]', 'alpha': 'alpha [1/V]', 'b1_over_c': 'B1/c',
             'sensor_offset_m': 'sensor offset [m]'}
    out = []
    for key, label in names.items():
        if key in result.bounds:
            lo, hi = result.bounds[key]
            out.append(f'{label}: {lo:.6g} ... {hi:.6g}')
    return ['95 % bounds: ' + '; '.join(out)]


def _run_drift(args: argparse.Namespace, base: StageParams) -> int:
    from piezo_stage_ros.core.identification.drift import drift_lines, estimate_drift
    loaded = _read_bags([(b, None) for b in args.drift])
    status = 0
    for rec, _ in loaded:
        report = estimate_drift(rec, base, threshold=args.drift_threshold)
        for line in drift_lines(report):
            print(line)
    return status


def _run(args: argparse.Namespace) -> int:
    from piezo_stage_ros.core.identification.support import identify_checked, RefusedError
    config = cli.read_config(args.config)
    loop = cli.offline_loop(PROG, config)
    base = loop.stage
    if args.drift:
        if args.bags or args.noise or args.step or args.sine or args.simulate:
            raise cli.UsageError('--drift takes operation bags only (no other bag or '
                                 '--simulate)')
        return _run_drift(args, base)
    inputs: list[tuple[str, str | None]] = [(b, None) for b in args.bags]
    inputs += [(b, 'frequency') for b in args.noise] + [(b, 'step') for b in args.step]
    inputs += [(b, 'hysteresis') for b in args.sine]
    true_stage = None
    if args.simulate is not None:
        paths, true_stage = _simulate(args, base)
        inputs += [(p, None) for p in paths]
    elif args.perturb is not None:
        raise cli.UsageError('--perturb needs --simulate DIR')
    if not inputs:
        raise cli.UsageError('no bag given (BAG..., --noise, --step, --sine or --simulate DIR)')
    loaded = _read_bags(inputs)
    records = [r for r, _ in loaded]
    if true_stage is None:
        true_stage = _true_stage(records)
    slope = args.hysteresis_slope
    if slope is None:
        slope = _model_slope(base, args.model)
    params = IdentificationParams(hysteresis_model=args.model, hysteresis_slope=slope,
                                  step_fixes_omega=not args.free_omega)
    try:
        checked = identify_checked(records, base, params, roles=[role for _, role in loaded],
                                   closed_loop=True if args.closed_loop else None)
    except RefusedError as exc:
        # one line per parameter the data cannot support; no parameter file
        for line in exc.lines:
            cli.error(PROG, line)
        if args.json:
            print(json.dumps({'accepted': False, 'refused': exc.lines}))
        return 1
    result = checked.result
    stage = result.stage
    if args.pscm is not None:
        x0, x10 = args.pscm
        stage = stage.replace(chain=stage.chain.replace(
            sensor_gain_v_per_m=pscm_gain(x0, x10), sensor_offset_m=x0))
    header = ['Identified by: identify ' + ' '.join(sys.argv[1:] if args.argv is None
                                                    else args.argv),
              f'Hysteresis slope convention: {slope:g} (only k_p times the slope is '
              'identifiable, see docs/explanation/model.md).']
    if result.loop == 'closed':
        header.append('Closed-loop data: frequency response averaged over whole periods of the '
                      'reference; 95 % bounds: ' + ', '.join(
                          f'{k} {lo:.6g} ... {hi:.6g}' for k, (lo, hi) in result.bounds.items()))
    text = parameter_file_text(stage, header=header, reference=loop.controller.to_flat(),
                               reference_stage=base)
    Path(args.output).write_text(text, encoding='utf-8')
    for line in _summary_lines(result) + _bound_lines(result):
        print(line)
    for warning in checked.warnings:
        print(f'warning: {warning}')
    for note in result.notes:
        print(f'note: {note}')
    print(f'parameter file: {args.output}')
    if args.report.lower() != 'none':
        from piezo_stage_ros.analysis.identification_report import write_report
        files = write_report(result, args.report, true_stage=true_stage,
                             extra={'parameter file': args.output})
        print(f'report: {files[-1]}')
    if true_stage is not None:
        from piezo_stage_ros.analysis.identification_report import comparison_rows, format_table
        print()
        print(format_table(comparison_rows(result, true_stage)))
    if args.json:
        print(json.dumps(json_summary(checked)))
    return 0


#: JSON key of each identified quantity, by its name in the result's summary and bounds.
JSON_KEYS = {'static_gain_m_per_v': 'static_gain_m_per_v', 'gain_m_per_v': 'gain_m_per_v',
             'omega_n_rad_s': 'omega_n_rad_s', 'zeta': 'zeta', 'tau_s': 'tau_s',
             'alpha': 'alpha_per_v', 'b1_over_c': 'b1_over_c',
             'sensor_offset_m': 'sensor_offset_m', 'delay_samples': 'delay_samples'}


def json_summary(checked: CheckedIdentification) -> dict[str, Any]:
    """
    Return what ``identify --json`` prints: parameters with 95 % bounds and the verdicts.

    Parameters
    ----------
    checked : CheckedIdentification
        The identification.

    Returns
    -------
    dict
        ``accepted`` (true), ``loop`` (``'open'`` or ``'closed'``, the verdict on the
        frequency run: reported, the estimate does not depend on it), ``parameters`` (name ->
        ``{"value", "low", "high"}``; low = high = value for a quantity without bounds, e.g.
        a whole-sample delay chosen among whole delays, or the small-signal k_p),
        ``roles`` (role -> runs), ``runs`` (each run's role, loop verdict and its reason),
        ``warnings`` and ``notes``.

    """
    result = checked.result
    s = result.summary()
    values: dict[str, float] = {k: float(v) for k, v in s.items()}
    h = result.hysteresis
    if h is not None:
        values.update({k: float(v) for k, v in h.estimates.items()})
    values['delay_samples'] = float(result.factors.delay_samples)
    params: dict[str, dict[str, float]] = {}
    for name, key in JSON_KEYS.items():
        if name not in values:
            continue
        value = values[name]
        low, high = result.bounds.get(name, (value, value))
        params[key] = {'value': value, 'low': float(low), 'high': float(high)}
    return {'accepted': True, 'loop': result.loop, 'parameters': params,
            'roles': {k: list(v) for k, v in result.roles.items() if v},
            'runs': [{'name': r.name, 'role': r.role, 'loop': r.loop, 'why': r.loop_reason,
                      'excitation': r.lines.method} for r in checked.runs],
            'warnings': list(checked.warnings), 'notes': list(result.notes)}


def _model_slope(base: StageParams, model: str) -> float:
    h = base.hysteresis
    if model == 'backlash_like':
        return h.backlash_like.c
    if model == 'bouc_wen':
        return h.bouc_wen.d_p
    p = h.prandtl_ishlinskii
    return p.p0 + sum(p.weights)


main = cli.command_main(PROG, build_parser, _run,
                        '0 success, 1 bad data / parameters / failed '
                        'fit, 2 bad usage', keep_argv=True)


if __name__ == '__main__':
    sys.exit(main())
