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
The three nodes for a stage of several axes, in lockstep (rclpy).

A parameter file whose plant_node section has ``axes.names`` describes a stage of several axes
(:mod:`piezo_stage_ros.core.config.axes`); the executables then make these node classes, under
the same names, topics and parameter tables, instead of the one-axis ones (:func:`axes_factories`).
Each node declares its one-axis table (the base of every axis) and the multi-axis names the
files give it (``axes.*``, ``scan.*``: each described as the table's parameter it overrides),
and builds the loop as the offline runner does from the same files
(:func:`~piezo_stage_ros.core.config.axes.axes_loop_config`), its own section as declared.

Messages: one per sample and topic, every axis in it (a sample stays atomic: one stamp, one
message to wait for): ``stage/position``, ``stage/true_position`` and ``stage/reference`` are
JointStates naming one joint per axis (``stage_x`` ...), ``stage/command`` a Float64MultiArray
in the axis order with ``layout.dim`` = [{``axes``, N, N}], ros2_control's joint-group
convention (:mod:`piezo_stage_ros.core.contracts.wire`). These are the topics of the offline
runner's bag (:func:`~piezo_stage_ros.analysis.bagwrite.write_axes`), so that a recorder
records the run as that bag. The behaviour is :mod:`piezo_stage_ros.nodes.axes_logic`.

Real time (``mode: realtime``) runs in one process, ``stage_servo --direct``
(:func:`connect_axes`): the plant node drives the servo of several axes
(:class:`~piezo_stage_ros.nodes.servo_axes.AxesServoLoop`, in a thread of the process) which
computes every node's part of each sample on its own clock; the executor drains its samples in
batches and publishes them on the same topics, the reference and command from the trajectory
and controller nodes' publishers, so that a recorder records a real-time run as a lockstep one;
with ``recording.block`` every sample also goes on ``stage/block``, every axis in a row
(:class:`~piezo_stage_ros.nodes.recording.AxesBlockRecorder`), which a recorder keeps whole.
Goals (``stage/follow_joint_trajectory``, ``stage/joint_trajectory``, joints ``stage_x`` ...)
are followed in lockstep, composed or in three processes (:class:`AxesTrajectoryNode`). The
trajectory node announces each change of the goals' reference on ``stage/trajectory`` (the
follower's spline, JSON), before the reference of the sample it changes at, and the
controller node binds every axis' feed-forward to it there, as the offline twin does; a
learning feed-forward keeps the scan's reference, finds the goal's changed and leaves those
samples to the feedback. Refused at start-up with the reason: another backend than the
model, real time without ``--direct``, ``--direct`` in lockstep; in real time every goal is
refused with the reason; the trajectory node offers no start/stop services with several axes;
parameters cannot change at run time.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Any, Callable, Sequence
import warnings

import numpy as np
from piezo_stage_ros.core.config.axes import axes_loop_config, AxesLoopConfig, has_axes
from piezo_stage_ros.core.config.loader import load_config
from piezo_stage_ros.core.config.unknown import MULTI_AXIS_PREFIXES
from piezo_stage_ros.core.contracts import wire
from piezo_stage_ros.core.contracts.cdr import (
    CdrError,
    decode_joint_state_message,
    decode_multi_array,
    encode_clock,
    encode_multi_array,
    JointStateEncoder,
    JointStateMessage,
)
from piezo_stage_ros.core.contracts.errors import ParameterError, PiezoStageError
from piezo_stage_ros.core.control.axes import AxesController, coupled_loop_check
from piezo_stage_ros.core.control.stability import enforce
from piezo_stage_ros.core.model.axes import AxesStage
from piezo_stage_ros.hardware.pacing import servo_setup
from piezo_stage_ros.nodes import qos
from piezo_stage_ros.nodes.axes_logic import (
    announce_axes_goal,
    axes_follower,
    AxesCommand,
    AxesControllerLogic,
    AxesPlantLogic,
    AxesSample,
    AxesTrajectoryLogic,
    parse_axes_goal,
    refuse_axes_mode,
)
from piezo_stage_ros.nodes.goal_server import GoalServer
from piezo_stage_ros.nodes.logic import Gate
from piezo_stage_ros.nodes.parameters import _plain, descriptor, ParameterBinding
from piezo_stage_ros.nodes.recording import AxesBlockRecorder, backlog_samples
from piezo_stage_ros.nodes.servo_axes import axes_servo_from_config, AxesSampleBatch, AxesServoLoop
from piezo_stage_ros.nodes.tables import (
    controller_table,
    NodeTable,
    plant_table,
    scan_table,
    trajectory_table,
)
from piezo_stage_ros.nodes.tables import (
    params_files as files_of,
)
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.task import Future
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String

#: The plant node's timer [s]: lockstep resends and the start; in real time the drain.
TICK_S = 0.005

__all__ = ['AxesControllerNode', 'AxesPlantNode', 'AxesTrajectoryNode', 'axes_factories',
           'connect_axes']


def _refuse_change(old: Sequence[Any], new: Sequence[Any]) -> None:
    raise PiezoStageError('a stage of several axes takes no parameter change at run time')


def _stamp_ns(msg: JointStateMessage) -> int:
    return msg.sec * wire.NS_PER_S + msg.nanosec


class _AxesNode(Node):
    """
    What the three nodes share: the tables declared, the loop built, malformed messages counted.

    Parameters
    ----------
    name : str
        The node's name (that of its one-axis counterpart).
    table : NodeTable
        Its one-axis parameter table: the base of every axis.
    params_files : sequence of str
        The process's parameter files; the node's own ``cli_args`` files are added.
    direct : bool
        Whether the three nodes run composed with ``--direct`` (:func:`connect_axes`).
    **kwargs
        Passed to :class:`rclpy.node.Node`.

    Raises
    ------
    PiezoStageError
        A mode the nodes cannot run with several axes, a bad value (naming it), or files that
        describe no stage of several axes.

    """

    def __init__(self, name: str, table: NodeTable, params_files: Sequence[str] = (),
                 direct: bool = False, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        cli = kwargs.get('cli_args')
        self.files = [*params_files, *(files_of(cli) if cli else [])]
        # before the table's binding, whose check of a change knows the table's names only
        axes = self._declare_axes(table, scan=name == 'trajectory_node')
        self.binding = ParameterBinding(self, table, _refuse_change)
        opts = self.binding.objects[-1]
        refused = refuse_axes_mode(name, opts.mode, getattr(opts, 'backend', 'model'), direct)
        if refused is not None:
            raise PiezoStageError(refused)
        own = {d.name: _plain(self.get_parameter(d.name).value) for d in table.declarations()}
        own.update(axes)
        #: This node's section as declared (the files' values, its overrides, its axes.*).
        self.own = own
        self.loop: AxesLoopConfig = self._loop({name: own})
        self.names = self.loop.stage.names
        self.joints = list(wire.axis_joint_names(self.names))
        self.rate_hz = float(self.loop.stage.axes[0].sample_rate_hz)
        self.malformed = 0

    def _declare_axes(self, table: NodeTable, scan: bool) -> dict[str, Any]:
        # the multi-axis names given to this node, each described as the table's parameter it
        # overrides for one axis (axes.<axis>.<name>); refused at run time like the rest. The
        # scan (scan.*) is the trajectory node's only: elsewhere it stays undeclared, and the
        # runner refuses it as any name the node does not declare (as the offline loader does)
        base = {d.name: d for d in table.declarations()}
        scans = {d.name: d for d in scan_table().declarations()} if scan else {}
        out = {}
        for name, given in sorted(getattr(self, '_parameter_overrides', {}).items()):
            if not name.startswith(MULTI_AXIS_PREFIXES):
                continue
            parts = name.split('.', 2)
            if parts[0] == 'scan' and not scan:
                continue
            if parts[0] == 'scan':
                decl = scans.get(name)
            elif len(parts) == 3 and parts[1] not in ('coupling', 'names'):
                decl = base.get(parts[2])  # axes.<axis>.<name>
            else:
                decl = None
            desc = descriptor(dataclasses.replace(decl, name=name, read_only=True)) \
                if decl is not None else ParameterDescriptor(
                    name=name, read_only=True, dynamic_typing=True,
                    description='multi-axis stage (docs/reference/ros-interface.md)')
            out[name] = _plain(self.declare_parameter(name, given.value, desc).value)
        return out

    def _loop(self, sections: dict[str, dict[str, Any]]) -> AxesLoopConfig:
        # the files' loop with the nodes' sections as declared
        try:
            config = load_config(self.files)
            for name, own in sections.items():
                config = config.with_overrides(name, own)
            return axes_loop_config(config)
        except ParameterError as exc:
            raise ParameterError(exc.name, exc.value, f'{exc.allowed}; read from '
                                 + (', '.join(self.files) or 'no parameter file'),
                                 exc.reason) from None

    def detach(self) -> None:
        """Stop taking the loop's messages: the servo calls this node's part (real time)."""
        for sub in getattr(self, '_subs', ()):
            self.destroy_subscription(sub)
        self._subs: list[Any] = []

    def _dropped(self, text: str) -> None:
        self.malformed += 1
        self.get_logger().warning(f'{text}: dropped', throttle_duration_sec=1.0)

    def _decode(self, data: bytes, topic: str) -> JointStateMessage | None:
        """Return a JointState's bytes decoded, or None (counted) if malformed."""
        try:
            return decode_joint_state_message(data)
        except CdrError as exc:
            self._dropped(f'{topic}: {exc}')
            return None

    def _values(self, msg: JointStateMessage, field: str) -> list[float] | None:
        """Return a JointState's ``field`` in the axis order, or None (counted) if malformed."""
        try:
            values = getattr(msg, field).tolist()
            return [values[msg.names.index(j)] for j in self.joints]
        except (ValueError, IndexError):
            self._dropped(f'a JointState without the joints {self.joints} in its {field}')
            return None


class AxesPlantNode(_AxesNode):
    """
    The stage model of several axes: in lockstep one sample of every axis per command.

    In real time the servo of :meth:`attach_servo` samples every axis on its own clock (see
    the module's docstring); the node starts it and publishes what it served.

    Attributes
    ----------
    finished : rclpy.task.Future
        Done (with the counters) when the run of ``duration_s`` is complete, or failed.
    servo : AxesServoLoop or None
        The real-time loop (:meth:`attach_servo`), None in lockstep.

    """

    def __init__(self, *, params_files: Sequence[str] = (), direct: bool = False,
                 **kwargs: Any) -> None:
        super().__init__('plant_node', plant_table(), params_files, direct, **kwargs)
        opts = self.binding.objects[1]
        self.opts = opts
        self.realtime = opts.mode != 'lockstep'
        self.servo: AxesServoLoop | None = None
        self._peers: Sequence[Callable[[int, int, AxesSampleBatch, int], None]] = ()
        self._block_pub: Any = None
        self._blocks: AxesBlockRecorder | None = None
        self.logic = AxesPlantLogic(AxesStage(self.loop.stage), sample_rate_hz=self.rate_hz,
                                    duration_s=opts.duration_s, resend_s=opts.lockstep.resend_s)
        self.finished = Future()
        # CDR bytes out and in (core/contracts/cdr.py), as the one-axis nodes
        self._encoder = JointStateEncoder(self.joints)
        self._pub = self.create_publisher(JointState, wire.POSITION, qos.LOOP_OUT)
        self._true_pub = self.create_publisher(JointState, wire.TRUE_POSITION, qos.LOOP_OUT)
        self._clock_pub = self.create_publisher(ClockMsg, wire.CLOCK, qos.CLOCK)
        self._clock_gate: Callable[[], bool] = Gate(self._clock_pub.get_subscription_count)
        if not self.realtime:
            self.create_subscription(Float64MultiArray, wire.COMMAND, self._on_command,
                                     qos.LOOP, raw=True)
        self._matched_at: float | None = None
        self._t_start = 0.0
        self._timer = self.create_timer(TICK_S, self._tick,
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(
            f'{opts.mode} at {self.rate_hz:g} Hz, {self.logic.n} axes {list(self.names)}, plant '
            f'{self.loop.stage.axes[0].plant.model}'
            + (f', {self.logic.total} samples' if self.logic.total else ''))

    def _publish(self, sample: AxesSample) -> None:
        sec, nanosec = wire.ns_to_stamp(sample.stamp_ns)
        if self._clock_gate():
            self._clock_pub.publish(encode_clock(sec, nanosec))
        self._pub.publish(self._encoder.encode(sec, nanosec, sample.positions_m))
        self._true_pub.publish(self._encoder.encode(sec, nanosec, sample.true_positions_m))

    def attach_servo(self, loop: AxesLoopConfig,
                     peers: Sequence[Callable[[int, int, AxesSampleBatch, int], None]]
                     ) -> None:
        """
        Real time in one process: build the servo of ``loop``; ``peers`` publish its batches.

        Parameters
        ----------
        loop : AxesLoopConfig
            The loop of the three nodes' sections (:func:`connect_axes`).
        peers : sequence of callable
            ``peer(sec, nanosec, batch, i)`` publishes row ``i`` of a batch drained, from the
            executor, after the plant's messages of that sample (the trajectory's reference,
            then the controller's command: a lockstep sample's order, which a bag's reader
            pairs the unstamped command by).

        """
        self.servo = axes_servo_from_config(
            loop, self.opts.duration_s,
            capacity=backlog_samples(self.opts.recording, self.rate_hz))
        self._peers = tuple(peers)
        recording = self.opts.recording
        if recording.block:
            # every sample on stage/block, every axis in a row: what a recorder keeps whole
            self._block_pub = self.create_publisher(Float64MultiArray, wire.BLOCK, qos.BLOCK)
            self._blocks = AxesBlockRecorder(self.names, recording.block_samples)
        # the servo process (servo.process) runs the one-axis loop; several axes share this
        # process's interpreter with the executor, in a thread
        self.get_logger().info(f'servo of {len(self.names)} axes in a thread of this process'
                               + (' (servo.process serves one axis)'
                                  if self.opts.servo.process else ''))

    def _ready(self, now: float, peers: int) -> bool:
        # the start waits for lockstep.subscribers on stage/position (``peers`` of them are
        # called instead of subscribed), then lockstep.settle_s, so that a recorder misses
        # no sample
        lockstep = self.opts.lockstep
        if self._matched_at is None and \
                self._pub.get_subscription_count() + peers >= lockstep.subscribers:
            self._matched_at = now
        return self._matched_at is not None and now - self._matched_at >= lockstep.settle_s

    def _tick(self) -> None:
        try:
            now = time.monotonic()
            if self.realtime:
                self._servo_tick(now)
                return
            if self.logic.index < 0:
                if self._ready(now, 0):
                    self._t_start = now
                    self._publish(self.logic.start(now))
                    if self.logic.done:
                        self._finish()
                return
            again = self.logic.resend_due(now)
            if again is not None:
                self._publish(again)
        except Exception as exc:  # noqa: BLE001 -- any fault ends the run with it
            self._fault(exc)

    def _servo_tick(self, now: float) -> None:
        servo = self.servo
        if servo is None:
            raise PiezoStageError(str(refuse_axes_mode('plant_node', self.opts.mode)))
        if not self._t_start:
            if self._ready(now, len(self._peers)):
                self._t_start = now
                opts, period_ns = self.opts.servo, servo.pacer.period_ns
                # the executor's turn at the interpreter lock: two ticks of its timer
                servo.share_interpreter(2 * TICK_S)
                servo.start_thread(self.get_clock().now().nanoseconds,
                                   lambda: servo_setup(opts, period_ns),
                                   since_ns=time.monotonic_ns())
            return
        finished = servo.finished
        self._hand_on(servo.take_batch())
        if finished and self._blocks is not None:
            # the last rows, with what the plant held after them
            for raw in self._blocks.finish(servo.guard.held_v):
                self._block_pub.publish(raw)
            self._blocks = None
        if finished:
            for key, text in servo.setup_report.items():
                self.get_logger().info(f'servo {key}: {text}')
            if servo.error is not None:
                self._fault(servo.error)
            else:
                self._finish()

    def _hand_on(self, batch: AxesSampleBatch) -> None:
        # every sample into the blocks first; then every sample served, on the lockstep's
        # topics in a lockstep sample's order: y_k and x(t_k) here, x_d and u_k from the
        # peers' publishers
        if self._blocks is not None:
            for raw in self._blocks.add(batch):
                self._block_pub.publish(raw)
        encode, peers = self._encoder.encode, self._peers
        for i, stamp in enumerate(batch.stamp_ns.tolist()):
            sec, nanosec = wire.ns_to_stamp(stamp)
            self._pub.publish(encode(sec, nanosec, batch.position_m[i]))
            self._true_pub.publish(encode(sec, nanosec, batch.true_position_m[i]))
            for peer in peers:
                peer(sec, nanosec, batch, i)

    def _on_command(self, data: bytes) -> None:
        try:
            commands = decode_multi_array(data)[2].tolist()
        except CdrError as exc:
            self._dropped(f'{wire.COMMAND}: {exc}')
            return
        if len(commands) != self.logic.n:
            self._dropped(f'{wire.COMMAND}: {len(commands)} entries for {self.logic.n} axes')
            return
        try:
            sample = self.logic.on_command(commands, time.monotonic())
            if sample is not None:
                self._publish(sample)
            elif self.logic.done:
                self._finish()
        except Exception as exc:  # noqa: BLE001
            self._fault(exc)

    def stats(self) -> dict[str, Any]:
        """Return the counters and the loop rate reached (the servo's in real time)."""
        out = self.logic.stats() if self.servo is None else self.servo.stats()
        served = self.logic.index + 1 if self.servo is None else self.servo.pushed
        elapsed = time.monotonic() - self._t_start if self._t_start else 0.0
        out.update({'malformed': self.malformed, 'wall_s': round(elapsed, 6),
                    'samples_per_s': round(served / elapsed, 1) if elapsed > 0 else 0.0})
        return out

    def _stop(self) -> None:
        self._timer.cancel()
        self.logic.stop()
        if self.servo is not None:
            self.servo.stop()

    def destroy_node(self) -> None:
        """Stop the servo's thread (if any), then destroy the node."""
        if self.servo is not None:
            self.servo.stop()
        super().destroy_node()

    def _finish(self) -> None:
        if self.finished.done():
            return
        self._stop()
        stats = self.stats()
        self.get_logger().info('run complete: ' + ', '.join(f'{k} {v}'
                                                            for k, v in stats.items()))
        self.finished.set_result(stats)

    def _fault(self, exc: BaseException) -> None:
        self._stop()
        if not self.context.ok() or self.finished.done():
            return
        self.get_logger().error(f'fault: {exc}')
        self.finished.set_exception(exc if isinstance(exc, PiezoStageError)
                                    else PiezoStageError(repr(exc)))


class AxesTrajectoryNode(_AxesNode, GoalServer):
    """
    Every axis' reference (the scan of the files) for each position's stamp; goals in lockstep.

    ``stage/follow_joint_trajectory`` and ``stage/joint_trajectory`` take goals whose joints
    are the stage's axes (``stage_x`` ...; some of them: the others hold), in lockstep: a goal
    takes every axis over from the scan at the next sample (:class:`~piezo_stage_ros.nodes.
    axes_logic.AxesTrajectoryLogic`). In real time (the servo of several axes plays the scan)
    every goal is refused with the reason.
    """

    logic: AxesTrajectoryLogic

    def __init__(self, *, params_files: Sequence[str] = (), direct: bool = False,
                 **kwargs: Any) -> None:
        super().__init__('trajectory_node', trajectory_table(), params_files, direct, **kwargs)
        opts = self.binding.objects[1]
        self.logic = AxesTrajectoryLogic(self.loop.trajectories(), sample_rate_hz=self.rate_hz,
                                         chunk_s=opts.chunk_s, names=self.names)
        self._encoder = JointStateEncoder(self.joints, with_velocity=True)
        self._pub = self.create_publisher(JointState, wire.REFERENCE, qos.LOOP_OUT)
        self._subs = [self.create_subscription(JointState, wire.POSITION, self._on_position,
                                               qos.LOOP, raw=True)]
        self._init_goal_server(self.joints)
        if opts.mode == 'lockstep':
            self.logic.attach_goals(axes_follower(self.loop))
            # the goals' reference, as it changes, to the controller node's feed-forwards
            announce = self.create_publisher(String, wire.TRAJECTORY, qos.ANNOUNCE)
            self.logic.on_reference_change = lambda spline, stamp: announce.publish(
                String(data=announce_axes_goal(stamp, spline)))
        else:
            self.goals_refused = (
                f'mode {opts.mode!r}: goals on a stage of several axes are followed in lockstep '
                '(mode: lockstep); the real-time servo of several axes plays the scan of the '
                'parameter files')
        # the multi-axis plant is not a managed node: goals do not wait for its state
        self._make_goal_interfaces(follow_plant=False)
        self.get_logger().info(f'scan {self.loop.scan.kind} over the axes {list(self.names)}; '
                               + ('goals on ' + ', '.join(self.joints) if self.goals_refused
                                  is None else 'no goals in real time'))

    def publish_sample(self, sec: int, nanosec: int, batch: AxesSampleBatch, i: int) -> None:
        """Publish the references the servo computed for row ``i`` (:func:`connect_axes`)."""
        self._pub.publish(self._encoder.encode(sec, nanosec, batch.reference_m[i],
                                               batch.velocity_mps[i]))

    def _on_position(self, data: bytes) -> None:
        msg = self._decode(data, wire.POSITION)
        if msg is None:
            return
        positions = self._values(msg, 'position') if self.logic.follower is not None else None
        ref, vel = self.logic.on_position(_stamp_ns(msg), positions)
        self._pub.publish(self._encoder.encode(msg.sec, msg.nanosec, ref, vel))
        if self.logic.events:
            self._drain()


class AxesControllerNode(_AxesNode):
    """
    Every axis' controller, stepped together; checked at start as the offline runner checks.

    Raises
    ------
    StabilityError
        An axis' own loop unstable on its design model with ``stability.action: refuse``.

    """

    def __init__(self, *, params_files: Sequence[str] = (), direct: bool = False,
                 **kwargs: Any) -> None:
        super().__init__('controller_node', controller_table(), params_files, direct, **kwargs)
        loop = self.loop
        trajectories = loop.trajectories()
        ctrl = AxesController.build(loop.controllers, loop.stage, compensate=loop.compensate)
        log = self.get_logger()
        for name, report in loop.stability(trajectories).items():
            with warnings.catch_warnings():
                warnings.simplefilter('ignore')  # logged below
                text = enforce(report, loop.base.stability.action)
            (log.info if report.stable else log.warning)(f'axis {name}: {text}')
        self.logic = AxesControllerLogic(ctrl, trajectories)
        check = coupled_loop_check(ctrl)
        ok = check.certified and (check.learning_ratio is None or check.learning_ratio < 1.0)
        (log.info if ok else log.warning)(
            check.text() + '; coupling compensation on '
            + (', '.join(self.names[j] for j in ctrl.compensated) or 'no axis'))
        self._dims = wire.axes_command_dims(len(self.names))
        self._pub = self.create_publisher(Float64MultiArray, wire.COMMAND, qos.LOOP_OUT)
        self._subs = [
            self.create_subscription(JointState, wire.POSITION, self._on_position, qos.LOOP,
                                     raw=True),
            self.create_subscription(JointState, wire.REFERENCE, self._on_reference, qos.LOOP,
                                     raw=True),
            self.create_subscription(String, wire.TRAJECTORY, self._on_goal, qos.ANNOUNCE)]

    def publish_sample(self, sec: int, nanosec: int, batch: AxesSampleBatch, i: int) -> None:
        """Publish the commands the servo computed for row ``i`` (:func:`connect_axes`)."""
        self._pub.publish(encode_multi_array(self._dims, batch.command_v[i]))

    def _publish(self, out: AxesCommand | None) -> None:
        if out is not None:
            self._pub.publish(encode_multi_array(self._dims, np.array(out.commands_v)))

    def _on_position(self, data: bytes) -> None:
        msg = self._decode(data, wire.POSITION)
        values = self._values(msg, 'position') if msg is not None else None
        if msg is not None and values is not None:
            self._publish(self.logic.on_position(_stamp_ns(msg), values))

    def _on_goal(self, msg: String) -> None:
        # the goals' reference of the trajectory node, bound before the sample it changes at
        try:
            stamp, spline = parse_axes_goal(msg.data)
        except ParameterError as err:
            self._dropped(f'{wire.TRAJECTORY}: {err}')
            return
        self.logic.request_goal(spline, stamp)

    def _on_reference(self, data: bytes) -> None:
        msg = self._decode(data, wire.REFERENCE)
        if msg is None:
            return
        ref, vel = self._values(msg, 'position'), self._values(msg, 'velocity')
        if ref is not None and vel is not None:
            self._publish(self.logic.on_reference(_stamp_ns(msg), ref, vel))


_CLASSES: dict[str, type[_AxesNode]] = {'plant': AxesPlantNode, 'controller': AxesControllerNode,
                                        'trajectory': AxesTrajectoryNode}


def axes_factories(argv: Sequence[str], names: Sequence[str]
                   ) -> list[tuple[str, Callable[..., Node]]] | None:
    """
    Return the multi-axis node factories for a command line whose files describe several axes.

    Parameters
    ----------
    argv : sequence of str
        The process's command line (its ``--params-file`` files are read).
    names : sequence of str
        The short names wanted (``plant``, ``controller``, ``trajectory``), in order.

    Returns
    -------
    list of (str, callable) or None
        For :func:`~piezo_stage_ros.nodes.runner.run` (which adds ``direct``, the
        composition's); None when the files describe one axis
        (or cannot be read: the one-axis nodes then say why).

    """
    files = files_of(argv)
    if any(name not in _CLASSES for name in names):
        return None
    try:
        if not files or not has_axes(load_config(files)):
            return None
    except (PiezoStageError, OSError):
        return None
    return [(name, functools.partial(_CLASSES[name], params_files=files)) for name in names]


def connect_axes(plant: AxesPlantNode, controller: AxesControllerNode,
                 trajectory: AxesTrajectoryNode) -> None:
    """
    Compose the three nodes for real time (``stage_servo --direct`` with several axes).

    The plant's servo runs every axis' reference and controller of the three nodes' sections
    as declared (the loop the offline runner builds from the same files and values); the
    trajectory and controller nodes stop subscribing and publish what the servo computed.
    """
    controller.detach()
    trajectory.detach()
    loop = plant._loop({n.get_name(): n.own for n in (plant, controller, trajectory)})
    plant.attach_servo(loop, (trajectory.publish_sample, controller.publish_sample))
