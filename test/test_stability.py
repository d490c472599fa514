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
from piezo_stage_ros.core.controllers import ControllerParams, NotchParams, PIParams, RACParams
from piezo_stage_ros.core.errors import ParameterError, StabilityError
from piezo_stage_ros.core.linear import reduced_plant, ReducedParams
from piezo_stage_ros.core.stability import (
    check_stability,
    enforce,
    StabilityParams,
    StabilityWarning,
)
from piezo_stage_ros.core.stage import PlantParams
from piezo_stage_ros.tune import PAPER_RAC
import pytest

T = 1e-4
REDUCED = PlantParams(model='reduced')
THIRD = PlantParams(model='third_order')
NO_NOTCH = NotchParams(mode='off')
PAPER_PI = ControllerParams(type='pi', notch=NO_NOTCH)


def test_paper_pi_is_unstable_on_the_paper_third_order_model():
    rep = check_stability(PAPER_PI, THIRD, T)
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
    # the design rule of docs/controllers.md: at least 3 dB and 35 deg on every loop
    assert rep.gain_margin_db > 3.0 and rep.phase_margin_deg > 35.0


def test_the_notch_is_what_makes_the_default_rac_stable_on_the_third_order_model():
    rep = check_stability(ControllerParams(notch=NO_NOTCH), THIRD, T)
    assert not rep.stable
    assert check_stability(ControllerParams(notch=NO_NOTCH), REDUCED, T).stable


def test_p_only_loop_on_the_reduced_model_matches_the_analytic_pole_and_gain_margin():
    kp, slope = 2.0, 1.0
    d = reduced_plant(ReducedParams()).discretize(T)
    ad, gd = float(d.ad[0, 0]), float(d.c[0] * d.bd[0, 0])   # G(z) = gd / (z - ad)
    k = ControllerParams().sensor_gain_v_per_m
    opts = StabilityParams(slope_min=slope, slope_max=slope, slope_points=1)
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
    base = check_stability(PAPER_PI, REDUCED, T)
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
