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
How often the 95 % bounds of the identification hold the truth: a study over foreign loops.

A bound is only worth what its coverage is. :func:`coverage_cases` draws cases: a random member
of the stage family (:func:`~piezo_stage_ros.core.model.family.sample_family`) under one of the
foreign loops of :mod:`~piezo_stage_ros.core.identification.foreign` (the three designs in
turn), with 0.5 to 3 nm of sensor noise, a random crossover, a sensor offset in every third
case and one sample of loop delay in every fourth. :func:`run_case` records the excitation and
sine runs, identifies them with
:func:`~piezo_stage_ros.core.identification.support.identify_checked` exactly as ``identify``
does (no meta: roles, loop and period from the data), and compares with the truth;
:func:`summarize` gives, per parameter, how often the truth lies inside the bounds and the
median relative half-width.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Sequence

import numpy as np
from piezo_stage_ros.core.identification.experiments import run_experiments
from piezo_stage_ros.core.identification.foreign import (
    foreign_runs,
    ForeignLoopParams,
    LOOP_KINDS,
)
from piezo_stage_ros.core.identification.support import identify_checked, RefusedError
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.model.family import member_params, sample_family
from piezo_stage_ros.core.model.linear import factors_of
from piezo_stage_ros.core.model.stage import StageParams

__all__ = ['COMPARED', 'CoverageCase', 'coverage_cases', 'run_case', 'summarize', 'truth_of']

#: The quantities compared with the truth (names of the result's summary and bounds).
COMPARED = ('static_gain_m_per_v', 'omega_n_rad_s', 'zeta', 'tau_s', 'alpha', 'b1_over_c',
            'sensor_offset_m')


@dataclass(frozen=True)
class CoverageCase:
    """
    One case of the study: a stage, a foreign loop and the signal chain's faults.

    Attributes
    ----------
    index : int
    stage : dict
        The true stage, flat (:meth:`StageParams.to_flat`).
    loop : dict
        The loop, flat (:class:`ForeignLoopParams`).
    label : str
        Short description for the progress lines.
    open_loop : bool
        Record the package's three open-loop runs (noise, step, sine) instead of the foreign
        loop's two; the loop's offset and delay still apply.

    """

    index: int
    stage: dict[str, Any]
    loop: dict[str, Any]
    label: str
    open_loop: bool = False


def coverage_cases(n: int, seed: int = 0, base: StageParams | None = None, *,
                   open_loop: bool = False) -> list[CoverageCase]:
    """
    Return ``n`` cases: family members x foreign loops x noise, offsets and delays.

    Parameters
    ----------
    n : int
        Number of cases.
    seed : int
        Seed of the draw (members, noise, crossover, offset, multisine phases).
    base : StageParams, optional
        The nominal stage of the family; default the paper's.
    open_loop : bool
        Open-loop cases (the package's noise, step and sine runs) instead of foreign loops.

    Returns
    -------
    list of CoverageCase

    """
    base = base or StageParams()
    rng = np.random.default_rng(seed + 7919)
    members = sample_family(n, seed)
    out = []
    for i, member in enumerate(members):
        noise = float(rng.uniform(0.5e-9, 3e-9))
        stage = member_params(base, member).with_flat(
            {'chain.sensor_noise_std_m': noise, 'seed': seed * 100003 + i})
        offset = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.05e-6, 0.2e-6)) \
            if i % 3 == 2 else 0.0
        loop = ForeignLoopParams(kind=LOOP_KINDS[i % len(LOOP_KINDS)],
                                 crossover_hz=float(rng.uniform(70.0, 130.0)),
                                 sensor_offset_m=offset, delay_samples=1 if i % 4 == 3 else 0,
                                 seed=seed * 1009 + i + 1)
        kind = 'open loop' if open_loop else loop.kind
        label = (f'{member.name} {kind} noise {noise * 1e9:.2f} nm, crossover '
                 f'{loop.crossover_hz:.0f} Hz, offset {offset * 1e9:.0f} nm, delay '
                 f'{loop.delay_samples}')
        out.append(CoverageCase(i, stage.to_flat(), loop.to_flat(), label, open_loop))
    return out


def truth_of(stage: StageParams, loop: ForeignLoopParams) -> dict[str, float]:
    """Return the true values of the compared quantities for a stage under a loop."""
    f = factors_of(stage.plant.third_order)
    bl = stage.hysteresis.backlash_like
    return {'static_gain_m_per_v': f.gain_m_per_v * bl.c, 'omega_n_rad_s': f.omega_n_rad_s,
            'zeta': f.zeta, 'tau_s': f.tau_s, 'alpha': bl.alpha, 'b1_over_c': bl.b1 / bl.c,
            'sensor_offset_m': loop.sensor_offset_m,
            'delay_samples': float(loop.delay_samples)}


def _bare(record: RunRecord) -> RunRecord:
    """Return a run as a lab's recorder holds it: its name only."""
    return RunRecord(record.time_s, record.position_m, record.reference_m,
                     record.reference_velocity_mps, record.command_v,
                     meta={'name': record.meta['name']})


def run_case(case: CoverageCase, base: StageParams | None = None) -> dict[str, Any]:
    """
    Record and identify one case; compare with the truth.

    Parameters
    ----------
    case : CoverageCase
        The case.
    base : StageParams, optional
        The configured stage the identification starts from; default the paper's.

    Returns
    -------
    dict
        ``index``, ``label``, ``accepted``; when accepted, per compared quantity ``error``
        (estimate - truth, relative except for the offset, in metres), ``inside`` (the truth
        within the 95 % bounds), ``half_width`` (relative; metres for the offset), and the
        ``delay`` found and the true one; when refused, ``refused`` (the lines).

    """
    stage = StageParams.from_flat(case.stage)
    loop = ForeignLoopParams.from_flat(case.loop)
    if case.open_loop:
        runs = run_experiments(stage, sensor_offset_m=loop.sensor_offset_m,
                               delay_samples=loop.delay_samples)
    else:
        runs = foreign_runs(stage, loop)
    out: dict[str, Any] = {'index': case.index, 'label': case.label}
    try:
        checked = identify_checked([_bare(r) for r in runs.values()], base or StageParams())
    except RefusedError as exc:
        out.update(accepted=False, refused=exc.lines)
        return out
    res = checked.result
    values = dict(res.summary())
    if res.hysteresis is not None:
        values.update(res.hysteresis.estimates)
    values['b1_over_c'] = values.get('b1_over_c', values['b1'] / values['c'])
    truth = truth_of(stage, loop)
    params: dict[str, dict[str, Any]] = {}
    for name in COMPARED:
        if name not in values or name not in res.bounds:
            continue
        lo, hi = res.bounds[name]
        value, true = float(values[name]), truth[name]
        absolute = name == 'sensor_offset_m'
        scale = 1.0 if absolute else abs(true)
        params[name] = {'error': (value - true) / scale, 'inside': bool(lo <= true <= hi),
                        'half_width': 0.5 * (hi - lo) / scale}
    out.update(accepted=True, loop=res.loop, parameters=params,
               delay=float(res.factors.delay_samples), true_delay=truth['delay_samples'])
    return out


def summarize(results: Sequence[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """
    Return, per compared quantity, the coverage of its bounds over the accepted cases.

    Parameters
    ----------
    results : sequence of dict
        What :func:`run_case` returned.

    Returns
    -------
    dict
        Name -> ``runs``, ``inside`` (fraction of runs with the truth inside the bounds),
        ``median_half_width`` and ``median_abs_error`` (relative; metres for the offset),
        ``max_abs_error``.

    """
    out: dict[str, dict[str, float]] = {}
    for name in COMPARED:
        rows = [r['parameters'][name] for r in results
                if r.get('accepted') and name in r['parameters']]
        if not rows:
            continue
        err = np.array([abs(row['error']) for row in rows])
        out[name] = {'runs': float(len(rows)),
                     'inside': float(np.mean([row['inside'] for row in rows])),
                     'median_half_width': float(np.median([row['half_width'] for row in rows])),
                     'median_abs_error': float(np.median(err)),
                     'max_abs_error': float(np.max(err)) if err.size else math.nan}
    return out
