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
What recorded data can support, closed-loop identification on purpose, and refusals.

:func:`identify_checked` wraps :func:`piezo_stage_ros.core.identification.fit.identify`:

1. **Loop and role.** Each run's role comes from what it holds (:func:`content_role`): the
   reference when it changes (a closed loop's command is not a designed input), else the
   command; a step train, a sine (hysteresis), or broadband / a periodic multisine
   (frequency), whatever the order of the runs. The loop verdict (:func:`loop_kind`: open
   when the command is a fixed function of the reference or its innovations do not follow
   the position's) is reported, never needed: in closed loop the sensor noise enters the
   command and the H1 estimate S_uy / S_uu is biased toward -1/C, so whenever the reference
   repeats the estimate averaged over whole periods is used, open loop or closed.
2. **Excitation per line** (:func:`analyse_run`). The excitation is the reference (closed
   loop), or the reference / command (open loop). When it repeats over at least two whole
   periods, the DFT of every period gives the lines the excitation drives and, from the scatter
   over the periods, the signal-to-noise ratio of the applied input and of the position on
   each line (:mod:`piezo_stage_ros.core.identification.periodic`); otherwise Welch spectra give
   the excited bins and the coherence gives the signal-to-noise ratio (open loop only). The
   fraction of commands outside the amplifier range (saturation) is counted.
3. **Support rules** (:func:`refusals`). For each parameter the procedure would take from a
   run: w_n and zeta need good lines across the resonance region of the configured model,
   tau across the corner 1/(2 pi tau), the small-signal gain below the resonance; the step fit
   needs plateaus after the jumps; alpha needs an input range of about 1/alpha and a whole
   cycle; a saturated run supports nothing; ``closed_loop=True`` on an open-loop run is
   refused. A refused parameter gives one line naming it and the reason
   (:class:`RefusedError`); nothing is fitted.
4. **Periodic reference: the instrument** (:func:`fit_periodic_response`). The frequency
   response from the applied input to the position averaged over whole periods of the
   periodic reference (indirect in spirit: only what repeats with the reference is kept, so
   the feedback's share of the input does not matter), with a variance per line, fitted by
   weighted least squares with a frequency-independent complex factor for the hysteresis
   (its describing function) and the loop's delay (whole samples tried, a fraction kept when
   shown). The hysteresis is fitted in the time domain on the applied input, which stays
   consistent in closed loop (the position noise at sample k is independent of the inputs
   before k), with a sensor offset where the data show one.
5. **Bounds.** Every parameter gets 95 % bounds, +-1.96 sigma from the Jacobian of its fit
   (the frequency fit's covariance scaled up by chi^2/dof when the residuals exceed the
   variance per line), plus model-structure terms: the largest move of each parameter under
   two other describing functions of the hysteresis; the bias the hysteresis leaves in the
   linear fit at the run's own amplitude, found by replaying the identified model on the
   applied input (taken off, half kept in the bound); the tau the hysteresis fit holds fixed;
   and for the hysteresis, the spread of refits on its own answer with fresh noise where it
   exceeds the Jacobian's.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import math
from typing import Any, Mapping, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.errors import IdentificationError, PiezoStageError
from piezo_stage_ros.core.contracts.params import param, Params
from piezo_stage_ros.core.contracts.types import BoolArray, ComplexArray, FloatArray
from piezo_stage_ros.core.identification.fit import (
    _unit_filter,
    applied_voltage,
    choose_delay,
    classify_run,
    classify_signal,
    discrete_frequency_response,
    fit_hysteresis,
    fit_step_response,
    FrequencyFit,
    FrequencyResponse,
    IdentificationParams,
    IdentificationResult,
    identify,
    ROLES,
    sample_time_of,
    whole_delay_shift,
)
from piezo_stage_ros.core.identification.periodic import (
    detect_period,
    excited_lines,
    periodic_spectra,
    PeriodicSpectra,
)
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.linear import factors_of, LinearFactors, third_order_of
from piezo_stage_ros.core.model.stage import SignalChainParams, StageParams
from scipy import optimize, signal

__all__ = ['CheckedIdentification', 'LineAnalysis', 'RefusedError', 'RunSupport', 'SupportParams',
           'analyse_run', 'content_role', 'fit_periodic_response', 'identify_checked',
           'loop_kind', 'refusals']

#: 95 % two-sided normal quantile: the bounds are +- this many standard deviations.
Z95 = 1.959964


class RefusedError(IdentificationError):
    """The data cannot support one or more parameters; ``lines`` has one reason each."""

    def __init__(self, lines: Sequence[str]) -> None:
        self.lines = list(lines)
        super().__init__('; '.join(self.lines))


@dataclass(frozen=True)
class SupportParams(Params):
    """Thresholds of what a run must show to support a parameter."""

    snr_min: float = param(4.0, unit='-', description='Power signal-to-noise ratio a line '
                           'needs to count (4: the coherence 0.8 of the frequency fit).',
                           low=0.0, low_open=True)
    saturation_max: float = param(0.01, unit='-', description='Largest fraction of commands '
                                  'outside the amplifier range.', low=0.0, high=1.0)
    resonance_lines_min: int = param(8, unit='-', description='Good lines the resonance region '
                                     'needs (w_n, zeta).', low=1, high=100000)
    corner_lines_min: int = param(8, unit='-', description='Good lines the corner region needs '
                                  '(tau).', low=1, high=100000)
    gain_lines_min: int = param(3, unit='-', description='Good lines below the resonance the '
                                'small-signal gain needs.', low=1, high=100000)
    alpha_range_fraction: float = param(0.5, unit='-', description='Input range a hysteresis run '
                                        'needs, as a fraction of 1/alpha of the configured '
                                        'model.', low=0.0)
    alpha_rel_std_max: float = param(0.25, unit='-', description='Largest relative standard '
                                     'deviation of alpha accepted from the hysteresis fit.',
                                     low=0.0, low_open=True)
    innovation_corr_min: float = param(0.2, unit='-', description='Correlation of the command '
                                       'and position innovations above which a run is closed '
                                       'loop.', low=0.0, high=1.0)


# --------------------------------------------------------------------------------------------
# Loop and excitation


def _name(record: RunRecord) -> str:
    return str(record.meta.get('bag', record.meta.get('name', '<record>')))


def _lagged(x: FloatArray, lags: Sequence[int], n0: int) -> FloatArray:
    """Return columns x[k - lag] for k = n0 ... len(x) - 1."""
    return np.stack([x[n0 - lag:x.size - lag] for lag in lags], axis=1)


def _residual(target: FloatArray, cols: FloatArray) -> FloatArray:
    a = np.column_stack([np.ones(target.size), cols])
    scale = np.maximum(np.abs(a).max(axis=0), 1e-300)
    coef, *_ = np.linalg.lstsq(a / scale, target, rcond=None)
    return np.asarray(target - (a / scale) @ coef, dtype=np.float64)


def loop_kind(record: RunRecord, chain: SignalChainParams, *, order: int = 8,
              corr_min: float = 0.2) -> tuple[str, str]:
    """
    Say whether a run was recorded in open or closed loop, and why.

    Parameters
    ----------
    record : RunRecord
        The run.
    chain : SignalChainParams
        Signal chain giving the applied voltage.
    order : int
        Lags of the innovation regressions.
    corr_min : float
        Largest |correlation| of the innovations (lags 0 to 2) still taken as open loop.

    Returns
    -------
    kind : str
        ``'open'`` or ``'closed'``.
    reason : str
        What decided it.

    Notes
    -----
    Open loop when the command is an affine function of the reference and its velocity (rms
    residual below 1e-6 of the command's). Otherwise the innovations are compared: the
    position's (y_k less its prediction from past inputs and positions: the sensor noise) and
    the command's (u_k less its prediction from past commands and the reference). A controller
    puts the current or a recent position into the command, so in closed loop they correlate
    at lag 0 to 2; in open loop the command does not see the sensor noise.

    """
    # the controller's own output, clipped but not through the DAC: an integral action moves
    # the command by far less than one DAC step per sample of sensor noise, so the applied
    # (quantized) voltage would hide the feedback
    u = np.clip(np.asarray(record.command_v, dtype=np.float64), chain.amplifier_min_v,
                chain.amplifier_max_v)
    su = float(np.std(u))
    if not su > 0.0:
        return 'open', 'the command never changes'
    r = np.asarray(record.reference_m, dtype=np.float64)
    rv = np.asarray(record.reference_velocity_mps, dtype=np.float64)
    res = _residual(u, np.column_stack([r, rv]))
    rel = float(np.std(res)) / su
    if rel < 1e-6:
        return 'open', 'the command is a fixed function of the reference (open-loop controller)'
    y = np.asarray(record.position_m, dtype=np.float64)
    n0 = order + 2
    if y.size < 10 * (n0 + 2 * order):
        return 'open', 'too short to test for feedback'
    past = list(range(1, order + 1))
    ey = _residual(y[n0:], np.column_stack([_lagged(u, past, n0), _lagged(y, past, n0)]))
    cols = [_lagged(u, past, n0)]
    if float(np.std(r)) > 0.0:
        cols.append(_lagged(r, [0] + past, n0))
    eu = _residual(u[n0:], np.column_stack(cols))
    best = 0.0
    for lag in (0, 1, 2):
        a, b = eu[lag:], ey[:ey.size - lag]
        den = float(np.std(a) * np.std(b))
        if den > 0.0:
            best = max(best, abs(float(np.mean((a - a.mean()) * (b - b.mean())))) / den)
    if best > corr_min:
        return 'closed', (f'the command follows the position noise (innovation correlation '
                          f'{best:.2f})')
    return 'open', f'the command does not follow the position noise (correlation {best:.2f})'


def content_role(record: RunRecord, chain: SignalChainParams) -> str:
    """
    Say what a run can be used for from what its excitation holds.

    Parameters
    ----------
    record : RunRecord
        The run; ``meta['identification_role']``, when present, decides.
    chain : SignalChainParams
        Signal chain giving the applied voltage.

    Returns
    -------
    str
        One of :data:`~piezo_stage_ros.core.identification.fit.ROLES`. The excitation is the
        reference when it changes (in closed loop the command is not a designed input), else
        the applied command. A step train is ``'step'``; a periodic excitation with 8 or more
        lines is ``'frequency'`` even when a slow sine holds most of its power (a multisine on
        a sine serves both); otherwise one dominant frequency is ``'hysteresis'``, and
        broadband is ``'frequency'``.

    """
    role = record.meta.get('identification_role')
    if isinstance(role, str) and role in ROLES:
        return role
    r = np.asarray(record.reference_m, dtype=np.float64)
    if not float(np.ptp(r)) > 0.0:
        return classify_run(record, chain)
    kind = classify_signal(r)
    if kind == 'step':
        return kind
    period = detect_period(r)
    if period is not None:
        lines = np.abs(np.fft.rfft(r[:period] - float(np.mean(r[:period]))))[1:]
        if int(np.count_nonzero(excited_lines(lines))) >= 8:
            return 'frequency'
    return kind


@dataclass(frozen=True)
class LineAnalysis:
    """
    Which frequency lines a run excites, and their signal-to-noise ratios.

    Attributes
    ----------
    frequency_hz : ndarray
        Lines (periodic: k / (N T); Welch: the bins) [Hz].
    excited : ndarray of bool
        Lines the excitation drives.
    snr_u, snr_y : ndarray
        Power signal-to-noise ratio of the applied input and of the position per line
        (periodic: |mean|^2 / variance of the mean; Welch, open loop: gamma^2 / (1 - gamma^2)
        for the position, infinite for the input).
    method : str
        ``'periodic'``, ``'welch'`` or ``'none'`` (no excitation).
    period_samples : int or None
    periods : int
        Whole periods averaged (periodic).
    spectra : PeriodicSpectra or None

    """

    frequency_hz: FloatArray
    excited: BoolArray
    snr_u: FloatArray
    snr_y: FloatArray
    method: str
    period_samples: int | None = None
    periods: int = 0
    spectra: PeriodicSpectra | None = None

    def good(self, snr_min: float) -> BoolArray:
        """Return the excited lines whose input and position both pass ``snr_min``."""
        return np.asarray(self.excited & (self.snr_u >= snr_min) & (self.snr_y >= snr_min),
                          dtype=bool)


@dataclass(frozen=True)
class RunSupport:
    """
    What one run shows: its loop, saturation, excitation and input range.

    Attributes
    ----------
    name : str
    role : str
        What it is used for (one of :data:`~piezo_stage_ros.core.identification.fit.ROLES`).
    loop : str
        ``'open'`` or ``'closed'``.
    loop_reason : str
    saturated_fraction : float
        Fraction of commands at or beyond a limit of the amplifier range.
    input_range_v : float
        Peak-to-peak applied input over the part a hysteresis fit uses (the first
        ``head_s``) [V].
    reference_constant : bool
        True when the reference never changes.
    lines : LineAnalysis
    sample_time_s : float

    """

    name: str
    role: str
    loop: str
    loop_reason: str
    saturated_fraction: float
    input_range_v: float
    reference_constant: bool
    lines: LineAnalysis
    sample_time_s: float


def analyse_run(record: RunRecord, chain: SignalChainParams, role: str,
                loop: tuple[str, str], *, segment_s: float = 0.05,
                head_s: float = 0.2) -> RunSupport:
    """
    Return what a run shows: saturation, input range and its excitation line by line.

    Parameters
    ----------
    record : RunRecord
        The run.
    chain : SignalChainParams
        Signal chain (amplifier range, DAC).
    role : str
        What it is to be used for.
    loop : (str, str)
        Loop kind and reason from :func:`loop_kind`.
    segment_s : float
        Welch segment length when the excitation is not periodic [s].
    head_s : float
        Length from the start over which the input range is measured [s] (what the
        hysteresis fit uses).

    Returns
    -------
    RunSupport

    """
    t = sample_time_of(record)
    cmd = np.asarray(record.command_v, dtype=np.float64)
    u = applied_voltage(record, chain)
    y = np.asarray(record.position_m, dtype=np.float64)
    r = np.asarray(record.reference_m, dtype=np.float64)
    # at or beyond a limit: a controller clips its output to the range itself
    outside = ~((cmd > chain.amplifier_min_v) & (cmd < chain.amplifier_max_v))
    sat = float(np.mean(outside)) if cmd.size else 0.0
    ref_const = not float(np.ptp(r)) > 0.0
    closed = loop[0] == 'closed'
    excitation = r if (closed or not ref_const) else u
    empty = np.zeros(0)
    if closed and ref_const or not float(np.ptp(excitation)) > 0.0:
        lines = LineAnalysis(empty, np.zeros(0, dtype=bool), empty, empty, 'none')
    else:
        hint = record.meta.get('trajectory_period_s')
        hint_n = int(round(float(hint) / t)) if isinstance(hint, (int, float)) and hint > 0 \
            else None
        period = detect_period(excitation, hint_samples=hint_n)
        if period is not None and len(u) // period >= 2:
            spec = periodic_spectra(u, y, excitation, period, t)
            exc = excited_lines(spec.r)
            # measured in open loop too: a loop whose feedback the verdict missed still
            # scatters the input over the periods
            snr_u = spec.snr_u
            lines = LineAnalysis(spec.frequency_hz, exc, snr_u, spec.snr_y, 'periodic',
                                 period, spec.periods, spec)
        elif closed:
            lines = LineAnalysis(empty, np.zeros(0, dtype=bool), empty, empty, 'welch')
        else:
            nper = max(min(int(round(segment_s / t)), len(u) // 2), 16)
            kw: dict[str, Any] = {'fs': 1.0 / t, 'window': 'hann', 'nperseg': nper,
                                  'detrend': 'constant'}
            f, pee = signal.welch(excitation, **kw)
            _, coh = signal.coherence(u, y, **kw)
            top = float(pee[1:].max()) if pee.size > 1 else 0.0
            exc = (pee > 1e-8 * top) & (f > 0.0)
            coh = np.minimum(coh, 1.0 - 1e-12)
            lines = LineAnalysis(np.asarray(f, dtype=np.float64), np.asarray(exc, dtype=bool),
                                 np.full(f.size, np.inf), coh / (1.0 - coh), 'welch')
    return RunSupport(name=_name(record), role=role, loop=loop[0], loop_reason=loop[1],
                      saturated_fraction=sat,
                      input_range_v=float(np.ptp(u[:max(int(round(head_s / t)), 2)])),
                      reference_constant=ref_const, lines=lines, sample_time_s=t)


# --------------------------------------------------------------------------------------------
# Support rules


def _hz(f: float) -> str:
    return f'{f / 1000.0:.3g} kHz' if f >= 1000.0 else f'{f:.3g} Hz'


def _describe(freqs: FloatArray) -> str:
    n = int(freqs.size)
    if n == 0:
        return 'no line'
    if n <= 3:
        return f'{n} line{"s" if n > 1 else ""} (' + ', '.join(_hz(float(f)) for f in freqs) + ')'
    return f'{n} lines from {_hz(float(freqs[0]))} to {_hz(float(freqs[-1]))}'


def _region(run: RunSupport, params: IdentificationParams, support: SupportParams,
            low: float, high: float, need_low: float, need_high: float, count: int
            ) -> str | None:
    """Return why the good lines of ``run`` do not cover [need_low, need_high], or None."""
    la = run.lines
    nyq = 0.5 / run.sample_time_s
    top = params.band_high_fraction * nyq
    if la.frequency_hz.size == 0:
        return None
    usable = la.good(support.snr_min) & (la.frequency_hz >= params.band_low_hz) & \
        (la.frequency_hz <= top)
    f = la.frequency_hz[usable]
    inside = f[(f >= low) & (f <= min(high, top))]
    need_high = min(need_high, 0.98 * top)
    if inside.size >= count and inside[0] <= need_low and inside[-1] >= need_high:
        return None
    what = (f'the {run.role} run {run.name!r} excites {_describe(f)} above the noise '
            f'(signal-to-noise >= {support.snr_min:g})')
    if need_high <= need_low:
        return (f'{what}; needs {count} or more below {_hz(need_low)} (fix: a run with a '
                f'periodic multisine on the reference from {_hz(params.band_low_hz)} to '
                f'{_hz(need_low)} or beyond, repeated over two or more whole periods)')
    return (f'{what}; needs {count} or more from {_hz(need_low)} to {_hz(need_high)} (fix: a '
            'run with a periodic multisine on the reference over that band, repeated over two '
            'or more whole periods, loud enough to stand above the noise there)')


def refusals(runs: Sequence[RunSupport], base: StageParams, params: IdentificationParams,
             support: SupportParams | None = None, *,
             closed_loop: bool | None = None) -> list[str]:
    """
    Return one line per parameter the runs cannot support (empty when all are supported).

    Parameters
    ----------
    runs : sequence of RunSupport
        Every run with its role.
    base : StageParams
        The configured stage: where the resonance, the corner and 1/alpha are expected.
    params : IdentificationParams
        Band of the frequency fit, step window, hysteresis length.
    support : SupportParams, optional
        Thresholds.
    closed_loop : bool, optional
        True when the user said the data are closed loop.

    Returns
    -------
    list of str

    """
    support = support or SupportParams()
    out: list[str] = []
    prior = factors_of(base.plant.third_order)
    fn = prior.omega_n_rad_s / (2.0 * math.pi)
    fc = 1.0 / (2.0 * math.pi * prior.tau_s)
    has = {role: [r for r in runs if r.role == role] for role in ROLES}
    uses: dict[str, list[str]] = {
        'frequency': ['omega_n'] + ([] if has['step'] else ['zeta', 'tau'])
        + ([] if has['hysteresis'] or has['step'] else ['gain']),
        'step': ['zeta', 'tau'] + ([] if has['frequency'] else ['omega_n']),
        'hysteresis': ['alpha', 'static gain'],
    }
    for run in runs:
        names = ', '.join(uses[run.role])
        if closed_loop and run.loop == 'open' and run.role == 'frequency' and \
                run.lines.method != 'periodic':
            out.append(f'closed loop: run {run.name!r} is open loop ({run.loop_reason}) and '
                       'its excitation does not repeat over two whole periods; drop '
                       '--closed-loop, or record it under feedback with a periodic reference')
            continue
        if run.saturated_fraction > support.saturation_max:
            out.append(f'{names}: run {run.name!r} ({run.role}) is saturated: '
                       f'{100.0 * run.saturated_fraction:.1f} % of its commands lie at or '
                       'outside the amplifier range; identification needs an unsaturated run')
            continue
        if run.role == 'frequency':
            out += _frequency_refusals(run, uses['frequency'], params, support, fn, fc)
        if run.role == 'hysteresis' or (run.role == 'frequency' and run.lines.method ==
                                        'periodic' and not has['hysteresis']):
            # a closed-loop run without a sine run gives the hysteresis too
            bl = base.hysteresis.backlash_like
            need = support.alpha_range_fraction / bl.alpha if params.hysteresis_model == \
                'backlash_like' and bl.alpha > 0.0 else 0.0
            if run.input_range_v < need:
                out.append(f'alpha: the {run.role} run {run.name!r} spans '
                           f'{run.input_range_v:.3g} V of input; the curvature of the loop '
                           f'needs about {need:.3g} V or more (1/alpha = '
                           f'{1.0 / bl.alpha:.3g} V for the configured stage; fix: a slow '
                           f'sine run spanning {need:.3g} V or more of input, two whole '
                           'cycles)')
    return out


def _frequency_refusals(run: RunSupport, names: list[str], params: IdentificationParams,
                        support: SupportParams, fn: float, fc: float) -> list[str]:
    la = run.lines
    if la.method == 'none':
        if run.loop == 'closed':
            why = (f'the closed-loop run {run.name!r} has no excitation on its reference (it '
                   'is constant); its command only carries the sensor noise fed back, whose '
                   'ratio to the position is the controller (-1/C), not the stage')
        else:
            why = f'the run {run.name!r} has no excitation (its command never changes)'
        return [f'{", ".join(names)}: {why}']
    if la.method == 'welch' and run.loop == 'closed':
        return [f'{", ".join(names)}: the closed-loop run {run.name!r} has a reference that '
                'does not repeat over two or more whole periods; closed-loop identification '
                'averages over whole periods of a periodic excitation (e.g. trajectory kind '
                'noise, whose period_s is a whole number of samples)']
    out = []
    res = _region(run, params, support, 0.5 * fn, 1.5 * fn, 0.8 * fn, 1.2 * fn,
                  support.resonance_lines_min)
    if res is not None:
        for name in ('omega_n', 'zeta'):
            if name in names:
                out.append(f'{name}: {res} (the resonance near {_hz(fn)})')
    if 'tau' in names:
        res = _region(run, params, support, 0.25 * fc, 4.0 * fc, 0.5 * fc, 2.0 * fc,
                      support.corner_lines_min)
        if res is not None:
            out.append(f'tau: {res} (the corner 1/(2 pi tau) near {_hz(fc)})')
    if 'gain' in names:
        res = _region(run, params, support, 0.0, fn / 3.0, fn / 3.0, 0.0,
                      support.gain_lines_min)
        if res is not None:
            out.append(f'gain: {res} (below the resonance)')
    return out


def _plateau_refusal(record: RunRecord, run: RunSupport, names: str, chain: SignalChainParams,
                     params: IdentificationParams) -> str | None:
    v = applied_voltage(record, chain)
    edges = np.flatnonzero(np.diff(v)) + 1
    if edges.size == 0:
        return None
    edges = edges[:params.step_max_jumps + 1]
    plateaus = np.diff(np.concatenate([edges, [v.size]]))
    need = params.step_window_s / run.sample_time_s
    median = float(np.median(plateaus))
    if median >= 0.5 * need:
        return None
    return (f'{names}: the step run {run.name!r} has input jumps with plateaus of '
            f'{median:g} samples (median); the step fit needs about '
            f'{params.step_window_s * 1e3:g} ms ({need:.0f} samples) after each jump')


# --------------------------------------------------------------------------------------------
# Closed loop: the periodic frequency response and its fit


@dataclass(frozen=True)
class PeriodicFit:
    """
    The discrete-time model fitted to a periodic (e.g. closed-loop) frequency response.

    Attributes
    ----------
    fit : FrequencyFit
        In the form the report draws (``data.coherence`` is SNR / (1 + SNR) per line).
    phase_rad : float
        Frequency-independent phase lag of the hysteresis' describing function [rad].
    chi2_per_dof : float
        Weighted residual per degree of freedom (about 1 when the variances per line hold).
    relative_std_noise, relative_std_distortion : float
        Median relative standard deviation of G per line from noise and from distortion.
    h1_deviation : float
        Median |H1 / G - 1| over the excited lines: how far the usual H1 estimate of the same
        data is from the periodic one (the feedback bias of H1 in closed loop).
    feedback_bias : float
        Largest |cov(Y, U) / (P |U|^2)| / |G| over the used lines: the order of the bias the
        fed-back noise leaves in the averaged estimate.

    """

    fit: FrequencyFit
    phase_rad: float
    chi2_per_dof: float
    relative_std_noise: float
    relative_std_distortion: float
    h1_deviation: float
    feedback_bias: float


def _model_or_none(x: FloatArray, t: float, fu: FloatArray, delay: float
                   ) -> ComplexArray | None:
    """Return the model response of log-parameters ``x[:4]``, None outside the physical range."""
    with np.errstate(over='ignore', invalid='ignore'):
        values = np.exp(np.asarray(x[:4], dtype=np.float64))
    if not np.all(np.isfinite(values)) or not np.all(values > 0.0):
        return None
    try:
        model = discrete_frequency_response(third_order_of(LinearFactors(
            *(float(v) for v in values))), t, fu, delay)
    except (PiezoStageError, np.linalg.LinAlgError):
        return None
    return model if bool(np.all(np.isfinite(model))) and bool(np.all(model != 0.0)) else None


def fit_periodic_response(spectra: PeriodicSpectra, params: IdentificationParams,
                          initial: LinearFactors, *, u: FloatArray | None = None,
                          y: FloatArray | None = None,
                          delay_samples: float | None = None) -> PeriodicFit:
    """
    Fit k_p, w_n, zeta, tau and a constant phase to the averaged frequency response.

    Parameters
    ----------
    spectra : PeriodicSpectra
        Averages over whole periods.
    params : IdentificationParams
        Band of the fit (``band_low_hz``, ``band_high_fraction``).
    initial : LinearFactors
        Start of the search (the configured model).
    u, y : ndarray, optional
        The applied input and position of the run, to compare with the H1 estimate.
    delay_samples : float, optional
        Loop delay beyond the hold [samples], kept fixed; default: the best whole delay of
        :data:`~piezo_stage_ros.core.identification.fit.DELAYS_TRIED`, or a fraction when the
        data show one (:func:`~piezo_stage_ros.core.identification.fit.choose_delay`).

    Returns
    -------
    PeriodicFit

    Raises
    ------
    IdentificationError
        If fewer than 8 excited lines lie in the band.

    """
    g, var_n, var_d = spectra.response()
    f = spectra.frequency_hz
    t = spectra.sample_time_s
    nyq = 0.5 / t
    exc = excited_lines(spectra.r)
    used = exc & (f >= params.band_low_hz) & (f <= params.band_high_fraction * nyq)
    if int(used.sum()) < 8:
        raise IdentificationError(f'closed-loop frequency response: {int(used.sum())} excited '
                                  'lines in the band, need 8')
    var = var_n + var_d
    with np.errstate(divide='ignore', invalid='ignore'):
        sig = np.sqrt(np.maximum(var, 1e-300)) / np.abs(g)
    fu, gu, su = f[used], g[used], np.maximum(sig[used], 1e-6)

    # the lowest used line scales the relaxation term: x[6] is its phase lag there [rad]
    lag = 1.0 / (1j * fu / fu[0])

    def residual_at(delay: float | None, relax: bool = False) -> Any:
        # x: log k_p, log w_n, log zeta, log tau, phase, [delay when free], [relaxation]
        def residual(x: FloatArray) -> FloatArray:
            d = float(x[5]) if delay is None else delay
            model = _model_or_none(x, t, fu, d)
            if model is None:
                # a search that left the physical range (a wrong delay tried): a large, finite
                # residual sends it back
                return np.full(2 * fu.size, 1e6)
            model = model * np.exp(-1j * x[4])
            if relax:
                model = model * (1.0 + x[-1] * lag)
            r = np.log(model / gu) / su
            return np.asarray(np.concatenate([r.real, r.imag]), dtype=np.float64)
        return residual

    start = np.log([initial.gain_m_per_v, initial.omega_n_rad_s, initial.zeta,
                    initial.tau_s])

    def fit_at(delay: float) -> Any:
        # from the configured model (the delay is in the model's phase)
        return optimize.least_squares(residual_at(delay), np.append(start, 0.0), method='lm')

    if delay_samples is None:
        sol, delay = choose_delay(fit_at, residual_at(None))
    else:
        sol, delay = fit_at(delay_samples), delay_samples
    free = sol.x.size == 6

    def residual(x: FloatArray) -> FloatArray:
        return np.asarray(residual_at(None if free else delay)(x), dtype=np.float64)

    dof = max(sol.fun.size - sol.x.size, 1)
    chi2 = float(sol.fun @ sol.fun) / dof
    jac = np.asarray(sol.jac, dtype=np.float64)
    cov = np.linalg.pinv(jac.T @ jac) * max(chi2, 1.0)
    # model-structure term: how far two other describing functions of the hysteresis move each
    # parameter, the larger of the two: none at all (a purely linear model), and the constant
    # phase with the relaxation of the linearised dynamic backlash around the slow motion,
    # (B s + kappa c) / (s + kappa) ~ B (1 + kappa (c / B - 1) / s) on lines far above kappa
    # (a lag falling as 1 / f that the constant phase alone leaves to zeta and tau)
    fixed_phase = sol.x.copy()

    def no_phase(x: FloatArray) -> FloatArray:
        xf = fixed_phase.copy()
        xf[:4] = x[:4]
        xf[4] = 0.0
        if free:
            xf[5] = x[4]
        return residual(xf)

    alt_x0 = np.append(sol.x[:4], sol.x[5:6]) if free else sol.x[:4]
    alt = optimize.least_squares(no_phase, alt_x0, method='lm')
    relax = optimize.least_squares(residual_at(None if free else delay, relax=True),
                                   np.append(sol.x, 0.0), method='lm')
    structure = np.zeros(sol.x.size)
    structure[:4] = np.maximum(np.abs(alt.x[:4] - sol.x[:4]), np.abs(relax.x[:4] - sol.x[:4]))
    if free:
        # a fraction of a sample may stand for another phase that grows with frequency
        structure[:4] = np.maximum(structure[:4], whole_delay_shift(fit_at, sol, delay)[:4])
    rel = np.sqrt(np.maximum(np.diag(cov), 0.0) + structure ** 2)
    k, w, z, tau = (float(v) for v in np.exp(sol.x[:4]))
    fac = LinearFactors(k, w, z, tau, delay)
    std = LinearFactors(fac.gain_m_per_v * rel[0], fac.omega_n_rad_s * rel[1],
                        fac.zeta * rel[2], fac.tau_s * rel[3], float(rel[5]) if free else 0.0)
    model = discrete_frequency_response(third_order_of(fac), t, f, delay) * \
        np.exp(-1j * sol.x[4])
    with np.errstate(invalid='ignore'):
        snr = np.abs(g) ** 2 / np.maximum(var, 1e-300)
    data = FrequencyResponse(frequency_hz=f, response=g, coherence=snr / (1.0 + snr),
                             sample_time_s=t, segments=spectra.periods)
    err = np.log(model[used] / gu)
    ffit = FrequencyFit(factors=fac, std=std, data=data, used=used, model=model,
                        rms_log_error=float(np.sqrt(np.mean(np.abs(err) ** 2))))
    h1_dev = float('nan')
    if u is not None and y is not None:
        n = spectra.period_samples
        _, puy = signal.csd(u, y, fs=1.0 / t, window='boxcar', nperseg=n, noverlap=0,
                            detrend='constant')
        _, puu = signal.welch(u, fs=1.0 / t, window='boxcar', nperseg=n, noverlap=0,
                              detrend='constant')
        h1 = puy[1:n // 2 + 1] / np.maximum(puu[1:n // 2 + 1], 1e-300)
        h1_dev = float(np.median(np.abs(h1[used] / gu - 1.0)))
    with np.errstate(divide='ignore', invalid='ignore'):
        bias = np.abs(spectra.cov_yu / np.abs(spectra.u) ** 2) / np.abs(g)
    return PeriodicFit(fit=ffit, phase_rad=float(sol.x[4]), chi2_per_dof=chi2,
                       relative_std_noise=float(np.median(np.sqrt(var_n[used]) / np.abs(gu))),
                       relative_std_distortion=float(np.median(np.sqrt(var_d[used])
                                                               / np.abs(gu))),
                       h1_deviation=h1_dev, feedback_bias=float(np.max(bias[used])))


# --------------------------------------------------------------------------------------------
# The checked procedure


@dataclass
class CheckedIdentification:
    """
    An identification with what the data supported and the warnings.

    Attributes
    ----------
    result : IdentificationResult
        With ``bounds`` (95 %) and ``loop``.
    runs : list of RunSupport
    periodic : PeriodicFit or None
        The closed-loop frequency fit, when the data were closed loop.
    warnings : list of str

    """

    result: IdentificationResult
    runs: list[RunSupport]
    periodic: PeriodicFit | None = None
    warnings: list[str] = field(default_factory=list)


def _bounds(value: float, std: float) -> tuple[float, float]:
    return value - Z95 * std, value + Z95 * std


def identify_checked(records: Sequence[RunRecord], base: StageParams | None = None,
                     params: IdentificationParams | None = None,
                     roles: Sequence[str | None] | None = None, *,
                     closed_loop: bool | None = None,
                     support: SupportParams | None = None) -> CheckedIdentification:
    """
    Check what the runs support, refuse what they cannot, then identify (open or closed loop).

    Parameters
    ----------
    records : sequence of RunRecord
        The runs.
    base : StageParams, optional
        The configured stage (signal chain; where the resonance and corner are expected).
    params : IdentificationParams, optional
        Settings of the procedure.
    roles : sequence of str or None, optional
        Forced roles, one per record (None: classify).
    closed_loop : bool, optional
        True: the frequency runs are closed loop (an open-loop one is refused); None: detect.
    support : SupportParams, optional
        Thresholds of the support rules.

    Returns
    -------
    CheckedIdentification

    Raises
    ------
    RefusedError
        One line per parameter the data cannot support; nothing is fitted.

    """
    base = base or StageParams()
    params = params or IdentificationParams()
    support = support or SupportParams()
    chain = base.chain
    runs: list[RunSupport] = []
    resolved: list[str] = []
    loops = []
    for i, rec in enumerate(records):
        forced = roles[i] if roles is not None and i < len(roles) else None
        loop = loop_kind(rec, chain, corr_min=support.innovation_corr_min)
        # what the run holds decides its role, not the loop verdict nor its place in the list
        role = forced if forced is not None else content_role(rec, chain)
        if role not in ROLES:
            raise IdentificationError(f'role {role!r} is not one of {ROLES}')
        resolved.append(role)
        loops.append(loop)
        runs.append(analyse_run(rec, chain, role, loop, segment_s=params.segment_s,
                                head_s=params.hysteresis_max_s))
    lines = refusals(runs, base, params, support, closed_loop=closed_loop)
    by = {role: [r for r in runs if r.role == role] for role in ROLES}
    for rec, run in zip(records, runs):
        if run.role == 'step':
            names = 'zeta, tau' + ('' if by['frequency'] else ', omega_n')
            why = _plateau_refusal(rec, run, names, chain, params)
            if why is not None:
                lines.append(why)
    if lines:
        raise RefusedError(lines)
    warnings: list[str] = []
    # the periodic reference is the instrument: averaged over whole periods, the response from
    # the applied input to the position is consistent whatever share of the input the feedback
    # makes, so the same estimate serves open and closed loops and the verdict is only reported
    closed = [(rec, run) for rec, run in zip(records, runs)
              if run.role == 'frequency' and run.lines.method == 'periodic']
    closed.sort(key=lambda item: -int(np.count_nonzero(item[1].lines.good(support.snr_min))))
    periodic = None
    if closed:
        rec, run = closed[0]
        spec = run.lines.spectra
        assert spec is not None
        u = applied_voltage(rec, chain)
        y = np.asarray(rec.position_m, dtype=np.float64)
        periodic = fit_periodic_response(spec, params, factors_of(base.plant.third_order),
                                         u=u, y=y)
        if closed_loop and run.loop == 'open':
            warnings.append(f'run {run.name!r} was given as closed loop, but its commands do '
                            f'not show the feedback ({run.loop_reason}); the periodic '
                            'estimate used holds either way')
        warnings.append(
            f'run {run.name!r} is {run.loop} loop ({run.loop_reason}): the usual H1 = S_uy/S_uu '
            'of these data differs from the periodic estimate by '
            f'{100 * periodic.h1_deviation:.1f} % '
            '(median over the excited lines; feedback bias toward -1/C where the fed-back noise '
            f'dominates); used instead: {spec.periods} whole periods of '
            f'{spec.period_samples * run.sample_time_s:g} s averaged, remaining bias of the '
            f'order of {100 * periodic.feedback_bias:.2g} %')
        if len(closed) > 1:
            warnings.append(f'the periodic frequency run {run.name!r} has the most lines '
                            'above the noise and is used; left out: '
                            + ', '.join(repr(r.name) for _, r in closed[1:]))
        use_roles: list[str | None] = []
        keep: list[RunRecord] = []
        hyst_given = bool(by['hysteresis'])
        for rec2, run2 in zip(records, runs):
            if run2.role == 'frequency' and run2.lines.method == 'periodic':
                # the same periodic run gives the hysteresis when no sine run is given
                if not hyst_given and rec2 is rec:
                    keep.append(rec2)
                    use_roles.append('hysteresis')
                continue
            keep.append(rec2)
            use_roles.append(run2.role)
        result = identify(keep, base, params, use_roles, frequency_fit=periodic.fit)
        result.loop = run.loop
        result.roles['frequency'] = [run.name]
        if not hyst_given:
            result.notes.append(f'hysteresis fitted on the periodic run {run.name!r} '
                                f'(its first {params.hysteresis_max_s:g} s, or two cycles of its '
                                'strongest line when longer)')
    else:
        result = identify(records, base, params, resolved)
    structure: dict[str, float] = {}
    if periodic is not None and result.hysteresis is not None:
        rec, run = closed[0]
        structure = _correct_structure_bias(result, rec, run, base, params)
    elif result.frequency is not None and result.hysteresis is not None:
        freq = [rec for rec, r in zip(records, runs) if r.role == 'frequency']
        if freq:
            structure = _correct_structure_bias(result, freq[0], None, base, params)
    _fill_bounds(result)
    _widen_bounds(result.bounds, structure, relative=True)
    _widen_step_for_omega(result, base, params)
    # the hysteresis fit holds the linear shape fixed, open loop or closed
    _widen_for_shape(result, base, params)
    _widen_by_replay(result, base, params)
    post = _post_fit_refusals(result, support)
    if post:
        raise RefusedError(post)
    return CheckedIdentification(result=result, runs=runs, periodic=periodic,
                                 warnings=warnings)


def replay(result: IdentificationResult, v: FloatArray, sample_time_s: float) -> FloatArray:
    """
    Return the position the identified model gives for applied voltages ``v``, from rest.

    Parameters
    ----------
    result : IdentificationResult
        The identified stage: hysteresis, k_p, w_n, zeta, tau and the loop delay.
    v : ndarray
        Applied voltages [V], one per sample.
    sample_time_s : float
        Sample period [s].

    Returns
    -------
    ndarray
        Noise-free position [m] (rest at v[0] before the run).

    """
    h = make_hysteresis(result.stage.hysteresis)
    state = h.rest_state(float(v[0]))
    w = np.empty(v.size)
    step = h.step
    for k, vk in enumerate(np.asarray(v, dtype=np.float64).tolist()):
        state, wk = step(state, vk)
        w[k] = float(wk)
    f = result.factors
    num, den = _unit_filter(f, sample_time_s)
    w0 = float(w[0])
    return np.asarray(f.gain_m_per_v * (signal.lfilter(num, den, w - w0) + w0),
                      dtype=np.float64)


def _correct_structure_bias(result: IdentificationResult, record: RunRecord,
                            run: RunSupport | None, base: StageParams,
                            params: IdentificationParams) -> dict[str, float]:
    """
    Remove from w_n, zeta and tau the bias the hysteresis leaves in the linear fit; return it.

    The linear fits see the hysteresis through its describing function at the excitation's
    amplitude, which no frequency-independent factor captures exactly. The identified model
    (hysteresis included) is replayed on the run's own applied voltages and the same estimate
    and fit are made on that noise-free answer: how far they land from the model's own w_n,
    zeta and tau is the bias at this amplitude, this input and this sampling (the DAC steps are
    in the applied voltages). It is taken off the estimates; half of it, relative, is returned
    per parameter as the model-structure term of the bounds (what the correction itself may
    miss where the identified hysteresis is not the stage's).
    """
    t = sample_time_of(record)
    u = applied_voltage(record, base.chain)
    y_sim = replay(result, u, t)
    f = result.factors
    if run is not None:
        spec = run.lines.spectra
        assert spec is not None
        r = np.asarray(record.reference_m, dtype=np.float64)
        excitation = r if float(np.ptp(r)) > 0.0 else u
        sim = periodic_spectra(u, y_sim, excitation, spec.period_samples, t)
        got = fit_periodic_response(sim, params, f, delay_samples=f.delay_samples).fit.factors
    else:
        from piezo_stage_ros.core.identification.fit import (
            estimate_frequency_response,
            fit_frequency_response,
        )
        replayed = RunRecord(record.time_s, y_sim, record.reference_m,
                             record.reference_velocity_mps, record.command_v, meta=record.meta)
        data = estimate_frequency_response([replayed], base.chain, segment_s=params.segment_s)
        got = fit_frequency_response(data, params, initial=f).factors
    # with a step run, zeta and tau come from it (the step fit has no describing function):
    # the frequency run's bias is taken off w_n alone, whichever estimate the run gave
    names = ('omega_n_rad_s',) if result.step is not None else ('omega_n_rad_s', 'zeta', 'tau_s')
    bias = {n: math.log(getattr(got, n) / getattr(f, n)) for n in names}
    values = {n: getattr(f, n) * math.exp(-b) for n, b in bias.items()}
    fixed = replace(f, **values)
    third = third_order_of(fixed)
    plant = result.stage.plant.replace(third_order=third, reduced=third.reduced())
    result.factors = fixed
    result.third_order = third
    result.stage = result.stage.replace(plant=plant)
    result.notes.append('hysteresis bias of the linear fit removed (the identified model '
                        'replayed on the applied input): ' + ', '.join(
                            f'{n} {-100 * b:+.3g} %' for n, b in bias.items()))
    return {n: 0.5 * abs(b) for n, b in bias.items()}


def _fill_bounds(result: IdentificationResult) -> None:
    """Put 95 % bounds of every parameter with a standard deviation into ``result.bounds``."""
    b: dict[str, tuple[float, float]] = {}
    fr, st, hy = result.frequency, result.step, result.hysteresis
    f = result.factors
    if fr is not None:
        b['omega_n_rad_s'] = _bounds(f.omega_n_rad_s, fr.std.omega_n_rad_s)
    if st is not None:
        if st.std.omega_n_rad_s > 0.0:
            b['omega_n_rad_s'] = _bounds(f.omega_n_rad_s, st.std.omega_n_rad_s)
        b['zeta'] = _bounds(f.zeta, st.std.zeta)
        b['tau_s'] = _bounds(f.tau_s, st.std.tau_s)
    elif fr is not None:
        b['zeta'] = _bounds(f.zeta, fr.std.zeta)
        b['tau_s'] = _bounds(f.tau_s, fr.std.tau_s)
    if hy is not None:
        for name, value in hy.estimates.items():
            if name in hy.std:
                b[name] = _bounds(value, hy.std[name])
    result.bounds = b


def _widen_step_for_omega(result: IdentificationResult, base: StageParams,
                          params: IdentificationParams) -> None:
    """
    Widen zeta's and tau's bounds by what the step fit's fixed w_n and delay move them.

    The step fit keeps w_n and the delay from the frequency response; its own standard
    deviations do not carry their uncertainty. It is refitted with w_n at both ends of its
    bounds (and with the nearest whole delay when a fraction was kept), and the largest change
    of zeta and tau is added in quadrature to their half-widths.
    """
    st = result.step
    if st is None or st.std.omega_n_rad_s > 0.0 or 'omega_n_rad_s' not in result.bounds:
        return
    f = result.factors
    moved = {'zeta': 0.0, 'tau_s': 0.0}
    variants = [replace(f, omega_n_rad_s=w) for w in result.bounds['omega_n_rad_s'] if w > 0.0]
    if f.delay_samples != round(f.delay_samples):
        # a fraction of a sample may stand for another phase: the nearest whole delay too
        variants.append(replace(f, delay_samples=float(round(f.delay_samples))))
    for variant in variants:
        alt = fit_step_response(st.records, base.chain, params, variant,
                                fix_omega=True).factors
        moved['zeta'] = max(moved['zeta'], abs(alt.zeta - st.factors.zeta))
        moved['tau_s'] = max(moved['tau_s'], abs(alt.tau_s - st.factors.tau_s))
    _widen_bounds(result.bounds, moved)


def _widen_bounds(bounds: dict[str, tuple[float, float]], moved: Mapping[str, float], *,
                  relative: bool = False) -> None:
    """
    Add each estimate's change in ``moved`` in quadrature to the half-width of its bounds.

    With ``relative`` the changes are fractions of the estimate (the bounds' middle).
    """
    for name, delta in moved.items():
        if name in bounds:
            lo, hi = bounds[name]
            mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
            half = math.hypot(half, delta * abs(mid) if relative else delta)
            bounds[name] = (mid - half, mid + half)


def _widen_for_shape(result: IdentificationResult, base: StageParams,
                     params: IdentificationParams) -> None:
    """
    Widen the hysteresis bounds by what the uncertainty of the linear shape moves them.

    The hysteresis fit holds w_n, zeta and tau fixed; its own standard deviations do not carry
    their uncertainty. It is refitted with tau (the shape parameter it depends on most) at
    both ends of its bounds, and the largest change of each estimate is added in quadrature to
    its half-width.
    """
    hy = result.hysteresis
    if hy is None or 'tau_s' not in result.bounds or hy.model == 'bouc_wen':
        return
    f = result.factors
    moved: dict[str, float] = {}
    for tau in result.bounds['tau_s']:
        if not tau > 0.0:
            continue
        alt = fit_hysteresis(hy.records, base.chain, params,
                             replace(f, tau_s=tau),
                             base.hysteresis)
        for name, value in alt.estimates.items():
            if name in hy.estimates:
                moved[name] = max(moved.get(name, 0.0), abs(value - hy.estimates[name]))
    _widen_bounds(result.bounds, moved)


#: Refits of the hysteresis on replays of the identified model with fresh noise.
REPLAYS = 8
#: Student-t 97.5 % quantile for REPLAYS - 1 degrees of freedom, over the normal one: the
#: spread of a few replays is itself uncertain.
_T_OVER_Z = 2.3646 / Z95


def _widen_by_replay(result: IdentificationResult, base: StageParams,
                     params: IdentificationParams) -> None:
    """
    Widen the hysteresis bounds to the spread of the fit over replays with fresh noise.

    The Jacobian of the hysteresis fit understates its spread where the input is dithered by
    noise (every small reversal moves the loop's state, and the estimates of alpha, the gain,
    the offset and the initial state trade off nonlinearly): on a closed-loop sine the spread
    over noise realizations was several times the Jacobian's. The fitted model's answer to the
    run's own applied input (its initial state, offset and level included) is given fresh
    white noise of the fit's residual level, :data:`REPLAYS` times, and refitted; where the
    spread of the refits (times the Student-t over the normal quantile) exceeds the
    half-width, it replaces it. Deterministic (fixed
    seeds); backlash-like and Bouc-Wen only.
    """
    from scipy.stats import t as student_t
    hy = result.hysteresis
    if hy is None or hy.model == 'prandtl_ishlinskii':
        return
    rng = np.random.default_rng(20260525)
    # the fitted model's own answer: its initial state, offset and level before the run too
    clean = hy.models
    draws: dict[str, list[float]] = {}
    for _ in range(REPLAYS):
        recs = [RunRecord(rec.time_s, y + hy.residual_rms_m * rng.standard_normal(y.size),
                          rec.reference_m, rec.reference_velocity_mps, rec.command_v,
                          meta=rec.meta) for rec, y in zip(hy.records, clean)]
        try:
            alt = fit_hysteresis(recs, base.chain, params, result.factors, base.hysteresis,
                                 start=hy.estimates)
        except IdentificationError:
            continue
        for name, value in alt.estimates.items():
            draws.setdefault(name, []).append(value)
    for name, values in draws.items():
        if name not in result.bounds or len(values) < 3:
            continue
        # the Student-t quantile of the refits that came back (a failed refit leaves fewer)
        quantile = Z95 * _T_OVER_Z if len(values) == REPLAYS else float(
            student_t.ppf(0.975, len(values) - 1))
        half_replay = quantile * float(np.std(values, ddof=1))
        lo, hi = result.bounds[name]
        mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        if half_replay > half:
            result.bounds[name] = (mid - half_replay, mid + half_replay)


def _post_fit_refusals(result: IdentificationResult, support: SupportParams) -> list[str]:
    hy = result.hysteresis
    if hy is None or 'alpha' not in hy.estimates:
        return []
    alpha, sd = hy.estimates['alpha'], hy.std.get('alpha', 0.0)
    if alpha > 0.0 and sd / alpha > support.alpha_rel_std_max:
        names = ', '.join(repr(getattr(r, 'meta', {}).get('name', '?')) for r in hy.records)
        return [f'alpha: the hysteresis run {names} determines it only to +-'
                f'{100 * sd / alpha:.0f} % (1 sigma; at most {100 * support.alpha_rel_std_max:g} '
                '%): a larger input range or a longer run is needed']
    return []
