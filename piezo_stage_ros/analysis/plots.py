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
PNG figures of a run in the style of the paper's Figs. 4, 10 and 11.

- ``tracking.png``: x and x_d versus t (Fig. 11(a));
- ``error.png``: tracking error x - x_d versus t (Fig. 11(b), Fig. 10(c));
- ``io_curves.png``: x versus x_d and x versus v_in (Fig. 11(c), Fig. 6);
- ``step_zoom.png``: zoom on the largest reference step (Fig. 10(b)), when there is a step;
- ``bode.png``: frequency response estimated from v_in to x (Fig. 4), for noise or sweep runs;
- ``learning_curve.png``: e_rms and e_m of each whole period of a periodic reference
  (:func:`~piezo_stage_ros.core.loop.metrics.per_period_error`), measured and, for a simulation,
  true, with the first period a learning feed-forward updated its table after marked; when the
  run has a period and at least two whole periods;
- ``lines.png``: the error over the linear part of each line against the position on the line,
  trace and retrace apart, and per pixel when pixels are asked
  (:func:`~piezo_stage_ros.core.loop.metrics.line_profile`); for a scan line, or when asked;
- ``feedforward.png``: the feed-forward u_ff (diagnostic ``ff_u_v``) beside the command over the
  run, and over its last whole period; when the run has it;
- ``comparison_error.png``: the tracking errors of several runs over each other.

matplotlib is imported here only, with the non-interactive Agg backend, so nothing needs a display.
Long runs are reduced before drawing (min/max per pixel column for time plots, an even stride for
curves), so a 36 M-sample run draws as fast as a short one and looks the same.
"""

from __future__ import annotations

from collections.abc import Sequence
import math
from pathlib import Path
from typing import Any, Literal

import matplotlib

matplotlib.use('Agg')

from matplotlib.axes import Axes  # noqa: E402 - the backend must be chosen first
from matplotlib.figure import Figure  # noqa: E402
import numpy as np  # noqa: E402
from piezo_stage_ros.analysis.spectral import BodeEstimate  # noqa: E402
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.loop.metrics import (  # noqa: E402
    line_profile,
    LineOptions,
    LineProfile,
    LINES_KEY,
    meta_period,
    per_period_error,
    PeriodErrors,
    steady_state_start,
    window_slice,
)
from piezo_stage_ros.core.loop.record import RunRecord  # noqa: E402

__all__ = [
    'dress',
    'error_trace',
    'find_step',
    'plot_bode',
    'plot_comparison',
    'plot_error',
    'plot_feedforward',
    'plot_io_curves',
    'plot_learning_curve',
    'plot_lines',
    'plot_run',
    'plot_step_zoom',
    'plot_tracking',
]


_DPI = 110
_SIZE = (8.0, 4.5)
# Columns of the min/max envelope of a time plot: more than the figure has pixels.
_ENVELOPE_COLUMNS = 2000
_CURVE_POINTS = 40000


def _envelope(t: FloatArray, y: FloatArray,
              columns: int = _ENVELOPE_COLUMNS) -> tuple[FloatArray, FloatArray]:
    # Min and max of every column, drawn in turn: the plot keeps every peak a full plot has.
    n = t.size
    if n <= 4 * columns:
        return t, y
    per = n // columns
    m = per * columns
    ty = t[:m].reshape(columns, per)
    yy = y[:m].reshape(columns, per)
    lo, hi = np.nanmin(yy, axis=1), np.nanmax(yy, axis=1)
    tt = np.repeat(ty[:, 0], 2)
    out = np.empty(2 * columns)
    out[0::2], out[1::2] = lo, hi
    return np.concatenate([tt, t[m:]]), np.concatenate([out, y[m:]])


def _stride(*arrays: FloatArray, points: int = _CURVE_POINTS) -> list[FloatArray]:
    n = arrays[0].size
    step = max(1, n // points)
    return [a[::step] for a in arrays]


def _new(nrows: int = 1, height: float = _SIZE[1]) -> tuple[Figure, list[Axes]]:
    fig = Figure(figsize=(_SIZE[0], height), dpi=_DPI, layout='constrained')
    axes = [fig.add_subplot(nrows, 1, i + 1) for i in range(nrows)]
    return fig, axes


def _save(fig: Figure, path: Path) -> Path:
    # The layout needs the labels, not the data: measuring tens of thousands of line points
    # for it doubled the drawing time.
    for ax in fig.axes:
        for line in ax.lines:
            line.set_in_layout(False)
    fig.savefig(path)
    return path


def _relative_time(record: RunRecord) -> FloatArray:
    t = np.asarray(record.time_s, dtype=np.float64)
    return t - t[0] if t.size else t


def dress(ax: Axes, xlabel: str | None = None, ylabel: str | None = None, *,
          legend: str | None = None, which: Literal['major', 'both'] = 'major',
          **legend_options: Any) -> None:
    """
    Label an axis, draw its grid and, when asked, its legend: the finish all figures share.

    Parameters
    ----------
    ax : Axes
        The axis, its curves drawn (the legend collects them).
    xlabel, ylabel : str, optional
        Axis labels; None leaves a label unset.
    legend : str, optional
        Where the legend goes (a matplotlib ``loc``); None draws none.
    which : str
        Grid lines: ``'major'``, or ``'both'`` for a logarithmic axis.
    **legend_options
        More arguments of ``Axes.legend`` (e.g. ``fontsize``).

    """
    if xlabel is not None:
        ax.set_xlabel(xlabel)
    if ylabel is not None:
        ax.set_ylabel(ylabel)
    ax.grid(True, which=which, alpha=0.3)
    if legend is not None:
        ax.legend(**{'loc': legend, **legend_options})


def plot_tracking(record: RunRecord, path: Path, title: str = '') -> Path:
    """
    Draw x and x_d versus time (paper Fig. 11(a)).

    Parameters
    ----------
    record : RunRecord
        The run.
    path : Path
        PNG file to write.
    title : str
        Figure title (e.g. the bag name); empty: 'Trajectory tracking'.

    Returns
    -------
    Path
        ``path``.

    """
    fig, (ax,) = _new()
    t = _relative_time(record)
    ax.plot(*_envelope(t, record.reference_m * 1e6), color='tab:blue', lw=1.2,
            label='desired $x_d$')
    ax.plot(*_envelope(t, record.position_m * 1e6), color='tab:red', lw=0.8,
            label='measured $x$')
    ax.set_title(title or 'Trajectory tracking')
    dress(ax, 'time [s]', 'position [µm]', legend='upper right')
    return _save(fig, path)


def plot_error(record: RunRecord, path: Path, title: str = '',
               steady_state_start_s: float | None = None) -> Path:
    """
    Draw the tracking error x - x_d versus time in nanometres (paper Fig. 11(b)).

    Parameters
    ----------
    record : RunRecord
        The run.
    path : Path
        PNG file to write.
    title : str
        Figure title; empty: 'Tracking error'.
    steady_state_start_s : float, optional
        Start of the window the metrics use, relative to the first sample [s]; shaded.

    Returns
    -------
    Path
        ``path``.

    """
    fig, (ax,) = _new()
    t = _relative_time(record)
    ax.plot(*_envelope(t, record.error_m * 1e9), color='tab:red', lw=0.8)
    legend = None
    if steady_state_start_s is not None and t.size:
        ax.axvspan(steady_state_start_s, t[-1], color='0.9', zorder=0,
                   label='metrics window')
        legend = 'upper right'
    ax.set_title(title or 'Tracking error')
    dress(ax, 'time [s]', 'error $x - x_d$ [nm]', legend=legend)
    return _save(fig, path)


def plot_io_curves(record: RunRecord, path: Path, title: str = '') -> Path:
    """
    Draw x versus x_d and x versus v_in side by side (paper Fig. 11(c) and Fig. 6).

    Parameters
    ----------
    record : RunRecord
        The run.
    path : Path
        PNG file to write.
    title : str
        Figure title above both plots; empty: none.

    Returns
    -------
    Path
        ``path``.

    """
    fig = Figure(figsize=(_SIZE[0], 4.0), dpi=_DPI, layout='constrained')
    left, right = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    x, xd, v = _stride(record.position_m * 1e6, record.reference_m * 1e6, record.command_v)
    left.plot(xd, x, color='tab:red', lw=0.7)
    lo, hi = float(np.nanmin(xd)), float(np.nanmax(xd))
    left.plot([lo, hi], [lo, hi], color='0.5', lw=0.8, ls='--', label='$x = x_d$')
    left.set_title('closed loop: $x$ vs $x_d$')
    dress(left, 'desired position $x_d$ [µm]', 'measured position $x$ [µm]',
          legend='upper left')
    right.plot(v, x, color='tab:blue', lw=0.7)
    right.set_title('plant: $x$ vs $v_{in}$')
    dress(right, 'amplifier input $v_{in}$ [V]', 'measured position $x$ [µm]')
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def find_step(record: RunRecord) -> int | None:
    """
    Find the largest step of the reference, if the reference has steps.

    A step is a jump of x_d between two samples that is larger than 1 % of the reference's
    range and more than 20 times the median sample-to-sample change (a sine at 100 Hz sampled
    at 10 kHz changes by at most 6 % of its range per sample, but evenly, so the median rule
    keeps it out).

    Parameters
    ----------
    record : RunRecord
        The run.

    Returns
    -------
    int or None
        Index of the first sample after the largest jump, or None.

    """
    xd = np.asarray(record.reference_m, dtype=np.float64)
    if xd.size < 3:
        return None
    jumps = np.abs(np.diff(xd))
    span = float(np.nanmax(xd) - np.nanmin(xd))
    if span <= 0.0:
        return None
    k = int(np.nanargmax(jumps))
    if jumps[k] < 0.01 * span or jumps[k] <= 20.0 * float(np.nanmedian(jumps)):
        return None
    return k + 1


def plot_step_zoom(record: RunRecord, path: Path, title: str = '',
                   window_s: float = 0.03) -> Path | None:
    """
    Zoom on the largest reference step (paper Fig. 10(b)); nothing when there is no step.

    Parameters
    ----------
    record : RunRecord
        The run.
    path : Path
        PNG file to write.
    title : str
        Figure title; empty: 'Step at t = ...'.
    window_s : float
        Time shown after the step [s] (10 % of it is shown before).

    Returns
    -------
    Path or None
        ``path``, or None when the reference has no step.

    """
    k = find_step(record)
    if k is None:
        return None
    t = _relative_time(record)
    t0 = t[k]
    sel = (t >= t0 - 0.1 * window_s) & (t <= t0 + window_s)
    fig, (ax, ax_v) = _new(2, height=5.5)
    tm = (t[sel] - t0) * 1e3
    ax.plot(tm, record.reference_m[sel] * 1e6, color='tab:blue', lw=1.2, label='desired $x_d$')
    ax.plot(tm, record.position_m[sel] * 1e6, color='tab:red', lw=0.9, label='measured $x$')
    ax.set_title(title or f'Step at t = {t0:.4f} s')
    dress(ax, None, 'position [µm]', legend='lower right')
    ax_v.plot(tm, record.command_v[sel], color='tab:green', lw=0.9)
    dress(ax_v, 'time after the step [ms]', '$v_{in}$ [V]')
    return _save(fig, path)


def plot_bode(estimate: BodeEstimate, path: Path, title: str = '') -> Path:
    """
    Draw an estimated frequency response, magnitude and phase (paper Fig. 4).

    Parameters
    ----------
    estimate : BodeEstimate
        Estimate from :func:`piezo_stage_ros.analysis.spectral.estimate_bode`.
    path : Path
        PNG file to write.
    title : str
        Figure title; empty: 'Frequency response estimate' and the estimate's label.

    Returns
    -------
    Path
        ``path``.

    """
    fig, (ax_m, ax_p) = _new(2, height=6.0)
    f = estimate.frequency_hz
    good = estimate.coherence >= 0.8
    if good.any():
        # Above a band-limited excitation the estimate is noise: show a little of it, no more.
        keep = f <= 1.25 * float(f[good].max())
        f, response, good = f[keep], estimate.response[keep], good[keep]
    else:
        response = estimate.response
    mag_db = 20.0 * np.log10(np.maximum(np.abs(response), 1e-30) * estimate.scale)
    phase = np.degrees(np.unwrap(np.angle(response)))
    ax_m.semilogx(f, mag_db, color='0.7', lw=0.8, label='coherence < 0.8')
    ax_m.semilogx(f[good], mag_db[good], '.', color='tab:blue', ms=2.5, label='coherence >= 0.8')
    dress(ax_m, None, f'magnitude [dB re 1 {estimate.unit}]', legend='lower left',
          which='both')
    ax_p.semilogx(f, phase, color='0.7', lw=0.8)
    ax_p.semilogx(f[good], phase[good], '.', color='tab:blue', ms=2.5)
    dress(ax_p, 'frequency [Hz]', 'phase [deg]', which='both')
    if good.any():
        for ax, values in ((ax_m, mag_db), (ax_p, phase)):
            lo, hi = float(values[good].min()), float(values[good].max())
            pad = 0.15 * max(hi - lo, 10.0)
            ax.set_ylim(lo - pad, hi + pad)
    ax_m.set_title(title or f'Frequency response estimate: {estimate.label}')
    return _save(fig, path)


def plot_learning_curve(rows: PeriodErrors, path: Path, title: str = '',
                        first_update: int | None = None) -> Path:
    """
    Draw e_rms and e_m of every period against the period number (the learning curve).

    Parameters
    ----------
    rows : PeriodErrors
        :func:`~piezo_stage_ros.core.loop.metrics.per_period_error` of the run.
    path : Path
        PNG file to write.
    title : str
        Figure title; empty: 'Learning curve: error per period'.
    first_update : int, optional
        The period at whose end a learning feed-forward first updated its table (a dotted
        line).

    Returns
    -------
    Path
        ``path``.

    """
    fig, (ax,) = _new()
    index = np.arange(len(rows), dtype=np.float64)
    curves = [(rows.e_rms_m, rows.e_max_m, 'tab:red', 'measured')]
    if rows.e_rms_true_m is not None and rows.e_max_true_m is not None:
        curves.append((rows.e_rms_true_m, rows.e_max_true_m, 'tab:blue', 'true position'))
    for rms, top, color, label in curves:
        ax.plot(*_stride(index, rms * 1e9), color=color, lw=1.2, label=f'{label}: $e_{{rms}}$')
        ax.plot(*_stride(index, top * 1e9), color=color, lw=0.8, ls='--',
                label=f'{label}: $e_m$')
    finite = np.concatenate([c[0] for c in curves] + [c[1] for c in curves])
    finite = finite[np.isfinite(finite) & (finite > 0)]
    if finite.size:
        ax.set_yscale('log')
    if first_update is not None:
        ax.axvline(first_update + 0.5, color='0.4', ls=':', lw=1.0,
                   label=f'first table update (end of period {first_update})')
    ax.set_title(title or 'Learning curve: error per period')
    dress(ax, f'period (of {rows.period_s * 1e3:g} ms)', 'error per period [nm]',
          legend='upper right', which='both')
    return _save(fig, path)


def plot_lines(profile: LineProfile, path: Path, title: str = '') -> Path:
    """
    Draw the error along the linear part of the lines, trace and retrace, and per pixel.

    Parameters
    ----------
    profile : LineProfile
        :func:`~piezo_stage_ros.core.loop.metrics.line_profile` of the run's window.
    path : Path
        PNG file to write.
    title : str
        Figure title; empty: 'Error over the linear part of each line'.

    Returns
    -------
    Path
        ``path``.

    """
    pixels = profile.pixel_centre_m.size
    fig, axes = _new(2 if pixels else 1, _SIZE[1] * (1.6 if pixels else 1.0))
    which = 'true position' if profile.true else 'measured'
    ax = axes[0]
    for pos, err, color, label in (
            (profile.trace_position_m, profile.trace_error_m, 'tab:blue', 'trace'),
            (profile.retrace_position_m, profile.retrace_error_m, 'tab:orange', 'retrace')):
        if pos.size:
            xs, ys = _stride(pos * 1e6, err * 1e9)
            ax.plot(xs, ys, '.', ms=1.5, color=color, alpha=0.5,
                    label=f'{label} ({pos.size} samples)')
    ax.set_xlim(profile.low_m * 1e6, profile.high_m * 1e6)
    ax.set_title(title or 'Error over the linear part of each line')
    dress(ax, 'x_d along the line [µm]', f'error, {which} [nm]', legend='upper right',
          markerscale=6)
    if pixels:
        ax = axes[1]
        index = np.arange(pixels, dtype=np.float64)
        for image, color, label in ((profile.trace_pixels_m, 'tab:blue', 'trace'),
                                    (profile.retrace_pixels_m, 'tab:orange', 'retrace')):
            if not image.size or not np.isfinite(image).any():
                continue
            with np.errstate(invalid='ignore'):
                finite = np.isfinite(image).any(axis=0)
                mean = np.full(pixels, np.nan)
                low = np.full(pixels, np.nan)
                high = np.full(pixels, np.nan)
                mean[finite] = np.nanmean(image[:, finite], axis=0)
                low[finite] = np.nanmin(image[:, finite], axis=0)
                high[finite] = np.nanmax(image[:, finite], axis=0)
            ax.plot(index, mean * 1e9, color=color, lw=1.2,
                    label=f'{label}: mean over {image.shape[0]} lines')
            ax.fill_between(index, low * 1e9, high * 1e9, color=color, alpha=0.2,
                            label=f'{label}: lowest to highest line')
        size_nm = (profile.high_m - profile.low_m) * 1e9 / pixels
        dress(ax, f'pixel (of {pixels}, {size_nm:.4g} nm each)', f'pixel error, {which} [nm]',
              legend='upper right')
    return _save(fig, path)


#: The diagnostics of a feed-forward a figure reads (core/control/feedforward.py).
FEEDFORWARD_DIAGNOSTIC = 'ff_u_v'
PERIODS_LEARNED_DIAGNOSTIC = 'ff_periods_learned'


def first_update_period(record: RunRecord, period_s: float) -> int | None:
    """
    Return the period at whose end a learning feed-forward first updated its table.

    Parameters
    ----------
    record : RunRecord
        The run; its diagnostic ``ff_periods_learned`` counts the updates.
    period_s : float
        The reference period [s].

    Returns
    -------
    int or None
        j, counted from 0 at the first sample; None without the diagnostic or an update.

    """
    learned = record.diagnostics.get(PERIODS_LEARNED_DIAGNOSTIC)
    if learned is None:
        return None
    after = np.flatnonzero(np.asarray(learned) > 0.0)
    if after.size == 0:
        return None
    t = _relative_time(record)
    dt = float(t[1] - t[0]) if t.size > 1 else 0.0
    # the update is at the last sample of period j, t = (j + 1) P - T; diagnostics read every
    # m <= P / T samples show it first before (j + 2) P - T, which gives the same j
    return max(int(math.floor((t[after[0]] + dt) / period_s + 1e-9)) - 1, 0)


def plot_feedforward(record: RunRecord, path: Path, title: str = '') -> Path | None:
    """
    Draw the feed-forward u_ff beside the command: over the run, and over its last period.

    Parameters
    ----------
    record : RunRecord
        The run; nothing is drawn without the diagnostic ``ff_u_v``.
    path : Path
        PNG file to write.
    title : str
        Figure title; empty: 'Feed-forward and command'.

    Returns
    -------
    Path or None
        ``path``, or None when the run has no feed-forward signal.

    """
    u_ff = record.diagnostics.get(FEEDFORWARD_DIAGNOSTIC)
    if u_ff is None or not len(u_ff):
        return None
    fig, (ax, ax_p) = _new(2, height=1.6 * _SIZE[1])
    t = _relative_time(record)
    ax.plot(*_envelope(t, record.command_v), color='0.6', lw=0.8, label='command $v$')
    ax.plot(*_envelope(t, u_ff), color='tab:green', lw=0.8, label='feed-forward $u_{ff}$')
    ax.set_title(title or 'Feed-forward and command')
    dress(ax, 'time [s]', '[V]', legend='upper right')
    period = meta_period(record.meta)
    dt = float(t[1] - t[0]) if t.size > 1 else 0.0
    n = int(round(period / dt)) if period is not None and dt > 0.0 else 0
    if n and t.size >= n:
        last = slice(t.size - n, t.size)
        phase = (t[last] - t[last][0]) * 1e3
        ax_p.plot(phase, record.command_v[last], color='0.6', lw=1.0, label='command $v$')
        ax_p.plot(phase, u_ff[last], color='tab:green', lw=1.2, label='$u_{ff}$')
        xlabel = 'time in the last period [ms]'
    else:
        tail = slice(max(t.size - 1000, 0), t.size)
        ax_p.plot(t[tail], record.command_v[tail], color='0.6', lw=1.0, label='command $v$')
        ax_p.plot(t[tail], u_ff[tail], color='tab:green', lw=1.2, label='$u_{ff}$')
        xlabel = 'time [s] (last 1000 samples)'
    dress(ax_p, xlabel, '[V]', legend='upper right')
    return _save(fig, path)


def error_trace(record: RunRecord) -> tuple[FloatArray, FloatArray]:
    """
    Return the tracking error reduced for drawing: time from the first sample [s], error [m].

    Parameters
    ----------
    record : RunRecord
        The run.

    Returns
    -------
    (ndarray, ndarray)
        Min/max envelope of x - x_d, small enough to keep for a comparison of many runs.

    """
    return _envelope(_relative_time(record), record.error_m)


def plot_comparison(traces: Sequence[tuple[FloatArray, FloatArray]], labels: Sequence[str],
                    path: Path) -> Path:
    """
    Draw the tracking errors of several runs over each other.

    Parameters
    ----------
    traces : sequence of (ndarray, ndarray)
        Per run, time [s] and error [m] from :func:`error_trace`.
    labels : sequence of str
        One legend label per run.
    path : Path
        PNG file to write.

    Returns
    -------
    Path
        ``path``.

    """
    fig, (ax,) = _new()
    for (t, err), label in zip(traces, labels):
        ax.plot(t, err * 1e9, lw=0.8, label=label)
    ax.set_title('Tracking error, run by run')
    dress(ax, 'time [s]', 'error $x - x_d$ [nm]', legend='upper right')
    return _save(fig, path)


def plot_run(record: RunRecord, outdir: Path, *, title: str = '',
             steady_state_start_s: float | None = None,
             bode: BodeEstimate | None = None,
             lines: LineOptions | None = None) -> dict[str, Path]:
    """
    Draw every figure of one run into a directory.

    Parameters
    ----------
    record : RunRecord
        The run, times relative to its start [s].
    outdir : Path
        Directory for the PNGs (created if needed).
    title : str
        Prefix of the figure titles (e.g. the bag name).
    steady_state_start_s : float, optional
        Start of the metrics window [s], shaded on the error plot.
    bode : BodeEstimate, optional
        Frequency-response estimate to draw.
    lines : LineOptions, optional
        Draw the error over the linear part of the lines (middle fraction, pixels); a scan
        line's run draws it without asking.

    Returns
    -------
    dict of str to Path
        Figure name (``tracking``, ``error``, ``io_curves``, ``step_zoom``, ``bode``,
        ``learning_curve``, ``lines``, ``feedforward``) -> file; ``lines`` for a scan line or
        when asked; ``step_zoom`` only when the reference has
        a step, ``bode`` only with an estimate, ``learning_curve`` only when ``record.meta``
        gives the reference period and the run holds at least two whole periods,
        ``feedforward`` only when the run records the feed-forward (``ff_u_v``).

    """
    outdir.mkdir(parents=True, exist_ok=True)
    prefix = f'{title}: ' if title else ''
    files = {
        'tracking': plot_tracking(record, outdir / 'tracking.png', prefix + 'trajectory tracking'),
        'error': plot_error(record, outdir / 'error.png', prefix + 'tracking error',
                            steady_state_start_s),
        'io_curves': plot_io_curves(record, outdir / 'io_curves.png',
                                    prefix + 'input-output curves'),
    }
    step = find_step(record)
    zoom_title = '' if step is None else (
        f'{prefix}step at t = {float(_relative_time(record)[step]):.4f} s')
    zoom = plot_step_zoom(record, outdir / 'step_zoom.png', zoom_title)
    if zoom is not None:
        files['step_zoom'] = zoom
    if bode is not None:
        files['bode'] = plot_bode(bode, outdir / 'bode.png', prefix + f'frequency response '
                                  f'estimate ({bode.label})')
    period = meta_period(record.meta)
    if period is not None:
        rows = per_period_error(record, period)
        if len(rows) >= 2:
            files['learning_curve'] = plot_learning_curve(
                rows, outdir / 'learning_curve.png', prefix + 'learning curve: error per period',
                first_update_period(record, period))
    if lines is not None or LINES_KEY in record.meta:
        t = np.asarray(record.time_s, dtype=np.float64)
        if t.size:
            start = (steady_state_start(t, period) if steady_state_start_s is None
                     else float(t[0]) + steady_state_start_s)
            profile = line_profile(record, window_slice(t, start, period), lines)
            files['lines'] = plot_lines(profile, outdir / 'lines.png',
                                        prefix + 'error over the linear part of each line')
    ff = plot_feedforward(record, outdir / 'feedforward.png', prefix + 'feed-forward')
    if ff is not None:
        files['feedforward'] = ff
    return files
