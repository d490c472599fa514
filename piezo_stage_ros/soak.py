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
``soak``: a long closed-loop run (default one simulated hour at 10 kHz, 36 M samples).

The RAC tracks the configured multi-sine (``trajectory_node multisine.*``, 10 + 100 Hz) in
chunks of one second (:func:`piezo_stage_ros.core.loop.closed_loop.run` with ``keep=False``), so
memory stays flat; each chunk is reduced at once to per-minute statistics:

- e_m and e_rms of the minute (is the error bounded and stationary?);
- the range of theta_hat and phi_hat (do they stay inside their projection bounds?), read every
  10 samples as the loop records them;
- the range of the command over every sample (does it ever leave the amplifier's -2 ... 10 V?);
- the resident memory of the process at the end of the minute (does it grow?).

The verdict compares the last minute with the first: e_rms ratio, memory growth. Options:
``--minutes N`` for a short run, ``--bag DIR`` to stream the whole run into a bag, ``--json``.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import sys
from typing import Any

import numpy as np
from piezo_stage_ros import cli
from piezo_stage_ros.core.contracts.wire import STORAGE_IDS
from piezo_stage_ros.core.control.controllers import ControllerParams
from piezo_stage_ros.core.loop.trajectories import TrajectoryParams
from piezo_stage_ros.core.model.stage import PlantParams

__all__ = ['main', 'rss_mb']

PROG = 'soak'


def rss_mb() -> float:
    """Return the resident memory of this process [MB] (peak RSS where /proc is missing)."""
    try:
        with open('/proc/self/status', encoding='ascii') as status:
            for line in status:
                if line.startswith('VmRSS:'):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class _Minute:
    """Running statistics of one minute of the run."""

    def __init__(self) -> None:
        self.sum_sq = 0.0
        self.e_max = 0.0
        self.samples = 0
        self.cmd_min = math.inf
        self.cmd_max = -math.inf
        self.theta = [math.inf, -math.inf]
        self.phi = [math.inf, -math.inf]

    def add(self, error: np.ndarray[Any, Any], command: np.ndarray[Any, Any],
            diagnostics: dict[str, np.ndarray[Any, Any]]) -> None:
        self.sum_sq += float(np.dot(error, error))
        self.e_max = max(self.e_max, float(np.max(np.abs(error))))
        self.samples += error.size
        self.cmd_min = min(self.cmd_min, float(np.min(command)))
        self.cmd_max = max(self.cmd_max, float(np.max(command)))
        for name, rng in (('theta_hat', self.theta), ('phi_hat', self.phi)):
            if name in diagnostics:
                rng[0] = min(rng[0], float(np.min(diagnostics[name])))
                rng[1] = max(rng[1], float(np.max(diagnostics[name])))

    def row(self, minute: int, rss: float, wall: float) -> dict[str, Any]:
        def clean(v: float) -> float | None:
            return v if math.isfinite(v) else None
        return {'minute': minute, 'samples': self.samples,
                'e_rms_m': math.sqrt(self.sum_sq / max(self.samples, 1)),
                'e_max_m': self.e_max, 'command_min_v': self.cmd_min,
                'command_max_v': self.cmd_max, 'theta_hat_min': clean(self.theta[0]),
                'theta_hat_max': clean(self.theta[1]), 'phi_hat_min': clean(self.phi[0]),
                'phi_hat_max': clean(self.phi[1]), 'rss_mb': rss, 'wall_s': wall}


def _parser() -> argparse.ArgumentParser:
    p = cli.Parser(prog=PROG, description='Soak test: a long closed-loop run with per-minute '
                   'statistics (error, estimates, command range, memory).')
    p.add_argument('--minutes', type=float, default=60.0, metavar='N',
                   help='Simulated minutes (default 60: one hour, 36 M samples at 10 kHz).')
    cli.add_config_options(p)
    p.add_argument('--plant', choices=cli.choices(PlantParams, 'model'),
                   help='Plant model (default: the configured one).')
    p.add_argument('--controller', choices=cli.choices(ControllerParams, 'type'), default='rac',
                   help='Controller (default rac).')
    cli.add_feedforward_option(p)
    p.add_argument('--trajectory', choices=cli.choices(TrajectoryParams, 'kind'),
                   default='multisine', help='Trajectory (default multisine).')
    p.add_argument('--seed', type=int, metavar='N', help='Seed of the sensor noise.')
    p.add_argument('--noise', type=float, metavar='M', help='Sensor noise std [m].')
    p.add_argument('--bag', metavar='DIR', help='Stream the whole run into a rosbag2 bag.')
    p.add_argument('--storage', choices=STORAGE_IDS, default=STORAGE_IDS[0])
    p.add_argument('--overwrite', action='store_true', help='Replace an existing bag.')
    p.add_argument('--json', action='store_true', help='Print one JSON object on stdout.')
    return p


def _soak(args: argparse.Namespace) -> int:
    from piezo_stage_ros.core.control.stability import check_stability
    from piezo_stage_ros.core.loop.experiments import run_one
    from piezo_stage_ros.core.loop.record import RunRecord

    if not (args.minutes > 0 and math.isfinite(args.minutes)):
        from piezo_stage_ros.core.contracts.errors import ParameterError
        raise ParameterError('--minutes', args.minutes, '(0, inf)')
    loop = cli.offline_loop(PROG, cli.loop_overrides(
        cli.read_config(args.config, args.param), plant=args.plant, controller=args.controller,
        trajectory=args.trajectory, seed=args.seed, noise=args.noise,
        feedforward=args.feedforward))
    stage, ctrl, traj = loop.stage, loop.controller, loop.trajectory
    report = check_stability(ctrl, loop.design_plant, stage.sample_time_s,
                             options=loop.stability)
    if not report.stable:
        print(f'{PROG}: WARNING: UNSTABLE CONFIGURATION: {report.text()}', file=sys.stderr)
    duration = args.minutes * 60.0
    per_minute = int(round(60.0 * stage.sample_rate_hz))
    rows: list[dict[str, Any]] = []
    state = {'minute': _Minute(), 'done': 0}
    shown = cli.Progress(PROG)
    rss0 = rss_mb()
    writer: Any = None

    def on_chunk(chunk: RunRecord) -> None:
        if writer is not None:
            writer.write_chunk(chunk)
        err = chunk.position_m - chunk.reference_m
        cmd = chunk.command_v
        i = 0
        while i < err.size:
            minute: _Minute = state['minute']  # type: ignore[assignment]
            take = min(err.size - i, per_minute - minute.samples)
            minute.add(err[i:i + take], cmd[i:i + take],
                       {k: v[i:i + take] for k, v in chunk.diagnostics.items()})
            i += take
            if minute.samples == per_minute:
                row = minute.row(len(rows) + 1, rss_mb(), shown.elapsed())
                rows.append(row)
                shown.line(f'minute {row["minute"]:3d}: e_rms '
                           f'{row["e_rms_m"] * 1e9:7.2f} nm, e_m {row["e_max_m"] * 1e9:7.2f} '
                           f'nm, u {row["command_min_v"]:.3f} ... {row["command_max_v"]:.3f} '
                           f'V, theta_hat {row["theta_hat_min"]} ... '
                           f'{row["theta_hat_max"]}, RSS {row["rss_mb"]:.1f} MB')
                state['minute'] = _Minute()

    meta = {'soak_minutes': args.minutes, 'stable': bool(report.stable)}
    if args.bag is not None:
        from piezo_stage_ros.analysis.bagwrite import RunBagWriter
        with RunBagWriter(args.bag, storage=args.storage, overwrite=args.overwrite) as writer:
            run_one(stage, ctrl, traj, duration_s=duration, chunk_callback=on_chunk, keep=False,
                    meta=meta)
    else:
        run_one(stage, ctrl, traj, duration_s=duration, chunk_callback=on_chunk, keep=False,
                meta=meta)
    last: _Minute = state['minute']  # type: ignore[assignment]
    if last.samples:
        rows.append(last.row(len(rows) + 1, rss_mb(), shown.elapsed()))
    wall = shown.elapsed()
    bounds = ctrl.rac
    summary = _verdict(rows, ctrl.type, bounds, stage.chain.amplifier_min_v,
                       stage.chain.amplifier_max_v)
    summary.update({'sim_seconds': duration, 'wall_seconds': wall,
                    'realtime_factor': duration / wall, 'samples': sum(r['samples'] for r in rows),
                    'rss_start_mb': rss0, 'stable': bool(report.stable),
                    'plant': stage.plant.model, 'controller': ctrl.type,
                    'trajectory': traj.kind})
    if args.json:
        print(json.dumps({'summary': summary, 'minutes': rows}, sort_keys=True))
    else:
        _print(rows, summary)
    return 0 if summary['passed'] else 3


def _verdict(rows: list[dict[str, Any]], ctype: str, bounds: Any, vmin: float,
             vmax: float) -> dict[str, Any]:
    """Return the soak verdict from the per-minute rows."""
    e_rms = [r['e_rms_m'] for r in rows]
    first = rows[0]
    steady = rows[1:] if len(rows) > 1 else rows
    rms_ratio = e_rms[-1] / e_rms[0] if e_rms[0] > 0 else math.inf
    spread = (max(r['e_rms_m'] for r in steady) / min(r['e_rms_m'] for r in steady)
              if min(r['e_rms_m'] for r in steady) > 0 else math.inf)
    cmd_min = min(r['command_min_v'] for r in rows)
    cmd_max = max(r['command_max_v'] for r in rows)
    out: dict[str, Any] = {
        'minutes': len(rows), 'e_rms_first_m': e_rms[0], 'e_rms_last_m': e_rms[-1],
        'e_rms_last_over_first': rms_ratio, 'e_rms_max_over_min_after_first': spread,
        'e_max_m': max(r['e_max_m'] for r in rows), 'command_min_v': cmd_min,
        'command_max_v': cmd_max, 'command_in_range': vmin <= cmd_min and cmd_max <= vmax,
        'rss_first_minute_mb': first['rss_mb'], 'rss_last_minute_mb': rows[-1]['rss_mb'],
        'rss_growth_mb': rows[-1]['rss_mb'] - first['rss_mb']}
    ok = out['command_in_range'] and out['rss_growth_mb'] < 20.0 and spread < 1.5
    if ctype == 'rac':
        th = [v for r in rows for v in (r['theta_hat_min'], r['theta_hat_max']) if v is not None]
        ph = [v for r in rows for v in (r['phi_hat_min'], r['phi_hat_max']) if v is not None]
        out.update({'theta_hat_min': min(th), 'theta_hat_max': max(th),
                    'phi_hat_min': min(ph), 'phi_hat_max': max(ph),
                    'theta_bounds': [bounds.theta_min, bounds.theta_max],
                    'phi_bounds': [bounds.phi_min, bounds.phi_max]})
        out['estimates_in_bounds'] = (bounds.theta_min <= min(th) and max(th) <= bounds.theta_max
                                      and bounds.phi_min <= min(ph)
                                      and max(ph) <= bounds.phi_max)
        ok = ok and out['estimates_in_bounds']
    out['passed'] = bool(ok)
    out['criteria'] = ('command within the amplifier range on every sample; RSS growth from '
                       'the first to the last minute < 20 MB; per-minute e_rms after the first '
                       'minute within a factor 1.5 (max/min); RAC estimates within their '
                       'projection bounds')
    return out


def _print(rows: list[dict[str, Any]], s: dict[str, Any]) -> None:
    print(f'soak: {s["controller"]} on the {s["plant"]} plant, trajectory {s["trajectory"]}, '
          f'{s["sim_seconds"]:g} s simulated ({s["samples"]} samples) in '
          f'{s["wall_seconds"]:.1f} s wall ({s["realtime_factor"]:.1f}x real time)')
    print(f'{"minute":>6}  {"e_rms [nm]":>10}  {"e_m [nm]":>9}  {"u min [V]":>9}  '
          f'{"u max [V]":>9}  {"theta_hat":>17}  {"phi_hat":>21}  {"RSS [MB]":>8}')
    for r in rows:
        th = (f'{r["theta_hat_min"]:.4f}..{r["theta_hat_max"]:.4f}'
              if r['theta_hat_min'] is not None else '-')
        ph = (f'{r["phi_hat_min"]:.3e}..{r["phi_hat_max"]:.3e}'
              if r['phi_hat_min'] is not None else '-')
        print(f'{r["minute"]:>6}  {r["e_rms_m"] * 1e9:>10.3f}  {r["e_max_m"] * 1e9:>9.2f}  '
              f'{r["command_min_v"]:>9.3f}  {r["command_max_v"]:>9.3f}  {th:>17}  {ph:>21}  '
              f'{r["rss_mb"]:>8.1f}')
    print(f'e_rms last/first minute: {s["e_rms_last_over_first"]:.3f}; max/min after the first '
          f'minute: {s["e_rms_max_over_min_after_first"]:.3f}')
    print(f'command range over every sample: {s["command_min_v"]:.3f} ... '
          f'{s["command_max_v"]:.3f} V (in range: {s["command_in_range"]})')
    if 'estimates_in_bounds' in s:
        print(f'theta_hat {s["theta_hat_min"]:.4f} ... {s["theta_hat_max"]:.4f} in '
              f'{s["theta_bounds"]}, phi_hat {s["phi_hat_min"]:.3e} ... {s["phi_hat_max"]:.3e} '
              f'in {s["phi_bounds"]}: {s["estimates_in_bounds"]}')
    print(f'RSS: {s["rss_first_minute_mb"]:.1f} MB after minute 1, '
          f'{s["rss_last_minute_mb"]:.1f} MB at the end (growth {s["rss_growth_mb"]:+.1f} MB)')
    print(f'verdict: {"PASSED" if s["passed"] else "FAILED"} ({s["criteria"]})')


main = cli.command_main(PROG, _parser, _soak,
                        '0 passed, 1 bad parameter or configuration, 2 bad usage, '
                        '3 the soak failed a criterion')


if __name__ == '__main__':
    sys.exit(main())
