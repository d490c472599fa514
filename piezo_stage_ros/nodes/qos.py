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
The QoS profiles of every topic, chosen once here (imports rclpy).

- :data:`LOOP` (subscriptions to position, reference, command): reliable, volatile, keep last
  100. Reliable because in lockstep a lost message would stall the loop until the plant's
  resend; volatile because a late joiner has no use for old samples; 100 samples of backlog at
  most for a node that fell behind (it serves the newest, not a second of stale ones). In real
  time nothing ever waits for a message: the plant holds the last command it has.
- :data:`LOOP_OUT` (publishers of position, reference, command, diagnostics, applied): the same,
  keep last 10 000. A reliable keep-last writer drops the samples a reader has not acknowledged
  once more than its depth are newer: with 100, a recorder preempted for 10 ms on a loaded
  machine lost samples of a real-time run (measured: 9 000-22 000 of 597 000 per topic, each
  topic other ones). 10 000 is one second at 10 kHz, the depth ``config/record_qos.yaml`` gives
  the recorder; the writer keeps a sample only until every reader has acknowledged it.
- :data:`BLOCK` (``stage/block``, real time): reliable, volatile, keep last 1000: 10 s of blocks
  at 100 a second, for a recorder that stalls (a block is about 8 kB: 8 MB at most).
- :data:`CLOCK` (``/clock``, lockstep): reliable, keep last 1: only the newest time matters, and
  a reliable writer serves the best-effort subscription of every node's time source.
- :data:`STATUS` (``stage/status``): reliable, transient local, keep last 1, so that a tool
  started late still gets the plant's latest counters.
- :data:`ANNOUNCE` (``stage/trajectory``): reliable, transient local, keep last 10: a
  controller that starts late, or is busy through several switches, still binds each new
  trajectory at the stamp of its t = 0.
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

__all__ = ['ANNOUNCE', 'BLOCK', 'CLOCK', 'LOOP', 'LOOP_OUT', 'STATUS']

LOOP = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                  reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
LOOP_OUT = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10_000,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
BLOCK = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                   reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
CLOCK = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                   reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
STATUS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                    reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.TRANSIENT_LOCAL)
ANNOUNCE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)
