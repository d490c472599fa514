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
The computations of one real-time sample of a multi-axis stage: references and commands.

A paced servo of N axes (:mod:`piezo_stage_ros.nodes.servo_axes`) takes, per sample k, every
axis' x_d(t_k) and x_d'(t_k) from :class:`AxesReference` (the axes' trajectories evaluated
ahead in chunks, t_k = k T as the offline loop :func:`~piezo_stage_ros.core.loop.axes.run_axes`
computes it, so that the values are the same bit for bit) and every axis' command with its
commands ahead from :class:`AxesCommands`: one
:meth:`~piezo_stage_ros.core.control.axes.AxesController.step_ahead_rows` call (the
commands ahead of the axes with a whole period's tables computed only when read: the backend
reads them for the samples the host misses), the axes whose controller has no prediction of
its own (no feed-forward) predicted by a
:class:`~piezo_stage_ros.core.control.ahead.CommandPredictor` each along its reference ahead,
as the one-axis servo predicts them.
"""

from __future__ import annotations

import functools
from typing import Any, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.interfaces import Trajectory
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.control.ahead import CommandPredictor
from piezo_stage_ros.core.control.axes import AxesController
from piezo_stage_ros.core.control.controllers import SENSOR_GAIN_V_PER_M
from piezo_stage_ros.core.loop.axes import axis_references

__all__ = ['AxesCommands', 'AxesReference', 'REFERENCE_CHUNK']

#: Samples of each axis' reference evaluated at once. An evaluation costs a fixed part (tens
#: of microseconds per axis) and a little per sample: the samples that carry one stay few
#: (one axis each, the last samples of a chunk) and most samples carry none.
REFERENCE_CHUNK = 4000


class AxesReference:
    """
    Every axis' reference at each sample, evaluated ahead in chunks.

    Parameters
    ----------
    trajectories : sequence of Trajectory
        One per axis; t = 0 is sample 0.
    sample_time_s : float
        T [s].
    chunk : int
        Samples evaluated at once (per axis), >= 1.
    names : sequence of str
        The axes, for messages (default: their indices).

    """

    def __init__(self, trajectories: Sequence[Trajectory], sample_time_s: float, *,
                 chunk: int = REFERENCE_CHUNK, names: Sequence[str] = ()) -> None:
        if chunk < 1:
            raise ParameterError('chunk', chunk, '[1, inf) samples')
        if not trajectories:
            raise ParameterError('trajectories', 0, 'one per axis, at least one')
        self.trajectories = list(trajectories)
        self.n = len(self.trajectories)
        self.names = tuple(names[j] if j < len(names) else str(j) for j in range(self.n))
        self.sample_time_s = float(sample_time_s)
        self.chunk = int(chunk)
        self._first = -1
        # the chunk as (axes, chunk) arrays: a sample reads its column (no object per sample
        # is kept, so the garbage collector has nothing of it to scan)
        self._x = np.zeros((self.n, 0))
        self._v = np.zeros((self.n, 0))
        # the next chunk as it is evaluated: x_d, x_d', its first sample, axes done
        self._next: tuple[FloatArray, FloatArray, int, int] = (self._x, self._v, -1, 0)
        # per axis: (first sample, x_d, x_d') of the window read ahead last
        self._windows: list[tuple[int, FloatArray, FloatArray]] = [
            (-1, np.zeros(0), np.zeros(0)) for _ in range(self.n)]

    def _evaluate(self, axis: int, first: int, size: int) -> tuple[FloatArray, FloatArray]:
        # t_k = k T as run_axes computes it (the float of arange(k0, k0 + m) * T)
        return axis_references(self.trajectories[axis], first, size, self.sample_time_s,
                               self.names[axis])

    def at(self, index: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """
        Return x_d and x_d' of every axis at sample ``index`` [m, m/s] (axis order).

        The next chunk is evaluated one axis a sample over the last samples of the current
        one (the samples go on in order), so that no sample evaluates every axis' chunk.
        """
        i = index - self._first
        size = self._x.shape[1]
        if not 0 <= i < size:
            first = index - index % self.chunk
            nx, nv, nfirst, done = self._next
            if nfirst != first or done < self.n:
                nx, nv = np.empty((self.n, self.chunk)), np.empty((self.n, self.chunk))
                for j in range(self.n):
                    nx[j], nv[j] = self._evaluate(j, first, self.chunk)
            self._x, self._v, self._first = nx, nv, first
            self._next = (np.empty((self.n, self.chunk)), np.empty((self.n, self.chunk)),
                          first + self.chunk, 0)
            i = index - first
        elif i >= size - self.n:
            nx, nv, nfirst, done = self._next
            if done < self.n:
                nx[done], nv[done] = self._evaluate(done, nfirst, self.chunk)
                self._next = (nx, nv, nfirst, done + 1)
        return tuple(self._x[:, i].tolist()), tuple(self._v[:, i].tolist())

    def window(self, axis: int, index: int, count: int) -> tuple[Any, Any]:
        """
        Return x_d and x_d' of axis ``axis`` for the ``count`` samples after ``index``.

        Array views of a window evaluated ahead (``count`` plus a chunk at a time), for the
        commands ahead of an axis without its own prediction.
        """
        first, x, v = self._windows[axis]
        start = index + 1
        if first < 0 or start < first or start + count > first + x.size:
            x, v = self._evaluate(axis, start, count + self.chunk)
            first = start
            self._windows[axis] = (first, x, v)
        i = start - first
        return x[i:i + count], v[i:i + count]


class AxesCommands:
    """
    Every axis' command and its commands ahead, one call a sample.

    Parameters
    ----------
    controller : AxesController
        Bound to the axes' trajectories (:meth:`AxesController.bind`).
    reference : AxesReference
        The same trajectories, for the axes predicted along their reference.

    """

    def __init__(self, controller: AxesController, reference: AxesReference) -> None:
        if controller.n != reference.n:
            raise ParameterError('controller', controller.n, f'{reference.n} axes, one per '
                                 'trajectory')
        self.controller = controller
        self.reference = reference
        self.n = controller.n
        t = controller.sample_time_s
        # axes without a prediction of their own: the one-axis servo's predictor each
        self._predictors = [
            (j, CommandPredictor(SENSOR_GAIN_V_PER_M, t), c) for j, c in
            enumerate(controller.controllers) if not callable(getattr(c, 'predict', None))]
        self._step = controller.step
        self._step_ahead = controller.step_ahead_rows
        self.steps = 0

    def reset(self, positions_m: Sequence[float], references_m: Sequence[float]) -> None:
        """Reset every axis' controller (and predictor) from y_0 and x_d(0)."""
        self.controller.reset(positions_m, references_m)
        for _, predictor, _ in self._predictors:
            predictor.reset()

    def step(self, index: int, positions_m: Sequence[float], references_m: Sequence[float],
             velocities_mps: Sequence[float], count: int
             ) -> tuple[list[float], list[Any] | None]:
        """
        Return sample ``index``'s commands [V] and each axis' ``count`` commands ahead [V].

        One sequence per axis: an array, or the batched axes' values computed when read
        (:class:`~piezo_stage_ros.core.control.ahead.AheadRow`). ``count`` 0: the commands
        alone (None for the commands ahead).
        """
        self.steps += 1
        if not count:
            return self._step(positions_m, references_m, velocities_mps), None
        out, ahead = self._step_ahead(positions_m, references_m, velocities_mps, count)
        window = self.reference.window
        for j, predictor, c in self._predictors:
            pred: Any = predictor.predict(c, count, out[j], references_m[j],
                                          velocities_mps[j], functools.partial(window, j, index))
            values_into = getattr(pred, 'values_into', None)
            if values_into is not None:
                row = np.empty(count, dtype=np.float64)
                values_into(row)
                ahead[j] = row
            else:
                ahead[j] = np.asarray(pred, dtype=np.float64)
        return out, ahead
