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
A learning feed-forward in bags and files: ``simulate --bag/--save-table``, the feed-forward
signal per sample, the learning curve and ``analyze --export-table``.
"""

from __future__ import annotations

import json

import numpy as np
from piezo_stage_ros import analyze, simulate
from piezo_stage_ros.analysis.bagread import read_run
from piezo_stage_ros.analysis.plots import first_update_period, plot_run
from piezo_stage_ros.analysis.replay import analyze_bag, learning_metrics
from piezo_stage_ros.core.config.loader import load_loop_config
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.control.feedforward import read_learned_table
from piezo_stage_ros.core.loop import closed_loop
from piezo_stage_ros.core.loop.metrics import per_period_error
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant, Stage
import pytest

LOOP = load_loop_config([])
N = 100  # samples of a 100 Hz period at 10 kHz


@pytest.fixture(scope='module')
def learning_bag(tmp_path_factory):
    out = tmp_path_factory.mktemp('learning')
    bag, table = out / 'bag', out / 'table.npz'
    status = simulate.main(['--feedforward', 'learning', '--duration', '0.1', '--bag', str(bag),
                            '--save-table', str(table), '--json'])
    assert status == 0
    return bag, table


def test_the_bag_holds_the_feedforward_every_sample(learning_bag) -> None:
    record = read_run(learning_bag[0])
    u_ff = record.diagnostics['ff_u_v']
    assert len(u_ff) == len(record) == 1000
    # the learning starts at the end of the second period (learning_start_periods = 1)
    assert np.all(u_ff[:2 * N] == 0.0) and np.all(u_ff[2 * N:] != 0.0)
    # recorded every sample, not held over blocks of diagnostics
    assert np.count_nonzero(np.diff(u_ff[2 * N:])) >= len(u_ff) - 2 * N - 2


def test_export_gives_the_table_simulate_saved(learning_bag, tmp_path, capsys) -> None:
    bag, saved = learning_bag
    out = tmp_path / 'exported.npz'
    assert analyze.main([str(bag), '--export-table', str(out), '-q']) == 0
    assert f'learned table written to {out}' in capsys.readouterr().err
    a, b = read_learned_table(out), read_learned_table(saved)
    assert np.array_equal(a.table_v, b.table_v) and np.array_equal(a.reference_m, b.reference_m)
    assert (a.design, a.periods_learned, a.period_rms_m) == (b.design, b.periods_learned,
                                                             b.period_rms_m)
    assert a.periods_learned == 9  # ten periods, the first not learned


def test_export_refuses_a_bag_without_a_table_and_several_bags(learning_bag, tmp_path,
                                                                capsys) -> None:
    plain = tmp_path / 'plain'
    assert simulate.main(['--duration', '0.02', '--bag', str(plain)]) == 0
    capsys.readouterr()
    assert analyze.main([str(plain), '--export-table', str(tmp_path / 't.npz'), '-q']) == 1
    assert 'holds no learned table' in capsys.readouterr().err
    assert not (tmp_path / 't.npz').exists()
    assert analyze.main([str(plain), str(learning_bag[0]), '--export-table',
                         str(tmp_path / 't.npz')]) == 2
    assert 'takes the table of one bag; 2 given' in capsys.readouterr().err


def test_the_learning_curve_of_the_bag(learning_bag, tmp_path) -> None:
    analysis = analyze_bag(learning_bag[0])
    rows = per_period_error(analysis.record, 0.01)
    m = analysis.metrics
    assert m['whole_periods_count'] == len(rows) == 10
    assert m['periods_learned_count'] == 9
    assert m['period_e_rms_first_m'] == rows.e_rms_m[0]
    assert m['period_e_rms_last_m'] == rows.e_rms_m[-1]
    assert m['period_e_rms_true_last_m'] == rows.e_rms_true_m[-1]
    assert m['period_e_rms_last_m'] < 0.2 * m['period_e_rms_first_m']  # it learned
    files = plot_run(analysis.record, tmp_path, title='bag')
    assert {'learning_curve', 'feedforward'} <= set(files)
    assert all(p.stat().st_size > 0 for p in files.values())


@pytest.mark.parametrize('every', [1, 10, 100])
def test_the_first_update_is_found_however_often_diagnostics_are_read(every: int) -> None:
    tp = TrajectoryParams.from_flat({**LOOP.trajectory.to_flat(), 'kind': 'sine'})
    for start in (1, 3):
        cp = ControllerParams.from_flat({**LOOP.controller.to_flat(),
                                         'feedforward.mode': 'learning',
                                         'feedforward.learning_start_periods': start})
        ctrl = build_controller(cp, 1e-4, linear_plant(LOOP.design_plant),
                                make_hysteresis(LOOP.stage.hysteresis))
        rec = closed_loop.run(Stage(LOOP.stage), ctrl, make_trajectory(tp), duration_s=0.06,
                              diagnostics_every=every)
        # the first update is at the end of period `start` (periods counted from 0)
        assert first_update_period(rec, 0.01) == start


def test_no_learning_figures_or_metrics_without_a_feedforward(tmp_path) -> None:
    plain = tmp_path / 'plain'
    assert simulate.main(['--duration', '0.03', '--bag', str(plain)]) == 0
    analysis = analyze_bag(plain)
    assert learning_metrics(analysis.record) == {}
    assert 'feedforward' not in plot_run(analysis.record, tmp_path / 'png')


@pytest.mark.parametrize('mode,checked', [('none', False), ('inverse', False),
                                          ('learning', True)])
def test_simulate_reports_the_learning_check(mode: str, checked: bool, capsys) -> None:
    assert simulate.main(['--feedforward', mode, '--duration', '0.02', '--json']) == 0
    out = json.loads(capsys.readouterr().out)
    assert ('learning_ratio_design' in out) == checked
    if checked:
        # the design model with the computational delay the check assumes (half a sample by
        # default), which the learning filter is designed without: contracting, but by less
        # than |1 - gamma|; the worst case is a member
        assert 0.5 < out['learning_ratio_design'] < 1.0
        assert out['learning_ratio_max'] >= out['learning_ratio_design']
        assert out['learning_worst_member'] is not None
        # without the delay the loop is the design model itself: exactly |1 - gamma|
        assert simulate.main(['--feedforward', mode, '--duration', '0.02', '--json', '--param',
                              'controller_node:stability.delay_samples=0.0']) == 0
        out = json.loads(capsys.readouterr().out)
        assert out['learning_ratio_design'] == pytest.approx(0.5, abs=1e-15)
