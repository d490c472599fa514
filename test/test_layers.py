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
The layers go one way: core/ never needs rclpy, rosbags or matplotlib; analysis/ never rclpy.

Inside core/ the folders stack the same way: each imports only the folders below it.
"""

import ast
from pathlib import Path
import subprocess
import sys
import textwrap

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / 'piezo_stage_ros'
CORE_FORBIDDEN = ('rclpy', 'rosbags', 'matplotlib')
ANALYSIS_FORBIDDEN = ('rclpy',)


def _modules(folder):
    return sorted(p for p in (PACKAGE / folder).rglob('*.py'))


def _dotted(path):
    """'model.stage' for core/model/stage.py: the name below piezo_stage_ros.core."""
    return '.'.join(path.relative_to(PACKAGE / 'core').with_suffix('').parts)


def _imported_modules(path):
    """Dotted names of every import in a file, wherever it is (functions, importlib calls)."""
    tree = ast.parse(path.read_text(encoding='utf8'), filename=str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            # 'from piezo_stage_ros.core import loop' imports the folder loop
            names.update(f'{node.module}.{alias.name}' for alias in node.names)
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
              and node.func.attr == 'import_module' and node.args
              and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            names.add(node.args[0].value)
    return names


def _imported_roots(path):
    """Top-level names of every import in a file, wherever it is (functions included)."""
    return {name.split('.')[0] for name in _imported_modules(path)}


#: core/'s folders from the bottom up: a folder may import its own and those before it.
CORE_STACK = ('contracts', 'signals', 'model', 'control', 'loop', 'identification', 'config')


def _floor(dotted):
    """
    Height of a module of the package in the stack, None for a module outside the package.

    A core folder's index in CORE_STACK; a module of the package outside core/ (analysis,
    nodes, the commands) stands above every core folder.
    """
    parts = dotted.split('.')
    if parts[0] != 'piezo_stage_ros' or len(parts) < 2:
        return None
    if parts[1] != 'core':
        return len(CORE_STACK)
    if len(parts) < 3:
        return None
    return CORE_STACK.index(parts[2]) if parts[2] in CORE_STACK else len(CORE_STACK)


def _imports_above(path, folder):
    """The folders above core/<folder> a file imports ('piezo_stage_ros.core.loop'), sorted."""
    own = CORE_STACK.index(folder)
    return sorted({'.'.join(name.split('.')[:3 if name.split('.')[1] == 'core' else 2])
                   for name in _imported_modules(path) if (_floor(name) or 0) > own})


def _core_folder_modules():
    return [p for p in _modules('core') if len(p.relative_to(PACKAGE / 'core').parts) > 1]


def test_there_is_a_core_to_check():
    names = {_dotted(p) for p in _modules('core')}
    assert {'contracts.errors', 'contracts.params', 'loop.record', 'model.stage'} <= names


@pytest.mark.parametrize('path', _modules('core'), ids=_dotted)
def test_core_source_never_imports_ros_bags_or_plots(path):
    assert not _imported_roots(path) & set(CORE_FORBIDDEN)


@pytest.mark.parametrize('path', _modules('analysis'), ids=lambda p: p.name)
def test_analysis_source_never_imports_rclpy(path):
    assert not _imported_roots(path) & set(ANALYSIS_FORBIDDEN)


def test_the_static_check_can_fail(tmp_path):
    # The checker must see imports hidden in functions and importlib calls.
    bad = tmp_path / 'bad.py'
    bad.write_text(textwrap.dedent("""
        import importlib
        def later():
            from rosbags.rosbag2 import Reader
            return importlib.import_module('matplotlib.pyplot'), Reader
    """))
    assert _imported_roots(bad) >= {'rosbags', 'matplotlib'}


def test_every_core_folder_has_its_floor():
    folders = {p.relative_to(PACKAGE / 'core').parts[0] for p in _core_folder_modules()}
    assert folders == set(CORE_STACK)
    loose = [p.name for p in (PACKAGE / 'core').glob('*.py') if p.name != '__init__.py']
    assert not loose, f'core/ modules outside a folder have no floor: {loose}'
    assert not _imports_above(PACKAGE / 'core' / '__init__.py', 'contracts')


@pytest.mark.parametrize('path', _core_folder_modules(), ids=_dotted)
def test_core_folders_import_only_the_floors_below(path):
    folder = path.relative_to(PACKAGE / 'core').parts[0]
    assert not _imports_above(path, folder), (
        f'core/{folder} sits below {_imports_above(path, folder)} (stack: {CORE_STACK})')


def test_the_stack_check_can_fail(tmp_path):
    # A model-floor file reaching up three ways, one hidden in a function, one through importlib:
    # the checker must see each, and nothing else.
    bad = tmp_path / 'bad.py'
    bad.write_text(textwrap.dedent("""
        import importlib
        from piezo_stage_ros.core import identification
        from piezo_stage_ros.core.contracts.errors import ParameterError
        from piezo_stage_ros.core.model.stage import StageParams
        def later():
            from piezo_stage_ros.core.loop.trajectories import make_trajectory
            return importlib.import_module('piezo_stage_ros.core.config.loader'), make_trajectory
    """))
    assert _imports_above(bad, 'model') == [
        'piezo_stage_ros.core.config', 'piezo_stage_ros.core.identification',
        'piezo_stage_ros.core.loop']
    assert _imports_above(bad, 'config') == []
    # the rest of the package stands above every core folder
    bad.write_text('from piezo_stage_ros.analysis import plots\n')
    assert _imports_above(bad, 'config') == ['piezo_stage_ros.analysis']


_BLOCKER = textwrap.dedent("""
    import importlib, importlib.abc, pkgutil, sys

    FORBIDDEN = {forbidden!r}

    class Blocker(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split('.')[0] in FORBIDDEN:
                raise ImportError(f'{{name}} is blocked: core/ must not need it')
            return None

    for name in list(sys.modules):
        if name.split('.')[0] in FORBIDDEN:
            del sys.modules[name]
    sys.meta_path.insert(0, Blocker())

    import piezo_stage_ros.core as core
    loaded = []
    for info in pkgutil.walk_packages(core.__path__, 'piezo_stage_ros.core.'):
        importlib.import_module(info.name)
        if not info.ispkg:
            loaded.append(info.name.removeprefix('piezo_stage_ros.core.'))
    leaked = sorted(n for n in sys.modules if n.split('.')[0] in FORBIDDEN)
    assert not leaked, leaked
    print(' '.join(sorted(loaded)))
""")


def test_core_imports_with_ros_bags_and_plots_unimportable():
    code = _BLOCKER.format(forbidden=set(CORE_FORBIDDEN))
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=120, cwd=PACKAGE.parent)
    assert proc.returncode == 0, proc.stderr
    loaded = set(proc.stdout.split())
    assert loaded == {_dotted(p) for p in _modules('core') if p.stem != '__init__'}


def test_the_blocker_really_blocks():
    # Same harness, one forbidden import on purpose: it must fail, or the test above proves
    # nothing.
    code = _BLOCKER.format(forbidden=set(CORE_FORBIDDEN)) + '\nimport rosbags.rosbag2\n'
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=120, cwd=PACKAGE.parent)
    assert proc.returncode != 0
    assert 'rosbags.rosbag2 is blocked' in proc.stderr or 'rosbags is blocked' in proc.stderr
