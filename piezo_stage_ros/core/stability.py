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
Stability of the linearized discrete-time loop: controller + ZOH plant at the sample rate.

The loop is built exactly as it runs (see :mod:`piezo_stage_ros.core.interfaces`): the
controller sees y_k and returns u_k, which the plant holds over [t_k, t_k+1) (optionally after
``delay_samples`` more samples of computational delay). With the hysteresis replaced by a
gain (its local slope dw/dv) and the controller by its linear part, the loop transfer at the
plant input is::

    L(z) = z^-delay * N(z) * C(z) * slope * K_PSCM * G(z)

with G(z) the ZOH discretization of the plant model from w [V] to x [m]
(:meth:`piezo_stage_ros.core.linear.LinearPlant.discretize`), N(z) the notch filter and C(z) the
controller from sensor volts to the command (negative feedback)::

    PI:   C(z) = k_p + k_i T z/(z - 1)
    RAC:  C(z) = (k + phi_hat lambda - theta_hat) + k lambda T z/(z - 1)

where, for the RAC, k = k_d + k*/epsilon inside the boundary layer (|s| < epsilon) and k = k_d
outside it (there sat(s/epsilon) = +-1 is a constant); theta_hat and phi_hat are frozen. The
+theta_hat y term of eq. (36) is positive feedback and -phi_hat lambda e adds proportional gain.

The verdict covers every combination of: hysteresis slope on a grid over
``[slope_min, slope_max]`` (for eq. (21) the incremental slope dw/dv lies in [2 B1 - c, c]),
the RAC estimates at the four corners of their projection bounds and at their initial values
(Theorem 1 only keeps them inside the bounds, so every value inside must be safe; they enter the
linear loop only through its proportional gain, which is affine in them, so the corners give its
extremes) or only at their initial values, and both RAC regions. The loop is stable when
every closed-loop pole (root of den_L(z) + num_L(z)) lies strictly inside the unit circle.

The RAC's adaptation is a second, discrete loop (:func:`adaptation_bound`): outside the boundary
layer the Euler updates theta_hat += -T gamma y s_eps and phi_hat += -T eta u_fd s_eps move the
command by q = y d(theta_hat) + u_fd d(phi_hat), and with the regressors y, u_fd frozen::

    (z - 1) q = -g H(z) q,    g = T (gamma y^2 + eta u_fd^2)

where H(z) is the response of s to an additive command disturbance in the loop above (k = k_d,
H(1) = 1/k_d). Every root must lie inside the unit circle: g < g_crit, the smallest critical
gain over the cases. The report says whether the configured rates keep g at the largest
regressors the stage can produce (y_max: the largest output the command range can hold on the
model; u_fd: lambda y_max, a reference step across that range) below g_crit / 2.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Sequence
import warnings

import numpy as np
from numpy.typing import NDArray
from piezo_stage_ros.core.controllers import ControllerParams, notch_design
from piezo_stage_ros.core.errors import ParameterError, StabilityError
from piezo_stage_ros.core.linear import LinearPlant, third_order_plant
from piezo_stage_ros.core.params import group, param, Params
from piezo_stage_ros.core.stage import linear_plant, PlantParams
from piezo_stage_ros.core.types import FloatArray

__all__ = ['ADAPTATION_MARGIN', 'AdaptationBound', 'LoopCase', 'StabilityParams',
           'StabilityReport', 'StabilityWarning', 'adaptation_bound', 'check_stability',
           'enforce', 'loop_polynomials', 'stability_plant']


#: Required ratio g_crit / g of the adaptation loop (a gain margin of 6 dB).
ADAPTATION_MARGIN = 2.0


class StabilityWarning(UserWarning):
    """Warned when a configured loop is not stable on the configured model (action 'warn')."""


@dataclass(frozen=True)
class StabilityParams(Params):
    """Options of the stability check run before every closed-loop run."""

    action: str = param('warn', unit='-', description='On an unstable verdict: warn loudly and '
                        'run anyway, or refuse to run.', choices=('warn', 'refuse'))
    estimates: str = param('corners', unit='-', description='RAC estimates checked: the four '
                           'corners of their projection bounds and the initial values, or the '
                           'initial values only.',
                           choices=('corners', 'initial'))
    slope_min: float = param(0.8843, unit='-', description='Smallest hysteresis slope dw/dv '
                             '(2 B1 - c for the default backlash-like model).', low=0.0,
                             low_open=True)
    slope_max: float = param(1.0341, unit='-', description='Largest hysteresis slope dw/dv '
                             '(c for the default backlash-like model).', low=0.0, low_open=True)
    slope_points: int = param(5, unit='-', description='Slopes checked, evenly spaced over '
                              '[slope_min, slope_max].', low=1, high=101)
    delay_samples: int = param(0, unit='-', description='Extra computational delay of the loop '
                               '(0: u_k is applied at t_k).', low=0, high=10)
    design_model: str = param('plant', unit='-', description='Model the check and a notch in '
                              'model mode use: plant takes plant.* of the plant_node section of '
                              'the same parameter files, own takes stability.plant.* (a real '
                              'stage: the identified model).', choices=('plant', 'own'),
                              read_only=True)
    plant: PlantParams = group(PlantParams, 'own design model (design_model: own)')

    def _check(self) -> None:
        if self.slope_max < self.slope_min:
            raise ParameterError('slope_max', self.slope_max, f'>= slope_min = {self.slope_min:g}',
                                 'is below the smallest slope')

    def slopes(self) -> tuple[float, ...]:
        """Return the hysteresis slopes to check."""
        if self.slope_points == 1 or self.slope_max == self.slope_min:
            return (0.5 * (self.slope_min + self.slope_max),)
        return tuple(float(s) for s in np.linspace(self.slope_min, self.slope_max,
                                                   self.slope_points))


@dataclass(frozen=True)
class LoopCase:
    """
    One linearized loop and what the check found.

    Attributes
    ----------
    label : str
        What was frozen, e.g. ``'RAC inside boundary layer, theta=4, phi=0.005, slope=1.03'``.
    slope : float
        Hysteresis slope dw/dv.
    spectral_radius : float
        Largest |closed-loop pole|; < 1 is stable.
    gain_margin_db : float
        Over the phase crossovers, the gain margin closest to 0 dB [dB], signed (negative: the
        loop gain exceeds one there); inf when there is no crossover.
    phase_margin_deg : float
        Over the gain crossovers, the phase margin 180 deg + phase (wrapped to (-180, 180])
        closest to 0 [deg]; inf when there is no crossover.
    poles : ndarray
        Closed-loop poles in z.

    """

    label: str
    slope: float
    spectral_radius: float
    gain_margin_db: float
    phase_margin_deg: float
    poles: NDArray[np.complex128] = field(repr=False)

    @property
    def stable(self) -> bool:
        """Return whether every closed-loop pole is inside the unit circle."""
        return self.spectral_radius < 1.0


@dataclass(frozen=True)
class AdaptationBound:
    """
    The discrete adaptation loop of the RAC at its largest regressors (module docstring).

    Attributes
    ----------
    gamma : float
        Configured adaptation rate of theta_hat [1/(V^2 s)].
    eta : float
        Configured adaptation rate of phi_hat [s/V^2].
    sample_time_s : float
        Sample period T [s].
    y_max_v : float
        Largest sensor output the command range can hold on the model,
        K_PSCM |G(1)| (slope_max max(|u_min|, |u_max|) + rho) [V].
    u_fd_max_v_per_s : float
        Largest regressor of phi_hat taken, lambda y_max (a reference step across the whole
        reachable range, seen at once by the error) [V/s].
    critical_gain : float
        g_crit: smallest per-sample gain T (gamma y^2 + eta u_fd^2) that puts a root of
        (z - 1) + g H(z) on the unit circle, over the cases [-]; 0 when a frozen loop is
        already unstable, inf when no gain up to 1e4 does.
    worst_label : str
        The case that sets ``critical_gain``.

    """

    gamma: float
    eta: float
    sample_time_s: float
    y_max_v: float
    u_fd_max_v_per_s: float
    critical_gain: float
    worst_label: str

    @property
    def gain(self) -> float:
        """Return g = T (gamma y_max^2 + eta u_fd_max^2), the per-sample gain [-]."""
        return self.sample_time_s * (self.gamma * self.y_max_v ** 2
                                     + self.eta * self.u_fd_max_v_per_s ** 2)

    @property
    def ok(self) -> bool:
        """Return whether g <= g_crit / ADAPTATION_MARGIN."""
        return self.gain * ADAPTATION_MARGIN <= self.critical_gain

    def max_gamma(self, eta: float | None = None) -> float:
        """
        Return the largest gamma that keeps the bound with the given eta [1/(V^2 s)].

        Parameters
        ----------
        eta : float, optional
            Adaptation rate of phi_hat [s/V^2]; default the configured one.

        Returns
        -------
        float
            (g_crit / ADAPTATION_MARGIN / T - eta u_fd_max^2) / y_max^2, at least 0.

        """
        e = self.eta if eta is None else eta
        budget = self.critical_gain / ADAPTATION_MARGIN / self.sample_time_s
        return max((budget - e * self.u_fd_max_v_per_s ** 2) / self.y_max_v ** 2, 0.0)

    def text(self) -> str:
        """Return one sentence: the per-sample gain against the bound."""
        head = (f'Adaptation: T (gamma y_max^2 + eta u_fd_max^2) = {self.gain:.3g} at y_max = '
                f'{self.y_max_v:.2f} V, u_fd_max = lambda y_max = '
                f'{self.u_fd_max_v_per_s:.3g} V/s; discrete bound g_crit = '
                f'{self.critical_gain:.3g} ({self.worst_label})')
        if self.ok:
            return head + f', within g_crit/{ADAPTATION_MARGIN:g}.'
        return (head + f': ABOVE g_crit/{ADAPTATION_MARGIN:g}, the estimates can limit-cycle '
                'between their bounds on a plateau or after a step; lower gamma (at most '
                f'{self.max_gamma():.3g} with this eta) or eta.')


@dataclass(frozen=True)
class StabilityReport:
    """
    Verdict over every case of one controller configuration on one plant model.

    Attributes
    ----------
    controller : str
        Short description of the controller configuration.
    plant : str
        Plant model name.
    sample_time_s : float
        Sample period [s].
    cases : tuple of LoopCase
        Every loop checked.
    adaptation : AdaptationBound or None
        The discrete adaptation loop of a RAC (None for the other controllers); it does not
        enter the verdict :attr:`stable` (see :func:`enforce`).

    """

    controller: str
    plant: str
    sample_time_s: float
    cases: tuple[LoopCase, ...]
    adaptation: AdaptationBound | None = None

    @property
    def stable(self) -> bool:
        """Return whether every case is stable."""
        return all(c.stable for c in self.cases)

    @property
    def worst(self) -> LoopCase:
        """Return the case with the largest spectral radius."""
        return max(self.cases, key=lambda c: c.spectral_radius)

    @property
    def spectral_radius(self) -> float:
        """Return the largest spectral radius over the cases."""
        return self.worst.spectral_radius

    @property
    def gain_margin_db(self) -> float:
        """Return the gain margin closest to 0 dB over the cases [dB]."""
        return min((c.gain_margin_db for c in self.cases), key=abs)

    @property
    def phase_margin_deg(self) -> float:
        """Return the phase margin closest to 0 deg over the cases [deg]."""
        return min((c.phase_margin_deg for c in self.cases), key=abs)

    def text(self) -> str:
        """Return a one-paragraph human-readable report."""
        w = self.worst
        rate = 1.0 / self.sample_time_s
        unstable = [c for c in self.cases if not c.stable]
        head = (f'{self.controller} on the {self.plant} model at {rate:g} Hz: '
                f'{"STABLE" if self.stable else "UNSTABLE"} '
                f'({len(self.cases) - len(unstable)}/{len(self.cases)} linearized loops '
                f'stable).')
        worst = (f' Worst case: {w.label}: spectral radius {w.spectral_radius:.4f}, gain '
                 f'margin {_fmt(w.gain_margin_db)} dB, phase margin '
                 f'{_fmt(w.phase_margin_deg)} deg.')
        margins = (f' Over all cases: smallest gain margin {_fmt(self.gain_margin_db)} dB, '
                   f'smallest phase margin {_fmt(self.phase_margin_deg)} deg (closest to 0).')
        extra = '' if self.adaptation is None else ' ' + self.adaptation.text()
        if self.stable:
            return head + worst + margins + extra
        pole = w.poles[int(np.argmax(np.abs(w.poles)))]
        freq = abs(math.atan2(pole.imag, pole.real)) / (2.0 * math.pi * self.sample_time_s)
        advice = (f' The dominant closed-loop pole z = {pole.real:.4f}{pole.imag:+.4f}j lies '
                  f'outside the unit circle (oscillation near {freq:.0f} Hz): lower the '
                  'feedback gain (RAC: raise epsilon or lower k_d; PI: lower k_p/k_i), tighten '
                  'the projection bounds, or add a notch filter against a resonance.')
        return head + worst + advice + extra


def _fmt(value: float) -> str:
    return 'inf' if math.isinf(value) else f'{value:.1f}'


def stability_plant(plant_params: PlantParams) -> LinearPlant:
    """
    Return the single-input plant model (w [V] to x [m]) the check uses.

    Parameters
    ----------
    plant_params : PlantParams
        Model choice; the general electromechanical model is replaced by its third-order
        transfer function from v_in (hysteresis H = 0), eqs. (17)-(18).

    Returns
    -------
    LinearPlant

    """
    if plant_params.model == 'electromechanical':
        return third_order_plant(plant_params.electromechanical.third_order())
    return linear_plant(plant_params)


def _plant_tf(plant: LinearPlant, sample_time_s: float) -> tuple[FloatArray, FloatArray]:
    """Return (num, den) of the ZOH G(z) from w [V] to x [m], powers of z, highest first."""
    from scipy.signal import ss2tf
    d = plant.discretize(sample_time_s)
    num, den = ss2tf(d.ad, d.bd[:, :1], d.c[None, :], np.zeros((1, 1)))
    num = np.asarray(num, dtype=np.float64).ravel()
    return num, np.asarray(den, dtype=np.float64).ravel()


def _controller_cases(params: ControllerParams, estimates: str
                      ) -> list[tuple[str, float, float]]:
    """Return (label, proportional gain [V/V], integral gain [1/s]) of each linear controller."""
    if params.type == 'pi':
        p = params.pi
        return [(f'PI k_p={p.k_p:g}, k_i={p.k_i:g}', p.k_p, p.k_i)]
    if params.type == 'open_loop':
        return [('open loop', 0.0, 0.0)]
    r = params.rac
    if estimates == 'corners':
        # the estimates enter only through the proportional gain, affine in them: the corners
        # give its extremes; the initial pair is checked too (the loop the run starts with)
        pairs = [(t, f) for t in (r.theta_min, r.theta_max) for f in (r.phi_min, r.phi_max)]
        pairs.append((r.theta_init, r.phi_init))
    else:
        pairs = [(r.theta_init, r.phi_init)]
    out = []
    for region, k in (('inside', r.k_d + r.k_star_v / r.epsilon_v), ('outside', r.k_d)):
        for theta, phi in pairs:
            label = (f'RAC {region} boundary layer (k={k:g}), theta_hat={theta:g}, '
                     f'phi_hat={phi:g}')
            out.append((label, k + phi * r.lambda_per_s - theta, k * r.lambda_per_s))
    return out


def loop_polynomials(kp: float, ki: float, gain: float, plant_num: FloatArray,
                     plant_den: FloatArray, sample_time_s: float,
                     notch: tuple[Sequence[float], Sequence[float]] | None = None,
                     delay_samples: int = 0) -> tuple[FloatArray, FloatArray]:
    """
    Return (num, den) of the loop transfer L(z), powers of z, highest first.

    Parameters
    ----------
    kp : float
        Proportional gain of C(z) [V/V].
    ki : float
        Integral gain [1/s]; C(z) = kp + ki T z/(z - 1) (backward rectangle).
    gain : float
        Static gain between plant output and controller input times the hysteresis slope
        (K_PSCM * slope) [V/m].
    plant_num, plant_den : ndarray
        G(z) [m/V].
    sample_time_s : float
        T [s].
    notch : tuple, optional
        ``((b0, b1, b2), (1, a1, a2))`` of the notch filter.
    delay_samples : int
        Extra samples of delay.

    Returns
    -------
    num, den : ndarray

    """
    if ki != 0.0:
        # C(z) = ((kp + ki T) z - kp) / (z - 1)
        c_num = np.array([kp + ki * sample_time_s, -kp])
        c_den = np.array([1.0, -1.0])
    else:
        c_num = np.array([kp])
        c_den = np.array([1.0])
    num = np.convolve(c_num * gain, plant_num)
    den = np.convolve(c_den, plant_den)
    if notch is not None:
        num = np.convolve(num, np.asarray(notch[0], dtype=np.float64))
        den = np.convolve(den, np.asarray(notch[1], dtype=np.float64))
    if delay_samples:
        den = np.convolve(den, np.r_[1.0, np.zeros(delay_samples)])
    return np.asarray(num, dtype=np.float64), np.asarray(den, dtype=np.float64)


def _unit_circle(sample_time_s: float) -> NDArray[np.complex128]:
    """Return z = exp(j w T) on a log grid from 1e-4 of Nyquist up to (just below) Nyquist."""
    omega = np.geomspace(1e-4, 1.0, 10001) * math.pi / sample_time_s
    omega[-1] = math.pi / sample_time_s * (1.0 - 1e-9)
    return np.asarray(np.exp(1j * omega * sample_time_s), dtype=np.complex128)


def _margins(lz: NDArray[np.complex128], num: FloatArray, den: FloatArray
             ) -> tuple[float, float]:
    """Return the gain and phase margins of L(z) = num/den closest to zero [dB], [deg]."""
    mag = np.abs(lz)
    phase = np.unwrap(np.angle(lz))
    gm = math.inf
    pm = math.inf
    # gain crossovers |L| = 1: phase margin = 180 deg + phase, wrapped to (-180, 180]
    cross = np.flatnonzero(np.diff(np.sign(mag - 1.0)) != 0)
    for i in cross:
        f = (1.0 - mag[i]) / (mag[i + 1] - mag[i])
        ph = phase[i] + f * (phase[i + 1] - phase[i])
        pm = min(pm, _wrap_deg(math.degrees(ph) + 180.0), key=abs)
    # phase crossovers (phase = -180 deg modulo 360): gain margin = -20 log10 |L|
    shifted = (phase + math.pi) / (2.0 * math.pi)
    k = np.floor(shifted)
    idx = np.flatnonzero(np.diff(k) != 0)
    for i in idx:
        target = max(k[i], k[i + 1]) * 2.0 * math.pi - math.pi
        f = (target - phase[i]) / (phase[i + 1] - phase[i])
        m = float(mag[i] + f * (mag[i + 1] - mag[i]))
        gm = min(gm, -20.0 * math.log10(max(m, 1e-300)), key=abs)
    # at Nyquist L(-1) is real: a negative value is a phase crossover the grid can miss
    l_nyq = float(np.polyval(num, -1.0) / np.polyval(den, -1.0))
    if l_nyq < 0.0:
        gm = min(gm, -20.0 * math.log10(max(abs(l_nyq), 1e-300)), key=abs)
    return gm, pm


def _wrap_deg(angle: float) -> float:
    """Wrap an angle to (-180, 180] degrees."""
    a = (angle + 180.0) % 360.0 - 180.0
    return 180.0 if a == -180.0 else a


def _loop_parts(controller_params: ControllerParams, plant_params: PlantParams,
                sample_time_s: float, options: StabilityParams | None
                ) -> tuple[StabilityParams, LinearPlant, FloatArray, FloatArray,
                           tuple[tuple[float, float, float], tuple[float, float, float]] | None]:
    """Return the options, the plant model, G(z) (num, den) and the notch design of a check."""
    if not (sample_time_s > 0.0 and math.isfinite(sample_time_s)):
        raise ParameterError('sample_time_s', sample_time_s, '(0, inf)')
    opts = options if options is not None else StabilityParams()
    plant = stability_plant(plant_params)
    g_num, g_den = _plant_tf(plant, sample_time_s)
    return opts, plant, g_num, g_den, notch_design(controller_params.notch, sample_time_s, plant)


def check_stability(controller_params: ControllerParams, plant_params: PlantParams,
                    sample_time_s: float, *, options: StabilityParams | None = None
                    ) -> StabilityReport:
    """
    Check the linearized discrete-time loop of a controller on a plant model.

    Parameters
    ----------
    controller_params : ControllerParams
        Controller configuration (type, gains, bounds, notch).
    plant_params : PlantParams
        Plant model the check uses (its ``model`` field chooses it).
    sample_time_s : float
        Sample period T [s], > 0.
    options : StabilityParams, optional
        Slopes, estimates and delay to check; default :class:`StabilityParams` (its own
        ``plant`` group is ignored here: ``plant_params`` is used).

    Returns
    -------
    StabilityReport
        Closed-loop poles, spectral radius and margins of every case, and the verdict.

    """
    opts, plant, g_num, g_den, notch = _loop_parts(controller_params, plant_params,
                                                   sample_time_s, options)
    # frequency response of everything but the controller, once: G(z) N(z) z^-delay
    z = _unit_circle(sample_time_s)
    rest = np.polyval(g_num, z) / np.polyval(g_den, z) * z ** (-float(opts.delay_samples))
    if notch is not None:
        rest = rest * np.polyval(notch[0], z) / np.polyval(notch[1], z)
    cases: list[LoopCase] = []
    for label, kp, ki in _controller_cases(controller_params, opts.estimates):
        for slope in opts.slopes():
            gain = controller_params.sensor_gain_v_per_m * slope
            num, den = loop_polynomials(kp, ki, gain, g_num, g_den, sample_time_s, notch,
                                        opts.delay_samples)
            n = max(len(num), len(den))
            char = np.pad(den, (n - len(den), 0)) + np.pad(num, (n - len(num), 0))
            poles = np.roots(char).astype(np.complex128)
            radius = float(np.max(np.abs(poles))) if poles.size else 0.0
            if kp == 0.0 and ki == 0.0:
                gm, pm = math.inf, math.inf
            else:
                lz = gain * (kp + ki * sample_time_s * z / (z - 1.0)) * rest
                gm, pm = _margins(lz, num, den)
            cases.append(LoopCase(label=f'{label}, slope={slope:.4g}', slope=slope,
                                  spectral_radius=radius, gain_margin_db=gm,
                                  phase_margin_deg=pm, poles=poles))
    desc = {'rac': 'RAC', 'pi': 'PI', 'open_loop': 'open loop'}[controller_params.type]
    if controller_params.notch.mode != 'off':
        desc += f' + notch ({controller_params.notch.mode})'
    adaptation = None
    if controller_params.type == 'rac':
        adaptation = _adaptation(controller_params, plant, g_num, g_den, sample_time_s, notch,
                                 opts)
    return StabilityReport(controller=desc, plant=plant.name, sample_time_s=sample_time_s,
                           cases=tuple(cases), adaptation=adaptation)


def adaptation_bound(controller_params: ControllerParams, plant_params: PlantParams,
                     sample_time_s: float, *, options: StabilityParams | None = None
                     ) -> AdaptationBound:
    """
    Return the discrete bound on the RAC's adaptation rates for a plant model.

    Parameters
    ----------
    controller_params : ControllerParams
        Controller configuration; its ``rac`` group and notch are used whatever its type.
    plant_params : PlantParams
        Plant model (its ``model`` field chooses it).
    sample_time_s : float
        Sample period T [s], > 0.
    options : StabilityParams, optional
        Slopes, estimates and delay of the cases; default :class:`StabilityParams`.

    Returns
    -------
    AdaptationBound
        y_max, u_fd_max, g_crit over the cases (estimates, slopes; outside the boundary layer,
        where the adaptation acts) and the configured rates.

    """
    opts, plant, g_num, g_den, notch = _loop_parts(controller_params, plant_params,
                                                   sample_time_s, options)
    return _adaptation(controller_params, plant, g_num, g_den, sample_time_s, notch, opts)


def _adaptation(params: ControllerParams, plant: LinearPlant, g_num: FloatArray,
                g_den: FloatArray, sample_time_s: float,
                notch: tuple[Sequence[float], Sequence[float]] | None,
                opts: StabilityParams) -> AdaptationBound:
    """Return the :class:`AdaptationBound` of the RAC of ``params`` (see adaptation_bound)."""
    r = params.rac
    k_sensor = params.sensor_gain_v_per_m
    u_abs = max(abs(params.output_min_v), abs(params.output_max_v))
    y_max = k_sensor * abs(plant.dc_gain_m_per_v) * (opts.slope_max * u_abs + r.rho_v)
    if opts.estimates == 'corners':
        pairs = [(t, f) for t in (r.theta_min, r.theta_max) for f in (r.phi_min, r.phi_max)]
        pairs.append((r.theta_init, r.phi_init))
    else:
        pairs = [(r.theta_init, r.phi_init)]
    # s = ((1 + lambda T) z - 1)/(z - 1) e for a constant reference (backward rectangle)
    s_num = np.array([1.0 + r.lambda_per_s * sample_time_s, -1.0])
    best = (math.inf, 'no case')
    for theta, phi in pairs:
        # outside the boundary layer (where s_eps != 0): k = k_d
        kp = r.k_d + phi * r.lambda_per_s - theta
        ki = r.k_d * r.lambda_per_s
        for slope in opts.slopes():
            gain = k_sensor * slope
            l_num, l_den = loop_polynomials(kp, ki, gain, g_num, g_den, sample_time_s, notch,
                                            opts.delay_samples)
            # y/d = P N z^-delay / (1 + L) = gain g_num n_num (z - 1) / (l_den + l_num) for a
            # disturbance d added to the command, and s = y ((1 + lambda T) z - 1)/(z - 1):
            # H(z) = h_num / char_l, and the adaptation loop is (z - 1) char_l + g h_num = 0
            h_num = np.convolve(g_num * gain, s_num)
            if notch is not None:
                h_num = np.convolve(h_num, np.asarray(notch[0], dtype=np.float64))
            base = np.convolve(_padd(l_den, l_num), [1.0, -1.0])
            crit = _critical_gain(base, h_num)
            if crit < best[0]:
                best = (crit, f'theta_hat={theta:g}, phi_hat={phi:g}, slope={slope:.4g}')
    return AdaptationBound(gamma=r.gamma, eta=r.eta, sample_time_s=sample_time_s,
                           y_max_v=y_max, u_fd_max_v_per_s=r.lambda_per_s * y_max,
                           critical_gain=best[0], worst_label=best[1])


def enforce(report: StabilityReport, action: str) -> str:
    """
    Act on a report: nothing when stable; otherwise warn loudly or refuse.

    Parameters
    ----------
    report : StabilityReport
        The verdict.
    action : str
        ``'warn'``: issue a :class:`StabilityWarning` and return the text; ``'refuse'``: raise.

    Returns
    -------
    str
        The report text (for the caller to log or print).

    Raises
    ------
    StabilityError
        If the loop is unstable and ``action == 'refuse'``.
    ParameterError
        If ``action`` is not one of the two choices.

    """
    if action not in ('warn', 'refuse'):
        raise ParameterError('stability.action', action, "one of 'warn', 'refuse'",
                             'is not a valid choice')
    text = report.text()
    if report.stable:
        if report.adaptation is not None and not report.adaptation.ok:
            # a warning in both actions: the frozen loops are stable and the projection keeps
            # the estimates bounded, so the risk is a bounded limit cycle, not divergence, and
            # the bound is a frozen-regressor linearization (with a 2x margin), not a proof
            warnings.warn(text, StabilityWarning, stacklevel=2)
        return text
    if action == 'refuse':
        raise StabilityError(text)
    warnings.warn(text, StabilityWarning, stacklevel=2)
    return text


def _padd(a: FloatArray, b: FloatArray) -> FloatArray:
    """Return the sum of two polynomials (powers of z, highest first)."""
    n = max(len(a), len(b))
    return np.asarray(np.pad(a, (n - len(a), 0)) + np.pad(b, (n - len(b), 0)), dtype=np.float64)


def _radius(base: FloatArray, h_num: FloatArray, g: float) -> float:
    """Return the largest |root| of base + g h_num (same lengths, leading base[0] != 0)."""
    return float(np.max(np.abs(np.roots(base + g * h_num))))


def _critical_gain(base: FloatArray, h_num: FloatArray, *, g_max: float = 1e4) -> float:
    """
    Return the smallest g > 0 for which base + g h_num has a root on the unit circle.

    Parameters
    ----------
    base : ndarray
        (z - 1) times the characteristic polynomial of the loop with frozen estimates.
    h_num : ndarray
        Numerator of H(z) over that characteristic polynomial.
    g_max : float
        Largest gain searched; ``inf`` is returned when every gain up to it is stable.

    Returns
    -------
    float
        g_crit [-], to a relative 1e-3 (from below); 0 when small gains are already
        unstable.

    """
    n = max(len(base), len(h_num))
    base = np.pad(base, (n - len(base), 0))
    h_num = np.pad(h_num, (n - len(h_num), 0))
    grid = np.geomspace(1e-4, g_max, 33)
    lo = 0.0
    for g in grid:
        if _radius(base, h_num, float(g)) >= 1.0:
            hi = float(g)
            break
        lo = float(g)
    else:
        return math.inf
    if lo == 0.0:
        return 0.0
    while hi - lo > 1e-3 * hi:
        mid = 0.5 * (lo + hi)
        if _radius(base, h_num, mid) < 1.0:
            lo = mid
        else:
            hi = mid
    return lo
