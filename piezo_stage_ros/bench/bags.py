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
Bag benchmark: messages per second for writing, reading and analysing a 10 kHz run.

The issue's figure: a 60 s bag at 10 kHz on three topics (position, reference, command) holds
1.8 M messages; the analysis (read, align, metrics) must reach >= 500 000 messages/s where a
plain per-message ``deserialize_cdr`` loop reaches about 150 000. Run it with
``python3 -m piezo_stage_ros.bench.bags [DURATION_S]`` (or through ``benchmark``). This is a
benchmark, not a test: it prints numbers and asserts nothing.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import functools
import math
from pathlib import Path
import sys
import tempfile
import time
from typing import TypeVar

import numpy as np
from piezo_stage_ros.analysis.bagread import read_run
from piezo_stage_ros.analysis.bagwrite import write_run
from piezo_stage_ros.analysis.replay import analyze_bag
from piezo_stage_ros.core.contracts.wire import STORAGE_IDS
from piezo_stage_ros.core.loop.record import RunRecord

__all__ = ['duration_argument', 'run_bag_benchmark', 'synthetic_record']

_T = TypeVar('_T')
SAMPLE_RATE_HZ = 10000.0
# The baseline loop is slow; it is timed on this many messages and reported per second.
_BASELINE_MESSAGES = 300_000


def synthetic_record(duration_s: float, *, diagnostics: bool = False,
                     seed: int = 0) -> RunRecord:
    """
    Build a 10 kHz run that looks like a tracking run (100 Hz sine, noise, a lagging stage).

    Parameters
    ----------
    duration_s : float
        Length of the run [s].
    diagnostics : bool
        Add four controller diagnostics (a fourth topic).
    seed : int
        Seed of the noise.

    Returns
    -------
    RunRecord
        ``round(duration_s * 10 kHz)`` samples from t = 0.

    """
    n = max(int(round(duration_s * SAMPLE_RATE_HZ)), 1)
    t = np.arange(n) / SAMPLE_RATE_HZ
    rng = np.random.default_rng(seed)
    w = 2.0 * math.pi * 100.0
    reference = 3.8e-6 + 3.8e-6 * np.sin(w * t)
    position = 3.8e-6 + 3.8e-6 * np.sin(w * t - 0.01) + rng.normal(0.0, 2e-9, n)
    diag = {}
    if diagnostics:
        diag = {'theta_hat': 1.29 + 0.01 * np.tanh(t), 'phi_hat': 3.2e-4 + 0.0 * t,
                's_v': rng.normal(0.0, 1e-3, n), 'saturated': np.zeros(n)}
    return RunRecord(time_s=t, position_m=position, reference_m=reference,
                     reference_velocity_mps=3.8e-6 * w * np.cos(w * t),
                     command_v=1.34 + 1.34 * np.sin(w * t + 0.05),
                     diagnostics=diag,
                     meta={'trajectory_period_s': 0.01, 'controller': {'type': 'synthetic'}})


def _timed(func: Callable[[], _T]) -> tuple[_T, float, float]:
    # Wall and CPU time: on a shared machine the CPU figure says what the code costs.
    start, cpu = time.perf_counter(), time.process_time()
    result = func()
    return result, time.perf_counter() - start, time.process_time() - cpu


def _baseline(bag: Path, messages: int) -> tuple[float, float]:
    """Time the plain rosbags loop: every message through ``deserialize_cdr``."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    count = 0
    start, cpu = time.perf_counter(), time.process_time()
    with Reader(bag) as reader:
        for connection, _, raw in reader.messages():
            store.deserialize_cdr(raw, connection.msgtype)
            count += 1
            if count >= messages:
                break
    return (count / (time.perf_counter() - start),
            count / max(time.process_time() - cpu, 1e-9))


def _store(out: dict[str, float], key: str, messages: int, wall: float, cpu: float) -> None:
    out[f'{key}_msgs_per_s'] = messages / wall
    out[f'{key}_msgs_per_cpu_s'] = messages / cpu if cpu > 0 else math.inf


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob('*') if p.is_file())


def run_bag_benchmark(duration_s: float = 60.0, tmpdir: str | Path | None = None, *,
                      diagnostics: bool = False, storages: Sequence[str] = STORAGE_IDS,
                      baseline: bool = True, echo: bool = True) -> dict[str, float]:
    """
    Write a synthetic 10 kHz run as bags and time writing, reading and analysing them.

    Parameters
    ----------
    duration_s : float
        Length of the run [s] (60 s: 600 000 samples, 1.8 M messages on three topics).
    tmpdir : path-like, optional
        Where to put the bags (default: a temporary directory, removed afterwards).
    diagnostics : bool
        Also record four controller diagnostics (a fourth topic).
    storages : sequence of str
        Storage plugins to measure ('mcap' is the default and the issue's figure).
    baseline : bool
        Also time the plain per-message deserialize loop (on the first 300 000 messages).
    echo : bool
        Print one line per figure.

    Returns
    -------
    dict of str to float
        ``messages``; per storage ``<storage>_write_msgs_per_s``, ``<storage>_read_msgs_per_s``
        (bag to aligned run), ``<storage>_analyze_msgs_per_s`` (read + align + metrics, the
        issue's figure), each also per CPU second (``..._msgs_per_cpu_s``, what the code costs
        on a shared machine), ``<storage>_bag_mb``; ``baseline_deserialize_msgs_per_s``; and
        ``analyze_vs_baseline`` (analysis throughput of the first storage / baseline).

    """
    record = synthetic_record(duration_s, diagnostics=diagnostics)
    topics = 3 + (1 if diagnostics else 0)
    messages = len(record) * topics
    out: dict[str, float] = {'messages': float(messages), 'duration_s': float(duration_s)}

    def say(text: str) -> None:
        if echo:
            print(text, flush=True)

    say(f'bag benchmark: {duration_s:g} s at 10 kHz, {topics} topics, {messages} messages')
    with tempfile.TemporaryDirectory(dir=tmpdir) as work:
        for storage in storages:
            bag = Path(work) / f'bench_{storage}'
            _, dt, cpu = _timed(functools.partial(write_run, record, bag, storage=storage))
            _store(out, f'{storage}_write', messages, dt, cpu)
            out[f'{storage}_bag_mb'] = _size(bag) / 1e6
            back, dt, cpu = _timed(functools.partial(read_run, bag))
            if len(back) != len(record):
                raise RuntimeError(f'benchmark: {storage} bag read back {len(back)} samples '
                                   f'of {len(record)}')
            del back
            _store(out, f'{storage}_read', messages, dt, cpu)
            _, dt, cpu = _timed(functools.partial(analyze_bag, bag))
            _store(out, f'{storage}_analyze', messages, dt, cpu)
            for what, note in (('write', f'({out[f"{storage}_bag_mb"]:.1f} MB)'),
                               ('read', '(bag -> aligned run)'),
                               ('analyze', '(read + align + metrics)')):
                say(f'  {storage:8s} {what:8s}{out[f"{storage}_{what}_msgs_per_s"]:>12,.0f} '
                    f'msg/s, {out[f"{storage}_{what}_msgs_per_cpu_s"]:>12,.0f} msg/CPU-s '
                    f'{note}')
            if baseline and storage == storages[0]:
                rate, rate_cpu = _baseline(bag, min(_BASELINE_MESSAGES, messages))
                out['baseline_deserialize_msgs_per_s'] = rate
                out['baseline_deserialize_msgs_per_cpu_s'] = rate_cpu
                say(f'  baseline: per-message deserialize_cdr loop {rate:>12,.0f} msg/s, '
                    f'{rate_cpu:>12,.0f} msg/CPU-s')
    first = f'{storages[0]}_analyze_msgs_per_s'
    if 'baseline_deserialize_msgs_per_s' in out:
        out['analyze_vs_baseline'] = out[first] / out['baseline_deserialize_msgs_per_s']
        say(f'  analysis is {out["analyze_vs_baseline"]:.1f}x the plain loop; target >= 500,000 '
            f'msg/s: {"met" if out[first] >= 500_000 else "NOT met"} (wall clock)')
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """
    Run the benchmark from the command line: ``python3 -m piezo_stage_ros.bench.bags [S]``.

    Parameters
    ----------
    argv : sequence of str, optional
        Optional run length in seconds (default 60).

    Returns
    -------
    int
        0, or 2 on a bad argument.

    """
    duration = duration_argument(argv, 'bags benchmark')
    if duration is None:
        return 2
    run_bag_benchmark(duration)
    return 0


def duration_argument(argv: Sequence[str] | None, prog: str) -> float | None:
    """Return the run length [s] of a benchmark's command line (default 60), None if bad."""
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        duration = float(args[0]) if args else 60.0
        if not (math.isfinite(duration) and duration > 0):
            raise ValueError
    except ValueError:
        print(f'{prog}: error: duration {args[0]!r} is not a number of seconds > 0',
              file=sys.stderr)
        return None
    return duration


if __name__ == '__main__':
    sys.exit(main())
