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
Safety around every plant backend: clamping, the command watchdog, safe start and safe stop.

The rules hold whatever the backend (:mod:`piezo_stage_ros.hardware.bridge`):

- start at the safe voltage (:meth:`GuardedPlant.start`);
- clamp every command to the amplifier range; a non-finite command becomes the safe voltage;
- drive the safe voltage on shutdown (:meth:`GuardedPlant.stop`) and on an exception
  (:meth:`GuardedPlant.fault`);
- commands ahead: a command may come with the controller's prediction of the next ones
  (:mod:`piezo_stage_ros.core.control.ahead`); a sample without a new command, taken or
  missed, applies the prediction for it instead of holding the last command, and a backend
  that keeps a queue (``write_commands``: the UDP target, the simulated stage) receives them
  with each command so that it plays them over the samples the host misses;
- when commands stop for longer than ``command_timeout_s`` (:class:`Watchdog`), never jump: ramp
  from the voltage applied last to the safe voltage by at most ``slew_v_per_s * T`` a sample,
  and when commands come back, follow them by at most as much a sample until they are reached
  (:meth:`GuardedPlant.sample`; each trip is kept as a :class:`Trip`).

Time is passed in (seconds of any monotonic clock), never read here, so the logic is tested with
an injected clock and no sleeps.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import math
from typing import Any, Callable, Sequence

import numpy as np
from piezo_stage_ros.core.config.nodes import WatchdogParams
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.model.stage import SignalChainParams
from piezo_stage_ros.hardware.bridge import Bridge

__all__ = ['GuardedPlant', 'Trip', 'Watchdog', 'clamp_command', 'slew_toward']

#: Commands ahead [V], as lists or arrays.
Commands = Sequence[float] | FloatArray

#: The default ramp rate of the watchdog [V/s] (``watchdog.slew_v_per_s``).
DEFAULT_SLEW_V_PER_S = WatchdogParams().slew_v_per_s


def clamp_command(command_v: float, low_v: float, high_v: float,
                  safe_v: float) -> tuple[float, bool]:
    """
    Clamp a command to the amplifier range.

    Parameters
    ----------
    command_v : float
        Requested amplifier input [V].
    low_v, high_v : float
        Amplifier input range [V].
    safe_v : float
        Voltage used instead of a non-finite command [V].

    Returns
    -------
    voltage_v : float
        The voltage to apply [V].
    changed : bool
        Whether the command was clamped or replaced.

    """
    if not math.isfinite(command_v):
        return safe_v, True
    if command_v < low_v:
        return low_v, True
    if command_v > high_v:
        return high_v, True
    return command_v, False


def slew_toward(from_v: float, to_v: float, max_step_v: float) -> float:
    """
    Return ``to_v`` [V] if within ``max_step_v`` of ``from_v``, else one step toward it.

    Within means up to a part in 10^9 more than the step, so that a ramp whose length is a whole
    number of steps ends on ``to_v`` instead of leaving a rounding residue for one more sample.
    """
    reach = max_step_v * (1.0 + 1e-9)
    if to_v - from_v > reach:
        return from_v + max_step_v
    if from_v - to_v > reach:
        return from_v - max_step_v
    return to_v


@dataclass
class Trip:
    """
    One trip of the command watchdog, from its first sample to the one that ended it.

    Attributes
    ----------
    start_s : float
        Time of the first sample the watchdog drove [s] (the guard's clock).
    silence_s : float
        How long no command had come then [s] (longer than the timeout).
    start_sample : int
        The guard's sample count at the trip's first sample.
    from_v : float
        The voltage applied before the trip [V] (where the ramp started).
    samples : int
        Samples the watchdog drove: ramp, safe and recovery together.
    ramp_samples : int
        Samples that moved toward the safe voltage.
    safe_samples : int
        Samples at the safe voltage (the ramp complete).
    recovery_samples : int
        Samples on the way back to the commands after they came back: each the command plus
        an offset, from where the ramp was, that shrinks by at most ``slew_v_per_s * T`` a
        sample.
    max_step_v : float
        The largest change of the applied voltage from one sample to the next while the
        watchdog alone drove it (the ramp and the safe voltage; the first sample against the
        one before the trip included) [V]: at most ``slew_v_per_s * T``.
    return_max_step_v : float
        The largest change from one sample to the next on the way back [V]: the commands' own
        change plus at most ``slew_v_per_s * T`` of the offset.
    duration_s : float
        From the first sample to the one that ended the trip [s].
    ended : str
        ``'commands'`` (the applied voltage reached the commands again), ``'tripped again'``
        (commands stopped again while it followed them: a new trip starts from there),
        ``'wind down'`` (a wind-down began: its own trip starts from there) or ``'stop'`` (the
        run ended during the trip); ``''`` while it goes on.
    wind_down : bool
        The ramp was asked for (:meth:`GuardedPlant.wind_down`), not caused by silence.

    """

    start_s: float
    silence_s: float
    start_sample: int
    from_v: float
    samples: int = 0
    ramp_samples: int = 0
    safe_samples: int = 0
    recovery_samples: int = 0
    max_step_v: float = 0.0
    return_max_step_v: float = 0.0
    duration_s: float = 0.0
    ended: str = ''
    wind_down: bool = False


class Watchdog:
    """
    Trips when nothing was fed for longer than a timeout.

    Parameters
    ----------
    timeout_s : float
        Longest allowed silence [s], > 0.

    Attributes
    ----------
    trips : int
        How many times it went from fed to expired.

    """

    def __init__(self, timeout_s: float) -> None:
        if not (timeout_s > 0.0 and math.isfinite(timeout_s)):
            raise ParameterError('command_timeout_s', timeout_s, '(0, inf)')
        self.timeout_s = timeout_s
        self._last_s: float | None = None
        self._tripped = False
        self.trips = 0

    def arm(self, now_s: float) -> None:
        """Start watching at ``now_s`` [s] as if fed then."""
        self._last_s = now_s
        self._tripped = False

    def feed(self, now_s: float) -> None:
        """Record that the watched thing arrived at ``now_s`` [s]."""
        self._last_s = now_s
        self._tripped = False

    @property
    def last_s(self) -> float | None:
        """Return when it was last fed (or armed) [s]; None before."""
        return self._last_s

    @property
    def armed(self) -> bool:
        """Return whether :meth:`arm` or :meth:`feed` was called."""
        return self._last_s is not None

    def expired(self, now_s: float) -> bool:
        """
        Return whether the silence at ``now_s`` [s] is longer than the timeout.

        An unarmed watchdog never expires. Each transition to expired counts one trip.
        """
        if self._last_s is None:
            return False
        if now_s - self._last_s > self.timeout_s:
            if not self._tripped:
                self._tripped = True
                self.trips += 1
            return True
        return False


class GuardedPlant:
    """
    A bridge driven through the safety rules; the object the plant node owns.

    Parameters
    ----------
    bridge : Bridge
        The backend.
    chain : SignalChainParams
        Amplifier range and safe voltage.
    command_timeout_s : float
        Silence after which the watchdog ramps to the safe voltage (real-time sampling) [s].
    slew_v_per_s : float
        Rate of that ramp, and of following the commands back after it [V/s], > 0.
    sample_period_s : float
        The sample period T [s]: the watchdog moves the applied voltage by at most
        ``slew_v_per_s * T`` from one sample to the next (a stall of the host makes no larger
        step: the backend held the last voltage meanwhile).

    Notes
    -----
    A backend whose ``clamps_itself`` attribute is true (the core model, whose signal chain
    clamps after its DAC as the real amplifier does) receives the commands unclamped: clamping
    ahead of its DAC would change saturated samples against the offline runner. The watchdog's
    ramp works on clamped values for it too (a ramp never leaves the amplifier range).

    When commands stop (real-time sampling, :meth:`sample`), each sample without a new command
    holds the last one for ``command_timeout_s`` (or, when the command came with commands
    ahead, applies the prediction for it: the n-th sample since the command, taken or
    skipped, gets the n-th prediction, and the last one is held after the queue); then the
    watchdog trips and the applied voltage ramps from the voltage applied last to the safe
    voltage by at most ``slew_v_per_s * T`` a sample, and stays there. A command that comes
    n samples late (the loop skipped them: :meth:`skipped`) is applied as its own n-th
    prediction: the host computed it for a sample that has passed.

    When commands come back during or after the ramp, the stage is where the ramp left it and
    the controller's new command can be anywhere in the range (after a long stall of the host
    the reference has moved on). Applying it at once would be the jump the ramp avoided. The
    guard applies the commands plus an offset that starts at the difference (applied voltage
    minus the first command: no step at the return) and shrinks to zero by at most
    ``slew_v_per_s * T`` a sample; then the trip ends and each command is applied as it comes.
    On the way back the stage moves by the commands' own change plus at most one step of the
    offset a sample: the watchdog adds no step larger than the slew allows, and the
    controller's motion goes through as in tracking. Two other choices were measured and
    refused (the direct composition, RAC on a 100 Hz sine, stalls of the host of 15 and 50 ms,
    scripted clock, ``slew_v_per_s`` 100): limiting the commands themselves to the slew until
    the stage reaches them took 37 ms in one case and had not reached them 0.25 s later in the
    other (the controller's integral winds up against a stage that does not follow: about 5 um
    of error meanwhile); restarting the controller from the applied voltage threw away the
    RAC's adapted estimates (e_max about 50 nm for the rest of the run against 17.6). The
    return here took 45 and 11 samples, e_max 0.91 and 0.21 um around the stall and 17.6 nm
    after it, against 0.68 and 1.15 um for the old jump to the safe voltage and back. The guard
    sees every applied voltage whatever the controller (in this process or in another node), so
    the rule lives here. Each trip, from its first sample to the one that reached the commands
    again, is a :class:`Trip` in :attr:`ended_trips` (and given to :attr:`on_trip`).

    """

    def __init__(self, bridge: Bridge, chain: SignalChainParams,
                 command_timeout_s: float = 0.01, *,
                 slew_v_per_s: float = DEFAULT_SLEW_V_PER_S,
                 sample_period_s: float = 1e-4) -> None:
        if not (slew_v_per_s > 0.0 and math.isfinite(slew_v_per_s)):
            raise ParameterError('watchdog.slew_v_per_s', slew_v_per_s, '(0, inf)')
        if not (sample_period_s > 0.0 and math.isfinite(sample_period_s)):
            raise ParameterError('sample_period_s', sample_period_s, '(0, inf)')
        self.bridge = bridge
        self.low_v = chain.amplifier_min_v
        self.high_v = chain.amplifier_max_v
        self.safe_v = chain.safe_voltage_v
        self.watchdog = Watchdog(command_timeout_s)
        #: Rate of the watchdog's ramp and of the recovery after it [V/s] (settable between
        #: samples).
        self.slew_v_per_s = float(slew_v_per_s)
        self.sample_period_s = float(sample_period_s)
        self._clamp = not bool(getattr(bridge, 'clamps_itself', False))
        self._direct = getattr(bridge, 'step', None) if not self._clamp else None
        self.held_v = self.safe_v
        # the voltage written with the last sample: held over the sample it measured
        self.applied_v = self.safe_v
        self.started = False
        self.stopped = False
        self.commands = 0
        self.clamped = 0
        self.samples = 0
        self.late = 0
        self.ramp_samples = 0
        self.safe_samples = 0
        self.recovery_samples = 0
        self.max_step_v = 0.0
        self._fresh = False
        self._released = False
        # the sample written last applies the command itself (what follow() extends)
        self._wrote_command = False
        self._trip_number = 0
        self._offset: float | None = None
        #: Samples since the last command, taken or skipped (the n of its n-th prediction).
        self.since_command = 0
        # the last command's predictions of the commands after it (commands ahead), and what
        # the backend still plays of the queue written with the last sample
        self._ahead: Commands = ()
        self._queued: Commands = ()
        self._write_commands: Callable[[float, Commands], None] | None = getattr(
            bridge, 'write_commands', None)
        #: Samples that applied a prediction (commands ahead), taken or skipped.
        self.predicted_samples = 0
        #: What the last sample did: ``'track'`` (a command, or the last one held), ``'ramp'``,
        #: ``'safe'`` or ``'recover'`` (the watchdog's).
        self.phase = 'track'
        #: The trip in progress (None: tracking).
        self.trip: Trip | None = None
        #: Trips that have ended, oldest first (a reader pops them; the oldest go first when
        #: nobody does).
        self.ended_trips: deque[Trip] = deque(maxlen=1000)
        #: Called with each trip as it ends (in the thread that samples; keep it short).
        self.on_trip: Callable[[Trip], None] | None = None
        #: Set by :meth:`wind_down`: every sample from the next one on ramps to the safe
        #: voltage as a trip does, whatever the commands.
        self.winding = False

    def start(self, now_s: float) -> float:
        """
        Open the backend, drive the safe voltage and return y_0 [m].

        Parameters
        ----------
        now_s : float
            Monotonic time [s]; the watchdog starts here.

        """
        self.bridge.open()
        self.held_v = self.safe_v
        y0 = self.bridge.safe_start(self.safe_v)
        self.started = True
        self.watchdog.arm(now_s)
        return y0

    def _accept(self, command_v: float) -> float:
        self.commands += 1
        if not self._clamp:
            return command_v
        voltage, changed = clamp_command(command_v, self.low_v, self.high_v, self.safe_v)
        self.clamped += changed
        return voltage

    def command(self, command_v: float, now_s: float,
                ahead_v: Commands | None = None) -> None:
        """
        Take a new command to hold from the next sample on (real-time sampling).

        Parameters
        ----------
        command_v : float
            Amplifier input [V] as the controller sent it.
        now_s : float
            Arrival time [s] (feeds the watchdog).
        ahead_v : sequence of float, optional
            Commands ahead: the commands predicted for the samples after the next one [V],
            applied (clamped) over samples without a new command. Refused as a whole (the
            command is held) if any is not finite.

        """
        self.held_v = self._accept(command_v)
        self.watchdog.feed(now_s)
        self._fresh = True
        self.since_command = 0
        self._ahead = self._accept_ahead(ahead_v) if ahead_v is not None else ()

    def _accept_ahead(self, ahead_v: Commands) -> Commands:
        low, high = self.low_v, self.high_v
        finite = getattr(ahead_v, 'finite', None)
        if finite is not None:
            # computed when read (core.control.ahead.Ahead): checked and clipped as such
            if not finite():
                return ()
            return ahead_v.clamped(low, high) if self._clamp else ahead_v  # type: ignore
        total = sum(ahead_v) if isinstance(ahead_v, list) else float(np.sum(ahead_v))
        if not math.isfinite(total):
            return ()  # a prediction that is not finite: hold the command instead
        if self._clamp:
            if isinstance(ahead_v, np.ndarray):
                # a feed-forward's tables read ahead: 128 values one by one cost 38 us here
                return np.minimum(np.maximum(ahead_v, low), high)
            return [high if v > high else (low if v < low else float(v)) for v in ahead_v]
        return ahead_v

    def _in_range(self, voltage_v: float) -> float:
        return clamp_command(voltage_v, self.low_v, self.high_v, self.safe_v)[0]

    def _predicted(self, since: int) -> tuple[float, Commands]:
        # the n-th sample since the last command (n >= 1), the watchdog not expired: the
        # command's n-th prediction (the last one after the queue), and the rest of the queue
        ahead = self._ahead
        if not len(ahead):
            return self.held_v, ()
        self.predicted_samples += 1
        if since <= len(ahead):
            return float(ahead[since - 1]), ahead[since:]
        return float(ahead[-1]), ()

    def _watchdog_voltage(self, expired: bool, now_s: float) -> float:
        trip = self.trip
        winding = self.winding and (trip is None or not trip.wind_down)
        if expired and (trip is None or self.watchdog.trips != self._trip_number or winding):
            # a new trip (commands stopped, or stopped again while they were being followed,
            # or a wind-down asked for: its ramp is a trip of its own, from where it begins)
            if trip is not None:
                self._end_trip(trip, 'wind down' if winding else 'tripped again', now_s)
            self._trip_number = self.watchdog.trips
            self._offset = None
            trip = self.trip = Trip(start_s=now_s,
                                    silence_s=now_s - (self.watchdog.last_s or now_s),
                                    start_sample=self.samples,
                                    from_v=self._in_range(self.applied_v),
                                    wind_down=self.winding)
        assert trip is not None
        step = self.slew_v_per_s * self.sample_period_s
        was = self._in_range(self.applied_v)
        if expired:
            voltage = slew_toward(was, self.safe_v, step)
            if voltage == was == self.safe_v:
                self.phase = 'safe'
                self.safe_samples += 1
                trip.safe_samples += 1
            else:
                self.phase = 'ramp'
                self.ramp_samples += 1
                trip.ramp_samples += 1
            moved = abs(voltage - was)
            if moved > trip.max_step_v:
                trip.max_step_v = moved
                self.max_step_v = max(self.max_step_v, moved)
        else:
            # the return: the commands plus an offset that starts at where the ramp left the
            # stage and shrinks by at most one step a sample
            target = self._in_range(self.held_v)
            offset = was - target if self._offset is None else self._offset
            offset = self._offset = slew_toward(offset, 0.0, step)
            voltage = self._in_range(target + offset)
            self.phase = 'recover'
            self.recovery_samples += 1
            trip.recovery_samples += 1
            trip.return_max_step_v = max(trip.return_max_step_v, abs(voltage - was))
        trip.samples += 1
        trip.duration_s = now_s - trip.start_s
        if not expired and self._offset == 0.0:
            # the commands are reached: from the next sample on they are applied as they come
            self._end_trip(trip, 'commands', now_s)
            return self.held_v
        return voltage

    def _end_trip(self, trip: Trip, why: str, now_s: float) -> None:
        trip.ended = why
        trip.duration_s = now_s - trip.start_s
        self.trip = None
        self.ended_trips.append(trip)
        if self.on_trip is not None:
            self.on_trip(trip)

    def sample(self, now_s: float) -> float:
        """
        Take one real-time sample: hold the last command (or the watchdog's voltage), measure.

        Parameters
        ----------
        now_s : float
            Time of the sample [s] (checked against the watchdog).

        Returns
        -------
        float
            Measured position at the end of the sample [m].

        """
        if self._released:
            self._released = False
        else:
            self._write(now_s)
        self._wrote_command = False
        return self.bridge.read_position()

    def release(self, now_s: float) -> None:
        """
        Write the coming sample's voltage to the backend now; :meth:`sample` then only measures.

        For a backend whose write sends at once (the host of a target-paced stream): the
        answer leaves as soon as the command is known, ahead of the loop's bookkeeping, and
        :meth:`sample` called later decides nothing again. ``now_s``: as :meth:`sample`'s.
        """
        if not self._released:
            self._write(now_s)
            self._released = True

    def follow(self, ahead_v: Commands) -> None:
        """
        Hand over the commands ahead of the command :meth:`release` wrote, after it [V].

        For the host of a target-paced stream: the answer leaves without them, as early as it
        can, and they follow in a second datagram that only the samples the host misses need
        (``write_ahead`` of the backend). Taken as :meth:`command`'s ``ahead_v``; ignored when
        the sample released was not the command's (the watchdog's, or a prediction's).
        """
        if not self._wrote_command:
            return
        queue = self._accept_ahead(ahead_v)
        self._ahead = self._queued = queue
        write_ahead = getattr(self.bridge, 'write_ahead', None)
        if write_ahead is not None and len(queue):
            write_ahead(queue)

    def _write(self, now_s: float) -> None:
        """Decide the voltage of the coming sample (command, queue or watchdog) and write it."""
        expired = self.winding or self.watchdog.expired(now_s)
        queue: Commands = ()
        if expired or self.trip is not None:
            voltage = self._watchdog_voltage(expired, now_s)
        else:
            self.phase = 'track'
            since = self.since_command
            if since == 0:
                voltage, queue = self.held_v, self._ahead
                self._wrote_command = True
            else:
                # no command for this sample (or a command late by the samples skipped)
                voltage, queue = self._predicted(since)
        if not self._fresh and self.samples > 0:
            # no command since the last sample: the previous one is held, the sample is late
            self.late += 1
        self._fresh = False
        self.since_command += 1
        self.samples += 1
        self.applied_v = voltage
        write = self._write_commands
        if write is not None and (len(queue) or len(self._queued)):
            write(voltage, queue)
        else:
            self.bridge.write_voltage(voltage)
        self._queued = queue

    def skipped(self, samples: int) -> None:
        """
        Let ``samples`` samples that were not taken pass (a paced loop's stall).

        The voltage written last stays held over them (or the backend plays the commands ahead
        written with it); a simulated backend (one with ``advance(n)``) steps through them so
        that it stays in step with wall time, a physical one has done so by itself.
        """
        if samples <= 0:
            return
        self.since_command += samples
        queued = self._queued
        if len(queued):
            # the backend plays the queue written with the last sample, then holds its last
            played = min(samples, len(queued))
            self.predicted_samples += played
            self.applied_v = float(queued[played - 1])
            self._queued = queued[played:]
        advance = getattr(self.bridge, 'advance', None)
        if callable(advance):
            advance(samples)

    def step(self, command_v: float) -> float:
        """
        Apply the command for this sample and measure at its end (lockstep).

        Parameters
        ----------
        command_v : float
            Amplifier input [V] as the controller sent it.

        Returns
        -------
        float
            Measured position y_k+1 [m].

        """
        self.samples += 1
        if self._direct is not None:
            self.commands += 1
            self.applied_v = command_v
            return float(self._direct(command_v))
        voltage = self._accept(command_v)
        self.held_v = self.applied_v = voltage
        self.bridge.write_voltage(voltage)
        return self.bridge.read_position()

    def wind_down(self) -> None:
        """
        Ramp to the safe voltage from the next real-time sample on, ignoring commands.

        The watchdog's ramp (at most ``slew_v_per_s * T`` a sample) without waiting for its
        timeout: a stage taken out of service (a managed node deactivated) gets no step larger
        than the slew. :attr:`phase` is ``'safe'`` once a sample applied the safe voltage. The
        ramp is a :class:`Trip` of its own marked ``wind_down`` (a trip in progress ends there).
        """
        self.winding = True

    def ramp_to_safe(self) -> tuple[int, float]:
        """
        Step the safe voltage's ramp sample by sample now (lockstep) and return what it took.

        Each sample applies the voltage applied last moved toward the safe voltage by at most
        ``slew_v_per_s * T`` (as the watchdog's ramp), through :meth:`step`, until the safe
        voltage is applied.

        Returns
        -------
        tuple of (int, float)
            The samples stepped and the largest change between two applied voltages [V].

        """
        step_v = self.slew_v_per_s * self.sample_period_s
        was = self._in_range(self.applied_v)
        samples, largest = 0, 0.0
        while was != self.safe_v:
            voltage = slew_toward(was, self.safe_v, step_v)
            self.step(voltage)
            largest = max(largest, abs(voltage - was))
            was = voltage
            samples += 1
        self.phase = 'safe'
        return samples, largest

    def stop(self) -> None:
        """Drive the safe voltage and release the backend (idempotent)."""
        if self.stopped:
            return
        self.stopped = True
        if self.trip is not None:
            trip = self.trip
            self._end_trip(trip, 'stop', trip.start_s + trip.duration_s)
        self.held_v = self.safe_v
        if self.started:
            self.bridge.safe_stop(self.safe_v)

    def fault(self, exc: BaseException) -> None:
        """Drive the safe voltage after ``exc``; never raises (the caller reports ``exc``)."""
        del exc
        try:
            self.stop()
        except Exception:  # noqa: BLE001 -- the original error is the one to report
            pass

    def stats(self) -> dict[str, Any]:
        """Return the counters of this guard and of its backend."""
        out: dict[str, Any] = {'samples': self.samples, 'commands': self.commands,
                               'clamped': self.clamped, 'late': self.late,
                               'watchdog_trips': self.watchdog.trips,
                               'ramp_samples': self.ramp_samples,
                               'safe_samples': self.safe_samples,
                               'recovery_samples': self.recovery_samples,
                               'watchdog_max_step_v': self.max_step_v,
                               'predicted_samples': self.predicted_samples}
        out.update({f'bridge_{k}': v for k, v in self.bridge.stats().items()})
        return out
