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
What data support: refusals, closed-loop identification, drift from operation bags.

Bags are made with the offline runner as ``test_identify.py`` makes them (no role, no true
parameters in the bag), on stages the package was not configured for.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
from piezo_stage_ros.analysis.bagwrite import write_run
from piezo_stage_ros.core.config.loader import find_config, load_config, LoopConfig
from piezo_stage_ros.core.identification.experiments import (
    ClosedLoopPlan,
    ExperimentPlan,
    run_closed_loop_experiment,
    run_experiments,
    run_tracking,
)
from piezo_stage_ros.core.identification.periodic import detect_period
from piezo_stage_ros.core.identification.support import identify_checked, loop_kind
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.model.family import member_params, StageVariation
from piezo_stage_ros.core.model.linear import factors_of
from piezo_stage_ros.core.model.stage import StageParams
from piezo_stage_ros.identify import main
import pytest

#: a stage unlike the configured one (the family of `robustness`), with sensor noise
FOREIGN = StageVariation('foreign', gain=1.2, omega_n=0.92, zeta=1.3, tau=1.2, alpha=0.8,
                         noise_m=2e-9)


def _bare(rec: RunRecord, name: str) -> RunRecord:
    """Return the run as a recorder would hold it: no role, no true stage, no period."""
    return RunRecord(rec.time_s, rec.position_m, rec.reference_m, rec.reference_velocity_mps,
                     rec.command_v, meta={'name': name})


def _bag(rec: RunRecord, path: Path) -> str:
    write_run(_bare(rec, path.name), path)
    return str(path)


@pytest.fixture(scope='module')
def loop() -> LoopConfig:
    return LoopConfig.from_config(load_config([find_config('default.yaml')]))


def _identify(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    status = main(argv)
    out = capsys.readouterr()
    return status, out.out, out.err


def _refused(err: str) -> list[str]:
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines and all(line.startswith('identify: error: ') for line in lines), err
    assert 'Traceback' not in err
    return [line[len('identify: error: '):] for line in lines]


def test_tracking_bag_forced_as_frequency_run_is_refused(
        tmp_path: Path, loop: LoopConfig, capsys: pytest.CaptureFixture[str]) -> None:
    # main (4ad0954) wrote omega_n = 3430 rad/s (truth 18221) from such a bag, exit status 0
    true = member_params(loop.stage, FOREIGN)
    bag = _bag(run_tracking(true, loop.controller, design_stage=loop.stage), tmp_path / 'track')
    out = tmp_path / 'id.yaml'
    status, _, err = _identify(['--noise', bag, '--output', str(out), '--report', 'none'], capsys)
    assert status == 1 and not out.exists()
    lines = _refused(err)
    by_name = {line.split(':')[0]: line for line in lines}
    assert set(by_name) >= {'omega_n', 'zeta', 'tau'}
    assert 'excites 1 line (100 Hz)' in by_name['omega_n']
    assert 'resonance near 3.' in by_name['omega_n']


def test_open_loop_sine_forced_as_frequency_run_is_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    runs = run_experiments(member_params(StageParams(), FOREIGN))
    sine, step = _bag(runs['sine'], tmp_path / 'sine'), _bag(runs['step'], tmp_path / 'step')
    out = tmp_path / 'id.yaml'
    status, _, err = _identify(['--noise', sine, '--step', step, '--output', str(out),
                                '--report', 'none'], capsys)
    assert status == 1 and not out.exists()
    (line,) = _refused(err)  # zeta and tau come from the step run: only omega_n is refused
    assert line.startswith('omega_n: the frequency run') and '1 line (100 Hz)' in line


def test_saturated_run_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    plan = ExperimentPlan(noise_offset_v=9.8, noise_rms_v=0.3)
    runs = run_experiments(member_params(StageParams(), FOREIGN), plan)
    noise, step = _bag(runs['noise'], tmp_path / 'noise'), _bag(runs['step'], tmp_path / 'step')
    out = tmp_path / 'id.yaml'
    status, _, err = _identify([noise, step, '--output', str(out), '--report', 'none'], capsys)
    assert status == 1 and not out.exists()
    (line,) = _refused(err)
    assert line.startswith('omega_n: run ') and 'saturated' in line
    assert 'outside the amplifier range' in line


def test_closed_loop_without_excitation_is_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # holding 5 um: the command only carries the sensor noise fed back
    rec = run_closed_loop_experiment(member_params(StageParams(), FOREIGN), ClosedLoopPlan(
        multisine_rms_m=0.0, slow_amplitude_m=0.0, duration_s=0.5))
    bag = _bag(rec, tmp_path / 'hold')
    out = tmp_path / 'id.yaml'
    status, _, err = _identify([bag, '--closed-loop', '--output', str(out), '--report', 'none'],
                               capsys)
    assert status == 1 and not out.exists()
    lines = _refused(err)
    assert lines[0].startswith('omega_n, zeta, tau') and 'no excitation on its reference' in \
        lines[0]


def test_open_loop_forced_as_closed_loop_is_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    runs = run_experiments(member_params(StageParams(), FOREIGN))
    noise = _bag(runs['noise'], tmp_path / 'noise')
    out = tmp_path / 'id.yaml'
    status, _, err = _identify(['--closed-loop', noise, '--output', str(out), '--report',
                                'none'], capsys)
    assert status == 1 and not out.exists()
    (line,) = _refused(err)
    assert line.startswith('closed loop: run ') and 'is open loop' in line


def test_loop_kind_and_period() -> None:
    stage = member_params(StageParams(), FOREIGN)
    runs = run_experiments(stage)
    chain = stage.chain
    for rec in runs.values():
        assert loop_kind(_bare(rec, 'x'), chain)[0] == 'open'
    closed = run_closed_loop_experiment(stage, ClosedLoopPlan(duration_s=0.5))
    kind, why = loop_kind(_bare(closed, 'x'), chain)
    assert kind == 'closed' and 'position noise' in why
    # 0.1 s multisine plus a 5 Hz sine at 10 kHz: 2000 samples
    assert detect_period(closed.reference_m) == 2000
    assert detect_period(np.sin(np.arange(1000) * 0.1234)) is None
    assert detect_period(np.full(100, 3.0)) is None


@pytest.fixture(scope='module')
def closed_loop_result() -> tuple[StageParams, object]:
    true = member_params(StageParams(), FOREIGN)
    rec = run_closed_loop_experiment(true, ClosedLoopPlan(duration_s=2.0))
    return true, identify_checked([_bare(rec, 'closed')], StageParams())


def test_closed_loop_identification_of_a_foreign_stage_and_controller(
        closed_loop_result: tuple[StageParams, object]) -> None:
    true, checked = closed_loop_result
    res = checked.result  # type: ignore[attr-defined]
    assert res.loop == 'closed'
    tf = factors_of(true.plant.third_order)
    bl = true.hysteresis.backlash_like
    s = res.summary()
    truth = {'static_gain_m_per_v': (tf.gain_m_per_v * bl.c, 0.02),
             'omega_n_rad_s': (tf.omega_n_rad_s, 0.02), 'tau_s': (tf.tau_s, 0.02),
             'zeta': (tf.zeta, 0.10), 'alpha': (bl.alpha, 0.10)}
    for name, (value, tol) in truth.items():
        assert s[name] == pytest.approx(value, rel=tol), name
        lo, hi = res.bounds[name]
        assert lo <= value <= hi, (name, lo, value, hi)
        # bounds that say something: narrower than the target tolerance
        assert (hi - lo) / 2.0 < tol * value, name
    assert any('closed loop' in w and 'H1' in w for w in checked.warnings)  # type: ignore


def test_closed_loop_cli_writes_file_with_bounds(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec = run_closed_loop_experiment(member_params(StageParams(), FOREIGN),
                                     ClosedLoopPlan(duration_s=1.0))
    bag = _bag(rec, tmp_path / 'cl')
    out = tmp_path / 'id.yaml'
    status, stdout, _ = _identify([bag, '--output', str(out), '--report', 'none'], capsys)
    assert status == 0 and out.exists()
    assert '95 % bounds:' in stdout and 'warning: run ' in stdout


def test_drift_from_an_operation_bag(tmp_path: Path, loop: LoopConfig,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    base = loop.stage
    changed = member_params(base, StageVariation('gain_up', gain=1.15, noise_m=2e-9))
    same = member_params(base, StageVariation('same', noise_m=2e-9))
    bags = [_bag(run_tracking(st, loop.controller, design_stage=base), tmp_path / name)
            for name, st in (('changed', changed), ('same', same))]
    status, out, _ = _identify(['--drift', bags[0], '--drift', bags[1]], capsys)
    assert status == 0
    gains = [line for line in out.splitlines() if line.startswith('DC gain')]
    assert 'CHANGED by +' in gains[0] and 'unchanged' in gains[1]
    true_gain = factors_of(changed.plant.third_order).gain_m_per_v * \
        changed.hysteresis.backlash_like.c
    estimate = float(gains[0].split('=')[1].split('m/V')[0])
    assert estimate == pytest.approx(true_gain, rel=0.02)
    # the change printed is the estimate's, within the same 2 % of the 1.15 ratio
    change = float(gains[0].split('CHANGED by ')[1].split('%')[0])
    assert change == pytest.approx(15.0, abs=2.0 * 1.15)
    assert not (tmp_path / 'identified.yaml').exists()
    with contextlib.redirect_stderr(io.StringIO()):
        assert main(['--drift', bags[0], '--step', bags[1]]) == 2


def test_replay_bounds_take_the_student_t_of_the_refits_that_came_back(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # Three of the eight refits come back: their spread has 2 degrees of freedom, and the
    # 95 % half-width is t_0.975(2) = 4.303 standard deviations, not the 2.365 of 7.
    from types import SimpleNamespace

    from piezo_stage_ros.core.identification import support
    from piezo_stage_ros.core.identification.fit import IdentificationError
    from scipy import stats
    values = iter([1.0, 1.3, 0.8])

    def refit(*_args: object, **_kwargs: object) -> SimpleNamespace:
        try:
            return SimpleNamespace(estimates={'alpha': next(values)})
        except StopIteration:
            raise IdentificationError('refit failed') from None

    monkeypatch.setattr(support, 'fit_hysteresis', refit)
    n = 32
    record = RunRecord(np.arange(n) * 1e-4, np.zeros(n), np.zeros(n), np.zeros(n),
                       np.zeros(n), meta={'name': 'sine'})
    hy = SimpleNamespace(model='backlash_like', models=[np.zeros(n)], records=[record],
                         residual_rms_m=1e-9, estimates={'alpha': 1.0})
    result = SimpleNamespace(hysteresis=hy, bounds={'alpha': (0.999, 1.001)}, factors=None)
    support._widen_by_replay(result, StageParams(), None)
    lo, hi = result.bounds['alpha']
    expected = float(stats.t.ppf(0.975, 2)) * float(np.std([1.0, 1.3, 0.8], ddof=1))
    assert 0.5 * (hi - lo) == pytest.approx(expected, rel=1e-12)
    assert 0.5 * (lo + hi) == pytest.approx(1.0, rel=1e-12)
