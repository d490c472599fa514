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
The paced servo loop of a stage of several axes, without rclpy.

:class:`AxesServoLoop` is :class:`~piezo_stage_ros.nodes.servo.ServoLoop` (its clock, its
start, its skipping after a stall, its run and stop) serving every axis of a sample at once: y_k
of every axis from the guarded backend of N axes (:class:`~piezo_stage_ros.hardware.axes.
AxesGuard`), x_d(t_k) of every axis (:class:`~piezo_stage_ros.core.loop.axes_servo.
AxesReference`), every axis' command and its commands ahead in one call (:class:`~piezo_stage_ros.
core.loop.axes_servo.AxesCommands`), handed to the guard to hold from now on. Each sample goes,
numbered, into a bounded queue (packed into bytes: no object a sample for the garbage
collector to scan), read as :class:`AxesServoSample` by :meth:`AxesServoLoop.drain`;
:meth:`AxesServoLoop.take_batch`
returns the queued samples as an :class:`AxesSampleBatch`: one row per sample, each quantity an
(n, axes) array in the axis order, what one JointState (one joint per axis) or one
Float64MultiArray command a sample carries, and the arrays the multi-axis bag writer takes
(``RunBagWriter.write_samples``).

With an injected clock that is always on time, the samples are those of the offline loop
:func:`~piezo_stage_ros.core.loop.axes.run_axes` bit for bit (``test/test_servo_axes.py``).
The one-axis servo is untouched: a one-axis stage keeps :class:`ServoLoop`.
"""

from __future__ import annotations

import copy
import functools
import math
import struct
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np
from piezo_stage_ros.core.config.axes import AxesLoopConfig
from piezo_stage_ros.core.config.nodes import PlantNodeParams
from piezo_stage_ros.core.contracts.types import FloatArray, IntArray
from piezo_stage_ros.core.contracts.wire import NS_PER_S
from piezo_stage_ros.core.control.axes import AxesController
from piezo_stage_ros.core.loop.axes_servo import AxesCommands, AxesReference, REFERENCE_CHUNK
from piezo_stage_ros.core.model.axes import AxesStageParams
from piezo_stage_ros.hardware.axes import AxesGuard, AxesModelBridge
from piezo_stage_ros.hardware.pacing import Pacer
from piezo_stage_ros.hardware.safety import Trip
from piezo_stage_ros.nodes.servo import ServoLoop

__all__ = ['AxesSampleBatch', 'AxesServoLoop', 'AxesServoSample', 'axes_batch_of',
           'axes_servo_from_config', 'make_axes_bridge', 'sample_of_row']


class AxesServoSample(NamedTuple):
    """
    One sample of every axis, as handed to the ROS side (tuples in the axis order).

    Attributes
    ----------
    k : int
        The sample's number on the grid.
    stamp_ns : int
        t_k [ns].
    positions_m : tuple of float
        y_k [m].
    references_m, velocities_mps : tuple of float
        x_d(t_k) [m], x_d'(t_k) [m/s] (NaN during a wind-down).
    commands_v : tuple of float
        u_k [V] as the controllers computed them (NaN during a wind-down).
    applied_v : tuple of float
        The amplifier inputs held over the sample that y_k ends [V] (after the guard).
    lateness_ns : int
        Time the sample was taken minus its due time [ns].
    true_positions_m : tuple of float
        x(t_k) [m] where the backend knows it (the model), else NaN.

    """

    k: int
    stamp_ns: int
    positions_m: Sequence[float]
    references_m: Sequence[float]
    velocities_mps: Sequence[float]
    commands_v: Sequence[float]
    applied_v: Sequence[float]
    lateness_ns: int
    true_positions_m: Sequence[float]


class AxesSampleBatch(NamedTuple):
    """
    Samples of every axis handed over at once: one row per sample, one column per axis.

    Attributes
    ----------
    number : ndarray of int64, shape (n,)
        Each sample's number among those the servo served (0, 1, 2 ...).
    k, stamp_ns, lateness_ns : ndarray of int64, shape (n,)
        Grid number, t_k [ns], lateness [ns].
    position_m, reference_m, velocity_mps, command_v, applied_v, true_position_m : ndarray
        (n, axes) [m, m, m/s, V, V, m]: y_k, x_d, x_d', u_k, the input held over the sample
        y_k ends, x(t_k) (NaN where unknown).
    axes : tuple of str
        The axis names, in column order.

    """

    number: IntArray
    k: IntArray
    stamp_ns: IntArray
    lateness_ns: IntArray
    position_m: FloatArray
    reference_m: FloatArray
    velocity_mps: FloatArray
    command_v: FloatArray
    applied_v: FloatArray
    true_position_m: FloatArray
    axes: tuple[str, ...]

    @property
    def size(self) -> int:
        """Return the number of samples."""
        return int(self.number.size)


@functools.lru_cache(maxsize=None)
def _row_struct(axes: int) -> struct.Struct:
    """Return the packing of a queued row of ``axes`` axes (4 int64, then 6 N doubles)."""
    return struct.Struct(f'<4q{6 * axes}d')


def axes_batch_of(rows: Sequence[Any], axes: Sequence[str]) -> AxesSampleBatch:
    """
    Return queued rows as an :class:`AxesSampleBatch`.

    A row is flat: number, k, stamp [ns], lateness [ns], then the N values of each of y_k, x_d,
    x_d', u_k, the applied inputs and the true positions; as a tuple, or packed into bytes as
    :class:`AxesServoLoop` queues it (4 little-endian int64, then the doubles: one object a
    sample that the garbage collector never has to look at).
    """
    n, width = len(rows), len(axes)
    if n and isinstance(rows[0], bytes):
        packed = np.frombuffer(b''.join(rows), dtype=np.dtype(
            [('i', '<i8', (4,)), ('f', '<f8', (6, width))]))
        ints = packed['i'].astype(np.int64)
        floats = packed['f'].astype(np.float64)
    else:
        ints = np.array([r[:4] for r in rows], dtype=np.int64).reshape(n, 4)
        floats = np.array([r[4:] for r in rows], dtype=np.float64).reshape(n, 6, width)
    columns = [floats[:, q].copy() for q in range(6)]
    return AxesSampleBatch(ints[:, 0].copy(), ints[:, 1].copy(), ints[:, 2].copy(),
                           ints[:, 3].copy(), columns[0], columns[1], columns[2], columns[3],
                           columns[4], columns[5], tuple(axes))


def sample_of_row(row: Sequence[Any] | bytes, axes: int) -> AxesServoSample:
    """Return one queued row (see :func:`axes_batch_of`) as an :class:`AxesServoSample`."""
    if isinstance(row, bytes):
        row = _row_struct(axes).unpack(row)
    values = [tuple(row[4 + q * axes:4 + (q + 1) * axes]) for q in range(6)]
    return AxesServoSample(row[1], row[2], values[0], values[1], values[2], values[3],
                           values[4], row[3], values[5])


class AxesServoLoop(ServoLoop):
    """
    Backend, references, controllers and safety of every axis, paced by one clock.

    Parameters
    ----------
    plant : AxesGuard
        The backend of N axes behind the safety rules.
    controller : AxesController
        One controller per axis.
    trajectories : sequence of Trajectory
        One per axis; t = 0 is sample 0 (the controller is bound to them here).
    sample_rate_hz, duration_s, pacer, capacity, commands_ahead
        As :class:`~piezo_stage_ros.nodes.servo.ServoLoop` (``commands_ahead`` per axis).
    on_sample : callable, optional
        Called in the loop's thread with each :class:`AxesServoSample`; keep it short.
    chunk : int
        Samples of the references evaluated at once.

    """

    def __init__(self, plant: AxesGuard, controller: AxesController,
                 trajectories: Sequence[Any], *, sample_rate_hz: float,
                 duration_s: float = 0.0, pacer: Pacer | None = None,
                 capacity: int = 65536,
                 on_sample: Callable[[AxesServoSample], None] | None = None,
                 commands_ahead: int = 0, chunk: int = REFERENCE_CHUNK) -> None:
        super().__init__(plant, None, None, sample_rate_hz=sample_rate_hz,  # type: ignore
                         duration_s=duration_s, pacer=pacer, capacity=capacity,
                         on_sample=on_sample, commands_ahead=commands_ahead)  # type: ignore
        #: The guard of the axes (:attr:`plant` too).
        self.guard = plant
        self.axes = plant.names
        self.axes_controller = controller
        controller.bind(list(trajectories))
        self.reference = AxesReference(trajectories, 1.0 / self.rate_hz, chunk=chunk,
                                       names=plant.names)
        self.commands = AxesCommands(controller, self.reference)
        self._fresh = True  # the controllers are reset from the first sample served
        self._true_axes: Callable[[], list[float]] | None = \
            plant.bridge.stage.read_positions_m if isinstance(plant.bridge, AxesModelBridge) \
            else None
        self._nans = (math.nan,) * plant.n
        self._pack = _row_struct(plant.n).pack

    def _serve(self, index: int, position_m: Any, now_ns: int, lateness_ns: int) -> None:
        positions: list[float] = position_m
        stamp = self.stamp_ns(index)
        plant = self.guard
        self.index = index
        true = self._true_axes() if self._true_axes is not None else self._nans
        if plant.winding:
            nans = self._nans
            # one flat row a sample (numbers only), queued packed
            row = (self.pushed, index, stamp, lateness_ns, *positions, *nans, *nans, *nans,
                   *plant.applied_v, *true)
            if plant.phase == 'safe':
                self.done = True
        else:
            refs, vels = self.reference.at(index)
            if self._fresh:
                self._fresh = False
                self.commands.reset(positions, refs)
            commands, ahead = self.commands.step(index, positions, refs, vels,
                                                 self.commands_ahead)
            applied = plant.applied_v
            plant.command(commands, now_ns / NS_PER_S, ahead)
            row = (self.pushed, index, stamp, lateness_ns, *positions, *refs, *vels, *commands,
                   *applied, *true)
        if self.samples.maxlen:
            # packed: a tuple kept in the queue is an object the collector scans until it
            # learns that the tuple holds numbers only, one a sample
            self.samples.append(self._pack(*row))  # type: ignore[arg-type]
            self.pushed += 1
        if self.on_sample is not None:
            self.on_sample(sample_of_row(row, self.guard.n))  # type: ignore[arg-type]
        if self.total and index + 1 >= self.total:
            self.done = True

    def warm_up(self, samples: int = ServoLoop.WARM_UP_SAMPLES) -> str:
        """
        Run the per-sample code on copies of references and controllers before the clock starts.

        As :meth:`ServoLoop.warm_up`: the copies take each axis' reference as its position;
        the run's objects and the backend are not touched.
        """
        if samples <= 0:
            return 'skipped: no samples asked for'
        try:
            commands = copy.deepcopy(self.commands)
            m = self.commands_ahead
            for index in range(samples):
                refs, vels = commands.reference.at(index)
                if index == 0:
                    commands.reset(refs, refs)
                commands.step(index, refs, refs, vels, m)
        except Exception as exc:  # noqa: BLE001 -- an optimisation: the run goes on cold
            return f'skipped: {type(exc).__name__}: {exc}'
        return f'applied: {samples} dry samples on copies'

    def drain(self, limit: int = 0) -> list[AxesServoSample]:  # type: ignore[override]
        """Return the samples queued since the last call, oldest first (at most ``limit``)."""
        self._took_turn()
        out: list[AxesServoSample] = []
        queue, n = self.samples, self.guard.n
        while queue and (not limit or len(out) < limit):
            out.append(sample_of_row(queue.popleft(), n))
        self.drained += len(out)
        return out

    def take_batch(self) -> AxesSampleBatch:  # type: ignore[override]
        """Return the samples queued since the last call as an :class:`AxesSampleBatch`."""
        self._took_turn()
        rows = []
        queue = self.samples
        while queue:
            rows.append(queue.popleft())
        self.drained += len(rows)
        return axes_batch_of(rows, self.axes)  # type: ignore[arg-type]

    def take_trips(self) -> list[Trip]:
        """Return each axis' trips that ended since the last call (the axis in ``causes``)."""
        trips = self.guard.ended_trips
        out: list[Trip] = []
        while trips:
            out.append(trips.popleft()[1])
        return out

    def stats(self) -> dict[str, Any]:
        """Return the guard's counters, the lateness figures and the queue overruns."""
        out = self.guard.stats()
        out.update(self.pacer.stats.summary())
        out.update({'index': self.index, 'queue_overruns':
                    max(self.pushed - self.drained - len(self.samples), 0),
                    'controller_steps': self.commands.steps, 'axes': list(self.axes)})
        if self._turn_every_ns:
            out['handovers'] = self.handovers
        if self.error is not None:
            out['error'] = repr(self.error)
        return out


def make_axes_bridge(stage: AxesStageParams, opts: PlantNodeParams) -> Any:
    """
    Return the backend of N axes the plant node parameters name.

    ``backend: model`` the core model (:class:`AxesModelBridge`); ``udp`` the UDP target of
    several axes (protocol version 4, :class:`~piezo_stage_ros.hardware.udp_axes.
    UdpAxesBridge`).
    """
    if opts.backend == 'udp':
        from piezo_stage_ros.hardware.udp_axes import UdpAxesBridge
        bridge = opts.bridge
        return UdpAxesBridge(bridge.host, bridge.port, stage.n, timeout_s=bridge.timeout_s,
                             max_consecutive_losses=bridge.max_consecutive_losses)
    if opts.backend != 'model':
        from piezo_stage_ros.core.contracts.errors import ParameterError
        raise ParameterError('plant_node backend', opts.backend, "'model' or 'udp' for a "
                             'stage of several axes')
    return AxesModelBridge(stage)


def axes_servo_from_config(loop: AxesLoopConfig, duration_s: float, bridge: Any = None, *,
                           capacity: int = 65536,
                           on_sample: Callable[[AxesServoSample], None] | None = None
                           ) -> AxesServoLoop:
    """
    Return the servo loop of a stage of several axes as ``loop`` configures it.

    The entry of the N-axis servo, as :func:`~piezo_stage_ros.nodes.servo.servo_from_config`
    is the one-axis one: the backend of ``plant_node`` (``bridge`` if given), each axis'
    controller built on its axis' design model (:meth:`AxesController.build`, the coupling
    compensation as configured), the scan's trajectories, the guard with each axis' chain and
    the plant node's watchdog, the clock and ``servo.commands_ahead`` of the plant node.
    """
    stage = loop.stage
    opts = loop.base.plant_node
    rate = stage.axes[0].sample_rate_hz
    period = 1.0 / rate
    ctrl = AxesController.build(loop.controllers, stage, compensate=loop.compensate)
    backend = bridge if bridge is not None else make_axes_bridge(stage, opts)
    guard = AxesGuard(backend, [a.chain for a in stage.axes], stage.names,
                      opts.command_timeout_s, slew_v_per_s=opts.watchdog.slew_v_per_s,
                      sample_period_s=period)
    return AxesServoLoop(guard, ctrl, loop.trajectories(), sample_rate_hz=rate,
                         duration_s=duration_s,
                         pacer=Pacer(round(NS_PER_S / rate),
                                     spin_ns=round(opts.servo.spin_us * 1000)),
                         capacity=capacity, on_sample=on_sample,
                         commands_ahead=opts.servo.commands_ahead)

