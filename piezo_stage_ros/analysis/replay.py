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
Replay of one bag: read it, compute the metrics of the control issue, summarise.

The metrics are those of :func:`piezo_stage_ros.core.loop.metrics.summarize`, the function the
offline runner uses, with the same field names, so ``analyze --json`` of a bag and
``simulate --json`` of the run that wrote it compare one to one. Times are taken relative to
the first aligned sample (the offline runner starts at t = 0, so its bags are unchanged; a
recording from the ROS graph has wall-clock or sim-time stamps).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from pathlib import Path
from typing import Any

import numpy as np
from piezo_stage_ros.analysis.bagread import ProgressCallback, read_run, read_status
from piezo_stage_ros.analysis.spectral import BodeEstimate, estimate_bode, is_excitation_run
from piezo_stage_ros.core.contracts.errors import PiezoStageError
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.control.feedforward import LearnedTable, TABLE_META_KEY
from piezo_stage_ros.core.loop.metrics import (
    grid_step,
    line_spec,
    LineOptions,
    LINES_KEY,
    LineSpec,
)
from piezo_stage_ros.core.loop.record import RunRecord

__all__ = ['BagAnalysis', 'HEADLINE', 'analyze_bag', 'compute_metrics', 'estimate_period',
           'find_period', 'format_metric', 'format_summary', 'learned_table', 'learning_metrics',
           'ordered_keys', 'summary_json']

#: Key in ``RunRecord.meta`` where a runner may store the start of its metrics window [s].
STEADY_STATE_META_KEY = 'steady_state_start_s'


@dataclass
class BagAnalysis:
    """
    The result of replaying one bag.

    Attributes
    ----------
    path : Path
        The bag.
    record : RunRecord
        The aligned run, ``time_s`` relative to the first sample.
    time_origin_s : float
        Header stamp of the first sample [s] (0 for bags of the offline runner).
    metrics : dict of str to float
        :func:`~piezo_stage_ros.core.loop.metrics.summarize` of the run.
    steady_state_start_s : float or None
        Start of the metrics window used [s] (None: summarize's default).
    bode : BodeEstimate or None
        Frequency-response estimate, for noise or sweep runs.
    notes : list of str
        Things the reader of a report should know (dropped samples, a skipped plot).
    samples : int
        Aligned samples (kept when the record is released).
    duration_s : float
        Time from the first to the last sample [s].

    """

    path: Path
    record: RunRecord
    time_origin_s: float
    metrics: dict[str, float]
    steady_state_start_s: float | None
    bode: BodeEstimate | None = None
    notes: list[str] = field(default_factory=list)
    samples: int = 0
    duration_s: float = 0.0

    def __post_init__(self) -> None:
        if len(self.record):
            self.samples = len(self.record)
            self.duration_s = float(self.record.time_s[-1] - self.record.time_s[0])

    def release(self) -> None:
        """Drop the per-sample arrays (keep metrics and meta) once figures are drawn."""
        empty = np.zeros(0)
        self.record = RunRecord(empty, empty, empty, empty, empty, {}, self.record.meta)

    @property
    def name(self) -> str:
        """Short name of the bag (its directory or file name)."""
        return self.path.name or str(self.path)


def compute_metrics(record: RunRecord, steady_state_start_s: float | None = None,
                    lines: LineOptions | None = None) -> dict[str, float]:
    """
    Compute the run's metrics with the offline runner's own function.

    Parameters
    ----------
    record : RunRecord
        The run, times relative to its start [s].
    steady_state_start_s : float, optional
        Start of the metrics window [s]; None uses summarize's default (as ``simulate`` does).
    lines : LineOptions, optional
        The line figures to measure (``line_...``; a scan line's bag without asking).

    Returns
    -------
    dict of str to float
        ``e_max_m``, ``e_rms_m``, ... as :func:`piezo_stage_ros.core.loop.metrics.summarize` names
        them; when the reference is piecewise constant (steps, square wave) also the step
        figures of :func:`~piezo_stage_ros.core.loop.metrics.square_wave_metrics` (``rise_time_s``,
        ``overshoot_pct``, ``settling_time_s``, ``ss_e_max_m``, ``ss_e_rms_m``, ...).

    """
    from piezo_stage_ros.core.loop.metrics import square_wave_metrics, summarize
    out = summarize(record, steady_state_start_s=steady_state_start_s, lines=lines).as_dict()
    out.update(learning_metrics(record))
    if _is_piecewise_constant(record.reference_m):
        period = record.meta.get('trajectory_period_s')
        try:
            steps = square_wave_metrics(
                record.time_s, record.position_m, record.reference_m,
                period_s=float(period) if isinstance(period, (int, float)) else float(
                    record.time_s[-1] - record.time_s[0]))
        except PiezoStageError:
            return out
        out.update({k: v for k, v in steps.as_dict().items() if k not in out})
    return out


def learning_metrics(record: RunRecord) -> dict[str, float]:
    """
    Return the learning curve's ends for a run with a learning feed-forward.

    Parameters
    ----------
    record : RunRecord
        The run; nothing is returned unless it has the diagnostic ``ff_periods_learned`` and
        a reference period.

    Returns
    -------
    dict of str to float
        ``whole_periods_count``, ``periods_learned_count`` (table updates at the end of the
        run), ``period_e_rms_first_m`` and ``period_e_rms_last_m`` (the first and last whole
        periods of :func:`~piezo_stage_ros.core.loop.metrics.per_period_error`), and
        ``period_e_rms_true_last_m`` with a true position.

    """
    from piezo_stage_ros.core.loop.metrics import meta_period, per_period_error
    learned = record.diagnostics.get('ff_periods_learned')
    period = meta_period(record.meta)
    if learned is None or period is None or not len(learned):
        return {}
    rows = per_period_error(record, period)
    if not len(rows):
        return {}
    out = {'whole_periods_count': float(len(rows)),
           'periods_learned_count': float(learned[-1]),
           'period_e_rms_first_m': float(rows.e_rms_m[0]),
           'period_e_rms_last_m': float(rows.e_rms_m[-1])}
    if rows.e_rms_true_m is not None:
        out['period_e_rms_true_last_m'] = float(rows.e_rms_true_m[-1])
    return out


def learned_table(analysis: BagAnalysis) -> LearnedTable:
    """
    Return the learned table a bag holds (``simulate --bag`` of a learning run).

    Parameters
    ----------
    analysis : BagAnalysis
        The replayed bag.

    Returns
    -------
    LearnedTable

    Raises
    ------
    PiezoStageError
        If the bag holds none, or not a readable one.

    """
    fields = analysis.record.meta.get(TABLE_META_KEY)
    if not isinstance(fields, dict):
        raise PiezoStageError(f'bag {analysis.path}: holds no learned table (simulate --bag '
                              'stores one for a learning feed-forward)')
    return LearnedTable.from_fields(fields, f'bag {analysis.path}: learned table')


def _turns_around(record: RunRecord, spec: LineSpec) -> bool:
    # a raster line spends a share of each line below its line speed, turning around; a
    # triangle reaches its corners at full speed
    speed = np.abs(np.asarray(record.reference_velocity_mps, dtype=np.float64))
    slow = np.count_nonzero(speed < spec.speed_mps * (1.0 - 1e-9))
    return bool(slow >= 0.01 * speed.size)


def _is_piecewise_constant(reference_m: Any) -> bool:
    # Steps, a staircase or a square wave: the reference changes on at most 1 % of the samples
    # (a sine changes on every one), so the step figures mean something.
    changes = np.count_nonzero(np.diff(np.asarray(reference_m, dtype=np.float64)))
    return bool(0 < changes <= 0.01 * len(reference_m))


#: Meta key of the reference period (written by the closed loop; see core/loop/metrics.py).
PERIOD_META_KEY = 'trajectory_period_s'
# Longest period looked for when a bag does not say [samples]: 2 s at 10 kHz.
_MAX_PERIOD_SAMPLES = 20000


def estimate_period(record: RunRecord) -> float | None:
    """
    Find the period of the reference from its samples, for bags that do not store it.

    A bag recorded from the ROS graph carries no run description, so the steady-state window
    ``simulate`` takes from the trajectory's period must come from the samples: the smallest
    lag L (in samples) with x_d[k + L] = x_d[k] for every k, to 1e-9 of the reference's range,
    gives the period L * T. Candidates are checked on the first samples, the winner on the
    whole run. A run recorded in real time has holes in its time grid (skipped samples): the
    samples are put on the grid and only pairs of samples both present are compared.

    Parameters
    ----------
    record : RunRecord
        The run, sampled on a uniform grid (holes allowed).

    Returns
    -------
    float or None
        Period [s]; None for a constant or aperiodic reference, a run shorter than two periods,
        a period longer than 20000 samples, or times off a uniform grid
        (:func:`find_period` says which).

    """
    return find_period(record)[0]


def find_period(record: RunRecord) -> tuple[float | None, str]:
    """
    Find the period of the reference from its samples, or say why there is none.

    Parameters
    ----------
    record : RunRecord
        The run (see :func:`estimate_period`).

    Returns
    -------
    period_s : float or None
        The period [s], or None.
    why : str
        Why there is none (empty with a period).

    """
    xd = np.asarray(record.reference_m, dtype=np.float64)
    t = np.asarray(record.time_s, dtype=np.float64)
    n = xd.size
    if n < 4 or not np.all(np.isfinite(xd)):
        return None, 'fewer than 4 samples, or a reference that is not finite'
    span = float(np.ptp(xd))
    if span <= 0.0:
        return None, 'the reference is constant'
    step, missing = grid_step(t)
    if missing:
        # real time: samples skipped; each sample's place on the grid, within 1 % of a step
        place = np.rint((t - t[0]) / step)
        if float(np.max(np.abs(t - t[0] - place * step))) > 0.01 * step:
            return None, ('the sample times are not on a uniform grid (with holes); times off '
                          'it by more than 1 % of a step')
        grid = np.full(int(place[-1]) + 1, np.nan)
        grid[place.astype(np.int64)] = xd
        xd, n, period = grid, grid.size, step
    else:
        dt = np.diff(t)
        period = float(np.median(dt))
        if period <= 0.0 or float(np.max(np.abs(dt - period))) > 0.01 * period:
            return None, 'the sample times are not uniform (spacings differ by more than 1 %)'
    tol = 1e-9 * span

    def worst(a: FloatArray, b: FloatArray) -> float:
        # the largest difference over the pairs both present; no pair: no evidence either way
        d = np.abs(a - b)
        d = d[np.isfinite(d)]
        return float(np.max(d)) if d.size else math.inf
    probe = min(n // 2, 2000)
    for lag in range(1, min(n // 2, _MAX_PERIOD_SAMPLES) + 1):
        if n - lag < probe:
            break
        if worst(xd[lag:lag + probe], xd[:probe]) > tol:
            continue
        if worst(xd[lag:], xd[:-lag]) <= tol:
            return lag * period, ''
        return None, (f'the reference repeats on its first samples after {lag} samples but '
                      'not over the whole run (not periodic)')
    return None, (f'no lag up to {min(n // 2, _MAX_PERIOD_SAMPLES)} samples repeats the '
                  'reference to 1e-9 of its range (aperiodic, or a period longer than half '
                  'the run)')


def analyze_bag(path: str | Path, *, namespace: str | None = None,
                steady_state_start_s: float | None = None, bode: bool | None = None,
                progress: ProgressCallback | None = None,
                lines: LineOptions | None = None) -> BagAnalysis:
    """
    Read a bag, align it, and compute its metrics (and a Bode estimate when it makes sense).

    Parameters
    ----------
    path : path-like
        The bag.
    namespace : str, optional
        Topic namespace; found from the bag when there is one stage in it.
    steady_state_start_s : float, optional
        Start of the metrics window relative to the first sample [s]. Default: the value the
        runner stored in the bag's meta (``steady_state_start_s``), else summarize's default.
    bode : bool, optional
        Estimate the frequency response: True always, False never, None (default) when the
        run's description says the reference was noise or a sweep.
    progress : callable, optional
        ``progress(messages_read, messages_total)`` while reading.
    lines : LineOptions, optional
        Measure the linear part of each line (a scan line's bag: without asking).

    Returns
    -------
    BagAnalysis
        Aligned run, metrics and notes.

    Raises
    ------
    BagError
        The bag cannot be read (see :func:`~piezo_stage_ros.analysis.bagread.read_run`).
    PiezoStageError
        The metrics or the Bode estimate cannot be computed.

    """
    rebased = read_run(path, namespace=namespace, progress=progress, relative_time=True)
    record = rebased
    origin = int(record.meta['time_origin_ns']) / 1e9
    window = steady_state_start_s
    if window is None:
        stored = record.meta.get(STEADY_STATE_META_KEY)
        if isinstance(stored, (int, float)) and math.isfinite(stored):
            window = float(stored)
    notes = []
    step, missing = grid_step(rebased.time_s)
    if missing:
        notes.append(f'{missing} samples missing from the time grid of {step:g} s (skipped in '
                     f'real time, or lost): the figures are over the {len(rebased.time_s)} '
                     'samples present')
    if not isinstance(rebased.meta.get(PERIOD_META_KEY), (int, float)):
        period, why = find_period(rebased)
        if period is not None:
            # What the closed loop would have stored: the same window as simulate.
            rebased.meta[PERIOD_META_KEY] = period
            notes.append(f'reference period {period:g} s found from the samples (sets the '
                         'steady-state window)')
        elif not _is_piecewise_constant(rebased.reference_m) and why != 'the reference is ' \
                'constant':
            notes.append(f'no reference period found from the samples ({why}): the metrics '
                         'window is the whole run (or the one given), and there is no '
                         'learning curve')
    if LINES_KEY not in rebased.meta:
        spec = line_spec(rebased)
        # a raster line recorded from the graph (no run description): its linear part, as the
        # closed loop would have stored it; a triangle (all of it linear) only when asked
        if spec is not None and _turns_around(rebased, spec):
            rebased.meta[LINES_KEY] = {'low_m': spec.low_m, 'high_m': spec.high_m,
                                       'speed_mps': spec.speed_mps, 'source': spec.source}
            notes.append(f'scan line found from the reference velocity: linear from '
                         f'{spec.low_m * 1e6:.6g} to {spec.high_m * 1e6:.6g} um at '
                         f'{spec.speed_mps * 1e3:.6g} mm/s (sets the line figures)')
    metrics = compute_metrics(rebased, window, lines)
    align: dict[str, Any] = record.meta.get('alignment', {})
    dropped = {k: v for k, v in align.items() if k.startswith('dropped_') and v}
    if dropped:
        notes.append('messages that could not be aligned were dropped: '
                     + ', '.join(f'{k[8:]} {v}' for k, v in dropped.items()))
    notes += [f'warning: {text}' for text in align.get('warnings', ())]
    status = read_status(path, namespace=record.meta.get('namespace'))
    if status:
        # the plant's own account of a real-time run: late commands, skipped samples, lateness
        shown = [f'{k} {status[k]}' for k in STATUS_KEYS if k in status]
        notes.append('the plant at the end of the run (stage/status): ' + ', '.join(shown))
        taken = status.get('paced_samples', '')
        held = len(record.time_s)
        if taken.isdigit() and held < int(taken):
            notes.append(f'warning: the plant took {int(taken)} samples, the bag holds {held} '
                         f'of them: {int(taken) - held} were lost between the plant and the '
                         'recorder, or recorded before the first or after the last message '
                         'of this bag')
    estimate = None
    if bode or (bode is None and is_excitation_run(record.meta)):
        try:
            estimate = estimate_bode(rebased)
        except PiezoStageError as err:
            if bode:
                raise
            notes.append(f'no Bode estimate: {err}')
    return BagAnalysis(Path(path), rebased, origin, metrics, window, estimate, notes)


#: The plant counters of stage/status an analysis reports (those present), in this order.
STATUS_KEYS = ('index', 'paced_samples', 'late', 'skipped', 'late_half_period',
               'lateness_p50_us', 'lateness_p99_us', 'lateness_max_us', 'watchdog_trips',
               'safe_samples', 'queue_overruns', 'ring_missed', 'live_dropped', 'resends')


#: The metrics a reader looks at first, in this order; the others (diagnostics) follow.
HEADLINE = ('e_max_m', 'e_rms_m', 'e_max_all_m', 'e_rms_all_m', 'e_max_true_m', 'e_rms_true_m',
            'loop_width_pct', 'rise_time_s',
            'overshoot_pct', 'settling_time_s', 'settling_time_max_s', 'ss_e_max_m',
            'ss_e_rms_m', 'command_min_v', 'command_max_v', 'samples', 'duration_s',
            'steady_state_start_s', 'steady_state_samples', 'edges', 'settle_band_m')


def ordered_keys(keys: list[str]) -> list[str]:
    """
    Order metric names for reading: the headline metrics first, then the rest as given.

    Parameters
    ----------
    keys : list of str
        Metric names.

    Returns
    -------
    list of str
        The same names, reordered.

    """
    first = [k for k in HEADLINE if k in keys]
    return first + [k for k in keys if k not in HEADLINE]


def format_metric(key: str, value: float) -> str:
    """
    Format one metric with a unit a person reads easily (nm, ms, V).

    Parameters
    ----------
    key : str
        Metric name; its suffix gives the SI unit (``_m``, ``_s``, ``_v``, ``_mps``).
    value : float
        Value in SI units.

    Returns
    -------
    str
        E.g. ``'39.4 nm'``.

    """
    if not math.isfinite(value):
        return 'n/a'
    if key == 'samples' or key.endswith('_count'):
        return f'{value:.0f}'
    if key.endswith('_m'):
        return f'{value * 1e9:.3f} nm'
    if key.endswith('_s'):
        return f'{value * 1e3:.3f} ms'
    if key.endswith('_v'):
        return f'{value:.4f} V'
    if key.endswith('_mps'):
        return f'{value * 1e6:.3f} µm/s'
    if key.endswith(('_pct', '_percent')):
        return f'{value:.3f} %'
    return f'{value:.6g}'


def summary_json(analysis: BagAnalysis) -> dict[str, Any]:
    """
    Return the JSON object ``analyze --json`` prints for a bag.

    Parameters
    ----------
    analysis : BagAnalysis
        The replayed bag.

    Returns
    -------
    dict
        ``bag``, ``time_origin_s`` (stamp of the first sample [s]) and
        ``trajectory_period_s`` (as ``simulate --json``) plus every metric under summarize's
        own name (SI units); non-finite values become null so the line is strict JSON.

    """
    out: dict[str, Any] = {'bag': str(analysis.path)}
    for key, value in analysis.metrics.items():
        out[key] = value if math.isfinite(value) else None
    period = analysis.record.meta.get(PERIOD_META_KEY)
    out[PERIOD_META_KEY] = float(period) if isinstance(period, (int, float)) else None
    out['time_origin_s'] = analysis.time_origin_s
    return out


def format_summary(analysis: BagAnalysis) -> str:
    """
    Return a short human-readable summary of a replayed bag.

    Parameters
    ----------
    analysis : BagAnalysis
        The replayed bag.

    Returns
    -------
    str
        Several lines: the bag, its duration and samples, then one metric per line.

    """
    rec = analysis.record
    rate = (f' ({(analysis.samples - 1) / analysis.duration_s:.0f} Hz)'
            if analysis.duration_s > 0 else '')
    lines = [f'{analysis.path}: {analysis.samples} samples over {analysis.duration_s:.4f} s'
             f'{rate}, storage {rec.meta.get("storage")}, namespace {rec.meta.get("namespace")}']
    for key in ('controller', 'trajectory', 'experiment'):
        if key in rec.meta:
            lines.append(f'  {key}: {_short(rec.meta[key])}')
    window = ('default' if analysis.steady_state_start_s is None
              else f'from {analysis.steady_state_start_s:g} s')
    lines.append(f'  metrics window: {window}')
    width = max((len(k) for k in analysis.metrics), default=0)
    for key in ordered_keys(list(analysis.metrics)):
        lines.append(f'  {key:<{width}}  {format_metric(key, analysis.metrics[key])}')
    table = rec.meta.get(TABLE_META_KEY)
    if isinstance(table, dict):
        lines.append(f'  learned table: {len(table.get("table_v", ()))} samples, '
                     f'{table.get("periods_learned")} periods learned, design '
                     f'{table.get("design_hash")} (analyze --export-table FILE writes it)')
    if analysis.bode is not None:
        lines.append(f'  Bode estimate ({analysis.bode.label}): low-frequency gain '
                     f'{analysis.bode.dc_gain() * 1e6:.4g} µm/V')
    lines.extend(f'  note: {n}' for n in analysis.notes)
    return '\n'.join(lines)


def _short(value: Any) -> str:
    if isinstance(value, dict):
        kind = value.get('type', value.get('kind'))
        if kind is not None:
            return str(kind)
    text = str(value)
    return text if len(text) <= 80 else text[:77] + '...'
