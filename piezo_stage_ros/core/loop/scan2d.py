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
Scans over several axes: raster frames, Lissajous and spiral scans, point-to-point moves.

Each scan is a tuple of one-axis trajectories (one per axis, the objects the one-axis loop
takes: ``evaluate(time_s)`` and ``period_s``), so that every axis' controller, feed-forward and
learning work on its own reference as they do for one axis.

- **Raster** (:func:`raster`): the fast axis follows any periodic one-axis trajectory, one
  period a line (a triangle: trace and retrace); the slow axis moves ``lines`` times a
  ``pitch_m`` over a frame, as a ramp (constant speed) or a staircase (one level a line, an
  S-curve between levels), up one frame and down the next, so that frames repeat without a
  fly-back jump. Its period is two frames; the fast axis keeps the line's period.
- **Lissajous** (:func:`lissajous`): a sine per axis, each its own frequency; every axis takes
  the common period of all (1 s for 97 and 103 Hz), the period the learning needs.
- **Spiral** (:func:`spiral`): x = c_x + r(t) cos(2 pi f t), y = c_y + r(t) sin(2 pi f t) with
  the radius rising linearly to ``radius_m`` over ``duration_s`` and back (period 2 durations).
- **Moves** (:func:`moves`): point-to-point per axis: quintic S-curves of ``move_s`` from
  level to level with ``dwell_s`` between them, the last level held (aperiodic).

Every scan is refused when it leaves the travel of an axis, the error naming the parameter,
its value and the travel.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.interfaces import Trajectory
from piezo_stage_ros.core.contracts.params import group, param, Params
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.loop.trajectories import (
    _common_period,
    make_trajectory,
    TrajectoryBase,
    TrajectoryParams,
    TRAVEL_MAX_M,
)
from piezo_stage_ros.core.model.axes import AXIS_NAMES
from piezo_stage_ros.core.signals.shapes import s_curve

__all__ = ['LissajousParams', 'MovesParams', 'RasterParams', 'SCANS', 'SLOW_PROFILES',
           'ScanParams', 'SpiralParams', 'extent_m', 'lissajous', 'make_scan', 'moves',
           'raster', 'spiral']

#: Slow-axis profiles of a raster frame.
SLOW_PROFILES = ('ramp', 'staircase')

Travel = tuple[float, float]
DEFAULT_TRAVEL: Travel = (0.0, TRAVEL_MAX_M)


def extent_m(trajectory: Trajectory, span_s: float, samples: int = 20001) -> Travel:
    """
    Return the lowest and highest x_d of ``trajectory`` over [0, span_s] (sampled densely).

    Parameters
    ----------
    trajectory : Trajectory
        Any one-axis trajectory.
    span_s : float
        The time span [s] (a period for a periodic trajectory).
    samples : int
        Points of the grid.

    Returns
    -------
    (float, float)

    """
    x, _ = trajectory.evaluate(np.linspace(0.0, span_s, samples))
    return float(np.min(x)), float(np.max(x))


def _inside(name: str, value: object, low: float, high: float, travel: Travel,
            axis: str) -> None:
    """Refuse x_d outside the travel, naming the parameter that sets it."""
    lo, hi = travel
    if low < lo - 1e-15 or high > hi + 1e-15:
        bad = low if low < lo - 1e-15 else high
        raise ParameterError(name, value, f'x_d of axis {axis!r} within its travel '
                             f'[{lo:g}, {hi:g}] m', f'takes x_d to {bad:.4g} m, outside the '
                             'travel')


def _positive(name: str, value: float) -> float:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0.0):
        raise ParameterError(name, value, '(0, inf)')
    return float(value)


class _Slow(TrajectoryBase):
    """The slow axis of a raster: up one frame, down the next (module docstring)."""

    kind = 'raster_slow'

    def __init__(self, start_m: float, pitch_m: float, lines: int, line_s: float,
                 profile: str, transition_s: float, delay_s: float) -> None:
        self._start, self._pitch, self._lines = start_m, pitch_m, lines
        self._line_s, self._profile = line_s, profile
        self._tr, self._delay = transition_s, delay_s
        self.frame_s = lines * line_s
        self.period_s = 2.0 * self.frame_s

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        t = np.asarray(time_s, dtype=np.float64) - self._delay
        frame = self.frame_s
        # time into the two-frame period; u counts lines from the bottom (0 ... lines - 1)
        tau = np.mod(t, 2.0 * frame)
        up = tau < frame
        into = np.where(up, tau, tau - frame)
        top = float(self._lines - 1)
        if self._profile == 'ramp':
            # (lines - 1) pitches over the frame, back down over the next
            speed = top * self._pitch / frame
            pos = np.where(up, into, frame - into) * (top / frame)
            vel = np.where(up, speed, -speed)
            return self._start + self._pitch * pos, np.asarray(vel, dtype=np.float64)
        # staircase: line k of a frame sits on level k (up) or lines - 1 - k (down); each line
        # but a frame's first starts with an S-curve from the level before
        k = np.minimum(np.floor(into / self._line_s + 1e-9), top)
        q, dq = s_curve((into - k * self._line_s) / self._tr)
        moving = k >= 1.0
        level = np.where(moving, k - 1.0 + q, 0.0)
        dlevel = np.where(moving, dq / self._tr, 0.0)
        pos = np.where(up, level, top - level)
        vel = np.where(up, dlevel, -dlevel)
        return (np.asarray(self._start + self._pitch * pos, dtype=np.float64),
                np.asarray(self._pitch * vel, dtype=np.float64))


def raster(line: Trajectory, *, lines: int, pitch_m: float, start_m: float,
           profile: str = 'staircase', transition_s: float = 1e-3, delay_s: float = 0.0,
           fast_travel: Travel = DEFAULT_TRAVEL, slow_travel: Travel = DEFAULT_TRAVEL,
           fast_axis: str = 'x', slow_axis: str = 'y') -> tuple[Trajectory, TrajectoryBase]:
    """
    Return the (fast, slow) trajectories of a raster frame repeated up and down.

    Parameters
    ----------
    line : Trajectory
        The fast axis, one period a line (e.g. a triangle: trace and retrace); any one-axis
        trajectory with a ``period_s``.
    lines : int
        Lines per frame, >= 2.
    pitch_m : float
        Slow-axis distance between two lines [m] (negative: the frame runs downwards).
    start_m : float
        Slow-axis position of the first line [m].
    profile : str
        ``'staircase'`` (one level a line) or ``'ramp'`` (constant speed).
    transition_s : float
        Staircase: the S-curve from one level to the next [s], (0, line period].
    delay_s : float
        The slow axis' profile is delayed by this much against the lines [s], [0, line
        period) (a staircase can step while the fast axis turns).
    fast_travel, slow_travel : (float, float)
        Travel of each axis [m].
    fast_axis, slow_axis : str
        Axis names, for the errors.

    Returns
    -------
    (Trajectory, TrajectoryBase)
        The line itself and the slow axis (period two frames).

    Raises
    ------
    ParameterError
        A bad count, profile or time, a line without a period, or a frame that leaves the
        travel of an axis (naming the value and the travel).

    """
    period = getattr(line, 'period_s', None)
    if not (isinstance(period, float) and period > 0.0):
        raise ParameterError('raster.line.period_s', period, 'a periodic line trajectory '
                             '(period_s > 0)', 'the fast axis needs one period a line')
    if isinstance(lines, bool) or not isinstance(lines, int) or lines < 2:
        raise ParameterError('raster.lines', lines, 'an integer >= 2')
    if profile not in SLOW_PROFILES:
        raise ParameterError('raster.profile', profile, f'one of {list(SLOW_PROFILES)}')
    if not (math.isfinite(pitch_m) and pitch_m != 0.0):
        raise ParameterError('raster.pitch_m', pitch_m, 'finite and not 0')
    if profile == 'staircase':
        _positive('raster.transition_s', transition_s)
        if transition_s > period:
            raise ParameterError('raster.transition_s', transition_s,
                                 f'(0, {period:g}] s (the line period)')
    if not (math.isfinite(delay_s) and 0.0 <= delay_s < period):
        raise ParameterError('raster.delay_s', delay_s, f'[0, {period:g}) s (the line period)')
    lo_f, hi_f = extent_m(line, period)
    _inside('raster.line', f'x_d from {lo_f:.4g} to {hi_f:.4g} m', lo_f, hi_f, fast_travel,
            fast_axis)
    if not math.isfinite(start_m):
        raise ParameterError('raster.start_m', start_m, 'finite')
    _inside('raster.start_m', start_m, start_m, start_m, slow_travel, slow_axis)
    end = start_m + (lines - 1) * pitch_m
    _inside('raster.pitch_m', pitch_m, min(start_m, end), max(start_m, end), slow_travel,
            slow_axis)
    slow = _Slow(start_m, pitch_m, lines, period, profile, transition_s, delay_s)
    return line, slow


class _Sine(TrajectoryBase):
    kind = 'lissajous'

    def __init__(self, offset_m: float, amplitude_m: float, frequency_hz: float,
                 phase_rad: float, period_s: float | None) -> None:
        self._c, self._a = offset_m, amplitude_m
        self._w, self._p = 2.0 * math.pi * frequency_hz, phase_rad
        self.period_s = period_s

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        ph = self._w * np.asarray(time_s, dtype=np.float64) + self._p
        return self._c + self._a * np.sin(ph), self._a * self._w * np.cos(ph)


def _per_axis(name: str, values: Sequence[float], n: int) -> list[float]:
    items = [float(v) for v in values]
    if len(items) != n or not all(math.isfinite(v) for v in items):
        raise ParameterError(name, list(values), f'{n} finite values, one per axis')
    return items


def lissajous(*, frequencies_hz: Sequence[float], amplitudes_m: Sequence[float],
              offsets_m: Sequence[float], phases_rad: Sequence[float] | None = None,
              travel: Sequence[Travel] | None = None, names: Sequence[str] = ('x', 'y', 'z')
              ) -> tuple[TrajectoryBase, ...]:
    """
    Return one sine per axis, all with the common period of the set.

    Parameters
    ----------
    frequencies_hz, amplitudes_m, offsets_m : sequence of float
        One per axis [Hz], [m], [m].
    phases_rad : sequence of float, optional
        Phase of each sine [rad] (default 0: all rise through their offsets at t = 0).
    travel : sequence of (float, float), optional
        Travel of each axis [m]; default 0 ... 38 um.
    names : sequence of str
        Axis names, for the errors.

    Returns
    -------
    tuple of TrajectoryBase
        ``period_s`` the common period (None when the frequencies have none below 1000 s).

    """
    n = len(frequencies_hz)
    f = _per_axis('lissajous.frequencies_hz', frequencies_hz, n)
    a = _per_axis('lissajous.amplitudes_m', amplitudes_m, n)
    c = _per_axis('lissajous.offsets_m', offsets_m, n)
    ph = _per_axis('lissajous.phases_rad', phases_rad if phases_rad is not None else [0.0] * n,
                   n)
    for k in range(n):
        _positive('lissajous.frequencies_hz', f[k])
        if a[k] < 0.0:
            raise ParameterError('lissajous.amplitudes_m', a, 'each >= 0')
    period = _common_period(tuple(f))
    out = []
    for k in range(n):
        tr = travel[k] if travel is not None else DEFAULT_TRAVEL
        _inside('lissajous.amplitudes_m', a[k], c[k] - a[k], c[k] + a[k], tr, names[k])
        out.append(_Sine(c[k], a[k], f[k], ph[k], period))
    return tuple(out)


class _Spiral(TrajectoryBase):
    kind = 'spiral'

    def __init__(self, centre_m: float, radius_m: float, frequency_hz: float,
                 duration_s: float, sine: bool) -> None:
        self._c, self._r, self._w = centre_m, radius_m, 2.0 * math.pi * frequency_hz
        self._d, self._sine = duration_s, sine
        self.period_s = 2.0 * duration_s

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        t = np.asarray(time_s, dtype=np.float64)
        tau = np.mod(t, 2.0 * self._d)
        out = tau < self._d
        # radius out over one duration, back in over the next
        r = self._r * np.where(out, tau, 2.0 * self._d - tau) / self._d
        dr = np.where(out, 1.0, -1.0) * self._r / self._d
        ph = self._w * t
        if self._sine:
            return self._c + r * np.sin(ph), dr * np.sin(ph) + r * self._w * np.cos(ph)
        return self._c + r * np.cos(ph), dr * np.cos(ph) - r * self._w * np.sin(ph)


def spiral(*, centres_m: Sequence[float], radius_m: float, frequency_hz: float,
           duration_s: float, travel: Sequence[Travel] | None = None,
           names: Sequence[str] = ('x', 'y')) -> tuple[TrajectoryBase, TrajectoryBase]:
    """
    Return the (x, y) trajectories of an Archimedean spiral out and back in.

    Parameters
    ----------
    centres_m : sequence of float
        Centre on each of the two axes [m].
    radius_m : float
        Largest radius [m], > 0.
    frequency_hz : float
        Turns per second [Hz].
    duration_s : float
        Time from the centre to the largest radius [s]; the period is twice that.
    travel : sequence of (float, float), optional
        Travel of each axis [m].
    names : sequence of str
        Axis names, for the errors.

    Returns
    -------
    (TrajectoryBase, TrajectoryBase)

    """
    c = _per_axis('spiral.centres_m', centres_m, 2)
    _positive('spiral.radius_m', radius_m)
    _positive('spiral.frequency_hz', frequency_hz)
    _positive('spiral.duration_s', duration_s)
    for k in range(2):
        tr = travel[k] if travel is not None else DEFAULT_TRAVEL
        _inside('spiral.radius_m', radius_m, c[k] - radius_m, c[k] + radius_m, tr, names[k])
    return (_Spiral(c[0], radius_m, frequency_hz, duration_s, False),
            _Spiral(c[1], radius_m, frequency_hz, duration_s, True))


class _Moves(TrajectoryBase):
    kind = 'moves'

    def __init__(self, levels_m: Sequence[float], move_s: float, dwell_s: float) -> None:
        self._levels = np.asarray(levels_m, dtype=np.float64)
        self._move, self._dwell = move_s, dwell_s

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        t = np.asarray(time_s, dtype=np.float64)
        lv = self._levels
        step = self._move + self._dwell
        # move j (to level j + 1) starts at dwell + j step
        j = np.clip(np.floor((t - self._dwell) / step), 0, len(lv) - 2).astype(np.intp) \
            if len(lv) > 1 else np.zeros(t.shape, dtype=np.intp)
        if len(lv) == 1:
            return np.full(t.shape, lv[0]), np.zeros(t.shape)
        u = (t - self._dwell - j * step) / self._move
        q, dq = s_curve(u)
        jump = lv[j + 1] - lv[j]
        return (np.asarray(lv[j] + jump * q, dtype=np.float64),
                np.asarray(jump * dq / self._move, dtype=np.float64))


def moves(levels_m: Sequence[float], *, move_s: float, dwell_s: float,
          travel: Travel = DEFAULT_TRAVEL, axis: str = 'x') -> TrajectoryBase:
    """
    Return a point-to-point trajectory: S-curve moves through ``levels_m``, the last held.

    Parameters
    ----------
    levels_m : sequence of float
        The positions visited, the first held from t = 0 for ``dwell_s`` [m].
    move_s : float
        Duration of each move [s], > 0.
    dwell_s : float
        Rest at each level before the next move [s], >= 0.
    travel : (float, float)
        Travel of the axis [m].
    axis : str
        Axis name, for the errors.

    Returns
    -------
    TrajectoryBase
        Aperiodic (``period_s`` None).

    """
    levels = [float(v) for v in levels_m]
    if not levels or not all(math.isfinite(v) for v in levels):
        raise ParameterError('moves.levels_m', list(levels_m), 'a non-empty list of finite '
                             'positions')
    _positive('moves.move_s', move_s)
    if not (math.isfinite(dwell_s) and dwell_s >= 0.0):
        raise ParameterError('moves.dwell_s', dwell_s, '[0, inf)')
    _inside('moves.levels_m', levels, min(levels), max(levels), travel, axis)
    return _Moves(levels, move_s, dwell_s)


# --------------------------------------------------------------------------------------------
# Parameters (trajectory_node scan.*) and the scan they describe

#: Scan kinds of a multi-axis stage.
SCANS = ('raster', 'lissajous', 'spiral', 'moves', 'each')


@dataclass(frozen=True)
class RasterParams(Params):
    """A raster frame: the fast axis plays its line trajectory, the slow axis steps."""

    fast_axis: str = param('x', unit='-', description='Axis that plays the line (its '
                           'one-axis trajectory: kind and parameters of trajectory_node, with '
                           'axes.<name>.* overrides).', choices=AXIS_NAMES)
    slow_axis: str = param('y', unit='-', description='Axis that steps from line to line.',
                           choices=AXIS_NAMES)
    lines: int = param(64, unit='-', description='Lines per frame.', low=2, high=100000)
    pitch_m: float = param(10e-6 / 63, unit='m', description='Slow-axis distance between two '
                           'lines (negative: downwards).')
    start_m: float = param(5e-6, unit='m', description='Slow-axis position of the first '
                           'line.')
    profile: str = param('staircase', unit='-', description='Slow axis: one level a line '
                         '(staircase) or constant speed (ramp).', choices=SLOW_PROFILES)
    transition_s: float = param(1e-3, unit='s', description='Staircase: S-curve from one '
                                'level to the next.', low=0.0, low_open=True, high=1.0)
    delay_s: float = param(0.0, unit='s', description='Slow-axis profile delayed by this '
                           'much against the lines.', low=0.0)

    def _check(self) -> None:
        if self.slow_axis == self.fast_axis:
            raise ParameterError('slow_axis', self.slow_axis, f'an axis other than the fast '
                                 f'axis {self.fast_axis!r}', 'is the fast axis too')


@dataclass(frozen=True)
class LissajousParams(Params):
    """One sine per axis of the stage (amplitude 0: the axis holds its offset)."""

    frequencies_hz: tuple[float, ...] = param((97.0, 103.0), unit='Hz', description='Frequency '
                                              'of each axis, in axis order.', low=0.0,
                                              low_open=True, high=5000.0)
    amplitudes_m: tuple[float, ...] = param((3e-6, 3e-6), unit='m', description='Amplitude of '
                                            'each axis.', low=0.0)
    offsets_m: tuple[float, ...] = param((10e-6, 10e-6), unit='m', description='Centre of '
                                         'each axis.')
    phases_rad: tuple[float, ...] = param((0.0, 0.0), unit='rad', description='Phase of each '
                                          'axis.')


@dataclass(frozen=True)
class SpiralParams(Params):
    """An Archimedean spiral on the first two axes, out and back in."""

    centres_m: tuple[float, ...] = param((15e-6, 15e-6), unit='m', description='Centre on each '
                                         'of the first two axes.')
    radius_m: float = param(5e-6, unit='m', description='Largest radius.', low=0.0,
                            low_open=True)
    frequency_hz: float = param(50.0, unit='Hz', description='Turns per second.', low=0.0,
                                low_open=True, high=5000.0)
    duration_s: float = param(0.5, unit='s', description='From the centre to the largest '
                              'radius (the period is twice that).', low=0.0, low_open=True)


@dataclass(frozen=True)
class MovesParams(Params):
    """Point-to-point moves per axis: S-curves through each axis' levels."""

    x_m: tuple[float, ...] = param((5e-6, 15e-6, 10e-6), unit='m', description='Levels of '
                                   'axis x.')
    y_m: tuple[float, ...] = param((5e-6, 10e-6, 15e-6), unit='m', description='Levels of '
                                   'axis y.')
    z_m: tuple[float, ...] = param((5e-6, 8e-6, 5e-6), unit='m', description='Levels of '
                                   'axis z.')
    move_s: float = param(2e-3, unit='s', description='Duration of a move.', low=0.0,
                          low_open=True)
    dwell_s: float = param(20e-3, unit='s', description='Rest at each level before the next '
                           'move.', low=0.0)


@dataclass(frozen=True)
class ScanParams(Params):
    """The scan of a multi-axis stage (trajectory_node ``scan.*``)."""

    kind: str = param('raster', unit='-', description='raster, lissajous, spiral, moves, or '
                      'each (every axis its own one-axis trajectory).', choices=SCANS)
    raster: RasterParams = group(RasterParams, 'kind raster')
    lissajous: LissajousParams = group(LissajousParams, 'kind lissajous')
    spiral: SpiralParams = group(SpiralParams, 'kind spiral')
    moves: MovesParams = group(MovesParams, 'kind moves')


class _Hold(TrajectoryBase):
    """An axis the scan does not move: it holds a level (periodic with the scan's period)."""

    kind = 'hold'

    def __init__(self, level_m: float, period_s: float | None) -> None:
        self._level = level_m
        self.period_s = period_s

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        t = np.asarray(time_s, dtype=np.float64)
        return np.full(t.shape, self._level), np.zeros(t.shape)


def make_scan(params: ScanParams, names: Sequence[str], lines: Sequence[TrajectoryParams],
              rest_m: Sequence[float]) -> tuple[Trajectory, ...]:
    """
    Build one trajectory per axis for the scan ``params.kind`` names.

    Parameters
    ----------
    params : ScanParams
        The scan.
    names : sequence of str
        The stage's axes.
    lines : sequence of TrajectoryParams
        Each axis' one-axis trajectory (the raster's fast axis plays its own; kind ``each``:
        every axis); its travel is the axis' travel.
    rest_m : sequence of float
        Each axis' rest position, held by the axes the scan does not move [m].

    Returns
    -------
    tuple of Trajectory
        In axis order; an axis the scan leaves holds its rest position, periodic with the
        scan's period.

    Raises
    ------
    ParameterError
        A scan naming an axis the stage lacks, lists of the wrong length, or a scan that
        leaves an axis' travel.

    """
    travel = [(p.travel_min_m, p.travel_max_m) for p in lines]
    n = len(names)
    kind = params.kind
    if kind == 'each':
        return tuple(make_trajectory(p) for p in lines)
    out: list[Trajectory | None] = [None] * n
    if kind == 'raster':
        r = params.raster
        for key in ('fast_axis', 'slow_axis'):
            if getattr(r, key) not in names:
                raise ParameterError(f'scan.raster.{key}', getattr(r, key),
                                     f'one of the axes {list(names)}')
        f, s = names.index(r.fast_axis), names.index(r.slow_axis)
        fast, slow = raster(make_trajectory(lines[f]), lines=r.lines, pitch_m=r.pitch_m,
                            start_m=r.start_m, profile=r.profile, transition_s=r.transition_s,
                            delay_s=r.delay_s, fast_travel=travel[f], slow_travel=travel[s],
                            fast_axis=r.fast_axis, slow_axis=r.slow_axis)
        out[f], out[s] = fast, slow
        period: float | None = slow.period_s
    elif kind == 'lissajous':
        li = params.lissajous
        for key in ('frequencies_hz', 'amplitudes_m', 'offsets_m', 'phases_rad'):
            if len(getattr(li, key)) != n:
                raise ParameterError(f'scan.lissajous.{key}', list(getattr(li, key)),
                                     f'{n} values, one per axis {list(names)}')
        out = list(lissajous(frequencies_hz=li.frequencies_hz, amplitudes_m=li.amplitudes_m,
                             offsets_m=li.offsets_m, phases_rad=li.phases_rad, travel=travel,
                             names=names))
        period = None
    elif kind == 'spiral':
        sp = params.spiral
        if n < 2:
            raise ParameterError('scan.kind', kind, 'a scan of one axis (raster needs two, '
                                 'spiral two)', f'needs two axes, the stage has {list(names)}')
        out[0], out[1] = spiral(centres_m=sp.centres_m, radius_m=sp.radius_m,
                                frequency_hz=sp.frequency_hz, duration_s=sp.duration_s,
                                travel=travel[:2], names=names[:2])
        period = 2.0 * sp.duration_s
    else:
        mv = params.moves
        for k, name in enumerate(names):
            out[k] = moves(getattr(mv, f'{name}_m'), move_s=mv.move_s, dwell_s=mv.dwell_s,
                           travel=travel[k], axis=name)
        period = None
    return tuple(tr if tr is not None else _Hold(rest_m[k], period)
                 for k, tr in enumerate(out))
