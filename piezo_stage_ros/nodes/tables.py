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
The declarative parameter table of each node, and what a node needs from it (rclpy-free).

A node's table is the core parameter group it configures (the stage, the controller, the
trajectory) plus a small node group (mode, timeouts, bridge), all declared with
:func:`~piezo_stage_ros.core.params.param`. From the table come:

- the ROS parameter declarations (:meth:`NodeTable.declarations`: name, default, descriptor
  fields: description with unit and allowed range, range when both ends are bounded, read-only);
- the validated objects at start-up (:meth:`NodeTable.build`);
- the validation of a run-time change (:meth:`NodeTable.change`): the new objects, or a
  :class:`~piezo_stage_ros.core.errors.ParameterError` naming the parameter, value and range,
  which the node turns into a refused ``SetParametersResult``.

Every parameter is declared with dynamic typing and validated here, because ROS would otherwise
refuse an integer written in YAML for a double parameter (``0`` instead of ``0.0``); the core
validation accepts integers where floats are expected and refuses everything else with a
reason.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import math
from typing import Any, Mapping, Sequence

from piezo_stage_ros.core.controllers import ControllerParams
from piezo_stage_ros.core.errors import ParameterError
from piezo_stage_ros.core.params import group, param, Params, ParamSpec
from piezo_stage_ros.core.stability import StabilityParams
from piezo_stage_ros.core.stage import StageParams
from piezo_stage_ros.core.trajectories import TrajectoryParams

__all__ = ['BridgeParams', 'ControllerNodeParams', 'Declaration', 'Group', 'LockstepParams',
           'MODES', 'NodeTable', 'PlantNodeParams', 'TrajectoryNodeParams', 'controller_table',
           'plant_table', 'trajectory_table']

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
    """The UDP hardware bridge (backend 'udp'); protocol in docs/nodes.md."""

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
class PlantNodeParams(Params):
    """Plant node parameters beyond the stage itself."""

    mode: str = param('lockstep', unit='-', description=_MODE_DOC, choices=MODES,
                      read_only=True)
    backend: str = param('model', unit='-', description='The stage model of the core, or the '
                         'UDP bridge to a real-time I/O target.', choices=('model', 'udp'),
                         read_only=True)
    duration_s: float = param(0.0, unit='s', description='Stop after this much loop time '
                              '(round(duration_s * rate) samples); 0 runs until shut down.',
                              low=0.0, read_only=True)
    command_timeout_s: float = param(0.01, unit='s', description='Drive the safe voltage when '
                                     'commands stop for longer than this (realtime).',
                                     low=0.0, low_open=True, high=10.0)
    status_period_s: float = param(1.0, unit='s', description='Period of the stage/status '
                                   'counters (wall time).', low=0.01, high=3600.0)
    lockstep: LockstepParams = group(LockstepParams, 'lockstep start-up')
    bridge: BridgeParams = group(BridgeParams, 'UDP bridge')


@dataclass(frozen=True)
class ControllerNodeParams(Params):
    """Controller node parameters beyond the controller itself."""

    sample_rate_hz: float = param(10000.0, unit='Hz', description='Sample rate of the loop '
                                  '(set once for every node under /**).', low=1.0, high=1e6,
                                  read_only=True)
    mode: str = param('lockstep', unit='-', description=_MODE_DOC, choices=MODES,
                      read_only=True)
    position_timeout_s: float = param(0.01, unit='s', description='Publish the safe voltage '
                                      'when positions stop for longer than this (realtime).',
                                      low=0.0, low_open=True, high=10.0)
    safe_voltage_v: float = param(0.0, unit='V', description='Command published by the '
                                  "position watchdog (keep equal to the plant's "
                                  'chain.safe_voltage_v).', low=-10.0, high=10.0)
    diagnostics_every: int = param(10, unit='-', description='Publish stage/diagnostics every '
                                   'this many samples.', low=1, high=1000000)


@dataclass(frozen=True)
class TrajectoryNodeParams(Params):
    """Trajectory node parameters beyond the trajectory itself."""

    sample_rate_hz: float = param(10000.0, unit='Hz', description='Sample rate of the loop '
                                  '(set once for every node under /**).', low=1.0, high=1e6,
                                  read_only=True)
    mode: str = param('lockstep', unit='-', description=_MODE_DOC, choices=MODES,
                      read_only=True)
    active: bool = param(True, unit='-', description='Stream the trajectory (true) or hold the '
                         'last reference with zero velocity (false); also set by the start and '
                         'stop services.')
    chunk_s: float = param(1.0, unit='s', description='The reference is evaluated this much at '
                           'a time, aligned as the offline runner does (real time: at most '
                           '5 ms at a time).', low=1e-4, high=100.0, read_only=True)


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
    bounded = spec.low is not None and spec.high is not None
    float_range = (float(spec.low), float(spec.high)) if bounded and \
        spec.type_name == 'double' else None  # type: ignore[arg-type]
    int_range = (int(spec.low), int(spec.high)) if bounded and \
        spec.type_name == 'integer' else None  # type: ignore[arg-type]
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
        The :class:`~piezo_stage_ros.core.params.Params` subclass.
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

    def declarations(self) -> list[Declaration]:
        """Return what the node declares, one entry per parameter."""
        return [declaration(spec) for spec in self._specs.values()]

    def _split(self, values: Mapping[str, Any]) -> list[dict[str, Any]]:
        parts: list[dict[str, Any]] = [{} for _ in self.groups]
        for name, value in values.items():
            owner = self._owner.get(name)
            if owner is None:
                raise ParameterError(name, value, 'a parameter of ' + self.node_name +
                                     ' (see docs/nodes.md)', 'is not a parameter of this node')
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


def plant_table() -> NodeTable:
    """Return the table of ``plant_node``: the stage (start-up only) and the node group."""
    return NodeTable('plant_node', [Group(StageParams, frozen=True), Group(PlantNodeParams)])


def controller_table() -> NodeTable:
    """Return the table of ``controller_node``: controller, stability check, node group."""
    return NodeTable('controller_node', [Group(ControllerParams),
                                         Group(StabilityParams, prefix='stability.'),
                                         Group(ControllerNodeParams)])


def trajectory_table() -> NodeTable:
    """Return the table of ``trajectory_node``: the trajectory and the node group."""
    return NodeTable('trajectory_node', [Group(TrajectoryParams), Group(TrajectoryNodeParams)])


def main() -> int:
    """Print the three tables as Markdown (``python3 -m piezo_stage_ros.nodes.tables``)."""
    for table in (plant_table(), controller_table(), trajectory_table()):
        print(table.markdown())
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
