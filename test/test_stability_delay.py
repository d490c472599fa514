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

"""The computational delay of the stability check, against the analytic first-order loop."""

import math

import numpy as np
from piezo_stage_ros.core.control.controllers import ControllerParams, NotchParams, PIParams
from piezo_stage_ros.core.control.stability import (
    _plant_tf,
    check_stability,
    StabilityParams,
)
from piezo_stage_ros.core.model.linear import reduced_plant, ReducedParams
from piezo_stage_ros.core.model.stage import PlantParams
import pytest

GAIN_M_PER_V = 2.843e-6
TAU_S = 2.445e-4
PLANT = PlantParams.from_flat({'model': 'reduced', 'reduced.gain_m_per_v': GAIN_M_PER_V,
                               'reduced.tau_s': TAU_S})
K_SENSOR = ControllerParams().sensor_gain_v_per_m
#: points of the unit circle, from 1e-3 of Nyquist to just below it
W = np.geomspace(1e-3, 0.999, 200) * math.pi
Z = np.exp(1j * W)


def response(num, den):
    return np.polyval(num, Z) / np.polyval(den, Z)


def first_order_delayed(delay, sample_time_s):
    """Return G(e^jw) of g/(tau s + 1) held from t_k + delay T: the modified z-transform."""
    m = math.floor(delay)
    frac = delay - m
    beta = math.exp(-sample_time_s / TAU_S)
    late = beta ** (1.0 - frac)
    return (GAIN_M_PER_V * ((1.0 - late) * Z + (late - beta)) / (Z * (Z - beta))
            * Z ** (-float(m)))


@pytest.mark.parametrize('delay', [0.0, 0.25, 0.5, 0.9, 1.0, 1.3, 2.75])
def test_fractional_delay_is_the_modified_z_transform_of_the_first_order_plant(delay):
    t = 1e-4
    num, den = _plant_tf(reduced_plant(ReducedParams()), t, delay)
    want = first_order_delayed(delay, t)
    # the matrix exponential and ss2tf of a 2-state model: errors near machine precision,
    # amplified by the conditioning of the polynomial evaluation near z = beta (|z - beta|
    # >= 1 - beta ~ 0.34), so 1e-9 of the gain is far above them
    assert np.max(np.abs(response(num, den) - want)) <= 1e-9 * GAIN_M_PER_V


def test_fractional_delay_reduces_to_the_integer_delays():
    t = 1e-4
    plant = reduced_plant(ReducedParams())
    g0 = response(*_plant_tf(plant, t, 0.0))
    # a delay of 1e-9 of a sample moves the held edge by 1e-9 T: the response changes by
    # at most about 1e-9 of its size (|dG/d delay| <= |G| (1 + T/tau) for this plant)
    assert np.max(np.abs(response(*_plant_tf(plant, t, 1e-9)) - g0)) <= 1e-8 * GAIN_M_PER_V
    below_one = response(*_plant_tf(plant, t, 1.0 - 1e-9))
    one = response(*_plant_tf(plant, t, 1.0))
    assert np.max(np.abs(one - g0 / Z)) <= 1e-9 * GAIN_M_PER_V
    assert np.max(np.abs(below_one - one)) <= 1e-8 * GAIN_M_PER_V
    two = response(*_plant_tf(plant, t, 2.0))
    assert np.max(np.abs(two - g0 / Z ** 2)) <= 1e-9 * GAIN_M_PER_V


def _p_control(loop_gain):
    """Return a proportional controller (PI without integral) of loop gain k_p K g."""
    return ControllerParams(type='pi', notch=NotchParams(mode='off'),
                            pi=PIParams(k_p=loop_gain / (K_SENSOR * GAIN_M_PER_V), k_i=0.0))


def _critical_delay(params, sample_time_s, hi=10.0):
    """Return the smallest delay [samples] the check finds unstable, by bisection."""
    def stable(d):
        opts = StabilityParams(delay_samples=d, slope_min=1.0, slope_max=1.0, slope_points=1)
        return check_stability(params, PLANT, sample_time_s, options=opts).stable
    lo = 0.0
    assert stable(lo) and not stable(hi)
    while hi - lo > 1e-4:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if stable(mid) else (lo, mid)
    return 0.5 * (lo + hi)


def _exact_critical_delay(loop_gain, sample_time_s):
    """Return the exact discrete boundary: roots of z^m z (z - beta) + L0 N(z) by bisection."""
    beta = math.exp(-sample_time_s / TAU_S)

    def radius(d):
        m = math.floor(d)
        late = beta ** (1.0 - (d - m))
        char = np.polyadd(np.r_[1.0, -beta, np.zeros(m + 1)],
                          loop_gain * np.r_[1.0 - late, late - beta])
        return np.max(np.abs(np.roots(char)))
    lo, hi = 0.0, 10.0
    while hi - lo > 1e-6:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if radius(mid) < 1.0 else (lo, mid)
    return 0.5 * (lo + hi)


@pytest.mark.parametrize('loop_gain, t', [(3.0, 2e-5), (5.0, 1e-5)])
def test_the_delay_boundary_of_a_first_order_loop_is_the_analytic_one(loop_gain, t):
    # the loop crosses over at omega_c T = sqrt(L0^2 - 1) T / tau <= 0.24 rad, where the
    # zero-order hold acts as half a sample of delay to O((omega_c T)^2); the margins are
    # 8-9 samples, inside the parameter's range
    found = _critical_delay(_p_control(loop_gain), t)
    # the exact discrete boundary of the same loop (modified z-transform), independently
    assert found == pytest.approx(_exact_critical_delay(loop_gain, t), abs=2e-4)
    # the continuous delay margin (pi - atan(omega_c tau)) / omega_c, less the hold's half
    # sample; the hold's gain (omega_c T)^2 / 24 <= 0.0024 moves the crossover and with it
    # the margin by about twice that, relatively: 1 % bounds the discretisation's share
    wc = math.sqrt(loop_gain ** 2 - 1.0) / TAU_S
    margin = (math.pi - math.atan(wc * TAU_S)) / wc / t - 0.5
    assert found == pytest.approx(margin, rel=0.01)


@pytest.mark.parametrize('model', ['reduced', 'third_order', 'electromechanical'])
def test_the_default_controller_passes_with_one_sample_of_computational_delay(model):
    # the default must hold on a target that applies each command at its next tick: every
    # frozen loop of the box stable, the adaptation within its bound, and the design rule's
    # margins (2 dB, 25 deg) on every sampled loop
    opts = StabilityParams(delay_samples=1.0)
    rep = check_stability(ControllerParams(), PlantParams(model=model), 1e-4, options=opts)
    assert rep.certified, rep.text()
    assert rep.gain_margin_db > 2.0 and rep.phase_margin_deg > 25.0
    assert rep.delay_samples == 1.0 and '1 sample of computational delay' in rep.text()


def test_the_default_delay_covers_the_in_process_servo():
    assert StabilityParams().delay_samples == 0.5
    rep = check_stability(ControllerParams(), PlantParams(model='third_order'), 1e-4)
    assert rep.certified and rep.delay_samples == 0.5


def test_the_words_printed_match_the_box_checked():
    params = ControllerParams()
    r = params.rac
    third = PlantParams(model='third_order')
    box = check_stability(params, third, 1e-4, options=StabilityParams(delay_samples=1.0))
    text = box.text()
    assert 'Frozen-parameter robust stability over the box' in text
    assert f'theta_hat in [{r.theta_min:g}, {r.theta_max:g}]' in text
    assert f'phi_hat in [{r.phi_min:g}, {r.phi_max:g}] s' in text
    assert 'Not proven: the running loop' in text
    assert 'certified' not in text.lower() and 'guarantee' not in text.lower()
    assert box.box.estimates == 'corners' and box.box.theta == (r.theta_min, r.theta_max)
    # the initial pair only: the sentence says so and names the box it left out
    one = check_stability(params, third, 1e-4, options=StabilityParams(estimates='initial'))
    text = one.text()
    assert 'Stable at the initial estimates only' in text
    assert f'theta_hat = {r.theta_init:g}, phi_hat = {r.phi_init:g} s' in text
    assert 'was NOT checked' in text and 'over the box:' not in text
    assert one.box.theta == (r.theta_init, r.theta_init)
    assert len(one.cases) == 2 * StabilityParams().slope_points
    # a controller without estimates: only the slopes are frozen
    pi = check_stability(ControllerParams(type='pi'), third, 1e-4)
    assert 'over the slopes' in pi.text() and 'theta_hat' not in pi.scope()
    # a failing box says NOT stable, with what was checked
    fast = params.replace(rac=r.replace(lambda_per_s=3000.0, epsilon_v=0.2))
    bad = check_stability(fast, third, 1e-4, options=StabilityParams(delay_samples=1.0))
    assert not bad.stable
    assert 'NOT stable over what was checked' in bad.text()
    assert 'NOT STABLE OVER THE BOX' in bad.text()


# -- the time-varying loop: a common quadratic Lyapunov function -----------------------------


def _vertices(params, plant, delay):
    from piezo_stage_ros.core.control import stability as st
    opts = StabilityParams(delay_samples=delay)
    _, _, g_num, g_den, notch = st._loop_parts(params, plant, 1e-4, opts)
    return st._vertex_matrices(params, g_num, g_den, notch, 1e-4, opts)


@pytest.mark.parametrize('delay', [0.0, 0.5, 1.0])
def test_the_vertex_matrices_are_the_frozen_loops_of_the_check(delay):
    # each vertex (a corner of k_p, each region, the end slopes) is a frozen loop the check
    # also samples: the same poles, from a state space instead of a polynomial
    params = ControllerParams()
    third = PlantParams(model='third_order')
    rep = check_stability(params, third, 1e-4, options=StabilityParams(delay_samples=delay))
    radii = [c.spectral_radius for c in rep.cases]
    for a in _vertices(params, third, delay):
        r = float(np.max(np.abs(np.linalg.eigvals(a))))
        # eigenvalues of an 8 x 8 matrix against polynomial roots: both ~1e-12 here
        assert min(abs(r - x) for x in radii) < 1e-8


def test_a_p_loop_has_a_common_lyapunov_function_exactly_when_every_vertex_is_stable():
    # P control of the reduced plant, no delay: one state, A = a - K b k_p slope, and
    # V = x^2 works for every sequence exactly when |A| < 1 at both slope ends
    from piezo_stage_ros.core.control.stability import varying_check
    red = ReducedParams()
    a = math.exp(-1e-4 / red.tau_s)
    kb = K_SENSOR * red.gain_m_per_v * (1.0 - a)
    kp = 10.0
    limit = (1.0 + a) / (kb * kp)
    params = ControllerParams(type='pi', notch=NotchParams(mode='off'),
                              pi=PIParams(k_p=kp, k_i=0.0))
    for top, ok in ((0.98 * limit, True), (1.02 * limit, False)):
        cert = varying_check(params, PlantParams(model='reduced'), 1e-4, options=StabilityParams(
            slope_min=0.5 * limit, slope_max=top, slope_points=2, delay_samples=0.0))
        assert cert.vertices == 2 and cert.found == ok
        assert cert.contraction == pytest.approx(abs(a - kb * kp * top), rel=1e-6)


def test_the_default_is_proven_for_the_time_varying_loop_at_the_default_delay():
    from piezo_stage_ros.core.control.stability import varying_check
    params = ControllerParams()
    third = PlantParams(model='third_order')
    cert = varying_check(params, third, 1e-4)
    assert cert.found and cert.vertices == 8 and cert.contraction < 1.0
    # what the certificate promises: every product of vertex matrices shrinks in the P-norm
    # by at most contraction^n, so its spectral radius is below that
    rng = np.random.default_rng(7)
    matrices = _vertices(params, third, 0.5)
    for _ in range(20):
        prod = np.eye(matrices[0].shape[0])
        for i in rng.integers(0, len(matrices), 40):
            prod = matrices[i] @ prod
        assert np.max(np.abs(np.linalg.eigvals(prod))) <= cert.contraction ** 40 * (1 + 1e-6)
    rep = check_stability(params, third, 1e-4, varying=True)
    assert rep.varying == cert
    assert 'Time-varying loop: a common quadratic Lyapunov function' in rep.text()
    assert 'Not proven: the loop while the command saturates' in rep.text()
