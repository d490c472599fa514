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
Excitation signals for system identification (section III-D of the paper).

Two signals the paper's procedure needs beyond the trajectories of
:mod:`piezo_stage_ros.core.loop.trajectories` (whose ``step`` and ``square`` kinds give the small
step and the step train, and ``sine`` the 1 + sin(2 pi 100 t) V hysteresis run):

- :class:`NoiseExcitation` (``noise``): band-limited white noise, a random-phase multisine with a
  flat amplitude spectrum between ``band_low_hz`` and ``band_high_hz`` and nothing outside it,
  periodic with ``period_s``. It is computed once on a fine grid by an inverse FFT (value and
  exact derivative) and interpolated linearly between grid points; loop sample times that fall on
  the grid (10 and 20 kHz loops with the default 40 kHz grid) get the exact band-limited values.
- :class:`ChirpExcitation` (``chirp``): a sine sweep from ``f0_hz`` to ``f1_hz`` in ``sweep_s``,
  linear or logarithmic in frequency, repeated; exact derivative.

Both are :class:`~piezo_stage_ros.core.contracts.interfaces.Trajectory` objects in metres (a
position reference for the trajectory node and the closed loop, ``simulate --trajectory noise``).
For an open-loop (voltage) run, the ``open_loop`` controller turns them into volts
(v = gain x_d + offset); identification uses the recorded command, whatever produced it. Every
signal is deterministic: the same parameters (and seed) give the same samples.

They live with the signals, below the model, rather than with identification: the trajectories
(:mod:`piezo_stage_ros.core.loop.trajectories`, a floor below identification) offer them as the
``noise`` and ``chirp`` kinds, and a floor may only use the floors under it.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
from numpy.typing import ArrayLike
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.params import param, Params
from piezo_stage_ros.core.contracts.types import FloatArray

__all__ = ['ChirpExcitation', 'ChirpParams', 'NoiseExcitation', 'NoiseParams',
           'make_excitation']


@dataclass(frozen=True)
class NoiseParams(Params):
    """
    Band-limited white noise around an offset, deterministic from a seed.

    The default is a small excitation for the paper's stage: 0.1 um rms around 3.8 um, flat from
    5 Hz to 5 kHz (above the 3.2 kHz resonance), repeating every second.
    """

    offset_m: float = param(3.8e-6, unit='m', description='Mean of the noise.')
    amplitude_m: float = param(0.1e-6, unit='m', description='Root-mean-square deviation from '
                               'the offset.', low=0.0)
    band_low_hz: float = param(5.0, unit='Hz', description='Lowest frequency of the flat band.',
                               low=0.0, low_open=True)
    band_high_hz: float = param(5000.0, unit='Hz', description='Highest frequency of the flat '
                                'band (must be below grid_rate_hz / 2).', low=0.0, low_open=True)
    period_s: float = param(1.0, unit='s', description='Length of the realization, repeated '
                            'after it (frequency resolution 1/period).', low=1e-3, high=100.0)
    grid_rate_hz: float = param(40000.0, unit='Hz', description='Rate of the grid the signal is '
                                'computed on; a multiple of the loop rate gives exact samples.',
                                low=100.0, high=1e6)
    seed: int = param(1, unit='-', description='Seed of the random phases.', low=0)

    def _check(self) -> None:
        if not self.band_low_hz < self.band_high_hz:
            raise ParameterError('band_high_hz', self.band_high_hz,
                                 f'> band_low_hz = {self.band_low_hz:g}',
                                 'is not above the low end of the band')
        if not self.band_high_hz < self.grid_rate_hz / 2.0:
            raise ParameterError('band_high_hz', self.band_high_hz,
                                 f'< grid_rate_hz / 2 = {self.grid_rate_hz / 2.0:g}',
                                 'is above the Nyquist frequency of the grid')
        if self.band_high_hz - self.band_low_hz < 1.0 / self.period_s:
            raise ParameterError('band_high_hz', self.band_high_hz,
                                 f'>= band_low_hz + 1/period_s = '
                                 f'{self.band_low_hz + 1.0 / self.period_s:g}',
                                 'leaves no frequency of the period inside the band')


@dataclass(frozen=True)
class ChirpParams(Params):
    """
    Sine sweep x = offset + A sin(phi(t)) from ``f0_hz`` to ``f1_hz`` in ``sweep_s``, repeated.

    With ``f0_hz == f1_hz`` it is a sine (e.g. the paper's 100 Hz hysteresis test).
    """

    offset_m: float = param(3.8e-6, unit='m', description='Centre of the sweep.')
    amplitude_m: float = param(0.1e-6, unit='m', description='Amplitude A.', low=0.0)
    f0_hz: float = param(10.0, unit='Hz', description='Frequency at the start of a sweep.',
                         low=0.0, low_open=True)
    f1_hz: float = param(5000.0, unit='Hz', description='Frequency at the end of a sweep.',
                         low=0.0, low_open=True)
    sweep_s: float = param(1.0, unit='s', description='Duration of one sweep; the sweep '
                           'restarts (phase 0) after it.', low=1e-3, high=1000.0)
    method: str = param('logarithmic', unit='-', description='How the frequency moves: '
                        'linearly or geometrically in time.',
                        choices=('linear', 'logarithmic'))


class _ExcitationBase:
    """Attributes shared with the trajectories: ``kind``, ``period_s``, the extent, evaluation."""

    kind = ''
    period_s: float | None = None

    @property
    def extent_m(self) -> tuple[float, float]:
        """Return the lowest and highest value the signal takes [m]."""
        raise NotImplementedError

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """
        Return the signal and its derivative at ``time_s``.

        Parameters
        ----------
        time_s : array_like
            Times since the start [s].

        Returns
        -------
        position_m, velocity_mps : ndarray
            Same shape as ``time_s``.

        """
        pos, vel = self._evaluate(np.asarray(time_s, dtype=np.float64))
        return np.asarray(pos, dtype=np.float64), np.asarray(vel, dtype=np.float64)

    def _evaluate(self, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Return position [m] and velocity [m/s] at the times ``t`` [s]."""
        raise NotImplementedError


class NoiseExcitation(_ExcitationBase):
    """
    Band-limited white noise (random-phase multisine), see :class:`NoiseParams`.

    Parameters
    ----------
    params : NoiseParams
        Band, amplitude, offset, period, grid and seed.

    """

    kind = 'noise'

    def __init__(self, params: NoiseParams) -> None:
        self.params = params
        n = max(int(round(params.period_s * params.grid_rate_hz)), 4)
        self.period_s = n / params.grid_rate_hz
        freqs = np.fft.rfftfreq(n, d=1.0 / params.grid_rate_hz)
        band = (freqs >= params.band_low_hz) & (freqs <= params.band_high_hz)
        rng = np.random.default_rng(params.seed)
        # flat magnitude and uniform random phases: exactly band-limited, white inside the band,
        # near-Gaussian in amplitude when the band holds many frequencies
        spectrum = np.zeros(freqs.size, dtype=np.complex128)
        spectrum[band] = np.exp(1j * rng.uniform(0.0, 2.0 * math.pi, int(band.sum())))
        shape = np.fft.irfft(spectrum, n)
        slope = np.fft.irfft(spectrum * (2j * math.pi * freqs), n)
        rms = float(np.sqrt(np.mean(shape ** 2)))
        scale = params.amplitude_m / rms if rms > 0.0 else 0.0
        self._grid_s = np.arange(n) / params.grid_rate_hz
        self._value = params.offset_m + scale * shape
        self._slope = scale * slope

    @property
    def extent_m(self) -> tuple[float, float]:
        """Return the lowest and highest value on the grid [m]."""
        return float(self._value.min()), float(self._value.max())

    def _evaluate(self, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        pos = np.interp(t, self._grid_s, self._value, period=self.period_s)
        vel = np.interp(t, self._grid_s, self._slope, period=self.period_s)
        return pos, vel


class ChirpExcitation(_ExcitationBase):
    """
    Repeated sine sweep, see :class:`ChirpParams`.

    Parameters
    ----------
    params : ChirpParams
        Band, sweep duration, law, amplitude and offset.

    """

    kind = 'chirp'

    def __init__(self, params: ChirpParams) -> None:
        self.params = params
        self.period_s = params.sweep_s

    @property
    def extent_m(self) -> tuple[float, float]:
        """Return offset -+ amplitude [m]."""
        p = self.params
        return p.offset_m - p.amplitude_m, p.offset_m + p.amplitude_m

    def frequency_hz(self, time_s: ArrayLike) -> FloatArray:
        """Return the instantaneous frequency d phi/dt / (2 pi) [Hz] at ``time_s`` [s]."""
        p = self.params
        tau = np.mod(np.asarray(time_s, dtype=np.float64), p.sweep_s) / p.sweep_s
        if p.method == 'linear' or p.f0_hz == p.f1_hz:
            return np.asarray(p.f0_hz + (p.f1_hz - p.f0_hz) * tau, dtype=np.float64)
        return np.asarray(p.f0_hz * (p.f1_hz / p.f0_hz) ** tau, dtype=np.float64)

    def _evaluate(self, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        p = self.params
        t = np.mod(t, p.sweep_s)
        if p.method == 'linear' or p.f0_hz == p.f1_hz:
            phase = 2.0 * math.pi * (p.f0_hz * t + (p.f1_hz - p.f0_hz) * t * t / (2 * p.sweep_s))
        else:
            ratio = p.f1_hz / p.f0_hz
            phase = 2.0 * math.pi * p.f0_hz * p.sweep_s / math.log(ratio) * (
                ratio ** (t / p.sweep_s) - 1.0)
        omega = 2.0 * math.pi * self.frequency_hz(t)
        return p.offset_m + p.amplitude_m * np.sin(phase), p.amplitude_m * omega * np.cos(phase)


def make_excitation(kind: str, params: NoiseParams | ChirpParams
                    ) -> NoiseExcitation | ChirpExcitation:
    """
    Build the excitation ``kind`` names from its parameters.

    Parameters
    ----------
    kind : {'noise', 'chirp'}
        Signal kind.
    params : NoiseParams or ChirpParams
        Its parameters (the type must match the kind).

    Returns
    -------
    NoiseExcitation or ChirpExcitation

    Raises
    ------
    ParameterError
        On an unknown kind or parameters of the wrong type.

    """
    if kind == 'noise' and isinstance(params, NoiseParams):
        return NoiseExcitation(params)
    if kind == 'chirp' and isinstance(params, ChirpParams):
        return ChirpExcitation(params)
    raise ParameterError('kind', kind, "'noise' with NoiseParams or 'chirp' with ChirpParams",
                         f'does not match {type(params).__name__}')
