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

"""Line metrics: the linear part of each line, trace and retrace, pixels; bags and plots."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from piezo_stage_ros.analysis.bagwrite import write_run
from piezo_stage_ros.analysis.replay import analyze_bag
from piezo_stage_ros.analyze import main as analyze_main
from piezo_stage_ros.core.contracts.errors import ParameterError, PiezoStageError
from piezo_stage_ros.core.loop.metrics import (
    line_metrics,
    line_profile,
    line_spec,
    LineOptions,
    LINES_KEY,
    summarize,
)
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
import pytest

T = 1e-4
# the error comes back as (x_d + e) - x_d: exact to the rounding of a position near 9 um
ROUND = 4 * float(np.spacing(9e-6))


def triangle_record(error_fn, *, f: float = 50.0, n: int = 4000, meta: dict | None = None
                    ) -> RunRecord:
    """A triangle 1 ... 9 um (200 samples a line at 50 Hz) with a given error(x_d, v)."""
    traj = make_trajectory(TrajectoryParams.from_flat(
        {'kind': 'triangle', 'triangle.offset_m': 5e-6, 'triangle.amplitude_m': 4e-6,
         'triangle.frequency_hz': f}))
    t = np.arange(n) * T
    x, v = traj.evaluate(t)
    e = error_fn(x, v)
    return RunRecord(t, x + e, x, v, np.zeros(n), {}, dict(meta or {}), None)


def exact_lines(speed: float = 4 * 4e-6 * 50.0) -> dict[str, float]:
    return {'low_m': 1e-6, 'high_m': 9e-6, 'speed_mps': speed}


def test_trace_and_retrace_are_measured_apart() -> None:
    rec = triangle_record(lambda x, v: np.where(v > 0, 1e-9, -2e-9))
    m = line_metrics(rec, slice(None))
    assert m.trace_e_rms_m == pytest.approx(1e-9, abs=ROUND)
    assert m.retrace_e_rms_m == pytest.approx(2e-9, abs=ROUND)
    assert m.trace_e_max_m == pytest.approx(1e-9, abs=ROUND)
    # a constant error is all mean: the line's shift, trace and retrace apart
    assert m.trace_e_mean_m == pytest.approx(1e-9, abs=ROUND)
    assert m.retrace_e_mean_m == pytest.approx(-2e-9, abs=ROUND)
    # every sample of a triangle is on its linear part: all of them counted, half each way
    assert m.trace_samples + m.retrace_samples == rec.time_s.size
    assert abs(m.trace_samples - m.retrace_samples) <= 2 * 4000 / 200


def test_the_middle_fraction_leaves_the_corners_out() -> None:
    # an error only within 10 % of the range of a corner: the middle 80 % sees none
    def corners(x: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.where(np.abs(x - 5e-6) > 0.8 * 4e-6 + 1e-12, 5e-9, 0.0)
    rec = triangle_record(corners, meta={LINES_KEY: exact_lines()})
    whole = line_metrics(rec, slice(None))
    middle = line_metrics(rec, slice(None), LineOptions(middle_fraction=0.8))
    assert whole.trace_e_max_m == pytest.approx(5e-9)
    assert middle.trace_e_max_m == 0.0 and middle.retrace_e_max_m == 0.0
    assert (middle.low_m, middle.high_m) == pytest.approx((1.8e-6, 8.2e-6), rel=1e-12)
    # the samples within the middle: 80 % of those of the whole linear part, to a sample a
    # line (20 lines, two ends each)
    assert abs(middle.trace_samples - 0.8 * whole.trace_samples) <= 2 * 20


def test_pixels_average_their_samples_exactly() -> None:
    # a piecewise-constant error, one value per pixel: each pixel's mean is that value
    pixels = 16
    width = 8e-6 / pixels

    def stepped(x: np.ndarray, v: np.ndarray) -> np.ndarray:
        index = np.clip(np.floor((x - 1e-6) / width), 0, pixels - 1)
        return (index - 7.5) * 1e-10 * np.where(v > 0, 1.0, -1.0)
    rec = triangle_record(stepped, meta={LINES_KEY: exact_lines()})
    m = line_metrics(rec, slice(None), LineOptions(pixels=pixels))
    values = (np.arange(pixels) - 7.5) * 1e-10
    profile = line_profile(rec, slice(None), LineOptions(pixels=pixels))
    whole_lines = np.isfinite(profile.trace_pixels_m).all(axis=1)
    np.testing.assert_allclose(profile.trace_pixels_m[whole_lines],
                               np.broadcast_to(values, (whole_lines.sum(), pixels)),
                               rtol=0, atol=ROUND)
    assert m.pixel_trace_e_max_m == pytest.approx(7.5e-10, abs=ROUND)
    assert m.pixel_retrace_e_max_m == pytest.approx(7.5e-10, abs=ROUND)
    # the window's partial lines hold every pixel they reach, each with its value
    assert m.pixel_trace_e_rms_m == pytest.approx(float(np.sqrt(np.mean(values ** 2))),
                                                  rel=0.02)


def test_more_pixels_than_samples_take_the_error_at_each_pixel_centre() -> None:
    # 100 samples a trace, 1000 pixels: the error, linear in x_d, interpolated at the centres
    pixels = 1000
    rec = triangle_record(lambda x, v: 1e-3 * (x - 1e-6), meta={LINES_KEY: exact_lines()})
    profile = line_profile(rec, slice(None), LineOptions(pixels=pixels))
    # the samples reach within one sample (80 nm, 10 pixels) of the corners: beyond them a
    # pixel takes the end sample's error; so do those beyond the window's cut of the first and
    # last lines
    for image in (profile.trace_pixels_m, profile.retrace_pixels_m):
        expected = np.broadcast_to(1e-3 * (profile.pixel_centre_m - 1e-6), image.shape)
        inside = np.zeros(image.shape, dtype=bool)
        inside[1:-1] = np.abs(profile.pixel_centre_m - 5e-6) < 4e-6 - 80e-9
        finite = np.isfinite(image)
        assert finite.any(axis=0).all()
        np.testing.assert_allclose(image[finite & inside], expected[finite & inside],
                                   rtol=0, atol=ROUND)
        assert np.all(np.abs(image[finite] - expected[finite]) <= 1e-3 * 80e-9 + ROUND)


def test_the_linear_part_found_from_the_velocity_is_within_a_sample_of_the_corners() -> None:
    rec = triangle_record(lambda x, v: np.zeros_like(x), f=80.0)
    spec = line_spec(rec)
    assert spec is not None and spec.source == 'reference velocity'
    travel = 4 * 4e-6 * 80.0 * T
    assert 1e-6 <= spec.low_m <= 1e-6 + travel and 9e-6 - travel <= spec.high_m <= 9e-6
    assert spec.speed_mps == pytest.approx(4 * 4e-6 * 80.0, rel=1e-12)


def test_no_linear_part_is_said_not_guessed() -> None:
    t = np.arange(2000) * T
    x = 5e-6 + 1e-6 * np.sin(2 * np.pi * 50 * t)
    v = 1e-6 * 2 * np.pi * 50 * np.cos(2 * np.pi * 50 * t)
    rec = RunRecord(t, x, x, v, np.zeros(t.size), {}, {}, None)
    assert line_spec(rec) is None
    with pytest.raises(PiezoStageError, match='no linear part'):
        summarize(rec, lines=LineOptions())
    # not asked: no line figures, the object as it always was
    assert not any(k.startswith('line_') for k in summarize(rec).as_dict())
    with pytest.raises(ParameterError, match='middle_fraction'):
        LineOptions(middle_fraction=0.0)
    with pytest.raises(ParameterError, match='pixels'):
        LineOptions(pixels=-1)


def test_a_scan_line_bag_gives_the_line_figures_of_the_run_and_plots_them(
        tmp_path: Path, capsys) -> None:
    from piezo_stage_ros.simulate import main as simulate_main
    bag = tmp_path / 'line'
    assert simulate_main(['--trajectory', 'scan_line', '--duration', '0.3', '--json',
                          '--bag', str(bag), '--pixels', '32']) == 0
    sim = json.loads(capsys.readouterr().out)
    assert sim['line_pixels'] == 32.0
    # from the bag alone: the meta holds the line's linear part
    analysis = analyze_bag(bag)
    assert analysis.record.meta[LINES_KEY]['low_m'] == pytest.approx(5e-6)
    for key in ('line_trace_e_rms_m', 'line_retrace_e_max_m', 'line_trace_e_rms_true_m',
                'line_trace_samples'):
        assert analysis.metrics[key] == sim[key], key
    assert analyze_main(['-q', '--json', '--pixels', '32', '--plots', str(tmp_path / 'fig'),
                         str(bag)]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in ('line_pixel_trace_e_rms_m', 'line_pixel_retrace_e_max_m'):
        assert out[key] == sim[key], key
    assert (tmp_path / 'fig' / 'lines.png').stat().st_size > 0


def test_a_triangle_bag_has_line_figures_only_when_asked(tmp_path: Path, capsys) -> None:
    rec = triangle_record(lambda x, v: np.where(v > 0, 1e-9, -1e-9), meta={
        'trajectory_period_s': 0.02})
    write_run(rec, tmp_path / 'tri')
    assert not any(k.startswith('line_') for k in analyze_bag(tmp_path / 'tri').metrics)
    assert analyze_main(['-q', '--json', '--line-middle', '0.8', str(tmp_path / 'tri')]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out['line_middle_fraction'] == 0.8
    assert out['line_trace_e_rms_m'] == pytest.approx(1e-9, abs=ROUND)
    assert analyze_main(['-q', '--line-middle', '1.5', str(tmp_path / 'tri')]) == 2


def test_a_scan_line_recorded_without_description_is_found_from_its_velocity(
        tmp_path: Path) -> None:
    from piezo_stage_ros.core.control.controllers import ControllerParams
    from piezo_stage_ros.core.loop.experiments import run_one
    from piezo_stage_ros.core.model.stage import StageParams
    rec = run_one(StageParams(), ControllerParams().with_flat({'feedforward.mode': 'inverse'}),
                  TrajectoryParams.from_flat({'kind': 'scan_line'}), duration_s=0.3)
    write_run(rec, tmp_path / 'sim')
    # what a recording of the nodes holds: the samples, no run description
    write_run(RunRecord(rec.time_s, rec.position_m, rec.reference_m,
                        rec.reference_velocity_mps, rec.command_v), tmp_path / 'graph')
    sim, graph = analyze_bag(tmp_path / 'sim'), analyze_bag(tmp_path / 'graph')
    assert any('scan line found from the reference velocity' in n for n in graph.notes)
    spec = graph.record.meta[LINES_KEY]
    # the linear part's ends are samples: within one sample's travel of the line's own, and the
    # rounding of x_d there (of t mod P, eps t, times the speed)
    rounding = spec['speed_mps'] * 4 * np.finfo(float).eps * 0.3 + ROUND
    travel = spec['speed_mps'] * T + rounding
    assert 5e-6 - rounding <= spec['low_m'] <= 5e-6 + travel
    assert 15e-6 - travel <= spec['high_m'] <= 15e-6 + rounding
    assert spec['speed_mps'] == pytest.approx(2.5e-3, rel=1e-12)
    # so the same samples are measured: the same figures
    for key in ('line_trace_samples', 'line_retrace_samples', 'line_trace_e_rms_m',
                'line_retrace_e_rms_m', 'line_trace_e_max_m', 'line_retrace_e_max_m'):
        assert graph.metrics[key] == pytest.approx(sim.metrics[key], rel=1e-12), key
    # a triangle without description: every sample at full speed, figures only when asked
    tri = triangle_record(lambda x, v: np.zeros_like(x))
    write_run(RunRecord(tri.time_s, tri.position_m, tri.reference_m,
                        tri.reference_velocity_mps, tri.command_v), tmp_path / 'tri')
    assert LINES_KEY not in analyze_bag(tmp_path / 'tri').record.meta
