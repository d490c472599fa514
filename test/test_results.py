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
The results command writes only between its markers, and formats what the commands print.

The studies themselves are the commands' (``simulate``, ``benchmark``), tested elsewhere; here
the page's markers, the section replacement and the tables, on known inputs.
"""

from pathlib import Path

from piezo_stage_ros import results
from piezo_stage_ros.core.contracts.errors import PiezoStageError
import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_the_results_page_has_every_generated_section():
    text = (ROOT / 'docs' / 'results.md').read_text(encoding='utf-8')
    for study in results.STUDIES:
        begin, end = results.markers(study.name)
        assert text.count(begin) == 1 and text.count(end) == 1, study.name
        assert text.index(begin) < text.index(end), study.name


def test_a_section_is_replaced_and_nothing_else():
    begin, end = results.markers('x')
    text = f'head\n{begin}\nold\n{end}\ntail\n'
    assert results.replace_section(text, 'x', 'new') == f'head\n{begin}\nnew\n{end}\ntail\n'
    # twice gives the same page: the markers survive
    once = results.replace_section(text, 'x', 'new')
    assert results.replace_section(once, 'x', 'new') == once


@pytest.mark.parametrize('text', ['no markers', '<!-- results: x end -->\n'
                                  '<!-- results: x begin -->'])
def test_a_page_without_the_markers_is_refused(text: str):
    with pytest.raises(PiezoStageError, match="section 'x'"):
        results.replace_section(text, 'x', 'new')


def test_table3_rows_carry_the_readme_labels_and_the_figures():
    rows = [{'controller': c, 'plant': p, 'frequency_hz': f, 'e_rms_m': 1e-9 * (i + 1)}
            for i, (c, p, _) in enumerate(results.TABLE3_ROWS)
            for f in results.TABLE3_FREQUENCIES_HZ]
    table = results.table3_section({'experiments': [{'experiment': 'table3', 'rows': rows}]})
    lines = table.splitlines()
    assert lines[0] == '| e_rms [nm] | 1 Hz | 10 Hz | 50 Hz | 100 Hz |'
    assert '| paper RAC (experiment) | 4.4 | 5.6 | 17.6 | 39.4 |' in lines
    assert '| project RAC, reduced plant (25) | 1.0 | 1.0 | 1.0 | 1.0 |' in lines
    assert ('| project PI (paper gains) + notch, third-order plant (20) | 4.0 | 4.0 | 4.0 | 4.0 |'
            in lines)


def test_feedforward_rows_per_mode_and_frequency():
    runs = {(m, f): {'e_rms_m': 1e-9, 'e_max_m': 2e-9, 'e_rms_true_m': None}
            for m in results.FEEDFORWARD_MODES for f in (100.0, 200.0)}
    lines = results.feedforward_section(runs).splitlines()
    assert len(lines) == 2 + len(results.FEEDFORWARD_MODES)
    assert lines[2] == '| `none` | 1.00 / 2.00 | - | 1.00 / 2.00 | - |'


def test_the_machine_line_names_the_versions():
    import numpy
    line = results.machine()
    assert f'numpy {numpy.__version__}' in line and 'Python' in line and 'commit' in line


def test_scan_rows_take_their_figure_and_compare_it_with_the_target():
    line = results.ScanCase('line', ('--x',), 'line', 1e-9)
    base = results.ScanCase('base', ('--y',), 'true')
    against = results.ScanCase('against', ('--z',), 'true', against='base')
    runs = [
        # a line's figure is the larger of trace and retrace, of the true position
        (line, {'line_trace_e_rms_true_m': 0.5e-9, 'line_retrace_e_rms_true_m': 2e-9,
                'line_trace_e_rms_m': 0.1e-9, 'line_retrace_e_rms_m': 0.1e-9}),
        (base, {'e_rms_true_m': 3e-9, 'e_rms_m': 9e-9}),
        (against, {'e_rms_true_m': 3e-9, 'e_rms_m': 1e-9, 'ff_clipped_samples': 12.0}),
    ]
    lines = results.scan_section(runs).splitlines()
    assert lines[2] == '| line | 2.00 | <= 1.00 | **no** |'
    assert lines[3] == '| base | 3.00 | - | - |'
    # no worse than the row it names (equal passes); a run that clipped says so
    assert lines[4] == '| against (12 commands clipped, reported) | 3.00 | <= 3.00 | yes |'
    # without a true position, the measured one
    measured = {'line_trace_e_rms_m': 1e-9, 'line_retrace_e_rms_m': 0.5e-9}
    assert results.scan_figure(line, measured) == 1e-9


def test_every_scan_row_against_another_names_an_earlier_row():
    seen: set[str] = set()
    for case in results.SCAN_CASES:
        assert not case.against or case.against in seen, case.label
        assert case.figure in ('line', 'true', 'measured')
        seen.add(case.label)
