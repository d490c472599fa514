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
A reference that changes its line rate during a run: one trajectory, then another.

What a scanner does when the image asks for another line rate: the first trajectory plays
until ``at_s``, then the second starts at its own t = 0. A feed-forward bound to it
(:meth:`~piezo_stage_ros.core.control.feedforward.FeedForwardController.bind`) binds each
segment in turn at the sample it starts: the model inverse of the new line from its first
sample, a learned table started afresh for the new period.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.interfaces import Trajectory
from piezo_stage_ros.core.contracts.types import FloatArray

__all__ = ['LineRateChange']


class LineRateChange:
    """
    ``first`` until ``at_s``, then ``second`` from its own t = 0.

    Parameters
    ----------
    first, second : Trajectory
        The two references.
    at_s : float
        When the second starts [s], > 0. When the first is periodic it must be a whole number
        of its periods (to 1e-9 of one), so that the reference does not jump at the change.

    Raises
    ------
    ParameterError
        ``line_rate_change.at_s`` outside (0, inf) or not a whole number of periods.

    """

    #: Aperiodic as a whole: each segment has its own period.
    period_s = None

    def __init__(self, first: Trajectory, second: Trajectory, at_s: float) -> None:
        if not (at_s > 0.0 and math.isfinite(at_s)):
            raise ParameterError('line_rate_change.at_s', at_s, '(0, inf) s')
        period = getattr(first, 'period_s', None)
        if period:
            cycles = at_s / period
            if abs(cycles - round(cycles)) > 1e-9 * max(cycles, 1.0) or round(cycles) < 1:
                raise ParameterError('line_rate_change.at_s', at_s,
                                     f'a whole number of the first line period ({period:g} s)',
                                     'would make the reference jump at the change')
        self.first = first
        self.second = second
        self.at_s = float(at_s)

    @property
    def segments(self) -> tuple[tuple[float, Trajectory], ...]:
        """Return (start [s], trajectory) of each segment, in order."""
        return ((0.0, self.first), (self.at_s, self.second))

    def evaluate(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Return x_d, x_d' [m, m/s]: the first before ``at_s``, the second after."""
        t = np.asarray(time_s, dtype=np.float64)
        x1, v1 = self.first.evaluate(t)
        x2, v2 = self.second.evaluate(np.maximum(t - self.at_s, 0.0))
        later = t >= self.at_s
        return (np.asarray(np.where(later, x2, x1), dtype=np.float64),
                np.asarray(np.where(later, v2, v1), dtype=np.float64))
