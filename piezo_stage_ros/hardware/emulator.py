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
A real-time I/O target emulator on loopback: the stage model behind the UDP protocol.

It speaks the protocol of :mod:`piezo_stage_ros.hardware.udp`, simulating the stage with the core
model.

Request-reply (:meth:`TargetEmulator.serve`): it steps one
:class:`~piezo_stage_ros.core.model.stage.Stage` per COMMAND request (so a lockstep run through it
gives the samples of the model itself). Target-paced (:meth:`TargetEmulator.serve_paced`,
``stage_emulator --paced``): after a STREAM request it owns the sample clock as a real-time
target does, paced like the servo loop (:class:`~piezo_stage_ros.hardware.pacing.Pacer`): at
each sample it applies the newest command received, counts the sample missing when no command
answered the previous one (and applies that command's prediction for it instead, when the
command came with commands ahead), steps the stage and sends the sample. A request of another
protocol version is refused with status 16 and said once on stderr. It binds to 127.0.0.1 only
and stops by itself: on STOP, after ``idle_timeout_s`` without a request, or after
``max_requests``. Run it as ``stage_emulator --port 50000`` (console script) or in a thread
from a test.
"""

from __future__ import annotations

import argparse
import math
import socket
import sys
import threading
from typing import Any, Sequence

from piezo_stage_ros import cli
from piezo_stage_ros.core.config.nodes import ServoParams
from piezo_stage_ros.core.contracts.errors import ParameterError, PiezoStageError
from piezo_stage_ros.core.model.stage import Stage, StageParams
from piezo_stage_ros.hardware.pacing import Pacer, servo_setup
from piezo_stage_ros.hardware.udp import (
    COMMAND,
    foreign_version,
    HELLO,
    MAX_AHEAD,
    pack_reply,
    REQUEST,
    STATUS_CLAMPED,
    STATUS_NOT_FINITE,
    STATUS_PREDICTED,
    STATUS_REFUSED,
    STATUS_VERSION,
    STOP,
    STREAM,
    unpack_request,
    VERSION,
)

__all__ = ['TargetEmulator', 'main']

LOOPBACK = '127.0.0.1'
_HALF = 2 ** 31
#: The largest datagram read: a request with the most commands ahead.
_DATAGRAM = REQUEST.size + 8 * MAX_AHEAD


class TargetEmulator:
    """
    The target side of the protocol, simulating the stage.

    Parameters
    ----------
    params : StageParams
        The simulated stage.
    port : int
        UDP port on 127.0.0.1; 0 picks a free one (see :attr:`port`).
    host : str
        Must be ``'127.0.0.1'``: the emulator never listens beyond loopback.
    idle_timeout_s : float
        Stop after this long without a request [s].
    max_requests : int
        Stop after this many requests (0: no limit).
    drop_reply_every : int
        Swallow every n-th COMMAND reply (0: none), to exercise the loss counting.

    """

    def __init__(self, params: StageParams, *, port: int = 0, host: str = LOOPBACK,
                 idle_timeout_s: float = 5.0, max_requests: int = 0,
                 drop_reply_every: int = 0) -> None:
        if host != LOOPBACK:
            raise ParameterError('host', host, f'{LOOPBACK!r}',
                                 'is not loopback (the emulator binds to loopback only)')
        if not (idle_timeout_s > 0.0 and math.isfinite(idle_timeout_s)):
            raise ParameterError('idle_timeout_s', idle_timeout_s, '(0, inf)')
        if max_requests < 0:
            raise ParameterError('max_requests', max_requests, '[0, inf)')
        if drop_reply_every < 0:
            raise ParameterError('drop_reply_every', drop_reply_every, '[0, inf)')
        self.params = params
        self.stage = Stage(params)
        chain = params.chain
        self._low, self._high = chain.amplifier_min_v, chain.amplifier_max_v
        self.idle_timeout_s = idle_timeout_s
        self.max_requests = max_requests
        self.drop_reply_every = drop_reply_every
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind((LOOPBACK, port))
        except OSError as exc:
            self._sock.close()
            raise PiezoStageError(f'stage_emulator: cannot bind {LOOPBACK}:{port} '
                                  f'({exc.strerror})') from None
        self.port: int = self._sock.getsockname()[1]
        self.requests = 0
        self.commands = 0
        self.missing = 0
        self.dropped = 0
        self.stop_reason = ''
        self._expected: int | None = None
        self._voltage_v = chain.safe_voltage_v
        # the stage is at rest already; reading its true position draws no noise, so the
        # noise sequence after HELLO is the one the offline runner sees
        self._position_m = self.stage.position_m
        self._thread: threading.Thread | None = None
        self._halt = threading.Event()
        self._sent = 0
        # a stream: whether the sample sent last has its answer, the next sample stepped ahead
        # of its due time (position, status), why to stop, when the last request came
        self._answered = False
        self._ready: tuple[float, int] | None = None
        self._reason = ''
        self._last_request_ns = 0
        self.pacer: Pacer | None = None
        # the newest command of a stream (the sample it answers), the newest commands ahead
        # and the sample whose command they came with
        self._newest = 0
        self._queue: tuple[float, ...] = ()
        self._queue_seq = 0
        #: Samples that applied a command ahead (paced).
        self.predicted = 0
        #: Requests refused for another protocol version.
        self.refused_version = 0

    def _refuse_version(self, data: bytes) -> bytes | None:
        """Return the refusal of a request of another protocol version (None: not one)."""
        version = foreign_version(data)
        if version is None or len(data) < 8:
            return None
        self.refused_version += 1
        if self.refused_version == 1:
            print(f'stage_emulator: refused a request of protocol version {version} (this '
                  f'target speaks version {VERSION})', file=sys.stderr, flush=True)
        seq = int.from_bytes(data[4:8], 'little')
        return pack_reply(data[3] & 0x7F, seq, math.nan, STATUS_REFUSED | STATUS_VERSION,
                          self.missing)

    def _handle(self, data: bytes) -> tuple[bytes | None, bool]:
        """Return the reply to one datagram (None: no reply) and whether the session ends."""
        request = unpack_request(data)
        if request is None:
            return self._refuse_version(data), False
        kind, seq, value, _ = request
        status = 0
        if self._expected is not None and kind != HELLO:
            gap = (seq - self._expected) % 2 ** 32
            if gap >= _HALF:
                # older than the last one: a duplicate or reordered request; never step twice
                return None, False
            self.missing += gap
        self._expected = (seq + 1) % 2 ** 32
        if not math.isfinite(value):
            status |= STATUS_NOT_FINITE
        elif not self._low <= value <= self._high:
            status |= STATUS_CLAMPED
        if kind == HELLO:
            self._position_m = self.stage.reset()
            self._voltage_v = value
            self.missing = 0
        elif kind == COMMAND:
            self.commands += 1
            self._voltage_v = value
            self._position_m = self.stage.step(value)
            if self.drop_reply_every and self.commands % self.drop_reply_every == 0:
                self.dropped += 1
                return None, False
        elif kind == STOP:
            # the stage is left holding the safe voltage; no more samples are taken
            self._voltage_v = value
            return pack_reply(kind, seq, self._position_m, status, self.missing), True
        else:
            status |= STATUS_REFUSED
        return pack_reply(kind, seq, self._position_m, status, self.missing), False

    def serve(self) -> str:
        """
        Answer requests until STOP, idleness, the request limit or :meth:`close`.

        Returns
        -------
        str
            Why it stopped: ``'stop'``, ``'idle'``, ``'limit'`` or ``'closed'``.

        """
        sock = self._sock
        sock.settimeout(min(self.idle_timeout_s, 0.1))
        while True:
            got = self._receive(0.0)
            if got is None:
                break
            data, peer, _ = got
            self.requests += 1
            reply, done = self._handle(data)
            if reply is not None:
                sock.sendto(reply, peer)
            if done:
                self.stop_reason = 'stop'
                break
            if self.max_requests and self.requests >= self.max_requests:
                self.stop_reason = 'limit'
                break
        sock.close()
        return self.stop_reason

    def _receive(self, idle_s: float) -> tuple[bytes, Any, float] | None:
        """
        Wait for the next datagram on the blocking socket; None when waiting has to end.

        Both ways of serving wait alike, so a host that goes silent or a :meth:`close` ends
        either the same way.

        Parameters
        ----------
        idle_s : float
            Time already waited without a datagram that counts [s].

        Returns
        -------
        tuple or None
            The datagram, its sender and the idle time counted so far [s] (what came before
            it included); None with :attr:`stop_reason` ``'idle'`` after ``idle_timeout_s``
            without a datagram, or ``'closed'`` when the socket is closed or the server halted.

        """
        sock = self._sock
        while not self._halt.is_set():
            try:
                data, peer = sock.recvfrom(_DATAGRAM)
            except TimeoutError:
                idle_s += sock.gettimeout() or 0.0
                if idle_s >= self.idle_timeout_s:
                    self.stop_reason = 'idle'
                    return None
                continue
            except OSError:
                break
            return data, peer, idle_s
        self.stop_reason = 'closed'
        return None

    def serve_paced(self, pacer: Pacer | None = None) -> str:
        """
        Wait for STREAM, then sample on the own clock until STOP, idleness, limit or close.

        Parameters
        ----------
        pacer : Pacer, optional
            The clock; default a :class:`~piezo_stage_ros.hardware.pacing.Pacer` at the
            stage's sample rate. Its statistics (:attr:`pacer`) are the target's own lateness.

        Returns
        -------
        str
            Why it stopped: ``'stop'``, ``'idle'``, ``'limit'`` or ``'closed'``.

        """
        self.pacer = pacer if pacer is not None else \
            Pacer(round(1e9 / self.params.sample_rate_hz))
        sock = self._sock
        sock.settimeout(min(self.idle_timeout_s, 0.1))
        peer = None
        # a datagram other than STREAM does not restart the idle time
        idle_s = 0.0
        while peer is None:
            got = self._receive(idle_s)
            if got is None:
                sock.close()
                return self.stop_reason
            data, addr, idle_s = got
            request = unpack_request(data)
            if request is not None and request[0] == STREAM:
                peer = addr
                self._voltage_v = request[2]
                self._queue, self._queue_seq = (), 0
            elif request is None:
                refusal = self._refuse_version(data)
                if refusal is not None:
                    sock.sendto(refusal, addr)
        self.requests += 1
        self._position_m = self.stage.reset()
        self.missing = 0
        sock.setblocking(False)
        pacer = self.pacer
        pacer.start()
        index, _ = pacer.wait()
        sock.sendto(pack_reply(STREAM, index, self._position_m, 0, 0), peer)
        self._sent, self._answered, self._ready, self._reason = index, False, None, ''
        self._last_request_ns = pacer.clock()

        def poll() -> None:
            # while the clock spins to the next sample: take the commands as they come, and
            # once the answer to the sample sent last is in, step the next sample with it
            # ahead of its due time, so that its reply leaves at once then, as an ADC's would
            if self._reason or self._ready is not None:
                return
            self._reason = self._take_requests(sock, peer)
            if self._answered and not self._reason:
                self._ready = self._sample(self._sent + 1)

        while not self._reason:
            if self._halt.is_set():
                self._reason = 'closed'
                break
            before = index
            index, _ = pacer.wait(poll)
            ready, self._ready = self._ready, None
            for skipped in range(before + 1, index):
                # samples skipped after a stall: the stage went on under the held voltage (or
                # the commands ahead); the first of them stepped already if the answer came
                if not (skipped == before + 1 and ready is not None):
                    self.stage.step(self._ahead_voltage(skipped)[0])
            self._reason = self._reason or self._take_requests(sock, peer)
            if self._reason:
                break
            position, status = ready if ready is not None and index == before + 1 else \
                self._sample(index)
            self._position_m = position
            self._sent, self._answered = index, False
            sock.sendto(pack_reply(STREAM, index, position, status, self.missing), peer)
            if self.max_requests and self.requests >= self.max_requests:
                self._reason = 'limit'
            elif (pacer.clock() - self._last_request_ns) / 1e9 > self.idle_timeout_s:
                self._reason = 'idle'
        self.stop_reason = self._reason
        sock.close()
        return self.stop_reason

    def _take_requests(self, sock: socket.socket, peer: Any) -> str:
        """
        Take every request waiting at the socket (a stream's); return why to stop, or ''.

        The newest command is held; it answers the sample sent last, or is late. The first
        command answering the sample sent last fixes its value (its step may have been taken
        already): a repeat of it (the same number) brings only its commands ahead.
        """
        assert self.pacer is not None
        while True:
            try:
                data = sock.recv(_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return ''
            except OSError:
                return 'closed'
            request = unpack_request(data)
            if request is None:
                refusal = self._refuse_version(data)
                if refusal is not None:
                    sock.sendto(refusal, peer)
                continue
            kind, seq, value, ahead = request
            self.requests += 1
            self._last_request_ns = self.pacer.clock()
            if kind == STOP:
                self._voltage_v = value
                sock.sendto(pack_reply(STOP, seq, self._position_m, 0, self.missing), peer)
                return 'stop'
            if kind == COMMAND:
                self.commands += 1
                answers_last = seq % 2 ** 32 == self._sent % 2 ** 32
                if not (answers_last and self._answered):
                    self._voltage_v = value
                    self._newest = seq
                if ahead and (seq - self._queue_seq) % 2 ** 32 < 2 ** 31:
                    # a command without commands ahead keeps the queue it has (version 3)
                    self._queue, self._queue_seq = ahead, seq
                self._answered = self._answered or answers_last

    def _sample(self, index: int) -> tuple[float, int]:
        """
        Step sample ``index`` with the answer, a command ahead or the held command.

        The answer is the command answering sample ``index - 1``: after a stall of the
        target's own clock the sample sent last is older, and its answer, however punctual,
        is the newest command the queue's prediction for ``index`` goes on from, not a command
        to hold over it.
        """
        status = 0
        if not (self._answered and index == self._sent + 1):
            self.missing += 1
            value, predicted = self._ahead_voltage(index)
            if predicted:
                status |= STATUS_PREDICTED
        else:
            value = self._voltage_v
        if not math.isfinite(value):
            status |= STATUS_NOT_FINITE
        elif not self._low <= value <= self._high:
            status |= STATUS_CLAMPED
        return self.stage.step(value), status

    def _ahead_voltage(self, index: int) -> tuple[float, bool]:
        """
        Return the voltage of sample ``index`` without a command answering the one before.

        The newest commands ahead's prediction for it (``index - 1 - q`` samples after the
        sample q they came with, the last one after the queue) and True, or the newest command
        itself (no queue) and False.
        """
        queue = self._queue
        if not queue:
            return self._voltage_v, False
        ahead = (index - 1 - self._queue_seq) % 2 ** 32
        if ahead == 0 or ahead >= 2 ** 31:
            return self._voltage_v, False
        self.predicted += 1
        value = queue[min(ahead, len(queue)) - 1]
        newer = (self._newest - self._queue_seq) % 2 ** 32
        if 0 < newer <= len(queue) and newer < ahead:
            # a newer command than the queue's: the queue moved onto it (its prediction for
            # that command shifted to the command itself)
            value += self._voltage_v - queue[newer - 1]
        return value, True

    def start_thread(self) -> TargetEmulator:
        """Serve in a daemon thread; return self."""
        self._thread = threading.Thread(target=self.serve, name='stage_emulator', daemon=True)
        self._thread.start()
        return self

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop serving and wait for the thread (if any) up to ``timeout_s`` [s]."""
        self._halt.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        else:
            self._sock.close()

    def __enter__(self) -> TargetEmulator:
        return self.start_thread()

    def __exit__(self, *exc: object) -> None:
        self.close()


def main(argv: Sequence[str] | None = None) -> int:
    """
    Run the emulator from the command line (console script ``stage_emulator``).

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments (default ``sys.argv[1:]``).

    Returns
    -------
    int
        0 when it stopped normally, 2 on bad arguments or parameters.

    """
    parser = argparse.ArgumentParser(
        prog='stage_emulator',
        description='Real-time I/O target emulator on 127.0.0.1: the stage model behind the '
                    'UDP protocol of piezo_stage_ros.hardware.udp '
                    '(docs/reference/udp-protocol.md).')
    parser.add_argument('--config', action='append', default=[], metavar='FILE',
                        help='ROS parameter file on top of config/default.yaml (repeatable); '
                        'the plant_node section is the stage')
    parser.add_argument('--port', type=int, default=50000, help='UDP port (0: any free one)')
    parser.add_argument('--idle-timeout-s', type=float, default=10.0,
                        help='stop after this long without a request [s]')
    parser.add_argument('--max-requests', type=int, default=0,
                        help='stop after this many requests (0: no limit)')
    parser.add_argument('--paced', action='store_true',
                        help='own the sample clock: stream samples after a STREAM request and '
                        'hold the newest command (a real-time target)')
    parser.add_argument('--spin-us', type=float, default=200.0,
                        help='paced: sleep until this close to each due time, then spin')
    parser.add_argument('--fifo-priority', type=int, default=0,
                        help='paced: SCHED_FIFO priority (0: the default scheduler)')
    parser.add_argument('--cpu', type=int, default=-1, help='paced: run on this CPU (-1: any)')
    parser.add_argument('--nice', type=int, default=-20,
                        help='paced: nice value of the clock under the default scheduler '
                        '(-20 .. 19; applied where permitted)')
    args = parser.parse_args(argv)
    try:
        # the same loader as every command: the plant node's own settings (mode, backend ...)
        # are validated beside the stage, and noted when the emulator cannot honour them
        config = cli.read_config(args.config)
        params = cli.offline_loop('stage_emulator', config).stage
        # the clock's options are those of the host's servo loop (servo.*), validated alike
        clock = ServoParams(spin_us=args.spin_us, fifo_priority=args.fifo_priority,
                            cpu=args.cpu, nice=args.nice)
        emulator = _emulator_of(config, params, args)
    except PiezoStageError as exc:
        print(f'stage_emulator: {exc}', file=sys.stderr)
        return 2
    print(f'stage_emulator: listening on {LOOPBACK}:{emulator.port}', flush=True)
    names = getattr(getattr(emulator, 'axes_stage', None), 'names', None)
    if names is not None:
        print(f'stage_emulator: axes {list(names)}, protocol version 4', flush=True)
    try:
        if args.paced and names is not None:
            emulator.close()
            print('stage_emulator: --paced serves one axis; a stage of several axes is served '
                  'request-reply', file=sys.stderr)
            return 2
        if args.paced:
            period_ns = round(1e9 / params.sample_rate_hz)
            for key, text in servo_setup(clock, period_ns).items():
                print(f'stage_emulator: {key} {text}', flush=True)
            reason = emulator.serve_paced(Pacer(period_ns, spin_ns=round(args.spin_us * 1000)))
        else:
            reason = emulator.serve()
    except KeyboardInterrupt:
        reason = 'interrupted'
    print(f'stage_emulator: stopped ({reason}) after {emulator.requests} requests, '
          f'{emulator.missing} missing, {emulator.predicted} played ahead', flush=True)
    if emulator.pacer is not None:
        print('stage_emulator: clock ' + ', '.join(
            f'{k} {v}' for k, v in emulator.pacer.stats.summary().items()), flush=True)
    return 0


def _emulator_of(config: Any, params: StageParams, args: argparse.Namespace) -> TargetEmulator:
    """Return the emulator of the files: of several axes (version 4) when they name axes."""
    from piezo_stage_ros.core.config.axes import axes_loop_config, has_axes
    if has_axes(config):
        from piezo_stage_ros.hardware.emulator_axes import AxesTargetEmulator
        return AxesTargetEmulator(axes_loop_config(config).stage, port=args.port,
                                  idle_timeout_s=args.idle_timeout_s,
                                  max_requests=args.max_requests)
    return TargetEmulator(params, port=args.port, idle_timeout_s=args.idle_timeout_s,
                          max_requests=args.max_requests)


if __name__ == '__main__':
    sys.exit(main())
