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
``results``: run the quick studies and rewrite the generated sections of docs/results.md.

Each generated section lies between ``<!-- results: NAME begin -->`` and ``<!-- results: NAME
end -->`` and is written whole by this command: the figures, the exact command that made them
and the machine it ran on (platform, CPU, CPU count, Python, numpy, scipy, load, date, commit).
The figures come from the commands a user runs (``simulate --json``, ``benchmark --json``), run
as subprocesses of this interpreter, so the page shows what those commands print and nothing
is copied by hand. Sections of long studies and of ROS runs are recorded by hand outside the
markers and left alone.

Sections: ``table3`` (the paper's Table III, ``simulate --experiment table3``),
``feedforward`` (the feed-forward modes on the 100 Hz and 200 Hz sines), ``speed``
(``benchmark --suite sim``), ``scan`` (lines at any rate against the scanning targets:
triangles, raster lines up to 1 kHz, fast sines, a line-rate change, the amplifier's
limit). ``--quick`` runs the feed-forward at 100 Hz only and the
benchmark with one repeat and fewer controller steps; ``--sections`` picks some.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
import datetime
import json
import os
from pathlib import Path
import platform
import subprocess
import sys
from typing import Any, Callable, Sequence

from piezo_stage_ros import cli
from piezo_stage_ros.core.contracts.errors import PiezoStageError

PROG = 'results'
DEFAULT_FILE = Path(__file__).resolve().parents[1] / 'docs' / 'results.md'
FEEDFORWARD_MODES = ('none', 'inverse', 'learning', 'inverse_learning')

# Table III's row labels, as the README repeats them (test/test_docs.py checks the copy)
TABLE3_ROWS = (
    ('rac', 'reduced', 'project RAC, reduced plant (25)'),
    ('pi', 'reduced', 'project PI (paper gains), reduced plant (25)'),
    ('rac', 'third_order', 'project RAC, third-order plant (20)'),
    ('pi', 'third_order', 'project PI (paper gains) + notch, third-order plant (20)'),
)
PAPER_ROWS = (
    ('paper RAC (experiment)', (4.4, 5.6, 17.6, 39.4)),
    ('paper PIC (experiment)', (13.8, 131.4, 614.4, 1004.6)),
)
TABLE3_FREQUENCIES_HZ = (1.0, 10.0, 50.0, 100.0)


def markers(name: str) -> tuple[str, str]:
    """Return the begin and end markers of the generated section ``name``."""
    return f'<!-- results: {name} begin -->', f'<!-- results: {name} end -->'


def replace_section(text: str, name: str, body: str) -> str:
    """
    Return ``text`` with the generated section ``name`` replaced by ``body``.

    Parameters
    ----------
    text : str
        The page.
    name : str
        Section name, as in the markers.
    body : str
        The new content between the markers (without them).

    Returns
    -------
    str
        The page with everything outside the markers unchanged.

    Raises
    ------
    PiezoStageError
        When the page lacks either marker, or holds them out of order.

    """
    begin, end = markers(name)
    start = text.find(begin)
    stop = text.find(end)
    if start < 0 or stop < start:
        raise PiezoStageError(f'section {name!r}: the page has no {begin} ... {end} pair')
    return text[:start + len(begin)] + '\n' + body.strip('\n') + '\n' + text[stop:]


def _git_commit() -> str:
    """Return the short commit of the checkout, or 'unknown' outside a git checkout."""
    try:
        out = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], capture_output=True,
                             text=True, check=True, cwd=Path(__file__).resolve().parent)
    except (OSError, subprocess.CalledProcessError):
        return 'unknown'
    return out.stdout.strip() or 'unknown'


def _cpu_model() -> str:
    """Return the CPU model name the kernel reports, or the platform's processor string."""
    try:
        for line in Path('/proc/cpuinfo').read_text(encoding='utf-8').splitlines():
            if line.startswith('model name'):
                return line.split(':', 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or 'unknown CPU'


def machine() -> str:
    """
    Return one line that says where and when the figures were made.

    Platform, CPU model and count, Python, numpy and scipy versions, the load average at the
    start, the UTC time and the commit.
    """
    import numpy
    import scipy
    load = '/'.join(f'{x:.1f}' for x in os.getloadavg()) if hasattr(os, 'getloadavg') else '?'
    now = datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')
    return (f'{platform.platform()}, {_cpu_model()} x {os.cpu_count()}, Python '
            f'{platform.python_version()}, numpy {numpy.__version__}, scipy '
            f'{scipy.__version__}; load average {load} at the start; {now}; commit '
            f'{_git_commit()}')


def run_json(module: str, args: Sequence[str]) -> Any:
    """
    Run ``python -m piezo_stage_ros.MODULE ARGS --json`` and return the JSON it prints.

    Raises
    ------
    PiezoStageError
        When the command exits with an error (its stderr's last line is in the message).

    """
    cmd = [sys.executable, '-m', f'piezo_stage_ros.{module}', *args, '--json']
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ['no message'])[-1]
        raise PiezoStageError(f'{module} {" ".join(args)} failed ({done.returncode}): {last}')
    return json.loads(done.stdout)


def _nm(value: float | None) -> str:
    return '-' if value is None else f'{value * 1e9:.2f}'


def table3_section(data: Any) -> str:
    """Return the Table III rows (e_rms, nm) from ``simulate --experiment table3 --json``."""
    rows = next(e for e in data['experiments'] if e['experiment'] == 'table3')['rows']
    rms = {(r['controller'], r['plant'], float(r['frequency_hz'])): r['e_rms_m'] for r in rows}
    head = '| e_rms [nm] | ' + ' | '.join(f'{f:g} Hz' for f in TABLE3_FREQUENCIES_HZ) + ' |'
    lines = [head, '| --- |' + ' ---: |' * len(TABLE3_FREQUENCIES_HZ)]
    lines += [f'| {label} | ' + ' | '.join(f'{v:g}' for v in values) + ' |'
              for label, values in PAPER_ROWS]
    for controller, plant, label in TABLE3_ROWS:
        cells = [f'{rms[(controller, plant, f)] * 1e9:.1f}' for f in TABLE3_FREQUENCIES_HZ]
        lines.append(f'| {label} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def feedforward_section(runs: dict[tuple[str, float], Any]) -> str:
    """Return e_rms / e_m (measured) and the true e_rms per mode and sine frequency, in nm."""
    freqs = sorted({f for _, f in runs})
    head = '| mode | ' + ' | '.join(
        f'{f:g} Hz e_rms / e_m | {f:g} Hz true e_rms' for f in freqs) + ' |'
    lines = [head, '| --- |' + ' ---: | ---: |' * len(freqs)]
    for mode in FEEDFORWARD_MODES:
        cells = []
        for f in freqs:
            r = runs[(mode, f)]
            cells += [f'{_nm(r["e_rms_m"])} / {_nm(r["e_max_m"])}', _nm(r.get('e_rms_true_m'))]
        lines.append(f'| `{mode}` | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def speed_section(data: Any) -> str:
    """Return the offline speed rows from ``benchmark --suite sim --json``."""
    sim = data['sim']
    rows = [
        ('offline closed loop, RAC + notch, reduced plant: simulated s per wall s',
         f'{sim["realtime_reduced"]:.1f}', '>= 20, aim 100'),
        ('the same, third-order plant', f'{sim["realtime_third_order"]:.1f}', '>= 20'),
        ('the same, electromechanical model', f'{sim["realtime_electromechanical"]:.1f}', '-'),
        ('per sample, third-order: stage / controller / whole loop [us CPU]',
         '{stage_us:.2f} / {controller_us:.2f} / {loop_us:.2f}'.format(
             **sim['breakdown_third_order']), '-'),
        ('`StageBatch` of the batch size: stage-steps per wall s / per CPU s',
         f'{sim["batch_steps_per_s"]:.3g} / {sim["batch_steps_per_cpu_s"]:.3g}', '>= 1e7'),
        ('batched closed loop, RAC + notch, family members: stage-steps per wall s / CPU s',
         f'{sim["batch_loop_steps_per_s"]:.3g} / {sim["batch_loop_steps_per_cpu_s"]:.3g}',
         '>= 1e7'),
    ]
    for mode in ('learning', 'inverse_learning'):
        if f'batch_loop_{mode}_steps_per_s' in sim:
            rows.append((f'the same + feed-forward `{mode}`',
                         f'{sim[f"batch_loop_{mode}_steps_per_s"]:.3g} / '
                         f'{sim[f"batch_loop_{mode}_steps_per_cpu_s"]:.3g}', '>= 5e6'))
    steps = [('PI', 'pi_step'), ('RAC + notch', 'rac_step')]
    steps += [(f'RAC + notch + `{m}`', f'rac_{m}_step') for m in ('inverse', 'learning',
                                                                     'inverse_learning')]
    for label, key in steps:
        if key in sim:
            t = sim[key]
            rows.append((f'one controller step, {label}: median / p99 [us]',
                         f'{t["median_ns"] / 1e3:.2f} / {t["p99_ns"] / 1e3:.2f}', '-'))
    lines = ['| what | measured | target |', '| --- | ---: | --- |']
    lines += [f'| {a} | {b} | {c} |' for a, b, c in rows]
    return '\n'.join(lines)


@dataclass(frozen=True)
class ScanCase:
    """
    One row of the ``scan`` section: a ``simulate`` run, its figure and its target.

    ``figure`` is ``'line'`` (the larger of the trace and retrace e_rms over the measured part
    of the lines, of the true position when the run has one), ``'true'`` (e_rms of the true
    position) or ``'measured'`` (e_rms). The target is ``target_m``, or the figure of the
    row labelled ``against`` (no worse than it), or none.
    """

    label: str
    args: tuple[str, ...]
    figure: str
    target_m: float | None = None
    against: str = ''


def _sine(f: float, mode: str, duration_s: float = 2.0) -> tuple[str, ...]:
    return ('--trajectory', 'sine', '--frequency', f'{f:g}', '--feedforward', mode,
            '--duration', f'{duration_s:g}')


def _line(kind: str, f: float, mode: str, *more: str) -> tuple[str, ...]:
    return ('--trajectory', kind, '--frequency', f'{f:g}', '--feedforward', mode,
            '--duration', '3', '--steady-state-start', '2', *more)


_SAT = ('--trajectory', 'sine', '--frequency', '50', '--amplitude', '14.3e-6', '--offset',
        '15e-6', '--duration', '10', '--feedforward')
_CHANGE = ('--trajectory', 'sine', '--frequency', '100', '--line-rate-change', '1.0:137')
#: The first line after the change: the window is the one whole 137 Hz line from 1 s.
_FIRST_LINE = ('--steady-state-start', '1.0', '--duration', '1.0074')

_FIRST_INVERSE = '100 -> 137 Hz at 1 s, first new line, `inverse`, true'
_SAT_NONE = '50 Hz sine of 14.3 um around 15 um (to the amplifier limit), `none`, true'

#: The rows of the ``scan`` section.
SCAN_CASES = (
    ScanCase('triangle 70 Hz, `inverse_learning`, middle 80 %',
             _line('triangle', 70.0, 'inverse_learning', '--line-middle', '0.8'), 'line', 2e-9),
    ScanCase('triangle 80 Hz, `inverse_learning`, middle 80 %',
             _line('triangle', 80.0, 'inverse_learning', '--line-middle', '0.8'), 'line', 2e-9),
    ScanCase('sine 300 Hz, `learning`, true', _sine(300.0, 'learning'), 'true', 1e-9),
    ScanCase('raster line 100 Hz, `inverse_learning`, linear part',
             _line('scan_line', 100.0, 'inverse_learning'), 'line', 0.5e-9),
    ScanCase('raster line 300 Hz, `inverse_learning`, linear part',
             _line('scan_line', 300.0, 'inverse_learning'), 'line', 1e-9),
    ScanCase('raster line 1 kHz, `inverse_learning`, linear part',
             _line('scan_line', 1000.0, 'inverse_learning'), 'line', 3e-9),
    ScanCase('raster line 300 Hz, `inverse`, linear part',
             _line('scan_line', 300.0, 'inverse'), 'line'),
    ScanCase('raster line 1 kHz, `inverse`, linear part',
             _line('scan_line', 1000.0, 'inverse'), 'line'),
    ScanCase(_FIRST_INVERSE, (*_CHANGE, '--feedforward', 'inverse', *_FIRST_LINE), 'true'),
    ScanCase('the same, `learning`, true',
             (*_CHANGE, '--feedforward', 'learning', *_FIRST_LINE), 'true',
             against=_FIRST_INVERSE),
    ScanCase('the same, `inverse_learning`, true',
             (*_CHANGE, '--feedforward', 'inverse_learning', *_FIRST_LINE), 'true',
             against=_FIRST_INVERSE),
    ScanCase('100 -> 137 Hz, from the 50th new line, `inverse_learning`, true',
             (*_CHANGE, '--feedforward', 'inverse_learning', '--duration', '2',
              '--steady-state-start', '1.365'), 'true', 1e-9),
    ScanCase('sine 300 Hz, `inverse`, true', _sine(300.0, 'inverse'), 'true', 1.6e-9),
    ScanCase('sine 500 Hz, `inverse`, true', _sine(500.0, 'inverse'), 'true', 2.4e-9),
    ScanCase(_SAT_NONE, (*_SAT, 'none'), 'true'),
    ScanCase('the same, `learning`, true', (*_SAT, 'learning'), 'true', against=_SAT_NONE),
    ScanCase('the same, `inverse_learning`, true', (*_SAT, 'inverse_learning'), 'true',
             against=_SAT_NONE),
)


def scan_figure(case: ScanCase, data: Any) -> float:
    """Return the figure of one ``scan`` row from its ``simulate --json`` output [m]."""
    if case.figure == 'line':
        suffix = '_true_m' if data.get('line_trace_e_rms_true_m') is not None else '_m'
        return max(float(data[f'line_trace_e_rms{suffix}']),
                   float(data[f'line_retrace_e_rms{suffix}']))
    key = 'e_rms_true_m' if case.figure == 'true' else 'e_rms_m'
    return float(data[key])


def scan_section(runs: Sequence[tuple[ScanCase, Any]]) -> str:
    """
    Return the ``scan`` rows: figure, target and whether it is met, in nm.

    A run that clipped commands says how many (the run reports it).
    """
    lines = ['| case | e_rms [nm] | target [nm] | met |', '| --- | ---: | ---: | --- |']
    seen: dict[str, float] = {}
    for case, data in runs:
        value = scan_figure(case, data)
        seen[case.label] = value
        bound = seen[case.against] if case.against else case.target_m
        goal = '-' if bound is None else f'<= {bound * 1e9:.2f}'
        met = '-' if bound is None else ('yes' if value <= bound else '**no**')
        label = case.label
        clipped = data.get('ff_clipped_samples')
        if clipped:
            label += f' ({int(clipped)} commands clipped, reported)'
        lines.append(f'| {label} | {value * 1e9:.2f} | {goal} | {met} |')
    return '\n'.join(lines)


@dataclass(frozen=True)
class Study:
    """A generated section: how to run it, and how to turn its output into Markdown."""

    name: str
    title: str
    run: Callable[[bool], tuple[list[str], str]]


def _fenced(commands: Sequence[str]) -> str:
    return '```sh\n' + '\n'.join(commands) + '\n```'


def _table3(quick: bool) -> tuple[list[str], str]:
    args = ['--experiment', 'table3']
    return ['simulate ' + ' '.join(args)], table3_section(run_json('simulate', args))


def _feedforward(quick: bool) -> tuple[list[str], str]:
    freqs = (100.0,) if quick else (100.0, 200.0)
    runs: dict[tuple[str, float], Any] = {}
    commands = []
    for f in freqs:
        for mode in FEEDFORWARD_MODES:
            args = ['--trajectory', 'sine', '--frequency', f'{f:g}', '--duration', '2',
                    '--feedforward', mode]
            commands.append('simulate ' + ' '.join(args) + ' --json')
            runs[(mode, f)] = run_json('simulate', args)
    return commands, feedforward_section(runs)


def _speed(quick: bool) -> tuple[list[str], str]:
    args = ['--suite', 'sim'] + (['--repeats', '1', '--controller-steps', '20000'] if quick
                                 else [])
    return (['OPENBLAS_NUM_THREADS=1 benchmark ' + ' '.join(args) + ' --json'],
            speed_section(run_json('benchmark', args)))


def _scan(quick: bool) -> tuple[list[str], str]:
    runs = [(case, run_json('simulate', case.args)) for case in SCAN_CASES]
    return ['simulate ' + ' '.join(case.args) + ' --json' for case in SCAN_CASES], \
        scan_section(runs)


STUDIES = (
    Study('table3', 'Table III', _table3),
    Study('feedforward', 'feed-forward', _feedforward),
    Study('speed', 'offline speed', _speed),
    Study('scan', 'lines at any rate', _scan),
)


def _parser() -> argparse.ArgumentParser:
    p = cli.Parser(prog=PROG, description='Run the quick studies and rewrite the generated '
                   'sections of docs/results.md with their figures, commands and machine.')
    p.add_argument('--file', type=Path, default=DEFAULT_FILE,
                   help='The results page (default: docs/results.md of this checkout).')
    p.add_argument('--quick', action='store_true',
                   help='Fewer runs and repeats: the feed-forward at 100 Hz only, the '
                   'benchmark once with fewer controller steps.')
    p.add_argument('--sections', nargs='+', choices=[s.name for s in STUDIES],
                   default=[s.name for s in STUDIES], help='Which sections to rewrite.')
    return p


def _results(args: argparse.Namespace) -> int:
    text = args.file.read_text(encoding='utf-8')
    for study in STUDIES:
        if study.name in args.sections:
            replace_section(text, study.name, '')  # a page without the markers: refused now
            print(f'{PROG}: {study.title} ...', file=sys.stderr, flush=True)
            where = machine()
            commands, table = study.run(args.quick)
            body = (f'Made by `python -m piezo_stage_ros.results'
                    f'{" --quick" if args.quick else ""}` on {where}, with:\n\n'
                    f'{_fenced(commands)}\n\n{table}')
            text = replace_section(text, study.name, body)
            args.file.write_text(text, encoding='utf-8')
    return 0


main = cli.command_main(PROG, _parser, _results, '0 success, 1 a study failed, 2 bad usage')


if __name__ == '__main__':
    sys.exit(main())
