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

- ``noise``: small-amplitude band-limited white noise
(:class:`~piezo_stage_ros.core.signals.excitation.NoiseExcitation`), for the frequency response;
- ``step``: a train of small steps (the ``square`` trajectory), for the transient response;
- ``sine``: 1 + sin(2 pi 100 t) V (the ``sine`` trajectory), for the hysteresis.

The plan is written in volts; the trajectories get metres through the open-loop gain, and the
recorded ``command_v`` are the volts again. :func:`perturbed_stage` draws a stage with parameters
perturbed from the paper's (the test cases of the identification).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.interfaces import Trajectory
from piezo_stage_ros.core.contracts.params import param, Params
from piezo_stage_ros.core.contracts.types import FloatArray
from piezo_stage_ros.core.control.controllers import (
    build_controller,
    ControllerParams,
    OpenLoopController,
    OpenLoopParams,
)
from piezo_stage_ros.core.identification.foreign import SignalPath
from piezo_stage_ros.core.loop.closed_loop import Plant, run
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.loop.trajectories import (
    make_trajectory,
    SineParams,
    SquareParams,
    TrajectoryParams,
)
from piezo_stage_ros.core.model.linear import factors_of, LinearFactors, third_order_of
from piezo_stage_ros.core.model.stage import linear_plant, Stage, StageParams
from piezo_stage_ros.core.signals.excitation import NoiseExcitation, NoiseParams

__all__ = ['ClosedLoopPlan', 'ExperimentPlan', 'FeedforwardIntegralController', 'SumTrajectory',
           'perturbed_stage', 'run_closed_loop_experiment', 'run_experiments',
           'run_tracking']


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
                    open_loop_gain_m_per_v: float | None = None, sensor_offset_m: float = 0.0,
                    delay_samples: int = 0,
                    plant: Callable[[StageParams], Plant] | None = None
                    ) -> dict[str, RunRecord]:
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
    sensor_offset_m : float
        Added to every measured position (a sensor whose zero is not the stage's rest) [m].
    delay_samples : int
        Extra whole samples between a command and the sample it is held over (a DAQ
        pipeline), see :class:`~piezo_stage_ros.core.identification.foreign.SignalPath`.
    plant : callable, optional
        Builds the plant a run is made on from the stage parameters of that run (default
        :class:`~piezo_stage_ros.core.model.stage.Stage`): e.g. one axis of a multi-axis stage.

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
        # a plant of the factory has what SignalPath reads of a Stage (a multi-axis view too)
        bare: Any = (plant or Stage)(params.replace(seed=params.seed + i))
        stage: Plant = bare
        if sensor_offset_m != 0.0 or delay_samples != 0:
            stage = SignalPath(bare, sensor_offset_m, delay_samples)
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


# --------------------------------------------------------------------------------------------
# Closed-loop runs: a controller the package did not write, a periodic excitation on the
# reference, and ordinary tracking (operation) runs


class FeedforwardIntegralController:
    """
    A plain feed-forward plus integral position loop: v = g x_d + k_i int(x_d - y) dt.

    Not one of the package's controllers: the "foreign controller" of the closed-loop
    identification tests (the identification must not rely on knowing it).

    Parameters
    ----------
    feedforward_v_per_m : float
        g, the static inverse of the stage [V/m].
    integral_v_per_m_s : float
        k_i [V/(m s)]; the loop crosses over near k_i g_stage / (2 pi) Hz.
    sample_time_s : float
        Sample period [s].
    output_min_v, output_max_v : float
        Command limits [V].

    """

    def __init__(self, feedforward_v_per_m: float, integral_v_per_m_s: float,
                 sample_time_s: float, *, output_min_v: float = -2.0,
                 output_max_v: float = 10.0) -> None:
        self._g = float(feedforward_v_per_m)
        self._ki = float(integral_v_per_m_s)
        self._t = float(sample_time_s)
        self._lo, self._hi = float(output_min_v), float(output_max_v)
        self._i = 0.0

    @property
    def sample_time_s(self) -> float:
        """Return the sample period [s]."""
        return self._t

    def reset(self, position_m: float, reference_m: float) -> None:
        """Start with an empty integral."""
        self._i = 0.0

    def step(self, position_m: float, reference_m: float,
             reference_velocity_mps: float) -> float:
        """Return the command for one sample (backward-rectangle integral, clipped)."""
        self._i += self._t * (reference_m - position_m)
        u = self._g * reference_m + self._ki * self._i
        return min(max(u, self._lo), self._hi)

    def diagnostics(self) -> Mapping[str, float]:
        """Return the integral state [m s]."""
        return {'integral_m_s': self._i}


class SumTrajectory:
    """
    A hold position plus the sum of other signals (each evaluated without its offset).

    Parameters
    ----------
    hold_m : float
        Constant part [m].
    parts : sequence of Trajectory
        Signals added to it (their own offsets should be 0).
    period_s : float, optional
        Common period of the sum, if any (recorded in the run's meta).

    """

    kind = 'sum'

    def __init__(self, hold_m: float, parts: Sequence[Trajectory],
                 period_s: float | None = None) -> None:
        self.hold_m = float(hold_m)
        self.parts = tuple(parts)
        self.period_s = period_s

    def evaluate(self, time_s: Any) -> tuple[FloatArray, FloatArray]:
        """Return the sum and its derivative at ``time_s``."""
        t = np.asarray(time_s, dtype=np.float64)
        pos = np.full(t.shape, self.hold_m)
        vel = np.zeros(t.shape)
        for part in self.parts:
            p, v = part.evaluate(t)
            pos = pos + p
            vel = vel + v
        return pos, vel


@dataclass(frozen=True)
class ClosedLoopPlan:
    """
    A closed-loop identification run: hold, periodic multisine and a slow sine on the reference.

    Attributes
    ----------
    sample_rate_hz : float
    hold_m : float
        Position held [m].
    multisine_rms_m : float
        Rms of the multisine added to the reference [m].
    multisine_band_hz : tuple of float
        Its flat band [Hz].
    multisine_period_s : float
        Its period [s]; the slow sine's period should be a multiple of it.
    slow_amplitude_m, slow_frequency_hz : float
        A slow sine on the reference (for the hysteresis) [m], [Hz]; amplitude 0 for none.
    duration_s : float
    crossover_hz : float
        Crossover of the foreign feed-forward + integral loop [Hz].
    seed : int
        Seed of the multisine phases.

    """

    sample_rate_hz: float = 10000.0
    hold_m: float = 5e-6
    multisine_rms_m: float = 0.12e-6
    multisine_band_hz: tuple[float, float] = (20.0, 4500.0)
    multisine_period_s: float = 0.1
    slow_amplitude_m: float = 3e-6
    slow_frequency_hz: float = 5.0
    duration_s: float = 2.0
    crossover_hz: float = 100.0
    seed: int = 3


class _Sine:
    def __init__(self, amplitude_m: float, frequency_hz: float) -> None:
        self.a, self.w = amplitude_m, 2.0 * math.pi * frequency_hz

    def evaluate(self, time_s: Any) -> tuple[FloatArray, FloatArray]:
        t = np.asarray(time_s, dtype=np.float64)
        return self.a * np.sin(self.w * t), self.a * self.w * np.cos(self.w * t)


def run_closed_loop_experiment(stage_params: StageParams, plan: ClosedLoopPlan | None = None, *,
                               nominal_gain_m_per_v: float = 2.843e-6 * 1.0341,
                               meta: Mapping[str, Any] | None = None) -> RunRecord:
    """
    Run a stage in closed loop under :class:`FeedforwardIntegralController` with excitation.

    Parameters
    ----------
    stage_params : StageParams
        The (true) stage; its rate is replaced by the plan's.
    plan : ClosedLoopPlan, optional
        Excitation, loop and length; default :class:`ClosedLoopPlan`.
    nominal_gain_m_per_v : float
        The static gain the foreign controller assumes (its feed-forward is the inverse).
    meta : Mapping, optional
        Added to the record's meta (``true_stage`` is always added).

    Returns
    -------
    RunRecord
        Reference = hold + multisine + slow sine; period in ``meta['trajectory_period_s']``.

    """
    plan = plan or ClosedLoopPlan()
    params = stage_params.replace(sample_rate_hz=plan.sample_rate_hz)
    grid = 2.0 * plan.sample_rate_hz
    parts: list[Trajectory] = [NoiseExcitation(NoiseParams(
        offset_m=0.0, amplitude_m=plan.multisine_rms_m, band_low_hz=plan.multisine_band_hz[0],
        band_high_hz=plan.multisine_band_hz[1], period_s=plan.multisine_period_s,
        grid_rate_hz=grid, seed=plan.seed))]
    period = plan.multisine_period_s
    if plan.slow_amplitude_m > 0.0:
        parts.append(_Sine(plan.slow_amplitude_m, plan.slow_frequency_hz))
        period = max(period, 1.0 / plan.slow_frequency_hz)
    traj = SumTrajectory(plan.hold_m, parts, period_s=period)
    g = nominal_gain_m_per_v
    ctrl = FeedforwardIntegralController(1.0 / g, 2.0 * math.pi * plan.crossover_hz / g,
                                         params.sample_time_s)
    info: dict[str, Any] = {'name': 'closed_loop_multisine', 'experiment': 'closed_loop',
                            'controller': 'feedforward_integral', 'true_stage': params.to_flat()}
    info.update(meta or {})
    return run(Stage(params), ctrl, traj, duration_s=plan.duration_s,
               initial_position_m=plan.hold_m, record_diagnostics=False, meta=info)


def run_tracking(stage_params: StageParams, controller: ControllerParams, *,
                 design_stage: StageParams | None = None, frequency_hz: float = 100.0,
                 duration_s: float = 0.2, sample_rate_hz: float = 10000.0,
                 meta: Mapping[str, Any] | None = None) -> RunRecord:
    """
    Run an ordinary tracking run (the Table III sine, no added excitation) in closed loop.

    Parameters
    ----------
    stage_params : StageParams
        The (true) stage.
    controller : ControllerParams
        The configured controller.
    design_stage : StageParams, optional
        The model the controller's notch is designed on; default ``stage_params``.
    frequency_hz : float
        Frequency of the sine 3.8 + 3.8 sin(2 pi f t) um.
    duration_s : float
        Length of the run [s].
    sample_rate_hz : float
        Loop rate [Hz].
    meta : Mapping, optional
        Added to the record's meta.

    Returns
    -------
    RunRecord

    """
    params = stage_params.replace(sample_rate_hz=sample_rate_hz)
    design = design_stage or stage_params
    ctrl = build_controller(controller, params.sample_time_s, linear_plant(design.plant))
    traj = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine',
                                                       'sine.frequency_hz': frequency_hz}))
    info: dict[str, Any] = {'name': f'tracking_{frequency_hz:g}hz', 'experiment': 'tracking',
                            'true_stage': params.to_flat()}
    info.update(meta or {})
    return run(Stage(params), ctrl, traj, duration_s=duration_s, record_diagnostics=False,
               meta=info)
