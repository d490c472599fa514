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
Hardware side of the plant node: the bridge interface, its backends and a target emulator.

Nothing here imports rclpy; the plant node owns one :class:`~.safety.GuardedPlant` built on one
:class:`~.bridge.Bridge` backend (the core model, or the UDP protocol of :mod:`.udp` to an external
real-time I/O target). :mod:`.emulator` is such a target on loopback, simulating the stage with
the core model, for tests and demonstrations.
"""
