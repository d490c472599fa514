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

"""The ``identify`` command: real bags in, a parameter file the other programs accept out."""

from __future__ import annotations

from pathlib import Path
import re

import numpy as np
from piezo_stage_ros.analysis.bagwrite import write_run
from piezo_stage_ros.core.config.loader import load_config, LoopConfig
from piezo_stage_ros.core.identification.experiments import perturbed_stage, run_experiments
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.model.linear import factors_of
from piezo_stage_ros.core.model.stage import StageParams
from piezo_stage_ros.identify import main, parameter_file_text
from piezo_stage_ros.simulate import main as simulate_main
import pytest


@pytest.fixture(scope='module')
def bags(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Path], StageParams]:
    true, _ = perturbed_stage(5)
    true = true.replace(chain=true.chain.replace(sensor_noise_std_m=1.5e-9))
    out = tmp_path_factory.mktemp('bags')
    paths = {}
    for name, rec in run_experiments(true).items():
        # a bag as a recorder would hold it: no role, no true parameters
        bare = RunRecord(rec.time_s, rec.position_m, rec.reference_m,
                         rec.reference_velocity_mps, rec.command_v, meta={'name': name})
        write_run(bare, out / name)
        paths[name] = out / name
    return paths, true


@pytest.fixture(scope='module')
def identified(bags: tuple[dict[str, Path], StageParams],
               tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str]:
    paths, _ = bags
    out = tmp_path_factory.mktemp('out')
    yaml_path, report = out / 'stage.yaml', out / 'report'
    # the bags in any order: each is classified by its command signal
    argv = [str(paths['sine']), str(paths['noise']), str(paths['step']),
            '--output', str(yaml_path), '--report', str(report), '--pscm', '0', '40e-6']
    import contextlib
    import io
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(argv) == 0
    return yaml_path, report, buf.getvalue()


def test_parameter_file_is_what_the_nodes_and_simulate_read(
        bags: tuple[dict[str, Path], StageParams], identified: tuple[Path, Path, str]) -> None:
    _, true = bags
    yaml_path, _, _ = identified
    config = load_config([yaml_path])
    loop = LoopConfig.from_config(config)
    stage = loop.stage
    f, t = factors_of(stage.plant.third_order), factors_of(true.plant.third_order)
    assert stage.plant.model == 'third_order'
    assert f.omega_n_rad_s == pytest.approx(t.omega_n_rad_s, rel=0.02)
    assert f.tau_s == pytest.approx(t.tau_s, rel=0.02)
    assert f.zeta == pytest.approx(t.zeta, rel=0.10)
    bl, tb = stage.hysteresis.backlash_like, true.hysteresis.backlash_like
    # the default convention c = 1.0341: compare the identifiable products
    assert f.gain_m_per_v * bl.c == pytest.approx(t.gain_m_per_v * tb.c, rel=0.01)
    assert bl.alpha == pytest.approx(tb.alpha, rel=0.05)
    assert bl.b1 / bl.c == pytest.approx(tb.b1 / tb.c, rel=0.05)
    assert stage.plant.reduced == stage.plant.third_order.reduced()
    # the loop rate is not a property of the stage: the file leaves it to the loop's config
    assert 'sample_rate_hz' not in config.node('plant_node')
    ctrl_values = config.node('controller_node')
    assert loop.stability.slope_max == pytest.approx(bl.c)
    # the plant model is stated once, in plant_node: the controller designs on it
    assert not any(k.startswith('stability.plant.') for k in ctrl_values)
    assert loop.design_plant == stage.plant
    # eq. (15) from the two points of --pscm, for the plant's sensor and the controller
    assert stage.chain.sensor_gain_v_per_m == pytest.approx(10.0 / 40e-6)
    assert ctrl_values['sensor_gain_v_per_m'] == pytest.approx(10.0 / 40e-6)


def test_simulate_runs_with_the_identified_file(identified: tuple[Path, Path, str],
                                                capsys: pytest.CaptureFixture[str]) -> None:
    yaml_path, _, _ = identified
    assert simulate_main(['--config', str(yaml_path), '--duration', '0.02', '--json']) == 0
    assert 'e_rms' in capsys.readouterr().out


def test_report_has_the_three_figures(identified: tuple[Path, Path, str]) -> None:
    _, report, stdout = identified
    for name in ('frequency_response.png', 'step_response.png', 'hysteresis.png'):
        data = (report / name).read_bytes()
        assert data[:8] == b'\x89PNG\r\n\x1a\n' and len(data) > 10000
    text = (report / 'report.md').read_text(encoding='utf-8')
    assert '## Estimates and their standard deviations' in text
    assert re.search(r'frequency runs: `[^`]*noise`', text)
    assert re.search(r'hysteresis runs: `[^`]*sine`', text)
    assert 'static gain k_p c' in stdout and 'parameter file:' in stdout


def test_parameter_file_round_trip(tmp_path: Path) -> None:
    stage, _ = perturbed_stage(2)
    stage = stage.replace(seed=4, chain=stage.chain.replace(sensor_noise_std_m=1e-9))
    path = tmp_path / 'p.yaml'
    path.write_text(parameter_file_text(stage, header=['test']), encoding='utf-8')
    back = StageParams.from_flat(load_config([path]).node('plant_node'))
    assert back == stage


def test_simulate_option_prints_recovered_vs_true(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    argv = ['--simulate', str(tmp_path / 'bags'), '--perturb', '3', '--output',
            str(tmp_path / 'id.yaml'), '--report', 'none', '--sample-rate', '10000']
    assert main(argv) == 0
    out = capsys.readouterr().out
    rows = {line.split('|')[1].strip(): line for line in out.splitlines()
            if line.startswith('| ') and '%' in line}
    for name in ('w_n [rad/s]', 'tau [s]', 'zeta [-]', 'static gain k_p c [m/V]',
                 'alpha [1/V]', 'B1 [-]', 'c [-]'):
        err = float(rows[name].split('|')[4].strip().rstrip('%').strip())
        # c is the convention, so B1 and c carry the difference of the true c from 1.0341
        limit = {'zeta [-]': 10.0, 'static gain k_p c [m/V]': 1.0}.get(name, 2.0)
        if name in ('B1 [-]', 'c [-]'):
            limit = 40.0
        assert abs(err) < limit, rows[name]
    assert (tmp_path / 'bags' / 'noise').is_dir()
    # bags exist now: a second run needs --overwrite
    assert main(argv) == 1
    assert 'exists' in capsys.readouterr().err


def _one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert 'Traceback' not in err
    return lines[0]


def test_bad_input_gives_one_line_and_a_status(tmp_path: Path,
                                               bags: tuple[dict[str, Path], StageParams],
                                               capsys: pytest.CaptureFixture[str]) -> None:
    paths, _ = bags
    assert main([str(tmp_path / 'nope')]) == 1
    assert 'does not exist' in _one_line(capsys.readouterr().err)
    assert main([]) == 2
    assert 'no bag given' in _one_line(capsys.readouterr().err)
    assert main(['--perturb', '3', str(paths['step'])]) == 2
    assert '--perturb needs --simulate' in _one_line(capsys.readouterr().err)
    assert main(['--sine', str(paths['sine']), '--output', str(tmp_path / 'x.yaml')]) == 1
    assert 'need a noise (or chirp) run or a step run' in _one_line(capsys.readouterr().err)
    n = 400
    flat = RunRecord(np.arange(n) * 5e-5, np.full(n, 3e-6), np.zeros(n), np.zeros(n),
                     np.full(n, 1.0))
    write_run(flat, tmp_path / 'flat')
    assert main([str(tmp_path / 'flat'), '--output', str(tmp_path / 'y.yaml')]) == 1
    assert 'the command never changes' in _one_line(capsys.readouterr().err)
    not_a_bag = tmp_path / 'empty'
    not_a_bag.mkdir()
    assert main([str(not_a_bag)]) == 1
    _one_line(capsys.readouterr().err)
    assert main(['--model', 'preisach', str(paths['step'])]) == 2
    _one_line(capsys.readouterr().err)


def test_report_without_a_sine_run_has_no_fig6(bags: tuple[dict[str, Path], StageParams],
                                               tmp_path: Path) -> None:
    from piezo_stage_ros.analysis.bagread import read_run
    from piezo_stage_ros.analysis.identification_report import write_report
    from piezo_stage_ros.core.identification.fit import identify
    paths, _ = bags
    result = identify([read_run(paths['noise']), read_run(paths['step'])])
    files = write_report(result, tmp_path / 'rep')
    assert [f.name for f in files] == ['frequency_response.png', 'step_response.png',
                                       'report.md']
    text = files[-1].read_text(encoding='utf-8')
    assert 'no sine run' in text and 'Recovered vs true' not in text
