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

"""
The discrete adaptation loop of the RAC: the derived bound and the square-wave regression.

With the paper's rates (gamma = 3000, eta = 0.01) the Euler updates of theta_hat and phi_hat
close a discrete loop through the command that limit-cycles on the high plateau of Fig. 10
(theta_hat banging between 0.9 and 1.7, 1.2 um rms). The default rates keep the per-sample
gain T (gamma y_max^2 + eta (lambda y_max)^2) below half the critical gain the stability check
derives from the model; these tests fail with the paper's rates or with a dead zone as wide as
the boundary layer.
"""

import math
import warnings

import numpy as np
from piezo_stage_ros.core.control.controllers import ControllerParams, NotchParams
from piezo_stage_ros.core.control.stability import (
    adaptation_bound,
    ADAPTATION_MARGIN,
    check_stability,
    enforce,
    StabilityParams,
    StabilityWarning,
)
from piezo_stage_ros.core.loop import metrics
from piezo_stage_ros.core.loop.experiments import run_one
from piezo_stage_ros.core.loop.trajectories import TrajectoryParams
from piezo_stage_ros.core.model.linear import ReducedParams
from piezo_stage_ros.core.model.stage import PlantParams, StageParams
import pytest

T = 1e-4
PAPER_RATES = ControllerParams().with_flat({'rac.gamma': 3000.0, 'rac.eta': 0.01,
                                            'rac.normalisation': 0.0})


@pytest.mark.parametrize('model', ['reduced', 'third_order', 'electromechanical'])
def test_default_rates_are_within_half_the_critical_gain(model):
    bound = adaptation_bound(ControllerParams(), PlantParams(model=model), T)
    assert bound.critical_gain > 0.0 and math.isfinite(bound.critical_gain)
    assert bound.ok
    # the default's normalisation certifies every regressor size: g/(1 + kappa g) < 1/kappa
    assert bound.all_regressors and bound.normalisation * bound.critical_gain >= ADAPTATION_MARGIN
    assert bound.effective_gain * ADAPTATION_MARGIN <= bound.critical_gain
    # y_max: the largest output the -2 ... 10 V command holds, K g (c * 10 V + rho) ~ 7.9 V
    assert bound.y_max_v == pytest.approx(10 / 38e-6 * 2.843e-6 * (1.0341 * 10 + 0.18),
                                          rel=0.01)
    paper = adaptation_bound(PAPER_RATES, PlantParams(model=model), T)
    assert not paper.ok and paper.max_gamma() == 0.0   # eta = 0.01 alone is over the bound


def test_critical_gain_matches_the_state_space_loop_of_the_reduced_plant():
    # independent of the transfer functions: the 3-state linear loop (plant x, integral I,
    # command perturbation q of the adaptation) built by hand for the reduced plant, no notch,
    # one slope, the initial estimates; its spectral radius crosses 1 at g_crit
    params = ControllerParams(notch=NotchParams(mode='off'))
    opts = StabilityParams(estimates='initial', slope_points=1, slope_min=1.0, slope_max=1.0,
                           delay_samples=0.0)
    g_crit = adaptation_bound(params, PlantParams(model='reduced'), T,
                              options=opts).critical_gain
    r = params.rac
    matrix = _reduced_loop_matrix(params, 1.0, r.k_d, r.theta_init, r.phi_init)

    def radius(g: float) -> float:
        return float(np.max(np.abs(np.linalg.eigvals(matrix(g)))))

    # +-2 % of g_crit moves the spectral radius by far more than eigvals' rounding of a 3x3
    # matrix (~n eps kappa(V)), so the crossing is placed the same on any machine
    assert radius(0.98 * g_crit) < 1.0 < radius(1.02 * g_crit)


def test_report_and_enforce_warn_on_rates_above_the_bound():
    report = check_stability(PAPER_RATES, PlantParams(model='reduced'), T)
    assert report.stable                       # the frozen loops are fine: not in the verdict
    assert 'ABOVE g_crit/2' in report.text()
    with pytest.warns(StabilityWarning, match=r'Adaptation .* ABOVE g_crit/2'):
        enforce(report, 'refuse')              # a warning, not a refusal (see enforce)
    ok = check_stability(ControllerParams(), PlantParams(model='reduced'), T)
    assert 'within g_crit/2' in ok.text()
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        enforce(ok, 'refuse')


def _reduced_loop_matrix(params, slope, k, theta, phi):
    """
    Return g -> M(g), the hand-built 3-state adaptation loop of the reduced plant.

    State (x_k, I_k-1, q_k) of the reduced plant under the frozen RAC with gain k (k_d outside
    the boundary layer, k_d + k*/eps inside) and the adaptation's command perturbation q:
    y = K x, I = I_prev + T y, s = y + lambda I, v = -k s - phi lambda y + theta y + q,
    x' = alpha x + beta v, q' = q - g s.
    """
    r = params.rac
    red = ReducedParams()
    alpha = math.exp(-T / red.tau_s)
    beta = red.gain_m_per_v * (1.0 - alpha) * slope
    kk = params.sensor_gain_v_per_m

    def matrix(g):
        m = np.zeros((3, 3))
        for j in range(3):
            x, i_prev, q = np.eye(3)[j]
            y = kk * x
            i_now = i_prev + T * y
            s = y + r.lambda_per_s * i_now
            v = -k * s - phi * r.lambda_per_s * y + theta * y + q
            m[:, j] = (alpha * x + beta * v, i_now, q - g * s)
        return m

    return matrix


def _reduced_loop_polynomial(params, slope, k, theta, phi):
    """Return p0, p1 with det(zI - M(g)) = p0 + g p1 (only the q row of M depends on g)."""
    matrix = _reduced_loop_matrix(params, slope, k, theta, phi)
    p0 = np.poly(matrix(0.0))
    return p0, np.poly(matrix(1.0)) - p0


def _cubic_critical_gain(p0, p1):
    """
    Return the smallest g > 0 putting a root of z^3 + a z^2 + b z + c = p0 + g p1 on |z| = 1.

    Closed form: a root at z = +-1 makes p(+-1) = 0 (linear in g); a pair exp(+-j w) with a
    real root r makes p = (z - r)(z^2 - 2 cos(w) z + 1), i.e. c = -r, a = c - 2 cos(w) and
    b = 1 + a c - c^2, a quadratic in g, with |cos(w)| = |c - a|/2 <= 1.
    """
    roots = []
    for z in (1.0, -1.0):
        d = np.polyval(p1, z)
        if d != 0.0:
            roots.append(-np.polyval(p0, z) / d)
    (_, a0, b0, c0), (_, a1, b1, c1) = p0, p1
    # 1 - c^2 - b + a c = 0 with a = a0 + g a1, ...
    quad = [a1 * c1 - c1 * c1, a0 * c1 + a1 * c0 - 2 * c0 * c1 - b1,
            1.0 - c0 * c0 - b0 + a0 * c0]
    for g in np.roots(quad):
        if abs(g.imag) < 1e-12 * abs(g):
            g = g.real
            a, c = a0 + g * a1, c0 + g * c1
            if abs(c - a) <= 2.0:
                roots.append(g)
    # g = 0 is the adaptation's own integrator at z = 1 (p0(1) = 0): the crossing sought is
    # the first one of a loop that g > 0 has made stable
    return min(g for g in roots if g > 1e-9)


@pytest.mark.parametrize('dead_zone, regions', [(None, ('outside',)),
                                                (0.002, ('inside', 'outside'))])
def test_critical_gain_is_the_closed_form_of_the_reduced_plant_loop(dead_zone, regions):
    # one slope, the initial estimates, no notch, no delay: g_crit is the first g at which the
    # cubic's Schur-Cohn boundary is crossed, solved in closed form above; a dead zone narrower
    # than the boundary layer (None: equal to it) adds the region inside it (k = k_d + k*/eps)
    params = ControllerParams(notch=NotchParams(mode='off'))
    params = params.with_flat({'rac.adaptation_dead_zone_v': dead_zone if dead_zone is not None
                               else params.rac.epsilon_v})
    opts = StabilityParams(estimates='initial', slope_points=1, slope_min=1.0, slope_max=1.0,
                           delay_samples=0.0)
    bound = adaptation_bound(params, PlantParams(model='reduced'), T, options=opts)
    assert bound.regions == regions
    r = params.rac
    ks = {'outside': r.k_d, 'inside': r.k_d + r.k_star_v / r.epsilon_v}
    expected = min(_cubic_critical_gain(*_reduced_loop_polynomial(
        params, 1.0, ks[region], r.theta_init, r.phi_init)) for region in regions)
    # the bisection stops within a relative 1e-3 below the crossing
    assert expected * (1.0 - 2e-3) <= bound.critical_gain <= expected


def test_normalisation_bounds_the_effective_gain_for_every_regressor():
    base = ControllerParams().with_flat({'rac.gamma': 300.0, 'rac.eta': 1e-4,
                                         'rac.adaptation_dead_zone_v': 0.002,
                                         'rac.normalisation': 0.0})
    plain = adaptation_bound(base, PlantParams(model='third_order'), T)
    assert not plain.ok and plain.gain > plain.critical_gain      # far above at y_max
    kappa = ADAPTATION_MARGIN / plain.critical_gain
    for k, certified in ((1.01 * kappa, True), (0.5 * kappa, False)):
        b = adaptation_bound(base.with_flat({'rac.normalisation': k}),
                             PlantParams(model='third_order'), T)
        assert b.critical_gain == plain.critical_gain            # kappa is not in the loop
        assert b.effective_gain == pytest.approx(b.gain / (1.0 + k * b.gain), rel=1e-12)
        assert b.effective_gain < 1.0 / k
        assert b.all_regressors == certified
        assert b.ok == certified        # at y_max g is so large that g_eff ~ 1/kappa
        assert (b.max_gamma() == math.inf) == certified
        assert ('within g_crit/2 for every regressor size' in b.text()) == certified


def _square(model: str, low_m: float, high_m: float, period_s: float,
            periods: int) -> tuple[dict[str, float], np.ndarray, np.ndarray]:
    """Run the default RAC on a square wave; return its metrics, theta_hat, plateau p-p [m]."""
    tp = TrajectoryParams.from_flat({'kind': 'square', 'square.low_m': low_m,
                                     'square.peak_to_peak_m': high_m - low_m,
                                     'square.period_s': period_s})
    rec = run_one(StageParams.from_flat({'plant.model': model}), ControllerParams(), tp,
                  duration_s=periods * period_s)
    m = metrics.square_wave_metrics(rec.time_s, rec.position_m, rec.reference_m,
                                    period_s=period_s)
    theta = np.asarray(rec.diagnostics['theta_hat'])
    n_half = int(round(0.5 * period_s / T))
    err = rec.position_m - rec.reference_m
    # peak-to-peak of the error over the last half of every plateau
    pp = np.array([np.ptp(err[j * n_half + n_half // 2:(j + 1) * n_half])
                   for j in range(2 * periods)])
    return m, theta, pp


@pytest.mark.parametrize('model', ['reduced', 'third_order'])
@pytest.mark.parametrize('low_m, high_m, period_s, periods', [
    (3.8e-6, 11.6e-6, 0.5, 2),      # Fig. 10: 7.8 um, 0.5 s
    (3.8e-6, 28e-6, 0.1, 2),        # near the top of what -2 ... 10 V can hold (~29.9 um)
])
def test_default_rac_has_no_limit_cycle_on_a_square_wave(model, low_m, high_m, period_s,
                                                          periods):
    m, theta, pp = _square(model, low_m, high_m, period_s, periods)
    r = ControllerParams().rac
    # the paper's rates limit-cycle here, by about a micrometre on the plateaus (Fig. 10)
    assert m.ss_e_rms_m < 3e-9      # a few ADC steps (1.16 nm)
    assert m.ss_e_max_m < 10e-9
    assert np.max(pp) < 10e-9          # no oscillation left on any plateau
    # theta_hat moves on the edges but never reaches a bound (the paper's rates bang it between
    # both), and it ends within 5 % of the model's theta = 1/(K_PSCM g c) = 1.293
    assert r.theta_min < np.min(theta) and np.max(theta) < r.theta_max
    assert theta[-1] == pytest.approx(1.293, rel=0.05)


def _family_case(stage_name, case, *, noise_m=None, changes=None):
    """Run the default RAC (or with ``changes``) on one stage of the family; e_rms after 1 s."""
    from dataclasses import replace

    from piezo_stage_ros.core.loop.robustness import run_study
    from piezo_stage_ros.core.model.family import default_family
    member = next(m for m in default_family() if m.name == stage_name)
    if noise_m is not None:
        member = replace(member, noise_m=noise_m)
    params = ControllerParams().with_flat(changes or {})
    res = run_study(StageParams.from_flat({'plant.model': 'third_order'}), params,
                    TrajectoryParams(), family=[member], cases=[case], duration_s=2.0)
    return res.rows[0]


@pytest.mark.parametrize('stage, case, noise_m, limit_m', [
    ('gain_lo_tau_hi', 'sine_100', None, None),      # the design target: 1.5 x nominal
    ('gain_lo_tau_hi', 'sine_10', None, None),
    ('gain_hi_tau_lo', 'square', 3e-9, 5e-9),        # Fig. 10 plateau with 3 nm sensor noise
    ('gain_hi_wn_lo_zeta_lo', 'square_2ms', 3e-9, 5e-9),
])
def test_the_default_serves_the_worst_stages_of_the_family(stage, case, noise_m, limit_m):
    # the stages that bound the design (tune section 9): a slow low-gain stage needs the
    # estimates high, the high-gain stages near the resonance's limit need them kept off the
    # high-gain corner; one configuration, nothing retuned. On the sines the target is
    # relative: within 1.5 times the nominal stage's error on the same case; on the noisy
    # plateaus 3 nm of noise alone gives about 3.5 nm
    row = _family_case(stage, case, noise_m=noise_m)
    r = ControllerParams().rac
    if limit_m is None:
        limit_m = 1.5 * _family_case('nominal', case)['e_rms_m']
    assert row['e_rms_m'] < limit_m
    assert r.theta_min <= row['theta_hat_min'] and row['theta_hat_max'] <= r.theta_max
    assert r.phi_min <= row['phi_hat_min'] and row['phi_hat_max'] <= r.phi_max


def test_measured_regressors_drift_on_the_noisy_plateau_of_a_high_gain_stage():
    # the same stage and wave with the paper's regressors: e s_a > 0 on every edge and noise
    # burst raises phi_hat and with it k + lambda phi_hat - theta_hat; with the desired ones
    # phi_hat's regressor dy_d/dt is zero on an ideal square wave and it does not move. How
    # much error the drift costs depends on the margin the gains leave at the raised phi_hat
    # (tune section 9); here it is measured only as no better than the desired regressors
    r = ControllerParams().rac
    desired = _family_case('gain_hi_tau_lo', 'square', noise_m=3e-9)
    measured = _family_case('gain_hi_tau_lo', 'square', noise_m=3e-9,
                            changes={'rac.adaptation_regressor': 'measured'})
    assert desired['phi_hat_end'] == r.phi_init
    assert measured['phi_hat_end'] > 1.5 * r.phi_init
    assert measured['e_rms_m'] > desired['e_rms_m']
