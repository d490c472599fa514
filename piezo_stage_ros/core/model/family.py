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
A family of stages unlike the model: the members a robust adaptive controller must serve.

One member is the configured (nominal) stage with some of its physical properties scaled. The
third-order plant (17) is varied in its factored form

    G(s) = K / (s^3 + a0 s^2 + a1 s + a2) = g a2 / ((s + 1/tau) (s^2 + 2 zeta w_n s + w_n^2))

with the DC gain g = K/a2, so that omega_n, zeta and tau move one at a time and the others stay
(:func:`piezo_stage_ros.core.model.linear.factors_of` and ``third_order_of``):

    a0 = 1/tau + 2 zeta w_n,   a1 = w_n^2 + 2 zeta w_n / tau,   a2 = w_n^2 / tau,   K = g a2.

What each variable stands for (:data:`RANGES` holds the declared ranges):

- ``gain``: K (``plant.third_order.gain``) times the factor, i.e. the DC gain: another unit of
  the same type, another amplifier or sensor calibration, ageing of the piezo;
- ``omega_n``: the resonance at the same DC gain (a load on the platform lowers it);
- ``zeta``: the damping of the resonance (the lightly damped mode of model (20));
- ``tau``: the real pole of the amplifier-actuator lag;
- ``alpha``, ``b1``: the backlash-like hysteresis (21) (rate and B1; c, the slope the
  controller's theta and phi refer to, stays);
- ``noise_m``: white sensor noise [m rms] (``chain.sensor_noise_std_m``).

The true parameters of the RAC for a member (:func:`true_estimates`), in the controller's units
(sensor volts in, amplifier volts out; design brief "Units"): at low frequency the third-order
plant behaves as g / (T_1 s + 1) with T_1 = a1/a2 = tau + 2 zeta / w_n (the first-order term of
its series in s; for model (20) T_1 = 2.445e-4 s, exactly the time constant of the paper's reduced
model (25)). With the sensor gain K_PSCM and the hysteresis slope c, the reduced plant in sensor
volts is dy/dt = -a y + b c v with a = 1/T_1 and b = a K_PSCM g, so

    theta = a/(b c) = 1/(K_PSCM g c),        phi = 1/(b c) = T_1 theta,

which gives the nominal theta = 1.293 and phi = 3.161e-4 s of docs/explanation/controllers.md.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
import math

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.linear import factors_of, LinearFactors, third_order_of
from piezo_stage_ros.core.model.stage import linear_plant, StageParams

__all__ = ['RANGES', 'StageVariation', 'default_family', 'member_params', 'sample_family',
           'true_estimates']

#: Declared range of each variable of the family: (low, high, what it scales). Factors are
#: relative to the configured stage; ``noise_m`` is absolute [m rms].
RANGES: dict[str, tuple[float, float, str]] = {
    'gain': (0.7, 1.4, 'K of eq. (17), i.e. the DC gain (plant.third_order.gain)'),
    'omega_n': (0.9, 1.1, 'natural frequency of the resonance, same DC gain (a load)'),
    'zeta': (0.7, 1.5, 'damping of the resonance'),
    'tau': (0.7, 1.3, 'time constant of the real pole'),
    'alpha': (0.7, 1.3, 'alpha of the backlash-like hysteresis (21)'),
    'b1': (0.97, 1.03, 'B1 of the backlash-like hysteresis (21)'),
    'noise_m': (0.0, 3e-9, 'white sensor noise [m rms] (chain.sensor_noise_std_m)'),
}


@dataclass(frozen=True)
class StageVariation:
    """
    One member of the family: a name and the factors applied to the configured stage.

    Attributes
    ----------
    name : str
        Short unique label (used in tables, JSON and plots).
    gain, omega_n, zeta, tau, alpha, b1 : float
        Factors on the configured value (1 = nominal), > 0.
    noise_m : float
        Sensor noise of the member [m rms], >= 0 (replaces the configured one).

    """

    name: str
    gain: float = 1.0
    omega_n: float = 1.0
    zeta: float = 1.0
    tau: float = 1.0
    alpha: float = 1.0
    b1: float = 1.0
    noise_m: float = 0.0

    def __post_init__(self) -> None:
        if not self.name:
            raise ParameterError('name', self.name, 'a non-empty label')
        for f in fields(self):
            if f.name == 'name':
                continue
            value = getattr(self, f.name)
            ok = value >= 0.0 if f.name == 'noise_m' else value > 0.0
            if not (ok and math.isfinite(value)):
                raise ParameterError(f.name, value, '[0, inf)' if f.name == 'noise_m'
                                     else '(0, inf)')

    def changes(self) -> dict[str, float]:
        """Return the variables that differ from the nominal stage, with their values."""
        return {f.name: getattr(self, f.name) for f in fields(self)
                if f.name != 'name' and getattr(self, f.name) != (0.0 if f.name == 'noise_m'
                                                                   else 1.0)}

    def describe(self) -> str:
        """Return e.g. ``'gain x1.4, zeta x0.7'`` (``'nominal'`` when nothing changes)."""
        parts = [f'noise {v * 1e9:g} nm' if k == 'noise_m' else f'{k} x{v:g}'
                 for k, v in self.changes().items()]
        return ', '.join(parts) if parts else 'nominal'


def default_family() -> tuple[StageVariation, ...]:
    """
    Return the study's family: nominal, each variable at both ends, and corner combinations.

    Returns
    -------
    tuple of StageVariation
        ``nominal``; ``<var>_lo`` / ``<var>_hi`` for every variable of :data:`RANGES` at the
        ends of its range, one at a time (``noise_hi`` only: the low end is the nominal); and
        corners that combine what hurts most: low gain with low damping (least loop gain, most
        ringing), high gain with low damping (least stability margin at the resonance), high
        gain with the resonance lowered by a load and low damping, low gain with a slow lag
        (most phase lag at 100 Hz), high gain with a fast lag, and the worst-margin corner
        again with sensor noise.

    """
    members = [StageVariation('nominal')]
    for var, (lo, hi, _) in RANGES.items():
        if var == 'noise_m':
            members.append(StageVariation('noise_hi', noise_m=hi))
            continue
        members.append(StageVariation(f'{var}_lo', **{var: lo}))
        members.append(StageVariation(f'{var}_hi', **{var: hi}))
    g_lo, g_hi = RANGES['gain'][:2]
    z_lo = RANGES['zeta'][0]
    w_lo = RANGES['omega_n'][0]
    t_lo, t_hi = RANGES['tau'][:2]
    members += [
        StageVariation('gain_lo_zeta_lo', gain=g_lo, zeta=z_lo),
        StageVariation('gain_hi_zeta_lo', gain=g_hi, zeta=z_lo),
        StageVariation('gain_hi_wn_lo_zeta_lo', gain=g_hi, omega_n=w_lo, zeta=z_lo),
        StageVariation('gain_lo_tau_hi', gain=g_lo, tau=t_hi),
        StageVariation('gain_hi_tau_lo', gain=g_hi, tau=t_lo),
        StageVariation('gain_hi_zeta_lo_noise', gain=g_hi, zeta=z_lo,
                       noise_m=RANGES['noise_m'][1]),
    ]
    return tuple(members)


def sample_family(n: int, seed: int = 0) -> tuple[StageVariation, ...]:
    """
    Return ``n`` members drawn uniformly and independently inside every range of :data:`RANGES`.

    Parameters
    ----------
    n : int
        Number of members, >= 0.
    seed : int
        Seed of the draw (the same seed gives the same members).

    Returns
    -------
    tuple of StageVariation
        Named ``random_0000``, ``random_0001`` ...

    """
    if n < 0:
        raise ParameterError('n', n, '[0, inf)')
    rng = np.random.default_rng(seed)
    names = list(RANGES)
    low = np.array([RANGES[v][0] for v in names])
    high = np.array([RANGES[v][1] for v in names])
    # one row per member, filled row after row: the first k members of any n are the same
    draws = rng.uniform(low, high, size=(n, len(names)))
    width = max(4, len(str(n - 1)))
    return tuple(StageVariation(f'random_{i:0{width}d}',
                                **{v: float(x) for v, x in zip(names, draws[i])})
                 for i in range(n))


def member_params(base: StageParams, member: StageVariation) -> StageParams:
    """
    Return the stage parameters of one member of the family.

    Parameters
    ----------
    base : StageParams
        The configured (nominal) stage: the third-order plant, backlash-like hysteresis when
        ``alpha`` or ``b1`` vary.
    member : StageVariation
        The factors.

    Returns
    -------
    StageParams
        ``base`` with the changed plant, hysteresis and noise; ``base`` itself (bit for bit)
        for the nominal member. A pure gain change scales K alone; omega_n, zeta or tau
        rebuild (K, a0, a1, a2) from the factored form at the nominal DC gain times ``gain``.

    Raises
    ------
    ParameterError
        If the configured plant is not ``third_order``, or the hysteresis is not
        ``backlash_like`` while ``alpha`` or ``b1`` vary.

    """
    if base.plant.model != 'third_order':
        raise ParameterError('plant.model', base.plant.model, "'third_order'",
                             'is not the third-order plant (20) the stage family varies')
    flat: dict[str, object] = {}
    third = base.plant.third_order
    if (member.omega_n, member.zeta, member.tau) != (1.0, 1.0, 1.0):
        f = factors_of(third)
        varied = third_order_of(LinearFactors(
            gain_m_per_v=f.gain_m_per_v * member.gain, omega_n_rad_s=f.omega_n_rad_s
            * member.omega_n, zeta=f.zeta * member.zeta, tau_s=f.tau_s * member.tau))
        flat.update({f'plant.third_order.{k}': v for k, v in varied.to_flat().items()})
    elif member.gain != 1.0:
        flat['plant.third_order.gain'] = third.gain * member.gain
    if (member.alpha, member.b1) != (1.0, 1.0):
        if base.hysteresis.model != 'backlash_like':
            raise ParameterError('hysteresis.model', base.hysteresis.model, "'backlash_like'",
                                 f'has no alpha and B1 to vary (stage {member.name!r})')
        bl = base.hysteresis.backlash_like
        flat['hysteresis.backlash_like.alpha'] = bl.alpha * member.alpha
        flat['hysteresis.backlash_like.b1'] = bl.b1 * member.b1
    if member.noise_m != base.chain.sensor_noise_std_m:
        flat['chain.sensor_noise_std_m'] = member.noise_m
    return base.with_flat(flat) if flat else base


def true_estimates(stage: StageParams) -> tuple[float, float]:
    """
    Return the true theta = a/(b c) and phi = 1/(b c) of a stage, in the RAC's units.

    Parameters
    ----------
    stage : StageParams
        The stage (plant, hysteresis slope c, sensor gain K_PSCM).

    Returns
    -------
    theta, phi : float
        theta = 1/(K_PSCM g c) [V/V] and phi = T_1 theta [s], with g the DC gain and T_1 the
        first-order time constant at low frequency: a1/a2 for the third-order plant, tau for
        the reduced plant (module docstring). For the general model, that of its third-order
        equivalent.

    """
    plant = stage.plant
    if plant.model == 'reduced':
        t1 = plant.reduced.tau_s
    else:
        third = (plant.electromechanical.third_order() if plant.model == 'electromechanical'
                 else plant.third_order)
        t1 = third.a1 / third.a2
    g = linear_plant(plant).dc_gain_m_per_v
    c = make_hysteresis(stage.hysteresis).slope
    theta = 1.0 / (stage.chain.sensor_gain_v_per_m * g * c)
    return theta, t1 * theta
