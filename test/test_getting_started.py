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
The getting-started page's commands run as written, without ROS.

The first ``sh`` block after the heading "The session" is run line by line, in order, in a
scratch folder that sees the repository's ``config/``: each line must name one of the package's
console scripts (setup.py), which runs as ``python -m`` of its module and must exit 0. The page
itself says that this test runs the block, so a command that changes its options or its
defaults fails here, not in a reader's terminal. The timeout only stops a hung command; the test
asserts nothing about speed.
"""

from pathlib import Path
import re
import shlex
import subprocess
import sys

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / 'docs' / 'getting-started.md'
SCRIPT = re.compile(r"'(\w+) = (piezo_stage_ros[\w.]*):main'")
HANG_S = 600.0


def console_scripts() -> dict[str, str]:
    """Return the console scripts of setup.py: name -> module."""
    return dict(SCRIPT.findall((ROOT / 'setup.py').read_text(encoding='utf-8')))


def session_commands(text: str) -> list[str]:
    """Return the command lines of the page's session block (comments and blanks dropped)."""
    section = text.split('\n## The session\n', 1)[1]
    block = re.search(r'```sh\n(.*?)```', section, re.DOTALL)
    assert block, 'no sh block under "The session"'
    lines = [line.split('#', 1)[0].strip() for line in block.group(1).splitlines()]
    return [line for line in lines if line]


def test_the_session_block_is_found_and_names_only_console_scripts():
    commands = session_commands(PAGE.read_text(encoding='utf-8'))
    scripts = console_scripts()
    assert len(commands) >= 5
    unknown = [c for c in commands if shlex.split(c)[0] not in scripts]
    assert not unknown, f'not a console script of the package: {unknown}'


@pytest.mark.slow
def test_the_getting_started_session_runs_as_written(tmp_path: Path):
    (tmp_path / 'config').symlink_to(ROOT / 'config', target_is_directory=True)
    scripts = console_scripts()
    for command in session_commands(PAGE.read_text(encoding='utf-8')):
        name, *args = shlex.split(command)
        done = subprocess.run([sys.executable, '-m', scripts[name], *args], cwd=tmp_path,
                              capture_output=True, text=True, timeout=HANG_S)
        assert done.returncode == 0, f'{command}: exit {done.returncode}: {done.stderr[-2000:]}'
    # what the last steps read and wrote is there
    assert (tmp_path / 'runs' / 'stage.yaml').is_file()
    assert (tmp_path / 'runs' / 'ms_report' / 'report.md').is_file()
