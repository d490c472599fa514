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
Rate-independent hysteresis operators w = P(v) placed ahead of the linear plant.

Every model has the same small interface (state in, input in, state and output out)::

    state = model.rest_state(v0)        # at rest at input v0
    state, w = model.step(state, v)     # input jumps from the last value to v

Inputs are piecewise constant (the DAC holds v_in between samples), so each model is stepped
*exactly* across each input jump; no ODE integrator is involved. The same code takes a float
or a numpy array of independent channels (vectorized stepping of a batch of stages).

Models:

- :class:`BacklashLike`, eq. (21): dw/dt = alpha |dv/dt| (c v - w) + B1 dv/dt. With
  e = w - c v, over a jump dv::

      e <- e exp(-alpha |dv|) + sign(dv) (B1 - c)/alpha (1 - exp(-alpha |dv|))

  which is eq. (22) with constant sign of dv/dt; |e| stays within (c - B1)/alpha, eqs. (23)-(24).
- :class:`BoucWen`: dh/dt = A d_p dv/dt - beta |dv/dt| h - gamma dv/dt |h|, w = d_p v - h
  (n = 1), solved in closed form piecewise in the sign of h.
- :class:`PrandtlIshlinskii`: w = p0 v + sum_i p_i F_ri[v] with play operators
  F_r[v] = max(v - r, min(v + r, F_prev)), exact for piecewise-constant input.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Protocol, Union

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.params import group, param, Params
from piezo_stage_ros.core.contracts.types import FloatArray

__all__ = [
    'BacklashLike', 'BacklashLikeParams', 'BoucWen', 'BoucWenParams', 'HysteresisModel',
    'HysteresisParams', 'NoHysteresis', 'PrandtlIshlinskii', 'PrandtlIshlinskiiParams',
    'make_hysteresis',
]

Value = Union[float, FloatArray]


class HysteresisModel(Protocol):
    """A rate-independent operator stepped exactly across piecewise-constant input jumps."""

    @property
    def slope(self) -> float:
        """Return the asymptotic slope dw/dv far from a reversal (the linear part c)."""
        ...

    @property
    def bound(self) -> float:
        """Return rho, a bound on |w - slope * v| once at rest (eq. (31)) [V]."""
        ...

    def rest_state(self, v0: Value) -> Any:
        """Return the state at rest at input ``v0`` [V] (output ``slope * v0``)."""
        ...

    def step(self, state: Any, v: Value) -> tuple[Any, Value]:
        """Return the new state and the output w [V] after the input jumps to ``v`` [V]."""
        ...


@dataclass(frozen=True)
class BacklashLikeParams(Params):
    """Dynamic backlash-like model, eq. (21); defaults identified in section III-D."""

    alpha: float = param(0.4195, unit='1/V', description='Rate alpha of eq. (21).', low=0.0,
                         low_open=True)
    c: float = param(1.0341, unit='-', description='Slope c of eq. (21).', low=0.0,
                     low_open=True)
    b1: float = param(0.9592, unit='-', description='B1 of eq. (21); must be below c.',
                      low=0.0)

    def _check(self) -> None:
        if not self.b1 < self.c:
            raise ParameterError('b1', self.b1, f'[0, c) = [0, {self.c:g})',
                                 'must be smaller than c (eq. (21) requires c > B1)')


class BacklashLike:
    """
    Dynamic backlash-like hysteresis, eq. (21), stepped exactly.

    State: ``(v, e)`` with the last input v and e = w - c v.

    Parameters
    ----------
    params : BacklashLikeParams
        alpha, c and B1.

    """

    def __init__(self, params: BacklashLikeParams) -> None:
        self.params = params
        self._alpha = params.alpha
        self._c = params.c
        self._shift = (params.b1 - params.c) / params.alpha  # = -rho, eq. (23)
        self._exp = math.exp

    @property
    def slope(self) -> float:
        """Return c."""
        return self._c

    @property
    def bound(self) -> float:
        """Return rho = (c - B1) / alpha, eqs. (23)-(24)."""
        return -self._shift

    def rest_state(self, v0: Value, e0: Value = 0.0) -> tuple[Value, Value]:
        """
        Return the state at rest at ``v0`` with w - c v = ``e0`` (default: centre of the band).

        Parameters
        ----------
        v0 : float or ndarray
            Input [V].
        e0 : float or ndarray
            Initial d(v) of eq. (22) [V], |e0| <= rho.

        Returns
        -------
        tuple
            The state ``(v0, e0)``.

        """
        return (v0, e0 + 0.0 * v0)

    def step(self, state: tuple[Value, Value], v: Value) -> tuple[tuple[Value, Value], Value]:
        """
        Step exactly across the jump from the last input to ``v``.

        Parameters
        ----------
        state : tuple
            ``(v_last, e)``.
        v : float or ndarray
            New input [V].

        Returns
        -------
        state, w
            New state and output w = c v + e [V].

        """
        v_last, e = state
        dv = v - v_last
        if isinstance(dv, float):
            decay = math.exp(-self._alpha * abs(dv))
            e = e * decay + self._shift * math.copysign(1.0 - decay, dv)
        else:
            decay_a = np.exp(-self._alpha * np.abs(dv))
            e = e * decay_a + self._shift * np.copysign(1.0 - decay_a, dv)
        return (v, e), self._c * v + e


@dataclass(frozen=True)
class BoucWenParams(Params):
    """
    Bouc-Wen model (n = 1) at the input: w = d_p v - h.

    With gamma = 0 and beta = alpha, A d_p = c - B1 it is the backlash-like model exactly; the
    defaults (beta = gamma, a least-squares fit to the backlash-like default loop on the
    paper's 1 + sin(2 pi 100 t) V test) give a loop of the same width but another shape.
    """

    d_p: float = param(1.0341, unit='-', description='Linear gain d_p of the Bouc-Wen output.',
                       low=0.0, low_open=True)
    a: float = param(0.0829, unit='-', description='Amplitude A of dh/dv at h = 0.', low=0.0,
                     low_open=True)
    beta: float = param(0.3551, unit='1/V', description='Bouc-Wen beta.', low=0.0)
    gamma: float = param(0.3551, unit='1/V', description='Bouc-Wen gamma, |gamma| <= beta.')

    def _check(self) -> None:
        if abs(self.gamma) > self.beta or self.beta + self.gamma <= 0.0:
            raise ParameterError('gamma', self.gamma, f'|gamma| <= beta = {self.beta:g} and '
                                 'beta + gamma > 0', 'gives an unbounded Bouc-Wen loop')


class BoucWen:
    """
    Bouc-Wen hysteresis (n = 1), rate independent, stepped exactly.

    With the travel u = |v - v_last| and g = sign(dv) h, dg/du = A d_p - beta g - gamma |g|: a
    linear ODE in each sign region of g, solved in closed form (at most one switch per jump).
    State: ``(v, h)``.

    Parameters
    ----------
    params : BoucWenParams
        d_p, A, beta, gamma.

    """

    def __init__(self, params: BoucWenParams) -> None:
        self.params = params
        self._ad = params.a * params.d_p
        self._k_pos = params.beta + params.gamma  # decay rate where g >= 0
        self._k_neg = params.beta - params.gamma  # where g < 0

    @property
    def slope(self) -> float:
        """Return d_p."""
        return self.params.d_p

    @property
    def bound(self) -> float:
        """Return the bound A d_p / (beta + gamma) of |h|."""
        return self._ad / self._k_pos

    def rest_state(self, v0: Value) -> tuple[Value, Value]:
        """Return ``(v0, 0)``: at rest on the centre line w = d_p v0."""
        return (v0, 0.0 * v0)

    def step(self, state: tuple[Value, Value], v: Value) -> tuple[tuple[Value, Value], Value]:
        """
        Step exactly across the jump from the last input to ``v``.

        Parameters
        ----------
        state : tuple
            ``(v_last, h)``.
        v : float or ndarray
            New input [V].

        Returns
        -------
        state, w
            New state and output w = d_p v - h [V].

        """
        v_last, h = state
        dv = np.asarray(v, dtype=np.float64) - v_last
        sgn = np.where(dv >= 0.0, 1.0, -1.0)
        u = np.abs(dv)
        g = sgn * h
        # Region g < 0: dg/du = A d_p - k_neg g, rising to 0 after travel u0.
        if self._k_neg > 0.0:
            g_inf = self._ad / self._k_neg
            with np.errstate(divide='ignore', invalid='ignore'):
                u0 = np.where(g < 0.0, np.log((g_inf - g) / g_inf) / self._k_neg, 0.0)
            g_neg = g_inf + (g - g_inf) * np.exp(-self._k_neg * np.minimum(u, u0))
        else:
            u0 = np.where(g < 0.0, -g / self._ad, 0.0)
            g_neg = g + self._ad * np.minimum(u, u0)
        g = np.where(g < 0.0, np.where(u < u0, g_neg, 0.0), g)
        rest = np.maximum(u - u0, 0.0)
        g_inf_pos = self._ad / self._k_pos
        g = np.where(g >= 0.0, g_inf_pos + (g - g_inf_pos) * np.exp(-self._k_pos * rest), g)
        h_new = sgn * g
        if isinstance(v, float):
            h_out: Value = float(h_new)
        else:
            h_out = h_new
        return (v, h_out), self.params.d_p * v - h_out


@dataclass(frozen=True)
class PrandtlIshlinskiiParams(Params):
    """
    Prandtl-Ishlinskii model w = p0 v + sum_i p_i F_ri[v] with play operators.

    Default weights are a non-negative least-squares fit, with these thresholds, to the
    backlash-like default loop on the paper's 1 + sin(2 pi 100 t) V test (see the tests).
    """

    p0: float = param(0.9363, unit='-', description='Weight p0 of the linear term.', low=0.0)
    thresholds_v: tuple[float, ...] = param(
        (0.2, 0.4, 0.6, 0.8, 1.0), unit='V',
        description='Thresholds r_i of the play operators, increasing, > 0.', low=0.0,
        low_open=True)
    weights: tuple[float, ...] = param(
        (0.0172, 0.0121, 0.0100, 0.0106, 0.0480), unit='-',
        description='Weights p_i of the play operators (same length as thresholds_v).',
        low=0.0)

    def _check(self) -> None:
        if len(self.weights) != len(self.thresholds_v):
            raise ParameterError('weights', list(self.weights),
                                 f'{len(self.thresholds_v)} values (one per threshold)',
                                 'has the wrong length')
        if any(b <= a for a, b in zip(self.thresholds_v, self.thresholds_v[1:])):
            raise ParameterError('thresholds_v', list(self.thresholds_v),
                                 'strictly increasing values', 'is not increasing')


class PrandtlIshlinskii:
    """
    Prandtl-Ishlinskii hysteresis, exact for piecewise-constant input.

    State: ``(v, y)`` with y the play operator outputs, shape (n,) or (n, channels).

    Parameters
    ----------
    params : PrandtlIshlinskiiParams
        p0, thresholds and weights.

    """

    def __init__(self, params: PrandtlIshlinskiiParams) -> None:
        self.params = params
        self._r = np.asarray(params.thresholds_v, dtype=np.float64)
        self._p = np.asarray(params.weights, dtype=np.float64)

    @property
    def slope(self) -> float:
        """Return p0 + sum p_i, the slope of the initial loading curve near rest."""
        return self.params.p0 + float(np.sum(self._p))

    @property
    def bound(self) -> float:
        """Return sum p_i r_i, the bound of |w - slope v|."""
        return float(np.sum(self._p * self._r))

    def rest_state(self, v0: Value) -> tuple[Value, FloatArray]:
        """Return ``(v0, y)`` with every play operator at rest at ``v0``."""
        y = np.multiply.outer(np.ones_like(self._r), np.asarray(v0, dtype=np.float64))
        return (v0, y)

    def step(self, state: tuple[Value, FloatArray],
             v: Value) -> tuple[tuple[Value, FloatArray], Value]:
        """
        Apply the play operators to the new input ``v`` [V].

        Parameters
        ----------
        state : tuple
            ``(v_last, y)``.
        v : float or ndarray
            New input [V].

        Returns
        -------
        state, w
            New state and output [V].

        """
        _, y = state
        va = np.asarray(v, dtype=np.float64)
        r = self._r.reshape((-1,) + (1,) * va.ndim)
        y = np.maximum(va - r, np.minimum(va + r, y))
        w = self.params.p0 * va + np.tensordot(self._p, y, axes=1)
        return (v, y), (float(w) if isinstance(v, float) else w)


class NoHysteresis:
    """The identity w = v (a purely linear stage)."""

    slope = 1.0
    bound = 0.0

    def rest_state(self, v0: Value) -> tuple[()]:
        """Return the empty state."""
        return ()

    def step(self, state: tuple[()], v: Value) -> tuple[tuple[()], Value]:
        """Return ``v`` unchanged."""
        return state, v


@dataclass(frozen=True)
class HysteresisParams(Params):
    """Choice of hysteresis model and the parameters of each."""

    model: str = param('backlash_like', unit='-', description='Hysteresis model ahead of the '
                       'linear plant.', choices=('backlash_like', 'bouc_wen',
                                                 'prandtl_ishlinskii', 'none'), read_only=True)
    backlash_like: BacklashLikeParams = group(BacklashLikeParams, 'eq. (21)')
    bouc_wen: BoucWenParams = group(BoucWenParams, 'Bouc-Wen')
    prandtl_ishlinskii: PrandtlIshlinskiiParams = group(PrandtlIshlinskiiParams,
                                                        'Prandtl-Ishlinskii')


def make_hysteresis(params: HysteresisParams) -> HysteresisModel:
    """
    Build the hysteresis model ``params.model`` names.

    Parameters
    ----------
    params : HysteresisParams
        Model choice and the parameters of each model.

    Returns
    -------
    HysteresisModel

    """
    if params.model == 'backlash_like':
        return BacklashLike(params.backlash_like)
    if params.model == 'bouc_wen':
        return BoucWen(params.bouc_wen)
    if params.model == 'prandtl_ishlinskii':
        return PrandtlIshlinskii(params.prandtl_ishlinskii)
    return NoHysteresis()
