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
Piecewise-polynomial joint trajectories, interpolated as joint_trajectory_controller does.

A segment joins two states over ``T`` seconds; its kind follows from what both ends give:

- positions only: **linear**, x = x_a + (x_b - x_a) tau / T (velocity the slope, acceleration 0);
- positions and velocities: **cubic** Hermite, position and velocity met at both ends;
- positions, velocities and accelerations: **quintic**, all three met at both ends.

The first segment starts from the state the axes are in when the trajectory is accepted (the
present reference: position, velocity, acceleration), so the reference has no position jump;
with positions only its velocity changes at once (as joint_trajectory_controller's linear
interpolation does). Before the start the start state is held; after the last point its
position is held at rest.

Every axis is a column: positions have shape ``(points, axes)``, and :meth:`Spline.sample`
returns arrays of shape ``time_s.shape + (axes,)``.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike
from piezo_stage_ros.core.contracts.errors import PiezoStageError
from piezo_stage_ros.core.contracts.types import FloatArray

__all__ = ['Spline', 'segment_coefficients']

#: Names of the interpolation kinds, by the number of boundary derivatives (0, 1, 2).
KIND_NAMES = ('linear', 'cubic', 'quintic')


def segment_coefficients(duration_s: ArrayLike, start: Sequence[FloatArray],
                         end: Sequence[FloatArray]) -> FloatArray:
    """
    Return the power-basis coefficients of one segment for every axis.

    Parameters
    ----------
    duration_s : float or array_like
        Length T of the segment [s], > 0; for several segments at once, an array that
        broadcasts against the boundary values (e.g. shape (segments, 1)).
    start, end : sequence of ndarray
        Boundary states: ``(position,)`` for linear, ``(position, velocity)`` for cubic,
        ``(position, velocity, acceleration)`` for quintic; each an array over the axes [m,
        m/s, m/s^2] (or segments x axes). Both ends give the same number of derivatives.

    Returns
    -------
    ndarray, shape (6,) + the boundary values' shape
        c_0 ... c_5 of x(tau) = sum c_j tau^j, tau = t - t_a in [0, T] (unused orders zero).

    Notes
    -----
    The cubic and quintic are the Hermite polynomials that meet the given derivatives at both
    ends (joint_trajectory_controller's formulas); the linear one meets the positions only.

    """
    t = np.asarray(duration_s, dtype=np.float64)
    x0 = np.asarray(start[0], dtype=np.float64)
    x1 = np.asarray(end[0], dtype=np.float64)
    c = np.zeros((6,) + np.broadcast_shapes(x0.shape, t.shape))
    c[0] = x0
    order = len(start)
    if order == 1:
        c[1] = (x1 - x0) / t
        return c
    v0 = np.asarray(start[1], dtype=np.float64)
    v1 = np.asarray(end[1], dtype=np.float64)
    c[1] = v0
    if order == 2:
        c[2] = (3.0 * (x1 - x0) - (2.0 * v0 + v1) * t) / t ** 2
        c[3] = (2.0 * (x0 - x1) + (v0 + v1) * t) / t ** 3
        return c
    a0 = np.asarray(start[2], dtype=np.float64)
    a1 = np.asarray(end[2], dtype=np.float64)
    c[2] = 0.5 * a0
    c[3] = (20.0 * (x1 - x0) - (8.0 * v1 + 12.0 * v0) * t - (3.0 * a0 - a1) * t ** 2) \
        / (2.0 * t ** 3)
    c[4] = (30.0 * (x0 - x1) + (14.0 * v1 + 16.0 * v0) * t + (3.0 * a0 - 2.0 * a1) * t ** 2) \
        / (2.0 * t ** 4)
    c[5] = (12.0 * (x1 - x0) - 6.0 * (v1 + v0) * t - (a0 - a1) * t ** 2) / (2.0 * t ** 5)
    return c


class Spline:
    """
    A joint trajectory as polynomial segments in absolute time, evaluated vectorised.

    Parameters
    ----------
    start_s : float
        Time of the start state [s] (the loop's time base).
    start_state : tuple of ndarray
        Position, velocity and acceleration of every axis at ``start_s`` [m, m/s, m/s^2].
    times_s : array_like, shape (points,)
        Absolute times of the points [s], strictly increasing and after ``start_s``.
    positions_m : array_like, shape (points, axes)
        Positions of the points [m].
    velocities_mps, accelerations_mps2 : array_like, optional
        Velocities [m/s] and accelerations [m/s^2] of the points, same shape, or None; the
        accelerations are used only with the velocities.

    Raises
    ------
    PiezoStageError
        If the shapes disagree or the times do not increase (checked in full by
        :func:`piezo_stage_ros.core.loop.goals.validate_goal` before a spline is built).

    """

    def __init__(self, start_s: float, start_state: tuple[ArrayLike, ArrayLike, ArrayLike],
                 times_s: ArrayLike, positions_m: ArrayLike,
                 velocities_mps: ArrayLike | None = None,
                 accelerations_mps2: ArrayLike | None = None) -> None:
        x = np.atleast_2d(np.asarray(positions_m, dtype=np.float64))
        times = np.asarray(times_s, dtype=np.float64).ravel()
        s0 = [np.asarray(s, dtype=np.float64).reshape(x.shape[1]) for s in start_state]
        if times.size != x.shape[0] or times.size == 0:
            raise PiezoStageError(f'spline: {times.size} times for {x.shape[0]} points')
        knots = np.concatenate([[float(start_s)], times])
        if not np.all(np.diff(knots) > 0.0):
            raise PiezoStageError('spline: point times must increase strictly after the start')
        order = 0
        columns: list[FloatArray] = [x]
        if velocities_mps is not None:
            order = 1
            columns.append(np.asarray(velocities_mps, dtype=np.float64).reshape(x.shape))
            if accelerations_mps2 is not None:
                order = 2
                columns.append(np.asarray(accelerations_mps2,
                                          dtype=np.float64).reshape(x.shape))
        # what it was built from, for a copy in another process (record / from_record)
        self._given = (float(start_s), [s.tolist() for s in s0], times.tolist(),
                       [c.tolist() for c in columns])
        self.order = order
        self.kind = KIND_NAMES[order]
        self.axes = x.shape[1]
        self.knots_s = knots
        self.start_state = (s0[0], s0[1], s0[2])
        # all segments at once: segment i runs from point i - 1 (the start state for i = 0)
        starts = [np.concatenate([s0[j][None, :], columns[j][:-1]]) for j in range(order + 1)]
        coeffs = segment_coefficients(np.diff(knots)[:, None], starts, columns)
        self._c = np.ascontiguousarray(np.moveaxis(coeffs, 0, 1))
        self.end_position_m = x[-1].copy()

    def record(self) -> dict[str, Any]:
        """
        Return what the spline was built from, as JSON-ready lists of floats.

        :meth:`from_record` builds it again from them, the same spline bit for bit (a float's
        JSON text reads back as the same float).
        """
        start, state, times, columns = self._given
        return {'start_s': start, 'start_state': state, 'times_s': times, 'columns': columns}

    @classmethod
    def from_record(cls, record: Mapping[str, Any]) -> Spline:
        """
        Return the spline of a :meth:`record`.

        Raises
        ------
        PiezoStageError
            If the record is not one (a key missing, shapes that disagree).

        """
        try:
            columns = list(record['columns'])
            state = record['start_state']
            return cls(float(record['start_s']), (state[0], state[1], state[2]),
                       record['times_s'], *columns[:3])
        except (KeyError, IndexError, TypeError, ValueError) as exc:
            raise PiezoStageError(f'spline record: {exc!r}') from None

    @property
    def start_s(self) -> float:
        """Return the time of the start state [s]."""
        return float(self.knots_s[0])

    @property
    def end_s(self) -> float:
        """Return the time of the last point [s]."""
        return float(self.knots_s[-1])

    def sample(self, time_s: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
        """
        Return position [m], velocity [m/s] and acceleration [m/s^2] at the given times.

        Parameters
        ----------
        time_s : array_like
            Absolute times [s], any shape.

        Returns
        -------
        position_m, velocity_mps, acceleration_mps2 : ndarray
            Each of shape ``time_s.shape + (axes,)``; the start state is held before the start
            (its velocity and acceleration included), the last position at rest after the end.

        """
        t = np.asarray(time_s, dtype=np.float64)
        flat = t.ravel()
        seg = np.clip(np.searchsorted(self.knots_s, flat, side='right') - 1, 0,
                      self._c.shape[0] - 1)
        tau = np.clip(flat - self.knots_s[seg], 0.0,
                      self.knots_s[seg + 1] - self.knots_s[seg])[:, None]
        c = self._c[seg]                      # (samples, 6, axes)
        pos = c[:, 5]
        vel = 5.0 * c[:, 5]
        acc = 20.0 * c[:, 5]
        for j in (4, 3, 2):
            pos = pos * tau + c[:, j]
            vel = vel * tau + j * c[:, j]
            acc = acc * tau + j * (j - 1) * c[:, j]
        pos = pos * tau + c[:, 1]
        pos = pos * tau + c[:, 0]
        vel = vel * tau + c[:, 1]
        before = flat < self.knots_s[0]
        after = flat >= self.knots_s[-1]
        if np.any(before):
            pos[before] = self.start_state[0]
            vel[before] = self.start_state[1]
            acc[before] = self.start_state[2]
        if np.any(after):
            pos[after] = self.end_position_m
            vel[after] = 0.0
            acc[after] = 0.0
        shape = t.shape + (self.axes,)
        return pos.reshape(shape), vel.reshape(shape), acc.reshape(shape)
