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
A binary protocol over UDP to an external real-time I/O target, and its host-side bridge.

The target (an FPGA, a microcontroller or a rapid-control-prototyping box) owns the DAC, the
amplifier input and the position ADC. The host sends one request per sample and the target
answers with the position measured at the end of that sample. Every datagram is one packet,
little-endian, packed without padding (``struct`` formats below):

Request, host -> target, 20 bytes and ``count`` doubles, ``'<2sBBIdI'`` + ``count * 'd'``:

======  =========  ======  ===========================================================
offset  bytes      type    field
======  =========  ======  ===========================================================
0       2          char    magic ``b'PZ'``
2       1          uint8   version, :data:`VERSION` (3)
3       1          uint8   kind: 1 HELLO (reset, drive ``value`` = safe voltage),
                           2 COMMAND (hold ``value`` over one sample), 3 STOP (drive
                           ``value`` = safe voltage and end the session)
4       4          uint32  sequence number, +1 per request, wraps at 2**32
8       8          double  value [V]: the amplifier input voltage
16      4          uint32  ``count``: commands ahead that follow (0 .. :data:`MAX_AHEAD`)
20      8 count    double  commands ahead [V]: the commands the host predicts for the
                           ``count`` samples after this one (COMMAND of a stream; see below)
======  =========  ======  ===========================================================

Reply, target -> host, 24 bytes, ``'<2sBBIdII'``:

======  =====  ======  ===============================================================
offset  bytes  type    field
======  =====  ======  ===============================================================
0       2      char    magic ``b'PZ'``
2       1      uint8   version (3)
3       1      uint8   kind of the request | 0x80
4       4      uint32  sequence number of the request answered
8       8      double  measured position [m] at the end of the sample
16      4      uint32  status bits: 1 command clamped, 2 command not finite (safe voltage
                       applied), 4 request refused (bad kind), 8 the sample applied a
                       command ahead (no command answered the one before in time), 16
                       request refused: another protocol version
20      4      uint32  requests the target found missing so far (gaps in sequence numbers)
======  =====  ======  ===============================================================

Versions: version 1 had no commands ahead (a 16-byte request); in version 2 a command without
commands ahead emptied the target's queue (see below). Each side refuses a datagram
of another version, and says so: the target answers it with a reply of its own version, status
16 (and the emulator prints it); the host raises
:class:`~piezo_stage_ros.hardware.bridge.BridgeError` naming both versions.

Target-paced streaming (kind 4, STREAM): the target owns the sample clock, as a real-time
target does. The host sends STREAM with the safe voltage; the target resets, drives it, and from
then on takes one sample every period on its own clock and sends it unasked as a reply of kind
STREAM (sequence number = the sample's number k, from 0; position y_k; status; missing). The host
answers each sample with a COMMAND whose sequence number is k and whose value is u_k. At its
next sample the target applies the newest command it has received (zero-order hold) and counts
the sample *missing* when no command answering the previous sample came in time. STOP ends the
stream (replied with kind STOP). :class:`UdpStreamBridge` is the host side.

Commands ahead: a COMMAND of a stream may carry the commands the host predicts for the samples
after the one it answers (the controller's, :mod:`piezo_stage_ros.core.control.ahead`): entry i
is its prediction of the command answering sample seq + 1 + i. The target keeps the newest
such queue and the number q of the command it came with; a command without commands ahead
leaves the queue as it is. When sample j has no command answering sample j - 1, the target
applies the queue's prediction for it (entry j - 2 - q; the last one after the queue) instead of
holding the newest command, and sets status 8 on sample j. When the newest command n is newer
than q (and inside the queue), that prediction is moved onto it: plus u_n minus the queue's
prediction for n (entry n - 1 - q), so that a queue a few samples old goes on from the command
actually applied. A command that arrives late (answering an older sample) is taken the same way.
With no queue (a host that sends none) the command is held as in version 1.

The host may send its answer twice: first the command alone, as soon as it is computed (the
target waits for it), then the same COMMAND with its commands ahead (only samples the host will
miss need them). :class:`UdpStreamBridge` does so (:meth:`UdpStreamBridge.write_ahead`), and
only when it keeps up (:meth:`UdpStreamBridge.ahead_wanted`); a host that falls behind the
target's clock answers the newest sample waiting, not each of a backlog too late.

Timing and losses (request-reply): the host waits for the reply with its own sequence number
for at most ``timeout_s``; a reply with an older number is stale (counted, dropped); no reply in
time is a lost sample (counted; the last position is held). More than
``max_consecutive_losses`` lost samples in a row raise
:class:`~piezo_stage_ros.hardware.bridge.BridgeError`, upon which the plant drives the safe
voltage and stops. Nothing is retransmitted except HELLO: a sample that
is late is worthless.
"""

from __future__ import annotations

import math
import socket
import struct
import time
from typing import Any, Callable, Final, Mapping

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.hardware.bridge import BridgeError
from piezo_stage_ros.hardware.pacing import LatenessStats

__all__ = ['HELLO', 'COMMAND', 'STOP', 'STREAM', 'REPLY', 'REQUEST', 'VERSION', 'MAGIC',
           'MAX_AHEAD', 'UdpBridge', 'UdpStreamBridge', 'foreign_version', 'pack_reply',
           'pack_request', 'RequestBuffer', 'unpack_reply', 'unpack_request']

MAGIC: Final = b'PZ'
VERSION: Final = 3
#: Most commands ahead one request carries (8 kB of them; above 185 a request no longer fits
#: one 1500-byte Ethernet frame).
MAX_AHEAD: Final = 1000
HELLO: Final = 1
COMMAND: Final = 2
STOP: Final = 3
STREAM: Final = 4
REPLY_FLAG: Final = 0x80
STATUS_CLAMPED: Final = 1
STATUS_NOT_FINITE: Final = 2
STATUS_REFUSED: Final = 4
STATUS_PREDICTED: Final = 8
STATUS_VERSION: Final = 16
REQUEST: Final = struct.Struct('<2sBBIdI')
REPLY: Final = struct.Struct('<2sBBIdII')
_SEQ_MOD: Final = 2 ** 32


def pack_request(kind: int, seq: int, value_v: float, ahead_v: Any = ()) -> bytes:
    """Return the request datagram (``kind``, sequence number, voltage [V], commands ahead)."""
    datagram = RequestBuffer()
    return bytes(datagram.view[:datagram.pack(kind, seq, value_v, ahead_v)])


class RequestBuffer:
    """
    One request datagram's memory, reused for each request a host sends.

    The commands-ahead field is an array view whose doubles are aligned (numpy on unaligned
    memory took 21 us for 128 of them here, 12 us aligned), so the datagram starts a few bytes
    into its storage.

    Attributes
    ----------
    view : memoryview
        The datagram (slice it to the size :meth:`pack` returns).

    """

    __slots__ = ('_storage', 'view', '_ahead', '_offset')

    def __init__(self) -> None:
        size = REQUEST.size + 8 * MAX_AHEAD
        self._storage = bytearray(size + 8)
        address = np.frombuffer(self._storage, dtype=np.uint8).ctypes.data
        self._offset = -(address + REQUEST.size) % 8
        self.view = memoryview(self._storage)[self._offset:self._offset + size]
        self._ahead = np.frombuffer(self._storage, dtype='<f8', count=MAX_AHEAD,
                                    offset=self._offset + REQUEST.size)

    def pack(self, kind: int, seq: int, value_v: float, ahead_v: Any = ()) -> int:
        """
        Pack a request (fields as :func:`pack_request`) and return its size [bytes].

        The commands ahead are written straight into the buffer: a sequence computed when
        read (``core.control.ahead.Ahead``) through its ``values_into``, any other at once; no
        array or bytes are made on the way.
        """
        count = len(ahead_v)
        if count > MAX_AHEAD:
            raise ParameterError('commands ahead', count, f'[0, {MAX_AHEAD}]')
        REQUEST.pack_into(self._storage, self._offset, MAGIC, VERSION, kind, seq % _SEQ_MOD,
                          value_v, count)
        if count:
            field = self._ahead[:count]
            values_into = getattr(ahead_v, 'values_into', None)
            if values_into is not None:
                values_into(field)
            else:
                field[:] = ahead_v
        return REQUEST.size + 8 * count


def unpack_request(data: bytes) -> tuple[int, int, float, tuple[float, ...]] | None:
    """
    Return ``(kind, seq, value_v, ahead_v)`` of a request datagram, or None if it is not one.

    ``ahead_v``: its commands ahead [V] (empty: none).
    """
    if len(data) < REQUEST.size:
        return None
    magic, version, kind, seq, value, count = REQUEST.unpack_from(data)
    if magic != MAGIC or version != VERSION or kind & REPLY_FLAG or \
            len(data) != REQUEST.size + 8 * count:
        return None
    ahead = struct.unpack_from(f'<{count}d', data, REQUEST.size) if count else ()
    return kind, seq, value, ahead


def foreign_version(data: bytes) -> int | None:
    """Return the version of a datagram of this protocol but of another version, else None."""
    if len(data) >= 4 and data[:2] == MAGIC and data[2] != VERSION:
        return int(data[2])
    return None


def pack_reply(kind: int, seq: int, position_m: float, status: int, missing: int) -> bytes:
    """Return the reply datagram to request ``kind`` / ``seq``."""
    return REPLY.pack(MAGIC, VERSION, kind | REPLY_FLAG, seq % _SEQ_MOD, position_m,
                      status, missing % _SEQ_MOD)


def unpack_reply(data: bytes) -> tuple[int, int, float, int, int] | None:
    """Return ``(kind, seq, position_m, status, missing)`` of a reply, or None if not one."""
    if len(data) != REPLY.size:
        return None
    magic, version, kind, seq, position, status, missing = REPLY.unpack(data)
    if magic != MAGIC or version != VERSION or not kind & REPLY_FLAG:
        return None
    return kind & ~REPLY_FLAG, seq, position, status, missing


class UdpBridge:
    """
    The host side of the UDP protocol: a :class:`~piezo_stage_ros.hardware.bridge.Bridge`.

    Parameters
    ----------
    host : str
        Address of the target.
    port : int
        UDP port of the target.
    timeout_s : float
        Longest wait for one reply [s].
    max_consecutive_losses : int
        Lost samples in a row tolerated before :class:`BridgeError`.
    hello_attempts : int
        HELLO requests sent before giving up on a silent target.

    """

    def __init__(self, host: str, port: int, *, timeout_s: float = 0.002,
                 max_consecutive_losses: int = 10, hello_attempts: int = 5) -> None:
        if not 0 < port < 65536:
            raise ParameterError('bridge.port', port, '[1, 65535]')
        if not (timeout_s > 0.0 and math.isfinite(timeout_s)):
            raise ParameterError('bridge.timeout_s', timeout_s, '(0, inf)')
        if max_consecutive_losses < 0:
            raise ParameterError('bridge.max_consecutive_losses', max_consecutive_losses,
                                 '[0, inf)')
        self.address = (host, port)
        self.timeout_s = timeout_s
        self.max_consecutive_losses = max_consecutive_losses
        self.hello_attempts = max(1, hello_attempts)
        self._sock: socket.socket | None = None
        self._request = RequestBuffer()
        self._seq = 0
        self._voltage_v = 0.0
        self._position_m = math.nan
        self._consecutive = 0
        self.lost = 0
        self.stale = 0
        self.malformed = 0
        self.target_missing = 0
        self.target_clamped = 0
        self.target_predicted = 0
        self.exchanges = 0
        #: Poll the socket without blocking while waiting for a reply (a thread that spins
        #: anyway, the servo loop's) instead of sleeping in ``recv``.
        self.spin = False
        #: Polls that found nothing yet (spinning).
        self.polls = 0

    def open(self) -> None:
        """Create the socket, connected to the target so that only its datagrams arrive."""
        if self._sock is not None:
            return
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.connect(self.address)
        except OSError as exc:
            sock.close()
            raise BridgeError(f'UDP bridge: cannot reach {self.address[0]}:{self.address[1]} '
                              f'({exc.strerror})') from None
        self._sock = sock

    def _send(self, kind: int, seq: int, value_v: float, ahead_v: Any = ()) -> None:
        sock = self._sock
        if sock is None:
            raise BridgeError('UDP bridge: not open')
        request = self._request
        size = request.pack(kind, seq, value_v, ahead_v)
        try:
            sock.send(request.view[:size])
        except OSError as exc:
            raise BridgeError(f'UDP bridge: send to {self.address[0]}:{self.address[1]} '
                              f'failed ({exc.strerror})') from None

    def _receive(self, kind: int, deadline_s: float,
                 accept: Callable[[int], bool]) -> tuple[int, float] | None:
        """
        Return ``(seq, position)`` of the first reply of ``kind`` whose number ``accept`` takes.

        Replies of another kind or malformed ones are counted and skipped, refused numbers
        count as stale; None when nothing came before ``deadline_s`` (``time.monotonic``).
        """
        sock = self._sock
        if sock is None:
            raise BridgeError('UDP bridge: not open')
        spin = self.spin
        if spin:
            # poll without blocking until the deadline: no wake-up of a sleeping thread
            # between the datagram and its reader; else block with a timeout
            sock.settimeout(0.0)
        while True:
            remaining = deadline_s - time.monotonic()
            if remaining <= 0.0:
                return None
            if not spin:
                sock.settimeout(remaining)
            try:
                data = sock.recv(64)
            except BlockingIOError:
                self.polls += 1
                continue  # spinning, nothing yet
            except TimeoutError:
                return None
            except ConnectionRefusedError:
                # ICMP port unreachable from an earlier datagram: nobody listens (yet)
                return None
            taken = self._take(data, kind, accept)
            if taken is not None:
                return taken

    def _take(self, data: bytes, kind: int, accept: Callable[[int], bool]
              ) -> tuple[int, float] | None:
        """
        Return ``(seq, position)`` of reply ``data`` if it is of ``kind`` and ``accept`` takes it.

        Else None: another kind or a malformed datagram is counted in ``malformed``, a refused
        number in ``stale``. A reply of another protocol version, or one that refuses the
        request, raises :class:`BridgeError`.
        """
        reply = unpack_reply(data)
        if reply is None or reply[0] != kind:
            version = foreign_version(data)
            if version is not None:
                raise BridgeError(f'UDP bridge: the target at {self.address[0]}:'
                                  f'{self.address[1]} speaks protocol version {version}, '
                                  f'this host version {VERSION}; update one of them '
                                  '(docs/reference/udp-protocol.md)')
            self.malformed += 1
            return None
        _, rseq, position, status, missing = reply
        if not self._count_reply(kind, rseq, status, missing, accept, VERSION):
            return None
        return rseq, position

    def _count_reply(self, kind: int, seq: int, status: int, missing: int,
                  accept: Callable[[int], bool], version: int) -> bool:
        """
        Count a reply's number and status bits; return whether ``accept`` takes its number.

        A reply that refuses the request (of protocol ``version``) raises :class:`BridgeError`.
        """
        if not accept(seq):
            self.stale += 1
            return False
        self.exchanges += 1
        self.target_missing = missing
        if status & (STATUS_CLAMPED | STATUS_NOT_FINITE):
            self.target_clamped += 1
        if status & STATUS_PREDICTED:
            self.target_predicted += 1
        if status & STATUS_VERSION:
            raise BridgeError(f'UDP bridge: the target at {self.address[0]}:'
                              f'{self.address[1]} refused protocol version {version}; '
                              'update one of them (docs/reference/udp-protocol.md)')
        if status & STATUS_REFUSED:
            raise BridgeError(f'UDP bridge: target refused request kind {kind}')
        return True

    def _exchange(self, kind: int, value_v: float) -> float | None:
        """Send one request and return the position of its reply, or None on timeout."""
        self._seq = (self._seq + 1) % _SEQ_MOD
        seq = self._seq
        self._send(kind, seq, value_v)
        reply = self._receive(kind, time.monotonic() + self.timeout_s, lambda r: r == seq)
        return None if reply is None else reply[1]

    def safe_start(self, safe_voltage_v: float) -> float:
        """Send HELLO (retried) with the safe voltage and return the first position [m]."""
        self.open()
        for _ in range(self.hello_attempts):
            position = self._exchange(HELLO, safe_voltage_v)
            if position is not None:
                self._voltage_v = safe_voltage_v
                self._position_m = position
                self._consecutive = 0
                return position
        raise BridgeError(f'UDP bridge: no answer from the target at {self.address[0]}:'
                          f'{self.address[1]} after {self.hello_attempts} HELLO requests of '
                          f'{self.timeout_s:g} s')

    def write_voltage(self, voltage_v: float) -> None:
        """Set the voltage [V] the next :meth:`read_position` sends."""
        self._voltage_v = voltage_v

    def _measured(self, position: float | None) -> float:
        """Return ``position`` [m], or on a loss (None) the last one, counting losses in a row."""
        if position is None:
            self.lost += 1
            self._consecutive += 1
            if self._consecutive > self.max_consecutive_losses:
                raise BridgeError(f'UDP bridge: {self._consecutive} samples in a row lost '
                                  f'(no reply within {self.timeout_s:g} s from '
                                  f'{self.address[0]}:{self.address[1]})')
            return self._position_m
        self._consecutive = 0
        self._position_m = position
        return position

    def read_position(self) -> float:
        """Send the held voltage for one sample and return the position at its end [m]."""
        return self._measured(self._exchange(COMMAND, self._voltage_v))

    def safe_stop(self, safe_voltage_v: float) -> None:
        """Send STOP with the safe voltage (one attempt) and close the socket."""
        if self._sock is None:
            return
        try:
            self._exchange(STOP, safe_voltage_v)
        except BridgeError:
            pass  # the target may be gone already; the socket is closed either way
        finally:
            self._sock.close()
            self._sock = None

    def stats(self) -> Mapping[str, float]:
        """Return the loss and error counters."""
        return {'exchanges': self.exchanges, 'lost': self.lost, 'stale': self.stale,
                'malformed': self.malformed, 'target_missing': self.target_missing,
                'target_clamped': self.target_clamped,
                'target_predicted': self.target_predicted}


class UdpStreamBridge(UdpBridge):
    """
    The host side of target-paced streaming: the target owns the clock, the host answers.

    A :class:`~piezo_stage_ros.hardware.bridge.Bridge` whose :meth:`read_position` waits for the
    target's next sample (at most ``timeout_s``) and whose :meth:`write_voltage` sends the
    command answering the sample received last at once. Driven by
    :class:`~piezo_stage_ros.nodes.servo.ServoLoop` with ``clock='bridge'``: the loop takes
    the sample's number (:attr:`sample_index`) and arrival time (:attr:`arrival_ns`) from here.

    Parameters
    ----------
    host, port, timeout_s, max_consecutive_losses, hello_attempts
        As :class:`UdpBridge`; ``timeout_s`` is the longest wait for the next sample.
    clock : callable, optional
        Monotonic clock [ns] of the arrival times; default :func:`time.monotonic_ns`.
    spin : bool
        Poll for the next sample without blocking (:attr:`UdpBridge.spin`): the servo loop's
        choice when it spins on its clock anyway (``servo.spin_us`` at or above the period).
    period_ns : int
        The target's sample period [ns]: an answer later than half of it counts in
        ``answer_late_half_period``.

    Attributes
    ----------
    answer : LatenessStats
        Time from each sample's arrival to its answer sent [ns] (a histogram; ``stats()``
        gives its p50 / p99 / max).

    """

    def __init__(self, host: str, port: int, *, timeout_s: float = 0.002,
                 max_consecutive_losses: int = 10, hello_attempts: int = 5,
                 clock: Callable[[], int] = time.monotonic_ns, spin: bool = False,
                 period_ns: int = 100_000) -> None:
        super().__init__(host, port, timeout_s=timeout_s,
                         max_consecutive_losses=max_consecutive_losses,
                         hello_attempts=hello_attempts)
        self.clock = clock
        self.spin = spin
        self.sample_index = -1
        self.arrival_ns = 0
        self._answered = True
        self.answer = LatenessStats(period_ns)
        self.gaps = 0
        self.overtaken = 0
        #: Answers sent again with their commands ahead (:meth:`write_ahead`).
        self.resent = 0
        self._ahead_index = -2 ** 62  # the sample whose commands ahead were sent last
        self.waited = False

    def _queued_newer(self) -> tuple[int, float] | None:
        """Return the next sample already queued at the socket, if newer (no wait)."""
        sock = self._sock
        if sock is None:
            return None
        if not self.spin:
            sock.settimeout(0.0)
        while True:
            try:
                data = sock.recv(64)
            except (BlockingIOError, InterruptedError, ConnectionRefusedError):
                return None
            taken = self._take(data, STREAM, self._newer)
            if taken is not None:
                return taken

    def _newer(self, seq: int) -> bool:
        # an older sample (reordered) is past already
        return self.sample_index < 0 or (seq - self.sample_index) % _SEQ_MOD < 2 ** 31

    def _next_sample(self, deadline_s: float) -> bool:
        """
        Wait for a sample newer than the last one; return whether one came.

        Of the samples already queued, the newest is taken: the host answers the present
        sample, and the target has played the commands ahead over those it overtakes (counted
        in ``overtaken``), instead of answering each of a backlog too late.
        """
        polls = self.polls
        reply = self._receive(STREAM, deadline_s, self._newer)
        if reply is None:
            return False
        # spinning: whether the host was there before the sample (else it came in behind)
        self.waited = self.polls > polls
        overtaken = 0
        # a host that was polling before the sample came has nothing queued behind it
        queued = None if self.waited else self._queued_newer()
        while queued is not None:
            overtaken += 1
            if (queued[0] - reply[0]) % _SEQ_MOD < 2 ** 31:
                reply = queued  # else one reordered behind the newest: overtaken too
            queued = self._queued_newer()
        self.overtaken += overtaken
        seq, self._position_m = reply
        self.arrival_ns = self.clock()
        if self.sample_index < 0:
            self.sample_index = seq
        else:
            step = (seq - self.sample_index) % _SEQ_MOD
            self.gaps += step - 1 - overtaken  # numbers that never came
            self.sample_index += step
        self._answered = False
        return True

    def safe_start(self, safe_voltage_v: float) -> float:
        """Send STREAM (retried) with the safe voltage and return the position of sample 0."""
        self.open()
        for _ in range(self.hello_attempts):
            self._send(STREAM, 0, safe_voltage_v)
            self.sample_index = -1
            if self._next_sample(time.monotonic() + max(self.timeout_s, 0.05)):
                self._voltage_v = safe_voltage_v
                self._consecutive = 0
                return self._position_m
        raise BridgeError(f'UDP bridge: no sample from the target at {self.address[0]}:'
                          f'{self.address[1]} after {self.hello_attempts} STREAM requests')

    def write_voltage(self, voltage_v: float) -> None:
        """Send ``voltage_v`` [V] at once as the answer to the sample received last."""
        self.write_commands(voltage_v, ())

    def write_commands(self, voltage_v: float, ahead_v: Any) -> None:
        """
        Send ``voltage_v`` [V] and the commands ahead after it [V] as the answer (at once).

        The target plays the commands ahead over the samples the host does not answer in
        time (see the module doc).
        """
        self._voltage_v = voltage_v
        if self._answered or self._sock is None:
            return  # the sample has its answer already (or the stream is over)
        self._send(COMMAND, self.sample_index, voltage_v, ahead_v)
        self._answered = True
        if len(ahead_v):
            self._ahead_index = self.sample_index
        self.answer.add(self.clock() - self.arrival_ns)

    def ahead_wanted(self, count: int) -> bool:
        """
        Return whether the answer just sent should be followed by its ``count`` commands ahead.

        Yes when the host keeps up: it left within half a period of its sample's arrival and
        (spinning) the host was waiting before the sample came, not behind it; and at least
        every ``count // 4`` samples whatever the time (the target's queue then always reaches
        three quarters of ``count`` ahead). A host that falls behind saves them on the other
        samples: the target keeps the queue it has (version 3).
        """
        if self.sample_index - self._ahead_index >= max(1, count // 4):
            return True
        if self.spin and not self.waited:
            return False  # the sample had come before the host looked: it is behind
        return (self.clock() - self.arrival_ns) * 2 < self.answer.period_ns

    def write_ahead(self, ahead_v: Any) -> None:
        """
        Send the answer to the sample received last again, now with its commands ahead [V].

        After :meth:`write_commands` without them: the answer has left as early as it could,
        the queue follows for the samples the host will miss (the target takes the later
        datagram's queue, see the module doc). Nothing is sent once a newer sample has come.
        """
        if not self._answered or self._sock is None or not len(ahead_v):
            return
        self._send(COMMAND, self.sample_index, self._voltage_v, ahead_v)
        self._ahead_index = self.sample_index
        self.resent += 1

    def read_position(self) -> float:
        """Wait for the target's next sample and return its position [m] (held if lost)."""
        came = self._next_sample(time.monotonic() + self.timeout_s)
        return self._measured(self._position_m if came else None)

    def stats(self) -> Mapping[str, float]:
        """Return the counters, the sequence gaps and the answer latency [us]."""
        out: dict[str, float] = dict(super().stats())
        out['gaps'] = self.gaps
        out['overtaken'] = self.overtaken
        out['resent'] = self.resent
        answer = self.answer
        # rounded alike, as LatenessStats.summary does: the p99 of a top bin is the maximum
        out.update({'answers': answer.samples,
                    'answer_p50_us': round(answer.percentile_us(50.0), 1),
                    'answer_p99_us': round(answer.percentile_us(99.0), 1),
                    'answer_max_us': round(answer.max_ns / 1000, 1),
                    'answer_late_half_period': answer.late_half})
        return out
