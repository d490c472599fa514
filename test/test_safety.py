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

"""The command watchdog never jumps the stage: a ramp to the safe voltage, a gentle way back."""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.stage import StageParams
from piezo_stage_ros.hardware.bridge import ModelBridge
from piezo_stage_ros.hardware.pacing import Pacer
from piezo_stage_ros.hardware.safety import clamp_command, GuardedPlant, slew_toward, Trip
from piezo_stage_ros.nodes.logic import ControllerLogic, TrajectoryLogic
from piezo_stage_ros.nodes.servo import ServoLoop, ServoProcess
import pytest

T = 1e-4  # s, 10 kHz
LOW, HIGH = -2.0, 10.0


class Written:
    """A backend that records what it is told to drive (``clamps_itself`` as the model's)."""

    def __init__(self, clamps_itself: bool = False) -> None:
        self.clamps_itself = clamps_itself
        self.written: list[float] = []

    def open(self) -> None:
        pass

    def safe_start(self, safe_voltage_v: float) -> float:
        self.written.append(safe_voltage_v)
        return 0.0

    def write_voltage(self, voltage_v: float) -> None:
        self.written.append(voltage_v)

    def read_position(self) -> float:
        return 0.0

    def safe_stop(self, safe_voltage_v: float) -> None:
        pass

    def stats(self):
        return {}


def chain(safe_v: float = 0.0):
    return StageParams.from_flat({'chain.safe_voltage_v': safe_v}).chain


def test_slew_toward_steps_at_most_the_step_and_lands_on_the_target():
    assert slew_toward(5.0, 0.0, 2.0) == 3.0
    assert slew_toward(-1.0, 4.0, 2.0) == 1.0
    assert slew_toward(1.0, 0.5, 2.0) == 0.5
    # a whole number of steps lands on the target, not a rounding residue short of it
    v = 5.0
    for _ in range(100):
        v = slew_toward(v, 0.0, 0.05)
    assert v == 0.0


def test_the_slew_and_the_period_are_validated():
    with pytest.raises(ParameterError, match='slew_v_per_s'):
        GuardedPlant(Written(), chain(), slew_v_per_s=0.0)
    with pytest.raises(ParameterError, match='sample_period_s'):
        GuardedPlant(Written(), chain(), sample_period_s=math.inf)


# Each sample of a history: None (no command since the previous sample), a command that arrived
# just before it (any float: out of range and non-finite included), or a stall of the host
# (the time jumps by that many periods; the backend holds its voltage meanwhile).
EVENT = st.one_of(st.none(), st.none(), st.none(),
                  st.floats(-20.0, 20.0), st.sampled_from([math.nan, math.inf, -math.inf]),
                  st.tuples(st.just('stall'), st.integers(1, 300)))


@settings(max_examples=300, deadline=None)
@given(history=st.lists(EVENT, max_size=600), timeout_samples=st.integers(0, 60),
       fraction=st.floats(0.05, 0.95), slew=st.floats(1.0, 1e5),
       safe_v=st.floats(LOW, HIGH), clamps_itself=st.booleans())
def test_no_step_larger_than_slew_times_t_during_a_trip(history, timeout_samples, fraction,
                                                        slew, safe_v, clamps_itself):
    bridge = Written(clamps_itself)
    timeout_s = (timeout_samples + fraction) * T
    guard = GuardedPlant(bridge, chain(safe_v), timeout_s, slew_v_per_s=slew,
                         sample_period_s=T)
    step = slew * T
    bound = step * (1.0 + 1e-9) + 1e-12

    def amplifier(v):  # what the amplifier gets: the model backend clamps after its DAC
        return clamp_command(v, LOW, HIGH, safe_v)[0]

    now = 1.0
    guard.start(now)
    last_command_s = now
    phases, targets = [], []
    for event in history:
        if isinstance(event, tuple):
            now += event[1] * T
            guard.skipped(event[1])
            continue
        if event is not None:
            guard.command(event, now)
            last_command_s = now
        now += T
        guard.sample(now)
        phases.append(guard.phase)
        targets.append(amplifier(guard.held_v))
        if guard.phase in ('ramp', 'safe'):
            # the ramp only once the last command is older than the timeout
            assert now - last_command_s > timeout_s
    applied = [amplifier(v) for v in bridge.written]  # applied[i + 1]: sample i
    for i, phase in enumerate(phases):
        before, now_v = applied[i], applied[i + 1]
        if phase == 'ramp':
            # the watchdog alone: one way, toward the safe voltage, one step at most
            assert abs(now_v - before) <= bound
            assert abs(now_v - safe_v) < abs(before - safe_v) or now_v == safe_v
        elif phase == 'safe':
            assert now_v == before == safe_v
        elif phase == 'recover':
            if phases[i - 1] in ('ramp', 'safe'):
                assert abs(now_v - before) <= bound  # the return: no step of its own
            else:
                # the commands' own change, plus one step of the offset at most
                assert abs(now_v - before) <= abs(targets[i] - targets[i - 1]) + bound
    stats = guard.stats()
    driven = sum(p != 'track' for p in phases)
    assert stats['ramp_samples'] + stats['safe_samples'] + stats['recovery_samples'] == driven
    assert stats['watchdog_max_step_v'] <= bound
    trips = [*guard.ended_trips] + ([guard.trip] if guard.trip is not None else [])
    assert len(trips) == stats['watchdog_trips']
    assert sum(trip.samples for trip in trips) == driven
    for trip in trips:
        # the way back ends: the offset shrinks by a step each sample
        assert trip.recovery_samples <= (HIGH - LOW) / step + 2


@settings(max_examples=100, deadline=None)
@given(held=st.floats(LOW, HIGH), safe_v=st.floats(LOW, HIGH), slew=st.floats(10.0, 1e4),
       back=st.floats(LOW, HIGH))
def test_a_ramp_reaches_the_safe_voltage_and_the_return_reaches_the_commands(held, safe_v, slew,
                                                                             back):
    bridge = Written()
    guard = GuardedPlant(bridge, chain(safe_v), 10 * T, slew_v_per_s=slew, sample_period_s=T)
    guard.start(0.0)
    guard.command(held, 0.0)
    need = math.ceil(abs(held - safe_v) / (slew * T)) + 1
    now = 0.0
    for _ in range(10 + need + 5):
        now += T
        guard.sample(now)
    assert bridge.written[-1] == safe_v and guard.phase == 'safe'
    need = math.ceil(abs(back - safe_v) / (slew * T)) + 1
    for _ in range(need + 1):
        guard.command(back, now)
        now += T
        guard.sample(now)
    assert bridge.written[-1] == back and guard.trip is None
    (trip,) = guard.ended_trips
    assert trip.ended == 'commands' and trip.from_v == held


def test_commands_stopping_again_while_followed_back_start_a_new_trip_from_there():
    bridge = Written()
    # 1 V a sample; the timeout two and a half periods
    guard = GuardedPlant(bridge, chain(0.0), 2.5 * T, slew_v_per_s=1e4, sample_period_s=T)
    guard.start(0.0)
    guard.command(5.0, 0.0)
    now = 0.0
    for _ in range(8):  # 2 held, then 5 V down to 0 V in 5 samples, 1 at it
        now += T
        guard.sample(now)
    guard.command(6.0, now)
    for _ in range(6):  # followed back 1 V a sample: 1, 2, then silent again: down
        now += T
        guard.sample(now)
    assert bridge.written[1:] == pytest.approx([5.0, 5.0, 4.0, 3.0, 2.0, 1.0, 0.0, 0.0,
                                                1.0, 2.0, 1.0, 0.0, 0.0, 0.0])
    first, = guard.ended_trips
    assert first.ended == 'tripped again' and first.recovery_samples == 2
    assert first.ramp_samples == 5 and first.safe_samples == 1
    assert guard.trip is not None and guard.trip.from_v == 2.0 and guard.watchdog.trips == 2
    guard.stop()
    assert [t.ended for t in guard.ended_trips] == ['tripped again', 'stop']


@pytest.mark.parametrize('kind', [list, np.array])  # a feed-forward's tables come as an array
def test_commands_ahead_come_before_the_ramp_and_the_last_is_held(kind):
    # samples without a command apply the command's predictions (clamped), the last one held
    # after the queue, until the timeout; the ramp then starts from the last one applied
    bridge = Written()
    guard = GuardedPlant(bridge, chain(0.0), 5.5 * T, slew_v_per_s=1e4, sample_period_s=T)
    guard.start(0.0)
    guard.command(4.0, 0.0, kind([5.0, 12.0]))
    now = 0.0
    for _ in range(7):
        now += T
        guard.sample(now)
    # the command, two predictions (12 V clamped to 10), the last held, then the ramp
    assert bridge.written[1:] == pytest.approx([4.0, 5.0, 10.0, 10.0, 10.0, 9.0, 8.0])
    assert guard.trip is not None and guard.trip.from_v == 10.0
    assert guard.predicted_samples == 4


def test_a_prediction_that_is_not_finite_is_refused_and_the_command_held():
    bridge = Written()
    guard = GuardedPlant(bridge, chain(0.0), 1.0, sample_period_s=T)
    guard.start(0.0)
    guard.command(4.0, 0.0, [5.0, math.nan])
    for n in range(3):
        guard.sample((n + 1) * T)
    assert bridge.written[1:] == [4.0, 4.0, 4.0] and guard.predicted_samples == 0


class Queue(Written):
    """A backend with a command queue: records each write and the queue that came with it."""

    def __init__(self) -> None:
        super().__init__()
        self.queues: list[list[float]] = []
        self.advanced = 0

    def write_commands(self, voltage_v: float, ahead_v) -> None:
        self.written.append(voltage_v)
        self.queues.append([float(a) for a in ahead_v])

    def advance(self, samples: int) -> None:
        self.advanced += samples


def test_the_queue_goes_to_the_backend_and_a_late_command_is_its_own_prediction():
    bridge = Queue()
    guard = GuardedPlant(bridge, chain(0.0), 1.0, sample_period_s=T)
    guard.start(0.0)
    guard.command(1.0, 0.0, [2.0, 3.0, 4.0])
    guard.sample(T)
    assert bridge.written[-1] == 1.0 and bridge.queues[-1] == [2.0, 3.0, 4.0]
    # the loop stalls two samples: the backend plays 2 and 3 meanwhile
    guard.command(1.5, T, [2.5, 3.5, 4.5])
    guard.skipped(2)
    assert bridge.advanced == 2 and guard.applied_v == 3.0
    # the command computed before the stall is two samples late: its second prediction
    guard.sample(4 * T)
    assert bridge.written[-1] == 3.5 and bridge.queues[-1] == [4.5]
    # without a queue (commands ahead off) the backend is written as before
    guard.command(2.0, 5 * T)
    guard.sample(5 * T)
    guard.sample(6 * T)
    assert bridge.written[-2:] == [2.0, 2.0] and bridge.queues[-1] == []


def test_a_trip_of_the_servo_loop_after_a_long_stall_steps_no_more_than_the_slew():
    # the direct composition: a stall of the host longer than the timeout trips the watchdog
    # when the loop wakes; that sample is one step of the ramp, then the controller's commands
    # are followed back at the slew rate (no jump of the whole command, as before)
    params = StageParams.from_flat({'plant.model': 'reduced'})
    ctrl = build_controller(ControllerParams.from_flat({'type': 'rac'}), T)
    now = [10**9]

    def clock() -> int:
        now[0] += 300
        return now[0]

    def sleep(seconds: float) -> None:
        now[0] += round(seconds * 1e9)

    loop = ServoLoop(GuardedPlant(ModelBridge(params), params.chain, 0.01, sample_period_s=T),
                     TrajectoryLogic(make_trajectory(TrajectoryParams.from_flat(
                         {'kind': 'sine', 'sine.frequency_hz': 100.0})), sample_rate_hz=1e4),
                     ControllerLogic(ctrl, mode='realtime', position_timeout_s=1.0),
                     sample_rate_hz=1e4, duration_s=0.1,
                     pacer=Pacer(100_000, clock=clock, sleep=sleep))
    loop.start()
    while loop.step():
        if loop.index == 300:
            now[0] += 150 * 100_000  # 15 ms: longer than the 10 ms timeout
    got = loop.drain()
    applied = np.array([s.applied_v for s in got])
    k = np.array([s.k for s in got])
    first = int(np.argmax(k > 300))
    (trip,) = loop.take_trips()
    assert trip.ended == 'commands' and trip.ramp_samples == 1 and trip.safe_samples == 0
    assert trip.samples == 1 + trip.recovery_samples
    step = loop.plant.slew_v_per_s * T
    # the sample the loop woke up on is one step of the ramp; then the controller's commands
    # plus an offset that shrinks a step a sample: the way back is short
    assert abs(applied[first] - applied[first - 1]) <= step * (1 + 1e-9)
    assert trip.max_step_v == pytest.approx(abs(applied[first] - applied[first - 1]))
    offset = applied[first:first + trip.samples] - [s.command_v for s in got[first - 1:
                                                                               first - 1
                                                                               + trip.samples]]
    assert np.all(np.abs(np.diff(np.abs(offset[1:]))) <= step * (1 + 1e-9))
    assert trip.recovery_samples < 200
    stats = loop.stats()
    assert stats['watchdog_trips'] == 1 and stats['ramp_samples'] == 1
    assert stats['recovery_samples'] == trip.recovery_samples
    # and the loop tracks again as before the stall
    err = np.abs([s.position_m - s.reference_m for s in got])
    assert err[first + trip.samples + 300:].max() < 2 * err[100:first].max()


def test_the_servo_process_hands_on_the_trips_its_guard_reported():
    from piezo_stage_ros.bench.servo import loop_config
    process = ServoProcess(loop_config())
    try:
        trip = Trip(start_s=1.0, silence_s=0.02, start_sample=5, from_v=3.0, samples=7,
                    ended='commands')
        # what the servo process sends when its guard ends a trip (plant.on_trip)
        process._sender.send(('trip', trip))
        assert process.take_trips() == [trip] and process.take_trips() == []
    finally:
        process.close()
