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

"""The paced servo loop and its clock, with an injected clock: no wall time, no sleeps."""

from __future__ import annotations

import dataclasses
import math
import os
import threading
import time

from fake_clock import FakeClock
import numpy as np
from piezo_stage_ros.core.config.nodes import ServoParams
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.loop.closed_loop import run
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.stage import Stage, StageParams
from piezo_stage_ros.hardware import pacing
from piezo_stage_ros.hardware.bridge import ModelBridge
from piezo_stage_ros.hardware.pacing import LatenessStats, Pacer, realtime_setup, servo_setup
from piezo_stage_ros.hardware.safety import GuardedPlant
from piezo_stage_ros.nodes.logic import ControllerLogic, TrajectoryLogic
from piezo_stage_ros.nodes.servo import apply_change, servo_from_config, ServoLoop, ServoProcess
import pytest

PERIOD = 100_000  # ns, 10 kHz


# --- the clock -------------------------------------------------------------------------------

def test_pacer_sleeps_far_from_the_due_time_and_spins_close_to_it():
    clock = FakeClock(per_read=1_000)
    pacer = Pacer(PERIOD, clock=clock, sleep=clock.sleep, spin_ns=20_000)
    t0 = pacer.start()
    assert pacer.wait()[0] == 0  # due at the start
    for k in range(1, 6):
        index, late = pacer.wait()
        assert index == k
        # the clock advances 1 us per read: the first read at or past the due time returns
        assert 0 <= late < 1_000 and clock.now - late == t0 + k * PERIOD
    # one sleep per period, each ending 20 us (the spin margin) before the due time
    assert len(clock.sleeps) == 5
    assert all(s <= (PERIOD - 20_000) / 1e9 for s in clock.sleeps)
    assert pacer.stats.samples == 6 and pacer.stats.skipped == 0


def test_pacer_skips_after_a_stall_instead_of_bursting():
    clock = FakeClock(per_read=1_000)
    pacer = Pacer(PERIOD, clock=clock, sleep=clock.sleep, spin_ns=0)
    t0 = pacer.start()
    assert [pacer.wait()[0] for _ in range(2)] == [0, 1]
    # a stall: sample 2 is looked at 3.5 periods after its due time
    clock.now = t0 + 2 * PERIOD + 3 * PERIOD + PERIOD // 2
    index, late = pacer.wait()
    # samples 2, 3, 4 are gone; 5 is taken half a period late (+ one clock read), no burst
    assert (index, late) == (5, PERIOD // 2 + 1_000)
    assert pacer.stats.skipped == 3 and pacer.stats.late_half == 1
    assert pacer.wait()[0] == 6
    assert pacer.stats.samples == 4


def test_pacer_refuses_a_period_that_is_not_positive():
    with pytest.raises(ParameterError, match='period_ns'):
        Pacer(0)


def test_lateness_statistics_from_the_histogram():
    stats = LatenessStats(PERIOD, max_us=1000)
    for lateness_us in range(100):  # 0 .. 99 us, one each
        stats.add(lateness_us * 1000 + 500)
    stats.add(70_000)  # > T/2
    stats.add(5_000_000)  # beyond the histogram: the top bin, the maximum kept exactly
    stats.skip(4)
    s = stats.summary()
    # later than T/2 = 50 us: 50.5 ... 99.5 us (50 samples) and the two added last
    assert s['paced_samples'] == 102 and s['late_half_period'] == 52 and s['skipped'] == 4
    # the 51st of 102 values is 50.5 us: the upper edge of its 1 us bin
    assert s['lateness_p50_us'] == 51.0
    assert s['lateness_max_us'] == 5000.0
    assert stats.percentile_us(100.0) == 5000.0
    with pytest.raises(ParameterError):
        stats.percentile_us(101.0)


def test_realtime_setup_reports_what_it_applied_or_was_refused():
    # in a thread of its own: affinity and scheduler are the calling thread's (Linux), and the
    # test process must not keep them (its children, the emulator of a benchmark, would)
    out: dict = {}
    worker = threading.Thread(target=lambda: out.update(realtime_setup(cpus=[0],
                                                                       fifo_priority=1)))
    worker.start()
    worker.join()
    report = out
    assert set(report) == {'affinity', 'sched_fifo'}
    assert all(v.startswith(('applied', 'refused')) for v in report.values())
    assert realtime_setup() == {}


def test_realtime_setup_sets_the_nice_value_of_the_calling_thread_only():
    out: dict = {}
    before = os.getpriority(os.PRIO_PROCESS, 0)
    # one step up is permitted to anyone; the worker's value must not reach this thread
    worker = threading.Thread(target=lambda: out.update(
        realtime_setup(nice=min(before + 1, 19)),
        seen=os.getpriority(os.PRIO_PROCESS, 0)))
    worker.start()
    worker.join()
    assert out['nice'] == f'applied: {min(before + 1, 19)}' and out['seen'] == min(before + 1, 19)
    assert os.getpriority(os.PRIO_PROCESS, 0) == before


@pytest.mark.parametrize('spin_us, fifo, throttle, warned', [
    (200.0, 'applied: priority 1', (950_000, 1_000_000), True),
    (100.0, 'applied: priority 1', (950_000, 1_000_000), True),   # spins the whole period
    (30.0, 'applied: priority 1', (950_000, 1_000_000), False),   # sleeps most of it
    (200.0, 'refused: [Errno 1] Operation not permitted', (950_000, 1_000_000), False),
    (200.0, 'applied: priority 1', None, False),                  # throttling off (-1)
])
def test_servo_setup_warns_of_a_fifo_loop_the_kernel_will_throttle(monkeypatch, spin_us, fifo,
                                                                   throttle, warned):
    asked: dict = {}

    def fake_setup(**kwargs):
        asked.update(kwargs)
        return {'sched_fifo': fifo}

    monkeypatch.setattr(pacing, 'realtime_setup', fake_setup)
    monkeypatch.setattr(pacing, 'rt_throttling', lambda: throttle)
    opts = ServoParams(spin_us=spin_us, fifo_priority=1, cpu=1, nice=-5,
                       switch_interval_us=50.0)
    out = servo_setup(opts, PERIOD)
    # every option of servo.* reaches realtime_setup
    # us -> s is one multiplication: within half an ulp of 50e-6
    assert asked.pop('switch_interval_s') == pytest.approx(50e-6, rel=1e-15, abs=0.0)
    assert asked == {'cpus': [1], 'fifo_priority': 1, 'nice': -5}
    assert ('rt_throttling' in out) == warned
    if warned:
        assert out['rt_throttling'].startswith('warning') and 'stall of 50 ms every 1 s' in \
            out['rt_throttling'] and f'servo.spin_us = {spin_us:g}' in out['rt_throttling']


def test_rt_throttling_reads_the_kernel_settings():
    got = pacing.rt_throttling()
    try:
        with open('/proc/sys/kernel/sched_rt_runtime_us', encoding='ascii') as stream:
            runtime = int(stream.read())
    except OSError:
        assert got is None
        return
    assert got is None if runtime < 0 else (got is not None and got[0] == runtime)


# --- the servo loop --------------------------------------------------------------------------

STAGE = {'plant.model': 'reduced', 'chain.sensor_noise_std_m': 1e-9, 'seed': 3}
TRAJ = {'kind': 'sine', 'sine.frequency_hz': 50.0}


def servo(clock: FakeClock, duration_s: float, kind: str = 'rac',
          commands_ahead: int = 0) -> ServoLoop:
    params = StageParams.from_flat(STAGE)
    ctrl = build_controller(ControllerParams.from_flat({'type': kind}), 1e-4)
    return ServoLoop(GuardedPlant(ModelBridge(params), params.chain, 0.01),
                     TrajectoryLogic(make_trajectory(TrajectoryParams.from_flat(TRAJ)),
                                     sample_rate_hz=1e4, chunk_s=1.0),
                     ControllerLogic(ctrl, mode='realtime'), sample_rate_hz=1e4,
                     duration_s=duration_s,
                     pacer=Pacer(PERIOD, clock=clock, sleep=clock.sleep),
                     commands_ahead=commands_ahead)


@pytest.mark.parametrize('ahead', [0, 32])
@pytest.mark.parametrize('kind', ['rac', 'pi'])
def test_servo_loop_on_time_equals_the_offline_runner(kind, ahead):
    # with commands ahead too: a sample the loop takes applies the command, bit for bit
    loop = servo(FakeClock(per_read=300), 0.05, kind, ahead)
    loop.run(start_ns=7 * PERIOD)
    assert loop.error is None and loop.done
    got = loop.drain()
    params = StageParams.from_flat(STAGE)
    rec = run(Stage(params), build_controller(ControllerParams.from_flat({'type': kind}), 1e-4),
              make_trajectory(TrajectoryParams.from_flat(TRAJ)), duration_s=0.05,
              record_diagnostics=False)
    assert [s.k for s in got] == list(range(500))
    assert [s.stamp_ns for s in got] == [(7 + k) * PERIOD for k in range(500)]
    np.testing.assert_array_equal([s.position_m for s in got], rec.position_m)
    np.testing.assert_array_equal([s.reference_m for s in got], rec.reference_m)
    np.testing.assert_array_equal([s.command_v for s in got], rec.command_v)
    stats = loop.stats()
    assert stats['skipped'] == 0 and stats['late'] == 0 and stats['queue_overruns'] == 0
    assert stats['paced_samples'] == 500 and stats['late_half_period'] == 0
    # the stage held each command over the next sample: 499 samples after the start
    assert stats['samples'] == 499 and stats['commands'] == 500


@pytest.mark.parametrize('mode', ['none', 'learning', 'inverse_learning'])
def test_the_warm_up_leaves_the_run_it_precedes_bit_for_bit_alone(mode):
    # the dry samples run on copies: the run after them is the run without them, stalls and
    # commands ahead included (a copy that shared state with the run would show here)
    def run_once(warm: bool) -> tuple[list, dict]:
        loop = _loop_config()
        ff = loop.controller.feedforward.replace(mode=mode)
        loop = dataclasses.replace(loop, controller=loop.controller.replace(feedforward=ff))
        servo_loop = servo_from_config(loop, 0.05)
        clock = FakeClock(per_read=300)
        clock.stalls = {40: 7 * PERIOD, 200: 25 * PERIOD}
        servo_loop.pacer = Pacer(PERIOD, clock=clock, sleep=clock.sleep)
        if not warm:
            servo_loop.warm_up = lambda samples=0: 'skipped: off'  # type: ignore[method-assign]
        servo_loop.run(start_ns=7 * PERIOD)
        assert servo_loop.error is None
        return servo_loop.drain(), servo_loop.setup_report

    (cold, _), (warm, report) = run_once(False), run_once(True)
    assert report['warm_up'].startswith('applied: 64 dry samples')
    assert [s.k for s in warm] == [s.k for s in cold] and len(cold) < 500  # stalls skipped
    for column in ('position_m', 'reference_m', 'command_v', 'applied_v', 'diagnostics'):
        assert [getattr(s, column) for s in warm] == [getattr(s, column) for s in cold], column


class _Executor:
    """The executor thread as the loop's turn event sees it: it takes its turn while waited for."""

    def __init__(self, loop: ServoLoop) -> None:
        self.loop = loop
        self.taken: list = []
        self.timeouts: list[float] = []

    def clear(self) -> None:
        pass

    def set(self) -> None:
        pass

    def wait(self, timeout: float) -> bool:
        self.timeouts.append(timeout)
        self.taken.extend(self.loop.drain())
        return True


def _columns(samples: list) -> dict:
    return {c: np.array([getattr(s, c) for s in samples]) for c in
            ('k', 'stamp_ns', 'position_m', 'reference_m', 'command_v', 'applied_v')}


def test_a_servo_thread_hands_the_executor_the_lock_when_its_turn_is_overdue_only():
    every = 10  # periods
    loop = servo(FakeClock(per_read=300), 0.05)
    loop.share_interpreter(every * PERIOD / 1e9)
    executor = _Executor(loop)
    loop._turn = executor  # type: ignore[assignment]
    loop.run(start_ns=7 * PERIOD)
    assert loop.error is None
    got = executor.taken + loop.drain()
    # a handover is a wait of at most a period, each one the executor's turn
    assert executor.timeouts == [PERIOD / 1e9] * loop.handovers
    # every `every` periods or a little more (the clock moves on each read): never more often
    assert 500 // (every + 1) <= loop.handovers <= 500 // every
    assert loop.stats()['handovers'] == loop.handovers
    # the samples are those of the loop that never hands over, bit for bit
    alone = servo(FakeClock(per_read=300), 0.05)
    alone.run(start_ns=7 * PERIOD)
    want = alone.drain()
    assert 'handovers' not in alone.stats()
    for (name, a), b in zip(_columns(got).items(), _columns(want).values()):
        np.testing.assert_array_equal(a, b, err_msg=name)


def test_a_servo_thread_whose_executor_takes_its_turns_never_waits_for_it():
    loop = servo(FakeClock(per_read=300), 0.05)
    loop.share_interpreter(10 * PERIOD / 1e9)
    executor = _Executor(loop)
    loop._turn = executor  # type: ignore[assignment]
    taken: list = []
    loop.boundary = lambda: bool(taken.extend(loop.drain()) or True)  # a turn each sample
    loop.run(start_ns=7 * PERIOD)
    assert loop.handovers == 0 and not executor.timeouts and len(taken + loop.drain()) == 500
    for bad in (-1.0, math.inf, math.nan):
        with pytest.raises(ParameterError, match='every_s'):
            loop.share_interpreter(bad)


def test_the_warm_up_copies_a_controller_logic_whose_hooks_are_a_nodes_methods():
    # the composed nodes hand the logic their own methods (rebuild, on_bound, on_refused); a
    # node holds locks, which cannot be copied: the copies leave the hooks out
    class Node:
        def __init__(self) -> None:
            self.lock = threading.Lock()

        def hook(self, *args: object) -> None:
            raise AssertionError('a dry sample called the node')

    node = Node()
    loop = servo(FakeClock(per_read=300), 0.01)
    logic = loop.controller
    logic._rebuild = logic._on_bound = logic._on_refused = node.hook
    assert loop.warm_up().startswith('applied: 64 dry samples')
    assert logic._rebuild == logic._on_bound == logic._on_refused == node.hook


def test_servo_loop_after_a_stall_skips_and_counts_never_bursts():
    clock = FakeClock(per_read=300)
    loop = servo(clock, 0.01)
    loop.start()
    for _ in range(3):
        loop.step()
    # samples 0 .. 3 taken; a stall of 5.2 periods: sample 4 is looked at 4.2 periods late
    clock.now += 5 * PERIOD + 20_000
    while loop.step():
        pass
    got = loop.drain()
    indices = [s.k for s in got]
    stats = loop.stats()
    # samples 4 .. 7 are skipped, 8 is taken 0.2 periods late (no burst), then the grid goes on
    assert indices == [0, 1, 2, 3] + list(range(8, 100))
    assert stats['skipped'] == 4 and stats['late_half_period'] == 0
    assert got[4].lateness_ns >= 20_000
    # and the stamps stay on the grid
    assert all(s.stamp_ns == s.k * PERIOD for s in got)


def test_servo_loop_queue_drops_the_oldest_and_counts_it():
    loop = servo(FakeClock(per_read=300), 0.01)
    loop.samples = type(loop.samples)(maxlen=30)
    loop.run()
    got = loop.drain(limit=10)
    rest = loop.drain()
    assert [s.k for s in got + rest] == list(range(70, 100))
    assert loop.stats()['queue_overruns'] == 70


def test_servo_loop_fault_drives_the_safe_voltage_and_keeps_the_error():
    loop = servo(FakeClock(per_read=300), 0.01)

    def broken(stamp_ns: int) -> tuple[float, float]:
        raise RuntimeError('trajectory broke')

    loop.trajectory.on_position = broken  # type: ignore[method-assign]
    loop.run()
    assert isinstance(loop.error, RuntimeError) and loop.plant.stopped
    assert 'trajectory broke' in loop.stats()['error']


def test_servo_loop_records_what_the_plant_applied_with_each_sample():
    loop = servo(FakeClock(per_read=300), 0.01)
    loop.run()
    got = loop.drain()
    safe = loop.plant.safe_v
    # y_0 was measured at the safe voltage; y_k at the command of sample k-1 (the model backend
    # clamps in its own chain, so the guard passes the command through)
    assert got[0].applied_v == safe
    assert [s.applied_v for s in got[1:]] == [s.command_v for s in got[:-1]]


def plant_alone(clock: FakeClock, duration_s: float) -> ServoLoop:
    params = StageParams.from_flat(STAGE)
    return ServoLoop(GuardedPlant(ModelBridge(params), params.chain, 0.01), None, None,
                     sample_rate_hz=1e4, duration_s=duration_s,
                     pacer=Pacer(PERIOD, clock=clock, sleep=clock.sleep))


def test_servo_loop_of_the_plant_alone_holds_what_it_was_given_and_counts_late():
    clock = FakeClock(per_read=300)
    loop = plant_alone(clock, 0.001)
    guard = loop.plant
    loop.start()
    loop.step()  # sample 1: no command yet (the guard counts lateness from sample 2 on)
    guard.command(1.5, clock.now / 1e9)  # a command from another node
    loop.step()
    loop.step()  # sample 3: the same command held, late again
    got = loop.drain()
    assert [s.applied_v for s in got] == [guard.safe_v, guard.safe_v, 1.5, 1.5]
    assert np.isnan(got[1].command_v) and loop.stats()['late'] == 1


def test_servo_loop_stalled_past_its_end_counts_only_the_samples_of_the_run():
    clock = FakeClock(per_read=300)
    loop = servo(clock, 0.001)  # 10 samples
    loop.start()
    for _ in range(5):
        loop.step()
    clock.now += 20 * PERIOD  # samples 6 .. 9 skipped, and the run is over
    assert not loop.step()
    stats = loop.stats()
    assert stats['paced_samples'] == 6 and stats['skipped'] == 4 and loop.done


def test_sample_ring_hands_samples_to_another_reader_and_counts_what_it_missed():
    from piezo_stage_ros.nodes.servo import SampleRing, ServoSample
    ring = SampleRing(capacity=8)
    reader = SampleRing(capacity=8, name=ring.name)
    try:
        stamp = 1_700_000_000_123_456_789  # since the epoch: must stay an exact integer
        for k in range(5):
            ring.append(ServoSample(k, stamp + k, 1.0 * k, 2.0, 3.0, 4.0, 5.0, 10 * k, None))
        ints, floats, missed = reader.take()
        assert missed == 0 and ints[:, 0].tolist() == list(range(5))
        assert ints[:, 1].tolist() == [stamp + k for k in range(5)]
        assert floats[:, 0].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0]
        for k in range(5, 20):  # 15 more into 8 rows: the reader misses 7
            ring.append(ServoSample(k, stamp + k, 1.0 * k, 2.0, 3.0, 4.0, 5.0, 0, None))
        ints, _, missed = reader.take()
        assert missed == 7 and ints[:, 0].tolist() == list(range(12, 20))
        assert reader.take()[0].shape == (0, len(SampleRing.INTS))
    finally:
        reader.close()
        ring.close(unlink=True)


def test_a_ring_attached_by_name_takes_the_creators_layout():
    # the servo process attaches by name only: a capacity or diagnostics width other than the
    # defaults must still put every column where the creator reads it
    from piezo_stage_ros.nodes.servo import SampleRing, ServoSample
    ring = SampleRing(capacity=100_000, diagnostics=3)
    writer = SampleRing(name=ring.name)
    try:
        assert (writer.capacity, writer.width) == (100_000, 3)
        for k in range(3):
            writer.append(ServoSample(k, 10 + k, 1.0 + k, 2.0, 3.0, 4.0, 5.0, 0, (7.0, 8.0, 9.0),
                                      ('a', 'b', 'c'), 6.0))
        ints, floats, missed = ring.take()
        assert missed == 0 and ints[:, 0].tolist() == [0, 1, 2]
        np.testing.assert_array_equal(floats[:, :len(SampleRing.FLOATS)],
                                      [[1.0 + k, 2.0, 3.0, 4.0, 5.0, 6.0] for k in range(3)])
        np.testing.assert_array_equal(floats[:, len(SampleRing.FLOATS):], [[7.0, 8.0, 9.0]] * 3)
    finally:
        writer.close()
        ring.close(unlink=True)
    with pytest.raises(ValueError, match='capacity 0'):
        SampleRing(capacity=0)


def test_sample_ring_carries_diagnostics_with_their_layout_and_counts_what_does_not_fit():
    from piezo_stage_ros.nodes.servo import SampleRing, ServoSample
    ring = SampleRing(capacity=8, diagnostics=3)
    reader = SampleRing(capacity=8, name=ring.name, diagnostics=3)
    layouts: list = []
    ring.on_layout = lambda number, names: layouts.append((number, names, ring.get('count')))
    rac, pi, wide = ('a', 'b', 'c'), ('e',), ('1', '2', '3', '4')
    rows = [(None, None), ((1.0, 2.0, 3.0), rac), (None, None), ((4.0, 5.0, 6.0), rac),
            ((7.0,), pi), ((1.0, 2.0, 3.0, 4.0), wide), ((8.0, 9.0, 10.0), tuple(rac))]
    try:
        for k, (values, names) in enumerate(rows):
            ring.append(ServoSample(k, k, 0.0, 0.0, 0.0, 0.0, 0.0, 0, values, names))
        ints, floats, _ = reader.take()
    finally:
        reader.close()
        ring.close(unlink=True)
    # each new set of names is handed on once, before the first row that carries it (the
    # count of rows written then); equal names again are a new layout only after others
    assert layouts == [(0, rac, 1), (1, pi, 4), (2, wide, 5), (3, rac, 6)]
    assert ints[:, 3].tolist() == [-1, 0, 0, 0, 1, 2, 3]
    # four values do not fit in three columns: stored without them, counted
    assert ints[:, 4].tolist() == [0, 3, 0, 3, 1, 0, 3] and ring.dropped == 1
    first = len(SampleRing.FLOATS)  # the diagnostics follow the sample's values
    assert floats[1, first:].tolist() == [1.0, 2.0, 3.0] and floats[4, first] == 7.0
    assert floats[6, first:].tolist() == [8.0, 9.0, 10.0]


def test_servo_loop_of_the_plant_alone_ramps_to_the_safe_voltage_when_commands_stop():
    clock = FakeClock(per_read=300)
    loop = plant_alone(clock, 0.03)
    guard = loop.plant
    guard.slew_v_per_s = 500.0  # 0.05 V a sample: from 5 V to the safe 0 V in 100 samples
    loop.start()
    command_s = clock.now / 1e9
    guard.command(5.0, command_s)  # the only command from the controller, then silence
    while loop.step():
        pass
    got = loop.drain()
    applied = np.array([s.applied_v for s in got])
    first_trip = int(np.argmax(applied[1:] < 5.0)) + 1
    # held while the silence is within the 10 ms timeout, then a ramp of 0.05 V a sample down
    # to the safe voltage, no step larger, and the safe voltage to the end
    assert set(applied[1:first_trip]) == {5.0}
    taken_s = [(loop.pacer.due_ns(s.k) + s.lateness_ns) / 1e9 for s in got]
    assert taken_s[first_trip] - command_s > 0.01 >= taken_s[first_trip - 1] - command_s
    steps = np.diff(applied[first_trip - 1:])
    assert np.all(steps <= 0.0) and np.all(steps >= -0.05 - 1e-12)
    at_safe = first_trip + int(np.argmax(applied[first_trip:] == guard.safe_v))
    assert at_safe - first_trip == 99 and set(applied[at_safe:]) == {guard.safe_v}
    stats = loop.stats()
    assert stats['watchdog_trips'] == 1 and stats['ramp_samples'] == 100
    assert stats['safe_samples'] == len(got) - at_safe - 1
    assert stats['watchdog_max_step_v'] == pytest.approx(0.05)
    # the trip goes on to the end of the run: it ends with the stop, and is taken once
    assert not loop.take_trips() and guard.trip is not None
    guard.stop()
    (trip,) = loop.take_trips()
    assert trip.ended == 'stop' and trip.samples == len(got) - first_trip
    assert trip.ramp_samples == 100 and trip.from_v == 5.0 and not loop.take_trips()


def test_servo_loop_keeps_the_voltage_held_after_the_last_sample():
    loop = servo(FakeClock(per_read=300), 0.001)
    loop.run()
    got = loop.drain()
    # held over the sample after the last one (the plant's stop then drives the safe voltage)
    assert loop.held_v == got[-1].command_v and loop.plant.held_v == loop.plant.safe_v


# --- the servo loop in a process of its own (spawned: no rclpy there) ------------------------

def _loop_config():
    from piezo_stage_ros.bench.servo import loop_config
    return loop_config()


@pytest.mark.parametrize('spin_us, spins', [(200.0, True), (100.0, True), (30.0, False)])
def test_the_stream_host_polls_its_socket_only_when_the_servo_spins(spin_us, spins):
    from piezo_stage_ros.hardware.udp import UdpBridge, UdpStreamBridge
    from piezo_stage_ros.nodes.servo import make_bridge
    loop = _loop_config()
    node = dataclasses.replace(loop.plant_node, mode='realtime', backend='udp_stream',
                               servo=dataclasses.replace(loop.plant_node.servo,
                                                         spin_us=spin_us))
    bridge = make_bridge(loop.stage, node)  # nothing opened before start
    assert isinstance(bridge, UdpStreamBridge) and bridge.spin is spins
    assert bridge.answer.period_ns == 100_000
    lockstep = make_bridge(loop.stage, dataclasses.replace(node, mode='lockstep', backend='udp'))
    assert type(lockstep) is UdpBridge and lockstep.spin is False


class _TargetPacedModel(ModelBridge):
    """The model as a target-paced stream: each sample arrives as soon as it is asked for."""

    def __init__(self, params: StageParams, wanted) -> None:
        super().__init__(params)
        self.sample_index, self.arrival_ns = -1, 0
        self.wanted = wanted
        self.events: list[tuple[str, int, int]] = []

    first = 0  # the first sample the host gets (the ones before it went by unanswered)

    def safe_start(self, safe_voltage_v: float) -> float:
        self.sample_index = self.first
        self.arrival_ns = self.first * PERIOD
        return super().safe_start(safe_voltage_v)

    def write_voltage(self, voltage_v: float) -> None:
        self.write_commands(voltage_v, ())

    def write_commands(self, voltage_v: float, ahead_v) -> None:
        self.events.append(('answer', self.sample_index, len(ahead_v)))
        super().write_voltage(voltage_v)

    def write_ahead(self, ahead_v) -> None:
        self.events.append(('ahead', self.sample_index, len(ahead_v)))

    def ahead_wanted(self, count: int) -> bool:
        return self.wanted(self.sample_index)

    def read_position(self) -> float:
        self.sample_index += 1
        self.arrival_ns += PERIOD
        return super().read_position()


def _run_on_a_target_clock(ahead: int) -> tuple[list[tuple[str, int, int]], list[float]]:
    # the answers, commands ahead and samples served in their order; the positions taken
    loop = _loop_config()
    loop = dataclasses.replace(loop, plant_node=dataclasses.replace(
        loop.plant_node, servo=dataclasses.replace(loop.plant_node.servo,
                                                   commands_ahead=ahead)))
    target = _TargetPacedModel(loop.stage, lambda k: k % 3 == 0)
    servo = servo_from_config(loop, 0.005, target,
                              on_sample=lambda s: target.events.append(('served', s.k, 0)))
    assert servo.bridge_clock is target
    servo.run()
    assert servo.error is None and servo.done
    return target.events, [s.position_m for _, s in servo.samples]


@pytest.mark.parametrize('ahead', [0, 16])
def test_on_a_target_clock_the_answer_leaves_first_and_its_commands_ahead_after(ahead):
    events, _ = _run_on_a_target_clock(ahead)
    assert [e[1] for e in events if e[0] == 'served'] == list(range(50))
    for k in range(50):
        i = events.index(('served', k, 0))
        # the answer to sample k, alone, before the loop's bookkeeping of it; then its
        # commands ahead when the host has time for them
        follows = ahead > 0 and k % 3 == 0
        assert events[i - 1 - follows] == ('answer', k, 0)
        if follows:
            assert events[i - 1] == ('ahead', k, ahead)
    assert sum(e[0] == 'ahead' for e in events) == (17 if ahead else 0)


def test_on_a_target_clock_the_commands_ahead_change_no_sample_taken():
    # they serve only the samples the host misses; the model here misses none
    without, with_ahead = (_run_on_a_target_clock(m)[1] for m in (0, 16))
    assert with_ahead == without and len(without) == 50


def test_on_a_target_clock_the_samples_before_the_first_taken_count_as_skipped():
    # the host took sample 5 first (the newest waiting): 0-4 count as skipped, and the stamps
    # stay on the target's grid, k periods after the start
    loop = _loop_config()
    target = _TargetPacedModel(loop.stage, lambda k: False)
    target.first = 5
    servo = servo_from_config(loop, 0.005, target)
    servo.run(start_ns=10**9, since_ns=0)
    got = servo.drain()
    assert servo.error is None and [s.k for s in got] == list(range(5, 50))
    stats = servo.stats()
    assert stats['skipped'] == 5 and stats['paced_samples'] + stats['skipped'] == 50
    assert all(s.stamp_ns == 10**9 + s.k * PERIOD for s in got)


def test_the_backends_start_runs_before_the_clock_and_costs_sample_1_nothing():
    # a backend whose start takes 0.3 ms (the model's reset took about 0.1 ms here): run in
    # sample 0 it made samples 1-2 late and skipped, while the RAC's start-up transient ran
    clock = FakeClock()

    class SlowStart(ModelBridge):
        def safe_start(self, safe_voltage_v: float) -> float:
            clock.now += 300_000
            return super().safe_start(safe_voltage_v)

    loop = _loop_config()
    servo = servo_from_config(loop, 0.002, SlowStart(loop.stage))
    servo.pacer = Pacer(PERIOD, clock=clock, sleep=clock.sleep, spin_ns=0)
    servo.run()
    assert servo.error is None and servo.pacer.stats.skipped == 0
    assert [s.k for _, s in servo.samples] == list(range(20))
    # the watchdog is armed on the loop's clock at sample 0, as before
    assert servo.plant.stats()['watchdog_trips'] == 0


def _wait_for(condition, what: str, limit_s: float = 120.0) -> None:
    # a bound on a wait for a spawned process, not a timing figure: the test asserts nothing
    # on how long it took
    import time
    end = time.monotonic() + limit_s
    while not condition():
        if time.monotonic() > end:
            raise AssertionError(f'{what}: not within {limit_s:g} s')
        time.sleep(0.01)


def _run_with_a_change(proc, served, kind: str, value) -> dict:
    # start, send one change after the first samples, serve 200 samples after it is applied,
    # stop; ``served()`` takes what the process handed over and returns how many so far
    try:
        proc.start()
        _wait_for(lambda: served() > 10, 'first samples')
        proc.change(kind, value)
        _wait_for(lambda: served() and proc.ring.get('applied') == 1, 'the change applied')
        at = served()
        _wait_for(lambda: served() > at + 200, 'samples after the change')
        stats = proc.stop()
        served()
    finally:
        proc.close()
    return stats


def test_apply_change_reaches_the_logic_and_names_a_bad_change():
    servo = servo_from_config(_loop_config(), 0.01)
    apply_change(servo, 'active', False)
    assert servo.trajectory is not None and not servo.trajectory.active
    apply_change(servo, 'set', ('controller.watchdog.timeout_s', 0.5))
    assert servo.controller is not None and servo.controller.watchdog.timeout_s == 0.5
    with pytest.raises(ValueError, match='nope'):
        apply_change(servo, 'nope', 1)
    with pytest.raises(ValueError, match='stage.x'):
        apply_change(servo, 'set', ('stage.x', 1))
    with pytest.raises(ValueError, match='controller.no_such'):
        apply_change(servo, 'set', ('controller.no_such', 1))


def test_servo_process_writes_the_table_its_controller_learned(tmp_path):
    # the process runs the controller: its table, not the controller node's idle copy, is the
    # one save_table_file keeps (the node skips its own write when it forwards to a process)
    from piezo_stage_ros.core.control.feedforward import read_learned_table
    loop = _loop_config()
    path = tmp_path / 'table.npz'
    ff = loop.controller.feedforward.replace(mode='learning', save_table_file=str(path))
    loop = dataclasses.replace(loop, controller=loop.controller.replace(feedforward=ff))
    proc = ServoProcess(loop, 0.05)  # 500 samples: five periods of the 100 Hz sine
    try:
        proc.start()
        _wait_for(lambda: proc.take() is not None and proc.finished, 'run of 500 samples')
        proc.stop()
        stats = proc.stats()  # the figures of the end-of-run line: the table has its own
    finally:
        proc.close()
    assert 'error' not in stats and 'learned_table' not in stats
    table = read_learned_table(path)
    # the run's periods, less the first (which only fills the table's history) and any a
    # stall cut short
    assert table.mode == 'learning' and 1 <= table.periods_learned <= 5
    assert proc.table_line is not None and str(path) in proc.table_line
    assert f'{table.periods_learned} periods learned' in proc.table_line


def test_servo_process_refuses_fork_and_an_unknown_change():
    with pytest.raises(ValueError, match="'fork'"):
        ServoProcess(_loop_config(), 0.01, context='fork')
    proc = ServoProcess(_loop_config(), 0.01)
    try:
        with pytest.raises(ValueError, match='gains'):
            proc.change('gains', 1)
    finally:
        proc.close()


def test_servo_process_runs_its_samples_and_hands_over_every_one():
    loop = _loop_config()
    proc = ServoProcess(loop, 0.05)  # 500 samples of the grid
    try:
        called = time.monotonic_ns()
        proc.start(7_000)
        got = []
        _wait_for(lambda: got.append(proc.take()[0]) or proc.finished, 'run of 500 samples')
        got.append(proc.take()[0])
        ended = time.monotonic_ns()
        stats = proc.stats()
    finally:
        proc.close()
    ints = np.concatenate(got)
    assert 'error' not in stats
    # every sample served went through the ring; a stall skips samples, never repeats one
    assert ints.shape[0] == stats['paced_samples'] == stats['controller_steps']
    assert stats['ring_missed'] == 0
    assert np.all(np.diff(ints[:, 0]) > 0) and ints[0, 0] == 0 and ints[-1, 0] <= 499
    assert ints[:, 0].size + stats['skipped'] == 500
    period = round(1e9 / loop.stage.sample_rate_hz)
    # stamps on the grid, from the ROS time given plus the time the process took to start
    # (its imports: more than nothing, less than the whole call)
    origin = ints[0, 1]
    assert 7_000 < origin < 7_000 + ended - called
    assert np.array_equal(ints[:, 1], origin + ints[:, 0] * period)


@pytest.mark.parametrize('capacity', [65536, 100_000])  # 100 000: the node's 10 s backlog
def test_servo_process_hands_over_the_diagnostics_of_the_same_loop_in_a_thread(capacity):
    # the process and a thread-mode loop on the same configuration give the same samples with
    # the same diagnostics (every diagnostics_every-th controller step, named as in thread
    # mode): the thread's clock replays the process's, so that it serves the same grid samples
    # (a loaded machine makes the process skip some) at the same lateness
    loop = _loop_config()
    proc = ServoProcess(loop, 0.05, capacity=capacity)  # 500 samples of the grid
    got: list = []
    try:
        proc.start(7_000)
        _wait_for(lambda: got.extend(proc.drain()) or proc.finished, 'run of 500 samples')
        got.extend(proc.drain())
        stats = proc.stats()
    finally:
        proc.close()
    assert 'error' not in stats and len(got) == stats['paced_samples']
    period = round(1e9 / loop.stage.sample_rate_hz)
    t0 = 10**12
    times = iter([t0] + [t0 + s.k * period + s.lateness_ns for s in got])
    thread = servo_from_config(loop, 0.05)
    # after the process's last sample (which a loaded machine may have skipped): the end of
    # the run's grid, as a stall past it ends the run
    end = t0 + thread.total * period
    thread.pacer = Pacer(period, clock=lambda: next(times, end), sleep=None)
    thread.run(start_ns=7_000)
    want = thread.drain()
    assert thread.error is None
    assert [s.k for s in got] == [s.k for s in want]
    for column in ('position_m', 'reference_m', 'command_v', 'applied_v'):
        np.testing.assert_array_equal([getattr(s, column) for s in got],
                                      [getattr(s, column) for s in want], err_msg=column)
    carried = [i for i, s in enumerate(want) if s.diagnostics is not None]
    every = loop.controller_node.diagnostics_every
    assert carried == list(range(0, len(want), every)) and len(carried) > 1
    assert [i for i, s in enumerate(got) if s.diagnostics is not None] == carried
    assert all(got[i].diagnostic_names == want[i].diagnostic_names
               == thread.controller.names for i in carried)
    np.testing.assert_array_equal([got[i].diagnostics for i in carried],
                                  [want[i].diagnostics for i in carried])


def test_servo_process_names_the_diagnostics_of_a_rebuilt_controller():
    # a structural change (another controller type) rebuilds the controller in the process,
    # with other diagnostics: the samples after it carry the new names and values
    loop = _loop_config()
    proc = ServoProcess(loop, 0.0)  # on until stopped
    got: list = []

    def served() -> int:
        got.extend(proc.drain())
        return len(got)

    stats = _run_with_a_change(proc, served, 'controller',
                               ControllerParams.from_flat({'type': 'pi'}))
    assert 'error' not in stats
    names = [s.diagnostic_names for s in got if s.diagnostics is not None]
    from piezo_stage_ros.core.contracts.wire import diagnostic_reader
    rac = servo_from_config(loop, 0.01).controller.names
    pi = diagnostic_reader(build_controller(ControllerParams.from_flat({'type': 'pi'}),
                                            1e-4))[0]
    assert rac != pi
    first_pi = names.index(pi)
    assert set(names[:first_pi]) == {rac} and first_pi > 0
    assert set(names[first_pi:]) == {pi}
    assert all(len(s.diagnostics) == len(s.diagnostic_names) for s in got if s.diagnostics)


def test_servo_process_reports_its_setup_while_it_runs():
    # the report of the real-time setup comes as soon as the setup ran, not with the figures:
    # a CPU that does not exist is refused (EINVAL), the interpreter's switch interval applied
    # (5000 us: CPython's default, nothing changes in the process)
    base = _loop_config()
    servo = dataclasses.replace(base.plant_node.servo, cpu=1000, switch_interval_us=5000.0)
    loop = dataclasses.replace(base, plant_node=dataclasses.replace(base.plant_node,
                                                                     servo=servo))
    proc = ServoProcess(loop, 0.0)  # on until stopped
    try:
        proc.start()
        _wait_for(lambda: proc.setup_report, 'the setup report')
        report = proc.setup_report
        running = not proc.finished
        stats = proc.stop()
    finally:
        proc.close()
    assert running and 'error' not in stats
    assert report['affinity'].startswith('refused') and 'Invalid argument' in report['affinity']
    assert report['switch_interval'].startswith('applied')
    assert proc.setup_report == report


def test_servo_process_applies_a_change_at_a_sample_and_stops_on_request():
    proc = ServoProcess(_loop_config(), 0.0)  # on until stopped
    taken = []

    def served() -> int:
        taken.append(proc.take())
        return sum(t[0].shape[0] for t in taken)

    stats = _run_with_a_change(proc, served, 'active', False)
    assert 'error' not in stats and proc.finished
    assert stats['stopped_at_v'] == _loop_config().stage.chain.safe_voltage_v
    floats = np.concatenate([t[1] for t in taken])
    # stopped: the reference is held, with zero velocity, from a sample on
    assert floats[-1, 2] == 0.0 and floats[-1, 1] == floats[-100, 1]
    assert np.any(floats[:, 2] != 0.0)


def test_servo_process_error_drives_the_safe_voltage_and_is_reported():
    proc = ServoProcess(_loop_config(), 0.0)
    try:
        proc.start()
        _wait_for(lambda: proc.ring.get('count') > 10, 'first samples')
        proc.change('set', ('controller.no_such', 1.0))
        _wait_for(lambda: proc.finished, 'the end after the error')
        stats = proc.stats()
    finally:
        proc.close()
    assert 'controller.no_such' in stats['error']
    assert stats['stopped_at_v'] == _loop_config().stage.chain.safe_voltage_v
