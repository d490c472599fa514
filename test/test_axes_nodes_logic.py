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
The multi-axis node logic without rclpy: the lockstep sequence of the three nodes over N axes
gives the offline runner's samples bit for bit, and refuses what it cannot run.
"""

from __future__ import annotations

import numpy as np
from piezo_stage_ros.cli import read_config
from piezo_stage_ros.core.config.axes import axes_loop_config
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.control.axes import AxesController
from piezo_stage_ros.core.loop.axes import run_axes
from piezo_stage_ros.core.model.axes import AxesStage
from piezo_stage_ros.nodes.axes_logic import (
    AxesControllerLogic,
    AxesPlantLogic,
    AxesTrajectoryLogic,
    refuse_axes_mode,
)
import pytest


def loop_of(name, mode=None, params=()):
    loop = axes_loop_config(read_config([name], params))
    if mode is not None:
        loop = loop.replace(controllers=tuple(c.replace(feedforward=c.feedforward.replace(
            mode=mode)) for c in loop.controllers))
    return loop


def offline(loop, duration_s):
    ctrl = AxesController.build(loop.controllers, loop.stage, compensate=loop.compensate)
    return run_axes(AxesStage(loop.stage), ctrl, loop.trajectories(), duration_s=duration_s)


def nodes_in_lockstep(loop, duration_s, *, resend_every=0, chunk_s=1.0):
    """The three logics wired as the nodes wire them, every message delivered in order."""
    rate = loop.stage.axes[0].sample_rate_hz
    plant = AxesPlantLogic(AxesStage(loop.stage), sample_rate_hz=rate, duration_s=duration_s)
    trajectory = AxesTrajectoryLogic(loop.trajectories(), sample_rate_hz=rate, chunk_s=chunk_s,
                                     names=loop.stage.names)
    controller = AxesControllerLogic(
        AxesController.build(loop.controllers, loop.stage, compensate=loop.compensate),
        loop.trajectories())
    positions, true, references, velocities, commands = [], [], [], [], []
    sample = plant.start(0.0)
    while sample is not None:
        positions.append(sample.positions_m)
        true.append(sample.true_positions_m)
        ref, vel = trajectory.on_position(sample.stamp_ns)
        references.append(ref)
        velocities.append(vel)
        # the reference may come before or after the position; a resend repeats both
        assert controller.on_reference(sample.stamp_ns, ref, vel) is None
        command = controller.on_position(sample.stamp_ns, sample.positions_m)
        assert command is not None and command.stamp_ns == sample.stamp_ns
        if resend_every and sample.index % resend_every == 1:
            assert controller.on_position(sample.stamp_ns, sample.positions_m) is None
            assert controller.on_reference(sample.stamp_ns, ref, vel) is None
        commands.append(command.commands_v)
        sample = plant.on_command(command.commands_v, 0.0)
    assert plant.done and plant.on_command(commands[-1], 0.0) is None
    assert plant.stats()['unexpected_commands'] == 1
    return {k: np.array(v) for k, v in (('position', positions), ('true', true),
                                        ('reference', references), ('velocity', velocities),
                                        ('command', commands))}


@pytest.mark.parametrize('name, mode, duration_s, chunk_s', [
    ('xy_stage.yaml', None, 0.05, 1.0),           # inverse_learning, coupling compensation
    ('xy_stage.yaml', 'none', 0.03, 0.0123),      # feedback alone, chunks not the runner's
    ('xyz_stage.yaml', None, 0.02, 1.0),
])
def test_the_node_logic_in_lockstep_is_the_offline_runner_bit_for_bit(name, mode, duration_s,
                                                                      chunk_s):
    loop = loop_of(name, mode)
    records = offline(loop, duration_s)
    got = nodes_in_lockstep(loop, duration_s, resend_every=97, chunk_s=chunk_s)
    n = round(duration_s * loop.stage.axes[0].sample_rate_hz)
    assert got['position'].shape == (n, loop.stage.n)
    for j, rec in enumerate(records):
        assert np.array_equal(got['position'][:, j], rec.position_m)
        assert np.array_equal(got['true'][:, j], rec.true_position_m)
        assert np.array_equal(got['reference'][:, j], rec.reference_m)
        assert np.array_equal(got['velocity'][:, j], rec.reference_velocity_mps)
        assert np.array_equal(got['command'][:, j], rec.command_v)
    # the run is not trivial: every axis moves and is driven
    assert np.all(np.ptp(got['command'], axis=0) > 0.0)


@pytest.mark.parametrize('kind', ['lissajous', 'spiral', 'moves', 'each'])
def test_every_scan_kind_runs_on_the_node_logic_as_offline(kind):
    loop = loop_of('xy_stage.yaml', 'none', [f'trajectory_node:scan.kind={kind}'])
    records = offline(loop, 0.02)
    got = nodes_in_lockstep(loop, 0.02)
    for j, rec in enumerate(records):
        assert np.array_equal(got['reference'][:, j], rec.reference_m)
        assert np.array_equal(got['command'][:, j], rec.command_v)
        assert np.array_equal(got['position'][:, j], rec.position_m)


def test_a_sample_of_another_number_of_axes_is_refused_with_the_count():
    loop = loop_of('xy_stage.yaml')
    rate = loop.stage.axes[0].sample_rate_hz
    plant = AxesPlantLogic(AxesStage(loop.stage), sample_rate_hz=rate, duration_s=0.01)
    plant.start(0.0)
    with pytest.raises(ParameterError, match='2 entries, one per axis'):
        plant.on_command([0.0, 0.0, 0.0], 0.0)
    controller = AxesControllerLogic(
        AxesController.build(loop.controllers, loop.stage), loop.trajectories())
    with pytest.raises(ParameterError, match='stage/position'):
        controller.on_position(0, [1e-6])


def test_the_waiting_sample_is_sent_again_after_resend_s_only():
    loop = loop_of('xy_stage.yaml')
    plant = AxesPlantLogic(AxesStage(loop.stage), sample_rate_hz=10_000.0, duration_s=0.01,
                           resend_s=0.5)
    first = plant.start(10.0)
    assert plant.resend_due(10.4) is None
    assert plant.resend_due(10.6) == first and plant.stats()['resends'] == 1


@pytest.mark.parametrize('mode, backend, direct, words', [
    ('realtime', 'model', False, "mode 'realtime' without --direct"),
    ('realtime', 'udp', True, "backend 'udp'"),
    ('lockstep', 'udp', False, "backend 'udp'"),
    ('lockstep', 'model', True, '--direct in lockstep'),
])
def test_what_the_nodes_cannot_run_with_several_axes_is_named(mode, backend, direct, words):
    text = refuse_axes_mode('plant_node', mode, backend, direct)
    # the refusal names the value and what is allowed
    assert text is not None and words in text
    assert 'in lockstep by topics or in real time' in text and 'stage_servo --direct' in text
    assert refuse_axes_mode('plant_node', 'lockstep') is None
    assert refuse_axes_mode('plant_node', 'realtime', direct=True) is None
