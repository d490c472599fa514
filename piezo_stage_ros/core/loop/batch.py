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
and sensor noise on). How that is kept:

- every sum is written out left to right as the scalar code adds it (no matmul, einsum or
  reduction, whose summation order is the library's), every constant is the float the scalar
  code uses (:func:`piezo_stage_ros.core.model.stage.fused_constants`), products keep the scalar
  code's association ((dt eta) u_fd) s_a;
- the exponential of the hysteresis jump is libm's ``exp``, as ``math.exp`` in the scalar
  kernel: numpy's own float64 ``exp`` is a SIMD implementation (AVX-512 here) that differs from
  libm by one ulp for about 5-10 % of arguments. Without the converters that ulp is in the
  samples at once; with the 16-bit ADC it hides in the stage's state until the position lies
  within that ulp of a code boundary, and then becomes a whole LSB (1.16 nm) after which the
  runs part (rare: 20 stages x 2 s with numpy's exp gave no differing sample, but not never).
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
from piezo_stage_ros.core.control.controllers import ControllerParams, notch_design
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.model.linear import LinearPlant
from piezo_stage_ros.core.model.stage import fused_constants, FusedConstants, Stage, StageParams

__all__ = ['ControllerBatch', 'StageFamilyBatch', 'libm_exp', 'run_batch']



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
            k = fused_constants(st._core)
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
        states = [st._kernel.get() for st in self._stages]
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
        # the adaptive law of issue 10 (docs/controllers.md): its own dead zone eps_a, the
        # normalisation kappa, measured or desired regressors
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
              plant: LinearPlant | None = None, chunk_s: float = 1.0, record: bool = True,
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
        Model of a notch in ``model`` mode (the configured plant, the same for all).
    chunk_s : float
        The reference is evaluated and the noise drawn per chunk of this length [s].
    record : bool
        Return the records (y, x_d, x_d', u and the RAC's theta_hat, phi_hat every sample);
        with False nothing is kept (speed measurements) and an empty list is returned.
    progress : callable, optional
        Called with the simulated time [s] after each chunk.

    Returns
    -------
    list of RunRecord
        One per member, with the samples :func:`closed_loop.run` gives with
        ``diagnostics_every=1`` (diagnostics: ``theta_hat``, ``phi_hat`` for the RAC only).

    Raises
    ------
    ParameterError
        On a bad duration, chunk, or a trajectory list of the wrong length.
    PiezoStageError
        If a command or a measurement is not finite (the batch has no per-sample fallback).

    """
    if controller.feedforward.mode != 'none':
        raise ParameterError('feedforward.mode', controller.feedforward.mode,
                             "'none' in the batched loop",
                             'is not vectorized yet: run one closed loop per stage '
                             '(robustness --single)')
    if not (duration_s > 0.0 and math.isfinite(duration_s)):
        raise ParameterError('duration_s', duration_s, '(0, inf)')
    if not (chunk_s > 0.0 and math.isfinite(chunk_s)):
        raise ParameterError('chunk_s', chunk_s, '(0, inf)')
    batch = stages if isinstance(stages, StageFamilyBatch) else StageFamilyBatch(stages)
    n_members = batch.n
    trajs: list[Trajectory] = (list(trajectory) if isinstance(trajectory, (list, tuple))
                               else [trajectory])  # type: ignore[list-item]
    shared = not isinstance(trajectory, (list, tuple))
    if not shared and len(trajs) != n_members:
        raise ParameterError('trajectory', len(trajs), f'one or {n_members} trajectories')
    dt = batch.sample_time_s
    ctrl = ControllerBatch(controller, dt, plant)
    total = max(int(round(duration_s / dt)), 1)
    per_chunk = max(int(round(chunk_s / dt)), 1)
    y = batch.reset()
    ctrl.reset(y)
    names = ctrl.diagnostic_names
    chunks: list[dict[str, Any]] = []
    cstep, pstep = ctrl.step, batch.step
    k0 = 0
    while k0 < total:
        n = min(per_chunk, total - k0)
        time_s = np.arange(k0, k0 + n, dtype=np.float64) * dt
        ref, vel = _reference_columns(trajs, time_s)
        refs: Any = ref[:, 0].tolist() if shared else ref
        vels: Any = vel[:, 0].tolist() if shared else vel
        batch.reserve(n)
        if record:
            pos = np.empty((n, n_members))
            cmd = np.empty((n, n_members))
            diag = [np.empty((n, n_members)) for _ in names]
            for j in range(n):
                u = cstep(y, refs[j], vels[j])
                pos[j] = y
                cmd[j] = u
                for arr, val in zip(diag, ctrl.diagnostic_values()):
                    arr[j] = val
                y = pstep(u)
            if not (np.isfinite(pos).all() and np.isfinite(cmd).all()):
                raise PiezoStageError('run_batch: a non-finite command or measurement')
            chunks.append({'time_s': time_s, 'pos': pos, 'cmd': cmd, 'ref': ref, 'vel': vel,
                           'diag': diag})
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
                                 {name: diag_all[j][i] for j, name in enumerate(names)}, m))
    return records
