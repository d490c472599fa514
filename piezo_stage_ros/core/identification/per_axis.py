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
"""

from __future__ import annotations

import dataclasses
from typing import Any

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
from piezo_stage_ros.core.model.axes import AxesStage, AxesStageParams
from piezo_stage_ros.core.model.stage import StageParams

__all__ = ['AxisView', 'axis_overrides', 'commission_axis', 'identify_axis']

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

    """

    def __init__(self, stage: AxesStageParams, index: int, axis: StageParams) -> None:
        rate = axis.sample_rate_hz
        axes = [p.replace(sample_rate_hz=rate) for p in stage.axes]
        axes[index] = axis
        params = dataclasses.replace(stage, axes=tuple(axes))
        self.index = index
        self._sim = AxesStage(params)
        self._holds = rest_voltages(params)
        self._cmds = list(self._holds)

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
        """Hold the command on this axis, the others at rest; return its measurement [m]."""
        self._cmds[self.index] = command_v
        return self._sim.step(self._cmds)[self.index]

    def read_position_m(self) -> float:
        """Return this axis' true position now [m] (the coupling it receives included)."""
        return self._sim.read_positions_m()[self.index]


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
                    progress: ProgressFn | None = None) -> CommissionResult:
    """
    Commission axis ``index`` of a (simulated) stage, the other axes holding.

    The one-axis commissioning (:func:`~piezo_stage_ros.core.identification.commission.
    commission`: hold and excite in closed loop, identify, design, certify, verify) with its
    runs and its verification made on that axis of the multi-axis stage through
    :class:`AxisView`.

    Parameters
    ----------
    stage : AxesStageParams
        The true stage.
    index : int
        The axis commissioned.
    configured, controller, derive, params, stability, progress
        As :func:`~piezo_stage_ros.core.identification.commission.commission`, for this axis.

    Returns
    -------
    CommissionResult

    """
    stage.index(stage.names[index])
    return commission(stage.axes[index], configured, controller, derive, params,
                      stability=stability, progress=progress,
                      plant=lambda p: AxisView(stage, index, p))
