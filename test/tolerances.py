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
Rounding-error bounds for the tests' floating-point comparisons.

A tolerance between two computations of the same quantity is the sum of the rounding errors of
both, and those are fixed by the conditioning of each computation, not by what one machine printed:
BLAS kernels (OPENBLAS_CORETYPE), thread counts, numpy's SIMD level and library versions change
the order of operations and so the last bits, always within these bounds. See
docs/explanation/testing.md.
"""

import math

import numpy as np
from numpy.typing import ArrayLike
from piezo_stage_ros.core.contracts.types import FloatArray

EPS = float(np.finfo(np.float64).eps)  # 2.2e-16, unit roundoff u = EPS / 2


def ss2tf_freqz_error_bound(a: FloatArray, b: FloatArray,
                            c: FloatArray, den: FloatArray,
                            z: ArrayLike) -> FloatArray:
    """
    Bound the absolute error of H(z) computed as ss2tf then freqz, and of C (zI - A)^-1 B.

    ``scipy.signal.ss2tf`` forms the numerator as ``poly(A - B C) - poly(A)`` and ``np.poly``
    multiplies out computed eigenvalues. A backward-stable eigensolver moves each eigenvalue by
    about ``n eps kappa(V) ||A||`` (Bauer-Fike, kappa(V) the eigenvector matrix's condition
    number), and each polynomial coefficient by that times the size of the coefficients, at
    most ``||den||_1``. The numerator is the *difference* of two such polynomials, so its error is
    absolute, of the size of the denominator's coefficients, however small the numerator (the DC
    gain) is: a tolerance relative to the response is wrong for this reference. freqz then
    divides by D(z), so on |z| = 1 the error of H is the ``n + 1`` coefficient errors over
    ``|D(z)|``, plus the denominator's own error times ``|H|``. The other side, a linear solve
    with zI - A, adds ``n eps cond(zI - A) |H|``. A factor 2 covers the eigenvalues of both
    A - B C and A and the products in np.poly.
    """
    n = a.shape[0]
    bc = b @ c
    v_a = np.linalg.eig(a)[1]
    v_abc = np.linalg.eig(a - bc)[1]
    kappa = max(np.linalg.cond(v_a), np.linalg.cond(v_abc))
    scale = max(np.linalg.norm(a, 2), np.linalg.norm(a - bc, 2))
    coefficient_error = 2 * n * EPS * kappa * scale * np.sum(np.abs(den))
    z = np.atleast_1d(np.asarray(z, dtype=np.complex128))
    d_of_z = np.abs(np.polyval(den, z))
    h = np.array([abs((c @ np.linalg.solve(zk * np.eye(n) - a, b)).item()) for zk in z])
    cond = np.array([np.linalg.cond(zk * np.eye(n) - a) for zk in z])
    return np.asarray((n + 1) * coefficient_error * (1.0 + h) / d_of_z + n * EPS * cond * h)


def gamma(m: int) -> float:
    """Return gamma_m = m u / (1 - m u), the relative error bound of an m-term dot product."""
    u = EPS / 2
    return m * u / (1 - m * u)


def lti_rounding_bound(ad: FloatArray, bd: FloatArray,
                       c: FloatArray, x_abs_max: FloatArray,
                       w_abs_max: FloatArray, steps: int) -> float:
    """
    Bound |y_a - y_b| of two runs of x+ = Ad x + Bd w, y = c x that round differently.

    Two evaluations of the same recursion that differ only in the order of their additions
    (a BLAS matmul, with or without FMA, against a left-to-right scalar loop) each make an error
    of at most ``gamma_(n+m) (|Ad| |x| + |Bd| |w|)`` per step (componentwise, Higham's dot
    product bound). The difference of the two runs is that error driven through the recursion,
    ``e_k+1 = Ad e_k + r_k``, so at the output it is at most
    ``sum_j |c Ad^j| r_max`` over the run, plus the output dot product's own rounding.
    """
    n, m = bd.shape
    per_step = 2 * gamma(n + m) * (np.abs(ad) @ x_abs_max + np.abs(bd) @ w_abs_max)
    gain = np.zeros(n)
    power = np.eye(n)
    for _ in range(steps):
        gain += np.abs(c @ power)
        power = ad @ power
    return float(gain @ per_step + 2 * gamma(n) * np.abs(c) @ x_abs_max)


def charpoly_error_bound(a: FloatArray) -> FloatArray:
    """
    Bound the absolute error of each coefficient of ``np.poly(a)``, highest power first.

    np.poly takes computed eigenvalues, each within ``delta = n eps kappa(V) ||A||_2`` of the
    exact one (backward-stable eigensolver, Bauer-Fike), and multiplies out prod (s - lambda_i).
    The coefficient of s^(n-k) is the k-th elementary symmetric function e_k of the eigenvalues:
    moving each by delta moves it by at most ``C(n, k) ((r + delta)^k - r^k)`` with r the spectral
    radius, and forming the products rounds it by ``gamma_n C(n, k) (r + delta)^k`` more.
    """
    n = a.shape[0]
    lam, v = np.linalg.eig(a)
    delta = n * EPS * np.linalg.cond(v) * np.linalg.norm(a, 2)
    r = float(np.max(np.abs(lam)))
    k = np.arange(n + 1)
    binom = np.array([math.comb(n, int(j)) for j in k], dtype=np.float64)
    return binom * (((r + delta) ** k - r ** k) + 2 * gamma(n) * (r + delta) ** k)
