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
What the launch tests share: their skips, and closed_loop.launch.py with the probe counted.

Imported at the top of a launch test, it skips the whole module with the reason where ROS 2
Jazzy, launch_testing or the installed package is missing.
"""

from __future__ import annotations

from pathlib import Path
import tempfile
from typing import Any

import pytest

pytest.importorskip('rclpy', reason='rclpy (ROS 2 Jazzy) is not importable here')
pytest.importorskip('launch_testing', reason='launch_testing is not installed')
ament_index = pytest.importorskip('ament_index_python.packages',
                                  reason='ament_index_python is not installed')
try:
    SHARE = Path(ament_index.get_package_share_directory('piezo_stage_ros'))
except ament_index.PackageNotFoundError:
    pytest.skip('piezo_stage_ros is not installed in the ament index (colcon build it first)',
                allow_module_level=True)

from launch.launch_description_sources import PythonLaunchDescriptionSource  # noqa: E402
import launch_testing.actions  # noqa: E402

import launch  # noqa: E402

# the probe is a third subscriber to the positions: the plant waits for it before sample 0
OVERRIDES = """
plant_node:
  ros__parameters:
    lockstep:
      subscribers: 3
"""


def closed_loop(arguments: dict[str, str]) -> Any:
    """Return the launch of closed_loop.launch.py with these arguments, the probe counted."""
    overrides = Path(tempfile.mkdtemp(prefix='pz_launch_')) / 'overrides.yaml'
    overrides.write_text(OVERRIDES)
    included = launch.actions.IncludeLaunchDescription(
        PythonLaunchDescriptionSource(str(SHARE / 'launch' / 'closed_loop.launch.py')),
        launch_arguments={**arguments, 'overrides': str(overrides),
                          # the test, not the plant's end, ends this launch
                          'end_with_plant': 'false'}.items())
    return launch.LaunchDescription([included, launch_testing.actions.ReadyToTest()])
