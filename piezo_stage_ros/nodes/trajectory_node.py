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
The trajectory node: x_d and x_d' for every position sample, from any trajectory of the core.

Parameters: :func:`piezo_stage_ros.nodes.tables.trajectory_table` (the trajectory of the core and
the node group). For each ``stage/position`` sample it publishes ``stage/reference`` with the
same stamp: x_d(t) and x_d'(t) at the trajectory's own time t (0 at the sample where it started).
Start and stop: the ``active`` parameter, or the services ``~/start`` and ``~/stop``
(``std_srvs/srv/Trigger``). Switch: set any trajectory parameter (``kind``, ``sine.frequency_hz``
...); the new trajectory is validated, refused with the reason if bad, and starts at its t = 0
at the next sample; ``stage/trajectory`` announces it with the stamp of that sample, for the
controller's feed-forward, which predicts from its own copy of the trajectory.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

from piezo_stage_ros.core.contracts import wire
from piezo_stage_ros.core.contracts.cdr import JointStateDecoder, JointStateEncoder
from piezo_stage_ros.core.loop.trajectories import make_trajectory
from piezo_stage_ros.nodes import qos
from piezo_stage_ros.nodes.logic import announce_trajectory, Gate, TrajectoryLogic
from piezo_stage_ros.nodes.parameters import ParameterBinding
from piezo_stage_ros.nodes.runner import decode_or_drop, run, stops_quietly
from piezo_stage_ros.nodes.tables import trajectory_table, TrajectoryNodeParams
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger

__all__ = ['TrajectoryNode', 'main']


class TrajectoryNode(Node):
    """
    The trajectory as a ROS node.

    Parameters
    ----------
    **kwargs
        Passed to :class:`rclpy.node.Node`.

    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('trajectory_node', **kwargs)
        self.binding = ParameterBinding(self, trajectory_table(), self._on_change)
        params, opts = self.binding.objects
        self.opts: TrajectoryNodeParams = opts
        # lockstep evaluates in the offline runner's chunks (same floats); real time in short
        # ones, so that no single sample pays for a long evaluation and comes late
        chunk_s = opts.chunk_s if opts.mode == 'lockstep' else min(opts.chunk_s, 0.005)
        self.logic = TrajectoryLogic(make_trajectory(params, sample_rate_hz=opts.sample_rate_hz),
                                     sample_rate_hz=opts.sample_rate_hz,
                                     chunk_s=chunk_s, active=opts.active)
        # CDR bytes in and out (core/contracts/cdr.py): rclpy message objects cost more than a
        # sample
        self._encoder = JointStateEncoder([wire.JOINT_NAME], with_velocity=True)
        self._decoder = JointStateDecoder([wire.JOINT_NAME])
        self.malformed = 0
        self._pub = self.create_publisher(JointState, wire.REFERENCE, qos.LOOP_OUT)
        self._announce_pub = self.create_publisher(String, wire.TRAJECTORY, qos.ANNOUNCE)
        self._params = params
        self._sub = self.create_subscription(JointState, wire.POSITION, self._on_position,
                                             qos.LOOP, raw=True)
        self._gate: Callable[[], bool] = lambda: True
        self._ahead = opts.lockstep_ahead if opts.mode == 'lockstep' else 0
        #: Where changes go besides ``logic``: a servo process that runs its own copy of it
        #: (``ServoProcess.change``; stage_servo --direct in real time).
        self.forward: Callable[[str, Any], None] | None = None
        self.create_service(Trigger, '~/start', self._start)
        self.create_service(Trigger, '~/stop', self._stop)
        self.get_logger().info(f'trajectory {params.kind}, '
                               f'{"active" if opts.active else "inactive"}')

    def _on_change(self, old: Sequence[Any], new: Sequence[Any]) -> None:
        params, opts = new
        if params is not old[0]:
            # builds (and so checks) the new trajectory before accepting the change
            self.logic.switch(make_trajectory(params, sample_rate_hz=self.opts.sample_rate_hz))
            self._params = params
            if self.forward is not None:
                self.forward('trajectory', params)
            self.get_logger().info(f'trajectory switched to {params.kind} at the next sample')
        if opts.active != self.opts.active:
            if opts.active:
                self.logic.start()
            else:
                self.logic.stop()
            if self.forward is not None:
                self.forward('active', opts.active)
        self.opts = opts

    def _set_active(self, active: bool, response: Trigger.Response) -> Trigger.Response:
        result = self.set_parameters([Parameter('active', value=active)])[0]
        response.success = result.successful
        response.message = ('started' if active else 'stopped') if result.successful \
            else result.reason
        return response

    def _start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        return self._set_active(True, response)

    def _stop(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        return self._set_active(False, response)

    def attach_direct(self) -> None:
        """
        Answer by call (:meth:`answer`) instead of from ``stage/position``.

        For ``stage_servo --direct``: the subscription goes, and the reference is published for
        outside subscribers (a recorder) only.
        """
        self.destroy_subscription(self._sub)
        self._gate = Gate(self._pub.get_subscription_count)

    def answer(self, stamp_ns: int) -> tuple[float, float]:
        """Return x_d [m] and x_d' [m/s] for the sample stamped ``stamp_ns`` [ns]."""
        ref, vel = self.logic.on_position(stamp_ns)
        self._announce()
        self.publish(stamp_ns, ref, vel)
        return ref, vel

    def _announce(self) -> None:
        """Announce a new trajectory once its t = 0 has a stamp (before its references)."""
        stamp = self.logic.take_switch()
        if stamp is not None:
            self._announce_pub.publish(String(data=announce_trajectory(stamp, self._params)))

    def publish(self, stamp_ns: int, reference_m: float, velocity_mps: float) -> None:
        """Publish a reference computed by call, while an outside subscriber listens."""
        if self._gate():
            sec, nanosec = wire.ns_to_stamp(stamp_ns)
            self._pub.publish(self._encoder.encode(sec, nanosec, (reference_m,),
                                                   (velocity_mps,)))

    @stops_quietly
    def _on_position(self, data: bytes) -> None:
        msg = decode_or_drop(self, wire.POSITION, self._decoder.decode, data)
        if msg is None:
            return
        sec, nanosec, _, _ = msg
        stamp = wire.stamp_to_ns(sec, nanosec)
        try:
            if self._ahead:
                # lockstep_ahead: x_d goes out ahead of its position (it does not depend on
                # it); the controller pairs by stamp, so this node leaves the critical path
                encode, publish = self._encoder.encode, self._pub.publish
                out = self.logic.ahead(stamp, self._ahead)
                self._announce()
                for k_stamp, ref, vel in out:
                    ksec, knsec = divmod(k_stamp, 1_000_000_000)
                    publish(encode(ksec, knsec, (ref,), (vel,)))
                return
            ref, vel = self.logic.on_position(stamp)
            self._announce()
            self._pub.publish(self._encoder.encode(sec, nanosec, (ref,), (vel,)))
        except Exception:
            if self.context.ok():
                raise  # Ctrl-C shuts the context down under a running callback: not an error


def main(args: Sequence[str] | None = None) -> int:
    """Run the trajectory node (console script ``trajectory_node``)."""
    return run('trajectory_node', [('trajectory', TrajectoryNode)], args,
               'The trajectory streamer of piezo_stage_ros.')

