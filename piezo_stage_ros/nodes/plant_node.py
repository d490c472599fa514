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
The plant node: the stage model or a hardware bridge, publishing the measured position.

Parameters: :func:`piezo_stage_ros.nodes.tables.plant_table` (the stage of the core, start-up
only, and the node group: mode, backend, duration, timeouts, bridge). Topics: publishes
``stage/position`` (and ``/clock`` in lockstep), ``stage/status`` and ``/diagnostics``
(:mod:`piezo_stage_ros.nodes.diagnostics`), subscribes to
``stage/command``; in real time ``stage/applied``, and with the servo loop running trajectory
and controller (``stage_servo --direct``) ``stage/block``, every sample in blocks
(:mod:`piezo_stage_ros.nodes.recording`). The behaviour is
:class:`piezo_stage_ros.nodes.logic.PlantLogic`; this class only moves messages and owns the
timers. It is a managed node (``rclpy.lifecycle``): :class:`PlantNode` says what each
transition does.

Run: ``ros2 run piezo_stage_ros plant_node --ros-args --params-file default.yaml`` (configured
and activated at once; ``--autostart false`` leaves it unconfigured).
"""

from __future__ import annotations

from dataclasses import replace
import time
from typing import Any, Callable, Sequence

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from piezo_stage_ros.core.contracts import wire
from piezo_stage_ros.core.contracts.cdr import (
    decode_float64,
    encode_clock,
    JointStateEncoder,
)
from piezo_stage_ros.core.contracts.errors import PiezoStageError
from piezo_stage_ros.hardware.pacing import Pacer, servo_setup
from piezo_stage_ros.hardware.safety import GuardedPlant, Trip
from piezo_stage_ros.nodes import qos
from piezo_stage_ros.nodes.diagnostics import DIAGNOSTICS_PERIOD_S, DiagnosticsPublisher
from piezo_stage_ros.nodes.health import (
    hardware_id,
    loop_status,
    OK,
    StageLifecycle,
    Status,
    watchdog_status,
)
from piezo_stage_ros.nodes.logic import (
    ControllerLogic,
    Gate,
    PlantLogic,
    realtime_warning,
    run_verdict,
    Sample,
    TrajectoryLogic,
    TripLog,
)
from piezo_stage_ros.nodes.parameters import ParameterBinding
from piezo_stage_ros.nodes.recording import backlog_samples, Handover, SampleBatch
from piezo_stage_ros.nodes.runner import decode_or_drop, run, start_managed
from piezo_stage_ros.nodes.servo import (
    make_bridge,
    samples_of,
    ServoLoop,
    ServoProcess,
    ServoSample,
)
from piezo_stage_ros.nodes.tables import plant_table, PlantNodeParams
from rclpy.clock import Clock, ClockType
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.task import Future
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, Float64MultiArray

__all__ = ['PlantNode', 'main']

#: Period [s] of the executor's timer that takes the samples of a real-time servo loop.
SERVO_TICK_S = 0.002

#: The state each transition of :class:`PlantNode` ends in when it succeeds.
_AFTER = {'configure': 'inactive', 'activate': 'active', 'deactivate': 'inactive',
          'cleanup': 'unconfigured', 'shutdown': 'finalized'}


class PlantNode(LifecycleNode):
    """
    The stage (model or bridge) as a ROS managed node.

    Parameters
    ----------
    autostart : bool
        Configure and activate at once (the node runs as soon as it is spun); False leaves
        it unconfigured for a lifecycle manager (``ros2 lifecycle set``).
    **kwargs
        Passed to :class:`rclpy.node.Node` (``context``, ``namespace``,
        ``parameter_overrides`` ...).

    Attributes
    ----------
    finished : rclpy.task.Future
        Done when a run of ``duration_s`` is complete, or failed with the error of a fault, or
        the node was shut down.
    diagnostics : DiagnosticsPublisher
        ``/diagnostics`` at about 1 Hz; :meth:`DiagnosticsPublisher.add` takes more sources.
    check : callable or None
        Called by configure: None when the controller this process runs passes its checks,
        else why not (the configure fails with that reason).

    Notes
    -----
    configure builds the backend behind the guard, the publishers and the loop from the
    parameters as they are then (declared and validated when the node is made); activate
    starts the loop (lockstep answering, or the real-time servo); deactivate ramps the
    amplifier to the safe voltage at ``watchdog.slew_v_per_s`` through the guard and stops
    the loop; cleanup releases the backend; shutdown does what is left of these. A run ended
    by deactivate is not resumed (:class:`~piezo_stage_ros.nodes.health.StageLifecycle`).

    """

    def __init__(self, *, autostart: bool = True, **kwargs: Any) -> None:
        super().__init__('plant_node', **kwargs)
        self.binding = ParameterBinding(self, plant_table(), self._on_change)
        self.opts: PlantNodeParams = self.binding.objects[1]
        self.finished = Future()
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.lifecycle = StageLifecycle()
        self.check: Callable[[], str | None] | None = None
        # what connect_direct wired (applied by configure): ('direct', step) or ('servo', ...)
        self._wiring: tuple[Any, ...] | None = None
        self._timer: Any = None
        self._status_timer: Any = None
        self.servo: ServoLoop | ServoProcess | None = None
        self.malformed = 0
        self._before: dict[str, Any] | None = None
        self.ramp: dict[str, float] = {}
        self.diagnostics = DiagnosticsPublisher(self, DIAGNOSTICS_PERIOD_S)
        self.diagnostics.add(self._statuses)
        #: Called with the state's label as each transition begins and ends, and with
        #: ``'faulted'`` on a fault: peers in this process (the trajectory node's goals) learn
        #: it at once, in the transition's own call (across processes: ``~/transition_event``).
        self.on_state: list[Callable[[str], None]] = []
        if autostart:
            start_managed([self])

    #: Why the last transition failed ('' after a success).
    refused = ''

    def _build(self) -> None:
        stage, opts = self.binding.objects
        self.opts = opts
        self.guard = GuardedPlant(make_bridge(stage, opts), stage.chain, opts.command_timeout_s,
                                  slew_v_per_s=opts.watchdog.slew_v_per_s,
                                  sample_period_s=1.0 / stage.sample_rate_hz)
        self._trip_log = TripLog(stage.chain.safe_voltage_v)
        self.logic = PlantLogic(self.guard, mode=opts.mode, sample_rate_hz=stage.sample_rate_hz,
                                duration_s=opts.duration_s, resend_s=opts.lockstep.resend_s)
        # messages go out and come in as CDR bytes (core/contracts/cdr.py): rclpy message objects
        # cost more than the whole sample
        self._encoder = JointStateEncoder([wire.JOINT_NAME])
        self._pub = self.create_publisher(JointState, wire.POSITION, qos.LOOP_OUT)
        self._clock_pub = self.create_publisher(ClockMsg, wire.CLOCK, qos.CLOCK) \
            if self.logic.lockstep else None
        # /clock goes out only while someone listens (looked at every 1000 samples)
        self._clock_gate: Callable[[], bool] = Gate(self._clock_pub.get_subscription_count) \
            if self._clock_pub is not None else (lambda: False)
        self._status_pub = self.create_publisher(DiagnosticStatus, wire.STATUS, qos.STATUS)
        self._cmd_sub: Any = self.create_subscription(Float64, wire.COMMAND, self._on_command,
                                                      qos.LOOP, raw=True)
        self._direct: Callable[[Sample], float] | None = None
        self._position_gate: Callable[[], bool] = lambda: True
        self.servo = None
        self._peers: Callable[[list[ServoSample]], None] | None = None
        self._servo_reported = False
        # real time: what the plant held over each sample, stamped with it, for the bag
        # (stage/applied, JointState effort; wire.APPLIED): published from the executor
        self._applied_pub = None if self.logic.lockstep else self.create_publisher(
            JointState, wire.APPLIED, qos.LOOP_OUT)
        self._applied_encoder = JointStateEncoder([wire.JOINT_NAME], effort=True)
        self._applied_gate: Callable[[], bool] = Gate(
            self._applied_pub.get_subscription_count, every=50) \
            if self._applied_pub is not None else (lambda: False)
        self._held_since: int | None = None
        # direct real time (attach_servo): every sample on stage/block; the per-sample topics
        # leave out what an overloaded executor cannot afford, counted
        self._block_pub: Any = None
        self._handover: Handover | None = None
        if not self.logic.lockstep:
            # real time: the servo loop's thread owns the sample clock (nodes/servo.py); the
            # executor only starts it and publishes what it measured, in batches
            # the plant alone: y_k goes out from the servo thread as soon as it is measured,
            # for a controller in another node to answer before the next sample
            self.servo = self._make_servo(None, None, self._publish_sample)
        self._status_timer = self.create_timer(opts.status_period_s, self.publish_status,
                                               clock=self._steady)
        self._t_start = 0.0
        self._matched_at: float | None = None
        self._sample: Sample | None = None
        self.get_logger().info(
            f'{opts.mode} at {stage.sample_rate_hz:g} Hz, backend {opts.backend}, plant '
            f'{stage.plant.model} + {stage.hysteresis.model}'
            + (f', {self.logic.total} samples' if self.logic.total else ''))

    def _start_timer(self) -> None:
        # the loop's timer, as the wiring asks (wall (steady) time: simulation time stands
        # still while the plant waits)
        if self._timer is not None:
            self._timer.cancel()
        if self._direct is not None and self.logic.lockstep:
            tick = self._direct_lockstep_tick
            period = 0.001
        elif self.logic.lockstep:
            tick, period = self._lockstep_tick, 0.005
        else:
            tick, period = self._servo_tick, SERVO_TICK_S
        self._timer = self.create_timer(period, tick, clock=self._steady)

    def _transition(self, name: str, action: Callable[[], str | None],
                    previous: LifecycleState) -> TransitionCallbackReturn:
        # rclpy turns an exception in a transition into ERROR without a word: log it here
        started = time.monotonic()
        self._tell(self.state)
        try:
            refused = action()
        except Exception as exc:  # noqa: BLE001 -- the transition fails with the reason
            refused = f'{type(exc).__name__}: {exc}'
        self.refused = refused or ''
        took_ms = (time.monotonic() - started) * 1e3
        if refused:
            self.get_logger().error(f'{name} refused: {refused}')
            self._tell(previous.label)  # rclpy goes back to it
            return TransitionCallbackReturn.FAILURE
        self.get_logger().info(f'{name}: done in {took_ms:.1f} ms')
        self._tell(_AFTER[name])
        return TransitionCallbackReturn.SUCCESS

    @property
    def state(self) -> str:
        """Return the lifecycle state's label (``'unconfigured'``, ``'active'`` ...)."""
        return str(self._state_machine.current_state[1])

    def _tell(self, state: str) -> None:
        for listener in self.on_state:
            listener(state)

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Build the backend, the publishers and the loop; check the controller."""
        return self._transition('configure', self._configure, state)

    def _configure(self) -> str | None:
        refused = self.lifecycle.configure()
        if refused is None and self.check is not None:
            refused = self.check()
        if refused is not None:
            return refused
        self._build()
        if self._wiring is not None:
            self._wire()
        self.lifecycle.configured_ok()
        return None

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Start the loop: lockstep answering, or the real-time servo."""
        return self._transition('activate', self._activate, state)

    def _activate(self) -> str | None:
        refused = self.lifecycle.activate()
        if refused is not None:
            return refused
        self._start_timer()
        self.lifecycle.activated()
        return None

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Ramp to the safe voltage at the slew through the guard, then stop the loop."""
        if isinstance(self.servo, ServoLoop) and self._t_start and not self.finished.done():
            # a servo thread runs the peers' logic: the ramp takes over its samples before the
            # peers hear of the deactivate, so that the goals they end there are not also
            # played to their end by the loop (a cancel ends a slow goal in a sample or two)
            self.guard.wind_down()
        return self._transition('deactivate', self._deactivate, state)

    def _deactivate(self) -> str | None:
        self.lifecycle.deactivated()
        if self._timer is not None:
            self._timer.cancel()
        if self.finished.done() or self.logic.done and self.servo is None:
            return None  # the run is over: the stop drove the safe voltage already
        slew = self.opts.watchdog.slew_v_per_s
        servo = self.servo
        if servo is None or not self._t_start:
            # lockstep (or a servo never started): no more answers; the ramp's samples are
            # stepped here, through the guard, not published
            from_v = self.guard.applied_v
            self.logic.done, self.logic.waiting = True, False
            samples, largest = self.guard.ramp_to_safe()
            self.ramp = {'from_v': from_v, 'samples': float(samples), 'max_step_v': largest,
                         'slew_step_v': slew * self.logic.period_s}
        else:
            if isinstance(servo, ServoProcess):
                servo.change('wind_down', None)
            else:
                self.guard.wind_down()
            # the ramp's length at the slew from the amplifier's farthest end, plus the time to
            # notice the end
            wait_s = max(abs(self.guard.high_v - self.guard.safe_v),
                         abs(self.guard.low_v - self.guard.safe_v)) / slew + 2.0
            end = time.monotonic() + wait_s
            while not servo.finished and time.monotonic() < end:
                self._hand_on(servo.take_batch())
                time.sleep(0.002)
            if not servo.finished:
                servo.stop()
                return f'the ramp did not end within {wait_s:.3f} s: stopped at once'
            self._hand_on(servo.take_batch())
            trips = servo.take_trips()
            self._log_trips([t for t in trips if not t.wind_down], final=True)
            # the guard's record of the ramp, from the voltage where it began
            wound = [t for t in trips if t.wind_down]
            ramp = wound[-1] if wound else None
            self.ramp = {'from_v': ramp.from_v if ramp else self.guard.safe_v,
                         'samples': float(ramp.ramp_samples if ramp else 0),
                         'max_step_v': ramp.max_step_v if ramp else 0.0,
                         'slew_step_v': slew * self.logic.period_s}
        self.get_logger().info(
            f'deactivated: ramped from {self.ramp["from_v"]:.6g} V to the safe voltage '
            f'{self.guard.safe_v:g} V in {self.ramp["samples"]:.0f} samples, largest step '
            f'{self.ramp["max_step_v"]:.6g} V (slew step {self.ramp["slew_step_v"]:.6g} V)')
        return None

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Release the backend and destroy the publishers, subscriptions and timers."""
        return self._transition('cleanup', self._cleanup, state)

    def _cleanup(self) -> str | None:
        self._release()
        for timer in (self._timer, self._status_timer):
            if timer is not None:
                self.destroy_timer(timer)
        self._timer = self._status_timer = None
        for pub in (self._pub, self._clock_pub, self._status_pub, self._applied_pub,
                    self._block_pub):
            if pub is not None:
                self.destroy_publisher(pub)
        if self._cmd_sub is not None:
            self.destroy_subscription(self._cmd_sub)
        self.servo = None
        self.lifecycle.cleaned_up()
        return None

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Deactivate and clean up as needed, then end the node's run."""
        def shutdown() -> str | None:
            if self.lifecycle.active:
                self._deactivate()
            if self.lifecycle.configured:
                self._cleanup()
            if not self.finished.done():
                self.finished.set_result({'shutdown': True})
            return None
        return self._transition('shutdown', shutdown, state)

    def _statuses(self) -> list[Status]:
        name, hw_id = self.get_name(), hardware_id(self.get_namespace())
        state = 'active' if self.lifecycle.active else (
            'inactive' if self.lifecycle.configured else 'unconfigured')
        if not self.lifecycle.configured:
            return [Status(OK, f'{name}: loop', f'{state}: no backend connected', hw_id,
                           (('state', state), ('backend', self.opts.backend)))]
        stats = self.stats()
        before, self._before = self._before, stats
        # a servo process runs its own guard: what it applied comes with its figures
        servo = self.servo
        local = not isinstance(servo, ServoProcess)
        applied = servo.held_v if isinstance(servo, ServoProcess) else self.guard.applied_v
        phase = self.guard.phase if local and self.lifecycle.active else 'track'
        loop = loop_status(name, hw_id, stats, before, state)
        return [replace(loop, values=loop.values + (('backend', self.opts.backend),)),
                watchdog_status(name, hw_id, stats, before, applied, phase)]

    def _on_change(self, old: Sequence[Any], new: Sequence[Any]) -> None:
        opts: PlantNodeParams = new[1]
        if not self.lifecycle.configured:
            self.opts = opts  # taken by the next configure
            return
        # applied between two samples: every callback of this node runs on one executor thread
        self.guard.watchdog.timeout_s = opts.command_timeout_s
        self.guard.slew_v_per_s = opts.watchdog.slew_v_per_s
        if isinstance(self.servo, ServoProcess):
            self.servo.change('set', ('plant.watchdog.timeout_s', opts.command_timeout_s))
            self.servo.change('set', ('plant.slew_v_per_s', opts.watchdog.slew_v_per_s))
        self.logic.resend_s = opts.lockstep.resend_s
        if opts.status_period_s != self.opts.status_period_s:
            self._status_timer.cancel()
            self._status_timer = self.create_timer(opts.status_period_s, self.publish_status,
                                                   clock=self._steady)
        self.opts = opts

    def _publish(self, sample: Sample) -> None:
        sec, nanosec = wire.ns_to_stamp(sample.stamp_ns)
        if self._clock_pub is not None and self._clock_gate():
            self._clock_pub.publish(encode_clock(sec, nanosec))
        if self._position_gate():
            self._pub.publish(self._encoder.encode(sec, nanosec, (sample.position_m,)))

    def attach_direct(self, step: Callable[[Sample], float]) -> None:
        """
        Take each command from ``step(sample)`` by call instead of from ``stage/command``.

        For the nodes composed in one process (``stage_servo --direct``): the sample goes from
        node to node by call, as rclcpp's intra-process communication does, and the topics are
        published for outside subscribers (a recorder) only. ``step`` returns u_k for y_k.
        Applied now when the node is configured, else by its configure.
        """
        self._wiring = ('direct', step)
        if self.lifecycle.configured:
            self._wire()

    def _wire(self) -> None:
        assert self._wiring is not None
        kind, *args = self._wiring
        self.destroy_subscription(self._cmd_sub)
        self._cmd_sub = None
        if kind == 'direct':
            self._direct = args[0]
            self._position_gate = Gate(self._pub.get_subscription_count)
            if self.lifecycle.active and self.logic.lockstep:
                self._start_timer()
            return
        trajectory, controller, publish, process = args
        self.servo = process if process is not None else \
            self._make_servo(trajectory, controller)
        self._peers = publish
        recording = self.opts.recording
        if recording.block:
            self._block_pub = self.create_publisher(Float64MultiArray, wire.BLOCK, qos.BLOCK)
            self._handover = Handover.from_params(recording, self.logic.rate_hz)
        # looked at every 50 batches (0.1 s) as the per-sample gates look every 1000 samples
        self._position_gate = Gate(self._pub.get_subscription_count, every=50)

    def _make_servo(self, trajectory: TrajectoryLogic | None,
                    controller: ControllerLogic | None,
                    on_sample: Callable[[ServoSample], None] | None = None) -> ServoLoop:
        opts = self.opts
        return ServoLoop(self.guard, trajectory, controller, sample_rate_hz=self.logic.rate_hz,
                         duration_s=opts.duration_s,
                         pacer=Pacer(round(1e9 / self.logic.rate_hz),
                                     spin_ns=round(opts.servo.spin_us * 1000)),
                         capacity=backlog_samples(opts.recording, self.logic.rate_hz),
                         on_sample=on_sample)

    def _publish_sample(self, s: ServoSample) -> None:
        sec, nanosec = wire.ns_to_stamp(s.stamp_ns)
        self._pub.publish(self._encoder.encode(sec, nanosec, (s.position_m,)))

    def attach_servo(self, trajectory: TrajectoryLogic, controller: ControllerLogic,
                     publish: Callable[[list[ServoSample]], None],
                     process: ServoProcess | None = None) -> None:
        """
        Real time in one process (``--direct``): the servo loop runs trajectory and controller.

        Each sample's y_k, x_d and u_k are computed in the servo thread, in the order of one
        sample; ``publish(batch)`` publishes the reference, command and diagnostics of a batch
        for outside subscribers, from the executor. Parameter changes reach the logic objects
        as ever and apply at the next sample boundary. With ``process`` (``servo.process``),
        that process runs the loop on its own copies of the logic (built from the same
        parameters) and the peers forward their changes to it. Applied now when the node is
        configured, else by its configure.
        """
        self._wiring = ('servo', trajectory, controller, publish, process)
        if self.lifecycle.configured:
            self._wire()

    def _servo_tick(self) -> None:
        try:
            servo = self.servo
            assert servo is not None
            if self._t_start == 0.0:
                self._t_start = time.monotonic()
                # at once, before the first sample: real time by messages cannot hold the rate
                advice = realtime_warning(self.opts.mode, self._peers is not None,
                                          self.logic.rate_hz)
                if advice is not None:
                    self.get_logger().warning(advice)
                opts = self.opts.servo
                start_ns = self.get_clock().now().nanoseconds
                if isinstance(servo, ServoProcess):
                    servo.start(start_ns)  # sets its own scheduling up, in its process
                    return
                # one interpreter for both: the loop hands the executor the lock once two ticks
                # have gone by without one
                servo.share_interpreter(2 * SERVO_TICK_S)
                servo.start_thread(start_ns, lambda: servo_setup(opts, servo.pacer.period_ns),
                                   since_ns=time.monotonic_ns())
                return
            finished = servo.finished
            self._hand_on(servo.take_batch())
            self._log_trips(servo.take_trips())
            if not self._servo_reported and (servo.setup_report or finished):
                self._servo_reported = True
                for key, text in servo.setup_report.items():
                    # one call site per severity: rclpy refuses a second severity at a site
                    if text.startswith('applied'):
                        self.get_logger().info(f'servo {key}: {text}')
                    else:
                        self.get_logger().warning(f'servo {key}: {text}')
            if finished:
                if servo.error is not None:
                    self._fault(servo.error)
                else:
                    self._finish()
        except KeyboardInterrupt:
            return
        except Exception as exc:  # noqa: BLE001
            self._fault(exc)

    def _log_trips(self, trips: list[Trip], final: bool = False) -> None:
        # every trip line is a warning (one call site, one severity)
        for line in self._trip_log.lines(trips, time.monotonic(), final=final,
                                         slew_v_per_s=self.opts.watchdog.slew_v_per_s,
                                         period_s=self.logic.period_s):
            self.get_logger().warning(line)

    def _log_figures(self, head: str, stats: dict[str, Any]) -> None:
        # the severity comes from run_verdict; one call site per severity (rclpy refuses a
        # second severity at one call site)
        level, reasons = run_verdict(stats)
        figures = ', '.join(f'{k}={v}' for k, v in stats.items())
        if level == 'warn':
            self.get_logger().warning(f'{head}, degraded ({"; ".join(reasons)}): {figures}')
        else:
            self.get_logger().info(f'{head}: {figures}')

    def _hand_on(self, batch: SampleBatch) -> None:
        # every sample into the blocks first; then the per-sample topics, without the oldest
        # of a backlog the executor cannot afford one message at a time (counted)
        if batch.size == 0:
            return
        first = 0
        if self._handover is not None:
            messages, first = self._handover.take(batch)
            for raw in messages:
                self._block_pub.publish(raw)
            if first:
                # the first sample published ends the hold that began at the one before it
                self._held_since = int(batch.ints[first - 1, 1])
        samples = samples_of(batch, first)
        self._publish_batch(samples)
        self._publish_applied(samples)

    def _publish_applied(self, batch: list[ServoSample]) -> None:
        # sample k's applied_v was held over the sample that ended at t_k: it goes out stamped
        # with the sample taken before (the start of that hold), as stage/command is stamped
        gate = self._applied_gate()
        encode, publish = self._applied_encoder.encode, self._applied_pub
        since = self._held_since
        for s in batch:
            if since is not None and gate and publish is not None:
                sec, nanosec = wire.ns_to_stamp(since)
                publish.publish(encode(sec, nanosec, (s.applied_v,)))
            since = s.stamp_ns
        self._held_since = since

    def _publish_batch(self, batch: list[ServoSample]) -> None:
        if self._peers is None:
            return  # the plant alone published each sample from the servo thread
        if self._position_gate():
            publish, encode = self._pub.publish, self._encoder.encode
            for s in batch:
                sec, nanosec = wire.ns_to_stamp(s.stamp_ns)
                publish(encode(sec, nanosec, (s.position_m,)))
        self._peers(batch)

    def _start(self) -> None:
        now = time.monotonic()
        start_ns = 0 if self.logic.lockstep else self.get_clock().now().nanoseconds
        self._t_start = now
        self._publish(self.logic.start(now, start_ns))
        if self.logic.done:
            self._finish()

    def _lockstep_tick(self) -> None:
        try:
            if self.logic.index < 0:
                now = time.monotonic()
                if self._matched_at is None:
                    if self._pub.get_subscription_count() >= self.opts.lockstep.subscribers:
                        self._matched_at = now
                if self._matched_at is not None and \
                        now - self._matched_at >= self.opts.lockstep.settle_s:
                    self._start()
                return
            again = self.logic.resend_due(time.monotonic())
            if again is not None:
                self._publish(again)
        except KeyboardInterrupt:
            return  # Ctrl-C inside a callback: rclpy shuts down, the runner stops cleanly
        except Exception as exc:  # noqa: BLE001 -- any fault: safe voltage, then report
            self._fault(exc)

    def _direct_lockstep_tick(self) -> None:
        # a batch of samples per tick (about 2 ms), so that parameter and service requests
        # are served between batches
        try:
            logic, step = self.logic, self._direct
            assert step is not None
            now = time.monotonic()
            if logic.index < 0:
                # the controller and trajectory are called directly: wait only for outsiders
                outside = max(self.opts.lockstep.subscribers - 2, 0)
                if self._matched_at is None and self._pub.get_subscription_count() >= outside:
                    self._matched_at = now
                if self._matched_at is None or now - self._matched_at < \
                        self.opts.lockstep.settle_s:
                    return
                self._start()
                self._sample = logic.last_sample
            deadline = now + 0.002
            sample = self._sample
            while sample is not None and not logic.done:
                sample = logic.on_command(step(sample), now)
                if sample is not None:
                    self._publish(sample)
                now = time.monotonic()
                if now > deadline:
                    break
            self._sample = sample
            if logic.done:
                self._finish()
        except KeyboardInterrupt:
            return
        except Exception as exc:  # noqa: BLE001
            self._fault(exc)

    def _on_command(self, data: bytes) -> None:
        command_v = decode_or_drop(self, wire.COMMAND, decode_float64, data)
        if command_v is None:
            return
        if not self.lifecycle.active:
            self.logic.unexpected += 1  # deactivated: the guard's ramp holds the stage
            return
        try:
            if self.servo is not None:
                # real time: held from the servo loop's next sample on
                if self._t_start and not self.servo.done:
                    self.guard.command(command_v, time.monotonic())
                else:
                    self.logic.unexpected += 1
                return
            sample = self.logic.on_command(command_v, time.monotonic())
            if sample is not None:
                self._publish(sample)
            elif self.logic.done and self.logic.lockstep:
                self._finish()
        except KeyboardInterrupt:
            return
        except Exception as exc:  # noqa: BLE001
            self._fault(exc)

    def stats(self) -> dict[str, Any]:
        """Return the counters, with the loop rate reached so far (and the lateness)."""
        out = self.logic.stats()
        index = self.logic.index
        if self.servo is not None:
            out.update(self.servo.stats())
            index = self.servo.index
            out['index'] = index
            # what the real-time setup applied or was refused, e.g. servo_affinity
            out.update({f'servo_{k}': v for k, v in self.servo.setup_report.items()})
        if self._handover is not None:
            out.update(self._handover.stats())
        out['malformed'] = self.malformed
        elapsed = time.monotonic() - self._t_start if self._t_start else 0.0
        samples = max(index + 1, 0)
        out['wall_s'] = round(elapsed, 6)
        out['samples_per_s'] = round(samples / elapsed, 1) if elapsed > 0 else 0.0
        out['real_time_factor'] = round(samples * self.logic.period_s / elapsed, 4) \
            if elapsed > 0 else 0.0
        return out

    def publish_status(self) -> None:
        """Publish the counters on ``stage/status``."""
        stats = self.stats()
        # under load the loop degrades with counts: any of them makes the status a warning
        worse = ('late', 'watchdog_trips', 'late_half_period', 'skipped', 'queue_overruns',
                 'ring_missed', 'live_dropped')
        level = DiagnosticStatus.WARN if any(stats.get(k) for k in worse) \
            else DiagnosticStatus.OK
        self._status_pub.publish(DiagnosticStatus(
            level=level, name=self.get_fully_qualified_name(),
            message=f'{self.opts.mode}: {stats["index"] + 1} samples',
            hardware_id=self.opts.backend,
            values=[KeyValue(key=k, value=str(v)) for k, v in stats.items()]))

    def _finish(self) -> None:
        if self.finished.done():
            return
        if self._timer is not None:
            self._timer.cancel()
        if self.servo is not None:
            self.servo.stop()
            self._hand_on(self.servo.take_batch())
            if self._handover is not None:
                for raw in self._handover.finish(self.servo.held_v):
                    self._block_pub.publish(raw)
            if self._held_since is not None and self._applied_pub is not None \
                    and self._peers is not None and self._applied_gate():
                # the last sample's command, held until the stop drove the safe voltage (the
                # plant alone does not know what it would have held next: left out)
                sec, nanosec = wire.ns_to_stamp(self._held_since)
                self._applied_pub.publish(self._applied_encoder.encode(
                    sec, nanosec, (self.servo.held_v,)))
        self.logic.stop()
        if self.servo is not None:
            self._log_trips(self.servo.take_trips(), final=True)
            self._log_table()
        self.publish_status()
        stats = self.stats()
        self._log_figures('run complete', stats)
        self.finished.set_result(stats)

    def _log_table(self) -> None:
        # the servo process ran the controller and wrote its learned table itself
        # (one call site per severity: rclpy refuses a second severity at a site)
        line = self.servo.table_line if isinstance(self.servo, ServoProcess) else None
        if line is None:
            return
        if line.startswith('learned table written'):
            self.get_logger().info(line)
        else:
            self.get_logger().error(line)

    def _fault(self, exc: BaseException) -> None:
        if self.servo is not None:
            self.servo.stop()
        self.guard.fault(exc)
        self.logic.done = True
        if not self.context.ok():
            # Ctrl-C shut the context down under a running callback: a stop, not a fault
            if not self.finished.done():
                self.finished.set_result(self.logic.stats())
            return
        if self._timer is not None:
            self._timer.cancel()
        self.get_logger().error(f'fault, safe voltage driven: {exc}')
        self._tell('faulted')
        if not self.finished.done():
            err = exc if isinstance(exc, PiezoStageError) else PiezoStageError(repr(exc))
            self.finished.set_exception(err)

    def _release(self) -> None:
        # drive the safe voltage and release the backend (a servo process does both itself)
        if isinstance(self.servo, ServoProcess):
            stopped = self.servo.started and not self.finished.done()
            self.servo.close()
            if stopped:
                # stopped before its end (Ctrl-C, shutdown): its counters still go out
                self._log_trips(self.servo.take_trips(), final=True)
                self._log_figures('servo process stopped', self.stats())
                self._log_table()
        elif self.servo is not None:
            self.servo.stop()
        self.logic.stop()

    def destroy_node(self) -> None:
        """Drive the safe voltage, release the backend, then destroy the node."""
        try:
            if self.lifecycle.configured:
                self._release()
        finally:
            super().destroy_node()


def main(args: Sequence[str] | None = None) -> int:
    """Run the plant node (console script ``plant_node``)."""
    return run('plant_node', [('plant', PlantNode)], args,
               'The stage model or hardware bridge of piezo_stage_ros.')
