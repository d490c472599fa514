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
The robustness study: one controller configuration, unchanged, on every stage of a family.

For each stage of :mod:`piezo_stage_ros.core.model.family` and each case of :data:`CASES` (the
Table III sines, the Fig. 12 multi-sine, the Fig. 10 square wave with ideal jumps and with a
2 ms S-curve, the Fig. 9 staircase) the closed loop runs for ``duration_s`` and is measured in
steady state, after ``settle_s`` (1 s by default):

- sines and multi-sine: e_m and e_rms of :func:`piezo_stage_ros.core.loop.metrics.summarize` over
  the whole periods after ``settle_s``;
- lines (a triangle's middle 80 %, a raster line's linear part): e_m and e_rms over those
  samples of the whole periods after ``settle_s``, trace and retrace together
  (:func:`piezo_stage_ros.core.loop.metrics.line_metrics`);
- square wave: e_m and e_rms over the last half of every plateau after ``settle_s`` (the plateau
  error of :func:`piezo_stage_ros.core.loop.experiments.square_edge_metrics`), with overshoot and
  settling time of the edges there;
- staircase (19 nm steps, 50 ms each, continued for the whole run): e_m and e_rms over the last
  half of every level that starts after ``settle_s``;

and, for every case, the command range over the whole run and the RAC's estimates theta_hat and
phi_hat (final value, smallest and largest) beside the stage's true theta and phi
(:func:`piezo_stage_ros.core.model.family.true_estimates`). The sines and the multi-sine also
give the true-position error (``e_rms_true_m``, ``e_max_true_m``: the stage's position before
sensor noise and ADC), which shows tracking below the sensor noise.

The controller is built from the configuration once per run, with a notch in ``model`` mode and
a feed-forward (``feedforward.mode``) designed on the *configured* plant and hysteresis, never
on the member's: nothing is retuned per stage. Given a design per member (``designs``, e.g. each
member commissioned first, as a lab commissions a new stage), each member instead runs the
controller, notch model and feed-forward model of its own design.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Any, Callable, Collection, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError, PiezoStageError
from piezo_stage_ros.core.contracts.interfaces import Controller
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.loop import closed_loop, metrics
from piezo_stage_ros.core.loop.batch import run_batch
from piezo_stage_ros.core.loop.experiments import square_edge_metrics
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.family import member_params, StageVariation, true_estimates
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant, Stage, StageParams

__all__ = ['BATCH_MEMBERS', 'BATCH_RECORD_BYTES', 'CASES', 'COLUMNS', 'DesignFn',
           'MemberDesign', 'RobustnessResult', 'batch_members', 'case_metrics',
           'case_trajectory', 'format_result', 'run_study', 'stage_table', 'summary_table',
           'worst']

#: The cases of the study: name -> (trajectory_node values, what is measured).
CASES: dict[str, tuple[dict[str, Any], str]] = {
    'sine_1': ({'kind': 'sine', 'sine.frequency_hz': 1.0}, 'periodic'),
    'sine_10': ({'kind': 'sine', 'sine.frequency_hz': 10.0}, 'periodic'),
    'sine_50': ({'kind': 'sine', 'sine.frequency_hz': 50.0}, 'periodic'),
    'sine_100': ({'kind': 'sine', 'sine.frequency_hz': 100.0}, 'periodic'),
    # line rates that are not a whole number of samples a period (72.99 and 33.33 at 10 kHz)
    'sine_137': ({'kind': 'sine', 'sine.frequency_hz': 137.0}, 'periodic'),
    'sine_300': ({'kind': 'sine', 'sine.frequency_hz': 300.0}, 'periodic'),
    'triangle_70': ({'kind': 'triangle', 'triangle.frequency_hz': 70.0}, 'periodic'),
    # measured where an image is taken: the middle 80 % of a triangle's lines, the linear
    # part of a raster line (trace and retrace together)
    'triangle_80': ({'kind': 'triangle', 'triangle.frequency_hz': 80.0}, 'lines'),
    'scan_line_137': ({'kind': 'scan_line', 'scan_line.frequency_hz': 137.0}, 'lines'),
    'multisine': ({'kind': 'multisine'}, 'periodic'),
    'square': ({'kind': 'square', 'square.transition_s': 0.0}, 'square'),
    'square_2ms': ({'kind': 'square', 'square.transition_s': 2e-3}, 'square'),
    'staircase': ({'kind': 'staircase', 'staircase.transition_s': 0.0}, 'staircase'),
}

#: The share of the linear range measured by the ``lines`` cases (the rest: all of it).
LINE_MIDDLE = {'triangle_80': 0.8}

#: Columns of the per-case table: (key, header, scale, format, how the worst is chosen).
COLUMNS: tuple[tuple[str, str, float, str, str], ...] = (
    ('e_rms_m', 'e_rms [nm]', 1e9, '.2f', 'max'),
    ('e_max_m', 'e_m [nm]', 1e9, '.1f', 'max'),
    ('e_rms_true_m', 'true e_rms [nm]', 1e9, '.2f', 'max'),
    ('command_min_v', 'u min [V]', 1.0, '.2f', 'min'),
    ('command_max_v', 'u max [V]', 1.0, '.2f', 'max'),
    ('theta_error_pct', 'theta_hat end/true-1 [%]', 1.0, '+.1f', 'abs'),
    ('phi_error_pct', 'phi_hat end/true-1 [%]', 1.0, '+.1f', 'abs'),
)

#: Receives one line of progress.
ProgressFn = Callable[[str], None]


@dataclass(frozen=True)
class MemberDesign:
    """
    The controller one member runs with when each member gets a design of its own.

    Attributes
    ----------
    controller : ControllerParams
        The member's controller (gains, notch, feed-forward mode).
    stage : StageParams
        The model it was designed on: its plant is the notch's and the feed-forward's model,
        its hysteresis the one the feed-forward inverts.
    note : str
        One line on how the design came about (shown beside the member); say here why, when
        the design fell back to the configured one.
    own : bool
        The member's own design; False when it fell back to the configured one.

    """

    controller: ControllerParams
    stage: StageParams
    note: str = ''
    own: bool = True


#: Returns the design of one member from its variation and its (true) stage parameters.
DesignFn = Callable[[StageVariation, StageParams], MemberDesign]


def case_trajectory(case: str, base: TrajectoryParams, duration_s: float) -> TrajectoryParams:
    """
    Return the reference of one case on top of the configured trajectory parameters.

    Parameters
    ----------
    case : str
        A key of :data:`CASES`.
    base : TrajectoryParams
        The configured trajectory parameters (levels, amplitudes, periods of each kind).
    duration_s : float
        Length of the run [s]; the staircase gets enough steps to climb for all of it.

    Returns
    -------
    TrajectoryParams

    """
    if case not in CASES:
        raise ParameterError('--cases', case, ', '.join(CASES))
    values = dict(CASES[case][0])
    if values['kind'] == 'staircase':
        dwell = base.staircase.dwell_s
        values['staircase.steps'] = max(base.staircase.steps,
                                        int(math.ceil(duration_s / dwell - 1e-9)) - 1)
    return base.with_flat(values)


def _nan_metrics() -> dict[str, float]:
    return {'e_max_m': math.nan, 'e_rms_m': math.nan}


def _line_figures(record: RunRecord, start_s: float, period_s: float | None,
                  middle: float) -> dict[str, float]:
    """Return e_m and e_rms over the lines' measured samples, trace and retrace together."""
    window = metrics.window_slice(record.time_s - record.time_s[0], start_s, period_s)
    lm = metrics.line_metrics(record, window, metrics.LineOptions(middle, 0))
    out: dict[str, float] = {}
    for suffix in ('', '_true'):
        figures = [getattr(lm, f'{side}_e_{what}{suffix}_m') for what in ('rms', 'max')
                   for side in ('trace', 'retrace')]
        if any(value is None for value in figures):
            continue
        rms_tr, rms_re, max_tr, max_re = (float(value) for value in figures)
        n_tr, n_re = lm.trace_samples, lm.retrace_samples
        out[f'e_rms{suffix}_m'] = math.sqrt((n_tr * rms_tr ** 2 + n_re * rms_re ** 2)
                                            / max(n_tr + n_re, 1))
        out[f'e_max{suffix}_m'] = max(max_tr, max_re)
    return out


def case_metrics(case: str, record: RunRecord, trajectory: TrajectoryParams, *,
                 settle_s: float) -> dict[str, float]:
    """
    Return the steady-state figures of one run of one case (see the module docstring).

    Parameters
    ----------
    case : str
        A key of :data:`CASES`.
    record : RunRecord
        The run, from t = 0, with ``theta_hat`` / ``phi_hat`` diagnostics when the controller
        has them.
    trajectory : TrajectoryParams
        Its reference (square and staircase geometry).
    settle_s : float
        Start of the steady state [s].

    Returns
    -------
    dict
        ``e_max_m``, ``e_rms_m`` (NaN when the run holds no steady state), ``command_min_v``,
        ``command_max_v``; periodic cases of a run with a true position: ``e_max_true_m``,
        ``e_rms_true_m``; and when present ``theta_hat_end``/``_min``/``_max``,
        ``phi_hat_end``/``_min``/``_max``; square: also ``overshoot_pct``, ``settling_time_s``.

    """
    how = CASES[case][1]
    t = record.time_s
    out: dict[str, float] = {}
    if how in ('periodic', 'lines'):
        period = make_trajectory(trajectory).period_s
        # a record may start late (window_only): the start is counted from its first sample
        s = metrics.summarize(record, steady_state_start_s=settle_s - float(t[0]),
                              period_s=period)
        late = t[-1] + (t[1] - t[0] if t.size > 1 else 0.0) > settle_s + (period or 0.0) - 1e-9
        out.update({'e_max_m': s.e_max_m, 'e_rms_m': s.e_rms_m} if late
                   else _nan_metrics())
        if s.e_rms_true_m is not None and s.e_max_true_m is not None:
            out.update({'e_max_true_m': s.e_max_true_m, 'e_rms_true_m': s.e_rms_true_m}
                       if late else {'e_max_true_m': math.nan, 'e_rms_true_m': math.nan})
        if how == 'lines' and late:
            out.update(_line_figures(record, settle_s - float(t[0]), period,
                                     LINE_MIDDLE.get(case, 1.0)))
    elif how == 'square':
        sq = trajectory.square
        start = math.ceil(settle_s / sq.period_s - 1e-9) * sq.period_s
        i0 = int(np.searchsorted(t, start - 0.5 * (t[1] - t[0]))) if t.size > 1 else t.size
        try:
            m = square_edge_metrics(t[i0:] - start, record.position_m[i0:],
                                    record.reference_m[i0:], sq)
            out.update({'e_max_m': m.ss_e_max_m, 'e_rms_m': m.ss_e_rms_m,
                        'overshoot_pct': m.overshoot_pct,
                        'settling_time_s': m.settling_time_s})
        except PiezoStageError:
            out.update(_nan_metrics())
    else:
        dt = float(t[1] - t[0]) if t.size > 1 else 1.0
        n_dwell = max(int(round(trajectory.staircase.dwell_s / dt)), 1)
        err = record.position_m - record.reference_m
        tails = [err[(j + 1) * n_dwell - n_dwell // 2:(j + 1) * n_dwell]
                 for j in range(t.size // n_dwell) if j * n_dwell * dt >= settle_s - 0.5 * dt]
        tails = [x for x in tails if x.size]
        e_max, e_rms = metrics.error_metrics(np.concatenate(tails)) if tails else (math.nan,
                                                                                  math.nan)
        out.update({'e_max_m': e_max, 'e_rms_m': e_rms})
    out['command_min_v'] = float(np.min(record.command_v))
    out['command_max_v'] = float(np.max(record.command_v))
    for name in ('theta_hat', 'phi_hat'):
        values = record.diagnostics.get(name)
        if values is not None and len(values):
            out[f'{name}_end'] = float(values[-1])
            out[f'{name}_min'] = float(np.min(values))
            out[f'{name}_max'] = float(np.max(values))
    return out


@dataclass
class RobustnessResult:
    """
    Every (stage, case) of a study.

    Attributes
    ----------
    stages : list of dict
        Per stage: ``name``, ``description``, ``changes`` (factors), ``theta_true``,
        ``phi_true``, ``listed`` (printed and plotted one by one; the others, e.g. random
        members, only count in the worst case and the summary line).
    cases : list of str
        The cases run, in order.
    rows : list of dict
        One per (stage, case): ``stage``, ``case`` and the keys of :func:`case_metrics`, plus
        ``theta_error_pct`` and ``phi_error_pct`` (final estimate against the truth).
    traces : dict
        ``(case, stage) -> (time_s, theta_hat, phi_hat)``, the estimates every
        ``trace_every`` samples, for plots (not in the JSON).
    meta : dict
        Controller, duration, steady-state start, the path taken (single runs or batch).

    """

    stages: list[dict[str, Any]] = field(default_factory=list)
    cases: list[str] = field(default_factory=list)
    rows: list[dict[str, Any]] = field(default_factory=list)
    traces: dict[tuple[str, str], tuple[np.ndarray, np.ndarray, np.ndarray]] = \
        field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """Return a JSON-ready dict (NaN becomes None), with the worst case per case."""
        def clean(v: Any) -> Any:
            if isinstance(v, float) and not math.isfinite(v):
                return None
            if isinstance(v, dict):
                return {k: clean(x) for k, x in v.items()}
            return v
        return {'meta': clean(self.meta), 'stages': [clean(s) for s in self.stages],
                'cases': list(self.cases), 'rows': [clean(r) for r in self.rows],
                'worst': {case: clean(worst(self, case)) for case in self.cases},
                'summary': summary_table(self)}


def _stage_rows(name: str, case: str, m: dict[str, float], truth: tuple[float, float]
                ) -> dict[str, Any]:
    row: dict[str, Any] = {'stage': name, 'case': case, **m}
    for key, true in zip(('theta', 'phi'), truth):
        end = m.get(f'{key}_hat_end', math.nan)
        row[f'{key}_error_pct'] = 100.0 * (end / true - 1.0)
    return row


#: Members per batch: the records of a batch are held in memory until measured (56 bytes per
#: member and sample: y, x_d, x_d', u, x, theta_hat, phi_hat), 128 members of a 2 s run take
#: 143 MB.
BATCH_MEMBERS = 128

#: Longer runs batch fewer members, so that a batch's records stay within this many bytes
#: (building them takes about three times as much for a moment): 60 s runs, 35 members.
BATCH_RECORD_BYTES = 1.2e9


def batch_members(samples: int) -> int:
    """Return the members per batch for runs of ``samples`` samples (1 ... BATCH_MEMBERS)."""
    return max(1, min(BATCH_MEMBERS, int(BATCH_RECORD_BYTES // (56 * max(samples, 1)))))


def run_study(stage: StageParams, controller: ControllerParams, trajectory: TrajectoryParams, *,
              family: Sequence[StageVariation], cases: Sequence[str], duration_s: float = 2.0,
              settle_s: float = 1.0, trace_every: int = 10,
              traced: Collection[str] | None = None, batch: bool = True,
              window_only: bool = False, progress: ProgressFn | None = None,
              designs: DesignFn | None = None) -> RobustnessResult:
    """
    Run one controller configuration on every member of a family, for every case.

    Parameters
    ----------
    stage : StageParams
        The configured (nominal) stage; each member is derived from it.
    controller : ControllerParams
        The controller, the same for every stage.
    trajectory : TrajectoryParams
        The configured trajectory parameters (levels and shapes of each kind); each case sets
        its kind on top.
    family : sequence of StageVariation
        The stages (names unique).
    cases : sequence of str
        Keys of :data:`CASES`.
    duration_s : float
        Simulated time per run [s], > ``settle_s``.
    settle_s : float
        Start of the steady state [s], >= 0.
    trace_every : int
        Keep the estimates every this many samples for the plots (>= 1).
    traced : collection of str, optional
        The members whose estimates are kept for the plots; default all.
    batch : bool
        Run the members of each case together (:func:`piezo_stage_ros.core.loop.batch.run_batch`,
        :func:`batch_members` at a time), feed-forward included; with False one
        :func:`closed_loop.run` per member and case. Both give the same samples, bit for bit
        (tested).
    window_only : bool
        Keep the samples from ``settle_s`` on only (long runs: memory, and larger batches);
        the command range and the estimates' ranges then cover that window. Sines and
        multi-sine only.
    progress : callable, optional
        Receives a line per run (single) or per simulated second of a batch.
    designs : callable, optional
        A design per member, made once before its runs (:data:`DesignFn`); default none:
        every member runs ``controller`` designed on ``stage``. Needs ``batch=False`` (a batch
        runs one controller configuration).

    Returns
    -------
    RobustnessResult

    Raises
    ------
    ParameterError
        On a bad duration, no stages or names repeated, an unknown case, a case that cannot be
        measured on a window, or ``designs`` with ``batch``.

    """
    if not (duration_s > settle_s >= 0.0 and math.isfinite(duration_s)):
        raise ParameterError('duration_s', duration_s, f'({settle_s:g}, inf) s',
                             f'leaves no steady state after {settle_s:g} s')
    names = [m.name for m in family]
    if len(set(names)) != len(names) or not names:
        raise ParameterError('stages', names, 'at least one, names unique')
    for case in cases:
        case_trajectory(case, trajectory, duration_s)  # refuse an unknown case up front
        if window_only and CASES[case][1] not in ('periodic', 'lines'):
            raise ParameterError('--cases', case, 'sines and multisine with a window only')
    if designs is not None and batch:
        raise ParameterError('batch', batch, 'False with a design per member',
                             'runs one controller configuration for every member')
    result = RobustnessResult(cases=list(cases), meta={
        'controller': controller.type, 'feedforward': controller.feedforward.mode,
        'duration_s': duration_s, 'settle_s': settle_s, 'window_only': window_only,
        'path': 'batch' if batch else 'single', 'sample_rate_hz': stage.sample_rate_hz,
        'design': 'configured' if designs is None else 'per member'})
    members = [(m, member_params(stage, m)) for m in family]
    # the notch's and feed-forward's model: the configured stage's (or each member's design)
    own = {m.name: MemberDesign(controller, stage) for m, _ in members}
    for m, sp in members:
        theta, phi = true_estimates(sp)
        info: dict[str, Any] = {'name': m.name, 'description': m.describe(),
                                'changes': m.changes(), 'theta_true': theta, 'phi_true': phi,
                                'listed': traced is None or m.name in traced}
        if designs is not None:
            own[m.name] = designs(m, sp)
            info['design'] = own[m.name].note
            info['own_design'] = own[m.name].own
            if progress is not None:
                progress(f'design {m.name}: {own[m.name].note}')
        result.stages.append(info)
    nominal_plant = linear_plant(stage.plant)
    nominal_hysteresis = make_hysteresis(stage.hysteresis)
    dt = stage.sample_time_s
    start_s = settle_s if window_only else 0.0
    size = batch_members(int(round((duration_s - start_s) / dt))) if batch else 1
    for case in cases:
        tp = case_trajectory(case, trajectory, duration_s)
        for g0 in range(0, len(members), size):
            group = members[g0:g0 + size]
            if batch:
                def say(t: float, case: str = case, g0: int = g0, size: int = len(group)
                        ) -> None:
                    if progress is not None:
                        progress(f'{case:10s} members {g0}-{g0 + size - 1}: {t:g} s simulated')
                records = run_batch([sp for _, sp in group], controller, make_trajectory(tp),
                                    duration_s=duration_s, plant=nominal_plant,
                                    hysteresis=nominal_hysteresis, record_from_s=start_s,
                                    progress=say)
            else:
                records = [_window(closed_loop.run(Stage(sp), _member_controller(
                    own[m.name], dt), make_trajectory(tp), duration_s=duration_s,
                    diagnostics_every=1), start_s) for m, sp in group]
            for (m, _), info, rec in zip(group, result.stages[g0:], records):
                mets = case_metrics(case, rec, tp, settle_s=settle_s)
                row = _stage_rows(m.name, case, mets, (info['theta_true'], info['phi_true']))
                result.rows.append(row)
                if 'theta_hat' in rec.diagnostics and (traced is None or m.name in traced):
                    sl = slice(None, None, max(int(trace_every), 1))
                    # copies: a view would keep the whole batch's records alive
                    result.traces[(case, m.name)] = (
                        rec.time_s[sl].copy(), rec.diagnostics['theta_hat'][sl].copy(),
                        rec.diagnostics['phi_hat'][sl].copy())
                if progress is not None and not batch:
                    progress(f'{case:10s} {m.name:22s} e_rms {row["e_rms_m"] * 1e9:8.2f} nm, '
                             f'e_m {row["e_max_m"] * 1e9:8.1f} nm')
    return result


def _member_controller(design: MemberDesign, dt: float) -> Controller:
    """Build a member's controller on its design model (the configured one by default)."""
    return build_controller(design.controller, dt, linear_plant(design.stage.plant),
                            make_hysteresis(design.stage.hysteresis))


def _window(record: RunRecord, start_s: float) -> RunRecord:
    """Return the samples from ``round(start_s / T)`` on (what run_batch records)."""
    if start_s <= 0.0:
        return record
    k = int(round(start_s / float(record.time_s[1] - record.time_s[0])))
    k = min(k, record.time_s.size - 1)

    def cut(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else a[k:].copy()
    return RunRecord(record.time_s[k:].copy(), record.position_m[k:].copy(),
                     record.reference_m[k:].copy(), record.reference_velocity_mps[k:].copy(),
                     record.command_v[k:].copy(),
                     {name: v[k:].copy() for name, v in record.diagnostics.items()},
                     dict(record.meta), cut(record.true_position_m))


def worst(result: RobustnessResult, case: str) -> dict[str, Any]:
    """
    Return the worst stage per column of one case.

    Parameters
    ----------
    result : RobustnessResult
        The study.
    case : str
        One of its cases.

    Returns
    -------
    dict
        ``column -> {'value': ..., 'stage': ...}`` for every column of :data:`COLUMNS` with a
        finite value: largest (``max``), smallest (``min``) or largest in magnitude (``abs``).

    """
    rows = [r for r in result.rows if r['case'] == case]
    out: dict[str, Any] = {}
    for key, _, _, _, how in COLUMNS:
        vals = [(float(r.get(key, math.nan)), r['stage']) for r in rows]
        vals = [(v, s) for v, s in vals if math.isfinite(v)]
        if not vals:
            continue
        if how == 'max':
            v, s = max(vals)
        elif how == 'min':
            v, s = min(vals)
        else:
            v, s = max(vals, key=lambda x: abs(x[0]))
        out[key] = {'value': v, 'stage': s}
    return out


def summary_table(result: RobustnessResult) -> list[str]:
    """
    Return the lines of a Markdown table of the study: the nominal stage and the family's worst.

    One row per case: e_rms of the nominal stage, median and worst over every member (with its
    name), how many members exceed 1.5 times the nominal e_rms, the worst e_m, the command
    range, the largest final estimate error against the truth [%].
    """
    lines = ['| case | nominal e_rms [nm] | median [nm] | worst e_rms [nm] (stage) | '
             '> 1.5 x nominal | worst e_m [nm] | command [V] | theta_hat, phi_hat end vs true '
             '[%] |', '| --- | ---: | ---: | --- | ---: | ---: | --- | --- |']
    for case in result.cases:
        rows = [r for r in result.rows if r['case'] == case]
        nominal = next((r['e_rms_m'] for r in rows if r['stage'] == 'nominal'), math.nan)
        e = np.asarray([r['e_rms_m'] for r in rows], dtype=np.float64)
        finite = e[np.isfinite(e)]
        over = int(np.count_nonzero(finite > 1.5 * nominal)) if math.isfinite(nominal) else 0
        w = worst(result, case)

        def cell(key: str, scale: float, fmt: str, name: bool = True,
                 w: dict[str, Any] = w) -> str:
            if key not in w:
                return '-'
            text = format(w[key]['value'] * scale, fmt)
            return f'{text} ({w[key]["stage"]})' if name else text
        lines.append(
            f'| {case} | {nominal * 1e9:.2f} | '
            f'{float(np.median(finite)) * 1e9 if finite.size else math.nan:.2f} | '
            f'{cell("e_rms_m", 1e9, ".2f")} | {over} of {len(rows)} | '
            f'{cell("e_max_m", 1e9, ".1f", False)} | '
            f'{cell("command_min_v", 1.0, ".2f", False)} ... '
            f'{cell("command_max_v", 1.0, ".2f", False)} | '
            f'{cell("theta_error_pct", 1.0, "+.0f", False)}, '
            f'{cell("phi_error_pct", 1.0, "+.0f", False)} |')
    return lines


def stage_table(result: RobustnessResult) -> list[str]:
    """
    Return the lines of a Markdown table of the study's e_rms [nm], a row per listed stage.

    One column per case; the last row is the worst over every member (listed or not).
    """
    by = {(r['stage'], r['case']): r['e_rms_m'] for r in result.rows}
    lines = ['| e_rms [nm] | ' + ' | '.join(result.cases) + ' |',
             '| --- |' + ' ---: |' * len(result.cases)]
    for st in result.stages:
        if st.get('listed', True):
            cells = [by.get((st['name'], c), math.nan) for c in result.cases]
            lines.append(f'| {st["name"]} | ' + ' | '.join(f'{v * 1e9:.2f}' for v in cells)
                         + ' |')
    worst_cells = []
    for c in result.cases:
        w = worst(result, c).get('e_rms_m')
        worst_cells.append(f'{w["value"] * 1e9:.2f}' if w else '-')
    lines.append(f'| worst of all {len(result.stages)} | ' + ' | '.join(worst_cells) + ' |')
    return lines


def format_result(result: RobustnessResult) -> str:
    """
    Return one plain-text table per case, each with its worst-case line.

    Parameters
    ----------
    result : RobustnessResult
        The study.

    Returns
    -------
    str
        Per case: a header, one line per listed stage (e_rms, e_m, command range, theta_hat
        and phi_hat at the end and their range against the true values), a summary of the
        other members, the worst per column over all.

    """
    truth = {s['name']: (s['theta_true'], s['phi_true']) for s in result.stages}
    listed = {s['name'] for s in result.stages if s.get('listed', True)}
    width = max(len(s['name']) for s in result.stages) if result.stages else 5
    lines: list[str] = []
    meta = result.meta
    ff = meta.get('feedforward', 'none')
    lines.append(f'robustness: {meta.get("controller")}'
                 f'{"" if ff == "none" else " + feed-forward " + str(ff)} on '
                 f'{len(result.stages)} stages, '
                 f'{meta.get("duration_s"):g} s per run, steady state after '
                 f'{meta.get("settle_s"):g} s ({meta.get("path")} runs)')
    if meta.get('design') == 'per member':
        own = [s for s in result.stages if 'design' in s]
        kept = [s for s in own if not s['own_design']]
        lines.append(f'each member runs its own design: {len(own) - len(kept)} of {len(own)} '
                     'from their own commissioning')
        lines += [f'  {s["name"]}: {s["design"]}' for s in own
                  if s.get('listed', True) or s in kept]
    head = (f'{"stage":{width}s} {"e_rms[nm]":>9s} {"e_m[nm]":>8s} {"u min":>6s} {"u max":>6s}'
            f' {"theta end":>9s} {"true":>6s} {"range":>13s} {"phi end":>8s} {"true":>8s} '
            f'{"range":>17s}')
    for case in result.cases:
        lines += ['', f'case {case}', head, '-' * len(head)]
        others = [r['e_rms_m'] for r in result.rows
                  if r['case'] == case and r['stage'] not in listed]
        for r in (r for r in result.rows if r['case'] == case and r['stage'] in listed):
            th, ph = truth[r['stage']]
            lines.append(
                f'{r["stage"]:{width}s} {r["e_rms_m"] * 1e9:9.2f} {r["e_max_m"] * 1e9:8.1f} '
                f'{r["command_min_v"]:6.2f} {r["command_max_v"]:6.2f} '
                f'{r.get("theta_hat_end", math.nan):9.3f} {th:6.3f} '
                f'{r.get("theta_hat_min", math.nan):6.3f}-{r.get("theta_hat_max", math.nan):6.3f}'
                f' {r.get("phi_hat_end", math.nan):8.2e} {ph:8.2e} '
                f'{r.get("phi_hat_min", math.nan):8.2e}-{r.get("phi_hat_max", math.nan):8.2e}')
        e = np.asarray(others, dtype=np.float64) * 1e9
        e = e[np.isfinite(e)]
        if e.size:
            lines.append(f'{len(others)} more members: e_rms [nm] median {np.median(e):.2f}, '
                         f'90 % {np.percentile(e, 90):.2f}, max {np.max(e):.2f}')
        w = worst(result, case)
        parts = []
        for key, header, scale, fmt, _ in COLUMNS:
            if key in w:
                parts.append(f'{header} {format(w[key]["value"] * scale, fmt)} '
                             f'({w[key]["stage"]})')
        lines.append('worst: ' + '; '.join(parts))
    lines += ['', 'summary (every member):', *summary_table(result), '', 'e_rms per stage:',
              *stage_table(result)]
    return '\n'.join(lines)
