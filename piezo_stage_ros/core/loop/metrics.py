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
from piezo_stage_ros.core.contracts.errors import PiezoStageError
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.loop.record import RunRecord

__all__ = ['EdgeMetrics', 'PeriodErrors', 'StepMetrics', 'TRANSIENT_PERIODS', 'TRANSIENT_S',
           'TrackingMetrics', 'edge_metrics', 'error_metrics', 'loop_width', 'meta_period',
           'per_period_error', 'square_wave_metrics', 'steady_state_start', 'step_response',
           'summarize']


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

    def as_dict(self) -> dict[str, float]:
        """
        Return the metrics keyed by their JSON field names, counts as floats.

        Returns
        -------
        dict of str to float
            The fields in declaration order, then ``e_max_true_m``, ``e_rms_true_m`` when the
            run has a true position (left out otherwise, so the object of a run without one is
            what it always was), then ``<name>_min``, ``<name>_max`` of each diagnostic in name
            order: the objects ``simulate --json`` and ``analyze --json`` print.

        """
        out = super().as_dict()
        if self.e_max_true_m is not None and self.e_rms_true_m is not None:
            out['e_max_true_m'] = float(self.e_max_true_m)
            out['e_rms_true_m'] = float(self.e_rms_true_m)
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
    span = (t1 - t0) + (t1 - t0) / max(t.size - 1, 1)
    if span - skip >= period_s * (1 - 1e-9):
        return t0 + skip
    whole = math.floor(span / period_s + 1e-9)
    return t0 + max(whole - 1, 0) * period_s


def _window(time_s: FloatArray, start_s: float, period_s: float | None) -> slice:
    """Return the slice of samples in [start, end of the last whole period)."""
    n = time_s.size
    dt = (time_s[-1] - time_s[0]) / (n - 1) if n > 1 else 0.0
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
              period_s: float | None = None) -> TrackingMetrics:
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

    Returns
    -------
    TrackingMetrics
        ``e_max_m``, ``e_rms_m`` (steady-state window), ``e_max_all_m``, ``e_rms_all_m`` (whole
        run), ``command_min_v``, ``command_max_v`` (whole run), ``samples``, ``duration_s``,
        ``steady_state_start_s`` (since the first sample), ``steady_state_samples``,
        ``loop_width_pct`` (x vs x_d over the window; NaN when x_d is constant), the
        finite range of each diagnostic, and ``e_max_true_m``, ``e_rms_true_m`` over the window
        when the record has a true position (else None); ``as_dict()`` gives the JSON object.

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
    dt = (t[-1] - t[0]) / (n - 1) if n > 1 else 0.0
    if steady_state_start_s is None:
        start_abs = steady_state_start(t, period)
    else:
        start_abs = float(t[0]) + float(steady_state_start_s)
    window = _window(t, start_abs, period)
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
                           command_max_v=_finite_extreme(cmd, np.max), duration_s=float(n * dt),
                           steady_state_start_s=start_abs - float(t[0]),
                           steady_state_samples=window.stop - window.start,
                           loop_width_pct=width, diagnostic_ranges=ranges,
                           e_max_true_m=e_max_true, e_rms_true_m=e_rms_true)


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
    dt = (t[-1] - t[0]) / (n - 1) if n > 1 else 0.0
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
