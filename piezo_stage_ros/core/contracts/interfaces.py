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
The small interfaces the closed loop is made of.

The offline runner (:mod:`piezo_stage_ros.core.loop.closed_loop`) and the ROS nodes drive the same
objects through these interfaces, one sample at a time:

1. the plant gives the measured position y_k at t_k
(:meth:`piezo_stage_ros.core.model.stage.Stage.reset`
   or the previous :meth:`~piezo_stage_ros.core.model.stage.Stage.step`);
2. the trajectory gives x_d(t_k) and its derivative;
3. the controller turns (y_k, x_d, x_d') into the amplifier input voltage u_k;
4. the plant holds u_k over [t_k, t_k+1) (zero-order hold) and returns y_k+1.

Units at these interfaces are SI: metres, metres per second, volts, seconds.
"""

from __future__ import annotations

from typing import Mapping, Protocol, runtime_checkable

from numpy.typing import ArrayLike
from piezo_stage_ros.core.contracts.types import FloatArray

__all__ = ['Controller', 'Trajectory']


@runtime_checkable
class Trajectory(Protocol):
    """A desired position x_d(t) [m] with its time derivative [m/s]."""

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """
        Evaluate the trajectory.

        Parameters
        ----------
        time_s : array_like
            Times since the start of the trajectory [s].

        Returns
        -------
        position_m, velocity_mps : ndarray
            x_d and dx_d/dt at those times, same shape as ``time_s``.

        """
        ...


@runtime_checkable
class Controller(Protocol):
    """One controller step per sample: measurement and reference in, amplifier voltage out."""

    @property
    def sample_time_s(self) -> float:
        """The sample period the controller was designed for [s]."""
        ...

    def reset(self, position_m: float, reference_m: float) -> None:
        """Forget all history and start again from this measured position and reference."""
        ...

    def step(self, position_m: float, reference_m: float,
             reference_velocity_mps: float) -> float:
        """Return the amplifier input voltage [V] to hold over the next sample."""
        ...

    def diagnostics(self) -> Mapping[str, float]:
        """Return internal state worth recording after the last step (e.g. ``theta_hat``)."""
        ...
