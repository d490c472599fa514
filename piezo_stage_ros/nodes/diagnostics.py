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
Publishing statuses on ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``, imports rclpy).

The content comes from :mod:`piezo_stage_ros.nodes.health` (no rclpy): each node adds its
sources, callables returning :class:`~piezo_stage_ros.nodes.health.Status` lists, and this
publishes them all in one array at the period given (about 1 Hz), as diagnostic_updater does:
topic ``/diagnostics`` (absolute: diagnostic_aggregator listens there whatever the node's
namespace), reliable, depth 10.
"""

from __future__ import annotations

from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from piezo_stage_ros.nodes.health import Status, StatusSource
from rclpy.clock import Clock, ClockType
from rclpy.qos import QoSProfile, ReliabilityPolicy

__all__ = ['DIAGNOSTICS_PERIOD_S', 'DIAGNOSTICS_TOPIC', 'DiagnosticsPublisher', 'to_message']

#: The topic diagnostic_aggregator reads.
DIAGNOSTICS_TOPIC = '/diagnostics'

#: Period of the reports [s] (diagnostic_updater's default rate).
DIAGNOSTICS_PERIOD_S = 1.0


def to_message(status: Status) -> DiagnosticStatus:
    """Return ``status`` as a ``diagnostic_msgs/DiagnosticStatus``."""
    return DiagnosticStatus(level=bytes([status.level]), name=status.name,
                            message=status.message, hardware_id=status.hardware_id,
                            values=[KeyValue(key=k, value=v) for k, v in status.values])


class DiagnosticsPublisher:
    """
    One ``/diagnostics`` publisher and timer for a node, fed by any number of sources.

    Parameters
    ----------
    node : rclpy.node.Node
        The node that publishes.
    period_s : float
        Report period [s] on the steady clock (lockstep simulation time may stand still).

    Attributes
    ----------
    sources : list of callable
        Each called once a report, returning a sequence of statuses; add more with
        :meth:`add` (a goal server's status, say). A source that raises is reported as an
        ERROR status in its place, and the others still go out.

    """

    def __init__(self, node: Any, period_s: float = 1.0) -> None:
        self.node = node
        self.sources: list[StatusSource] = []
        self.published = 0
        self._pub = node.create_publisher(
            DiagnosticArray, DIAGNOSTICS_TOPIC,
            QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        self._timer = node.create_timer(period_s, self.publish,
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))

    def add(self, source: StatusSource) -> None:
        """Add a source of statuses to every report from now on."""
        self.sources.append(source)

    def collect(self) -> list[Status]:
        """Return the statuses of every source now."""
        out: list[Status] = []
        for source in self.sources:
            try:
                out.extend(source())
            except Exception as exc:  # noqa: BLE001 -- one bad source must not hide the rest
                name = getattr(source, '__qualname__', repr(source))
                out.append(Status(2, f'{self.node.get_name()}: {name}',
                                  f'status not computed: {exc!r}'))
        return out

    def publish(self) -> None:
        """Publish one array of every source's statuses, stamped with the node's clock."""
        msg = DiagnosticArray()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.status = [to_message(s) for s in self.collect()]
        self._pub.publish(msg)
        self.published += 1

    def destroy(self) -> None:
        """Stop the timer and destroy the publisher."""
        self.node.destroy_timer(self._timer)
        self.node.destroy_publisher(self._pub)
