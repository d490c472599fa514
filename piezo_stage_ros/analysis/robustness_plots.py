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
PNG figures of a robustness study (:mod:`piezo_stage_ros.core.loop.robustness`).

- ``robustness_errors.png``: per case, steady-state e_rms of every stage as bars, the nominal
  stage's value as a vertical line;
- ``estimates_<case>.png``: theta_hat(t) and phi_hat(t) of every stage, each beside its true
  value (dashed, same colour), for the cases where the controller has estimates.
"""

from __future__ import annotations

import math
from pathlib import Path

from matplotlib.figure import Figure
import numpy as np
from piezo_stage_ros.analysis.plots import _DPI, _save
from piezo_stage_ros.core.loop.robustness import RobustnessResult

__all__ = ['plot_errors', 'plot_estimates', 'save_plots']


def plot_errors(result: RobustnessResult, path: Path) -> Path:
    """
    Draw the steady-state e_rms per stage, one panel per case.

    Parameters
    ----------
    result : RobustnessResult
        The study.
    path : Path
        PNG to write.

    Returns
    -------
    Path
        ``path``.

    """
    names = [s['name'] for s in result.stages if s.get('listed', True)]
    cols = 2 if len(result.cases) > 1 else 1
    rows = math.ceil(len(result.cases) / cols)
    height = max(2.5, 0.16 * len(names) + 1.0)
    fig = Figure(figsize=(5.0 * cols, height * rows), dpi=_DPI, layout='constrained')
    y = np.arange(len(names))
    for i, case in enumerate(result.cases):
        ax = fig.add_subplot(rows, cols, i + 1)
        by_stage = {r['stage']: r for r in result.rows if r['case'] == case}
        vals = np.array([by_stage[n]['e_rms_m'] * 1e9 if n in by_stage else math.nan
                         for n in names])
        ax.barh(y, np.nan_to_num(vals, nan=0.0), color='tab:blue')
        if 'nominal' in by_stage:
            ax.axvline(by_stage['nominal']['e_rms_m'] * 1e9, color='k', lw=0.8, ls='--')
        ax.set_yticks(y, names, fontsize=6)
        ax.invert_yaxis()
        ax.set_xlabel('steady-state e_rms [nm]')
        ax.set_title(case, fontsize=9)
    fig.suptitle(f'{result.meta.get("controller")}: e_rms per stage (dashed: nominal)')
    return _save(fig, path)


def plot_estimates(result: RobustnessResult, case: str, path: Path) -> Path | None:
    """
    Draw theta_hat(t) and phi_hat(t) of every stage against the true values, for one case.

    Parameters
    ----------
    result : RobustnessResult
        The study.
    case : str
        The case.
    path : Path
        PNG to write.

    Returns
    -------
    Path or None
        ``path``, or None when the case has no estimates (not an adaptive controller).

    """
    stages = [s for s in result.stages if (case, s['name']) in result.traces]
    if not stages:
        return None
    fig = Figure(figsize=(9.0, 6.5), dpi=_DPI, layout='constrained')
    axes = [fig.add_subplot(2, 1, i + 1) for i in range(2)]
    colours = [f'C{i % 10}' for i in range(len(stages))]
    for s, colour in zip(stages, colours):
        t, theta, phi = result.traces[(case, s['name'])]
        for ax, values, true in ((axes[0], theta, s['theta_true']),
                                 (axes[1], phi, s['phi_true'])):
            ax.plot(t, values, color=colour, lw=0.9, label=s['name'])
            ax.axhline(true, color=colour, lw=0.6, ls='--')
    axes[0].set_ylabel('theta_hat [V/V]')
    axes[1].set_ylabel('phi_hat [s]')
    axes[1].set_xlabel('t [s]')
    axes[0].legend(fontsize=5, ncol=4, loc='best')
    fig.suptitle(f'{case}: estimates (solid) and true values (dashed) per stage')
    return _save(fig, path)


def save_plots(result: RobustnessResult, outdir: Path) -> list[Path]:
    """
    Write every figure of a study into ``outdir``.

    Parameters
    ----------
    result : RobustnessResult
        The study.
    outdir : Path
        Existing directory.

    Returns
    -------
    list of Path
        The files written.

    """
    written = [plot_errors(result, outdir / 'robustness_errors.png')]
    for case in result.cases:
        p = plot_estimates(result, case, outdir / f'estimates_{case}.png')
        if p is not None:
            written.append(p)
    return written
