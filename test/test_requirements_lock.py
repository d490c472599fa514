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
The lock files agree with the requirements they were resolved from.

`make venv` and `make test` install the locks as they are (``pip install --no-deps`` then
``pip check``), so a requirement edited without `make lock` would silently not be installed. This
check fails instead: every requirement is in its lock, the locked version satisfies its specifier,
and every lock line is an exact ``name==version`` pin. It reads files only, so it gives the same
answer in every environment (and where ``packaging`` is missing it skips).
"""

from pathlib import Path

import pytest

packaging_requirements = pytest.importorskip('packaging.requirements')
packaging_utils = pytest.importorskip('packaging.utils')

ROOT = Path(__file__).resolve().parent.parent

# (requirements file, the lock that must satisfy it). The Jazzy lock must also satisfy the runtime
# floor of requirements.txt: that is the claim that the code runs on the versions Jazzy ships.
PAIRS = [
    ('requirements-dev.txt', 'requirements-lock.txt'),
    ('requirements.txt', 'requirements-lock.txt'),
    ('requirements-jazzy.txt', 'requirements-jazzy-lock.txt'),
    ('requirements.txt', 'requirements-jazzy-lock.txt'),
]


def _lines(text):
    for raw in text.splitlines():
        line = raw.split(' #', 1)[0].strip()
        if line and not line.startswith('#'):
            yield line


def read_requirements(path):
    """Requirements of a file and of the files it includes with ``-r``."""
    requirements = []
    for line in _lines(path.read_text()):
        if line.startswith(('-r ', '--requirement ')):
            requirements += read_requirements(path.parent / line.split(None, 1)[1])
        elif line.startswith('-'):
            raise ValueError(f'{path.name}: option {line!r} is not understood by this check')
        else:
            requirements.append(packaging_requirements.Requirement(line))
    return requirements


def parse_lock(text):
    """Map canonical name -> version; every line must be an exact, unconditional pin."""
    pins = {}
    for line in _lines(text):
        requirement = packaging_requirements.Requirement(line)
        specifiers = list(requirement.specifier)
        if requirement.marker or len(specifiers) != 1 or specifiers[0].operator != '==':
            raise ValueError(f'lock line {line!r} is not an exact pin name==version')
        name = packaging_utils.canonicalize_name(requirement.name)
        if name in pins:
            raise ValueError(f'lock pins {name} twice')
        pins[name] = specifiers[0].version
    return pins


def disagreements(requirements, pins):
    """Every way the requirements and the lock disagree, as sentences (empty: they agree)."""
    problems = []
    for requirement in requirements:
        if requirement.marker is not None:
            problems.append(f'{requirement}: environment markers are not supported by the lock')
            continue
        name = packaging_utils.canonicalize_name(requirement.name)
        if name not in pins:
            problems.append(f'{requirement}: {name} is not in the lock (run `make lock`)')
        elif not requirement.specifier.contains(pins[name], prereleases=True):
            problems.append(f'{requirement}: the lock has {name}=={pins[name]} (run `make lock`)')
    return problems


@pytest.mark.parametrize(('requirements_file', 'lock_file'), PAIRS)
def test_lock_satisfies_requirements(requirements_file, lock_file):
    requirements = read_requirements(ROOT / requirements_file)
    pins = parse_lock((ROOT / lock_file).read_text())
    assert requirements, f'{requirements_file} lists no requirement'
    assert disagreements(requirements, pins) == []


@pytest.mark.parametrize('lock_file', sorted({lock for _, lock in PAIRS}))
def test_lock_pins_the_installer_too(lock_file):
    # pip, setuptools (the editable install builds with it) and wheel come from the lock as well,
    # so a new machine does not get whatever pip is current that day.
    pins = parse_lock((ROOT / lock_file).read_text())
    assert {'pip', 'setuptools', 'wheel'} <= set(pins)


def test_check_finds_each_kind_of_disagreement():
    requirements = [packaging_requirements.Requirement(text)
                    for text in ('numpy>=2', 'scipy>=1.11', 'PyYAML==6.0.1', 'ruff')]
    pins = parse_lock('numpy==1.26.4\nscipy==1.11.4\npyyaml==6.0.3\n')
    problems = disagreements(requirements, pins)
    assert [problem.split(':')[0] for problem in problems] == ['numpy>=2', 'PyYAML==6.0.1', 'ruff']
    assert disagreements(requirements[1:2], pins) == []


@pytest.mark.parametrize('line', ['numpy>=1.26', 'numpy', 'numpy==1.26; python_version<"3.12"'])
def test_lock_rejects_lines_that_are_not_exact_pins(line):
    with pytest.raises(ValueError, match='not an exact pin'):
        parse_lock(line)
