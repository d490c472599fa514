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
FollowJointTrajectory and JointTrajectory messages to the goals of the core, and back.

Thin on purpose: everything is checked and followed by
:class:`~piezo_stage_ros.core.loop.follow.GoalFollower`; here fields are copied (durations to
seconds, empty velocity and acceleration lists to none). The readers take any object with the
messages' fields; the writers build ``control_msgs`` messages, imported when called.
"""

from __future__ import annotations

import importlib
from typing import Any

from piezo_stage_ros.core.contracts import wire
from piezo_stage_ros.core.loop.follow import Feedback, GoalResult
from piezo_stage_ros.core.loop.goals import (
    GoalVerdict,
    JointTolerance,
    JointTrajectoryGoal,
    ResultCode,
    TrajectoryPoint,
)

__all__ = ['feedback_msg', 'follow_joint_trajectory', 'goal_from_msg', 'joint_trajectory',
           'plant_state_types', 'result_msg', 'result_of', 'seconds', 'stamp_ns',
           'trajectory_from_msg']


def follow_joint_trajectory() -> Any:
    """Return ``control_msgs.action.FollowJointTrajectory`` (ImportError without it)."""
    return importlib.import_module('control_msgs.action').FollowJointTrajectory


def joint_trajectory() -> Any:
    """Return ``trajectory_msgs.msg.JointTrajectory`` (ImportError without it)."""
    return importlib.import_module('trajectory_msgs.msg').JointTrajectory


def plant_state_types() -> tuple[Any, Any]:
    """Return ``lifecycle_msgs``' TransitionEvent and GetState (ImportError without them)."""
    return (importlib.import_module('lifecycle_msgs.msg').TransitionEvent,
            importlib.import_module('lifecycle_msgs.srv').GetState)


def seconds(duration: Any) -> float:
    """Return a ``builtin_interfaces/Duration`` in seconds."""
    return float(duration.sec) + 1e-9 * float(duration.nanosec)


def stamp_ns(header: Any) -> int | None:
    """Return a header's stamp [ns], or None when it is zero (start now)."""
    ns = wire.stamp_to_ns(int(header.stamp.sec), int(header.stamp.nanosec))
    return ns if ns != 0 else None


def trajectory_from_msg(msg: Any) -> JointTrajectoryGoal:
    """Return the goal of a ``trajectory_msgs/JointTrajectory`` (no tolerances)."""
    points = tuple(
        TrajectoryPoint(seconds(p.time_from_start), tuple(float(x) for x in p.positions),
                        tuple(float(x) for x in p.velocities),
                        tuple(float(x) for x in p.accelerations))
        for p in msg.points)
    return JointTrajectoryGoal(tuple(str(n) for n in msg.joint_names), points)


def _tolerances(items: Any) -> tuple[JointTolerance, ...]:
    return tuple(JointTolerance(str(t.name), float(t.position), float(t.velocity),
                                float(t.acceleration)) for t in items)


def goal_from_msg(goal: Any) -> tuple[JointTrajectoryGoal | None, GoalVerdict]:
    """
    Return the core's goal of a ``FollowJointTrajectory.Goal``, or why it cannot be one.

    Returns
    -------
    goal : JointTrajectoryGoal or None
        None when the message asks for what this stage does not do.
    verdict : GoalVerdict
        SUCCESSFUL, or ``INVALID_GOAL`` with the reason (a multi-DOF trajectory, component
        tolerances): the follower checks the rest.

    """
    multi = getattr(goal, 'multi_dof_trajectory', None)
    if multi is not None and len(multi.points):
        return None, GoalVerdict(ResultCode.INVALID_GOAL, 'multi_dof_trajectory: the stage has '
                                 'no multi-DOF joints; give the points in trajectory')
    for name in ('component_path_tolerance', 'component_goal_tolerance'):
        if len(getattr(goal, name, ())):
            return None, GoalVerdict(ResultCode.INVALID_GOAL, f'{name}: component tolerances '
                                     'are not supported; use path_tolerance, goal_tolerance')
    base = trajectory_from_msg(goal.trajectory)
    return JointTrajectoryGoal(base.joint_names, base.points,
                               _tolerances(goal.path_tolerance),
                               _tolerances(goal.goal_tolerance),
                               seconds(goal.goal_time_tolerance)), GoalVerdict(
                                   ResultCode.SUCCESSFUL)


def result_msg(code: int, reason: str) -> Any:
    """Return a ``FollowJointTrajectory.Result`` with this error code and string."""
    return follow_joint_trajectory().Result(error_code=int(code), error_string=reason)


def result_of(result: GoalResult) -> Any:
    """Return the ``FollowJointTrajectory.Result`` of how a goal ended."""
    return result_msg(result.code, result.reason)


def feedback_msg(feedback: Feedback, joints: tuple[str, ...], stamp: int) -> Any:
    """Return the ``FollowJointTrajectory.Feedback`` of ``feedback`` stamped ``stamp`` [ns]."""
    msg = follow_joint_trajectory().Feedback()
    sec, nanosec = wire.ns_to_stamp(stamp)
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    msg.joint_names = list(joints)
    msg.desired.positions = [float(x) for x in feedback.desired_m]
    msg.desired.velocities = [float(x) for x in feedback.desired_velocity_mps]
    msg.actual.positions = [float(x) for x in feedback.actual_m]
    msg.error.positions = [float(x) for x in feedback.error_m]
    return msg
