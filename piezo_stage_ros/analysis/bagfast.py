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
The fast paths of the bag tools, and the only module that touches rosbags' internals.

Writing (:class:`BulkWriter`): ``Writer.write`` of rosbags costs some 10 us per message in
Python, more than simulating a sample. The bulk writer appends whole batches of prebuilt MCAP
message records to the open chunk of rosbags' MCAP storage writer, or inserts sqlite3 rows with
one ``executemany``, and keeps rosbags' bookkeeping itself. It depends on these internals of
rosbags 0.11 (checked by ``test/test_bagfast.py``, which fails when an upgrade removes or
changes them; the writing test compares every byte with what ``Writer.write`` gives):

- ``rosbags.rosbag2.Writer`` attributes ``counts`` (message count per connection id),
  ``min_timestamp``, ``max_timestamp``, ``compression_mode`` and ``storage`` (the storage
  writer), which ``Writer.close`` turns into ``metadata.yaml``;
- ``rosbags.rosbag2.storage_mcap.McapWriter`` attributes ``bio`` (the file), ``chunk`` (a
  ``PendingChunk(start, end, bio, index)`` whose ``bio`` holds the open chunk's records),
  ``chunks`` (the chunk index records, as ``BytesIO``, written by ``close``),
  ``channel_stats`` (messages per channel id), ``message_start_time``, ``message_end_time``,
  ``compressor`` and ``compression``; the rule that a chunk is closed after the message that
  takes it past 1 MiB, and the record layout ``McapWriter.close_chunk`` writes (chunk, message
  index, chunk index);
- ``rosbags.rosbag2.storage_sqlite3.Sqlite3Writer.cursor`` and its ``messages`` table;
- ``rosbags.rosbag2.storage_mcap.decompress(data, compression, size, crc)`` for reading.

The bulk writer is used only with a rosbags version in :data:`VERIFIED_ROSBAGS` (the range the
internals were checked against) that has every attribute above; otherwise it falls back to the
public ``Writer.write`` (the same bytes, slower). A newer rosbags, which ``python3-rosbags-pip``
may install regardless of ``requirements.txt``, thus never gets records written on a guess;
``test/test_bagfast.py`` turns the fallback into a CI failure instead of a silent slow-down.

Reading (:class:`McapScanner`): an MCAP file is scanned chunk by chunk; each chunk's message
records are found in bulk and handed to a :class:`MessageSink` as ``(messages, bytes)`` uint8
matrices, one per topic and message size, without a Python object per message.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
import functools
from importlib.metadata import PackageNotFoundError, version
from io import BytesIO
from pathlib import Path
import re
import struct
from typing import BinaryIO, Final, Protocol

import numpy as np
from numpy.typing import NDArray
from piezo_stage_ros.core.contracts.errors import BagError
from piezo_stage_ros.core.contracts.types import ByteMatrix, IntArray
from rosbags.interfaces import Connection
from rosbags.rosbag2 import CompressionMode, ReaderError, Writer
from rosbags.rosbag2.storage_mcap import decompress as mcap_decompress
from rosbags.rosbag2.storage_mcap import McapWriter, PendingChunk
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Writer

__all__ = ['VERIFIED_ROSBAGS', 'WRITE_BATCH', 'BulkWriter', 'McapScanner', 'MessageSink',
           'describe', 'rosbags_verified']

#: rosbags versions ``[low, high)`` whose internals the bulk writer was checked against (the
#: bytes compared with ``Writer.write``); widen it only after ``test/test_bags.py`` and
#: ``test/test_bagfast.py`` pass with the new version.
VERIFIED_ROSBAGS: Final = ((0, 11, 9), (0, 12, 0))


_MCAP_MAGIC = b'\x89MCAP0\r\n'
_U64 = struct.Struct('<Q')


@functools.cache
def rosbags_verified() -> bool:
    """Return whether the installed rosbags is in :data:`VERIFIED_ROSBAGS`."""
    try:
        installed = version('rosbags')
    except PackageNotFoundError:
        return False
    parts = tuple(int(p) for p in re.findall(r'\d+', installed)[:3])
    low, high = VERIFIED_ROSBAGS
    return low <= parts < high


class MessageSink(Protocol):
    """Takes the raw messages of one topic (see ``bagread``)."""

    def add(self, log_ns: IntArray, rows: ByteMatrix) -> None:
        """Take ``(n, size)`` raw messages of one size with their log times [ns]."""
        ...

    def push(self, log_ns: int, data: bytes) -> None:
        """Take one raw message with its log time [ns]."""
        ...

    def flush(self) -> None:
        """Decode what :meth:`push` has collected."""
        ...


def describe(err: BaseException) -> str:
    """Return an exception as one line for an error message."""
    text = str(err).strip() or type(err).__name__
    return text.rstrip('.')


# The storage writers of rosbags 0.11 keep these; without them the bulk path is not taken.
_MCAP_STATE = ('chunk', 'chunks', 'channel_stats', 'message_start_time', 'message_end_time',
               'compressor', 'compression', 'bio')
_WRITER_STATE = ('counts', 'min_timestamp', 'max_timestamp', 'compression_mode', 'storage')
_MCAP_CHUNK_BYTES = 2**20
# Samples serialized at once: bounds the memory of a batch to some tens of MB.
WRITE_BATCH = 50_000


class BulkWriter:
    """
    Write many samples at once into the storage writer of rosbags.

    ``Writer.write`` costs some 10 us per message in Python (a BytesIO and five small writes per
    record, two more per message when the chunk is closed), which makes writing a 10 kHz run
    slower than simulating it. Here the MCAP message records of a batch are built as one numpy
    matrix and appended to the writer's open chunk in slices, with the bookkeeping
    ``McapWriter.write`` does (the chunk is closed after the message that takes it past 1 MiB,
    the statistics, the time range), and chunks are closed with the message index built in
    numpy; the file is byte for byte the one ``Writer.write`` gives (a test compares them). For
    sqlite3 the rows go in with one ``executemany``. Any other storage, or compression, takes
    the public path (:meth:`supported` is False).

    Parameters
    ----------
    writer : Writer
        An open rosbags writer into which nothing has been written yet.

    """

    def __init__(self, writer: Writer) -> None:
        self.writer = writer
        self.storage = getattr(writer, 'storage', None)
        # Per channel, in the order of the first message in the open chunk: (log, offset) pairs.
        self.index: dict[int, list[NDArray[np.uint64]]] = {}

    @property
    def supported(self) -> bool:
        """Whether this rosbags writer can be written in bulk."""
        writer, storage = self.writer, self.storage
        if not rosbags_verified():
            return False
        if not all(hasattr(writer, name) for name in _WRITER_STATE):
            return False
        if writer.compression_mode != CompressionMode.NONE:
            return False
        if isinstance(storage, Sqlite3Writer):
            return hasattr(storage, 'cursor')
        return isinstance(storage, McapWriter) and all(hasattr(storage, a) for a in _MCAP_STATE)

    def write(self, messages: Sequence[tuple[Connection, ByteMatrix]],
              stamp_ns: IntArray) -> None:
        """
        Write samples: per sample the message of every topic, in the order given.

        Parameters
        ----------
        messages : sequence of (Connection, ndarray)
            Per topic its connection and ``(n, size)`` serialized messages.
        stamp_ns : ndarray of int64
            Log time of sample k [ns].

        """
        n = stamp_ns.size
        storage = self.storage
        if isinstance(storage, Sqlite3Writer):
            logs = stamp_ns.tolist()
            table = [(connection.id, logs[k], matrix[k].tobytes())
                     for k in range(n) for connection, matrix in messages]
            storage.cursor.executemany(
                'INSERT INTO messages (topic_id, timestamp, data) VALUES(?, ?, ?)', table)
        else:
            assert isinstance(storage, McapWriter)
            self._mcap(storage, messages, stamp_ns)
        writer = self.writer
        for connection, _ in messages:
            writer.counts[connection.id] += n
        writer.min_timestamp = min(writer.min_timestamp, int(stamp_ns.min()))
        writer.max_timestamp = max(writer.max_timestamp, int(stamp_ns.max()))

    def _mcap(self, storage: McapWriter, messages: Sequence[tuple[Connection, ByteMatrix]],
              stamp_ns: IntArray) -> None:
        n = stamp_ns.size
        topic_count = len(messages)
        # One row per sample: the message records of every topic, back to back.
        sizes = np.asarray([9 + 22 + rows.shape[1] for _, rows in messages], dtype=np.int64)
        width = int(sizes.sum())
        starts = np.concatenate(([0], np.cumsum(sizes)[:-1]))
        block = np.zeros((n, width), dtype=np.uint8)
        log_bytes = stamp_ns.astype('<u8').view(np.uint8).reshape(n, 8)
        for (connection, rows), start, size in zip(messages, starts.tolist(), sizes.tolist()):
            block[:, start] = 0x05
            block[:, start + 1:start + 9] = np.frombuffer(struct.pack('<Q', size - 9), np.uint8)
            block[:, start + 9:start + 11] = np.frombuffer(struct.pack('<H', connection.id),
                                                           np.uint8)
            block[:, start + 15:start + 23] = log_bytes
            block[:, start + 23:start + 31] = log_bytes
            block[:, start + 31:start + size] = rows
        data = block.tobytes()
        del block
        # Offset of the start and of the end of every message of the batch, in write order.
        begins = (np.arange(n, dtype=np.int64)[:, None] * width + starts[None, :]).ravel()
        ends = begins + np.tile(sizes, n)
        ids = [connection.id for connection, _ in messages]
        logs = stamp_ns.astype(np.uint64)
        done, total = 0, n * topic_count
        while done < total:
            chunk = storage.chunk
            base = chunk.bio.tell()
            offset0 = int(begins[done])
            # rosbags closes the chunk after the first message that takes it past 1 MiB.
            over = int(np.searchsorted(ends, _MCAP_CHUNK_BYTES - base + offset0, side='right'))
            last = min(max(over, done), total - 1)
            for r in range(min(topic_count, last - done + 1)):
                j = (done + r) % topic_count
                first = done + r
                samples = np.arange(first // topic_count, last // topic_count + 1
                                    if last % topic_count >= j else last // topic_count)
                if samples.size == 0:
                    continue
                pairs = np.empty((samples.size, 2), dtype=np.uint64)
                pairs[:, 0] = logs[samples]
                pairs[:, 1] = (begins[samples * topic_count + j] - offset0 + base).astype(
                    np.uint64)
                self.index.setdefault(ids[j], []).append(pairs)
                storage.channel_stats[ids[j]] += int(samples.size)
            first_sample, last_sample = done // topic_count, last // topic_count
            lo = int(stamp_ns[first_sample:last_sample + 1].min())
            hi = int(stamp_ns[first_sample:last_sample + 1].max())
            chunk.message_start_time = min(chunk.message_start_time, lo)
            chunk.message_end_time = max(chunk.message_end_time, hi)
            storage.message_start_time = min(storage.message_start_time, lo)
            storage.message_end_time = max(storage.message_end_time, hi)
            chunk.bio.write(data[offset0:int(ends[last])])
            done = last + 1
            if chunk.bio.tell() > _MCAP_CHUNK_BYTES:
                self._close_chunk(storage)

    def finish(self) -> None:
        """Close the open MCAP chunk (before ``Writer.close``, which does not know our index)."""
        storage = self.storage
        if isinstance(storage, McapWriter) and storage.chunk.bio.tell() and self.index:
            self._close_chunk(storage)

    def _close_chunk(self, storage: McapWriter) -> None:
        # McapWriter.close_chunk, with the message index from our arrays.
        chunk = storage.chunk
        payload = chunk.bio.getvalue()
        compressed = storage.compressor(payload)
        compression = storage.compression.encode()
        body = (struct.pack('<QQQI', chunk.message_start_time, chunk.message_end_time,
                            len(payload), 0)
                + struct.pack('<I', len(compression)) + compression
                + struct.pack('<Q', len(compressed)))
        bio = storage.bio
        chunk_start = bio.tell()
        bio.write(b'\x06' + struct.pack('<Q', len(body) + len(compressed)) + body)
        bio.write(compressed)
        chunk_end = bio.tell()
        offsets: list[tuple[int, int]] = []
        for cid, parts in self.index.items():
            offsets.append((cid, bio.tell()))
            pairs = np.concatenate(parts).astype('<u8').tobytes()
            record = struct.pack('<HI', cid, len(pairs)) + pairs
            bio.write(b'\x07' + struct.pack('<Q', len(record)) + record)
        summary = BytesIO()
        summary.write(struct.pack('<QQQQI', chunk.message_start_time, chunk.message_end_time,
                                  chunk_start, chunk_end - chunk_start, len(offsets) * 10))
        summary.write(b''.join(struct.pack('<HQ', cid, off) for cid, off in offsets))
        summary.write(struct.pack('<Q', bio.tell() - chunk_end))
        summary.write(struct.pack('<I', len(compression)) + compression)
        summary.write(struct.pack('<QQ', len(compressed), len(payload)))
        storage.chunks.append(summary)
        storage.chunk = PendingChunk(2**63 - 1, 0, BytesIO(), defaultdict(list))
        self.index = {}


def _read_exact(stream: BinaryIO, size: int, bag: Path, what: str) -> bytes:
    data = stream.read(size)
    if len(data) != size:
        raise BagError(f'bag {bag}: storage file is truncated (in {what})')
    return data


def _gather_u64(buf: ByteMatrix, offsets: IntArray) -> IntArray:
    rows = np.ascontiguousarray(_rows(buf, offsets, 8))
    out: IntArray = rows.view('<u8')[:, 0].astype(np.int64)
    return out


def _gather_u16(buf: ByteMatrix, offsets: IntArray) -> IntArray:
    rows = np.ascontiguousarray(_rows(buf, offsets, 2))
    out: IntArray = rows.view('<u2')[:, 0].astype(np.int64)
    return out


def _mcap_string(data: bytes, offset: int) -> tuple[str, int]:
    (length,) = struct.unpack_from('<I', data, offset)
    return data[offset + 4:offset + 4 + length].decode('utf8'), offset + 4 + length


def _record_starts(data: bytes, buf: ByteMatrix, bag: Path) -> IntArray:
    """
    Return the offsets of the records in a decompressed MCAP chunk.

    Every record is ``op (1 byte), length (u64), body``, so finding them is a sequential walk.
    Walking 1.8 M records in Python costs more than everything else together, so the walk is
    done in Python only until the record sizes repeat with a short period (position,
    reference, command, ... in a bag of a run); the following starts are then predicted in bulk
    and every predicted record's length is checked against the prediction. A record whose
    length does not match ends the prediction (its start is still right, since all records
    before it were checked) and the Python walk resumes there.
    """
    end = len(data)
    unpack = _U64.unpack_from
    parts: list[IntArray] = []
    pos = 0
    walked: list[int] = []
    try:
        while pos < end:
            walked.append(pos)
            pos += 9 + unpack(data, pos + 1)[0]
            # Look for a repeating pattern every 16 records walked (cheap when there is none).
            if len(walked) % 16 or pos >= end:
                continue
            sizes = np.diff(np.asarray(walked[-16:] + [pos], dtype=np.int64))
            pattern = None
            for period in range(1, 9):
                # the whole window must repeat it: two equal sizes in a row (a JointState of
                # the same shape on two topics) are not a period of one
                whole = 16 // period * period
                if np.array_equal(sizes[-whole:],
                                  np.tile(sizes[-period:], whole // period)):
                    pattern = sizes[-period:]
                    break
            if pattern is None:
                continue
            parts.append(np.asarray(walked, dtype=np.int64))
            walked = []
            stride = int(pattern.sum())
            repeats = (end - pos) // stride
            if repeats == 0:
                continue
            cum = np.concatenate(([0], np.cumsum(pattern)[:-1]))
            predicted = (pos + stride * np.arange(repeats, dtype=np.int64)[:, None]
                         + cum[None, :]).ravel()
            lengths = _gather_u64(buf, predicted + 1) + 9
            bad = np.flatnonzero(lengths != np.tile(pattern, repeats))
            good = int(bad[0]) if bad.size else predicted.size
            parts.append(predicted[:good])
            pos = int(predicted[good]) if good < predicted.size else pos + repeats * stride
    except struct.error:
        pos = end + 1
    if pos != end:
        raise BagError(f'bag {bag}: corrupt MCAP chunk (records overrun the chunk)')
    parts.append(np.asarray(walked, dtype=np.int64))
    return np.concatenate(parts)


def _rows(buf: ByteMatrix, first: IntArray, size: int) -> ByteMatrix:
    """Return the ``(n, size)`` bytes of n messages starting at ``first`` (a view if regular)."""
    n = first.size
    if n > 1:
        step = int(first[1] - first[0])
        if step > 0 and np.all(np.diff(first) == step):
            view: ByteMatrix = np.lib.stride_tricks.as_strided(
                buf[int(first[0]):], shape=(n, size), strides=(step, 1), writeable=False)
            return view
    rows: ByteMatrix = buf[first[:, None] + np.arange(size)]
    return rows


class McapScanner:
    """Reads the message records of an MCAP file chunk by chunk, without per-message objects."""

    def __init__(self, bag: Path, file: Path, wanted: Mapping[str, MessageSink],
                 tick: Callable[[int], None]) -> None:
        self.bag = bag
        self.file = file
        self.wanted = wanted
        self.tick = tick
        self.channels: dict[int, MessageSink | None] = {}

    def _channel(self, record: bytes) -> None:
        (channel_id,) = struct.unpack_from('<H', record, 0)
        topic, _ = _mcap_string(record, 4)
        self.channels[channel_id] = self.wanted.get(topic)

    def scan(self) -> None:
        with self.file.open('rb') as stream:
            if stream.read(8) != _MCAP_MAGIC:
                raise BagError(f'bag {self.bag}: {self.file.name} is not an MCAP file')
            while True:
                head = stream.read(9)
                if len(head) == 0:
                    break
                if len(head) != 9:
                    raise BagError(f'bag {self.bag}: storage file is truncated')
                op = head[0]
                (length,) = _U64.unpack_from(head, 1)
                if op in (0x0F, 0x02):  # data end, footer: the data section is over
                    break
                if op in (0x03, 0x04, 0x05, 0x06):
                    record = _read_exact(stream, length, self.bag, 'a record')
                    if op == 0x04:
                        self._channel(record)
                    elif op == 0x05:
                        self._loose_message(record)
                    elif op == 0x06:
                        self._chunk(record)
                else:
                    stream.seek(length, 1)
        for topic in self.wanted.values():
            topic.flush()

    def _loose_message(self, record: bytes) -> None:
        channel_id, _, log_ns, _ = struct.unpack_from('<HIQQ', record, 0)
        topic = self.channels.get(channel_id)
        if topic is not None:
            topic.push(log_ns, record[22:])
            self.tick(1)

    def _chunk(self, record: bytes) -> None:
        try:
            _, _, size, crc = struct.unpack_from('<QQQI', record, 0)
            compression, offset = _mcap_string(record, 28)
            (records_size,) = _U64.unpack_from(record, offset)
            start = offset + 8
            if start + records_size > len(record):
                raise BagError(f'bag {self.bag}: a chunk is larger than its record (corrupt)')
            raw = record[start:start + records_size]
            data = mcap_decompress(raw, compression, size, crc)
        except (ReaderError, struct.error, UnicodeDecodeError, ValueError) as err:
            raise BagError(f'bag {self.bag}: corrupt MCAP chunk: {describe(err)}') from None
        buf = np.frombuffer(data, dtype=np.uint8)
        offsets = _record_starts(data, buf, self.bag)
        ops = buf[offsets]
        for i in np.flatnonzero(ops == 0x04):
            s = int(offsets[i])
            (length,) = _U64.unpack_from(data, s + 1)
            self._channel(data[s + 9:s + 9 + length])
        is_message = ops == 0x05
        messages = offsets[is_message]
        if messages.size == 0:
            return
        # Records are contiguous, so a record's length is the distance to the next one.
        lengths = np.diff(np.append(offsets, len(data)))[is_message] - 9
        if np.any(lengths < 22):
            raise BagError(f'bag {self.bag}: corrupt MCAP message record')
        channel_ids = _gather_u16(buf, messages + 9)
        for channel_id in np.flatnonzero(np.bincount(channel_ids)):
            topic = self.channels.get(int(channel_id), None)
            if topic is None:
                if int(channel_id) not in self.channels:
                    raise BagError(f'bag {self.bag}: message on unknown MCAP channel '
                                   f'{int(channel_id)} (corrupt file)')
                continue
            mine = channel_ids == channel_id
            starts_c = messages[mine]
            sizes = lengths[mine] - 22
            log_ns = _gather_u64(buf, starts_c + 15)
            if np.all(sizes == sizes[0]):
                topic.add(log_ns, _rows(buf, starts_c + 31, int(sizes[0])))
                self.tick(int(starts_c.size))
                continue
            for size in np.unique(sizes):
                same = sizes == size
                topic.add(log_ns[same], _rows(buf, starts_c[same] + 31, int(size)))
            self.tick(int(starts_c.size))


