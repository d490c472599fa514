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
Topic names, message layout and units of the nodes, in one place (rclpy-free).

Names are relative, so a launch file puts several stages in namespaces; under the root
namespace they resolve to ``/stage/position`` ..., the default namespace of
:mod:`piezo_stage_ros.analysis.bagio` (a test checks that both agree).

- ``stage/position``, ``sensor_msgs/msg/JointState``: stamp t_k, name ['stage'], position [y_k] m;
- ``stage/reference``, ``sensor_msgs/msg/JointState``: stamp t_k, position [x_d] m,
  velocity [x_d'] m/s;
- ``stage/command``, ``std_msgs/msg/Float64``: amplifier input u_k [V], held over the sample;
- ``stage/diagnostics``, ``sensor_msgs/msg/JointState``: stamp t_k, name [keys],
  position [values] (controller internals);
- ``stage/status``, ``diagnostic_msgs/msg/DiagnosticStatus``: plant counters, about once a second;
- ``/clock``, ``rosgraph_msgs/msg/Clock``: t_k, lockstep only (absolute: one clock per graph).
"""

from __future__ import annotations

from typing import Final

__all__ = ['CLOCK', 'COMMAND', 'DIAGNOSTICS', 'JOINT_NAME', 'POSITION', 'REFERENCE', 'STATUS',
           'TOPIC_TYPES']

POSITION: Final = 'stage/position'
REFERENCE: Final = 'stage/reference'
COMMAND: Final = 'stage/command'
DIAGNOSTICS: Final = 'stage/diagnostics'
#: Plant counters (late samples, resends, watchdog trips, bridge losses), about once a second.
STATUS: Final = 'stage/status'
CLOCK: Final = '/clock'
JOINT_NAME: Final = 'stage'

TOPIC_TYPES: Final = {
    POSITION: 'sensor_msgs/msg/JointState',
    REFERENCE: 'sensor_msgs/msg/JointState',
    COMMAND: 'std_msgs/msg/Float64',
    DIAGNOSTICS: 'sensor_msgs/msg/JointState',
    STATUS: 'diagnostic_msgs/msg/DiagnosticStatus',
    CLOCK: 'rosgraph_msgs/msg/Clock',
}
