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
Controllers of section IV: the robust adaptive controller (RAC), a PI baseline, open loop.

Units. Every controller takes SI values at its interface (position and reference in metres,
reference velocity in m/s) and returns the amplifier input voltage [V]. Inside, the paper's
controllers run on *sensor volts*, y = K_PSCM x (``sensor_gain_v_per_m``); this is the one place
where that conversion happens, and the only units in which the paper's gains and bounds mean
what the paper says (design brief, "Units").

RAC, eqs. (33)-(40), in sensor volts (e = y - y_d is the paper's x tilde)::

    s     = e + lambda * I,            I = integral of e            (33)
    s_eps = s - eps * sat(s / eps)                                  (34)-(35)
    v     = -k_d s + phi_hat u_fd + theta_hat y - k* sat(s / eps)   (36)
    u_fd  = dy_d/dt - lambda e                                      (37)
    dphi_hat/dt   = proj(phi_hat,   -eta   u_fd s_eps)              (38)
    dtheta_hat/dt = proj(theta_hat, -gamma y    s_eps)              (39)

The package's discrete adaptive law generalises (38)-(39) in two ways, each of which reduces to
the paper's law with its parameter at the neutral value (docs/explanation/controllers.md
derives them)::

    s_a   = s - eps_a * sat(s / eps_a)       (eps_a = 0: s_a = s)   dead zone of its own
    (r_theta, r_phi) = (y, u_fd) measured, or (y_d, dy_d/dt) desired  regressors
    n     = 1 + kappa T (gamma r_theta^2 + eta r_phi^2)             normalisation
    phi_hat   <- clip(phi_hat   - (T/n) eta   r_phi   s_a, phi_min,   phi_max)
    theta_hat <- clip(theta_hat - (T/n) gamma r_theta s_a, theta_min, theta_max)

- the adaptation dead zone eps_a (``adaptation_dead_zone_v``) is separate from the robust
  term's boundary layer eps (``epsilon_v``, which still shapes -k* sat(s/eps) in (36)): the
  boundary layer must be wide for the discrete loop's gain k_d + k*/eps, but as the dead zone
  of the adaptation the same width (hundreds of nanometres) means the estimates never move
  while tracking. eps_a = eps is the paper's s_eps;
- the normalisation kappa (``normalisation``) divides each update by n: the adaptation loop's
  per-sample gain g = T (gamma y^2 + eta u_fd^2) becomes g/(1 + kappa g) < 1/kappa whatever the
  regressors, so kappa >= ADAPTATION_MARGIN/g_crit certifies the adaptation loop for every
  y and u_fd, not only up to y_max (:mod:`piezo_stage_ros.core.control.stability`). kappa = 0 is
  the unnormalised law;
- the regressors (``adaptation_regressor``): the paper's measured y and u_fd = dy_d/dt -
  lambda e, or the desired y_d and dy_d/dt (desired compensation, Sadegh and Horowitz 1990).
  With the measured ones the update holds -gamma e s_a and +eta lambda e s_a, and e s_a > 0 on
  every transient (square-wave edges, sensor noise): the estimates are pumped towards a larger
  proportional gain k + lambda phi_hat - theta_hat, which drives the high-gain stages unstable.
  The desired regressors carry neither the error nor the noise.

Discretization at the sample period T (step k sees y_k and returns v_k, held over one sample):

- the integral by the backward rectangle I_k = I_k-1 + T e_k (the current error is in s_k,
  so the discrete PI part has no extra delay; it is the velocity form of a textbook PI);
- the adaptation by forward Euler from the values of step k, then the projection (40) applied
  to the *updated* estimate, i.e. clipping to [min, max]: for a step that would cross a bound
  this is the exact discrete counterpart of (40) (the continuous law stops at the bound), and
  it guarantees (P1)-(P2) for every sample, whatever the inputs;
- anti-windup by conditional integration: when the command is clipped to the output limits
  and the new error would drive it further out, the integral keeps its last value, and the
  adaptation is frozen for that sample (the law (36) was not applied, so its gradient is not
  informative).

Edge-case contract (all controllers, tested in ``test/test_controllers.py``):

- the output is always finite and inside ``[output_min_v, output_max_v]``;
- a non-finite measurement, reference or reference velocity leaves the state untouched and
  returns the last output (the safe, bumpless choice); it is counted in ``nonfinite_inputs``;
- ``step(..., dt_s=...)`` with dt_s <= 0 or non-finite does the same and counts ``bad_dt``;
  without ``dt_s`` the configured sample time is used;
- ``reset(position_m, reference_m)`` returns to the initial estimates and a zero integral;
  with ``output_v`` given it starts bumpless from that held voltage (PI: integral preset);
- the optional notch filter on the command starts at rest at the first command it filters.

The default RAC gains are the discrete-time tuning of ``python3 -m piezo_stage_ros.tune``
(docs/explanation/controllers.md), not the paper's: its epsilon = 0.005 makes the boundary-layer
gain k*/epsilon = 40, which is unstable at 10 kHz, and its unnormalised adaptation rates gamma =
3000, eta = 0.01 close a discrete loop through v (the update is an integrator whose per-sample gain
is g = T (gamma y^2 + eta u_fd^2) times the response of s to v) that limit-cycles on a plateau of a
few volts; :func:`piezo_stage_ros.core.control.stability.adaptation_bound` derives the largest
stable per-sample gain g_crit from the plant model, and the default normalisation kappa = 40 >=
2/g_crit keeps g/(1 + kappa g) below half of it for every regressor. The gains k_d, lambda, epsilon
and kappa are sized so that the stability check passes with one whole sample of computational delay
(a target that applies each command at its next tick), not only with the fraction of a sample an
in-process servo takes: a larger lambda or a narrower boundary layer tracks a fast sine more
closely and fails that check. The rates, the dead zone, the regressors and the box were chosen on a
family of stages unlike the model (tune section 9).

Which law this is, and what the paper's Theorem 1 covers. Theorem 1 is a continuous-time
Lyapunov argument for the first-order model (28) with the hysteresis written as c v + d,
|d| <= rho, under its Assumption (the true theta = a/(b c) and phi = 1/(b c) inside the
projection box) and for the law (36)-(40) as printed: the adaptation driven by s_eps (dead zone
equal to the boundary layer), the measured regressors, no normalisation. It then proves bounded
signals and s_eps -> 0. It does not cover the discrete-time loop, the third-order plant's
resonance and the notch, the computational delay, the command limits or the converters. The
law of this class reduces to the paper's only with ``adaptation_dead_zone_v = epsilon_v``,
``adaptation_regressor = measured`` and ``normalisation = 0`` (``config/rac_paper.yaml``). The
default is outside Theorem 1 on each of these counts: its dead zone (0.002 V) is far narrower
than its boundary layer (0.4 V), so the estimates move where sat(s/epsilon) is still linear and
the step of the proof that needs |s_eps| = s_eps sat(s/epsilon) fails; its regressors are the
desired ones; its updates are normalised; and its box theta in [1.05, 2] leaves out the true
theta = 0.92 of a stage with 1.4 times the model's gain (on purpose: a smaller theta_hat raises
the loop gain), which breaks the Assumption for that stage. What covers the default is the
frozen-parameter check of :mod:`piezo_stage_ros.core.control.stability` (every linear loop with
estimates and hysteresis slope frozen anywhere in their box is stable, at the configured
computational delay) and its linearized bound on the adaptation loop: neither is a proof for
the running, time-varying loop.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Generic, Mapping, TypeVar

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.params import group, param, Params
from piezo_stage_ros.core.control.feedforward import FeedForwardController, FeedForwardParams
from piezo_stage_ros.core.model.hysteresis import (
    HysteresisModel,
    HysteresisParams,
    make_hysteresis,
)
from piezo_stage_ros.core.model.linear import LinearPlant

__all__ = [
    'ControllerParams', 'NotchFilter', 'NotchParams', 'NotchedController', 'OpenLoopController',
    'OpenLoopParams', 'PIController', 'PIParams', 'RACController', 'RACParams',
    'SENSOR_GAIN_V_PER_M', 'bound_controller', 'build_controller', 'notch_coefficients',
    'notch_design', 'plant_resonance', 'proj', 'rac_linear_gains', 'sat',
]

#: K_PSCM of eq. (15), 10 V over 38 um [V/m] (same value as the stage's sensor).
SENSOR_GAIN_V_PER_M = 10.0 / 38e-6

#: Gain of the RAC's running mean of its error (an exponential window of 100 samples), and the
#: factor a sample by which a stall's error relaxes from the last one to that mean (a time
#: constant of 10 samples): :meth:`RACController.missed`. Against the last error carried over
#: the whole stall, this is about the same over short stalls and smaller over long ones
#: (``benchmark --suite servo``, case ``stall``).
_MEAN_GAIN = 1.0 / 100.0
_MISSED_RELAX = math.exp(-1.0 / 10.0)


def rac_linear_gains(k: float, lambda_per_s: float, theta: float, phi: float
                     ) -> tuple[float, float]:
    """
    Return (k_p [V/V], k_i [1/s]) of the RAC as a PI on the sensor-volt error.

    With a feedback gain k on s (k_d + k*/epsilon inside the boundary layer, k_d outside) and
    the estimates theta_hat, phi_hat: v = -(k + phi lambda - theta) e - k lambda int(e) + terms
    in y_d only. The stability check and the feed-forward's learning filter both linearize so.
    """
    return k + phi * lambda_per_s - theta, k * lambda_per_s


def sat(z: float) -> float:
    """
    Return the standard saturation function of eq. (35).

    Parameters
    ----------
    z : float
        Argument (dimensionless).

    Returns
    -------
    float
        1 for z >= 1, -1 for z <= -1, z otherwise.

    """
    return 1.0 if z >= 1.0 else (-1.0 if z <= -1.0 else z)


def proj(estimate: float, step: float, low: float, high: float) -> float:
    """
    Apply one Euler step of an adaptation law with the projection of eq. (40).

    Parameters
    ----------
    estimate : float
        Current estimate, inside ``[low, high]``.
    step : float
        The unprojected increment ``T * (-y)`` of the law ``d/dt estimate = proj(estimate, -y)``.
    low, high : float
        Bounds of the estimate (Omega of eqs. (29)-(30)).

    Returns
    -------
    float
        The updated estimate clipped to ``[low, high]``: at a bound, a step pointing outward is
        dropped (eq. (40)); a step that would cross a bound stops on it.

    """
    z = estimate + step
    return high if z > high else (low if z < low else z)


# --------------------------------------------------------------------------------------------
# Parameters


@dataclass(frozen=True)
class RACParams(Params):
    """
    Gains and bounds of the RAC, eqs. (33)-(40), in the paper's units (sensor volts in).

    Defaults are the discrete-time tuning found by ``python3 -m piezo_stage_ros.tune`` (see
    docs/explanation/controllers.md); the paper's values are quoted in each description. They
    are outside the paper's Theorem 1 (module docstring): the law reduces to the paper's only with
    ``adaptation_dead_zone_v = epsilon_v``, ``adaptation_regressor = 'measured'`` and
    ``normalisation = 0``, and the theorem also needs the true parameters inside the box.
    """

    k_d: float = param(1.0, unit='V/V', description='Feedback gain k_d on s, eq. (36) (paper '
                       '1.5).', low=0.0, low_open=True)
    lambda_per_s: float = param(2000.0, unit='1/s', description='Integral weight lambda of '
                                's = e + lambda * int(e), eq. (33) (paper 1500). With the '
                                'default box, 2000 keeps the stability check passing with one '
                                'sample of computational delay.', low=0.0, low_open=True)
    epsilon_v: float = param(0.4, unit='V (sensor)', description='Boundary-layer width epsilon '
                             'of eq. (34); the feedback gain inside it is k_d + k_star/epsilon '
                             '(paper 0.005, which chatters at 10 kHz).', low=0.0, low_open=True)
    k_star_v: float = param(0.2, unit='V', description='Robust gain k* of eq. (36); must be '
                            ">= rho/c_min (paper 0.2), the sizing of Theorem 1's proof; the "
                            'default law is outside that theorem (module docstring), so this '
                            'is a sizing rule for the robust term, not a guarantee.', low=0.0)
    gamma: float = param(100.0, unit='1/(V^2 s)', description='Adaptation rate gamma of '
                         'theta_hat, eq. (39) (paper 3000). With the normalisation the '
                         'discrete adaptation loop is stable for any rate; 100 is what the '
                         'stage-family study of tune (section 9) found best: faster rates add '
                         'estimate jitter to the tracking error.', low=0.0)
    eta: float = param(3e-4, unit='s/V^2', description='Adaptation rate eta of phi_hat, '
                       'eq. (38) (paper 0.01; phi_hat is excited only by dy_d/dt, and 1e-3 '
                       'is already slightly worse on the noisy stages of tune section 9).',
                       low=0.0)
    adaptation_dead_zone_v: float = param(0.002, unit='V (sensor)', description='Dead zone '
                                          'epsilon_a of the adaptation: (38)-(39) are driven by '
                                          's_a = s - epsilon_a sat(s/epsilon_a) instead of '
                                          's_eps (0: no dead zone; equal to epsilon_v: the '
                                          "paper's law). 2 mV = 7.6 nm: above the 16-bit "
                                          'ADC step (0.3 mV) and 2.5 times the s of 3 nm rms '
                                          'sensor noise, far below the boundary layer (as '
                                          'wide as that, the estimates never move while '
                                          'tracking).',
                                          low=0.0)
    adaptation_regressor: str = param('desired', unit='-', description='Regressors of '
                                      "(38)-(39): measured = the paper's y and u_fd = dy_d/dt "
                                      '- lambda e; desired = y_d and dy_d/dt (desired '
                                      'compensation: no error or sensor noise in the update, '
                                      'so no drift towards a larger loop gain).',
                                      choices=('measured', 'desired'))
    normalisation: float = param(40.0, unit='-', description='Normalisation kappa of the '
                                 'adaptation: each update is divided by n = 1 + kappa T '
                                 '(gamma r_theta^2 + eta r_phi^2), which caps the per-sample '
                                 "loop gain below 1/kappa (0: the paper's unnormalised law). "
                                 '40 >= 2/g_crit on model (20) with up to one sample of '
                                 'computational delay: the linearized adaptation bound of the '
                                 'stability check then holds for every regressor size.',
                                 low=0.0)
    theta_min: float = param(1.05, unit='V/V', description='Lower bound of theta = a/(b c), '
                             'eq. (29) (paper 0.5). Above the true 0.92 of a 1.4x-gain stage on '
                             'purpose: a smaller theta_hat raises the proportional gain '
                             'k + lambda phi_hat - theta_hat towards instability there.',
                             low=0.0, low_open=True)
    theta_max: float = param(2.0, unit='V/V', description='Upper bound of theta, eq. (29) '
                             '(paper 4; theta = 1.85 for a 0.7x-gain stage).', low=0.0,
                             low_open=True)
    theta_init: float = param(1.29, unit='V/V', description='Initial estimate theta_hat(0) '
                              '(paper 1; the model value).', low=0.0, low_open=True)
    phi_min: float = param(2e-4, unit='s', description='Lower bound of phi = 1/(b c), '
                           'eq. (30) (paper 1e-4).', low=0.0, low_open=True)
    phi_max: float = param(9e-4, unit='s', description='Upper bound of phi, eq. (30) '
                           '(paper 5e-3); the feedforward gain a slow, 0.7x-gain stage needs '
                           'at 100 Hz is about 8e-4 (1.5 times its phi: ZOH delay and '
                           'hysteresis lag).', low=0.0, low_open=True)
    phi_init: float = param(3.16e-4, unit='s', description='Initial estimate phi_hat(0) '
                            '(paper 7.5e-4): the model value 1/(b c). The stability check '
                            'covers every phi_hat of the box, so a start below it buys no '
                            'margin; it adapts up where dy_d/dt excites it.',
                            low=0.0, low_open=True)
    rho_v: float = param(0.18, unit='V', description='Bound rho on the hysteresis term |d|, '
                         'eq. (31) (paper 0.18; (c - B1)/alpha = 0.1785 for the default stage).',
                         low=0.0)
    c_min: float = param(1.0, unit='-', description='Lower bound c_min of the hysteresis slope '
                         'used in k* >= rho/c_min (paper 1).', low=0.0, low_open=True)

    def _check(self) -> None:
        for name, lo, hi, init in (('theta', self.theta_min, self.theta_max, self.theta_init),
                                   ('phi', self.phi_min, self.phi_max, self.phi_init)):
            if not lo < hi:
                raise ParameterError(f'{name}_max', hi, f'> {name}_min = {lo:g}',
                                     'is not above the lower bound')
            if not lo <= init <= hi:
                raise ParameterError(f'{name}_init', init, f'[{lo:g}, {hi:g}]',
                                     'is outside its bounds (eqs. (29)-(30))')
        # the paper's sizing of k*, kept as a rule for the robust term: the default law is
        # outside Theorem 1 (module docstring), which therefore guarantees nothing for it
        k_min = self.rho_v / self.c_min
        if self.k_star_v < k_min:
            raise ParameterError('k_star_v', self.k_star_v,
                                 f'[rho/c_min, inf) = [{k_min:g}, inf)',
                                 f'is below the minimum rho/c_min = {k_min:g} of Theorem 1')


@dataclass(frozen=True)
class PIParams(Params):
    """The paper's PI baseline (PIC of Table III) in sensor volts: v = k_p e + k_i int(e)."""

    k_p: float = param(1.5, unit='V/V', description='Proportional gain (paper PIC 1.5).',
                       low=0.0)
    k_i: float = param(1500.0, unit='1/s', description='Integral gain (paper PIC 1500).',
                       low=0.0)
    anti_windup: str = param('conditional', unit='-', description='What the integral does while '
                             'the output saturates: conditional = stop integrating when the '
                             'error drives further into saturation; none = integrate anyway.',
                             choices=('conditional', 'none'))


@dataclass(frozen=True)
class OpenLoopParams(Params):
    """Open-loop command v = gain * x_d + offset (ignores the measurement)."""

    gain_v_per_m: float = param(1.0 / (2.843e-6 * 1.0341), unit='V/m', description='Static '
                                'inverse of the plant, 1/(g c) for the default stage.')
    offset_v: float = param(0.0, unit='V', description='Voltage added to the command.')


@dataclass(frozen=True)
class NotchParams(Params):
    """
    Notch filter on the command against a lightly damped resonance.

    N(s) = (s^2 + 2 zeta_z w0 s + w0^2) / (s^2 + 2 zeta_p w0 s + w0^2), discretized by the
    bilinear transform pre-warped at w0 (so the notch sits exactly at w0 in discrete time).
    """

    mode: str = param('manual', unit='-', description="off; manual (frequency_hz, zero_damping); "
                      "model (w0 and zero damping from the plant model's lightest-damped "
                      'complex pole pair).', choices=('off', 'manual', 'model'))
    frequency_hz: float = param(3166.0, unit='Hz', description='Notch frequency in manual mode.',
                                low=0.0, low_open=True)
    zero_damping: float = param(0.084, unit='-', description='Damping of the notch zeros in '
                                'manual mode (depth: 0 = infinitely deep).', low=0.0, high=1.0)
    pole_damping: float = param(1.5, unit='-', description='Damping of the notch poles '
                                '(width), both modes.', low=0.0, low_open=True, high=2.0)


@dataclass(frozen=True)
class ControllerParams(Params):
    """Everything that defines a controller; SI at the interface."""

    type: str = param('rac', unit='-', description='Controller: robust adaptive (eqs. (33)-(40)),'
                      ' PI baseline or open loop.', choices=('rac', 'pi', 'open_loop'),
                      read_only=True)
    sensor_gain_v_per_m: float = param(SENSOR_GAIN_V_PER_M, unit='V/m', description='K_PSCM '
                                       'the controller uses to convert metres to sensor volts.',
                                       low=0.0, low_open=True)
    output_min_v: float = param(-2.0, unit='V', description='Lowest command (amplifier input '
                                'range).')
    output_max_v: float = param(10.0, unit='V', description='Highest command (amplifier input '
                                'range).')
    rac: RACParams = group(RACParams, 'robust adaptive controller, eqs. (33)-(40)')
    pi: PIParams = group(PIParams, 'PI baseline')
    open_loop: OpenLoopParams = group(OpenLoopParams, 'open-loop command')
    notch: NotchParams = group(NotchParams, 'notch filter on the command')
    feedforward: FeedForwardParams = group(FeedForwardParams, 'feed-forward from the reference: '
                                           'model inverse and learning across periods')

    def _check(self) -> None:
        if not self.output_min_v < self.output_max_v:
            raise ParameterError('output_max_v', self.output_max_v,
                                 f'> output_min_v = {self.output_min_v:g}',
                                 'is not above the lowest command')


# --------------------------------------------------------------------------------------------
# Controllers


class _Output:
    """The last command and the limits of a controller, as its users read them."""

    _u: float
    _vmin: float
    _vmax: float

    @property
    def output_v(self) -> float:
        """Return the last command [V]: what a refused sample returns again."""
        return self._u

    @property
    def output_limits_v(self) -> tuple[float, float]:
        """Return the command limits (lowest, highest) [V]."""
        return self._vmin, self._vmax


_P = TypeVar('_P', bound=Params)


class _Feedback(_Output, Generic[_P]):
    """
    What the three controllers share: sample time, command limits, counters, the last command.

    Parameters
    ----------
    params : Params
        The controller's own parameters (:attr:`params`).
    sample_time_s : float
        Sample period T [s], > 0.
    output_min_v, output_max_v : float
        Command limits [V].
    built : ControllerParams, optional
        The configuration :func:`build_controller` made it from (None when built directly):
        what :meth:`update_params` compares a run-time change with.
    sensor_gain_v_per_m : float, optional
        K_PSCM [V/m] converting positions to sensor volts (None: a controller without it).

    Notes
    -----
    Each controller's ``step`` stays written out in full, with its own refusal of a bad
    ``dt_s`` and of non-finite inputs: it runs once per sample, and a shared helper would add a
    call to every one.

    """

    #: The ``type`` of :class:`ControllerParams` whose gains :meth:`update_params` takes in
    #: place ('': none; every change rebuilds the controller).
    _kind = ''

    def __init__(self, params: _P, sample_time_s: float, output_min_v: float,
                 output_max_v: float, built: ControllerParams | None,
                 sensor_gain_v_per_m: float | None = None) -> None:
        _check_sample_time(sample_time_s)
        self.params = params
        self._t = float(sample_time_s)
        self._k = 0.0 if sensor_gain_v_per_m is None else float(sensor_gain_v_per_m)
        self._vmin = float(output_min_v)
        self._vmax = float(output_max_v)
        self._built = built
        self._u = 0.0
        self.nonfinite_inputs = 0
        self.bad_dt = 0

    @property
    def sample_time_s(self) -> float:
        """Return the sample period T [s]."""
        return self._t

    @property
    def sensor_gain_v_per_m(self) -> float | None:
        """Return K_PSCM [V/m], the conversion of positions to sensor volts (None: unused)."""
        return self._k if self._k > 0.0 else None

    @property
    def built(self) -> ControllerParams | None:
        """Return the configuration it was built from (None when built directly)."""
        return self._built

    def diagnostic_values(self) -> tuple[float, ...]:
        raise NotImplementedError

    #: Names of :meth:`diagnostic_values`, in order (the closed loop's cheap path).
    diagnostic_names: tuple[str, ...] = ()

    def diagnostics(self) -> Mapping[str, float]:
        """Return :attr:`diagnostic_names` with their values (see each controller's list)."""
        return dict(zip(self.diagnostic_names, self.diagnostic_values()))

    def _held_output(self, output_v: float | None) -> float:
        """Return the voltage held before a start, clipped to the limits (0 V when unknown)."""
        out = 0.0 if output_v is None or not math.isfinite(output_v) else float(output_v)
        return min(max(out, self._vmin), self._vmax)

    def update_params(self, params: ControllerParams) -> bool:
        """
        Take new gains between two samples, keeping the state.

        Parameters
        ----------
        params : ControllerParams
            The whole new controller configuration.

        Returns
        -------
        bool
            True when applied in place; False when the change is structural (another type,
            sensor gain or output limits, or a controller without state to keep) and the
            caller must build a new controller.

        """
        if not self._kind or not _same_structure(self._built, params, self._kind):
            return False
        self._take(params)
        self._built = params
        return True

    def _take(self, params: ControllerParams) -> None:
        """Apply the gains of ``params`` (same structure) to the running controller."""
        raise NotImplementedError


class _InSensorVolts(_Feedback[_P]):
    """
    A controller on sensor volts, y = K_PSCM x: the RAC and the PI.

    The arguments are those :class:`RACController` lists, and ``built``, the configuration
    :func:`build_controller` made it from (None when built directly).
    """

    def __init__(self, params: _P, sample_time_s: float, *,
                 sensor_gain_v_per_m: float = SENSOR_GAIN_V_PER_M, output_min_v: float = -2.0,
                 output_max_v: float = 10.0, built: ControllerParams | None = None) -> None:
        super().__init__(params, sample_time_s, output_min_v, output_max_v, built,
                         sensor_gain_v_per_m)
        self._set_gains(params)
        self.reset(0.0, 0.0)

    def _set_gains(self, p: _P) -> None:
        raise NotImplementedError

    def reset(self, position_m: float, reference_m: float,
              output_v: float | None = None) -> None:
        raise NotImplementedError


class RACController(_InSensorVolts[RACParams]):
    """
    The robust adaptive controller of eqs. (33)-(40), one step per sample.

    The law is the paper's (36) with the generalised update of the module docstring; it is
    the paper's (38)-(40) only with ``adaptation_dead_zone_v = epsilon_v``, the measured
    regressors and no normalisation, and even then the paper's Theorem 1 is a continuous-time
    result for the first-order model, not a guarantee for this sampled loop (module
    docstring).

    Parameters
    ----------
    params : RACParams
        Gains and bounds (sensor volts).
    sample_time_s : float
        Sample period T [s], > 0.
    sensor_gain_v_per_m : float
        K_PSCM [V/m] converting positions to sensor volts.
    output_min_v, output_max_v : float
        Command limits [V].
    built : ControllerParams, optional
        The whole configuration, from :func:`build_controller` (it compares run-time changes
        with it).

    Notes
    -----
    See the module docstring for the discretization, anti-windup and edge cases. The step
    works on plain floats (no numpy): it runs 10 000 times per simulated second.
    :class:`piezo_stage_ros.core.loop.batch.ControllerBatch` repeats its arithmetic over many
    stages at once, on purpose (see that module); a change here goes there too, and the
    bit-for-bit tests of ``test/test_batch.py`` say where the two part.

    """

    _kind = 'rac'

    #: Whether the estimates are held (:meth:`hold_estimates`).
    _held = False

    def reset(self, position_m: float, reference_m: float,
              output_v: float | None = None) -> None:
        """
        Return to the initial estimates, a zero integral and the given starting point.

        Parameters
        ----------
        position_m : float
            Measured position at the start [m] (used for the diagnostics only).
        reference_m : float
            Reference at the start [m] (used for the diagnostics only).
        output_v : float, optional
            Voltage held before the start [V]; it is the "last output" returned on a
            non-finite first sample. The integral starts at zero as in eq. (33) whatever it is.

        """
        p = self.params
        self._theta = p.theta_init
        self._phi = p.phi_init
        self._i = 0.0
        self._s = 0.0
        self._saturated = 0.0
        self._u = self._held_output(output_v)
        e = (position_m - reference_m) * self._k
        self._e = e if math.isfinite(e) else 0.0
        self._e_mean = self._e

    def step(self, position_m: float, reference_m: float, reference_velocity_mps: float,
             dt_s: float | None = None) -> float:
        """
        Compute the command for one sample.

        Parameters
        ----------
        position_m : float
            Measured position y_k [m].
        reference_m : float
            Desired position x_d(t_k) [m].
        reference_velocity_mps : float
            Desired velocity dx_d/dt(t_k) [m/s].
        dt_s : float, optional
            Time since the last step [s] (real-time mode); default the sample time.

        Returns
        -------
        float
            Amplifier input voltage v_k [V], finite, inside the output limits.

        """
        # the refusals are written out in each controller's step, as the whole step is: it
        # runs once per sample, and a shared helper would add a call to every one
        if dt_s is None:
            dt = self._t
        else:
            dt = dt_s
            if not dt > 0.0 or dt - dt != 0.0:
                self.bad_dt += 1
                return self._u
        k = self._k
        y = position_m * k
        yd = reference_m * k
        ydd = reference_velocity_mps * k
        total = y + yd + ydd
        if total - total != 0.0:  # NaN or +-inf somewhere (or an overflow to inf)
            self.nonfinite_inputs += 1
            return self._u
        lam = self._lam
        e = y - yd
        i_new = self._i + dt * e
        s = e + lam * i_new
        z = s * self._inv_eps
        sz = 1.0 if z >= 1.0 else (-1.0 if z <= -1.0 else z)
        u_fd = ydd - lam * e
        theta = self._theta
        phi = self._phi
        v = -self._kd * s + phi * u_fd + theta * y - self._kstar * sz
        vmax = self._vmax
        vmin = self._vmin
        if v > vmax or v < vmin:
            # conditional integration: keep the old integral if the new error pushes further out
            if (v > vmax) == (e < 0.0):
                i_new = self._i
                s = e + lam * i_new
                z = s * self._inv_eps
                sz = 1.0 if z >= 1.0 else (-1.0 if z <= -1.0 else z)
                v = -self._kd * s + phi * u_fd + theta * y - self._kstar * sz
            self._saturated = 1.0
            v = vmax if v > vmax else (vmin if v < vmin else v)
        else:
            self._saturated = 0.0
            eps_a = self._eps_a
            if eps_a > 0.0:
                za = s * self._inv_eps_a
                s_a = s - eps_a * (1.0 if za >= 1.0 else (-1.0 if za <= -1.0 else za))
            else:
                s_a = s
            if s_a != 0.0:
                # Euler step of (38)-(39) with the normalised step g = T/n, then the
                # projection (40) on the updated estimate; kappa = 0 keeps g = T exactly
                if self._desired:
                    r_t, r_f = yd, ydd
                else:
                    r_t, r_f = y, u_fd
                kappa = self._kappa
                g = dt / (1.0 + kappa * dt * (self._gamma * r_t * r_t + self._eta * r_f * r_f)
                          ) if kappa > 0.0 else dt
                p = self.params
                ph = phi - g * self._eta * r_f * s_a
                self._phi = p.phi_max if ph > p.phi_max else (p.phi_min if ph < p.phi_min
                                                              else ph)
                th = theta - g * self._gamma * r_t * s_a
                self._theta = p.theta_max if th > p.theta_max else (
                    p.theta_min if th < p.theta_min else th)
        if v != v:  # unreachable with finite inputs and bounded estimates; belt and braces
            return self._u
        self._i = i_new
        self._s = s
        self._e = e
        self._e_mean += (e - self._e_mean) * _MEAN_GAIN
        self._u = v
        return v

    #: Names of :meth:`diagnostic_values`, in order (the closed loop's cheap path).
    diagnostic_names = ('theta_hat', 'phi_hat', 's_v', 'integral_v_s', 'error_v', 'saturated',
                        'nonfinite_inputs', 'bad_dt')

    def diagnostic_values(self) -> tuple[float, ...]:
        """Return the values of :attr:`diagnostic_names` (no dictionary is built)."""
        return (self._theta, self._phi, self._s, self._i, self._e, self._saturated,
                float(self.nonfinite_inputs), float(self.bad_dt))

    def hold_estimates(self, hold: bool) -> None:
        """
        Stop (True) or resume (False) the adaptation of theta_hat and phi_hat.

        For a learning feed-forward: both would learn the same periodic error, and the estimates
        then drift along the direction where their effect and the learned table's cancel, to
        their bounds, where the learning, whose filter assumes the loop gain at the estimates,
        can diverge. Held, the updates are exact zeros: the estimates keep their values bit for
        bit.
        """
        self._held = hold
        self._gamma, self._eta = (0.0, 0.0) if hold else (self.params.gamma, self.params.eta)

    def missed(self, samples: int) -> None:
        """
        Let ``samples`` samples the loop missed (a stall) pass before the next step.

        The integral of eq. (33) goes on over them (the commands ahead kept the stage near
        where it was; without this it would lack their area for the rest of the run, an
        offset the loop then works off slowly), with the error it most likely had: the last
        one, relaxing to the recent mean (the last 100 samples, exponentially weighted) with
        a time constant of 10 samples. The last error alone, carried over a long stall, puts
        the noise and the ripple of one sample into the integral once per missed sample: a
        kick when the loop comes back (``benchmark --suite servo``, case ``stall``).
        """
        if samples > 0 and not self._saturated:
            mean = self._e_mean
            r = _MISSED_RELAX
            relaxing = (self._e - mean) * r * (1.0 - r ** samples) / (1.0 - r)
            self._i += self._t * (samples * mean + relaxing)

    def reference_gains(self) -> tuple[float, float]:
        """
        Return (a [V/m], b [V s/m]): the model-based part a x_d + b x_d' of the command.

        theta_hat y + phi_hat dy_d/dt of eq. (36) at perfect tracking (y = y_d), at the present
        estimates: what changes of the command the reference alone explains (commands ahead,
        :mod:`piezo_stage_ros.core.control.ahead`).
        """
        return self._theta * self._k, self._phi * self._k

    def linear_gains(self) -> tuple[float, float]:
        """Return (k_p, k_i) inside the boundary layer at the present estimates."""
        p = self.params
        return rac_linear_gains(p.k_d + p.k_star_v / p.epsilon_v, p.lambda_per_s, self._theta,
                                self._phi)

    def _take(self, params: ControllerParams) -> None:
        """
        Take new RAC gains, keeping the integral and the estimates.

        The estimates are clipped into the new projection bounds, so (P1)-(P2) keep holding.
        """
        p = params.rac
        self.params = p
        self._set_gains(p)
        self._theta = min(max(self._theta, p.theta_min), p.theta_max)
        self._phi = min(max(self._phi, p.phi_min), p.phi_max)

    def _set_gains(self, p: RACParams) -> None:
        """Cache the gains of the law, the adaptation's dead zone and its normalisation."""
        self._kd, self._lam, self._eps = p.k_d, p.lambda_per_s, p.epsilon_v
        self._inv_eps = 1.0 / p.epsilon_v
        self._kstar = p.k_star_v
        self._gamma, self._eta = (0.0, 0.0) if self._held else (p.gamma, p.eta)
        eps_a = p.adaptation_dead_zone_v
        inv = 1.0 / eps_a if eps_a > 0.0 else math.inf
        # a dead zone so narrow that its inverse overflows (subnormal) is no dead zone: s * inf
        # would be NaN at s = 0
        self._eps_a = eps_a if math.isfinite(inv) else 0.0
        self._inv_eps_a = inv if math.isfinite(inv) else 0.0
        self._kappa = p.normalisation
        self._desired = p.adaptation_regressor == 'desired'



class PIController(_InSensorVolts[PIParams]):
    """
    PI baseline v = k_p e + k_i int(e), e = y_d - y in sensor volts, with output limits.

    Parameters
    ----------
    params : PIParams
        Gains and anti-windup choice.
    sample_time_s : float
        Sample period T [s], > 0.
    sensor_gain_v_per_m : float
        K_PSCM [V/m].
    output_min_v, output_max_v : float
        Command limits [V].

    Notes
    -----
    The integral is the backward rectangle I_k = I_k-1 + T e_k, as in the RAC. With
    ``anti_windup='conditional'`` the integral keeps its value while the output is clipped and
    the error drives it further out.

    """

    _kind = 'pi'


    def reset(self, position_m: float, reference_m: float,
              output_v: float | None = None) -> None:
        """
        Forget the history; with ``output_v`` [V] given, start bumpless from it.

        The integral is then preset so that the first output for this position and reference
        [m] equals the held voltage (bumpless transfer); otherwise it starts at zero.
        """
        e = (reference_m - position_m) * self._k
        e = e if math.isfinite(e) else 0.0
        self._i = 0.0
        self._u = 0.0
        self._saturated = 0.0
        self._e = e
        if output_v is not None and math.isfinite(output_v):
            u0 = min(max(float(output_v), self._vmin), self._vmax)
            self._u = u0
            if self._ki > 0.0:
                # first step: v = k_p e + k_i (I + T e) = u0
                self._i = (u0 - self._kp * e) / self._ki - self._t * e

    def step(self, position_m: float, reference_m: float, reference_velocity_mps: float,
             dt_s: float | None = None) -> float:
        """
        Compute the command [V] for one sample, arguments as :meth:`RACController.step`.

        A PI does not use the reference velocity, but a non-finite value is still refused, as
        for every controller.
        """
        # the refusals are written out in each controller's step, as the whole step is: it
        # runs once per sample, and a shared helper would add a call to every one
        if dt_s is None:
            dt = self._t
        else:
            dt = dt_s
            if not dt > 0.0 or dt - dt != 0.0:
                self.bad_dt += 1
                return self._u
        total = position_m + reference_m + reference_velocity_mps
        if total - total != 0.0:
            self.nonfinite_inputs += 1
            return self._u
        e = (reference_m - position_m) * self._k
        i_new = self._i + dt * e
        v = self._kp * e + self._ki * i_new
        vmax = self._vmax
        vmin = self._vmin
        if v > vmax or v < vmin:
            if self._conditional and (v > vmax) == (e > 0.0):
                i_new = self._i
                v = self._kp * e + self._ki * i_new
            self._saturated = 1.0
            v = vmax if v > vmax else (vmin if v < vmin else v)
        else:
            self._saturated = 0.0
        if v != v:
            return self._u
        self._i = i_new
        self._e = e
        self._u = v
        return v

    #: Names of :meth:`diagnostic_values`, in order (the closed loop's cheap path).
    diagnostic_names = ('error_v', 'integral_v_s', 'saturated', 'nonfinite_inputs', 'bad_dt')

    def diagnostic_values(self) -> tuple[float, ...]:
        """Return the values of :attr:`diagnostic_names` (no dictionary is built)."""
        return (self._e, self._i, self._saturated, float(self.nonfinite_inputs),
                float(self.bad_dt))

    def missed(self, samples: int) -> None:
        """Let ``samples`` missed samples pass: the integral goes on with the last error."""
        if samples > 0 and not self._saturated:
            self._i += samples * self._t * self._e

    def reference_gains(self) -> tuple[float, float]:
        """Return (0, 0): a PI has no model-based part (commands ahead hold its command)."""
        return 0.0, 0.0

    def linear_gains(self) -> tuple[float, float]:
        """Return (k_p, k_i) on the sensor-volt error."""
        return self.params.k_p, self.params.k_i

    def _take(self, params: ControllerParams) -> None:
        """
        Take new PI gains without a bump in the command.

        The integral is rescaled so that k_i I, the part of the command it holds, is the same
        before and after (bumpless gain change); the proportional part changes with k_p at
        once, by k_p e, which is small while tracking.
        """
        p = params.pi
        if p.k_i > 0.0:
            self._i = self._i * self._ki / p.k_i
        self.params = p
        self._set_gains(p)

    def _set_gains(self, p: PIParams) -> None:
        """Cache the gains and the anti-windup choice."""
        self._kp, self._ki = p.k_p, p.k_i
        self._conditional = p.anti_windup == 'conditional'


class OpenLoopController(_Feedback[OpenLoopParams]):
    """
    Open loop: v = gain * x_d + offset, clipped to the output limits.

    Parameters
    ----------
    params : OpenLoopParams
        Gain [V/m] and offset [V].
    sample_time_s : float
        Sample period T [s], > 0.
    output_min_v, output_max_v : float
        Command limits [V].

    """

    # _kind stays '': an open-loop gain change rebuilds the controller (it has no state)

    def __init__(self, params: OpenLoopParams, sample_time_s: float, *,
                 output_min_v: float = -2.0, output_max_v: float = 10.0,
                 built: ControllerParams | None = None) -> None:
        super().__init__(params, sample_time_s, output_min_v, output_max_v, built)

    def reset(self, position_m: float, reference_m: float,
              output_v: float | None = None) -> None:
        """
        Forget the last output (open loop has no other state).

        The positions [m] are unused; ``output_v`` [V], the voltage held before the start, is
        returned on a non-finite first sample.
        """
        self._u = self._held_output(output_v)

    def step(self, position_m: float, reference_m: float, reference_velocity_mps: float,
             dt_s: float | None = None) -> float:
        """
        Return gain * x_d + offset [V], clipped; arguments as :meth:`RACController.step`.

        The measurement and the reference velocity are unused; dt_s <= 0 holds the last
        output.
        """
        if dt_s is not None and (not dt_s > 0.0 or dt_s - dt_s != 0.0):
            self.bad_dt += 1
            return self._u
        if reference_m - reference_m != 0.0:
            self.nonfinite_inputs += 1
            return self._u
        v = self.params.gain_v_per_m * reference_m + self.params.offset_v
        v = self._vmax if v > self._vmax else (self._vmin if v < self._vmin else v)
        if v != v:
            return self._u
        self._u = v
        return v

    #: Names of :meth:`diagnostic_values`, in order.
    diagnostic_names = ('nonfinite_inputs', 'bad_dt')

    def diagnostic_values(self) -> tuple[float, ...]:
        """Return the values of :attr:`diagnostic_names`."""
        return (float(self.nonfinite_inputs), float(self.bad_dt))

    def reference_gains(self) -> tuple[float, float]:
        """Return (gain [V/m], 0): the whole command is the reference's."""
        return self.params.gain_v_per_m, 0.0

    def linear_gains(self) -> tuple[float, float]:
        """Return (0, 0): no feedback."""
        return 0.0, 0.0



# --------------------------------------------------------------------------------------------
# Notch filter


def plant_resonance(plant: LinearPlant) -> tuple[float, float]:
    """
    Return the natural frequency and damping of the plant's lightest-damped complex pole pair.

    Parameters
    ----------
    plant : LinearPlant
        Continuous-time model.

    Returns
    -------
    omega_rad_s, zeta : float
        |p| [rad/s] and -Re(p)/|p| of that pair.

    Raises
    ------
    ParameterError
        If the model has no complex pole pair (e.g. the reduced first-order model).

    """
    poles = plant.poles()
    pairs = [p for p in poles if p.imag > 1e-9 * abs(p)]
    if not pairs:
        raise ParameterError('notch.mode', 'model', "'off' or 'manual' for this plant",
                             f'needs a resonance, but the {plant.name} model has none')
    zetas = [-p.real / abs(p) for p in pairs]
    best = int(np.argmin(zetas))
    return float(abs(pairs[best])), float(zetas[best])


def notch_coefficients(omega_rad_s: float, zero_damping: float, pole_damping: float,
                       sample_time_s: float) -> tuple[tuple[float, float, float],
                                                      tuple[float, float, float]]:
    """
    Discretize the notch N(s) by the bilinear transform pre-warped at its centre.

    Parameters
    ----------
    omega_rad_s : float
        Centre w0 [rad/s], below the Nyquist frequency pi/T.
    zero_damping : float
        Damping of the zeros (0 = infinitely deep notch).
    pole_damping : float
        Damping of the poles (sets the width).
    sample_time_s : float
        Sample period T [s].

    Returns
    -------
    (b0, b1, b2), (1, a1, a2) : tuple of float
        N(z) = (b0 + b1 z^-1 + b2 z^-2) / (1 + a1 z^-1 + a2 z^-2); N(1) = 1.

    Raises
    ------
    ParameterError
        If w0 is not below the Nyquist frequency.

    """
    nyquist = math.pi / sample_time_s
    if not 0.0 < omega_rad_s < nyquist:
        raise ParameterError('notch.frequency_hz', omega_rad_s / (2.0 * math.pi),
                             f'(0, {nyquist / (2.0 * math.pi):g}) (below Nyquist)')
    w0 = omega_rad_s
    c = w0 / math.tan(w0 * sample_time_s / 2.0)  # pre-warping: N(e^{j w0 T}) = N(j w0)

    def quad(zeta: float) -> tuple[float, float, float]:
        return (c * c + 2.0 * zeta * w0 * c + w0 * w0, 2.0 * (w0 * w0 - c * c),
                c * c - 2.0 * zeta * w0 * c + w0 * w0)

    num = quad(zero_damping)
    den = quad(pole_damping)
    return ((num[0] / den[0], num[1] / den[0], num[2] / den[0]),
            (1.0, den[1] / den[0], den[2] / den[0]))


class NotchFilter:
    """
    Second-order section (transposed direct form II) on plain floats.

    Parameters
    ----------
    num : tuple of float
        (b0, b1, b2).
    den : tuple of float
        (1, a1, a2).

    """

    def __init__(self, num: tuple[float, float, float],
                 den: tuple[float, float, float]) -> None:
        self.num = num
        self.den = den
        self.reset(0.0)

    def reset(self, value: float) -> None:
        """Put the filter at rest with input and output ``value`` (N(1) = 1)."""
        b0, b1, b2 = self.num
        _, a1, a2 = self.den
        # steady state of the transposed form for a constant input u: y = u
        self._z2 = (b2 - a2) * value
        self._z1 = (b1 - a1) * value + self._z2

    def step(self, u: float) -> float:
        """Filter one sample ``u`` and return the output."""
        b0, b1, b2 = self.num
        _, a1, a2 = self.den
        y = b0 * u + self._z1
        self._z1 = b1 * u - a1 * y + self._z2
        self._z2 = b2 * u - a2 * y
        return y

    def bridge(self, last: float, u: float, gap: int) -> None:
        """
        Filter ``gap`` samples a stalled loop missed, before the sample whose input is ``u``.

        The input goes from the last one, ``last``, to ``u`` in equal steps, as if the filter
        had seen the commands ahead the stage played over them, instead of one jump that would
        ring. Every filter of a command that missed the samples must be bridged alike, so that
        what they cancel between them (the feed-forward's share of the RAC's model part)
        still cancels.
        """
        for j in range(1, gap + 1):
            self.step(last + (u - last) * j / (gap + 1))


class NotchedController(_Output):
    """
    A controller followed by a notch filter on its command, clipped again to the limits.

    Parameters
    ----------
    inner : RACController or PIController or OpenLoopController
        The controller whose command is filtered.
    notch : NotchFilter
        The filter (unity DC gain).
    output_min_v, output_max_v : float
        Command limits [V].

    """

    def __init__(self, inner: RACController | PIController | OpenLoopController,
                 notch: NotchFilter, *, output_min_v: float, output_max_v: float) -> None:
        self.inner = inner
        self.notch = notch
        self._vmin = output_min_v
        self._vmax = output_max_v
        self._u = inner.output_v
        self._fresh = True
        self._gap = 0
        self._last_in = 0.0

    @property
    def sample_time_s(self) -> float:
        """Return the sample period [s]."""
        return self.inner.sample_time_s

    @property
    def sensor_gain_v_per_m(self) -> float | None:
        """Return the inner controller's K_PSCM [V/m] (None: it has none)."""
        return self.inner.sensor_gain_v_per_m

    def reset(self, position_m: float, reference_m: float,
              output_v: float | None = None) -> None:
        """
        Reset the controller; the notch starts at rest at the first command it filters.

        Parameters
        ----------
        position_m, reference_m : float
            As for the inner controller [m].
        output_v : float, optional
            Voltage held before the start [V], returned on a refused first sample.

        """
        self.inner.reset(position_m, reference_m, output_v)
        self._u = self.inner.output_v
        # Starting the filter at rest at 0 V (or at a held voltage that differs from the first
        # command) would put a step through it at t = 0, whose ringing the RAC reads as a
        # tracking error and adapts to; at rest at its first input the filter adds nothing.
        self._fresh = True

    def step(self, position_m: float, reference_m: float, reference_velocity_mps: float,
             dt_s: float | None = None) -> float:
        """Return the filtered, clipped command [V] (arguments as the inner controller)."""
        inner = self.inner
        calls = inner.nonfinite_inputs + inner.bad_dt
        v = inner.step(position_m, reference_m, reference_velocity_mps, dt_s)
        if inner.nonfinite_inputs + inner.bad_dt != calls:
            return self._u  # a refused sample holds the output: the filter does not advance
        if self._fresh:
            self.notch.reset(v)
            self._fresh = False
        elif self._gap:
            # samples missed before this one: the notch's input goes there in equal steps
            self.notch.bridge(self._last_in, v, self._gap)
        self._gap = 0
        self._last_in = v
        f = self.notch.step(v)
        f = self._vmax if f > self._vmax else (self._vmin if f < self._vmin else f)
        self._u = f
        return f

    @property
    def diagnostic_names(self) -> tuple[str, ...]:
        """Return the inner controller's diagnostic names."""
        return self.inner.diagnostic_names

    def diagnostic_values(self) -> tuple[float, ...]:
        """Return the inner controller's diagnostic values."""
        return self.inner.diagnostic_values()

    def missed(self, samples: int) -> None:
        """
        Let ``samples`` missed samples pass before the next step.

        The inner controller goes on over them (:meth:`RACController.missed`); the notch gets,
        for each, the way from its last input to the next one in equal steps at that step, as
        if it had filtered the commands ahead, instead of one jump that would ring.
        """
        missed = getattr(self.inner, 'missed', None)
        if missed is not None:
            missed(samples)
        if samples > 0:
            self._gap = samples

    def reference_gains(self) -> tuple[float, float]:
        """Return the inner controller's (the notch's DC gain is 1)."""
        return self.inner.reference_gains()

    def linear_gains(self) -> tuple[float, float]:
        """Return the inner controller's (k_p, k_i) (the notch is not in them)."""
        return self.inner.linear_gains()

    def update_params(self, params: ControllerParams) -> bool:
        """
        Pass new gains to the inner controller when the notch stays as it is.

        As :meth:`RACController.update_params`, for the whole new configuration ``params``;
        applied in place, the filter keeps its state; a changed notch returns False too.
        """
        built = self.inner.built
        if built is None or params.notch != built.notch:
            return False
        return self.inner.update_params(params)

    def diagnostics(self) -> Mapping[str, float]:
        """Return the inner controller's diagnostics."""
        return self.inner.diagnostics()


def _same_structure(built: ControllerParams | None, new: ControllerParams, kind: str) -> bool:
    """Return whether ``new`` only changes gains of a ``kind`` controller built from ``built``."""
    return (built is not None and new.type == kind and built.type == kind
            and new.sensor_gain_v_per_m == built.sensor_gain_v_per_m
            and new.output_min_v == built.output_min_v
            and new.output_max_v == built.output_max_v)


def _check_sample_time(sample_time_s: float) -> None:
    if not (sample_time_s > 0.0 and math.isfinite(sample_time_s)):
        raise ParameterError('sample_time_s', sample_time_s, '(0, inf)')


def build_controller(params: ControllerParams, sample_time_s: float,
                     plant: LinearPlant | None = None,
                     hysteresis: HysteresisModel | None = None
                     ) -> RACController | PIController | OpenLoopController | NotchedController \
        | FeedForwardController:
    """
    Build the controller ``params.type`` names, with its notch filter if enabled.

    Parameters
    ----------
    params : ControllerParams
        Controller configuration.
    sample_time_s : float
        Sample period T [s], > 0.
    plant : LinearPlant, optional
        Model the notch is designed from when ``notch.mode == 'model'``, and the feed-forward
        inverts (required when ``feedforward.mode`` is not ``none``).
    hysteresis : HysteresisModel, optional
        Design hysteresis the feed-forward inverts; default the paper's stage.

    Returns
    -------
    Controller
        An object implementing :class:`piezo_stage_ros.core.contracts.interfaces.Controller`; with
        feed-forward a :class:`~piezo_stage_ros.core.control.feedforward.FeedForwardController`
        that must be bound to the trajectory (``bind``) before it adds anything.

    Raises
    ------
    ParameterError
        On a bad sample time, a notch in ``model`` mode without a plant with a resonance, or
        feed-forward without a plant model.

    """
    limits = {'output_min_v': params.output_min_v, 'output_max_v': params.output_max_v}
    inner: RACController | PIController | OpenLoopController
    if params.type == 'rac':
        inner = RACController(params.rac, sample_time_s,
                              sensor_gain_v_per_m=params.sensor_gain_v_per_m, built=params,
                              **limits)
    elif params.type == 'pi':
        inner = PIController(params.pi, sample_time_s,
                             sensor_gain_v_per_m=params.sensor_gain_v_per_m, built=params,
                             **limits)
    else:
        inner = OpenLoopController(params.open_loop, sample_time_s, built=params, **limits)
    coeffs = notch_design(params.notch, sample_time_s, plant)
    fb: RACController | PIController | OpenLoopController | NotchedController = inner
    if coeffs is not None:
        fb = NotchedController(inner, NotchFilter(*coeffs), **limits)
    if params.feedforward.mode == 'none':
        return fb
    if plant is None:
        raise ParameterError('feedforward.mode', params.feedforward.mode, "'none' without a "
                             'plant model', 'needs the design model it inverts')
    if hysteresis is None:
        hysteresis = make_hysteresis(HysteresisParams())
    return FeedForwardController(fb, params.feedforward, plant, hysteresis,
                                 sensor_gain_v_per_m=params.sensor_gain_v_per_m, **limits)


def bound_controller(params: ControllerParams, sample_time_s: float, plant: LinearPlant,
                     hysteresis: HysteresisModel, trajectory: Any
                     ) -> RACController | PIController | OpenLoopController | NotchedController \
        | FeedForwardController:
    """
    Return :func:`build_controller`'s controller, a feed-forward bound to ``trajectory``.

    What the nodes build: the reference ahead comes from the same trajectory parameters the
    trajectory node plays (a reference that differs from it, a trajectory switched at run time,
    gets feedback alone, counted in the ``ff_mismatches`` diagnostic).
    """
    ctrl = build_controller(params, sample_time_s, plant, hysteresis)
    if isinstance(ctrl, FeedForwardController):
        ctrl.bind(trajectory)
    return ctrl


def notch_design(params: NotchParams, sample_time_s: float, plant: LinearPlant | None = None
                 ) -> tuple[tuple[float, float, float], tuple[float, float, float]] | None:
    """
    Return the notch coefficients the parameters ask for, or None when it is off.

    Parameters
    ----------
    params : NotchParams
        Mode, frequency and dampings.
    sample_time_s : float
        Sample period T [s].
    plant : LinearPlant, optional
        Required in ``model`` mode.

    Returns
    -------
    tuple or None
        ``(num, den)`` as :func:`notch_coefficients` returns them.

    """
    if params.mode == 'off':
        return None
    if params.mode == 'model':
        if plant is None:
            raise ParameterError('notch.mode', 'model', "'off' or 'manual' without a plant model",
                                 'needs the plant model the notch is designed from')
        omega, zeta = plant_resonance(plant)
    else:
        omega, zeta = 2.0 * math.pi * params.frequency_hz, params.zero_damping
    return notch_coefficients(omega, zeta, params.pole_damping, sample_time_s)
