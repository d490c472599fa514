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
Desired trajectories x_d(t) [m] with their exact derivatives [m/s], evaluated vectorized.

The kinds are those of the paper's experiments (section V) and a few for users:

- ``sine``: x_d = offset + A sin(2 pi f t) (Table III, Fig. 11: 3.8 + 3.8 sin(2 pi f t) um);
- ``multisine``: x_d = offset + sum_i A_i sin(2 pi f_i t) (Fig. 12: 10 Hz + 100 Hz);
- ``square``: between ``low_m`` and ``low_m + peak_to_peak_m``, low first (Fig. 10: 7.8 um peak
  to peak, 0.5 s period, 50 % duty); derivative 0 (the jump's Dirac impulse is left out);
- ``staircase``: ``steps`` steps of ``step_m`` every ``dwell_s`` from ``start_m``, then held
  (Fig. 9, 19 nm resolution); derivative 0;
- ``step``: ``initial_m`` until ``time_s``, then ``final_m``; derivative 0;
- ``hold``: x_d = ``position_m`` at all times (a stage that waits for goals);

  each of these three takes ``transition_s``: 0 (the default) is the ideal discontinuous jump
  of the paper; T_r > 0 replaces every jump of height D at t_0 by the quintic (minimum-jerk)
  S-curve x = x_0 + D q((t - t_0)/T_r), q(u) = 10 u^3 - 15 u^4 + 6 u^5 on [t_0, t_0 + T_r],
  with its exact derivative D q'(u)/T_r, q'(u) = 30 u^2 (1 - u)^2 (position, velocity and
  acceleration continuous; peak velocity 1.875 D/T_r at the middle), as instrument makers
  shape point-to-point moves. The transition starts where the ideal jump is and must fit in
  the level it leads to (refused otherwise);
- ``triangle``: offset + A tri(f t), with the phase of the sine (rising through the offset at
  t = 0) and the exact piecewise derivative +-4 A f (at a corner, the slope of the piece that
  starts there);
- ``scan_line``: the fast axis of a raster scan: trace up and retrace down at the constant speed
  v over the linear part [offset - A, offset + A] (the image), each linear part lasting
  ``linear_fraction`` of its half line, joined by turnarounds outside that range whose velocity
  v (1 - 2 S_N(s)) follows the smoothstep polynomial S_N of order N = ``continuity_order`` - 1
  (s the turnaround's normalised time): x_d is continuous with its first ``continuity_order``
  derivatives (1: velocity, 2: acceleration, 3: jerk), exactly, at every junction. Rising
  through the offset at t = 0 like the triangle; see :class:`ScanLineParams` for why the
  turnarounds are polynomial blends;
- ``csv``: a table with columns ``time_s, position_m``, interpolated **piecewise linearly**; the
  derivative is the slope of the segment [t_i, t_i+1) that contains t (piecewise constant, the
  derivative of the same rule). Before the first row and after the last the position is held and
  the derivative is 0.

t = 0 is the first sample of a run: the loop evaluates x_d(t_k) at t_k = k T. Every trajectory
must stay inside the stage's travel (0 ... 38 um by default); a parameter set that leaves it is
refused with an error naming the parameter, its value and the allowed range.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from piezo_stage_ros.core.contracts.errors import ConfigError, ParameterError
from piezo_stage_ros.core.contracts.params import group, param, Params
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.signals.excitation import (
    ChirpExcitation,
    ChirpParams,
    NoiseExcitation,
    NoiseParams,
)
from piezo_stage_ros.core.signals.shapes import s_curve, smoothstep

__all__ = ['CsvParams', 'HoldParams', 'MultisineParams', 'ScanLineParams', 'SineParams',
           'SquareParams', 'StaircaseParams', 'StepParams', 'TableTrajectory', 'TrajectoryBase',
           'TrajectoryParams', 'TriangleParams', 'check_sampling', 'load_table',
           'make_trajectory']


#: Stage travel of the P-753.31C [m] (sensor 0 ... 10 V over 0 ... 38 um).
TRAVEL_MAX_M = 38e-6

KINDS = ('sine', 'multisine', 'square', 'staircase', 'step', 'triangle', 'csv', 'noise', 'chirp',
         'scan_line', 'hold')


def _transition() -> Any:
    """Declare ``transition_s`` of a kind with jumps (a fresh field each: fields are per class)."""
    return param(0.0, unit='s', description='Duration of the quintic S-curve that replaces each '
                 'jump (0: ideal jump, as in the paper).', low=0.0)


@dataclass(frozen=True)
class SineParams(Params):
    """x_d = offset + A sin(2 pi f t); defaults: Table III at 100 Hz."""

    offset_m: float = param(3.8e-6, unit='m', description='Centre of the sine.')
    amplitude_m: float = param(3.8e-6, unit='m', description='Amplitude A.', low=0.0)
    frequency_hz: float = param(100.0, unit='Hz', description='Frequency f.', low=0.0,
                                low_open=True, high=5000.0)


@dataclass(frozen=True)
class MultisineParams(Params):
    """x_d = offset + sum A_i sin(2 pi f_i t); defaults: Fig. 12 (10 Hz + 100 Hz)."""

    offset_m: float = param(3.8e-6, unit='m', description='Centre of the sum.')
    amplitudes_m: tuple[float, ...] = param((1.9e-6, 1.9e-6), unit='m',
                                            description='Amplitude of each sine.', low=0.0)
    frequencies_hz: tuple[float, ...] = param((10.0, 100.0), unit='Hz',
                                              description='Frequency of each sine.', low=0.0,
                                              low_open=True, high=5000.0)

    def _check(self) -> None:
        if len(self.amplitudes_m) != len(self.frequencies_hz):
            raise ParameterError('amplitudes_m', list(self.amplitudes_m),
                                 f'{len(self.frequencies_hz)} values, one per frequency',
                                 'has a different length from frequencies_hz')


@dataclass(frozen=True)
class SquareParams(Params):
    """Square wave, low level first; defaults: Fig. 10 (7.8 um peak to peak, 0.5 s)."""

    low_m: float = param(3.8e-6, unit='m', description='Low level (held first).')
    peak_to_peak_m: float = param(7.8e-6, unit='m', description='High minus low level.',
                                  low=0.0)
    period_s: float = param(0.5, unit='s', description='Period.', low=0.0, low_open=True)
    duty: float = param(0.5, unit='-', description='Fraction of the period at the high level.',
                        low=0.0, high=1.0, low_open=True, high_open=True)
    transition_s: float = _transition()


@dataclass(frozen=True)
class StaircaseParams(Params):
    """Equal steps up from ``start_m`` (Fig. 9: 19 nm steps)."""

    start_m: float = param(3.8e-6, unit='m', description='Level before the first step.')
    step_m: float = param(19e-9, unit='m', description='Height of each step (may be negative).')
    steps: int = param(10, unit='-', description='Number of steps.', low=1, high=100000)
    dwell_s: float = param(0.05, unit='s', description='Time on each level.', low=0.0,
                           low_open=True)
    transition_s: float = _transition()


@dataclass(frozen=True)
class StepParams(Params):
    """One step from ``initial_m`` to ``final_m`` at ``time_s``."""

    initial_m: float = param(3.8e-6, unit='m', description='Level before the step.')
    final_m: float = param(11.6e-6, unit='m', description='Level after the step.')
    time_s: float = param(0.01, unit='s', description='Time of the step.', low=0.0)
    transition_s: float = _transition()


@dataclass(frozen=True)
class HoldParams(Params):
    """x_d = ``position_m``: the stage holds still (where the plant starts, by default)."""

    position_m: float = param(3.8e-6, unit='m', description='Position held.')


@dataclass(frozen=True)
class TriangleParams(Params):
    """Triangle wave offset + A tri(f t), rising through the offset at t = 0."""

    offset_m: float = param(3.8e-6, unit='m', description='Centre of the triangle.')
    amplitude_m: float = param(3.8e-6, unit='m', description='Amplitude A.', low=0.0)
    frequency_hz: float = param(10.0, unit='Hz', description='Frequency f.', low=0.0,
                                low_open=True, high=5000.0)


@dataclass(frozen=True)
class ScanLineParams(Params):
    """
    A raster scan line: linear trace and retrace over offset +- A, smooth turnarounds outside.

    The turnarounds are polynomial blends, not designed from the stage's inverse: a trajectory
    is a property of the image, not of one stage, so the same line is drawn on every stage and
    controller, its linear part is exactly the image, and its velocity is exact. What a stage
    cannot follow is the turnarounds' content above the learning filter's band Q (neither the
    feedback nor the learning follows it; the model inverse of ``inverse_learning`` does). The
    blend's order m is the lever on it: x_d continuous with m derivatives makes the harmonics
    fall off as f^-(m+2) far above 1/T_turn, but a higher order also raises the peak
    acceleration within the same time (1.5, 1.875, 2.19 times the constant deceleration of
    order 1 for orders 2, 3, 4) and so widens the turnaround's main lobe. When a turnaround
    lasts about one period of Q (a 100 Hz line 80 % linear: 1 ms against 1.2 kHz) order 2 puts
    the least content above Q of the family, hence the default; a slow line is far below Q at
    any order. The line rate a sample rate can draw is checked where the rate is known
    (:func:`check_sampling`).
    """

    offset_m: float = param(10e-6, unit='m', description='Centre of the line.')
    amplitude_m: float = param(5e-6, unit='m', description='Half the linear (imaged) range A; '
                               'the turnarounds go beyond it.', low=0.0, low_open=True)
    frequency_hz: float = param(100.0, unit='Hz', description='Line rate f (one trace and one '
                                'retrace per line).', low=0.0, low_open=True, high=5000.0)
    linear_fraction: float = param(0.8, unit='-', description='Fraction of each trace (and '
                                   'retrace) spent at constant speed; the rest turns around.',
                                   low=0.0, high=1.0, low_open=True, high_open=True)
    continuity_order: int = param(2, unit='-', description='Derivatives of x_d continuous at '
                                  'the turnarounds (1 velocity, 2 acceleration, 3 jerk ...).',
                                  low=1, high=6)

    @property
    def speed_mps(self) -> float:
        """Return the constant speed of the linear parts, 4 A f / linear_fraction [m/s]."""
        return 4.0 * self.amplitude_m * self.frequency_hz / self.linear_fraction

    @property
    def turn_s(self) -> float:
        """Return the duration of one turnaround, (1 - linear_fraction) / (2 f) [s]."""
        return (1.0 - self.linear_fraction) / (2.0 * self.frequency_hz)

    @property
    def overshoot_m(self) -> float:
        """Return how far a turnaround goes beyond the linear range [m]."""
        _, _, integral = smoothstep(self.continuity_order - 1)
        # the velocity v (1 - 2 q) integrated over the first half of the turnaround
        half = float(integral(0.5))
        return self.speed_mps * self.turn_s * (0.5 - 2.0 * half)


@dataclass(frozen=True)
class CsvParams(Params):
    """A table of (time_s, position_m) rows, interpolated piecewise linearly."""

    path: str = param('', unit='-', description='CSV file with a header row naming the columns '
                      'time_s and position_m; times strictly increasing.')


@dataclass(frozen=True)
class TrajectoryParams(Params):
    """The desired trajectory: its kind and one parameter group per kind."""

    kind: str = param('sine', unit='-', description='Kind of trajectory.', choices=KINDS)
    travel_min_m: float = param(0.0, unit='m', description='Lowest position the stage can '
                                'reach; every x_d must stay at or above it.')
    travel_max_m: float = param(TRAVEL_MAX_M, unit='m', description='Highest position the stage '
                                'can reach (38 um for the P-753.31C).')
    sine: SineParams = group(SineParams, 'kind sine')
    multisine: MultisineParams = group(MultisineParams, 'kind multisine')
    square: SquareParams = group(SquareParams, 'kind square')
    staircase: StaircaseParams = group(StaircaseParams, 'kind staircase')
    step: StepParams = group(StepParams, 'kind step')
    triangle: TriangleParams = group(TriangleParams, 'kind triangle')
    csv: CsvParams = group(CsvParams, 'kind csv')
    scan_line: ScanLineParams = group(ScanLineParams, 'kind scan_line (raster line: linear '
                                      'trace and retrace, smooth turnarounds)')
    hold: HoldParams = group(HoldParams, 'kind hold')
    noise: NoiseParams = group(NoiseParams, 'kind noise (band-limited white noise, '
                               'identification: core/signals/excitation.py)')
    chirp: ChirpParams = group(ChirpParams, 'kind chirp (sine sweep, identification: '
                               'core/signals/excitation.py)')

    def _check(self) -> None:
        for name, fits, room in (
                ('square.transition_s', self.square.transition_s,
                 min(self.square.duty, 1.0 - self.square.duty) * self.square.period_s),
                ('staircase.transition_s', self.staircase.transition_s, self.staircase.dwell_s)):
            if fits > room * (1.0 + 1e-9):
                raise ParameterError(name, fits, f'[0, {room:g}] s',
                                     'is longer than the shortest level it leads to')
        if not self.travel_min_m < self.travel_max_m:
            raise ParameterError('travel_max_m', self.travel_max_m,
                                 f'> travel_min_m = {self.travel_min_m:g}',
                                 'is not above the low end of the travel')
        if self.kind != 'csv':
            # the table is only read when the trajectory is built (make_trajectory checks it)
            _check_range(self, *_extent(self))


def _extent(p: TrajectoryParams) -> tuple[float, float, str, str]:
    """Return (min, max) of x_d over all time and the parameters that set each end."""
    if p.kind == 'sine':
        s = p.sine
        return (s.offset_m - s.amplitude_m, s.offset_m + s.amplitude_m, 'sine.amplitude_m',
                'sine.offset_m')
    if p.kind == 'triangle':
        r = p.triangle
        return (r.offset_m - r.amplitude_m, r.offset_m + r.amplitude_m,
                'triangle.amplitude_m', 'triangle.offset_m')
    if p.kind == 'scan_line':
        sl = p.scan_line
        reach = sl.amplitude_m + sl.overshoot_m
        return (sl.offset_m - reach, sl.offset_m + reach, 'scan_line.amplitude_m',
                'scan_line.offset_m')
    if p.kind == 'multisine':
        m = p.multisine
        # the bound sum |A_i| is reached (or approached) unless the frequencies are special;
        # refusing on the bound keeps every phase combination inside the travel
        total = sum(m.amplitudes_m)
        return (m.offset_m - total, m.offset_m + total, 'multisine.amplitudes_m',
                'multisine.offset_m')
    if p.kind == 'square':
        q = p.square
        return q.low_m, q.low_m + q.peak_to_peak_m, 'square.low_m', 'square.peak_to_peak_m'
    if p.kind == 'staircase':
        c = p.staircase
        end = c.start_m + c.steps * c.step_m
        lo_name = 'staircase.start_m' if c.step_m >= 0 else 'staircase.step_m'
        hi_name = 'staircase.step_m' if c.step_m >= 0 else 'staircase.start_m'
        return min(c.start_m, end), max(c.start_m, end), lo_name, hi_name
    if p.kind == 'noise':
        lo, hi = NoiseExcitation(p.noise).extent_m
        return lo, hi, 'noise.amplitude_m', 'noise.offset_m'
    if p.kind == 'chirp':
        ch = p.chirp
        return (ch.offset_m - ch.amplitude_m, ch.offset_m + ch.amplitude_m, 'chirp.amplitude_m',
                'chirp.offset_m')
    if p.kind == 'step':
        st = p.step
        lo_name = 'step.initial_m' if st.initial_m <= st.final_m else 'step.final_m'
        hi_name = 'step.final_m' if st.initial_m <= st.final_m else 'step.initial_m'
        return (min(st.initial_m, st.final_m), max(st.initial_m, st.final_m), lo_name, hi_name)
    if p.kind == 'hold':
        return p.hold.position_m, p.hold.position_m, 'hold.position_m', 'hold.position_m'
    raise AssertionError(p.kind)  # csv is checked on its data


def _check_range(p: TrajectoryParams, lo: float, hi: float, lo_name: str, hi_name: str) -> None:
    allowed = f'x_d within the stage travel [{p.travel_min_m:g}, {p.travel_max_m:g}] m'
    if lo < p.travel_min_m - 1e-15:
        value = _get(p, lo_name)
        raise ParameterError(lo_name, value, allowed,
                             f'takes x_d down to {lo:.4g} m, below the stage travel')
    if hi > p.travel_max_m + 1e-15:
        value = _get(p, hi_name)
        raise ParameterError(hi_name, value, allowed,
                             f'takes x_d up to {hi:.4g} m, above the stage travel')


def _get(p: Params, dotted: str) -> object:
    obj: object = p
    for part in dotted.split('.'):
        obj = getattr(obj, part)
    return list(obj) if isinstance(obj, tuple) else obj


def check_sampling(params: TrajectoryParams, sample_rate_hz: float) -> None:
    """
    Refuse a trajectory the sample rate cannot draw.

    A scan line needs at least one sample period in each turnaround and in each linear part:
    otherwise the samples jump from one linear part to the next (or over it) and the sampled
    reference is no raster line. The fastest line is so min(phi, 1 - phi) f_s / 2 (1 kHz at
    10 kHz with 80 % linear). The other kinds are not checked here.

    Parameters
    ----------
    params : TrajectoryParams
        The trajectory.
    sample_rate_hz : float
        The loop's sample rate f_s [Hz].

    Raises
    ------
    ParameterError
        Naming ``scan_line.frequency_hz``, its value and the allowed range.

    """
    if params.kind != 'scan_line':
        return
    sl = params.scan_line
    fastest = min(sl.linear_fraction, 1.0 - sl.linear_fraction) * sample_rate_hz / 2.0
    if sl.frequency_hz > fastest * (1.0 + 1e-12):
        raise ParameterError('scan_line.frequency_hz', sl.frequency_hz,
                             f'(0, {fastest:g}] Hz at {sample_rate_hz:g} Hz sampling and '
                             f'linear_fraction {sl.linear_fraction:g}',
                             'is above the line rate the sample rate can draw (each turnaround '
                             'and each linear part needs at least one sample period)')


def _common_period(frequencies_hz: tuple[float, ...]) -> float | None:
    """Return the common period of sines of these frequencies, or None if above 1000 s."""
    fracs = [Fraction(f).limit_denominator(1000) for f in frequencies_hz]
    if any(abs(float(fr) - f) > 1e-9 * f for fr, f in zip(fracs, frequencies_hz)):
        return None
    # period = lcm of 1/f_i = 1 / gcd(f_i) for rationals
    num = 0
    den = 1
    for fr in fracs:
        den = den * fr.denominator // math.gcd(den, fr.denominator)
    for fr in fracs:
        num = math.gcd(num, fr.numerator * (den // fr.denominator))
    if num == 0:
        return None
    period = den / num
    return period if period <= 1000.0 else None


class TrajectoryBase:
    """
    Common part of the trajectories: the period (None if aperiodic) and the extent.

    Attributes
    ----------
    period_s : float or None
        Period of x_d [s]; the steady-state window of :mod:`piezo_stage_ros.core.loop.metrics`
        uses it.
    kind : str
        The trajectory kind.
    lines : dict or None
        A raster line's linear part (``low_m``, ``high_m``, ``speed_mps``, ``period_s``, ...),
        stored in a run's meta for the line metrics; None for the other kinds.

    """

    period_s: float | None = None
    kind: str = ''
    lines: dict[str, float] | None = None

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """
        Return x_d(t) [m] and dx_d/dt(t) [m/s], same shape as ``time_s``.

        Parameters
        ----------
        time_s : array_like
            Times since the start of the run [s].

        Returns
        -------
        position_m, velocity_mps : ndarray

        """
        raise NotImplementedError


class _Sine(TrajectoryBase):
    kind = 'sine'

    def __init__(self, p: SineParams) -> None:
        self._c, self._a, self._w = p.offset_m, p.amplitude_m, 2 * math.pi * p.frequency_hz
        self.period_s = 1.0 / p.frequency_hz

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        phase = self._w * np.asarray(time_s, dtype=np.float64)
        return self._c + self._a * np.sin(phase), self._a * self._w * np.cos(phase)


class _Multisine(TrajectoryBase):
    kind = 'multisine'

    def __init__(self, p: MultisineParams) -> None:
        self._c = p.offset_m
        self._terms = [(a, 2 * math.pi * f) for a, f in zip(p.amplitudes_m, p.frequencies_hz)]
        self.period_s = _common_period(p.frequencies_hz)

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        t = np.asarray(time_s, dtype=np.float64)
        pos = np.full(t.shape, self._c)
        vel = np.zeros(t.shape)
        for a, w in self._terms:
            pos += a * np.sin(w * t)
            vel += a * w * np.cos(w * t)
        return pos, vel


class _Square(TrajectoryBase):
    kind = 'square'

    def __init__(self, p: SquareParams) -> None:
        self._p = p
        self.period_s = p.period_s

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        t = np.asarray(time_s, dtype=np.float64)
        p = self._p
        # low for the first (1 - duty) of each period; a tiny guard makes k T land on the
        # level that starts exactly there despite rounding in k * T / period
        frac = np.mod(t / p.period_s + 1e-9, 1.0)
        if p.transition_s == 0.0:
            pos = np.where(frac < 1.0 - p.duty, p.low_m, p.low_m + p.peak_to_peak_m)
            return np.asarray(pos, dtype=np.float64), np.zeros(t.shape)
        tau = (frac - 1e-9) * p.period_s           # time since the start of the period
        rise_at = (1.0 - p.duty) * p.period_s
        # rising S-curve from rise_at; falling one from the start of every period but the
        # first (the run starts at rest on the low level)
        up, dup = s_curve((tau - rise_at) / p.transition_s)
        down, ddown = s_curve(tau / p.transition_s)
        first = t / p.period_s + 1e-9 < 1.0
        falling = (tau < rise_at) & ~first
        q = np.where(tau >= rise_at, up, np.where(falling, 1.0 - down, 0.0))
        dq = np.where(tau >= rise_at, dup, np.where(falling, -ddown, 0.0))
        return (np.asarray(p.low_m + p.peak_to_peak_m * q, dtype=np.float64),
                np.asarray(p.peak_to_peak_m * dq / p.transition_s, dtype=np.float64))


class _Staircase(TrajectoryBase):
    kind = 'staircase'

    def __init__(self, p: StaircaseParams) -> None:
        self._p = p

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        t = np.asarray(time_s, dtype=np.float64)
        p = self._p
        level = np.clip(np.floor(t / p.dwell_s + 1e-9), 0, p.steps)
        if p.transition_s == 0.0:
            return p.start_m + level * p.step_m, np.zeros(t.shape)
        # level j >= 1 starts at j dwell with an S-curve up from level j - 1
        q, dq = s_curve((t - level * p.dwell_s) / p.transition_s)
        moving = level >= 1
        pos = p.start_m + np.where(moving, level - 1.0 + q, 0.0) * p.step_m
        vel = np.where(moving, dq, 0.0) * p.step_m / p.transition_s
        return np.asarray(pos, dtype=np.float64), np.asarray(vel, dtype=np.float64)


class _Step(TrajectoryBase):
    kind = 'step'

    def __init__(self, p: StepParams) -> None:
        self._p = p

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        t = np.asarray(time_s, dtype=np.float64)
        p = self._p
        if p.transition_s == 0.0:
            pos = np.where(t >= p.time_s - 1e-12, p.final_m, p.initial_m)
            return np.asarray(pos, dtype=np.float64), np.zeros(t.shape)
        q, dq = s_curve((t - p.time_s) / p.transition_s)
        jump = p.final_m - p.initial_m
        return (np.asarray(p.initial_m + jump * q, dtype=np.float64),
                np.asarray(jump * dq / p.transition_s, dtype=np.float64))


class _Triangle(TrajectoryBase):
    kind = 'triangle'

    def __init__(self, p: TriangleParams) -> None:
        self._p = p
        self.period_s = 1.0 / p.frequency_hz

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        t = np.asarray(time_s, dtype=np.float64)
        p = self._p
        # phase u in [0, 1): rising on [0, 1/4) and [3/4, 1), falling on [1/4, 3/4)
        u = np.mod(t * p.frequency_hz, 1.0)
        falling = (u >= 0.25) & (u < 0.75)
        shape = np.where(falling, 2.0 - 4.0 * u, np.where(u < 0.25, 4.0 * u, 4.0 * u - 4.0))
        slope = np.where(falling, -4.0, 4.0) * p.amplitude_m * p.frequency_hz
        return p.offset_m + p.amplitude_m * shape, np.asarray(slope, dtype=np.float64)


class _ScanLine(TrajectoryBase):
    kind = 'scan_line'

    def __init__(self, p: ScanLineParams) -> None:
        self._p = p
        self._period = 1.0 / p.frequency_hz
        self.period_s = self._period
        self._q, _, self._integral = smoothstep(p.continuity_order - 1)
        self.speed_mps = p.speed_mps
        # the linear part of each line, as the metrics take it (JSON-able; in a run's meta)
        self.lines = {'low_m': p.offset_m - p.amplitude_m, 'high_m': p.offset_m + p.amplitude_m,
                      'speed_mps': p.speed_mps, 'period_s': self._period,
                      'linear_fraction': p.linear_fraction,
                      'continuity_order': p.continuity_order}

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        t = np.asarray(time_s, dtype=np.float64)
        p = self._p
        v, period, turn = self.speed_mps, self._period, p.turn_s
        linear = p.linear_fraction * period / 2.0
        half = period / 2.0
        # tau: time since the start of a trace's linear part; t = 0 is its middle (x_d = offset)
        tau = np.mod(t + linear / 2.0, period)
        retrace = tau >= half
        tau_h = np.where(retrace, tau - half, tau)      # time into the half line
        turning = tau_h >= linear
        s = np.clip((tau_h - linear) / turn, 0.0, 1.0)
        # within the half line going up (trace) from offset - A: linear then the turnaround
        up = np.where(turning, p.amplitude_m + v * turn * (s - 2.0 * self._integral(s)),
                      -p.amplitude_m + v * tau_h)
        dup = np.where(turning, v * (1.0 - 2.0 * self._q(s)), v)
        sign = np.where(retrace, -1.0, 1.0)
        return (np.asarray(p.offset_m + sign * up, dtype=np.float64),
                np.asarray(sign * dup, dtype=np.float64))
class _Hold(TrajectoryBase):
    kind = 'hold'

    def __init__(self, p: HoldParams) -> None:
        self._x = p.position_m

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        shape = np.shape(time_s)
        return np.full(shape, self._x), np.zeros(shape)


class _Excitation(TrajectoryBase):
    """An identification excitation (core/signals/excitation.py) as a trajectory."""

    def __init__(self, inner: NoiseExcitation | ChirpExcitation) -> None:
        self._inner = inner
        self.kind = inner.kind
        self.period_s = inner.period_s

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        return self._inner.evaluate(time_s)


class TableTrajectory(TrajectoryBase):
    """
    A trajectory from a table: piecewise-linear position, piecewise-constant derivative.

    Parameters
    ----------
    time_s : array_like
        Strictly increasing times [s].
    position_m : array_like
        Positions [m] at those times.

    """

    kind = 'csv'

    def __init__(self, time_s: ArrayLike, position_m: ArrayLike) -> None:
        self._t = np.asarray(time_s, dtype=np.float64).ravel()
        self._x = np.asarray(position_m, dtype=np.float64).ravel()
        if self._t.size < 2 or self._t.size != self._x.size:
            raise ConfigError(f'trajectory table: need at least 2 rows of (time_s, position_m), '
                              f'got {self._t.size} times and {self._x.size} positions')
        if not (np.all(np.isfinite(self._t)) and np.all(np.isfinite(self._x))):
            raise ConfigError('trajectory table: times and positions must be finite numbers')
        if not np.all(np.diff(self._t) > 0.0):
            i = int(np.flatnonzero(np.diff(self._t) <= 0.0)[0]) + 1
            raise ConfigError(f'trajectory table: time_s must increase strictly; row {i + 1} '
                              f'has {self._t[i]:g} s after {self._t[i - 1]:g} s')
        self._slope = np.diff(self._x) / np.diff(self._t)

    @property
    def end_s(self) -> float:
        """Return the time of the table's last row [s]: where the recorded reference ends."""
        return float(self._t[-1])

    @property
    def extent_m(self) -> tuple[float, float]:
        """Return the lowest and highest position of the table [m]."""
        return float(np.min(self._x)), float(np.max(self._x))

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        t = np.asarray(time_s, dtype=np.float64)
        pos = np.interp(t, self._t, self._x)
        # segment i covers [t_i, t_i+1); outside the table the position is held
        seg = np.searchsorted(self._t, t, side='right') - 1
        inside = (seg >= 0) & (seg < self._slope.size)
        vel = np.where(inside, self._slope[np.clip(seg, 0, self._slope.size - 1)], 0.0)
        return np.asarray(pos, dtype=np.float64), np.asarray(vel, dtype=np.float64)


def load_table(path: str | os.PathLike[str]) -> TableTrajectory:
    """
    Read a CSV table with a header naming the columns ``time_s`` and ``position_m``.

    Parameters
    ----------
    path : path-like
        The file; other columns are ignored; ``#`` starts a comment.

    Returns
    -------
    TableTrajectory

    Raises
    ------
    ConfigError
        If the file cannot be read, lacks a column, holds a non-number or non-increasing times.

    """
    p = Path(path)
    try:
        lines = [ln for ln in p.read_text(encoding='utf-8').splitlines()
                 if ln.strip() and not ln.lstrip().startswith('#')]
    except OSError as exc:
        raise ConfigError(f'{p}: cannot read trajectory table ({exc.strerror})') from None
    if not lines:
        raise ConfigError(f'{p}: trajectory table is empty')
    header = [h.strip() for h in lines[0].split(',')]
    for need in ('time_s', 'position_m'):
        if need not in header:
            raise ConfigError(f'{p}: trajectory table has no column {need!r} '
                              f'(header: {", ".join(header)})')
    it, ix = header.index('time_s'), header.index('position_m')
    times: list[float] = []
    positions: list[float] = []
    for row, line in enumerate(lines[1:], start=2):
        cells = line.split(',')
        try:
            times.append(float(cells[it]))
            positions.append(float(cells[ix]))
        except (IndexError, ValueError):
            raise ConfigError(f'{p}: line {row} of the trajectory table is not two numbers '
                              f'under time_s and position_m: {line.strip()!r}') from None
    try:
        return TableTrajectory(times, positions)
    except ConfigError as exc:
        raise ConfigError(f'{p}: {exc}') from None


def make_trajectory(params: TrajectoryParams, *,
                    sample_rate_hz: float | None = None) -> TrajectoryBase:
    """
    Build the trajectory ``params.kind`` names.

    Parameters
    ----------
    params : TrajectoryParams
        Kind and parameters (validated, inside the travel).
    sample_rate_hz : float, optional
        The loop's sample rate [Hz]: when given, a trajectory it cannot draw is refused
        (:func:`check_sampling`).

    Returns
    -------
    TrajectoryBase
        An object with ``evaluate(time_s)`` and ``period_s``.

    Raises
    ------
    ParameterError
        If a csv table leaves the stage travel, or the sample rate cannot draw the trajectory.
    ConfigError
        If the csv table cannot be read.

    """
    kind = params.kind
    if sample_rate_hz is not None:
        check_sampling(params, sample_rate_hz)
    if kind == 'sine':
        return _Sine(params.sine)
    if kind == 'scan_line':
        return _ScanLine(params.scan_line)
    if kind == 'multisine':
        return _Multisine(params.multisine)
    if kind == 'square':
        return _Square(params.square)
    if kind == 'staircase':
        return _Staircase(params.staircase)
    if kind == 'step':
        return _Step(params.step)
    if kind == 'triangle':
        return _Triangle(params.triangle)
    if kind == 'noise':
        return _Excitation(NoiseExcitation(params.noise))
    if kind == 'chirp':
        return _Excitation(ChirpExcitation(params.chirp))
    if kind == 'hold':
        return _Hold(params.hold)
    if not params.csv.path:
        raise ParameterError('csv.path', '', 'the path of a CSV file',
                             'is empty but kind is csv')
    table = load_table(params.csv.path)
    lo, hi = table.extent_m
    allowed = f'x_d within the stage travel [{params.travel_min_m:g}, {params.travel_max_m:g}] m'
    if lo < params.travel_min_m or hi > params.travel_max_m:
        bad = lo if lo < params.travel_min_m else hi
        raise ParameterError('csv.path', params.csv.path, allowed,
                             f'holds position {bad:.4g} m, outside the stage travel')
    return table
