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
``robustness``: one controller configuration, unchanged, on a family of stages unlike the model.

The family (:mod:`piezo_stage_ros.core.model.family`) varies the configured third-order stage: gain
0.7-1.4x, omega_n +-10 %, zeta 0.7-1.5x, tau +-30 %, alpha +-30 %, B1 +-3 %, sensor noise
0-3 nm, one at a time and in corner combinations. The cases and what is measured:
:mod:`piezo_stage_ros.core.loop.robustness`. Parameters come from files and ``--param`` exactly as
for ``simulate`` (its loader).

Examples::

    robustness                                   # every stage, every case, 2 s runs
    robustness --cases sine_100,square --stages nominal,gain_lo,gain_hi --out runs/rob
    robustness --param controller_node:rac.gamma=300 --json
    robustness --samples 1000 --cases sine_100   # and 1000 members drawn inside the ranges
    robustness --commission --cases scan_line_137 --feedforward inverse_learning
                                                 # each member commissioned first

With ``--commission`` each member is first commissioned as ``commission --stage`` does (hold,
closed-loop excitation with the member's sensor noise, or 2 nm when it has none; identify;
design; certify; verify) and runs every case with its own identified model and designed
controller, the feed-forward mode being the configured one. A member whose commissioning is
refused or not accepted runs the configured design, and the table says so beside it.

Exit status: 0 on success, 1 on a bad parameter or configuration, 2 on bad command-line usage.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
import json
from pathlib import Path
import sys
from typing import Any, Sequence

from piezo_stage_ros import cli
from piezo_stage_ros.core.config.loader import LoopConfig
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.control.controllers import ControllerParams
from piezo_stage_ros.core.loop.robustness import DesignFn, MemberDesign
from piezo_stage_ros.core.model.family import StageVariation
from piezo_stage_ros.core.model.stage import StageParams

__all__ = ['main']

PROG = 'robustness'


def _parser() -> argparse.ArgumentParser:
    p = cli.Parser(prog=PROG, description='Run one controller configuration on a family of '
                   'stages and print e_rms, e_m, command range and the adapted estimates per '
                   'stage.')
    cli.add_config_options(p)
    p.add_argument('--controller', choices=cli.choices(ControllerParams, 'type'),
                   help='Controller (default: the configured one).')
    cli.add_feedforward_option(p)
    p.add_argument('--cases', metavar='A,B,...',
                   help='Cases to run (default all): sine_1, sine_10, sine_50, sine_100, '
                   'multisine, square, square_2ms, staircase.')
    p.add_argument('--stages', metavar='A,B,...',
                   help='Members of the family to run (default all; names as listed by '
                   '--list-stages).')
    p.add_argument('--list-stages', action='store_true', help='Print the family and exit.')
    p.add_argument('--samples', type=int, default=0, metavar='N',
                   help='Add N members drawn uniformly inside every range (seed --sample-seed); '
                   'they count in the worst case, the tables list only the named members.')
    p.add_argument('--sample-seed', type=int, default=0, metavar='N',
                   help='Seed of the drawn members (default 0).')
    p.add_argument('--single', action='store_true',
                   help='One closed-loop run per stage and case instead of the batch (the '
                   'reference path; same numbers, slower for many stages).')
    p.add_argument('--commission', action='store_true',
                   help='Commission each member first (as commission --stage) and run it with '
                   'its identified model and designed controller (single runs).')
    p.add_argument('--duration', type=float, default=2.0, metavar='S',
                   help='Simulated time per run [s] (default 2).')
    p.add_argument('--settle', type=float, default=1.0, metavar='S',
                   help='Start of the steady state [s] (default 1).')
    p.add_argument('--window-only', action='store_true',
                   help='Keep only the samples after --settle (long runs: memory, larger '
                   'batches); the command and estimate ranges then cover that window. Sines and '
                   'multisine only.')
    p.add_argument('--out', metavar='DIR', help='Write robustness.json, robustness.txt and '
                   'the plots there.')
    p.add_argument('--json', action='store_true', help='Print the JSON on stdout instead of '
                   'the tables.')
    p.add_argument('--quiet', action='store_true', help='No progress lines on stderr.')
    return p


def _pick(text: str | None, known: Sequence[str], what: str) -> list[str]:
    if text is None:
        return list(known)
    names = [n.strip() for n in text.split(',') if n.strip()]
    for n in names:
        if n not in known:
            raise ParameterError(what, n, ', '.join(known))
    return names


def _run(args: argparse.Namespace) -> int:
    from piezo_stage_ros.core.loop.robustness import CASES, format_result, run_study
    from piezo_stage_ros.core.model.family import default_family, sample_family

    family = default_family()
    if args.list_stages:
        for m in family:
            print(f'{m.name:24s} {m.describe()}')
        return 0
    loop = cli.offline_loop(PROG, cli.loop_overrides(
        cli.read_config(args.config, args.param), controller=args.controller,
        feedforward=args.feedforward))
    by_name = {m.name: m for m in family}
    stages = [by_name[n] for n in _pick(args.stages, list(by_name), '--stages')]
    named = {m.name for m in stages}
    stages += list(sample_family(args.samples, args.sample_seed)) if args.samples > 0 else []
    cases = _pick(args.cases, list(CASES), '--cases')
    progress = cli.Progress(PROG, enabled=not args.quiet)
    result = run_study(loop.stage, loop.controller, loop.trajectory,
                       family=stages, cases=cases, duration_s=args.duration,
                       settle_s=args.settle, traced=named,
                       batch=not (args.single or args.commission),
                       window_only=args.window_only, progress=progress.line,
                       designs=_commissioned(loop) if args.commission else None)
    result.meta['wall_seconds'] = progress.elapsed()
    result.meta['config_files'] = [str(p) for p in loop.sources]
    result.meta['params'] = list(args.param)
    text = format_result(result)
    payload = result.to_json()
    if args.out is not None:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / 'robustness.json').write_text(json.dumps(payload, indent=1, sort_keys=True)
                                             + '\n', encoding='utf8')
        (out / 'robustness.txt').write_text(text + '\n', encoding='utf8')
        from piezo_stage_ros.analysis.robustness_plots import save_plots
        written = save_plots(result, out)
        progress.line(f'wrote {out / "robustness.json"}, {out / "robustness.txt"} and '
                      f'{len(written)} plots')
    print(json.dumps(payload, sort_keys=True) if args.json else text)
    return 0


def _commissioned(loop: LoopConfig) -> DesignFn:
    """Return the design of a member: its commissioning, or the configured one if refused."""
    from piezo_stage_ros.commission import DEFAULT_NOISE_M
    from piezo_stage_ros.core.identification.commission import (
        commission,
        CommissionRefusedError,
    )
    from piezo_stage_ros.core.model.family import member_params
    from piezo_stage_ros.identify import controller_values

    def derive(identified: StageParams) -> dict[str, Any]:
        return controller_values(identified, loop.controller.to_flat(), loop.stage)

    def design(member: StageVariation, _stage: StageParams) -> MemberDesign:
        noisy = member if member.noise_m > 0.0 else replace(member, noise_m=DEFAULT_NOISE_M)
        try:
            result = commission(member_params(loop.stage, noisy), loop.stage, loop.controller,
                                derive, stability=loop.stability)
        except CommissionRefusedError as exc:
            return MemberDesign(loop.controller, loop.stage,
                                f'commissioning refused ({exc}); configured design', False)
        if not result.accepted:
            return MemberDesign(loop.controller, loop.stage,
                                f'commissioning not accepted ({"; ".join(result.refused)}); '
                                'configured design', False)
        ver = result.verification
        return MemberDesign(result.design.controller, result.identified,
                            f'commissioned, verification e_rms {ver.e_rms_m * 1e9:.2f} nm')
    return design


main = cli.command_main(PROG, _parser, _run,
                        '0 success, 1 a bad parameter, configuration or '
                        'file, 2 bad usage, 130 Ctrl-C')


if __name__ == '__main__':
    sys.exit(main())
