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

r"""
Feed-forward from the known reference: inverse hysteresis, preview plant inversion, learning.

A two-degree-of-freedom structure around any controller of
:mod:`piezo_stage_ros.core.control.controllers` (RAC or PI, notched or not)::

    v_lin,k = C(y_k, r_k) - N(s_k) + u_ff,k + L[k mod N]          (volts, "linear" input)
    v_k     = H^-1(c v_lin,k)   clipped to the amplifier range

- **u_ff** (``inverse``): the input the design model needs to follow the reference exactly,
  w = G^-1 x_d, computed ahead of time from the reference (the trajectory is known). G(z) is the
  zero-order-hold model from the hysteresis output w [V] to x [m]; its zeros outside the unit
  circle are inverted anti-causally (stable inversion with a preview of a few samples), the
  others causally. For a periodic reference with a whole number of samples per period the
  inverse is taken exactly on the period's harmonics (W = X / G(e^{j w T})).
- **s_k**, the feed-forward share of the inner controller: the RAC already contains a first-
  order inverse, theta_hat y + phi_hat dy_d/dt (eq. (36)); at perfect tracking it would double
  u_ff. Its share at the initial estimates, s = k (theta_0 x_d + phi_0 dx_d/dt), is subtracted
  (through a copy of the notch when there is one): on the design model the RAC then adds
  nothing at perfect tracking, and on another stage its adaptation still works on top of the
  model inverse, (theta_hat - theta_0) y + (phi_hat - phi_0) dy_d/dt making up a gain or lag the
  model lacks. The feedback part is untouched: (theta_hat - phi_hat lambda) e - k_d s - k*
  sat(s/eps), the terms the stability check linearizes. A PI has no share (s = 0).
  ``inverse`` alone holds the estimates over the start (:data:`START_HOLD_DECAY`): the error
  there is the stage settling onto the model inverse's orbit, which no estimate explains.
- **H^-1** (``inverse``): the inverse of the design hysteresis w = H(v), applied to the whole
  command, so that the plant seen from v_lin is c G with no hysteresis (c the model's slope,
  which keeps the RAC's estimates at their model values). Exact for backlash-like hysteresis
  (Newton on its closed-form jump solution) and solved by safeguarded secant steps for the
  other models, both to 1e-10 V (the DAC's step is 1.8e-4 V).
- **L** (``learning``): iterative learning across periods of a periodic reference. After each
  period j the table is updated on the harmonics: L_{j+1} = Q (L_j - gamma E_j / P_s), with E_j
  the measured error of that period and P_s = c G / (1 + N C k c G) the closed-loop process
  sensitivity of the design model (the controller linearized as the stability check does).
  Q keeps the harmonics below ``learning_bandwidth_hz`` (a fast line's first ones a little
  above it, :func:`kept_harmonics`); on the design model each kept harmonic
  converges monotonically with ratio |1 - gamma|; on another stage the ratio is
  |1 - gamma P_true / P_s| (:func:`learning_convergence`). The update is summed in runs of 16
  (no FFT at the period's end), and the RAC's estimates are held while the table learns: both
  would chase the same periodic error and drift.
- **Jumps**: an ideal jump cannot be followed; each jump of the reference is replaced by the
  quintic S-curve of ``transition_s`` starting at it (nothing moves before the jump is due),
  and the inner controller tracks that path and the learning learns against it. A jump is a
  step the reference's velocity does not explain by more than a smooth path could
  (:func:`shape_jumps`: the test scales with T). ``learning`` without the model inverse can
  only draw what lies in Q's band: its S-curves last at least
  :data:`LEARNING_SHAPE_CYCLES` / ``learning_bandwidth_hz``, so that what Q drops of them, which
  would ring over the whole period ahead of the edge, stays below 5e-4 of the jump.

The learned table can be kept: :meth:`FeedForwardController.learned` returns it with what it
was learned for (:class:`LearnedTable`: the period's reference, T, the mode, the design), saved
relative to the RAC's initial estimates; :func:`write_learned_table` and
:func:`read_learned_table` put it in a versioned ``.npz`` file, and ``table_file`` starts a
bound controller from one, refused unless period, reference and design match.

The reference comes from the trajectory object the wrapper is bound to
(:meth:`FeedForwardController.bind`): the offline runner and the nodes hold the same one, and
the reference each step receives is checked against it (a mismatch, a trajectory changed
elsewhere, turns the feed-forward off until the next bind, counted in ``ff_mismatches``).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
import hashlib
import math
import os
from pathlib import Path
from typing import Any, Callable, Mapping
import zipfile

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError, PiezoStageError
from piezo_stage_ros.core.contracts.interfaces import Trajectory
from piezo_stage_ros.core.contracts.params import param, Params
from piezo_stage_ros.core.contracts.types import ComplexArray, FloatArray, IntArray
from piezo_stage_ros.core.model.hysteresis import BacklashLike, HysteresisModel, NoHysteresis
from piezo_stage_ros.core.model.linear import LinearPlant
from piezo_stage_ros.core.signals.shapes import s_curve

__all__ = ['FeedForwardController', 'FeedForwardParams', 'HysteresisInverse', 'LearnedTable',
           'MIN_PERIOD_SAMPLES', 'MODES', 'PhaseLearning', 'PreviewInverse', 'TABLE_FORMAT',
           'TABLE_META_KEY', 'TABLE_VERSION', 'boundary_weights', 'check_learning_period',
           'CLIP_SETTLE_SAMPLES', 'clipped_excess', 'LEARNING_SHAPE_CYCLES',
           'BANDWIDTH_STRETCH', 'kept_harmonics', 'LEARN_SPECTRUM_SAMPLES',
           'LEARN_SPREAD_SAMPLES', 'MIN_LEARNED_HARMONICS',
           'learning_columns', 'learning_convergence', 'make_hysteresis_inverse',
           'period_harmonics', 'phase_learning_convergence', 'phase_windows',
           'process_sensitivity', 'read_learned_table', 'shape_jumps', 'START_HOLD_DECAY',
           'start_hold_samples', 'whole_period', 'write_learned_table']

#: The feed-forward modes.
MODES = ('none', 'inverse', 'learning', 'inverse_learning')

#: Samples whose errors enter the learning update together (one correlation each run).
LEARN_CHUNK = 16

#: Periods of at least this many samples spread each run's correlation over the next samples,
#: a slice of the period's columns a sample: the run's whole correlation costs LEARN_CHUNK
#: times the period, too much for one sample of a long period (a raster's frame), and the
#: slices add the same products in the same order to each column, so the update is the same.
LEARN_SPREAD_SAMPLES = 1024

#: Periods of at least this many samples learn on the kept harmonics instead, where the
#: controller is told to (``spectrum_samples``; the multi-axis controller does): each error is
#: added to the period's spectrum on them as it comes (a few operations on the harmonics a
#: sample, not on the period's samples), and the period's end turns the filtered spectrum into
#: the update with one inverse FFT. The update differs from the summed columns in the last
#: bits only (other roundings); it makes a many-axis servo's sample cheap where the columns
#: cost a period's length a sample and axis.
LEARN_SPECTRUM_SAMPLES = 4096

#: ``learning`` without the model inverse shapes a jump over at least this many periods of
#: ``learning_bandwidth_hz``: the quintic S-curve's content above Q is then below 5e-4 of the
#: jump (3 cycles: 1e-3; 1.2: 2e-2), the part the table cannot learn.
LEARNING_SHAPE_CYCLES = 3.6

#: A line's first harmonics carry its hysteresis distortion (odd harmonics, the 3rd and the
#: 5th foremost): Q keeps the first this many of a line even a little above
#: ``learning_bandwidth_hz`` (a fast line, whose 5th harmonic would otherwise be the first one
#: dropped, and which ``learning`` alone could not draw at all). A line slow enough to hold
#: them below the edge is unchanged.
MIN_LEARNED_HARMONICS = 5

#: How far above ``learning_bandwidth_hz`` Q reaches for those first harmonics: the 5th of a
#: line whose 4th lies on the edge. The learning check covers the harmonics kept.
BANDWIDTH_STRETCH = 1.25

#: Samples after a command the amplifier's range clipped whose errors are not learned: the
#: clip's own transient (the closed loop settles from a lost input within a few samples at the
#: resonance of the default stage) tells nothing about what the table could do.
CLIP_SETTLE_SAMPLES = 8

#: ``inverse`` alone holds the RAC's estimates from the start until the design model's slowest
#: mode has decayed to this fraction: the model inverse of a periodic reference starts on its
#: steady-state orbit while the stage rests, and the error of that start is the stage's own
#: initial-condition response, not a wrong estimate. Adapted on, it moved the estimates where
#: the dead zone kept them (a lasting error at the fundamental) or, on a line near the loop's
#: limits, started a drift the adaptation did not come back from.
START_HOLD_DECAY = 1e-3


def start_hold_samples(den: FloatArray) -> int:
    """
    Return the samples until the slowest mode of a sampled model decays to START_HOLD_DECAY.

    Parameters
    ----------
    den : ndarray
        Denominator of the model's z-transfer function (descending powers).

    Returns
    -------
    int
        Samples (0 for a model without stable dynamics to wait for).

    """
    radii = np.abs(np.roots(den)) if len(den) > 1 else np.zeros(0)
    slowest = float(np.max(radii)) if radii.size else 0.0
    if not 0.0 < slowest < 1.0:
        return 0
    return int(math.ceil(math.log(START_HOLD_DECAY) / math.log(slowest)))


@dataclass(frozen=True)
class FeedForwardParams(Params):
    """Feed-forward from the reference: model inverse and learning across periods."""

    mode: str = param('none', unit='-', description='none: feedback only (the paper); inverse: '
                      'inverse hysteresis and preview inversion of the design model; '
                      'learning: iterative learning across periods of a periodic reference; '
                      'inverse_learning: both.', choices=MODES, read_only=True)
    preview_samples: int = param(40, unit='samples', description='Length of the anti-causal '
                                 'part of the stable inverse (zeros of the sampled model '
                                 'outside the unit circle); the reference is read this many '
                                 'samples (plus the model delay) ahead.', low=1, high=1000)
    block_samples: int = param(256, unit='samples', description='Aperiodic references: the '
                               'feed-forward is computed this many samples at a time.', low=16,
                               high=100000)
    transition_s: float = param(1e-3, unit='s', description='Each ideal jump of the reference '
                                'is replaced by a quintic S-curve of this duration starting at '
                                'it, which the feedback follows and the learning learns (0: '
                                'jumps are passed on as they are); learning without the '
                                'inverse takes at least 3.6 / learning_bandwidth_hz (what Q '
                                'drops of the curve stays below 5e-4 of the jump).',
                                low=0.0, high=0.1)
    learning_gain: float = param(0.5, unit='-', description='Learning gain gamma: the share of '
                                 "a period's error removed at the next period on the design "
                                 'model.', low=0.0, low_open=True, high=1.0)
    learning_bandwidth_hz: float = param(1200.0, unit='Hz', description='Robustness filter Q: '
                                         'harmonics of the period above this frequency are '
                                         'not learned, except the first five harmonics of a fast '
                                         'line, up to '
                                         '1.25 times it (at 1200 the learning contracts every '
                                         'period on every member of the stage family: '
                                         'docs/explanation/robustness.md).',
                                         low=0.0, low_open=True)
    learning_start_periods: int = param(1, unit='periods', description='Whole periods run '
                                        'before the first update (the start transient is not '
                                        'periodic).', low=0, high=1000)
    learning_limit_v: float = param(3.0, unit='V', description='Bound on every entry of the '
                                    'learned table.', low=0.0, low_open=True)
    period_s: float = param(0.0, unit='s', description='Period learned over (0: the '
                            "trajectory's own period).", low=0.0)
    table_file: str = param('', unit='-', description='Learned table to start from (a file '
                            'written by save_table_file or simulate --save-table), loaded when '
                            'the controller is bound to the trajectory; refused unless its '
                            'period, sample time, reference and design match (empty: start '
                            'from zero).', read_only=True)
    save_table_file: str = param('', unit='-', description='controller_node: write the learned '
                                 'table to this file when the node shuts down, or the servo '
                                 'process at the end of its run when it ran the controller '
                                 '(empty: not written).', read_only=True)

    @property
    def inverse(self) -> bool:
        """Return whether the model inverse is on."""
        return self.mode in ('inverse', 'inverse_learning')

    @property
    def learning(self) -> bool:
        """Return whether learning is on."""
        return self.mode in ('learning', 'inverse_learning')


# --------------------------------------------------------------------------------------------
# Inverse hysteresis


class HysteresisInverse:
    """
    The inverse of a hysteresis model w = H(v), stepped with the commands actually applied.

    :meth:`invert` returns the input whose output, from the present state, is the target;
    :meth:`commit` advances the state with the input that was applied (clipped).

    Parameters
    ----------
    model : HysteresisModel
        The design model.
    tolerance_v : float
        Output tolerance of the solve [V].

    """

    def __init__(self, model: HysteresisModel, tolerance_v: float = 1e-10) -> None:
        self.model = model
        self.tolerance_v = tolerance_v
        self.slope = float(model.slope)
        self._state: Any = None
        self._w = 0.0
        self.iterations = 0
        self.reset(0.0)

    def reset(self, v0: float) -> None:
        """Start at rest at input ``v0`` [V] (the stage's own rest state)."""
        self._state = self.model.rest_state(float(v0))
        _, w = self.model.step(self._state, float(v0))
        self._v = float(v0)
        self._w = float(w)

    @property
    def output_v(self) -> float:
        """Return the model output w at the last committed input [V]."""
        return self._w

    def output_at(self, v: float) -> float:
        """Return the output w the model would give for input ``v`` now [V]."""
        return float(self.model.step(self._state, float(v))[1])

    def invert(self, w_target: float) -> float:
        """Return v with H(v) = ``w_target`` from the present state (safeguarded secant)."""
        w0 = self._w
        if w_target == w0:
            return self._v
        f = self.output_at
        slope = self.slope if self.slope > 0.0 else 1.0
        # bracket: the output is increasing in the input
        lo, hi = self._v, self._v + (w_target - w0) / slope
        f_lo, f_hi = w0 - w_target, f(hi) - w_target
        grow = (w_target - w0) / slope
        while f_hi * f_lo > 0.0:
            lo, f_lo = hi, f_hi
            grow *= 2.0
            hi = hi + grow
            f_hi = f(hi) - w_target
            if abs(grow) > 1e6:
                raise PiezoStageError(f'inverse hysteresis: no input gives w = {w_target:g} V')
        side = 0
        for _ in range(200):
            self.iterations += 1
            # regula falsi, Illinois variant: superlinear and never leaves the bracket
            x = hi - f_hi * (hi - lo) / (f_hi - f_lo)
            fx = f(x) - w_target
            if abs(fx) <= self.tolerance_v or x in (lo, hi):
                return x
            if fx * f_hi < 0.0:
                lo, f_lo = hi, f_hi
                if side == -1:
                    f_lo *= 0.5
                side = -1
            else:
                if side == 1:
                    f_lo *= 0.5
                side = 1
            hi, f_hi = x, fx
        return hi

    def commit(self, v: float) -> None:
        """Advance the model with the input that was applied [V]."""
        self._state, w = self.model.step(self._state, float(v))
        self._v = float(v)
        self._w = float(w)


class BacklashInverse(HysteresisInverse):
    """
    The exact inverse of dynamic backlash-like hysteresis, eq. (21).

    Across a jump dv from the state (v0, e0): w(dv) = c (v0 + dv) + e0 exp(-alpha |dv|) +
    sign(dv) (B1 - c)/alpha (1 - exp(-alpha |dv|)), increasing in dv (its slope is at least
    B1 - alpha rho > 0), smooth on each side of 0: the side is the sign of w_target - w0, and
    Newton's method on that branch converges to machine precision in a few steps.
    """

    def __init__(self, model: BacklashLike, tolerance_v: float = 1e-10) -> None:
        p = model.params
        self._alpha = p.alpha
        self._c = p.c
        self._shift = (p.b1 - p.c) / p.alpha
        self._e = 0.0
        # Across a jump of sign sgn from any state (|e0| <= rho = -shift), with y = |dv| and
        # a = sgn shift - e0, so that a sgn is in [2 shift, 0]: w(dv) - w0 = c dv + a (1 -
        # exp(-alpha y)) has the slope c + alpha a sgn exp(-alpha y), between
        # c + 2 alpha shift = 2 B1 - c and c, and is convex in y. Newton from the tangent at 0
        # comes down to the root monotonically, and after a step delta the output error is at
        # most bound delta^2, bound = c (c / s_min)^2 alpha^2 2 rho / (2 s_min) with
        # s_min = 2 B1 - c: the step that makes it smaller than the tolerance is the last one
        # (no evaluation only to confirm it). A model with B1 <= c / 2 gets plain Newton.
        s_min = 2.0 * p.b1 - p.c
        self._bound = (p.c * (p.c / s_min) ** 2 * p.alpha ** 2 * -self._shift / s_min
                       if s_min > 0.0 else math.inf)
        super().__init__(model, tolerance_v)

    def reset(self, v0: float) -> None:
        """Start at rest at ``v0`` with e = 0 (the stage's rest state)."""
        self._v = float(v0)
        self._e = 0.0
        self._w = self._c * self._v

    def output_at(self, v: float) -> float:
        """Return w for input ``v`` now [V]."""
        dv = v - self._v
        decay = math.exp(-self._alpha * abs(dv))
        return self._c * v + self._e * decay + self._shift * math.copysign(1.0 - decay, dv)

    def invert(self, w_target: float) -> float:
        """Return v with H(v) = ``w_target`` (Newton on the branch of the jump's sign)."""
        c, e0, v0 = self._c, self._e, self._v
        dw = w_target - (c * v0 + e0)
        if dw > 0.0:
            a = self._shift - e0
            a_s = a
        elif dw < 0.0:
            a = -self._shift - e0
            a_s = -a
        else:
            return v0
        alpha = self._alpha
        slope = c + alpha * a_s
        dv = dw / (slope if slope > 0.0 else c)
        exp = math.exp
        tol = self.tolerance_v
        bound = self._bound
        for _ in range(30):
            decay = exp(-alpha * abs(dv))
            g = c * dv + a * (1.0 - decay) - dw
            if -tol <= g <= tol:
                break
            step = g / (c + alpha * a_s * decay)
            dv -= step
            if bound * step * step <= tol:
                break
        return v0 + dv

    def jump_constants(self) -> tuple[float, float, float, float, float]:
        """
        Return the constants of the solve, as it uses them (batched loop).

        (alpha, c, (B1 - c)/alpha, tolerance, bound of the a-priori stop).
        """
        return self._alpha, self._c, self._shift, self.tolerance_v, self._bound

    def commit(self, v: float) -> None:
        """Advance the state across the jump to the applied input ``v`` [V]."""
        dv = v - self._v
        decay = math.exp(-self._alpha * abs(dv))
        self._e = self._e * decay + self._shift * math.copysign(1.0 - decay, dv)
        self._v = v
        self._w = self._c * v + self._e


class _Identity(HysteresisInverse):
    """No hysteresis: v = w."""

    def invert(self, w_target: float) -> float:
        return w_target

    def commit(self, v: float) -> None:
        self._v = self._w = v


def make_hysteresis_inverse(model: HysteresisModel) -> HysteresisInverse:
    """Return the inverse of ``model`` (exact for backlash-like, solved for the others)."""
    if isinstance(model, BacklashLike):
        return BacklashInverse(model)
    if isinstance(model, NoHysteresis):
        return _Identity(model)
    return HysteresisInverse(model)


# --------------------------------------------------------------------------------------------
# Stable inversion of the sampled linear model


def _zoh_tf(plant: LinearPlant, sample_time_s: float) -> tuple[FloatArray, FloatArray]:
    """Return (num, den) of the ZOH G(z) from w [V] to x [m], powers of z, highest first."""
    num, den = plant.discretize(sample_time_s).transfer_function()
    # the numerator is padded to the denominator's length: drop its leading (near) zeros
    scale = float(np.max(np.abs(num)))
    first = int(np.argmax(np.abs(num) > 1e-9 * scale))
    return num[first:], den


class PreviewInverse:
    """
    A stable inverse of the sampled model G(z) from w [V] to x [m], with preview.

    With G(z) = b0 prod(z - z_i) / A(z) of relative degree d, the input that makes x follow
    x_d is w = A(z) / (b0 prod(z - z_i)) x_d: a causal filter for the zeros inside the unit
    circle, an anti-causal one (a power series in z, truncated after ``preview`` terms) for
    those outside. w_k needs x_d up to k + :attr:`lead`.

    Parameters
    ----------
    plant : LinearPlant
        The design model.
    sample_time_s : float
        T [s].
    preview : int
        Terms of the anti-causal series.

    """

    def __init__(self, plant: LinearPlant, sample_time_s: float, preview: int = 40) -> None:
        from scipy.signal import lfilter_zi
        num, den = _zoh_tf(plant, sample_time_s)
        self.num, self.den = num, den
        self.sample_time_s = sample_time_s
        zeros = np.asarray(np.roots(num) if len(num) > 1 else np.zeros(0), dtype=np.complex128)
        inside: ComplexArray = zeros[np.abs(zeros) < 1.0]
        outside: ComplexArray = zeros[np.abs(zeros) >= 1.0]
        self.zeros_inside = inside
        self.zeros_outside = outside
        n = len(den) - 1
        m_in = len(inside)
        self.delay = n - len(zeros)
        # anti-causal series of 1/prod(q - z_o) in powers of the forward shift q
        p_asc = np.real(np.poly(outside))[::-1] if len(outside) else np.ones(1)
        series = np.zeros(preview if len(outside) else 1)
        series[0] = 1.0 / p_asc[0]
        for j in range(1, len(series)):
            acc = sum(p_asc[i] * series[j - i] for i in range(1, min(j, len(p_asc) - 1) + 1))
            series[j] = -acc / p_asc[0]
        self.truncation = float(abs(series[-1]) / max(abs(series[0]), 1e-300)) \
            if len(outside) else 0.0
        # one FIR on the reference ahead: taps h_j on x_{k - m_in + j}, j = 0 .. n + P - 1
        # (the denominator A(q) = sum a_i q^(n - i) applied first, then the series)
        a_fwd = den[::-1]  # a_fwd[j] multiplies x_{k + j}
        self.taps = np.convolve(series, a_fwd) / num[0]
        self.iir = np.real(np.poly(inside)) if m_in else np.ones(1)
        self._zi_unit = lfilter_zi(np.ones(1), self.iir) if m_in else np.zeros(0)
        self.back = m_in
        #: Samples of the reference ahead of k that w_k needs.
        self.lead = len(self.taps) - 1 - m_in
        self.dc_gain = float(np.sum(num) / np.sum(den))

    def frequency_response(self, z: ComplexArray) -> ComplexArray:
        """Return G(z) [m/V]."""
        return np.asarray(np.polyval(self.num, z) / np.polyval(self.den, z),
                          dtype=np.complex128)

    def start(self, x0: float) -> Any:
        """Return the filter state of a reference at rest at ``x0`` before the start."""
        fir_rest = float(np.sum(self.taps)) * x0
        return self._zi_unit * fir_rest

    def block(self, x: FloatArray, state: Any) -> tuple[FloatArray, Any]:
        """
        Return w for the samples x[back : len(x) - lead] and the new state.

        ``x`` holds the reference from ``back`` samples before the first output to ``lead``
        samples after the last one.
        """
        return self.causal(self.preview(x), state)

    def preview(self, x: FloatArray) -> FloatArray:
        """Return the first half of :meth:`block`: the FIR on the reference ahead."""
        return np.asarray(np.correlate(x, self.taps, mode='valid'), dtype=np.float64)

    def causal(self, fir: FloatArray, state: Any) -> tuple[FloatArray, Any]:
        """Return the second half of :meth:`block`: the zeros inside the unit circle; the state."""
        from scipy.signal import lfilter
        if self.back:
            out, state = lfilter(np.ones(1), self.iir, fir, zi=state)
            return np.asarray(out, dtype=np.float64), state
        return fir, state

    def periodic(self, x: FloatArray) -> FloatArray:
        """Return the exact periodic inverse of one period ``x`` (harmonic by harmonic)."""
        n = len(x)
        spectrum = np.fft.rfft(x)
        z = np.exp(2j * math.pi * np.arange(len(spectrum)) / n)
        g = self.frequency_response(z)
        tiny = 1e-9 * abs(self.dc_gain)
        w = np.where(np.abs(g) > tiny, spectrum / np.where(np.abs(g) > tiny, g, 1.0), 0.0)
        return np.asarray(np.fft.irfft(w, n), dtype=np.float64)


# --------------------------------------------------------------------------------------------
# Learning


def process_sensitivity(g: ComplexArray, z: ComplexArray, k_p: float, k_i: float,
                        sensor_gain_v_per_m: float, sample_time_s: float,
                        notch: tuple[Any, Any] | None = None) -> ComplexArray:
    """
    Return P_s(z) = G / (1 + N C k G): from a voltage added to the command to the position.

    Parameters
    ----------
    g : ndarray
        The plant seen from that voltage, c G(z) [m/V], at ``z``.
    z : ndarray
        Points on the unit circle.
    k_p, k_i : float
        Linearized controller C(z) = k_p + k_i T z/(z - 1) on the sensor-volt error (the
        controller's ``linear_gains()``).
    sensor_gain_v_per_m : float
        k [V/m].
    sample_time_s : float
        T [s].
    notch : tuple, optional
        ``(num, den)`` of the notch on the controller's output.

    """
    with np.errstate(divide='ignore', invalid='ignore'):
        c = k_p + (k_i * sample_time_s * z / (z - 1.0) if k_i else 0.0)
        if notch is not None:
            c = c * np.polyval(notch[0], z) / np.polyval(notch[1], z)
        loop = c * sensor_gain_v_per_m * g
        ps = g / (1.0 + loop)
    return np.asarray(np.where(np.isfinite(ps), ps, 0.0), dtype=np.complex128)


#: The shortest period learned [samples]: four samples draw its first harmonic.
MIN_PERIOD_SAMPLES = 4


def whole_period(period_s: float, sample_time_s: float) -> tuple[int, float]:
    """
    Return (n, P/T): n the samples of the period when it is a whole number of them, else 0.

    A whole period (to 1e-9 of it) keeps the table of samples; another one learns on the
    period's phase (:class:`PhaseLearning`).
    """
    if not period_s > 0.0:
        return 0, 0.0
    n = int(round(period_s / sample_time_s))
    whole = n >= 1 and abs(n * sample_time_s - period_s) <= 1e-9 * period_s
    return (n if whole else 0), (float(n) if whole else period_s / sample_time_s)


def check_learning_period(period_s: float, sample_time_s: float) -> None:
    """
    Refuse a period the learning cannot use, naming the value and the range allowed.

    Raises
    ------
    ParameterError
        ``feedforward.period_s``: no period (an aperiodic reference), or one shorter than
        :data:`MIN_PERIOD_SAMPLES` samples (its first harmonic not drawn below the Nyquist
        frequency with room for the learning).

    """
    shortest = MIN_PERIOD_SAMPLES * sample_time_s
    allowed = (f'a period of at least {MIN_PERIOD_SAMPLES} samples (>= {shortest:g} s, a '
               f'line rate <= {1.0 / shortest:g} Hz at T = {sample_time_s:g} s), a whole '
               'number of samples or not')
    if not period_s > 0.0:
        raise ParameterError('feedforward.period_s', period_s, allowed,
                             'learning needs a periodic reference')
    if period_s < shortest * (1.0 - 1e-9):
        raise ParameterError('feedforward.period_s', period_s, allowed,
                             f'is {period_s / sample_time_s:.4g} samples: too short to learn')


def period_harmonics(samples: float) -> ComplexArray:
    """
    Return z = exp(2 pi j h / n) of the harmonics h = 0 .. floor(n / 2) of a period of n samples.

    ``samples`` is P/T, a whole number or not (a harmonic at exactly n / 2 exists only for a
    whole, even n).
    """
    return np.asarray(np.exp(2j * math.pi * np.arange(int(samples // 2) + 1) / samples),
                      dtype=np.complex128)


def kept_harmonics(ps: ComplexArray, samples: float, sample_time_s: float,
                   bandwidth_hz: float) -> FloatArray:
    """
    Return Q on the harmonics of a period: 1 where the learning acts, 0 elsewhere.

    Parameters
    ----------
    ps : ndarray
        The design process sensitivity at the harmonics h = 0 .. n // 2 of a period
        (:func:`period_harmonics`).
    samples : float
        n = P/T, the samples of a period (a whole number or not).
    sample_time_s : float
        T [s].
    bandwidth_hz : float
        ``learning_bandwidth_hz``: Q keeps 0 < h / (n T) <= it, where P_s is not 0, and the
        harmonics h <= :data:`MIN_LEARNED_HARMONICS` up to :data:`BANDWIDTH_STRETCH` times it.

    """
    harmonic = np.arange(len(ps))
    freq = harmonic / (samples * sample_time_s)
    band = (freq <= bandwidth_hz) | ((harmonic <= MIN_LEARNED_HARMONICS)
                                     & (freq <= BANDWIDTH_STRETCH * bandwidth_hz))
    kept = (freq > 0.0) & band & (np.abs(ps) > 0.0)
    return kept.astype(np.float64)


def learning_convergence(design_ps: ComplexArray, true_ps: ComplexArray, gain: float,
                         kept: FloatArray) -> float:
    """
    Return the largest per-period contraction max |Q (1 - gamma P_true / P_design)|.

    Below 1, every learned harmonic converges monotonically on the true stage; the design
    model itself gives |1 - gamma|.
    """
    with np.errstate(divide='ignore', invalid='ignore'):
        ratio = np.abs(kept * (1.0 - gain * true_ps / design_ps))
    ratio = ratio[kept > 0.0]
    return float(np.max(ratio)) if ratio.size else 0.0


# --------------------------------------------------------------------------------------------
# Learning on the phase of a period of any length


def period_index(k: int, cycles_per_sample: float) -> int:
    """Return the period sample ``k`` falls in, floor(k T / P) (the one rounding used)."""
    return int(math.floor(k * cycles_per_sample))


def phase_windows(samples: float, count: int = 16) -> list[tuple[float, int]]:
    """
    Return the windows a period of ``samples`` samples can cut from the sample grid.

    A period starts between two samples: its first sample lies a fraction a in [0, 1) of a
    sample after the period's start, at the phase phi_0 = a / n, and it holds the m samples
    with phi_0 + i/n < 1. Returns ``count`` (phi_0, m) for a spread evenly over [0, 1): the
    learning check takes the worst of them.
    """
    r = 1.0 / samples
    out = []
    for j in range(count):
        phi0 = r * j / count
        m = int(math.ceil((1.0 - phi0) / r - 1e-9))
        out.append((phi0, m))
    return out


def boundary_weights(a: float) -> tuple[float, float, float, float]:
    """
    Return the trapezoid weights of the two samples around a period's boundary.

    The boundary lies a fraction 1 - a of a sample after the last sample of the period
    ending there and a before the first sample of the next one (a in [0, 1)). The integral
    over a period by the trapezoid rule, with the integrand interpolated linearly to the
    period's ends, weights its interior samples by 1 (in samples) and:
    (last sample: own period, next period; first sample: own period, previous period) =
    (1/2 + b - b^2/2, a^2/2, 1/2 + a - a^2/2, b^2/2) with b = 1 - a. A whole period (a = 0)
    gives (1, 0, 1/2, 1/2): the samples' plain sum when the error repeats.
    """
    b = 1.0 - a
    return 0.5 + b - 0.5 * b * b, 0.5 * a * a, 0.5 + a - 0.5 * a * a, 0.5 * b * b


def phase_learning_convergence(design_ps: ComplexArray, true_ps: ComplexArray, gain: float,
                               kept: FloatArray, samples: float) -> float:
    """
    Return the per-period contraction of learning on a period of any length.

    When the period is not a whole number of samples, one period holds m = floor or ceil of
    n = P/T samples at a phase that moves from period to period, and :class:`PhaseLearning`
    measures the error's harmonics by the trapezoid rule over the period, the samples just
    outside it interpolated to its ends (:func:`boundary_weights`): a quadrature that is
    exact only for whole periods. Harmonic h' then leaks into h by
    A_{h h'} = (1/n) sum_i w_i exp(2 pi j (h' - h) phi_i) (A_hh is not exactly 1), and its
    mirror -h' by B_{h h'} = (1/n) sum_i w_i exp(-2 pi j (h' + h) phi_i), the error being
    real. The table's harmonics c move over one period by c <- c - F (A (P c) + B conj(P c)),
    F = gamma Q / P_design, P the true process sensitivity. Returned: the largest gain
    (spectral norm, as a real map) of that map over the windows a period can cut
    (:func:`phase_windows`); above :data:`EXACT_HARMONICS` harmonics a bound of it,
    max_h |1 - F_h P_h| (the whole-period ratio) plus the Frobenius norms of F (A - I) P and
    F B P. Below 1, the table converges monotonically in the root-sum-square of its
    harmonics on that stage. A whole number of samples gives the whole-period ratio,
    max |1 - F_h P_h|, exactly (the table of samples is learned then).

    Parameters
    ----------
    design_ps, true_ps : ndarray
        P_s of the design model and of the stage at the harmonics h = 0 .. floor(n/2)
        (:func:`period_harmonics` of ``samples``).
    gain : float
        gamma.
    kept : ndarray
        Q at those harmonics (:func:`kept_harmonics`).
    samples : float
        n = P/T.

    """
    base = learning_convergence(design_ps, true_ps, gain, kept)
    idx = np.flatnonzero(kept > 0.0)
    if idx.size == 0 or float(samples).is_integer():
        return base
    h = idx.astype(np.float64)
    with np.errstate(divide='ignore', invalid='ignore'):
        f = gain / design_ps[idx]
    p = true_ps[idx]
    diff = h[None, :] - h[:, None]
    summ = h[None, :] + h[:, None]
    eye = np.eye(h.size)
    worst = 0.0
    for phi0, m in phase_windows(samples):
        a = _window_sum(diff, phi0, m, samples)
        b = _window_sum(-summ, phi0, m, samples)
        if h.size <= EXACT_HARMONICS:
            x = eye - f[:, None] * a * p[None, :]
            y = -f[:, None] * b * np.conj(p)[None, :]
            real = np.block([[x.real + y.real, -x.imag + y.imag],
                             [x.imag + y.imag, x.real - y.real]])
            worst = max(worst, float(np.linalg.norm(real, 2)))
        else:
            scale = np.abs(f)[:, None] * np.abs(p)[None, :]
            leak = (math.sqrt(float(np.sum((scale * np.abs(a - eye)) ** 2)))
                    + math.sqrt(float(np.sum((scale * np.abs(b)) ** 2))))
            worst = max(worst, base + leak)
    return worst


#: Up to this many harmonics :func:`phase_learning_convergence` takes the exact norm.
EXACT_HARMONICS = 128


def _window_sum(d: FloatArray, phi0: float, m: int, samples: float) -> ComplexArray:
    """
    Return (1/n) sum_i w_i exp(2 pi j d phi_i) over a period's window, for every entry d.

    phi_i = phi0 + i/n, i = -1 .. m, with the trapezoid weights of :func:`boundary_weights`
    (1 inside; the sum over i = 0 .. m - 1 in closed form, then the ends corrected).
    """
    theta = 2.0 * math.pi * d / samples
    with np.errstate(divide='ignore', invalid='ignore'):
        geometric = np.where(np.isclose(np.sin(theta / 2.0), 0.0, atol=1e-12),
                             float(m) + 0j, (1.0 - np.exp(1j * theta * m))
                             / (1.0 - np.exp(1j * theta)))
    a = phi0 * samples  # the first sample, after the period's start [samples]
    _, prev_cross, first_own, _ = boundary_weights(a)
    last_own, _, _, next_cross = boundary_weights(a + m - samples)  # at the period's end
    total = (geometric + (first_own - 1.0)
             + (last_own - 1.0) * np.exp(1j * theta * (m - 1))
             + prev_cross * np.exp(-1j * theta) + next_cross * np.exp(1j * theta * m))
    return np.asarray(np.exp(2j * math.pi * d * phi0) * total / samples, dtype=np.complex128)


def clipped_excess(lost: Any, table: Any) -> Any:
    """
    Return the part of the table's entry the amplifier's range clipped off [V].

    ``lost`` is the linear input asked minus the one applied (through the inverse hysteresis,
    when there is one); the part is at most the entry itself, and of its sign: the table is
    not blamed for what the feedback asked beyond the range. Scalars or arrays.
    """
    up = np.where(table > 0.0, np.minimum(lost, table), 0.0)
    down = np.where(table < 0.0, np.maximum(lost, table), 0.0)
    return np.where(lost > 0.0, up, np.where(lost < 0.0, down, 0.0))


def _member_products(a: FloatArray, b: FloatArray) -> FloatArray:
    """
    Return a @ b one member (column of b) at a time.

    The same matrix-vector product for one member alone as for each of M: a product of all M
    at once may take another kernel and round otherwise.
    """
    out = np.empty((a.shape[0], b.shape[1]))
    for j in range(b.shape[1]):
        out[:, j] = a @ np.ascontiguousarray(b[:, j])
    return out


def _row_sum(x: FloatArray) -> FloatArray:
    """
    Return the sum over the first axis, row after row in their order, whatever the shape.

    (``sum(axis=0)`` may pair the rows differently when the other axes hold one element: one
    member would not compute what each of M members computes.)
    """
    return np.asarray(np.cumsum(x, axis=0)[-1], dtype=np.float64)


class PhaseLearning:
    r"""
    A learned table that belongs to the phase of a period of any length, for M members.

    The table is a band-limited periodic function of the phase phi in [0, 1) of the period
    P, held as its harmonics: L(phi) = sum_h alpha_h cos(2 pi h phi) + beta_h sin(2 pi h phi)
    over the harmonics h that Q keeps (no DC, :func:`kept_harmonics`, below the Nyquist
    frequency). Why harmonics and not a table of samples: when P/T is not a
    whole number the samples fall at other phases every period, so a table of samples would
    need an interpolation in playback and its transpose in the update, which low-pass and
    alias what is learned; the learning filter gamma Q / P_s acts on harmonics of the period
    anyway, so on harmonics it is exact, Q holds by construction (the table never holds a
    component Q drops, however it was limited) and playback at any phase is exact.

    Sample k lies in period floor(k T / P) at phase frac(k T / P). The error's harmonics over
    a period, E_h = (1/P) int e(t) exp(-2 pi j h t / P) dt, are summed as the samples come by
    the trapezoid rule with the samples just outside the period interpolated to its ends
    (:func:`boundary_weights`), and the table takes c_h <- c_h - gamma E_h / P_s(exp(2 pi j
    h T / P)) once the first sample after the period is in (one sample after it ends). The
    quadrature leaks a little between harmonics when the period is not whole:
    :func:`phase_learning_convergence` takes it into the convergence ratio.

    The work is spread over runs of up to :data:`LEARN_CHUNK` samples inside one period (a
    period's first sample is a run of its own): at the start of a run its playback is
    computed (the phasors of its first sample times those of the run's constant steps) and
    the errors of the run before are summed into the update; a period's update costs O(H).
    Every sum runs over a leading axis with the members last (row after row, no BLAS), so
    that one member computes what each of M members computes.

    Parameters
    ----------
    filter_gains : ndarray
        gamma / P_s at the kept harmonics (complex, shape (H,)).
    harmonics : ndarray
        The kept harmonics h (shape (H,), whole numbers >= 1).
    samples : float
        n = P/T, the samples of one period (> 2 h for every h kept).
    members : int
        M, the tables learned side by side.
    limit_v : float
        Bound on the table's amplitude: the sum over h of sqrt(alpha_h^2 + beta_h^2), which
        bounds |L| everywhere, is kept at or below it by scaling the table down (it stays
        in Q's band, with no DC).
    start_periods : int
        Whole periods before the first error is learned.

    """

    def __init__(self, filter_gains: ComplexArray, harmonics: FloatArray, samples: float,
                 members: int, limit_v: float, start_periods: int) -> None:
        self.samples = float(samples)
        self.r = 1.0 / self.samples
        self._starts: dict[int, int] = {}
        self.harmonics = np.asarray(harmonics, dtype=np.float64)
        if self.harmonics.size and 2.0 * float(np.max(self.harmonics)) >= self.samples:
            raise ParameterError('learned harmonics', float(np.max(self.harmonics)),
                                 f'below {self.samples / 2:g} (the Nyquist frequency)',
                                 'cannot be drawn at this sample rate')
        g = 2.0 * self.r * np.asarray(filter_gains, dtype=np.complex128)
        self._g_re = g.real[:, None]
        self._g_im = g.imag[:, None]
        self.members = int(members)
        self.limit_v = float(limit_v)
        self.start_periods = int(start_periods)
        h = self.harmonics
        steps = 2.0 * math.pi * np.multiply.outer(h, np.arange(LEARN_CHUNK) * self.r)
        # cos and sin of the run's constant steps i T / P, rows h: (2H, chunk), and its
        # transpose for the playback
        self._steps = np.concatenate([np.cos(steps), np.sin(steps)])
        self._steps_t = np.ascontiguousarray(self._steps.T)
        size = h.size
        #: The harmonics of every member's table: alpha_h rows, then beta_h rows (2H, M).
        self.coefficients = np.zeros((2 * size, self.members))
        #: A constant added to the table, never learned: the mean of a table loaded.
        self.offset = np.zeros(self.members)
        self._sums: dict[int, FloatArray] = {}
        self._errors = np.zeros((LEARN_CHUNK, self.members))
        self._error_column = self._errors[:, 0]
        #: Kept instead of the error after a clip, times the table [m/V] (the wrapper's).
        self.leak = 0.0
        # what the amplifier's range clipped off the table (:meth:`record_excess`): its
        # harmonics are taken out of the table at the period's end
        self._excess = np.zeros((LEARN_CHUNK, self.members))
        self._excess_sums: dict[int, FloatArray] = {}
        self._excess_run = False
        # cos and sin of the present run's first phase, (H, 1) each
        self._c0 = np.ones((size, 1))
        self._s0 = np.zeros((size, 1))
        self._play = np.zeros((LEARN_CHUNK, self.members))
        self._play_one: list[float] = []
        self._run_start = 0
        self._run_end = 0  # no run yet
        self._run_period = 0
        self._run_length = 0
        self._recorded = 0
        self._stale = True
        #: The first sample whose error is learned.
        self.learn_from = self.period_start(self.start_periods)
        self.periods_learned = 0
        #: Updates after which a member's table was scaled to stay within ``limit_v``.
        self.limited = 0

    def period_start(self, period: int) -> int:
        """Return the first sample of period ``period`` (the first k with k T / P >= it)."""
        cached = self._starts.get(period)
        if cached is not None:
            return cached
        if len(self._starts) > 8:
            self._starts.clear()
        k = max(int(math.ceil(period * self.samples)) - 1, 0)
        while period_index(k, self.r) < period:
            k += 1
        while k > 0 and period_index(k - 1, self.r) >= period:
            k -= 1
        self._starts[period] = k
        return k

    def reset(self) -> None:
        """Restart at sample 0: the table stays, the errors of unfinished periods go."""
        self._recorded = 0
        self._errors.fill(0.0)
        self._excess.fill(0.0)
        self._excess_run = False
        self._sums.clear()
        self._excess_sums.clear()
        self._run_end = self._run_start = 0
        self._stale = True

    def play(self, k: int) -> FloatArray:
        """
        Return every member's table at sample ``k`` [V], shape (M,) (a row of a buffer).

        Called once per sample, in sample order (a gap is allowed: skipped samples add no
        error); a new run starts here when ``k`` leaves the present one, and a finished
        period's update is applied there.
        """
        if self._stale or not self._run_start <= k < self._run_end:
            self._start_run(k)
        row: FloatArray = self._play[k - self._run_start]
        return row

    def learn_one(self, k: int, error: float, masked: bool) -> float:
        """
        Return the first member's table at sample ``k`` [V] and keep the sample's error [m].

        :meth:`play` and :meth:`record` of one member, as floats (the real-time step); the
        error is not kept before :attr:`learn_from`, and ``masked`` keeps
        :attr:`leak` times the table instead (an error a clip made).
        """
        if self._stale or not self._run_start <= k < self._run_end:
            self._start_run(k)
            self._play_one = self._play[:, 0].tolist()
        i = k - self._run_start
        value = self._play_one[i]
        if k >= self.learn_from:
            self._error_column[i] = self.leak * value if masked else error
            if i >= self._recorded:
                self._recorded = i + 1
        return value

    def record(self, k: int, error: Any) -> None:
        """Keep the error of sample ``k`` [m] (after :meth:`play` of the same sample)."""
        if k >= self.learn_from:
            i = k - self._run_start
            self._errors[i] = error
            if i >= self._recorded:
                self._recorded = i + 1

    def record_excess(self, k: int, excess: Any) -> None:
        """
        Keep what the range clipped off the table at sample ``k`` [V] (after :meth:`play`).

        The table then takes, at the period's end, the input that was applied: the excess's
        harmonics in Q's band (the same quadrature as the errors) are subtracted, so the
        table does not wind up against a limit and Q holds after the clip.
        """
        i = k - self._run_start
        self._excess[i] += excess
        self._excess_run = True
        if i >= self._recorded:
            self._recorded = i + 1

    def values(self, first: int, count: int) -> FloatArray:
        """Return the present table at samples first .. first + count - 1, shape (count, M)."""
        return self._evaluate(np.arange(first, first + count, dtype=np.float64) * self.r % 1.0)

    def on_grid(self, points: int) -> FloatArray:
        """Return the table at phases i / ``points``, i = 0 .. points - 1, shape (points, M)."""
        return self._evaluate(np.arange(points) / points)

    def _evaluate(self, phases: FloatArray) -> FloatArray:
        ang = 2.0 * math.pi * np.multiply.outer(self.harmonics, phases)
        phasors = np.concatenate([np.cos(ang), np.sin(ang)])
        return _row_sum(phasors[:, :, None] * self.coefficients[:, None, :]) + self.offset

    def load_grid(self, table: FloatArray) -> None:
        """
        Start every member from a table given at phases i / N, keeping Q's harmonics.

        The grid's DFT gives the harmonics; those Q drops are left out. Its mean becomes
        :attr:`offset` (a saved table holds what the RAC's estimates had added, a constant
        among it; the learning itself adds no DC), within the ``limit_v``.
        """
        table = np.asarray(table, dtype=np.float64).reshape(-1)
        points = table.size
        spectrum = np.fft.rfft(table) / points
        size = self.harmonics.size
        coef = np.zeros(2 * size)
        for j, h in enumerate(self.harmonics.astype(int)):
            if h < points / 2:
                coef[j] = 2.0 * spectrum[h].real
                coef[size + j] = -2.0 * spectrum[h].imag
        self.coefficients[:] = coef[:, None]
        self.offset[:] = min(max(float(spectrum[0].real), -self.limit_v), self.limit_v)
        self._limit()
        self._stale = True

    def _start_run(self, k: int) -> None:
        """Sum the last run's errors, apply the finished periods' updates, then play from k."""
        self._flush()
        period = period_index(k, self.r)
        first = self.period_start(period)
        for q in sorted(self._sums):
            # period q is finished once the first sample of q + 1 has passed
            if q < period - 1 or (q == period - 1 and k > first):
                sums = self._sums.pop(q)
                excess = self._excess_sums.pop(q, None)
                if q >= self.start_periods:
                    self._apply(sums, excess)
        end = k + 1 if k == first else min(k + LEARN_CHUNK, self.period_start(period + 1))
        ang = 2.0 * math.pi * (k * self.r - period) * self.harmonics
        self._c0 = c0 = np.cos(ang)[:, None]
        self._s0 = s0 = np.sin(ang)[:, None]
        size = self.harmonics.size
        # the table from the run's first phase a: alpha cos(a + b) + beta sin(a + b) is
        # (alpha cos a + beta sin a) cos b + (beta cos a - alpha sin a) sin b, b the steps
        alpha = self.coefficients[:size]
        beta = self.coefficients[size:]
        turned = np.concatenate([c0 * alpha + s0 * beta, c0 * beta - s0 * alpha])
        self._play = _member_products(self._steps_t, turned)
        self._play += self.offset
        self._run_start = k
        self._run_end = end
        self._run_period = period
        self._run_length = end - k
        self._stale = False

    def _sum_of(self, period: int, sums: dict[int, FloatArray] | None = None) -> FloatArray:
        table = self._sums if sums is None else sums
        out = table.get(period)
        if out is None:
            out = table[period] = np.zeros((2 * self.harmonics.size, self.members))
        return out

    def _flush(self) -> None:
        """Add the errors kept in the present run to its period's sums (and its neighbours')."""
        m = self._recorded
        if not m:
            return
        self._recorded = 0
        self._flush_rows(self._errors[:m], self._sums)
        if self._excess_run:
            self._flush_rows(self._excess[:m], self._excess_sums)
            self._excess_run = False

    def _flush_rows(self, rows: FloatArray, sums: dict[int, FloatArray]) -> None:
        """Add the trapezoid sums of ``rows`` (samples of the present run) to ``sums``."""
        m = len(rows)
        period = self._run_period
        k0 = self._run_start
        weighted = rows.copy()
        if k0 == self.period_start(period):
            # the period's first sample: its own weight and its share of the period before
            a = k0 - period * self.samples
            _, _, own, back = boundary_weights(a)
            weighted[0] *= own
            self._sum_of(period - 1, sums)[:] += self._phasor(0) * (rows[0] * back)
        last = k0 + m - 1
        if m == self._run_length and last + 1 == self.period_start(period + 1):
            # the period's last sample: its own weight and its share of the period after
            own, ahead, _, _ = boundary_weights(last + 1 - (period + 1) * self.samples)
            weighted[m - 1] *= own
            self._sum_of(period + 1, sums)[:] += self._phasor(m - 1) * (rows[m - 1] * ahead)
        # sums over the run at its steps b, then turned to its first phase a:
        # sum w cos(a + b) = cos a sum w cos b - sin a sum w sin b, and the sin likewise
        size = self.harmonics.size
        at_steps = _member_products(self._steps[:, :m], weighted)
        c0, s0 = self._c0, self._s0
        self._sum_of(period, sums)[:] += np.concatenate([
            c0 * at_steps[:size] - s0 * at_steps[size:],
            s0 * at_steps[:size] + c0 * at_steps[size:]])
        rows.fill(0.0)

    def _phasor(self, i: int) -> FloatArray:
        """Return cos and sin of every harmonic at sample i of the present run, (2H, 1)."""
        size = self.harmonics.size
        cos_b = self._steps[:size, i:i + 1]
        sin_b = self._steps[size:, i:i + 1]
        c0, s0 = self._c0, self._s0
        return np.concatenate([c0 * cos_b - s0 * sin_b, s0 * cos_b + c0 * sin_b])

    def _apply(self, sums: FloatArray, excess: FloatArray | None = None) -> None:
        """
        Apply a period's update, c_h <- c_h - gamma E_h / P_s, on the cos and sin rows.

        With what the range clipped off the table (``excess``'s sums), its harmonics first:
        the table takes the input applied, projected on Q's band.
        """
        size = self.harmonics.size
        coef = self.coefficients
        if excess is not None:
            coef -= (2.0 * self.r) * excess
        cos_sum = sums[:size]
        sin_sum = sums[size:]
        coef[:size] -= self._g_re * cos_sum + self._g_im * sin_sum
        coef[size:] -= self._g_re * sin_sum - self._g_im * cos_sum
        self._limit()
        self.periods_learned += 1
        self._stale = True

    def amplitude_bound(self) -> FloatArray:
        """Return sum_h sqrt(alpha_h^2 + beta_h^2) per member [V]: |L| stays below it."""
        size = self.harmonics.size
        if not size:
            return np.zeros(self.members)
        return _row_sum(np.hypot(self.coefficients[:size], self.coefficients[size:]))

    def _limit(self) -> None:
        """Scale a member's table down to the amplitude bound (in band, no DC)."""
        bound = self.amplitude_bound()
        over = bound > self.limit_v
        if np.any(over):
            scale = np.where(over, self.limit_v / np.where(over, bound, 1.0), 1.0)
            self.coefficients *= scale[None, :]
            self.limited += 1


# --------------------------------------------------------------------------------------------
# The learned table in a file

#: Format name of a learned-table file, and its version (:func:`write_learned_table`).
TABLE_FORMAT = 'piezo_stage_ros.learned_table'
TABLE_VERSION = 1
#: Key of a run's learned table (:meth:`LearnedTable.fields`) in its description (a bag's meta).
TABLE_META_KEY = 'learned_table'


@dataclass(frozen=True)
class LearnedTable:
    """
    One period of a learning feed-forward's table and what it was learned for.

    Attributes
    ----------
    table_v : ndarray
        L[i], i = 0 .. n - 1: the learned input added at sample i of each period [V] (the
        linear input v_lin, before the inverse hysteresis).
    reference_m : ndarray
        x_d at the same n samples (the trajectory's second period) [m]: a table belongs to
        one reference.
    sample_time_s : float
        T [s].
    period_s : float
        n T [s].
    mode : str
        The feed-forward mode it was learned in (``learning`` or ``inverse_learning``: the
        table of ``learning`` also holds what the model inverse would add).
    design : str
        What the learning and the feed-forward were designed on, one ``name=value`` item per
        part, separated by ``'; '``: the ZOH model G(z), the hysteresis, the controller's
        linear gains at its initial estimates, the sensor gain, the notch, the mode.
    periods_learned : int
        Updates the table had received.
    period_rms_m : float
        The rms error of the last period the controller measured when it was saved [m] (NaN
        when none).

    """

    table_v: FloatArray
    reference_m: FloatArray
    sample_time_s: float
    period_s: float
    mode: str
    design: str
    periods_learned: int = 0
    period_rms_m: float = math.nan

    @property
    def samples(self) -> int:
        """Return n, the samples of one period."""
        return int(self.table_v.size)

    @property
    def design_hash(self) -> str:
        """Return the first 16 hex digits of the SHA-256 of :attr:`design`."""
        return hashlib.sha256(self.design.encode()).hexdigest()[:16]

    def fields(self) -> dict[str, Any]:
        """Return the fields of the file format, version :data:`TABLE_VERSION` (JSON-ready)."""
        return {'format': TABLE_FORMAT, 'version': TABLE_VERSION,
                'table_v': [float(v) for v in self.table_v],
                'reference_m': [float(v) for v in self.reference_m],
                'sample_time_s': float(self.sample_time_s), 'period_s': float(self.period_s),
                'mode': self.mode, 'design': self.design, 'design_hash': self.design_hash,
                'periods_learned': int(self.periods_learned),
                'period_rms_m': float(self.period_rms_m)}

    @classmethod
    def from_fields(cls, fields: Mapping[str, Any], where: str) -> LearnedTable:
        """
        Return the table of :meth:`fields` (or the arrays of a file), checked.

        Parameters
        ----------
        fields : Mapping
            Field name to value (lists or NumPy arrays and scalars).
        where : str
            What the fields come from, for the error message.

        Raises
        ------
        PiezoStageError
            Not a learned table, another version, a missing field or inconsistent fields.

        """
        if str(fields.get('format', '')) != TABLE_FORMAT:
            raise PiezoStageError(f'{where}: not a learned table (format '
                                  f'{str(fields.get("format", "missing"))!r}, expected '
                                  f'{TABLE_FORMAT!r})')
        version = int(fields.get('version', -1))
        if version != TABLE_VERSION:
            raise PiezoStageError(f'{where}: version {version}; this program reads version '
                                  f'{TABLE_VERSION}')
        try:
            table = cls(table_v=np.asarray(fields['table_v'], dtype=np.float64).reshape(-1),
                        reference_m=np.asarray(fields['reference_m'],
                                               dtype=np.float64).reshape(-1),
                        sample_time_s=float(fields['sample_time_s']),
                        period_s=float(fields['period_s']), mode=str(fields['mode']),
                        design=str(fields['design']),
                        periods_learned=int(fields['periods_learned']),
                        period_rms_m=float(fields['period_rms_m']))
        except KeyError as err:
            raise PiezoStageError(f'{where}: field {err} is missing') from None
        if (table.reference_m.size != table.samples or table.samples == 0
                or not np.all(np.isfinite(table.table_v))):
            raise PiezoStageError(f'{where}: {table.samples} table entries (finite, at least '
                                  f'one) and {table.reference_m.size} reference samples do '
                                  'not agree')
        return table


def write_learned_table(path: str | Path, table: LearnedTable) -> Path:
    """
    Write a learned table as a NumPy ``.npz`` archive, replacing ``path`` at once.

    Version 1 holds the arrays ``format`` (:data:`TABLE_FORMAT`), ``version`` (1),
    ``table_v``, ``reference_m``, ``sample_time_s``, ``period_s``, ``mode``, ``design``,
    ``design_hash``, ``periods_learned``, ``period_rms_m`` (fields of :class:`LearnedTable`),
    no pickled objects: ``numpy.load(path)`` reads it anywhere.

    Parameters
    ----------
    path : path-like
        File to write (the name is kept as given; ``.npz`` is the customary suffix).
    table : LearnedTable
        What to write.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    PiezoStageError
        If the file cannot be written.

    """
    path = Path(path)
    tmp = path.with_name(path.name + '.tmp')
    try:
        with open(tmp, 'wb') as f:
            arrays: dict[str, Any] = {key: np.asarray(value)
                                      for key, value in table.fields().items()}
            np.savez(f, **arrays)
        os.replace(tmp, path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise PiezoStageError(f'learned table {path}: cannot write it: {err}') from None
    return path


def read_learned_table(path: str | Path) -> LearnedTable:
    """
    Read a file of :func:`write_learned_table`.

    Parameters
    ----------
    path : path-like
        The file.

    Returns
    -------
    LearnedTable

    Raises
    ------
    PiezoStageError
        If it cannot be read, is not a learned table, has another version or inconsistent
        fields.

    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            fields = {key: data[key] for key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise PiezoStageError(f'learned table {path}: cannot read it: {err}') from None
    return LearnedTable.from_fields(fields, f'learned table {path}')


# --------------------------------------------------------------------------------------------
# Jumps


def shape_jumps(x: FloatArray, v: FloatArray, sample_time_s: float, transition_s: float,
                tolerance_m: float = 1e-9) -> tuple[FloatArray, FloatArray, int]:
    """
    Replace each ideal jump of a sampled reference by a quintic S-curve starting at it.

    A jump is a step x_{k+1} - x_k that its velocity does not explain. The trapezoid
    T (v_k + v_{k+1}) / 2 leaves T^3 / 12 times the third derivative on a smooth path, that is
    T d2 / 12 with d2 the velocity's second difference around the step (the larger of its
    two), and at most T |v_{k+1} - v_k| / 2 at a corner of the velocity (a triangle's turn),
    where that difference is as large as d2; a step off by more than twice
    T (min(|v_{k+1} - v_k|, d2) / 2 + d2 / 12) plus ``tolerance_m`` is a jump. The test
    scales with the sample time and the reference's own motion: a fast smooth reference (a
    sine of a fifth of the sample rate) is never taken for jumps, a jump of a reference at
    rest is found down to ``tolerance_m``, one riding on a moving reference above the
    motion's own allowance. Returns the shaped position and velocity and the number of
    jumps; the reference is unchanged outside [t_jump, t_jump + transition_s] of each jump.
    """
    x = np.asarray(x, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if transition_s <= 0.0 or len(x) < 2:
        return x, v, 0
    explained = 0.5 * sample_time_s * (v[1:] + v[:-1])
    jump = np.diff(x) - explained
    dv = np.abs(np.diff(v))
    turn = dv.copy()  # two samples: no second difference, a corner's bound
    if len(v) >= 3:
        second = np.abs(np.diff(v, 2))
        turn[:-1] = second
        turn[1:] = np.maximum(turn[1:], second)
    smooth = 2.0 * sample_time_s * (0.5 * np.minimum(dv, turn) + turn / 12.0)
    where = np.flatnonzero(np.abs(jump) > tolerance_m + smooth)
    if where.size == 0:
        return x, v, 0
    xs, vs = x.copy(), v.copy()
    idx = np.arange(len(x), dtype=np.float64)
    width = transition_s / sample_time_s
    for j in where:
        size = jump[j]
        start = j + 0.5  # halfway between the two samples the ideal jump falls between
        q, dq = s_curve((idx - start) / width)
        step = (idx > start).astype(np.float64)
        xs += size * (q - step)
        vs += size * dq / transition_s
    return xs, vs, int(where.size)


# --------------------------------------------------------------------------------------------
# The wrapper


def learning_columns(kernel2: FloatArray) -> FloatArray:
    """
    Return the windows of the learning kernel over two periods, row s = kernel2[s : s + n].

    Row n - i is column i of the circulant learning operator (a view, nothing copied).
    """
    n = len(kernel2) // 2
    return np.asarray(np.lib.stride_tricks.sliding_window_view(kernel2, n), dtype=np.float64)


def _values_of(trajectory: Trajectory) -> Any:
    """
    Return what ``trajectory``'s values stand on now, to tell whether they changed since.

    None for a trajectory whose values never change; for a view of a reference that changes
    (a goal follower's: it offers ``snapshot()``), the spline it shows now (each change is a
    new one); a new object each call (never the same) for a view that names none.
    """
    snapshot = getattr(trajectory, 'snapshot', None)
    if snapshot is None:
        return None
    return getattr(snapshot(), 'spline', object())


class _Block:
    """
    An aperiodic reference's block of tables, computed in :data:`STAGES` stages.

    The stages (:meth:`FeedForwardController._block_stage`) are the steps of the whole
    computation, in its order, on the same arrays: run one a sample over the samples before
    the block is needed, they give the tables it gives at once.
    """

    #: Evaluate the reference, shape its jumps, the model inverse's FIR, its causal filter
    #: (the filter goes on), make the lists.
    STAGES = 5

    def __init__(self, k: int) -> None:
        self.k = k
        self.stage = 0
        #: What the reference's values stood on when it was evaluated (:func:`_values_of`).
        self.values: Any = None
        #: Taken as they are: the first use found the reference as it was evaluated.
        self.confirmed = False
        self.raw_x: FloatArray = np.zeros(0)
        self.raw_v: FloatArray = np.zeros(0)
        self.xs: FloatArray = np.zeros(0)
        self.vs: FloatArray = np.zeros(0)
        self.fir: FloatArray = np.zeros(0)
        #: The filter state before the block and after it (once ``filtered``).
        self.state_before: Any = None
        self.state: Any = None
        self.filtered = False
        self.tables: tuple[FloatArray, FloatArray, FloatArray, FloatArray] = (
            np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
        self.lists: tuple[list[float], list[float], list[float], list[float]] = ([], [], [],
                                                                                 [])

    @property
    def done(self) -> bool:
        """Return whether every stage has run."""
        return self.stage >= self.STAGES


class FeedForwardController:
    """
    Feed-forward (model inverse, learning) around a feedback controller; see the module doc.

    Parameters
    ----------
    inner : Controller
        The feedback controller (RAC, PI, notched or not) as :func:`build_controller` builds it.
    params : FeedForwardParams
        Mode and settings.
    plant : LinearPlant
        Design model of the linear part (w [V] to x [m]).
    hysteresis : HysteresisModel
        Design model of the hysteresis.
    sensor_gain_v_per_m : float
        k of the controller [V/m].
    output_min_v, output_max_v : float
        Amplifier input range [V].

    """

    #: The tables of :meth:`predict` as arrays, and the lists they were made from.
    _ahead_cache: tuple[tuple[Any, ...], tuple[FloatArray, FloatArray, FloatArray]] | None = None

    def __init__(self, inner: Any, params: FeedForwardParams, plant: LinearPlant,
                 hysteresis: HysteresisModel, *, sensor_gain_v_per_m: float,
                 output_min_v: float, output_max_v: float) -> None:
        if params.mode == 'none':
            raise ParameterError('feedforward.mode', 'none', str(MODES[1:]),
                                 'builds no feed-forward wrapper')
        self.inner = inner
        self.params = params
        self._t = float(inner.sample_time_s)
        self._ksens = float(sensor_gain_v_per_m)
        self._vmin = float(output_min_v)
        self._vmax = float(output_max_v)
        self._inverse_on = params.inverse
        self._learning_on = params.learning
        #: The S-curve's duration a jump is shaped over [s] (module doc, Jumps).
        self.transition_s = params.transition_s
        if self._learning_on and not self._inverse_on and params.transition_s > 0.0:
            self.transition_s = max(params.transition_s,
                                    LEARNING_SHAPE_CYCLES / params.learning_bandwidth_hz)
        self.plant_inverse = PreviewInverse(plant, self._t, params.preview_samples)
        #: Samples from the start that ``inverse`` alone holds the estimates over.
        self.start_hold = start_hold_samples(self.plant_inverse.den) \
            if self._inverse_on and not self._learning_on else 0
        self._start_holding = False
        # the plant seen from v_lin: c G with the compensator (inverse modes), about c G
        # (hysteresis slope) without
        self.slope = float(hysteresis.slope) if not isinstance(hysteresis, NoHysteresis) \
            else 1.0
        self.hysteresis_inverse: HysteresisInverse | None = \
            make_hysteresis_inverse(hysteresis) if self._inverse_on else None
        self._hysteresis_model = hysteresis
        #: What the table was designed on (:meth:`design_summary` at :meth:`bind`).
        self.design = ''
        #: The file the table started from ('' when it started from zero).
        self.table_source = ''
        # the table and sample at the last feedforward_v (the entry a period's last sample used)
        self._seen_table: list[float] = []
        self._seen_k = -1
        self._theta0 = self._phi0 = 0.0
        self._set_share()
        notch = getattr(inner, 'notch', None)
        self._notch_coeffs = None if notch is None else (notch.num, notch.den)
        self._share_notch: Any = None
        if notch is not None:
            self._share_notch = type(notch)(notch.num, notch.den)
        self._share_fresh = True
        # samples a stalled loop missed before the next step, and the share's last input
        # (missed: the share's notch is bridged over them as the inner notch is)
        self._share_gap = 0
        self._share_last = 0.0
        self._drift_gap = 0
        self._drift_last = 0.0
        # inverse modes: what the held estimates add over the initial ones, k (d_theta x_d +
        # d_phi x_d'), is taken off through its own copy of the notch (see _hold)
        self._drift_gains = (0.0, 0.0)
        self._drift_notch: Any = None
        if notch is not None:
            self._drift_notch = type(notch)(notch.num, notch.den)
        self._drift_fresh = True
        self._trajectory: Trajectory | None = None
        # the segments of a trajectory still to come: (start [s], trajectory), and when the
        # next one starts [samples from the present segment's start]
        self._segments: list[tuple[float, Trajectory]] = []
        self._segment_start_k = 0
        self._switch_in = 0
        self.mismatches = 0
        self.periods_learned = 0
        self.last_period_rms_m = math.nan
        self._period_n = 0
        #: The period learned over [s] (0 when the mode does not learn or nothing is bound).
        self.period_s = 0.0
        # a period that is not a whole number of samples: the table on its phase
        self._phase: PhaseLearning | None = None
        self._next_period_k = 0
        self._sync_k = 0
        self._sq_count = 0
        self._last_learned = 0.0
        # the amplifier's range: the last sample it clipped, the linear input asked then, and
        # what it clipped off the table's entries this period (projected out at its end)
        self._clip_k = -(1 << 62)
        self._asked = 0.0
        #: Commands the amplifier's range clipped since the controller was bound.
        self.clipped_samples = 0
        #: Learning updates the table's bound ``learning_limit_v`` scaled down.
        self.limited_updates = 0
        self._excess_table: FloatArray = np.zeros(0)
        self._excess_any = False
        self._kept: Any = None
        self._leak = 0.0
        self._learned: FloatArray = np.zeros(0)
        self._ll: list[float] = []
        # learning, spread over the period: the errors of each run of LEARN_CHUNK samples go
        # through their columns of the circulant learning operator (one correlation with a
        # slice of _kernel2) into _delta; the period's end applies it
        self._kernel2: FloatArray = np.zeros(0)
        self._columns: FloatArray = np.zeros((0, 0))
        self._delta: FloatArray = np.zeros(0)
        self._errors: list[float] = []
        # a long period (LEARN_SPREAD_SAMPLES): the runs whose correlation is still being
        # added, a slice of columns a sample; each [errors, first row, last row + 1, next column]
        self._backlog: list[list[Any]] = []
        self._slice = 0
        # a longer period (LEARN_SPECTRUM_SAMPLES): the period's error spectrum on the kept
        # harmonics, the phasor of the next sample and which sample it is for, the turn a sample
        self._spectral = False
        #: Periods of at least this many samples learn on the kept harmonics (None: never;
        #: see ``LEARN_SPECTRUM_SAMPLES``). Taken at :meth:`bind`.
        self.spectrum_samples: int | None = None
        self._harmonics: IntArray = np.zeros(0, dtype=np.int64)
        self._spectrum: ComplexArray = np.zeros(0, dtype=np.complex128)
        self._phasor: ComplexArray = np.zeros(0, dtype=np.complex128)
        self._phasor_i = -1
        self._turn: ComplexArray = np.zeros(0, dtype=np.complex128)
        self._learning_gains: ComplexArray = np.zeros(0, dtype=np.complex128)
        self._pending = 0
        self._sq = 0.0
        self._holding = False
        self._lx_raw: list[float] = []
        self._lx: list[float] = []
        self._lv: list[float] = []
        self._lw: list[float] = []
        self._block_start = 0
        self._filter_state: Any = None
        # the next block, computed a stage a step after the present one is installed (a
        # sample pays for a stage, never for a whole block), read ahead by predict
        self._block_ahead: _Block | None = None
        # the first block of a reference to come, computed ahead (prepare_block)
        self._first_block: _Block | None = None
        self._k = 0
        self._matched = False
        self._u = 0.0
        # what prepare computed of a trajectory ahead: (trajectory, table points, samples a
        # period, the model command of the seed)
        self._prepared: tuple[Trajectory, int, float, FloatArray] | None = None

    # -- the Controller interface --------------------------------------------------------

    @property
    def sample_time_s(self) -> float:
        """Return the sample period [s]."""
        return self._t

    def bind(self, trajectory: Trajectory) -> None:
        """
        Take the reference ahead from ``trajectory`` (t = 0 at the first step after reset).

        A new trajectory starts the learned table afresh. A trajectory of segments (a line
        rate changed during the run, :class:`~piezo_stage_ros.core.loop.switched.
        LineRateChange`) is bound one segment at a time, each at the sample it starts
        (:meth:`switch`).
        """
        segments = getattr(trajectory, 'segments', None)
        for start_s, _ in (segments or ())[1:]:
            k = round(start_s / self._t)
            if abs(k * self._t - start_s) > 1e-9 * self._t:
                raise ParameterError('line_rate_change.at_s', start_s,
                                     f'a whole number of samples (T = {self._t:g} s)',
                                     'would start the new line between two samples')
        self._segments = list(segments[1:]) if segments else []
        self._segment_start_k = 0
        self._switch_in = self._sample_at(self._segments[0][0]) if self._segments else 0
        self._bind_one(segments[0][1] if segments else trajectory, load_file=True)

    def _sample_at(self, time_s: float) -> int:
        """Return the first sample k with k T >= ``time_s`` (the loop's own rounding)."""
        k = max(int(math.ceil(time_s / self._t)) - 1, 0)
        while k * self._t < time_s:
            k += 1
        return k

    def switch(self, trajectory: Trajectory) -> None:
        """
        Bind a new trajectory from the next step on, at its t = 0, without a reset.

        A new line rate: the feedback, the inverse hysteresis and the estimates go on (those of
        ``inverse`` alone held over the new start, as over a run's); the model inverse of the
        new reference acts from its first sample and the learned table starts afresh for the
        new period (a table file is not loaded again: it belongs to the first trajectory).
        Nothing is refused that :meth:`bind` of the first one accepted, except a period the
        learning cannot use (its error names the range).
        """
        self._segments = []
        self._bind_one(trajectory, load_file=False)
        self._k = 0
        self._seen_k = -1
        # With the model inverse, held estimates stay held and their term stays taken off: the
        # new line starts from the model inverse, and estimates released here would re-adapt
        # under that term and be held again with the two offsets added, walking a little
        # further towards the box's bounds at every change of line rate. Without it (learning
        # alone, the seed above carries the RAC's present term) they adapt again from there.
        if not (self._holding and self._inverse_on):
            self._hold(False)
        # the new line's start moves the stage as a run's start does: ``inverse`` alone holds
        # its estimates over it again, or its transient leaves them off for every line after
        self._arm_start_hold()
        if self._learning_on and not self._inverse_on:
            self._seed_from_model()

    def prepare(self, trajectory: Trajectory) -> None:
        """
        Compute ahead what :meth:`switch` to ``trajectory`` needs of it alone (thread-safe).

        ``learning`` alone seeds its table at a switch from the model inverse's command for the
        new line (:meth:`_seed_from_model`), whose inverse hysteresis runs over up to 20 periods:
        too long for a sample's step on a slow line. Called when the change is requested (in
        the requesting thread), that command is ready at the switch, which then only adds the
        terms of the loop's state at that sample: the table is the one the switch alone would
        compute. Nothing for the other modes; a trajectory the switch would refuse is left to
        the switch.
        """
        if not self._learning_on or self._inverse_on:
            return
        dry = copy.copy(self)  # binding assigns what it sets: self is left as it is
        try:
            dry._bind_one(trajectory, load_file=False)
        except ParameterError:
            return
        points, samples, x, _, z = dry._seed_grid()
        self._prepared = (trajectory, points, samples, dry._model_command(x, z, points))

    def _seed_grid(self) -> tuple[int, float, FloatArray, FloatArray, ComplexArray]:
        """Return the table's points, samples a period, x_d, x_d' and z of its harmonics."""
        points = self.table_points()
        samples = self._phase.samples if self._phase is not None else float(points)
        x, v = self._grid_reference() if self._phase is not None else \
            (np.asarray(self._lx, dtype=np.float64), np.asarray(self._lv, dtype=np.float64))
        if self._phase is not None:
            x, v = self._shape_periodic(x, v)
        z = np.exp(2j * math.pi * np.arange(points // 2 + 1) / samples)
        return points, samples, x, v, z

    def _model_command(self, x: FloatArray, z: ComplexArray, points: int) -> FloatArray:
        """Return H^-1(G^-1 x_d) over the period: the model inverse's command for ``x``."""
        g = self.plant_inverse.frequency_response(z)
        w = np.fft.irfft(np.fft.rfft(x) / g, points)
        return self._periodic_hysteresis_inverse(w)

    def _seed_from_model(self) -> None:
        """
        Start ``learning`` (no model inverse) from the model inverse's command for the reference.

        What the table converges to on the design model is the command that makes the stage
        follow the reference, H^-1(G^-1 x_d) (the stable inverse of the linear part, then the
        inverse hysteresis, run over the period until its orbit repeats), less what the RAC
        adds at tracking with its estimates where they now stand, k (theta_hat x_d +
        phi_hat x_d') through the notch. Q's harmonics of that (no DC: the feedback holds it)
        are the table a new line rate starts from, so that its first line has the model
        inverse's hysteresis compensation in the band the table can hold.
        """
        points, samples, x, v, z = self._seed_grid()
        kept = np.zeros(z.size, dtype=bool)
        if self._phase is not None:
            kept[self._phase.harmonics.astype(int)] = True
        else:
            kept[:len(self._kept)] = self._kept
        prepared, self._prepared = self._prepared, None
        if prepared is not None and prepared[0] is self._trajectory \
                and prepared[1:3] == (points, samples):
            command = prepared[3]
        else:
            command = self._model_command(x, z, points)
        share = self._ksens * (self._theta0 * np.fft.rfft(x) + self._phi0 * np.fft.rfft(v))
        if self._notch_coeffs is not None:
            num, den = self._notch_coeffs
            share = share * np.polyval(num, z) / np.polyval(den, z)
        share = share + np.fft.rfft(self._estimate_drift())
        seed = np.where(kept, np.fft.rfft(command) - share, 0.0)
        table = np.fft.irfft(seed, points)
        peak = float(np.max(np.abs(table)))
        limit = self.params.learning_limit_v
        if peak > limit:
            table *= limit / peak
        self.load_table(table)

    def _periodic_hysteresis_inverse(self, w: FloatArray) -> FloatArray:
        """
        Return the inputs v of the design hysteresis's periodic orbit through outputs ``w``.

        The hysteresis is rate-independent, so one period on the table's phase grid stands
        for the period; it is run from rest at the first point until an orbit repeats to
        1e-9 of the command's span (at most 20 periods), and the last is returned.
        """
        inverse = make_hysteresis_inverse(self._hysteresis_model)
        slope = inverse.slope if inverse.slope > 0.0 else 1.0
        inverse.reset(float(w[0]) / slope)
        out = np.zeros(len(w))
        last = np.full(len(w), np.inf)
        for _ in range(20):
            for i, target in enumerate(w):
                out[i] = inverse.invert(float(target))
                inverse.commit(float(out[i]))
            span = float(np.ptp(out)) if len(out) else 0.0
            if np.max(np.abs(out - last)) <= 1e-9 * max(span, 1e-12):
                break
            last = out.copy()
        return out

    def _next_segment(self, k: int) -> int:
        """Bind the next segment of the trajectory at sample ``k``; return k in it."""
        start_s, trajectory = self._segments.pop(0)
        start_k = self._sample_at(start_s)
        local = k - (start_k - self._segment_start_k)
        rest = self._segments
        self.switch(trajectory)
        self._segments = rest
        self._segment_start_k = start_k
        self._switch_in = self._sample_at(rest[0][0]) - start_k if rest else 0
        return local

    def _bind_one(self, trajectory: Trajectory, *, load_file: bool) -> None:
        """Bind one trajectory: its tables, a fresh table, the table file when asked."""
        self._trajectory = trajectory
        period = self.params.period_s or getattr(trajectory, 'period_s', None) or 0.0
        n, samples = whole_period(period, self._t)
        if 0.0 < period <= 2.0 * self._t:
            raise ParameterError('feedforward.period_s' if self.params.period_s else
                                 'trajectory period', period,
                                 f'> {2.0 * self._t:g} s (a line rate below the Nyquist '
                                 f'frequency, {0.5 / self._t:g} Hz)',
                                 f'is {period / self._t:.3g} samples: the sample rate cannot '
                                 'draw it')
        if self._learning_on:
            check_learning_period(period, self._t)
        exact = n >= 4
        self._period_n = n if exact else 0
        self._phase = None
        self.period_s = period if self._learning_on else 0.0
        self._learned = np.zeros(self._period_n)
        self._ll = self._learned.tolist()
        self._excess_table = np.zeros(self._period_n)
        self._excess_any = False
        self._clip_k = -(1 << 62)
        self.clipped_samples = 0
        self.limited_updates = 0
        self._delta = np.zeros(self._period_n)
        self._errors = [0.0] * self._period_n
        self._backlog = []
        self._slice = -(-self._period_n // LEARN_CHUNK) \
            if self._period_n >= LEARN_SPREAD_SAMPLES else 0
        self._pending = 0
        self._sq = 0.0
        if self._learning_on:
            self._set_leak(n if exact else samples)
        if self._learning_on and exact:
            # designed here, on the controller's initial estimates: nothing of it in the loop
            filt = self._learning_filter(n)
            self._kept = filt != 0.0
            kernel = np.fft.irfft(filt, n)
            self._kernel2 = np.concatenate([kernel, kernel])
            self._columns = learning_columns(self._kernel2)
            long = self.spectrum_samples
            self._spectral = long is not None and n >= long
            if self._spectral:
                self._slice = 0
                self._harmonics = np.flatnonzero(self._kept).astype(np.int64)
                self._learning_gains = filt[self._harmonics]
                self._spectrum = np.zeros(self._harmonics.size, dtype=np.complex128)
                self._turn = np.exp(-2j * math.pi * self._harmonics / n)
                self._phasor_i = -1
        elif self._learning_on:
            # a period of any length: the table on the period's harmonics (PhaseLearning)
            self._phase = self.phase_learning(samples, 1)
        self.periods_learned = 0
        self._prepare_tables()
        self.design = self.design_summary()
        self.table_source = ''
        if self.params.table_file and load_file:
            if not self._learning_on:
                raise ParameterError('feedforward.table_file', self.params.table_file,
                                     "'' unless feedforward.mode learns",
                                     f'names a table, but mode {self.params.mode!r} learns none')
            self.load_table_file(self.params.table_file)

    def reset(self, position_m: float, reference_m: float,
              output_v: float | None = None) -> None:
        """Reset the inner controller and restart the feed-forward at sample 0."""
        self.inner.reset(position_m, reference_m, output_v)
        self._u = self.inner.output_v
        self._rewind()
        # a table from a file was saved relative to the initial estimates (:meth:`learned`):
        # they are held from the first sample
        self._hold(bool(self.table_source))
        self._arm_start_hold()
        if self.hysteresis_inverse is not None:
            # the stage rests with w = c v: the compensator starts where the stage does
            hyst = self.hysteresis_inverse
            hyst.reset(position_m / (self.plant_inverse.dc_gain * hyst.slope)
                       if hyst.slope > 0 else 0.0)
        if self._trajectory is not None and self._period_n == 0:
            self._prepare_tables()

    def restart(self) -> None:
        """
        Play the bound trajectory again from its t = 0 at the next step, without a reset.

        A start after a stop of the same line: the feedback, the inverse hysteresis, the
        estimates (held or not) and the learned table go on; the table's phase is taken from
        the new t = 0, the errors of the unfinished period are kept as :meth:`reset` keeps
        them, and ``inverse`` alone holds its estimates over the start again.
        """
        self._segments = []
        self._rewind()
        self._arm_start_hold()
        if self._trajectory is not None and self._period_n == 0:
            self._prepare_tables()

    def _rewind(self) -> None:
        """Set the reference index back to sample 0; the table stays."""
        if self._learning_on and self._period_n:
            self._accumulate(self._k % self._period_n)  # the errors so far stay in the update
            self._pending = 0
        if self._phase is not None:
            self._phase.reset()
            self._next_period_k = 0
            self._sq = 0.0
            self._sq_count = 0
        self._k = 0
        self._seen_k = -1
        self._share_fresh = True

    def _arm_start_hold(self) -> None:
        """Hold the estimates of ``inverse`` alone over the next ``start_hold`` samples."""
        self._start_holding = self.start_hold > 0
        if self._start_holding:
            self._hold_inner(True)

    def step(self, position_m: float, reference_m: float, reference_velocity_mps: float,
             dt_s: float | None = None) -> float:
        """
        Return the command [V]: feedback plus feed-forward, through the inverse hysteresis.

        Each call is the next sample of the bound reference; a caller that let samples pass
        without a step (a stalled real-time loop) says so with :meth:`skip`. ``dt_s`` goes to
        the feedback controller.
        """
        k = self._k
        if self._segments and k >= self._switch_in:
            k = self._next_segment(k)
        self._k = k + 1
        if self._start_holding and k >= self.start_hold:
            self._start_holding = False
            self._hold_inner(False)
        if self._trajectory is None:
            return self._plain(position_m, reference_m, reference_velocity_mps, dt_s)
        n = self._period_n
        i = k % n if n else k - self._block_start
        if not n:
            if i >= len(self._lx):
                self._next_block(k)
                i = k - self._block_start
            elif self._block_ahead is not None and not self._block_ahead.done:
                self._block_stage(self._block_ahead)
        xd = self._lx_raw[i]
        if abs(reference_m - xd) > 1e-12 + 1e-9 * abs(xd):
            # not the reference bound (a periodic trajectory's first period that is not yet
            # periodic, or a trajectory changed elsewhere): feedback alone for this sample
            self.mismatches += 1
            self._matched = False
            return self._plain(position_m, reference_m, reference_velocity_mps, dt_s)
        self._matched = True
        x_ref = self._lx[i]
        v_ref = self._lv[i]
        inner = self.inner
        u = inner.step(position_m, x_ref, v_ref, dt_s)
        if self._inverse_on:
            share = (self._theta0 * x_ref + self._phi0 * v_ref) * self._ksens
            notch = self._share_notch
            if notch is not None:
                if self._share_fresh:
                    notch.reset(share)
                    self._share_fresh = False
                elif self._share_gap:
                    # bridged as the inner notch bridges the same missed samples (missed)
                    notch.bridge(self._share_last, share, self._share_gap)
                self._share_gap = 0
                self._share_last = share
                share = notch.step(share)
            u = u - share + self._lw[i]
            if self._drift_gains != (0.0, 0.0):
                u = u - self._drift(x_ref, v_ref)
        if self._learning_on:
            if not n:
                return self._phase_step(k, u, position_m - x_ref)
            table = self._ll[i]
            u += table
            e = position_m - x_ref  # the shaped path, the one the feedback follows
            self._sq += e * e
            if k >= self._learn_from:
                if not self._holding:
                    self._hold(True)
                # no error learned from a clipped command's samples
                self._errors[i] = e if k - self._clip_k > CLIP_SETTLE_SAMPLES \
                    else self._leak * table
                if self._spectral:
                    self._add_spectrum(i)
                elif i % LEARN_CHUNK == LEARN_CHUNK - 1 or i == n - 1:
                    self._accumulate(i + 1)
            if self._backlog:
                self._work(self._backlog)
            if i == n - 1:
                self._learn(k)
            v = self._output(u)
            if self._clip_k == k:
                self._fold_excess(i, table)
            return v
        return self._output(u)

    def _phase_step(self, k: int, u: float, e: float) -> float:
        """Return the command of sample ``k`` with the table of a period of any length."""
        phase = self._phase
        assert phase is not None
        value = phase.learn_one(k, e, k - self._clip_k <= CLIP_SETTLE_SAMPLES)
        if k >= self._next_period_k:
            self._end_phase_period(k)
        elif k == self._sync_k:  # a period's update is applied one sample after its end
            self.periods_learned = phase.periods_learned
        self._sq += e * e
        self._sq_count += 1
        if not self._holding and k >= phase.learn_from:
            self._hold(True)
        self._last_learned = value
        v = self._output(u + value)
        if self._clip_k == k:
            phase.record_excess(k, self._excess(value))
        return v

    def _excess(self, table: float) -> float:
        """Return the part of the table's entry the amplifier's range clipped off [V]."""
        hyst = self.hysteresis_inverse
        applied = hyst.output_v / self.slope if hyst is not None else self._u
        return float(clipped_excess(np.float64(self._asked - applied), np.float64(table)))

    def limit_terms(self) -> tuple[float, Any]:
        """
        Return what the learning does at the range's limits, for the batched loop.

        (the leak of an entry whose error is not learned [m/V], Q on the period's harmonics
        of a whole period).
        """
        return self._leak, self._kept

    def _fold_excess(self, i: int, table: float) -> None:
        """Keep what the range clipped off entry ``i`` (the table is projected at the end)."""
        fold = self._excess(table)
        if fold != 0.0:
            self._excess_table[i] += fold
            self._excess_any = True

    def _end_phase_period(self, k: int) -> None:
        """Close a period of any length that ended before sample ``k``: its rms, its updates."""
        phase = self._phase
        assert phase is not None
        if self._sq_count:
            self.last_period_rms_m = math.sqrt(self._sq / self._sq_count)
        self._sq = 0.0
        self._sq_count = 0
        self.periods_learned = phase.periods_learned
        self.limited_updates = phase.limited
        self._sync_k = k + 1
        self._next_period_k = phase.period_start(period_index(k, phase.r) + 1)

    def _output(self, u: float) -> float:
        """Return the command for the linear input ``u``: inverse hysteresis, then the range."""
        hyst = self.hysteresis_inverse
        self._asked = u
        if hyst is not None:
            u = hyst.invert(self.slope * u)
        v = self._vmax if u > self._vmax else (self._vmin if u < self._vmin else u)
        if v != u:
            self._clip_k = self._k - 1
            self.clipped_samples += 1
        if hyst is not None:
            hyst.commit(v)
        self._u = v
        return v

    def skip(self, samples: int) -> None:
        """Advance the reference index over ``samples`` samples the caller did not step."""
        if samples > 0:
            n = self._period_n
            if self._learning_on and n:
                # the errors so far go in now: the skipped samples have none
                self._accumulate(self._k % n)
            self._k += int(samples)
            if n:
                self._pending = self._k % n

    def missed(self, samples: int) -> None:
        """
        Let ``samples`` missed samples pass in the inner controller (its ``missed``).

        The inner notch bridges them at the next step (the command's input in equal steps);
        the notches of what the model inverse takes off the command (the share of the RAC's
        model part, the held estimates' drift) are bridged alike, or the difference of the
        filters, fed a jump on one side and a ramp on the other, rings into the command (a
        kick of several nanometres after one missed sample of a moving reference).
        """
        missed = getattr(self.inner, 'missed', None)
        if missed is not None:
            missed(samples)
        if samples > 0:
            self._share_gap = self._drift_gap = int(samples)

    def predict(self, count: int) -> FloatArray:
        """
        Return the commands predicted for the ``count`` samples after the last step [V].

        Commands ahead (:mod:`piezo_stage_ros.core.control.ahead`): the last command plus the
        change the tables explain, read ahead from them (no step is run): the inner
        controller's model-based part (``reference_gains()``, less the share the inverse
        replaces) on the shaped reference, the model inverse and the learned table; the
        feedback part held, the inverse hysteresis taken with its secant from the present
        state to the largest change ahead (one solve, not one a sample). A periodic reference
        wraps around its period; an aperiodic one (and one whose period is not a whole number
        of samples) is read on into the next block (computed a stage a step before, as it
        stands when first read). Held throughout when the last step was feedback alone (no
        reference bound, or not the one bound).
        """
        v = self._u
        k = self._k - 1
        if self._trajectory is None or not self._matched or k < 0 or count <= 0:
            return np.full(max(count, 0), v)
        x, xv, wl = self._ahead_tables(count)
        n = self._period_n
        i = k % n if n else k - self._block_start
        if not n and i + 1 + count > len(x):
            # an aperiodic reference's block ends within the count: the next one, ahead
            _, nx, nv, nw = self._peek_block()
            x = np.concatenate([x, nx])
            xv = np.concatenate([xv, nv])
            wl = np.concatenate([wl, nw if self._inverse_on else np.zeros(len(nw))])
        stop = min(i + 1 + count, len(x))
        a, b = self._ahead_gains()
        ahead: FloatArray = x[i + 1:stop] - x[i]
        ahead *= a
        ahead += b * (xv[i + 1:stop] - xv[i])
        ahead += wl[i + 1:stop] - wl[i]
        if self._phase is not None and len(ahead):
            ahead += self._phase.values(k + 1, len(ahead))[:, 0] - self._last_learned
        hyst = self.hysteresis_inverse
        if hyst is not None and len(ahead):
            # through the inverse hysteresis: its secant from here to the largest change ahead
            # (on a branch about 1; up to c/B1 after a reversal of a backlash)
            j = int(np.argmax(np.abs(ahead)))
            du = float(ahead[j])
            if du != 0.0:
                ahead *= self.ahead_secant(du)
        ahead += v
        np.minimum(ahead, self._vmax, out=ahead)
        np.maximum(ahead, self._vmin, out=ahead)
        if len(ahead) < count:
            # more than a block ahead: the last prediction is held
            ahead = np.concatenate([ahead, np.full(count - len(ahead),
                                                   ahead[-1] if len(ahead) else v)])
        return ahead

    def _ahead_gains(self) -> tuple[float, float]:
        """Return (a [V/m], b [V s/m]): the inner controller's reference gains less the share."""
        a, b = getattr(self.inner, 'reference_gains', lambda: (0.0, 0.0))()
        if self._inverse_on:
            a -= self._theta0 * self._ksens
            b -= self._phi0 * self._ksens
        return a, b

    def ahead_secant(self, du: float) -> float:
        """
        Return the inverse hysteresis' secant from the last command to a change ``du`` ahead.

        The factor :meth:`predict` scales its linear changes by (1 without a compensator or
        for no change).
        """
        hyst = self.hysteresis_inverse
        if hyst is None or du == 0.0:
            return 1.0
        return (hyst.invert(hyst.output_v + self.slope * du) - self._u) / du

    def ahead_plan(self, count: int) -> tuple[tuple[FloatArray, FloatArray, FloatArray], int,
                                              float, float, float] | None:
        """
        Return what :meth:`predict` reads from a whole period's tables, for a batch of axes.

        ((x_d, x_d', model inverse + learned), each repeated so that ``count`` samples after
        the index are one slice, the same tuple until a table is replaced; the index of the
        last step; a; b; the last command [V]), or None
        when :meth:`predict` goes another way (held, aperiodic, a period of any length).
        :class:`~piezo_stage_ros.core.control.ahead.AxesAhead` does the rest of
        :meth:`predict` on the axes together, the same operations on each value.
        """
        k = self._k - 1
        n = self._period_n
        if not n or self._phase is not None or self._trajectory is None or \
                not self._matched or k < 0 or count <= 0:
            return None
        a, b = self._ahead_gains()
        return self._ahead_tables(count), k % n, a, b, self._u

    def _ahead_tables(self, count: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """
        Return the tables as arrays for :meth:`predict`: x_d, x_d', model inverse + learned.

        Built again only when a table is replaced (a new block, a period learned); a periodic
        table is repeated so that ``count`` samples after any index are one slice.
        """
        sources = (self._lx, self._lv, self._lw, self._ll, count)
        cache = self._ahead_cache
        if cache is not None:
            held = cache[0]
            if held[0] is sources[0] and held[1] is sources[1] and held[2] is sources[2] and \
                    held[3] is sources[3] and held[4] >= count:
                return cache[1]
        n = self._period_n
        reps = 2 + count // n if n else 1
        if cache is not None and cache[0][0] is sources[0] and cache[0][1] is sources[1] and \
                len(cache[1][0]) == reps * len(self._lx):
            # a period learned: only the learned table changed (the reference's are kept)
            x, xv = cache[1][0], cache[1][1]
        else:
            x = np.array(self._lx)
            xv = np.array(self._lv)
            if n:
                x, xv = np.tile(x, reps), np.tile(xv, reps)
        wl = np.array(self._lw) if self._inverse_on else np.zeros(len(self._lx))
        if self._learning_on and len(self._ll) == len(wl):
            wl = wl + np.array(self._ll)
        if n:
            wl = np.tile(wl, reps)
        tables = (x, xv, wl)
        self._ahead_cache = (sources, tables)
        return tables

    def _set_share(self) -> None:
        """Take the RAC's initial estimates as the share the model inverse replaces (PI: 0)."""
        params = getattr(self.inner, 'inner', self.inner).params
        self._theta0 = getattr(params, 'theta_init', 0.0)
        self._phi0 = getattr(params, 'phi_init', 0.0)

    def _plain(self, position_m: float, reference_m: float, reference_velocity_mps: float,
               dt_s: float | None) -> float:
        """Feedback alone (still through the hysteresis compensator: no jump of the command)."""
        self._share_fresh = True
        return self._output(float(self.inner.step(position_m, reference_m,
                                                  reference_velocity_mps, dt_s)))

    # -- tables ----------------------------------------------------------------------------

    def _evaluate(self, first: int, count: int) -> tuple[FloatArray, FloatArray]:
        """Return x_d, x_d' at samples first .. first + count - 1 (held at t = 0 before it)."""
        assert self._trajectory is not None
        idx = np.arange(first, first + count, dtype=np.float64)
        t = np.maximum(idx, 0.0) * self._t
        x, v = self._trajectory.evaluate(t)
        x = np.asarray(x, dtype=np.float64).copy()
        v = np.asarray(v, dtype=np.float64).copy()
        v[idx < 0.0] = 0.0
        return x, v

    def _shape(self, x: FloatArray, v: FloatArray) -> tuple[FloatArray, FloatArray]:
        if not (self._inverse_on or self._learning_on):
            return x, v
        xs, vs, _ = shape_jumps(x, v, self._t, self.transition_s)
        return xs, vs

    def _prepare_tables(self) -> None:
        self._share_fresh = True
        n = self._period_n
        if n:
            # one period taken from the second: a trajectory may start with a first period
            # that is not yet periodic (a square wave's first transition); those samples are
            # told apart by the reference check in step
            x, v = self._evaluate(n, n)
            xs, vs = self._shape_periodic(x, v)
            w = self.plant_inverse.periodic(xs) / self.slope if self._inverse_on \
                else np.zeros(n)
            self._set_tables(x, xs, vs, w)
            return
        self._block_start = 0
        self._filter_state = None
        self._block_ahead = None
        self._lx = []

    def _next_block(self, k: int) -> None:
        """Install the feed-forward of samples k .. k + block - 1 (aperiodic references)."""
        work = self._block_ahead
        self._block_ahead = None
        first = self._first_block
        if work is not None and work.k == k and self._current(work):
            self._finish_block(work)
        elif work is None and self._filter_state is None and first is not None and \
                first.k == k and first.values is not None and self._current(first):
            # the first block after a bind, computed ahead on the values shown now
            self._first_block = None
            self._filter_state = first.state
            work = first
        else:
            if work is not None:
                self._drop_block(work)  # the block read ahead was not used
            work = self._compute_block(k)
        self._x_lists(work.lists)
        self._block_start = k
        # the next one, a stage a step from the next step on
        self._block_ahead = _Block(k + len(self._lx))

    def prepare_block(self, trajectory: Trajectory, k: int) -> None:
        """
        Compute ahead the first block of a reference a bind will show, from sample ``k`` on.

        For a view of a reference that changes (a goal follower's): when a goal is checked,
        before the sample it starts at, its reference is known (``trajectory``, whose
        ``spline`` is what the view will show). Called in the checking thread: the block is
        computed on a copy (this controller is not touched but for keeping it) and the first
        block after the next bind takes it if that bind starts at ``k`` and its view shows
        that spline; otherwise it is computed then, as without.
        """
        values = getattr(trajectory, 'spline', None)
        if values is None or not self._inverse_on or self._learning_on:
            return  # nothing to identify it by; learning does not take such a reference
        dry = copy.copy(self)  # computing assigns what it sets: self is left as it is
        dry._trajectory = trajectory
        dry._filter_state = None
        work = dry._compute_block(k)
        work.values = values
        self._first_block = work

    def _peek_block(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Return the next block's tables ahead of time (:meth:`predict` at a block's end)."""
        k = self._block_start + len(self._lx)
        work = self._block_ahead
        if work is None or work.k != k or not self._current(work):
            if work is not None:
                self._drop_block(work)
            work = self._compute_block(k)
            self._block_ahead = work
        else:
            self._finish_block(work)
        # the tables as of this first use: later uses take them as they are
        work.confirmed = True
        return work.tables

    def _current(self, work: _Block) -> bool:
        """Return whether ``work`` is what computing it now gives (its reference unchanged)."""
        if work.confirmed or work.stage == 0 or work.values is None:
            return True
        assert self._trajectory is not None
        return work.values is _values_of(self._trajectory)

    def _drop_block(self, work: _Block) -> None:
        """Forget a block computed ahead: the filter goes on from where it was before it."""
        if work.filtered:
            self._filter_state = work.state_before

    def _finish_block(self, work: _Block) -> None:
        """Run the stages of ``work`` still to run."""
        while not work.done:
            self._block_stage(work)

    def _compute_block(self, k: int) -> _Block:
        """Return x_d, shaped x_d, x_d', w of samples k .. k + block - 1 (the filter goes on)."""
        work = _Block(k)
        self._finish_block(work)
        return work

    def _block_stage(self, work: _Block) -> None:
        """Run the next stage of ``work`` (:class:`_Block`); the filter goes on at the fourth."""
        inv = self.plant_inverse
        size = self.params.block_samples
        half = int(math.ceil(self.transition_s / self._t)) + 2
        stage = work.stage
        if stage == 0:
            assert self._trajectory is not None
            work.values = _values_of(self._trajectory)
            work.raw_x, work.raw_v = self._evaluate(work.k - inv.back - half,
                                                    size + inv.back + inv.lead + 2 * half)
        elif stage == 1:
            work.xs, work.vs = self._shape(work.raw_x, work.raw_v)
        elif stage == 2:
            if self._inverse_on:
                work.fir = inv.preview(work.xs[half:len(work.xs) - half])
        elif stage == 3:
            work.state_before = work.state = self._filter_state
            w = np.zeros(size)
            if self._inverse_on:
                if work.state is None:
                    work.state = inv.start(float(work.xs[half]))
                w, work.state = inv.causal(work.fir, work.state)
                w = w / self.slope
            self._filter_state = work.state
            work.filtered = True
            core = slice(inv.back + half, inv.back + half + size)
            work.tables = (work.raw_x[core], work.xs[core], work.vs[core], w)
        else:
            x_raw, x, v, w = work.tables
            work.lists = (x_raw.tolist(), x.tolist(), v.tolist(), w.tolist())
        work.stage = stage + 1

    def _set_tables(self, x_raw: FloatArray, x: FloatArray, v: FloatArray,
                    w: FloatArray) -> None:
        """Keep the tables as plain-float lists: numpy scalars cost more per use in the step."""
        self._x_lists((x_raw.tolist(), x.tolist(), v.tolist(), w.tolist()))

    def _x_lists(self, lists: tuple[list[float], list[float], list[float], list[float]]
                 ) -> None:
        """Install the tables x_d, shaped x_d, x_d', w as lists (:meth:`_set_tables`)."""
        self._lx_raw, self._lx, self._lv, self._lw = lists

    # -- learning ----------------------------------------------------------------------------

    def _hold(self, hold: bool) -> None:
        """
        Hold the RAC's estimates while the table learns (see ``hold_estimates``).

        With the model inverse, the estimates are held where the start's transient left them,
        and at tracking they add k ((theta_hat - theta_0) x_d + (phi_hat - phi_0) x_d') to the
        command: the table takes that off in Q's band, but above it (a fast line's
        turnarounds, drawn by the model inverse alone) it would stay as an error. So while
        held, that term is taken off the command too: the loop at tracking is the model
        inverse and the table, whatever the estimates were held at.
        """
        self._holding = hold
        rac = self._hold_inner(hold)
        self._drift_gains = (0.0, 0.0)
        if hold and self._inverse_on and hasattr(rac, 'diagnostics'):
            values = dict(rac.diagnostics())
            if 'theta_hat' in values and 'phi_hat' in values:
                self._drift_gains = (float(values['theta_hat']) - self._theta0,
                                     float(values['phi_hat']) - self._phi0)
                self._drift_fresh = True

    def _hold_inner(self, hold: bool) -> Any:
        """Hold or release the RAC's estimates (nothing for a PI); return the RAC."""
        rac = getattr(self.inner, 'inner', self.inner)
        hold_estimates = getattr(rac, 'hold_estimates', None)
        if hold_estimates is not None:
            hold_estimates(hold)
        return rac

    def _drift(self, x_ref: float, v_ref: float) -> float:
        """Return what the held estimates add over the initial ones at x_ref, through the notch."""
        d_theta, d_phi = self._drift_gains
        drift = (d_theta * x_ref + d_phi * v_ref) * self._ksens
        notch = self._drift_notch
        if notch is None:
            return drift
        if self._drift_fresh:  # at rest on the present value, as the share's notch starts
            self._drift_fresh = False
            notch.reset(drift)
        elif self._drift_gap:
            notch.bridge(self._drift_last, drift, self._drift_gap)
        self._drift_gap = 0
        self._drift_last = drift
        return float(notch.step(drift))

    def _accumulate(self, end: int) -> None:
        """
        Add the errors of samples pending .. end - 1 of the period to the update.

        delta_j += sum_i e_i h_((j - i) mod n): columns i of the circulant operator, the
        windows of h over two periods, weighted by the errors and summed in one call.
        """
        n = self._period_n  # > 0: learning binds only a periodic reference
        start = self._pending
        self._pending = end % n
        if end <= start or self._spectral:  # the spectrum took each error as it came
            return
        errors = self._errors
        chunk = np.array(errors[start:end][::-1])
        errors[start:end] = [0.0] * (end - start)
        if self._slice:
            self._backlog.append([chunk[:, None], n - end + 1, n - start + 1, 0])
            return
        # row n - i of the windows is column i; the sum over the rows runs in their order
        # (no BLAS: the same sums on every machine, and the batched loop repeats them)
        self._delta += (chunk[:, None] * self._columns[n - end + 1:n - start + 1]).sum(axis=0)

    def _work(self, backlog: list[list[Any]]) -> None:
        """
        Add the next slice of columns of the oldest run's correlation to the update.

        The same products summed over the same rows in the same order as :meth:`_accumulate`
        sums them whole, column by column, and each column gets the runs in the order they
        came: the update is the one the whole sums give. A slice keeps at least two columns
        (a single column would be summed as a row, in another order).
        """
        run = backlog[0]
        chunk, first, last, c0 = run
        n = self._period_n
        c1 = c0 + self._slice
        if c1 > n - 2:
            c1 = n
            del backlog[0]
        else:
            run[3] = c1
        self._delta[c0:c1] += (chunk * self._columns[first:last, c0:c1]).sum(axis=0)

    def _add_spectrum(self, i: int) -> None:
        """
        Add the error of sample ``i`` of the period to its spectrum on the kept harmonics.

        E_h += e_i exp(-2 pi j h i / n), the phasor turned on a sample at a time from an exact
        one taken at the first sample after a jump (a period's start, a stall, a reset), so
        that its rounding grows over one period at most.
        """
        e = self._errors[i]
        self._errors[i] = 0.0
        if i != self._phasor_i:
            n = self._period_n
            self._phasor = np.exp(-2j * math.pi * ((self._harmonics * i) % n) / n)
        self._spectrum += e * self._phasor
        self._phasor *= self._turn
        self._phasor_i = i + 1

    def _drain(self) -> None:
        """Add what the runs still owe to the update (before it is applied)."""
        backlog = self._backlog
        while backlog:
            self._work(backlog)

    @property
    def _learn_from(self) -> int:
        """Return the first sample whose error is learned (after the start periods)."""
        return self.params.learning_start_periods * self._period_n

    def _set_leak(self, n: float) -> None:
        """|P_s| at the period's first harmonic [m/V]: see ``CLIP_SETTLE_SAMPLES``."""
        z = period_harmonics(n)[1:2]
        k_p, k_i = self.inner.linear_gains()
        g = self.slope * self.plant_inverse.frequency_response(z)
        ps = process_sensitivity(g, z, k_p, k_i, self._ksens, self._t, self._notch_coeffs)
        self._leak = float(np.abs(ps[0])) if ps.size else 0.0

    def phase_learning(self, samples: float, members: int) -> PhaseLearning:
        """Return the learning of a period of ``samples`` samples (any length), M members."""
        filt = self._learning_filter(samples)
        kept = np.flatnonzero(filt != 0.0)
        table = PhaseLearning(filt[kept], kept.astype(np.float64), samples, members,
                              self.params.learning_limit_v,
                              self.params.learning_start_periods)
        table.leak = self._leak
        return table

    def _learning_filter(self, n: float) -> ComplexArray:
        """Return gamma Q / P_s on the harmonics of a period of n samples (0 where Q drops)."""
        z = period_harmonics(n)
        # the plant seen from v_lin: c G (the compensator removes the hysteresis; without it,
        # the hysteresis slope c is its gain)
        g = self.slope * self.plant_inverse.frequency_response(z)
        k_p, k_i = self.inner.linear_gains()
        ps = process_sensitivity(g, z, k_p, k_i, self._ksens, self._t, self._notch_coeffs)
        kept = kept_harmonics(ps, n, self._t, self.params.learning_bandwidth_hz) > 0.0
        return np.asarray(np.where(kept, self.params.learning_gain / np.where(kept, ps, 1.0),
                                   0.0), dtype=np.complex128)

    def _learn(self, k: int) -> None:
        """
        End of a period: apply the update accumulated over it, L <- L - gamma Q E / P_s.

        The update is the period's error through the learning filter, a circular convolution
        with its impulse response, summed sample by sample as the errors came (no FFT at the
        period's end: the real-time step stays even); a long period learning on its harmonics
        (``spectrum_samples``) filters the spectrum summed so and takes one inverse FFT here.
        The table stays inside Q's band (every update is), so Q L = L.
        """
        self.last_period_rms_m = math.sqrt(self._sq / self._period_n)
        self._sq = 0.0
        if k < self._learn_from:
            return
        limit = self.params.learning_limit_v
        learned = self._learned
        self._drain()
        if self._spectral:
            # the circular convolution with the filter's response: the filtered spectrum back
            n = self._period_n
            full = np.zeros(n // 2 + 1, dtype=np.complex128)
            full[self._harmonics] = self._learning_gains * self._spectrum
            self._spectrum.fill(0.0)
            self._delta = np.fft.irfft(full, n)
        learned -= self._delta
        if self._excess_any:
            # what the range clipped off the table: the table takes the input that was
            # applied, then Q (band, no DC)
            learned -= self._excess_table
            self._excess_table.fill(0.0)
            self._excess_any = False
            learned[:] = np.fft.irfft(np.fft.rfft(learned) * self._kept, len(learned))
        peak = float(np.max(np.abs(learned)))
        if peak > limit:
            # scaled, not clipped: the table stays in Q's band with no DC
            learned *= limit / peak
            self.limited_updates += 1
        self._delta.fill(0.0)
        self._ll = learned.tolist()
        self.periods_learned += 1

    # -- tables for others ---------------------------------------------------------------------

    def table_points(self) -> int:
        """
        Return N, the points of one period in :meth:`learned_table` and in a table file.

        A whole period: its n samples. Any other: ceil(P/T) points evenly spaced in phase,
        at least one per sample (the table is band-limited below the Nyquist frequency, so
        they hold it whole).
        """
        if self._phase is not None:
            return int(math.ceil(self._phase.samples - 1e-9))
        return self._period_n

    def learned_table(self) -> FloatArray:
        """Return a copy of the learned table (one period, :meth:`table_points`) [V]."""
        if self._phase is not None:
            return np.asarray(self._phase.on_grid(self.table_points())[:, 0], dtype=np.float64)
        return self._learned.copy()

    def load_table(self, table: FloatArray) -> None:
        """Start from a saved learned table (same period) [V]."""
        table = np.asarray(table, dtype=np.float64)
        if self._phase is not None:
            if table.shape != (self.table_points(),):
                raise ParameterError('learned table', f'{table.shape[0]} points',
                                     f'{self.table_points()} points (one period)',
                                     'has the wrong length')
            self._phase.load_grid(table)
            return
        if table.shape != (self._period_n,):
            raise ParameterError('learned table', f'{table.shape[0]} samples',
                                 f'{self._period_n} samples (one period)', 'has the wrong length')
        self._learned = np.clip(table, -self.params.learning_limit_v,
                                self.params.learning_limit_v)
        self._ll = self._learned.tolist()

    def design_summary(self) -> str:
        """
        Return what the feed-forward is designed on, one ``name=value`` item per part.

        The mode, T, the ZOH model G(z), the design hysteresis and its slope c, the inner
        controller's linear gains (at its present estimates: :meth:`bind` takes them at the
        initial ones), the sensor gain, the RAC's share and the notch; floats in full
        precision, so equal designs give equal text (:attr:`LearnedTable.design`).
        """
        def floats(values: Any) -> str:
            return '[' + ', '.join(repr(float(v)) for v in np.ravel(values)) + ']'
        hyst = self._hysteresis_model
        k_p, k_i = self.inner.linear_gains()
        notch = 'none' if self._notch_coeffs is None else \
            f'{floats(self._notch_coeffs[0])}/{floats(self._notch_coeffs[1])}'
        parts = [f'mode={self.params.mode}', f'T={self._t!r}',
                 f'G={floats(self.plant_inverse.num)}/{floats(self.plant_inverse.den)}',
                 f'hysteresis={type(hyst).__name__}({getattr(hyst, "params", "")!r})',
                 f'c={self.slope!r}', f'k_p={float(k_p)!r}', f'k_i={float(k_i)!r}',
                 f'k={self._ksens!r}', f'share={self._theta0!r},{self._phi0!r}',
                 f'notch={notch}']
        return '; '.join(parts)

    def learned(self) -> LearnedTable:
        """
        Return the learned table with what it was learned for (to write to a file or a bag).

        Raises
        ------
        PiezoStageError
            If the mode does not learn or the controller is not bound to a periodic reference.

        """
        if not self._learning_on or not (self._period_n or self._phase is not None):
            raise PiezoStageError(f'feed-forward mode {self.params.mode!r}: no learned table '
                                  '(the mode does not learn, or no trajectory is bound)')
        # with the model inverse the held estimates' term is taken off the command (_hold):
        # the table holds nothing of it
        drift = np.zeros(self.table_points()) if self._inverse_on and self._holding \
            else self._estimate_drift()
        if self._phase is not None:
            x, _ = self._grid_reference()
            table = self.learned_table() + drift
            period = self.period_s
        else:
            x = np.asarray(self._lx_raw, dtype=np.float64)
            table = self._learned + drift
            period = self._period_n * self._t
        return LearnedTable(table_v=table, reference_m=x,
                            sample_time_s=self._t, period_s=period,
                            mode=self.params.mode, design=self.design,
                            periods_learned=self.periods_learned,
                            period_rms_m=self.last_period_rms_m)

    def _estimate_drift(self) -> FloatArray:
        """
        Return what the RAC's estimates add over their initial values at the reference [V].

        At tracking (y = x_d) the RAC's command holds theta_hat y + phi_hat dy_d/dt, and the
        table was learned with the estimates where they stood (held): k ((theta_hat - theta_0)
        x_d + (phi_hat - phi_0) dx_d/dt), through the notch when there is one, is what a table
        used with the initial estimates must add. Zero for a PI.
        """
        rac = getattr(self.inner, 'inner', self.inner)
        values = dict(rac.diagnostics()) if hasattr(rac, 'diagnostics') else {}
        n = self.table_points()
        if 'theta_hat' not in values or 'phi_hat' not in values:
            return np.zeros(n)
        d_theta = float(values['theta_hat']) - self._theta0
        d_phi = float(values['phi_hat']) - self._phi0
        if self._phase is not None:
            x, v = self._grid_reference()
            x, v = self._shape_periodic(x, v)
        else:
            x, v = np.asarray(self._lx), np.asarray(self._lv)
        drift = self._ksens * (d_theta * x + d_phi * v)
        if self._notch_coeffs is not None:
            # the harmonics of the period: h / (P/T) cycles a sample
            samples = self._phase.samples if self._phase is not None else n
            z = np.exp(2j * math.pi * np.arange(n // 2 + 1) / samples)
            num, den = self._notch_coeffs
            drift = np.fft.irfft(np.fft.rfft(drift) * np.polyval(num, z) / np.polyval(den, z), n)
        return np.asarray(drift, dtype=np.float64)

    def _grid_reference(self) -> tuple[FloatArray, FloatArray]:
        """Return x_d, x_d' at the phases of :meth:`table_points` of the second period."""
        assert self._trajectory is not None
        n = self.table_points()
        t = self.period_s * (1.0 + np.arange(n) / n)
        x, v = self._trajectory.evaluate(t)
        return np.asarray(x, dtype=np.float64).copy(), np.asarray(v, dtype=np.float64).copy()

    def _shape_periodic(self, x: FloatArray, v: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Shape the jumps of one period (a jump across its end too: three periods shaped)."""
        n = len(x)
        x3, v3 = self._shape(np.tile(x, 3), np.tile(v, 3))
        return x3[n:2 * n], v3[n:2 * n]

    def save_table_file(self, path: str | Path) -> Path:
        """Write :meth:`learned` to ``path`` (:func:`write_learned_table`) and return it."""
        return write_learned_table(path, self.learned())

    def load_table_file(self, path: str | Path) -> None:
        """
        Start from the table of a file, if it was learned for this reference and design.

        Parameters
        ----------
        path : path-like
            A file of :func:`write_learned_table`.

        Raises
        ------
        ParameterError
            Named ``feedforward.table_file``: the file cannot be read, or its sample time,
            period length, reference or design differ from the bound controller's (the
            message gives the file's value and the one expected).

        """
        name = 'feedforward.table_file'
        try:
            saved = read_learned_table(path)
        except PiezoStageError as err:
            raise ParameterError(name, str(path), 'a learned-table file (.npz, version '
                                 f'{TABLE_VERSION})', f'cannot be loaded ({err})') from None
        here = self.learned()
        if (saved.samples != here.samples
                or abs(saved.sample_time_s - here.sample_time_s) > 1e-12 * here.sample_time_s):
            raise ParameterError(
                name, str(path), f'a table of {here.samples} samples of T = '
                f'{here.sample_time_s:g} s (period {here.period_s:g} s, the bound trajectory)',
                f'holds {saved.samples} samples of T = {saved.sample_time_s:g} s (period '
                f'{saved.period_s:g} s)')
        if abs(saved.period_s - here.period_s) > 1e-9 * here.period_s:
            raise ParameterError(
                name, str(path), f'a table of the period {here.period_s!r} s (the bound '
                'trajectory)', f'was learned for a period of {saved.period_s!r} s: a table '
                'belongs to one line rate (learn it again at this one)')
        gap = np.abs(saved.reference_m - here.reference_m)
        bad = gap > 1e-12 + 1e-9 * np.abs(here.reference_m)
        if np.any(bad):
            i = int(np.argmax(gap))
            raise ParameterError(
                name, str(path), 'a table learned on the bound trajectory', 'was learned on '
                f'another reference: {int(np.sum(bad))} of {here.samples} samples differ, most '
                f'at sample {i}: {saved.reference_m[i]:.9g} m, expected '
                f'{here.reference_m[i]:.9g} m')
        if saved.design != here.design:
            theirs = saved.design.split('; ')
            mine = here.design.split('; ')
            differ = [f'{a} (expected {b})' for a, b in zip(theirs, mine) if a != b] \
                or [f'{saved.design} (expected {here.design})']
            raise ParameterError(name, str(path), f'a table of design {here.design_hash}',
                                 f'was learned on design {saved.design_hash}: '
                                 + '; '.join(differ))
        self.load_table(saved.table_v)
        self.table_source = str(path)

    # -- for a batched loop (N stages, one reference) -----------------------------------------

    def reference_tables(self, k: int) -> tuple[int, int, list[float], list[float],
                                                list[float], list[float]]:
        """
        Return the tables the step of sample ``k`` reads, for a loop that steps N stages.

        ``(period, start, x_d, x_ref, x_ref', w)``: periodic (period > 0), one period read at
        ``k mod period``; else the block holding sample ``k``, read at ``k - start`` (the next
        block is computed when ``k`` passes the present one: ask in sample order, as the step
        does). The lists are the wrapper's own: read, do not change.
        """
        if not self._period_n:
            if k - self._block_start >= len(self._lx):
                self._next_block(k)
            elif self._block_ahead is not None and not self._block_ahead.done:
                self._block_stage(self._block_ahead)
        return (self._period_n, self._block_start, self._lx_raw, self._lx, self._lv,
                self._lw)

    def add_to_inverse(self, w_v: FloatArray) -> None:
        """
        Add a table over the bound period to the model inverse's w [V] (until the next bind).

        A multi-axis stage's coupling compensation: the inverse of this axis' model acting on
        the displacement the other axes' references are predicted to cause here.
        """
        if not self._inverse_on:
            raise ParameterError('feedforward.mode', self.params.mode, "'inverse' or "
                                 "'inverse_learning'", 'has no model inverse to add to')
        n = self._period_n
        table = np.asarray(w_v, dtype=np.float64)
        if not n or table.shape != (n,):
            raise ParameterError('w_v', table.shape, f'({n},): one period of a periodic bound '
                                 'reference')
        self._lw = (np.asarray(self._lw) + table).tolist()

    @property
    def phase_table(self) -> PhaseLearning | None:
        """Return the learning of a period that is not a whole number of samples (or None)."""
        return self._phase

    def learning_kernel(self) -> FloatArray:
        """Return the learning operator's impulse response over two periods (a copy)."""
        return self._kernel2.copy()

    @property
    def output_limits_v(self) -> tuple[float, float]:
        """Return the command limits (lowest, highest) [V]."""
        return self._vmin, self._vmax

    @property
    def sensor_gain_v_per_m(self) -> float:
        """Return K_PSCM [V/m], the conversion of positions to sensor volts."""
        return self._ksens

    def share_gains(self) -> tuple[float, float, float]:
        """Return (theta_0, phi_0, k): the share subtracted is (theta_0 x + phi_0 x') k."""
        return self._theta0, self._phi0, self._ksens

    # -- diagnostics -----------------------------------------------------------------------

    @property
    def diagnostic_names(self) -> tuple[str, ...]:
        """Return the inner controller's names and the feed-forward's."""
        return tuple(getattr(self.inner, 'diagnostic_names', ())) + (
            'ff_active', 'ff_mismatches', 'ff_periods_learned', 'ff_period_rms_m', 'ff_u_v')

    def diagnostic_values(self) -> tuple[float, ...]:
        """Return the values of :attr:`diagnostic_names`."""
        return tuple(self.inner.diagnostic_values()) + (
            1.0 if self._matched else 0.0, float(self.mismatches),
            float(self.periods_learned), self.last_period_rms_m, self.feedforward_v())

    def feedforward_v(self) -> float:
        """
        Return the feed-forward of the last sample: the model inverse plus the learned table [V].

        u_ff = W[i] + L[i] on the linear input v_lin (W the model inverse, already divided by
        the hysteresis slope c; L the learned table), 0 when the sample got feedback alone.
        The RAC's own first-order share at its initial estimates, which the model inverse
        replaces (module doc), is not in it. The last sample of a period updates the table
        after using it: the entry it used is the one of the table seen by an earlier call in
        the same period, which a caller reading at least once a period (the diagnostics are
        read every sample or every few) has made; otherwise the updated entry is returned.
        """
        if not self._matched or self._trajectory is None:
            return 0.0
        k = self._k - 1
        n = self._period_n
        i = k % n if n else k - self._block_start
        u = self._lw[i] if self._inverse_on else 0.0
        if self._phase is not None:
            return u + self._last_learned
        if self._learning_on:
            table = self._ll
            if i == n - 1 and table is not self._seen_table and self._seen_k >= k - i:
                table = self._seen_table  # updated at this sample, after its use
            u += table[i]
            self._seen_table = self._ll
            self._seen_k = k
        return u

    def diagnostics(self) -> Mapping[str, float]:
        """Return the diagnostics as a mapping."""
        return dict(zip(self.diagnostic_names, self.diagnostic_values()))

    def update_params(self, params: Any) -> bool:
        """Pass gains to the inner controller when the feed-forward settings stay."""
        ff = getattr(params, 'feedforward', None)
        if ff is not None and ff != self.params:
            return False
        update: Callable[[Any], bool] | None = getattr(self.inner, 'update_params', None)
        applied = bool(update(params)) if update is not None else False
        if applied:
            self._set_share()
        return applied
