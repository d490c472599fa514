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
The report of a commissioning run, for a person to review before using its parameters.

- ``report.json``: :func:`piezo_stage_ros.core.identification.commission.summary` (identified
  values, 95 % bounds, the design and its certification, the verification);
- ``frequency_response.png``: the frequency response measured in closed loop (averaged over
  whole periods) with its 95 % band per line, the fit, and the envelope of the model over the
  corners of the 95 % bounds the certification checked;
- ``excitation.png``: reference and position of the hold and excitation;
- ``verification.png``: the verification track and its error.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Mapping

import matplotlib

matplotlib.use('Agg')  # files only; never a window

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from piezo_stage_ros.analysis.identification_report import save_figure  # noqa: E402
from piezo_stage_ros.analysis.plots import dress, plot_tracking  # noqa: E402
from piezo_stage_ros.core.identification.commission import (  # noqa: E402
    CommissionResult,
    corner_plants,
    summary,
)
from piezo_stage_ros.core.identification.fit import discrete_frequency_response  # noqa: E402
from piezo_stage_ros.core.identification.support import Z95  # noqa: E402
from piezo_stage_ros.core.model.stage import StageParams  # noqa: E402

__all__ = ['plot_closed_loop_frf', 'write_commission_report']


def plot_closed_loop_frf(result: CommissionResult, path: Path) -> Path | None:
    """
    Write the closed-loop frequency response with its bounds against the fit.

    Parameters
    ----------
    result : CommissionResult
        The commissioning run.
    path : Path
        PNG file to write.

    Returns
    -------
    Path or None
        None when the run had no periodic fit.

    """
    periodic = result.checked.periodic
    if periodic is None:
        return None
    fit = periodic.fit
    data = fit.data
    f = data.frequency_hz
    used = fit.used
    coh = np.clip(data.coherence, 0.0, 1.0 - 1e-15)
    rel = Z95 * np.sqrt((1.0 - coh) / np.maximum(coh, 1e-300))  # 1.96 / sqrt(SNR)
    g = data.response
    shift = np.exp(-1j * periodic.phase_rad)
    corners = [discrete_frequency_response(st.plant.third_order, data.sample_time_s, f) * shift
               for _, st in corner_plants(result.identified, result.checked.result.bounds)]
    fig, (mag, phase) = plt.subplots(2, 1, figsize=(7.5, 7.0), sharex=True)
    db = 20.0 * np.log10(np.abs(g[used]) * 1e6)
    lo = 20.0 * np.log10(np.maximum(np.abs(g[used]) * (1.0 - rel[used]), 1e-30) * 1e6)
    hi = 20.0 * np.log10(np.abs(g[used]) * (1.0 + rel[used]) * 1e6)
    mag.errorbar(f[used], db, yerr=[db - lo, hi - db], fmt='.', markersize=3,
                 color='tab:blue', elinewidth=0.8, label='measured, closed loop (95 % per line)')
    ph = np.degrees(np.unwrap(np.angle(g[used])))
    dph = np.degrees(np.minimum(rel[used], math.pi))
    phase.errorbar(f[used], ph, yerr=dph, fmt='.', markersize=3, color='tab:blue',
                   elinewidth=0.8)
    if corners:
        stack = np.array(corners)
        m_db = 20.0 * np.log10(np.abs(stack) * 1e6)
        mag.fill_between(f, m_db.min(axis=0), m_db.max(axis=0), color='tab:orange', alpha=0.3,
                         label=f'identified model (w to x) over the {len(corners)} corners '
                         'of the 95 % bounds')
        m_ph = np.degrees(np.unwrap(np.angle(stack), axis=1))
        phase.fill_between(f, m_ph.min(axis=0), m_ph.max(axis=0), color='tab:orange', alpha=0.3)
    mag.semilogx(f, 20.0 * np.log10(np.abs(fit.model) * 1e6), color='tab:red', linestyle='--',
                 linewidth=1.2, label='fit (small-signal k_p, hysteresis phase)')
    phase.semilogx(f, np.degrees(np.unwrap(np.angle(fit.model))), color='tab:red',
                   linestyle='--', linewidth=1.2)
    mag.set_xscale('log')
    dress(mag, None, 'magnitude [dB re 1 um/V]', legend='lower left', which='both', fontsize=8)
    dress(phase, 'frequency [Hz]', 'phase [deg]', which='both')
    wn = result.checked.result.factors.omega_n_rad_s
    mag.set_title(f'Closed-loop frequency response: {data.segments} periods averaged, w_n = '
                  f'{wn:.5g} rad/s, chi2/dof {periodic.chi2_per_dof:.2f}', fontsize=10)
    return save_figure(fig, path)


def write_commission_report(result: CommissionResult, out_dir: str | Path, *,
                            true_stage: StageParams | None = None,
                            extra: Mapping[str, Any] | None = None) -> list[Path]:
    """
    Write the JSON summary and the figures of a commissioning run.

    Parameters
    ----------
    result : CommissionResult
        The run.
    out_dir : str or Path
        Directory (created).
    true_stage : StageParams, optional
        The simulated stage, for the recovered-vs-true section of the JSON.
    extra : Mapping, optional
        Added to the JSON (e.g. the parameter file written).

    Returns
    -------
    list of Path
        The files written, ``report.json`` last.

    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    frf = plot_closed_loop_frf(result, out / 'frequency_response.png')
    if frf is not None:
        files.append(frf)
    files.append(plot_tracking(result.whole, out / 'excitation.png',
                               title='Hold and excitation (closed loop throughout)'))
    ver = result.verification
    files.append(plot_tracking(ver.record, out / 'verification.png',
                               title=f'Verification: {ver.frequency_hz:g} Hz sine, e_rms '
                               f'{ver.e_rms_m * 1e9:.1f} nm'))
    doc = summary(result, true_stage)
    doc['files'] = [p.name for p in files]
    doc.update(extra or {})
    path = out / 'report.json'
    path.write_text(json.dumps(doc, indent=2, default=float) + '\n', encoding='utf-8')
    files.append(path)
    return files
