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
Frequency-response estimate of a recorded run (the paper's Fig. 4 from band-limited noise).

The estimate is the H1 estimator G(f) = S_uy(f) / S_uu(f) (Welch averages, Hann windows, half
overlap) with the magnitude-squared coherence to say where it can be trusted. For a run with
noise or sweep excitation the plant estimate is from the amplifier input v_in to the measured
position x. In closed loop the measurement noise fed back makes H1 biased where the coherence
is low; the plot marks those frequencies.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
import re
from typing import Any

import numpy as np
from piezo_stage_ros.core.contracts.errors import IdentificationError, PiezoStageError
from piezo_stage_ros.core.contracts.types import ComplexArray, FloatArray
from piezo_stage_ros.core.identification.fit import estimate_frequency_response
from piezo_stage_ros.core.loop.record import RunRecord
from piezo_stage_ros.core.model.stage import StageParams

__all__ = ['BodeEstimate', 'estimate_bode', 'is_excitation_run']


_EXCITATION = re.compile(r'chirp|sweep|noise|prbs', re.IGNORECASE)


@dataclass(frozen=True)
class BodeEstimate:
    """
    An estimated frequency response.

    Attributes
    ----------
    frequency_hz : ndarray
        Frequencies [Hz], without 0 Hz.
    response : ndarray of complex
        G(f) in SI units of output per input (e.g. m/V).
    coherence : ndarray
        Magnitude-squared coherence, 0 ... 1.
    unit : str
        Unit of ``response * scale`` (e.g. ``'µm/V'``).
    scale : float
        Factor from SI to ``unit`` (e.g. 1e6 for m -> µm).
    label : str
        What is estimated, e.g. ``'v_in -> x'``.

    """

    frequency_hz: FloatArray
    response: ComplexArray
    coherence: FloatArray
    unit: str
    scale: float
    label: str

    def dc_gain(self, band_hz: tuple[float, float] = (0.0, 50.0)) -> float:
        """
        Return the mean magnitude in a low-frequency band, in SI units.

        Parameters
        ----------
        band_hz : (float, float)
            Frequency band [Hz].

        Returns
        -------
        float
            Mean of |G| over the band (NaN if the band holds no frequency).

        """
        sel = (self.frequency_hz > band_hz[0]) & (self.frequency_hz <= band_hz[1])
        return float(np.mean(np.abs(self.response[sel]))) if sel.any() else float('nan')


def _strings(value: Any) -> list[str]:
    if isinstance(value, str):
        return [value]
    if isinstance(value, Mapping):
        return [s for k, v in value.items() for s in _strings(k) + _strings(v)]
    if isinstance(value, (list, tuple)):
        return [s for v in value for s in _strings(v)]
    return []


def is_excitation_run(meta: Mapping[str, Any]) -> bool:
    """
    Tell from a run's description whether its reference was noise or a sweep.

    Parameters
    ----------
    meta : dict
        ``RunRecord.meta``; ``identification_role == 'frequency'`` (the identification runs)
        decides, else the trajectory entries (``trajectory``, ``kind``, ``experiment``) are
        searched for chirp, sweep, noise or PRBS (a multisine of a few tones is a tracking
        test, not broadband).

    Returns
    -------
    bool
        True when a Bode estimate makes sense.

    """
    if meta.get('identification_role') == 'frequency':  # the identification runs say so
        return True
    trajectory = {k: v for k, v in meta.items() if 'trajectory' in str(k).lower()
                  or str(k).lower() in ('kind', 'experiment', 'excitation')}
    return any(_EXCITATION.search(s) for s in _strings(trajectory))


def estimate_bode(record: RunRecord, *, segment_s: float = 0.05) -> BodeEstimate:
    """
    Estimate the frequency response from v_in to x of a recorded run.

    Parameters
    ----------
    record : RunRecord
        The run, uniformly sampled.
    segment_s : float
        Welch segment length [s]; sets the frequency resolution 1/segment_s (20 Hz by default)
        and, with the run length, the number of averages.

    Returns
    -------
    BodeEstimate
        G(f) = S_uy / S_uu in m/V (plotted in µm/V) with its coherence.

    Raises
    ------
    PiezoStageError
        Fewer than two segments of samples, or a sampling that is not uniform.

    """
    # One H1 estimator for the package: the identification's, on the voltage the amplifier
    # applied (DAC and clamp of the default signal chain), with its checks of the sampling.
    try:
        fr = estimate_frequency_response([record], StageParams().chain, segment_s=segment_s)
    except IdentificationError as exc:
        raise PiezoStageError(f'Bode estimate: {exc}') from None
    return BodeEstimate(
        frequency_hz=fr.frequency_hz,
        response=fr.response,
        coherence=fr.coherence,
        unit='µm/V',
        scale=1e6,
        label='v_in -> x',
    )
