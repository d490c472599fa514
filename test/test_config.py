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

"""ROS 2 parameter files map onto the parameter groups."""

from piezo_stage_ros.core.config.loader import find_config, flatten, load_config
from piezo_stage_ros.core.contracts.errors import ConfigError
from piezo_stage_ros.core.model.stage import StageParams
import pytest


def test_default_file_is_the_paper_stage():
    config = load_config([find_config('default.yaml')])
    assert StageParams.from_flat(config.node('plant_node')) == StageParams()


def test_later_files_override_and_wildcard_merges(tmp_path):
    first = tmp_path / 'a.yaml'
    first.write_text('/**:\n  ros__parameters:\n    sample_rate_hz: 20000.0\n'
                     'plant_node:\n  ros__parameters:\n    plant:\n      model: reduced\n')
    second = tmp_path / 'b.yaml'
    second.write_text('/stage/plant_node:\n  ros__parameters:\n    seed: 3\n'
                      '    plant: {reduced: {tau_s: 1e-4}}\n')
    config = load_config([find_config(), first, second])
    p = StageParams.from_flat(config.node('plant_node'))
    assert p.sample_rate_hz == 20000.0
    assert p.plant.model == 'reduced'
    assert p.seed == 3
    # ROS reads 1e-4 as a double; PyYAML alone would give the string '1e-4'
    assert p.plant.reduced.tau_s == 1e-4
    assert config.sources[-1] == second


def test_flatten_nests_with_dots():
    assert flatten({'a': {'b': 1, 'c': {'d': [1, 2]}}, 'e': 'x'}) == \
        {'a.b': 1, 'a.c.d': [1, 2], 'e': 'x'}


@pytest.mark.parametrize('text, pattern', [
    ('plant_node: [1, 2]\n', "section 'plant_node' must contain exactly 'ros__parameters:'"),
    ('plant_node:\n  parameters: {seed: 1}\n', "must contain exactly 'ros__parameters:'"),
    ('- 1\n- 2\n', 'expected a mapping of node names, got list'),
    ('plant_node: {ros__parameters: {a: [}\n', 'not valid YAML'),
])
def test_malformed_files_are_refused_with_the_file_name(tmp_path, text, pattern):
    path = tmp_path / 'bad.yaml'
    path.write_text(text)
    with pytest.raises(ConfigError, match=pattern) as info:
        load_config([path])
    assert str(path) in str(info.value)


def test_missing_files_are_named(tmp_path):
    with pytest.raises(ConfigError, match='nope.yaml: cannot read'):
        load_config([tmp_path / 'nope.yaml'])
    with pytest.raises(ConfigError, match="configuration 'nope.yaml' not found; looked in"):
        find_config('nope.yaml')
