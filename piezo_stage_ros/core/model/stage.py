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
The stage: hysteresis + linear plant + signal chain, stepped one sample at a time.

One sample k of the loop (see :mod:`piezo_stage_ros.core.contracts.interfaces`)::

    u_k --DAC (16 bit)--> clamp to amplifier range --> v_k --P(.)--> w_k --G (ZOH)--> x(t_k+1)
    x(t_k+1) --sensor K_PSCM (+ noise)--> ADC (16 bit) --> y_k+1 / K_PSCM = measured position

The signal chain is that of sections II and V of the paper: amplifier input -2 ... 10 V (gain 10
inside the plant), position sensor module K_PSCM = 10 V / 38 um, 16-bit DAC and ADC over +-10 V
(dSPACE DS1104), 10 kHz. With the general electromechanical model the hysteresis acts on the
charge, H(q) of eq. (2), inside the plant (see :class:`Stage`).

:class:`Stage` is the scalar, allocation-free path used by the closed loop and the nodes;
:class:`StageBatch` steps n independent stages at once with numpy (sweeps, benchmarks). Both use
the same discretized matrices and the same hysteresis objects.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import functools
import math
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.params import group, param, Params
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.model.hysteresis import (
    BacklashLike,
    HysteresisModel,
    HysteresisParams,
    make_hysteresis,
    NoHysteresis,
)
from piezo_stage_ros.core.model.linear import (
    DiscreteLinearPlant,
    electromechanical_plant,
    ElectromechanicalParams,
    LinearPlant,
    reduced_plant,
    ReducedParams,
    third_order_plant,
    ThirdOrderParams,
)

__all__ = ['FusedConstants', 'PlantParams', 'SignalChainParams', 'Stage', 'StageBatch',
           'StageParams', 'amplifier_input', 'fused_constants', 'linear_plant', 'quantize']


#: K_PSCM of eq. (15): 10 V over the 38 um travel, in V/m.
SENSOR_GAIN_V_PER_M = 10.0 / 38e-6


@dataclass(frozen=True)
class SignalChainParams(Params):
    """Amplifier, converters and sensor of the paper's set-up (sections II and V)."""

    amplifier_min_v: float = param(-2.0, unit='V', description='Lowest amplifier input voltage.')
    amplifier_max_v: float = param(10.0, unit='V',
                                   description='Highest amplifier input voltage.')
    safe_voltage_v: float = param(0.0, unit='V', description='Voltage applied on a non-finite '
                                  'command (and by bridges on faults).')
    sensor_gain_v_per_m: float = param(SENSOR_GAIN_V_PER_M, unit='V/m',
                                       description='Position sensor module gain K_PSCM, '
                                       'eq. (15).', low=0.0, low_open=True)
    sensor_offset_m: float = param(0.0, unit='m', description='Position x_0 at which the sensor '
                                   'reads 0 V, eq. (15).')
    sensor_noise_std_m: float = param(0.0, unit='m', description='Standard deviation of white '
                                      'sensor noise, in position units.', low=0.0)
    quantize: bool = param(True, unit='-', description='Model DAC and ADC quantization.')
    dac_bits: int = param(16, unit='bit', description='DAC resolution.', low=1, high=32)
    dac_min_v: float = param(-10.0, unit='V', description='DAC output range, low end.')
    dac_max_v: float = param(10.0, unit='V', description='DAC output range, high end.')
    adc_bits: int = param(16, unit='bit', description='ADC resolution.', low=1, high=32)
    adc_min_v: float = param(-10.0, unit='V', description='ADC input range, low end.')
    adc_max_v: float = param(10.0, unit='V', description='ADC input range, high end.')

    def _check(self) -> None:
        for lo, hi in (('amplifier_min_v', 'amplifier_max_v'), ('dac_min_v', 'dac_max_v'),
                       ('adc_min_v', 'adc_max_v')):
            if not getattr(self, lo) < getattr(self, hi):
                raise ParameterError(hi, getattr(self, hi), f'> {lo} = {getattr(self, lo):g}',
                                     'is not above the low end of its range')
        if not self.amplifier_min_v <= self.safe_voltage_v <= self.amplifier_max_v:
            raise ParameterError('safe_voltage_v', self.safe_voltage_v,
                                 f'[{self.amplifier_min_v:g}, {self.amplifier_max_v:g}]',
                                 'is outside the amplifier range')

    @property
    def dac_lsb_v(self) -> float:
        """Return one DAC step [V]."""
        return (self.dac_max_v - self.dac_min_v) / 2.0 ** self.dac_bits

    @property
    def adc_lsb_m(self) -> float:
        """Return one ADC step in position units [m] (1.16 nm for the defaults)."""
        return (self.adc_max_v - self.adc_min_v) / 2.0 ** self.adc_bits / self.sensor_gain_v_per_m


@dataclass(frozen=True)
class PlantParams(Params):
    """Choice of linear model and the parameters of each."""

    model: str = param('third_order', unit='-', description='Linear model of the stage: general '
                       'eqs. (11)-(12), third-order eq. (17) or reduced eq. (25).',
                       choices=('electromechanical', 'third_order', 'reduced'), read_only=True)
    electromechanical: ElectromechanicalParams = group(ElectromechanicalParams, 'eqs. (11)-(12)')
    third_order: ThirdOrderParams = group(ThirdOrderParams, 'eq. (17), values eq. (20)')
    reduced: ReducedParams = group(ReducedParams, 'eq. (25)')
    substeps: int = param(8, unit='-', description='Sub-steps per sample for the hysteresis '
                          'H(q) inside the general model (electromechanical only).', low=1,
                          high=1000)


@dataclass(frozen=True)
class StageParams(Params):
    """Everything that defines a simulated stage; defaults are the paper's P-753.31C."""

    sample_rate_hz: float = param(10000.0, unit='Hz', description='Sample rate of the loop.',
                                  low=1.0, high=1e6, read_only=True)
    initial_position_m: float = param(3.8e-6, unit='m', description='Stage at rest here at the '
                                      'start (the paper starts at 3.8 um).', low=0.0, high=38e-6)
    seed: int = param(0, unit='-', description='Seed of the sensor noise generator.', low=0)
    plant: PlantParams = group(PlantParams, 'linear dynamics')
    hysteresis: HysteresisParams = group(HysteresisParams, 'input hysteresis')
    chain: SignalChainParams = group(SignalChainParams, 'amplifier, sensor, converters')

    @property
    def sample_time_s(self) -> float:
        """Return the sample period [s]."""
        return 1.0 / self.sample_rate_hz


def linear_plant(params: PlantParams) -> LinearPlant:
    """
    Return the linear model ``params.model`` names.

    Parameters
    ----------
    params : PlantParams
        Model choice and the parameters of each model.

    Returns
    -------
    LinearPlant
        For ``'electromechanical'`` the inputs are (v_in, H); otherwise the single input w.

    """
    if params.model == 'electromechanical':
        return electromechanical_plant(params.electromechanical)
    if params.model == 'third_order':
        return third_order_plant(params.third_order)
    return reduced_plant(params.reduced)


@dataclass(frozen=True)
class _Converter:
    """
    An ideal converter from a physical input to a quantized physical output.

    code = clip(floor(value * scale + offset), 0, top); output = code * out_scale + out_offset.
    The DAC maps volts to volts; the ADC path maps position through the sensor gain to a code
    and back to metres. The scalar and the batch stage use the very same constants, so they
    round identically.
    """

    scale: float
    offset: float
    top: float
    out_scale: float
    out_offset: float

    @classmethod
    def for_range(cls, bits: int, low: float, high: float, gain: float = 1.0,
                  zero: float = 0.0) -> _Converter:
        """Return the converter for ``gain * (value - zero)`` V over [low, high], ``bits``."""
        lsb = (high - low) / 2 ** bits
        return cls(scale=gain / lsb, offset=(-gain * zero - low) / lsb + 0.5,
                   top=float(2 ** bits - 1), out_scale=lsb / gain,
                   out_offset=low / gain + zero)

    def scalar(self, value: float) -> float:
        """Quantize one float."""
        code = float(math.floor(value * self.scale + self.offset))
        return min(max(code, 0.0), self.top) * self.out_scale + self.out_offset

    def array(self, value: FloatArray) -> FloatArray:
        """Quantize an array (same arithmetic as :meth:`scalar`)."""
        # np.array: a 0-d input stays an array, which the in-place calls below need
        code = np.array(np.floor(value * self.scale + self.offset), dtype=np.float64)
        # in place: several times faster than np.clip on small arrays
        np.minimum(np.maximum(code, 0.0, out=code), self.top, out=code)
        return np.asarray(code * self.out_scale + self.out_offset, dtype=np.float64)


def quantize(value: Any, bits: int, low: float, high: float) -> Any:
    """
    Round to the nearest converter code and clip to the converter range.

    Parameters
    ----------
    value : float or ndarray
        Voltage [V].
    bits : int
        Resolution.
    low, high : float
        Range [V]; codes 0 ... 2**bits - 1 map to low + code * (high - low) / 2**bits.

    Returns
    -------
    float or ndarray
        The quantized voltage.

    """
    conv = _Converter.for_range(bits, low, high)
    if isinstance(value, float):
        return conv.scalar(value)
    return conv.array(np.asarray(value, dtype=np.float64))


def amplifier_input(command_v: ArrayLike, chain: SignalChainParams) -> FloatArray:
    """
    Return the voltage the amplifier sees for commanded voltages (vectorized).

    Parameters
    ----------
    command_v : array_like
        Commanded amplifier inputs [V].
    chain : SignalChainParams
        DAC resolution and range, amplifier range, safe voltage.

    Returns
    -------
    ndarray
        The commands through the DAC (when ``chain.quantize``) and clamped to the amplifier
        range; a non-finite command gives ``chain.safe_voltage_v`` [V]. This is what
        :class:`Stage` and :class:`StageBatch` apply.

    """
    dac = _dac_converter(chain) if chain.quantize else None
    return _amplifier_input(np.asarray(command_v, dtype=np.float64), chain, dac)


def _amplifier_input(u: FloatArray, chain: SignalChainParams, dac: _Converter | None
                     ) -> FloatArray:
    """Return :func:`amplifier_input` with the DAC converter given (the batch stage has it)."""
    finite = np.isfinite(u)
    all_finite = bool(finite.all())
    if not all_finite:
        u = np.where(finite, u, 0.0)
    if dac is not None:
        u = dac.array(u)
    v = np.minimum(np.maximum(u, chain.amplifier_min_v), chain.amplifier_max_v)
    if not all_finite:
        v = np.where(finite, v, chain.safe_voltage_v)
    return np.asarray(v, dtype=np.float64)


@functools.lru_cache(maxsize=8)
def _dac_converter(chain: SignalChainParams) -> _Converter:
    """Return the DAC converter of a signal chain (cached: the batch stage asks every step)."""
    return _Converter.for_range(chain.dac_bits, chain.dac_min_v, chain.dac_max_v)


class _StageCore:
    """Parts shared by the scalar and the batch stage: models, matrices, rest state."""

    def __init__(self, params: StageParams) -> None:
        self.params = params
        self.chain = params.chain
        self.sample_time_s = params.sample_time_s
        self.hysteresis: HysteresisModel = make_hysteresis(params.hysteresis)
        self.plant = linear_plant(params.plant)
        self.charge_hysteresis = params.plant.model == 'electromechanical'
        self.substeps = params.plant.substeps if self.charge_hysteresis else 1
        self.discrete: DiscreteLinearPlant = self.plant.discretize(
            self.sample_time_s / self.substeps)
        self.dc_gain_m_per_v = self.plant.dc_gain_m_per_v
        chain = params.chain
        self.dac = _dac_converter(chain) if chain.quantize else None
        self.adc = _Converter.for_range(chain.adc_bits, chain.adc_min_v, chain.adc_max_v,
                                        chain.sensor_gain_v_per_m, chain.sensor_offset_m) \
            if chain.quantize else None
        if self.charge_hysteresis:
            em = params.plant.electromechanical
            # u = q / q_ref is the charge in "volts of w": q_ref = C_A k_amp kbar_s / k_s is
            # the charge per volt of w at rest. H(q) = k_amp (u - P(u)), so that at rest the
            # general model behaves like P ahead of G (exactly so when P is linear).
            self.amplifier_gain = em.amplifier_gain
            # scaled state 0 is q / (C_A k_amp), see linear.electromechanical_plant
            self.charge_to_u = em.stiffness_n_per_m / em.stiffness_bar_n_per_m

    def rest(self, position_m: Any) -> tuple[Any, Any, Any]:
        """Return (linear state columns, hysteresis state, held input v) at rest."""
        u0 = np.asarray(position_m, dtype=np.float64) / self.dc_gain_m_per_v
        slope = self.hysteresis.slope
        if self.charge_hysteresis:
            # at rest u = v - H/k_amp = v - (1 - slope) u, so v = (2 - slope) u
            v0 = (2.0 - slope) * u0
            h_state = self.hysteresis.rest_state(u0 if u0.ndim else float(u0))
            h_volt = self.amplifier_gain * (1.0 - slope) * u0
            rhs = np.multiply.outer(self.plant.b[:, 0], v0) + \
                np.multiply.outer(self.plant.b[:, 1], h_volt)
        else:
            v0 = u0 / slope
            h_state = self.hysteresis.rest_state(v0 if v0.ndim else float(v0))
            rhs = np.multiply.outer(self.plant.b[:, 0], slope * v0)
        x = -np.linalg.solve(self.plant.a, rhs)
        return x, h_state, v0


@dataclass
class _KernelState:
    """The state of one scalar stage, as the kernels exchange it with :class:`Stage`."""

    x: list[float]
    h: Any
    v: float
    w: float
    steps: int = 0
    faults: int = 0


@dataclass(frozen=True)
class _Kernel:
    """A per-sample step function and access to the state it keeps in its closure."""

    step: Callable[[float], float]
    get: Callable[[], _KernelState]
    set: Callable[[_KernelState], None]
    #: the true position c x [m] now, the same sum as :func:`_dot` of c and the state
    true_position: Callable[[], float]


def _dot(coefficients: Sequence[float], values: Sequence[float]) -> float:
    """
    Return sum(c * v) added left to right, as the fused kernel writes it out.

    Not ``sum()``: from Python 3.12 it adds floats with compensation, which rounds differently
    from the plain additions of :func:`_fused_kernel`.
    """
    acc = 0.0
    for c, v in zip(coefficients, values):
        acc += c * v
    return acc


def _generic_kernel(core: _StageCore, rng: np.random.Generator) -> _Kernel:
    """
    Return the kernel for any model: hysteresis objects and the general model's sub-steps.

    Uses the same matrices, converters and hysteresis objects as the batch stage, through their
    own methods.
    """
    chain = core.params.chain
    ad = tuple(tuple(float(a) for a in row) for row in core.discrete.ad)
    bd = tuple(tuple(float(b) for b in row) for row in core.discrete.bd)
    c = tuple(float(v) for v in core.discrete.c)
    hyst = core.hysteresis
    dac = core.dac.scalar if core.dac is not None else None
    adc = core.adc.scalar if core.adc is not None else None
    vmin, vmax, safe = chain.amplifier_min_v, chain.amplifier_max_v, chain.safe_voltage_v
    noise = chain.sensor_noise_std_m
    st = _KernelState(x=[0.0] * len(c), h=None, v=0.0, w=0.0)

    def step(command_v: float) -> float:
        if math.isfinite(command_v):
            v = float(command_v)
            if dac is not None:
                v = dac(v)
            v = min(max(v, vmin), vmax)
        else:
            st.faults += 1
            v = safe
        st.v = v
        x = st.x
        if core.charge_hysteresis:
            for _ in range(core.substeps):
                u = x[0] * core.charge_to_u
                st.h, pu = hyst.step(st.h, u)
                h_volt = core.amplifier_gain * (u - float(pu))
                x = [_dot(row, x) + b[0] * v + b[1] * h_volt for row, b in zip(ad, bd)]
            st.w = x[0] * core.charge_to_u
        else:
            st.h, w = hyst.step(st.h, v)
            st.w = w = float(w)
            x = [_dot(row, x) + b[0] * w for row, b in zip(ad, bd)]
        st.x = x
        st.steps += 1
        pos = _dot(c, x)
        if noise > 0.0:
            pos += noise * float(rng.standard_normal())
        return adc(pos) if adc is not None else pos

    def get() -> _KernelState:
        return dataclasses.replace(st, x=list(st.x))

    def set_(new: _KernelState) -> None:
        for f in dataclasses.fields(st):
            setattr(st, f.name, getattr(new, f.name))
        st.x = list(new.x)

    def true_position() -> float:
        return _dot(c, st.x)

    return _Kernel(step, get, set_, true_position)


@dataclass(frozen=True)
class FusedConstants:
    """
    The plain floats the fused per-sample kernel computes with, for one stage.

    The scalar kernel (:func:`_fused_kernel`) and the batch of stages
    (:class:`piezo_stage_ros.core.loop.batch.StageFamilyBatch`) both take them from
    :func:`fused_constants`, so the two step the same numbers.

    Attributes
    ----------
    order : int
        1 (reduced) or 3 (third-order).
    has_hysteresis : bool
        Backlash-like hysteresis ahead of the plant (else none).
    alpha, slope, shift : float
        alpha, c and -rho of eq. (21) (0, 1, 0 without hysteresis).
    ad : tuple of tuple of float
        Ad, order x order.
    bd : tuple of float
        The w column of Bd.
    c : tuple of float
        The output row.
    vmin, vmax, safe : float
        Amplifier range and safe voltage [V].
    noise : float
        Sensor noise [m rms].
    dac, adc : tuple of float or None
        (scale, offset, top, out_scale, out_offset) of each converter; None without
        quantization.

    """

    order: int
    has_hysteresis: bool
    alpha: float
    slope: float
    shift: float
    ad: tuple[tuple[float, ...], ...]
    bd: tuple[float, ...]
    c: tuple[float, ...]
    vmin: float
    vmax: float
    safe: float
    noise: float
    dac: tuple[float, float, float, float, float] | None
    adc: tuple[float, float, float, float, float] | None


def fused_constants(core: _StageCore) -> FusedConstants | None:
    """
    Return the constants of the fused kernel for a stage, or None where it does not apply.

    Parameters
    ----------
    core : _StageCore
        The stage's models and matrices.

    Returns
    -------
    FusedConstants or None
        None unless the stage is a linear model of order 1 or 3 with the backlash-like
        hysteresis (or none) ahead of it.

    """
    hyst = core.hysteresis
    order = core.plant.order
    if core.charge_hysteresis or order not in (1, 3) or \
            not isinstance(hyst, (BacklashLike, NoHysteresis)):
        return None
    chain = core.params.chain

    def conv(c: _Converter | None) -> tuple[float, float, float, float, float] | None:
        return None if c is None else (c.scale, c.offset, c.top, c.out_scale, c.out_offset)
    return FusedConstants(
        order=order, has_hysteresis=isinstance(hyst, BacklashLike),
        alpha=hyst.params.alpha if isinstance(hyst, BacklashLike) else 0.0,
        slope=hyst.slope, shift=-hyst.bound,
        ad=tuple(tuple(float(a) for a in row) for row in core.discrete.ad),
        bd=tuple(float(row[0]) for row in core.discrete.bd),
        c=tuple(float(v) for v in core.discrete.c),
        vmin=chain.amplifier_min_v, vmax=chain.amplifier_max_v, safe=chain.safe_voltage_v,
        noise=chain.sensor_noise_std_m, dac=conv(core.dac), adc=conv(core.adc))


def _fused_kernel(core: _StageCore, rng: np.random.Generator) -> _Kernel | None:
    """
    Return a fused per-sample kernel for the common case, or None where it does not apply.

    The common case is the default stage: a linear model of order 1 or 3 with the backlash-like
    hysteresis (or none) ahead of it. DAC, clamp, the exact hysteresis jump, the ZOH update,
    sensor noise and ADC are written out in one closure over plain floats: in CPython a method
    call costs as much as the arithmetic of a whole sample, and this is the hot path of the
    offline runner and of the simulated plant node. It computes exactly what the generic kernel
    computes, operation for operation (a test compares the two bit for bit).
    """
    k = fused_constants(core)
    if k is None:
        return None
    order, has_h, alpha, slope, shift = k.order, k.has_hysteresis, k.alpha, k.slope, k.shift
    vmin, vmax, safe, noise = k.vmin, k.vmax, k.safe, k.noise
    normal = rng.standard_normal
    quantize_in, quantize_out = k.dac is not None, k.adc is not None
    ds, do, dtop, dos, doo = k.dac if k.dac is not None else (0.0,) * 5
    as_, ao, atop, aos, aoo = k.adc if k.adc is not None else (0.0,) * 5
    ad, bd = k.ad, k.bd
    cc = list(k.c) + [0.0, 0.0]
    c0, c1, c2 = cc[0], cc[1], cc[2]
    exp, floor, copysign, isfinite = math.exp, math.floor, math.copysign, math.isfinite
    if order == 3:
        (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = ad
        b0, b1, b2 = bd
    else:
        a00, b0 = ad[0][0], bd[0]
        a01 = a02 = a10 = a11 = a12 = a20 = a21 = a22 = b1 = b2 = 0.0
    x0 = x1 = x2 = 0.0
    v_last = e = w = v_held = 0.0
    steps = faults = 0

    def step(command_v: float) -> float:
        nonlocal x0, x1, x2, v_last, e, w, v_held, steps, faults
        if isfinite(command_v):
            v = float(command_v)
            if quantize_in:
                code = floor(v * ds + do)
                v = min(max(code, 0.0), dtop) * dos + doo
            if v < vmin:
                v = vmin
            elif v > vmax:
                v = vmax
        else:
            faults += 1
            v = safe
        v_held = v
        if has_h:
            dv = v - v_last
            decay = exp(-alpha * abs(dv))
            e = e * decay + shift * copysign(1.0 - decay, dv)
            v_last = v
            w = slope * v + e
        else:
            w = v
        if order == 3:
            x0, x1, x2 = (a00 * x0 + a01 * x1 + a02 * x2 + b0 * w,
                          a10 * x0 + a11 * x1 + a12 * x2 + b1 * w,
                          a20 * x0 + a21 * x1 + a22 * x2 + b2 * w)
            pos = c0 * x0 + c1 * x1 + c2 * x2
        else:
            x0 = a00 * x0 + b0 * w
            pos = c0 * x0
        steps += 1
        if noise > 0.0:
            pos += noise * float(normal())
        if quantize_out:
            code = floor(pos * as_ + ao)
            return min(max(code, 0.0), atop) * aos + aoo
        return pos

    def get() -> _KernelState:
        x = [x0, x1, x2][:order]
        return _KernelState(x=x, h=(v_last, e) if has_h else (), v=v_held, w=w, steps=steps,
                            faults=faults)

    def set_(new: _KernelState) -> None:
        nonlocal x0, x1, x2, v_last, e, w, v_held, steps, faults
        x0, x1, x2 = (list(new.x) + [0.0, 0.0])[:3]
        if has_h:
            v_last, e = (float(new.h[0]), float(new.h[1]))
        v_held, w, steps, faults = new.v, new.w, new.steps, new.faults

    if order == 3:
        def true_position() -> float:
            # _dot's left-to-right sum (0.0 + a is a): the bits of Stage.position_m
            return c0 * x0 + c1 * x1 + c2 * x2
    else:
        def true_position() -> float:
            return c0 * x0

    return _Kernel(step, get, set_, true_position)


class Stage:
    """
    One simulated stage, stepped one sample at a time (scalar fast path).

    Parameters
    ----------
    params : StageParams
        Models and signal chain.
    rng : numpy.random.Generator, optional
        Source of sensor noise; default ``np.random.default_rng(params.seed)``.

    Attributes
    ----------
    step : callable
        ``step(command_v) -> float``: hold the commanded amplifier input [V] over one sample
        (quantized by the DAC, clamped to the amplifier range; a non-finite command applies
        ``chain.safe_voltage_v`` and counts a fault) and return the measured position at its
        end [m]. A plain function, not a method, for speed.
    read_position_m : callable
        ``read_position_m() -> float``: the true position now [m], what :attr:`position_m`
        returns; a plain function, so that the closed loop can record it every sample.

    Notes
    -----
    With the general model, H(q) is updated ``plant.substeps`` times per sample (the linear part
    is exact over each sub-step, the hysteresis follows the charge at the sub-step ends): a
    first-order splitting whose error falls with the number of sub-steps.

    """

    step: Callable[[float], float]
    read_position_m: Callable[[], float]

    def __init__(self, params: StageParams, rng: np.random.Generator | None = None,
                 *, fused: bool = True) -> None:
        self._core = _StageCore(params)
        self.params = params
        self.rng = rng if rng is not None else np.random.default_rng(params.seed)
        kernel = _fused_kernel(self._core, self.rng) if fused else None
        self._kernel = kernel if kernel is not None else _generic_kernel(self._core, self.rng)
        self.step = self._kernel.step
        self.read_position_m = self._kernel.true_position
        self.reset()

    @property
    def sample_time_s(self) -> float:
        """Return the sample period [s]."""
        return self._core.sample_time_s

    def fused_constants(self) -> FusedConstants | None:
        """Return the fused kernel's constants, or None where no fused kernel serves the model."""
        return fused_constants(self._core)

    def kernel_state(self) -> _KernelState:
        """Return the state the last reset or step left (a batch of stages takes it over)."""
        return self._kernel.get()

    @property
    def position_m(self) -> float:
        """Return the true position x [m] (no noise, no quantization)."""
        return self._kernel.true_position()

    @property
    def applied_voltage_v(self) -> float:
        """Return the amplifier input voltage held over the last sample [V]."""
        return self._kernel.get().v

    @property
    def hysteresis_output_v(self) -> float:
        """Return the hysteresis output w [V] (the charge variable u for the general model)."""
        return self._kernel.get().w

    @property
    def faults(self) -> int:
        """Return how many non-finite commands were replaced by the safe voltage."""
        return self._kernel.get().faults

    @property
    def steps(self) -> int:
        """Return the samples stepped since the last reset."""
        return self._kernel.get().steps

    @property
    def time_s(self) -> float:
        """Return the simulated time since the last reset [s]."""
        return self.steps * self._core.sample_time_s

    def reset(self, position_m: float | None = None) -> float:
        """
        Put the stage at rest at ``position_m`` and return the measured position there.

        Parameters
        ----------
        position_m : float, optional
            Rest position [m]; default ``params.initial_position_m``.

        Returns
        -------
        float
            Measured position y_0 [m].

        """
        pos = self.params.initial_position_m if position_m is None else float(position_m)
        x, h_state, v0 = self._core.rest(pos)
        faults = self._kernel.get().faults
        self._kernel.set(_KernelState(x=[float(v) for v in x], h=h_state, v=float(v0),
                                      w=pos / self._core.dc_gain_m_per_v, steps=0,
                                      faults=faults))
        return self.measure()

    def apply_command(self, command_v: float) -> float:
        """Return the voltage the amplifier would see for ``command_v`` [V] (no stepping)."""
        return float(amplifier_input(command_v, self.params.chain))

    def measure(self) -> float:
        """Return the measured position [m] now (sensor, noise, ADC) without stepping."""
        pos = self.position_m
        noise = self.params.chain.sensor_noise_std_m
        if noise > 0.0:
            pos += noise * float(self.rng.standard_normal())
        adc = self._core.adc
        return adc.scalar(pos) if adc is not None else pos

    def run_open_loop(self, commands_v: ArrayLike) -> FloatArray:
        """
        Apply a sequence of commands, one per sample, and return the measured positions.

        Parameters
        ----------
        commands_v : array_like
            u_0 ... u_N-1 [V].

        Returns
        -------
        ndarray
            y_1 ... y_N [m] (the measurement at the end of each sample).

        """
        cmds = np.asarray(commands_v, dtype=np.float64).ravel()
        step = self.step
        return np.fromiter((step(u) for u in cmds.tolist()), dtype=np.float64, count=cmds.size)


class StageBatch:
    """
    ``n`` independent stages stepped together with numpy (same parameters, own noise).

    Parameters
    ----------
    params : StageParams
        Models and signal chain (shared by every stage).
    n : int
        Number of stages.
    rng : numpy.random.Generator, optional
        Source of sensor noise; default ``np.random.default_rng(params.seed)``.

    """

    def __init__(self, params: StageParams, n: int, rng: np.random.Generator | None = None
                 ) -> None:
        if n < 1:
            raise ParameterError('n', n, '[1, inf)')
        self._core = _StageCore(params)
        self.params = params
        self.n = n
        self.rng = rng if rng is not None else np.random.default_rng(params.seed)
        self.faults = 0
        self.reset()

    @property
    def sample_time_s(self) -> float:
        """Return the sample period [s]."""
        return self._core.sample_time_s

    @property
    def position_m(self) -> FloatArray:
        """Return the true positions [m], shape (n,)."""
        c = self._core.discrete.c
        nonzero = np.flatnonzero(c)
        if nonzero.size == 1:  # every model here measures one state directly
            return np.asarray(c[nonzero[0]] * self._x[nonzero[0]], dtype=np.float64)
        return np.asarray(c @ self._x, dtype=np.float64)

    def reset(self, position_m: ArrayLike | None = None) -> FloatArray:
        """
        Put every stage at rest (one position or one per stage) and return the measurements.

        Parameters
        ----------
        position_m : array_like, optional
            Rest position(s) [m]; default ``params.initial_position_m``.

        Returns
        -------
        ndarray
            Measured positions [m], shape (n,).

        """
        pos = self.params.initial_position_m if position_m is None else position_m
        pos_a = np.broadcast_to(np.asarray(pos, dtype=np.float64), (self.n,)).copy()
        self._x, self._h, v0 = self._core.rest(pos_a)
        self._v = np.asarray(v0, dtype=np.float64)
        return self.measure()

    def measure(self) -> FloatArray:
        """Return the measured positions [m] now."""
        noise = self.params.chain.sensor_noise_std_m
        pos = self.position_m
        if noise > 0.0:
            pos = pos + noise * self.rng.standard_normal(self.n)
        return self._core.adc.array(pos) if self._core.adc is not None else pos

    def step(self, command_v: ArrayLike) -> FloatArray:
        """
        Hold one command per stage over one sample and return the measured positions.

        Parameters
        ----------
        command_v : array_like
            Commands [V], shape (n,) or scalar.

        Returns
        -------
        ndarray
            Measured positions [m], shape (n,).

        """
        u = np.asarray(command_v, dtype=np.float64)
        if u.shape != (self.n,):
            # np.broadcast_to costs more than the whole step for scalars; np.full does not
            u = np.full(self.n, float(u)) if u.ndim == 0 else np.broadcast_to(u, (self.n,))
        if not np.isfinite(u).all():
            self.faults += int(np.count_nonzero(~np.isfinite(u)))
        v = _amplifier_input(u, self.params.chain, self._core.dac)
        self._v = v
        core = self._core
        d = core.discrete
        if core.charge_hysteresis:
            for _ in range(core.substeps):
                uq = self._x[0] * core.charge_to_u
                self._h, pu = core.hysteresis.step(self._h, uq)
                h_volt = core.amplifier_gain * (uq - pu)
                self._x = d.ad @ self._x + d.bd[:, :1] * v + d.bd[:, 1:2] * h_volt
        else:
            self._h, w = core.hysteresis.step(self._h, v)
            self._x = d.ad @ self._x + d.bd[:, :1] * w
        return self.measure()
