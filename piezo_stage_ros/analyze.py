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
Replay bags: metrics, plots and a report (``analyze BAG...``, ``python3 -m ...analyze``).

Examples
--------
``analyze run.bag``
    Human summary of one bag.
``analyze --json rac.bag pi.bag``
    One JSON object per bag and line, the field names of ``simulate --json``.
``analyze --report report/ rac.bag pi.bag``
    ``report/report.md`` comparing the bags, with their figures.
``analyze --export-table table.npz learning.bag``
    The learned table of a learning run, as ``simulate --save-table`` writes it.
``analyze --plots figs/ xy.bag``
    A multi-axis bag: per-axis metrics as ``simulate_axes`` prints them, the raster frame's
    error and a grating imaged over it.

Exit status: 0 when every bag was analysed, 1 when any bag failed (one line on stderr per bad
bag, naming it and the problem; the other bags are still analysed), 2 for bad options.

"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import sys

from piezo_stage_ros import cli

__all__ = ['main']

PROG = 'analyze'


def _non_negative(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
    if not math.isfinite(value) or value < 0.0:
        raise argparse.ArgumentTypeError(f'{text!r} is out of range; allowed: [0, inf) s')
    return value


def _positive(text: str) -> float:
    value = _non_negative(text)
    if value == 0.0:
        raise argparse.ArgumentTypeError(f'{text!r} is out of range; allowed: (0, inf)')
    return value


def build_parser() -> argparse.ArgumentParser:
    """
    Build the command-line parser.

    Returns
    -------
    argparse.ArgumentParser
        The parser of ``analyze``.

    """
    parser = cli.Parser(
        prog=PROG,
        description='Replay rosbag2 bags of piezo stage runs (written by simulate --bag or '
                    'recorded from the nodes): align position, reference and command, compute '
                    'the metrics, draw the paper-style figures, write a report.')
    parser.add_argument('bags', nargs='+', metavar='BAG', type=Path,
                        help='bag directory (MCAP or sqlite3), or a single .mcap/.db3 file')
    parser.add_argument('--json', action='store_true',
                        help='print one JSON object per bag (same field names as simulate '
                             '--json, SI units) instead of the human summary')
    parser.add_argument('--plots', type=Path, metavar='DIR',
                        help='write PNG figures into DIR (DIR/<bag>/ for several bags)')
    parser.add_argument('--report', type=Path, metavar='DIR',
                        help='write DIR/report.md with the figures; several bags are compared '
                             'in one table')
    parser.add_argument('--namespace', metavar='NS',
                        help="topic namespace, e.g. '/stage' (default: found from the bag)")
    parser.add_argument('--steady-state-start', type=_non_negative, metavar='S',
                        dest='steady_state_start_s',
                        help='start of the metrics window, seconds after the first sample '
                             '(default: the one stored by simulate, else the same default as '
                             'simulate)')
    cli.add_line_options(parser, 'measure and plot')
    bode = parser.add_mutually_exclusive_group()
    bode.add_argument('--bode', dest='bode', action='store_true', default=None,
                      help='always estimate the frequency response v_in -> x')
    bode.add_argument('--no-bode', dest='bode', action='store_false',
                      help='never estimate it (default: only for noise or sweep runs)')
    parser.add_argument('--export-table', type=Path, metavar='FILE', dest='export_table',
                        help='write the learned table the bag holds (a simulate --bag run with '
                             'a learning feed-forward) to FILE, the file controller_node '
                             'feedforward.table_file loads; one bag only')
    parser.add_argument('--window', type=_positive, metavar='S', dest='window_s',
                        help='multi-axis bags: metrics over the last S seconds (default: the '
                             "run's own window, else the last second)")
    parser.add_argument('--grating-pitch', type=_positive, metavar='M', dest='grating_pitch_m',
                        default=1e-6,
                        help='multi-axis raster bags: pitch of the grating imaged over the last '
                             'frame [m] (default 1e-6)')
    parser.add_argument('-q', '--quiet', action='store_true',
                        help='no progress line and no notes on stderr')
    return parser




def _export(analysis: object, path: Path) -> None:
    from piezo_stage_ros.analysis.replay import BagAnalysis, learned_table
    from piezo_stage_ros.core.control.feedforward import write_learned_table
    assert isinstance(analysis, BagAnalysis)
    table = learned_table(analysis)
    write_learned_table(path, table)
    print(f'{PROG}: learned table written to {path} ({table.samples} samples, '
          f'{table.periods_learned} periods learned)', file=sys.stderr)


def _is_axes(bag: Path, namespace: str | None) -> bool:
    # a bag that cannot be opened is reported by the one-axis path, as ever
    from piezo_stage_ros.analysis.bagread import bag_info, is_axes_bag
    from piezo_stage_ros.core.contracts.errors import PiezoStageError
    try:
        return is_axes_bag(bag_info(bag), namespace)
    except PiezoStageError:
        return False


def _analyze_axes(args: argparse.Namespace, bag: Path, outdir: Path | None) -> bool:
    """Analyse a multi-axis bag: print its figures, draw them; False when it failed."""
    from piezo_stage_ros.analysis.axes_replay import (
        analyze_axes_bag,
        axes_summary_json,
        format_axes_summary,
    )
    from piezo_stage_ros.core.contracts.errors import PiezoStageError
    for option, value in (('--export-table', args.export_table), ('--report', args.report),
                          ('--steady-state-start', args.steady_state_start_s)):
        if value is not None:
            print(f'{PROG}: error: bag {bag}: {option} takes one-axis bags; this one holds '
                  'several axes (use --plots, --window)', file=sys.stderr)
            return False
    try:
        analysis = analyze_axes_bag(bag, namespace=args.namespace, window_s=args.window_s,
                                    grating_pitch_m=args.grating_pitch_m)
    except PiezoStageError as err:
        print(f'{PROG}: error: {err}', file=sys.stderr)
        return False
    except MemoryError:
        print(f'{PROG}: error: bag {bag}: not enough memory to hold its samples',
              file=sys.stderr)
        return False
    except Exception as err:  # noqa: BLE001 - a bag must never end in a traceback
        print(f'{PROG}: error: bag {bag}: cannot be analysed ({type(err).__name__}: {err}); '
              'please report this with the bag', file=sys.stderr)
        return False
    for text in analysis.records[0].meta.get('alignment', {}).get('warnings', ()):
        print(f'{PROG}: warning: bag {bag}: {text}', file=sys.stderr)
    if args.json:
        print(json.dumps(axes_summary_json(analysis), sort_keys=False), flush=True)
    else:
        print(format_axes_summary(analysis), flush=True)
    if outdir is not None:
        from piezo_stage_ros.analysis.axes_plots import plot_axes_run
        try:
            plot_axes_run(analysis.records, outdir, title=analysis.name,
                          fast_axis=analysis.fast_axis, slow_axis=analysis.slow_axis,
                          lines=analysis.lines, grating=analysis.grating,
                          open_loop=analysis.open_loop is not None)
        except OSError as err:
            print(f'{PROG}: error: cannot write figures into {outdir}: {err.strerror}',
                  file=sys.stderr)
            return False
    return True


def _analyze(args: argparse.Namespace) -> int:
    # Imported here so that --help works (and is fast) without the analysis dependencies, and
    # matplotlib only when figures are asked for.
    if args.export_table is not None and len(args.bags) != 1:
        print(f'{PROG}: error: --export-table takes the table of one bag; {len(args.bags)} '
              'given', file=sys.stderr)
        return 2
    figure_root: Path | None = args.plots if args.plots is not None else args.report
    try:
        from piezo_stage_ros.analysis.replay import analyze_bag, format_summary, summary_json
        from piezo_stage_ros.analysis.report import ReportEntry, unique_names, write_report
        from piezo_stage_ros.core.contracts.errors import PiezoStageError
        from piezo_stage_ros.core.loop.metrics import LineOptions
        if figure_root is not None:
            from piezo_stage_ros.analysis.plots import error_trace, plot_comparison, plot_run
    except ImportError as err:
        print(f'{PROG}: error: a dependency is missing: {err}', file=sys.stderr)
        return 1

    lines = LineOptions.asked(args.line_middle, args.pixels)
    shown = cli.Progress(PROG, enabled=not args.quiet and sys.stderr.isatty())
    names = unique_names(args.bags)
    entries = []
    traces = []
    failed = 0
    for index, (bag, name) in enumerate(zip(args.bags, names), start=1):
        label = f'[{index}/{len(args.bags)}] {name}'

        def progress(done: int, total: int, label: str = label) -> None:
            shown.fraction(label, done, total)
        if _is_axes(bag, args.namespace):
            outdir = None if args.plots is None else (
                args.plots if len(args.bags) == 1 else args.plots / name)
            failed += not _analyze_axes(args, bag, outdir)
            continue
        try:
            analysis = analyze_bag(bag, namespace=args.namespace,
                                   steady_state_start_s=args.steady_state_start_s,
                                   bode=args.bode,
                                   progress=progress if shown.enabled else None,
                                   lines=lines)
        except PiezoStageError as err:
            shown.end()
            print(f'{PROG}: error: {err}', file=sys.stderr)
            failed += 1
            continue
        except MemoryError:
            shown.end()
            print(f'{PROG}: error: bag {bag}: not enough memory to hold its samples',
                  file=sys.stderr)
            failed += 1
            continue
        except Exception as err:  # noqa: BLE001 - a bag must never end in a traceback
            shown.end()
            print(f'{PROG}: error: bag {bag}: cannot be analysed ({type(err).__name__}: {err}); '
                  'please report this with the bag', file=sys.stderr)
            failed += 1
            continue
        shown.end()
        for text in analysis.record.meta.get('alignment', {}).get('warnings', ()):
            # analysed all the same (e.g. a real-time run whose commands cannot be paired)
            print(f'{PROG}: warning: bag {bag}: {text}', file=sys.stderr)
        if args.json:
            print(json.dumps(summary_json(analysis), sort_keys=False), flush=True)
        else:
            print(format_summary(analysis), flush=True)
        if args.export_table is not None:
            try:
                _export(analysis, args.export_table)
            except PiezoStageError as err:
                print(f'{PROG}: error: {err}', file=sys.stderr)
                failed += 1
        if figure_root is not None:
            outdir = figure_root if len(args.bags) == 1 else figure_root / name
            try:
                window = analysis.metrics.get('steady_state_start_s')
                figures = plot_run(analysis.record, outdir, title=name,
                                   steady_state_start_s=window, bode=analysis.bode,
                                   lines=lines)
            except OSError as err:
                print(f'{PROG}: error: cannot write figures into {outdir}: {err.strerror}',
                      file=sys.stderr)
                return 1
            entries.append(ReportEntry(analysis, figures, name))
            traces.append(error_trace(analysis.record))
        # The metrics and figures are made; a long bag's samples need not stay in memory.
        analysis.release()
    if args.report is not None and entries:
        try:
            comparison = None
            if len(entries) > 1:
                comparison = plot_comparison(traces, [e.label for e in entries],
                                             args.report / 'comparison_error.png')
            path = write_report(entries, args.report, comparison)
        except OSError as err:
            print(f'{PROG}: error: cannot write the report into {args.report}: {err.strerror}',
                  file=sys.stderr)
            return 1
        if not args.quiet:
            print(f'{PROG}: report written to {path}', file=sys.stderr)
    return 1 if failed else 0


main = cli.command_main(PROG, build_parser, _analyze,
                        '0 all bags analysed, 1 some bag failed, 2 bad options')


if __name__ == '__main__':
    sys.exit(main())
