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
Closed-loop runs of a stage under linear loops the package did not write, and signal-chain faults.

A lab's recordings come from its own loop. This module makes such recordings in simulation, to
test the identification against them and to measure how often its bounds hold
(:func:`coverage_case`):

- :class:`ForeignController`: a two-degree-of-freedom linear loop u = F(s) x_d + C(s)(x_d - y),
  discretized by Tustin, clipped to the amplifier range, with one of three designs
  (:data:`LOOP_KINDS`): ``integral_ff`` (integral feedback plus a first-order feed-forward),
  ``pi_ff`` (PI plus a static feed-forward), ``lead_lag`` (integral with a lead, no
  feed-forward). Its gains come from a nominal static gain, as a user would set them, not from
  the true stage.
- :class:`SignalPath`: the stage seen through a sensor offset (the sensor's zero is not the
  stage's rest) and a command delay of whole samples (a DAQ pipeline).
- :func:`foreign_runs`: the two runs of a closed-loop identification with such a loop: a
  periodic multisine on the reference around a hold (``excite``), and a slow sine around the
  hold (``sine``, for the hysteresis).
- :func:`shifted`: a record with a sensor offset added to its positions.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import math
from typing import Any, Mapping

import numpy as np
from piezo_stage_ros.core.contracts.params import param, Params
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.loop.closed_loop import run
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.model.stage import Stage, StageParams
from piezo_stage_ros.core.signals.excitation import NoiseExcitation, NoiseParams
from scipy import signal

__all__ = ['ForeignController', 'ForeignLoopParams', 'LOOP_KINDS', 'SignalPath',
           'foreign_runs', 'shifted']

#: The foreign loop designs.
LOOP_KINDS = ('integral_ff', 'pi_ff', 'lead_lag')


@dataclass(frozen=True)
class ForeignLoopParams(Params):
    """A foreign closed loop, its excitation and the signal chain's faults."""

    kind: str = param('integral_ff', unit='-', description='Loop design.', choices=LOOP_KINDS)
    crossover_hz: float = param(100.0, unit='Hz', description='Crossover the design aims at '
                                'on the nominal static gain.', low=1.0, high=1000.0)
    nominal_gain_m_per_v: float = param(2.843e-6 * 1.0341, unit='m/V', description='Static '
                                        'gain the loop was designed for.', low=0.0,
                                        low_open=True)
    sample_rate_hz: float = param(10000.0, unit='Hz', description='Loop rate.', low=1000.0,
                                  high=1e6)
    hold_m: float = param(5e-6, unit='m', description='Position held.', low=0.0, high=38e-6)
    multisine_rms_m: float = param(0.12e-6, unit='m', description='Rms of the periodic '
                                   'multisine of the excitation run.', low=0.0, low_open=True)
    band_hz: tuple[float, float] = param((20.0, 4500.0), unit='Hz', description='Flat band of '
                                         'the multisine.')
    period_s: float = param(0.1, unit='s', description='Period of the multisine.', low=1e-3)
    excite_s: float = param(1.0, unit='s', description='Length of the excitation run.',
                            low=0.0, low_open=True)
    sine_amplitude_m: float = param(3e-6, unit='m', description='Amplitude of the slow sine '
                                    'run.', low=0.0, low_open=True)
    sine_frequency_hz: float = param(5.0, unit='Hz', description='Frequency of the slow sine.',
                                     low=0.0, low_open=True)
    sine_s: float = param(0.4, unit='s', description='Length of the sine run.', low=0.0,
                          low_open=True)
    sensor_offset_m: float = param(0.0, unit='m', description='Added to every measured '
                                   'position (the sensor reads x + offset).')
    delay_samples: int = param(0, unit='-', description='Extra samples between a command and '
                               'the sample it is applied in.', low=0, high=100)
    seed: int = param(3, unit='-', description='Seed of the multisine phases.', low=0)


def _design(p: ForeignLoopParams) -> tuple[tuple[FloatArray, FloatArray],
                                           tuple[FloatArray, FloatArray]]:
    """Return continuous (num, den) of the feedback C(s) and the feed-forward F(s) [V/m]."""
    g = p.nominal_gain_m_per_v
    wc = 2.0 * math.pi * p.crossover_hz
    if p.kind == 'integral_ff':
        fb = (np.array([wc / g]), np.array([1.0, 0.0]))
        w1, w2 = 2.0 * math.pi * 400.0, 2.0 * math.pi * 2000.0
        ff = (np.array([1.0 / (g * w1), 1.0 / g]), np.array([1.0 / w2, 1.0]))
    elif p.kind == 'pi_ff':
        kp = 0.1 / g
        fb = (np.array([kp, wc / g]), np.array([1.0, 0.0]))
        ff = (np.array([1.0 / g]), np.array([1.0]))
    else:
        # integral with a lead around the crossover: phase at the crossover, a gain at the
        # resonance that the stage's damping still keeps inside the unit circle
        wz, wp = wc / 2.0, wc * 2.0
        fb = (np.array([wc / (g * wz), wc / g]), np.array([1.0 / wp, 1.0, 0.0]))
        ff = (np.array([0.0]), np.array([1.0]))
    return fb, ff


def _tustin(num: FloatArray, den: FloatArray, t: float) -> tuple[list[list[float]], list[float],
                                                                  list[float], float]:
    ss = signal.cont2discrete(signal.tf2ss(num, den), t, method='bilinear')
    a, b, c, d = (np.atleast_2d(np.asarray(m, dtype=np.float64)) for m in ss[:4])
    return ([list(map(float, row)) for row in a], [float(v) for v in b[:, 0]],
            [float(v) for v in c[0]], float(d[0, 0]))


class ForeignController:
    """
    A linear two-degree-of-freedom loop u = F x_d + C (x_d - y), Tustin-discretized, clipped.

    Parameters
    ----------
    params : ForeignLoopParams
        Design (``kind``, ``crossover_hz``, ``nominal_gain_m_per_v``).
    sample_time_s : float
        Sample period [s].
    output_min_v, output_max_v : float
        Command limits [V].

    Notes
    -----
    Written as a lab would write it, not with the package's controllers: the identification
    must not rely on knowing it. On reset the feedback's integrator state is set so that the
    command starts at the hold voltage of the nominal model (a bumpless start).

    """

    def __init__(self, params: ForeignLoopParams, sample_time_s: float, *,
                 output_min_v: float = -2.0, output_max_v: float = 10.0) -> None:
        self.params = params
        self._t = float(sample_time_s)
        (fbn, fbd), (ffn, ffd) = _design(params)
        self._fb = _tustin(fbn, fbd, self._t)
        self._ff = _tustin(ffn, ffd, self._t) if np.any(ffn) and ffd.size > 1 else None
        self._ff_gain = float(ffn[-1] / ffd[-1]) if self._ff is None else 0.0
        self._lo, self._hi = float(output_min_v), float(output_max_v)
        self._xf = [0.0] * len(self._fb[1])
        self._xff = [0.0] * (len(self._ff[1]) if self._ff is not None else 0)

    @property
    def sample_time_s(self) -> float:
        """Return the sample period [s]."""
        return self._t

    def reset(self, position_m: float, reference_m: float) -> None:
        """Start at rest at the hold voltage of the nominal model."""
        hold_v = reference_m / self.params.nominal_gain_m_per_v
        if self._ff is not None:
            a, b, c, d = self._ff
            # feed-forward state at rest for a constant reference
            x = np.linalg.solve(np.eye(len(b)) - np.array(a), np.array(b) * reference_m)
            self._xff = [float(v) for v in x]
            ff = float(np.dot(c, x) + d * reference_m)
        else:
            ff = self._ff_gain * reference_m
        a, b, c, d = self._fb
        # the integrator direction: the eigenvector of A for the eigenvalue 1
        vals, vecs = np.linalg.eig(np.array(a))
        v = np.real(vecs[:, int(np.argmin(np.abs(vals - 1.0)))])
        cv = float(np.dot(c, v))
        scale = (hold_v - ff) / cv if abs(cv) > 0.0 else 0.0
        self._xf = [float(s) * scale for s in v]

    def step(self, position_m: float, reference_m: float,
             reference_velocity_mps: float) -> float:
        """Return the clipped command for one sample [V]."""
        e = reference_m - position_m
        a, b, c, d = self._fb
        x = self._xf
        u = d * e
        for ci, xi in zip(c, x):
            u += ci * xi
        self._xf = [sum(aij * xj for aij, xj in zip(row, x)) + bi * e for row, bi in zip(a, b)]
        if self._ff is not None:
            a2, b2, c2, d2 = self._ff
            x2 = self._xff
            u += d2 * reference_m
            for ci, xi in zip(c2, x2):
                u += ci * xi
            self._xff = [sum(aij * xj for aij, xj in zip(row, x2)) + bi * reference_m
                         for row, bi in zip(a2, b2)]
        else:
            u += self._ff_gain * reference_m
        return min(max(u, self._lo), self._hi)

    def diagnostics(self) -> Mapping[str, float]:
        """Return nothing (a lab's loop records no internals)."""
        return {}


class SignalPath:
    """
    A stage seen through a sensor offset and a command delay.

    Parameters
    ----------
    stage : Stage
        The stage.
    offset_m : float
        Added to every measured position [m].
    delay_samples : int
        Whole samples a command waits before the stage applies it (the rest voltage is applied
        meanwhile).

    """

    def __init__(self, stage: Stage, offset_m: float = 0.0, delay_samples: int = 0) -> None:
        self.stage = stage
        self.offset_m = float(offset_m)
        self.delay_samples = int(delay_samples)
        self._queue: deque[float] = deque()
        self.read_position_m = stage.read_position_m

    @property
    def sample_time_s(self) -> float:
        """Return the sample period [s]."""
        return self.stage.sample_time_s

    def reset(self, position_m: float | None = None) -> float:
        """Put the stage at rest and return the measured position (offset added) [m]."""
        y = self.stage.reset(position_m)
        self._queue = deque([self.stage.applied_voltage_v] * self.delay_samples)
        return y + self.offset_m

    def step(self, command_v: float) -> float:
        """Queue the command, apply the one due and return the measured position [m]."""
        self._queue.append(command_v)
        return self.stage.step(self._queue.popleft()) + self.offset_m


class _Reference:
    """Hold plus a periodic multisine or a sine, with the period in ``period_s``."""

    kind = 'foreign'

    def __init__(self, hold_m: float, noise: NoiseExcitation | None, amplitude_m: float,
                 frequency_hz: float, period_s: float) -> None:
        self.hold_m, self.noise = hold_m, noise
        self.a, self.w = amplitude_m, 2.0 * math.pi * frequency_hz
        self.period_s = period_s

    def evaluate(self, time_s: Any) -> tuple[FloatArray, FloatArray]:
        t = np.asarray(time_s, dtype=np.float64)
        pos = self.hold_m + self.a * np.sin(self.w * t)
        vel = self.a * self.w * np.cos(self.w * t)
        if self.noise is not None:
            p, v = self.noise.evaluate(t)
            pos, vel = pos + p, vel + v
        return np.asarray(pos, dtype=np.float64), np.asarray(vel, dtype=np.float64)


def foreign_runs(stage_params: StageParams, params: ForeignLoopParams | None = None,
                 *, meta: Mapping[str, Any] | None = None) -> dict[str, RunRecord]:
    """
    Record the excitation run and the sine run of a stage under a foreign loop.

    Parameters
    ----------
    stage_params : StageParams
        The true stage (its sensor noise is used; its rate is replaced by the loop's).
    params : ForeignLoopParams, optional
        Loop, excitation, faults; default :class:`ForeignLoopParams`.
    meta : Mapping, optional
        Added to both records' meta.

    Returns
    -------
    dict of str to RunRecord
        ``'excite'``: hold plus the periodic multisine; ``'sine'``: hold plus the slow sine.
        Their meta holds only what a lab's bag would (a name), plus ``true_stage`` and
        ``foreign_loop`` for the comparison.

    """
    p = params or ForeignLoopParams()
    stage = stage_params.replace(sample_rate_hz=p.sample_rate_hz)
    t = stage.sample_time_s
    noise = NoiseExcitation(NoiseParams(
        offset_m=0.0, amplitude_m=p.multisine_rms_m, band_low_hz=p.band_hz[0],
        band_high_hz=p.band_hz[1], period_s=p.period_s, grid_rate_hz=2.0 * p.sample_rate_hz,
        seed=p.seed))
    refs = {'excite': (_Reference(p.hold_m, noise, 0.0, 1.0, p.period_s), p.excite_s),
            'sine': (_Reference(p.hold_m, None, p.sine_amplitude_m, p.sine_frequency_hz,
                                1.0 / p.sine_frequency_hz), p.sine_s)}
    out = {}
    for i, (name, (ref, length)) in enumerate(refs.items()):
        path = SignalPath(Stage(stage.replace(seed=stage.seed + 17 * i + p.seed)),
                          p.sensor_offset_m, p.delay_samples)
        info: dict[str, Any] = {'name': name, 'true_stage': stage.to_flat(),
                                'foreign_loop': p.to_flat()}
        info.update(meta or {})
        rec = run(path, ForeignController(p, t), ref, duration_s=length,
                  initial_position_m=p.hold_m, record_diagnostics=False, meta=info)
        # a lab's bag does not carry the excitation's period
        rec.meta.pop('trajectory_period_s', None)
        out[name] = rec
    return out


def shifted(record: RunRecord, *, offset_m: float = 0.0) -> RunRecord:
    """
    Return a record with a sensor offset added to its positions.

    Parameters
    ----------
    record : RunRecord
        A run.
    offset_m : float
        Added to every position [m] (in open loop this is exactly what a sensor whose zero is
        not the stage's rest records; in closed loop use :class:`SignalPath`).

    Returns
    -------
    RunRecord

    """
    return RunRecord(record.time_s, record.position_m + offset_m, record.reference_m,
                     record.reference_velocity_mps, record.command_v, {}, dict(record.meta),
                     record.true_position_m)
