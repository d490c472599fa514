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
Version 4 of the UDP protocol: a stage of several axes, and its host-side bridge.

Version 3 (:mod:`piezo_stage_ros.hardware.udp`) carries one axis; version 4 carries the axis
count in the header and one value per axis in each field, little-endian, packed, the doubles
aligned on 8 bytes:

Request, host -> target, 16 bytes, ``'<2sBBIB3xI'``, then ``axes`` doubles (the commands [V],
axis order), then ``axes * count`` doubles (the commands ahead [V], axis after axis: entry
``a * count + i`` is axis a's prediction for the i-th sample after this one):

======  =====  ======  =============================================================
offset  bytes  type    field
======  =====  ======  =============================================================
0       2      char    magic ``b'PZ'``
2       1      uint8   version, :data:`VERSION_AXES` (4)
3       1      uint8   kind, as version 3 (HELLO, COMMAND, STOP, STREAM)
4       4      uint32  sequence number
8       1      uint8   ``axes``: the axis count N (1 .. 3)
9       3              padding (zero)
12      4      uint32  ``count``: commands ahead per axis (0 .. :func:`max_ahead` (N))
======  =====  ======  =============================================================

Reply, target -> host, 24 bytes, ``'<2sBBIB3xII4x'``, then ``axes`` doubles (the measured
positions [m], axis order): magic, version 4, kind | 0x80, sequence number, the target's axis
count, status bits (as version 3, and 32: request refused, another axis count), requests
missing so far.

Each side refuses what it cannot serve and says which: a target of another version answers
with a reply of its own version and status 16, a target of N axes answers a request of
another count with status 32 and its own count in ``axes``; the host raises
:class:`~piezo_stage_ros.hardware.bridge.BridgeError` naming both versions or both counts.
"""

from __future__ import annotations

import math
import struct
from typing import Any, Callable, Final, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.hardware.bridge import BridgeError
from piezo_stage_ros.hardware.udp import (
    COMMAND,
    MAGIC,
    MAX_AHEAD,
    REPLY_FLAG,
    UdpBridge,
)

__all__ = ['MAX_AXES', 'REPLY_AXES', 'REQUEST_AXES', 'STATUS_AXES', 'UdpAxesBridge',
           'VERSION_AXES', 'max_ahead', 'pack_axes_reply', 'pack_axes_request',
           'unpack_axes_reply', 'unpack_axes_request']

VERSION_AXES: Final = 4
#: Most axes a datagram carries.
MAX_AXES: Final = 3
#: The request is refused: the target has another axis count (in the reply's ``axes``).
STATUS_AXES: Final = 32
REQUEST_AXES: Final = struct.Struct('<2sBBIB3xI')
REPLY_AXES: Final = struct.Struct('<2sBBIB3xII4x')
_SEQ_MOD: Final = 2 ** 32


def max_ahead(axes: int) -> int:
    """
    Return the most commands ahead per axis a request of ``axes`` axes carries.

    The datagram of version 3 at its largest (:data:`MAX_AHEAD` commands ahead and the
    command): as many doubles, shared by the axes.
    """
    return (MAX_AHEAD + 1) // max(int(axes), 1) - 1


def _check_axes(axes: int) -> None:
    if not 1 <= axes <= MAX_AXES:
        raise ParameterError('axes', axes, f'[1, {MAX_AXES}]')


def pack_axes_request(kind: int, seq: int, values_v: Sequence[float],
                      ahead_v: Any = None) -> bytes:
    """
    Return a request of version 4.

    Parameters
    ----------
    kind, seq : int
        As version 3.
    values_v : sequence of float
        One command per axis [V].
    ahead_v : array_like, optional
        (axes, count) commands ahead [V]; None: none.

    """
    axes = len(values_v)
    _check_axes(axes)
    ahead = np.zeros((axes, 0)) if ahead_v is None else np.asarray(ahead_v, dtype='<f8')
    if ahead.ndim != 2 or ahead.shape[0] != axes:
        raise ParameterError('commands ahead', ahead.shape, f'({axes}, count): one row per axis')
    count = ahead.shape[1]
    if count > max_ahead(axes):
        raise ParameterError('commands ahead', count, f'[0, {max_ahead(axes)}] per axis')
    head = REQUEST_AXES.pack(MAGIC, VERSION_AXES, kind, seq % _SEQ_MOD, axes, count)
    body = np.asarray(values_v, dtype='<f8').tobytes() + np.ascontiguousarray(ahead).tobytes()
    return head + body


def unpack_axes_request(data: bytes
                        ) -> tuple[int, int, int, tuple[float, ...], Any] | None:
    """
    Return ``(kind, seq, axes, values_v, ahead_v)`` of a request of version 4, else None.

    ``ahead_v``: an (axes, count) array [V] (count 0: none). The axis count is returned as
    sent (1 .. :data:`MAX_AXES`); the target compares it with its own.
    """
    if len(data) < REQUEST_AXES.size:
        return None
    magic, version, kind, seq, axes, count = REQUEST_AXES.unpack_from(data)
    if magic != MAGIC or version != VERSION_AXES or kind & REPLY_FLAG or \
            not 1 <= axes <= MAX_AXES or len(data) != REQUEST_AXES.size + 8 * axes * (1 + count):
        return None
    values = struct.unpack_from(f'<{axes}d', data, REQUEST_AXES.size)
    ahead = np.frombuffer(data, dtype='<f8', count=axes * count,
                          offset=REQUEST_AXES.size + 8 * axes).reshape(axes, count)
    return kind, seq, axes, values, ahead


def pack_axes_reply(kind: int, seq: int, positions_m: Sequence[float], status: int,
                    missing: int) -> bytes:
    """Return the reply of version 4 to request ``kind`` / ``seq`` (one position per axis)."""
    axes = len(positions_m)
    return REPLY_AXES.pack(MAGIC, VERSION_AXES, kind | REPLY_FLAG, seq % _SEQ_MOD, axes,
                           status, missing % _SEQ_MOD) + struct.pack(f'<{axes}d', *positions_m)


def unpack_axes_reply(data: bytes
                      ) -> tuple[int, int, int, tuple[float, ...], int, int] | None:
    """Return ``(kind, seq, axes, positions_m, status, missing)`` of a reply, else None."""
    if len(data) < REPLY_AXES.size:
        return None
    magic, version, kind, seq, axes, status, missing = REPLY_AXES.unpack_from(data)
    if magic != MAGIC or version != VERSION_AXES or not kind & REPLY_FLAG or \
            len(data) != REPLY_AXES.size + 8 * axes:
        return None
    positions = struct.unpack_from(f'<{axes}d', data, REPLY_AXES.size)
    return kind & ~REPLY_FLAG, seq, axes, positions, status, missing


class UdpAxesBridge(UdpBridge):
    """
    The host side of version 4, request-reply: one datagram a sample for every axis.

    The backend of N axes (:class:`~piezo_stage_ros.hardware.axes.AxesGuard` drives it):
    each axis' voltage is set (:meth:`set_axis`), :meth:`read_positions` sends them for one
    sample and returns every axis' position at its end (the last ones held on a loss, counted
    as in version 3). A request-reply target steps a sample per request, so the commands
    ahead are not sent.

    Parameters
    ----------
    host, port : str, int
        The target.
    axes : int
        The axis count (the target must have as many).
    timeout_s, max_consecutive_losses, hello_attempts
        As :class:`~piezo_stage_ros.hardware.udp.UdpBridge`.

    """

    def __init__(self, host: str, port: int, axes: int, *, timeout_s: float = 0.002,
                 max_consecutive_losses: int = 10, hello_attempts: int = 5) -> None:
        _check_axes(axes)
        super().__init__(host, port, timeout_s=timeout_s,
                         max_consecutive_losses=max_consecutive_losses,
                         hello_attempts=hello_attempts)
        self.n = int(axes)
        self.voltages_v: list[float] = [0.0] * self.n
        self._positions: tuple[float, ...] = (math.nan,) * self.n

    def _send(self, kind: int, seq: int, value_v: Any, ahead_v: Any = ()) -> None:
        sock = self._sock
        if sock is None:
            raise BridgeError('UDP bridge: not open')
        try:
            sock.send(pack_axes_request(kind, seq, value_v))
        except OSError as exc:
            raise BridgeError(f'UDP bridge: send to {self.address[0]}:{self.address[1]} '
                              f'failed ({exc.strerror})') from None

    def _take(self, data: bytes, kind: int, accept: Callable[[int], bool]
              ) -> tuple[int, Any] | None:
        reply = unpack_axes_reply(data)
        where = f'{self.address[0]}:{self.address[1]}'
        if reply is None or reply[0] != kind:
            if len(data) >= 4 and data[:2] == MAGIC and data[2] != VERSION_AXES:
                version = data[2]
                raise BridgeError(f'UDP bridge: the target at {where} speaks protocol version '
                                  f'{version}, this host version {VERSION_AXES} ({self.n} '
                                  'axes); update one of them (docs/reference/udp-protocol.md)')
            self.malformed += 1
            return None
        _, rseq, axes, positions, status, missing = reply
        if status & STATUS_AXES or axes != self.n:
            raise BridgeError(f'UDP bridge: the target at {where} has {axes} axes, this host '
                              f'{self.n}; configure both for the same stage')
        if not self._count_reply(kind, rseq, status, missing, accept, VERSION_AXES):
            return None
        return rseq, positions

    def safe_start(self, safe_voltage_v: Any) -> Any:
        """Send HELLO with every axis' safe voltage and return every axis' y_0 [m]."""
        self.voltages_v = [float(v) for v in safe_voltage_v]
        volts: Any = list(self.voltages_v)
        return list(super().safe_start(volts))  # type: ignore[call-overload]

    def set_axis(self, axis: int, voltage_v: float, ahead_v: Any) -> None:
        """Set one axis' voltage [V] for the next sample (commands ahead: not sent)."""
        del ahead_v
        self.voltages_v[axis] = voltage_v

    def read_positions(self) -> list[float]:
        """Send every axis' voltage for one sample and return the positions at its end [m]."""
        return list(self._measured(self._exchange(COMMAND, self.voltages_v)))  # type: ignore

    def safe_stop(self, safe_voltage_v: Any) -> None:
        """Send STOP with every axis' safe voltage and close the socket."""
        volts: Any = list(safe_voltage_v)
        super().safe_stop(volts)
