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
The closed loop of N stages at once: stage and controller vectorized over the stages with numpy.

:func:`run_batch` computes, for every member, exactly what
:func:`piezo_stage_ros.core.loop.closed_loop.run` computes for that member alone with a
:class:`~piezo_stage_ros.core.model.stage.Stage` and the controller of
:func:`~piezo_stage_ros.core.control.controllers.build_controller`: the same IEEE operations in
the same order, elementwise, so the samples agree bit for bit (tested, with the 16-bit converters
and sensor noise on). The two loops are twins on purpose: the scalar one is the reference, read
sample by sample and run by the nodes; this one runs a family of stages at a fraction of the
cost a member, and repeating the scalar arithmetic (rather than calling it) is what makes it
fast; the bit-for-bit tests keep the twins one. How that is kept:

- every sum is written out left to right as the scalar code adds it (no matmul, einsum or
  reduction, whose summation order is the library's), every constant is the float the scalar
  code uses (:func:`piezo_stage_ros.core.model.stage.fused_constants`), products keep the scalar
  code's association ((dt eta) u_fd) s_a;
- the exponential of the hysteresis jump is libm's ``exp``, as ``math.exp`` in the scalar
  kernel: numpy's own float64 ``exp`` may be a SIMD implementation that differs from libm by
  one ulp for some arguments. Without the converters that ulp is in the samples at once; with
  the 16-bit ADC it hides in the stage's state until the position lies within that ulp of a
  code boundary, and then becomes a whole LSB after which the runs part (rarely, but not
  never).
  :func:`libm_exp` uses ``scipy.special.inv_boxcox(x, 0)``, a compiled loop that calls libm's
  ``exp``, after checking on 4096 arguments that it returns what ``math.exp`` returns; where it
  does not, it falls back to ``math.exp`` per element (exact, slower);
- sensor noise comes from each member's own generator, seeded as the single stage seeds it,
  drawn in blocks (a block of k normals is the k normals drawn one by one);
- the reset is the single stage's reset (one scalar :class:`Stage` per member sets the state).

Adding a zero (a structural zero of the output row) is skipped: the value is the same, at most the
sign of a zero result differs, and -0.0 == 0.0.

The reference is evaluated once per chunk for each distinct trajectory: one trajectory shared by
every member (the sample's x_d is then a Python float, as in the scalar loop), or one per member.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError, PiezoStageError
from piezo_stage_ros.core.contracts.interfaces import Trajectory
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.control.controllers import (
    build_controller,
    ControllerParams,
    notch_design,
    NotchFilter,
)
from piezo_stage_ros.core.control.feedforward import (
    BacklashInverse,
    CLIP_SETTLE_SAMPLES,
    clipped_excess,
    FeedForwardController,
    LEARN_CHUNK,
    learning_columns,
)
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.model.hysteresis import (
    HysteresisModel,
    HysteresisParams,
    make_hysteresis,
    NoHysteresis,
)
from piezo_stage_ros.core.model.linear import LinearPlant
from piezo_stage_ros.core.model.stage import FusedConstants, Stage, StageParams

__all__ = ['ControllerBatch', 'FeedForwardBatch', 'StageFamilyBatch', 'libm_exp', 'run_batch']



def _exp_by_math(x: FloatArray, out: FloatArray) -> FloatArray:
    out[...] = np.fromiter(map(math.exp, x.tolist()), dtype=np.float64, count=x.size)
    return out


def _select_exp() -> Callable[[FloatArray, FloatArray], FloatArray]:
    try:
        from scipy.special import inv_boxcox
    except ImportError:  # pragma: no cover - scipy is a dependency
        return _exp_by_math
    # the arguments the hysteresis sees: -alpha |dv| from 0 down to -alpha * 12 V and beyond
    probe = -np.concatenate([np.geomspace(1e-12, 50.0, 4000), np.linspace(0.0, 5.0, 96)])
    fast = np.asarray(inv_boxcox(probe, 0.0), dtype=np.float64)
    exact = np.array([math.exp(v) for v in probe.tolist()])
    if not np.array_equal(fast, exact):
        return _exp_by_math

    def exp(x: FloatArray, out: FloatArray) -> FloatArray:
        return np.asarray(inv_boxcox(x, 0.0, out=out), dtype=np.float64)
    return exp


_EXP: Callable[[FloatArray, FloatArray], FloatArray] | None = None


def libm_exp(x: FloatArray, out: FloatArray | None = None) -> FloatArray:
    """
    Return exp(x) elementwise, equal to ``math.exp`` of each element (libm's ``exp``).

    Parameters
    ----------
    x : ndarray
        Arguments (float64).
    out : ndarray, optional
        Where to write (same shape).

    Returns
    -------
    ndarray
        ``out`` (or a new array) holding ``math.exp(x_i)`` bit for bit (module docstring).

    """
    xa = np.ascontiguousarray(x, dtype=np.float64)
    return _exp_function()(xa, np.empty_like(xa) if out is None else out)


def _clip(x: FloatArray, low: Any, high: Any) -> None:
    """Clip in place: min(max(x, low), high), what the scalar code's comparisons give."""
    # two ufunc calls cost less than np.clip's Python-level dispatch on arrays of this size
    np.maximum(x, low, out=x)
    np.minimum(x, high, out=x)


def _exp_function() -> Callable[[FloatArray, FloatArray], FloatArray]:
    """Return the checked implementation :func:`libm_exp` uses (contiguous arrays only)."""
    global _EXP
    if _EXP is None:
        _EXP = _select_exp()
    return _EXP


def _same(values: Sequence[float]) -> float | FloatArray:
    """Return the common value as a float, or the values as an array when they differ."""
    first = values[0]
    if all(v == first and math.copysign(1.0, v) == math.copysign(1.0, first) for v in values):
        return float(first)
    return np.asarray(values, dtype=np.float64)


class StageFamilyBatch:
    """
    N stages, one :class:`~piezo_stage_ros.core.model.stage.StageParams` each, stepped together.

    Each member computes what a :class:`~piezo_stage_ros.core.model.stage.Stage` of its parameters
    computes (module docstring). The members must share the sample rate, the model order (the
    reduced or the third-order plant), the hysteresis (backlash-like or none) and whether the
    converters quantize; any parameter may differ otherwise.

    Parameters
    ----------
    params : sequence of StageParams
        One per member.

    Raises
    ------
    ParameterError
        For an empty sequence, the general model, another hysteresis model, or members that
        differ in sample rate, model order, hysteresis or quantization.

    """

    def __init__(self, params: Sequence[StageParams]) -> None:
        if not params:
            raise ParameterError('stages', 0, '[1, inf) members')
        self.params = list(params)
        self.n = len(self.params)
        self._stages = [Stage(p) for p in self.params]
        consts: list[FusedConstants] = []
        for p, st in zip(self.params, self._stages):
            k = st.fused_constants()
            if k is None:
                raise ParameterError('plant.model', p.plant.model,
                                     "'reduced' or 'third_order' with backlash_like or no "
                                     'hysteresis', 'is not supported by the batch of stages')
            consts.append(k)
        first = consts[0]
        for name, get in (('sample_rate_hz', lambda i: self.params[i].sample_rate_hz),
                          ('plant.model order', lambda i: consts[i].order),
                          ('hysteresis.model', lambda i: consts[i].has_hysteresis),
                          ('chain.quantize', lambda i: (consts[i].dac is None,
                                                        consts[i].adc is None))):
            if any(get(i) != get(0) for i in range(self.n)):
                raise ParameterError(name, [get(i) for i in range(self.n)],
                                     'the same value for every member of the batch')
        self.sample_time_s = self._stages[0].sample_time_s
        self._order = first.order
        self._has_h = first.has_hysteresis
        col = _same
        self._neg_alpha = col([-k.alpha for k in consts])
        self._slope = col([k.slope for k in consts])
        self._shift = col([k.shift for k in consts])
        o = self._order
        # column j of Ad and the column of Bd for every member, shape (order, n): one product
        # per column updates every state row at once, each row still summed left to right
        self._acol = [np.array([[k.ad[i][j] for k in consts] for i in range(o)])
                      for j in range(o)]
        self._bcol = np.array([[k.bd[i] for k in consts] for i in range(o)])
        cs = [col([k.c[i] for k in consts]) for i in range(o)]
        # the output row: the terms whose coefficient is zero for every member are left out
        self._c = [(i, c) for i, c in enumerate(cs) if not (isinstance(c, float) and c == 0.0)]
        self._vmin = col([k.vmin for k in consts])
        self._vmax = col([k.vmax for k in consts])
        self._dac = None if first.dac is None else \
            tuple(col([k.dac[j] for k in consts if k.dac is not None]) for j in range(5))
        self._adc = None if first.adc is None else \
            tuple(col([k.adc[j] for k in consts if k.adc is not None]) for j in range(5))
        noise = np.array([k.noise for k in consts])
        self._noisy = np.flatnonzero(noise > 0.0)
        self._noise = noise[self._noisy]
        # members that share a seed share a noise stream: one generator per seed draws it
        seeds = [self.params[i].seed for i in self._noisy.tolist()]
        self._seed_list = sorted(set(seeds))
        self._seed_of = np.array([self._seed_list.index(s) for s in seeds], dtype=np.intp)
        self._lead = {s: int(self._noisy[seeds.index(s)]) for s in self._seed_list}
        self._reserve = 1
        self._exp = _exp_function()
        self._load_state()

    def reset(self, position_m: float | None = None) -> FloatArray:
        """
        Put every member at rest, as :meth:`Stage.reset` does, and return the measurements.

        Parameters
        ----------
        position_m : float, optional
            Rest position [m]; default each member's ``initial_position_m``.

        Returns
        -------
        ndarray
            Measured positions y_0 [m], shape (n,).

        """
        # the members of one seed continue from where the stream that drew for them stands
        for s in self._seed_list:
            lead = self._stages[self._lead[s]].rng
            for i, si in zip(self._noisy.tolist(), self._seed_of.tolist()):
                if self._seed_list[si] == s and i != self._lead[s]:
                    self._stages[i].rng.bit_generator.state = lead.bit_generator.state
        y = np.array([st.reset(position_m) for st in self._stages], dtype=np.float64)
        self._load_state()
        return y

    def _load_state(self) -> None:
        """Take over the state of the scalar stages (as their last reset left it)."""
        states = [st.kernel_state() for st in self._stages]
        self._x = np.array([[s.x[i] for s in states] for i in range(self._order)],
                           dtype=np.float64)
        self._x_next = np.empty_like(self._x)
        self._tmp3 = np.empty_like(self._x)
        self._buf = np.empty((6, self.n))
        self._v_last = np.array([s.h[0] if self._has_h else 0.0 for s in states])
        self._e = np.array([s.h[1] if self._has_h else 0.0 for s in states])
        self._normals = np.zeros((0, len(self._seed_list)))
        self._cursor = 0

    def reserve(self, steps: int) -> None:
        """
        Say how many steps follow, so that the sensor noise is drawn in one block per seed.

        Parameters
        ----------
        steps : int
            Steps that will be taken before the next reset or reserve; the noise of exactly
            that many is drawn when the next step needs it.

        """
        self._reserve = max(int(steps), 1)

    def _next_normals(self) -> Any:
        """Return the next normal of every noisy member (a scalar when they share one seed)."""
        if self._cursor >= self._normals.shape[0]:
            # one column per seed; members of a seed read its column
            self._normals = np.stack([self._stages[self._lead[s]].rng.standard_normal(
                self._reserve) for s in self._seed_list], axis=1)
            self._cursor = 0
            self._reserve = 1
        row = self._normals[self._cursor]
        self._cursor += 1
        return row[0] if len(self._seed_list) == 1 else row[self._seed_of]

    def true_position_m(self) -> FloatArray:
        """
        Return the true positions c x now [m], shape (n,): what ``Stage.read_position_m`` gives.

        The output row's sum of :meth:`step` before the noise and the converter (the terms whose
        coefficient is zero for every member left out: the same value).
        """
        terms, x = self._c, self._x
        pos: FloatArray = np.multiply(x[terms[0][0]], terms[0][1])
        for i, c in terms[1:]:
            pos += c * x[i]
        return pos

    def step(self, command_v: FloatArray) -> FloatArray:
        """
        Hold one command per member over one sample and return the measured positions.

        Parameters
        ----------
        command_v : ndarray
            Commands [V], shape (n,), finite (the controllers of the batch never return
            anything else).

        Returns
        -------
        ndarray
            Measured positions [m], shape (n,).

        """
        v, dv, decay, om, w, pos = self._buf
        if self._dac is not None:
            ds, do, dtop, dos, doo = self._dac
            np.multiply(command_v, ds, out=v)
            v += do
            np.floor(v, out=v)
            _clip(v, 0.0, dtop)
            v *= dos
            v += doo
        else:
            v[...] = command_v
        _clip(v, self._vmin, self._vmax)
        if self._has_h:
            # e <- e decay + shift copysign(1 - decay, dv), decay = exp(-alpha |dv|)
            np.subtract(v, self._v_last, out=dv)
            np.abs(dv, out=decay)
            decay *= self._neg_alpha
            self._exp(decay, decay)
            np.subtract(1.0, decay, out=om)
            np.copysign(om, dv, out=om)
            om *= self._shift
            e = self._e
            e *= decay
            e += om
            self._v_last[...] = v
            np.multiply(v, self._slope, out=w)
            w += e
        else:
            w[...] = v
        # x <- Ad x + Bd w, each row ((a_i0 x0 + a_i1 x1) + a_i2 x2) + b_i w as the scalar adds
        x, xn, t = self._x, self._x_next, self._tmp3
        np.multiply(self._acol[0], x[0], out=xn)
        for j in range(1, self._order):
            np.multiply(self._acol[j], x[j], out=t)
            xn += t
        np.multiply(self._bcol, w, out=t)
        xn += t
        self._x, self._x_next = xn, x
        terms = self._c
        np.multiply(xn[terms[0][0]], terms[0][1], out=pos)
        for i, c in terms[1:]:
            pos += c * xn[i]
        if self._noisy.size:
            idx = self._noisy
            z = self._next_normals()
            if idx.size == self.n:
                pos += self._noise * z
            else:
                pos[idx] = pos[idx] + self._noise * z
        if self._adc is None:
            return pos.copy()
        as_, ao, atop, aos, aoo = self._adc
        pos *= as_
        pos += ao
        np.floor(pos, out=pos)
        _clip(pos, 0.0, atop)
        pos *= aos
        return np.add(pos, aoo)


class ControllerBatch:
    """
    One controller configuration applied to N stages: RAC, PI or open loop, with the notch.

    Each member computes what the controller of :func:`build_controller` computes for it alone
    (``step`` without ``dt_s``, finite inputs), elementwise.

    Parameters
    ----------
    params : ControllerParams
        The configuration (the same for every member).
    sample_time_s : float
        Sample period T [s].
    plant : LinearPlant, optional
        The model a notch in ``model`` mode is designed on.

    """

    def __init__(self, params: ControllerParams, sample_time_s: float,
                 plant: LinearPlant | None = None) -> None:
        self.params = params
        self.type = params.type
        self._t = float(sample_time_s)
        self._k = float(params.sensor_gain_v_per_m)
        self._vmin = float(params.output_min_v)
        self._vmax = float(params.output_max_v)
        rac = params.rac
        self._neg_kd = -rac.k_d
        self._lam = rac.lambda_per_s
        self._inv_eps = 1.0 / rac.epsilon_v
        self._kstar = rac.k_star_v
        self._gamma, self._eta = rac.gamma, rac.eta
        # the generalised adaptive law (docs/explanation/controllers.md): its own dead zone
        # eps_a, the normalisation kappa, measured or desired regressors
        eps_a = rac.adaptation_dead_zone_v
        inv = 1.0 / eps_a if eps_a > 0.0 else math.inf
        # as the controller: a dead zone whose inverse overflows (subnormal) is no dead zone
        self._eps_a = eps_a if math.isfinite(inv) else 0.0
        self._inv_eps_a = inv if math.isfinite(inv) else 0.0
        self._kappa = rac.normalisation
        self._kappa_dt = self._kappa * self._t
        self._desired = rac.adaptation_regressor == 'desired'
        self._dt_gamma = self._t * rac.gamma
        self._dt_eta = self._t * rac.eta
        self._kp, self._ki = params.pi.k_p, params.pi.k_i
        self._conditional = params.pi.anti_windup == 'conditional'
        self._notch = notch_design(params.notch, self._t, plant)
        self.n = 0
        self.reset(np.zeros(1))

    @property
    def sample_time_s(self) -> float:
        """Return the sample period T [s]."""
        return self._t

    @property
    def diagnostic_names(self) -> tuple[str, ...]:
        """Return ``('theta_hat', 'phi_hat')`` for the RAC, ``()`` otherwise."""
        return ('theta_hat', 'phi_hat') if self.type == 'rac' else ()

    def reset(self, position_m: FloatArray) -> None:
        """
        Return every member to the initial estimates, a zero integral, a fresh notch.

        Parameters
        ----------
        position_m : ndarray
            Measured positions at the start [m], shape (n,) (sets n).

        """
        self.n = int(np.asarray(position_m).size)
        rac = self.params.rac
        self._theta = np.full(self.n, rac.theta_init)
        self._phi = np.full(self.n, rac.phi_init)
        self._i = np.zeros(self.n)
        self._rbuf = [np.empty(self.n) for _ in range(7)]
        self._spare = (np.empty(self.n), np.empty(self.n), np.empty(self.n))
        self._fresh = True
        self._z1 = self._z2 = np.zeros(self.n)
        self.hold_estimates(False)

    def hold_estimates(self, hold: bool) -> None:
        """
        Stop (True) or resume (False) the adaptation of every member, as the RAC's own does.

        Held, the rates gamma and eta are zero: the updates are exact zeros and each member's
        estimates keep their values bit for bit (a PI or open loop has none to hold).
        """
        rac = self.params.rac
        self._gamma, self._eta = (0.0, 0.0) if hold else (rac.gamma, rac.eta)
        self._dt_gamma = self._t * self._gamma
        self._dt_eta = self._t * self._eta

    def diagnostic_values(self) -> tuple[FloatArray, ...]:
        """Return theta_hat and phi_hat per member (RAC), or nothing; valid until the next step."""
        return (self._theta, self._phi) if self.type == 'rac' else ()

    def step(self, position_m: FloatArray, reference_m: float | FloatArray,
             reference_velocity_mps: float | FloatArray) -> FloatArray:
        """
        Compute the commands of one sample.

        Parameters
        ----------
        position_m : ndarray
            Measured positions y_k [m], shape (n,).
        reference_m, reference_velocity_mps : float or ndarray
            x_d(t_k) [m] and its derivative [m/s], shared or one per member.

        Returns
        -------
        ndarray
            Commands [V], shape (n,), inside the output limits.

        """
        if self.type == 'rac':
            v = self._rac(position_m, reference_m, reference_velocity_mps)
        elif self.type == 'pi':
            v = self._pi(position_m, reference_m)
        else:
            ol = self.params.open_loop
            u = ol.gain_v_per_m * np.asarray(reference_m, dtype=np.float64) + ol.offset_v
            v = np.broadcast_to(np.minimum(np.maximum(u, self._vmin), self._vmax),
                                (self.n,)).copy()
        if self._notch is None:
            return v
        (b0, b1, b2), (_, a1, a2) = self._notch
        if self._fresh:
            self._z2 = (b2 - a2) * v
            self._z1 = (b1 - a1) * v + self._z2
            self._fresh = False
        y = b0 * v + self._z1
        self._z1 = b1 * v - a1 * y + self._z2
        self._z2 = b2 * v - a2 * y
        return np.minimum(np.maximum(y, self._vmin), self._vmax)

    def _rac(self, position_m: FloatArray, reference_m: float | FloatArray,
             reference_velocity_mps: float | FloatArray) -> FloatArray:
        k = self._k
        y, e, i_new, s, sz, u_fd, t = self._rbuf
        yd = reference_m * k
        ydd = reference_velocity_mps * k
        lam, theta, phi = self._lam, self._theta, self._phi
        np.multiply(position_m, k, out=y)
        np.subtract(y, yd, out=e)
        np.multiply(e, self._t, out=i_new)                 # I + dt e
        np.add(self._i, i_new, out=i_new)
        np.multiply(i_new, lam, out=s)                     # s = e + lambda I
        np.add(e, s, out=s)
        np.multiply(s, self._inv_eps, out=sz)              # sat(s / eps)
        _clip(sz, -1.0, 1.0)
        np.multiply(e, lam, out=u_fd)                      # u_fd = dy_d/dt - lambda e
        np.subtract(ydd, u_fd, out=u_fd)
        # v = ((-k_d s + phi_hat u_fd) + theta_hat y) - k* sat
        v = np.multiply(s, self._neg_kd)
        np.multiply(phi, u_fd, out=t)
        v += t
        np.multiply(theta, y, out=t)
        v += t
        np.multiply(sz, self._kstar, out=t)
        v -= t
        any_sat = bool(v.max() > self._vmax or v.min() < self._vmin)
        if any_sat:
            high = v > self._vmax
            sat = high | (v < self._vmin)
            # conditional integration where the new error pushes further out
            redo = sat & (high == (e < 0.0))
            if redo.any():
                s_old = e + lam * self._i
                sz_old = np.minimum(np.maximum(s_old * self._inv_eps, -1.0), 1.0)
                v_old = self._neg_kd * s_old + phi * u_fd + theta * y - self._kstar * sz_old
                np.copyto(i_new, self._i, where=redo)
                np.copyto(s, s_old, where=redo)
                np.copyto(sz, sz_old, where=redo)
                np.copyto(v, v_old, where=redo)
            _clip(v, self._vmin, self._vmax)
        rac = self.params.rac
        th, ph, i_old = self._spare
        # s_a = s - eps_a sat(s / eps_a) (s_a = s without a dead zone); where s_a = 0 the
        # updates below subtract a zero, which leaves the estimates as the scalar code does
        s_a = sz
        if self._eps_a > 0.0:
            np.multiply(s, self._inv_eps_a, out=s_a)
            _clip(s_a, -1.0, 1.0)
            s_a *= self._eps_a
            np.subtract(s, s_a, out=s_a)
        else:
            s_a[...] = s
        r_t, r_f = (yd, ydd) if self._desired else (y, u_fd)
        # the coefficients ((g eta) r_phi) and ((g gamma) r_theta) of s_a, g = T / n
        c_f: Any
        c_t: Any
        if self._kappa > 0.0:
            if isinstance(r_t, float) and isinstance(r_f, float):
                # desired regressors of a shared reference: one g, computed as the scalar does
                g = self._t / (1.0 + self._kappa * self._t * (self._gamma * r_t * r_t
                                                              + self._eta * r_f * r_f))
                c_f, c_t = g * self._eta * r_f, g * self._gamma * r_t
            else:
                # n = 1 + (kappa T) ((gamma r_t) r_t + (eta r_f) r_f)
                n = np.multiply(self._gamma, r_t) * r_t
                n += np.multiply(self._eta, r_f) * r_f
                n *= self._kappa_dt
                n += 1.0
                g_n = np.divide(self._t, n)
                c_f = np.multiply(g_n, self._eta) * r_f
                c_t = np.multiply(g_n, self._gamma) * r_t
        else:  # g = T
            c_f = r_f * self._dt_eta
            c_t = r_t * self._dt_gamma
        np.multiply(c_f, s_a, out=t)
        np.subtract(phi, t, out=ph)
        _clip(ph, rac.phi_min, rac.phi_max)
        np.multiply(c_t, s_a, out=t)
        np.subtract(theta, t, out=th)
        _clip(th, rac.theta_min, rac.theta_max)
        if any_sat:  # the adaptation is frozen for a clipped sample
            np.copyto(ph, phi, where=sat)
            np.copyto(th, theta, where=sat)
        # new estimates and integral in, the old arrays become the spares of the next step
        self._spare = (theta, phi, self._i)
        self._theta, self._phi = th, ph
        self._i, self._rbuf[2] = i_new, i_old
        return v

    def _pi(self, position_m: FloatArray, reference_m: float | FloatArray) -> FloatArray:
        e = (reference_m - position_m) * self._k
        i_new = self._i + self._t * e
        v = self._kp * e + self._ki * i_new
        high = v > self._vmax
        sat = high | (v < self._vmin)
        if sat.any():
            if self._conditional:
                redo = sat & (high == (e > 0.0))
                i_new = np.where(redo, self._i, i_new)
                v = np.where(redo, self._kp * e + self._ki * self._i, v)
            v = np.minimum(np.maximum(v, self._vmin), self._vmax)
        self._i = i_new
        return np.asarray(v, dtype=np.float64)


class FeedForwardBatch:
    """
    The feed-forward around a :class:`ControllerBatch`, for N members that share one reference.

    What :class:`~piezo_stage_ros.core.control.feedforward.FeedForwardController` computes for
    each member alone. Designed once, as the scalar wrapper is, on the design model (the
    configured plant and hysteresis, never a member's): a scalar wrapper built by
    :func:`build_controller` and bound to the trajectory is kept as the *template* and gives
    the tables (reference, shaped reference, model inverse w: shared by every member), the
    learning filter and the share of the RAC's initial estimates. Per member: the learned table
    and the update accumulated over the period (shape (period, n)), the state of the inverse
    hysteresis and, in the controller batch, the estimates the learning holds. Each member
    computes what the scalar wrapper computes for it alone, the same operations in the same
    order (the learning update summed sample by sample, the inverse hysteresis by the same
    Newton steps with libm's ``exp``).

    Parameters
    ----------
    params : ControllerParams
        The configuration (``feedforward.mode`` not ``none``).
    ctrl : ControllerBatch
        The feedback of every member.
    plant : LinearPlant
        Design model of the linear part (None is refused, as by :func:`build_controller`).
    hysteresis : HysteresisModel
        Design hysteresis (backlash-like or none).
    trajectory : Trajectory
        The reference every member follows.

    """

    def __init__(self, params: ControllerParams, ctrl: ControllerBatch,
                 plant: LinearPlant | None, hysteresis: HysteresisModel,
                 trajectory: Trajectory) -> None:
        if getattr(trajectory, 'segments', None):
            raise ParameterError('trajectory', type(trajectory).__name__,
                                 'one trajectory for the whole run',
                                 'changes its line rate: the batched loop binds one reference '
                                 '(run one closed loop per stage)')
        template = build_controller(params, ctrl.sample_time_s, plant, hysteresis)
        assert isinstance(template, FeedForwardController)
        self.template = template
        self.ctrl = ctrl
        ff = params.feedforward
        self._inverse, self._learning = ff.inverse, ff.learning
        self._vmin, self._vmax = float(params.output_min_v), float(params.output_max_v)
        self._slope = template.slope
        self._theta0, self._phi0, self._ksens = template.share_gains()
        hyst = template.hysteresis_inverse
        self._jump: tuple[float, float, float, float, float] | None = None
        self._rest_gain = 0.0
        if hyst is not None and not isinstance(hysteresis, NoHysteresis):
            if not isinstance(hyst, BacklashInverse):
                raise ParameterError('hysteresis.model', type(hysteresis).__name__,
                                     'backlash_like or none', 'has no inverse in the batched '
                                     'loop: run one closed loop per stage')
            self._jump = hyst.jump_constants()
            self._rest_gain = template.plant_inverse.dc_gain * hyst.slope
        coeffs = notch_design(params.notch, ctrl.sample_time_s, plant)
        self._share_notch = None if coeffs is None else NotchFilter(*coeffs)
        # what the held estimates add over the initial ones, per member (the scalar's _drift)
        self._drift_notch: Any = None if coeffs is None else NotchFilter(*coeffs)
        self._drift_gains: tuple[FloatArray, FloatArray] | None = None
        self._drift_fresh = True
        self._limit = ff.learning_limit_v
        self._start_periods = ff.learning_start_periods
        self._exp = _exp_function()
        self.trajectory = trajectory
        self._start_holding = False
        self.n = 0
        self.mismatches = 0
        self.periods_learned = 0

    def reset(self, position_m: FloatArray) -> None:
        """
        Bind the template to the reference afresh and put every member at sample 0.

        Parameters
        ----------
        position_m : ndarray
            Measured positions at the start [m], shape (n,): the inverse hysteresis of each
            member starts at rest where its stage does.

        """
        self.template.bind(self.trajectory)
        self._periodic = self.template.reference_tables(0)
        period = self._periodic[0]
        self.n = n = int(np.asarray(position_m).size)
        self._period = period
        self._k = 0
        self._share_fresh = True
        self._holding = False
        # inverse alone: the estimates held over the start-up transient (the scalar wrapper)
        self._start_holding = self.template.start_hold > 0
        self.ctrl.hold_estimates(self._start_holding)
        self._drift_gains = None
        self._learned = np.zeros((period, n))
        self._delta = np.zeros((n, period))
        self._errors = np.zeros((period, n))
        self._acc = np.zeros((n, period))
        self._term = np.zeros((n, period))
        self._columns = learning_columns(self.template.learning_kernel()) if self._learning \
            else np.zeros((0, 0))
        self._learn_from = self._start_periods * period
        # the amplifier's range, per member (the scalar wrapper's _clip_k, _excess_table)
        self._clip_k = np.full(n, -(1 << 62), dtype=np.int64)
        self._excess = np.zeros((period, n))
        self._excess_any = np.zeros(n, dtype=bool)
        self._leak, self._kept = self.template.limit_terms()
        #: Commands the amplifier's range clipped, per member.
        self.clipped_samples = np.zeros(n, dtype=np.int64)
        # a period that is not a whole number of samples: every member's table on its phase
        template_phase = self.template.phase_table
        self._phase = None if template_phase is None or not self._learning else \
            self.template.phase_learning(template_phase.samples, n)
        if self._jump is not None:
            # BacklashInverse.reset at position / (dc gain slope): at rest, e = 0
            self._hv = np.asarray(position_m, dtype=np.float64) / self._rest_gain
            self._he = np.zeros(n)
        self.mismatches = 0
        self.periods_learned = 0

    def learned_table(self) -> FloatArray:
        """
        Return a copy of every member's learned table [V], shape (period, n).

        A period that is not a whole number of samples: the table at the phases of
        :meth:`~piezo_stage_ros.core.control.feedforward.FeedForwardController.table_points`.
        """
        if self._phase is not None:
            return self._phase.on_grid(self.template.table_points())
        return self._learned.copy()

    def step(self, position_m: FloatArray, reference_m: float,
             reference_velocity_mps: float) -> FloatArray:
        """
        Return every member's command [V]: feedback plus feed-forward, through the inverse.

        Parameters
        ----------
        position_m : ndarray
            Measured positions y_k [m], shape (n,).
        reference_m, reference_velocity_mps : float
            The shared reference of this sample, checked against the bound one.

        Returns
        -------
        ndarray
            Commands [V], shape (n,).

        """
        k = self._k
        self._k = k + 1
        if self._start_holding and k >= self.template.start_hold:
            self._start_holding = False
            self.ctrl.hold_estimates(False)
        n = self._period
        if n:
            i = k % n
            tables = self._periodic
        else:
            tables = self.template.reference_tables(k)
            i = k - tables[1]
        _, _, lx_raw, lx, lv, lw = tables
        xd = lx_raw[i]
        if abs(reference_m - xd) > 1e-12 + 1e-9 * abs(xd):
            # not the bound reference: feedback alone for this sample (the scalar wrapper)
            self.mismatches += 1
            self._share_fresh = True
            return self._output(self.ctrl.step(position_m, reference_m, reference_velocity_mps))
        x_ref = lx[i]
        v_ref = lv[i]
        u = self.ctrl.step(position_m, x_ref, v_ref)
        if self._inverse:
            u = u - self._share(x_ref, v_ref)
            u += lw[i]
            if self._drift_gains is not None:
                u = u - self._drift(x_ref, v_ref)
        phase = self._phase
        if phase is not None:
            value = phase.play(k)
            u = u + value
            if k >= phase.learn_from:
                if not self._holding:
                    self._hold()
                phase.record(k, np.where(k - self._clip_k > CLIP_SETTLE_SAMPLES,
                                         position_m - x_ref, self._leak * value))
            self.periods_learned = phase.periods_learned
            v = self._output(u)
            if self._clipped.any():
                phase.record_excess(k, np.where(self._clipped, self._fold(value), 0.0))
            return v
        if self._learning:
            table = self._learned[i]
            u = u + table
            if k >= self._learn_from:
                if not self._holding:
                    self._hold()
                self._errors[i] = np.where(k - self._clip_k > CLIP_SETTLE_SAMPLES,
                                           position_m - x_ref, self._leak * table)
                if i % LEARN_CHUNK == LEARN_CHUNK - 1 or i == n - 1:
                    self._accumulate(i + 1)
            if i == n - 1 and k >= self._learn_from:
                self._update()
            v = self._output(u)
            if self._clipped.any():
                fold = np.where(self._clipped, self._fold(table), 0.0)
                self._excess[i] += fold
                self._excess_any |= fold != 0.0
            return v
        return self._output(u)

    def _fold(self, table: FloatArray) -> FloatArray:
        """Return what the range clipped off each member's table entry (the scalar's)."""
        jump = self._jump
        applied = (jump[1] * self._hv + self._he) / self._slope if jump is not None \
            else self._v
        return np.asarray(clipped_excess(self._asked - applied, table), dtype=np.float64)

    def _update(self) -> None:
        """Apply the period's update to every member's table, as the scalar wrapper's _learn."""
        learned = self._learned
        learned -= self._delta.T
        for j in np.flatnonzero(self._excess_any):
            column = learned[:, j] - self._excess[:, j]
            learned[:, j] = np.fft.irfft(np.fft.rfft(column) * self._kept, len(column))
        self._excess.fill(0.0)
        self._excess_any.fill(False)
        peak = np.max(np.abs(learned), axis=0)
        for j in np.flatnonzero(peak > self._limit):
            learned[:, j] *= self._limit / float(peak[j])
        self._delta.fill(0.0)
        self.periods_learned += 1

    def _accumulate(self, end: int) -> None:
        """
        Add the errors of the run of samples ending at ``end`` to every member's update.

        The scalar wrapper's sums, in its order: the errors of the run, latest first, times
        the windows of the kernel, added row after row (its ``sum(axis=0)``).
        """
        n = self._period
        start = (end - 1) // LEARN_CHUNK * LEARN_CHUNK
        rows = self._columns[n - end + 1:n - start + 1]
        chunk = self._errors[start:end][::-1]
        acc, term = self._acc, self._term
        np.multiply(chunk[0][:, None], rows[0], out=acc)
        for c in range(1, end - start):
            np.multiply(chunk[c][:, None], rows[c], out=term)
            acc += term
        self._delta += acc

    def _hold(self) -> None:
        """Hold every member's estimates; with the model inverse, take off what they add."""
        self._holding = True
        self.ctrl.hold_estimates(True)
        estimates = self.ctrl.diagnostic_values()
        if self._inverse and len(estimates) == 2:
            theta, phi = estimates
            self._drift_gains = (theta - self._theta0, phi - self._phi0)
            self._drift_fresh = True

    def _drift(self, x_ref: float, v_ref: float) -> FloatArray:
        """Return what each member's held estimates add at x_ref, through the notch (scalar's)."""
        assert self._drift_gains is not None
        d_theta, d_phi = self._drift_gains
        drift = (d_theta * x_ref + d_phi * v_ref) * self._ksens
        notch = self._drift_notch
        if notch is None:
            return np.asarray(drift, dtype=np.float64)
        if self._drift_fresh:
            self._drift_fresh = False
            notch.reset(drift)
        return np.asarray(notch.step(drift), dtype=np.float64)

    def _share(self, x_ref: float, v_ref: float) -> float:
        """Return the RAC's share at its initial estimates (one for all), through the notch."""
        share = (self._theta0 * x_ref + self._phi0 * v_ref) * self._ksens
        notch = self._share_notch
        if notch is None:
            return share
        if self._share_fresh:  # restarted at rest on the present share, as the scalar wrapper
            self._share_fresh = False
            notch.reset(share)
        return notch.step(share)

    def _output(self, u: FloatArray) -> FloatArray:
        """Return the commands for the linear inputs ``u``: inverse hysteresis, the range."""
        jump = self._jump
        self._asked = u
        if jump is not None:
            u = self._invert(self._slope * u)
        v = np.minimum(np.maximum(u, self._vmin), self._vmax)
        self._clipped = v != u
        if self._clipped.any():
            self._clip_k[self._clipped] = self._k - 1
            self.clipped_samples += self._clipped
        if jump is not None:
            self._commit(v)
        self._v = v
        return v

    def _invert(self, w_target: FloatArray) -> FloatArray:
        """BacklashInverse.invert for every member: Newton on the branch of the jump's sign."""
        assert self._jump is not None
        alpha, c, shift, tol, bound = self._jump
        v0, e0 = self._hv, self._he
        exp = self._exp
        with np.errstate(divide='ignore', invalid='ignore'):
            dw = w_target - (c * v0 + e0)
            sgn = np.where(dw > 0.0, 1.0, -1.0)
            a = sgn * shift - e0
            a_s = a * sgn
            slope = c + alpha * a_s
            dv = dw / np.where(slope > 0.0, slope, c)
            alpha_a_s = alpha * a_s
            one_minus = np.empty_like(dv)
            decay = np.empty_like(dv)
            active = np.ones(dv.shape, dtype=bool)
            for _ in range(30):
                # the same operations as the scalar solve, member by member: exp(-alpha |dv|)
                exp(np.abs(dv) * -alpha, decay)
                np.subtract(1.0, decay, out=one_minus)
                g = c * dv + a * one_minus - dw
                active &= ~((-tol <= g) & (g <= tol))
                if not active.any():
                    break
                step = g / (c + alpha_a_s * decay)
                np.copyto(dv, dv - step, where=active)
                # the a-priori stop: this step was the last one for the members it brings
                # within the tolerance
                active &= ~(bound * step * step <= tol)
                if not active.any():
                    break
        return np.where(dw == 0.0, v0, v0 + dv)

    def _commit(self, v: FloatArray) -> None:
        """BacklashInverse.commit for every member: the state across the applied jump."""
        assert self._jump is not None
        alpha, _, shift, _, _ = self._jump
        dv = v - self._hv
        decay = np.abs(dv)
        decay *= -alpha
        self._exp(decay, decay)
        self._he = self._he * decay + shift * np.copysign(1.0 - decay, dv)
        self._hv = v


def _reference_columns(trajectories: Sequence[Trajectory], time_s: FloatArray
                       ) -> tuple[FloatArray, FloatArray]:
    """Evaluate each distinct trajectory once and return (n, members) arrays."""
    cache: dict[int, tuple[FloatArray, FloatArray]] = {}
    for tr in trajectories:
        if id(tr) not in cache:
            r, v = tr.evaluate(time_s)
            cache[id(tr)] = (np.asarray(r, dtype=np.float64), np.asarray(v, dtype=np.float64))
    ref = np.stack([cache[id(tr)][0] for tr in trajectories], axis=1)
    vel = np.stack([cache[id(tr)][1] for tr in trajectories], axis=1)
    return ref, vel


def run_batch(stages: Sequence[StageParams] | StageFamilyBatch, controller: ControllerParams,
              trajectory: Trajectory | Sequence[Trajectory], *, duration_s: float,
              plant: LinearPlant | None = None, hysteresis: HysteresisModel | None = None,
              chunk_s: float = 1.0, record: bool = True, record_from_s: float = 0.0,
              progress: Callable[[float], None] | None = None) -> list[RunRecord]:
    """
    Run the closed loop of every member at once; each as :func:`closed_loop.run` would.

    Parameters
    ----------
    stages : sequence of StageParams or StageFamilyBatch
        One per member (see :class:`StageFamilyBatch` for what they must share), or a batch
        built from them (reset here, as the loop resets its stage).
    controller : ControllerParams
        The configuration every member's controller is built from.
    trajectory : Trajectory or sequence of Trajectory
        One reference shared by all (evaluated once per chunk), or one per member.
    duration_s : float
        Simulated time [s]; ``round(duration_s / T)`` samples, at least one.
    plant : LinearPlant, optional
        Model of a notch in ``model`` mode and of the feed-forward (the configured plant, the
        same for all; required with feed-forward).
    hysteresis : HysteresisModel, optional
        Design hysteresis the feed-forward inverts (backlash-like or none); default the paper's,
        as :func:`build_controller`'s.
    chunk_s : float
        The reference is evaluated and the noise drawn per chunk of this length [s].
    record : bool
        Return the records (y, x_d, x_d', u, the true position x and the RAC's theta_hat,
        phi_hat every sample);
        with False nothing is kept (speed measurements) and an empty list is returned.
    record_from_s : float
        Record the samples from ``round(record_from_s / T)`` on only (long runs measured on a
        late window: memory); the samples before are stepped alike, unrecorded.
    progress : callable, optional
        Called with the simulated time [s] after each chunk.

    Returns
    -------
    list of RunRecord
        One per member, with the samples :func:`closed_loop.run` gives with
        ``diagnostics_every=1`` (diagnostics: ``theta_hat``, ``phi_hat`` for the RAC only),
        feed-forward included (:class:`FeedForwardBatch`).

    Raises
    ------
    ParameterError
        On a bad duration, chunk, or a trajectory list of the wrong length; feed-forward with
        one trajectory per member, without a plant, with a design hysteresis other than
        backlash-like or none, or learning on an aperiodic reference.
    PiezoStageError
        If a command or a measurement is not finite (the batch has no per-sample fallback).

    """
    if not (duration_s > 0.0 and math.isfinite(duration_s)):
        raise ParameterError('duration_s', duration_s, '(0, inf)')
    if not (chunk_s > 0.0 and math.isfinite(chunk_s)):
        raise ParameterError('chunk_s', chunk_s, '(0, inf)')
    if not (record_from_s >= 0.0 and math.isfinite(record_from_s)):
        raise ParameterError('record_from_s', record_from_s, '[0, inf)')
    batch = stages if isinstance(stages, StageFamilyBatch) else StageFamilyBatch(stages)
    n_members = batch.n
    trajs: list[Trajectory] = (list(trajectory) if isinstance(trajectory, (list, tuple))
                               else [trajectory])  # type: ignore[list-item]
    shared = not isinstance(trajectory, (list, tuple))
    if not shared and len(trajs) != n_members:
        raise ParameterError('trajectory', len(trajs), f'one or {n_members} trajectories')
    dt = batch.sample_time_s
    ctrl = ControllerBatch(controller, dt, plant)
    ff: FeedForwardBatch | None = None
    if controller.feedforward.mode != 'none':
        if not shared:
            raise ParameterError('trajectory', f'{len(trajs)} trajectories', 'one shared by '
                                 'every member', 'with feed-forward in the batched loop')
        ff = FeedForwardBatch(controller, ctrl, plant,
                              make_hysteresis(HysteresisParams()) if hysteresis is None
                              else hysteresis, trajs[0])
    total = max(int(round(duration_s / dt)), 1)
    per_chunk = max(int(round(chunk_s / dt)), 1)
    y = batch.reset()
    ctrl.reset(y)
    if ff is not None:
        ff.reset(y)
    names = ctrl.diagnostic_names
    chunks: list[dict[str, Any]] = []
    cstep, pstep = (ctrl.step if ff is None else ff.step), batch.step
    read_true = batch.true_position_m
    first = min(max(int(round(record_from_s / dt)), 0), total - 1) if record else total
    k0 = 0
    while k0 < total:
        # a chunk ends where the recording starts
        n = min(per_chunk, total - k0, first - k0 if k0 < first else total)
        time_s = np.arange(k0, k0 + n, dtype=np.float64) * dt
        ref, vel = _reference_columns(trajs, time_s)
        refs: Any = ref[:, 0].tolist() if shared else ref
        vels: Any = vel[:, 0].tolist() if shared else vel
        batch.reserve(n)
        if k0 >= first:
            pos = np.empty((n, n_members))
            cmd = np.empty((n, n_members))
            true = np.empty((n, n_members))
            diag = [np.empty((n, n_members)) for _ in names]
            for j in range(n):
                u = cstep(y, refs[j], vels[j])
                pos[j] = y
                true[j] = read_true()
                cmd[j] = u
                for arr, val in zip(diag, ctrl.diagnostic_values()):
                    arr[j] = val
                y = pstep(u)
            if not (np.isfinite(pos).all() and np.isfinite(cmd).all()):
                raise PiezoStageError('run_batch: a non-finite command or measurement')
            chunks.append({'time_s': time_s, 'pos': pos, 'cmd': cmd, 'ref': ref, 'vel': vel,
                           'true': true, 'diag': diag})
        else:
            for j in range(n):
                y = pstep(cstep(y, refs[j], vels[j]))
            if not np.isfinite(y).all():
                raise PiezoStageError('run_batch: a non-finite measurement')
        k0 += n
        if progress is not None:
            progress(k0 * dt)
    if not record:
        return []
    time_all = np.concatenate([c['time_s'] for c in chunks])
    pos_all = np.concatenate([c['pos'] for c in chunks]).T.copy()
    cmd_all = np.concatenate([c['cmd'] for c in chunks]).T.copy()
    ref_all = np.concatenate([c['ref'] for c in chunks]).T.copy()
    vel_all = np.concatenate([c['vel'] for c in chunks]).T.copy()
    true_all = np.concatenate([c['true'] for c in chunks]).T.copy()
    diag_all = [np.concatenate([c['diag'][j] for c in chunks]).T.copy()
                for j in range(len(names))]
    meta: dict[str, Any] = {'sample_time_s': dt, 'duration_s': total * dt}
    records = []
    for i in range(n_members):
        period = getattr(trajs[0 if shared else i], 'period_s', None)
        m = dict(meta)
        if isinstance(period, float) and period > 0.0:
            m['trajectory_period_s'] = period
        records.append(RunRecord(time_all, pos_all[i], ref_all[0 if shared else i],
                                 vel_all[0 if shared else i], cmd_all[i],
                                 {name: diag_all[j][i] for j, name in enumerate(names)}, m,
                                 true_all[i]))
    return records
