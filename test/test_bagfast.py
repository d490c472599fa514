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
The internals of rosbags that analysis/bagfast.py relies on are still there and still mean it.

The bulk writer falls back to the public ``Writer.write`` when an internal is missing: bags stay
right, but writing becomes ~10x slower without a word. These tests turn such a rosbags upgrade
into a failure that names what changed (test_bags.py compares the bytes of both paths).
"""

import ast
import inspect
from io import BytesIO
from pathlib import Path

from piezo_stage_ros.analysis import bagfast
from piezo_stage_ros.analysis.bagwrite import RunBagWriter
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.storage_mcap import McapWriter, PendingChunk
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Writer


def test_installed_rosbags_is_verified():
    from importlib.metadata import version
    assert bagfast.rosbags_verified(), (
        f'rosbags {version("rosbags")} is outside VERIFIED_ROSBAGS {bagfast.VERIFIED_ROSBAGS}: '
        'the bulk writer is off; check the internals listed in analysis/bagfast.py, then widen '
        'the range')


def test_version_gate_turns_the_bulk_path_off(tmp_path, monkeypatch):
    monkeypatch.setattr(bagfast, 'VERIFIED_ROSBAGS', ((0, 0, 0), (0, 0, 1)))
    bagfast.rosbags_verified.cache_clear()
    try:
        with RunBagWriter(tmp_path / 'run') as writer:
            writer.write_samples([0.0], [1e-6], [1e-6], [0.0], [0.5])
            assert writer._bulk is None
    finally:
        bagfast.rosbags_verified.cache_clear()


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_bulk_path_is_taken(tmp_path, storage):
    with RunBagWriter(tmp_path / 'run', storage=storage) as writer:
        writer.write_samples([0.0, 1e-4], [1e-6, 2e-6], [1e-6, 2e-6], [0.0, 0.0], [0.5, 0.6])
        assert writer._bulk is not None, (
            f'rosbags {storage} writer lacks an internal the bulk writer needs (see '
            'analysis/bagfast.py); writes went through the slow public path')


def test_writer_internals_are_there(tmp_path):
    writer = Writer(tmp_path / 'run', version=Writer.VERSION_LATEST,
                    storage_plugin=StoragePlugin.MCAP)
    writer.open()
    try:
        missing = [name for name in bagfast._WRITER_STATE if not hasattr(writer, name)]
        assert not missing, f'rosbags Writer lost {missing}'
        storage = writer.storage
        assert isinstance(storage, McapWriter)
        missing = [name for name in bagfast._MCAP_STATE if not hasattr(storage, name)]
        assert not missing, f'rosbags McapWriter lost {missing}'
        chunk = storage.chunk
        assert isinstance(chunk, PendingChunk)
        assert (chunk.message_start_time, chunk.message_end_time) == (2**63 - 1, 0)
        assert isinstance(chunk.bio, BytesIO) and isinstance(storage.chunks, list)
        # what these internals mean (chunk size, index, statistics) is checked by comparing
        # the bytes of a bulk-written bag with those Writer.write gives (test_bags.py)
    finally:
        writer.close()


def test_sqlite_writer_has_its_cursor(tmp_path):
    writer = Writer(tmp_path / 'run', version=Writer.VERSION_LATEST,
                    storage_plugin=StoragePlugin.SQLITE3)
    writer.open()
    try:
        assert isinstance(writer.storage, Sqlite3Writer)
        assert hasattr(writer.storage, 'cursor'), 'rosbags Sqlite3Writer lost cursor'
    finally:
        writer.close()


def test_decompress_signature():
    params = list(inspect.signature(bagfast.mcap_decompress).parameters)
    assert len(params) == 4, params  # (data, compression, size, crc)
    assert bagfast.mcap_decompress(b'abc', '', 3, 0) == b'abc'


def test_no_other_module_touches_rosbags_internals():
    # rosbags' public API is rosbags.rosbag2 (Reader, Writer, ...), rosbags.typesys and
    # rosbags.interfaces; the storage plugins' modules are its internals.
    package = Path(__file__).resolve().parents[1] / 'piezo_stage_ros'
    users = set()
    for path in package.rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text(encoding='utf8'))):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module] + [f'{node.module}.{a.name}' for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            if any(n.startswith(('rosbags.rosbag2.storage_', 'rosbags.rosbag2.writer',
                                 'rosbags.rosbag2.reader')) for n in names):
                users.add(path.relative_to(package).as_posix())
    assert users == {'analysis/bagfast.py'}
