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
The recording path of a real-time loop: served samples as columns, into block messages.

At 10 kHz one message per sample and topic costs the executor more than the servo leaves it on
a busy machine, so under load it fell behind, and the servo's ring overwrote samples before
they were read (``ring_missed``). The block topic (``stage/block``, layout in
:mod:`piezo_stage_ros.core.contracts.wire`) carries :data:`~piezo_stage_ros.core.contracts.wire.
BLOCK_SAMPLES` samples a message: the executor takes what the servo handed over as numpy columns
(:class:`SampleBatch`), :class:`BlockRecorder` turns them into whole blocks, and every sample is
published that way first. The per-sample topics (for live subscribers) get what the executor
can still afford: :func:`live_share` leaves out the oldest samples of a backlog, and the plant
counts them (``live_dropped``, in ``stage/status`` and the end-of-run line).

No rclpy here: the plant node publishes the bytes.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
import math
from typing import NamedTuple, TYPE_CHECKING

import numpy as np
from piezo_stage_ros.core.config.nodes import RecordingParams
from piezo_stage_ros.core.contracts.cdr import encode_block
from piezo_stage_ros.core.contracts.types import FloatArray, IntArray
from piezo_stage_ros.core.contracts.wire import (
    axes_block_columns,
    AXES_BLOCK_OWN,
    AXES_BLOCK_SHARED,
    block_columns,
    BLOCK_SAMPLES,
    NS_PER_S,
)

if TYPE_CHECKING:
    from piezo_stage_ros.nodes.servo_axes import AxesSampleBatch

__all__ = ['AxesBlockRecorder', 'BlockRecorder', 'Handover', 'SampleBatch', 'backlog_samples',
           'live_share']

# The columns of a batch (those of the servo's ring, nodes/servo.py SampleRing).
_K, _STAMP, _LATE, _LAYOUT, _COUNT = range(5)
_POSITION, _REFERENCE, _VELOCITY, _COMMAND, _APPLIED, _TRUE = range(6)
_VALUES = 6
# the column of the true position in a block's rows (before it leaves a block without one)
_TRUE_COLUMN = 8


class SampleBatch(NamedTuple):
    """
    Samples the servo handed to the ROS side at once, as columns.

    Attributes
    ----------
    number : ndarray of int64, shape (n,)
        The number of each sample among those the servo served (0, 1, 2 ...); consecutive
        except where samples were lost before the ROS side read them.
    ints : ndarray of int64, shape (n, 5)
        k, stamp t_k [ns], lateness [ns], the layout of the diagnostics, how many the row has.
    floats : ndarray of float64, shape (n, 6 + width)
        y_k, x_d, x_d', u_k, the input held over the sample y_k ends (``applied_v`` of
        :class:`~piezo_stage_ros.nodes.servo.ServoSample`), the true position (NaN where
        unknown), then the diagnostics.
    layouts : mapping of int to tuple of str
        Diagnostic names of each layout number.

    """

    number: IntArray
    ints: IntArray
    floats: FloatArray
    layouts: Mapping[int, tuple[str, ...]]

    @property
    def size(self) -> int:
        """Return the number of samples."""
        return int(self.number.size)


def backlog_samples(recording: RecordingParams, rate_hz: float) -> int:
    """Return the samples the servo keeps for the executor (``recording.backlog_s`` [s])."""
    return max(1, math.ceil(recording.backlog_s * rate_hz))


def live_share(waiting: int, limit: int) -> int:
    """
    Return how many of the oldest ``waiting`` samples the per-sample topics leave out.

    The per-sample topics publish at most ``limit`` samples a batch, the newest (a live
    subscriber wants the present, not a backlog); the block topic has every sample.

    Parameters
    ----------
    waiting : int
        Samples handed over since the last batch.
    limit : int
        Most samples published one by one per batch (>= 1).

    """
    return max(0, int(waiting) - max(1, int(limit)))


def _held_over(number: IntArray, applied_v: FloatArray) -> FloatArray:
    """
    Return what the plant held over each served sample, [t_k, t_k+1) [V].

    ``applied_v`` (one value or one row of the axes' values a sample) is the input held over
    the sample that ended at t_k; the input over the next one is the next sample's, where the
    next sample number follows (NaN across a gap, and after the last sample).
    """
    following = np.full(applied_v.shape, np.nan)
    after = number[1:] == number[:-1] + 1
    following[:-1][after] = applied_v[1:][after]
    return following


class BlockRecorder:
    """
    Served samples in, block messages (CDR bytes of ``stage/block``) out.

    Each row carries the input the plant held over [t_k, t_k+1) (``applied_v``), which is
    known only with the next sample: the last sample of a batch waits for the next batch (or
    :meth:`finish`). Where the next sample was lost (a gap in the numbers) it is NaN. A block
    has :attr:`block_samples` rows; a change of the diagnostic names (a controller rebuilt of
    another kind) ends a block early, so that each message has one column set (the first names
    seen do not: the rows before them get NaN columns).

    Parameters
    ----------
    block_samples : int
        Rows a block message carries (>= 1).

    Attributes
    ----------
    rows : int
        Samples put into messages so far.
    messages : int
        Messages returned so far.

    """

    def __init__(self, block_samples: int = BLOCK_SAMPLES) -> None:
        self.block_samples = max(1, int(block_samples))
        self.rows = 0
        self.messages = 0
        # batches not yet made into rows: numpy pays off once per block, not per small batch
        self._waiting: list[SampleBatch] = []
        self._waiting_rows = 0
        self._names: tuple[str, ...] | None = None  # diagnostics of the pending rows
        self._columns: dict[tuple[str, ...], tuple[tuple[str, ...], IntArray]] = {}
        self._pending: list[FloatArray] = []
        self._pending_rows = 0

    def add(self, batch: SampleBatch) -> list[bytes]:
        """Take a batch; return the whole blocks now complete, oldest first."""
        if batch.size == 0:
            return []
        self._waiting.append(batch)
        self._waiting_rows += batch.size
        # the last sample waits for the next (its applied input): a whole block needs one more
        if self._waiting_rows <= self.block_samples:
            return []
        return self._process(None)

    def finish(self, held_v: float = math.nan) -> list[bytes]:
        """
        Return the remaining rows as blocks (the last may be shorter).

        Parameters
        ----------
        held_v : float
            What the plant held after the last sample [V] (until the stop drove the safe
            voltage); NaN when unknown.

        """
        out = self._process(held_v) if self._waiting_rows else []
        return out + self._flush()

    def _process(self, held_v: float | None) -> list[bytes]:
        # the rows waiting, each with the input held after it (the next sample's applied_v,
        # NaN across a gap); without held_v the last row waits for the next batch
        batch = _join(self._waiting)
        following = _held_over(batch.number, batch.floats[:, _APPLIED])
        if held_v is None:
            last = batch.size - 1
            self._waiting, self._waiting_rows = [_take(batch, slice(last, None))], 1
            return self._rows(_take(batch, slice(0, last)), following[:last])
        self._waiting, self._waiting_rows = [], 0
        following[-1] = held_v
        return self._rows(batch, following)

    def _rows(self, batch: SampleBatch, applied: FloatArray) -> list[bytes]:
        n = batch.size
        if n == 0:
            return []
        sec, nanosec = np.divmod(batch.ints[:, _STAMP], NS_PER_S)
        base = np.column_stack((batch.number, sec, nanosec,
                                batch.floats[:, _POSITION:_COMMAND + 1], applied,
                                batch.floats[:, _TRUE])).astype(np.float64)
        # diagnostics: where their names change, a new block begins
        count = batch.ints[:, _COUNT]
        names_of = [(i, batch.layouts.get(int(batch.ints[i, _LAYOUT])))
                    for i in np.flatnonzero(count > 0).tolist()]
        cuts = []
        current = self._names
        for i, names in names_of:
            if names is not None and names != current:
                cuts.append((i, names))
                current = names
        out: list[bytes] = []
        start = 0
        for i, names in cuts:
            out += self._append(batch, base, start, i)
            if self._names is None:
                # the first names: the rows before them (no diagnostics yet) get NaN columns
                self._pending = [np.hstack((rows, np.full((rows.shape[0], len(names)), np.nan)))
                                 for rows in self._pending]
            else:
                out += self._flush()
            self._names = names
            start = i
        return out + self._append(batch, base, start, n)

    def _append(self, batch: SampleBatch, base: FloatArray, lo: int, hi: int) -> list[bytes]:
        if hi <= lo:
            return []
        names = self._names or ()
        _, order = self._layout(names)
        width = len(names)
        diag = np.full((hi - lo, width), np.nan)
        if width:
            layout = batch.ints[lo:hi, _LAYOUT]
            mine = np.zeros(hi - lo, dtype=bool)
            for number, known in batch.layouts.items():
                if known == names:
                    mine |= layout == number
            mine &= batch.ints[lo:hi, _COUNT] == width
            diag[mine] = batch.floats[lo:hi][mine, _VALUES:_VALUES + width]
        self._pending.append(np.hstack((base[lo:hi], diag[:, order])))
        self._pending_rows += hi - lo
        out: list[bytes] = []
        while self._pending_rows >= self.block_samples:
            rows = np.vstack(self._pending)
            size = self.block_samples
            out.append(self._message(rows[:size]))
            self._pending = [rows[size:]] if rows.shape[0] > size else []
            self._pending_rows = rows.shape[0] - size
        return out

    def _flush(self) -> list[bytes]:
        if not self._pending_rows:
            return []
        rows = np.vstack(self._pending)
        self._pending, self._pending_rows = [], 0
        return [self._message(rows)]

    def _layout(self, names: tuple[str, ...]) -> tuple[tuple[str, ...], IntArray]:
        # the block's column names (with a true position), and the order that puts the
        # diagnostics in theirs (sorted)
        known = self._columns.get(names)
        if known is None:
            order = np.asarray(sorted(range(len(names)), key=names.__getitem__), dtype=np.int64)
            known = self._columns[names] = (
                block_columns(applied=True, true_position=True, diagnostics=names), order)
        return known

    def _message(self, rows: FloatArray) -> bytes:
        self.rows += rows.shape[0]
        self.messages += 1
        columns = self._layout(self._names or ())[0]
        if np.isnan(rows[:, _TRUE_COLUMN]).all():
            # a backend that does not know the true position (hardware): no such column
            columns = columns[:_TRUE_COLUMN] + columns[_TRUE_COLUMN + 1:]
            rows = np.delete(rows, _TRUE_COLUMN, axis=1)
        return encode_block(columns, rows)


class AxesBlockRecorder:
    """
    Served samples of several axes in, block messages of several axes out.

    As :class:`BlockRecorder` for one axis: each row carries what the plant held over
    [t_k, t_k+1) on every axis (``<axis>.applied_v``: the next sample's applied input, NaN
    across a gap in the numbers), so the last sample of a batch waits for the next batch or
    :meth:`finish`; the columns are those of
    :func:`~piezo_stage_ros.core.contracts.wire.axes_block_columns`, without the true position
    where the backend does not know it (hardware).

    Parameters
    ----------
    axes : sequence of str
        The axes, in the stage's order (the batches' column order).
    block_samples : int
        Rows a block message carries (>= 1).

    """

    def __init__(self, axes: Sequence[str], block_samples: int = BLOCK_SAMPLES) -> None:
        self.axes = tuple(axes)
        self.block_samples = max(1, int(block_samples))
        self.rows = 0
        self.messages = 0
        self._columns = {true: axes_block_columns(self.axes, applied=True, true_position=true)
                         for true in (False, True)}
        self._waiting: list[AxesSampleBatch] = []
        self._pending: list[FloatArray] = []

    def add(self, batch: AxesSampleBatch) -> list[bytes]:
        """Take a batch (an ``AxesSampleBatch``); return the blocks now complete."""
        if batch.size:
            self._waiting.append(batch)
        waiting = sum(b.size for b in self._waiting)
        return self._process(None) if waiting > self.block_samples else []

    def finish(self, held_v: Sequence[float] | None = None) -> list[bytes]:
        """
        Return the remaining rows as blocks (the last may be shorter).

        Parameters
        ----------
        held_v : sequence of float, optional
            What the plant held on each axis after the last sample [V]; None: unknown (NaN).

        """
        held = np.full(len(self.axes), np.nan) if held_v is None else \
            np.asarray(held_v, dtype=np.float64)
        out = self._process(held) if self._waiting else []
        if self._pending:
            out.append(self._message(np.vstack(self._pending)))
            self._pending = []
        return out

    def _process(self, held_v: FloatArray | None) -> list[bytes]:
        number = np.concatenate([b.number for b in self._waiting])
        stamp = np.concatenate([b.stamp_ns for b in self._waiting])

        def stack(field: str) -> FloatArray:
            return np.vstack([getattr(b, field) for b in self._waiting])
        following = _held_over(number, stack('applied_v'))
        values = [stack(f) for f in ('position_m', 'reference_m', 'velocity_mps', 'command_v')]
        true = stack('true_position_m')
        n = number.size
        if held_v is None:  # the last row waits for the next batch: its input is not known
            last = self._waiting[-1]
            keep = slice(last.size - 1, None)
            self._waiting = [last._replace(**{f: getattr(last, f)[keep]
                                              for f in last._fields if f != 'axes'})]
            n -= 1
        else:
            following[-1] = held_v
            self._waiting = []
        sec, nanosec = np.divmod(stamp[:n], NS_PER_S)
        own = [column[:n, j] for j in range(len(self.axes))
               for column in (*values, following, true)]
        rows = np.column_stack([number[:n], sec, nanosec, *own]).astype(np.float64)
        self._pending.append(rows)
        out: list[bytes] = []
        pending = np.vstack(self._pending)
        size = self.block_samples
        whole = pending.shape[0] // size * size
        for lo in range(0, whole, size):
            out.append(self._message(pending[lo:lo + size]))
        self._pending = [pending[whole:]] if pending.shape[0] > whole else []
        return out

    def _message(self, rows: FloatArray) -> bytes:
        self.rows += rows.shape[0]
        self.messages += 1
        per = len(AXES_BLOCK_OWN) + 2  # the axis' own columns, applied_v, true_position_m
        shared = len(AXES_BLOCK_SHARED)
        true = [shared + j * per + per - 1 for j in range(len(self.axes))]
        if np.isnan(rows[:, true]).all():
            # a backend that does not know the true position (hardware): no such columns
            return encode_block(self._columns[False], np.delete(rows, true, axis=1))
        return encode_block(self._columns[True], rows)


class Handover:
    """
    What the plant node does with each batch the servo handed over, without rclpy.

    Every sample goes into the blocks; the per-sample topics get the newest ``live_limit`` of
    a batch, and the older ones are counted in :attr:`live_dropped`.

    Parameters
    ----------
    block_samples : int
        Rows a block message carries.
    live_limit : int
        Most samples of one batch published one by one (>= 1).

    Attributes
    ----------
    blocks : BlockRecorder
        The block messages made so far (its counters).
    live_dropped : int
        Samples left out of the per-sample topics so far.

    """

    def __init__(self, block_samples: int = BLOCK_SAMPLES, live_limit: int = 1000) -> None:
        self.blocks = BlockRecorder(block_samples)
        self.live_limit = max(1, int(live_limit))
        self.live_dropped = 0

    @classmethod
    def from_params(cls, recording: RecordingParams, rate_hz: float) -> Handover:
        """Return the handover ``recording.*`` configures at this sample rate [Hz]."""
        return cls(recording.block_samples, max(1, round(recording.live_backlog_s * rate_hz)))

    def take(self, batch: SampleBatch) -> tuple[list[bytes], int]:
        """
        Return the block messages now complete, and the first row to publish one by one.

        Rows before that one are left out of the per-sample topics (and counted); the input
        held over the first row published began at the row before it
        (``batch.ints[first - 1, 1]`` is that row's stamp [ns]).
        """
        messages = self.blocks.add(batch)
        first = live_share(batch.size, self.live_limit)
        self.live_dropped += first
        return messages, first

    def finish(self, held_v: float = math.nan) -> list[bytes]:
        """Return the last block messages (see :meth:`BlockRecorder.finish`)."""
        return self.blocks.finish(held_v)

    def stats(self) -> dict[str, int]:
        """Return the counters for ``stage/status`` and the end-of-run line."""
        return {'live_dropped': self.live_dropped, 'block_messages': self.blocks.messages,
                'block_samples': self.blocks.rows}


def _take(batch: SampleBatch, rows: slice) -> SampleBatch:
    return SampleBatch(batch.number[rows], batch.ints[rows], batch.floats[rows], batch.layouts)


def _join(batches: list[SampleBatch]) -> SampleBatch:
    if len(batches) == 1:
        return batches[0]
    width = max(b.floats.shape[1] for b in batches)

    def pad(values: FloatArray) -> FloatArray:
        if values.shape[1] == width:
            return values
        return np.hstack((values, np.full((values.shape[0], width - values.shape[1]),
                                          np.nan)))
    layouts: dict[int, tuple[str, ...]] = {}
    for b in batches:
        layouts.update(b.layouts)
    return SampleBatch(np.concatenate([b.number for b in batches]),
                       np.vstack([b.ints for b in batches]),
                       np.vstack([pad(b.floats) for b in batches]), layouts)
