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
The documentation holds no copy that drifts and no link that leads nowhere.

The parameter tables of docs/parameters.md are the declarations; every relative link of the
README and of docs/ (every folder of it) names a file (and a heading) that exists. The README is
a front page (at most 10 KB), no page passes 40 KB, and the guide carries no history: issue
numbers and dates belong to the results pages (docs/results*.md) and CHANGELOG.rst only.
"""

from pathlib import Path
import re

from piezo_stage_ros.nodes.tables import (
    axes_markdown,
    controller_table,
    plant_table,
    trajectory_table,
)
import pytest

ROOT = Path(__file__).resolve().parents[1]
PARAMETERS = ROOT / 'docs' / 'parameters.md'
PAGES = [ROOT / 'README.md', *sorted((ROOT / 'docs').rglob('*.md'))]
# the pages that may hold dated runs and name issues (results.md and its recorded pages)
HISTORY = {*(ROOT / 'docs').glob('results*.md'), ROOT / 'CHANGELOG.rst'}
README_MAX_BYTES = 10_000
PAGE_MAX_BYTES = 40_000
ISSUE = re.compile(r'\bissues?\s+#?\d+|(?<![\w&/#])#\d+\b', re.IGNORECASE)
DATE = re.compile(r'\b(19|20)\d\d-(0[1-9]|1[0-2])-(0[1-9]|[12]\d|3[01])\b')
BEGIN = '<!-- parameter tables: begin -->'
END = '<!-- parameter tables: end -->'

FENCE = re.compile(r'^(```|~~~).*?^\1', re.MULTILINE | re.DOTALL)
CODE = re.compile(r'`[^`\n]*`')
LINK = re.compile(r'\[[^\]]*\]\(([^)\s]+)\)')
HEADING = re.compile(r'^#{1,6}\s+(.*?)\s*#*\s*$', re.MULTILINE)


def generated() -> str:
    return '\n'.join([*(t.markdown() for t in (plant_table(), controller_table(),
                                                 trajectory_table())), axes_markdown()])


def test_parameter_tables_are_current():
    text = PARAMETERS.read_text(encoding='utf-8')
    assert BEGIN in text and END in text
    block = text.split(BEGIN, 1)[1].split(END, 1)[0].strip()
    assert block == generated().strip(), (
        'docs/parameters.md is out of date: replace the block between the markers with '
        'the output of `python3 -m piezo_stage_ros.nodes.tables`')


def test_every_declared_parameter_is_documented():
    text = PARAMETERS.read_text(encoding='utf-8')
    for table in (plant_table(), controller_table(), trajectory_table()):
        for spec in table.specs():
            assert f'| `{spec.name}` |' in text, spec.name


def _prose(text: str) -> str:
    """
    Return the text without fenced code blocks.

    Headings and links inside a code block are not Markdown (e.g. a shell comment).
    """
    return FENCE.sub('', text)


def anchors(path: Path) -> set[str]:
    """
    Return the anchors GitHub gives the headings of a Markdown file.

    Lower case, punctuation other than '-' and '_' dropped, spaces to '-'; a repeated heading
    gets '-1', '-2', ... appended.
    """
    seen: dict[str, int] = {}
    result = set()
    for heading in HEADING.findall(_prose(path.read_text(encoding='utf-8'))):
        slug = re.sub(r'[^\w\- ]', '', heading.strip().lower()).replace(' ', '-')
        count = seen.get(slug, 0)
        seen[slug] = count + 1
        result.add(slug if count == 0 else f'{slug}-{count}')
    return result


def links(path: Path) -> list[str]:
    """Return the relative link targets of a Markdown file (no URLs, no code)."""
    prose = CODE.sub('', _prose(path.read_text(encoding='utf-8')))
    return [t for t in LINK.findall(prose) if not re.match(r'[a-z][a-z0-9+.-]*:', t)]


def test_the_link_checker_sees_links_and_anchors(tmp_path):
    # The check below must be able to fail: a page with one good and two bad links.
    page = tmp_path / 'page.md'
    page.write_text('# A `b` c, d\n\n## A `b` c, d\n\n[x](page.md#a-b-c-d-1) [y](gone.md) '
                    '[z](#nothing) `[w](not-a-link.md)` [u](https://example.org)\n',
                    encoding='utf-8')
    assert anchors(page) == {'a-b-c-d', 'a-b-c-d-1'}
    assert links(page) == ['page.md#a-b-c-d-1', 'gone.md', '#nothing']


@pytest.mark.parametrize('page', PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_lead_somewhere(page: Path):
    broken = []
    for target in links(page):
        file_part, _, anchor = target.partition('#')
        dest = (page.parent / file_part).resolve() if file_part else page
        if not dest.exists():
            broken.append(f'{target}: no file {dest}')
        elif anchor and dest.suffix == '.md' and anchor not in anchors(dest):
            broken.append(f'{target}: no heading with anchor #{anchor} in {dest.name}')
    assert not broken, f'{page.name}: ' + '; '.join(broken)


def _section(text: str, title: str) -> str:
    start = text.index(f'\n## {title}\n')
    end = text.find('\n## ', start + 1)
    return text[start:] if end < 0 else text[start:end]


@pytest.mark.parametrize('section, least', [('Results beside the paper', 7), ('Speed', 4)])
def test_the_readme_headline_rows_are_copies_of_the_docs(section, least):
    # The README repeats the Table III and speed rows of docs/results.md, where `python -m
    # piezo_stage_ros.results` writes them with their command and machine; a rerun that moves a
    # figure makes this test name the copy left behind.
    readme = ROOT / 'README.md'
    docs_rows = set((ROOT / 'docs' / 'results.md').read_text(encoding='utf-8').splitlines())
    rows = [
        line for line in _section(readme.read_text(encoding='utf-8'), section).splitlines()
        if line.startswith('| ') and not line.startswith('| ---')]
    assert len(rows) >= least  # the header and the figures
    stale = [row for row in rows if row not in docs_rows]
    assert not stale, ('README rows not in docs/results.md (copy them from there): '
                       + '; '.join(stale))


def _id(page: Path) -> str:
    return str(page.relative_to(ROOT))


def test_the_readme_is_a_front_page():
    size = len((ROOT / 'README.md').read_bytes())
    assert size <= README_MAX_BYTES, f'README.md is {size} bytes; at most {README_MAX_BYTES}'


@pytest.mark.parametrize('page', PAGES, ids=_id)
def test_no_page_is_too_long(page: Path):
    size = len(page.read_bytes())
    assert size <= PAGE_MAX_BYTES, f'{_id(page)} is {size} bytes; at most {PAGE_MAX_BYTES}'


def test_the_history_checks_can_fail():
    assert ISSUE.search('as issue 17 asked') and ISSUE.search('fixed in #17')
    assert ISSUE.search('Issues 10 and 12')
    assert not ISSUE.search('[a](page.md#17-x) &#39; 3#4 `x`')
    assert DATE.search('run on 2026-11-25') and not DATE.search('version 2026-13-01')


@pytest.mark.parametrize('page', [p for p in PAGES if p not in HISTORY], ids=_id)
def test_no_history_outside_results_and_changelog(page: Path):
    found = [(n, m.group(0)) for n, line in enumerate(
        page.read_text(encoding='utf-8').splitlines(), 1)
        for pattern in (ISSUE, DATE) for m in pattern.finditer(line)]
    assert not found, (f'{_id(page)} names issues or dates (they belong in docs/results.md or '
                       f'CHANGELOG.rst): ' + '; '.join(f'line {n}: {t!r}' for n, t in found))


SCRIPT = re.compile(r"'(\w+) = (piezo_stage_ros[\w.]*):main'")
LAUNCH_ARGUMENT = re.compile(r"^    '(\w+)': \(", re.MULTILINE)


def test_every_command_and_executable_is_in_the_reference():
    # A console script is a command (reference/commands.md) or a node executable
    # (reference/ros-interface.md); a new one fails here until its page names it.
    scripts = SCRIPT.findall((ROOT / 'setup.py').read_text(encoding='utf-8'))
    commands = (ROOT / 'docs' / 'reference' / 'commands.md').read_text(encoding='utf-8')
    ros = (ROOT / 'docs' / 'reference' / 'ros-interface.md').read_text(encoding='utf-8')
    assert len(scripts) > 10
    missing = [name for name, module in scripts
               if f'## `{name}`' not in commands and f'| `{name}` |' not in ros]
    assert not missing, f'console scripts in no reference page: {missing}'


@pytest.mark.parametrize('launch', sorted((ROOT / 'launch').glob('*.launch.py')),
                         ids=lambda p: p.name)
def test_every_launch_argument_is_in_the_reference(launch: Path):
    names = LAUNCH_ARGUMENT.findall(launch.read_text(encoding='utf-8'))
    ros = (ROOT / 'docs' / 'reference' / 'ros-interface.md').read_text(encoding='utf-8')
    section = ros.split(f'### `{launch.name}`', 1)[1].split('\n### ', 1)[0]
    assert len(names) >= 5
    missing = [n for n in names if f'| `{n}` |' not in section]
    assert not missing, f'{launch.name}: arguments not in reference/ros-interface.md: {missing}'


def test_every_topic_of_the_wire_contract_is_in_the_reference_with_its_type():
    from piezo_stage_ros.core.contracts.wire import SIMULATION_TOPICS, TOPIC_TYPES
    ros = (ROOT / 'docs' / 'reference' / 'ros-interface.md').read_text(encoding='utf-8')
    bags = (ROOT / 'docs' / 'reference' / 'bags.md').read_text(encoding='utf-8')
    simulation = {f'stage/{leaf}' for leaf in SIMULATION_TOPICS}
    missing = []
    for topic, msgtype in TOPIC_TYPES.items():
        # a topic no node publishes (the simulation's true position) lives in the bag reference
        page, name = (bags, '/' + topic) if topic in simulation else (ros, topic)
        if not any(line.startswith(f'| `{name}`') and f'`{msgtype}`' in line
                   for line in page.splitlines()):
            missing.append(f'{topic} ({msgtype})')
    assert not missing, f'topics not in the reference with their type: {missing}'
