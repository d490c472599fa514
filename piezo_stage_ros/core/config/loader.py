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
The loader: from ROS 2 parameter files to the loop's validated objects, read top to bottom.

The parameter files in ``config/`` configure three ROS nodes; the offline commands (``simulate``,
``soak``, ``identify``, ``tune``, ``check``), the emulator, the nodes and the launch files all turn
them into objects here, so a file means the same thing everywhere. The way, in the order of this
module:

1. **Read the files** (:func:`load_config`, :func:`find_config`): ordinary ROS 2 parameter files,
   usable with ``ros2 run ... --ros-args --params-file FILE`` and in launch files::

       /**:
         ros__parameters:
           sample_rate_hz: 10000.0
       plant_node:
         ros__parameters:
           plant:
             model: third_order

   Nested mappings become dotted names (``plant.model``), as ROS 2 does; a later file overrides
   an earlier one. The result is a :class:`Config`: flat per-node dictionaries, knowing no
   parameter.
2. **Merge overrides** (:func:`merge_overrides`, :meth:`Config.with_overrides`): values given
   on a command line or by a launch file go on top of the files' section of a node.
3. **Validate** each node's section against its table (:func:`validate`; :func:`plant_table`,
   :func:`controller_table`, :func:`trajectory_table`; the tables themselves are
   :class:`~piezo_stage_ros.core.config.nodes.NodeTable`): which names belong to the node
   (:meth:`~piezo_stage_ros.core.config.nodes.NodeTable.select`) is a name whose first dotted
   part is a parameter or group of the node's table; it is validated strictly (a misspelt
   ``rac.epsilon`` is refused), each group by its own
   :meth:`~piezo_stage_ros.core.contracts.params.Params.from_flat`. Other names (``use_sim_time``
   in a ``/**`` wildcard section, ``qos_overrides.*``) are left to ROS, which ignores what a node
   does not declare.
4. **Build** the objects: :class:`LoopConfig` holds those of all three tables
   (:meth:`LoopConfig.from_config`), and :func:`load_loop_config` takes the whole way from files
   to it. A multi-axis stage is the same loader's other entry
   (:func:`piezo_stage_ros.core.config.axes.axes_loop_config`), built on this one-axis base.

Why here, on top of core/: the loader builds the stage (model), the controller and its stability
check (control) and the trajectory (loop), so it stands above all of them; below, every floor
(contracts <- signals <- model <- control <- loop <- identification) uses only the floors under
it, and none needs the loader. The folder is named after what it reads (the ``config/`` files),
so whoever looks for where a YAML file becomes objects finds it there.

Node settings without meaning offline (rule, the same for every offline command): ``mode``,
``backend``, ``duration_s``, the timeouts, ``lockstep.*`` and ``bridge.*`` are validated like
any other value (a bad one is refused everywhere), and an offline command runs the stage model
in its own loop whatever they say; :meth:`LoopConfig.offline_notes` names the ones set to
something an offline run cannot honour (``mode: realtime``, ``backend: udp``), and the commands
print that note once.

The design model (the plant the controller's stability check and a ``model`` notch use) is the
plant node's ``plant.*`` unless ``controller_node stability.design_model: own`` selects the
controller's own ``stability.plant.*`` (:attr:`LoopConfig.design_plant`,
docs/reference/ros-interface.md).

Every parameter is declared with dynamic typing in the nodes and validated here, because ROS
would otherwise refuse an integer written in YAML for a double parameter (``0`` instead of
``0.0``); the core validation accepts integers where floats are expected and refuses everything
else with a reason.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
import os
from pathlib import Path
import re
import sys
from typing import Any, Iterable, Mapping

from piezo_stage_ros.core.config.nodes import (
    closest_name,
    ControllerNodeParams,
    Group,
    NodeTable,
    PlantNodeParams,
    TrajectoryNodeParams,
)
from piezo_stage_ros.core.contracts.errors import ConfigError, ParameterError
from piezo_stage_ros.core.control.controllers import ControllerParams
from piezo_stage_ros.core.control.stability import StabilityParams
from piezo_stage_ros.core.loop.trajectories import check_sampling, TrajectoryParams
from piezo_stage_ros.core.model.stage import PlantParams, StageParams
import yaml

__all__ = ['AXES_HEADS', 'check_heads', 'Config', 'LoopConfig', 'OTHER_HEADS', 'TABLES',
           'controller_table', 'design_plant', 'find_config', 'flatten', 'load_config',
           'load_loop_config', 'merge_overrides', 'nest', 'plant_table', 'trajectory_table',
           'validate']


# --------------------------------------------------------------------------------------------
# 1. Read the files


WILDCARD = '/**'
PACKAGE = 'piezo_stage_ros'


class _RosYamlLoader(yaml.SafeLoader):
    """
    A safe YAML loader that reads ``1e-6`` as a float, as ROS 2 (yaml-cpp) does.

    PyYAML follows YAML 1.1, where a float needs a dot (``1.0e-6``); a parameter file written for
    ROS would otherwise give the string ``'1e-6'``.
    """


_RosYamlLoader.add_implicit_resolver(
    'tag:yaml.org,2002:float',
    re.compile(r"""^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"""),
    list('-+0123456789'))


def flatten(mapping: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """
    Flatten nested mappings into dotted names, as ROS 2 does for parameter files.

    Parameters
    ----------
    mapping : Mapping
        Nested parameter values.
    prefix : str
        Prepended to every name.

    Returns
    -------
    dict
        ``{'a.b': value}`` for ``{'a': {'b': value}}``.

    """
    out: dict[str, Any] = {}
    for key, value in mapping.items():
        name = f'{prefix}{key}'
        if isinstance(value, Mapping):
            out.update(flatten(value, name + '.'))
        else:
            out[name] = value
    return out


def nest(flat: Mapping[str, Any]) -> dict[str, Any]:
    """Turn dotted names into nested mappings, as a ROS 2 parameter file holds them."""
    out: dict[str, Any] = {}
    for name, value in flat.items():
        node = out
        parts = name.split('.')
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out


def _node_key(section: str) -> str:
    """Return ``'plant_node'`` for ``'/ns/plant_node'``, and ``'/**'`` for any wildcard."""
    if section.strip('/') in ('**', '*'):
        return WILDCARD
    return section.rstrip('/').rsplit('/', 1)[-1]


@dataclass(frozen=True)
class Config:
    """
    Parameters of every node, read from one or more ROS 2 parameter files.

    Attributes
    ----------
    sources : tuple of Path
        Files read, in order (later files override earlier ones).
    sections : dict
        ``{node name or '/**': {dotted name: value}}``.

    """

    sources: tuple[Path, ...] = ()
    sections: dict[str, dict[str, Any]] = field(default_factory=dict)

    def node(self, name: str) -> dict[str, Any]:
        """
        Return the flat parameters of node ``name``, wildcard ``/**`` values included.

        Parameters
        ----------
        name : str
            Node name, e.g. ``'controller_node'``.

        Returns
        -------
        dict
            ``{dotted name: value}``; node-specific values override wildcard ones.

        """
        merged = dict(self.sections.get(WILDCARD, {}))
        merged.update(self.sections.get(name, {}))
        return merged

    def with_overrides(self, name: str, values: Mapping[str, Any]) -> Config:
        """Return a copy with ``values`` set in the section of node ``name``."""
        sections = {k: dict(v) for k, v in self.sections.items()}
        sections.setdefault(name, {}).update(values)
        return Config(self.sources, sections)


def load_config(paths: Iterable[str | os.PathLike[str]]) -> Config:
    """
    Read ROS 2 parameter files into one :class:`Config`.

    Parameters
    ----------
    paths : iterable of path-like
        Files, read in order; a later file overrides values of an earlier one.

    Returns
    -------
    Config

    Raises
    ------
    ConfigError
        If a file is missing, is not YAML, or is not shaped ``<node>: ros__parameters: {...}``;
        the message names the file and what is wrong.

    """
    sources: list[Path] = []
    sections: dict[str, dict[str, Any]] = {}
    for raw in paths:
        path = Path(raw)
        try:
            text = path.read_text(encoding='utf-8')
        except OSError as exc:
            raise ConfigError(f'{path}: cannot read parameter file ({exc.strerror})') from None
        try:
            doc = yaml.load(text, Loader=_RosYamlLoader)  # noqa: S506 (a SafeLoader)
        except yaml.YAMLError as exc:
            raise ConfigError(f'{path}: not valid YAML ({exc})') from None
        if doc is None:
            doc = {}
        if not isinstance(doc, dict):
            raise ConfigError(f'{path}: expected a mapping of node names, '
                              f'got {type(doc).__name__}')
        for section, body in doc.items():
            if not isinstance(body, dict) or set(body) != {'ros__parameters'} or \
                    not isinstance(body['ros__parameters'], dict):
                raise ConfigError(f'{path}: section {section!r} must contain exactly '
                                  "'ros__parameters:' with a mapping of parameters")
            key = _node_key(str(section))
            sections.setdefault(key, {}).update(flatten(body['ros__parameters']))
        sources.append(path)
    return Config(tuple(sources), sections)


def find_config(name: str = 'default.yaml') -> Path:
    """
    Locate a configuration file shipped with the package.

    Looks, in order, in the source tree (``config/`` beside the package), in
    ``<sys.prefix>/share/piezo_stage_ros/config`` (pip or virtualenv install) and in every
    ``share/piezo_stage_ros/config`` of ``AMENT_PREFIX_PATH`` (a colcon install). A name that is
    an existing path is returned as it is.

    Parameters
    ----------
    name : str
        File name (``'default.yaml'``, ``'table3_rac.yaml'`` ...) or a path.

    Returns
    -------
    Path

    Raises
    ------
    ConfigError
        If no such file exists; the message lists where it looked.

    """
    given = Path(name)
    if given.is_file():
        return given
    roots = [Path(__file__).resolve().parents[3] / 'config',
             Path(sys.prefix) / 'share' / PACKAGE / 'config']
    roots += [Path(p) / 'share' / PACKAGE / 'config'
              for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    for root in roots:
        if (root / name).is_file():
            return root / name
    raise ConfigError(f'configuration {name!r} not found; looked in: '
                      + ', '.join(str(r) for r in roots))


# --------------------------------------------------------------------------------------------
# 2. Merge overrides


def merge_overrides(config: Config,
                    overrides: Mapping[str, Mapping[str, Any]] | None) -> Config:
    """Return ``config`` with ``{node name: {dotted name: value}}`` set over its files."""
    for node, values in (overrides or {}).items():
        config = config.with_overrides(node, values)
    return config


# --------------------------------------------------------------------------------------------
# 3. Validate: each node's table, its core groups and its own, checked strictly


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


#: The three nodes of the loop, by their node names.
TABLES = {'plant_node': plant_table, 'controller_node': controller_table,
          'trajectory_node': trajectory_table}

#: Top-level names a node section may hold besides its table's: what rclpy declares itself or
#: reads on request.
OTHER_HEADS = ('use_sim_time', 'qos_overrides')

#: Top-level names the nodes of several axes (files with ``plant_node axes.names``) declare
#: besides the one-axis tables'; the nodes of one axis declare none of them.
AXES_HEADS = {'plant_node': ('axes',), 'controller_node': ('axes',),
              'trajectory_node': ('axes', 'scan')}


def check_heads(config: Config) -> None:
    """
    Refuse a name in a node's own section whose first dotted part the node does not know.

    The tables refuse an unknown name under one of their groups; a name outside every group
    (``sed: 3`` for ``seed: 3``) would otherwise be left out unread, where the node refuses it.
    ``axes.*`` and ``scan.*`` (:data:`AXES_HEADS`) are names only in files of several axes.
    Wildcard (``/**``) values are not checked: they may be meant for another node.

    Parameters
    ----------
    config : Config
        The files' sections.

    Raises
    ------
    ParameterError
        Naming the node, the name and the allowed top-level names.

    """
    several = 'axes.names' in config.node('plant_node')
    for node, make in TABLES.items():
        table = make()
        heads = list(dict.fromkeys(spec.name.split('.', 1)[0] for spec in table.specs()))
        others = list(OTHER_HEADS) + list(AXES_HEADS[node] if several else ())
        for name, value in config.sections.get(node, {}).items():
            head = name.split('.', 1)[0]
            if head in heads or head in others:
                continue
            close = closest_name(name, [spec.name for spec in table.specs()])
            hint = f"did you mean '{close}'? " if close else ''
            if not several and head in AXES_HEADS[node]:
                hint += (f'{head}.* only in a file of several axes (with plant_node '
                         'axes.names); otherwise ')
            allowed = ', '.join(heads + others)
            raise ParameterError(f'{node} {name}', value, f'{hint}a name under one of the '
                                 f'top-level keys of {node}: {allowed} '
                                 '(docs/reference/ros-interface.md)',
                                 'is not a parameter of this node')


def validate(config: Config) -> dict[str, Any]:
    """
    Validate each node's section against its table: plant, controller, trajectory, in this order.

    Parameters
    ----------
    config : Config
        The files' sections (and any overrides merged into them).

    Returns
    -------
    dict
        The validated objects by their :class:`LoopConfig` field: ``stage``, ``plant_node``,
        ``controller``, ``stability``, ``controller_node``, ``trajectory``, ``trajectory_node``.

    Raises
    ------
    ParameterError
        On the first bad value, or an unknown name (:func:`check_heads`, or under a known
        group) of any node, or a trajectory the sample rate cannot draw.

    """
    check_heads(config)
    stage, plant_node = plant_table().build(plant_table().select(config.node('plant_node')))
    table = controller_table()
    controller, stability, controller_node = table.build(
        table.select(config.node('controller_node')))
    table = trajectory_table()
    trajectory, trajectory_node = table.build(table.select(config.node('trajectory_node')))
    check_sampling(trajectory, trajectory_node.sample_rate_hz)
    return {'stage': stage, 'plant_node': plant_node, 'controller': controller,
            'stability': stability, 'controller_node': controller_node,
            'trajectory': trajectory, 'trajectory_node': trajectory_node}


# --------------------------------------------------------------------------------------------
# 4. Build the objects


@dataclass(frozen=True)
class LoopConfig:
    """
    Every parameter of the loop, validated: the objects of the three node tables.

    Attributes
    ----------
    stage : StageParams
        The stage (plant node).
    plant_node : PlantNodeParams
        The plant node's own settings.
    controller : ControllerParams
        The controller.
    stability : StabilityParams
        The controller's stability check (and its own design model, ``stability.plant``).
    controller_node : ControllerNodeParams
        The controller node's own settings.
    trajectory : TrajectoryParams
        The reference.
    trajectory_node : TrajectoryNodeParams
        The trajectory node's own settings.
    sources : tuple of Path
        The parameter files read, in order.

    """

    stage: StageParams = dataclasses.field(default_factory=StageParams)
    plant_node: PlantNodeParams = dataclasses.field(default_factory=PlantNodeParams)
    controller: ControllerParams = dataclasses.field(default_factory=ControllerParams)
    stability: StabilityParams = dataclasses.field(default_factory=StabilityParams)
    controller_node: ControllerNodeParams = dataclasses.field(
        default_factory=ControllerNodeParams)
    trajectory: TrajectoryParams = dataclasses.field(default_factory=TrajectoryParams)
    trajectory_node: TrajectoryNodeParams = dataclasses.field(
        default_factory=TrajectoryNodeParams)
    sources: tuple[Path, ...] = ()

    @classmethod
    def from_config(cls, config: Config) -> LoopConfig:
        """Build every object of the loop from files already read; errors as :func:`validate`."""
        return cls(**validate(config), sources=config.sources)

    def replace(self, **changes: Any) -> LoopConfig:
        """Return a copy with some objects changed (like ``dataclasses.replace``)."""
        return dataclasses.replace(self, **changes)

    @property
    def design_plant(self) -> PlantParams:
        """
        Return the model the controller is checked (and a ``model`` notch designed) against.

        The plant node's ``plant.*``, unless ``stability.design_model`` is ``'own'``: then the
        controller's own ``stability.plant.*`` (a real stage: the identified model).
        """
        return design_plant(self.stability, self.stage.plant)

    def offline_notes(self) -> list[str]:
        """
        Return what an offline run does not honour of the node settings (module docstring).

        Returns
        -------
        list of str
            One sentence per setting; empty when the files describe a lockstep model run.

        """
        notes = []
        modes = [(name, obj.mode) for name, obj in (('plant_node', self.plant_node),
                                                    ('controller_node', self.controller_node),
                                                    ('trajectory_node', self.trajectory_node))
                 if obj.mode != 'lockstep']
        if modes:
            said = ', '.join(f'{name} mode: {mode}' for name, mode in modes)
            notes.append(f'{said} applies to the ROS nodes; an offline run steps the loop in '
                         'its own time (as lockstep does)')
        if self.plant_node.backend != 'model':
            notes.append(f'plant_node backend: {self.plant_node.backend} applies to the ROS '
                         'plant node; an offline run simulates the stage model')
        return notes


def design_plant(stability: StabilityParams, plant: PlantParams) -> PlantParams:
    """
    Return the controller's design model: ``plant`` or, on request, its own.

    Parameters
    ----------
    stability : StabilityParams
        The controller's stability options (``design_model``, ``plant``).
    plant : PlantParams
        The plant node's model.

    Returns
    -------
    PlantParams
        ``plant`` when ``stability.design_model`` is ``'plant'``, else ``stability.plant``.

    """
    return plant if stability.design_model == 'plant' else stability.plant


def load_loop_config(paths: Iterable[str | os.PathLike[str]],
                     overrides: Mapping[str, Mapping[str, Any]] | None = None) -> LoopConfig:
    """
    Read parameter files and build the loop configuration.

    Parameters
    ----------
    paths : iterable of path-like
        Parameter files, in order (later files win).
    overrides : mapping, optional
        ``{node name: {dotted name: value}}`` applied on top of the files.

    Returns
    -------
    LoopConfig

    Raises
    ------
    ConfigError
        If a file cannot be read or is not a parameter file.
    ParameterError
        On a bad value.

    """
    return LoopConfig.from_config(merge_overrides(load_config(paths), overrides))
