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

"""The controller_node section of the default config holds every parameter at its default."""

from piezo_stage_ros.core.config.loader import find_config, load_config
from piezo_stage_ros.core.control.controllers import ControllerParams
from piezo_stage_ros.core.control.stability import StabilityParams


def _section():
    return load_config([find_config()]).node('controller_node')


def test_default_config_holds_every_controller_parameter_at_its_default():
    flat = _section()
    names = {s.name for s in ControllerParams.specs() + StabilityParams.specs('stability.')}
    # the plant model is stated once, in plant_node; the controller's own design model
    # (stability.plant.*, used with stability.design_model: own) is not repeated here
    own = {n for n in names if n.startswith('stability.plant.')}
    assert own and not own & set(flat)
    assert names - own <= set(flat)
    assert flat['stability.design_model'] == 'plant'
    controller = ControllerParams.from_flat({k: v for k, v in flat.items()
                                             if not k.startswith('stability.')},
                                            strict=False)
    assert controller == ControllerParams()
    assert StabilityParams.from_flat(flat, prefix='stability.') == StabilityParams()
