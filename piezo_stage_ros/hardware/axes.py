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
The backends and the safety of a stage of several axes.

A backend of N axes moves one sample of every axis at a time: each axis' voltage (and its
commands ahead) is set, then :meth:`AxesModelBridge.read_positions` holds them all over the
sample and returns every axis' position at its end. The core model of several axes is
:class:`AxesModelBridge`; the UDP target of several axes is
:class:`~piezo_stage_ros.hardware.udp_axes.UdpAxesBridge`.

:class:`AxesGuard` drives such a backend through the one-axis safety rules, one
:class:`~piezo_stage_ros.hardware.safety.GuardedPlant` per axis (its range, safe voltage,
clamping, commands ahead, ramp and return), each writing into its axis of the backend. The
watchdog is per axis and the decision is common: each axis' watchdog is fed by that axis'
commands, and as soon as any of them expires every axis ramps to its safe voltage at the slew
and later returns to its commands together, so that no axis goes on tracking while another one
falls away (the axes are coupled, and a scan is meaningless with one axis stopped). Each trip
names the axes whose commands stopped (:attr:`AxesGuard.causes`). A non-finite command on
an axis is refused (the axis plays its commands ahead or holds the last one, its watchdog is
not fed): a controller that keeps giving them trips every axis after the timeout, naming that
axis, instead of one axis jumping to its safe voltage.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import math
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.model.axes import AxesStage, AxesStageParams
from piezo_stage_ros.core.model.stage import SignalChainParams
from piezo_stage_ros.hardware.safety import DEFAULT_SLEW_V_PER_S, GuardedPlant, Trip, Watchdog

__all__ = ['AxesGuard', 'AxesModelBridge', 'AxesTripCause', 'AxisPort']


class AxesModelBridge:
    """
    The core model of several axes behind the backend interface of N axes.

    As :class:`~piezo_stage_ros.hardware.bridge.ModelBridge` per axis: the model starts at rest
    where the offline loop starts it, each :meth:`read_positions` steps it once with every
    axis' voltage written last, and :meth:`advance` plays each axis' commands ahead over
    samples nobody takes, then holds its last.

    Parameters
    ----------
    params : AxesStageParams
        The stage.

    """

    def __init__(self, params: AxesStageParams) -> None:
        self.params = params
        self.names = params.names
        self.n = params.n
        self.stage = AxesStage(params)
        #: Each axis' voltage to hold over the next sample [V].
        self.voltages_v: list[float] = [a.chain.safe_voltage_v for a in params.axes]
        #: Each axis' commands ahead after it [V] (empty: none).
        self.ahead_v: list[Any] = [()] * self.n
        self._played = [0] * self.n
        self.steps = 0

    @property
    def clamps_itself(self) -> bool:
        """Return True: each axis' signal chain clamps after its DAC, as the real one."""
        return True

    def open(self) -> None:
        """Nothing to acquire."""

    def safe_start(self, safe_voltages_v: Sequence[float]) -> list[float]:
        """Put the model at rest and return every axis' y_0 [m]."""
        self.voltages_v = list(safe_voltages_v)
        self.ahead_v = [()] * self.n
        self.steps = 0
        return self.stage.reset()

    def set_axis(self, axis: int, voltage_v: float, ahead_v: Any) -> None:
        """Set one axis' voltage [V] and its commands ahead [V] (empty: hold the voltage)."""
        self.voltages_v[axis] = voltage_v
        self.ahead_v[axis] = ahead_v
        self._played[axis] = 0

    def read_positions(self) -> list[float]:
        """Step the model one sample and return every axis' measured position [m]."""
        self.steps += 1
        return self.stage.step(self.voltages_v)

    def advance(self, samples: int) -> None:
        """Step the model ``samples`` times, each axis playing its commands ahead, unmeasured."""
        volts, played = self.voltages_v, self._played
        for _ in range(samples):
            for j, ahead in enumerate(self.ahead_v):
                if played[j] < len(ahead):
                    volts[j] = float(ahead[played[j]])
                    played[j] += 1
            self.steps += 1
            self.stage.step(volts)

    def safe_stop(self, safe_voltages_v: Sequence[float]) -> None:
        """Remember the safe voltages; a model has nothing to release."""
        self.voltages_v = list(safe_voltages_v)
        self.ahead_v = [()] * self.n

    def stats(self) -> Mapping[str, Any]:
        """Return the samples stepped and, per axis, the non-finite commands replaced."""
        return {'samples': self.steps, 'faults': sum(self.stage.faults)}


class AxisPort:
    """
    One axis of a backend of N axes, as the one-axis backend a :class:`GuardedPlant` drives.

    Writes go into the axis of the shared backend; the position read is the axis' part of the
    measurement the guard of the axes took for all of them (:attr:`position_m`).
    """

    def __init__(self, backend: Any, axis: int) -> None:
        self.backend = backend
        self.axis = axis
        self.clamps_itself = bool(getattr(backend, 'clamps_itself', False))
        #: The axis' position of the sample the guard took last [m].
        self.position_m = math.nan

    def open(self) -> None:
        """Do nothing: the guard of the axes opens the backend."""

    def safe_start(self, safe_voltage_v: float) -> float:
        """Return y_0 of the axis (the backend was started by the guard of the axes)."""
        self.backend.set_axis(self.axis, safe_voltage_v, ())
        return self.position_m

    def write_voltage(self, voltage_v: float) -> None:
        """Set the axis' voltage [V] for the next sample."""
        self.backend.set_axis(self.axis, voltage_v, ())

    def write_commands(self, voltage_v: float, ahead_v: Any) -> None:
        """Set the axis' voltage [V] and its commands ahead after it [V]."""
        self.backend.set_axis(self.axis, voltage_v, ahead_v)

    def read_position(self) -> float:
        """Return the axis' position of the sample taken [m]."""
        return self.position_m

    def safe_stop(self, safe_voltage_v: float) -> None:
        """Set the axis' safe voltage; the backend is stopped by the guard of the axes."""
        self.backend.set_axis(self.axis, safe_voltage_v, ())

    def stats(self) -> Mapping[str, float]:
        """Return nothing: the backend's counters are the guard of the axes' to report."""
        return {}


class _CheckedRow:
    """
    One axis' commands ahead, checked for finite values with the others' (a row of them).

    What the guard of an axis reads of commands ahead computed when read
    (:class:`~piezo_stage_ros.core.control.ahead.Ahead`): ``finite()``, ``clamped()``, length
    and items (slices are the row's own array slices).
    """

    __slots__ = ('_row', '_finite')

    def __init__(self, row: Any, finite: bool) -> None:
        self._row = row
        self._finite = finite

    def finite(self) -> bool:
        return self._finite

    def clamped(self, low_v: float, high_v: float) -> Any:
        return np.minimum(np.maximum(self._row, low_v), high_v)

    def __len__(self) -> int:
        return len(self._row)

    def __getitem__(self, index: Any) -> Any:
        return self._row[index]


@dataclass(frozen=True)
class AxesTripCause:
    """
    Why the axes' watchdog tripped: which axes' commands had stopped.

    Attributes
    ----------
    start_s : float
        Time of the trip's first sample [s] (the guard's clock).
    axes : tuple of str
        The axes whose watchdog had expired then.
    silence_s : float
        The longest silence among them [s].

    """

    start_s: float
    axes: tuple[str, ...]
    silence_s: float


class _Verdict:
    """
    What each axis' guard sees as its watchdog: the axes' common decision of the sample.

    ``expired`` returns whether any axis' watchdog has expired (decided once a sample by
    :class:`AxesGuard`); ``feed`` and ``arm`` reach the axis' own watchdog.
    """

    def __init__(self, group: AxesGuard, own: Watchdog) -> None:
        self._group = group
        self._own = own
        self.timeout_s = own.timeout_s

    @property
    def trips(self) -> int:
        return self._group.trips

    @property
    def last_s(self) -> float | None:
        return self._group.oldest_feed_s

    @property
    def armed(self) -> bool:
        return self._own.armed

    def arm(self, now_s: float) -> None:
        self._own.arm(now_s)

    def feed(self, now_s: float) -> None:
        self._own.feed(now_s)

    def expired(self, now_s: float) -> bool:
        del now_s
        return self._group.expired_now


class AxesGuard:
    """
    A backend of N axes driven through the safety rules, one :class:`GuardedPlant` per axis.

    Parameters
    ----------
    bridge : AxesModelBridge or UdpAxesBridge
        The backend of N axes.
    chains : sequence of SignalChainParams
        Each axis' amplifier range and safe voltage.
    names : sequence of str
        The axes, in order (the trips name them).
    command_timeout_s : float
        Silence of any axis' commands after which every axis ramps to its safe voltage [s].
    slew_v_per_s : float
        Rate of that ramp and of the return [V/s], every axis.
    sample_period_s : float
        T [s].

    Attributes
    ----------
    axes : list of GuardedPlant
        The guard of each axis (its counters, phase and trips).
    causes : deque of AxesTripCause
        Which axes stopped, per trip, oldest first.
    ended_trips : deque of (str, Trip)
        Each axis' trips as they end, oldest first (the axis named).

    """

    def __init__(self, bridge: Any, chains: Sequence[SignalChainParams],
                 names: Sequence[str], command_timeout_s: float = 0.01, *,
                 slew_v_per_s: float = DEFAULT_SLEW_V_PER_S,
                 sample_period_s: float = 1e-4) -> None:
        for what, count in (('chains', len(chains)), ('names', len(names))):
            if count != int(bridge.n):
                raise ParameterError(what, count, f'{bridge.n}, one per axis of the backend '
                                     f'(axes {list(names)})')
        self.bridge = bridge
        self.names = tuple(str(a) for a in names)
        self.n = len(self.names)
        self.ports = [AxisPort(bridge, j) for j in range(self.n)]
        self.axes = [GuardedPlant(port, chain, command_timeout_s, slew_v_per_s=slew_v_per_s,
                                  sample_period_s=sample_period_s)
                     for port, chain in zip(self.ports, chains)]
        self._own = [g.watchdog for g in self.axes]
        for g, own in zip(self.axes, self._own):
            g.watchdog = _Verdict(self, own)  # type: ignore[assignment]
        #: Every axis' watchdog as one (arm it; ``trips``: the axes' trips).
        self.watchdog = self
        self.timeout_s = float(command_timeout_s)
        self.trips = 0
        self.expired_now = False
        self.oldest_feed_s: float | None = None
        self.safe_v = [g.safe_v for g in self.axes]
        self.causes: deque[AxesTripCause] = deque(maxlen=1000)
        self.ended_trips: deque[tuple[str, Trip]] = deque(maxlen=1000)
        self.on_trip: Callable[[tuple[str, Trip]], None] | None = None
        for name, g in zip(self.names, self.axes):
            g.on_trip = lambda trip, name=name: self._ended(name, trip)
        #: Non-finite commands refused, per axis.
        self.refused = [0] * self.n
        self._commands = [g.command for g in self.axes]
        self._release = [g.release for g in self.axes]
        self._sample = [g.sample for g in self.axes]

    def _ended(self, name: str, trip: Trip) -> None:
        self.ended_trips.append((name, trip))
        if self.on_trip is not None:
            self.on_trip((name, trip))

    # -- the watchdog of the axes

    def arm(self, now_s: float) -> None:
        """Start every axis' watchdog at ``now_s`` [s]."""
        for own in self._own:
            own.arm(now_s)

    def _decide(self, now_s: float) -> None:
        """Decide once for the coming sample whether any axis' commands have stopped."""
        expired = [own.expired(now_s) for own in self._own]
        was = self.expired_now
        self.expired_now = any(expired)
        if self.expired_now and not was:
            self.trips += 1
            lasts = [own.last_s for own, e in zip(self._own, expired) if e]
            oldest = min(s for s in lasts if s is not None) if any(
                s is not None for s in lasts) else now_s
            self.oldest_feed_s = oldest
            self.causes.append(AxesTripCause(
                now_s, tuple(a for a, e in zip(self.names, expired) if e), now_s - oldest))

    # -- the plant's interface, every axis at once

    @property
    def winding(self) -> bool:
        """Return whether a wind-down was asked for."""
        return self.axes[0].winding

    @property
    def phase(self) -> str:
        """Return ``'safe'`` when every axis applies its safe voltage, else the first axis'."""
        phases = [g.phase for g in self.axes]
        return 'safe' if all(p == 'safe' for p in phases) else phases[0]

    @property
    def applied_v(self) -> tuple[float, ...]:
        """Return each axis' voltage held over the sample just measured [V]."""
        return tuple([g.applied_v for g in self.axes])

    @property
    def held_v(self) -> list[float]:
        """Return each axis' voltage held now [V]."""
        return [g.held_v for g in self.axes]

    def start(self, now_s: float) -> list[float]:
        """Open the backend, drive every safe voltage and return y_0 of every axis [m]."""
        self.bridge.open()
        y0 = self.bridge.safe_start(self.safe_v)
        for port, y in zip(self.ports, y0):
            port.position_m = y
        for g in self.axes:
            g.start(now_s)
        self.expired_now = False
        return list(y0)

    def command(self, commands_v: Sequence[float], now_s: float,
                ahead_v: Any = None) -> None:
        """
        Take every axis' new command [V] (and its row of commands ahead [V]) at ``now_s``.

        A non-finite command is refused for its axis (counted in :attr:`refused`).
        """
        rows: Any = None
        if isinstance(ahead_v, np.ndarray):
            # every axis' row checked at once (each axis' guard would sum its own)
            finite: Any = np.isfinite(ahead_v).all(axis=1).tolist()
            rows = [_CheckedRow(row, ok) for row, ok in zip(ahead_v, finite)]
        elif ahead_v is not None:
            # one sequence per axis: arrays checked as the rows of one, the others (computed
            # when read) say themselves whether they are finite
            rows = [_CheckedRow(row, bool(np.isfinite(row).all()))
                    if isinstance(row, np.ndarray) else row for row in ahead_v]
        for j, (take, u) in enumerate(zip(self._commands, commands_v)):
            if u - u != 0.0:  # NaN or infinite
                self.refused[j] += 1
                continue
            take(u, now_s, rows[j] if rows is not None else None)

    def sample(self, now_s: float) -> list[float]:
        """Take one real-time sample of every axis; return the positions at its end [m]."""
        if not self.axes[0].winding:
            # a wind-down ramps whatever the commands (as one axis: its watchdog not looked at)
            self._decide(now_s)
        for release in self._release:
            release(now_s)
        positions: list[float] = self.bridge.read_positions()
        for port, y in zip(self.ports, positions):
            port.position_m = y
        for take in self._sample:
            take(now_s)
        return positions

    def skipped(self, samples: int) -> None:
        """Let ``samples`` untaken samples pass on every axis (the backend plays its queues)."""
        if samples <= 0:
            return
        for g in self.axes:
            g.skipped(samples)
        advance = getattr(self.bridge, 'advance', None)
        if callable(advance):
            advance(samples)

    def wind_down(self) -> None:
        """Ramp every axis to its safe voltage from the next sample on (see GuardedPlant)."""
        for g in self.axes:
            g.wind_down()

    def stop(self) -> None:
        """Drive every safe voltage and release the backend (idempotent)."""
        if all(g.stopped for g in self.axes):
            return
        for g in self.axes:
            g.stop()
        if any(g.started for g in self.axes):
            self.bridge.safe_stop(self.safe_v)

    #: Drive the safe voltages after an error; never raises (the caller reports it).
    fault = GuardedPlant.fault

    def stats(self) -> dict[str, Any]:
        """Return the counters: the axes' sums, each axis' own as ``<axis>.<name>``."""
        out: dict[str, Any] = {'watchdog_trips': self.trips,
                               'refused_commands': int(np.sum(self.refused))}
        for key in ('samples', 'commands', 'clamped', 'late', 'ramp_samples', 'safe_samples',
                    'recovery_samples', 'predicted_samples'):
            values = [getattr(g, key) for g in self.axes]
            out[key] = max(values) if key in ('samples', 'late') else sum(values)
        out['watchdog_max_step_v'] = max(g.max_step_v for g in self.axes)
        for name, g in zip(self.names, self.axes):
            for key in ('commands', 'clamped', 'ramp_samples', 'recovery_samples'):
                out[f'{name}.{key}'] = getattr(g, key)
        out.update({f'bridge_{k}': v for k, v in self.bridge.stats().items()})
        return out
