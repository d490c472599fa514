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
Run the commissioning excitation on the nodes and record it; then ``commission --bag BAG``.

The loop of ``closed_loop.launch.py`` (plant, controller, trajectory; lockstep by default, or
realtime through the hardware bridge with a parameter file that sets ``plant_node backend``)
runs with three changes (:func:`piezo_stage_ros.core.identification.commission.ros_overrides`):
the controller node runs the conservative hold PI without notch, the trajectory node a table
of the commissioning reference (hold ``settle_s``, then the periodic multisine and slow sine,
at most 1 um from the hold, sampled at the loop rate), and a simulated plant starts at the
hold. The run is recorded into ``bag`` and ends after the excitation. The recorded run is
then commissioned offline::

    ros2 launch piezo_stage_ros commission.launch.py bag:=commission_bag
    commission --bag commission_bag --output stage.yaml

Arguments: ``config``, ``scenario`` (as ``closed_loop.launch.py``), ``mode``, ``bag``,
``hold_m``, ``duration_s`` (excitation length, at most 10 s), ``multisine_rms_m``,
``slow_amplitude_m``.
"""

# see closed_loop.launch.py for why the import order is marked
from __future__ import annotations  # noqa: I001

import os
import tempfile
from typing import Any

from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, IncludeLaunchDescription, OpaqueFunction
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration
from piezo_stage_ros.core.config.loader import find_config, load_config, LoopConfig
from piezo_stage_ros.commission import write_excitation
from piezo_stage_ros.core.identification.commission import CommissionParams

_D = CommissionParams()
ARGUMENTS = {
    'config': ('default.yaml', 'parameter file: a name in config/ or a path'),
    'scenario': ('', 'second parameter file applied on top of config (empty: none)'),
    'mode': ('lockstep', 'lockstep | realtime'),
    'bag': ('commission_bag', 'bag directory the run is recorded into'),
    'hold_m': (repr(_D.hold_m), 'position held [m]'),
    'duration_s': (repr(_D.duration_s), 'length of the excitation [s], at most 10'),
    'multisine_rms_m': (repr(_D.multisine_rms_m), 'rms of the multisine [m]'),
    'slow_amplitude_m': (repr(_D.slow_amplitude_m), 'amplitude of the slow sine [m]'),
}


def _launch(context: LaunchContext) -> list[Any]:
    arg = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
    files = [str(find_config(arg['config']))]
    if arg['scenario']:
        files.append(str(find_config(arg['scenario'])))
    rate = LoopConfig.from_config(load_config(files)).stage.sample_rate_hz
    # validated here, before any process starts (the table checks the excursion)
    params = CommissionParams(hold_m=float(arg['hold_m']), duration_s=float(arg['duration_s']),
                              multisine_rms_m=float(arg['multisine_rms_m']),
                              slow_amplitude_m=float(arg['slow_amplitude_m']))
    _, overrides, length = write_excitation(
        params, rate, tempfile.mkdtemp(prefix='piezo_commission_'))
    loop_launch = os.path.join(os.path.dirname(os.path.abspath(__file__)),
                               'closed_loop.launch.py')
    return [IncludeLaunchDescription(
        PythonLaunchDescriptionSource(loop_launch),
        launch_arguments={'config': files[0], 'scenario': arg['scenario'],
                          'overrides': str(overrides), 'mode': arg['mode'], 'record': 'true',
                          'bag': arg['bag'], 'duration_s': repr(length),
                          'end_with_plant': 'true'}.items())]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=doc)
         for name, (default, doc) in ARGUMENTS.items()]
        + [OpaqueFunction(function=_launch)])
