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

"""Scans over several axes: raster frames, Lissajous, spiral, point-to-point moves."""

import math

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.loop.scan2d import lissajous, moves, raster, spiral
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
import pytest

LINE_S = 0.01


def triangle(offset=10e-6, amplitude=5e-6, hz=100.0):
    return make_trajectory(TrajectoryParams.from_flat({
        'kind': 'triangle', 'triangle.offset_m': offset, 'triangle.amplitude_m': amplitude,
        'triangle.frequency_hz': hz}))


def check_velocity(tr, t, tol_rel):
    """x_d' against the central difference of x_d (error h^2 x''' / 6 on smooth stretches)."""
    h = 1e-7
    x_p, _ = tr.evaluate(t + h)
    x_m, _ = tr.evaluate(t - h)
    _, v = tr.evaluate(t)
    fd = (x_p - x_m) / (2 * h)
    scale = float(np.max(np.abs(v))) or 1.0
    assert np.max(np.abs(fd - v)) <= tol_rel * scale


def test_staircase_raster_sits_on_one_level_a_line_up_then_down():
    fast, slow = raster(triangle(), lines=8, pitch_m=0.5e-6, start_m=5e-6,
                        profile='staircase', transition_s=1e-3)
    assert slow.period_s == pytest.approx(2 * 8 * LINE_S, rel=1e-15)
    assert fast.period_s == LINE_S
    # the second half of every line: the level has settled
    k = np.arange(16)
    x, v = slow.evaluate((k + 0.5) * LINE_S)
    levels = np.concatenate([np.arange(8), np.arange(7, -1, -1)])
    assert np.allclose(x, 5e-6 + 0.5e-6 * levels, rtol=0, atol=1e-18)
    assert np.all(v == 0.0)
    # repeats with the period of two frames
    t = np.linspace(0.0, 0.16, 3001)
    assert np.allclose(slow.evaluate(t)[0], slow.evaluate(t + 0.16)[0], rtol=0, atol=1e-17)
    check_velocity(slow, np.linspace(0.0003, 0.3, 997), 1e-6)


def test_ramp_raster_covers_the_frame_at_constant_speed():
    _, slow = raster(triangle(), lines=64, pitch_m=10e-6 / 63, start_m=5e-6, profile='ramp')
    frame = 64 * LINE_S
    x, v = slow.evaluate(np.array([0.0, frame / 2, frame, 1.5 * frame]))
    assert x == pytest.approx([5e-6, 10e-6, 15e-6, 10e-6], rel=1e-12)
    assert v[0] == pytest.approx(10e-6 / frame, rel=1e-12) and v[3] == -v[0]


@pytest.mark.parametrize('kwargs, name, value', [
    ({'start_m': 30e-6, 'pitch_m': 0.2e-6}, 'raster.pitch_m', 0.2e-6),
    ({'start_m': 40e-6, 'pitch_m': 0.1e-6}, 'raster.start_m', 40e-6),
    ({'start_m': 5e-6, 'pitch_m': -0.1e-6}, 'raster.pitch_m', -0.1e-6),
])
def test_a_frame_that_leaves_the_travel_is_refused_naming_the_value_and_the_travel(
        kwargs, name, value):
    with pytest.raises(ParameterError) as err:
        raster(triangle(), lines=64, **kwargs)
    assert err.value.name == name and err.value.value == value
    assert "axis 'y' within its travel [0, 3.8e-05] m" in str(err.value)


def test_a_line_outside_the_fast_travel_or_without_a_period_is_refused():
    # an axis of a shorter travel than the line's trajectory was checked against
    with pytest.raises(ParameterError, match=r"'raster.line'.*takes x_d to 1.5e-05 m.*axis "
                       r"'x' within its travel \[0, 1.2e-05\] m"):
        raster(triangle(), lines=8, pitch_m=1e-7, start_m=5e-6, fast_travel=(0.0, 12e-6))
    from piezo_stage_ros.core.loop.trajectories import TableTrajectory
    with pytest.raises(ParameterError, match='raster.line.period_s'):
        raster(TableTrajectory([0.0, 1.0], [1e-6, 2e-6]), lines=8, pitch_m=1e-7, start_m=5e-6)
    with pytest.raises(ParameterError, match='raster.lines'):
        raster(triangle(), lines=1, pitch_m=1e-7, start_m=5e-6)


def test_lissajous_97_103_has_the_common_period_of_one_second():
    x, y = lissajous(frequencies_hz=[97.0, 103.0], amplitudes_m=[4e-6, 4e-6],
                     offsets_m=[10e-6, 10e-6])
    assert x.period_s == 1.0 and y.period_s == 1.0
    t = np.linspace(0.0, 0.05, 501)
    assert np.allclose(x.evaluate(t)[0], 10e-6 + 4e-6 * np.sin(2 * math.pi * 97 * t),
                       rtol=0, atol=1e-18)
    assert np.allclose(x.evaluate(t + 1.0)[0], x.evaluate(t)[0], rtol=0, atol=1e-16)
    check_velocity(y, t, 1e-6)
    with pytest.raises(ParameterError, match=r"'lissajous.amplitudes_m' = 1.2e-05.*axis 'y'"):
        lissajous(frequencies_hz=[97.0, 103.0], amplitudes_m=[4e-6, 12e-6],
                  offsets_m=[10e-6, 10e-6])


def test_spiral_radius_rises_linearly_and_returns():
    x, y = spiral(centres_m=[15e-6, 15e-6], radius_m=5e-6, frequency_hz=50.0, duration_s=0.5)
    t = np.linspace(0.0, 1.0, 2001)
    r = np.hypot(x.evaluate(t)[0] - 15e-6, y.evaluate(t)[0] - 15e-6)
    want = 5e-6 * np.where(t < 0.5, t, 1.0 - t) / 0.5
    assert np.allclose(r, want, rtol=0, atol=1e-17)
    check_velocity(x, np.linspace(0.01, 0.49, 97), 1e-5)
    with pytest.raises(ParameterError, match='spiral.radius_m'):
        spiral(centres_m=[3e-6, 15e-6], radius_m=5e-6, frequency_hz=50.0, duration_s=0.5)


def test_moves_visit_each_level_and_hold_the_last():
    tr = moves([5e-6, 12e-6, 8e-6], move_s=2e-3, dwell_s=10e-3)
    x, v = tr.evaluate(np.array([0.0, 9e-3, 11e-3, 20e-3, 24e-3, 40e-3, 1.0]))
    assert x[0] == x[1] == 5e-6 and v[0] == 0.0
    assert 5e-6 < x[2] < 12e-6 and v[2] > 0.0
    assert x[3] == 12e-6 and x[5] == 8e-6 and x[6] == 8e-6 and v[6] == 0.0
    assert tr.period_s is None
    check_velocity(tr, np.linspace(0.0101, 0.0119, 50), 1e-5)
    with pytest.raises(ParameterError, match=r"'moves.levels_m'.*within its travel"):
        moves([5e-6, 40e-6], move_s=1e-3, dwell_s=1e-3)
