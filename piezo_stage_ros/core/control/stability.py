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
Frozen-parameter robust stability of the discrete-time loop: controller + held plant.

What the check proves, and what it does not. It proves that every *linear time-invariant*
loop obtained by freezing the RAC's estimates anywhere in their projection box (or at their
initial pair only, ``estimates: initial``), the hysteresis slope anywhere in
``[slope_min, slope_max]`` and the boundary layer in either region, with the configured
computational delay, has its closed-loop poles inside the unit circle: frozen-parameter
robust stability over the box. It does not prove that the running loop is stable: there the
estimates move, the robust term switches between sat(s/epsilon) = s/epsilon and +-1, the
hysteresis slope jumps at every reversal and the command saturates; a loop whose every frozen
member is stable can still be destabilised by such variation (slow variation cannot, fast
variation can). The adaptation bound below is a frozen-regressor linearization with a 2x gain
margin, not a proof either. Words used in the report: "stable over the box" for this verdict,
never "guaranteed".

On request (``check_stability(..., varying=True)``, :func:`varying_check`, and the ``check``
command by default) the check goes further: it searches a common quadratic Lyapunov function
for the loop whose estimates, robust-term gain sat(s/epsilon)/(s/epsilon) in [0, 1] and
hysteresis slope all vary in time inside their ranges (the estimates stay in the box whatever
the adaptation does: the projection). One found proves that loop exponentially stable for
every such sequence, and its signals bounded under bounded inputs (the reference, the
quantisers, the hysteresis' bounded part d): a real nonlinear certificate, short of the command
limits. The search is local: one not found proves nothing either way.

The loop is built as it runs (see :mod:`piezo_stage_ros.core.contracts.interfaces`): the
controller sees y_k and returns u_k, which reaches the plant ``delay_samples`` = d sample
periods later (the computational delay: the time to read, compute and write; 0 in the offline
runner, a fraction of a period in a servo that computes within the period, one period in a
target that applies the answer at its next tick) and is held until u_k+1 replaces it. With the
hysteresis replaced by a gain (its local slope dw/dv) and the controller by its linear part,
the loop transfer at the plant input is::

    L(z) = N(z) * C(z) * slope * K_PSCM * G_d(z)

with G_d(z) the exact discretization of the plant model from w [V] to x [m] under that delayed
hold (:func:`_plant_tf`: the modified z-transform, exact for a fractional d; d = 0 is
:meth:`piezo_stage_ros.core.model.linear.LinearPlant.discretize`), N(z) the notch filter and C(z)
the controller from sensor volts to the command (negative feedback)::

    PI:   C(z) = k_p + k_i T z/(z - 1)
    RAC:  C(z) = (k + phi_hat lambda - theta_hat) + k lambda T z/(z - 1)

where, for the RAC, k = k_d + k*/epsilon inside the boundary layer (|s| < epsilon) and k = k_d
outside it (there sat(s/epsilon) = +-1 is a constant); theta_hat and phi_hat are frozen. The
+theta_hat y term of eq. (36) is positive feedback and -phi_hat lambda e adds proportional gain.

The check samples every combination of: hysteresis slope on a grid over
``[slope_min, slope_max]`` (for eq. (21) the incremental slope dw/dv lies in [2 B1 - c, c]),
the RAC estimates at the four corners of their projection box and at their initial values
(``estimates: corners``) or only at their initial values, and both RAC regions, and reports
the poles and margins of each. It then checks the whole set, not only the samples: the
estimates enter the linear loop only through its proportional gain k_p = k + phi_hat lambda -
theta_hat, affine in them, so the box maps onto an interval of k_p, and the characteristic
polynomial den_L + num_L is affine in (slope k_p, slope k lambda). The family "every estimate
of the box x every slope" is therefore a polytope of polynomials (a trapezoid), and by the edge
theorem (Bartlett, Hollot and Huang 1988) every member has its roots inside the unit circle if
and only if its four edges do: a stable vertex and no edge along which a root reaches the
circle (:func:`_polytope_failure`, a frequency sweep with the exact crossing parameter). The
verdict :attr:`StabilityReport.stable` is the sampled cases and these box checks (each a
:class:`BoxCertificate`: a certificate of the frozen family, not of the time-varying loop).

The RAC's adaptation is a second, discrete loop (:func:`adaptation_bound`): where |s| exceeds
the adaptation's dead zone epsilon_a the updates theta_hat += -(T/n) gamma y s_a and
phi_hat += -(T/n) eta u_fd s_a move the command by q = y d(theta_hat) + u_fd d(phi_hat), and
with the regressors y, u_fd frozen::

    (z - 1) q = -g_eff H(z) q,   g = T (gamma y^2 + eta u_fd^2),   g_eff = g / (1 + kappa g)

where n = 1 + kappa g is the normalisation and H(z) is the response of s to an additive
command disturbance in the loop above (H(1) = 1/k). Every root must lie inside the unit
circle: g_eff < g_crit, the smallest critical gain over the estimate box, the slopes and the
regions where the adaptation acts (outside the boundary layer, k = k_d; and inside it,
k = k_d + k*/epsilon, when epsilon_a < epsilon); for a fixed g the family is again a polytope,
checked on its edges. The dead zone does not change this linear loop: for |s| > epsilon_a,
s_a = s - epsilon_a sign(s) has slope 1, inside it the adaptation stops (slope 0), a sector
[0, 1] nonlinearity whose every gain g' in [0, g] is below the first crossing g_crit. The
report requires g_eff <= g_crit / ADAPTATION_MARGIN at the largest regressors the stage can
produce (y_max: the largest output the command range can hold on the model; u_fd: lambda
y_max, a reference step across that range), or, for every regressor size, kappa >=
ADAPTATION_MARGIN / g_crit, since g_eff < 1/kappa whatever g is. It says which constraint
binds (the frozen loops' worst case or the adaptation bound) and by how much.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Callable, Sequence
import warnings

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError, StabilityError
from piezo_stage_ros.core.contracts.params import group, param, Params
from piezo_stage_ros.core.contracts.types import ComplexArray, FloatArray
from piezo_stage_ros.core.control.controllers import (
    build_controller,
    ControllerParams,
    notch_design,
    rac_linear_gains,
    RACParams,
)
from piezo_stage_ros.core.control.feedforward import (
    FeedForwardController,
    FeedForwardParams,
    kept_harmonics,
    MIN_PERIOD_SAMPLES,
    period_harmonics,
    phase_learning_convergence,
    process_sensitivity,
    whole_period,
)
from piezo_stage_ros.core.model.family import default_family, member_params
from piezo_stage_ros.core.model.hysteresis import HysteresisParams, make_hysteresis, NoHysteresis
from piezo_stage_ros.core.model.linear import LinearPlant, third_order_plant
from piezo_stage_ros.core.model.stage import linear_plant, PlantParams, StageParams

__all__ = ['ADAPTATION_MARGIN', 'AdaptationBound', 'BoxCertificate', 'CheckedBox',
           'LearningConvergence', 'VaryingCertificate', 'varying_check',
           'LoopCase', 'StabilityParams', 'StabilityReport', 'StabilityWarning',
           'adaptation_bound', 'check_stability', 'enforce', 'learning_check', 'loop_polynomials',
           'stability_plant']


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
    delay_samples: float = param(0.5, unit='samples', description='Computational delay of the '
                                 'loop: u_k reaches the plant this many sample periods after y_k '
                                 'is read (0: at t_k, as the offline runner applies it; a '
                                 'fraction: computed within the period; 1: at t_k+1). '
                                 'Fractional delays are discretised exactly (zero-order hold '
                                 'switched part-way through the period). 0.5 covers the '
                                 'in-process servo, which reads, computes and writes within '
                                 'the first half of the period; a UDP target that applies the '
                                 'answer at its next tick needs 1.', low=0.0, high=10.0)
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
    poles: ComplexArray = field(repr=False)

    @property
    def stable(self) -> bool:
        """Return whether every closed-loop pole is inside the unit circle."""
        return self.spectral_radius < 1.0


@dataclass(frozen=True)
class CheckedBox:
    """
    What the frozen-parameter check covered: the estimates, the slopes and the delay.

    Attributes
    ----------
    estimates : str
        ``'corners'`` (the whole projection box), ``'initial'`` (the initial pair only) or
        ``'none'`` (a controller without estimates).
    theta : tuple of float
        The theta_hat interval checked [V/V] (both ends the initial value with ``'initial'``).
    phi_s : tuple of float
        The phi_hat interval checked [s].
    slope : tuple of float
        The hysteresis slope interval [-].
    slope_points : int
        Slopes sampled for the margins (the interval itself is checked whole).
    delay_samples : float
        Computational delay assumed [samples].
    box_theta : tuple of float
        The projection bounds of theta_hat (what ``'initial'`` leaves out).
    box_phi_s : tuple of float
        The projection bounds of phi_hat [s].

    """

    estimates: str
    theta: tuple[float, float]
    phi_s: tuple[float, float]
    slope: tuple[float, float]
    slope_points: int
    delay_samples: float
    box_theta: tuple[float, float] = (0.0, 0.0)
    box_phi_s: tuple[float, float] = (0.0, 0.0)

    def text(self) -> str:
        """Return what was frozen where, in one clause."""
        lo, hi = self.slope
        slope = f'the hysteresis slope frozen anywhere in [{lo:.4g}, {hi:.4g}]'
        if self.estimates == 'none':
            return slope
        if self.estimates == 'initial':
            return (f'the estimates at their initial pair only (theta_hat = {self.theta[0]:g}, '
                    f'phi_hat = {self.phi_s[0]:g} s; the projection box theta_hat in '
                    f'[{self.box_theta[0]:g}, {self.box_theta[1]:g}] x phi_hat in '
                    f'[{self.box_phi_s[0]:g}, {self.box_phi_s[1]:g}] s was NOT checked), '
                    f'{slope} and either boundary-layer region')
        return (f'the estimates frozen anywhere in the box theta_hat in [{self.theta[0]:g}, '
                f'{self.theta[1]:g}] x phi_hat in [{self.phi_s[0]:g}, {self.phi_s[1]:g}] s, '
                f'{slope} and either boundary-layer region')


@dataclass(frozen=True)
class BoxCertificate:
    """
    Whether every frozen linear loop of one controller family is stable, not only the sampled.

    A certificate of the frozen-parameter family (edge theorem), not of the running loop
    whose parameters vary (module docstring).

    Attributes
    ----------
    label : str
        The family: region, range of the proportional gain over the estimate box and the
        slope interval.
    certified : bool
        Every loop with a proportional gain and a slope in those intervals is stable.
    detail : str
        Where it fails (empty when certified).

    """

    label: str
    certified: bool
    detail: str = ''


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
        g_crit: smallest per-sample gain that puts a root of (z - 1) + g H(z) on the unit
        circle, over every estimate in the box, every slope and every region where the
        adaptation acts [-]; 0 when a frozen loop is already unstable, inf when no gain up to
        1e4 does.
    worst_label : str
        The case that sets ``critical_gain``.
    normalisation : float
        kappa of the law: the effective per-sample gain is g / (1 + kappa g) [-].
    dead_zone_v : float
        epsilon_a, the adaptation's dead zone [V].
    regions : tuple of str
        Where the adaptation acts: ``'outside'`` the boundary layer, and ``'inside'`` it too
        when epsilon_a < epsilon.
    regressor : str
        ``'measured'`` (y, u_fd) or ``'desired'`` (y_d, dy_d/dt); with the desired ones the
        command moves by y d(theta_hat) + u_fd d(phi_hat) = -g s_a (gamma y y_d + eta u_fd
        dy_d/dt), the same loop gain while tracking (y = y_d, u_fd = dy_d/dt), which is the
        regime the frozen-regressor bound describes; y_max and lambda y_max bound both kinds.

    """

    gamma: float
    eta: float
    sample_time_s: float
    y_max_v: float
    u_fd_max_v_per_s: float
    critical_gain: float
    worst_label: str
    normalisation: float = 0.0
    dead_zone_v: float = 0.0
    regions: tuple[str, ...] = ('outside',)
    regressor: str = 'measured'

    @property
    def gain(self) -> float:
        """Return g = T (gamma y_max^2 + eta u_fd_max^2), the unnormalised per-sample gain [-]."""
        return self.sample_time_s * (self.gamma * self.y_max_v ** 2
                                     + self.eta * self.u_fd_max_v_per_s ** 2)

    @property
    def effective_gain(self) -> float:
        """Return g / (1 + kappa g) at the largest regressors [-]."""
        g = self.gain
        return g / (1.0 + self.normalisation * g)

    @property
    def all_regressors(self) -> bool:
        """Return whether kappa >= ADAPTATION_MARGIN / g_crit (bound for every regressor)."""
        return self.normalisation * self.critical_gain >= ADAPTATION_MARGIN

    @property
    def ok(self) -> bool:
        """Return whether g / (1 + kappa g) <= g_crit / ADAPTATION_MARGIN at y_max (or any)."""
        return (self.all_regressors
                or self.effective_gain * ADAPTATION_MARGIN <= self.critical_gain)

    @property
    def margin_db(self) -> float:
        """Return 20 log10(g_crit / (ADAPTATION_MARGIN g_eff)): >= 0 when :attr:`ok` [dB]."""
        g = self.effective_gain
        if self.all_regressors:
            g = 1.0 / self.normalisation   # the supremum over every regressor
        if g == 0.0:
            return math.inf
        if self.critical_gain == 0.0:
            return -math.inf
        return 20.0 * math.log10(self.critical_gain / (ADAPTATION_MARGIN * g))

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
            (g_lim / T - eta u_fd_max^2) / y_max^2, at least 0, with g_lim the largest raw
            gain whose normalised value is g_crit / ADAPTATION_MARGIN, G/(1 - kappa G) with
            G = g_crit / ADAPTATION_MARGIN; inf when kappa G >= 1 (every gain is within).

        """
        e = self.eta if eta is None else eta
        limit = self.critical_gain / ADAPTATION_MARGIN
        if self.normalisation * limit >= 1.0:
            return math.inf
        budget = limit / (1.0 - self.normalisation * limit) / self.sample_time_s
        return max((budget - e * self.u_fd_max_v_per_s ** 2) / self.y_max_v ** 2, 0.0)

    def text(self) -> str:
        """Return one sentence: the per-sample gain against the bound."""
        where = ' and '.join(self.regions)
        kappa = self.normalisation
        head = (f'Adaptation ({self.regressor} regressors, dead zone {self.dead_zone_v:g} V, '
                f'acts {where} the boundary layer, kappa = {kappa:g}): T (gamma y_max^2 + eta '
                'u_fd_max^2) = '
                f'{self.gain:.3g} at y_max = {self.y_max_v:.2f} V, u_fd_max = lambda y_max = '
                f'{self.u_fd_max_v_per_s:.3g} V/s')
        if kappa > 0.0:
            head += f', normalised g/(1 + kappa g) = {self.effective_gain:.3g} (< 1/kappa)'
        head += f'; discrete bound g_crit = {self.critical_gain:.3g} ({self.worst_label})'
        if self.all_regressors:
            return (head + f': kappa >= {ADAPTATION_MARGIN:g}/g_crit = '
                    f'{ADAPTATION_MARGIN / self.critical_gain:.3g}, within '
                    f'g_crit/{ADAPTATION_MARGIN:g} for every regressor size '
                    f'({self.margin_db:.1f} dB to spare).')
        need = (f' (kappa >= {ADAPTATION_MARGIN / self.critical_gain:.3g} would hold it for '
                'every regressor size)' if self.critical_gain > 0.0 else '')
        if self.ok:
            return (head + f', within g_crit/{ADAPTATION_MARGIN:g} up to y_max '
                    f'({self.margin_db:.1f} dB to spare){need}.')
        return (head + f': ABOVE g_crit/{ADAPTATION_MARGIN:g}, the estimates can limit-cycle '
                'between their bounds on a plateau or after a step; lower gamma (at most '
                f'{self.max_gamma():.3g} with this eta) or eta, or raise kappa{need}.')


@dataclass(frozen=True)
class LearningConvergence:
    """
    The learning feed-forward's contraction per period on the harmonics it learns.

    After period j the table moves by -gamma Q E_j / P_s (P_s the design model's process
    sensitivity); on a stage whose process sensitivity is P_true the error of a learned
    harmonic then follows E_{j+1} = (1 - gamma P_true / P_s) E_j: it converges monotonically,
    harmonic by harmonic, when every |1 - gamma P_true / P_s| < 1 (Q keeps the table inside
    its band, so the harmonics above it do not grow). On the design model itself the ratio is
    |1 - gamma|.

    Attributes
    ----------
    period_s : float
        The period learned over [s].
    harmonics : int
        Harmonics Q keeps.
    gain : float
        gamma.
    bandwidth_hz : float
        Q's band [Hz].
    design_ratio : float
        max |1 - gamma P_true / P_s| with P_true the design model at the hysteresis slope c
        the learning was designed with.
    slopes : tuple of (float, float)
        (slope, ratio) of the design model at each hysteresis slope of the check (learning
        without the model inverse: the hysteresis is in the loop); empty with the inverse.
    members : tuple of (str, float)
        (name, ratio) of every member of the stage family (:func:`~piezo_stage_ros.core.model.
        family.default_family`), the worst slope of each; empty when the family cannot be
        built (a plant other than the third-order one).
    note : str
        Why the family is missing, when it is.

    """

    period_s: float
    harmonics: int
    gain: float
    bandwidth_hz: float
    design_ratio: float
    slopes: tuple[tuple[float, float], ...] = ()
    members: tuple[tuple[str, float], ...] = ()
    note: str = ''

    @property
    def worst_member(self) -> tuple[str, float] | None:
        """Return the member with the largest ratio (None without a family)."""
        return max(self.members, key=lambda m: m[1]) if self.members else None

    @property
    def ratio(self) -> float:
        """Return the largest ratio over the design model, its slopes and the family."""
        return max([self.design_ratio, *(r for _, r in self.slopes),
                    *(r for _, r in self.members)])

    @property
    def ok(self) -> bool:
        """Return whether every learned harmonic converges monotonically on every case."""
        return self.ratio < 1.0

    @property
    def design_ok(self) -> bool:
        """Return whether it converges monotonically on the design model at every slope."""
        return max([self.design_ratio, *(r for _, r in self.slopes)]) < 1.0

    def text(self) -> str:
        """Return the verdict in one paragraph."""
        top_hz = self.harmonics / self.period_s if self.period_s > 0.0 else 0.0
        # Q reaches a little above its edge for a fast line's first harmonics: say how far
        reach = (f", a fast line's first harmonics to {top_hz:.0f} Hz"
                 if top_hz > self.bandwidth_hz * (1.0 + 1e-9) else '')
        head = (f'Learning (gamma {self.gain:g}, Q to {self.bandwidth_hz:g} Hz{reach}: '
                f'{self.harmonics} '
                f'harmonics of {self.period_s:g} s; assumes a linear loop: the command inside '
                'the amplifier range, the table inside learning_limit_v): per-period ratio '
                f'max|1 - gamma P_true/P_s| = {self.design_ratio:.3f} on the design model')
        if self.slopes:
            worst = max(self.slopes, key=lambda c: c[1])
            head += (f', {worst[1]:.3f} at worst over the hysteresis slopes '
                     f'[{self.slopes[0][0]:.4g}, {self.slopes[-1][0]:.4g}] (slope '
                     f'{worst[0]:.4g})')
        member = self.worst_member
        if member is not None:
            bad = [name for name, r in self.members if r >= 1.0]
            head += (f'; over the stage family ({len(self.members)} members) worst '
                     f'{member[1]:.3f} ({member[0]})')
            if bad:
                head += f', NOT CONVERGING on {len(bad)}: ' + ', '.join(bad)
        elif self.note:
            head += f'; {self.note}'
        if self.ok:
            return head + ': every learned harmonic converges monotonically.'
        if self.design_ok:
            return (head + ': monotone on the design model, not on every member (lower '
                    'learning_gain or learning_bandwidth_hz to cover them).')
        return (head + ': ABOVE 1 on the design model, the learning can grow the error; lower '
                'learning_gain or learning_bandwidth_hz.')


@dataclass(frozen=True)
class VaryingCertificate:
    """
    A common quadratic Lyapunov function of the loop whose parameters vary in time.

    The loop x_k+1 = A(p_k) x_k with p_k = (hysteresis slope, boundary-layer gain, estimates)
    anywhere in their box, in any sequence: A is multi-affine in p, so A(p) is a convex
    combination of the vertex matrices A_i, and V = x' P x with A_i' P A_i < P at every vertex
    decreases along every such sequence (:func:`varying_check`).

    Attributes
    ----------
    found : bool
        A P was found and verified at every vertex.
    contraction : float
        max_i ||A_i||_P, the largest factor by which sqrt(V) shrinks in one sample (< 1 when
        found) [-]; the best found when not.
    vertices : int
        Vertex matrices checked.
    estimates : str
        ``'corners'``, ``'initial'`` or ``'none'``: whether the estimates vary over the box.
    slope : tuple of float
        The interval the hysteresis slope varies in [-].
    layer : bool
        Whether the robust term's gain varies (a RAC: sat(s/epsilon)/(s/epsilon) in [0, 1]).

    """

    found: bool
    contraction: float
    vertices: int
    estimates: str
    slope: tuple[float, float]
    layer: bool

    def text(self) -> str:
        """Return what the certificate covers, or that none was found."""
        varying = []
        if self.estimates == 'corners':
            varying.append('the estimates varying anywhere in the box')
        if self.layer:
            varying.append('the robust term switching in and out of the boundary layer')
        varying.append(f'the hysteresis slope varying in [{self.slope[0]:.4g}, '
                       f'{self.slope[1]:.4g}]')
        what = ', '.join(varying)
        if not self.found:
            return (f'Time-varying loop: no common quadratic Lyapunov function found over '
                    f'{self.vertices} vertices (best contraction {self.contraction:.4f} per '
                    'sample; the search is not exhaustive), so its stability with '
                    f'{what} is not proven.')
        return (f'Time-varying loop: a common quadratic Lyapunov function over {self.vertices} '
                f'vertices (contraction {self.contraction:.4f} per sample) proves the loop '
                f'exponentially stable with {what} in any sequence, and every signal bounded '
                'under the bounded inputs (reference, quantisation, and the hysteresis as '
                'c v + d with |d| <= rho, c in that interval).')


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
    certificates : tuple of BoxCertificate
        The frozen families checked whole (edge theorem).
    learning : LearningConvergence or None
        The learning feed-forward's convergence, when it learns.
    box : CheckedBox or None
        What was frozen where, and the delay assumed.

    """

    controller: str
    plant: str
    sample_time_s: float
    cases: tuple[LoopCase, ...]
    adaptation: AdaptationBound | None = None
    certificates: tuple[BoxCertificate, ...] = ()
    learning: LearningConvergence | None = None
    box: CheckedBox | None = None
    varying: VaryingCertificate | None = None

    @property
    def stable(self) -> bool:
        """Return whether every sampled frozen loop and every frozen family is stable."""
        return (all(c.stable for c in self.cases)
                and all(c.certified for c in self.certificates))

    @property
    def certified(self) -> bool:
        """
        Return whether the frozen loops are stable and the adaptation is within its bound.

        Frozen-parameter robust stability over the checked box plus the linearized adaptation
        bound: what the check can say, not a guarantee for the running loop.
        """
        return self.stable and (self.adaptation is None or self.adaptation.ok)

    @property
    def delay_samples(self) -> float:
        """Return the computational delay the check assumed [samples]."""
        return self.box.delay_samples if self.box is not None else 0.0

    def scope(self) -> str:
        """Return one sentence: what is proven (or failed) and what is not proven."""
        failed = [c for c in self.certificates if not c.certified]
        what = self.box.text() if self.box is not None else 'the sampled loops'
        delay = _delay_text(self.delay_samples)
        n = len(self.certificates)
        if not self.stable:
            proven = f'NOT stable over what was checked ({what}, {delay}).'
        else:
            estimates = self.box.estimates if self.box is not None else 'none'
            kind = {'initial': 'Stable at the initial estimates only',
                    'corners': 'Frozen-parameter robust stability over the box'}.get(
                        estimates, 'Frozen-parameter robust stability over the slopes')
            proven = (f'{kind}: every linear time-invariant loop with {what} is stable with '
                      f'{delay} (edge theorem over {n} famil{"y" if n == 1 else "ies"}).')
        fails = ''.join(f' NOT STABLE OVER THE BOX: {c.label}, {c.detail}.' for c in failed)
        v = self.varying
        if v is not None and v.found:
            return (proven + fails + ' ' + v.text() + ' Not proven: the loop while the '
                    'command saturates (clipping and conditional integration), and any '
                    'convergence of the error or the estimates.')
        varying = ('estimates that move, a boundary layer that switches, '
                   if self.adaptation is not None else '')
        searched = (' ' + v.text()) if v is not None else (
            ' (the time-varying check was not run: the check command runs it)')
        unproven = (f' Not proven: the running loop, with {varying}a hysteresis slope that '
                    f'jumps at reversals and a command that saturates.{searched}')
        return proven + fails + unproven

    def as_dict(self) -> dict[str, object]:
        """
        Return the report as plain JSON-ready values.

        Returns
        -------
        dict
            Verdicts, margins, the worst case, the binding constraint, what was checked
            (``box``), the families, the adaptation bound, the learning and the words of
            :meth:`scope`.

        """
        w = self.worst

        def num(x: float) -> float | str:
            return x if math.isfinite(x) else ('inf' if x > 0 else '-inf')
        out: dict[str, object] = {
            'controller': self.controller, 'plant': self.plant,
            'sample_time_s': self.sample_time_s, 'delay_samples': self.delay_samples,
            'stable_over_box': self.stable, 'certified': self.certified,
            'spectral_radius': w.spectral_radius, 'worst_case': w.label,
            'gain_margin_db': num(self.gain_margin_db),
            'phase_margin_deg': num(self.phase_margin_deg),
            'worst_gain_margin_db': num(w.gain_margin_db),
            'worst_phase_margin_deg': num(w.phase_margin_deg),
            'loops_checked': len(self.cases),
            'loops_stable': sum(c.stable for c in self.cases),
            'binding': self.binding(), 'scope': self.scope(),
            'families': [{'label': c.label, 'stable': c.certified, 'detail': c.detail}
                         for c in self.certificates],
        }
        if self.box is not None:
            b = self.box
            out['box'] = {'estimates': b.estimates, 'theta': list(b.theta),
                          'phi_s': list(b.phi_s), 'slope': list(b.slope),
                          'slope_points': b.slope_points, 'delay_samples': b.delay_samples,
                          'projection_theta': list(b.box_theta),
                          'projection_phi_s': list(b.box_phi_s)}
        a = self.adaptation
        if a is not None:
            out['adaptation'] = {'ok': a.ok, 'gain': a.gain, 'effective_gain': a.effective_gain,
                                 'critical_gain': num(a.critical_gain),
                                 'margin_db': num(a.margin_db), 'worst_case': a.worst_label,
                                 'normalisation': a.normalisation, 'text': a.text()}
        if self.learning is not None:
            out['learning'] = {'ok': self.learning.ok, 'ratio': self.learning.ratio,
                               'text': self.learning.text()}
        if self.varying is not None:
            v = self.varying
            out['varying'] = {'found': v.found, 'contraction': v.contraction,
                              'vertices': v.vertices, 'text': v.text()}
        return out

    def binding(self) -> str:
        """
        Return which constraint binds and by how much.

        Returns
        -------
        str
            The frozen loops (their worst case, and the smallest gain margin over the cases,
            which must stay above 0 dB) or the adaptation bound (its gain ratio over the
            required ADAPTATION_MARGIN, in dB), whichever is closer to its limit; a failing
            constraint always binds.

        """
        w = self.worst
        loops = abs(self.gain_margin_db)
        loop_text = (f'the frozen loops (worst case {w.label}: spectral radius '
                     f'{w.spectral_radius:.4f}; smallest gain margin {_fmt(loops)} dB)')
        if not self.stable:
            return f'Binding constraint: {loop_text}, UNSTABLE.'
        a = self.adaptation
        if a is None or (a.ok and a.margin_db >= loops):
            return f'Binding constraint: {loop_text}.'
        state = 'within' if a.ok else 'ABOVE'
        return (f'Binding constraint: the adaptation bound, g {state} g_crit/'
                f'{ADAPTATION_MARGIN:g} by {a.margin_db:.1f} dB (frozen loops: {_fmt(loops)} '
                'dB gain margin).')

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
                f'{"STABLE" if self.stable else "UNSTABLE"} with parameters frozen, '
                f'{_delay_text(self.delay_samples)} '
                f'({len(self.cases) - len(unstable)}/{len(self.cases)} sampled linear loops '
                f'stable).')
        worst = (f' Worst case: {w.label}: spectral radius {w.spectral_radius:.4f}, gain '
                 f'margin {_fmt(w.gain_margin_db)} dB, phase margin '
                 f'{_fmt(w.phase_margin_deg)} deg.')
        margins = (f' Over all cases: smallest gain margin {_fmt(self.gain_margin_db)} dB, '
                   f'smallest phase margin {_fmt(self.phase_margin_deg)} deg (closest to 0).')
        extra = '' if self.adaptation is None else ' ' + self.adaptation.text()
        extra = ' ' + self.scope() + extra + ' ' + self.binding()
        if self.learning is not None:
            extra += ' ' + self.learning.text()
        if self.stable:
            return head + worst + margins + extra
        if w.stable:  # every sampled case is stable, but the box is not
            return head + worst + extra
        pole = w.poles[int(np.argmax(np.abs(w.poles)))]
        freq = abs(math.atan2(pole.imag, pole.real)) / (2.0 * math.pi * self.sample_time_s)
        advice = (f' The dominant closed-loop pole z = {pole.real:.4f}{pole.imag:+.4f}j lies '
                  f'outside the unit circle (oscillation near {freq:.0f} Hz): lower the '
                  'feedback gain (RAC: raise epsilon or lower k_d; PI: lower k_p/k_i), tighten '
                  'the projection bounds, or add a notch filter against a resonance.')
        return head + worst + advice + extra


def _delay_text(delay_samples: float) -> str:
    """Return e.g. '1 sample of computational delay'."""
    unit = 'sample' if delay_samples == 1.0 else 'samples'
    return f'{delay_samples:g} {unit} of computational delay'


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


def _plant_tf(plant: LinearPlant, sample_time_s: float, delay_samples: float = 0.0
              ) -> tuple[FloatArray, FloatArray]:
    """
    Return (num, den) of G(z) from w [V] to x [m] with the loop's delay, powers of z.

    Parameters
    ----------
    plant : LinearPlant
        Continuous-time model.
    sample_time_s : float
        T [s].
    delay_samples : float
        d = m + delta >= 0 [samples]: u_k is held from t_k + d T to t_k+1 + d T.

    Returns
    -------
    num, den : ndarray
        The exact discretisation (the modified z-transform of the held input): over
        [t_k, t_k+1) the plant sees u_k-m-1 until t_k + delta T and u_k-m after, so with
        Phi = exp(A T)::

            x_k+1 = Phi x_k + Gamma_0 u_k-m + Gamma_1 u_k-m-1
            Gamma_0 = int_0^((1 - delta) T) exp(A s) ds B
            Gamma_1 = exp(A (1 - delta) T) int_0^(delta T) exp(A s) ds B

        and G(z) = z^-m C (z I - Phi)^-1 (Gamma_0 + Gamma_1 / z). delta = 0 is the
        zero-order hold at the sample instants; delta -> 1 tends to one more whole sample.

    """
    m = math.floor(delay_samples)
    delta = delay_samples - m
    if delta == 0.0:
        num, den = plant.discretize(sample_time_s).transfer_function()
    else:
        from scipy.signal import ss2tf
        late = plant.discretize((1.0 - delta) * sample_time_s)
        early = plant.discretize(delta * sample_time_s)
        n = plant.order
        # state (x_k, u_k-m-1): the held command of the previous sample is a state
        ad = np.zeros((n + 1, n + 1))
        ad[:n, :n] = late.ad @ early.ad
        ad[:n, n] = late.ad @ early.bd[:, 0]
        bd = np.zeros((n + 1, 1))
        bd[:n, 0] = late.bd[:, 0]
        bd[n, 0] = 1.0
        c = np.r_[plant.c, 0.0]
        num2, den2 = ss2tf(ad, bd, c[None, :], np.zeros((1, 1)))
        num = np.asarray(num2, dtype=np.float64).ravel()
        den = np.asarray(den2, dtype=np.float64).ravel()
    if m:
        den = np.convolve(den, np.r_[1.0, np.zeros(m)])
    return np.asarray(num, dtype=np.float64), np.asarray(den, dtype=np.float64)


def _rac_pairs(r: RACParams, estimates: str) -> list[tuple[float, float]]:
    """Return the (theta_hat, phi_hat) pairs checked: the box's corners and the initial pair."""
    if estimates == 'corners':
        # the estimates enter only through the proportional gain, affine in them: the corners
        # give its extremes; the initial pair is checked too (the loop the run starts with)
        pairs = [(t, f) for t in (r.theta_min, r.theta_max) for f in (r.phi_min, r.phi_max)]
        pairs.append((r.theta_init, r.phi_init))
        return pairs
    return [(r.theta_init, r.phi_init)]


def _controller_families(params: ControllerParams, estimates: str
                         ) -> list[tuple[str, float, list[tuple[str, float]]]]:
    """
    Return the linear controllers checked, grouped by integral gain.

    Each family is (label, integral gain [1/s], [(case label, proportional gain [V/V]), ...]);
    inside a family only the proportional gain varies (the RAC's estimates), so its extremes
    and the slope interval span the polytope :func:`_polytope_failure` certifies.
    """
    if params.type == 'pi':
        p = params.pi
        label = f'PI k_p={p.k_p:g}, k_i={p.k_i:g}'
        return [(label, p.k_i, [(label, p.k_p)])]
    if params.type == 'open_loop':
        return [('open loop', 0.0, [('open loop', 0.0)])]
    r = params.rac
    out = []
    for region, k in (('inside', r.k_d + r.k_star_v / r.epsilon_v), ('outside', r.k_d)):
        head = f'RAC {region} boundary layer (k={k:g})'
        cases = [(f'{head}, theta_hat={theta:g}, phi_hat={phi:g}',
                  rac_linear_gains(k, r.lambda_per_s, theta, phi)[0])
                 for theta, phi in _rac_pairs(r, estimates)]
        out.append((head, k * r.lambda_per_s, cases))
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


def _unit_circle(sample_time_s: float) -> ComplexArray:
    """Return z = exp(j w T) on a log grid from 1e-4 of Nyquist up to (just below) Nyquist."""
    omega = np.geomspace(1e-4, 1.0, 10001) * math.pi / sample_time_s
    omega[-1] = math.pi / sample_time_s * (1.0 - 1e-9)
    return np.asarray(np.exp(1j * omega * sample_time_s), dtype=np.complex128)


def _margins(lz: ComplexArray, num: FloatArray, den: FloatArray
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
    g_num, g_den = _plant_tf(plant, sample_time_s, opts.delay_samples)
    return opts, plant, g_num, g_den, notch_design(controller_params.notch, sample_time_s, plant)


def check_stability(controller_params: ControllerParams, plant_params: PlantParams,
                    sample_time_s: float, *, options: StabilityParams | None = None,
                    period_s: float | None = None, stage: StageParams | None = None,
                    varying: bool = False) -> StabilityReport:
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
    period_s : float, optional
        The reference's period [s]: with a learning feed-forward the report holds its
        convergence (:func:`learning_check`; ``feedforward.period_s`` takes precedence).
    stage : StageParams, optional
        The configured stage, for the learning's design hysteresis and stage family.
    varying : bool
        Also search a common quadratic Lyapunov function of the time-varying loop
        (:func:`varying_check`, seconds rather than milliseconds).

    Returns
    -------
    StabilityReport
        Closed-loop poles, spectral radius and margins of every case, and the verdict; the
        learning's convergence and the time-varying certificate do not enter
        :attr:`StabilityReport.stable`.

    """
    opts, plant, g_num, g_den, notch = _loop_parts(controller_params, plant_params,
                                                   sample_time_s, options)
    # frequency response of everything but the controller, once: G(z) N(z), the delay in G
    z = _unit_circle(sample_time_s)
    rest = np.polyval(g_num, z) / np.polyval(g_den, z)
    if notch is not None:
        rest = rest * np.polyval(notch[0], z) / np.polyval(notch[1], z)
    cases: list[LoopCase] = []
    certificates: list[BoxCertificate] = []
    k_sensor = controller_params.sensor_gain_v_per_m
    grid = _circle_grid()

    def char(kp: float, ki: float, slope: float) -> FloatArray:
        num, den = loop_polynomials(kp, ki, k_sensor * slope, g_num, g_den, sample_time_s, notch)
        return _padd(den, num)

    for family, ki, members in _controller_families(controller_params, opts.estimates):
        for label, kp in members:
            for slope in opts.slopes():
                gain = k_sensor * slope
                poles = np.roots(char(kp, ki, slope)).astype(np.complex128)
                radius = float(np.max(np.abs(poles))) if poles.size else 0.0
                if kp == 0.0 and ki == 0.0:
                    gm, pm = math.inf, math.inf
                else:
                    num, den = loop_polynomials(kp, ki, gain, g_num, g_den, sample_time_s,
                                                notch)
                    lz = gain * (kp + ki * sample_time_s * z / (z - 1.0)) * rest
                    gm, pm = _margins(lz, num, den)
                cases.append(LoopCase(label=f'{label}, slope={slope:.4g}', slope=slope,
                                      spectral_radius=radius, gain_margin_db=gm,
                                      phase_margin_deg=pm, poles=poles))
        kps = [kp for _, kp in members]
        lo, hi = min(kps), max(kps)
        vertices = [(f'slope={sl:.4g}, k_p={kp:.4g}', char(kp, ki, sl))
                    for sl, kp in _rectangle(opts.slope_min, opts.slope_max, lo, hi)]
        failure = _polytope_failure(vertices, grid, sample_time_s)
        certificates.append(BoxCertificate(
            label=(f'{family}: k_p in [{lo:.4g}, {hi:.4g}] x slope in '
                   f'[{opts.slope_min:.4g}, {opts.slope_max:.4g}]'),
            certified=failure is None, detail=failure or ''))
    desc = {'rac': 'RAC', 'pi': 'PI', 'open_loop': 'open loop'}[controller_params.type]
    if controller_params.notch.mode != 'off':
        desc += f' + notch ({controller_params.notch.mode})'
    adaptation = None
    if controller_params.type == 'rac':
        adaptation = _adaptation(controller_params, plant, g_num, g_den, sample_time_s, notch,
                                 opts)
    learning = learning_check(controller_params, plant_params, sample_time_s,
                              period_s or 0.0, stage=stage, options=opts)
    return StabilityReport(controller=desc, plant=plant.name, sample_time_s=sample_time_s,
                           cases=tuple(cases), adaptation=adaptation,
                           certificates=tuple(certificates), learning=learning,
                           box=_checked_box(controller_params, opts),
                           varying=(_varying(controller_params, plant, g_num, g_den, notch,
                                             sample_time_s, opts) if varying else None))


def varying_check(controller_params: ControllerParams, plant_params: PlantParams,
                  sample_time_s: float, *, options: StabilityParams | None = None
                  ) -> VaryingCertificate:
    """
    Search a common quadratic Lyapunov function of the loop with time-varying parameters.

    Parameters
    ----------
    controller_params : ControllerParams
        Controller configuration (type, gains, box, notch).
    plant_params : PlantParams
        Plant model.
    sample_time_s : float
        T [s], > 0.
    options : StabilityParams, optional
        Slopes, estimates and delay; default :class:`StabilityParams`.

    Returns
    -------
    VaryingCertificate

    Notes
    -----
    The loop of the module docstring in state space (plant with its delayed hold, the
    integral, the notch), with the reference terms as bounded inputs, is x_k+1 = A x_k with
    the command v_k = -k_p e_k - k_i I_k; the time-varying parameters enter only through
    slope (k_p, k_i): the RAC's k_p = k + phi_hat lambda - theta_hat and k_i = k lambda with
    k = k_d + sigma k*/epsilon, sigma = sat(z)/z in [0, 1] for z = s/epsilon, and the slope
    multiplies the command. A is affine in each of slope, sigma and phi_hat lambda - theta_hat,
    so its values lie in the convex hull of the 2 x 2 x 2 vertex matrices, and
    [[P, A' P], [P A, P]] > 0 is affine in A: a P found at the vertices holds for every
    sequence. The search (BFGS on a smooth maximum of ||A_i||_P^2 over the Cholesky factor
    of P, from the Lyapunov solution of the mean vertex) may miss a P that exists; the one it
    returns is verified directly: P - A_i' P A_i positive definite at every vertex.

    """
    opts, plant, g_num, g_den, notch = _loop_parts(controller_params, plant_params,
                                                   sample_time_s, options)
    return _varying(controller_params, plant, g_num, g_den, notch, sample_time_s, opts)


def _varying(params: ControllerParams, plant: LinearPlant, g_num: FloatArray,
             g_den: FloatArray, notch: tuple[Sequence[float], Sequence[float]] | None,
             sample_time_s: float, opts: StabilityParams) -> VaryingCertificate:
    """Return the :class:`VaryingCertificate` of a loop (see varying_check)."""
    matrices = _vertex_matrices(params, g_num, g_den, notch, sample_time_s, opts)
    found, contraction = _common_lyapunov(matrices)
    box = _checked_box(params, opts)
    return VaryingCertificate(found=found, contraction=contraction, vertices=len(matrices),
                              estimates=box.estimates, slope=box.slope,
                              layer=params.type == 'rac')


def _vertex_matrices(params: ControllerParams, g_num: FloatArray, g_den: FloatArray,
                     notch: tuple[Sequence[float], Sequence[float]] | None,
                     sample_time_s: float, opts: StabilityParams) -> list[FloatArray]:
    """Return the closed-loop state matrices at the vertices of (k_p, k_i) x slope."""
    from scipy.signal import tf2ss
    num = np.trim_zeros(np.asarray(g_num, dtype=np.float64), 'f')
    a, b, c, d = tf2ss(num, g_den)
    if np.any(d):  # the hold makes G(z) strictly proper; a feedthrough would close a loop
        raise ValueError('the discretized plant has a direct feedthrough')
    if notch is not None:
        an, bn, cn, dn = tf2ss(np.asarray(notch[0], dtype=np.float64),
                               np.asarray(notch[1], dtype=np.float64))
    else:
        an, bn, cn, dn = (np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)),
                          np.ones((1, 1)))
    n, m = a.shape[0], an.shape[0]
    t = sample_time_s
    kc = params.sensor_gain_v_per_m * c[0]          # e_k = K C x_k (the reference aside)
    gains: list[tuple[float, float]] = []
    for _, ki, members in _controller_families(params, opts.estimates):
        kps = [kp for _, kp in members]
        for kp in sorted({min(kps), max(kps)}):
            gains.append((kp, ki))
    out = []
    # without integral action the integral is no state of the loop (an idle integrator would
    # sit on the unit circle)
    integral = any(ki != 0.0 for _, ki in gains)
    for slope in sorted({opts.slope_min, opts.slope_max}):
        for kp, ki in gains:
            # v_k = -(k_p + k_i T) K C x_k - k_i I_k-1;  I_k = I_k-1 + T K C x_k
            v_x = -(kp + ki * t) * kc
            big = np.zeros((n + 1 + m, n + 1 + m))
            big[:n, :n] = a + slope * dn[0, 0] * np.outer(b[:, 0], v_x)
            big[:n, n] = slope * dn[0, 0] * b[:, 0] * -ki
            big[:n, n + 1:] = slope * np.outer(b[:, 0], cn[0])
            big[n, :n] = t * kc
            big[n, n] = 1.0
            big[n + 1:, :n] = np.outer(bn[:, 0], v_x)
            big[n + 1:, n] = bn[:, 0] * -ki
            big[n + 1:, n + 1:] = an
            out.append(big if integral else np.delete(np.delete(big, n, 0), n, 1))
    return out


def _common_lyapunov(matrices: Sequence[FloatArray]) -> tuple[bool, float]:
    """
    Return (verified, max_i ||A_i||_P) for the best P a local search finds.

    The search minimises a smooth maximum (log-sum-exp, sharpened in steps) of the largest
    eigenvalue of L^-1 A_i' P A_i L^-T over the Cholesky factor L of P = L L'. The P it ends
    with counts only if P - A_i' P A_i is positive definite at every vertex with a margin of
    1e-9 of ||P|| (rounding of the 2-norm products is near 1e-15 of it) and P is not
    ill-conditioned (condition number below 1e12).
    """
    from scipy.linalg import (
        cho_factor,
        matrix_balance,
        solve_discrete_lyapunov,
        solve_triangular,
    )
    from scipy.optimize import minimize
    size = matrices[0].shape[0]
    # a diagonal similarity by powers of two (exact in floating point) evens the states'
    # scales (plant states in metres, the integral in volt-seconds): a P for the balanced
    # matrices is one for the originals
    _, (scale_vec, _) = matrix_balance(np.mean(np.stack(matrices), axis=0), permute=False,
                                      separate=True)
    matrices = [a * scale_vec[None, :] / scale_vec[:, None] for a in matrices]
    mean = np.mean(np.stack(matrices), axis=0)
    try:
        start = solve_discrete_lyapunov(mean.T, np.eye(size))
        chol = np.linalg.cholesky(start / (np.trace(start) / size))
    except (np.linalg.LinAlgError, ValueError):
        chol = np.eye(size)
    lower = np.tril_indices(size)

    def norms(x: FloatArray) -> FloatArray:
        factor = np.zeros((size, size))
        factor[lower] = x
        p = factor @ factor.T
        try:
            lc = np.linalg.cholesky(p)
        except np.linalg.LinAlgError:
            return np.full(len(matrices), 1e6)
        out = []
        for a in matrices:
            m = solve_triangular(lc, a.T @ p @ a, lower=True)
            m = solve_triangular(lc, m.T, lower=True)
            out.append(np.linalg.eigvalsh(0.5 * (m + m.T))[-1])
        return np.asarray(out)

    x = chol[lower]

    def feasible(x: FloatArray) -> bool:
        return bool(np.max(norms(x)) < 1.0 - 1e-6)

    for sharpness in (30.0, 300.0):
        if feasible(x):
            break

        def smooth_max(x: FloatArray, beta: float = sharpness) -> float:
            v = norms(x)
            top = float(np.max(v))
            return top + float(np.log(np.sum(np.exp(beta * (v - top))))) / beta

        best = [x]

        def stop(xk: FloatArray, best: list[FloatArray] = best) -> None:
            # feasibility, not the optimum, is what is asked: stop at the first P that holds
            best[0] = np.array(xk, copy=True)
            if feasible(xk):
                raise StopIteration
        try:
            x = minimize(smooth_max, x, method='BFGS', callback=stop,
                         options={'maxiter': 120}).x
        except StopIteration:  # scipy before 1.11 lets it through
            x = best[0]
        if feasible(best[0]):
            x = best[0]
    factor = np.zeros((size, size))
    factor[lower] = x
    p = factor @ factor.T
    contraction = math.sqrt(max(float(np.max(norms(x))), 0.0))
    scale = float(np.linalg.norm(p, 2))
    ok = scale > 0.0 and np.linalg.cond(p) < 1e12
    for a in matrices if ok else []:
        gap = p - a.T @ p @ a
        ok = ok and float(np.linalg.eigvalsh(0.5 * (gap + gap.T))[0]) > 1e-9 * scale
    try:
        cho_factor(p)
    except np.linalg.LinAlgError:
        ok = False
    return bool(ok and contraction < 1.0), contraction


def _checked_box(params: ControllerParams, opts: StabilityParams) -> CheckedBox:
    """Return what a check of ``params`` with ``opts`` freezes where."""
    r = params.rac
    slope = (opts.slope_min, opts.slope_max)
    if params.type != 'rac':
        return CheckedBox('none', (0.0, 0.0), (0.0, 0.0), slope, opts.slope_points,
                          opts.delay_samples)
    box_theta, box_phi = (r.theta_min, r.theta_max), (r.phi_min, r.phi_max)
    if opts.estimates == 'initial':
        theta, phi = (r.theta_init, r.theta_init), (r.phi_init, r.phi_init)
    else:
        theta, phi = box_theta, box_phi
    return CheckedBox(opts.estimates, theta, phi, slope, opts.slope_points, opts.delay_samples,
                      box_theta, box_phi)


def learning_check(controller_params: ControllerParams, plant_params: PlantParams,
                   sample_time_s: float, period_s: float, *, stage: StageParams | None = None,
                   options: StabilityParams | None = None) -> LearningConvergence | None:
    """
    Return the learning feed-forward's per-period convergence ratios (None when it is off).

    Parameters
    ----------
    controller_params : ControllerParams
        Controller configuration; nothing is checked unless ``feedforward.mode`` learns.
    plant_params : PlantParams
        The design model the learning filter is designed on.
    sample_time_s : float
        T [s].
    period_s : float
        The period learned over [s] (``feedforward.period_s`` when set, else the
        trajectory's), any length of at least four samples (None is returned for a shorter
        one or none); a period that is not a whole number of samples adds the leakage of its
        windows (:func:`~piezo_stage_ros.core.control.feedforward.phase_learning_convergence`).
    stage : StageParams, optional
        The configured stage: its hysteresis is the design hysteresis (slope c), and the
        stage family of ``robustness`` is built from it; default the paper's stage, without
        the family.
    options : StabilityParams, optional
        Its hysteresis slopes are checked when the model inverse is off.

    Returns
    -------
    LearningConvergence or None

    """
    ff = controller_params.feedforward
    if not ff.learning:
        return None
    period = ff.period_s or period_s
    whole, n = whole_period(period, sample_time_s)
    if n < MIN_PERIOD_SAMPLES:
        return None
    opts = options if options is not None else StabilityParams()
    hysteresis = make_hysteresis(stage.hysteresis if stage is not None
                                 else HysteresisParams())
    c = 1.0 if isinstance(hysteresis, NoHysteresis) else float(hysteresis.slope)
    plant = stability_plant(plant_params)
    z = period_harmonics(n)
    # the feedback controller as the feed-forward linearizes it (initial estimates)
    fb = build_controller(controller_params.replace(feedforward=FeedForwardParams()),
                          sample_time_s, plant)
    assert not isinstance(fb, FeedForwardController)  # mode none builds none
    k_p, k_i = fb.linear_gains()
    notch = notch_design(controller_params.notch, sample_time_s, plant)
    k = controller_params.sensor_gain_v_per_m

    def sensitivity(model: LinearPlant, slope: float,
                    delay: float = opts.delay_samples) -> ComplexArray:
        # the learning filter is designed without the computational delay; the loop it
        # learns on has it
        num, den = _plant_tf(model, sample_time_s, delay)
        g = slope * np.polyval(num, z) / np.polyval(den, z)
        return process_sensitivity(g, z, k_p, k_i, k, sample_time_s, notch)
    design = sensitivity(plant, c, 0.0)
    kept = kept_harmonics(design, n, sample_time_s, ff.learning_bandwidth_hz)

    def convergence(design: ComplexArray, true: ComplexArray, gain: float,
                    kept: FloatArray) -> float:
        return phase_learning_convergence(design, true, gain, kept, n)
    # with the inverse the compensator removes the design hysteresis; without it the loop
    # sees the hysteresis' incremental slope
    slopes = () if ff.inverse else opts.slopes()

    def ratio(model: LinearPlant) -> float:
        return max(convergence(design, sensitivity(model, s), ff.learning_gain, kept)
                   for s in (slopes or (c,)))
    members: list[tuple[str, float]] = []
    note = ''
    if stage is None:
        note = 'no stage given: the family is not checked'
    elif stage.plant.model != 'third_order':
        note = f'the stage family varies the third-order plant, not {stage.plant.model}'
    else:
        members = [(m.name, ratio(stability_plant(member_params(stage, m).plant)))
                   for m in default_family()]
    return LearningConvergence(
        period_s=whole * sample_time_s if whole else period, harmonics=int(np.sum(kept)),
        gain=ff.learning_gain,
        bandwidth_hz=ff.learning_bandwidth_hz,
        design_ratio=convergence(design, sensitivity(plant, c), ff.learning_gain, kept),
        slopes=tuple((s, convergence(design, sensitivity(plant, s), ff.learning_gain,
                                     kept)) for s in slopes),
        members=tuple(members), note=note)


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
    # s = ((1 + lambda T) z - 1)/(z - 1) e for a constant reference (backward rectangle)
    s_num = np.array([1.0 + r.lambda_per_s * sample_time_s, -1.0])
    # the adaptation acts where |s| > epsilon_a: outside the boundary layer always, and inside
    # it too when its dead zone is narrower than the layer (there k = k_d + k*/epsilon)
    regions = [('outside', r.k_d)]
    if r.adaptation_dead_zone_v < r.epsilon_v:
        regions.insert(0, ('inside', r.k_d + r.k_star_v / r.epsilon_v))
    grid = _circle_grid()

    def parts(k: float, kp: float, slope: float) -> tuple[FloatArray, FloatArray]:
        # y/d = P N z^-delay / (1 + L) = gain g_num n_num (z - 1) / (l_den + l_num) for a
        # disturbance d added to the command, and s = y ((1 + lambda T) z - 1)/(z - 1):
        # H(z) = h_num / char_l, and the adaptation loop is (z - 1) char_l + g h_num = 0
        gain = k_sensor * slope
        l_num, l_den = loop_polynomials(kp, k * r.lambda_per_s, gain, g_num, g_den,
                                        sample_time_s, notch)
        h_num = np.convolve(g_num * gain, s_num)
        if notch is not None:
            h_num = np.convolve(h_num, np.asarray(notch[0], dtype=np.float64))
        base = np.convolve(_padd(l_den, l_num), [1.0, -1.0])
        n = max(len(base), len(h_num))
        return np.pad(base, (n - len(base), 0)), np.pad(h_num, (n - len(h_num), 0))

    best = (math.inf, 'no case')
    box = math.inf
    pairs = _rac_pairs(r, opts.estimates)
    for region, k in regions:
        sampled = (math.inf, 'no case')
        for theta, phi in pairs:
            kp = k + phi * r.lambda_per_s - theta
            for slope in opts.slopes():
                base, h_num = parts(k, kp, slope)

                def stable_at(g: float, b: FloatArray = base, h: FloatArray = h_num) -> bool:
                    return _radius(b + g * h) < 1.0

                crit = _critical_gain(stable_at)
                if crit < sampled[0]:
                    sampled = (crit, f'{region} boundary layer (k={k:g}), theta_hat={theta:g}, '
                               f'phi_hat={phi:g}, slope={slope:.4g}')
        if sampled[0] < best[0]:
            best = sampled
        # the whole box x every slope: the polynomials at a fixed g are affine in
        # slope (k_p, k lambda, g), a polytope whose edges decide (edge theorem)
        kps = [k + phi * r.lambda_per_s - theta for theta, phi in pairs]
        corners = [(sl, kp, *parts(k, kp, sl))
                   for sl, kp in _rectangle(opts.slope_min, opts.slope_max, min(kps), max(kps))]

        def box_stable(g: float, corners: list[tuple[float, float, FloatArray, FloatArray]]
                       = corners) -> bool:
            verts = [(f'slope={sl:.4g}, k_p={kp:.4g}', b + g * h) for sl, kp, b, h in corners]
            return _polytope_failure(verts, grid, sample_time_s) is None

        top = sampled[0]
        if math.isinf(top):
            top = _G_MAX
        if top == 0.0 or box_stable(top * (1.0 - 1e-3)):
            g_box = top
        else:
            g_box = _critical_gain(box_stable, g_max=top)
        box = min(box, g_box)
    label = best[1]
    if box < best[0] * (1.0 - 2e-3):
        label = f'inside the box, below every sampled case ({label} gives {best[0]:.3g})'
    return AdaptationBound(gamma=r.gamma, eta=r.eta, sample_time_s=sample_time_s,
                           y_max_v=y_max, u_fd_max_v_per_s=r.lambda_per_s * y_max,
                           critical_gain=min(box, best[0]), worst_label=label,
                           normalisation=r.normalisation,
                           dead_zone_v=r.adaptation_dead_zone_v,
                           regions=tuple(region for region, _ in regions),
                           regressor=r.adaptation_regressor)


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


def _radius(poly: FloatArray) -> float:
    """Return the largest |root| of a polynomial (leading coefficient != 0)."""
    return float(np.max(np.abs(np.roots(poly))))


#: Largest adaptation gain searched by :func:`_critical_gain`.
_G_MAX = 1e4


def _critical_gain(stable: Callable[[float], bool], *, g_max: float = _G_MAX) -> float:
    """
    Return the smallest g > 0 at which a loop whose stability ``stable(g)`` tells turns unstable.

    Parameters
    ----------
    stable : callable
        Whether the loop (or family of loops) with adaptation gain g is stable.
    g_max : float
        Largest gain searched; ``inf`` is returned when every gain up to it is stable.

    Returns
    -------
    float
        g_crit [-], to a relative 1e-3 (from below): the first gain of a geometric grid from
        1e-4 to ``g_max`` that is unstable, refined by bisection; 0 when small gains are
        already unstable.

    """
    grid = np.geomspace(min(1e-4, 0.5 * g_max), g_max, 33)
    lo = 0.0
    for g in grid:
        if not stable(float(g)):
            hi = float(g)
            break
        lo = float(g)
    else:
        return math.inf
    if lo == 0.0:
        return 0.0
    while hi - lo > 1e-3 * hi:
        mid = 0.5 * (lo + hi)
        if stable(mid):
            lo = mid
        else:
            hi = mid
    return lo


def _rectangle(slope_lo: float, slope_hi: float, kp_lo: float, kp_hi: float
               ) -> list[tuple[float, float]]:
    """Return the (slope, k_p) corners in cyclic order, without repeating a degenerate side."""
    corners = [(slope_lo, kp_lo), (slope_lo, kp_hi), (slope_hi, kp_hi), (slope_hi, kp_lo)]
    out: list[tuple[float, float]] = []
    for c in corners:
        if c not in out:
            out.append(c)
    return out


def _circle_grid(points: int = 16384) -> ComplexArray:
    """Return z = exp(j w) for w evenly spaced strictly inside (0, pi) (z = +-1 apart)."""
    w = np.linspace(0.0, math.pi, points + 2)[1:-1]
    return np.asarray(np.exp(1j * w), dtype=np.complex128)


def _edge_crossing(f0: FloatArray, f1: FloatArray, grid: ComplexArray
                   ) -> tuple[float, float] | None:
    """
    Return the first point of a segment of polynomials with a root on the unit circle.

    Parameters
    ----------
    f0, f1 : ndarray
        End polynomials (same length, powers of z, highest first).
    grid : ndarray
        Points of the upper unit circle strictly between z = 1 and z = -1.

    Returns
    -------
    (t, w) or None
        The smallest t in [0, 1] for which f0 + t (f1 - f0) vanishes at some z = exp(j w),
        w in [0, pi] [rad/sample]; None when there is none.

    Notes
    -----
    f0(z) + t q(z) = 0 with t real needs f0(z) conj(q(z)) real: the sign changes of its
    imaginary part over the grid locate the candidates (linear interpolation between grid
    points; a 0.2 mrad grid resolves resonances with damping down to about 1e-3 at 10 kHz),
    where t = -Re(f0 conj q)/|q|^2. At z = +-1 every value is real and t is exact.

    """
    q = f1 - f0
    if not np.any(q):
        return None
    fv = np.polyval(f0, grid)
    qv = np.polyval(q, grid)
    w = fv * np.conj(qv)
    im = w.imag
    re = w.real
    qq = (qv * np.conj(qv)).real
    ang = np.angle(grid)
    hits: list[tuple[float, float]] = []
    for i in np.flatnonzero(np.signbit(im[:-1]) != np.signbit(im[1:])):
        a = im[i] / (im[i] - im[i + 1])
        den = qq[i] + a * (qq[i + 1] - qq[i])
        if den > 0.0:
            hits.append((float(-(re[i] + a * (re[i + 1] - re[i])) / den),
                         float(ang[i] + a * (ang[i + 1] - ang[i]))))
    for zz, wz in ((1.0, 0.0), (-1.0, math.pi)):
        qz = float(np.polyval(q, zz))
        if qz != 0.0:
            hits.append((-float(np.polyval(f0, zz)) / qz, wz))
    inside = [h for h in hits if -1e-9 <= h[0] <= 1.0 + 1e-9]
    return min(inside) if inside else None


def _polytope_failure(vertices: Sequence[tuple[str, FloatArray]],
                      grid: ComplexArray, sample_time_s: float) -> str | None:
    """
    Return None when every polynomial of a polytope is Schur stable, else where it fails.

    Parameters
    ----------
    vertices : sequence of (label, polynomial)
        The polytope's vertices in cyclic order (each edge joins two neighbours); the family
        is every convex combination. Leading coefficients must not vanish on it.
    grid : ndarray
        Points of the upper unit circle for :func:`_edge_crossing`.
    sample_time_s : float
        T [s], to report the frequency of a crossing in Hz.

    Returns
    -------
    str or None
        Which vertex is unstable, or between which vertices a root reaches the unit circle.

    Notes
    -----
    By the edge theorem (Bartlett, Hollot and Huang, 1988) a polytope of polynomials of
    constant degree has every root inside a simply connected region (here the unit disc) if
    and only if every polynomial on its exposed edges has: a stable vertex and no edge that
    puts a root on the circle.

    """
    n = max(len(v) for _, v in vertices)
    verts = [(label, np.pad(v, (n - len(v), 0))) for label, v in vertices]
    for label, v in verts:
        radius = _radius(v)
        if radius >= 1.0:
            return f'at {label}: spectral radius {radius:.4f}'
    edges = [(i, (i + 1) % len(verts)) for i in range(len(verts) if len(verts) > 2 else 1)]
    for i, j in edges if len(verts) > 1 else []:
        hit = _edge_crossing(verts[i][1], verts[j][1], grid)
        if hit is not None:
            t, w = hit
            freq = w / (2.0 * math.pi * sample_time_s)
            return (f'between {verts[i][0]} and {verts[j][0]} (t = {t:.3g}): a root reaches '
                    f'the unit circle at {freq:.0f} Hz')
    return None
