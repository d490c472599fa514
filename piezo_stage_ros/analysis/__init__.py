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
Bag writing and reading (rosbags), reports and plots (matplotlib); no rclpy here.

- :mod:`~piezo_stage_ros.analysis.bagwrite`: runs written as rosbag2 bags (``simulate --bag``);
- :mod:`~piezo_stage_ros.analysis.bagread`: bags read in bulk into runs, time alignment;
- :mod:`~piezo_stage_ros.analysis.bagfast`: the bulk writer and the MCAP scanner, the only
  module that uses rosbags' internals;
- :mod:`~piezo_stage_ros.analysis.replay`: metrics of a bag (``analyze``), its summary;
- :mod:`~piezo_stage_ros.analysis.spectral`: frequency-response estimate of noise/sweep runs;
- :mod:`~piezo_stage_ros.analysis.plots`: the paper-style figures (imports matplotlib);
- :mod:`~piezo_stage_ros.analysis.report`: Markdown report and comparison of several bags.
"""
