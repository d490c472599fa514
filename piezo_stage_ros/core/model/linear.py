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
Linear dynamics of the stage: general electromechanical model, third-order plant, reduced model.

Equations (numbers as in the paper):

- general model, eqs. (11)-(12), states (q, x, dx/dt)::

      R0 C_A dq/dt + q - T_em x = C_A k_amp (v_in - H(q)/k_amp)
      m d2x/dt2 + b_s dx/dt + kbar_s x = (T_em / C_A) q,     kbar_s = k_s + T_em^2 / C_A

- third-order plant, eq. (17): G(s) = X(s)/W(s) = K / (s^3 + a0 s^2 + a1 s + a2);
- reduced plant, eq. (25): G_r(s) = g / (tau s + 1);
- the factored third-order plant k_p w_n^2 / ((tau s + 1)(s^2 + 2 zeta w_n s + w_n^2))
  (:class:`LinearFactors`, :func:`factors_of`, :func:`third_order_of`): the family of stages
  varies one factor at a time and identification fits them, so the conversions belong to the
  model both use.

Eliminating q from (11)-(12) with H = 0 gives (17) with

    a0 = 1/(R0 C_A) + b_s/m
    a1 = b_s/(m R0 C_A) + kbar_s/m          (the paper's eq. (18) prints k_s/m here)
    a2 = k_s/(m R0 C_A)                     (kbar_s - T_em^2/C_A = k_s)
    K  = k_amp T_em/(m R0 C_A)

The printed (18) has k_s/m in a1; with kbar_s/m the Table II values give a1 = 4.125e8, within 0.6 %
of the identified 4.1e8 of eq. (20), while k_s/m gives 3.24e8 (21 % off). The derivation wins.

All models are exact under zero-order hold: :meth:`LinearPlant.discretize` uses the matrix
exponential of the (scaled) state-space model once; no ODE integrator runs per sample.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike
from piezo_stage_ros.core.contracts.errors import IdentificationError
from piezo_stage_ros.core.contracts.params import param, Params
from piezo_stage_ros.core.contracts.types import ComplexArray, FloatArray
from scipy.linalg import expm

__all__ = [
    'DiscreteLinearPlant', 'ElectromechanicalParams', 'LinearFactors', 'LinearPlant',
    'ReducedParams', 'ThirdOrderParams', 'electromechanical_plant', 'factors_of', 'reduced_plant',
    'third_order_of', 'third_order_plant',
]



@dataclass(frozen=True)
class ElectromechanicalParams(Params):
    """Physical parameters of the general model, eqs. (11)-(12); defaults from Table II."""

    mass_kg: float = param(0.0515, unit='kg', description='Moving mass m.', low=0.0,
                           low_open=True)
    damping_n_s_per_m: float = param(114.0, unit='N s/m', description='Damping b_s.', low=0.0)
    stiffness_n_per_m: float = param(16.08e6, unit='N/m', description='Stiffness k_s.',
                                     low=0.0, low_open=True)
    resistance_ohm: float = param(40.5, unit='Ohm',
                                  description='Amplifier internal resistance R0.', low=0.0,
                                  low_open=True)
    capacitance_f: float = param(4.6e-6, unit='F', description='Actuator capacitance C_A.',
                                 low=0.0, low_open=True)
    transformer_n_per_v: float = param(4.575, unit='N/V',
                                       description='Electromechanical transformer ratio T_em.',
                                       low=0.0, low_open=True)
    amplifier_gain: float = param(10.0, unit='-', description='Amplifier gain k_amp.', low=0.0,
                                  low_open=True)

    @property
    def stiffness_bar_n_per_m(self) -> float:
        """Return kbar_s = k_s + T_em^2 / C_A [N/m], eq. (10)."""
        return self.stiffness_n_per_m + self.transformer_n_per_v ** 2 / self.capacitance_f

    def third_order(self) -> ThirdOrderParams:
        """
        Return the third-order plant (17) these physical parameters give.

        Returns
        -------
        ThirdOrderParams
            K, a0, a1, a2 from the derivation in the module docstring (eq. (18), corrected a1).

        """
        m = self.mass_kg
        rc = self.resistance_ohm * self.capacitance_f
        b = self.damping_n_s_per_m
        return ThirdOrderParams(
            gain=self.amplifier_gain * self.transformer_n_per_v / (m * rc),
            a0=1.0 / rc + b / m,
            a1=b / (m * rc) + self.stiffness_bar_n_per_m / m,
            a2=self.stiffness_n_per_m / (m * rc),
        )


@dataclass(frozen=True)
class ThirdOrderParams(Params):
    """Coefficients of G(s) = K / (s^3 + a0 s^2 + a1 s + a2), eq. (17); defaults eq. (20)."""

    gain: float = param(4.767e6, unit='m/(V s^3)', description='Numerator K of eq. (17).',
                        low=0.0, low_open=True)
    a0: float = param(7582.0, unit='1/s', description='Coefficient a0 of eq. (17).', low=0.0,
                      low_open=True)
    a1: float = param(4.1e8, unit='1/s^2', description='Coefficient a1 of eq. (17).', low=0.0,
                      low_open=True)
    a2: float = param(1.677e12, unit='1/s^3', description='Coefficient a2 of eq. (17).',
                      low=0.0, low_open=True)

    def _check(self) -> None:
        # Routh-Hurwitz for a monic cubic: stable iff all a_i > 0 and a0 a1 > a2.
        if self.a0 * self.a1 <= self.a2:
            from piezo_stage_ros.core.contracts.errors import ParameterError
            raise ParameterError('a2', self.a2, f'< a0*a1 = {self.a0 * self.a1:g}',
                                 'makes the third-order plant unstable (Routh-Hurwitz)')

    def reduced(self) -> ReducedParams:
        """
        Return the reduced first-order plant (25) of this third-order plant.

        The DC gain K/a2 is kept and the slow real pole of the cubic becomes the time constant,
        as the paper does for frequencies well below the resonance.

        Returns
        -------
        ReducedParams
            g = K/a2 and tau = 1/|p_slow|.

        """
        roots = np.roots([1.0, self.a0, self.a1, self.a2])
        real = roots[np.abs(roots.imag) < 1e-9 * np.abs(roots)].real
        slow = float(np.max(real)) if real.size else float(np.max(roots.real))
        return ReducedParams(gain_m_per_v=self.gain / self.a2, tau_s=-1.0 / slow)


@dataclass(frozen=True)
class ReducedParams(Params):
    """Reduced plant G_r(s) = g / (tau s + 1), eq. (25)."""

    gain_m_per_v: float = param(2.843e-6, unit='m/V', description='DC gain g of eq. (25).',
                                low=0.0, low_open=True)
    tau_s: float = param(2.445e-4, unit='s', description='Time constant tau of eq. (25).',
                         low=0.0, low_open=True)


@dataclass(frozen=True)
class DiscreteLinearPlant:
    """
    Exact zero-order-hold discretization x[k+1] = Ad x[k] + Bd u[k], y = C x.

    Attributes
    ----------
    ad : ndarray, shape (n, n)
    bd : ndarray, shape (n, m)
        One column per input (the hysteresis output w; for the general model also H(q)).
    c : ndarray, shape (n,)
        Output row (position in m).
    sample_time_s : float

    """

    ad: FloatArray
    bd: FloatArray
    c: FloatArray
    sample_time_s: float

    def poles(self) -> ComplexArray:
        """Return the eigenvalues of Ad (discrete-time poles)."""
        return np.asarray(np.linalg.eigvals(self.ad), dtype=np.complex128)

    def transfer_function(self) -> tuple[FloatArray, FloatArray]:
        """
        Return (num, den) of G(z) from the first input to position, powers of z, highest first.

        ``scipy.signal.ss2tf`` of (Ad, Bd[:, 0], C): the numerator is padded to the
        denominator's length (leading zeros, one at least: the zero-order hold delays a sample).
        """
        from scipy.signal import ss2tf
        num, den = ss2tf(self.ad, self.bd[:, :1], self.c[None, :], np.zeros((1, 1)))
        return (np.asarray(num, dtype=np.float64).ravel(),
                np.asarray(den, dtype=np.float64).ravel())


@dataclass(frozen=True)
class LinearPlant:
    """
    Continuous-time state-space model dx/dt = A x + B u, y = C x (SI units, scaled states).

    States are scaled to be of order one for inputs of order one volt, so that the matrix
    exponential of the discretization is well conditioned; :attr:`c` maps them to metres.

    Attributes
    ----------
    a : ndarray, shape (n, n)
    b : ndarray, shape (n, m)
    c : ndarray, shape (n,)
    name : str
        ``'electromechanical'``, ``'third_order'`` or ``'reduced'``.

    """

    a: FloatArray
    b: FloatArray
    c: FloatArray
    name: str

    @property
    def order(self) -> int:
        """Return the number of states."""
        return int(self.a.shape[0])

    @property
    def dc_gain_m_per_v(self) -> float:
        """Return the static gain from the first input (w, volts) to position (metres)."""
        return float(-self.c @ np.linalg.solve(self.a, self.b[:, 0]))

    def rest_state(self, w0: float) -> FloatArray:
        """Return the equilibrium state for a constant first input ``w0`` [V] (others zero)."""
        return np.asarray(-np.linalg.solve(self.a, self.b[:, 0] * w0), dtype=np.float64)

    def poles(self) -> ComplexArray:
        """Return the continuous-time poles [rad/s]."""
        return np.asarray(np.linalg.eigvals(self.a), dtype=np.complex128)

    def frequency_response(self, omega_rad_s: ArrayLike) -> ComplexArray:
        """
        Evaluate G(j omega) from the first input to position.

        Parameters
        ----------
        omega_rad_s : array_like
            Angular frequencies [rad/s].

        Returns
        -------
        ndarray of complex
            G(j omega) [m/V], same shape as ``omega_rad_s``.

        """
        w = np.atleast_1d(np.asarray(omega_rad_s, dtype=np.float64))
        eye = np.eye(self.order)
        out = np.array([self.c @ np.linalg.solve(1j * wk * eye - self.a, self.b[:, 0])
                        for wk in w.ravel()], dtype=np.complex128)
        return out.reshape(np.shape(omega_rad_s))

    def transfer_function(self) -> tuple[FloatArray, FloatArray]:
        """
        Return (num, den) of G(s) from the first input, highest power first, den monic.

        Returns
        -------
        num, den : ndarray
            Polynomial coefficients in SI units.

        """
        den = np.poly(self.a).real
        # num(s) = det(sI - A + B c) - det(sI - A) for a single input/output pair
        num = np.poly(self.a - np.outer(self.b[:, 0], self.c)).real - den
        num = np.trim_zeros(np.where(np.abs(num) > 1e-9 * np.max(np.abs(num)), num, 0.0), 'f')
        return np.asarray(num, dtype=np.float64), np.asarray(den, dtype=np.float64)

    def discretize(self, sample_time_s: float) -> DiscreteLinearPlant:
        """
        Discretize exactly under zero-order hold on every input.

        Parameters
        ----------
        sample_time_s : float
            Hold period [s], > 0.

        Returns
        -------
        DiscreteLinearPlant
            Ad = exp(A T), Bd = integral_0^T exp(A s) ds B, from one matrix exponential of the
            augmented matrix [[A, B], [0, 0]] (Van Loan).

        """
        if not (sample_time_s > 0.0 and math.isfinite(sample_time_s)):
            from piezo_stage_ros.core.contracts.errors import ParameterError
            raise ParameterError('sample_time_s', sample_time_s, '(0, inf)')
        n, m = self.b.shape
        aug = np.zeros((n + m, n + m))
        aug[:n, :n] = self.a
        aug[:n, n:] = self.b
        phi = expm(aug * sample_time_s)
        return DiscreteLinearPlant(ad=phi[:n, :n].copy(), bd=phi[:n, n:].copy(), c=self.c.copy(),
                                   sample_time_s=float(sample_time_s))


def _scaled(a: ArrayLike, b: ArrayLike, c: ArrayLike, scale: Sequence[float],
            name: str) -> LinearPlant:
    """Return the plant in states z = x / scale (A' = S^-1 A S, B' = S^-1 B, C' = C S)."""
    s = np.asarray(scale, dtype=np.float64)
    a_ = np.asarray(a, dtype=np.float64) * s[None, :] / s[:, None]
    b_ = np.asarray(b, dtype=np.float64) / s[:, None]
    c_ = np.asarray(c, dtype=np.float64) * s
    return LinearPlant(a=a_, b=b_, c=c_, name=name)


def third_order_plant(p: ThirdOrderParams) -> LinearPlant:
    """
    Return eq. (17) as a state-space model, input w [V], output x [m].

    Parameters
    ----------
    p : ThirdOrderParams
        K, a0, a1, a2.

    Returns
    -------
    LinearPlant
        Controllable canonical form in (x, dx/dt, d2x/dt2), scaled by powers of a2^(1/3) and by
        the DC gain so every state is of order one.

    """
    a = [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-p.a2, -p.a1, -p.a0]]
    b = [[0.0], [0.0], [p.gain]]
    ws = p.a2 ** (1.0 / 3.0)
    g = p.gain / p.a2
    return _scaled(a, b, [1.0, 0.0, 0.0], [g, g * ws, g * ws * ws], 'third_order')


@dataclass(frozen=True)
class LinearFactors:
    """
    The factored third-order plant k_p w_n^2 / ((tau s + 1)(s^2 + 2 zeta w_n s + w_n^2)).

    Attributes
    ----------
    gain_m_per_v : float
        k_p, the DC gain K/a2 [m/V].
    omega_n_rad_s : float
        w_n [rad/s].
    zeta : float
        Damping ratio [-].
    tau_s : float
        Time constant of the real pole [s].

    """

    gain_m_per_v: float
    omega_n_rad_s: float
    zeta: float
    tau_s: float
    #: Loop delay beyond the sample-and-hold, in samples (0: the command of sample k is held
    #: over sample k); not part of the stage's plant, the signal chain's.
    delay_samples: float = 0.0


def third_order_of(f: LinearFactors) -> ThirdOrderParams:
    """
    Return K, a0, a1, a2 of eq. (17) for factored parameters.

    Parameters
    ----------
    f : LinearFactors
        k_p [m/V], w_n [rad/s], zeta [-], tau [s].

    Returns
    -------
    ThirdOrderParams
        a2 = w_n^2/tau, a1 = w_n^2 + 2 zeta w_n/tau, a0 = 1/tau + 2 zeta w_n, K = k_p a2.

    """
    w, z, t = f.omega_n_rad_s, f.zeta, f.tau_s
    a2 = w * w / t
    return ThirdOrderParams(gain=f.gain_m_per_v * a2, a0=1.0 / t + 2.0 * z * w,
                            a1=w * w + 2.0 * z * w / t, a2=a2)


def factors_of(p: ThirdOrderParams) -> LinearFactors:
    """
    Return the factored form of a third-order plant (the inverse of :func:`third_order_of`).

    Parameters
    ----------
    p : ThirdOrderParams
        The plant of eq. (17): K / (s^3 + a0 s^2 + a1 s + a2).

    Returns
    -------
    LinearFactors
        From the roots of s^3 + a0 s^2 + a1 s + a2: the real pole gives tau, the complex pair
        w_n = |p| and zeta = -Re p / |p|.

    Raises
    ------
    IdentificationError
        If the cubic has three real roots (no resonance to factor out).

    """
    roots = np.roots([1.0, p.a0, p.a1, p.a2])
    cplx = roots[np.abs(roots.imag) > 1e-9 * np.abs(roots)]
    if cplx.size != 2:
        raise IdentificationError(f'third-order plant {p.to_flat()} has no complex pole pair')
    real = roots[np.abs(roots.imag) <= 1e-9 * np.abs(roots)].real
    wn = float(np.abs(cplx[0]))
    return LinearFactors(gain_m_per_v=p.gain / p.a2, omega_n_rad_s=wn,
                         zeta=float(-cplx[0].real / wn), tau_s=float(-1.0 / real[0]))


def reduced_plant(p: ReducedParams) -> LinearPlant:
    """
    Return eq. (25) as a state-space model, input w [V], output x [m].

    Parameters
    ----------
    p : ReducedParams
        g and tau.

    Returns
    -------
    LinearPlant
        One state, scaled by g.

    """
    return _scaled([[-1.0 / p.tau_s]], [[p.gain_m_per_v / p.tau_s]], [1.0], [p.gain_m_per_v],
                   'reduced')


def electromechanical_plant(p: ElectromechanicalParams) -> LinearPlant:
    """
    Return eqs. (11)-(12) as a state-space model with inputs (v_in, H) and output x.

    Parameters
    ----------
    p : ElectromechanicalParams
        Physical parameters (Table II).

    Returns
    -------
    LinearPlant
        States (q, x, dx/dt) scaled to order one; input 0 is the amplifier input v_in [V],
        input 1 the hysteresis voltage H(q) [V] of eq. (2). With H = 0 it has the transfer
        function of :meth:`ElectromechanicalParams.third_order`.

    """
    rc = p.resistance_ohm * p.capacitance_f
    ca = p.capacitance_f
    a = [[-1.0 / rc, p.transformer_n_per_v / rc, 0.0],
         [0.0, 0.0, 1.0],
         [p.transformer_n_per_v / (ca * p.mass_kg), -p.stiffness_bar_n_per_m / p.mass_kg,
          -p.damping_n_s_per_m / p.mass_kg]]
    b = [[ca * p.amplifier_gain / rc, -ca / rc], [0.0, 0.0], [0.0, 0.0]]
    g = p.third_order().gain / p.third_order().a2
    ws = math.sqrt(p.stiffness_bar_n_per_m / p.mass_kg)
    return _scaled(a, b, [0.0, 1.0, 0.0], [ca * p.amplifier_gain, g, g * ws],
                   'electromechanical')
