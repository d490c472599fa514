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

"""The README's parameter tables are the declarations, not a copy that drifts."""

from pathlib import Path

from piezo_stage_ros.nodes.tables import controller_table, plant_table, trajectory_table

README = Path(__file__).resolve().parents[1] / 'README.md'
BEGIN = '<!-- parameter tables: begin -->'
END = '<!-- parameter tables: end -->'


def generated() -> str:
    return '\n'.join(t.markdown() for t in (plant_table(), controller_table(), trajectory_table()))


def test_parameter_tables_are_current():
    text = README.read_text(encoding='utf-8')
    assert BEGIN in text and END in text
    block = text.split(BEGIN, 1)[1].split(END, 1)[0].strip()
    assert block == generated().strip(), (
        'README parameter tables are out of date: replace the block between the markers with '
        'the output of `python3 -m piezo_stage_ros.nodes.tables`')


def test_every_declared_parameter_is_in_the_readme():
    text = README.read_text(encoding='utf-8')
    for table in (plant_table(), controller_table(), trajectory_table()):
        for spec in table.specs():
            assert f'| `{spec.name}` |' in text, spec.name
