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
A sample clock that holds a fixed period in plain Python, and the statistics of its lateness.

:class:`Pacer` owns the schedule: sample k is due at t_0 + k T. It sleeps while the due time is
far (more than ``spin_ns``, 200 us by default: ``time.sleep`` wakes up to ~100 us late on Linux)
and spins on the clock for the rest, so a sample is taken within microseconds of its due time.
Each sample's lateness (actual minus due) goes into :class:`LatenessStats`. After a stall longer
than one period (a descheduled process, a page fault, a debugger), the samples whose time has
passed are *skipped*, counted, and the schedule moves on by whole periods: never a burst of
catch-up samples, which a real amplifier would see as a glitch in the zero-order hold.

The clock and the sleep are injected (``clock() -> ns`` of a monotonic clock, ``sleep(s)``), so
the schedule, the skipping and the statistics are tested without wall time; the defaults are
:func:`time.monotonic_ns` and :func:`time.sleep`.

:func:`realtime_setup` applies the options of a real-time thread or process (CPU affinity,
``SCHED_FIFO`` priority, the interpreter's switch interval) where the OS permits, and returns
what it applied and what it was refused, so that the caller can report it.
"""

from __future__ import annotations

import os
import sys
import time
from typing import Any, Callable, Sequence

from piezo_stage_ros.core.config.nodes import ServoParams
from piezo_stage_ros.core.contracts.errors import ParameterError

__all__ = ['LatenessStats', 'Pacer', 'realtime_setup', 'rt_throttling', 'servo_setup']

NS_PER_US = 1000


class LatenessStats:
    """
    Lateness of every sample of a paced loop, in a histogram of 1 us bins.

    Parameters
    ----------
    period_ns : int
        The sample period [ns]; a sample later than half of it counts as ``late_half``.
    max_us : int
        Lateness beyond this [us] goes into the last bin (the maximum is kept exactly).

    Notes
    -----
    A histogram keeps the cost per sample constant (one list index) and the memory bounded
    for endless runs; percentiles are exact to the bin width (1 us), the maximum exactly.

    """

    def __init__(self, period_ns: int, max_us: int = 100_000) -> None:
        self.period_ns = int(period_ns)
        self._half = self.period_ns // 2
        self._bins = [0] * (int(max_us) + 1)
        self._top = int(max_us)
        self.samples = 0
        self.late_half = 0
        self.skipped = 0
        self.max_ns = 0

    def add(self, lateness_ns: int) -> None:
        """Record the lateness [ns] of one sample (negative: early, counted as 0)."""
        self.samples += 1
        if lateness_ns > self.max_ns:
            self.max_ns = lateness_ns
        if lateness_ns > self._half:
            self.late_half += 1
        b = lateness_ns // NS_PER_US
        self._bins[b if 0 <= b < self._top else (0 if b < 0 else self._top)] += 1

    def remove(self, lateness_ns: int) -> None:
        """Undo :meth:`add` of a sample that was not taken after all (the maximum stays)."""
        self.samples -= 1
        if lateness_ns > self._half:
            self.late_half -= 1
        b = lateness_ns // NS_PER_US
        self._bins[b if 0 <= b < self._top else (0 if b < 0 else self._top)] -= 1

    def skip(self, count: int) -> None:
        """Record ``count`` samples skipped after a stall."""
        self.skipped += count

    def percentile_us(self, q: float) -> float:
        """
        Return the ``q``-th percentile (``q`` in [0, 100]) of the lateness [us].

        The upper edge of the bin holding it (the maximum for the top bin), 0 with no sample.
        """
        if not 0.0 <= q <= 100.0:
            raise ParameterError('q', q, '[0, 100]')
        if self.samples == 0:
            return 0.0
        rank = max(1, -(-int(q * self.samples) // 100))  # ceil(q n / 100), at least 1
        seen = 0
        for b, count in enumerate(self._bins):
            seen += count
            if seen >= rank:
                # the top bin holds everything beyond the histogram: its edge is the maximum
                return self.max_ns / NS_PER_US if b == self._top else \
                    min(float(b + 1), self.max_ns / NS_PER_US)
        return self.max_ns / NS_PER_US

    def summary(self) -> dict[str, Any]:
        """
        Return samples, p50/p99/max lateness [us], samples late > T/2, skipped samples.

        All three lateness figures are rounded alike (0.1 us): the p99 of a top bin is the
        maximum, and rounding only one of them could put it above the maximum.
        """
        return {'paced_samples': self.samples,
                'lateness_p50_us': round(self.percentile_us(50.0), 1),
                'lateness_p99_us': round(self.percentile_us(99.0), 1),
                'lateness_max_us': round(self.max_ns / NS_PER_US, 1),
                'late_half_period': self.late_half, 'skipped': self.skipped}


class Pacer:
    """
    A fixed-period schedule: sample k is due at t_0 + k T; :meth:`wait` returns at each one.

    Parameters
    ----------
    period_ns : int
        Sample period T [ns], > 0.
    clock : callable, optional
        Monotonic clock in nanoseconds; default :func:`time.monotonic_ns`.
    sleep : callable, optional
        ``sleep(seconds)``; default :func:`time.sleep`.
    spin_ns : int
        Sleep only while the due time is further than this [ns]; spin closer to it.
    stats : LatenessStats, optional
        Where the lateness goes; default a new one for ``period_ns``.

    """

    def __init__(self, period_ns: int, *, clock: Callable[[], int] = time.monotonic_ns,
                 sleep: Callable[[float], None] = time.sleep, spin_ns: int = 200_000,
                 stats: LatenessStats | None = None) -> None:
        if not period_ns > 0:
            raise ParameterError('period_ns', period_ns, '(0, inf)')
        self.period_ns = int(period_ns)
        self.clock = clock
        self.sleep = sleep
        self.spin_ns = int(spin_ns)
        self.stats = stats if stats is not None else LatenessStats(self.period_ns)
        self.t0_ns = 0
        self.index = -1

    def start(self, now_ns: int | None = None) -> int:
        """Make sample 0 due at ``now_ns`` (default: now; the next :meth:`wait` returns it)."""
        self.t0_ns = self.clock() if now_ns is None else int(now_ns)
        self.index = -1
        return self.t0_ns

    def due_ns(self, index: int) -> int:
        """Return the due time [ns] of sample ``index``."""
        return self.t0_ns + index * self.period_ns

    def wait(self, poll: Callable[[], None] | None = None) -> tuple[int, int]:
        """
        Wait for the next sample's due time and return ``(index, lateness_ns)``.

        If the next sample is already overdue by a whole period or more, the samples whose
        time has passed are skipped (counted in ``stats.skipped``) and the one due latest is
        returned with its lateness (less than a period): the index says which sample of the
        grid this is, so stamps stay on the grid. ``poll``, if given, is called over and over
        while the wait spins (work that can be done before the due time; keep each call
        short), never while it sleeps.
        """
        index = self.index + 1
        due = self.t0_ns + index * self.period_ns
        now = self.clock()
        while now < due:
            ahead = due - now
            if ahead > self.spin_ns:
                self.sleep((ahead - self.spin_ns) / 1e9)
            elif poll is not None:
                poll()
            now = self.clock()
        if now - due >= self.period_ns:
            # a stall (here or in a sleep that overshot): no burst, move on by whole periods
            skip = (now - due) // self.period_ns
            self.stats.skip(skip)
            index += skip
            due += skip * self.period_ns
        self.index = index
        lateness = now - due
        self.stats.add(lateness)
        return index, lateness


def realtime_setup(*, cpus: Sequence[int] = (), fifo_priority: int = 0,
                   switch_interval_s: float = 0.0, nice: int | None = None) -> dict[str, str]:
    """
    Apply real-time options to the calling thread/process where permitted.

    Parameters
    ----------
    cpus : sequence of int
        CPUs to run on (``os.sched_setaffinity`` of the calling thread); empty: unchanged.
    fifo_priority : int
        ``SCHED_FIFO`` priority (1..99) of the calling thread; 0: unchanged.
    switch_interval_s : float
        The interpreter's switch interval (:func:`sys.setswitchinterval`, process-wide): how
        long a thread holding the GIL runs before it is asked to let another one in; 0:
        unchanged (CPython's default is 5 ms, long against a 100 us period).
    nice : int, optional
        Nice value (-20 .. 19) of the calling thread (``os.setpriority``; on Linux a thread's
        own), for the default scheduler: at -20 the scheduler lets other work take only short
        slices of the CPU the loop spins on; None: unchanged. Lowering it needs
        ``CAP_SYS_NICE`` or an ``RLIMIT_NICE`` (``nice`` in ``/etc/security/limits.conf``).

    Returns
    -------
    dict
        Per option ``'applied ...'`` or ``'refused: <reason>'``; empty when nothing was asked.

    """
    out: dict[str, str] = {}
    if cpus:
        try:
            os.sched_setaffinity(0, set(int(c) for c in cpus))
            out['affinity'] = f'applied: CPUs {sorted(set(cpus))}'
        except (OSError, AttributeError, ValueError) as exc:
            out['affinity'] = f'refused: {exc}'
    if fifo_priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(fifo_priority)))
            out['sched_fifo'] = f'applied: priority {int(fifo_priority)}'
        except (OSError, AttributeError, ValueError) as exc:
            out['sched_fifo'] = f'refused: {exc}'
    if nice is not None:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, int(nice))
            out['nice'] = f'applied: {os.getpriority(os.PRIO_PROCESS, 0)}'
        except (OSError, AttributeError, ValueError) as exc:
            out['nice'] = f'refused: {exc} (needs CAP_SYS_NICE or RLIMIT_NICE)'
    if switch_interval_s > 0.0:
        sys.setswitchinterval(switch_interval_s)
        out['switch_interval'] = f'applied: {sys.getswitchinterval() * 1e6:g} us'
    return out


def rt_throttling() -> tuple[int, int] | None:
    """
    Return the kernel's real-time throttling ``(runtime_us, period_us)``, None when off.

    Linux lets ``SCHED_FIFO`` threads run ``sched_rt_runtime_us`` of every
    ``sched_rt_period_us`` (950 000 of 1 000 000 by default), then stops them for the rest:
    a FIFO loop that never sleeps stalls for 50 ms every second. None also where the files
    cannot be read (not Linux).
    """
    try:
        with open('/proc/sys/kernel/sched_rt_runtime_us', encoding='ascii') as stream:
            runtime = int(stream.read())
        with open('/proc/sys/kernel/sched_rt_period_us', encoding='ascii') as stream:
            period = int(stream.read())
    except (OSError, ValueError):
        return None
    return None if runtime < 0 else (runtime, period)


def servo_setup(opts: ServoParams, period_ns: int) -> dict[str, str]:
    """
    Apply the ``servo.*`` options to the calling thread (the servo loop's) and report them.

    :func:`realtime_setup` of ``cpu``, ``fifo_priority``, ``nice`` and
    ``switch_interval_us``; and a warning (key ``rt_throttling``) when ``SCHED_FIFO`` was
    applied to a loop that always spins (``spin_us`` at or above the period) on a kernel that
    throttles real-time threads: it would stall for the throttled part of every second.
    """
    out = realtime_setup(cpus=[opts.cpu] if opts.cpu >= 0 else [],
                         fifo_priority=opts.fifo_priority,
                         switch_interval_s=opts.switch_interval_us * 1e-6, nice=opts.nice)
    throttle = rt_throttling()
    if out.get('sched_fifo', '').startswith('applied') and \
            opts.spin_us * NS_PER_US >= period_ns and throttle is not None:
        runtime, period = throttle
        out['rt_throttling'] = (
            f'warning: SCHED_FIFO with servo.spin_us = {opts.spin_us:g} (>= the period, '
            f'{period_ns / NS_PER_US:g} us) never sleeps, and the kernel stops real-time '
            f'threads after {runtime} us of every {period} us (sched_rt_runtime_us): expect a '
            f'stall of {(period - runtime) / 1000:g} ms every {period / 1e6:g} s; set '
            'servo.spin_us below the period (30 sleeps most of it)')
    return out
