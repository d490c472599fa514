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
The property tests that gate a landing are reproducible: each one runs derandomized.

test/conftest.py loads the ``ci`` profile unless ``HYPOTHESIS_PROFILE`` names another; a module
whose ``@settings`` turned ``derandomize`` off again would draw new examples on every run.
"""

import importlib
import os

from hypothesis import settings
import pytest

PROPERTY_MODULES = ['test_commands_ahead', 'test_controllers', 'test_feedforward', 'test_safety']

random_profile = pytest.mark.skipif(
    os.environ.get('HYPOTHESIS_PROFILE', 'ci') != 'ci',
    reason='another Hypothesis profile is loaded on purpose (make test-random)')


@random_profile
def test_the_default_profile_derandomizes():
    assert settings.default.derandomize


@random_profile
@pytest.mark.parametrize('name', PROPERTY_MODULES)
def test_every_property_test_is_derandomized(name: str):
    module = importlib.import_module(name)
    tests = {attr: getattr(module, attr) for attr in dir(module) if attr.startswith('test_')}
    props = {attr: fn._hypothesis_internal_use_settings for attr, fn in tests.items()
             if hasattr(fn, '_hypothesis_internal_use_settings')}
    assert props, f'{name}: no property test found (the list above is stale)'
    random = [attr for attr, s in props.items() if not s.derandomize]
    assert not random, f'{name}: draws new examples on each run: {random}'
