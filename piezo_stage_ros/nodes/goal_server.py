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
The goal interfaces of a trajectory node, of one axis or several (rclpy).

:class:`GoalServer` serves ``stage/follow_joint_trajectory``
(``control_msgs/action/FollowJointTrajectory``) and ``stage/joint_trajectory``
(``trajectory_msgs/msg/JointTrajectory``; an empty one holds) and hands their goals to the
node's goal logic (:class:`~piezo_stage_ros.nodes.logic.GoalDesk`), which checks and follows
them; verdicts, results and feedback go back to the clients, the goals' status to
``/diagnostics``. Every goal is accepted by the action server and checked at the sample it
would start from: a refusal ends it at once ABORTED with its ``error_code`` and the reason in
``error_string`` (a rejected goal carries neither). The one-axis
(:class:`~piezo_stage_ros.nodes.trajectory_node.TrajectoryNode`) and the multi-axis trajectory
node (:class:`~piezo_stage_ros.nodes.axes_nodes.AxesTrajectoryNode`) are both one.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

from piezo_stage_ros.core.contracts import wire
from piezo_stage_ros.core.loop.follow import GoalLedger, GoalResult, GoalsStatus, GoalStatus
from piezo_stage_ros.core.loop.goals import GoalVerdict, JointTrajectoryGoal, ResultCode
from piezo_stage_ros.nodes import goals_msgs
from piezo_stage_ros.nodes.diagnostics import DIAGNOSTICS_PERIOD_S, DiagnosticsPublisher
from piezo_stage_ros.nodes.health import GoalGate, goals_of, hardware_id
from piezo_stage_ros.nodes.logic import GoalDesk
import rclpy.callback_groups
from rclpy.node import Node
import rclpy.task

__all__ = ['FOLLOW_ACTION', 'GoalServer', 'JOINT_TRAJECTORY', 'PLANT_NODE']

#: Action and topic names, relative to the namespace.
FOLLOW_ACTION = f'{wire.STAGE}/follow_joint_trajectory'
JOINT_TRAJECTORY = f'{wire.STAGE}/joint_trajectory'
#: The managed plant node whose state the goals follow (in this node's namespace).
PLANT_NODE = 'plant_node'


class GoalServer(Node):
    """
    The goal interfaces of a trajectory node, of one axis or several (a base of both nodes).

    ``stage/follow_joint_trajectory`` and ``stage/joint_trajectory`` handed to the node's
    ``logic`` (a :class:`~piezo_stage_ros.nodes.logic.GoalDesk`), or to a servo that runs a
    copy of it (:attr:`forward`); verdicts, results and feedback handed back to the clients
    (:meth:`_drain`); the goals' status on ``/diagnostics``. The node calls
    :meth:`_init_goal_server` before it makes its goal follower, then
    :meth:`_make_goal_interfaces`.
    """

    logic: GoalDesk
    #: Why goals are refused whatever they ask (a composition that does not follow them).
    goals_refused: str | None = None

    def _init_goal_server(self, joints: Sequence[str]) -> None:
        #: The joints in feedback, in the stage's order.
        self.goal_joints = tuple(joints)
        #: Where changes go besides ``logic``: a servo process that runs its own copy of it
        #: (``ServoProcess.change``; stage_servo --direct in real time).
        self.forward: Callable[[str, Any], None] | None = None
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

    def _make_goal_interfaces(self, follow_plant: bool = True) -> None:
        """
        Serve the action and the topic; ``follow_plant``: take goals as a managed plant allows.

        Also ``/diagnostics`` with the goals' status (phase, active goal, last result,
        refusals).
        """
        self.diagnostics = DiagnosticsPublisher(self, DIAGNOSTICS_PERIOD_S)
        self.diagnostics.add(lambda: [goals_of(self.get_name(),
                                               hardware_id(self.get_namespace()),
                                               self.goals_status())])
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
        if follow_plant:
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
        refusal = self.goals_refused or self.gate.refusal()
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
        refusal = self.goals_refused or self.gate.refusal()
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
                        fb, self.goal_joints, self.logic.stamp_of(fb.time_s)))
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
