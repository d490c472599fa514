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
Markdown reports: one bag with its figures, or several bags side by side in one table.

The report is a single ``report.md`` next to its PNGs (one sub-directory per bag), so the whole
directory can be viewed on GitHub or converted with pandoc as it is.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
import json
import math
import os
from pathlib import Path
import re

from piezo_stage_ros.analysis.replay import BagAnalysis, format_metric, ordered_keys

__all__ = ['ReportEntry', 'unique_names', 'write_report']

# Figures in the order a reader wants them, with their captions (paper figure in brackets).
_CAPTIONS = {
    'tracking': 'Trajectory tracking, x and x_d versus t (as Fig. 11(a))',
    'error': 'Tracking error x - x_d (as Fig. 11(b)); shaded: the metrics window',
    'io_curves': 'Input-output curves: x versus x_d and x versus v_in (as Fig. 11(c), Fig. 6)',
    'step_zoom': 'Zoom on the largest reference step (as Fig. 10(b))',
    'bode': 'Frequency response estimated from v_in to x (as Fig. 4)',
    'learning_curve': 'Learning curve: e_rms (solid) and e_m (dashed) of each period, measured '
                      'and, for a simulation, of the true position',
    'lines': 'Error over the linear part of each line against the position on it, trace and '
             'retrace, and per pixel when asked',
    'feedforward': 'Feed-forward u_ff (model inverse plus learned table) beside the command, '
                   'over the run and over its last period',
}


@dataclass
class ReportEntry:
    """
    One bag in a report.

    Attributes
    ----------
    analysis : BagAnalysis
        The replayed bag.
    figures : dict of str to Path
        Figure name -> PNG file (inside the report directory).
    label : str
        Column / section name (unique within the report).

    """

    analysis: BagAnalysis
    figures: Mapping[str, Path]
    label: str


def unique_names(paths: Sequence[Path]) -> list[str]:
    """
    Return short, unique, file-system-safe names for bags.

    Parameters
    ----------
    paths : sequence of Path
        Bag paths.

    Returns
    -------
    list of str
        The bag names, with ``_2``, ``_3`` ... added where two bags share a name.

    """
    names: list[str] = []
    for path in paths:
        base = re.sub(r'[^A-Za-z0-9_.-]+', '_', path.name or 'bag').strip('._') or 'bag'
        name, i = base, 2
        while name in names:
            name, i = f'{base}_{i}', i + 1
        names.append(name)
    return names


def _cell(text: str) -> str:
    return text.replace('|', '\\|').replace('\n', ' ')


def _is_error(key: str) -> bool:
    line = key.startswith('line_') and '_e_' in key  # the line figures' errors, not the range
    return (key.startswith(('e_', 'ss_e_')) or line) and key.endswith('_m')


def _metrics_table(entries: Sequence[ReportEntry]) -> list[str]:
    keys: list[str] = []
    for entry in entries:
        keys.extend(k for k in entry.analysis.metrics if k not in keys)
    lines = ['| metric | ' + ' | '.join(_cell(e.label) for e in entries) + ' |',
             '| --- |' + ' ---: |' * len(entries)]
    for key in ordered_keys(keys):
        values = [e.analysis.metrics.get(key) for e in entries]
        cells = [format_metric(key, v) if v is not None else '' for v in values]
        finite = [v for v in values if v is not None and math.isfinite(v)]
        if len(entries) > 1 and _is_error(key) and len(finite) > 1:
            # The smallest tracking error of a row in bold: the comparison at a glance.
            best = min(finite)
            cells = [f'**{c}**' if v == best else c for c, v in zip(cells, values)]
        lines.append(f'| `{key}` | ' + ' | '.join(cells) + ' |')
    return lines


def _run_section(entry: ReportEntry, outdir: Path, heading: str) -> list[str]:
    analysis = entry.analysis
    rec = analysis.record
    lines = [f'{heading} {entry.label}', '',
             f'- bag: `{analysis.path}`',
             f'- {analysis.samples} samples over {analysis.duration_s:.4f} s; '
             f'storage {rec.meta.get("storage")}, namespace `{rec.meta.get("namespace")}`',
             f'- first sample stamp: {analysis.time_origin_s:.9f} s (times below are relative '
             'to it)',
             '- metrics window: ' + ('summarize default' if analysis.steady_state_start_s is None
                                     else f'from {analysis.steady_state_start_s:g} s')]
    lines.extend(f'- note: {note}' for note in analysis.notes)
    lines.append('')
    for name, caption in _CAPTIONS.items():
        file = entry.figures.get(name)
        if file is not None:
            rel = Path(os.path.relpath(file, outdir)).as_posix()
            lines += [f'![{caption}]({rel})', '', f'*{caption}.*', '']
    meta = {k: v for k, v in rec.meta.items() if k not in ('bag', 'alignment')}
    if meta:
        text = json.dumps(meta, indent=2, sort_keys=True, default=str)
        if len(text) > 6000:
            text = text[:6000] + '\n...'
        lines += ['<details><summary>Run description stored in the bag</summary>', '',
                  '```json', text, '```', '', '</details>', '']
    return lines


def write_report(entries: Sequence[ReportEntry], outdir: Path,
                 comparison_figure: Path | None = None) -> Path:
    """
    Write ``report.md`` for one bag, or a comparison of several.

    Parameters
    ----------
    entries : sequence of ReportEntry
        The bags, in the order given on the command line.
    outdir : Path
        Report directory; figures elsewhere are linked by relative path.
    comparison_figure : Path, optional
        Overlay of the tracking errors (several bags).

    Returns
    -------
    Path
        The report file.

    """
    outdir.mkdir(parents=True, exist_ok=True)
    if len(entries) == 1:
        entry = entries[0]
        lines = [f'# Run report: {entry.label}', '', '## Metrics', '']
        lines += _metrics_table(entries) + ['']
        lines += _run_section(entry, outdir, '## Run')
    else:
        lines = [f'# Comparison of {len(entries)} runs', '',
                 'Metrics of each bag, computed by the same function as `simulate` '
                 '(SI values converted to nm, ms, V for reading); the smallest tracking error '
                 'of each row in bold.', '']
        lines += _metrics_table(entries) + ['']
        if comparison_figure is not None:
            rel = Path(os.path.relpath(comparison_figure, outdir)).as_posix()
            lines += [f'![Tracking errors of all runs]({rel})', '',
                      '*Tracking errors of all runs.*', '']
        for entry in entries:
            lines += _run_section(entry, outdir, '##')
    path = outdir / 'report.md'
    path.write_text('\n'.join(lines).rstrip() + '\n', encoding='utf8')
    return path
