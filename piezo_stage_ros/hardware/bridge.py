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
The bridge interface behind the plant node, and the core model as one of its backends.

A bridge moves one sample at a time: :meth:`Bridge.write_voltage` sets the amplifier input to hold
over the next sample, :meth:`Bridge.read_position` returns the position measured at the end of
that sample. Around that come :meth:`Bridge.open`, :meth:`Bridge.safe_start` (drive the safe
voltage, return the first measurement) and :meth:`Bridge.safe_stop` (drive the safe voltage,
release the device). Clamping and the watchdog are not the backend's business: every backend is
driven through :class:`piezo_stage_ros.hardware.safety.GuardedPlant`.

Commands ahead (optional): a backend that keeps a queue has ``write_commands(voltage_v,
ahead_v)``, a :meth:`Bridge.write_voltage` that also hands over the commands predicted for the
samples after that one. A sample without a newer write then applies the next of them instead of
holding the voltage (the last one is held after the queue); any write replaces the queue. A
backend that owns the clock and sends each write at once (``UdpStreamBridge``) also has
``write_ahead(ahead_v)``: the commands ahead of the write just sent, sent after it (see
:meth:`~piezo_stage_ros.hardware.safety.GuardedPlant.follow`).
"""

from __future__ import annotations

from typing import Mapping, Protocol, runtime_checkable, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.errors import PiezoStageError
from piezo_stage_ros.core.model.stage import Stage, StageParams

__all__ = ['Bridge', 'BridgeError', 'ModelBridge']


class BridgeError(PiezoStageError):
    """A bridge cannot reach its device, or the device reports a fault; the message says which."""


@runtime_checkable
class Bridge(Protocol):
    """One plant backend: the core model, or a real stage behind an I/O target."""

    def open(self) -> None:
        """Acquire the device (socket, driver); drives nothing yet."""
        ...

    def safe_start(self, safe_voltage_v: float) -> float:
        """
        Drive the safe voltage and return the first measured position y_0.

        Parameters
        ----------
        safe_voltage_v : float
            Amplifier input to apply first [V].

        Returns
        -------
        float
            Measured position [m].

        """
        ...

    def write_voltage(self, voltage_v: float) -> None:
        """Set the amplifier input [V] to hold over the next sample (already clamped)."""
        ...

    def read_position(self) -> float:
        """Return the position [m] measured at the end of the sample just written."""
        ...

    def safe_stop(self, safe_voltage_v: float) -> None:
        """Drive ``safe_voltage_v`` [V] and release the device; safe to call more than once."""
        ...

    def stats(self) -> Mapping[str, float]:
        """Return counters worth reporting (losses, timeouts, faults)."""
        ...


class ModelBridge:
    """
    The core stage model behind the bridge interface (the default plant backend).

    Parameters
    ----------
    params : StageParams
        The stage; ``initial_position_m`` is where it rests at the start.
    rng : numpy.random.Generator, optional
        Sensor-noise source; default seeded from ``params.seed`` as the offline runner does.

    Notes
    -----
    :meth:`safe_start` puts the model at rest at ``initial_position_m`` (that is what
    :meth:`~piezo_stage_ros.core.model.stage.Stage.reset` means) rather than at the safe voltage: a
    model has nothing to protect, and starting where the offline runner starts is what makes a
    lockstep run equal to ``simulate``. Each :meth:`read_position` steps the model once with the
    voltage written last (a physical stage would have moved on by itself).

    """

    def __init__(self, params: StageParams, rng: np.random.Generator | None = None) -> None:
        self.params = params
        self.stage = Stage(params, rng)
        self._voltage_v = params.chain.safe_voltage_v
        self._ahead: Sequence[float] = ()
        self._played = 0
        self.steps = 0

    @property
    def clamps_itself(self) -> bool:
        """Return True: the model's own signal chain clamps after its DAC, as the real one."""
        return True

    def open(self) -> None:
        """Nothing to acquire."""

    def safe_start(self, safe_voltage_v: float) -> float:
        """Put the model at rest at its initial position and return y_0 [m]."""
        self._voltage_v = safe_voltage_v
        self._ahead = ()
        self.steps = 0
        return self.stage.reset()

    def write_voltage(self, voltage_v: float) -> None:
        """Set the voltage [V] the next :meth:`read_position` holds over one sample."""
        self._voltage_v = voltage_v
        self._ahead = ()

    def write_commands(self, voltage_v: float, ahead_v: Sequence[float]) -> None:
        """
        Set the voltage [V] of the next sample and the queue of commands ahead after it [V].

        :meth:`advance` plays the queue over the samples nobody takes, one command a sample,
        then holds the last: what a real-time target with a command queue does while the host
        stalls.
        """
        self._voltage_v = voltage_v
        self._ahead = ahead_v
        self._played = 0

    def read_position(self) -> float:
        """Step the model one sample and return the measured position [m]."""
        self.steps += 1
        return self.stage.step(self._voltage_v)

    def advance(self, samples: int) -> None:
        """
        Step the model ``samples`` times with the voltage held, measuring nothing.

        For samples a paced loop skipped after a stall: a physical stage goes on under the held
        voltage while nobody looks, so the model does too and stays in step with wall time. With
        a queue of commands ahead (:meth:`write_commands`), each skipped sample applies the next
        of them instead, then the last is held.
        """
        ahead = self._ahead
        for _ in range(samples):
            if self._played < len(ahead):
                self._voltage_v = float(ahead[self._played])
                self._played += 1
            self.steps += 1
            self.stage.step(self._voltage_v)

    def step(self, voltage_v: float) -> float:
        """Write and read in one call (the hot path of the lockstep loop)."""
        self.steps += 1
        return self.stage.step(voltage_v)

    def safe_stop(self, safe_voltage_v: float) -> None:
        """Remember the safe voltage; a model has nothing to release."""
        self._voltage_v = safe_voltage_v
        self._ahead = ()

    def stats(self) -> Mapping[str, int]:
        """Return the number of samples stepped and of non-finite commands the model replaced."""
        return {'samples': self.steps, 'faults': self.stage.faults}
