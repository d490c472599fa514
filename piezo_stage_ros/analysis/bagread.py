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
Read rosbag2 bags of runs in bulk with numpy, and align their topics by time.

Reading does not build a Python message object per message. The messages of one topic have the
same CDR layout (a 1-element array and a fixed name list), so each storage chunk is cut into a
``(messages, bytes)`` uint8 matrix, every byte that must be constant is compared with a template
(:class:`~piezo_stage_ros.core.contracts.cdr.Layout`, the codec the nodes use), and the stamps and
values are taken out as numpy views. A message that does not match the template (another layout,
big-endian CDR, a changed frame_id) is decoded by the codec's generic decoder instead, so the
fast path is an optimisation, never a guess. MCAP files are scanned by
:class:`~.bagfast.McapScanner`, sqlite3 files with one query per topic, anything else
(compressed bags) through rosbags' ``Reader``.

Alignment rule (:func:`read_run`): position and reference samples are paired by equal header
stamp (exact nanoseconds); stamps present on only one of them (a recorder that started late or
stopped early) are dropped. The command has no stamp; receive times jitter by more than a
sample period in real recordings, so commands are paired by order: command i + offset with
position message i, the offset (a recorder that caught a few more or fewer commands at the
start) being the one that minimises the median log-time difference. Diagnostics are paired by
stamp and are NaN where missing, and so is the true position of a simulation's bag
(``true_position``). The counts of dropped messages are in
``record.meta['alignment']``.

A bag with the block topic (``<ns>/block``, many samples per ``std_msgs/Float64MultiArray``,
layout in :mod:`piezo_stage_ros.core.contracts.wire`) is read from it alone: every row is a
sample with its stamp, values and number, so nothing needs pairing; a gap in the sample numbers
is a sample lost on the way to the bag, counted in ``meta['alignment']['missing_samples']``.
The block messages are few (about 100 a second), so each is decoded on its own
(:func:`~piezo_stage_ros.core.contracts.cdr.decode_block`, one copy of its data).

A bag of a stage of several axes (its command a ``Float64MultiArray``, one entry per axis;
format in :mod:`piezo_stage_ros.core.contracts.wire`) is read by :func:`read_axes` into one
record per axis, aligned by the same rules: the joints are found by name (``stage_<axis>``) in
every message, whatever their order, and the command's entries are in the stage's axis order.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
import dataclasses
from dataclasses import dataclass, field
import json
from pathlib import Path, PurePath
import sqlite3
import struct
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from piezo_stage_ros.analysis.bagfast import describe as _describe
from piezo_stage_ros.analysis.bagfast import McapScanner
from piezo_stage_ros.core.contracts.cdr import (
    CdrError,
    decode_block,
    decode_float64,
    decode_joint_state_message,
    decode_multi_array,
    float64_layout,
    joint_state_layout,
    JointStateMessage,
    Layout,
    multi_array_layout,
)
from piezo_stage_ros.core.contracts.errors import BagError
from piezo_stage_ros.core.contracts.types import ByteMatrix, FloatArray, IntArray
from piezo_stage_ros.core.contracts.wire import (
    AXES_BAG_TOPICS,
    AXES_BLOCK_SHARED,
    axes_command_dims,
    AXES_COMMAND_TYPE,
    AXIS_DIAGNOSTIC_SEPARATOR,
    axis_joint_names,
    AXIS_JOINT_PREFIX,
    axis_of_joint,
    BAG_TOPICS,
    BLOCK_DIAGNOSTIC_PREFIX,
    BLOCK_SEPARATOR,
    block_topic,
    BLOCK_TYPE,
    COMMAND_TYPE,
    is_axes_block,
    META_KEY,
    normalize_namespace,
    NS_PER_S,
    parse_axes_block_columns,
    REQUIRED_TOPICS,
    stamp_to_ns,
    STATUS_TYPE,
    topic_names,
)
from piezo_stage_ros.core.loop.record import RunRecord
from rosbags.rosbag2 import Reader, ReaderError
import yaml

__all__ = ['BagInfo', 'ProgressCallback', 'bag_axes', 'bag_info', 'is_axes_bag', 'read_axes',
           'read_run', 'read_topics']


#: Called as ``progress(messages_read, messages_total)`` while a bag is read.
ProgressCallback = Callable[[int, int], None]

# Messages handed to the decoder at once: big enough for numpy to pay off, small enough that the
# raw bytes of a long bag are never all in memory.
_BATCH = 65536
# Byte layouts kept per message size (e.g. two frame_ids of the same length).
_LAYOUTS_PER_SIZE = 4


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
                         and f'{topic[:-len("/position")]}/command' in info.topics}
                        | {topic[:-len('/block')] for topic, (msgtype, _) in info.topics.items()
                           if topic.endswith('/block') and msgtype == BLOCK_TYPE})
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise BagError(f'bag {info.path}: no stage topics found (expected <namespace>/position, '
                       '/reference and /command, or <namespace>/block; the bag has '
                       f'{sorted(info.topics) or "none"})')
    raise BagError(f'bag {info.path}: several stages recorded ({", ".join(candidates)}); '
                   'choose one with namespace= / --namespace')


class _TopicData:
    """Accumulates the decoded messages of one topic as numpy arrays."""

    def __init__(self, bag: Path, topic: str, msgtype: str,
                 joints: tuple[str, ...] | None = None) -> None:
        self.bag = bag
        self.topic = topic
        self.msgtype = msgtype
        # a stage of several axes: the joints to take, by name, in this order
        self.joints = joints
        self._picks: dict[tuple[str, ...], list[int]] = {}
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
        elif self.msgtype == AXES_COMMAND_TYPE:
            values = self._decode_axes_command(data)
            layout = multi_array_layout(axes_command_dims(values.size), values.size)
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

    def _decode_axes_command(self, data: bytes) -> FloatArray:
        # one value per axis, the layout saying so (wire.axes_command_dims)
        try:
            dims, data_offset, values = decode_multi_array(data)
        except CdrError as err:
            raise self._corrupt(err) from None
        n = len(self.joints or ())
        if dims != axes_command_dims(n) or data_offset != 0 or values.size != n:
            raise BagError(f'bag {self.bag}: a message on {self.topic} has the layout {dims} '
                           f'(data_offset {data_offset}) and {values.size} values; expected '
                           f'{n} values, one per axis {list(self.joints or ())}, dim '
                           f'{axes_command_dims(n)}')
        return values

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
        elif self.msgtype == AXES_COMMAND_TYPE:
            arrays = {'data': self._decode_axes_command(data).reshape(1, -1)}
            names = ()
        else:
            msg = self._decode_joint_state(data)
            stamps = np.array([stamp_to_ns(msg.sec, msg.nanosec)], dtype=np.int64)
            names = msg.names
            arrays = {'position': msg.position.reshape(1, -1),
                      'velocity': msg.velocity.reshape(1, -1),
                      'effort': msg.effort.reshape(1, -1)}
        self._append(np.array([log_ns], dtype=np.int64), stamps, self._columns(arrays, names))

    def _columns(self, arrays: Mapping[str, FloatArray], names: tuple[str, ...]) -> FloatArray:
        if self.msgtype == COMMAND_TYPE:
            return arrays['data'][:, :1]
        if self.msgtype == AXES_COMMAND_TYPE:
            return arrays['data']
        if self.joints is not None and not self.topic.endswith(('/diagnostics', '/applied')):
            return self._axes_columns(arrays, names)
        position = arrays.get('position')
        n = 0 if position is None else position.shape[0]
        if self.names is None:
            self.names = names
        if self.topic.endswith('/applied'):
            # the amplifier input the plant applied, in the effort array
            effort = arrays.get('effort')
            if effort is None or effort.shape[1] < 1:
                raise BagError(f'bag {self.bag}: a message on {self.topic} has an empty effort')
            return effort[:, :1]
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

    def _axes_columns(self, arrays: Mapping[str, FloatArray], names: tuple[str, ...]
                      ) -> FloatArray:
        # the positions (and velocities) of the joints asked for, found by name
        assert self.joints is not None
        pick = self._picks.get(names)
        if pick is None:
            if len(set(names)) != len(names):
                raise BagError(f'bag {self.bag}: a message on {self.topic} names a joint twice: '
                               f'{list(names)}')
            missing = [j for j in self.joints if j not in names]
            if missing:
                raise BagError(f'bag {self.bag}: a message on {self.topic} has the joints '
                               f'{list(names)}; missing: {missing} (expected the axes '
                               f'{list(self.joints)})')
            pick = self._picks[names] = [names.index(j) for j in self.joints]
        position = arrays.get('position')
        n = len(names)
        if position is None or position.shape[1] != n:
            raise BagError(f'bag {self.bag}: a message on {self.topic} has '
                           f'{0 if position is None else position.shape[1]} positions for the '
                           f'{n} joints {list(names)}')
        out = position[:, pick]
        if self.topic.endswith('/reference'):
            velocity = arrays.get('velocity')
            vel = np.full_like(out, np.nan)
            if velocity is not None and velocity.shape[1] == n:
                vel = velocity[:, pick]
            out = np.hstack((out, vel))
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
            1 if self.msgtype == COMMAND_TYPE or self.topic.endswith('/applied') else 2)
        if self.joints is not None and not self.topic.endswith(('/diagnostics', '/applied')):
            width = len(self.joints) * (2 if self.topic.endswith('/reference') else 1)
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


class _BlockData:
    """Collects the messages of the block topic and decodes each (they are few and large)."""

    def __init__(self, bag: Path, topic: str) -> None:
        self.bag = bag
        self.topic = topic
        self.blocks: list[tuple[int, tuple[str, ...], FloatArray]] = []

    def push(self, log_ns: int, data: bytes) -> None:
        try:
            names, rows = decode_block(data)
        except CdrError as err:
            raise BagError(f'bag {self.bag}: a message on {self.topic} cannot be decoded as a '
                           f'block ({BLOCK_TYPE}; corrupt data?): {_describe(err)}') from None
        self.blocks.append((log_ns, names, rows))

    def add(self, log_ns: IntArray, rows: ByteMatrix) -> None:
        for i in range(rows.shape[0]):
            self.push(int(log_ns[i]), rows[i].tobytes())

    def flush(self) -> None:
        """Nothing to do: every message is decoded as it comes."""


class _BlockTable(NamedTuple):
    """The rows of a bag's block topic, in stamp order, a republished sample once."""

    stamps: IntArray
    columns: dict[str, FloatArray]
    alignment: dict[str, Any]
    decoding: dict[str, Any]


def _block_table(info: BagInfo, ns: str, progress: ProgressCallback | None,
                 axes: bool) -> _BlockTable:
    """Return the rows of a bag's block topic by column name (blocks of one axis, or of axes)."""
    topic = block_topic(ns)
    if info.topics[topic][0] != BLOCK_TYPE:
        raise BagError(f'bag {info.path}: topic {topic} has type {info.topics[topic][0]}, '
                       f'expected {BLOCK_TYPE}')
    sink = _BlockData(info.path, topic)
    _scan(info, {topic: sink}, _progress_ticker(progress, info.topics[topic][1]))
    blocks = [(names, rows) for _, names, rows in sink.blocks if rows.shape[0]]
    if not blocks:
        raise BagError(f'bag {info.path}: topic {topic} has no samples')
    shared = len(AXES_BLOCK_SHARED)
    several = [is_axes_block(BLOCK_SEPARATOR.join(names)) for names, _ in blocks]
    if any(s != axes for s in several):
        what = 'several axes' if axes else 'one axis'
        raise BagError(f'bag {info.path}: topic {topic} has blocks that are not of {what}; '
                       + ('read it with read_run' if axes else 'read it with read_axes'))
    # every column of every block (an optional column a block does not have, or another
    # controller's diagnostics, is NaN in its rows)
    where: dict[str, int] = {}
    for names, _ in blocks:
        for name in names:
            where.setdefault(name, len(where))
    total = sum(rows.shape[0] for _, rows in blocks)
    table = np.full((total, len(where)), np.nan)
    at = 0
    for names, rows in blocks:
        n = rows.shape[0]
        table[at:at + n, [where[name] for name in names]] = rows
        at += n
    head = table[:, :shared]
    sample, sec, nanosec = head[:, 0], head[:, 1], head[:, 2]
    exact = (np.isfinite(head).all(axis=1) & (np.floor(head) == head).all(axis=1)
             & (sample >= 0) & (sec >= 0) & (nanosec >= 0) & (nanosec < NS_PER_S))
    if not exact.all():
        raise BagError(f'bag {info.path}: topic {topic} has {int((~exact).sum())} rows whose '
                       'sample number or stamp is not a whole number in range (corrupt data?)')
    stamps = sec.astype(np.int64) * NS_PER_S + nanosec.astype(np.int64)
    order = np.argsort(stamps, kind='stable')
    keep = order[_unique_first(stamps[order])]  # a republished sample counts once
    numbers = np.unique(sample[keep].astype(np.int64))
    missing = int(numbers[-1] - numbers[0] + 1 - numbers.size)
    warnings = []
    if missing:
        warnings.append(f'{missing} samples missing from the blocks (gaps in the sample '
                        f'numbers {int(numbers[0])}..{int(numbers[-1])}): lost on the way to '
                        'the bag')
    columns = {name: table[keep, j] for name, j in where.items()}
    alignment = {
        'source': 'block',
        'samples': int(keep.size),
        'block_messages': len(sink.blocks),
        'block_rows': total,
        'dropped_duplicate': total - int(keep.size),
        'first_sample': int(numbers[0]),
        'missing_samples': missing,
        'commands_paired': False,
        'command_source': 'command',
        'warnings': warnings,
    }
    return _BlockTable(stamps[keep], columns, alignment,
                       {topic: {'messages': len(sink.blocks), 'rows': total}})


def _block_command(table: _BlockTable, prefix: str = '') -> FloatArray:
    """
    Return the commands of a block's rows (of the axis whose columns start with ``prefix``).

    What the plant held (``applied_v``, real time) where the blocks have it, else what the
    controller computed (``command_v``); the alignment notes which, and unknown inputs.
    """
    columns, alignment = table.columns, table.alignment
    applied = prefix + 'applied_v'
    if applied in columns:
        command = columns[applied]
        unknown = int(np.isnan(command).sum())
        if unknown:
            alignment['warnings'].append(
                f'{unknown} of {command.size} samples have no applied input recorded '
                f'({applied}); their command is NaN')
    else:
        command = columns[prefix + 'command_v']
    alignment['commands_paired'] = alignment['commands_paired'] \
        or bool(np.isfinite(command).any())
    alignment['command_source'] = 'applied' if applied in columns else 'command'
    return command


def _read_blocks(info: BagInfo, ns: str, progress: ProgressCallback | None,
                 relative_time: bool) -> RunRecord:
    """Return the run of a bag's block topic (see :func:`read_run`)."""
    table = _block_table(info, ns, progress, axes=False)
    columns = table.columns
    command = _block_command(table)
    diagnostics = {name[len(BLOCK_DIAGNOSTIC_PREFIX):]: columns[name]
                   for name in sorted(columns) if name.startswith(BLOCK_DIAGNOSTIC_PREFIX)}
    return _run_record(info, ns, table.stamps, relative_time, table.alignment, table.decoding,
                       RunRecord(table.stamps / 1e9, columns['position_m'],
                                 columns['reference_m'], columns['velocity_mps'], command,
                                 diagnostics, true_position_m=columns.get('true_position_m')))


def _run_record(info: BagInfo, ns: str, stamps: IntArray, relative_time: bool,
                alignment: dict[str, Any], decoding: dict[str, Any],
                record: RunRecord) -> RunRecord:
    # the record of a bag: its samples, times from the first stamp if asked, the description
    # stored in the bag plus where it came from and how it was aligned
    meta = dict(info.meta)
    origin_ns = int(stamps[0])
    meta.update({'bag': str(info.path), 'time_origin_ns': origin_ns, 'namespace': ns,
                 'storage': info.storage, 'alignment': alignment, 'decoding': decoding})
    return dataclasses.replace(record, meta=meta, time_s=(stamps - origin_ns) / 1e9
                               if relative_time else record.time_s)


def _scan_sqlite(bag: Path, file: Path, wanted: Mapping[str, _TopicData | _BlockData],
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


def _scan_generic(info: BagInfo, wanted: Mapping[str, _TopicData | _BlockData],
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


def read_status(path: str | Path, namespace: str | None = None) -> dict[str, str] | None:
    """
    Return the plant's last ``stage/status`` counters in a bag, or None if it has none.

    The plant publishes them about once a second and at the end of a run (samples, late
    commands, skipped samples, lateness p50/p99/max ...); the last message holds the run's totals.

    Parameters
    ----------
    path : path-like
        The bag.
    namespace : str, optional
        Topic namespace; found from the bag when it holds exactly one stage.

    """
    info = bag_info(path)
    topic = f'{_find_namespace(info, namespace)}/status'
    if topic not in info.topics:
        return None
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    last: tuple[int, bytes] | None = None
    try:
        with Reader(info.path) as reader:
            connections = [c for c in reader.connections if c.topic == topic]
            for _, log_ns, data in reader.messages(connections=connections):
                if last is None or log_ns >= last[0]:
                    last = (log_ns, bytes(data))
        if last is None:
            return None
        msg: Any = store.deserialize_cdr(last[1], STATUS_TYPE)
    except Exception as err:  # noqa: BLE001 - storage plugins and decompressors vary
        raise BagError(f'bag {info.path}: cannot read {topic}: {_describe(err)}') from None
    return {str(kv.key): str(kv.value) for kv in msg.values}


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
    return (info, ns) + _read_topics(info, ns, progress)


def _scan(info: BagInfo, wanted: Mapping[str, _TopicData | _BlockData],
          tick: Callable[[int], None]) -> None:
    if info.compressed or info.storage not in ('mcap', 'sqlite3'):
        _scan_generic(info, wanted, tick)
    else:
        for file in info.files:
            if info.storage == 'mcap':
                McapScanner(info.path, file, wanted, tick).scan()
            else:
                _scan_sqlite(info.path, file, wanted, tick)


def _read_topics(info: BagInfo, ns: str, progress: ProgressCallback | None,
                 joints: tuple[str, ...] | None = None
                 ) -> tuple[dict[str, tuple[IntArray, IntArray | None, FloatArray]],
                            dict[str, tuple[str, ...]]]:
    # joints: the joints of a stage of several axes, in its axis order (None: one axis)
    topics = topic_names(ns)
    if info.message_count == 0:
        raise BagError(f'bag {info.path}: bag is empty (no messages)')
    for key in REQUIRED_TOPICS:
        if topics[key] not in info.topics:
            raise BagError(f'bag {info.path}: topic {topics[key]} is missing')
    types = BAG_TOPICS if joints is None else AXES_BAG_TOPICS
    if joints is None and info.topics[topics['command']][0] == AXES_COMMAND_TYPE:
        raise BagError(f'bag {info.path}: holds a run of several axes (topic '
                       f'{topics["command"]} is {AXES_COMMAND_TYPE}); read it with read_axes '
                       '(analyze does)')
    if joints is not None and topics['applied'] in info.topics:
        raise BagError(f'bag {info.path}: topic {topics["applied"]} holds one axis; a bag of '
                       'several axes cannot have it')
    for key, topic in topics.items():
        if topic in info.topics and info.topics[topic][0] != types[key]:
            raise BagError(f'bag {info.path}: topic {topic} has type {info.topics[topic][0]}, '
                           f'expected {types[key]}')
    wanted = {topic: _TopicData(info.path, topic, types[key], joints)
              for key, topic in topics.items() if topic in info.topics}
    total = sum(info.topics[t][1] for t in wanted)
    _scan(info, wanted, _progress_ticker(progress, total))
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
    return out, names


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


def _by_stamp(stamps: IntArray, values: FloatArray, wanted: IntArray) -> FloatArray:
    """Return the value of the first message stamped each of ``wanted``, NaN where none is."""
    first = _unique_first(stamps)
    out = np.full(wanted.size, np.nan)
    if first.size:
        k = np.clip(np.searchsorted(stamps[first], wanted), 0, first.size - 1)
        found = stamps[first][k] == wanted
        out[found] = values[first[k[found]]]
    return out


def read_run(path: str | Path, *, namespace: str | None = None,
             progress: ProgressCallback | None = None, relative_time: bool = False) -> RunRecord:
    """
    Read a bag into a run record, aligning its topics by time.

    Alignment: position and reference are paired by equal header stamps; the command (no stamp)
    is paired by order, command i + offset with position message i, the offset found from the
    log times (:func:`_command_offset`); diagnostics and the true position (a simulation's
    ``true_position``) are paired by stamp (NaN where missing).
    Samples that cannot be paired are dropped and counted in ``meta['alignment']``. When far
    fewer commands than positions were recorded (fewer than half: a real-time run whose commands
    came late or not at all), or none pairs, the commands are left out (NaN) and every sample
    with a position and a reference is kept, with a warning in ``meta['alignment']['warnings']``.
    A bag with ``applied`` (real time: the amplifier input the plant held over each sample,
    stamped) takes the command from it by stamp instead, NaN (with a warning) where missing.

    A bag with the block topic (``<ns>/block``) is read from it alone: the samples in stamp
    order (a sample recorded twice counts once), the command from ``applied_v`` where the
    blocks have it (real time) and from ``command_v`` otherwise, diagnostics and the true
    position from their columns; ``meta['alignment']`` has ``source`` = ``'block'`` and
    ``missing_samples`` (gaps in the sample numbers). From the same run, both paths give the
    same record.

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
        ``storage``, ``alignment`` and ``time_origin_ns`` (the first aligned stamp);
        ``true_position_m`` when the bag has ``true_position``, else None.

    Raises
    ------
    BagError
        Not a bag, empty bag, missing topic, wrong message type on a known topic, truncated or
        corrupt file, unknown storage, or no sample that can be aligned; the message names the
        bag and the problem.

    """
    info = bag_info(path)
    ns = _find_namespace(info, namespace)
    if block_topic(ns) in info.topics:
        return _read_blocks(info, ns, progress, relative_time)
    topics, names = _read_topics(info, ns, progress)
    common, pi, ri, command, alignment = _align(info, ns, topics)
    pos_val, ref_val = topics['position'][2], topics['reference'][2]
    true_position: FloatArray | None = None
    if 'true_position' in topics:
        _, true_stamp, true_val = topics['true_position']
        assert true_stamp is not None
        true_position = _by_stamp(true_stamp, true_val[:, 0], common)
    diagnostics: dict[str, FloatArray] = {}
    if 'diagnostics' in topics:
        _, diag_stamp, diag_val = topics['diagnostics']
        assert diag_stamp is not None
        for col, key in enumerate(names.get('diagnostics', ())):
            diagnostics[key] = _by_stamp(diag_stamp, diag_val[:, col], common)
    # How many messages the bulk decoder took (the rest went through rosbags one by one).
    decoding = {topic: {'messages': count, 'bulk': fast}
                for topic, (count, fast) in info.decoded.items()}
    return _run_record(info, ns, common, relative_time, alignment, decoding,
                       RunRecord(common / 1e9, pos_val[pi, 0], ref_val[ri, 0],
                                 ref_val[ri, 1], command[:, 0], diagnostics,
                                 true_position_m=true_position))


def _align(info: BagInfo, ns: str,
           topics: Mapping[str, tuple[IntArray, IntArray | None, FloatArray]]
           ) -> tuple[IntArray, IntArray, IntArray, FloatArray, dict[str, Any]]:
    """
    Pair the samples of position, reference and command (the rules of :func:`read_run`).

    Returns
    -------
    common : ndarray of int64
        The stamps of the aligned samples [ns].
    pi, ri : ndarray of int
        Their rows in the position's and the reference's values.
    command : ndarray, shape (samples, width)
        Their commands (NaN where none is paired), as many columns as the command topic has.
    alignment : dict
        What was paired and dropped (``meta['alignment']``).

    """
    pos_log, pos_stamp, _ = topics['position']
    _, ref_stamp, _ = topics['reference']
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
    warnings: list[str] = []
    by_order = order.size >= pi.size // 2
    if by_order:
        pi_cmd, cmd_pick = pi[has_cmd], order[idx[has_cmd]]
        common, ia, ib = np.intersect1d(pos_stamp[pi_cmd], ref_stamp[ri], assume_unique=True,
                                        return_indices=True)
    if 'applied' in topics:
        # real time: what the plant applied over each sample, stamped with it; the command
        # topic (no stamp) is not needed to pair anything
        common, ia, ib = np.intersect1d(pos_stamp[pi], ref_stamp[ri], assume_unique=True,
                                        return_indices=True)
        if common.size == 0:
            raise BagError(f'bag {info.path}: no position and reference messages that belong '
                           'to the same sample; nothing to align')
        pi, ri = pi[ia], ri[ib]
        _, app_stamp, app_val = topics['applied']
        assert app_stamp is not None
        command = _by_stamp(app_stamp, app_val[:, 0], common)[:, None]
        missing = int(np.isnan(command).sum())
        if missing:
            warnings.append(f'{missing} of {common.size} samples have no applied input '
                            'recorded (stage/applied); their command is NaN')
        offset, residual_ns = 0, 0.0
    elif not by_order or common.size == 0:
        # Commands carry no stamp; when far fewer came than positions (a real-time run whose
        # commands came late or not at all) they cannot be paired by order. The tracking error
        # needs position and reference only: every sample that has both is kept, the command
        # is NaN, and the bag is analysed with a warning instead of refused.
        common, ia, ib = np.intersect1d(pos_stamp[pi], ref_stamp[ri], assume_unique=True,
                                        return_indices=True)
        if common.size == 0:
            raise BagError(f'bag {info.path}: no position and reference messages that belong '
                           'to the same sample; nothing to align')
        warnings.append(f'{cmd_log.size} commands for {pi.size} positions: commands (no '
                        'stamp) cannot be paired with their samples; the tracking error is over '
                        f'all {common.size} samples, the command is left out (NaN)')
        pi, ri = pi[ia], ri[ib]
        command = np.full((common.size, cmd_val.shape[1]), np.nan)
        offset, residual_ns = 0, 0.0
    else:
        pi, ri, cmd_pick = pi_cmd[ia], ri[ib], cmd_pick[ia]
        command = cmd_val[cmd_pick]
    alignment = {
        'samples': int(common.size),
        'position_messages': int(pos_stamp.size),
        'reference_messages': int(ref_stamp.size),
        'command_messages': int(cmd_log.size),
        'dropped_position': int(pos_stamp.size - common.size),
        'dropped_reference': int(ref_stamp.size - common.size),
        'dropped_command': int(cmd_log.size - common.size),
        'command_offset': int(offset),
        'command_log_delay_median_s': float(residual_ns) / 1e9,
        'commands_paired': bool(np.isfinite(command).any()),
        'command_source': 'applied' if 'applied' in topics else 'command',
        'warnings': warnings,
    }
    return common, pi, ri, command, alignment


def is_axes_bag(info: BagInfo, namespace: str | None = None) -> bool:
    """
    Return whether a bag holds a run of several axes.

    Its command is a ``Float64MultiArray`` of one entry per axis, or, in a bag of the block
    topic alone, its blocks carry the columns of several axes.
    """
    ns = _find_namespace(info, namespace)
    command = topic_names(ns)['command']
    if command in info.topics:
        return info.topics[command][0] == AXES_COMMAND_TYPE
    label = _first_block_label(info, ns)
    return label is not None and is_axes_block(label)


def _first_block_label(info: BagInfo, ns: str) -> str | None:
    """Return the column names (``dim[1].label``) of the first block of a bag, if it has one."""
    topic = block_topic(ns)
    if topic not in info.topics or info.topics[topic][0] != BLOCK_TYPE:
        return None
    try:
        with Reader(info.path) as reader:
            connections = [c for c in reader.connections if c.topic == topic]
            for _, _, data in reader.messages(connections=connections):
                dims = decode_multi_array(bytes(data))[0]
                return str(dims[1][0]) if len(dims) == 2 else None
    except CdrError as err:
        raise BagError(f'bag {info.path}: a message on {topic} cannot be decoded as a block '
                       f'({BLOCK_TYPE}; corrupt data?): {_describe(err)}') from None
    except Exception as err:  # noqa: BLE001 - storage plugins and decompressors vary
        raise BagError(f'bag {info.path}: cannot read {topic}: {_describe(err)}') from None
    return None


def bag_axes(info: BagInfo, namespace: str | None = None) -> tuple[str, ...]:
    """
    Return the axes of a multi-axis bag in the stage's order (the order of its command).

    The run description's ``axes`` when the bag has one (a bag of this package), else the joint
    names of the first ``<ns>/position`` message (``stage_<axis>``; other joints left out),
    which the stage publishes in its axis order; in a bag of the block topic alone, the axes of
    its first block's columns.

    Raises
    ------
    BagError
        A bag with none of them, or a joint name that is not ``stage_<axis>``.

    """
    axes = info.meta.get('axes')
    if isinstance(axes, list) and axes and all(isinstance(a, str) for a in axes):
        return tuple(axes)
    ns = _find_namespace(info, namespace)
    topic = topic_names(ns)['position']
    if topic not in info.topics:
        label = _first_block_label(info, ns)
        if label is not None and is_axes_block(label):
            try:
                return parse_axes_block_columns(label).axes
            except BagError as err:
                raise BagError(f'bag {info.path}: {err}') from None
    try:
        with Reader(info.path) as reader:
            connections = [c for c in reader.connections if c.topic == topic]
            for _, _, data in reader.messages(connections=connections):
                names = decode_joint_state_message(bytes(data)).names
                axes = tuple(axis_of_joint(name) for name in names
                             if name.startswith(AXIS_JOINT_PREFIX))
                if not axes:
                    raise BagError(f'bag {info.path}: the joints {list(names)} on {topic} '
                                   f"name no axis; allowed: '{AXIS_JOINT_PREFIX}<axis>'")
                return axes
    except BagError:
        raise
    except CdrError as err:
        raise BagError(f'bag {info.path}: a message on {topic} cannot be decoded as '
                       f'sensor_msgs/msg/JointState (corrupt data?): {_describe(err)}') from None
    except Exception as err:  # noqa: BLE001 - storage plugins and decompressors vary
        raise BagError(f'bag {info.path}: cannot read {topic}: {_describe(err)}') from None
    raise BagError(f'bag {info.path}: topic {topic} has no messages')


def read_axes(path: str | Path, *, namespace: str | None = None,
              axes: tuple[str, ...] | None = None, progress: ProgressCallback | None = None,
              relative_time: bool = False) -> list[RunRecord]:
    """
    Read the bag of a stage of several axes into one run record per axis.

    The samples are aligned as :func:`read_run` aligns them, once for all axes (one message a
    sample holds every axis). Each axis' values are taken from its joint ``stage_<axis>`` by
    name, in whatever order a message lists its joints (other joints are left alone); the
    command's entries are in the stage's axis order (:func:`bag_axes`).

    Parameters
    ----------
    path : path-like
        The bag (written by :func:`~piezo_stage_ros.analysis.bagwrite.write_axes`, or
        recorded from a stage of several axes).
    namespace : str, optional
        Topic namespace; found from the bag when it holds exactly one stage.
    axes : tuple of str, optional
        The axes in the stage's order (the order of the command's entries); default
        :func:`bag_axes`.
    progress : callable, optional
        Called as ``progress(messages_read, messages_total)`` while reading.
    relative_time : bool
        ``time_s`` from the first aligned stamp (see :func:`read_run`).

    Returns
    -------
    list of RunRecord
        One per axis, in the axis order; ``meta`` is the run description of the bag, with
        its ``per_axis`` entry of that axis merged in, plus ``axis`` and what
        :func:`read_run` adds (``bag``, ``alignment`` ...). Diagnostics named ``<axis>.<key>``
        go to their axis as ``key``.

    Raises
    ------
    BagError
        What :func:`read_run` refuses, and: a one-axis bag, a bag with only the block topic
        (one axis), a message missing an axis' joint, a command of another number of axes.

    """
    info = bag_info(path)
    ns = _find_namespace(info, namespace)
    if not is_axes_bag(info, ns):
        command_topic = topic_names(ns)['command']
        if command_topic in info.topics:
            what = f'a one-axis run ({command_topic} is not {AXES_COMMAND_TYPE})'
        elif block_topic(ns) in info.topics:
            what = 'the blocks of one axis'
        else:
            raise BagError(f'bag {info.path}: has neither {command_topic} nor '
                           f'{block_topic(ns)}; a run of several axes needs one of them')
        raise BagError(f'bag {info.path}: holds {what}; read it with read_run')
    names = bag_axes(info, ns) if axes is None else tuple(axes)
    if block_topic(ns) in info.topics:
        return _read_axes_blocks(info, ns, names, progress, relative_time)
    joints = axis_joint_names(names)
    topics, found = _read_topics(info, ns, progress, joints)
    common, pi, ri, command, alignment = _align(info, ns, topics)
    n = len(names)
    if command.shape[1] != n:
        raise BagError(f'bag {info.path}: the command has {command.shape[1]} values a sample '
                       f'for the {n} axes {list(names)}')
    pos_val, ref_val = topics['position'][2], topics['reference'][2]
    true_val: FloatArray | None = None
    true_stamp: IntArray | None = None
    if 'true_position' in topics:
        _, true_stamp, true_val = topics['true_position']
    decoding = {topic: {'messages': count, 'bulk': fast}
                for topic, (count, fast) in info.decoded.items()}
    per_axis = info.meta.get('per_axis')
    records = []
    for j, name in enumerate(names):
        true_position = None
        if true_val is not None:
            assert true_stamp is not None
            true_position = _by_stamp(true_stamp, true_val[:, j], common)
        diagnostics: dict[str, FloatArray] = {}
        if 'diagnostics' in topics:
            _, diag_stamp, diag_val = topics['diagnostics']
            assert diag_stamp is not None
            prefix = name + AXIS_DIAGNOSTIC_SEPARATOR
            for col, key in enumerate(found.get('diagnostics', ())):
                if key.startswith(prefix):
                    diagnostics[key[len(prefix):]] = _by_stamp(diag_stamp, diag_val[:, col],
                                                               common)
        record = _run_record(info, ns, common, relative_time, alignment, decoding,
                             RunRecord(common / 1e9, pos_val[pi, j], ref_val[ri, j],
                                       ref_val[ri, n + j], command[:, j], diagnostics,
                                       true_position_m=true_position))
        records.append(_axis_meta(record, name, per_axis))
    return records


def _axis_meta(record: RunRecord, axis: str, per_axis: Any) -> RunRecord:
    """Return an axis' record with its ``per_axis`` description merged into ``meta``."""
    own = per_axis.get(axis, {}) if isinstance(per_axis, dict) else {}
    record.meta.pop('per_axis', None)
    record.meta.update({**(own if isinstance(own, dict) else {}), 'axis': axis})
    return record


def _read_axes_blocks(info: BagInfo, ns: str, axes: tuple[str, ...],
                      progress: ProgressCallback | None,
                      relative_time: bool) -> list[RunRecord]:
    """Return the runs of each axis from a bag's block topic (see :func:`read_axes`)."""
    table = _block_table(info, ns, progress, axes=True)
    columns = table.columns
    got = tuple(dict.fromkeys(name.split(AXIS_DIAGNOSTIC_SEPARATOR, 1)[0]
                              for name in columns if AXIS_DIAGNOSTIC_SEPARATOR in name
                              and not name.startswith(BLOCK_DIAGNOSTIC_PREFIX)))
    if set(got) != set(axes):
        raise BagError(f'bag {info.path}: the blocks hold the axes {list(got)}; expected '
                       f'{list(axes)}')
    # the commands first: the alignment (one for all axes, as the per-sample topics have it)
    # notes each axis' source and unknown applied inputs
    commands = {name: _block_command(table, name + AXIS_DIAGNOSTIC_SEPARATOR) for name in axes}
    records = []
    for name in axes:
        prefix = name + AXIS_DIAGNOSTIC_SEPARATOR
        command = commands[name]
        own = BLOCK_DIAGNOSTIC_PREFIX + prefix
        diagnostics = {key[len(own):]: columns[key] for key in sorted(columns)
                       if key.startswith(own)}
        record = _run_record(info, ns, table.stamps, relative_time, table.alignment,
                             table.decoding,
                             RunRecord(table.stamps / 1e9, columns[prefix + 'position_m'],
                                       columns[prefix + 'reference_m'],
                                       columns[prefix + 'velocity_mps'], command, diagnostics,
                                       true_position_m=columns.get(prefix + 'true_position_m')))
        records.append(_axis_meta(record, name, info.meta.get('per_axis')))
    return records
