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
The paced servo loop of real-time mode, without rclpy: one owner of the sample clock.

One :class:`ServoLoop` runs the whole sample in one place, in the order of
:mod:`piezo_stage_ros.core.contracts.interfaces`: wait for the due time
(:class:`~piezo_stage_ros.hardware. pacing.Pacer`), measure y_k through the guarded backend (which
holds u_k-1 over the sample that just ended), x_d(t_k) from the trajectory (evaluated ahead in
chunks), u_k from the controller, and hand u_k to the backend to hold from now on. Nothing in that
path waits for ROS: each sample goes, numbered, into a bounded queue (:attr:`ServoLoop.samples`)
that the ROS side drains (:meth:`ServoLoop.take_batch`: as the columns of
:class:`~piezo_stage_ros.nodes.recording.SampleBatch`) and publishes in batches; a full queue
drops its oldest entries and counts them (``queue_overruns``), the servo never blocks.

Parameters changed through ROS reach the loop as they reach the logic objects
(:meth:`~piezo_stage_ros.nodes.logic.ControllerLogic.request_change`,
:meth:`~piezo_stage_ros.nodes.logic.TrajectoryLogic.switch` ...): one attribute set, applied at
the next sample boundary by the servo thread.

With an injected clock that is always on time, the loop's samples are those of the offline
runner bit for bit (``test/test_servo.py``); with a stalled clock, the skipped samples are
counted and the schedule moves on (no catch-up burst).
"""

from __future__ import annotations

from collections import deque
import copy
import functools
import gc
import math
import multiprocessing
from multiprocessing import shared_memory
import os
import queue
import signal
import threading
import time
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np
from piezo_stage_ros.core.config.loader import LoopConfig
from piezo_stage_ros.core.config.nodes import PlantNodeParams
from piezo_stage_ros.core.contracts.errors import ParameterError, PiezoStageError
from piezo_stage_ros.core.contracts.interfaces import Controller
from piezo_stage_ros.core.contracts.wire import JOINT_NAME, NS_PER_S
from piezo_stage_ros.core.control.ahead import CommandPredictor
from piezo_stage_ros.core.control.controllers import (
    bound_controller,
    ControllerParams,
    SENSOR_GAIN_V_PER_M,
)
from piezo_stage_ros.core.loop.closed_loop import true_position_reader
from piezo_stage_ros.core.loop.follow import FollowParams, GoalFollower, SplineTrajectory
from piezo_stage_ros.core.loop.goals import AxisLimits, finish, Steps
from piezo_stage_ros.core.loop.trajectories import make_trajectory
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant, PlantParams, StageParams
from piezo_stage_ros.hardware.bridge import Bridge, ModelBridge
from piezo_stage_ros.hardware.pacing import Pacer, servo_setup
from piezo_stage_ros.hardware.safety import GuardedPlant, Trip
from piezo_stage_ros.hardware.udp import UdpBridge, UdpStreamBridge
from piezo_stage_ros.nodes.logic import (
    ControllerLogic,
    rebuild_or_learn_afresh,
    sample_count,
    save_learned_table,
    TrajectoryLogic,
)
from piezo_stage_ros.nodes.recording import SampleBatch

# the float columns of a ring row before the diagnostics (SampleRing.FLOATS)
_VALUES = 6

__all__ = ['apply_change', 'batch_of', 'freeze_gc', 'make_bridge', 'SampleRing', 'samples_of',
           'servo_from_config', 'ServoLoop', 'ServoProcess', 'ServoSample', 'unfreeze_gc']

# the servo loops of this process that hold the garbage collector frozen (freeze_gc)
_gc_lock = threading.Lock()
_gc_holders = [0]


def freeze_gc() -> None:
    """
    Move everything the process holds now out of the garbage collector's reach (a servo's start).

    The first holder collects first (:func:`gc.collect`, before its clock starts), then
    :func:`gc.freeze`: the collections during the run scan only what the run makes, instead
    of stopping a sample now and then for milliseconds (the oldest generation: every table,
    module and configuration) to scan them all again. A loop that starts while another runs
    freezes what was built since, without a collection that would stall the running one.
    Each call is paired with :func:`unfreeze_gc`; the last one gives them back.
    """
    with _gc_lock:
        if _gc_holders[0] == 0:
            gc.collect()
        gc.freeze()
        _gc_holders[0] += 1


def unfreeze_gc() -> None:
    """
    End a :func:`freeze_gc`; the last holder gives the frozen objects back to the collector.

    Frozen objects are never collected: a cycle of them dropped after the run (the run's own
    objects, a servo started again in the process) would otherwise stay for the process' life.
    :func:`gc.unfreeze` gives back every frozen object, those frozen before the first holder
    too (Python 3.12 starts with some): the collector then scans them as old objects.
    """
    with _gc_lock:
        _gc_holders[0] = max(_gc_holders[0] - 1, 0)
        if _gc_holders[0] == 0:
            gc.unfreeze()


class ServoSample(NamedTuple):
    """
    One sample of the servo loop, as handed to the ROS side.

    Attributes
    ----------
    k : int
        The sample's number on the grid (skipped samples leave gaps).
    stamp_ns : int
        t_k [ns].
    position_m : float
        y_k [m].
    reference_m, velocity_mps : float
        x_d(t_k) [m], x_d'(t_k) [m/s] (NaN for the plant alone).
    command_v : float
        u_k [V] as the controller computed it (NaN for the plant alone).
    applied_v : float
        The amplifier input the plant held over the sample that y_k ends [V]: u_k-1 after the
        guard, the safe voltage at the start or after the watchdog tripped (what the plant
        applied, whatever arrived).
    lateness_ns : int
        Time the sample was taken minus its due time [ns].
    diagnostics : sequence of float or None
        Controller internals (every ``diagnostics_every`` samples).
    diagnostic_names : tuple of str or None
        Their names (those of the controller that computed them; None without diagnostics).
    true_position_m : float
        x(t_k) [m], the true position behind y_k where the backend knows it (the model of
        :class:`~piezo_stage_ros.hardware.bridge.ModelBridge`); NaN otherwise.

    """

    k: int
    stamp_ns: int
    position_m: float
    reference_m: float
    velocity_mps: float
    command_v: float
    applied_v: float
    lateness_ns: int
    diagnostics: Sequence[float] | None
    diagnostic_names: tuple[str, ...] | None = None
    true_position_m: float = math.nan


class SampleRing:
    """
    A single-writer ring of servo samples in shared memory, for a servo loop in another process.

    The writer (the servo process) stores each sample in row ``n % capacity`` and then
    increments the count ``n``; a reader copies the rows written since its last read and tells
    from the count how many it missed (overwritten before it came). No lock: one writer, the
    count is written after its row (x86 and ARM64 keep the order of these two stores as seen
    from Python), and a reader only copies. Stamps stay integers (int64 [ns]).

    Each row has the integer columns :data:`INTS` and the float columns :data:`FLOATS`, then
    ``diagnostics`` float columns for the controller internals of the samples that carry them
    (every ``diagnostics_every``-th): a row stores how many it filled (0: none) and the number
    of their layout (their names). The names do not go through the ring: a writer that meets
    names it has not passed on yet numbers them (0, 1 ...: a structural change of the
    controller may rebuild it of another kind, with other names) and hands them to
    :attr:`on_layout` before it writes the row, so that a reader has them (through a pipe that
    keeps the order, :class:`ServoProcess`) before it can read a row of that layout. A sample
    with more internals than ``diagnostics`` columns is stored without them and counted in
    :attr:`dropped` (the writer's side).

    A header of int64 words beside the count carries the control of the process that writes
    (:data:`HEADER`): ``halt`` (set by the parent: stop after the current sample), ``posted``
    (changes put in the queue of :class:`ServoProcess`, so that the servo looks at the queue
    only when something is in it), ``applied`` (changes the servo has applied) and the live
    counters of the servo's clock, written by the servo every
    :data:`ServoProcess.LIVE_EVERY` samples for the parent's status.

    Parameters
    ----------
    capacity : int
        Rows (samples) the ring holds (when creating it).
    name : str, optional
        Attach to an existing ring of that name (the other process); default: create one.
        The side that attaches takes the capacity and the diagnostics columns from the ring's
        header, so that both sides always share one layout.
    diagnostics : int
        Columns for controller internals (when creating it; the controllers of the core
        report at most 8: the RAC).

    """

    INTS = ('k', 'stamp_ns', 'lateness_ns', 'layout', 'diagnostics')
    FLOATS = ('position_m', 'reference_m', 'velocity_mps', 'command_v', 'applied_v',
              'true_position_m')
    HEADER = ('count', 'halt', 'posted', 'applied', 'index', 'paced_samples',
              'late_half_period', 'skipped', 'lateness_max_ns', 'watchdog_trips',
              'ramp_samples', 'safe_samples', 'recovery_samples', 'capacity', 'diagnostics')
    #: The header words :meth:`ServoProcess.stats` reports while the run goes on.
    LIVE = ('index', 'paced_samples', 'late_half_period', 'skipped', 'watchdog_trips',
            'ramp_samples', 'safe_samples', 'recovery_samples')

    def __init__(self, capacity: int = 65536, name: str | None = None, *,
                 diagnostics: int = 16) -> None:
        head = 8 * len(self.HEADER)
        n_ints = len(self.INTS)
        if name is None:
            if capacity < 1 or diagnostics < 0:
                raise ValueError(f'sample ring: capacity {capacity} (>= 1), diagnostics '
                                 f'{diagnostics} (>= 0)')
            self.capacity, self.width = int(capacity), int(diagnostics)
            size = head + self.capacity * 8 * (n_ints + len(self.FLOATS) + self.width)
            self.shm = shared_memory.SharedMemory(create=True, size=size)
        else:
            self.shm = shared_memory.SharedMemory(name=name)
            known = np.ndarray((len(self.HEADER),), dtype=np.int64, buffer=self.shm.buf)
            self.capacity = int(known[self.HEADER.index('capacity')])
            self.width = int(known[self.HEADER.index('diagnostics')])
            del known
        n_floats = len(self.FLOATS) + self.width
        buf = self.shm.buf
        self.header = np.ndarray((len(self.HEADER),), dtype=np.int64, buffer=buf)
        self._count = self.header[0:1]
        self._ints = np.ndarray((self.capacity, n_ints), dtype=np.int64, buffer=buf,
                                offset=head)
        self._floats = np.ndarray((self.capacity, n_floats), dtype=np.float64, buffer=buf,
                                  offset=head + self.capacity * 8 * n_ints)
        if name is None:
            self.header[:] = 0
            self.header[self.HEADER.index('index')] = -1
            self.header[self.HEADER.index('capacity')] = self.capacity
            self.header[self.HEADER.index('diagnostics')] = self.width
        self.read = 0
        #: The writer's side: ``on_layout(number, names)`` is called with diagnostic names not
        #: passed on before, before the first row that carries them is written.
        self.on_layout: Callable[[int, tuple[str, ...]], None] | None = None
        #: The writer's side: the number of the current layout (-1: none yet).
        self.layout = -1
        self._names: tuple[str, ...] | None = None
        #: The writer's side: samples stored without their internals (more than the columns).
        self.dropped = 0

    @property
    def name(self) -> str:
        """Return the name another process attaches with."""
        return str(self.shm.name)

    def get(self, key: str) -> int:
        """Return the header word ``key`` (one of :data:`HEADER`)."""
        return int(self.header[self.HEADER.index(key)])

    def set(self, key: str, value: int) -> None:
        """Set the header word ``key`` (one of :data:`HEADER`)."""
        self.header[self.HEADER.index(key)] = value

    def append(self, s: ServoSample) -> None:
        """Store one sample (the writer's side; never waits but for :attr:`on_layout`)."""
        n = int(self._count[0])
        row = n % self.capacity
        floats = self._floats[row]
        values = s.diagnostics
        width = 0
        if values is not None:
            names = s.diagnostic_names
            if names is not self._names and names != self._names:
                # names not passed on yet: the reader gets them before it can read the row
                self.layout += 1
                self._names = names
                if self.on_layout is not None and names is not None:
                    self.on_layout(self.layout, names)
            width = len(values)
            if width > self.width:
                self.dropped += 1
                width = 0
            else:
                floats[_VALUES:_VALUES + width] = values
        self._ints[row] = (s.k, s.stamp_ns, s.lateness_ns, self.layout, width)
        floats[:_VALUES] = (s.position_m, s.reference_m, s.velocity_mps, s.command_v,
                            s.applied_v, s.true_position_m)
        self._count[0] = n + 1

    def take(self) -> tuple[Any, Any, int]:
        """
        Return the samples written since the last call (the reader's side).

        Returns
        -------
        ints : ndarray of int64, shape (n, 5)
            Columns :attr:`INTS`: k, stamp [ns], lateness [ns], the layout of the
            diagnostics and how many the row carries (0: none).
        floats : ndarray of float64, shape (n, 6 + diagnostics)
            Columns :attr:`FLOATS`, then the diagnostics (the first as many as the row
            carries).
        missed : int
            Samples overwritten before they were read.

        """
        _, ints, floats, missed = self.take_numbered()
        return ints, floats, missed

    def take_numbered(self) -> tuple[int, Any, Any, int]:
        """
        Return the samples written since the last call, with the number of the first.

        As :meth:`take`, with first the number of the first row returned among all the rows
        ever written (0, 1, 2 ...: the rows that follow it are numbered on without gaps).
        """
        end = int(self._count[0])
        missed = max(end - self.read - self.capacity, 0)
        start = self.read + missed
        rows = np.arange(start, end) % self.capacity
        self.read = end
        return start, self._ints[rows], self._floats[rows], missed

    def close(self, unlink: bool = False) -> None:
        """Detach (and remove, by the creator)."""
        del self._count, self._ints, self._floats, self.header
        self.shm.close()
        if unlink:
            self.shm.unlink()


class ServoLoop:
    """
    Plant I/O, trajectory, controller and safety of every sample, paced by one clock.

    Parameters
    ----------
    plant : GuardedPlant
        The backend behind the safety rules.
    trajectory : TrajectoryLogic or None
        x_d for each stamp.
    controller : ControllerLogic or None
        u_k for (y_k, x_d); its position watchdog is fed by every sample. Without controller
        and trajectory the loop is the plant alone: it samples on its clock and holds whatever
        :meth:`GuardedPlant.command` gave it last (a controller in another node); a sample
        without a new command since the previous one is counted late by the guard.
    sample_rate_hz : float
        Sample rate [Hz].
    duration_s : float
        Run ``round(duration_s * rate)`` samples of the grid (skipped ones included); 0: on
        until :meth:`stop`.
    pacer : Pacer, optional
        The clock; default a :class:`~piezo_stage_ros.hardware.pacing.Pacer` on
        :func:`time.monotonic_ns`. A backend that owns the clock
        (:class:`~piezo_stage_ros.hardware.udp.UdpStreamBridge`: a real-time target streams
        its samples) paces the loop instead: each sample is served when it arrives, its
        lateness is the arrival against the grid of the first one, and gaps count as skipped.
    capacity : int
        Samples the queue to the ROS side holds (65536: 6.5 s at 10 kHz); 0: no queue (the
        samples go only to ``on_sample``, e.g. :meth:`SampleRing.append` in another process).
    on_sample : callable, optional
        Called in the loop's thread with each sample as soon as it is served (the plant alone
        publishes y_k at once, for a controller in another node); keep it short.
    commands_ahead : int
        With each command, the controller's prediction of this many next ones goes to the
        guard and the backend (:mod:`piezo_stage_ros.core.control.ahead`), applied over
        samples the loop misses; 0: the last command is held.

    """

    def __init__(self, plant: GuardedPlant, trajectory: TrajectoryLogic | None,
                 controller: ControllerLogic | None, *, sample_rate_hz: float,
                 duration_s: float = 0.0, pacer: Pacer | None = None,
                 capacity: int = 65536,
                 on_sample: Callable[[ServoSample], None] | None = None,
                 commands_ahead: int = 0) -> None:
        self.plant = plant
        self.commands_ahead = int(commands_ahead)
        period_s = 1.0 / float(sample_rate_hz)
        # in the controller's sensor volts (read from it; the paper's K_PSCM until then)
        self._predictor = CommandPredictor(SENSOR_GAIN_V_PER_M, period_s)
        self.trajectory = trajectory
        self.controller = controller
        self.rate_hz = float(sample_rate_hz)
        period_ns = round(NS_PER_S / self.rate_hz)
        self.pacer = pacer if pacer is not None else Pacer(period_ns)
        self.total = sample_count(duration_s, self.rate_hz)
        # (number among the samples served, sample)
        self.samples: deque[tuple[int, ServoSample]] = deque(maxlen=max(0, capacity))
        self.pushed = 0
        self.drained = 0
        self.start_ns = 0
        self.index = -1
        self.done = False
        self.error: BaseException | None = None
        self.setup_report: dict[str, str] = {}
        #: The voltage held after the last sample served (its command after the guard).
        self.held_v = plant.safe_v
        # a bridge that owns the clock (UdpStreamBridge: the target paces, the host answers)
        self.bridge_clock: Any = plant.bridge if hasattr(plant.bridge, 'sample_index') \
            else None
        self._t0_arrival = 0
        self.on_sample = on_sample
        # x(t_k) behind y_k, for the recording, where the backend is the model
        self._true = true_position_reader(plant.bridge.stage) \
            if isinstance(plant.bridge, ModelBridge) else None
        #: Called after each sample served (a sample boundary); returning False ends the run.
        self.boundary: Callable[[], bool] | None = None
        #: Called with :attr:`setup_report` as soon as the setup of :meth:`run` has run.
        self.on_setup: Callable[[dict[str, str]], None] | None = None
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None
        # a loop in a thread beside the executor: the executor's turns at the interpreter lock
        # (share_interpreter); 0: never handed over
        self._turn = threading.Event()
        self._turn_ns = 0
        self._turn_every_ns = 0
        #: Samples at which the loop waited for the executor to take its turn.
        self.handovers = 0
        #: :meth:`run` freezes the garbage collector's view of what was built before its
        #: clock starts (:func:`freeze_gc`) and gives it back at its end.
        self.freeze_gc = True
        self._frozen = False

    def stamp_ns(self, index: int) -> int:
        """Return t_k [ns] of grid sample ``index``, as the plant node stamps it."""
        return self.start_ns + round(index * NS_PER_S / self.rate_hz)

    def _serve(self, index: int, position_m: float, now_ns: int, lateness_ns: int) -> None:
        stamp = self.stamp_ns(index)
        plant = self.plant
        self.index = index
        if self.controller is None or self.trajectory is None or plant.winding:
            # the plant alone: the command comes from elsewhere (another node), held as is;
            # or the wind-down (GuardedPlant.wind_down) ramps, the controller no longer asked
            sample = ServoSample(index, stamp, position_m, math.nan, math.nan, math.nan,
                                 plant.applied_v, lateness_ns, None, None,
                                 self._true() if self._true is not None else math.nan)
            if plant.winding and plant.phase == 'safe':
                self.done = True
        else:
            now_s = now_ns / NS_PER_S
            ref, vel = self.trajectory.on_position(stamp)
            at = self.trajectory.take_switch()
            if at is not None:
                # a start or a new trajectory: its t = 0 is this sample, bound at this step
                self.controller.request_trajectory(self.trajectory.trajectory, at)
            # the goals' tolerances and feedback take y_k against that x_d
            self.trajectory.observe(stamp, position_m)
            self.controller.on_position(stamp, position_m, now_s)
            out = self.controller.on_reference(stamp, ref, vel)
            u = out.voltage_v if out is not None else self.controller.safe_voltage_v
            applied = plant.applied_v
            m = self.commands_ahead
            trajectory = self.trajectory
            if self.bridge_clock is not None:
                # the target waits for this answer: it leaves now, its commands ahead (only
                # the samples the host misses need them) and the bookkeeping after it
                plant.command(u, now_s)
                plant.release(now_s)
                if m and out is not None:
                    wanted = getattr(self.bridge_clock, 'ahead_wanted', None)
                    if wanted is None or wanted(m):
                        plant.follow(self._predictor.predict(
                            self.controller.controller, m, u, ref, vel,
                            lambda count: trajectory.window(stamp, count)))
                    else:
                        self._predictor.observe(self.controller.controller, u, ref, vel)
            elif m and out is not None:
                plant.command(u, now_s, self._predictor.predict(
                    self.controller.controller, m, u, ref, vel,
                    lambda count: trajectory.window(stamp, count)))
            else:
                plant.command(u, now_s)
            self.held_v = plant.held_v
            sample = ServoSample(index, stamp, position_m, ref, vel, u, applied, lateness_ns,
                                 out.diagnostics if out else None,
                                 out.diagnostic_names if out else None,
                                 self._true() if self._true is not None else math.nan)
        if self.samples.maxlen:
            self.samples.append((self.pushed, sample))
            self.pushed += 1
        if self.on_sample is not None:
            self.on_sample(sample)
        if self.total and index + 1 >= self.total:
            self.done = True

    #: Dry samples :meth:`warm_up` runs before the clock starts.
    WARM_UP_SAMPLES = 64

    def warm_up(self, samples: int = WARM_UP_SAMPLES) -> str:
        """
        Run the per-sample code on copies of trajectory and controller before the clock starts.

        A cold loop pays for its first calls (the interpreter specialising the code, numpy's
        caches, first allocations): measured here about 0.3 ms for sample 0 and 50-80 us too
        much for the next few, so that every real-time start skipped samples 1-3 and the stage
        fell away under a held command. The copies take the reference as position; the
        trajectory, controller, predictor and backend of the run are not touched.

        Returns
        -------
        str
            ``'applied: ...'``, or why not (``'skipped: ...'``; the run goes on cold).

        """
        if self.controller is None or self.trajectory is None or samples <= 0:
            return 'skipped: no controller in this loop'
        try:
            trajectory, controller, predictor = copy.deepcopy(
                (self.trajectory, self.controller, self._predictor))
            m = self.commands_ahead
            period = NS_PER_S / self.rate_hz
            for index in range(samples):
                stamp = round(index * period)
                now_s = time.monotonic()
                ref, vel = trajectory.on_position(stamp)
                controller.on_position(stamp, ref, now_s)
                out = controller.on_reference(stamp, ref, vel)
                if m and out is not None:
                    predictor.predict(controller.controller, m, out.voltage_v, ref, vel,
                                      functools.partial(trajectory.window, stamp))
        except Exception as exc:  # noqa: BLE001 -- an optimisation: the run goes on cold
            return f'skipped: {type(exc).__name__}: {exc}'
        return f'applied: {samples} dry samples on copies'

    def start(self, start_ns: int = 0, since_ns: int | None = None) -> None:
        """
        Start the backend and serve sample 0 now.

        Parameters
        ----------
        start_ns : int
            t_0 [ns] of the stamps (the ROS time of the start).
        since_ns : int, optional
            The monotonic time [ns] at which ``start_ns`` was read (in another process: the
            clock is system-wide); sample 0 is then stamped ``start_ns`` plus the time since,
            so that the stamps stay on the ROS clock however long the start took (a spawned
            process imports for a second or two). None: ``start_ns`` as given.

        """
        # the backend's start (the model's reset: about 0.1 ms) before the clock's: in sample
        # 0 it made samples 1-2 late, skipped while the RAC's start-up transient ran
        y0 = self.plant.start(time.monotonic())
        if self.bridge_clock is not None:
            bridge = self.bridge_clock
            self._t0_arrival = bridge.arrival_ns - bridge.sample_index * self.pacer.period_ns
            # the grid's origin: the first sample taken may be a later one (the host takes the
            # newest waiting; those before it played the safe voltage and count as skipped)
            self._set_origin(start_ns, since_ns, self._t0_arrival)
            first = min(bridge.sample_index, self.total) if self.total else bridge.sample_index
            if first > 0:
                self.pacer.stats.skip(first)
            self.pacer.stats.add(0)
            self._serve(bridge.sample_index, y0, bridge.arrival_ns, 0)
            return
        self.pacer.start()
        index, lateness = self.pacer.wait()  # sample 0, due now
        now = self.pacer.due_ns(index) + lateness
        self.plant.watchdog.arm(now / NS_PER_S)  # on the loop's clock, from sample 0
        self._set_origin(start_ns, since_ns, now)
        self._serve(index, y0, now, lateness)

    def _set_origin(self, start_ns: int, since_ns: int | None, now_ns: int) -> None:
        self.start_ns = int(start_ns) + (now_ns - since_ns if since_ns is not None else 0)

    def share_interpreter(self, every_s: float) -> None:
        """
        Hand the interpreter lock to the thread that takes the samples when its turn is overdue.

        For a loop in a thread beside the ROS executor (:meth:`start_thread`), whose timer
        takes the samples (:meth:`take_batch`, :meth:`drain`: each call is a turn). When the
        last turn began ``every_s`` [s] ago or more, the loop waits before its next sample
        until the executor has begun one (at most a period), in a blocking wait that frees
        the lock. CPython's own switching cannot be relied on here: a thread waiting for the
        lock asks the holder to drop it only when a whole switch interval passed without a
        wake-up, and the loop releases the lock and takes it back at once now and then (numpy
        over a chunk of the trajectory, a socket poll): each release wakes the waiter, which
        finds the lock taken again and waits a whole interval anew. Releases as often as the
        interval (chunks of 5 ms against CPython's 5 ms) keep it waiting for good, and the
        samples pile up. 0: never (the loop's own thread is the only one that needs the lock).
        """
        if not 0.0 <= every_s < math.inf:
            raise ParameterError('every_s', every_s, '[0, inf)')
        self._turn_every_ns = round(every_s * NS_PER_S)
        self._turn_ns = self.pacer.clock()

    def _took_turn(self) -> None:
        # the executor's side: it holds the interpreter lock now
        self._turn_ns = self.pacer.clock()
        self._turn.set()

    def _hand_over(self) -> None:
        # the loop's side, before it waits for its next sample
        clock, every, turn = self.pacer.clock, self._turn_every_ns, self._turn
        if clock() - self._turn_ns < every:
            return
        turn.clear()
        if clock() - self._turn_ns < every:
            return  # taken meanwhile
        self.handovers += 1
        turn.wait(self.pacer.period_ns / NS_PER_S)

    def step(self) -> bool:
        """Wait for the next sample, serve it, and return whether the run goes on."""
        if self.done:
            return False
        if self._turn_every_ns:
            self._hand_over()
        trajectory = self.trajectory
        if trajectory is not None and trajectory.has_work:
            self._idle_work(trajectory)
        if self.bridge_clock is not None:
            return self._step_on_target_clock(self.bridge_clock)
        before = self.pacer.index
        index, lateness = self.pacer.wait()
        if index - before > 1:
            self.plant.skipped(index - before - 1)
        if self.total and index >= self.total:
            # a stall ran past the end of the run: nothing left to take, and the samples after
            # its end were never due in it
            self.pacer.stats.remove(lateness)
            self.pacer.stats.skipped -= index - self.total
            self.done = True
            return False
        now = self.pacer.due_ns(index) + lateness
        self._serve(index, self.plant.sample(now / NS_PER_S), now, lateness)
        return not self.done

    #: Idle work (a slice of a goal's check) starts only while the next sample is due at
    #: least this fraction of a period ahead.
    IDLE_MARGIN = 0.25

    def _idle_work(self, trajectory: TrajectoryLogic) -> None:
        """Do slices of the goals' checks while the next sample is far enough ahead."""
        if self.bridge_clock is not None:
            # the target's next sample has no due time here: one slice a sample
            trajectory.work()
            return
        pacer = self.pacer
        due = pacer.due_ns(pacer.index + 1)
        margin = round(self.IDLE_MARGIN * pacer.period_ns)
        while due - pacer.clock() > margin and trajectory.work():
            pass

    def _step_on_target_clock(self, bridge: Any) -> bool:
        # the target owns the clock: the sample's number and arrival come from the bridge; the
        # lateness is the arrival against the grid of the first arrival
        before = bridge.sample_index
        position = self.plant.sample(time.monotonic())
        index = bridge.sample_index
        if index == before:
            return True  # nothing arrived in time (counted lost by the bridge); wait again
        last = min(index, self.total) if self.total else index
        if last - before > 1:
            self.pacer.stats.skip(last - before - 1)
        if self.total and index >= self.total:
            self.done = True  # the gap ran past the end of the run
            return False
        lateness = bridge.arrival_ns - (self._t0_arrival + index * self.pacer.period_ns)
        self.pacer.stats.add(lateness)
        self._serve(index, position, bridge.arrival_ns, lateness)
        return not self.done

    def run(self, start_ns: int = 0,
            setup: Callable[[], Any] | None = None, since_ns: int | None = None) -> None:
        """
        Start and serve samples until the run is complete, :meth:`stop`, or an error.

        ``start_ns``, ``since_ns``: as :meth:`start`; ``setup`` runs first, in this thread,
        then :meth:`warm_up` and, with :attr:`freeze_gc`, :func:`freeze_gc` (undone at the end).

        An error drives the safe voltage (:meth:`GuardedPlant.fault`) and is kept in
        :attr:`error` for the caller to report; the backend is stopped at the end either way.
        """
        try:
            report = dict(self.setup_report)
            if setup is not None:
                report = dict(setup() or {})
            report['warm_up'] = self.warm_up()
            # whole at once: the executor reads it from its own thread once it is not empty
            # (an entry added while it iterates the dictionary ended its iteration with an error)
            self.setup_report = report
            if self.on_setup is not None:
                self.on_setup(self.setup_report)
            if self.freeze_gc:
                # after the warm-up: its copies are collected, not frozen
                freeze_gc()
                self._frozen = True
            self.start(start_ns, since_ns)
            halt, boundary = self._halt, self.boundary
            while not halt.is_set() and self.step():
                if boundary is not None and not boundary():
                    break
        except BaseException as exc:  # noqa: BLE001 -- any fault: safe voltage, then report
            self.error = exc
            self.plant.fault(exc)
        finally:
            self.done = True
            self.plant.stop()
            if self._frozen:
                self._frozen = False
                unfreeze_gc()

    def start_thread(self, start_ns: int = 0, setup: Callable[[], Any] | None = None,
                     since_ns: int | None = None) -> threading.Thread:
        """Run :meth:`run` in a daemon thread (``setup`` runs first, in that thread)."""
        self._thread = threading.Thread(target=self.run, args=(start_ns, setup, since_ns),
                                        name='servo', daemon=True)
        self._thread.start()
        return self._thread

    @property
    def finished(self) -> bool:
        """Return whether the thread of :meth:`start_thread` has ended."""
        return self._thread is not None and not self._thread.is_alive()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Ask the loop to stop after the current sample and wait for its thread."""
        self._halt.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)

    def drain(self, limit: int = 0) -> list[ServoSample]:
        """
        Return the samples queued since the last call, oldest first (at most ``limit``; 0: all).

        Called from another thread than the loop's: ``deque`` appends and pops are atomic.
        """
        self._took_turn()
        out: list[ServoSample] = []
        queue = self.samples
        while queue and (not limit or len(out) < limit):
            out.append(queue.popleft()[1])
        self.drained += len(out)
        return out

    def take_batch(self) -> SampleBatch:
        """Return the samples queued since the last call as columns (the block recording)."""
        self._took_turn()
        items = []
        queue = self.samples
        while queue:
            items.append(queue.popleft())
        self.drained += len(items)
        return batch_of(items)

    def take_trips(self) -> list[Trip]:
        """Return the watchdog trips that ended since the last call, oldest first."""
        trips = self.plant.ended_trips
        out: list[Trip] = []
        while trips:
            out.append(trips.popleft())
        return out

    def stats(self) -> dict[str, Any]:
        """Return the plant counters, the lateness figures and the queue overruns."""
        out = self.plant.stats()
        out.update(self.pacer.stats.summary())
        out.update({'index': self.index, 'queue_overruns':
                    max(self.pushed - self.drained - len(self.samples), 0),
                    'controller_steps': self.controller.steps if self.controller else 0})
        if self._turn_every_ns:
            out['handovers'] = self.handovers
        if self.error is not None:
            out['error'] = repr(self.error)
        return out



def samples_of(batch: SampleBatch, first: int = 0) -> list[ServoSample]:
    """
    Return rows ``first ...`` of a batch as :class:`ServoSample`.

    Diagnostics are named by their layout (None where the batch has no names for it: the
    publisher then uses its own).
    """
    ints, floats, layouts = batch.ints[first:], batch.floats[first:], batch.layouts
    diagnostics = floats[:, len(SampleRing.FLOATS):]
    out = []
    for i, ((k, stamp, late, layout, n), (p, r, v, c, a, x)) in enumerate(zip(
            ints.tolist(), floats[:, :len(SampleRing.FLOATS)].tolist())):
        if n:
            out.append(ServoSample(k, stamp, p, r, v, c, a, late,
                                   tuple(diagnostics[i, :n].tolist()), layouts.get(layout), x))
        else:
            out.append(ServoSample(k, stamp, p, r, v, c, a, late, None, None, x))
    return out


def batch_of(items: Sequence[tuple[int, ServoSample]]) -> SampleBatch:
    """Return numbered samples (``(number, sample)``) as the columns of a batch."""
    n = len(items)
    width = max((len(s.diagnostics) for _, s in items if s.diagnostics is not None),
                default=0)
    ints = np.zeros((n, len(SampleRing.INTS)), dtype=np.int64)
    floats = np.full((n, len(SampleRing.FLOATS) + width), np.nan)
    numbers = np.empty(n, dtype=np.int64)
    layouts: dict[tuple[str, ...], int] = {}
    for i, (number, s) in enumerate(items):
        numbers[i] = number
        layout, count = -1, 0
        if s.diagnostics is not None and s.diagnostic_names is not None:
            layout = layouts.setdefault(s.diagnostic_names, len(layouts))
            count = len(s.diagnostics)
            floats[i, len(SampleRing.FLOATS):len(SampleRing.FLOATS) + count] = s.diagnostics
        ints[i] = (s.k, s.stamp_ns, s.lateness_ns, layout, count)
        floats[i, :_VALUES] = (s.position_m, s.reference_m, s.velocity_mps, s.command_v,
                               s.applied_v, s.true_position_m)
    return SampleBatch(numbers, ints, floats, {v: k for k, v in layouts.items()})


def make_bridge(stage: StageParams, opts: PlantNodeParams) -> Bridge:
    """
    Return the backend the plant node parameters name.

    The host of a target-paced stream (``udp_stream``) polls its socket without blocking when
    the servo loop spins anyway (``servo.spin_us`` at or above the period): a thread asleep in
    ``recv`` wakes tens of microseconds after its datagram on a virtual machine.
    """
    bridge = opts.bridge
    if opts.backend == 'udp_stream':
        period_ns = round(NS_PER_S / stage.sample_rate_hz)
        return UdpStreamBridge(bridge.host, bridge.port, timeout_s=bridge.timeout_s,
                               max_consecutive_losses=bridge.max_consecutive_losses,
                               spin=opts.servo.spin_us * 1000 >= period_ns, period_ns=period_ns)
    if opts.backend == 'udp':
        return UdpBridge(bridge.host, bridge.port, timeout_s=bridge.timeout_s,
                         max_consecutive_losses=bridge.max_consecutive_losses)
    return ModelBridge(stage)


def servo_from_config(loop: LoopConfig, duration_s: float, bridge: Bridge | None = None, *,
                      capacity: int = 65536,
                      on_sample: Callable[[ServoSample], None] | None = None,
                      design_plant: PlantParams | None = None) -> ServoLoop:
    """
    Return the servo loop of plant, controller and trajectory as ``loop`` configures them.

    What the three nodes of ``stage_servo --direct`` build from the same parameters: the
    backend of ``plant_node`` (``bridge`` if given), the controller on the design model
    (rebuilt for a structural change), the trajectory evaluated in real-time chunks.
    ``design_plant``: the controller node's design model, if not ``loop.design_plant`` (an
    identified model read from a file).
    """
    stage = loop.stage
    period = 1.0 / stage.sample_rate_hz
    design = linear_plant(design_plant if design_plant is not None else loop.design_plant)
    cn, tn = loop.controller_node, loop.trajectory_node
    hysteresis = make_hysteresis(stage.hysteresis)
    # one trajectory object (its evaluation is pure): played by the trajectory logic, read
    # ahead by a feed-forward
    reference = make_trajectory(loop.trajectory)
    # the trajectory bound last (at the sample of its t = 0): a rebuild binds that one
    bound = [reference]

    def build(params: ControllerParams) -> Controller:
        return bound_controller(params, period, design, hysteresis, bound[0])
    controller = ControllerLogic(
        build(loop.controller), mode='realtime',
        safe_voltage_v=cn.safe_voltage_v, position_timeout_s=cn.position_timeout_s,
        diagnostics_every=cn.diagnostics_every,
        # the controller node warns about a table it cannot load after a change; here too the
        # new controller learns afresh instead of faulting at a sample
        rebuild=lambda params: rebuild_or_learn_afresh(build, params),
        on_bound=lambda trajectory: bound.__setitem__(0, trajectory), trajectory=reference)
    trajectory = TrajectoryLogic(reference, sample_rate_hz=stage.sample_rate_hz,
                                 chunk_s=min(tn.chunk_s, 0.005), active=tn.active)
    # goals are checked outside the sample, for one a little ahead (ServoProcess.change)
    trajectory.attach_goals(GoalFollower((JOINT_NAME,), [AxisLimits.from_stage(stage)],
                                         [trajectory.hold_m], FollowParams(sample_time_s=period)),
                            lead_s=0.02)
    trajectory.on_reference_change = controller.request_trajectory
    # the feed-forward's first block of a goal's reference, computed where the goal is checked
    # (outside the sample), taken at the sample the goal starts at
    follower = trajectory.follower
    assert follower is not None
    follower.prepare = functools.partial(  # type: ignore[method-assign]
        _prepare_goal, follower, controller, stage.sample_rate_hz)
    follower.preparing = functools.partial(  # type: ignore[method-assign]
        _preparing_goal, follower, controller, stage.sample_rate_hz)
    # a goal is checked a slice at a time in the loop's own thread, in the time its samples
    # leave free (ServoLoop.step), not in a thread beside it that takes the interpreter from it
    trajectory.check_in_slices = True
    opts = loop.plant_node
    plant = GuardedPlant(bridge if bridge is not None else make_bridge(stage, opts),
                         stage.chain, opts.command_timeout_s,
                         slew_v_per_s=opts.watchdog.slew_v_per_s, sample_period_s=period)
    return ServoLoop(plant, trajectory, controller, sample_rate_hz=stage.sample_rate_hz,
                     duration_s=duration_s,
                     pacer=Pacer(round(NS_PER_S / stage.sample_rate_hz),
                                 spin_ns=round(opts.servo.spin_us * 1000)),
                     capacity=capacity, on_sample=on_sample,
                     commands_ahead=opts.servo.commands_ahead)


def _prepare_goal(follower: GoalFollower, controller: ControllerLogic, rate_hz: float,
                  goal: Any, time_s: float, **options: Any) -> tuple[Any, Any]:
    return finish(_preparing_goal(follower, controller, rate_hz, goal, time_s, **options))


def _preparing_goal(follower: GoalFollower, controller: ControllerLogic, rate_hz: float,
                    goal: Any, time_s: float, **options: Any) -> Steps[tuple[Any, Any]]:
    # GoalFollower.preparing, then the controller's first block of the goal's reference ahead
    # (a feed-forward's prepare_block: used only where it is what the start would compute)
    verdict, prepared = yield from GoalFollower.preparing(follower, goal, time_s, **options)
    prepare_block = getattr(controller.controller, 'prepare_block', None)
    if prepared is not None and prepare_block is not None:
        yield
        prepare_block(SplineTrajectory(prepared.spline), round(time_s * rate_hz))
    return verdict, prepared


def apply_change(servo: ServoLoop, kind: str, value: Any) -> None:
    """
    Apply one change of :meth:`ServoProcess.change` to the loop (in the servo's process).

    ``kind``: ``'controller'`` (ControllerParams, applied by the controller at its next
    sample), ``'trajectory'`` (TrajectoryParams: the new trajectory starts at the next
    sample), ``'active'`` (bool: start or stop the trajectory), ``'wind_down'`` (ramp to the
    safe voltage at the slew, then end the run: :meth:`GuardedPlant.wind_down`) or ``'set'``
    (``(path, value)``, an attribute under ``controller``, ``trajectory`` or ``plant``, e.g.
    ``('controller.watchdog.timeout_s', 0.02)``).
    """
    if kind == 'controller':
        assert servo.controller is not None
        servo.controller.request_change(value)
    elif kind == 'trajectory':
        assert servo.trajectory is not None
        # checked against the sample rate as the trajectory node checks it (a change from
        # elsewhere than that node is refused here, between samples, with the reason)
        trajectory = make_trajectory(value, sample_rate_hz=servo.rate_hz)
        if servo.controller is not None:
            # what the feed-forward can compute of the new line goes here, between samples,
            # not into the step of the sample where the line starts
            servo.controller.prepare_trajectory(trajectory)
        servo.trajectory.switch(trajectory)
    elif kind == 'active':
        assert servo.trajectory is not None
        if value:
            servo.trajectory.start()
        else:
            servo.trajectory.stop()
    elif kind == 'wind_down':
        servo.plant.wind_down()
    elif kind in ('goal', 'cancel', 'hold'):
        _apply_goal(servo, kind, value)
    elif kind == 'set':
        path, new = value
        names = str(path).split('.')
        if names[0] not in ('controller', 'trajectory', 'plant'):
            raise ValueError(f'servo change: path {path!r} must start with controller, '
                             'trajectory or plant')
        target: Any = servo
        for name in names[:-1]:
            target = getattr(target, name)
        if not hasattr(target, names[-1]):
            raise ValueError(f'servo change: no attribute {path!r}')
        setattr(target, names[-1], new)
    else:
        raise ValueError(f'servo change: kind {kind!r}; allowed: controller, trajectory, '
                         'active, wind_down, set, goal, cancel, hold')


def _apply_goal(servo: ServoLoop, kind: str, value: Any) -> None:
    """
    Apply a goal (``(token, goal, tracked, stamp_ns)``), a cancel (token) or a hold.

    A goal is checked for the sample ``TrajectoryLogic`` starts it at: a slice at a time by
    the loop's own thread between samples (:attr:`TrajectoryLogic.check_in_slices`, as
    :func:`servo_from_config` builds it), else in a thread of its own (the check runs over
    every sample of the trajectory); a cancel or a hold is taken at the next sample.
    """
    logic = servo.trajectory
    assert logic is not None
    if kind == 'goal':
        token, goal, tracked, stamp = value
        if logic.check_in_slices:
            logic.goal(token, goal, tracked=tracked, stamp_ns=stamp)
        else:
            threading.Thread(target=logic.goal, args=(token, goal),
                             kwargs={'tracked': tracked, 'stamp_ns': stamp}, daemon=True).start()
    elif kind == 'cancel':
        logic.cancel(int(value))
    else:
        logic.hold()


def _servo_main(loop: LoopConfig, design_plant: PlantParams | None, duration_s: float,
                ring_name: str, start_ns: int, since_ns: int, changes: Any,
                results: Any) -> None:
    # the servo process: no rclpy here, nothing else in this interpreter. Ctrl-C reaches the
    # whole process group: the parent stops this process (halt word), so SIGINT is ignored;
    # SIGTERM (the parent's last resort) and a parent that vanished end the run the same way
    # as a halt: safe voltage, backend stopped (ServoLoop.run). ``results`` is the sending end
    # of a pipe: messages go out in order and at once (no feeder thread), so that the parent
    # has a layout of diagnostic names before it can read a row of it
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    ring = SampleRing(name=ring_name)  # its capacity and columns from its header
    parent = os.getppid()
    stop = [False]
    signal.signal(signal.SIGTERM, lambda *_: stop.__setitem__(0, True))

    def send(message: tuple[str, Any]) -> None:
        try:
            results.send(message)
        except OSError:
            pass  # the parent is gone (its end of the pipe closed): nobody to tell

    try:
        servo = servo_from_config(loop, duration_s, capacity=0, on_sample=ring.append,
                                  design_plant=design_plant)
        # the real-time setup's report goes out as soon as it has run, not with the figures
        servo.on_setup = lambda report: send(('setup', report))
        ring.on_layout = lambda number, names: send(('layout', (number, names)))
        # each watchdog trip as it ends, for the parent to log (rare: a pipe message is fine)
        servo.plant.on_trip = lambda trip: send(('trip', trip))
        header = ring.header
        halt, posted = SampleRing.HEADER.index('halt'), SampleRing.HEADER.index('posted')
        # the controller's parameters as changed at run time (where its table is to be saved)
        params = [loop.controller]
        assert servo.trajectory is not None
        goal_events = servo.trajectory.events
        applied = 0
        served = 0
        stats = servo.pacer.stats
        guard = servo.plant
        every = ServoProcess.LIVE_EVERY

        def boundary() -> bool:
            nonlocal applied, served
            served += 1
            if header[posted] != applied:
                try:
                    while True:
                        kind, value = changes.get_nowait()
                        applied += 1
                        apply_change(servo, kind, value)
                        if kind == 'controller':
                            params[0] = value
                        ring.set('applied', applied)
                except queue.Empty:
                    pass  # the rest is still in the queue's pipe: taken at a later sample
            if goal_events:
                # verdicts, results, feedback to the parent; a goal the reference changed under
                # is checked again here
                while goal_events:
                    event = goal_events.popleft()
                    if event[0] == 'retry':
                        _apply_goal(servo, 'goal', event[1:])
                    else:
                        send(('goal', event))
            if served % every == 0:
                ring.set('index', servo.index)
                ring.set('paced_samples', stats.samples)
                ring.set('late_half_period', stats.late_half)
                ring.set('skipped', stats.skipped)
                ring.set('lateness_max_ns', stats.max_ns)
                ring.set('watchdog_trips', guard.watchdog.trips)
                ring.set('ramp_samples', guard.ramp_samples)
                ring.set('safe_samples', guard.safe_samples)
                ring.set('recovery_samples', guard.recovery_samples)
                if os.getppid() != parent:
                    return False
            return not (header[halt] or stop[0])

        servo.boundary = boundary
        servo.run(start_ns, setup=lambda: servo_setup(loop.plant_node.servo,
                                                      servo.pacer.period_ns),
                  since_ns=since_ns)
        ring.set('index', servo.index)
        out = servo.stats()
        out['held_v'] = servo.held_v
        # what the backend holds now: the safe voltage the stop or the fault drove
        out['stopped_at_v'] = servo.plant.held_v
        out['setup'] = servo.setup_report
        out['diagnostics_dropped'] = ring.dropped
        # this process ran the controller: its learned table is the one to keep
        assert servo.controller is not None
        try:
            line = save_learned_table(servo.controller.controller,
                                      params[0].feedforward.save_table_file)
        except PiezoStageError as err:
            line = f'learned table not written: {err}'
        if line is not None:
            out['learned_table'] = line
        send(('final', out))
    except BaseException as exc:  # noqa: BLE001 -- reported to the parent, which faults
        send(('final', {'error': repr(exc)}))
    finally:
        ring.close()
        results.close()


class ServoProcess:
    """
    The servo loop of ``loop`` in a process of its own, started with ``spawn`` (no rclpy).

    The process builds plant, controller and trajectory from ``loop``
    (:func:`servo_from_config`), owns the backend and runs :meth:`ServoLoop.run`: its
    interpreter does nothing else, so the executor of the ROS side never holds a lock the
    servo waits for. The samples come back through a :class:`SampleRing` (:meth:`take`),
    changes go to it through a queue (:meth:`change`, applied at the next sample boundary).
    Messages come back through a pipe, in the order sent: the report of the real-time setup
    as soon as it has run (:attr:`setup_report`), the names of the controller's diagnostics
    before the first sample that carries them (:meth:`drain`), and the figures at the end
    (:meth:`stop`). Any error in the process drives the safe voltage there (the process owns
    the backend) and is reported in ``stats()['error']``.

    Parameters
    ----------
    loop : LoopConfig
        Stage, plant node, controller and trajectory parameters (picklable).
    duration_s : float
        As :class:`ServoLoop` (0: until :meth:`stop`).
    capacity : int
        Samples the ring holds (65536: 6.5 s at 10 kHz).
    diagnostics : int
        Columns for the controller's diagnostics in the ring (:class:`SampleRing`).
    design_plant : PlantParams, optional
        The controller's design model, if not ``loop.design_plant``.
    context : str
        The multiprocessing start method, ``'spawn'`` or ``'forkserver'`` (not ``'fork'``: a
        fork of a process with rclpy's threads is not safe).

    """

    #: Samples between two updates of the live counters in the ring's header.
    LIVE_EVERY = 1000

    def __init__(self, loop: LoopConfig, duration_s: float = 0.0, *, capacity: int = 65536,
                 diagnostics: int = 16, design_plant: PlantParams | None = None,
                 context: str = 'spawn') -> None:
        if context not in ('spawn', 'forkserver'):
            raise ValueError(f"servo process: context {context!r}; allowed: 'spawn', "
                             "'forkserver'")
        self.loop = loop
        self.design_plant = design_plant
        self.duration_s = float(duration_s)
        self._ctx: Any = multiprocessing.get_context(context)
        self.ring = SampleRing(capacity, diagnostics=diagnostics)
        self._changes = self._ctx.Queue()
        self._results, self._sender = self._ctx.Pipe(duplex=False)
        self._proc: Any = None
        self.result: dict[str, Any] | None = None
        self.missed = 0
        self._setup: dict[str, str] = {}
        self._layouts: dict[int, tuple[str, ...]] = {}
        self._trips: list[Trip] = []
        self._goal_events: list[tuple[Any, ...]] = []
        self._ended = False  # the process closed its end of the pipe
        self._joined = False

    def start(self, start_ns: int = 0) -> None:
        """
        Start the process; ``start_ns`` [ns] is the ROS time now.

        Sample 0 is stamped ``start_ns`` plus the time the process took to start (its
        imports), measured on the monotonic clock: the stamps are the ROS time of each sample.
        """
        self._proc = self._ctx.Process(
            target=_servo_main, args=(self.loop, self.design_plant, self.duration_s,
                                      self.ring.name, int(start_ns), time.monotonic_ns(),
                                      self._changes, self._sender),
            name='servo', daemon=True)
        self._proc.start()
        # the child has its copy: with this one closed, the pipe ends when the process does
        self._sender.close()

    def _receive(self, timeout_s: float = 0.0) -> None:
        # take the messages sent so far (waiting up to timeout_s for the first one)
        reader = self._results
        wait = timeout_s
        try:
            while not self._ended and not reader.closed and reader.poll(wait):
                kind, payload = reader.recv()
                wait = 0.0
                if kind == 'setup':
                    self._setup = dict(payload)
                elif kind == 'layout':
                    number, names = payload
                    self._layouts[int(number)] = tuple(names)
                elif kind == 'trip':
                    self._trips.append(payload)
                elif kind == 'goal':
                    self._goal_events.append(payload)
                else:
                    self.result = dict(payload)
                    self._setup = self._setup or dict(self.result.get('setup', {}))
        except (EOFError, OSError):
            self._ended = True

    @property
    def started(self) -> bool:
        """Return whether :meth:`start` was called."""
        return self._proc is not None

    @property
    def finished(self) -> bool:
        """Return whether the process has ended (its run complete, stopped or failed)."""
        return self._proc is not None and not self._proc.is_alive()

    @property
    def table_line(self) -> str | None:
        """Return what the process did with its learned table (``None``: nothing to write)."""
        value = (self.result or {}).get('learned_table')
        return None if value is None else str(value)

    def change(self, kind: str, value: Any) -> None:
        """Send a change (see :func:`apply_change`), applied at the servo's next sample."""
        if kind not in ('controller', 'trajectory', 'active', 'wind_down', 'set', 'goal',
                        'cancel', 'hold'):
            raise ValueError(f'servo change: kind {kind!r}; allowed: controller, trajectory, '
                             'active, wind_down, set, goal, cancel, hold')
        if kind == 'trajectory':
            # refused here, with the reason, rather than in the servo's sample
            make_trajectory(value, sample_rate_hz=self.loop.stage.sample_rate_hz)
        self._changes.put((kind, value))
        self.ring.set('posted', self.ring.get('posted') + 1)

    def take_goal_events(self) -> list[tuple[Any, ...]]:
        """Return the goals' events the servo sent since the last call (``TrajectoryLogic``)."""
        self._receive()
        events, self._goal_events = self._goal_events, []
        return events

    def take(self) -> tuple[Any, Any, int]:
        """Return the samples handed over since the last call (:meth:`SampleRing.take`)."""
        ints, floats, missed = self.ring.take()
        self.missed += missed
        return ints, floats, missed

    def stop(self, timeout_s: float = 5.0) -> dict[str, Any]:
        """
        Stop the process after its current sample, wait for it and return its figures.

        The process drives the safe voltage and stops its backend itself; if it does not end
        within ``timeout_s`` it is terminated (SIGTERM: the same path), then killed.
        """
        if self._proc is None:
            return {}
        if self.result is None:
            self.ring.set('halt', 1)
            end = time.monotonic() + timeout_s
            while self.result is None and not self._ended and time.monotonic() < end:
                self._receive(end - time.monotonic())
            if self.result is None:
                self.result = {'error': 'servo process ended without its figures'
                               if self._ended else
                               f'servo process gave no figures in {timeout_s:g} s'}
        if not self._joined:
            # the figures may have come with a drain, just before the process ended
            self._joined = True
            self._proc.join(timeout_s)
            if self._proc.is_alive():
                self._proc.terminate()
                self._proc.join(timeout_s)
            if self._proc.is_alive():
                self._proc.kill()
                self._proc.join()
        return self.result

    def poll(self) -> dict[str, Any] | None:
        """Return the figures of a run that has ended (``None`` while it goes on)."""
        if self.result is None and self.finished:
            return self.stop()
        return self.result

    def stats(self) -> dict[str, Any]:
        """Return the final figures, or the live counters of a run in progress."""
        out: dict[str, Any]
        if self.poll() is not None:
            assert self.result is not None
            out = {k: v for k, v in self.result.items() if k not in ('setup', 'learned_table')}
        else:
            ring = self.ring
            out = {k: ring.get(k) for k in SampleRing.LIVE}
            out['lateness_max_us'] = round(ring.get('lateness_max_ns') / 1e3, 1)
        out['ring_missed'] = self.missed
        return out

    # the interface of ServoLoop the plant node uses, so that it drives either

    @property
    def done(self) -> bool:
        """Return whether the run has ended."""
        return self.finished

    @property
    def index(self) -> int:
        """Return the grid number of the last sample served (-1 before the first)."""
        return int(self.result['index']) if self.result and 'index' in self.result \
            else self.ring.get('index')

    @property
    def error(self) -> BaseException | None:
        """Return the error the run ended with (as a PiezoStageError), or None."""
        text = (self.poll() or {}).get('error')
        return PiezoStageError(f'servo process: {text}') if text else None

    @property
    def setup_report(self) -> dict[str, str]:
        """Return what the process's real-time setup applied or was refused (once it ran)."""
        if not self._setup and self._proc is not None:
            self._receive()
        return dict(self._setup)

    @property
    def held_v(self) -> float:
        """Return the voltage held after the last sample (NaN before the end)."""
        return float((self.result or {}).get('held_v', math.nan))

    def take_trips(self) -> list[Trip]:
        """Return the watchdog trips the process reported since the last call, oldest first."""
        self._receive()
        out, self._trips = self._trips, []
        return out

    def drain(self, limit: int = 0) -> list[ServoSample]:
        """
        Return the samples handed over since the last call, as :class:`ServoSample`.

        With the controller's diagnostics on the samples that carry them, named as the
        controller that computed them named them (a layout sent before the first of its rows
        was written: received here after the rows were taken, it is always in).
        """
        return samples_of(self.take_batch())

    def take_batch(self) -> SampleBatch:
        """Return the samples handed over since the last call as columns, numbered."""
        start, ints, floats, missed = self.ring.take_numbered()
        self.missed += missed
        self._receive()
        return SampleBatch(np.arange(start, start + ints.shape[0], dtype=np.int64), ints,
                           floats, dict(self._layouts))

    def close(self) -> None:
        """Stop the process if it runs, remove the ring and close the pipe."""
        self.stop()
        self.ring.close(unlink=True)
        self._results.close()
        self._sender.close()
