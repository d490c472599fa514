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

"""The CDR codec (core/contracts/cdr.py), byte for byte against the serializer of rosbags."""

from __future__ import annotations

import math

from piezo_stage_ros.core.contracts import cdr
import pytest

typesys = pytest.importorskip('rosbags.typesys', reason='rosbags is the reference serializer')
STORE = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
JointState = STORE.types['sensor_msgs/msg/JointState']
Header = STORE.types['std_msgs/msg/Header']
Time = STORE.types['builtin_interfaces/msg/Time']
Float64 = STORE.types['std_msgs/msg/Float64']
Clock = STORE.types['rosgraph_msgs/msg/Clock']
np = pytest.importorskip('numpy')


def reference(sec, nanosec, names, position, velocity=(), effort=(), frame_id=''):
    msg = JointState(header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id),
                     name=list(names), position=np.array(position, dtype=np.float64),
                     velocity=np.array(velocity, dtype=np.float64),
                     effort=np.array(effort, dtype=np.float64))
    return bytes(STORE.serialize_cdr(msg, 'sensor_msgs/msg/JointState'))


CASES = [
    (0, 0, ['stage'], [3.8e-6], [], [], ''),
    (12, 999_999_999, ['stage'], [-1e-9], [2.5e-4], [], ''),
    (5, 100_000, ['theta_hat', 'phi_hat', 's_v', 'saturated'], [1.29, 3.2e-4, -0.01, 0.0],
     [], [], ''),
    (1, 2, ['a', 'bc', 'def'], [1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0], 'frame'),
    (1, 2, [], [], [], [], 'xyz12'),
]


@pytest.mark.parametrize('sec, nanosec, names, position, velocity, effort, frame', CASES)
def test_joint_state_bytes_equal_the_reference(sec, nanosec, names, position, velocity, effort,
                                               frame):
    ours = cdr.encode_joint_state(sec, nanosec, names, position, velocity, effort, frame)
    assert ours == reference(sec, nanosec, names, position, velocity, effort, frame)
    got = cdr.decode_joint_state(ours)
    assert got[:2] == (sec, nanosec)
    assert got[2] == position[0] if position else math.isnan(got[2])
    assert got[3] == velocity[0] if velocity else math.isnan(got[3])


def test_fast_encoder_equals_the_reference():
    enc = cdr.JointStateEncoder(['stage'])
    assert enc.encode(3, 400, [1.5e-6]) == reference(3, 400, ['stage'], [1.5e-6])
    ref = cdr.JointStateEncoder(['stage'], with_velocity=True)
    assert ref.encode(7, 8, [2e-6], [3e-4]) == reference(7, 8, ['stage'], [2e-6], [3e-4])
    names = ['theta_hat', 'phi_hat', 's_v']
    diag = cdr.JointStateEncoder(names)
    assert diag.encode(1, 2, [0.1, 0.2, 0.3]) == reference(1, 2, names, [0.1, 0.2, 0.3])
    # the template is reused: a second message carries its own values only
    assert diag.encode(9, 9, [1.0, 2.0, 3.0]) == reference(9, 9, names, [1.0, 2.0, 3.0])
    assert cdr.JointStateEncoder([]).encode(4, 5, []) == reference(4, 5, [], [])


@pytest.mark.parametrize('sec, nanosec, names, position, velocity, effort, frame', CASES)
def test_fast_decoder_agrees_with_the_generic_one(sec, nanosec, names, position, velocity,
                                                  effort, frame):
    raw = reference(sec, nanosec, names, position, velocity, effort, frame)
    for decoder in (cdr.JointStateDecoder(['stage']),
                    cdr.JointStateDecoder(['stage'], with_velocity=True)):
        # bit for bit: both decoders copy the same float64 bytes, no arithmetic
        np.testing.assert_array_equal(decoder.decode(raw), cdr.decode_joint_state(raw))
    fast = cdr.JointStateDecoder(['stage'], with_velocity=True)
    assert fast.decode(reference(1, 2, ['stage'], [3e-6], [4e-4])) == (1, 2, 3e-6, 4e-4)
    np.testing.assert_array_equal(
        cdr.JointStateDecoder(['stage']).decode(reference(1, 2, ['stage'], [3e-6])),
        (1, 2, 3e-6, math.nan))


def test_float64_and_clock_equal_the_reference():
    for value in (0.0, -2.0, 9.999, math.inf):
        ours = cdr.encode_float64(value)
        assert ours == bytes(STORE.serialize_cdr(Float64(data=value), 'std_msgs/msg/Float64'))
        assert cdr.decode_float64(ours) == value
    assert math.isnan(cdr.decode_float64(cdr.encode_float64(math.nan)))
    clock = Clock(clock=Time(sec=4, nanosec=100_000))
    assert cdr.encode_clock(4, 100_000) == bytes(STORE.serialize_cdr(clock,
                                                                      'rosgraph_msgs/msg/Clock'))


def test_big_endian_messages_decode():
    msg = JointState(header=Header(stamp=Time(sec=3, nanosec=5), frame_id='f'), name=['stage'],
                     position=np.array([1.25]), velocity=np.array([-0.5]),
                     effort=np.array([], dtype=np.float64))
    raw = bytes(STORE.serialize_cdr(msg, 'sensor_msgs/msg/JointState',
                                    little_endian=False))
    assert raw[:2] == b'\x00\x00'
    assert cdr.decode_joint_state(raw) == (3, 5, 1.25, -0.5)
    f64 = bytes(STORE.serialize_cdr(Float64(data=2.5), 'std_msgs/msg/Float64',
                                    little_endian=False))
    assert cdr.decode_float64(f64) == 2.5


def test_bad_bytes_are_refused():
    with pytest.raises(cdr.CdrError, match='encapsulation header'):
        cdr.decode_joint_state(b'\x01\x01\x00\x00' + bytes(60))
    with pytest.raises(cdr.CdrError, match='representation'):
        cdr.decode_float64(b'\x00\x07\x00\x00' + bytes(8))
    with pytest.raises(cdr.CdrError, match='truncated JointState'):
        cdr.decode_joint_state(cdr.encode_joint_state(1, 2, ['stage'], [1.0])[:40])
    with pytest.raises(cdr.CdrError, match='12 bytes'):
        cdr.decode_float64(cdr.HEADER_LE + b'\x00' * 4)


# --- the batch layouts of the bag tools: the same codec, many messages at once ------------

LAYOUT_CASES = [
    ('', ['stage'], 1, 0, 0),
    ('', ['stage'], 1, 1, 0),
    ('', ['error_v', 'integral_v_s', 'saturated'], 3, 0, 0),
    ('frame', ['a', 'bc'], 2, 2, 1),
    ('xyz12', [], 0, 0, 0),
]


@pytest.mark.parametrize('frame, names, n_pos, n_vel, n_eff', LAYOUT_CASES)
def test_batch_layout_equals_the_reference(frame, names, n_pos, n_vel, n_eff):
    layout = cdr.joint_state_layout(frame_id=frame, names=names, n_position=n_pos,
                                    n_velocity=n_vel, n_effort=n_eff)
    rng = np.random.default_rng(3)
    n = 5
    stamp_ns = np.array([0, 1, 999_999_999, 1_600_000_000_123_456_789, 2**31 * 10**9 - 1])
    values = {'position': rng.normal(size=(n, n_pos)), 'velocity': rng.normal(size=(n, n_vel)),
              'effort': rng.normal(size=(n, n_eff))}
    rows = layout.encode(stamp_ns, {k: v for k, v in values.items() if v.shape[1]}, n)
    for i in range(n):
        sec, nsec = divmod(int(stamp_ns[i]), 1_000_000_000)
        expected = reference(sec, nsec, names, values['position'][i], values['velocity'][i],
                             values['effort'][i], frame)
        assert rows[i].tobytes() == expected
    ok, stamps, arrays = layout.decode(rows)
    assert ok.all()
    np.testing.assert_array_equal(stamps, stamp_ns)
    for name, vals in values.items():
        if vals.shape[1]:
            np.testing.assert_array_equal(arrays[name], vals)


def test_batch_layout_rejects_rows_of_another_layout():
    layout = cdr.joint_state_layout(names=['stage'], n_position=1)
    ours = np.frombuffer(reference(1, 2, ['stage'], [3.0]), np.uint8)
    other = np.frombuffer(reference(1, 2, ['stagf'], [3.0]), np.uint8)  # same size
    ok, stamps, arrays = layout.decode(np.stack([ours, other, ours]))
    np.testing.assert_array_equal(ok, [True, False, True])
    np.testing.assert_array_equal(arrays['position'][:, 0], [3.0, 3.0])


def test_float64_layout_equals_the_reference():
    layout = cdr.float64_layout()
    data = np.array([[0.0], [-2.5], [math.inf]])
    rows = layout.encode(None, {'data': data}, 3)
    for i, value in enumerate(data[:, 0]):
        assert rows[i].tobytes() == bytes(STORE.serialize_cdr(Float64(data=value),
                                                              'std_msgs/msg/Float64'))
    ok, stamps, arrays = layout.decode(rows)
    assert ok.all() and stamps is None
    np.testing.assert_array_equal(arrays['data'], data)


@pytest.mark.parametrize('little_endian', [True, False])
@pytest.mark.parametrize('sec, nanosec, names, position, velocity, effort, frame', CASES)
def test_generic_decoder_reads_every_field(sec, nanosec, names, position, velocity, effort,
                                           frame, little_endian):
    msg = JointState(header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame),
                     name=list(names), position=np.array(position, dtype=np.float64),
                     velocity=np.array(velocity, dtype=np.float64),
                     effort=np.array(effort, dtype=np.float64))
    raw = bytes(STORE.serialize_cdr(msg, 'sensor_msgs/msg/JointState',
                                    little_endian=little_endian))
    got = cdr.decode_joint_state_message(raw)
    assert (got.sec, got.nanosec, got.frame_id, got.names) == (sec, nanosec, frame, tuple(names))
    for field, expected in (('position', position), ('velocity', velocity),
                            ('effort', effort)):
        np.testing.assert_array_equal(getattr(got, field), np.array(expected, dtype=float))
        assert getattr(got, field).dtype == np.float64


def test_generic_decoder_refuses_overruns():
    raw = bytearray(cdr.encode_joint_state(1, 2, ['stage'], [1.0], [2.0]))
    with pytest.raises(cdr.CdrError, match='truncated'):
        cdr.decode_joint_state_message(bytes(raw[:-1]))
    raw[12] = 0xFF  # frame_id length far beyond the message
    with pytest.raises(cdr.CdrError, match='truncated'):
        cdr.decode_joint_state_message(bytes(raw))
