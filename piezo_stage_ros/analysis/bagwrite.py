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
Write run records as rosbag2 bags with rosbags, chunk by chunk.

A run is stored on the topics of :mod:`piezo_stage_ros.core.contracts.wire` under one namespace
(default ``/stage``), each message serialized by :mod:`piezo_stage_ros.core.contracts.cdr`:

- ``<ns>/position``: ``sensor_msgs/msg/JointState``, stamp t_k, name ['stage'], position [y_k] m;
- ``<ns>/reference``: ``sensor_msgs/msg/JointState``, stamp t_k, name ['stage'],
  position [x_d] m, velocity [dx_d/dt] m/s;
- ``<ns>/command``: ``std_msgs/msg/Float64``, data u_k V (no stamp);
- ``<ns>/diagnostics``: ``sensor_msgs/msg/JointState``, stamp t_k, name [keys, sorted],
  position [values];
- ``<ns>/true_position``: ``sensor_msgs/msg/JointState``, stamp t_k, name ['stage'],
  position [x(t_k)] m: the true position behind y_k, only for a record that has one (a
  simulation); a bag of a record without one is what it always was;
- ``<ns>/block`` (``topics='block'`` or ``'both'``): ``std_msgs/msg/Float64MultiArray``, the
  same samples :data:`~piezo_stage_ros.core.contracts.wire.BLOCK_SAMPLES` to a message (the
  block layout of :mod:`~piezo_stage_ros.core.contracts.wire`), log time = stamp of its last row.

A run of a stage of several axes (``axes=``, :func:`write_axes`) has the same topics, one
message per sample holding every axis: the JointStates name one joint per axis
(``stage_x`` ...) in the stage's axis order, the command is a ``Float64MultiArray`` of one entry
per axis (layout ``dim[0]`` = {``axes``, N, N}), the diagnostics are named ``<axis>.<key>``;
its block holds every axis in a row (the columns of
:func:`~piezo_stage_ros.core.contracts.wire.axes_block_columns`).

Bags written here have message log time = header stamp = sample time. The run's ``meta`` dict is
kept as JSON in the bag's ``custom_data`` under
:data:`~piezo_stage_ros.core.contracts.wire.META_KEY`. Many messages go into the storage at once
through :class:`~.bagfast.BulkWriter`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
import functools
import json
from pathlib import Path
import shutil
import sqlite3
from types import TracebackType
from typing import Any, Final, Literal

import numpy as np
from numpy.typing import ArrayLike
from piezo_stage_ros.analysis.bagfast import BulkWriter, WRITE_BATCH
from piezo_stage_ros.core.contracts.cdr import (
    encode_block,
    float64_layout,
    joint_state_layout,
    Layout,
    multi_array_layout,
)
from piezo_stage_ros.core.contracts.errors import BagError
from piezo_stage_ros.core.contracts.types import ByteMatrix, FloatArray, IntArray
from piezo_stage_ros.core.contracts.wire import (
    AXES_BAG_TOPICS,
    axes_block_columns,
    axes_command_dims,
    AXIS_DIAGNOSTIC_SEPARATOR,
    axis_joint_names,
    BAG_TOPICS,
    block_columns,
    BLOCK_SAMPLES,
    block_topic,
    BLOCK_TYPE,
    DEFAULT_NAMESPACE,
    JOINT_NAME,
    JOINT_STATE_TYPE,
    META_KEY,
    NS_PER_S,
    REQUIRED_TOPICS,
    STORAGE_IDS,
    topic_names,
)
from piezo_stage_ros.core.loop.record import RunRecord
from rosbags.interfaces import (
    Connection,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
from rosbags.typesys import get_typestore, Stores
from rosbags.typesys.store import Typestore

__all__ = ['OFFERED_QOS', 'STORAGES', 'TOPIC_SETS', 'RunBagWriter', 'write_axes', 'write_run']

#: What a bag of a run can hold: the per-sample topics (as ever), the block topic, or both.
TOPIC_SETS: Final = ('samples', 'block', 'both')


STORAGES: Final[Mapping[str, StoragePlugin]] = {
    storage: StoragePlugin[storage.upper()] for storage in STORAGE_IDS}

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


@functools.cache
def _typestore() -> Typestore:
    return get_typestore(Stores.ROS2_JAZZY)


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
    topics : {'samples', 'block', 'both'}
        The per-sample topics (the default: the bag is what it always was), the block topic
        ``<ns>/block`` only (:data:`TOPIC_SETS`), or both.
    block_samples : int
        Rows of a block message (the last one of the run may have fewer), >= 1.
    axes : sequence of str, optional
        The axes of a stage of several axes, in its order (``['x', 'y']``): every sample's
        values are then one per axis (:meth:`write_axes_chunk`), on the topics of a
        multi-axis bag (module docstring); None (the default): one axis, the bag as ever.

    Raises
    ------
    BagError
        Bad storage, namespace, topics, block size or axis names, an existing path without
        ``overwrite``, a write failure.

    """

    def __init__(self, path: str | Path, *, storage: str = 'mcap', overwrite: bool = False,
                 namespace: str = DEFAULT_NAMESPACE, meta: Mapping[str, Any] | None = None,
                 bulk: bool = True, topics: str = 'samples',
                 block_samples: int = BLOCK_SAMPLES, axes: Sequence[str] | None = None) -> None:
        self.path = Path(path)
        self.axes = None if axes is None else tuple(str(a) for a in axes)
        self.joints = (JOINT_NAME,) if self.axes is None else axis_joint_names(self.axes)
        if topics not in TOPIC_SETS:
            raise BagError(f'topics {topics!r} is not supported; allowed: '
                           + ', '.join(repr(t) for t in TOPIC_SETS))
        if int(block_samples) != block_samples or block_samples < 1:
            raise BagError(f'block_samples = {block_samples!r} is out of range; allowed: an '
                           'integer >= 1')
        self.per_sample = topics != 'block'
        self.block = topics != 'samples'
        self.block_samples = int(block_samples)
        self._block_columns: tuple[str, ...] | None = None
        self._block_rows: FloatArray | None = None  # rows not yet in a message
        self._block_stamps: IntArray | None = None
        self.bulk = bulk
        self.storage = storage
        self._plugin = _check_storage(storage)
        self.overwrite = overwrite
        self.topics = topic_names(namespace)
        self.namespace = namespace
        self.meta: dict[str, Any] = dict(meta or {})
        self._writer: Writer | None = None
        self._connections: dict[str, Connection] = {}
        self._diagnostic_keys: tuple[str, ...] | None = None
        self._has_true: bool | None = None
        self._layouts: dict[str, Layout] = {}
        self._last_ns = -1
        self.samples_written = 0
        self._bulk: BulkWriter | None = None

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
            bulk = BulkWriter(writer)
            self._bulk = bulk if bulk.supported else None
        store = _typestore()
        types = BAG_TOPICS if self.axes is None else AXES_BAG_TOPICS
        for key in REQUIRED_TOPICS if self.per_sample else ():
            self._connections[key] = writer.add_connection(
                self.topics[key], types[key], typestore=store,
                offered_qos_profiles=[OFFERED_QOS])
        n = len(self.joints)
        self._layouts['position'] = joint_state_layout(names=self.joints, n_position=n)
        self._layouts['reference'] = joint_state_layout(names=self.joints, n_position=n,
                                                        n_velocity=n)
        self._layouts['command'] = float64_layout() if self.axes is None else \
            multi_array_layout(axes_command_dims(n), n)

    def _add_joint_states(self, key: str, names: Sequence[str]) -> None:
        """Add an optional JointState topic whose messages carry one position per name."""
        assert self._writer is not None
        self._connections[key] = self._writer.add_connection(
            self.topics[key], JOINT_STATE_TYPE, typestore=_typestore(),
            offered_qos_profiles=[OFFERED_QOS])
        self._layouts[key] = joint_state_layout(names=names, n_position=len(names))

    def _add_diagnostics(self, keys: tuple[str, ...]) -> None:
        self._diagnostic_keys = keys
        if keys and self.per_sample:
            self._add_joint_states('diagnostics', keys)

    def _add_true_position(self, present: bool) -> None:
        self._has_true = present
        if present and self.per_sample:
            self._add_joint_states('true_position', self.joints)

    def _add_block(self) -> None:
        assert self._writer is not None and self._diagnostic_keys is not None
        if self.axes is None:
            self._block_columns = block_columns(true_position=bool(self._has_true),
                                                diagnostics=self._diagnostic_keys)
        else:
            self._block_columns = axes_block_columns(self.axes,
                                                     true_position=bool(self._has_true),
                                                     diagnostics=self._diagnostic_keys)
        self._connections['block'] = self._writer.add_connection(
            block_topic(self.namespace), BLOCK_TYPE, typestore=_typestore(),
            offered_qos_profiles=[OFFERED_QOS])

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
                           diagnostics=record.diagnostics,
                           true_position_m=record.true_position_m)

    def write_samples(self, time_s: ArrayLike, position_m: ArrayLike, reference_m: ArrayLike,
                      reference_velocity_mps: ArrayLike, command_v: ArrayLike, *,
                      diagnostics: Mapping[str, ArrayLike] | None = None,
                      true_position_m: ArrayLike | None = None) -> None:
        """
        Append samples given as parallel arrays.

        Parameters
        ----------
        time_s : array_like
            Sample times t_k [s], >= 0 and strictly increasing (also across calls); they become
            the header stamps and the log times, rounded to whole nanoseconds.
        position_m : array_like
            Measured position y_k [m]; with ``axes``, this and the other per-sample values
            (not the diagnostics) have shape (samples, axes), columns in the axis order.
        reference_m : array_like
            Desired position x_d(t_k) [m].
        reference_velocity_mps : array_like
            Desired velocity [m/s].
        command_v : array_like
            Amplifier input voltage u_k [V].
        diagnostics : dict of str to array_like, optional
            Controller internals per sample; the same keys in every call.
        true_position_m : array_like, optional
            True position x(t_k) [m] (simulation only), on ``true_position``; given in every
            call or in none.

        Raises
        ------
        BagError
            Bag not open, arrays of different lengths, bad times, changed diagnostic keys, a
            true position in some calls only.

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
        take = self._values
        columns = {
            'position': {'position': take(position_m, n, 'position_m')},
            'reference': {'position': take(reference_m, n, 'reference_m'),
                          'velocity': take(reference_velocity_mps, n,
                                             'reference_velocity_mps')},
            'command': {'data': take(command_v, n, 'command_v')},
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
        present = true_position_m is not None
        if self._has_true is None:
            self._add_true_position(present)
        elif present != self._has_true:
            raise BagError(f'bag {self.path}: the true position is given in some chunks only')
        if true_position_m is not None:
            columns['true_position'] = {
                'position': take(true_position_m, n, 'true_position_m')}
        if self.block and self._block_columns is None:
            self._add_block()
        if n == 0:
            return
        if self.per_sample:
            order = [key for key in BAG_TOPICS if key in columns]
            messages = []
            for key in order:
                layout = self._layouts[key]
                stamps = None if layout.stamp_offset is None else stamp_ns
                messages.append((self._connections[key],
                                 layout.encode(stamps, columns[key], n)))
            # Sample k's messages go out together, in the order the nodes publish them.
            self._write(messages, stamp_ns)
        if self.block:
            self._add_rows(stamp_ns, columns)
        self._last_ns = int(stamp_ns[-1])
        self.samples_written += n

    def _values(self, values: ArrayLike, n: int, what: str) -> FloatArray:
        # one value a sample, or with axes a row of one value per axis
        if self.axes is None:
            return _as_float(values, n, what, self.path)
        arr = np.asarray(values, dtype=np.float64)
        width = len(self.axes)
        if arr.shape != (n, width):
            raise BagError(f'bag {self.path}: {what} has shape {arr.shape}, expected '
                           f'({n}, {width}): {n} samples of the axes {list(self.axes)}')
        return arr

    def write_axes_chunk(self, records: Sequence[RunRecord]) -> None:
        """
        Append the samples of a multi-axis run: one record per axis, in the axis order.

        Parameters
        ----------
        records : sequence of RunRecord
            One per axis of ``axes`` (same sample times; ``meta['axis']``, where given, must
            name the axis); their diagnostics go out as ``<axis>.<key>``.

        Raises
        ------
        BagError
            Not opened for axes, a record count or axis that does not match, times that
            differ between the axes, or anything :meth:`write_samples` refuses.

        """
        if self.axes is None:
            raise BagError(f'bag {self.path}: opened for one axis; pass axes= for a '
                           'multi-axis run')
        got = [str(r.meta.get('axis', a)) for r, a in zip(records, self.axes)]
        if len(records) != len(self.axes) or got != list(self.axes):
            raise BagError(f'bag {self.path}: records of the axes {got} for a bag of the axes '
                           f'{list(self.axes)}; allowed: one record per axis, in that order')
        time_s = records[0].time_s
        if any(not np.array_equal(r.time_s, time_s) for r in records[1:]):
            raise BagError(f"bag {self.path}: the axes' records have different sample times")
        has_true = [r.true_position_m is not None for r in records]
        if any(has_true) and not all(has_true):
            raise BagError(f'bag {self.path}: the true position is given for some axes only')

        def stack(field: str) -> FloatArray:
            return np.column_stack([np.asarray(getattr(r, field), dtype=np.float64)
                                    for r in records]) if records else np.zeros((0, 0))
        diagnostics = {f'{a}{AXIS_DIAGNOSTIC_SEPARATOR}{key}': values
                       for a, r in zip(self.axes, records) for key, values in
                       r.diagnostics.items()}
        self.write_samples(time_s, stack('position_m'), stack('reference_m'),
                           stack('reference_velocity_mps'), stack('command_v'),
                           diagnostics=diagnostics,
                           true_position_m=stack('true_position_m') if all(has_true) else None)

    def _write(self, messages: Sequence[tuple[Connection, ByteMatrix]],
               stamp_ns: IntArray) -> None:
        assert self._writer is not None
        try:
            if self._bulk is not None:
                n = stamp_ns.size
                for lo in range(0, n, WRITE_BATCH):
                    hi = min(lo + WRITE_BATCH, n)
                    self._bulk.write([(c, rows[lo:hi]) for c, rows in messages],
                                     stamp_ns[lo:hi])
            else:
                _write_each(self._writer, messages, stamp_ns)
        except (WriterError, OSError, sqlite3.Error) as err:
            raise BagError(f'bag {self.path}: write failed: {err}') from None

    def _add_rows(self, stamp_ns: IntArray, columns: Mapping[str, Mapping[str, FloatArray]]
                  ) -> None:
        # the rows of the block layout (wire.block_columns, or axes_block_columns: each axis'
        # columns together), then every whole block goes out
        n = stamp_ns.size
        sec, nanosec = np.divmod(stamp_ns, NS_PER_S)
        own = [columns['position']['position'], columns['reference']['position'],
               columns['reference']['velocity'], columns['command']['data']]
        if 'true_position' in columns:
            own.append(columns['true_position']['position'])
        if self.axes is not None:  # (n, axes) each: axis by axis
            own = [column[:, j] for j in range(len(self.axes)) for column in own]
        rows = np.column_stack([self.samples_written + np.arange(n, dtype=np.float64), sec,
                                nanosec, *own]).astype(np.float64)
        if 'diagnostics' in columns:
            rows = np.hstack((rows, columns['diagnostics']['position']))
        if self._block_rows is not None:
            assert self._block_stamps is not None
            rows = np.vstack((self._block_rows, rows))
            stamp_ns = np.concatenate((self._block_stamps, stamp_ns))
        whole = rows.shape[0] // self.block_samples * self.block_samples
        self._write_blocks(rows[:whole], stamp_ns[:whole])
        self._block_rows, self._block_stamps = rows[whole:], stamp_ns[whole:]

    def _write_blocks(self, rows: FloatArray, stamp_ns: IntArray) -> None:
        # blocks of block_samples rows (the last may be shorter), each logged at its last row
        assert self._block_columns is not None
        n, size = rows.shape[0], self.block_samples
        starts = range(0, n, size)
        blobs = [encode_block(self._block_columns, rows[i:i + size]) for i in starts]
        last = np.asarray([min(i + size, n) - 1 for i in starts], dtype=np.int64)
        whole = n // size
        # the whole blocks have one size and go in one matrix; a shorter last one on its own
        for lo, hi in ((0, whole), (whole, len(blobs))):
            if hi > lo:
                matrix = np.frombuffer(b''.join(blobs[lo:hi]), np.uint8).reshape(hi - lo, -1)
                self._write([(self._connections['block'], matrix)], stamp_ns[last[lo:hi]])

    def close(self) -> None:
        """Write the last block, the index and ``metadata.yaml``; the bag is complete then."""
        if self._writer is not None and self._block_rows is not None \
                and self._block_rows.shape[0]:
            assert self._block_stamps is not None
            self._write_blocks(self._block_rows, self._block_stamps)
        self._block_rows = self._block_stamps = None
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


def _remove_bag(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        if (path / 'metadata.yaml').exists() or not any(path.iterdir()):
            shutil.rmtree(path)
            return
    raise BagError(f'bag {path}: exists and is not a rosbag2 bag directory; refusing to '
                   'delete it, choose another path')


def write_run(record: RunRecord, path: str | Path, *, storage: str = 'mcap',
              overwrite: bool = False, namespace: str = DEFAULT_NAMESPACE,
              topics: str = 'samples', block_samples: int = BLOCK_SAMPLES) -> None:
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
    topics : {'samples', 'block', 'both'}
        Per-sample topics, the block topic, or both (see :class:`RunBagWriter`).
    block_samples : int
        Rows of a block message.

    Raises
    ------
    BagError
        The path exists (without ``overwrite``), bad options, or a write failure.

    """
    with RunBagWriter(path, storage=storage, overwrite=overwrite, namespace=namespace,
                      meta=record.meta, topics=topics,
                      block_samples=block_samples) as writer:
        writer.write_chunk(record)


def write_axes(records: Sequence[RunRecord], path: str | Path, *, storage: str = 'mcap',
               overwrite: bool = False, namespace: str = DEFAULT_NAMESPACE,
               meta: Mapping[str, Any] | None = None, topics: str = 'samples') -> None:
    """
    Write a whole multi-axis run as a bag, one message per sample and topic for all axes.

    Parameters
    ----------
    records : sequence of RunRecord
        One per axis, in the stage's axis order, each with ``meta['axis']`` (as
        :func:`~piezo_stage_ros.core.loop.axes.run_axes` returns them).
    path : path-like
        Bag directory to create.
    storage : {'mcap', 'sqlite3'}
        Storage plugin.
    overwrite : bool
        Replace an existing bag at ``path`` (see :class:`RunBagWriter`).
    namespace : str
        Topic namespace, default ``'/stage'``.
    meta : Mapping, optional
        The run's description, stored with ``axes`` (the axis order) added.
    topics : {'samples', 'block', 'both'}
        The per-sample topics, the block topic (every axis in a row), or both.

    Raises
    ------
    BagError
        A record without its axis name, the path exists (without ``overwrite``), bad
        options, or a write failure.

    """
    axes = []
    for j, rec in enumerate(records):
        if 'axis' not in rec.meta:
            raise BagError(f"bag {path}: record {j} has no meta['axis'] naming its axis")
        axes.append(str(rec.meta['axis']))
    with RunBagWriter(path, storage=storage, overwrite=overwrite, namespace=namespace,
                      meta={**(meta or {}), 'axes': axes}, axes=axes,
                      topics=topics) as writer:
        writer.write_axes_chunk(records)
