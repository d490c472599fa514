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
The work of a sample kept even: a long period's learning spread, the axes' commands ahead.

A long period's learning update is added a slice of columns a sample instead of a whole run
of LEARN_CHUNK errors at once: the same products summed in the same order per column, so the
table is the chunked one bit for bit. Several axes learn a longer period on its harmonics:
the same update within the rounding of its phasors, sums and inverse FFT. The axes' commands
ahead computed together equal each axis' own prediction bit for bit.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from piezo_stage_ros.core.config.loader import load_loop_config
from piezo_stage_ros.core.control import feedforward
from piezo_stage_ros.core.control.axes import AxesController
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.control.feedforward import (
    FeedForwardController,
    LEARN_CHUNK,
    LEARN_SPECTRUM_SAMPLES,
    LEARN_SPREAD_SAMPLES,
)
from piezo_stage_ros.core.loop.axes import run_axes
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.axes import AxesStage, AxesStageParams, CouplingParams
from piezo_stage_ros.core.model.hysteresis import HysteresisParams, make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant
import pytest
from tolerances import EPS

T = 1e-4
LOOP = load_loop_config([])


def _controller(mode: str, **flat: object) -> ControllerParams:
    return ControllerParams.from_flat({**LOOP.controller.to_flat(), 'feedforward.mode': mode,
                                       **flat})


def _sine(hz: float, offset: float = 6e-6, amplitude: float = 3e-6) -> Any:
    return make_trajectory(TrajectoryParams.from_flat({
        'kind': 'sine', 'sine.offset_m': offset, 'sine.amplitude_m': amplitude,
        'sine.frequency_hz': hz}))


def _learning(n: int, spectrum: bool = False) -> tuple[FeedForwardController, Any]:
    params = _controller('learning', **{'notch.mode': 'off',
                                        'feedforward.learning_limit_v': 100.0})
    ctrl = build_controller(params, T, linear_plant(LOOP.design_plant),
                            make_hysteresis(HysteresisParams(model='none')))
    assert isinstance(ctrl, FeedForwardController)
    if spectrum:
        ctrl.spectrum_samples = LEARN_SPECTRUM_SAMPLES
    sine = _sine(1.0 / (n * T))
    ctrl.bind(sine)
    ctrl.reset(3.8e-6, 3.8e-6)
    return ctrl, sine


def _stepped(ctrl: FeedForwardController, sine: Any, n: int, stall: tuple[int, int],
             backlog: list[int] | None = None) -> list[float]:
    """Step three periods of the reference plus errors; skip ``stall`` (first, count)."""
    errors = 1e-8 * np.random.default_rng(5).standard_normal(3 * n)
    xd, vd = sine.evaluate(np.arange(3 * n) * T)
    commands = []
    k = 0
    while k < 3 * n:
        if k == stall[0]:
            ctrl.skip(stall[1])
            k += stall[1]
            continue
        commands.append(ctrl.step(float(xd[k] + errors[k]), float(xd[k]), float(vd[k])))
        if backlog is not None:
            backlog.append(len(ctrl._backlog))
        k += 1
    return commands


# a period a multiple of the run, and ones whose last run and last slice are short
@pytest.mark.parametrize('n', [1024, 1030, 1283])
def test_spread_learning_is_the_chunked_learning_bit_for_bit(n: int,
                                                             monkeypatch: Any) -> None:
    # a stall across a run's end inside a period and one across the period's end
    stalls = ((n + 2 * LEARN_CHUNK - 3, 5), (2 * n - 3, 5))
    for stall in stalls:
        spread, sine = _learning(n)
        assert spread._slice > 0  # the period is long: the runs are spread
        backlog: list[int] = []
        got = _stepped(spread, sine, n, stall, backlog)
        with monkeypatch.context() as m:
            m.setattr(feedforward, 'LEARN_SPREAD_SAMPLES', 10 * n)
            chunked, sine = _learning(n)
            assert chunked._slice == 0
            want = _stepped(chunked, sine, n, stall)
        assert spread.periods_learned == chunked.periods_learned >= 1
        assert np.array_equal(spread.learned_table(), chunked.learned_table())
        assert np.max(np.abs(spread.learned_table())) > 0.0
        assert got == want
        assert np.array_equal(spread.predict(64), chunked.predict(64))
        # the runs are worked off as they come: a fixed slice a sample, never a whole run
        assert max(backlog) <= 2 and sum(b > 0 for b in backlog) > n


def test_spread_learning_is_the_circular_convolution_of_the_errors() -> None:
    # the update against the learning operator applied at once (in another order): sums of
    # 2 n products, 2 n rounding steps of the largest partial sum
    n = 1030
    ctrl, sine = _learning(n)
    _stepped(ctrl, sine, n, (3 * n, 0))
    assert ctrl.periods_learned == 2
    errors = 1e-8 * np.random.default_rng(5).standard_normal(3 * n)
    xd = sine.evaluate(np.arange(3 * n) * T)[0]
    learned = xd + errors - np.tile(ctrl._lx_raw, 3)
    learned = learned[n:2 * n] + learned[2 * n:]
    h = ctrl._kernel2[:n]
    circulant = h[(np.arange(n)[:, None] - np.arange(n)[None, :]) % n]
    expected = -(circulant @ learned)
    bound = 4 * n * EPS * float(np.max(np.abs(circulant) @ np.abs(learned)))
    assert np.max(np.abs(ctrl.learned_table() - expected)) <= bound
    assert np.max(np.abs(expected)) > 1e3 * bound


def test_short_periods_keep_the_runs_whole() -> None:
    ctrl, _ = _learning(100, spectrum=True)
    assert LEARN_SPREAD_SAMPLES > 100 and ctrl._slice == 0 and not ctrl._spectral


def test_only_several_axes_learn_on_the_harmonics() -> None:
    sp = LOOP.stage
    cp = _controller('inverse_learning')
    one = AxesController.build([cp], AxesStageParams(names=('x',), axes=(sp,)))
    two = AxesController.build([cp, cp], AxesStageParams(names=('x', 'y'), axes=(sp, sp)))
    assert [c.spectrum_samples for c in one.controllers] == [None]
    assert [c.spectrum_samples for c in two.controllers] == \
        [LEARN_SPECTRUM_SAMPLES] * 2


@pytest.mark.parametrize('n', [4096, 4106])
def test_spectrum_learning_is_the_summed_learning_within_its_rounding(n: int) -> None:
    # The spectrum of the errors on the kept harmonics, E_h = sum_i e_i p_i, each phasor p_i
    # turned on from an exact one (at most n turns: each a complex product, relative error
    # <= sqrt(5) eps, by a turn rounded to 2 eps of exp(-2 pi j h / n), so |p_i - exact|
    # <= 5 n eps), summed over m terms (<= m eps sum |e| a part, complex: x 2):
    # |dE_h| <= (5 n + 2 m) eps |e|_1. The update (1/n) sum over +-h of F_h E_h is off by at
    # most (2/n) |F|_1 (5 n + 2 m) eps |e|_1 from that, plus the inverse FFT's own rounding
    # (a few log2(n) eps of (2/n) sum |F_h E_h|), against the summed columns' own
    # 4 m eps max(|C| |e|) (the bound of the circulant test).
    # A stall across the second period's end: that update is applied with the third's, and
    # the phasor starts anew after the stall.
    assert n >= LEARN_SPECTRUM_SAMPLES
    stall = (2 * n - 3, 5)
    spectral, sine = _learning(n, spectrum=True)
    assert spectral._spectral and spectral._slice == 0
    got = _stepped(spectral, sine, n, stall)
    summed, sine = _learning(n)  # one axis' controller: the columns, as before
    assert not summed._spectral
    want = _stepped(summed, sine, n, stall)
    assert spectral.periods_learned == summed.periods_learned == 1
    errors = 1e-8 * np.random.default_rng(5).standard_normal(3 * n)
    xd = sine.evaluate(np.arange(3 * n) * T)[0]
    e = xd + errors - np.tile(summed._lx_raw, 3)
    e[stall[0]:stall[0] + stall[1]] = 0.0
    m = 2 * n
    norm1 = float(np.sum(np.abs(e[n:])))
    folded = e[n:2 * n] + e[2 * n:]
    h = summed._kernel2[:n]
    circulant = h[(np.arange(n)[:, None] - np.arange(n)[None, :]) % n]
    gains = np.abs(spectral._learning_gains)
    spectrum = np.abs(np.fft.rfft(folded)[spectral._harmonics])
    bound = (2.0 / n * float(np.sum(gains)) * (5 * n + 2 * m) * EPS * norm1
             + 8 * np.log2(n) * EPS * 2.0 / n * float(np.sum(gains * spectrum))
             + 4 * m * EPS * float(np.max(np.abs(circulant) @ np.abs(e[n:2 * n])
                                          + np.abs(circulant) @ np.abs(e[2 * n:]))))
    diff = np.max(np.abs(spectral.learned_table() - summed.learned_table()))
    assert diff <= bound
    assert np.max(np.abs(summed.learned_table())) > 1e3 * bound  # not a comparison of zeros
    # the commands differ by the tables' difference at most (learning alone, no hysteresis)
    assert np.max(np.abs(np.asarray(got) - np.asarray(want))) <= bound


def _axes(flats: list[dict[str, object]], trajectories: list[Any], duration_s: float,
          coupling: CouplingParams | None = None) -> None:
    """Run the axes; at every sample the batched commands ahead equal each axis' own."""
    names = ('x', 'y', 'z')[:len(flats)]
    sp = LOOP.stage
    params = AxesStageParams(names=names, axes=tuple(sp for _ in names),
                             **({'coupling': coupling} if coupling is not None else {}))
    ctrl = AxesController.build([_controller('none', **f) if 'feedforward.mode' not in f
                                 else ControllerParams.from_flat(
                                     {**LOOP.controller.to_flat(), **f}) for f in flats],
                                params)
    count = 128
    checked = {'batched': 0, 'samples': 0}

    def step(y: Any, r: Any, v: Any) -> list[float]:
        u, ahead = ctrl.step_ahead(y, r, v, count)
        own = [np.asarray(c.predict(count)) if hasattr(c, 'predict')
               else np.full(count, u[j]) for j, c in enumerate(ctrl.controllers)]
        assert ahead.shape == (len(names), count)
        for j, row in enumerate(own):
            assert np.array_equal(ahead[j], row), j
        plans = [getattr(c, 'ahead_plan', lambda _: None)(count) for c in ctrl.controllers]
        checked['batched'] += sum(p is not None for p in plans) >= 2
        checked['samples'] += 1
        return u

    wrapped = _Stepping(ctrl, step)
    run_axes(AxesStage(params), wrapped, trajectories, duration_s=duration_s)  # type: ignore
    if len(names) > 1:
        assert checked['batched'] > checked['samples'] // 2


class _Stepping:
    """An AxesController whose step is the checking one (what run_axes calls)."""

    def __init__(self, ctrl: AxesController, step: Any) -> None:
        self._ctrl = ctrl
        self.step = step

    def __getattr__(self, name: str) -> Any:
        return getattr(self._ctrl, name)


def test_batched_commands_ahead_are_each_axis_prediction_bit_for_bit() -> None:
    # a short and a long whole period learning, a model inverse alone, with coupling
    flats: list[dict[str, object]] = [
        {'feedforward.mode': 'inverse_learning'},
        {'feedforward.mode': 'inverse_learning'},
        {'feedforward.mode': 'inverse'}]
    coupling = CouplingParams(gain=(0.0, 0.02, 0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
                              resonance_hz=(0.0, 1800.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    _axes(flats, [_sine(100.0), _sine(1.0 / (1200 * T), 5e-6, 2e-6), _sine(100.0, 7e-6)],
          0.3, coupling)


def test_batched_commands_ahead_with_axes_predicted_alone() -> None:
    # a period of any length (its own prediction), a controller without feed-forward (held)
    flats: list[dict[str, object]] = [
        {'feedforward.mode': 'inverse_learning'},
        {'feedforward.mode': 'inverse_learning', 'feedforward.period_s': 0.01234},
        {},
        {'feedforward.mode': 'inverse'}][:3]
    _axes([flats[0], flats[1], {'feedforward.mode': 'inverse'}],
          [_sine(100.0), _sine(1.0 / 0.01234), _sine(50.0)], 0.1)
    _axes([flats[0], flats[2], flats[0]], [_sine(100.0), _sine(20.0), _sine(100.0, 7e-6)],
          0.05)
    _axes([flats[0]], [_sine(100.0)], 0.05)  # one axis: its own prediction as the row
