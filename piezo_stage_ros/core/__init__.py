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
ROS-free core: models, hysteresis, signal chain, controllers, trajectories, metrics, the wire.

Grouped by job, one folder each, stacked: a folder imports only the folders below it (a test
enforces this), from the bottom:

- ``contracts``: parameters, types, interfaces, the wire and its CDR codec, errors;
- ``signals``: signals in time that need no stage (the S-curve, the identification excitations);
- ``model``: linear dynamics, hysteresis, the stage with its signal chain, a family of stages;
- ``control``: the RAC, PI and open loop, the feed-forward, the stability check;
- ``loop``: trajectories, the scalar and batched closed loops, the paper's experiments, the run
  record and its metrics, the robustness study;
- ``identification``: the paper's procedure (``fit``), what closed-loop and operation data
  support, drift, commissioning;
- ``config``: the loader, from parameter files to the validated objects of every floor below.

Imports numpy and scipy only (PyYAML in :mod:`piezo_stage_ros.core.config.loader`); never
rclpy, rosbags or matplotlib. A test enforces this. The wire contract (topics, stamps,
diagnostics layout: :mod:`~piezo_stage_ros.core.contracts.wire`) and the CDR codec
(:mod:`~piezo_stage_ros.core.contracts.cdr`) live here because both the nodes and the bag tools
need them without rclpy or rosbags.
"""
