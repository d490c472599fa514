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

"""The batched closed loop gives, member for member, the samples of single closed-loop runs."""

from __future__ import annotations

import math

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.loop import closed_loop
from piezo_stage_ros.core.loop.batch import (
    ControllerBatch,
    FeedForwardBatch,
    libm_exp,
    run_batch,
    StageFamilyBatch,
)
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.family import default_family, member_params
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant, Stage, StageParams
import pytest

BASE = StageParams()
FAMILY = {m.name: m for m in default_family()}
# a small family: nominal, gain and resonance extremes, hysteresis, noise, a corner; two of
# them with sensor noise (same seed: one stream, as two single stages with that seed draw it)
SMALL = ['nominal', 'gain_lo', 'gain_hi', 'zeta_lo', 'tau_hi', 'alpha_hi', 'b1_lo',
         'noise_hi', 'gain_hi_zeta_lo_noise']


def _singles(stages, cp, tp, duration_s):
    plant = linear_plant(BASE.plant)
    out = []
    for sp in stages:
        ctrl = build_controller(cp, sp.sample_time_s, plant)
        out.append(closed_loop.run(Stage(sp), ctrl, make_trajectory(tp), duration_s=duration_s,
                                   diagnostics_every=1, chunk_s=0.05))
    return out


def _assert_same(batch, singles):
    # Bit for bit, not "to 1e-12": with the 16-bit ADC any rounding difference becomes a whole
    # LSB (1.16 nm, 1e-4 of the signal) within a few hundred samples, so a tolerance would hide
    # nothing and prove nothing (core/loop/batch.py says how the two stay identical).
    assert len(batch) == len(singles)
    for b, s in zip(batch, singles):
        np.testing.assert_array_equal(b.time_s, s.time_s)
        np.testing.assert_array_equal(b.position_m, s.position_m)
        np.testing.assert_array_equal(b.reference_m, s.reference_m)
        np.testing.assert_array_equal(b.reference_velocity_mps, s.reference_velocity_mps)
        np.testing.assert_array_equal(b.command_v, s.command_v)
        for name, values in b.diagnostics.items():
            np.testing.assert_array_equal(values, s.diagnostics[name])


@pytest.mark.parametrize('controller,trajectory', [
    ({}, {'kind': 'sine', 'sine.frequency_hz': 100.0}),
    # fast adaptation, so the estimates really move, and a square wave that saturates the
    # command at the edges (conditional integration and frozen adaptation per member)
    ({'rac.gamma': 300.0, 'rac.eta': 1e-4, 'rac.k_d': 3.0},
     {'kind': 'square', 'square.period_s': 0.02, 'square.peak_to_peak_m': 20e-6}),
    ({'type': 'pi'}, {'kind': 'multisine'}),
    ({'type': 'pi', 'notch.mode': 'off', 'pi.k_p': 0.5, 'pi.k_i': 3000.0},
     {'kind': 'square', 'square.period_s': 0.02, 'square.peak_to_peak_m': 20e-6}),
    ({'type': 'open_loop'}, {'kind': 'sine', 'sine.frequency_hz': 10.0}),
    ({'notch.mode': 'off', 'rac.gamma': 100.0}, {'kind': 'staircase', 'staircase.dwell_s': 0.01}),
])
@pytest.mark.parametrize('quantize', [True, False])
def test_the_batch_equals_single_runs_member_for_member(controller, trajectory, quantize):
    # Without the converters every rounding difference shows in the samples at once; with them
    # (the study's case) a difference of an ulp hides until it moves a position across an ADC
    # code boundary, and then the runs part by a whole LSB.
    stages = [member_params(BASE.with_flat({'chain.quantize': quantize}), FAMILY[name])
              for name in SMALL]
    cp = ControllerParams.from_flat(controller)
    tp = TrajectoryParams.from_flat(trajectory)
    duration = 0.12
    singles = _singles(stages, cp, tp, duration)
    batch = run_batch(stages, cp, make_trajectory(tp), duration_s=duration,
                      plant=linear_plant(BASE.plant), chunk_s=0.05)
    _assert_same(batch, singles)
    assert any(np.ptp(s.command_v) > 0.1 for s in singles)
    if cp.type == 'rac' and cp.rac.gamma >= 300.0:
        # the estimates moved and the command saturated, so those paths were compared too
        assert any(np.ptp(s.diagnostics['theta_hat']) > 1e-3 for s in singles)
        assert any(s.diagnostics['saturated'].max() == 1.0 for s in singles)


LAWS = [
    # its own small dead zone, fast rates: the estimates move while tracking
    {'rac.adaptation_dead_zone_v': 0.002, 'rac.gamma': 300.0, 'rac.eta': 1e-4},
    # no dead zone and the normalised update (g = T / n per member)
    {'rac.adaptation_dead_zone_v': 0.0, 'rac.normalisation': 5.0, 'rac.gamma': 300.0,
     'rac.eta': 1e-4},
    # the desired regressors, without and with the normalisation (one g for all members)
    {'rac.adaptation_dead_zone_v': 0.002, 'rac.adaptation_regressor': 'desired',
     'rac.gamma': 300.0, 'rac.eta': 1e-4},
    {'rac.adaptation_dead_zone_v': 0.002, 'rac.adaptation_regressor': 'desired',
     'rac.normalisation': 5.0, 'rac.gamma': 300.0, 'rac.eta': 1e-4},
    # a subnormal dead zone, whose inverse overflows, is no dead zone
    {'rac.adaptation_dead_zone_v': 1e-310, 'rac.gamma': 300.0, 'rac.eta': 1e-4},
]


@pytest.mark.parametrize('law', LAWS)
@pytest.mark.parametrize('trajectory', [{'kind': 'sine', 'sine.frequency_hz': 100.0},
                                        {'kind': 'square', 'square.period_s': 0.04}])
def test_the_batch_follows_the_adaptive_law_of_the_controller(law, trajectory):
    stages = [member_params(BASE, FAMILY[name]) for name in SMALL]
    cp = ControllerParams.from_flat(law)
    tp = TrajectoryParams.from_flat(trajectory)
    singles = _singles(stages, cp, tp, 0.1)
    _assert_same(run_batch(stages, cp, make_trajectory(tp), duration_s=0.1,
                           plant=linear_plant(BASE.plant), chunk_s=0.05), singles)
    # the estimates moved (phi_hat stays on a square wave's plateaus with desired regressors)
    assert all(np.ptp(s.diagnostics['theta_hat']) > 0.0 for s in singles)
    # per-member references: the regressors and g become arrays
    tps = [TrajectoryParams.from_flat({'kind': 'sine', 'sine.frequency_hz': 20.0 * (i + 1)})
           for i in range(len(stages))]
    singles = [_singles([sp], cp, t, 0.05)[0] for sp, t in zip(stages, tps)]
    _assert_same(run_batch(stages, cp, [make_trajectory(t) for t in tps], duration_s=0.05,
                           plant=linear_plant(BASE.plant), chunk_s=0.05), singles)


def test_per_member_trajectories_and_the_reduced_plant():
    reduced = BASE.with_flat({'plant.model': 'reduced', 'chain.sensor_noise_std_m': 2e-9})
    stages = [reduced, reduced.with_flat({'plant.reduced.gain_m_per_v': 3.5e-6, 'seed': 4}),
              reduced.with_flat({'chain.sensor_noise_std_m': 0.0})]
    tps = [TrajectoryParams.from_flat({'kind': 'sine', 'sine.frequency_hz': f})
           for f in (10.0, 50.0, 100.0)]
    cp = ControllerParams.from_flat({'notch.mode': 'off'})
    singles = [_singles([sp], cp, tp, 0.08)[0] for sp, tp in zip(stages, tps)]
    batch = run_batch(stages, cp, [make_trajectory(tp) for tp in tps], duration_s=0.08,
                      chunk_s=0.05)
    _assert_same(batch, singles)


def test_libm_exp_is_math_exp():
    x = -np.abs(np.random.default_rng(3).standard_normal(20000)) * np.logspace(-6, 1, 20000)
    assert libm_exp(x).tolist() == [math.exp(v) for v in x.tolist()]


def test_without_recording_nothing_is_returned_and_the_run_still_happens():
    stages = [BASE, member_params(BASE, FAMILY['gain_hi'])]
    assert run_batch(stages, ControllerParams(), make_trajectory(TrajectoryParams()),
                     duration_s=0.01, record=False) == []


def test_the_batch_refuses_members_it_cannot_step_together():
    with pytest.raises(ParameterError, match='plant.model'):
        StageFamilyBatch([BASE, BASE.with_flat({'plant.model': 'reduced'})])
    with pytest.raises(ParameterError, match='plant.model'):
        StageFamilyBatch([BASE.with_flat({'plant.model': 'electromechanical'})])
    with pytest.raises(ParameterError, match='hysteresis'):
        StageFamilyBatch([BASE, BASE.with_flat({'hysteresis.model': 'none'})])
    with pytest.raises(ParameterError, match='stages'):
        StageFamilyBatch([])
    with pytest.raises(ParameterError, match='trajectory'):
        run_batch([BASE, BASE], ControllerParams(), [make_trajectory(TrajectoryParams())],
                  duration_s=0.01)


# -- feed-forward ------------------------------------------------------------------------------

# members the model inverse fits badly (gain 1.4x, the most lag) beside the nominal one, two of
# them with sensor noise
FF_MEMBERS = ['nominal', 'gain_hi', 'gain_lo_tau_hi', 'alpha_hi', 'gain_hi_zeta_lo_noise']


def _ff_singles(stages, cp, tp, duration_s, hysteresis):
    plant = linear_plant(BASE.plant)
    return [closed_loop.run(Stage(sp), build_controller(cp, sp.sample_time_s, plant, hysteresis),
                            make_trajectory(tp), duration_s=duration_s, diagnostics_every=1,
                            chunk_s=0.05) for sp in stages]


@pytest.mark.parametrize('mode,controller,trajectory', [
    ('learning', {}, {'kind': 'sine', 'sine.frequency_hz': 100.0}),
    ('inverse', {}, {'kind': 'sine', 'sine.frequency_hz': 100.0}),
    ('inverse_learning', {}, {'kind': 'sine', 'sine.frequency_hz': 100.0}),
    # the first period of a square wave is not yet periodic (feedback alone, the share notch
    # restarted), ideal jumps shaped by the inverse, the notch off
    ('inverse_learning', {'notch.mode': 'off'}, {'kind': 'square', 'square.period_s': 0.02}),
    # an aperiodic reference: the inverse computed block by block
    ('inverse', {}, {'kind': 'staircase', 'staircase.dwell_s': 0.01}),
    ('inverse_learning', {'type': 'pi'}, {'kind': 'multisine'}),
    # periods that are not a whole number of samples: the tables on the period's phase
    ('learning', {}, {'kind': 'sine', 'sine.frequency_hz': 300.0}),
    ('inverse_learning', {}, {'kind': 'triangle', 'triangle.frequency_hz': 70.0}),
    # a fast raster line: the held estimates' term taken off, member by member
    ('inverse_learning', {}, {'kind': 'scan_line', 'scan_line.frequency_hz': 300.0}),
])
def test_the_batch_equals_single_runs_with_feedforward(mode, controller, trajectory):
    # Bit for bit, as without feed-forward: the tables are the scalar wrapper's own, the learning
    # update is summed in the same order, the inverse hysteresis takes the same Newton steps
    # with libm's exp (a tolerance would hide nothing: the 16-bit ADC turns any difference into
    # a whole LSB).
    stages = [member_params(BASE, FAMILY[name]) for name in FF_MEMBERS]
    cp = ControllerParams.from_flat({**controller, 'feedforward.mode': mode})
    tp = TrajectoryParams.from_flat(trajectory)
    hyst = make_hysteresis(BASE.hysteresis)
    duration = 0.15
    singles = _ff_singles(stages, cp, tp, duration, hyst)
    batch = run_batch(stages, cp, make_trajectory(tp), duration_s=duration,
                      plant=linear_plant(BASE.plant), hysteresis=hyst, chunk_s=0.05)
    _assert_same(batch, singles)
    for b, s in zip(batch, singles):
        np.testing.assert_array_equal(b.true_position_m, s.true_position_m)
    # the feed-forward is in the commands: feedback alone gives other ones
    alone = run_batch(stages[:1], cp.with_flat({'feedforward.mode': 'none'}),
                      make_trajectory(tp), duration_s=duration, plant=linear_plant(BASE.plant),
                      chunk_s=0.05)
    assert not np.array_equal(alone[0].command_v, batch[0].command_v)


def test_learning_is_per_member():
    # each member learns its own table from its own error, and the RAC's estimates are held
    # per member at the values each had when learning began
    stages = [member_params(BASE, FAMILY[name]) for name in ('nominal', 'gain_hi', 'tau_hi')]
    cp = ControllerParams.from_flat({'feedforward.mode': 'learning'})
    tp = TrajectoryParams.from_flat({'kind': 'sine', 'sine.frequency_hz': 100.0})
    plant, hyst = linear_plant(BASE.plant), make_hysteresis(BASE.hysteresis)
    batch = StageFamilyBatch(stages)
    dt = batch.sample_time_s
    ctrl = ControllerBatch(cp, dt, plant)
    ff = FeedForwardBatch(cp, ctrl, plant, hyst, make_trajectory(tp))
    y = batch.reset()
    ctrl.reset(y)
    ff.reset(y)
    period = 100
    ref, vel = make_trajectory(tp).evaluate(np.arange(5 * period) * dt)
    theta = []
    for k in range(5 * period):
        y = batch.step(ff.step(y, float(ref[k]), float(vel[k])))
        theta.append(ctrl.diagnostic_values()[0].copy())
    tables = ff.learned_table()
    assert tables.shape == (period, 3) and ff.periods_learned == 4
    for sp, table in zip(stages, tables.T):
        ctl = build_controller(cp, dt, plant, hyst)
        closed_loop.run(Stage(sp), ctl, make_trajectory(tp), duration_s=5 * period * dt)
        np.testing.assert_array_equal(table, ctl.learned_table())
    assert not np.array_equal(tables[:, 0], tables[:, 1])
    held = np.asarray(theta[period:])  # learning starts after one period
    assert (held == held[0]).all() and len(set(held[0].tolist())) == 3


def test_feedforward_in_the_batch_needs_one_reference_and_a_model():
    stages = [BASE, member_params(BASE, FAMILY['gain_hi'])]
    cp = ControllerParams.from_flat({'feedforward.mode': 'inverse'})
    tp = make_trajectory(TrajectoryParams())
    with pytest.raises(ParameterError, match='trajectory'):
        run_batch(stages, cp, [tp, tp], duration_s=0.01, plant=linear_plant(BASE.plant))
    with pytest.raises(ParameterError, match='feedforward.mode'):
        run_batch(stages, cp, tp, duration_s=0.01)
    with pytest.raises(ParameterError, match='feedforward.period_s'):
        run_batch(stages, cp.with_flat({'feedforward.mode': 'learning'}),
                  make_trajectory(TrajectoryParams.from_flat({'kind': 'staircase'})),
                  duration_s=0.01, plant=linear_plant(BASE.plant))
