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
The paper's experiments (sections III-D and V) run offline, with the paper's numbers as data.

Each ``run_*`` function takes the configured stage and controller parameters, runs the closed
(or open) loop the experiment needs and returns an :class:`ExperimentResult`: rows of "project
vs paper" that :func:`format_result` prints as a table and ``simulate --json`` prints as JSON.
Their optional ``stability`` is a check run on each configuration, whose verdict goes in the
rows, and their optional ``progress`` receives one line per run.

Which plant: the paper designs its controller on the reduced model (25) preceded by the
backlash-like hysteresis, and its PI gains land near its PIC row of Table III only there; the
third-order model (20) is the paper's full linear model. Every closed-loop experiment therefore
runs on both by default (``plants=('reduced', 'third_order')``) and says which in every row.
The hysteresis is the configured one (backlash-like, eq. (21), by default).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Any, Callable, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.interfaces import Trajectory
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.loop import closed_loop, metrics
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.loop.trajectories import (
    make_trajectory,
    SquareParams,
    TableTrajectory,
    TrajectoryBase,
    TrajectoryParams,
)
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant, PlantParams, Stage, StageParams

__all__ = ['EXPERIMENTS', 'ExperimentResult', 'PAPER_FIG10', 'PAPER_FIG12', 'PAPER_FIG6',
           'PAPER_FIG9_RESOLUTION_M', 'PAPER_TABLE3', 'StabilityFn', 'default_duration_s',
           'format_result', 'linear_lag_width_pct', 'open_loop_sine_width', 'run_fig6',
           'square_edge_metrics',
           'run_multisine', 'run_one', 'run_square', 'run_staircase', 'run_table3']

#: Table III: frequency [Hz] -> controller -> (e_m, e_rms) [m], x_d = 3.8 + 3.8 sin(2 pi f t) um.
PAPER_TABLE3: dict[float, dict[str, tuple[float, float]]] = {
    1.0: {'rac': (0.0273e-6, 0.0044e-6), 'pi': (0.0455e-6, 0.0138e-6)},
    10.0: {'rac': (0.0317e-6, 0.0056e-6), 'pi': (0.2056e-6, 0.1314e-6)},
    50.0: {'rac': (0.0484e-6, 0.0176e-6), 'pi': (0.8901e-6, 0.6144e-6)},
    100.0: {'rac': (0.0864e-6, 0.0394e-6), 'pi': (1.4401e-6, 1.0046e-6)},
}
#: Fig. 10 (section V-A): 7.8 um square wave, 0.5 s period, RAC.
PAPER_FIG10: dict[str, float] = {'rise_time_s': 6e-3, 'overshoot_pct': 1.5,
                                 'settling_time_s': 15e-3, 'ss_e_max_m': 20e-9,
                                 'ss_e_rms_m': 4.58e-9}
#: Fig. 9: positioning resolution of the stepwise response [m].
PAPER_FIG9_RESOLUTION_M = 19e-9
#: Fig. 12 (section V-C): loop width of x vs x_d, 10 + 100 Hz multi-sine [% of range].
PAPER_FIG12: dict[str, float] = {'closed_loop_width_pct': 1.05, 'open_loop_width_pct': 17.25}
#: Fig. 6: open loop v_in = 1 + sin(2 pi 100 t) V; the paper shows the loop, not its width.
PAPER_FIG6: dict[float, float | None] = {1.0: None, 10.0: None, 50.0: None, 100.0: None}

#: ``f(stage_params, controller_params) -> (stable or None, one-line text)``, run before a loop.
StabilityFn = Callable[[StageParams, ControllerParams], tuple[bool | None, str]]
#: Receives one line of progress per run.
ProgressFn = Callable[[str], None]


@dataclass
class ExperimentResult:
    """
    Rows of one experiment, project beside paper.

    Attributes
    ----------
    name : str
        ``'table3'``, ``'square'``, ``'staircase'``, ``'multisine'`` or ``'fig6'``.
    title : str
        One line saying what ran (plant, hysteresis, trajectory).
    columns : list of (key, header, scale, format)
        How :func:`format_result` prints each row key (``scale`` multiplies the value).
    rows : list of dict
        One dict per row: plain str / float / bool / None values (JSON-ready).
    notes : list of str
        What the reader must know to compare (windows, definitions, differences).
    summary : list of str
        Optional compact table printed after the notes (Table III: e_rms per frequency).

    """

    name: str
    title: str
    columns: list[tuple[str, str, float, str]]
    rows: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    summary: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        """Return a JSON-ready dict (NaN becomes None)."""
        def clean(v: Any) -> Any:
            return None if isinstance(v, float) and not math.isfinite(v) else v
        return {'experiment': self.name, 'title': self.title, 'notes': list(self.notes),
                'rows': [{k: clean(v) for k, v in row.items()} for row in self.rows],
                'summary': list(self.summary)}


def default_duration_s(trajectory: TrajectoryBase, params: TrajectoryParams) -> float:
    """
    Return a run length that covers the transient and at least two steady-state periods [s].

    Parameters
    ----------
    trajectory : TrajectoryBase
        The built trajectory (its ``period_s``).
    params : TrajectoryParams
        Its parameters (for the aperiodic kinds).

    Returns
    -------
    float
        Periodic: ``max(1 s, skip + 2 periods)`` with the steady-state skip of
        :mod:`piezo_stage_ros.core.loop.metrics`; staircase: every level plus one dwell; step: 0.1
        s after the step; csv: the table's last time (at least one sample); otherwise 1 s.

    """
    period = trajectory.period_s
    if period is not None:
        skip = math.ceil(max(metrics.TRANSIENT_PERIODS * period, metrics.TRANSIENT_S)
                         / period - 1e-9) * period
        return max(1.0, skip + 2 * period)
    if params.kind == 'staircase':
        return (params.staircase.steps + 1) * params.staircase.dwell_s
    if params.kind == 'step':
        return params.step.time_s + 0.1
    if params.kind == 'csv':
        end = trajectory.end_s if isinstance(trajectory, TableTrajectory) else 0.0
        return end if end > 0 else 1.0
    return 1.0


def run_one(stage_params: StageParams, controller_params: ControllerParams,
            trajectory_params: TrajectoryParams, *, duration_s: float | None = None,
            chunk_callback: closed_loop.ChunkCallback | None = None, keep: bool = True,
            meta: dict[str, Any] | None = None, design_plant: PlantParams | None = None,
            diagnostics_every: int = 10, built: Callable[[Any], None] | None = None,
            trajectory: Trajectory | None = None) -> RunRecord:
    """
    Build a stage, a controller and a trajectory and run one closed loop.

    Parameters
    ----------
    stage_params : StageParams
        The stage (plant, hysteresis, signal chain, seed).
    controller_params : ControllerParams
        The controller (a notch in ``model`` mode is designed on the stage's plant).
    trajectory_params : TrajectoryParams
        The reference.
    duration_s : float, optional
        Simulated time [s]; default :func:`default_duration_s`.
    chunk_callback : callable, optional
        Passed to :func:`piezo_stage_ros.core.loop.closed_loop.run`.
    keep : bool
        Passed to :func:`piezo_stage_ros.core.loop.closed_loop.run`.
    meta : dict, optional
        Extra description stored in the record.
    design_plant : PlantParams, optional
        The model a ``model`` notch is designed on; default the stage's plant
        (:attr:`piezo_stage_ros.core.config.loader.LoopConfig.design_plant`).
    diagnostics_every : int
        Passed to :func:`piezo_stage_ros.core.loop.closed_loop.run`.
    built : callable, optional
        Called with the controller before the run (a caller that reads its state afterwards:
        a feed-forward's learned table).
    trajectory : Trajectory, optional
        The reference itself (a line rate changed during the run,
        :class:`~piezo_stage_ros.core.loop.switched.LineRateChange`); default the one of
        ``trajectory_params``.

    Returns
    -------
    RunRecord
        The run; ``meta`` holds plant, hysteresis, controller type, trajectory kind, seed.

    """
    stage = Stage(stage_params)
    plant = linear_plant(stage_params.plant if design_plant is None else design_plant)
    controller = build_controller(controller_params, stage_params.sample_time_s, plant,
                                  make_hysteresis(stage_params.hysteresis))
    base = make_trajectory(trajectory_params, sample_rate_hz=stage_params.sample_rate_hz)
    if trajectory is None:
        trajectory = base
    if duration_s is None:
        duration_s = default_duration_s(base, trajectory_params)
    run_meta: dict[str, Any] = {
        'plant': stage_params.plant.model, 'hysteresis': stage_params.hysteresis.model,
        'controller': controller_params.type, 'trajectory': trajectory_params.kind,
        'seed': stage_params.seed, 'sample_rate_hz': stage_params.sample_rate_hz,
    }
    run_meta.update(meta or {})
    if built is not None:
        built(controller)
    return closed_loop.run(stage, controller, trajectory, duration_s=duration_s,
                           chunk_callback=chunk_callback, keep=keep, meta=run_meta,
                           diagnostics_every=diagnostics_every)


def _with_plant(stage_params: StageParams, plant: str) -> StageParams:
    return stage_params.with_flat({'plant.model': plant})


def _verdict(stability: StabilityFn | None, stage_params: StageParams,
             controller_params: ControllerParams) -> bool | None:
    if stability is None:
        return None
    return stability(stage_params, controller_params)[0]


def _say(progress: ProgressFn | None, line: str) -> None:
    if progress is not None:
        progress(line)


def run_table3(stage_params: StageParams, controllers: dict[str, ControllerParams], *,
               plants: Sequence[str] = ('reduced', 'third_order'),
               frequencies_hz: Sequence[float] = (1.0, 10.0, 50.0, 100.0),
               stability: StabilityFn | None = None, progress: ProgressFn | None = None
               ) -> ExperimentResult:
    """
    Track x_d = 3.8 + 3.8 sin(2 pi f t) um with the RAC and the PI (Table III).

    Parameters
    ----------
    stage_params : StageParams
        The configured stage; its plant model is replaced by each of ``plants``.
    controllers : dict of str to ControllerParams
        ``{'rac': ..., 'pi': ...}`` (configured gains; their ``type`` is the key).
    plants : sequence of str
        Plant models to run on.
    frequencies_hz : sequence of float
        Frequencies of Table III [Hz].
    stability : callable, optional
        Stability check run before each configuration; its verdict goes in the rows.
    progress : callable, optional
        Receives one line per run.

    Returns
    -------
    ExperimentResult
        One row per (plant, controller, frequency): e_m and e_rms of the project and of the
        paper [m], their ratio, command range, stability verdict.

    """
    result = ExperimentResult(
        name='table3',
        title=('Table III: x_d = 3.8 + 3.8 sin(2 pi f t) um, hysteresis '
               f'{stage_params.hysteresis.model}, {stage_params.sample_rate_hz:g} Hz'),
        columns=[('plant', 'plant', 1.0, 's'), ('controller', 'ctrl', 1.0, 's'),
                 ('frequency_hz', 'f [Hz]', 1.0, 'g'), ('e_max_m', 'e_m [nm]', 1e9, '.1f'),
                 ('paper_e_max_m', 'paper e_m', 1e9, '.1f'),
                 ('e_rms_m', 'e_rms [nm]', 1e9, '.1f'),
                 ('paper_e_rms_m', 'paper e_rms', 1e9, '.1f'),
                 ('rms_ratio', 'rms/paper', 1.0, '.2f'), ('command_min_v', 'u min', 1.0, '.2f'),
                 ('command_max_v', 'u max', 1.0, '.2f'), ('stable', 'stable', 1.0, 's')])
    for plant in plants:
        sp = _with_plant(stage_params, plant)
        for name, cp in controllers.items():
            stable = _verdict(stability, sp, cp)
            for f in frequencies_hz:
                tp = TrajectoryParams.from_flat({'kind': 'sine', 'sine.frequency_hz': f,
                                                 'sine.offset_m': 3.8e-6,
                                                 'sine.amplitude_m': 3.8e-6})
                rec = run_one(sp, cp, tp)
                s = metrics.summarize(rec)
                paper = PAPER_TABLE3.get(float(f), {}).get(cp.type)
                row: dict[str, Any] = {
                    'plant': plant, 'controller': name, 'frequency_hz': float(f),
                    'e_max_m': s.e_max_m, 'e_rms_m': s.e_rms_m,
                    'paper_e_max_m': paper[0] if paper else math.nan,
                    'paper_e_rms_m': paper[1] if paper else math.nan,
                    'rms_ratio': s.e_rms_m / paper[1] if paper else math.nan,
                    'command_min_v': s.command_min_v, 'command_max_v': s.command_max_v,
                    'stable': stable, 'duration_s': s.duration_s,
                    'steady_state_start_s': s.steady_state_start_s}
                result.rows.append(row)
                _say(progress, f'table3: {plant:11s} {name:4s} {f:6g} Hz: e_rms '
                               f'{s.e_rms_m * 1e9:9.1f} nm (paper '
                               f'{row["paper_e_rms_m"] * 1e9:.1f})')
    result.summary = _table3_matrix(result.rows, list(frequencies_hz))
    result.notes += [
        'e_m, e_rms: measured position (16-bit ADC) minus x_d over the steady-state window: '
        f'after max({metrics.TRANSIENT_PERIODS} periods, {metrics.TRANSIENT_S:g} s), whole '
        'periods to the end of the run (1 Hz: 2 s skipped, 4 s run; others: 1 s run).',
        'Paper rows are experiments on the real stage; the project rows are simulations.',
        'reduced = eq. (25), the model the paper designs on; third_order = eq. (20).',
    ]
    return result


def _table3_matrix(rows: list[dict[str, Any]], frequencies: list[float]) -> list[str]:
    """Return e_rms [nm] per frequency: the paper's two rows, then one row per run series."""
    head = f'{"e_rms [nm]":38s}' + ''.join(f'{f:>9g} Hz' for f in frequencies)
    lines = [head, '-' * len(head)]
    for ctrl, label in (('rac', 'paper RAC (experiment)'), ('pi', 'paper PIC (experiment)')):
        vals = [PAPER_TABLE3.get(float(f), {}).get(ctrl, (math.nan, math.nan))[1]
                for f in frequencies]
        lines.append(f'{label:38s}' + ''.join(f'{v * 1e9:12.1f}' for v in vals))
    series: dict[tuple[str, str], dict[float, float]] = {}
    for row in rows:
        series.setdefault((row['controller'], row['plant']), {})[row['frequency_hz']] = \
            row['e_rms_m']
    for (ctrl, plant), values in series.items():
        label = f'project {ctrl.upper()} ({plant}, simulation)'
        lines.append(f'{label:38s}' + ''.join(
            f'{values.get(float(f), math.nan) * 1e9:12.1f}' for f in frequencies))
    return lines


def square_edge_metrics(time_s: np.ndarray, position_m: np.ndarray, reference_m: np.ndarray,
                        square: SquareParams, *, settle_band_m: float = 0.0,
                        plateau_fraction: float = 0.5) -> metrics.EdgeMetrics:
    """
    Return the step-response figures of a square-wave run, edges taken from its parameters.

    Parameters
    ----------
    time_s, position_m, reference_m : ndarray
        Samples of the run from t = 0 [s], [m], [m].
    square : SquareParams
        The square wave (levels, period, duty, ``transition_s``).
    settle_band_m : float
        Absolute settling band [m] (see :func:`piezo_stage_ros.core.loop.metrics.step_response`).
    plateau_fraction : float
        Last fraction of each plateau taken as steady state, in (0, 1].

    Returns
    -------
    EdgeMetrics
        The figures of :func:`piezo_stage_ros.core.loop.metrics.square_wave_metrics`. Each edge is
        measured from the time of the ideal jump, which is where a shaped transition starts,
        between the two levels (not the moving reference): rise time 10-90 % and settling of the
        measured position, so for a shaped reference they include the reference's own motion.
        Steady state: measured minus reference over the last ``plateau_fraction`` of each
        plateau. With ``transition_s = 0`` the numbers are those of ``square_wave_metrics``.

    """
    t = np.asarray(time_s, dtype=np.float64)
    y = np.asarray(position_m, dtype=np.float64)
    r = np.asarray(reference_m, dtype=np.float64)
    dt = float(t[1] - t[0]) if t.size > 1 else 0.0
    period = square.period_s
    low, high = square.low_m, square.low_m + square.peak_to_peak_m
    edges: list[tuple[float, float, float]] = []      # (time, initial, final)
    n = 0
    while True:
        rise = (n + (1.0 - square.duty)) * period
        fall = (n + 1) * period
        if rise > t[-1]:
            break
        edges.append((rise, low, high))
        if fall <= t[-1]:
            edges.append((fall, high, low))
        n += 1
    indexed = [(int(np.searchsorted(t, te - 0.5 * dt)), initial, final)
               for te, initial, final in edges]
    return metrics.edge_metrics(t, y, r, indexed, settle_band_m=settle_band_m,
                                plateau_fraction=plateau_fraction,
                                what=f'square_edge_metrics: no complete edge; run longer than '
                                f'{period:g} s')


def run_square(stage_params: StageParams, controller_params: ControllerParams, *,
               plants: Sequence[str] = ('reduced', 'third_order'), periods: int = 3,
               settle_band_m: float = 0.0,
               transitions_s: Sequence[float] = (0.0, 1e-3, 2e-3),
               stability: StabilityFn | None = None,
               progress: ProgressFn | None = None) -> ExperimentResult:
    """
    Track the 7.8 um, 0.5 s square wave of Fig. 10 and report its step-response figures.

    Parameters
    ----------
    stage_params : StageParams
        The configured stage.
    controller_params : ControllerParams
        The controller (the paper uses the RAC).
    plants : sequence of str
        Plant models to run on.
    periods : int
        Square-wave periods to run.
    settle_band_m : float
        Absolute settling band [m]; the band is max(2 % of the step, this).
    transitions_s : sequence of float
        Reference shapes to run [s]: 0 is the paper's ideal square wave, T_r > 0 the same wave
        with every jump replaced by a quintic S-curve of duration T_r (``square.transition_s``).
    stability, progress : callable, optional
        The stability check and the progress line (module docstring).

    Returns
    -------
    ExperimentResult
        The paper's Fig. 10 figures, then per plant and reference shape: rise time,
        overshoot, settling time, steady-state e_m and e_rms, theta_hat range, verdict.

    """
    base = TrajectoryParams.from_flat({'kind': 'square'})
    period = base.square.period_s
    result = ExperimentResult(
        name='square', title=(f'Fig. 10: square wave {base.square.peak_to_peak_m * 1e6:g} um '
                              f'peak to peak, {period:g} s period, {controller_params.type}, '
                              f'hysteresis {stage_params.hysteresis.model}'),
        columns=[('plant', 'plant', 1.0, 's'), ('reference', 'reference', 1.0, 's'),
                 ('rise_time_s', 'rise [ms]', 1e3, '.3g'),
                 ('overshoot_pct', 'overshoot [%]', 1.0, '.3g'),
                 ('settling_time_s', 'settling [ms]', 1e3, '.3g'),
                 ('ss_e_max_m', 'ss e_m [nm]', 1e9, '.3g'),
                 ('ss_e_rms_m', 'ss e_rms [nm]', 1e9, '.3g'),
                 ('theta_hat_min', 'theta_hat min', 1.0, '.3f'),
                 ('theta_hat_max', 'max', 1.0, '.3f'), ('stable', 'stable', 1.0, 's')])
    result.rows.append({'plant': 'paper', 'reference': 'real stage', 'transition_s': math.nan,
                        **PAPER_FIG10, 'theta_hat_min': math.nan, 'theta_hat_max': math.nan,
                        'stable': None})
    for plant in plants:
        sp = _with_plant(stage_params, plant)
        stable = _verdict(stability, sp, controller_params)
        for tr in transitions_s:
            tp = base.with_flat({'square.transition_s': float(tr)})
            rec = run_one(sp, controller_params, tp, duration_s=periods * period)
            m = square_edge_metrics(rec.time_s, rec.position_m, rec.reference_m, tp.square,
                                    settle_band_m=settle_band_m)
            theta = np.asarray(rec.diagnostics.get('theta_hat', [math.nan]), dtype=np.float64)
            label = 'ideal jump (paper)' if tr == 0.0 else f'S-curve {tr * 1e3:g} ms'
            result.rows.append({'plant': plant, 'reference': label, 'transition_s': float(tr),
                                **{k: getattr(m, k) for k in PAPER_FIG10},
                                'settling_time_max_s': m.settling_time_max_s,
                                'theta_hat_min': float(np.min(theta)),
                                'theta_hat_max': float(np.max(theta)), 'stable': stable})
            _say(progress, f'square: {plant:11s} {label:18s} rise {m.rise_time_s * 1e3:.2f} '
                           f'ms, overshoot {m.overshoot_pct:.2f} %, settling '
                           f'{m.settling_time_s * 1e3:.2f} ms, ss e_rms '
                           f'{m.ss_e_rms_m * 1e9:.2f} nm')
    result.notes += [
        'Medians over every edge of the run (rising and falling), each measured from the time '
        'of the ideal jump between the two levels: rise time 10-90 % of the step and settling '
        f'into max(2 % of the step, {settle_band_m * 1e9:g} nm) for good, of the measured '
        'position; overshoot past the final level in % of the step; steady state = measured '
        'minus reference over the last half of each plateau.',
        'ideal jump (paper): the reference jumps 7.8 um in one sample, as in Fig. 10; the '
        'error is then the whole step, and the overshoot is that of a fast PI-type loop '
        '(integral zero at lambda) answering a step, not a metric artefact.',
        'S-curve T_r: the same square wave with each jump replaced by the quintic '
        '10u^3 - 15u^4 + 6u^5 over T_r (trajectory_node square.transition_s); rise and '
        'settling then include the motion of the reference itself (10-90 % of the S-curve '
        'alone is 0.48 T_r).',
        'Paper: 6 ms rise, 1.5 % overshoot and 15 ms settling of the real stage with the '
        'paper tuning (epsilon = 0.005); the default discrete tuning is far faster.',
    ]
    return result


def run_staircase(stage_params: StageParams, controller_params: ControllerParams, *,
                  plants: Sequence[str] = ('reduced', 'third_order'),
                  step_m: float = PAPER_FIG9_RESOLUTION_M, steps: int = 10,
                  dwell_s: float = 0.05, stability: StabilityFn | None = None,
                  progress: ProgressFn | None = None) -> ExperimentResult:
    """
    Climb a staircase of ``step_m`` steps (Fig. 9) and check every step is resolved.

    Parameters
    ----------
    stage_params : StageParams
        The configured stage (its sensor noise and ADC set what can be resolved).
    controller_params : ControllerParams
        The controller (the paper uses the RAC).
    plants : sequence of str
        Plant models to run on.
    step_m : float
        Step height [m] (the paper's resolution, 19 nm).
    steps : int
        Number of steps.
    dwell_s : float
        Time on each level [s].
    stability, progress : callable, optional
        The stability check and the progress line (module docstring).

    Returns
    -------
    ExperimentResult
        Per plant: mean, smallest and largest measured step (plateau means over the last half
        of each dwell), the plateau noise (largest peak-to-peak), whether every step is
        resolved (each measured step within 50 % of ``step_m`` and larger than the plateau
        peak-to-peak), beside the paper's 19 nm.

    """
    tp = TrajectoryParams.from_flat({'kind': 'staircase', 'staircase.step_m': step_m,
                                     'staircase.steps': steps, 'staircase.dwell_s': dwell_s})
    result = ExperimentResult(
        name='staircase', title=(f'Fig. 9: staircase of {steps} steps of {step_m * 1e9:g} nm, '
                                 f'{dwell_s * 1e3:g} ms each, {controller_params.type}'),
        columns=[('plant', 'plant', 1.0, 's'), ('step_mean_m', 'step mean [nm]', 1e9, '.2f'),
                 ('step_min_m', 'min [nm]', 1e9, '.2f'), ('step_max_m', 'max [nm]', 1e9, '.2f'),
                 ('plateau_pp_m', 'plateau p-p [nm]', 1e9, '.2f'),
                 ('resolved', 'resolved', 1.0, 's'),
                 ('paper_resolution_m', 'paper [nm]', 1e9, '.0f'),
                 ('stable', 'stable', 1.0, 's')])
    for plant in plants:
        sp = _with_plant(stage_params, plant)
        stable = _verdict(stability, sp, controller_params)
        rec = run_one(sp, controller_params, tp, duration_s=(steps + 1) * dwell_s)
        n_dwell = int(round(dwell_s / sp.sample_time_s))
        means, pps = [], []
        for j in range(steps + 1):
            seg = rec.position_m[j * n_dwell + n_dwell // 2:(j + 1) * n_dwell]
            means.append(float(np.mean(seg)))
            pps.append(float(np.ptp(seg)))
        diffs = np.diff(means)
        pp = max(pps)
        resolved = bool(np.all(np.abs(diffs - step_m) < 0.5 * abs(step_m))
                        and np.all(np.abs(diffs) > pp))
        result.rows.append({'plant': plant, 'step_mean_m': float(np.mean(diffs)),
                            'step_min_m': float(np.min(diffs)),
                            'step_max_m': float(np.max(diffs)), 'plateau_pp_m': pp,
                            'resolved': resolved, 'paper_resolution_m': PAPER_FIG9_RESOLUTION_M,
                            'stable': stable})
        _say(progress, f'staircase: {plant:11s} mean step {np.mean(diffs) * 1e9:.2f} nm, '
                       f'resolved {resolved}')
    lsb = stage_params.chain.adc_lsb_m
    result.notes += [
        f'The ADC step is {lsb * 1e9:.2f} nm and the sensor noise '
        f'{stage_params.chain.sensor_noise_std_m * 1e9:g} nm rms (chain.sensor_noise_std_m): '
        'these, not the controller, bound the resolution in simulation.',
    ]
    return result


def run_multisine(stage_params: StageParams, controller_params: ControllerParams,
                  open_loop_params: ControllerParams, *,
                  plants: Sequence[str] = ('reduced', 'third_order'),
                  stability: StabilityFn | None = None, progress: ProgressFn | None = None
                  ) -> ExperimentResult:
    """
    Track the 10 + 100 Hz multi-sine of Fig. 12; loop width of x vs x_d, closed vs open loop.

    Parameters
    ----------
    stage_params : StageParams
        The configured stage.
    controller_params : ControllerParams
        The closed-loop controller (the paper uses the RAC).
    open_loop_params : ControllerParams
        The open-loop command (``type='open_loop'``: the static inverse v = x_d / (g c)).
    plants : sequence of str
        Plant models to run on.
    stability, progress : callable, optional
        The stability check and the progress line (module docstring).

    Returns
    -------
    ExperimentResult
        Per plant and loop: loop width [% of range], e_m and e_rms, beside Fig. 12's widths.

    """
    tp = TrajectoryParams.from_flat({'kind': 'multisine'})
    ms = tp.multisine
    result = ExperimentResult(
        name='multisine',
        title=('Fig. 12: x_d = ' + f'{ms.offset_m * 1e6:g}'
               + ''.join(f' + {a * 1e6:g} sin(2 pi {f:g} t)'
                         for a, f in zip(ms.amplitudes_m, ms.frequencies_hz))
               + f' um, hysteresis {stage_params.hysteresis.model}'),
        columns=[('plant', 'plant', 1.0, 's'), ('loop', 'loop', 1.0, 's'),
                 ('loop_width_pct', 'width [%]', 1.0, '.2f'),
                 ('paper_width_pct', 'paper [%]', 1.0, '.2f'),
                 ('e_max_m', 'e_m [nm]', 1e9, '.1f'), ('e_rms_m', 'e_rms [nm]', 1e9, '.1f'),
                 ('stable', 'stable', 1.0, 's')])
    for plant in plants:
        sp = _with_plant(stage_params, plant)
        for loop, cp, paper in (('closed', controller_params,
                                 PAPER_FIG12['closed_loop_width_pct']),
                                ('open', open_loop_params, PAPER_FIG12['open_loop_width_pct'])):
            stable = _verdict(stability, sp, cp) if loop == 'closed' else None
            rec = run_one(sp, cp, tp)
            s = metrics.summarize(rec)
            result.rows.append({'plant': plant, 'loop': f'{loop} ({cp.type})',
                                'loop_width_pct': s.loop_width_pct, 'paper_width_pct': paper,
                                'e_max_m': s.e_max_m, 'e_rms_m': s.e_rms_m,
                                'stable': stable})
            _say(progress, f'multisine: {plant:11s} {loop:6s} loop width '
                           f'{s.loop_width_pct:.2f} %')
    result.notes += [
        'Loop width: largest vertical distance between the ascending and descending branches '
        'of x (measured) vs x_d, in % of the range of x, over the steady-state window.',
        'Open loop: the static inverse v = x_d / (g c) of the controller type open_loop.',
        'The paper does not state the amplitudes of its multi-sine; this one uses '
        'trajectory_node multisine.* (config/multisine.yaml).',
    ]
    return result


def open_loop_sine_width(stage_params: StageParams, frequency_hz: float, *,
                         offset_v: float = 1.0, amplitude_v: float = 1.0,
                         periods: int = 4) -> dict[str, float]:
    """
    Drive the stage open loop with v_in = offset + A sin(2 pi f t); loop width of x vs v_in.

    Parameters
    ----------
    stage_params : StageParams
        The stage (plant, hysteresis, converters).
    frequency_hz : float
        Frequency f [Hz].
    offset_v, amplitude_v : float
        Offset and amplitude of v_in [V] (Fig. 6: 1 + 1 sin).
    periods : int
        Steady-state periods measured, after a transient of max(2 periods, 0.1 s).

    Returns
    -------
    dict
        ``loop_width_pct`` (measured x vs v_in, paired at the same sample t_k, as a data
        acquisition records them), ``range_m`` (peak-to-peak of x) and ``duration_s``.

    """
    dt = stage_params.sample_time_s
    period = 1.0 / frequency_hz
    skip = math.ceil(max(metrics.TRANSIENT_PERIODS * period, metrics.TRANSIENT_S)
                     / period - 1e-9) * period
    n = int(round((skip + periods * period) / dt))
    t = np.arange(n) * dt
    v = offset_v + amplitude_v * np.sin(2 * np.pi * frequency_hz * t)
    stage = Stage(stage_params)
    # at rest at the position the mean input holds, so the transient is short
    slope = make_hysteresis(stage_params.hysteresis).slope
    rest_m = offset_v * slope * linear_plant(stage_params.plant).dc_gain_m_per_v
    y0 = stage.reset(min(max(rest_m, 0.0), 38e-6))
    after = stage.run_open_loop(v)
    y = np.concatenate(([y0], after[:-1]))  # y_k pairs with v_k, both at t_k
    i0 = int(round(skip / dt))
    return {'loop_width_pct': metrics.loop_width(v[i0:], y[i0:]),
            'range_m': float(np.ptp(y[i0:])), 'duration_s': n * dt,
            'linear_width_pct': linear_lag_width_pct(stage_params, frequency_hz)}


def linear_lag_width_pct(stage_params: StageParams, frequency_hz: float) -> float:
    """
    Return the loop width the linear part alone gives: 100 sin(phase lag) [% of range].

    Parameters
    ----------
    stage_params : StageParams
        The stage (its plant model and sample rate; the hysteresis is left out).
    frequency_hz : float
        Frequency of the input sine [Hz].

    Returns
    -------
    float
        For a linear system a sine input gives an ellipse of width 2 |H| A sin(phi) over a
        range 2 |H| A: the width is ``100 sin(phi)`` with phi the phase lag of the *sampled*
        transfer H(z) = c (zI - Ad)^-1 Bd from v_k to y_k at z = exp(j omega T), the same
        pairing as :func:`open_loop_sine_width`.

    """
    d = linear_plant(stage_params.plant).discretize(stage_params.sample_time_s)
    z = complex(math.cos(2 * math.pi * frequency_hz * d.sample_time_s),
                math.sin(2 * math.pi * frequency_hz * d.sample_time_s))
    n = d.ad.shape[0]
    h = complex(d.c @ np.linalg.solve(z * np.eye(n) - d.ad, d.bd[:, 0].astype(complex)))
    lag = -math.atan2(h.imag, h.real)
    return 100.0 * abs(math.sin(lag))


def run_fig6(stage_params: StageParams, *,
             frequencies_hz: Sequence[float] = (1.0, 10.0, 50.0, 100.0),
             progress: ProgressFn | None = None) -> ExperimentResult:
    """
    Open loop, v_in = 1 + sin(2 pi f t) V (Fig. 6): loop width of x vs v_in per frequency.

    Parameters
    ----------
    stage_params : StageParams
        The configured stage (plant and hysteresis as configured).
    frequencies_hz : sequence of float
        Frequencies [Hz].
    progress : callable, optional
        Receives one line per run.

    Returns
    -------
    ExperimentResult
        One row per frequency: loop width [% of the output range] and the output range [um].

    """
    result = ExperimentResult(
        name='fig6', title=(f'Fig. 6: open loop v_in = 1 + sin(2 pi f t) V, plant '
                            f'{stage_params.plant.model}, hysteresis '
                            f'{stage_params.hysteresis.model}'),
        columns=[('frequency_hz', 'f [Hz]', 1.0, 'g'),
                 ('loop_width_pct', 'loop width [%]', 1.0, '.2f'),
                 ('linear_width_pct', 'linear lag alone [%]', 1.0, '.2f'),
                 ('range_m', 'range [um]', 1e6, '.3f')])
    for f in frequencies_hz:
        m = open_loop_sine_width(stage_params, float(f))
        result.rows.append({'frequency_hz': float(f), 'loop_width_pct': m['loop_width_pct'],
                            'linear_width_pct': m['linear_width_pct'], 'range_m': m['range_m']})
        _say(progress, f'fig6: {f:g} Hz: loop width {m["loop_width_pct"]:.2f} %')
    result.notes += [
        'Loop width: largest vertical distance between the branches of x (measured) vs v_in, '
        'in % of the range of x; x_k and v_k paired at the same sample time t_k.',
        'The backlash-like hysteresis alone gives about 1.4 % at this amplitude (rate '
        'independent); the rest is the phase lag of the linear plant and of the sampling: '
        '"linear lag alone" is 100 sin(phase lag) of the sampled plant from v_k to y_k, '
        'which includes the half-sample delay of the zero-order hold (1.8 deg at 100 Hz).',
    ]
    return result


def format_result(result: ExperimentResult) -> str:
    """
    Return the result as a plain-text table with its title and notes.

    Parameters
    ----------
    result : ExperimentResult
        Rows to print.

    Returns
    -------
    str
        Title line, header, one line per row, then the notes.

    """
    headers = [h for _, h, _, _ in result.columns]
    lines_cells: list[list[str]] = []
    for row in result.rows:
        cells = []
        for key, _, scale, fmt in result.columns:
            value = row.get(key)
            if value is None:
                cells.append('-')
            elif isinstance(value, bool):
                cells.append('yes' if value else 'NO')
            elif isinstance(value, float):
                cells.append('-' if not math.isfinite(value) else format(value * scale, fmt))
            else:
                cells.append(str(value))
        lines_cells.append(cells)
    widths = [max([len(h)] + [len(c[i]) for c in lines_cells]) for i, h in enumerate(headers)]
    out = [result.title, '  '.join(h.rjust(w) for h, w in zip(headers, widths))]
    out.append('  '.join('-' * w for w in widths))
    out += ['  '.join(c.rjust(w) for c, w in zip(cells, widths)) for cells in lines_cells]
    out += [f'* {note}' for note in result.notes]
    if result.summary:
        out += [''] + result.summary
    return '\n'.join(out)


#: The experiments ``simulate --experiment`` knows.
EXPERIMENTS = ('table3', 'square', 'staircase', 'multisine', 'fig6')
