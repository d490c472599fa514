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
Project exceptions.

Every error the package raises on purpose derives from :class:`PiezoStageError`, so a command-line
program can catch it and print one clear line instead of a traceback.
"""

from __future__ import annotations

from typing import Any


class PiezoStageError(Exception):
    """Base class of every error raised on purpose by piezo_stage_ros."""


class ParameterError(PiezoStageError, ValueError):
    """
    A parameter has a bad value.

    Parameters
    ----------
    name : str
        Dotted parameter name, e.g. ``'controller.rac.epsilon'``.
    value : Any
        The offending value.
    allowed : str
        The allowed values or range, in words, e.g. ``'(0, inf)'`` or ``"one of 'rac', 'pi'"``.
    reason : str, optional
        What is wrong, when it is not simply "out of range".

    """

    def __init__(self, name: str, value: Any, allowed: str,
                 reason: str = 'is out of range') -> None:
        self.name = name
        self.value = value
        self.allowed = allowed
        self.reason = reason
        super().__init__(f'parameter {name!r} = {value!r} {reason}; allowed: {allowed}')

    def with_prefix(self, prefix: str) -> ParameterError:
        """Return the same error with ``prefix`` put in front of the parameter name."""
        return ParameterError(prefix + self.name, self.value, self.allowed, self.reason)


class ConfigError(PiezoStageError):
    """A configuration file cannot be read or does not have the expected structure."""


class StabilityError(PiezoStageError):
    """A controller configuration is not stable on the configured plant (refused on request)."""


class BagError(PiezoStageError):
    """A bag cannot be written or read; the message names the bag and the problem."""


class IdentificationError(PiezoStageError):
    """
    The data or the model cannot give what was asked.

    A missing run, no excitation, a failed fit, or a third-order plant without the resonance its
    factored form needs (raised by the model's factor conversion as well as by identification).
    """
