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
PNG figures of a multi-axis run (a bag of several axes).

- ``error_<axis>.png``: each axis' tracking error versus time (the one-axis figure); for an
  open-loop run, which has no reference, ``response_<axis>.png`` instead: the axis' command and
  its position versus time;
- ``frame_error.png``: a raster frame's error as images, the fast and the slow axis, rows the
  lines (slow axis up) from the fast axis' low turn-around, columns the time along a line:
  trace, then retrace (:func:`~piezo_stage_ros.core.loop.axes.frame_images`);
- ``grating.png``: a cross grating imaged over that frame at the positions reached, trace and
  retrace, and how far its lines are displaced in the image
  (:func:`~piezo_stage_ros.core.loop.axes.grating_image`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from matplotlib.figure import Figure
import numpy as np
from piezo_stage_ros.analysis.plots import (
    _DPI,
    _envelope,
    _new,
    _relative_time,
    _save,
    dress,
    plot_error,
)
from piezo_stage_ros.core.loop.axes import frame_images, GratingImage, line_start
from piezo_stage_ros.core.loop.record import RunRecord

__all__ = ['plot_axes_run', 'plot_frame_error', 'plot_grating', 'plot_response']


def plot_frame_error(fast: RunRecord, slow: RunRecord, path: Path, *, lines: int,
                     title: str = '') -> Path:
    """
    Draw the last whole raster frame's error of the fast and the slow axis as images.

    A row is a line from the fast axis' low turn-around: trace, then (after the dashed line)
    retrace. The measured position's error, and below it the true position's where the run
    has one (a simulation).

    Parameters
    ----------
    fast, slow : RunRecord
        The raster's axes.
    path : Path
        PNG to write.
    lines : int
        Lines per frame.
    title : str
        Figure title prefix.

    Returns
    -------
    Path
        ``path``.

    """
    start = line_start(fast)
    kinds = [('measured', False)]
    if fast.true_position_m is not None and slow.true_position_m is not None:
        kinds.append(('true', True))
    dt = float(fast.meta['sample_time_s'])
    fig = Figure(figsize=(10.0, 4.2 * len(kinds)), dpi=_DPI, layout='constrained')
    for row, (kind, true) in enumerate(kinds):
        images = frame_images(fast, slow, lines=lines, start=start, true=true)
        # the fast axis' high turn-around: where the trace ends and the retrace begins
        period = images[0].shape[1]
        turn = int(np.argmax(fast.reference_m[start:start + period])) * dt * 1e3
        for k, (rec, image) in enumerate(zip((fast, slow), images)):
            ax = fig.add_subplot(len(kinds), 2, 2 * row + k + 1)
            limit = float(np.nanmax(np.abs(image))) * 1e9 or 1.0
            shown = ax.imshow(image * 1e9, origin='lower', aspect='auto', cmap='RdBu_r',
                              vmin=-limit, vmax=limit,
                              extent=(0.0, period * dt * 1e3, -0.5, lines - 0.5))
            ax.axvline(turn, color='k', lw=0.6, ls='--')
            ax.set_xlabel('time along the line [ms] (trace | retrace)')
            ax.set_ylabel('line')
            ax.set_title(f'axis {rec.meta["axis"]}: error of the {kind} position [nm]')
            fig.colorbar(shown, ax=ax)
    fig.suptitle(f'{title}raster frame error (last whole frame)')
    return _save(fig, path)


def plot_grating(grating: GratingImage, path: Path, *, title: str = '') -> Path:
    """
    Draw a grating imaged over a frame, trace and retrace, and its lines' displacement.

    Parameters
    ----------
    grating : GratingImage
        :func:`~piezo_stage_ros.core.loop.axes.grating_image` of the frame.
    path : Path
        PNG to write.
    title : str
        Figure title prefix.

    Returns
    -------
    Path
        ``path``.

    """
    g = grating
    fig = Figure(figsize=(10.0, 8.0), dpi=_DPI, layout='constrained')
    x_um = g.x_m * 1e6
    rows = np.arange(g.y_m.size)
    y_um = np.where(np.isfinite(g.y_m), g.y_m, np.nan) * 1e6
    extent = (float(x_um[0]), float(x_um[-1]), float(np.nanmin(y_um)), float(np.nanmax(y_um)))
    shifts = np.abs(np.concatenate([s.ravel() for s in g.shift_x_m]))
    shifts = shifts[np.isfinite(shifts)]
    limit = max(float(shifts.max()) if shifts.size else 0.0, 1e-12) * 1e9
    marks = np.arange(g.shift_x_m[0].shape[1])
    for k, label in enumerate(('trace', 'retrace')):
        ax = fig.add_subplot(2, 2, k + 1)
        ax.imshow(g.imaged[k], origin='lower', aspect='auto', cmap='gray', extent=extent)
        ax.set_xlabel('x desired [µm]')
        ax.set_ylabel('y desired [µm]')
        ax.set_title(f'{label}: grating imaged at the {g.source} position')
        ax = fig.add_subplot(2, 2, k + 3)
        shown = ax.imshow(g.shift_x_m[k] * 1e9, origin='lower', aspect='auto', cmap='RdBu_r',
                          vmin=-limit, vmax=limit,
                          extent=(-0.5, marks.size - 0.5, -0.5, rows.size - 0.5))
        ax.set_xlabel('grating line (along the fast axis)')
        ax.set_ylabel('image row')
        ax.set_title(f'{label}: line displacement, {g.rms_x_m[k] * 1e9:.2f} nm rms '
                     f'(rows: {g.rms_y_m[k] * 1e9:.2f} nm rms)', fontsize=9)
        fig.colorbar(shown, ax=ax, label='[nm]')
    fig.suptitle(f'{title}grating of {g.pitch_m * 1e6:g} µm pitch over one frame')
    return _save(fig, path)


def plot_response(record: RunRecord, path: Path, title: str = '') -> Path:
    """
    Draw an axis' command [V] and position [um] versus time, one above the other.

    Parameters
    ----------
    record : RunRecord
        One axis of an open-loop run.
    path : Path
        PNG file to write.
    title : str
        Figure title.

    Returns
    -------
    Path
        ``path``.

    """
    fig, (top, bottom) = _new(2, height=6.0)
    t = _relative_time(record)
    top.plot(*_envelope(t, record.command_v), color='tab:green', lw=0.8)
    top.set_title(title)
    dress(top, None, 'command [V]')
    bottom.plot(*_envelope(t, record.position_m * 1e6), color='tab:red', lw=0.8)
    dress(bottom, 'time [s]', 'position [µm]')
    return _save(fig, path)


def plot_axes_run(records: Sequence[RunRecord], outdir: Path, *, title: str = '',
                  fast_axis: str | None = None, slow_axis: str | None = None,
                  lines: int | None = None, grating: GratingImage | None = None,
                  open_loop: bool = False) -> dict[str, Path]:
    """
    Draw the figures of a multi-axis run into a directory.

    Parameters
    ----------
    records : sequence of RunRecord
        One per axis (``meta['axis']``).
    outdir : Path
        Directory for the PNGs (created if needed).
    title : str
        Prefix of the figure titles (e.g. the bag name).
    fast_axis, slow_axis : str, optional
        A raster's axes; with ``lines``, the frame's error is drawn when the run holds a
        whole frame.
    lines : int, optional
        A raster's lines per frame.
    grating : GratingImage, optional
        The grating imaged over the frame.
    open_loop : bool
        An open-loop run (no reference): each axis' command and position instead of its error.

    Returns
    -------
    dict of str to Path
        ``error_<axis>`` (``response_<axis>`` for an open-loop run) per axis, ``frame_error``
        and ``grating`` where drawn.

    """
    outdir.mkdir(parents=True, exist_ok=True)
    prefix = f'{title}: ' if title else ''
    files = {}
    by_name = {str(r.meta['axis']): r for r in records}
    for name, rec in by_name.items():
        if open_loop:
            files[f'response_{name}'] = plot_response(
                rec, outdir / f'response_{name}.png', f'{prefix}axis {name}: open loop')
            continue
        files[f'error_{name}'] = plot_error(rec, outdir / f'error_{name}.png',
                                            f'{prefix}axis {name}: tracking error')
    if grating is not None and fast_axis in by_name and slow_axis in by_name and lines:
        # a grating exists only for a run holding a whole frame
        files['frame_error'] = plot_frame_error(by_name[fast_axis], by_name[slow_axis],
                                                outdir / 'frame_error.png', lines=lines,
                                                title=prefix)
        files['grating'] = plot_grating(grating, outdir / 'grating.png', title=prefix)
    return files
