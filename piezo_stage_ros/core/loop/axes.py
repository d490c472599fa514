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
The offline closed loop of a multi-axis stage, and per-axis metrics.

One sample k, for every axis at once, in the order of the one-axis loop
(:mod:`piezo_stage_ros.core.loop.closed_loop`)::

    x_d,j, x_d,j' = trajectory_j(t_k)                 (per chunk, vectorised)
    u_k = controller.step(y_k, x_d, x_d')             (one command per axis)
    record (t_k, y_k, x_d, x_d', u_k) and the true positions x(t_k)
    y_k+1 = stage.step(u_k)

The controllers are bound to their trajectories (:meth:`AxesController.bind`) and reset from
y_0 and x_d(0) before the first step, as in the one-axis loop; a one-axis run therefore gives
the samples of :func:`closed_loop.run` bit for bit. The result is one
:class:`~piezo_stage_ros.core.loop.record.RunRecord` per axis.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import math
from typing import Any, Mapping, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError, PiezoStageError
from piezo_stage_ros.core.contracts.interfaces import Trajectory
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.control.axes import AxesController
from piezo_stage_ros.core.loop.metrics import error_metrics
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.model.axes import AxesStage

__all__ = ['AxisMetrics', 'axis_metrics', 'frame_images', 'middle_of_lines', 'run_axes']


def run_axes(stage: AxesStage, controller: AxesController,
             trajectories: Sequence[Trajectory], *, duration_s: float,
             initial_positions_m: Sequence[float | None] | None = None, chunk_s: float = 1.0,
             meta: Mapping[str, Any] | None = None) -> list[RunRecord]:
    """
    Run the multi-axis closed loop for ``duration_s`` and return one record per axis.

    Parameters
    ----------
    stage : AxesStage
        The stage (reset here).
    controller : AxesController
        One controller per axis (bound and reset here).
    trajectories : sequence of Trajectory
        One reference per axis; t = 0 is the first sample.
    duration_s : float
        Simulated time [s]; ``round(duration_s / T)`` samples, at least one.
    initial_positions_m : sequence, optional
        Each axis' own rest position [m] (None: its default).
    chunk_s : float
        The references are evaluated per chunk of this length [s].
    meta : Mapping, optional
        Copied into every record's meta, with ``axis``, ``sample_time_s``, ``duration_s`` and
        the axis' ``trajectory_period_s`` when it has one.

    Returns
    -------
    list of RunRecord
        One per axis, in the stage's axis order, with the true positions.

    Raises
    ------
    ParameterError
        A bad duration or chunk, a trajectory count that is not one per axis, or a controller
        whose sample time differs from the stage's.
    PiezoStageError
        A trajectory that returns arrays of the wrong shape.

    """
    n = stage.n
    dt = float(stage.sample_time_s)
    if not (duration_s > 0.0 and math.isfinite(duration_s)):
        raise ParameterError('duration_s', duration_s, '(0, inf)')
    if not (chunk_s > 0.0 and math.isfinite(chunk_s)):
        raise ParameterError('chunk_s', chunk_s, '(0, inf)')
    if len(trajectories) != n or controller.n != n:
        raise ParameterError('trajectories', len(trajectories),
                             f'{n}, one per axis {list(stage.names)} (controllers: '
                             f'{controller.n})')
    if abs(controller.sample_time_s - dt) > 1e-12 * dt:
        raise ParameterError('controller.sample_time_s', controller.sample_time_s,
                             f'the stage sample time {dt:g} s')
    total = max(int(round(duration_s / dt)), 1)
    per_chunk = max(int(round(chunk_s / dt)), 1)
    controller.bind(trajectories)
    y = stage.reset(initial_positions_m)
    x0 = [float(np.asarray(tr.evaluate(np.zeros(1))[0])[0]) for tr in trajectories]
    controller.reset(y, x0)
    step, plant_step, read_true = controller.step, stage.step, stage.read_positions_m
    pos = np.empty((total, n))
    cmd = np.empty((total, n))
    true = np.empty((total, n))
    ref = np.empty((total, n))
    vel = np.empty((total, n))
    k0 = 0
    while k0 < total:
        m = min(per_chunk, total - k0)
        time_s = np.arange(k0, k0 + m, dtype=np.float64) * dt
        for j, tr in enumerate(trajectories):
            r, v = tr.evaluate(time_s)
            r, v = np.asarray(r, dtype=np.float64), np.asarray(v, dtype=np.float64)
            if r.shape != time_s.shape or v.shape != time_s.shape:
                raise PiezoStageError(f'trajectory of axis {stage.names[j]!r} returned '
                                      f'arrays of shape {r.shape} and {v.shape}, expected '
                                      f'{time_s.shape}')
            ref[k0:k0 + m, j] = r
            vel[k0:k0 + m, j] = v
        refs = ref[k0:k0 + m].tolist()
        vels = vel[k0:k0 + m].tolist()
        ys: list[list[float]] = []
        us: list[list[float]] = []
        xs: list[list[float]] = []
        for r_row, v_row in zip(refs, vels):
            u = step(y, r_row, v_row)
            ys.append(y)
            xs.append(read_true())
            us.append(u)
            y = plant_step(u)
        pos[k0:k0 + m] = ys
        cmd[k0:k0 + m] = us
        true[k0:k0 + m] = xs
        k0 += m
    time_all = np.arange(total, dtype=np.float64) * dt
    records = []
    for j, name in enumerate(stage.names):
        m_j: dict[str, Any] = dict(meta or {})
        m_j.update({'axis': name, 'sample_time_s': dt, 'duration_s': total * dt})
        period = getattr(trajectories[j], 'period_s', None)
        if isinstance(period, float) and period > 0.0:
            m_j['trajectory_period_s'] = period
        records.append(RunRecord(time_all, np.ascontiguousarray(pos[:, j]),
                                 np.ascontiguousarray(ref[:, j]),
                                 np.ascontiguousarray(vel[:, j]),
                                 np.ascontiguousarray(cmd[:, j]), {}, m_j,
                                 np.ascontiguousarray(true[:, j])))
    return records


@dataclass(frozen=True)
class AxisMetrics:
    """
    The tracking error of one axis over a window: e_rms and e_max, measured and true.

    Attributes
    ----------
    axis : str
    samples : int
        Samples in the window.
    e_max_m, e_rms_m : float
        Of the measured position [m].
    e_max_true_m, e_rms_true_m : float
        Of the true position [m] (NaN without it).

    """

    axis: str
    samples: int
    e_max_m: float
    e_rms_m: float
    e_max_true_m: float
    e_rms_true_m: float

    def as_dict(self) -> dict[str, Any]:
        """Return the metrics as a plain dict (JSON)."""
        return dataclasses.asdict(self)


def axis_metrics(record: RunRecord, *, last_s: float | None = None,
                 mask: FloatArray | None = None) -> AxisMetrics:
    """
    Return the tracking metrics of one axis' record over its last ``last_s`` seconds.

    Parameters
    ----------
    record : RunRecord
        One axis of :func:`run_axes`.
    last_s : float, optional
        Window length at the end of the run [s]; default the whole run.
    mask : ndarray of bool, optional
        Samples of the window to keep (e.g. :func:`middle_of_lines`), same length as the
        record.

    Returns
    -------
    AxisMetrics

    """
    n = len(record)
    dt = float(record.meta.get('sample_time_s', 0.0)) or (
        float(record.time_s[1] - record.time_s[0]) if n > 1 else 1.0)
    first = 0 if last_s is None else max(n - int(round(last_s / dt)), 0)
    keep = np.zeros(n, dtype=bool)
    keep[first:] = True
    if mask is not None:
        keep &= np.asarray(mask, dtype=bool)
    e_max, e_rms = error_metrics(record.error_m[keep])
    true = record.true_error_m
    t_max, t_rms = error_metrics(true[keep]) if true is not None else (math.nan, math.nan)
    return AxisMetrics(str(record.meta.get('axis', '')), int(np.count_nonzero(keep)), e_max,
                       e_rms, t_max, t_rms)


def middle_of_lines(reference_m: FloatArray, fraction: float = 0.8) -> FloatArray:
    """
    Return the samples where a fast axis' reference is in the middle ``fraction`` of its range.

    The turn-arounds of a raster line (where the fast axis reverses, and an image is not
    taken) are left out.

    Parameters
    ----------
    reference_m : ndarray
        The fast axis' reference [m].
    fraction : float
        Share of the range kept, (0, 1].

    Returns
    -------
    ndarray of bool

    """
    if not 0.0 < fraction <= 1.0:
        raise ParameterError('fraction', fraction, '(0, 1]')
    x = np.asarray(reference_m, dtype=np.float64)
    lo, hi = float(np.min(x)), float(np.max(x))
    centre, half = 0.5 * (lo + hi), 0.5 * fraction * (hi - lo)
    return np.asarray(np.abs(x - centre) <= half, dtype=bool)


def frame_images(fast: RunRecord, slow: RunRecord, *, lines: int, frame: int = -1,
                 true: bool = False) -> tuple[FloatArray, FloatArray]:
    """
    Return one raster frame's errors as images: rows the lines, columns the samples of a line.

    A line is one period of the fast axis' reference (``trajectory_period_s`` of its record),
    trace and retrace side by side as the line runs; frames follow each other every ``lines``
    lines, the slow axis going up one frame and down the next (:func:`~piezo_stage_ros.core.
    loop.scan2d.raster`). Row 0 is the line at the low end of the slow axis in either frame, so
    that the images of an up and a down frame overlay.

    Parameters
    ----------
    fast, slow : RunRecord
        The fast and the slow axis of one run (:func:`run_axes`).
    lines : int
        Lines per frame.
    frame : int
        Which complete frame of the run (negative: counted from the last).
    true : bool
        The true position's error instead of the measured one.

    Returns
    -------
    (ndarray, ndarray)
        The fast and the slow axis' error [m], each of shape (lines, samples per line).

    Raises
    ------
    ParameterError
        Without a fast-axis period of a whole number of samples, or for a frame the run does
        not hold whole.

    """
    dt = float(fast.meta.get('sample_time_s', 0.0))
    period = fast.meta.get('trajectory_period_s')
    line_s = float(period) if isinstance(period, (int, float)) else 0.0
    per_line = int(round(line_s / dt)) if dt > 0.0 else 0
    if per_line < 2 or abs(per_line * dt - line_s) > 1e-9 * line_s:
        raise ParameterError('fast.meta.trajectory_period_s', period,
                             'a line period of a whole number (>= 2) of samples')
    size = lines * per_line
    frames = len(fast) // size
    index = frame + frames if frame < 0 else frame
    if not 0 <= index < frames:
        raise ParameterError('frame', frame, f'[{-frames}, {frames}) (complete frames in the '
                             'run)')
    out = []
    for rec in (fast, slow):
        err = rec.true_error_m if true else rec.error_m
        if err is None:
            raise ParameterError('true', true, 'False for a record without true positions')
        image = np.asarray(err[index * size:(index + 1) * size], dtype=np.float64).reshape(
            lines, per_line)
        # odd frames run down the slow axis: their first line is the top one
        out.append(image[::-1].copy() if index % 2 else image.copy())
    return out[0], out[1]
