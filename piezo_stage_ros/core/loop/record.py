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
The record of one closed-loop run: the samples every bag, metric and plot is made from.

Row k holds what happened at sample time t_k: the measured position y_k the plant published, the
reference x_d(t_k) and its derivative, and the command u_k the controller computed from them (held
by the plant over [t_k, t_k+1)). A simulated run also knows the true position x(t_k) behind y_k
(before sensor noise and ADC): ``true_position_m``, None where it is not known (a real stage, a
bag without it). The same structure comes out of the offline runner and out of a
bag read back, so metrics of a run and of its bag compare one to one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from piezo_stage_ros.core.contracts.errors import PiezoStageError
from piezo_stage_ros.core.contracts.types import FloatArray

__all__ = ['RunRecord']


@dataclass
class RunRecord:
    """
    Samples of one run, as parallel arrays of equal length.

    Attributes
    ----------
    time_s : ndarray
        Sample times t_k [s] (in a bag: the header stamps, seconds since the epoch).
    position_m : ndarray
        Measured position y_k [m] (after sensor, noise and ADC).
    reference_m : ndarray
        Desired position x_d(t_k) [m].
    reference_velocity_mps : ndarray
        Desired velocity dx_d/dt(t_k) [m/s].
    command_v : ndarray
        Amplifier input voltage u_k [V] held over [t_k, t_k+1).
    diagnostics : dict of str to ndarray
        Controller internals per sample (e.g. ``theta_hat``, ``phi_hat``, ``s_v``, ``saturated``).
    meta : dict
        Free-form description of the run (controller, plant, trajectory, seed, parameters).
    true_position_m : ndarray or None
        True position x(t_k) [m] behind y_k (no noise, no quantization); simulation only,
        None when unknown.

    """

    time_s: FloatArray
    position_m: FloatArray
    reference_m: FloatArray
    reference_velocity_mps: FloatArray
    command_v: FloatArray
    diagnostics: dict[str, FloatArray] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)
    true_position_m: FloatArray | None = None

    def __post_init__(self) -> None:
        n = len(self.time_s)
        for name in ('position_m', 'reference_m', 'reference_velocity_mps', 'command_v',
                     'true_position_m'):
            if getattr(self, name) is not None and len(getattr(self, name)) != n:
                raise PiezoStageError(
                    f'run record: {name} has {len(getattr(self, name))} samples, time_s has {n}')
        for name, values in self.diagnostics.items():
            if len(values) != n:
                raise PiezoStageError(
                    f'run record: diagnostic {name} has {len(values)} samples, time_s has {n}')

    def __len__(self) -> int:
        return len(self.time_s)

    @property
    def error_m(self) -> FloatArray:
        """Tracking error x - x_d [m] per sample."""
        return np.asarray(self.position_m - self.reference_m, dtype=np.float64)

    @property
    def true_error_m(self) -> FloatArray | None:
        """True tracking error x(t_k) - x_d(t_k) [m] per sample; None without the true position."""
        if self.true_position_m is None:
            return None
        return np.asarray(self.true_position_m - self.reference_m, dtype=np.float64)
