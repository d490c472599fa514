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

"""The scripted clock of the real-time loop tests: time passes only when the test says so."""

from __future__ import annotations


class FakeClock:
    """A monotonic clock in ns that moves only when slept on, or by a scripted delay per read."""

    def __init__(self, start: int = 10**9, per_read: int = 0) -> None:
        self.now = start
        self.per_read = per_read
        self.sleeps: list[float] = []
        self.stalls: dict[int, int] = {}  # read number -> extra ns added at that read
        self.reads = 0

    def __call__(self) -> int:
        self.reads += 1
        self.now += self.per_read + self.stalls.pop(self.reads, 0)
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += int(seconds * 1e9)
