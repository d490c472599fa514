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

"""The UDP bridge against its target emulator on loopback, and the safety rules around it."""

from __future__ import annotations

import math
import socket
import struct
import subprocess
import sys
import threading
import time

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.loop.closed_loop import run
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.stage import Stage, StageParams
from piezo_stage_ros.hardware import udp
from piezo_stage_ros.hardware.bridge import BridgeError, ModelBridge
from piezo_stage_ros.hardware.emulator import main as emulator_main
from piezo_stage_ros.hardware.emulator import TargetEmulator
from piezo_stage_ros.hardware.safety import clamp_command, GuardedPlant, Watchdog
from piezo_stage_ros.nodes.logic import ControllerLogic, PlantLogic, TrajectoryLogic
import pytest

PARAMS = StageParams.from_flat({'plant.model': 'reduced'})


@pytest.fixture
def emulator():
    emu = TargetEmulator(PARAMS, idle_timeout_s=5.0).start_thread()
    yield emu
    emu.close()


def connected(emu: TargetEmulator, **kwargs) -> udp.UdpBridge:
    bridge = udp.UdpBridge('127.0.0.1', emu.port, timeout_s=kwargs.pop('timeout_s', 1.0),
                           **kwargs)
    bridge.open()
    return bridge


def test_packets_round_trip_and_malformed_ones_are_refused():
    assert udp.REQUEST.size == 20 and udp.REPLY.size == 24 and udp.VERSION == 3
    assert udp.unpack_request(udp.pack_request(udp.COMMAND, 7, 1.25)) == (udp.COMMAND, 7, 1.25,
                                                                         ())
    # commands ahead follow the header, their count in it
    data = udp.pack_request(udp.COMMAND, 7, 1.25, np.array([1.5, -0.25]))
    assert len(data) == 20 + 16 and data[16:20] == (2).to_bytes(4, 'little')
    assert udp.unpack_request(data) == (udp.COMMAND, 7, 1.25, (1.5, -0.25))
    assert udp.unpack_request(data[:-1]) is None and udp.unpack_request(data + bytes(8)) is None
    with pytest.raises(ParameterError, match='commands ahead'):
        udp.pack_request(udp.COMMAND, 1, 0.0, np.zeros(udp.MAX_AHEAD + 1))
    assert udp.unpack_request(udp.pack_request(udp.HELLO, 2 ** 32 + 3, 0.0))[1] == 3
    reply = udp.pack_reply(udp.COMMAND, 9, 3.8e-6, udp.STATUS_CLAMPED, 2)
    assert udp.unpack_reply(reply) == (udp.COMMAND, 9, 3.8e-6, udp.STATUS_CLAMPED, 2)
    # little-endian, magic first
    assert reply[:4] == b'PZ\x03\x82' and reply[4:8] == (9).to_bytes(4, 'little')
    assert udp.unpack_reply(reply[:-1]) is None
    assert udp.unpack_reply(b'XX' + reply[2:]) is None
    assert udp.unpack_reply(reply[:2] + b'\x01' + reply[3:]) is None
    assert udp.unpack_request(reply) is None
    assert udp.unpack_reply(udp.pack_request(udp.COMMAND, 1, 0.0) + bytes(8)) is None


def test_bridge_through_emulator_equals_the_model(emulator):
    bridge = connected(emulator)
    stage = Stage(PARAMS)
    assert bridge.safe_start(0.0) == stage.reset()
    commands = np.linspace(0.0, 6.0, 200) + 0.3 * np.sin(np.arange(200))
    got = []
    for u in commands:
        bridge.write_voltage(float(u))
        got.append(bridge.read_position())
    # bit for bit: the emulator steps the same Stage kernel on the same commands and the UDP
    # frames carry float64 as they are
    np.testing.assert_array_equal(got, stage.run_open_loop(commands))
    assert bridge.stats()['lost'] == 0 and bridge.stats()['target_missing'] == 0
    bridge.safe_stop(0.0)
    assert emulator._thread is not None
    emulator._thread.join(5.0)
    assert emulator.stop_reason == 'stop'
    assert emulator._voltage_v == 0.0


def test_lost_replies_are_counted_and_the_last_position_held():
    with TargetEmulator(PARAMS, drop_reply_every=4) as emu:
        # a reply that comes must not count as lost: on a loaded machine the emulator's thread
        # can wait tens of ms for a core, so the timeout is 0.5 s (each dropped reply costs it)
        bridge = connected(emu, timeout_s=0.5)
        bridge.safe_start(0.0)
        positions = []
        for k in range(12):
            bridge.write_voltage(0.5 * k)
            positions.append(bridge.read_position())
        stats = bridge.stats()
        assert stats['lost'] == 3 and emu.dropped == 3
        # every 4th sample repeats the one before it
        assert positions[3] == positions[2] and positions[7] == positions[6]
        bridge.safe_stop(0.0)


def test_consecutive_losses_raise_and_a_silent_target_fails_start():
    silent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    silent.bind(('127.0.0.1', 0))
    try:
        bridge = udp.UdpBridge('127.0.0.1', silent.getsockname()[1], timeout_s=0.01,
                               hello_attempts=2)
        with pytest.raises(BridgeError, match='no answer from the target .* 2 HELLO'):
            bridge.safe_start(0.0)
    finally:
        silent.close()
    with TargetEmulator(PARAMS, drop_reply_every=1) as emu:
        # 0.2 s, not 10 ms: the HELLO replies of safe_start do come, on a loaded machine late
        bridge = connected(emu, timeout_s=0.2, max_consecutive_losses=2)
        bridge.safe_start(0.0)
        bridge.read_position()
        bridge.read_position()
        with pytest.raises(BridgeError, match='3 samples in a row lost'):
            bridge.read_position()
        bridge.safe_stop(0.0)


def test_target_counts_missing_and_ignores_old_requests():
    with TargetEmulator(PARAMS) as emu:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.settimeout(2.0)
        sock.connect(('127.0.0.1', emu.port))
        sock.send(udp.pack_request(udp.HELLO, 1, 0.0))
        assert udp.unpack_reply(sock.recv(64))[4] == 0
        sock.send(udp.pack_request(udp.COMMAND, 2, 1.0))
        assert udp.unpack_reply(sock.recv(64))[4] == 0
        sock.send(udp.pack_request(udp.COMMAND, 5, 1.0))  # 3 and 4 never arrived
        kind, seq, _, status, missing = udp.unpack_reply(sock.recv(64))
        assert (kind, seq, status, missing) == (udp.COMMAND, 5, 0, 2)
        steps = emu.stage.steps
        sock.send(udp.pack_request(udp.COMMAND, 4, 1.0))  # late: never stepped twice
        sock.send(udp.pack_request(udp.COMMAND, 6, 50.0))
        kind, seq, _, status, missing = udp.unpack_reply(sock.recv(64))
        assert seq == 6 and status == udp.STATUS_CLAMPED and missing == 2
        assert emu.stage.steps == steps + 1
        sock.send(udp.pack_request(9, 7, 0.0))
        assert udp.unpack_reply(sock.recv(64))[3] == udp.STATUS_REFUSED
        sock.send(b'garbage')
        sock.send(udp.pack_request(udp.STOP, 8, 0.0))
        assert udp.unpack_reply(sock.recv(64))[0] == udp.STOP
        sock.close()


def test_bridge_skips_stale_and_malformed_replies():
    target = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    target.bind(('127.0.0.1', 0))
    target.settimeout(5.0)

    def serve() -> None:
        for _ in range(2):
            data, peer = target.recvfrom(256)
            _, seq, _, _ = udp.unpack_request(data)
            kind = udp.unpack_request(data)[0]
            target.sendto(udp.pack_reply(kind, seq - 1, -1.0, 0, 0), peer)  # stale
            target.sendto(b'nonsense', peer)
            target.sendto(udp.pack_reply(kind, seq, 1e-6 * seq, 0, 0), peer)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    bridge = udp.UdpBridge('127.0.0.1', target.getsockname()[1], timeout_s=2.0)
    assert bridge.safe_start(0.0) == 1e-6
    assert bridge.read_position() == 2e-6
    thread.join(5.0)
    assert bridge.stale == 2 and bridge.malformed == 2 and bridge.lost == 0
    target.close()


def test_guarded_udp_plant_clamps_before_sending(emulator):
    guard = GuardedPlant(connected(emulator), PARAMS.chain, command_timeout_s=0.01)
    guard.start(0.0)
    guard.step(25.0)
    guard.step(math.nan)
    guard.step(-7.0)
    assert guard.clamped == 3
    assert guard.bridge.stats()['target_clamped'] == 0  # nothing out of range left the host
    assert emulator._voltage_v == PARAMS.chain.amplifier_min_v
    guard.stop()
    guard.stop()
    emulator._thread.join(5.0)
    assert emulator.stop_reason == 'stop'


@pytest.mark.parametrize('noise', [0.0, 2e-9])
def test_lockstep_through_udp_equals_the_offline_runner(noise):
    params = PARAMS.with_flat({'chain.sensor_noise_std_m': noise, 'seed': 11})
    emulator = TargetEmulator(params).start_thread()
    dt = params.sample_time_s
    cp = ControllerParams.from_flat({'type': 'pi'})
    tp = TrajectoryParams.from_flat({'kind': 'sine', 'sine.frequency_hz': 20.0})
    rec = run(Stage(params), build_controller(cp, dt), make_trajectory(tp), duration_s=0.05,
              record_diagnostics=False)
    assert rec.command_v.min() > -2.0 and rec.command_v.max() < 10.0  # no clamping involved
    plant = PlantLogic(GuardedPlant(connected(emulator), params.chain), mode='lockstep',
                       sample_rate_hz=1.0 / dt, duration_s=0.05)
    traj = TrajectoryLogic(make_trajectory(tp), sample_rate_hz=1.0 / dt)
    ctrl = ControllerLogic(build_controller(cp, dt))
    positions = []
    sample = plant.start(0.0)
    while sample is not None:
        positions.append(sample.position_m)
        xd, vd = traj.on_position(sample.stamp_ns)
        ctrl.on_position(sample.stamp_ns, sample.position_m, 0.0)
        sample = plant.on_command(ctrl.on_reference(sample.stamp_ns, xd, vd).voltage_v, 0.0)
    # bit for bit: lockstep runs the offline runner's scalar stage and controller arithmetic in
    # the same order, sample by sample (see test_lockstep.py)
    np.testing.assert_array_equal(positions, rec.position_m)
    plant.stop()
    emulator.close()


def test_emulator_stops_by_itself_and_binds_loopback_only():
    with pytest.raises(ParameterError, match="'host' = '0.0.0.0' is not loopback"):
        TargetEmulator(PARAMS, host='0.0.0.0')
    with pytest.raises(ParameterError, match='idle_timeout_s'):
        TargetEmulator(PARAMS, idle_timeout_s=0.0)
    idle = TargetEmulator(PARAMS, idle_timeout_s=0.05)
    assert idle.serve() == 'idle'
    limited = TargetEmulator(PARAMS, max_requests=2, idle_timeout_s=5.0)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for seq in (1, 2):
        sock.sendto(udp.pack_request(udp.COMMAND, seq, 0.0), ('127.0.0.1', limited.port))
    assert limited.serve() == 'limit'
    sock.close()


def test_emulator_command_line(tmp_path, capsys):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('plant_node:\n  ros__parameters:\n    seed: -1\n')
    assert emulator_main(['--config', str(bad), '--port', '0']) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'seed' = -1" in err[0]
    proc = subprocess.Popen([sys.executable, '-m', 'piezo_stage_ros.hardware.emulator',
                             '--port', '0', '--idle-timeout-s', '20'],
                            stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith('stage_emulator: listening on 127.0.0.1:')
        port = int(line.rsplit(':', 1)[1])
        bridge = udp.UdpBridge('127.0.0.1', port, timeout_s=2.0)
        assert bridge.safe_start(0.0) == Stage(StageParams()).reset()
        bridge.safe_stop(0.0)
        assert proc.wait(timeout=20) == 0
        assert 'stopped (stop)' in proc.stdout.read()
    finally:
        proc.kill()
        proc.stdout.close()


def test_clamp_command_and_watchdog():
    assert clamp_command(1.0, -2.0, 10.0, 0.5) == (1.0, False)
    assert clamp_command(11.0, -2.0, 10.0, 0.5) == (10.0, True)
    assert clamp_command(-3.0, -2.0, 10.0, 0.5) == (-2.0, True)
    assert clamp_command(math.inf, -2.0, 10.0, 0.5) == (0.5, True)
    dog = Watchdog(0.01)
    assert not dog.expired(100.0)  # not armed yet
    dog.arm(0.0)
    assert not dog.expired(0.01)
    assert dog.expired(0.0101) and dog.expired(0.5)
    assert dog.trips == 1
    dog.feed(0.5)
    assert not dog.expired(0.505)
    assert dog.expired(0.52) and dog.trips == 2
    with pytest.raises(ParameterError, match="'command_timeout_s' = 0.0"):
        Watchdog(0.0)


class RecordingBridge:
    """A backend that records what it is told to drive."""

    def __init__(self, fail_stop: bool = False) -> None:
        self.written: list[float] = []
        self.started_with: float | None = None
        self.stopped_with: list[float] = []
        self.fail_stop = fail_stop

    def open(self) -> None:
        pass

    def safe_start(self, safe_voltage_v: float) -> float:
        self.started_with = safe_voltage_v
        return 1e-6

    def write_voltage(self, voltage_v: float) -> None:
        self.written.append(voltage_v)

    def read_position(self) -> float:
        return 2e-6

    def safe_stop(self, safe_voltage_v: float) -> None:
        self.stopped_with.append(safe_voltage_v)
        if self.fail_stop:
            raise OSError('device gone')

    def stats(self):
        return {'n': len(self.written)}


def test_guard_drives_safe_voltage_at_start_ramps_to_it_on_silence_and_at_stop():
    chain = StageParams.from_flat({'chain.safe_voltage_v': 1.5}).chain
    bridge = RecordingBridge()
    # 2 V a sample at most while the watchdog drives (2e4 V/s x 0.1 ms)
    guard = GuardedPlant(bridge, chain, command_timeout_s=0.01, slew_v_per_s=2e4,
                         sample_period_s=1e-4)
    assert guard.start(0.0) == 1e-6 and bridge.started_with == 1.5
    guard.sample(0.0001)
    guard.command(4.0, 0.0002)
    guard.sample(0.0002)
    guard.command(40.0, 0.0003)
    guard.sample(0.0003)
    guard.sample(0.0004)       # no new command: held, counted late
    for k in range(6):         # silent for > 10 ms: ramp to the safe voltage, then stay
        guard.sample(0.0104 + k * 1e-4)
    guard.command(9.0, 0.011)  # commands are back: followed from 1.5 V at the same rate
    for k in range(4):
        guard.sample(0.011 + k * 1e-4)
    assert guard.trip is None and guard.phase == 'recover'  # reached on the last one
    guard.command(3.0, 0.0114)  # from then on each command as it comes
    guard.sample(0.0114)
    assert bridge.written == pytest.approx([1.5, 4.0, 10.0, 10.0, 8.0, 6.0, 4.0, 2.0, 1.5, 1.5,
                                            3.5, 5.5, 7.5, 9.0, 3.0])
    stats = guard.stats()
    assert stats['late'] == 10 and stats['watchdog_trips'] == 1
    assert (stats['ramp_samples'], stats['safe_samples'], stats['recovery_samples']) == (5, 1, 4)
    assert stats['watchdog_max_step_v'] == pytest.approx(2.0)
    assert stats['clamped'] == 1 and stats['bridge_n'] == 15
    (trip,) = guard.ended_trips
    assert trip.ended == 'commands' and trip.samples == 10 and trip.from_v == 10.0
    assert trip.silence_s == pytest.approx(0.0101) and trip.duration_s == pytest.approx(0.0009)
    guard.stop()
    guard.stop()
    assert bridge.stopped_with == [1.5]


class QueueingBridge(RecordingBridge):
    """A backend with a queue that records each write and each queue sent after it."""

    def __init__(self) -> None:
        super().__init__()
        self.events: list[tuple[str, float | list[float]]] = []

    def write_voltage(self, voltage_v: float) -> None:
        super().write_voltage(voltage_v)
        self.events.append(('write', voltage_v))

    def write_commands(self, voltage_v: float, ahead_v) -> None:
        super().write_voltage(voltage_v)
        self.events.append(('write', voltage_v))
        self.events.append(('queue', [float(a) for a in ahead_v]))

    def write_ahead(self, ahead_v) -> None:
        self.events.append(('ahead', [float(a) for a in ahead_v]))


def test_guard_releases_the_answer_first_and_its_commands_ahead_after():
    bridge = QueueingBridge()
    guard = GuardedPlant(bridge, StageParams().chain, command_timeout_s=0.01,
                         slew_v_per_s=2e4, sample_period_s=1e-4)
    guard.start(0.0)
    guard.command(4.0, 0.0)
    guard.release(0.0)                  # the answer leaves at once, alone
    guard.follow([4.5, 20.0])           # its commands ahead after it, clamped as any
    assert guard.sample(0.0) == 2e-6    # measures only: decided and written already
    guard.sample(0.0001)                # no new command: the first prediction, the rest queued
    assert bridge.events == [('write', 4.0), ('ahead', [4.5, 10.0]), ('write', 4.5),
                             ('queue', [10.0])]
    assert guard.stats()['predicted_samples'] == 1
    # the watchdog's sample is no command's: nothing follows it
    bridge.events.clear()
    guard.release(0.05)
    guard.follow([1.0, 2.0])
    guard.sample(0.05)
    # (its write empties the backend's queue: the watchdog plays no predictions)
    assert guard.trip is not None and bridge.events[1:] == [('queue', [])]


def test_guard_fault_drives_safe_voltage_and_never_raises():
    bridge = RecordingBridge(fail_stop=True)
    guard = GuardedPlant(bridge, StageParams().chain)
    guard.start(0.0)
    guard.fault(RuntimeError('boom'))
    assert bridge.stopped_with == [0.0]
    unstarted = RecordingBridge()
    GuardedPlant(unstarted, StageParams().chain).stop()
    assert unstarted.stopped_with == []


def test_model_bridge_passes_commands_unclamped_to_its_own_chain():
    guard = GuardedPlant(ModelBridge(PARAMS), PARAMS.chain)
    reference = Stage(PARAMS)
    assert guard.start(0.0) == reference.reset()
    for u in (-2.5, 12.0, math.nan, 3.0):
        assert guard.step(u) == reference.step(u)
    assert guard.clamped == 0 and guard.bridge.stats()['faults'] == 1


class HostPacedClock:
    """
    The emulator's clock in a test: it moves to the next due time only once the host is done.

    The target's pacer sleeps on it; each sleep waits (at most 5 s) for the host to signal that
    it answered (or chose not to answer) the sample, so the run is the same on any machine.
    """

    def __init__(self) -> None:
        self.now = 0
        self.host_done = threading.Event()
        self.free = False  # at the end: run freely until the STOP arrives
        self.stall_ns = 0  # added to the next sleep once: the target's own clock stalls

    def clock(self) -> int:
        return self.now

    def sleep(self, seconds: float) -> None:
        if not self.free:
            self.host_done.wait(5.0)
            self.host_done.clear()
        self.now += round(seconds * 1e9) + self.stall_ns
        self.stall_ns = 0


def _paced_target() -> tuple[HostPacedClock, TargetEmulator, threading.Thread]:
    """Start an emulator that paces its own 10 kHz clock on a :class:`HostPacedClock`."""
    from piezo_stage_ros.hardware.pacing import Pacer
    clock = HostPacedClock()
    emu = TargetEmulator(PARAMS, idle_timeout_s=5.0)
    target = threading.Thread(target=emu.serve_paced, daemon=True,
                              args=(Pacer(100_000, clock=clock.clock, sleep=clock.sleep,
                                          spin_ns=0),))
    target.start()
    return clock, emu, target


@pytest.mark.parametrize('spin', [False, True])
@pytest.mark.parametrize('unanswered', [(), (3, 4)])
def test_paced_target_holds_the_newest_command_and_counts_missing_ones(unanswered, spin):
    clock, emu, target = _paced_target()
    # spin: the host polls its socket without blocking (as the servo loop's host does)
    bridge = udp.UdpStreamBridge('127.0.0.1', emu.port, timeout_s=5.0, spin=spin)
    positions = [bridge.safe_start(0.0)]
    indices = [bridge.sample_index]
    applied, held = [], 0.0
    for k in range(10):
        if k not in unanswered:
            held = 1.0 + 0.5 * k
            bridge.write_voltage(held)
        applied.append(held)  # what the target holds over the next sample
        clock.host_done.set()
        positions.append(bridge.read_position())
        indices.append(bridge.sample_index)
    # what the target reported with sample 10 (it keeps counting while it runs freely to STOP)
    missing = bridge.stats()['target_missing']
    clock.free = True
    clock.host_done.set()
    bridge.safe_stop(0.0)
    target.join(5.0)
    assert indices == list(range(11)) and emu.stop_reason == 'stop'
    assert missing == len(unanswered) and bridge.stats()['gaps'] == 0
    model = Stage(PARAMS)
    expected = [model.reset()] + [model.step(v) for v in applied]
    np.testing.assert_array_equal(positions, expected)
    # each answered sample's answer latency is counted once
    assert bridge.answer.samples == 10 - len(unanswered)
    assert bridge.stats()['answer_max_us'] == round(bridge.answer.max_ns / 1000, 1)


def test_another_protocol_version_is_refused_clearly_on_both_sides(capsys):
    # the version-1 request of an old host (16 bytes, no commands ahead)
    old = struct.pack('<2sBBId', b'PZ', 1, udp.HELLO, 1, 0.0)
    assert udp.unpack_request(old) is None and udp.foreign_version(old) == 1
    with TargetEmulator(PARAMS) as emu:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.settimeout(2.0)
        sock.connect(('127.0.0.1', emu.port))
        sock.send(old)
        kind, seq, _, status, _ = udp.unpack_reply(sock.recv(64))
        assert (kind, seq) == (udp.HELLO, 1)
        assert status == udp.STATUS_REFUSED | udp.STATUS_VERSION and emu.refused_version == 1
        sock.close()
    assert 'protocol version 1 (this target speaks version 3)' in capsys.readouterr().err
    # a target of another version: the host names both versions
    target = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    target.bind(('127.0.0.1', 0))
    target.settimeout(5.0)

    def serve() -> None:
        data, peer = target.recvfrom(256)
        target.sendto(struct.pack('<2sBBIdII', b'PZ', 2, udp.HELLO | 0x80, 1, 0.0, 0, 0), peer)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    bridge = udp.UdpBridge('127.0.0.1', target.getsockname()[1], timeout_s=2.0)
    with pytest.raises(BridgeError, match='speaks protocol version 2, this host version 3'):
        bridge.safe_start(0.0)
    thread.join(5.0)
    target.close()


@pytest.mark.parametrize('late', [False, True])
def test_paced_target_plays_the_commands_ahead_over_unanswered_samples(late):
    clock, emu, target = _paced_target()
    bridge = udp.UdpStreamBridge('127.0.0.1', emu.port, timeout_s=5.0)
    positions = [bridge.safe_start(0.0)]
    applied = []
    unanswered = (3, 4, 5)
    for k in range(10):
        command = 1.0 + 0.5 * k
        ahead = [command + 0.1 * j for j in range(1, 3)]  # two commands ahead
        if k not in unanswered:
            bridge.write_commands(command, ahead)
            applied.append(command)
        elif k == 5 and late:
            # the answer to sample 4 comes while sample 5 is due: the target applies its
            # prediction for the sample after 5 (one ahead of the one it answers)
            bridge._send(udp.COMMAND, 4, 9.0, [9.1, 9.2])
            applied.append(9.1)
        else:
            # the target plays the predictions of the command answering sample 2, then holds
            # the last one
            applied.append(applied[2] + 0.1 * min(k - 2, 2))
        clock.host_done.set()
        positions.append(bridge.read_position())
    # what the target reported with sample 10 (it runs freely to STOP after)
    predicted, missing = (bridge.stats()[k] for k in ('target_predicted', 'target_missing'))
    clock.free = True
    clock.host_done.set()
    bridge.safe_stop(0.0)
    target.join(5.0)
    assert predicted == len(unanswered) and missing == len(unanswered)
    model = Stage(PARAMS)
    expected = [model.reset()] + [model.step(v) for v in applied]
    np.testing.assert_array_equal(positions, expected)


def test_paced_target_keeps_its_queue_and_moves_it_onto_a_newer_command():
    # version 3: the queue comes with the answer to sample 0 only, sent again after it
    # (write_ahead); the answers to 1 and 2 come without one; 3, 4 and 5 go unanswered
    clock, emu, target = _paced_target()
    bridge = udp.UdpStreamBridge('127.0.0.1', emu.port, timeout_s=5.0)
    positions = [bridge.safe_start(0.0)]
    commands = [1.0 + 0.5 * k for k in range(10)]
    queue = [commands[0] + 0.1 * j for j in range(1, 5)]  # for the answers to 1 .. 4
    applied = []
    for k in range(10):
        if k == 0:
            bridge.write_voltage(commands[0])
            bridge.write_ahead(queue)
            applied.append(commands[0])
        elif k in (3, 4, 5):
            # the queue's prediction for the answer to k (the last one after the queue),
            # shifted by what the newest command (the answer to 2) made of its own prediction
            applied.append(queue[min(k, len(queue)) - 1] + (commands[2] - queue[1]))
        else:
            bridge.write_voltage(commands[k])
            applied.append(commands[k])
        clock.host_done.set()
        positions.append(bridge.read_position())
    predicted = bridge.stats()['target_predicted']
    clock.free = True
    clock.host_done.set()
    bridge.safe_stop(0.0)
    target.join(5.0)
    assert predicted == 3 and bridge.resent == 1
    model = Stage(PARAMS)
    expected = [model.reset()] + [model.step(v) for v in applied]
    np.testing.assert_array_equal(positions, expected)


def test_stream_host_answers_the_newest_sample_and_overtakes_a_backlog():
    # a host that fell behind finds four samples queued: it answers the newest, and the
    # three it overtakes are neither gaps nor answered late one by one
    target = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    target.bind(('127.0.0.1', 0))
    target.settimeout(5.0)
    bridge = udp.UdpStreamBridge('127.0.0.1', target.getsockname()[1], timeout_s=5.0)
    bridge.open()
    bridge._send(udp.STREAM, 0, 0.0)
    _, peer = target.recvfrom(256)
    for k, position in enumerate((1e-6, 2e-6, 3e-6, 4e-6)):
        target.sendto(udp.pack_reply(udp.STREAM, k, position, 0, 0), peer)
    time.sleep(0.2)  # all four are queued before the host reads
    assert bridge.read_position() == 4e-6
    assert (bridge.sample_index, bridge.overtaken, bridge.gaps) == (3, 3, 0)
    bridge.write_voltage(1.5)
    kind, seq, value, ahead = udp.unpack_request(target.recv(256))
    assert (kind, seq, value, ahead) == (udp.COMMAND, 3, 1.5, ())
    # a number that never came is a gap, not overtaken
    target.sendto(udp.pack_reply(udp.STREAM, 5, 6e-6, 0, 0), peer)
    assert bridge.read_position() == 6e-6
    assert (bridge.sample_index, bridge.overtaken, bridge.gaps) == (5, 3, 1)
    bridge._sock.close()
    target.close()


def test_stream_host_follows_with_commands_ahead_when_it_keeps_up():
    # the rule that spares a late host its commands ahead, on a scripted clock
    now = [0]
    bridge = udp.UdpStreamBridge('127.0.0.1', 9, clock=lambda: now[0], period_ns=100_000)
    bridge.sample_index, bridge.arrival_ns, bridge._ahead_index = 10, 0, 9
    now[0] = 40_000
    assert bridge.ahead_wanted(128)  # answered within half a period
    now[0] = 60_000
    assert not bridge.ahead_wanted(128)  # past half a period
    bridge.spin, bridge.waited, now[0] = True, False, 10_000
    assert not bridge.ahead_wanted(128)  # spinning, the sample came before the host looked
    bridge.waited = True
    assert bridge.ahead_wanted(128)
    bridge.waited, now[0] = False, 90_000
    bridge.sample_index = 9 + 32
    assert bridge.ahead_wanted(128) and not bridge.ahead_wanted(132)  # every count // 4


def test_request_buffer_packs_commands_ahead_aligned_and_as_read_one_by_one():
    from piezo_stage_ros.core.control.ahead import Ahead
    x = np.linspace(0.0, 1e-5, 300)
    v = np.cos(np.linspace(0.0, 3.0, 300)) * 1e-3
    ahead = Ahead(x, v, 40, 168, 0.25, (5.0e5, 2.0), -1.0, 2.0)
    request = udp.RequestBuffer()
    size = request.pack(udp.COMMAND, 5, 0.5, ahead)
    assert request._ahead.flags.aligned and size == udp.REQUEST.size + 8 * 128
    kind, seq, value, values = udp.unpack_request(bytes(request.view[:size]))
    assert (kind, seq, value) == (udp.COMMAND, 5, 0.5)
    assert list(values) == list(ahead)  # bit for bit, clipped alike
    assert max(values) == 2.0 and min(values) < 1.0  # the top ones clipped
    # the buffer is reused: a shorter request after a longer one carries only its own
    size = request.pack(udp.COMMAND, 6, 0.5, [1.0, 2.0])
    assert udp.unpack_request(bytes(request.view[:size]))[3] == (1.0, 2.0)


def test_after_a_stall_of_its_own_clock_the_target_plays_the_queue_not_a_stale_answer():
    # the target's clock stalls for three samples after the host answered sample 1: those
    # samples play the queue (the answer was not read yet), and the sample after them, whose
    # previous sample the host never saw, plays the queue's prediction moved onto that answer,
    # not the answer held four samples late
    clock, emu, target = _paced_target()
    bridge = udp.UdpStreamBridge('127.0.0.1', emu.port, timeout_s=5.0)
    positions = [bridge.safe_start(0.0)]
    c0, c1, c5 = 1.0, 1.2, 2.0
    queue = [c0 + 0.1 * j for j in range(1, 5)]  # for the answers to 1 .. 4
    bridge.write_commands(c0, queue)
    clock.host_done.set()
    positions.append(bridge.read_position())  # sample 1: applies c0
    bridge.write_voltage(c1)
    clock.stall_ns = 3 * 100_000
    clock.host_done.set()
    positions.append(bridge.read_position())  # sample 5, after 2, 3 and 4 on the queue
    assert (bridge.sample_index, bridge.gaps) == (5, 3)
    bridge.write_voltage(c5)
    clock.host_done.set()
    positions.append(bridge.read_position())  # sample 6: applies c5
    clock.free = True
    clock.host_done.set()
    bridge.safe_stop(0.0)
    target.join(5.0)
    model = Stage(PARAMS)
    expected = [model.reset(), model.step(c0)]
    for v in queue[:3]:
        model.step(v)  # samples 2, 3, 4: nobody measures them
    expected += [model.step(queue[3] + (c1 - queue[0])), model.step(c5)]
    np.testing.assert_array_equal(positions, expected)
    assert emu.pacer is not None and emu.pacer.stats.skipped == 3
