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

"""Stability check of the linearized discrete-time loop, against analytic answers."""

import math
import warnings

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError, StabilityError
from piezo_stage_ros.core.control.controllers import (
    ControllerParams,
    NotchParams,
    PIParams,
    RACParams,
)
from piezo_stage_ros.core.control.stability import (
    _edge_crossing,
    _polytope_failure,
    check_stability,
    enforce,
    StabilityParams,
    StabilityWarning,
)
from piezo_stage_ros.core.model.linear import reduced_plant, ReducedParams
from piezo_stage_ros.core.model.stage import PlantParams
from piezo_stage_ros.tune import PAPER_RAC
import pytest

T = 1e-4
REDUCED = PlantParams(model='reduced')
THIRD = PlantParams(model='third_order')
NO_NOTCH = NotchParams(mode='off')
PAPER_PI = ControllerParams(type='pi', notch=NO_NOTCH)
#: the loop as the offline runner closes it: u_k applied at t_k (the analytic answers below)
NO_DELAY = StabilityParams(delay_samples=0.0)


def test_paper_pi_is_unstable_on_the_paper_third_order_model():
    rep = check_stability(PAPER_PI, THIRD, T, options=NO_DELAY)
    assert not rep.stable
    assert rep.spectral_radius > 1.0
    assert 'UNSTABLE' in rep.text() and 'third_order' in rep.text()
    # the escaping pole oscillates near the 3.2 kHz resonance
    pole = rep.worst.poles[np.argmax(np.abs(rep.worst.poles))]
    assert abs(np.angle(pole)) / (2 * math.pi * T) == pytest.approx(2900, rel=0.1)


def test_paper_pi_is_stable_on_the_reduced_model():
    rep = check_stability(PAPER_PI, REDUCED, T)
    assert rep.stable
    assert rep.gain_margin_db > 6.0 and rep.phase_margin_deg > 45.0
    assert rep.text().startswith('PI on the reduced model at 10000 Hz: STABLE')


def test_paper_rac_epsilon_chatters_in_discrete_time():
    # k_d + k*/eps = 41.5 inside the boundary layer: a pole near z = -13 on the reduced model
    rep = check_stability(ControllerParams(type='rac', rac=PAPER_RAC, notch=NO_NOTCH), REDUCED, T)
    assert not rep.stable
    assert rep.worst.poles[np.argmax(np.abs(rep.worst.poles))].real < -1.0


@pytest.mark.parametrize('plant', [REDUCED, THIRD, PlantParams(model='electromechanical')],
                         ids=lambda p: p.model)
def test_default_rac_is_stable_on_every_model_at_every_corner(plant):
    rep = check_stability(ControllerParams(), plant, T)
    assert rep.stable, rep.text()
    # (4 corners + the initial estimates) x 2 regions x 5 slopes
    assert len(rep.cases) == 50
    # the design rule of docs/explanation/controllers.md: the whole box certified, and at least 2.5
    # dB and 25 deg on every sampled loop (lower than a narrow box would give: the family needs
    # theta_hat up to 2 and phi_hat up to 9e-4, and the box's corner theta_min, phi_max, which
    # no stage has, sets these margins)
    assert all(c.certified for c in rep.certificates)
    assert rep.gain_margin_db > 2.5 and rep.phase_margin_deg > 25.0


def test_the_notch_is_what_makes_the_default_rac_stable_on_the_third_order_model():
    rep = check_stability(ControllerParams(notch=NO_NOTCH), THIRD, T)
    assert not rep.stable
    assert check_stability(ControllerParams(notch=NO_NOTCH), REDUCED, T).stable


def test_p_only_loop_on_the_reduced_model_matches_the_analytic_pole_and_gain_margin():
    kp, slope = 2.0, 1.0
    d = reduced_plant(ReducedParams()).discretize(T)
    ad, gd = float(d.ad[0, 0]), float(d.c[0] * d.bd[0, 0])   # G(z) = gd / (z - ad)
    k = ControllerParams().sensor_gain_v_per_m
    opts = StabilityParams(slope_min=slope, slope_max=slope, slope_points=1, delay_samples=0.0)
    rep = check_stability(ControllerParams(type='pi', pi=PIParams(k_p=kp, k_i=0.0),
                                           notch=NO_NOTCH), REDUCED, T, options=opts)
    (case,) = rep.cases
    # a first-order loop: its one pole from the eigensolver is within a few eps (relative) of
    # the scalar formula on any machine; approx's default 1e-6 is far above that
    assert case.poles == pytest.approx([ad - kp * k * slope * gd])
    # the only phase crossover is at Nyquist, z = -1: L(-1) = -kp K gd / (1 + ad)
    assert case.gain_margin_db == pytest.approx(
        20 * math.log10((1 + ad) / (kp * k * slope * gd)), abs=1e-6)


def test_an_obviously_unstable_gain_is_reported_and_refused_or_warned():
    params = ControllerParams(type='pi', pi=PIParams(k_p=100.0, k_i=1500.0), notch=NO_NOTCH)
    rep = check_stability(params, REDUCED, T)
    assert not rep.stable
    assert rep.gain_margin_db < 0.0
    text = rep.text()
    assert 'UNSTABLE' in text and 'lower the feedback gain' in text
    with pytest.raises(StabilityError, match='UNSTABLE'):
        enforce(rep, 'refuse')
    with pytest.warns(StabilityWarning, match='UNSTABLE'):
        assert enforce(rep, 'warn') == text


def test_enforce_is_silent_on_a_stable_loop_and_checks_its_action():
    rep = check_stability(PAPER_PI, REDUCED, T)
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        assert enforce(rep, 'refuse') == rep.text()
    with pytest.raises(ParameterError, match="'stability.action' = 'ignore'"):
        enforce(rep, 'ignore')


def test_a_computational_delay_costs_margin():
    base = check_stability(PAPER_PI, REDUCED, T, options=NO_DELAY)
    delayed = check_stability(PAPER_PI, REDUCED, T, options=StabilityParams(delay_samples=1))
    assert delayed.gain_margin_db < base.gain_margin_db
    assert delayed.phase_margin_deg < base.phase_margin_deg


def test_initial_estimates_only_is_a_subset_of_the_corners():
    opts = StabilityParams(estimates='initial')
    rep = check_stability(ControllerParams(), THIRD, T, options=opts)
    assert len(rep.cases) == 2 * 5
    assert rep.stable


def test_open_loop_is_as_stable_as_the_plant():
    rep = check_stability(ControllerParams(type='open_loop'), THIRD, T)
    assert rep.stable and math.isinf(rep.gain_margin_db)


def test_stability_options_are_validated():
    with pytest.raises(ParameterError, match="'slope_max'"):
        StabilityParams(slope_min=1.0, slope_max=0.9)
    assert StabilityParams().slopes() == pytest.approx(np.linspace(0.8843, 1.0341, 5))
    with pytest.raises(ParameterError, match="'stability.action'"):
        StabilityParams.from_flat({'stability.action': 'shrug'}, prefix='stability.')
    with pytest.raises(ParameterError, match="'sample_time_s'"):
        check_stability(PAPER_PI, REDUCED, -1.0)


def test_a_larger_rac_estimate_box_is_checked_and_can_fail():
    # the paper's bounds allow phi_hat lambda = 7.5 of proportional gain: unstable corners
    wide = ControllerParams(rac=RACParams(phi_min=1e-4, phi_max=5e-3, theta_min=0.5,
                                          theta_max=4.0))
    assert not check_stability(wide, REDUCED, T).stable
    assert check_stability(wide, REDUCED, T,
                           options=StabilityParams(estimates='initial')).stable


def _circle(n=4096):
    return np.exp(1j * np.linspace(0.0, math.pi, n + 2)[1:-1])


@pytest.mark.parametrize('f0, f1, t, w', [
    ([1.0, -0.5], [1.0, -1.5], 0.5, 0.0),              # z = 0.5 + t reaches z = 1 at t = 0.5
    ([1.0, 0.5], [1.0, 1.5], 0.5, math.pi),            # z = -(0.5 + t) reaches z = -1
    ([1.0, 0.0, 0.5], [1.0, 0.0, 1.5], 0.5, math.pi / 2),   # z^2 + c: |z| = 1 at c = 1, z = j
    ([1.0, 0.0, 0.25], [1.0, 0.0, 0.81], None, None),  # stays inside
])
def test_edge_crossing_finds_the_analytic_crossing(f0, f1, t, w):
    hit = _edge_crossing(np.array(f0), np.array(f1), _circle())
    if t is None:
        assert hit is None
    else:
        # linear interpolation between grid points 7.7e-4 rad apart
        assert hit == pytest.approx((t, w), abs=1e-3)


def test_a_segment_of_stable_cubics_can_be_unstable_inside_and_is_caught():
    # two Schur-stable cubics whose midpoint is not: sampling the vertices is not enough
    f0 = np.real(np.poly([-0.8, 0.9 * np.exp(2.8j), 0.9 * np.exp(-2.8j)]))
    f1 = np.real(np.poly([0.8, 0.8 * np.exp(0.1j), 0.8 * np.exp(-0.1j)]))
    assert max(abs(np.roots(f0))) < 1.0 and max(abs(np.roots(f1))) < 1.0
    radii = [max(abs(np.roots((1 - t) * f0 + t * f1))) for t in np.linspace(0.0, 1.0, 201)]
    assert max(radii) > 1.0
    failure = _polytope_failure([('f0', f0), ('f1', f1)], _circle(), T)
    assert failure is not None and 'between f0 and f1' in failure
    # the first crossing it reports is where the dense sampling first leaves the disc
    t_hit = float(failure.split('t = ')[1].split(')')[0])
    t_first = np.linspace(0.0, 1.0, 201)[np.argmax(np.array(radii) >= 1.0)]
    assert t_first - 0.005 - 1e-3 <= t_hit <= t_first + 1e-3
    assert _polytope_failure([('f0', f0), ('f0 again', f0 * 1.0)], _circle(), T) is None


def test_the_certificate_covers_every_slope_between_the_sampled_ones():
    # P control of the reduced plant: pole a - K b slope k_p, unstable for
    # slope > (1 + a)/(K b k_p); sample only the two ends, both stable, with the limit between
    # them impossible (a P loop is stable on an interval of slopes), so both agree; then push
    # the upper end over: the sampled check and the certificate both refuse
    red = ReducedParams()
    a = math.exp(-T / red.tau_s)
    kb = PAPER_PI.sensor_gain_v_per_m * red.gain_m_per_v * (1.0 - a)
    kp = 10.0
    limit = (1.0 + a) / (kb * kp)
    params = ControllerParams(type='pi', pi=PIParams(k_p=kp, k_i=0.0), notch=NO_NOTCH)
    for top, ok in ((0.999 * limit, True), (1.001 * limit, False)):
        rep = check_stability(params, REDUCED, T, options=StabilityParams(
            slope_min=0.5 * limit, slope_max=top, slope_points=2, delay_samples=0.0))
        assert all(c.certified for c in rep.certificates) == ok
        assert rep.stable == ok


def test_the_paper_rac_on_model_20_is_refused_and_names_the_binding_constraint():
    paper = ControllerParams(type='rac', rac=PAPER_RAC, notch=NO_NOTCH)
    rep = check_stability(paper, THIRD, T)
    assert not rep.stable and not rep.certified
    assert 'Binding constraint: the frozen loops' in rep.text() and 'UNSTABLE' in rep.text()
    with pytest.raises(StabilityError):
        enforce(rep, 'refuse')
    # default: both constraints hold; the report says which is closer to its limit
    ok = check_stability(ControllerParams(), THIRD, T)
    assert ok.certified
    assert all(c.certified for c in ok.certificates) and len(ok.certificates) == 2
    assert 'Binding constraint:' in ok.text()


def test_config_rac_paper_is_the_paper_law_and_is_refused_on_model_20():
    from piezo_stage_ros.core.config.loader import find_config, load_config
    config = load_config([find_config('default.yaml'), find_config('rac_paper.yaml')])
    flat = {k: v for k, v in config.node('controller_node').items()
            if k.split('.')[0] in ('type', 'rac', 'notch')}
    params = ControllerParams.from_flat(flat)
    assert params.rac == PAPER_RAC and params.notch.mode == 'off'
    rep = check_stability(params, THIRD, T)
    assert not rep.stable
    assert not rep.adaptation.ok        # kappa = 0: the paper's rates are far above the bound
    with pytest.raises(StabilityError):
        enforce(rep, 'refuse')
