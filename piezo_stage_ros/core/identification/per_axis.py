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
One-axis identification of each axis of a multi-axis stage, the other axes holding.

The paper's three open-loop runs (:func:`~piezo_stage_ros.core.identification.experiments.
run_experiments`) are made on one axis of the multi-axis stage through :class:`AxisView` while
every other axis holds its rest voltage, and identified by the one-axis procedure
(:func:`~piezo_stage_ros.core.identification.support.identify_checked`) unchanged. The coupling
the held axes send into the excited one is constant (their positions do not move), so it shifts
the measured position by a constant and nothing else; the excited axis' own coupling goes to the
other axes, which this axis' sensor does not read (unless the sensors cross-talk).

Commissioned in closed loop (:func:`commission_axis`), the axis runs as the multi-axis controller
will run it: where that controller compensates the coupling, the constant its compensation adds
to this axis' command for the held axes (:func:`held_compensation_v`) is added to every command,
and the verification's prediction runs the identified axis inside the design stage, the same axes
holding and the same compensation applied. The constant matters to the RAC: it holds the
command's constant part in its integral, so s keeps a constant part outside the adaptation's dead
zone, and the update of theta_hat, whose regressor y_d carries the sine's offset, settles only
where an in-phase periodic error balances it: a displacement the loop must hold becomes periodic
error. Compensated, the held axes cost the loop what the design model mispredicts of them; the
prediction on the design stage carries what the model predicts of them.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from piezo_stage_ros.core.control.axes import coupled_displacement
from piezo_stage_ros.core.control.controllers import ControllerParams
from piezo_stage_ros.core.control.stability import StabilityParams
from piezo_stage_ros.core.identification.commission import (
    commission,
    CommissionParams,
    CommissionResult,
    DeriveFn,
    ProgressFn,
)
from piezo_stage_ros.core.identification.coupling import rest_voltages
from piezo_stage_ros.core.identification.experiments import ExperimentPlan, run_experiments
from piezo_stage_ros.core.identification.fit import IdentificationParams
from piezo_stage_ros.core.identification.support import CheckedIdentification, identify_checked
from piezo_stage_ros.core.model.axes import AxesStage, AxesStageParams, coupling_paths
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant, StageParams

__all__ = ['AxisView', 'axis_overrides', 'commission_axis', 'held_compensation_v',
           'identify_axis']

#: Stage parameters the identification does not estimate: never written as an override.
NOT_IDENTIFIED = ('sample_rate_hz', 'seed', 'initial_position_m')


class AxisView:
    """
    One axis of a multi-axis stage seen as a one-axis plant, the other axes holding.

    Parameters
    ----------
    stage : AxesStageParams
        The stage.
    index : int
        The axis driven through the view.
    axis : StageParams
        That axis' parameters for this run (the run's seed and rate); every axis is run at its
        rate.
    compensation_v : float
        Added to every command of this axis [V]: the multi-axis controller's compensation of the
        held axes' coupling (:func:`held_compensation_v`); 0 without one.

    """

    def __init__(self, stage: AxesStageParams, index: int, axis: StageParams, *,
                 compensation_v: float = 0.0) -> None:
        rate = axis.sample_rate_hz
        axes = [p.replace(sample_rate_hz=rate) for p in stage.axes]
        axes[index] = axis
        params = dataclasses.replace(stage, axes=tuple(axes))
        self.index = index
        self._sim = AxesStage(params)
        self._holds = rest_voltages(params)
        self._cmds = list(self._holds)
        self.compensation_v = float(compensation_v)

    @property
    def sample_time_s(self) -> float:
        """Return the sample period [s]."""
        return self._sim.sample_time_s

    def reset(self, position_m: float | None = None) -> float:
        """Put every axis at rest (this one at ``position_m``) and return its measurement [m]."""
        given: list[float | None] = [None] * self._sim.n
        given[self.index] = position_m
        self._cmds = list(self._holds)
        return self._sim.reset(given)[self.index]

    def step(self, command_v: float) -> float:
        """
        Hold the command (and the compensation) on this axis, the others at rest.

        Returns this axis' measurement [m]. Without a compensation the command is applied
        as given, bit for bit.
        """
        comp = self.compensation_v
        self._cmds[self.index] = command_v + comp if comp else command_v
        return self._sim.step(self._cmds)[self.index]

    def read_position_m(self) -> float:
        """Return this axis' true position now [m] (the coupling it receives included)."""
        return self._sim.read_positions_m()[self.index]


def held_compensation_v(design: AxesStageParams, index: int) -> float:
    """
    Return what the coupling compensation adds to axis ``index``'s command, the others held.

    The multi-axis controller's compensation (:mod:`piezo_stage_ros.core.control.axes`) predicts
    the displacement the other axes' references put on this axis through the design model's
    coupling and subtracts it through this axis' model inverse (its plant's DC gain times the
    hysteresis slope, as the feed-forward's inverse). Held at their initial positions, the other
    axes' references are constant, and so is the compensation.

    Parameters
    ----------
    design : AxesStageParams
        The design model (axes and coupling) the controller compensates with.
    index : int
        The axis that receives the coupling.

    Returns
    -------
    float
        The constant [V]; 0 when no other axis couples into this one.

    """
    held = {i: np.full(2, p.initial_position_m) for i, p in enumerate(design.axes)
            if i != index}
    if not held:
        return 0.0
    moved = float(coupled_displacement(coupling_paths(design), index, held)[0])
    if moved == 0.0:
        return 0.0
    axis = design.axes[index]
    gain_m_per_v = (linear_plant(axis.plant).dc_gain_m_per_v
                    * float(make_hysteresis(axis.hysteresis).slope))
    return -moved / gain_m_per_v


def identify_axis(stage: AxesStageParams, index: int, configured: StageParams, *,
                  plan: ExperimentPlan | None = None,
                  params: IdentificationParams | None = None) -> CheckedIdentification:
    """
    Run the one-axis experiments on axis ``index`` of a (simulated) stage and identify it.

    Parameters
    ----------
    stage : AxesStageParams
        The true stage.
    index : int
        The axis identified.
    configured : StageParams
        That axis' configured parameters (signal chain, where the resonance is expected).
    plan : ExperimentPlan, optional
        The runs (default :class:`ExperimentPlan`).
    params : IdentificationParams, optional
        Settings of the procedure.

    Returns
    -------
    CheckedIdentification

    Raises
    ------
    RefusedError
        Parameters the runs cannot support (as the one-axis procedure).

    """
    stage.index(stage.names[index])
    records = run_experiments(stage.axes[index], plan,
                              plant=lambda p: AxisView(stage, index, p))
    return identify_checked(list(records.values()), configured, params)


def axis_overrides(identified: StageParams, configured: StageParams) -> dict[str, Any]:
    """
    Return the identified values that differ from the configured axis, as flat names.

    Parameters
    ----------
    identified, configured : StageParams
        The identification's stage and the axis it started from.

    Returns
    -------
    dict of str to value
        ``axes.<name>.*`` keys without their prefix; the loop rate, the seed and the initial
        position are never included (not identified).

    """
    new, old = identified.to_flat(), configured.to_flat()
    return {k: v for k, v in new.items() if k not in NOT_IDENTIFIED and old.get(k) != v}


def commission_axis(stage: AxesStageParams, index: int, configured: StageParams,
                    controller: ControllerParams, derive: DeriveFn,
                    params: CommissionParams | None = None, *,
                    stability: StabilityParams | None = None,
                    progress: ProgressFn | None = None,
                    design: AxesStageParams | None = None,
                    compensate: bool = False) -> CommissionResult:
    """
    Commission axis ``index`` of a (simulated) stage, the other axes holding.

    The one-axis commissioning (:func:`~piezo_stage_ros.core.identification.commission.
    commission`: hold and excite in closed loop, identify, design, certify, verify) with its
    runs and its verification made on that axis of the multi-axis stage through
    :class:`AxisView`, and the verification's prediction made on the identified axis inside
    the design stage, the other axes holding there too.

    Parameters
    ----------
    stage : AxesStageParams
        The true stage.
    index : int
        The axis commissioned.
    configured, controller, derive, params, stability, progress
        As :func:`~piezo_stage_ros.core.identification.commission.commission`, for this axis.
    design : AxesStageParams, optional
        The configured stage (its coupling is what the controller compensates and what the
        prediction holds the other axes through); default ``stage``.
    compensate : bool
        Whether the multi-axis controller compensates the coupling into this axis (its
        ``axes.coupling_compensation`` with a model-inverse feed-forward): every run then
        carries :func:`held_compensation_v` of the design stage on this axis' command, as
        the controller adds it.

    Returns
    -------
    CommissionResult

    """
    stage.index(stage.names[index])
    model = stage if design is None else design
    comp = held_compensation_v(model, index) if compensate else 0.0
    return commission(stage.axes[index], configured, controller, derive, params,
                      stability=stability, progress=progress,
                      plant=lambda p: AxisView(stage, index, p, compensation_v=comp),
                      model_plant=lambda p: AxisView(model, index, p, compensation_v=comp))
