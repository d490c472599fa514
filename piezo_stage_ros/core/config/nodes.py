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
What each node declares: its own parameter groups and the table that joins them to the core's.

A node's *table* (:class:`NodeTable`) is the core parameter group it configures (the stage, the
controller with its stability check, the trajectory) plus a node group of this module (mode,
timeouts, bridge, servo, recording), all declared with
:func:`~piezo_stage_ros.core.contracts.params.param`. From the table come the ROS parameter
declarations (:meth:`NodeTable.declarations`), the validated objects (:meth:`NodeTable.build`)
and the validation of a run-time change (:meth:`NodeTable.change`). Which core groups each node
has is the loader's business (:mod:`piezo_stage_ros.core.config.loader`); this module needs
nothing of core but the contracts.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import difflib
import math
from typing import Any, Iterable, Mapping, Sequence

from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.params import group, param, Params, ParamSpec

__all__ = ['BridgeParams', 'ControllerNodeParams', 'Declaration', 'Group', 'LockstepParams',
           'MODES', 'NodeTable', 'PlantNodeParams', 'RecordingParams', 'ServoParams',
           'TrajectoryNodeParams', 'WatchdogParams', 'closest_name', 'declaration']

MODES = ('lockstep', 'realtime')
_MODE_DOC = ('Time: lockstep (the plant owns simulation time and waits for each command) or '
             'realtime (the plant samples on its own clock and holds the last command).')



@dataclass(frozen=True)
class LockstepParams(Params):
    """How the plant starts and keeps a lockstep loop going."""

    subscribers: int = param(2, unit='-', description='Position subscribers (controller and '
                             'trajectory) to wait for before sample 0 is published.', low=0,
                             high=100, read_only=True)
    settle_s: float = param(0.0, unit='s', description='Wait this long (wall time) after the '
                            'subscribers matched before sample 0, so that a recorder is '
                            'subscribed to every topic.', low=0.0, high=60.0, read_only=True)
    resend_s: float = param(0.5, unit='s', description='Publish the current sample again when '
                            'its command has not come after this long (wall time; covers a '
                            'command lost while the graph was still matching).', low=0.001,
                            high=60.0)


@dataclass(frozen=True)
class BridgeParams(Params):
    """The UDP hardware bridge (backend 'udp'); protocol in docs/reference/udp-protocol.md."""

    host: str = param('127.0.0.1', unit='-', description='Address of the real-time I/O target.',
                      read_only=True)
    port: int = param(50000, unit='-', description='UDP port of the target.', low=1,
                      high=65535, read_only=True)
    timeout_s: float = param(0.002, unit='s', description='Longest wait for the reply to one '
                             'sample before it counts as lost.', low=1e-5, high=1.0,
                             read_only=True)
    max_consecutive_losses: int = param(10, unit='-', description='Lost samples in a row '
                                        'before the plant gives up and drives the safe '
                                        'voltage.', low=0, high=100000, read_only=True)


@dataclass(frozen=True)
class ServoParams(Params):
    """The paced servo loop of real-time mode (nodes/servo.py): its clock and its thread."""

    process: bool = param(True, unit='-', description='stage_servo --direct in real time: run '
                          'the servo loop in a process of its own (multiprocessing spawn, '
                          'samples through shared memory); false: a thread beside the ROS '
                          'executor (the plant alone always uses a thread).', read_only=True)
    spin_us: float = param(200.0, unit='us', description='Sleep until this close to each due '
                           'time, then spin on the clock (above the period: always spin; with '
                           'SCHED_FIFO, whose sleeps wake on time, 30 leaves the CPU idle in '
                           'between).', low=0.0, high=1e6, read_only=True)
    fifo_priority: int = param(0, unit='-', description='SCHED_FIFO priority of the servo '
                               'thread (1..99; 0: the default scheduler); applied where '
                               'permitted, else reported.', low=0, high=99, read_only=True)
    nice: int = param(-20, unit='-', description='Nice value of the servo thread under the '
                      'default scheduler (-20: the highest priority; others get only short '
                      'slices of its CPU); applied where permitted (CAP_SYS_NICE, '
                      'RLIMIT_NICE), else reported.', low=-20, high=19, read_only=True)
    cpu: int = param(-1, unit='-', description='CPU the servo thread runs on (-1: any).',
                     low=-1, high=1023, read_only=True)
    switch_interval_us: float = param(0.0, unit='us', description="The interpreter's switch "
                                      'interval (sys.setswitchinterval; 0: unchanged, '
                                      "CPython's default is 5000).", low=0.0, high=1e6,
                                      read_only=True)
    commands_ahead: int = param(128, unit='samples', description='Commands ahead: with each '
                                'command the controller predicts this many next ones, and the '
                                'backend (the simulated stage, the udp_stream target) applies '
                                'them over samples the host misses instead of holding the last '
                                'command (128: 12.8 ms at 10 kHz, past the 10 ms command timeout '
                                'after which the watchdog takes over; a stall longer than the '
                                'queue holds its last prediction; 0: hold, as without). Samples '
                                'the host takes are the same either way.', low=0, high=1000,
                                read_only=True)


@dataclass(frozen=True)
class RecordingParams(Params):
    """What a real-time loop hands to recorders and live subscribers (nodes/recording.py)."""

    block: bool = param(True, unit='-', description='Real time with the servo loop running '
                        'trajectory and controller (stage_servo --direct): publish every sample '
                        'on stage/block, block_samples to a std_msgs/Float64MultiArray (the '
                        'recording that keeps every sample under load; docs/reference/bags.md).',
                        read_only=True)
    block_samples: int = param(100, unit='-', description='Samples a stage/block message '
                               'carries (100: 10 ms at 10 kHz, 100 messages a second).', low=1,
                               high=100000, read_only=True)
    backlog_s: float = param(10.0, unit='s', description='Samples the servo keeps for the '
                             'executor to take, in seconds at the sample rate (the ring of the '
                             'servo process, the queue of a servo thread): a stall of the '
                             'executor shorter than this loses no sample.', low=0.01,
                             high=600.0, read_only=True)
    live_backlog_s: float = param(0.1, unit='s', description='With block: of the samples '
                                  'waiting when the executor comes, the per-sample topics '
                                  'publish the newest this many seconds one by one and leave '
                                  'the older out (counted: live_dropped; stage/block has every '
                                  'one), so that an overloaded executor keeps up.', low=0.0,
                                  low_open=True, high=600.0, read_only=True)


@dataclass(frozen=True)
class WatchdogParams(Params):
    """What the plant drives once commands have stopped (real time; hardware/safety.py)."""

    slew_v_per_s: float = param(100.0, unit='V/s', description='After command_timeout_s '
                                'without a command, ramp the amplifier input to the safe '
                                'voltage at this rate, and follow the commands that come back '
                                'at this rate until they are reached (100: the whole -2..10 V '
                                'input in 0.12 s, 10 mV a sample at 10 kHz). At least 1 V/s: '
                                "a ramp or a deactivate's wind-down ends within seconds.",
                                low=1.0,
                                high=1e6)


@dataclass(frozen=True)
class PlantNodeParams(Params):
    """Plant node parameters beyond the stage itself."""

    mode: str = param('lockstep', unit='-', description=_MODE_DOC, choices=MODES,
                      read_only=True)
    backend: str = param('model', unit='-', description='The stage model of the core, the '
                         'UDP bridge to a real-time I/O target (udp: one request per sample), '
                         'or the same target streaming samples on its own clock (udp_stream: '
                         'the host answers each).', choices=('model', 'udp', 'udp_stream'),
                         read_only=True)
    duration_s: float = param(0.0, unit='s', description='Stop after this much loop time '
                              '(round(duration_s * rate) samples); 0 runs until shut down.',
                              low=0.0, read_only=True)
    command_timeout_s: float = param(0.01, unit='s', description='Hold the last command this '
                                     'long when commands stop, then ramp to the safe voltage '
                                     '(watchdog.slew_v_per_s; realtime).',
                                     low=0.0, low_open=True, high=10.0)
    watchdog: WatchdogParams = group(WatchdogParams, 'command watchdog')
    status_period_s: float = param(1.0, unit='s', description='Period of the stage/status '
                                   'counters (wall time).', low=0.01, high=3600.0)
    lockstep: LockstepParams = group(LockstepParams, 'lockstep start-up')
    bridge: BridgeParams = group(BridgeParams, 'UDP bridge')
    servo: ServoParams = group(ServoParams, 'real-time servo loop')
    recording: RecordingParams = group(RecordingParams, 'real-time recording')

    def _check(self) -> None:
        if self.backend == 'udp_stream' and self.mode != 'realtime':
            raise ParameterError('backend', self.backend, "'model' or 'udp' in lockstep",
                                 'needs mode realtime (the target owns the clock)')


@dataclass(frozen=True)
class _PeerNodeParams(Params):
    """What the controller and trajectory nodes share: the loop's rate and their mode."""

    sample_rate_hz: float = param(10000.0, unit='Hz', description='Sample rate of the loop '
                                  '(set once for every node under /**).', low=1.0, high=1e6,
                                  read_only=True)
    mode: str = param('lockstep', unit='-', description=_MODE_DOC, choices=MODES,
                      read_only=True)


@dataclass(frozen=True)
class ControllerNodeParams(_PeerNodeParams):
    """Controller node parameters beyond the controller itself."""

    position_timeout_s: float = param(0.01, unit='s', description='Publish the safe voltage '
                                      'when positions stop for longer than this (realtime).',
                                      low=0.0, low_open=True, high=10.0)
    safe_voltage_v: float = param(0.0, unit='V', description='Command published by the '
                                  "position watchdog (keep equal to the plant's "
                                  'chain.safe_voltage_v).', low=-10.0, high=10.0)
    diagnostics_every: int = param(10, unit='-', description='Publish stage/diagnostics every '
                                   'this many samples.', low=1, high=1000000)


@dataclass(frozen=True)
class TrajectoryNodeParams(_PeerNodeParams):
    """Trajectory node parameters beyond the trajectory itself."""

    active: bool = param(True, unit='-', description='Stream the trajectory (true) or hold the '
                         'last reference with zero velocity (false); also set by the start and '
                         'stop services.')
    chunk_s: float = param(1.0, unit='s', description='The reference is evaluated this much at '
                           'a time, aligned as the offline runner does (real time: at most '
                           '5 ms at a time).', low=1e-4, high=100.0, read_only=True)
    lockstep_ahead: int = param(0, unit='samples', description='Lockstep: publish the reference '
                                'this many samples ahead of the position it answers (it does '
                                'not depend on the position; the controller pairs by stamp), '
                                'which takes the trajectory node out of the per-sample path; '
                                'a start, stop or switch then takes effect after the samples '
                                'already sent; at most 99, below the depth of the loop '
                                "topics' queues; 0: answer each position.", low=0, high=99,
                                read_only=True)


@dataclass(frozen=True)
class Declaration:
    """
    One ROS parameter as a node declares it (plain values; the node builds the descriptor).

    Attributes
    ----------
    name : str
        Dotted parameter name.
    default : Any
        Default value (lists for arrays).
    type_name : str
        ROS type name of the default (``'double'``, ``'integer'``, ...).
    description : str
        Description with unit and allowed values.
    read_only : bool
        Settable at start-up only.
    float_range : tuple of float or None
        ``(from, to)`` for a double bounded on both sides.
    int_range : tuple of int or None
        ``(from, to)`` for an integer bounded on both sides.
    additional_constraints : str
        The allowed values in words.

    """

    name: str
    default: Any
    type_name: str
    description: str
    read_only: bool
    float_range: tuple[float, float] | None
    int_range: tuple[int, int] | None
    additional_constraints: str


def closest_name(name: str, names: Iterable[str]) -> str | None:
    """Return the name of ``names`` closest to a misspelt ``name`` (difflib), or None."""
    close = difflib.get_close_matches(name, sorted(names), n=1)
    return close[0] if close else None


def declaration(spec: ParamSpec) -> Declaration:
    """
    Return how a node declares the parameter ``spec`` describes.

    Parameters
    ----------
    spec : ParamSpec
        One row of a parameter table.

    Returns
    -------
    Declaration

    """
    unit = '' if spec.unit == '-' else f' [{spec.unit}]'
    default = list(spec.default) if isinstance(spec.default, tuple) else spec.default
    float_range: tuple[float, float] | None = None
    int_range: tuple[int, int] | None = None
    if spec.low is not None and spec.high is not None:
        if spec.type_name == 'double':
            float_range = (float(spec.low), float(spec.high))
        elif spec.type_name == 'integer':
            int_range = (int(spec.low), int(spec.high))
    return Declaration(name=spec.name, default=default, type_name=spec.type_name,
                       description=f'{spec.description}{unit}', read_only=spec.read_only,
                       float_range=float_range, int_range=int_range,
                       additional_constraints=spec.allowed())


@dataclass(frozen=True)
class Group:
    """
    One parameter group of a node table.

    Attributes
    ----------
    cls : type
        The :class:`~piezo_stage_ros.core.contracts.params.Params` subclass.
    prefix : str
        Prepended to its names (``'stability.'``), empty at the top level.
    frozen : bool
        Every parameter of the group is read-only in this node, whatever the group says (the
        stage of the plant node: a stage is not rebuilt under a running loop).

    """

    cls: type[Params]
    prefix: str = ''
    frozen: bool = False


class NodeTable:
    """
    The parameter table of one node: several parameter groups with disjoint names.

    Parameters
    ----------
    node_name : str
        Node name (for messages and the Markdown title).
    groups : sequence of Group or type
        The groups; a bare class is a top-level group.

    Raises
    ------
    ValueError
        If two groups declare the same name.

    """

    def __init__(self, node_name: str, groups: Sequence[Group | type[Params]]) -> None:
        self.node_name = node_name
        self.groups = tuple(g if isinstance(g, Group) else Group(g) for g in groups)
        self._owner: dict[str, int] = {}
        self._specs: dict[str, ParamSpec] = {}
        for index, grp in enumerate(self.groups):
            for spec in grp.cls.specs(grp.prefix):
                if spec.name in self._owner:
                    raise ValueError(f'{node_name}: parameter {spec.name!r} is declared twice')
                if grp.frozen and not spec.read_only:
                    spec = dataclasses.replace(spec, read_only=True)
                self._owner[spec.name] = index
                self._specs[spec.name] = spec

    def specs(self) -> list[ParamSpec]:
        """Return every row of the table, group by group, in declaration order."""
        return list(self._specs.values())

    def select(self, values: Mapping[str, Any]) -> dict[str, Any]:
        """
        Return the values of a node section that belong to this node (the loader's step 3).

        Parameters
        ----------
        values : Mapping[str, Any]
            A node's section of parameter files, wildcard values included
            (:meth:`piezo_stage_ros.core.config.loader.Config.node`).

        Returns
        -------
        dict
            The values whose first dotted part names a parameter or group of the table; names
            under it that the table does not know stay in, for :meth:`build` to refuse.

        """
        heads = {name.split('.', 1)[0] for name in self._specs}
        return {name: value for name, value in values.items()
                if name.split('.', 1)[0] in heads}

    def declarations(self) -> list[Declaration]:
        """Return what the node declares, one entry per parameter."""
        return [declaration(spec) for spec in self._specs.values()]

    def _split(self, values: Mapping[str, Any]) -> list[dict[str, Any]]:
        parts: list[dict[str, Any]] = [{} for _ in self.groups]
        for name, value in values.items():
            owner = self._owner.get(name)
            if owner is None:
                close = closest_name(name, self._specs)
                hint = f"did you mean '{close}'?; " if close else ''
                raise ParameterError(name, value, 'a parameter of ' + self.node_name +
                                     f' ({hint}see docs/reference/ros-interface.md)',
                                     'is not a parameter of this node')
            parts[owner][name] = value
        return parts

    def build(self, values: Mapping[str, Any]) -> tuple[Any, ...]:
        """
        Validate start-up values and return one object per group.

        Parameters
        ----------
        values : Mapping[str, Any]
            Dotted names to values; missing names keep their defaults.

        Returns
        -------
        tuple of Params
            In the order of ``groups``.

        Raises
        ------
        ParameterError
            On the first unknown or bad value.

        """
        return tuple(grp.cls.from_flat(part, prefix=grp.prefix)
                     for grp, part in zip(self.groups, self._split(values)))

    def change(self, current: Sequence[Params], values: Mapping[str, Any]) -> tuple[Any, ...]:
        """
        Validate a run-time change and return the objects with it applied.

        Parameters
        ----------
        current : sequence of Params
            The objects in force, in the order of ``groups``.
        values : Mapping[str, Any]
            The parameters to change.

        Returns
        -------
        tuple of Params
            New objects (unchanged groups are the same objects).

        Raises
        ------
        ParameterError
            For a read-only, unknown or bad value, or a combination a group refuses.

        """
        parts = self._split(values)
        for name, value in values.items():
            if self._specs[name].read_only:
                grp = self.groups[self._owner[name]]
                now = current[self._owner[name]].to_flat(grp.prefix)[name]
                raise ParameterError(name, value, f'its start-up value {now!r}',
                                     'is read-only (set it in the parameter file)')
        return tuple(obj.with_flat(part, prefix=grp.prefix) if part else obj
                     for obj, grp, part in zip(current, self.groups, parts))

    def markdown(self) -> str:
        """Return the table as Markdown (name, type, default, unit, allowed, description)."""
        lines = [f'#### `{self.node_name}`', '',
                 '| name | type | default | unit | allowed | read-only | description |',
                 '| --- | --- | --- | --- | --- | --- | --- |']
        for spec in self._specs.values():
            default = spec.default
            if isinstance(default, float):
                text = repr(default) if math.isfinite(default) else str(default)
            elif isinstance(default, bool):
                text = 'true' if default else 'false'
            elif isinstance(default, tuple):
                text = '[' + ', '.join(repr(v) for v in default) + ']'
            else:
                text = str(default)
            lines.append(f'| `{spec.name}` | {spec.type_name} | `{text}` | {spec.unit} | '
                         f'{spec.allowed()} | {"yes" if spec.read_only else "no"} | '
                         f'{spec.description} |')
        return '\n'.join(lines) + '\n'
