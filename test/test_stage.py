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

"""The stage: rest state, signal chain, batch stepping, the general model with H(q)."""

import math

import numpy as np
from piezo_stage_ros.core.model.hysteresis import BacklashLikeParams
from piezo_stage_ros.core.model.linear import ElectromechanicalParams
from piezo_stage_ros.core.model.stage import _dot, quantize, Stage, StageBatch, StageParams
import pytest
from scipy.integrate import solve_ivp
from tolerances import EPS, lti_rounding_bound

PLANTS = ['electromechanical', 'third_order', 'reduced']
LSB_M = 20.0 / 2 ** 16 / (10.0 / 38e-6)     # one ADC step in metres: 1.16 nm


def params(**flat):
    return StageParams.from_flat(flat)


@pytest.mark.parametrize('plant', PLANTS)
@pytest.mark.parametrize('hysteresis', ['backlash_like', 'bouc_wen', 'prandtl_ishlinskii', 'none'])
def test_starts_at_rest_at_the_initial_position(plant, hysteresis):
    stage = Stage(params(**{'plant.model': plant, 'hysteresis.model': hysteresis,
                            'chain.quantize': False}))
    # the rest state is a solve (n eps cond(A) ~ 1e-14 relative); 50 steps of the stable
    # recursion add at most 50 times gamma_4 (|Ad| |x|) ~ 1e-13 (measured: 1 eps)
    assert stage.position_m == pytest.approx(3.8e-6, rel=1e-12)
    held = stage.applied_voltage_v
    for _ in range(50):          # holding the rest voltage keeps it there
        stage.step(held)
    assert stage.position_m == pytest.approx(3.8e-6, rel=1e-9)


def test_measurement_is_quantized_to_the_adc_step():
    stage = Stage(StageParams())
    y0 = stage.reset()
    assert abs(y0 - 3.8e-6) <= LSB_M / 2
    assert StageParams().chain.adc_lsb_m == pytest.approx(LSB_M)
    codes = (np.array([stage.step(1.5) for _ in range(20)]) * (10.0 / 38e-6) + 10.0) / (20 / 2**16)
    np.testing.assert_allclose(codes, np.round(codes), atol=1e-6)


def test_reduced_plant_step_is_exact_without_hysteresis_or_quantization():
    stage = Stage(params(**{'plant.model': 'reduced', 'hysteresis.model': 'none',
                            'chain.quantize': False, 'initial_position_m': 0.0}))
    y = stage.run_open_loop(np.full(40, 2.0))
    t = 1e-4 * np.arange(1, 41)
    # as test_linear.test_zoh_is_exact_for_the_reduced_step: ~10 eps / (1 - a_d) relative
    np.testing.assert_allclose(y, 2.0 * 2.843e-6 * (1 - np.exp(-t / 2.445e-4)), rtol=1e-12)


@pytest.mark.parametrize('command, applied', [(50.0, 10.0), (-5.0, -2.0), (3.0, 3.0)])
def test_amplifier_range_clamps_every_command(command, applied):
    stage = Stage(params(**{'chain.quantize': False}))
    stage.step(command)
    assert stage.applied_voltage_v == applied


@pytest.mark.parametrize('bad', [math.nan, math.inf, -math.inf])
def test_non_finite_command_applies_the_safe_voltage(bad):
    stage = Stage(params(**{'chain.safe_voltage_v': 0.5}))
    stage.step(bad)
    assert stage.applied_voltage_v == 0.5
    assert stage.faults == 1
    assert math.isfinite(stage.position_m)


def test_dac_quantization():
    stage = Stage(StageParams())
    stage.step(1.23456)
    lsb = 20.0 / 2 ** 16
    assert abs(stage.applied_voltage_v - 1.23456) <= lsb / 2
    assert ((stage.applied_voltage_v + 10.0) / lsb) == pytest.approx(
        round((stage.applied_voltage_v + 10.0) / lsb), abs=1e-9)
    assert quantize(100.0, 16, -10.0, 10.0) == pytest.approx(10.0 - lsb)   # top code
    assert quantize(-100.0, 16, -10.0, 10.0) == -10.0


def test_sensor_noise_is_seeded_and_has_the_configured_spread():
    p = params(**{'chain.sensor_noise_std_m': 2e-9, 'chain.quantize': False, 'seed': 5})
    a = Stage(p).run_open_loop(np.full(20000, 1.2925))
    b = Stage(p).run_open_loop(np.full(20000, 1.2925))
    np.testing.assert_array_equal(a, b)  # bit for bit: the same seed and kernel, twice
    clean = Stage(params(**{'chain.quantize': False})).run_open_loop(np.full(20000, 1.2925))
    assert np.std(a - clean) == pytest.approx(2e-9, rel=0.03)
    other = Stage(p, rng=np.random.default_rng(6)).run_open_loop(np.full(100, 1.2925))
    assert not np.array_equal(other, a[:100])


def _batch_and_scalar(p, commands):
    batch = StageBatch(p, 3)
    ys, states = [], []
    for u in commands:
        ys.append(batch.step(np.full(3, u)))
        states.append(np.abs(batch._x).max(axis=1))
    return np.array(ys), Stage(p).run_open_loop(commands), batch, np.max(states, axis=0)


@pytest.mark.parametrize('plant', PLANTS)
def test_batch_equals_scalar_to_rounding(plant):
    # Not bit for bit: the batch steps with a matmul (BLAS: its kernel and FMA decide the order
    # of the additions), the scalar kernel adds left to right. Unquantized, the two differ by
    # rounding driven through the plant, bounded in tolerances.lti_rounding_bound.
    p = params(**{'plant.model': plant, 'hysteresis.model': 'none', 'chain.quantize': False})
    commands = 1.0 + np.sin(2 * np.pi * 100 * 1e-4 * np.arange(300))
    ys, scalar, batch, x_max = _batch_and_scalar(p, commands)
    d = batch._core.discrete
    bound = lti_rounding_bound(d.ad, d.bd[:, :1], d.c, x_max, np.array([np.max(commands)]),
                               commands.size)
    assert bound < 1e-12 * np.max(np.abs(scalar))   # a sharp test: ~1e-20 m against 6e-6 m
    for column in (0, 2):
        assert np.max(np.abs(ys[:, column] - scalar)) <= bound


@pytest.mark.parametrize('plant', PLANTS)
def test_batch_equals_scalar_to_one_adc_code(plant):
    # With hysteresis and the 16-bit ADC: the unquantized positions differ by rounding (above),
    # so a sample whose true position lies within that rounding of a code boundary may read one
    # code apart; no more. (In practice none does: the bound is ~1e-20 m, a code 1.16 nm.)
    p = params(**{'plant.model': plant})
    commands = 1.0 + np.sin(2 * np.pi * 100 * 1e-4 * np.arange(300))
    ys, scalar, _, _ = _batch_and_scalar(p, commands)
    for column in (0, 2):
        # one code, plus the rounding of the two quantized values themselves
        assert np.max(np.abs(ys[:, column] - scalar)) <= LSB_M + 4 * EPS * np.max(np.abs(scalar))


def test_batch_stages_are_independent():
    batch = StageBatch(params(**{'chain.quantize': False}), 2)
    batch.reset([1e-6, 5e-6])
    np.testing.assert_allclose(batch.position_m, [1e-6, 5e-6], rtol=1e-12)
    batch.step(np.array([0.0, math.nan]))
    assert batch.faults == 1


def test_general_model_without_hysteresis_is_its_third_order_plant():
    em = ElectromechanicalParams()
    third = {'plant.third_order.' + k: v for k, v in em.third_order().to_flat().items()}
    commands = 1.0 + np.sin(2 * np.pi * 100 * 1e-4 * np.arange(200))
    y_em = Stage(params(**{'plant.model': 'electromechanical', 'hysteresis.model': 'none',
                           'chain.quantize': False})).run_open_loop(commands)
    y_3 = Stage(params(**{'plant.model': 'third_order', 'hysteresis.model': 'none',
                          'chain.quantize': False, **third})).run_open_loop(commands)
    # two realizations, each discretized by expm (relative error ~ n eps ||A T|| ~ 1e-15 in the
    # scaled states) and run 200 steps: the errors are driven through the plant, whose impulse
    # response sums to a few times its DC gain, so ~1e-13 relative (measured 25 eps = 6e-15).
    # Unquantized on purpose: a 16-bit ADC would turn an ulp into a code.
    np.testing.assert_allclose(y_em, y_3, rtol=1e-10)


def test_general_model_with_charge_hysteresis_matches_a_stiff_ode_solution():
    """Eqs. (11)-(12) with H(q) = k_amp (u - P(u)), u = q / q_ref, against LSODA."""
    em, bl = ElectromechanicalParams(), BacklashLikeParams()
    dt, n = 1e-4, 150
    commands = 1.0 + np.sin(2 * np.pi * 100 * dt * np.arange(n))
    stage = Stage(params(**{'plant.model': 'electromechanical', 'plant.substeps': 32,
                            'chain.quantize': False}))
    simulated = stage.run_open_loop(commands)

    m, r, c, t_em, k = (em.mass_kg, em.resistance_ohm, em.capacitance_f, em.transformer_n_per_v,
                        em.amplifier_gain)
    kb = em.stiffness_bar_n_per_m
    q_ref = c * k * kb / em.stiffness_n_per_m

    def rhs(_, y, v_in):
        q, x, xd, p = y
        u = q / q_ref
        qd = (c * k * v_in - c * k * (u - p) - q + t_em * x) / (r * c)
        ud = qd / q_ref
        pd = bl.alpha * abs(ud) * (bl.c * u - p) + bl.b1 * ud
        return [qd, xd, (t_em / c * q - em.damping_n_s_per_m * xd - kb * x) / m, pd]

    u0 = 3.8e-6 / stage._core.dc_gain_m_per_v
    y = [u0 * q_ref, 3.8e-6, 0.0, bl.c * u0]
    reference = []
    for v_in in commands:
        sol = solve_ivp(rhs, (0.0, dt), y, args=(v_in,), method='LSODA', rtol=1e-11,
                        atol=[1e-16, 1e-18, 1e-12, 1e-14])
        y = sol.y[:, -1]
        reference.append(y[1])
    reference = np.array(reference)
    # first-order splitting with 32 sub-steps: within 5e-5 of the travel (measured 2.1e-5)
    assert np.max(np.abs(simulated - reference)) < 5e-5 * np.ptp(reference)


@pytest.mark.parametrize('flat', [
    {},
    {'plant.model': 'reduced'},
    {'hysteresis.model': 'none', 'chain.quantize': False},
    {'plant.model': 'reduced', 'chain.sensor_noise_std_m': 3e-9, 'seed': 4},
    {'chain.sensor_noise_std_m': 1e-9, 'chain.safe_voltage_v': 0.25},
])
def test_fused_kernel_computes_exactly_what_the_generic_one_does(flat):
    p = params(**flat)
    commands = np.concatenate([1.0 + np.sin(2 * np.pi * 100 * 1e-4 * np.arange(300)),
                               [math.nan, 20.0, -7.0, 1.0, 1.0, math.inf, 3.3]])
    fused, generic = Stage(p), Stage(p, fused=False)
    assert fused._kernel is not generic._kernel
    # Bit for bit, on purpose: both kernels are scalar Python arithmetic in the same order
    # (the fused one is the generic one written out; _dot adds left to right, not sum()), so
    # IEEE rounding is the same everywhere; quantized or not, any difference is a bug.
    np.testing.assert_array_equal(fused.run_open_loop(commands), generic.run_open_loop(commands))
    assert (fused.faults, fused.steps, fused.applied_voltage_v, fused.hysteresis_output_v) == \
        (generic.faults, generic.steps, generic.applied_voltage_v, generic.hysteresis_output_v)
    assert fused.position_m == generic.position_m
    assert fused.reset(2e-6) == generic.reset(2e-6)
    assert fused.time_s == 0.0
    # the true position read every sample (what the closed loop records), bit for bit against
    # the generic kernel and against c x summed left to right from the kernel's state
    c = [float(v) for v in fused._core.discrete.c]
    for u in commands.tolist():
        fused.step(u)
        generic.step(u)
        true = fused.read_position_m()
        assert true == generic.read_position_m() == _dot(c, fused._kernel.get().x)
        assert true == fused.position_m
