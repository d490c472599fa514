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
Shapes of a transition from one level to another, with their exact derivatives.

The quintic S-curve (minimum jerk) replaces a jump of a step-like trajectory and a jump of the
feed-forward's reference; the smoothstep family blends the turnarounds of a scan line. They live
below the model and the controllers (not with the trajectories) because the feed-forward, on a
floor below the trajectories, shapes jumps with the same curve.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike
from piezo_stage_ros.core.contracts.types import FloatArray

__all__ = ['s_curve', 'smoothstep']


def s_curve(u: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """
    Return the quintic S-curve q(u) = 10 u^3 - 15 u^4 + 6 u^5 and q'(u), u clipped to [0, 1].

    Parameters
    ----------
    u : array_like
        Normalized time (t - t_0)/T_r of a transition [-].

    Returns
    -------
    q, dq_du : ndarray
        Fraction of the jump done (0 ... 1) and its derivative with respect to u (0 outside
        (0, 1); 30 u^2 (1 - u)^2 inside).

    """
    v = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
    v2 = v * v
    return v2 * v * (10.0 + v * (6.0 * v - 15.0)), 30.0 * v2 * (1.0 - v) ** 2


def smoothstep(order: int) -> tuple[np.polynomial.Polynomial, np.polynomial.Polynomial,
                                      np.polynomial.Polynomial]:
    """
    Return the smoothstep polynomial S_N, its derivative and its integral from 0.

    Parameters
    ----------
    order : int
        N >= 0: S_N rises from S(0) = 0 to S(1) = 1 with its first N derivatives 0 at both ends
        (N = 0: s; N = 1: 3 s^2 - 2 s^3; N = 2: the quintic of :func:`s_curve`).

    Returns
    -------
    q, dq_ds, integral : numpy.polynomial.Polynomial
        S_N(s) = s^(N+1) sum_n C(N+n, n) C(2N+1, N-n) (-s)^n, S_N'(s) and int_0^s S_N; the
        integral reaches 1/2 at s = 1 (S_N(1 - s) = 1 - S_N(s)).

    """
    coef = np.zeros(2 * order + 2)
    for n in range(order + 1):
        coef[order + 1 + n] = math.comb(order + n, n) * math.comb(2 * order + 1, order - n) * (
            -1.0) ** n
    q = np.polynomial.Polynomial(coef)
    return q, q.deriv(), q.integ(lbnd=0.0)
