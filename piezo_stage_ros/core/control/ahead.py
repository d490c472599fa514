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
Commands ahead: the controller's prediction of its next commands, for samples the host misses.

At each sample k the controller gives u_k and a prediction p_k+1 .. p_k+m of the commands it
would give next if the stage followed the reference. The I/O target (or the simulated stage)
keeps them as a queue and applies p_k+j over a sample the host missed instead of holding u_k
(:class:`~piezo_stage_ros.hardware.safety.GuardedPlant`).

The prediction moves the part of the command the reference explains along the reference ahead:

    p_k+j = u_k + a (x_d,k+j - x_d,k) + b (x_d',k+j - x_d',k)

with (a, b) the controller's ``reference_gains()`` (the RAC's theta_hat k and phi_hat k: its
model-based part theta_hat y + phi_hat dy_d/dt at y = y_d, eq. (36); an open loop's gain;
(0, 0) for a PI) plus the trend of the feedback part along the reference, fitted over the last
samples by :class:`CommandPredictor`; what the fit cannot explain is held. A feed-forward
wrapper predicts from its own tables
(:meth:`~piezo_stage_ros.core.control.feedforward.FeedForwardController.predict`). No controller
step is run: a few array operations on m values per sample.
"""

from __future__ import annotations

import copy
import math
from typing import Any, Callable, Iterator, overload, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.types import FloatArray, IntArray

__all__ = ['Ahead', 'AheadRow', 'AxesAhead', 'CommandPredictor']

#: Variance of a regressor [V^2, sensor volts] below which the reference counts as at rest: a
#: microvolt rms, far below any motion and far above the rounding of the sums (1e-16 of ~1 V).
_AT_REST = 1e-12


class Ahead(Sequence[float]):
    """
    Commands ahead u_k + a (x_d,j - x_d,k) + b (x_d',j - x_d',k), computed when read.

    What :meth:`CommandPredictor.predict` returns for a controller with reference gains, as a
    sequence that costs nothing until a value is read: a backend reads them only for the
    samples the host misses (the simulated stage), or packs them at once into its request (the
    UDP target, :meth:`to_array`). Slices are views; :meth:`clamped` narrows the range,
    :meth:`finite` says whether every value is finite (the reference is).

    Parameters
    ----------
    ahead_m, ahead_mps : sequence of float
        x_d and x_d' [m, m/s]; the values are those of indices ``start`` .. ``stop - 1``.
    start, stop : int
        The part of them that is ahead.
    base_v : float
        u_k - a x_d,k - b x_d',k [V].
    gains : tuple of float
        (a [V/m], b [V s/m]).
    low_v, high_v : float
        Command limits [V].

    """

    __slots__ = ('_x', '_v', '_start', '_stop', '_base', '_a', '_b', '_low', '_high')

    def __init__(self, ahead_m: Sequence[float], ahead_mps: Sequence[float], start: int,
                 stop: int, base_v: float, gains: tuple[float, float],
                 low_v: float = -math.inf, high_v: float = math.inf) -> None:
        self._x, self._v = ahead_m, ahead_mps
        self._start, self._stop = start, stop
        self._base = base_v
        self._a, self._b = gains
        self._low, self._high = low_v, high_v

    def __len__(self) -> int:
        return max(self._stop - self._start, 0)

    def _value(self, j: int) -> float:
        p = float(self._base + self._a * self._x[j] + self._b * self._v[j])
        return self._high if p > self._high else (self._low if p < self._low else p)

    @overload
    def __getitem__(self, index: int) -> float: ...

    @overload
    def __getitem__(self, index: slice) -> Ahead: ...

    def __getitem__(self, index: int | slice) -> float | Ahead:
        n = len(self)
        if isinstance(index, slice):
            first, last, step = index.indices(n)
            if step != 1:
                raise ValueError('commands ahead: slices have step 1')
            return Ahead(self._x, self._v, self._start + first,
                         self._start + max(last, first), self._base, (self._a, self._b),
                         self._low, self._high)
        if index < 0:
            index += n
        if not 0 <= index < n:
            raise IndexError('commands ahead: index out of range')
        return self._value(self._start + index)

    def __iter__(self) -> Iterator[float]:
        return iter([self._value(j) for j in range(self._start, self._stop)])

    def to_array(self) -> FloatArray:
        """
        Return every value at once, as an array [V] (what a backend packs for its target).

        The same arithmetic as reading them one by one, element for element, for a fraction of
        its cost: 128 values read one by one took about 1 us each in the UDP host's answer.
        """
        out = np.empty(len(self), dtype=np.float64)
        self.values_into(out)
        return out

    def values_into(self, out: FloatArray) -> None:
        """
        Write every value into ``out`` (an array of ``len(self)``) [V], as :meth:`to_array`.

        No array is made: the UDP host writes them straight into its datagram.
        """
        x = np.asarray(self._x[self._start:self._stop], dtype=np.float64)
        v = np.asarray(self._v[self._start:self._stop], dtype=np.float64)
        # base + a x + b v, summed in that order as _value does
        np.multiply(x, self._a, out=out)
        out += self._base
        out += self._b * v
        if self._high < math.inf:
            np.minimum(out, self._high, out=out)
        if self._low > -math.inf:
            np.maximum(out, self._low, out=out)

    def clamped(self, low_v: float, high_v: float) -> Ahead:
        """Return the same commands clipped to ``[low_v, high_v]`` too [V]."""
        return Ahead(self._x, self._v, self._start, self._stop, self._base,
                     (self._a, self._b), max(self._low, low_v), min(self._high, high_v))

    def finite(self) -> bool:
        """Return whether every value is finite (the coefficients are; the reference is)."""
        return math.isfinite(self._base + self._a + self._b)


def _sensor_gain(controller: Any) -> float | None:
    """Return the sensor gain k [V/m] of a controller or of the one it wraps (None: none)."""
    for _ in range(3):
        gain = getattr(controller, 'sensor_gain_v_per_m', None)
        if isinstance(gain, float) and gain > 0.0:
            return gain
        controller = getattr(controller, 'inner', None)
        if controller is None:
            break
    return None


class CommandPredictor:
    """
    The commands ahead of a controller, sample by sample, with the trend of its feedback part.

    Its model-based part moves along the reference ahead (:class:`Ahead`). The
    feedback part f_k = u_k - a x_d,k - b x_d',k is what the model-based part does not explain
    (the estimates still adapting, the ZOH's lag, the hysteresis); it is not constant while
    the reference moves. Its part along the reference, f ~ f0 + alpha x_d + beta x_d', is
    fitted by least squares over the last ``memory_samples`` samples (exponential forgetting,
    a few multiplications a sample) and moves along the reference ahead with the model-based
    part; the rest of it is held. A fit the reference does not excite (a reference at rest) is
    damped to no trend by a ridge of ``ridge`` times each regressor's variance (and a floor of
    (1 uV)^2 in sensor volts, far above the rounding of the sums): the feedback part is then
    held.

    Parameters
    ----------
    sensor_gain_v_per_m : float
        k [V/m]: the regressors are fitted in sensor volts (numbers near 1); the controller's
        own k when it has one (:meth:`predict` reads it).
    sample_time_s : float
        T [s] (x_d' is fitted as its change per sample).
    memory_samples : float
        Time constant of the forgetting [samples].
    ridge : float
        Relative ridge of the fit.

    """

    def __init__(self, sensor_gain_v_per_m: float, sample_time_s: float, *,
                 memory_samples: float = 100.0, ridge: float = 1e-3) -> None:
        self._t = float(sample_time_s)
        self._kx = float(sensor_gain_v_per_m)
        self._kv = float(sensor_gain_v_per_m) * self._t
        self._forget = 1.0 - 1.0 / float(memory_samples)
        # the weight of samples the fit needs before its trend is taken (about 0.7 memories)
        self._warm = 0.5 * float(memory_samples)
        self._ridge = float(ridge)
        # exponentially weighted sums of 1, x, v, f and their products
        self._sums = [0.0] * 9
        self._controller: Any = None
        self._own: Callable[[int], Any] | None = None
        self._gains: Callable[[], tuple[float, float]] | None = None
        self._limits = (-math.inf, math.inf)

    def reset(self) -> None:
        """Forget the fit (a controller rebuilt)."""
        self._sums = [0.0] * 9

    def trend(self, feedback_v: float, reference_m: float, velocity_mps: float
              ) -> tuple[float, float]:
        """Take this sample's feedback part [V]; return its (alpha [V/m], beta [V s/m])."""
        self._accumulate(feedback_v, reference_m, velocity_mps)
        return self._solve()

    def _accumulate(self, feedback_v: float, reference_m: float, velocity_mps: float) -> None:
        """Take this sample's feedback part [V] into the fit's sums (no solve)."""
        x = reference_m * self._kx
        v = velocity_mps * self._kv
        f = feedback_v
        lam = self._forget
        s1, sx, sv, sf, sxx, sxv, svv, sxf, svf = self._sums
        s1 = lam * s1 + 1.0
        sx = lam * sx + x
        sv = lam * sv + v
        sf = lam * sf + f
        sxx = lam * sxx + x * x
        sxv = lam * sxv + x * v
        svv = lam * svv + v * v
        sxf = lam * sxf + x * f
        svf = lam * svf + v * f
        self._sums = [s1, sx, sv, sf, sxx, sxv, svv, sxf, svf]

    def _solve(self) -> tuple[float, float]:
        """
        Return the trend (alpha [V/m], beta [V s/m]) the sums give.

        (0, 0) until the fit has seen half its memory's weight of samples (70 of them at
        the default 100): a fit of the first few samples of a start, while the
        controller catches up with the reference, extrapolates its steep transient, and a
        stall there costs far more with the trend than without it or with the command held.
        """
        s1, sx, sv, sf, sxx, sxv, svv, sxf, svf = self._sums
        if s1 < self._warm:
            return 0.0, 0.0
        mx, mv, mf = sx / s1, sv / s1, sf / s1
        cxx = sxx / s1 - mx * mx
        cxv = sxv / s1 - mx * mv
        cvv = svv / s1 - mv * mv
        cxf = sxf / s1 - mx * mf
        cvf = svf / s1 - mv * mf
        if cxx + cvv <= _AT_REST:
            return 0.0, 0.0  # the reference at rest: nothing to fit, the feedback part held
        cxx = cxx * (1.0 + self._ridge) + _AT_REST
        cvv = cvv * (1.0 + self._ridge) + _AT_REST
        det = cxx * cvv - cxv * cxv
        if not det > 0.0:
            return 0.0, 0.0
        alpha = (cvv * cxf - cxv * cvf) / det
        beta = (cxx * cvf - cxv * cxf) / det
        if not (math.isfinite(alpha) and math.isfinite(beta)):
            return 0.0, 0.0
        return alpha * self._kx, beta * self._kv

    def _look_up(self, controller: Any) -> None:
        if controller is not self._controller:
            # looked up once per controller (a rebuild makes a new one)
            self._controller = controller
            gain = _sensor_gain(controller)
            if gain is not None and gain * self._t != self._kv:
                self._kx, self._kv = gain, gain * self._t
                self.reset()
            self._own = getattr(controller, 'predict', None)
            self._gains = getattr(controller, 'reference_gains', None)
            self._limits = getattr(controller, 'output_limits_v', (-math.inf, math.inf))

    def observe(self, controller: Any, command_v: float, reference_m: float,
                velocity_mps: float) -> None:
        """
        Take a sample whose commands ahead are not wanted: only the trend's fit takes it.

        For a caller that predicts on some samples only (the host of a UDP stream when its
        answer leaves late): the fit's memory stays ``memory_samples`` samples, and the next
        :meth:`predict` is the one it would have been.
        """
        self._look_up(controller)
        gains = self._gains
        if self._own is None and gains is not None:
            a, b = gains()
            self._accumulate(command_v - a * reference_m - b * velocity_mps, reference_m,
                             velocity_mps)

    def predict(self, controller: Any, count: int, command_v: float, reference_m: float,
                velocity_mps: float,
                reference_ahead: Callable[[int], tuple[Sequence[float], Sequence[float]]]
                ) -> Sequence[float] | FloatArray:
        """
        Return ``count`` commands predicted after ``command_v`` for ``controller`` [V].

        Call once a sample, after the controller's step. A controller with its own
        ``predict(count)`` (a feed-forward) predicts from its tables; any other moves its
        ``reference_gains()`` part and the trend of its feedback part along
        ``reference_ahead(count)`` (x_d and x_d' of the next ``count`` samples); one without
        reference gains holds its command.
        """
        self._look_up(controller)
        if self._own is not None:
            return np.asarray(self._own(count), dtype=np.float64)
        gains = self._gains
        if gains is None:
            return [command_v] * count
        a, b = gains()
        alpha, beta = self.trend(command_v - a * reference_m - b * velocity_mps,
                                 reference_m, velocity_mps)
        ahead_m, ahead_mps = reference_ahead(count)
        a += alpha
        b += beta
        # computed when read (a few values after a stall, not 32 every sample)
        low, high = self._limits
        return Ahead(ahead_m, ahead_mps, 0, len(ahead_m),
                     command_v - a * reference_m - b * velocity_mps, (a, b), low, high)


class _SecantAt:
    """
    A feed-forward's ``ahead_secant`` as it is at one sample, to be taken later.

    The secant reads the inverse hysteresis' state, the slope and the last command; they are
    copied here (the inverse's attributes are replaced, never changed in place, when it is
    stepped), and the controller's own method is applied to the copy: the same operations
    on the same numbers as the controller's call at that sample.
    """

    __slots__ = ('hysteresis_inverse', 'slope', '_u', '_secant')

    def __init__(self, controller: Any, last_v: float) -> None:
        hyst = controller.hysteresis_inverse
        state = getattr(hyst, '__dict__', None)
        if state is None:
            held = copy.copy(hyst)
        else:
            held = object.__new__(type(hyst))
            held.__dict__.update(state)
        self.hysteresis_inverse = held
        self.slope = controller.slope
        self._u = last_v
        self._secant = type(controller).ahead_secant

    def __call__(self, du: float) -> float:
        return float(self._secant(self, du))

    def finite(self) -> bool:
        """Return whether the state the secant starts from is finite."""
        return math.isfinite(self.hysteresis_inverse.output_v)


class _Pending:
    """One sample's commands ahead of the batched axes, computed when one of them is read."""

    __slots__ = ('_owner', '_count', '_rows', '_plans', '_secants', '_values')

    def __init__(self, owner: AxesAhead, count: int, rows: list[int],
                 plans: list[tuple[Any, ...]], secants: list[Callable[[float], float]]
                 ) -> None:
        self._owner = owner
        self._count = count
        self._rows = rows
        self._plans = plans
        self._secants = secants
        self._values: FloatArray | None = None

    def values(self) -> FloatArray:
        """Return the (rows, count) commands ahead [V], computed on the first call."""
        values = self._values
        if values is None:
            values = self._values = self._owner._evaluate(self._count, self._rows,
                                                          self._plans, self._secants)
        return values


class AheadRow(Sequence[float]):
    """
    One axis' commands ahead out of :meth:`AxesAhead.rows`, computed when read.

    The sequence the guard of an axis takes (as :class:`Ahead`): ``finite()``,
    ``clamped()``, length, items and slices (views), :meth:`to_array`, :meth:`values_into`.
    Reading any value computes the batch of every axis of that sample at once, from the
    tables, coefficients and inverse hysteresis' state of that sample, whatever the
    controllers did since: the values are those :meth:`AxesAhead.predict` gave then.

    ``finite()`` is decided from what the values are computed from (the tables, the
    coefficients, the inverse hysteresis' state), as :class:`Ahead` decides from its
    coefficients. A row that is not finite all the same when it is computed (a secant that
    is not a number) reads as the command held: the voltages a guard refusing it would apply
    (a guard that took it counts its samples as predicted).
    """

    __slots__ = ('_pending', '_row', '_start', '_stop', '_finite', '_last', '_clamps',
                 '_array')

    def __init__(self, pending: _Pending, row: int, stop: int, finite: bool, last_v: float,
                 *, start: int = 0, clamps: tuple[tuple[float, float], ...] = (),
                 array: FloatArray | None = None) -> None:
        self._pending = pending
        self._row = row
        self._start, self._stop = start, stop
        self._finite = finite
        self._last = last_v
        self._clamps = clamps
        self._array = array

    def _values(self) -> FloatArray:
        """Return the whole row (from index 0), clamped as asked, computed once per view."""
        array = self._array
        if array is None:
            array = self._pending.values()[self._row]
            if not np.isfinite(array).all():
                array = np.full(array.size, self._last)
            for low, high in self._clamps:
                array = np.minimum(np.maximum(array, low), high)
            self._array = array
        return array

    def __len__(self) -> int:
        return max(self._stop - self._start, 0)

    @overload
    def __getitem__(self, index: int) -> float: ...

    @overload
    def __getitem__(self, index: slice) -> AheadRow: ...

    def __getitem__(self, index: int | slice) -> float | AheadRow:
        n = len(self)
        if isinstance(index, slice):
            first, last, step = index.indices(n)
            if step != 1:
                raise ValueError('commands ahead: slices have step 1')
            return AheadRow(self._pending, self._row, self._start + max(last, first),
                            self._finite, self._last, start=self._start + first,
                            clamps=self._clamps, array=self._array)
        if index < 0:
            index += n
        if not 0 <= index < n:
            raise IndexError('commands ahead: index out of range')
        return float(self._values()[self._start + index])

    def __iter__(self) -> Iterator[float]:
        return iter(self.to_array().tolist())

    def to_array(self) -> FloatArray:
        """Return every value at once, as an array [V]."""
        return self._values()[self._start:self._stop].copy()

    def values_into(self, out: FloatArray) -> None:
        """Write every value into ``out`` (an array of ``len(self)``) [V]."""
        out[:] = self._values()[self._start:self._stop]

    def clamped(self, low_v: float, high_v: float) -> AheadRow:
        """Return the same commands clipped to ``[low_v, high_v]`` too [V] (a view)."""
        return AheadRow(self._pending, self._row, self._stop, self._finite, self._last,
                        start=self._start, clamps=self._clamps + ((low_v, high_v),))

    def finite(self) -> bool:
        """Return whether every value is finite (decided from what they are computed from)."""
        return self._finite


class AxesAhead:
    """
    The commands ahead of the axes' controllers together, as one (axes, count) array [V].

    A feed-forward with a whole period's tables (``ahead_plan``) is predicted with the other
    such axes in one set of array operations over their tables stacked into rows (each axis'
    own values, the same operations on each value as its own ``predict``: the rows equal it
    bit for bit); any other axis through its own ``predict(count)``, and a controller without
    one holds its last command. :meth:`rows` gives the same values computed when read.

    Parameters
    ----------
    controllers : sequence of Controller
        One per axis.

    """

    def __init__(self, controllers: Sequence[Any]) -> None:
        self._ctrls = list(controllers)
        self.n = len(self._ctrls)
        self._plans = [getattr(c, 'ahead_plan', None) for c in self._ctrls]
        self._own = [getattr(c, 'predict', None) for c in self._ctrls]
        limits = [getattr(c, 'output_limits_v', (-math.inf, math.inf)) for c in self._ctrls]
        self._low = np.array([[lo] for lo, _ in limits], dtype=np.float64)
        self._high = np.array([[hi] for _, hi in limits], dtype=np.float64)
        # the stacked tables: (x_d, x_d', w) x axes x samples, and which tables each row holds
        self._stack = np.zeros((3, self.n, 0))
        self._held: list[tuple[Any, ...] | None] = [None] * self.n
        self._steps = np.arange(1)
        self._row_index: dict[int, IntArray] = {}
        # per axis: the tables last checked for finite values, and the verdict
        self._checked: list[tuple[Any, bool]] = [((), True)] * self.n

    def predict(self, count: int, last_v: Sequence[float]) -> FloatArray:
        """
        Return each axis' ``count`` commands after its last step [V], one row per axis.

        Parameters
        ----------
        count : int
            Commands ahead per axis.
        last_v : sequence of float
            Each axis' last command [V] (held by a controller without a prediction).

        Returns
        -------
        ndarray
            (axes, count).

        """
        own = self._own
        if self.n == 1:  # one axis: its own prediction, as a row
            pred = own[0]
            return np.asarray(pred(count), dtype=np.float64)[None] if pred is not None \
                else np.full((1, count), last_v[0])
        out = np.empty((self.n, count), dtype=np.float64)
        rows: list[int] = []
        plans: list[tuple[Any, ...]] = []
        if self.n > 1:
            for r, plan in enumerate(self._plans):
                p = plan(count) if plan is not None else None
                if p is not None:
                    rows.append(r)
                    plans.append(p)
        if len(rows) == self.n:
            return self._batch(count, rows, plans)
        if len(rows) < 2:  # one axis alone costs less through its own predict
            rows = []
        for r in range(self.n):
            if r not in rows:
                pred = own[r]
                out[r] = pred(count) if pred is not None else last_v[r]
        if rows:
            out[rows] = self._batch(count, rows, plans)
        return out

    def rows(self, count: int, last_v: Sequence[float]) -> list[Any]:
        """
        Return each axis' ``count`` commands after its last step [V], computed when read.

        The values of :meth:`predict`, row for row: an axis with a whole period's tables as
        an :class:`AheadRow` (the axes' batch computed when one of them is first read, from
        what this sample left: a backend reads them only for the samples the host misses),
        any other axis' row as an array.

        Parameters
        ----------
        count : int
            Commands ahead per axis.
        last_v : sequence of float
            Each axis' last command [V].

        Returns
        -------
        list
            One sequence of ``count`` values per axis.

        """
        out: list[Any] = []
        rows: list[int] = []
        plans: list[tuple[Any, ...]] = []
        secants: list[Callable[[float], float]] = []
        finite: list[bool] = []
        ctrls = self._ctrls
        for r, plan in enumerate(self._plans):
            p = plan(count) if plan is not None else None
            if p is None:
                pred = self._own[r]
                out.append(np.asarray(pred(count), dtype=np.float64) if pred is not None
                           else np.full(count, last_v[r]))
                continue
            c = ctrls[r]
            tables = p[0]
            held, ok = self._checked[r]
            if held is not tables:
                ok = self._tables_finite(r, tables)
            a, b, u = p[2], p[3], p[4]
            # x - x is 0 for a finite x, NaN otherwise
            ok = ok and (a - a) + (b - b) + (u - u) == 0.0
            if c.hysteresis_inverse is None:
                secants.append(c.ahead_secant)  # 1 whatever the state
            else:
                at = _SecantAt(c, u)
                secants.append(at)
                ok = ok and at.finite()
            rows.append(r)
            plans.append(p)
            finite.append(ok)
            out.append(r)
        if rows:
            pending = _Pending(self, count, rows, plans, secants)
            for q, (r, ok, p) in enumerate(zip(rows, finite, plans)):
                out[r] = AheadRow(pending, q, count, ok, p[4])
        return out

    def _tables_finite(self, r: int, tables: tuple[FloatArray, ...]) -> bool:
        """Return whether axis ``r``'s tables are finite (checked once per tables)."""
        held, ok = self._checked[r]
        if held is not tables:
            ok = bool(all(np.isfinite(t).all() for t in tables))
            self._checked[r] = (tables, ok)
        return ok

    def _tables(self, rows: list[int], plans: list[tuple[Any, ...]]) -> FloatArray:
        """Return the stacked tables, rows copied in where an axis' tables were replaced."""
        stack = self._stack
        width = max(len(p[0][0]) for p in plans)
        if width > stack.shape[2]:
            stack = self._stack = np.zeros((3, self.n, width))
            self._held = [None] * self.n
        held = self._held
        for r, p in zip(rows, plans):
            tables = p[0]
            if held[r] is not tables:
                size = len(tables[0])
                for q in range(3):
                    stack[q, r, :size] = tables[q]
                held[r] = tables
        return stack

    def _batch(self, count: int, rows: list[int], plans: list[tuple[Any, ...]]) -> FloatArray:
        """Return :meth:`FeedForwardController.predict` of the axes ``rows`` together."""
        stack = self._tables(rows, plans)
        width = stack.shape[2]
        if self._steps.size != count + 1:
            self._steps = np.arange(count + 1)
        # each row's index and the count after it, in the rows' flat tables
        at = np.take(stack.reshape(3, self.n * width),
                     np.array([r * width + p[1] for r, p in zip(rows, plans)])[:, None]
                     + self._steps, axis=1)
        ctrls = self._ctrls
        return self._combine(at, rows, plans, [ctrls[r].ahead_secant for r in rows])

    def _evaluate(self, count: int, rows: list[int], plans: list[tuple[Any, ...]],
                  secants: list[Callable[[float], float]]) -> FloatArray:
        """Return :meth:`_batch` of a past sample, from its own tables (not the stack)."""
        at = np.empty((3, len(rows), count + 1), dtype=np.float64)
        for q, p in enumerate(plans):
            i = p[1]
            for t in range(3):
                at[t, q] = p[0][t][i:i + count + 1]
        return self._combine(at, rows, plans, secants)

    def _combine(self, at: FloatArray, rows: list[int], plans: list[tuple[Any, ...]],
                 secants: list[Callable[[float], float]]) -> FloatArray:
        """Return the commands ahead from the tables read at each index and after it."""
        change = at[:, :, 1:] - at[:, :, :1]
        coef = np.array([p[2:] for p in plans])
        # (x - x_k) a + b (x' - x'_k) + (w - w_k), in the order predict sums them
        ahead: FloatArray = change[0] * coef[:, 0:1]
        ahead += coef[:, 1:2] * change[1]
        ahead += change[2]
        m = len(rows)
        if m not in self._row_index:
            self._row_index[m] = np.arange(m)
        peak = ahead[self._row_index[m], np.argmax(np.abs(ahead), axis=1)].tolist()
        ahead *= np.array([[secant(du)] for secant, du in zip(secants, peak)])
        ahead += coef[:, 2:3]
        every = m == self.n
        np.minimum(ahead, self._high if every else self._high[rows], out=ahead)
        np.maximum(ahead, self._low if every else self._low[rows], out=ahead)
        return ahead
