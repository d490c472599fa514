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
Drift of the stage from an operation bag: what ordinary tracking data support.

An ordinary tracking run (a sine or other periodic reference, no added excitation) drives the
stage at the reference frequency and its harmonics, far below the resonance. Such data
support two numbers, and :func:`estimate_drift` gives them against the configured model:

- the **static gain k_p c**: the configured hysteresis (its shape alpha, B1/c, with the
  configured slope as the convention) and linear shape are run on the recorded applied input;
  the position is linear in the static gain and in the unknown level before the window, which
  linear least squares give (with a standard deviation from the residual);
- the **dominant lag at the reference frequency**: with the static gain free, the time
  constant tau of the real pole is fitted (a one-dimensional search); at 100 Hz the real pole
  gives ~8 degrees of the lag and the resonance ~0.3, so tau is what the lag measures. w_n and
  zeta are not supported (the run excites no line near the resonance).

The window is the first ``window_s`` of the run (the hysteresis is stepped per sample).
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
from piezo_stage_ros.core.contracts.errors import IdentificationError
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.identification.fit import (
    _unit_filter,
    applied_voltage,
    discrete_frequency_response,
    sample_time_of,
)
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.linear import factors_of, LinearFactors, third_order_of
from piezo_stage_ros.core.model.stage import StageParams
from scipy import optimize, signal

__all__ = ['DriftReport', 'drift_lines', 'estimate_drift']


@dataclass(frozen=True)
class DriftReport:
    """
    Static gain and lag from an operation run, against the configured model.

    Attributes
    ----------
    name : str
        The run.
    window_s : float
        Length used [s].
    reference_hz : float
        Dominant frequency of the reference [Hz].
    static_gain_m_per_v, static_gain_std : float
        Estimated k_p c and its standard deviation [m/V].
    configured_gain_m_per_v : float
        k_p c of the configured model [m/V].
    tau_s, tau_std : float
        Time constant fitted to the lag, and its standard deviation [s].
    configured_tau_s : float
    lag_deg, configured_lag_deg : float
        Phase lag of the linear part at the reference frequency, fitted and configured [deg].
    residual_rms_m : float
        Rms of measured minus model position with the fitted gain and tau [m].
    threshold : float
        Relative gain change reported as a change.

    """

    name: str
    window_s: float
    reference_hz: float
    static_gain_m_per_v: float
    static_gain_std: float
    configured_gain_m_per_v: float
    tau_s: float
    tau_std: float
    configured_tau_s: float
    lag_deg: float
    configured_lag_deg: float
    residual_rms_m: float
    threshold: float

    @property
    def gain_change(self) -> float:
        """Return the relative change of the static gain (0.15 = +15 %)."""
        return self.static_gain_m_per_v / self.configured_gain_m_per_v - 1.0

    @property
    def tau_change(self) -> float:
        """Return the relative change of tau."""
        return self.tau_s / self.configured_tau_s - 1.0

    @property
    def changed(self) -> bool:
        """Return True when the gain moved by more than the threshold."""
        return abs(self.gain_change) > self.threshold


def _reference_hz(r: FloatArray, t: float) -> float:
    x = r - float(np.mean(r))
    power = np.abs(np.fft.rfft(x)) ** 2
    power[0] = 0.0
    k = int(np.argmax(power))
    return float(k / (x.size * t))


def estimate_drift(record: RunRecord, base: StageParams, *, window_s: float = 0.3,
                   threshold: float = 0.05) -> DriftReport:
    """
    Estimate the static gain and the dominant lag of an operation run against the model.

    Parameters
    ----------
    record : RunRecord
        An ordinary tracking run (open or closed loop), gap-free.
    base : StageParams
        The configured stage: signal chain, hysteresis (shape and slope convention) and the
        linear shape the gain is measured through.
    window_s : float
        Length used from the start [s].
    threshold : float
        Relative gain change reported as a change.

    Returns
    -------
    DriftReport

    Raises
    ------
    IdentificationError
        If the command never changes or the run is too short.

    """
    t = sample_time_of(record)
    n = min(len(record), max(int(round(window_s / t)), 16))
    v = applied_voltage(record, base.chain)[:n]
    y = np.asarray(record.position_m, dtype=np.float64)[:n]
    r = np.asarray(record.reference_m, dtype=np.float64)[:n]
    name = str(record.meta.get('bag', record.meta.get('name', '<record>')))
    if not float(np.ptp(v)) > 0.0:
        raise IdentificationError(f'run {name!r}: the command never changes; no drift to '
                                  'estimate')
    h = make_hysteresis(base.hysteresis)
    slope = float(h.slope)
    state = h.rest_state(float(v[0]))
    w = np.empty(n)
    for k, vk in enumerate(v.tolist()):
        state, wk = h.step(state, vk)
        w[k] = float(wk)
    w /= slope  # unit slope: the fitted coefficient is the static gain k_p c
    prior = factors_of(base.plant.third_order)
    configured = prior.gain_m_per_v * slope

    def columns(tau: float) -> FloatArray:
        num, den = _unit_filter(LinearFactors(1.0, prior.omega_n_rad_s, prior.zeta, tau), t)
        zi = signal.lfilter_zi(num, den)
        free, _ = signal.lfilter(num, den, np.zeros(n), zi=zi)
        return np.asarray(np.vstack([signal.lfilter(num, den, w), free]), dtype=np.float64)

    def solve(tau: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        cols = columns(tau)
        sol, *_ = np.linalg.lstsq(cols.T, y, rcond=None)
        coef = np.asarray(sol, dtype=np.float64)
        return coef, np.asarray(y - coef @ cols, dtype=np.float64), cols

    def cost(log_tau: float) -> float:
        _, res, _ = solve(math.exp(log_tau))
        return float(res @ res)

    x0 = math.log(prior.tau_s)
    sol = optimize.minimize_scalar(cost, bracket=(x0 - 0.3, x0 + 0.3), tol=1e-10)
    tau = math.exp(float(sol.x))
    coef, res, cols = solve(tau)
    # standard deviations: Jacobian of the residual in (G0, b, log tau)
    h_step = 1e-4
    _, res_p, _ = solve(tau * math.exp(h_step))
    _, res_m, _ = solve(tau * math.exp(-h_step))
    jac = np.column_stack([-cols.T, (res_p - res_m) / (2.0 * h_step)])
    dof = max(n - 3, 1)
    s2 = float(res @ res) / dof
    norms = np.maximum(np.linalg.norm(jac, axis=0), 1e-300)
    cov = s2 * np.linalg.pinv((jac / norms).T @ (jac / norms)) / np.outer(norms, norms)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    f0 = _reference_hz(r if float(np.ptp(r)) > 0.0 else v, t)

    def lag(tau_s: float) -> float:
        fac = LinearFactors(1.0, prior.omega_n_rad_s, prior.zeta, tau_s)
        g = discrete_frequency_response(third_order_of(fac), t, np.array([max(f0, 1e-3)]))
        return float(-np.degrees(np.angle(g[0])))

    return DriftReport(name=name, window_s=n * t, reference_hz=f0,
                       static_gain_m_per_v=float(coef[0]), static_gain_std=float(sd[0]),
                       configured_gain_m_per_v=configured, tau_s=tau,
                       tau_std=float(tau * sd[2]), configured_tau_s=prior.tau_s,
                       lag_deg=lag(tau), configured_lag_deg=lag(prior.tau_s),
                       residual_rms_m=float(np.sqrt(np.mean(res ** 2))), threshold=threshold)


def drift_lines(report: DriftReport) -> list[str]:
    """
    Return the lines ``identify --drift`` prints for one run.

    Parameters
    ----------
    report : DriftReport
        The estimate.

    Returns
    -------
    list of str

    """
    d = report
    verdict = (f'CHANGED by {100 * d.gain_change:+.1f} % (threshold {100 * d.threshold:g} %)'
               if d.changed else f'unchanged (within {100 * d.threshold:g} %)')
    return [
        f'drift: run {d.name!r}, first {d.window_s:g} s, reference at {d.reference_hz:g} Hz',
        f'DC gain k_p c = {d.static_gain_m_per_v:.5g} m/V +- '
        f'{100 * d.static_gain_std / d.static_gain_m_per_v:.2g} % (1 sigma), configured '
        f'{d.configured_gain_m_per_v:.5g} m/V: {verdict}',
        f'lag at {d.reference_hz:g} Hz: {d.lag_deg:.2f} deg (configured '
        f'{d.configured_lag_deg:.2f} deg), tau = {d.tau_s:.4g} s +- '
        f'{100 * d.tau_std / d.tau_s:.2g} % (configured {d.configured_tau_s:.4g} s, '
        f'{100 * d.tau_change:+.1f} %)',
        f'model residual {d.residual_rms_m * 1e9:.3g} nm rms; not supported by this run: w_n, '
        'zeta (no excitation near the resonance), alpha and B1 (kept as configured)',
    ]
