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

"""Parameter groups validate themselves and name the offending parameter, value and range."""

import math

from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.model.hysteresis import BacklashLikeParams, PrandtlIshlinskiiParams
from piezo_stage_ros.core.model.linear import ThirdOrderParams
from piezo_stage_ros.core.model.stage import SignalChainParams, StageParams
import pytest


@pytest.mark.parametrize('flat, pattern', [
    ({'plant.third_order.a0': -1.0}, r"'plant\.third_order\.a0' = -1\.0 is out of range; "
                                     r'allowed: finite number in \(0, inf\)'),
    ({'plant.third_order.a0': math.nan}, r"'plant\.third_order\.a0' = nan is not finite"),
    ({'plant.third_order.a0': 'fast'}, r"'plant\.third_order\.a0' = 'fast' is not a number"),
    ({'plant.third_order.a0': True}, r"'plant\.third_order\.a0' = True is not a number"),
    ({'plant.model': 'fourth_order'}, r"'plant\.model' = 'fourth_order' is not a valid choice; "
                                      r"allowed: one of 'electromechanical'"),
    ({'chain.adc_bits': 16.5}, r"'chain\.adc_bits' = 16\.5 is not an integer"),
    ({'chain.adc_bits': 40}, r"'chain\.adc_bits' = 40 is out of range; allowed: finite integer "
                             r'in \[1, 32\]'),
    ({'chain.quantize': 1}, r"'chain\.quantize' = 1 is not a boolean"),
    ({'plant.thrid_order.a0': 1.0}, r"'plant\.thrid_order\.a0' = 1\.0 is not a parameter"),
    ({'initial_position_m': 40e-6}, r"'initial_position_m' = 4e-05 is out of range; allowed: "
                                    r'finite number in \[0, 3\.8e-05\]'),
    ({'chain.amplifier_min_v': 10.0, 'chain.amplifier_max_v': -2.0},
     r"'chain\.amplifier_max_v' = -2\.0 is not above the low end"),
    ({'hysteresis.backlash_like.b1': 1.2}, r"'hysteresis\.backlash_like\.b1' = 1\.2 must be "
                                           r'smaller than c'),
    ({'hysteresis.prandtl_ishlinskii.weights': [0.1]},
     r"'hysteresis\.prandtl_ishlinskii\.weights' = \[0\.1\] has the wrong length"),
    ({'plant.third_order.a2': 1e13},
     r"'plant\.third_order\.a2' = 10000000000000\.0 makes the third-order plant unstable"),
])
def test_bad_values_name_parameter_value_and_range(flat, pattern):
    with pytest.raises(ParameterError, match=pattern):
        StageParams.from_flat(flat)


def test_error_carries_structured_fields():
    with pytest.raises(ParameterError) as info:
        StageParams.from_flat({'chain.sensor_noise_std_m': -1e-9})
    assert info.value.name == 'chain.sensor_noise_std_m'
    assert info.value.value == -1e-9
    assert info.value.allowed == 'finite number in [0, inf)'


def test_ints_become_floats_and_lists_become_tuples():
    p = StageParams.from_flat({'plant.third_order.a0': 7582,
                               'hysteresis.prandtl_ishlinskii.thresholds_v': [1, 2, 3, 4, 5]})
    assert isinstance(p.plant.third_order.a0, float)
    assert p.hysteresis.prandtl_ishlinskii.thresholds_v == (1.0, 2.0, 3.0, 4.0, 5.0)


def test_flat_round_trip_and_prefix():
    p = StageParams().with_flat({'plant.model': 'reduced', 'seed': 7})
    assert StageParams.from_flat(p.to_flat()) == p
    prefixed = {'stage.' + k: v for k, v in p.to_flat().items()}
    assert StageParams.from_flat(prefixed, prefix='stage.') == p
    with pytest.raises(ParameterError, match=r"'stage\.seed' = -1"):
        StageParams.from_flat({'stage.seed': -1}, prefix='stage.')


def test_frozen_and_replace_validates():
    p = ThirdOrderParams()
    with pytest.raises(AttributeError):
        p.a0 = 1.0  # type: ignore[misc]
    with pytest.raises(ParameterError, match="'a1' = -5.0"):
        p.replace(a1=-5.0)


def test_specs_table_is_complete():
    specs = {s.name: s for s in StageParams.specs()}
    assert set(specs) == set(StageParams().to_flat())
    a1 = specs['plant.third_order.a1']
    assert (a1.type_name, a1.unit, a1.default, a1.low, a1.low_open) == \
        ('double', '1/s^2', 4.1e8, 0.0, True)
    assert specs['plant.model'].read_only
    assert specs['hysteresis.prandtl_ishlinskii.weights'].type_name == 'double_array'
    assert all(s.description for s in specs.values())


@pytest.mark.parametrize('group, name', [(BacklashLikeParams, 'alpha'),
                                         (SignalChainParams, 'sensor_gain_v_per_m'),
                                         (PrandtlIshlinskiiParams, 'thresholds_v')])
def test_open_lower_bound_refuses_zero(group, name):
    value = [0.0] * 5 if name == 'thresholds_v' else 0.0
    with pytest.raises(ParameterError, match=f"'{name}'"):
        group(**{name: value})
