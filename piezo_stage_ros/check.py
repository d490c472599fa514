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
Check a parameter file's controller offline, without ROS: ``check PARAMS.yaml``.

Reads ``config/default.yaml`` and then the given ROS 2 parameter files (the same files the
nodes read), builds the controller, the design model and the stability options exactly as the
controller node does at start-up, runs the stability check and prints its whole report: the
verdict, the worst case and the margins, every frozen family checked, the box and the
computational delay assumed, the adaptation bound, the learning's convergence, which
constraint binds, the search for a common quadratic Lyapunov function of the loop whose
estimates, boundary layer and hysteresis slope vary in time, and in words what is proven and
what is not.

The verdict is frozen-parameter robust stability over the box
(:mod:`piezo_stage_ros.core.control.stability`): every linear loop with the estimates and the
hysteresis slope frozen anywhere in their ranges is stable at the assumed delay. That alone is
not a proof for the running loop. The time-varying check goes further when it finds a common
quadratic Lyapunov function: then the loop stays exponentially stable however the estimates,
the boundary layer and the slope vary inside their ranges, and every signal stays bounded;
the command limits remain outside it. The report says which of the two holds.

Exit status: 0 when the frozen loops are stable over the box and the adaptation is within its
bound; 3 when a frozen loop is unstable; 4 when the frozen loops are stable but the adaptation
bound is exceeded; 1 on a bad file or value; 2 on bad usage.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Callable, Sequence, TYPE_CHECKING

from piezo_stage_ros import cli

if TYPE_CHECKING:
    from piezo_stage_ros.core.control.stability import StabilityReport

PROG = 'check'

#: Exit status of a check whose frozen loops are unstable.
EXIT_UNSTABLE = 3
#: Exit status of a check whose frozen loops are stable but whose adaptation bound fails.
EXIT_ADAPTATION = 4


def build_parser() -> argparse.ArgumentParser:
    """Return the command-line parser of ``check``."""
    p = cli.Parser(prog=PROG, description=__doc__.split('\n\n')[1].strip())
    p.add_argument('files', nargs='*', metavar='PARAMS.yaml',
                   help='ROS 2 parameter files applied on top of config/default.yaml, in order '
                   '(later files win; --config files come after them); bare names are looked '
                   'up in the package config/.')
    cli.add_config_options(p)
    p.add_argument('--delay-samples', type=float, metavar='D',
                   help="Computational delay to assume [samples] (default: the file's "
                   'stability.delay_samples).')
    p.add_argument('--estimates', choices=('corners', 'initial'),
                   help="RAC estimates to check (default: the file's stability.estimates).")
    p.add_argument('--no-varying', action='store_true',
                   help='Skip the search for a common quadratic Lyapunov function of the loop '
                   'with time-varying estimates, boundary layer and slope (seconds; up to a '
                   'minute when none exists).')
    p.add_argument('--delay-margin', action='store_true',
                   help='Also find the largest computational delay at which the frozen loops '
                   'stay stable (bisection to 0.01 sample, up to 10 samples).')
    p.add_argument('--json', action='store_true',
                   help='Print one JSON object on stdout instead of the text report.')
    return p




def _run(args: argparse.Namespace) -> int:
    from piezo_stage_ros.core.config.loader import LoopConfig
    from piezo_stage_ros.core.control.stability import check_stability
    from piezo_stage_ros.core.loop.trajectories import make_trajectory

    config = cli.read_config([*args.files, *args.config], args.param)
    changes: dict[str, object] = {}
    if args.delay_samples is not None:
        changes['stability.delay_samples'] = args.delay_samples
    if args.estimates is not None:
        changes['stability.estimates'] = args.estimates
    if changes:
        config = config.with_overrides('controller_node', changes)
    loop = LoopConfig.from_config(config)
    stage, ctrl, opts = loop.stage, loop.controller, loop.stability
    period_s = make_trajectory(loop.trajectory).period_s
    report = check_stability(ctrl, loop.design_plant, stage.sample_time_s, options=opts,
                             period_s=period_s, stage=stage, varying=not args.no_varying)
    margin = None
    if args.delay_margin:
        def stable(delay: float) -> bool:
            return check_stability(ctrl, loop.design_plant, stage.sample_time_s,
                                   options=opts.replace(delay_samples=delay)).stable
        margin = delay_margin(stable)
    sources = [str(p) for p in loop.sources]
    model = (f'{loop.design_plant.model} (stability.plant.*, design_model: own)'
             if opts.design_model == 'own' else
             f'{loop.design_plant.model} (plant_node plant.*)')
    if args.json:
        payload = report.as_dict()
        payload.update({'files': sources, 'design_model': model,
                        'action': opts.action, 'exit_status': exit_status(report)})
        if margin is not None:
            payload['delay_margin_samples'] = margin if math.isfinite(margin) else 'inf'
        print(json.dumps(payload, sort_keys=True))
    else:
        print(format_report(report, sources=sources, model=model, delay_margin=margin))
    return exit_status(report)


def exit_status(report: StabilityReport) -> int:
    """Return 0, :data:`EXIT_UNSTABLE` or :data:`EXIT_ADAPTATION` for a stability report."""
    if not report.stable:
        return EXIT_UNSTABLE
    return 0 if report.certified else EXIT_ADAPTATION


def delay_margin(stable: Callable[[float], bool], *, high: float = 10.0,
                 resolution: float = 0.01) -> float:
    """
    Return the largest computational delay [samples] at which ``stable(delay)`` holds.

    Parameters
    ----------
    stable : callable
        Whether the frozen loops are stable with a given delay [samples].
    high : float
        Largest delay searched [samples]; inf is returned when it is still stable there.
    resolution : float
        Bisection stops when the bracket is this narrow [samples].

    Returns
    -------
    float
        The stable end of the bracket (from below); -inf when the loop is unstable without
        delay. Stability need not be monotone in the delay: this is the first loss of
        stability found from 0 upwards on a 0.25-sample grid, refined by bisection.

    """
    if not stable(0.0):
        return -math.inf
    lo = 0.0
    step = 0.25
    hi = step
    while hi <= high and stable(hi):
        lo, hi = hi, hi + step
    if hi > high:
        return math.inf
    while hi - lo > resolution:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if stable(mid) else (lo, mid)
    return lo


def format_report(report: StabilityReport, *, sources: Sequence[str] = (), model: str = '',
                  delay_margin: float | None = None) -> str:
    """
    Return the full report as lines of text.

    Parameters
    ----------
    report : StabilityReport
        The check's result.
    sources : sequence of str
        The parameter files read, in order.
    model : str
        The design model and where it comes from.
    delay_margin : float, optional
        The largest delay that keeps the frozen loops stable [samples].

    Returns
    -------
    str

    """
    w = report.worst
    rate = 1.0 / report.sample_time_s
    box = report.box
    verdict = ('stable over the box (frozen parameters)' if report.stable
               else 'NOT stable over the box (frozen parameters)')
    if report.stable and not report.certified:
        verdict += '; adaptation ABOVE its bound'
    rows = [
        ('files', ', '.join(sources) or '(defaults)'),
        ('controller', report.controller),
        ('design model', model or report.plant),
        ('sample rate', f'{rate:g} Hz'),
        ('delay assumed', f'{report.delay_samples:g} samples (stability.delay_samples: the '
         'time from reading y_k to applying u_k)'),
        ('checked', box.text() if box is not None else 'the sampled loops'),
        ('verdict', verdict),
        ('worst case', f'{w.label}: spectral radius {w.spectral_radius:.4f}, gain margin '
         f'{_num(w.gain_margin_db)} dB, phase margin {_num(w.phase_margin_deg)} deg'),
        ('margins', f'smallest over the {len(report.cases)} sampled loops: gain '
         f'{_num(report.gain_margin_db)} dB, phase {_num(report.phase_margin_deg)} deg'),
    ]
    if delay_margin is not None:
        rows.append(('delay margin', f'stable up to {_num(delay_margin, 2)} samples of '
                     'computational delay (frozen loops)'))
    for c in report.certificates:
        rows.append(('family', f'{c.label}: ' + ('stable' if c.certified
                                                 else f'NOT stable, {c.detail}')))
    if report.adaptation is not None:
        rows.append(('adaptation', report.adaptation.text()))
    if report.learning is not None:
        rows.append(('learning', report.learning.text()))
    if report.varying is not None:
        rows.append(('time-varying', report.varying.text()))
    rows.append(('binding', report.binding()))
    scope = report.scope()
    proven, _, unproven = scope.partition(' Not proven: ')
    rows.append(('proven', proven))
    rows.append(('not proven', unproven))
    width = max(len(k) for k, _ in rows)
    return '\n'.join(f'{k:<{width}}  {v}' for k, v in rows)


def _num(value: float, digits: int = 1) -> str:
    return f'{value:.{digits}f}' if math.isfinite(value) else ('inf' if value > 0 else '-inf')


main = cli.command_main(PROG, build_parser, _run,
                        '0 stable, 3 a frozen loop unstable, 4 the adaptation bound '
                        'exceeded, 1 bad file or value, 2 bad usage')


if __name__ == '__main__':
    sys.exit(main())
