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
Closed-loop Table III sines on the default stage (10 kHz, 16-bit converters, backlash-like).

Short runs: the steady-state window of core.loop.metrics (after max(2 periods, 0.1 s)) plus one
period or 0.1 s, as ``python3 -m piezo_stage_ros.tune`` does.
"""

from piezo_stage_ros.core.control.controllers import ControllerParams, NotchParams
from piezo_stage_ros.core.control.stability import check_stability, StabilityParams
from piezo_stage_ros.core.model.stage import PlantParams
from piezo_stage_ros.tune import PAPER_PIC_NM, PAPER_RAC_NM, track
import pytest

PAPER_PI = ControllerParams(type='pi', notch=NotchParams(mode='off'))
_RAC = ControllerParams().rac
#: the default RAC without its notch, frozen (no adaptation) at the corner of its box where
#: the check finds it unstable on model (20): the loop the check's verdict is about
FROZEN_CORNER_NO_NOTCH = ControllerParams(notch=NotchParams(mode='off'), rac=_RAC.replace(
    theta_init=_RAC.theta_min, phi_init=_RAC.phi_max, gamma=0.0, eta=0.0))


@pytest.mark.parametrize('f', [50.0, 100.0])
def test_paper_pi_on_the_reduced_plant_lands_on_the_paper_pic_row(f):
    # validates the plant and the units: within 15 % of the experiment
    e_rms, _ = track(PAPER_PI, 'reduced', f)
    assert e_rms * 1e9 == pytest.approx(PAPER_PIC_NM[f], rel=0.15)


#: The default is sized to pass the stability check with one sample of computational delay;
#: the price is tracking: at 50 Hz it no longer beats the paper's experiment (at par on Table
#: III's 1 s window, above it on this short run, where phi_hat is still adapting)
AT_PAR_50_HZ = pytest.mark.xfail(strict=True, reason='the one-sample-delay default tracks 50 Hz '
                                 "no better than the paper's RAC")


@pytest.mark.parametrize('f', [1.0, 10.0, pytest.param(50.0, marks=AT_PAR_50_HZ), 100.0])
def test_default_rac_on_the_reduced_plant_beats_the_paper_rac_row(f):
    e_rms, e_max = track(ControllerParams(), 'reduced', f)
    assert e_rms * 1e9 <= PAPER_RAC_NM[f]
    assert e_max < 3.0 * PAPER_RAC_NM[f] * 1e-9


@pytest.mark.xfail(strict=True, reason='the one-sample-delay default gives about 0.6 of the '
                   "paper's 100 Hz error, not half")
def test_default_rac_reaches_half_the_paper_error_at_100_hz():
    e_rms, _ = track(ControllerParams(), 'reduced', 100.0)
    assert e_rms * 1e9 <= 0.5 * PAPER_RAC_NM[100.0]


@pytest.mark.parametrize('model', ['reduced', 'third_order'])
def test_default_rac_beats_the_paper_at_100_hz_with_one_sample_of_delay(model):
    # what the default was sized for: each command applied one sample late (tune.Delayed),
    # the loop the check passes with stability.delay_samples = 1
    e_rms, _ = track(ControllerParams(), model, 100.0, delay=True)
    assert e_rms * 1e9 <= PAPER_RAC_NM[100.0]


def test_default_rac_with_its_notch_tracks_on_the_third_order_model():
    e_rms, _ = track(ControllerParams(), 'third_order', 100.0)
    assert e_rms * 1e9 <= PAPER_RAC_NM[100.0]


@pytest.mark.parametrize('params', [FROZEN_CORNER_NO_NOTCH, PAPER_PI],
                         ids=['rac-no-notch', 'paper-pi'])
def test_what_the_check_calls_unstable_does_oscillate_on_the_third_order_model(params):
    # the simulated loop applies u_k at t_k: the check with no delay, at the estimates the
    # run keeps
    opts = StabilityParams(delay_samples=0.0, estimates='initial')
    assert not check_stability(params, PlantParams(model='third_order'), 1e-4,
                               options=opts).stable
    e_rms, _ = track(params, 'third_order', 100.0)
    assert e_rms > 1e-6
