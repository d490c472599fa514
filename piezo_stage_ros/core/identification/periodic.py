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
Spectra of a periodic excitation averaged over whole periods, with a noise estimate per line.

With an excitation that repeats every N samples, the DFT of each whole period puts the
excitation exactly on the lines k / (N T) (no leakage, no window). Averaging P periods keeps
what repeats (the response to the excitation, and the periodic part of any nonlinear
distortion) and shrinks what does not (sensor noise, and the noise fed back by a controller)
by P; the scatter of the P spectra around their mean estimates that noise line by line
(Pintelon and Schoukens, *System Identification: A Frequency Domain Approach*, ch. 2 and 7).

The frequency response from the applied input U to the position Y is G = mean(Y) / mean(U) on
the excited lines. In closed loop both U and Y carry the same fed-back noise; averaged over
whole periods it enters as cov(U, Y) / P, so the ratio is consistent (the H1 estimate
S_uy / S_uu of a closed loop is not: where the noise dominates it tends to -1/C, the inverse of
the controller). The lines that the excitation leaves out measure the nonlinear distortion
(mean) and the noise (scatter): the distortion level, interpolated onto the excited lines, is
added to their variance (the "best linear approximation" with its stochastic nonlinear
contribution).
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
from piezo_stage_ros.core.contracts.types import BoolArray, ComplexArray, FloatArray

__all__ = ['PeriodicSpectra', 'detect_period', 'excited_lines', 'periodic_spectra']


def detect_period(x: FloatArray, *, tolerance: float = 1e-6, min_periods: int = 2,
                  hint_samples: int | None = None) -> int | None:
    """
    Return the shortest whole-sample period of a signal, or None if it does not repeat.

    Parameters
    ----------
    x : ndarray
        The signal (e.g. a reference or an applied voltage).
    tolerance : float
        Largest rms of x[k + N] - x[k] allowed, relative to the rms of x about its mean.
    min_periods : int
        The signal must hold at least this many whole periods.
    hint_samples : int, optional
        A period to try first (e.g. from the run's meta); its multiples are tried too.

    Returns
    -------
    int or None
        N in samples, or None (constant signal, not periodic, or fewer than ``min_periods``
        periods).

    Notes
    -----
    sum (x[k+N] - x[k])^2 over the overlap is computed for every N at once from the
    autocorrelation (FFT) and cumulative sums of x^2: O(n log n).

    """
    x = np.asarray(x, dtype=np.float64)
    x = x - float(np.mean(x))
    n = x.size
    scale = float(np.sqrt(np.mean(x * x)))
    if n < 2 * min_periods or not scale > 0.0:
        return None
    top = n // min_periods

    def mismatch(lag: int) -> float:
        d = x[lag:] - x[:-lag]
        return float(np.sqrt(np.mean(d * d))) / scale

    if hint_samples is not None and 2 <= hint_samples <= top:
        for m in range(1, top // hint_samples + 1):
            if mismatch(hint_samples * m) <= tolerance:
                return hint_samples * m
    size = 1 << int(math.ceil(math.log2(2 * n)))
    spec = np.fft.rfft(x, size)
    acf = np.fft.irfft(spec * np.conj(spec), size)[:top + 1]
    c2 = np.concatenate([[0.0], np.cumsum(x * x)])
    lags = np.arange(1, top + 1)
    # sum over k < n - N of x[k+N]^2 + x[k]^2 - 2 x[k+N] x[k]
    ss = (c2[n] - c2[lags]) + c2[n - lags] - 2.0 * acf[1:top + 1]
    ms = np.sqrt(np.maximum(ss, 0.0) / (n - lags)) / scale
    # a loose pass to find candidates (FFT rounding), an exact check on each
    for lag in lags[ms <= max(10.0 * tolerance, 1e-6)]:
        if mismatch(int(lag)) <= tolerance:
            return int(lag)
    return None


@dataclass(frozen=True)
class PeriodicSpectra:
    """
    DFT lines of the input, the output and the excitation averaged over whole periods.

    Attributes
    ----------
    frequency_hz : ndarray
        Line frequencies k / (N T), k = 1 ... N/2 [Hz].
    u, y, r : ndarray of complex
        Mean over the periods of the DFT of the applied input, the position and the excitation
        (reference) per line (unnormalized DFT).
    var_u, var_y : ndarray
        Variance of the mean of U and Y per line (the scatter over periods / P).
    cov_yu : ndarray of complex
        Covariance of the means of Y and conj(U) per line.
    periods : int
        Whole periods averaged.
    period_samples : int
    sample_time_s : float

    """

    frequency_hz: FloatArray
    u: ComplexArray
    y: ComplexArray
    r: ComplexArray
    var_u: FloatArray
    var_y: FloatArray
    cov_yu: ComplexArray
    periods: int
    period_samples: int
    sample_time_s: float

    @property
    def snr_u(self) -> FloatArray:
        """Return |mean U|^2 / var(mean U) per line (power signal-to-noise ratio)."""
        return np.asarray(np.abs(self.u) ** 2 / np.maximum(self.var_u, 1e-300),
                          dtype=np.float64)

    @property
    def snr_y(self) -> FloatArray:
        """Return |mean Y|^2 / var(mean Y) per line."""
        return np.asarray(np.abs(self.y) ** 2 / np.maximum(self.var_y, 1e-300),
                          dtype=np.float64)

    def response(self) -> tuple[ComplexArray, FloatArray, FloatArray]:
        """
        Return G = mean Y / mean U, its noise variance and its distortion variance per line.

        Returns
        -------
        g : ndarray of complex
            The frequency response [m/V].
        var_noise : ndarray
            Variance of G from the noise (first order in the noise of U and Y, their
            correlation included).
        var_distortion : ndarray
            Variance of G from the nonlinear distortion: the power of mean Y and mean U on the
            lines the excitation leaves out (interpolated onto every line in log power)
            through G, over |mean U|^2; zeros when every line is excited.

        """
        # a line the excitation leaves out may hold exactly nothing (a pure sine's reference):
        # its ratio is not a number, and is never used as an excited line
        with np.errstate(divide='ignore', invalid='ignore'):
            g = self.y / self.u
            rel_var = (self.var_y / np.abs(self.y) ** 2 + self.var_u / np.abs(self.u) ** 2
                       - 2.0 * np.real(self.cov_yu / (self.y * np.conj(self.u))))
        var_noise = np.abs(g) ** 2 * np.maximum(rel_var, 0.0)
        quiet = ~excited_lines(self.r)
        if int(quiet.sum()) < 2:
            return (np.asarray(g, dtype=np.complex128), np.asarray(var_noise, dtype=np.float64),
                    np.zeros(g.size))
        f = self.frequency_hz
        # the mean on a line the excitation leaves out: distortion, plus the averaged noise
        py = np.maximum(np.abs(self.y[quiet]) ** 2 - self.var_y[quiet], 0.0) + 1e-300
        pu = np.maximum(np.abs(self.u[quiet]) ** 2 - self.var_u[quiet], 0.0) + 1e-300
        py_i = np.exp(np.interp(f, f[quiet], np.log(py)))
        pu_i = np.exp(np.interp(f, f[quiet], np.log(pu)))
        var_dist = (py_i + np.abs(g) ** 2 * pu_i) / np.abs(self.u) ** 2
        return (np.asarray(g, dtype=np.complex128), np.asarray(var_noise, dtype=np.float64),
                np.asarray(var_dist, dtype=np.float64))


def excited_lines(r: ComplexArray, *, floor: float = 1e-4) -> BoolArray:
    """
    Return the lines an excitation drives: amplitude above ``floor`` times the largest line.

    Parameters
    ----------
    r : ndarray of complex
        Averaged DFT lines of the excitation (DC left out).
    floor : float
        Relative amplitude threshold (1e-4: -80 dB, above the rounding and DAC-quantization
        lines of a repeated signal).

    Returns
    -------
    ndarray of bool

    """
    mag = np.abs(np.asarray(r))
    top = float(mag.max()) if mag.size else 0.0
    if not top > 0.0:
        return np.zeros(mag.size, dtype=bool)
    return np.asarray(mag > floor * top, dtype=bool)


def periodic_spectra(u: FloatArray, y: FloatArray, r: FloatArray, period_samples: int,
                     sample_time_s: float, *, skip_periods: int = 1) -> PeriodicSpectra:
    """
    Average the DFT of u, y and r over whole periods.

    Parameters
    ----------
    u, y, r : ndarray
        Applied input [V], position [m], excitation (the reference, or the input itself in
        open loop), same length.
    period_samples : int
        Period N of the excitation in samples.
    sample_time_s : float
        Sample period T [s].
    skip_periods : int
        Whole periods left out at the start (the transient), kept down to leave two periods.

    Returns
    -------
    PeriodicSpectra

    Raises
    ------
    ValueError
        If fewer than two whole periods are available.

    """
    n = period_samples
    total = len(u) // n
    skip = min(skip_periods, max(total - 2, 0))
    count = total - skip
    if count < 2:
        raise ValueError(f'{total} whole periods of {n} samples, need at least 2')
    sl = slice(skip * n, (skip + count) * n)

    def lines(x: FloatArray) -> ComplexArray:
        blocks = np.asarray(x, dtype=np.float64)[sl].reshape(count, n)
        return np.asarray(np.fft.rfft(blocks, axis=1)[:, 1:n // 2 + 1], dtype=np.complex128)

    uu, yy, rr = lines(u), lines(y), lines(r)
    um, ym = uu.mean(axis=0), yy.mean(axis=0)
    var_u = np.sum(np.abs(uu - um) ** 2, axis=0) / (count - 1) / count
    var_y = np.sum(np.abs(yy - ym) ** 2, axis=0) / (count - 1) / count
    cov = np.sum((yy - ym) * np.conj(uu - um), axis=0) / (count - 1) / count
    freqs = np.arange(1, n // 2 + 1) / (n * sample_time_s)
    return PeriodicSpectra(frequency_hz=np.asarray(freqs, dtype=np.float64), u=um, y=ym,
                           r=np.asarray(rr.mean(axis=0), dtype=np.complex128),
                           var_u=np.asarray(var_u, dtype=np.float64),
                           var_y=np.asarray(var_y, dtype=np.float64),
                           cov_yu=np.asarray(cov, dtype=np.complex128), periods=count,
                           period_samples=n, sample_time_s=sample_time_s)
