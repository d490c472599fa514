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
- drive the safe voltage on shutdown (:meth:`GuardedPlant.stop`), on an exception
  (:meth:`GuardedPlant.fault`) and while commands have stopped for longer than
  ``command_timeout_s`` (:class:`Watchdog`), until they come back.

Time is passed in (seconds of any monotonic clock), never read here, so the logic is tested with
an injected clock and no sleeps.
"""

from __future__ import annotations

import math
from typing import Any

from piezo_stage_ros.core.errors import ParameterError
from piezo_stage_ros.core.stage import SignalChainParams
from piezo_stage_ros.hardware.bridge import Bridge

__all__ = ['GuardedPlant', 'Watchdog', 'clamp_command']


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
        Silence after which the safe voltage is driven (real-time sampling) [s].

    Notes
    -----
    A backend whose ``clamps_itself`` attribute is true (the core model, whose signal chain
    clamps after its DAC as the real amplifier does) receives the commands unclamped: clamping
    ahead of its DAC would change saturated samples against the offline runner. It still gets
    the safe voltage from the watchdog.

    """

    def __init__(self, bridge: Bridge, chain: SignalChainParams,
                 command_timeout_s: float = 0.01) -> None:
        self.bridge = bridge
        self.low_v = chain.amplifier_min_v
        self.high_v = chain.amplifier_max_v
        self.safe_v = chain.safe_voltage_v
        self.watchdog = Watchdog(command_timeout_s)
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
        self.safe_samples = 0
        self._fresh = False

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

    def command(self, command_v: float, now_s: float) -> None:
        """
        Take a new command to hold from the next sample on (real-time sampling).

        Parameters
        ----------
        command_v : float
            Amplifier input [V] as the controller sent it.
        now_s : float
            Arrival time [s] (feeds the watchdog).

        """
        self.held_v = self._accept(command_v)
        self.watchdog.feed(now_s)
        self._fresh = True

    def sample(self, now_s: float) -> float:
        """
        Take one real-time sample: hold the last command (or the safe voltage) and measure.

        Parameters
        ----------
        now_s : float
            Time of the sample [s] (checked against the watchdog).

        Returns
        -------
        float
            Measured position at the end of the sample [m].

        """
        if self.watchdog.expired(now_s):
            voltage = self.safe_v
            self.safe_samples += 1
        else:
            voltage = self.held_v
        if not self._fresh and self.samples > 0:
            # no command since the last sample: the previous one is held, the sample is late
            self.late += 1
        self._fresh = False
        self.samples += 1
        self.applied_v = voltage
        self.bridge.write_voltage(voltage)
        return self.bridge.read_position()

    def skipped(self, samples: int) -> None:
        """
        Let ``samples`` samples that were not taken pass (a paced loop's stall).

        The voltage written last stays held over them; a simulated backend (one with
        ``advance(n)``) steps through them so that it stays in step with wall time, a physical
        one has done so by itself.
        """
        advance = getattr(self.bridge, 'advance', None)
        if samples > 0 and callable(advance):
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

    def stop(self) -> None:
        """Drive the safe voltage and release the backend (idempotent)."""
        if self.stopped:
            return
        self.stopped = True
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
                               'safe_samples': self.safe_samples,
                               'watchdog_trips': self.watchdog.trips}
        out.update({f'bridge_{k}': v for k, v in self.bridge.stats().items()})
        return out
