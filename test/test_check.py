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

"""The offline check-only command: the report of a parameter file, its JSON and exit status."""

import json
import math

from piezo_stage_ros import check
from piezo_stage_ros.core.control.controllers import ControllerParams
from piezo_stage_ros.core.control.stability import check_stability, StabilityParams
from piezo_stage_ros.core.model.stage import PlantParams
import pytest


def _json(capsys, argv):
    status = check.main([*argv, '--json'])
    return status, json.loads(capsys.readouterr().out)


def test_the_default_file_passes_and_the_report_names_what_it_checked(capsys):
    assert check.main([]) == 0
    out = capsys.readouterr().out
    for key in ('delay assumed', 'checked', 'verdict', 'worst case', 'margins', 'family',
                'adaptation', 'binding', 'proven', 'not proven'):
        assert f'\n{key} ' in '\n' + out, key
    assert '0.5 samples' in out and 'theta_hat in [1.05, 2]' in out
    assert '\ntime-varying ' in out
    # the same verdict and figures as the library's check on the same objects
    rep = check_stability(ControllerParams(), PlantParams(model='third_order'), 1e-4,
                          varying=True)
    status, data = _json(capsys, [])
    assert status == 0 and data['exit_status'] == 0
    assert data['varying']['found'] and data['varying']['vertices'] == 8
    assert data['stable_over_box'] and data['certified']
    assert data['spectral_radius'] == rep.spectral_radius
    assert data['gain_margin_db'] == rep.gain_margin_db
    assert data['delay_samples'] == 0.5 and data['box']['estimates'] == 'corners'
    assert data['scope'] == rep.scope()


def test_a_parameter_file_is_read_as_the_nodes_read_it(tmp_path, capsys):
    params = tmp_path / 'stage.yaml'
    params.write_text('controller_node:\n  ros__parameters:\n    stability:\n'
                      '      delay_samples: 1.0\n      estimates: initial\n', encoding='utf8')
    status, data = _json(capsys, [str(params), '--no-varying'])
    assert status == 0
    assert data['delay_samples'] == 1.0 and data['box']['estimates'] == 'initial'
    assert data['files'][-1] == str(params)
    assert 'initial estimates only' in data['scope'] and 'NOT checked' in data['scope']


def test_a_loop_the_delay_destabilises_exits_non_zero(capsys):
    # the previous, faster gains fail with one sample of delay at the box's corner
    fast = ['--param', 'controller_node:rac.lambda_per_s=3000', '--param',
            'controller_node:rac.epsilon_v=0.2', '--param', 'controller_node:rac.normalisation=20']
    assert check.main([*fast, '--delay-samples', '0', '--no-varying']) == 0
    capsys.readouterr()
    status, data = _json(capsys, [*fast, '--delay-samples', '1', '--no-varying'])
    assert status == check.EXIT_UNSTABLE
    assert not data['stable_over_box'] and data['spectral_radius'] > 1.0
    assert any(not f['stable'] for f in data['families'])


def test_an_adaptation_above_its_bound_has_its_own_status(capsys):
    paper_rates = ['--param', 'controller_node:rac.gamma=3000', '--param',
                   'controller_node:rac.eta=0.01', '--param',
                   'controller_node:rac.normalisation=0']
    status, data = _json(capsys, [*paper_rates, '--no-varying'])
    assert status == check.EXIT_ADAPTATION
    assert data['stable_over_box'] and not data['certified']
    assert not data['adaptation']['ok']


def test_a_bad_value_is_refused_with_status_one(capsys):
    assert check.main(['--delay-samples', '-1', '--no-varying']) == 1
    assert "'stability.delay_samples' = -1.0" in capsys.readouterr().err


@pytest.mark.parametrize('boundary', [0.0, 0.3, 2.37, 11.0])
def test_delay_margin_finds_the_first_loss_of_stability(boundary):
    def stable(d):
        return d < boundary
    found = check.delay_margin(stable)
    if boundary == 0.0:
        assert found == -math.inf
    elif boundary > 10.0:
        assert found == math.inf
    else:
        assert boundary - 0.01 <= found < boundary


def test_the_delay_margin_of_the_default_is_above_one_sample(capsys):
    status, data = _json(capsys, ['--delay-margin', '--no-varying'])
    assert status == 0
    margin = data['delay_margin_samples']
    assert margin > 1.0
    # just past it the frozen loops are unstable
    rep = check_stability(ControllerParams(), PlantParams(model='third_order'), 1e-4,
                          options=StabilityParams(delay_samples=margin + 0.01))
    assert not rep.stable
