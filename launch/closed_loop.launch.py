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
Start the closed loop: plant, controller and trajectory nodes from one parameter file.

Arguments (``ros2 launch piezo_stage_ros closed_loop.launch.py --show-args``):

- ``config``: parameter file (a name in the package's ``config/`` or a path), default
  ``default.yaml``; ``scenario``: a second file applied on top (``table3_rac.yaml`` ...);
  ``overrides``: a third file applied last (empty: none);
- ``mode``: ``lockstep`` | ``realtime``; ``controller``: ``rac`` | ``pi`` | ``open_loop`` (empty:
  as configured); ``duration_s``: stop the run after this much loop time (0: run on);
- ``composed``: ``true`` runs the three nodes in one process (``stage_servo``, one
  EventsExecutor), ``false`` one process each;
- ``record``: ``true`` records the stage topics with ``ros2 bag record`` into ``bag`` (in real
  time with ``direct:=true``: ``stage/block``, every sample in blocks, and ``stage/status``);
- ``namespace``: puts the stage's topics and nodes under it (several stages side by side);
- ``end_with_plant``: ``true`` ends the launch when the plant's process exits (its run of
  ``duration_s`` is complete, or it failed); ``executor``: ``events`` | ``single``;
- ``direct``: with ``composed:=true``, the three nodes hand each sample to each other by call
  (``stage_servo --direct``, as rclcpp's intra-process communication) and publish the topics
  for outside subscribers only;
- ``autostart``: ``true`` configures and activates the plant node (a managed node) as soon as
  its process is up, so that the loop runs at once; ``false`` leaves it unconfigured, for
  ``ros2 lifecycle set /plant_node configure`` (then ``activate``). The executables make the
  transitions themselves (``--autostart``): launch_ros's ``LifecycleNode`` action names its
  node, which in the composed process would rename all three nodes;
- ``sim_time``: in lockstep, ``use_sim_time`` on the controller and trajectory nodes (their logs
  and clocks follow ``/clock``); ``false`` saves delivering every ``/clock`` message to them. The
  plant owns simulation time and keeps its own clock either way.

The files are read and validated once here by the loader every command uses
(:class:`piezo_stage_ros.core.config.loader.LoopConfig`): a bad value stops the launch
before any process starts. The controller's stability check runs against the plant model the plant
node runs, as ``simulate`` does: all three nodes get one merged parameter file, and the controller
takes the design model from its plant_node section (``stability.design_model: plant``, the
default; docs/reference/ros-interface.md). When the plant ends its run the launch ends. A file
with plant_node ``axes.names`` (``config:=xy_stage.yaml``) runs the nodes of several axes: in
lockstep, or in real time composed with ``direct:=true`` (the servo's composition; real time
without it, and ``direct:=true`` in lockstep, are refused here).
"""

# ruff takes `launch` for this repository's launch/ folder; for ament (flake8) it is the
# third-party package it is, sorted as below. mypy checks this file (make typecheck) with
# namespace packages off (pyproject.toml), so `launch` is ROS's package, not that folder.
from __future__ import annotations  # noqa: I001

import os
import tempfile
from typing import Any, Mapping

from launch import LaunchContext, LaunchDescription
from launch.actions import (
    DeclareLaunchArgument,
    EmitEvent,
    ExecuteProcess,
    OpaqueFunction,
    RegisterEventHandler,
)
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from piezo_stage_ros.cli import choices
from piezo_stage_ros.core.config.axes import axes_loop_config, has_axes
from piezo_stage_ros.core.config.loader import Config, find_config, load_config, LoopConfig
from piezo_stage_ros.core.config.nodes import MODES
from piezo_stage_ros.core.control.controllers import ControllerParams
from piezo_stage_ros.core.contracts.wire import (
    BLOCK_RECORDED_TOPICS,
    RECORDED_TOPICS,
    TRUE_POSITION,
)
from piezo_stage_ros.nodes.axes_logic import refuse_axes_mode
import yaml

ARGUMENTS = {
    'config': ('default.yaml', 'parameter file: a name in config/ or a path'),
    'scenario': ('', 'second parameter file applied on top of config (empty: none)'),
    'overrides': ('', 'third parameter file applied last (empty: none)'),
    'mode': ('lockstep', ' | '.join(MODES)),
    'controller': ('', ' | '.join(choices(ControllerParams, 'type')) + ' (empty: as configured)'),
    'duration_s': ('0.0', 'run length in loop time [s]; 0 runs until shut down'),
    'composed': ('true', 'true: one process (stage_servo); false: one process per node'),
    'record': ('false', 'record the stage topics with ros2 bag record'),
    'bag': ('', 'bag directory for record:=true (empty: piezo_<time> in the working dir)'),
    'namespace': ('', 'namespace of the stage'),
    'executor': ('events', 'events (EventsExecutor) | single (SingleThreadedExecutor)'),
    'end_with_plant': ('true', 'end the whole launch when the plant process exits'),
    'sim_time': ('true', 'lockstep: use_sim_time on the controller and trajectory nodes'),
    'direct': ('false', 'composed only: hand samples from node to node by call (intra-process)'),
    'autostart': ('true', 'configure and activate the plant (a managed node) at once; false: '
                  'leave it unconfigured for ros2 lifecycle set'),
}


def _unflatten(values: Mapping[str, Any]) -> dict[str, Any]:
    """Return ``{'a': {'b': v}}`` for ``{'a.b': v}``."""
    out: dict[str, Any] = {}
    for name, value in values.items():
        *groups, leaf = name.split('.')
        node = out
        for part in groups:
            node = node.setdefault(part, {})
        node[leaf] = value
    return out


class _Dumper(yaml.SafeDumper):
    """YAML that ROS reads back as written: rcl takes a bare y or n for a boolean."""


def _string(dumper: yaml.SafeDumper, text: str) -> yaml.ScalarNode:
    style = "'" if text in ('y', 'Y', 'n', 'N') else None
    return dumper.represent_scalar('tag:yaml.org,2002:str', text, style=style)


_Dumper.add_representer(str, _string)


def _parameter_file(config: Config, per_node: Mapping[str, Mapping[str, Any]]) -> str:
    """
    Write one parameter file with a section per node and return its path.

    The sections are keyed ``/**/<node>`` so that they apply in any namespace, and they hold
    the merged values of every file given plus this launch's own settings: one file serves the
    three processes or the composed one alike.
    """
    doc: dict[str, Any] = {}
    for node, extra in per_node.items():
        values = dict(config.node(node))
        values.update(extra)
        doc[f'/**/{node}'] = {'ros__parameters': _unflatten(values)}
    handle, path = tempfile.mkstemp(prefix='piezo_stage_', suffix='.yaml')
    with os.fdopen(handle, 'w', encoding='utf-8') as stream:
        yaml.dump(doc, stream, Dumper=_Dumper, default_flow_style=False, sort_keys=False)
    return path


def _launch(context: LaunchContext) -> list[Any]:
    arg = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
    files = [str(find_config(arg['config']))]
    files += [str(find_config(arg[k])) for k in ('scenario', 'overrides') if arg[k]]
    mode = arg['mode']
    if mode not in MODES:
        raise ValueError(f'launch argument mode:={mode!r}: allowed: '
                         + ', '.join(repr(m) for m in MODES))
    lockstep = mode == 'lockstep'
    config = load_config(files)
    axes = has_axes(config)
    sim_time = lockstep and arg['sim_time'].lower() == 'true'
    common = {'mode': mode, 'use_sim_time': sim_time}
    # the plant owns simulation time: its own clock need not follow /clock
    plant = dict(common, use_sim_time=False, duration_s=float(arg['duration_s']))
    if arg['record'].lower() == 'true':
        # lockstep waits for the recorder too, and gives it time to subscribe to every topic
        subscribers = LoopConfig.from_config(config).plant_node.lockstep.subscribers
        plant.update({'lockstep.subscribers': subscribers + 1, 'lockstep.settle_s': 1.0})
    controller = dict(common)
    if arg['controller']:
        controller['type'] = arg['controller']
    trajectory = dict(common)
    # validate every value the nodes will get, as every command does, before any process starts
    checked = LoopConfig.from_config(config.with_overrides('plant_node', plant)
                                     .with_overrides('controller_node', controller)
                                     .with_overrides('trajectory_node', trajectory))
    if axes:
        direct = arg['composed'].lower() == 'true' and arg['direct'].lower() == 'true'
        refused = refuse_axes_mode('launch', mode, checked.plant_node.backend, direct=direct)
        if refused is not None:
            raise ValueError(', '.join(files) + f': {refused}')
        axes_loop_config(config.with_overrides('plant_node', plant)
                         .with_overrides('controller_node', controller)
                         .with_overrides('trajectory_node', trajectory))
    params = _parameter_file(config, {'plant_node': plant, 'controller_node': controller,
                                      'trajectory_node': trajectory})
    ns = arg['namespace']
    extra = ['--executor', arg['executor']]
    # the plant's process (stage_servo or plant_node) makes the lifecycle transitions
    autostart = ['--autostart', 'true' if arg['autostart'].lower() == 'true' else 'false']
    actions: list[Any] = []
    if arg['composed'].lower() == 'true':
        if arg['direct'].lower() == 'true':
            extra.append('--direct')
        main = Node(package='piezo_stage_ros', executable='stage_servo', namespace=ns,
                    output='screen', arguments=extra + autostart, parameters=[params])
        actions.append(main)
    else:
        main = Node(package='piezo_stage_ros', executable='plant_node', name='plant_node',
                    namespace=ns, output='screen', arguments=extra + autostart,
                    parameters=[params])
        actions += [
            main,
            Node(package='piezo_stage_ros', executable='controller_node',
                 name='controller_node', namespace=ns, output='screen', arguments=extra,
                 parameters=[params]),
            Node(package='piezo_stage_ros', executable='trajectory_node',
                 name='trajectory_node', namespace=ns, output='screen', arguments=extra,
                 parameters=[params]),
        ]
    if arg['record'].lower() == 'true':
        prefix = '/' + ns.strip('/') + '/' if ns.strip('/') else '/'
        cmd = ['ros2', 'bag', 'record', '--storage', 'mcap']
        if arg['bag']:
            cmd += ['--output', arg['bag']]
        # no --use-sim-time: that recorder waits for a non-zero /clock, and lockstep time starts
        # at 0 (as offline); the header stamps carry the sample times, and the analysis aligns
        # by them (docs/reference/bags.md)
        qos_file = os.path.join(os.path.dirname(files[0]), 'record_qos.yaml')
        if os.path.isfile(qos_file):
            cmd += ['--qos-profile-overrides-path', qos_file]
        # direct real time puts every sample on stage/block (every axis in a row with several
        # axes): the recorder takes that (about 100 messages a second) and leaves the
        # per-sample topics to live subscribers
        blocks = (not lockstep and arg['composed'].lower() == 'true'
                  and arg['direct'].lower() == 'true' and checked.plant_node.recording.block)
        topics = BLOCK_RECORDED_TOPICS if blocks else RECORDED_TOPICS
        if axes and not blocks:
            # the model's true positions too, as the offline runner's multi-axis bag has them
            topics = (*topics, TRUE_POSITION)
        cmd += ['--topics'] + [prefix + t for t in topics]
        actions.append(ExecuteProcess(cmd=cmd, output='screen'))
    if arg['end_with_plant'].lower() == 'true':
        # the plant's run is complete (or failed): end the whole launch, the recorder included
        actions.append(RegisterEventHandler(OnProcessExit(
            target_action=main, on_exit=[EmitEvent(event=Shutdown(reason='plant finished'))])))
    return actions


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=doc)
         for name, (default, doc) in ARGUMENTS.items()]
        + [OpaqueFunction(function=_launch)])
