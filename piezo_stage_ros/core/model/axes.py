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
A stage of one to three named axes (x, y, z) with cross-coupling, stepped one sample at a time.

Each axis is the one-axis stage of :mod:`piezo_stage_ros.core.model.stage` with its own
parameters: DAC, amplifier clamp, hysteresis P(.), linear plant G_i, sensor, noise, ADC. On top
of them, the drive of axis i moves every other axis j through a coupling path::

    d_ij(s) = kappa_ij M_ij(s) x_i(s),   M_ij(s) = w^2 / (s^2 + 2 zeta w s + w^2)

x_i is the driving axis' own position (its hysteresis and plant G_i), kappa_ij the coupling gain
(position of j per position of i at DC) and M_ij a second-order mode of unit DC gain at the
path's resonance w = 2 pi f_ij (f_ij = 0: a static gain, M = 1). The true position of axis j is
x_j + sum_i d_ij; the sensor of axis j may read the other axes' true positions too (sensor
cross-talk s_ij) before its noise and ADC.

Exact under zero-order hold, as the one-axis stage: the augmented linear system of a driving axis
and its modes, [[A_i, 0], [E, A_m]] with input w_i, is discretised once with the matrix
exponential. Its block for the axis' own states is the one-axis stage's own (the system is block
triangular), so the axis' own motion is computed by the one-axis stage itself and the modes
take x_i(t_k) and the held w_i from it: each axis' own position is the one-axis stage's, bit for
bit, whatever the coupling; with no path into an axis and no cross-talk, its measurement is too
(the same noise stream, seeded by the axis' own ``seed``, and the same converters).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
import math
from typing import Any, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.model.stage import _Converter, _dac_converter, Stage, StageParams
from scipy.linalg import expm

__all__ = ['AXIS_NAMES', 'AxesStage', 'AxesStageParams', 'CouplingParams', 'CouplingPath',
           'FAMILY_COUPLING', 'check_axis_names', 'coupling_paths', 'sample_axes_family',
           'state_response']

#: The axis names a stage may have, in their canonical order.
AXIS_NAMES = ('x', 'y', 'z')

#: Damping of a coupling mode when none is given [-].
DEFAULT_DAMPING = 0.05

#: Sensor noise values drawn from an axis' generator at a time.
NOISE_BLOCK = 256


def check_axis_names(names: Sequence[Any], where: str = 'axes.names') -> tuple[str, ...]:
    """
    Return the axis names as a tuple, refusing an unknown name, a repeated one or none.

    Parameters
    ----------
    names : sequence of str
        One to three of ``x``, ``y``, ``z``, each at most once.
    where : str
        Parameter name used in the error.

    Returns
    -------
    tuple of str

    Raises
    ------
    ParameterError
        Naming the bad value and what is allowed.

    """
    allowed = f'1 to 3 distinct names out of {list(AXIS_NAMES)}'
    if isinstance(names, str) or not hasattr(names, '__iter__'):
        raise ParameterError(where, names, allowed, 'is not a list of names')
    out = tuple(names)
    if not 1 <= len(out) <= len(AXIS_NAMES):
        raise ParameterError(where, list(out), allowed, f'has {len(out)} names')
    for name in out:
        if name not in AXIS_NAMES:
            raise ParameterError(where, name, allowed, 'is not an axis name')
    for k, name in enumerate(out):
        if name in out[:k]:
            raise ParameterError(where, list(out), allowed, f'names axis {name!r} twice')
    return out


def _matrix(name: str, values: Sequence[Any], n: int, low: float, high: float,
            *, zero_diagonal: bool, default: float) -> FloatArray:
    """Return an n x n matrix from its row-major values (empty: ``default`` off the diagonal)."""
    shape = (f'an {n} x {n} matrix as {n * n} values, row-major (row i: the driving axis, '
             f'column j: the moved axis)')
    if isinstance(values, (str, bytes)) or not hasattr(values, '__iter__'):
        raise ParameterError(name, values, shape, 'is not a list')
    items = list(values)
    if not items:
        m = np.full((n, n), default)
        np.fill_diagonal(m, 0.0)
        return m
    if len(items) != n * n:
        raise ParameterError(name, items, shape, f'has {len(items)} values')
    out = np.empty(n * n)
    for k, v in enumerate(items):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
            raise ParameterError(name, items, shape + ' of numbers',
                                 f'has {v!r} at index {k}, not a number')
        f = float(v)
        if not math.isfinite(f) or not low <= f <= high:
            raise ParameterError(name, items, f'{shape}, each finite in [{low:g}, {high:g}]',
                                 f'has {f!r} at row {k // n}, column {k % n}')
        out[k] = f
    m = out.reshape(n, n)
    if zero_diagonal and np.any(np.diag(m) != 0.0):
        k = int(np.flatnonzero(np.diag(m) != 0.0)[0])
        raise ParameterError(name, items, f'{shape} with zeros on the diagonal (an axis '
                             'couples to the others, not to itself)',
                             f'has {float(m[k, k])!r} at row {k}, column {k}')
    return m


@dataclass(frozen=True)
class CouplingParams:
    """
    Cross-coupling between the axes: n x n matrices given row-major (row i drives column j).

    An empty matrix is all zeros (damping: :data:`DEFAULT_DAMPING`); the diagonal of the gain and
    of the cross-talk must be zero. Validated against the number of axes by
    :class:`AxesStageParams`.

    Attributes
    ----------
    gain : tuple of float
        kappa_ij: position of axis j per position of axis i at DC [m/m], each in [-1, 1].
    resonance_hz : tuple of float
        f_ij of the path's mode [Hz], each in [0, fs/2) (0: a static gain, no mode).
    damping : tuple of float
        zeta_ij of the mode [-], each in (0, 10].
    sensor_crosstalk : tuple of float
        s_ij: what the sensor of axis j reads of axis i's true position [m/m], each in [-1, 1].

    """

    gain: tuple[float, ...] = ()
    resonance_hz: tuple[float, ...] = ()
    damping: tuple[float, ...] = ()
    sensor_crosstalk: tuple[float, ...] = ()

    def matrices(self, n: int, sample_rate_hz: float
                 ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """
        Return (gain, resonance_hz, damping, sensor_crosstalk) as validated n x n arrays.

        Raises
        ------
        ParameterError
            A matrix of the wrong size, a non-finite or out-of-range value, a non-zero
            diagonal; the message names the parameter, the value and the allowed shape/range.

        """
        nyquist = sample_rate_hz / 2.0
        gain = _matrix('coupling.gain', self.gain, n, -1.0, 1.0, zero_diagonal=True,
                       default=0.0)
        res = _matrix('coupling.resonance_hz', self.resonance_hz, n, 0.0, nyquist,
                      zero_diagonal=False, default=0.0)
        if np.any(res >= nyquist):
            k = int(np.flatnonzero(res.ravel() >= nyquist)[0])
            raise ParameterError('coupling.resonance_hz', list(self.resonance_hz),
                                 f'each in [0, {nyquist:g}) Hz (below the Nyquist frequency)',
                                 f'has {float(res.ravel()[k])!r} at row {k // n}, '
                                 f'column {k % n}')
        damp = _matrix('coupling.damping', self.damping, n, 0.0, 10.0, zero_diagonal=False,
                       default=DEFAULT_DAMPING)
        np.fill_diagonal(damp, DEFAULT_DAMPING)
        if np.any(damp <= 0.0):
            k = int(np.flatnonzero(damp.ravel() <= 0.0)[0])
            raise ParameterError('coupling.damping', list(self.damping), 'each in (0, 10]',
                                 f'has {float(damp.ravel()[k])!r} at row {k // n}, '
                                 f'column {k % n}')
        talk = _matrix('coupling.sensor_crosstalk', self.sensor_crosstalk, n, -1.0, 1.0,
                       zero_diagonal=True, default=0.0)
        return gain, res, damp, talk


@dataclass(frozen=True)
class AxesStageParams:
    """
    A stage of 1-3 named axes: one :class:`StageParams` each and the coupling between them.

    Attributes
    ----------
    names : tuple of str
        The axes, e.g. ``('x', 'y')`` (:func:`check_axis_names`).
    axes : tuple of StageParams
        One per name, in the same order; all at the same sample rate.
    coupling : CouplingParams
        Cross-coupling (validated here against the number of axes).

    """

    names: tuple[str, ...] = ('x',)
    axes: tuple[StageParams, ...] = (StageParams(),)
    coupling: CouplingParams = field(default_factory=CouplingParams)

    def __post_init__(self) -> None:
        object.__setattr__(self, 'names', check_axis_names(self.names))
        object.__setattr__(self, 'axes', tuple(self.axes))
        if len(self.axes) != len(self.names):
            raise ParameterError('axes', len(self.axes), f'{len(self.names)} stage parameter '
                                 f'sets, one per axis {list(self.names)}')
        for name, p in zip(self.names, self.axes):
            if not isinstance(p, StageParams):
                raise ParameterError(f'axes.{name}', p, 'a StageParams', 'has the wrong type')
            if p.sample_rate_hz != self.axes[0].sample_rate_hz:
                raise ParameterError(f'axes.{name}.sample_rate_hz', p.sample_rate_hz,
                                     f'{self.axes[0].sample_rate_hz:g} Hz, the rate of axis '
                                     f'{self.names[0]!r}', 'differs between the axes')
        gain, _, _, _ = self.matrices()
        for i, name in enumerate(self.names):
            if np.any(gain[i] != 0.0) and self.axes[i].plant.model == 'electromechanical':
                raise ParameterError(f'axes.{name}.plant.model', 'electromechanical',
                                     "'third_order' or 'reduced' on a driving axis",
                                     'drives a coupling path: its hysteresis acts inside the '
                                     'plant, so the path would not be exact under ZOH')

    @property
    def n(self) -> int:
        """Return the number of axes."""
        return len(self.names)

    @property
    def sample_time_s(self) -> float:
        """Return the sample period [s]."""
        return self.axes[0].sample_time_s

    def matrices(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Return the coupling matrices (:meth:`CouplingParams.matrices`) for these axes."""
        return self.coupling.matrices(self.n, self.axes[0].sample_rate_hz)

    def index(self, name: str) -> int:
        """Return the position of axis ``name``, refusing a name the stage does not have."""
        if name not in self.names:
            raise ParameterError('axis', name, f'one of {list(self.names)}',
                                 'is not an axis of this stage')
        return self.names.index(name)


@dataclass(frozen=True)
class CouplingPath:
    """
    The coupling paths driven by one axis, discretised exactly under ZOH.

    States: two per path with a mode (scaled position and velocity of the mode), stepped
    z <- ad z + f x_i + h w_i with the driving axis' own state x_i at the start of the sample
    and its held hysteresis output w_i; a static path reads the driving axis' position.

    Attributes
    ----------
    source : int
        The driving axis.
    targets : tuple of int
        The moved axis of each path with a mode.
    gains : tuple of float
        kappa of each path with a mode times the mode state's scale (metres per unit state).
    ad, f, h : ndarray
        The discrete matrices (2 m x 2 m, 2 m x order, 2 m).
    static : tuple of (int, float)
        (moved axis, kappa) of each path without a mode.
    c : ndarray
        The driving axis' output row (its own position from its state) [m].
    scale : float
        Metres per unit of a mode's position state (the driving axis' DC gain).
    a_cont, b_cont : ndarray
        The continuous augmented system (own states, then the modes) and its input column.
    ad_full, bd_full : ndarray
        Its exact ZOH discretisation.
    sample_time_s : float
        T [s].

    """

    source: int
    targets: tuple[int, ...]
    gains: tuple[float, ...]
    ad: FloatArray
    f: FloatArray
    h: FloatArray
    static: tuple[tuple[int, float], ...]
    c: FloatArray
    scale: float
    a_cont: FloatArray
    b_cont: FloatArray
    ad_full: FloatArray
    bd_full: FloatArray
    sample_time_s: float

    def frequency_response(self, target: int, omega_rad_s: Any, *, discrete: bool
                           ) -> Any:
        """
        Return the response from w_i [V] to the displacement of axis ``target`` [m/V].

        Parameters
        ----------
        target : int
            Moved axis (one of :attr:`targets` or of :attr:`static`).
        omega_rad_s : array_like
            Angular frequencies [rad/s].
        discrete : bool
            The discretised model at z = exp(j omega T) (True), or the continuous one at
            s = j omega (False).

        Returns
        -------
        ndarray of complex

        """
        w = np.atleast_1d(np.asarray(omega_rad_s, dtype=np.float64))
        order = self.c.size
        m = self.ad.shape[0]
        # the whole augmented system: own states, then the modes
        out_row = np.zeros(order + m)
        for (j, kappa) in self.static:
            if j == target:
                out_row[:order] += kappa * self.c
        for p, j in enumerate(self.targets):
            if j == target:
                out_row[order + 2 * p] += self.gains[p]
        if discrete:
            a, b = self.ad_full, self.bd_full
            pts = np.exp(1j * w * self.sample_time_s)
        else:
            a, b = self.a_cont, self.b_cont
            pts = 1j * w
        return state_response(a, b, pts) @ out_row


def state_response(a: FloatArray, b: FloatArray, points: Any) -> Any:
    """
    Return (pI - A)^-1 b at every point p: the states' response to the input.

    Parameters
    ----------
    a : ndarray, shape (n, n)
        State matrix (discrete: Ad at p = z; continuous: A at p = s).
    b : ndarray, shape (n,)
        Input column.
    points : array_like of complex, shape (K,)
        Points of the z- or s-plane.

    Returns
    -------
    ndarray of complex, shape (K, n)

    """
    size = a.shape[0]
    pts = np.asarray(points, dtype=np.complex128).ravel()
    lhs = pts[:, None, None] * np.eye(size)[None] - a[None]
    rhs = np.broadcast_to(np.asarray(b, dtype=np.complex128)[None, :, None],
                          (pts.size, size, 1))
    return np.linalg.solve(lhs, rhs)[..., 0]


def coupling_paths(params: AxesStageParams) -> list[CouplingPath]:
    """
    Return the discretised coupling paths of each driving axis (none for zero coupling).

    Parameters
    ----------
    params : AxesStageParams
        Axes and coupling.

    Returns
    -------
    list of CouplingPath
        One per axis that drives at least one path, in axis order.

    """
    gain, res, damp, _ = params.matrices()
    t = params.sample_time_s
    out: list[CouplingPath] = []
    for i, p in enumerate(params.axes):
        if not np.any(gain[i] != 0.0):
            continue
        stage = Stage(p)
        core = stage._core
        plant = core.plant
        order = plant.order
        a_i, b_i, c_i = plant.a, plant.b[:, :1], plant.c
        # scale the mode states like the plant's: position in volts of w (dc gain), velocity
        # times w, so that the matrix exponential sees entries of the same order
        scale = core.dc_gain_m_per_v
        modes = [(j, float(res[i, j]), float(damp[i, j])) for j in range(params.n)
                 if gain[i, j] != 0.0 and res[i, j] > 0.0]
        static = tuple((j, float(gain[i, j])) for j in range(params.n)
                       if gain[i, j] != 0.0 and res[i, j] == 0.0)
        m = 2 * len(modes)
        a = np.zeros((order + m, order + m))
        a[:order, :order] = a_i
        for k, (_, f_hz, zeta) in enumerate(modes):
            wn = 2.0 * math.pi * f_hz
            r = order + 2 * k
            # q' = wn v, v' = -wn q - 2 zeta wn v + wn (c x) / scale
            a[r, r + 1] = wn
            a[r + 1, r] = -wn
            a[r + 1, r + 1] = -2.0 * zeta * wn
            a[r + 1, :order] = wn * c_i / scale
        b = np.zeros((order + m, 1))
        b[:order] = b_i
        aug = np.zeros((order + m + 1, order + m + 1))
        aug[:order + m, :order + m] = a
        aug[:order + m, order + m:] = b
        phi = expm(aug * t)
        ad_full = phi[:order + m, :order + m].copy()
        bd_full = phi[:order + m, order + m].copy()
        gains = tuple(float(gain[i, j]) * scale for j, _, _ in modes)
        path = CouplingPath(
            source=i, targets=tuple(j for j, _, _ in modes), gains=gains,
            ad=ad_full[order:, order:].copy(), f=ad_full[order:, :order].copy(),
            h=bd_full[order:].copy(), static=static, c=np.asarray(core.discrete.c).copy(),
            scale=scale, a_cont=a, b_cont=b[:, 0].copy(), ad_full=ad_full, bd_full=bd_full,
            sample_time_s=t)
        out.append(path)
    return out


class _Axis:
    """One axis of :class:`AxesStage`: the one-axis stage without its sensor, and the sensor."""

    def __init__(self, params: StageParams) -> None:
        chain = params.chain
        # the one-axis stage computes the true position; the DAC ahead of it and the noise and
        # ADC after it are applied here, with its very constants, so that a coupled
        # displacement can be added before the sensor
        inner = params.replace(chain=chain.replace(quantize=False, sensor_noise_std_m=0.0))
        self.stage = Stage(inner)
        self.kernel = self.stage._kernel
        self.dac: _Converter | None = _dac_converter(chain) if chain.quantize else None
        self.adc: _Converter | None = _Converter.for_range(
            chain.adc_bits, chain.adc_min_v, chain.adc_max_v, chain.sensor_gain_v_per_m,
            chain.sensor_offset_m) if chain.quantize else None
        self.noise = chain.sensor_noise_std_m
        self.rng = np.random.default_rng(params.seed)
        # the noise drawn a block at a time: a generator gives the same numbers in a block as
        # one by one, and a call per sample costs more than the sample's other sensor work
        self._normals: list[float] = []
        self._drawn = 0

    def sense(self, position_m: float) -> float:
        """Return what the sensor and the ADC give for a true position (as Stage.measure)."""
        pos = position_m
        if self.noise > 0.0:
            i = self._drawn
            if i == len(self._normals):
                self._normals = self.rng.standard_normal(NOISE_BLOCK).tolist()
                i = 0
            self._drawn = i + 1
            pos += self.noise * self._normals[i]
        adc = self.adc
        return adc.scalar(pos) if adc is not None else pos


class AxesStage:
    """
    A simulated stage of 1-3 coupled axes, stepped one sample at a time.

    Parameters
    ----------
    params : AxesStageParams
        The axes and their coupling.

    Notes
    -----
    Per sample: every axis' command goes through its DAC (a non-finite command is passed on and
    gives the axis' safe voltage and a fault, as in the one-axis stage), its own stage steps, the
    coupling modes step on the driving axes' state and held hysteresis output, and each axis'
    sensor reads its true position (plus the cross-talk of the others) with its noise and ADC.

    """

    def __init__(self, params: AxesStageParams) -> None:
        self.params = params
        self.names = params.names
        self.n = params.n
        self._axes = [_Axis(p) for p in params.axes]
        self._paths = coupling_paths(params)
        _, _, _, talk = params.matrices()
        # cross-talk terms into each axis: (source, s_ij)
        self._talk = [[(i, float(talk[i, j])) for i in range(self.n) if talk[i, j] != 0.0]
                      for j in range(self.n)]
        self._coupled = bool(self._paths)
        # the paths with modes (states to step): (index, path, its driving axis' state)
        self._moving = [(k, path, self._axes[path.source].kernel.get)
                        for k, path in enumerate(self._paths) if path.targets]
        # what each path adds to the true positions, in the order the sum takes it: its
        # modes' (moved axis, gain, state index), then its static (moved axis, kappa)
        self._adds = [(k, path.source,
                       [(j, path.gains[p], 2 * p) for p, j in enumerate(path.targets)],
                       list(path.static)) for k, path in enumerate(self._paths)]
        self._z: list[FloatArray] = []
        self._x_prev: list[FloatArray] = []
        self._true: list[float] = [0.0] * self.n
        self.reset()

    @property
    def sample_time_s(self) -> float:
        """Return the sample period [s]."""
        return self.params.sample_time_s

    @property
    def faults(self) -> tuple[int, ...]:
        """Return the non-finite commands replaced by the safe voltage, per axis."""
        return tuple(a.stage.faults for a in self._axes)

    @property
    def paths(self) -> list[CouplingPath]:
        """Return the discretised coupling paths (see :func:`coupling_paths`)."""
        return list(self._paths)

    def read_positions_m(self) -> list[float]:
        """Return the true positions now [m], one per axis (coupling in, no sensor)."""
        return list(self._true)

    def reset(self, positions_m: Sequence[float | None] | None = None) -> list[float]:
        """
        Put every axis at rest and return the measured positions there.

        Parameters
        ----------
        positions_m : sequence of float or None, optional
            Each axis' own rest position [m] (None: its ``initial_position_m``). The coupled
            axes rest where the static coupling puts them: own position plus kappa_ij times
            each driving axis' position.

        Returns
        -------
        list of float
            Measured positions y_0 [m].

        """
        given = [None] * self.n if positions_m is None else list(positions_m)
        if len(given) != self.n:
            raise ParameterError('positions_m', given, f'{self.n} positions, one per axis')
        own = [a.stage.reset(p) for a, p in zip(self._axes, given)]
        self._z = []
        self._x_prev = []
        for path in self._paths:
            x = np.asarray(self._axes[path.source].kernel.get().x, dtype=np.float64)
            self._x_prev.append(x)
            # at rest each mode's position equals its input (unit DC gain), velocity zero
            z = np.zeros(path.ad.shape[0])
            pos_i = own[path.source]
            z[0::2] = pos_i / path.scale
            self._z.append(z)
        return self._measure(own)

    def _measure(self, own: list[float]) -> list[float]:
        true = list(own)
        states = self._z
        for k, source, modes, static in self._adds:
            if modes:
                z = states[k].tolist()
                for j, gain, q in modes:
                    true[j] += gain * z[q]
            for j, kappa in static:
                true[j] += kappa * own[source]
        self._true = true
        out = []
        for j, axis in enumerate(self._axes):
            pos = true[j]
            for i, s in self._talk[j]:
                pos += s * true[i]
            out.append(axis.sense(pos))
        return out

    def step(self, commands_v: Sequence[float]) -> list[float]:
        """
        Hold one command per axis over one sample and return the measured positions.

        Parameters
        ----------
        commands_v : sequence of float
            Amplifier input commands [V], one per axis.

        Returns
        -------
        list of float
            Measured positions at the end of the sample [m].

        """
        own = []
        for axis, u in zip(self._axes, commands_v):
            dac = axis.dac
            if dac is not None and math.isfinite(u):
                u = dac.scalar(u)
            own.append(axis.stage.step(u))
        # a path without modes has no state: its static gains read the positions alone
        z, x_prev = self._z, self._x_prev
        for k, path, get in self._moving:
            state = get()
            z[k] = path.ad @ z[k] + path.f @ x_prev[k] + path.h * state.w
            x_prev[k] = np.asarray(state.x, dtype=np.float64)
        return self._measure(own)

    def run_open_loop(self, commands_v: Any) -> FloatArray:
        """
        Apply a sequence of commands, one row per sample, and return the measured positions.

        Parameters
        ----------
        commands_v : array_like, shape (samples, n)
            Commands [V].

        Returns
        -------
        ndarray, shape (samples, n)
            y_1 ... y_N [m].

        """
        cmds = np.asarray(commands_v, dtype=np.float64).reshape(-1, self.n)
        return np.array([self.step(row) for row in cmds.tolist()], dtype=np.float64).reshape(
            -1, self.n)


#: Range of the coupling gains of :func:`sample_axes_family` [m/m] (magnitude).
FAMILY_COUPLING = (0.005, 0.05)


def sample_axes_family(design: AxesStageParams, n: int, seed: int = 0,
                       coupling: tuple[float, float] = FAMILY_COUPLING
                       ) -> tuple[tuple[str, AxesStageParams], ...]:
    """
    Return ``n`` multi-axis stages unlike the design: each axis its own family member.

    Every axis of a member is drawn independently from the one-axis stage family
    (:func:`~piezo_stage_ros.core.model.family.sample_family`: gain, resonance, damping, lag,
    hysteresis, noise), and every coupling path of the design gets a gain drawn uniformly in
    ``coupling`` (magnitude; the design's sign, resonance and damping kept).

    Parameters
    ----------
    design : AxesStageParams
        The configured stage (third-order axes).
    n : int
        Members, >= 0.
    seed : int
        Seed of the draw (the same seed gives the same members).
    coupling : (float, float)
        Range of the coupling gains' magnitude [m/m], within [0, 1].

    Returns
    -------
    tuple of (str, AxesStageParams)
        A description of each member (its axes' variations and coupling) and the stage.

    """
    from piezo_stage_ros.core.model.family import member_params, sample_family

    lo, hi = coupling
    if not (0.0 <= lo <= hi <= 1.0):
        raise ParameterError('coupling', list(coupling), '0 <= low <= high <= 1')
    axes = sample_family(n * design.n, seed)
    rng = np.random.default_rng([seed, 1])
    gain, _, _, _ = design.matrices()
    paths = np.flatnonzero(gain.ravel() != 0.0)
    out = []
    for k in range(n):
        members = axes[k * design.n:(k + 1) * design.n]
        stages = tuple(member_params(p, m) for p, m in zip(design.axes, members))
        g = gain.ravel().copy()
        g[paths] = np.sign(g[paths]) * rng.uniform(lo, hi, paths.size)
        stage = AxesStageParams(names=design.names, axes=stages, coupling=dataclasses.replace(
            design.coupling, gain=tuple(float(v) for v in g)))
        text = '; '.join(f'{name}: {m.describe()}' for name, m in zip(design.names, members))
        text += '; coupling ' + ', '.join(f'{design.names[p // design.n]}->'
                                          f'{design.names[p % design.n]} {g[p] * 100:.2f} %'
                                          for p in paths)
        out.append((text, stage))
    return tuple(out)
