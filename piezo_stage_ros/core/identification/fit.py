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
System identification of the stage from recorded runs, section III-D of the paper.

The model is the paper's: a hysteresis w = P(v_in) ahead of the linear plant (17), written as

    G(s) = k_p w_n^2 / ((tau s + 1)(s^2 + 2 zeta w_n s + w_n^2))

with K = k_p a2, a2 = w_n^2 / tau, a1 = w_n^2 + 2 zeta w_n / tau, a0 = 1/tau + 2 zeta w_n.

The procedure (every fit is in discrete time: the model's response is that of the exact
zero-order-hold discretization at the record's sample period, so the sampling and the hold near
the 3.2 kHz resonance are modelled, not ignored):

1. PSCM gain from two points, eq. (15): :func:`pscm_gain`.
2. Frequency response of a small-amplitude noise (or chirp) run, H1 = S_uy / S_uu from Welch
   cross-spectra of the applied voltage u and the measured position y
   (:func:`estimate_frequency_response`); a weighted least-squares fit of the log of the discrete
   model's response gives k_p and w_n (:func:`fit_frequency_response`).
3. Step response of a small-amplitude step run: with w_n fixed, zeta and tau
   (:func:`fit_step_response`). A DAC step is exact for the linear part: the hysteresis output
   jumps once per input jump and is then constant, so the response is a linear step response
   whose heights (one per jump) are fitted too, as linear parameters.
4. Hysteresis by nonlinear least squares on a sine run (the paper: 1 + sin(2 pi 100 t) V), with
   the linear shape (w_n, zeta, tau) fixed (:func:`fit_hysteresis`), using the exact stepping of
   :mod:`piezo_stage_ros.core.model.hysteresis` on the applied voltages (one pass per evaluation).

What v_in -> x data cannot give, and how it is resolved: scaling the linear gain k_p by lambda
and the hysteresis output w by 1/lambda (c, B1 and the initial d of eq. (22) for the
backlash-like model; d_p for Bouc-Wen; every weight for Prandtl-Ishlinskii) gives exactly the same
v_in -> x behaviour. Only products are identifiable: the static gain k_p c (the slope of x
against v far from a reversal), k_p B1, alpha. Step 4 therefore fits the static gain k_p c with
the hysteresis shape, and the split is fixed by a convention: the hysteresis slope (c, d_p or
p0 + sum p_i) is set to ``IdentificationParams.hysteresis_slope`` (default the paper's c =
1.0341). Every use of the model is invariant under this choice (simulated positions, and the
controller's theta = a/(b c), phi = 1/(b c), rho/c). The small-signal k_p of step 2 is reported
but not used for K: under small noise the hysteresis acts with a slope between B1 and c, so it
is biased by up to (c - B1)/c (7 % for the paper's stage).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.errors import (
    IdentificationError,
    ParameterError,
    PiezoStageError,
)
from piezo_stage_ros.core.contracts.params import param, Params
from piezo_stage_ros.core.contracts.types import BoolArray, ComplexArray, FloatArray
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.model.hysteresis import (
    BacklashLike,
    BacklashLikeParams,
    BoucWen,
    BoucWenParams,
    HysteresisParams,
    PrandtlIshlinskii,
    PrandtlIshlinskiiParams,
)
from piezo_stage_ros.core.model.linear import (
    factors_of,
    LinearFactors,
    third_order_of,
    third_order_plant,
    ThirdOrderParams,
)
from piezo_stage_ros.core.model.stage import amplifier_input, SignalChainParams, StageParams
from scipy import optimize, signal

__all__ = [
    'DELAYS_TRIED', 'FrequencyFit', 'FrequencyResponse', 'HysteresisFit', 'IdentificationParams',
    'IdentificationResult', 'ROLES', 'StepFit', 'WHITE_LAG1_MAX', 'applied_voltage',
    'choose_delay', 'classify_run', 'classify_signal', 'discrete_frequency_response',
    'estimate_frequency_response', 'fit_frequency_response', 'fit_hysteresis',
    'fit_step_response', 'identify', 'pscm_gain', 'residual_whiteness', 'sample_time_of',
    'whole_delay_shift',
]

ComplexArray = ComplexArray

#: Residuals of the time-domain fits are in nanometres (optimizer tolerances are absolute).
_NM = 1e9

#: What a run is used for: the frequency response (noise or chirp), the step response, the
#: hysteresis (a sine).
ROLES = ('frequency', 'step', 'hysteresis')


@dataclass(frozen=True)
class IdentificationParams(Params):
    """Settings of the identification procedure."""

    hysteresis_model: str = param('backlash_like', unit='-', description='Hysteresis model '
                                  'fitted on the sine run.',
                                  choices=('backlash_like', 'bouc_wen', 'prandtl_ishlinskii'))
    hysteresis_slope: float = param(1.0341, unit='-', description='Convention fixing the split '
                                    'of the identifiable static gain k_p c: the hysteresis '
                                    'slope (c, d_p or p0 + sum p_i) is set to this value.',
                                    low=0.0, low_open=True)
    segment_s: float = param(0.05, unit='s', description='Welch segment length of the frequency '
                             'response estimate (resolution 1/segment_s).', low=1e-3)
    band_low_hz: float = param(20.0, unit='Hz', description='Lowest frequency used in the '
                               'frequency-response fit.', low=0.0)
    band_high_fraction: float = param(0.9, unit='-', description='Highest frequency used in the '
                                      'fit, as a fraction of the Nyquist frequency.', low=0.0,
                                      low_open=True, high=1.0)
    coherence_min: float = param(0.8, unit='-', description='Frequencies with a lower '
                                 'coherence are left out of the fit.', low=0.0, high=1.0,
                                 high_open=True)
    step_window_s: float = param(0.006, unit='s', description='Window after each input jump '
                                 'used by the step fit (the paper shows 6 ms).', low=0.0,
                                 low_open=True)
    step_fixes_omega: bool = param(True, unit='-', description='Keep w_n from the frequency '
                                   'response in the step fit (the paper); false fits w_n too.')
    step_max_jumps: int = param(40, unit='-', description='Input jumps of a step run used by '
                                'the fit (the run is cut after the window of the last one).',
                                low=1, high=10000)
    hysteresis_max_s: float = param(0.2, unit='s', description='Length of a sine run used by '
                                    'the hysteresis fit (from its start).', low=0.0,
                                    low_open=True)


def pscm_gain(x0_m: float, x10_m: float, *, span_v: float = 10.0) -> float:
    """
    Return the position sensor module gain from two points, eq. (15).

    Parameters
    ----------
    x0_m : float
        Stage position at which the sensor monitor reads 0 V [m].
    x10_m : float
        Stage position at which it reads ``span_v`` [m].
    span_v : float
        Sensor output span [V] (10 V for the paper's PSCM).

    Returns
    -------
    float
        K_PSCM = span / (x10 - x0) [V/m] (10/38 V/um for the paper's stage).

    Raises
    ------
    ParameterError
        If x10 <= x0 or a value is not finite.

    """
    if not (math.isfinite(x0_m) and math.isfinite(x10_m) and x10_m > x0_m):
        raise ParameterError('x10_m', x10_m, f'a finite number > x0_m = {x0_m:g}',
                             'does not give a positive sensor span')
    if not (span_v > 0.0 and math.isfinite(span_v)):
        raise ParameterError('span_v', span_v, '(0, inf)')
    return span_v / (x10_m - x0_m)


def sample_time_of(record: RunRecord) -> float:
    """
    Return the sample period of a record, checking that it is uniform.

    Parameters
    ----------
    record : RunRecord
        A run with at least 16 samples.

    Returns
    -------
    float
        Median of the time steps [s].

    Raises
    ------
    IdentificationError
        Too few samples, or steps that differ from the median by more than 5 % (gaps).

    """
    n = len(record)
    if n < 16:
        raise IdentificationError(f'run {_name(record)}: {n} samples, need at least 16')
    time_s = np.asarray(record.time_s, dtype=np.float64)
    dt = np.diff(time_s)
    period = float(np.median(dt))
    # stamps in seconds since the epoch are rounded to ~0.24 us: every step, and so their
    # median, is off by up to that (0.24 % of 100 us), which moves w_n and tau by as much;
    # the whole span over the steps is exact to that rounding over n samples
    span = float(time_s[-1] - time_s[0]) / (n - 1)
    if abs(period - span) > 1e-9 * span:
        period = span
    # 5 %: stamps in seconds since the epoch carry ~0.2 us of rounding (0.5 % of 50 us), while
    # a lost sample is a step of 200 %
    if not period > 0.0 or float(np.max(np.abs(dt - period))) > 0.05 * period:
        raise IdentificationError(
            f'run {_name(record)}: sample times are not uniform (median step {period:g} s, '
            f'steps from {float(dt.min()):g} to {float(dt.max()):g} s); identification needs '
            'a gap-free run')
    return period


def applied_voltage(record: RunRecord, chain: SignalChainParams) -> FloatArray:
    """
    Return the amplifier voltage the stage applied for the recorded commands.

    Parameters
    ----------
    record : RunRecord
        The run; ``command_v`` is what the controller asked for [V].
    chain : SignalChainParams
        DAC resolution and range, amplifier range, safe voltage (as the stage applies them).

    Returns
    -------
    ndarray
        Commands through the DAC (if ``chain.quantize``) and clamped to the amplifier range,
        non-finite commands replaced by the safe voltage, as :class:`Stage` does [V].

    """
    return amplifier_input(record.command_v, chain)


def _head(record: RunRecord, n: int) -> RunRecord:
    """Return the first ``n`` samples of a record (the record itself when it is not longer)."""
    if len(record) <= n:
        return record
    return RunRecord(record.time_s[:n], record.position_m[:n], record.reference_m[:n],
                     record.reference_velocity_mps[:n], record.command_v[:n],
                     {k: v[:n] for k, v in record.diagnostics.items()}, record.meta,
                     None if record.true_position_m is None else record.true_position_m[:n])


def _name(record: RunRecord) -> str:
    return str(record.meta.get('bag', record.meta.get('name', '<record>')))


def classify_run(record: RunRecord, chain: SignalChainParams | None = None) -> str:
    """
    Say what a run can be used for, from its meta or else from its input signal.

    Parameters
    ----------
    record : RunRecord
        The run. ``meta['identification_role']`` (one of :data:`ROLES`), when present, decides.
    chain : SignalChainParams, optional
        Signal chain used to compute the applied voltage; default the paper's.

    Returns
    -------
    str
        ``'step'`` when the input is piecewise constant with few jumps (at most 1 % of the
        samples), ``'hysteresis'`` when one frequency holds more than 90 % of the input's
        variance (a sine), else ``'frequency'`` (noise, chirp, closed-loop commands).

    Raises
    ------
    IdentificationError
        If the input never changes (no excitation).

    """
    role = record.meta.get('identification_role')
    if isinstance(role, str) and role in ROLES:
        return role
    v = applied_voltage(record, chain or SignalChainParams())
    if int(np.count_nonzero(np.diff(v))) == 0:
        raise IdentificationError(f'run {_name(record)}: the command never changes; '
                                  'there is no excitation to identify from')
    return classify_signal(v)


def classify_signal(v: FloatArray) -> str:
    """
    Say what a designed input signal is: a step train, a sine, or broadband.

    Parameters
    ----------
    v : ndarray
        The signal (an applied voltage, or the reference of a closed loop), not constant.

    Returns
    -------
    str
        ``'step'`` when it is piecewise constant with few jumps (at most 1 % of the samples),
        ``'hysteresis'`` when one frequency holds more than 90 % of its variance, else
        ``'frequency'``.

    """
    v = np.asarray(v, dtype=np.float64)
    jumps = int(np.count_nonzero(np.diff(v)))
    if jumps <= max(1, len(v) // 100):
        return 'step'
    power = np.abs(np.fft.rfft(v - v.mean())) ** 2
    power[0] = 0.0
    k = int(np.argmax(power))
    if float(power[max(k - 2, 0):k + 3].sum()) > 0.9 * float(power.sum()):
        return 'hysteresis'
    return 'frequency'


# --------------------------------------------------------------------------------------------
# Discrete-time model responses


def _discrete(p: ThirdOrderParams, sample_time_s: float) -> tuple[FloatArray, FloatArray,
                                                                    FloatArray]:
    d = third_order_plant(p).discretize(sample_time_s)
    return d.ad, d.bd[:, 0], d.c


def _delayed(p: ThirdOrderParams, sample_time_s: float, delay_samples: float
             ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, int]:
    """
    Return (Ad, B0, B1, C, n): the exact sampled plant behind a held input delayed d samples.

    With d = n + f (n whole, 0 <= f < 1) the input held over sample k is u[k - n - 1] for the
    first f T and u[k - n] for the rest, so x[k+1] = Ad x[k] + B0 u[k - n] + B1 u[k - n - 1],
    B0 = int_0^((1-f)T) e^(As) ds B, B1 = e^(A(1-f)T) int_0^(fT) e^(As) ds B (the modified
    z-transform). A fraction of a sample is thus modelled as what it is, not as e^(-j w f T),
    which the resonance near the Nyquist frequency would alias.
    """
    from scipy.linalg import expm
    plant = third_order_plant(p)
    a = np.asarray(plant.a, dtype=np.float64)
    b = np.asarray(plant.b, dtype=np.float64)[:, 0]
    c = np.asarray(plant.c, dtype=np.float64).reshape(-1)
    n = int(math.floor(delay_samples))
    frac = float(delay_samples - n)
    m = a.shape[0]
    # distinct poles (the usual case): e^(At) and its integral from the eigenvalues, far
    # cheaper than a matrix exponential per call inside the fits
    lam, vec = np.linalg.eig(a)
    well = np.linalg.cond(vec) < 1e8 and bool(np.all(np.abs(lam) > 0.0))
    vb = np.linalg.solve(vec, b.astype(np.complex128)) if well else None
    vinv = np.linalg.inv(vec) if well else None

    def phi_gamma(t: float) -> tuple[FloatArray, FloatArray]:
        if vb is not None and vinv is not None:
            e = np.exp(lam * t)
            phi = (vec * e[None, :]) @ vinv
            gamma = vec @ (vb * (e - 1.0) / lam)
            return np.asarray(phi.real, dtype=np.float64), np.asarray(gamma.real,
                                                                      dtype=np.float64)
        big = np.zeros((m + 1, m + 1))
        big[:m, :m] = a * t
        big[:m, m] = b * t
        ex = expm(big)
        return ex[:m, :m], ex[:m, m]

    ad, _ = phi_gamma(sample_time_s)
    p_rest, g_rest = phi_gamma((1.0 - frac) * sample_time_s)
    _, g_head = phi_gamma(frac * sample_time_s)
    return ad, g_rest, p_rest @ g_head, c, n


def discrete_frequency_response(p: ThirdOrderParams, sample_time_s: float,
                                frequency_hz: FloatArray, delay_samples: float = 0.0
                                ) -> ComplexArray:
    """
    Return the response of the ZOH-discretized plant, C (zI - Ad)^-1 Bd at z = exp(j w T).

    Parameters
    ----------
    p : ThirdOrderParams
        The plant.
    sample_time_s : float
        Sample and hold period T [s].
    frequency_hz : ndarray
        Frequencies [Hz], below the Nyquist frequency 1/(2T).
    delay_samples : float
        Loop delay beyond the hold [samples], whole or not (see :func:`_delayed`).

    Returns
    -------
    ndarray of complex
        Response from the held input (sample k) to the position sample (sample k) [m/V],
        comparable with an H1 estimate from recorded (command_v, position_m).

    """
    z = np.exp(2j * math.pi * np.asarray(frequency_hz, dtype=np.float64) * sample_time_s)
    if delay_samples == 0.0:
        ad, bd, c = _discrete(p, sample_time_s)
        mats = z[:, None, None] * np.eye(3)[None, :, :] - ad[None, :, :]
        x = np.linalg.solve(mats, np.broadcast_to(bd.astype(np.complex128),
                                                  (z.size, 3))[..., None])
        return np.asarray(x[..., 0] @ c, dtype=np.complex128)
    ad, b0, b1, c, n = _delayed(p, sample_time_s, delay_samples)
    mats = z[:, None, None] * np.eye(3)[None, :, :] - ad[None, :, :]
    rhs = b0[None, :] + b1[None, :] / z[:, None]
    x = np.linalg.solve(mats, rhs.astype(np.complex128)[..., None])
    return np.asarray((x[..., 0] @ c) * z ** (-n), dtype=np.complex128)


def _unit_filter(shape: LinearFactors, sample_time_s: float) -> tuple[FloatArray, FloatArray]:
    """Return (num, den) of the discretized plant with unit DC gain."""
    unit = LinearFactors(1.0, shape.omega_n_rad_s, shape.zeta, shape.tau_s)
    if shape.delay_samples == 0.0:
        ad, bd, c = _discrete(third_order_of(unit), sample_time_s)
        num, den = signal.ss2tf(ad, bd[:, None], c[None, :], np.zeros((1, 1)))
        num = np.asarray(num[0], dtype=np.float64)
        den = np.asarray(den, dtype=np.float64)
        return num / (num.sum() / den.sum()), den
    ad, b0, b1, c, n = _delayed(third_order_of(unit), sample_time_s, shape.delay_samples)
    n0, den = signal.ss2tf(ad, b0[:, None], c[None, :], np.zeros((1, 1)))
    n1, _ = signal.ss2tf(ad, b1[:, None], c[None, :], np.zeros((1, 1)))
    num = np.concatenate([np.zeros(n), np.asarray(n0[0], dtype=np.float64), [0.0]])
    num[n + 1:] += np.asarray(n1[0], dtype=np.float64)
    den = np.concatenate([np.asarray(den, dtype=np.float64), np.zeros(num.size - len(den))])
    return num / (num.sum() / den.sum()), den


def _filter_columns(num: FloatArray, den: FloatArray, inputs: FloatArray,
                    rest_level: bool = True) -> FloatArray:
    """
    Filter each row of ``inputs`` from rest at zero; add the free response from rest at 1.

    Returns an array (rows + 1, n) when ``rest_level``: the last row is the response of the
    plant left at rest at level 1 with zero input, the column of an unknown initial level.
    """
    out = signal.lfilter(num, den, inputs, axis=-1)
    if not rest_level:
        return np.asarray(out, dtype=np.float64)
    zi = signal.lfilter_zi(num, den)
    free, _ = signal.lfilter(num, den, np.zeros(inputs.shape[-1]), zi=zi)
    return np.asarray(np.vstack([out, free[None, :]]), dtype=np.float64)


def _covariance(jac: FloatArray, residual: FloatArray) -> FloatArray:
    """
    Return s^2 (J^T J)^-1, s^2 the residual variance per degree of freedom.

    The columns are normalized first: their scales differ by many orders of magnitude (metres
    per volt against metres per unit of alpha), and the pseudo-inverse of the unscaled J^T J
    would drop the small singular values, i.e. the largest variances.
    """
    m, p = jac.shape
    dof = max(m - p, 1)
    s2 = float(residual @ residual) / dof
    norms = np.linalg.norm(jac, axis=0)
    norms = np.where(norms > 0.0, norms, 1.0)
    js = jac / norms
    inv = np.linalg.pinv(js.T @ js) / np.outer(norms, norms)
    return np.asarray(s2 * inv, dtype=np.float64)


# --------------------------------------------------------------------------------------------
# Step 2: frequency response


@dataclass(frozen=True)
class FrequencyResponse:
    """
    An H1 estimate of the response from the applied voltage to the measured position.

    Attributes
    ----------
    frequency_hz : ndarray
        Frequencies [Hz] (0 Hz left out).
    response : ndarray of complex
        S_uy / S_uu [m/V].
    coherence : ndarray
        Magnitude-squared coherence, 0 ... 1.
    sample_time_s : float
        Sample period of the runs [s].
    segments : int
        Number of Welch segments averaged (over all runs).

    """

    frequency_hz: FloatArray
    response: ComplexArray
    coherence: FloatArray
    sample_time_s: float
    segments: int


def estimate_frequency_response(records: Sequence[RunRecord], chain: SignalChainParams, *,
                                segment_s: float = 0.05) -> FrequencyResponse:
    """
    Estimate the frequency response from one or more runs (Welch cross-spectra, H1).

    Parameters
    ----------
    records : sequence of RunRecord
        Runs with a broadband input (noise, chirp), all at the same sample rate.
    chain : SignalChainParams
        Signal chain giving the applied voltage from the commands.
    segment_s : float
        Welch segment length [s]; Hann window, half overlap, mean removed per segment.

    Returns
    -------
    FrequencyResponse
        Cross- and auto-spectra are summed over runs before the ratio.

    Raises
    ------
    IdentificationError
        No run, runs at different rates, or a run shorter than two segments.

    """
    if not records:
        raise IdentificationError('no frequency-response run (noise or chirp) given')
    period = sample_time_of(records[0])
    nper = max(int(round(segment_s / period)), 16)
    s_uy: ComplexArray | None = None
    s_uu: FloatArray | None = None
    s_yy: FloatArray | None = None
    freqs: FloatArray | None = None
    segments = 0
    for rec in records:
        t = sample_time_of(rec)
        if abs(t - period) > 1e-6 * period:
            raise IdentificationError(f'run {_name(rec)}: sample period {t:g} s differs from '
                                      f'{period:g} s of the other frequency-response runs')
        if len(rec) < 2 * nper:
            raise IdentificationError(
                f'run {_name(rec)}: {len(rec)} samples, need at least {2 * nper} (two Welch '
                f'segments of {segment_s:g} s) for a frequency response')
        u = applied_voltage(rec, chain)
        y = np.asarray(rec.position_m, dtype=np.float64)
        kw: dict[str, Any] = {'fs': 1.0 / period, 'window': 'hann', 'nperseg': nper,
                              'detrend': 'constant'}
        f, puy = signal.csd(u, y, **kw)
        _, puu = signal.welch(u, **kw)
        _, pyy = signal.welch(y, **kw)
        count = (len(rec) - nper) // (nper // 2) + 1
        segments += count
        s_uy = puy * count if s_uy is None else s_uy + puy * count
        s_uu = puu * count if s_uu is None else s_uu + puu * count
        s_yy = pyy * count if s_yy is None else s_yy + pyy * count
        freqs = f
    assert s_uy is not None and s_uu is not None and s_yy is not None and freqs is not None
    keep = (freqs > 0.0) & (s_uu > 0.0)
    response = s_uy[keep] / s_uu[keep]
    coherence = np.abs(s_uy[keep]) ** 2 / (s_uu[keep] * np.maximum(s_yy[keep], 1e-300))
    return FrequencyResponse(frequency_hz=np.asarray(freqs[keep], dtype=np.float64),
                             response=np.asarray(response, dtype=np.complex128),
                             coherence=np.asarray(np.clip(coherence, 0.0, 1.0),
                                                  dtype=np.float64),
                             sample_time_s=period, segments=segments)


@dataclass(frozen=True)
class FrequencyFit:
    """
    The discrete-time model fitted to a frequency response.

    Attributes
    ----------
    factors : LinearFactors
        Fitted k_p (small-signal gain), w_n, zeta, tau.
    std : LinearFactors
        One standard deviation of each (from the Jacobian at the optimum).
    data : FrequencyResponse
        The estimate that was fitted.
    used : ndarray of bool
        Frequencies of ``data`` that entered the fit.
    model : ndarray of complex
        Fitted model response at ``data.frequency_hz``.
    rms_log_error : float
        RMS of |log(model / data)| over the used frequencies.

    """

    factors: LinearFactors
    std: LinearFactors
    data: FrequencyResponse
    used: BoolArray
    model: ComplexArray
    rms_log_error: float


def _factors(x: FloatArray) -> LinearFactors:
    return LinearFactors(*(float(v) for v in np.exp(x)))


def _grid_starts(fu: FloatArray, hu: ComplexArray, weight: FloatArray,
                 sample_time_s: float, keep: int = 3) -> list[LinearFactors]:
    """
    Return the best ``keep`` points of a coarse grid over (w_n, zeta, tau).

    For each grid point the best gain is the weighted mean log-magnitude ratio, so the grid is
    three-dimensional. A local search from a single guess can lock onto the wrong side of the
    resonance when it sits near the Nyquist frequency, where its peak in the sampled response
    is flattened; the grid avoids it.
    """
    nyq = 0.5 / sample_time_s
    w2 = weight ** 2
    grid = np.array([(wn, zeta, tau)
                     for wn in 2.0 * math.pi * np.geomspace(50.0, 2.0 * nyq, 24)
                     for zeta in (0.03, 0.1, 0.3, 0.7)
                     for tau in (3e-5, 1e-4, 3e-4, 1e-3, 3e-3)])
    wn, zeta, tau = grid[:, 0], grid[:, 1], grid[:, 2]
    # The whole grid at once, by partial fractions: unit-DC-gain G(s) = sum r_i / (s - p_i)
    # with distinct poles discretizes under ZOH to sum r_i (e^(p_i T) - 1) / (p_i (z - e^(p_i T))),
    # exact, and without a matrix exponential per grid point.
    poles = np.stack([-1.0 / tau + 0j, wn * (-zeta + 1j * np.sqrt(1.0 - zeta ** 2)),
                      wn * (-zeta - 1j * np.sqrt(1.0 - zeta ** 2))], axis=1)
    gain = -np.prod(poles, axis=1)
    z = np.exp(2j * math.pi * fu * sample_time_s)
    resp = np.zeros((grid.shape[0], fu.size), dtype=np.complex128)
    for i in range(3):
        others = [j for j in range(3) if j != i]
        r = gain / ((poles[:, i] - poles[:, others[0]]) * (poles[:, i] - poles[:, others[1]]))
        e = np.exp(poles[:, i] * sample_time_s)
        resp += (r * (e - 1.0) / poles[:, i])[:, None] / (z[None, :] - e[:, None])
    r_all = np.log(resp / hu[None, :])
    shift = (r_all.real @ w2) / np.sum(w2)
    cost = ((r_all.real - shift[:, None]) ** 2 + r_all.imag ** 2) @ w2
    scored = [(float(cost[i]), LinearFactors(float(np.exp(-shift[i])), float(wn[i]),
                                             float(zeta[i]), float(tau[i])))
              for i in range(grid.shape[0])]
    scored.sort(key=lambda item: item[0])
    return [fac for _, fac in scored[:keep]]


def fit_frequency_response(data: FrequencyResponse, params: IdentificationParams,
                           initial: LinearFactors | None = None) -> FrequencyFit:
    """
    Fit k_p, w_n, zeta, tau of the ZOH-discretized plant to a frequency response.

    Parameters
    ----------
    data : FrequencyResponse
        H1 estimate from a noise or chirp run.
    params : IdentificationParams
        Band and coherence threshold.
    initial : LinearFactors, optional
        Start of the search; default: the three best points of a coarse grid over w_n, zeta
        and tau (each with its best gain), each refined, the best kept.

    Returns
    -------
    FrequencyFit

    Raises
    ------
    IdentificationError
        If fewer than 8 frequencies pass the band and coherence tests.

    Notes
    -----
    Residuals are log(G_model / H) (log magnitude and phase) weighted by
    sqrt(gamma^2 / (1 - gamma^2)), the inverse of the standard deviation of log H1 up to a
    constant; parameters are searched in log space (all positive).

    """
    f = data.frequency_hz
    nyq = 0.5 / data.sample_time_s
    used = (f >= params.band_low_hz) & (f <= params.band_high_fraction * nyq) & \
        (data.coherence >= params.coherence_min)
    if int(used.sum()) < 8:
        raise IdentificationError(
            f'frequency response: only {int(used.sum())} frequencies between '
            f'{params.band_low_hz:g} Hz and {params.band_high_fraction * nyq:g} Hz have '
            f'coherence >= {params.coherence_min:g}; need 8 (more excitation, longer run)')
    fu, hu = f[used], data.response[used]
    coh = np.minimum(data.coherence[used], 0.999)
    weight = np.sqrt(coh / (1.0 - coh))
    t = data.sample_time_s

    zu = np.exp(2j * math.pi * fu * t)

    def residual_at(delay: float) -> Callable[[FloatArray], FloatArray]:
        def residual(x: FloatArray) -> FloatArray:
            d = delay if x.size == 4 else float(x[4])
            try:
                with np.errstate(over='ignore', invalid='ignore'):
                    model = discrete_frequency_response(third_order_of(_factors(x[:4])), t, fu,
                                                        d)
            except (PiezoStageError, np.linalg.LinAlgError):
                model = np.full(fu.size, np.nan + 0j)
            if not np.all(np.isfinite(model)) or np.any(model == 0.0):
                # a search that left the physical range (a wrong delay tried): a large, finite
                # residual sends it back
                return np.full(2 * fu.size, 1e6)
            r = np.log(model / hu) * weight
            return np.asarray(np.concatenate([r.real, r.imag]), dtype=np.float64)
        return residual

    def fit_at(delay: float) -> Any:
        residual = residual_at(delay)
        # the grid searches the data with the delay's whole samples taken out
        starts = [initial] if initial is not None else _grid_starts(
            fu, hu * zu ** round(delay), weight, t)
        best: Any = None
        for start in starts:
            x0 = np.log([start.gain_m_per_v, start.omega_n_rad_s, start.zeta, start.tau_s])
            sol = optimize.least_squares(residual, x0, x_scale=1.0, method='lm')
            if best is None or sol.cost < best.cost:
                best = sol
        return best

    best, delay = choose_delay(fit_at, residual_at(0.0))
    cov = _covariance(best.jac, best.fun)
    fac = _factors(best.x[:4])
    shift = np.zeros(best.x.size)
    if best.x.size > 4:
        shift[:4] = whole_delay_shift(fit_at, best, delay)[:4]
    # log-space std = relative std
    rel = np.sqrt(np.maximum(np.diag(cov), 0.0) + shift ** 2)
    fac = LinearFactors(fac.gain_m_per_v, fac.omega_n_rad_s, fac.zeta, fac.tau_s, delay)
    std = LinearFactors(fac.gain_m_per_v * rel[0], fac.omega_n_rad_s * rel[1],
                        fac.zeta * rel[2], fac.tau_s * rel[3],
                        float(rel[4]) if rel.size > 4 else 0.0)
    model = discrete_frequency_response(third_order_of(fac), t, f, delay)
    err = np.log(model[used] / hu)
    return FrequencyFit(factors=fac, std=std, data=data, used=used, model=model,
                        rms_log_error=float(np.sqrt(np.mean(np.abs(err) ** 2))))


#: Whole samples of loop delay tried beyond the sample-and-hold.
DELAYS_TRIED = (0.0, 1.0, 2.0)


def choose_delay(fit_at: Callable[[float], Any], free_residual: Callable[[FloatArray], FloatArray]
                 ) -> tuple[Any, float]:
    """
    Return the fit and the loop delay [samples]: the best whole delay, or a fraction if shown.

    Parameters
    ----------
    fit_at : callable
        ``fit_at(delay)`` fits with the delay fixed and returns a ``least_squares`` result
        whose ``x`` does not hold the delay.
    free_residual : callable
        The residual of ``x`` with the delay appended as its last element.

    Returns
    -------
    solution, delay
        The solution (its ``x`` holds the delay last when the delay was fitted free) and the
        delay.

    Notes
    -----
    A delay of whole samples (a DAQ pipeline, a filter of the sensor module) is the common
    case: each of :data:`DELAYS_TRIED` is fitted and the best kept. The delay is then freed
    (0 to 4 samples) and a fraction kept only when its 95 % interval leaves out the whole
    delay, so a run without a delay keeps exactly the fit it had.

    """
    best: Any = None
    delay = 0.0
    for d in DELAYS_TRIED:
        sol = fit_at(d)
        if best is None or sol.cost < best.cost:
            best, delay = sol, d
    x0 = np.append(best.x, delay)
    lower = np.full(x0.size, -np.inf)
    upper = np.full(x0.size, np.inf)
    lower[-1], upper[-1] = 0.0, 4.0
    free = optimize.least_squares(free_residual, x0, bounds=(lower, upper), method='trf',
                                  x_scale='jac')
    cov = _covariance(free.jac, free.fun)
    sd = math.sqrt(max(float(cov[-1, -1]), 0.0))
    if free.cost < best.cost and abs(float(free.x[-1]) - delay) > 1.959964 * sd:
        return free, float(free.x[-1])
    return best, delay


def whole_delay_shift(fit_at: Callable[[float], Any], solution: Any, delay: float
                      ) -> FloatArray:
    """
    Return how far the parameters move when a fractional delay is replaced by the nearest whole.

    A fraction kept by :func:`choose_delay` may stand for something else with a phase that
    grows with frequency (the hysteresis, a filter); the move of the other parameters between
    the two delay models is a model-structure term of their bounds. Zeros for a whole delay.
    """
    n = solution.x.size - 1
    if delay == round(delay):
        return np.zeros(n)
    whole = fit_at(float(round(delay)))
    return np.asarray(np.abs(whole.x[:n] - solution.x[:n]), dtype=np.float64)


# --------------------------------------------------------------------------------------------
# Step 3: step response


@dataclass(frozen=True)
class StepFit:
    """
    The discrete-time model fitted to the step responses of step runs.

    Attributes
    ----------
    factors : LinearFactors
        w_n (fixed or fitted), zeta, tau; ``gain_m_per_v`` is the mean ratio of the fitted
        position jumps to the voltage jumps (the large-signal step gain, hysteresis included).
    std : LinearFactors
        One standard deviation of each (0 where fixed).
    records : list of RunRecord
        The runs.
    models : list of ndarray
        Fitted position per sample of each run [m].
    masks : list of ndarray of bool
        Samples that entered the fit (windows after each jump).
    residual_rms_m : float
        RMS of measured minus model over the fitted samples [m].
    jumps_v, jumps_m : ndarray
        Every voltage jump [V] and fitted position jump [m].

    """

    factors: LinearFactors
    std: LinearFactors
    records: list[RunRecord]
    models: list[FloatArray]
    masks: list[BoolArray]
    residual_rms_m: float
    jumps_v: FloatArray
    jumps_m: FloatArray


def fit_step_response(records: Sequence[RunRecord], chain: SignalChainParams,
                      params: IdentificationParams, initial: LinearFactors,
                      fix_omega: bool | None = None) -> StepFit:
    """
    Fit zeta and tau (and w_n unless fixed) to the responses to the input jumps of step runs.

    Parameters
    ----------
    records : sequence of RunRecord
        Runs whose applied voltage is piecewise constant (one or more jumps).
    chain : SignalChainParams
        Signal chain giving the applied voltage.
    params : IdentificationParams
        ``step_window_s``: samples up to this long after each jump are fitted;
        ``step_max_jumps``: a run with more jumps is cut after that many.
    initial : LinearFactors
        w_n (kept when fixed) and the start of zeta and tau.
    fix_omega : bool, optional
        Keep w_n at ``initial``; default ``params.step_fixes_omega``.

    Returns
    -------
    StepFit

    Raises
    ------
    IdentificationError
        If a run has no jump.

    Notes
    -----
    The input of the linear plant is piecewise constant with one unknown level per plateau
    (the hysteresis output after each jump) and an unknown level before the run (the plant at
    rest there); the position is linear in these levels, which are solved by linear least
    squares inside every evaluation (variable projection). The standard deviations come from
    the Jacobian of these projected residuals.

    """
    fix = params.step_fixes_omega if fix_omega is None else fix_omega
    prepared = []
    for rec in records:
        t = sample_time_of(rec)
        v = applied_voltage(rec, chain)
        edges = np.flatnonzero(np.diff(v)) + 1
        if edges.size == 0:
            raise IdentificationError(f'run {_name(rec)}: no input jump; not a step run')
        if edges.size > params.step_max_jumps:
            # one linear level per plateau: bound the size of the least-squares problem
            last = params.step_max_jumps - 1
            rec = _head(rec, min(int(edges[last]) + max(int(round(params.step_window_s / t)), 4),
                                 int(edges[last + 1])))
            v = v[:len(rec)]
            edges = edges[edges < len(rec)]
        starts = np.concatenate([[0], edges])
        ends = np.concatenate([edges, [v.size]])
        ind = np.zeros((starts.size, v.size))
        for j, (a, b) in enumerate(zip(starts, ends)):
            ind[j, a:b] = 1.0
        win = max(int(round(params.step_window_s / t)), 4)
        mask = np.zeros(v.size, dtype=bool)
        for e in edges:
            mask[max(e - 2, 0):e + win] = True
        y = np.asarray(rec.position_m, dtype=np.float64)
        prepared.append((rec, t, v, ind, mask, y, starts))

    def columns(fac: LinearFactors, t: float, ind: FloatArray) -> FloatArray:
        num, den = _unit_filter(fac, t)
        return _filter_columns(num, den, ind)

    def unpack(x: FloatArray) -> LinearFactors:
        if fix:
            return LinearFactors(1.0, initial.omega_n_rad_s, float(np.exp(x[0])),
                                 float(np.exp(x[1])), initial.delay_samples)
        w, z, tau = (float(v) for v in np.exp(x))
        return LinearFactors(1.0, w, z, tau, initial.delay_samples)

    def solve(x: FloatArray) -> tuple[FloatArray, list[FloatArray], list[FloatArray]]:
        fac = unpack(x)
        res, models, levels = [], [], []
        for _, t, _, ind, mask, y, _ in prepared:
            cols = columns(fac, t, ind)
            coef, *_ = np.linalg.lstsq(cols[:, mask].T, y[mask], rcond=None)
            model = coef @ cols
            res.append((y - model)[mask])
            models.append(model)
            levels.append(np.asarray(coef, dtype=np.float64))
        return np.concatenate(res), models, levels

    x0 = [initial.zeta, initial.tau_s] if fix else [initial.omega_n_rad_s, initial.zeta,
                                                    initial.tau_s]
    # residuals in nanometres: in metres the optimizer's absolute tolerances stop it at once
    sol = optimize.least_squares(lambda x: solve(x)[0] * _NM, np.log(x0), method='lm')
    res, models, levels = solve(sol.x)
    cov = _covariance(sol.jac, sol.fun)
    rel = np.sqrt(np.maximum(np.diag(cov), 0.0))
    fac = unpack(sol.x)
    jumps_v, jumps_m = [], []
    for (_, _, v, _, _, _, starts), coef in zip(prepared, levels):
        jumps_v.append(np.diff(v[starts]))
        jumps_m.append(np.diff(coef[:-1]))
    jv, jm = np.concatenate(jumps_v), np.concatenate(jumps_m)
    gain = float(np.sum(jm * jv) / np.sum(jv * jv))
    if fix:
        std = LinearFactors(0.0, 0.0, fac.zeta * rel[0], fac.tau_s * rel[1])
    else:
        std = LinearFactors(0.0, fac.omega_n_rad_s * rel[0], fac.zeta * rel[1],
                            fac.tau_s * rel[2])
    return StepFit(factors=LinearFactors(gain, fac.omega_n_rad_s, fac.zeta, fac.tau_s,
                                         fac.delay_samples),
                   std=std, records=[p[0] for p in prepared], models=models,
                   masks=[p[4] for p in prepared],
                   residual_rms_m=float(np.sqrt(np.mean(res ** 2))), jumps_v=jv, jumps_m=jm)


# --------------------------------------------------------------------------------------------
# Step 4: hysteresis


@dataclass(frozen=True)
class HysteresisFit:
    """
    A hysteresis model fitted to sine runs with the linear shape fixed.

    Attributes
    ----------
    model : str
        ``'backlash_like'``, ``'bouc_wen'`` or ``'prandtl_ishlinskii'``.
    params : HysteresisParams
        The fitted group (slope set by the convention), other groups as given.
    static_gain_m_per_v : float
        k_p times the hysteresis slope: the identifiable slope of x against v [m/V].
    linear_gain_m_per_v : float
        k_p = static gain / slope under the convention [m/V].
    estimates : dict of str to float
        Fitted values by name (gauge-free ones: ``static_gain_m_per_v``, ``alpha``,
        ``b1_over_c``, ...).
    std : dict of str to float
        One standard deviation of each estimate.
    records : list of RunRecord
        The runs.
    voltages : list of ndarray
        Applied voltage of each run [V].
    models : list of ndarray
        Fitted position of each run [m].
    residual_rms_m : float
        RMS of measured minus model [m].

    """

    model: str
    params: HysteresisParams
    static_gain_m_per_v: float
    linear_gain_m_per_v: float
    estimates: dict[str, float]
    std: dict[str, float]
    records: list[RunRecord]
    voltages: list[FloatArray]
    models: list[FloatArray]
    residual_rms_m: float


def _run_model(step: Callable[[Any, float], tuple[Any, Any]], state: Any,
               v: FloatArray) -> FloatArray:
    """Step a hysteresis model through ``v`` (one pass) and return its outputs."""
    out = np.empty(v.size)
    for k, vk in enumerate(v.tolist()):
        state, w = step(state, vk)
        out[k] = w
    return out


def fit_hysteresis(records: Sequence[RunRecord], chain: SignalChainParams,
                   params: IdentificationParams, shape: LinearFactors,
                   base: HysteresisParams | None = None, *,
                   start: Mapping[str, float] | None = None) -> HysteresisFit:
    """
    Fit the hysteresis model and the static gain to sine runs, the linear shape fixed.

    Parameters
    ----------
    records : sequence of RunRecord
        Runs with a periodic input (the paper: 1 + sin(2 pi 100 t) V).
    chain : SignalChainParams
        Signal chain giving the applied voltage.
    params : IdentificationParams
        Model choice, the slope convention and ``hysteresis_max_s`` (each run is cut to it).
    shape : LinearFactors
        w_n, zeta, tau of the linear part (its gain is not used).
    base : HysteresisParams, optional
        Groups not fitted are copied from it; Prandtl-Ishlinskii thresholds come from it.
    start : Mapping, optional
        Start of the search by name (``estimates`` of an earlier fit); default a generic one.

    Returns
    -------
    HysteresisFit

    Notes
    -----
    The model of a run is y = G0 F[u + d](k) + b r(k), with F the unit-gain discretized plant,
    u + d the normalized hysteresis output (slope 1), G0 the static gain and r the free response
    of the plant from rest (b: the unknown level before the run). G0 and b are solved linearly
    in each evaluation; the shape parameters of the hysteresis and its initial state are
    searched by ``scipy.optimize.least_squares`` (bounded, trust region). For
    Prandtl-Ishlinskii with fixed thresholds the whole fit is linear (non-negative least
    squares on the play operator outputs).

    """
    base = base or HysteresisParams()
    if not records:
        raise IdentificationError('no hysteresis run (a sine of the input) given')
    runs = []
    for rec in records:
        t = sample_time_of(rec)
        # one pass of the exact hysteresis stepping per evaluation: bound its length, but
        # keep two cycles of the input's main line: the first from rest leaves the initial
        # state, the sensor offset and the curvature of the loop partly confounded
        rec = _head(rec, max(int(round(params.hysteresis_max_s / t)), 16,
                             _two_cycles(applied_voltage(rec, chain))))
        num, den = _unit_filter(shape, t)
        v = applied_voltage(rec, chain)
        y = np.asarray(rec.position_m, dtype=np.float64)
        free = _filter_columns(num, den, np.zeros((0, v.size)))[-1]
        runs.append((rec, num, den, v, y, free))
    slope = params.hysteresis_slope
    if params.hysteresis_model == 'prandtl_ishlinskii':
        return _fit_pi(runs, slope, base)
    model = params.hysteresis_model
    names: tuple[str, ...]
    if model == 'backlash_like':
        names = ('alpha', 'b1_over_c', 'e0_fraction')
        x0 = np.array([0.4, 0.9, 0.0])
        lower, upper = np.array([1e-3, 0.0, -1.0]), np.array([50.0, 0.999, 1.0])

        def normalized(x: FloatArray, v: FloatArray) -> FloatArray:
            hp = BacklashLikeParams(alpha=float(x[0]), c=1.0, b1=float(x[1]))
            h = BacklashLike(hp)
            return _run_model(h.step, h.rest_state(float(v[0]), float(x[2]) * h.bound), v)
    else:
        names = ('a', 'beta', 'gamma_fraction', 'h0_fraction')
        x0 = np.array([0.1, 0.3, 0.5, 0.0])
        lower, upper = np.array([1e-4, 1e-3, -0.999, -1.0]), np.array([10.0, 50.0, 1.0, 1.0])

        def normalized(x: FloatArray, v: FloatArray) -> FloatArray:
            # min(): beta * 1.0 may round above beta, which the model refuses
            hp = BoucWenParams(d_p=1.0, a=float(x[0]), beta=float(x[1]),
                               gamma=min(float(x[1] * x[2]), float(x[1])))
            h = BoucWen(hp)
            _, h0 = h.rest_state(float(v[0]))
            return _run_model(h.step, (float(v[0]), float(x[3]) * h.bound + h0), v)

    def solve(x: FloatArray, offset: bool = True
              ) -> tuple[FloatArray, list[FloatArray], list[FloatArray]]:
        res, models, coefs = [], [], []
        for _, num, den, v, y, free in runs:
            w = normalized(x, v)
            # F[w] from rest at 0, the free response of the unknown level before the run, and
            # a constant: the sensor's zero need not be the stage's rest at 0 V
            cols = np.vstack([signal.lfilter(num, den, w), free,
                              np.ones(v.size) if offset else np.zeros(v.size)])
            coef, *_ = np.linalg.lstsq(cols.T, y, rcond=None)
            model_y = coef @ cols
            res.append(y - model_y)
            models.append(model_y)
            coefs.append(coef)
        return np.concatenate(res), models, coefs

    if start is not None:
        x0 = np.clip(np.array([float(start.get(n, v)) for n, v in zip(names, x0)]), lower,
                     upper)
    nx = x0.size
    # The offset is tested, not assumed: a sine around a level gives the static gain from the
    # level (the volts and the metres at rest) unless an offset is free, when the gain must
    # come from the swing, which the curvature of the loop shares; so it is kept only where
    # the data show it (likelihood ratio at 95 %, one offset per run: _offsets_shown).
    sol = optimize.least_squares(lambda x: solve(x, False)[0] * _NM, x0,
                                 bounds=(lower, upper), x_scale='jac', method='trf')
    sol_off = optimize.least_squares(lambda x: solve(x)[0] * _NM, sol.x,
                                     bounds=(lower, upper), x_scale='jac', method='trf')
    rss0, rss1 = 2.0 * float(sol.cost), 2.0 * float(sol_off.cost)
    dof = max(int(sol_off.fun.size) - nx - 3 * len(runs), 1)
    with_offset = _offsets_shown(rss0, rss1, dof, len(runs))
    if with_offset:
        sol = sol_off
    res, models, coefs = solve(sol.x, with_offset)
    # Covariance of every parameter, the linear ones included: Jacobian of the full residual.
    g0s = [float(c[0]) for c in coefs]
    g0 = float(np.mean(g0s))
    offsets = np.array([float(c[2]) for c in coefs])

    def full(xf: FloatArray) -> FloatArray:
        out = []
        for i, ((_, num, den, v, y, free), coef) in enumerate(zip(runs, coefs)):
            w = normalized(xf[:nx], v)
            model_y = xf[nx] * signal.lfilter(num, den, w) + coef[1] * free
            if xf.size > nx + 1:
                model_y = model_y + xf[nx + 1 + i]
            out.append(y - model_y)
        return np.concatenate(out)

    steps = np.concatenate([np.maximum(np.abs(sol.x), 1e-3) * 1e-6, [abs(g0) * 1e-6]])
    x_full = np.concatenate([sol.x, [g0]])
    # the offset's standard deviation always (how large an offset could hide when not kept)
    x_off = np.concatenate([x_full, offsets])
    cov_off = _covariance(_numeric_jacobian(full, x_off, np.concatenate([
        steps, np.full(offsets.size, 1e-9)])), full(x_off))
    cov = cov_off if with_offset else _covariance(_numeric_jacobian(full, x_full, steps),
                                                  full(x_full))
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    est = {n: float(v) for n, v in zip(names, sol.x)}
    std = {n: float(s) for n, s in zip(names, sd[:nx])}
    est['static_gain_m_per_v'] = g0
    std['static_gain_m_per_v'] = float(sd[nx])
    # the sensor offset of the first run (0 when the data do not show one)
    est['sensor_offset_m'] = float(offsets[0])
    std['sensor_offset_m'] = float(np.sqrt(max(float(cov_off[nx + 1, nx + 1]), 0.0)))
    if model == 'backlash_like':
        group = BacklashLikeParams(alpha=est['alpha'], c=slope, b1=est['b1_over_c'] * slope)
        hyst = base.replace(model=model, backlash_like=group)
    else:
        group_bw = BoucWenParams(d_p=slope, a=est['a'], beta=est['beta'],
                                 gamma=min(est['beta'] * est['gamma_fraction'], est['beta']))
        hyst = base.replace(model=model, bouc_wen=group_bw)
    return HysteresisFit(model=model, params=hyst, static_gain_m_per_v=g0,
                         linear_gain_m_per_v=g0 / slope, estimates=est, std=std,
                         records=[r[0] for r in runs], voltages=[r[3] for r in runs],
                         models=models, residual_rms_m=float(np.sqrt(np.mean(res ** 2))))


def _offsets_shown(rss_without: float, rss_with: float, dof: int, offsets: int) -> bool:
    """
    Return whether the data show sensor offsets: a likelihood-ratio test at 95 %.

    ``offsets`` constants (one per run) freed in a least-squares fit whose noise is white with
    the variance rss_with / dof: without offsets in the data, the drop of the residual sum of
    squares over that variance is chi^2 with ``offsets`` degrees of freedom (one per constant
    freed, not one for all).
    """
    from scipy.stats import chi2
    if not rss_with > 0.0:
        return False
    return (rss_without - rss_with) / (rss_with / dof) > float(chi2.ppf(0.95, offsets))


def _two_cycles(v: FloatArray) -> int:
    """Return the samples of two cycles of the strongest line of ``v`` (0 for none)."""
    power = np.abs(np.fft.rfft(v - float(np.mean(v)))) ** 2
    if power.size < 2:
        return 0
    power[0] = 0.0
    k = int(np.argmax(power))
    return int(math.ceil(2.0 * v.size / k)) if k > 0 else 0


def _numeric_jacobian(fun: Callable[[FloatArray], FloatArray], x: FloatArray,
                      steps: FloatArray) -> FloatArray:
    """Return the central-difference Jacobian of ``fun`` at ``x``."""
    cols = []
    for i, h in enumerate(steps):
        dx = np.zeros_like(x)
        dx[i] = h
        cols.append((fun(x + dx) - fun(x - dx)) / (2.0 * h))
    return np.asarray(np.stack(cols, axis=1), dtype=np.float64)


def _fit_pi(runs: list[Any], slope: float, base: HysteresisParams) -> HysteresisFit:
    """Prandtl-Ishlinskii: non-negative linear least squares on the play operator outputs."""
    thresholds = base.prandtl_ishlinskii.thresholds_v
    n_op = len(thresholds)
    blocks, ys, cols_all = [], [], []
    for idx, (_, num, den, v, y, free) in enumerate(runs):
        model = PrandtlIshlinskii(PrandtlIshlinskiiParams(
            p0=1.0, thresholds_v=thresholds, weights=(0.0,) * n_op))
        state = model.rest_state(float(v[0]))
        plays = np.empty((n_op, v.size))
        for k, vk in enumerate(v.tolist()):
            state, _ = model.step(state, vk)
            plays[:, k] = state[1]
        inputs = np.vstack([v[None, :], plays])
        filt = signal.lfilter(num, den, inputs, axis=-1)
        # the free response column (unknown level before the run) may take either sign; no
        # sensor offset here: a play whose threshold the run never reaches holds its initial
        # output, a constant column, so an offset would be confounded with its weight (and
        # the static gain, their sum, left undetermined)
        extra = np.zeros((2 * len(runs), v.size))
        extra[2 * idx] = free
        extra[2 * idx + 1] = -free
        cols_all.append(np.vstack([filt, extra]))
        ys.append(y)
        blocks.append(v)
    a = np.hstack(cols_all).T
    y_all = np.concatenate(ys)
    scale = np.maximum(np.abs(a).max(axis=0), 1e-30)
    coef, _ = optimize.nnls(a / scale, y_all)
    coef = coef / scale
    model_all = a @ coef
    res = y_all - model_all
    q = coef[:n_op + 1]
    g0 = float(q.sum())
    gain = g0 / slope
    cov = _covariance(a[:, :n_op + 1], res)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    pi = PrandtlIshlinskiiParams(p0=float(q[0] / gain), thresholds_v=thresholds,
                                 weights=tuple(float(w / gain) for w in q[1:]))
    est = {'p0_over_slope': float(q[0] / g0), 'static_gain_m_per_v': g0}
    std = {'p0_over_slope': float(sd[0] / g0), 'static_gain_m_per_v': float(np.sqrt(cov.sum()))}
    for i, (w, s) in enumerate(zip(q[1:], sd[1:])):
        est[f'weight_{i}_over_slope'] = float(w / g0)
        std[f'weight_{i}_over_slope'] = float(s / g0)
    models, start = [], 0
    for y in ys:
        models.append(model_all[start:start + y.size])
        start += y.size
    return HysteresisFit(model='prandtl_ishlinskii',
                         params=base.replace(model='prandtl_ishlinskii', prandtl_ishlinskii=pi),
                         static_gain_m_per_v=g0, linear_gain_m_per_v=gain, estimates=est,
                         std=std, records=[r[0] for r in runs], voltages=blocks, models=models,
                         residual_rms_m=float(np.sqrt(np.mean(res ** 2))))


# --------------------------------------------------------------------------------------------
# The whole procedure


@dataclass
class IdentificationResult:
    """
    Everything the procedure found, and the stage parameters it gives.

    Attributes
    ----------
    factors : LinearFactors
        Final k_p (under the slope convention), w_n, zeta, tau.
    third_order : ThirdOrderParams
        K, a0, a1, a2 of eq. (17).
    stage : StageParams
        The base stage with the identified plant (third-order model, reduced model (25) from
        it), hysteresis and sensor noise.
    static_gain_m_per_v : float
        Identifiable slope of x against v_in far from a reversal (k_p times the slope) [m/V].
    frequency : FrequencyFit or None
    step : StepFit or None
    hysteresis : HysteresisFit or None
    roles : dict of str to list of str
        Which run was used for what.
    notes : list of str
        What was assumed where a run was missing, and other caveats.
    bounds : dict of str to (float, float)
        Confidence bounds of the parameters that carry them (filled by
        :func:`piezo_stage_ros.core.identification.support.identify_checked`).
    loop : str
        ``'open'``, or ``'closed'`` when the frequency response came from closed-loop data.

    """

    factors: LinearFactors
    third_order: ThirdOrderParams
    stage: StageParams
    static_gain_m_per_v: float
    frequency: FrequencyFit | None
    step: StepFit | None
    hysteresis: HysteresisFit | None
    roles: dict[str, list[str]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)
    loop: str = 'open'

    def summary(self) -> dict[str, float]:
        """Return the headline numbers by name (SI units)."""
        out = {
            'static_gain_m_per_v': self.static_gain_m_per_v,
            'gain_m_per_v': self.factors.gain_m_per_v,
            'omega_n_rad_s': self.factors.omega_n_rad_s,
            'zeta': self.factors.zeta,
            'tau_s': self.factors.tau_s,
            'K': self.third_order.gain, 'a0': self.third_order.a0, 'a1': self.third_order.a1,
            'a2': self.third_order.a2,
        }
        h = self.stage.hysteresis
        if h.model == 'backlash_like':
            out.update(alpha=h.backlash_like.alpha, c=h.backlash_like.c, b1=h.backlash_like.b1)
        return out


def identify(records: Sequence[RunRecord], base: StageParams | None = None,
             params: IdentificationParams | None = None,
             roles: Sequence[str | None] | None = None, *,
             frequency_fit: FrequencyFit | None = None) -> IdentificationResult:
    """
    Run the procedure of section III-D on recorded runs and return the identified stage.

    Parameters
    ----------
    records : sequence of RunRecord
        Runs of the stage; each is used for what :func:`classify_run` (or ``roles``) says.
    base : StageParams, optional
        Signal chain of the recordings (DAC, amplifier range) and the values of everything not
        identified (electromechanical group, initial position); default the paper's stage.
    params : IdentificationParams, optional
        Settings; default :class:`IdentificationParams`.
    roles : sequence of str or None, optional
        One per record, one of :data:`ROLES` or None (classify).
    frequency_fit : FrequencyFit, optional
        A frequency-response fit made elsewhere (closed-loop data averaged over periods);
        used in place of the estimate from runs of role ``'frequency'``.

    Returns
    -------
    IdentificationResult

    Raises
    ------
    IdentificationError
        If there is neither a frequency nor a step run, or a fit fails.

    """
    base = base or StageParams()
    params = params or IdentificationParams()
    chain = base.chain
    by_role: dict[str, list[RunRecord]] = {r: [] for r in ROLES}
    names: dict[str, list[str]] = {r: [] for r in ROLES}
    for i, rec in enumerate(records):
        role = roles[i] if roles is not None and i < len(roles) else None
        if role is None:
            role = classify_run(rec, chain)
        elif role not in ROLES:
            raise ParameterError('role', role, 'one of ' + ', '.join(repr(r) for r in ROLES))
        by_role[role].append(rec)
        names[role].append(_name(rec))
    notes: list[str] = []
    if not by_role['frequency'] and not by_role['step'] and frequency_fit is None:
        raise IdentificationError('need a noise (or chirp) run or a step run for the linear '
                                  'part; got ' + (', '.join(
                                      f'{len(v)} {k}' for k, v in by_role.items()) or 'none'))
    prior = factors_of(base.plant.third_order)
    freq_fit = frequency_fit
    if freq_fit is not None:
        shape = freq_fit.factors
    elif by_role['frequency']:
        data = estimate_frequency_response(by_role['frequency'], chain,
                                           segment_s=params.segment_s)
        freq_fit = fit_frequency_response(data, params)
        shape = freq_fit.factors
    else:
        notes.append('no noise/chirp run: w_n fitted on the step run, from the base model')
        shape = prior
    step_fit = None
    if by_role['step']:
        step_fit = fit_step_response(by_role['step'], chain, params, shape,
                                     fix_omega=params.step_fixes_omega and freq_fit is not None)
        shape = step_fit.factors
    else:
        notes.append('no step run: zeta and tau from the frequency response fit')
    hyst_fit = None
    if by_role['hysteresis']:
        hyst_fit = fit_hysteresis(by_role['hysteresis'], chain, params, shape, base.hysteresis)
        static = hyst_fit.static_gain_m_per_v
        hyst = hyst_fit.params
        gain = hyst_fit.linear_gain_m_per_v
    else:
        hyst = base.hysteresis
        slope = _slope(hyst)
        if freq_fit is not None:
            static = freq_fit.factors.gain_m_per_v * slope
            notes.append('no sine run: hysteresis kept from the base configuration, static '
                         'gain from the small-signal k_p of the frequency response (biased by '
                         'the hysteresis, see docs/explanation/model.md)')
        else:
            assert step_fit is not None
            static = step_fit.factors.gain_m_per_v
            notes.append('no sine run: hysteresis kept from the base configuration, static '
                         'gain from the step heights')
        gain = static / slope
    factors = LinearFactors(gain, shape.omega_n_rad_s, shape.zeta, shape.tau_s,
                            shape.delay_samples)
    if shape.delay_samples != 0.0:
        notes.append(f'loop delay: {shape.delay_samples:.3g} samples between a command and the '
                     'sample it is held over, beyond the sample-and-hold (fitted with the '
                     'model; a signal-chain delay, not part of the stage)')
    third = third_order_of(factors)
    plant = base.plant.replace(model='third_order', third_order=third, reduced=third.reduced())
    noise = _noise_estimate(step_fit, chain, notes)
    stage = base.replace(plant=plant, hysteresis=hyst,
                         chain=chain if noise is None else chain.replace(
                             sensor_noise_std_m=noise))
    return IdentificationResult(factors=factors, third_order=third, stage=stage,
                                static_gain_m_per_v=static, frequency=freq_fit, step=step_fit,
                                hysteresis=hyst_fit, roles=names, notes=notes)


def _slope(h: HysteresisParams) -> float:
    if h.model == 'backlash_like':
        return h.backlash_like.c
    if h.model == 'bouc_wen':
        return h.bouc_wen.d_p
    if h.model == 'prandtl_ishlinskii':
        p = h.prandtl_ishlinskii
        return p.p0 + sum(p.weights)
    return 1.0


#: Largest lag-1 correlation of a fit's residual still taken as sensor noise: white noise
#: has none, a model error (a wrong delay, a missing mode) is smooth and near 1.
WHITE_LAG1_MAX = 0.5


def residual_whiteness(residual: FloatArray) -> float:
    """Return the lag-1 correlation coefficient of a residual (0 for white noise)."""
    r = np.asarray(residual, dtype=np.float64) - float(np.mean(residual))
    den = float(r @ r)
    return float(r[1:] @ r[:-1]) / den if den > 0.0 else 0.0


def _noise_estimate(step_fit: StepFit | None, chain: SignalChainParams,
                    notes: list[str] | None = None) -> float | None:
    """
    Return the sensor noise [m rms] the step residual shows, quantization removed.

    None when there is no step fit, or when its residual is not white: then it is model error,
    not the sensor's noise, and is reported in ``notes`` instead of being stored.
    """
    if step_fit is None:
        return None
    res = np.concatenate([(np.asarray(r.position_m, dtype=np.float64) - m)[k]
                          for r, m, k in zip(step_fit.records, step_fit.models,
                                             step_fit.masks)])
    lag1 = residual_whiteness(res)
    if lag1 > WHITE_LAG1_MAX:
        if notes is not None:
            notes.append(f'the step fit leaves {step_fit.residual_rms_m * 1e9:.3g} nm rms that '
                         f'is not white (lag-1 correlation {lag1:.2f}): model error, not the '
                         'sensor noise; the configured sensor noise is kept')
        return None
    lsb = chain.adc_lsb_m if chain.quantize else 0.0
    var = step_fit.residual_rms_m ** 2 - lsb * lsb / 12.0
    return float(math.sqrt(var)) if var > 0.0 else 0.0
