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
Multi-axis bag benchmark: samples per second written and read for 1-3 axes at 10 kHz.

A sample of a multi-axis bag is one message per topic for all axes (position, reference,
command, true position), so its cost grows with the message's size, not with N messages.
``python3 -m piezo_stage_ros.bench.axes_bags [DURATION_S]`` (default 60 s) prints, per storage,
the one-axis bag of :func:`~piezo_stage_ros.analysis.bagwrite.write_run` beside the
multi-axis bags of :func:`~piezo_stage_ros.analysis.bagwrite.write_axes` of 1, 2 and 3 axes:
samples per wall and per CPU second for writing and for reading back (aligned records). A
benchmark, not a test: it prints numbers and asserts nothing.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import dataclasses
import functools
from pathlib import Path
import tempfile

from piezo_stage_ros.analysis.bagread import read_axes, read_run
from piezo_stage_ros.analysis.bagwrite import write_axes, write_run
from piezo_stage_ros.bench.bags import _timed, duration_argument, synthetic_record
from piezo_stage_ros.core.contracts.wire import STORAGE_IDS

__all__ = ['main', 'run_axes_bag_benchmark']


def run_axes_bag_benchmark(duration_s: float = 60.0, *, axes: Sequence[int] = (1, 2, 3),
                           storages: Sequence[str] = STORAGE_IDS,
                           echo: bool = True) -> dict[str, float]:
    """
    Time writing and reading bags of a synthetic 10 kHz run of one to three axes.

    Parameters
    ----------
    duration_s : float
        Length of the run [s].
    axes : sequence of int
        Axis counts of the multi-axis bags (each 1-3).
    storages : sequence of str
        Storage plugins.
    echo : bool
        Print one line per case.

    Returns
    -------
    dict of str to float
        ``<storage>_<case>_write_samples_per_s`` and ``..._read_samples_per_s`` (wall; also
        ``..._per_cpu_s``), case ``one`` (the one-axis bag) or ``axes<N>``.

    """
    base = synthetic_record(duration_s)
    base = dataclasses.replace(base, true_position_m=base.position_m.copy())
    names = ('x', 'y', 'z')
    out: dict[str, float] = {'samples': float(len(base))}
    with tempfile.TemporaryDirectory() as work:
        for storage in storages:
            cases = [('one', None)] + [(f'axes{n}', names[:n]) for n in axes]
            for case, chosen in cases:
                bag = Path(work) / f'{storage}_{case}'
                calls: tuple[Callable[[], object], Callable[[], object]]
                if chosen is None:
                    calls = (functools.partial(write_run, base, bag, storage=storage),
                             functools.partial(read_run, bag))
                else:
                    records = [dataclasses.replace(base, meta={'axis': a}) for a in chosen]
                    calls = (functools.partial(write_axes, records, bag, storage=storage),
                             functools.partial(read_axes, bag))
                for what, func in (('write', calls[0]), ('read', calls[1])):
                    _, wall, cpu = _timed(func)
                    key = f'{storage}_{case}_{what}'
                    out[f'{key}_samples_per_s'] = len(base) / wall
                    out[f'{key}_samples_per_cpu_s'] = len(base) / cpu if cpu > 0 else 0.0
                if echo:
                    print(f'{storage:8s} {case:6s} write '
                          f'{out[f"{storage}_{case}_write_samples_per_s"]:>11,.0f} samples/s '
                          f'({out[f"{storage}_{case}_write_samples_per_cpu_s"]:>11,.0f} per '
                          f'CPU-s), read {out[f"{storage}_{case}_read_samples_per_s"]:>11,.0f} '
                          f'samples/s ({out[f"{storage}_{case}_read_samples_per_cpu_s"]:>11,.0f}'
                          ' per CPU-s)', flush=True)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark: ``python3 -m piezo_stage_ros.bench.axes_bags [S]``; 0, or 2."""
    duration = duration_argument(argv, 'axes bags benchmark')
    if duration is None:
        return 2
    print(f'multi-axis bags: {duration:g} s at 10 kHz (position, reference, command, true '
          'position; one message a sample and topic)')
    run_axes_bag_benchmark(duration)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
