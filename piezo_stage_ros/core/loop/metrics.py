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
Performance metrics of a run: the paper's e_m and e_rms, loop width, step-response figures.

Definitions (section V of the paper and this package's choices, stated once here):

- (D1) e_m = max |x - x_d| and (D2) e_rms = sqrt(mean (x - x_d)^2), over the samples of a
  window; x is the *measured* position y_k (what the paper's dSPACE saw), x_d = x_d(t_k).
- **True-position error**: a simulated run also records the true position x(t_k) behind y_k
  (before sensor noise and ADC); e_m and e_rms of x(t_k) - x_d(t_k) over the same window are
  ``e_max_true_m`` and ``e_rms_true_m`` (absent, None, when the run has no true position): with
  sensor noise the measured error cannot show nanometre tracking, the true one can.
- **Steady-state window** (:func:`steady_state_start`): for a periodic reference of period P,
  the first ``TRANSIENT_PERIODS`` periods or ``TRANSIENT_S`` seconds, whichever is longer,
  rounded *up* to a whole number of periods, are skipped, and the window is the whole periods
  that follow (a trailing partial period is dropped, so a sine's error is averaged over whole
  cycles). If the run holds no whole period after the transient, the window is the last whole
  period of the run (or the whole run when it is shorter than one period). A reference without a
  period (step, staircase, table) uses the whole run unless the caller gives a start.
- **Loop width** (:func:`loop_width`): the largest vertical distance between the ascending and
  the descending branch of y plotted against x, in % of the range of y. Each monotone piece of x
  is interpolated onto one grid of x levels; the branches are the mean over the ascending and
  the descending pieces at each level (so cycle-to-cycle jitter and quantization average out).
- **Per-period error** (:func:`per_period_error`, the learning curve of a periodic reference):
  e_rms and e_m of each whole period counted from the first sample, period j being the samples
  with t_0 + j P <= t_k < t_0 + (j + 1) P (half a sample of tolerance); a trailing partial
  period is dropped.
- **Line figures** (:func:`line_metrics`, raster lines and triangles): e_m and e_rms over the
  samples of the linear part of each line in the steady-state window, trace (x_d rising) and
  retrace apart: the samples whose reference speed is the line speed (to 1e-9) and whose x_d lies
  in the centred ``middle_fraction`` of the linear range; at ``pixels`` equal pixels over that
  range, each line's error per pixel (the mean of its samples, or interpolated at its centre
  when a line has fewer samples than pixels), rms and largest over every pixel of every line.
- **Holes in the time grid** (a run recorded in real time skips samples): the sample step is
  the median spacing (:func:`grid_step`) and windows and periods are counted on the grid, each
  over the samples present; a run without holes keeps the mean spacing, as it always did.
- **Step response** (:func:`step_response`): rise time 10-90 % of the step, overshoot in % of
  the step, settling time into a band of ``max(2 % of the step, settle_band_m)`` that the
  response never leaves again, steady-state e_m and e_rms over the last ``plateau_fraction`` of
  the plateau.

Every function takes arrays and returns plain floats or a frozen record of them
(:class:`TrackingMetrics`, :class:`StepMetrics`, :class:`EdgeMetrics`: typed fields with the unit
in each name, and ``as_dict()`` giving the JSON field names of ``simulate --json`` and
``analyze --json``): the same numbers come from an offline run (:func:`summarize` of the
:class:`~piezo_stage_ros.core.loop.record.RunRecord`) and from its bag read back by ``analyze``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
import math
from typing import Any, Callable, ClassVar, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from piezo_stage_ros.core.contracts.errors import ParameterError, PiezoStageError
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.loop.record import RunRecord

__all__ = ['EdgeMetrics', 'LineMetrics', 'LineOptions', 'LineProfile', 'LineSpec',
           'PeriodErrors', 'StepMetrics', 'TRANSIENT_PERIODS', 'TRANSIENT_S', 'TrackingMetrics',
           'edge_metrics', 'error_metrics', 'grid_step', 'line_metrics', 'line_profile',
           'line_spec', 'loop_width', 'meta_period', 'per_period_error', 'square_wave_metrics',
           'steady_state_start', 'step_response', 'summarize', 'window_slice']


#: Whole periods of a periodic reference skipped before the steady-state window.
TRANSIENT_PERIODS = 2
#: Minimum time skipped before the steady-state window of a periodic reference [s].
TRANSIENT_S = 0.1
#: Meta key holding the reference period [s] (written by the closed loop, read from bags).
PERIOD_KEY = 'trajectory_period_s'


class _Record:
    """A frozen record of figures whose JSON object is its fields, in declaration order."""

    # set by @dataclass on each subclass; declared so that dataclasses.fields(self) type-checks
    __dataclass_fields__: ClassVar[dict[str, Any]]

    def as_dict(self) -> dict[str, float]:
        """
        Return the figures keyed by field name (the JSON field names), counts as floats.

        Returns
        -------
        dict of str to float
            One entry per field, in declaration order (fields marked ``json: False`` left out).

        """
        return {f.name: float(getattr(self, f.name)) for f in dataclasses.fields(self)
                if f.metadata.get('json', True)}


@dataclass(frozen=True)
class StepMetrics(_Record):
    """
    Figures of one step response (:func:`step_response`).

    Attributes
    ----------
    rise_time_s : float
        10 % to 90 % of the step [s]; NaN if the response never gets there.
    overshoot_pct : float
        Largest excursion past the final value in % of the step, 0 if none.
    settling_time_s : float
        From the step to the last entry into the band [s]; NaN if it never settles.
    settle_band_m : float
        Half-width of the settling band [m].
    ss_e_max_m, ss_e_rms_m : float
        Steady-state error to the final value over the end of the plateau [m].

    """

    rise_time_s: float
    overshoot_pct: float
    settling_time_s: float
    settle_band_m: float
    ss_e_max_m: float
    ss_e_rms_m: float


@dataclass(frozen=True)
class EdgeMetrics(_Record):
    """
    Step-response figures over the edges of a run (:func:`edge_metrics`).

    Attributes
    ----------
    rise_time_s, overshoot_pct, settling_time_s : float
        Medians over the edges of the :class:`StepMetrics` fields [s], [%], [s] (NaN edges
        left out).
    settling_time_max_s : float
        Longest settling time over the edges [s]; NaN if one edge never settles.
    settle_band_m : float
        Half-width of the settling band of the first edge [m].
    ss_e_max_m, ss_e_rms_m : float
        Measured minus reference over all plateau tails: largest and rms [m].
    edges : int
        Number of edges measured.

    """

    rise_time_s: float
    overshoot_pct: float
    settling_time_s: float
    settling_time_max_s: float
    settle_band_m: float
    ss_e_max_m: float
    ss_e_rms_m: float
    edges: int


@dataclass(frozen=True)
class TrackingMetrics(_Record):
    """
    The standard metrics of one run (:func:`summarize`).

    Attributes
    ----------
    samples : int
        Samples in the run.
    e_max_m, e_rms_m : float
        (D1), (D2) over the steady-state window [m].
    e_max_all_m, e_rms_all_m : float
        (D1), (D2) over the whole run [m].
    command_min_v, command_max_v : float
        Range of the command over the whole run [V].
    duration_s : float
        Samples times the sample time [s].
    steady_state_start_s : float
        Start of the steady-state window since the first sample [s].
    steady_state_samples : int
        Samples in the steady-state window.
    loop_width_pct : float
        Loop width of x against x_d over the window [%]; NaN when x_d is constant.
    diagnostic_ranges : mapping of str to (float, float)
        Finite minimum and maximum of each diagnostic, by name (NaN, NaN when none is finite);
        the JSON fields ``<name>_min`` and ``<name>_max``.
    e_max_true_m, e_rms_true_m : float or None
        (D1), (D2) of the true position x(t_k) - x_d(t_k) over the steady-state window [m];
        None when the run has no true position (then they are not in the JSON object).
    line : LineMetrics or None
        The figures over the linear part of each line (:func:`line_metrics`), for a scan line
        or when asked; None otherwise (then they are not in the JSON object).

    """

    samples: int
    e_max_m: float
    e_rms_m: float
    e_max_all_m: float
    e_rms_all_m: float
    command_min_v: float
    command_max_v: float
    duration_s: float
    steady_state_start_s: float
    steady_state_samples: int
    loop_width_pct: float
    # left out of the hash (a dict has none), so the record hashes like its float fields
    diagnostic_ranges: Mapping[str, tuple[float, float]] = field(
        default_factory=dict, hash=False, metadata={'json': False})
    e_max_true_m: float | None = field(default=None, metadata={'json': False})
    e_rms_true_m: float | None = field(default=None, metadata={'json': False})
    line: LineMetrics | None = field(default=None, metadata={'json': False})

    def as_dict(self) -> dict[str, float]:
        """
        Return the metrics keyed by their JSON field names, counts as floats.

        Returns
        -------
        dict of str to float
            The fields in declaration order, then ``e_max_true_m``, ``e_rms_true_m`` when the
            run has a true position (left out otherwise, so the object of a run without one is
            what it always was), then ``<name>_min``, ``<name>_max`` of each diagnostic in name
            order, then the line figures (``line_...``) when measured: the objects
            ``simulate --json`` and ``analyze --json`` print.

        """
        out = super().as_dict()
        if self.e_max_true_m is not None and self.e_rms_true_m is not None:
            out['e_max_true_m'] = float(self.e_max_true_m)
            out['e_rms_true_m'] = float(self.e_rms_true_m)
        if self.line is not None:
            out.update(self.line.as_dict())
        for name, (low, high) in sorted(self.diagnostic_ranges.items()):
            out[f'{name}_min'] = low
            out[f'{name}_max'] = high
        return out


def _f64(values: ArrayLike) -> FloatArray:
    return np.asarray(values, dtype=np.float64).ravel()


def error_metrics(error_m: ArrayLike) -> tuple[float, float]:
    """
    Return (e_m, e_rms) of a sequence of tracking errors, (D1) and (D2).

    Parameters
    ----------
    error_m : array_like
        x - x_d per sample [m].

    Returns
    -------
    e_max_m, e_rms_m : float
        Largest absolute error and root mean square error [m]; NaN for an empty input.

    """
    e = _f64(error_m)
    if e.size == 0:
        return math.nan, math.nan
    return float(np.max(np.abs(e))), float(np.sqrt(np.mean(e * e)))


def grid_step(time_s: ArrayLike) -> tuple[float, int]:
    """
    Return the sample step of a run's times and how many samples its grid misses.

    A run recorded in real time has holes where the loop skipped samples: its times are a
    uniform grid with some points missing. The step is then the median spacing (most spacings
    are one step), not the mean; a run without holes keeps the mean (t_n-1 - t_0)/(n - 1).

    Parameters
    ----------
    time_s : array_like
        Sample times [s], increasing.

    Returns
    -------
    step_s : float
        The grid step [s] (0 for fewer than 2 samples).
    missing : int
        Grid points between the first and last sample that hold no sample (0 without holes).

    """
    t = _f64(time_s)
    n = t.size
    if n < 2:
        return 0.0, 0
    mean = float((t[-1] - t[0]) / (n - 1))
    spacing = np.diff(t)
    step = float(np.median(spacing))
    # a hole is a spacing of two steps or more; jitter of a stamp stays far below half a step
    if not step > 0.0 or float(np.max(spacing)) <= 1.5 * step:
        return mean, 0
    return step, max(int(round(float(t[-1] - t[0]) / step)) + 1 - n, 0)


def steady_state_start(time_s: ArrayLike, period_s: float | None) -> float:
    """
    Return the start of the steady-state window [s] (see the module docstring).

    Parameters
    ----------
    time_s : array_like
        Sample times [s]; only the first and last are used.
    period_s : float or None
        Period of the reference [s]; ``None`` or non-positive for an aperiodic reference.

    Returns
    -------
    float
        Start time of the window [s], in the time base of ``time_s``.

    """
    t = _f64(time_s)
    if t.size == 0:
        return 0.0
    t0, t1 = float(t[0]), float(t[-1])
    if period_s is None or not period_s > 0.0 or not math.isfinite(period_s):
        return t0
    skip = max(TRANSIENT_PERIODS * period_s, TRANSIENT_S)
    skip = math.ceil(skip / period_s - 1e-9) * period_s
    # the samples span [t0, t1 + T); whole periods are counted on (t1 - t0) plus one sample
    span = (t1 - t0) + grid_step(t)[0]
    if span - skip >= period_s * (1 - 1e-9):
        return t0 + skip
    whole = math.floor(span / period_s + 1e-9)
    return t0 + max(whole - 1, 0) * period_s


def window_slice(time_s: FloatArray, start_s: float, period_s: float | None) -> slice:
    """
    Return the slice of samples in [start, end of the last whole period).

    Parameters
    ----------
    time_s : ndarray
        Sample times [s] (holes in the grid allowed).
    start_s : float
        Start of the window, in the time base of ``time_s`` [s].
    period_s : float or None
        Reference period [s]; None: to the end of the run.

    Returns
    -------
    slice

    """
    n = time_s.size
    dt = grid_step(time_s)[0]
    # half a sample of tolerance: epoch stamps of a bag carry rounding far above 1e-9 s
    i0 = int(np.searchsorted(time_s, start_s - 0.5 * dt))
    i1 = n
    if period_s is not None and period_s > 0.0 and n > 1:
        whole = math.floor(((time_s[-1] - start_s) + dt) / period_s + 1e-9)
        if whole >= 1:
            end = start_s + whole * period_s
            i1 = int(np.searchsorted(time_s, end - 0.5 * dt))
    return slice(i0, max(i1, i0))


def loop_width(x: ArrayLike, y: ArrayLike, *, levels: int = 201) -> float:
    """
    Return the loop width of the curve y(x) in % of the range of y.

    Parameters
    ----------
    x : array_like
        Input of the loop (x_d in closed loop, v_in in open loop); its sign of change splits the
        curve into ascending and descending pieces.
    y : array_like
        Output (the measured position), same length as ``x``.
    levels : int
        Number of x levels of the common grid (the end points are left out).

    Returns
    -------
    float
        ``100 * max_x |y_desc(x) - y_asc(x)| / (max y - min y)`` [%]; 0 when there is no
        level with both branches, NaN when y is constant.

    Notes
    -----
    For x = sin t, y = sin(t - phi) the width is 2 sin(phi) over a range of 2: sin(phi) * 100 %.

    """
    xa, ya = _f64(x), _f64(y)
    if xa.size != ya.size:
        raise PiezoStageError(f'loop_width: x has {xa.size} samples, y has {ya.size}')
    if xa.size < 3:
        return math.nan
    y_range = float(np.max(ya) - np.min(ya))
    if not y_range > 0.0:
        return math.nan
    grid = np.linspace(float(np.min(xa)), float(np.max(xa)), levels + 2)[1:-1]
    sums = np.zeros((2, grid.size))
    counts = np.zeros((2, grid.size))
    dx = np.diff(xa)
    sign = np.sign(dx)
    # a flat step keeps the direction of the one before it
    nz = np.flatnonzero(sign)
    if nz.size == 0:
        return 0.0
    fill = np.maximum.accumulate(np.where(sign != 0, np.arange(sign.size), nz[0]))
    sign = sign[fill]
    breaks = np.flatnonzero(np.diff(sign)) + 1
    starts = np.concatenate(([0], breaks))
    ends = np.concatenate((breaks, [sign.size]))
    for s, e in zip(starts.tolist(), ends.tolist()):
        up = sign[s] > 0
        xs = xa[s:e + 1]
        ys = ya[s:e + 1]
        if not up:
            xs, ys = xs[::-1], ys[::-1]
        lo, hi = xs[0], xs[-1]
        i0 = int(np.searchsorted(grid, lo, side='left'))
        i1 = int(np.searchsorted(grid, hi, side='right'))
        if i1 <= i0:
            continue
        row = 0 if up else 1
        sums[row, i0:i1] += np.interp(grid[i0:i1], xs, ys)
        counts[row, i0:i1] += 1.0
    both = (counts[0] > 0) & (counts[1] > 0)
    if not both.any():
        return 0.0
    gap = sums[1, both] / counts[1, both] - sums[0, both] / counts[0, both]
    return float(100.0 * np.max(np.abs(gap)) / y_range)


def step_response(time_s: ArrayLike, position_m: ArrayLike, *, step_time_s: float,
                  initial_m: float, final_m: float, settle_band_m: float = 0.0,
                  settle_fraction: float = 0.02, plateau_fraction: float = 0.5
                  ) -> StepMetrics:
    """
    Return rise time, overshoot, settling time and steady-state error of one step.

    Parameters
    ----------
    time_s : array_like
        Sample times [s] from the step to the end of the plateau (earlier samples are ignored).
    position_m : array_like
        Measured position [m] at those times.
    step_time_s : float
        Time of the reference step [s].
    initial_m, final_m : float
        Reference before and after the step [m]; they must differ.
    settle_band_m : float
        Absolute half-width of the settling band [m]; the band is the larger of this and
        ``settle_fraction`` of the step.
    settle_fraction : float
        Relative half-width of the settling band (0.02: the 2 % band).
    plateau_fraction : float
        Last fraction of the plateau over which the steady-state error is taken, in (0, 1].

    Returns
    -------
    StepMetrics
        ``rise_time_s`` (10 % to 90 % of the step), ``overshoot_pct`` (largest excursion past
        the final value in % of the step, 0 if none), ``settling_time_s`` (from the step to the
        last entry into the band; NaN if it never settles), ``settle_band_m``, ``ss_e_max_m``
        and ``ss_e_rms_m`` (error to ``final_m`` over the end of the plateau).

    """
    t, y = _f64(time_s), _f64(position_m)
    step = final_m - initial_m
    if step == 0.0:
        raise PiezoStageError('step_response: initial_m equals final_m; no step to measure')
    keep = t >= step_time_s - 1e-12
    t, y = t[keep] - step_time_s, y[keep]
    if t.size < 2:
        raise PiezoStageError('step_response: fewer than 2 samples after the step')
    frac = (y - initial_m) / step  # 0 before, 1 at the target, whatever the step's sign
    above10 = np.flatnonzero(frac >= 0.1)
    above90 = np.flatnonzero(frac >= 0.9)
    rise = math.nan
    if above10.size and above90.size:
        rise = _crossing(t, frac, int(above90[0]), 0.9) - _crossing(t, frac, int(above10[0]), 0.1)
    overshoot = max(float(np.max(frac)) - 1.0, 0.0) * 100.0
    band = max(settle_fraction * abs(step), settle_band_m)
    outside = np.flatnonzero(np.abs(y - final_m) > band)
    if outside.size == 0:
        settling = 0.0
    elif outside[-1] == t.size - 1:
        settling = math.nan
    else:
        settling = float(t[outside[-1] + 1])
    n_tail = max(int(round(plateau_fraction * t.size)), 1)
    e_max, e_rms = error_metrics(y[-n_tail:] - final_m)
    return StepMetrics(rise_time_s=rise, overshoot_pct=overshoot, settling_time_s=settling,
                       settle_band_m=band, ss_e_max_m=e_max, ss_e_rms_m=e_rms)


def _crossing(t: FloatArray, frac: FloatArray, i: int, level: float) -> float:
    """Return the time frac crosses ``level`` between samples i-1 and i (linear)."""
    if i == 0:
        return float(t[0])
    f0, f1 = frac[i - 1], frac[i]
    if f1 == f0:
        return float(t[i])
    return float(t[i - 1] + (level - f0) / (f1 - f0) * (t[i] - t[i - 1]))


def square_wave_metrics(time_s: ArrayLike, position_m: ArrayLike, reference_m: ArrayLike, *,
                        period_s: float, settle_band_m: float = 0.0,
                        plateau_fraction: float = 0.5, skip_edges: int = 0
                        ) -> EdgeMetrics:
    """
    Return step-response figures of a square-wave run, over its edges.

    Parameters
    ----------
    time_s, position_m, reference_m : array_like
        Samples of the run [s], [m], [m].
    period_s : float
        Square-wave period [s]; each half period is one plateau.
    settle_band_m : float
        Absolute settling band [m] (see :func:`step_response`).
    plateau_fraction : float
        Last fraction of each plateau taken as steady state.
    skip_edges : int
        Edges left out at the start (e.g. while an adaptive controller is still learning).

    Returns
    -------
    EdgeMetrics
        Medians over the edges of ``rise_time_s``, ``overshoot_pct``, ``settling_time_s``
        (max over edges as ``settling_time_max_s``), steady-state ``ss_e_max_m`` (max over
        plateaus) and ``ss_e_rms_m`` (rms over all plateau tails), and ``edges``.

    """
    t, y, r = _f64(time_s), _f64(position_m), _f64(reference_m)
    jumps = (np.flatnonzero(np.diff(r) != 0.0) + 1).tolist()[skip_edges:]
    edges = [(i, float(r[i - 1]), float(r[i])) for i in jumps]
    return edge_metrics(t, y, r, edges, settle_band_m=settle_band_m,
                        plateau_fraction=plateau_fraction,
                        what=f'square_wave_metrics: no complete edge in the run; run longer '
                        f'than {period_s:g} s')


def edge_metrics(time_s: FloatArray, position_m: FloatArray, reference_m: FloatArray,
                 edges: Sequence[tuple[int, float, float]], *, settle_band_m: float = 0.0,
                 plateau_fraction: float = 0.5, what: str = 'no complete edge in the run'
                 ) -> EdgeMetrics:
    """
    Return step-response figures over given edges, each lasting until the next one.

    Parameters
    ----------
    time_s, position_m, reference_m : ndarray
        Samples of the run [s], [m], [m].
    edges : sequence of (int, float, float)
        Sample index where each edge starts, with the level before and after it [m].
    settle_band_m : float
        Absolute settling band [m] (see :func:`step_response`).
    plateau_fraction : float
        Last fraction of each plateau taken as steady state, in (0, 1].
    what : str
        Message of the error raised when no edge is long enough.

    Returns
    -------
    EdgeMetrics
        The figures of :func:`square_wave_metrics`.

    Raises
    ------
    PiezoStageError
        If no edge has at least 4 samples.

    """
    t, y, r = time_s, position_m, reference_m
    rows: list[StepMetrics] = []
    tail_errors: list[FloatArray] = []
    bounds = [i for i, _, _ in edges] + [t.size]
    for (i0, initial, final), i1 in zip(edges, bounds[1:]):
        if i1 - i0 < 4:
            continue
        rows.append(step_response(t[i0:i1], y[i0:i1], step_time_s=float(t[i0]),
                                  initial_m=initial, final_m=final,
                                  settle_band_m=settle_band_m,
                                  plateau_fraction=plateau_fraction))
        n_tail = max(int(round(plateau_fraction * (i1 - i0))), 1)
        tail_errors.append(y[i1 - n_tail:i1] - r[i1 - n_tail:i1])
    if not rows:
        raise PiezoStageError(what)
    e_max, e_rms = error_metrics(np.concatenate(tail_errors))

    def med(values: list[float]) -> float:
        finite = np.asarray(values, dtype=np.float64)
        finite = finite[np.isfinite(finite)]
        return float(np.median(finite)) if finite.size else math.nan
    settle = [row.settling_time_s for row in rows]
    return EdgeMetrics(
        rise_time_s=med([row.rise_time_s for row in rows]),
        overshoot_pct=med([row.overshoot_pct for row in rows]),
        settling_time_s=med(settle),
        settling_time_max_s=float(np.max(settle)) if not np.isnan(settle).any() else math.nan,
        settle_band_m=rows[0].settle_band_m, ss_e_max_m=e_max, ss_e_rms_m=e_rms,
        edges=len(rows))


def _finite_extreme(values: FloatArray, pick: Callable[[FloatArray], Any]) -> float:
    # commands a bag could not pair with their samples are NaN: the extremes of the others
    finite = values[np.isfinite(values)]
    return float(pick(finite)) if finite.size else math.nan


def summarize(record: RunRecord, *, steady_state_start_s: float | None = None,
              period_s: float | None = None, lines: LineOptions | None = None
              ) -> TrackingMetrics:
    """
    Return the standard metrics of one run (what ``simulate --json`` and ``analyze`` print).

    Parameters
    ----------
    record : RunRecord
        The run (offline or read from a bag).
    steady_state_start_s : float, optional
        Start of the steady-state window, in seconds *since the first sample*; default from the
        reference period (``period_s`` or ``record.meta['trajectory_period_s']``) by
        :func:`steady_state_start`.
    period_s : float, optional
        Reference period [s]; overrides the record's meta.
    lines : LineOptions, optional
        Measure the linear part of each line (:func:`line_metrics`) with these options; a scan
        line (``meta['trajectory_lines']``) is measured without asking, over its whole linear
        part without pixels.

    Returns
    -------
    TrackingMetrics
        ``e_max_m``, ``e_rms_m`` (steady-state window), ``e_max_all_m``, ``e_rms_all_m`` (whole
        run), ``command_min_v``, ``command_max_v`` (whole run), ``samples``, ``duration_s``,
        ``steady_state_start_s`` (since the first sample), ``steady_state_samples``,
        ``loop_width_pct`` (x vs x_d over the window; NaN when x_d is constant), the
        finite range of each diagnostic, and ``e_max_true_m``, ``e_rms_true_m`` over the window
        when the record has a true position (else None), ``line`` when measured;
        ``as_dict()`` gives the JSON object.

    Raises
    ------
    PiezoStageError
        If ``lines`` asks for the line figures of a reference without a linear part.

    """
    t = _f64(record.time_s)
    n = t.size
    period = period_s if period_s is not None else meta_period(record.meta)
    if n == 0:
        nan = math.nan
        return TrackingMetrics(samples=0, e_max_m=nan, e_rms_m=nan, e_max_all_m=nan,
                               e_rms_all_m=nan, command_min_v=nan, command_max_v=nan,
                               duration_s=0.0, steady_state_start_s=0.0,
                               steady_state_samples=0, loop_width_pct=nan)
    dt, missing = grid_step(t)
    if steady_state_start_s is None:
        start_abs = steady_state_start(t, period)
    else:
        start_abs = float(t[0]) + float(steady_state_start_s)
    window = window_slice(t, start_abs, period)
    err = _f64(record.position_m) - _f64(record.reference_m)
    e_max, e_rms = error_metrics(err[window])
    e_max_all, e_rms_all = error_metrics(err)
    e_max_true: float | None = None
    e_rms_true: float | None = None
    if record.true_position_m is not None:
        true_err = _f64(record.true_position_m) - _f64(record.reference_m)
        e_max_true, e_rms_true = error_metrics(true_err[window])
    cmd = _f64(record.command_v)
    ref = _f64(record.reference_m)[window]
    pos = _f64(record.position_m)[window]
    width = loop_width(ref, pos) if ref.size > 2 and np.ptp(ref) > 0.0 else math.nan
    ranges: dict[str, tuple[float, float]] = {}
    for name, values in sorted(record.diagnostics.items()):
        v = _f64(values)
        finite = v[np.isfinite(v)]
        ranges[name] = ((float(np.min(finite)), float(np.max(finite))) if finite.size
                        else (math.nan, math.nan))
    return TrackingMetrics(samples=n, e_max_m=e_max, e_rms_m=e_rms, e_max_all_m=e_max_all,
                           e_rms_all_m=e_rms_all, command_min_v=_finite_extreme(cmd, np.min),
                           command_max_v=_finite_extreme(cmd, np.max),
                           duration_s=float((n + missing) * dt),
                           steady_state_start_s=start_abs - float(t[0]),
                           steady_state_samples=window.stop - window.start,
                           loop_width_pct=width, diagnostic_ranges=ranges,
                           e_max_true_m=e_max_true, e_rms_true_m=e_rms_true,
                           line=(line_metrics(record, window, lines)
                                 if lines is not None or LINES_KEY in record.meta else None))


@dataclass(frozen=True)
class PeriodErrors:
    """
    The error of each whole period of a run (:func:`per_period_error`): the learning curve.

    Attributes
    ----------
    period_s : float
        The period [s].
    start_s : ndarray
        Start of each period since the first sample [s] (j P).
    samples : ndarray of int
        Samples in each period.
    e_rms_m, e_max_m : ndarray
        (D2), (D1) of the measured error y_k - x_d(t_k) in each period [m].
    e_rms_true_m, e_max_true_m : ndarray or None
        The same of the true error x(t_k) - x_d(t_k) [m]; None without a true position.

    """

    period_s: float
    start_s: FloatArray
    samples: NDArray[np.int64]
    e_rms_m: FloatArray
    e_max_m: FloatArray
    e_rms_true_m: FloatArray | None = None
    e_max_true_m: FloatArray | None = None

    def __len__(self) -> int:
        return int(self.start_s.size)


def per_period_error(record: RunRecord, period_s: float) -> PeriodErrors:
    """
    Return e_rms and e_m of every whole period of a run, measured and (when known) true.

    Parameters
    ----------
    record : RunRecord
        The run (offline or read from a bag).
    period_s : float
        The reference period [s], > 0 and finite.

    Returns
    -------
    PeriodErrors
        One row per whole period counted from the first sample (period j: the samples with
        ``t_0 + j P <= t_k < t_0 + (j + 1) P``, half a sample of tolerance); a trailing
        partial period is dropped, so a run shorter than one period has no row.

    Raises
    ------
    PiezoStageError
        If ``period_s`` is not a positive finite number.

    """
    if not (math.isfinite(period_s) and period_s > 0.0):
        raise PiezoStageError(f'per_period_error: period_s = {period_s!r}; allowed: a finite '
                              'number > 0 s')
    t = _f64(record.time_s)
    n = t.size
    empty = np.zeros(0)
    has_true = record.true_position_m is not None
    if n == 0:
        return PeriodErrors(period_s, empty, np.zeros(0, np.int64), empty, empty,
                            empty if has_true else None, empty if has_true else None)
    dt = grid_step(t)[0]
    whole = math.floor(((t[-1] - t[0]) + dt) / period_s + 1e-9) if n > 1 else 0
    starts = np.arange(whole, dtype=np.float64) * period_s
    edges = np.searchsorted(t - t[0], np.arange(whole + 1) * period_s - 0.5 * dt)
    counts = np.diff(edges).astype(np.int64)
    keep = counts > 0

    def rows(error: FloatArray) -> tuple[FloatArray, FloatArray]:
        if whole == 0:
            return empty, empty
        lo = edges[:-1][keep]
        e = error[:edges[-1]]
        sq = np.add.reduceat(e * e, lo)
        peak = np.maximum.reduceat(np.abs(e), lo)
        rms = np.full(whole, np.nan)
        top = np.full(whole, np.nan)
        rms[keep] = np.sqrt(sq / counts[keep])
        top[keep] = peak
        return rms, top
    ref = _f64(record.reference_m)
    e_rms, e_max = rows(_f64(record.position_m) - ref)
    t_rms: FloatArray | None = None
    t_max: FloatArray | None = None
    if record.true_position_m is not None:
        t_rms, t_max = rows(_f64(record.true_position_m) - ref)
    return PeriodErrors(float(period_s), starts, counts, e_rms, e_max, t_rms, t_max)


def meta_period(meta: Mapping[str, Any]) -> float | None:
    """
    Return the reference period a run's description holds, if it is a usable one.

    Parameters
    ----------
    meta : Mapping
        ``RunRecord.meta`` (offline, or read from a bag).

    Returns
    -------
    float or None
        ``meta['trajectory_period_s']`` when it is a positive finite number [s], else None.

    """
    value = meta.get(PERIOD_KEY)
    try:
        period = float(value) if value is not None else None
    except (TypeError, ValueError):
        return None
    return period if period is not None and period > 0.0 and math.isfinite(period) else None


#: Meta key of a scan line's linear part (written by the closed loop, read from bags).
LINES_KEY = 'trajectory_lines'
# |x_d'| within this share of the line speed counts as the linear part: the speed is one float
# on every linear sample; a turnaround's 1 - 2 S(s) differs from 1 by more from its second
# sample on
_SPEED_TOL = 1e-9
# the linear part found from the reference velocity must hold this share of the samples at least
# (a sine reaches its top speed on a sample or two a period)
_MIN_LINEAR_SHARE = 0.25


@dataclass(frozen=True)
class LineOptions:
    """
    What the line metrics measure (:func:`line_metrics`).

    Attributes
    ----------
    middle_fraction : float
        Share of the linear range, centred, over which the error is taken, in (0, 1] (a pure
        triangle: the middle of each line, away from the corners).
    pixels : int
        Pixels per line over that range; 0: no pixel figures.

    """

    middle_fraction: float = 1.0
    pixels: int = 0

    def __post_init__(self) -> None:
        if not (0.0 < self.middle_fraction <= 1.0):
            raise ParameterError('line middle_fraction', self.middle_fraction, '(0, 1]')
        if not 0 <= self.pixels <= 1_000_000:
            raise ParameterError('line pixels', self.pixels, '[0, 1000000] (0: none)')

    @classmethod
    def asked(cls, middle_fraction: float | None, pixels: int | None) -> LineOptions | None:
        """
        Return the options a command line asked for, or None when it asked for neither.

        Parameters
        ----------
        middle_fraction : float or None
            ``--line-middle`` (None: 1, the whole linear part).
        pixels : int or None
            ``--pixels`` (None: no pixel figures).

        Returns
        -------
        LineOptions or None

        """
        if middle_fraction is None and pixels is None:
            return None
        return cls(1.0 if middle_fraction is None else middle_fraction, pixels or 0)


@dataclass(frozen=True)
class LineSpec:
    """
    The linear part of the lines of a run: the range the reference crosses at constant speed.

    Attributes
    ----------
    low_m, high_m : float
        Ends of the linear range [m].
    speed_mps : float
        Speed along it [m/s].
    source : str
        Where it comes from: ``'trajectory'`` (a scan line's description in the run's meta)
        or ``'reference velocity'`` (found from x_d').

    """

    low_m: float
    high_m: float
    speed_mps: float
    source: str


@dataclass(frozen=True)
class LineMetrics:
    """
    Figures over the linear part of each line, trace (x_d rising) and retrace separately.

    Attributes
    ----------
    middle_fraction : float
        Share of the linear range measured.
    low_m, high_m : float
        The measured range [m] (the middle of the linear range).
    trace_samples, retrace_samples : int
        Samples in it, in the steady-state window.
    trace_e_max_m, trace_e_rms_m, retrace_e_max_m, retrace_e_rms_m : float
        (D1), (D2) of y_k - x_d(t_k) over those samples [m].
    trace_e_mean_m, retrace_e_mean_m : float
        The mean of that error [m]: the part of e_rms that shifts the whole line (an image
        offset, not a distortion; a trace-retrace difference shows as their difference).
    trace_e_max_true_m, ... : float or None
        The same of the true position [m]; None without one.
    pixels : int
        Pixels per line (0: no pixel figures).
    pixel_trace_e_max_m, pixel_trace_e_rms_m, pixel_retrace_e_max_m, pixel_retrace_e_rms_m :
        float or None
        Largest and rms pixel value over every pixel of every line [m] (:func:`line_profile`);
        the true position's when the run has one, else the measured.

    """

    middle_fraction: float
    low_m: float
    high_m: float
    trace_samples: int
    retrace_samples: int
    trace_e_max_m: float
    trace_e_rms_m: float
    retrace_e_max_m: float
    retrace_e_rms_m: float
    trace_e_mean_m: float = math.nan
    retrace_e_mean_m: float = math.nan
    trace_e_max_true_m: float | None = None
    trace_e_rms_true_m: float | None = None
    retrace_e_max_true_m: float | None = None
    retrace_e_rms_true_m: float | None = None
    pixels: int = 0
    pixel_trace_e_max_m: float | None = None
    pixel_trace_e_rms_m: float | None = None
    pixel_retrace_e_max_m: float | None = None
    pixel_retrace_e_rms_m: float | None = None

    def as_dict(self) -> dict[str, float]:
        """
        Return the figures under their JSON names, ``line_`` in front, counts as floats.

        Returns
        -------
        dict of str to float
            The fields that have a value (the true-position and pixel ones only when known),
            e.g. ``line_trace_e_rms_m``, ``line_pixel_retrace_e_max_m``.

        """
        return {f'line_{f.name}': float(getattr(self, f.name)) for f in dataclasses.fields(self)
                if getattr(self, f.name) is not None}

    def text(self) -> list[str]:
        """
        Return the figures as lines a person reads (nm, um).

        Returns
        -------
        list of str
            The range measured, then trace and retrace (true position when known), then the
            pixel figures when measured.

        """
        out = [f'linear part of each line, middle {self.middle_fraction * 100:g} % '
               f'({self.low_m * 1e6:.4g} ... {self.high_m * 1e6:.4g} um):']
        for name in ('trace', 'retrace'):
            e_max, e_rms = getattr(self, f'{name}_e_max_m'), getattr(self, f'{name}_e_rms_m')
            row = (f'  {name:<7} e_m = {e_max * 1e9:8.2f} nm, e_rms = {e_rms * 1e9:8.2f} nm '
                   f'(mean {getattr(self, f"{name}_e_mean_m") * 1e9:.2f} nm; '
                   f'{getattr(self, f"{name}_samples")} samples)')
            true_rms = getattr(self, f'{name}_e_rms_true_m')
            if true_rms is not None:
                row += (f'; true e_m = {getattr(self, f"{name}_e_max_true_m") * 1e9:.2f} nm, '
                        f'e_rms = {true_rms * 1e9:.2f} nm')
            out.append(row)
        if self.pixels:
            for name in ('trace', 'retrace'):
                out.append(f'  {name:<7} {self.pixels} pixels a line: largest pixel '
                           f'{getattr(self, f"pixel_{name}_e_max_m") * 1e9:.2f} nm, rms '
                           f'{getattr(self, f"pixel_{name}_e_rms_m") * 1e9:.2f} nm')
        return out


@dataclass(frozen=True)
class LineProfile:
    """
    The error along the line, trace and retrace, for plots (:func:`line_profile`).

    Attributes
    ----------
    spec : LineSpec
        The linear part.
    low_m, high_m : float
        The measured range [m].
    trace_position_m, trace_error_m, retrace_position_m, retrace_error_m : ndarray
        x_d and the error (true when known, else measured) of every sample measured [m].
    pixel_centre_m : ndarray
        Centre of each pixel [m] (empty without pixels).
    trace_pixels_m, retrace_pixels_m : ndarray
        Lines x pixels: each pixel's error on each line [m] (NaN where a line does not reach).
    true : bool
        Whether the errors are of the true position.

    """

    spec: LineSpec
    low_m: float
    high_m: float
    trace_position_m: FloatArray
    trace_error_m: FloatArray
    retrace_position_m: FloatArray
    retrace_error_m: FloatArray
    pixel_centre_m: FloatArray
    trace_pixels_m: FloatArray
    retrace_pixels_m: FloatArray
    true: bool


def line_spec(record: RunRecord, *, window: slice | None = None) -> LineSpec | None:
    """
    Return the linear part of a run's lines: from its meta, else from the reference velocity.

    Parameters
    ----------
    record : RunRecord
        The run; ``meta['trajectory_lines']`` (a scan line's description) is used when present.
    window : slice, optional
        Samples from which the linear part is found when the meta has none (default: all).

    Returns
    -------
    LineSpec or None
        None when the reference has no linear part: no constant speed on at least a quarter of
        the samples, or no rising and falling part at that speed (a sine, a step).

    """
    stored = record.meta.get(LINES_KEY)
    if isinstance(stored, Mapping):
        try:
            low, high, speed = (float(stored['low_m']), float(stored['high_m']),
                                float(stored['speed_mps']))
        except (KeyError, TypeError, ValueError):
            low = high = speed = math.nan
        if math.isfinite(low) and math.isfinite(high) and high > low and speed > 0.0:
            return LineSpec(low, high, speed, 'trajectory')
    sel = window if window is not None else slice(None)
    v = _f64(record.reference_velocity_mps)[sel]
    x = _f64(record.reference_m)[sel]
    finite = np.isfinite(v) & np.isfinite(x)
    if not finite.any():
        return None
    speed = float(np.max(np.abs(v[finite])))
    if not speed > 0.0:
        return None
    linear = finite & (np.abs(v) >= speed * (1.0 - _SPEED_TOL))
    if linear.sum() < _MIN_LINEAR_SHARE * finite.sum():
        return None
    if not ((v[linear] > 0).any() and (v[linear] < 0).any()):
        return None
    low, high = float(np.min(x[linear])), float(np.max(x[linear]))
    if not high > low:
        return None
    return LineSpec(low, high, speed, 'reference velocity')


def _measured_range(spec: LineSpec, options: LineOptions) -> tuple[float, float]:
    centre = 0.5 * (spec.low_m + spec.high_m)
    half = 0.5 * options.middle_fraction * (spec.high_m - spec.low_m)
    return centre - half, centre + half


def _line_samples(record: RunRecord, spec: LineSpec, options: LineOptions,
                  window: slice) -> tuple[FloatArray, FloatArray, NDArray[np.bool_],
                                          NDArray[np.bool_], float, float]:
    """Return x_d, v of the window and its trace and retrace masks, with the measured range."""
    x = _f64(record.reference_m)[window]
    v = _f64(record.reference_velocity_mps)[window]
    low, high = _measured_range(spec, options)
    # the range's ends are floats of the line's own arithmetic: a relative 1e-12 of slack
    slack = 1e-12 * (spec.high_m - spec.low_m)
    with np.errstate(invalid='ignore'):
        linear = (np.abs(v) >= spec.speed_mps * (1.0 - _SPEED_TOL)) & (x >= low - slack) & (
            x <= high + slack)
        return x, v, linear & (v > 0), linear & (v < 0), low, high


def _segments(mask: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """Return [start, end) of each run of True in ``mask``."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], mask.astype(np.int8), [0]))))
    return list(zip(edges[0::2].tolist(), edges[1::2].tolist()))


def _pixel_image(x: FloatArray, e: FloatArray, mask: NDArray[np.bool_], low: float, high: float,
                 pixels: int) -> FloatArray:
    """
    Return lines x pixels of the error: the mean of each pixel's samples, or interpolated.

    A line whose every pixel holds a sample gives each pixel the mean of its samples (the
    pixel integrates over its dwell); a line with fewer samples than pixels gives each pixel the
    error interpolated linearly in x_d at its centre, the end sample's within one sample's
    travel beyond the ends, NaN further out (a line the window cuts).
    """
    width = (high - low) / pixels
    centres = low + (np.arange(pixels) + 0.5) * width
    rows = []
    for i0, i1 in _segments(mask):
        xs, es = x[i0:i1], e[i0:i1]
        index = np.clip(np.floor((xs - low) / width).astype(np.int64), 0, pixels - 1)
        counts = np.bincount(index, minlength=pixels)
        if np.all(counts > 0):
            rows.append(np.bincount(index, weights=es, minlength=pixels) / counts)
            continue
        order = np.argsort(xs, kind='stable')
        xs, es = xs[order], es[order]
        row = np.interp(centres, xs, es)
        # a pixel within a sample's travel of the line's end takes the end's error; further
        # out the line was cut by the window
        reach = float(np.median(np.diff(xs))) if xs.size > 1 else 0.0
        row[(centres < xs[0] - reach) | (centres > xs[-1] + reach)] = np.nan
        rows.append(row)
    return np.array(rows, dtype=np.float64).reshape(len(rows), pixels)


def _line_parts(record: RunRecord, window: slice, options: LineOptions | None,
                spec: LineSpec | None) -> tuple[LineSpec, LineOptions, FloatArray,
                                                NDArray[np.bool_], NDArray[np.bool_], float,
                                                float]:
    """Return the spec, options, x_d, trace and retrace masks and range measured."""
    opts = options if options is not None else LineOptions()
    found = spec if spec is not None else line_spec(record, window=window)
    if found is None:
        raise PiezoStageError('line metrics: the reference has no linear part (no constant '
                              'speed up and down on at least a quarter of the samples: not a '
                              'scan line or a triangle)')
    x, _, trace, retrace, low, high = _line_samples(record, found, opts, window)
    return found, opts, x, trace, retrace, low, high


def line_profile(record: RunRecord, window: slice, options: LineOptions | None = None,
                 spec: LineSpec | None = None) -> LineProfile:
    """
    Return the error along the linear part of each line, trace and retrace, and per pixel.

    Parameters
    ----------
    record : RunRecord
        The run.
    window : slice
        The samples measured (the steady-state window).
    options : LineOptions, optional
        Middle fraction and pixels (default: the whole linear part, no pixels).
    spec : LineSpec, optional
        The linear part (default :func:`line_spec` of the run).

    Returns
    -------
    LineProfile

    Raises
    ------
    PiezoStageError
        If the run has no linear part.

    """
    found, opts, x, trace, retrace, low, high = _line_parts(record, window, options, spec)
    true = record.true_position_m is not None
    pos = _f64(record.position_m if record.true_position_m is None
               else record.true_position_m)[window]
    err = pos - x
    pixels = opts.pixels
    centres = (low + (np.arange(pixels) + 0.5) * (high - low) / pixels if pixels
               else np.zeros(0))
    empty = np.zeros((0, 0))
    return LineProfile(
        spec=found, low_m=low, high_m=high, trace_position_m=x[trace], trace_error_m=err[trace],
        retrace_position_m=x[retrace], retrace_error_m=err[retrace], pixel_centre_m=centres,
        trace_pixels_m=_pixel_image(x, err, trace, low, high, pixels) if pixels else empty,
        retrace_pixels_m=_pixel_image(x, err, retrace, low, high, pixels) if pixels else empty,
        true=true)


def line_metrics(record: RunRecord, window: slice, options: LineOptions | None = None,
                 spec: LineSpec | None = None) -> LineMetrics:
    """
    Return e_m and e_rms over the linear part of each line, trace and retrace, and per pixel.

    The arguments, and the error raised when the run has no linear part, are those of
    :func:`line_profile` (the same samples are measured); the figures are of the measured
    error, and of the true one when the run has it.

    Returns
    -------
    LineMetrics

    """
    found, opts, ref, trace, retrace, low, high = _line_parts(record, window, options, spec)
    profile = line_profile(record, window, opts, found)
    measured = _f64(record.position_m)[window] - ref
    tr_max, tr_rms = error_metrics(measured[trace])
    re_max, re_rms = error_metrics(measured[retrace])
    fields: dict[str, Any] = {
        'trace_e_mean_m': float(np.mean(measured[trace])) if trace.any() else math.nan,
        'retrace_e_mean_m': float(np.mean(measured[retrace])) if retrace.any() else math.nan}
    if record.true_position_m is not None:
        true_err = _f64(record.true_position_m)[window] - ref
        a, b = error_metrics(true_err[trace])
        c, d = error_metrics(true_err[retrace])
        fields.update({'trace_e_max_true_m': a, 'trace_e_rms_true_m': b,
                       'retrace_e_max_true_m': c, 'retrace_e_rms_true_m': d})
    if opts.pixels:
        for name, image in (('trace', profile.trace_pixels_m),
                            ('retrace', profile.retrace_pixels_m)):
            cells = image[np.isfinite(image)]
            top, rms = error_metrics(cells)
            fields[f'pixel_{name}_e_max_m'] = top
            fields[f'pixel_{name}_e_rms_m'] = rms
    return LineMetrics(middle_fraction=opts.middle_fraction, low_m=low, high_m=high,
                       trace_samples=int(trace.sum()), retrace_samples=int(retrace.sum()),
                       trace_e_max_m=tr_max, trace_e_rms_m=tr_rms, retrace_e_max_m=re_max,
                       retrace_e_rms_m=re_rms, pixels=opts.pixels, **fields)
