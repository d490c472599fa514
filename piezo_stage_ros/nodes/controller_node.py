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
The controller node: RAC or PI from parameters, position and reference in, command out.

Parameters: :func:`piezo_stage_ros.nodes.tables.controller_table` (the controller of the core,
the stability check under ``stability.``, and the node group). At start-up the loop is checked
against the design model (:func:`piezo_stage_ros.nodes.tables.design_model`: the plant node's
``plant.*`` from the same parameter files, or with ``stability.design_model: own`` the node's
``stability.plant.*``), and the log says which model and the verdict; an unstable verdict with
``stability.action: refuse`` stops the node. Gains changed at run time are validated
(ranges, then the stability check again) and applied at the next sample; a refused value leaves
everything as it was. Topics: subscribes to ``stage/position`` and ``stage/reference``,
publishes ``stage/command`` and ``stage/diagnostics`` (controller internals: theta_hat,
phi_hat, s, saturation ...). A feed-forward predicts from its own copy of the trajectory: a new
one announced on ``stage/trajectory`` is bound at the sample of its t = 0 (model inverse at
once, learning afresh); a start after a stop is announced too, and the same line goes on from
its new t = 0 with the table it learned.
"""

from __future__ import annotations

import functools
import sys
import time
from typing import Any, Callable, Sequence

from piezo_stage_ros.core.contracts import wire
from piezo_stage_ros.core.contracts.cdr import (
    encode_float64,
    JointStateDecoder,
    JointStateEncoder,
)
from piezo_stage_ros.core.contracts.errors import (
    PiezoStageError,
    StabilityError,
)
from piezo_stage_ros.core.contracts.interfaces import Controller
from piezo_stage_ros.core.control.controllers import (
    bound_controller,
    build_controller,
    ControllerParams,
)
from piezo_stage_ros.core.control.stability import check_stability, StabilityParams
from piezo_stage_ros.core.loop.follow import SplineTrajectory
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryBase
from piezo_stage_ros.core.model.hysteresis import HysteresisModel
from piezo_stage_ros.core.model.stage import linear_plant, PlantParams
from piezo_stage_ros.nodes import qos
from piezo_stage_ros.nodes.diagnostics import DIAGNOSTICS_PERIOD_S, DiagnosticsPublisher
from piezo_stage_ros.nodes.health import controller_statuses, hardware_id, Status
from piezo_stage_ros.nodes.logic import (
    Command,
    ControllerLogic,
    Gate,
    parse_announcement,
    rebuild_or_learn_afresh,
    save_learned_table,
)
from piezo_stage_ros.nodes.parameters import ParameterBinding
from piezo_stage_ros.nodes.runner import decode_or_drop, run, stops_quietly
from piezo_stage_ros.nodes.tables import (
    controller_table,
    ControllerNodeParams,
    design_model,
    feedforward_context,
    params_files,
)
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, String

__all__ = ['ControllerNode', 'main']


class ControllerNode(Node):
    """
    The controller as a ROS node.

    Parameters
    ----------
    params_files : sequence of str
        The ``--params-file`` files of the process's command line: the design model is the
        plant_node section's ``plant.*`` in them (``stability.design_model: plant``); the
        node's own ``cli_args`` files are added.
    **kwargs
        Passed to :class:`rclpy.node.Node`.

    Raises
    ------
    StabilityError
        If the configured loop is unstable on the design model and
        ``stability.action`` is ``'refuse'``.

    """

    def __init__(self, *, params_files: Sequence[str] = (), **kwargs: Any) -> None:
        super().__init__('controller_node', **kwargs)
        self._files = [*params_files, *_files_of(kwargs.get('cli_args'))]
        self.binding = ParameterBinding(self, controller_table(), self._on_change)
        params, stability, opts = self.binding.objects
        self.opts: ControllerNodeParams = opts
        self.sample_time_s = 1.0 / opts.sample_rate_hz
        self.design_plant, source = self._design(stability)
        # the feed-forward's design hysteresis and reference ahead, from the same files; read
        # only when one is configured (feedforward.mode is read-only: no change turns it on)
        self._ff_context: tuple[HysteresisModel, TrajectoryBase] | None = None
        self._check_context: dict[str, Any] = {}
        if params.feedforward.mode != 'none':
            self._ff_context, self._check_context = feedforward_context(self._files)
        self.get_logger().info(f'design model: {source}')
        self.verdict = self._check(params, stability)
        self.logic = ControllerLogic(self._build(params, stability), mode=opts.mode,
                                     safe_voltage_v=opts.safe_voltage_v,
                                     position_timeout_s=opts.position_timeout_s,
                                     diagnostics_every=opts.diagnostics_every,
                                     rebuild=self._rebuild,
                                     on_refused=self._log_error,
                                     on_bound=self._bound_trajectory,
                                     trajectory=self._ff_context[1] if self._ff_context
                                     else None)
        self._stability = stability
        #: Where changes go besides ``logic``: a servo process that runs its own copy of it
        #: (``ServoProcess.change``; stage_servo --direct in real time).
        self.forward: Callable[[str, Any], None] | None = None
        # CDR bytes in and out (core/contracts/cdr.py): rclpy message objects cost more than a
        # sample
        self._diag_names = self.logic.names
        self._diag = JointStateEncoder(self._diag_names)
        self._positions = JointStateDecoder([wire.JOINT_NAME])
        self._references = JointStateDecoder([wire.JOINT_NAME], with_velocity=True)
        self._matched = False
        self.malformed = 0
        self._cmd_pub = self.create_publisher(Float64, wire.COMMAND, qos.LOOP_OUT)
        self._diag_pub = self.create_publisher(JointState, wire.DIAGNOSTICS, qos.LOOP_OUT)
        self._subs = [
            self.create_subscription(JointState, wire.POSITION, self._on_position, qos.LOOP,
                                     raw=True),
            self.create_subscription(JointState, wire.REFERENCE, self._on_reference,
                                     qos.LOOP, raw=True)]
        if self._ff_context is not None:
            self._trajectory_sub = self.create_subscription(String, wire.TRAJECTORY,
                                                            self._on_trajectory, qos.ANNOUNCE)
        self._cmd_gate: Callable[[], bool] = lambda: True
        self._diag_gate: Callable[[], bool] = lambda: True
        self._last_u: float = opts.safe_voltage_v
        self._lockstep = opts.mode == 'lockstep'
        self._watch = None
        if not self._lockstep:
            self._watch = self.create_timer(opts.position_timeout_s / 2.0, self._check_watchdog,
                                            clock=Clock(clock_type=ClockType.STEADY_TIME))
        # /diagnostics: the verdict, the estimates and the learning from the last diagnostics
        self._latest: tuple[Sequence[str], Sequence[float]] | None = None
        self._rms_before: float | None = None
        self.diagnostics = DiagnosticsPublisher(self, DIAGNOSTICS_PERIOD_S)
        self.diagnostics.add(self._statuses)

    def _statuses(self) -> list[Status]:
        rac = self.binding.objects[0].rac
        bounds = {'theta_hat': (rac.theta_min, rac.theta_max),
                  'phi_hat': (rac.phi_min, rac.phi_max)}
        latest = self._latest
        if self.forward is None:
            # the controller runs in this process (on this executor or the servo thread):
            # read now, whatever the per-sample topics left out under load
            names, read = wire.diagnostic_reader(self.logic.controller)
            latest = (names, read()) if names else None
        out = controller_statuses(self.get_name(), hardware_id(self.get_namespace()),
                                  latest, bounds, self.verdict, self._stable, self._caution,
                                  self._rms_before)
        if latest is not None and 'ff_period_rms_m' in latest[0]:
            self._rms_before = float(latest[1][list(latest[0]).index('ff_period_rms_m')])
        return out

    def _log_error(self, text: str) -> None:
        self.get_logger().error(text)

    def _bound_trajectory(self, trajectory: TrajectoryBase) -> None:
        # from the sample it is bound at (not when announced, nor when refused): a rebuild (a
        # structural gain change) binds the trajectory that plays, and the check judges the
        # learning at its period
        if self._ff_context is not None:
            self._ff_context = (self._ff_context[0], trajectory)
            self._check_context['period_s'] = trajectory.period_s

    def _design(self, stability: StabilityParams) -> tuple[PlantParams, str]:
        return design_model(stability, self._files)

    def _check(self, params: ControllerParams, stability: StabilityParams) -> str:
        report = check_stability(params, self.design_plant, self.sample_time_s,
                                 options=stability, **self._check_context)
        text = report.text()
        adaptation = report.adaptation
        self._stable = bool(report.stable)
        self._caution = adaptation is not None and not adaptation.ok
        if report.stable and adaptation is not None and not adaptation.ok:
            # stable loops, but adaptation rates that can limit-cycle between the bounds
            self.get_logger().warning('stability check: ' + text)
        elif report.stable:
            self.get_logger().info('stability check: ' + text)
        elif stability.action == 'refuse':
            raise StabilityError(text)
        else:
            self.get_logger().warning('stability check: ' + text)
        return text

    def _build(self, params: ControllerParams, stability: StabilityParams) -> Controller:
        # the plant a 'model' notch is designed from, built as the offline runner builds it
        plant = linear_plant(self.design_plant)
        if self._ff_context is None:
            return build_controller(params, self.sample_time_s, plant)
        return bound_controller(params, self.sample_time_s, plant, *self._ff_context)

    def _rebuild(self, params: ControllerParams) -> Controller:
        return rebuild_or_learn_afresh(lambda p: self._build(p, self._stability), params,
                                       self.get_logger().warning)

    def _on_change(self, old: Sequence[Any], new: Sequence[Any]) -> None:
        params, stability, opts = new
        if params is not old[0] or stability is not old[1]:
            # raises StabilityError for a refused verdict: the change is refused with its text
            # (the design model is read-only: it stays what start-up chose)
            self.verdict = self._check(params, stability)
            self._stability = stability
            if params is not old[0]:
                self.logic.request_change(params)
                if self.forward is not None:
                    self.forward('controller', params)
        self.logic.safe_voltage_v = opts.safe_voltage_v
        self.logic.watchdog.timeout_s = opts.position_timeout_s
        self.logic.diagnostics_every = opts.diagnostics_every
        if self.forward is not None:
            for path, value in (('safe_voltage_v', opts.safe_voltage_v),
                                ('watchdog.timeout_s', opts.position_timeout_s),
                                ('diagnostics_every', max(1, opts.diagnostics_every))):
                self.forward('set', ('controller.' + path, value))
        self.opts = opts

    def attach_direct(self) -> None:
        """
        Take position and reference by call (:meth:`answer`) instead of from the topics.

        For ``stage_servo --direct``: the subscriptions go, and the command and diagnostics are
        published for outside subscribers (a recorder) only.
        """
        for sub in self._subs:
            self.destroy_subscription(sub)
        self._subs = []
        self._matched = True
        self._cmd_gate = Gate(self._cmd_pub.get_subscription_count)
        self._diag_gate = Gate(self._diag_pub.get_subscription_count, every=100)
        if self._watch is not None:
            # positions come by call from the plant in this process (in real time from its
            # servo loop, which owns the safety of the loop): no topic to fall silent
            self._watch.cancel()

    def answer(self, stamp_ns: int, position_m: float, reference_m: float,
               reference_velocity_mps: float) -> float:
        """Return u_k for y_k and x_d(t_k) given by call (``stage_servo --direct``)."""
        self.logic.on_position(stamp_ns, position_m, time.monotonic())
        out = self.logic.on_reference(stamp_ns, reference_m, reference_velocity_mps)
        self.publish(out)
        return self._last_u

    def publish(self, out: Command | None) -> None:
        """Publish a command (and its diagnostics) computed by the logic; None: nothing."""
        if out is None:
            return
        self._last_u = out.voltage_v
        try:
            if self._cmd_gate():
                self._cmd_pub.publish(encode_float64(out.voltage_v))
        except Exception:
            if self.context.ok():
                raise
            return  # Ctrl-C shut the context down while this callback ran: nothing to send
        if self.forward is not None and out.diagnostics is not None:
            # a servo process runs the controller: its diagnostics come only this way
            self._latest = (out.diagnostic_names if out.diagnostic_names is not None
                            else self.logic.names, out.diagnostics)
        if out.diagnostics is not None and self._diag_gate():
            # the names the command came with: those of the controller that computed it (a
            # servo process runs its own copy of the logic, whose names this node's copy
            # does not follow)
            names = out.diagnostic_names if out.diagnostic_names is not None \
                else self.logic.names
            if names != self._diag_names:
                # a rebuilt controller of another kind reports other internals
                self._diag_names = names
                self._diag = JointStateEncoder(names)
            sec, nanosec = wire.ns_to_stamp(out.stamp_ns)
            self._diag_pub.publish(self._diag.encode(sec, nanosec, out.diagnostics))

    def _decode(self, data: bytes, topic: str) -> tuple[int, int, float, float] | None:
        decoder = self._positions if topic == wire.POSITION else self._references
        return decode_or_drop(self, topic, decoder.decode, data)

    @stops_quietly
    def _on_reference(self, data: bytes) -> None:
        msg = self._decode(data, wire.REFERENCE)
        if msg is not None:
            self.publish(self.logic.on_reference(wire.stamp_to_ns(msg[0], msg[1]), msg[2],
                                                  msg[3]))

    @stops_quietly
    def _on_trajectory(self, msg: String) -> None:
        if self.forward is not None or self._ff_context is None:
            return  # a servo process runs the controller: the trajectory node forwards to it
        try:
            stamp, given = parse_announcement(msg.data)
            trajectory = given if isinstance(given, SplineTrajectory) else make_trajectory(
                given, sample_rate_hz=self.opts.sample_rate_hz)
        except PiezoStageError as err:
            self.get_logger().error(f'{wire.TRAJECTORY}: {err}; the feed-forward keeps '
                                    'the trajectory it has')
            return
        self.logic.request_trajectory(trajectory, stamp)
        if not isinstance(given, SplineTrajectory):  # a goal's reference changes often
            self.get_logger().info(f'feed-forward: trajectory {given.kind} from stamp {stamp} '
                                   'ns')

    @stops_quietly
    def _on_position(self, data: bytes) -> None:
        if self._lockstep and not self._matched:
            if self._cmd_pub.get_subscription_count() == 0:
                # the command would reach nobody yet; the plant publishes this sample again
                return
            self._matched = True
        msg = self._decode(data, wire.POSITION)
        if msg is not None:
            self.publish(self.logic.on_position(wire.stamp_to_ns(msg[0], msg[1]), msg[2],
                                                 time.monotonic()))

    def _check_watchdog(self) -> None:
        out = self.logic.on_check(time.monotonic())
        if out is not None:
            self._cmd_pub.publish(encode_float64(out.voltage_v))
            if self.logic.safe_commands == 1 or self.logic.safe_commands % 1000 == 0:
                self.get_logger().warning(
                    f'no position for {self.logic.watchdog.timeout_s:g} s: safe command '
                    f'{out.voltage_v:g} V published ({self.logic.safe_commands} so far)')


    def destroy_node(self) -> None:
        """Write the learned table (``feedforward.save_table_file``), then destroy the node."""
        try:
            # with the servo in a process of its own, that process ran the controller and
            # writes its table (the plant node logs it); this node's copy stayed idle
            if self.forward is None:
                line = save_learned_table(self.logic.controller,
                                          self.binding.objects[0].feedforward.save_table_file)
                if line is not None:
                    self.get_logger().info(line)
        except PiezoStageError as err:
            self.get_logger().error(f'learned table not written: {err}')
        finally:
            super().destroy_node()


def _files_of(cli_args: Sequence[str] | None) -> list[str]:
    return params_files(cli_args) if cli_args else []


def factory(args: Sequence[str] | None) -> Callable[[], ControllerNode]:
    """Return a factory of the node that knows the parameter files of the command line."""
    return functools.partial(ControllerNode,
                             params_files=params_files(sys.argv if args is None else args))


def main(args: Sequence[str] | None = None) -> int:
    """Run the controller node (console script ``controller_node``)."""
    return run('controller_node', [('controller', factory(args))], args,
               'The RAC or PI controller of piezo_stage_ros.')
