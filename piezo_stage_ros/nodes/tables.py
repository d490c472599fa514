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
The node side of the loop configuration (rclpy-free): the tables, and the files a node was given.

The parameter tables and the typed loader live in :mod:`piezo_stage_ros.core.config.loader`
(every command, the emulator, the launch file and the nodes build their objects there); this
module names them for the nodes and adds what only a node needs: the parameter files on its
command line (:func:`params_files`), from which the controller node takes the plant node's
model (docs/reference/ros-interface.md, "Parameters at run time").
"""

from __future__ import annotations

from typing import Any, Sequence

from piezo_stage_ros.core.config.loader import (
    controller_table,
    design_plant,
    load_loop_config,
    LoopConfig,
    plant_table,
    trajectory_table,
)
from piezo_stage_ros.core.config.nodes import (
    BridgeParams,
    ControllerNodeParams,
    Declaration,
    declaration,
    Group,
    LockstepParams,
    MODES,
    NodeTable,
    PlantNodeParams,
    TrajectoryNodeParams,
)
from piezo_stage_ros.core.config.unknown import ros_options
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.control.stability import StabilityParams
from piezo_stage_ros.core.loop.scan2d import ScanParams
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryBase
from piezo_stage_ros.core.model.hysteresis import HysteresisModel, make_hysteresis
from piezo_stage_ros.core.model.stage import PlantParams

__all__ = ['BridgeParams', 'ControllerNodeParams', 'Declaration', 'Group', 'LockstepParams',
           'MODES', 'NodeTable', 'PlantNodeParams', 'TrajectoryNodeParams', 'controller_table',
           'axes_markdown', 'declaration', 'design_model', 'params_files', 'plant_table',
           'scan_table', 'trajectory_table']


def params_files(argv: Sequence[str]) -> list[str]:
    """
    Return the ``--params-file`` arguments of a ROS command line, in order.

    Parameters
    ----------
    argv : sequence of str
        The command line (``sys.argv``, or a node's ``cli_args``); only the parts between
        ``--ros-args`` and ``--`` (or the end) are ROS arguments.

    Returns
    -------
    list of str
        The files, in the order ROS applies them (later ones win).

    """
    return [value for flag, value in ros_options(argv) if flag == '--params-file']


def _loop(files: Sequence[str]) -> LoopConfig:
    """Return the files' loop configuration; a bad value's error names the files."""
    try:
        return load_loop_config(files)
    except ParameterError as exc:
        raise ParameterError(exc.name, exc.value, f'{exc.allowed}; read from '
                             + ', '.join(files), exc.reason) from None


def design_model(stability: StabilityParams, files: Sequence[str]
                 ) -> tuple[PlantParams, str]:
    """
    Return the controller node's design model and, in words, where it comes from.

    The rule of :attr:`piezo_stage_ros.core.config.loader.LoopConfig.design_plant`, for a
    node that sees only its own parameters: with ``stability.design_model: plant`` the model is the
    ``plant.*`` of the plant_node section of the parameter files the node was given (the files
    the plant node reads, or the launch file's merged one); no file gives the plant node's
    defaults, as a plant node started without one runs them.

    Parameters
    ----------
    stability : StabilityParams
        The controller node's stability options.
    files : sequence of str
        The ``--params-file`` files of the node's command line (:func:`params_files`).

    Returns
    -------
    plant : PlantParams
        The design model.
    source : str
        For the start-up log, e.g. ``"the plant node's reduced model (plant_node plant.* of
        a.yaml, b.yaml)"``.

    Raises
    ------
    ConfigError, ParameterError
        If a file cannot be read or holds a bad value.

    """
    if stability.design_model == 'own':
        return stability.plant, (f'its own {stability.plant.model} model (stability.plant.*, '
                                 'stability.design_model: own)')
    if not files:
        plant = design_plant(stability, PlantParams())
        return plant, (f"the plant node's default {plant.model} model (no --params-file; set "
                       'the plant in a parameter file given to both nodes, or '
                       'stability.design_model: own)')
    plant = design_plant(stability, _loop(files).stage.plant)
    return plant, (f"the plant node's {plant.model} model (plant_node plant.* of "
                   + ', '.join(files) + ')')


def feedforward_context(files: Sequence[str]
                        ) -> tuple[tuple[HysteresisModel, TrajectoryBase], dict[str, Any]]:
    """
    Return what a controller node's feed-forward is bound to, and what its check is told.

    Read from the same parameter files as :func:`design_model` (the plant_node and
    trajectory_node sections the other two nodes read; their defaults without a file), so that
    the reference ahead is the one the trajectory node will play.

    Returns
    -------
    bound : (HysteresisModel, TrajectoryBase)
        The design hysteresis and the trajectory (``bound_controller``'s last two arguments).
    check : dict
        ``period_s`` (the trajectory's period, ``None`` if aperiodic) and ``stage`` (the
        configured stage) for ``check_stability``: the learning's convergence over the
        hysteresis slopes and the stage family.

    """
    loop = _loop(files)
    reference = make_trajectory(loop.trajectory)
    return ((make_hysteresis(loop.stage.hysteresis), reference),
            {'period_s': reference.period_s, 'stage': loop.stage})


def scan_table() -> NodeTable:
    """Return the trajectory node's scan over several axes (``scan.*``, read at start-up)."""
    return NodeTable('trajectory_node, several axes', [Group(ScanParams, 'scan.', frozen=True)])


_AXES_ROWS = (
    ('plant_node', 'axes.names', 'string array', 'one, two or three of x, y, z (quoted: ROS '
     'reads a bare y as true), each once', 'The axes; given, the nodes run several axes.'),
    ('plant_node', 'axes.coupling.gain', 'double array', 'n x n, row-major, row i driving '
     'column j', 'DC coupling from the driving axis to the moved one [m/m].'),
    ('plant_node', 'axes.coupling.resonance_hz', 'double array', 'n x n, 0: none',
     'Coupled resonance of each path [Hz].'),
    ('plant_node', 'axes.coupling.damping', 'double array', 'n x n', 'Its damping [-].'),
    ('plant_node', 'axes.coupling.sensor_crosstalk', 'double array', 'n x n',
     'Sensor cross-talk [m/m].'),
    ('controller_node', 'axes.coupling_compensation', 'bool', 'true, false',
     'The model inverse of the coupling in the feed-forward.'),
    ('every node', 'axes.<axis>.<name>', 'as `<name>`', 'as `<name>`',
     "Overrides the node's parameter `<name>` for one axis."),
)


def axes_markdown() -> str:
    """Return the multi-axis parameters as Markdown: the names above every node's tables."""
    lines = ['#### Several axes', '',
             'Read at start-up only (read-only), from the files with plant_node `axes.names`; '
             "every node's own parameters are the base of each axis.", '',
             '| node | name | type | allowed | description |', '| --- | --- | --- | --- | --- |']
    lines += [f'| {node} | `{name}` | {kind} | {allowed} | {text} |'
              for node, name, kind, allowed, text in _AXES_ROWS]
    return '\n'.join(lines) + '\n\n' + scan_table().markdown()


def main() -> int:
    """Print the node tables as Markdown (``python3 -m piezo_stage_ros.nodes.tables``)."""
    for table in (plant_table(), controller_table(), trajectory_table()):
        print(table.markdown())
    print(axes_markdown())
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
