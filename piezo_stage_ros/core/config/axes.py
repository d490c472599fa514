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
The configuration of a multi-axis stage, read from the same ROS 2 parameter files.

A file describes a multi-axis stage when ``plant_node`` has ``axes.names``. Every one-axis
parameter of a node section is the base of each axis; ``axes.<name>.*`` overrides it for one
axis (the same dotted names, validated as strictly)::

    plant_node:
      ros__parameters:
        initial_position_m: 5.0e-6          # every axis
        axes:
          names: [x, y]
          y: {seed: 1}                      # axis y only
          coupling:                         # n x n, row-major: row i drives column j
            gain: [0.0, 0.02, 0.0, 0.0]
            resonance_hz: [0.0, 1800.0, 0.0, 0.0]
    controller_node:
      ros__parameters:
        axes:
          coupling_compensation: true
          x: {rac: {k_d: 1.2}}
    trajectory_node:
      ros__parameters:
        kind: triangle                      # each axis' one-axis trajectory (the raster's line)
        scan: {kind: raster, raster: {lines: 64}}

The one-axis loader ignores ``axes.*`` and ``scan.*`` (not parameters of its tables), so the
base of such a file is still a valid one-axis configuration. This is the loader's other entry
(:mod:`piezo_stage_ros.core.config.loader`): the files are read and merged the same way, the base
is the one-axis :class:`~piezo_stage_ros.core.config.loader.LoopConfig`, and each axis is that
base with its ``axes.<name>.*`` applied by the base group's own validation.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping, Sequence, TypeVar

from piezo_stage_ros.core.config.loader import Config, LoopConfig
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.interfaces import Trajectory
from piezo_stage_ros.core.contracts.params import Params
from piezo_stage_ros.core.control.controllers import ControllerParams
from piezo_stage_ros.core.control.stability import check_stability, StabilityReport
from piezo_stage_ros.core.loop.scan2d import make_scan, ScanParams
from piezo_stage_ros.core.loop.trajectories import TrajectoryParams
from piezo_stage_ros.core.model.axes import AxesStageParams, check_axis_names, CouplingParams

__all__ = ['AxesLoopConfig', 'axes_loop_config', 'has_axes']

_P = TypeVar('_P', bound=Params)

_COUPLING = ('gain', 'resonance_hz', 'damping', 'sensor_crosstalk')


def has_axes(config: Config) -> bool:
    """Return whether the files describe a multi-axis stage (``plant_node axes.names``)."""
    return 'axes.names' in config.node('plant_node')


@dataclass(frozen=True)
class AxesLoopConfig:
    """
    Every parameter of a multi-axis loop, validated.

    Attributes
    ----------
    base : LoopConfig
        The one-axis configuration every axis starts from.
    stage : AxesStageParams
        The axes and their coupling.
    controllers : tuple of ControllerParams
        One per axis.
    compensate : bool
        Coupling compensation in the feed-forward.
    lines : tuple of TrajectoryParams
        Each axis' one-axis trajectory (the raster's line; kind ``each``: every axis').
    scan : ScanParams
        The scan over the axes.

    """

    base: LoopConfig
    stage: AxesStageParams
    controllers: tuple[ControllerParams, ...]
    compensate: bool
    lines: tuple[TrajectoryParams, ...]
    scan: ScanParams

    def trajectories(self) -> tuple[Trajectory, ...]:
        """Return one trajectory per axis (:func:`make_scan`)."""
        return make_scan(self.scan, self.stage.names, self.lines,
                         [p.initial_position_m for p in self.stage.axes])

    def replace(self, **changes: Any) -> AxesLoopConfig:
        """Return a copy with some fields changed."""
        return dataclasses.replace(self, **changes)

    def stability(self, trajectories: Sequence[Trajectory]) -> dict[str, StabilityReport]:
        """
        Return each axis' own loop checked as the one-axis loop is, by axis name.

        Parameters
        ----------
        trajectories : sequence of Trajectory
            One per axis (:meth:`trajectories`): a learning axis is checked over its period.

        Returns
        -------
        dict of str to StabilityReport
            In the axis order (:func:`~piezo_stage_ros.core.control.stability.enforce` acts on
            each as ``base.stability.action`` says).

        """
        return {name: check_stability(cp, sp.plant, sp.sample_time_s,
                                      options=self.base.stability,
                                      period_s=getattr(tr, 'period_s', None), stage=sp)
                for name, sp, cp, tr in zip(self.stage.names, self.stage.axes,
                                            self.controllers, trajectories)}


def _per_axis(base: _P, section: Mapping[str, Any], names: tuple[str, ...], node: str,
              extra: tuple[str, ...]) -> tuple[_P, ...]:
    """
    Return ``base`` with each axis' ``axes.<name>.*`` of a node section applied, one per axis.

    Parameters
    ----------
    base : Params
        The one-axis object every axis starts from.
    section : Mapping[str, Any]
        The node's flat section.
    names : tuple of str
        The stage's axes.
    node : str
        Node name, for messages.
    extra : tuple of str
        Names under ``axes.`` that are not axes (``names``, ``coupling`` ...).

    Returns
    -------
    tuple of Params
        One per axis, in the order of ``names``.

    Raises
    ------
    ParameterError
        For ``axes.<name>`` naming no axis of the stage, or a bad per-axis value.

    """
    out: dict[str, dict[str, Any]] = {n: {} for n in names}
    for key, value in section.items():
        if not key.startswith('axes.'):
            continue
        head = key.split('.')[1]
        if head in extra:
            continue
        if head not in names:
            raise ParameterError(f'{node} {key}', value, f'axes.<name>.* with <name> one of '
                                 f'{list(names)}, or axes.{{{", ".join(extra)}}}',
                                 'names no axis of this stage')
        out[head][key] = value
    return tuple(base.with_flat(out[n], prefix=f'axes.{n}.') for n in names)


def axes_loop_config(config: Config) -> AxesLoopConfig:
    """
    Build the multi-axis loop from parameter files already read.

    Parameters
    ----------
    config : Config
        The files (``plant_node axes.names`` set).

    Returns
    -------
    AxesLoopConfig

    Raises
    ------
    ParameterError
        On the first bad value: the base (as the one-axis loader), an axis named twice or
        unknown, a per-axis override that is not a parameter, a coupling matrix of the wrong
        size, a scan that leaves the travel.

    """
    base = LoopConfig.from_config(config)
    plant = config.node('plant_node')
    if 'axes.names' not in plant:
        raise ParameterError('plant_node axes.names', None, "a list of 1-3 axes out of "
                             "['x', 'y', 'z']", 'is not set: not a multi-axis stage')
    names = check_axis_names(plant['axes.names'], 'plant_node axes.names')
    stages = _per_axis(base.stage, plant, names, 'plant_node', ('names', 'coupling'))
    coupling_keys = {k: v for k, v in plant.items() if k.startswith('axes.coupling.')}
    for key, value in coupling_keys.items():
        if key[len('axes.coupling.'):] not in _COUPLING:
            raise ParameterError(f'plant_node {key}', value, f'axes.coupling.{{'
                                 f'{", ".join(_COUPLING)}}}', 'is not a coupling parameter')
    coupling = CouplingParams(**{k: tuple(coupling_keys.get(f'axes.coupling.{k}', ()))
                                 for k in _COUPLING})
    stage = AxesStageParams(names=names, axes=stages,
                            coupling=coupling)
    ctrl = config.node('controller_node')
    compensate = ctrl.get('axes.coupling_compensation', True)
    if not isinstance(compensate, bool):
        raise ParameterError('controller_node axes.coupling_compensation', compensate,
                             'true or false', 'is not a boolean')
    controllers = _per_axis(base.controller, ctrl, names, 'controller_node',
                            ('coupling_compensation',))
    traj = config.node('trajectory_node')
    lines = _per_axis(base.trajectory, traj, names, 'trajectory_node', ())
    scan = ScanParams.from_flat({k: v for k, v in traj.items() if k.startswith('scan.')},
                                prefix='scan.')
    out = AxesLoopConfig(base=base, stage=stage, controllers=controllers,
                         compensate=compensate, lines=lines, scan=scan)
    out.trajectories()  # a scan that leaves the travel is refused here
    return out
