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

__all__ = ['LINE_FRACTION', 'AxisMetrics', 'GratingImage', 'axes_references', 'axis_metrics',
           'axis_references', 'frame_images', 'grating_image', 'line_start', 'middle_of_lines',
           'run_axes', 'run_metrics']

#: Share of a raster line's range over which its fast axis is measured (the turn-arounds, where
#: no image is taken, left out).
LINE_FRACTION = 0.8


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
        ref[k0:k0 + m], vel[k0:k0 + m] = axes_references(trajectories, k0, m, dt,
                                                         stage.names)
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


def axes_references(trajectories: Sequence[Trajectory], first: int, count: int,
                    sample_time_s: float, names: Sequence[str] = ()
                    ) -> tuple[FloatArray, FloatArray]:
    """
    Return every axis' reference and its velocity over ``count`` samples from ``first``.

    The samples' times are k T for k = first ... first + count - 1, computed as the loop
    computes them, so that a caller that evaluates the same chunks (the trajectory node in
    lockstep) gets the loop's floats.

    Parameters
    ----------
    trajectories : sequence of Trajectory
        One per axis.
    first, count : int
        The chunk's first sample and its length.
    sample_time_s : float
        T [s].
    names : sequence of str
        The axes' names, for messages.

    Returns
    -------
    (ndarray, ndarray)
        x_d [m] and x_d' [m/s], each of shape (count, axes).

    Raises
    ------
    PiezoStageError
        A trajectory that returns arrays of the wrong shape.

    """
    ref = np.empty((count, len(trajectories)))
    vel = np.empty((count, len(trajectories)))
    for j, tr in enumerate(trajectories):
        ref[:, j], vel[:, j] = axis_references(tr, first, count, sample_time_s,
                                               names[j] if j < len(names) else str(j))
    return ref, vel


def axis_references(trajectory: Trajectory, first: int, count: int, sample_time_s: float,
                    name: str) -> tuple[FloatArray, FloatArray]:
    """
    Return one axis' x_d [m] and x_d' [m/s] over ``count`` samples from ``first``.

    As :func:`axes_references` for the axis ``name`` (named in the error), each of shape
    (count,).
    """
    time_s = np.arange(first, first + count, dtype=np.float64) * sample_time_s
    r, v = trajectory.evaluate(time_s)
    r, v = np.asarray(r, dtype=np.float64), np.asarray(v, dtype=np.float64)
    if r.shape != time_s.shape or v.shape != time_s.shape:
        raise PiezoStageError(f'trajectory of axis {name!r} returned arrays of shape '
                              f'{r.shape} and {v.shape}, expected {time_s.shape}')
    return r, v


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


def run_metrics(records: Sequence[RunRecord], *, window_s: float | None,
                fast_axis: str | None = None,
                fraction: float = LINE_FRACTION) -> dict[str, AxisMetrics]:
    """
    Return every axis' metrics over the last ``window_s``, a raster's fast axis over its lines.

    The one place the figures of a multi-axis run are computed, so that ``simulate_axes`` of a
    run and ``analyze`` of its bag give the same numbers.

    Parameters
    ----------
    records : sequence of RunRecord
        One per axis, ``meta['axis']`` naming it.
    window_s : float or None
        Window length at the end of the run [s]; None: the whole run.
    fast_axis : str, optional
        A raster's fast axis: measured where its reference lies in the middle ``fraction`` of
        its range (:func:`middle_of_lines`).
    fraction : float
        That share, (0, 1].

    Returns
    -------
    dict of str to AxisMetrics
        Per axis name, in the records' order.

    """
    out = {}
    for rec in records:
        name = str(rec.meta.get('axis', ''))
        mask = middle_of_lines(rec.reference_m, fraction) if name == fast_axis else None
        out[name] = axis_metrics(rec, last_s=window_s, mask=mask)
    return out


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
                 true: bool = False, start: int = 0) -> tuple[FloatArray, FloatArray]:
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
    start : int
        The lines begin at this sample (e.g. :func:`line_start`: a row from the fast axis'
        low turn-around, trace then retrace); 0: at the run's start.

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
    out = []
    for rec in (fast, slow):
        err = rec.true_error_m if true else rec.error_m
        if err is None:
            raise ParameterError('true', true, 'False for a record without true positions')
        out.append(_frame_rows(fast, err, lines, frame, start))
    return out[0], out[1]


def line_start(fast: RunRecord) -> int:
    """
    Return the sample of the fast axis' low turn-around in its first line period.

    Lines counted from there run trace (up), then retrace (down); a raster's slow axis steps
    at that turn-around (its ``delay_s``), so each such line lies on one slow-axis level.

    Raises
    ------
    ParameterError
        Without a fast-axis period of a whole number of samples.

    """
    return int(np.argmin(fast.reference_m[:_line_samples(fast)]))


def _line_samples(fast: RunRecord) -> int:
    # samples of one line: the fast axis' period, a whole number of samples
    dt = float(fast.meta.get('sample_time_s', 0.0))
    period = fast.meta.get('trajectory_period_s')
    line_s = float(period) if isinstance(period, (int, float)) else 0.0
    per_line = int(round(line_s / dt)) if dt > 0.0 else 0
    if per_line < 2 or abs(per_line * dt - line_s) > 1e-9 * line_s:
        raise ParameterError('fast.meta.trajectory_period_s', period,
                             'a line period of a whole number (>= 2) of samples')
    return per_line


def _frame_rows(fast: RunRecord, values: FloatArray, lines: int, frame: int,
                offset: int = 0) -> FloatArray:
    # one frame of per-sample values as (lines, samples per line), the lines counted from
    # sample ``offset``, row 0 at the slow axis' low end (odd frames run down the slow axis:
    # their first line is the top one)
    per_line = _line_samples(fast)
    size = lines * per_line
    frames = (len(fast) - offset) // size
    index = frame + frames if frame < 0 else frame
    if not 0 <= index < frames:
        raise ParameterError('frame', frame, f'[{-frames}, {frames}) (complete frames in the '
                             'run)')
    first = offset + index * size
    image = np.asarray(values[first:first + size], dtype=np.float64).reshape(lines, per_line)
    return image[::-1].copy() if index % 2 else image.copy()


@dataclass(frozen=True)
class GratingImage:
    """
    A cross grating imaged over one raster frame: what a user's image of it shows.

    The sample is h(x, y) = (cos(2 pi x / p) + cos(2 pi y / p)) / 2, lines of pitch p across
    both axes. An image puts each sample where the stage was told to be (the desired
    positions); the tip was where the stage went (the true position, else the measured one).
    Index 0 of each pair is the trace (fast axis moving up), 1 the retrace.

    Attributes
    ----------
    pitch_m : float
        The grating's pitch p [m].
    x_m : ndarray
        Pixel centres along the fast axis [m]: the middle ``fraction`` of the line's range.
    y_m : ndarray
        Each row's desired slow-axis position (its mean over the imaged part) [m].
    desired, imaged : tuple of ndarray
        Trace and retrace images (lines x pixels): the grating at the desired positions (what
        a perfect stage images) and at the positions reached.
    shift_x_m : tuple of ndarray
        Per row and grating line x = m p inside the imaged range: where the line shows in the
        image minus where it is [m] (lines x grating lines; NaN where a row does not cross it).
    shift_y_m : tuple of ndarray
        Per row and pixel: the desired minus the reached slow-axis position, how far the row
        (and every grating line across it) is displaced in the image [m].
    rms_x_m, rms_y_m : tuple of float
        Rms of those displacements, trace and retrace [m]: the distortion in numbers.
    source : str
        ``'true'`` or ``'measured'``: which position the tip was taken at.

    """

    pitch_m: float
    x_m: FloatArray
    y_m: FloatArray
    desired: tuple[FloatArray, FloatArray]
    imaged: tuple[FloatArray, FloatArray]
    shift_x_m: tuple[FloatArray, FloatArray]
    shift_y_m: tuple[FloatArray, FloatArray]
    rms_x_m: tuple[float, float]
    rms_y_m: tuple[float, float]
    source: str


def _rms(values: FloatArray) -> float:
    finite = values[np.isfinite(values)]
    return float(np.sqrt(np.mean(finite ** 2))) if finite.size else math.nan


def grating_image(fast: RunRecord, slow: RunRecord, *, lines: int, pitch_m: float = 1e-6,
                  frame: int = -1, fraction: float = LINE_FRACTION) -> GratingImage:
    """
    Image a cross grating over one raster frame at the reached against the desired positions.

    A row of the image is a line from the fast axis' low turn-around to the next (trace, then
    retrace), where a raster's slow axis steps. Each row's samples of one direction inside the
    middle ``fraction`` of the fast axis' range are resampled onto a pixel grid of as many
    pixels as a line has samples there, by linear interpolation along the desired fast
    position. A grating line x = m p shows in a
    row where the tip reached it: at the desired position the stage had when its true (else
    measured) position crossed m p, interpolated between the samples around the crossing.

    Parameters
    ----------
    fast, slow : RunRecord
        The fast and the slow axis of one raster run (:func:`run_axes`, or read from its bag).
    lines : int
        Lines per frame.
    pitch_m : float
        The grating's pitch [m], > 0.
    frame : int
        Which complete frame (negative: counted from the last).
    fraction : float
        Share of the line's range imaged, (0, 1].

    Returns
    -------
    GratingImage

    Raises
    ------
    ParameterError
        A bad pitch or fraction, or what :func:`frame_images` refuses.

    """
    if not (pitch_m > 0.0 and math.isfinite(pitch_m)):
        raise ParameterError('pitch_m', pitch_m, '(0, inf) m')
    if not 0.0 < fraction <= 1.0:
        raise ParameterError('fraction', fraction, '(0, 1]')
    use_true = fast.true_position_m is not None and slow.true_position_m is not None

    def reached(r: RunRecord) -> FloatArray:
        true = r.true_position_m
        return true if use_true and true is not None else r.position_m
    # the rows begin at the fast axis' low turn-around
    start = line_start(fast)
    xd = _frame_rows(fast, fast.reference_m, lines, frame, start)
    vd = _frame_rows(fast, fast.reference_velocity_mps, lines, frame, start)
    x = _frame_rows(fast, reached(fast), lines, frame, start)
    yd = _frame_rows(fast, slow.reference_m, lines, frame, start)
    y = _frame_rows(fast, reached(slow), lines, frame, start)
    lo, hi = float(xd.min()), float(xd.max())
    centre, half = 0.5 * (lo + hi), 0.5 * fraction * (hi - lo)
    inside = np.abs(xd - centre) <= half
    pixels = max(int(np.count_nonzero(inside & (vd > 0.0)) // lines), 2)
    x_px = np.linspace(centre - half, centre + half, pixels)
    marks = np.arange(math.ceil((centre - half) / pitch_m),
                      math.floor((centre + half) / pitch_m) + 1) * pitch_m

    def height(px: FloatArray, py: FloatArray) -> FloatArray:
        return np.asarray(0.5 * (np.cos(2.0 * np.pi * px / pitch_m)
                                 + np.cos(2.0 * np.pi * py / pitch_m)), dtype=np.float64)

    y_rows = np.array([float(np.mean(yd[i][inside[i]])) if inside[i].any() else math.nan
                       for i in range(lines)])
    desired, imaged, shift_x, shift_y = [], [], [], []
    for sign in (1.0, -1.0):
        d_img = np.full((lines, pixels), np.nan)
        i_img = np.full((lines, pixels), np.nan)
        sx = np.full((lines, marks.size), np.nan)
        sy = np.full((lines, pixels), np.nan)
        for i in range(lines):
            keep = sign * vd[i] > 0.0
            if np.count_nonzero(keep) < 2:
                continue
            order = np.argsort(xd[i][keep], kind='stable')
            xd_k, x_k = xd[i][keep][order], x[i][keep][order]
            yd_k, y_k = yd[i][keep][order], y[i][keep][order]
            d_img[i] = np.interp(x_px, xd_k, height(xd_k, yd_k), left=np.nan, right=np.nan)
            i_img[i] = np.interp(x_px, xd_k, height(x_k, y_k), left=np.nan, right=np.nan)
            sy[i] = np.interp(x_px, xd_k, yd_k - y_k, left=np.nan, right=np.nan)
            # where the reached position crossed each mark, on the desired axis
            by_reached = np.argsort(x_k, kind='stable')
            seen = np.interp(marks, x_k[by_reached], xd_k[by_reached], left=np.nan,
                             right=np.nan)
            sx[i] = seen - marks
        desired.append(d_img)
        imaged.append(i_img)
        shift_x.append(sx)
        shift_y.append(sy)
    return GratingImage(float(pitch_m), x_px, y_rows, (desired[0], desired[1]),
                        (imaged[0], imaged[1]), (shift_x[0], shift_x[1]),
                        (shift_y[0], shift_y[1]), (_rms(shift_x[0]), _rms(shift_x[1])),
                        (_rms(shift_y[0]), _rms(shift_y[1])),
                        'true' if use_true else 'measured')
