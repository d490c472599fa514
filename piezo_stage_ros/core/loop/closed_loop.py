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
The offline closed loop: stage, controller and trajectory stepped at the sample rate, no ROS.

One sample k, in the order of :mod:`piezo_stage_ros.core.contracts.interfaces` (the nodes'
lockstep mode follows the same order, so both give the same samples)::

    t_k = k T
    x_d, x_d' = trajectory(t_k)                    (precomputed per chunk, vectorized)
    u_k = controller.step(y_k, x_d, x_d')
    record (t_k, y_k, x_d, x_d', u_k)  and x(t_k), the true position, when the stage has one
    y_k+1 = stage.step(u_k)

y_0 comes from ``stage.reset()``, and ``controller.reset(y_0, x_d(0))`` is called before the first
step. The loop runs in chunks (default one second): the reference of a chunk is evaluated at
once, outputs go into preallocated arrays, and a ``chunk_callback`` receives each chunk as a
:class:`RunRecord` (streamed to a bag, or reduced to per-minute statistics by the soak) so that
memory stays flat however long the run.

Controller diagnostics are read by :func:`piezo_stage_ros.core.contracts.wire.diagnostic_reader`,
the reader the controller node uses too (names in sorted order), every ``diagnostics_every``
samples and held in between (zero-order), which keeps the per-sample cost of the loop low.

A simulated stage also knows its true position x(t_k) behind y_k (before sensor noise and ADC):
the loop records it as ``true_position_m`` when the plant offers it (:func:`true_position_reader`:
:class:`~piezo_stage_ros.core.model.stage.Stage`'s plain function ``read_position_m``, else a
``position_m`` attribute), so that metrics can show the tracking error below the sensor noise.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping, Protocol, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError, PiezoStageError
from piezo_stage_ros.core.contracts.interfaces import Controller, Trajectory
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.contracts.wire import diagnostic_reader
from piezo_stage_ros.core.loop.record import RunRecord

__all__ = ['ChunkCallback', 'Plant', 'concatenate', 'run', 'true_position_reader']


#: Receives every chunk of a run as it is produced.
ChunkCallback = Callable[[RunRecord], None]


class Plant(Protocol):
    """What the loop needs of a stage (:class:`~piezo_stage_ros.core.model.stage.Stage` has it)."""

    @property
    def sample_time_s(self) -> float:
        """The sample period [s]."""
        ...

    def reset(self, position_m: float | None = None) -> float:
        """Put the stage at rest and return the measured position y_0 [m]."""
        ...

    def step(self, command_v: float) -> float:
        """Hold the command over one sample and return the measured position [m]."""
        ...


def true_position_reader(stage: object) -> Callable[[], float] | None:
    """
    Return a function reading a plant's true position now [m], or None if it has none.

    Parameters
    ----------
    stage : object
        The plant: a ``read_position_m()`` function is used as it is (the cheap path of
        :class:`~piezo_stage_ros.core.model.stage.Stage`); else a ``position_m`` attribute or
        property is read on each call; else there is no true position (a real stage).

    Returns
    -------
    callable or None

    """
    read = getattr(stage, 'read_position_m', None)
    if callable(read):
        return read  # type: ignore[no-any-return]
    if hasattr(stage, 'position_m'):
        return lambda: float(stage.position_m)  # type: ignore[attr-defined]
    return None


def run(stage: Plant, controller: Controller, trajectory: Trajectory, *, duration_s: float,
        initial_position_m: float | None = None, record_diagnostics: bool = True,
        diagnostics_every: int = 10, chunk_s: float = 1.0,
        chunk_callback: ChunkCallback | None = None, keep: bool = True,
        meta: Mapping[str, Any] | None = None, record_true_position: bool = True
        ) -> RunRecord:
    """
    Run the closed loop for ``duration_s`` and return the record of every sample.

    Parameters
    ----------
    stage : Plant
        The stage (reset here to ``initial_position_m``).
    controller : Controller
        The controller (reset here from y_0 and x_d(0)); its ``sample_time_s`` must equal the
        stage's.
    trajectory : Trajectory
        The reference; t = 0 is the first sample.
    duration_s : float
        Simulated time [s]; the run has ``round(duration_s / T)`` samples, at least one.
    initial_position_m : float, optional
        Rest position of the stage at the start [m]; default the stage's own default.
    record_diagnostics : bool
        Record the controller's diagnostics.
    diagnostics_every : int
        Read the diagnostics every this many samples (held in between), >= 1.
    chunk_s : float
        Length of one chunk [s] (reference evaluation and callback granularity), > 0.
    chunk_callback : callable, optional
        Called with each chunk (a :class:`RunRecord` whose ``time_s`` continues across chunks
        and whose ``meta`` is the run's meta) as soon as it is complete.
    keep : bool
        Keep every chunk and return the whole run; with ``False`` only the last chunk is returned
        (for long runs streamed through ``chunk_callback``).
    meta : Mapping, optional
        Description of the run, copied into the record's ``meta`` (``sample_time_s``,
        ``duration_s`` and, when the trajectory has ``period_s``, ``trajectory_period_s`` are
        added; a scan line's ``lines`` as ``trajectory_lines``).
    record_true_position : bool
        Record the stage's true position x(t_k) as ``true_position_m`` when it has one
        (:func:`true_position_reader`); False leaves it None.

    Returns
    -------
    RunRecord
        The samples (see :mod:`piezo_stage_ros.core.loop.record`).

    Raises
    ------
    ParameterError
        If ``duration_s``, ``chunk_s`` or ``diagnostics_every`` is out of range, or the
        controller's sample time differs from the stage's.

    """
    dt = float(stage.sample_time_s)
    if not (duration_s > 0.0 and math.isfinite(duration_s)):
        raise ParameterError('duration_s', duration_s, '(0, inf)')
    if not (chunk_s > 0.0 and math.isfinite(chunk_s)):
        raise ParameterError('chunk_s', chunk_s, '(0, inf)')
    if diagnostics_every < 1:
        raise ParameterError('diagnostics_every', diagnostics_every, '[1, inf)')
    ctrl_dt = float(controller.sample_time_s)
    if abs(ctrl_dt - dt) > 1e-12 * dt:
        raise ParameterError('controller.sample_time_s', ctrl_dt,
                             f'the stage sample time {dt:g} s',
                             'differs from the stage sample time')
    total = max(int(round(duration_s / dt)), 1)
    per_chunk = max(int(round(chunk_s / dt)), 1)
    run_meta: dict[str, Any] = dict(meta or {})
    run_meta.setdefault('sample_time_s', dt)
    run_meta['duration_s'] = total * dt
    period = getattr(trajectory, 'period_s', None)
    if isinstance(period, float) and period > 0.0:
        run_meta.setdefault('trajectory_period_s', period)
    lines = getattr(trajectory, 'lines', None)
    if isinstance(lines, dict):
        # the linear part of a scan line, so that the line metrics need only the record
        run_meta.setdefault('trajectory_lines', dict(lines))

    bind = getattr(controller, 'bind', None)
    if callable(bind):
        bind(trajectory)  # a feed-forward reads the reference ahead from the trajectory
    y = float(stage.reset(initial_position_m))
    xd0, _ = trajectory.evaluate(np.zeros(1))
    controller.reset(y, float(xd0[0]))
    names: tuple[str, ...] = ()
    read_diag: Callable[[], Sequence[float]] | None = None
    if record_diagnostics:
        names, read_diag = diagnostic_reader(controller)

    chunks: list[RunRecord] = []
    last: RunRecord | None = None
    ctrl_step = controller.step
    plant_step = stage.step
    read_true = true_position_reader(stage) if record_true_position else None
    pos_out: list[float] = []
    cmd_out: list[float] = []
    true_out: list[float] = []
    pos_append = pos_out.append
    cmd_append = cmd_out.append
    true_append = true_out.append

    # The hot loop over consecutive samples: plain floats, bound methods, no allocation per
    # sample. The true position x(t_k) is read before the plant steps, beside y_k.
    def span(y: float, refs: Sequence[float], vels: Sequence[float]) -> float:
        for xd, vd in zip(refs, vels):
            u = ctrl_step(y, xd, vd)
            pos_append(y)
            cmd_append(u)
            y = plant_step(u)
        return y

    def span_true(y: float, refs: Sequence[float], vels: Sequence[float]) -> float:
        assert read_true is not None
        for xd, vd in zip(refs, vels):
            u = ctrl_step(y, xd, vd)
            pos_append(y)
            true_append(read_true())
            cmd_append(u)
            y = plant_step(u)
        return y
    steps = span if read_true is None else span_true

    k0 = 0
    while k0 < total:
        n = min(per_chunk, total - k0)
        time_s = (np.arange(k0, k0 + n, dtype=np.float64)) * dt
        ref, vel = trajectory.evaluate(time_s)
        ref = np.asarray(ref, dtype=np.float64)
        vel = np.asarray(vel, dtype=np.float64)
        if ref.shape != time_s.shape or vel.shape != time_s.shape:
            raise PiezoStageError('trajectory.evaluate returned arrays of shape '
                                  f'{ref.shape} and {vel.shape}, expected {time_s.shape}')
        diag_rows: list[Sequence[float]] = []
        ref_l = ref.tolist()
        vel_l = vel.tolist()
        if read_diag is None:
            y = steps(y, ref_l, vel_l)
        else:
            # blocks of `every` samples: the diagnostics are read after the first step of each
            # block (and held over it), the rest of the block runs the plain loop
            every = diagnostics_every
            diag_append = diag_rows.append
            for b0 in range(0, n, every):
                u = ctrl_step(y, ref_l[b0], vel_l[b0])
                pos_append(y)
                if read_true is not None:
                    true_append(read_true())
                cmd_append(u)
                diag_append(read_diag())
                y = plant_step(u)
                y = steps(y, ref_l[b0 + 1:b0 + every], vel_l[b0 + 1:b0 + every])
        diagnostics: dict[str, FloatArray] = {}
        if names:
            table = np.asarray(diag_rows, dtype=np.float64).reshape(len(diag_rows), len(names))
            held = np.repeat(table, diagnostics_every, axis=0)[:n]
            diagnostics = {name: np.ascontiguousarray(held[:, j])
                           for j, name in enumerate(names)}
        chunk = RunRecord(time_s=time_s, position_m=np.asarray(pos_out, dtype=np.float64),
                          reference_m=ref, reference_velocity_mps=vel,
                          command_v=np.asarray(cmd_out, dtype=np.float64),
                          diagnostics=diagnostics, meta=run_meta,
                          true_position_m=(np.asarray(true_out, dtype=np.float64)
                                           if read_true is not None else None))
        pos_out.clear()
        cmd_out.clear()
        true_out.clear()
        if chunk_callback is not None:
            chunk_callback(chunk)
        if keep:
            chunks.append(chunk)
        last = chunk
        k0 += n
    assert last is not None
    return concatenate(chunks, meta=run_meta) if keep else last


def concatenate(records: Sequence[RunRecord], *, meta: Mapping[str, Any] | None = None
                ) -> RunRecord:
    """
    Join consecutive records of one run into one.

    Parameters
    ----------
    records : sequence of RunRecord
        Chunks in time order with the same diagnostic names; the result has a true position
        when every chunk has one.
    meta : Mapping, optional
        Meta of the result; default the first record's.

    Returns
    -------
    RunRecord

    """
    if not records:
        raise PiezoStageError('concatenate: no records')
    if len(records) == 1:
        only = records[0]
        return RunRecord(only.time_s, only.position_m, only.reference_m,
                         only.reference_velocity_mps, only.command_v, dict(only.diagnostics),
                         dict(meta if meta is not None else only.meta), only.true_position_m)

    def cat(name: str) -> FloatArray:
        return np.concatenate([getattr(r, name) for r in records])
    names = list(records[0].diagnostics)
    diagnostics = {k: np.concatenate([r.diagnostics[k] for r in records]) for k in names}
    # the true position is kept only when every chunk has it
    true = (cat('true_position_m') if all(r.true_position_m is not None for r in records)
            else None)
    return RunRecord(cat('time_s'), cat('position_m'), cat('reference_m'),
                     cat('reference_velocity_mps'), cat('command_v'), diagnostics,
                     dict(meta if meta is not None else records[0].meta), true)
