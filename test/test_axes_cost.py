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
The servo sample of several axes made cheaper, each fast path equal to the way it replaced.

The commands ahead computed when read equal, read samples later, the predictions of their own
sample bit for bit; the stage of several axes stepped with its paths without modes left out
and its noise drawn a block at a time gives the numbers it gave stepped the long way.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from piezo_stage_ros.core.config.loader import load_loop_config
from piezo_stage_ros.core.control.ahead import AheadRow
from piezo_stage_ros.core.control.axes import AxesController
from piezo_stage_ros.core.loop.axes import run_axes
from piezo_stage_ros.core.model.axes import (
    AxesStage,
    AxesStageParams,
    CouplingParams,
    NOISE_BLOCK,
)
from piezo_stage_ros.core.model.stage import StageParams
import pytest
from test_axes_speed import _controller, _sine, _Stepping

T = 1e-4
LOOP = load_loop_config([])


def _lazy(params: list[Any], trajectories: list[Any], duration_s: float,
          coupling: CouplingParams | None = None, late: int = 3,
          hysteresis: tuple[str, ...] = ()) -> dict[str, int]:
    """
    Run the axes taking the rows computed when read; read each ``late`` samples later.

    Each read row must equal what every axis' own ``predict`` gave at the row's sample.
    """
    names = ('x', 'y', 'z')[:len(params)]
    sp = LOOP.stage
    axes = tuple(sp.with_flat({'hysteresis.model': hysteresis[j]}) if j < len(hysteresis)
                 else sp for j in range(len(names)))
    stage = AxesStageParams(names=names, axes=axes,
                            **({'coupling': coupling} if coupling is not None else {}))
    ctrl = AxesController.build(params, stage)
    count = 128
    kept: list[tuple[list[Any], list[Any], list[float]]] = []
    seen = {'lazy': 0, 'samples': 0, 'tables': 0}
    held: list[Any] = [None] * len(names)

    def check(rows: list[Any], want: list[Any], u: list[float]) -> None:
        del u
        for row, own in zip(rows, want):
            assert len(row) == count
            if isinstance(row, AheadRow):
                seen['lazy'] += 1
                assert row.finite()
                # a view first (slice, clamp), the whole row after: each computed when read
                lo, hi = float(np.min(own)) + 1e-3, float(np.max(own)) - 1e-3
                clamped = row.clamped(lo, hi)[5:]
                np.testing.assert_array_equal(clamped.to_array(),
                                              np.minimum(np.maximum(own, lo), hi)[5:])
                assert clamped[0] == float(np.minimum(np.maximum(own, lo), hi)[5])
                np.testing.assert_array_equal(row.to_array(), own)
                out = np.empty(count)
                row[2:].values_into(out[2:])
                np.testing.assert_array_equal(out[2:], own[2:])
                assert list(row) == own.tolist() and row[-1] == own[-1]
            else:
                np.testing.assert_array_equal(np.asarray(row), own)

    def step(y: Any, r: Any, v: Any) -> list[float]:
        u, rows = ctrl.step_ahead_rows(y, r, v, count)
        want = [np.asarray(c.predict(count)) if hasattr(c, 'predict')
                else np.full(count, u[j]) for j, c in enumerate(ctrl.controllers)]
        for j, c in enumerate(ctrl.controllers):
            tables = getattr(c, '_ahead_cache', None)
            if tables is not None and held[j] is not None and tables[1] is not held[j]:
                seen['tables'] += 1  # a table replaced while rows of before were unread
            held[j] = tables[1] if tables is not None else None
        kept.append((rows, want, u))
        if len(kept) > late:
            check(*kept.pop(0))
        seen['samples'] += 1
        return u

    run_axes(AxesStage(stage), _Stepping(ctrl, step), trajectories,  # type: ignore[arg-type]
             duration_s=duration_s)
    for item in kept:
        check(*item)
    return seen


def test_rows_read_later_are_the_predictions_of_their_sample_bit_for_bit() -> None:
    # a short and a long whole period learning (tables replaced at each period's end while
    # rows of before are unread), a model inverse alone, with coupling
    coupling = CouplingParams(gain=(0.0, 0.02, 0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
                              resonance_hz=(0.0, 1800.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    seen = _lazy([_controller('inverse_learning'), _controller('inverse_learning'),
                  _controller('inverse')],
                 [_sine(100.0), _sine(1.0 / (1200 * T), 5e-6, 2e-6), _sine(100.0, 7e-6)],
                 0.3, coupling, late=7)
    assert seen['lazy'] > 2 * seen['samples']
    assert seen['tables'] >= 3


def test_rows_of_axes_predicted_alone_and_of_one_axis() -> None:
    # a period of any length (its own prediction), no feed-forward (held), one axis alone
    seen = _lazy([_controller('inverse_learning'),
                  _controller('inverse_learning', **{'feedforward.period_s': 0.01234}),
                  _controller('none')],
                 [_sine(100.0), _sine(1.0 / 0.01234), _sine(20.0)], 0.06)
    assert seen['lazy'] > 0
    seen = _lazy([_controller('inverse_learning')], [_sine(100.0)], 0.05, late=1)
    assert seen['lazy'] > seen['samples'] // 2


def test_rows_read_later_with_the_solved_inverse_hysteresis_models() -> None:
    # the secant's state copied for the general inverse (a solve from the model's state)
    seen = _lazy([_controller('inverse_learning'), _controller('inverse')],
                 [_sine(100.0), _sine(100.0, 7e-6)], 0.05, late=5,
                 hysteresis=('bouc_wen', 'prandtl_ishlinskii'))
    assert seen['lazy'] > seen['samples']


def test_a_row_not_finite_when_read_is_the_command_held() -> None:
    # a secant that is not a number (finite inputs): what a guard refusing the row applies
    stage = AxesStageParams(names=('x', 'y'), axes=(LOOP.stage, LOOP.stage))
    ctrl = AxesController.build([_controller('learning'), _controller('learning')], stage)
    trajectories = [_sine(100.0), _sine(100.0, 7e-6)]
    ctrl.bind(trajectories)
    t = np.arange(301) * T
    refs = [tr.evaluate(t) for tr in trajectories]

    def at(k: int) -> tuple[list[float], list[float]]:
        return [float(x[k]) for x, _ in refs], [float(v[k]) for _, v in refs]
    ctrl.reset(*at(0))
    for k in range(300):
        r, v = at(k)
        u, rows = ctrl.step_ahead_rows(r, r, v, 16)
    assert all(isinstance(row, AheadRow) for row in rows)
    ctrl.controllers[1].ahead_secant = lambda du: math.nan  # type: ignore[union-attr]
    r, v = at(300)
    u, rows = ctrl.step_ahead_rows(r, r, v, 16)
    assert rows[1].finite()  # decided from its inputs, which are
    # the batch computed at once is not finite there (a guard refuses it and holds u)
    assert not np.isfinite(ctrl.predict_array(16)[1]).all()
    np.testing.assert_array_equal(rows[1].to_array(), np.full(16, u[1]))
    np.testing.assert_array_equal(rows[0].to_array(), ctrl.controllers[0].predict(16))
    # a last command or a coefficient that is not finite: the row says so before it is read
    ctrl.controllers[0]._u = math.nan  # type: ignore[union-attr]
    assert not ctrl._ahead.rows(16, u)[0].finite()
    assert not np.isfinite(ctrl.predict_array(16)[0]).all()
    # a table that is not finite (a learned value), the rest finite: the row says so too
    first = ctrl.controllers[0]
    first._u = u[0]  # type: ignore[union-attr]
    assert ctrl._ahead.rows(16, u)[0].finite()
    learned = list(first._ll)  # type: ignore[union-attr]
    learned[len(learned) // 2] = math.nan
    first._ll = learned  # type: ignore[union-attr]
    assert not ctrl._ahead.rows(16, u)[0].finite()


class _Before(AxesStage):
    """The stage stepped the long way: every path's state, one noise draw a sample."""

    def step(self, commands_v: Any) -> list[float]:
        own = []
        for axis, u in zip(self._axes, commands_v):
            dac = axis.dac
            if dac is not None and math.isfinite(u):
                u = dac.scalar(u)
            own.append(axis.stage.step(u))
        for k, path in enumerate(self._paths):
            state = self._axes[path.source].kernel.get()
            x_prev = self._x_prev[k]
            z = self._z[k]
            self._z[k] = path.ad @ z + path.f @ x_prev + path.h * state.w
            self._x_prev[k] = np.asarray(state.x, dtype=np.float64)
        return self._measure(own)

    def _measure(self, own: list[float]) -> list[float]:
        true = list(own)
        for path, z in zip(self._paths, self._z):
            for p, j in enumerate(path.targets):
                true[j] += path.gains[p] * float(z[2 * p])
            for j, kappa in path.static:
                true[j] += kappa * own[path.source]
        self._true = true
        out = []
        for j, axis in enumerate(self._axes):
            pos = true[j]
            for i, s in self._talk[j]:
                pos += s * true[i]
            if axis.noise > 0.0:
                pos += axis.noise * float(axis.rng.standard_normal())
            adc = axis.adc
            out.append(adc.scalar(pos) if adc is not None else pos)
        return out


@pytest.mark.parametrize('quantize', [True, False])
def test_the_stage_steps_as_it_did_bit_for_bit(quantize: bool) -> None:
    # modes and static paths both ways, sensor cross-talk, noise on every axis, a NaN command
    axes = tuple(StageParams.from_flat({'chain.sensor_noise_std_m': 1e-9 * (j + 1),
                                        'chain.quantize': quantize, 'seed': 3 + j,
                                        'initial_position_m': 5e-6 + 2e-6 * j})
                 for j in range(3))
    params = AxesStageParams(names=('x', 'y', 'z'), axes=axes, coupling=CouplingParams(
        gain=(0.0, 0.02, 0.01, 0.005, 0.0, 0.005, 0.002, 0.002, 0.0),
        resonance_hz=(0.0, 1800.0, 2500.0, 1800.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        sensor_crosstalk=(0.0, 0.001, 0.0, 0.0, 0.0, 0.002, 0.003, 0.0, 0.0)))
    u = np.random.default_rng(4).uniform(-3.0, 12.0, (3 * NOISE_BLOCK + 17, 3))
    u[300, 1] = np.nan
    now, before = AxesStage(params), _Before(params)
    assert now.reset() == before.reset()
    for row in u.tolist():
        assert now.step(row) == before.step(row)
        assert now.read_positions_m() == before.read_positions_m()
    assert now.faults == before.faults == (0, 1, 0)
    assert now.reset() == before.reset()  # and again after a reset, the noise going on
    np.testing.assert_array_equal(now.run_open_loop(u[:50]), before.run_open_loop(u[:50]))


def test_rows_queued_packed_are_the_rows_as_tuples() -> None:
    # what the servo queues (bytes) gives the batch and the samples the tuples give
    from piezo_stage_ros.nodes.servo_axes import _row_struct, axes_batch_of, sample_of_row
    rng = np.random.default_rng(2)
    rows = []
    for i in range(40):
        values = rng.normal(size=18) * 10.0 ** rng.integers(-9, 3, 18)
        values[3 * (i % 6)] = math.nan if i % 5 == 0 else values[3 * (i % 6)]
        rows.append((i, 7 + 2 * i, 10**18 + 7 + 100_000 * i, -3 + i * 11, *values.tolist()))
    pack = _row_struct(3).pack
    packed = [pack(*row) for row in rows]
    want, got = axes_batch_of(rows, 'xyz'), axes_batch_of(packed, 'xyz')
    for a, b in zip(want[:-1], got[:-1]):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b)
    assert got.stamp_ns[-1] == 10**18 + 7 + 100_000 * 39
    for row, data in zip(rows, packed):
        a, b = sample_of_row(row, 3), sample_of_row(data, 3)
        assert repr(a) == repr(b)  # NaN compares unequal: their text
