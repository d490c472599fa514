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

"""The servo loop of several axes and protocol version 4, with an injected clock."""

from __future__ import annotations

import math
import subprocess
import sys

from fake_clock import FakeClock
import numpy as np
from piezo_stage_ros import cli
from piezo_stage_ros.core.config.axes import axes_loop_config
from piezo_stage_ros.core.control.axes import AxesController
from piezo_stage_ros.core.loop.axes import run_axes
from piezo_stage_ros.core.loop.axes_servo import AxesReference, REFERENCE_CHUNK
from piezo_stage_ros.core.model.axes import AxesStage
from piezo_stage_ros.hardware import udp
from piezo_stage_ros.hardware.axes import AxesGuard, AxesModelBridge
from piezo_stage_ros.hardware.bridge import BridgeError
from piezo_stage_ros.hardware.emulator import main as emulator_main
from piezo_stage_ros.hardware.emulator import TargetEmulator
from piezo_stage_ros.hardware.emulator_axes import AxesTargetEmulator
from piezo_stage_ros.hardware.pacing import Pacer
from piezo_stage_ros.hardware.udp_axes import (
    max_ahead,
    pack_axes_reply,
    pack_axes_request,
    STATUS_AXES,
    UdpAxesBridge,
    unpack_axes_reply,
    unpack_axes_request,
)
from piezo_stage_ros.nodes.servo_axes import axes_servo_from_config
import pytest

PERIOD = 100_000  # ns, 10 kHz
# every axis a 200 Hz sine (50-sample periods): the learning runs within a short test
EACH = ['trajectory_node:scan.kind=each', 'trajectory_node:kind=sine',
        'trajectory_node:sine.frequency_hz=200.0']


def loop_of(config: str, params: list[str]):
    each = [] if 'raster' in params else EACH
    return axes_loop_config(cli.read_config([config], each + [p for p in params
                                                              if p != 'raster']))


def offline(loop, duration_s):
    ctrl = AxesController.build(loop.controllers, loop.stage, compensate=loop.compensate)
    return run_axes(AxesStage(loop.stage), ctrl, loop.trajectories(), duration_s=duration_s)


def paced(servo, per_read=300):
    clock = FakeClock(per_read=per_read)
    servo.pacer = Pacer(PERIOD, clock=clock, sleep=clock.sleep)
    return clock


def assert_equal_to_offline(batch, records, samples):
    assert batch.k.tolist() == list(range(samples))
    for j, rec in enumerate(records):
        for got, want in ((batch.position_m, rec.position_m), (batch.command_v, rec.command_v),
                          (batch.reference_m, rec.reference_m),
                          (batch.velocity_mps, rec.reference_velocity_mps)):
            np.testing.assert_array_equal(got[:, j], want)


@pytest.mark.parametrize('config, params', [
    ('xyz_stage.yaml', []),                                   # 3 axes, learning, coupled
    ('xyz_stage.yaml', ['raster']),                           # the file's raster frame
    ('xy_stage.yaml', ['controller_node:axes.y.feedforward.mode=none']),  # y predicted
    ('default.yaml', ['plant_node:axes.names=[x]']),          # one axis
])
def test_axes_servo_on_time_equals_the_offline_loop(config, params):
    loop = loop_of(config, params)
    servo = axes_servo_from_config(loop, 0.03)
    assert servo.commands_ahead == 128
    paced(servo)
    servo.run(start_ns=3 * PERIOD)
    assert servo.error is None and servo.done
    batch = servo.take_batch()
    n = loop.stage.n
    assert batch.position_m.shape == (300, n) and batch.axes == loop.stage.names
    assert batch.number.tolist() == list(range(300))
    assert batch.stamp_ns.tolist() == [(3 + k) * PERIOD for k in range(300)]
    records = offline(loop, 0.03)
    assert_equal_to_offline(batch, records, 300)
    for j, rec in enumerate(records):
        np.testing.assert_array_equal(batch.true_position_m[:, j], rec.true_position_m)
    # each sample held the command of the one before it (the guard clamps nothing here)
    np.testing.assert_array_equal(batch.applied_v[1:], batch.command_v[:-1])
    assert servo.stats()['predicted_samples'] == 0


def test_commands_ahead_of_every_axis_are_played_over_a_stall():
    loop = loop_of('xyz_stage.yaml', [])
    servo = axes_servo_from_config(loop, 0.05)
    clock = paced(servo)
    # a clock read near sample 180 (about 330 reads a sample) comes 6.5 periods late
    clock.stalls = {60_000: 6 * PERIOD + PERIOD // 2}
    handed = []
    commands = servo.commands
    step = commands.step
    ctrls = servo.axes_controller.controllers

    def spy(index, y, r, v, count):
        out, ahead = step(index, y, r, v, count)
        # each axis' own prediction now; the rows handed on are computed only when read
        handed.append((index, np.array([c.predict(count) for c in ctrls])))
        return out, ahead
    # spied on after the warm-up (its dry samples run on copies)
    servo.on_setup = lambda report: setattr(commands, 'step', spy)
    stepped = []
    stage = servo.guard.bridge.stage
    stage_step = stage.step
    stage.step = lambda u: (stepped.append(list(u)), stage_step(u))[1]
    servo.run()
    assert servo.error is None
    stats = servo.stats()
    skipped = stats['skipped']
    assert skipped >= 5
    # every grid sample was stepped by the model, taken or not
    assert len(stepped) == servo.guard.bridge.steps == 499
    # per axis: the skipped samples and the first one taken after them applied predictions
    assert stats['predicted_samples'] == 3 * (skipped + 1)
    ks = [k for k, _ in handed]
    gap = next(i for i in range(1, len(ks)) if ks[i] - ks[i - 1] > 1)
    last = ks[gap - 1]
    assert 100 < last < 400 and ks[gap] == last + skipped + 1
    before, ahead = handed[gap - 2][1], handed[gap - 1][1]
    assert ahead.shape == (3, 128)
    # the model holds a command from the next sample's write on (stepped[k] holds u_k): the
    # command of the sample before the stall was not written yet, so the skipped samples
    # play each axis' queue written last (the predictions of the command before it), and the
    # sample taken after them applies the late command's own prediction for it
    for i in range(skipped):
        assert stepped[last + i] == before[:, i].tolist()
    assert stepped[last + skipped] == ahead[:, skipped - 1].tolist()


def guard_of(loop, timeout_s=0.001, slew=1000.0):
    bridge = AxesModelBridge(loop.stage)
    return AxesGuard(bridge, [a.chain for a in loop.stage.axes], loop.stage.names,
                     timeout_s, slew_v_per_s=slew, sample_period_s=1e-4)


def test_a_silent_axis_ramps_every_axis_and_is_named():
    loop = loop_of('xyz_stage.yaml', [])
    guard = guard_of(loop)
    t = 0.0
    guard.start(t)
    volts = [2.0, 3.0, 4.0]  # inside the amplifier input range of every axis
    step_v = 1000.0 * 1e-4
    applied = []
    for k in range(200):
        t = k * 1e-4
        guard.sample(t)
        applied.append(guard.applied_v)
        # axis y's controller gives NaN from sample 50 on: refused, its watchdog starves
        u = [volts[0], math.nan if k >= 50 else volts[1], volts[2]]
        guard.command(u, t)
    assert guard.refused == [0, 150, 0]
    assert guard.trips == 1 and guard.causes[0].axes == ('y',)
    # the silence that tripped it: longer than the timeout by at most one sample
    assert 0.001 < guard.causes[0].silence_s <= 0.0011 + 1e-12
    a = np.array(applied)
    # sample 0 holds the safe voltage; the first sample after it off the command: the trip's
    trip = 1 + int(np.argmax(a[1:, 0] != volts[0]))
    assert 55 <= trip <= 65
    # every axis left its command at the same sample, toward its safe voltage, within the slew
    safe = np.array(guard.safe_v)
    for j in range(3):
        assert a[trip, j] != volts[j] and abs(a[trip, j] - safe[j]) < abs(volts[j] - safe[j])
        assert np.all(np.abs(np.diff(a[trip - 1:, j])) <= step_v * (1 + 1e-9))
    assert {g.phase for g in guard.axes} <= {'ramp', 'safe'}
    # commands of every axis again: the axes return together, then track
    for k in range(200, 1400):
        t = k * 1e-4
        guard.sample(t)
        guard.command(volts, t)
    guard.sample(1400 * 1e-4)
    assert list(guard.applied_v) == volts
    ended = list(guard.ended_trips)
    assert sorted(name for name, _ in ended) == ['x', 'y', 'z']
    assert all(trip.ended == 'commands' for _, trip in ended)
    guard.stop()


# --- protocol version 4 --------------------------------------------------------------------

def test_version_4_packets_round_trip():
    ahead = np.arange(6.0).reshape(3, 2)
    data = pack_axes_request(udp.COMMAND, 7, [1.0, -2.0, 3.5], ahead)
    assert len(data) == 16 + 8 * 3 * 3 and data[2] == 4
    kind, seq, axes, values, got = unpack_axes_request(data)
    assert (kind, seq, axes, values) == (udp.COMMAND, 7, 3, (1.0, -2.0, 3.5))
    np.testing.assert_array_equal(got, ahead)
    reply = pack_axes_reply(udp.COMMAND, 7, [1e-6, 2e-6], 8, 3)
    assert unpack_axes_reply(reply) == (udp.COMMAND, 7, 2, (1e-6, 2e-6), 8, 3)
    # version 3 reads neither, and version 4 reads no version-3 datagram
    assert udp.unpack_request(data) is None and udp.unpack_reply(reply) is None
    assert unpack_axes_request(udp.pack_request(udp.COMMAND, 1, 1.0)) is None
    assert unpack_axes_request(data[:-8]) is None
    # the datagram of version 3 at its largest, shared by the axes
    assert max_ahead(1) == udp.MAX_AHEAD and max_ahead(3) == 332
    with pytest.raises(Exception, match='commands ahead'):
        pack_axes_request(udp.COMMAND, 1, [0.0] * 3, np.zeros((3, 333)))


def test_axes_servo_through_the_version_4_emulator_equals_the_offline_loop():
    loop = loop_of('xy_stage.yaml', [])
    with AxesTargetEmulator(loop.stage, idle_timeout_s=5.0) as emu:
        bridge = UdpAxesBridge('127.0.0.1', emu.port, loop.stage.n, timeout_s=1.0)
        servo = axes_servo_from_config(loop, 0.02, bridge)
        paced(servo)
        servo.run()
        assert servo.error is None
        batch = servo.take_batch()
    assert_equal_to_offline(batch, offline(loop, 0.02), 200)
    assert emu.missing == 0 and emu.stop_reason == 'stop'


def test_version_and_axis_count_mismatches_are_refused_naming_both():
    loop = loop_of('xyz_stage.yaml', [])
    with AxesTargetEmulator(loop.stage) as emu:
        # a version-3 host at a target of three axes
        with pytest.raises(BridgeError, match='speaks protocol version 4, this host version 3'):
            udp.UdpBridge('127.0.0.1', emu.port, timeout_s=1.0,
                          hello_attempts=1).safe_start(0.0)
        # a host of two axes
        with pytest.raises(BridgeError, match='has 3 axes, this host 2'):
            UdpAxesBridge('127.0.0.1', emu.port, 2, timeout_s=1.0,
                          hello_attempts=1).safe_start([0.0, 0.0])
        assert emu.refused_version == 1 and emu.refused_axes == 1
        # a host of three axes is served
        host = UdpAxesBridge('127.0.0.1', emu.port, 3, timeout_s=1.0)
        y0 = host.safe_start([0.0, 0.0, 0.0])
        assert len(y0) == 3 and all(math.isfinite(y) for y in y0)
        host.safe_stop([0.0, 0.0, 0.0])
    # a version-4 host at a one-axis target of version 3
    with TargetEmulator(loop.stage.axes[0]) as one:
        with pytest.raises(BridgeError, match='speaks protocol version 3, this host version 4'):
            UdpAxesBridge('127.0.0.1', one.port, 1, timeout_s=1.0,
                          hello_attempts=1).safe_start([0.0])
    assert STATUS_AXES == 32


def test_emulator_command_line_serves_the_axes_of_its_files(capsys):
    assert emulator_main(['--config', 'xy_stage.yaml', '--port', '0', '--paced']) == 2
    assert 'request-reply' in capsys.readouterr().err
    proc = subprocess.Popen([sys.executable, '-m', 'piezo_stage_ros.hardware.emulator',
                             '--config', 'xy_stage.yaml', '--port', '0',
                             '--idle-timeout-s', '20'], stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith('stage_emulator: listening on 127.0.0.1:')
        port = int(line.rsplit(':', 1)[1])
        assert proc.stdout.readline().strip() == \
            "stage_emulator: axes ['x', 'y'], protocol version 4"
        bridge = UdpAxesBridge('127.0.0.1', port, 2, timeout_s=2.0)
        stage = loop_of('xy_stage.yaml', []).stage
        assert bridge.safe_start([0.0, 0.0]) == AxesStage(stage).reset()
        bridge.safe_stop([0.0, 0.0])
        assert proc.wait(timeout=20) == 0
        assert 'stopped (stop)' in proc.stdout.read()
    finally:
        proc.kill()
        proc.stdout.close()


@pytest.mark.parametrize('chunk', [1, 2, 7, 1000, REFERENCE_CHUNK])
def test_references_read_ahead_in_chunks_are_the_trajectories_values(chunk):
    loop = loop_of('xyz_stage.yaml', ['raster'])
    trs = loop.trajectories()
    dt = loop.stage.sample_time_s
    ref = AxesReference(trs, dt, chunk=chunk)
    # past the end of the first chunk (the servo's own: two of them), then a jump
    end = max(1500, chunk + 500)
    k = np.arange(end + 600)
    want = [tr.evaluate(k * dt) for tr in trs]
    # in order, as the servo reads them (the next chunk evaluated over the current one's end)
    for index in list(range(end)) + [end + 550, end + 599]:  # and a jump, as after a stall
        x, v = ref.at(index)
        assert x == tuple(float(w[0][index]) for w in want)
        assert v == tuple(float(w[1][index]) for w in want)
    for axis in range(3):
        x, v = ref.window(axis, 40, 128)
        np.testing.assert_array_equal(x, want[axis][0][41:169])
        np.testing.assert_array_equal(v, want[axis][1][41:169])


def test_a_reference_of_the_wrong_shape_is_refused_naming_its_axis():
    # the servo's references are checked as the offline runner checks them, axis named
    from piezo_stage_ros.core.contracts.errors import PiezoStageError

    class Scalar:
        def evaluate(self, t):
            return 0.0, 0.0

    loop = loop_of('xy_stage.yaml', [])
    trs = loop.trajectories()
    ref = AxesReference([trs[0], Scalar()], loop.stage.sample_time_s, chunk=10,
                        names=loop.stage.names)
    with pytest.raises(PiezoStageError, match="axis 'y' returned arrays of shape"):
        ref.at(0)
    with pytest.raises(PiezoStageError, match="axis 'y' returned arrays of shape"):
        ref.window(1, 0, 5)


def test_samples_drained_one_by_one_are_the_batch_rows():
    loop = loop_of('xy_stage.yaml', [])
    got = []
    servo = axes_servo_from_config(loop, 0.005, on_sample=got.append)
    paced(servo)
    servo.run(start_ns=10**18 + 7)
    samples = servo.drain(20)
    batch = servo.take_batch()
    assert len(samples) == 20 and batch.number.tolist() == list(range(20, 50))
    assert got[:20] == samples and servo.stats()['queue_overruns'] == 0
    # stamps stay integers [ns] beyond float64's 2**53
    assert batch.stamp_ns[0] == 10**18 + 7 + 20 * PERIOD and batch.stamp_ns.dtype == np.int64
    for s, i in zip(got[20:], range(30)):
        assert (s.k, s.stamp_ns, s.lateness_ns) == (batch.k[i], batch.stamp_ns[i],
                                                    batch.lateness_ns[i])
        for field, column in (('positions_m', batch.position_m), ('commands_v', batch.command_v),
                              ('references_m', batch.reference_m),
                              ('velocities_mps', batch.velocity_mps),
                              ('applied_v', batch.applied_v),
                              ('true_positions_m', batch.true_position_m)):
            assert getattr(s, field) == tuple(column[i].tolist())


def test_a_wind_down_ramps_every_axis_to_its_safe_voltage_and_ends_the_run():
    loop = loop_of('xyz_stage.yaml', [])
    servo = axes_servo_from_config(loop, 0.0)  # until stopped
    paced(servo)
    slew = loop.base.plant_node.watchdog.slew_v_per_s * 1e-4  # V a sample
    servo.boundary = lambda: (servo.index != 100 or servo.guard.wind_down()) or True
    servo.run()
    assert servo.error is None and servo.done
    batch = servo.take_batch()
    applied = batch.applied_v
    # from the wind-down on: no command asked for, every axis moves by at most the slew a
    # sample, and the run ends once every axis applies its safe voltage
    down = batch.k > 101
    assert np.all(np.isnan(batch.command_v[down]))
    assert np.all(np.abs(np.diff(applied[100:], axis=0)) <= slew * (1 + 1e-9))
    assert applied[-1].tolist() == servo.guard.safe_v
    assert all(g.phase == 'safe' for g in servo.guard.axes)
    # one trip per axis, the wind-down's, ended by the stop (the watchdog is not looked at)
    assert [(a, t.wind_down, t.ended) for a, t in servo.guard.ended_trips] == [
        (a, True, 'stop') for a in ('x', 'y', 'z')]
    assert servo.guard.trips == 0


def test_what_the_run_froze_is_collectable_again_after_it():
    # the run moves what exists at its start out of the garbage collector's reach: after the
    # run, a cycle of that time that is dropped must be collected again, or every run leaves
    # its process all that it froze (a servo started again, a test session)
    import gc
    import weakref

    class Cycle:
        pass

    loop = loop_of('xy_stage.yaml', [])
    servo = axes_servo_from_config(loop, 0.002)
    paced(servo)
    cycle = Cycle()
    cycle.self = cycle  # type: ignore[attr-defined]
    alive = weakref.ref(cycle)
    servo.run(start_ns=3 * PERIOD)
    assert servo.error is None and servo.done
    del cycle
    gc.collect()
    assert alive() is None


@pytest.mark.parametrize('chains, names, wrong', [(1, 2, "'chains' = 1"),
                                                  (2, 1, "'names' = 1")])
def test_a_guard_of_another_axis_count_names_what_is_wrong(chains, names, wrong):
    from piezo_stage_ros.core.contracts.errors import ParameterError
    loop = loop_of('xy_stage.yaml', [])
    bridge = AxesModelBridge(loop.stage)
    with pytest.raises(ParameterError, match=f'{wrong} .*2, one per axis'):
        AxesGuard(bridge, [a.chain for a in loop.stage.axes][:chains], loop.stage.names[:names])


class _Executor:
    """The executor as the loop's turn event sees it: it takes its turn while waited for."""

    def __init__(self, take) -> None:
        self.take = take
        self.taken: list = []

    def clear(self) -> None:
        pass

    def set(self) -> None:
        pass

    def wait(self, timeout: float) -> bool:
        self.taken.append(self.take())
        return True


@pytest.mark.parametrize('take', ['drain', 'take_batch'])
def test_each_take_of_the_samples_of_several_axes_is_the_executors_turn(take):
    # drain and take_batch are the executor's turns, as the one-axis loop's: a loop whose
    # executor takes its samples in its turns hands the lock over once every `every` periods
    every = 10
    loop = loop_of('xy_stage.yaml', [])
    servo = axes_servo_from_config(loop, 0.05)
    paced(servo)
    servo.share_interpreter(every * PERIOD / 1e9)
    executor = _Executor(getattr(servo, take))
    servo._turn = executor  # type: ignore[assignment]
    servo.run(start_ns=7 * PERIOD)
    assert servo.error is None and len(executor.taken) == servo.handovers
    assert 500 // (every + 1) <= servo.handovers <= 500 // every
