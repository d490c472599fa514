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
The few messages of the loop in CDR, encoded and decoded with ``struct`` (rclpy-free).

At 10 kHz the cost of rclpy message objects dominates a sample: building a ``JointState``
from a received message takes tens of microseconds, publishing one about as much. The nodes
therefore subscribe with ``raw=True`` and publish ``bytes``: this module turns those bytes into
plain values and back. The encoding is the one every ROS 2 middleware uses on the wire (OMG CDR,
XCDR1, little-endian by default, alignment relative to the end of the 4-byte encapsulation
header); a CI test checks it byte for byte against the serializer of ``rosbags`` for every
message the nodes send, and decodes messages ``rosbags`` wrote in both byte orders.

Layouts (``B`` = byte offset in the body, after the 4-byte header)::

    std_msgs/Float64         B0 float64 data
    rosgraph_msgs/Clock      B0 int32 sec, B4 uint32 nanosec
    sensor_msgs/JointState   B0 int32 sec, B4 uint32 nanosec, B8 string frame_id,
                             sequence<string> name, sequence<float64> position, velocity, effort

(string: uint32 length including the NUL, the characters, NUL; sequence: uint32 count, then the
elements, each aligned to its own size.)
"""

from __future__ import annotations

import math
import struct
from typing import Final, Sequence

__all__ = ['CdrError', 'JointStateDecoder', 'JointStateEncoder', 'decode_float64',
           'decode_joint_state',
           'encode_clock', 'encode_float64', 'encode_joint_state']

HEADER_LE: Final = b'\x00\x01\x00\x00'
_U32 = {'<': struct.Struct('<I'), '>': struct.Struct('>I')}
_F64 = {'<': struct.Struct('<d'), '>': struct.Struct('>d')}
_STAMP = {'<': struct.Struct('<iI'), '>': struct.Struct('>iI')}
_FLOAT64_LE = struct.Struct('<4sd')
_CLOCK_LE = struct.Struct('<4siI')


class CdrError(ValueError):
    """Bytes that are not a CDR message of the expected type."""


def _order(data: bytes) -> str:
    if len(data) < 4 or data[0] != 0:
        raise CdrError('not a CDR message (bad encapsulation header)')
    if data[1] in (0, 2):
        return '>'
    if data[1] in (1, 3):
        return '<'
    raise CdrError(f'unsupported CDR representation {data[1]}')


def encode_float64(value: float) -> bytes:
    """Return ``std_msgs/msg/Float64`` with ``data`` = ``value``."""
    return _FLOAT64_LE.pack(HEADER_LE, value)


def decode_float64(data: bytes) -> float:
    """Return ``data`` of a ``std_msgs/msg/Float64``."""
    order = _order(data)
    if len(data) < 12:
        raise CdrError(f'Float64 needs 12 bytes, got {len(data)}')
    return float(_F64[order].unpack_from(data, 4)[0])


def encode_clock(sec: int, nanosec: int) -> bytes:
    """Return ``rosgraph_msgs/msg/Clock`` for the time ``sec`` [s] + ``nanosec`` [ns]."""
    return _CLOCK_LE.pack(HEADER_LE, sec, nanosec)


def _string(text: str, offset: int) -> tuple[bytes, int]:
    """Return the CDR of a string starting at body offset ``offset``, and the new offset."""
    raw = text.encode('utf-8') + b'\x00'
    pad = (-offset) % 4
    return b'\x00' * pad + struct.pack('<I', len(raw)) + raw, offset + pad + 4 + len(raw)


def _doubles(values: Sequence[float], offset: int) -> tuple[bytes, int]:
    pad = (-offset) % 4
    out = b'\x00' * pad + struct.pack('<I', len(values))
    offset += pad + 4
    if values:
        pad = (-offset) % 8
        out += b'\x00' * pad + struct.pack(f'<{len(values)}d', *values)
        offset += pad + 8 * len(values)
    return out, offset


def encode_joint_state(sec: int, nanosec: int, names: Sequence[str],
                       position: Sequence[float], velocity: Sequence[float] = (),
                       effort: Sequence[float] = (), frame_id: str = '') -> bytes:
    """
    Return a ``sensor_msgs/msg/JointState``.

    Parameters
    ----------
    sec, nanosec : int
        Header stamp [s] and [ns].
    names : sequence of str
        Joint names.
    position, velocity, effort : sequence of float
        The arrays (SI units of the joint).
    frame_id : str
        Header frame.

    Returns
    -------
    bytes
        Little-endian CDR with its encapsulation header.

    """
    parts = [HEADER_LE, struct.pack('<iI', sec, nanosec)]
    chunk, offset = _string(frame_id, 8)
    parts.append(chunk)
    pad = (-offset) % 4
    parts.append(b'\x00' * pad + struct.pack('<I', len(names)))
    offset += pad + 4
    for name in names:
        chunk, offset = _string(name, offset)
        parts.append(chunk)
    for values in (position, velocity, effort):
        chunk, offset = _doubles(list(values), offset)
        parts.append(chunk)
    return b''.join(parts)


class JointStateEncoder:
    """
    Fast encoder of JointStates with fixed names and array lengths (the loop's messages).

    Parameters
    ----------
    names : sequence of str
        Joint names (``['stage']``, or the controller's diagnostic keys).
    with_velocity : bool
        Whether a velocity array of the same length follows the positions.

    """

    def __init__(self, names: Sequence[str], with_velocity: bool = False) -> None:
        n = len(names)
        zeros = [0.0] * n
        template = encode_joint_state(0, 0, names, zeros, zeros if with_velocity else ())
        probe = encode_joint_state(0, 0, names, [1.0] * n, [2.0] * n if with_velocity else ())
        # the arrays start where the probe's marker values are
        self._template = bytearray(template)
        self._n = n
        self._values = struct.Struct(f'<{n}d')
        self._pos_at = probe.index(struct.pack('<d', 1.0)) if n else -1
        self._vel_at = probe.index(struct.pack('<d', 2.0)) if n and with_velocity else -1

    def encode(self, sec: int, nanosec: int, position: Sequence[float],
               velocity: Sequence[float] | None = None) -> bytes:
        """Return the message with this stamp and these values."""
        buf = self._template
        _STAMP['<'].pack_into(buf, 4, sec, nanosec)
        if self._pos_at >= 0:
            self._values.pack_into(buf, self._pos_at, *position)
        if velocity is not None and self._vel_at >= 0:
            self._values.pack_into(buf, self._vel_at, *velocity)
        return bytes(buf)


def _skip_string(data: bytes, offset: int, order: str) -> int:
    offset += (-offset) % 4
    (length,) = _U32[order].unpack_from(data, 4 + offset)
    return offset + 4 + length


def decode_joint_state(data: bytes) -> tuple[int, int, float, float]:
    """
    Return the stamp and the first position and velocity of a ``sensor_msgs/msg/JointState``.

    Returns
    -------
    sec, nanosec : int
        Header stamp.
    position : float
        ``position[0]`` (NaN when the array is empty).
    velocity : float
        ``velocity[0]`` (NaN when the array is empty).

    Raises
    ------
    CdrError
        If the bytes are not a JointState.

    """
    order = _order(data)
    try:
        sec, nanosec = _STAMP[order].unpack_from(data, 4)
        offset = _skip_string(data, 8, order)
        offset += (-offset) % 4
        (count,) = _U32[order].unpack_from(data, 4 + offset)
        offset += 4
        for _ in range(count):
            offset = _skip_string(data, offset, order)
        first = []
        for _ in range(2):
            offset += (-offset) % 4
            (count,) = _U32[order].unpack_from(data, 4 + offset)
            offset += 4
            if count:
                offset += (-offset) % 8
                first.append(_F64[order].unpack_from(data, 4 + offset)[0])
                offset += 8 * count
            else:
                first.append(math.nan)
    except struct.error:
        raise CdrError(f'truncated JointState ({len(data)} bytes)') from None
    if 4 + offset > len(data):
        raise CdrError(f'truncated JointState ({len(data)} bytes)')
    return sec, nanosec, float(first[0]), float(first[1])


class JointStateDecoder:
    """
    Fast decoder of the loop's JointStates, with the generic decoder as fallback.

    A message laid out exactly as ``JointStateEncoder(names, with_velocity)`` lays it out
    (little-endian, empty frame, these names, one-element arrays) is read at fixed offsets; any
    other JointState goes through :func:`decode_joint_state`, so the fast path is an
    optimisation, never a guess.

    Parameters
    ----------
    names : sequence of str
        The expected joint names (``['stage']``).
    with_velocity : bool
        Whether a one-element velocity array is expected.

    """

    def __init__(self, names: Sequence[str], with_velocity: bool = False) -> None:
        values = (1.0,) * len(names)
        probe = encode_joint_state(0, 0, names, values, (2.0,) * len(names) if with_velocity
                                   else ())
        self._size = len(probe)
        self._pos_at = probe.index(struct.pack('<d', 1.0)) if names else -1
        self._vel_at = probe.index(struct.pack('<d', 2.0)) if names and with_velocity else -1
        # the bytes between the stamp and the first value (frame, names, counts) must match;
        # with the length fixed that pins the layout down (any other array count changes it)
        self._head = probe[12:self._pos_at] if names else b''
        self._middle = probe[self._pos_at + 8:self._vel_at] if self._vel_at >= 0 else b''
        # one unpack for stamp and values, the bytes between them skipped
        fmt = f'<4xiI{self._pos_at - 12}xd' if names else '<4xiI'
        if self._vel_at >= 0:
            fmt += f'{self._vel_at - self._pos_at - 8}xd'
        self._fast = struct.Struct(fmt)

    def decode(self, data: bytes) -> tuple[int, int, float, float]:
        """Return ``(sec, nanosec, position[0], velocity[0])`` (NaN for an empty array)."""
        pos_at = self._pos_at
        if len(data) == self._size and pos_at >= 0 and data[:4] == HEADER_LE and \
                data[12:pos_at] == self._head:
            if self._vel_at < 0:
                sec, nanosec, position = self._fast.unpack_from(data)
                return sec, nanosec, position, math.nan
            if data[pos_at + 8:self._vel_at] == self._middle:
                sec, nanosec, position, velocity = self._fast.unpack_from(data)
                return sec, nanosec, position, velocity
        return decode_joint_state(data)
