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
Control over the axes of a multi-axis stage: one controller per axis, stepped together.

Each axis has the controller the one-axis loop builds (:func:`build_controller`: RAC or PI, the
notch, the feed-forward with its learning), designed on that axis' model, so that a one-axis
stage is controlled exactly as today. They are stepped one after the other in plain Python:
the batched controller of :mod:`piezo_stage_ros.core.loop.batch` vectorises over members with
numpy, which pays at hundreds of members, but at three its two dozen array operations per
sample cost an order of magnitude more than three scalar steps (``benchmark --suite axes``).

Coupling compensation (feed-forward with the model inverse, periodic references): the drive of
axis i moves axis j by d_ij = H_ij(z) w_i, H_ij the coupling path of the design model from the
hysteresis output w_i. With the model inverse, w_i is about G_i(z)^-1 x_d,i, so axis j is
predicted to move by d_j = sum_i H_ij(z) G_i(z)^-1 x_d,i; its feed-forward adds
-G_j(z)^-1 d_j / c to its model input (c the hysteresis slope, as the model inverse itself),
computed once per bind on the harmonics of axis j's period (exact there, as the model inverse
is). The feedback still tracks x_d,j: the compensation only removes what the model predicts.
The driving axes' references must repeat within that period (a raster's lines within its
frame, the axes of a Lissajous scan within their common period).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Sequence

import numpy as np
from piezo_stage_ros.core.contracts.errors import ParameterError
from piezo_stage_ros.core.contracts.interfaces import Trajectory
from piezo_stage_ros.core.contracts.types import ComplexArray, FloatArray
from piezo_stage_ros.core.control.ahead import AxesAhead
from piezo_stage_ros.core.control.controllers import build_controller, ControllerParams
from piezo_stage_ros.core.control.feedforward import FeedForwardController, LEARN_SPECTRUM_SAMPLES
from piezo_stage_ros.core.model.axes import (
    AxesStageParams,
    coupling_paths,
    CouplingPath,
    state_response,
)
from piezo_stage_ros.core.model.hysteresis import make_hysteresis
from piezo_stage_ros.core.model.stage import linear_plant

__all__ = ['AxesController', 'CoupledLoopCheck', 'coupled_displacement', 'coupled_loop_check',
           'path_responses']


def path_responses(path: CouplingPath, z: ComplexArray) -> tuple[ComplexArray,
                                                                 dict[int, ComplexArray]]:
    """
    Return the discrete responses from the driving axis' w [V]: its own position, each path's.

    Parameters
    ----------
    path : CouplingPath
        The discretised paths of one driving axis.
    z : ndarray of complex
        Points of the z-plane (e.g. the harmonics of a period on the unit circle).

    Returns
    -------
    own : ndarray of complex
        G_i(z) [m/V].
    coupled : dict
        {moved axis: H_ij(z) [m/V]}.

    """
    order = path.c.size
    zz = np.asarray(z, dtype=np.complex128).ravel()
    states = state_response(path.ad_full, path.bd_full, zz)
    own = states[:, :order] @ path.c
    coupled: dict[int, ComplexArray] = {}
    zero = np.zeros(zz.size, dtype=np.complex128)
    for j, kappa in path.static:
        coupled[j] = np.asarray(coupled.get(j, zero) + kappa * own, dtype=np.complex128)
    for p, j in enumerate(path.targets):
        coupled[j] = np.asarray(coupled.get(j, zero) + path.gains[p] * states[:, order + 2 * p],
                                dtype=np.complex128)
    return np.asarray(own, dtype=np.complex128), coupled


def coupled_displacement(paths: Sequence[CouplingPath], target: int,
                         references: dict[int, FloatArray]) -> FloatArray:
    """
    Return the displacement of axis ``target`` the other axes' periodic references predict.

    Parameters
    ----------
    paths : sequence of CouplingPath
        The design model's coupling (:func:`coupling_paths`).
    target : int
        The moved axis.
    references : dict
        {driving axis: one period of its reference [m]}, all of the same length N.

    Returns
    -------
    ndarray
        d_target over the period [m] (zero when nothing drives the axis).

    """
    n = len(next(iter(references.values())))
    out = np.zeros(n // 2 + 1, dtype=np.complex128)
    z = np.exp(2j * math.pi * np.arange(n // 2 + 1) / n)
    for path in paths:
        if path.source not in references:
            continue
        own, coupled = path_responses(path, z)
        if target not in coupled:
            continue
        spectrum = np.fft.rfft(references[path.source])
        # H_ij / G_i: the path from the driving axis' position (its model inverse undone)
        tiny = 1e-9 * float(np.max(np.abs(own)))
        ratio = np.where(np.abs(own) > tiny, coupled[target] / np.where(
            np.abs(own) > tiny, own, 1.0), 0.0)
        out += ratio * spectrum
    return np.asarray(np.fft.irfft(out, n), dtype=np.float64)


class AxesController:
    """
    One controller per axis, stepped together; coupling compensation in the feed-forward.

    Parameters
    ----------
    controllers : sequence of Controller
        One per axis (as :func:`build_controller` builds them).
    design : AxesStageParams, optional
        The design model of the stage (axes and coupling) the compensation inverts.
    compensate : bool
        Add the coupling compensation to the feed-forwards with a model inverse.
    params : sequence of ControllerParams, optional
        Each axis' configuration (:func:`coupled_loop_check` needs it).

    """

    def __init__(self, controllers: Sequence[Any], design: AxesStageParams | None = None,
                 *, compensate: bool = True,
                 params: Sequence[ControllerParams] | None = None) -> None:
        self.controllers = list(controllers)
        #: Each axis' configuration, when built from it (:meth:`build`).
        self.params = tuple(params) if params is not None else None
        self.n = len(self.controllers)
        self.design = design
        self.compensate = compensate
        self._paths = coupling_paths(design) if design is not None else []
        self._steps = [c.step for c in self.controllers]
        self._last = [0.0] * self.n
        self._ahead = AxesAhead(self.controllers)
        #: The axes whose feed-forward got a coupling compensation at the last bind.
        self.compensated: tuple[int, ...] = ()
        #: Per axis, the displacement the compensation was computed for over its period [m].
        self.predicted_m: dict[int, FloatArray] = {}
        t = {float(c.sample_time_s) for c in self.controllers}
        if len(t) != 1:
            raise ParameterError('controllers', sorted(t), 'one sample time for every axis')
        self.sample_time_s = t.pop()

    @classmethod
    def build(cls, params: Sequence[ControllerParams], design: AxesStageParams, *,
              compensate: bool = True) -> AxesController:
        """
        Build each axis' controller on that axis' model, as the one-axis loop does.

        Parameters
        ----------
        params : sequence of ControllerParams
            One per axis.
        design : AxesStageParams
            The stage: each axis' plant and hysteresis are its controller's design model, the
            coupling the compensation's.
        compensate : bool
            Coupling compensation in the feed-forward.

        Returns
        -------
        AxesController

        """
        if len(params) != design.n:
            raise ParameterError('controllers', len(params), f'{design.n}, one per axis '
                                 f'{list(design.names)}')
        ctrls = [build_controller(p, s.sample_time_s, linear_plant(s.plant),
                                  make_hysteresis(s.hysteresis))
                 for p, s in zip(params, design.axes)]
        if design.n > 1:
            # several axes: a long period learns on its harmonics, the sample's work even and
            # small (one axis stays the one-axis controller, bit for bit)
            for c in ctrls:
                if isinstance(c, FeedForwardController):
                    c.spectrum_samples = LEARN_SPECTRUM_SAMPLES
        return cls(ctrls, design, compensate=compensate, params=params)

    def bind(self, trajectories: Sequence[Trajectory]) -> None:
        """
        Bind every feed-forward to its axis' trajectory and add the coupling compensation.

        Parameters
        ----------
        trajectories : sequence of Trajectory
            One per axis.

        Raises
        ------
        ParameterError
            If a driving axis' reference does not repeat within a compensated axis' period.

        """
        if len(trajectories) != self.n:
            raise ParameterError('trajectories', len(trajectories), f'{self.n}, one per axis')
        for c, tr in zip(self.controllers, trajectories):
            bind = getattr(c, 'bind', None)
            if callable(bind):
                bind(tr)
        self.compensated = ()
        self.predicted_m = {}
        if not (self.compensate and self._paths):
            return
        done = []
        dt = self.sample_time_s
        for j, c in enumerate(self.controllers):
            if not isinstance(c, FeedForwardController) or not c.params.inverse:
                continue
            n = c.reference_tables(0)[0]
            sources = {p.source for p in self._paths if p.source != j and (
                j in p.targets or any(t == j for t, _ in p.static))}
            if not n or not sources:
                continue
            # one period from the second, as the feed-forward's own tables
            refs: dict[int, FloatArray] = {}
            t = np.arange(n, 2 * n, dtype=np.float64) * dt
            for i in sources:
                x = np.asarray(trajectories[i].evaluate(t)[0], dtype=np.float64)
                again = np.asarray(trajectories[i].evaluate(t + n * dt)[0], dtype=np.float64)
                scale = float(np.max(np.abs(x))) or 1.0
                if float(np.max(np.abs(again - x))) > 1e-9 * scale:
                    name = self.design.names[i] if self.design is not None else str(i)
                    raise ParameterError('feedforward.period_s', n * dt, 'a period over which '
                                         f'every driving axis repeats (axis {name!r} does not)',
                                         'cannot carry the coupling compensation')
                refs[i] = x
            d = coupled_displacement(self._paths, j, refs)
            c.add_to_inverse(-c.plant_inverse.periodic(d) / c.slope)
            self.predicted_m[j] = d
            done.append(j)
        self.compensated = tuple(done)

    def reset(self, positions_m: Sequence[float], references_m: Sequence[float]) -> None:
        """Reset every axis' controller from its measured position and reference."""
        for c, y, r in zip(self.controllers, positions_m, references_m):
            c.reset(y, r)

    def step(self, positions_m: Sequence[float], references_m: Sequence[float],
             velocities_mps: Sequence[float]) -> list[float]:
        """
        Return every axis' command [V] for one sample.

        Parameters
        ----------
        positions_m, references_m, velocities_mps : sequence of float
            y_k, x_d and x_d' per axis.

        Returns
        -------
        list of float

        """
        out = [s(y, r, v) for s, y, r, v in zip(self._steps, positions_m, references_m,
                                                 velocities_mps)]
        self._last = out
        return out

    def predict(self, count: int) -> list[FloatArray]:
        """
        Return each axis' ``count`` commands ahead [V].

        A feed-forward's own prediction from its tables; a controller without one holds its
        last command here (the servo's :class:`~piezo_stage_ros.core.control.ahead.
        CommandPredictor` per axis is the servo's to add).
        """
        out = []
        for j, c in enumerate(self.controllers):
            pred = getattr(c, 'predict', None)
            out.append(pred(count) if callable(pred) else np.full(count, self._last[j]))
        return out

    def predict_array(self, count: int) -> FloatArray:
        """
        Return every axis' ``count`` commands ahead as one (axes, count) array [V].

        Row j equals ``predict(count)[j]``; the axes whose feed-forward has a whole period's
        tables are predicted together (:class:`~piezo_stage_ros.core.control.ahead.AxesAhead`).
        """
        return self._ahead.predict(count, self._last)

    def step_ahead(self, positions_m: Sequence[float], references_m: Sequence[float],
                   velocities_mps: Sequence[float], count: int
                   ) -> tuple[list[float], FloatArray]:
        """
        Return one sample's commands [V] and the (axes, ``count``) commands ahead [V].

        :meth:`step`, then :meth:`predict_array`: the one call a servo makes per sample.
        """
        out = [s(y, r, v) for s, y, r, v in zip(self._steps, positions_m, references_m,
                                                 velocities_mps)]
        self._last = out
        return out, self._ahead.predict(count, out)

    def step_ahead_rows(self, positions_m: Sequence[float], references_m: Sequence[float],
                        velocities_mps: Sequence[float], count: int
                        ) -> tuple[list[float], list[Any]]:
        """
        Return one sample's commands [V] and each axis' ``count`` commands ahead [V].

        :meth:`step_ahead` with the commands ahead computed when read
        (:meth:`~piezo_stage_ros.core.control.ahead.AxesAhead.rows`): the same values, one
        sequence per axis, for a servo whose backend reads them only for the samples it
        misses.
        """
        out = [s(y, r, v) for s, y, r, v in zip(self._steps, positions_m, references_m,
                                                 velocities_mps)]
        self._last = out
        return out, self._ahead.rows(count, out)

    def diagnostic_names(self) -> list[tuple[str, ...]]:
        """Return each axis' controller's diagnostic names."""
        return [tuple(getattr(c, 'diagnostic_names', ())) for c in self.controllers]


@dataclass(frozen=True)
class CoupledLoopCheck:
    """
    The axes' loops checked together with the coupling (:func:`coupled_loop_check`).

    Attributes
    ----------
    coupling_gain : float
        sup over frequency of the spectral radius of M = (I + P_d K)^-1 P_o K: the coupling
        paths P_o closed through the other axes' loops. Below 1 the coupled loop is stable
        whenever each axis' own loop is (small gain); 0 for coupling one way only.
    coupling_frequency_hz : float
        Where the supremum is [Hz].
    learning_ratio : float or None
        The largest contraction per period of the learning on the coupled stage: the spectral
        radius of I - P_cl D over the harmonics the learning axes keep (P_cl the coupled
        loop's process sensitivity, D = gamma Q / P_s of each axis' design); the design model
        without coupling gives |1 - gamma|. None when no axis learns.
    learning_frequency_hz : float or None
        Where that largest ratio is [Hz].

    """

    coupling_gain: float
    coupling_frequency_hz: float
    learning_ratio: float | None
    learning_frequency_hz: float | None

    @property
    def certified(self) -> bool:
        """Return whether the small-gain test certifies the coupled loop (gain < 1)."""
        return self.coupling_gain < 1.0

    def text(self) -> str:
        """Return the verdict in one line."""
        out = (f'coupled loops: small-gain radius {self.coupling_gain:.3g} at '
               f'{self.coupling_frequency_hz:.4g} Hz ('
               + ("certified stable with the axes' own loops" if self.certified else
                  'not certified by the small-gain test') + ')')
        if self.learning_ratio is not None:
            out += (f'; learning contracts by {self.learning_ratio:.3g} a period at worst '
                    f'({self.learning_frequency_hz:.4g} Hz)'
                    + ('' if self.learning_ratio < 1.0 else ': NOT CONVERGENT'))
        return out


def coupled_loop_check(ctrl: AxesController, points: int = 4000) -> CoupledLoopCheck:
    """
    Check the axes' linearised loops together with the design model's coupling.

    Each axis' loop is the one the one-axis stability check linearises (the controller's
    linear gains at its present estimates, its notch, the hysteresis as its slope c), checked
    per axis by :func:`~piezo_stage_ros.core.control.stability.check_stability`. With the
    plant P(z) from the axes' commands to their positions (diagonal: c_i G_i; off the diagonal:
    c_i H_ij, the coupling paths) and K = diag(N_i C_i k_i), det(I + P K) = det(I + P_d K)
    det(I + M) with M = (I + P_d K)^-1 P_o K; when every axis' own loop is stable and the
    spectral radius of M stays below 1 on the unit circle, no eigenvalue of I + s M crosses 0
    as the coupling grows from 0 (s from 0 to 1), so the coupled loop is stable too (sufficient,
    not necessary). The learning iterates E <- (I - P_cl D) E per harmonic over the axes that
    learn it.

    Parameters
    ----------
    ctrl : AxesController
        Built by :meth:`AxesController.build` (design model and parameters known).
    points : int
        Frequencies on a log grid from 1e-4 of Nyquist to Nyquist.

    Returns
    -------
    CoupledLoopCheck

    """
    from piezo_stage_ros.core.control.feedforward import BANDWIDTH_STRETCH, process_sensitivity
    from piezo_stage_ros.core.control.stability import stability_plant
    from piezo_stage_ros.core.model.hysteresis import NoHysteresis

    design, params = ctrl.design, ctrl.params
    if design is None or params is None:
        raise ParameterError('ctrl', 'an AxesController without design or parameters',
                             'one built by AxesController.build')
    n = design.n
    t = ctrl.sample_time_s
    omega = np.geomspace(1e-4, 1.0 - 1e-9, points) * math.pi / t
    z = np.exp(1j * omega * t)
    plant = np.zeros((z.size, n, n), dtype=np.complex128)
    k_fb = np.zeros((z.size, n), dtype=np.complex128)
    slopes, fbs = [], []
    for j, (sp, cp, c) in enumerate(zip(design.axes, params, ctrl.controllers)):
        hyst = make_hysteresis(sp.hysteresis)
        slope = 1.0 if isinstance(hyst, NoHysteresis) else float(hyst.slope)
        d = stability_plant(sp.plant).discretize(t)
        plant[:, j, j] = slope * (state_response(d.ad, d.bd[:, 0], z) @ d.c)
        fb = c.inner if isinstance(c, FeedForwardController) else c
        k_p, k_i = fb.linear_gains()
        with np.errstate(divide='ignore', invalid='ignore'):
            cz = k_p + (k_i * t * z / (z - 1.0) if k_i else 0.0)
        notch = getattr(fb, 'notch', None)
        if notch is not None:
            cz = cz * np.polyval(notch.num, z) / np.polyval(notch.den, z)
        k_fb[:, j] = cz * cp.sensor_gain_v_per_m
        slopes.append(slope)
        fbs.append((k_p, k_i, None if notch is None else (notch.num, notch.den)))
    for path in coupling_paths(design):
        _, coupled = path_responses(path, z)
        for j, h in coupled.items():
            plant[:, j, path.source] += slopes[path.source] * h
    own = np.einsum('kjj->kj', plant)
    m = plant * k_fb[:, None, :] / (1.0 + own * k_fb)[:, :, None]
    for j in range(n):
        m[:, j, j] = 0.0
    radius = np.max(np.abs(np.linalg.eigvals(m)), axis=1)
    worst = int(np.argmax(radius))
    freq = omega / (2.0 * math.pi)
    learning = [j for j, c in enumerate(ctrl.controllers)
                if isinstance(c, FeedForwardController) and c.params.learning]
    ratio: float | None = None
    ratio_hz: float | None = None
    if learning:
        eye = np.eye(n)
        p_cl = np.linalg.solve(eye[None] + plant * k_fb[:, None, :], plant)
        d_gain = np.zeros((z.size, n), dtype=np.complex128)
        for j in learning:
            ff = ctrl.controllers[j].params
            k_p, k_i, notch_j = fbs[j]
            # the diagonal is the axis' own c G (the paths fill the rest): the design P_s
            ps = process_sensitivity(plant[:, j, j], z, k_p, k_i,
                                     params[j].sensor_gain_v_per_m, t, notch_j)
            # every frequency some line's kept harmonic can lie at: Q keeps a fast line's
            # first harmonics up to BANDWIDTH_STRETCH times its edge (kept_harmonics)
            kept = (freq <= BANDWIDTH_STRETCH * ff.learning_bandwidth_hz) & (np.abs(ps) > 0.0)
            d_gain[kept, j] = ff.learning_gain / ps[kept]
        best = 0.0
        for k in range(z.size):
            s_idx = [j for j in learning if d_gain[k, j] != 0.0]
            if not s_idx:
                continue
            block = np.eye(len(s_idx)) - p_cl[k][np.ix_(s_idx, s_idx)] * d_gain[k, s_idx][None]
            r = float(np.max(np.abs(np.linalg.eigvals(block))))
            if r > best:
                best, ratio_hz = r, float(freq[k])
        ratio = best
    return CoupledLoopCheck(float(radius[worst]), float(freq[worst]), ratio, ratio_hz)

