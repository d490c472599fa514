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
Benchmarks (not tests): they time things and print numbers, they assert nothing.

- :mod:`piezo_stage_ros.bench.sim`: closed-loop simulation speed, batch stage throughput,
  controller step latency;
- :mod:`piezo_stage_ros.bench.bags`: bag writing, reading and analysis throughput;
- :mod:`piezo_stage_ros.bench.mcap_library`: Foxglove's ``mcap`` through its public API, for
  comparison (needs ``pip install mcap``, not a dependency).

The ``benchmark`` command runs them (``benchmark --suite sim|bags|all``).
"""
