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

"""The controller_node section of the default config, and the parameter table of the docs."""

from pathlib import Path

from piezo_stage_ros.core.config import find_config, load_config
from piezo_stage_ros.core.controllers import ControllerParams
from piezo_stage_ros.core.stability import StabilityParams
from piezo_stage_ros.tune import controller_node_specs, params_table

DOCS = Path(__file__).resolve().parents[1] / 'docs' / 'controllers.md'


def _section():
    return load_config([find_config()]).node('controller_node')


def test_default_config_holds_every_controller_parameter_at_its_default():
    flat = _section()
    names = {s.name for s in controller_node_specs()}
    assert names <= set(flat)
    controller = ControllerParams.from_flat({k: v for k, v in flat.items()
                                             if not k.startswith('stability.')},
                                            strict=False)
    assert controller == ControllerParams()
    assert StabilityParams.from_flat(flat, prefix='stability.') == StabilityParams()


def test_parameter_table_lists_every_parameter_once():
    table = params_table(controller_node_specs()).splitlines()
    specs = controller_node_specs()
    assert len(table) == len(specs) + 2
    for spec, line in zip(specs, table[2:]):
        assert line.startswith(f'| `{spec.name}` |')


def test_docs_carry_the_current_parameter_table():
    assert params_table(controller_node_specs()) in DOCS.read_text()
