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
:mod:`piezo_stage_ros.core.interfaces`: wait for the due time (:class:`~piezo_stage_ros.hardware.
pacing.Pacer`), measure y_k through the guarded backend (which holds u_k-1 over the sample that
just ended), x_d(t_k) from the trajectory (evaluated ahead in chunks), u_k from the controller,
and hand u_k to the backend to hold from now on. Nothing in that path waits for ROS: each
sample goes as a tuple into a bounded queue (:attr:`ServoLoop.samples`) that the ROS side
drains and publishes in batches; a full queue drops its oldest entries and counts them
(``queue_overruns``), the servo never blocks.

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
import math
from multiprocessing import shared_memory
import threading
import time
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np
from piezo_stage_ros.core.wire import NS_PER_S
from piezo_stage_ros.hardware.pacing import Pacer
from piezo_stage_ros.hardware.safety import GuardedPlant
from piezo_stage_ros.nodes.logic import ControllerLogic, sample_count, TrajectoryLogic

__all__ = ['SampleRing', 'ServoLoop', 'ServoSample']


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


class SampleRing:
    """
    A single-writer ring of servo samples in shared memory, for a servo loop in another process.

    The writer (the servo process) stores each sample in row ``n % capacity`` and then
    increments the count ``n``; a reader copies the rows written since its last read and tells
    from the count how many it missed (overwritten before it came). No lock: one writer, the
    count is written after its row (x86 and ARM64 keep the order of these two stores as seen
    from Python), and a reader only copies. Stamps stay integers (int64 [ns]).

    Parameters
    ----------
    capacity : int
        Rows (samples) the ring holds.
    name : str, optional
        Attach to an existing ring of that name (the other process); default: create one.

    """

    FLOATS = ('position_m', 'reference_m', 'velocity_mps', 'command_v', 'applied_v')

    def __init__(self, capacity: int = 65536, name: str | None = None) -> None:
        self.capacity = int(capacity)
        size = 8 + self.capacity * 8 * (3 + len(self.FLOATS))
        self.shm = shared_memory.SharedMemory(name=name, create=name is None, size=size)
        buf = self.shm.buf
        self._count = np.ndarray((1,), dtype=np.int64, buffer=buf)
        self._ints = np.ndarray((self.capacity, 3), dtype=np.int64, buffer=buf, offset=8)
        self._floats = np.ndarray((self.capacity, len(self.FLOATS)), dtype=np.float64,
                                  buffer=buf, offset=8 + self.capacity * 24)
        if name is None:
            self._count[0] = 0
        self.read = 0

    @property
    def name(self) -> str:
        """Return the name another process attaches with."""
        return str(self.shm.name)

    def append(self, s: ServoSample) -> None:
        """Store one sample (the writer's side; never waits)."""
        n = int(self._count[0])
        row = n % self.capacity
        self._ints[row] = (s.k, s.stamp_ns, s.lateness_ns)
        self._floats[row] = (s.position_m, s.reference_m, s.velocity_mps, s.command_v,
                             s.applied_v)
        self._count[0] = n + 1

    def take(self) -> tuple[Any, Any, int]:
        """
        Return the samples written since the last call (the reader's side).

        Returns
        -------
        ints : ndarray of int64, shape (n, 3)
            k, stamp [ns], lateness [ns] per sample.
        floats : ndarray of float64, shape (n, 5)
            Columns :attr:`FLOATS`.
        missed : int
            Samples overwritten before they were read.

        """
        end = int(self._count[0])
        missed = max(end - self.read - self.capacity, 0)
        start = self.read + missed
        rows = [i % self.capacity for i in range(start, end)]
        self.read = end
        return self._ints[rows].copy(), self._floats[rows].copy(), missed

    def close(self, unlink: bool = False) -> None:
        """Detach (and remove, by the creator)."""
        del self._count, self._ints, self._floats
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

    """

    def __init__(self, plant: GuardedPlant, trajectory: TrajectoryLogic | None,
                 controller: ControllerLogic | None, *, sample_rate_hz: float,
                 duration_s: float = 0.0, pacer: Pacer | None = None,
                 capacity: int = 65536,
                 on_sample: Callable[[ServoSample], None] | None = None) -> None:
        self.plant = plant
        self.trajectory = trajectory
        self.controller = controller
        self.rate_hz = float(sample_rate_hz)
        period_ns = round(NS_PER_S / self.rate_hz)
        self.pacer = pacer if pacer is not None else Pacer(period_ns)
        self.total = sample_count(duration_s, self.rate_hz)
        self.samples: deque[ServoSample] = deque(maxlen=max(0, capacity))
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
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None

    def stamp_ns(self, index: int) -> int:
        """Return t_k [ns] of grid sample ``index``, as the plant node stamps it."""
        return self.start_ns + round(index * NS_PER_S / self.rate_hz)

    def _serve(self, index: int, position_m: float, now_ns: int, lateness_ns: int) -> None:
        stamp = self.stamp_ns(index)
        plant = self.plant
        self.index = index
        if self.controller is None or self.trajectory is None:
            # the plant alone: the command comes from elsewhere (another node), held as is
            sample = ServoSample(index, stamp, position_m, math.nan, math.nan, math.nan,
                                 plant.applied_v, lateness_ns, None)
        else:
            now_s = now_ns / NS_PER_S
            ref, vel = self.trajectory.on_position(stamp)
            self.controller.on_position(stamp, position_m, now_s)
            out = self.controller.on_reference(stamp, ref, vel)
            u = out.voltage_v if out is not None else self.controller.safe_voltage_v
            applied = plant.applied_v
            plant.command(u, now_s)
            self.held_v = plant.held_v
            sample = ServoSample(index, stamp, position_m, ref, vel, u, applied, lateness_ns,
                                 out.diagnostics if out else None)
        if self.samples.maxlen:
            self.samples.append(sample)
            self.pushed += 1
        if self.on_sample is not None:
            self.on_sample(sample)
        if self.total and index + 1 >= self.total:
            self.done = True

    def start(self, start_ns: int = 0) -> None:
        """
        Start the backend and serve sample 0 now.

        Parameters
        ----------
        start_ns : int
            t_0 [ns] of the stamps (the ROS time of the start).

        """
        self.start_ns = int(start_ns)
        if self.bridge_clock is not None:
            y0 = self.plant.start(time.monotonic())
            bridge = self.bridge_clock
            self._t0_arrival = bridge.arrival_ns - bridge.sample_index * self.pacer.period_ns
            self.pacer.stats.add(0)
            self._serve(bridge.sample_index, y0, bridge.arrival_ns, 0)
            return
        self.pacer.start()
        index, lateness = self.pacer.wait()  # sample 0, due now
        now = self.pacer.due_ns(index) + lateness
        self._serve(index, self.plant.start(now / NS_PER_S), now, lateness)

    def step(self) -> bool:
        """Wait for the next sample, serve it, and return whether the run goes on."""
        if self.done:
            return False
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
            setup: Callable[[], Any] | None = None) -> None:
        """
        Start and serve samples until the run is complete, :meth:`stop`, or an error.

        An error drives the safe voltage (:meth:`GuardedPlant.fault`) and is kept in
        :attr:`error` for the caller to report; the backend is stopped at the end either way.
        """
        try:
            if setup is not None:
                self.setup_report = dict(setup() or {})
            self.start(start_ns)
            halt = self._halt
            while not halt.is_set() and self.step():
                pass
        except BaseException as exc:  # noqa: BLE001 -- any fault: safe voltage, then report
            self.error = exc
            self.plant.fault(exc)
        finally:
            self.done = True
            self.plant.stop()

    def start_thread(self, start_ns: int = 0, setup: Callable[[], Any] | None = None,
                     ) -> threading.Thread:
        """Run :meth:`run` in a daemon thread (``setup`` runs first, in that thread)."""
        self._thread = threading.Thread(target=self.run, args=(start_ns, setup),
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
        out: list[ServoSample] = []
        queue = self.samples
        while queue and (not limit or len(out) < limit):
            out.append(queue.popleft())
        self.drained += len(out)
        return out

    def stats(self) -> dict[str, Any]:
        """Return the plant counters, the lateness figures and the queue overruns."""
        out = self.plant.stats()
        out.update(self.pacer.stats.summary())
        out.update({'index': self.index, 'queue_overruns':
                    max(self.pushed - self.drained - len(self.samples), 0),
                    'controller_steps': self.controller.steps if self.controller else 0})
        if self.error is not None:
            out['error'] = repr(self.error)
        return out

