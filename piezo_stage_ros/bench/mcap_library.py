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
What Foxglove's ``mcap`` library reaches on the loop's messages through its public API.

The question: could ``mcap`` carry the fast MCAP path instead of rosbags' private
storage classes (``analysis/bagfast.py``)? Its public writer takes one message per
``add_message`` call and its reader yields one Python object per message; this prints the
messages per second of both on records of the loop's sizes, to compare with
``benchmark --suite bags`` (targets: write >= 2.3 M, analyze >= 1.5 M messages/s). The
``mcap`` package is not a dependency of this package: ``pip install mcap`` in a scratch
environment, then ``python3 -m piezo_stage_ros.bench.mcap_library [SAMPLES]``.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time

import numpy as np


def main(argv: list[str] | None = None) -> int:
    """Print the write and read rates; return the exit status."""
    args = sys.argv[1:] if argv is None else argv
    try:
        from mcap.reader import make_reader
        from mcap.writer import CompressionType, Writer
    except ImportError:
        print('mcap_library: the mcap package is not installed (pip install mcap)',
              file=sys.stderr)
        return 2
    samples = int(args[0]) if args else 200_000
    # position, reference, command as the loop writes them (bytes of the CDR messages)
    sizes = {'position': 48, 'reference': 60, 'command': 12}
    rng = np.random.default_rng(1)
    blobs = {key: [row.tobytes() for row in rng.integers(0, 255, (samples, size), np.uint8)]
             for key, size in sizes.items()}
    handle, path = tempfile.mkstemp(suffix='.mcap')
    os.close(handle)
    try:
        wall, cpu = time.perf_counter(), time.process_time()
        with open(path, 'wb') as stream:
            writer = Writer(stream, compression=CompressionType.NONE)
            writer.start(profile='ros2', library='piezo_stage_ros bench')
            schema = writer.register_schema('sensor_msgs/msg/JointState', 'ros2msg', b'')
            channels = {key: writer.register_channel(f'/stage/{key}', 'cdr', schema)
                        for key in sizes}
            add = writer.add_message
            for k in range(samples):
                log_ns = k * 100_000
                for key in sizes:
                    add(channels[key], log_ns, blobs[key][k], log_ns)
            writer.finish()
        messages = samples * len(sizes)
        _report('mcap Writer.add_message', messages, wall, cpu)
        wall, cpu = time.perf_counter(), time.process_time()
        with open(path, 'rb') as stream:
            count = sum(1 for _ in make_reader(stream).iter_messages())
        _report('mcap iter_messages (no decoding)', count, wall, cpu)
    finally:
        os.remove(path)
    return 0


def _report(what: str, messages: int, wall: float, cpu: float) -> None:
    wall = time.perf_counter() - wall
    cpu = time.process_time() - cpu
    print(f'{what:34s} {messages / wall:12,.0f} msg/s, {messages / cpu:12,.0f} msg/CPU-s '
          f'({messages} messages)')


if __name__ == '__main__':
    sys.exit(main())
