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

"""analyze on real-time bags: skipped samples leave holes in the time grid."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from piezo_stage_ros.analysis.bagwrite import write_run
from piezo_stage_ros.analysis.replay import analyze_bag, find_period
from piezo_stage_ros.core.control.controllers import ControllerParams
from piezo_stage_ros.core.loop.experiments import run_one
from piezo_stage_ros.core.loop.metrics import (
    error_metrics,
    grid_step,
    per_period_error,
    steady_state_start,
    summarize,
    window_slice,
)
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.loop.trajectories import TrajectoryParams
from piezo_stage_ros.core.model.stage import StageParams
import pytest

T = 1e-4


@pytest.fixture(scope='module')
def lockstep() -> RunRecord:
    """A lockstep run of the learning feed-forward on a 125 Hz triangle (80 samples a period)."""
    ctrl = ControllerParams().with_flat({'feedforward.mode': 'learning'})
    traj = TrajectoryParams.from_flat({'kind': 'triangle', 'triangle.frequency_hz': 125.0})
    return run_one(StageParams(), ctrl, traj, duration_s=0.4, diagnostics_every=1)


def skipped(n: int, seed: int = 3) -> np.ndarray:
    """The samples a stalled real-time loop skips: bursts after stalls and lone ones."""
    rng = np.random.default_rng(seed)
    gone = {k for k in (*range(1, 4), *range(n * 17 // 40, n * 17 // 40 + 5),
                        *range(n * 31 // 40, n * 31 // 40 + 2))}
    gone |= set(rng.choice(np.arange(5, n - 1), size=n // 100, replace=False).tolist())
    keep = np.ones(n, dtype=bool)
    keep[sorted(gone)] = False
    return keep


def as_recorded(record: RunRecord, keep: np.ndarray) -> RunRecord:
    """The bag of the nodes: the samples the loop took, no run description."""
    return RunRecord(record.time_s[keep], record.position_m[keep], record.reference_m[keep],
                     record.reference_velocity_mps[keep], record.command_v[keep],
                     {k: v[keep] for k, v in record.diagnostics.items()}, {},
                     None if record.true_position_m is None else record.true_position_m[keep])


def test_grid_step_and_holes() -> None:
    t = np.arange(1000) * T
    assert grid_step(t) == ((t[-1] - t[0]) / 999, 0)  # no holes: the mean, as ever
    keep = skipped(1000)
    step, missing = grid_step(t[keep])
    # each spacing is exact to the rounding of t (1e-16 of 0.1 s): the median is one step
    assert step == pytest.approx(T, rel=1e-9) and missing == int((~keep).sum())


@pytest.mark.parametrize('period_samples', [80, 125, 200])
def test_the_period_is_found_on_a_grid_with_holes(period_samples: int) -> None:
    n = 6000
    t = 1000.0 + np.arange(n) * T  # sim-time stamps, as a bag of the nodes has them
    u = np.mod(np.arange(n) / period_samples, 1.0)
    xd = 1e-6 * np.abs(2 * u - 1)
    keep = skipped(n)
    rec = RunRecord(t[keep] - t[keep][0], xd[keep], xd[keep], np.zeros(keep.sum()),
                    np.zeros(keep.sum()))
    period, why = find_period(rec)
    # lag * step: the step is a median of spacings, exact to 1e-16 t / T = 1e-9 relative
    assert why == '' and period == pytest.approx(period_samples * T, rel=1e-9)


def test_times_off_any_grid_are_said_not_guessed() -> None:
    rng = np.random.default_rng(5)
    n = 3000
    keep = skipped(n)
    t = (np.arange(n) * T + rng.uniform(-0.2, 0.2, n) * T)[keep]
    xd = np.sin(2 * np.pi * 100 * t)
    rec = RunRecord(t - t[0], xd, xd, np.zeros(t.size), np.zeros(t.size))
    period, why = find_period(rec)
    assert period is None and 'not on a uniform grid' in why


def test_a_real_time_bag_gives_its_lockstep_twins_window_and_figures(
        tmp_path: Path, lockstep: RunRecord) -> None:
    n = lockstep.time_s.size
    keep = skipped(n)
    write_run(as_recorded(lockstep, np.ones(n, dtype=bool)), tmp_path / 'lockstep')
    write_run(as_recorded(lockstep, keep), tmp_path / 'realtime')
    twin = analyze_bag(tmp_path / 'lockstep')
    real = analyze_bag(tmp_path / 'realtime')
    period = lockstep.meta['trajectory_period_s']
    # the same period and window as the run that knew its trajectory
    for a in (twin, real):
        assert a.record.meta['trajectory_period_s'] == pytest.approx(period, rel=1e-9)
    full = summarize(lockstep).as_dict()
    assert twin.metrics['steady_state_start_s'] == pytest.approx(
        full['steady_state_start_s'], abs=1e-12)
    assert real.metrics['steady_state_start_s'] == pytest.approx(
        full['steady_state_start_s'], abs=1e-12)
    assert real.metrics['duration_s'] == pytest.approx(full['duration_s'], rel=1e-9)
    # the figures: those of the twin's window over the samples present, exactly
    t = lockstep.time_s
    window = window_slice(t, steady_state_start(t, period), period)
    inside = np.zeros(n, dtype=bool)
    inside[window] = True
    err = lockstep.position_m - lockstep.reference_m
    e_max, e_rms = error_metrics(err[inside & keep])
    assert real.metrics['steady_state_samples'] == int((inside & keep).sum())
    assert real.metrics['e_max_m'] == pytest.approx(e_max, rel=1e-12)
    assert real.metrics['e_rms_m'] == pytest.approx(e_rms, rel=1e-12)
    assert real.metrics['e_max_m'] <= twin.metrics['e_max_m']
    # the learning curve: every whole period, each over its samples present
    assert real.metrics['whole_periods_count'] == twin.metrics['whole_periods_count'] == 50
    rows = per_period_error(lockstep, period)
    last = np.flatnonzero((t >= rows.start_s[-1] - T / 2) & keep)
    assert real.metrics['period_e_rms_last_m'] == pytest.approx(
        error_metrics(err[last])[1], rel=1e-12)
    assert real.metrics['periods_learned_count'] == twin.metrics['periods_learned_count']
    # said, not silent
    missing = int((~keep).sum())
    assert any(f'{missing} samples missing from the time grid' in note for note in real.notes)
    assert any('found from the samples' in note for note in real.notes)
    assert not any('missing from the time grid' in note for note in twin.notes)


def test_no_period_is_said_in_the_notes(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    n = 4000
    t = np.arange(n) * T
    xd = np.cumsum(rng.normal(0.0, 1e-9, n))  # a random walk: no period
    write_run(RunRecord(t, xd, xd, np.zeros(n), np.zeros(n)), tmp_path / 'walk')
    analysis = analyze_bag(tmp_path / 'walk')
    assert any('no reference period found' in note and 'whole run' in note
               for note in analysis.notes)
    assert analysis.metrics['steady_state_start_s'] == 0.0
