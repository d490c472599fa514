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
at the next sample; ``stage/trajectory`` announces it (and the t = 0 of each start) with the
stamp of that sample, for the controller's feed-forward, which predicts from its own copy of
the trajectory.

Goals: the action ``stage/follow_joint_trajectory`` (``control_msgs/action/FollowJointTrajectory``)
and the topic ``stage/joint_trajectory`` (``trajectory_msgs/msg/JointTrajectory``; an empty one
holds), joint ``stage``. A goal takes x_d over from whatever plays, without a jump, checked
against what the stage can reach and follow (the plant node's stage, read from the same
parameter files); :class:`~piezo_stage_ros.core.loop.follow.GoalFollower` checks and follows
it, in this node's logic or, in real time with ``stage_servo --direct``, in the servo.
Every goal is accepted by the action server and checked at the sample it would start from: a
refusal ends it at once ABORTED with its ``error_code`` (``INVALID_GOAL``, ``INVALID_JOINTS``
...) and the reason in ``error_string`` (a rejected goal carries neither). Goals run only
while the plant node is active (:meth:`TrajectoryNode.plant_state`): refused at once otherwise,
ended when it leaves active.
"""

from __future__ import annotations

import sys
from typing import Any, Callable, Sequence

from piezo_stage_ros.core.config.loader import load_loop_config
from piezo_stage_ros.core.contracts import wire
from piezo_stage_ros.core.contracts.cdr import JointStateDecoder, JointStateEncoder
from piezo_stage_ros.core.contracts.errors import PiezoStageError
from piezo_stage_ros.core.contracts.interfaces import Trajectory
from piezo_stage_ros.core.loop.follow import FollowParams, GoalFollower, GoalTrajectory
from piezo_stage_ros.core.loop.goals import AxisLimits
from piezo_stage_ros.core.loop.trajectories import make_trajectory
from piezo_stage_ros.core.model.stage import StageParams
from piezo_stage_ros.nodes import qos
from piezo_stage_ros.nodes.goal_server import GoalServer
from piezo_stage_ros.nodes.logic import (
    announce_goal,
    announce_trajectory,
    Gate,
    TrajectoryLogic,
)
from piezo_stage_ros.nodes.parameters import ParameterBinding
from piezo_stage_ros.nodes.runner import decode_or_drop, run, stops_quietly
from piezo_stage_ros.nodes.tables import trajectory_table, TrajectoryNodeParams
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger

__all__ = ['TrajectoryNode', 'goal_lead_s', 'main', 'stage_of_args']


def goal_lead_s(mode: str) -> float:
    """
    Return how far ahead of its start a goal is checked [s]: 0 in lockstep, 20 ms in real time.

    In real time the check (every sample of the trajectory against the limits) and the spline
    run outside the loop's sample, for a sample this far ahead, which alone starts it.
    """
    return 0.0 if mode == 'lockstep' else 0.02


def stage_of_args(args: Sequence[str]) -> StageParams | None:
    """Return the stage of the ``--params-file`` files in ``args``, or None if none reads."""
    files = [args[i + 1] for i, a in enumerate(args[:-1]) if a == '--params-file']
    if not files:
        return None
    try:
        return load_loop_config(files).stage
    except (PiezoStageError, OSError):
        return None


class TrajectoryNode(GoalServer):
    """
    The trajectory as a ROS node.

    Parameters
    ----------
    **kwargs
        Passed to :class:`rclpy.node.Node`.

    """

    logic: TrajectoryLogic

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
        # a goal's reference, as it changes, to a controller in another process (the direct
        # composition binds it by call instead)
        self.logic.on_reference_change = self._announce_goal
        self._params = params
        self._sub = self.create_subscription(JointState, wire.POSITION, self._on_position,
                                             qos.LOOP, raw=True)
        self._gate: Callable[[], bool] = lambda: True
        self._ahead = opts.lockstep_ahead if opts.mode == 'lockstep' else 0
        self.create_service(Trigger, '~/start', self._start)
        self.create_service(Trigger, '~/stop', self._stop)
        self._init_goal_server((wire.JOINT_NAME,))
        stage = stage_of_args(sys.argv)
        if stage is None:
            self.get_logger().warning('goals: no stage in the parameter files given; checking '
                                      'them against the default stage')
        self.set_stage(stage if stage is not None else StageParams())
        self._make_goal_interfaces()
        self.get_logger().info(f'trajectory {params.kind}, '
                               f'{"active" if opts.active else "inactive"}')

    def set_stage(self, stage: StageParams) -> None:
        """Check goals against ``stage`` (what it can reach and follow)."""
        self.stage = stage
        follower = GoalFollower((wire.JOINT_NAME,), [AxisLimits.from_stage(stage)],
                                [self.logic.hold_m],
                                FollowParams(sample_time_s=1.0 / self.opts.sample_rate_hz))
        self.logic.attach_goals(follower, goal_lead_s(self.opts.mode))

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

    def answer(self, stamp_ns: int, position_m: float = float('nan')) -> tuple[float, float]:
        """Return x_d [m] and x_d' [m/s] for the sample stamped ``stamp_ns`` [ns] (y_k)."""
        ref, vel = self.logic.on_position(stamp_ns, position_m)
        self._announce()
        self.publish(stamp_ns, ref, vel)
        if self.logic.events:
            self._drain()
        return ref, vel

    def _announce_goal(self, view: Trajectory, origin_ns: int) -> None:
        """Announce a goal's reference before the reference of the sample it changes at."""
        if isinstance(view, GoalTrajectory):  # the spline as it stands now
            self._announce_pub.publish(String(data=announce_goal(origin_ns, view.snapshot())))

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
        sec, nanosec, position, _ = msg
        stamp = wire.stamp_to_ns(sec, nanosec)
        try:
            if self._ahead:
                # lockstep_ahead: x_d goes out ahead of its position (it does not depend on
                # it); the controller pairs by stamp, so this node leaves the critical path
                encode, publish = self._encoder.encode, self._pub.publish
                self.logic.observe(stamp, position)
                out = self.logic.ahead(stamp, self._ahead)
                self._announce()
                for k_stamp, ref, vel in out:
                    ksec, knsec = divmod(k_stamp, 1_000_000_000)
                    publish(encode(ksec, knsec, (ref,), (vel,)))
                return
            ref, vel = self.logic.on_position(stamp, position)
            self._announce()
            self._pub.publish(self._encoder.encode(sec, nanosec, (ref,), (vel,)))
            if self.logic.events:
                self._drain()
        except Exception:
            if self.context.ok():
                raise  # Ctrl-C shuts the context down under a running callback: not an error


def main(args: Sequence[str] | None = None) -> int:
    """Run the trajectory node (console script ``trajectory_node``)."""
    return run('trajectory_node', [('trajectory', TrajectoryNode)], args,
               'The trajectory streamer of piezo_stage_ros.')

