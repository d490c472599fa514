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
Plots and a Markdown report of an identification, like the paper's Figs. 4-6.

- ``frequency_response.png`` (Fig. 4): Bode plot of the H1 estimate from the noise run, the
  discrete-time fit of step 2 and the final model (static gain k_p c), coherence below;
- ``step_response.png`` (Fig. 5): the first 6 ms after the first upward input jump, measured and
  model, and the residual;
- ``hysteresis.png`` (Fig. 6): position against applied voltage, measured and model, and the
  residual in time;
- ``report.md``: every identified value with its standard deviation, the residuals, which run
  was used for what, and the caveats (notes); and, for simulated runs that carry their true
  parameters, the recovered-vs-true table.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

import matplotlib

matplotlib.use('Agg')  # files only; never a window

from matplotlib.figure import Figure  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from piezo_stage_ros.analysis.plots import dress  # noqa: E402
from piezo_stage_ros.core.identification.fit import (  # noqa: E402
    discrete_frequency_response,
    IdentificationResult,
)
from piezo_stage_ros.core.model.linear import (  # noqa: E402
    factors_of,
    LinearFactors,
    third_order_of,
)
from piezo_stage_ros.core.model.stage import StageParams  # noqa: E402

__all__ = ['comparison_rows', 'format_table', 'plot_frequency_response', 'plot_hysteresis',
           'plot_step_response', 'save_figure', 'write_report']


_MODEL_STYLE: dict[str, Any] = {'color': 'tab:red', 'linestyle': '--', 'linewidth': 1.4}
_DATA_STYLE: dict[str, Any] = {'color': 'tab:blue', 'linewidth': 1.2}


def save_figure(fig: Figure, path: Path) -> Path:
    """
    Write a report's figure (tight layout, 110 dpi) to ``path``, close it and return ``path``.

    Parameters
    ----------
    fig : Figure
        A figure made with ``pyplot``; closed here so that a long study does not keep them.
    path : Path
        PNG file to write.

    Returns
    -------
    Path

    """
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_frequency_response(result: IdentificationResult, path: Path) -> Path | None:
    """
    Write the Bode plot (Fig. 4) and return its path, or None without a frequency run.

    Parameters
    ----------
    result : IdentificationResult
        The identification.
    path : Path
        PNG file to write.

    Returns
    -------
    Path or None

    """
    fit = result.frequency
    if fit is None:
        return None
    data = fit.data
    f = data.frequency_hz
    final = LinearFactors(result.static_gain_m_per_v, result.factors.omega_n_rad_s,
                          result.factors.zeta, result.factors.tau_s)
    final_resp = discrete_frequency_response(third_order_of(final), data.sample_time_s, f)
    fig, axes = plt.subplots(3, 1, figsize=(7.5, 8.0), sharex=True,
                             gridspec_kw={'height_ratios': [3, 3, 1.3]})
    mag, phase, coh = axes
    # measured values where the coherence says nothing are dots, and their phase is not drawn
    good = data.coherence >= 0.5
    for freqs, resp, label, style in (
            (f[good], data.response[good], 'measured (H1, noise run)', _DATA_STYLE),
            (f, fit.model, 'fit of step 2 (small-signal k_p)',
             {'color': 'tab:green', 'linewidth': 1.0}),
            (f, final_resp, 'identified model (static gain k_p c)', _MODEL_STYLE)):
        mag.semilogx(freqs, 20.0 * np.log10(np.abs(resp) * 1e6), label=label, **style)
        phase.semilogx(freqs, np.degrees(np.unwrap(np.angle(resp))), **style)
    skipped = ~fit.used
    mag.semilogx(f[skipped], 20.0 * np.log10(np.abs(data.response[skipped]) * 1e6), '.',
                 color='0.6', markersize=3, label='not fitted (band, coherence)')
    dress(mag, None, 'magnitude [dB re 1 um/V]', legend='lower left', which='both', fontsize=8)
    dress(phase, None, 'phase [deg]', which='both')
    coh.semilogx(f, data.coherence, color='0.3', linewidth=1.0)
    coh.set_ylim(0.0, 1.05)
    dress(coh, 'frequency [Hz]', 'coherence', which='both')
    wn_hz = result.factors.omega_n_rad_s / (2.0 * math.pi)
    for ax in axes:
        ax.axvline(wn_hz, color='0.5', linewidth=0.8, linestyle=':')
    mag.set_title(f'Frequency response (Fig. 4): w_n = {result.factors.omega_n_rad_s:.5g} rad/s '
                  f'({wn_hz:.0f} Hz), sampled at {1.0 / data.sample_time_s:.0f} Hz', fontsize=10)
    return save_figure(fig, path)


def plot_step_response(result: IdentificationResult, path: Path,
                       window_s: float = 0.006) -> Path | None:
    """
    Write the step response plot (Fig. 5) and return its path, or None without a step run.

    Parameters
    ----------
    result : IdentificationResult
        The identification.
    path : Path
        PNG file to write.
    window_s : float
        Time shown after the first upward jump [s] (the paper: 6 ms).

    Returns
    -------
    Path or None

    """
    fit = result.step
    if fit is None:
        return None
    rec, model = fit.records[0], fit.models[0]
    u = np.asarray(rec.command_v, dtype=np.float64)
    jumps = np.flatnonzero(np.diff(u) > 0.0) + 1
    k0 = int(jumps[0]) if jumps.size else int(np.flatnonzero(np.diff(u))[0]) + 1
    t = np.asarray(rec.time_s, dtype=np.float64)
    dt = float(t[1] - t[0])
    sel = slice(max(k0 - 5, 0), min(k0 + int(round(window_s / dt)), len(rec)))
    ts = (t[sel] - t[k0]) * 1e3
    y = np.asarray(rec.position_m, dtype=np.float64)
    fig, (ax, res) = plt.subplots(2, 1, figsize=(7.5, 6.0), sharex=True,
                                  gridspec_kw={'height_ratios': [3, 1.3]})
    ax.plot(ts, y[sel] * 1e6, label='measured', **_DATA_STYLE)
    ax.plot(ts, model[sel] * 1e6, label='identified model', **_MODEL_STYLE)
    dress(ax, None, 'position [um]', legend='best', fontsize=8)
    dv = float(u[k0] - u[k0 - 1]) if k0 > 0 else float('nan')
    ax.set_title(f'Step response (Fig. 5): {dv:.3g} V step; zeta = {result.factors.zeta:.4g}, '
                 f'tau = {result.factors.tau_s * 1e3:.4g} ms', fontsize=10)
    res.plot(ts, (y[sel] - model[sel]) * 1e9, color='0.3', linewidth=0.8)
    dress(res, 'time after the step [ms]', 'residual [nm]')
    return save_figure(fig, path)


def plot_hysteresis(result: IdentificationResult, path: Path) -> Path | None:
    """
    Write the hysteresis loop plot (Fig. 6) and return its path, or None without a sine run.

    Parameters
    ----------
    result : IdentificationResult
        The identification.
    path : Path
        PNG file to write.

    Returns
    -------
    Path or None

    """
    fit = result.hysteresis
    if fit is None:
        return None
    rec, v, model = fit.records[0], fit.voltages[0], fit.models[0]
    y = np.asarray(rec.position_m, dtype=np.float64)
    t = np.asarray(rec.time_s, dtype=np.float64)
    fig, (loop, res) = plt.subplots(2, 1, figsize=(7.5, 8.0),
                                    gridspec_kw={'height_ratios': [3, 1.3]})
    loop.plot(v, y * 1e6, label='measured', **_DATA_STYLE)
    loop.plot(v, model * 1e6, label='identified model', **_MODEL_STYLE)
    dress(loop, 'amplifier input v_in [V]', 'position [um]', legend='best', fontsize=8)
    loop.set_title(f'Hysteresis (Fig. 6): {fit.model}, residual rms '
                   f'{fit.residual_rms_m * 1e9:.3g} nm', fontsize=10)
    res.plot((t - t[0]) * 1e3, (y - model) * 1e9, color='0.3', linewidth=0.8)
    dress(res, 'time [ms]', 'residual [nm]')
    return save_figure(fig, path)


def comparison_rows(result: IdentificationResult, true_stage: StageParams
                    ) -> list[tuple[str, float, float, float]]:
    """
    Return (name, true, identified, error in %) for the headline parameters.

    Parameters
    ----------
    result : IdentificationResult
        The identification.
    true_stage : StageParams
        The stage the runs were simulated with.

    Returns
    -------
    list of tuple
        ``static gain k_p c`` (gauge free), w_n, zeta, tau, k_p, K, a0, a1, a2 and, for the
        backlash-like model, alpha, c, B1 and B1/c.

    """
    true_f = factors_of(true_stage.plant.third_order)
    th = true_stage.hysteresis.backlash_like
    rows: list[tuple[str, float, float]] = []
    ident = result.summary()
    if true_stage.hysteresis.model == 'backlash_like':
        rows.append(('static gain k_p c [m/V]', true_f.gain_m_per_v * th.c,
                     ident['static_gain_m_per_v']))
    rows += [('w_n [rad/s]', true_f.omega_n_rad_s, ident['omega_n_rad_s']),
             ('zeta [-]', true_f.zeta, ident['zeta']),
             ('tau [s]', true_f.tau_s, ident['tau_s']),
             ('k_p = K/a2 [m/V]', true_f.gain_m_per_v, ident['gain_m_per_v']),
             ('K', true_stage.plant.third_order.gain, ident['K']),
             ('a0', true_stage.plant.third_order.a0, ident['a0']),
             ('a1', true_stage.plant.third_order.a1, ident['a1']),
             ('a2', true_stage.plant.third_order.a2, ident['a2'])]
    if true_stage.hysteresis.model == 'backlash_like' and 'alpha' in ident:
        rows += [('alpha [1/V]', th.alpha, ident['alpha']), ('c [-]', th.c, ident['c']),
                 ('B1 [-]', th.b1, ident['b1']),
                 ('B1/c [-]', th.b1 / th.c, ident['b1'] / ident['c'])]
    return [(n, t, i, 100.0 * (i / t - 1.0)) for n, t, i in rows]


def format_table(rows: list[tuple[str, float, float, float]]) -> str:
    """
    Return a Markdown table of :func:`comparison_rows`.

    Parameters
    ----------
    rows : list of tuple
        (name, true, identified, error %).

    Returns
    -------
    str

    """
    lines = ['| parameter | true | identified | error |', '| --- | ---: | ---: | ---: |']
    lines += [f'| {n} | {t:.5g} | {i:.5g} | {e:+.2f} % |' for n, t, i, e in rows]
    return '\n'.join(lines)


def _std_rows(result: IdentificationResult) -> list[str]:
    out = ['| quantity | value | std (1 sigma) | from |', '| --- | ---: | ---: | --- |']
    if result.frequency is not None:
        f, s = result.frequency.factors, result.frequency.std
        out += [f'| k_p small-signal [m/V] | {f.gain_m_per_v:.5g} | {s.gain_m_per_v:.2g} | '
                'noise run |',
                f'| w_n [rad/s] | {f.omega_n_rad_s:.6g} | {s.omega_n_rad_s:.2g} | noise run |',
                f'| zeta (frequency fit) | {f.zeta:.5g} | {s.zeta:.2g} | noise run |',
                f'| tau (frequency fit) [s] | {f.tau_s:.5g} | {s.tau_s:.2g} | noise run |']
    if result.step is not None:
        f, s = result.step.factors, result.step.std
        if s.omega_n_rad_s > 0.0:
            out.append(f'| w_n [rad/s] | {f.omega_n_rad_s:.6g} | {s.omega_n_rad_s:.2g} | '
                       'step run |')
        out += [f'| zeta [-] | {f.zeta:.5g} | {s.zeta:.2g} | step run |',
                f'| tau [s] | {f.tau_s:.5g} | {s.tau_s:.2g} | step run |',
                f'| step gain (large signal) [m/V] | {f.gain_m_per_v:.5g} | | step run |']
    if result.hysteresis is not None:
        h = result.hysteresis
        for name, value in h.estimates.items():
            out.append(f'| {name} | {value:.5g} | {h.std.get(name, float("nan")):.2g} | '
                       'sine run |')
    return out


def write_report(result: IdentificationResult, out_dir: str | Path, *,
                 true_stage: StageParams | None = None,
                 extra: Mapping[str, str] | None = None) -> list[Path]:
    """
    Write the three figures and ``report.md`` into ``out_dir`` (created if needed).

    Parameters
    ----------
    result : IdentificationResult
        The identification.
    out_dir : path-like
        Directory for the files.
    true_stage : StageParams, optional
        The true stage of simulated runs: adds the recovered-vs-true table.
    extra : Mapping of str to str, optional
        More lines for the header of the report (e.g. the command and the parameter file).

    Returns
    -------
    list of Path
        The files written, the report last.

    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figures = [p for p in (plot_frequency_response(result, out / 'frequency_response.png'),
                           plot_step_response(result, out / 'step_response.png'),
                           plot_hysteresis(result, out / 'hysteresis.png')) if p is not None]
    lines = ['# Identification report', '']
    for key, value in (extra or {}).items():
        lines.append(f'- {key}: {value}')
    for role, names in result.roles.items():
        if names:
            lines.append(f'- {role} runs: ' + ', '.join(f'`{n}`' for n in names))
    lines += ['', '## Identified model', '',
              '| parameter | value |', '| --- | ---: |']
    lines += [f'| {k} | {v:.6g} |' for k, v in result.summary().items()]
    lines += ['', '## Estimates and their standard deviations', ''] + _std_rows(result)
    lines += ['', '## Residuals', '']
    if result.frequency is not None:
        lines.append(f'- frequency response: rms |log(model/measured)| = '
                     f'{result.frequency.rms_log_error:.3g} over '
                     f'{int(result.frequency.used.sum())} frequencies')
    if result.step is not None:
        lines.append(f'- step response: rms {result.step.residual_rms_m * 1e9:.3g} nm')
    if result.hysteresis is not None:
        lines.append(f'- sine run: rms {result.hysteresis.residual_rms_m * 1e9:.3g} nm')
    lines.append(f'- sensor noise estimate (step residual, quantization removed): '
                 f'{result.stage.chain.sensor_noise_std_m * 1e9:.3g} nm')
    if true_stage is not None:
        lines += ['', '## Recovered vs true (simulated runs)', '',
                  format_table(comparison_rows(result, true_stage))]
    if result.notes:
        lines += ['', '## Notes', ''] + [f'- {n}' for n in result.notes]
    lines += ['', '## Figures', ''] + [f'![{p.stem}]({p.name})' for p in figures]
    report = out / 'report.md'
    report.write_text('\n'.join(lines) + '\n', encoding='utf-8')
    return figures + [report]
