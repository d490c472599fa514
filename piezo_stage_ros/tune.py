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
The discrete-time tuning study of the RAC: ``python3 -m piezo_stage_ros.tune``.

It reproduces the table of docs/explanation/controllers.md: the Table III sines x_d = 3.8 + 3.8
sin(2 pi f t) um at 1, 10, 50 and 100 Hz, on the default stage (10 kHz, 16-bit converters,
backlash-like hysteresis) with the reduced plant (25) and the third-order plant (20), for

1. the stability verdict of the paper's gains and of the default tuning (every linearized loop of
   :mod:`piezo_stage_ros.core.control.stability`);
2. a sweep of the boundary layer epsilon with the other default gains (no notch, reduced plant);
3. a small (k_d, lambda) grid with the notch;
4. a sweep of the initial estimate phi_hat(0) (in steady state the estimates sit still inside
   the boundary layer, so phi_hat(0) is the feedforward gain on dy_d/dt);
5. what the adaptation buys when the plant gain differs from the model's;
6. Table III: e_rms and e_max of the paper's PI, the paper's RAC and the default RAC on both
   plants, with and without the notch;
7. the same with one sample of computational delay (each command applied a sample late in the
   simulation, and the check with ``stability.delay_samples = 1``): the default, which is sized
   to pass it, and the faster tuning :data:`FAST` that tracks closer and fails it;
8. the discrete adaptation loop: the bound of :func:`piezo_stage_ros.core.control.stability.
   adaptation_bound` per model, and the square-wave steady state (Fig. 10, and a 3.8 -> 28 um
   square wave near the top of the reachable range) against the adaptation rates gamma, eta;
9. the stage family (:mod:`piezo_stage_ros.core.model.family`): the worst stage of each case
   for the default, for the wide-dead-zone tuning :data:`OLD_DEFAULT`, for the reference
   tuning :data:`REFERENCE_TUNING` and for one change at a time from the default
   (``--family`` runs only this section, about 3 minutes);
10. the delay trade (``--delay`` runs only this section): tunings that pass the check with one
   sample of computational delay against what they cost on the Table III sines and on the stage
   family, and the largest delay each keeps its frozen loops stable at.

Errors are those of :func:`piezo_stage_ros.core.loop.metrics.summarize` (measured position,
steady-state window after max(2 periods, 0.1 s)). The default run takes about a minute.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Mapping, Sequence

import numpy as np
from piezo_stage_ros import cli
from piezo_stage_ros.core.contracts.interfaces import Controller
from piezo_stage_ros.core.control.controllers import (
    build_controller,
    ControllerParams,
    NotchParams,
    PIParams,
    RACParams,
)
from piezo_stage_ros.core.control.stability import (
    adaptation_bound,
    check_stability,
    stability_plant,
    StabilityParams,
)
from piezo_stage_ros.core.loop.closed_loop import run
from piezo_stage_ros.core.loop.experiments import run_one, square_edge_metrics
from piezo_stage_ros.core.loop.metrics import summarize
from piezo_stage_ros.core.loop.trajectories import make_trajectory, TrajectoryParams
from piezo_stage_ros.core.model.linear import ReducedParams
from piezo_stage_ros.core.model.stage import PlantParams, Stage, StageParams

PROG = 'tune'
FREQUENCIES_HZ = (1.0, 10.0, 50.0, 100.0)

#: Table III of the paper, e_rms [nm].
PAPER_RAC_NM = {1.0: 4.4, 10.0: 5.6, 50.0: 17.6, 100.0: 39.4}
PAPER_PIC_NM = {1.0: 13.8, 10.0: 131.4, 50.0: 614.4, 100.0: 1004.6}

#: The paper's RAC, section V (its epsilon chatters at 10 kHz).
PAPER_RAC = RACParams(k_d=1.5, lambda_per_s=1500.0, epsilon_v=0.005, k_star_v=0.2, gamma=3000.0,
                      eta=0.01, adaptation_dead_zone_v=0.005, normalisation=0.0,
                      adaptation_regressor='measured',
                      theta_min=0.5, theta_max=4.0, theta_init=1.0, phi_min=1e-4,
                      phi_max=5e-3, phi_init=7.5e-4, rho_v=0.18, c_min=1.0)
NOTCH_OFF = NotchParams(mode='off')

#: A faster tuning than the default: it tracks the 100 Hz sine about twice as closely, but its
#: box corner theta_min, phi_max inside the boundary layer fails the check with half a sample
#: of computational delay already; the default is sized to pass with one sample.
FAST = RACParams(lambda_per_s=3000.0, epsilon_v=0.2, normalisation=20.0, phi_init=2.5e-4)


#: A comparison case: the RAC with its adaptation dead zone as wide as the boundary layer
#: (0.2 V), which keeps the estimates still while tracking, the paper's measured regressors
#: and no normalisation; it shows what the default's narrow dead zone and law buy.
OLD_DEFAULT = RACParams(gamma=10.0, eta=1e-6, adaptation_dead_zone_v=0.2,
                        adaptation_regressor='measured', normalisation=0.0, theta_min=0.9,
                        theta_max=1.7, phi_min=2.2e-4, phi_max=5.5e-4, phi_init=5e-4)
#: The narrower notch that :data:`OLD_DEFAULT` runs with.
OLD_NOTCH = NotchParams(pole_damping=1.0)

#: The best tuning found that is stable on the third-order model (20) *without* the notch
#: (every corner, >= 3 dB and >= 35 deg, with :data:`OLD_DEFAULT`'s box and law, whose
#: estimates do not move); it differs from :data:`OLD_DEFAULT` in k_d, lambda, epsilon,
#: phi_hat(0).
WITHOUT_NOTCH = OLD_DEFAULT.replace(k_d=0.4, lambda_per_s=2000.0, epsilon_v=0.6,
                                    phi_init=4.2e-4)
#: A reference tuning for the reduced plant, the paper's measured regressors adapting fast:
#: its own 2 mV dead zone, gamma 300, eta 1e-4, a wider box.
REFERENCE_TUNING = OLD_DEFAULT.replace(gamma=300.0, eta=1e-4, adaptation_dead_zone_v=0.002,
                                      theta_max=2.0, phi_min=2e-4, phi_max=6e-4)

#: Cases of section 9 (keys of :data:`piezo_stage_ros.core.loop.robustness.CASES`), with the sensor
#: noise they run with: None keeps each stage's own (0 or 3 nm), a number sets it on every
#: stage [m rms].
FAMILY_CASES: tuple[tuple[str, str, float | None], ...] = (
    ('100 Hz', 'sine_100', None), ('10 Hz', 'sine_10', None),
    ('Fig. 10 square, 3 nm', 'square', 3e-9), ('Fig. 10 S-curve 2 ms, 3 nm', 'square_2ms', 3e-9),
)


def family_worst(params: ControllerParams, *, duration_s: float = 2.0
                 ) -> dict[str, tuple[float, str, float]]:
    """
    Run the stage family on the cases of :data:`FAMILY_CASES` and return the worst stages.

    Parameters
    ----------
    params : ControllerParams
        Controller, the same on every stage (nothing retuned).
    duration_s : float
        Simulated time per run [s]; the steady state starts after 1 s.

    Returns
    -------
    dict
        Case label -> (largest e_rms [m], its stage, the nominal stage's e_rms [m]); for the
        sines, noise-free stages and stages with 3 nm noise apart (``'10 Hz, noisy stages'``),
        since 3 nm of sensor noise alone puts about 3.5 nm into the measured error.

    """
    from dataclasses import replace as dc_replace

    from piezo_stage_ros.core.loop.robustness import run_study
    from piezo_stage_ros.core.model.family import default_family

    stage = StageParams.from_flat({'plant.model': 'third_order'})
    family = default_family()
    out: dict[str, tuple[float, str, float]] = {}
    for label, case, noise in FAMILY_CASES:
        members = family if noise is None else tuple(dc_replace(m, noise_m=noise)
                                                     for m in family)
        res = run_study(stage, params, TrajectoryParams(), family=members, cases=[case],
                        duration_s=duration_s)
        noisy = {m.name for m in members if m.noise_m > 0.0}
        groups = [(label, [r for r in res.rows if noise is not None or r['stage'] not in noisy])]
        if noise is None and noisy:
            groups.append((f'{label}, noisy stages', [r for r in res.rows
                                                      if r['stage'] in noisy]))
        nominal = next(r['e_rms_m'] for r in res.rows if r['stage'] == 'nominal')
        for name, rows in groups:
            top = max(rows, key=lambda r: r['e_rms_m'] if r['e_rms_m'] == r['e_rms_m']
                      else np.inf)
            out[name] = (top['e_rms_m'], top['stage'], nominal)
    return out


def family_table() -> None:
    """Print section 9: the worst stage of the family per case, per configuration."""
    default = ControllerParams()
    d = default.rac
    rows: list[tuple[str, ControllerParams]] = [
        ('default', default),
        ('wide dead zone (never adapts)', controller('rac', rac=OLD_DEFAULT).replace(
            notch=OLD_NOTCH)),
        ('reference tuning (measured regressors)', controller(
            'rac', rac=REFERENCE_TUNING).replace(notch=OLD_NOTCH)),
        ('measured regressors', controller('rac', rac=d.replace(
            adaptation_regressor='measured'))),
        ('gamma 300', controller('rac', rac=d.replace(gamma=300.0))),
        ('gamma 30', controller('rac', rac=d.replace(gamma=30.0))),
        ('eta 1e-3', controller('rac', rac=d.replace(eta=1e-3))),
        ('theta_min 0.9', controller('rac', rac=d.replace(theta_min=0.9))),
        ('theta_min 1.1', controller('rac', rac=d.replace(theta_min=1.1))),
        ('phi_init 4e-4', controller('rac', rac=d.replace(phi_init=4e-4))),
        ('phi_max 7e-4', controller('rac', rac=d.replace(phi_max=7e-4))),
        ('notch pole damping 1.0', default.replace(notch=OLD_NOTCH)),
        ('dead zone 0.2 V (= epsilon)', controller('rac', rac=d.replace(
            adaptation_dead_zone_v=0.2))),
    ]
    heads = [label for label, _, _ in FAMILY_CASES]
    heads.insert(2, '10 Hz, noisy stages')
    print(_row(['configuration', *heads, 'nominal 100 / 10 Hz', 'check (model (20))']))
    print(_row(['---'] * (len(heads) + 3)))
    for name, params in rows:
        w = family_worst(params)
        cells = [f'{w[h][0] * 1e9:.1f} ({w[h][1]})' for h in heads]
        rep = check_stability(params, PlantParams(model='third_order'), 1e-4)
        check = ('stable over the box' if rep.certified else 'loops unstable'
                 if not rep.stable else 'adaptation above bound')
        check += f', GM {rep.gain_margin_db:.1f} dB, PM {rep.phase_margin_deg:.0f} deg'
        nominal = f"{w['100 Hz'][2] * 1e9:.1f} / {w['10 Hz'][2] * 1e9:.1f}"
        print(_row([name, *cells, nominal, check]), flush=True)


#: Section 10: tunings against the delay (label, changes from the default RAC).
DELAY_TRADE: tuple[tuple[str, dict[str, float]], ...] = (
    ('default', {}),
    ('FAST (lambda 3000, epsilon 0.2, kappa 20)', {
        'lambda_per_s': 3000.0, 'epsilon_v': 0.2, 'normalisation': 20.0, 'phi_init': 2.5e-4}),
    ('lambda 3000, epsilon 0.4, phi_max 7e-4', {'lambda_per_s': 3000.0, 'phi_max': 7e-4}),
    ('lambda 3000, epsilon 0.5, phi_max 6e-4', {
        'lambda_per_s': 3000.0, 'epsilon_v': 0.5, 'phi_max': 6e-4}),
    ('lambda 2500, epsilon 0.6', {'lambda_per_s': 2500.0, 'epsilon_v': 0.6}),
    ('lambda 2500, epsilon 0.4', {'lambda_per_s': 2500.0}),
)


def delay_table() -> None:
    """Print section 10: the check against the computational delay, and what passing costs."""
    from piezo_stage_ros.check import delay_margin
    from piezo_stage_ros.core.loop.robustness import run_study
    from piezo_stage_ros.core.model.family import default_family

    print('\n## 10. The delay trade: the check (third-order model, frozen parameters over the '
          'box) at 0, 0.5 and 1 sample of computational delay, the largest delay the frozen '
          'loops stay stable at, Table III e_rms on the reduced plant (short runs) and the '
          "family's worst 100 Hz e_rms (2 s runs)\n")
    print(_row(['tuning', 'delay 0', 'delay 0.5', 'delay 1', 'delay margin [samples]',
                '10 Hz [nm]', '50 Hz [nm]', '100 Hz [nm]', 'family 100 Hz worst [nm]']))
    print(_row(['---'] * 9))
    third = PlantParams(model='third_order')
    stage = StageParams.from_flat({'plant.model': 'third_order'})
    base = ControllerParams()
    for label, changes in DELAY_TRADE:
        params = base.replace(rac=base.rac.replace(**changes))
        cells = [verdict(params, 'third_order', delay_samples=d) for d in (0.0, 0.5, 1.0)]

        def stable(d: float, params: ControllerParams = params) -> bool:
            return check_stability(params, third, 1e-4,
                                   options=StabilityParams(delay_samples=d)).stable
        cells.append(f'{delay_margin(stable):.2f}')
        cells += [f'{track(params, "reduced", f)[0] * 1e9:.1f}' for f in (10.0, 50.0, 100.0)]
        res = run_study(stage, params, TrajectoryParams(), family=default_family(),
                        cases=['sine_100'], duration_s=2.0)
        top = max(res.rows, key=lambda r: r['e_rms_m'] if r['e_rms_m'] == r['e_rms_m']
                  else np.inf)
        cells.append(f"{top['e_rms_m'] * 1e9:.1f} ({top['stage']})")
        print(_row([label, *cells]), flush=True)


class Delayed:
    """
    A controller whose command reaches the plant one sample late (study only).

    Parameters
    ----------
    inner : Controller
        The controller; its first command is applied at once, then each one a sample late.

    """

    def __init__(self, inner: Controller) -> None:
        self.inner = inner
        self._last: float | None = None

    @property
    def sample_time_s(self) -> float:
        """Return the inner controller's sample time [s]."""
        return self.inner.sample_time_s

    def reset(self, position_m: float, reference_m: float) -> None:
        """Reset the inner controller and empty the delay line."""
        self.inner.reset(position_m, reference_m)
        self._last = None

    def step(self, position_m: float, reference_m: float,
             reference_velocity_mps: float) -> float:
        """Return the command computed one sample earlier [V]."""
        u = self.inner.step(position_m, reference_m, reference_velocity_mps)
        out = u if self._last is None else self._last
        self._last = u
        return out

    def diagnostics(self) -> Mapping[str, float]:
        """Return the inner controller's diagnostics."""
        return self.inner.diagnostics()


def controller(kind: str, *, rac: RACParams | None = None, pi: PIParams | None = None,
               notch: bool = True) -> ControllerParams:
    """
    Return controller parameters for the study.

    Parameters
    ----------
    kind : str
        ``'rac'`` or ``'pi'``.
    rac : RACParams, optional
        RAC gains; default the package default.
    pi : PIParams, optional
        PI gains; default the paper's PIC.
    notch : bool
        Keep the default notch (True) or switch it off.

    Returns
    -------
    ControllerParams

    """
    base = ControllerParams(type=kind)
    changes: dict[str, object] = {}
    if rac is not None:
        changes['rac'] = rac
    if pi is not None:
        changes['pi'] = pi
    if not notch:
        changes['notch'] = NOTCH_OFF
    return base.replace(**changes) if changes else base


def track(params: ControllerParams, model: str, frequency_hz: float,
          sample_rate_hz: float = 10000.0, *, delay: bool = False,
          plant_gain_scale: float = 1.0, duration_s: float | None = None
          ) -> tuple[float, float]:
    """
    Run one Table III sine and return the steady-state errors.

    Parameters
    ----------
    params : ControllerParams
        Controller.
    model : str
        Plant model, ``'reduced'`` or ``'third_order'`` (or ``'electromechanical'``).
    frequency_hz : float
        Sine frequency [Hz].
    sample_rate_hz : float
        Loop rate [Hz].
    delay : bool
        Apply each command one sample late (:class:`Delayed`).
    plant_gain_scale : float
        Factor on the DC gain of the simulated reduced plant (the controller is not told).
    duration_s : float, optional
        Simulated time [s]; default the steady-state window plus one period or 0.1 s.

    Returns
    -------
    e_rms_m, e_max_m : float
        Over the steady-state window of :func:`piezo_stage_ros.core.loop.metrics.summarize` [m].

    """
    stage_params = StageParams.from_flat({
        'plant.model': model, 'sample_rate_hz': sample_rate_hz,
        'plant.reduced.gain_m_per_v': ReducedParams().gain_m_per_v * plant_gain_scale})
    stage = Stage(stage_params)
    plant = stability_plant(stage_params.plant)
    ctrl: Controller = build_controller(params, stage.sample_time_s,
                                        plant if plant.name != 'reduced' else None)
    if delay:
        ctrl = Delayed(ctrl)
    traj = make_trajectory(TrajectoryParams.from_flat({'kind': 'sine',
                                                       'sine.frequency_hz': frequency_hz}))
    period = 1.0 / frequency_hz
    skip = max(2.0 * period, 0.1)
    duration = skip + max(period, 0.1) + 0.5 / sample_rate_hz
    if duration_s is not None:
        duration = duration_s
    record = run(stage, ctrl, traj, duration_s=duration, record_diagnostics=False)
    m = summarize(record, period_s=period)
    return m.e_rms_m, m.e_max_m


def square_steady_state(params: ControllerParams, model: str, *, high_m: float = 11.6e-6,
                        period_s: float = 0.5, periods: int = 2
                        ) -> tuple[float, float, float, float]:
    """
    Run an ideal square wave from 3.8 um and return its steady state and the theta_hat range.

    Parameters
    ----------
    params : ControllerParams
        Controller.
    model : str
        Plant model.
    high_m : float
        High level [m] (Fig. 10: 11.6 um).
    period_s : float
        Period [s] (Fig. 10: 0.5 s).
    periods : int
        Periods run.

    Returns
    -------
    ss_e_rms_m, ss_e_max_m : float
        Measured minus reference over the last half of every plateau [m].
    theta_min, theta_max : float
        Range of theta_hat over the run [V/V].

    """
    tp = TrajectoryParams.from_flat({'kind': 'square', 'square.peak_to_peak_m': high_m - 3.8e-6,
                                     'square.period_s': period_s})
    rec = run_one(StageParams.from_flat({'plant.model': model}), params, tp,
                  duration_s=periods * period_s)
    m = square_edge_metrics(rec.time_s, rec.position_m, rec.reference_m, tp.square)
    theta = np.asarray(rec.diagnostics['theta_hat'])
    return m.ss_e_rms_m, m.ss_e_max_m, float(np.min(theta)), float(np.max(theta))


def verdict(params: ControllerParams, model: str, sample_time_s: float = 1e-4,
            delay_samples: float | None = None) -> str:
    """
    Return 'stable (GM x dB, PM y deg)' or 'UNSTABLE (radius r)' over the box's frozen loops.

    ``delay_samples`` defaults to the check's default computational delay.
    """
    opts = StabilityParams() if delay_samples is None else StabilityParams(
        delay_samples=delay_samples)
    rep = check_stability(params, PlantParams(model=model), sample_time_s, options=opts)
    if rep.stable:
        return f'stable (GM {rep.gain_margin_db:.1f} dB, PM {rep.phase_margin_deg:.0f} deg)'
    return f'UNSTABLE (radius {rep.spectral_radius:.3f})'


def _row(cells: Sequence[str]) -> str:
    return '| ' + ' | '.join(cells) + ' |'


def errors_row(params: ControllerParams, model: str, *, with_max: bool = False,
               delay: bool = False) -> list[str]:
    """Return the e_rms (and e_max) cells [nm] over :data:`FREQUENCIES_HZ`."""
    cells = []
    for f in FREQUENCIES_HZ:
        e_rms, e_max = track(params, model, f, delay=delay)
        cells.append(f'{e_rms * 1e9:.1f} / {e_max * 1e9:.1f}' if with_max
                     else f'{e_rms * 1e9:.1f}')
    return cells




def build_parser() -> argparse.ArgumentParser:
    """Return the command-line parser of ``tune``."""
    parser = cli.Parser(prog=PROG, description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('--skip-sweeps', action='store_true',
                        help='print only the stability verdicts and Table III')
    parser.add_argument('--family', action='store_true',
                        help='print only section 9, the stage family (about 3 minutes)')
    parser.add_argument('--delay', action='store_true',
                        help='print only section 10, the delay trade (about a minute)')
    parser.add_argument('--params-table', action='store_true',
                        help='print the Markdown table of the controller_node parameters and exit')
    return parser


def _study(args: argparse.Namespace) -> int:
    """Print the study's tables (or the parameter table)."""
    if args.params_table:
        # the node's own table (docs/parameters.md is generated from the same declarations)
        from piezo_stage_ros.core.config.loader import controller_table
        print(controller_table().markdown())
        return 0
    start = time.monotonic()
    if args.delay:
        delay_table()
        print(f'\n(study took {time.monotonic() - start:.0f} s)')
        return 0
    if args.family:
        print('## 9. The stage family: worst e_rms [nm] (stage) over the family, steady state '
              'after 1 s of 2 s runs\n')
        family_table()
        print(f'\n(study took {time.monotonic() - start:.0f} s)')
        return 0
    default = ControllerParams()
    d = default.rac
    freqs = ' | '.join(f'{f:g} Hz' for f in FREQUENCIES_HZ)

    print('## 1. Frozen-parameter stability over the box (10 kHz, the default computational '
          f'delay of {StabilityParams().delay_samples:g} samples)\n')
    print(_row(['controller', 'reduced (25)', 'third-order (20)']))
    print(_row(['---'] * 3))
    cases = [
        ('paper PIC (k_p 1.5, k_i 1500)', controller('pi', notch=False)),
        ('paper RAC (epsilon 0.005, paper bounds)', controller('rac', rac=PAPER_RAC,
                                                               notch=False)),
        ('default RAC, no notch', controller('rac', notch=False)),
        ('default RAC + notch (default)', default),
        ('RAC tuned without notch', controller('rac', rac=WITHOUT_NOTCH, notch=False)),
        ('paper PIC + notch', controller('pi')),
    ]
    for name, params in cases:
        print(_row([name, verdict(params, 'reduced'), verdict(params, 'third_order')]))

    if not args.skip_sweeps:
        print('\n## 2. Boundary layer epsilon, other gains default, no notch, reduced plant '
              '(e_rms nm)\n')
        print(_row(['epsilon [V]', 'k_d + k*/epsilon', freqs, 'reduced', 'third-order + notch']))
        print(_row(['---'] * (4 + len(FREQUENCIES_HZ))))
        for eps in (0.005, 0.02, 0.05, 0.1, 0.2, 0.5):
            rac = d.replace(epsilon_v=eps)
            p_off = controller('rac', rac=rac, notch=False)
            print(_row([f'{eps:g}', f'{d.k_d + d.k_star_v / eps:.3g}',
                        *errors_row(p_off, 'reduced'), verdict(p_off, 'reduced'),
                        verdict(controller('rac', rac=rac), 'third_order')]), flush=True)

        print('\n## 3. k_d and lambda at the default epsilon, with the notch (100 Hz e_rms)\n')
        print(_row(['k_d', 'lambda [1/s]', 'reduced 100 Hz [nm]', 'reduced',
                    'third-order + notch']))
        print(_row(['---'] * 5))
        for k_d in (0.5, 1.0, 1.5):
            for lam in (1500.0, 3000.0, 4500.0):
                p = controller('rac', rac=d.replace(k_d=k_d, lambda_per_s=lam))
                e_rms, _ = track(p, 'reduced', 100.0)
                print(_row([f'{k_d:g}', f'{lam:g}', f'{e_rms * 1e9:.1f}', verdict(p, 'reduced'),
                            verdict(p, 'third_order')]), flush=True)

        print('\n## 4. Initial estimate phi_hat(0) (the feedforward gain on dy_d/dt), with the '
              'notch (e_rms nm)\n')
        print(_row(['phi_hat(0) [s]', 'reduced 50 Hz', 'reduced 100 Hz', 'third-order 100 Hz']))
        print(_row(['---'] * 4))
        for phi0 in (3.16e-4, 3.8e-4, 4.2e-4, 4.6e-4, 5.0e-4, 5.5e-4):
            p = controller('rac', rac=d.replace(phi_init=phi0))
            cells = [f'{track(p, m, f)[0] * 1e9:.1f}'
                     for m, f in (('reduced', 50.0), ('reduced', 100.0), ('third_order', 100.0))]
            print(_row([f'{phi0:g}', *cells]), flush=True)

        print('\n## 5. What the adaptation buys: reduced plant with its gain g scaled, the '
              'controller not told, 100 Hz, 0.5 s (e_rms nm)\n')
        print(_row(['g / g_model', 'default RAC + notch', 'adaptation off (gamma = eta = 0)']))
        print(_row(['---'] * 3))
        frozen = controller('rac', rac=d.replace(gamma=0.0, eta=0.0))
        for scale in (0.6, 0.8, 1.0, 1.25):
            errs = [track(p, 'reduced', 100.0, plant_gain_scale=scale, duration_s=0.5)[0]
                    for p in (default, frozen)]
            cells = [f'{e * 1e9:.1f}' for e in errs]
            print(_row([f'{scale:g}', *cells]), flush=True)

    print('\n## 6. Table III on the default stage: e_rms / e_max [nm]\n')
    print(_row(['controller', 'plant', freqs]))
    print(_row(['---'] * (2 + len(FREQUENCIES_HZ))))
    print(_row(['paper PIC (experiment)', 'real stage',
                *(f'{PAPER_PIC_NM[f]:g}' for f in FREQUENCIES_HZ)]))
    print(_row(['paper RAC (experiment)', 'real stage',
                *(f'{PAPER_RAC_NM[f]:g}' for f in FREQUENCIES_HZ)]))
    rows = [
        ('paper PIC', controller('pi', notch=False), 'reduced'),
        ('paper RAC (epsilon 0.005)', controller('rac', rac=PAPER_RAC, notch=False), 'reduced'),
        ('default RAC, no notch', controller('rac', notch=False), 'reduced'),
        ('default RAC + notch', default, 'reduced'),
        ('paper PIC', controller('pi', notch=False), 'third_order'),
        ('paper PIC + notch', controller('pi'), 'third_order'),
        ('default RAC, no notch', controller('rac', notch=False), 'third_order'),
        ('RAC tuned without notch', controller('rac', rac=WITHOUT_NOTCH, notch=False),
         'third_order'),
        ('default RAC + notch', default, 'third_order'),
        ('default RAC + notch', default, 'electromechanical'),
    ]
    for name, params, model in rows:
        print(_row([name, model, *errors_row(params, model, with_max=True)]), flush=True)

    print('\n## 7. One sample of computational delay (u_k applied at t_k+1): e_rms / e_max [nm] '
          'and the verdict with stability.delay_samples = 1\n')
    print(_row(['controller', 'plant', freqs, 'verdict']))
    print(_row(['---'] * (3 + len(FREQUENCIES_HZ))))
    for name, params in (('paper PIC', controller('pi', notch=False)),
                         ('default RAC + notch', default),
                         ('fast RAC + notch (FAST)', controller('rac', rac=FAST))):
        for model in ('reduced', 'third_order'):
            print(_row([name, model, *errors_row(params, model, with_max=True, delay=True),
                        verdict(params, model, delay_samples=1)]), flush=True)
    if not args.skip_sweeps:
        print('\n## 8. The discrete adaptation loop\n')
        print(_row(['plant', 'y_max [V]', 'u_fd_max = lambda y_max [V/s]', 'g_crit (corners)',
                    'g_crit (initial estimates)', 'g -> g/(1 + kappa g) of the default',
                    'max gamma (eta 0 / default eta)']))
        print(_row(['---'] * 7))
        for model in ('reduced', 'third_order', 'electromechanical'):
            b = adaptation_bound(default, PlantParams(model=model), 1e-4)
            b0 = adaptation_bound(default, PlantParams(model=model), 1e-4,
                                  options=StabilityParams(estimates='initial'))
            print(_row([model, f'{b.y_max_v:.2f}', f'{b.u_fd_max_v_per_s:.3g}',
                        f'{b.critical_gain:.3f}', f'{b0.critical_gain:.3f}',
                        f'{b.gain:.3g} -> {b.effective_gain:.3g}',
                        f'{b.max_gamma(0.0):.1f} / {b.max_gamma():.1f}']))
        print('\nSquare waves from 3.8 um with the default RAC and the rates below (ideal jumps, '
              '2 periods): steady-state e_rms / e_max [nm] over the last half of every '
              'plateau, and the theta_hat range; g / g_crit at y_max on the reduced model, '
              'g/(1 + kappa g) with the default kappa.\n')
        print(_row(['gamma', 'eta', 'g_eff / g_crit', 'Fig. 10 reduced', 'Fig. 10 third-order',
                    '28 um reduced', '28 um third-order', 'theta_hat range (Fig. 10 reduced)']))
        print(_row(['---'] * 8))
        crit = adaptation_bound(default, PlantParams(model='reduced'), 1e-4)
        for gamma, eta in ((3000.0, 0.01), (3000.0, d.eta), (1000.0, d.eta), (300.0, d.eta),
                           (100.0, d.eta), (30.0, d.eta), (10.0, 0.01), (d.gamma, d.eta)):
            p = controller('rac', rac=d.replace(gamma=gamma, eta=eta))
            g = crit.sample_time_s * (gamma * crit.y_max_v ** 2
                                      + eta * crit.u_fd_max_v_per_s ** 2)
            ratio = g / (1.0 + d.normalisation * g)
            cells = []
            rng = ''
            for high, period in ((11.6e-6, 0.5), (28e-6, 0.1)):
                for model in ('reduced', 'third_order'):
                    e_rms, e_max, t0, t1 = square_steady_state(p, model, high_m=high,
                                                               period_s=period)
                    cells.append(f'{e_rms * 1e9:.1f} / {e_max * 1e9:.1f}')
                    if high == 11.6e-6 and model == 'reduced':
                        rng = f'{t0:.3f} ... {t1:.3f}'
            print(_row([f'{gamma:g}', f'{eta:g}', f'{ratio / crit.critical_gain:.3g}', *cells,
                        rng]), flush=True)
    if not args.skip_sweeps:
        print('\n## 9. The stage family: worst e_rms [nm] (stage) over the family, steady '
              'state after 1 s of 2 s runs\n')
        family_table()
        delay_table()
    print(f'\n(study took {time.monotonic() - start:.0f} s)')
    return 0


main = cli.command_main(PROG, build_parser, _study, '0 success, 1 bad parameter, 2 bad usage')


if __name__ == '__main__':
    sys.exit(main())
