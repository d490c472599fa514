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
Commissioning a stage without leaving closed loop: excite, identify, design, certify, verify.

:func:`commission` runs the five steps on a (simulated) stage:

1. **Hold and excite.** A conservative PI (:func:`hold_controller`, no notch, certified on the
   configured model before anything runs) holds the stage at ``hold_m`` for ``settle_s``; then
   a periodic multisine (flat band, ``period_s``) plus a slow sine (one whole cycle per
   excitation period, for the hysteresis) is added to its reference for ``duration_s``. The
   loop is never opened; the reference never leaves ``hold_m +- max_excursion_m`` (checked
   over one whole period before the run, :class:`CommissionParams`).
2. **Identify** the excitation part of the run in closed loop with
   :func:`piezo_stage_ros.core.identification.support.identify_checked` (frequency response
   averaged over whole periods, its fit, the hysteresis, 95 % bounds; the refusals). The only
   support threshold commissioning changes is the input range the hysteresis pre-check asks
   for (``alpha_range_fraction``): an excitation of at most 1 um cannot span 0.5/alpha of
   input; whether alpha is determined is left to the post-fit check of its standard deviation,
   which stays.
3. **Design** on the identified model: the model-dependent controller values (the notch on the
   identified resonance, the RAC's estimate box and initial values scaled to the identified
   theta and phi, rho and k*, the slope range), given by the caller (``identify``'s
   ``controller_values``), on top of the configured controller; its feedback gains scaled by
   :func:`loop_gain_ratio` so that the loop gain on the identified stage is the one the
   configured tuning has on the configured stage; then the tunings of :data:`LADDER` in order,
   more conservative each, until one is certified (a step that fails only the RAC's adaptation
   bound is retried with the normalisation kappa the bound asks for).
4. **Certify** a tuning with :func:`piezo_stage_ros.core.control.stability.check_stability` on
   every corner of the box the 95 % bounds of (k_p, w_n, zeta, tau) span, with the hysteresis
   slope over [c (2 B1/c - 1), c] at the lower bound of B1/c: every corner must be certified
   (frozen loops and the adaptation bound). Corners are sampled; the plants inside the box
   between them are not certified (the slope and estimate directions are, by the edge theorem).
5. **Verify** on the stage: the Table III sine at ``verify_frequency_hz`` for
   ``verify_duration_s`` with the designed controller (a fresh run from rest, as ``tune``
   runs it), its e_rms over the steady-state window, and the same run on the identified
   model (what the design predicted).

A step that cannot go on raises :class:`CommissionRefusedError` with one line.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import itertools
import math
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError, PiezoStageError
from piezo_stage_ros.core.contracts.params import param, Params
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.control.controllers import (
    build_controller,
    ControllerParams,
    NotchParams,
    PIParams,
)
from piezo_stage_ros.core.control.stability import (
    ADAPTATION_MARGIN,
    check_stability,
    StabilityParams,
    StabilityReport,
)
from piezo_stage_ros.core.identification.fit import IdentificationParams
from piezo_stage_ros.core.identification.support import (
    CheckedIdentification,
    identify_checked,
    RefusedError,
    SupportParams,
)
from piezo_stage_ros.core.loop.closed_loop import Plant, run
from piezo_stage_ros.core.loop.metrics import summarize
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.family import true_estimates
from piezo_stage_ros.core.model.linear import factors_of, LinearFactors, third_order_of
from piezo_stage_ros.core.model.stage import linear_plant, Stage, StageParams
from piezo_stage_ros.core.signals.excitation import NoiseExcitation, NoiseParams

__all__ = ['CommissionParams', 'CommissionRefusedError', 'CommissionResult', 'Certification',
           'Design', 'Excitation', 'KAPPA_MARGIN', 'LADDER', 'Verification', 'certify',
           'checked_excitation', 'commission', 'commission_record', 'comparison',
           'corner_plants', 'design', 'excitation_part', 'excitation_run', 'excitation_table',
           'feedback_only',
           'hold_controller', 'identify_excitation', 'loop_gain_ratio', 'ros_overrides',
           'slope_range', 'summary', 'true_values', 'verification_failures', 'verify']

#: Called with one line of progress.
ProgressFn = Callable[[str], None]
#: Returns the controller_node values the identified stage determines (flat names).
DeriveFn = Callable[[StageParams], Mapping[str, Any]]

#: Builds the plant a run is made on from the stage parameters.
PlantFn = Callable[[StageParams], Plant]


class CommissionRefusedError(PiezoStageError):
    """Commissioning stopped: the data, the design or the verification do not support it."""


@dataclass(frozen=True)
class CommissionParams(Params):
    """Settings of the commissioning run: hold, excitation, hold controller, verification."""

    hold_m: float = param(5e-6, unit='m', description='Position held during the excitation '
                          '(a safe point inside the range).', low=0.0)
    settle_s: float = param(0.2, unit='s', description='Hold before the excitation starts '
                            '(the hold controller settles).', low=0.0, high=10.0)
    duration_s: float = param(3.0, unit='s', description='Length of the excitation.',
                              low=0.0, low_open=True, high=10.0)
    period_s: float = param(0.2, unit='s', description='Period of the excitation (multisine '
                            'and one slow-sine cycle); the run holds duration_s/period_s of '
                            'them, the first left out as the transient.', low=1e-3, high=5.0)
    multisine_rms_m: float = param(0.15e-6, unit='m', description='Rms of the multisine on the '
                                   'reference.', low=0.0)
    band_low_hz: float = param(20.0, unit='Hz', description='Lowest frequency of the '
                               'multisine band.', low=0.0, low_open=True)
    band_high_hz: float = param(4500.0, unit='Hz', description='Highest frequency of the '
                                'multisine band (above the resonance).', low=0.0, low_open=True)
    slow_amplitude_m: float = param(0.5e-6, unit='m', description='Amplitude of the slow sine '
                                    '(one cycle per period) that shows the hysteresis.', low=0.0)
    max_excursion_m: float = param(1e-6, unit='m', description='Largest distance of the '
                                   'reference from hold_m the excitation may reach.',
                                   low=0.0, low_open=True, high=1e-6)
    seed: int = param(3, unit='-', description='Seed of the multisine phases.', low=0)
    hold_k_p: float = param(0.5, unit='V/V', description='Proportional gain of the hold PI '
                            '(sensor volts).', low=0.0)
    hold_k_i: float = param(1500.0, unit='1/s', description='Integral gain of the hold PI.',
                            low=0.0, low_open=True)
    alpha_range_fraction: float = param(0.1, unit='-', description='Input range the hysteresis '
                                        'pre-check asks for, as a fraction of 1/alpha (the '
                                        'post-fit check of alpha stays).', low=0.0)
    verify_frequency_hz: float = param(100.0, unit='Hz', description='Frequency of the '
                                       'verification sine (Table III amplitude).', low=0.0,
                                       low_open=True)
    verify_duration_s: float = param(0.3, unit='s', description='Length of the verification '
                                     'run (the steady state after max(2 periods, 0.1 s)).',
                                     low=0.0, low_open=True, high=10.0)
    verify_max_m: float = param(35e-9, unit='m', description='Largest e_rms of the '
                                'verification accepted: 1.5 times what the default controller '
                                'gives on the nominal stage at 100 Hz.', low=0.0,
                                low_open=True)
    verify_max_ratio: float = param(1.5, unit='-', description='Largest e_rms of the '
                                    'verification on the stage accepted, as a multiple of '
                                    'what the identified model predicts with its sensor noise '
                                    '(sqrt(predicted^2 + noise^2)): a stage that tracks worse '
                                    'than its model says is not described by it.', low=1.0)

    def _check(self) -> None:
        if not self.band_low_hz < self.band_high_hz:
            raise ParameterError('band_high_hz', self.band_high_hz,
                                 f'> band_low_hz = {self.band_low_hz:g}')
        if self.duration_s < 2.0 * self.period_s:
            raise ParameterError('duration_s', self.duration_s,
                                 f'>= 2 period_s = {2.0 * self.period_s:g}',
                                 'holds fewer than two whole periods of the excitation')


# --------------------------------------------------------------------------------------------
# 1. Hold and excite


class Excitation:
    """
    The commissioning reference: hold, then hold + multisine + slow sine from ``settle_s``.

    Parameters
    ----------
    params : CommissionParams
        Hold, excitation and its timing.
    sample_rate_hz : float
        Loop rate [Hz] (the multisine is computed on a grid of twice it).

    Attributes
    ----------
    period_s : float
        Period of the excitation part [s].

    """

    kind = 'commission'

    def __init__(self, params: CommissionParams, sample_rate_hz: float) -> None:
        p = params
        self.params = p
        self.period_s = p.period_s
        self._noise = NoiseExcitation(NoiseParams(
            offset_m=0.0, amplitude_m=p.multisine_rms_m, band_low_hz=p.band_low_hz,
            band_high_hz=p.band_high_hz, period_s=p.period_s, grid_rate_hz=2.0 * sample_rate_hz,
            seed=p.seed))
        self._w = 2.0 * math.pi / p.period_s

    def excitation(self, time_s: Any) -> tuple[FloatArray, FloatArray]:
        """Return the excitation alone (no hold, no gate) and its derivative at ``time_s``."""
        t = np.asarray(time_s, dtype=np.float64)
        a = self.params.slow_amplitude_m
        pos, vel = self._noise.evaluate(t)
        return pos + a * np.sin(self._w * t), vel + a * self._w * np.cos(self._w * t)

    def evaluate(self, time_s: Any) -> tuple[FloatArray, FloatArray]:
        """Return the reference and its derivative at ``time_s`` (t = 0: start of the hold)."""
        t = np.asarray(time_s, dtype=np.float64)
        on = t >= self.params.settle_s - 1e-12
        pos, vel = self.excitation(t - self.params.settle_s)
        return (np.where(on, self.params.hold_m + pos, self.params.hold_m),
                np.where(on, vel, 0.0))

    def peak_m(self, sample_time_s: float) -> float:
        """Return the largest |reference - hold| over one whole period, at the samples [m]."""
        t = np.arange(int(round(self.period_s / sample_time_s))) * sample_time_s
        return float(np.max(np.abs(self.excitation(t)[0])))


def checked_excitation(params: CommissionParams, sample_rate_hz: float) -> Excitation:
    """
    Return the excitation after checking that it stays within ``max_excursion_m`` of the hold.

    Parameters
    ----------
    params : CommissionParams
        Hold and excitation.
    sample_rate_hz : float
        Loop rate [Hz].

    Returns
    -------
    Excitation

    Raises
    ------
    ParameterError
        If the reference leaves ``hold_m +- max_excursion_m`` at a sample.

    """
    exc = Excitation(params, sample_rate_hz)
    peak = exc.peak_m(1.0 / sample_rate_hz)
    if peak > params.max_excursion_m:
        raise ParameterError('multisine_rms_m', params.multisine_rms_m,
                             f'a reference within {params.max_excursion_m * 1e6:g} um of the '
                             'hold', f'with slow_amplitude_m = {params.slow_amplitude_m:g} takes '
                             f'the reference {peak * 1e6:.3g} um from the hold')
    return exc


def hold_controller(params: CommissionParams, configured: ControllerParams) -> ControllerParams:
    """
    Return the conservative controller that holds the stage during the excitation.

    Parameters
    ----------
    params : CommissionParams
        Its gains.
    configured : ControllerParams
        The configured controller (sensor gain, output range).

    Returns
    -------
    ControllerParams
        A PI (``hold_k_p``, ``hold_k_i``) without notch: its low gain keeps the resonance far
        below 0 dB on any plausible stage, and its proportional path puts the excitation on
        the command up to the resonance; no feed-forward (the configured one is designed on
        the model being identified).

    """
    return feedback_only(configured).replace(
        type='pi', pi=PIParams(k_p=params.hold_k_p, k_i=params.hold_k_i),
        notch=NotchParams(mode='off'))


def feedback_only(controller: ControllerParams) -> ControllerParams:
    """
    Return ``controller`` without its feed-forward.

    The hold and the verification run the feedback alone: the excitation must reach the
    command unshaped, and the acceptance limits of the verification are those of a feedback
    design on a sine, whatever feed-forward the stage will later scan with.
    """
    return controller.replace(feedforward=controller.feedforward.replace(mode='none'))


def excitation_run(true_stage: StageParams, configured: StageParams,
                   configured_controller: ControllerParams, params: CommissionParams,
                   stability: StabilityParams | None = None, *,
                   plant: PlantFn | None = None) -> tuple[RunRecord, RunRecord,
                                                          StabilityReport]:
    """
    Hold the stage under the hold controller and excite it; never open the loop.

    Parameters
    ----------
    true_stage : StageParams
        The stage that runs (simulated).
    configured : StageParams
        The configured stage (the hold controller is checked on it).
    configured_controller : ControllerParams
        The configured controller (sensor gain, output range).
    params : CommissionParams
        The run.
    stability : StabilityParams, optional
        Options of the check of the hold controller.
    plant : callable, optional
        Builds the plant that runs from ``true_stage`` (default
        :class:`~piezo_stage_ros.core.model.stage.Stage`), e.g. one axis of a multi-axis stage.

    Returns
    -------
    whole : RunRecord
        Hold and excitation.
    excited : RunRecord
        The excitation part (from ``settle_s``), time from 0, its period in the meta.
    hold_check : StabilityReport
        The hold controller on the configured model.

    Raises
    ------
    CommissionRefusedError
        If the hold controller is not stable on the configured model.
    ParameterError
        If the excitation leaves ``hold_m +- max_excursion_m``.

    """
    t = true_stage.sample_time_s
    exc = checked_excitation(params, true_stage.sample_rate_hz)
    hold = hold_controller(params, configured_controller)
    opts = stability or StabilityParams()
    check = check_stability(hold, configured.plant, t, options=opts)
    if not check.stable:
        raise CommissionRefusedError('the hold controller is not stable on the configured '
                                     'model: ' + check.binding())
    ctrl = build_controller(hold, t, None)
    whole = run((plant or Stage)(true_stage), ctrl, exc,
                duration_s=params.settle_s + params.duration_s,
                initial_position_m=params.hold_m, record_diagnostics=False,
                meta={'name': 'commission_excitation', 'experiment': 'commission'})
    i0 = int(round(params.settle_s / t))
    excited = RunRecord(whole.time_s[i0:] - whole.time_s[i0], whole.position_m[i0:],
                        whole.reference_m[i0:], whole.reference_velocity_mps[i0:],
                        whole.command_v[i0:],
                        meta={'name': 'commission_excitation', 'sample_time_s': t,
                              'trajectory_period_s': params.period_s})
    return whole, excited, check


def identify_excitation(excited: RunRecord, configured: StageParams,
                        params: CommissionParams) -> CheckedIdentification:
    """
    Identify the stage from the excitation run, in closed loop, with bounds.

    Parameters
    ----------
    excited : RunRecord
        The excitation part of the run.
    configured : StageParams
        The configured stage (signal chain, where the resonance and corner are expected).
    params : CommissionParams
        ``alpha_range_fraction``.

    Returns
    -------
    CheckedIdentification

    Raises
    ------
    CommissionRefusedError
        With the refusals joined on one line.

    """
    try:
        return identify_checked([excited], configured, IdentificationParams(), closed_loop=True,
                                support=SupportParams(
                                    alpha_range_fraction=params.alpha_range_fraction))
    except RefusedError as exc:
        raise CommissionRefusedError('the excitation cannot support the model: '
                                     + '; '.join(exc.lines)) from exc


def excitation_table(params: CommissionParams, sample_rate_hz: float
                     ) -> tuple[FloatArray, FloatArray]:
    """
    Return the commissioning reference at every sample, for a trajectory table (``csv``).

    Parameters
    ----------
    params : CommissionParams
        Hold and excitation.
    sample_rate_hz : float
        Loop rate of the nodes [Hz].

    Returns
    -------
    time_s, position_m : ndarray
        Samples k T for k = 0 ... (settle_s + duration_s) / T: at the loop's sample times the
        table's piecewise-linear interpolation gives the samples themselves, so the reference
        the nodes run repeats exactly as offline.

    Raises
    ------
    ParameterError
        As :func:`checked_excitation`.

    """
    exc = checked_excitation(params, sample_rate_hz)
    t_s = 1.0 / sample_rate_hz
    n = int(round((params.settle_s + params.duration_s) / t_s))
    t = np.arange(n + 1) * t_s
    return np.asarray(t, dtype=np.float64), exc.evaluate(t)[0]


def ros_overrides(params: CommissionParams, table_path: str) -> dict[str, dict[str, Any]]:
    """
    Return the node parameters that run the hold and excitation on the ROS nodes.

    Parameters
    ----------
    params : CommissionParams
        Hold controller and hold position.
    table_path : str
        The CSV of :func:`excitation_table`.

    Returns
    -------
    dict
        ``{node name: {flat name: value}}``: the controller node runs the hold PI without notch,
        the trajectory node the table, the plant (a simulated one) starts at the hold.

    """
    return {'controller_node': {'type': 'pi', 'pi.k_p': params.hold_k_p,
                                'pi.k_i': params.hold_k_i, 'notch.mode': 'off'},
            'trajectory_node': {'kind': 'csv', 'csv.path': table_path},
            'plant_node': {'initial_position_m': params.hold_m}}


# --------------------------------------------------------------------------------------------
# 3, 4. Design and certify


@dataclass(frozen=True)
class Certification:
    """
    The stability check of one controller over the corners of the identified bounds.

    Attributes
    ----------
    certified : bool
        Every corner certified (frozen loops and adaptation bound).
    corners : int
        Plants checked.
    failed : tuple of str
        The corners that fail, with what binds.
    gain_margin_db, phase_margin_deg : float
        Smallest over every corner (closest to 0).
    slope_range : tuple of float
        Hysteresis slopes covered.
    nominal : StabilityReport
        The check on the identified model itself.
    loops_stable : bool
        Every frozen loop of every plant stable (the adaptation bound aside).
    critical_gain : float
        Smallest g_crit of the RAC's adaptation loop over the plants (inf for a PI).

    """

    certified: bool
    corners: int
    failed: tuple[str, ...]
    gain_margin_db: float
    phase_margin_deg: float
    slope_range: tuple[float, float]
    nominal: StabilityReport
    loops_stable: bool = True
    critical_gain: float = math.inf


def corner_plants(stage: StageParams, bounds: Mapping[str, tuple[float, float]]
                  ) -> list[tuple[str, StageParams]]:
    """
    Return the stages at the corners of the (k_p, w_n, zeta, tau) bounds, with a label each.

    Parameters
    ----------
    stage : StageParams
        The identified stage (its hysteresis slope c converts the static-gain bounds).
    bounds : Mapping
        95 % bounds; a quantity without bounds stays at its identified value.

    Returns
    -------
    list of (str, StageParams)

    Raises
    ------
    CommissionRefusedError
        If a bound is not positive.

    """
    f = factors_of(stage.plant.third_order)
    c = stage.hysteresis.backlash_like.c
    k = bounds.get('static_gain_m_per_v')
    ranges = {
        'k_p': (k[0] / c, k[1] / c) if k is not None else (f.gain_m_per_v,),
        'w_n': bounds.get('omega_n_rad_s', (f.omega_n_rad_s,)),
        'zeta': bounds.get('zeta', (f.zeta,)),
        'tau': bounds.get('tau_s', (f.tau_s,)),
    }
    out = []
    for values in itertools.product(*ranges.values()):
        if min(values) <= 0.0:
            raise CommissionRefusedError(
                'the identified bounds reach a non-positive value ('
                + ', '.join(f'{n} {v:.4g}' for n, v in zip(ranges, values))
                + '): too wide to certify a controller')
        label = ', '.join(f'{n} {v:.5g}' for n, v in zip(ranges, values))
        plant = stage.plant.replace(third_order=third_order_of(LinearFactors(*values)))
        out.append((label, stage.replace(plant=plant)))
    return out


def slope_range(stage: StageParams, bounds: Mapping[str, tuple[float, float]]
                ) -> tuple[float, float]:
    """
    Return the incremental slopes of the identified hysteresis, its bounds included.

    Parameters
    ----------
    stage : StageParams
        The identified stage (backlash-like hysteresis).
    bounds : Mapping
        95 % bounds (``b1_over_c``).

    Returns
    -------
    slope_min, slope_max : float
        c (2 B1/c - 1) at the lower bound of B1/c, and c.

    """
    bl = stage.hysteresis.backlash_like
    low = bounds.get('b1_over_c', (bl.b1 / bl.c, bl.b1 / bl.c))[0]
    return max(bl.c * (2.0 * low - 1.0), 1e-6), bl.c


def certify(controller: ControllerParams, stage: StageParams,
            bounds: Mapping[str, tuple[float, float]], options: StabilityParams,
            progress: ProgressFn | None = None) -> Certification:
    """
    Check a controller on every corner of the identified bounds.

    Parameters
    ----------
    controller : ControllerParams
        The designed controller (its notch fixed, manual).
    stage : StageParams
        The identified stage.
    bounds : Mapping
        Its 95 % bounds.
    options : StabilityParams
        Options of the check (estimates, delay); the slope range is replaced.
    progress : callable, optional
        Told how far the check is.

    Returns
    -------
    Certification

    """
    lo, hi = slope_range(stage, bounds)
    opts = options.replace(slope_min=lo, slope_max=hi)
    t = stage.sample_time_s
    nominal = check_stability(controller, stage.plant, t, options=opts)
    corners = corner_plants(stage, bounds)
    failed = []
    gms, pms = [nominal.gain_margin_db], [nominal.phase_margin_deg]
    reports = [nominal]
    for i, (label, plant_stage) in enumerate(corners):
        rep = check_stability(controller, plant_stage.plant, t, options=opts)
        reports.append(rep)
        gms.append(rep.gain_margin_db)
        pms.append(rep.phase_margin_deg)
        if not rep.certified:
            failed.append(f'{label}: {rep.binding()}')
        if progress is not None and (i + 1) % 4 == 0:
            progress(f'certify: {i + 1}/{len(corners)} corners checked')
    if not nominal.certified:
        failed.insert(0, f'identified model: {nominal.binding()}')
    crit = [r.adaptation.critical_gain for r in reports if r.adaptation is not None]
    return Certification(certified=not failed, corners=len(corners) + 1, failed=tuple(failed),
                         gain_margin_db=min(gms, key=abs), phase_margin_deg=min(pms, key=abs),
                         slope_range=(lo, hi), nominal=nominal,
                         loops_stable=all(r.stable for r in reports),
                         critical_gain=min(crit, default=math.inf))


#: The tunings tried in order on the identified model: (label, changes of the RAC gains as
#: factors on the configured k_d and epsilon; of the PI gains as a factor on both), after the
#: gains are scaled to keep the configured loop gain (:func:`loop_gain_ratio`). Each is more
#: conservative than the one before (less proportional gain inside the boundary layer). When a
#: step's frozen loops are stable everywhere but the RAC's adaptation bound is not, the step is
#: tried again with the normalisation kappa the bound asks for (:data:`KAPPA_MARGIN` times
#: ADAPTATION_MARGIN / g_crit, g_crit the smallest over the plants): g_crit does not depend on
#: kappa, and with it the bound holds for every regressor size.
LADDER: tuple[tuple[str, float, float], ...] = (
    ('configured loop gain', 1.0, 1.0),
    ('boundary layer x2', 1.0, 2.0),
    ('k_d x0.5, boundary layer x4', 0.5, 4.0),
)


#: Factor on the smallest normalisation kappa that holds the adaptation bound.
KAPPA_MARGIN = 1.25


def loop_gain_ratio(identified: StageParams, configured: StageParams) -> float:
    """
    Return the factor on the feedback gains that keeps the configured tuning's loop gain.

    Parameters
    ----------
    identified, configured : StageParams
        The identified and the configured stage.

    Returns
    -------
    float
        theta(identified) / theta(configured) = (g c)_configured / (g c)_identified, with
        theta = 1/(K_PSCM g c) (:func:`piezo_stage_ros.core.model.family.true_estimates`): the
        loop gain from the controller's sensor-volt error to the position is proportional to
        g c, so the feedback gains scale inversely.

    """
    return true_estimates(identified)[0] / true_estimates(configured)[0]


def _step(controller: ControllerParams, kd_factor: float, eps_factor: float, ratio: float
          ) -> ControllerParams:
    if controller.type == 'rac':
        r = controller.rac
        # k_d and the gain inside the boundary layer, k*/epsilon, scale with the loop gain;
        # k* itself stays (it covers the hysteresis' disturbance, in command volts)
        return controller.replace(rac=r.replace(k_d=r.k_d * kd_factor * ratio,
                                                epsilon_v=r.epsilon_v * eps_factor / ratio))
    scale = ratio * kd_factor / eps_factor
    return controller.replace(pi=controller.pi.replace(k_p=controller.pi.k_p * scale,
                                                       k_i=controller.pi.k_i * scale))


@dataclass(frozen=True)
class Design:
    """
    The controller designed on the identified model.

    Attributes
    ----------
    controller : ControllerParams
        The certified controller.
    label : str
        Which step of :data:`LADDER` it is.
    derived : dict
        The model-dependent controller_node values (flat), ``stability.*`` included.
    certification : Certification
    tried : tuple of (str, Certification)
        Every step tried, in order.

    """

    controller: ControllerParams
    label: str
    derived: dict[str, Any]
    certification: Certification
    tried: tuple[tuple[str, Certification], ...]


def design(stage: StageParams, bounds: Mapping[str, tuple[float, float]],
           configured: ControllerParams, derived: Mapping[str, Any], options: StabilityParams,
           progress: ProgressFn | None = None, *, ratio: float = 1.0) -> Design:
    """
    Put the notch and gains on the identified model and keep the first certified tuning.

    Parameters
    ----------
    stage : StageParams
        The identified stage.
    bounds : Mapping
        Its 95 % bounds.
    configured : ControllerParams
        The configured controller (its type and gains are the start).
    derived : Mapping
        Model-dependent controller_node values for ``stage`` (``identify``'s
        ``controller_values``); ``stability.*`` names go to the check, the others onto the
        controller.
    options : StabilityParams
        The configured check (estimates, delay).
    progress : callable, optional
        Told each step and how far the certification is.
    ratio : float
        Factor on the feedback gains (:func:`loop_gain_ratio`).

    Returns
    -------
    Design

    Raises
    ------
    CommissionRefusedError
        If no tuning of :data:`LADDER` is certified over the bounds.

    """
    if configured.type == 'open_loop':
        raise CommissionRefusedError('the configured controller is open loop: commissioning '
                                     'designs a feedback controller (configure type rac or pi)')
    own = {k: v for k, v in derived.items() if not k.startswith('stability.')}
    flat = dict(configured.to_flat())
    flat.update(own)
    # the notch sits on the identified resonance, fixed: a model-mode notch would follow every
    # plant the certification checks
    flat['notch.mode'] = 'manual'
    start = ControllerParams.from_flat(flat)
    tried = []
    for label, kd, eps in LADDER:
        ctrl = _step(start, kd, eps, ratio)
        if progress is not None:
            progress(f'design: {label}')
        cert = certify(ctrl, stage, bounds, options, progress)
        tried.append((label, cert))
        if (not cert.certified and cert.loops_stable and ctrl.type == 'rac'
                and 0.0 < cert.critical_gain < math.inf):
            kappa = KAPPA_MARGIN * ADAPTATION_MARGIN / cert.critical_gain
            if kappa > ctrl.rac.normalisation:
                ctrl = ctrl.replace(rac=ctrl.rac.replace(normalisation=kappa))
                label = f'{label}, kappa {kappa:.3g} (adaptation bound)'
                if progress is not None:
                    progress(f'design: {label}')
                cert = certify(ctrl, stage, bounds, options, progress)
                tried.append((label, cert))
        if cert.certified:
            return Design(controller=ctrl, label=label, derived=dict(derived),
                          certification=cert, tried=tuple(tried))
    first, last = tried[0], tried[-1]
    raise CommissionRefusedError(
        f'no tuning is certified over the identified bounds ({len(tried)} tried): '
        f'{first[0]} fails at {first[1].failed[0]}; {last[0]} at {last[1].failed[0]}')


# --------------------------------------------------------------------------------------------
# 5. Verify


@dataclass(frozen=True)
class Verification:
    """
    The verification track on the stage and on the identified model.

    Attributes
    ----------
    frequency_hz : float
    e_rms_m, e_max_m : float
        On the stage (or, without one, on the identified model), steady-state window [m].
    predicted_e_rms_m : float
        The same run on the identified model without sensor noise [m].
    record : RunRecord
        The run behind ``e_rms_m``.
    on_stage : bool
        False when no stage was at hand (a recorded run): ``e_rms_m`` is the model's.

    """

    frequency_hz: float
    e_rms_m: float
    e_max_m: float
    predicted_e_rms_m: float
    record: RunRecord
    on_stage: bool = True


def _track(stage: StageParams, controller: ControllerParams, design_stage: StageParams,
           frequency_hz: float, duration_s: float, plant: PlantFn | None = None) -> RunRecord:
    ctrl = build_controller(feedback_only(controller), stage.sample_time_s,
                            linear_plant(design_stage.plant))
    traj = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine',
                                                       'sine.frequency_hz': frequency_hz}))
    return run((plant or Stage)(stage), ctrl, traj, duration_s=duration_s,
               record_diagnostics=False,
               meta={'name': f'verification_{frequency_hz:g}hz'})


def verify(true_stage: StageParams | None, identified: StageParams,
           controller: ControllerParams, params: CommissionParams,
           plant: PlantFn | None = None, model_plant: PlantFn | None = None) -> Verification:
    """
    Run the verification sine on the stage and on the identified model.

    Parameters
    ----------
    true_stage : StageParams or None
        The stage; None runs the identified model with its sensor noise in its place.
    identified : StageParams
        The identified model (the controller's design model).
    controller : ControllerParams
        The designed controller.
    params : CommissionParams
        Frequency and length.
    plant : callable, optional
        Builds the plant of ``true_stage`` (as :func:`excitation_run`).
    model_plant : callable, optional
        Builds the plant of the prediction from the identified model without sensor noise
        (default the one-axis stage): the conditions ``plant`` puts the stage in (e.g. the other
        axes of a multi-axis stage holding), on the model.

    Returns
    -------
    Verification

    """
    f, d = params.verify_frequency_hz, params.verify_duration_s
    rec = _track(true_stage or identified, controller, identified, f, d,
                 plant if true_stage is not None else None)
    m = summarize(rec, period_s=1.0 / f)
    model = identified.replace(chain=identified.chain.replace(sensor_noise_std_m=0.0))
    pred = summarize(_track(model, controller, identified, f, d, model_plant),
                     period_s=1.0 / f)
    return Verification(frequency_hz=f, e_rms_m=m.e_rms_m, e_max_m=m.e_max_m,
                        predicted_e_rms_m=pred.e_rms_m, record=rec,
                        on_stage=true_stage is not None)


def verification_failures(ver: Verification, params: CommissionParams,
                          noise_std_m: float) -> list[str]:
    """
    Return why a verification is not accepted (empty when it is).

    Two limits: ``verify_max_m`` on the error itself, which catches a design that tracks
    poorly; and, on a stage, ``verify_max_ratio`` times what the identified model predicts with
    the identified sensor noise added in quadrature, which catches a model that does not
    describe the stage (the design and its certificate rest on that model).

    Parameters
    ----------
    ver : Verification
        The verification run.
    params : CommissionParams
        The limits.
    noise_std_m : float
        Identified sensor noise [m], which the stage's error carries and the prediction not.

    Returns
    -------
    list of str

    """
    failed = []
    if not ver.e_rms_m <= params.verify_max_m:
        failed.append(f'verification e_rms {ver.e_rms_m * 1e9:.1f} nm exceeds verify_max_m = '
                      f'{params.verify_max_m * 1e9:g} nm')
    expected = math.hypot(ver.predicted_e_rms_m, noise_std_m)
    if ver.on_stage and not ver.e_rms_m <= params.verify_max_ratio * expected:
        failed.append(f'verification e_rms {ver.e_rms_m * 1e9:.1f} nm exceeds verify_max_ratio '
                      f'= {params.verify_max_ratio:g} times what the identified model gives, '
                      f'{expected * 1e9:.2f} nm (prediction {ver.predicted_e_rms_m * 1e9:.2f} '
                      f'nm, sensor noise {noise_std_m * 1e9:.2f} nm): the model does not '
                      'describe the stage')
    return failed


# --------------------------------------------------------------------------------------------
# The workflow


@dataclass
class CommissionResult:
    """
    Everything a person reviews before using the commissioned parameters.

    Attributes
    ----------
    identified : StageParams
        The identified stage (the loop rate of the run).
    checked : CheckedIdentification
    design : Design
    verification : Verification
    whole, excited : RunRecord
        The hold-and-excitation run and its excitation part.
    hold_check : StabilityReport or None
        The hold controller on the configured model (None for a recorded run).
    excitation_peak_m : float
        Largest |reference - hold| of the excitation [m].
    position_peak_m : float
        Largest |position - hold| measured during the excitation [m].
    accepted : bool
        Certified, and the verification within ``verify_max_m`` and, on a stage, within
        ``verify_max_ratio`` of the identified model's prediction.
    notes : list of str
    refused : list of str
        Why the verification is not accepted (:func:`verification_failures`; also in
        ``notes``); empty when it is.

    """

    identified: StageParams
    checked: CheckedIdentification
    design: Design
    verification: Verification
    whole: RunRecord
    excited: RunRecord
    hold_check: StabilityReport | None
    excitation_peak_m: float
    position_peak_m: float
    accepted: bool
    notes: list[str] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)


def commission(true_stage: StageParams, configured: StageParams,
               configured_controller: ControllerParams, derive: DeriveFn,
               params: CommissionParams | None = None, *,
               stability: StabilityParams | None = None,
               progress: ProgressFn | None = None,
               plant: PlantFn | None = None,
               model_plant: PlantFn | None = None) -> CommissionResult:
    """
    Commission a stage: hold and excite, identify, design, certify, verify.

    Parameters
    ----------
    true_stage : StageParams
        The stage that runs (simulated; its own loop rate).
    configured : StageParams
        The configured stage (signal chain; the hold controller's check; the prior of the
        identification).
    configured_controller : ControllerParams
        The configured controller: its type and gains are the start of the design.
    derive : callable
        The model-dependent controller_node values of an identified stage (``identify``'s
        ``controller_values`` with the configured controller as reference).
    params : CommissionParams, optional
        Hold, excitation, hold controller, verification; default :class:`CommissionParams`.
    stability : StabilityParams, optional
        The configured stability check (estimates, delay).
    progress : callable, optional
        Told each step.
    plant : callable, optional
        Builds the plant of ``true_stage`` for the runs (as :func:`excitation_run`).
    model_plant : callable, optional
        Builds the verification's prediction plant from the identified model (as
        :func:`verify`).

    Returns
    -------
    CommissionResult

    Raises
    ------
    CommissionRefusedError
        One line: why the stage cannot be commissioned from this run.

    """
    params, opts, say = _or_defaults(params, stability, progress)
    say(f'hold {params.hold_m * 1e6:g} um for {params.settle_s:g} s, then excite for '
        f'{params.duration_s:g} s (PI k_p {params.hold_k_p:g}, k_i {params.hold_k_i:g})')
    whole, excited, hold_check = excitation_run(true_stage, configured, configured_controller,
                                                params, opts, plant=plant)
    return _finish(whole, excited, hold_check, true_stage, configured, configured_controller,
                   derive, params, opts, say, plant, model_plant)


def excitation_part(record: RunRecord) -> RunRecord:
    """
    Return the part of a recorded commissioning run from the first move of its reference.

    Parameters
    ----------
    record : RunRecord
        Hold, then excitation (e.g. a bag of ``launch/commission.launch.py``).

    Returns
    -------
    RunRecord
        From the first sample whose reference differs from the first one, time from 0.

    Raises
    ------
    CommissionRefusedError
        If the reference never moves.

    """
    r = np.asarray(record.reference_m, dtype=np.float64)
    moved = np.flatnonzero(r != r[0]) if r.size else np.zeros(0, dtype=np.intp)
    if moved.size == 0:
        raise CommissionRefusedError('the recorded run has no excitation: its reference '
                                     'never leaves the hold')
    i0 = int(moved[0])
    meta = {k: v for k, v in record.meta.items() if k != 'trajectory_period_s'}
    return RunRecord(record.time_s[i0:] - record.time_s[i0], record.position_m[i0:],
                     r[i0:], record.reference_velocity_mps[i0:], record.command_v[i0:],
                     meta=meta)


def commission_record(record: RunRecord, configured: StageParams,
                      configured_controller: ControllerParams, derive: DeriveFn,
                      params: CommissionParams | None = None, *,
                      stability: StabilityParams | None = None,
                      progress: ProgressFn | None = None) -> CommissionResult:
    """
    Commission from a recorded hold-and-excitation run: identify, design, certify, verify.

    Parameters
    ----------
    record : RunRecord
        The run (the nodes with the overrides of :func:`ros_overrides`, recorded).
    configured, configured_controller, derive, params, stability, progress
        As :func:`commission`; the hold is the run's first reference.

    Returns
    -------
    CommissionResult
        Verified on the identified model (no stage at hand): run the nodes with the parameter
        file to verify on the stage.

    Raises
    ------
    CommissionRefusedError
        One line: why the stage cannot be commissioned from this run.

    """
    params, opts, say = _or_defaults(params, stability, progress)
    excited = excitation_part(record)
    params = params.replace(hold_m=float(record.reference_m[0]))
    return _finish(record, excited, None, None, configured, configured_controller, derive,
                   params, opts, say)


def _or_defaults(params: CommissionParams | None, stability: StabilityParams | None,
                 progress: ProgressFn | None
                 ) -> tuple[CommissionParams, StabilityParams, ProgressFn]:
    """Return the options of a commissioning run, the defaults where one is not given."""
    return (params or CommissionParams(), stability or StabilityParams(),
            progress or (lambda _line: None))


def _finish(whole: RunRecord, excited: RunRecord, hold_check: StabilityReport | None,
            true_stage: StageParams | None, configured: StageParams,
            configured_controller: ControllerParams, derive: DeriveFn,
            params: CommissionParams, opts: StabilityParams,
            say: ProgressFn, plant: PlantFn | None = None,
            model_plant: PlantFn | None = None) -> CommissionResult:
    """Identify, design, certify and verify from the excitation part of a run."""
    exc_peak = float(np.max(np.abs(excited.reference_m - params.hold_m)))
    pos_peak = float(np.max(np.abs(excited.position_m - params.hold_m)))
    # a recorded run ran at the configured rate of the nodes
    rate = (true_stage or configured).sample_rate_hz
    say('identify in closed loop')
    checked = identify_excitation(excited, configured, params)
    result = checked.result
    identified = result.stage.replace(sample_rate_hz=rate)
    if identified.hysteresis.model != 'backlash_like':
        raise CommissionRefusedError('commissioning certifies the backlash-like hysteresis '
                                     f'only (identified: {identified.hysteresis.model})')
    shown = result.factors.delay_samples
    longer = shown > opts.delay_samples
    if longer:
        # the run shows a longer loop delay than the configured check assumes: certify at it
        opts = opts.replace(delay_samples=shown)
    say('design on the identified model, certify over its bounds')
    des = design(identified, result.bounds, configured_controller, derive(identified), opts,
                 say, ratio=loop_gain_ratio(identified, configured))
    say(f'verify: {params.verify_frequency_hz:g} Hz sine for {params.verify_duration_s:g} s')
    ver = verify(true_stage, identified, des.controller, params, plant, model_plant)
    notes = list(checked.warnings) + list(result.notes)
    if longer:
        notes.append(f'certified at the loop delay the run shows ({shown:.3g} samples), '
                     'longer than the configured stability.delay_samples')
    failed = verification_failures(ver, params, identified.chain.sensor_noise_std_m)
    accepted = des.certification.certified and not failed
    notes.extend(failed)
    if true_stage is None:
        notes.append(f'recorded run at {rate:.0f} Hz: the verification ran on the identified '
                     'model; verify on the stage by running the nodes with the parameter file')
    return CommissionResult(identified=identified, checked=checked, design=des,
                            verification=ver, whole=whole, excited=excited,
                            hold_check=hold_check, excitation_peak_m=exc_peak,
                            position_peak_m=pos_peak, accepted=accepted, notes=notes,
                            refused=failed)


def summary(result: CommissionResult, true_stage: StageParams | None = None) -> dict[str, Any]:
    """
    Return the JSON-ready summary of a commissioning run.

    Parameters
    ----------
    result : CommissionResult
        The run.
    true_stage : StageParams, optional
        The simulated stage, for a recovered-vs-true section.

    Returns
    -------
    dict

    """
    res = result.checked.result
    s = res.summary()
    cert = result.design.certification
    ver = result.verification
    out: dict[str, Any] = {
        'accepted': result.accepted,
        'excitation': {'duration_s': result.excited.time_s.size
                       * result.identified.sample_time_s,
                       'reference_peak_m': result.excitation_peak_m,
                       'position_peak_m': result.position_peak_m,
                       'loop': 'closed throughout (hold PI)',
                       'hold_controller_check': None if result.hold_check is None
                       else result.hold_check.text()},
        'identified': {k: float(v) for k, v in s.items()},
        'bounds_95': {k: [float(lo), float(hi)] for k, (lo, hi) in res.bounds.items()},
        'design': {'tuning': result.design.label,
                   'tried': [{'tuning': label, 'certified': c.certified,
                              'failed': list(c.failed)} for label, c in result.design.tried],
                   'derived': dict(result.design.derived)},
        'certification': {'certified': cert.certified, 'plants': cert.corners,
                          'slope_range': list(cert.slope_range),
                          'gain_margin_db': cert.gain_margin_db,
                          'phase_margin_deg': cert.phase_margin_deg,
                          'delay_samples': cert.nominal.delay_samples,
                          'identified_model': cert.nominal.text()},
        'verification': {'frequency_hz': ver.frequency_hz, 'on_stage': ver.on_stage,
                         'e_rms_m': ver.e_rms_m,
                         'e_max_m': ver.e_max_m, 'predicted_e_rms_m': ver.predicted_e_rms_m},
        'notes': list(result.notes),
    }
    if true_stage is not None:
        out['true'] = true_values(true_stage)
    return out


def true_values(stage: StageParams) -> dict[str, float]:
    """Return the identified quantities of a (simulated) stage, named as the summary names them."""
    f = factors_of(stage.plant.third_order)
    bl = stage.hysteresis.backlash_like
    return {'static_gain_m_per_v': f.gain_m_per_v * bl.c, 'omega_n_rad_s': f.omega_n_rad_s,
            'zeta': f.zeta, 'tau_s': f.tau_s, 'alpha': bl.alpha, 'b1_over_c': bl.b1 / bl.c}


def comparison(result: CommissionResult, true_stage: StageParams,
               names: Sequence[str] = ('static_gain_m_per_v', 'omega_n_rad_s', 'tau_s', 'zeta',
                                       'alpha')) -> dict[str, tuple[float, bool]]:
    """
    Return the relative error of each identified quantity and whether its bounds hold the truth.

    Parameters
    ----------
    result : CommissionResult
        The run.
    true_stage : StageParams
        The simulated stage.
    names : sequence of str
        Quantities compared (names of the identification's summary and bounds).

    Returns
    -------
    dict
        Name -> (estimate / truth - 1, truth inside the 95 % bounds).

    """
    s = result.checked.result.summary()
    truth = true_values(true_stage)
    bounds = result.checked.result.bounds
    out = {}
    for name in names:
        est = s['b1'] / s['c'] if name == 'b1_over_c' else s[name]
        lo, hi = bounds.get(name, (math.nan, math.nan))
        out[name] = (est / truth[name] - 1.0, bool(lo <= truth[name] <= hi))
    return out
