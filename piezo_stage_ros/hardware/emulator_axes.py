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
The target emulator of a stage of several axes: the model of N axes behind protocol version 4.

As :class:`~piezo_stage_ros.hardware.emulator.TargetEmulator` (loopback only, the same ways to
stop), request-reply: each COMMAND request of version 4 holds every axis' command over one
sample of an :class:`~piezo_stage_ros.core.model.axes.AxesStage` and is answered with every
axis' position, so that a run through it gives the samples of the model itself. A request of
another version (a version-3 host) is refused with status 16, one of another axis count with
status 32 and this target's count; each said once on stderr.
"""

from __future__ import annotations

import math
import sys
from typing import Any

from piezo_stage_ros.core.contracts.errors import PiezoStageError
from piezo_stage_ros.core.model.axes import AxesStage, AxesStageParams
from piezo_stage_ros.hardware.emulator import LOOPBACK, TargetEmulator
from piezo_stage_ros.hardware.pacing import Pacer
from piezo_stage_ros.hardware.udp import (
    COMMAND,
    HELLO,
    MAGIC,
    STATUS_CLAMPED,
    STATUS_NOT_FINITE,
    STATUS_REFUSED,
    STATUS_VERSION,
    STOP,
)
from piezo_stage_ros.hardware.udp_axes import (
    pack_axes_reply,
    STATUS_AXES,
    unpack_axes_request,
    VERSION_AXES,
)

__all__ = ['AxesTargetEmulator']

_HALF = 2 ** 31


class AxesTargetEmulator(TargetEmulator):
    """
    The target side of version 4, simulating a stage of several axes (request-reply).

    Parameters
    ----------
    params : AxesStageParams
        The simulated stage.
    port, host, idle_timeout_s, max_requests, drop_reply_every
        As :class:`~piezo_stage_ros.hardware.emulator.TargetEmulator`.

    """

    def __init__(self, params: AxesStageParams, *, port: int = 0, host: str = LOOPBACK,
                 idle_timeout_s: float = 5.0, max_requests: int = 0,
                 drop_reply_every: int = 0) -> None:
        super().__init__(params.axes[0], port=port, host=host, idle_timeout_s=idle_timeout_s,
                         max_requests=max_requests, drop_reply_every=drop_reply_every)
        self.axes_params = params
        self.n = params.n
        self.axes_stage = AxesStage(params)
        self._lows = [a.chain.amplifier_min_v for a in params.axes]
        self._highs = [a.chain.amplifier_max_v for a in params.axes]
        self._voltages: tuple[float, ...] = tuple(a.chain.safe_voltage_v for a in params.axes)
        # at rest already (no noise drawn): the noise after HELLO is the offline runner's
        self._positions: list[float] = self.axes_stage.read_positions_m()
        #: Requests refused for another axis count.
        self.refused_axes = 0

    def _refuse(self, data: bytes, status: int, said: str) -> bytes:
        seq = int.from_bytes(data[4:8], 'little')
        if (self.refused_version if status & STATUS_VERSION else self.refused_axes) == 1:
            print(f'stage_emulator: refused a request {said}', file=sys.stderr, flush=True)
        return pack_axes_reply(data[3] & 0x7F, seq, [math.nan] * self.n,
                               STATUS_REFUSED | status, self.missing)

    def _handle(self, data: bytes) -> tuple[bytes | None, bool]:
        """Return the reply to one datagram (None: no reply) and whether the session ends."""
        request = unpack_axes_request(data)
        if request is None:
            if len(data) >= 8 and data[:2] == MAGIC and data[2] != VERSION_AXES:
                self.refused_version += 1
                return self._refuse(data, STATUS_VERSION, f'of protocol version {data[2]} '
                                    f'(this target speaks version {VERSION_AXES}, '
                                    f'{self.n} axes)'), False
            return None, False
        kind, seq, axes, values, _ = request
        if axes != self.n:
            self.refused_axes += 1
            return self._refuse(data, STATUS_AXES, f'of {axes} axes (this target has '
                                f'{self.n})'), False
        if self._expected is not None and kind != HELLO:
            gap = (seq - self._expected) % 2 ** 32
            if gap >= _HALF:
                return None, False  # a duplicate or reordered request: never step twice
            self.missing += gap
        self._expected = (seq + 1) % 2 ** 32
        status = 0
        for u, low, high in zip(values, self._lows, self._highs):
            if not math.isfinite(u):
                status |= STATUS_NOT_FINITE
            elif not low <= u <= high:
                status |= STATUS_CLAMPED
        if kind == HELLO:
            self._positions = self.axes_stage.reset()
            self._voltages = values
            self.missing = 0
        elif kind == COMMAND:
            self.commands += 1
            self._voltages = values
            self._positions = self.axes_stage.step(values)
            if self.drop_reply_every and self.commands % self.drop_reply_every == 0:
                self.dropped += 1
                return None, False
        elif kind == STOP:
            self._voltages = values
            return pack_axes_reply(kind, seq, self._positions, status, self.missing), True
        else:
            status |= STATUS_REFUSED
        return pack_axes_reply(kind, seq, self._positions, status, self.missing), False

    def serve_paced(self, pacer: Pacer | None = None) -> str:
        """Refuse: a stage of several axes is served request-reply (:meth:`serve`)."""
        del pacer
        raise PiezoStageError('stage_emulator: --paced serves one axis (protocol version 3); '
                              'a stage of several axes is served request-reply')

    def stats(self) -> dict[str, Any]:
        """Return the request counters."""
        return {'requests': self.requests, 'commands': self.commands, 'missing': self.missing,
                'refused_version': self.refused_version, 'refused_axes': self.refused_axes}
