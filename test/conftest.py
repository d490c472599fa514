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
Hypothesis profiles: the suite that gates a landing draws the same examples on every run.

``ci`` (the default) derandomizes every property test: its examples follow from the test alone,
so a clean checkout passes or fails as the last run did. ``random`` draws new examples on each
run, the search for counterexamples that ``make test-random`` runs on its own
(``HYPOTHESIS_PROFILE=random``). The test modules' own ``@settings`` inherit from the profile
loaded here: they set only what differs (``max_examples``, ``deadline``).
"""

import os

from hypothesis import settings

PROFILE_ENV = 'HYPOTHESIS_PROFILE'

settings.register_profile('ci', derandomize=True, database=None)
settings.register_profile('random', derandomize=False)
settings.load_profile(os.environ.get(PROFILE_ENV, 'ci'))
