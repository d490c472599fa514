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
The paper's identification experiments, run open loop on a (simulated) stage.

Three runs, all in amplifier volts through the ``open_loop`` controller (v = gain x_d) so that
they are exactly the runs ``simulate --controller open_loop`` makes and the ROS nodes can stream:

- ``noise``: small-amplitude band-limited white noise (:class:`~piezo_stage_ros.core.excitation.
  NoiseExcitation`), for the frequency response;
- ``step``: a train of small steps (the ``square`` trajectory), for the transient response;
- ``sine``: 1 + sin(2 pi 100 t) V (the ``sine`` trajectory), for the hysteresis.

The plan is written in volts; the trajectories get metres through the open-loop gain, and the
recorded ``command_v`` are the volts again. :func:`perturbed_stage` draws a stage with parameters
perturbed from the paper's (the test cases of the identification).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any

import numpy as np
from piezo_stage_ros.core.closed_loop import run
from piezo_stage_ros.core.controllers import OpenLoopController, OpenLoopParams
from piezo_stage_ros.core.excitation import NoiseExcitation, NoiseParams
from piezo_stage_ros.core.identification import factors_of, LinearFactors, third_order_of
from piezo_stage_ros.core.interfaces import Trajectory
from piezo_stage_ros.core.params import param, Params
from piezo_stage_ros.core.record import RunRecord
from piezo_stage_ros.core.stage import Stage, StageParams
from piezo_stage_ros.core.trajectories import (
    make_trajectory,
    SineParams,
    SquareParams,
    TrajectoryParams,
)

__all__ = ['ExperimentPlan', 'perturbed_stage', 'run_experiments']


@dataclass(frozen=True)
class ExperimentPlan:
    """
    Amplitudes and lengths of the three identification runs (volts, seconds).

    Attributes
    ----------
    sample_rate_hz : float
        Rate of the identification runs (the paper: 20 kHz).
    noise_offset_v, noise_rms_v : float
        Mean and rms of the noise run [V].
    noise_band_hz : tuple of float
        Flat band of the noise [Hz].
    noise_duration_s : float
    step_low_v, step_height_v : float
        Low level and height of the step train [V] (the paper's Fig. 5: a 1 V step).
    step_period_s : float
        Period of the step train (one step up and one down) [s].
    step_duration_s : float
    sine_offset_v, sine_amplitude_v, sine_frequency_hz : float
        The paper's 1 + sin(2 pi 100 t) V.
    sine_duration_s : float
    noise_seed : int
        Seed of the noise realization.

    """

    sample_rate_hz: float = 20000.0
    noise_offset_v: float = 1.3
    noise_rms_v: float = 0.1
    noise_band_hz: tuple[float, float] = (5.0, 6000.0)
    noise_duration_s: float = 0.5
    step_low_v: float = 1.0
    step_height_v: float = 1.0
    step_period_s: float = 0.012
    step_duration_s: float = 0.048
    sine_offset_v: float = 1.0
    sine_amplitude_v: float = 1.0
    sine_frequency_hz: float = 100.0
    sine_duration_s: float = 0.06
    noise_seed: int = 1


def _trajectories(plan: ExperimentPlan, gain_m_per_v: float) -> dict[str, Trajectory]:
    g = gain_m_per_v
    noise = NoiseExcitation(NoiseParams(
        offset_m=plan.noise_offset_v * g, amplitude_m=plan.noise_rms_v * g,
        band_low_hz=plan.noise_band_hz[0], band_high_hz=plan.noise_band_hz[1],
        period_s=plan.noise_duration_s, grid_rate_hz=2.0 * plan.sample_rate_hz,
        seed=plan.noise_seed))
    square = make_trajectory(TrajectoryParams(kind='square', square=SquareParams(
        low_m=plan.step_low_v * g, peak_to_peak_m=plan.step_height_v * g,
        period_s=plan.step_period_s, duty=0.5)))
    sine = make_trajectory(TrajectoryParams(kind='sine', sine=SineParams(
        offset_m=plan.sine_offset_v * g, amplitude_m=plan.sine_amplitude_v * g,
        frequency_hz=plan.sine_frequency_hz)))
    return {'noise': noise, 'step': square, 'sine': sine}


def run_experiments(stage_params: StageParams, plan: ExperimentPlan | None = None, *,
                    open_loop_gain_m_per_v: float | None = None) -> dict[str, RunRecord]:
    """
    Run the three identification experiments open loop on a simulated stage.

    Parameters
    ----------
    stage_params : StageParams
        The (true) stage; its ``sample_rate_hz`` is replaced by the plan's.
    plan : ExperimentPlan, optional
        Amplitudes and durations; default :class:`ExperimentPlan`.
    open_loop_gain_m_per_v : float, optional
        Metres of trajectory per volt of command (any positive value: the recorded commands are
        the plan's volts); default the nominal static gain of the paper's stage.

    Returns
    -------
    dict of str to RunRecord
        ``'noise'``, ``'step'`` and ``'sine'`` runs; ``meta`` names the experiment and the
        identification role, and holds the true stage parameters (flat).

    """
    plan = plan or ExperimentPlan()
    g = open_loop_gain_m_per_v or 2.843e-6 * 1.0341
    params = stage_params.replace(sample_rate_hz=plan.sample_rate_hz)
    durations = {'noise': plan.noise_duration_s, 'step': plan.step_duration_s,
                 'sine': plan.sine_duration_s}
    roles = {'noise': 'frequency', 'step': 'step', 'sine': 'hysteresis'}
    out: dict[str, RunRecord] = {}
    for i, (name, traj) in enumerate(_trajectories(plan, g).items()):
        # each run on a fresh stage at rest where the nominal model puts the first command
        stage = Stage(params.replace(seed=params.seed + i))
        first = float(traj.evaluate(np.zeros(1))[0][0])
        controller = OpenLoopController(OpenLoopParams(gain_v_per_m=1.0 / g),
                                        params.sample_time_s)
        meta: dict[str, Any] = {'name': name, 'identification_role': roles[name],
                                'experiment': name, 'controller': 'open_loop',
                                'true_stage': params.to_flat()}
        out[name] = run(stage, controller, traj, duration_s=durations[name],
                        initial_position_m=min(max(first, 0.0), 38e-6),
                        record_diagnostics=False, meta=meta)
    return out


@dataclass(frozen=True)
class Perturbation(Params):
    """Relative changes of the paper's parameters (0.1 = +10 %)."""

    gain: float = param(0.0, unit='-', description='Change of k_p.', low=-0.5, high=0.5)
    omega_n: float = param(0.0, unit='-', description='Change of w_n.', low=-0.5, high=0.5)
    zeta: float = param(0.0, unit='-', description='Change of zeta.', low=-0.5, high=0.5)
    tau: float = param(0.0, unit='-', description='Change of tau.', low=-0.5, high=0.5)
    alpha: float = param(0.0, unit='-', description='Change of alpha.', low=-0.5, high=0.5)
    c: float = param(0.0, unit='-', description='Change of c.', low=-0.5, high=0.5)
    rho: float = param(0.0, unit='-', description='Change of (c - B1)/alpha.', low=-0.5,
                       high=0.5)


def perturbed_stage(seed: int | None, *, spread: float = 0.3,
                    base: StageParams | None = None) -> tuple[StageParams, Perturbation]:
    """
    Return the paper's stage with every identified parameter changed by up to +-``spread``.

    Parameters
    ----------
    seed : int or None
        Seed of the draw; None gives the unperturbed stage.
    spread : float
        Largest relative change (0.3 = 30 %), uniform.
    base : StageParams, optional
        Stage to perturb; default the paper's.

    Returns
    -------
    StageParams, Perturbation
        The perturbed stage and the relative changes drawn.

    """
    base = base or StageParams()
    if seed is None:
        pert = Perturbation()
    else:
        rng = np.random.default_rng(seed)
        names = [s.name for s in Perturbation.specs()]
        pert = Perturbation(**{n: float(v) for n, v in
                               zip(names, rng.uniform(-spread, spread, len(names)))})
    f = factors_of(base.plant.third_order)
    lin = LinearFactors(f.gain_m_per_v * (1 + pert.gain), f.omega_n_rad_s * (1 + pert.omega_n),
                        f.zeta * (1 + pert.zeta), f.tau_s * (1 + pert.tau))
    third = third_order_of(lin)
    bl = base.hysteresis.backlash_like
    alpha = bl.alpha * (1 + pert.alpha)
    c = bl.c * (1 + pert.c)
    rho = (bl.c - bl.b1) / bl.alpha * (1 + pert.rho)
    b1 = c - rho * alpha
    if not 0.0 <= b1 < c or not math.isfinite(b1):
        b1 = 0.5 * c
    hyst = base.hysteresis.replace(model='backlash_like', backlash_like=bl.replace(
        alpha=alpha, c=c, b1=b1))
    plant = base.plant.replace(model='third_order', third_order=third, reduced=third.reduced())
    return base.replace(plant=plant, hysteresis=hyst), pert
