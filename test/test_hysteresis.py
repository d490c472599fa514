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

"""Hysteresis operators: exact stepping, bounds, loop closure, rate independence."""

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.model.hysteresis import (
    BacklashLike,
    BacklashLikeParams,
    BoucWen,
    BoucWenParams,
    HysteresisParams,
    make_hysteresis,
    PrandtlIshlinskii,
    PrandtlIshlinskiiParams,
)
import pytest
from scipy.integrate import solve_ivp

MODELS = ['backlash_like', 'bouc_wen', 'prandtl_ishlinskii']
# A piecewise-constant DAC input with reversals of several sizes (volts)
INPUT = [1.0, 1.3, 2.5, 2.4, 0.2, -1.0, 0.7, 0.69, 3.0, 9.5, 9.0, 1.0]


def run(model, inputs):
    state = model.rest_state(float(inputs[0]))
    out = []
    for v in inputs[1:]:
        state, w = model.step(state, float(v))
        out.append(w)
    return np.array(out)


def ode_solution(rhs, w0, inputs, ramp_s=1e-3):
    """Integrate dw/dt of a rate-independent model with v ramping linearly between samples."""
    w = w0
    out = []
    for v0, v1 in zip(inputs[:-1], inputs[1:]):
        rate = (v1 - v0) / ramp_s

        def f(t, y, v0=v0, rate=rate):
            return [rhs(v0 + rate * t, y[0], rate)]
        sol = solve_ivp(f, (0.0, ramp_s), [w], method='DOP853', rtol=1e-13, atol=1e-15)
        w = sol.y[0, -1]
        out.append(w)
    return np.array(out)


def test_backlash_exact_step_matches_ode_of_eq21():
    p = BacklashLikeParams()

    def eq21(v, w, vdot):
        return p.alpha * abs(vdot) * (p.c * v - w) + p.b1 * vdot
    exact = run(BacklashLike(p), INPUT)
    reference = ode_solution(eq21, p.c * INPUT[0], INPUT)
    np.testing.assert_allclose(exact, reference, rtol=1e-9)


def test_bouc_wen_exact_step_matches_its_ode():
    p = BoucWenParams(d_p=1.0, a=0.3, beta=0.5, gamma=0.2)
    model = BoucWen(p)

    def hdot(v, h, vdot):
        return p.a * p.d_p * vdot - p.beta * abs(vdot) * h - p.gamma * vdot * abs(h)
    # integrate h, then w = d_p v - h
    h = ode_solution(hdot, 0.0, INPUT)
    np.testing.assert_allclose(run(model, INPUT), p.d_p * np.array(INPUT[1:]) - h, rtol=1e-9)


def test_bouc_wen_with_gamma_zero_is_the_backlash_like_model():
    b = BacklashLikeParams()
    bw = BoucWenParams(d_p=b.c, a=(b.c - b.b1) / b.c, beta=b.alpha, gamma=0.0)
    np.testing.assert_allclose(run(BoucWen(bw), INPUT), run(BacklashLike(b), INPUT),
                               rtol=1e-12)


def test_backlash_bound_eqs_23_24():
    p = BacklashLikeParams()
    model = BacklashLike(p)
    rho = (p.c - p.b1) / p.alpha
    assert model.bound == pytest.approx(0.17854588796, rel=1e-9)
    state = model.rest_state(-2.0)
    state, w = model.step(state, 98.0)            # a long rise: d -> -(c - B1)/alpha, eq. (23)
    assert w - p.c * 98.0 == pytest.approx(-rho, rel=1e-12)
    state, w = model.step(state, -102.0)          # a long fall: d -> +(c - B1)/alpha, eq. (24)
    assert w + p.c * 102.0 == pytest.approx(rho, rel=1e-12)


@pytest.mark.parametrize('name', MODELS)
def test_output_stays_within_the_band(name):
    model = make_hysteresis(HysteresisParams(model=name))
    rng = np.random.default_rng(1)
    inputs = np.cumsum(rng.normal(0.0, 0.8, 3000))
    w = run(model, inputs)
    assert np.max(np.abs(w - model.slope * inputs[1:])) <= model.bound * (1 + 1e-12)


@pytest.mark.parametrize('name', MODELS)
def test_loop_closes_on_periodic_input(name):
    model = make_hysteresis(HysteresisParams(model=name))
    period = 1.0 + np.sin(2 * np.pi * np.arange(100) / 100)
    w = run(model, np.concatenate([[1.0], np.tile(period, 30)]))
    last, before = w[-100:], w[-200:-100]
    np.testing.assert_allclose(last, before, rtol=0, atol=1e-12)
    # and it is a loop: rising and falling branches differ at the same input
    rising, falling = last[99], last[49]     # both near v = 1 V
    assert abs(rising - falling) > 0.01


@pytest.mark.parametrize('name', MODELS)
def test_rate_independence(name):
    """The output at the turning points does not depend on how finely the path is sampled."""
    model = make_hysteresis(HysteresisParams(model=name))
    turning = np.array([1.0, 2.5, 0.2, 3.0, -1.0, 1.7])
    coarse = run(model, turning)
    fine_path = np.concatenate([np.linspace(a, b, 37)[:-1] for a, b in
                                zip(turning[:-1], turning[1:])] + [turning[-1:]])
    fine = run(model, fine_path)
    np.testing.assert_allclose(fine[35::36], coarse, rtol=0, atol=1e-12)


@pytest.mark.parametrize('name', MODELS)
def test_vectorized_matches_scalar(name):
    model = make_hysteresis(HysteresisParams(model=name))
    inputs = np.array([[1.0, -0.5], [2.0, 0.5], [0.5, 3.0], [1.5, 1.0]])
    state = model.rest_state(inputs[0].copy())
    for row in inputs[1:]:
        state, w = model.step(state, row.copy())
    # Not bit for bit: the scalar path calls math.exp (libm, < 1 ulp), the vectorized one np.exp
    # (numpy's SIMD loops, a few ulp, by CPU). Three steps, each moving e by at most
    # 5 eps |e - s rho| (0.4 V here) in an output of ~1 V: ~10 eps, under 1e-14 = 45 eps.
    for channel in range(2):
        assert w[channel] == pytest.approx(run(model, inputs[:, channel])[-1], rel=1e-14)


def loop_width(model):
    """Max vertical gap between the branches of w vs v on v = 1 + sin (Fig. 6 input)."""
    v = 1.0 + np.sin(2 * np.pi * np.arange(400) / 200)
    w = run(model, np.concatenate([[1.0], v]))[200:]
    v = v[200:]
    up = np.gradient(v) > 0
    grid = np.linspace(0.1, 1.9, 50)
    rise = np.interp(grid, np.sort(v[up]), w[up][np.argsort(v[up])])
    fall = np.interp(grid, np.sort(v[~up]), w[~up][np.argsort(v[~up])])
    return np.max(np.abs(rise - fall))


def test_backlash_loop_width_has_the_analytic_value():
    # Steady loop of eq. (21) between 0 and 2 V: e swings between -+rho (1 - E)/(1 + E) with
    # E = exp(-2 alpha); at mid-travel the branches are 2 rho (1 - E1)/(1 + E) ... apart,
    # E1 = exp(-alpha): width = 2 * |e_top * E1 - rho * (1 - E1)|.
    p = BacklashLikeParams()
    rho = (p.c - p.b1) / p.alpha
    big, half = np.exp(-2 * p.alpha), np.exp(-p.alpha)
    e_top = rho * (1 - big) / (1 + big)
    expected = 2 * abs(e_top * half - rho * (1 - half))
    assert loop_width(BacklashLike(p)) == pytest.approx(expected, rel=0.02)
    assert expected == pytest.approx(0.0294, abs=5e-4)


@pytest.mark.parametrize('name', ['bouc_wen', 'prandtl_ishlinskii'])
def test_other_models_defaults_give_a_loop_of_similar_width(name):
    reference = loop_width(BacklashLike(BacklashLikeParams()))
    width = loop_width(make_hysteresis(HysteresisParams(model=name)))
    assert width == pytest.approx(reference, rel=0.15)


def test_prandtl_ishlinskii_play_operator_by_hand():
    model = PrandtlIshlinskii(PrandtlIshlinskiiParams(p0=0.5, thresholds_v=(1.0,), weights=(2.0,)))
    state = model.rest_state(0.0)
    state, w = model.step(state, 3.0)    # play output dragged to 3 - 1 = 2
    assert w == pytest.approx(0.5 * 3.0 + 2.0 * 2.0)
    state, w = model.step(state, 2.5)    # inside the dead band: play output stays 2
    assert w == pytest.approx(0.5 * 2.5 + 2.0 * 2.0)
    state, w = model.step(state, 0.0)    # dragged down to 0 + 1 = 1
    assert w == pytest.approx(0.0 + 2.0 * 1.0)


def test_parameter_rules():
    with pytest.raises(ParameterError, match="'b1' = 1.1 must be smaller than c"):
        BacklashLikeParams(b1=1.1)
    with pytest.raises(ParameterError, match="'gamma' = 0.5 gives an unbounded Bouc-Wen loop"):
        BoucWenParams(beta=0.3, gamma=0.5)
    with pytest.raises(ParameterError, match="'thresholds_v' .* is not increasing"):
        PrandtlIshlinskiiParams(thresholds_v=(0.5, 0.4, 0.6, 0.8, 1.0))
