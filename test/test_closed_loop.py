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

"""The offline closed loop: sample order, chunking, diagnostics, errors."""

from __future__ import annotations

from typing import Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.loop import closed_loop
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.model.stage import Stage, StageParams
import pytest

T = 1e-4


class Ramp:
    """x_d(t) = 1 um + 1 m/s * t (only the sample order matters here)."""

    period_s = None

    def evaluate(self, time_s: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        t = np.asarray(time_s, dtype=np.float64)
        return 1e-6 + t, np.ones_like(t)


class Echo:
    """Commands u_k = k (the step count), remembers what it was given."""

    sample_time_s = T

    def __init__(self) -> None:
        self.seen: list[tuple[float, float, float]] = []
        self.k = 0
        self.reset_args: tuple[float, float] | None = None

    def reset(self, position_m: float, reference_m: float) -> None:
        self.reset_args = (position_m, reference_m)
        self.k = 0

    def step(self, position_m: float, reference_m: float,
             reference_velocity_mps: float) -> float:
        self.seen.append((position_m, reference_m, reference_velocity_mps))
        self.k += 1
        return float(self.k)

    def diagnostics(self) -> Mapping[str, float]:
        return {'k': float(self.k)}


class FakeStage:
    """y_k+1 = the last command * 1e-9 m, so each sample is traceable."""

    sample_time_s = T

    def __init__(self) -> None:
        self.commands: list[float] = []

    def reset(self, position_m: float | None = None) -> float:
        return 5e-6 if position_m is None else position_m

    def step(self, command_v: float) -> float:
        self.commands.append(command_v)
        return command_v * 1e-9


def test_sample_order_matches_interfaces() -> None:
    ctrl, stage = Echo(), FakeStage()
    rec = closed_loop.run(stage, ctrl, Ramp(), duration_s=10 * T, chunk_s=3 * T)
    assert len(rec) == 10
    assert ctrl.reset_args == (5e-6, 1e-6)
    np.testing.assert_allclose(rec.time_s, np.arange(10) * T, rtol=0, atol=1e-15)
    # u_k = k + 1 computed from y_k; y_k+1 = u_k * 1e-9
    np.testing.assert_array_equal(rec.command_v, np.arange(1, 11))
    assert rec.position_m[0] == 5e-6
    np.testing.assert_allclose(rec.position_m[1:], np.arange(1, 10) * 1e-9)
    np.testing.assert_allclose(rec.reference_m, 1e-6 + np.arange(10) * T)
    assert [s[0] for s in ctrl.seen] == rec.position_m.tolist()
    assert stage.commands == rec.command_v.tolist()


def test_chunks_stream_and_keep_false_returns_last_chunk() -> None:
    chunks: list[RunRecord] = []
    rec = closed_loop.run(FakeStage(), Echo(), Ramp(), duration_s=25 * T, chunk_s=10 * T,
                          chunk_callback=chunks.append, keep=False)
    assert [len(c) for c in chunks] == [10, 10, 5]
    assert rec is chunks[-1]
    joined = closed_loop.concatenate(chunks)
    np.testing.assert_array_equal(joined.command_v, np.arange(1, 26))


def test_diagnostics_sampled_and_held() -> None:
    rec = closed_loop.run(FakeStage(), Echo(), Ramp(), duration_s=7 * T, diagnostics_every=3)
    # read after steps 1, 4, 7 and held for 3 samples
    np.testing.assert_array_equal(rec.diagnostics['k'], [1, 1, 1, 4, 4, 4, 7])
    rec = closed_loop.run(FakeStage(), Echo(), Ramp(), duration_s=7 * T,
                          record_diagnostics=False)
    assert rec.diagnostics == {}


def test_same_samples_as_a_hand_written_loop_on_the_real_stage() -> None:
    params = StageParams()
    ref = Ramp()
    rec = closed_loop.run(Stage(params), Echo(), ref, duration_s=50 * T, chunk_s=7 * T)
    stage, ctrl = Stage(params), Echo()
    y = stage.reset()
    ctrl.reset(y, 1e-6)
    for k in range(50):
        xd, vd = ref.evaluate(np.array([k * T]))
        u = ctrl.step(y, float(xd[0]), float(vd[0]))
        assert rec.position_m[k] == y
        assert rec.command_v[k] == u
        # x(t_k), the state behind y_k: read before the stage steps (same kernel, same bits)
        assert rec.true_position_m is not None
        assert rec.true_position_m[k] == stage.position_m
        y = stage.step(u)


class TruthStage(FakeStage):
    """FakeStage whose true position is the last command * 1e-9 m plus 1 nm of offset."""

    def __init__(self) -> None:
        super().__init__()
        self.position_m = 4e-6

    def step(self, command_v: float) -> float:
        self.position_m = command_v * 1e-9 + 1e-9
        return super().step(command_v)


@pytest.mark.parametrize('every', [None, 3])
def test_true_position_recorded_beside_y_k(every: int | None) -> None:
    # a plain attribute position_m (no read_position_m) is read each sample, before the step
    chunks: list[RunRecord] = []
    rec = closed_loop.run(TruthStage(), Echo(), Ramp(), duration_s=10 * T, chunk_s=4 * T,
                          record_diagnostics=every is not None, diagnostics_every=every or 1,
                          chunk_callback=chunks.append)
    assert rec.true_position_m is not None
    # x_0 = the position at reset, x_k = u_k-1 * 1e-9 + 1e-9 with u_k-1 = k
    np.testing.assert_array_equal(rec.true_position_m,
                                  [4e-6] + [k * 1e-9 + 1e-9 for k in range(1, 10)])
    assert [len(c.true_position_m) for c in chunks  # type: ignore[arg-type]
            ] == [4, 4, 2]
    np.testing.assert_array_equal(rec.true_error_m, rec.true_position_m - rec.reference_m)


def test_no_true_position_without_one_or_when_not_asked() -> None:
    rec = closed_loop.run(FakeStage(), Echo(), Ramp(), duration_s=5 * T)
    assert rec.true_position_m is None and rec.true_error_m is None
    rec = closed_loop.run(TruthStage(), Echo(), Ramp(), duration_s=5 * T,
                          record_true_position=False)
    assert rec.true_position_m is None


def test_concatenate_keeps_the_true_position_only_when_every_chunk_has_it() -> None:
    chunks: list[RunRecord] = []
    closed_loop.run(TruthStage(), Echo(), Ramp(), duration_s=9 * T, chunk_s=4 * T,
                    chunk_callback=chunks.append)
    joined = closed_loop.concatenate(chunks)
    assert joined.true_position_m is not None
    np.testing.assert_array_equal(joined.true_position_m, np.concatenate(
        [c.true_position_m for c in chunks]))  # type: ignore[misc]
    assert closed_loop.concatenate(chunks[:1]).true_position_m is chunks[0].true_position_m
    bare = RunRecord(chunks[1].time_s, chunks[1].position_m, chunks[1].reference_m,
                     chunks[1].reference_velocity_mps, chunks[1].command_v,
                     chunks[1].diagnostics)
    assert closed_loop.concatenate([chunks[0], bare]).true_position_m is None


def test_record_refuses_a_true_position_of_another_length() -> None:
    from piezo_stage_ros.core.contracts.errors import PiezoStageError
    z = np.zeros(3)
    with pytest.raises(PiezoStageError, match='true_position_m has 2 samples, time_s has 3'):
        RunRecord(z, z, z, z, z, true_position_m=np.zeros(2))


@pytest.mark.parametrize('kwargs, name', [
    ({'duration_s': 0.0}, 'duration_s'),
    ({'duration_s': float('nan')}, 'duration_s'),
    ({'duration_s': 1.0, 'chunk_s': -1.0}, 'chunk_s'),
    ({'duration_s': 1.0, 'diagnostics_every': 0}, 'diagnostics_every'),
])
def test_bad_arguments(kwargs: dict[str, float], name: str) -> None:
    with pytest.raises(ParameterError, match=name):
        closed_loop.run(FakeStage(), Echo(), Ramp(), **kwargs)  # type: ignore[arg-type]


def test_sample_time_mismatch_refused() -> None:
    ctrl = Echo()
    ctrl.sample_time_s = 2e-4
    with pytest.raises(ParameterError, match='differs from the stage sample time'):
        closed_loop.run(FakeStage(), ctrl, Ramp(), duration_s=1.0)


def test_meta_carries_period() -> None:
    class Periodic(Ramp):
        period_s = 0.25  # type: ignore[assignment]
    rec = closed_loop.run(FakeStage(), Echo(), Periodic(), duration_s=3 * T,
                          meta={'controller': 'echo'})
    assert rec.meta['trajectory_period_s'] == 0.25
    assert rec.meta['controller'] == 'echo'
    assert rec.meta['sample_time_s'] == T
