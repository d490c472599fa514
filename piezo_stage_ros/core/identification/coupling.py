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
Identification of the cross-coupling of a multi-axis stage, one axis excited at a time.

The experiment: one axis (the source i) is driven open loop by a periodic band-limited noise
(:class:`~piezo_stage_ros.core.signals.excitation.NoiseExcitation`, a random-phase multisine)
around its rest voltage while every other axis holds its rest voltage. Open loop, because a
holding axis' controller would reject the coupled displacement it is asked to show: in open loop
what axis j measures beyond its constant rest is the coupling alone (plus sensor noise).

The fit: every coupling path i -> j of the model
(:mod:`piezo_stage_ros.core.model.axes`) is d_j = kappa M(s) x_i, driven by the source's own
position. Both the measured x_i and the displacement on j are linear, time-invariant responses to
the same held hysteresis output w_i, so in periodic steady state the ratio of their DFT lines is
exactly, at every excited line, kappa P(z) / G(z): P the path from w_i to d_j per unit gain and
G the source's own plant, both from the model's exact ZOH discretisation
(:func:`~piezo_stage_ros.core.model.axes.coupling_paths`), whatever the hysteresis does.
The ratio is averaged over whole periods
(:func:`~piezo_stage_ros.core.identification.periodic.periodic_spectra`), and weighted by its
variance from the scatter over the periods (the sensors' white noise pooled over the lines, with
the ADC's quantisation as a floor: without sensor noise a periodic signal quantises the same way
every period, so that error does not average down). The residual's own variance per degree of
freedom scales the bounds, so a floor that is off only moves the weights. kappa enters linearly:
for a fixed mode (f, zeta) it is a weighted linear least squares; (f, zeta) come from a grid and a
nonlinear least-squares refinement over the projected cost. A static path (no mode) is the model
with one parameter; the mode is kept when an F test says its two extra parameters explain the data
(at 1 %). Bounds: +-1.96 sigma from the Jacobian of the weighted residual, as the one-axis fits.

The functions take arrays (time, commands (samples, n), positions (samples, n)) so that recorded
runs can be fed as they are.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.errors import IdentificationError, ParameterError
from piezo_stage_ros.core.contracts.params import param, Params
from piezo_stage_ros.core.contracts.types import ComplexArray, FloatArray
from piezo_stage_ros.core.identification.periodic import (
    detect_period,
    excited_lines,
    periodic_spectra,
)
from piezo_stage_ros.core.identification.support import Z95
from piezo_stage_ros.core.model.axes import (
    AxesStage,
    AxesStageParams,
    coupling_paths,
    CouplingParams,
    DEFAULT_DAMPING,
    state_response,
)
from piezo_stage_ros.core.model.stage import Stage
from piezo_stage_ros.core.signals.excitation import NoiseExcitation, NoiseParams
from scipy import stats
from scipy.optimize import least_squares

__all__ = ['AxesRun', 'CouplingPlan', 'PathFit', 'coupling_model', 'excitation_runs',
           'fit_coupling', 'identified_coupling', 'rest_voltages']

#: Significance of the F test that keeps a mode instead of a static gain.
MODE_SIGNIFICANCE = 0.01


@dataclass(frozen=True)
class CouplingPlan(Params):
    """
    The excitation of one axis at a time (volts around the axis' rest voltage, seconds).

    The default drives a stage of the paper's kind by about 3 um rms on the source axis, flat
    from 10 Hz to 4 kHz (past a coupled mode below the Nyquist frequency of a 10 kHz loop).
    """

    rms_v: float = param(0.8, unit='V', description='Root-mean-square of the noise added to '
                         "the source axis' rest voltage.", low=0.0, low_open=True)
    band_low_hz: float = param(10.0, unit='Hz', description='Lowest excited frequency.',
                               low=0.0, low_open=True)
    band_high_hz: float = param(4000.0, unit='Hz', description='Highest excited frequency '
                                '(below the Nyquist frequency of the loop).', low=0.0,
                                low_open=True)
    period_s: float = param(0.2, unit='s', description='Period of the excitation (line '
                            'spacing 1/period).', low=1e-3, high=100.0)
    periods: int = param(11, unit='-', description='Periods run per axis; the first is the '
                         'transient and left out.', low=3, high=10000)
    seed: int = param(1, unit='-', description='Seed of the random phases.', low=0)


@dataclass(frozen=True)
class AxesRun:
    """
    One experiment on a multi-axis stage, as arrays.

    Attributes
    ----------
    time_s : ndarray, shape (samples,)
        Time of each row [s] (uniform).
    commands_v : ndarray, shape (samples, n)
        Command of each axis held over the sample [V].
    positions_m : ndarray, shape (samples, n)
        Measured position of each axis at the end of the sample [m].
    source : int
        The excited axis.
    initial_m : ndarray, shape (n,), optional
        Measured positions at rest before the first command [m] (y_0), when known: with it the
        run is a sequence of samples as a bag records them (y_k measured at t_k, u_k held over
        [t_k, t_k+1)).

    """

    time_s: FloatArray
    commands_v: FloatArray
    positions_m: FloatArray
    source: int
    initial_m: FloatArray | None = None


@dataclass(frozen=True)
class PathFit:
    """
    The coupling path i -> j identified from one run.

    Attributes
    ----------
    source, target : int
        Driving axis i and moved axis j.
    gain : float
        kappa_ij [m/m].
    resonance_hz : float
        f_ij [Hz]; 0 for a static path.
    damping : float
        zeta_ij [-] (:data:`~piezo_stage_ros.core.model.axes.DEFAULT_DAMPING` for a static path,
        where it has no effect).
    std : dict of str to float
        One standard deviation of ``gain``, ``resonance_hz``, ``damping`` (static: gain only).
    bounds : dict of str to (float, float)
        95 % bounds (+-1.96 sigma) of the same.
    static : bool
        Whether the static model was kept (the F test did not support a mode).
    lines : int
        Excited DFT lines used.
    periods : int
        Whole periods averaged.
    chi2_per_dof : float
        Weighted residual per degree of freedom (about 1 when the model and the noise floor
        explain the data).

    """

    source: int
    target: int
    gain: float
    resonance_hz: float
    damping: float
    std: dict[str, float]
    bounds: dict[str, tuple[float, float]]
    static: bool
    lines: int
    periods: int
    chi2_per_dof: float

    @property
    def shown(self) -> bool:
        """Return whether the gain's 95 % bounds exclude zero (a coupling the data shows)."""
        lo, hi = self.bounds['gain']
        return lo > 0.0 or hi < 0.0


def rest_voltages(stage: AxesStageParams) -> list[float]:
    """Return the voltage that holds each axis at its initial position [V]."""
    out = []
    for p in stage.axes:
        one = Stage(p)
        one.reset()
        out.append(one.applied_voltage_v)
    return out


def excitation_runs(stage: AxesStageParams, plan: CouplingPlan | None = None
                    ) -> list[AxesRun]:
    """
    Run the experiment once per axis on a simulated stage: that axis excited, the others held.

    Parameters
    ----------
    stage : AxesStageParams
        The (true) stage; each run starts at rest at the axes' initial positions.
    plan : CouplingPlan, optional
        The excitation; default :class:`CouplingPlan`.

    Returns
    -------
    list of AxesRun
        One per axis, in axis order.

    Raises
    ------
    ParameterError
        An excitation leaving the source axis' amplifier range, or a band above the Nyquist
        frequency of the loop.

    """
    plan = plan or CouplingPlan()
    t = stage.sample_time_s
    rate = 1.0 / t
    if not plan.band_high_hz < rate / 2.0:
        raise ParameterError('band_high_hz', plan.band_high_hz,
                             f'< {rate / 2.0:g} Hz (the Nyquist frequency of the loop)')
    samples = int(round(plan.period_s * rate)) * plan.periods
    time_s = np.arange(samples, dtype=np.float64) * t
    holds = rest_voltages(stage)
    out = []
    for i in range(stage.n):
        chain = stage.axes[i].chain
        noise = NoiseExcitation(NoiseParams(
            offset_m=holds[i], amplitude_m=plan.rms_v, band_low_hz=plan.band_low_hz,
            band_high_hz=plan.band_high_hz, period_s=plan.period_s, grid_rate_hz=2.0 * rate,
            seed=plan.seed))
        low, high = noise.extent_m
        if low < chain.amplifier_min_v or high > chain.amplifier_max_v:
            raise ParameterError('rms_v', plan.rms_v, 'an excitation within the amplifier '
                                 f'range [{chain.amplifier_min_v:g}, '
                                 f'{chain.amplifier_max_v:g}] V of axis {stage.names[i]!r}',
                                 f'reaches [{low:.3g}, {high:.3g}] V around the rest voltage '
                                 f'{holds[i]:.3g} V')
        cmds = np.tile(np.asarray(holds, dtype=np.float64), (samples, 1))
        cmds[:, i] = noise.evaluate(time_s)[0]
        sim = AxesStage(stage)
        initial = np.asarray(sim.reset(), dtype=np.float64)
        out.append(AxesRun(time_s=time_s, commands_v=cmds,
                           positions_m=sim.run_open_loop(cmds), source=i, initial_m=initial))
    return out


def coupling_model(design: AxesStageParams, source: int, target: int, resonance_hz: float,
                   damping: float, frequency_hz: Any) -> ComplexArray:
    """
    Return P(z) / G(z) per unit gain: the sampled displacement of ``target`` per sampled x_i.

    Parameters
    ----------
    design : AxesStageParams
        The axes (the source's plant enters through the samples between the measurements).
    source, target : int
        The path i -> j.
    resonance_hz, damping : float
        The mode (0 Hz: static, the ratio is 1).
    frequency_hz : array_like
        Frequencies of the lines [Hz].

    Returns
    -------
    ndarray of complex

    """
    n = design.n
    gain = [0.0] * (n * n)
    res = [0.0] * (n * n)
    damp = [DEFAULT_DAMPING] * (n * n)
    gain[source * n + target] = 1.0
    res[source * n + target] = resonance_hz
    damp[source * n + target] = damping
    p = AxesStageParams(names=design.names, axes=design.axes, coupling=CouplingParams(
        gain=tuple(gain), resonance_hz=tuple(res), damping=tuple(damp)))
    path = coupling_paths(p)[0]
    omega = 2.0 * math.pi * np.atleast_1d(np.asarray(frequency_hz, dtype=np.float64))
    z = np.exp(1j * omega * path.sample_time_s)
    states = state_response(path.ad_full, path.bd_full, z)
    own = states[:, :path.c.size] @ path.c
    moved = path.frequency_response(target, omega, discrete=True)
    return np.asarray(moved / own, dtype=np.complex128)


def _check_arrays(time_s: Any, commands_v: Any, positions_m: Any, n: int
                  ) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    t = np.asarray(time_s, dtype=np.float64)
    u = np.asarray(commands_v, dtype=np.float64)
    y = np.asarray(positions_m, dtype=np.float64)
    if t.ndim != 1 or t.size < 4:
        raise ParameterError('time_s', f'shape {t.shape}', 'a 1-d array of at least 4 times')
    for name, a in (('commands_v', u), ('positions_m', y)):
        if a.shape != (t.size, n):
            raise ParameterError(name, f'shape {a.shape}', f'shape ({t.size}, {n}): one row '
                                 f'per time, one column per axis')
        if not np.all(np.isfinite(a)):
            raise ParameterError(name, 'non-finite values', 'finite values')
    steps = np.diff(t)
    dt = float(np.median(steps))
    if not dt > 0.0 or np.max(np.abs(steps - dt)) > 1e-6 * dt:
        raise ParameterError('time_s', f'steps {float(steps.min()):g} ... '
                             f'{float(steps.max()):g} s', 'uniform, increasing times')
    return t, u, y, dt


def _excited_axis(u: FloatArray, source: int | None, n: int) -> int:
    varies = [int(k) for k in range(n) if float(np.ptp(u[:, k])) > 0.0]
    if source is None:
        if len(varies) != 1:
            raise ParameterError('commands_v', f'axes {varies} vary',
                                 'exactly one excited axis, the others held constant')
        return varies[0]
    if not 0 <= source < n:
        raise ParameterError('source', source, f'an axis index in [0, {n - 1}]')
    if source not in varies:
        raise ParameterError('source', source, 'an axis whose command varies (the excited '
                             'one)', f'was not excited: its command is constant; varying: '
                             f'{varies}')
    others = [k for k in varies if k != source]
    if others:
        raise ParameterError('commands_v', f'axes {others} vary besides the source {source}',
                             'the other axes held constant')
    return source


def _resolution(y: FloatArray) -> float:
    """
    Return the finest step the data resolves [m].

    The smallest step between distinct values: the ADC step of quantised data; at least the
    floating-point spacing of the values (a constant signal: nothing finer is resolved).
    """
    steps = np.diff(np.unique(y))
    spacing = float(np.spacing(np.max(np.abs(y)))) if y.size else 0.0
    return max(float(steps.min()) if steps.size else 0.0, spacing, 1e-300)


def fit_coupling(time_s: Any, commands_v: Any, positions_m: Any, design: AxesStageParams, *,
                 source: int | None = None, targets: Sequence[int] | None = None,
                 period_samples: int | None = None, skip_periods: int = 1,
                 max_resonance_hz: float | None = None) -> list[PathFit]:
    """
    Fit the coupling paths from the excited axis to the others from one run.

    Parameters
    ----------
    time_s : array_like, shape (samples,)
        Uniform sample times [s].
    commands_v : array_like, shape (samples, n)
        Commands [V]: one axis excited by a periodic signal, the others constant.
    positions_m : array_like, shape (samples, n)
        Measured positions [m], row k at the end of command row k's sample.
    design : AxesStageParams
        The axes (names, plants; the coupling there is not used): the exact discretisation of
        each path needs the source's plant between the samples.
    source : int, optional
        The excited axis (default: the one whose command varies).
    targets : sequence of int, optional
        Moved axes to fit (default: every other axis).
    period_samples : int, optional
        Period of the excitation (default: detected from the command).
    skip_periods : int
        Whole periods left out at the start (the transient).
    max_resonance_hz : float, optional
        Highest resonance searched (default: 0.45 of the sample rate).

    Returns
    -------
    list of PathFit
        One per target, in the order given.

    Raises
    ------
    ParameterError
        Arrays of the wrong shape or not finite, times not uniform or not at the design's
        rate, no or several excited axes, a source that was not excited, a bad target.
    IdentificationError
        A command that does not repeat, or fewer than two whole periods after the transient.

    """
    n = design.n
    t, u, y, dt = _check_arrays(time_s, commands_v, positions_m, n)
    if abs(dt - design.sample_time_s) > 1e-6 * design.sample_time_s:
        raise ParameterError('time_s', f'sample time {dt:g} s',
                             f"the design's sample time {design.sample_time_s:g} s")
    src = _excited_axis(u, source, n)
    tgt = [k for k in range(n) if k != src] if targets is None else list(targets)
    for k in tgt:
        if not (isinstance(k, (int, np.integer)) and 0 <= k < n and k != src):
            raise ParameterError('targets', list(tgt), f'axis indices in [0, {n - 1}] other '
                                 f'than the source {src}')
    period = period_samples or detect_period(u[:, src], tolerance=1e-9)
    if period is None:
        raise IdentificationError(f'the command of axis {design.names[src]!r} does not repeat: '
                                  'a periodic excitation (at least two whole periods) is needed')
    top = max_resonance_hz or 0.45 / dt
    out = []
    for j in tgt:
        try:
            spectra = periodic_spectra(y[:, src], y[:, j], u[:, src], period, dt,
                                       skip_periods=skip_periods)
        except ValueError as exc:
            raise IdentificationError(str(exc)) from None
        used = excited_lines(spectra.r)
        count, p = spectra.periods, period
        window = y[len(y) - count * p:]
        if float(np.ptp(window[:, j])) == 0.0:
            # nothing moved axis j by one step of its sensor: the gain is below that step over
            # the source's travel, and nothing else can be said
            chain = design.axes[j].chain
            step = chain.adc_lsb_m if chain.quantize else _resolution(window[:, j])
            half = step / max(float(np.ptp(window[:, src])), 1e-300)
            out.append(PathFit(source=src, target=int(j), gain=0.0, resonance_hz=0.0,
                               damping=DEFAULT_DAMPING, std={'gain': half / Z95},
                               bounds={'gain': (-half, half)}, static=True,
                               lines=int(used.sum()), periods=count, chi2_per_dof=0.0))
            continue
        # the quantisation error of a periodic signal repeats every period unless noise dithers
        # it: it does not average down, so its floor is one period's
        floor_y = p * _resolution(y[:, j]) ** 2 / 12.0
        floor_u = p * _resolution(y[:, src]) ** 2 / 12.0
        f = spectra.frequency_hz[used]
        xu, xy = spectra.u[used], spectra.y[used]
        g = xy / xu
        # the sensors' noise is white: its variance is pooled over the lines, so that a line
        # whose few periods happen to scatter little does not get a weight it has not earned
        var_y = max(float(np.mean(spectra.var_y[used])), floor_y)
        var_u = max(float(np.mean(spectra.var_u[used])), floor_u)
        var = (var_y + np.abs(g) ** 2 * var_u) / np.abs(xu) ** 2
        # var is E|error|^2 of a complex line: its real and imaginary parts hold half each
        out.append(_fit_path(design, src, int(j), f, g, np.sqrt(2.0 / var), top, count))
    return out


def _fit_path(design: AxesStageParams, i: int, j: int, f: FloatArray, g: ComplexArray,
              weight: FloatArray, top_hz: float, periods: int) -> PathFit:
    def model(res_hz: float, zeta: float) -> ComplexArray:
        return coupling_model(design, i, j, res_hz, zeta, f)

    def project(h: ComplexArray) -> tuple[float, FloatArray]:
        wh = weight * h
        kappa = float(np.sum(np.real(np.conj(wh) * weight * g)) / np.sum(np.abs(wh) ** 2))
        r = weight * (g - kappa * h)
        return kappa, np.concatenate([r.real, r.imag])

    def projected(x: FloatArray) -> FloatArray:
        return project(model(math.exp(x[0]), math.exp(x[1])))[1]

    def full(x: FloatArray) -> FloatArray:
        r = weight * (g - x[0] * model(x[1], x[2]))
        return np.concatenate([r.real, r.imag])

    m = 2 * f.size
    kappa_s, r_s = project(np.ones(f.size, dtype=np.complex128))
    rss_s = float(r_s @ r_s)
    best = (math.inf, 0.0, 0.0)
    low_hz = max(float(f.min()), 1.0)
    # a coarse grid, plus the line where the ratio peaks (a light mode's resonance)
    peak = float(f[int(np.argmax(np.abs(g) * (f <= top_hz)))])
    for fr in np.append(np.geomspace(low_hz, top_hz, 20), peak):
        for zeta in np.geomspace(0.005, 1.0, 6):
            r = projected(np.log([fr, zeta]))
            cost = float(r @ r)
            if cost < best[0]:
                best = (cost, float(fr), float(zeta))
    sol = least_squares(projected, np.log([best[1], best[2]]),
                        bounds=(np.log([low_hz / 2.0, 1e-4]), np.log([top_hz, 10.0])),
                        x_scale=1.0, xtol=1e-12, ftol=1e-12)
    res_hz, zeta = math.exp(float(sol.x[0])), math.exp(float(sol.x[1]))
    kappa_m, r_m = project(model(res_hz, zeta))
    rss_m = float(r_m @ r_m)
    dof_m = max(m - 3, 1)
    f_stat = ((rss_s - rss_m) / 2.0) / (rss_m / dof_m) if rss_m > 0.0 else math.inf
    keep_mode = bool(f_stat > stats.f.ppf(1.0 - MODE_SIGNIFICANCE, 2, dof_m))
    if keep_mode:
        x = np.array([kappa_m, res_hz, zeta])
        jac = _jacobian(full, x)
        s2 = rss_m / dof_m
        cov = s2 * np.linalg.pinv(jac.T @ jac)
        std = {k: float(math.sqrt(max(cov[q, q], 0.0)))
               for q, k in enumerate(('gain', 'resonance_hz', 'damping'))}
        values = {'gain': kappa_m, 'resonance_hz': res_hz, 'damping': zeta}
        chi2 = s2
    else:
        wsum = float(np.sum(weight ** 2))
        s2 = rss_s / max(m - 1, 1)
        std = {'gain': math.sqrt(s2 / wsum)}
        values = {'gain': kappa_s}
        chi2 = s2
    bounds = {k: (values[k] - Z95 * s, values[k] + Z95 * s) for k, s in std.items()}
    return PathFit(source=i, target=j, gain=values['gain'],
                   resonance_hz=values.get('resonance_hz', 0.0),
                   damping=values.get('damping', DEFAULT_DAMPING), std=std, bounds=bounds,
                   static=not keep_mode, lines=int(f.size), periods=periods,
                   chi2_per_dof=float(chi2))


def _jacobian(fun: Any, x: FloatArray) -> FloatArray:
    """Return the central-difference Jacobian of ``fun`` at ``x`` (relative steps)."""
    cols = []
    for q in range(x.size):
        h = 1e-6 * max(abs(float(x[q])), 1e-12)
        xp, xm = x.copy(), x.copy()
        xp[q] += h
        xm[q] -= h
        cols.append((fun(xp) - fun(xm)) / (2.0 * h))
    return np.asarray(np.stack(cols, axis=1), dtype=np.float64)


def identified_coupling(design: AxesStageParams, fits: Sequence[PathFit]) -> CouplingParams:
    """
    Return the coupling matrices of the fits: a path the data does not show is zero.

    Parameters
    ----------
    design : AxesStageParams
        The axes (their number and rate).
    fits : sequence of PathFit
        At most one per path.

    Returns
    -------
    CouplingParams
        Gain, resonance and damping row-major (row i: the driving axis); the design's sensor
        cross-talk kept (not identified).

    """
    n = design.n
    gain = np.zeros((n, n))
    res = np.zeros((n, n))
    damp = np.full((n, n), DEFAULT_DAMPING)
    for fit in fits:
        if fit.shown:
            gain[fit.source, fit.target] = fit.gain
            res[fit.source, fit.target] = fit.resonance_hz
            damp[fit.source, fit.target] = fit.damping
    out = CouplingParams(gain=tuple(float(v) for v in gain.ravel()),
                         resonance_hz=tuple(float(v) for v in res.ravel()),
                         damping=tuple(float(v) for v in damp.ravel()),
                         sensor_crosstalk=design.coupling.sensor_crosstalk)
    out.matrices(n, 1.0 / design.sample_time_s)
    return out
