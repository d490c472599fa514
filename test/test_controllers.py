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

"""Controllers: the RAC law, projection, PI, notch, and the edge-case contract."""

import cmath
import math

from hypothesis import given, settings
from hypothesis import strategies as st
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.interfaces import Controller
from piezo_stage_ros.core.control.controllers import (
    build_controller,
    ControllerParams,
    notch_coefficients,
    NotchedController,
    NotchFilter,
    NotchParams,
    OpenLoopController,
    PIController,
    PIParams,
    plant_resonance,
    proj,
    RACController,
    RACParams,
    sat,
    SENSOR_GAIN_V_PER_M,
)
from piezo_stage_ros.core.model.linear import (
    reduced_plant,
    ReducedParams,
    third_order_plant,
    ThirdOrderParams,
)
import pytest

T = 1e-4
K = SENSOR_GAIN_V_PER_M
NO_NOTCH = NotchParams(mode='off')


# ---------------------------------------------------------------- sat and proj


@pytest.mark.parametrize('z, expected', [(-3.0, -1.0), (-1.0, -1.0), (-0.25, -0.25), (0.0, 0.0),
                                         (0.7, 0.7), (1.0, 1.0), (12.0, 1.0)])
def test_sat_is_eq_35(z, expected):
    assert sat(z) == expected


@pytest.mark.parametrize('estimate, step, expected', [
    (1.0, 0.5, 1.5),      # inside: the law acts
    (2.0, 0.5, 2.0),      # at the upper bound, pushing out: dropped (eq. (40))
    (2.0, -0.5, 1.5),     # at the upper bound, pushing in: acts
    (0.5, -0.1, 0.5),     # at the lower bound, pushing out: dropped
    (1.9, 0.5, 2.0),      # would cross: stops on the bound
    (0.6, -0.5, 0.5),
])
def test_proj_is_eq_40_on_the_updated_estimate(estimate, step, expected):
    assert proj(estimate, step, 0.5, 2.0) == pytest.approx(expected)


# ---------------------------------------------------------------- parameters


def test_defaults_satisfy_the_paper_assumptions_for_the_default_stage():
    p = RACParams()
    theta = 1.0 / (2.843e-6 * K * 1.0341)           # a/(b c) in sensor volts
    phi = 2.445e-4 * theta                          # 1/(b c)
    assert p.theta_min < theta < p.theta_max
    assert p.phi_min < phi < p.phi_max
    assert p.k_star_v >= p.rho_v / p.c_min


def test_k_star_below_rho_over_c_min_is_refused_naming_value_and_minimum():
    with pytest.raises(ParameterError, match=r"'k_star_v' = 0\.1 .*minimum rho/c_min = 0\.18"):
        RACParams(k_star_v=0.1)
    with pytest.raises(ParameterError, match=r"'rac\.k_star_v' = 0\.1"):
        ControllerParams.from_flat({'rac.k_star_v': 0.1})
    RACParams(k_star_v=0.09, c_min=2.0)  # rho/c_min = 0.09: allowed


@pytest.mark.parametrize('changes, name', [
    ({'theta_min': 2.0, 'theta_max': 1.0}, 'theta_max'),
    ({'phi_min': 5e-4, 'phi_max': 4e-4}, 'phi_max'),
    ({'theta_init': 3.0}, 'theta_init'),
    ({'phi_init': 1e-5}, 'phi_init'),
])
def test_bounds_must_be_ordered_and_contain_the_initial_estimates(changes, name):
    with pytest.raises(ParameterError, match=f"'{name}'"):
        RACParams(**changes)


def test_output_limits_must_be_ordered_and_types_are_choices():
    with pytest.raises(ParameterError, match="'output_max_v'"):
        ControllerParams(output_min_v=1.0, output_max_v=1.0)
    with pytest.raises(ParameterError, match="'type' = 'pid'.*one of 'rac', 'pi', 'open_loop'"):
        ControllerParams(type='pid')
    with pytest.raises(ParameterError, match="'pi.anti_windup'"):
        ControllerParams.from_flat({'pi.anti_windup': 'clamp'})


def test_every_parameter_name_is_a_dotted_path_without_python_keywords():
    import keyword
    names = [s.name for s in ControllerParams.specs()]
    assert 'rac.epsilon_v' in names and 'notch.mode' in names
    assert not [n for n in names for part in n.split('.') if keyword.iskeyword(part)]


# ---------------------------------------------------------------- the RAC law


def test_rac_step_is_eqs_33_to_40_in_sensor_volts():
    # the adaptation's own dead zone (narrower than the boundary layer) drives (38)-(39)
    p = RACParams(gamma=100.0, eta=0.02, epsilon_v=0.01, adaptation_dead_zone_v=0.004,
                  adaptation_regressor='measured', normalisation=0.0)
    c = RACController(p, T)
    c.reset(0.0, 0.0)
    x, xd, vd = 4.0e-6, 3.9e-6, 1e-3
    y, yd, ydd = K * x, K * xd, K * vd
    e = y - yd
    i = T * e                                    # backward rectangle
    s = e + p.lambda_per_s * i
    assert abs(s) > p.epsilon_v                  # outside the boundary layer: adaptation acts
    u_fd = ydd - p.lambda_per_s * e
    v = -p.k_d * s + p.phi_init * u_fd + p.theta_init * y - p.k_star_v * sat(s / p.epsilon_v)
    assert c.step(x, xd, vd) == pytest.approx(v, rel=1e-12)
    s_a = s - p.adaptation_dead_zone_v * sat(s / p.adaptation_dead_zone_v)
    d = c.diagnostics()
    assert d['s_v'] == pytest.approx(s)
    assert d['theta_hat'] == pytest.approx(
        min(max(p.theta_init - T * p.gamma * y * s_a, p.theta_min), p.theta_max))
    assert d['phi_hat'] == pytest.approx(
        min(max(p.phi_init - T * p.eta * u_fd * s_a, p.phi_min), p.phi_max))


def test_inside_the_boundary_layer_the_estimates_do_not_move():
    c = RACController(RACParams(), T)
    c.reset(3.8e-6, 3.8e-6)
    for _ in range(10):
        c.step(3.8e-6 + 1e-9, 3.8e-6, 0.0)
    d = c.diagnostics()
    assert abs(d['s_v']) < RACParams().epsilon_v
    assert (d['theta_hat'], d['phi_hat']) == (RACParams().theta_init, RACParams().phi_init)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-1e-3, 1e-3), st.floats(-1e-3, 1e-3),
                          st.floats(-10.0, 10.0)), min_size=1, max_size=60),
       st.floats(1.0, 1e7), st.floats(0.0, 1.0), st.floats(0.0, 1e3),
       st.sampled_from(['measured', 'desired']))
def test_projection_keeps_the_estimates_in_their_bounds_for_any_inputs(samples, gain, eps_a,
                                                                       kappa, regressor):
    # huge adaptation rates, wild inputs, any dead zone, normalisation and regressors: (P1)-(P2)
    # must hold at every sample
    p = RACParams(gamma=gain, eta=gain * 1e-3, epsilon_v=0.01, adaptation_dead_zone_v=eps_a,
                  normalisation=kappa, adaptation_regressor=regressor)
    c = RACController(p, T)
    c.reset(0.0, 0.0)
    for x, xd, vd in samples:
        u = c.step(x, xd, vd)
        d = c.diagnostics()
        assert p.theta_min <= d['theta_hat'] <= p.theta_max
        assert p.phi_min <= d['phi_hat'] <= p.phi_max
        assert -2.0 <= u <= 10.0 and math.isfinite(u)


def test_reset_returns_to_the_initial_estimates_and_a_zero_integral():
    p = RACParams(epsilon_v=0.01, gamma=1e5, eta=1.0)
    c = RACController(p, T)
    c.reset(3.8e-6, 3.8e-6)
    for k in range(50):
        c.step(3.8e-6 + 0.5e-6 * math.sin(k), 3.8e-6, 1e-3)
    d = c.diagnostics()
    assert (d['theta_hat'], d['phi_hat']) != (p.theta_init, p.phi_init)
    c.reset(3.8e-6, 3.8e-6)
    d = c.diagnostics()
    assert (d['theta_hat'], d['phi_hat'], d['integral_v_s']) == (p.theta_init, p.phi_init, 0.0)


def _paper_law_step(state, p, x, xd, vd, dt=T):
    """
    Return the command of the paper's law (38)-(39) driven by s_eps, as shipped before the
    adaptation got its own dead zone and normalisation; ``state`` is updated in place.
    """
    y, yd, ydd = x * K, xd * K, vd * K
    lam = p.lambda_per_s
    e = y - yd
    i_new = state['i'] + dt * e
    s = e + lam * i_new
    z = s * (1.0 / p.epsilon_v)
    sz = 1.0 if z >= 1.0 else (-1.0 if z <= -1.0 else z)
    u_fd = ydd - lam * e
    theta, phi = state['theta'], state['phi']
    v = -p.k_d * s + phi * u_fd + theta * y - p.k_star_v * sz
    if v > 10.0 or v < -2.0:
        if (v > 10.0) == (e < 0.0):
            i_new = state['i']
            s = e + lam * i_new
            z = s * (1.0 / p.epsilon_v)
            sz = 1.0 if z >= 1.0 else (-1.0 if z <= -1.0 else z)
            v = -p.k_d * s + phi * u_fd + theta * y - p.k_star_v * sz
        v = min(max(v, -2.0), 10.0)
    else:
        s_eps = s - p.epsilon_v * sz
        if s_eps != 0.0:
            state['phi'] = min(max(phi - dt * p.eta * u_fd * s_eps, p.phi_min), p.phi_max)
            state['theta'] = min(max(theta - dt * p.gamma * y * s_eps, p.theta_min),
                                 p.theta_max)
    state['i'] = i_new
    return v


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(-2e-6, 40e-6), st.floats(0.0, 38e-6),
                          st.floats(-0.05, 0.05), st.floats(1e-5, 2e-4)),
                min_size=1, max_size=80),
       st.floats(1e-3, 0.5), st.floats(0.0, 1e5), st.floats(0.0, 1e-2))
def test_neutral_dead_zone_and_normalisation_are_the_paper_law_bit_for_bit(samples, eps, gamma,
                                                                           eta):
    # kappa = 0 and epsilon_a = epsilon: the same floating-point operations as the paper's law
    p = RACParams(epsilon_v=eps, adaptation_dead_zone_v=eps, normalisation=0.0, gamma=gamma,
                  eta=eta, theta_min=0.5, theta_max=4.0, phi_min=1e-4, phi_max=5e-3,
                  adaptation_regressor='measured')
    c = RACController(p, T)
    c.reset(0.0, 0.0)
    state = {'i': 0.0, 'theta': p.theta_init, 'phi': p.phi_init}
    for x, xd, vd, dt in samples:
        assert c.step(x, xd, vd, dt) == _paper_law_step(state, p, x, xd, vd, dt)
        d = c.diagnostics()
        assert (d['theta_hat'], d['phi_hat'], d['integral_v_s']) == (
            state['theta'], state['phi'], state['i'])


def _first_step(p, x, xd, vd):
    """Return (y, u_fd, s) in sensor volts and the diagnostics after one step from reset."""
    c = RACController(p, T)
    c.reset(xd, xd)
    c.step(x, xd, vd)
    d = c.diagnostics()
    e = K * (x - xd)
    return K * x, K * vd - p.lambda_per_s * e, d['s_v'], d


@pytest.mark.parametrize('offset_m, moves', [(0.3e-9, False), (-0.3e-9, False),
                                             (1.9e-9, False), (3e-9, True), (-3e-9, True)])
def test_the_adaptation_dead_zone_freezes_the_estimates_inside_it(offset_m, moves):
    # a boundary layer much narrower than the dead zone: only epsilon_a decides (lambda set
    # here, so that the offsets below fall on either side of it as the comment computes)
    p = RACParams(epsilon_v=1e-5, adaptation_dead_zone_v=0.001, gamma=1e3, eta=1e-3,
                  adaptation_regressor='measured', normalisation=0.0, lambda_per_s=3000.0)
    y, u_fd, s, d = _first_step(p, 3.8e-6 + offset_m, 3.8e-6, 0.0)
    # s = (1 + lambda T) K offset: 0.10 mV at 0.3 nm, 0.65 mV at 1.9 nm, 1.03 mV at 3 nm
    assert (abs(s) > p.adaptation_dead_zone_v) == moves
    if not moves:
        assert (d['theta_hat'], d['phi_hat']) == (p.theta_init, p.phi_init)
    else:
        s_a = s - p.adaptation_dead_zone_v * sat(s / p.adaptation_dead_zone_v)
        assert d['theta_hat'] == pytest.approx(p.theta_init - T * p.gamma * y * s_a, rel=1e-12)
        assert d['phi_hat'] == pytest.approx(p.phi_init - T * p.eta * u_fd * s_a, rel=1e-12)


def test_a_zero_dead_zone_adapts_on_every_nonzero_s():
    p = RACParams(adaptation_dead_zone_v=0.0, gamma=1e3, eta=1e-3,
                  adaptation_regressor='measured', normalisation=0.0)
    y, u_fd, s, d = _first_step(p, 3.8e-6 + 0.3e-9, 3.8e-6, 0.0)
    assert 0.0 < abs(s) < p.epsilon_v                 # deep inside the boundary layer
    assert d['theta_hat'] == pytest.approx(p.theta_init - T * p.gamma * y * s, rel=1e-12)
    assert d['phi_hat'] == pytest.approx(p.phi_init - T * p.eta * u_fd * s, rel=1e-12)


@settings(max_examples=80, deadline=None)
@given(st.floats(0.0, 38e-6), st.floats(-2e-6, 2e-6), st.floats(-0.05, 0.05),
       st.floats(1e-3, 1e3), st.floats(1.0, 1e6), st.floats(1e-6, 1.0))
def test_normalisation_bounds_the_per_sample_step(xd, err, vd, kappa, gamma, eta):
    # wide bounds so no clipping: the command moves by q = y dtheta + u_fd dphi = -g/(1+kappa g)
    # s_a with g = T (gamma y^2 + eta u_fd^2), so |q| < |s_a|/kappa for any regressor size
    p = RACParams(adaptation_dead_zone_v=0.0, normalisation=kappa, gamma=gamma, eta=eta,
                  theta_min=1e-9, theta_max=1e9, phi_min=1e-12, phi_max=1e9, theta_init=1.0,
                  phi_init=1.0, adaptation_regressor='measured')
    y, u_fd, s, d = _first_step(p, xd + err, xd, vd)
    if d['saturated']:
        return                                         # frozen adaptation: nothing to bound
    q = y * (d['theta_hat'] - p.theta_init) + u_fd * (d['phi_hat'] - p.phi_init)
    g = T * (gamma * y * y + eta * u_fd * u_fd)
    # q is a difference of O(1) estimates times regressors: its rounding is ~1e-16 of
    # |y| theta + |u_fd| phi, the size of the terms cancelled
    tol = 1e-14 * (abs(y) + abs(u_fd)) * 1e9 + 1e-300
    projected = d['theta_hat'] in (p.theta_min, p.theta_max) or \
        d['phi_hat'] in (p.phi_min, p.phi_max)
    if not projected:
        assert q == pytest.approx(-g / (1.0 + kappa * g) * s, rel=1e-9, abs=tol)
    # both terms of q have the sign of -s: the projection (40), which shortens one of them
    # (theta_hat from 1 to 1e-9 when gamma y^2 is large and kappa small), shrinks |q|
    assert abs(q) <= abs(s) / kappa + tol


@pytest.mark.parametrize('kappa', [0.0, 20.0])
def test_desired_regressors_drive_the_update_by_the_reference(kappa):
    p = RACParams(adaptation_dead_zone_v=0.001, gamma=300.0, eta=1e-3, normalisation=kappa,
                  adaptation_regressor='desired', theta_min=0.5, theta_max=4.0,
                  phi_min=1e-4, phi_max=5e-3)
    x, xd, vd = 4.0e-6, 3.9e-6, 2e-3
    _, _, s, d = _first_step(p, x, xd, vd)
    yd, ydd = K * xd, K * vd
    s_a = s - p.adaptation_dead_zone_v * sat(s / p.adaptation_dead_zone_v)
    g = T / (1.0 + kappa * T * (p.gamma * yd * yd + p.eta * ydd * ydd))
    assert d['theta_hat'] == pytest.approx(p.theta_init - g * p.gamma * yd * s_a, rel=1e-12)
    assert d['phi_hat'] == pytest.approx(p.phi_init - g * p.eta * ydd * s_a, rel=1e-12)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-30e-9, 30e-9), min_size=1, max_size=80), st.floats(0.0, 38e-6))
def test_with_desired_regressors_noise_on_a_plateau_cannot_move_phi_hat(noise, level):
    # a constant reference has dy_d/dt = 0: whatever the sensor reads, phi_hat stays; with the
    # measured regressor u_fd = -lambda e the same noise moves it (the drift it cures)
    kw = dict(adaptation_dead_zone_v=0.0, gamma=300.0, eta=1e-2)
    desired = RACController(RACParams(adaptation_regressor='desired', **kw), T)
    desired.reset(level, level)
    for n in noise:
        desired.step(level + n, level, 0.0)
        assert desired.diagnostics()['phi_hat'] == RACParams().phi_init


# ---------------------------------------------------------------- PI


def test_pi_response_to_a_constant_error_is_the_exact_ramp():
    p = PIParams(k_p=1.5, k_i=1500.0)
    c = PIController(p, T, output_min_v=-1e9, output_max_v=1e9)
    c.reset(0.0, 0.0)
    e = 1e-8                                   # metres: 2.63 mV of sensor
    for k in range(20):
        u = c.step(0.0, e, 0.0)
        assert u == pytest.approx(K * e * (p.k_p + p.k_i * T * (k + 1)), rel=1e-12)


def test_pi_on_a_static_plant_has_no_steady_state_error():
    # a static plant y_k+1 = g u_k [m/V]; the loop z (z - 1) + g K ((k_p + k_i T) z - k_p) has
    # poles 0.972 and -0.406 for these values
    g = 1e-6
    c = PIController(PIParams(), T)
    c.reset(0.0, 0.0)
    y = 0.0
    for _ in range(4000):
        y = g * c.step(y, 5e-6, 0.0)
    assert y == pytest.approx(5e-6, abs=1e-15)


def test_pi_bumpless_reset_starts_at_the_held_voltage():
    c = PIController(PIParams(), T)
    c.reset(3.8e-6, 3.9e-6, output_v=1.29)
    assert c.step(3.8e-6, 3.9e-6, 0.0) == pytest.approx(1.29)


@pytest.mark.parametrize('anti_windup, stuck', [('conditional', False), ('none', True)])
def test_pi_anti_windup(anti_windup, stuck):
    c = PIController(PIParams(anti_windup=anti_windup), T)
    c.reset(0.0, 0.0)
    for _ in range(2000):                      # far below the reference: saturates at 10 V
        assert c.step(0.0, 30e-6, 0.0) == 10.0
        assert c.diagnostics()['saturated'] == 1.0
    # the reference drops below the position: the output must leave saturation at once
    # unless the integral wound up
    u = c.step(20e-6, 10e-6, 0.0)
    assert (u == 10.0) is stuck


def test_rac_anti_windup_holds_the_integral_while_saturated():
    c = RACController(RACParams(), T)
    c.reset(0.0, 0.0)
    c.step(0.0, 30e-6, 0.0)
    i0 = c.diagnostics()['integral_v_s']
    for _ in range(500):
        assert c.step(0.0, 30e-6, 0.0) == 10.0
    assert c.diagnostics()['integral_v_s'] == i0
    assert c.step(31e-6, 30e-6, 0.0) < 10.0   # leaves saturation as soon as the error reverses


# ---------------------------------------------------------------- edge-case contract


def _controllers():
    return [build_controller(ControllerParams(type=t, notch=n), T)
            for t in ('rac', 'pi', 'open_loop') for n in (NO_NOTCH, NotchParams())]


@pytest.mark.parametrize('ctrl', _controllers(), ids=lambda c: type(c).__name__)
def test_every_controller_implements_the_protocol(ctrl):
    assert isinstance(ctrl, Controller)
    assert ctrl.sample_time_s == T


@pytest.mark.parametrize('bad', [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize('where', [0, 1, 2])
@pytest.mark.parametrize('kind', ['rac', 'pi'])
def test_non_finite_input_holds_the_last_output_and_leaves_the_state(bad, where, kind):
    a = build_controller(ControllerParams(type=kind), T)
    b = build_controller(ControllerParams(type=kind), T)
    for c in (a, b):
        c.reset(3.8e-6, 3.8e-6)
    args = [3.81e-6, 3.8e-6, 1e-3]
    last = a.step(*args)
    b.step(*args)
    bad_args = list(args)
    bad_args[where] = bad
    assert a.step(*bad_args) == last
    assert a.diagnostics()['nonfinite_inputs'] == 1.0
    # the refused sample changed nothing: both continue identically
    assert a.step(3.79e-6, 3.8e-6, 0.0) == b.step(3.79e-6, 3.8e-6, 0.0)


def test_open_loop_refuses_a_non_finite_reference():
    c = OpenLoopController(ControllerParams().open_loop, T)
    c.reset(0.0, 0.0, output_v=1.0)
    assert c.step(0.0, math.nan, 0.0) == 1.0
    assert c.step(0.0, 3.8e-6, 0.0) == pytest.approx(3.8e-6 / (2.843e-6 * 1.0341))


def test_a_nan_first_sample_returns_the_held_or_zero_voltage():
    c = RACController(RACParams(), T)
    c.reset(3.8e-6, 3.8e-6, output_v=1.3)
    assert c.step(math.nan, 3.8e-6, 0.0) == 1.3
    c.reset(3.8e-6, 3.8e-6)
    assert c.step(math.nan, 3.8e-6, 0.0) == 0.0


@pytest.mark.parametrize('dt', [0.0, -1e-4, math.nan, math.inf])
@pytest.mark.parametrize('kind', ['rac', 'pi', 'open_loop'])
def test_bad_dt_holds_the_last_output(dt, kind):
    c = build_controller(ControllerParams(type=kind, notch=NO_NOTCH), T)
    c.reset(3.8e-6, 3.8e-6)
    last = c.step(3.81e-6, 3.8e-6, 0.0)
    assert c.step(3.9e-6, 3.8e-6, 0.0, dt_s=dt) == last
    assert c.diagnostics()['bad_dt'] == 1.0


def test_a_given_dt_scales_the_integral():
    a = PIController(PIParams(), T)
    b = PIController(PIParams(), T)
    a.reset(0.0, 0.0)
    b.reset(0.0, 0.0)
    a.step(0.0, 1e-8, 0.0, dt_s=2 * T)
    b.step(0.0, 1e-8, 0.0)
    b.step(0.0, 1e-8, 0.0)
    assert a.diagnostics()['integral_v_s'] == pytest.approx(b.diagnostics()['integral_v_s'])


@pytest.mark.parametrize('x', [1e300, -1e300, 1e-3, -1e-3])
def test_extreme_finite_inputs_give_a_finite_output_inside_the_limits(x):
    for c in _controllers():
        c.reset(0.0, 0.0)
        u = c.step(x, -x, x)
        assert math.isfinite(u) and -2.0 <= u <= 10.0


def test_bad_sample_time_is_refused():
    with pytest.raises(ParameterError, match="'sample_time_s' = 0"):
        build_controller(ControllerParams(), 0.0)


# ---------------------------------------------------------------- notch


def test_notch_has_unity_dc_gain_and_the_designed_depth_at_its_centre():
    w0, zz, zp = 2 * math.pi * 3166.0, 0.084, 1.0
    num, den = notch_coefficients(w0, zz, zp, T)

    def n_of(z):
        return (num[0] + num[1] / z + num[2] / z ** 2) / (den[0] + den[1] / z + den[2] / z ** 2)

    assert n_of(1.0) == pytest.approx(1.0)
    # pre-warped bilinear: N(e^{j w0 T}) = N(j w0) = zeta_z / zeta_p exactly
    assert n_of(cmath.exp(1j * w0 * T)) == pytest.approx(zz / zp)


def test_notch_filter_rests_at_a_constant_and_is_skipped_when_off():
    f = NotchFilter(*notch_coefficients(2 * math.pi * 3166.0, 0.084, 1.0, T))
    f.reset(1.3)
    assert [f.step(1.3) for _ in range(5)] == pytest.approx([1.3] * 5)
    assert isinstance(build_controller(ControllerParams(), T), NotchedController)
    assert isinstance(build_controller(ControllerParams(notch=NO_NOTCH), T), RACController)


def test_notch_from_the_model_finds_the_resonance_of_eq_20():
    omega, zeta = plant_resonance(third_order_plant(ThirdOrderParams()))
    assert omega == pytest.approx(19_900, rel=0.01)
    assert zeta == pytest.approx(0.084, abs=0.002)
    assert ControllerParams().notch.frequency_hz == pytest.approx(omega / (2 * math.pi), rel=1e-3)


def test_notch_from_a_model_without_resonance_is_refused():
    params = ControllerParams(notch=NotchParams(mode='model'))
    with pytest.raises(ParameterError, match="'notch.mode'.*reduced model has none"):
        build_controller(params, T, reduced_plant(ReducedParams()))
    with pytest.raises(ParameterError, match="'notch.mode'.*needs the plant model"):
        build_controller(params, T)


def test_notch_above_nyquist_is_refused():
    with pytest.raises(ParameterError, match="'notch.frequency_hz'"):
        build_controller(ControllerParams(notch=NotchParams(frequency_hz=6000.0)), T)


def test_the_notch_starts_at_rest_at_the_first_command():
    # a filter at rest at 0 V would pass a 1.3 V step at t = 0 and ring
    inner = build_controller(ControllerParams(notch=NO_NOTCH), T)
    notched = build_controller(ControllerParams(), T)
    for c in (inner, notched):
        c.reset(3.8e-6, 3.8e-6)
    assert notched.step(3.8e-6, 3.8e-6, 0.0) == pytest.approx(inner.step(3.8e-6, 3.8e-6, 0.0))


def test_rac_adaptation_is_frozen_while_the_command_saturates():
    p = RACParams(epsilon_v=0.01, gamma=1e5, eta=1.0)
    c = RACController(p, T)
    c.reset(0.0, 0.0)
    for _ in range(20):
        assert c.step(0.0, 30e-6, 0.0) == 10.0
    d = c.diagnostics()
    assert abs(d['s_v']) > p.epsilon_v
    assert (d['theta_hat'], d['phi_hat']) == (p.theta_init, p.phi_init)


def test_rac_gain_change_keeps_its_state_and_bounds():
    from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
    base = ControllerParams.from_flat({'type': 'rac', 'notch.mode': 'off',
                                       'rac.gamma': 1e6})
    ctrl = build_controller(base, 1e-4)
    ctrl.reset(3.8e-6, 3.8e-6)
    for _ in range(50):                        # a large error: adaptation moves theta_hat
        ctrl.step(3.8e-6, 6e-6, 0.0)
    moved = ctrl.diagnostics()
    assert moved['theta_hat'] != base.rac.theta_init
    tighter = base.with_flat({'rac.k_d': 0.5, 'rac.theta_max': 1.3, 'rac.theta_min': 1.28})
    assert ctrl.update_params(tighter)
    kept = ctrl.diagnostics()
    assert kept['integral_v_s'] == moved['integral_v_s']
    assert 1.28 <= kept['theta_hat'] <= 1.3            # clipped into the new box, (P1)
    assert kept['phi_hat'] == moved['phi_hat']
    # structural changes are refused, so the caller builds a new controller
    assert not ctrl.update_params(tighter.with_flat({'type': 'pi'}))
    assert not ctrl.update_params(tighter.with_flat({'output_max_v': 9.0}))


def test_pi_gain_change_is_bumpless_in_its_integral():
    from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
    base = ControllerParams.from_flat({'type': 'pi', 'notch.mode': 'off'})
    ctrl = build_controller(base, 1e-4)
    ctrl.reset(3.8e-6, 3.8e-6, output_v=1.3)        # holding the stage at rest
    held = ctrl.step(3.8e-6, 3.8e-6, 0.0)            # zero error: the integral holds 1.3 V
    assert held == pytest.approx(1.3, rel=1e-12)
    assert ctrl.update_params(base.with_flat({'pi.k_i': 500.0, 'pi.k_p': 4.0}))
    # the same zero error after the change: the command does not move
    assert ctrl.step(3.8e-6, 3.8e-6, 0.0) == pytest.approx(1.3, rel=1e-12)


def test_notched_controller_rebuilds_when_the_notch_changes():
    from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
    base = ControllerParams.from_flat({'type': 'rac'})
    ctrl = build_controller(base, 1e-4)
    assert ctrl.update_params(base.with_flat({'rac.k_d': 0.8}))
    assert not ctrl.update_params(base.with_flat({'notch.frequency_hz': 3000.0}))
