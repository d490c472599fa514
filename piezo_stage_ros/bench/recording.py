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
Recording benchmark: what one sample costs on the block topic and as per-sample messages.

Two sides, no ROS needed:

- **the executor** (the plant node in real time): the samples of a servo run on a scripted
  clock (RAC, diagnostics every 10th sample) are handed over in batches of 20 (2 ms at 10 kHz,
  the node's timer), and each path does the work of the node: the per-sample path makes a
  :class:`~piezo_stage_ros.nodes.servo.ServoSample` of each row and serializes its messages
  (position, reference, command, applied, and the diagnostics of every 10th); the block path
  turns the batch into ``stage/block`` messages
  (:class:`~piezo_stage_ros.nodes.recording.BlockRecorder`). Reported: CPU time per sample and
  messages handed to the middleware per sample (each costs a publish call and a delivery per
  subscriber on top of what is timed here; not measured here, where there is no rclpy);
- **the bag**: a 10 kHz run written as per-sample topics and as blocks (``write_run``), read
  back (``read_run``): CPU time per sample and bytes per sample.

Run: ``python3 -m piezo_stage_ros.bench.recording [DURATION_S]`` or ``benchmark --suite
recording``. A benchmark, not a test: it prints figures and asserts only that both paths hold
the same samples.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import functools
import math
from pathlib import Path
import sys
import tempfile
import time
from typing import Any, TypeVar

import numpy as np
from piezo_stage_ros.analysis.bagread import read_run
from piezo_stage_ros.analysis.bagwrite import write_run
from piezo_stage_ros.bench.bags import duration_argument, synthetic_record
from piezo_stage_ros.core.contracts.cdr import encode_float64, JointStateEncoder
from piezo_stage_ros.core.contracts.wire import BLOCK_SAMPLES, JOINT_NAME, ns_to_stamp
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.stage import StageParams
from piezo_stage_ros.hardware.bridge import ModelBridge
from piezo_stage_ros.hardware.pacing import Pacer
from piezo_stage_ros.hardware.safety import GuardedPlant
from piezo_stage_ros.nodes.logic import ControllerLogic, TrajectoryLogic
from piezo_stage_ros.nodes.recording import BlockRecorder, SampleBatch
from piezo_stage_ros.nodes.servo import batch_of, samples_of, ServoLoop, ServoSample

__all__ = ['executor_cost', 'format_lines', 'main', 'run_recording_benchmark']

_T = TypeVar('_T')
_PERIOD_NS = 100_000
#: Samples the node's timer (2 ms) finds waiting at 10 kHz.
BATCH = 20


class _Clock:
    """A scripted monotonic clock: never late, no wall time."""

    def __init__(self) -> None:
        self.now = 10**9

    def __call__(self) -> int:
        self.now += 300
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += int(seconds * 1e9)


def _served(samples: int) -> list[tuple[int, ServoSample]]:
    # a servo run on a scripted clock: the samples a real-time loop hands to the executor
    clock = _Clock()
    params = StageParams.from_flat({'plant.model': 'reduced', 'seed': 1})
    loop = ServoLoop(
        GuardedPlant(ModelBridge(params), params.chain, 0.01),
        TrajectoryLogic(make_trajectory(TrajectoryParams()), sample_rate_hz=1e4, chunk_s=1.0),
        ControllerLogic(build_controller(ControllerParams.from_flat({'type': 'rac'}), 1e-4),
                        mode='realtime', diagnostics_every=10),
        sample_rate_hz=1e4, duration_s=samples / 1e4, capacity=samples + 1,
        pacer=Pacer(_PERIOD_NS, clock=clock, sleep=clock.sleep))
    loop.run(start_ns=1_700_000_000 * 10**9)
    return list(loop.samples)


def _cpu(fn: Callable[[], _T]) -> tuple[_T, float]:
    start = time.process_time()
    out = fn()
    return out, time.process_time() - start


def _per_sample(batches: Sequence[SampleBatch]) -> int:
    # what the node does for the per-sample topics: a ServoSample per row, then its messages
    position = JointStateEncoder([JOINT_NAME])
    reference = JointStateEncoder([JOINT_NAME], with_velocity=True)
    applied = JointStateEncoder([JOINT_NAME], effort=True)
    diagnostics: dict[tuple[str, ...], JointStateEncoder] = {}
    messages = 0
    for batch in batches:
        for s in samples_of(batch):
            sec, nanosec = ns_to_stamp(s.stamp_ns)
            position.encode(sec, nanosec, (s.position_m,))
            reference.encode(sec, nanosec, (s.reference_m,), (s.velocity_mps,))
            encode_float64(s.command_v)
            applied.encode(sec, nanosec, (s.applied_v,))
            messages += 4
            if s.diagnostics is not None and s.diagnostic_names is not None:
                encoder = diagnostics.get(s.diagnostic_names)
                if encoder is None:
                    encoder = diagnostics[s.diagnostic_names] = JointStateEncoder(
                        s.diagnostic_names)
                encoder.encode(sec, nanosec, s.diagnostics)
                messages += 1
    return messages


def _blocks(batches: Sequence[SampleBatch]) -> list[bytes]:
    recorder = BlockRecorder(BLOCK_SAMPLES)
    out: list[bytes] = []
    for batch in batches:
        out += recorder.add(batch)
    return out + recorder.finish()


def executor_cost(samples: int = 20_000, repeats: int = 3) -> dict[str, float]:
    """
    Return the executor's CPU time per sample [us] and messages per sample of both paths.

    Parameters
    ----------
    samples : int
        Samples of the servo run (10 kHz).
    repeats : int
        Each path is timed this often; the least time is kept (the others had company).

    """
    items = _served(samples)
    batches = [batch_of(items[lo:lo + BATCH]) for lo in range(0, len(items), BATCH)]
    n = len(items)
    per_sample = block = math.inf
    messages = 0
    blocks: list[bytes] = []
    for _ in range(repeats):
        messages, cpu = _cpu(lambda: _per_sample(batches))
        per_sample = min(per_sample, cpu)
        blocks, cpu = _cpu(lambda: _blocks(batches))
        block = min(block, cpu)
    return {
        'samples': float(n),
        'per_sample_us': 1e6 * per_sample / n,
        'per_sample_messages_per_sample': messages / n,
        'block_us': 1e6 * block / n,
        'block_messages_per_sample': len(blocks) / n,
        'block_bytes_per_sample': sum(len(b) for b in blocks) / n,
    }


def bag_cost(duration_s: float, tmpdir: str | None = None) -> dict[str, float]:
    """Return write and read CPU time per sample [us] and bytes per sample of both bags."""
    record = synthetic_record(duration_s, diagnostics=True)
    n = len(record)
    out: dict[str, float] = {'bag_samples': float(n)}
    with tempfile.TemporaryDirectory(dir=tmpdir) as work:
        back = {}
        for topics in ('samples', 'block'):
            bag = Path(work) / topics
            _, cpu = _cpu(functools.partial(write_run, record, bag, topics=topics))
            out[f'bag_{topics}_write_us'] = 1e6 * cpu / n
            back[topics], cpu = _cpu(functools.partial(read_run, bag))
            out[f'bag_{topics}_read_us'] = 1e6 * cpu / n
            out[f'bag_{topics}_bytes_per_sample'] = sum(
                p.stat().st_size for p in bag.iterdir()) / n
        for name in ('time_s', 'position_m', 'reference_m', 'command_v'):
            if not np.array_equal(getattr(back['samples'], name), getattr(back['block'], name)):
                raise RuntimeError(f'recording benchmark: the two bags differ in {name}')
    return out


def run_recording_benchmark(duration_s: float = 60.0, samples: int = 20_000,
                            echo: bool = True) -> dict[str, Any]:
    """
    Run both sides and print the figures.

    Parameters
    ----------
    duration_s : float
        Length of the bag run [s] at 10 kHz.
    samples : int
        Samples of the servo run timed on the executor side.
    echo : bool
        Print the lines (:func:`format_lines`).

    """
    out: dict[str, Any] = dict(executor_cost(samples))
    out.update(bag_cost(duration_s))
    if echo:
        print('\n'.join(format_lines(out)), flush=True)
    return out


def format_lines(out: dict[str, Any]) -> list[str]:
    """Return the figures as lines of text."""
    ratio = out['per_sample_us'] / out['block_us']
    return [
        f'recording benchmark: executor side, {out["samples"]:.0f} servo samples in batches '
        f'of {BATCH}',
        f'  per-sample messages  {out["per_sample_us"]:7.2f} us CPU/sample, '
        f'{out["per_sample_messages_per_sample"]:.2f} messages/sample (+ a publish call each)',
        f'  stage/block          {out["block_us"]:7.2f} us CPU/sample, '
        f'{out["block_messages_per_sample"]:.3f} messages/sample, '
        f'{out["block_bytes_per_sample"]:.0f} B/sample',
        f'  the block path costs 1/{ratio:.0f} of the per-sample encoding and '
        f'1/{out["per_sample_messages_per_sample"] / out["block_messages_per_sample"]:.0f} of '
        'its publish calls',
        f'recording benchmark: bag side, {out["bag_samples"]:.0f} samples (10 kHz, diagnostics)',
        f'  per-sample topics    write {out["bag_samples_write_us"]:6.2f} us/sample, read '
        f'{out["bag_samples_read_us"]:6.2f} us/sample, '
        f'{out["bag_samples_bytes_per_sample"]:.0f} B/sample',
        f'  stage/block          write {out["bag_block_write_us"]:6.2f} us/sample, read '
        f'{out["bag_block_read_us"]:6.2f} us/sample, {out["bag_block_bytes_per_sample"]:.0f} '
        'B/sample',
    ]


def main(argv: Sequence[str] | None = None) -> int:
    """``python3 -m piezo_stage_ros.bench.recording [DURATION_S]``: 0, or 2 on a bad argument."""
    duration = duration_argument(argv, 'recording benchmark')
    if duration is None:
        return 2
    run_recording_benchmark(duration)
    return 0


if __name__ == '__main__':
    sys.exit(main())
