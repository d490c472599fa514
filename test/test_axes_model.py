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

"""The multi-axis stage: one axis as today, the coupling's exact ZOH, bad input refused."""

import math

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.model.axes import (
    AxesStage,
    AxesStageParams,
    check_axis_names,
    CouplingParams,
)
from piezo_stage_ros.core.model.stage import Stage, StageParams
import pytest
from tolerances import EPS

T = 1e-4


def stage_params(**flat):
    return StageParams.from_flat(flat)


def commands(samples, n, seed=1):
    """Commands over the whole amplifier range and beyond, a NaN among them."""
    u = np.random.default_rng(seed).uniform(-3.0, 12.0, (samples, n))
    u[57, 0] = np.nan
    return u


AXES = {
    'x': stage_params(**{'chain.sensor_noise_std_m': 1e-9, 'seed': 3}),
    'y': stage_params(**{'chain.sensor_noise_std_m': 2e-9, 'seed': 5,
                         'initial_position_m': 5e-6, 'plant.model': 'reduced'}),
    'z': stage_params(**{'seed': 7, 'initial_position_m': 2e-6,
                         'hysteresis.model': 'bouc_wen'}),
}


@pytest.mark.parametrize('names', [('x',), ('x', 'y'), ('x', 'y', 'z'), ('z', 'x')])
def test_without_coupling_each_axis_is_the_one_axis_stage_bit_for_bit(names):
    # the same noise streams, converters, NaN handling and fault count as one-axis stages
    params = AxesStageParams(names=names, axes=tuple(AXES[n] for n in names))
    stage = AxesStage(params)
    singles = [Stage(AXES[n]) for n in names]
    u = commands(1500, len(names))
    assert stage.reset() == [s.reset() for s in singles]
    got = stage.run_open_loop(u)
    want = np.column_stack([s.run_open_loop(u[:, k]) for k, s in enumerate(singles)])
    assert np.array_equal(got, want)
    assert stage.faults == tuple(s.faults for s in singles)
    assert stage.read_positions_m() == [s.position_m for s in singles]


def test_the_driving_axis_and_each_own_motion_stay_the_one_axis_stage_with_coupling():
    coupling = CouplingParams(gain=(0.0, 0.02, 0.0, 0.0), resonance_hz=(0.0, 1500.0, 0.0, 0.0))
    params = AxesStageParams(names=('x', 'y'), axes=(AXES['x'], AXES['y']), coupling=coupling)
    stage = AxesStage(params)
    x, y = Stage(AXES['x']), Stage(AXES['y'])
    u = commands(800, 2)
    stage.reset(), x.reset(), y.reset()
    for row in u.tolist():
        out = stage.step(row)
        # nothing couples into x: its measurement is the one-axis stage's
        assert out[0] == x.step(row[0])
        y.step(row[1])
        assert stage.read_positions_m()[0] == x.position_m
    # y's own motion is the one-axis stage's; the rest is the coupled displacement, which is
    # small against the driving axis' motion (2 % through a mode of a few x gain at most)
    coupled = stage.read_positions_m()[1] - y.position_m
    assert coupled != 0.0
    assert abs(coupled) < 0.02 * 20.0 * 38e-6


def coupled_stage(gain=0.02, resonance_hz=1500.0, damping=0.05, plant='third_order'):
    axes = (stage_params(**{'plant.model': plant, 'hysteresis.model': 'none',
                            'chain.quantize': False}),) * 2
    coupling = CouplingParams(gain=(0.0, gain, 0.0, 0.0), resonance_hz=(0.0, resonance_hz,
                                                                       0.0, 0.0),
                              damping=(0.05, damping, 0.05, 0.05))
    return AxesStage(AxesStageParams(names=('x', 'y'), axes=axes, coupling=coupling))


def continuous_path(stage, w_rad_s):
    """kappa G_x(j w) M(j w) from the parameters (the analytic transfer function)."""
    p = stage.params.axes[0].plant.third_order
    s = 1j * np.asarray(w_rad_s)
    g = p.gain / (s ** 3 + p.a0 * s ** 2 + p.a1 * s + p.a2)
    wn = 2.0 * math.pi * 1500.0
    m = wn ** 2 / (s ** 2 + 2.0 * 0.05 * wn * s + wn ** 2)
    return 0.02 * g * m


def test_coupling_dc_gain_is_kappa_times_the_driving_axis_gain():
    stage = coupled_stage()
    path = stage.paths[0]
    p = stage.params.axes[0].plant.third_order
    want = 0.02 * p.gain / p.a2
    # z = 1 of the discretised model: a solve with I - Ad, whose condition number is that of
    # the slowest pole (1/(1 - |z_p|) ~ 1e2 here); 1e3 n eps relative covers it
    got = path.frequency_response(1, [0.0], discrete=True)[0]
    assert abs(got - want) <= 1e3 * 5 * EPS * abs(want)
    # a constant command: the coupled displacement settles at kappa x_x
    for _ in range(4000):
        stage.step([4.0, 0.0])
    x_pos, y_pos = stage.read_positions_m()
    y_alone = Stage(stage.params.axes[1])
    y_alone.reset()
    for _ in range(4000):
        y_alone.step(0.0)
    assert abs((y_pos - y_alone.position_m) - 0.02 * x_pos) <= 1e-9 * 0.02 * x_pos


@pytest.mark.parametrize('f_hz', [10.0, 300.0, 1200.0, 1500.0, 2500.0])
def test_discretised_coupling_matches_the_continuous_one_under_zoh(f_hz):
    # exact ZOH: G_d(e^{jwT}) = sum_k G(j(w + k ws)) (1 - e^{-jwT}) / (j (w + k ws) T); the path
    # rolls off as w^-5, so the terms beyond |k| = 400 add less than 1e-14 of the sum
    stage = coupled_stage()
    w = 2.0 * math.pi * f_hz
    ws = 2.0 * math.pi / T
    k = np.arange(-400, 401)
    wk = w + k * ws
    hold = (1.0 - np.exp(-1j * w * T)) / (1j * wk * T)
    want = np.sum(continuous_path(stage, wk) * hold)
    got = stage.paths[0].frequency_response(1, [w], discrete=True)[0]
    # the solve with e^{jwT} I - Ad is conditioned by the lightly damped mode (1/(zeta wn T)
    # ~ 20); the continuous evaluation by its polynomials, near the resonance ~ 1/(2 zeta)
    assert abs(got - want) <= 1e-9 * abs(want)
    # and the model's own continuous matrices are the analytic transfer function
    cont = stage.paths[0].frequency_response(1, [w], discrete=False)[0]
    assert abs(cont - continuous_path(stage, w)) <= 1e-10 * abs(cont)


def test_coupling_resonance_is_the_discrete_pole_of_the_mode():
    stage = coupled_stage(damping=0.02)
    wn = 2.0 * math.pi * 1500.0
    s = -0.02 * wn + 1j * wn * math.sqrt(1.0 - 0.02 ** 2)
    poles = np.linalg.eigvals(stage.paths[0].ad)
    assert np.min(np.abs(poles - np.exp(s * T))) <= 1e-12


@pytest.mark.parametrize('names, match', [
    (('x', 'x'), "names axis 'x' twice"),
    (('x', 'w'), "'w' is not an axis name"),
    ((), 'has 0 names'),
    (('x', 'y', 'z', 'x'), 'has 4 names'),
])
def test_bad_axis_names_are_refused_naming_the_value_and_the_allowed(names, match):
    with pytest.raises(ParameterError, match=match) as err:
        check_axis_names(names)
    assert "out of ['x', 'y', 'z']" in str(err.value)


@pytest.mark.parametrize('coupling, match', [
    (CouplingParams(gain=(0.0, 0.02, 0.0)), r"'coupling.gain'.*has 3 values.*2 x 2 matrix as 4"),
    (CouplingParams(gain=(0.0, math.nan, 0.0, 0.0)), r"'coupling.gain'.*has nan at row 0, "
     r'column 1.*each finite in \[-1, 1\]'),
    (CouplingParams(gain=(0.0, 2.0, 0.0, 0.0)), r'has 2.0 at row 0, column 1'),
    (CouplingParams(gain=(0.1, 0.0, 0.0, 0.0)), r'zeros on the diagonal'),
    (CouplingParams(resonance_hz=(0.0, 5000.0, 0.0, 0.0)), r'below the Nyquist'),
    (CouplingParams(damping=(0.05, 0.0, 0.05, 0.05)), r"'coupling.damping'.*has 0.0 at row 0"),
    (CouplingParams(sensor_crosstalk=(0.0, math.inf, 0.0, 0.0)),
     r"'coupling.sensor_crosstalk'.*has inf"),
])
def test_bad_coupling_is_refused_naming_the_value_and_the_allowed_shape(coupling, match):
    with pytest.raises(ParameterError, match=match):
        AxesStageParams(names=('x', 'y'), axes=(StageParams(),) * 2, coupling=coupling)


def test_a_driving_axis_with_the_general_model_is_refused():
    em = stage_params(**{'plant.model': 'electromechanical'})
    with pytest.raises(ParameterError, match=r"'axes.x.plant.model'"):
        AxesStageParams(names=('x', 'y'), axes=(em, StageParams()),
                        coupling=CouplingParams(gain=(0.0, 0.01, 0.0, 0.0)))
    # moved, not driving: allowed
    AxesStageParams(names=('x', 'y'), axes=(StageParams(), em),
                    coupling=CouplingParams(gain=(0.0, 0.01, 0.0, 0.0)))


def test_sensor_crosstalk_reads_the_other_axis_true_position():
    axes = (stage_params(**{'chain.quantize': False}),) * 2
    stage = AxesStage(AxesStageParams(names=('x', 'y'), axes=axes, coupling=CouplingParams(
        sensor_crosstalk=(0.0, 0.01, 0.0, 0.0))))
    y = stage.reset()
    true = stage.read_positions_m()
    assert y[1] == true[1] + 0.01 * true[0]
    assert y[0] == true[0]


def test_static_coupling_path_follows_the_driving_position_at_once():
    stage = coupled_stage(resonance_hz=0.0)
    own_y = Stage(stage.params.axes[1])
    stage.reset(), own_y.reset()
    for u in (1.0, 5.0, 2.0):
        stage.step([u, 0.0])
        own_y.step(0.0)
        x_pos, y_pos = stage.read_positions_m()
        assert y_pos == own_y.position_m + 0.02 * x_pos


def test_axes_family_draws_each_axis_and_every_path_in_range_reproducibly():
    from piezo_stage_ros.core.model.axes import sample_axes_family
    design = AxesStageParams(names=('x', 'y'), axes=(StageParams(),) * 2, coupling=CouplingParams(
        gain=(0.0, 0.02, -0.01, 0.0), resonance_hz=(0.0, 1800.0, 0.0, 0.0)))
    family = sample_axes_family(design, 5, seed=3)
    assert family == sample_axes_family(design, 5, seed=3)
    assert len(family) == 5
    for text, stage in family:
        gain, res, _, _ = stage.matrices()
        assert 0.005 <= gain[0, 1] <= 0.05 and -0.05 <= gain[1, 0] <= -0.005
        assert gain[0, 0] == gain[1, 1] == 0.0 and res[0, 1] == 1800.0
        # the axes are different members of the stage family
        assert stage.axes[0] != stage.axes[1]
        assert 'x->y' in text and 'y->x' in text
    with pytest.raises(ParameterError, match='coupling'):
        sample_axes_family(design, 1, coupling=(0.1, 0.01))
