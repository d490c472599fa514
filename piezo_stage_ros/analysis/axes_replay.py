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
Replay of a multi-axis bag: per-axis metrics, the raster frame's distortion, a summary.

The figures are those ``simulate_axes`` prints for the run, from the same function
(:func:`~piezo_stage_ros.core.loop.axes.run_metrics`) over the same window, measured as the
run's description in the bag says: the last ``window_s`` seconds, a raster's fast axis over
the middle of its lines. A bag without a description (recorded from a graph) is measured over
its last second, every axis over all samples, with a note.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
import math
from pathlib import Path
from typing import Any

import numpy as np
from piezo_stage_ros.analysis.bagread import ProgressCallback, read_axes
from piezo_stage_ros.core.contracts.errors import PiezoStageError
from piezo_stage_ros.core.loop.axes import (
    grating_image,
    GratingImage,
    LINE_FRACTION,
    run_metrics,
)
from piezo_stage_ros.core.loop.record import RunRecord

__all__ = ['AxesAnalysis', 'analyze_axes_bag', 'axes_summary_json', 'format_axes_summary',
           'open_loop_summary', 'OpenLoopAxis']

#: Pitch of the synthetic grating imaged over a raster frame [m].
GRATING_PITCH_M = 1e-6


@dataclass(frozen=True)
class OpenLoopAxis:
    """
    What one axis of an open-loop run did over the window: no reference, so no error.

    Attributes
    ----------
    command_mean_v, command_rms_v : float
        The command's mean and its rms about the mean [V].
    position_mean_m, position_rms_m, position_peak_to_peak_m : float
        The measured position's mean, rms about the mean and peak to peak [m].
    excited : bool
        Whether the command varies (the axis driven; the others hold a constant command).

    """

    command_mean_v: float
    command_rms_v: float
    position_mean_m: float
    position_rms_m: float
    position_peak_to_peak_m: float
    excited: bool


def open_loop_summary(records: list[RunRecord], window_s: float
                      ) -> dict[str, OpenLoopAxis] | None:
    """
    Return each axis' excitation and response over the last ``window_s`` of an open-loop run.

    Parameters
    ----------
    records : list of RunRecord
        One per axis (``meta['axis']``).
    window_s : float
        Window length at the end of the run [s].

    Returns
    -------
    dict of str to OpenLoopAxis, or None
        Per axis name; None when any axis has a reference (a closed-loop run, measured by its
        error instead).

    """
    if not records or not all(np.all(np.isnan(r.reference_m)) for r in records):
        return None
    out = {}
    for rec in records:
        n = len(rec)
        dt = float(rec.meta.get('sample_time_s', 0.0)) or (
            float(rec.time_s[1] - rec.time_s[0]) if n > 1 else 1.0)
        first = max(n - int(round(window_s / dt)), 0)
        u = np.asarray(rec.command_v[first:], dtype=np.float64)
        y = np.asarray(rec.position_m[first:], dtype=np.float64)
        y = y[np.isfinite(y)]
        # about the first sample, so that a constant signal has exactly zero spread
        u, u0 = (u - u[0], float(u[0])) if u.size else (u, 0.0)
        y, y0 = (y - y[0], float(y[0])) if y.size else (y, 0.0)
        out[str(rec.meta.get('axis', ''))] = OpenLoopAxis(
            command_mean_v=u0 + float(np.mean(u)), command_rms_v=float(np.std(u)),
            position_mean_m=y0 + float(np.mean(y)) if y.size else math.nan,
            position_rms_m=float(np.std(y)) if y.size else math.nan,
            position_peak_to_peak_m=float(np.ptp(y)) if y.size else math.nan,
            excited=bool(np.ptp(u) > 0.0) if u.size else False)
    return out


@dataclass
class AxesAnalysis:
    """
    The result of replaying one multi-axis bag.

    Attributes
    ----------
    path : Path
        The bag.
    records : list of RunRecord
        One per axis, in the stage's axis order, times from the first sample.
    metrics : dict
        Per axis: ``e_rms_m``, ``e_max_m``, ``e_rms_true_m``, ``e_max_true_m``, ``samples``,
        ``window`` (as ``simulate_axes --json`` names them).
    window_s : float
        The window at the end of the run the metrics are over [s].
    fast_axis, slow_axis : str or None
        A raster's axes (None for other scans or without a description).
    lines : int or None
        A raster's lines per frame.
    grating : GratingImage or None
        The grating imaged over the last whole frame of a raster.
    notes : list of str
        What a reader should know (no description, no whole frame ...).
    open_loop : dict of str to OpenLoopAxis, or None
        An open-loop run (no reference on any axis, e.g. a coupling run of ``identify_axes``):
        what each axis was driven with and how it moved, in place of the error.

    """

    path: Path
    records: list[RunRecord]
    metrics: dict[str, dict[str, Any]]
    window_s: float
    fast_axis: str | None = None
    slow_axis: str | None = None
    lines: int | None = None
    grating: GratingImage | None = None
    notes: list[str] = field(default_factory=list)
    open_loop: dict[str, OpenLoopAxis] | None = None

    @property
    def name(self) -> str:
        """Short name of the bag (its directory or file name)."""
        return self.path.name or str(self.path)


def analyze_axes_bag(path: str | Path, *, namespace: str | None = None,
                     window_s: float | None = None, progress: ProgressCallback | None = None,
                     grating_pitch_m: float = GRATING_PITCH_M) -> AxesAnalysis:
    """
    Read a multi-axis bag and compute its per-axis metrics and a raster frame's distortion.

    Parameters
    ----------
    path : path-like
        The bag.
    namespace : str, optional
        Topic namespace; found from the bag when it holds one stage.
    window_s : float, optional
        Metrics over the last this many seconds; default the run's own (``window_s`` of its
        description), else the last second (the whole run when shorter).
    progress : callable, optional
        ``progress(messages_read, messages_total)`` while reading.
    grating_pitch_m : float
        Pitch of the grating imaged over the last whole raster frame [m].

    Returns
    -------
    AxesAnalysis

    Raises
    ------
    BagError
        The bag cannot be read (:func:`~piezo_stage_ros.analysis.bagread.read_axes`).
    PiezoStageError
        A window outside the run.

    """
    records = read_axes(path, namespace=namespace, progress=progress, relative_time=True)
    meta = records[0].meta
    notes: list[str] = []
    span = float(records[0].time_s[-1] - records[0].time_s[0]) if len(records[0]) else 0.0
    dt = meta.get('sample_time_s')
    duration = span + (float(dt) if isinstance(dt, (int, float)) else 0.0)
    if window_s is None:
        stored = meta.get('window_s')
        window_s = float(stored) if isinstance(stored, (int, float)) else min(1.0, duration)
    if not (0.0 < window_s and math.isfinite(window_s)):
        raise PiezoStageError(f'window {window_s!r} s is out of range; allowed: (0, '
                              f'{duration:g}] s (the run)')
    if window_s > duration:
        notes.append(f'window of {window_s:g} s longer than the run ({duration:g} s): the '
                     'metrics are over the whole run')
    scan = meta.get('scan')
    raster = scan == 'raster'
    fast = str(meta['fast_axis']) if raster and meta.get('fast_axis') else None
    slow = str(meta['slow_axis']) if raster and meta.get('slow_axis') else None
    lines = int(meta['lines']) if raster and isinstance(meta.get('lines'), int) else None
    open_loop = open_loop_summary(records, float(window_s))
    if scan is None and open_loop is None:
        notes.append('no run description in the bag: every axis measured over all samples of '
                     'the window (no raster fast axis known)')
    fraction = meta.get('line_fraction', LINE_FRACTION)
    fraction = float(fraction) if isinstance(fraction, (int, float)) else LINE_FRACTION
    measured = run_metrics(records, window_s=window_s, fast_axis=fast, fraction=fraction)
    metrics = {name: {'e_rms_m': m.e_rms_m, 'e_max_m': m.e_max_m,
                      'e_rms_true_m': m.e_rms_true_m, 'e_max_true_m': m.e_max_true_m,
                      'samples': m.samples,
                      'window': (f'middle {100.0 * fraction:g} % of the lines'
                                 if name == fast else 'all')}
               for name, m in measured.items()}
    grating = None
    by_name = {str(r.meta['axis']): r for r in records}
    if fast in by_name and slow in by_name and lines is not None:
        try:
            grating = grating_image(by_name[fast], by_name[slow], lines=lines,
                                    pitch_m=grating_pitch_m, fraction=fraction)
        except PiezoStageError as err:
            notes.append(f'no grating image: {err}')
    return AxesAnalysis(Path(path), records, metrics, float(window_s), fast, slow, lines,
                        grating, notes, open_loop)


def axes_summary_json(analysis: AxesAnalysis) -> dict[str, Any]:
    """Return the analysis as one JSON object (``simulate_axes --json``'s ``axes`` field)."""
    meta = analysis.records[0].meta
    out: dict[str, Any] = {
        'bag': str(analysis.path), 'axes': {k: _clean(v) for k, v in analysis.metrics.items()},
        'scan': meta.get('scan'), 'window_s': analysis.window_s,
        'samples': len(analysis.records[0]), 'fast_axis': analysis.fast_axis,
        'slow_axis': analysis.slow_axis, 'lines': analysis.lines, 'notes': analysis.notes}
    if analysis.open_loop is not None:
        out['open_loop'] = {
            'experiment': meta.get('experiment'),
            'excited': [k for k, v in analysis.open_loop.items() if v.excited],
            'axes': {k: {f.name: _finite(getattr(v, f.name)) if f.type == 'float'
                         else getattr(v, f.name) for f in fields(v)}
                     for k, v in analysis.open_loop.items()}}
    g = analysis.grating
    if g is not None:
        out['grating'] = {'pitch_m': g.pitch_m, 'source': g.source,
                          'shift_x_rms_trace_m': _finite(g.rms_x_m[0]),
                          'shift_x_rms_retrace_m': _finite(g.rms_x_m[1]),
                          'shift_y_rms_trace_m': _finite(g.rms_y_m[0]),
                          'shift_y_rms_retrace_m': _finite(g.rms_y_m[1])}
    return out


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _clean(axis: dict[str, Any]) -> dict[str, Any]:
    return {k: _finite(v) if isinstance(v, float) else v for k, v in axis.items()}


def format_axes_summary(analysis: AxesAnalysis) -> str:
    """Return the readable summary of a multi-axis bag, one line per axis."""
    rec = analysis.records[0]
    meta = rec.meta
    out = [f'{analysis.name}: {len(rec)} samples, {len(analysis.records)} axes '
           f'({", ".join(str(r.meta["axis"]) for r in analysis.records)}), scan '
           f'{meta.get("scan", "unknown")}, storage {meta.get("storage")}',
           f'last {analysis.window_s:g} s:']
    if analysis.open_loop is not None:
        return '\n'.join(out[:1] + _open_loop_lines(analysis, str(meta.get('experiment', '')))
                         + [f'note: {n}' for n in analysis.notes])
    for name, m in analysis.metrics.items():
        out.append(f'  {name} ({m["window"]}): e_rms = {m["e_rms_m"] * 1e9:.2f} nm, e_m = '
                   f'{m["e_max_m"] * 1e9:.2f} nm; true position: e_rms = '
                   f'{m["e_rms_true_m"] * 1e9:.2f} nm, e_m = {m["e_max_true_m"] * 1e9:.2f} nm')
    g = analysis.grating
    if g is not None:
        out.append(f'grating of {g.pitch_m * 1e6:g} um pitch imaged over the last frame (tip at '
                   f'the {g.source} position): lines displaced by {g.rms_x_m[0] * 1e9:.2f} nm '
                   f'rms along {analysis.fast_axis} on the trace, {g.rms_x_m[1] * 1e9:.2f} nm '
                   f'on the retrace; rows by {g.rms_y_m[0] * 1e9:.2f} / '
                   f'{g.rms_y_m[1] * 1e9:.2f} nm rms along {analysis.slow_axis}')
    out += [f'note: {n}' for n in analysis.notes]
    return '\n'.join(out)


def _open_loop_lines(analysis: AxesAnalysis, experiment: str) -> list[str]:
    runs = analysis.open_loop or {}
    excited = [k for k, v in runs.items() if v.excited]
    source = runs[excited[0]] if len(excited) == 1 else None
    out = [f'no reference: open-loop run{f" ({experiment})" if experiment else ""}, no '
           'tracking error; ' + (f'{", ".join(excited)} excited' if excited else
                                 'no axis excited (every command constant)'),
           f'last {analysis.window_s:g} s:']
    for name, a in runs.items():
        drive = (f'command {a.command_mean_v:.4g} V mean, {a.command_rms_v:.4g} V rms about it'
                 if a.excited else f'command {a.command_mean_v:.4g} V, constant')
        line = (f'  {name} ({"excited" if a.excited else "held"}): {drive}; position '
                f'{a.position_mean_m * 1e6:.4g} um mean, {a.position_rms_m * 1e9:.4g} nm rms '
                f'about it, {a.position_peak_to_peak_m * 1e9:.4g} nm peak to peak')
        if source is not None and not a.excited and source.position_rms_m > 0.0:
            line += (f' ({100.0 * a.position_rms_m / source.position_rms_m:.3g} % of '
                     f"{excited[0]}'s rms; the coupling per path: identify_axes --from-bags)")
        out.append(line)
    return out
