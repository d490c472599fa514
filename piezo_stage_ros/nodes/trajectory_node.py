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
from piezo_stage_ros.core.loop.follow import (
    FollowParams,
    GoalFollower,
    GoalLedger,
    GoalResult,
    GoalsStatus,
    GoalStatus,
    GoalTrajectory,
)
from piezo_stage_ros.core.loop.goals import (
    AxisLimits,
    GoalVerdict,
    JointTrajectoryGoal,
    ResultCode,
)
from piezo_stage_ros.core.loop.trajectories import make_trajectory
from piezo_stage_ros.core.model.stage import StageParams
from piezo_stage_ros.nodes import goals_msgs, qos
from piezo_stage_ros.nodes.diagnostics import DIAGNOSTICS_PERIOD_S, DiagnosticsPublisher
from piezo_stage_ros.nodes.health import GoalGate, goals_of, hardware_id
from piezo_stage_ros.nodes.logic import (
    announce_goal,
    announce_trajectory,
    Gate,
    TrajectoryLogic,
)
from piezo_stage_ros.nodes.parameters import ParameterBinding
from piezo_stage_ros.nodes.runner import decode_or_drop, run, stops_quietly
from piezo_stage_ros.nodes.tables import trajectory_table, TrajectoryNodeParams
import rclpy.callback_groups
from rclpy.node import Node
from rclpy.parameter import Parameter
import rclpy.task
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger

__all__ = ['TrajectoryNode', 'goal_lead_s', 'main', 'stage_of_args']

#: Action and topic names, relative to the namespace.
FOLLOW_ACTION = f'{wire.STAGE}/follow_joint_trajectory'
JOINT_TRAJECTORY = f'{wire.STAGE}/joint_trajectory'
#: The managed plant node whose state the goals follow (in this node's namespace).
PLANT_NODE = 'plant_node'


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
        # a goal's reference, as it changes, to a controller in another process (the direct
        # composition binds it by call instead)
        self.logic.on_reference_change = self._announce_goal
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
        self._tokens = 0
        # token -> (goal handle or None for a topic message, future of the end, what it was)
        self._waiting: dict[int, tuple[Any, Any, tuple[Any, ...]]] = {}
        self._by_goal: dict[int, int] = {}
        self._token_of: dict[bytes, int] = {}
        #: The goals' bookkeeping for the stage's status (:meth:`goals_status`).
        self.ledger = GoalLedger()
        #: Whether goals may run: the plant node's lifecycle state (:meth:`plant_state`).
        self.gate = GoalGate()
        self._state_sub: Any = None
        self._state_client: Any = None
        self._state_timer: Any = None
        #: Goal events from a servo that runs this logic elsewhere (``ServoProcess``).
        self.goal_events: Callable[[], list[tuple[Any, ...]]] | None = None
        #: The last sample index of that servo (the goals' loop time there).
        self.loop_index: Callable[[], int] | None = None
        stage = stage_of_args(sys.argv)
        if stage is None:
            self.get_logger().warning('goals: no stage in the parameter files given; checking '
                                      'them against the default stage')
        self.set_stage(stage if stage is not None else StageParams())
        self._make_goal_interfaces()
        # /diagnostics: the goals (phase, active goal, last result, refusals)
        self.diagnostics = DiagnosticsPublisher(self, DIAGNOSTICS_PERIOD_S)
        self.diagnostics.add(lambda: [goals_of(self.get_name(),
                                               hardware_id(self.get_namespace()),
                                               self.goals_status())])
        self.get_logger().info(f'trajectory {params.kind}, '
                               f'{"active" if opts.active else "inactive"}')

    def set_stage(self, stage: StageParams) -> None:
        """Check goals against ``stage`` (what it can reach and follow)."""
        self.stage = stage
        follower = GoalFollower((wire.JOINT_NAME,), [AxisLimits.from_stage(stage)],
                                [self.logic.hold_m],
                                FollowParams(sample_time_s=1.0 / self.opts.sample_rate_hz))
        self.logic.attach_goals(follower, goal_lead_s(self.opts.mode))

    def _make_goal_interfaces(self) -> None:
        try:
            FollowJointTrajectory = goals_msgs.follow_joint_trajectory()
            JointTrajectory = goals_msgs.joint_trajectory()
            from rclpy.action import ActionServer, CancelResponse, GoalResponse
        except ImportError as exc:
            self.get_logger().warning(f'goals: no {exc.name}: no action, no joint_trajectory')
            return
        group = rclpy.callback_groups.ReentrantCallbackGroup()
        # every goal is accepted: the check needs the reference at the sample it starts from
        # (the servo's, in real time), and only a result carries its code and reason
        self._action = ActionServer(
            self, FollowJointTrajectory, FOLLOW_ACTION, self._execute,
            goal_callback=lambda _: GoalResponse.ACCEPT,
            cancel_callback=self._cancel, callback_group=group)
        self._accept_cancel = CancelResponse.ACCEPT
        # reliable, volatile, depth 10: any publisher's QoS meets it (joint_trajectory_controller
        # takes the system default)
        self._traj_sub = self.create_subscription(JointTrajectory, JOINT_TRAJECTORY,
                                                  self._on_trajectory, 10)
        # goals' events reach this side between samples: at 100 Hz (feedback comes at 50 Hz of
        # loop time); in lockstep after each sample as well
        self._drain_timer = self.create_timer(0.01, self._drain, callback_group=group)
        self._follow_plant_topics(group)

    def _follow_plant_topics(self, group: Any) -> None:
        # the plant node in another process: its transition events, and its state once at the
        # start (the events are volatile: a transition before this node was found is not
        # heard); a plant in this process tells its state by call instead (follow_plant)
        try:
            TransitionEvent, GetState = goals_msgs.plant_state_types()
        except ImportError as exc:
            self.get_logger().warning(f'goals: no {exc.name}: goals do not follow the plant '
                                      "node's lifecycle")
            return
        self._state_sub = self.create_subscription(
            TransitionEvent, f'{PLANT_NODE}/transition_event',
            lambda msg: self.plant_state(str(msg.goal_state.label)), 10,
            callback_group=group)
        self._state_client = self.create_client(GetState, f'{PLANT_NODE}/get_state',
                                                callback_group=group)
        self._state_timer = self.create_timer(0.5, self._ask_plant_state, callback_group=group)

    def _ask_plant_state(self) -> None:
        # until a state is known: ask the plant once its service is there
        client = self._state_client
        if self.gate.state is not None or client is None:
            self._state_timer.cancel()
            return
        if client.service_is_ready():
            self._state_timer.cancel()
            future = client.call_async(client.srv_type.Request())

            def answered(done: Any) -> None:
                response = done.result()
                if response is not None and self.gate.state is None:
                    self.plant_state(str(response.current_state.label))
            future.add_done_callback(answered)

    def _stop_asking(self) -> None:
        if self._state_timer is not None:
            self.destroy_timer(self._state_timer)
            self._state_timer = None

    def follow_plant(self, state: str, listeners: list[Callable[[str], None]]) -> None:
        """
        Follow a plant node in this process: its ``state`` now, then each one by call.

        ``listeners``: the plant's :attr:`PlantNode.on_state`. Its transition events are not
        listened to then: one source, in the order of the transitions.
        """
        if self._state_sub is not None:
            self.destroy_subscription(self._state_sub)
            self._state_sub = None
        self._stop_asking()
        if self._state_client is not None:
            self.destroy_client(self._state_client)
            self._state_client = None
        listeners.append(self.plant_state)
        self.plant_state(state)

    def plant_state(self, state: str) -> None:
        """
        Take the plant node's lifecycle state: goals run only while it is active.

        Leaving it ends every goal not yet ended, ABORTED (``INVALID_GOAL``, as
        joint_trajectory_controller's deactivate) with the reason; the stage is then the
        plant's: it ramps to the safe voltage at the watchdog's slew. Called on this node's
        executor (the plant's transition in this process, or its event).
        """
        reason = self.gate.update(state)
        if reason is None:
            return
        # the action goals not yet ended (a topic's goal has no result to end)
        tokens = [token for token, entry in self._waiting.items() if entry[1] is not None]
        if self.forward is None:
            # the loop that follows them may still run (a servo thread's ramp): to rest
            for token in tokens:
                self.logic.cancel(token)
            if self.logic.goal_active:
                self.logic.hold()
        if tokens:
            self.get_logger().warning(f'{len(tokens)} goal(s) aborted: {reason}')
        goal_ids = {token: goal_id for goal_id, token in self._by_goal.items()}
        for token in tokens:
            self._by_goal.pop(goal_ids.get(token, 0), None)
            result = GoalResult(goal_ids.get(token, 0), GoalStatus.ABORTED,
                                ResultCode.INVALID_GOAL, reason, 0.0)
            self.ledger.take(('result', result))
            self._end(token, result)

    def _submit(self, token: int, goal: JointTrajectoryGoal, tracked: bool,
                stamp: int | None) -> None:
        if self.forward is not None:
            self.forward('goal', (token, goal, tracked, stamp))
        else:
            self.logic.goal(token, goal, tracked=tracked, stamp_ns=stamp)

    def _on_trajectory(self, msg: Any) -> None:
        refusal = self.gate.refusal()
        if refusal is not None:
            self.get_logger().warning(f'joint_trajectory ignored: {refusal}')
            return
        if not msg.points:
            # an empty trajectory holds (joint_trajectory_controller)
            if self.forward is not None:
                self.forward('hold', None)
            else:
                self.logic.hold()
            return
        self._tokens += 1
        goal = goals_msgs.trajectory_from_msg(msg)
        stamp = goals_msgs.stamp_ns(msg.header)
        self._waiting[self._tokens] = (None, None, (goal, False, stamp))
        self._submit(self._tokens, goal, False, stamp)

    async def _execute(self, handle: Any) -> Any:
        goal, verdict = goals_msgs.goal_from_msg(handle.request)
        if goal is None:
            self.get_logger().warning(f'goal refused: {verdict.reason}')
            handle.abort()
            return goals_msgs.result_msg(verdict.code, verdict.reason)
        refusal = self.gate.refusal()
        if refusal is not None:
            self.get_logger().warning(f'goal refused: {refusal}')
            self.ledger.take(('verdict', 0, None, 0))
            handle.abort()
            return goals_msgs.result_msg(ResultCode.INVALID_GOAL, refusal)
        self._tokens += 1
        token = self._tokens
        future = rclpy.task.Future()
        stamp = goals_msgs.stamp_ns(handle.request.trajectory.header)
        self._waiting[token] = (handle, future, (goal, True, stamp))
        self._token_of[bytes(handle.goal_id.uuid)] = token
        self._submit(token, goal, True, stamp)
        try:
            end = await future
        finally:
            self._token_of.pop(bytes(handle.goal_id.uuid), None)
        if isinstance(end, GoalVerdict):
            self.get_logger().warning(f'goal refused ({end.code.name}): {end.reason}')
            handle.abort()
            return goals_msgs.result_msg(end.code, end.reason)
        assert isinstance(end, GoalResult)
        if end.status == GoalStatus.SUCCEEDED:
            handle.succeed()
        elif end.status == GoalStatus.CANCELED and handle.is_cancel_requested:
            handle.canceled()
        else:
            # ABORTED, or preempted by a new goal (FollowJointTrajectory's INVALID_GOAL with
            # joint_trajectory_controller's text): an executing goal can only abort
            handle.abort()
        return goals_msgs.result_of(end)

    def goals_status(self) -> GoalsStatus:
        """Return the goals' status (level, message, key-values) for ``/diagnostics``."""
        index = self.loop_index() if self.loop_index is not None else self.logic._index
        now_s = max(index, 0) * self.logic.period_s
        phase = self.logic.follower.phase if self.forward is None and \
            self.logic.follower is not None and self.logic.goal_active else None
        return self.ledger.status(now_s, phase)

    def _cancel(self, handle: Any) -> Any:
        """Cancel a goal: the reference decelerates to a hold, then the goal ends CANCELED."""
        token = self._token_of.get(bytes(handle.goal_id.uuid))
        if token is not None:
            if self.forward is not None:
                self.forward('cancel', token)
            else:
                self.logic.cancel(token)
        return self._accept_cancel

    def _drain(self) -> None:
        """Hand the goals' verdicts, results and feedback to their clients."""
        events = self.logic.events
        more = self.goal_events() if self.goal_events is not None else []
        while events or more:
            event = events.popleft() if events else more.pop(0)
            kind = event[0]
            self.ledger.take(event)
            if kind == 'feedback':
                fb = event[1]
                entry = self._waiting.get(self._by_goal.get(fb.goal_id, 0))
                if entry is not None and entry[0] is not None:
                    entry[0].publish_feedback(goals_msgs.feedback_msg(
                        fb, (wire.JOINT_NAME,), self.logic.stamp_of(fb.time_s)))
            elif kind == 'verdict':
                _, token, verdict, goal_id = event
                entry = self._waiting.get(token)
                if goal_id and entry is not None and entry[1] is None:
                    # a topic message runs with no result to wait for: nothing more to keep
                    self._waiting.pop(token, None)
                elif goal_id:
                    self._by_goal[goal_id] = token
                else:
                    self._end(token, verdict)
            elif kind == 'result':
                token = self._by_goal.pop(event[1].goal_id, 0)
                self._end(token, event[1])
            elif kind == 'retry':
                # the reference changed while the goal was checked: check it again
                _, token, goal, tracked, stamp = event
                self._submit(token, goal, tracked, stamp)
            elif kind == 'cancelled':
                self._end(event[1], GoalResult(0, GoalStatus.CANCELED, ResultCode.SUCCESSFUL,
                                               'cancelled before it started', 0.0))

    def _end(self, token: int, end: GoalVerdict | GoalResult) -> None:
        entry = self._waiting.pop(token, None)
        if entry is None:
            return
        if entry[1] is not None:
            entry[1].set_result(end)
        elif isinstance(end, GoalVerdict):
            self.get_logger().warning(f'joint_trajectory refused ({end.code.name}): '
                                      f'{end.reason}')

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

