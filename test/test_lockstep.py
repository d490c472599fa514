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

"""Lockstep equivalence: the node logic driven message by message equals the offline runner."""

from __future__ import annotations

import numpy as np
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.loop.closed_loop import run
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.stage import Stage, StageParams
from piezo_stage_ros.hardware.bridge import ModelBridge
from piezo_stage_ros.hardware.safety import GuardedPlant
from piezo_stage_ros.nodes.logic import ControllerLogic, PlantLogic, TrajectoryLogic
import pytest

RATE = 10000.0


def stage_params(noise: float = 0.0, model: str = 'third_order') -> StageParams:
    return StageParams.from_flat({'chain.sensor_noise_std_m': noise, 'seed': 7,
                                  'plant.model': model})


def controller(kind: str) -> object:
    return build_controller(ControllerParams.from_flat({'type': kind}), 1.0 / RATE)


def offline(params: StageParams, kind: str, traj: TrajectoryParams, duration_s: float,
            chunk_s: float):
    return run(Stage(params), controller(kind), make_trajectory(traj), duration_s=duration_s,
               chunk_s=chunk_s, record_diagnostics=False)


def lockstep(params: StageParams, kind: str, traj: TrajectoryParams, duration_s: float,
             chunk_s: float, *, lose_first_command: bool = False,
             reference_first: bool = False, duplicate_every: int = 0):
    """Deliver the messages of a lockstep run in the order the nodes exchange them."""
    plant = PlantLogic(GuardedPlant(ModelBridge(params), params.chain), mode='lockstep',
                       sample_rate_hz=RATE, duration_s=duration_s, resend_s=0.5)
    trajectory = TrajectoryLogic(make_trajectory(traj), sample_rate_hz=RATE, chunk_s=chunk_s)
    ctrl = ControllerLogic(controller(kind), mode='lockstep')
    stamps, pos, ref, vel, cmd = [], [], [], [], []
    now = 0.0
    sample = plant.start(now)
    if lose_first_command:
        # sample 0 went out before the subscribers matched and reached nobody (the controller
        # node also drops a sample while its command publisher is unmatched): nothing comes
        # back, so the plant publishes it again once resend_s has passed, and not before
        assert plant.resend_due(now + 0.4) is None
        now += 0.6
        again = plant.resend_due(now)
        assert again == sample
        sample = again
    while sample is not None:
        xd, vd = trajectory.on_position(sample.stamp_ns)
        if reference_first:
            out = ctrl.on_reference(sample.stamp_ns, xd, vd)
            assert out is None
            out = ctrl.on_position(sample.stamp_ns, sample.position_m, now)
        else:
            assert ctrl.on_position(sample.stamp_ns, sample.position_m, now) is None
            out = ctrl.on_reference(sample.stamp_ns, xd, vd)
        assert out is not None and out.stamp_ns == sample.stamp_ns
        stamps.append(sample.stamp_ns)
        pos.append(sample.position_m)
        ref.append(xd)
        vel.append(vd)
        cmd.append(out.voltage_v)
        if duplicate_every and sample.index % duplicate_every == 3:
            # the same sample again (a resend racing its command): answered by nobody
            assert trajectory.on_position(sample.stamp_ns) == (xd, vd)
            assert ctrl.on_position(sample.stamp_ns, sample.position_m, now) is None
            assert ctrl.on_reference(sample.stamp_ns, xd, vd) is None
        sample = plant.on_command(out.voltage_v, now)
    assert plant.done and plant.unexpected == 0
    return (np.array(stamps), np.array(pos), np.array(ref), np.array(vel), np.array(cmd),
            ctrl, plant)


CASES = [
    ('pi', {'kind': 'sine'}, 0.0, 'third_order'),
    ('rac', {'kind': 'sine', 'sine.frequency_hz': 50.0}, 0.0, 'reduced'),
    ('rac', {'kind': 'square'}, 2e-9, 'reduced'),
    ('pi', {'kind': 'staircase'}, 2e-9, 'reduced'),
    ('pi', {'kind': 'multisine'}, 0.0, 'reduced'),
]


@pytest.mark.parametrize('kind, traj, noise, model', CASES)
def test_lockstep_equals_offline_runner_bit_for_bit(kind, traj, noise, model):
    params = stage_params(noise, model)
    tp = TrajectoryParams.from_flat(traj)
    # 0.2537 s: not a whole number of chunks, so the short last chunk is covered too
    duration, chunk = 0.2537, 0.1
    rec = offline(params, kind, tp, duration, chunk)
    stamps, pos, ref, vel, cmd, ctrl, plant = lockstep(params, kind, tp, duration, chunk)
    assert len(pos) == len(rec) == 2537
    # Bit for bit, on purpose: the nodes' logic calls the same scalar stage kernel and the same
    # controller step as the offline runner, in the same order, and the trajectory is the same
    # numpy ufunc on the same times (one per call here, a chunk there: numpy's loops give an
    # element the same value at any position, at every SIMD level test-matrix runs). Any
    # difference would be a real divergence, which the 16-bit quantization would then amplify.
    np.testing.assert_array_equal(stamps, np.round(np.arange(2537) * 1e9 / RATE).astype(int))
    np.testing.assert_array_equal(pos, rec.position_m)
    np.testing.assert_array_equal(ref, rec.reference_m)
    np.testing.assert_array_equal(vel, rec.reference_velocity_mps)
    np.testing.assert_array_equal(cmd, rec.command_v)
    assert ctrl.steps == 2537 and plant.plant.samples == 2537


def test_lockstep_survives_resends_duplicates_and_reordering():
    params = stage_params(1e-9, 'reduced')
    tp = TrajectoryParams.from_flat({'kind': 'sine'})
    rec = offline(params, 'rac', tp, 0.05, 1.0)
    stamps, pos, _, _, cmd, ctrl, plant = lockstep(params, 'rac', tp, 0.05, 1.0,
                                                   lose_first_command=True,
                                                   reference_first=True, duplicate_every=7)
    np.testing.assert_array_equal(pos, rec.position_m)
    np.testing.assert_array_equal(cmd, rec.command_v)
    assert plant.resends == 1
    assert ctrl.duplicates > 1


def test_lockstep_run_of_a_tenth_of_a_second_has_1000_samples():
    params = stage_params()
    tp = TrajectoryParams.from_flat({'kind': 'sine'})
    stamps, *_ = lockstep(params, 'pi', tp, 0.1, 1.0)
    assert len(stamps) == 1000
    assert stamps[-1] == 999 * 100_000


@pytest.mark.parametrize('ahead', [1, 64])
def test_references_streamed_ahead_give_the_same_run(ahead):
    # lockstep_ahead: the trajectory sends x_d for the next samples as soon as a position
    # comes (it does not depend on it); the controller pairs by stamp, the run is unchanged
    params = stage_params(1e-9, 'reduced')
    tp = TrajectoryParams.from_flat({'kind': 'square'})
    rec = offline(params, 'rac', tp, 0.0537, 0.01)
    plant = PlantLogic(GuardedPlant(ModelBridge(params), params.chain), mode='lockstep',
                       sample_rate_hz=RATE, duration_s=0.0537)
    trajectory = TrajectoryLogic(make_trajectory(tp), sample_rate_hz=RATE, chunk_s=0.01)
    ctrl = ControllerLogic(controller('rac'), mode='lockstep')
    sample = plant.start(0.0)
    pos, cmd, sent = [], [], []
    while sample is not None:
        batch = trajectory.ahead(sample.stamp_ns, ahead)
        sent += [stamp for stamp, _, _ in batch]
        for stamp, xd, vd in batch:
            # the references come before their positions: nothing to pair yet
            assert ctrl.on_reference(stamp, xd, vd) is None
        out = ctrl.on_position(sample.stamp_ns, sample.position_m, 0.0)
        assert out is not None and out.stamp_ns == sample.stamp_ns
        pos.append(sample.position_m)
        cmd.append(out.voltage_v)
        sample = plant.on_command(out.voltage_v, 0.0)
    np.testing.assert_array_equal(pos, rec.position_m)
    np.testing.assert_array_equal(cmd, rec.command_v)
    # every stamp sent once, on the plant's grid, up to `ahead` past the last sample
    assert sent == [plant.stamp_ns(k) for k in range(537 + ahead)]


def test_a_resent_sample_gets_its_reference_again_when_streamed_ahead():
    # the first burst of references may be more than a subscriber's queue holds: the plant
    # sends the waiting sample again after resend_s, and its reference goes again with it
    trajectory = TrajectoryLogic(make_trajectory(TrajectoryParams.from_flat({'kind': 'sine'})),
                                 sample_rate_hz=RATE)
    first = trajectory.ahead(0, 3)
    assert [s for s, _, _ in first] == [0, 100_000, 200_000, 300_000]
    assert trajectory.ahead(0, 3) == first[:1]        # sample 0 sent again
    assert [s for s, _, _ in trajectory.ahead(100_000, 3)] == [400_000]
