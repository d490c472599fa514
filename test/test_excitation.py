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

"""Excitation signals: determinism, band limits, amplitudes, exact derivatives, bad values."""

from __future__ import annotations

import math

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.interfaces import Trajectory
from piezo_stage_ros.core.signals.excitation import (
    ChirpExcitation,
    ChirpParams,
    make_excitation,
    NoiseExcitation,
    NoiseParams,
)
import pytest

FS = 20000.0


def test_noise_is_a_trajectory_deterministic_from_its_seed() -> None:
    t = np.arange(4000) / FS
    a = NoiseExcitation(NoiseParams(seed=3))
    assert isinstance(a, Trajectory)
    x1, v1 = a.evaluate(t)
    x2, v2 = NoiseExcitation(NoiseParams(seed=3)).evaluate(t)
    # bit for bit: the same generator, FFT and arithmetic on the same machine, twice
    np.testing.assert_array_equal(x1, x2)
    np.testing.assert_array_equal(v1, v2)
    x3, _ = NoiseExcitation(NoiseParams(seed=4)).evaluate(t)
    assert np.max(np.abs(x3 - x1)) > 1e-8


def test_noise_amplitude_offset_and_band() -> None:
    p = NoiseParams(offset_m=5e-6, amplitude_m=0.2e-6, band_low_hz=100.0, band_high_hz=2000.0,
                    period_s=0.5, grid_rate_hz=2 * FS, seed=7)
    exc = NoiseExcitation(p)
    t = np.arange(int(0.5 * FS)) / FS  # one period, loop samples on the grid
    x, _ = exc.evaluate(t)
    assert np.mean(x) == pytest.approx(5e-6, abs=1e-12)
    assert np.std(x) == pytest.approx(0.2e-6, rel=0.02)
    spectrum = np.abs(np.fft.rfft(x - x.mean())) ** 2
    f = np.fft.rfftfreq(x.size, 1.0 / FS)
    inside = (f >= 100.0) & (f <= 2000.0)
    # Out of the band only rounding is left: samples rounded at eps * 5e-6 m (the offset)
    # against a 0.2e-6 m signal, and the FFTs' own eps * log2(N) relative error, give a power
    # ratio ~(log2(N) eps * 5e-6 / 0.2e-6)^2 ~ 1e-26: 1e-20 is a million times above it.
    assert spectrum[~inside].sum() < 1e-20 * spectrum[inside].sum()
    # flat ("white") inside the band: every frequency of the band has the same power, to the
    # FFT's rounding, |dX_k| / |X_k| <= log2(N) eps sqrt(bins in band) ~ 1e-13 (1e-8 is above)
    assert np.ptp(spectrum[inside]) < 1e-8 * spectrum[inside].max()
    assert exc.extent_m[0] <= x.min() and x.max() <= exc.extent_m[1]


def test_noise_is_periodic_and_its_derivative_exact() -> None:
    p = NoiseParams(band_high_hz=1000.0, period_s=0.2, seed=2)
    exc = NoiseExcitation(p)
    t = np.linspace(0.0, 0.05, 2001)
    x, v = exc.evaluate(t)
    x_next, _ = exc.evaluate(t + 0.2)
    np.testing.assert_allclose(x_next, x, rtol=0, atol=1e-15)
    # central difference on a fine grid agrees with the derivative from the spectrum
    h = 1e-7
    fd = (exc.evaluate(t + h)[0] - exc.evaluate(t - h)[0]) / (2 * h)
    assert np.max(np.abs(fd - v)) < 0.02 * np.max(np.abs(v))
    assert exc.period_s == pytest.approx(0.2)
    assert exc.kind == 'noise'


def test_chirp_with_equal_frequencies_is_the_sine() -> None:
    p = ChirpParams(offset_m=1e-6, amplitude_m=2e-6, f0_hz=100.0, f1_hz=100.0, sweep_s=0.05)
    t = np.arange(1000) / FS
    x, v = ChirpExcitation(p).evaluate(t)
    np.testing.assert_allclose(x, 1e-6 + 2e-6 * np.sin(2 * math.pi * 100.0 * t), atol=1e-15)
    np.testing.assert_allclose(v, 2e-6 * 2 * math.pi * 100.0 * np.cos(2 * math.pi * 100.0 * t),
                               atol=1e-12)


@pytest.mark.parametrize('method', ['linear', 'logarithmic'])
def test_chirp_frequency_law_and_exact_derivative(method: str) -> None:
    p = ChirpParams(amplitude_m=1e-6, f0_hz=10.0, f1_hz=1000.0, sweep_s=0.5, method=method)
    exc = ChirpExcitation(p)
    assert exc.frequency_hz(np.array([0.0]))[0] == pytest.approx(10.0)
    assert exc.frequency_hz(np.array([0.5 - 1e-12]))[0] == pytest.approx(1000.0, rel=1e-6)
    mid = 505.0 if method == 'linear' else 100.0
    assert exc.frequency_hz(np.array([0.25]))[0] == pytest.approx(mid)
    t = np.linspace(0.001, 0.49, 3001)
    h = 1e-8
    fd = (exc.evaluate(t + h)[0] - exc.evaluate(t - h)[0]) / (2 * h)
    _, v = exc.evaluate(t)
    assert np.max(np.abs(fd - v)) < 1e-4 * np.max(np.abs(v))
    assert exc.extent_m == (p.offset_m - 1e-6, p.offset_m + 1e-6)


@pytest.mark.parametrize('flat, match', [
    ({'band_low_hz': 500.0, 'band_high_hz': 100.0}, "'band_high_hz' = 100.0 is not above"),
    ({'band_high_hz': 30000.0}, "'band_high_hz' = 30000.0 is above the Nyquist"),
    ({'band_low_hz': 10.0, 'band_high_hz': 10.5, 'period_s': 0.1}, 'leaves no frequency'),
    ({'amplitude_m': -1.0}, "'amplitude_m' = -1.0 is out of range"),
    ({'seed': -1}, "'seed' = -1 is out of range"),
])
def test_noise_bad_values_are_refused(flat: dict[str, object], match: str) -> None:
    with pytest.raises(ParameterError, match=match):
        NoiseParams.from_flat(flat)


def test_chirp_bad_method_and_kind_mismatch_are_refused() -> None:
    with pytest.raises(ParameterError, match="'method' = 'square' is not a valid choice"):
        ChirpParams(method='square')
    with pytest.raises(ParameterError, match="'kind' = 'noise'"):
        make_excitation('noise', ChirpParams())
    assert isinstance(make_excitation('chirp', ChirpParams()), ChirpExcitation)
    assert isinstance(make_excitation('noise', NoiseParams()), NoiseExcitation)


def test_kinds_noise_and_chirp_are_trajectories_of_the_trajectory_node() -> None:
    from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
    for kind in ('noise', 'chirp'):
        params = TrajectoryParams.from_flat({'kind': kind})
        traj = make_trajectory(params)
        assert isinstance(traj, Trajectory) and traj.kind == kind
        t = np.arange(100) / FS
        x, v = traj.evaluate(t)
        direct = make_excitation(kind, getattr(params, kind)).evaluate(t)
        # bit for bit: the same object's code on the same times, reached two ways
        np.testing.assert_array_equal(x, direct[0])
        np.testing.assert_array_equal(v, direct[1])
    # the travel check covers the excitations too
    with pytest.raises(ParameterError, match="'noise.amplitude_m' .* below the stage travel"):
        TrajectoryParams.from_flat({'kind': 'noise', 'noise.offset_m': 0.1e-6})
    with pytest.raises(ParameterError, match="'chirp.offset_m' .* above the stage travel"):
        TrajectoryParams.from_flat({'kind': 'chirp', 'chirp.offset_m': 38e-6})
