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
The CDR codec of the loop's messages: one message at a time for the nodes, many for bags.

ROS 2 middlewares put messages on the wire, and rosbag2 into bags, as OMG CDR (XCDR1, an
encapsulation header of 4 bytes, then the body with every value aligned to its size relative to
the end of that header). The loop has three message types; this module encodes and decodes them
with ``struct`` and numpy only (no rclpy, no rosbags: the nodes and the bag tools share it, and
``core`` may hold it). A test checks every layout byte for byte against the serializer of
``rosbags`` and decodes what ``rosbags`` wrote in both byte orders.

Two speeds, one layout:

- per message (the nodes, 10 kHz): :class:`JointStateEncoder` / :class:`JointStateDecoder` write
  and read a JointState of fixed names at fixed offsets with one ``struct`` call, since an rclpy
  message object costs tens of microseconds; :func:`encode_float64`, :func:`encode_clock`;
- per batch (bags): :class:`Layout` serializes or parses a ``(messages, bytes)`` uint8 matrix at
  once with numpy; every byte that must be constant is compared with the template.

Both find their offsets in a template made by :func:`encode_joint_state` with sentinel values
(:func:`joint_state_layout`). A message that does not fit a layout (another frame_id or names,
big-endian) goes through the generic decoder :func:`decode_joint_state_message`, so the fast
paths are an optimisation, never a guess.

Layouts (``B`` = byte offset in the body, after the 4-byte header)::

    std_msgs/Float64         B0 float64 data
    rosgraph_msgs/Clock      B0 int32 sec, B4 uint32 nanosec
    sensor_msgs/JointState   B0 int32 sec, B4 uint32 nanosec, B8 string frame_id,
                             sequence<string> name, sequence<float64> position, velocity, effort
    std_msgs/Float64MultiArray  B0 sequence<MultiArrayDimension> layout.dim (each: string
                             label, uint32 size, uint32 stride), uint32 layout.data_offset,
                             sequence<float64> data

The block topic (``stage/block``, many samples per message, layout in
:mod:`piezo_stage_ros.core.contracts.wire`) is a Float64MultiArray:
:func:`encode_block` / :func:`decode_block` write and read its (samples, columns) matrix with
one copy of the data.

(string: uint32 length including the NUL, the characters, NUL; sequence: uint32 count, then the
elements, each aligned to its own size.)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
import math
import struct
from typing import Final

import numpy as np
from piezo_stage_ros.core.contracts.errors import BagError
from piezo_stage_ros.core.contracts.types import BoolArray, ByteMatrix, FloatArray, IntArray
from piezo_stage_ros.core.contracts.wire import (
    BLOCK_ROWS_LABEL,
    BLOCK_SEPARATOR,
    is_axes_block,
    NS_PER_S,
    parse_axes_block_columns,
    parse_block_columns,
)

__all__ = ['HEADER_LE', 'CdrError', 'JointStateDecoder', 'JointStateEncoder',
           'JointStateMessage', 'Layout', 'decode_block', 'decode_float64', 'decode_joint_state',
           'decode_joint_state_message', 'decode_multi_array', 'encode_block', 'encode_clock',
           'encode_float64', 'encode_joint_state', 'encode_multi_array', 'float64_layout',
           'joint_state_layout', 'multi_array_layout']


HEADER_LE: Final = b'\x00\x01\x00\x00'
_U32 = {'<': struct.Struct('<I'), '>': struct.Struct('>I')}
_F64 = {'<': struct.Struct('<d'), '>': struct.Struct('>d')}
_STAMP = {'<': struct.Struct('<iI'), '>': struct.Struct('>iI')}
_FLOAT64_LE = struct.Struct('<4sd')
_CLOCK_LE = struct.Struct('<4siI')
_FIELDS: Final = ('position', 'velocity', 'effort')


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


# --------------------------------------------------------------------------------------------
# One message at a time


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


def _read_string(order: str, body: memoryview, offset: int) -> tuple[str, int]:
    """Return the string at body offset ``offset`` (aligned to 4 here) and the offset after it."""
    offset += (-offset) % 4
    (length,) = _U32[order].unpack_from(body, offset)
    end = offset + 4 + length
    if length < 1 or end > len(body):
        raise struct.error('string overruns the message')
    return bytes(body[offset + 4:end - 1]).decode('utf-8'), end


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


@dataclass(frozen=True)
class JointStateMessage:
    """
    A decoded ``sensor_msgs/msg/JointState``.

    Attributes
    ----------
    sec, nanosec : int
        Header stamp [s] and [ns].
    frame_id : str
        Header frame.
    names : tuple of str
        Joint names.
    position, velocity, effort : ndarray of float64
        The arrays (native byte order).

    """

    sec: int
    nanosec: int
    frame_id: str
    names: tuple[str, ...]
    position: FloatArray
    velocity: FloatArray
    effort: FloatArray


def decode_joint_state_message(data: bytes) -> JointStateMessage:
    """
    Decode a whole ``sensor_msgs/msg/JointState``, in either byte order.

    Raises
    ------
    CdrError
        If the bytes are not a JointState (bad header, truncated, a string not UTF-8).

    """
    order = _order(data)
    u32 = _U32[order].unpack_from
    body = memoryview(data)[4:]

    def string(offset: int) -> tuple[str, int]:
        return _read_string(order, body, offset)

    try:
        sec, nanosec = _STAMP[order].unpack_from(body, 0)
        frame_id, offset = string(8)
        offset += (-offset) % 4
        (count,) = u32(body, offset)
        offset += 4
        names = []
        for _ in range(count):
            name, offset = string(offset)
            names.append(name)
        arrays = []
        for _ in _FIELDS:
            offset += (-offset) % 4
            (count,) = u32(body, offset)
            offset += 4
            if count:
                offset += (-offset) % 8
            if offset + 8 * count > len(body):
                raise struct.error('array overruns the message')
            arrays.append(np.frombuffer(body, dtype=f'{order}f8', count=count,
                                        offset=offset).astype(np.float64))
            offset += 8 * count
    except (struct.error, UnicodeDecodeError):
        raise CdrError(f'truncated JointState ({len(data)} bytes)') from None
    return JointStateMessage(int(sec), int(nanosec), frame_id, tuple(names), *arrays)


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
    msg = decode_joint_state_message(data)
    return (msg.sec, msg.nanosec,
            float(msg.position[0]) if msg.position.size else math.nan,
            float(msg.velocity[0]) if msg.velocity.size else math.nan)


class JointStateEncoder:
    """
    Fast encoder of JointStates with fixed names and array lengths (the loop's messages).

    Parameters
    ----------
    names : sequence of str
        Joint names (``['stage']``, or the controller's diagnostic keys).
    with_velocity : bool
        Whether a velocity array of the same length follows the positions.
    effort : bool
        Put the values in the effort array instead (position and velocity empty): an actuator
        input, as ``stage/applied`` carries it.

    """

    def __init__(self, names: Sequence[str], with_velocity: bool = False,
                 effort: bool = False) -> None:
        n = len(names)
        layout = joint_state_layout(names=names, n_position=0 if effort else n,
                                    n_velocity=n if with_velocity else 0,
                                    n_effort=n if effort else 0)
        self._template = bytearray(layout.template.tobytes())
        for off, count in layout.arrays.values():  # values not given are sent as 0.0
            self._template[off:off + 8 * count] = bytes(8 * count)
        self._values = struct.Struct(f'<{n}d')
        self._pos_at = layout.arrays['effort' if effort else 'position'][0] if n else -1
        self._vel_at = layout.arrays['velocity'][0] if n and with_velocity else -1

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
        layout = joint_state_layout(names=names, n_position=len(names),
                                    n_velocity=len(names) if with_velocity else 0)
        probe = layout.template.tobytes()
        self._size = len(probe)
        self._pos_at = layout.arrays['position'][0] if names else -1
        self._vel_at = layout.arrays['velocity'][0] if names and with_velocity else -1
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


# --------------------------------------------------------------------------------------------
# Float64MultiArray: the block topic


def encode_multi_array(dims: Sequence[tuple[str, int, int]], data: FloatArray,
                       data_offset: int = 0) -> bytes:
    """
    Return a ``std_msgs/msg/Float64MultiArray``.

    Parameters
    ----------
    dims : sequence of (str, int, int)
        ``layout.dim``: (label, size, stride) of each dimension, outermost first.
    data : ndarray of float64
        ``data`` (flattened in C order).
    data_offset : int
        ``layout.data_offset``.

    Returns
    -------
    bytes
        Little-endian CDR with its encapsulation header.

    """
    parts = [HEADER_LE, struct.pack('<I', len(dims))]
    offset = 4
    for label, size, stride in dims:
        chunk, offset = _string(label, offset)
        pad = (-offset) % 4
        parts += [chunk, b'\x00' * pad + struct.pack('<II', size, stride)]
        offset += pad + 8
    values = np.ascontiguousarray(data, dtype='<f8').reshape(-1)
    pad = (-offset) % 4
    parts.append(b'\x00' * pad + struct.pack('<II', data_offset, values.size))
    offset += pad + 8
    if values.size:
        parts += [b'\x00' * ((-offset) % 8), values.tobytes()]
    return b''.join(parts)


def decode_multi_array(data: bytes) -> tuple[list[tuple[str, int, int]], int, FloatArray]:
    """
    Decode a ``std_msgs/msg/Float64MultiArray``, in either byte order.

    Returns
    -------
    dims : list of (str, int, int)
        ``layout.dim``: (label, size, stride).
    data_offset : int
        ``layout.data_offset``.
    values : ndarray of float64
        ``data`` (native byte order).

    Raises
    ------
    CdrError
        If the bytes are not a Float64MultiArray (bad header, truncated, a label not UTF-8).

    """
    order = _order(data)
    u32 = _U32[order].unpack_from
    body = memoryview(data)[4:]
    try:
        (count,) = u32(body, 0)
        offset = 4
        if count > len(body) // 12:
            raise struct.error('dimension count overruns the message')
        dims = []
        for _ in range(count):
            label, end = _read_string(order, body, offset)
            offset = end + (-end) % 4
            size, stride = u32(body, offset)[0], u32(body, offset + 4)[0]
            dims.append((label, int(size), int(stride)))
            offset += 8
        data_offset, n = u32(body, offset)[0], u32(body, offset + 4)[0]
        offset += 8
        if n:
            offset += (-offset) % 8
        if offset + 8 * n > len(body):
            raise struct.error('data overruns the message')
        values = np.frombuffer(body, dtype=f'{order}f8', count=n, offset=offset).astype(
            np.float64)
    except (struct.error, UnicodeDecodeError):
        raise CdrError(f'truncated Float64MultiArray ({len(data)} bytes)') from None
    return dims, int(data_offset), values


def encode_block(columns: Sequence[str], rows: FloatArray) -> bytes:
    """
    Return a block message (``stage/block``) of ``rows`` under these column names.

    Parameters
    ----------
    columns : sequence of str
        Column names (:func:`~piezo_stage_ros.core.contracts.wire.block_columns`).
    rows : ndarray of float64, shape (n, len(columns))
        One sample per row.

    """
    n, c = rows.shape
    if c != len(columns):
        raise ValueError(f'block of {c} columns for {len(columns)} names')
    return encode_multi_array([(BLOCK_ROWS_LABEL, n, n * c),
                               (BLOCK_SEPARATOR.join(columns), c, c)], rows)


def decode_block(data: bytes) -> tuple[tuple[str, ...], FloatArray]:
    """
    Return the column names and the (samples, columns) matrix of a block message.

    Raises
    ------
    CdrError
        If the bytes are not a Float64MultiArray, or its layout is not that of a block (two
        dimensions, the first labelled ``samples``, strides of a dense row-major matrix, no
        data offset, the columns of :func:`~piezo_stage_ros.core.contracts.wire.block_columns`
        or of :func:`~piezo_stage_ros.core.contracts.wire.axes_block_columns`).

    """
    dims, data_offset, values = decode_multi_array(data)
    if len(dims) != 2 or dims[0][0] != BLOCK_ROWS_LABEL or data_offset != 0:
        raise CdrError(f'not a block layout: dims {dims}, data_offset {data_offset}')
    (_, n, stride0), (label, c, stride1) = dims
    if stride1 != c or stride0 != n * c or values.size != n * c:
        raise CdrError(f'not a dense row-major block: dims {dims}, {values.size} values')
    try:
        names = (parse_axes_block_columns(label) if is_axes_block(label)
                 else parse_block_columns(label)).names
    except BagError as err:
        raise CdrError(str(err)) from None
    if len(names) != c:
        raise CdrError(f'block of {c} columns names {len(names)}')
    return names, values.reshape(n, c)


# --------------------------------------------------------------------------------------------
# Many messages at a time


@dataclass(frozen=True)
class Layout:
    """
    Byte layout of one serialized message whose variable parts sit at fixed offsets.

    Offsets count from the start of the message, the encapsulation header included.

    Attributes
    ----------
    template : ndarray of uint8
        A serialized message with sentinel values.
    fixed : ndarray of bool
        True for bytes every message of this layout must share with ``template``.
    stamp_offset : int or None
        Offset of ``header.stamp.sec`` (int32, then uint32 nanosec), None for unstamped types.
    arrays : dict of str to (int, int)
        Float64 fields: name -> (byte offset, element count); arrays of no element are left out.
    names : tuple of str
        JointState ``name`` list (empty for other types).

    """

    template: ByteMatrix
    fixed: BoolArray
    stamp_offset: int | None
    arrays: dict[str, tuple[int, int]]
    names: tuple[str, ...]

    @property
    def size(self) -> int:
        """Return the size of a message [bytes]."""
        return int(self.template.size)

    def encode(self, stamp_ns: IntArray | None, arrays: Mapping[str, FloatArray],
               n: int) -> ByteMatrix:
        """
        Serialize ``n`` messages at once.

        Parameters
        ----------
        stamp_ns : ndarray of int64 or None
            Header stamps [ns] >= 0 (None for unstamped types).
        arrays : dict of str to ndarray
            Per field, a ``(n, count)`` float64 array.
        n : int
            Number of messages.

        Returns
        -------
        ndarray of uint8
            ``(n, size)`` matrix, one serialized message per row.

        """
        out = np.empty((n, self.size), dtype=np.uint8)
        out[:] = self.template
        if self.stamp_offset is not None:
            assert stamp_ns is not None
            off = self.stamp_offset
            stamps = np.empty((n, 2), dtype='<u4')
            stamps[:, 0] = stamp_ns // NS_PER_S
            stamps[:, 1] = stamp_ns % NS_PER_S
            out[:, off:off + 8] = stamps.view(np.uint8)
        for name, (off, count) in self.arrays.items():
            values = np.ascontiguousarray(arrays[name], dtype='<f8').reshape(n, count)
            out[:, off:off + 8 * count] = values.view(np.uint8)
        return out

    def decode(self, rows: ByteMatrix) -> tuple[BoolArray, IntArray | None,
                                                dict[str, FloatArray]]:
        """
        Decode the rows that match this layout.

        Parameters
        ----------
        rows : ndarray of uint8
            ``(n, size)`` serialized messages.

        Returns
        -------
        ok : ndarray of bool
            Rows whose constant bytes match the template; the other outputs hold only these.
        stamp_ns : ndarray of int64 or None
            Header stamps [ns].
        arrays : dict of str to ndarray
            Per field, a ``(n_ok, count)`` float64 array.

        """
        ok = np.all(rows[:, self.fixed] == self.template[self.fixed], axis=1)
        good = rows[ok] if not ok.all() else rows
        stamp_ns: IntArray | None = None
        if self.stamp_offset is not None:
            off = self.stamp_offset
            sec = np.ascontiguousarray(good[:, off:off + 4]).view('<i4')[:, 0].astype(np.int64)
            nsec = np.ascontiguousarray(good[:, off + 4:off + 8]).view('<u4')[:, 0]
            stamp_ns = sec * NS_PER_S + nsec.astype(np.int64)
        arrays = {
            name: np.ascontiguousarray(good[:, off:off + 8 * count]).view('<f8').astype(
                np.float64)
            for name, (off, count) in self.arrays.items()
        }
        return ok, stamp_ns, arrays


# Sentinels that cannot be confused with anything else in a small message.
_SENTINEL_SEC = 0x1A2B3C4D
_SENTINEL_NSEC = 0x1E2F3A4B


def _sentinel(field_index: int, element: int) -> float:
    return float(struct.unpack('<d', bytes([0x5A, 0xA5, 0x3C, 0xC3, element & 0xFF,
                                            field_index, 0x13, 0x91]))[0])


def _find_unique(raw: bytes, needle: bytes, what: str) -> int:
    offset = raw.find(needle)
    if offset < 0 or raw.find(needle, offset + 1) >= 0:
        raise CdrError(f'internal error: cannot locate {what} in the serialized template')
    return offset


def _layout(raw: bytes, stamp_offset: int | None, offsets: dict[str, tuple[int, int]],
            names: tuple[str, ...]) -> Layout:
    template = np.frombuffer(raw, dtype=np.uint8).copy()
    fixed = np.ones(template.size, dtype=bool)
    if stamp_offset is not None:
        fixed[stamp_offset:stamp_offset + 8] = False
    for off, count in offsets.values():
        fixed[off:off + 8 * count] = False
    return Layout(template, fixed, stamp_offset, offsets, names)


def float64_layout() -> Layout:
    """Return the layout of ``std_msgs/msg/Float64`` (field ``data``, one element)."""
    value = _sentinel(0, 0)
    raw = encode_float64(value)
    return _layout(raw, None, {'data': (_find_unique(raw, struct.pack('<d', value), 'data'), 1)},
                   ())


def joint_state_layout(*, frame_id: str = '', names: Sequence[str] = (), n_position: int = 0,
                       n_velocity: int = 0, n_effort: int = 0) -> Layout:
    """
    Return the little-endian layout of a ``sensor_msgs/msg/JointState`` of this shape.

    Parameters
    ----------
    frame_id : str
        Header frame.
    names : sequence of str
        Joint names.
    n_position, n_velocity, n_effort : int
        Lengths of the arrays.

    Returns
    -------
    Layout
        Stamp at offset 4; ``arrays`` has ``position``, ``velocity``, ``effort`` where not
        empty.

    """
    counts = {'position': n_position, 'velocity': n_velocity, 'effort': n_effort}
    values = {name: [_sentinel(i + 1, j) for j in range(count)]
              for i, (name, count) in enumerate(counts.items())}
    raw = encode_joint_state(_SENTINEL_SEC, _SENTINEL_NSEC, names, values['position'],
                             values['velocity'], values['effort'], frame_id)
    stamp_offset = _find_unique(raw, struct.pack('<iI', _SENTINEL_SEC, _SENTINEL_NSEC),
                                'header.stamp')
    offsets = {name: (_find_unique(raw, struct.pack(f'<{len(vals)}d', *vals), name), len(vals))
               for name, vals in values.items() if vals}
    return _layout(raw, stamp_offset, offsets, tuple(names))


def multi_array_layout(dims: Sequence[tuple[str, int, int]], count: int) -> Layout:
    """
    Return the little-endian layout of a ``std_msgs/msg/Float64MultiArray`` of fixed shape.

    Parameters
    ----------
    dims : sequence of (str, int, int)
        ``layout.dim`` (label, size, stride), the same in every message; ``data_offset`` 0.
    count : int
        Length of ``data``, >= 1.

    Returns
    -------
    Layout
        No stamp; ``arrays`` has ``data`` (``count`` elements).

    """
    values = [_sentinel(0, j) for j in range(count)]
    raw = encode_multi_array(dims, np.asarray(values, dtype=np.float64))
    offset = _find_unique(raw, struct.pack(f'<{count}d', *values), 'data')
    return _layout(raw, None, {'data': (offset, count)}, ())
