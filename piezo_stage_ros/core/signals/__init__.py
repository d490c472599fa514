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
Signals in time that need no stage: transition shapes and identification excitations.

They sit just above the contracts, below the model, because users on several floors draw them:
the feed-forward (control) shapes jumps with the S-curve, the trajectories (loop) use the S-curve,
the smoothstep and the excitations as reference kinds, and identification drives the stage with
the excitations. A signal depends on nothing but time and its parameters.
"""
