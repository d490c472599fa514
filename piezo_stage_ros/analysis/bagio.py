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
Run records as rosbag2 bags: writing with rosbags, bulk reading with numpy, time alignment.

A run is stored on four topics under one namespace (default ``/stage``):

- ``<ns>/position``: ``sensor_msgs/msg/JointState``, stamp t_k, name ['stage'], position [y_k] m;
- ``<ns>/reference``: ``sensor_msgs/msg/JointState``, stamp t_k, name ['stage'],
  position [x_d] m, velocity [dx_d/dt] m/s;
- ``<ns>/command``: ``std_msgs/msg/Float64``, data u_k V (no stamp);
- ``<ns>/diagnostics``: ``sensor_msgs/msg/JointState``, stamp t_k, name [keys], position [values].

Bags written here have message log time = header stamp = sample time. The run's ``meta`` dict is
kept as JSON in the bag's ``custom_data`` under :data:`META_KEY`.

Reading does not build a Python message object per message. The messages of one topic have the
same CDR layout (a 1-element array and a fixed name list), so each storage chunk is cut into a
``(messages, bytes)`` uint8 matrix, every byte that must be constant is compared with a template
serialized by rosbags itself, and the stamps and values are taken out as numpy views. A message
that does not match the template (another layout, big-endian CDR, a changed frame_id) is decoded
by the generic rosbags deserializer instead, so the fast path is an optimisation, never a guess.

Alignment rule (:func:`read_run`): position and reference samples are paired by equal header
stamp (exact nanoseconds); stamps present on only one of them (a recorder that started late or
stopped early) are dropped. The command has no stamp; receive times jitter by more than a
sample period in real recordings, so commands are paired by order: command i + offset with
position message i, the offset (a recorder that caught a few more or fewer commands at the
start) being the one that minimises the median log-time difference. Diagnostics are paired by
stamp and are NaN where missing. The counts of dropped messages are in
``record.meta['alignment']``.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
import functools
from io import BytesIO
import json
from pathlib import Path, PurePath
import shutil
import sqlite3
import struct
from types import TracebackType
from typing import Any, BinaryIO, Final, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from piezo_stage_ros.core.cdr import (
    CdrError,
    decode_float64,
    decode_joint_state_message,
    float64_layout,
    joint_state_layout,
    JointStateMessage,
    Layout,
)
from piezo_stage_ros.core.errors import BagError
from piezo_stage_ros.core.record import RunRecord
from piezo_stage_ros.core.wire import (
    BAG_TOPICS,
    COMMAND_TYPE,
    DEFAULT_NAMESPACE,
    JOINT_NAME,
    JOINT_STATE_TYPE,
    META_KEY,
    normalize_namespace,
    NS_PER_S,
    REQUIRED_TOPICS,
    stamp_to_ns,
    topic_names,
)
from rosbags.interfaces import (
    Connection,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import (
    CompressionMode,
    Reader,
    ReaderError,
    StoragePlugin,
    Writer,
    WriterError,
)
from rosbags.rosbag2.storage_mcap import decompress as mcap_decompress
from rosbags.rosbag2.storage_mcap import McapWriter, PendingChunk
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Writer
from rosbags.typesys import get_typestore, Stores
from rosbags.typesys.store import Typestore
import yaml

__all__ = [
    'STORAGES',
    'BagInfo',
    'ProgressCallback',
    'RunBagWriter',
    'bag_info',
    'read_run',
    'read_topics',
    'write_run',
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
ByteMatrix = NDArray[np.uint8]

#: Called as ``progress(messages_read, messages_total)`` while a bag is read.
ProgressCallback = Callable[[int, int], None]

STORAGES: Final[Mapping[str, StoragePlugin]] = {
    'mcap': StoragePlugin.MCAP,
    'sqlite3': StoragePlugin.SQLITE3,
}

# What the recorder needs to replay a topic faithfully: reliable, volatile, a deep queue (the
# Jazzy recorder stores the same profile for the publishers it saw). "Infinite" durations are
# written the way rosbag2 of Jazzy writes them.
_INFINITE = QosTime(sec=9223372036, nsec=854775807)
OFFERED_QOS: Final = Qos(
    history=QosHistory.KEEP_LAST,
    depth=1000,
    reliability=QosReliability.RELIABLE,
    durability=QosDurability.VOLATILE,
    deadline=_INFINITE,
    lifespan=_INFINITE,
    liveliness=QosLiveliness.AUTOMATIC,
    liveliness_lease_duration=_INFINITE,
    avoid_ros_namespace_conventions=False,
)

_MCAP_MAGIC = b'\x89MCAP0\r\n'
_U64 = struct.Struct('<Q')
# Messages handed to the decoder at once: big enough for numpy to pay off, small enough that the
# raw bytes of a long bag are never all in memory.
_BATCH = 65536
# Byte layouts kept per message size (e.g. two frame_ids of the same length).
_LAYOUTS_PER_SIZE = 4


@functools.cache
def _typestore() -> Typestore:
    return get_typestore(Stores.ROS2_JAZZY)


# --------------------------------------------------------------------------------------------
# Writing


def _check_storage(storage: str) -> StoragePlugin:
    try:
        return STORAGES[storage]
    except KeyError:
        raise BagError(f'storage {storage!r} is not supported; allowed: '
                       + ', '.join(repr(s) for s in STORAGES)) from None


def _as_float(values: ArrayLike, n: int, what: str, path: Path) -> FloatArray:
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    if arr.size != n:
        raise BagError(f'bag {path}: {what} has {arr.size} samples, time_s has {n}')
    return arr


class RunBagWriter:
    """
    Write a run into a new bag, chunk by chunk, so a long run need not be held in memory.

    Use as a context manager. On an exception inside the ``with`` block the partly written bag
    directory is removed, so a bag that exists is always complete.

    Parameters
    ----------
    path : path-like
        Bag directory to create (rosbag2 layout: ``metadata.yaml`` plus one storage file).
    storage : {'mcap', 'sqlite3'}
        Storage plugin; MCAP is Jazzy's default.
    overwrite : bool
        Replace an existing bag at ``path``. Only a rosbag2 directory (one with a
        ``metadata.yaml``) or an empty directory is ever removed; anything else is refused.
    namespace : str
        Namespace of the topics, default ``'/stage'`` (topics ``/stage/position`` ...).
    meta : dict, optional
        Description of the run, stored as JSON in the bag's custom_data (values that JSON
        cannot represent are stored as their ``str``).
    bulk : bool
        Write many messages at once into the rosbags storage writer (the default, several
        times faster, same bytes); False writes one message at a time through the public
        ``Writer.write`` (the tests compare both).

    Raises
    ------
    BagError
        Bad storage or namespace, an existing path without ``overwrite``, a write failure.

    """

    def __init__(self, path: str | Path, *, storage: str = 'mcap', overwrite: bool = False,
                 namespace: str = DEFAULT_NAMESPACE, meta: Mapping[str, Any] | None = None,
                 bulk: bool = True) -> None:
        self.path = Path(path)
        self.bulk = bulk
        self.storage = storage
        self._plugin = _check_storage(storage)
        self.overwrite = overwrite
        self.topics = topic_names(namespace)
        self.meta: dict[str, Any] = dict(meta or {})
        self._writer: Writer | None = None
        self._connections: dict[str, Connection] = {}
        self._diagnostic_keys: tuple[str, ...] | None = None
        self._layouts: dict[str, Layout] = {}
        self._last_ns = -1
        self.samples_written = 0
        self._bulk: _BulkWriter | None = None

    # The context-manager protocol.
    def __enter__(self) -> RunBagWriter:
        self.open()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> Literal[False]:
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return False

    def open(self) -> None:
        """Create the bag directory and its topics."""
        if self.path.exists() or self.path.is_symlink():
            if not self.overwrite:
                raise BagError(f'bag {self.path} exists already; refusing to overwrite it '
                               '(pass overwrite=True / --overwrite to replace it)')
            _remove_bag(self.path)
        writer = Writer(self.path, version=Writer.VERSION_LATEST, storage_plugin=self._plugin)
        try:
            writer.open()
        except (WriterError, OSError) as err:
            raise BagError(f'bag {self.path}: cannot create it: {err}') from None
        self._writer = writer
        if self.bulk:
            bulk = _BulkWriter(writer)
            self._bulk = bulk if bulk.supported else None
        store = _typestore()
        for key in REQUIRED_TOPICS:
            self._connections[key] = writer.add_connection(
                self.topics[key], BAG_TOPICS[key], typestore=store,
                offered_qos_profiles=[OFFERED_QOS])
        self._layouts['position'] = joint_state_layout(names=[JOINT_NAME], n_position=1)
        self._layouts['reference'] = joint_state_layout(names=[JOINT_NAME], n_position=1,
                                                        n_velocity=1)
        self._layouts['command'] = float64_layout()

    def _add_diagnostics(self, keys: tuple[str, ...]) -> None:
        assert self._writer is not None
        self._diagnostic_keys = keys
        if keys:
            self._connections['diagnostics'] = self._writer.add_connection(
                self.topics['diagnostics'], JOINT_STATE_TYPE, typestore=_typestore(),
                offered_qos_profiles=[OFFERED_QOS])
            self._layouts['diagnostics'] = joint_state_layout(names=keys, n_position=len(keys))

    def set_meta(self, meta: Mapping[str, Any]) -> None:
        """
        Replace the run description stored with the bag (written on close).

        Parameters
        ----------
        meta : dict
            Description of the run (controller, plant, trajectory, seed, parameters).

        """
        self.meta = dict(meta)

    def write_chunk(self, record: RunRecord) -> None:
        """
        Append the samples of a run record (one chunk of a longer run, or a whole run).

        Parameters
        ----------
        record : RunRecord
            Samples to append; their times must follow those already written.

        """
        self.write_samples(record.time_s, record.position_m, record.reference_m,
                           record.reference_velocity_mps, record.command_v,
                           diagnostics=record.diagnostics)

    def write_samples(self, time_s: ArrayLike, position_m: ArrayLike, reference_m: ArrayLike,
                      reference_velocity_mps: ArrayLike, command_v: ArrayLike, *,
                      diagnostics: Mapping[str, ArrayLike] | None = None) -> None:
        """
        Append samples given as parallel arrays.

        Parameters
        ----------
        time_s : array_like
            Sample times t_k [s], >= 0 and strictly increasing (also across calls); they become
            the header stamps and the log times, rounded to whole nanoseconds.
        position_m : array_like
            Measured position y_k [m].
        reference_m : array_like
            Desired position x_d(t_k) [m].
        reference_velocity_mps : array_like
            Desired velocity [m/s].
        command_v : array_like
            Amplifier input voltage u_k [V].
        diagnostics : dict of str to array_like, optional
            Controller internals per sample; the same keys in every call.

        Raises
        ------
        BagError
            Bag not open, arrays of different lengths, bad times, changed diagnostic keys.

        """
        if self._writer is None:
            raise BagError(f'bag {self.path}: not open for writing')
        times = np.asarray(time_s, dtype=np.float64).reshape(-1)
        n = times.size
        if not np.all(np.isfinite(times)) or (n and times.min() < 0.0):
            raise BagError(f'bag {self.path}: sample times must be finite and >= 0 s')
        stamp_ns = np.rint(times * NS_PER_S).astype(np.int64)
        if n and (stamp_ns[0] <= self._last_ns or np.any(np.diff(stamp_ns) <= 0)):
            raise BagError(f'bag {self.path}: sample times must be strictly increasing '
                           '(at nanosecond resolution)')
        columns = {
            'position': {'position': _as_float(position_m, n, 'position_m', self.path)},
            'reference': {'position': _as_float(reference_m, n, 'reference_m', self.path),
                          'velocity': _as_float(reference_velocity_mps, n,
                                                'reference_velocity_mps', self.path)},
            'command': {'data': _as_float(command_v, n, 'command_v', self.path)},
        }
        keys = tuple(sorted(diagnostics or {}))
        if self._diagnostic_keys is None:
            self._add_diagnostics(keys)
        elif keys != self._diagnostic_keys:
            raise BagError(f'bag {self.path}: diagnostic keys changed from '
                           f'{list(self._diagnostic_keys)} to {list(keys)}')
        if keys:
            assert diagnostics is not None
            values = np.column_stack([_as_float(diagnostics[k], n, f'diagnostic {k}', self.path)
                                      for k in keys])
            columns['diagnostics'] = {'position': values}
        if n == 0:
            return
        order = [key for key in BAG_TOPICS if key in columns]
        messages = []
        for key in order:
            layout = self._layouts[key]
            stamps = None if layout.stamp_offset is None else stamp_ns
            messages.append((self._connections[key], layout.encode(stamps, columns[key], n)))
        try:
            # Sample k's messages go out together, in the order the nodes publish them.
            if self._bulk is not None:
                for lo in range(0, n, _WRITE_BATCH):
                    hi = min(lo + _WRITE_BATCH, n)
                    self._bulk.write([(c, rows[lo:hi]) for c, rows in messages],
                                     stamp_ns[lo:hi])
            else:
                _write_each(self._writer, messages, stamp_ns)
        except (WriterError, OSError, sqlite3.Error) as err:
            raise BagError(f'bag {self.path}: write failed: {err}') from None
        self._last_ns = int(stamp_ns[-1])
        self.samples_written += n

    def close(self) -> None:
        """Write the index and ``metadata.yaml``; the bag is complete afterwards."""
        writer, self._writer = self._writer, None
        if writer is None:
            return
        writer.set_custom_data(META_KEY, json.dumps(self.meta, default=str, sort_keys=True))
        try:
            if self._bulk is not None:
                self._bulk.finish()
            writer.close()
        except (WriterError, OSError) as err:
            raise BagError(f'bag {self.path}: cannot finish it: {err}') from None

    def abort(self) -> None:
        """Stop writing and remove the incomplete bag."""
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.abort()
            shutil.rmtree(self.path, ignore_errors=True)


def _write_each(writer: Writer, messages: Sequence[tuple[Connection, ByteMatrix]],
                stamp_ns: IntArray) -> None:
    """Write sample by sample through the public ``Writer.write``."""
    write = writer.write
    blobs = [(connection, rows.shape[1], rows.tobytes()) for connection, rows in messages]
    for k, log_ns in enumerate(stamp_ns.tolist()):
        for connection, size, blob in blobs:
            write(connection, log_ns, blob[k * size:(k + 1) * size])


# The storage writers of rosbags 0.11 keep these; without them the bulk path is not taken.
_MCAP_STATE = ('chunk', 'chunks', 'channel_stats', 'message_start_time', 'message_end_time',
               'compressor', 'compression', 'bio')
_WRITER_STATE = ('counts', 'min_timestamp', 'max_timestamp', 'compression_mode', 'storage')
_MCAP_CHUNK_BYTES = 2**20
# Samples serialized at once: bounds the memory of a batch to some tens of MB.
_WRITE_BATCH = 50_000


class _BulkWriter:
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


def _remove_bag(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        if (path / 'metadata.yaml').exists() or not any(path.iterdir()):
            shutil.rmtree(path)
            return
    raise BagError(f'bag {path}: exists and is not a rosbag2 bag directory; refusing to '
                   'delete it, choose another path')


def write_run(record: RunRecord, path: str | Path, *, storage: str = 'mcap',
              overwrite: bool = False, namespace: str = DEFAULT_NAMESPACE) -> None:
    """
    Write a whole run record as a bag.

    Parameters
    ----------
    record : RunRecord
        The run; ``record.meta`` is stored with it.
    path : path-like
        Bag directory to create.
    storage : {'mcap', 'sqlite3'}
        Storage plugin.
    overwrite : bool
        Replace an existing bag at ``path`` (see :class:`RunBagWriter`).
    namespace : str
        Topic namespace, default ``'/stage'``.

    Raises
    ------
    BagError
        The path exists (without ``overwrite``), bad options, or a write failure.

    """
    with RunBagWriter(path, storage=storage, overwrite=overwrite, namespace=namespace,
                      meta=record.meta) as writer:
        writer.write_chunk(record)


# --------------------------------------------------------------------------------------------
# Reading


@dataclass
class BagInfo:
    """
    What a bag holds, from its metadata.

    Attributes
    ----------
    path : Path
        The bag.
    storage : str
        Storage identifier (``'mcap'`` or ``'sqlite3'``).
    message_count : int
        Messages in the bag.
    topics : dict of str to (str, int)
        Topic -> (message type, message count).
    meta : dict
        The run description written by :class:`RunBagWriter` (empty for other bags).
    compressed : bool
        True when rosbag2 compression is on (then the generic reader is used).
    files : list of Path
        Storage files.
    decoded : dict of str to (int, int)
        After reading: topic -> (messages decoded, of which by the bulk path).

    """

    path: Path
    storage: str
    message_count: int
    topics: dict[str, tuple[str, int]]
    meta: dict[str, Any]
    compressed: bool
    files: list[Path]
    decoded: dict[str, tuple[int, int]] = field(default_factory=dict)


def bag_info(path: str | Path) -> BagInfo:
    """
    Open a bag with rosbags and return its metadata, checking that it can be read.

    Parameters
    ----------
    path : path-like
        A rosbag2 directory, or a single ``.mcap`` / ``.db3`` file.

    Returns
    -------
    BagInfo
        Storage, topics, counts and run description.

    Raises
    ------
    BagError
        Not a bag, unreadable metadata, unknown storage, missing or truncated storage file.

    """
    bag = Path(path)
    if not bag.exists():
        raise BagError(f'bag {bag}: does not exist')
    if bag.is_dir() and not (bag / 'metadata.yaml').is_file():
        raise BagError(f'bag {bag}: not a rosbag2 bag (no metadata.yaml)')
    try:
        with Reader(bag) as reader:
            topics: dict[str, tuple[str, int]] = {}
            for conn in reader.connections:
                old = topics.get(conn.topic)
                if old is not None and old[0] != conn.msgtype:
                    raise BagError(f'bag {bag}: topic {conn.topic} has two types, {old[0]} and '
                                   f'{conn.msgtype}')
                topics[conn.topic] = (conn.msgtype, (old[1] if old else 0) + conn.msgcount)
            count = reader.message_count
            compressed = bool(reader.compression_mode)
    except BagError:
        raise
    except (ReaderError, OSError, KeyError, ValueError, TypeError, IndexError,
            struct.error, sqlite3.Error) as err:
        raise BagError(f'bag {bag}: cannot open it: {_describe(err)}') from None
    except Exception as err:  # noqa: BLE001 - apsw and the storage plugins raise their own types
        raise BagError(f'bag {bag}: cannot open it: {_describe(err)}') from None
    storage, files, meta = _storage_files(bag)
    return BagInfo(bag, storage, count, topics, meta, compressed, files)


def _describe(err: BaseException) -> str:
    text = str(err).strip() or type(err).__name__
    return text.rstrip('.')


def _storage_files(bag: Path) -> tuple[str, list[Path], dict[str, Any]]:
    if not bag.is_dir():
        return ('mcap' if bag.suffix == '.mcap' else 'sqlite3'), [bag], {}
    # rosbags has validated metadata.yaml already; this only picks out what it does not expose.
    try:
        with (bag / 'metadata.yaml').open('r', encoding='utf8') as stream:
            info = yaml.safe_load(stream)['rosbag2_bagfile_information']
        files = [bag / PurePath(str(name)).name for name in info['relative_file_paths']]
    except (OSError, yaml.YAMLError, KeyError, TypeError) as err:
        raise BagError(f'bag {bag}: cannot read metadata.yaml: {_describe(err)}') from None
    meta: dict[str, Any] = {}
    custom = info.get('custom_data')
    if isinstance(custom, dict) and isinstance(custom.get(META_KEY), str):
        try:
            loaded = json.loads(custom[META_KEY])
        except ValueError:
            loaded = None
        if isinstance(loaded, dict):
            meta = loaded
    return str(info['storage_identifier']), files, meta


def _find_namespace(info: BagInfo, namespace: str | None) -> str:
    if namespace is not None:
        return normalize_namespace(namespace)
    candidates = sorted({topic[:-len('/position')] for topic in info.topics
                         if topic.endswith('/position')
                         and f'{topic[:-len("/position")]}/command' in info.topics})
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise BagError(f'bag {info.path}: no stage topics found (expected <namespace>/position, '
                       f'/reference and /command; the bag has {sorted(info.topics) or "none"})')
    raise BagError(f'bag {info.path}: several stages recorded ({", ".join(candidates)}); '
                   'choose one with namespace= / --namespace')


class _TopicData:
    """Accumulates the decoded messages of one topic as numpy arrays."""

    def __init__(self, bag: Path, topic: str, msgtype: str) -> None:
        self.bag = bag
        self.topic = topic
        self.msgtype = msgtype
        self.layouts: dict[int, list[Layout]] = {}
        self.names: tuple[str, ...] | None = None
        self.log_ns: list[IntArray] = []
        self.stamp_ns: list[IntArray] = []
        self.values: list[FloatArray] = []
        self.pending: list[tuple[int, bytes]] = []
        self.count = 0
        self.fast = 0

    # Messages that arrive one at a time (generic reader, unchunked MCAP) are batched first.
    def push(self, log_ns: int, data: bytes) -> None:
        self.pending.append((log_ns, data))
        if len(self.pending) >= _BATCH:
            self.flush()

    def flush(self) -> None:
        pending, self.pending = self.pending, []
        by_size: dict[int, list[tuple[int, bytes]]] = {}
        for item in pending:
            by_size.setdefault(len(item[1]), []).append(item)
        for size, items in by_size.items():
            rows = np.frombuffer(b''.join(d for _, d in items), dtype=np.uint8)
            self.add(np.fromiter((t for t, _ in items), dtype=np.int64, count=len(items)),
                     rows.reshape(len(items), size))

    def add(self, log_ns: IntArray, rows: ByteMatrix) -> None:
        """Decode ``(n, size)`` raw messages of one size with their log times [ns]."""
        n, size = rows.shape
        if n == 0:
            return
        self.count += n
        layouts = self.layouts.setdefault(size, [])
        if not layouts:
            layouts.append(self._layout_for(rows[0].tobytes()))
        # Try the known layouts of this size in turn; a message none of them fits starts a new
        # one (a few per size at most), the rest goes through the generic decoder.
        index = 0
        while True:
            layout = layouts[index]
            ok, stamps, arrays = layout.decode(rows)
            if ok.any():
                good = slice(None) if ok.all() else ok
                self._append(log_ns[good], stamps, self._columns(arrays, layout.names))
                self.fast += int(ok.sum())
                if ok.all():
                    return
                rows, log_ns = rows[~ok], log_ns[~ok]
            index += 1
            if index == len(layouts):
                if len(layouts) >= _LAYOUTS_PER_SIZE:
                    break
                layouts.append(self._layout_for(rows[0].tobytes()))
        for i in range(rows.shape[0]):
            self._generic(int(log_ns[i]), rows[i].tobytes())

    def _layout_for(self, data: bytes) -> Layout:
        if self.msgtype == COMMAND_TYPE:
            self._decode_command(data)
            layout = float64_layout()
        else:
            msg = self._decode_joint_state(data)
            layout = joint_state_layout(frame_id=msg.frame_id, names=msg.names,
                                        n_position=msg.position.size,
                                        n_velocity=msg.velocity.size, n_effort=msg.effort.size)
        # A layout whose template does not reproduce a real message (big-endian, other
        # padding) would decode garbage: such messages go through the generic decoder (the
        # layout's size never matches).
        if layout.size != len(data):
            return Layout(np.zeros(len(data), np.uint8), np.ones(len(data), bool), None, {}, ())
        return layout

    def _corrupt(self, err: CdrError) -> BagError:
        return BagError(f'bag {self.bag}: a message on {self.topic} cannot be decoded as '
                        f'{self.msgtype} (corrupt data?): {_describe(err)}')

    def _decode_command(self, data: bytes) -> float:
        try:
            return decode_float64(data)
        except CdrError as err:
            raise self._corrupt(err) from None

    def _decode_joint_state(self, data: bytes) -> JointStateMessage:
        try:
            return decode_joint_state_message(data)
        except CdrError as err:
            raise self._corrupt(err) from None

    def _generic(self, log_ns: int, data: bytes) -> None:
        stamps: IntArray | None = None
        if self.msgtype == COMMAND_TYPE:
            arrays = {'data': np.array([[self._decode_command(data)]])}
            names: tuple[str, ...] = ()
        else:
            msg = self._decode_joint_state(data)
            stamps = np.array([stamp_to_ns(msg.sec, msg.nanosec)], dtype=np.int64)
            names = msg.names
            arrays = {'position': msg.position.reshape(1, -1),
                      'velocity': msg.velocity.reshape(1, -1)}
        self._append(np.array([log_ns], dtype=np.int64), stamps, self._columns(arrays, names))

    def _columns(self, arrays: Mapping[str, FloatArray], names: tuple[str, ...]) -> FloatArray:
        if self.msgtype == COMMAND_TYPE:
            return arrays['data'][:, :1]
        position = arrays.get('position')
        n = 0 if position is None else position.shape[0]
        if self.names is None:
            self.names = names
        if self.topic.endswith('/diagnostics'):
            if names != self.names:
                raise BagError(f'bag {self.bag}: the names on {self.topic} change from '
                               f'{list(self.names)} to {list(names)}')
            assert position is not None
            return position
        if position is None or position.shape[1] < 1:
            raise BagError(f'bag {self.bag}: a message on {self.topic} has an empty position')
        velocity = arrays.get('velocity')
        out = np.full((n, 2), np.nan)
        out[:, 0] = position[:, 0]
        if velocity is not None and velocity.shape[1] >= 1:
            out[:, 1] = velocity[:, 0]
        return out

    def _append(self, log_ns: IntArray, stamp_ns: IntArray | None, values: FloatArray) -> None:
        self.log_ns.append(log_ns)
        if stamp_ns is not None:
            self.stamp_ns.append(stamp_ns)
        self.values.append(values)

    def finish(self) -> tuple[IntArray, IntArray | None, FloatArray]:
        """Return log times, stamps (None for unstamped) and values, ordered by time."""
        self.flush()
        log_ns = np.concatenate(self.log_ns) if self.log_ns else np.zeros(0, np.int64)
        width = len(self.names or ()) if self.topic.endswith('/diagnostics') else (
            1 if self.msgtype == COMMAND_TYPE else 2)
        values = np.concatenate(self.values) if self.values else np.zeros((0, width))
        stamps = None
        if self.msgtype != COMMAND_TYPE:
            stamps = np.concatenate(self.stamp_ns) if self.stamp_ns else np.zeros(0, np.int64)
        key = log_ns if stamps is None else stamps
        order = np.argsort(key, kind='stable')
        if np.any(order != np.arange(order.size)):
            log_ns, values = log_ns[order], values[order]
            stamps = None if stamps is None else stamps[order]
        return log_ns, stamps, values


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
                if np.array_equal(sizes[-period:], sizes[-2 * period:-period]):
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


class _McapScanner:
    """Reads the message records of an MCAP file chunk by chunk, without per-message objects."""

    def __init__(self, bag: Path, file: Path, wanted: Mapping[str, _TopicData],
                 tick: Callable[[int], None]) -> None:
        self.bag = bag
        self.file = file
        self.wanted = wanted
        self.tick = tick
        self.channels: dict[int, _TopicData | None] = {}

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
            raise BagError(f'bag {self.bag}: corrupt MCAP chunk: {_describe(err)}') from None
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


def _scan_sqlite(bag: Path, file: Path, wanted: Mapping[str, _TopicData],
                 tick: Callable[[int], None]) -> None:
    try:
        con = sqlite3.connect(f'file:{file}?mode=ro', uri=True)
    except sqlite3.Error as err:
        raise BagError(f'bag {bag}: cannot open {file.name}: {_describe(err)}') from None
    try:
        ids = {name: tid for tid, name in con.execute('SELECT id, name FROM topics')}
        for name, topic in wanted.items():
            if name not in ids:
                continue
            cursor = con.execute('SELECT timestamp, data FROM messages WHERE topic_id = ? '
                                 'ORDER BY id', (ids[name],))
            while rows := cursor.fetchmany(_BATCH):
                sizes = {len(data) for _, data in rows}
                if len(sizes) == 1:
                    size = sizes.pop()
                    log_ns = np.fromiter((t for t, _ in rows), dtype=np.int64, count=len(rows))
                    raw = np.frombuffer(b''.join(d for _, d in rows), dtype=np.uint8)
                    topic.add(log_ns, raw.reshape(len(rows), size))
                else:
                    for log, data in rows:
                        topic.push(int(log), bytes(data))
                    topic.flush()
                tick(len(rows))
    except sqlite3.Error as err:
        raise BagError(f'bag {bag}: corrupt sqlite3 storage: {_describe(err)}') from None
    finally:
        con.close()


def _scan_generic(info: BagInfo, wanted: Mapping[str, _TopicData],
                  tick: Callable[[int], None]) -> None:
    try:
        with Reader(info.path) as reader:
            connections = [c for c in reader.connections if c.topic in wanted]
            for connection, log_ns, data in reader.messages(connections=connections):
                wanted[connection.topic].push(log_ns, bytes(data))
                tick(1)
    except BagError:
        raise
    except Exception as err:  # noqa: BLE001 - storage plugins and decompressors vary
        raise BagError(f'bag {info.path}: cannot read messages: {_describe(err)}') from None
    for topic in wanted.values():
        topic.flush()


def _progress_ticker(progress: ProgressCallback | None, total: int) -> Callable[[int], None]:
    if progress is None:
        return lambda n: None
    done = [0]
    every = max(total // 100, 1)
    last = [0]

    def tick(n: int) -> None:
        done[0] += n
        if done[0] - last[0] >= every or done[0] >= total:
            last[0] = done[0]
            progress(done[0], total)
    return tick


def read_topics(path: str | Path, *, namespace: str | None = None,
                progress: ProgressCallback | None = None
                ) -> tuple[BagInfo, str, dict[str, tuple[IntArray, IntArray | None, FloatArray]],
                           dict[str, tuple[str, ...]]]:
    """
    Read the stage topics of a bag as numpy arrays, without aligning them.

    Parameters
    ----------
    path : path-like
        The bag.
    namespace : str, optional
        Topic namespace; found from the bag when there is exactly one stage in it.
    progress : callable, optional
        Called as ``progress(messages_read, messages_total)`` about a hundred times.

    Returns
    -------
    info : BagInfo
        Metadata of the bag.
    namespace : str
        The namespace used.
    topics : dict
        Relative topic name -> (log times [ns], header stamps [ns] or None, values).
    names : dict
        Relative topic name -> JointState names seen (for diagnostics: the keys).

    Raises
    ------
    BagError
        See :func:`read_run`.

    """
    info = bag_info(path)
    ns = _find_namespace(info, namespace)
    topics = topic_names(ns)
    if info.message_count == 0:
        raise BagError(f'bag {info.path}: bag is empty (no messages)')
    for key in REQUIRED_TOPICS:
        if topics[key] not in info.topics:
            raise BagError(f'bag {info.path}: topic {topics[key]} is missing')
    for key, topic in topics.items():
        if topic in info.topics and info.topics[topic][0] != BAG_TOPICS[key]:
            raise BagError(f'bag {info.path}: topic {topic} has type {info.topics[topic][0]}, '
                           f'expected {BAG_TOPICS[key]}')
    wanted = {topic: _TopicData(info.path, topic, BAG_TOPICS[key])
              for key, topic in topics.items() if topic in info.topics}
    total = sum(info.topics[t][1] for t in wanted)
    tick = _progress_ticker(progress, total)
    if info.compressed or info.storage not in ('mcap', 'sqlite3'):
        _scan_generic(info, wanted, tick)
    else:
        for file in info.files:
            if info.storage == 'mcap':
                _McapScanner(info.path, file, wanted, tick).scan()
            else:
                _scan_sqlite(info.path, file, wanted, tick)
    out = {}
    names = {}
    for key, topic in topics.items():
        if topic in wanted:
            out[key] = wanted[topic].finish()
            names[key] = wanted[topic].names or ()
            info.decoded[topic] = (wanted[topic].count, wanted[topic].fast)
    for key in REQUIRED_TOPICS:
        if out[key][0].size == 0:
            raise BagError(f'bag {info.path}: topic {topics[key]} has no messages')
    return info, ns, out, names


def _unique_first(stamps: IntArray) -> NDArray[np.intp]:
    # Indices of the first message of each stamp (a republished sample counts once).
    if stamps.size < 2:
        return np.arange(stamps.size)
    keep = np.ones(stamps.size, dtype=bool)
    keep[1:] = stamps[1:] != stamps[:-1]
    return np.flatnonzero(keep)


def _command_offset(position_log_ns: IntArray, command_log_ns: IntArray,
                    search: int = 50) -> tuple[int, float]:
    """
    Find the index offset that pairs position and command messages, by their log times.

    Receive times jitter by more than a sample period in a real recording (bursts of several
    milliseconds were seen at 1 kHz), so nearest-log-time matching mispairs; both topics are
    published in sample order over reliable QoS, so pairing by index is right once the offset
    at the start is known. The command of sample k is computed from the position of sample k,
    so it is received after it: among the offsets whose median log-time difference
    command - position is not negative, the one with the smallest median is chosen (causal
    pairing). Nearest-in-time would be wrong for a lockstep recording, where the plant publishes
    sample k+1 right after command k arrives, closer to it than sample k. Only when no offset
    is causal (clock trouble) does the smallest median absolute difference decide. A command
    that comes back later than one sample period cannot be told apart from the next one by log
    times; the command message has no stamp (design section 6).

    Parameters
    ----------
    position_log_ns : ndarray of int64
        Log times of the position messages in stamp order [ns].
    command_log_ns : ndarray of int64
        Log times of the command messages, sorted [ns].
    search : int
        Largest offset tried, in messages.

    Returns
    -------
    offset : int
        Command index = position index + offset.
    median_ns : float
        Median log-time difference command - position at that offset [ns].

    """
    n, m = position_log_ns.size, command_log_ns.size
    causal: tuple[float, int, float] | None = None
    nearest: tuple[float, int, float] | None = None
    for offset in sorted(range(-search, search + 1), key=abs):
        lo, hi = max(0, -offset), min(n, m - offset)
        if hi - lo < min(n, m) // 2 or hi <= lo:
            continue
        # A few thousand pairs spread over the run decide the median as well as all of them.
        pick = np.linspace(lo, hi - 1, min(hi - lo, 4096)).astype(np.int64)
        delta = command_log_ns[pick + offset] - position_log_ns[pick]
        median = float(np.median(delta))
        cost = float(np.median(np.abs(delta)))
        if median >= 0.0 and (causal is None or median < causal[0]):
            causal = (median, offset, median)
        if nearest is None or cost < nearest[0]:
            nearest = (cost, offset, median)
    best = causal if causal is not None else nearest
    if best is None:
        return 0, 0.0
    return best[1], best[2]


def read_run(path: str | Path, *, namespace: str | None = None,
             progress: ProgressCallback | None = None, relative_time: bool = False) -> RunRecord:
    """
    Read a bag into a run record, aligning its topics by time.

    Alignment: position and reference are paired by equal header stamps; the command (no stamp)
    is paired by order, command i + offset with position message i, the offset found from the
    log times (:func:`_command_offset`); diagnostics are paired by stamp (NaN where missing).
    Samples that cannot be paired are dropped and counted in ``meta['alignment']``.

    Parameters
    ----------
    path : path-like
        A rosbag2 bag directory (MCAP or sqlite3), or a single ``.mcap``/``.db3`` file.
    namespace : str, optional
        Topic namespace (``'/stage'``); found from the bag when it holds exactly one stage.
    progress : callable, optional
        Called as ``progress(messages_read, messages_total)`` while reading.
    relative_time : bool
        Give ``time_s`` from the first aligned stamp, computed in integer nanoseconds (stamps
        since the epoch lose 0.2 us to float64 otherwise).

    Returns
    -------
    RunRecord
        ``time_s`` are the header stamps [s] (from the first one with ``relative_time``);
        ``meta`` is the run description stored in the bag plus ``bag``, ``namespace``,
        ``storage``, ``alignment`` and ``time_origin_ns`` (the first aligned stamp).

    Raises
    ------
    BagError
        Not a bag, empty bag, missing topic, wrong message type on a known topic, truncated or
        corrupt file, unknown storage, or no sample that can be aligned; the message names the
        bag and the problem.

    """
    info, ns, topics, names = read_topics(path, namespace=namespace, progress=progress)
    pos_log, pos_stamp, pos_val = topics['position']
    ref_log, ref_stamp, ref_val = topics['reference']
    cmd_log, _, cmd_val = topics['command']
    assert pos_stamp is not None and ref_stamp is not None
    pi = _unique_first(pos_stamp)
    ri = _unique_first(ref_stamp)
    for key, stamps, unique in (('position', pos_stamp, pi), ('reference', ref_stamp, ri)):
        # A publisher that does not stamp its messages gives one sample for the whole run.
        if stamps.size >= 4 and unique.size < stamps.size // 2:
            raise BagError(f'bag {info.path}: topic {ns}/{key} has {stamps.size} messages but '
                           f'only {unique.size} distinct header stamps; are the messages '
                           'stamped with the sample time?')
    # The command of position message i (in stamp order) is command message i + offset (in
    # log-time order); the offset absorbs a recorder that started a few messages late or early.
    order = np.argsort(cmd_log, kind='stable')
    offset, residual_ns = _command_offset(pos_log[pi], cmd_log[order])
    idx = np.arange(pi.size) + offset
    has_cmd = (idx >= 0) & (idx < order.size)
    pi, cmd_pick = pi[has_cmd], order[idx[has_cmd]]
    common, ia, ib = np.intersect1d(pos_stamp[pi], ref_stamp[ri], assume_unique=True,
                                    return_indices=True)
    pi, ri, cmd_pick = pi[ia], ri[ib], cmd_pick[ia]
    if common.size == 0:
        raise BagError(f'bag {info.path}: no position, reference and command messages that '
                       'belong to the same sample; nothing to align')
    command = cmd_val[cmd_pick, 0]
    diagnostics: dict[str, FloatArray] = {}
    if 'diagnostics' in topics:
        _, diag_stamp, diag_val = topics['diagnostics']
        assert diag_stamp is not None
        di = _unique_first(diag_stamp)
        k = np.searchsorted(diag_stamp[di], common)
        k = np.clip(k, 0, max(di.size - 1, 0))
        found = (di.size > 0) & (diag_stamp[di][k] == common) if di.size else np.zeros(
            common.size, dtype=bool)
        for col, key in enumerate(names.get('diagnostics', ())):
            column = np.full(common.size, np.nan)
            if di.size:
                column[found] = diag_val[di[k[found]], col]
            diagnostics[key] = column
    meta = dict(info.meta)
    origin_ns = int(common[0])
    meta.update({
        'bag': str(info.path),
        'time_origin_ns': origin_ns,
        'namespace': ns,
        'storage': info.storage,
        'alignment': {
            'samples': int(common.size),
            'position_messages': int(pos_stamp.size),
            'reference_messages': int(ref_stamp.size),
            'command_messages': int(cmd_log.size),
            'dropped_position': int(pos_stamp.size - common.size),
            'dropped_reference': int(ref_stamp.size - common.size),
            'dropped_command': int(cmd_log.size - common.size),
            'command_offset': int(offset),
            'command_log_delay_median_s': float(residual_ns) / 1e9,
        },
        # How many messages the bulk decoder took (the rest went through rosbags one by one).
        'decoding': {topic: {'messages': count, 'bulk': fast}
                     for topic, (count, fast) in info.decoded.items()},
    })
    return RunRecord(
        time_s=(common - origin_ns) / 1e9 if relative_time else common / 1e9,
        position_m=pos_val[pi, 0],
        reference_m=ref_val[ri, 0],
        reference_velocity_mps=ref_val[ri, 1],
        command_v=command,
        diagnostics=diagnostics,
        meta=meta,
    )

