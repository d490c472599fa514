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

"""Linear models against the paper's numbers and analytic responses."""

import numpy as np
from piezo_stage_ros.core.errors import ParameterError
from piezo_stage_ros.core.linear import (
    electromechanical_plant,
    ElectromechanicalParams,
    reduced_plant,
    ReducedParams,
    third_order_plant,
    ThirdOrderParams,
)
import pytest

PAPER_EQ20 = {'gain': 4.767e6, 'a0': 7582.0, 'a1': 4.1e8, 'a2': 1.677e12}


@pytest.mark.parametrize('name', sorted(PAPER_EQ20))
def test_table2_gives_eq20_within_one_percent(name):
    derived = ElectromechanicalParams().third_order()
    assert getattr(derived, name) == pytest.approx(PAPER_EQ20[name], rel=0.01)


def test_printed_eq18_a1_would_miss_eq20():
    # The printed (18) uses k_s/m in a1; that is 21 % off the identified 4.1e8, the derivation
    # (kbar_s/m) is 0.6 % off. Guard the derivation against a "fix" back to the print.
    p = ElectromechanicalParams()
    rc = p.resistance_ohm * p.capacitance_f
    printed = p.damping_n_s_per_m / (p.mass_kg * rc) + p.stiffness_n_per_m / p.mass_kg
    assert abs(printed / 4.1e8 - 1) > 0.2
    assert abs(p.third_order().a1 / 4.1e8 - 1) < 0.01


def test_dc_gains():
    third = third_order_plant(ThirdOrderParams())
    assert third.dc_gain_m_per_v == pytest.approx(4.767e6 / 1.677e12, rel=1e-12)
    reduced = reduced_plant(ReducedParams())
    assert reduced.dc_gain_m_per_v == pytest.approx(2.843e-6, rel=1e-12)
    # eq. (25) keeps the DC gain of eq. (20) (to the digits the paper prints)
    assert third.dc_gain_m_per_v == pytest.approx(2.843e-6, rel=2e-4)


def test_third_order_poles_are_a_lag_and_a_light_resonance():
    poles = third_order_plant(ThirdOrderParams()).poles()
    real = poles[np.abs(poles.imag) < 1.0].real
    pair = poles[poles.imag > 1.0][0]
    assert real[0] == pytest.approx(-4236.7, rel=1e-4)
    assert abs(pair) == pytest.approx(19895.0, rel=1e-3)
    zeta = -pair.real / abs(pair)
    assert zeta == pytest.approx(0.0841, abs=5e-4)
    # The paper's reduced model keeps the DC gain; the slow pole of (20) gives tau = 0.236 ms
    # against the 0.2445 ms of eq. (25), which the paper fitted to the step response instead.
    assert ThirdOrderParams().reduced().tau_s == pytest.approx(1 / 4236.7, rel=1e-4)


@pytest.mark.parametrize('omega', [1.0, 628.3, 4090.0, 2e4, 1e5])
def test_frequency_response_matches_the_polynomial(omega):
    p = ThirdOrderParams()
    s = 1j * omega
    expected = p.gain / (s ** 3 + p.a0 * s ** 2 + p.a1 * s + p.a2)
    got = third_order_plant(p).frequency_response(omega)
    assert got == pytest.approx(expected, rel=1e-10)
    r = ReducedParams()
    assert reduced_plant(r).frequency_response(omega) == pytest.approx(
        r.gain_m_per_v / (r.tau_s * s + 1), rel=1e-12)


def test_transfer_function_coefficients():
    num, den = third_order_plant(ThirdOrderParams()).transfer_function()
    assert num == pytest.approx([4.767e6], rel=1e-9)
    assert den == pytest.approx([1.0, 7582.0, 4.1e8, 1.677e12], rel=1e-9)


def test_electromechanical_model_without_hysteresis_is_the_derived_third_order():
    em = ElectromechanicalParams()
    num, den = electromechanical_plant(em).transfer_function()
    t = em.third_order()
    assert num == pytest.approx([t.gain], rel=1e-8)
    assert den == pytest.approx([1.0, t.a0, t.a1, t.a2], rel=1e-8)


def _zoh_step(plant, n, dt):
    d = plant.discretize(dt)
    x = np.zeros(plant.order)
    out = []
    for _ in range(n):
        x = d.ad @ x + d.bd[:, 0]
        out.append(d.c @ x)
    return np.array(out), dt * np.arange(1, n + 1)


def test_zoh_is_exact_for_the_reduced_step():
    r = ReducedParams()
    y, t = _zoh_step(reduced_plant(r), 100, 1e-4)
    np.testing.assert_allclose(y, r.gain_m_per_v * (1 - np.exp(-t / r.tau_s)), rtol=1e-12,
                               atol=1e-20)


def test_zoh_is_exact_for_the_third_order_step():
    p = ThirdOrderParams()
    y, t = _zoh_step(third_order_plant(p), 60, 1e-4)
    # unit step by residues: K / (s D(s)) at s = 0 and at the three poles
    den = np.array([1.0, p.a0, p.a1, p.a2])
    poles = np.roots(den)
    dden = np.polyder(den)
    analytic = p.gain / p.a2 + sum(
        (p.gain / (pk * np.polyval(dden, pk)) * np.exp(pk * t)).real for pk in poles)
    np.testing.assert_allclose(y, analytic, rtol=1e-9, atol=1e-18)
    # the lightly damped resonance rings: the step response is not monotone
    assert np.any(np.diff(y) < 0)


@pytest.mark.parametrize('dt', [0.0, -1e-4, float('nan')])
def test_discretize_refuses_bad_sample_time(dt):
    with pytest.raises(ParameterError, match='sample_time_s'):
        reduced_plant(ReducedParams()).discretize(dt)


def test_rest_state_is_an_equilibrium():
    plant = third_order_plant(ThirdOrderParams())
    x0 = plant.rest_state(1.5)
    assert plant.a @ x0 + plant.b[:, 0] * 1.5 == pytest.approx(np.zeros(3), abs=1e-9)
    assert plant.c @ x0 == pytest.approx(1.5 * plant.dc_gain_m_per_v, rel=1e-12)
